"""The uniform grid of the VNC engine: how the kernels of :mod:`kernels.vnc_sums` find their (query, source) pairs.

Read :mod:`kernels.vnc_reference` first: it sums the same pairs with a ``wp.Bvh`` query per thread. Here the
*sources* (edges, pieces of edges, or vertices in an adjoint pass) are sorted by the row-major index of a uniform grid
cell (:func:`cell_keys`, :func:`tier_cell_keys`, :func:`piece_keys`), so that the cells ``x0..x1`` of one ``(y, z)``
row are one contiguous range ``first[c(x0, y, z)] .. first[c(x1, y, z) + 1]``. *Queries* are taken in *groups* of
consecutive threads (a CUDA warp on the GPU, one thread on the CPU) that share one box of cells (:func:`thread_extents`,
:func:`group_boxes`), so the threads of a group walk the same sources in lockstep: their loads are uniform and their
loop bounds equal (only the cut-off test differs per thread); a group whose balls are far apart lets each thread walk
the box of its own ball(s) instead. A grid of one cell makes the same kernels an all-pairs (dense) traversal. The rows
of a box are split over ``ns`` threads (:func:`row_walk`, :func:`row_share`, :func:`row_part`) for occupancy; each
writes its partial sums to row ``s`` of a ``(ns, Q)`` array that a reduction adds up in a fixed order, so results are
deterministic. A thread of one query reads of each row only the cells some ball of its warp reaches
(:func:`walk_span`).

The ball kernels (Eqs. 1-2) reach an edge from up to half its length beyond the radius. A single-scale traversal reads
*pieces* of the edges (:func:`piece_counts`, :func:`piece_keys`, :func:`pack_piece_sources`), so that half a piece, not
half the longest edge, widens the balls; the multi-scale traversal reads whole edges sorted once for all their
edge-length tiers (:func:`tier_cell_keys`). Either way each cell's records can run along a Morton curve, so that a run
of ``chunk`` consecutive records is a small patch whose box (:func:`chunk_boxes_kernel`) can be tested against a
thread's balls as a whole.

Every cell coordinate is clamped to the grid, so a point outside the box a grid was made for is still found: it counts
in the nearest boundary cell; a culled row walk then takes its ball's centre clamped to the box (:func:`clamp_ball`).
A grid planned for one set of positions thus stays exact for the next (a flow step), only slower where points left
its box.
"""

import functools

import warp as wp

from .vnc_terms import segment_frame

@wp.func_native(
    """
#if defined(__CUDA_ARCH__)
    const float4 v = __ldg(reinterpret_cast<const float4*>(a.data) + i);
    return wp::vec4(v.x, v.y, v.z, v.w);
#else
    return a.data[i];
#endif
"""
)
def load4(a: wp.array(dtype=wp.vec4), i: int) -> wp.vec4:
    """``a[i]`` as one 128-bit read-only load on CUDA (a ``wp.vec4`` element is otherwise read as four 32-bit
    loads). The traversal kernels read two or three such records per pair, the same for every thread of a
    group: this quarters their load instructions. ``a`` must be a contiguous array of its own allocation."""
    ...


@wp.func
def cell_coord(p: wp.vec3, origin: wp.vec3, inv_h: float, dims: wp.vec3i):
    """Integer cell of ``p`` in a grid of ``dims`` cells of size ``1 / inv_h`` from ``origin``, clamped to the grid."""
    q = (p - origin) * inv_h
    return wp.vec3i(
        int(wp.clamp(wp.floor(q[0]), 0.0, float(dims[0] - 1))),
        int(wp.clamp(wp.floor(q[1]), 0.0, float(dims[1] - 1))),
        int(wp.clamp(wp.floor(q[2]), 0.0, float(dims[2] - 1))),
    )


@wp.func
def cell_index(c: wp.vec3i, dims: wp.vec3i):
    """Row-major cell index, x fastest."""
    return c[0] + dims[0] * (c[1] + dims[1] * c[2])


@wp.func
def box_rows(lo: wp.vec3i, hi: wp.vec3i):
    """Number of ``(y, z)`` rows of the cell box ``lo..hi``."""
    return (hi[1] - lo[1] + 1) * (hi[2] - lo[2] + 1)


