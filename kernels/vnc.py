"""Warp kernels of the VNC operator (paper Sec. 3.1): edge quantities, VNC-soft, VNC-hard, Eq. (1).

Conventions shared by every kernel here:

* An interior edge ``j`` is stored as ``(a, b, c0, c1)``: face ``(a, b, c0)`` runs ``a -> b`` and face
  ``(b, a, c1)`` runs ``b -> a`` (consistent winding, outward normals).
* ``angle[j]`` is the signed dihedral angle ``alpha_j * delta_j`` with ``alpha_j`` in ``[0, pi]`` and
  ``delta_j = +1`` on convex edges, so a sphere has positive curvature.
* ``enormal[j]`` is the unit, area-weighted normal of the edge's two faces.
* Gaussian weights are written with ``g = 1 / (2 sigma^2)`` per query so that ``g = 0`` means unweighted.

Two ways to find the pairs within the cut-off live here. The ``bvh`` kernels walk a ``wp.Bvh`` per query
thread. The ``cells`` kernels read *sources* (edges, or vertices in the backward pass) sorted by the
row-major index of a uniform grid cell, so that the cells ``x0..x1`` of one ``(y, z)`` row are one
contiguous range ``first[c(x0, y, z)] .. first[c(x1, y, z) + 1]``. *Queries* are taken in *groups* of
consecutive threads (a CUDA warp on the GPU, one thread on the CPU) that share one box of cells, so the
threads of a group walk the same sources in lockstep: their loads are uniform and their loop bounds
equal (only the cut-off test differs per thread); a group whose balls are far apart (marked by
:func:`group_boxes`) lets each thread walk the box of its own ball(s) instead. A grid of one cell makes the same
kernels an all-pairs (dense) traversal. The rows of a box are split over ``ns`` threads (the leading launch
dimension) for occupancy (a box of many rows by whole rows in turn, a box of few rows by parts of every row:
:func:`row_walk`, :func:`row_share`); each thread
writes its partial sums to row ``s`` of a ``(ns, Q)`` array that a reduction kernel adds up in a fixed order, so
results are deterministic. The forward VNC-soft kernel holds ``QB`` queries per thread. The forward kernels of one
query per thread read of each row only the cells some ball of the group reaches (:func:`walk_span`): a box is the
bounding box of its balls, and its rows' ends are mostly beyond all of them.

The ball kernels (Eqs. 1-2) reach an edge from up to half its length beyond the radius. A single-scale traversal
reads *pieces* of the edges (:func:`piece_counts`, :func:`piece_keys`, :func:`pack_piece_sources`: each edge cut into
equal pieces no longer than a set length, each piece in the cell of its centre, its record holding the edge's midpoint
and the piece's ends along the edge), so that half a piece, not half the longest edge, widens the balls; the
multi-scale traversal reads whole edges sorted once for all their edge-length tiers (:func:`tier_cell_keys`). Either
way each cell's records can run along a Morton curve, so that a run of ``CHUNK`` consecutive records is a small patch
whose box (:func:`chunk_boxes`) can be tested against a thread's balls as a whole (``ball_cells_kernel(chunks=True)``).
"""


import warp as wp


@wp.func
def signed_dihedral(xa: wp.vec3, xb: wp.vec3, xc0: wp.vec3, xc1: wp.vec3):
    """Signed dihedral angle ``alpha * delta`` of edge ``a -> b`` (radians, in ``[-pi, pi]``).

    Uses ``atan2(|n0 x n1| sign, n0 . n1)`` rather than ``arccos``, so the gradient stays finite on flat edges.
    """
    e = xb - xa
    n0 = wp.cross(e, xc0 - xa)
    n1 = wp.cross(xa - xb, xc1 - xb)
    y = wp.dot(wp.cross(n0, n1), e)
    x = wp.dot(n0, n1) * wp.length(e)
    return wp.atan2(y, x)


@wp.kernel
def edge_geometry(
    x: wp.array(dtype=wp.vec3),
    edges: wp.array(dtype=wp.vec4i),
    mid: wp.array(dtype=wp.vec3),
    length: wp.array(dtype=float),
    angle: wp.array(dtype=float),
    enormal: wp.array(dtype=wp.vec3),
):
    """Per interior edge: midpoint, length ``L_j``, signed dihedral angle, unit area-weighted normal."""
    j = wp.tid()
    ev = edges[j]
    xa = x[ev[0]]
    xb = x[ev[1]]
    xc0 = x[ev[2]]
    xc1 = x[ev[3]]
    e = xb - xa
    mid[j] = 0.5 * (xa + xb)
    length[j] = wp.length(e)
    angle[j] = signed_dihedral(xa, xb, xc0, xc1)
    # raw cross products are twice the face areas times the unit normals: their sum is area-weighted
    ns = wp.cross(e, xc0 - xa) + wp.cross(xa - xb, xc1 - xb)
    enormal[j] = ns / wp.max(wp.length(ns), 1.0e-30)


@wp.kernel(enable_backward=False)
def midpoint_bounds(mid: wp.array(dtype=wp.vec3), lowers: wp.array(dtype=wp.vec3), uppers: wp.array(dtype=wp.vec3)):
    """Degenerate boxes at the edge midpoints: the spatial index of VNC-soft."""
    j = wp.tid()
    lowers[j] = mid[j]
    uppers[j] = mid[j]


@wp.kernel(enable_backward=False)
def segment_bounds(
    x: wp.array(dtype=wp.vec3),
    edges: wp.array(dtype=wp.vec4i),
    lowers: wp.array(dtype=wp.vec3),
    uppers: wp.array(dtype=wp.vec3),
):
    """Boxes around whole edges: the spatial index of VNC-hard and Eq. (1)."""
    j = wp.tid()
    xa = x[edges[j][0]]
    xb = x[edges[j][1]]
    lowers[j] = wp.min(xa, xb)
    uppers[j] = wp.max(xa, xb)


@wp.func
def segment_ball_length(xa: wp.vec3, xb: wp.vec3, c: wp.vec3, r: float):
    """Length of the part of segment ``[xa, xb]`` inside the ball ``|p - c| <= r`` (the ``l_j`` of Eq. (1))."""
    l = xb - xa
    oc = xa - c
    ll = wp.dot(l, l)
    lo = wp.dot(l, oc)
    disc = lo * lo - ll * (wp.dot(oc, oc) - r * r)
    out = float(0.0)
    if disc > 0.0 and ll > 0.0:
        s = wp.sqrt(disc)
        d1 = wp.clamp((-lo - s) / ll, 0.0, 1.0)
        d2 = wp.clamp((-lo + s) / ll, 0.0, 1.0)
        out = (d2 - d1) * wp.sqrt(ll)
    return out


@wp.kernel(enable_backward=False)
def soft_forward(
    x: wp.array(dtype=wp.vec3),
    tau: wp.array(dtype=float),
    kappa: float,
    bvh: wp.uint64,
    mid: wp.array(dtype=wp.vec3),
    length: wp.array(dtype=float),
    angle: wp.array(dtype=float),
    enormal: wp.array(dtype=wp.vec3),
    num: wp.array(dtype=float),
    den: wp.array(dtype=float),
    nsum: wp.array(dtype=wp.vec3),
    H: wp.array(dtype=float),
    n: wp.array(dtype=wp.vec3),
):
    """VNC-soft, Eq. (3), for one vertex per thread, pruned at the cut-off ``r = kappa * sigma = tau``.

    ``num``, ``den`` and ``nsum`` keep the three weighted sums for the backward pass.
    """
    k = wp.tid()
    p = x[k]
    r = tau[k]
    sigma = r / kappa
    g = 1.0 / (2.0 * sigma * sigma)
    r2 = r * r
    ext = wp.vec3(r, r, r)
    acc_num = float(0.0)
    acc_den = float(0.0)
    acc_n = wp.vec3(0.0)
    query = wp.bvh_query_aabb(bvh, p - ext, p + ext)
    j = int(0)
    while wp.bvh_query_next(query, j):
        d = p - mid[j]
        q = wp.dot(d, d)
        if q <= r2:
            c = wp.exp(-q * g) * length[j]
            acc_num += c * angle[j]
            acc_den += c
            acc_n += c * enormal[j]
    num[k] = acc_num
    den[k] = acc_den
    nsum[k] = acc_n
    h = float(0.0)
    if acc_den > 0.0:
        h = acc_num / (2.0 * acc_den)
    H[k] = h
    n[k] = acc_n / wp.max(wp.length(acc_n), 1.0e-30)


