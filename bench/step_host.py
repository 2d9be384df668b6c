"""Host work of one C-VAE-I training step at the ``gpu`` preset's sizes (issue 24): what the CPU does per item, per
batch and per step, the part of a step that no GPU makes faster.

Rows (each prints as it ends; the JSON holds them all):

- ``item``: one training item as the experiment's loader worker makes it (the preset's ``SuffixInput`` over the
  synthetic ``EllipsoidTrajectories`` of the throughput bench, or over a ``vnc-warp dataset`` folder with ``--data``,
  its arrays cached as the experiment preloads them), ms per item on one thread.
- ``collate``: ``default_collate`` of one batch of those items (in the worker too), ms per batch, and its MB.
- ``ops``: ATen operators dispatched by one forward + loss and by its backward (the profiler's top-level ones; each
  is at least one kernel launch on a GPU); they do not depend on the batch, the widths or the point counts.
- ``dispatch``: one forward + loss + backward of the same layers and losses at negligible sizes (width 48, 32 latents,
  64 queries, batch 1) on ``--device``, ms (median of ``--repeats``, synchronised): the step's host floor, the
  time a step takes however fast the GPU is.

    python -m bench.step_host --device cpu --out OUT             # about a minute on one CPU core
    timeout 300 python -m bench.step_host --device cuda --out OUT
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import default_collate

from bench.train_throughput import bench_config, synthetic_dataset
from vnc_warp.training.config import TrainConfig
from vnc_warp.training.losses import cvae_loss, gradient_queries
from vnc_warp.training.model import build_model
from vnc_warp.training.synthetic import EllipsoidTrajectories
from vnc_warp.training.train import open_dataset, to_device


def _log(message: str) -> None:
    print(message, flush=True)


def _source(config: TrainConfig, data: str | None):
    if data is None:
        return synthetic_dataset(config, items=64)
    from vnc_warp.training.data import TrajectoryDataset

    d = config.data
    ds = TrajectoryDataset(data, num_surface=d.num_surface, num_queries=d.num_queries, near_fraction=d.near_fraction,
                           num_on_surface=d.num_on_surface, fresh_fraction=d.fresh_fraction, seed=config.seed,
                           cache=True, split="all")
    ds.preload()
    return ds


def _step(model: torch.nn.Module, batch: dict, config: TrainConfig) -> torch.Tensor:
    grad_q = gradient_queries(batch, config.loss)
    out = model(batch["surface"], batch["queries"], batch["t"],
                eikonal_queries=None if grad_q is None else grad_q.points)
    return cvae_loss(out, batch, config.loss, step=1, gradient=grad_q)["loss"]


def _top_level_ops(fn) -> tuple[object, int]:
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU]) as prof:
        result = fn()
    events = [e for e in prof.events() if e.name.startswith("aten::")]
    return result, sum(1 for e in events if e.cpu_parent is None or not e.cpu_parent.name.startswith("aten::"))


def _small(config: TrainConfig) -> TrainConfig:
    """``config``'s layers and losses at negligible sizes: the same operators, almost no arithmetic."""
    cfg = TrainConfig.from_dict(config.to_dict())
    cfg.model = dataclasses.replace(cfg.model, width=8 * cfg.model.heads, num_latents=32, latent_dim=8)
    cfg.data = dataclasses.replace(cfg.data, num_surface=64, num_queries=64, num_on_surface=min(16, cfg.data.num_on_surface))
    cfg.loss = dataclasses.replace(cfg.loss, eikonal_queries=16)
    return cfg


