"""``python -m bench.flow_stall`` on the CPU with a small generated mesh: it flows the mesh, diagnoses the stage it
is given, and what it writes agrees with the trajectory's own records (Eq. 7 recomputed from the stored state, the
remeshed state's S by two separate paths). No timing is asserted."""

import json

import numpy as np

from bench import flow_stall
from vnc_warp.shapes import random_shape


def test_flow_stall_measures_the_stage_it_is_given(tmp_path):
    """A 4-stage run at 600 faces, stage 2 diagnosed: the stage's t recomputed from its stored file is its recorded
    t; Eq. (5) from the remeshed state starts at the t of the first remesh (the stepper's S and total_complexity);
    every Eq. (5) variant and every smoothing row is there with finite t; without --stage, a run with no held stage
    says so instead of diagnosing one."""
    meshes = tmp_path / "meshes"
    meshes.mkdir()
    random_shape(3, subdivisions=3).save(meshes / "shape.obj")
    out = tmp_path / "out"
    result = flow_stall.main(["--meshes", str(meshes), "--names", "shape.obj", "--stages", "4", "--faces", "600",
                              "--stage", "2", "--steps", "4", "--dts", "1", "16", "--device", "cpu", "--out",
                              str(out)])
    assert json.loads((out / "flow_stall.json").read_text()) == json.loads(json.dumps(result))
    (doc,) = result["runs"]
    assert doc["stage"] == 2 and doc["faces"] == 600
    assert np.isclose(doc["t_state"], doc["t_recorded"], rtol=1e-5)
    assert len(doc["remesh"]) == 3 and all(np.isfinite(r["t"]) and r["t"] > 0 for r in doc["remesh"])
    eq5 = doc["eq5_remeshed"]
    assert [r["variant"] for r in eq5] == [name for name, _ in flow_stall.VARIANTS]
    assert all(np.isclose(r["t_start"], doc["remesh"][0]["t"], rtol=1e-4) for r in eq5)
    for r in eq5 + [doc["eq5_state"]]:
        assert r["t_min"] <= min(r["t_start"], r["t_end"]) and r["step_of_min"] % 4 == 0
    assert np.isclose(doc["eq5_state"]["t_start"], doc["t_state"], rtol=1e-4)
    rows = {(r["from"], r["volume_preserving"], r["dt"]) for r in doc["smoothing"]}
    assert rows == {(b, v, d) for b in ("state", "remeshed") for v in (False, True) for d in (1.0, 16.0)}
    assert all(len(r["t"]) == 3 and np.all(np.isfinite(r["t"])) for r in doc["smoothing"])

    run_dir = str(out / "trajectories" / "shape.obj")
    manifest = json.loads((out / "trajectories" / "shape.obj" / "manifest.json").read_text())
    statuses = [r["status"] for r in manifest["stages"]]
    first = flow_stall.diagnose(run_dir, None, dts=[1.0], steps=4, device="cpu")
    if "held" in statuses:
        assert first["stage"] == statuses.index("held") - 1
    else:
        assert first == {"run": run_dir, "held": [], "note": "no held stage"}
