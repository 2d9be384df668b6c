"""What a user gets for bad inputs, interruptions and re-runs (issue 20): every case run as a user would, observed.

    python -m bench.bad_inputs --out OUT                       # this checkout
    python -m bench.bad_inputs --root OLD_CHECKOUT --out OUT   # another checkout of the package, for comparison
    python -m bench.bad_inputs --markdown AFTER.json [--before BEFORE.json]

``--only`` runs the cases whose name holds one of its words; with ``--out`` it updates those cases in the JSON a
full run left there (the JSON lists such re-runs).

Each case makes its inputs in a fresh folder, runs the ``vnc-warp`` commands (``python -m vnc_warp.cli`` from the
checkout) or a few lines of Python, and records what came back: the exit code, the error line (or that a raw
traceback came instead), and the state of the files afterwards (checkpoint step, log rows, batch.json statuses,
...). Nothing is asserted: the outcome is a description of what happened. Writes ``OUT/bad_inputs.json`` and
prints a markdown table; ``--markdown`` renders a table from saved JSON (two columns with ``--before``).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

HERE = Path(__file__).resolve().parents[1]
MAKE_MESHES = """
import numpy as np, trimesh, sys
from vnc_warp.shapes import random_shape
d = sys.argv[1]
for s in range(3):
    random_shape(s, subdivisions=2).save(f"{d}/shape{s}.obj")
