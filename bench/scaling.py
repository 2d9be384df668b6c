"""Scale-out over K processes: ``flow-batch`` and DDP training of C-VAE-I under torchrun, measured per K.

    python -m bench.scaling --device cpu --ranks 1,2 --out OUT        # gloo, one CPU process per rank
    python -m bench.scaling --device cuda --ranks 1,2,4 --out OUT     # one GPU per rank (cuda:LOCAL_RANK), NCCL

For every K it runs, as a user would,
``torchrun --nproc_per_node=K -m vnc_warp.cli flow-batch IN OUT_K ...`` over a folder it assembles (real meshes
from ``--meshes`` when that folder exists, the genus-0 ``random_shape`` family and, when ``vnc_warp.shapes`` has
one, the humanoid family), builds a dataset from the K = 1 trajectories (``vnc-warp dataset``) and runs
``torchrun --nproc_per_node=K -m vnc_warp.cli train --config CFG_K ...`` for a fixed number of steps, then reports:

* wall time of each torchrun command (process start-up included), meshes per minute and training samples per
  second (end to end, and steady: the harmonic mean of the logged per-step rates after the first tenth of the
  steps), and the scaling efficiency ``rate_K / (K rate_1)``;
* whether the results match the K = 1 run: every stage file of every trajectory bit for bit (the SHA-256 in each
  ``manifest.json``), and the training loss curve within a stated tolerance (below);
* that the work was sharded as documented: each mesh on rank ``sorted index mod K``, each rank on its own device
  (``cuda:LOCAL_RANK``; recorded per mesh in ``batch.json``).

The global batch is the same for every K: each rank takes ``--global-batch / K`` items per step
(``data.batch_size``), so one optimiser step sees the same items for every K (DistributedSampler deals rank r the
items ``r, r + K, ...`` of the one seeded permutation, and an item's point subsets depend on its index and epoch
only). The loss curves still cannot match step by step: each rank draws its own random numbers (the first
farthest-point sample, the posterior noise, the eikonal subset) from a generator seeded by ``seed + rank``, so K = 2
draws other noise than K = 1 for the same items, and after a few steps the runs differ as any two runs with other
draws do. What is checked, with the loss logged at every step:

* the first step's loss, where every K holds the same initial weights and the same global batch and the draws do
  not enter (at initialisation the decoded SDF does not depend on the latent, the eikonal term is 1 and beta_kl is
  0: measured on the tiny config with three seeds of the draws), within ``--first-step-rtol`` (1e-5 on the CPU,
  float32, where K = 2 gave 0 to 1.2e-7; 1e-2 on CUDA for bf16, not yet measured);
* the mean loss over the last half of the steps, within ``--loss-rtol`` (5 %). On the CPU preset (16 trajectories,
  global batch 8, 40 steps) K = 2 and K = 1 agreed to 0.2 % for three steps, then differed by 4.3 % per step on
  average (26 % at most) and by 1.7 % in the last half's mean, while K = 1 with seed + 1, an equally valid run,
  differed from K = 1 by 5.8 % (24 %) and 0.4 %. Every run trains K = 1 with ``seed + 1`` too and reports that
  yardstick (``--no-seed-spread`` skips it).

Bit-identical trajectories across K need each mesh's flow to be deterministic on its device: ``--repeat N`` flows
the first N meshes once more with K = 1 and reports whether they came out bit for bit again (on CUDA a mismatch
between K values that a repeat also shows is the device's run-to-run nondeterminism, not the sharding).

Every torchrun gets the same ``OMP_NUM_THREADS`` (``--threads``; default 1 on the CPU device, the host's cores over
the largest K on CUDA), so that K = 1 is not given more threads than a rank of K = 4, and on CUDA NVLink multicast
is left off (``NCCL_NVLS_ENABLE=0``, ``TORCH_SYMM_MEM_DISABLE_MULTICAST=1``, ``NVSHMEM_DISABLE_NVLS=1``). Before
the timed runs a small untimed flow-batch compiles Warp's kernels (the compile cache is shared by all K). The report
is rewritten after every run, and ``--max-minutes`` starts no run after its budget, so a run cut short keeps what
finished.

Writes ``OUT/scaling.json`` and ``OUT/scaling.md``; the inputs, trajectories, dataset, training runs and every
command's output go to ``OUT/work/`` (``--keep-work`` keeps them, otherwise the bulky folders are removed).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_MESHES = ROOT.parent / "shared" / "data" / "meshes"
SCHEMA = "vnc-warp-scaling/1"
NO_MULTICAST = {"NCCL_NVLS_ENABLE": "0", "TORCH_SYMM_MEM_DISABLE_MULTICAST": "1", "NVSHMEM_DISABLE_NVLS": "1"}

# Real meshes of each preset, smallest first (``all``: every mesh file in --meshes).
CPU_REAL = ("brucewick.obj", "torus.obj", "goathead.obj", "spot_lowres.obj", "wingnut.obj", "bunny.obj",
            "penguin.obj", "fandisk.obj")
PRESETS = {
    # 2 shared CPU cores: 16 small meshes, 2 stages, the tiny C-VAE-I
    "cpu": dict(real=CPU_REAL, procedural=8, humanoids=0, subdivisions=3, faces=1500, stages=2, max_iters=80,
                train_config="tiny", steps=40, global_batch=8, log_every=1, workers=0,
                samples=(2048, 2048, 2048), repeat=4),
    # one 2- or 4-GPU host, about 7 minutes for K = 1, 2, 4: 40 meshes at 4000 faces, 8 stages; C-VAE-I of the
    # experiment's GPU preset (384 wide, 512 x 32 latents, bf16), global batch 32
    "gpu": dict(real="all", procedural=12, humanoids=4, subdivisions=4, faces=4000, stages=8, max_iters=300,
                train_config="experiment-gpu", steps=100, global_batch=32, log_every=1, workers=4,
                samples=(8192, 8192, 8192), repeat=4),
}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _torchrun(k: int, args: list[str], port: int) -> list[str]:
    return [sys.executable, "-m", "torch.distributed.run", f"--nproc_per_node={k}", f"--master_port={port}",
            "-m", "vnc_warp.cli", *args]


def _shown(cmd: list[str]) -> str:
    """A command as a user types it (``torchrun`` for ``python -m torch.distributed.run``)."""
    parts = list(cmd)
    if parts[:3] == [sys.executable, "-m", "torch.distributed.run"]:
        parts = ["torchrun"] + [p for p in parts[3:] if not p.startswith("--master_port")]
    elif parts[:1] == [sys.executable]:
        parts = ["python"] + parts[1:]
    return " ".join(parts)


def _run(cmd: list[str], env: dict, log: Path, *, timeout: float | None = None) -> dict:
    """Run ``cmd`` from the repository root, its output to ``log``: wall seconds, exit code, load averages."""
    log.parent.mkdir(parents=True, exist_ok=True)
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    with log.open("w") as fh:
        fh.write("$ " + _shown(cmd) + "\n")
        fh.flush()
        proc = subprocess.run(cmd, env=env, cwd=ROOT, stdout=fh, stderr=subprocess.STDOUT, timeout=timeout)
    wall = time.perf_counter() - t0
    return {"command": _shown(cmd), "rc": proc.returncode, "wall_s": round(wall, 3), "load_before": round(load0, 2),
            "load_after": round(os.getloadavg()[0], 2), "log": str(log)}


def _tail(path: str, n: int = 15) -> str:
    try:
        return "\n".join(Path(path).read_text(errors="replace").splitlines()[-n:])
    except OSError:
        return ""


# --- inputs ---------------------------------------------------------------------------------------------------


def assemble_inputs(folder: Path, *, meshes_dir: Path | None, real, procedural: int, humanoids: int,
                    subdivisions: int, seed: int = 0) -> list[dict]:
    """Fill ``folder`` with the benchmark's meshes: real ones copied from ``meshes_dir`` (when it exists),
    ``procedural`` genus-0 shapes (``vnc_warp.shapes.shape_family``) and ``humanoids`` bodies
    (``humanoid_family``, when the package has it).

    Args:
        folder: the input folder (created; must not hold mesh files yet).
        meshes_dir: folder of real meshes, or None.
        real: file names to copy, or ``"all"`` (every .obj/.ply/.off/.stl there).
        procedural: number of random genus-0 shapes.
        humanoids: number of random humanoids (none when ``vnc_warp.shapes`` has no ``humanoid_family``).
        subdivisions: icosphere subdivisions of the genus-0 shapes (642 vertices at 3, 2562 at 4).
        seed: family seed.

    Returns:
        One dict per file: ``name``, ``kind`` (real, genus0, humanoid), ``vertices``, ``faces``.
    """
    from vnc_warp import shapes
    from vnc_warp.commands.flow_batch import SUFFIXES
    from vnc_warp.mesh import load_mesh

    folder.mkdir(parents=True, exist_ok=True)
    if any(n.lower().endswith(SUFFIXES) for n in os.listdir(folder)):
        raise FileExistsError(f"{folder}: already holds mesh files; give an empty folder")
    listing = []
    if meshes_dir is not None and meshes_dir.is_dir():
        names = sorted(n for n in os.listdir(meshes_dir) if n.lower().endswith(SUFFIXES)) if real == "all" else \
            [n for n in real if (meshes_dir / n).is_file()]
        for name in names:
            shutil.copyfile(meshes_dir / name, folder / name)
            m = load_mesh(folder / name)
            listing.append({"name": name, "kind": "real", "vertices": m.num_vertices, "faces": m.num_faces})
    families = [("genus0", shapes.shape_family(procedural, seed, subdivisions=subdivisions) if procedural else [])]
    if humanoids and hasattr(shapes, "humanoid_family"):
        families.append(("humanoid", shapes.humanoid_family(humanoids, seed)))
    for kind, members in families:
        for m in members:
            name = f"{m.name}.obj"
            m.save(folder / name)
            listing.append({"name": name, "kind": kind, "vertices": m.num_vertices, "faces": m.num_faces})
    return sorted(listing, key=lambda d: d["name"])


# --- comparisons (the checks that can fail) --------------------------------------------------------------------


def trajectory_digests(folder: Path) -> dict:
    """``{mesh folder name: {"sha256": [...], "t": [...], "complete": bool}}`` of a flow-batch output folder,
    from each trajectory's ``manifest.json`` (folders without one are left out)."""
    out = {}
    for sub in sorted(p for p in folder.iterdir() if p.is_dir()):
        man = sub / "manifest.json"
        if not man.is_file():
            continue
        data = json.loads(man.read_text())
        stages = sorted(data.get("stages", []), key=lambda s: int(s["index"]))
        out[sub.name] = {"sha256": [s.get("sha256") for s in stages], "t": [float(s["t"]) for s in stages],
                         "complete": bool(data.get("complete"))}
    return out


