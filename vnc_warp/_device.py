"""Device selection shared by every entry point: ``None`` means Warp's preferred device (CUDA if present)."""

from __future__ import annotations

import warp as wp

# Warp's start-up banner and per-module load lines are noise inside a library; users can lower this again.
if wp.config.log_level < wp.LOG_WARNING:
    wp.config.log_level = wp.LOG_WARNING
_initialized = False


def init() -> None:
    """Initialise Warp quietly once."""
    global _initialized
    if not _initialized:
        wp.init()
        _initialized = True


def get_device(device=None) -> wp.Device:
    """Resolve ``device`` (None, "cpu", "cuda", "cuda:0", a ``wp.Device`` or a ``torch.device``)."""
    init()
    if device is None:
        return wp.get_preferred_device()
    if hasattr(device, "type") and not isinstance(device, (str, wp.Device)):  # torch.device
        device = str(device)
        if device == "cuda":
            device = "cuda:0"
    try:
        return wp.get_device(device)
    except Exception as exc:
        raise ValueError(f"unknown or unavailable device {device!r}: {exc}") from exc
