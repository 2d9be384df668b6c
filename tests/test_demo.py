"""`vnc-warp demo` end to end on the CPU with its smallest settings: files, figures, summary, meshes.

Oracles: Pillow reading back every PNG at the size the summary states; trimesh's normal-cycle measure
(``discrete_mean_curvature_measure``) for the Eq. (1) baseline statistics; VNC-soft evaluated one scale
at a time (a different kernel from the multi-scale curves the demo uses) for the VNC statistics; the
flow's own invariants (t starts at 1 and decreases, one mesh per stage).
"""

import json

import numpy as np
import pytest
import trimesh
from PIL import Image

import vnc_warp as vw
from vnc_warp.cli import main
from vnc_warp.data import mesh_path

PNGS = ["curvature_scales.png", "scale_stability.png", "flow_auc.png", "adaptive_scales.png", "filmstrip.png",
        "comparison.png"]
STAGES = 2
SMALLEST = ["--device", "cpu", "--scales", "4", "--faces", "600", "--stages", str(STAGES), "--max-iters", "8",
            "--compare-faces", "400", "--compare-stages", "1", "--compare-max-iters", "4", "--frame-size", "64",
            "--no-progress"]


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """One run of the demo on the bundled Spot with the smallest settings; its folder and summary."""
    out = tmp_path_factory.mktemp("demo")
    assert main(["demo", "--out", str(out)] + SMALLEST) == 0
    return out, json.loads((out / "summary.json").read_text())


def test_demo_writes_every_figure_as_a_valid_png_of_the_stated_size(demo):
    """The six figures exist, are PNGs of the [width, height] the summary states, and are not blank."""
    out, summary = demo
    assert sorted(summary["images"]) == sorted(PNGS)
    for name in PNGS:
        with Image.open(out / name) as im:
            assert im.format == "PNG"
            assert list(im.size) == summary["images"][name]
            px = np.asarray(im.convert("RGB"))
        ink = np.any(px < 250, axis=2)
        assert ink.mean() > 0.02, name
        assert len(np.unique(px.reshape(-1, 3).astype(np.int64) @ [65536, 256, 1])) > 50, name


def test_demo_summary_lists_existing_files_and_a_consistent_flow(demo):
    """Every listed file exists; the flow has one t per stage, starting at 1 and decreasing, sphericities in
    (0, 1]; the comparison ran all five methods, each starting from t = 1."""
    out, summary = demo
    for f in summary["files"]:
        assert (out / f).is_file(), f
    t = np.asarray(summary["flow"]["t"])
    assert t.shape == (STAGES + 1,) and t[0] == 1.0
    assert np.all(np.diff(t) < 0)
    s = np.asarray(summary["flow"]["sphericity"])
    assert np.all((s > 0) & (s <= 1.0))
    assert len(summary["comparison"]) == 5
    assert all(run["t"][0] == 1.0 for run in summary["comparison"].values())
    assert summary["seconds"]["total"] >= sum(v for k, v in summary["seconds"].items() if k != "total") - 1e-6


def test_demo_curvature_statistics_match_independent_evaluations(demo):
    """The Fig. 6 numbers: the Eq. (1) baseline mean equals trimesh's normal-cycle measure, and the VNC-soft
    mean and variance equal VNC-soft evaluated at each scale on its own."""
    _, summary = demo
    mesh = vw.load_mesh(mesh_path("spot"))
    taus = summary["curvature"]["taus"]
    tm = mesh.to_trimesh()
    for k in (0, 1):  # trimesh's cost grows with the ball; two small scales keep the test quick
        ref = trimesh.curvature.discrete_mean_curvature_measure(tm, tm.vertices, taus[k])
        assert summary["curvature"]["baseline_eq1"]["mean"][k] == pytest.approx(ref.mean(), rel=1e-4)
        h = vw.vnc_soft(mesh, taus[k], device="cpu")[0].numpy().astype(np.float64)
        assert summary["curvature"]["vnc_soft"]["mean"][k] == pytest.approx(h.mean(), rel=1e-4, abs=1e-6)
        assert summary["curvature"]["vnc_soft"]["var"][k] == pytest.approx(h.var(), rel=1e-3)


def test_demo_meshes_are_coloured_plys_of_the_flow_states(demo):
    """Each stage PLY loads with one RGBA colour per vertex and the vertex count the summary records; the input
    PLYs hold Spot's vertices, coloured (not all one colour)."""
    out, summary = demo
    for i, count in enumerate(summary["flow"]["vertices"]):
        tm = trimesh.load(out / "meshes" / f"stage_{i:03d}.ply", process=False)
        assert len(tm.vertices) == count
        assert tm.visual.vertex_colors.shape == (count, 4)
    inputs = sorted((out / "meshes").glob("input_vnc_scale*.ply"))
    assert len(inputs) == 4
    tm = trimesh.load(inputs[0], process=False)
    assert len(tm.vertices) == summary["vertices"]
    assert len(np.unique(tm.visual.vertex_colors, axis=0)) > 10


def test_demo_rejects_bad_settings(tmp_path, capsys):
    """Non-positive counts are reported as a usage error (exit code 2), before any work."""
    assert main(["demo", "--out", str(tmp_path / "x"), "--stages", "0", "--device", "cpu"]) == 2
    assert "--stages" in capsys.readouterr().err


def test_demo_with_a_checkpoint_adds_the_c_vae_figures(tmp_path):
    """With --checkpoint (here an untrained tiny C-VAE-I), the demo also writes Fig. 9b, one decoded cell per
    flow stage (empty level sets become placeholders), and Fig. 11 from the latents of the input across t."""
    import torch

    from vnc_warp.training.checkpoint import save_checkpoint
    from vnc_warp.training.config import named_config
    from vnc_warp.training.model import build_model

    config = named_config("tiny")
    torch.manual_seed(0)
    ckpt = save_checkpoint(tmp_path / "run" / "checkpoints" / "last.pt", model=build_model(config.model),
                           config=config, step=0)
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--no-compare", "--checkpoint", str(ckpt), "--resolution", "16"]
                + SMALLEST) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert len(summary["cvae"]["decoded"]) == STAGES + 1
    for name in ("decoded_trajectory.png", "latent_space.png"):
        with Image.open(out / name) as im:
            assert im.format == "PNG" and list(im.size) == summary["images"][name]
    assert "comparison.png" not in summary["images"]
