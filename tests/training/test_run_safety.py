"""Training runs that protect the user's work (issue 20): re-runs resume instead of overwriting, refused or stated
setting changes on resume, checkpoints on SIGINT/SIGTERM with an exact resume, NaN samples and non-finite losses.

Each test reproduces a case of issue 20 that lost work or trained on silently at dd885f9 (its docstring says what
happened then).
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.multiprocessing as mp

from vnc_warp.cli import main
from vnc_warp.flow import Trajectory
from vnc_warp.shapes import icosphere
from vnc_warp.training import data as data_mod
from vnc_warp.training.checkpoint import load_checkpoint
from vnc_warp.training.config import named_config
from vnc_warp.training.data import DatasetError, TrajectoryDataset, build_dataset
from vnc_warp.training.synthetic import EllipsoidTrajectories
from vnc_warp.training.train import lr_factor, train

pytestmark = pytest.mark.usefixtures("one_torch_thread")
ROOT = Path(__file__).resolve().parents[2]
SAMPLES = ["--num-surface", "300", "--num-uniform", "300", "--num-near", "300"]


def _rows(run: Path) -> list[dict]:
    return [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines() if line.strip()]


def _tiny(**optim):
    cfg = named_config("tiny")
    cfg.optim = dataclasses.replace(cfg.optim, **optim)
    return cfg


@pytest.fixture(scope="module")
def dataset_dir(tmp_path_factory):
    """A dataset folder of two 2-stage trajectories (spheres shrinking), 4 items: one tiny batch per epoch."""
    base = tmp_path_factory.mktemp("runs")
    trajs = []
    for k, radius in enumerate((0.5, 2.0)):
        s = icosphere(2, radius=radius)
        meshes = [s, s.with_vertices(s.vertices * 0.8)]
        records = [{"index": i, "t": t, "file": f"stage_{i:03d}.ply"} for i, t in enumerate((1.0, 0.5))]
        Trajectory(meshes, np.array([1.0, 0.5]), records, {"source": f"s{k}.obj", "params": {"stages": 1}}).save(
            base / f"s{k}")
        trajs.append(base / f"s{k}")
    build_dataset(trajs, base / "data", device="cpu", progress=False, num_surface=300, num_uniform=300,
                  num_near=300)
    return base / "data"


def _train_cli(data, run, *extra):
    return main(["train", "--config", "tiny", "--data", str(data), "--out", str(run), "--device", "cpu",
                 "--no-progress", *extra])


# --- re-runs: resume, never overwrite (item 1) ---------------------------------------------------------------


def test_rerunning_the_same_command_resumes_instead_of_overwriting(dataset_dir, tmp_path, capsys):
    """`vnc-warp train --out RUN` run again without --resume truncated log.jsonl and overwrote
    checkpoints/last.pt (a 40-step run re-run with --stop-at 12 was left at step 12); now the same command
    resumes, and a run already past --stop-at is left as it is."""
    run = tmp_path / "run"
    assert _train_cli(dataset_dir, run, "--steps", "8") == 0
    capsys.readouterr()
    assert _train_cli(dataset_dir, run, "--steps", "8", "--stop-at", "3") == 0
    # the command line states it as a log line (warnings become log lines there)
    err = capsys.readouterr().err
    assert "warning: " in err and "at step 8, at or past the requested end 3: nothing to train" in err, err
    assert load_checkpoint(run / "checkpoints" / "last.pt")["step"] == 8
    assert [r["step"] for r in _rows(run)] == list(range(1, 9))
    assert _train_cli(dataset_dir, run, "--steps", "8", "--stop-at", "4", "--restart", "--resume") == 2
    assert "exclude each other" in capsys.readouterr().err
    assert load_checkpoint(run / "checkpoints" / "last.pt")["step"] == 8


def test_restart_is_explicit(dataset_dir, tmp_path):
    """Starting over takes --restart: the old log and checkpoint are discarded and the run starts at step 1."""
    run = tmp_path / "run"
    assert _train_cli(dataset_dir, run, "--steps", "8", "--stop-at", "5") == 0
    assert _train_cli(dataset_dir, run, "--steps", "8", "--stop-at", "2", "--restart") == 0
    assert [r["step"] for r in _rows(run)] == [1, 2]
    assert load_checkpoint(run / "checkpoints" / "last.pt")["step"] == 2


def test_stop_at_must_be_a_positive_step(dataset_dir, tmp_path, capsys):
    """`--stop-at -5` trained nothing and printed the path of a checkpoint that did not exist; now it is refused
    in one line with exit code 2."""
    for bad in ("-5", "0"):
        assert _train_cli(dataset_dir, tmp_path / "run", "--stop-at", bad) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and f"stop_at must be a step >= 1, got {bad}" in err[0], err
    assert not (tmp_path / "run" / "checkpoints" / "last.pt").exists()


def test_changed_lr_or_batch_on_resume_is_refused(tmp_path):
    """A changed learning rate or batch size on --resume was silently mixed into the stored run (the stored lr
    kept, the data position counted in other batches); now resuming with them is refused, listing each change,
    and the stored run is untouched."""
    ds = EllipsoidTrajectories(num_shapes=2, num_stages=4, seed=2)
    cfg = _tiny(warmup_steps=2, total_steps=10)
    train(cfg, data=ds, out_dir=tmp_path, device="cpu", stop_at=3, progress=False)
    for section, change, text in (("optim", {"lr": 2e-3}, "optim.lr: 0.001 -> 0.002"),
                                  ("data", {"batch_size": 2}, "data.batch_size: 4 -> 2")):
        other = _tiny(warmup_steps=2, total_steps=10)
        setattr(other, section, dataclasses.replace(getattr(other, section), **change))
        with pytest.raises(ValueError, match=f"trained with other settings: {text}"):
            train(other, data=ds, out_dir=tmp_path, device="cpu", resume=True, stop_at=6, progress=False)
    assert load_checkpoint(tmp_path / "checkpoints" / "last.pt")["step"] == 3
    assert [r["step"] for r in _rows(tmp_path)] == [1, 2, 3]


def test_changed_schedule_on_resume_is_stated_and_followed(tmp_path):
    """A longer schedule on resume (--steps) is stated in a warning and the learning rate follows it from the
    resume step on (it used to keep the stored schedule's value for the first step, without a word)."""
    ds = EllipsoidTrajectories(num_shapes=2, num_stages=4, seed=2)
    train(_tiny(warmup_steps=2, total_steps=10), data=ds, out_dir=tmp_path, device="cpu", stop_at=5, progress=False)
    with pytest.warns(UserWarning, match=r"schedule settings changed \(optim.total_steps: 10 -> 40\)"):
        train(_tiny(warmup_steps=2, total_steps=40), data=ds, out_dir=tmp_path, device="cpu", resume=True, stop_at=7,
              progress=False)
    rows = _rows(tmp_path)
    assert [r["step"] for r in rows] == list(range(1, 8))
    for r in rows[5:]:
        assert r["lr"] == pytest.approx(1e-3 * lr_factor(r["step"] - 1, warmup_steps=2, total_steps=40,
                                                         min_lr_ratio=0.1), rel=1e-6), r


# --- signals (item 6) ----------------------------------------------------------------------------------------


class _SignalAt(torch.utils.data.Dataset):
    """The items of ``base``; the ``at``-th read (0-based) sends ``sig`` to this process, as a Ctrl-C would."""

    def __init__(self, base, at: int | None, sig=signal.SIGINT):
        self.base, self.at, self.sig, self.reads = base, at, sig, 0

    def __len__(self):
        return len(self.base)

    def item_ids(self):
        return self.base.item_ids()

    def __getitem__(self, i):
        if self.reads == self.at:
            os.kill(os.getpid(), self.sig)
        self.reads += 1
        return self.base[i]


def test_sigint_saves_a_checkpoint_and_resume_is_exact(tmp_path):
    """SIGINT during training saved nothing (up to ckpt_every steps lost); now the run ends after the step under
    way with a checkpoint, and resuming from it gives the losses, log rows and weights of an uninterrupted run,
    even inside a log window."""
    ds = EllipsoidTrajectories(num_shapes=2, num_stages=4, seed=5)  # 8 items, 2 batches per epoch
    cfg = _tiny(warmup_steps=2, total_steps=9)
    cfg.log_every, cfg.ckpt_every = 3, 1000
    cfg.data = dataclasses.replace(cfg.data, encoder_input="item")  # one read per item: read 13 is in step 4
    train(cfg, data=_SignalAt(ds, None), out_dir=tmp_path / "a", device="cpu", progress=False)
    with pytest.raises(KeyboardInterrupt, match="SIGINT at step 4"):  # TrainingInterrupted
        train(cfg, data=_SignalAt(ds, 13), out_dir=tmp_path / "b", device="cpu", progress=False)
    ck = load_checkpoint(tmp_path / "b" / "checkpoints" / "last.pt")
    assert ck["step"] == 4 and [r["step"] for r in _rows(tmp_path / "b")] == [3]
    train(cfg, data=_SignalAt(ds, None), out_dir=tmp_path / "b", device="cpu", progress=False)
    a, b = _rows(tmp_path / "a"), _rows(tmp_path / "b")
    assert [r["step"] for r in b] == [3, 6, 9]
    for ra, rb in zip(a, b):
        for key in ("loss", "tsdf", "kl", "eik", "grad_norm", "lr", "beta_kl", "epoch"):
            assert ra[key] == rb[key], (ra["step"], key)
    wa = load_checkpoint(tmp_path / "a" / "checkpoints" / "last.pt")["model"]
    wb = load_checkpoint(tmp_path / "b" / "checkpoints" / "last.pt")["model"]
    assert all(torch.equal(wa[k], wb[k]) for k in wa)
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # handlers restored


def test_a_deadline_stops_with_a_checkpoint_and_resume_is_exact(tmp_path):
    """A deadline (a run split over calls of bounded length, `vnc-warp experiment --max-minutes`) ends the run after
    the step under way with a checkpoint and returns ``stopped="deadline"`` (no exception); calls until the end give
    the losses, log rows and weights of an uninterrupted run, and a finished run is not trained again."""
    ds = EllipsoidTrajectories(num_shapes=2, num_stages=4, seed=5)
    cfg = _tiny(warmup_steps=2, total_steps=9)
    cfg.log_every, cfg.ckpt_every = 3, 1000
    whole = train(cfg, data=ds, out_dir=tmp_path / "a", device="cpu", progress=False)
    assert whole["stopped"] is None and whole["step"] == 9
    past = time.monotonic() - 1.0  # each call takes exactly one step: the first step ends past the deadline
    calls = [train(cfg, data=ds, out_dir=tmp_path / "b", device="cpu", progress=False, deadline=past)
             for _ in range(4)]
    assert [(c["start_step"], c["step"], c["stopped"]) for c in calls] == [(k, k + 1, "deadline") for k in range(4)]
    assert load_checkpoint(tmp_path / "b" / "checkpoints" / "last.pt")["step"] == 4
    rest = train(cfg, data=ds, out_dir=tmp_path / "b", device="cpu", progress=False,
                 deadline=time.monotonic() + 3600.0)
    assert (rest["start_step"], rest["step"], rest["stopped"]) == (4, 9, None)
    a, b = _rows(tmp_path / "a"), _rows(tmp_path / "b")
    assert [r["step"] for r in b] == [3, 6, 9]
    for ra, rb in zip(a, b):
        for key in ("loss", "tsdf", "eval_tsdf", "kl", "eik", "grad_norm", "lr", "beta_kl", "epoch"):
            assert ra[key] == rb[key], (ra["step"], key)
    wa = load_checkpoint(tmp_path / "a" / "checkpoints" / "last.pt")["model"]
    wb = load_checkpoint(tmp_path / "b" / "checkpoints" / "last.pt")["model"]
    assert all(torch.equal(wa[k], wb[k]) for k in wa)
    stamp = (tmp_path / "b" / "checkpoints" / "last.pt").stat().st_mtime_ns
    with pytest.warns(UserWarning, match="nothing to train"):
        again = train(cfg, data=ds, out_dir=tmp_path / "b", device="cpu", progress=False, deadline=past)
    assert (again["step"], again["stopped"]) == (9, None)
    assert (tmp_path / "b" / "checkpoints" / "last.pt").stat().st_mtime_ns == stamp


def test_sigterm_from_outside_saves_a_checkpoint(dataset_dir, tmp_path):
    """SIGTERM (a scheduler's kill) ended `vnc-warp train` without a checkpoint; now it exits 130 with one line
    naming the checkpoint it wrote, and the same command resumes from that step."""
    run = tmp_path / "run"
    cmd = [sys.executable, "-m", "vnc_warp.cli", "train", "--config", "tiny", "--data", str(dataset_dir), "--out",
           str(run), "--device", "cpu", "--steps", "100000", "--no-progress"]
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONWARNINGS="ignore")
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.time() + 120
    while time.time() < deadline and proc.poll() is None:
        if (run / "log.jsonl").is_file() and len(_rows(run)) >= 3:
            break
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    step = load_checkpoint(run / "checkpoints" / "last.pt")["step"]
    assert step >= 3 and f"stopped by SIGTERM at step {step}" in err.strip().splitlines()[-1]
    assert _train_cli(dataset_dir, run, "--steps", "100000", "--stop-at", str(step + 2)) == 0
    assert [r["step"] for r in _rows(run)] == list(range(1, step + 3))


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _ddp_signal_worker(rank: int, world: int, port: int, out: str) -> None:
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank), WORLD_SIZE=str(world),
                      LOCAL_RANK=str(rank))
    torch.set_num_threads(1)
    ds = _SignalAt(EllipsoidTrajectories(num_shapes=2, num_stages=4, seed=4), 2 if rank == 1 else None)
    cfg = _tiny(total_steps=12)
    cfg.data = dataclasses.replace(cfg.data, batch_size=2)
    cfg.log_every, cfg.ckpt_every = 2, 1000
    try:
        summary = {"finished": train(cfg, data=ds, out_dir=out, device="cpu", progress=False)["step"]}
    except KeyboardInterrupt as exc:  # TrainingInterrupted
        summary = {"interrupted": str(exc)}
    Path(out, f"rank{rank}.json").write_text(json.dumps(summary))