def compare_trajectories(reference: dict, other: dict) -> dict:
    """Compare two :func:`trajectory_digests`: every stage file must be bit-identical.

    Returns:
        ``ok`` (every reference mesh present in ``other``, complete in both, same stage count and checksums),
        ``identical`` (meshes that match), ``differ`` (one entry per mismatch: mesh, reason, first differing stage,
        largest ``|t_other - t_ref|`` over the common stages) and ``missing`` (reference meshes absent in
        ``other``).
    """
    differ, identical, missing = [], [], []
    for name, ref in sorted(reference.items()):
        got = other.get(name)
        if got is None:
            missing.append(name)
            continue
        common = min(len(ref["t"]), len(got["t"]))
        dt = max((abs(a - b) for a, b in zip(ref["t"][:common], got["t"][:common])), default=0.0)
        first = next((i for i in range(common) if ref["sha256"][i] != got["sha256"][i]), None)
        if not (ref["complete"] and got["complete"]):
            differ.append({"mesh": name, "reason": "incomplete", "first_stage": first, "max_dt": dt})
        elif len(ref["sha256"]) != len(got["sha256"]):
            differ.append({"mesh": name, "reason": f"{len(got['sha256'])} stages, reference {len(ref['sha256'])}",
                           "first_stage": first if first is not None else common, "max_dt": dt})
        elif first is not None:
            differ.append({"mesh": name, "reason": "stage files differ", "first_stage": first, "max_dt": dt})
        else:
            identical.append(name)
    return {"ok": not differ and not missing and bool(reference), "identical": identical, "differ": differ,
            "missing": missing}


