"""Batched farthest-point sampling of torch point clouds on a Warp kernel (:mod:`vnc_warp.kernels.sampling`).

One kernel launch per call, on the tensor's device and, on CUDA, on torch's current stream: nothing is read back
to the host (unless ``start`` is given, whose range is checked), so a training step that samples stays
asynchronous.
"""

from __future__ import annotations

import torch
import warp as wp

from . import _device
from .kernels import sampling as _kernels

__all__ = ["farthest_point_sample"]

#: Threads per batch item on CUDA; the CPU device runs a block as one thread.
BLOCK_DIM = 256


def farthest_point_sample(points: torch.Tensor, num_samples: int, *, start: torch.Tensor | None = None,
                          random_start: bool = False) -> torch.Tensor:
    """Batched farthest-point sampling.

    Each next sample is the point farthest (Euclidean) from all samples taken so far; ties go to
    the lowest index. Distances are compared squared, in float32 (``(dx^2 + dy^2) + dz^2``, each operation
    rounded), so the indices equal those of the plain torch loop ``dist = min(dist, ((p - q)^2).sum(-1));
    argmax(dist)``. Once every remaining point coincides with a sample (duplicate points), all distances are 0 and
    the lowest index is taken again. Points must be finite.

    Args:
        points: (B, N, 3) float positions (any float dtype, compared in float32), CPU or CUDA (or meta: the result
            has the shape, no values); not differentiated.
        num_samples: M <= N samples per batch item.
        start: (B,) integer index of the first sample; overrides ``random_start``.
        random_start: draw the first index uniformly with the global torch RNG of ``points``' device
            (training); otherwise start at index 0 (deterministic).

    Returns:
        (B, M) int64 indices into ``points``, on ``points.device``.

    Raises:
        ValueError: ``points`` not (B, N, 3) or not floating point, ``num_samples`` outside [1, N], or ``start``
            not (B,) integers in [0, N).
    """
    if points.ndim != 3 or points.shape[-1] != 3:
        raise ValueError(f"farthest_point_sample: points must be (B, N, 3), got {tuple(points.shape)}")
    if not points.is_floating_point():
        raise ValueError(f"farthest_point_sample: points must be floating point, got {points.dtype}")
    b, n, _ = points.shape
    if not 1 <= num_samples <= n:
        raise ValueError(f"farthest_point_sample: num_samples must be in [1, {n}], got {num_samples}")
    if start is None:
        start = (torch.randint(n, (b,), device=points.device) if random_start
                 else torch.zeros(b, dtype=torch.long, device=points.device))
    else:
        if start.shape != (b,):
            raise ValueError(f"farthest_point_sample: start must be ({b},), got {tuple(start.shape)}")
        if start.is_floating_point() or start.is_complex() or start.dtype == torch.bool:
            raise ValueError(f"farthest_point_sample: start must hold integers, got {start.dtype}")
        if b and start.device.type != "meta" and not bool(((start >= 0) & (start < n)).all()):
            raise ValueError(f"farthest_point_sample: start must be in [0, {n}), got {start.tolist()}")
    out = torch.empty(b, num_samples, dtype=torch.long, device=points.device)
    if b == 0 or points.device.type == "meta":  # meta tensors carry shapes only (models built without memory)
        return out
    pts = points.detach().to(torch.float32).contiguous()
    first = start.to(device=points.device, dtype=torch.long).contiguous()
    dist = torch.empty(b, n, dtype=torch.float32, device=points.device)
    args = [wp.from_torch(pts, dtype=wp.vec3, requires_grad=False), wp.from_torch(first, requires_grad=False),
            wp.from_torch(dist, requires_grad=False), wp.from_torch(out, requires_grad=False)]
    if points.device.type == "cuda":
        wp.launch_tiled(_kernels.farthest_point_sample, dim=b, inputs=args, block_dim=BLOCK_DIM,
                        stream=wp.stream_from_torch(points.device))
    else:
        wp.launch_tiled(_kernels.farthest_point_sample, dim=b, inputs=args, block_dim=BLOCK_DIM,
                        device=_device.get_device("cpu"))
    return out
