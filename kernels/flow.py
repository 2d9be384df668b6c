"""Warp kernels of VNC-Flow (paper Sec. 3.2, Eq. 5).

The step reads one state and writes another (never in place), so K steps can be recorded on a
``wp.Tape`` and differentiated with respect to the initial vertices.
"""

import warp as wp


@wp.kernel
def mean_value(values: wp.array(dtype=float), inv_count: float, out: wp.array(dtype=float)):
    """``out[0] += values[k] / V`` (``out`` zeroed first): the global reference of Eq. (5)."""
    k = wp.tid()
    wp.atomic_add(out, 0, values[k] * inv_count)


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


@wp.kernel(enable_backward=False)
def vertex_edge_length(
    x: wp.array(dtype=wp.vec3),
    edges: wp.array(dtype=wp.vec2i),
    total: wp.array(dtype=float),
    count: wp.array(dtype=float),
):
    """Sum and count of incident edge lengths per vertex (``total``/``count`` zeroed first)."""
    j = wp.tid()
    a = edges[j][0]
    b = edges[j][1]
    l = wp.length(x[b] - x[a])
    wp.atomic_add(total, a, l)
    wp.atomic_add(total, b, l)
    wp.atomic_add(count, a, 1.0)
    wp.atomic_add(count, b, 1.0)
