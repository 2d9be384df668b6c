"""Training loop of the C-VAE (Sec. 3.3) and the plain VecSet VAE.

One process or many: launched with ``torchrun`` (``WORLD_SIZE`` > 1 in the environment), the loop
joins the process group (NCCL on GPUs, gloo on CPU), wraps the model in DistributedDataParallel and
shards the data with a DistributedSampler; rank 0 alone logs and writes checkpoints. On CUDA with
``config.bf16`` the forward pass runs under bf16 autocast (float32 where precision matters: the SDF
head, the losses and the eikonal gradient norm); GPUs without bf16 fall back to float32 with a warning.

Data: any map-style Dataset whose items are dicts with ``surface`` (Ns, 6), ``queries`` (Nq, 3),
``tsdf`` (Nq,), ``near`` (Nq,) bool and ``t`` () (the contract of
:class:`vnc_warp.training.data.TrajectoryDataset`; ``shape_id`` and ``stage`` too for
``data.encoder_input="stage0"``, ``on_surface`` (S, 6) for the surface and normal terms). The C-VAEs encode the detailed stage-0 surface of a trajectory and
decode the shape at the item's time t (:class:`Stage0Input`), as ``vnc-warp generate`` does; the
plain VAE auto-encodes every item (``data.encoder_input="item"``).

A run folder holds ``config.json``, ``log.jsonl`` (one row per ``log_every`` steps: step, epoch,
loss terms, beta_kl, lr, grad_norm, samples/s, and ``eval_tsdf``: L_tsdf of the step's last batch decoded as
inference decodes, in eval mode from the posterior mean, beside ``tsdf`` decoded from posterior samples) and
``checkpoints/last.pt``. Resuming continues from
``checkpoints/last.pt`` exactly: model, optimiser, scheduler, per-rank RNG states, the data-loader
position and the partly filled log window are restored, so the losses equal those of an uninterrupted
run (given items that are a deterministic function of their epoch and index, as every dataset here is, or
``num_workers=0``). One DataLoader serves the whole run: its workers persist across epochs and learn each item's
epoch from the sampler's key ``(epoch, index)``, not from ``set_epoch`` in the main process.

Run control (nothing lost, nothing silently wrong):

* A run folder that holds a checkpoint is resumed, never overwritten: starting over takes ``restart=True``
  (``--restart``). ``resume=True`` insists on a checkpoint; ``resume=False`` refuses a folder that has one.
* On resume the stored settings are compared with the given ones. Settings that only change how a run goes
  (:data:`RUNTIME_KEYS`: workers, log and checkpoint intervals, bf16) may differ; the schedule
  (:data:`SCHEDULE_KEYS`: length, warm-ups, final lr ratio, KL curriculum) may change and is then followed
  from the checkpoint's step on, with a warning that says so; any other difference (the learning rate, the
  batch size, the model, ...) is refused, listed in the message, instead of being mixed into the stored run.
* SIGINT or SIGTERM ends the run at the end of the current step with a checkpoint (every process agrees on the
  step at the next log step under torchrun, whose agent waits 30 s before it kills), then raises
  :class:`TrainingInterrupted`; a second signal of the same kind stops at once (the last checkpoint is intact,
  writes being atomic).
* A ``deadline`` (a :func:`time.monotonic` time) ends the run the same way, with a checkpoint at the end of the
  first step past it (under torchrun, of the first log step past it), and returns with ``stopped="deadline"``
  instead of raising: a run split over calls of bounded length (``vnc-warp experiment --max-minutes``) is the
  run trained in one go.
* A non-finite loss stops the run (:class:`TrainingError`) at the next log or checkpoint step, before anything is
  saved, naming the first bad step and the sample files of its batch; samples are checked for NaN when read.
"""

from __future__ import annotations

import itertools
import json
import math
import os
import random
import signal
import threading
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import torch
import torch.distributed as dist
from torch.nn.parallel import DistributedDataParallel
from torch.utils.data import DataLoader, Dataset, Sampler
from torch.utils.data.distributed import DistributedSampler
from tqdm.auto import tqdm

from vnc_warp._device import torch_device as resolve_device  # the library's one torch device resolver
from vnc_warp._files import output_dir, write_bytes

from .checkpoint import load_checkpoint, rng_state, save_checkpoint, set_rng_state, unwrap
from .config import TrainConfig
from .losses import cvae_loss, gradient_queries, kl_weight_at, tsdf_loss
from .model import build_model

__all__ = ["train", "train_step", "to_device", "open_dataset", "Stage0Input", "SuffixInput", "Symmetric", "lr_factor", "resolve_device", "REQUIRED_KEYS", "TrainingError",
           "TrainingInterrupted", "RUNTIME_KEYS", "SCHEDULE_KEYS"]

REQUIRED_KEYS = ("surface", "queries", "tsdf", "near", "t")
OPTIONAL_KEYS = ("on_surface",)
_TERMS = ("loss", "tsdf", "kl", "eik", "surf", "normal")
#: Settings a resumed run may change freely: how it runs, not what it computes.
RUNTIME_KEYS = ("name", "data.num_workers", "log_every", "ckpt_every", "bf16")
#: Settings a resumed run may change, stated in a warning: functions of the step, followed from the resume step on.
SCHEDULE_KEYS = ("optim.total_steps", "optim.warmup_steps", "optim.min_lr_ratio", "loss.kl_schedule",
                 "loss.kl_weight_start", "loss.kl_warmup_start", "loss.kl_warmup_steps")
