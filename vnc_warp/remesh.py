"""SDF-remesh: the topology regularization of VNC-Flow (paper Sec. 3.2 (3), Algorithm 1 lines 2 and 7).

``sdf_remesh`` returns a clean closed surface of a mesh's signed distance field: watertight, edge- and
vertex-manifold, consistently and outwardly wound, finite, without degenerate faces (the VNC operator's
prerequisites, :func:`validate_surface`), with the face count asked for and the input's surface area. The
zero level set of the signed distance (Warp mesh queries with the winding-number sign, so scans with holes
close) is sampled on a narrow-band grid of spacing ``h``, and one of two surfaces is tessellated:

* **The input's own surface** when it is already that level set: a closed manifold with the face count
  asked for, whose level set at spacing ``h`` has the same Euler characteristic and lies within ``h`` of it
  both ways (nothing to join, split or drop at that resolution). It is re-tessellated in place by an
  isotropic regularization projected back onto itself. This is the path of every stage transition of
  VNC-Flow whose state needs no topology change: no marching cubes surface, no decimation and no host pass
  over the mesh; all of it runs as Warp kernels on the state's device.
* **The marching-cubes surface** of the level set otherwise (the first remesh of a raw input, a face count
  to change, a state whose parts touch, pinch or intersect): marching cubes, connected components,
  quadric decimation (fast-simplification) to the face count, and the same regularization projected onto
  the marching-cubes surface.

A level set that only tears a part thinner than the grid (more handles or pieces on every grid, some solid
thinner than two cells, no gap that narrow, nothing intersecting) does not count as a disagreement: the grid,
not the shape, made the hole (sword.obj's blade: S +3.39 % on an H200 before; see ``_Remesher._disagreement``).

Where detail went (measured with the total VNC-AUC ``S`` of Eq. (4) summed over vertices, 16 scales, at
the input's face count on CPU; see ``docs/flow_balance.md``): remeshing an already remeshed surface through
marching cubes moved ``S`` by -2.2 / -3.7 % (human_man), -2.1 / -1.3 % (bunny), +4.1 / -5.8 % (torus) and
-10.7 % (FAUST 025: marching cubes at spacing ``h`` broke the finger tips off, they were dropped as small
components), up to 2 % more from a face count that was only matched within 2 % (``S`` is a sum over
vertices), all of it compounding over 32 stages. The grid (features below ``h`` are rounded off or break
up), the decimation (it keeps a face-count budget, not the shape) and relaxation projected onto the
marching-cubes surface instead of the true one each took their share. Re-tessellating the surface itself
keeps the vertex count exactly and projects onto the surface itself: ``S`` moves by 0.03-0.2 %.

Why the regularization: VNC-soft (Eq. 3) is a length-weighted mean of dihedral angles, and a dihedral angle
grows with the edge length (about ``L * kappa`` on a surface of curvature ``kappa``), so on a mesh whose edge
lengths vary, H varies with them and Eq. (4) counts that as shape complexity. Quadric decimation is
curvature-adaptive (edge lengths vary by a factor of several): on a remeshed sphere the total VNC-AUC was
4.5x that of an icosphere. The regularization makes the edge lengths nearly uniform (the paper's
"regularizes triangle areas, mitigating VNC-soft/hard discrepancies on irregular tessellations").

Nothing is dropped or changed without a word: every call can return a :class:`RemeshReport` (what was
repaired in the input, which path ran, components dropped and their share of the area, the Euler
characteristic before and after, the area scale, seconds per part); a first remesh at the automatic
resolution that would drop or lose more than 1 % of the surface in parts thinner than the grid is made again on
a finer grid chosen from their thickness (``RemeshReport.grid_refined``), a result that still drops or loses more
than 1 % is refused unless ``allow_changes=True``, and other changes (a new topology, repaired input) are warned
about with a :class:`RemeshWarning`.
"""

from __future__ import annotations

import dataclasses
import os
import time
import warnings
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import warp as wp

from vnc_warp._device import get_device
from vnc_warp._reduce import face_measures, ordered_sum, vertex_normals
from vnc_warp.kernels import remesh as _kr
from vnc_warp.kernels import sdf as _k
from vnc_warp.mesh import EdgeTopology, Mesh, MeshError, framed_mesh, load_mesh
from vnc_warp.sdf import choose_band_factor, inward_distances, sample_grid, sign_flag, surface_samples

__all__ = ["sdf_remesh", "validate_surface", "RemeshReport", "RemeshWarning"]

# Marching-cubes triangles per (area / spacing^2) (2.80-2.95 measured on spot, armadillo and the open
# bunny; skimage's Lewiner MC and Warp's MC give the same count).
_MC_FACES_PER_AREA = 2.83
# Marching cubes aims at this many times the target face count before decimation.
_OVERSAMPLE = 4.0
# ... and a blend's finer grid (_SurfaceBlend) gives it at most this many times: the bridge's grid, twice as fine as
# a remesher's whose spacing the thin parts had already halved (16x), gave 64x (FAUST 025 at 13,772 faces: spacing
# 0.00504, ~880k marching-cubes faces to label and decimate at every trial of a; bridged stages took 15-39 s on an H200
# at 36d1669, human_man's 5-7 s)
_MAX_BLEND_OVERSAMPLE = 16.0
# Grid cells across the thinnest parts kept by the automatic resolution ...
_CELLS_ACROSS_THIN = 2.0
# ... where "thinnest" is this area-weighted percentile of the inward thickness.
_THIN_PERCENTILE = 1.0
_THICKNESS_SAMPLES = 4096
# ... but at most this much finer than the face-count spacing: parts too thin for the target face
# count would only be pinched into non-manifold fins by the decimation.
_MAX_THIN_REFINE = 2.0
# Bounds on the automatic resolution: at least this many nodes along the longest bounding-box side, ...
_MIN_NODES = 32
# ... and at most this many nodes in the whole grid (a 384^3 cube's; 226 MB of float32). A bound on the nodes of the
# grid, not of its longest side: a long thin shape (sword.obj: 0.92 x 0.23 x 0.034, a blade thinner than a 384-node
# cell over half its area) was held to 384 x 98 x 15 nodes, 9 % of the budget, and broke into pieces that held
# fewer faces than it had.
_MAX_GRID_NODES = 384**3
# A face whose 2 * area is below this fraction of its summed squared edge lengths is a sliver; Warp's
# closest-point queries skip such faces, so the next SDF-remesh would not see them either.
_SLIVER = 1.0e-6
_FACE_COUNT_TOLERANCE = 0.02
# Grid values are kept at least this many cells away from zero before marching cubes, so its vertices
# stay off the nodes (distance error 0.1% of a cell) and it emits no zero-area triangles.
_MIN_ABS_SDF = 1.0e-3
# Tried in turn until the output is valid: grids (offset in cells, spacing factor), and for each grid
# fast-simplification aggressiveness values (its default 7 first; lower is slower but collapses more
# carefully, which avoids most pinched edges). Offsets are odd fractions of a cell so that flat,
# axis-aligned faces (CAD parts, a mesh's bounding-box planes) never lie on grid nodes, where the
# SDF is zero and marching cubes emits zero-area triangles.
_GRIDS = (((0.31, 0.17, 0.43), 1.0), ((0.62, 0.84, 0.29), 1.0), ((0.77, 0.53, 0.61), 1.5))
_AGGRESSIVENESS = (7.0, 5.0, 3.0)
# The input's own surface is its level set when both have one Euler characteristic, the level set lies
# within this many cells of the surface (nothing was added: no union of parts that touch or intersect;
# marching cubes cuts sharp corners by up to about half a cell) ...
_AGREE_CELLS = 1.0
# ... and no vertex's point this many cells out along its normal is inside the shape (no part buried in
# another: a self-intersection; sheets merely close together are the level set's business: it joins them
# when its Euler characteristic says so, and a narrow gap it keeps must not send every call down the
# marching-cubes path, as penguin's flipper did at 0.25 cells). Distances the other way are not asked for: the
# surface may reach past its level set at tips thinner than the grid, which marching cubes cuts short (1.8
# cells at human_man's finger tips, 3.2 at FAUST's).
_BURIED_CELLS = 0.02
# A handful of buried vertices (at most this share) is a fold at a bridge thinner than the grid that marching
# cubes itself pinches (penguin's flipper: 2-6 of 3360 after every level-set pass), not a part inside another.
_BURIED_SHARE = 0.003
# Level-set components other than the largest that hold less than this share of its area in all are specks
# off tips thinner than the grid, not a topology change of the surface.
_SPECKS = 1.0e-3
# A level set that shows the surface with more handles or more pieces on both grids (each resolution of ambiguous
# faces), while the surface intersects nothing, is the grid tearing a part thinner than itself when some of the solid
# is thinner than this many cells (no node need fall inside it: a slab thinner than sqrt(3) cells can miss every
# node) and no gap outside it is narrower than this many cells (nothing the level set could have joined): see
# _Remesher._disagreement.
_TEAR_CELLS = 2.0
# At most this many further level-set passes on a level-set result that disagrees with its own level set.
_TOPOLOGY_PASSES = 3
# Input surface farther than this many edge lengths of the result from it counts as lost (a part thinner
# than the grid broke up or vanished; nearer detail is what any tessellation at that face count rounds
# off); a level-set component that is not kept counts as dropped.
_LOST_EDGES = 2.0
# The marching-cubes surface's area is within this share of the input's when nothing broke up (chords
# under a curved surface); beyond it, the kept part is not scaled up to the input's area.
_CHORD_LOSS = 0.05
# Refused unless allow_changes: more than this share of the input's area lost, or of the level set's
# area dropped with its other components.
_MAX_LOST = 0.01
# A first remesh at the automatic resolution that would drop or lose more than that because parts thinner than the
# grid broke up is made again on a finer grid, _CELLS_ACROSS_THIN cells across the missing parts: the input farther
# than this many edge lengths of the result from it (broken-off pieces beside the kept part included), ...
_MISSING_EDGES = 1.0
# ... whose thickness is this area-weighted percentile of theirs (4096 samples, inward rays; at least _MIN_MISSING
# samples, or nothing is measured) ...
_MISSING_PERCENTILE = 90.0
_MIN_MISSING = 8
# ... no finer than this many times the spacing that lost them, nor past the grid's node cap (the missing parts must
# be at least a cell across there, and the spacing at most _MIN_REFINE_STEP of the last one, or it is not tried),
# at most _THIN_RETRIES times. sword.obj at 6,000 faces: spacing 0.00167 dropped 2 pieces of its blade's tip (2.6 %
# of the level set's area) and lost 2.0 % of the input; the missing blade was 0.00132 thick (0.79 cells), and at
# spacing 0.00066 nothing was dropped or lost.
_MAX_RETRY_REFINE = 4.0
_MIN_REFINE_STEP = 0.8
_THIN_RETRIES = 2
# Isotropic regularization (see _HalfEdgeSurface.regularize): edges shorter / longer than these fractions
# of the target length are collapsed / split (the thresholds of Botsch and Kobbelt's isotropic
# remeshing), ...
_SHORT_EDGE = 0.8
_LONG_EDGE = 4.0 / 3.0
# ... a collapse never makes a vertex of more edges than this, ...
_MAX_VALENCE = 10
# ... and no operation turns a face by more than acos(this) (60 degrees), unless the face then agrees
# that well with the normal of the vertices' rings, nor bends an edge to a dihedral angle sharper than
# that unless it already was: no fold-overs.
_MIN_COS_TURN = 0.5
# Features stay: a vertex whose faces' normals spread (|sum n_f| < this * sum |n_f|: a tip, a corner,
# a crease, a part thinner than two edges) is not moved by the relaxation, and an edge whose two faces
# meet at cos < this (a crease) is not flipped. At about 37 degrees, only features sharper than the
# target edge length can resolve are held.
_FEATURE_COS = 0.8
# Collapses need a flatter neighbourhood than a ring this curved (|sum n_f| >= this * sum |n_f| over
# the faces of both ends), so tips are not collapsed away.
_COLLAPSE_FLAT_COS = 0.5
# Bound on the steps of a walk around a vertex; a surface with a busier vertex is not regularized.
_MAX_RING = 64
# An unclaimed vertex (priorities are below 2^30).
_NO_LOCK = 2**31 - 1
# Flips draw their priorities from another stream than relocations.
_FLIP_SEED = 1 << 20
# A regularization that settles runs until one relaxation sweep moves vertices by less than this many edge
# lengths on average (the torus's VNC-AUC then changes by < 0.05 % per 48 further iterations), checked every
# _SETTLE_CHUNK iterations, at most _MAX_SETTLE iterations.
_SETTLED = 1.0e-4
_SETTLE_RATE = 0.85
_SETTLE_CHUNK = 24
_MAX_SETTLE = 2400
# Relaxation moves that fold or crease an edge (neighbours moving at once) are undone; a second pass
# catches the rare edge creased by the first undo.
_REVERT_PASSES = 2
# Problems of an input that the level set repairs (the messages of vnc_warp.mesh.from_arrays).
_REPAIRABLE = ("non-manifold", "degenerate face", "inconsistent winding")
# A regularized result with at most this many sliver faces (and nothing else wrong) has them flipped or collapsed
# away (_repair_slivers); more is a failure of the regularization, reported as such.
_MAX_SLIVER_REPAIRS = 16


class RemeshWarning(UserWarning):
    """:func:`sdf_remesh` repaired its input or changed the surface's topology; the message says what."""