@wp.kernel(enable_backward=False)
def soft_backward(
    x: wp.array(dtype=wp.vec3),
    tau: wp.array(dtype=float),
    kappa: float,
    bvh: wp.uint64,
    mid: wp.array(dtype=wp.vec3),
    length: wp.array(dtype=float),
    angle: wp.array(dtype=float),
    enormal: wp.array(dtype=wp.vec3),
    num: wp.array(dtype=float),
    den: wp.array(dtype=float),
    nsum: wp.array(dtype=wp.vec3),
    H_grad: wp.array(dtype=float),
    n_grad: wp.array(dtype=wp.vec3),
    x_grad: wp.array(dtype=wp.vec3),
    mid_grad: wp.array(dtype=wp.vec3),
    length_grad: wp.array(dtype=float),
    angle_grad: wp.array(dtype=float),
    enormal_grad: wp.array(dtype=wp.vec3),
):
    """Adjoint of :func:`soft_forward`: scatters dL/dH and dL/dn to the vertex and the edge quantities.

    With ``c_kj = w_kj L_j``, ``H = N / 2D`` and ``n = S / |S|``: ``dH/dN = 1/2D``, ``dH/dD = -H/D`` and
    ``dn/dS = (I - n n^T) / |S|``; the Gaussian gives ``dw/dx_k = -2 g w (x_k - m_j)``.
    """
    k = wp.tid()
    D = den[k]
    if D <= 0.0:
        return
    p = x[k]
    r = tau[k]
    sigma = r / kappa
    g = 1.0 / (2.0 * sigma * sigma)
    r2 = r * r
    h = num[k] / (2.0 * D)
    gN = H_grad[k] / (2.0 * D)
    gD = -H_grad[k] * h / D
    S = nsum[k]
    sl = wp.max(wp.length(S), 1.0e-30)
    nk = S / sl
    gn = n_grad[k]
    gS = (gn - nk * wp.dot(nk, gn)) / sl
    ext = wp.vec3(r, r, r)
    gx = wp.vec3(0.0)
    query = wp.bvh_query_aabb(bvh, p - ext, p + ext)
    j = int(0)
    while wp.bvh_query_next(query, j):
        d = p - mid[j]
        q = wp.dot(d, d)
        if q <= r2:
            w = wp.exp(-q * g)
            L = length[j]
            c = w * L
            u = enormal[j]
            gc = gN * angle[j] + gD + wp.dot(gS, u)
            wp.atomic_add(angle_grad, j, gN * c)
            wp.atomic_add(enormal_grad, j, gS * c)
            wp.atomic_add(length_grad, j, gc * w)
            gd = (gc * L * w * (-2.0 * g)) * d
            gx += gd
            wp.atomic_sub(mid_grad, j, gd)
    x_grad[k] = x_grad[k] + gx


@wp.kernel(enable_backward=False)
def soft_multiscale(
    x: wp.array(dtype=wp.vec3),
    taus: wp.array(dtype=float),
    kappa: float,
    bvh: wp.uint64,
    mid: wp.array(dtype=wp.vec3),
    length: wp.array(dtype=float),
    angle: wp.array(dtype=float),
    num: wp.array2d(dtype=float),
    den: wp.array2d(dtype=float),
):
    """Eq. (3) at every scale of ``taus`` (ascending) in one neighbour traversal at the largest scale.

    A pair at distance ``d`` contributes to the scales with ``tau_s >= d`` only, so the work is that of the
    separate launches while the tree is walked once.
    """
    k = wp.tid()
    p = x[k]
    S = taus.shape[0]
    r = taus[S - 1]
    ext = wp.vec3(r, r, r)
    query = wp.bvh_query_aabb(bvh, p - ext, p + ext)
    j = int(0)
    while wp.bvh_query_next(query, j):
        d = p - mid[j]
        q = wp.dot(d, d)
        L = length[j]
        a = angle[j]
        s = S - 1
        while s >= 0:
            ts = taus[s]
            if q > ts * ts:
                break
            sigma = ts / kappa
            c = wp.exp(-q / (2.0 * sigma * sigma)) * L
            num[s, k] = num[s, k] + c * a
            den[s, k] = den[s, k] + c
            s -= 1


@wp.kernel(enable_backward=False)
def ball_sums(
    points: wp.array(dtype=wp.vec3),
    radius: wp.array(dtype=float),
    g: wp.array(dtype=float),
    bvh: wp.uint64,
    x: wp.array(dtype=wp.vec3),
    edges: wp.array(dtype=wp.vec4i),
    mid: wp.array(dtype=wp.vec3),
    angle: wp.array(dtype=float),
    enormal: wp.array(dtype=wp.vec3),
    num: wp.array(dtype=float),
    den: wp.array(dtype=float),
    nsum: wp.array(dtype=wp.vec3),
):
    """Exact edge/ball sums of Eqs. (1)-(2) for one query point per thread.

    ``num = sum alpha delta w l``, ``den = sum w l``, ``nsum = sum w l n_j`` over the edges that cross the ball
    of radius ``radius[i]``, with ``l`` the intersected length and ``w = exp(-g |p - m_j|^2)`` (``g = 0``: w = 1).
    """
    i = wp.tid()
    p = points[i]
    r = radius[i]
    gi = g[i]
    ext = wp.vec3(r, r, r)
    acc_num = float(0.0)
    acc_den = float(0.0)
    acc_n = wp.vec3(0.0)
    query = wp.bvh_query_aabb(bvh, p - ext, p + ext)
    j = int(0)
    while wp.bvh_query_next(query, j):
        ev = edges[j]
        l = segment_ball_length(x[ev[0]], x[ev[1]], p, r)
        if l > 0.0:
            d = p - mid[j]
            c = wp.exp(-gi * wp.dot(d, d)) * l
            acc_num += c * angle[j]
            acc_den += c
            acc_n += c * enormal[j]
    num[i] = acc_num
    den[i] = acc_den
    nsum[i] = acc_n


@wp.kernel(enable_backward=False)
def ball_multiscale(
    points: wp.array(dtype=wp.vec3),
    taus: wp.array(dtype=float),
    kappa: float,
    bvh: wp.uint64,
    x: wp.array(dtype=wp.vec3),
    edges: wp.array(dtype=wp.vec4i),
    mid: wp.array(dtype=wp.vec3),
    angle: wp.array(dtype=float),
    num: wp.array2d(dtype=float),
    den: wp.array2d(dtype=float),
):
    """Eq. (2) at every scale of ``taus`` (ascending) in one traversal at the largest radius."""
    i = wp.tid()
    p = points[i]
    S = taus.shape[0]
    r = taus[S - 1]
    ext = wp.vec3(r, r, r)
    query = wp.bvh_query_aabb(bvh, p - ext, p + ext)
    j = int(0)
    while wp.bvh_query_next(query, j):
        ev = edges[j]
        xa = x[ev[0]]
        xb = x[ev[1]]
        d = p - mid[j]
        q = wp.dot(d, d)
        a = angle[j]
        s = S - 1
        while s >= 0:
            ts = taus[s]
            l = segment_ball_length(xa, xb, p, ts)
            if l <= 0.0:
                break
            sigma = ts / kappa
            c = wp.exp(-q / (2.0 * sigma * sigma)) * l
            num[s, i] = num[s, i] + c * a
            den[s, i] = den[s, i] + c
            s -= 1


@wp.kernel(enable_backward=False)
def normalize_sums(
    num: wp.array(dtype=float),
    den: wp.array(dtype=float),
    nsum: wp.array(dtype=wp.vec3),
    H: wp.array(dtype=float),
    n: wp.array(dtype=wp.vec3),
):
    """``H = num / (2 den)`` (Eq. (2)) and ``n = nsum / |nsum|``; zero where nothing was in reach."""
    i = wp.tid()
    d = den[i]
    h = float(0.0)
    if d > 0.0:
        h = num[i] / (2.0 * d)
    H[i] = h
    s = nsum[i]
    n[i] = s / wp.max(wp.length(s), 1.0e-30)


@wp.kernel(enable_backward=False)
def ratio2d(num: wp.array2d(dtype=float), den: wp.array2d(dtype=float), H: wp.array2d(dtype=float)):
    """``H = num / (2 den)`` elementwise, zero where ``den = 0``."""
    s, k = wp.tid()
    d = den[s, k]
    h = float(0.0)
    if d > 0.0:
        h = num[s, k] / (2.0 * d)
    H[s, k] = h