#: Batches each DataLoader worker keeps in flight (torch's default is 2): a slow item (a cache miss, a large
#: mesh) is absorbed instead of stalling the step.
PREFETCH_BATCHES = 4


class TrainingError(ValueError):
    """A run that cannot start or go on as asked (a folder holding another run, refused setting changes, a
    non-finite loss); the message says what and how to proceed."""


class TrainingInterrupted(KeyboardInterrupt):
    """SIGINT or SIGTERM ended the run after a checkpoint was written; the message names the step and file."""


def _item_ids(base: Dataset) -> list[tuple[int, int]]:
    """``(shape_id, stage)`` of every item of ``base``: from ``base.item_ids()`` when it exists, otherwise from
    reading every item once."""
    if hasattr(base, "item_ids"):
        return [(int(s), int(st)) for s, st in base.item_ids()]
    return [(int(it["shape_id"]), int(it["stage"])) for it in (base[i] for i in range(len(base)))]


def _surface(base: Dataset, i: int) -> torch.Tensor:
    """``base[i]["surface"]``, through ``base.surface(i)`` when the dataset can draw it alone (half a
    :class:`TrajectoryDataset` item's cost: no queries, labels or fresh points)."""
    return base.surface(i) if hasattr(base, "surface") else base[i]["surface"]


class Stage0Input(Dataset):
    """The items of ``base`` with ``surface`` taken from the same shape's stage 0 (t = 1).

    The C-VAE encodes the detailed input and decodes the shape at time t (Sec. 3.3, Fig. 9b), so
    the encoder input of every stage is its trajectory's stage-0 surface. ``(shape_id, stage)`` of the
    items come from ``base.item_ids()`` when it exists, otherwise from reading every item once.
    """

    def __init__(self, base: Dataset) -> None:
        self.base = base
        self.ids = _item_ids(base)
        stage0 = {sid: i for i, (sid, st) in enumerate(self.ids) if st == 0}
        missing = sorted({sid for sid, _ in self.ids} - set(stage0))
        if missing:
            raise ValueError(f"shape id(s) {missing[:5]} have no stage-0 item, the encoder input of "
                             "data.encoder_input='stage0'")
        self.source = [stage0[sid] for sid, _ in self.ids]

    def __len__(self) -> int:
        return len(self.source)

    def set_epoch(self, epoch: int) -> None:
        if hasattr(self.base, "set_epoch"):
            self.base.set_epoch(epoch)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        item = dict(self.base[i])
        if self.source[i] != i:
            item["surface"] = _surface(self.base, self.source[i])
        return item


class SuffixInput(Stage0Input):
    """The items of ``base`` encoded from an earlier stage of their own trajectory, at the time relative to it.

    Item ``i`` (stage j of a shape, time ``t_j``) takes the surface of stage s <= j of the same shape, stage 0
    with probability ``stage0_share`` and otherwise one of the stages 1..j drawn uniformly, and its ``t`` becomes
    ``t_j / t_s``. Eq. (7) measures time as the share of the start's total VNC-AUC left, ``t = S / S_init``; the
    trajectory that starts at stage s has ``S_init = S_s`` and passes stage j at ``S_j / S_s = t_j / t_s``, with
    equal stage budgets again (``1 - (j - s) / (N - s)`` for a balanced flow). So every stage is an encoder input
    with a true target at every later time, not only the ~one stage 0 per shape that :class:`Stage0Input` shows
    the encoder. With ``detail_share`` > 0 an item is, with that probability, its shape's stage 0 encoded from
    itself at t = 1 instead (the detailed input auto-encoded: the t = 1 end of the task, which the draw above
    gives only the ~1/(N+1) stage-0 items, as a plain VAE's uniform items do). The draw depends on
    ``(seed, epoch, i)`` only (reproducible, resumable, worker-safe); with ``detail_share`` = 0 it is the draw of
    the plain suffix. Needs the stages' times: ``base.stage_times()`` when it exists, otherwise the items' ``t``
    read once.

    Args:
        base: the trajectory items (``shape_id``, ``stage``, ``t``, ``surface``, ...).
        stage0_share: probability of encoding stage 0, as at inference.
        seed: base seed of the draws.
        detail_share: probability that an item is replaced by its shape's stage 0 at t = 1.
    """

    def __init__(self, base: Dataset, *, stage0_share: float = 0.5, seed: int = 0, detail_share: float = 0.0) -> None:
        super().__init__(base)
        if not 0.0 <= stage0_share <= 1.0:
            raise ValueError(f"SuffixInput: stage0_share must be in [0, 1], got {stage0_share}")
        if not 0.0 <= detail_share <= 1.0:
            raise ValueError(f"SuffixInput: detail_share must be in [0, 1], got {detail_share}")
        self.stage0_share, self.seed, self.epoch = float(stage0_share), int(seed), 0
        self.detail_share = float(detail_share)
        times = base.stage_times() if hasattr(base, "stage_times") else [float(base[i]["t"]) for i in range(len(base))]
        first: dict[tuple[int, int], int] = {}
        for i, key in enumerate(self.ids):
            first.setdefault(key, i)
        self.first = first
        self.time = {key: float(times[i]) for key, i in first.items()}
        # A stage at t = 0 (an exact base shape) starts no suffix: t_j / t_s has no value there.
        stages: dict[int, list[int]] = {}
        for sid, st in first:
            if self.time[(sid, st)] > 0.0:
                stages.setdefault(sid, []).append(st)
        self.earlier = {key: [s for s in sorted(stages.get(key[0], [])) if 0 < s <= key[1]] for key in first}

    def set_epoch(self, epoch: int) -> None:
        super().set_epoch(epoch)
        self.epoch = int(epoch)

    def draw(self, i: int) -> tuple[int, int]:
        """``(target, start)`` of item ``i`` in this epoch: the index of the item it trains on (``i``, or its
        shape's stage 0 under ``detail_share``) and the stage whose surface is encoded."""
        sid, st = self.ids[i]
        earlier = self.earlier[(sid, st)]
        rng = np.random.default_rng([self.seed, self.epoch, int(i), 7])
        if self.detail_share > 0.0 and st != 0 and rng.random() < self.detail_share:
            return self.first[(sid, 0)], 0
        if not earlier or rng.random() < self.stage0_share:
            return int(i), 0
        return int(i), int(earlier[rng.integers(len(earlier))])

    def start(self, i: int) -> int:
        """The stage whose surface item ``i`` is encoded from, in this epoch."""
        return self.draw(i)[1]

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        i, s = self.draw(i)
        sid, st = self.ids[i]
        if s == 0:
            return super().__getitem__(i)
        item = dict(self.base[i])
        item["surface"] = _surface(self.base, self.first[(sid, s)])
        t = min(1.0, self.time[(sid, st)] / self.time[(sid, s)])
        item["t"] = torch.tensor(t, dtype=torch.float32)
        return item