@dataclass
class RemeshReport:
    """What one :func:`sdf_remesh` call did; ``to_dict()`` is what VNC-Flow records per stage.

    Attributes:
        method: ``"surface"`` (the input's own surface, re-tessellated) or ``"level_set"`` (the
            marching-cubes surface).
        spacing: grid spacing ``h`` of the level set (mesh units).
        faces_in, faces, vertices: face count of the input, face and vertex counts of the result.
        euler_in: Euler characteristic V - E + F of the input (None when it is not edge-manifold).
        euler: Euler characteristic of the result (2 - 2 genus).
        components_in: connected components of the input's faces.
        components_level_set: components of the marching-cubes surface (None on the surface path).
        dropped_components: level-set components not kept (all but the largest).
        dropped_area: their share of the level set's area.
        lost_area: share of the input's area farther than 2 h from the result (parts that broke up or
            vanished at spacing ``h``).
        area_scale: linear factor of the final scaling to the kept area (1 = none).
        why_level_set: why the input's own surface was not used (None on the surface path).
        grid_tear: on the surface path, why a level set that showed more handles or pieces than the surface was
            taken for the grid tearing a part thinner than itself (None when the level set agreed).
        grid_refined: on a first remesh at the automatic resolution, why and how the grid was refined: the result at
            the automatic spacing would have dropped or lost more than 1 % of the surface in parts thinner than the
            grid, so it was made again on a finer grid chosen from their thickness (``spacing`` is the grid used;
            None when it was not refined). When no finer grid kept them, ``changes`` says so too.
        topology_passes: further level-set passes until the result agreed with its own level set.
        slivers_repaired: edge flips and collapses that removed sliver faces the regularization left
            (``_repair_slivers``).
        repairs: counts of what was wrong with the input and repaired (``non_manifold_edges``,
            ``non_manifold_vertices``, ``duplicate_faces``, ``degenerate_faces``, ``reoriented_faces``,
            ``boundary_edges``, ``components``); empty for a valid closed input.
        changes: one sentence per repair or change, as warned.
        seconds: wall seconds per part: ``input``, ``sdf``, ``marching_cubes``, ``decimation``,
            ``regularize``, ``checks`` (device work synchronized at each boundary).
    """

    method: str
    spacing: float
    faces_in: int
    faces: int = 0
    vertices: int = 0
    euler_in: int | None = None
    euler: int = 0
    components_in: int = 1
    components_level_set: int | None = None
    dropped_components: int = 0
    dropped_area: float = 0.0
    lost_area: float = 0.0
    area_scale: float = 1.0
    why_level_set: str | None = None
    grid_tear: str | None = None
    grid_refined: str | None = None
    topology_passes: int = 0
    slivers_repaired: int = 0
    repairs: dict = field(default_factory=dict)
    changes: list = field(default_factory=list)
    seconds: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        """The report as JSON-ready builtins."""
        return dataclasses.asdict(self)


class _Clock:
    """Wall seconds per part, with the device synchronized at each boundary so that asynchronous kernel
    launches are charged to the part that issued them."""

    def __init__(self, device, seconds: dict):
        self.device, self.seconds = device, seconds
        wp.synchronize_device(device)
        self.last = time.perf_counter()

    def lap(self, part: str) -> None:
        wp.synchronize_device(self.device)
        now = time.perf_counter()
        self.seconds[part] = self.seconds.get(part, 0.0) + now - self.last
        self.last = now


def _first(idx: np.ndarray, k: int = 5) -> str:
    idx = np.asarray(idx).ravel()
    return ", ".join(str(int(i)) for i in idx[:k]) + (", ..." if idx.size > k else "")


def _pairs(p: np.ndarray, k: int = 3) -> str:
    return "; ".join(f"({int(a)}, {int(b)})" for a, b in p[:k]) + ("; ..." if len(p) > k else "")


