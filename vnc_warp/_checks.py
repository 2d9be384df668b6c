"""Arguments of the operators checked once, and the warning for a result that can only be zero.

Shared by :mod:`vnc_warp._engine`, :mod:`vnc_warp.operators` and :mod:`vnc_warp.scale` (which import it, never each
other's private helpers).
"""

from __future__ import annotations

import warnings

import numpy as np
import warp as wp

from .mesh import Mesh, MeshInput

__all__ = ["DegenerateResultWarning"]


class DegenerateResultWarning(UserWarning):
    """A result that is zero for a reason outside the surface: no edge in reach, or weights that underflow."""


def host_values(value):
    """A Warp array, torch tensor or array-like as NumPy (a device array is read back)."""
    return value.numpy() if isinstance(value, wp.array) else (
        value.detach().cpu().numpy() if hasattr(value, "detach") else value)


def host_scalar(value, what: str) -> float | None:
    """``value`` as a float when it is a scalar given on the host (checked positive and finite), else None."""
    if isinstance(value, wp.array) or (hasattr(value, "requires_grad") and value.requires_grad) or np.ndim(value) != 0:
        return None
    try:
        v = float(value.detach().cpu() if hasattr(value, "detach") else value)
    except (TypeError, ValueError):
        raise TypeError(f"{what} must be a positive number or an array of per-point values, got {value!r}") from None
    if not (np.isfinite(v) and v > 0.0):
        raise ValueError(f"{what} must be positive and finite, got {v}")
    return v


def host_array(value, count: int, what: str) -> np.ndarray | None:
    """A per-point array given on the host (NumPy, a list, a CPU or CUDA tensor) as (count,) float32, checked positive
    and finite; None for a scalar or a ``wp.array`` (on the device: checked there)."""
    if isinstance(value, wp.array) or np.ndim(value) == 0:
        return None
    arr = np.asarray(value.detach().cpu().numpy() if hasattr(value, "detach") else value, dtype=np.float64)
    if arr.shape != (count,):
        raise ValueError(f"{what}: expected a scalar or shape ({count},), got {arr.shape}")
    bad = np.nonzero(~np.isfinite(arr) | (arr <= 0.0))[0]
    if bad.size:
        raise ValueError(f"{what} must be positive and finite; {bad.size} value(s) are not, e.g. index {int(bad[0])}: "
                         f"{arr[bad[0]]}")
    return arr.astype(np.float32)


def radius_stats(value) -> tuple[float, float] | None:
    """``(max, mean)`` of a scalar or host array of radii (None for a ``wp.array``: its values are on the device)."""
    if isinstance(value, wp.array):
        return None
    arr = np.asarray(value.detach().cpu().numpy() if hasattr(value, "detach") else value, dtype=np.float32)
    return float(arr.max()), float(arr.astype(np.float64).mean())


def per_point(value, count: int, device, what: str, pool=None) -> wp.array:
    """A positive, finite scalar or (count,) array as a float32 wp.array on ``device`` (a scalar's array from
    ``pool``, when given; a ``wp.array`` as it is, its values checked where it is read)."""
    if isinstance(value, wp.array):
        if value.shape != (count,) or value.dtype != wp.float32:
            raise ValueError(f"{what}: expected a ({count},) float32 array, got {value.shape} {value.dtype}")
        return value if value.device == device else value.to(device)
    v = host_scalar(value, what)
    if v is not None:
        if pool is not None:
            arr = pool.empty(count, wp.float32)
            arr.fill_(np.float32(v))
            return arr
        return wp.full(count, np.float32(v), dtype=wp.float32, device=device)
    return wp.array(host_array(value, count, what), dtype=wp.float32, device=device)


def check_kappa(kappa, *, soft: bool) -> float | None:
    """``kappa`` as a float (None for VNC-hard's unweighted operator), or a ValueError."""
    if soft:
        if kappa is None or not kappa > 0.0:
            raise ValueError(f"kappa must be positive for VNC-soft, got {kappa}")
        return float(kappa)
    if kappa is not None and not kappa > 0.0:
        raise ValueError(f"kappa must be positive or None, got {kappa}")
    return None if kappa is None else float(kappa)


def mesh_only(src: MeshInput, op: str, **advanced) -> None:
    """Arguments that address a Mesh's own vertex order (``positions=``, ``tape=``) need a :class:`Mesh`."""
    given = [k for k, v in advanced.items() if v is not None]
    if given and src.kind != "warp":
        raise TypeError(f"{op}: {', '.join(given)}= needs a vw.Mesh (its own vertex order); "
                        "make one with vw.load_mesh(...)")


_warned: set = set()


def warn_once(op: str, reason: str, message: str, stacklevel: int = 4) -> None:
    """A :class:`DegenerateResultWarning`, once per operator and reason in a process (stack: user, operator,
    checker, here)."""
    if (op, reason) not in _warned:
        _warned.add((op, reason))
        warnings.warn(message, DegenerateResultWarning, stacklevel=stacklevel)


def degenerate_reason(mesh: Mesh, tau, kappa: float | None, *, soft: bool) -> tuple[str, str] | None:
    """Why nothing was in reach anywhere: ``("reach", text)`` or ``("kappa", text)``; None when neither explains it."""
    from scipy.spatial import cKDTree

    v = mesh.local_vertices.astype(np.float64)
    e = mesh.topology.interior
    if e.shape[0] == 0:
        return None
    d = cKDTree(0.5 * (v[e[:, 0]] + v[e[:, 1]])).query(v)[0]
    t = np.broadcast_to(np.asarray(host_values(tau), np.float64), d.shape)
    edge = mesh.mean_edge_length
    if soft and (t < d).all():
        return "reach", (f"tau = {_fmt(t)} is below every vertex's distance to its nearest edge midpoint (at least "
                         f"{d.min():.4g}, {d.min() / edge:.2f} mean edge lengths), so no edge is within reach; take "
                         f"tau of a few mean edge lengths (vw.default_scales)")
    if kappa is not None:
        sigma = t / float(kappa)
        ratio = float((d / sigma).min())
        if ratio > 13.0:
            return "kappa", (f"kappa = {kappa:g} makes sigma = tau / kappa = {_fmt(sigma)}, and the nearest edge "
                             f"midpoints are {ratio:.0f} sigma away or more: every Gaussian weight exp(-d^2 / 2 "
                             f"sigma^2) underflows to 0 in float32; the paper uses kappa = 6")
    return None


def warn_if_degenerate(op: str, src: MeshInput, tau, kappa: float | None, n, *, soft: bool = True) -> None:
    """Warn once per operator and reason when no vertex had anything in reach (``n = 0`` everywhere: on a flat
    mesh ``n`` is not zero, so only the reach is tested). Checked where reading ``n`` (a ``wp.array`` or a torch
    tensor) costs nothing: on the CPU, or when the results go to the host anyway."""
    if src.kind == "warp" and n.device.is_cuda:
        return
    if np.any(host_values(n)):
        return
    reason = degenerate_reason(src.mesh, tau, kappa, soft=soft)
    if reason is not None:
        warn_once(op, reason[0], f"{op} on {src.mesh.name}: every vertex got H = 0 and n = 0: {reason[1]}")


def _fmt(a: np.ndarray) -> str:
    a = np.asarray(a)
    lo, hi = float(a.min()), float(a.max())
    return f"{lo:.4g}" if lo == hi else f"{lo:.4g}..{hi:.4g}"
