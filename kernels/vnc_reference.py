"""The VNC operator as the paper writes it (Sec. 3.1), one query per thread through a ``wp.Bvh``: the reference.

Read this file beside the paper. Each kernel sums one equation over the edges a BVH query returns, with the terms of
:mod:`kernels.vnc_terms` (the edge quantities come from :func:`kernels.vnc_terms.edge_geometry`):

* :func:`soft_forward` and :func:`soft_backward`: VNC-soft, Eq. (3), ``H = sum alpha delta w L / (2 sum w L)`` over
  the edges whose midpoint is within the cut-off ``r = kappa sigma = tau``, and its adjoint;
* :func:`ball_sums` and :func:`ball_backward`: the sums of Eqs. (1)-(2), ``sum alpha delta w l`` and ``sum w l`` over
  the edges that cross a ball (``l`` the chord inside it), and their adjoint (the chord's included);
* :func:`soft_multiscale` and :func:`ball_multiscale`: Eqs. (3) and (2) at many scales in one traversal.

They are the ``strategy="bvh"`` of every operator and the oracle the tests hold the grid engine
(:mod:`kernels.vnc_sums`, read second) against: both visit the same pairs and evaluate them with the same terms.
"""

import warp as wp

from .vnc_terms import (adjoint_coefficients, ball_pair_adjoint, curvature_ratio, gaussian_factor, gaussian_gradient,
                        gaussian_weight, segment_chord, unit)


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
    """VNC-soft, Eq. (3), at vertex ``k`` (one per thread): ``N = sum alpha_j delta_j w_kj L_j``,
    ``D = sum w_kj L_j``, ``S = sum w_kj L_j n_j`` over the edges with ``|x_k - m_j| <= tau_k``;
    ``H = N / 2D``, ``n = S / |S|``. ``num``, ``den`` and ``nsum`` keep the sums for the backward pass."""
    k = wp.tid()
    p = x[k]
    r = tau[k]
    f = gaussian_factor(r, kappa)
    r2 = r * r
    ext = wp.vec3(r, r, r)
    acc_num = float(0.0)
    acc_den = float(0.0)
    acc_n = wp.vec3(0.0)
    query = wp.bvh_query_aabb(bvh, p - ext, p + ext)
    j = int(0)
    while wp.bvh_query_next(query, j):
        d = p - mid[j]
        d2 = wp.dot(d, d)
        if d2 <= r2:
            c = gaussian_weight(d2, f) * length[j]
            acc_num += c * angle[j]
            acc_den += c
            acc_n += c * enormal[j]
    num[k] = acc_num
    den[k] = acc_den
    nsum[k] = acc_n
    H[k] = curvature_ratio(acc_num, acc_den)
    n[k] = unit(acc_n)


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
    """The adjoint of :func:`soft_forward`: for ``c_kj = w_kj L_j`` each pair contributes ``G = dL/dc =
    gN alpha_j + gD + gS . n_j`` (:func:`kernels.vnc_terms.adjoint_coefficients`): ``dalpha_j += gN c``,
    ``dn_j += gS c``, ``dL_j += G w`` and ``G L_j dw/dx_k`` to the vertex, minus that to the midpoint."""
    k = wp.tid()
    p = x[k]
    r = tau[k]
    f = gaussian_factor(r, kappa)
    r2 = r * r
    gN, gD, gS = adjoint_coefficients(num[k], den[k], nsum[k], H_grad[k], n_grad[k])
    ext = wp.vec3(r, r, r)
    gx = wp.vec3(0.0)
    query = wp.bvh_query_aabb(bvh, p - ext, p + ext)
    j = int(0)
    while wp.bvh_query_next(query, j):
        d = p - mid[j]
        d2 = wp.dot(d, d)
        if d2 <= r2:
            w = gaussian_weight(d2, f)
            L = length[j]
            c = w * L
            G = gN * angle[j] + gD + wp.dot(gS, enormal[j])
            wp.atomic_add(angle_grad, j, gN * c)
            wp.atomic_add(enormal_grad, j, gS * c)
            wp.atomic_add(length_grad, j, G * w)
            gd = (G * L) * gaussian_gradient(d, f, w)
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
    """Eq. (3) at every scale of ``taus`` (ascending) in one traversal at the largest scale: a pair at distance
    ``d`` contributes to the scales with ``tau_s >= d`` only, so the work is that of separate calls while the tree is
    walked once."""
    k = wp.tid()
    p = x[k]
    S = taus.shape[0]
    r = taus[S - 1]
    ext = wp.vec3(r, r, r)
    query = wp.bvh_query_aabb(bvh, p - ext, p + ext)
    j = int(0)
    while wp.bvh_query_next(query, j):
        d = p - mid[j]
        d2 = wp.dot(d, d)
        L = length[j]
        a = angle[j]
        s = S - 1
        while s >= 0:
            ts = taus[s]
            if d2 > ts * ts:
                break
            c = gaussian_weight(d2, gaussian_factor(ts, kappa)) * L
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
    """Eqs. (1)-(2) at query point ``i`` (one per thread): ``num = sum alpha_j delta_j w l_j``, ``den = sum w l_j``,
    ``nsum = sum w l_j n_j`` over the edges that cross the ball of radius ``radius[i]``, ``l_j`` the length inside it
    (:func:`kernels.vnc_terms.segment_chord`) and ``w`` the Gaussian weight of factor ``g[i]`` at the edge's midpoint
    (``g = 0``: w = 1, Eq. (1))."""
    i = wp.tid()
    p = points[i]
    r = radius[i]
    f = g[i]
    ext = wp.vec3(r, r, r)
    acc_num = float(0.0)
    acc_den = float(0.0)
    acc_n = wp.vec3(0.0)
    query = wp.bvh_query_aabb(bvh, p - ext, p + ext)
    j = int(0)
    while wp.bvh_query_next(query, j):
        ev = edges[j]
        l = segment_chord(x[ev[0]], x[ev[1]], p, r)
        if l > 0.0:
            d = p - mid[j]
            c = gaussian_weight(wp.dot(d, d), f) * l
            acc_num += c * angle[j]
            acc_den += c
            acc_n += c * enormal[j]
    num[i] = acc_num
    den[i] = acc_den
    nsum[i] = acc_n


