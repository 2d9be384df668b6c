"""Warp kernels of sums whose result does not depend on thread timing.

On CUDA an ``atomic_add`` of floats adds in the order the threads arrive, so a sum over a mesh differs in its last
bits from run to run, and a flow that branches on it (a remesh's settling test, a rescale) parts from itself. The
kernels here add in a fixed order instead: a first pass of a fixed number of strided partial sums, each added in
index order, then a pass over the partials in order; and per-vertex gathers over a fixed list of incident faces.
"""

import warp as wp


@wp.kernel(enable_backward=False)
def strided_sums_f64(values: wp.array(dtype=wp.float64), partial: wp.array(dtype=wp.float64)):
    """``partial[t] = sum_j values[t + j P]`` (``P = partial.shape[0]``), added in index order."""
    t = wp.tid()
    acc = wp.float64(0.0)
    for k in range(t, values.shape[0], partial.shape[0]):
        acc += values[k]
    partial[t] = acc


@wp.kernel(enable_backward=False)
def strided_sums_vec3d(values: wp.array(dtype=wp.vec3d), partial: wp.array(dtype=wp.vec3d)):
    """``partial[t] = sum_j values[t + j P]`` (``P = partial.shape[0]``), added in index order."""
    t = wp.tid()
    acc = wp.vec3d(wp.float64(0.0))
    for k in range(t, values.shape[0], partial.shape[0]):
        acc += values[k]
    partial[t] = acc


# Threads of :func:`fold_stats` at most: the length of its shared tile, which must be known when it is compiled.
FOLD = wp.constant(64)


# A module of its own: its tile of one value per thread is as long as the block it is compiled for, so in a module
# built for another block size (the other kernels here launch 256 threads a block) it would not fit its shared tile.
@wp.kernel(enable_backward=False, module="unique")
def fold_stats(partial: wp.array2d(dtype=float), parts: int, stats: wp.array(dtype=float)):
    """Add the threads' sums of :func:`kernels.vnc_grid.point_stats` (``partial``, (threads, 2)) into ``stats[7]``
    and ``stats[9]`` in a fixed order, in one block of ``parts <= FOLD`` threads (``launch_tiled``, ``dim=1``,
    ``block_dim=parts``): thread ``t`` adds ``partial[t + j parts]`` in index order, then thread 0 adds the ``parts``
    results in thread order. One launch: the block shares its results through shared memory rather than a second
    pass."""
    _block, t = wp.tid()
    rsum = float(0.0)
    lsum = float(0.0)
    for k in range(t, partial.shape[0], parts):
        rsum += partial[k, 0]
        lsum += partial[k, 1]
    folded = wp.tile_empty(shape=FOLD, dtype=wp.vec2, storage="shared")
    wp.tile_assign(folded, wp.tile(wp.vec2(rsum, lsum), preserve_type=True))
    if t == 0:
        rsum = stats[7]
        lsum = stats[9]
        for k in range(parts):
            s = wp.tile_extract(folded, k)
            rsum += s[0]
            lsum += s[1]
        stats[7] = rsum
        stats[9] = lsum


@wp.kernel(enable_backward=False)
def iota(out: wp.array(dtype=wp.int32)):
    """``out[i] = i``."""
    i = wp.tid()
    out[i] = i


@wp.kernel(enable_backward=False)
def count_corners(tri: wp.array(dtype=wp.int32), counts: wp.array(dtype=wp.int32)):
    """Per corner: count it at its vertex (``counts`` zeroed first; integer atomics add in any order alike)."""
    c = wp.tid()
    wp.atomic_add(counts, tri[c], 1)


@wp.kernel(enable_backward=False)
def gather_vertex_normals(x: wp.array(dtype=wp.vec3), tri: wp.array(dtype=wp.int32), corners: wp.array(dtype=wp.int32),
                          offsets: wp.array(dtype=wp.int32), counts: wp.array(dtype=wp.int32),
                          out: wp.array(dtype=wp.vec3)):
    """Per vertex: the unit sum of the area-weighted normals (cross products) of its faces, added in the order of
    ``corners[offsets[v] : offsets[v] + counts[v]]`` (its corners in ascending index, so its faces in face order);
    zero where the sum is zero."""
    v = wp.tid()
    acc = wp.vec3(0.0)
    for j in range(offsets[v], offsets[v] + counts[v]):
        f = corners[j] // 3
        a = x[tri[3 * f]]
        acc += wp.cross(x[tri[3 * f + 1]] - a, x[tri[3 * f + 2]] - a)
    n = wp.length(acc)
    if n > 0.0:
        acc = acc / n
    out[v] = acc