def test_a_signal_to_one_ddp_rank_stops_every_rank_with_a_checkpoint(tmp_path):
    """Under DDP (2 gloo processes) a signal that reaches one rank only stops both at the same step (the next log
    step) with one checkpoint holding both ranks' RNG states; at dd885f9 that rank died and the other waited."""
    ctx = mp.start_processes(_ddp_signal_worker, args=(2, _free_port(), str(tmp_path)), nprocs=2, join=False,
                             start_method="spawn")
    deadline = time.time() + 120
    while not ctx.join(timeout=5):
        if time.time() > deadline:
            for p in ctx.processes:
                p.kill()
            pytest.fail("the ranks did not stop together")
    s0, s1 = (json.loads((tmp_path / f"rank{r}.json").read_text()) for r in (0, 1))
    assert "SIGINT at step 2" in s1["interrupted"] and "another process at step 2" in s0["interrupted"]
    ck = load_checkpoint(tmp_path / "checkpoints" / "last.pt")
    assert ck["step"] == 2 and len(ck["rng"]) == 2 and ck["world_size"] == 2


# --- non-finite samples and losses (item 5) ------------------------------------------------------------------


def _rewrite_sample(root: Path, rel: str, **arrays) -> None:
    """Replace arrays of a sample file and record its new checksum in index.json (a file that passes the check)."""
    path = root / rel
    with np.load(path) as z:
        content = {k: z[k] for k in z.files}
    content.update(arrays)
    with open(path, "wb") as fh:
        np.savez(fh, **content)
    index = json.loads((root / "index.json").read_text())
    for shape in index["shapes"]:
        for st in shape["stages"]:
            if st["file"] == rel:
                st["sha256"] = data_mod._sha256(path)
    (root / "index.json").write_text(json.dumps(index))