def _corner_fans(f: np.ndarray, num_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """Vertex and fan label of every corner (face ``i``, slot ``k`` is corner ``3 i + k``).

    Corners of one vertex are linked across every edge at that vertex that is manifold and
    consistently wound (exactly one half-edge each way); each linked group is one fan. A manifold
    vertex of a closed mesh has exactly one fan (its disk).
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    nc = 3 * f.shape[0]
    a = f.reshape(-1).astype(np.int64)
    b = np.roll(f, -1, axis=1).reshape(-1).astype(np.int64)
    key = a * num_vertices + b
    order = np.argsort(key, kind="stable")
    sorted_key = key[order]
    rev_lo = np.searchsorted(sorted_key, b * num_vertices + a, "left")
    rev_count = np.searchsorted(sorted_key, b * num_vertices + a, "right") - rev_lo
    fwd_count = np.searchsorted(sorted_key, key, "right") - np.searchsorted(sorted_key, key, "left")
    h = np.nonzero((rev_count == 1) & (fwd_count == 1))[0]
    t = order[rev_lo[h]]
    corner = np.arange(nc)
    nxt = 3 * (corner // 3) + (corner + 1) % 3
    # half-edge h = a -> b starts at corner a; its twin t = b -> a starts at b, and next(t) is at a
    rows = np.concatenate([h, nxt[h]])
    cols = np.concatenate([nxt[t], t])
    graph = coo_matrix((np.ones(rows.size, np.int8), (rows, cols)), shape=(nc, nc))
    _, label = connected_components(graph, directed=False)
    return a, label


def _nonmanifold_vertices(f: np.ndarray, num_vertices: int) -> np.ndarray:
    """Vertices whose faces form more than one fan."""
    a, label = _corner_fans(f, num_vertices)
    fans = np.unique(a * f.size + label)
    return np.nonzero(np.bincount(fans // f.size, minlength=num_vertices) > 1)[0]


def _pinched_vertices_closed(f: np.ndarray, num_vertices: int) -> np.ndarray:
    """Vertices whose faces form more than one fan, for a closed surface whose every edge has two faces wound
    opposite ways (as :func:`_nonmanifold_vertices`, without its graph labelling).

    There, turning around a vertex (corner ``c`` to the twin of the half-edge that ends at ``c``) is a
    permutation of the corners whose cycles are the fans. Each corner takes the smallest corner index of its
    cycle by pointer doubling (``log2`` of the largest valence rounds of two gathers); a vertex has as many fans
    as corners that are their own cycle's smallest.
    """
    a = f.reshape(-1).astype(np.int64)
    b = np.roll(f, -1, axis=1).reshape(-1).astype(np.int64)
    key = a * num_vertices + b
    order = np.argsort(key)
    twin = order[np.searchsorted(key[order], b * num_vertices + a)]
    corner = np.arange(a.size)
    turn = twin[3 * (corner // 3) + (corner + 2) % 3]
    label = corner.copy()
    for _ in range(int(np.ceil(np.log2(max(int(np.bincount(a).max()), 2))))):
        label = np.minimum(label, label[turn])
        turn = turn[turn]
    fans = np.bincount(a[label == corner], minlength=num_vertices)
    return np.nonzero(fans > 1)[0]


def _split_fans(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cut non-manifold edges and vertices: one vertex copy per fan.

    Quadric decimation without a link-condition check can flatten a thin part onto a spine edge
    (two sheets through one edge, four faces) or a point. Giving each sheet its own copy of those
    vertices makes every edge two-faced and every vertex one disk; each copy moves 5% of the way to
    its fan's centroid so that the sheets no longer share positions either. A part cut off
    entirely becomes its own component.
    """
    a, label = _corner_fans(f, v.shape[0])
    fan_of_corner = a * f.size + label
    fans, copy = np.unique(fan_of_corner, return_inverse=True)
    copy = copy.reshape(-1)
    origin = fans // f.size
    v2 = v[origin]
    split = np.bincount(origin, minlength=v.shape[0])[origin] > 1
    if split.any():
        f2 = copy.reshape(-1, 3)
        ring = v2[np.roll(f2, 1, axis=1)] + v2[np.roll(f2, -1, axis=1)]
        total = np.stack([np.bincount(copy, ring.reshape(-1, 3)[:, i], minlength=fans.size) for i in range(3)], 1)
        centroid = total / (2.0 * np.bincount(copy, minlength=fans.size)[:, None])
        v2[split] += 0.05 * (centroid[split] - v2[split])
    return v2, copy.reshape(-1, 3)


def surface_problems(vertices: np.ndarray, faces: np.ndarray) -> list[str]:
    """Every reason the surface is not a valid VNC input, as messages; empty when it is valid."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3 or f.shape[0] == 0:
        return [f"expected (V, 3) vertices and non-empty (F, 3) faces, got {v.shape} and {f.shape}"]
    if not np.issubdtype(f.dtype, np.integer):
        return [f"faces must be integer indices, got {f.dtype}"]
    nv = v.shape[0]
    out = np.nonzero((f < 0).any(1) | (f >= nv).any(1))[0]
    if out.size:
        return [f"{out.size} face(s) index vertices outside [0, {nv}), e.g. faces {_first(out)}"]
    f = f.astype(np.int64)
    problems = []
    finite = bool(np.isfinite(v).all())
    if not finite:
        bad = np.nonzero(~np.isfinite(v).all(axis=1))[0]
        problems.append(f"{bad.size} vertex coordinate row(s) are NaN or infinite, e.g. vertices {_first(bad)}")
    rep = np.nonzero((f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 2] == f[:, 0]))[0]
    if rep.size:
        problems.append(f"{rep.size} degenerate face(s) repeat a vertex index, e.g. faces {_first(rep)}")
    if finite:
        e0 = v[f[:, 1]] - v[f[:, 0]]
        e1 = v[f[:, 2]] - v[f[:, 0]]
        e2 = v[f[:, 2]] - v[f[:, 1]]
        area2 = np.linalg.norm(np.cross(e0, e1), axis=1)
        sq = (e0 * e0).sum(1) + (e1 * e1).sum(1) + (e2 * e2).sum(1)
        diag2 = float(((v.max(0) - v.min(0)) ** 2).sum())
        sliver = np.nonzero((area2 <= _SLIVER * sq) | (area2 <= 1e-12 * diag2))[0]
        sliver = np.setdiff1d(sliver, rep)
        if sliver.size:
            problems.append(f"{sliver.size} degenerate face(s) have (near) zero area, e.g. faces {_first(sliver)}")
    a = f.reshape(-1)
    b = np.roll(f, -1, axis=1).reshape(-1)
    undirected, counts = np.unique(np.minimum(a, b) * nv + np.maximum(a, b), return_counts=True)
    edge_problem = False
    many = counts > 2
    if many.any():
        e = undirected[many]
        problems.append(f"non-manifold: {e.size} edge(s) are shared by three or more faces "
                        f"(max {int(counts.max())}), e.g. between vertices {_pairs(np.stack([e // nv, e % nv], 1))}")
        edge_problem = True
    open_ = counts == 1
    if open_.any():
        e = undirected[open_]
        problems.append(f"not watertight: {e.size} boundary edge(s) with a single face, "
                        f"e.g. between vertices {_pairs(np.stack([e // nv, e % nv], 1))}")
        edge_problem = True
    directed, dcounts = np.unique(a * nv + b, return_counts=True)
    same = directed[dcounts > 1]
    if same.size and not many.any():
        problems.append(f"inconsistent orientation: {same.size} edge(s) are traversed in the same direction by "
                        f"both their faces, e.g. {_pairs(np.stack([same // nv, same % nv], 1))}")
        edge_problem = True
    if not edge_problem and not rep.size:
        pinched = _pinched_vertices_closed(f, nv)
        if pinched.size:
            problems.append(f"non-manifold: {pinched.size} vertex(es) join separate fans of faces, "
                            f"e.g. vertices {_first(pinched)}")
        if finite:
            volume = np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum() / 6.0
            if volume <= 0.0:
                problems.append(f"inward orientation: the enclosed volume is {volume:.6g} <= 0 "
                                "(faces wound clockwise seen from outside)")
    return problems


def validate_surface(mesh: Any, *, where: str = "") -> None:
    """Check that a surface is a valid VNC-Flow state; raise naming every problem found.

    Valid means: finite coordinates, no degenerate faces (repeated index, zero area, or slivers that
    Warp's closest-point queries skip), every edge shared by exactly two faces (watertight and
    edge-manifold), one fan of faces around every vertex (vertex-manifold), consistent winding, and
    positive enclosed volume (outward orientation).

    Args:
        mesh: a :class:`~vnc_warp.mesh.Mesh`, a ``trimesh.Trimesh`` or a ``(vertices, faces)`` pair;
            checked as given (nothing merged, flipped or repaired).
        where: prefix for the message, e.g. ``"VNC-Flow stage 7"``.

    Raises:
        MeshError: ``"<where>: <name>: <problem>; <problem> ..."`` with counts and example
            vertices/faces; problems are named "NaN", "degenerate", "non-manifold", "not watertight",
            "inconsistent orientation", "inward orientation".
    """
    if isinstance(mesh, Mesh):
        v, f, name = mesh.vertices, mesh.faces, mesh.name
    elif isinstance(mesh, tuple) and len(mesh) == 2:
        v, f, name = mesh[0], mesh[1], "mesh"
    elif hasattr(mesh, "vertices") and hasattr(mesh, "faces"):
        v, f, name = mesh.vertices, mesh.faces, type(mesh).__name__
    else:
        raise TypeError(f"validate_surface: expected a Mesh, trimesh.Trimesh or (vertices, faces), "
                        f"got {type(mesh).__name__}")
    problems = surface_problems(v, f)
    if problems:
        prefix = f"{where}: " if where else ""
        raise MeshError(f"{prefix}{name}: " + "; ".join(problems))


@dataclass
class _Source:
    """An input as the level set sees it: positions, triangles and what was repaired on the way.

    ``mesh`` is set when the input is a valid closed surface (:func:`validate_surface`); ``euler`` is
    None unless the input is edge-manifold (then ``V - E + F``), ``loops`` its boundary loops.
    """

    v: np.ndarray
    f: np.ndarray
    name: str
    mesh: Mesh | None
    repairs: dict
    euler: int | None
    loops: int
    components: int


def _raw_arrays(source: Any) -> tuple[np.ndarray, np.ndarray, str]:
    """Positions and triangles of ``source`` as stored, with no checks beyond shapes."""
    import trimesh

    if isinstance(source, Mesh):
        return source.vertices.astype(np.float64), source.faces.astype(np.int64), source.name
    if isinstance(source, tuple) and len(source) == 2:
        return np.asarray(source[0], np.float64), np.asarray(source[1], np.int64), "mesh"
    if isinstance(source, trimesh.Trimesh):
        return np.asarray(source.vertices, np.float64), np.asarray(source.faces, np.int64), "trimesh"
    path = os.fspath(source)
    tm = trimesh.load(path, process=False, force="mesh")
    return np.asarray(tm.vertices, np.float64), np.asarray(tm.faces, np.int64), os.path.basename(path)


def _face_components(f: np.ndarray, num_vertices: int) -> np.ndarray:
    """Connected-component label of every face (faces sharing a vertex are connected)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    rows = f.reshape(-1)
    cols = np.roll(f, -1, axis=1).reshape(-1)
    _, label = connected_components(coo_matrix((np.ones(rows.size, np.int8), (rows, cols)),
                                               shape=(num_vertices, num_vertices)), directed=False)
    return label[f[:, 0]]


def _topology_counts(v: np.ndarray, f: np.ndarray, topology: EdgeTopology | None = None
                     ) -> tuple[int | None, int, int, int, int]:
    """Euler characteristic (None unless edge-manifold), boundary loops, non-manifold edges, inconsistently
    wound edges and components of a triangle soup (of a loaded mesh, given its ``topology``: no edge pass)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    nv = v.shape[0]
    if topology is not None:
        # a loaded Mesh: load_mesh refused non-manifold edges and inconsistent winding, and its edges are counted
        many = inconsistent = 0
        boundary = topology.boundary[:, 0].astype(np.int64) * nv + topology.boundary[:, 1]
        num_edges = topology.edges.shape[0]
    else:
        a = f.reshape(-1)
        b = np.roll(f, -1, axis=1).reshape(-1)
        undirected, counts = np.unique(np.minimum(a, b) * nv + np.maximum(a, b), return_counts=True)
        many = int(np.count_nonzero(counts > 2))
        _, dcounts = np.unique(a * nv + b, return_counts=True)
        inconsistent = int(np.count_nonzero(dcounts > 1))
        boundary = undirected[counts == 1]
        num_edges = undirected.size
    loops = 0
    if boundary.size:
        ends = np.stack([boundary // nv, boundary % nv])
        used, compact = np.unique(ends, return_inverse=True)
        compact = compact.reshape(2, -1)
        graph = coo_matrix((np.ones(boundary.size, np.int8), (compact[0], compact[1])), shape=(used.size,) * 2)
        loops = int(connected_components(graph, directed=False)[0])
    euler = None if many else int(np.unique(f).size - num_edges + f.shape[0])
    components = int(np.unique(_face_components(f, nv)).size)
    return euler, loops, many, inconsistent, components


def _read_source(source: Any) -> _Source:
    """The input, repaired where the level set can repair it, with a record of what was repaired.

    A valid input is used as it is. One that :func:`~vnc_warp.mesh.load_mesh` refuses for a reason the
    level set removes (non-manifold edges or vertices, duplicate or degenerate faces, inconsistent winding)
    is read as stored instead: degenerate faces are dropped, duplicated faces kept once (both dropped
    where a pair is wound both ways: a double-sided sheet encloses nothing), inconsistent winding fixed
    where the faces allow (trimesh), and the rest left to the winding-number sign. Anything else
    (NaN, empty, bad indices, unreadable files) raises as ``load_mesh`` does.
    """
    import trimesh

    try:
        mesh = load_mesh(source)
    except MeshError as exc:
        if not any(key in str(exc) for key in _REPAIRABLE):
            raise
        mesh = None
    if mesh is not None:
        euler, loops, _, _, components = _topology_counts(mesh.vertices, mesh.faces, mesh.topology)
        valid = mesh.is_watertight and not surface_problems(mesh.vertices, mesh.faces)
        return _Source(mesh.vertices.astype(np.float64), mesh.faces.astype(np.int64), mesh.name,
                       mesh if valid else None, {"components": components} if components > 1 else {},
                       euler, loops, components)
    v, f, name = _raw_arrays(source)
    # merged by position as load_mesh does, so texture seams do not read as boundaries
    v, inv = np.unique(v, axis=0, return_inverse=True)
    f = inv.reshape(-1)[f]
    repairs = {}
    scale = float(np.linalg.norm(v.max(0) - v.min(0)))
    area2 = np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    degenerate = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 2] == f[:, 0]) | (area2 <= 1e-12 * scale**2)
    if degenerate.any():
        repairs["degenerate_faces"] = int(degenerate.sum())
        f = f[~degenerate]
    key = np.sort(f, axis=1)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    if first.size < f.shape[0]:
        # a face is wound "even" when the vertex after its smallest one is the middle one
        lowest = np.argmin(f, axis=1)
        even = f[np.arange(f.shape[0]), (lowest + 1) % 3] == key[:, 1]
        mixed = np.zeros(first.size, dtype=bool)
        np.logical_or.at(mixed, inverse, even != even[first[inverse]])
        keep = (np.arange(f.shape[0]) == first[inverse]) & ~mixed[inverse]
        repairs["duplicate_faces"] = int(f.shape[0] - keep.sum())
        f = f[keep]
    euler, loops, many, inconsistent, components = _topology_counts(v, f)
    if many:
        repairs["non_manifold_edges"] = many
    if inconsistent and not many:
        tm = trimesh.Trimesh(v, f, process=False)
        trimesh.repair.fix_winding(tm)
        repairs["reoriented_faces"] = int(np.count_nonzero((np.asarray(tm.faces) != f).any(axis=1)))
        f = np.asarray(tm.faces, np.int64)
        euler, loops, many, inconsistent, components = _topology_counts(v, f)
    pinched = _nonmanifold_vertices(f, v.shape[0]) if not many and not inconsistent else np.zeros(0)
    if pinched.size:
        repairs["non_manifold_vertices"] = int(pinched.size)
        euler = None
    if components > 1:
        repairs["components"] = components
    used = np.unique(f)
    remap = np.zeros(v.shape[0], dtype=np.int64)
    remap[used] = np.arange(used.size)
    return _Source(v[used], remap[f], name, None, repairs, euler, loops, components)


def finest_spacing(extent: np.ndarray) -> float:
    """Smallest grid spacing (mesh units) at which a bounding box of ``extent`` (3,) spans at most ``_MAX_GRID_NODES``
    nodes (``side / 383`` for a cube: the cap when it was 384 nodes along the longest side)."""
    extent = np.maximum(np.asarray(extent, np.float64), 0.0)

    def nodes(h: float) -> float:
        return float(np.prod(extent / h + 1.0))

    lo, hi = float(extent.max()) / (_MAX_GRID_NODES - 1), float(extent.max())
    for _ in range(60):  # bisection in log scale: the count falls as h grows
        mid = float(np.sqrt(lo * hi))
        lo, hi = (mid, hi) if nodes(mid) > _MAX_GRID_NODES else (lo, mid)
    return hi


def auto_spacing(area: float, extent: np.ndarray, target: int, wm: wp.Mesh, x: wp.array, tri: wp.array) -> float:
    """Grid spacing of the automatic resolution (mesh units); see :func:`sdf_remesh`.

    Args:
        area: surface area of the input.
        extent: (3,) sides of its bounding box.
        target: face count asked for.
        wm: ``wp.Mesh`` of the input, its faces wound outward.
        x, tri: its (V,) vec3 positions and (3F,) int32 corners on ``wm``'s device.
    """
    side = float(np.max(extent))
    h_faces = np.sqrt(_MC_FACES_PER_AREA * area / (_OVERSAMPLE * target))
    hits = inward_distances(wm, x, tri, _THICKNESS_SAMPLES, span=np.sqrt(3.0) * side)
    hits = hits[hits > 0.0]
    thin = float(np.percentile(hits, _THIN_PERCENTILE)) if hits.size >= 16 else np.sqrt(3.0) * side
    h = max(min(h_faces, thin / _CELLS_ACROSS_THIN), h_faces / _MAX_THIN_REFINE)
    return float(np.clip(h, finest_spacing(extent), side / (_MIN_NODES - 1)))


@dataclass
class _LevelSet:
    """A marching-cubes surface on the device: (V,) vec3 ``points``, (3F,) int32 ``indices``; its host copy and
    component labels are made once, when first asked for (the agreement check and the level-set path both
    read them).

    Marching cubes resolves a cube face whose diagonal corners have equal signs (inside on one diagonal, outside on
    the other) one of two ways: the inside corners apart, or joined. Warp's table (the CUDA default) keeps them
    apart, scikit-image's (Lewiner, the CPU default) decides per face, so a part or gap about one cell across
    comes out differently: boot.obj's laces (Euler characteristic -22) gave -14 from Warp and -24 from scikit-image
    on one grid, and the CUDA remesh lost 4 handles and 5.3 % of ``S`` where the CPU one lost none. This surface is
    the grid's marching cubes with ``method``; :meth:`joined` is the other resolution, the marching cubes of the
    negated grid (whose apart-resolution joins the inside), wound back outward.
    """

    points: wp.array
    indices: wp.array
    grid: wp.array | None = field(default=None, repr=False)
    origin: np.ndarray | None = field(default=None, repr=False)
    spacing: float = 0.0
    method: str = "warp"
    negated: bool = False
    _host: tuple | None = field(default=None, repr=False)
    _labels: tuple | None = field(default=None, repr=False)
    _other: _LevelSet | None = field(default=None, repr=False)

    @property
    def num_faces(self) -> int:
        return self.indices.shape[0] // 3

    @property
    def euler(self) -> int:
        """V - E + F of the closed surface marching cubes makes (E = 3F / 2)."""
        return self.points.shape[0] - self.num_faces // 2

    def host(self) -> tuple[np.ndarray, np.ndarray]:
        """(V, 3) float64 positions and (F, 3) int64 triangles (shared: not to be modified)."""
        if self._host is None:
            self._host = (self.points.numpy().astype(np.float64), self.indices.numpy().reshape(-1, 3).astype(np.int64))
        return self._host

    def components(self) -> tuple[np.ndarray, np.ndarray]:
        """Per face its component label, and per component its area (:func:`_components`)."""
        if self._labels is None:
            self._labels = _components(*self.host())
        return self._labels

    def mesh(self) -> wp.Mesh:
        return wp.Mesh(points=self.points, indices=self.indices)

    def joined(self) -> _LevelSet:
        """The same grid's level set with every ambiguous face resolved the other way (made once)."""
        if self._other is None:
            if self.grid is None:
                return self
            negated = wp.empty_like(self.grid)
            wp.launch(_k.negate_grid, dim=self.grid.shape, inputs=[self.grid], outputs=[negated],
                      device=self.grid.device)
            self._other = _extract(negated, self.origin, self.spacing, self.method, not self.negated)
            self._other._other = self
        return self._other

    def resolutions(self) -> tuple[_LevelSet, ...]:
        """This level set and, on a grid that has one, its other resolution of ambiguous faces."""
        return (self,) if self.grid is None else (self, self.joined())

    def nearest(self, euler: int | None) -> _LevelSet:
        """Of the two resolutions, the one whose topology is ``euler``'s or nearest to it (this one on a tie, or
        when ``euler`` is None)."""
        if euler is None or self.grid is None or _same_topology(self, euler):
            return self
        other = self.joined()
        if _same_topology(other, euler) or (other.num_faces and abs(other.euler - euler) < abs(self.euler - euler)):
            return other
        return self


def _extract(grid: wp.array, origin: np.ndarray, h: float, method: str, negated: bool) -> _LevelSet:
    """Marching cubes of ``grid`` (node ``(i, j, k)`` at ``origin + h (i, j, k)``), wound outward (a ``negated``
    grid is positive inside)."""
    device = grid.device
    shape = grid.shape
    if method == "warp":
        import warp.geometry

        upper = origin + h * (np.asarray(shape) - 1)
        points, indices = warp.geometry.IsoSurfaceMarchingCubes.extract(
            grid, 0.0, lower=wp.vec3(*origin), upper=wp.vec3(*upper))
        if negated and indices.shape[0]:
            flipped = wp.empty_like(indices)
            wp.launch(_k.reverse_triangles, dim=indices.shape[0] // 3, inputs=[indices], outputs=[flipped],
                      device=device)
            indices = flipped
    else:
        from skimage.measure import marching_cubes

        values = grid.numpy()
        if not values.min() < 0.0 < values.max():  # no node inside: every part is thinner than the grid
            return _LevelSet(wp.empty(0, dtype=wp.vec3, device=device), wp.empty(0, dtype=wp.int32, device=device))
        verts, tris, _, _ = marching_cubes(values, 0.0, spacing=(h,) * 3)
        if negated:
            tris = tris[:, ::-1]
        points = wp.array(verts.astype(np.float64) + origin, dtype=wp.vec3, device=device)
        indices = wp.array(np.ascontiguousarray(tris, dtype=np.int32).reshape(-1), dtype=wp.int32, device=device)
    return _LevelSet(points, indices, grid, origin, h, method, negated)


def _level_set(wm: wp.Mesh, lo: np.ndarray, hi: np.ndarray, h: float, shift, area: float, use_winding: int,
               method: str, clock: _Clock) -> _LevelSet:
    """Zero level set of ``wm``'s signed distance on a grid of spacing ``h`` covering ``[lo, hi]``."""
    device = clock.device
    origin = lo - (2.0 - np.asarray(shift)) * h
    shape = tuple(int(n) for n in np.ceil((hi - origin) / h).astype(int) + 3)
    grid = sample_grid(wm, origin, h, shape, band_factor=choose_band_factor(shape, area, h),
                       use_winding=use_winding, device=device)
    wp.launch(_k.push_off_zero, dim=shape, inputs=[grid, _MIN_ABS_SDF * h], device=device)
    clock.lap("sdf")
    ls = _extract(grid, origin, h, method, False)
    clock.lap("marching_cubes")
    return ls


def _farthest(wm: wp.Mesh, points: wp.array, cap: float) -> float:
    """Largest distance from ``points`` to ``wm`` (at most ``cap``)."""
    out = wp.zeros(1, dtype=wp.float32, device=points.device)
    if points.shape[0]:
        wp.launch(_k.farthest_distance, dim=points.shape[0], inputs=[wm.id, points, float(cap)], outputs=[out],
                  device=points.device)
    return float(out.numpy()[0])


def _main_topology(ls: _LevelSet) -> tuple[int, float]:
    """Euler characteristic of a non-empty level set's largest component, and the share of its area in the others."""
    v, f = ls.host()
    label, area = ls.components()
    main = label == np.argmax(area)
    used = np.zeros(v.shape[0], dtype=bool)
    used[f[main].reshape(-1)] = True
    return int(np.count_nonzero(used)) - int(main.sum()) // 2, float(1.0 - area.max() / area.sum())


def _same_topology(ls: _LevelSet, euler: int) -> bool:
    """Whether a level set has the Euler characteristic ``euler``: it has, or its largest component has and the others
    are specks (less than ``_SPECKS`` of the area in all) that marching cubes samples off a tip thinner than the grid."""
    if not ls.num_faces:
        return False
    if ls.euler == euler:
        return True
    main, others = _main_topology(ls)
    return main == euler and others <= _SPECKS


def _torn(ls: _LevelSet, euler: int) -> bool:
    """Whether a level set shows a surface of Euler characteristic ``euler`` torn or broken up and nothing closed: its
    largest component has more handles (a hole punched through a sheet: Euler characteristic below ``euler``), or
    the same and other pieces beside it that are more than specks (a sheet broken into fragments). A handle that
    closed raises the largest component's Euler characteristic (a torus whose tube is thinner than the grid breaks
    into a ball: 2 around 0), which is no tear."""
    if not ls.num_faces:
        return False
    main, others = _main_topology(ls)
    return main < euler or (main == euler and others > _SPECKS)


def _thinnest_and_narrowest(wm: wp.Mesh, span: float) -> tuple[float, float]:
    """Thinnest solid and narrowest gap of the closed surface ``wm`` (mesh units): the shortest distances to the next
    surface hit along the inward and the outward face normals from ``_THICKNESS_SAMPLES`` area-weighted points
    (``inf`` where no ray hit). ``span`` is the longest distance looked for (the bounding-box diagonal)."""
    x, tri = wm.points, wm.indices
    points, normals = surface_samples(x, tri, _THICKNESS_SAMPLES, seed=0)
    outward = wp.array(-normals.numpy(), dtype=wp.vec3, device=x.device)
    out = []
    for n in (normals, outward):
        d = wp.empty(points.shape[0], dtype=wp.float32, device=x.device)
        wp.launch(_k.inward_thickness, dim=points.shape[0], inputs=[wm.id, points, n, 1e-5 * span, 2.0 * span],
                  outputs=[d], device=x.device)
        d = d.numpy()
        out.append(float(d[d > 0.0].min()) if (d > 0.0).any() else float("inf"))
    return out[0], out[1]


def _grid_allows(ls: _LevelSet, euler: int) -> bool:
    """Whether the grid of ``ls`` is consistent with a surface of Euler characteristic ``euler``: a resolution of its
    ambiguous faces (:class:`_LevelSet`) has that topology (:func:`_same_topology`), or ``euler`` lies between the
    two: the two resolutions are the extremes this grid shows for necks and gaps about one cell across (boot's laces:
    -14 and -28 around the surface's -22), a surface between them has its topology at some resolution of them, and
    a neck narrowed below the grid or parts that met change both. The bound is measured, not proved: on a torus whose
    tube is one cell across both resolutions broke the ring (2 and 34 around 0), which is then a real change."""
    sides = ls.resolutions()
    if any(_same_topology(r, euler) for r in sides):
        return True
    if len(sides) < 2 or not all(r.num_faces for r in sides):
        return False
    low, high = sorted(r.euler for r in sides)
    return low <= euler <= high


def _far_samples(x: wp.array, tri: wp.array, result: wp.Mesh, distance: float) -> tuple[wp.array, wp.array, np.ndarray]:
    """A surface's 4096 area-weighted samples, their normals, and which lie outside ``result`` (a ``wp.Mesh`` with
    winding numbers) and farther than ``distance`` from it."""
    points, normals = surface_samples(x, tri, _THICKNESS_SAMPLES, seed=1)
    d = wp.empty(points.shape[0], dtype=wp.float32, device=x.device)
    wp.launch(_k.signed_distance_points, dim=points.shape[0], inputs=[result.id, points, 2.0 * float(distance), 1],
              outputs=[d], device=x.device)
    return points, normals, d.numpy() > distance


def _lost_share(x: wp.array, tri: wp.array, result: wp.Mesh, distance: float) -> float:
    """Share of a surface's area (4096 area-weighted samples) outside ``result`` (a ``wp.Mesh`` with winding
    numbers) and farther than ``distance`` from it: parts that vanished. Input surface inside the result (the
    faces where overlapping components met) is not lost."""
    return float(np.mean(_far_samples(x, tri, result, distance)[2]))


def _unfaithful(report: RemeshReport) -> bool:
    """Whether a result drops or loses more of the surface than a new input may lose (``_MAX_LOST``)."""
    return report.dropped_area > _MAX_LOST or report.lost_area > _MAX_LOST


def _loss_text(report: RemeshReport) -> str:
    return (f"dropped {report.dropped_components} level-set component(s) ({100 * report.dropped_area:.1f} % of its "
            f"area), {100 * report.lost_area:.1f} % of the input's area lost")


def _missing_thickness(x: wp.array, tri: wp.array, wm: wp.Mesh, result: wp.Mesh, distance: float,
                       span: float) -> tuple[float, float]:
    """Share of a closed surface's area (the 4096 area-weighted samples of :func:`_lost_share`) outside ``result`` (a
    ``wp.Mesh`` with winding numbers) and farther than ``distance`` from it, and the ``_MISSING_PERCENTILE``-th
    percentile of the surface's thickness there (inward rays through ``wm``, the surface's own ``wp.Mesh``; 0 when
    fewer than ``_MIN_MISSING`` samples are missing or no ray hit). ``span``: the bounding-box diagonal."""
    points, normals, far = _far_samples(x, tri, result, distance)
    if np.count_nonzero(far) < _MIN_MISSING:
        return float(np.mean(far)), 0.0
    t = wp.empty(points.shape[0], dtype=wp.float32, device=x.device)
    wp.launch(_k.inward_thickness, dim=points.shape[0], inputs=[wm.id, points, normals, 1e-5 * span, 2.0 * span],
              outputs=[t], device=x.device)
    t = t.numpy()[far]
    t = t[t > 0.0]
    return float(np.mean(far)), (float(np.percentile(t, _MISSING_PERCENTILE)) if t.size >= _MIN_MISSING else 0.0)


@dataclass
class _Given:
    """A new input as one remesh attempt used it (relative to the remesher's origin): its source, (V,) vec3 positions,
    (3F,) corners, ``wp.Mesh``, bounds and area, so that a finer attempt and its measures need not build them again."""

    src: Any
    x: wp.array
    tri: wp.array
    wm: wp.Mesh
    lo: np.ndarray
    hi: np.ndarray
    area: float


def _device_bounds(x: wp.array) -> tuple[np.ndarray, np.ndarray]:
    lo = wp.array(np.full(3, np.inf, np.float32), dtype=wp.float32, device=x.device)
    hi = wp.array(np.full(3, -np.inf, np.float32), dtype=wp.float32, device=x.device)
    wp.launch(_k.bounds, dim=x.shape[0], inputs=[x], outputs=[lo, hi], device=x.device)
    return lo.numpy().astype(np.float64), hi.numpy().astype(np.float64)


def _components(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per face its component label, and per component its area."""
    label = _face_components(f, v.shape[0])
    area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    return label, np.bincount(label, weights=area)


def _keep_faces(v: np.ndarray, f: np.ndarray, keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The faces ``f[keep]`` with their vertices renumbered."""
    f = f[keep]
    # a mask, not np.unique: the same vertices in the same order, without a sort of every corner (9x faster on a
    # 200k-face marching-cubes surface)
    used = np.zeros(v.shape[0], dtype=bool)
    used[f.reshape(-1)] = True
    return v[used], (np.cumsum(used) - 1)[f]


def _largest_component(v: np.ndarray, f: np.ndarray):
    """The connected component with the most area, its vertices renumbered."""
    label, area = _components(v, f)
    if not f.shape[0]:
        return v, f
    return _keep_faces(v, f, label == np.argmax(area))


def _drop_double_faces(f: np.ndarray) -> np.ndarray:
    """Faces without the groups that share one vertex triple.

    Quadric decimation can flatten a part thinner than its budget allows (a finger, a tube) into a
    double-sided triangle: two faces on the same three vertices, which make their edges four-faced.
    Without both, the part keeps a three-vertex waist and every edge has two faces again.
    """
    s = np.sort(f, axis=1).astype(np.int64)
    n = int(f.max()) + 1 if f.size else 1
    if n < 2**21:  # one int64 key per vertex triple: a 1-D unique, not a (slower) row-wise one
        _, inverse, counts = np.unique((s[:, 0] * n + s[:, 1]) * n + s[:, 2], return_inverse=True,
                                       return_counts=True)
    else:
        _, inverse, counts = np.unique(s, axis=0, return_inverse=True, return_counts=True)
    return f[counts[inverse.reshape(-1)] == 1]


def _area_and_centroid(v: np.ndarray, f: np.ndarray) -> tuple[float, np.ndarray]:
    """Surface area and area-weighted centroid (3,)."""
    area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    return float(area.sum()), (area[:, None] * v[f].mean(1)).sum(0) / area.sum()


def _sliver_mask(v: np.ndarray, f: np.ndarray, tiny: float) -> np.ndarray:
    """Per face whether it is a sliver by the device check's rule (``kernels.remesh.face_measures``)."""
    e0, e1, e2 = v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 1]]
    area2 = np.linalg.norm(np.cross(e0, e1), axis=1)
    sq = (e0 * e0).sum(1) + (e1 * e1).sum(1) + (e2 * e2).sum(1)
    return (area2 <= _SLIVER * sq) | (area2 <= tiny)


