"""Every measured knob of the VNC engine in one frozen value, passed in rather than patched.

The operators run with :data:`DEFAULT`. A benchmark or a test that wants other settings builds a :class:`Tuning` and
passes it (``vw.vnc_soft(mesh, tau, tuning=Tuning(qb=8))``, ``vw.engine(mesh, device, tuning=...)``), as PyTorch3D
passes ``version=``: each tuning gets an engine of its own (its own kernels, plans and graphs), so nothing set for one
call leaks into another. Every setting gives the same sums (the tests check that); only the time differs. Where each
value comes from (the timings, per GPU) is in ``docs/results/TUNING.md``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

__all__ = ["Tuning", "DEFAULT"]


@dataclass(frozen=True)
class Tuning:
    """The engine's knobs; the defaults are those measured best (``docs/results/TUNING.md``).

    Attributes:
        qb: queries per thread of a busy forward traversal on CUDA: each source record a warp reads serves ``qb``
            queries (4 beat 1 from 16 mean edge lengths up, 8 no better).
        block_dim: threads per block of the traversal kernels: a block is freed when its slowest warp ends, and
            warps differ in work (64 was 5-12 % faster than 256 from 16 mean edge lengths up).
        busy_sources: candidates per query from which a traversal is busy (``qb`` queries per thread, more splits):
            one query per thread was faster up to 8 mean edge lengths (~700 candidates), ``qb`` from 16 (~5000).
        light_fill: splits of a light traversal on CUDA, ``light_fill x (resident threads / threads)^(2/3)``: best
            about 10 at 50k vertices, 4 at 200k, 2 at 800k (shorter threads leave a shorter tail).
        splits: how many ways a box's rows are shared; None: by the rule of ``light_fill`` (tests force some).
        group: threads per group of queries sharing a box; None: a warp (32) on CUDA, one thread on the CPU; 32 makes
            the CPU run the CUDA launch shape, fewer than 32 share a warp among groups on CUDA (tests).
        per_thread: queries per thread forced on every device (tests); None: ``qb`` for a busy traversal on CUDA,
            else one.
        emulate_cuda: plan launches on the CPU device as on a CUDA device of this many multiprocessors (groups of
            32 threads, splits and queries per thread by the expected work: tests); 0: off.
        cell_fraction: grid cell size as a fraction of the typical radius: a box of cells overshoots a ball by at
            most half a radius per side.
        cells_per_source: the most cells per source a grid may have (memory O(sources)); 8 and 16 were no better.
        spread: a group whose shared box has this many times the cells of its threads' largest own box walks
            per-thread boxes instead (its balls are far apart).
        fine_bits: Morton bits ordering a cell's records along a curve (3 per axis), so that a run of records is a
            small patch the chunked ball kernel can test as a whole.
        dense_fraction: a dense (all-pairs) traversal when the balls' boxes are expected to cover this fraction of
            the sources anyway.
        cuda_small_pairs: on CUDA a dense traversal below this many query x source pairs, where launches dominate.
        chunk: sorted records per run of the chunked ball kernel (a warp's width).
        min_run: the fewest records a run must hold to be tested as a whole (a shorter run goes straight to chords).
        chunk_reach_cuda: runs of records are tested as a whole from this ball radius on, in mean edge lengths, on
            CUDA (they cost 5-16 % at 6-8 edge lengths and saved a third from 12 on);
        chunk_reach_cpu: the same on the CPU device.
        ball_prefilter: the ball kernel's midpoint prefilter; None: on the CPU only (one thread skips the chord of
            every far edge; on CUDA a warp computes the chords any of its threads needs: 2-7 % slower with it).
        ball_chunks: runs tested as a whole in every ball traversal (True), none (False), or by the rule of
            ``chunk_reach_*`` and dense traversals (None).
        cull: a thread of one query reads only the cells of each row some ball of its warp reaches (CUDA).
        cull_cpu: the same on the CPU device, where it costs more than the candidates it skips (spot at 2 mean
            edge lengths: 20.9 -> 27.4 ms); tests turn it on to cover the culled walk.
        tier_base: edge-length tiers of the multi-scale ball traversal start at this many mean edge lengths and
            double, so that a few long edges do not widen every ball (a single-scale one cuts edges into pieces).
        max_tiers: at most this many tiers (a fourth of a fraction of a percent of the edges still costs a launch).
        tier_grow: the first tier takes every edge when that widens the balls by at most this fraction.
        busy_ball_cell: cell size of a busy ball traversal as a fraction of the reach (longer rows of runs the
            chunked kernel skips: 4-15 % faster than half the reach at 16-32 mean edge lengths).
        piece_min, piece_max: a single-scale ball traversal cuts the edges into pieces of at most
            ``max(piece_min, min(piece_max, r / 2), r / 4)`` mean edge lengths (best: 1.5 at 2 edge lengths, 2 at
            4-8, a quarter of the radius from 16), so half a piece, not half the longest edge, pads the balls.
        cpu_pieces: on the CPU device, the ``(piece, cell)`` sizes in mean edge lengths of the pieces of a mesh's own
            edges kept for every radius (as trimesh keeps an R-tree); None sorts them per call.
        vertex_scatter: device kinds on which VNC-soft's backward pass adds each query vertex's gradient through its
            weights from the edge adjoint's pairs (an add per vertex record a thread reads) rather than from 15
            moments per vertex that the forward pass accumulates (on the CPU, icosphere(4) at 16 mean edge lengths:
            forward with gradients 124 -> 75 ms, edge adjoint 99 -> 125 ms; on one H200 the atomics make the edge
            adjoint 12x slower, 13.5 -> 160 ms on a 50k mesh at diag/2: docs/results/TUNING.md).
        replay: device kinds whose repeated calls replay captured graphs; None follows
            :func:`vnc_warp.set_graph_replay` (CUDA by default: on the CPU kernel time dominates).
        max_graphs: captured graphs (and moving-position plans) an engine keeps, least recently used first out.
        pool_limit: scratch buffers an engine keeps for calls that are not replayed.
        replan_cells: a plan made for earlier positions is made again once their box has moved this many cells
            past the plan's grid (it stays exact; only slower, as boundary cells fill).
        replan_ratio: ... or once the mean radius, or the box's extent along an axis, differs from the plan's by
            more than this factor.
    """

    qb: int = 4
    block_dim: int = 64
    busy_sources: float = 2000.0
    light_fill: float = 3.3
    splits: int | None = None
    group: int | None = None
    per_thread: int | None = None
    emulate_cuda: int = 0
    cell_fraction: float = 0.5
    cells_per_source: int = 4
    spread: float = 8.0
    fine_bits: int = 9
    dense_fraction: float = 0.9
    cuda_small_pairs: int = 1 << 22
    chunk: int = 32
    min_run: int = 8
    chunk_reach_cuda: float = 10.0
    chunk_reach_cpu: float = 6.0
    ball_prefilter: bool | None = None
    ball_chunks: bool | None = None
    cull: bool = True
    cull_cpu: bool = False
    tier_base: float = 1.5
    max_tiers: int = 3
    tier_grow: float = 0.02
    busy_ball_cell: float = 1.0
    piece_min: float = 1.5
    piece_max: float = 2.0
    cpu_pieces: tuple[float, float] | None = (2.0, 3.0)
    vertex_scatter: tuple[str, ...] = ("cpu",)
    replay: tuple[str, ...] | None = None
    max_graphs: int = 8
    pool_limit: int = 128
    replan_cells: float = 1.0
    replan_ratio: float = 1.25

    def __post_init__(self):
        if self.qb < 1 or self.block_dim < 1 or self.chunk < 1 or self.min_run < 1:
            raise ValueError("Tuning: qb, block_dim, chunk and min_run must be positive")
        if self.replay is not None and not set(self.replay) <= {"cuda", "cpu"}:
            raise ValueError(f"Tuning.replay: device kinds are 'cuda' and 'cpu', got {self.replay}")
        if not set(self.vertex_scatter) <= {"cuda", "cpu"}:
            raise ValueError(f"Tuning.vertex_scatter: device kinds are 'cuda' and 'cpu', got {self.vertex_scatter}")
        if self.group is not None and not 1 <= self.group <= 32:
            raise ValueError(f"Tuning.group: 1 to 32 threads, got {self.group}")

    def replace(self, **changes) -> "Tuning":
        """A copy with ``changes`` (``dataclasses.replace``)."""
        return dataclasses.replace(self, **changes)

    def cull_on(self, cuda: bool) -> bool:
        """Whether one-query threads walk culled rows on a device of this kind."""
        return self.cull and (cuda or self.cull_cpu)

    def scatter_on(self, cuda: bool) -> bool:
        """Whether VNC-soft's backward pass adds the query vertices' gradient from the edge adjoint's pairs."""
        return ("cuda" if cuda else "cpu") in self.vertex_scatter

    def chunk_reach(self, cuda: bool) -> float:
        return self.chunk_reach_cuda if cuda else self.chunk_reach_cpu


DEFAULT = Tuning()