@wp.kernel(enable_backward=False)
def scaled_copy(src: wp.array(dtype=float), s: float, dst: wp.array(dtype=float)):
    """``dst = s * src``."""
    i = wp.tid()
    dst[i] = s * src[i]


@wp.kernel(enable_backward=False)
def column_mean(H: wp.array2d(dtype=float), stride: int, inv_count: float, mean: wp.array(dtype=float)):
    """``mean[s] += sum_k H[s, k] / V`` over the columns ``k = c, c + stride, ...``: the global mean curve of the
    VNC-Scale curves (``mean`` zeroed first; one atomic per thread rather than per element)."""
    s, c = wp.tid()
    acc = float(0.0)
    for k in range(c, H.shape[1], stride):
        acc += H[s, k]
    wp.atomic_add(mean, s, acc * inv_count)


@wp.kernel(enable_backward=False)
def scale_auc(
    H: wp.array2d(dtype=float),
    mean: wp.array(dtype=float),
    taus: wp.array(dtype=float),
    out: wp.array(dtype=float),
):
    """Eq. (4) at ``tau_max``: trapezoid rule for ``int |H(v_k, x) - mean(x)| dx`` over the sampled scales."""
    k = wp.tid()
    S = taus.shape[0]
    acc = float(0.0)
    prev = wp.abs(H[0, k] - mean[0])
    for s in range(1, S):
        cur = wp.abs(H[s, k] - mean[s])
        acc += 0.5 * (prev + cur) * (taus[s] - taus[s - 1])
        prev = cur
    out[k] = acc


@wp.kernel(enable_backward=False)
def adaptive_scale(
    H: wp.array2d(dtype=float),
    mean: wp.array(dtype=float),
    taus: wp.array(dtype=float),
    phi: float,
    out: wp.array(dtype=float),
):
    """Eq. (6): the scale at which the running integral of Eq. (4) reaches ``phi``.

    The integral is accumulated with the trapezoid rule and the crossing is interpolated linearly inside the
    interval that contains it; a vertex whose total stays below ``phi`` gets ``tau_max``.
    """
    k = wp.tid()
    S = taus.shape[0]
    acc = float(0.0)
    prev = wp.abs(H[0, k] - mean[0])
    result = taus[S - 1]
    found = int(0)
    if phi <= 0.0:
        result = taus[0]
        found = 1
    for s in range(1, S):
        cur = wp.abs(H[s, k] - mean[s])
        inc = 0.5 * (prev + cur) * (taus[s] - taus[s - 1])
        if found == 0 and inc > 0.0 and acc + inc >= phi:
            result = taus[s - 1] + (phi - acc) / inc * (taus[s] - taus[s - 1])
            found = 1
        acc += inc
        prev = cur
    out[k] = result


# --- uniform-grid traversal ("cells" kernels): see the module docstring ---------------------------------------------

vec16 = wp.types.vector(length=16, dtype=wp.float32)
# (num, den, n.x, n.y, n.z): the sums of one query, updated in place so a rejected candidate costs no work
vec5 = wp.types.vector(length=5, dtype=wp.float32)


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


@wp.func_native(
"return exp2f(x);"
)
def exp2(x: float) -> float:
    """``2^x`` (one ``ex2.approx`` with fast math on CUDA)."""
    ...


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


@wp.func
def chord(cc: float, ch: float, hh: float, inv_hh: float, half_l: float, r2: float):
    """Length inside the ball ``|p - q| <= r`` of the segment ``m + u h``, ``u`` in [-1, 1] (the ``l_j`` of Eq. (1)).

    ``cc = |m - q|^2``, ``ch = (m - q) . h``, ``hh = |h|^2``, ``inv_hh = 1 / hh`` (0 for a degenerate edge),
    ``half_l = |h|``. The roots of ``|m - q + u h|^2 = r^2`` clipped to [-1, 1] bound the chord, without a branch: a
    segment with both ends inside gets ``u = -1 .. 1`` (its whole length), one that misses the ball (no real root,
    or roots outside [-1, 1]) an empty range, a degenerate one nothing.
    """
    disc = ch * ch - hh * (cc - r2)
    sq = wp.sqrt(wp.max(disc, 0.0))
    u1 = wp.max((-ch - sq) * inv_hh, -1.0)
    u2 = wp.min((-ch + sq) * inv_hh, 1.0)
    return wp.max(u2 - u1, 0.0) * half_l


@wp.kernel(enable_backward=False)
def point_stats(
    x: wp.array(dtype=wp.vec3),
    radius: wp.array(dtype=float),
    length: wp.array(dtype=float),
    stride: int,
    stats: wp.array(dtype=float),
):
    """Bounding box of ``x``, radius statistics and the longest edge in one strided pass.

    ``stats`` is preset to ``[+inf] * 3 + [-inf] * 4 + [0, 0, 0, 0, 0]`` and becomes
    ``[lo.xyz, hi.xyz, max radius, sum radius, max length, sum length, bad points, bad radii]``: the counts of
    points with a NaN or infinite coordinate and of radii that are not positive and finite (which would otherwise
    come out as silent zeros).
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
    wp.atomic_add(stats, 7, rsum)
    wp.atomic_max(stats, 8, lmax)
    wp.atomic_add(stats, 9, lsum)
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
    tier_slot: wp.vec4i,
    grid_tiers: int,
    dense_bucket: int,
    fine_bits: int,
    keys: wp.array(dtype=int),
    values: wp.array(dtype=int),
    counts: wp.array(dtype=int),
):
    """Sort keys of edges in length tiers, for one sort that serves every tier: tier ``t`` holds the edges with
    ``tier_hi[t - 1] < length <= tier_hi[t]`` (``tier_hi`` ascending, the last one infinite). A tier traversed
    through a grid (``tier_slot[t] = g < grid_tiers``; grid ``g`` of cells ``1 / inv_h[g]`` and ``dims{g}`` from
    ``origin``, coarser for longer edges) buckets an edge ``base[g] + cell``; every other tier in bucket
    ``dense_bucket``, tested densely. Keys: the bucket shifted left by ``fine_bits`` that order a bucket along a
    Morton curve (within the cell, or over grid 0 for the dense bucket); ``counts[bucket]`` (zeroed first) += 1."""
    i = wp.tid()
    L = length[i]
    t = int(0)
    for k in range(3):
        if L > tier_hi[k]:
            t = k + 1
    slot = tier_slot[t]
    bucket = dense_bucket
    fine = int(0)
    if slot < grid_tiers:
        ih, dims = tier_grid(slot, inv_h, dims0, dims1, dims2, dims3)
        q = (points[i] - origin) * ih
        c = cell_coord(points[i], origin, ih, dims)
        bucket = base[slot] + cell_index(c, dims)
        fine = fine_code(q, c, fine_bits)
    else:
        # the whole of grid 0 as one cell
        q = (points[i] - origin) * inv_h[0]
        fine = fine_code(wp.cw_div(q, wp.vec3(float(dims0[0]), float(dims0[1]), float(dims0[2]))), wp.vec3i(0),
                         fine_bits)
    keys[i] = (bucket << fine_bits) | fine
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
    return true;
#else
    return false;
#endif
"""
)
def on_cuda() -> bool:
    """Whether the calling kernel runs on a CUDA device (a constant of each device's build)."""
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


# Traversals of one query per thread walk only the cells of each row that a ball reaches (walk_span)
CULL = True
# ... and on the CPU device, where one thread walks its own ball's box and every row holds few candidates, the per-row
# reach costs more than the candidates it skips (VNC-hard with the prefilter, spot at 2 mean edge lengths: 20.9 ->
# 27.4 ms; tests set it to cover the culled walk on the CPU too)
CULL_CPU = False


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
    unit: int,
    seg_m: wp.array(dtype=wp.vec4),
    seg_h: wp.array(dtype=wp.vec4),
    val: wp.array(dtype=wp.vec4),
):
    """Edges in sorted order for the ball kernels, ``val = (alpha_j delta_j, n_j)`` and either (``unit``) midpoint
    and unit direction ``d`` (zero for a degenerate edge), ``seg_m = (m_j, L_j / 2)``, ``seg_h = (d_j, L_j / 2)``
    (the segment ``m + u d``, ``u`` in ``[-seg_h[3], seg_m[3]]``, as :func:`pack_piece_sources` writes a piece of
    an edge), or midpoint and half-vector ``h = (x_b - x_a) / 2``, ``seg_m = (m_j, 1 / |h|^2)`` (0 for a degenerate
    edge), ``seg_h = (h, |h|)``."""
    i = wp.tid()
    j = order[i]
    ev = edges[j]
    xa = x[ev[0]]
    xb = x[ev[1]]
    m = 0.5 * (xa + xb)
    h = 0.5 * (xb - xa)
    hh = wp.dot(h, h)
    half = wp.sqrt(hh)
    if unit != 0:
        d = wp.vec3(0.0)
        if half > 0.0:
            d = h / half
        seg_m[i] = wp.vec4(m[0], m[1], m[2], half)
        seg_h[i] = wp.vec4(d[0], d[1], d[2], half)
    else:
        inv = float(0.0)
        if hh > 0.0:
            inv = 1.0 / hh
        seg_m[i] = wp.vec4(m[0], m[1], m[2], inv)
        seg_h[i] = wp.vec4(h[0], h[1], h[2], half)
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
    m = 0.5 * (xa + xb)
    h = 0.5 * (xb - xa)
    half = wp.length(h)
    d = wp.vec3(0.0)
    if half > 0.0:
        d = h / half
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