def test_a_nan_sample_is_refused_when_read(dataset_dir, tmp_path, capsys):
    """A sample holding NaN with a matching checksum trained to the end with loss NaN; now reading it raises,
    naming the file, and `vnc-warp train` stops with that line and exit code 2."""
    root = tmp_path / "data"
    shutil.copytree(dataset_dir, root)
    with np.load(root / "s1" / "stage_001.npz") as z:
        tsdf = z["tsdf"].copy()
    tsdf[7] = np.nan
    _rewrite_sample(root, "s1/stage_001.npz", tsdf=tsdf)
    ds = TrajectoryDataset(root, split="all", num_surface=64, num_queries=64)
    with pytest.raises(DatasetError, match=r"s1/stage_001\.npz: 1 non-finite value\(s\) .* in 'tsdf'"):
        ds[3]
    assert _train_cli(root, tmp_path / "run", "--steps", "3") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert "s1/stage_001.npz: 1 non-finite value(s)" in err[-1]


def test_building_refuses_non_finite_samples(dataset_dir, tmp_path, monkeypatch):
    """Samples are checked for finiteness before they are written: NaN signed distances were stored silently."""
    real = data_mod.signed_distance

    def nan_distance(mesh, points, **kw):
        d = real(mesh, points, **kw)
        d[0] = float("nan")
        return d

    monkeypatch.setattr(data_mod, "signed_distance", nan_distance)
    trajs = [dataset_dir.parent / "s0"]
    with pytest.raises(DatasetError, match=r"s0/stage_000\.ply \(sampled for s0/stage_000\.npz\): .* in 'tsdf'"):
        build_dataset(trajs, tmp_path / "d", device="cpu", progress=False, num_surface=100, num_uniform=100,
                      num_near=100)
    assert not list((tmp_path / "d").rglob("*.npz"))


