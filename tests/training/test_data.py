"""The C-VAE dataset: trajectory reading, TSDF labels, shared normalization, re-runs, corruption, items."""

import argparse
import json
import shutil

import numpy as np
import pytest
import torch
import trimesh

from vnc_warp import from_arrays
from vnc_warp.cli import add_common_options
from vnc_warp.commands import dataset as dataset_cmd
from vnc_warp.shapes import icosphere
from vnc_warp.training import data as data_mod
from vnc_warp.training.data import (DatasetError, TrajectoryDataset, build_dataset, normalization, read_trajectory,
                                     verify_dataset)
from vnc_warp.trajectory import Trajectory, TrajectoryError

CENTER = np.array([1.0, -2.0, 0.5])
RADIUS = 0.5
SMALL = dict(num_surface=1500, num_uniform=1500, num_near=1500, noise=(0.005, 0.02), truncation=0.1)


def _stages():
    """Stage 0: an icosphere (642 vertices) of radius 0.5 at CENTER; stage 1: shrunk by 0.8 and bumped."""
    s = icosphere(3, radius=RADIUS)
    v0 = s.vertices.astype(np.float64)
    u = v0 / RADIUS
    v1 = 0.8 * v0 * (1.0 + 0.03 * np.sin(3.0 * u[:, :1]) * u[:, 1:2])
    return [from_arrays(v0 + CENTER, s.faces), from_arrays(v1 + CENTER, s.faces)]


def write_trajectory(root, meshes, ts, *, listed=None):
    """A trajectory folder written by vnc_warp.trajectory: ``listed`` stages finished (default all) and, when fewer,
    the next stage's file on disk but still being written (a run stopped while saving it)."""
    n = len(meshes) if listed is None else listed
    records = [{"index": i, "t": t, "file": f"stage_{i:03d}.ply", "iterations": 3} for i, t in enumerate(ts)]
    info = {"source": "fake.obj", "params": {"stages": len(meshes) - 1}}
    Trajectory(list(meshes[:n]), np.array(ts[:n]), records[:n], info).save(root)
    if n < len(meshes):
        meshes[n].save(root / records[n]["file"])
        manifest = json.loads((root / "manifest.json").read_text())
        (root / "manifest.json").write_text(json.dumps(dict(manifest, writing=records[n]["file"])))
    return root


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """Two trajectories ("alpha", "beta") sampled on the CPU into one dataset."""
    base = tmp_path_factory.mktemp("ds")
    trajs = [write_trajectory(base / name, _stages(), [1.0, 0.55]) for name in ("alpha", "beta")]
    summary = build_dataset(trajs, base / "data", device="cpu", progress=False, **SMALL)
    return base, trajs, summary


def _analytic_sdf(q, center_n, radius_n):
    return np.linalg.norm(q - center_n, axis=1) - radius_n