# Queries per thread of the forward VNC-soft traversal (:func:`soft_cells_kernel`): every source read is used for
# this many queries
QB = 4
# Threads per block of the forward traversal kernels (soft_cells, ball_cells): a block's resources are freed when its
# slowest warp ends, and the warps of a traversal differ in work (the balls of a dense region hold more sources).
# On an H200 64 was 5-12 % faster than 256 for both operators from 16 mean edge lengths up, the same below
# (koala, nefertiti, armadillo; 128 close to 64, 32 no better).
CELLS_BLOCK = 64
LOG2E = wp.constant(1.4426950408889634)

_soft_cells_kernels = {}


def soft_cells_kernel(qb: int):
    """The forward VNC-soft traversal kernel with ``qb`` queries per thread (compiled once per ``qb``).

    Other forms of its pair update were timed on an H200 (``bench/tune.py``; ``docs/results/tune_h200_kernels.json``
    and ``tune_h200_splits.json``) and dropped: coordinates scaled per query (one multiply less per pair, as fast,
    less precise), a select instead of the cut-off branch, two sources per iteration, and the exponent expanded about
    each thread's first query (four multiply-adds per pair instead of seven, but 1.5x slower at large scales).
    """
    key = (qb, bool(CULL), bool(CULL_CPU))
    if key in _soft_cells_kernels:
        return _soft_cells_kernels[key]
    vq = wp.types.vector(length=qb, dtype=wp.float32)

    @wp.kernel(enable_backward=False, module="unique", module_options={"fast_math": True})
    def soft_cells(
        x: wp.array(dtype=wp.vec3),
        tau: wp.array(dtype=float),
        kappa: float,
        count: int,
        size: int,
        order: wp.array(dtype=int),
        box_lo: wp.array(dtype=wp.vec3i),
        box_hi: wp.array(dtype=wp.vec3i),
        first: wp.array(dtype=int),
        dims: wp.vec3i,
        origin: wp.vec3,
        inv_h: float,
        pad: float,
        pos: wp.array(dtype=wp.vec4),
        val: wp.array(dtype=wp.vec4),
        part_num: wp.array2d(dtype=float),
        part_den: wp.array2d(dtype=float),
        part_n: wp.array2d(dtype=wp.vec3),
    ):
        """VNC-soft, Eq. (3), cut off at ``r = kappa sigma = tau``: partial sums of split ``s`` for the ``qb``
        consecutive sorted queries ``qb u .. qb u + qb - 1`` of thread ``u``.

        Every source record read (two 16-byte loads) serves ``qb`` queries held in registers. With
        ``g = -kappa^2 log2(e) / (2 tau^2)`` per query, ``exp(-|p - m|^2 / 2 sigma^2) = 2^(g |p - m|^2)`` and the
        cut-off ``|p - m| <= tau`` is ``g |p - m|^2 >= -kappa^2 log2(e) / 2`` for every query: a pair costs its offset
        and square, one multiply and one compare, and within the cut-off one ``exp2`` and five multiply-adds. Groups
        hold ``qb x 32`` queries on CUDA.
        """
        s, u = wp.tid()
        t0 = u * qb
        g = t0 // size
        # one query per thread: the threads past the last query of a group that walks a shared box walk it too
        # (walk_span)
        shared = wp.static(qb == 1) and box_lo[g][0] >= 0
        if t0 >= count and not shared:
            return
        emin = -kappa * kappa * (0.5 * LOG2E)
        px = vq()
        py = vq()
        pz = vq()
        gq = vq()
        tlo = wp.vec3(1.0e30)
        thi = wp.vec3(-1.0e30)
        for q in range(qb):
            px[q] = FAR  # an empty slot: far from every source
            py[q] = FAR
            pz[q] = FAR
            gq[q] = -1.0
            if t0 + q < count:
                k = order[t0 + q]
                p = x[k]
                r = tau[k]
                px[q] = p[0]
                py[q] = p[1]
                pz[q] = p[2]
                gq[q] = emin / (r * r)
                e = wp.vec3(r + pad)
                tlo = wp.min(tlo, p - e)
                thi = wp.max(thi, p + e)
        lo, hi = thread_span_box(g, tlo, thi, box_lo, box_hi, origin, inv_h, dims)
        ball = thread_ball(tlo, thi, origin, inv_h)
        ns = part_num.shape[0]
        an = vq()
        ad = vq()
        ax = vq()
        ay = vq()
        az = vq()
        nrows = box_rows(lo, hi)
        steps = row_walk(nrows, s, ns)
        held = wp.vec2i(0, 0)
        walked = int(0)
        for row in range(steps[0], nrows, steps[1]):
            whole, held = walk_span(walked, row, steps[1], nrows, shared, held, lo, hi, dims, first,
                                    wp.static(qb == 1 and CULL) and (on_cuda() or wp.static(CULL_CPU)), ball)
            walked += 1
            span = row_share(whole, s, ns, steps[1])
            for i in range(span[0], span[1]):
                ep = load4(pos, i)
                ev = load4(val, i)
                for q in range(qb):
                    dx = px[q] - ep[0]
                    dy = py[q] - ep[1]
                    dz = pz[q] - ep[2]
                    lw = (dx * dx + dy * dy + dz * dz) * gq[q]
                    if lw >= emin:
                        w = exp2(lw)
                        an[q] += w * ev[0]
                        ad[q] += w * ep[3]
                        ax[q] += w * ev[1]
                        ay[q] += w * ev[2]
                        az[q] += w * ev[3]
        for q in range(qb):
            if t0 + q < count:
                part_num[s, t0 + q] = an[q]
                part_den[s, t0 + q] = ad[q]
                part_n[s, t0 + q] = wp.vec3(ax[q], ay[q], az[q])

    _soft_cells_kernels[key] = soft_cells
    return soft_cells


# Sorted edge records per run of the chunked ball kernels (ball_cells_kernel(chunks=True)), and the fewest records a
# run must hold to be tested as a whole (a shorter run goes straight to the chords)
CHUNK = wp.constant(32)
MIN_RUN = wp.constant(8)


_ball_cells_kernels = {}


