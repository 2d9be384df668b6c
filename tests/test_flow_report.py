"""``python -m bench.flow_report`` on the CPU with two small generated meshes: the JSON, the Markdown table and the
filmstrip it writes hold what the report promises, and the time budget skips (and lists) a mesh instead of
running past it. No timing is asserted."""

import json

import numpy as np

from bench import flow_report
from vnc_warp.shapes import random_shape


def test_flow_report_writes_table_json_and_filmstrip(tmp_path):
    """Two 4-stage runs at 600 faces: the first is kept with its filmstrip; every summary number is present and
    agrees with the per-stage records (max |t_i - (1 - i/N)|, the smallest thickness ratios, 5th percentile and
    thinnest part); the part breakdown
    has the remesh, within-stage remesh and stage parts (contact checks and remeshes within stages too, which the
    table left out), each stage says where its t went (t after the remesh between stages, the remeshes within, the
    S history), and the warm-up before timing is reported. Run again with a budget already spent after one mesh, the second is skipped
    and named as skipped."""
    meshes = tmp_path / "meshes"
    meshes.mkdir()
    for k in range(2):
        random_shape(3 + k, subdivisions=3).save(meshes / f"shape{k}.obj")
    out = tmp_path / "out"
    args = ["--meshes", str(meshes), "--all", "--stages", "4", "--max-faces", "600", "--device", "cpu",
            "--filmstrips", "shape0.obj", "--out", str(out)]
    assert flow_report.main(args) == 0
    report = json.loads((out / "flow_report.json").read_text())
    assert [r["mesh"] for r in report["runs"]] == ["shape0.obj", "shape1.obj"] and not report["skipped"]
    for run in report["runs"]:
        stages = run["stages"]
        assert len(stages) == 5
        dev = max(abs(r["t"] - (1 - r["index"] / 4)) for r in stages[1:])
        assert np.isclose(run["max_dt"], dev)
        ratios = [r["thickness_ratio"] for r in stages[1:]]
        assert np.isclose(run["min_thickness_ratio"], min(ratios))
        thinnest = [r["thinnest_ratio"] for r in stages[1:]]
        assert np.isclose(run["min_thinnest_ratio"], min(thinnest)) and len(run["thinnest"]) == 5
        # where t went: stage 1 starts from stage 0 unremeshed, and a stage that met its budget ends on its history
        assert np.isclose(stages[1]["t_start"], 1.0, atol=1e-5) and stages[0]["t_start"] is None
        for r in stages[1:]:
            assert r["t_start"] == r["history_t"][0][1] and isinstance(r["within"], list)
            if r["status"] == "budget":
                assert np.isclose(r["history_t"][-1][1], r["t"]), r
        assert np.isfinite(run["remesh_alone"]["dS"]) and run["seconds"] > 0
        assert {"remesh.sdf", "remesh.marching_cubes", "remesh.decimation", "remesh.checks", "within.n", "within.sdf",
                "stage.steps", "stage.evaluations", "stage.checks", "stage.remesh"} <= set(run["parts"])
    assert (out / "filmstrip_shape0.png").stat().st_size > 1000
    assert not (out / "filmstrip_shape1.png").exists()
    assert report["warmup_seconds"] > 0
    md = (out / "flow_report.md").read_text()
    assert "| shape0.obj |" in md and "S change, one remesh" in md and "remesh.sdf" in md and "stage.remesh" in md
    assert "smallest thinnest-part ratio" in md and "thinnest part" in md

    spent = tmp_path / "spent"
    assert flow_report.main(args[:-1] + [str(spent), "--max-minutes", "1e-6"]) == 0
    report = json.loads((spent / "flow_report.json").read_text())
    assert [r["mesh"] for r in report["runs"]] == ["shape0.obj"]
    assert [r["mesh"] for r in report["skipped"]] == ["shape1.obj"]
    assert "Skipped (time budget): shape1.obj" in (spent / "flow_report.md").read_text()


def test_a_stage_without_a_step_holds_the_previous_state():
    """summarize lists a stage that took no step of Eq. (5) (its mesh is the previous state re-tessellated, new
    vertices) as holding the previous stage's state, beside a stage whose vertices are the previous stage's; a
    stage that stepped is not listed."""
    from types import SimpleNamespace

    rng = np.random.default_rng(0)
    meshes = [SimpleNamespace(num_vertices=5, vertices=rng.random((5, 3))) for _ in range(4)]
    meshes[3] = SimpleNamespace(num_vertices=5, vertices=meshes[2].vertices.copy())
    recs = [{"index": i, "t": 1.0 - i / 4, "status": "budget", "thickness": 0.5, "thickness_ratio": 1.0,
             "iterations": it} for i, it in enumerate([0, 4, 0, 3])]
    traj = SimpleNamespace(records=recs, meshes=meshes, t=np.array([r["t"] for r in recs]))
    assert flow_report.summarize(traj, 4)["same_mesh_stages"] == [2, 3]
