"""Nothing lost, nothing silently wrong (issue 20): trajectory folders that own their files, flow-batch outcomes,
output folders checked first, bad arguments of the operators, and one-line errors from every command.

Every test here reproduces a case of issue 20 that lost work, returned a wrong answer without a word or ended in a
raw traceback at dd885f9; the docstrings say what happened then.
"""

import json
import os
import shutil
import signal
import subprocess
import sys
import time
import warnings

import numpy as np
import pytest
import trimesh
import warp as wp

import vnc_warp as vw
from vnc_warp.cli import main
from vnc_warp.flow import Trajectory, flow
from vnc_warp.shapes import icosphere, random_shape

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# These tests are about files, errors and resumes, not the schedule: one flow per stage (no sub-stages) keeps
# their flows short; a resume and the run it continues must agree on it.
ONE_PIECE = {"substage_budget": 1.0}
ONE_PIECE_ARGS = ["--substage-budget", "1"]


def _quiet_flow(src, out, stages=1, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return flow(src, stages=stages, device="cpu", progress=False, out_dir=out, **{**ONE_PIECE, **kw})


@pytest.fixture(scope="module")
def meshes(tmp_path_factory):
    """Three small closed shapes as .obj files, a non-manifold one and a file that is no mesh at all."""
    d = tmp_path_factory.mktemp("meshes")
    for s in range(3):
        random_shape(s, subdivisions=2).save(d / f"shape{s}.obj")
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1]], float)
    trimesh.Trimesh(v, [[0, 1, 2], [1, 0, 3], [0, 1, 4]], process=False).export(d / "fin.obj")
    (d / "garbage.ply").write_bytes(b"ply\nformat nonsense\n\x00\x01")
    return d


@pytest.fixture(scope="module")
def finished(meshes, tmp_path_factory):
    """A finished 2-stage trajectory of shape0.obj (copied by the tests that alter it)."""
    out = tmp_path_factory.mktemp("finished") / "traj"
    _quiet_flow(str(meshes / "shape0.obj"), out, stages=2)
    return out


@pytest.fixture
def readonly_dir(tmp_path):
    """A folder nothing can be written into: permission bits for a user, the immutable attribute for root."""
    d = tmp_path / "readonly"
    d.mkdir()
    root = os.geteuid() == 0
    if root:
        if shutil.which("chattr") is None or subprocess.run(["chattr", "+i", str(d)], capture_output=True).returncode:
            pytest.skip("running as root without chattr +i: no read-only folder can be made")
    else:
        d.chmod(0o555)
    try:
        (d / "probe").write_text("x")
    except OSError:
        pass
    else:
        pytest.skip("this file system lets every user write into a read-only folder")
    yield d
    if root:
        subprocess.run(["chattr", "-i", str(d)], check=True)
    else:
        d.chmod(0o755)


def _one_line_error(capsys, *needles):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "Traceback" not in err[0], err
    for needle in needles:
        assert needle in err[0], (needle, err[0])
    return err[0]


# --- trajectory folders (item 3) -----------------------------------------------------------------------------


def test_stage_files_without_a_manifest_are_refused(meshes, tmp_path, capsys):
    """A folder holding stage PLYs but no manifest.json (a user's stray copy) was silently mixed with a new run
    (save() skipped the existing file, so the manifest described one mesh and the file held another); now the
    flow, Trajectory.load and `vnc-warp dataset` refuse it and the stray file is left as it was."""
    out = tmp_path / "traj"
    out.mkdir()
    icosphere(2).save(out / "stage_000.ply")
    before = (out / "stage_000.ply").read_bytes()
    with pytest.raises(ValueError, match="stage file.*but no manifest.json"):
        _quiet_flow(str(meshes / "shape1.obj"), out)
    assert (out / "stage_000.ply").read_bytes() == before and not (out / "manifest.json").exists()
    with pytest.raises(ValueError, match="but no manifest.json"):
        Trajectory.load(out)
    assert main(["dataset", str(out), "--out", str(tmp_path / "data"), "--device", "cpu", "--quiet"]) == 2
    _one_line_error(capsys, "but no manifest.json", str(out))