random_shape(5, subdivisions=2).save(f"{d}/shape0.ply")
v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1]], float)
trimesh.Trimesh(v, [[0, 1, 2], [1, 0, 3], [0, 1, 4]], process=False).export(f"{d}/fin.obj")
"""


class Case:
    """One case: ``root`` is the checkout under test, ``work`` a fresh folder, ``meshes`` the shared inputs."""

    def __init__(self, root: Path, work: Path, meshes: Path):
        self.root, self.work, self.meshes = root, work, meshes

    def run(self, *args, timeout=600, env=None) -> subprocess.CompletedProcess:
        e = dict(os.environ, OMP_NUM_THREADS="1", **(env or {}))
        p = subprocess.run([sys.executable, *map(str, args)], cwd=self.root, env=e, capture_output=True, text=True,
                           timeout=timeout)
        p.stdout, p.stderr = self.clean(p.stdout), self.clean(p.stderr)
        return p

    def clean(self, text: str) -> str:
        """``text`` with the temporary folders shortened (``WORK/``, ``MESHES/``)."""
        return text.replace(str(self.work) + "/", "WORK/").replace(str(self.meshes) + "/", "MESHES/")

    def cli(self, *args, **kw) -> subprocess.CompletedProcess:
        return self.run("-m", "vnc_warp.cli", *args, **kw)

    def py(self, code: str, **kw) -> subprocess.CompletedProcess:
        return self.run("-c", textwrap.dedent(code), **kw)


def said(p: subprocess.CompletedProcess) -> str:
    """What the user read: the error line, 'raw traceback (...)' or the first warning, shortened."""
    lines = [x for x in p.stderr.splitlines() if x.strip() and "CUDA driver" not in x]
    if lines and lines[-1].startswith("still running"):
        return lines[-1]
    if any(x.startswith("Traceback") for x in lines):
        return f"raw traceback ({_short(lines[-1])})"
    errors = [x for x in lines if ": error:" in x or ": interrupted" in x]
    if errors:
        return _short(errors[-1].split(": ", 1)[1])
    warns = [x for x in lines if "Warning:" in x and "VNC-Flow stage" not in x]
    return f"warning: {_short(warns[0].split('Warning: ', 1)[1])}" if warns else "no message"


def _short(text: str, n: int = 170) -> str:
    text = text.strip()
    return text if len(text) <= n else text[: n - 3] + "..."


def _rows(run: Path) -> int:
    p = run / "log.jsonl"
    return len([x for x in p.read_text().splitlines() if x.strip()]) if p.is_file() else 0


def _ckpt_step(case: Case, run: Path) -> str:
    p = case.py(f"import torch; print(torch.load({str(run / 'checkpoints' / 'last.pt')!r}, weights_only=True)['step'])")
    return p.stdout.strip() if p.returncode == 0 else "none"


def _statuses(out: Path) -> str:
    p = out / "batch.json"
    if not p.is_file():
        return "no batch.json"
    meshes = json.loads(p.read_text())["meshes"]
    return ", ".join(f"{m['mesh']}: {m['status']}" for m in meshes)


# --- shared inputs -------------------------------------------------------------------------------------------


def _trajectory(case: Case, name="shape0.obj", stages=2) -> Path:
    out = case.work / "traj"
    case.cli("flow", case.meshes / name, "--out", out, "--stages", stages, "--device", "cpu", "--no-progress")
    return out


def _dataset(case: Case) -> Path:
    trajs = []
    for k in (0, 1):
        out = case.work / f"t{k}"
        case.cli("flow", case.meshes / f"shape{k}.obj", "--out", out, "--stages", 1, "--device", "cpu",
                 "--no-progress")
        trajs.append(out)
    case.cli("dataset", *trajs, "--out", case.work / "data", "--device", "cpu", "--num-surface", 300,
             "--num-uniform", 300, "--num-near", 300, "--quiet")
    return case.work / "data"


def _train(case: Case, data: Path, run: Path, *extra, **kw) -> subprocess.CompletedProcess:
    return case.cli("train", "--config", "tiny", "--data", data, "--out", run, "--device", "cpu", "--no-progress",
                    *extra, **kw)


def _readonly(path: Path) -> bool:
    path.mkdir(parents=True, exist_ok=True)
    if os.geteuid() == 0:
        if shutil.which("chattr") is None or subprocess.run(["chattr", "+i", str(path)]).returncode:
            return False
    else:
        path.chmod(0o555)
    return True


def _writable(path: Path) -> None:
    if os.geteuid() == 0:
        subprocess.run(["chattr", "-i", str(path)])
    else:
        path.chmod(0o755)


# --- the cases -----------------------------------------------------------------------------------------------


def train_rerun(case: Case) -> str:
    data, run = _dataset(case), case.work / "run"
    _train(case, data, run, "--steps", 40)
    p = _train(case, data, run, "--steps", 40, "--stop-at", 12)
    return f"exit {p.returncode}; {said(p)}; checkpoint at step {_ckpt_step(case, run)}, {_rows(run)} log rows"


def _resume_with(case: Case, change: dict) -> str:
    """Train 10 of 40 steps with ``tiny``, then --resume with ``change`` (section -> {key: value}) applied."""
    data, run = _dataset(case), case.work / "run"
    _train(case, data, run, "--steps", 40, "--stop-at", 10)
    tiny = case.py("from vnc_warp.training.config import named_config; import json; "
                   "print(json.dumps(named_config('tiny').to_dict()))")
    config = json.loads(tiny.stdout)
    config["optim"]["total_steps"] = 40
    for section, values in change.items():
        config[section].update(values)
    (case.work / "cfg.json").write_text(json.dumps(config))
    p = case.cli("train", "--config", case.work / "cfg.json", "--data", data, "--out", run, "--device", "cpu",
                 "--no-progress", "--resume", "--stop-at", 12)
    return f"exit {p.returncode}; {said(p)}; checkpoint at step {_ckpt_step(case, run)}"


def train_resume_lr(case: Case) -> str:
    return _resume_with(case, {"optim": {"lr": 0.002}})


def train_resume_batch(case: Case) -> str:
    return _resume_with(case, {"data": {"batch_size": 2}})


def train_resume_steps(case: Case) -> str:
    return _resume_with(case, {"optim": {"total_steps": 80}})


def train_stop_at_negative(case: Case) -> str:
    data, run = _dataset(case), case.work / "run"
    p = _train(case, data, run, "--stop-at", -5)
    printed = p.stdout.strip().splitlines()[-1][:90] if p.stdout.strip() else ""
    return (f"exit {p.returncode}; {said(p) if p.returncode else 'printed ' + printed}; "
            f"checkpoint file exists: {(run / 'checkpoints' / 'last.pt').exists()}")


def _signal(case: Case, sig: int) -> str:
    data, run = _dataset(case), case.work / "run"
    cmd = [sys.executable, "-m", "vnc_warp.cli", "train", "--config", "tiny", "--data", str(data), "--out", str(run),
           "--device", "cpu", "--no-progress", "--steps", "100000"]
    # as from a terminal: a shell's background job would start with SIGINT ignored
    proc = subprocess.Popen(cmd, cwd=case.root, env=dict(os.environ, OMP_NUM_THREADS="1"), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.time() + 120
    while time.time() < deadline and _rows(run) < 5 and proc.poll() is None:
        time.sleep(0.05)
    proc.send_signal(sig)
    try:
        out, err = proc.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
        err += "\nstill running 60 s after the signal: killed"
    p = subprocess.CompletedProcess(cmd, proc.returncode, case.clean(out), case.clean(err))
    return (f"exit {p.returncode}; {said(p)}; {_rows(run)} log rows; checkpoint at step {_ckpt_step(case, run)} "
            "(ckpt_every 50)")


def train_sigint(case: Case) -> str:
    return _signal(case, signal.SIGINT)


def train_sigterm(case: Case) -> str:
    return _signal(case, signal.SIGTERM)


def train_nan_sample(case: Case) -> str:
    data = _dataset(case)
    case.py(f"""
        import json, hashlib, numpy as np
        root = {str(data)!r}
        index = json.load(open(root + "/index.json"))
        st = index["shapes"][0]["stages"][1]
        z = dict(np.load(root + "/" + st["file"]))
        z["tsdf"][5] = np.nan
        np.savez(open(root + "/" + st["file"], "wb"), **z)
        st["sha256"] = hashlib.sha256(open(root + "/" + st["file"], "rb").read()).hexdigest()
        json.dump(index, open(root + "/index.json", "w"))
    """)
    run = case.work / "run"
    p = _train(case, data, run, "--steps", 20)
    log = run / "log.jsonl"
    losses = [json.loads(x)["loss"] for x in log.read_text().splitlines() if x.strip()] if log.is_file() else []
    nan = sum(1 for v in losses if not v == v)
    return f"exit {p.returncode}; {said(p)}; {len(losses)} log rows, {nan} with loss NaN"


def flow_batch_other_stages(case: Case) -> str:
    src = case.work / "in"
    src.mkdir()
    shutil.copy(case.meshes / "shape0.obj", src)
    case.cli("flow-batch", src, case.work / "out", "--stages", 1, "--device", "cpu", "--no-progress")
    p = case.cli("flow-batch", src, case.work / "out", "--stages", 2, "--device", "cpu", "--no-progress")
    return f"exit {p.returncode}; {_statuses(case.work / 'out')}; {_errors(case, case.work / 'out')}{said(p)}"


def _errors(case: Case, out: Path) -> str:
    p = out / "batch.json"
    entries = json.loads(p.read_text())["meshes"] if p.is_file() else []
    return "".join(f"{m['mesh']}: {_short(case.clean(m['error']), 110)}; " for m in entries if m.get("error"))


def flow_batch_bad_mesh(case: Case) -> str:
    src = case.work / "in"
    src.mkdir()
    for name in ("fin.obj", "shape1.obj"):
        shutil.copy(case.meshes / name, src)
    p = case.cli("flow-batch", src, case.work / "out", "--stages", 1, "--device", "cpu", "--no-progress")
    return f"exit {p.returncode}; {_statuses(case.work / 'out')}; {_errors(case, case.work / 'out')}{said(p)}"


def flow_batch_obj_and_ply(case: Case) -> str:
    src = case.work / "in"
    src.mkdir()
    for name in ("shape0.obj", "shape0.ply"):
        shutil.copy(case.meshes / name, src)
    p = case.cli("flow-batch", src, case.work / "out", "--stages", 1, "--device", "cpu", "--no-progress")
    folders = sorted(x.name for x in (case.work / "out").iterdir() if x.is_dir())
    return f"exit {p.returncode}; folders {folders}; {_statuses(case.work / 'out')}"


def flow_batch_accumulates(case: Case) -> str:
    for k, name in enumerate(("shape0.obj", "shape1.obj")):
        src = case.work / f"in{k}"
        src.mkdir()
        shutil.copy(case.meshes / name, src)
        case.cli("flow-batch", src, case.work / "out", "--stages", 1, "--device", "cpu", "--no-progress")
    return f"after two runs on two folders: {_statuses(case.work / 'out')}"


def flow_batch_torchrun_bad_mesh(case: Case) -> str:
    src = case.work / "in"
    src.mkdir()
    for name in ("shape0.obj", "shape1.obj", "shape2.obj", "fin.obj"):
        shutil.copy(case.meshes / name, src)
    p = case.run("-m", "torch.distributed.run", "--nproc_per_node=2", "--master_port=29591", "-m", "vnc_warp.cli",
                 "flow-batch", src, case.work / "out", "--stages", 1, "--device", "cpu", "--no-progress")
    done = sorted(x.name for x in (case.work / "out").iterdir() if (x / "manifest.json").is_file()) \
        if (case.work / "out").is_dir() else []
    return f"exit {p.returncode}; trajectories written: {done}; {_statuses(case.work / 'out')}"


def flow_stray_stage_files(case: Case) -> str:
    out = case.work / "traj"
    out.mkdir()
    shutil.copy(case.meshes / "shape2.obj", case.work / "x.obj")
    case.py(f"import vnc_warp as vw; vw.load_mesh({str(case.meshes / 'shape2.obj')!r}).save({str(out / 'stage_000.ply')!r})")
    before = (out / "stage_000.ply").read_bytes()
    p = case.cli("flow", case.meshes / "shape0.obj", "--out", out, "--stages", 1, "--device", "cpu", "--no-progress")
    kept = (out / "stage_000.ply").read_bytes() == before
    mixed = kept and (out / "manifest.json").is_file()
    return (f"exit {p.returncode}; {said(p)}; "
            + ("manifest now describes shape0.obj while stage_000.ply holds shape2" if mixed else
               "stray file left untouched, no manifest written" if kept else "stray file overwritten"))


def _load(case: Case, out: Path) -> subprocess.CompletedProcess:
    return case.py(f"""
        import warnings; warnings.simplefilter("ignore")
        from vnc_warp.flow import Trajectory
        try:
            t = Trajectory.load({str(out)!r})
            print("loaded", len(t.meshes), "stages")
        except Exception as exc:
            print(type(exc).__name__ + ": " + str(exc))
    """)


def flow_replaced_stage(case: Case) -> str:
    out = _trajectory(case)
    case.py(f"import vnc_warp as vw; vw.icosphere(2).save({str(out / 'stage_001.ply')!r})")
    load = _load(case, out).stdout.strip()
    p = case.cli("dataset", out, "--out", case.work / "data", "--device", "cpu", "--quiet")
    return f"load: {_short(load, 120)}; dataset: exit {p.returncode}, {said(p)}"


def flow_unlisted_stage(case: Case) -> str:
    out = _trajectory(case)
    shutil.copy(out / "stage_001.ply", out / "stage_007.ply")
    load = _load(case, out).stdout.strip()
    p = case.cli("flow", case.meshes / "shape0.obj", "--out", out, "--stages", 2, "--device", "cpu", "--no-progress")
    return f"load: {_short(load, 110)}; flow (resume): exit {p.returncode}, {said(p)}"


def manifest_json_list(case: Case) -> str:
    out = _trajectory(case)
    (out / "manifest.json").write_text("[1, 2]")
    p = case.cli("flow", case.meshes / "shape0.obj", "--out", out, "--stages", 2, "--device", "cpu", "--no-progress")
    return f"flow (resume): exit {p.returncode}, {said(p)}"


def manifest_truncated(case: Case) -> str:
    out = _trajectory(case)
    text = (out / "manifest.json").read_text()
    (out / "manifest.json").write_text(text[: len(text) // 2])
    load = _load(case, out).stdout.strip()
    return f"load: {_short(load, 160)}"


def _out_under_file(case: Case, command: list) -> str:
    (case.work / "file").write_text("x")
    p = case.cli(*[case.work / "file" / "sub" if a == "OUT" else a for a in command])
    return f"exit {p.returncode}; {said(p)}"


def _out_readonly(case: Case, command: list) -> str:
    ro = case.work / "ro"
    if not _readonly(ro):
        return "not run (no way to make a read-only folder here)"
    try:
        p = case.cli(*[ro / "sub" if a == "OUT" else a for a in command])
        return f"exit {p.returncode}; {said(p)}"
    finally:
        _writable(ro)


def _commands(case: Case) -> dict:
    traj = _trajectory(case, stages=1)
    (case.work / "nodata").mkdir()
    return {
        "curvature": ["curvature", case.meshes / "shape0.obj", "--out", "OUT", "--tau", "0.2", "--device", "cpu"],
        "flow": ["flow", case.meshes / "shape0.obj", "--out", "OUT", "--stages", "2", "--device", "cpu",
                 "--no-progress"],
        "dataset": ["dataset", traj, "--out", "OUT", "--device", "cpu", "--quiet"],
        "train": ["train", "--config", "tiny", "--data", _dataset(case), "--out", "OUT", "--device", "cpu",
                  "--no-progress", "--steps", "2"],
    }


def out_under_file(case: Case) -> str:
    return " / ".join(f"{name}: {_out_under_file(case, cmd)}" for name, cmd in _commands(case).items())


def out_readonly(case: Case) -> str:
    return " / ".join(f"{name}: {_out_readonly(case, cmd)}" for name, cmd in _commands(case).items())


def _api(case: Case, body: str) -> str:
    p = case.py(f"""
        import numpy as np, warp as wp, vnc_warp as vw
        mesh = vw.icosphere(2)
        try:
            {body}
        except Exception as exc:
            print("raises " + type(exc).__name__ + ": " + str(exc).splitlines()[0])
    """)
    return _short(p.stdout.strip() or said(p))


def api_tau_none(case: Case) -> str:
    return _api(case, "vw.vnc_soft(mesh, None, device='cpu'); print('returned')")


def api_points_empty(case: Case) -> str:
    return _api(case, "r = vw.integrated_mean_curvature(mesh, 0.3, points=np.zeros((0, 3)), device='cpu'); "
                      "print('returns shape', r.shape)")


def api_positions_nan(case: Case) -> str:
    return _api(case, "v = mesh.vertices.copy(); v[3] = np.nan; "
                      "H, n = vw.vnc_soft(mesh, 0.3, positions=wp.array(v, dtype=wp.vec3, device='cpu')); "
                      "print('returns', int(np.isnan(H.numpy()).sum()), 'NaN,', int((H.numpy() == 0).sum()), 'zeros')")


def generate_bad_format(case: Case) -> str:
    run = case.work / "run"
    _train(case, _dataset(case), run, "--steps", 40)  # enough for the decoder to find a surface to write
    p = case.cli("generate", run, "--input", case.meshes / "shape0.obj", "--out", case.work / "g", "--format",
                 "xyz123", "--resolution", 16, "--device", "cpu")
    shown = said(p)
    if shown == "no message" and p.stdout.strip():
        shown = "printed " + _short(" / ".join(p.stdout.strip().splitlines()[:2]), 120)
    return f"exit {p.returncode}; {shown}"


def _generate_from(case: Case, checkpoint: Path) -> str:
    p = case.cli("generate", checkpoint, "--input", case.meshes / "shape0.obj", "--out", case.work / "g",
                 "--device", "cpu")
    advice = "weights_only` set to `False" in p.stderr or "weights_only=False" in p.stderr
    return f"exit {p.returncode}; {said(p)}; advises weights_only=False: {advice}"


def checkpoint_random_bytes(case: Case) -> str:
    # seeded: which error torch raises depends on the first bytes
    case.py(f"import numpy as np; open({str(case.work / 'random.pt')!r}, 'wb').write("
            "np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8).tobytes())")
    return _generate_from(case, case.work / "random.pt")


def checkpoint_malicious(case: Case) -> str:
    case.py(f"""
        import os, torch
        class Evil:
            def __reduce__(self):
                return (os.system, ("echo owned",))
        torch.save({{"format": "vnc-warp-checkpoint", "payload": Evil()}}, {str(case.work / 'evil.pt')!r})
    """)
    return _generate_from(case, case.work / "evil.pt")


def non_manifold(case: Case) -> str:
    p = case.cli("curvature", case.meshes / "fin.obj", "--out", case.work / "c", "--tau", 0.3, "--device", "cpu")
    return f"exit {p.returncode}; {said(p)}"


CASES = {
    "train: re-run of a 40-step run with --stop-at 12, no --resume": train_rerun,
    "train --resume with another lr": train_resume_lr,
    "train --resume with another batch size": train_resume_batch,
    "train --resume with another schedule length": train_resume_steps,
    "train --stop-at -5": train_stop_at_negative,
    "train: SIGINT after 5 steps": train_sigint,
    "train: SIGTERM after 5 steps": train_sigterm,
    "train on a sample holding NaN (checksum matching)": train_nan_sample,
    "flow-batch re-run with other --stages": flow_batch_other_stages,
    "flow-batch over a non-manifold mesh and a good one": flow_batch_bad_mesh,
    "flow-batch over shape0.obj and shape0.ply": flow_batch_obj_and_ply,
    "flow-batch twice, on two input folders, one OUT": flow_batch_accumulates,
    "flow-batch under torchrun (2 ranks) with a bad mesh": flow_batch_torchrun_bad_mesh,
    "flow into a folder holding a stray stage_000.ply, no manifest": flow_stray_stage_files,
    "a finished trajectory whose stage_001.ply was replaced": flow_replaced_stage,
    "a trajectory folder with an unlisted stage_007.ply": flow_unlisted_stage,
    "manifest.json that is a JSON list": manifest_json_list,
    "truncated manifest.json": manifest_truncated,
    "--out under a file": out_under_file,
    "--out in a read-only folder": out_readonly,
    "vnc_soft(mesh, tau=None)": api_tau_none,
    "integrated_mean_curvature(points=np.zeros((0, 3)))": api_points_empty,
    "vnc_soft(positions=...) with a NaN vertex": api_positions_nan,
    "generate --format xyz123": generate_bad_format,
    "a checkpoint of random bytes (generate)": checkpoint_random_bytes,
    "a checkpoint holding a pickled os.system call (generate)": checkpoint_malicious,
    "curvature of a non-manifold mesh (fin.obj)": non_manifold,
}


def run_all(root: Path, only: list[str] | None) -> dict:
    results = {}
    with tempfile.TemporaryDirectory(prefix="vnc-bad-inputs-") as tmp:
        meshes = Path(tmp) / "meshes"
        meshes.mkdir()
        subprocess.run([sys.executable, "-c", MAKE_MESHES, str(meshes)], cwd=root, check=True, capture_output=True)
        for k, (name, fn) in enumerate(CASES.items()):
            if only and not any(o in name for o in only):
                continue
            work = Path(tmp) / f"case{k}"
            work.mkdir()
            t0 = time.perf_counter()
            try:
                outcome = fn(Case(root, work, meshes))
            except Exception as exc:  # a case that cannot be run is reported as such
                outcome = f"case did not run: {type(exc).__name__}: {exc}"
            results[name] = {"outcome": outcome, "seconds": round(time.perf_counter() - t0, 1)}
            print(f"{name}: {outcome}", flush=True)
    return results


def markdown(after: dict, before: dict | None = None) -> str:
    def cell(text: str) -> str:
        return text.replace("|", "\\|")

    if before is None:
        lines = ["| case | what the user gets |", "|---|---|"]
        lines += [f"| {cell(k)} | {cell(v['outcome'])} |" for k, v in after["cases"].items()]
    else:
        lines = [f"| case | before ({before['label']}) | now ({after['label']}) |", "|---|---|---|"]
        lines += [f"| {cell(k)} | {cell(before['cases'].get(k, {}).get('outcome', '-'))} | {cell(v['outcome'])} |"
                  for k, v in after["cases"].items()]
    return "\n".join(lines)


def main(argv=None) -> dict | None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--root", default=str(HERE), help="checkout whose vnc_warp is run (default: this one)")
    p.add_argument("--label", default=None, help="name of this checkout in the table (default: its git commit)")
    p.add_argument("--out", default=None, help="folder for bad_inputs.json")
    p.add_argument("--only", nargs="*", default=None, help="run the cases whose name contains one of these")
    p.add_argument("--markdown", default=None, metavar="AFTER.json", help="render saved results instead of running")
    p.add_argument("--before", default=None, metavar="BEFORE.json", help="with --markdown: a column for these")
    args = p.parse_args(argv)
    if args.markdown:
        after = json.loads(Path(args.markdown).read_text())
        before = json.loads(Path(args.before).read_text()) if args.before else None
        print(markdown(after, before))
        return None
    root = Path(args.root).resolve()
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True)
    label = args.label or commit.stdout.strip() or root.name
    doc = {"label": label, "root": str(root), "date": time.strftime("%Y-%m-%d"),
           "command": "python -m bench.bad_inputs " + " ".join(argv if argv is not None else sys.argv[1:]),
           "cases": run_all(root, args.only)}
    if args.out:
        Path(args.out).mkdir(parents=True, exist_ok=True)
        path = Path(args.out) / "bad_inputs.json"
        if args.only and path.is_file():  # a partial run updates its cases in an earlier full one
            earlier = json.loads(path.read_text())
            earlier["cases"].update(doc["cases"])
            earlier.setdefault("reruns", []).append({k: doc[k] for k in ("label", "date", "command")})
            doc = earlier
        path.write_text(json.dumps(doc, indent=1) + "\n")
    print()
    print(markdown(doc))
    return doc


if __name__ == "__main__":
    main()
