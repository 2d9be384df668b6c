"""Smoke test of the benchmark harness (``python -m bench.vnc --quick`` on the CPU device): the JSON it writes is
complete and self-consistent, the dense PyTorch Eq. (3) agrees with vnc_soft, and failing rows are reported, not
raised. No timing is asserted."""

import json
import math

import numpy as np
import pytest

from bench import vnc as bench
from conftest import mesh_path


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench") / "bench.json"
    doc, worker = bench.main(["--device", "cpu", "--quick", "--out", str(out), "--max-minutes", "5"])
    return out, doc, worker


def test_quick_run_writes_complete_json(quick_run):
    """The JSON on disk is the returned document and names the device, the versions, the meshes and every row."""
    out, doc, worker = quick_run
    assert worker is None or not worker.is_alive()
    on_disk = json.loads(out.read_text())
    assert on_disk["rows"] == json.loads(json.dumps(doc["rows"]))
    assert on_disk["schema"] == "vnc-warp-bench/1"
    assert on_disk["device"]["kind"] == "cpu" and on_disk["device"]["name"]
    assert {"warp", "torch", "trimesh", "numpy", "vnc_warp", "python"} <= set(on_disk["versions"])
    assert "python -m bench.vnc" in on_disk["command"] and on_disk["date"]
    (mesh,) = on_disk["meshes"]
    assert mesh["vertices"] > 1000 and mesh["interior_edges"] > mesh["vertices"]
    sections = {r["section"] for r in on_disk["rows"]}
    assert sections == {"operator", "scale", "eq1", "flow", "trajectory"}
    assert len(on_disk["goals"]) == 11 and all({"goal", "target", "measured", "met"} <= set(g) for g in on_disk["goals"])
    md = out.with_suffix(".md").read_text()
    assert on_disk["command"] in md and "| goal |" in md


def test_quick_run_rows_are_consistent(quick_run):
    """Every row is ok or says why not; medians are positive and bounded by min/max; ratios are the quotient of the
    two medians they name; the package's own rows ran at every scale."""
    _, doc, _ = quick_run
    rows = doc["rows"]
    by_key = {(r["mesh"], r["tau_label"], f"{r['name']}[{r['variant']}]"): r for r in rows}
    for r in rows:
        assert r["status"] in ("ok", "skipped"), (r["name"], r["variant"], r["note"])
        if r["status"] != "ok":
            assert r["note"]
            continue
        assert r["median_ms"] > 0 and r["min_ms"] <= r["median_ms"] <= r["max_ms"]
        if r["ratio"] is not None:
            ref = by_key[(r["mesh"], r["tau_label"], r["ratio_to"])]
            assert math.isclose(r["ratio"], r["median_ms"] / ref["median_ms"], rel_tol=1e-9)
    soft = [r for r in rows if r["name"] == "vnc_soft" and r["variant"] == "auto"]
    assert [r["tau_label"] for r in soft] == [t[0] for t in bench.QUICK_TAUS]
    assert all(r["status"] == "ok" and r["extra"]["chosen"] in ("grid", "dense") for r in soft)
    traj = next(r for r in rows if r["section"] == "trajectory")
    assert traj["status"] == "ok" and traj["extra"]["stages_done"] == traj["extra"]["stages"] == 2


def test_dense_torch_row_agrees_with_vnc_soft(quick_run):
    """The blocked dense PyTorch Eq. (3) (the paper's matrix form) gives the same H as vnc_soft at every scale, and
    Eq. (1) from the package equals trimesh's measure on the same points."""
    _, doc, _ = quick_run
    torch_rows = [r for r in doc["rows"] if r["name"] == "torch_dense_eq3" and r["status"] == "ok"]
    assert len(torch_rows) == len(bench.QUICK_TAUS)
    for r in torch_rows:
        assert r["extra"]["max_abs_dH"] < 1e-3 * max(r["extra"]["H_std"], 1e-3), r
    eq1 = [r for r in doc["rows"] if r["name"] == "trimesh_eq1"]
    assert eq1 and all(r["status"] == "ok" and r["extra"]["max_rel_diff"] < 1e-4 for r in eq1)


def test_failing_row_is_reported_not_raised(tmp_path):
    """A row whose function raises is recorded as an error with its message; a skipped row keeps its reason."""
    args = bench.parse_args(["--device", "cpu", "--quick", "--out", str(tmp_path / "b.json")])
    b = bench.Bench(args)

    def boom():
        raise RuntimeError("kernel exploded")

    row = b.run(bench.Row(section="operator", mesh="m", name="broken", variant="x"), boom)
    assert row.status == "error" and "kernel exploded" in row.note and "traceback" in row.extra
    row = b.run(bench.Row(section="operator", mesh="m", name="huge", variant="x"), boom, skip="too many pairs")
    assert row.status == "skipped" and row.note == "too many pairs"
    ok = b.run(bench.Row(section="operator", mesh="m", name="fine", variant="x"), lambda: np.zeros(3))
    assert ok.status == "ok" and ok.repeats >= 1


