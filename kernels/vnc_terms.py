"""The terms of the VNC operator (paper Sec. 3.1, Eqs. (1)-(3)), each written once as a ``@wp.func``.

Every kernel of the operator, the readable BVH reference (:mod:`kernels.vnc_reference`) and the grid engine
(:mod:`kernels.vnc_sums`) alike, evaluates a pair (query point, edge) with these functions, as Warp's own
``warp/geometry`` module provides per-point functions for kernels to call:

==============================  ================================================================================
term                            function
==============================  ================================================================================
``alpha_j delta_j`` (Eq. 1)     :func:`signed_dihedral`
``n_j`` (Eq. 2 normals)         :func:`edge_normal` (area-weighted) and :func:`unit` (normalization)
``l_j`` (Eq. 1)                 :func:`chord` (a segment by its midpoint and direction), :func:`segment_chord`
``w_kj`` (Eqs. 2-3)             :func:`gaussian_factor`, :func:`gaussian_weight`: ``w = 2^(f d^2)``; cut-off
                                :func:`gaussian_cutoff`
``H = N / 2D`` (Eqs. 2-3)       :func:`curvature_ratio`
adjoints                        :func:`adjoint_coefficients`, :func:`gaussian_gradient`, :func:`chord_gradient`
==============================  ================================================================================

Conventions shared by every kernel:

* An interior edge ``j`` is stored as ``(a, b, c0, c1)``: face ``(a, b, c0)`` runs ``a -> b`` and face
  ``(b, a, c1)`` runs ``b -> a`` (consistent winding, outward normals).
* ``angle[j]`` is the signed dihedral angle ``alpha_j * delta_j`` with ``alpha_j`` in ``[0, pi]`` and
  ``delta_j = +1`` on convex edges, so a sphere has positive curvature.
* The Gaussian weight has one parametrisation: ``w = exp(-d^2 / 2 sigma^2) = 2^(f d^2)`` with the factor
  ``f = -kappa^2 log2(e) / (2 tau^2)`` of a query (``sigma = tau / kappa``); ``f = 0`` is the unweighted
  operator (``w = 1``). Its cut-off ``d <= tau`` is ``f d^2 >= f tau^2 =`` :func:`gaussian_cutoff`.
"""

from typing import Any

import warp as wp

LOG2E = wp.constant(1.4426950408889634)
LN2 = wp.constant(0.6931471805599453)


@wp.func_native(
"return exp2f(x);"
)
def exp2(x: float) -> float:
    """``2^x`` (one ``ex2.approx`` with fast math on CUDA)."""
    ...


@wp.func
def signed_dihedral(xa: wp.vec3, xb: wp.vec3, xc0: wp.vec3, xc1: wp.vec3):
    """Eq. (1): the signed dihedral angle ``alpha_j delta_j`` of edge ``a -> b`` (radians, in ``[-pi, pi]``).

    ``atan2`` of the cross product of the face normals projected on the edge and their dot product, rather than
    ``arccos``: smooth through flat edges, so the gradient stays finite there.
    """
    e = xb - xa
    n0 = wp.cross(e, xc0 - xa)
    n1 = wp.cross(xa - xb, xc1 - xb)
    y = wp.dot(wp.cross(n0, n1), e)
    x = wp.dot(n0, n1) * wp.length(e)
    return wp.atan2(y, x)


@wp.func
def unit(v: wp.vec3):
    """``v / |v|``, zero for a zero vector: the normals of Eq. (2) and of an edge's faces."""
    return v / wp.max(wp.length(v), 1.0e-30)


@wp.func
def edge_normal(xa: wp.vec3, xb: wp.vec3, xc0: wp.vec3, xc1: wp.vec3):
    """The unit, area-weighted normal ``n_j`` of the two faces of edge ``a -> b`` (Eq. (2)'s averaged normals):
    the raw cross products are twice the face areas times the unit normals, so their sum is area-weighted."""
    return unit(wp.cross(xb - xa, xc0 - xa) + wp.cross(xa - xb, xc1 - xb))


@wp.func
def gaussian_cutoff(kappa: float):
    """``f tau^2 = -kappa^2 log2(e) / 2``: the exponent of the Gaussian weight at the cut-off ``d = tau = kappa sigma``
    of Eq. (3), the same for every query (a pair is within it where ``f d^2 >= gaussian_cutoff(kappa)``)."""
    return -kappa * kappa * (0.5 * LOG2E)


@wp.func
def gaussian_factor(tau: float, kappa: float):
    """The factor ``f = -kappa^2 log2(e) / (2 tau^2)`` of the Gaussian weight ``w = 2^(f d^2)`` of Eqs. (2)-(3)
    (``sigma = tau / kappa``); ``kappa = 0`` gives ``f = 0``, the unweighted operator."""
    return gaussian_cutoff(kappa) / (tau * tau)


@wp.func
def gaussian_weight(d2: float, f: float):
    """``w = exp(-d^2 / 2 sigma^2) = 2^(f d^2)`` of Eqs. (2)-(3), ``d2 = d^2``, ``f`` from :func:`gaussian_factor`."""
    return exp2(d2 * f)


