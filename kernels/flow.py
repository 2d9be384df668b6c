"""Warp kernels of VNC-Flow (paper Sec. 3.2, Eq. 5).

The step reads one state and writes another (never in place), so K steps can be recorded on a
``wp.Tape`` and differentiated with respect to the initial vertices.
"""

import warp as wp


# Partial sums of a fixed-order mean (:func:`strided_sums`, :func:`ordered_mean`): a fixed count, the same on every
# device, so the order of the additions is the same on the CPU and on CUDA.
MEAN_PARTS = 256


@wp.kernel(enable_backward=False)
def strided_sums(values: wp.array(dtype=float), partial: wp.array(dtype=wp.float64)):
    """``partial[t] = sum_j values[t + j P]`` (``P = partial.shape[0]``), added in index order in float64: the first
    pass of a mean whose result does not depend on thread timing, as an atomic float sum on CUDA does."""
    t = wp.tid()
    acc = wp.float64(0.0)
    for k in range(t, values.shape[0], partial.shape[0]):
        acc += wp.float64(values[k])
    partial[t] = acc


@wp.kernel(enable_backward=False)
def ordered_mean(partial: wp.array(dtype=wp.float64), inv_count: wp.float64, out: wp.array(dtype=float)):
    """``out[0] = inv_count * sum_t partial[t]``, added in index order by one thread (launch with ``dim=1``)."""
    acc = wp.float64(0.0)
    for t in range(partial.shape[0]):
        acc += partial[t]
    out[0] = float(acc * inv_count)


@wp.kernel(enable_backward=False)
def mean_adjoint(out_grad: wp.array(dtype=float), inv_count: float, values_grad: wp.array(dtype=float)):
    """Adjoint of the mean: ``values_grad[k] += out_grad[0] * inv_count``."""
    k = wp.tid()
    values_grad[k] = values_grad[k] + out_grad[0] * inv_count


@wp.func
def eq5_move(H: float, H_ref: float, lam: float, max_move: float) -> float:
    """Eq. (5): the inward move ``lambda (H(v_k, tau_k) - H_ref)`` along the normal, clamped to ``max_move``."""
    return wp.clamp(lam * (H - H_ref), -max_move, max_move)


@wp.kernel
def flow_step(
    x_in: wp.array(dtype=wp.vec3),
    H: wp.array(dtype=float),
    n: wp.array(dtype=wp.vec3),
    H_ref: wp.array(dtype=float),
    lam: float,
    max_move: wp.array(dtype=float),
    x_out: wp.array(dtype=wp.vec3),
):
    """Eq. (5): ``v_k <- v_k - lambda (H(v_k, tau_k) - H_ref) n(v_k, tau_k)``, each move clamped to ``max_move[k]``."""
    k = wp.tid()
    x_out[k] = x_in[k] - eq5_move(H[k], H_ref[0], lam, max_move[k]) * n[k]


@wp.func
def part_excess(H: float, part: wp.vec4, neck: float) -> float:
    """The thin-part correction of a vertex with curvature ``H`` at its own scale and ``part = (w, h, tube, m)`` from
    :func:`thin_part_correction`: ``w max(H_part - m, 0)``, with the part-scale curvature ``H_part`` the curvature at
    tau_max ``h``, or, at a neck (``h < H <= h / neck``), ``H`` up to ``tube``."""
    h = part[1]
    hp = h
    if H > h and H * neck <= h:
        hp = wp.max(h, wp.min(H, part[2]))
    return part[0] * wp.max(hp - part[3], 0.0)


@wp.kernel(enable_backward=False)
def balanced_step(
    x_in: wp.array(dtype=wp.vec3),
    H: wp.array(dtype=float),
    n: wp.array(dtype=wp.vec3),
    H_ref: wp.array(dtype=float),
    lam: float,
    max_move: wp.array(dtype=float),
    part: wp.array(dtype=wp.vec4),
    neck: float,
    x_out: wp.array(dtype=wp.vec3),
):
    """Eq. (5) as :func:`flow_step`, with the thin-part correction taken off the deviation:
    ``v_k <- v_k - clamp(lambda d_k) n(v_k, tau_k)``. ``d_k = H(v_k, tau_k) - H_ref - w max(h - m, 0)`` with
    :func:`thin_part_correction`'s ``(w, h, tube, m)`` (the part-scale excess turned around on tube-like parts), except
    at a neck (see :func:`part_excess`), where the excess of the neck's own curvature takes off at most the inward
    part of that deviation: ``d_k = max(H(v_k, tau_k) - H_ref - part_excess, min(d_k, 0))``, so a neck stops thinning
    but is never pushed outward by more than the rule before."""
    k = wp.tid()
    c = part[k]
    d = H[k] - H_ref[0] - c[0] * wp.max(c[1] - c[3], 0.0)
    d = wp.max(H[k] - H_ref[0] - part_excess(H[k], c, neck), wp.min(d, 0.0))
    x_out[k] = x_in[k] - eq5_move(d, 0.0, lam, max_move[k]) * n[k]