# The 8 symmetries of the square [-1, 1]^2 in the horizontal (x, z) plane, y (up) fixed: quarter turns, mirrored
# or not. Each maps the box [-1, 1]^3 onto itself and keeps distances, so TSDF values stay exact.
_SQUARE = [np.array([[c, 0, -s], [0, 1, 0], [s, 0, c]], dtype=np.float32) @ np.diag([m, 1, 1]).astype(np.float32)
           for c, s in ((1, 0), (0, 1), (-1, 0), (0, -1)) for m in (1, -1)]


class Symmetric(Dataset):
    """The items of ``base`` under one of the 8 symmetries of the box's horizontal square, drawn per item.

    The same matrix moves the encoder surface, the queries and the on-surface points (positions and normals), so
    the TSDF targets, the ``near`` flags and ``t`` hold as they are. The draw depends on ``(seed, epoch, i)``.
    """

    def __init__(self, base: Dataset, *, seed: int = 0) -> None:
        self.base, self.seed, self.epoch = base, int(seed), 0

    def __len__(self) -> int:
        return len(self.base)

    def set_epoch(self, epoch: int) -> None:
        if hasattr(self.base, "set_epoch"):
            self.base.set_epoch(epoch)
        self.epoch = int(epoch)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        item = dict(self.base[i])
        k = int(np.random.default_rng([self.seed, self.epoch, int(i), 8]).integers(len(_SQUARE)))
        if k == 0:
            return item
        r = torch.from_numpy(_SQUARE[k].T.copy())  # row vectors: p' = p @ R^T
        item["queries"] = item["queries"] @ r
        for key in ("surface", "on_surface"):
            if key in item:
                v = item[key]
                item[key] = torch.cat([v[:, :3] @ r, v[:, 3:6] @ r, v[:, 6:]], dim=1)
        return item


def open_dataset(data: str | os.PathLike | Dataset, config: TrainConfig, *, split: str = "train") -> Dataset:
    """The training dataset: ``data`` itself when it is a Dataset, else a ``TrajectoryDataset`` over
    the folder ``data``; wrapped in :class:`Stage0Input` or :class:`SuffixInput` by ``config.data.encoder_input``
    and in :class:`Symmetric` with ``config.data.symmetry``.

    Raises:
        FileNotFoundError: the folder or its ``index.json`` is missing.
        ValueError: ``data`` is already a :class:`Stage0Input`, :class:`SuffixInput` or :class:`Symmetric`.
    """
    if isinstance(data, (Stage0Input, Symmetric)):
        # wrapping twice draws encoder inputs of encoder inputs and reads every item up front (no item_ids)
        raise ValueError(f"open_dataset: the dataset is already wrapped ({type(data).__name__}); pass the items it "
                         "wraps, and config.data wraps them")
    if isinstance(data, Dataset):
        dataset = data
    else:
        root = Path(data)
        if not root.is_dir():
            raise FileNotFoundError(f"data folder not found: {root}")
        if not (root / "index.json").is_file():
            raise FileNotFoundError(f"{root}: no index.json, so not a trajectory dataset folder "
                                    "(build one with `vnc-warp dataset`)")
        from .data import TrajectoryDataset

        dataset = TrajectoryDataset(root, num_surface=config.data.num_surface, num_queries=config.data.num_queries,
                                    near_fraction=config.data.near_fraction,
                                    num_on_surface=config.data.num_on_surface,
                                    fresh_fraction=config.data.fresh_fraction, split=split, seed=config.seed)
    d = config.data
    if d.encoder_input == "stage0":
        dataset = Stage0Input(dataset)
    elif d.encoder_input == "suffix":
        dataset = SuffixInput(dataset, stage0_share=d.stage0_share, seed=config.seed,
                              detail_share=d.detail_share)
    return Symmetric(dataset, seed=config.seed) if d.symmetry else dataset