def _turns_ok(v: np.ndarray, old: np.ndarray, new: np.ndarray, tiny: float) -> bool:
    """Whether the faces ``new`` (K, 3) are no slivers and each turns by at most ``acos(_MIN_COS_TURN)`` from
    the normal of the faces ``old`` (summed: the patch they replace)."""
    ref = np.cross(v[old[:, 1]] - v[old[:, 0]], v[old[:, 2]] - v[old[:, 0]]).sum(0)
    n = np.cross(v[new[:, 1]] - v[new[:, 0]], v[new[:, 2]] - v[new[:, 0]])
    cos = n @ ref / np.maximum(np.linalg.norm(n, axis=1) * np.linalg.norm(ref), 1e-300)
    return not _sliver_mask(v, new, tiny).any() and bool((cos >= _MIN_COS_TURN).all())


def _repair_slivers(v: np.ndarray, f: np.ndarray, tiny: float) -> tuple[np.ndarray, np.ndarray, int] | None:
    """A closed manifold surface without its sliver faces (``_sliver_mask``), or None when one cannot be removed.

    A sliver is a cap (a corner on the opposite edge: the edge is flipped, joining the corner to the vertex across
    it) or a needle (a corner at another: the face's shortest edge is collapsed into its midpoint, if the link
    condition holds). Either keeps the closed manifold and the area (the sliver's is ~0), and is done only if no
    face it makes is a sliver or turns by more than ``acos(_MIN_COS_TURN)`` from the patch it replaces. Host
    work, one face at a time: for the few slivers a regularization leaves (2 of 44,574 faces on sword.obj).

    Returns:
        ``(v, f, count)``: positions (V', 3) float64, faces (F', 3) int64, operations done.
    """
    v, f = v.copy(), f.astype(np.int64).copy()
    done = 0
    for _ in range(4 * _MAX_SLIVER_REPAIRS):
        bad = np.nonzero(_sliver_mask(v, f, tiny))[0]
        if not bad.size:
            return (*_keep_faces(v, f, np.ones(f.shape[0], dtype=bool)), done)
        i = int(bad[0])
        tri = f[i]
        length = np.linalg.norm(v[np.roll(tri, -1)] - v[tri], axis=1)  # edge k: tri[k] -> tri[k + 1]
        nxt = np.roll(f, -1, axis=1)
        # cap: flip the longest edge (a, b) to (c, d)
        k = int(np.argmax(length))
        a, b, c = tri[k], tri[(k + 1) % 3], tri[(k + 2) % 3]
        j = np.nonzero(((f == b) & (nxt == a)).any(1))[0]
        if j.size == 1:
            j = int(j[0])
            d = int(f[j][(np.nonzero(f[j] == a)[0][0] + 1) % 3])
            linked = ((f == c).any(1) & (f == d).any(1)).any()
            new = np.array([[a, d, c], [d, b, c]])
            if d != c and not linked and _turns_ok(v, f[[j]], new, tiny):
                f[i], f[j] = new
                done += 1
                continue
        # needle: collapse the shortest edge (p, q) into its midpoint
        k = int(np.argmin(length))
        p, q = tri[k], tri[(k + 1) % 3]
        pair = np.nonzero((f == p).any(1) & (f == q).any(1))[0]
        ring_p = np.unique(f[(f == p).any(1)])
        ring_q = np.unique(f[(f == q).any(1)])
        common = np.setdiff1d(np.intersect1d(ring_p, ring_q), [p, q])
        if pair.size != 2 or common.size != 2:
            return None
        keep = np.ones(f.shape[0], dtype=bool)
        keep[pair] = False
        moved = keep & ((f == p) | (f == q)).any(1)
        new_v = v.copy()
        new_v[p] = 0.5 * (v[p] + v[q])
        new_f = np.where(f == q, p, f)
        if not all(_turns_ok(new_v, f[[m]], new_f[[m]], tiny) for m in np.nonzero(moved)[0]):
            return None
        v, f = new_v, new_f[keep]
        done += 1
    return None


class _Target:
    """A surface the regularization projects onto: its ``wp.Mesh`` and unit vertex normals."""

    def __init__(self, mesh: wp.Mesh):
        self.mesh = mesh
        dev = mesh.points.device
        self.normals = vertex_normals(mesh.points, mesh.indices)

    @property
    def args(self) -> list:
        return [self.mesh.id, self.mesh.points, self.mesh.indices, self.normals]


