"""How the VNC kernels find their (query, source) pairs: the strategies, and the plan of one traversal.

Every operator sums over the pairs of a query (a vertex or a ball centre) and a source (an edge, or a piece of one)
closer than a cut-off radius. Three strategies visit exactly those pairs, so they give the same result up to float32
rounding; they differ in cost:

* ``"grid"``: sources sorted into a uniform grid of cells (:mod:`kernels.vnc_grid`); groups of queries (a CUDA warp
  of threads on the GPU, one thread on the CPU) walk the cells that their balls reach, in lockstep; a group whose
  balls are far apart lets each thread walk its own box instead. Cost: the candidates in those cells, read as
  contiguous rows, plus a sort of the sources and a few small launches.
* ``"dense"``: the same kernels over a one-cell grid: every query reads every source (the paper's "global dense"
  form, without a V x E matrix). Cheapest when most pairs are within reach anyway.
* ``"bvh"``: one ``wp.Bvh`` query per thread (:mod:`kernels.vnc_reference`), the independent check.
* ``"auto"``: ``"dense"`` when the balls' boxes would cover most of the grid anyway (or, on CUDA, when there are few
  pairs in all, where launch count dominates), otherwise ``"grid"``.

A plan is made on the host from a :class:`Bounds` (the box of the points, their radii, the edge lengths): the cell size,
the launch shape (:func:`launch_shape`: splits of each box's rows over several threads, several queries per thread
in a busy traversal), and for the ball kernels (Eqs. 1-2, which reach an edge from up to half its length beyond the
radius) pieces of the edges (:func:`piece_plan`) or edge-length tiers (:func:`ball_plans`). Every number it weighs
comes from a :class:`~vnc_warp.tuning.Tuning`. The launches it makes (sorts, group boxes) read nothing back, so a plan
can be captured in a graph and replayed, and a grid made for one set of positions stays exact for the next.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from vnc_warp.kernels import reduce as _r
from vnc_warp.kernels import vnc_grid as _g

from .tuning import Tuning

STRATEGIES = ("auto", "grid", "dense", "bvh")

# Queries per group on CUDA: one warp, so a group's threads share one loop and one address per load.
CUDA_GROUP = 32


def check_strategy(strategy: str) -> str:
    """``strategy`` if it is one of :data:`STRATEGIES`, else a ValueError naming them."""
    if strategy not in STRATEGIES:
        raise ValueError(f"strategy must be one of {', '.join(STRATEGIES)}; got {strategy!r}")
    return strategy


def queries_per_thread(device: wp.Device, work: float, most: int, t: Tuning) -> int:
    """Queries per thread of the forward traversals: ``most`` on CUDA for a traversal of at least
    ``t.busy_sources`` candidates per query, where every source record a warp reads then serves ``most`` queries per
    thread; else one (small balls: a thread's box is then its own ball's, and a thread never straddles a jump of the
    Morton curve with a box spanning both sides). One on the CPU; ``t.per_thread`` when set."""
    if t.per_thread is not None:
        return min(int(t.per_thread), most)
    return most if (device.is_cuda or t.emulate_cuda) and work >= t.busy_sources else 1


def launch_shape(device: wp.Device, count: int, per_thread: int, work: float, t: Tuning) -> tuple[int, int]:
    """``(group size, splits)`` for ``count`` queries taken ``per_thread`` at a time, each expecting ``work``
    candidate sources: one warp of threads per group and on CUDA enough splits to fill the device several times
    (``t.light_fill``; a busy traversal four times: its threads wait on loads of long rows, and more of them hide
    it); on the (single-threaded) CPU device one thread per group and no split (unless ``t.emulate_cuda``).
    ``t.group`` and ``t.splits`` when set."""
    if device.is_cpu and not t.emulate_cuda:
        return (t.group or 1) * per_thread, 1 if t.splits is None else int(t.splits)
    group = (t.group or CUDA_GROUP) * per_thread
    if t.splits is not None:
        return group, int(t.splits)
    threads = -(-count // per_thread)
    sm_count = t.emulate_cuda if device.is_cpu else int(getattr(device, "sm_count", 0) or 0)
    resident = 2048 * max(sm_count, 1)
    if work >= t.busy_sources:
        splits = (4 * resident) // max(threads, 1)
        cap = 32 * per_thread ** 0.5
    else:
        splits = round(t.light_fill * (resident / max(threads, 1)) ** (2.0 / 3.0))
        cap = 16 * per_thread ** 0.5
    return group, int(np.clip(splits, 1, cap))


class Pool:
    """Scratch arrays reused from one call to the next: creating a ``wp.array`` costs more host time than the
    small kernels it feeds. The ``n``-th request of a call of one ``kind`` gets back the buffer of the previous
    such call with the same shape and dtype. Reuse is in stream order on one device, and scratch is never handed
    to the caller; calls whose backward pass keeps its intermediates take none (``pool=None``)."""

    def __init__(self, device: wp.Device, kind: str, store: dict, limit: int | None):
        """``store``: the dict of buffers (an engine's, or a captured graph's); ``limit``: buffers kept (None: all)."""
        self.store, self.limit = store, limit
        self.device, self.kind, self.n = device, kind, 0

    def empty(self, shape, dtype) -> wp.array:
        self.n += 1
        key = (self.kind, self.n, shape if isinstance(shape, tuple) else (int(shape),), dtype)
        arr = self.store.pop(key, None)
        if arr is None:
            arr = wp.empty(shape, dtype=dtype, device=self.device)
        self.store[key] = arr  # most recently used last
        while self.limit is not None and len(self.store) > self.limit:
            self.store.pop(next(iter(self.store)))
        return arr

    def zeros(self, shape, dtype) -> wp.array:
        arr = self.empty(shape, dtype)
        arr.zero_()
        return arr


def empty(pool: Pool | None, device, shape, dtype) -> wp.array:
    """A scratch array from ``pool``, or a new one (``pool=None``)."""
    return wp.empty(shape, dtype=dtype, device=device) if pool is None else pool.empty(shape, dtype)


def zeros(pool: Pool | None, device, shape, dtype) -> wp.array:
    return wp.zeros(shape, dtype=dtype, device=device) if pool is None else pool.zeros(shape, dtype)


@dataclass
class Bounds:
    """Host-side summary of one call: bounding box of the sources' vertices, query radii, edge lengths."""

    lo: np.ndarray
    hi: np.ndarray
    rmax: float
    rmean: float
    lmax: float
    lmean: float


