"""The grid engine's sums: VNC-soft (Eq. 3), VNC-hard and the integrated measure (Eqs. 1-2), their scale curves and
their adjoints, over the pairs that :mod:`kernels.vnc_grid` finds.

Each kernel evaluates a pair with the terms of :mod:`kernels.vnc_terms` (read :mod:`kernels.vnc_reference` first: it
sums the same pairs one query per thread through a ``wp.Bvh``) and writes partial sums of split ``s`` to row ``s`` of
``(splits, Q)`` arrays that the ``reduce_*`` kernels add up in a fixed order. Choices that change the generated code
are arguments of the kernel factories (``qb`` queries per thread, the culled row walk, the ball kernel's prefilter
and runs), compiled once per combination; every measured choice of which to launch lives in
:class:`vnc_warp.tuning.Tuning`.

Source records are 16-byte ``vec4`` read with one load each (:func:`kernels.vnc_grid.load4`):

* VNC-soft edges: ``pos = (m_j, L_j)``, ``val = (L_j alpha_j delta_j, L_j n_j)`` (:func:`kernels.vnc_grid.pack_soft_sources`);
* ball edges or pieces: ``seg_m = (m_j, a)``, ``seg_h = (d_j, b)`` (the segment ``m_j + u d_j``, ``u`` in ``[-b, a]``),
  ``val = (alpha_j delta_j, n_j)`` (:func:`kernels.vnc_grid.pack_ball_sources`, ``pack_piece_sources``);
* vertices of the VNC-soft edge adjoint: ``pos = (x_k, f_k)``, ``coef = (gN_k, gD_k, 0, 0)``, ``gs = (gS_k, 0)``
  (:func:`pack_vertex_adjoints`).
"""

import functools

import warp as wp

from .vnc_grid import (FAR, box_rows, clamp_ball, load4, row_part, row_share, row_span, row_walk, thread_ball,
                       thread_box, thread_span_box, walk_span, warp_any)
from .vnc_terms import (LN2, adjoint_coefficients, ball_pair_adjoint, chord, curvature_ratio, gaussian_cutoff,
                        gaussian_factor, gaussian_weight, unit)

vec16 = wp.types.vector(length=16, dtype=wp.float32)


