"""CD / EMD / NCE against exact and analytic values, trajectory evaluation, and the latent anatomy."""

import argparse
import itertools
import json

import numpy as np
import pytest
import scipy.stats
from PIL import Image

from vnc_warp.commands import evaluate as evaluate_cmd
from vnc_warp.shapes import icosphere, random_shape
from vnc_warp.training.latent import analyze_latents, pca, pearson
from vnc_warp.training.metrics import (chamfer_distance, combine_reports, compare_meshes, earth_movers_distance,
                                       evaluate_trajectory, normal_consistency_error, read_prediction_dir,
                                       sampling_floors)


def _sphere_points(n, r, rng):
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return r * u, u


def test_chamfer_and_emd_match_brute_force():
    """CD equals a dense NumPy double loop; EMD equals the best of all 6! permutations."""
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(40, 3)), rng.normal(size=(55, 3))
    d2 = ((a[:, None] - b[None]) ** 2).sum(-1)
    assert chamfer_distance(a, b) == pytest.approx(d2.min(1).mean() + d2.min(0).mean(), rel=1e-12)
    a, b = rng.normal(size=(6, 3)), rng.normal(size=(6, 3))
    cost = np.linalg.norm(a[:, None] - b[None], axis=-1)
    best = min(cost[np.arange(6), list(p)].mean() for p in itertools.permutations(range(6)))
    assert earth_movers_distance(a, b) == pytest.approx(best, rel=1e-12)
    with pytest.raises(ValueError, match="equal size"):
        earth_movers_distance(a, b[:5])


def test_shifted_point_set_exact():
    """A unit grid shifted by d (|d| < 1/2): CD = 2 |d|^2 and EMD = |d| exactly (triangle inequality)."""
    g = np.stack(np.meshgrid(*[np.arange(6.0)] * 3, indexing="ij"), -1).reshape(-1, 3)
    d = np.array([0.1, -0.2, 0.05])
    assert chamfer_distance(g, g + d) == pytest.approx(2.0 * d @ d, rel=1e-12)
    assert earth_movers_distance(g, g[::-1] + d) == pytest.approx(np.linalg.norm(d), rel=1e-12)


def test_normal_consistency_values():
    """Same normals -> 0; flipped normals -> pi oriented and 0 unoriented; normals tilted by a fixed
    angle theta -> theta."""
    rng = np.random.default_rng(1)
    p, n = _sphere_points(500, 1.0, rng)
    assert normal_consistency_error(p, n, p, n) == pytest.approx(0.0, abs=1e-6)
    assert normal_consistency_error(p, n, p, -n) == pytest.approx(np.pi, abs=1e-6)
    assert normal_consistency_error(p, n, p, -n, oriented=False) == pytest.approx(0.0, abs=1e-6)
    theta = 0.3
    t = np.cross(n, rng.normal(size=3))
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    assert normal_consistency_error(p, n, p, np.cos(theta) * n + np.sin(theta) * t) == pytest.approx(theta, abs=1e-6)


def test_compare_meshes_identical_and_concentric_spheres():
    """Identical meshes score exactly 0. Concentric spheres r1 = 0.6, r2 = 0.7: CD ~ 2 (r1 - r2)^2,
    EMD ~ |r1 - r2| (up to the polyhedral inset of icosphere(4)), NCE ~ 0; independent samples of
    exact spheres give CD within 10% of 2 (r1 - r2)^2."""
    s = random_shape(0, subdivisions=3)
    z = compare_meshes(s, s, n_points=3000, n_emd=500)
    assert z["cd"] == 0.0 and z["emd"] == 0.0 and z["nce"] == pytest.approx(0.0, abs=1e-6)
    r1, r2 = 0.6, 0.7
    m = compare_meshes(icosphere(4, radius=r1), icosphere(4, radius=r2), n_points=4000, n_emd=800, seed=2)
    assert m["cd"] == pytest.approx(2 * (r1 - r2) ** 2, rel=0.02)
    assert m["emd"] == pytest.approx(r2 - r1, rel=0.02)
    assert m["cd_x1e4"] == pytest.approx(m["cd"] * 1e4) and m["emd_x1e2"] == pytest.approx(m["emd"] * 1e2)
    assert m["nce"] < 0.05
    rng = np.random.default_rng(3)
    a, _ = _sphere_points(20000, r1, rng)
    b, _ = _sphere_points(20000, r2, rng)
    assert chamfer_distance(a, b) == pytest.approx(2 * (r1 - r2) ** 2, rel=0.1)