@wp.kernel(enable_backward=False)
def thin_part_correction(
    thickness: wp.array(dtype=float),
    H_large: wp.array2d(dtype=float),
    mean_large: wp.array(dtype=float),
    row: int,
    edge: float,
    tube: float,
    ball: float,
    out: wp.array(dtype=wp.vec4),
):
    """Per vertex ``(w, h, tube, m)`` of :func:`part_excess`: the part-scale excess of curvature, turned around where
    the part is tube-like.

    ``w = 1 - c_k``, ``c_k`` going from -1 at shape factor ``rho <= tube`` to 1 at ``rho >= ball``, with ``rho =
    thickness * 2 sqrt(3) H(v_k, tau_max) / edge``: the thickness along the inward normal times the mean curvature
    (VNC-soft's dimensionless H is ``edge / (2 sqrt(3))`` times it on a regular tessellation), 1 on a tube, 2 on a
    ball, more at a tip. ``h = H(v_k, tau_max)``, ``m`` its mean over the vertices, and ``tube = edge / (2 sqrt(3)
    thickness) = h / rho``, the curvature of a tube as thick as the part is at ``v_k``. The excess is ``w max(h - m,
    0)`` (the rule before necks) except where the part is thinner than its curvature at tau_max says (``rho < 1``,
    ``tube > h``: a neck between a limb and the body, whose tau_max also sees the body): there the vertex's
    curvature at its own scale counts as part-scale, up to ``tube``, so that the neck fattens with the limb instead
    of thinning into a stalk (see :func:`part_excess`). ``H_large[row]`` is the scale curve at tau_max; a vertex
    whose inward ray found no surface (``thickness < 0``) keeps Eq. (5) (``w = 0``)."""
    k = wp.tid()
    t = thickness[k]
    h = H_large[row, k]
    w = float(0.0)
    tb = h
    if t > 0.0:
        rho = t * 3.4641016 * h / edge
        w = 1.0 - wp.clamp(2.0 * (rho - tube) / wp.max(ball - tube, 1.0e-6) - 1.0, -1.0, 1.0)
        tb = edge / (3.4641016 * t)
    out[k] = wp.vec4(w, h, tb, mean_large[row])


@wp.kernel(enable_backward=False)
def max_deviation(values: wp.array(dtype=float), ref: wp.array(dtype=float), out: wp.array(dtype=float)):
    """``out[0] = max_k |values[k] - ref[0]|`` (``out`` zeroed first)."""
    k = wp.tid()
    wp.atomic_max(out, 0, wp.abs(values[k] - ref[0]))


@wp.kernel(enable_backward=False)
def deviation_histogram(values: wp.array(dtype=float), ref: wp.array(dtype=float), top: wp.array(dtype=float),
                        counts: wp.array(dtype=wp.int32)):
    """Histogram of ``|values[k] - ref[0]|`` over ``[0, top[0]]`` in ``counts.shape[0]`` equal bins (zeroed first)."""
    k = wp.tid()
    bins = counts.shape[0]
    b = int(float(bins) * wp.abs(values[k] - ref[0]) / wp.max(top[0], 1.0e-30))
    wp.atomic_add(counts, wp.clamp(b, 0, bins - 1), 1)


@wp.kernel(enable_backward=False)
def lerp_positions(a: wp.array(dtype=wp.vec3), b: wp.array(dtype=wp.vec3), theta: float, out: wp.array(dtype=wp.vec3)):
    """Per vertex: ``a + theta (b - a)``: a state on the chord between two states of one stage."""
    k = wp.tid()
    out[k] = a[k] + theta * (b[k] - a[k])
