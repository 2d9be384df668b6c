"""The checks of ``bench.scaling`` can fail: a trajectory whose stage file differs by one bit, a missing or unfinished
trajectory, and a loss curve that starts elsewhere, ends elsewhere, misses a step or goes non-finite are all mismatches;
the inputs are files in the formats flow-batch and training write (``manifest.json``, ``log.jsonl``). And the one
command runs end to end with 1 and 2 gloo processes at the smallest sizes."""

import json
import math
import shutil

import numpy as np
import pytest

from bench import scaling
from vnc_warp.flow import Trajectory
from vnc_warp.shapes import icosphere, random_shape


def _batch(root, *, moved=None, stages=2):
    """A flow-batch-like folder: one trajectory per shape, ``stages + 1`` stage files each; ``moved = (name, i)``
    nudges one coordinate of stage ``i`` of that shape by one float32 step."""
    for s in range(2):
        name = f"shape{s}.obj"
        base = random_shape(s, subdivisions=1)
        meshes = [base] + [icosphere(1, radius=1.0 + 0.1 * i, name=name) for i in range(1, stages + 1)]
        if moved is not None and moved[0] == name:
            m = meshes[moved[1]]
            v = m.vertices.astype(np.float32).copy()
            v[0, 0] = np.nextafter(v[0, 0], np.float32(np.inf))
            meshes[moved[1]] = type(m)(v, m.faces, m.topology, m.name)
        t = np.linspace(1.0, 0.1, stages + 1)
        traj = Trajectory(meshes, t, [{"index": i, "t": float(t[i])} for i in range(stages + 1)],
                          {"params": {"stages": stages}, "source": name})
        traj.save(root / name)
    return scaling.trajectory_digests(root)


def test_trajectory_comparison_detects_one_changed_bit(tmp_path):
    """Equal runs match; a stage file one float32 step apart, a trajectory that is missing and one with a stage
    fewer are mismatches, each naming the mesh (and the first differing stage)."""
    ref = _batch(tmp_path / "k1")
    same = _batch(tmp_path / "k2")
    res = scaling.compare_trajectories(ref, same)
    assert res["ok"] and res["identical"] == ["shape0.obj", "shape1.obj"]

    changed = scaling.compare_trajectories(ref, _batch(tmp_path / "moved", moved=("shape1.obj", 2)))
    assert not changed["ok"] and changed["identical"] == ["shape0.obj"]
    (d,) = changed["differ"]
    assert d["mesh"] == "shape1.obj" and d["first_stage"] == 2 and d["reason"] == "stage files differ"

    shutil.rmtree(tmp_path / "k2" / "shape0.obj")
    missing = scaling.compare_trajectories(ref, scaling.trajectory_digests(tmp_path / "k2"))
    assert not missing["ok"] and missing["missing"] == ["shape0.obj"]

    short = scaling.compare_trajectories(ref, _batch(tmp_path / "short", stages=1))
    assert not short["ok"] and {d["mesh"] for d in short["differ"]} == {"shape0.obj", "shape1.obj"}
    assert not scaling.compare_trajectories({}, {})["ok"]  # nothing compared is no match


