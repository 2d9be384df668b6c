"""Analytic trajectories for tests and smoke runs: ellipsoids that round off into spheres.

:class:`EllipsoidTrajectories` follows the data contract of
:class:`vnc_warp.training.data.TrajectoryDataset` (same item keys, shapes, dtypes and
normalisation) with exact signed distances, so the training loop, the losses and the inference path
can be checked without generated VNC-Flow data.
"""

from __future__ import annotations

import numpy as np
import torch
from torch.utils.data import Dataset

__all__ = ["ellipsoid_sdf", "EllipsoidTrajectories"]


def ellipsoid_sdf(points: np.ndarray, axes: np.ndarray, *, iterations: int = 100) -> np.ndarray:
    """Exact signed distance to the axis-aligned ellipsoid ``sum (x_i / a_i)^2 = 1``.

    The closest point is ``y_i = a_i^2 x_i / (a_i^2 + lam)`` where ``lam`` is the root of
    ``sum a_i^2 x_i^2 / (a_i^2 + lam)^2 = 1`` in ``(-min a_i^2, inf)``; that function decreases
    monotonically there, so bisection finds it (inside: ``lam < 0``, outside: ``lam > 0``).

    Args:
        points: (Q, 3) positions.
        axes: (3,) positive semi-axes.

    Returns:
        (Q,) float64 signed distance, negative inside.
    """
    x = np.asarray(points, dtype=np.float64)
    a2 = np.asarray(axes, dtype=np.float64) ** 2

    def excess(lam: np.ndarray) -> np.ndarray:
        return (a2 * x * x / (a2 + lam[:, None]) ** 2).sum(1) - 1.0

    outside = excess(np.zeros(len(x))) > 0.0
    lo = np.where(outside, 0.0, -a2.min() * (1.0 - 1e-12))
    hi = np.where(outside, np.sqrt(a2.max()) * np.linalg.norm(x, axis=1), 0.0)
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        above = excess(mid) > 0.0
        lo = np.where(above, mid, lo)
        hi = np.where(above, hi, mid)
    lam = 0.5 * (lo + hi)
    closest = a2 * x / (a2 + lam[:, None])
    dist = np.linalg.norm(x - closest, axis=1)
    return np.where(outside, dist, -dist)


class EllipsoidTrajectories(Dataset):
    """Trajectories from an ellipsoid (t = 1, stage 0) to the sphere of equal axis product (t = 0).

    Shape ``s`` has random semi-axes ``a``, scaled so that the stage-0 bounding box has max extent 1.8
    and centred at the origin (the contract's normalisation); stage ``i`` of ``num_stages`` has
    ``t = 1 - i / (num_stages - 1)`` and semi-axes ``r + t (a - r)`` with ``r = (a_0 a_1 a_2)^(1/3)``.
    Items are a deterministic function of ``(seed, index)``.

    Item keys (those of ``TrajectoryDataset``): ``surface`` (Ns, 6) float32 points on the stage's
    surface and their outward unit normals; ``queries`` (Nq, 3) float32, half uniform in [-1, 1]^3 and half within
    ``near_sigma`` of the stage's surface; ``tsdf`` (Nq,) float32 SDF of the stage clipped to
    +-``truncation``; ``near`` (Nq,) bool ``|sdf| < truncation``; ``t`` () float32; ``shape_id`` ()
    int64; ``stage`` () int64; with ``num_on_surface > 0`` also ``on_surface`` (num_on_surface, 6): points and
    normals on the stage's own surface. ``sdf_iterations``: bisection steps of :func:`ellipsoid_sdf` (each halves
    the bracket of its root, at most ~3 long: 32 reach float32 precision at a third of the default's cost).
    """

    def __init__(self, *, num_shapes: int = 2, num_stages: int = 4, num_surface: int = 256, num_queries: int = 256,
                 truncation: float = 0.1, near_sigma: float = 0.03, seed: int = 0, num_on_surface: int = 0,
                 sdf_iterations: int = 100) -> None:
        if num_shapes < 1 or num_stages < 2:
            raise ValueError(f"EllipsoidTrajectories: need num_shapes >= 1 and num_stages >= 2, "
                             f"got {num_shapes} and {num_stages}")
        rng = np.random.default_rng(seed)
        axes = rng.uniform(0.45, 1.0, size=(num_shapes, 3))
        self.axes0 = 0.9 * axes / axes.max(1, keepdims=True)
        self.num_stages = num_stages
        self.num_surface = num_surface
        self.num_queries = num_queries
        self.num_on_surface = num_on_surface
        self.truncation = truncation
        self.near_sigma = near_sigma
        self.seed = seed
        self.sdf_iterations = sdf_iterations

    def __len__(self) -> int:
        return len(self.axes0) * self.num_stages

    def item_ids(self) -> list[tuple[int, int]]:
        """``(shape_id, stage)`` of every item, without generating them."""
        return [divmod(i, self.num_stages) for i in range(len(self))]

    def stage_times(self) -> list[float]:
        """``t`` of every item, without generating them."""
        return [1.0 - (i % self.num_stages) / (self.num_stages - 1) for i in range(len(self))]

    def axes(self, shape_id: int, t: float) -> np.ndarray:
        """(3,) semi-axes of shape ``shape_id`` at time ``t``."""
        a = self.axes0[shape_id]
        r = float(np.prod(a) ** (1.0 / 3.0))
        return r + t * (a - r)

    @staticmethod
    def surface_points(axes: np.ndarray, count: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """(count, 3) points on the ellipsoid and their (count, 3) outward unit normals."""
        u = rng.normal(size=(count, 3))
        p = axes * u / np.linalg.norm(u, axis=1, keepdims=True)
        n = p / axes**2
        return p, n / np.linalg.norm(n, axis=1, keepdims=True)

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        if not 0 <= index < len(self):
            raise IndexError(f"EllipsoidTrajectories: index {index} out of range [0, {len(self)})")
        shape_id, stage = divmod(index, self.num_stages)
        t = 1.0 - stage / (self.num_stages - 1)
        rng = np.random.default_rng([self.seed, index])
        axes_t = self.axes(shape_id, t)
        p0, n0 = self.surface_points(axes_t, self.num_surface, rng)
        half = self.num_queries // 2
        near, _ = self.surface_points(axes_t, self.num_queries - half, rng)
        near = near + rng.normal(scale=self.near_sigma, size=near.shape)
        queries = np.concatenate([rng.uniform(-1.0, 1.0, size=(half, 3)), near])
        sdf = ellipsoid_sdf(queries, axes_t, iterations=self.sdf_iterations)
        item = {
            "surface": torch.from_numpy(np.concatenate([p0, n0], 1).astype(np.float32)),
            "queries": torch.from_numpy(queries.astype(np.float32)),
            "tsdf": torch.from_numpy(np.clip(sdf, -self.truncation, self.truncation).astype(np.float32)),
            "near": torch.from_numpy(np.abs(sdf) < self.truncation),
            "t": torch.tensor(t, dtype=torch.float32),
            "shape_id": torch.tensor(shape_id, dtype=torch.int64),
            "stage": torch.tensor(stage, dtype=torch.int64),
        }
        if self.num_on_surface:
            p, n = self.surface_points(axes_t, self.num_on_surface, rng)
            item["on_surface"] = torch.from_numpy(np.concatenate([p, n], 1).astype(np.float32))
        return item