class _HalfEdgeSurface:
    """A closed manifold surface as half-edges on one device (layout: ``vnc_warp.kernels.remesh``), with
    every work array of the regularization allocated once; the methods only launch kernels.

    Isotropic regularization (:meth:`regularize`): each iteration runs, as Warp kernels, with no host
    round trip:

    1. one round of *relocations*: edges shorter than 4/5 of the target length ``L`` are collapsed
       into their midpoints, and as many edges longer than 4/3 ``L`` are split at theirs, reusing the
       vertex and the two faces each collapse frees, so the vertex and face counts never change.
       Pairing collapses with splits anywhere on the surface moves vertices from dense regions to
       sparse ones in one step; smoothing alone is a diffusion that would need hundreds of sweeps to
       even out the density across a shape, and uniform density is what VNC-soft needs;
    2. one round of edge flips that lower the deviation of valences from 6;
    3. one sweep of tangential relaxation toward the area-weighted centroid of the one-ring,
       followed by projection onto the target surface (``wp.mesh_query_point_no_sign``).

    After the last iteration every vertex moves along its normal by minus the mean distance of its
    faces' centroids from the target surface: projected vertices make every face a chord under a
    convex surface, which would lose area (2.4% on the armadillo) and make ``keep_area`` inflate the
    whole shape.

    ``L = sqrt(4 A / (sqrt(3) F))`` is the edge of an equilateral triangle of the mean face area.
    The connectivity changes every round, so one-rings are walked on the half-edge structure rather
    than read from a fixed adjacency list. Operations of one round run in parallel on an independent
    set; collapses keep the link condition (so the genus); no operation folds a face; tips and creases
    are held (``_FEATURE_COS``, ``_COLLAPSE_FLAT_COS``).
    """

    def __init__(self, v: np.ndarray, f: np.ndarray, twin: np.ndarray, out_he: np.ndarray, device):
        nv, self.num_faces, self.num_he = v.shape[0], f.shape[0], 3 * f.shape[0]
        self.device = device
        self.x = wp.array(v, dtype=wp.vec3, device=device)
        self.x_next = wp.empty_like(self.x)
        self.tri = wp.array(np.ascontiguousarray(f, dtype=np.int32).reshape(-1), dtype=wp.int32, device=device)
        self.twin = wp.array(twin, dtype=wp.int32, device=device)
        self.out_he = wp.array(out_he, dtype=wp.int32, device=device)
        self.valence = wp.empty(nv, dtype=wp.int32, device=device)
        self.lock = wp.empty(nv, dtype=wp.int32, device=device)
        self.revert = wp.zeros(nv, dtype=wp.int32, device=device)
        self.kind = wp.empty(self.num_he, dtype=wp.int32, device=device)
        self.num_kind = wp.zeros(2, dtype=wp.int32, device=device)
        self.winners = [wp.empty(self.num_he, dtype=wp.int32, device=device) for _ in range(2)]
        self.offsets = [wp.empty(self.num_he, dtype=wp.int32, device=device) for _ in range(2)]
        self.lists = [wp.empty(self.num_he, dtype=wp.int32, device=device) for _ in range(2)]
        self.counts = [wp.zeros(1, dtype=wp.int32, device=device) for _ in range(2)]
        self.moved = wp.zeros(nv, dtype=wp.float64, device=device)
        self.length = 0.0

    @property
    def num_vertices(self) -> int:
        return self.x.shape[0]

    @property
    def euler(self) -> int:
        return self.num_vertices - self.num_faces // 2

    @classmethod
    def build(cls, v: np.ndarray, f: np.ndarray, device) -> _HalfEdgeSurface | None:
        """The surface, or None unless every edge has exactly two opposite half-edges and every vertex
        one fan of faces (host work: once per surface that does not come from a previous state)."""
        nv = v.shape[0]
        a = f.reshape(-1).astype(np.int64)
        b = np.roll(f, -1, axis=1).reshape(-1).astype(np.int64)
        key = a * nv + b
        order = np.argsort(key)
        sorted_key = key[order]
        if np.any(sorted_key[1:] == sorted_key[:-1]):
            return None
        reverse = b * nv + a
        pos = np.minimum(np.searchsorted(sorted_key, reverse), key.size - 1)
        if not np.array_equal(sorted_key[pos], reverse):
            return None
        out_he = np.full(nv, -1, dtype=np.int32)
        out_he[a] = np.arange(a.size, dtype=np.int32)
        state = cls(v, f, order[pos].astype(np.int32), out_he, device)
        state._count_valence()
        # a vertex whose faces form several fans is not a disk: the walk around it misses faces
        if not np.array_equal(state.valence.numpy(), np.bincount(a, minlength=nv)):
            return None
        return state

    def _count_valence(self):
        wp.launch(_kr.ring_size, dim=self.valence.shape[0], inputs=[self.tri, self.twin, self.out_he, _MAX_RING],
                  outputs=[self.valence], device=self.device)

    def measures(self, tiny: float = 0.0) -> tuple[float, float, np.ndarray, int, int]:
        """Area, enclosed volume, area centroid (3,), faces with non-finite corners, and slivers (below
        ``_SLIVER``, or twice the area below ``tiny``)."""
        area, volume, centroid, bad = face_measures(self.x, self.tri, _SLIVER, tiny)
        return area, volume, centroid / max(area, 1e-300), int(bad[0]), int(bad[1])

    def problems(self, tiny: float) -> list[str]:
        """Every reason the surface is not a valid VNC-Flow state (as :func:`surface_problems` names
        them), from device counts: half-edges without a matching twin, rings that do not close over
        all faces, non-finite or sliver faces, non-positive volume."""
        errors = wp.zeros(3, dtype=wp.int32, device=self.device)
        wp.launch(_kr.check_halfedges, dim=self.num_he, inputs=[self.tri, self.twin], outputs=[errors],
                  device=self.device)
        self._count_valence()
        wp.launch(_kr.check_rings, dim=self.num_vertices, inputs=[self.valence], outputs=[errors], device=self.device)
        _, volume, _, nonfinite, slivers = self.measures(tiny)
        e = errors.numpy()
        out = []
        if e[0]:
            out.append(f"non-manifold or inconsistent orientation: {e[0]} half-edge(s) without an opposite twin")
        if e[1] or e[2] != self.num_he:
            out.append(f"non-manifold: {e[1]} vertex ring(s) do not close; the rings meet {e[2]} of "
                       f"{self.num_he} half-edges")
        if nonfinite:
            out.append(f"{nonfinite} face(s) have NaN or infinite corners")
        if slivers:
            out.append(f"{slivers} degenerate face(s) have (near) zero area")
        if not volume > 0.0:
            out.append(f"inward orientation: the enclosed volume is {volume:.6g} <= 0")
        return out

    def checked(self, tiny: float) -> tuple[_HalfEdgeSurface, list[str], int]:
        """This surface, or one with its slivers removed (:func:`_repair_slivers`) when they are all that is wrong
        and at most ``_MAX_SLIVER_REPAIRS``; what is still wrong (:meth:`problems`); the repairs done."""
        problems = self.problems(tiny)
        slivers = self.measures(tiny)[4]
        if not slivers or slivers > _MAX_SLIVER_REPAIRS or len(problems) != 1:
            return self, problems, 0
        fixed = _repair_slivers(self.x.numpy().astype(np.float64), self.tri.numpy().reshape(-1, 3), tiny)
        st = None if fixed is None else _HalfEdgeSurface.build(*fixed[:2], self.device)
        if st is None:
            return self, problems, 0
        return st, st.problems(tiny), fixed[2]

    def buried(self, wm: wp.Mesh, offset: float, use_winding: int) -> int:
        """Vertices whose point ``offset`` out along their normal is inside ``wm`` (this surface, with winding
        numbers): see ``count_buried``."""
        normals = vertex_normals(self.x, self.tri)
        count = wp.zeros(1, dtype=wp.int32, device=self.device)
        wp.launch(_k.count_buried, dim=self.num_vertices, inputs=[wm.id, self.x, normals, float(offset),
                                                                     use_winding], outputs=[count], device=self.device)
        return int(count.numpy()[0])

    def set_positions(self, x: wp.array) -> None:
        wp.copy(self.x, x)

    def frozen(self, *, winding: bool) -> wp.Mesh:
        """A ``wp.Mesh`` of the current surface on copies of its arrays (the state may change after)."""
        return wp.Mesh(points=wp.clone(self.x), indices=wp.clone(self.tri), support_winding_number=winding)

    def scale_about(self, centre: np.ndarray, factor: float) -> None:
        wp.launch(_kr.scale_about, dim=self.num_vertices, inputs=[self.x, wp.vec3(*centre), float(factor)],
                  device=self.device)

    def to_mesh(self, name: str, origin: np.ndarray) -> Mesh:
        """The surface as a :class:`~vnc_warp.mesh.Mesh` whose :attr:`~vnc_warp.mesh.Mesh.origin` is ``origin``
        (the frame the device positions are relative to), its edge topology built on the device. Each vertex's
        outgoing half-edge is reset to the one :meth:`build` picks (the last), so that a run resumed from the
        saved mesh regularizes exactly as the run that wrote it."""
        dev = self.device
        self.out_he.fill_(-1)
        wp.launch(_kr.last_outgoing, dim=self.num_he, inputs=[self.tri], outputs=[self.out_he], device=dev)
        flags = wp.empty(self.num_he, dtype=wp.int32, device=dev)
        wp.launch(_kr.owned_edges, dim=self.num_he, inputs=[self.twin], outputs=[flags], device=dev)
        offsets = wp.empty_like(flags)
        wp.utils.array_scan(flags, offsets, inclusive=False)
        num_edges = self.num_he // 2
        edges = wp.empty(num_edges, dtype=wp.vec2i, device=dev)
        interior = wp.empty(num_edges, dtype=wp.vec4i, device=dev)
        wp.launch(_kr.edge_topology, dim=self.num_he, inputs=[self.tri, self.twin, offsets], outputs=[edges, interior],
                  device=dev)
        topo = EdgeTopology(edges.numpy().reshape(-1, 2).copy(), interior.numpy().reshape(-1, 4).copy(),
                            np.zeros((0, 2), np.int32))
        # copies: on the CPU device .numpy() is a view, and the state changes at the next call
        return framed_mesh(self.x.numpy().copy(), self.tri.numpy().reshape(-1, 3).copy(), topo, name, origin)

    def regularize(self, surface: wp.Mesh, iterations: int, area: float, *, settle: bool = False) -> int:
        """``iterations`` rounds of relocations, flips and relaxation onto ``surface`` (a ``wp.Mesh``
        wound outward), then every vertex onto it; ``area`` sets the target edge length.

        With ``settle``, rounds go on (``_SETTLE_CHUNK`` at a time, at most ``_MAX_SETTLE``) until a
        relaxation sweep moves vertices by less than ``_SETTLED`` edge lengths on average, or by no less
        than ``_SETTLE_RATE`` times what it moved a chunk before (the moves have reached the floor of
        the flips and relocations that go on): the density of a tessellation evens out by diffusion,
        and a surface regularized only part of the way drifts on at every later regularization (the
        torus's inner/outer edge-length ratio 0.85 -> 0.93 took 300 iterations, and its VNC-AUC rose
        10 % with it). Returns the iterations run.
        """
        self.length = float(np.sqrt(4.0 * area / (np.sqrt(3.0) * self.num_faces)))
        target = _Target(surface)
        done, before = 0, np.inf
        while True:
            for _ in range(iterations if done == 0 else _SETTLE_CHUNK):
                self.relocate(done)
                self.flip(done)
                self.relax(target)
                done += 1
            if not settle or done >= _MAX_SETTLE:
                break
            moved = ordered_sum(self.moved) / (self.length * self.num_vertices)
            if moved < _SETTLED or moved > _SETTLE_RATE * before:
                break
            before = moved
        self.project(target)
        return done

    def relocate(self, it: int):
        """One round of paired collapses and splits (``it`` seeds the priorities)."""
        dev, n = self.device, self.num_he
        self._count_valence()
        self.num_kind.zero_()
        wp.launch(_kr.mark_relocations, dim=n,
                  inputs=[self.x, self.tri, self.twin, self.out_he, self.valence, _SHORT_EDGE * self.length,
                          _LONG_EDGE * self.length, _MAX_VALENCE, _MIN_COS_TURN, _COLLAPSE_FLAT_COS, _MAX_RING],
                  outputs=[self.kind, self.num_kind], device=dev)
        for phase in range(2):
            self.lock.fill_(_NO_LOCK)
            if phase == 1:
                wp.launch(_kr.reserve_relocations, dim=n, inputs=[self.tri, self.twin, *self.winners, _MAX_RING],
                          outputs=[self.lock], device=dev)
            wp.launch(_kr.claim_relocations, dim=n,
                      inputs=[self.tri, self.twin, self.kind, self.num_kind, phase, it, _MAX_RING],
                      outputs=[self.lock], device=dev)
            wp.launch(_kr.relocation_winners, dim=n,
                      inputs=[self.tri, self.twin, self.kind, self.num_kind, phase, it, _MAX_RING, self.lock],
                      outputs=self.winners, device=dev)
        for k in range(2):
            wp.utils.array_scan(self.winners[k], self.offsets[k], inclusive=False)
            wp.launch(_kr.compact, dim=n, inputs=[self.winners[k], self.offsets[k]],
                      outputs=[self.lists[k], self.counts[k]], device=dev)
        wp.launch(_kr.apply_relocations, dim=n // 2,
                  inputs=[self.x, self.tri, self.twin, self.out_he, self.lists[0], self.counts[0], self.lists[1],
                          self.counts[1], _MAX_RING], device=dev)

    def flip(self, it: int):
        """One round of valence-improving edge flips."""
        self._count_valence()
        self.lock.fill_(_NO_LOCK)
        seed = _FLIP_SEED + it
        wp.launch(_kr.mark_flips, dim=self.num_he,
                  inputs=[self.x, self.tri, self.twin, self.out_he, self.valence, _MIN_COS_TURN, _FEATURE_COS,
                          _MAX_RING, seed], outputs=[self.kind, self.lock], device=self.device)
        wp.launch(_kr.apply_flips, dim=self.num_he,
                  inputs=[self.tri, self.twin, self.out_he, self.kind, self.lock, seed], device=self.device)

    def relax(self, surface: _Target):
        """One sweep of tangential relaxation and projection onto ``surface``; moves that fold or crease
        an edge are undone."""
        dev = self.device
        wp.launch(_kr.tangential_relax, dim=self.x.shape[0],
                  inputs=[*surface.args, self.x, self.tri, self.twin, self.out_he, self.length, _MIN_COS_TURN,
                          _FEATURE_COS, _MAX_RING], outputs=[self.x_next, self.moved], device=dev)
        for _ in range(_REVERT_PASSES):
            wp.launch(_kr.mark_sharpened_edges, dim=self.num_he, inputs=[self.x, self.x_next, self.tri, self.twin,
                                                                         _MIN_COS_TURN],
                      outputs=[self.revert], device=dev)
            wp.launch(_kr.revert_vertices, dim=self.x.shape[0], inputs=[self.x, self.revert], outputs=[self.x_next],
                      device=dev)
        self.x, self.x_next = self.x_next, self.x

    def project(self, surface: _Target):
        """Every vertex onto ``surface`` (the relocations of the last iteration leave some at edge midpoints)."""
        wp.launch(_kr.project_onto, dim=self.x.shape[0],
                  inputs=[*surface.args, self.x, self.tri, self.twin, self.out_he, self.length, _FEATURE_COS,
                          _MAX_RING], outputs=[self.x_next], device=self.device)
        self.x, self.x_next = self.x_next, self.x


def _repairs_text(repairs: dict) -> str:
    """What :func:`_read_source` repaired, in words ("1 non-manifold edge(s), 2 duplicate face(s) removed")."""
    return ", ".join(f"{n} {what}" for key, what in (("non_manifold_edges", "non-manifold edge(s)"),
                                                     ("non_manifold_vertices", "non-manifold vertex(es)"),
                                                     ("duplicate_faces", "duplicate face(s) removed"),
                                                     ("degenerate_faces", "degenerate face(s) removed"),
                                                     ("reoriented_faces", "face(s) re-wound"))
                     if (n := repairs.get(key)))