@functools.cache
def soft_cells_kernel(qb: int, cull: bool, moving: bool = False, moments: bool = False):
    """The VNC-soft traversal with ``qb`` queries per thread (compiled once per variant): the sums of Eq. (3), and
    with ``moments`` the first moments that the adjoint with respect to the query vertex reads, over the same pairs.

    ``cull``: with one query per thread, each row reads only the cells some ball of the warp reaches
    (:func:`kernels.vnc_grid.walk_span`; on CUDA, where it pays). ``moving``: the grid may have been made for earlier
    positions than the sources' (a plan kept while they move), so the culled walk clamps the balls to its box
    (:func:`kernels.vnc_grid.clamp_ball`).

    Other forms of the pair update were timed on an H200 and dropped (``docs/results/TUNING.md``): coordinates
    scaled per query, a select instead of the cut-off branch, two sources per iteration, the exponent expanded about
    each thread's first query.
    """
    vq = wp.types.vector(length=qb, dtype=wp.float32)
    vq3 = wp.types.vector(length=3 * qb, dtype=wp.float32)

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
        part_v: wp.array2d(dtype=wp.vec3),
        part_t: wp.array2d(dtype=wp.vec3),
    ):
        """VNC-soft, Eq. (3), cut off at ``r = kappa sigma = tau``: partial sums of split ``s`` for the ``qb``
        consecutive sorted queries ``qb u .. qb u + qb - 1`` of thread ``u``: ``(N, D, S)`` into ``part_num``,
        ``part_den``, ``part_v``; with ``moments``, also ``T_c = sum_j w_kj (x_k - m_j) v_jc`` of the five record
        values ``v_j = (L_j alpha_j delta_j, L_j, L_j n_j)`` into rows ``5 s + c`` of ``part_t``
        (:func:`vertex_gradient` turns them into the query's gradient once the upstream gradients are known, so
        the backward pass evaluates no weight of a pair a second time).

        Every source record read (two 16-byte loads) serves ``qb`` queries held in registers. With the Gaussian
        factor ``f`` of each query (:func:`kernels.vnc_terms.gaussian_factor`) the cut-off ``|p - m| <= tau`` is
        ``f |p - m|^2 >= gaussian_cutoff(kappa)`` for every query: a pair costs its offset and square, one multiply
        and one compare, and within the cut-off one ``exp2`` and five multiply-adds (three multiplies and fifteen
        more for the moments). Groups hold ``qb x 32`` queries on CUDA.
        """
        s, u = wp.tid()
        t0 = u * qb
        g = t0 // size
        # one query per thread: the threads past the last query of a group that walks a shared box walk it too
        # (walk_span)
        shared = wp.static(qb == 1) and box_lo[g][0] >= 0
        if t0 >= count and not shared:
            return
        emin = gaussian_cutoff(kappa)
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
                gq[q] = gaussian_factor(r, kappa)
                e = wp.vec3(r + pad)
                tlo = wp.min(tlo, p - e)
                thi = wp.max(thi, p + e)
        lo, hi = thread_span_box(g, tlo, thi, box_lo, box_hi, origin, inv_h, dims)
        ball = thread_ball(tlo, thi, origin, inv_h)
        if wp.static(moving):
            ball = clamp_ball(ball, dims)
        ns = part_v.shape[0]
        an = vq()
        ad = vq()
        ax = vq()
        ay = vq()
        az = vq()
        # the moments: (x, y, z) of value c at 3 q .. 3 q + 2 of tc
        t0m = vq3()
        t1m = vq3()
        t2m = vq3()
        t3m = vq3()
        t4m = vq3()
        nrows = box_rows(lo, hi)
        steps = row_walk(nrows, s, ns)
        held = wp.vec2i(0, 0)
        walked = int(0)
        for row in range(steps[0], nrows, steps[1]):
            whole, held = walk_span(walked, row, steps[1], nrows, shared, held, lo, hi, dims, first,
                                    wp.static(qb == 1 and cull), ball)
            walked += 1
            span = row_share(whole, s, ns, steps[1])
            for i in range(span[0], span[1]):
                ep = load4(pos, i)
                ev = load4(val, i)
                for q in range(qb):
                    dx = px[q] - ep[0]
                    dy = py[q] - ep[1]
                    dz = pz[q] - ep[2]
                    d2 = dx * dx + dy * dy + dz * dz
                    if d2 * gq[q] >= emin:
                        w = gaussian_weight(d2, gq[q])
                        an[q] += w * ev[0]
                        ad[q] += w * ep[3]
                        ax[q] += w * ev[1]
                        ay[q] += w * ev[2]
                        az[q] += w * ev[3]
                        if wp.static(moments):
                            wx = w * dx
                            wy = w * dy
                            wz = w * dz
                            t0m[3 * q] += wx * ev[0]
                            t0m[3 * q + 1] += wy * ev[0]
                            t0m[3 * q + 2] += wz * ev[0]
                            t1m[3 * q] += wx * ep[3]
                            t1m[3 * q + 1] += wy * ep[3]
                            t1m[3 * q + 2] += wz * ep[3]
                            t2m[3 * q] += wx * ev[1]
                            t2m[3 * q + 1] += wy * ev[1]
                            t2m[3 * q + 2] += wz * ev[1]
                            t3m[3 * q] += wx * ev[2]
                            t3m[3 * q + 1] += wy * ev[2]
                            t3m[3 * q + 2] += wz * ev[2]
                            t4m[3 * q] += wx * ev[3]
                            t4m[3 * q + 1] += wy * ev[3]
                            t4m[3 * q + 2] += wz * ev[3]
        for q in range(qb):
            if t0 + q < count:
                part_num[s, t0 + q] = an[q]
                part_den[s, t0 + q] = ad[q]
                part_v[s, t0 + q] = wp.vec3(ax[q], ay[q], az[q])
                if wp.static(moments):
                    part_t[5 * s, t0 + q] = wp.vec3(t0m[3 * q], t0m[3 * q + 1], t0m[3 * q + 2])
                    part_t[5 * s + 1, t0 + q] = wp.vec3(t1m[3 * q], t1m[3 * q + 1], t1m[3 * q + 2])
                    part_t[5 * s + 2, t0 + q] = wp.vec3(t2m[3 * q], t2m[3 * q + 1], t2m[3 * q + 2])
                    part_t[5 * s + 3, t0 + q] = wp.vec3(t3m[3 * q], t3m[3 * q + 1], t3m[3 * q + 2])
                    part_t[5 * s + 4, t0 + q] = wp.vec3(t4m[3 * q], t4m[3 * q + 1], t4m[3 * q + 2])

    return soft_cells