STATS_SIZE = 12


def stats_init(device) -> wp.array:
    """A ``(12,)`` float32 array preset for :func:`kernels.vnc_grid.point_stats`."""
    return wp.array(np.array([np.inf] * 3 + [-np.inf] * 4 + [0.0] * 5, dtype=np.float32), device=device)


# Threads of :func:`kernels.vnc_grid.point_stats` at most; the fixed-order fold of their sums
# (:func:`kernels.reduce.fold_stats`) runs in ``FOLD`` parts on CUDA: short strided sums in one block rather than one
# thread walking 4096 partial sums. On the CPU it adds them in one part, in thread order, the order in which the
# single CPU thread's atomics added them before, so CPU results stay what they were.
STATS_THREADS = 4096


def stats_partial(device) -> wp.array:
    """Scratch for :func:`launch_stats`: (STATS_THREADS, 2) float32."""
    return wp.empty((STATS_THREADS, 2), dtype=wp.float32, device=device)


def launch_stats(x: wp.array, radius: wp.array, length: wp.array | None, stats: wp.array,
                 partial: wp.array | None = None) -> None:
    """Enqueue :func:`kernels.vnc_grid.point_stats` into ``stats`` (preset by the caller), its sums added in a fixed
    order (``partial``: :func:`stats_partial`, new if None): two launches, one when there is nothing to add (no
    radii, no lengths: a call with one scale); reads nothing back."""
    device = x.device
    if length is None:
        length = wp.empty(0, dtype=wp.float32, device=device)
    if partial is None:
        partial = stats_partial(device)
    stride = int(min(max(x.shape[0], radius.shape[0], length.shape[0]), STATS_THREADS))
    wp.launch(_g.point_stats, dim=stride, inputs=[x, radius, length, stride], outputs=[stats, partial],
              device=device, record_tape=False)
    if not radius.shape[0] and not length.shape[0]:
        return
    parts = _r.FOLD if device.is_cuda else 1
    wp.launch_tiled(_r.fold_stats, dim=1, inputs=[partial[:stride], parts], outputs=[stats], block_dim=parts,
                    device=device, record_tape=False)


def stats_bounds(s: np.ndarray, points: int, radii: int, lengths: int) -> Bounds:
    """The :class:`Bounds` of host ``stats`` of ``point_stats``, checked.

    Raises:
        ValueError: a point has a NaN or infinite coordinate, or a radius is not positive and finite.
    """
    s = np.asarray(s, dtype=np.float64)
    if s[10] > 0:
        raise ValueError(f"positions: {int(s[10])} of {points} point(s) have a NaN or infinite coordinate")
    if s[11] > 0:
        raise ValueError(f"scales (tau or radius): {int(s[11])} of {radii} value(s) are not positive and finite")
    return Bounds(s[0:3], s[3:6], float(s[6]), float(s[7]) / max(radii, 1), float(s[8]),
                  float(s[9]) / max(lengths, 1))


def bounds(x: wp.array, radius: wp.array, length: wp.array | None = None) -> Bounds:
    """Bounding box of ``x``, statistics of ``radius`` and ``length``: one launch, one small copy to the host.

    Raises:
        ValueError: a point of ``x`` has a NaN or infinite coordinate, or a radius is not positive and finite
            (counted in the same pass: values given on the device are checked at no extra cost).
    """
    stats = stats_init(x.device)
    launch_stats(x, radius, length, stats)
    return stats_bounds(stats.numpy(), x.shape[0], radius.shape[0], 0 if length is None else length.shape[0])