def run(*, device: str, tiny: bool, data: str | None, items: int, repeats: int) -> dict:
    """Measure the rows (see the module docstring) and return the report."""
    dev = torch.device(device)
    torch.set_num_threads(1)
    config = bench_config(tiny=tiny)
    rows = {}
    dataset = open_dataset(_source(config, data), config)
    n = len(dataset)
    for i in range(min(2, n)):  # first reads: caches, imports
        dataset[i]
    t0 = time.perf_counter()
    for i in range(items):
        dataset[i % n]
    rows["item"] = {"ms": 1e3 * (time.perf_counter() - t0) / items, "items": items}
    _log(f"  item      {rows['item']['ms']:8.2f} ms per item (one thread)")
    bs = config.data.batch_size
    batch_items = [dataset[i % n] for i in range(bs)]
    t0 = time.perf_counter()
    for _ in range(5):
        batch = default_collate(batch_items)
    rows["collate"] = {"ms": 1e3 * (time.perf_counter() - t0) / 5, "batch": bs,
                       "mb": sum(v.numel() * v.element_size() for v in batch.values()) / 2**20}
    _log(f"  collate   {rows['collate']['ms']:8.2f} ms per batch of {bs} ({rows['collate']['mb']:.1f} MB)")

    small = _small(config)
    small_ds = open_dataset(EllipsoidTrajectories(num_shapes=2, num_stages=4, num_surface=small.data.num_surface,
                                                  num_queries=small.data.num_queries,
                                                  num_on_surface=small.data.num_on_surface, sdf_iterations=32), small)
    b = to_device(default_collate([small_ds[0]]), dev)
    torch.manual_seed(config.seed)
    model = build_model(small.model).to(dev).train()
    amp = config.bf16 and dev.type == "cuda" and torch.cuda.is_bf16_supported()

    def step() -> None:
        with torch.autocast(device_type=dev.type, dtype=torch.bfloat16, enabled=amp):
            loss = _step(model, b, small)
        loss.backward()

    for _ in range(2):
        step()
    with torch.autocast(device_type=dev.type, dtype=torch.bfloat16, enabled=amp):
        loss, fwd = _top_level_ops(lambda: _step(model, b, small))
    _, bwd = _top_level_ops(loss.backward)
    rows["ops"] = {"forward_and_loss": fwd, "backward": bwd, "total": fwd + bwd, "bf16_autocast": amp}
    _log(f"  ops       {fwd} forward + loss, {bwd} backward")
    times = []
    for _ in range(repeats):
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)
        t0 = time.perf_counter()
        step()
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)
        times.append(time.perf_counter() - t0)
    ms = 1e3 * float(np.median(times))
    rows["dispatch"] = {"ms": ms, "us_per_op": 1e3 * ms / (fwd + bwd), "repeats": repeats,
                        "width": small.model.width, "num_latents": small.model.num_latents}
    _log(f"  dispatch  {ms:8.2f} ms per forward + backward at negligible sizes ({rows['dispatch']['us_per_op']:.1f} "
         "us per operator)")
    return {"device": torch.cuda.get_device_name(dev) if dev.type == "cuda" else platform.processor() or "cpu",
            "torch": torch.__version__, "tiny": tiny, "data": data or "synthetic EllipsoidTrajectories (SuffixInput)",
            "rows": rows}


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--tiny", action="store_true", help="the cpu-smoke preset's C-VAE-I sizes (CPU check)")
    p.add_argument("--data", default=None, help="a `vnc-warp dataset` folder instead of the synthetic items")
    p.add_argument("--items", type=int, default=64, help="items timed in the item row")
    p.add_argument("--repeats", type=int, default=7, help="timed steps of the dispatch row")
    p.add_argument("--out", type=Path, default=None, help="folder for step_host.json")
    a = p.parse_args(argv)
    if a.items < 1 or a.repeats < 1:
        p.error(f"--items and --repeats must be >= 1, got {a.items} and {a.repeats}")
    t0 = time.perf_counter()
    report = run(device=a.device, tiny=a.tiny, data=a.data, items=a.items, repeats=a.repeats)
    report["wall_s"] = time.perf_counter() - t0
    report["command"] = " ".join(["python -m bench.step_host", *(argv if argv is not None else sys.argv[1:])])
    _log(f"host work per C-VAE-I step on {report['device']} ({report['wall_s']:.0f} s)")
    if a.out is not None:
        a.out.mkdir(parents=True, exist_ok=True)
        (a.out / "step_host.json").write_text(json.dumps(report, indent=2) + "\n")
        _log(f"wrote {a.out / 'step_host.json'}")
    return report


if __name__ == "__main__":
    main()
