"""How the VNC kernels find their (query, source) pairs: the traversal strategies and their set-up.

Every operator of :mod:`vnc_warp.operators` and :mod:`vnc_warp.scale` sums over the pairs of a query
(a vertex or a ball centre) and a source (an edge) closer than a cut-off radius. Three strategies visit
exactly those pairs, so they give the same result up to float32 rounding; they differ in cost:

* ``"grid"``: sources sorted into a uniform grid of cells; groups of queries (a CUDA warp on the GPU,
  one thread on the CPU) walk the cells that their balls reach, in lockstep. Cost: the candidates in
  those cells, read as contiguous rows, plus two sorts and a few small launches to set up.
* ``"dense"``: the same kernels over a one-cell grid: every query reads every source (the paper's
  "global dense" form, without a V x E matrix). Cheapest when most pairs are within reach anyway.
* ``"bvh"``: one ``wp.Bvh`` query per thread (the original kernels), kept as an independent check.
* ``"auto"``: ``"dense"`` when the balls' boxes would cover most of the grid anyway (or, on CUDA, when
  there are fewer than 4M pairs in all, where launch count dominates), otherwise ``"grid"``.

The split of each group's candidates over several threads (``splits``) only raises occupancy on the GPU;
partial sums are added in a fixed order afterwards, so every strategy is deterministic. The ball kernels
(Eqs. 1-2) reach an edge from up to half its length beyond the radius, so they traverse the edges in tiers
of similar length (:func:`ball_plans`): a few long edges, common in scans, do not widen every query's box.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from vnc_warp.kernels import vnc as _k

STRATEGIES = ("auto", "grid", "dense", "bvh")

# Queries per group on CUDA: one warp, so a group's threads share one loop and one address per load.
_CUDA_GROUP = 32
# A dense traversal is chosen when the balls' boxes are expected to cover this fraction of the sources.
_DENSE_FRACTION = 0.9
# On CUDA, launch count dominates below this many query x source pairs: use the dense traversal.
_CUDA_SMALL_PAIRS = 1 << 22


def check_strategy(strategy: str) -> str:
    """``strategy`` if it is one of :data:`STRATEGIES`, else a ValueError naming them."""
    if strategy not in STRATEGIES:
        raise ValueError(f"strategy must be one of {', '.join(STRATEGIES)}; got {strategy!r}")
    return strategy


def launch_shape(device: wp.Device, count: int) -> tuple[int, int]:
    """``(group size, splits)`` for ``count`` queries: one warp per group and enough splits on CUDA to fill
    the device about twice; one query per group and no split on the (single-threaded) CPU device."""
    if device.is_cpu:
        return 1, 1
    resident = 2048 * max(int(getattr(device, "sm_count", 0) or 0), 1)
    return _CUDA_GROUP, int(np.clip((2 * resident) // max(count, 1), 1, 16))


@dataclass
class Bounds:
    """Host-side summary of one call: bounding box of the sources' vertices, query radii, edge lengths."""

    lo: np.ndarray
    hi: np.ndarray
    rmax: float
    rmean: float
    lmax: float
    lmean: float


def bounds(x: wp.array, radius: wp.array, length: wp.array | None = None) -> Bounds:
    """Bounding box of ``x``, statistics of ``radius`` and ``length``: one launch, one small copy to the host."""
    device = x.device
    if length is None:
        length = wp.empty(0, dtype=wp.float32, device=device)
    stats = wp.array(np.array([np.inf] * 3 + [-np.inf] * 4 + [0.0, 0.0, 0.0], dtype=np.float32), device=device)
    stride = int(min(max(x.shape[0], radius.shape[0], length.shape[0]), 4096))
    wp.launch(_k.point_stats, dim=stride, inputs=[x, radius, length, stride], outputs=[stats], device=device,
              record_tape=False)
    s = stats.numpy().astype(np.float64)
    return Bounds(s[0:3], s[3:6], float(s[6]), float(s[7]) / max(radius.shape[0], 1), float(s[8]),
                  float(s[9]) / max(length.shape[0], 1))


def _grid_dims(ext: np.ndarray, h: float) -> np.ndarray:
    return np.floor(ext / h).astype(np.int64) + 1


def cell_size(b: Bounds, reach: float, sources: int, device: wp.Device) -> float:
    """Cell size for balls of typical radius ``reach``: half the radius (a box of cells then overshoots a ball, or
    a warp's group of balls, by half a radius at most per side), enlarged until the grid has at most
    ``4 x sources`` cells, so memory stays O(sources)."""
    ext = np.maximum(b.hi - b.lo, 0.0)
    scale = max(float(ext.max()), float(np.abs(np.concatenate([b.lo, b.hi])).max()), 1e-30)
    h = max(0.5 * reach, 1e-6 * scale)
    cap = max(4 * sources, 4096)
    for _ in range(64):
        n = float(np.prod(_grid_dims(ext, h).astype(np.float64)))
        if n <= cap:
            break
        h *= 1.01 * (n / cap) ** (1.0 / 3.0)
    return h


