"""Training throughput of C-VAE-I on one device, cause by cause (issue 24).

The ``gpu`` experiment preset's C-VAE-I (``run_config(preset("gpu"), "cvae1")``: 384 wide, 512 x 32 latents,
2 + 6 layers, batch 32, 4,096 surface points, 8,192 queries, 1,024 on-surface points, L_eik on 512 queries,
bf16) trains on synthetic ellipsoid trajectories of the same sizes (``EllipsoidTrajectories``, encoded through
the preset's ``SuffixInput``), or on a dataset folder with ``--data``. Each row changes one thing:

- ``a_train``: ``training.train.train`` as the experiment runs it (DataLoader with the preset's workers, logging
  and the eval-mode decode every ``log_every`` steps); items/s from its log rows after the first.
- ``a0_loader``: the training loop's DataLoader alone (no model; persistent workers, pinned memory on CUDA): what
  the workers deliver.
- ``b_fixed_batch``: ``train_step`` on one batch already on the device (no loader, no logging).
- ``c_no_eikonal``: (b) without L_eik (its 512 queries are not decoded; the surface terms stay).
- ``d_no_surface``: (b) without L_surf and L_normal (L_eik stays).
- ``cd_no_grad_terms``: (b) without all three: no input gradient, no double backward.
- ``e_forward``: (b)'s forward and loss (with the first-order input gradient), no backward, no optimiser.
- ``f_compile``: (b) with every attention block compiled (``nn.Module.compile``) except the query decoder's
  cross-attention, whose double backward torch.compile does not support; warm-up includes the compilation.
- ``g_batch64``: (b) with twice the batch.
- ``h_fps``: the encoder's farthest-point sampling alone (512 of 4,096 points per item, one Warp kernel launch,
  :mod:`vnc_warp.sampling`).

Every timed row runs ``--warmup`` steps, then ``--steps`` steps between ``torch.cuda.synchronize()`` calls; peak
memory is ``torch.cuda.max_memory_allocated`` of the row. Prints a line as each row starts and ends (flushed, so a
piped log shows it), then a table, and writes ``OUT/train_throughput.json``.

    timeout 480 python -m bench.train_throughput --device cuda --out OUT   # ~1-2 minutes on one H200 (estimate)
    python -m bench.train_throughput --device cpu --tiny --out OUT         # the CPU check (cpu-smoke sizes)

Until issue 24's h39 the ``a_train`` row handed ``train`` items already wrapped in ``SuffixInput``, which ``train``
wrapped again: the outer wrapper, finding no ``item_ids`` / ``stage_times`` on the inner one, read all 3,968
items twice in the main process before the first step (~260 s of the 333 s H200 run, nothing printed meanwhile),
and then drew encoder inputs of encoder inputs (up to four reads per item, so its 165 items/s undercounts the
experiment's loader). ``open_dataset`` now refuses a wrapped dataset.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import platform
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from torch.utils.data import Dataset, DistributedSampler, default_collate

from vnc_warp.training.config import TrainConfig
from vnc_warp.training.experiment import preset, run_config
from vnc_warp.training.losses import cvae_loss, gradient_queries
from vnc_warp.training.model import AttentionBlock, build_model, farthest_point_sample
from vnc_warp.training.synthetic import EllipsoidTrajectories
from vnc_warp.training.train import (
    _data_loader,
    _EpochSampler,
    _optimizer,
    open_dataset,
    to_device,
    train,
    train_step,
)

ROWS = ("a_train", "a0_loader", "b_fixed_batch", "c_no_eikonal", "d_no_surface", "cd_no_grad_terms", "e_forward",
        "f_compile", "g_batch64", "h_fps")


def bench_config(*, tiny: bool) -> TrainConfig:
    """C-VAE-I's training configuration of the ``gpu`` preset, or of ``cpu-smoke`` with ``tiny``."""
    return run_config(preset("cpu-smoke" if tiny else "gpu"), "cvae1")