def grid_dims(ext: np.ndarray, h: float) -> np.ndarray:
    return np.floor(ext / h).astype(np.int64) + 1


def cell_size(b: Bounds, reach: float, sources: int, t: Tuning, fraction: float | None = None) -> float:
    """Cell size for balls of typical radius ``reach``: ``fraction`` (default ``t.cell_fraction``, half) of the
    radius (a box of cells then overshoots a ball, or a warp's group of balls, by half a radius at most per side),
    enlarged until the grid has at most ``t.cells_per_source`` cells per source, so memory stays O(sources)."""
    ext = np.maximum(b.hi - b.lo, 0.0)
    scale = max(float(ext.max()), float(np.abs(np.concatenate([b.lo, b.hi])).max()), 1e-30)
    h = max((t.cell_fraction if fraction is None else fraction) * reach, 1e-6 * scale)
    cap = max(t.cells_per_source * sources, 4096)
    for _ in range(64):
        n = float(np.prod(grid_dims(ext, h).astype(np.float64)))
        if n <= cap:
            break
        h *= 1.01 * (n / cap) ** (1.0 / 3.0)
    return h


def dense_fraction(b: Bounds, reach: float, h: float) -> float:
    """Expected fraction of the sources inside one group's box of cells (uniform-density estimate)."""
    ext = np.maximum(b.hi - b.lo, 0.0)
    return float(np.prod(np.minimum(1.0, (2.0 * reach + h) / (ext + h))))


def grid_cell(b: Bounds, reach: float, sources: int, device: wp.Device, t: Tuning, max_per_thread: int = 1,
              busy_fraction: float | None = None) -> tuple[float, float]:
    """``(cell size, expected candidates per query)`` of a grid traversal over ``sources`` (see :func:`cell_size`);
    ``busy_fraction``: the cell size, as a fraction of ``reach``, of a busy traversal (one of several queries per
    thread, :func:`queries_per_thread`)."""
    h = cell_size(b, reach, sources, t)
    work = dense_fraction(b, reach, h) * sources
    if busy_fraction is not None and queries_per_thread(device, work, max_per_thread, t) > 1:
        h = cell_size(b, reach, sources, t, busy_fraction)
        work = max(work, dense_fraction(b, reach, h) * sources)
    return h, work


def resolve(strategy: str, device: wp.Device, b: Bounds, reach: float, queries: int, sources: int,
            t: Tuning) -> str:
    """The concrete strategy for ``strategy`` ("auto" is decided here; see the module docstring)."""
    check_strategy(strategy)
    if strategy != "auto":
        return strategy
    if device.is_cuda and queries * sources <= t.cuda_small_pairs:
        return "dense"
    h = cell_size(b, reach, sources, t)
    return "dense" if dense_fraction(b, reach, h) >= t.dense_fraction else "grid"


@dataclass
class Cells:
    """Sources sorted by cell: ``order[i]`` is the source at sorted position ``i``; the sources of cell ``c``
    are at positions ``first[c]..first[c + 1]``."""

    order: wp.array
    first: wp.array
    origin: wp.vec3
    inv_h: float
    dims: wp.vec3i

    @property
    def one_cell(self) -> bool:
        return tuple(self.dims) == (1, 1, 1)