def lr_factor(step: int, *, warmup_steps: int, total_steps: int, min_lr_ratio: float) -> float:
    """Learning-rate multiplier after ``step`` optimiser steps: linear warm-up, then cosine to ``min_lr_ratio``."""
    if step < warmup_steps:
        return (step + 1) / warmup_steps
    progress = min((step - warmup_steps) / max(total_steps - warmup_steps, 1), 1.0)
    return min_lr_ratio + (1.0 - min_lr_ratio) * 0.5 * (1.0 + math.cos(math.pi * progress))


@dataclass
class _Dist:
    rank: int
    world_size: int
    local_rank: int
    device: torch.device
    owns_group: bool

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    def barrier(self) -> None:
        if self.world_size > 1:
            dist.barrier()


def _setup_distributed(device: str | torch.device | None) -> _Dist:
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    local = int(os.environ.get("LOCAL_RANK", str(rank)))
    dev = resolve_device(device, local_rank=local if world > 1 else None)
    owns = False
    if dev.type == "cuda":
        # The current device is where NCCL collectives, pinned-memory copies and the CUDA RNG state
        # saved in checkpoints (rng_state) refer to.
        torch.cuda.set_device(dev)
    if world > 1:
        if not dist.is_initialized():
            dist.init_process_group(backend="nccl" if dev.type == "cuda" else "gloo")
            owns = True
    return _Dist(rank, world, local, dev, owns)


class _EpochItems(Dataset):
    """The items of ``base`` keyed ``(epoch, i)``: item ``i`` of ``base`` set to that epoch, in whichever process
    reads it. Persistent DataLoader workers keep their own copy of the dataset, which ``set_epoch`` in the main
    process never reaches; the key carries the epoch to them."""

    def __init__(self, base: Dataset) -> None:
        self.base = base
        self.epoch: int | None = None

    def __len__(self) -> int:
        return len(self.base)

    def __getitem__(self, key: tuple[int, int]) -> dict[str, torch.Tensor]:
        epoch, i = key
        if epoch != self.epoch and hasattr(self.base, "set_epoch"):
            self.base.set_epoch(epoch)
        self.epoch = epoch
        return self.base[i]


class _EpochSampler(Sampler):
    """``(epoch, i)`` for the indices of ``base`` in the epoch set by :meth:`start`, after the first ``skip``
    (resuming inside an epoch): one sampler, so one DataLoader and its persistent workers, for a whole run."""

    def __init__(self, base: DistributedSampler) -> None:
        self.base = base
        self.epoch = self.skip = 0

    def start(self, epoch: int, skip: int) -> None:
        """The next iteration yields epoch ``epoch``'s indices after the first ``skip``."""
        self.epoch, self.skip = int(epoch), int(skip)
        self.base.set_epoch(self.epoch)

    def __iter__(self) -> Iterator[tuple[int, int]]:
        return ((self.epoch, i) for i in itertools.islice(iter(self.base), self.skip, None))

    def __len__(self) -> int:
        return max(len(self.base) - self.skip, 0)


def _data_loader(dataset: Dataset, sampler: _EpochSampler, config: TrainConfig, device: torch.device, *,
                 seed: int) -> DataLoader:
    """The run's one DataLoader of ``_EpochItems(dataset)`` in ``sampler``'s order.

    With workers, they persist across epochs (no start-up, no re-read cache per epoch) and each keeps
    ``PREFETCH_BATCHES`` batches in flight; batches come in pinned memory for a CUDA ``device``. Items equal those
    read in the main process when they are a function of ``(epoch, i)``; the workers' own RNGs are seeded once,
    from ``seed``.
    """
    workers = config.data.num_workers
    extra = {"persistent_workers": True, "prefetch_factor": PREFETCH_BATCHES} if workers > 0 else {}
    return DataLoader(_EpochItems(dataset), batch_size=config.data.batch_size, sampler=sampler, num_workers=workers,
                      drop_last=True, generator=torch.Generator().manual_seed(seed), pin_memory=device.type == "cuda",
                      worker_init_fn=_quiet_worker, **extra)