def read_loss_curve(run_dir: Path) -> dict[int, float]:
    """``{step: loss}`` of a training run's ``log.jsonl`` (each row: the mean over its logging window and ranks)."""
    rows = [json.loads(line) for line in (run_dir / "log.jsonl").read_text().splitlines() if line.strip()]
    return {int(r["step"]): float(r["loss"]) for r in rows}


def compare_losses(reference: dict[int, float], other: dict[int, float], *, first_rtol: float,
                   tail_rtol: float) -> dict:
    """Compare two loss curves of the same configuration (see the module docstring for why not step by step).

    Args:
        reference, other: ``{step: loss}`` (:func:`read_loss_curve`), logged every step.
        first_rtol: largest relative difference at the first logged step, where both runs hold the same weights and
            the same global batch.
        tail_rtol: largest relative difference of the mean loss over the last half of the steps.

    Returns:
        ``ok`` (every reference step present and finite, both bounds met), ``first_rel``, ``tail_rel``, and for
        information the per-step relative differences' ``mean_rel``, ``max_rel`` and ``worst_step``; ``steps``
        compared, ``missing`` reference steps, the tolerances.
    """
    steps = sorted(reference)
    missing = [s for s in steps if s not in other]
    rel = {s: abs(other[s] - reference[s]) / max(abs(reference[s]), 1e-30) for s in steps if s in other}
    finite = all(math.isfinite(v) for v in rel.values())
    worst = max(rel, key=lambda s: rel[s] if math.isfinite(rel[s]) else math.inf) if rel else None
    tail = [s for s in steps if s > steps[-1] / 2] if steps else []
    if tail and not missing:
        ref_tail = sum(reference[s] for s in tail) / len(tail)
        tail_rel = abs(sum(other[s] for s in tail) / len(tail) - ref_tail) / max(abs(ref_tail), 1e-30)
    else:
        tail_rel = math.nan
    first_rel = rel.get(steps[0], math.nan) if steps else math.nan
    return {"ok": bool(rel) and not missing and finite and first_rel <= first_rtol and tail_rel <= tail_rtol,
            "first_rel": first_rel, "tail_rel": tail_rel, "mean_rel": sum(rel.values()) / len(rel) if rel else math.nan,
            "max_rel": rel[worst] if worst is not None else math.nan, "worst_step": worst, "steps": len(rel),
            "missing": missing, "first_rtol": first_rtol, "tail_rtol": tail_rtol}