def test_a_replaced_stage_file_is_refused(finished, meshes, tmp_path, capsys):
    """A stage file replaced after it was written was loaded, resumed from and sampled without notice; now the
    manifest holds every stage file's SHA-256, and loading, resuming and `vnc-warp dataset` refuse the file."""
    out = tmp_path / "traj"
    shutil.copytree(finished, out)
    icosphere(2).save(out / "stage_001.ply")
    with pytest.raises(ValueError, match=r"stage_001\.ply: does not match its checksum"):
        Trajectory.load(out)
    man = json.loads((out / "manifest.json").read_text())
    man["stages"] = man["stages"][:2]  # a run interrupted after stage 1: the next run resumes from it
    man["complete"] = False
    (out / "manifest.json").write_text(json.dumps(man))
    (out / "stage_002.ply").unlink()
    with pytest.raises(ValueError, match=r"stage_001\.ply: does not match its checksum"):
        _quiet_flow(str(meshes / "shape0.obj"), out, stages=2)
    assert main(["dataset", str(out), "--out", str(tmp_path / "data"), "--device", "cpu", "--quiet"]) == 2
    _one_line_error(capsys, "stage_001.ply: does not match its checksum")


def test_a_stage_file_the_manifest_does_not_list_is_refused(finished, meshes, tmp_path, capsys):
    """A stage file the manifest does not own (here a copy of another stage) made load, resume and the dataset
    accept a folder whose files are not all the run's; now all three refuse it, naming the file."""
    out = tmp_path / "traj"
    shutil.copytree(finished, out)
    shutil.copy(out / "stage_001.ply", out / "stage_007.ply")
    with pytest.raises(ValueError, match=r"does not list \(stage_007\.ply\)"):
        Trajectory.load(out)
    with pytest.raises(ValueError, match=r"does not list \(stage_007\.ply\)"):
        _quiet_flow(str(meshes / "shape0.obj"), out, stages=2)
    assert main(["dataset", str(out), "--out", str(tmp_path / "data"), "--device", "cpu", "--quiet"]) == 2
    _one_line_error(capsys, "stage_007.ply")