def _seed_all(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def _check_batch(batch: Any) -> None:
    if not isinstance(batch, dict):
        raise ValueError(f"dataset items must be dicts with keys {REQUIRED_KEYS}, got {type(batch).__name__}")
    missing = [k for k in REQUIRED_KEYS if k not in batch]
    if missing:
        raise ValueError(f"dataset items lack key(s) {missing}; required: {REQUIRED_KEYS}")
    b, nq = batch["queries"].shape[:2]
    expected = {"surface": (b, None, 6), "queries": (b, nq, 3), "tsdf": (b, nq), "near": (b, nq), "t": (b,)}
    for key, shape in expected.items():
        got = tuple(batch[key].shape)
        if len(got) != len(shape) or any(s is not None and s != g for s, g in zip(shape, got)):
            raise ValueError(f"dataset key {key!r}: batched shape {got}, expected {shape} (None: any)")
    if batch["near"].dtype != torch.bool:
        raise ValueError(f"dataset key 'near' must be bool, got {batch['near'].dtype}")
    if "on_surface" in batch and (batch["on_surface"].ndim != 3 or tuple(batch["on_surface"].shape[::2]) != (b, 6)):
        raise ValueError(f"dataset key 'on_surface': batched shape {tuple(batch['on_surface'].shape)}, "
                         f"expected ({b}, S, 6)")


class _Log:
    """Append-only JSONL log on rank 0; on resume, rows after the checkpoint's step are dropped."""

    def __init__(self, path: Path, *, keep_until: int | None) -> None:
        self.path = path
        if keep_until is not None and path.is_file():
            rows = [line for line in path.read_text().splitlines() if line.strip()]
            kept = [r for r in rows if json.loads(r).get("step", 0) <= keep_until]
            write_bytes(path, "".join(r + "\n" for r in kept).encode())
        elif keep_until is None:
            write_bytes(path, b"")

    def write(self, row: dict[str, Any]) -> None:
        with self.path.open("a") as f:
            f.write(json.dumps(row) + "\n")


def _optimizer(model: torch.nn.Module, config: TrainConfig) -> tuple[torch.optim.Optimizer, Any, list]:
    o = config.optim
    params = [p for p in model.parameters() if p.requires_grad]
    groups = [{"params": [p for p in params if p.ndim >= 2], "weight_decay": o.weight_decay},
              {"params": [p for p in params if p.ndim < 2], "weight_decay": 0.0}]
    opt = torch.optim.AdamW(groups, lr=o.lr, betas=o.betas, eps=o.eps)

    def schedule(step: int) -> float:
        return lr_factor(step, warmup_steps=o.warmup_steps, total_steps=o.total_steps, min_lr_ratio=o.min_lr_ratio)

    return opt, torch.optim.lr_scheduler.LambdaLR(opt, schedule), params


def train(config: TrainConfig, *, data: str | os.PathLike | Dataset, out_dir: str | os.PathLike,
          device: str | torch.device | None = None, resume: bool | None = None, restart: bool = False,
          stop_at: int | None = None, deadline: float | None = None, progress: bool = True) -> dict[str, Any]:
    """Train the model ``config.model`` describes (see the module docstring for run control).

    Args:
        config: the run configuration (``optim.total_steps`` sets the schedule and the default end).
        data: a dataset folder (read with ``TrajectoryDataset``) or any Dataset with the contract's keys.
        out_dir: run folder (created; checked writable before anything is computed).
        device: None (CUDA when present), ``"cpu"``, ``"cuda"``, ``"cuda:1"``...
        resume: None: continue from ``out_dir/checkpoints/last.pt`` when it exists, else start; True: continue,
            a checkpoint must exist; False: start, refusing a folder that holds a checkpoint.
        restart: discard the folder's checkpoint and log and start from step 0 (not with ``resume=True``).
        stop_at: stop after this step (>= 1; the schedule still follows ``total_steps``); default
            ``total_steps``. A run already at or past it trains nothing.
        deadline: a :func:`time.monotonic` time; the first step that ends after it ends the run with a checkpoint
            (under torchrun, the first log step after it), as a signal does but without raising: the summary's
            ``stopped`` says so, and training the same run again resumes it exactly.
        progress: show a tqdm bar on rank 0.

    Returns:
        Summary of this process: ``rank``, ``world_size``, ``device``, ``start_step``, ``step``,
        ``checkpoint`` (path), ``last`` (loss terms of the last logged window), ``samples_per_s``
        (mean over the run, all ranks), ``stopped`` (``"deadline"`` when the deadline ended the run before its
        end, else None).

    Raises:
        FileNotFoundError: missing data folder, or ``resume=True`` without a checkpoint.
        OSError: ``out_dir`` cannot be created or written to.
        CheckpointError: unreadable checkpoint.
        TrainingError: ``resume=False`` on a folder with a checkpoint, settings changed on resume beyond the
            schedule (listed), or a non-finite loss (step and sample files named).
        TrainingInterrupted: SIGINT or SIGTERM, after the checkpoint was written.
        ValueError: invalid config or ``stop_at``, dataset items that break the contract, a dataset smaller than
            one global batch, or a checkpoint whose model config differs from ``config.model``.
    """
    config.validate()
    if stop_at is not None and (isinstance(stop_at, bool) or int(stop_at) != stop_at or stop_at < 1):
        raise ValueError(f"stop_at must be a step >= 1, got {stop_at!r}")
    if restart and resume:
        raise ValueError("resume and restart exclude each other: resume continues the run, restart discards it")
    ctx = _setup_distributed(device)
    try:
        return _run(config, data, Path(out_dir), ctx, resume=resume, restart=restart, stop_at=stop_at,
                    deadline=deadline, progress=progress)
    finally:
        if ctx.owns_group:
            dist.destroy_process_group()


def _flat(d: dict, prefix: str = "") -> dict[str, Any]:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def _setting_changes(stored: dict, new: dict) -> tuple[list[str], list[str]]:
    """The settings that differ between a checkpoint's config and the given one, as ``"key: old -> new"``:
    (refused, schedule)."""
    a, b = _flat(stored), _flat(new)
    refused, schedule = [], []
    for key in sorted(set(a) | set(b)):
        if a.get(key) == b.get(key) or key in RUNTIME_KEYS:
            continue
        (schedule if key in SCHEDULE_KEYS else refused).append(f"{key}: {a.get(key)!r} -> {b.get(key)!r}")
    return refused, schedule


class _Signals:
    """SIGINT / SIGTERM turned into a request to stop at the end of the current step (main thread only); a second
    signal of the same kind raises KeyboardInterrupt at once. A signal the process was told to ignore (a job started
    in the background by a shell) stays ignored."""

    def __init__(self) -> None:
        self.received: int | None = None
        self._old: dict[int, Any] = {}

    def __enter__(self) -> "_Signals":
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                if signal.getsignal(sig) is not signal.SIG_IGN:
                    self._old[sig] = signal.signal(sig, self._handle)
        return self

    def _handle(self, signum, frame) -> None:
        if self.received == signum:
            raise KeyboardInterrupt(f"second {signal.Signals(signum).name}: stopped without a new checkpoint")
        self.received = signum

    def __exit__(self, *exc) -> None:
        for sig, old in self._old.items():
            signal.signal(sig, old)


def _quiet_worker(worker_id: int) -> None:
    """DataLoader workers leave SIGINT and SIGTERM to the main process, which stops the run cleanly (a Ctrl-C
    reaches every process of the terminal's group)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)


def _item_files(dataset: Dataset, shape_ids, stages) -> list[str]:
    """What a batch was made of, for messages: the sample files of a TrajectoryDataset, else shape ids and stages."""
    base = getattr(dataset, "base", dataset)
    name = getattr(base, "item_file", None)
    pairs = list(zip(shape_ids.tolist(), stages.tolist())) if shape_ids is not None and stages is not None else []
    if not pairs:
        return ["(items without shape_id/stage)"]
    return [name(int(s), int(st)) if name is not None else f"shape {s} stage {st}" for s, st in pairs]


class _Window:
    """Loss sums of the steps since the last log row, and what is needed to name a non-finite step's batch."""

    def __init__(self, device: torch.device, state: dict | None) -> None:
        self.sums = torch.zeros(len(_TERMS) + 1, dtype=torch.float64, device=device)  # _TERMS, grad_norm
        self.steps = 0
        if state and len(state["sums"]) == self.sums.numel():
            self.sums += torch.tensor(state["sums"], dtype=torch.float64, device=device)
            self.steps = int(state["steps"])
        self.losses: list[torch.Tensor] = []
        self.batches: list[tuple[int, Any, Any]] = []

    def add(self, step: int, terms: dict, grad_norm: torch.Tensor, batch: dict) -> None:
        loss = terms["loss"].detach()
        self.sums += torch.stack([*(terms[k].detach() for k in _TERMS), grad_norm.detach()]).double()
        self.steps += 1
        self.losses.append(loss.reshape(1))
        self.batches.append((step, batch.get("shape_id"), batch.get("stage")))

    def first_nonfinite(self) -> tuple[int, float, Any, Any] | None:
        """(step, loss, shape ids, stages) of this process's first non-finite loss since the last check."""
        if not self.losses:
            return None
        values = torch.cat(self.losses)
        batches = self.batches
        self.losses, self.batches = [], []
        bad = torch.nonzero(~torch.isfinite(values)).flatten()
        if bad.numel() == 0:
            return None
        k = int(bad[0])
        step, sids, stages = batches[k]
        return step, float(values[k]), sids, stages

    def state(self) -> dict:
        return {"sums": self.sums.tolist(), "steps": self.steps}

    def reset(self) -> None:
        self.sums.zero_()
        self.steps = 0


def _prepare_folder(out: Path, ckpt_path: Path, ctx: _Dist, resume: bool | None, restart: bool) -> bool:
    """Check the run folder before anything is computed and decide whether to resume (see the module docstring)."""
    if ctx.is_main:
        output_dir(out, what="run folder")
    has = ckpt_path.is_file()
    if resume is True and not has:
        raise FileNotFoundError(f"resume: no checkpoint at {ckpt_path}")
    if has and resume is False and not restart:
        raise TrainingError(f"{out} holds a run (checkpoint {ckpt_path}); resume it, start over with --restart "
                            "(restart=True), or train into a new folder")
    if restart and ctx.is_main:
        for stale in (ckpt_path, ckpt_path.with_name(ckpt_path.name + ".tmp"), out / "log.jsonl"):
            stale.unlink(missing_ok=True)
    ctx.barrier()
    return has and not restart


def _run(config: TrainConfig, data: Any, out: Path, ctx: _Dist, *, resume: bool | None, restart: bool,
         stop_at: int | None, deadline: float | None, progress: bool) -> dict[str, Any]:
    ckpt_path = out / "checkpoints" / "last.pt"
    resuming = _prepare_folder(out, ckpt_path, ctx, resume, restart)
    state = None
    if resuming:
        state = load_checkpoint(ckpt_path)
        if state["config"]["model"] != config.to_dict()["model"]:
            raise ValueError(f"resume: model config of {ckpt_path} differs from the given config")
        # Settings added after the checkpoint was written take their defaults, as from_dict gives them.
        refused, changed = _setting_changes({**_flat(TrainConfig().to_dict()), **_flat(state["config"])},
                                            _flat(config.to_dict()))
        if refused:
            raise TrainingError(f"resume: {ckpt_path} (step {state['step']}) was trained with other settings: "
                                f"{'; '.join(refused)}. Resuming would mix them into the stored run: give the "
                                "stored settings, start over with --restart, or train into a new folder")
        if changed and ctx.is_main:
            warnings.warn(f"resume at step {state['step']}: schedule settings changed ({'; '.join(changed)}); "
                          f"the schedules follow the new settings from step {state['step']} on", stacklevel=3)
    end = config.optim.total_steps if stop_at is None else stop_at
    if state is not None and state["step"] >= end:
        if ctx.is_main:
            warnings.warn(f"{out} is at step {state['step']}, at or past the requested end {end}: nothing to train",
                          stacklevel=3)
        return {"rank": ctx.rank, "world_size": ctx.world_size, "device": str(ctx.device),
                "start_step": state["step"], "step": state["step"], "checkpoint": str(ckpt_path), "last": {},
                "samples_per_s": 0.0, "stopped": None}
    dataset = open_dataset(data, config)
    bs = config.data.batch_size
    if len(dataset) < bs * ctx.world_size:
        raise ValueError(f"dataset has {len(dataset)} items, fewer than one global batch "
                         f"(batch_size {bs} x {ctx.world_size} processes)")
    if ctx.is_main:
        write_bytes(out / "config.json", (json.dumps(config.to_dict(), indent=2) + "\n").encode())

    _seed_all(config.seed)  # identical initial weights on every rank
    model = build_model(config.model).to(ctx.device)
    opt, sched, params = _optimizer(model, config)
    step = epoch = batch_in_epoch = 0
    if state is not None:
        unwrap(model).load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])
        sched.load_state_dict(state["scheduler"])
        step, epoch, batch_in_epoch = state["step"], state["epoch"], state["batch_in_epoch"]
        if changed:
            # the stored learning rate is the old schedule's; the new one takes over at this step
            sched = torch.optim.lr_scheduler.LambdaLR(opt, sched.lr_lambdas, last_epoch=step - 1)
        rngs = state["rng"]
        if rngs is not None and len(rngs) == ctx.world_size:
            set_rng_state(rngs[ctx.rank])
        else:
            warnings.warn(f"resume: checkpoint has RNG states for {len(rngs or [])} process(es), this run has "
                          f"{ctx.world_size}; re-seeding, so the continuation (random draws, data order) is not "
                          "bit-identical", stacklevel=2)
            _seed_all(config.seed + 1000 * ctx.rank + step)
    else:
        _seed_all(config.seed + ctx.rank)
    start_step = step
    if ctx.world_size > 1:
        model = DistributedDataParallel(model, device_ids=[ctx.device.index] if ctx.device.type == "cuda" else None)
    model.train()

    sampler = _EpochSampler(DistributedSampler(dataset, num_replicas=ctx.world_size, rank=ctx.rank, shuffle=True,
                                               seed=config.seed, drop_last=True))
    loader = _data_loader(dataset, sampler, config, ctx.device, seed=config.seed * 1_000_003 + epoch)

    amp = config.bf16 and ctx.device.type == "cuda"
    if amp and not torch.cuda.is_bf16_supported():
        warnings.warn(f"{ctx.device} does not support bf16; training in float32", stacklevel=2)
        amp = False
    log = _Log(out / "log.jsonl", keep_until=step if resuming else None) if ctx.is_main else None
    bar = tqdm(total=end, initial=step, disable=not (progress and ctx.is_main), desc=f"train {config.name}",
               dynamic_ncols=True)
    windows = state.get("window") if state is not None else None
    window = _Window(ctx.device, windows[ctx.rank] if windows and len(windows) == ctx.world_size else None)
    window_t0, run_t0 = time.perf_counter(), time.perf_counter()
    last: dict[str, float] = {}
    checked = False
    saved_at = step
    stop = late = False

    def save() -> None:
        nonlocal saved_at
        _save(ckpt_path, model, config, step, opt, sched, epoch, batch_in_epoch, ctx, window.state())
        saved_at = step

    def overdue() -> bool:
        return deadline is not None and time.monotonic() >= deadline

    def check(signals: _Signals) -> tuple[bool, bool]:
        """Every process's verdict on non-finite losses (raised), stop requests and the deadline since the last
        check: (a signal, the deadline) asks to stop."""
        bad = window.first_nonfinite()
        flags = torch.tensor([bad is not None, signals.received is not None, overdue()], dtype=torch.float64,
                             device=ctx.device)
        if ctx.world_size > 1:
            dist.all_reduce(flags)
        if flags[0] > 0:
            where = "on another process" if bad is None else (
                f"{bad[1]} at step {bad[0]}, batch of {', '.join(_item_files(dataset, bad[2], bad[3]))}")
            kept = f"the last checkpoint ({ckpt_path}, step {saved_at}) is intact" if ckpt_path.is_file() else \
                "no checkpoint was written"
            raise TrainingError(f"non-finite loss {where}; stopped without saving: {kept}. Check those samples "
                                "(`vnc-warp dataset --verify`) or lower optim.lr")
        return bool(flags[1] > 0), bool(flags[2] > 0)

    with _Signals() as signals:
        try:
            while step < end and not (stop or late):
                sampler.start(epoch, batch_in_epoch * bs)
                for batch in loader:
                    if not checked:
                        _check_batch(batch)
                        checked = True
                    b = to_device(batch, ctx.device)
                    terms, grad_norm, lr = train_step(model, b, config, opt, sched, params, step=step, amp=amp)
                    step += 1
                    batch_in_epoch += 1
                    window.add(step, terms, grad_norm, batch)
                    bar.update(1)
                    at_log = step % config.log_every == 0 or step == end
                    at_ckpt = step % config.ckpt_every == 0 or step == end
                    if at_log or at_ckpt or (ctx.world_size == 1 and (signals.received is not None or overdue())):
                        stop, late = check(signals)
                    if at_log:
                        sums = window.sums
                        eval_tsdf = _eval_tsdf(unwrap(model), b, config, amp)
                        if ctx.world_size > 1:
                            dist.all_reduce(sums)
                            dist.all_reduce(eval_tsdf)
                        means = (sums / (window.steps * ctx.world_size)).tolist()
                        elapsed = time.perf_counter() - window_t0
                        last = dict(zip((*_TERMS, "grad_norm"), means))
                        last["eval_tsdf"] = float(eval_tsdf) / ctx.world_size
                        row = {"step": step, "epoch": epoch, **last, "beta_kl": kl_weight_at(step - 1, config.loss),
                               "lr": lr, "samples_per_s": window.steps * bs * ctx.world_size / max(elapsed, 1e-9)}
                        if log is not None:
                            log.write(row)
                            bar.set_postfix(loss=f"{last['loss']:.4g}")
                        window.reset()
                        window_t0 = time.perf_counter()
                    if at_ckpt or stop or late:
                        save()
                    if step >= end or stop or late:
                        break
                else:
                    epoch += 1
                    batch_in_epoch = 0
        finally:
            bar.close()
            # the persistent workers end with their loader, now: they ignore SIGTERM, so workers still alive at
            # the interpreter's exit (a traceback holding this frame) would block it
            del loader
    if stop:
        name = signal.Signals(signals.received).name if signals.received else "a signal on another process"
        raise TrainingInterrupted(f"stopped by {name} at step {step}; checkpoint {ckpt_path} written; run the same "
                                  "command again to resume")
    total_time = time.perf_counter() - run_t0
    return {"rank": ctx.rank, "world_size": ctx.world_size, "device": str(ctx.device), "start_step": start_step,
            "step": step, "checkpoint": str(ckpt_path), "last": last,
            "samples_per_s": (step - start_step) * bs * ctx.world_size / max(total_time, 1e-9),
            "stopped": "deadline" if late and step < end else None}