@functools.cache
def ball_cells_kernel(qb: int, cull: bool, prefilter: bool, chunks: bool, chunk: int, min_run: int):
    """The edge/ball traversal of Eqs. (1)-(2) with ``qb`` queries per thread (compiled once per variant).

    The chord is the roots clipped to the segment with no branch on whether its line meets the ball
    (:func:`kernels.vnc_terms.chord`). ``prefilter``: an edge whose midpoint is beyond the radius plus its half
    length skips the chord (on the CPU, where one thread skips it alone). ``chunks``: the records are read in runs
    of at most ``chunk`` sorted records, each tested as a whole against the thread's balls first (from ``min_run``
    records on; :func:`kernels.vnc_grid.chunk_boxes_kernel`): a run beyond every ball is skipped, one inside every
    ball adds its segments' whole lengths with no chord (a segment with both ends in a ball lies in it). The
    threads of a CUDA warp walk the same runs; where some of them need the chords of a run, the others take the
    chords too (:func:`kernels.vnc_grid.warp_any`) rather than a second pass of the warp. ``cull``: as
    :func:`soft_cells_kernel`.
    """
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
        part_num: wp.array2d(dtype=float),
        part_den: wp.array2d(dtype=float),
        part_n: wp.array2d(dtype=wp.vec3),
    ):
        """Exact edge/ball sums of Eqs. (1)-(2), partial sums of split ``s`` (of ``splits``) for the ``qb``
        consecutive sorted queries of thread ``u``, written to row ``s``.

        ``num = sum alpha delta w l``, ``den = sum w l``, ``n = sum w l n_j`` with ``l`` the chord inside the ball
        of radius ``radius[k]`` and ``w = 2^(g[k] |p - m_j|^2)`` (:func:`kernels.vnc_terms.gaussian_weight`;
        ``g = 0``: w = 1). Every record read serves ``qb`` queries.
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
                gl[q] = g[k]
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
                                    wp.static(qb == 1 and cull), ball)
            walked += 1
            span = row_share(whole, s, splits, steps[1])
            i = span[0]
            while i < span[1]:
                j = span[1]
                mode = int(1)  # 0: beyond every ball, 1: the chords, 2: inside every ball
                if wp.static(chunks):
                    c = i // wp.static(chunk)
                    j = wp.min(j, (c + 1) * wp.static(chunk))
                    if j - i >= wp.static(min_run):
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
                    # a warp walks the runs in step: where some of its threads need the chords, those inside
                    # every ball take them too (the same sums) instead of a second, serialized pass
                    if warp_any(int(mode == 1)) != 0 and mode == 2:
                        mode = 1
                if mode == 2:
                    for ii in range(i, j):
                        sm = load4(seg_m, ii)
                        ev = load4(val, ii)
                        L = sm[3] + load4(seg_h, ii)[3]
                        for q in range(qb):
                            cx = sm[0] - px[q]
                            cy = sm[1] - py[q]
                            cz = sm[2] - pz[q]
                            w = L * gaussian_weight(cx * cx + cy * cy + cz * cz, gl[q])
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
                                l_in = chord(cc, cx * sh[0] + cy * sh[1] + cz * sh[2], r2[q], sm[3], sh[3])
                                w = l_in * gaussian_weight(cc, gl[q])
                                an[q] += w * ev[0]
                                ad[q] += w
                                ax[q] += w * ev[1]
                                ay[q] += w * ev[2]
                                az[q] += w * ev[3]
                i = j
        for q in range(qb):
            if t0 + q < count:
                part_num[s, t0 + q] = an[q]
                part_den[s, t0 + q] = ad[q]
                part_n[s, t0 + q] = wp.vec3(ax[q], ay[q], az[q])

    return ball_cells


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
    ``H = N / 2D`` (Eqs. (2), (3); :func:`kernels.vnc_terms.curvature_ratio`) and ``n = S / |S|``."""
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
    H[k] = curvature_ratio(a, b)
    n[k] = unit(c)


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
def add_vec3(src: wp.array(dtype=wp.vec3), dst: wp.array(dtype=wp.vec3)):
    """``dst += src``."""
    i = wp.tid()
    dst[i] = dst[i] + src[i]