def ball_cells_kernel(qb: int, prefilter: bool = False, form: str = "unit", chunks: bool = False):
    """The edge/ball traversal kernel of Eqs. (1)-(2) with ``qb`` queries per thread (compiled once per variant).

    ``form``: the edge records the kernel reads (:func:`pack_ball_sources`), "unit" (midpoint, unit direction and the
    segment's ends along it, the roots in length units: a whole edge, or a piece of one from
    :func:`pack_piece_sources`) or "half" (midpoint, half-vector, the roots in ``[-1, 1]``).
    The chord is the roots clipped to the edge with no branch on whether the edge's line meets the ball (a line that
    misses gets an empty chord from the same clipping): on an H200 1-8 % faster than a branch on the root at 2-8
    mean edge lengths (nefertiti, koala, their subdivisions, armadillo, spot); reading two edges per iteration was
    no faster (``docs/results/tune_h200_kernels.json``). ``prefilter`` first rejects an edge whose midpoint is beyond
    the radius plus its half length (see :func:`ball_variant`).
    ``chunks``: the edges are read in runs of at most :data:`CHUNK` sorted records, each tested as a whole against
    the thread's balls first (:func:`chunk_boxes`): a run beyond every ball is skipped, one inside every ball adds
    its edges' whole lengths with no chord (an edge with both ends in a ball lies in it). The threads of a CUDA warp
    walk the same runs; where some of them need the chords of a run, the others take the chords too (:data:`VOTE`,
    :func:`warp_any`) rather than a second pass of the warp: on an H200 8-12 % faster from 16 mean edge lengths up
    (armadillo 32 l 1.00 -> 0.90 ms, koala 32 l 3.86 -> 3.54 ms).
    """
    if form not in ("unit", "half"):
        raise ValueError(f"form must be 'unit' or 'half', got {form!r}")
    unit = form == "unit"
    vote = bool(VOTE)
    key = (qb, bool(prefilter), form, bool(chunks), vote, bool(CULL), bool(CULL_CPU))
    if key in _ball_cells_kernels:
        return _ball_cells_kernels[key]
    vq = wp.types.vector(length=qb, dtype=wp.float32)

    @wp.kernel(enable_backward=False, module="unique", module_options={"fast_math": True})
    def ball_cells(
        points: wp.array(dtype=wp.vec3),
        radius: wp.array(dtype=float),
        g: wp.array(dtype=float),
        count: int,
        size: int,
        order: wp.array(dtype=int),
        box_lo: wp.array(dtype=wp.vec3i),
        box_hi: wp.array(dtype=wp.vec3i),
        first: wp.array(dtype=int),
        dims: wp.vec3i,
        origin: wp.vec3,
        inv_h: float,
        pad: float,
        seg_m: wp.array(dtype=wp.vec4),
        seg_h: wp.array(dtype=wp.vec4),
        val: wp.array(dtype=wp.vec4),
        chunk_lo: wp.array(dtype=wp.vec3),
        chunk_hi: wp.array(dtype=wp.vec3),
        splits: int,
        accumulate: int,
        part_num: wp.array2d(dtype=float),
        part_den: wp.array2d(dtype=float),
        part_n: wp.array2d(dtype=wp.vec3),
    ):
        """Exact edge/ball sums of Eqs. (1)-(2), partial sums of split ``s`` (of ``splits``) for the ``qb``
        consecutive sorted queries of thread ``u``, written to row ``s`` (``accumulate``: added to it, as the
        edge-length tiers after the first are, one launch after another on one stream).

        ``num = sum alpha delta w l``, ``den = sum w l``, ``n = sum w l n_j`` with ``l`` the chord inside the ball
        of radius ``radius[k]`` and ``w = exp(-g[k] |p - m_j|^2)`` (``g = 0``: w = 1). Every edge record read
        serves ``qb`` queries.
        """
        s, u = wp.tid()
        t0 = u * qb
        grp = t0 // size
        # one query per thread: the threads past the last query of a group that walks a shared box walk it too
        # (walk_span)
        shared = wp.static(qb == 1) and box_lo[grp][0] >= 0
        if t0 >= count and not shared:
            return
        px = vq()
        py = vq()
        pz = vq()
        r2 = vq()
        rq = vq()
        gl = vq()
        tlo = wp.vec3(1.0e30)
        thi = wp.vec3(-1.0e30)
        for q in range(qb):
            r2[q] = -1.0
            px[q] = FAR
            py[q] = FAR
            pz[q] = FAR
            if t0 + q < count:
                k = order[t0 + q]
                p = points[k]
                r = radius[k]
                px[q] = p[0]
                py[q] = p[1]
                pz[q] = p[2]
                r2[q] = r * r
                rq[q] = r
                gl[q] = -LOG2E * g[k]
                e = wp.vec3(r + pad)
                tlo = wp.min(tlo, p - e)
                thi = wp.max(thi, p + e)
        lo, hi = thread_span_box(grp, tlo, thi, box_lo, box_hi, origin, inv_h, dims)
        ball = thread_ball(tlo, thi, origin, inv_h)
        an = vq()
        ad = vq()
        ax = vq()
        ay = vq()
        az = vq()
        nrows = box_rows(lo, hi)
        steps = row_walk(nrows, s, splits)
        held = wp.vec2i(0, 0)
        walked = int(0)
        for row in range(steps[0], nrows, steps[1]):
            whole, held = walk_span(walked, row, steps[1], nrows, shared, held, lo, hi, dims, first,
                                    wp.static(qb == 1 and CULL) and (on_cuda() or wp.static(CULL_CPU)), ball)
            walked += 1
            span = row_share(whole, s, splits, steps[1])
            i = span[0]
            while i < span[1]:
                j = span[1]
                mode = int(1)  # 0: beyond every ball, 1: the chords, 2: inside every ball
                if wp.static(chunks):
                    c = i // CHUNK
                    j = wp.min(j, (c + 1) * CHUNK)
                    if j - i >= MIN_RUN:
                        bl = chunk_lo[c]
                        bh = chunk_hi[c]
                        inside = True
                        near = False
                        for q in range(qb):
                            if r2[q] >= 0.0:
                                # farthest and nearest points of the run's box from the query
                                fx = wp.max(px[q] - bl[0], bh[0] - px[q])
                                fy = wp.max(py[q] - bl[1], bh[1] - py[q])
                                fz = wp.max(pz[q] - bl[2], bh[2] - pz[q])
                                nx = wp.max(wp.max(bl[0] - px[q], px[q] - bh[0]), 0.0)
                                ny = wp.max(wp.max(bl[1] - py[q], py[q] - bh[1]), 0.0)
                                nz = wp.max(wp.max(bl[2] - pz[q], pz[q] - bh[2]), 0.0)
                                if fx * fx + fy * fy + fz * fz > r2[q]:
                                    inside = False
                                if nx * nx + ny * ny + nz * nz <= r2[q]:
                                    near = True
                        mode = 0
                        if near:
                            mode = 1
                            if inside:
                                mode = 2
                    if wp.static(vote):
                        # a warp walks the runs in step: where some of its threads need the chords, those inside
                        # every ball take them too (the same sums) instead of a second, serialized pass
                        if warp_any(int(mode == 1)) != 0 and mode == 2:
                            mode = 1
                if mode == 2:
                    for ii in range(i, j):
                        sm = load4(seg_m, ii)
                        ev = load4(val, ii)
                        L = float(0.0)
                        if wp.static(unit):
                            L = sm[3] + load4(seg_h, ii)[3]
                        else:
                            L = 2.0 * load4(seg_h, ii)[3]
                        for q in range(qb):
                            cx = sm[0] - px[q]
                            cy = sm[1] - py[q]
                            cz = sm[2] - pz[q]
                            w = L * exp2((cx * cx + cy * cy + cz * cz) * gl[q])
                            an[q] += w * ev[0]
                            ad[q] += w
                            ax[q] += w * ev[1]
                            ay[q] += w * ev[2]
                            az[q] += w * ev[3]
                elif mode == 1:
                    for ii in range(i, j):
                        sm = load4(seg_m, ii)
                        sh = load4(seg_h, ii)
                        ev = load4(val, ii)
                        hh = sh[3] * sh[3]
                        half = sh[3]
                        if wp.static(unit):
                            # the farthest point of the segment m + u d, u in [-sh[3], sm[3]], from m
                            half = wp.max(sm[3], sh[3])
                        for q in range(qb):
                            cx = sm[0] - px[q]
                            cy = sm[1] - py[q]
                            cz = sm[2] - pz[q]
                            cc = cx * cx + cy * cy + cz * cz
                            near_q = True
                            if wp.static(prefilter):
                                t = rq[q] + half
                                near_q = cc <= t * t
                            if near_q:
                                ch = cx * sh[0] + cy * sh[1] + cz * sh[2]
                                l_in = float(0.0)
                                disc = float(0.0)
                                if wp.static(unit):
                                    # |m - p + u d|^2 = r^2 at u = -ch +- sqrt(disc)
                                    disc = ch * ch - (cc - r2[q])
                                else:
                                    disc = ch * ch - hh * (cc - r2[q])
                                # no branch on the root: an edge whose line misses the ball (disc <= 0) gets an empty
                                # chord from the same clipping
                                sq = wp.sqrt(wp.max(disc, 0.0))
                                if wp.static(unit):
                                    # the chord min(sq - ch, a) - max(-sq - ch, -b) of the segment u in [-b, a]
                                    # (a = b = L/2 for a whole edge), without negations
                                    l_in = wp.max(wp.min(sq - ch, sm[3]) + wp.min(sq + ch, sh[3]), 0.0)
                                else:
                                    # the roots of |m - p + u h|^2 = r^2 clipped to [-1, 1]: an edge with both
                                    # ends inside gets its whole length, a degenerate one (1 / hh = 0) nothing
                                    u1 = wp.max((-ch - sq) * sm[3], -1.0)
                                    u2 = wp.min((-ch + sq) * sm[3], 1.0)
                                    l_in = wp.max(u2 - u1, 0.0) * half
                                w = l_in * exp2(cc * gl[q])
                                an[q] += w * ev[0]
                                ad[q] += w
                                ax[q] += w * ev[1]
                                ay[q] += w * ev[2]
                                az[q] += w * ev[3]
                i = j
        for q in range(qb):
            if t0 + q < count:
                if accumulate != 0:
                    part_num[s, t0 + q] = part_num[s, t0 + q] + an[q]
                    part_den[s, t0 + q] = part_den[s, t0 + q] + ad[q]
                    part_n[s, t0 + q] = part_n[s, t0 + q] + wp.vec3(ax[q], ay[q], az[q])
                else:
                    part_num[s, t0 + q] = an[q]
                    part_den[s, t0 + q] = ad[q]
                    part_n[s, t0 + q] = wp.vec3(ax[q], ay[q], az[q])

    _ball_cells_kernels[key] = ball_cells
    return ball_cells