def to_device(batch: dict[str, torch.Tensor], device: torch.device) -> dict[str, torch.Tensor]:
    """The tensors of a collated batch that the step uses (:data:`REQUIRED_KEYS`, :data:`OPTIONAL_KEYS`), on
    ``device`` (asynchronous copies from the loader's pinned memory)."""
    return {k: batch[k].to(device, non_blocking=True) for k in (*REQUIRED_KEYS, *OPTIONAL_KEYS) if k in batch}


def train_step(model: torch.nn.Module, b: dict[str, torch.Tensor], config: TrainConfig, opt: torch.optim.Optimizer,
               sched: Any, params: list, *, step: int, amp: bool) -> tuple[dict[str, torch.Tensor], torch.Tensor, float]:
    """One optimiser step on a batch already on the model's device (the loop of :func:`train`, and the benchmark's).

    Args:
        model: the model (or its DistributedDataParallel wrapper), in training mode.
        b: the batch from :func:`to_device`.
        config: the run configuration (loss weights, gradient clipping).
        opt, sched, params: the optimiser, its learning-rate schedule and the trained parameters.
        step: optimiser steps taken so far (the beta_kl curriculum).
        amp: run the forward pass under bf16 autocast.

    Returns:
        ``(terms, grad_norm, lr)``: the loss terms of :func:`~vnc_warp.training.losses.cvae_loss`, the gradient
        norm before clipping (() tensors on the device, not synchronised) and the learning rate of this step.
    """
    grad_q = gradient_queries(b, config.loss)
    with torch.autocast(device_type=b["queries"].device.type, dtype=torch.bfloat16, enabled=amp):
        out = model(b["surface"], b["queries"], b["t"], eikonal_queries=None if grad_q is None else grad_q.points)
    terms = cvae_loss(out, b, config.loss, step=step, gradient=grad_q)
    opt.zero_grad(set_to_none=True)
    terms["loss"].backward()
    grad_norm = torch.nn.utils.clip_grad_norm_(params, config.optim.grad_clip or float("inf"))
    lr = sched.get_last_lr()[0]
    opt.step()
    sched.step()
    return terms, grad_norm, lr


