"""Eqs. (4) and (6) of the paper's multi-scale analysis (Sec. 3.1), on VNC-Scale curves ``H[s, k]`` sampled at
ascending scales ``taus[s]``: the global mean curve, VNC-AUC (Eq. 4) and adaptive scales (Eq. 6), each integral by the
trapezoid rule (:func:`auc_step`)."""

import warp as wp


@wp.func
def auc_step(h0: float, h1: float, mean0: float, mean1: float, t0: float, t1: float):
    """One trapezoid of Eq. (4): ``int |H(x) - mean(x)| dx`` over ``[t0, t1]`` from the curve's samples at both ends."""
    return 0.5 * (wp.abs(h0 - mean0) + wp.abs(h1 - mean1)) * (t1 - t0)


@wp.kernel(enable_backward=False)
def column_sums(H: wp.array2d(dtype=float), inv_count: float, partial: wp.array2d(dtype=float)):
    """``partial[s, c] = sum_k H[s, k] / V`` over the columns ``k = c, c + P, ...`` (``P = partial.shape[1]``), added
    in index order: the first pass of the global mean curve of the VNC-Scale curves (:func:`row_sums`)."""
    s, c = wp.tid()
    acc = float(0.0)
    for k in range(c, H.shape[1], partial.shape[1]):
        acc += H[s, k]
    partial[s, c] = acc * inv_count


@wp.kernel(enable_backward=False)
def row_sums(partial: wp.array2d(dtype=float), mean: wp.array(dtype=float)):
    """``mean[s] = sum_c partial[s, c]``, added in index order: unlike an atomic float sum (whose order follows
    thread timing on CUDA) the mean curve, and with it Eqs. (4) and (6), repeats bit for bit."""
    s = wp.tid()
    acc = float(0.0)
    for c in range(partial.shape[1]):
        acc += partial[s, c]
    mean[s] = acc


@wp.kernel(enable_backward=False)
def scale_auc(
    H: wp.array2d(dtype=float),
    mean: wp.array(dtype=float),
    taus: wp.array(dtype=float),
    out: wp.array(dtype=float),
):
    """Eq. (4) at ``tau_max``: trapezoid rule for ``int |H(v_k, x) - mean(x)| dx`` over the sampled scales."""
    k = wp.tid()
    acc = float(0.0)
    for s in range(1, taus.shape[0]):
        acc += auc_step(H[s - 1, k], H[s, k], mean[s - 1], mean[s], taus[s - 1], taus[s])
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
    result = taus[S - 1]
    found = int(0)
    if phi <= 0.0:
        result = taus[0]
        found = 1
    for s in range(1, S):
        inc = auc_step(H[s - 1, k], H[s, k], mean[s - 1], mean[s], taus[s - 1], taus[s])
        if found == 0 and inc > 0.0 and acc + inc >= phi:
            result = taus[s - 1] + (phi - acc) / inc * (taus[s] - taus[s - 1])
            found = 1
        acc += inc
    out[k] = result