def synthetic_dataset(config: TrainConfig, *, items: int, seed: int = 0) -> EllipsoidTrajectories:
    """Ellipsoid trajectories of 8 stages sized like ``config``'s items, about ``items`` of them in all."""
    d = config.data
    return EllipsoidTrajectories(num_shapes=max(1, math.ceil(items / 8)), num_stages=8, num_surface=d.num_surface,
                                 num_queries=d.num_queries, num_on_surface=d.num_on_surface, seed=seed,
                                 sdf_iterations=32)


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _reset_peak(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats(device)


def _peak_gib(device: torch.device) -> float | None:
    return torch.cuda.max_memory_allocated(device) / 2**30 if device.type == "cuda" else None


def _row(name: str, batch: int, seconds_per_step: float, device: torch.device, **extra) -> dict:
    return {"variant": name, "batch": batch, "items_per_s": batch / seconds_per_step,
            "ms_per_step": 1e3 * seconds_per_step, "peak_gib": _peak_gib(device), **extra}


def _fixed_batch(dataset: Dataset, size: int, device: torch.device, seed: int) -> dict[str, torch.Tensor]:
    idx = np.random.default_rng(seed).choice(len(dataset), size=size, replace=False)
    return to_device(default_collate([dataset[int(i)] for i in idx]), device)


def _timed(fn: Callable[[int], torch.Tensor], *, warmup: int, steps: int, device: torch.device) -> tuple[float, float, float]:
    """(seconds per step, warm-up seconds, last loss) of ``fn(step)`` over ``steps`` steps after ``warmup``."""
    t0 = time.perf_counter()
    for i in range(warmup):
        fn(i)
    _sync(device)
    t1 = time.perf_counter()
    loss = None
    for i in range(warmup, warmup + steps):
        loss = fn(i)
    _sync(device)
    t2 = time.perf_counter()
    return (t2 - t1) / steps, t1 - t0, float(loss)


def _step_row(name: str, config: TrainConfig, batch: dict, device: torch.device, *, warmup: int, steps: int,
              forward_only: bool = False, compile_backend: str | None = None) -> dict:
    """A row of :func:`train_step` (or its forward and loss) on a batch already on ``device``."""
    _reset_peak(device)
    torch.manual_seed(config.seed)
    model = build_model(config.model).to(device).train()
    if compile_backend is not None:
        skip = model.decoder.queries.cross  # double backward of L_eik / L_normal: not supported by torch.compile
        for m in model.modules():
            if isinstance(m, AttentionBlock) and m is not skip:
                m.compile(backend=compile_backend)
    opt, sched, params = _optimizer(model, config)
    amp = config.bf16 and device.type == "cuda" and torch.cuda.is_bf16_supported()

    def step(i: int) -> torch.Tensor:
        if forward_only:
            grad_q = gradient_queries(batch, config.loss)
            with torch.autocast(device_type=device.type, dtype=torch.bfloat16, enabled=amp):
                out = model(batch["surface"], batch["queries"], batch["t"],
                            eikonal_queries=None if grad_q is None else grad_q.points)
            return cvae_loss(out, batch, config.loss, step=i, gradient=grad_q)["loss"].detach()
        return train_step(model, batch, config, opt, sched, params, step=i, amp=amp)[0]["loss"].detach()

    per_step, warm_s, loss = _timed(step, warmup=warmup, steps=steps, device=device)
    row = _row(name, len(batch["t"]), per_step, device, loss=loss, warmup_s=warm_s)
    del model, opt, sched, params
    return row


def _loss_variant(config: TrainConfig, **weights) -> TrainConfig:
    cfg = TrainConfig.from_dict(config.to_dict())
    cfg.loss = dataclasses.replace(cfg.loss, **weights)
    return cfg


def _train_row(config: TrainConfig, source: Dataset | str, device: torch.device, *, steps: int, tiny: bool) -> dict:
    """``train`` as the experiment runs it, on the items before :func:`open_dataset` (``train`` wraps them, as in
    the experiment); items/s over its log windows after the first (worker start-up)."""
    cfg = TrainConfig.from_dict(config.to_dict())
    if tiny:
        cfg.log_every = 1
    windows = max(2, math.ceil(steps / cfg.log_every))
    _reset_peak(device)
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        train(cfg, data=source, out_dir=tmp, device=device, stop_at=cfg.log_every * (1 + windows), progress=False)
        wall = time.perf_counter() - t0
        rows = [json.loads(line) for line in (Path(tmp) / "log.jsonl").read_text().splitlines() if line.strip()]
    measured = rows[1:]
    items = cfg.log_every * cfg.data.batch_size * len(measured)
    seconds = sum(cfg.log_every * cfg.data.batch_size / r["samples_per_s"] for r in measured)
    return _row("a_train", cfg.data.batch_size, seconds / (cfg.log_every * len(measured)), device,
                loss=rows[-1]["loss"], log_every=cfg.log_every, measured_steps=items // cfg.data.batch_size,
                first_window_items_per_s=rows[0]["samples_per_s"], wall_s=wall, workers=cfg.data.num_workers)


def _loader_row(config: TrainConfig, dataset: Dataset, device: torch.device, *, warmup: int, steps: int) -> dict:
    """What the training loop's DataLoader alone delivers (its workers, prefetch and pinned memory); first-batch
    latency apart."""
    bs = config.data.batch_size
    sampler = _EpochSampler(DistributedSampler(dataset, num_replicas=1, rank=0, shuffle=True, seed=config.seed,
                                               drop_last=True))
    loader = _data_loader(dataset, sampler, config, device, seed=config.seed)
    it = iter(loader)
    t0 = time.perf_counter()
    next(it)
    first = time.perf_counter() - t0
    for _ in range(warmup):
        next(it)
    t1 = time.perf_counter()
    for _ in range(steps):
        to_device(next(it), device)
    _sync(device)
    per_step = (time.perf_counter() - t1) / steps
    del it, loader
    return _row("a0_loader", bs, per_step, device, first_batch_s=first, workers=config.data.num_workers)


def _fps_row(config: TrainConfig, batch: dict, device: torch.device, *, warmup: int, steps: int) -> dict:
    _reset_peak(device)
    xyz = batch["surface"][..., :3]
    m = config.model.num_latents

    def step(_: int) -> torch.Tensor:
        return farthest_point_sample(xyz, m, random_start=True)[0, -1]

    per_step, warm_s, _ = _timed(step, warmup=warmup, steps=steps, device=device)
    return _row("h_fps", len(xyz), per_step, device, warmup_s=warm_s, num_samples=m, num_points=xyz.shape[1])


def _log(message: str) -> None:
    print(message, flush=True)  # progress reaches a piped log (a remote job's) as it happens


def run(*, device: str, tiny: bool, steps: int, warmup: int, only: set[str], data: str | None = None,
        compile_backend: str | None = None, log: Callable[[str], None] = _log) -> dict:
    """Measure the rows of ``only`` (names of :data:`ROWS`) and return the report (see the module docstring)."""
    dev = torch.device(device)
    if dev.type == "cuda":
        torch.cuda.set_device(dev)
        torch.backends.cuda.matmul.allow_tf32 = True
    config = bench_config(tiny=tiny)
    bs = config.data.batch_size
    base = synthetic_dataset(config, items=max(4 * bs, 124 * bs)) if data is None else None
    dataset = open_dataset(data if data is not None else base, config)
    compile_backend = compile_backend or ("inductor" if dev.type == "cuda" else "aot_eager")
    rows: list[dict] = []
    t0 = time.perf_counter()

    def add(row: dict) -> None:
        rows.append(row)
        log(f"  {row['variant']:<18} {row['items_per_s']:9.1f} items/s  {row['ms_per_step']:9.1f} ms/step  "
            f"({time.perf_counter() - t0:.0f} s)")

    log(f"  {len(only)} row(s) on {dev}, batch {bs}, {steps} timed steps each after {warmup} warm-up step(s)")
    batch = big = None
    if only & {"b_fixed_batch", "c_no_eikonal", "d_no_surface", "cd_no_grad_terms", "e_forward", "f_compile", "h_fps"}:
        batch = _fixed_batch(dataset, bs, dev, config.seed)
    if "g_batch64" in only:
        big = _fixed_batch(dataset, 2 * bs, dev, config.seed + 1)
    kw = dict(warmup=warmup, steps=steps)
    for name in ROWS:
        if name not in only:
            continue
        log(f"  {name:<18} ... ({time.perf_counter() - t0:.0f} s)")
        try:
            if name == "a_train":
                add(_train_row(config, data if data is not None else base, dev, steps=max(steps, 2 * config.log_every) if not tiny else steps,
                               tiny=tiny))
            elif name == "a0_loader":
                add(_loader_row(config, dataset, dev, **kw))
            elif name == "b_fixed_batch":
                add(_step_row(name, config, batch, dev, **kw))
            elif name == "c_no_eikonal":
                add(_step_row(name, _loss_variant(config, eikonal_weight=0.0, eikonal_queries=0), batch, dev, **kw))
            elif name == "d_no_surface":
                add(_step_row(name, _loss_variant(config, surface_weight=0.0, normal_weight=0.0), batch, dev, **kw))
            elif name == "cd_no_grad_terms":
                add(_step_row(name, _loss_variant(config, eikonal_weight=0.0, surface_weight=0.0, normal_weight=0.0),
                              batch, dev, **kw))
            elif name == "e_forward":
                add(_step_row(name, config, batch, dev, forward_only=True, **kw))
            elif name == "f_compile":
                add(_step_row(name, config, batch, dev, compile_backend=compile_backend, **kw)
                    | {"backend": compile_backend})
            elif name == "g_batch64":
                cfg = TrainConfig.from_dict(config.to_dict())
                cfg.data = dataclasses.replace(cfg.data, batch_size=2 * bs)
                add(_step_row(name, cfg, big, dev, **kw))
            elif name == "h_fps":
                add(_fps_row(config, batch, dev, **kw))
        except Exception as err:  # a variant that fails (compile, memory) is a finding, not the end of the bench
            rows.append({"variant": name, "error": f"{type(err).__name__}: {err}"[:500]})
            log(f"  {name:<18} failed: {rows[-1]['error'][:200]}")
        finally:
            if dev.type == "cuda":
                torch.cuda.empty_cache()
    m, d, lo = config.model, config.data, config.loss
    return {
        "device": torch.cuda.get_device_name(dev) if dev.type == "cuda" else platform.processor() or "cpu",
        "torch": torch.__version__, "tiny": tiny, "steps": steps, "warmup": warmup,
        "data": data or "synthetic EllipsoidTrajectories (8 stages, SuffixInput)",
        "config": {"width": m.width, "num_latents": m.num_latents, "latent_dim": m.latent_dim,
                   "encoder_depth": m.encoder_depth, "decoder_depth": m.decoder_depth,
                   "parameters": sum(p.numel() for p in build_model(m).parameters()), "batch": bs,
                   "num_surface": d.num_surface, "num_queries": d.num_queries, "num_on_surface": d.num_on_surface,
                   "eikonal_queries": lo.eikonal_queries, "workers": d.num_workers, "bf16": config.bf16},
        "rows": rows,
    }


def format_table(report: dict) -> str:
    """The rows as a fixed-width table."""
    lines = [f"{'variant':<18} {'batch':>5} {'items/s':>10} {'ms/step':>10} {'peak GiB':>9}  note"]
    for r in report["rows"]:
        if "error" in r:
            lines.append(f"{r['variant']:<18} {'':>5} {'failed':>10} {'':>10} {'':>9}  {r['error'][:80]}")
            continue
        peak = "-" if r["peak_gib"] is None else f"{r['peak_gib']:.2f}"
        note = ""
        if "first_batch_s" in r:
            note = f"first batch {r['first_batch_s']:.2f} s, {r['workers']} workers"
        elif "warmup_s" in r:
            note = f"warm-up {r['warmup_s']:.1f} s"
        if "first_window_items_per_s" in r:
            note = f"first window {r['first_window_items_per_s']:.0f} items/s, {r['workers']} workers"
        lines.append(f"{r['variant']:<18} {r['batch']:>5} {r['items_per_s']:>10.1f} {r['ms_per_step']:>10.1f} "
                     f"{peak:>9}  {note}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--tiny", action="store_true", help="the cpu-smoke preset's C-VAE-I sizes (CPU check)")
    p.add_argument("--steps", type=int, default=None, help="timed steps per row (default 20; 3 with --tiny)")
    p.add_argument("--warmup", type=int, default=None, help="untimed steps first (default 5; 1 with --tiny)")
    p.add_argument("--only", default=",".join(ROWS), help=f"comma-separated rows of {', '.join(ROWS)}")
    p.add_argument("--data", default=None, help="a `vnc-warp dataset` folder instead of the synthetic data")
    p.add_argument("--compile-backend", default=None, help="torch.compile backend of f_compile "
                   "(default inductor on CUDA, aot_eager on the CPU)")
    p.add_argument("--out", type=Path, default=None, help="folder for train_throughput.json")
    a = p.parse_args(argv)
    only = {s.strip() for s in a.only.split(",") if s.strip()}
    if only - set(ROWS):
        p.error(f"--only: unknown row(s) {sorted(only - set(ROWS))}; rows: {', '.join(ROWS)}")
    steps = a.steps if a.steps is not None else (3 if a.tiny else 20)
    warmup = a.warmup if a.warmup is not None else (1 if a.tiny else 5)
    if steps < 1 or warmup < 0:
        p.error(f"--steps must be >= 1 and --warmup >= 0, got {steps} and {warmup}")
    if a.out is not None:
        a.out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    report = run(device=a.device, tiny=a.tiny, steps=steps, warmup=warmup, only=only, data=a.data,
                 compile_backend=a.compile_backend)
    report["wall_s"] = time.perf_counter() - t0
    report["command"] = " ".join(["python -m bench.train_throughput", *(argv if argv is not None else sys.argv[1:])])
    print(f"C-VAE-I training throughput on {report['device']} ({report['config']['parameters'] / 1e6:.1f}M "
          f"parameters, batch {report['config']['batch']}, {report['wall_s']:.0f} s)")
    print(format_table(report))
    if a.out is not None:
        (a.out / "train_throughput.json").write_text(json.dumps(report, indent=2) + "\n")
        print(f"wrote {a.out / 'train_throughput.json'}")
    return report


if __name__ == "__main__":
    main()