def test_compare_meshes_normalization_and_orientation():
    """Scaling both meshes by k and normalizing with scale 1/k reproduces the unscaled numbers; an
    inside-out (reversed winding) copy is re-oriented, so NCE stays ~0."""
    a, b = random_shape(1, subdivisions=3), random_shape(2, subdivisions=3)
    ref = compare_meshes(a, b, n_points=2000, n_emd=300)
    k, c = 40.0, np.array([3.0, -1.0, 2.0])
    big = [(m.vertices * k + c, m.faces) for m in (a, b)]
    out = compare_meshes(*big, n_points=2000, n_emd=300, normalization=(c, 1.0 / k))
    for key in ("cd", "emd", "nce"):
        assert out[key] == pytest.approx(ref[key], rel=1e-4)
    flipped = compare_meshes((a.vertices, a.faces[:, ::-1]), a, n_points=2000, n_emd=300)
    assert flipped["nce"] < 1e-3


def _write_traj(root, meshes, ts):
    root.mkdir(parents=True)
    stages = []
    for i, (m, t) in enumerate(zip(meshes, ts)):
        m.save(root / f"stage_{i:03d}.ply")
        stages.append({"index": i, "t": t, "file": f"stage_{i:03d}.ply"})
    (root / "manifest.json").write_text(json.dumps({"format": "vnc-warp-trajectory/1", "source": "x",
                                                    "stages": stages}))
    return root


def test_scoring_split_by_t_with_shared_floors_equals_one_call(tmp_path):
    """The experiment scores each t of a prediction folder in its own job without floors, the trajectory's floors
    once (sampling_floors), and joins them (combine_reports): every number equals one evaluate_trajectory call on
    all the predictions (oracle: that call), the floors included, and stage 0's floor is the one reported for
    the trajectory; the fragmented prediction's ``largest`` part is scored the same way."""
    s0 = random_shape(5, subdivisions=3)
    s1 = s0.with_vertices(0.6 * s0.vertices)
    s2 = s0.with_vertices(0.3 * s0.vertices)
    gt = _write_traj(tmp_path / "gt", [s0, s1, s2], [1.0, 0.5, 0.02])
    far = icosphere(2)
    two = (np.concatenate([s1.vertices * 1.02, far.vertices * 0.1 + 2.0]),
           np.concatenate([s1.faces, far.faces + s1.num_vertices]))
    preds = {1.0: s0.with_vertices(s0.vertices * 1.01), 0.5: two, 0.02: None}
    kw = dict(n_points=1500, n_emd=200, seed=3)
    whole = evaluate_trajectory(preds, gt, **kw)
    parts = [evaluate_trajectory({t: p}, gt, floors=False, **kw) for t, p in preds.items()]
    assert all(p["sampling_floor"] is None and all("floor" not in e for e in p["per_t"]) for p in parts)
    joined = combine_reports(parts)
    floors = sampling_floors(gt, list(preds), **kw)
    for e in joined["per_t"]:
        if "error" not in e:
            e["floor"] = floors["stages"][str(e["stage"])]
    joined["sampling_floor"] = floors["stage0"]
    assert json.dumps(joined, sort_keys=True) == json.dumps(whole, sort_keys=True)
    assert whole["failed"] == 1 and whole["per_t"][1]["components"] == 2
    with pytest.raises(ValueError, match="one trajectory"):
        combine_reports([])


