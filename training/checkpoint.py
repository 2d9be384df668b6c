"""Checkpoints: tensors and primitive types only, loadable with ``torch.load(weights_only=True)``.

A checkpoint is a dict::

    {"format": "vnc-warp-checkpoint", "version": 1,
     "config": TrainConfig.to_dict(), "model": state_dict,
     "optimizer": state_dict | None, "scheduler": state_dict | None,
     "step": int, "epoch": int, "batch_in_epoch": int, "world_size": int,
     "rng": [per-rank {"torch", "cuda", "numpy", "python"}] | None,
     "window": [per-rank {"sums": [5 floats], "steps": int}] | None}

``window`` (the loss sums of the log window under way, so that a resumed run logs the rows an uninterrupted
one would) is absent from checkpoints written before it existed; they load all the same.

Writes are atomic (temporary file in the same folder, then ``os.replace``), so a run killed while
saving leaves the previous checkpoint intact.
"""

from __future__ import annotations

import os
import pickle
import random
import re
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn as nn

from .config import TrainConfig

__all__ = ["CheckpointError", "save_checkpoint", "load_checkpoint", "load_model", "rng_state", "set_rng_state",
           "unwrap"]

FORMAT = "vnc-warp-checkpoint"
VERSION = 1
_REQUIRED = ("config", "model", "step")


class CheckpointError(ValueError):
    """A file that is not a usable vnc-warp checkpoint; the message says which file and why."""


def unwrap(model: nn.Module) -> nn.Module:
    """The module inside a DistributedDataParallel wrapper (or the module itself)."""
    return model.module if isinstance(model, nn.parallel.DistributedDataParallel) else model


def rng_state() -> dict[str, Any]:
    """RNG states of torch (CPU and the current CUDA device), NumPy's global generator and Python's ``random``."""
    _, keys, pos, has_gauss, cached = np.random.get_state()
    version, py_state, gauss_next = random.getstate()
    return {
        "torch": torch.get_rng_state(),
        "cuda": torch.cuda.get_rng_state() if torch.cuda.is_available() else None,  # this process's device only
        "numpy": {"keys": torch.from_numpy(keys.astype(np.int64)), "pos": int(pos), "has_gauss": int(has_gauss),
                  "cached_gaussian": float(cached)},
        "python": {"version": int(version), "state": torch.tensor(py_state, dtype=torch.int64),
                   "gauss_next": gauss_next},
    }


def set_rng_state(state: dict[str, Any]) -> None:
    """Restore what :func:`rng_state` returned."""
    torch.set_rng_state(state["torch"].cpu())
    if state["cuda"] is not None and torch.cuda.is_available():
        torch.cuda.set_rng_state(state["cuda"].cpu())
    npst = state["numpy"]
    np.random.set_state(("MT19937", npst["keys"].numpy().astype(np.uint32), npst["pos"], npst["has_gauss"],
                         npst["cached_gaussian"]))
    py = state["python"]
    random.setstate((py["version"], tuple(int(v) for v in py["state"].tolist()), py["gauss_next"]))


def save_checkpoint(path: str | os.PathLike, *, model: nn.Module, config: TrainConfig, step: int,
                    optimizer: torch.optim.Optimizer | None = None, scheduler: Any | None = None, epoch: int = 0,
                    batch_in_epoch: int = 0, world_size: int = 1, rng: list[dict[str, Any]] | None = None,
                    window: list[dict[str, Any]] | None = None) -> Path:
    """Write a checkpoint atomically (``path.tmp`` then ``os.replace``).

    Args:
        path: destination file; its folder is created.
        model: the model (a DDP wrapper is unwrapped).
        config: the run's configuration (stored as a dict).
        step: optimiser steps done.
        optimizer, scheduler: their state dicts are stored when given.
        epoch, batch_in_epoch: data-loader position (batches of ``epoch`` already consumed).
        world_size: processes of the run.
        rng: per-rank :func:`rng_state` dicts.
        window: per-rank loss sums of the log window under way (``{"sums": [...], "steps": n}``).

    Returns:
        The checkpoint path.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {
        "format": FORMAT,
        "version": VERSION,
        "config": config.to_dict(),
        "model": unwrap(model).state_dict(),
        "optimizer": optimizer.state_dict() if optimizer is not None else None,
        "scheduler": scheduler.state_dict() if scheduler is not None else None,
        "step": int(step),
        "epoch": int(epoch),
        "batch_in_epoch": int(batch_in_epoch),
        "world_size": int(world_size),
        "rng": rng,
        "window": window,
    }
    tmp = path.with_name(path.name + ".tmp")
    torch.save(state, tmp)
    os.replace(tmp, path)
    return path


def load_checkpoint(path: str | os.PathLike, *, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """Read and check a checkpoint with ``torch.load(weights_only=True)``.

    Raises:
        FileNotFoundError: no such file (or a folder without ``checkpoints/last.pt``).
        CheckpointError: unreadable, not a vnc-warp checkpoint, or missing entries.
    """
    path = Path(path)
    if path.is_dir():
        candidate = path / "checkpoints" / "last.pt"
        if not candidate.is_file():
            raise FileNotFoundError(f"{path} is a folder without checkpoints/last.pt; pass a checkpoint file")
        path = candidate
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint not found: {path}")
    try:
        state = torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as exc:
        raise CheckpointError(f"{path}: cannot read checkpoint: not a vnc-warp checkpoint ({_torch_reason(exc)}); "
                              "one holds only tensors and plain values, and nothing else is ever loaded") from None
    except Exception as exc:  # torch raises several types for truncated or foreign files
        raise CheckpointError(f"{path}: cannot read checkpoint, truncated or not a torch file "
                              f"({type(exc).__name__}: {_torch_reason(exc)})") from None
    if not isinstance(state, dict) or state.get("format") != FORMAT:
        raise CheckpointError(f"{path}: not a vnc-warp checkpoint (no format={FORMAT!r} entry)")
    if state.get("version") != VERSION:
        raise CheckpointError(f"{path}: checkpoint version {state.get('version')!r}, this code reads {VERSION}")
    missing = [k for k in _REQUIRED if k not in state]
    if missing:
        raise CheckpointError(f"{path}: checkpoint lacks {', '.join(missing)}")
    return state


def _torch_reason(exc: BaseException) -> str:
    """The part of torch's message that says what is wrong with the file, without its advice: torch suggests
    loading with ``weights_only=False``, which runs whatever code the file holds."""
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    keep = [line for line in lines if not _ADVICE.search(line)]
    text = " ".join(keep) or type(exc).__name__
    first = text.split(". ")[0]
    return first[:300]


_ADVICE = re.compile(r"weights.only|torch\.load|file an issue|documentation|trusted source|likely succeed", re.I)


def load_model(path: str | os.PathLike, *, device: str | torch.device = "cpu") -> tuple[nn.Module, TrainConfig]:
    """The model of a checkpoint, in eval mode on ``device``, and its configuration.

    Raises:
        FileNotFoundError, CheckpointError: see :func:`load_checkpoint`; CheckpointError also when the
            weights do not fit the stored configuration.
    """
    from .model import build_model

    state = load_checkpoint(path)
    try:
        config = TrainConfig.from_dict(state["config"])
    except ValueError as exc:
        raise CheckpointError(f"{path}: stored config is invalid ({exc})") from exc
    model = build_model(config.model, load_pretrained=False)
    try:
        model.load_state_dict(state["model"])
    except RuntimeError as exc:
        raise CheckpointError(f"{path}: weights do not match the stored model config ({exc})") from exc
    return model.to(device).eval(), config