@torch.no_grad()
def _eval_tsdf(model: torch.nn.Module, b: dict[str, torch.Tensor], config: TrainConfig, amp: bool) -> torch.Tensor:
    """L_tsdf of one batch decoded as inference decodes: eval mode, the posterior mean, the first FPS point fixed.

    Training decodes posterior samples; a decoder that only works on those shows here as a gap to ``tsdf``.
    """
    model.eval()
    try:
        with torch.autocast(device_type=b["queries"].device.type, dtype=torch.bfloat16, enabled=amp):
            out = model(b["surface"], b["queries"], b["t"])
        return tsdf_loss(out["tsdf"], b["tsdf"], kind=config.loss.tsdf, near=b["near"],
                         near_weight=config.loss.near_weight).double()
    finally:
        model.train()


def _save(path: Path, model: torch.nn.Module, config: TrainConfig, step: int, opt: torch.optim.Optimizer,
          sched: Any, epoch: int, batch_in_epoch: int, ctx: _Dist, window: dict) -> None:
    states = [(rng_state(), window)]
    if ctx.world_size > 1:
        states = [None] * ctx.world_size
        dist.all_gather_object(states, (rng_state(), window))
    if ctx.is_main:
        save_checkpoint(path, model=model, config=config, step=step, optimizer=opt, scheduler=sched, epoch=epoch,
                        batch_in_epoch=batch_in_epoch, world_size=ctx.world_size, rng=[r for r, _ in states],
                        window=[w for _, w in states])
    ctx.barrier()