@wp.func
def gaussian_gradient(d: wp.vec3, f: float, w: float):
    """``dw / dp`` of the weight ``w = 2^(f |p - m|^2)`` at ``d = p - m`` (minus its gradient in ``m``)."""
    return (2.0 * LN2 * f * w) * d


@wp.func
def chord(cc: Any, ch: Any, r2: Any, a: Any, b: Any):
    """Eq. (1): the length ``l_j`` of the segment ``m + u d``, ``u`` in ``[-b, a]`` (``d`` a unit vector, or zero
    for a degenerate edge), inside the ball ``|p - q| <= r``; ``cc = |m - q|^2``, ``ch = (m - q) . d``,
    ``r2 = r^2`` (float32, or float64 in the adjoints). A whole edge is ``a = b = L / 2``; a piece of it, a sub-range.

    The roots ``u = -ch -+ sqrt(ch^2 - cc + r^2)`` of ``|m - q + u d| = r`` clipped to ``[-b, a]`` bound the chord,
    without a branch: a segment with both ends inside gets its whole length, one whose line misses the ball (no real
    root) or that lies beyond it an empty range.
    """
    zero = type(cc)(0.0)
    sq = wp.sqrt(wp.max(ch * ch - (cc - r2), zero))
    # the chord min(sq - ch, a) - max(-sq - ch, -b), without negations
    return wp.max(wp.min(sq - ch, a) + wp.min(sq + ch, b), zero)


@wp.func
def segment_frame(xa: wp.vec3, xb: wp.vec3):
    """The segment ``xa -> xb`` as its midpoint ``m``, unit direction ``d`` (zero when ``xa = xb``) and half length:
    the form :func:`chord` reads."""
    m = 0.5 * (xa + xb)
    h = 0.5 * (xb - xa)
    half = wp.length(h)
    d = wp.vec3(0.0)
    if half > 0.0:
        d = h / half
    return m, d, half


@wp.func
def segment_chord(xa: wp.vec3, xb: wp.vec3, q: wp.vec3, r: float):
    """Eq. (1): the length of the segment ``[xa, xb]`` inside the ball ``|p - q| <= r`` (:func:`chord`)."""
    m, d, half = segment_frame(xa, xb)
    cm = m - q
    return chord(wp.dot(cm, cm), wp.dot(cm, d), r * r, half, half)


@wp.func
def chord_gradient(cm: wp.vec3d, d: wp.vec3d, L: wp.float64, r2: wp.float64, a: wp.float64, b: wp.float64):
    """The gradient of :func:`chord` ``l`` with respect to the ends ``xa``, ``xb`` of the edge the segment lies on
    and the ball's centre ``q``: ``(dl/dxa, dl/dxb, dl/dq)``. ``cm = m - q`` with ``m`` the edge's midpoint, ``d``
    its unit direction and ``L`` its length; the segment ``u`` in ``[-b, a]`` (along ``d`` from ``m``) is a fixed
    part of the edge (the edge itself or one of its pieces), so each end of the chord is either such a fixed point
    ``xa + t (xb - xa)`` or a root on the sphere.

    With ``l = (P2 - P1) . d``: a fixed end moves with ``(1 - t) dxa + t dxb``; a root ``P`` (``v = P - q``,
    ``lambda = v . d``) moves along the line by ``(v . dq - v_perp . ((1 - t) dxa + t dxb)) / lambda``, where
    ``v_perp = cm - (cm . d) d`` is the same for both roots. Zero where the chord is empty or the edge degenerate. In
    float64: near tangency (``lambda`` small) the gradient is ill-conditioned.
    """
    zero = wp.float64(0.0)
    one = wp.float64(1.0)
    half = wp.float64(0.5)
    ch = wp.dot(cm, d)
    disc = ch * ch - (wp.dot(cm, cm) - r2)
    ga = wp.vec3d()
    gb = wp.vec3d()
    gq = wp.vec3d()
    if disc > zero and L > zero:
        sq = wp.sqrt(disc)
        u1 = wp.max(-ch - sq, -b)
        u2 = wp.min(-ch + sq, a)
        if u2 > u1:
            perp = cm - ch * d
            t1 = u1 / L + half
            t2 = u2 / L + half
            if -ch - sq > -b:  # the chord starts on the sphere (lambda = -sq)
                ga -= ((one - t1) / sq) * perp
                gb -= (t1 / sq) * perp
                gq += perp / sq - d
            else:  # at a fixed point of the edge
                ga -= (one - t1) * d
                gb -= t1 * d
            if -ch + sq < a:  # the chord ends on the sphere (lambda = +sq)
                ga -= ((one - t2) / sq) * perp
                gb -= (t2 / sq) * perp
                gq += perp / sq + d
            else:
                ga += (one - t2) * d
                gb += t2 * d
    return ga, gb, gq