def test_tsdf_labels_match_analytic_sphere(tmp_path, device, monkeypatch):
    """Stage 0 is a sphere: stored TSDF labels equal clip(|q - c| - r, +-0.1) in normalized units (up to
    the polyhedral inset), negative inside, never beyond the truncation, exactly +-0.1 far away; the
    surface samples lie on the sphere with radial unit normals; near queries hug the surface; and the
    signed distances reach PyTorch as torch tensors (torch in, torch out)."""
    seen = []
    real = data_mod.signed_distance

    def spy(mesh, points, **kw):
        out = real(mesh, points, **kw)
        seen.append((type(points), type(out)))
        return out

    monkeypatch.setattr(data_mod, "signed_distance", spy)
    traj = write_trajectory(tmp_path / "sphere", _stages(), [1.0, 0.55])
    build_dataset([traj], tmp_path / "data", device=device, progress=False, **SMALL)
    assert seen == [(torch.Tensor, torch.Tensor)] * 2
    index = json.loads((tmp_path / "data" / "index.json").read_text())
    shape = index["shapes"][0]
    center, scale = np.array(shape["center"]), shape["scale"]
    c_n, r_n = (CENTER - center) * scale, RADIUS * scale
    with np.load(tmp_path / "data" / shape["stages"][0]["file"]) as z:
        q, tsdf, near, surf = z["queries"], z["tsdf"], z["near"], z["surface"]
        assert float(z["t"]) == 1.0
    assert q.shape == (3000, 3) and near.sum() == 1500 and not near[:1500].any()
    assert np.abs(q[~near]).max() <= 1.0
    ref = _analytic_sdf(q.astype(np.float64), c_n, r_n)
    inset = 0.006  # icosphere(3) faces sit up to ~0.004 r inside the sphere
    np.testing.assert_allclose(tsdf, np.clip(ref, -0.1, 0.1), atol=inset)
    assert np.abs(tsdf).max() <= 0.1 + 1e-7
    far = np.abs(ref) > 0.1 + inset
    assert far.sum() > 500 and np.all(np.abs(tsdf[far]) == np.float32(0.1))
    assert np.all(np.sign(tsdf[np.abs(ref) > inset]) == np.sign(ref[np.abs(ref) > inset]))
    assert np.abs(ref[near]).max() < 6 * 0.02 + inset
    assert np.abs(ref[near][:750]).max() < 6 * 0.005 + inset
    p, n = surf[:, :3].astype(np.float64), surf[:, 3:].astype(np.float64)
    assert np.abs(_analytic_sdf(p, c_n, r_n)).max() < inset
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-5)
    radial = (p - c_n) / np.linalg.norm(p - c_n, axis=1, keepdims=True)
    assert np.einsum("ij,ij->i", n, radial).min() > 0.98


def test_reference_queries_and_fresh_far_queries(tmp_path):
    """Defect 5 of issue 24 (small fixed query pools): stage 1 (a shrunk sphere) gets far-flagged queries near
    stage 0's larger sphere, labelled with stage 1's own TSDF; with a TSDF grid, every item draws new far queries
    in the box, at least half the truncation from the surface, whose labels match the analytic TSDF of the sphere
    (to the grid's interpolation), and two epochs draw different ones."""
    traj = write_trajectory(tmp_path / "sphere", [icosphere(3, radius=RADIUS).with_vertices(
        icosphere(3, radius=RADIUS).vertices + CENTER), _stages()[0].with_vertices(
        0.6 * (_stages()[0].vertices - CENTER) + CENTER)], [1.0, 0.4])
    build_dataset([traj], tmp_path / "data", device="cpu", progress=False, num_reference=600, grid_resolution=48,
                  **SMALL)
    shape = json.loads((tmp_path / "data" / "index.json").read_text())["shapes"][0]
    c_n, r0 = (CENTER - np.array(shape["center"])) * shape["scale"], RADIUS * shape["scale"]
    with np.load(tmp_path / "data" / shape["stages"][1]["file"]) as z:
        q, tsdf, near, grid = z["queries"].astype(np.float64), z["tsdf"], z["near"], z["grid"]
    assert q.shape == (3600, 3) and grid.shape == (48, 48, 48) and near.sum() == 1500
    ref = q[1500:2100]  # after the uniform ones: near stage 0's sphere (radius r0), flagged far
    assert not near[1500:2100].any() and np.abs(np.linalg.norm(ref - c_n, axis=1) - r0).mean() < 0.03
    np.testing.assert_allclose(tsdf[1500:2100], np.clip(_analytic_sdf(ref, c_n, 0.6 * r0), -0.1, 0.1), atol=0.006)
    ds = TrajectoryDataset(tmp_path / "data", num_surface=64, num_queries=400, near_fraction=0.5, fresh_fraction=1.0)
    item = ds[1]
    fresh, labels = item["queries"][:200].numpy().astype(np.float64), item["tsdf"][:200].numpy()
    assert not item["near"][:200].any() and np.abs(labels).min() >= 0.05
    truth = np.clip(_analytic_sdf(fresh, c_n, 0.6 * r0), -0.1, 0.1)
    assert np.abs(labels - truth).max() < 0.01 and np.mean(np.abs(labels - truth)) < 0.002
    ds.set_epoch(1)
    assert not np.allclose(ds[1]["queries"][:200].numpy(), fresh)
    with pytest.raises(ValueError, match="grid"):
        TrajectoryDataset(_no_grid(tmp_path), fresh_fraction=0.5)


