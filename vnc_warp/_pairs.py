"""How the VNC kernels find their (query, source) pairs: the traversal strategies and their set-up.

Every operator of :mod:`vnc_warp.operators` and :mod:`vnc_warp.scale` sums over the pairs of a query
(a vertex or a ball centre) and a source (an edge) closer than a cut-off radius. Three strategies visit
exactly those pairs, so they give the same result up to float32 rounding; they differ in cost:

* ``"grid"``: sources sorted into a uniform grid of cells; groups of queries (a CUDA warp of threads on the
  GPU, one thread on the CPU) walk the cells that their balls reach, in lockstep; a group whose balls are far
  apart (small balls, or a jump of the Morton curve) lets each thread walk its own box instead. Cost: the
  candidates in those cells, read as contiguous rows, plus a sort of the sources and a few small launches.
* ``"dense"``: the same kernels over a one-cell grid: every query reads every source (the paper's
  "global dense" form, without a V x E matrix). Cheapest when most pairs are within reach anyway.
* ``"bvh"``: one ``wp.Bvh`` query per thread (the original kernels), kept as an independent check.
* ``"auto"``: ``"dense"`` when the balls' boxes would cover most of the grid anyway (or, on CUDA, when
  there are fewer than 4M pairs in all, where launch count dominates), otherwise ``"grid"``.

The split of each box's rows over several threads (``splits``: whole rows dealt out in turn when a box has many,
parts of every row when it has few) only raises occupancy on the GPU; partial sums are added in a fixed order
afterwards, so every strategy is deterministic. A busy traversal (:data:`BUSY_SOURCES` candidates per query) takes
more splits and several queries per thread (:func:`queries_per_thread`), so that each source it reads serves all of
them. Scratch buffers come from a :class:`Pool` and the queries' Morton order is kept with the mesh: both only save
host time (as does :mod:`vnc_warp._replay`, which replays repeated calls from captured graphs). The ball kernels
(Eqs. 1-2) reach an edge from up to half its length beyond the radius, so that a few long edges, common in scans,
would widen every query's box: a single-scale traversal cuts the edges into pieces of at most a few mean edge lengths
(:func:`piece_plan`; on the CPU device the pieces of a mesh's own edges are sorted once for every radius and kept with
the mesh, :data:`CPU_PIECES`), the multi-scale one traverses them in tiers of similar length (:func:`ball_plans`, one
sort for all of them; the tiers of few edges tested against every query instead, in one traversal).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

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
# Grid cell size as a fraction of the typical query radius (see cell_size).
CELL_FRACTION = 0.5
# A grid has at most this many cells per source (cell_size): its first-source table is O(sources). The cap sets the
# cells of small balls on large meshes (at 800k vertices and 2 mean edge lengths: 2.2 edge lengths instead of half
# the radius); 8 and 16 were no better on an H200 (800k 2 l VNC-hard 3 % faster at 8, 200k 2 l 13 % slower).
CELLS_PER_SOURCE = 4
# How many ways a box's rows are shared on CUDA; None: enough to fill the device (launch_shape).
SPLITS = None


def check_strategy(strategy: str) -> str:
    """``strategy`` if it is one of :data:`STRATEGIES`, else a ValueError naming them."""
    if strategy not in STRATEGIES:
        raise ValueError(f"strategy must be one of {', '.join(STRATEGIES)}; got {strategy!r}")
    return strategy


# A traversal expecting at least this many candidate sources per query is busy: it takes twice the splits, and
# several queries per thread (queries_per_thread). Measured on an H200 (bench/tune.py, docs/results/tune_h200_*.json):
# 1 query per thread is faster up to 8 mean edge lengths (about 700 candidates), 4 from 16 (about 5000).
BUSY_SOURCES = 2000.0


def queries_per_thread(device: wp.Device, work: float, most: int) -> int:
    """Queries per thread of the forward traversals: ``most`` on CUDA for a traversal of at least
    :data:`BUSY_SOURCES` candidates per query, where every source record a warp reads then serves ``most`` queries
    per thread; else one (small balls: a thread's box is then its own ball's, and a thread never straddles a jump of
    the Morton curve with a box spanning both sides). One on the CPU."""
    return most if device.is_cuda and work >= BUSY_SOURCES else 1


# Splits of a light traversal on CUDA: LIGHT_FILL x (resident threads / threads) ^ (2/3). Measured on an H200
# (nefertiti and its subdivisions, koala; VNC-soft and VNC-hard at 2-8 mean edge lengths): the best splits were about
# 10 at 50k vertices, 4 at 200k and 2 at 800k, where one split already gives three waves of threads: a thread's work
# varies with the mesh's density, and shorter threads leave a shorter tail (800k, 4 l: 2.58 -> 2.25 ms soft,
# 4.54 -> 4.04 ms hard).
LIGHT_FILL = 3.3


def launch_shape(device: wp.Device, count: int, per_thread: int = 1, work: float = 0.0) -> tuple[int, int]:
    """``(group size, splits)`` for ``count`` queries taken ``per_thread`` at a time, each expecting ``work``
    candidate sources: one warp of threads per group and on CUDA enough splits to fill the device several times
    (:data:`LIGHT_FILL`; a busy traversal four times: its threads wait on loads of long rows, and more of them hide
    it); one thread per group and no split on the (single-threaded) CPU device."""
    if device.is_cpu:
        return per_thread, 1
    if SPLITS is not None:
        return _CUDA_GROUP * per_thread, int(SPLITS)
    threads = -(-count // per_thread)
    resident = 2048 * max(int(getattr(device, "sm_count", 0) or 0), 1)
    if work >= BUSY_SOURCES:
        splits = (4 * resident) // max(threads, 1)
        cap = 32 * per_thread ** 0.5
    else:
        splits = round(LIGHT_FILL * (resident / max(threads, 1)) ** (2.0 / 3.0))
        cap = 16 * per_thread ** 0.5
    return _CUDA_GROUP * per_thread, int(np.clip(splits, 1, cap))


class Pool:
    """Scratch arrays reused from one call to the next: creating a ``wp.array`` costs more host time than the
    small kernels it feeds. The ``n``-th request of a call of one ``kind`` gets back the buffer of the previous
    such call with the same shape and dtype. Reuse is in stream order on one device, and scratch is never handed
    to the caller; calls whose backward pass keeps its intermediates use no pool (``pool=None``)."""

    _stores: dict = {}
    LIMIT = 128

    def __init__(self, device: wp.Device, kind: str, store: dict | None = None, limit: int | None = LIMIT):
        """``store``: a dict of buffers of one's own (e.g. the scratch of captured graphs, :mod:`vnc_warp._replay`),
        else the shared one of the device and stream; ``limit``: buffers kept in it (None: all)."""
        if store is None:
            key = (device.alias, device.stream.cuda_stream if device.is_cuda else 0)
            store = Pool._stores.setdefault(key, {})
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

    @staticmethod
    def clear() -> None:
        """Drop every pooled buffer (e.g. to return memory)."""
        Pool._stores.clear()


def _empty(pool: Pool | None, device, shape, dtype) -> wp.array:
    return wp.empty(shape, dtype=dtype, device=device) if pool is None else pool.empty(shape, dtype)


def _zeros(pool: Pool | None, device, shape, dtype) -> wp.array:
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


def bounds(x: wp.array, radius: wp.array, length: wp.array | None = None) -> Bounds:
    """Bounding box of ``x``, statistics of ``radius`` and ``length``: one launch, one small copy to the host.

    Raises:
        ValueError: a point of ``x`` has a NaN or infinite coordinate, or a radius is not positive and finite
            (counted in the same pass: values given on the device are checked at no extra cost).
    """
    device = x.device
    if length is None:
        length = wp.empty(0, dtype=wp.float32, device=device)
    stats = wp.array(np.array([np.inf] * 3 + [-np.inf] * 4 + [0.0] * 5, dtype=np.float32), device=device)
    stride = int(min(max(x.shape[0], radius.shape[0], length.shape[0]), 4096))
    wp.launch(_k.point_stats, dim=stride, inputs=[x, radius, length, stride], outputs=[stats], device=device,
              record_tape=False)
    s = stats.numpy().astype(np.float64)
    if s[10] > 0:
        raise ValueError(f"positions: {int(s[10])} of {x.shape[0]} point(s) have a NaN or infinite coordinate")
    if s[11] > 0:
        raise ValueError(f"scales (tau or radius): {int(s[11])} of {radius.shape[0]} value(s) are not positive and "
                         "finite")
    return Bounds(s[0:3], s[3:6], float(s[6]), float(s[7]) / max(radius.shape[0], 1), float(s[8]),
                  float(s[9]) / max(length.shape[0], 1))


def _grid_dims(ext: np.ndarray, h: float) -> np.ndarray:
    return np.floor(ext / h).astype(np.int64) + 1


def cell_size(b: Bounds, reach: float, sources: int, device: wp.Device, fraction: float | None = None) -> float:
    """Cell size for balls of typical radius ``reach``: ``fraction`` (default :data:`CELL_FRACTION`, half) of the
    radius (a box of cells then overshoots a ball, or a warp's group of balls, by half a radius at most per side),
    enlarged until the grid has at most ``4 x sources`` cells, so memory stays O(sources)."""
    ext = np.maximum(b.hi - b.lo, 0.0)
    scale = max(float(ext.max()), float(np.abs(np.concatenate([b.lo, b.hi])).max()), 1e-30)
    h = max((CELL_FRACTION if fraction is None else fraction) * reach, 1e-6 * scale)
    cap = max(CELLS_PER_SOURCE * sources, 4096)
    for _ in range(64):
        n = float(np.prod(_grid_dims(ext, h).astype(np.float64)))
        if n <= cap:
            break
        h *= 1.01 * (n / cap) ** (1.0 / 3.0)
    return h


def grid_cell(b: Bounds, reach: float, sources: int, device: wp.Device, max_per_thread: int = 1,
              busy_fraction: float | None = None) -> tuple[float, float]:
    """``(cell size, expected candidates per query)`` of a grid traversal over ``sources`` (see :func:`cell_size`);
    ``busy_fraction``: the cell size, as a fraction of ``reach``, of a busy traversal (one of several queries per
    thread, :func:`queries_per_thread`)."""
    h = cell_size(b, reach, sources, device)
    work = dense_fraction(b, reach, h) * sources
    if busy_fraction is not None and queries_per_thread(device, work, max_per_thread) > 1:
        h = cell_size(b, reach, sources, device, busy_fraction)
        work = max(work, dense_fraction(b, reach, h) * sources)
    return h, work


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


def _fine_bits(buckets: int, fine: bool) -> tuple[int, int]:
    """``(bits of a bucket index, Morton bits within a bucket)`` for sort keys of at most 31 bits."""
    bits = max(int(buckets - 1).bit_length(), 1)
    return bits, (min(FINE_BITS, 31 - bits) // 3) * 3 if fine else 0


# Morton bits that order a cell's sources for the ball kernels (3 per axis: 512 sub-cells), so that a run of sorted
# records is a small patch: ball_cells_kernel(chunks=True) then finds more runs wholly inside or outside a ball.
FINE_BITS = 9


def build_cells(points: wp.array, b: Bounds, h: float | None, pool: Pool | None = None, fine: bool = False) -> Cells:
    """Sort ``points`` (the sources) into a grid of cells of size ``h`` over ``b`` (``h=None``: one cell);
    ``fine``: each cell's sources along a Morton curve (:data:`FINE_BITS`; with one cell, all of them)."""
    device = points.device
    n = points.shape[0]
    origin = wp.vec3(*b.lo)
    if h is None:
        if fine:
            order = query_order(points, b, None, pool)
        else:
            order = _empty(pool, device, n, wp.int32)
            wp.launch(_k.iota, dim=n, outputs=[order], device=device, record_tape=False)
        first = _empty(pool, device, 2, wp.int32)
        wp.launch(_k.one_cell, dim=1, inputs=[n], outputs=[first], device=device, record_tape=False)
        return Cells(order, first, origin, 0.0, wp.vec3i(1, 1, 1))
    dims_np = _grid_dims(np.maximum(b.hi - b.lo, 0.0), h)
    dims = wp.vec3i(*[int(d) for d in dims_np])
    num_cells = int(np.prod(dims_np))
    bits, fine_bits = _fine_bits(num_cells, fine)
    keys = _empty(pool, device, 2 * n, wp.int32)
    values = _empty(pool, device, 2 * n, wp.int32)
    counts = _zeros(pool, device, num_cells + 1, wp.int32)
    wp.launch(_k.cell_keys, dim=n, inputs=[points, origin, 1.0 / h, dims, fine_bits], outputs=[keys, values, counts],
              device=device, record_tape=False)
    wp.utils.radix_sort_pairs(keys, values, n, end_bit=bits + fine_bits)
    first = _empty(pool, device, num_cells + 1, wp.int32)
    wp.utils.array_scan(counts, first, inclusive=False)
    return Cells(values[:n], first, origin, 1.0 / h, dims)


def _grid_args(inv_h: list, dims: list) -> list:
    """The per-grid arguments ``inv_h, dims0, .., dims3`` of :func:`kernels.vnc.tier_grid`'s kernels for 1 to 4
    grids (unused slots padded)."""
    return [wp.vec4(*(list(inv_h) + [0.0] * (4 - len(inv_h)))), *(list(dims) + [dims[0]] * (4 - len(dims)))]


def build_tier_cells(points: wp.array, length: wp.array, b: Bounds, hs: list, tier_hi: list, slots: list,
                     pool: Pool | None = None, fine: bool = True) -> list[Cells]:
    """One sort of the edges ``points`` (midpoints) for every length tier (``tier_hi``: the tiers' upper bounds,
    ascending, the last infinite; ``slots[t]``: tier ``t``'s grid, ``len(hs)`` for the bucket tested densely;
    :func:`kernels.vnc.tier_cell_keys`), each bucket along a Morton curve when ``fine`` (:data:`FINE_BITS`). Grid
    ``g`` has cells of size ``hs[g]`` over ``b`` (coarser for the longer edges, whose balls reach farther). Returns the
    :class:`Cells` of every grid, then (when some tier has no grid) the one cell of the dense bucket, all sharing one
    ``order``."""
    device = points.device
    n = points.shape[0]
    if not 1 <= len(hs) <= 4:
        raise ValueError(f"1 to 4 grids, got {len(hs)}")
    dims_np = [_grid_dims(np.maximum(b.hi - b.lo, 0.0), h) for h in hs]
    sizes = [int(np.prod(d)) for d in dims_np]
    base = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    buckets = int(base[-1]) + 1  # the dense bucket last
    keys = _empty(pool, device, 2 * n, wp.int32)
    values = _empty(pool, device, 2 * n, wp.int32)
    counts = _zeros(pool, device, buckets + 1, wp.int32)
    hi = [float(v) for v in tier_hi] + [np.inf] * (4 - len(tier_hi))
    slot = [int(v) for v in slots] + [len(hs)] * (4 - len(slots))
    origin = wp.vec3(*b.lo)
    dims = [wp.vec3i(*[int(v) for v in d]) for d in dims_np]
    bits, fine_bits = _fine_bits(buckets, fine)
    wp.launch(_k.tier_cell_keys, dim=n,
              inputs=[points, origin, *_grid_args([1.0 / h for h in hs], dims),
                      wp.vec4i(*[int(v) for v in base[:len(hs)]] + [0] * (4 - len(hs))), length, wp.vec4(*hi),
                      wp.vec4i(*slot), len(hs), buckets - 1, fine_bits],
              outputs=[keys, values, counts], device=device, record_tape=False)
    wp.utils.radix_sort_pairs(keys, values, n, end_bit=bits + fine_bits)
    first = _empty(pool, device, buckets + 1, wp.int32)
    wp.utils.array_scan(counts, first, inclusive=False)
    order = values[:n]
    cells = [Cells(order, first[int(base[g]):int(base[g + 1]) + 1], origin, 1.0 / hs[g], dims[g])
             for g in range(len(hs))]
    if len(slots) and max(slots) >= len(hs):
        cells.append(Cells(order, first[buckets - 1:buckets + 1], origin, 0.0, wp.vec3i(1, 1, 1)))
    return cells


# A group's threads walk their own boxes when the group's shared box has this many times more cells than the
# largest box of one thread (see kernels.vnc.group_boxes).
SPREAD = 8.0


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


def query_order(points: wp.array, b: Bounds, cache: dict | None = None, pool: Pool | None = None) -> wp.array:
    """The queries sorted along a Morton curve, so that consecutive queries are close together.

    ``cache``: a dict (e.g. a mesh's) that keeps the order of the first call for every later call with as many
    queries on the same device. The order only decides how queries are grouped, never which pairs are summed,
    so a kept order stays correct when the points move (a flow); it only becomes less tight."""
    device = points.device
    count = points.shape[0]
    key = ("query_order", str(device), count)
    if cache is not None and key in cache:
        return cache[key]
    # a kept order must not be a pooled buffer; one made while capturing is not kept (it is only computed when the
    # graph runs) and must live as long as the graph: the pool's
    keep = pool if cache is None or device.is_capturing else None
    keys = _empty(keep, device, 2 * count, wp.int32)
    values = _empty(keep, device, 2 * count, wp.int32)
    extent = float(np.max(b.hi - b.lo))
    scale = 1024.0 / extent if extent > 0 else 0.0
    wp.launch(_k.morton_keys, dim=count, inputs=[points, wp.vec3(*b.lo), scale], outputs=[keys, values],
              device=device, record_tape=False)
    wp.utils.radix_sort_pairs(keys, values, count, end_bit=30)
    order = values[:count]
    if cache is not None and not device.is_capturing:  # a captured order is only computed when its graph runs
        cache[key] = order
    return order


def build_groups(points: wp.array, radius: wp.array, pads: list, cells: list, b: Bounds, *,
                 spatial_order: bool, splits: int | None = None, like: Groups | None = None, per_thread: int = 1,
                 work: float = 0.0, cache: dict | None = None, pool: Pool | None = None) -> list[Groups]:
    """Group the queries ``points`` (balls of radius ``radius[k] + pad``) for traversals of ``cells`` (a
    :class:`Cells` per pad), one :class:`Groups` per pad of ``pads`` (at most 4: the edge-length tiers of
    :func:`ball_plans`), in the same launches; the first pad's traversal decides the splits, the others share them.

    ``spatial_order`` sorts the queries along a Morton curve first (:func:`query_order`, kept in ``cache``), so a
    group's balls are close together (only worth it for groups of more than one query over more than one cell).
    ``like``: reuse the order, group size and queries per thread of another traversal of the same queries (their
    partial sums then line up), and its splits or fewer. ``work``: expected candidate sources per query (see
    :func:`launch_shape`).
    """
    device = points.device
    count = points.shape[0]
    size, default_splits = launch_shape(device, count, per_thread, work)
    if like is not None:
        # a traversal adding to ``like``'s partial sums: at most its splits (fewer when it expects less work)
        order, size, per_thread = like.order, like.size, like.per_thread
        splits = like.splits if splits is not None else min(like.splits, default_splits)
    else:
        splits = default_splits if splits is None else splits
        if spatial_order:
            order = query_order(points, b, cache, pool)
        else:
            order = _empty(pool, device, count, wp.int32)
            wp.launch(_k.iota, dim=count, outputs=[order], device=device, record_tape=False)
    num_groups = (count + size - 1) // size
    if size // per_thread > 32:
        raise ValueError(f"groups of at most 32 threads (kernels.vnc.group_boxes), got {size // per_thread}")
    pads = [float(p) for p in pads]
    if not 1 <= len(pads) <= 4 or len(cells) != len(pads):
        raise ValueError(f"1 to 4 pads, each with its cells; got {len(pads)} pads and {len(cells)} cells")
    box_lo = _empty(pool, device, (len(pads), num_groups), wp.vec3i)
    box_hi = _empty(pool, device, (len(pads), num_groups), wp.vec3i)
    # float32 rounding of p +- r must never drop a cell that holds a source within reach
    margin = 1e-6 * max(float(np.abs(np.concatenate([b.lo, b.hi])).max()), b.rmax)
    one_cell = [tuple(c.dims) == (1, 1, 1) for c in cells]
    if all(one_cell):  # one cell: every box is that cell
        box_lo.zero_()
        box_hi.zero_()
    else:
        if len({(tuple(c.origin)) for c in cells}) > 1:
            raise ValueError("the traversals grouped together share the origin of their grids")
        threads = -(-count // per_thread)
        acc = _zeros(pool, device, (3, len(pads), num_groups), wp.vec3i)  # lowest, highest cells, most cells
        wp.launch(_k.thread_extents, dim=threads,
                  inputs=[points, order, radius, margin, count, per_thread, size // per_thread, cells[0].origin,
                          *_grid_args([c.inv_h for c in cells], [c.dims for c in cells]),
                          wp.vec4(*(pads + [0.0] * (4 - len(pads))))],
                  outputs=[acc[0], acc[1], acc[2]], device=device, record_tape=False)
        wp.launch(_k.group_boxes, dim=(len(pads), num_groups),
                  inputs=[acc[0], acc[1], acc[2], SPREAD if size > per_thread else 1.0e30], outputs=[box_lo, box_hi],
                  device=device, record_tape=False)
    groups = [Groups(order, box_lo[t], box_hi[t], size, splits, count, num_groups * size, p + margin, per_thread)
              for t, p in enumerate(pads)]
    return groups


def plan(points: wp.array, radius: wp.array, sources: wp.array, b: Bounds, strategy: str, reach: float,
         pad: float = 0.0, *, splits: int | None = None, max_per_thread: int = 1, cache: dict | None = None,
         pool: Pool | None = None, fine: bool = False, busy_cell: float | None = None) -> tuple[Cells, Groups]:
    """Cells over ``sources`` (``fine``: in Morton order within each, see :func:`build_cells`) and groups of the
    query ``points`` (balls ``radius[k] + pad``, typically ``reach``) for a concrete "grid" or "dense" strategy, with
    up to ``max_per_thread`` queries per thread (:func:`queries_per_thread`, from the expected candidates per query
    that also set the splits; ``busy_cell``: see :func:`grid_cell`)."""
    if strategy == "dense":
        h, work = None, float(sources.shape[0])
    else:
        h, work = grid_cell(b, reach, sources.shape[0], points.device, max_per_thread, busy_cell)
    cells = build_cells(sources, b, h, pool, fine)
    return cells, _groups(points, radius, [pad], [cells], b, work, splits=splits, max_per_thread=max_per_thread,
                          cache=cache, pool=pool)[0]


def _groups(points: wp.array, radius: wp.array, pads: list, cells: list, b: Bounds, work: float, *,
            splits: int | None, max_per_thread: int, like: Groups | None = None, cache: dict | None = None,
            pool: Pool | None = None) -> list[Groups]:
    """:func:`build_groups` for traversals of ``cells`` (one per pad), the first expecting ``work`` candidates per
    query."""
    per_thread = queries_per_thread(points.device, work, max_per_thread) if like is None else like.per_thread
    size, _ = launch_shape(points.device, points.shape[0], per_thread)
    # queries in Morton order for the dense traversal too: a warp's balls then lie together, and a source beyond the
    # cut-off of all of them costs it no exp2
    return build_groups(points, radius, pads, cells, b, spatial_order=size > 1, splits=splits, like=like,
                        per_thread=per_thread, work=work, cache=cache, pool=pool)


# Edge-length tiers of the ball (Eq. 1-2) kernels: an edge reaches a ball from as far as half its length beyond the
# radius, so edges are traversed in tiers of similar length, each with its own pad; a few long edges (scans have
# them) then do not widen every query's box. Tier bounds: TIER_BASE x mean edge length, doubling, at most MAX_TIERS.
# Three, not four: a tier of a fraction of a percent of the edges still costs a launch that reads every query and
# walks its box's rows (at 2 mean edge lengths on an H200: nefertiti subdivided to 800k vertices 2.57 -> 2.51 ms,
# koala subdivided to 200k 0.87 -> 0.82 ms; the same on the 50k meshes, whose longest edges go to a dense tail).
TIER_BASE = 1.5
MAX_TIERS = 3


# The first edge-length tier of the ball kernels takes all edges when that widens its balls (radius + half the
# longest edge) by at most this fraction.
TIER_GROW = 0.02


# Cell size of a busy ball traversal, as a fraction of the reach (CELL_FRACTION otherwise): longer rows, whose runs
# of edge records the chunked ball kernel can test as a whole (on an H200 4-15 % faster than half the reach at 16-32
# mean edge lengths, within 5 % either way at a quarter of the diagonal: docs/results/tune_h200_chunks.json).
BUSY_BALL_CELL = 1.0


# A tier with at most this many query x edge pairs in all is traversed densely: a few long edges are cheaper to
# test against every query than to reach through a grid whose boxes they widen. Per device kind: a GPU tests 2^26
# pairs in tens of microseconds, the CPU device (one thread) in about a second.
DENSE_TIER_PAIRS = {"cuda": 1 << 26, "cpu": 1 << 16}


# A single-scale ball traversal through the grid, on a mesh whose longest edge would widen every ball (where
# ball_plans takes edge-length tiers), traverses pieces of the edges instead (piece_plan): every edge cut into equal
# pieces no longer than piece_length, each sorted into the grid by its centre, so that one traversal with a pad of
# half a piece finds them all. On an H200 VNC-hard took 22-32 % less time than with tiers at 2-4 mean edge lengths on
# nefertiti and koala (koala 4 l: 0.50 -> 0.38 ms), 14 % less at 8-16, 8-9 % at 32; 11-14 % less at 2-4 on their
# subdivisions to 200k and 800k vertices, 2-5 % at 8-16. On the CPU (one thread) 0-18 % less at 2-8.
PIECES = True
# The piece length in mean edge lengths for balls of radius r (in mean edge lengths):
# max(PIECE[0], min(PIECE[1], r / 2), r / 4). Shorter pieces widen the balls less, longer ones are fewer; measured on
# an H200 (nefertiti, koala and their subdivisions to 200k and 800k vertices, pieces of 1-8 edge lengths), the best
# were 1.5 at 2 edge lengths, 2 at 4-8, a quarter of the radius from 16 up.
PIECE = (1.5, 2.0)
# On the CPU device (one thread), a single-scale grid traversal of a mesh's own vertices reads pieces of its edges
# that do not depend on the radius, sorted and packed once and kept with the mesh (as trimesh keeps an R-tree of its
# edges): CPU_PIECES = (piece, cell) in mean edge lengths, None to sort per call. Per call, the edges' fields, sort and
# packing cost one thread more than the traversal itself when the queries are few (nefertiti, 2000 of its 50k
# vertices at 2 l: 9 of 14 ms). Timed on the 2-core CI machine (nefertiti's 2000 points, all of spot, at 2 / 5 / 10 l),
# pieces and cells of 1-3 by 1-6 edge lengths: (2, 3) was best or within 5 % at every radius but spot's 10 l, 10 %
# slower than a grid of cells of half the radius sorted for it (one row of the chunked kernel reads more records).
CPU_PIECES = (2.0, 3.0)


@dataclass
class Pieces:
    """The pieces of the edges (:func:`kernels.vnc.piece_keys`): ``counts[j]`` pieces of edge ``j`` (at most
    ``length`` long), sorted slot ``i`` holding piece ``piece_index[s]`` of edge ``piece_edge[s]``, ``s =
    cells.order[i]``; ``capacity`` slots in all, those past the last piece sorted last with ``piece_edge = -1``."""

    counts: wp.array
    piece_edge: wp.array
    piece_index: wp.array
    capacity: int
    length: float


def uses_pieces(strategy: str, b: Bounds, any_length: bool = False) -> bool:
    """Whether a single-scale ball traversal (``strategy`` "grid" or "dense") takes pieces of the edges
    (:func:`piece_plan`) instead of edge-length tiers (:func:`ball_plans`): on a grid, when the longest edge would
    widen the balls (the tiers' rule; :data:`PIECES`; ``any_length``: whatever the lengths, as the pieces kept with a
    mesh on the CPU, :data:`CPU_PIECES`), unless the ball kernels are set to "half" records
    (``kernels.vnc.BALL_VARIANT``, as ``bench.tune`` does), which cannot hold a piece."""
    return (PIECES and strategy == "grid" and _k.BALL_VARIANT["form"] != "half" and b.lmean > 0
            and (any_length or b.lmax > _first_tier(b)))


def _first_tier(b: Bounds) -> float:
    """The upper edge length of the first tier of :func:`ball_plans`: every edge when that widens the balls (radius +
    half the longest edge) by at most :data:`TIER_GROW`."""
    return max(TIER_BASE * b.lmean, 2.0 * ((1.0 + TIER_GROW) * (b.rmean + 0.5 * TIER_BASE * b.lmean) - b.rmean))


def piece_length(b: Bounds) -> float:
    """The longest piece of an edge in a ball traversal of :func:`piece_plan` (mesh units, see :data:`PIECE`)."""
    r = ball_reach(b)
    return b.lmean * max(PIECE[0], min(PIECE[1], 0.5 * r), 0.25 * r)


def piece_capacity(lengths: np.ndarray, piece: float) -> int:
    """Slots for the pieces of edges of host ``lengths`` (float32, as on the device, where float32 rounding may make
    them a part in 1e6 longer): at least the device's count of :func:`kernels.vnc.piece_counts`."""
    k = np.ceil(lengths.astype(np.float64) * ((1.0 + 1e-5) / piece))
    return int(np.maximum(k, 1.0).sum()) + 16


@dataclass
class PieceGrid:
    """The edge side of a traversal over pieces (:func:`piece_grid`): the pieces sorted into ``cells``, the pad that
    every ball takes (half a piece, float32 slack included) and the expected candidates per query of the radii the
    cells were chosen for (``work``; None when the cell size was given, as for every radius)."""

    cells: Cells
    pieces: Pieces
    pad: float
    work: float | None


def piece_grid(x: wp.array, edges: wp.array, length: wp.array, b: Bounds, strategy: str, *, piece: float | None = None,
               cell: float | None = None, fine: bool | None = None, capacity=None, max_per_thread: int = 1,
               pool: Pool | None = None) -> PieceGrid:
    """Cut the edges (``x[edges]``, of ``length``) into equal pieces no longer than ``piece`` (default
    :func:`piece_length`) and sort them by their centres into a grid over ``b``: cells of ``cell`` (capped as in
    :func:`cell_size`), default :func:`grid_cell` for the reach of ``b``'s radii plus half a piece; ``fine``: a Morton
    order within each cell (default: when the traversal of ``b``'s radii tests runs, :func:`chunked`).

    ``capacity(piece)``: the slots for the pieces (:func:`piece_capacity`), when the lengths are known on the host;
    None reads the exact count back from the device."""
    device = x.device
    ne = length.shape[0]
    piece = piece_length(b) if piece is None else float(piece)
    counts = _empty(pool, device, ne, wp.int32)
    offsets = _empty(pool, device, ne, wp.int32)
    wp.launch(_k.piece_counts, dim=ne, inputs=[length, 1.0 / piece], outputs=[counts], device=device,
              record_tape=False)
    wp.utils.array_scan(counts, offsets, inclusive=False)
    if capacity is None:
        n = int(offsets[ne - 1:].numpy()[0] + counts[ne - 1:].numpy()[0])
    else:
        n = int(capacity(piece))
    # float32 rounding may leave a piece a part in 1e6 longer than `piece`
    pad = 0.5 * min(piece, b.lmax) * (1.0 + 1e-5)
    if cell is None:
        h, work = grid_cell(b, b.rmean + pad, n, device, max_per_thread, BUSY_BALL_CELL)
    else:
        h, work = cell_size(b, float(cell), n, device, fraction=1.0), None
    dims_np = _grid_dims(np.maximum(b.hi - b.lo, 0.0), h)
    dims = wp.vec3i(*[int(d) for d in dims_np])
    num_cells = int(np.prod(dims_np))
    if fine is None:
        fine = chunked(strategy, b, num_cells == 1, device)
    bits, fine_bits = _fine_bits(num_cells + 1, fine)
    keys = _empty(pool, device, 2 * n, wp.int32)
    values = _empty(pool, device, 2 * n, wp.int32)
    piece_edge = _empty(pool, device, n, wp.int32)
    piece_index = _empty(pool, device, n, wp.int32)
    cell_counts = _zeros(pool, device, num_cells + 1, wp.int32)
    origin = wp.vec3(*b.lo)
    wp.launch(_k.piece_keys, dim=n, inputs=[x, edges, counts, offsets, origin, 1.0 / h, dims, fine_bits],
              outputs=[keys, values, piece_edge, piece_index, cell_counts], device=device, record_tape=False)
    wp.utils.radix_sort_pairs(keys, values, n, end_bit=bits + fine_bits)
    first = _empty(pool, device, num_cells + 1, wp.int32)
    wp.utils.array_scan(cell_counts, first, inclusive=False)
    cells = Cells(values[:n], first, origin, 1.0 / h, dims)
    return PieceGrid(cells, Pieces(counts, piece_edge, piece_index, n, piece), pad, work)


def piece_plan(points: wp.array, radius: wp.array, x: wp.array, edges: wp.array, length: wp.array, b: Bounds,
               strategy: str, *, capacity=None, splits: int | None = None, max_per_thread: int = 1,
               cache: dict | None = None, pool: Pool | None = None,
               grid: PieceGrid | None = None) -> tuple[Cells, Groups, Pieces]:
    """One grid traversal of the ball kernels over pieces of the edges (no longer than :func:`piece_length`):
    a piece crosses a ball only if its centre is within the radius plus half a piece, whatever the longest edge.

    ``grid``: the pieces already sorted (:func:`piece_grid`, e.g. kept with the mesh: :data:`CPU_PIECES`), else
    sorted here for ``b``'s radii (``capacity``: see :func:`piece_grid`). Returns the cells, the groups of the query
    ``points`` (balls of ``radius`` plus the grid's pad) and the pieces."""
    if grid is None:
        grid = piece_grid(x, edges, length, b, strategy, capacity=capacity, max_per_thread=max_per_thread, pool=pool)
    work = grid.work
    if work is None:  # cells not chosen for these radii
        work = dense_fraction(b, b.rmean + grid.pad, 1.0 / grid.cells.inv_h) * grid.pieces.capacity
    groups = _groups(points, radius, [grid.pad], [grid.cells], b, work, splits=splits, max_per_thread=max_per_thread,
                     cache=cache, pool=pool)[0]
    return grid.cells, groups, grid.pieces


def ball_reach(b: Bounds) -> float:
    """The mean ball radius of a ball traversal in mean edge lengths (:func:`kernels.vnc.ball_variant`)."""
    return b.rmean / max(b.lmean, 1e-30)


def chunked(strategy: str, b: Bounds, one_cell: bool, device: wp.Device) -> bool:
    """Whether a ball traversal (``strategy`` "grid" or "dense", over ``one_cell`` or more) on ``device`` tests runs
    of sorted edges as a whole (:func:`kernels.vnc.ball_variant`)."""
    return bool(_k.ball_variant(strategy, 1, ball_reach(b), one_cell, device.is_cuda)["chunks"])


def ball_plans(points: wp.array, radius: wp.array, mid: wp.array, length: wp.array, b: Bounds, strategy: str,
               *, splits: int | None = None, max_per_thread: int = 1, cache: dict | None = None,
               pool: Pool | None = None, tier_size=None) -> list[tuple[Cells, Groups]]:
    """The traversals of the ball kernels: one over all edges ("dense", or edges of similar lengths), else one per
    edge-length tier through the grid, then one dense traversal of the tiers with few pairs (``tier_size(lo, hi)``:
    the number of edges with ``lo < length <= hi``, when known on the host; a tier known to be empty is skipped).

    Every traversal reads one sort of the edges (:func:`build_tier_cells`: one packing of the edge records serves
    them all) and shares the query order and queries per thread of the first, the short edges', whose partial sums
    it adds to; a later traversal takes fewer splits when it expects fewer candidates (never more than the first).
    """
    # the first tier takes every edge when that widens its balls by at most TIER_GROW (the other tiers' launches
    # would cost more than the few extra candidates)
    first_hi = _first_tier(b)
    if strategy == "dense" or b.lmax <= first_hi:
        pad = 0.5 * b.lmax
        # (the order only speeds the chunked kernel up: a grid of one cell, a tiny mesh's, may read unordered runs)
        fine = chunked(strategy, b, strategy == "dense", points.device)
        return [plan(points, radius, mid, b, strategy, b.rmean + pad, pad, splits=splits,
                     max_per_thread=max_per_thread, cache=cache, pool=pool, fine=fine, busy_cell=BUSY_BALL_CELL)]
    bounds_ = [-1.0]
    while len(bounds_) < MAX_TIERS and TIER_BASE * b.lmean * 2 ** (len(bounds_) - 1) < b.lmax:
        bounds_.append(TIER_BASE * b.lmean * 2 ** (len(bounds_) - 1))
    bounds_.append(np.inf)
    tiers = list(zip(bounds_[:-1], bounds_[1:]))
    sizes = [None if tier_size is None else int(tier_size(lo, hi)) for lo, hi in tiers]
    limit = DENSE_TIER_PAIRS["cuda" if points.device.is_cuda else "cpu"]
    # the first tier (the short edges) is always a grid traversal: it sets the order and splits every tier shares
    grid = [t for t, n in enumerate(sizes) if t == 0 or n is None or n * points.shape[0] > limit]
    slots = [grid.index(t) if t in grid else len(grid) for t in range(len(tiers))]
    dense = sum(n for t, n in enumerate(sizes) if t not in grid)
    # the pads of the grid tiers, and their cells: the same fraction of each tier's own reach (a tier of long edges
    # reaches farther, and fewer of its edges share a cell: finer cells would only add empty rows to its boxes)
    pads = [0.5 * min(tiers[t][1], b.lmax) for t in grid]
    h0, _ = grid_cell(b, b.rmean + pads[0], mid.shape[0] if sizes[0] is None else sizes[0], points.device,
                      max_per_thread, BUSY_BALL_CELL)
    hs = [h0 * (b.rmean + p) / (b.rmean + pads[0]) for p in pads]
    # the edges of a cell along a Morton curve only for traversals that test runs of them as a whole
    ext = np.maximum(b.hi - b.lo, 0.0)
    fine = dense > 0 or any(chunked(strategy, b, tuple(_grid_dims(ext, h)) == (1, 1, 1), points.device) for h in hs)
    cells = build_tier_cells(mid, length, b, hs, [hi for _, hi in tiers], slots, pool, fine)
    works = [dense_fraction(b, b.rmean + p, h) * (mid.shape[0] if sizes[t] is None else sizes[t])
             for p, h, t in zip(pads, hs, grid)]
    # the grid tiers' groups in one pair of launches: boxes of the same queries, each in its tier's grid and pad
    groups = _groups(points, radius, pads, cells[:len(grid)], b, works[0], splits=splits,
                     max_per_thread=max_per_thread, cache=cache, pool=pool)
    lead = groups[0]
    plans = []
    for g, grp in enumerate(groups):
        if g > 0 and splits is None:  # fewer splits for a tier that expects less work
            grp = replace(grp, splits=min(lead.splits, launch_shape(points.device, points.shape[0], lead.per_thread,
                                                                    works[g])[1]))
        plans.append((cells[g], grp))
    if dense > 0:
        plans.append((cells[-1], _groups(points, radius, [0.5 * b.lmax], cells[-1:], b, float(dense), splits=splits,
                                         max_per_thread=max_per_thread, like=lead, cache=cache, pool=pool)[0]))
    return plans