@wp.func
def cells_span(row: int, cells: wp.vec2i, lo: wp.vec3i, hi: wp.vec3i, dims: wp.vec3i, first: wp.array(dtype=int)):
    """Sorted-source range ``[begin, end)`` of the cells ``cells[0]..cells[1]`` of row ``row`` of the box (empty
    where ``cells[0] > cells[1]``)."""
    ny = hi[1] - lo[1] + 1
    base = dims[0] * (lo[1] + row % ny + dims[1] * (lo[2] + row // ny))
    out = wp.vec2i(0, 0)
    if cells[0] <= cells[1]:
        out = wp.vec2i(first[base + cells[0]], first[base + cells[1] + 1])
    return out


@wp.func
def row_span(row: int, lo: wp.vec3i, hi: wp.vec3i, dims: wp.vec3i, first: wp.array(dtype=int)):
    """Sorted-source range ``[begin, end)`` of row ``row`` of the box: cells ``lo.x..hi.x`` at one ``(y, z)``."""
    return cells_span(row, wp.vec2i(lo[0], hi[0]), lo, hi, dims, first)


@wp.func
def thread_span_box(grp: int, plo: wp.vec3, phi: wp.vec3, box_lo: wp.array(dtype=wp.vec3i),
                    box_hi: wp.array(dtype=wp.vec3i), origin: wp.vec3, inv_h: float, dims: wp.vec3i):
    """Cell box walked by a thread: its group's shared box, or (a group marked ``box_lo.x = -1`` by
    :func:`group_boxes`, whose balls are far apart) the cells of the thread's own extent ``plo..phi``."""
    lo = box_lo[grp]
    hi = box_hi[grp]
    if lo[0] < 0:
        lo = cell_coord(plo, origin, inv_h, dims)
        hi = cell_coord(phi, origin, inv_h, dims)
    return lo, hi


@wp.func
def thread_box(grp: int, p: wp.vec3, reach: float, box_lo: wp.array(dtype=wp.vec3i), box_hi: wp.array(dtype=wp.vec3i),
               origin: wp.vec3, inv_h: float, dims: wp.vec3i):
    """:func:`thread_span_box` of a thread with one query, the ball ``|x - p| <= reach``."""
    e = wp.vec3(reach, reach, reach)
    return thread_span_box(grp, p - e, p + e, box_lo, box_hi, origin, inv_h, dims)


# a coordinate of an empty (or masked) query slot: its squared distance to any source is far beyond any cut-off
FAR = wp.constant(1.0e18)

# A box with at least this many rows per split is shared out by whole rows (split ``s`` takes rows ``s, s + ns, ..``);
# a box with fewer rows by parts of every row. Either way a split reads the ranges of the rows it walks and no others.
ROWS_PER_SPLIT = wp.constant(2)


@wp.func
def row_walk(nrows: int, s: int, ns: int):
    """``(first row, row step)`` of split ``s`` of ``ns`` over a box of ``nrows`` rows: every ``ns``-th row from
    row ``s`` when the box has many rows, else every row (each shared with :func:`row_share`)."""
    out = wp.vec2i(0, 1)
    if nrows >= ROWS_PER_SPLIT * ns:
        out = wp.vec2i(s, ns)
    return out


@wp.func
def box_cells(lo: wp.vec3i, hi: wp.vec3i):
    """Number of cells of the box ``lo..hi``."""
    return float(hi[0] - lo[0] + 1) * float(hi[1] - lo[1] + 1) * float(hi[2] - lo[2] + 1)


# For the multi-scale kernels (:func:`row_part`): a row with at least this many candidates per split is shared by
# all splits; shorter rows go whole to one split each, in turn.
LONG_ROW = wp.constant(8)


@wp.func
def row_part(span: wp.vec2i, row: int, s: int, ns: int):
    """The candidates of split ``s`` of ``ns`` in row ``row`` of a box when every split walks every row: part ``s``
    of a long row, the whole of every ``ns``-th short row. The multi-scale kernels use it: their few splits and
    costly pairs make balance matter more than the rows each split reads."""
    n = span[1] - span[0]
    out = wp.vec2i(span[0], span[0])
    if n >= LONG_ROW * ns:
        out = wp.vec2i(span[0] + (n * s) // ns, span[0] + (n * (s + 1)) // ns)
    elif row % ns == s:
        out = span
    return out


@wp.func
def row_share(span: wp.vec2i, s: int, ns: int, step: int):
    """The candidates of split ``s`` of ``ns`` in a row ``span`` it walks with row step ``step``
    (:func:`row_walk`): the whole row when rows are dealt out, else part ``s`` of it."""
    out = span
    if step == 1:
        n = span[1] - span[0]
        out = wp.vec2i(span[0] + (n * s) // ns, span[0] + (n * (s + 1)) // ns)
    return out


@wp.func
def spread_bits(v: int):
    """The low 10 bits of ``v`` moved to every third bit (Morton code)."""
    x = v & 1023
    x = (x | (x << 16)) & 50331903
    x = (x | (x << 8)) & 50393103
    x = (x | (x << 4)) & 51130563
    x = (x | (x << 2)) & 153391689
    return x


@wp.func
def fine_code(q: wp.vec3, c: wp.vec3i, bits: int):
    """Morton code of ``bits / 3`` bits per axis of the position ``q`` (in cell units) inside its cell ``c``: sorts
    a cell's sources along a curve, so that a run of consecutive records is a small patch."""
    b = bits // 3
    if b == 0:
        return 0
    top = float((1 << b) - 1)
    s = float(1 << b)
    x = int(wp.clamp((q[0] - float(c[0])) * s, 0.0, top))
    y = int(wp.clamp((q[1] - float(c[1])) * s, 0.0, top))
    z = int(wp.clamp((q[2] - float(c[2])) * s, 0.0, top))
    return spread_bits(x) | (spread_bits(y) << 1) | (spread_bits(z) << 2)


@wp.kernel(enable_backward=False)
def point_stats(
    x: wp.array(dtype=wp.vec3),
    radius: wp.array(dtype=float),
    length: wp.array(dtype=float),
    stride: int,
    stats: wp.array(dtype=float),
    partial: wp.array2d(dtype=float),
):
    """Bounding box of ``x``, radius statistics and the longest edge in one strided pass.

    ``stats`` is preset to ``[+inf] * 3 + [-inf] * 4 + [0, 0, 0, 0, 0]`` and becomes
    ``[lo.xyz, hi.xyz, max radius, sum radius, max length, sum length, bad points, bad radii]``: the counts of
    points with a NaN or infinite coordinate and of radii that are not positive and finite (which would otherwise
    come out as silent zeros). The two sums are this thread's part in ``partial[i]`` ((stride, 2)), added by
    :func:`kernels.reduce.fold_stats` in a fixed order: an atomic float sum would add in the order the threads
    finish, and the plans built on these means would part between two runs.
    """
    i = wp.tid()
    lo = wp.vec3(1.0e30)
    hi = wp.vec3(-1.0e30)
    bad_x = float(0.0)
    for k in range(i, x.shape[0], stride):
        if wp.isfinite(x[k]):
            lo = wp.min(lo, x[k])
            hi = wp.max(hi, x[k])
        else:
            bad_x += 1.0
    rmax = float(-1.0e30)
    rsum = float(0.0)
    bad_r = float(0.0)
    for k in range(i, radius.shape[0], stride):
        if wp.isfinite(radius[k]) and radius[k] > 0.0:
            rmax = wp.max(rmax, radius[k])
            rsum += radius[k]
        else:
            bad_r += 1.0
    lmax = float(0.0)
    lsum = float(0.0)
    for k in range(i, length.shape[0], stride):
        lmax = wp.max(lmax, length[k])
        lsum += length[k]
    for c in range(3):
        wp.atomic_min(stats, c, lo[c])
        wp.atomic_max(stats, 3 + c, hi[c])
    wp.atomic_max(stats, 6, rmax)
    partial[i, 0] = rsum
    wp.atomic_max(stats, 8, lmax)
    partial[i, 1] = lsum
    wp.atomic_add(stats, 10, bad_x)
    wp.atomic_add(stats, 11, bad_r)


@wp.func
def cell_key(p: wp.vec3, origin: wp.vec3, inv_h: float, dims: wp.vec3i, fine_bits: int):
    """``(sort key, cell)`` of a source at ``p``: its row-major cell index shifted left by ``fine_bits`` that order a
    cell's sources along a Morton curve (:func:`fine_code`)."""
    c = cell_coord(p, origin, inv_h, dims)
    cell = cell_index(c, dims)
    return (cell << fine_bits) | fine_code((p - origin) * inv_h, c, fine_bits), cell


@wp.kernel(enable_backward=False)
def cell_keys(
    points: wp.array(dtype=wp.vec3),
    origin: wp.vec3,
    inv_h: float,
    dims: wp.vec3i,
    fine_bits: int,
    keys: wp.array(dtype=int),
    values: wp.array(dtype=int),
    counts: wp.array(dtype=int),
):
    """Sort keys of the sources: their row-major cell index (values: their own index), shifted left by
    ``fine_bits`` that order a cell's sources along a Morton curve (:func:`fine_code`); ``counts[c]`` (zeroed
    first) += number of sources in cell ``c`` (an exclusive scan of it gives ``first``)."""
    i = wp.tid()
    key, cell = cell_key(points[i], origin, inv_h, dims, fine_bits)
    keys[i] = key
    values[i] = i
    wp.atomic_add(counts, cell, 1)


@wp.func
def tier_grid(slot: int, inv_h: wp.vec4, d0: wp.vec3i, d1: wp.vec3i, d2: wp.vec3i, d3: wp.vec3i):
    """``(1 / cell size, dims)`` of grid ``slot`` (0-3) of the edge-length tiers."""
    d = d0
    if slot == 1:
        d = d1
    elif slot == 2:
        d = d2
    elif slot == 3:
        d = d3
    return inv_h[slot], d


@wp.kernel(enable_backward=False)
def tier_cell_keys(
    points: wp.array(dtype=wp.vec3),
    origin: wp.vec3,
    inv_h: wp.vec4,
    dims0: wp.vec3i,
    dims1: wp.vec3i,
    dims2: wp.vec3i,
    dims3: wp.vec3i,
    base: wp.vec4i,
    length: wp.array(dtype=float),
    tier_hi: wp.vec4,
    fine_bits: int,
    keys: wp.array(dtype=int),
    values: wp.array(dtype=int),
    counts: wp.array(dtype=int),
):
    """Sort keys of edges in length tiers, for one sort that serves every tier: tier ``t`` holds the edges with
    ``tier_hi[t - 1] < length <= tier_hi[t]`` (``tier_hi`` ascending, the last one infinite) and has a grid of its
    own (cells ``1 / inv_h[t]`` and ``dims{t}`` from ``origin``, coarser for longer edges), whose cell ``c`` is bucket
    ``base[t] + c``. Keys: the bucket shifted left by ``fine_bits`` that order a bucket along a Morton curve;
    ``counts[bucket]`` (zeroed first) += 1."""
    i = wp.tid()
    L = length[i]
    t = int(0)
    for k in range(3):
        if L > tier_hi[k]:
            t = k + 1
    ih, dims = tier_grid(t, inv_h, dims0, dims1, dims2, dims3)
    c = cell_coord(points[i], origin, ih, dims)
    bucket = base[t] + cell_index(c, dims)
    keys[i] = (bucket << fine_bits) | fine_code((points[i] - origin) * ih, c, fine_bits)
    values[i] = i
    wp.atomic_add(counts, bucket, 1)


@wp.kernel(enable_backward=False)
def morton_keys(
    points: wp.array(dtype=wp.vec3),
    origin: wp.vec3,
    scale: float,
    keys: wp.array(dtype=int),
    values: wp.array(dtype=int),
):
    """Sort keys of the queries: 30-bit Morton codes on a 1024^3 grid (``scale = 1024 / largest extent``)."""
    i = wp.tid()
    q = (points[i] - origin) * scale
    x = int(wp.clamp(q[0], 0.0, 1023.0))
    y = int(wp.clamp(q[1], 0.0, 1023.0))
    z = int(wp.clamp(q[2], 0.0, 1023.0))
    keys[i] = spread_bits(x) | (spread_bits(y) << 1) | (spread_bits(z) << 2)
    values[i] = i


@wp.kernel(enable_backward=False)
def one_cell(n: int, first: wp.array(dtype=int)):
    """``first = [0, n]``: the cell bounds of a one-cell grid of ``n`` sources."""
    first[0] = 0
    first[1] = n


@wp.kernel(enable_backward=False)
def iota(values: wp.array(dtype=int)):
    """``values[i] = i``: the identity order."""
    i = wp.tid()
    values[i] = i


@wp.func_native(
    """
#if defined(__CUDA_ARCH__)
    return __any_sync(__activemask(), p);
#else
    return p;
#endif
"""
)
def warp_any(p: int) -> int:
    """Nonzero if ``p`` is nonzero on any active thread of the calling thread's CUDA warp; ``p`` itself on the
    CPU."""
    ...


@wp.func_native(
    """
#if defined(__CUDA_ARCH__)
    return 32;
#else
    return 1;
#endif
"""
)
def warp_lanes() -> int:
    """Threads per warp: 32 on CUDA, 1 on the CPU (a thread is its own warp)."""
    ...


@wp.func_native(
    """
#if defined(__CUDA_ARCH__)
    return (int)(threadIdx.x & 31);
#else
    return 0;
#endif
"""
)
def lane_id() -> int:
    """The calling thread's lane in its warp (0 on the CPU)."""
    ...


@wp.func_native(
    """
#if defined(__CUDA_ARCH__)
    return wp::vec2i(__shfl_sync(0xffffffffu, v[0], src), __shfl_sync(0xffffffffu, v[1], src));
#else
    return v;
#endif
"""
)
def warp_shfl2(v: wp.vec2i, src: int) -> wp.vec2i:
    """``v`` of lane ``src`` of the calling thread's CUDA warp, all 32 of whose threads must call it together;
    ``v`` itself on the CPU."""
    ...


@wp.func_native(
    """
#if defined(__CUDA_ARCH__) && (__CUDA_ARCH__ >= 800)
    return __reduce_min_sync(0xffffffffu, v);
#elif defined(__CUDA_ARCH__)
    int m = v;
    for (int o = 16; o > 0; o >>= 1)
        m = min(m, __shfl_xor_sync(0xffffffffu, m, o));
    return m;
#else
    return v;
#endif
"""
)
def warp_min(v: int) -> int:
    """Minimum of ``v`` over the 32 threads of the calling thread's CUDA warp, all of which must call it together;
    ``v`` itself on the CPU."""
    ...


@wp.func
def warp_max(v: int) -> int:
    """Maximum of ``v`` (> INT_MIN) over the 32 threads of the calling thread's CUDA warp, all of which must call
    it together (:func:`warp_min` of ``-v``); ``v`` itself on the CPU."""
    return -warp_min(-v)


@wp.func
def thread_ball(plo: wp.vec3, phi: wp.vec3, origin: wp.vec3, inv_h: float):
    """The ball ``plo..phi`` of a thread with one query (its centre +- radius, empty where ``plo > phi``: a thread
    with no query) in cell units of a grid from ``origin``: ``(centre, radius)``, radius < 0 when empty."""
    c = (0.5 * (plo + phi) - origin) * inv_h
    return wp.vec4(c[0], c[1], c[2], 0.5 * (phi[0] - plo[0]) * inv_h)


@wp.func
def clamp_ball(ball: wp.vec4, dims: wp.vec3i):
    """A :func:`thread_ball` with its centre clamped to the box of a grid of ``dims`` cells, for a grid made for other
    positions than its sources' (a plan kept while they move): a source outside the box counts in its nearest boundary
    cell (its position clamped to the box), and clamping to a box never lengthens a distance, so every source within
    the radius of the true centre is within the radius of the clamped one, in a cell :func:`ball_row_cells` keeps."""
    return wp.vec4(wp.clamp(ball[0], 0.0, float(dims[0])), wp.clamp(ball[1], 0.0, float(dims[1])),
                   wp.clamp(ball[2], 0.0, float(dims[2])), ball[3])


@wp.func
def ball_row_cells(row: int, lo: wp.vec3i, hi: wp.vec3i, ball: wp.vec4):
    """The cells ``(first, last)`` of row ``row`` of the box ``lo..hi`` (its ``(y, z)``: see :func:`row_span`) that
    the ball ``ball`` (:func:`thread_ball`) reaches, within ``lo.x..hi.x``; ``first > last`` where it misses the row.

    A source in cell ``(x, y, z)`` lies in ``[x, x + 1) x [y, y + 1) x [z, z + 1)`` (cell units): within the ball,
    its ``x`` is within ``w = sqrt(R^2 - dy^2 - dz^2)`` of the centre's, ``dy, dz`` the distances from the centre to
    the row's slab."""
    ny = hi[1] - lo[1] + 1
    y = float(lo[1] + row % ny)
    z = float(lo[2] + row // ny)
    dy = wp.max(wp.max(y - ball[1], ball[1] - (y + 1.0)), 0.0)
    dz = wp.max(wp.max(z - ball[2], ball[2] - (z + 1.0)), 0.0)
    w2 = ball[3] * ball[3] - dy * dy - dz * dz
    out = wp.vec2i(hi[0] + 1, lo[0] - 1)
    if ball[3] >= 0.0 and w2 >= 0.0:
        w = wp.sqrt(w2)
        out = wp.vec2i(int(wp.floor(wp.clamp(ball[0] - w, float(lo[0]), float(hi[0] + 1)))),
                       int(wp.floor(wp.clamp(ball[0] + w, float(lo[0] - 1), float(hi[0])))))
    return out


@wp.func
def walk_span(k: int, row: int, step: int, nrows: int, shared: bool, held: wp.vec2i, lo: wp.vec3i, hi: wp.vec3i,
              dims: wp.vec3i, first: wp.array(dtype=int), cull: bool, ball: wp.vec4):
    """``(span, held)``: the sorted-source range of row ``row`` of the box ``lo..hi``, the ``k``-th a thread walks
    (rows ``row, row + step, ..`` below ``nrows``), and what the thread holds for :func:`walk_span`'s next call.

    ``cull`` (one query per thread, the ball ``ball`` of :func:`thread_ball`): only the cells of the row that a
    ball reaches (:func:`ball_row_cells`), the thread's own, or where its warp walks a shared box, those any ball of
    the warp reaches. Where the whole warp walks one shared box (``shared``: a CUDA warp is one group, all of whose
    threads call this together), its threads read the ranges of its next 32 rows at once, one each, every 32nd
    row, and pass them round (:func:`warp_shfl2`), instead of one dependent read after another per row; otherwise
    the thread reads the range of each row itself."""
    span = wp.vec2i(0, 0)
    mine = held
    lanes = warp_lanes()
    if shared:
        j = k % lanes
        if j == 0:
            lane = lane_id()
            cells = wp.vec2i(lo[0], hi[0])
            if cull:
                # the reach of the warp's balls over each of the rows of this batch, one row at a time
                for m in range(wp.min(lanes, (nrows - row + step - 1) // step)):
                    c = ball_row_cells(row + m * step, lo, hi, ball)
                    c = wp.vec2i(warp_min(c[0]), warp_max(c[1]))
                    if m == lane:
                        cells = c
            r = row + lane * step
            mine = wp.vec2i(0, 0)
            if r < nrows:
                mine = cells_span(r, cells, lo, hi, dims, first)
        span = warp_shfl2(mine, j)
    else:
        cells = wp.vec2i(lo[0], hi[0])
        if cull:
            cells = ball_row_cells(row, lo, hi, ball)
        span = cells_span(row, cells, lo, hi, dims, first)
    return span, mine




# Offset of the cell coordinates gathered by atomic maxima in thread_extents: a group's smallest cell c is kept as
# BOX_OFFSET - c, so that every accumulator starts from zero
BOX_OFFSET = wp.constant(1 << 30)


@wp.func_native(
    """
#if defined(__CUDA_ARCH__) && (__CUDA_ARCH__ >= 800)
    const unsigned m = __activemask();
    if (__reduce_min_sync(m, g) == __reduce_max_sync(m, g)) {
        const int x = __reduce_max_sync(m, v[0]);
        const int y = __reduce_max_sync(m, v[1]);
        const int z = __reduce_max_sync(m, v[2]);
        if ((int)(threadIdx.x & 31) != __ffs(m) - 1)
            return wp::vec3i(0, 0, 0);
        return wp::vec3i(x, y, z);
    }
#endif
    return v;
"""
)
def group_max(v: wp.vec3i, g: int) -> wp.vec3i:
    """Componentwise maximum of ``v`` (non-negative) over the threads of a CUDA warp that belong to group ``g``,
    returned to one of them, zero to the others (which then skip their atomic): a warp of one group issues one
    atomic instead of 32. Returns ``v`` itself where the warp's threads are of several groups, on the CPU and
    before sm_80 (no ``__reduce_max_sync``)."""
    ...


@wp.func
def group_atomic_max(a: wp.array2d(dtype=wp.vec3i), t: int, g: int, v: wp.vec3i):
    """``a[t, g] = max(a[t, g], v)`` componentwise for ``v`` >= 0 (> 0 in x), one atomic per warp's group
    (:func:`group_max`)."""
    m = group_max(v, g)
    if m[0] > 0:
        wp.atomic_max(a, t, g, m)


@wp.kernel(enable_backward=False)
def thread_extents(
    points: wp.array(dtype=wp.vec3),
    order: wp.array(dtype=int),
    radius: wp.array(dtype=float),
    margin: float,
    count: int,
    per_thread: int,
    threads_per_group: int,
    origin: wp.vec3,
    inv_h: wp.vec4,
    dims0: wp.vec3i,
    dims1: wp.vec3i,
    dims2: wp.vec3i,
    dims3: wp.vec3i,
    pads: wp.vec4,
    low: wp.array2d(dtype=wp.vec3i),
    high: wp.array2d(dtype=wp.vec3i),
    most: wp.array2d(dtype=wp.vec3i),
):
    """Per thread of a traversal: the cells of the balls ``|x - p_k| <= radius[k] + margin + pads[t]`` of its
    ``per_thread`` consecutive sorted queries, for every traversal ``t`` (a row of ``low``: the edge-length tiers of
    the ball kernels, each over its own grid ``1 / inv_h[t]``, ``dims{t}``), gathered into its group's accumulators
    (zeroed first) by atomic maxima, one per warp (:func:`group_atomic_max`): ``low`` holds ``BOX_OFFSET`` minus the
    smallest cell, ``high`` one past the largest, ``most.x`` the cells of the largest box of one thread. One thread
    per entry: the reads of all queries are in flight together; :func:`group_boxes` ends."""
    u = wp.tid()
    lo = wp.vec3(1.0e30)
    hi = wp.vec3(-1.0e30)
    for t in range(u * per_thread, wp.min(u * per_thread + per_thread, count)):
        k = order[t]
        e = wp.vec3(radius[k] + margin)
        lo = wp.min(lo, points[k] - e)
        hi = wp.max(hi, points[k] + e)
    g = u // threads_per_group
    for t in range(low.shape[0]):
        e = wp.vec3(pads[t])
        ih, dims = tier_grid(t, inv_h, dims0, dims1, dims2, dims3)
        clo = cell_coord(lo - e, origin, ih, dims)
        chi = cell_coord(hi + e, origin, ih, dims)
        group_atomic_max(low, t, g, wp.vec3i(BOX_OFFSET) - clo)
        group_atomic_max(high, t, g, chi + wp.vec3i(1))
        group_atomic_max(most, t, g, wp.vec3i(int(box_cells(clo, chi)), 0, 0))


@wp.kernel(enable_backward=False)
def group_boxes(
    low: wp.array2d(dtype=wp.vec3i),
    high: wp.array2d(dtype=wp.vec3i),
    most: wp.array2d(dtype=wp.vec3i),
    spread: float,
    box_lo: wp.array2d(dtype=wp.vec3i),
    box_hi: wp.array2d(dtype=wp.vec3i),
):
    """Per traversal ``t`` and group ``g``, the cells reached by any ball of its threads (gathered by
    :func:`thread_extents`).

    The threads of a group walk that shared box. When it holds more than ``spread`` times the cells of the largest
    box of one thread (the balls are far apart, e.g. across a jump of the Morton curve, or small next to the group's
    extent) the group is marked ``box_lo.x = -1``: each thread then walks its own box (:func:`thread_box`)."""
    t, g = wp.tid()
    clo = wp.vec3i(BOX_OFFSET) - low[t, g]
    chi = high[t, g] - wp.vec3i(1)
    if box_cells(clo, chi) > spread * float(most[t, g][0]):
        clo = wp.vec3i(-1, clo[1], clo[2])
    box_lo[t, g] = clo
    box_hi[t, g] = chi


@wp.kernel(enable_backward=False)
def pack_soft_sources(
    order: wp.array(dtype=int),
    mid: wp.array(dtype=wp.vec3),
    length: wp.array(dtype=float),
    angle: wp.array(dtype=float),
    enormal: wp.array(dtype=wp.vec3),
    pos: wp.array(dtype=wp.vec4),
    val: wp.array(dtype=wp.vec4),
):
    """Edges in sorted order as two 16-byte records: ``pos = (m_j, L_j)``, ``val = (L_j alpha_j delta_j, L_j n_j)``."""
    i = wp.tid()
    j = order[i]
    L = length[j]
    m = mid[j]
    u = enormal[j] * L
    pos[i] = wp.vec4(m[0], m[1], m[2], L)
    val[i] = wp.vec4(L * angle[j], u[0], u[1], u[2])


@wp.kernel(enable_backward=False)
def pack_ball_sources(
    order: wp.array(dtype=int),
    x: wp.array(dtype=wp.vec3),
    edges: wp.array(dtype=wp.vec4i),
    angle: wp.array(dtype=float),
    enormal: wp.array(dtype=wp.vec3),
    seg_m: wp.array(dtype=wp.vec4),
    seg_h: wp.array(dtype=wp.vec4),
    val: wp.array(dtype=wp.vec4),
):
    """Whole edges in sorted order for the ball kernels: ``seg_m = (m_j, L_j / 2)``, ``seg_h = (d_j, L_j / 2)`` (the
    segment ``m + u d``, ``u`` in ``[-seg_h[3], seg_m[3]]`` of :func:`kernels.vnc_terms.chord`, as
    :func:`pack_piece_sources` writes a piece of an edge) and ``val = (alpha_j delta_j, n_j)``."""
    i = wp.tid()
    j = order[i]
    ev = edges[j]
    m, d, half = segment_frame(x[ev[0]], x[ev[1]])
    seg_m[i] = wp.vec4(m[0], m[1], m[2], half)
    seg_h[i] = wp.vec4(d[0], d[1], d[2], half)
    u = enormal[j]
    val[i] = wp.vec4(angle[j], u[0], u[1], u[2])


@wp.kernel(enable_backward=False)
def piece_counts(length: wp.array(dtype=float), inv_piece: float, counts: wp.array(dtype=int)):
    """Pieces of edge ``j`` for the ball kernels: ``k_j = max(ceil(L_j / P), 1)`` (``inv_piece = 1 / P``), so that no
    piece is longer than ``P`` (up to float32 rounding)."""
    j = wp.tid()
    counts[j] = wp.max(int(wp.ceil(length[j] * inv_piece)), 1)


@wp.func
def edge_piece(xa: wp.vec3, xb: wp.vec3, c: int, k: int):
    """Piece ``c`` of ``k`` equal pieces of the edge ``xa -> xb``: ``(m, d, a, b)``, the edge's midpoint ``m`` and unit
    direction ``d`` (zero for a degenerate edge) and the piece ``m + u d``, ``u`` in ``[-b, a]``. The ends are
    computed alike for neighbouring pieces and the outer ones are the edge's own, so the pieces tile the edge."""
    m, d, half = segment_frame(xa, xb)
    step = 2.0 * half / float(k)
    lo = -half + float(c) * step
    hi = half
    if c + 1 < k:
        hi = -half + float(c + 1) * step
    if c == 0:
        lo = -half
    return m, d, hi, -lo


@wp.kernel(enable_backward=False)
def piece_keys(
    x: wp.array(dtype=wp.vec3),
    edges: wp.array(dtype=wp.vec4i),
    counts: wp.array(dtype=int),
    offsets: wp.array(dtype=int),
    origin: wp.vec3,
    inv_h: float,
    dims: wp.vec3i,
    fine_bits: int,
    keys: wp.array(dtype=int),
    values: wp.array(dtype=int),
    piece_edge: wp.array(dtype=int),
    piece_index: wp.array(dtype=int),
    cell_counts: wp.array(dtype=int),
):
    """Sort keys of the pieces of the edges (:func:`piece_counts`; edge ``j``'s at slots ``offsets[j] ..``, an
    exclusive scan of ``counts``) in slots ``0 .. capacity - 1`` (``capacity = piece_edge.shape[0]``, at least the
    total): a piece's key is the row-major cell of its centre (shifted left by ``fine_bits`` of a Morton order within
    the cell, :func:`fine_code`), ``cell_counts[cell]`` (zeroed first) += 1; a slot past the last piece gets the key
    of bucket ``num_cells`` (sorted after every piece, counted nowhere) and ``piece_edge = -1``. Thread ``i`` writes
    the pieces of edge ``i`` and the slot ``i`` when it is past the last piece."""
    i = wp.tid()
    capacity = piece_edge.shape[0]
    ne = counts.shape[0]
    total = offsets[ne - 1] + counts[ne - 1]
    if i >= total:
        keys[i] = (dims[0] * dims[1] * dims[2]) << fine_bits
        values[i] = i
        piece_edge[i] = -1
        piece_index[i] = 0
    if i < ne:
        ev = edges[i]
        xa = x[ev[0]]
        xb = x[ev[1]]
        k = counts[i]
        for c in range(k):
            slot = offsets[i] + c
            if slot < capacity:
                m, d, a, b = edge_piece(xa, xb, c, k)
                key, cell = cell_key(m + d * (0.5 * (a - b)), origin, inv_h, dims, fine_bits)
                keys[slot] = key
                values[slot] = slot
                piece_edge[slot] = i
                piece_index[slot] = c
                wp.atomic_add(cell_counts, cell, 1)


@wp.kernel(enable_backward=False)
def pack_piece_sources(
    order: wp.array(dtype=int),
    piece_edge: wp.array(dtype=int),
    piece_index: wp.array(dtype=int),
    counts: wp.array(dtype=int),
    x: wp.array(dtype=wp.vec3),
    edges: wp.array(dtype=wp.vec4i),
    angle: wp.array(dtype=float),
    enormal: wp.array(dtype=wp.vec3),
    seg_m: wp.array(dtype=wp.vec4),
    seg_h: wp.array(dtype=wp.vec4),
    val: wp.array(dtype=wp.vec4),
):
    """Pieces of edges in sorted order (``order``: sorted slots of :func:`piece_keys`) for the ball kernels, in the
    "unit" form of :func:`pack_ball_sources` with the *edge's* midpoint: ``seg_m = (m_j, a)``, ``seg_h = (d_j, b)``,
    the piece ``m_j + u d_j``, ``u`` in ``[-b, a]``, ``val = (alpha_j delta_j, n_j)``. The chord of a ball and an edge
    is the sum of its pieces' chords, and the weight ``exp(-g |p - m_j|^2)`` of Eq. (2) is the edge's, so the sums of
    Eqs. (1)-(2) over pieces equal those over edges. Slots past the last piece get zero records."""
    i = wp.tid()
    s = order[i]
    j = piece_edge[s]
    if j < 0:
        seg_m[i] = wp.vec4(0.0)
        seg_h[i] = wp.vec4(0.0)
        val[i] = wp.vec4(0.0)
        return
    ev = edges[j]
    m, d, a, b = edge_piece(x[ev[0]], x[ev[1]], piece_index[s], counts[j])
    seg_m[i] = wp.vec4(m[0], m[1], m[2], a)
    seg_h[i] = wp.vec4(d[0], d[1], d[2], b)
    u = enormal[j]
    val[i] = wp.vec4(angle[j], u[0], u[1], u[2])


@functools.cache
def chunk_boxes_kernel(chunk: int):
    """The kernel of the boxes of runs of ``chunk`` sorted records (compiled once per ``chunk``): see
    ``chunk_boxes`` below."""

    @wp.kernel(enable_backward=False, module="unique", module_options={"max_unroll": 32})
    def chunk_boxes(
        seg_m: wp.array(dtype=wp.vec4),
        seg_h: wp.array(dtype=wp.vec4),
        start: wp.array(dtype=int),
        end: wp.array(dtype=int),
        lo: wp.array(dtype=wp.vec3),
        hi: wp.array(dtype=wp.vec3),
    ):
        """Bounding box of the segments of sorted records ``chunk c .. chunk (c + 1) - 1`` (both ends of each), from
        the records of :func:`pack_ball_sources` or :func:`pack_piece_sources`, for the runs that hold records from
        ``start[0]`` on (those the chunked traversals read: all, or a dense bucket of long edges sorted last) up to
        ``end[-1]`` (the last traversal's cell bounds: the records past it, slots with no piece, are left out). The
        loop has a fixed trip count, so it unrolls and all of a thread's reads are in flight together (there are few
        threads)."""
        c = wp.tid()
        if (c + 1) * wp.static(chunk) <= start[0]:
            return
        n = end[end.shape[0] - 1]
        blo = wp.vec3(1.0e30)
        bhi = wp.vec3(-1.0e30)
        for k in range(wp.static(chunk)):
            i = c * wp.static(chunk) + k
            if i < n:
                sm = seg_m[i]
                sh = seg_h[i]
                m = wp.vec3(sm[0], sm[1], sm[2])
                d = wp.vec3(sh[0], sh[1], sh[2])
                # the segment m + u d, u in [-sh[3], sm[3]]
                ea = m + d * sm[3]
                eb = m - d * sh[3]
                blo = wp.min(blo, wp.min(ea, eb))
                bhi = wp.max(bhi, wp.max(ea, eb))
        lo[c] = blo
        hi[c] = bhi

    return chunk_boxes