@wp.func
def curvature_ratio(num: float, den: float):
    """Eqs. (2)-(3): ``H = N / 2D`` of the weighted sums ``N = sum alpha delta w l`` and ``D = sum w l``; zero where
    nothing was in reach (``D = 0``)."""
    h = float(0.0)
    if den > 0.0:
        h = num / (2.0 * den)
    return h


@wp.func
def adjoint_coefficients(num: float, den: float, nsum: wp.vec3, gH: float, gn: wp.vec3):
    """The adjoint of ``H = N / 2D`` and ``n = S / |S|`` (Eqs. (2)-(3)) for upstream gradients ``gH``, ``gn``:
    ``(gN, gD, gS) = (gH / 2D, -gH H / D, (I - n n^T) gn / |S|)``, so that a pair of weight ``c = w l`` (or
    ``w L``) contributes ``dL/dc = gN alpha delta + gD + gS . n_j``. Zero where ``D = 0``."""
    gN = float(0.0)
    gD = float(0.0)
    gS = wp.vec3(0.0)
    if den > 0.0:
        gN = gH / (2.0 * den)
        gD = -gH * num / (2.0 * den * den)
        sl = wp.max(wp.length(nsum), 1.0e-30)
        nk = nsum / sl
        gS = (gn - nk * wp.dot(nk, gn)) / sl
    return gN, gD, gS


@wp.func
def ball_pair_adjoint(p: wp.vec3, xa: wp.vec3, xb: wp.vec3, a: float, b: float, L: float, r: float, f: float,
                      alpha: float, n: wp.vec3, gN: float, gD: float, gS: wp.vec3):
    """The adjoint of one pair of Eqs. (1)-(2): the query ``p`` (ball of radius ``r``, Gaussian factor ``f``) and the
    segment ``u`` in ``[-b, a]`` along the unit direction of the edge ``xa -> xb`` from its midpoint (the edge of
    length ``L``, or a piece of it), with the edge's signed angle ``alpha`` and normal ``n``, for the coefficients
    ``gN, gD, gS`` of its query (:func:`adjoint_coefficients`). With ``c = w l`` and
    ``G = dL/dc = gN alpha + gD + gS . n``: ``(dL/dp, dL/dxa, dL/dxb, dL/dalpha, dL/dn)``, the weight's gradient in
    the midpoint shared by both ends; the chord and its gradient in float64 (:func:`chord_gradient`)."""
    m, d, half = segment_frame(xa, xb)
    cm = m - p
    w = gaussian_weight(wp.dot(cm, cm), f)
    gp = wp.vec3(0.0)
    ga = wp.vec3(0.0)
    gb = wp.vec3(0.0)
    g_angle = float(0.0)
    g_normal = wp.vec3(0.0)
    xa64 = wp.vec3d(xa)
    xb64 = wp.vec3d(xb)
    h64 = wp.float64(0.5) * (xb64 - xa64)
    half64 = wp.length(h64)
    if half64 > wp.float64(0.0) and L > 0.0:
        d64 = h64 / half64
        cm64 = wp.float64(0.5) * (xa64 + xb64) - wp.vec3d(p)
        # the segment's extents, fractions of the float32 edge, on the float64 one
        s = half64 / wp.float64(0.5 * L)
        a64 = wp.float64(a) * s
        b64 = wp.float64(b) * s
        r64 = wp.float64(r)
        l = float(chord(wp.dot(cm64, cm64), wp.dot(cm64, d64), r64 * r64, a64, b64))
        if l > 0.0:
            G = gN * alpha + gD + wp.dot(gS, n)
            dla, dlb, dlq = chord_gradient(cm64, d64, wp.float64(2.0) * half64, r64 * r64, a64, b64)
            gw = gaussian_gradient(p - m, f, w)
            gp = G * (l * gw + w * wp.vec3(dlq))
            ga = G * (w * wp.vec3(dla) - 0.5 * l * gw)
            gb = G * (w * wp.vec3(dlb) - 0.5 * l * gw)
            g_angle = gN * w * l
            g_normal = (w * l) * gS
    return gp, ga, gb, g_angle, g_normal


@wp.kernel
def edge_geometry(
    x: wp.array(dtype=wp.vec3),
    edges: wp.array(dtype=wp.vec4i),
    mid: wp.array(dtype=wp.vec3),
    length: wp.array(dtype=float),
    angle: wp.array(dtype=float),
    enormal: wp.array(dtype=wp.vec3),
):
    """Per interior edge: midpoint ``m_j``, length ``L_j``, signed dihedral angle ``alpha_j delta_j`` and unit
    area-weighted normal ``n_j`` (Eqs. (1)-(3)); differentiable (Warp generates its adjoint)."""
    j = wp.tid()
    ev = edges[j]
    xa = x[ev[0]]
    xb = x[ev[1]]
    xc0 = x[ev[2]]
    xc1 = x[ev[3]]
    mid[j] = 0.5 * (xa + xb)
    length[j] = wp.length(xb - xa)
    angle[j] = signed_dihedral(xa, xb, xc0, xc1)
    enormal[j] = edge_normal(xa, xb, xc0, xc1)