def _log(path, losses):
    """A training run folder whose log.jsonl holds ``losses`` at steps 1.. (the rows train() writes)."""
    path.mkdir(parents=True, exist_ok=True)
    rows = [{"step": i + 1, "epoch": 0, "loss": v, "tsdf": v, "kl": 0.0, "eik": 0.0, "grad_norm": 1.0,
             "beta_kl": 0.0, "lr": 1e-3, "samples_per_s": 50.0 + i} for i, v in enumerate(losses)]
    (path / "log.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    return scaling.read_loss_curve(path)


def test_loss_comparison_detects_a_differing_curve(tmp_path):
    """A curve that starts equal and wanders by 3 % passes; one whose first step differs by 1e-4 (other weights or
    another global batch), one 6 % lower over the last half, one missing a step and one with a NaN fail."""
    base = 0.06 * np.exp(-np.arange(40) / 20.0)
    ref = _log(tmp_path / "ref", base.tolist())
    tol = dict(first_rtol=1e-5, tail_rtol=0.05)
    wander = base * (1 + 0.03 * np.sin(np.arange(40)))
    ok = scaling.compare_losses(ref, _log(tmp_path / "wander", wander.tolist()), **tol)
    assert ok["ok"] and ok["first_rel"] == 0.0 and ok["max_rel"] == pytest.approx(0.03, rel=1e-2)
    assert ok["steps"] == 40 and ok["tail_rel"] < 0.01

    first = base.copy()
    first[0] *= 1 + 1e-4
    moved = scaling.compare_losses(ref, _log(tmp_path / "first", first.tolist()), **tol)
    assert not moved["ok"] and moved["first_rel"] == pytest.approx(1e-4, rel=1e-3) and moved["tail_rel"] == 0.0

    lower = base.copy()
    lower[20:] *= 0.94
    tail = scaling.compare_losses(ref, _log(tmp_path / "lower", lower.tolist()), **tol)
    assert not tail["ok"] and tail["tail_rel"] == pytest.approx(0.06) and tail["first_rel"] == 0.0

    short = scaling.compare_losses(ref, _log(tmp_path / "short", base[:-1].tolist()), **tol)
    assert not short["ok"] and short["missing"] == [40]

    bad = base.copy()
    bad[25] = math.nan
    assert not scaling.compare_losses(ref, _log(tmp_path / "nan", bad.tolist()), **tol)["ok"]


def test_steady_rate_is_the_harmonic_mean_after_the_first_rows(tmp_path):
    """Steady samples/s: the first tenth of the rows is dropped and the rest averaged harmonically (total samples over
    total time for equal windows)."""
    _log(tmp_path, [0.1] * 10)  # rates 50, 51, ..., 59
    rates = np.arange(51.0, 60.0)
    assert scaling.steady_rate(tmp_path) == pytest.approx(len(rates) / np.sum(1.0 / rates))


def test_one_command_makes_the_table(tmp_path):
    """``python -m bench.scaling`` at the smallest sizes (2 genus-0 meshes, 1 stage, 2 training steps) runs every
    torchrun command for K = 1 and 2 on the CPU and writes the report: each mesh on its documented rank and device,
    the 2-process trajectories bit for bit those of one process, the K = 1 repeat too, the first step's loss equal."""
    doc = scaling.main(["--device", "cpu", "--ranks", "1,2", "--out", str(tmp_path / "out"), "--real", "",
                        "--procedural", "2", "--stages", "1", "--max-iters", "20", "--faces", "600", "--steps", "2",
                        "--substage-budget", "1",
                        "--global-batch", "2", "--repeat", "1", "--no-seed-spread"])
    on_disk = json.loads((tmp_path / "out" / "scaling.json").read_text())
    assert on_disk["table"] == json.loads(json.dumps(doc["table"]))
    assert [row["K"] for row in doc["table"]] == [1, 2]
    flows, trains = doc["flows"], doc["trains"]
    assert all(flows[k]["rc"] == 0 and flows[k]["statuses"] == {"done": 2} for k in ("1", "2"))
    assert flows["2"]["wrong_rank"] == [] and flows["2"]["devices"] == ["cpu"]
    assert flows["2"]["match"]["ok"] and len(flows["2"]["match"]["identical"]) == 2
    assert flows["repeat"]["match"]["ok"]
    assert trains["2"]["rc"] == 0 and trains["2"]["per_rank_batch"] == 1 and trains["1"]["per_rank_batch"] == 2
    assert trains["2"]["match"]["first_rel"] <= 1e-5 and sorted(trains["2"]["loss"]) == [1, 2]
    md = (tmp_path / "out" / "scaling.md").read_text()
    assert doc["command"] in md and "| 2 |" in md and "bit for bit" in md