def dense_fraction(b: Bounds, reach: float, h: float) -> float:
    """Expected fraction of the sources inside one group's box of cells (uniform-density estimate)."""
    ext = np.maximum(b.hi - b.lo, 0.0)
    return float(np.prod(np.minimum(1.0, (2.0 * reach + h) / (ext + h))))


def resolve(strategy: str, device: wp.Device, b: Bounds, reach: float, queries: int, sources: int) -> str:
    """The concrete strategy for ``strategy`` ("auto" is decided here; see the module docstring)."""
    check_strategy(strategy)
    if strategy != "auto":
        return strategy
    if device.is_cuda and queries * sources <= _CUDA_SMALL_PAIRS:
        return "dense"
    h = cell_size(b, reach, sources, device)
    return "dense" if dense_fraction(b, reach, h) >= _DENSE_FRACTION else "grid"


@dataclass
class Cells:
    """Sources sorted by cell: ``order[i]`` is the source at sorted position ``i``; the sources of cell ``c``
    are at positions ``first[c]..first[c + 1]``."""

    order: wp.array
    first: wp.array
    origin: wp.vec3
    inv_h: float
    dims: wp.vec3i


def build_cells(points: wp.array, b: Bounds, h: float | None, select: tuple | None = None) -> Cells:
    """Sort ``points`` (the sources) into a grid of cells of size ``h`` over ``b`` (``h=None``: one cell).

    ``select = (length, lmin, lmax)`` keeps only the sources with ``lmin < length <= lmax`` in the cells (the
    others sort past the last cell).
    """
    device = points.device
    n = points.shape[0]
    origin = wp.vec3(*b.lo)
    if h is None and select is None:
        order = wp.empty(n, dtype=wp.int32, device=device)
        wp.launch(_k.iota, dim=n, outputs=[order], device=device, record_tape=False)
        first = wp.array(np.array([0, n], dtype=np.int32), device=device)
        return Cells(order, first, origin, 0.0, wp.vec3i(1, 1, 1))
    dims_np = np.ones(3, dtype=np.int64) if h is None else _grid_dims(np.maximum(b.hi - b.lo, 0.0), h)
    inv_h = 0.0 if h is None else 1.0 / h
    dims = wp.vec3i(*[int(d) for d in dims_np])
    num_cells = int(np.prod(dims_np))
    length, lmin, lmax = select if select is not None else (wp.empty(0, dtype=wp.float32, device=device), 0.0, 0.0)
    keys = wp.empty(2 * n, dtype=wp.int32, device=device)
    values = wp.empty(2 * n, dtype=wp.int32, device=device)
    wp.launch(_k.cell_keys, dim=n, inputs=[points, origin, inv_h, dims, length, float(lmin), float(lmax)],
              outputs=[keys, values], device=device, record_tape=False)
    counts = wp.zeros(num_cells + 1, dtype=wp.int32, device=device)
    wp.launch(_k.cell_count, dim=n, inputs=[keys], outputs=[counts], device=device, record_tape=False)
    wp.utils.radix_sort_pairs(keys, values, n, end_bit=max(int(num_cells).bit_length(), 1))
    first = wp.empty(num_cells + 1, dtype=wp.int32, device=device)
    wp.utils.array_scan(counts, first, inclusive=False)
    return Cells(values[:n], first, origin, inv_h, dims)


@dataclass
class Groups:
    """Queries in traversal order, in groups of ``size`` that share a box of cells, split ``splits`` ways.

    Launch the pair kernels with ``dim=(splits, padded)``; partial sums have shape ``(splits, padded)``.
    """

    order: wp.array
    box_lo: wp.array
    box_hi: wp.array
    total: wp.array
    size: int
    splits: int
    count: int
    padded: int

    @property
    def dim(self) -> tuple[int, int]:
        return self.splits, self.padded

    def args(self, cells: Cells) -> list:
        """The shared traversal arguments of the ``*_cells`` kernels, after their per-query inputs."""
        return [self.count, self.size, self.order, self.box_lo, self.box_hi, self.total, cells.first, cells.dims]