def test_a_non_finite_loss_stops_the_run_with_step_and_files(dataset_dir, tmp_path):
    """A loss that turns non-finite (here: finite but huge labels, 3e38, that overflow the L1 sum) trained on to the
    end; now the run stops at the next check with the step and the sample files of its batch, without saving over
    the last checkpoint."""
    root = tmp_path / "data"
    shutil.copytree(dataset_dir, root)
    with np.load(root / "s0" / "stage_001.npz") as z:
        tsdf = np.full_like(z["tsdf"], 3e38)
    _rewrite_sample(root, "s0/stage_001.npz", tsdf=tsdf)
    cfg = _tiny(total_steps=6)
    cfg.data = dataclasses.replace(cfg.data, batch_size=2)
    cfg.ckpt_every = 1
    with pytest.raises(ValueError, match=r"non-finite loss inf at step (\d).*s0/stage_001\.npz") as info:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            train(cfg, data=root, out_dir=tmp_path / "run", device="cpu", progress=False)
    bad_step = int(str(info.value).split(" at step ")[1].split(",")[0])
    ckpt = tmp_path / "run" / "checkpoints" / "last.pt"
    if bad_step > 1:
        state = load_checkpoint(ckpt)
        assert state["step"] == bad_step - 1
        assert all(torch.isfinite(v).all() for v in state["model"].values() if v.is_floating_point())
    else:
        assert not ckpt.exists()