@wp.kernel(enable_backward=False, module="unique", module_options={"max_unroll": 32})
def chunk_boxes(
    seg_m: wp.array(dtype=wp.vec4),
    seg_h: wp.array(dtype=wp.vec4),
    unit: int,
    start: wp.array(dtype=int),
    end: wp.array(dtype=int),
    lo: wp.array(dtype=wp.vec3),
    hi: wp.array(dtype=wp.vec3),
):
    """Bounding box of the edges of sorted records ``CHUNK c .. CHUNK (c + 1) - 1`` (both ends of each), from the
    records of :func:`pack_ball_sources` or :func:`pack_piece_sources` (``unit``: of the "unit" form), for the chunks
    that hold records from ``start[0]`` on (those the chunked traversals read: all, or a dense bucket of long edges
    sorted last) up to ``end[-1]`` (the last traversal's cell bounds: the records past it, slots with no piece, are
    left out). The loop has a fixed trip count, so it unrolls and all of a thread's reads are in flight together
    (there are few threads)."""
    c = wp.tid()
    if (c + 1) * CHUNK <= start[0]:
        return
    n = end[end.shape[0] - 1]
    blo = wp.vec3(1.0e30)
    bhi = wp.vec3(-1.0e30)
    for k in range(CHUNK):
        i = c * CHUNK + k
        if i < n:
            sm = seg_m[i]
            sh = seg_h[i]
            m = wp.vec3(sm[0], sm[1], sm[2])
            d = wp.vec3(sh[0], sh[1], sh[2])
            if unit != 0:
                # the segment m + u d, u in [-sh[3], sm[3]]
                ea = m + d * sm[3]
                eb = m - d * sh[3]
                blo = wp.min(blo, wp.min(ea, eb))
                bhi = wp.max(bhi, wp.max(ea, eb))
            else:
                h = wp.vec3(wp.abs(d[0]), wp.abs(d[1]), wp.abs(d[2]))
                blo = wp.min(blo, m - h)
                bhi = wp.max(bhi, m + h)
    lo[c] = blo
    hi[c] = bhi


# the variant of the ball kernel the operators launch (bench/tune.py times the others); None: chosen per traversal
# by ball_variant
BALL_VARIANT = {"prefilter": None, "form": None, "chunks": None}
# runs of edge records are tested as a whole from this ball radius on, in mean edge lengths, per device kind (a run of
# CHUNK records is a patch a few edges wide: a smaller ball seldom holds one). On an H200, over pieces of the edges,
# testing runs cost 5-16 % at 6-8 edge lengths (koala 6 l 0.45 -> 0.52 ms, nefertiti 8 l 0.56 -> 0.59 ms) and saved a
# third from 12 on (koala 12 l 1.69 -> 1.11 ms, where a thread takes several queries).
CHUNK_REACH = {"cuda": 10.0, "cpu": 6.0}
# Chunked ball kernels: a run inside every ball of one thread but not of all threads of its warp takes the chords
VOTE = True


def ball_variant(strategy: str, per_thread: int, reach: float, one_cell: bool = False, cuda: bool = True) -> dict:
    """The :func:`ball_cells_kernel` options of one launch of a traversal (those of :data:`BALL_VARIANT` left None),
    measured on an H200 (``bench/tune.py``):

    * the midpoint prefilter, with "half" records, for a grid traversal on the CPU only, where one thread skips the
      chord of every far edge. On CUDA a warp takes the chords of an edge wherever one of its threads needs them,
      and since the row walk skips the cells beyond every ball of a warp (:func:`walk_span`), few edges are left
      that none needs: without the prefilter's branch VNC-hard was 2-7 % faster at 2-6 mean edge lengths on
      nefertiti and koala subdivided to 800k and 200k vertices, and as fast or faster on the 50k ones
      (``docs/results/tune_h200_prefilter_form.json``);
    * otherwise no prefilter and "unit" records (roots in length units: fewer operations per chord);
    * chunked runs for balls of at least :data:`CHUNK_REACH` mean edge lengths (a third faster at 12-16 on CUDA)
      and for every launch over one cell (``one_cell``: a dense traversal, 1.6x faster at half the diagonal, or the long
      edges' one of a grid traversal, most of whose runs are far from a small ball).
    """
    v = dict(BALL_VARIANT)
    if v["prefilter"] is None:
        v["prefilter"] = strategy == "grid" and not cuda
    if v["form"] is None:
        v["form"] = "half" if per_thread == 1 and v["prefilter"] else "unit"
    if v["chunks"] is None:
        v["chunks"] = strategy == "dense" or one_cell or reach >= CHUNK_REACH["cuda" if cuda else "cpu"]
    return v


@wp.kernel(enable_backward=False)
def reduce_sums(
    order: wp.array(dtype=int),
    part_num: wp.array2d(dtype=float),
    part_den: wp.array2d(dtype=float),
    part_n: wp.array2d(dtype=wp.vec3),
    num: wp.array(dtype=float),
    den: wp.array(dtype=float),
    nsum: wp.array(dtype=wp.vec3),
    H: wp.array(dtype=float),
    n: wp.array(dtype=wp.vec3),
):
    """Adds the split partial sums in a fixed order and scatters them to the query's own index ``order[t]``;
    ``H = num / (2 den)`` (Eqs. (2), (3), zero where nothing was in reach), ``n = nsum / |nsum|``."""
    t = wp.tid()
    k = order[t]
    a = float(0.0)
    b = float(0.0)
    c = wp.vec3(0.0)
    for s in range(part_num.shape[0]):
        a += part_num[s, t]
        b += part_den[s, t]
        c += part_n[s, t]
    num[k] = a
    den[k] = b
    nsum[k] = c
    h = float(0.0)
    if b > 0.0:
        h = a / (2.0 * b)
    H[k] = h
    n[k] = c / wp.max(wp.length(c), 1.0e-30)


@wp.kernel(enable_backward=False, module="unique", module_options={"fast_math": True})
def soft_cells_grad_x(
    x: wp.array(dtype=wp.vec3),
    tau: wp.array(dtype=float),
    kappa: float,
    count: int,
    size: int,
    order: wp.array(dtype=int),
    box_lo: wp.array(dtype=wp.vec3i),
    box_hi: wp.array(dtype=wp.vec3i),
    first: wp.array(dtype=int),
    dims: wp.vec3i,
    origin: wp.vec3,
    inv_h: float,
    pad: float,
    pos: wp.array(dtype=wp.vec4),
    val: wp.array(dtype=wp.vec4),
    num: wp.array(dtype=float),
    den: wp.array(dtype=float),
    nsum: wp.array(dtype=wp.vec3),
    H_grad: wp.array(dtype=float),
    n_grad: wp.array(dtype=wp.vec3),
    part_gx: wp.array2d(dtype=wp.vec3),
):
    """Adjoint of :func:`soft_cells_kernel` w.r.t. the query vertex (the ``x_grad`` part of :func:`soft_backward`),
    gathered over the same pairs: ``sum_j -2 g w_kj (gN L_j alpha_j + gD L_j + gS . L_j n_j) (x_k - m_j)``."""
    s, t = wp.tid()
    if t >= count:
        return
    k = order[t]
    grp = t // size
    D = den[k]
    if D <= 0.0:
        part_gx[s, t] = wp.vec3(0.0)
        return
    p = x[k]
    r = tau[k]
    sigma = r / kappa
    gk = 1.0 / (2.0 * sigma * sigma)
    r2 = r * r
    gN = H_grad[k] / (2.0 * D)
    gD = -H_grad[k] * num[k] / (2.0 * D * D)
    S = nsum[k]
    sl = wp.max(wp.length(S), 1.0e-30)
    nk = S / sl
    gS = (n_grad[k] - nk * wp.dot(nk, n_grad[k])) / sl
    lo, hi = thread_box(grp, p, r + pad, box_lo, box_hi, origin, inv_h, dims)
    nrows = box_rows(lo, hi)
    ns = part_gx.shape[0]
    acc = wp.vec3(0.0)
    walk = row_walk(nrows, s, ns)
    for row in range(walk[0], nrows, walk[1]):
        span = row_share(row_span(row, lo, hi, dims, first), s, ns, walk[1])
        for i in range(span[0], span[1]):
            ep = load4(pos, i)
            d = p - wp.vec3(ep[0], ep[1], ep[2])
            q = wp.dot(d, d)
            w = float(0.0)
            if q <= r2:
                w = wp.exp(-q * gk)
            ev = load4(val, i)
            acc += (w * (gN * ev[0] + gD * ep[3] + wp.dot(gS, wp.vec3(ev[1], ev[2], ev[3])))) * d
    part_gx[s, t] = (-2.0 * gk) * acc