def test_evaluate_trajectory_and_command(tmp_path, capsys):
    """GT stages given back as predictions score 0 in the world frame, and in the normalized frame
    once normalized; predictions match the GT stage of nearest t; a world-frame prediction off by a
    translation d scores EMD = d * scale; an empty mesh is reported, not scored; the command writes
    the JSON report."""
    s0 = random_shape(5, subdivisions=3)
    s0 = s0.with_vertices(s0.vertices * 30.0 + 7.0)
    s1 = s0.with_vertices(0.5 * (s0.vertices - 7.0) + 7.0)
    gt = _write_traj(tmp_path / "gt", [s0, s1], [1.0, 0.4])
    rep = evaluate_trajectory({0.98: s0, 0.45: s1}, gt, n_points=2000, n_emd=300)
    assert [(e["t"], e["t_gt"], e["stage"]) for e in rep["per_t"]] == [(0.98, 1.0, 0), (0.45, 0.4, 1)]
    assert rep["mean"]["cd_x1e4"] == 0.0 and rep["mean"]["emd_x1e2"] == 0.0 and rep["failed"] == 0
    floor = rep["sampling_floor"]
    assert 0.0 < floor["cd_x1e4"] < 100.0 and 0.0 < floor["emd_x1e2"] < 30.0 and 0.0 < floor["nce"] < 0.2
    lo, hi = s0.vertices.min(0).astype(np.float64), s0.vertices.max(0).astype(np.float64)
    center, scale = 0.5 * (lo + hi), 1.8 / (hi - lo).max()
    np.testing.assert_allclose(rep["normalization"]["center"], center, rtol=1e-6)
    norm1 = ((s1.vertices - center) * scale, s1.faces)
    rep = evaluate_trajectory({0.4: norm1}, gt, pred_frame="normalized", n_points=2000, n_emd=300)
    assert rep["per_t"][0]["cd"] < 1e-10
    shifted = (s1.vertices + np.array([0.3, 0.0, 0.0]), s1.faces)
    rep = evaluate_trajectory({0.4: shifted}, gt, n_points=2000, n_emd=300)
    assert rep["per_t"][0]["emd"] == pytest.approx(0.3 * scale, rel=1e-4)
    with pytest.raises(ValueError, match="no GT stage within"):
        evaluate_trajectory({0.7: s1}, gt, max_dt=0.1)
    rep = evaluate_trajectory({0.4: (np.zeros((0, 3)), np.zeros((0, 3), int)), 1.0: s0, 0.0: None}, gt,
                              n_points=500, n_emd=100)
    assert rep["failed"] == 2 and "empty" in rep["per_t"][1]["error"] and rep["mean"]["cd_x1e4"] == 0.0
    assert rep["per_t"][2]["error"] == "no predicted mesh"

    pred = tmp_path / "pred"
    pred.mkdir()
    s0.save(pred / "t_1.000.ply")
    s1.save(pred / "t_0.400.ply")
    listing = {"frame": "world", "meshes": [{"t": 1.0, "file": "t_1.000.ply"}, {"t": 0.4, "file": "t_0.400.ply"},
                                            {"t": 0.0, "file": None, "error": "empty level set"}]}
    (pred / "generate.json").write_text(json.dumps(listing))
    meshes, meta = read_prediction_dir(pred)
    assert sorted(meshes) == [0.0, 0.4, 1.0] and meshes[0.0] is None and meta["frame"] == "world"
    (pred / "generate.json").write_text(json.dumps(dict(listing, meshes=listing["meshes"][:2])))
    parser = argparse.ArgumentParser()
    evaluate_cmd.add_arguments(parser)
    out = tmp_path / "report.json"
    args = parser.parse_args(["--pred", str(pred), "--gt", str(gt), "--out", str(out), "--n-points", "1000",
                              "--n-emd", "200"])
    assert evaluate_cmd.run(args) == 0
    report = json.loads(out.read_text())
    assert len(report["per_t"]) == 2 and report["mean"]["nce"] < 1e-6
    assert "CD x1e-4" in capsys.readouterr().out


def test_floating_fragment_and_unit_box(tmp_path):
    """A prediction made of the GT stage plus a small sphere far from it (defect 5 of issue 24): two components;
    its largest component is the GT stage and scores 0, while the whole prediction's CD is large; the unit-box
    numbers equal an evaluation whose normalization maps the stage-0 box to extent 1 (CD / 1.8^2, EMD / 1.8);
    every entry carries the sampling floor of its stage."""
    s0 = random_shape(5, subdivisions=3)
    s0 = s0.with_vertices(s0.vertices * 30.0 + 7.0)
    s1 = s0.with_vertices(0.5 * (s0.vertices - 7.0) + 7.0)
    gt = _write_traj(tmp_path / "gt", [s0, s1], [1.0, 0.4])
    blob = icosphere(2, radius=3.0)
    fragment = (np.concatenate([s1.vertices, blob.vertices + [120.0, 7.0, 7.0]]),
                np.concatenate([s1.faces, blob.faces + s1.num_vertices]))
    rep = evaluate_trajectory({0.4: fragment, 1.0: s0}, gt, n_points=3000, n_emd=300)
    frag, whole = rep["per_t"][1], rep["per_t"][0]
    assert frag["components"] == 2 and whole["components"] == 1
    assert frag["largest"]["cd_x1e4"] == 0.0 and frag["largest"]["emd_x1e2"] == 0.0
    assert frag["cd_x1e4"] > 100.0 * frag["floor"]["cd_x1e4"] > 0.0
    assert rep["mean"]["largest"]["cd_x1e4"] == 0.0 and rep["mean"]["cd_x1e4"] > 0.0
    lo, hi = s0.vertices.min(0).astype(np.float64), s0.vertices.max(0).astype(np.float64)
    unit = compare_meshes(fragment, s1, n_points=3000, n_emd=300, normalization=(0.5 * (lo + hi), 1.0 / (hi - lo).max()))
    assert frag["unit_box"]["cd_x1e4"] == pytest.approx(unit["cd_x1e4"], rel=1e-9)
    assert frag["unit_box"]["emd_x1e2"] == pytest.approx(unit["emd_x1e2"], rel=1e-9)
    assert frag["unit_box"]["nce"] == pytest.approx(unit["nce"], rel=1e-6)
    assert frag["floor"]["cd_x1e4"] != whole["floor"]["cd_x1e4"]  # each stage its own floor