def _no_grid(tmp_path):
    traj = write_trajectory(tmp_path / "plain", _stages(), [1.0, 0.55])
    build_dataset([traj], tmp_path / "plain_data", device="cpu", progress=False, **SMALL)
    return tmp_path / "plain_data"


def test_shared_normalization(built):
    """Every stage uses stage 0's normalization: centre = stage-0 bbox centre, scale = 1.8 / its max
    extent; stage-1 samples map back onto the stage-1 world mesh, and stage 1 (shrunk by 0.8) spans
    about 0.8 * 1.8, not 1.8."""
    base, trajs, _ = built
    index = json.loads((base / "data" / "index.json").read_text())
    s0 = trimesh.load(trajs[0] / "stage_000.ply", process=False)
    lo, hi = s0.vertices.min(0), s0.vertices.max(0)
    shape = index["shapes"][0]
    np.testing.assert_allclose(shape["center"], 0.5 * (lo + hi), atol=1e-6)
    assert shape["scale"] == pytest.approx(1.8 / (hi - lo).max(), rel=1e-6)
    assert shape["truncation"] == 0.1
    assert [st["t"] for st in shape["stages"]] == [1.0, 0.55]
    with np.load(base / "data" / shape["stages"][1]["file"]) as z:
        p = z["surface"][:, :3].astype(np.float64)
        assert float(z["t"]) == pytest.approx(0.55)
    world = p / shape["scale"] + np.array(shape["center"])
    s1 = trimesh.load(trajs[0] / "stage_001.ply", process=False)
    _, dist, _ = trimesh.proximity.closest_point(s1, world[:300])
    assert dist.max() < 1e-5
    extent = (p.max(0) - p.min(0)).max()
    assert 0.8 * 1.8 * 0.95 < extent < 0.8 * 1.8 * 1.1


def test_rerun_skips_finished_samples(built):
    """A second build with the same settings writes nothing: every stage is skipped, files untouched;
    other settings into the same folder are refused."""
    base, trajs, summary = built
    assert summary["built"] == 4 and summary["skipped"] == 0 and summary["shapes"] == 2
    files = sorted((base / "data").rglob("*.npz"))
    stamps = [f.stat().st_mtime_ns for f in files]
    again = build_dataset(trajs, base / "data", device="cpu", progress=False, **SMALL)
    assert again["built"] == 0 and again["rebuilt"] == 0 and again["skipped"] == 4
    assert [f.stat().st_mtime_ns for f in files] == stamps
    assert verify_dataset(base / "data") == 4
    with pytest.raises(ValueError, match="other settings"):
        build_dataset(trajs, base / "data", device="cpu", progress=False, **dict(SMALL, truncation=0.2))