def steady_rate(run_dir: Path, *, skip_fraction: float = 0.1) -> float:
    """Training samples per second after the first ``skip_fraction`` of the logged rows: the harmonic mean of the
    rows' rates (total samples over total time when every window has as many samples)."""
    rows = [json.loads(line) for line in (run_dir / "log.jsonl").read_text().splitlines() if line.strip()]
    rates = [float(r["samples_per_s"]) for r in rows][int(math.ceil(skip_fraction * len(rows))):]
    return len(rates) / sum(1.0 / r for r in rates) if rates and min(rates) > 0 else math.nan


# --- the runs ---------------------------------------------------------------------------------------------------


def _env(threads: int, device: str) -> dict:
    env = dict(os.environ, OMP_NUM_THREADS=str(threads), MKL_NUM_THREADS=str(threads), PYTHONWARNINGS="ignore")
    if device == "cuda":
        env.update(NO_MULTICAST)
    return env


def _flow_args(in_dir: Path, out_dir: Path, p: dict, device: str) -> list[str]:
    return ["flow-batch", str(in_dir), str(out_dir), "--stages", str(p["stages"]), "--faces", str(p["faces"]),
            "--max-iters", str(p["max_iters"]), "--device", device, "--no-progress",
            *(["--substage-budget", str(p["substage_budget"])] if p.get("substage_budget") else [])]


def run_flow(k: int, in_dir: Path, out_dir: Path, p: dict, device: str, env: dict, logs: Path) -> dict:
    """One ``flow-batch`` under torchrun with K processes: wall time, per-rank flow seconds, outcomes, devices."""
    from vnc_warp.commands.flow_batch import read_record, shard

    res = _run(_torchrun(k, _flow_args(in_dir, out_dir, p, device), _free_port()), env, logs / f"flow_k{k}.log")
    entries = read_record(out_dir / "batch.json")["meshes"] if (out_dir / "batch.json").is_file() else []
    names = sorted(e["mesh"] for e in entries)
    busy = [0.0] * k
    for e in entries:
        if 0 <= e.get("rank", -1) < k:
            busy[e["rank"]] += float(e.get("seconds", 0.0))
    all_names = sorted(os.listdir(in_dir))
    expected_rank = {n: r for r in range(k) for n in shard(all_names, r, k)}
    wrong_rank = [e["mesh"] for e in entries if expected_rank.get(e["mesh"]) != e.get("rank")]
    wrong_device = [e["mesh"] for e in entries
                    if device == "cuda" and e.get("device") != f"cuda:{e.get('rank')}"]
    statuses: dict[str, int] = {}
    for e in entries:
        statuses[e["status"]] = statuses.get(e["status"], 0) + 1
    res.update(K=k, meshes=len(names), statuses=statuses, rank_busy_s=[round(b, 3) for b in busy],
               devices=sorted({str(e.get("device")) for e in entries}), wrong_rank=wrong_rank,
               wrong_device=wrong_device, meshes_per_min=60.0 * len(names) / res["wall_s"] if names else 0.0)
    return res