class _Remesher:
    """:func:`sdf_remesh` with its settings fixed and the last result kept on the device as half-edges.

    Called with a ``source``, it remeshes that input. Called with ``positions`` (a (V,) vec3 array of the
    last result's vertices, moved: a VNC-Flow state), it remeshes the last result at those positions
    without reading anything back to the host first, at the last result's face count and grid spacing
    (so that a surface made from the level set at spacing ``h`` is checked against its level set at
    the same ``h``).
    """

    def __init__(self, *, faces: int | None = None, resolution: int | None = None, device=None,
                 keep_area: bool = True, sign: str = "winding", marching_cubes: str = "auto",
                 relax_iterations: int = 24, allow_changes: bool = False, warn: bool = True):
        self.use_winding = sign_flag(sign)
        if marching_cubes not in ("auto", "skimage", "warp"):
            raise ValueError(f"sdf_remesh: marching_cubes must be 'auto', 'skimage' or 'warp', got {marching_cubes!r}")
        if faces is not None and int(faces) < 8:
            raise ValueError(f"sdf_remesh: target face count must be at least 8, got {faces!r}")
        if resolution is not None and int(resolution) < 8:
            raise ValueError(f"sdf_remesh: resolution must be at least 8 nodes, got {resolution!r}")
        if int(relax_iterations) != relax_iterations or relax_iterations < 0:
            raise ValueError(f"sdf_remesh: relax_iterations must be a non-negative integer, got {relax_iterations!r}")
        self.device = get_device(device)
        self.faces = None if faces is None else int(faces)
        self.resolution = None if resolution is None else int(resolution)
        self.keep_area, self.sign = keep_area, sign
        self.method = marching_cubes if marching_cubes != "auto" else ("warp" if self.device.is_cuda else "skimage")
        self.relax_iterations = int(relax_iterations)
        self.allow_changes, self.warn = allow_changes, warn
        self.state: _HalfEdgeSurface | None = None
        # every device position is relative to this point (float64), so that a mesh far from the coordinate
        # origin keeps float32 precision (as Mesh.local_vertices does for the operators)
        self.origin = np.zeros(3)
        self.spacing = 0.0
        self.name = "mesh"

    def adopt(self, mesh: Mesh, spacing: float, name: str) -> None:
        """Continue from ``mesh`` (a result of an earlier remesher with these settings, read back from disk), in its
        frame: positions given later are relative to ``mesh.origin``."""
        self.origin = np.asarray(mesh.origin, np.float64)
        self.state = _HalfEdgeSurface.build(mesh.local_vertices.astype(np.float64), mesh.faces.astype(np.int64),
                                            self.device)
        if self.state is None:
            raise MeshError(f"sdf_remesh: {name}: the stage to continue from is not a closed manifold surface")
        self.spacing, self.name = float(spacing), name

    def held(self) -> tuple:
        """What the remesher holds (its last surface on the device, its grid spacing and frame), for
        :meth:`restore`: a caller that tries a remesh and may not take it (VNC-Flow's deferred join)."""
        return self.state, self.spacing, self.origin.copy()

    def restore(self, held: tuple) -> None:
        """Hold again what :meth:`held` returned."""
        self.state, self.spacing, self.origin = held

    def interpenetrates(self, positions: wp.array) -> bool:
        """Whether the current surface at ``positions`` (its connectivity, relative to :attr:`origin`) has parts
        inside other parts (two limbs that touched and went on into each other, a sheet folded over) by the rule
        of :meth:`_disagreement`, so that a remesh of these positions goes through the level set, which joins the
        parts, instead of re-tessellating them in place."""
        st = self.state
        st.set_positions(positions)
        wm = st.frozen(winding=bool(self.use_winding))
        return st.buried(wm, _BURIED_CELLS * self.spacing, self.use_winding) > _BURIED_SHARE * st.num_vertices

    def __call__(self, source: Any = None, *, positions: wp.array | None = None) -> tuple[Mesh, RemeshReport]:
        if positions is not None:
            out, report, expected, _ = self._remesh(None, positions, None, {})
            return out, self._conclude(report, expected, refuse=False)
        seconds: dict = {}
        out, report, expected, given = self._remesh(source, None, None, seconds)
        if self.resolution is None and _unfaithful(report):
            out, report = self._refine_for_thin_parts(out, report, given, seconds)
        return out, self._conclude(report, expected, refuse=True)

    def _refine_for_thin_parts(self, out: Mesh, report: RemeshReport, given: _Given,
                               seconds: dict) -> tuple[Mesh, RemeshReport]:
        """Make a new input's first remesh again on finer grids when the automatic spacing dropped or lost more than
        ``_MAX_LOST`` of the surface in parts thinner than the grid (a blade, a fin, a thin ring).

        The missing parts (the input farther than ``_MISSING_EDGES`` edge lengths of the result from it) are measured
        (:func:`_missing_thickness`); if they are thin, the remesh is made again at ``_CELLS_ACROSS_THIN`` cells across
        their ``_MISSING_PERCENTILE``-th percentile thickness, no finer than ``1 / _MAX_RETRY_REFINE`` of the first
        spacing nor past the grid's node cap (:func:`finest_spacing`), and not at all when they would still be thinner
        than a cell there or the spacing would not shrink below ``_MIN_REFINE_STEP`` of the last one (parts that are
        not thin: a separate component, which a finer grid does not keep). At most ``_THIN_RETRIES`` attempts; the
        first faithful one is kept, else the one that kept the most (``report.grid_refined`` and, when none was
        faithful, ``report.changes`` say what was tried). The tolerance is not changed: a result is still refused as
        before when no grid kept the surface. Later remeshes of a VNC-Flow state use the spacing kept."""
        first = report
        floor = max(finest_spacing(given.hi - given.lo), first.spacing / _MAX_RETRY_REFINE)
        span = float(np.linalg.norm(given.hi - given.lo))
        best = (out, report, self.state, self.spacing)
        tried, current = [], report
        for _ in range(_THIN_RETRIES):
            edge = np.sqrt(4.0 * given.area * (1.0 - current.dropped_area) / (np.sqrt(3.0) * current.faces))
            share, thick = _missing_thickness(given.x, given.tri, given.wm, self.state.frozen(winding=True),
                                              _MISSING_EDGES * edge, span)
            h = max(thick / _CELLS_ACROSS_THIN, floor)
            if not thick or thick < h or h > _MIN_REFINE_STEP * current.spacing:
                break
            cells = thick / current.spacing
            why = (f"at spacing {current.spacing:.4g} parts {thick:.3g} thick ({cells:.2f} cells: the "
                   f"{_MISSING_PERCENTILE:g}th percentile of the {100 * share:.1f} % of the input farther than "
                   f"{_MISSING_EDGES:g} edge length(s) from the result) broke up ({_loss_text(current)})")
            try:
                o, r, _, _ = self._remesh(given.src, None, h, seconds)
            except MeshError as exc:  # no valid surface of the face count on this grid: keep what there is
                tried.append((why, f"spacing {h:.4g} gave no valid surface ({exc})"))
                break
            tried.append((why, f"spacing {r.spacing:.4g}: {_loss_text(r)}"))
            if max(r.dropped_area, r.lost_area) < max(best[1].dropped_area, best[1].lost_area):
                best = (o, r, self.state, self.spacing)
            current = r
            if not _unfaithful(r):
                break
        if not tried:
            return out, report
        out, report, self.state, self.spacing = best
        steps = "; then ".join(f"{why}, so made again at {then}" for why, then in tried)
        report.grid_refined = f"refined the grid from spacing {first.spacing:.4g} to {report.spacing:.4g}: {steps}"
        if report is first:
            report.grid_refined = f"tried finer grids and kept spacing {first.spacing:.4g}: {steps}"
        if _unfaithful(report):
            report.changes.append(f"no finer grid kept the thin parts ({steps})")
        return out, report

    def _remesh(self, source: Any, positions: wp.array | None, spacing: float | None,
                seconds: dict) -> tuple[Mesh, RemeshReport, int | None, _Given | None]:
        """One remesh of ``source`` (or of the last result at ``positions``) at grid spacing ``spacing`` (None: the
        remesher's own), not yet concluded (:meth:`_conclude`): the result, its report, the Euler characteristic
        expected, and the input as it was used (None for ``positions``)."""
        dev = self.device
        clock = _Clock(dev, seconds)
        if positions is not None:
            st = self.state
            st.set_positions(positions)
            area_in, _, _, nonfinite, slivers = st.measures()
            if nonfinite:
                raise MeshError(f"sdf_remesh: {self.name}: {nonfinite} face(s) have NaN or infinite corners")
            wm = st.frozen(winding=bool(self.use_winding))
            x, tri = wm.points, wm.indices
            target = st.num_faces
            report = RemeshReport("surface", 0.0, st.num_faces, euler_in=st.euler, seconds=seconds)
            why = (f"{slivers} degenerate face(s)" if slivers else
                   "no regularization asked for" if not self.relax_iterations else None)
            expected = st.euler
        else:
            src = source if isinstance(source, _Source) else _read_source(source)
            self.name = src.name
            target = self.faces or src.f.shape[0]
            if self.sign == "normal" and (src.mesh is None or src.loops):
                raise ValueError(f"sdf_remesh: {src.name} is not a closed manifold surface; the normal sign is only "
                                 "right for watertight meshes, use sign='winding'")
            f = src.f
            self.origin = 0.5 * (src.v.min(0) + src.v.max(0))
            v = src.v - self.origin
            if src.mesh is None and np.einsum("ij,ij->i", v[f[:, 0]] - v.mean(0),
                                              np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])).sum() < 0.0:
                f = f[:, ::-1]  # an open surface may be wound either way: inward distances need it outward
            x = wp.array(v, dtype=wp.vec3, device=dev)
            tri = wp.array(np.ascontiguousarray(f, dtype=np.int32).reshape(-1), dtype=wp.int32, device=dev)
            wm = wp.Mesh(points=x, indices=tri, support_winding_number=bool(self.use_winding))
            area_in = float(_area_and_centroid(v, src.f)[0])
            report = RemeshReport("surface", 0.0, src.f.shape[0], euler_in=src.euler, components_in=src.components,
                                  repairs=dict(src.repairs), seconds=seconds)
            why = ("the input is not a valid closed surface" if src.mesh is None else
                   "the face count changes" if target != src.f.shape[0] else
                   "no regularization asked for" if not self.relax_iterations else None)
            st = _HalfEdgeSurface.build(v, src.f, dev) if why is None else None
            expected = src.euler + src.loops if src.euler is not None and src.components == 1 else None
            clock.lap("input")
        lo, hi = _device_bounds(x)
        given = None if positions is not None else _Given(src, x, tri, wm, lo, hi, area_in)
        side = float((hi - lo).max())
        tiny = 1e-12 * float(((hi - lo) ** 2).sum())
        if spacing is not None:
            h = spacing
        elif self.resolution is not None:
            h = side / (self.resolution - 1)
        elif positions is not None:
            h = self.spacing
        else:
            h = auto_spacing(area_in, hi - lo, target, wm, x, tri)
        report.spacing = h
        clock.lap("checks")
        ls = _level_set(wm, lo, hi, h, _GRIDS[0][0], area_in, self.use_winding, self.method, clock)
        if why is None:
            why = self._disagreement(st, wm, ls, lo, hi, h, area_in, clock, report=report)
        if why is None:
            st.regularize(wm, self.relax_iterations, area_in, settle=positions is None)
            if positions is None:
                self._own_fixed_point(st, area_in)
            clock.lap("regularize")
            if self.keep_area:
                area, _, centre, _, _ = st.measures()
                st.scale_about(centre, np.sqrt(area_in / area))
                report.area_scale = float(np.sqrt(area_in / area))
            st, problems, report.slivers_repaired = st.checked(tiny)
            if not problems:
                out = st.to_mesh(f"{self.name}:remeshed", self.origin)
                clock.lap("checks")
                self.state, self.spacing = st, h
                report.faces, report.vertices, report.euler = out.num_faces, out.num_vertices, st.euler
                return out, report, expected, given
            why = f"re-tessellating the surface itself left {'; '.join(problems)}"
        report.method, report.why_level_set = "level_set", why
        st, out = self._level_set_path(wm, lo, hi, h, ls, area_in, target, report, clock, euler=expected)
        edge = np.sqrt(4.0 * area_in * (1.0 - report.dropped_area) / (np.sqrt(3.0) * out.num_faces))
        report.lost_area = _lost_share(x, tri, st.frozen(winding=True), _LOST_EDGES * edge)
        # a surface made from the level set has its own level set, on another grid, at thin gaps and necks:
        # remesh it from that until both agree, so the next call re-tessellates instead of flickering
        while report.topology_passes < _TOPOLOGY_PASSES:
            area, _, _, _, _ = st.measures()
            wm = st.frozen(winding=bool(self.use_winding))
            lo, hi = _device_bounds(st.x)
            ls = _level_set(wm, lo, hi, report.spacing, _GRIDS[0][0], area, self.use_winding, self.method, clock)
            if self._disagreement(st, wm, ls, lo, hi, report.spacing, area, clock) is None:
                break
            again = RemeshReport("level_set", report.spacing, out.num_faces, seconds=seconds)
            st, out = self._level_set_path(wm, lo, hi, report.spacing, ls, area, target, again, clock, euler=st.euler)
            report.topology_passes += 1
            report.dropped_components += again.dropped_components
            report.dropped_area = 1.0 - (1.0 - report.dropped_area) * (1.0 - again.dropped_area)
        clock.lap("checks")
        if self.relax_iterations:
            area, _, _, _, _ = st.measures()
            self._own_fixed_point(st, area)
            now, _, centre, _, _ = st.measures()
            st.scale_about(centre, np.sqrt(area / now))
            st, problems, repaired = st.checked(tiny)
            report.slivers_repaired += repaired
            if problems:
                raise MeshError(f"sdf_remesh: {self.name}: re-tessellating the result left " + "; ".join(problems))
            out = st.to_mesh(out.name, self.origin)
            clock.lap("regularize")
        self.state, self.spacing = st, report.spacing
        report.faces, report.vertices, report.euler = out.num_faces, out.num_vertices, st.euler
        return out, report, expected, given

    def _own_fixed_point(self, st: _HalfEdgeSurface, area: float) -> None:
        """Regularize a new result once more onto its own surface. It was projected onto a finer surface (the
        input, or marching cubes), whose detail below its edge length the next re-tessellation, projected onto
        the result's own surface, rounds off: on springer that first later call moved S by +0.78 %, the ones after
        it by 0.01-0.07 %. After this pass the first later call is like the others."""
        st.regularize(st.frozen(winding=False), self.relax_iterations, area)

    def _disagreement(self, st: _HalfEdgeSurface, wm: wp.Mesh, ls: _LevelSet, lo: np.ndarray, hi: np.ndarray, h: float,
                      area: float, clock: _Clock, *, report: RemeshReport | None = None) -> str | None:
        """Why the surface ``st`` (``wm`` its ``wp.Mesh``, ``area`` its area, ``[lo, hi]`` its bounds) is not its level
        set ``ls`` at spacing ``h``, or None.

        A level set whose Euler characteristic differs from the surface's is checked with the other resolution of
        its ambiguous cube faces (:func:`_grid_allows`), then sampled once more on the second grid of ``_GRIDS``
        (same spacing, offset by a fraction of a cell), and the surface is its level set if either grid allows it:
        a topology change that one grid or one resolution shows and another does not is a gap or a neck at the
        grid's own resolution, which the placement of the grid joins or splits, not the shape (boot's laces: Euler
        characteristic -26, -22, -22 and -28 on four offsets of one grid with scikit-image's marching cubes; -14
        and -28 on one grid with Warp's, ambiguous faces kept apart and joined). Sending such a surface down the
        marching-cubes path lost 8 of its 12 handles and 9.7 % of its total VNC-AUC in one remesh of an unchanged
        surface. A real change (a handle narrowed below the grid, parts that met) shows on both grids.

        A level set that shows more handles or more pieces than the surface on both grids and both resolutions, and
        closes none (:func:`_torn`), is the grid tearing a part thinner than itself when some of the solid is thinner
        than ``_TEAR_CELLS`` cells, no gap outside it is narrower (nothing the level set could have joined:
        :func:`_thinnest_and_narrowest`), and no part is buried in another: curvature flow never opens a hole in a
        sheet, and parts that touch show as a self-intersection. Then the surface is kept (``report.grid_tear`` says
        why). sword.obj's blade (5th-percentile thickness 0.009 of the radius of its sphere of equal area, thinner
        than a cell where the grid is capped at ``_MAX_GRID_NODES``) had its unchanged stage 0 sent down the
        level-set path on an H200 ("Euler characteristic 0 ..., the surface 2": a hole punched through the blade),
        S +3.39 %, and later remeshes broke the blade into fragments (Euler characteristic 28 around 2); the flow
        never reached a sphere (final sphericity 0.25). A plate 0.018 thick at its centre, remeshed at spacing 0.04:
        S +7.5 % and Euler characteristic 2 -> 0 before, +0.11 % on the surface path after. Handles that close
        (a torus's hole, boot's eyelets: the largest component's Euler characteristic rises) and contact joins (the
        self-intersection check below) still take the level set.
        """
        if not ls.num_faces:
            return "its level set is empty"
        tear = None
        if not _grid_allows(ls, st.euler):
            clock.lap("checks")
            other = _level_set(wm, lo, hi, h, _GRIDS[1][0], area, self.use_winding, self.method, clock)
            clock.lap("checks")
            if not _grid_allows(other, st.euler):
                topology = (f"its level set has Euler characteristic {ls.euler} ({ls.joined().euler} with ambiguous "
                            f"faces joined), the surface {st.euler}")
                if not all(_torn(r, st.euler) for g in (ls, other) for r in g.resolutions()):
                    return topology
                thin, gap = _thinnest_and_narrowest(wm, float(np.linalg.norm(hi - lo)))
                clock.lap("checks")
                if not (thin < _TEAR_CELLS * h <= gap):
                    return topology
                tear = (f"{topology}: the grid tore a part thinner than itself (thinnest {thin / h:.2f} cells, "
                        f"narrowest gap {gap / h:.2f} cells); the surface was kept")
            else:
                ls = other
        added = _farthest(wm, ls.points, 2.0 * _AGREE_CELLS * h) / h
        if added > _AGREE_CELLS:
            clock.lap("checks")
            return f"its level set lies up to {added:.2f} grid cells off the surface"
        buried = st.buried(wm, _BURIED_CELLS * h, self.use_winding)
        clock.lap("checks")
        if buried > _BURIED_SHARE * st.num_vertices:
            return f"{buried} vertex(es) lie inside another part of the shape (self-intersection)"
        if tear is not None and report is not None:
            report.grid_tear = tear
        return None

    def _level_set_path(self, wm, lo, hi, h0, first, area_in, target, report, clock, *, euler=None, sample=None):
        """Marching cubes, the largest component, decimation, regularization onto the marching-cubes
        surface; retried on other grids and less aggressive decimations until the result is valid. Of each grid's
        two resolutions of ambiguous faces, the one nearest the Euler characteristic ``euler`` (if given: the
        surface's) is used, so that handles and gaps about one cell across are kept on every device. ``sample(h,
        shift)``, if given, makes the level set of another grid (default: ``wm``'s signed distance), and then
        the result keeps the marching-cubes surface's own area (``area_in`` is not used)."""
        import fast_simplification

        failures = []
        tiny = 1e-12 * float(((hi - lo) ** 2).sum())
        for g, (shift, refine) in enumerate(_GRIDS):
            h = h0 * refine
            ls = first.nearest(euler) if g == 0 else None
            for _ in range(3):
                if ls is None:
                    ls = (sample(h, shift) if sample is not None else
                          _level_set(wm, lo, hi, h, shift, area_in, self.use_winding, self.method, clock)).nearest(euler)
                v_mc, f_mc = ls.host()
                kept = 0
                if f_mc.shape[0]:
                    label, comp_area = ls.components()
                    keep = label == np.argmax(comp_area)
                    kept = int(keep.sum())
                clock.lap("components")
                if kept >= 1.2 * target or self.resolution is not None:
                    break
                # aim at the oversampled count again, refining at most 4x per step and never past the cap
                finer = max(h * 0.9 * np.sqrt(max(kept, 1) / (_OVERSAMPLE * target)), 0.25 * h,
                            finest_spacing(hi - lo))
                if finer >= h:
                    break
                h, ls = finer, None
            if kept < (1.0 + _FACE_COUNT_TOLERANCE) * target:
                pieces = f" (the largest of {comp_area.size} pieces)" if f_mc.shape[0] and comp_area.size > 1 else ""
                failures.append(f"marching cubes gave {kept} faces{pieces} at spacing {h:.4g}, fewer than the "
                                f"{target} asked for; raise `resolution`")
                if self.resolution is not None:
                    break
                continue
            report.components_level_set = int(comp_area.size)
            report.dropped_components = int(comp_area.size - 1)
            report.dropped_area = float(1.0 - comp_area.max() / comp_area.sum())
            report.spacing = h
            v_k, f_k = _keep_faces(v_mc, f_mc, keep)
            if np.einsum("ij,ij->i", v_k[f_k[:, 0]], np.cross(v_k[f_k[:, 1]], v_k[f_k[:, 2]])).sum() < 0.0:
                f_k = f_k[:, ::-1]
            surface = wp.Mesh(points=wp.array(v_k, dtype=wp.vec3, device=self.device),
                              indices=wp.array(np.ascontiguousarray(f_k, dtype=np.int32).reshape(-1), dtype=wp.int32,
                                               device=self.device))
            # the kept part keeps its own area: dropping two of three spheres, or a ring too thin for the
            # grid, must not inflate what is left; only the chords' small loss of area is made up for
            total = float(comp_area.sum())
            scale = area_in / total if sample is None and abs(area_in / total - 1.0) <= _CHORD_LOSS else 1.0
            area = float(comp_area.max()) * scale if self.keep_area else None
            for agg in _AGGRESSIVENESS:
                v, f = fast_simplification.simplify(v_k, f_k, target_count=target, agg=agg)
                f = _drop_double_faces(f)
                clock.lap("decimation")
                done, problem = self._finish(v, f, surface, area, target, tiny, report, clock)
                if problem is None:
                    return done
                # cut what the decimation pinched, drop parts it cut off, and check once more
                v, f = _largest_component(*_split_fans(v, f))
                done, after_cut = self._finish(v, f, surface, area, target, tiny, report, clock)
                if after_cut is None:
                    return done
                failures.append(f"spacing {h:.4g}, agg {agg:g}: {problem} (after cutting pinched fans: {after_cut})")
        what = _repairs_text(report.repairs)
        raise MeshError(f"sdf_remesh: {self.name}: no valid surface after {len(failures)} attempt(s)"
                        + (f" from an input with {what}" if what else "") + ": " + " | ".join(failures))

    def _finish(self, v, f, surface, area, target, tiny, report, clock):
        """Orient outward, regularize, scale to ``area`` (if given) and check a decimated surface.

        The result is checked on the device (:meth:`_HalfEdgeSurface.problems`, slivers below ``tiny`` twice the
        area): :meth:`_HalfEdgeSurface.build` already refused a surface that is not a closed manifold, and the
        regularization keeps that; what it can break (a fold, a sliver, the volume's sign) is counted by kernels,
        with no host pass over the mesh.

        Returns:
            ``((state, mesh), None)`` when it is valid and within 2% of ``target`` faces, else
            ``(None, problem)``.
        """
        if abs(f.shape[0] - target) > _FACE_COUNT_TOLERANCE * target:
            return None, f"{f.shape[0]} faces, not within {_FACE_COUNT_TOLERANCE:.0%} of {target}"
        v, f = _keep_faces(v, f, np.ones(f.shape[0], dtype=bool))  # decimation can leave vertices unused
        current, _ = _area_and_centroid(v, f)
        if not (current > 0.0 and np.isfinite(current)):
            return None, f"surface area {current:.6g}"
        if np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum() < 0.0:
            f = np.ascontiguousarray(f[:, ::-1])
        st = _HalfEdgeSurface.build(v, f, self.device)
        if st is None:
            return None, "; ".join(surface_problems(v, f)) or "not a closed manifold surface"
        if self.relax_iterations:
            st.regularize(surface, self.relax_iterations, current, settle=True)
            clock.lap("regularize")
        if area is not None:
            now, _, centre, _, _ = st.measures()
            st.scale_about(centre, np.sqrt(area / now))
            report.area_scale = float(np.sqrt(area / now))
        st, problems, report.slivers_repaired = st.checked(tiny)
        clock.lap("checks")
        if problems:
            return None, f"sdf_remesh: {self.name}:remeshed: " + "; ".join(problems)
        return (st, st.to_mesh(f"{self.name}:remeshed", self.origin)), None

    def _conclude(self, report: RemeshReport, expected: int | None, *, refuse: bool) -> RemeshReport:
        """Say what was repaired or changed; refuse (``refuse``: a new input, not a VNC-Flow state whose
        changes are the flow's own) a result that is not a faithful surface unless allowed."""
        fixed = _repairs_text(report.repairs)
        if fixed:
            report.changes.append("repaired the input: " + fixed)
        if report.components_in > 1 and report.dropped_components == 0:
            report.changes.append(f"joined the input's {report.components_in} components into one surface")
        if report.dropped_components:
            report.changes.append(f"kept the largest of {report.components_level_set} level-set components: dropped "
                                  f"{report.dropped_components} ({100 * report.dropped_area:.1f} % of its area)")
        if report.lost_area > 0.0:
            report.changes.append(f"{100 * report.lost_area:.1f} % of the input's area lies farther than "
                                  f"{_LOST_EDGES:g} edge lengths from the result: parts thinner than the grid "
                                  f"spacing {report.spacing:.4g} broke up or vanished")
        if expected is not None and report.euler != expected:
            report.changes.append(f"the topology changed: Euler characteristic {expected} -> {report.euler}")
        if _unfaithful(report) and refuse and not self.allow_changes:
            raise MeshError(f"sdf_remesh: {self.name}: the result would not be a faithful surface: "
                            + "; ".join(report.changes) + ". Pass allow_changes=True to accept it, or a finer "
                            "resolution for thin parts")
        if report.changes and self.warn:
            warnings.warn(f"sdf_remesh: {self.name}: " + "; ".join(report.changes), RemeshWarning, stacklevel=3)
        return report


