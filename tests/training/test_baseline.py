"""The latent-interpolation baseline (vnc_warp.training.baseline) and the latent anatomy of trajectories."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

from vnc_warp.shapes import icosphere
from vnc_warp.training.baseline import (LatentInterpolation, encode_surface, interpolate_latents, interpolation_alpha,
                                        latent_interpolation)
from vnc_warp.training.checkpoint import load_model
from vnc_warp.training.config import named_config
from vnc_warp.training.data import normalization, read_trajectory
from vnc_warp.training.inference import decode_sdf_grid, surface_condition
from vnc_warp.training.latent import analyze_latents, latent_anatomy, trajectory_latents
from vnc_warp.training.metrics import evaluate_trajectory, read_prediction_dir
from vnc_warp.training.model import build_model
from vnc_warp.training.synthetic import EllipsoidTrajectories, ellipsoid_sdf
from vnc_warp.training.train import train

STAGES = 4


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def vae_and_trajectory(tmp_path_factory):
    """A tiny plain VAE trained on one analytic ellipsoid-to-sphere trajectory, and the same trajectory
    written as a VNC-Flow trajectory folder (icosphere meshes scaled to each stage's semi-axes)."""
    root = tmp_path_factory.mktemp("baseline")
    ds = EllipsoidTrajectories(num_shapes=1, num_stages=STAGES, seed=1)
    cfg = named_config("tiny-vae")
    cfg.optim = dataclasses.replace(cfg.optim, total_steps=200)
    train(cfg, data=ds, out_dir=root / "vae", device="cpu", progress=False)
    model, _ = load_model(root / "vae")
    traj = root / "ellipsoid"
    traj.mkdir()
    sphere = icosphere(3)
    stages = []
    for i in range(STAGES):
        t = 1.0 - i / (STAGES - 1)
        sphere.with_vertices(sphere.vertices * ds.axes(0, t)).save(traj / f"stage_{i:03d}.ply")
        stages.append({"index": i, "t": t, "file": f"stage_{i:03d}.ply"})
    (traj / "manifest.json").write_text(json.dumps({"format": "vnc-warp-trajectory/1", "stages": stages}))
    return model, traj, ds


def test_interpolation_weights_and_latents():
    """alpha is (t - t_end) / (1 - t_end) clipped to [0, 1]; alpha 1 / 0 return the endpoints bit for bit and
    alpha 0.25 the NumPy blend."""
    assert interpolation_alpha(1.0, t_end=0.2) == 1.0 and interpolation_alpha(0.2, t_end=0.2) == 0.0
    assert interpolation_alpha(0.6, t_end=0.2) == pytest.approx(0.5) and interpolation_alpha(0.0, t_end=0.2) == 0.0
    with pytest.raises(ValueError, match="t_start > t_end"):
        interpolation_alpha(0.5, t_start=0.3, t_end=0.3)
    g = torch.Generator().manual_seed(0)
    a, b = torch.randn(1, 8, 4, generator=g), torch.randn(1, 8, 4, generator=g)
    assert torch.equal(interpolate_latents(a, b, 1.0), a) and torch.equal(interpolate_latents(a, b, 0.0), b)
    np.testing.assert_allclose(interpolate_latents(a, b, 0.25).numpy(), 0.25 * a.numpy() + 0.75 * b.numpy(),
                               rtol=1e-6, atol=1e-7)
    with pytest.raises(ValueError, match="shapes differ"):
        interpolate_latents(a, b[:, :4], 0.5)


def test_endpoints_equal_endpoint_decodes(vae_and_trajectory):
    """Encode stage 0 and the last stage, interpolate, decode: at t = 1 (alpha 1) and t = t_end (alpha 0) the
    SDF grid equals the decode of the endpoint's own encoding exactly; the decoded t = 1 mesh lies nearer the
    stage-0 ellipsoid, the t = 0 mesh nearer the sphere (analytic SDFs as the oracle)."""
    model, traj_dir, ds = vae_and_trajectory
    traj = read_trajectory(traj_dir)
    start, end = traj.load_stage(0), traj.load_stage(STAGES - 1)
    interp = LatentInterpolation(model, start, end, t_end=traj.stages[-1].t, num_surface=256, seed=3)
    norm = normalization(start)
    z1 = encode_surface(model, surface_condition(start, num_points=256, seed=3, normalization=norm)[0])
    z0 = encode_surface(model, surface_condition(end, num_points=256, seed=3, normalization=norm)[0])
    assert not torch.allclose(z1, z0)
    for t, z in ((1.0, z1), (0.0, z0)):
        np.testing.assert_array_equal(decode_sdf_grid(model, interp.latent(t), resolution=16),
                                      decode_sdf_grid(model, z, resolution=16))
    np.testing.assert_allclose(interp.latent(0.5).numpy(), 0.5 * (z0 + z1).numpy(), rtol=1e-5, atol=1e-6)
    err = {}
    for t in (0.0, 1.0):
        verts = interp.decode(t, resolution=32).vertices
        for ref in (0.0, 1.0):
            err[t, ref] = float(np.abs(ellipsoid_sdf(verts, ds.axes(0, ref))).mean())
    assert err[1.0, 1.0] < err[1.0, 0.0] and err[0.0, 0.0] < err[0.0, 1.0], err
    with pytest.raises(ValueError, match="plain VecSet VAE"):
        LatentInterpolation(build_model(named_config("tiny").model).eval(), start, end)


def test_latent_interpolation_writes_scorable_predictions(vae_and_trajectory, tmp_path):
    """latent_interpolation writes one mesh per t and a generate.json that read_prediction_dir and
    evaluate_trajectory accept; the t = 1 file is the decode of the stage-0 latent."""
    model, traj_dir, _ = vae_and_trajectory
    times = [0.0, 0.5, 1.0]
    report = latent_interpolation(model, traj_dir, times, tmp_path, resolution=24, num_surface=256, seed=3)
    assert report["method"] == "latent_interpolation" and report["t_end"] == 0.0 and report["frame"] == "world"
    preds, meta = read_prediction_dir(tmp_path)
    assert sorted(preds) == times and all(preds[t] is not None for t in times)
    traj = read_trajectory(traj_dir)
    direct = LatentInterpolation(model, traj.load_stage(0), traj.load_stage(STAGES - 1), num_surface=256, seed=3)
    np.testing.assert_allclose(preds[1.0].vertices, direct.decode(1.0, resolution=24).vertices, atol=1e-5)
    scores = evaluate_trajectory(preds, traj_dir, n_points=2000, n_emd=200)
    assert scores["failed"] == 0
    assert all(np.isfinite([scores["mean"][k] for k in ("cd_x1e4", "emd_x1e2", "nce")]))
    assert [e["stage"] for e in scores["per_t"]] == [0, 2, 3]  # t = 1, 0.5 -> nearest 1/3, 0


def test_trajectory_latents_encoding(vae_and_trajectory):
    """A plain VAE encodes each stage's own surface, a C-VAE the stage-0 surface at each stage's t: both
    equal direct encode_surface calls, in stage order with the manifest's t."""
    model, traj_dir, _ = vae_and_trajectory
    traj = read_trajectory(traj_dir)
    norm = normalization(traj.load_stage(0))
    data = trajectory_latents(model, [traj_dir], num_surface=256, seed=5)
    assert data["latents"].shape == (STAGES, model.num_latents, model.latent_dim)
    np.testing.assert_allclose(data["t"], [s.t for s in traj.stages])
    last = surface_condition(traj.load_stage(STAGES - 1), num_points=256, seed=5, normalization=norm)[0]
    np.testing.assert_allclose(data["latents"][-1], encode_surface(model, last)[0].numpy(), rtol=1e-5, atol=1e-6)
    torch.manual_seed(0)
    cvae = build_model(named_config("tiny").model).eval()
    cond = surface_condition(traj.load_stage(0), num_points=256, seed=5, normalization=norm)[0]
    data = trajectory_latents(cvae, [traj_dir], num_surface=256, seed=5)
    for i, st in enumerate(traj.stages):
        np.testing.assert_allclose(data["latents"][i], encode_surface(cvae, cond, st.t)[0].numpy(), rtol=1e-5,
                                   atol=1e-6)
    report = latent_anatomy(cvae, [traj_dir, traj_dir], num_surface=256, use_umap=False)
    assert report["n"] == 2 * STAGES and report["encoding"] == "stage0_at_t" and report["shapes"] == ["ellipsoid"]


def test_within_group_correlations_known():
    """Groups whose latent norm grows exactly linearly with t but start from different offsets: the
    within-group correlations are 1, while the pooled one is far from 1 (an independent construction)."""
    rng = np.random.default_rng(0)
    t = np.tile(np.linspace(0.0, 1.0, 5), 3)
    groups = np.repeat(["a", "b", "c"], 5)
    offset = np.repeat([5.0, 0.0, 10.0], 5)
    direction = rng.normal(size=(6, 4))
    direction /= np.linalg.norm(direction)
    z = (offset + t)[:, None, None] * direction[None]
    rep = analyze_latents(z, t, groups=groups, use_umap=False)
    assert rep["norm_t_pearson_within"] == pytest.approx(1.0, abs=1e-9)
    assert rep["pc1_t_pearson_within"] == pytest.approx(1.0, abs=1e-9)
    assert rep["norm_t_pearson"] < 0.5
    with pytest.raises(ValueError, match="groups"):
        analyze_latents(z, t, groups=groups[:-1], use_umap=False)