@wp.kernel(enable_backward=False)
def reduce_moments(order: wp.array(dtype=int), part_t: wp.array2d(dtype=wp.vec3), moments: wp.array2d(dtype=wp.vec3)):
    """``moments[c, order[t]] = sum_s part_t[5 s + c, t]`` (fixed order): the first moments of
    :func:`soft_cells_kernel` per query vertex, ``c`` in ``0..4``."""
    c, t = wp.tid()
    acc = wp.vec3(0.0)
    for s in range(part_t.shape[0] // 5):
        acc += part_t[5 * s + c, t]
    moments[c, order[t]] = acc


@wp.kernel(enable_backward=False)
def vertex_gradient(
    tau: wp.array(dtype=float),
    kappa: float,
    num: wp.array(dtype=float),
    den: wp.array(dtype=float),
    nsum: wp.array(dtype=wp.vec3),
    moments: wp.array2d(dtype=wp.vec3),
    H_grad: wp.array(dtype=float),
    n_grad: wp.array(dtype=wp.vec3),
    x_grad: wp.array(dtype=wp.vec3),
):
    """The adjoint of VNC-soft (Eq. (3)) with respect to the query vertex ``x_k`` through its own weights:
    ``sum_j dL/dc_kj dw_kj/dx_k L_j = 2 ln2 f_k (gN T_0 + gD T_1 + gS . (T_2, T_3, T_4))`` (``c = w L``; the
    coefficients of :func:`kernels.vnc_terms.adjoint_coefficients`, the moments ``T`` of :func:`soft_cells_kernel`,
    :func:`kernels.vnc_terms.gaussian_gradient`), added to ``x_grad``."""
    k = wp.tid()
    gN, gD, gS = adjoint_coefficients(num[k], den[k], nsum[k], H_grad[k], n_grad[k])
    g = (gN * moments[0, k] + gD * moments[1, k] + gS[0] * moments[2, k] + gS[1] * moments[3, k]
         + gS[2] * moments[4, k])
    x_grad[k] = x_grad[k] + (2.0 * LN2 * gaussian_factor(tau[k], kappa)) * g


@wp.kernel(enable_backward=False)
def pack_soft_state(
    H: wp.array(dtype=float),
    n: wp.array(dtype=wp.vec3),
    num: wp.array(dtype=float),
    den: wp.array(dtype=float),
    nsum: wp.array(dtype=wp.vec3),
    moments: wp.array2d(dtype=wp.vec3),
    out: wp.array2d(dtype=float),
):
    """One row per vertex: ``(H, n, N, D, S)`` (the torch op's outputs and the sums its backward pass reads), then,
    in a row of 24, the 15 moments of :func:`reduce_moments`."""
    k = wp.tid()
    v = n[k]
    s = nsum[k]
    out[k, 0] = H[k]
    out[k, 1] = v[0]
    out[k, 2] = v[1]
    out[k, 3] = v[2]
    out[k, 4] = num[k]
    out[k, 5] = den[k]
    out[k, 6] = s[0]
    out[k, 7] = s[1]
    out[k, 8] = s[2]
    if out.shape[1] > 9:
        for c in range(5):
            m = moments[c, k]
            out[k, 9 + 3 * c] = m[0]
            out[k, 10 + 3 * c] = m[1]
            out[k, 11 + 3 * c] = m[2]


@wp.kernel(enable_backward=False)
def unpack_soft_state(
    state: wp.array2d(dtype=float),
    grads: wp.array2d(dtype=float),
    num: wp.array(dtype=float),
    den: wp.array(dtype=float),
    nsum: wp.array(dtype=wp.vec3),
    moments: wp.array2d(dtype=wp.vec3),
    H_grad: wp.array(dtype=float),
    n_grad: wp.array(dtype=wp.vec3),
):
    """The sums (and in a row of 24 the moments) of a :func:`pack_soft_state` row and the upstream gradients
    ``(dL/dH, dL/dn)`` of a row of 4."""
    k = wp.tid()
    num[k] = state[k, 4]
    den[k] = state[k, 5]
    nsum[k] = wp.vec3(state[k, 6], state[k, 7], state[k, 8])
    if state.shape[1] > 9:
        for c in range(5):
            moments[c, k] = wp.vec3(state[k, 9 + 3 * c], state[k, 10 + 3 * c], state[k, 11 + 3 * c])
    H_grad[k] = grads[k, 0]
    n_grad[k] = wp.vec3(grads[k, 1], grads[k, 2], grads[k, 3])


@wp.kernel(enable_backward=False)
def unpack_grads(grads: wp.array2d(dtype=float), H_grad: wp.array(dtype=float), n_grad: wp.array(dtype=wp.vec3)):
    """The upstream gradients ``(dL/dH, dL/dn)`` of a row of 4."""
    k = wp.tid()
    H_grad[k] = grads[k, 0]
    n_grad[k] = wp.vec3(grads[k, 1], grads[k, 2], grads[k, 3])


@wp.kernel(enable_backward=False)
def gaussian_factors(radius: wp.array(dtype=float), kappa: float, f: wp.array(dtype=float)):
    """``f = gaussian_factor(radius, kappa)`` per query point (zero for ``kappa = 0``: unweighted)."""
    i = wp.tid()
    f[i] = gaussian_factor(radius[i], kappa)


@wp.kernel(enable_backward=False)
def scaled_copy(src: wp.array(dtype=float), s: float, dst: wp.array(dtype=float)):
    """``dst = s * src``."""
    i = wp.tid()
    dst[i] = s * src[i]


# --- adjoints ------------------------------------------------------------------------------------------------------


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
    """Vertices in sorted order as the sources of the VNC-soft edge adjoint: ``pos = (x_k, f_k)``,
    ``coef = (gN_k, gD_k, 0, 0)``, ``gs = (gS_k, 0)`` (:func:`kernels.vnc_terms.adjoint_coefficients`)."""
    i = wp.tid()
    k = order[i]
    p = x[k]
    gN, gD, gS = adjoint_coefficients(num[k], den[k], nsum[k], H_grad[k], n_grad[k])
    pos[i] = wp.vec4(p[0], p[1], p[2], gaussian_factor(tau[k], kappa))
    coef[i] = wp.vec4(gN, gD, 0.0, 0.0)
    gs[i] = wp.vec4(gS[0], gS[1], gS[2], 0.0)


@functools.cache
def soft_edge_adjoint_kernel(qb: int, cull: bool, moving: bool = False, scatter: bool = False):
    """The adjoint of VNC-soft (Eq. (3)) with respect to the edge quantities (compiled once per variant), gathered per
    edge over the vertices whose ball reaches it: the same walk as :func:`soft_cells_kernel`, ``qb`` edges per thread
    (every vertex record read serves them all), ``cull`` and ``moving`` as there. ``scatter``: the pairs also add the
    query vertices' gradient through their weights (what :func:`vertex_gradient` gives from the forward's moments)."""
    vq = wp.types.vector(length=qb, dtype=wp.float32)

    @wp.kernel(enable_backward=False, module="unique", module_options={"fast_math": True})
    def soft_edge_adjoint(
        mid: wp.array(dtype=wp.vec3),
        angle: wp.array(dtype=float),
        enormal: wp.array(dtype=wp.vec3),
        reach: wp.array(dtype=float),
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
        coef: wp.array(dtype=wp.vec4),
        gs: wp.array(dtype=wp.vec4),
        part_a: wp.array2d(dtype=float),
        part_b: wp.array2d(dtype=float),
        part_c: wp.array2d(dtype=wp.vec3),
        part_m: wp.array2d(dtype=wp.vec3),
        length: wp.array(dtype=float),
        vorder: wp.array(dtype=int),
        x_grad: wp.array(dtype=wp.vec3),
    ):
        """Split ``s`` of the sums over the vertices (the sources, each within its own cut-off ``f_k d^2 >=
        gaussian_cutoff``; an edge's ball is the largest radius ``reach[j]`` of them, plus ``pad``) of the ``qb``
        consecutive sorted edges ``j = order[qb u + q]`` of thread ``u``: ``A = sum gN w``, ``B = sum gD w``,
        ``C = sum gS w`` and ``M = sum f w (gN alpha + gD + gS . n_j) (x_k - m_j)``; :func:`reduce_edge_grads` turns
        them into gradients. With ``scatter``, vertex record ``i`` adds
        ``2 ln2 L_j f w (gN alpha + gD + gS . n_j) (x_k - m_j)`` of its pairs to ``x_grad[vorder[i]]``
        (:func:`kernels.vnc_terms.gaussian_gradient`: minus the midpoint's part; one add per record read, its ``qb``
        edges summed first)."""
        s, u = wp.tid()
        t0 = u * qb
        g = t0 // size
        # one edge per thread: the threads past the last edge of a group that walks a shared box walk it too
        # (walk_span)
        shared = wp.static(qb == 1) and box_lo[g][0] >= 0
        if t0 >= count and not shared:
            return
        mx = vq()
        my = vq()
        mz = vq()
        ea = vq()
        lq = vq()
        ux = vq()
        uy = vq()
        uz = vq()
        tlo = wp.vec3(1.0e30)
        thi = wp.vec3(-1.0e30)
        for q in range(qb):
            mx[q] = FAR  # an empty slot: far from every source
            my[q] = FAR
            mz[q] = FAR
            if t0 + q < count:
                j = order[t0 + q]
                m = mid[j]
                n = enormal[j]
                mx[q] = m[0]
                my[q] = m[1]
                mz[q] = m[2]
                ea[q] = angle[j]
                if wp.static(scatter):
                    lq[q] = length[j]
                ux[q] = n[0]
                uy[q] = n[1]
                uz[q] = n[2]
                e = wp.vec3(reach[j] + pad)
                tlo = wp.min(tlo, m - e)
                thi = wp.max(thi, m + e)
        emin = gaussian_cutoff(kappa)
        lo, hi = thread_span_box(g, tlo, thi, box_lo, box_hi, origin, inv_h, dims)
        ball = thread_ball(tlo, thi, origin, inv_h)
        if wp.static(moving):
            ball = clamp_ball(ball, dims)
        ns = part_a.shape[0]
        A = vq()
        B = vq()
        Cx = vq()
        Cy = vq()
        Cz = vq()
        Mx = vq()
        My = vq()
        Mz = vq()
        nrows = box_rows(lo, hi)
        steps = row_walk(nrows, s, ns)
        held = wp.vec2i(0, 0)
        walked = int(0)
        for row in range(steps[0], nrows, steps[1]):
            whole, held = walk_span(walked, row, steps[1], nrows, shared, held, lo, hi, dims, first,
                                    wp.static(qb == 1 and cull), ball)
            walked += 1
            span = row_share(whole, s, ns, steps[1])
            for i in range(span[0], span[1]):
                vp = load4(pos, i)
                gv = wp.vec3(0.0)
                for q in range(qb):
                    dx = vp[0] - mx[q]
                    dy = vp[1] - my[q]
                    dz = vp[2] - mz[q]
                    d2 = dx * dx + dy * dy + dz * dz
                    if d2 * vp[3] >= emin:
                        w = gaussian_weight(d2, vp[3])
                        vc = load4(coef, i)
                        g4 = load4(gs, i)
                        A[q] += vc[0] * w
                        B[q] += vc[1] * w
                        Cx[q] += g4[0] * w
                        Cy[q] += g4[1] * w
                        Cz[q] += g4[2] * w
                        c = vp[3] * w * (vc[0] * ea[q] + vc[1] + g4[0] * ux[q] + g4[1] * uy[q] + g4[2] * uz[q])
                        Mx[q] += c * dx
                        My[q] += c * dy
                        Mz[q] += c * dz
                        if wp.static(scatter):
                            gv += (lq[q] * c) * wp.vec3(dx, dy, dz)
                if wp.static(scatter):
                    if wp.length_sq(gv) > 0.0:
                        wp.atomic_add(x_grad, vorder[i], (2.0 * LN2) * gv)
        for q in range(qb):
            if t0 + q < count:
                part_a[s, t0 + q] = A[q]
                part_b[s, t0 + q] = B[q]
                part_c[s, t0 + q] = wp.vec3(Cx[q], Cy[q], Cz[q])
                part_m[s, t0 + q] = wp.vec3(Mx[q], My[q], Mz[q])

    return soft_edge_adjoint


@wp.kernel(enable_backward=False)
def largest(values: wp.array(dtype=float), out: wp.array(dtype=float)):
    """``out[0] = max(out[0], values)`` (``out`` zeroed first; the values are positive)."""
    i = wp.tid()
    wp.atomic_max(out, 0, values[i])


@wp.kernel(enable_backward=False)
def broadcast(src: wp.array(dtype=float), dst: wp.array(dtype=float)):
    """``dst[i] = src[0]``."""
    i = wp.tid()
    dst[i] = src[0]


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
    """Edge gradients of VNC-soft from the gathered sums of :func:`soft_edge_adjoint_kernel` (``c = w L``):
    ``dalpha += L A``, ``dn += L C``, ``dL += alpha A + B + n . C`` and ``dm += -2 ln2 L M`` (the weight's gradient in
    ``m_j`` is minus its gradient in ``x_k``, :func:`kernels.vnc_terms.gaussian_gradient`)."""
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
    mid_grad[j] = mid_grad[j] - (2.0 * LN2 * L) * M


@wp.kernel(enable_backward=False)
def ball_adjoint_cells(
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
    source_edge: wp.array(dtype=int),
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
    part_gp: wp.array2d(dtype=wp.vec3),
    x_grad: wp.array(dtype=wp.vec3),
    angle_grad: wp.array(dtype=float),
    enormal_grad: wp.array(dtype=wp.vec3),
):
    """The adjoint of the ball sums of Eqs. (1)-(2) over the pairs of a grid traversal (one query per thread, the
    records of the forward, ``source_edge[i]`` the edge of record ``i``): the query's gradient into ``part_gp`` (split
    ``s``), the edges' ends, angles and normals by atomics (:func:`ball_pair_adjoint`)."""
    s, t = wp.tid()
    if t >= count:
        return
    k = order[t]
    grp = t // size
    p = points[k]
    r = radius[k]
    f = g[k]
    gN, gD, gS = adjoint_coefficients(num[k], den[k], nsum[k], H_grad[k], n_grad[k])
    acc = wp.vec3(0.0)
    if gN != 0.0 or gD != 0.0 or wp.length_sq(gS) > 0.0:
        lo, hi = thread_box(grp, p, r + pad, box_lo, box_hi, origin, inv_h, dims)
        nrows = box_rows(lo, hi)
        ns = part_gp.shape[0]
        walk = row_walk(nrows, s, ns)
        for row in range(walk[0], nrows, walk[1]):
            span = row_share(row_span(row, lo, hi, dims, first), s, ns, walk[1])
            for i in range(span[0], span[1]):
                j = source_edge[i]
                if j >= 0:
                    ev = edges[j]
                    gp, ga, gb, g_angle, g_normal = ball_pair_adjoint(
                        p, x[ev[0]], x[ev[1]], seg_m[i][3], seg_h[i][3], length[j], r, f, angle[j], enormal[j], gN,
                        gD, gS)
                    if g_angle != 0.0 or wp.length_sq(gp) > 0.0:
                        acc += gp
                        wp.atomic_add(x_grad, ev[0], ga)
                        wp.atomic_add(x_grad, ev[1], gb)
                        wp.atomic_add(angle_grad, j, g_angle)
                        wp.atomic_add(enormal_grad, j, g_normal)
    part_gp[s, t] = acc


@wp.kernel(enable_backward=False)
def source_edges(order: wp.array(dtype=int), piece_edge: wp.array(dtype=int), out: wp.array(dtype=int)):
    """The edge of each sorted ball record: ``piece_edge[order[i]]`` (-1 for an empty slot); for whole edges pass
    ``order`` itself as ``piece_edge`` of the identity."""
    i = wp.tid()
    out[i] = piece_edge[order[i]]


# --- scale curves ---------------------------------------------------------------------------------------------------


@wp.func
def scale_params(taus: wp.array(dtype=float), offset: int, kappa: float):
    """Squared radii and Gaussian factors (:func:`kernels.vnc_terms.gaussian_factor`) of the (up to) 16 scales
    ``taus[offset:]``; missing scales get radius^2 = -1 (never reached). ``kappa = 0`` gives unweighted scales."""
    r2 = vec16()
    gl = vec16()
    for c in range(16):
        r2[c] = -1.0
        if offset + c < taus.shape[0]:
            tc = taus[offset + c]
            r2[c] = tc * tc
            gl[c] = gaussian_factor(tc, kappa)
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
                        w = gaussian_weight(q, gl[12 + c])
                        an[12 + c] += w * la
                        ad[12 + c] += w * L
                if q <= pm[2]:
                    for c in range(4):
                        if q <= r2[8 + c]:
                            w = gaussian_weight(q, gl[8 + c])
                            an[8 + c] += w * la
                            ad[8 + c] += w * L
                    if q <= pm[1]:
                        for c in range(4):
                            if q <= r2[4 + c]:
                                w = gaussian_weight(q, gl[4 + c])
                                an[4 + c] += w * la
                                ad[4 + c] += w * L
                        if q <= pm[0]:
                            for c in range(4):
                                if q <= r2[0 + c]:
                                    w = gaussian_weight(q, gl[0 + c])
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
            # the chord grows with the radius: a segment whose line misses the largest ball of blocks 0..b (no real
            # root of |m - p + u d|^2 = r^2) misses all of them
            disc0 = ch * ch - cc
            if disc0 + pm[3] > 0.0:
                a = load4(val, i)[0]
                for c in range(4):
                    l_in = chord(cc, ch, r2[12 + c], sm[3], sh[3])
                    if l_in > 0.0:
                        w = l_in * gaussian_weight(cc, gl[12 + c])
                        an[12 + c] += w * a
                        ad[12 + c] += w
                if disc0 + pm[2] > 0.0:
                    for c in range(4):
                        l_in = chord(cc, ch, r2[8 + c], sm[3], sh[3])
                        if l_in > 0.0:
                            w = l_in * gaussian_weight(cc, gl[8 + c])
                            an[8 + c] += w * a
                            ad[8 + c] += w
                    if disc0 + pm[1] > 0.0:
                        for c in range(4):
                            l_in = chord(cc, ch, r2[4 + c], sm[3], sh[3])
                            if l_in > 0.0:
                                w = l_in * gaussian_weight(cc, gl[4 + c])
                                an[4 + c] += w * a
                                ad[4 + c] += w
                        if disc0 + pm[0] > 0.0:
                            for c in range(4):
                                l_in = chord(cc, ch, r2[0 + c], sm[3], sh[3])
                                if l_in > 0.0:
                                    w = l_in * gaussian_weight(cc, gl[0 + c])
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
    """``H[offset + c, order[t]] = N / 2D`` from the split partials of scale ``c``
    (:func:`kernels.vnc_terms.curvature_ratio`)."""
    c, t = wp.tid()
    a = float(0.0)
    b = float(0.0)
    for s in range(part_num.shape[0] // 16):
        a += part_num[16 * s + c, t]
        b += part_den[16 * s + c, t]
    H[offset + c, order[t]] = curvature_ratio(a, b)