def build_groups(points: wp.array, radius: wp.array, pad: float, cells: Cells, b: Bounds, *,
                 spatial_order: bool, splits: int | None = None, like: Groups | None = None) -> Groups:
    """Group the queries ``points`` (balls of radius ``radius[k] + pad``) for a traversal of ``cells``.

    ``spatial_order`` sorts the queries along a Morton curve first, so a group's balls are close together
    (only worth it for groups of more than one query over more than one cell). ``like``: reuse the order, group
    size and splits of another traversal of the same queries (their partial sums then line up).
    """
    device = points.device
    count = points.shape[0]
    size, default_splits = launch_shape(device, count)
    splits = default_splits if splits is None else splits
    if like is not None:
        order, size, splits = like.order, like.size, like.splits
    elif spatial_order:
        keys = wp.empty(2 * count, dtype=wp.int32, device=device)
        values = wp.empty(2 * count, dtype=wp.int32, device=device)
        extent = float(np.max(b.hi - b.lo))
        scale = 1024.0 / extent if extent > 0 else 0.0
        wp.launch(_k.morton_keys, dim=count, inputs=[points, wp.vec3(*b.lo), scale], outputs=[keys, values],
                  device=device, record_tape=False)
        wp.utils.radix_sort_pairs(keys, values, count, end_bit=30)
        order = values[:count]
    else:
        order = wp.empty(count, dtype=wp.int32, device=device)
        wp.launch(_k.iota, dim=count, outputs=[order], device=device, record_tape=False)
    num_groups = (count + size - 1) // size
    box_lo = wp.empty(num_groups, dtype=wp.vec3i, device=device)
    box_hi = wp.empty(num_groups, dtype=wp.vec3i, device=device)
    total = wp.empty(num_groups, dtype=wp.int32, device=device)
    # float32 rounding of p +- r must never drop a cell that holds a source within reach
    margin = 1e-6 * max(float(np.abs(np.concatenate([b.lo, b.hi])).max()), b.rmax)
    wp.launch(
        _k.group_boxes, dim=num_groups,
        inputs=[points, order, radius, float(pad + margin), count, size, cells.origin, cells.inv_h, cells.dims,
                cells.first],
        outputs=[box_lo, box_hi, total], device=device, record_tape=False,
    )
    return Groups(order, box_lo, box_hi, total, size, splits, count, num_groups * size)


def plan(points: wp.array, radius: wp.array, sources: wp.array, b: Bounds, strategy: str, reach: float,
         pad: float = 0.0, *, splits: int | None = None, select: tuple | None = None,
         like: Groups | None = None) -> tuple[Cells, Groups]:
    """Cells over ``sources`` (those kept by ``select``, see :func:`build_cells`) and groups of the query ``points``
    (balls ``radius[k] + pad``, typically ``reach``) for a concrete "grid" or "dense" strategy."""
    device = points.device
    if strategy == "dense":
        cells = build_cells(sources, b, None, select)
        return cells, build_groups(points, radius, pad, cells, b, spatial_order=False, splits=splits, like=like)
    cells = build_cells(sources, b, cell_size(b, reach, sources.shape[0], device), select)
    size, _ = launch_shape(device, points.shape[0])
    groups = build_groups(points, radius, pad, cells, b, spatial_order=size > 1, splits=splits, like=like)
    return cells, groups


# Edge-length tiers of the ball (Eq. 1-2) kernels: an edge reaches a ball from as far as half its length beyond the
# radius, so edges are traversed in tiers of similar length, each with its own pad; a few long edges (scans have
# them) then do not widen every query's box. Tier bounds: TIER_BASE x mean edge length, doubling, at most MAX_TIERS.
TIER_BASE = 1.5
MAX_TIERS = 4


def ball_plans(points: wp.array, radius: wp.array, mid: wp.array, length: wp.array, b: Bounds, strategy: str,
               *, splits: int | None = None) -> list[tuple[Cells, Groups]]:
    """The traversals of the ball kernels: one over all edges ("dense", or edges of similar lengths), else one per
    edge-length tier, all sharing the query order (their partial sums line up)."""
    if strategy == "dense" or b.lmax <= TIER_BASE * b.lmean:
        pad = 0.5 * b.lmax
        return [plan(points, radius, mid, b, strategy, b.rmean + pad, pad, splits=splits)]
    bounds_ = [-1.0]
    while len(bounds_) < MAX_TIERS and TIER_BASE * b.lmean * 2 ** (len(bounds_) - 1) < b.lmax:
        bounds_.append(TIER_BASE * b.lmean * 2 ** (len(bounds_) - 1))
    bounds_.append(np.inf)
    plans, first = [], None
    for lo, hi in zip(bounds_[:-1], bounds_[1:]):
        pad = 0.5 * min(hi, b.lmax)
        p = plan(points, radius, mid, b, strategy, b.rmean + pad, pad, splits=splits, select=(length, lo, hi),
                 like=first)
        first = first or p[1]
        plans.append(p)
    return plans