def moment_ellipsoid(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """The solid ellipsoid with the volume, centroid and second moments of the solid a closed, outward-wound
    triangle mesh bounds (a solid ellipsoid of semi-axes ``r`` has covariance ``diag(r^2) / 5``), scaled to the
    solid's volume.

    Args:
        v: (V, 3) float64 positions; f: (F, 3) int triangles.

    Returns:
        ``(centre (3,), axes (3, 3) with the principal directions as columns, radii (3,), volume)``, in ``v``'s units.
    """
    mean = v.mean(axis=0)
    a, b, c = v[f[:, 0]] - mean, v[f[:, 1]] - mean, v[f[:, 2]] - mean
    det = np.einsum("ij,ij->i", a, np.cross(b, c))  # 6 x the signed volume of the tetrahedron (0, a, b, c)
    volume = float(det.sum()) / 6.0
    if not volume > 0.0:
        raise MeshError(f"moment_ellipsoid: the surface encloses volume {volume:.6g}; it must be closed and wound "
                        "outward")
    s = a + b + c
    centroid = (s * det[:, None]).sum(axis=0) / (24.0 * volume)
    second = (np.einsum("i,ij,ik->jk", det, s, s)
              + sum(np.einsum("i,ij,ik->jk", det, w, w) for w in (a, b, c))) / 120.0
    cov = second / volume - np.outer(centroid, centroid)
    lam, axes = np.linalg.eigh(0.5 * (cov + cov.T))
    radii = np.sqrt(5.0 * np.maximum(lam, 1e-12 * max(float(lam.max()), 1e-300)))
    radii *= (3.0 * volume / (4.0 * np.pi * float(np.prod(radii)))) ** (1.0 / 3.0)
    return centroid + mean, axes, radii, volume


class _Blend:
    """The surfaces between a state and a second shape: for ``a`` in [0, 1] the zero level set of
    ``(1 - a) f + a g``, ``f`` the state's signed distance and ``g`` the other shape's (:meth:`_blend` writes it),
    made by the remesher's level-set path (marching cubes, largest component, decimation to the state's face count,
    regularization, checks) and scaled by :meth:`_scale`. ``f`` is sampled once per grid (spacing ``spacing``, the
    remesher's unless given, over :attr:`lo`, :attr:`hi`), then reused for every ``a``.

    Subclasses set ``lo``, ``hi`` (bounds of both shapes), ``what`` (the report's words) and ``name`` (the result's
    name suffix) in their constructor after calling this one's, then :meth:`_fit_spacing`."""

    def __init__(self, remesher: _Remesher, x: wp.array, tri: wp.array, *, spacing: float | None = None):
        self.remesher = remesher
        self.spacing = float(remesher.spacing if spacing is None else spacing)
        self.v = x.numpy().astype(np.float64)
        self.f = tri.numpy().reshape(-1, 3).astype(np.int64)
        self.wm = wp.Mesh(points=x, indices=tri, support_winding_number=bool(remesher.use_winding))
        self.area = float(_area_and_centroid(self.v, self.f)[0])
        self.euler = self.v.shape[0] - self.f.shape[0] // 2
        self.lo, self.hi = self.v.min(axis=0), self.v.max(axis=0)
        self.grids: dict = {}

    def _fit_spacing(self, coarsest: float = 0.0) -> None:
        """Coarsen the spacing to at least ``coarsest`` and to the grid's node cap over the bounds ``lo``, ``hi`` (both
        shapes'): the state's own spacing over a larger box can exceed the cap by far (sword.obj's blade, spacing
        set by its thinness, inside the cube of its moment ellipsoid's longest axis: 1.7e10 nodes, on an H200 at
        765207b; a blade of 2 x 0.25 x 0.012 at 6,000 faces: 1.30x the cap)."""
        self.spacing = max(self.spacing, float(coarsest), finest_spacing(self.hi - self.lo))

    def _sample(self, wm: wp.Mesh, area: float, h: float, shift, clock: _Clock) -> tuple[wp.array, np.ndarray]:
        origin = self.lo - (2.0 - np.asarray(shift)) * h
        shape = tuple(int(n) for n in np.ceil((self.hi - origin) / h).astype(int) + 3)
        grid = sample_grid(wm, origin, h, shape, band_factor=choose_band_factor(shape, area, h),
                           use_winding=self.remesher.use_winding, device=self.remesher.device)
        clock.lap("sdf")
        return grid, origin

    def _distance(self, h: float, shift, clock: _Clock) -> tuple[wp.array, np.ndarray]:
        key = (float(h), tuple(shift))
        if key not in self.grids:
            self.grids[key] = self._sample(self.wm, self.area, h, shift, clock)
        return self.grids[key]

    def _blend(self, grid: wp.array, origin: np.ndarray, h: float, shift, a: float, out: wp.array,
               clock: _Clock) -> None:
        raise NotImplementedError

    def _scale(self, st: _HalfEdgeSurface, a: float) -> None:
        raise NotImplementedError

    def __call__(self, a: float) -> tuple[Mesh, RemeshReport]:
        """The blended surface at ``a`` (in the remesher's frame) and its report (``method`` ``"blend"``)."""
        r = self.remesher

        seconds: dict = {}
        clock = _Clock(r.device, seconds)

        def sample(h: float, shift) -> _LevelSet:
            grid, origin = self._distance(h, shift, clock)
            out = wp.empty_like(grid)
            self._blend(grid, origin, h, shift, a, out, clock)
            clock.lap("sdf")
            ls = _extract(out, origin, h, r.method, False)
            clock.lap("marching_cubes")
            return ls

        target = self.f.shape[0]
        report = RemeshReport("blend", self.spacing, target, euler_in=self.euler, seconds=seconds)
        report.why_level_set = f"{self.what} at a = {a:.4g}"
        st, _ = r._level_set_path(self.wm, self.lo, self.hi, self.spacing, sample(self.spacing, _GRIDS[0][0]),
                                  self.area, target, report, clock, euler=self.euler, sample=sample)
        if r.relax_iterations:
            area, _, _, _, _ = st.measures()
            r._own_fixed_point(st, area)
        self._scale(st, a)
        st, problems, report.slivers_repaired = st.checked(1e-12 * float(((self.hi - self.lo) ** 2).sum()))
        if problems:
            raise MeshError(f"sdf_remesh: {r.name}: the blend at a = {a:.4g} left " + "; ".join(problems))
        out = st.to_mesh(f"{r.name}:{self.name}", r.origin)
        clock.lap("regularize")
        report.faces, report.vertices, report.euler = out.num_faces, out.num_vertices, st.euler
        return out, report


class _EllipsoidBlend(_Blend):
    """:class:`_Blend` toward the state's moment ellipsoid (:func:`moment_ellipsoid`), scaled to the state's volume;
    see :func:`vnc_warp.flow.flow` (the blend fallback) for why. ``roundness`` in [0, 1] moves the ellipsoid's
    semi-axes toward the radius of the sphere of its volume (geometric interpolation, the volume kept): at 1 the
    blend goes toward that sphere, for a state whose own ellipsoid is too elongated to lower ``S`` enough (a
    long-handled club's: on hammer.obj on the H200 at f00c328 no blend toward its ellipsoid lowered t below 0.375)."""

    name = "blended"

    def __init__(self, remesher: _Remesher, x: wp.array, tri: wp.array):
        super().__init__(remesher, x, tri)
        self.centre, self.axes, self.radii, self.volume = moment_ellipsoid(self.v, self.f)
        self.roundness = 0.0
        half = np.maximum(np.sqrt(((self.axes * self.radii[None, :]) ** 2).sum(axis=1)), self.radii.max())
        self.lo, self.hi = np.minimum(self.lo, self.centre - half), np.maximum(self.hi, self.centre + half)
        self._fit_spacing()

    @property
    def what(self) -> str:
        return f"blend toward the moment ellipsoid (roundness {self.roundness:g})"

    def _blend(self, grid, origin, h, shift, a, out, clock) -> None:
        sphere = float(np.prod(self.radii)) ** (1.0 / 3.0)
        radii = self.radii ** (1.0 - self.roundness) * sphere ** self.roundness
        wp.launch(_k.blend_ellipsoid_grid, dim=grid.shape,
                  inputs=[grid, wp.vec3(*origin), float(h), wp.vec3(*self.centre),
                          wp.mat33(*self.axes.reshape(-1).tolist()), wp.vec3(*radii), float(a), _MIN_ABS_SDF * h],
                  outputs=[out], device=self.remesher.device)

    def _scale(self, st: _HalfEdgeSurface, a: float) -> None:
        # the trajectory's S is measured at fixed scales: a smaller shape would count as a smoother one
        _, volume, centre, _, _ = st.measures()
        st.scale_about(centre, (self.volume / volume) ** (1.0 / 3.0))


class _SurfaceBlend(_Blend):
    """:class:`_Blend` from a state ``P`` toward another surface ``Q`` (``x_q``, ``tri_q``, in the same frame), both
    signed distances sampled on one grid: the continuous path between two states that one remesh joins (a level-set
    remesh that closes handles or cuts thin parts off in one step; see :func:`vnc_warp.flow.flow`, the bridge). The
    result is scaled to the area ``(1 - a) A_P + a A_Q``, as a remesh keeps the area. A grid finer than the remesher's
    (``spacing``) represents the features of ``P`` that the remesher's level set lost, so that they go along the
    path instead of at ``a = 0``; it is made no finer than marching cubes' ``_MAX_BLEND_OVERSAMPLE`` times the face
    count (nor than the grid's node cap)."""

    name = "bridged"
    what = "bridge from the state before the remesh toward the state after it"

    def __init__(self, remesher: _Remesher, x: wp.array, tri: wp.array, x_q: wp.array, tri_q: wp.array, *,
                 spacing: float):
        super().__init__(remesher, x, tri, spacing=spacing)
        v_q = x_q.numpy().astype(np.float64)
        f_q = tri_q.numpy().reshape(-1, 3).astype(np.int64)
        self.wm_q = wp.Mesh(points=x_q, indices=tri_q, support_winding_number=bool(remesher.use_winding))
        self.area_q = float(_area_and_centroid(v_q, f_q)[0])
        self.lo, self.hi = np.minimum(self.lo, v_q.min(axis=0)), np.maximum(self.hi, v_q.max(axis=0))
        # no finer than marching cubes' _MAX_BLEND_OVERSAMPLE times the face count, nor past the grid's node cap
        self._fit_spacing(np.sqrt(_MC_FACES_PER_AREA * max(self.area, self.area_q)
                                  / (_MAX_BLEND_OVERSAMPLE * self.f.shape[0])))
        self.grids_q: dict = {}

    def _blend(self, grid, origin, h, shift, a, out, clock) -> None:
        key = (float(h), tuple(shift))
        if key not in self.grids_q:
            self.grids_q[key] = self._sample(self.wm_q, self.area_q, h, shift, clock)
        wp.launch(_k.blend_grids, dim=grid.shape, inputs=[grid, self.grids_q[key][0], float(a), _MIN_ABS_SDF * h],
                  outputs=[out], device=self.remesher.device)

    def _scale(self, st: _HalfEdgeSurface, a: float) -> None:
        area, _, centre, _, _ = st.measures()
        st.scale_about(centre, np.sqrt(((1.0 - a) * self.area + a * self.area_q) / area))


def sdf_remesh(mesh: Any, *, faces: int | None = None, resolution: int | None = None, device=None,
               keep_area: bool = True, sign: str = "winding", marching_cubes: str = "auto",
               relax_iterations: int = 24, allow_changes: bool = False, return_report: bool = False):
    """Rebuild a mesh as a clean closed surface of its signed distance (Algorithm 1, lines 2 and 7).

    The signed distance (:func:`vnc_warp.sdf.sample_grid`; inside/outside from the winding number, so an
    open scan still yields a closed surface) is sampled on a narrow-band grid of spacing ``h`` and its
    zero level set extracted by marching cubes. Then (see the module docstring for why):

    * if the input is a valid closed surface with ``faces`` faces whose level set has its Euler
      characteristic and lies within ``h`` of it both ways, the input's own surface is regularized
      (``relax_iterations``, below) and projected back onto itself: same vertex and face counts, same
      topology, detail kept to the input's own resolution;
    * otherwise the marching-cubes surface is used: its largest component, quadric decimation
      (fast-simplification) to ``faces``, and the regularization projected onto it. Decimation can
      flatten parts too thin for the face budget: double-sided triangles are removed, and if the
      surface fails :func:`validate_surface`, edges and vertices pinched by the decimation are cut (one
      vertex copy per fan) and parts cut off are dropped. If it still fails, it is decimated again less
      aggressively, then on a grid shifted by a fraction of a cell, then on a shifted grid 1.5x coarser:
      at most three grids and nine decimations before giving up.

    With ``keep_area`` the result is scaled about its area centroid to the input's surface area (Sec. 3.2
    (3): remeshing keeps face count and surface area), or to the share of it that was kept when level-set
    components were dropped.

    Automatic resolution (``resolution=None``): the grid spacing ``h`` is the smaller of

    * ``sqrt(2.83 * A / (4 * faces))``, with ``A`` the input area: marching cubes makes about
      ``2.83 * A / h^2`` triangles, so this aims at 4x the target before decimation;
    * half the thinnest parts' thickness (the area-weighted 1st percentile of the distance through
      the shape along inward face normals, 4096 rays), so thin parts keep two cells across and do
      not break up, but no less than half the first;

    clamped to at least 32 nodes along the longest bounding-box side and at most 384^3 nodes in the
    whole grid. If marching cubes still yields
    fewer than 1.2x ``faces``, the spacing is refined and the grid resampled. If the result would not be
    faithful (below) because parts thinner than the grid broke up (the input missing from the result, farther
    than an edge length from it, is thin: its 90th-percentile thickness along inward normals below 1.6
    cells), it is made again on a grid two cells across that thickness, at most 4x finer than the first
    and within the node cap (at most twice); ``report.grid_refined`` says what was lost at which spacing and
    what the finer grid kept, and ``report.spacing`` is the grid used (sword.obj at 6,000 faces: spacing
    0.00167 dropped 2.6 % of the blade's tip; 0.00066 dropped nothing).

    Isotropic regularization: quadric decimation leaves edge lengths varying by a factor of several
    (coefficient of variation ~0.43 on Spot), which VNC-soft reads as curvature. Each of
    ``relax_iterations`` iterations pairs collapses of edges shorter than 4/5 of the target length with
    splits of edges longer than 4/3 of it (so vertex and face counts stay exactly those of the
    decimation), flips edges toward valence 6, and moves every vertex tangentially toward the
    area-weighted centroid of its one-ring, then back onto the target surface; finally vertices move
    along their normals so faces straddle that surface instead of cutting under it. Tips, creases and
    parts thinner than two edges are held. Measured on Spot: edge-length variation 0.43 -> 0.11, 1st
    percentile of the smallest face angle 3 -> 38 degrees. All of it runs as Warp kernels on ``device``.

    Faithfulness: a result that drops level-set components holding more than 1 % of the area (only the
    largest is kept), or leaves more than 1 % of the input's area farther than two grid cells away
    (parts thinner than the grid broke up: a thin sheet comes back with holes), is refused unless
    ``allow_changes`` (with the automatic resolution, after the finer grids above). A repaired input
    (non-manifold edges or vertices, duplicate or degenerate faces, inconsistent winding, several
    components joined by the level set) and a changed Euler characteristic are warned about
    (:class:`RemeshWarning`); the report records all of it.

    Args:
        mesh: a :class:`~vnc_warp.mesh.Mesh`, or anything :func:`~vnc_warp.mesh.load_mesh` accepts
            (also with the repairable problems above); need not be watertight with ``sign="winding"``.
        faces: target face count; None means the input's. The output is within 2% of it (exactly it
            on the surface path).
        resolution: grid nodes along the longest bounding-box side; None chooses it (see above).
        device: where everything but the decimation and the marching-cubes surface's component
            labelling runs; None means Warp's preferred device.
        keep_area: scale the result to the input's surface area.
        sign: ``"winding"`` (default; open meshes too) or ``"normal"`` (faster, watertight input).
        marching_cubes: ``"skimage"``, ``"warp"`` (``warp.geometry.IsoSurfaceMarchingCubes``, on the
            grid's device) or ``"auto"``: Warp's on CUDA, scikit-image's on the CPU.
        relax_iterations: iterations of the isotropic regularization; 0 returns the decimated
            marching-cubes surface as it is.
        allow_changes: accept a result that drops components or loses thin parts (see above).
        return_report: also return the :class:`RemeshReport`.

    Returns:
        A new :class:`~vnc_warp.mesh.Mesh` named ``"<name>:remeshed"``: watertight, manifold, outward,
        no degenerate faces; with ``return_report``, ``(mesh, report)``.

    Raises:
        ValueError: bad ``faces``, ``resolution``, ``sign``, ``marching_cubes`` or
            ``relax_iterations``; ``sign="normal"`` with an open mesh.
        MeshError: the input cannot be loaded or repaired, the result would not be faithful (and
            ``allow_changes`` is off), or no attempt produced a valid surface of the requested size
            (the message lists what went wrong in each attempt).
    """
    remesher = _Remesher(faces=faces, resolution=resolution, device=device, keep_area=keep_area, sign=sign,
                         marching_cubes=marching_cubes, relax_iterations=relax_iterations,
                         allow_changes=allow_changes)
    out, report = remesher(mesh)
    return (out, report) if return_report else out
