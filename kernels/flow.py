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
    d = lam * (H[k] - H_ref[0])
    m = max_move[k]
    d = wp.clamp(d, -m, m)
    x_out[k] = x_in[k] - d * n[k]
