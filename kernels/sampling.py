"""Warp kernel of batched farthest-point sampling: one block per batch item, one launch for all samples.

Each thread of a block owns the points ``lane, lane + D, lane + 2 D, ...`` (``D`` the block size) and their
distances to the samples taken so far; each step it scans its slice for its farthest point, and one block-wide
reduction picks the farthest of all, ties to the lowest index. On the CPU device a block is one thread that owns
every point (unless Warp's ``config.enable_cpu_blocks`` is on).

The squared distances are float32 ``(dx^2 + dy^2) + dz^2`` with every operation rounded on its own: the module is
compiled without floating-point contraction (``fuse_fp``), since a fused multiply-add rounds once where the torch
ops it replaces round twice, and a last-bit difference flips a near-tie.
"""

import warp as wp

wp.set_module_options({"fuse_fp": False, "enable_backward": False})


@wp.struct
class Candidate:
    """A point and its squared distance to the nearest sample so far."""

    dist: wp.float32
    index: wp.int32


@wp.func
def farther(a: Candidate, b: Candidate) -> Candidate:
    """The candidate with the larger distance, the lower index on equal distances (associative, commutative)."""
    if a.dist > b.dist:
        return a
    if a.dist == b.dist and a.index < b.index:
        return a
    return b


@wp.func
def squared_distance(p: wp.vec3, q: wp.vec3) -> wp.float32:
    """``(dx^2 + dy^2) + dz^2`` in float32, summed in that order."""
    d = p - q
    return (d[0] * d[0] + d[1] * d[1]) + d[2] * d[2]


@wp.kernel
def farthest_point_sample(points: wp.array2d(dtype=wp.vec3), start: wp.array(dtype=wp.int64),
                          dist: wp.array2d(dtype=wp.float32), out: wp.array2d(dtype=wp.int64)):
    """Per batch item ``b`` (launched tiled, ``dim = B``): ``out[b, 0] = start[b]``, then each next sample is the
    point farthest from all samples so far (squared distance, ties to the lowest index); ``dist`` is scratch of
    ``points``' shape, overwritten."""
    b, lane = wp.tid()
    n = points.shape[1]
    step = wp.block_dim()
    cur = wp.int32(start[b])
    if lane == 0:
        out[b, 0] = wp.int64(cur)
    for k in range(lane, n, step):
        dist[b, k] = wp.inf
    for i in range(1, out.shape[1]):
        q = points[b, cur]
        best = Candidate(-1.0, n)
        for k in range(lane, n, step):
            d = wp.min(dist[b, k], squared_distance(points[b, k], q))
            dist[b, k] = d
            if d > best.dist:
                best = Candidate(d, k)
        cur = wp.tile_reduce(farther, wp.tile(best))[0].index
        if lane == 0:
            out[b, i] = wp.int64(cur)