def test_corrupt_files_are_detected_and_rebuilt(built, tmp_path):
    """A flipped byte fails the checksum, a truncated file fails to load, a file without 'tsdf' is
    reported as missing a key: each raises DatasetError naming the file (never returned as an item);
    a re-run of the builder rebuilds the damaged file."""
    base, trajs, _ = built
    root = tmp_path / "data"
    shutil.copytree(base / "data", root)
    target = root / "alpha" / "stage_001.npz"
    raw = bytearray(target.read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    target.write_bytes(bytes(raw))
    ds = TrajectoryDataset(root, split="all", num_surface=64, num_queries=64)
    ds[0]
    with pytest.raises(DatasetError, match=r"alpha/stage_001\.npz: checksum mismatch"):
        ds[1]
    with pytest.raises(DatasetError, match="1 of 4"):
        verify_dataset(root)
    with pytest.warns(UserWarning, match="rebuilding: .*checksum mismatch"):
        summary = build_dataset(trajs, root, device="cpu", progress=False, **SMALL)
    assert summary["rebuilt"] == 1 and summary["skipped"] == 3
    assert TrajectoryDataset(root, split="all", num_surface=64, num_queries=64)[1]["tsdf"].shape == (64,)

    index = json.loads((root / "index.json").read_text())
    target.write_bytes(target.read_bytes()[:1000])
    index["shapes"][0]["stages"][1]["sha256"] = data_mod._sha256(target)
    with np.load(root / "beta" / "stage_000.npz") as z:
        arrays = {k: z[k] for k in z.files if k != "tsdf"}
    np.savez(root / "beta" / "stage_000.npz", **arrays)
    index["shapes"][1]["stages"][0]["sha256"] = data_mod._sha256(root / "beta" / "stage_000.npz")
    (root / "index.json").write_text(json.dumps(index))
    ds = TrajectoryDataset(root, split="all", num_surface=64, num_queries=64)
    with pytest.raises(DatasetError, match="cannot load sample file"):
        ds[1]
    with pytest.raises(DatasetError, match=r"missing key\(s\) \['tsdf'\]"):
        ds[2]


def test_dataset_items_splits_and_seeding(built):
    """Items have the documented shapes and dtypes, half the queries near the surface, the stage's t;
    holdout names select the test split with global shape ids; subsets are reproducible per
    (seed, epoch, index) and change with the epoch."""
    base, _, _ = built
    train = TrajectoryDataset(base / "data", num_surface=256, num_queries=512, holdout=["beta"], seed=3)
    test = TrajectoryDataset(base / "data", num_surface=256, num_queries=512, split="test", holdout=["beta"])
    assert len(train) == 2 and len(test) == 2 and train.shape_names == ["alpha", "beta"]
    assert train.item_ids() == [(0, 0), (0, 1)] and test.item_ids() == [(1, 0), (1, 1)]
    item = train[1]
    expect = {"surface": ((256, 6), torch.float32), "queries": ((512, 3), torch.float32),
              "tsdf": ((512,), torch.float32), "near": ((512,), torch.bool), "t": ((), torch.float32),
              "shape_id": ((), torch.int64), "stage": ((), torch.int64)}
    assert set(item) == set(expect)
    for k, (shape, dtype) in expect.items():
        assert tuple(item[k].shape) == shape and item[k].dtype == dtype, k
    assert item["t"].item() == pytest.approx(0.55) and item["stage"].item() == 1 and item["shape_id"].item() == 0
    assert int(item["near"].sum()) == 256
    assert test[0]["shape_id"].item() == 1
    np.testing.assert_allclose(torch.linalg.norm(item["surface"][:, 3:], dim=1).numpy(), 1.0, atol=1e-5)
    again = TrajectoryDataset(base / "data", num_surface=256, num_queries=512, holdout=["beta"], seed=3)[1]
    for k in expect:
        assert torch.equal(item[k], again[k]), k
    train.set_epoch(1)
    assert not torch.equal(train[1]["queries"], item["queries"])
    batch = next(iter(torch.utils.data.DataLoader(train, batch_size=2)))
    assert batch["surface"].shape == (2, 256, 6) and batch["t"].shape == (2,)
    with pytest.raises(ValueError, match="holdout names"):
        TrajectoryDataset(base / "data", holdout=["gamma"])
    with pytest.raises(ValueError, match="empty"):
        TrajectoryDataset(base / "data", split="test")


def test_surface_alone_equals_the_items_surface(built):
    """TrajectoryDataset.surface(i) is item i's encoder surface bit for bit (the first draw of the item's
    generator), in every epoch and with repeats; Stage0Input and SuffixInput, which take it from another stage,
    give what the whole item of that stage would give."""
    from vnc_warp.training.train import Stage0Input, SuffixInput

    base, _, _ = built
    ds = TrajectoryDataset(base / "data", num_surface=128, num_queries=200, num_on_surface=50, repeats=2,
                           split="all", seed=4)
    for epoch in (0, 3):
        ds.set_epoch(epoch)
        for i in range(len(ds)):
            assert torch.equal(ds.surface(i), ds[i]["surface"])
    stage0, suffix = Stage0Input(ds), SuffixInput(ds, stage0_share=0.0, seed=1)
    for i in range(len(ds)):
        assert torch.equal(stage0[i]["surface"], ds[stage0.source[i]]["surface"])
        sid, st = suffix.ids[i]
        start = suffix.start(i)
        source = suffix.source[i] if start == 0 else suffix.first[(sid, start)]
        assert torch.equal(suffix[i]["surface"], ds[source]["surface"])
    with pytest.raises(IndexError):
        ds.surface(len(ds))


def test_on_surface_points_are_the_items_own(built):
    """With num_on_surface, every item carries points and unit normals on its OWN stage's surface (the stage-1
    sphere of radius 0.8 r, normalized), also when Stage0Input gives the encoder stage 0's surface (radius r); the
    near fraction sets the share of near-surface queries (defect 5 of issue 24: on-surface and normal terms need
    the item's own surface, and most queries near it)."""
    from vnc_warp.training.train import Stage0Input

    base, _, _ = built
    ds = TrajectoryDataset(base / "data", num_surface=128, num_queries=400, holdout=["beta"], num_on_surface=200,
                           near_fraction=0.8)
    item, wrapped = ds[1], Stage0Input(ds)[1]
    assert item["on_surface"].shape == (200, 6) and int(item["near"].sum()) == 320
    assert torch.equal(wrapped["on_surface"], item["on_surface"])
    shape = json.loads((base / "data" / "index.json").read_text())["shapes"][0]
    r_norm = RADIUS * shape["scale"]
    radius = lambda pts: torch.linalg.norm(pts[:, :3], dim=1).numpy()  # noqa: E731  (centred: bbox centre)
    assert np.allclose(radius(wrapped["surface"]), r_norm, rtol=0.02)            # stage 0, encoder input
    assert np.allclose(radius(item["on_surface"]), 0.8 * r_norm, rtol=0.06)      # stage 1, its own surface
    pts, nrm = item["on_surface"][:, :3], item["on_surface"][:, 3:]
    assert float((torch.nn.functional.normalize(pts, dim=1) * nrm).sum(1).min()) > 0.9  # outward normals
    assert "on_surface" not in TrajectoryDataset(base / "data", num_surface=128, num_queries=400)[0]


def test_partial_trajectory_and_bad_manifests(tmp_path):
    """Only listed stages count (a trajectory stopped while writing a stage); a wrong format string, a missing
    stage file or a missing stage 0 is refused with the manifest's path in the message."""
    traj = write_trajectory(tmp_path / "partial", _stages(), [1.0, 0.55], listed=1)
    tr = read_trajectory(traj)
    assert [s.index for s in tr.stages] == [0] and tr.name == "partial"
    center, scale = normalization(tr.load_stage(0))
    assert scale == pytest.approx(1.8 / np.ptp(tr.load_stage(0).vertices, axis=0).max(), rel=1e-6)
    manifest = json.loads((traj / "manifest.json").read_text())
    (traj / "manifest.json").write_text(json.dumps(dict(manifest, format="other/2")))
    with pytest.raises(TrajectoryError, match="format must be"):
        read_trajectory(traj)
    (traj / "manifest.json").write_text(json.dumps(dict(manifest, stages=[dict(manifest["stages"][0], index=1)])))
    with pytest.raises(TrajectoryError, match="stage 0 is not listed"):
        read_trajectory(traj)
    (traj / "manifest.json").write_text(json.dumps(manifest))
    (traj / "stage_000.ply").unlink()
    with pytest.raises(TrajectoryError, match="manifest.json: stage 0 lists stage_000.ply, which is missing"):
        read_trajectory(traj)


def test_dataset_command(tmp_path, capsys):
    """`vnc-warp dataset` builds a dataset from a partial trajectory (one listed stage) and verifies it."""
    traj = write_trajectory(tmp_path / "cmd", _stages(), [1.0, 0.55], listed=1)
    parser = argparse.ArgumentParser()
    dataset_cmd.add_arguments(parser)
    add_common_options(parser)
    args = parser.parse_args([str(traj), "--out", str(tmp_path / "d"), "--device", "cpu", "--num-surface", "200",
                              "--num-uniform", "200", "--num-near", "200", "--verify", "--no-progress"])
    assert dataset_cmd.run(args) == 0
    out = capsys.readouterr().out
    assert "built 1" in out and "verified 1" in out
    index = json.loads((tmp_path / "d" / "index.json").read_text())
    assert len(index["shapes"][0]["stages"]) == 1