def test_damaged_manifests_are_named(finished, meshes, tmp_path, capsys):
    """A manifest that is a JSON list gave an AttributeError traceback and a truncated one a JSON error without
    the file's name; both are now a one-line error naming manifest.json, from the library and the flow command."""
    out = tmp_path / "traj"
    shutil.copytree(finished, out)
    text = (out / "manifest.json").read_text()
    for content, what in ((json.dumps([1, 2]), "holds a list"), (text[: len(text) // 2], "truncated")):
        (out / "manifest.json").write_text(content)
        with pytest.raises(ValueError, match=f"{out / 'manifest.json'}: .*{what}"):
            Trajectory.load(out)
        code = main(["flow", str(meshes / "shape0.obj"), "--out", str(out), "--stages", "2", "--device", "cpu",
                     "--no-progress"])
        assert code == 2
        _one_line_error(capsys, str(out / "manifest.json"), what)


def test_legacy_manifest_is_read_with_a_warning_and_gets_checksums(finished, meshes, tmp_path):
    """A manifest of the first format (no checksums) is read with a warning that its files are unverified, and
    resuming the run records the checksums of its files."""
    out = tmp_path / "traj"
    shutil.copytree(finished, out)
    man = json.loads((out / "manifest.json").read_text())
    for st in man["stages"]:
        st.pop("sha256", None)
    man = {k: v for k, v in man.items() if k != "writing"}
    (out / "manifest.json").write_text(json.dumps(dict(man, format="vnc-warp-trajectory/1")))
    with pytest.warns(UserWarning, match="without checksums"):
        assert len(Trajectory.load(out).meshes) == 3
    with pytest.warns(UserWarning, match="without checksums"):
        _quiet_flow_warned(str(meshes / "shape0.obj"), out)
    upgraded = json.loads((out / "manifest.json").read_text())
    assert upgraded["format"] == "vnc-warp-trajectory/2"
    assert all(len(st["sha256"]) == 64 for st in upgraded["stages"])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        Trajectory.load(out)


def _quiet_flow_warned(src, out):
    """Resume with the flow's own stage warnings hidden, its legacy-manifest warning kept."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="VNC-Flow stage")
        return flow(src, stages=2, device="cpu", progress=False, out_dir=out, **ONE_PIECE)


def test_a_run_killed_while_saving_resumes(meshes, tmp_path, monkeypatch):
    """A run killed after a stage file is written but before the manifest lists it resumes: the manifest names
    the file as the one being written, which the next run overwrites (design check: the write order)."""
    from vnc_warp import trajectory as traj_mod

    out = tmp_path / "traj"
    real = traj_mod._write_manifest
    calls = []

    def killed_after_stage_1(root, info, stages, *, writing, complete):
        calls.append(writing)
        if writing is None and len(stages) == 2:
            raise KeyboardInterrupt
        return real(root, info, stages, writing=writing, complete=complete)

    monkeypatch.setattr(traj_mod, "_write_manifest", killed_after_stage_1)
    with pytest.raises(KeyboardInterrupt):
        _quiet_flow(str(meshes / "shape1.obj"), out, stages=2)
    monkeypatch.setattr(traj_mod, "_write_manifest", real)
    man = json.loads((out / "manifest.json").read_text())
    assert [s["file"] for s in man["stages"]] == ["stage_000.ply"] and man["writing"] == "stage_001.ply"
    assert (out / "stage_001.ply").exists()
    traj = _quiet_flow(str(meshes / "shape1.obj"), out, stages=2)
    assert traj.complete and Trajectory.load(out).complete


# --- output folders checked first -----------------------------------------------------------------------------


@pytest.fixture
def a_file(tmp_path):
    f = tmp_path / "a_file"
    f.write_text("not a folder")
    return f


def _no_compute(monkeypatch):
    """Make any remeshing or VNC evaluation fail the test: the output must be checked before anything is computed."""
    from vnc_warp import remesh

    def forbidden(*a, **k):
        raise AssertionError("computed before the output location was checked")

    monkeypatch.setattr(remesh, "sdf_remesh", forbidden)
    monkeypatch.setattr(vw, "scale_curve", forbidden)
    monkeypatch.setattr(vw, "vnc_soft", forbidden)


@pytest.mark.parametrize("where", ["under_file", "readonly"])
def test_outputs_are_checked_before_computing(where, meshes, finished, a_file, request, tmp_path, monkeypatch, capsys):
    """`--out` under a file or in a read-only folder gave FileExistsError / NotADirectoryError / PermissionError
    tracebacks from curvature, flow, train and dataset, and the flow computed stage 0 first; now each exits 2 with
    one line naming the folder, before anything is computed."""
    base = a_file if where == "under_file" else request.getfixturevalue("readonly_dir")
    out = base / "sub" / "out"
    mesh = str(meshes / "shape0.obj")
    _no_compute(monkeypatch)
    runs = {
        "curvature": ["curvature", mesh, "--out", str(out), "--tau", "0.2", "--device", "cpu"],
        "flow": ["flow", mesh, "--out", str(out), "--stages", "1", "--device", "cpu", "--no-progress"],
        "dataset": ["dataset", str(finished), "--out", str(out), "--device", "cpu", "--quiet"],
        "train": ["train", "--config", "tiny", "--data", str(tmp_path), "--out", str(out), "--device", "cpu"],
    }
    for name, argv in runs.items():
        assert main(argv) == 2, name
        line = _one_line_error(capsys, str(base))
        assert ("is a file" in line) if where == "under_file" else ("not writable" in line or "cannot" in line), line


# --- flow-batch (item 2) --------------------------------------------------------------------------------------


def _batch(in_dir, out_dir, *extra):
    return main(["flow-batch", str(in_dir), str(out_dir), "--device", "cpu", "--no-progress", *ONE_PIECE_ARGS,
                 *extra])


def _entries(out_dir):
    return {m["mesh"]: m for m in json.loads((out_dir / "batch.json").read_text())["meshes"]}


def test_flow_batch_refuses_to_reuse_other_parameters(meshes, tmp_path, capsys):
    """Re-run with other --stages, flow-batch marked every mesh "skipped" and exited 0 with the old
    trajectories; now each is refused with the differing parameter, the old trajectory is left as it was and
    the exit code is 1."""
    src = tmp_path / "in"
    src.mkdir()
    shutil.copy(meshes / "shape0.obj", src)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert _batch(src, tmp_path / "out", "--stages", "1") == 0
        assert _entries(tmp_path / "out")["shape0.obj"]["status"] == "done"
        capsys.readouterr()
        assert _batch(src, tmp_path / "out", "--stages", "2") == 1
    entry = _entries(tmp_path / "out")["shape0.obj"]
    assert entry["status"] == "refused" and "stages: 1 there, 2 now" in entry["error"]
    assert len(Trajectory.load(tmp_path / "out" / "shape0.obj").meshes) == 2
    out = capsys.readouterr().out
    assert "shape0.obj: refused" in out and "1 refused" in out


def test_flow_batch_goes_on_after_a_bad_mesh(meshes, tmp_path, capsys):
    """One bad mesh aborted the batch with an error that did not name the file; now each bad mesh is recorded
    in batch.json with its error (naming it), the others are flowed, one line is printed per mesh and a total."""
    src = tmp_path / "in"
    src.mkdir()
    for name in ("fin.obj", "garbage.ply", "shape1.obj"):
        shutil.copy(meshes / name, src)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert _batch(src, tmp_path / "out", "--stages", "1") == 1
    e = _entries(tmp_path / "out")
    assert e["fin.obj"]["status"] == "failed" and "fin.obj" in e["fin.obj"]["error"]
    assert "non-manifold" in e["fin.obj"]["error"]
    assert e["garbage.ply"]["status"] == "failed" and "garbage.ply" in e["garbage.ply"]["error"]
    assert e["shape1.obj"]["status"] == "done"
    assert Trajectory.load(tmp_path / "out" / "shape1.obj").complete
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 4 and lines[-1].startswith("flow-batch: 3 mesh(es): 1 done, 2 failed")


def test_flow_batch_keys_outputs_by_file_name_and_accumulates(meshes, tmp_path):
    """shape.obj and shape.ply shared one output folder (the second was "skipped" with the first one's
    trajectory) and batch.json was overwritten by every run; now each file gets its own folder and batch.json
    keeps the entries of earlier runs."""
    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir()
    b.mkdir()
    shutil.copy(meshes / "shape1.obj", a / "shape.obj")
    random_shape(2, subdivisions=2).save(a / "shape.ply")
    shutil.copy(meshes / "shape0.obj", b / "other.obj")
    out = tmp_path / "out"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert _batch(a, out, "--stages", "1") == 0
        assert _batch(b, out, "--stages", "1") == 0
    e = _entries(out)
    assert sorted(e) == ["other.obj", "shape.obj", "shape.ply"]
    assert {m["status"] for m in e.values()} == {"done"}
    for name in ("shape.obj", "shape.ply"):
        assert Trajectory.load(out / name).source == name
    v_obj = Trajectory.load(out / "shape.obj").meshes[0].vertices
    v_ply = Trajectory.load(out / "shape.ply").meshes[0].vertices
    assert v_obj.shape != v_ply.shape or not np.allclose(v_obj, v_ply)


def _torchrun(args, port, **kw):
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node=2", f"--master_port={port}", "-m",
           "vnc_warp.cli", "flow-batch", *map(str, args), "--device", "cpu", "--no-progress", *ONE_PIECE_ARGS]
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONWARNINGS="ignore")
    return subprocess.Popen(cmd, env=env, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kw)


def _rank_pid(agent_pid: int, rank: int) -> int | None:
    """The pid of the torchrun worker of ``rank`` (a child of the agent with RANK=rank in its environment)."""
    for pid in os.listdir("/proc"):
        if not pid.isdigit():
            continue
        try:
            with open(f"/proc/{pid}/stat") as fh:
                ppid = int(fh.read().rsplit(")", 1)[1].split()[1])
            if ppid != agent_pid:
                continue
            with open(f"/proc/{pid}/environ", "rb") as fh:
                if f"RANK={rank}".encode() in fh.read().split(b"\0"):
                    return int(pid)
        except (OSError, ValueError, IndexError):
            continue
    return None


def _listed_stages(folder):
    """``{stage file: (sha256, mtime_ns)}`` of the stages a trajectory folder's manifest lists (empty without one)."""
    man = folder / "manifest.json"
    if not man.is_file():
        return {}
    return {st["file"]: (st["sha256"], (folder / st["file"]).stat().st_mtime_ns)
            for st in json.loads(man.read_text())["stages"]}


@pytest.mark.skipif(not os.path.isdir("/proc"), reason="finds the torchrun workers through /proc")
def test_flow_batch_under_torchrun_survives_bad_meshes_and_a_killed_rank(meshes, tmp_path, free_port):
    """Under torchrun (2 gloo ranks) a bad mesh killed its rank and torchrun the other one mid-flow, and nothing
    was recorded before the end; now the bad mesh is recorded and the batch goes on, every finished mesh is in
    batch.json at once, and after a rank is killed (SIGKILL) in the middle of a mesh a re-run finishes everything
    once: finished meshes are skipped, the interrupted ones resume after their last stage (the stage files written
    before the kill are neither recomputed nor rewritten), and the resumed trajectory is bit for bit the one an
    uninterrupted run makes."""
    src = tmp_path / "in"
    src.mkdir()
    names = ["a0.obj", "a1.obj", "b0.obj", "b1.obj", "c0.obj", "zfin.obj"]  # rank 0: a0 b0 c0; rank 1: a1 b1 zfin
    for k, name in enumerate(names[:-1]):
        random_shape(10 + k, subdivisions=2).save(src / name)
    shutil.copy(meshes / "fin.obj", src / "zfin.obj")
    out = tmp_path / "out"
    proc = _torchrun([src, out, "--stages", "3"], free_port())
    victim, killed_after = None, None
    deadline = time.time() + 240
    while time.time() < deadline and proc.poll() is None:
        try:
            entries = _entries(out)
        except (OSError, ValueError):
            entries = {}
        done1 = [m for m in entries.values() if m["rank"] == 1 and m["status"] == "done"]
        try:
            # rank 1's second mesh has a finished stage and is not complete: kill it in the middle of that mesh
            midway = 0 < len(_listed_stages(out / "b1.obj")) < 4
        except (OSError, ValueError, KeyError):
            midway = False
        if done1 and midway:
            victim = _rank_pid(proc.pid, 1)
            if victim is not None:
                os.kill(victim, signal.SIGKILL)
                killed_after = sorted(m["mesh"] for m in done1)
                break
        time.sleep(0.02)
    proc.communicate(timeout=120)
    assert killed_after, "rank 1 finished a mesh and was killed in the middle of the next one"
    before = {name: _listed_stages(out / name) for name in names[:-1]}
    assert 0 < len(before["b1.obj"]) < 4, before["b1.obj"]
    again = _torchrun([src, out, "--stages", "3"], free_port())
    stdout, stderr = again.communicate(timeout=300)
    assert again.returncode != 0, "a failed mesh gives exit code 1"
    e = _entries(out)
    assert sorted(e) == names
    assert e["zfin.obj"]["status"] == "failed" and "zfin.obj" in e["zfin.obj"]["error"]
    for name in killed_after:
        assert e[name]["status"] == "skipped", (name, e[name])  # finished before the kill: not computed again
    for name in names[:-1]:
        assert Trajectory.load(out / name).complete, name
        expected = "skipped" if len(before[name]) == 4 else "resumed" if before[name] else "done"
        assert e[name]["status"] == expected, (name, e[name], len(before[name]))
        after = _listed_stages(out / name)
        assert {f: after[f] for f in before[name]} == before[name], name  # same bytes, not rewritten
    reference = tmp_path / "uninterrupted"
    _quiet_flow(str(src / "b1.obj"), reference, stages=3)
    assert [v[0] for v in _listed_stages(reference).values()] == [v[0] for v in _listed_stages(out / "b1.obj").values()]
    assert "flow-batch: 6 mesh(es):" in stdout and "1 failed" in stdout


# --- operators: bad arguments ---------------------------------------------------------------------------------


def test_operator_arguments_are_checked(device):
    """tau=None gave a float() TypeError, points=np.zeros((0, 3)) raised from inside Warp, and NaN in
    `positions=` silently gave zeros and NaN on the Warp path while the torch wrapper refused it; now tau=None
    names tau, no points give no values, and NaN positions or bad scales given on the device raise with every
    strategy."""
    mesh = icosphere(2)
    with pytest.raises(TypeError, match="tau must be a positive number"):
        vw.vnc_soft(mesh, None, device=device)
    with pytest.raises(TypeError, match="tau must be a positive number"):
        vw.vnc_hard(mesh, "big", device=device)
    empty = vw.integrated_mean_curvature(mesh, 0.3, points=np.zeros((0, 3)), device=device)
    assert empty.shape == (0,)
    v = mesh.vertices.copy()
    v[3] = np.nan
    x = wp.array(v, dtype=wp.vec3, device=device)
    for strategy in vw.STRATEGIES:
        with pytest.raises(ValueError, match="positions: 1 of 162 point"):
            vw.vnc_soft(mesh, 0.3, positions=x, strategy=strategy)
        with pytest.raises(ValueError, match="positions: 1 of 162 point"):
            vw.scale_curve(mesh, [0.2, 0.3], positions=x, strategy=strategy)
    tau = np.full(mesh.num_vertices, 0.3, np.float32)
    tau[5] = 0.0
    for strategy in vw.STRATEGIES:
        with pytest.raises(ValueError, match="not positive and finite"):
            vw.vnc_soft(mesh, wp.array(tau, dtype=wp.float32, device=device), device=device, strategy=strategy)
        with pytest.raises(ValueError, match="not positive and finite"):
            vw.vnc_hard(mesh, wp.array(tau, dtype=wp.float32, device=device), device=device, strategy=strategy)


# --- commands: one line and exit code 2 -----------------------------------------------------------------------


def test_non_manifold_errors_name_the_file(meshes, tmp_path, capsys):
    """A non-manifold mesh gave "mesh is non-manifold" without saying which file; now the file is named."""
    assert main(["curvature", str(meshes / "fin.obj"), "--out", str(tmp_path / "c"), "--tau", "0.3"]) == 2
    _one_line_error(capsys, "fin.obj: mesh is non-manifold")


def test_generate_refuses_an_unknown_format_first(tmp_path, meshes, capsys, monkeypatch):
    """`generate --format xyz123` printed trimesh's unformatted tuple ('%s exporter not available!', 'xyz123')
    after decoding; now it is refused before anything is decoded, in one line."""
    from vnc_warp.training import inference
    from vnc_warp.training.checkpoint import save_checkpoint
    from vnc_warp.training.config import named_config
    from vnc_warp.training.model import build_model

    cfg = named_config("tiny")
    save_checkpoint(tmp_path / "m.pt", model=build_model(cfg.model), config=cfg, step=1)
    monkeypatch.setattr(inference, "decode_mesh", lambda *a, **k: pytest.fail("decoded before the check"))
    assert main(["generate", str(tmp_path / "m.pt"), "--input", str(meshes / "shape0.obj"), "--out",
                 str(tmp_path / "g"), "--format", "xyz123", "--device", "cpu"]) == 2
    _one_line_error(capsys, "--format 'xyz123'")


def test_checkpoint_errors_never_advise_weights_only_false(tmp_path):
    """A random-bytes checkpoint repeated torch's advice to load with weights_only=False (which runs any code in
    the file); neither it nor a malicious pickle's message suggests that now, and both name the file."""
    from vnc_warp.training.checkpoint import CheckpointError, load_checkpoint

    rng = np.random.default_rng(0)
    (tmp_path / "random.pt").write_bytes(rng.integers(0, 256, 4096, dtype=np.uint8).tobytes())

    class Evil:
        def __reduce__(self):
            return (os.system, ("echo owned",))

    import torch

    torch.save({"format": "vnc-warp-checkpoint", "payload": Evil()}, tmp_path / "evil.pt")
    for name in ("random.pt", "evil.pt"):
        with pytest.raises(CheckpointError) as info:
            load_checkpoint(tmp_path / name)
        msg = str(info.value)
        assert str(tmp_path / name) in msg and "weights_only" not in msg and "False" not in msg, msg


@pytest.mark.parametrize("argv", [
    ["curvature", "{missing}.obj", "--out", "{tmp}/c"],
    ["flow", "{missing}.obj", "--out", "{tmp}/f"],
    ["flow-batch", "{missing}", "{tmp}/b"],
    ["dataset", "{missing}", "--out", "{tmp}/d", "--quiet"],
    ["train", "--config", "tiny", "--data", "{missing}", "--out", "{tmp}/r"],
    ["generate", "{missing}.pt", "--input", "{missing}.obj", "--out", "{tmp}/g"],
    ["evaluate", "--pred", "{missing}", "--gt", "{missing}"],
    ["demo", "--mesh", "{missing}.obj", "--out", "{tmp}/demo"],
])
def test_every_command_gives_one_line_and_code_2(argv, tmp_path, capsys):
    """Each user-facing command answers a missing input with one line on stderr and exit code 2, never a traceback
    (a guard of the contract: this already held at dd885f9)."""
    filled = [a.format(missing=tmp_path / "missing", tmp=tmp_path) for a in argv]
    assert main(filled) == 2
    _one_line_error(capsys, "error:")


def test_bugs_keep_their_traceback(monkeypatch):
    """An exception that is no user error (a bug) is not turned into a one-line message (a guard)."""
    from vnc_warp.commands import curvature

    def bug(args):
        raise AttributeError("a bug")

    monkeypatch.setattr(curvature, "run", bug)
    with pytest.raises(AttributeError, match="a bug"):
        main(["curvature", "--out", "x"])