def _fine_bits(buckets: int, fine: bool, t: Tuning) -> tuple[int, int]:
    """``(bits of a bucket index, Morton bits within a bucket)`` for sort keys of at most 31 bits."""
    bits = max(int(buckets - 1).bit_length(), 1)
    return bits, (min(t.fine_bits, 31 - bits) // 3) * 3 if fine else 0


def build_cells(points: wp.array, b: Bounds, h: float | None, t: Tuning, pool: Pool | None = None,
                fine: bool = False) -> Cells:
    """Sort ``points`` (the sources) into a grid of cells of size ``h`` over ``b`` (``h=None``: one cell);
    ``fine``: each cell's sources along a Morton curve (``t.fine_bits``; with one cell, all of them)."""
    device = points.device
    n = points.shape[0]
    origin = wp.vec3(*b.lo)
    if h is None:
        if fine:
            order = query_order(points, b, None, pool)
        else:
            order = empty(pool, device, n, wp.int32)
            wp.launch(_g.iota, dim=n, outputs=[order], device=device, record_tape=False)
        first = empty(pool, device, 2, wp.int32)
        wp.launch(_g.one_cell, dim=1, inputs=[n], outputs=[first], device=device, record_tape=False)
        return Cells(order, first, origin, 0.0, wp.vec3i(1, 1, 1))
    dims_np = grid_dims(np.maximum(b.hi - b.lo, 0.0), h)
    dims = wp.vec3i(*[int(d) for d in dims_np])
    num_cells = int(np.prod(dims_np))
    bits, fine_bits = _fine_bits(num_cells, fine, t)
    keys = empty(pool, device, 2 * n, wp.int32)
    values = empty(pool, device, 2 * n, wp.int32)
    counts = zeros(pool, device, num_cells + 1, wp.int32)
    wp.launch(_g.cell_keys, dim=n, inputs=[points, origin, 1.0 / h, dims, fine_bits], outputs=[keys, values, counts],
              device=device, record_tape=False)
    wp.utils.radix_sort_pairs(keys, values, n, end_bit=bits + fine_bits)
    first = empty(pool, device, num_cells + 1, wp.int32)
    wp.utils.array_scan(counts, first, inclusive=False)
    return Cells(values[:n], first, origin, 1.0 / h, dims)


def _grid_args(inv_h: list, dims: list) -> list:
    """The per-grid arguments ``inv_h, dims0, .., dims3`` of :func:`kernels.vnc_grid.tier_grid`'s kernels for 1 to 4
    grids (unused slots padded)."""
    return [wp.vec4(*(list(inv_h) + [0.0] * (4 - len(inv_h)))), *(list(dims) + [dims[0]] * (4 - len(dims)))]


def build_tier_cells(points: wp.array, length: wp.array, b: Bounds, hs: list, tier_hi: list, t: Tuning,
                     pool: Pool | None = None, fine: bool = True) -> list[Cells]:
    """One sort of the edges ``points`` (midpoints) for every length tier (``tier_hi``: the tiers' upper bounds,
    ascending, the last infinite; :func:`kernels.vnc_grid.tier_cell_keys`), each cell along a Morton curve when
    ``fine``. Tier ``i`` has a grid of cells of size ``hs[i]`` over ``b`` (coarser for the longer edges, whose balls
    reach farther). Returns the :class:`Cells` of every tier, all sharing one ``order``."""
    device = points.device
    n = points.shape[0]
    if not 1 <= len(hs) <= 4 or len(tier_hi) != len(hs):
        raise ValueError(f"1 to 4 tiers, each with its grid; got {len(tier_hi)} tiers and {len(hs)} grids")
    dims_np = [grid_dims(np.maximum(b.hi - b.lo, 0.0), h) for h in hs]
    sizes = [int(np.prod(d)) for d in dims_np]
    base = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    buckets = int(base[-1])
    keys = empty(pool, device, 2 * n, wp.int32)
    values = empty(pool, device, 2 * n, wp.int32)
    counts = zeros(pool, device, buckets + 1, wp.int32)
    hi = [float(v) for v in tier_hi] + [np.inf] * (4 - len(tier_hi))
    origin = wp.vec3(*b.lo)
    dims = [wp.vec3i(*[int(v) for v in d]) for d in dims_np]
    bits, fine_bits = _fine_bits(buckets, fine, t)
    wp.launch(_g.tier_cell_keys, dim=n,
              inputs=[points, origin, *_grid_args([1.0 / h for h in hs], dims),
                      wp.vec4i(*[int(v) for v in base[:len(hs)]] + [0] * (4 - len(hs))), length, wp.vec4(*hi),
                      fine_bits],
              outputs=[keys, values, counts], device=device, record_tape=False)
    wp.utils.radix_sort_pairs(keys, values, n, end_bit=bits + fine_bits)
    first = empty(pool, device, buckets + 1, wp.int32)
    wp.utils.array_scan(counts, first, inclusive=False)
    order = values[:n]
    return [Cells(order, first[int(base[g]):int(base[g + 1]) + 1], origin, 1.0 / hs[g], dims[g])
            for g in range(len(hs))]


@dataclass
class Groups:
    """Queries in traversal order, in groups of ``size`` that share a box of cells (or walk their own boxes when
    their balls are far apart), each thread taking ``per_thread`` queries and its box split ``splits`` ways.

    Launch the pair kernels with ``dim=(splits, padded // per_thread)``; partial sums have shape
    ``(splits, padded)``. ``pad`` is added to every query's radius.
    """

    order: wp.array
    box_lo: wp.array
    box_hi: wp.array
    size: int
    splits: int
    count: int
    padded: int
    pad: float
    per_thread: int = 1

    @property
    def dim(self) -> tuple[int, int]:
        return self.splits, self.padded // self.per_thread

    def args(self, cells: Cells) -> list:
        """The shared traversal arguments of the ``*_cells`` kernels, after their per-query inputs."""
        return [self.count, self.size, self.order, self.box_lo, self.box_hi, cells.first, cells.dims, cells.origin,
                cells.inv_h, float(self.pad)]


def query_order(points: wp.array, b: Bounds, orders: dict | None = None, pool: Pool | None = None) -> wp.array:
    """The queries sorted along a Morton curve, so that consecutive queries are close together.

    ``orders``: a dict (an engine's) that keeps the order of the first call for every later call with as many
    queries. The order only decides how queries are grouped, never which pairs are summed, so a kept order stays
    correct when the points move (a flow); it only becomes less tight."""
    device = points.device
    count = points.shape[0]
    if orders is not None and count in orders:
        return orders[count]
    # a kept order must not be a pooled buffer; one made while capturing is not kept (it is only computed when the
    # graph runs) and must live as long as the graph: the pool's
    keep = pool if orders is None or device.is_capturing else None
    keys = empty(keep, device, 2 * count, wp.int32)
    values = empty(keep, device, 2 * count, wp.int32)
    extent = float(np.max(b.hi - b.lo))
    scale = 1024.0 / extent if extent > 0 else 0.0
    wp.launch(_g.morton_keys, dim=count, inputs=[points, wp.vec3(*b.lo), scale], outputs=[keys, values],
              device=device, record_tape=False)
    wp.utils.radix_sort_pairs(keys, values, count, end_bit=30)
    order = values[:count]
    if orders is not None and not device.is_capturing:  # a captured order is only computed when its graph runs
        orders[count] = order
    return order


def build_groups(points: wp.array, radius: wp.array, pads: list, cells: list, b: Bounds, t: Tuning, *,
                 spatial_order: bool, splits: int | None = None, like: Groups | None = None, per_thread: int = 1,
                 work: float = 0.0, orders: dict | None = None, pool: Pool | None = None) -> list[Groups]:
    """Group the queries ``points`` (balls of radius ``radius[k] + pad``) for traversals of ``cells`` (a
    :class:`Cells` per pad), one :class:`Groups` per pad of ``pads`` (at most 4: the edge-length tiers of
    :func:`ball_plans`), in the same launches; the first pad's traversal decides the splits, the others share them.

    ``spatial_order`` sorts the queries along a Morton curve first (:func:`query_order`, kept in ``orders``), so a
    group's balls are close together (only worth it for groups of more than one query over more than one cell).
    ``like``: reuse the order, group size and queries per thread of another traversal of the same queries (their
    partial sums then line up), and its splits or fewer. ``work``: expected candidate sources per query (see
    :func:`launch_shape`).
    """
    device = points.device
    count = points.shape[0]
    size, default_splits = launch_shape(device, count, per_thread, work, t)
    if like is not None:
        # a traversal adding to ``like``'s partial sums: at most its splits (fewer when it expects less work)
        order, size, per_thread = like.order, like.size, like.per_thread
        splits = like.splits if splits is not None else min(like.splits, default_splits)
    else:
        splits = default_splits if splits is None else splits
        if spatial_order:
            order = query_order(points, b, orders, pool)
        else:
            order = empty(pool, device, count, wp.int32)
            wp.launch(_g.iota, dim=count, outputs=[order], device=device, record_tape=False)
    num_groups = (count + size - 1) // size
    if size // per_thread > 32:
        raise ValueError(f"groups of at most 32 threads (kernels.vnc_grid.group_boxes), got {size // per_thread}")
    pads = [float(p) for p in pads]
    if not 1 <= len(pads) <= 4 or len(cells) != len(pads):
        raise ValueError(f"1 to 4 pads, each with its cells; got {len(pads)} pads and {len(cells)} cells")
    box_lo = empty(pool, device, (len(pads), num_groups), wp.vec3i)
    box_hi = empty(pool, device, (len(pads), num_groups), wp.vec3i)
    # float32 rounding of p +- r must never drop a cell that holds a source within reach
    margin = 1e-6 * max(float(np.abs(np.concatenate([b.lo, b.hi])).max()), b.rmax)
    if all(c.one_cell for c in cells):  # one cell: every box is that cell
        box_lo.zero_()
        box_hi.zero_()
    else:
        if len({(tuple(c.origin)) for c in cells}) > 1:
            raise ValueError("the traversals grouped together share the origin of their grids")
        threads = -(-count // per_thread)
        acc = zeros(pool, device, (3, len(pads), num_groups), wp.vec3i)  # lowest, highest cells, most cells
        wp.launch(_g.thread_extents, dim=threads,
                  inputs=[points, order, radius, margin, count, per_thread, size // per_thread, cells[0].origin,
                          *_grid_args([c.inv_h for c in cells], [c.dims for c in cells]),
                          wp.vec4(*(pads + [0.0] * (4 - len(pads))))],
                  outputs=[acc[0], acc[1], acc[2]], device=device, record_tape=False)
        wp.launch(_g.group_boxes, dim=(len(pads), num_groups),
                  inputs=[acc[0], acc[1], acc[2], t.spread if size > per_thread else 1.0e30],
                  outputs=[box_lo, box_hi], device=device, record_tape=False)
    return [Groups(order, box_lo[i], box_hi[i], size, splits, count, num_groups * size, p + margin, per_thread)
            for i, p in enumerate(pads)]


def groups_for(points: wp.array, radius: wp.array, pads: list, cells: list, b: Bounds, work: float, t: Tuning, *,
               splits: int | None = None, max_per_thread: int = 1, like: Groups | None = None,
               orders: dict | None = None, pool: Pool | None = None) -> list[Groups]:
    """:func:`build_groups` for traversals of ``cells`` (one per pad), the first expecting ``work`` candidates per
    query, taking up to ``max_per_thread`` queries per thread."""
    device = points.device
    per_thread = queries_per_thread(device, work, max_per_thread, t) if like is None else like.per_thread
    size, _ = launch_shape(device, points.shape[0], per_thread, 0.0, t)
    # queries in Morton order for the dense traversal too: a warp's balls then lie together, and a source beyond the
    # cut-off of all of them costs it no exp2
    return build_groups(points, radius, pads, cells, b, t, spatial_order=size > 1, splits=splits, like=like,
                        per_thread=per_thread, work=work, orders=orders, pool=pool)


def plan(points: wp.array, radius: wp.array, sources: wp.array, b: Bounds, strategy: str, reach: float, t: Tuning,
         pad: float = 0.0, *, splits: int | None = None, max_per_thread: int = 1, orders: dict | None = None,
         pool: Pool | None = None, fine: bool = False, busy_cell: float | None = None) -> tuple[Cells, Groups]:
    """Cells over ``sources`` (``fine``: in Morton order within each, see :func:`build_cells`) and groups of the
    query ``points`` (balls ``radius[k] + pad``, typically ``reach``) for a concrete "grid" or "dense" strategy, with
    up to ``max_per_thread`` queries per thread (:func:`queries_per_thread`, from the expected candidates per query
    that also set the splits; ``busy_cell``: see :func:`grid_cell`)."""
    if strategy == "dense":
        h, work = None, float(sources.shape[0])
    else:
        h, work = grid_cell(b, reach, sources.shape[0], points.device, t, max_per_thread, busy_cell)
    cells = build_cells(sources, b, h, t, pool, fine)
    return cells, groups_for(points, radius, [pad], [cells], b, work, t, splits=splits,
                             max_per_thread=max_per_thread, orders=orders, pool=pool)[0]


# --- the ball kernels (Eqs. 1-2): pieces of the edges, edge-length tiers, kernel variants ------------------------


def ball_reach(b: Bounds) -> float:
    """The mean ball radius of a ball traversal in mean edge lengths."""
    return b.rmean / max(b.lmean, 1e-30)


def ball_variant(t: Tuning, strategy: str, per_thread: int, reach: float, one_cell: bool, cuda: bool) -> dict:
    """The :func:`kernels.vnc_sums.ball_cells_kernel` options of one launch of a ball traversal: the midpoint
    prefilter for a grid traversal on the CPU only (``t.ball_prefilter`` None); runs of records tested as a whole
    for balls of at least ``t.chunk_reach_*`` mean edge lengths and every launch over one cell (a dense traversal,
    1.6x faster at half the diagonal, or the long edges' one of a grid traversal), ``t.ball_chunks`` None."""
    prefilter = t.ball_prefilter if t.ball_prefilter is not None else (strategy == "grid" and not cuda)
    chunks = t.ball_chunks if t.ball_chunks is not None else (
        strategy == "dense" or one_cell or reach >= t.chunk_reach(cuda))
    return {"qb": per_thread, "cull": t.cull_on(cuda), "prefilter": bool(prefilter), "chunks": bool(chunks),
            "chunk": t.chunk, "min_run": t.min_run}


def chunked(strategy: str, b: Bounds, one_cell: bool, device: wp.Device, t: Tuning) -> bool:
    """Whether a ball traversal (``strategy`` "grid" or "dense", over ``one_cell`` or more) on ``device`` tests runs
    of sorted records as a whole (:func:`ball_variant`)."""
    return ball_variant(t, strategy, 1, ball_reach(b), one_cell, device.is_cuda)["chunks"]


def _first_tier(b: Bounds, t: Tuning) -> float:
    """The upper edge length of the first tier of :func:`ball_plans`: every edge when that widens the balls (radius +
    half the longest edge) by at most ``t.tier_grow``."""
    return max(t.tier_base * b.lmean,
               2.0 * ((1.0 + t.tier_grow) * (b.rmean + 0.5 * t.tier_base * b.lmean) - b.rmean))


def edge_plan(points: wp.array, radius: wp.array, mid: wp.array, b: Bounds, strategy: str, t: Tuning, *,
              splits: int | None = None, max_per_thread: int = 1, orders: dict | None = None,
              pool: Pool | None = None) -> tuple[Cells, Groups]:
    """One traversal of the ball kernels over whole edges (sorted by their midpoints ``mid``), every ball padded by
    half the longest edge: "dense", or a grid when no edge is much longer than the others (:func:`uses_pieces`)."""
    pad = 0.5 * b.lmax
    # (the order only speeds the chunked kernel up: a grid of one cell, a tiny mesh's, may read unordered runs)
    fine = chunked(strategy, b, strategy == "dense", points.device, t)
    return plan(points, radius, mid, b, strategy, b.rmean + pad, t, pad, splits=splits, max_per_thread=max_per_thread,
                orders=orders, pool=pool, fine=fine, busy_cell=t.busy_ball_cell)


def ball_plans(points: wp.array, radius: wp.array, mid: wp.array, length: wp.array, b: Bounds, strategy: str,
               t: Tuning, *, splits: int | None = None, max_per_thread: int = 1, orders: dict | None = None,
               pool: Pool | None = None) -> list[tuple[Cells, Groups]]:
    """The traversals of the multi-scale ball kernel over whole edges: one over all edges (:func:`edge_plan`:
    "dense", or edges of similar lengths), else one per edge-length tier, each through a grid of its own.

    Every traversal reads one sort of the edges (:func:`build_tier_cells`: one packing of the edge records serves
    them all) and shares the query order, queries per thread and splits of the first, the short edges'.
    """
    device = points.device
    # the first tier takes every edge when that widens its balls by at most tier_grow (the other tiers' launches
    # would cost more than the few extra candidates)
    if strategy == "dense" or b.lmax <= _first_tier(b, t):
        return [edge_plan(points, radius, mid, b, strategy, t, splits=splits, max_per_thread=max_per_thread,
                          orders=orders, pool=pool)]
    tier_hi = []
    while len(tier_hi) < t.max_tiers - 1 and t.tier_base * b.lmean * 2 ** len(tier_hi) < b.lmax:
        tier_hi.append(t.tier_base * b.lmean * 2 ** len(tier_hi))
    tier_hi.append(np.inf)
    # the pads of the tiers, and their cells: the same fraction of each tier's own reach (a tier of long edges
    # reaches farther, and fewer of its edges share a cell: finer cells would only add empty rows to its boxes)
    pads = [0.5 * min(hi, b.lmax) for hi in tier_hi]
    h0, _ = grid_cell(b, b.rmean + pads[0], mid.shape[0], device, t, max_per_thread, t.busy_ball_cell)
    hs = [h0 * (b.rmean + p) / (b.rmean + pads[0]) for p in pads]
    # the edges of a cell along a Morton curve only for traversals that test runs of them as a whole
    ext = np.maximum(b.hi - b.lo, 0.0)
    fine = any(chunked(strategy, b, tuple(grid_dims(ext, h)) == (1, 1, 1), device, t) for h in hs)
    cells = build_tier_cells(mid, length, b, hs, tier_hi, t, pool, fine)
    work = dense_fraction(b, b.rmean + pads[0], hs[0]) * mid.shape[0]
    # the tiers' groups in one pair of launches: boxes of the same queries, each in its tier's grid and pad
    groups = groups_for(points, radius, pads, cells, b, work, t, splits=splits, max_per_thread=max_per_thread,
                        orders=orders, pool=pool)
    return list(zip(cells, groups))


@dataclass
class Pieces:
    """The pieces of the edges (:func:`kernels.vnc_grid.piece_keys`): ``counts[j]`` pieces of edge ``j`` (at most
    ``length`` long), sorted slot ``i`` holding piece ``piece_index[s]`` of edge ``piece_edge[s]``, ``s =
    cells.order[i]``; ``capacity`` slots in all, those past the last piece sorted last with ``piece_edge = -1``."""

    counts: wp.array
    piece_edge: wp.array
    piece_index: wp.array
    capacity: int
    length: float


def uses_pieces(strategy: str, b: Bounds, t: Tuning, any_length: bool = False) -> bool:
    """Whether a single-scale ball traversal (``strategy`` "grid" or "dense") takes pieces of the edges
    (:func:`piece_grid`) rather than whole edges (:func:`edge_plan`): on a grid, when the longest edge would widen
    the balls (beyond the first tier of :func:`ball_plans`; ``any_length``: whatever the lengths, as the pieces kept
    with an engine on the CPU, ``t.cpu_pieces``)."""
    return strategy == "grid" and b.lmean > 0 and (any_length or b.lmax > _first_tier(b, t))


def piece_length(b: Bounds, t: Tuning) -> float:
    """The longest piece of an edge in a ball traversal of :func:`piece_plan` (mesh units)."""
    r = ball_reach(b)
    return b.lmean * max(t.piece_min, min(t.piece_max, 0.5 * r), 0.25 * r)


def piece_capacity(lengths: np.ndarray, piece: float) -> int:
    """Slots for the pieces of edges of host ``lengths`` (float32, as on the device, where float32 rounding may make
    them a part in 1e6 longer): at least the device's count of :func:`kernels.vnc_grid.piece_counts`."""
    k = np.ceil(lengths.astype(np.float64) * ((1.0 + 1e-5) / piece))
    return int(np.maximum(k, 1.0).sum()) + 16


def piece_bound(b: Bounds, edges: int, piece: float) -> int:
    """Slots for the pieces of ``edges`` edges of mean length ``b.lmean`` from the bounds alone:
    ``sum ceil(L / P) <= E + sum L / P`` (with float32 slack)."""
    return int(np.ceil(edges * b.lmean * (1.0 + 1e-5) / piece)) + edges + 16


@dataclass
class PieceGrid:
    """The edge side of a traversal over pieces (:func:`piece_grid`): the pieces sorted into ``cells``, the pad that
    every ball takes (half a piece, float32 slack included) and the expected candidates per query of the radii the
    cells were chosen for (``work``; None when the cell size was given, as for every radius)."""

    cells: Cells
    pieces: Pieces
    pad: float
    work: float | None


def piece_grid(x: wp.array, edges: wp.array, length: wp.array, b: Bounds, strategy: str, t: Tuning, *,
               capacity: int, piece: float | None = None, cell: float | None = None, fine: bool | None = None,
               max_per_thread: int = 1, pool: Pool | None = None) -> PieceGrid:
    """Cut the edges (``x[edges]``, of ``length``) into equal pieces no longer than ``piece`` (default
    :func:`piece_length`) and sort them by their centres into a grid over ``b``: cells of ``cell`` (capped as in
    :func:`cell_size`), default :func:`grid_cell` for the reach of ``b``'s radii plus half a piece; ``fine``: a Morton
    order within each cell (default: when the traversal of ``b``'s radii tests runs, :func:`chunked`). ``capacity``:
    slots for the pieces, at least their count (:func:`piece_capacity`, :func:`piece_bound`)."""
    device = x.device
    ne = length.shape[0]
    piece = piece_length(b, t) if piece is None else float(piece)
    counts = empty(pool, device, ne, wp.int32)
    offsets = empty(pool, device, ne, wp.int32)
    wp.launch(_g.piece_counts, dim=ne, inputs=[length, 1.0 / piece], outputs=[counts], device=device,
              record_tape=False)
    wp.utils.array_scan(counts, offsets, inclusive=False)
    n = int(capacity)
    # float32 rounding may leave a piece a part in 1e6 longer than `piece`
    pad = 0.5 * min(piece, b.lmax) * (1.0 + 1e-5)
    if cell is None:
        h, work = grid_cell(b, b.rmean + pad, n, device, t, max_per_thread, t.busy_ball_cell)
    else:
        h, work = cell_size(b, float(cell), n, t, fraction=1.0), None
    dims_np = grid_dims(np.maximum(b.hi - b.lo, 0.0), h)
    dims = wp.vec3i(*[int(d) for d in dims_np])
    num_cells = int(np.prod(dims_np))
    if fine is None:
        fine = chunked(strategy, b, num_cells == 1, device, t)
    bits, fine_bits = _fine_bits(num_cells + 1, fine, t)
    keys = empty(pool, device, 2 * n, wp.int32)
    values = empty(pool, device, 2 * n, wp.int32)
    piece_edge = empty(pool, device, n, wp.int32)
    piece_index = empty(pool, device, n, wp.int32)
    cell_counts = zeros(pool, device, num_cells + 1, wp.int32)
    origin = wp.vec3(*b.lo)
    wp.launch(_g.piece_keys, dim=n, inputs=[x, edges, counts, offsets, origin, 1.0 / h, dims, fine_bits],
              outputs=[keys, values, piece_edge, piece_index, cell_counts], device=device, record_tape=False)
    wp.utils.radix_sort_pairs(keys, values, n, end_bit=bits + fine_bits)
    first = empty(pool, device, num_cells + 1, wp.int32)
    wp.utils.array_scan(cell_counts, first, inclusive=False)
    cells = Cells(values[:n], first, origin, 1.0 / h, dims)
    return PieceGrid(cells, Pieces(counts, piece_edge, piece_index, n, piece), pad, work)


def piece_groups(points: wp.array, radius: wp.array, grid: PieceGrid, b: Bounds, t: Tuning, *,
                 splits: int | None = None, max_per_thread: int = 1, orders: dict | None = None,
                 pool: Pool | None = None) -> Groups:
    """The groups of the query ``points`` (balls of ``radius`` plus the grid's pad) for a traversal of the pieces of
    ``grid``: a piece crosses a ball only if its centre is within the radius plus half a piece, whatever the longest
    edge."""
    work = grid.work
    if work is None:  # cells not chosen for these radii
        work = dense_fraction(b, b.rmean + grid.pad, 1.0 / grid.cells.inv_h) * grid.pieces.capacity
    return groups_for(points, radius, [grid.pad], [grid.cells], b, work, t, splits=splits,
                      max_per_thread=max_per_thread, orders=orders, pool=pool)[0]