def _train_config(name: str, p: dict, k: int, steps: int, seed_offset: int = 0):
    from vnc_warp.training.config import load_config

    if name == "experiment-gpu":
        from vnc_warp.training.experiment import preset, run_config

        cfg = run_config(preset("gpu"), "cvae1")
    else:
        cfg = load_config(name)
    if p["global_batch"] % k:
        raise ValueError(f"--global-batch {p['global_batch']} is not a multiple of K = {k}")
    d = cfg.to_dict()
    d["data"].update(batch_size=p["global_batch"] // k, num_workers=p["workers"])
    d["optim"].update(total_steps=steps, warmup_steps=min(d["optim"]["warmup_steps"], max(steps // 10, 1)))
    d.update(log_every=p["log_every"], ckpt_every=steps, seed=d["seed"] + seed_offset)
    if d["model"]["kind"] != "cvae1":
        raise ValueError(f"training config {name!r} is a {d['model']['kind']} model; the benchmark trains C-VAE-I")
    return d


def run_train(k: int, data: Path, run_dir: Path, p: dict, device: str, env: dict, logs: Path, work: Path, *,
              seed_offset: int = 0, label: str | None = None) -> dict:
    """One DDP training run under torchrun with K processes and the global batch of the preset."""
    label = label or f"train_k{k}"
    cfg = _train_config(p["train_config"], p, k, p["steps"], seed_offset)
    cfg_path = work / f"{label}.json"
    cfg_path.write_text(json.dumps(cfg, indent=2) + "\n")
    args = ["train", "--config", str(cfg_path), "--data", str(data), "--out", str(run_dir), "--device", device,
            "--no-progress"]
    res = _run(_torchrun(k, args, _free_port()), env, logs / f"{label}.log")
    res.update(K=k, per_rank_batch=cfg["data"]["batch_size"], global_batch=p["global_batch"], steps=p["steps"],
               seed=cfg["seed"])
    if res["rc"] == 0:
        res["samples_per_s"] = p["steps"] * p["global_batch"] / res["wall_s"]
        res["steady_samples_per_s"] = steady_rate(run_dir)
        res["loss"] = read_loss_curve(run_dir)
    return res


def _git_commit() -> str | None:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                              check=True).stdout.strip() or None
    except (OSError, subprocess.CalledProcessError):
        return None


def _machine(device: str) -> dict:
    info = {"host_cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version()}
    import torch
    import warp

    info.update(torch=torch.__version__, warp=warp.__version__)
    if device == "cuda":
        info["gpus"] = [torch.cuda.get_device_name(i) for i in range(torch.cuda.device_count())]
    else:
        try:
            info["cpu"] = next(line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo")
                               if line.startswith("model name"))
        except (OSError, StopIteration):
            info["cpu"] = platform.processor()
    return info


def _fmt(x, nd=1) -> str:
    return "—" if x is None or (isinstance(x, float) and not math.isfinite(x)) else f"{x:.{nd}f}"


def markdown(doc: dict) -> str:
    """The report as Markdown: the command, the table, what was checked and how it came out."""
    p = doc["params"]
    per_rank = " / ".join(f"{p['global_batch'] // k} x {k}" for k in doc["ranks"])
    lines = [f"# Scale-out: flow-batch and DDP training ({doc['device']})", "",
             f"`{doc['command']}` on {doc['date']} at {doc.get('commit') or 'an unknown commit'}; "
             f"{doc['machine'].get('cpu') or ', '.join(doc['machine'].get('gpus', []))}, "
             f"{doc['machine']['host_cpus']} CPU cores, OMP_NUM_THREADS={doc['threads']} per rank.", "",
             f"Flow-batch: {len(doc['inputs'])} meshes ({doc['input_kinds']}), {p['stages']} stages at "
             f"{p['faces']} faces, at most {p['max_iters']} iterations per stage. Training: C-VAE-I "
             f"(`{p['train_config']}`), {p['steps']} steps, global batch {p['global_batch']} "
             f"({per_rank} per rank x ranks).", "",
             "| K | flow-batch wall (s) | meshes/min | efficiency | rank flow s (max / mean) | trajectories = K=1 | "
             "train wall (s) | samples/s (end to end) | samples/s (steady) | efficiency (steady) | "
             "loss = K=1 |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for row in doc["table"]:
        lines.append(
            f"| {row['K']} | {_fmt(row.get('flow_wall_s'))} | {_fmt(row.get('meshes_per_min'))} | "
            f"{_fmt(row.get('flow_efficiency'), 2)} | {_fmt(row.get('rank_busy_max_s'))} / "
            f"{_fmt(row.get('rank_busy_mean_s'))} | {row.get('trajectories_match', '—')} | "
            f"{_fmt(row.get('train_wall_s'))} | {_fmt(row.get('samples_per_s'))} | "
            f"{_fmt(row.get('steady_samples_per_s'))} | {_fmt(row.get('train_efficiency'), 2)} | "
            f"{row.get('loss_match', '—')} |")
    lines += ["", "Efficiency is `rate_K / (K rate_1)` (flow-batch: meshes per minute of the whole torchrun command; "
              "training: the steady samples per second). Rank flow seconds are the sums of the per-mesh flow times "
              "in `batch.json` (without process start-up and Warp initialisation).", ""]
    for note in doc["notes"]:
        lines.append(f"- {note}")
    lines += ["", "Commands (each K):", ""] + [f"    {c}" for c in doc["commands"]]
    return "\n".join(lines) + "\n"


def build_doc(state: dict) -> dict:
    """The report of what has run so far (``state``: the settings and the runs of :func:`main`)."""
    ranks, flows, trains, p = state["ranks"], state["flows"], state["trains"], state["params"]
    first_rtol, tail_rtol = state["first_step_rtol"], state["loss_rtol"]
    table, notes = [], []
    f1, t1 = flows.get(1, {}), trains.get(1, {})
    for k in ranks:
        f, t = flows.get(k), trains.get(k, {})
        if f is None:
            continue
        busy = f["rank_busy_s"]
        match = f.get("match")
        row = {"K": k, "flow_wall_s": f["wall_s"], "meshes_per_min": f["meshes_per_min"],
               "flow_efficiency": f["meshes_per_min"] / (k * f1["meshes_per_min"]) if f1["meshes_per_min"] else None,
               "rank_busy_max_s": max(busy), "rank_busy_mean_s": sum(busy) / len(busy),
               "trajectories_match": "reference" if k == 1 else (
                   f"yes ({len(match['identical'])}/{len(f1['digests'])} bit for bit)" if match["ok"] else
                   f"NO ({len(match['identical'])}/{len(f1['digests'])} identical)")}
        if t.get("rc") == 0 and t1.get("rc") == 0:
            s1 = t1["steady_samples_per_s"]
            row.update(train_wall_s=t["wall_s"], samples_per_s=t["samples_per_s"],
                       steady_samples_per_s=t["steady_samples_per_s"],
                       train_efficiency=t["steady_samples_per_s"] / (k * s1) if s1 else None,
                       loss_match="reference" if k == 1 else
                       f"{'yes' if t['match']['ok'] else 'NO'} (step 1: {t['match']['first_rel']:.1e}; last half: "
                       f"{100 * t['match']['tail_rel']:.2f} %)")
        table.append(row)
    for k in ranks:
        f = flows.get(k)
        if f is None:
            notes.append(f"flow-batch K={k}: not run.")
            continue
        if f["rc"] != 0:
            notes.append(f"flow-batch K={k} exited with code {f['rc']} (log {f['log']}).")
        if f["wrong_rank"]:
            notes.append(f"flow-batch K={k}: meshes on an unexpected rank: {f['wrong_rank']}.")
        if f["wrong_device"]:
            notes.append(f"flow-batch K={k}: meshes not on cuda:LOCAL_RANK: {f['wrong_device']}.")
        for d in f.get("match", {}).get("differ", []):
            notes.append(f"K={k}: {d['mesh']}: {d['reason']} from stage {d['first_stage']}, max |dt| "
                         f"{d['max_dt']:.2e}.")
        if f.get("match", {}).get("missing"):
            notes.append(f"K={k}: trajectories missing: {f['match']['missing']}.")
    notes.append("Devices recorded per mesh in batch.json: " + "; ".join(
        f"K={k}: {', '.join(flows[k]['devices'])}" for k in ranks if k in flows) + ".")
    if "repeat" in flows:
        m, n = flows["repeat"]["match"], p["repeat"]
        notes.append(f"Run-to-run determinism: K = 1 again on {n} meshes gave {len(m['identical'])} of {n} "
                     "trajectories bit for bit"
                     + ("." if m["ok"] else f"; differ: {[d['mesh'] for d in m['differ']]}."))
    for k in ranks[1:]:
        t = trains.get(k, {})
        if "match" in t:
            m = t["match"]
            notes.append(f"Loss K={k} vs K=1: step 1 {m['first_rel']:.1e} relative (tolerance {first_rtol:.0e}), "
                         f"mean of the last half {100 * m['tail_rel']:.2f} % (tolerance {100 * tail_rtol:.0f} %); "
                         f"step by step {100 * m['mean_rel']:.2f} % on average, {100 * m['max_rel']:.2f} % at most "
                         f"(step {m['worst_step']}) over {m['steps']} steps.")
    if "match" in trains.get("seed1", {}):
        m = trains["seed1"]["match"]
        notes.append(f"Yardstick, two equally valid runs: K = 1 with seed + 1 differs from K = 1 by "
                     f"{100 * m['tail_rel']:.2f} % in the mean of the last half, and step by step by "
                     f"{100 * m['mean_rel']:.2f} % on average, {100 * m['max_rel']:.2f} % at most (its first step "
                     "starts from other weights).")
    for k, t in trains.items():
        if t.get("rc") not in (0, None):
            notes.append(f"training {k} exited with code {t['rc']} (log {t['log']}).")
    loads = [r[key] for runs in (flows, trains) for r in runs.values() for key in ("load_before", "load_after")]
    if loads:
        notes.append(f"1-minute load average during the runs: {min(loads):.1f} to {max(loads):.1f} on "
                     f"{state['machine']['host_cpus']} cores.")
    notes += state["skipped"]
    doc = {k: v for k, v in state.items() if k not in ("flows", "trains", "t_start")}
    doc.update(flows={str(k): v for k, v in flows.items()}, trains={str(k): v for k, v in trains.items()},
               table=table, notes=notes, total_s=round(time.perf_counter() - state["t_start"], 1))
    return doc


def _write(out: Path, state: dict) -> dict:
    doc = build_doc(state)
    out.mkdir(parents=True, exist_ok=True)
    (out / "scaling.json").write_text(json.dumps(doc, indent=1, default=str) + "\n")
    (out / "scaling.md").write_text(markdown(doc))
    return doc


def main(argv=None) -> dict:
    """Run the benchmark (see the module docstring); the report is rewritten after every run, so a run stopped by a
    time limit keeps what finished. Returns the report."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("--device", choices=["cpu", "cuda"], default="cpu",
                    help="cpu: gloo, one CPU process per rank; cuda: one GPU per rank, NCCL for training")
    ap.add_argument("--ranks", default="1,2", help="comma-separated process counts K (1 first)")
    ap.add_argument("--out", required=True, help="output folder: scaling.json, scaling.md, work/")
    ap.add_argument("--preset", choices=sorted(PRESETS), default=None, help="sizes (default: the device's)")
    ap.add_argument("--meshes", default=str(DEFAULT_MESHES), help="folder of real meshes (skipped when absent)")
    ap.add_argument("--real", default=None, help="comma-separated real mesh files, or 'all' (default: the preset's)")
    ap.add_argument("--procedural", type=int, default=None, help="genus-0 random shapes")
    ap.add_argument("--humanoids", type=int, default=None, help="random humanoids (when vnc_warp.shapes has them)")
    ap.add_argument("--faces", type=int, default=None, help="face count of every flow state")
    ap.add_argument("--stages", type=int, default=None, help="VNC-Flow stages")
    ap.add_argument("--max-iters", type=int, default=None, help="iteration cap per stage")
    ap.add_argument("--substage-budget", type=float, default=None,
                    help="VNC-Flow's largest share of S_init between two remeshes (default: the flow's, 1/32)")
    ap.add_argument("--train-config", default=None,
                    help="C-VAE-I config: a named config, a JSON file, or experiment-gpu (the experiment's GPU model)")
    ap.add_argument("--steps", type=int, default=None, help="training steps of every K")
    ap.add_argument("--global-batch", type=int, default=None, help="items per optimiser step, split over the ranks")
    ap.add_argument("--first-step-rtol", type=float, default=None,
                    help="largest relative difference of the first step's loss to K = 1 (default: 1e-5 on cpu, "
                         "float32; 1e-2 on cuda, bf16)")
    ap.add_argument("--loss-rtol", type=float, default=0.05,
                    help="largest relative difference of the mean loss over the last half of the steps to K = 1")
    ap.add_argument("--repeat", type=int, default=None,
                    help="flow the first N meshes a second time with K = 1 (run-to-run determinism); 0: no")
    ap.add_argument("--no-seed-spread", action="store_true",
                    help="skip the K = 1 run with seed + 1 (the loss difference of two equally valid runs)")
    ap.add_argument("--threads", type=int, default=None,
                    help="OMP_NUM_THREADS of every rank (default: 1 on cpu, the cores over the largest K on cuda)")
    ap.add_argument("--no-train", action="store_true", help="flow-batch only")
    ap.add_argument("--max-minutes", type=float, default=None,
                    help="start no further run after this many minutes (what finished is reported)")
    ap.add_argument("--keep-work", action="store_true", help="keep OUT/work (trajectories, dataset, runs)")
    args = ap.parse_args(argv)

    ranks = [int(k) for k in args.ranks.split(",")]
    if ranks[0] != 1 or len(set(ranks)) != len(ranks) or min(ranks) < 1:
        raise SystemExit(f"--ranks must start with 1 and list distinct counts, got {args.ranks!r}")
    dev = args.device
    p = dict(PRESETS[args.preset or dev])
    for key in ("procedural", "humanoids", "faces", "stages", "max_iters", "substage_budget", "train_config", "steps",
                "global_batch", "repeat"):
        if getattr(args, key) is not None:
            p[key] = getattr(args, key)
    if args.real is not None:
        p["real"] = "all" if args.real == "all" else tuple(n for n in args.real.split(",") if n)
    for k in ranks:
        if p["global_batch"] % k:
            raise SystemExit(f"--global-batch {p['global_batch']} is not a multiple of K = {k}")
    if dev == "cuda":
        import torch

        if torch.cuda.device_count() < max(ranks):
            raise SystemExit(f"--ranks {args.ranks} needs {max(ranks)} GPUs; torch sees {torch.cuda.device_count()}")
    first_rtol = args.first_step_rtol if args.first_step_rtol is not None else (1e-5 if dev == "cpu" else 1e-2)
    threads = args.threads or (1 if dev == "cpu" else max(1, (os.cpu_count() or 1) // max(ranks)))
    out = Path(args.out)
    work = out / "work"
    if work.exists():
        raise SystemExit(f"{work} exists (a previous run); give a new --out or move it away")
    logs = work / "logs"
    env = _env(threads, dev)
    t_start = time.perf_counter()

    def budget_left(what: str) -> bool:
        if args.max_minutes is None or time.perf_counter() - t_start < 60.0 * args.max_minutes:
            return True
        state["skipped"].append(f"{what}: not started, --max-minutes {args.max_minutes} spent.")
        return False

    inputs = assemble_inputs(work / "inputs", meshes_dir=Path(args.meshes), real=p["real"],
                             procedural=p["procedural"], humanoids=p["humanoids"], subdivisions=p["subdivisions"])
    if len(inputs) < 2:
        raise SystemExit("fewer than 2 input meshes")
    kinds: dict[str, int] = {}
    for m in inputs:
        kinds[m["kind"]] = kinds.get(m["kind"], 0) + 1
    print(f"{len(inputs)} meshes ({kinds}) in {work / 'inputs'}", flush=True)
    given = argv if argv is not None else sys.argv[1:]
    commands = [_shown(_torchrun(1, _flow_args(Path("IN"), Path("OUT_K"), p, dev), 0)).replace(
        "--nproc_per_node=1", "--nproc_per_node=K")]
    if not args.no_train:
        commands.append("torchrun --nproc_per_node=K -m vnc_warp.cli train --config CFG_K.json --data DATA "
                        f"--out RUN_K --device {dev} --no-progress")
    state = {"schema": SCHEMA, "command": "python -m bench.scaling " + " ".join(given),
             "date": time.strftime("%Y-%m-%d %H:%M"), "commit": _git_commit(), "device": dev, "ranks": ranks,
             "threads": threads, "machine": _machine(dev),
             "params": {k: (list(v) if isinstance(v, tuple) else v) for k, v in p.items()},
             "loss_rtol": args.loss_rtol, "first_step_rtol": first_rtol, "inputs": inputs,
             "input_kinds": ", ".join(f"{v} {k}" for k, v in kinds.items()), "commands": commands,
             "flows": {}, "trains": {}, "skipped": [], "t_start": t_start}
    flows, trains = state["flows"], state["trains"]

    # untimed: compile Warp's kernels for this device once (the cache is shared by every later process)
    warm_in = work / "warmup_inputs"
    warm_in.mkdir()
    for m in (inputs[0], inputs[-1]):
        shutil.copyfile(work / "inputs" / m["name"], warm_in / m["name"])
    def finished(line: str, run: dict) -> None:
        print(line, flush=True)
        if run["rc"] != 0:
            print(_tail(run["log"]), flush=True)
        _write(out, state)

    warm = run_flow(1, warm_in, work / "warmup_flow", dict(p, stages=min(2, p["stages"])), dev, env, logs)
    state["warmup"] = warm
    finished(f"warm-up flow-batch: {warm['wall_s']:.1f} s (rc {warm['rc']})", warm)

    for k in ranks:
        if not budget_left(f"flow-batch K={k}"):
            break
        r = run_flow(k, work / "inputs", work / f"flow_k{k}", p, dev, env, logs)
        r["digests"] = trajectory_digests(work / f"flow_k{k}")
        if k > 1:
            r["match"] = compare_trajectories(flows[1]["digests"], r["digests"])
        flows[k] = r
        finished(f"flow-batch K={k}: {r['wall_s']:.1f} s, {r['meshes_per_min']:.1f} meshes/min, "
                 f"rank flow s {r['rank_busy_s']}, {r['statuses']} (rc {r['rc']})", r)
    data = work / "data"
    if 1 not in flows:
        return _write(out, state)
    if not args.no_train and budget_left("the dataset"):
        trajs = [str(work / "flow_k1" / m["name"]) for m in inputs
                 if flows[1]["digests"].get(m["name"], {}).get("complete")]
        ns, nu, nn = p["samples"]
        ds = _run([sys.executable, "-m", "vnc_warp.cli", "dataset", *trajs, "--out", str(data), "--num-surface",
                   str(ns), "--num-uniform", str(nu), "--num-near", str(nn), "--device",
                   "cuda:0" if dev == "cuda" else "cpu", "--quiet"], env, logs / "dataset.log")
        state["dataset"] = dict(ds, trajectories=len(trajs))
        finished(f"dataset of {len(trajs)} trajectories: {ds['wall_s']:.1f} s (rc {ds['rc']})", ds)

    def train(key, k: int, offset: int) -> None:
        label = f"train_k{k}" if key == k else f"train_k{k}_{key}"
        r = run_train(k, data, work / label, p, dev, env, logs, work, seed_offset=offset, label=label)
        if "loss" in r and key != 1 and "loss" in trains.get(1, {}):
            r["match"] = compare_losses(trains[1]["loss"], r["loss"], first_rtol=first_rtol,
                                        tail_rtol=args.loss_rtol)
        trains[key] = r
        finished(f"train {label}: {r['wall_s']:.1f} s, {_fmt(r.get('samples_per_s'))} samples/s end to end, "
                 f"{_fmt(r.get('steady_samples_per_s'))} steady (rc {r['rc']})", r)

    trained = False
    if not args.no_train and budget_left("training"):
        for k in ranks:
            if state.get("dataset", {}).get("rc") != 0 or not budget_left(f"training K={k}"):
                break
            train(k, k, 0)
        trained = trains.get(1, {}).get("rc") == 0

    # the extras last, so that a time budget cuts them first
    if p["repeat"] and budget_left("the K = 1 repeat"):
        rep_in = work / "repeat_inputs"
        rep_in.mkdir()
        chosen = [m["name"] for m in inputs[:p["repeat"]]]
        for name in chosen:
            shutil.copyfile(work / "inputs" / name, rep_in / name)
        rep = run_flow(1, rep_in, work / "flow_repeat", p, dev, env, logs)
        rep["match"] = compare_trajectories({n: flows[1]["digests"][n] for n in chosen if n in flows[1]["digests"]},
                                            trajectory_digests(work / "flow_repeat"))
        flows["repeat"] = rep
        finished(f"K=1 repeat of {len(chosen)} meshes: identical {len(rep['match']['identical'])}", rep)

    if trained and not args.no_seed_spread and budget_left("training K = 1 with seed + 1"):
        train("seed1", 1, 1)

    doc = _write(out, state)
    print(markdown(doc), flush=True)
    if not args.keep_work:
        for sub in work.iterdir():
            if sub.is_dir() and sub.name != "logs":
                shutil.rmtree(sub)
    return doc


if __name__ == "__main__":
    main()