@wp.kernel(enable_backward=False)
def ball_backward(
    points: wp.array(dtype=wp.vec3),
    radius: wp.array(dtype=float),
    g: wp.array(dtype=float),
    bvh: wp.uint64,
    x: wp.array(dtype=wp.vec3),
    edges: wp.array(dtype=wp.vec4i),
    length: wp.array(dtype=float),
    angle: wp.array(dtype=float),
    enormal: wp.array(dtype=wp.vec3),
    num: wp.array(dtype=float),
    den: wp.array(dtype=float),
    nsum: wp.array(dtype=wp.vec3),
    H_grad: wp.array(dtype=float),
    n_grad: wp.array(dtype=wp.vec3),
    points_grad: wp.array(dtype=wp.vec3),
    x_grad: wp.array(dtype=wp.vec3),
    angle_grad: wp.array(dtype=float),
    enormal_grad: wp.array(dtype=wp.vec3),
):
    """The adjoint of :func:`ball_sums` normalized as Eq. (2) (``H = num / 2 den``, ``n = nsum / |nsum|``): each pair
    gives the ball's centre, the edge's ends (through its chord and its midpoint's weight), angle and normal their
    parts (:func:`kernels.vnc_terms.ball_pair_adjoint`)."""
    i = wp.tid()
    p = points[i]
    r = radius[i]
    f = g[i]
    gN, gD, gS = adjoint_coefficients(num[i], den[i], nsum[i], H_grad[i], n_grad[i])
    ext = wp.vec3(r, r, r)
    gp = wp.vec3(0.0)
    query = wp.bvh_query_aabb(bvh, p - ext, p + ext)
    j = int(0)
    while wp.bvh_query_next(query, j):
        ev = edges[j]
        L = length[j]
        dp, da, db, d_angle, d_normal = ball_pair_adjoint(p, x[ev[0]], x[ev[1]], 0.5 * L, 0.5 * L, L, r, f,
                                                          angle[j], enormal[j], gN, gD, gS)
        gp += dp
        wp.atomic_add(x_grad, ev[0], da)
        wp.atomic_add(x_grad, ev[1], db)
        wp.atomic_add(angle_grad, j, d_angle)
        wp.atomic_add(enormal_grad, j, d_normal)
    points_grad[i] = points_grad[i] + gp


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
    """Eq. (2) at every scale of ``taus`` (ascending) in one traversal at the largest radius (``kappa = 0``:
    unweighted); an edge that misses a ball misses every smaller one."""
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
        d2 = wp.dot(d, d)
        a = angle[j]
        s = S - 1
        while s >= 0:
            ts = taus[s]
            l = segment_chord(xa, xb, p, ts)
            if l <= 0.0:
                break
            c = gaussian_weight(d2, gaussian_factor(ts, kappa)) * l
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
    H[i] = curvature_ratio(num[i], den[i])
    n[i] = unit(nsum[i])


@wp.kernel(enable_backward=False)
def ratio2d(num: wp.array2d(dtype=float), den: wp.array2d(dtype=float), H: wp.array2d(dtype=float)):
    """``H = num / (2 den)`` elementwise (Eqs. (2)-(3)), zero where ``den = 0``."""
    s, k = wp.tid()
    H[s, k] = curvature_ratio(num[s, k], den[s, k])