def test_pca_and_pearson_against_oracles():
    """PCA recovers the direction of rank-one data with all the variance, scores reproduce the centred
    data; pearson agrees with scipy.stats.pearsonr."""
    rng = np.random.default_rng(4)
    d = rng.normal(size=8)
    d /= np.linalg.norm(d)
    s = rng.normal(size=50)
    x = s[:, None] * d + 2.0
    p = pca(x, 2)
    assert abs(p["components"][0] @ d) == pytest.approx(1.0, abs=1e-9)
    assert p["explained_variance_ratio"][0] == pytest.approx(1.0, abs=1e-9)
    np.testing.assert_allclose(p["scores"] @ p["components"] + p["mean"], x, atol=1e-9)
    a, b = rng.normal(size=30), rng.normal(size=30)
    assert pearson(a, a + b) == pytest.approx(scipy.stats.pearsonr(a, a + b)[0], abs=1e-12)


def test_analyze_latents_radial_structure_and_png(tmp_path):
    """Latents scaled by t along a shared direction (the radial structure) give norm/t and |PC1|/t
    correlations near 1; latents independent of t give small ones; the PCA scatter PNG is a valid image of the
    requested size."""
    rng = np.random.default_rng(5)
    n = 120
    t = rng.uniform(0.0, 1.0, n)
    d = rng.normal(size=16)
    z = t[:, None, None] * (d + 0.2 * rng.normal(size=(n, 8, 16))) + 0.02 * rng.normal(size=(n, 8, 16))
    rep = analyze_latents(z, t, out_dir=tmp_path, use_umap=False)
    assert rep["norm_t_pearson"] > 0.95 and rep["pc1_t_abs_pearson"] > 0.95
    assert rep["best_pc"]["pc"] == 1 and rep["best_pc"]["pooled_r"] > 0.95
    noise = analyze_latents(rng.normal(size=(n, 8, 16)), t, use_umap=False)
    assert abs(noise["norm_t_pearson"]) < 0.35 and noise["pc1_t_abs_pearson"] < 0.35
    img = Image.open(rep["plots"]["pca"])
    assert img.format == "PNG" and img.size == (640, 480)


def test_analyze_latents_finds_the_component_that_orders_every_trajectory():
    """Five trajectories far apart along one direction (PC1: identity, most of the variance) each move along a
    second, shared direction with t: the best component is PC2, which orders every trajectory by t (r = 1 within
    each, one sign), while PC1 orders none (defect 4 of issue 24: only PC1 was reported). A direction along which
    the trajectories run the opposite ways orders each of them but not with one sign: its min_within is -1."""
    rng = np.random.default_rng(1)
    ident, shared, mixed = np.linalg.qr(rng.normal(size=(12, 3)))[0].T
    t = np.tile(np.linspace(0.0, 1.0, 9), 5)
    groups = np.repeat([f"s{i}" for i in range(5)], 9)
    offset = np.repeat(np.linspace(-20.0, 20.0, 5), 9)
    sign = np.repeat([1.0, -1.0, 1.0, -1.0, 1.0], 9)
    z = offset[:, None] * ident + t[:, None] * shared + 0.3 * (sign * (t - 0.5))[:, None] * mixed
    rep = analyze_latents(z[:, None, :], t, groups=groups, use_umap=False, num_components=3)
    assert rep["best_pc"]["pc"] == 2
    assert rep["best_pc"]["min_within"] == pytest.approx(1.0, abs=1e-9)
    assert all(r == pytest.approx(1.0, abs=1e-9) for r in rep["best_pc"]["within"].values())
    assert rep["pcs"][0]["variance"] > 0.99 and abs(rep["pcs"][0]["pooled_r"]) < 0.1
    assert rep["pcs"][2]["min_within"] == pytest.approx(-1.0, abs=1e-6)
