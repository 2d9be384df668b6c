"""Device selection shared by every entry point: ``None`` means Warp's preferred device (CUDA if present)."""

from __future__ import annotations

import ctypes
import os
import sys

import warp as wp

# Warp's start-up banner and per-module load lines are noise inside a library; users can lower this again.
if wp.config.log_level < wp.LOG_WARNING:
    wp.config.log_level = wp.LOG_WARNING
_initialized = False


def _no_cuda_driver() -> bool:
    """True when no CUDA driver library can be loaded: Warp's native start-up then prints a warning to stderr
    (not through Python) about a GPU that this machine does not have."""
    names = {"linux": ("libcuda.so", "libcuda.so.1"), "win32": ("nvcuda.dll",)}.get(sys.platform)
    if names is None:  # macOS: Warp has no CUDA there and prints nothing
        return False
    for name in names:
        try:
            ctypes.CDLL(name)
            return False
        except OSError:
            continue
    return True


def init() -> None:
    """Initialise Warp quietly once (on a machine without a CUDA driver, without Warp's warning about it)."""
    global _initialized
    if _initialized:
        return
    if _no_cuda_driver():
        sys.stderr.flush()
        saved = os.dup(2)
        devnull = os.open(os.devnull, os.O_WRONLY)
        try:
            os.dup2(devnull, 2)
            wp.init()
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            os.close(devnull)
    else:
        wp.init()
    _initialized = True


# at import: any Warp call a user makes after `import vnc_warp` finds Warp initialised, quietly
init()


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