def test_breakdown_runs_and_reports_every_operator(tmp_path):
    """``python -m bench.breakdown`` on the CPU device writes one row per operator and scale, with finite wall
    and host times (no timing is asserted)."""
    from bench import breakdown

    out = tmp_path / "breakdown.json"
    assert breakdown.main(["--device", "cpu", "--mesh", str(mesh_path("spot_lowres.obj")), "--taus", "2", "diag/2",
                           "--repeats", "1", "--out", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert doc["V"] > 0 and doc["device"] == "cpu"
    assert [(r["op"], r["tau"]) for r in doc["rows"]] == [("soft", "2"), ("soft", "diag/2"), ("hard", "2"),
                                                            ("hard", "diag/2"), ("curve", "16 scales")]
    assert all(math.isfinite(r["wall_ms"]) and r["wall_ms"] > 0 and math.isfinite(r["host_ms"]) for r in doc["rows"])


def test_breakdown_times_the_torch_forward_and_backward(tmp_path):
    """``python -m bench.breakdown --ops torch`` on the CPU device times the torch op's VNC-soft forward + backward
    with every kernel launched (no graph replay), with the vertices' part from the forward's moments and from the edge
    adjoint (``--vertex-scatter``): one row per scale, with finite wall and host times and its kernels (each launch's
    thread CPU time on the CPU device), the vertex-gradient pass only where the moments are used."""
    from bench import breakdown

    out = tmp_path / "breakdown.json"
    for scatter in ("", "cpu"):
        assert breakdown.main(["--device", "cpu", "--mesh", str(mesh_path("spot_lowres.obj")), "--taus", "2", "--ops",
                               "torch", "--repeats", "1", "--no-graphs", "--vertex-scatter", scatter,
                               "--out", str(out)]) == 0
        rows = json.loads(out.read_text())["rows"]
        assert [(r["op"], r["tau"]) for r in rows] == [("torch", "2")]
        assert math.isfinite(rows[0]["wall_ms"]) and rows[0]["wall_ms"] > 0 and math.isfinite(rows[0]["host_ms"])
        kernels = rows[0]["kernels"]
        assert math.isfinite(rows[0]["device_ms"]) and kernels["soft_edge_adjoint"]["count"] == 1
        # the vertices' part: from the forward's moments, or added by the edge adjoint
        assert ("vertex_gradient" in kernels) == (scatter == "")


def test_tune_times_every_setting(tmp_path):
    """``python -m bench.tune`` on the CPU device times every setting of its grid per operator and scale, each a
    ``Tuning`` passed to the operators (no timing is asserted), and changes no default."""
    from bench import tune
    from vnc_warp.tuning import DEFAULT, Tuning

    out = tmp_path / "tune.json"
    assert tune.main(["--device", "cpu", "--mesh", str(mesh_path("spot_lowres.obj")), "--taus", "2", "--qb", "4",
                      "--splits", "auto", "--cell", "0.5", "1.0", "--spread", "8", "--busy", "0", "inf",
                      "--ball-kernels", "chords", "chunks", "--set", "min_run=4", "--repeats", "1",
                      "--out", str(out)]) == 0
    assert DEFAULT == Tuning()
    doc = json.loads(out.read_text())
    soft = [r for r in doc["rows"] if r["op"] == "soft"]
    hard = [r for r in doc["rows"] if r["op"] == "hard"]
    assert len(soft) == 4 and len(hard) == 8  # 2 cells x 2 busy (x 2 ball kernels)
    assert all(math.isfinite(r["ms"]) and r["ms"] > 0 for r in doc["rows"])
    assert {r["kernel"] for r in hard} == {"chords", "chunks"} and {r["min_run"] for r in doc["rows"]} == {4}


def test_counts_of_a_call(tmp_path):
    """``python -m bench.counts`` on the CPU device counts what each call asks of the device: with graph replay (as on
    CUDA) a call with ``positions=`` reads nothing back and launches one graph."""
    from bench import counts

    out = tmp_path / "counts.json"
    assert counts.main(["--mesh", str(mesh_path("spot_lowres.obj")), "--out", str(out)]) == 0
    calls = json.loads(out.read_text())["calls"]
    assert calls["vnc_soft (positions=)"].get("read back", 0) == 0
    assert calls["vnc_soft (positions=)"]["graph launch"] == 1 and "launch" not in calls["vnc_soft (positions=)"]
    assert calls["torch vnc_soft forward + backward"]["graph launch"] == 2


def test_out_folder_and_baseline_rows(tmp_path):
    """``--out`` naming a folder writes ``bench.json`` there; each row is set beside the same row of ``--baseline``
    (mesh, scale, name, variant) and a row more than 3 % slower is listed by the goal, a faster one is not."""
    args = bench.parse_args(["--device", "cpu", "--quick", "--out", str(tmp_path / "res")])
    assert args.out == str(tmp_path / "res" / "bench.json")
    base = tmp_path / "base.json"
    old = [{"mesh": "m", "tau_label": "2 l", "name": n, "variant": "auto", "median_ms": 10.0, "status": "ok"}
           for n in ("slow", "fast")]
    base.write_text(json.dumps({"device": {"name": "CPU"}, "date": "2026-11-21", "rows": old}))
    args = bench.parse_args(["--device", "cpu", "--out", str(tmp_path / "res"), "--baseline", str(base)])
    b = bench.Bench(args)
    for name, ms in (("slow", 10.4), ("fast", 9.0)):
        b.rows.append(bench.Row(section="operator", mesh="m", name=name, variant="auto", tau_label="2 l",
                                median_ms=ms))
    bench.compare_baseline(b)
    assert [round(r.extra["vs_baseline"], 3) for r in b.rows] == [1.04, 0.9]
    goal = next(g for g in bench.goals(b) if g["goal"].startswith("Every row of the baseline"))
    assert goal["met"] is False and goal["measured"] == 1 and "slow[auto] 1.040x" in goal["detail"]


def test_last_stage_moment_ellipsoid_recovers_an_ellipsoid():
    """bench.last_stage's oracle ellipsoid (from the solid's second moments, scaled to the area) of an exact
    ellipsoid, semi-axes 0.3 / 0.6 / 0.9 rotated and moved far from the origin, is that ellipsoid: its vertices
    satisfy the rotated quadric's equation to 1 %."""
    import trimesh

    from bench.last_stage import _moment_ellipsoid

    axes = np.array([0.3, 0.6, 0.9])
    rot = trimesh.transformations.rotation_matrix(0.7, [1.0, 2.0, 0.5])[:3, :3]
    centre = np.array([40.0, -7.0, 3.0])
    e = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
    e.vertices = (e.vertices * axes) @ rot.T + centre
    fit = _moment_ellipsoid(e)
    local = (np.asarray(fit.vertices) - centre) @ rot / axes
    assert np.abs(np.linalg.norm(local, axis=1) - 1.0).max() < 0.01


def test_remesh_topology_forces_the_level_set_path(tmp_path):
    """``bench.remesh_topology --force-level-set`` sends the second remesh of a small body down the marching-cubes
    path (the plain run re-tessellates it in place) and reports the S change and the edge-length spread of both
    results; the first remesh (the same in both runs) gives the same spread."""
    import trimesh
    from capsules import BODY, capsules

    from bench import remesh_topology

    trimesh.Trimesh(*capsules(BODY, nodes=64), process=False).export(tmp_path / "body.obj")
    rows = {}
    for flag in ([], ["--force-level-set"]):
        out = tmp_path / ("forced" if flag else "plain")
        remesh_topology.main(["--meshes", str(tmp_path), "--names", "body.obj", "--max-faces", "2000",
                              "--device", "cpu", "--out", str(out), *flag])
        rows[bool(flag)] = json.loads((out / "remesh_topology.json").read_text())["rows"][0]
    assert rows[False]["again_method"] == "surface" and rows[True]["again_method"] == "level_set"
    assert rows[True]["again_why"].startswith("forced")
    for row in rows.values():
        assert math.isfinite(row["dS"]) and row["euler_again"] == 2
        assert 0.0 < row["edge_spread0"] < 1.0 and 0.0 < row["edge_spread1"] < 1.0
    assert rows[True]["edge_spread0"] == pytest.approx(rows[False]["edge_spread0"], rel=1e-6)


def _run_json(path, device, medians):
    rows = [{"mesh": "m", "tau_label": s, "name": "vnc_soft", "variant": "auto", "status": "ok", "median_ms": v}
            for s, v in medians.items()]
    path.write_text(json.dumps({"device": {"name": device}, "rows": rows}))
    return str(path)


def test_ab_compares_the_best_median_of_each_side(tmp_path, capsys):
    """bench.ab sets each row's fastest base median beside its fastest head median: a row whose head is slower only
    in one of two runs is not flagged, one slower in both is; runs from two devices are refused."""
    from bench import ab

    b1 = _run_json(tmp_path / "b1.json", "gpu", {"2 l": 1.00, "8 l": 2.00})
    b2 = _run_json(tmp_path / "b2.json", "gpu", {"2 l": 1.04, "8 l": 2.02})
    h1 = _run_json(tmp_path / "h1.json", "gpu", {"2 l": 1.20, "8 l": 2.20})
    h2 = _run_json(tmp_path / "h2.json", "gpu", {"2 l": 1.01, "8 l": 2.10})
    res = ab.main(["--base", b1, b2, "--head", h1, h2, "--out", str(tmp_path / "ab.json")])
    by = {r["scale"]: r for r in res["rows"]}
    assert by["2 l"]["ratio"] == pytest.approx(1.01) and not by["2 l"]["slower"]
    assert by["8 l"]["ratio"] == pytest.approx(1.05) and by["8 l"]["slower"]
    assert res["compared"] == 2 and res["slower"] == 1
    assert json.loads((tmp_path / "ab.json").read_text())["slower"] == 1
    assert "1 more than 3 % slower" in capsys.readouterr().out
    other = _run_json(tmp_path / "o.json", "cpu", {"2 l": 1.0})
    with pytest.raises(SystemExit, match="more than one device"):
        ab.main(["--base", b1, other, "--head", h1])