@wp.kernel(enable_backward=False)
def reduce_add_vec3(order: wp.array(dtype=int), part: wp.array2d(dtype=wp.vec3), out: wp.array(dtype=wp.vec3)):
    """``out[order[t]] += sum_s part[s, t]`` (fixed order)."""
    t = wp.tid()
    acc = wp.vec3(0.0)
    for s in range(part.shape[0]):
        acc += part[s, t]
    k = order[t]
    out[k] = out[k] + acc


@wp.kernel(enable_backward=False)
def pack_vertex_adjoints(
    order: wp.array(dtype=int),
    x: wp.array(dtype=wp.vec3),
    tau: wp.array(dtype=float),
    kappa: float,
    num: wp.array(dtype=float),
    den: wp.array(dtype=float),
    nsum: wp.array(dtype=wp.vec3),
    H_grad: wp.array(dtype=float),
    n_grad: wp.array(dtype=wp.vec3),
    pos: wp.array(dtype=wp.vec4),
    coef: wp.array(dtype=wp.vec4),
    gs: wp.array(dtype=wp.vec4),
):
    """Vertices in sorted order as sources of the edge adjoint pass: ``pos = (x_k, tau_k^2)``,
    ``coef = (g_k, gN_k, gD_k, 0)`` and ``gs = (gS_k, 0)`` (see :func:`soft_backward`)."""
    i = wp.tid()
    k = order[i]
    p = x[k]
    r = tau[k]
    sigma = r / kappa
    D = den[k]
    gN = float(0.0)
    gD = float(0.0)
    gS = wp.vec3(0.0)
    if D > 0.0:
        gN = H_grad[k] / (2.0 * D)
        gD = -H_grad[k] * num[k] / (2.0 * D * D)
        S = nsum[k]
        sl = wp.max(wp.length(S), 1.0e-30)
        nk = S / sl
        gS = (n_grad[k] - nk * wp.dot(nk, n_grad[k])) / sl
    pos[i] = wp.vec4(p[0], p[1], p[2], r * r)
    coef[i] = wp.vec4(1.0 / (2.0 * sigma * sigma), gN, gD, 0.0)
    gs[i] = wp.vec4(gS[0], gS[1], gS[2], 0.0)


@wp.kernel(enable_backward=False, module="unique", module_options={"fast_math": True})
def soft_cells_grad_edges(
    mid: wp.array(dtype=wp.vec3),
    angle: wp.array(dtype=float),
    enormal: wp.array(dtype=wp.vec3),
    count: int,
    size: int,
    order: wp.array(dtype=int),
    box_lo: wp.array(dtype=wp.vec3i),
    box_hi: wp.array(dtype=wp.vec3i),
    first: wp.array(dtype=int),
    dims: wp.vec3i,
    origin: wp.vec3,
    inv_h: float,
    pad: float,
    pos: wp.array(dtype=wp.vec4),
    coef: wp.array(dtype=wp.vec4),
    gs: wp.array(dtype=wp.vec4),
    part_a: wp.array2d(dtype=float),
    part_b: wp.array2d(dtype=float),
    part_c: wp.array2d(dtype=wp.vec3),
    part_m: wp.array2d(dtype=wp.vec3),
):
    """Adjoint of :func:`soft_cells_kernel` w.r.t. the edge quantities, gathered per edge over the vertices that reach it:
    ``A = sum gN w``, ``B = sum gD w``, ``C = sum gS w`` and ``M = sum g w (gN alpha + gD + gS . n_j) (x_k - m_j)``."""
    s, t = wp.tid()
    if t >= count:
        return
    j = order[t]
    grp = t // size
    m = mid[j]
    a = angle[j]
    u = enormal[j]
    lo, hi = thread_box(grp, m, pad, box_lo, box_hi, origin, inv_h, dims)
    nrows = box_rows(lo, hi)
    ns = part_a.shape[0]
    A = float(0.0)
    B = float(0.0)
    C = wp.vec3(0.0)
    M = wp.vec3(0.0)
    walk = row_walk(nrows, s, ns)
    for row in range(walk[0], nrows, walk[1]):
        span = row_share(row_span(row, lo, hi, dims, first), s, ns, walk[1])
        for i in range(span[0], span[1]):
            vp = load4(pos, i)
            d = wp.vec3(vp[0], vp[1], vp[2]) - m
            q = wp.dot(d, d)
            vc = load4(coef, i)
            w = float(0.0)
            if q <= vp[3]:
                w = wp.exp(-q * vc[0])
            g4 = load4(gs, i)
            gsv = wp.vec3(g4[0], g4[1], g4[2])
            A += vc[1] * w
            B += vc[2] * w
            C += w * gsv
            M += (vc[0] * w * (vc[1] * a + vc[2] + wp.dot(gsv, u))) * d
    part_a[s, t] = A
    part_b[s, t] = B
    part_c[s, t] = C
    part_m[s, t] = M


@wp.kernel(enable_backward=False)
def reduce_edge_grads(
    order: wp.array(dtype=int),
    length: wp.array(dtype=float),
    angle: wp.array(dtype=float),
    enormal: wp.array(dtype=wp.vec3),
    part_a: wp.array2d(dtype=float),
    part_b: wp.array2d(dtype=float),
    part_c: wp.array2d(dtype=wp.vec3),
    part_m: wp.array2d(dtype=wp.vec3),
    angle_grad: wp.array(dtype=float),
    length_grad: wp.array(dtype=float),
    enormal_grad: wp.array(dtype=wp.vec3),
    mid_grad: wp.array(dtype=wp.vec3),
):
    """Edge gradients from the gathered sums (the atomics of :func:`soft_backward`, added up per edge):
    ``dalpha += L A``, ``dn += L C``, ``dL += alpha A + B + n . C``, ``dm += 2 L M``."""
    t = wp.tid()
    j = order[t]
    A = float(0.0)
    B = float(0.0)
    C = wp.vec3(0.0)
    M = wp.vec3(0.0)
    for s in range(part_a.shape[0]):
        A += part_a[s, t]
        B += part_b[s, t]
        C += part_c[s, t]
        M += part_m[s, t]
    L = length[j]
    angle_grad[j] = angle_grad[j] + L * A
    enormal_grad[j] = enormal_grad[j] + L * C
    length_grad[j] = length_grad[j] + angle[j] * A + B + wp.dot(enormal[j], C)
    mid_grad[j] = mid_grad[j] + (2.0 * L) * M


@wp.func
def scale_params(taus: wp.array(dtype=float), offset: int, kappa: float):
    """Squared radii and base-2 Gaussian factors ``-log2(e) kappa^2 / (2 tau^2)`` of the (up to) 16 scales
    ``taus[offset:]`` (``exp(-d^2 / 2 sigma^2) = 2^(d^2 gl)``); missing scales get radius^2 = -1 (never reached).
    ``kappa = 0`` gives unweighted scales (factor 0)."""
    r2 = vec16()
    gl = vec16()
    for c in range(16):
        r2[c] = -1.0
        if offset + c < taus.shape[0]:
            tc = taus[offset + c]
            r2[c] = tc * tc
            gl[c] = -LOG2E * kappa * kappa / (2.0 * tc * tc)
    return r2, gl


