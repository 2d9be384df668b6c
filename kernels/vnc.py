"""Warp kernels of the VNC operator (paper Sec. 3.1): edge quantities, VNC-soft, VNC-hard, Eq. (1).

Conventions shared by every kernel here:

* An interior edge ``j`` is stored as ``(a, b, c0, c1)``: face ``(a, b, c0)`` runs ``a -> b`` and face
  ``(b, a, c1)`` runs ``b -> a`` (consistent winding, outward normals).
* ``angle[j]`` is the signed dihedral angle ``alpha_j * delta_j`` with ``alpha_j`` in ``[0, pi]`` and
  ``delta_j = +1`` on convex edges, so a sphere has positive curvature.
* ``enormal[j]`` is the unit, area-weighted normal of the edge's two faces.
* Gaussian weights are written with ``g = 1 / (2 sigma^2)`` per query so that ``g = 0`` means unweighted.
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
def column_mean(H: wp.array2d(dtype=float), inv_count: float, mean: wp.array(dtype=float)):
    """``mean[s] += H[s, k] / V``: the global mean curve of the VNC-Scale curves (``mean`` zeroed first)."""
    s, k = wp.tid()
    wp.atomic_add(mean, s, H[s, k] * inv_count)


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