@wp.func
def prefix_max4(r2: vec16):
    """``pm[b] = max(r2[0 .. 4 b + 3])``: the largest squared radius of scale blocks ``0..b``."""
    pm = wp.vec4()
    m = float(-1.0)
    for b in range(4):
        for c in range(4):
            m = wp.max(m, r2[4 * b + c])
        pm[b] = m
    return pm


@wp.kernel(enable_backward=False, module="unique", module_options={"fast_math": True})
def soft_cells_multiscale(
    x: wp.array(dtype=wp.vec3),
    taus: wp.array(dtype=float),
    offset: int,
    kappa: float,
    count: int,
    size: int,
    order: wp.array(dtype=int),
    box_lo: wp.array(dtype=wp.vec3i),
    box_hi: wp.array(dtype=wp.vec3i),
    first: wp.array(dtype=int),
    dims: wp.vec3i,
    origin: wp.vec3,
    inv_h: float,
    pad: float,
    pos: wp.array(dtype=wp.vec4),
    val: wp.array(dtype=wp.vec4),
    part_num: wp.array2d(dtype=float),
    part_den: wp.array2d(dtype=float),
):
    """Eq. (3) at the 16 scales ``taus[offset:offset + 16]`` (ascending) in one traversal at the largest.

    The 32 sums live in registers; row ``16 s + c`` of the partial arrays holds scale ``c`` of split ``s``.
    """
    s, t = wp.tid()
    if t >= count:
        return
    k = order[t]
    grp = t // size
    r2, gl = scale_params(taus, offset, kappa)
    pm = prefix_max4(r2)
    rmax2 = pm[3]
    p = x[k]
    lo, hi = thread_box(grp, p, wp.sqrt(wp.max(rmax2, 0.0)) + pad, box_lo, box_hi, origin, inv_h, dims)
    nrows = box_rows(lo, hi)
    ns = part_num.shape[0] // 16
    an = vec16()
    ad = vec16()
    for row in range(nrows):
        span = row_part(row_span(row, lo, hi, dims, first), row, s, ns)
        for i in range(span[0], span[1]):
            ep = load4(pos, i)
            d = p - wp.vec3(ep[0], ep[1], ep[2])
            q = wp.dot(d, d)
            # scales ascend, so a pair beyond the largest radius of blocks 0..b reaches none of them: blocks are
            # visited from the top and the walk stops at the first block out of reach (about 3 scales per pair)
            if q <= pm[3]:
                la = load4(val, i)[0]
                L = ep[3]
                for c in range(4):
                    if q <= r2[12 + c]:
                        w = exp2(q * gl[12 + c])
                        an[12 + c] += w * la
                        ad[12 + c] += w * L
                if q <= pm[2]:
                    for c in range(4):
                        if q <= r2[8 + c]:
                            w = exp2(q * gl[8 + c])
                            an[8 + c] += w * la
                            ad[8 + c] += w * L
                    if q <= pm[1]:
                        for c in range(4):
                            if q <= r2[4 + c]:
                                w = exp2(q * gl[4 + c])
                                an[4 + c] += w * la
                                ad[4 + c] += w * L
                        if q <= pm[0]:
                            for c in range(4):
                                if q <= r2[0 + c]:
                                    w = exp2(q * gl[0 + c])
                                    an[0 + c] += w * la
                                    ad[0 + c] += w * L
    for c in range(16):
        part_num[16 * s + c, t] = an[c]
        part_den[16 * s + c, t] = ad[c]


@wp.kernel(enable_backward=False, module="unique", module_options={"fast_math": True})
def ball_cells_multiscale(
    points: wp.array(dtype=wp.vec3),
    taus: wp.array(dtype=float),
    offset: int,
    kappa: float,
    count: int,
    size: int,
    order: wp.array(dtype=int),
    box_lo: wp.array(dtype=wp.vec3i),
    box_hi: wp.array(dtype=wp.vec3i),
    first: wp.array(dtype=int),
    dims: wp.vec3i,
    origin: wp.vec3,
    inv_h: float,
    pad: float,
    seg_m: wp.array(dtype=wp.vec4),
    seg_h: wp.array(dtype=wp.vec4),
    val: wp.array(dtype=wp.vec4),
    splits: int,
    row0: int,
    part_num: wp.array2d(dtype=float),
    part_den: wp.array2d(dtype=float),
):
    """Eq. (2) at the 16 scales ``taus[offset:offset + 16]`` in one traversal at the largest radius
    (``kappa = 0``: unweighted); split ``s`` writes rows ``16 (row0 + s) + c``."""
    s, t = wp.tid()
    if t >= count:
        return
    k = order[t]
    grp = t // size
    r2, gl = scale_params(taus, offset, kappa)
    pm = prefix_max4(r2)
    rmax2 = pm[3]
    p = points[k]
    lo, hi = thread_box(grp, p, wp.sqrt(wp.max(rmax2, 0.0)) + pad, box_lo, box_hi, origin, inv_h, dims)
    nrows = box_rows(lo, hi)
    ns = splits
    an = vec16()
    ad = vec16()
    for row in range(nrows):
        span = row_part(row_span(row, lo, hi, dims, first), row, s, ns)
        for i in range(span[0], span[1]):
            sm = load4(seg_m, i)
            sh = load4(seg_h, i)
            cx = sm[0] - p[0]
            cy = sm[1] - p[1]
            cz = sm[2] - p[2]
            cc = cx * cx + cy * cy + cz * cz
            ch = cx * sh[0] + cy * sh[1] + cz * sh[2]
            hh = sh[3] * sh[3]
            # the chord grows with the radius: a segment missing the largest ball of blocks 0..b (no real root of
            # |m - p + u h|^2 = r^2) misses all of them
            disc0 = ch * ch - hh * cc
            if disc0 + hh * pm[3] > 0.0:
                a = load4(val, i)[0]
                for c in range(4):
                    l_in = chord(cc, ch, hh, sm[3], sh[3], r2[12 + c])
                    if l_in > 0.0:
                        w = l_in * exp2(cc * gl[12 + c])
                        an[12 + c] += w * a
                        ad[12 + c] += w
                if disc0 + hh * pm[2] > 0.0:
                    for c in range(4):
                        l_in = chord(cc, ch, hh, sm[3], sh[3], r2[8 + c])
                        if l_in > 0.0:
                            w = l_in * exp2(cc * gl[8 + c])
                            an[8 + c] += w * a
                            ad[8 + c] += w
                    if disc0 + hh * pm[1] > 0.0:
                        for c in range(4):
                            l_in = chord(cc, ch, hh, sm[3], sh[3], r2[4 + c])
                            if l_in > 0.0:
                                w = l_in * exp2(cc * gl[4 + c])
                                an[4 + c] += w * a
                                ad[4 + c] += w
                        if disc0 + hh * pm[0] > 0.0:
                            for c in range(4):
                                l_in = chord(cc, ch, hh, sm[3], sh[3], r2[0 + c])
                                if l_in > 0.0:
                                    w = l_in * exp2(cc * gl[0 + c])
                                    an[0 + c] += w * a
                                    ad[0 + c] += w
    for c in range(16):
        part_num[16 * (row0 + s) + c, t] = an[c]
        part_den[16 * (row0 + s) + c, t] = ad[c]


@wp.kernel(enable_backward=False)
def reduce_multiscale(
    order: wp.array(dtype=int),
    part_num: wp.array2d(dtype=float),
    part_den: wp.array2d(dtype=float),
    offset: int,
    H: wp.array2d(dtype=float),
):
    """``H[offset + c, order[t]] = num / (2 den)`` from the split partials of scale ``c`` (zero where ``den = 0``)."""
    c, t = wp.tid()
    a = float(0.0)
    b = float(0.0)
    for s in range(part_num.shape[0] // 16):
        a += part_num[16 * s + c, t]
        b += part_den[16 * s + c, t]
    h = float(0.0)
    if b > 0.0:
        h = a / (2.0 * b)
    H[offset + c, order[t]] = h


@wp.kernel(enable_backward=False)
def gaussian_factor(radius: wp.array(dtype=float), kappa: float, g: wp.array(dtype=float)):
    """``g = kappa^2 / (2 r^2)``: the Gaussian factor ``1 / (2 sigma^2)`` with ``sigma = r / kappa``."""
    i = wp.tid()
    r = radius[i]
    g[i] = kappa * kappa / (2.0 * r * r)
