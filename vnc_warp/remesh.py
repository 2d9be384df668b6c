"""SDF-remesh: the topology regularization of VNC-Flow (paper Sec. 3.2 (3), Algorithm 1 lines 2 and 7).

``sdf_remesh`` rebuilds a mesh as the zero level set of its signed distance: Warp mesh queries
(winding-number sign, so scans with holes still close) on a narrow-band grid, marching cubes, the
largest connected component, quadric decimation back to the face count, an isotropic
regularization on the marching-cubes surface, and a scale about the centroid that restores the
surface area. Every output passes :func:`validate_surface`, the prerequisites of the VNC operator:
watertight, edge- and vertex-manifold, consistently and outwardly wound, finite, no degenerate faces.

Why the regularization: VNC-soft (Eq. 3) is a length-weighted mean of dihedral angles, and a
dihedral angle grows with the edge length (about ``L * kappa`` on a surface of curvature ``kappa``),
so on a mesh whose edge lengths vary, H varies with them and Eq. (4) counts that as shape
complexity. Quadric decimation is curvature-adaptive (edge lengths vary by a factor of several):
on a remeshed sphere the total VNC-AUC was 4.5x that of an icosphere, and remeshing between VNC-Flow
stages made the normalized time of Eq. (7) jump back up. The regularization makes the edge lengths
nearly uniform (the paper's "regularizes triangle areas, mitigating VNC-soft/hard discrepancies on
irregular tessellations").
"""

from __future__ import annotations

from typing import Any

import numpy as np
import warp as wp

from vnc_warp._device import get_device
from vnc_warp.kernels import remesh as _kr
from vnc_warp.kernels import sdf as _k
from vnc_warp.mesh import Mesh, MeshError, from_arrays, load_mesh
from vnc_warp.sdf import choose_band_factor, sample_grid, sign_flag, warp_mesh

__all__ = ["sdf_remesh", "validate_surface"]

# Marching-cubes triangles per (area / spacing^2) (2.80-2.95 measured on spot, armadillo and the open
# bunny; skimage's Lewiner MC and Warp's MC give the same count).
_MC_FACES_PER_AREA = 2.83
# Marching cubes aims at this many times the target face count before decimation.
_OVERSAMPLE = 4.0
# Grid cells across the thinnest parts kept by the automatic resolution ...
_CELLS_ACROSS_THIN = 2.0
# ... where "thinnest" is this area-weighted percentile of the inward thickness.
_THIN_PERCENTILE = 1.0
_THICKNESS_SAMPLES = 4096
# ... but at most this much finer than the face-count spacing: parts too thin for the target face
# count would only be pinched into non-manifold fins by the decimation.
_MAX_THIN_REFINE = 2.0
# Bounds on the automatic resolution, in nodes along the longest bounding-box side.
_MIN_NODES = 32
_MAX_NODES = 384
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
# Isotropic regularization (see _Regularizer): edges shorter / longer than these fractions of the
# target length are collapsed / split (the thresholds of Botsch and Kobbelt's isotropic remeshing), ...
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
# Relaxation moves that fold or crease an edge (neighbours moving at once) are undone; a second pass
# catches the rare edge creased by the first undo.
_REVERT_PASSES = 2


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
        pinched = _nonmanifold_vertices(f, nv)
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


def _inward_thickness(m: Mesh, wm: wp.Mesh, device) -> float:
    """Area-weighted low percentile of the distance through the shape along inward face normals."""
    v = m.vertices.astype(np.float64)
    f = m.faces
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    area2 = np.linalg.norm(n, axis=1)
    rng = np.random.default_rng(0)
    pick = rng.choice(f.shape[0], size=min(_THICKNESS_SAMPLES, f.shape[0]), p=area2 / area2.sum())
    centroid = v.mean(0)
    # an open mesh may be wound either way: orient by the sign of its volume about the centroid
    vol = np.einsum("ij,ij->i", v[f[:, 0]] - centroid, n).sum()
    normals = n[pick] / area2[pick, None] * (1.0 if vol >= 0.0 else -1.0)
    points = v[f[pick]].mean(1)
    diag = m.bbox_diagonal
    t = wp.empty(pick.size, dtype=wp.float32, device=device)
    wp.launch(_k.inward_thickness, dim=pick.size,
              inputs=[wm.id, wp.array(points, dtype=wp.vec3, device=device),
                      wp.array(normals, dtype=wp.vec3, device=device), 1e-5 * diag, 2.0 * diag],
              outputs=[t], device=device)
    hits = t.numpy()
    hits = hits[hits > 0.0]
    if hits.size < 16:
        return float(diag)
    return float(np.percentile(hits, _THIN_PERCENTILE))


def auto_spacing(m: Mesh, target: int, wm: wp.Mesh, device) -> float:
    """Grid spacing of the automatic resolution (mesh units); see :func:`sdf_remesh`."""
    side = float((m.vertices.max(0) - m.vertices.min(0)).max())
    h_faces = np.sqrt(_MC_FACES_PER_AREA * m.area() / (_OVERSAMPLE * target))
    h_thin = _inward_thickness(m, wm, device) / _CELLS_ACROSS_THIN
    h = max(min(h_faces, h_thin), h_faces / _MAX_THIN_REFINE)
    return float(np.clip(h, side / (_MAX_NODES - 1), side / (_MIN_NODES - 1)))


def _marching_cubes(grid: wp.array, origin: np.ndarray, spacing: float, method: str):
    """Zero level set of the grid as (V, 3) float64 positions and (F, 3) int64 faces."""
    if method == "warp":
        import warp.geometry

        upper = origin + spacing * (np.asarray(grid.shape) - 1)
        verts, idx = warp.geometry.IsoSurfaceMarchingCubes.extract(
            grid, 0.0, lower=wp.vec3(*origin), upper=wp.vec3(*upper))
        return verts.numpy().astype(np.float64), idx.numpy().reshape(-1, 3).astype(np.int64)
    from skimage.measure import marching_cubes

    verts, tris, _, _ = marching_cubes(grid.numpy(), 0.0, spacing=(spacing,) * 3)
    return verts.astype(np.float64) + origin, tris.astype(np.int64)


def _largest_component(v: np.ndarray, f: np.ndarray):
    """The connected component with the most faces, its vertices renumbered."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    nv = v.shape[0]
    rows = f[:, [0, 1, 2]].reshape(-1)
    cols = f[:, [1, 2, 0]].reshape(-1)
    _, label = connected_components(coo_matrix((np.ones(rows.size, np.int8), (rows, cols)), shape=(nv, nv)),
                                    directed=False)
    face_label = label[f[:, 0]]
    keep = face_label == np.argmax(np.bincount(face_label))
    f = f[keep]
    used = np.unique(f)
    remap = np.zeros(nv, dtype=np.int64)
    remap[used] = np.arange(used.size)
    return v[used], remap[f]


def _drop_double_faces(f: np.ndarray) -> np.ndarray:
    """Faces without the groups that share one vertex triple.

    Quadric decimation can flatten a part thinner than its budget allows (a finger, a tube) into a
    double-sided triangle: two faces on the same three vertices, which make their edges four-faced.
    Without both, the part keeps a three-vertex waist and every edge has two faces again.
    """
    key = np.sort(f, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    return f[counts[inverse.reshape(-1)] == 1]


def _area_and_centroid(v: np.ndarray, f: np.ndarray) -> tuple[float, np.ndarray]:
    """Surface area and area-weighted centroid (3,)."""
    area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    return float(area.sum()), (area[:, None] * v[f].mean(1)).sum(0) / area.sum()


class _Regularizer:
    """Isotropic regularization of decimated surfaces on the marching-cubes surface they came from.

    Each iteration runs, as Warp kernels (``vnc_warp.kernels.remesh``) on arrays allocated once per
    call, with no host round trip:

    1. one round of *relocations*: edges shorter than 4/5 of the target length ``L`` are collapsed
       into their midpoints, and as many edges longer than 4/3 ``L`` are split at theirs, reusing the
       vertex and the two faces each collapse frees, so the vertex and face counts never change.
       Pairing collapses with splits anywhere on the surface moves vertices from dense regions to
       sparse ones in one step; smoothing alone is a diffusion that would need hundreds of sweeps to
       even out the density across a shape, and uniform density is what VNC-soft needs;
    2. one round of edge flips that lower the deviation of valences from 6;
    3. one sweep of tangential relaxation toward the area-weighted centroid of the one-ring,
       followed by projection onto the marching-cubes surface (``wp.mesh_query_point_no_sign``).

    After the last iteration every vertex moves along its normal by minus the mean distance of its
    faces' centroids from the marching-cubes surface: projected vertices make every face a chord
    under a convex surface, which would lose area (2.4% on the armadillo) and make ``keep_area``
    inflate the whole shape.

    ``L = sqrt(4 A / (sqrt(3) F))`` is the edge of an equilateral triangle of the mean face area.
    The connectivity changes every round, so one-rings are walked on a half-edge structure (built
    once with NumPy) rather than read from a fixed adjacency list. Operations of one round run in
    parallel on an independent set; collapses keep the link condition (so the genus); no operation
    folds a face; tips and creases are held (``_FEATURE_COS``, ``_COLLAPSE_FLAT_COS``).
    """

    def __init__(self, v_mc: np.ndarray, f_mc: np.ndarray, device):
        f_mc = np.asarray(f_mc, dtype=np.int32)
        # the projection test compares face normals with vertex normals: wind the target outward too
        if np.einsum("ij,ij->i", v_mc[f_mc[:, 0]], np.cross(v_mc[f_mc[:, 1]], v_mc[f_mc[:, 2]])).sum() < 0.0:
            f_mc = f_mc[:, ::-1]
        self.device = device
        self.surface = wp.Mesh(points=wp.array(v_mc, dtype=wp.vec3, device=device),
                               indices=wp.array(np.ascontiguousarray(f_mc).reshape(-1), dtype=wp.int32, device=device))

    def __call__(self, v: np.ndarray, f: np.ndarray, iterations: int) -> tuple[np.ndarray, np.ndarray]:
        """Regularized ``(v, f)``, same shapes; returned unchanged unless the surface is a closed
        manifold (then its validation names the problem)."""
        state = _HalfEdgeSurface.build(v, f, self.device)
        if state is None:
            return v, f
        for it in range(iterations):
            state.relocate(it)
            state.flip(it)
            state.relax(self.surface)
        state.straddle(self.surface)
        return state.x.numpy().astype(np.float64), state.tri.numpy().reshape(-1, 3).astype(np.int64)


class _HalfEdgeSurface:
    """A closed manifold surface as half-edges on one device (layout: ``vnc_warp.kernels.remesh``), with
    every work array of the regularization allocated once; the methods only launch kernels."""

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
        self.offset = wp.empty(self.num_faces, dtype=wp.float32, device=device)
        area, _ = _area_and_centroid(np.asarray(v, dtype=np.float64), f)
        self.length = float(np.sqrt(4.0 * area / (np.sqrt(3.0) * f.shape[0])))

    @classmethod
    def build(cls, v: np.ndarray, f: np.ndarray, device) -> _HalfEdgeSurface | None:
        """The surface, or None unless every edge has exactly two opposite half-edges and every vertex
        one fan of faces."""
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

    def relax(self, surface: wp.Mesh):
        """One sweep of tangential relaxation and projection onto ``surface``; moves that fold or crease
        an edge are undone."""
        dev = self.device
        wp.launch(_kr.tangential_relax, dim=self.x.shape[0],
                  inputs=[surface.id, self.x, self.tri, self.twin, self.out_he, self.length, _MIN_COS_TURN,
                          _FEATURE_COS, _MAX_RING], outputs=[self.x_next], device=dev)
        for _ in range(_REVERT_PASSES):
            wp.launch(_kr.mark_sharpened_edges, dim=self.num_he, inputs=[self.x, self.x_next, self.tri, self.twin,
                                                                         _MIN_COS_TURN],
                      outputs=[self.revert], device=dev)
            wp.launch(_kr.revert_vertices, dim=self.x.shape[0], inputs=[self.x, self.revert], outputs=[self.x_next],
                      device=dev)
        self.x, self.x_next = self.x_next, self.x

    def straddle(self, surface: wp.Mesh):
        """Move vertices along their normals so faces straddle ``surface`` rather than cut under it."""
        dev = self.device
        wp.launch(_kr.face_offsets, dim=self.num_faces, inputs=[surface.id, self.x, self.tri, self.length],
                  outputs=[self.offset], device=dev)
        wp.launch(_kr.straddle, dim=self.x.shape[0], inputs=[self.x, self.tri, self.twin, self.out_he, self.offset,
                                                             _MAX_RING], outputs=[self.x_next], device=dev)
        self.x, self.x_next = self.x_next, self.x


def _finish(v: np.ndarray, f: np.ndarray, target: int, area: float | None, name: str,
            regularizer: _Regularizer | None = None, iterations: int = 0):
    """Orient outward, regularize (``iterations`` > 0), scale to ``area`` (if given) and check a
    decimated surface.

    Returns:
        ``(mesh, None)`` when it is valid and within 2% of ``target`` faces, else ``(None, problem)``.
    """
    if abs(f.shape[0] - target) > _FACE_COUNT_TOLERANCE * target:
        return None, f"{f.shape[0]} faces, not within {_FACE_COUNT_TOLERANCE:.0%} of {target}"
    current, centroid = _area_and_centroid(v, f)
    if not (current > 0.0 and np.isfinite(current)):
        return None, f"surface area {current:.6g}"
    if np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum() < 0.0:
        f = np.ascontiguousarray(f[:, ::-1])
    if iterations > 0:
        v, f = regularizer(v, f, iterations)
        current, centroid = _area_and_centroid(v, f)
    if area is not None:
        v = centroid + (v - centroid) * np.sqrt(area / current)
    try:
        mesh = from_arrays(v, f, name=name, merge=False)
        # checked as stored (float32), so rounding cannot turn a valid face into a sliver afterwards
        validate_surface(mesh, where="sdf_remesh")
    except MeshError as exc:
        return None, str(exc)
    return mesh, None


def sdf_remesh(mesh: Any, *, faces: int | None = None, resolution: int | None = None, device=None,
               keep_area: bool = True, sign: str = "winding", marching_cubes: str = "auto",
               relax_iterations: int = 24) -> Mesh:
    """Rebuild a mesh as a clean closed surface of its signed distance (Algorithm 1, lines 2 and 7).

    Steps: signed distance on a narrow-band grid (:func:`vnc_warp.sdf.sample_grid`; inside/outside
    from the winding number, so an open scan still yields a closed surface), marching cubes, the
    largest connected component, quadric decimation (fast-simplification) to ``faces``, isotropic
    regularization (``relax_iterations``, below) and, with ``keep_area``, a scale about the area
    centroid so the area equals the input's (Sec. 3.2 (3): remeshing keeps face count and surface
    area). Decimation can flatten parts too thin for the face
    budget: double-sided triangles are removed, and if the surface fails :func:`validate_surface`,
    edges and vertices pinched by the decimation are cut (one vertex copy per fan) and parts cut
    off are dropped. If it still fails, it is decimated again less aggressively, then on
    a grid shifted by a fraction of a cell, then on a shifted grid 1.5x coarser (where thin parts
    that keep pinching merge or vanish): at most three grids and nine decimations before giving up.

    Automatic resolution (``resolution=None``): the grid spacing ``h`` is the smaller of

    * ``sqrt(2.83 * A / (4 * faces))``, with ``A`` the input area: marching cubes makes about
      ``2.83 * A / h^2`` triangles, so this aims at 4x the target before decimation;
    * half the thinnest parts' thickness (the area-weighted 1st percentile of the distance through
      the shape along inward face normals, 4096 rays), so thin parts keep two cells across and do
      not break up, but no less than half the first (at most 16x the target before decimation:
      parts too thin for the face budget would only be pinched by the decimation);

    clamped to 32-384 nodes along the longest bounding-box side. If marching cubes still yields
    fewer than 1.2x ``faces``, the spacing is refined and the grid resampled.

    Isotropic regularization: quadric decimation leaves edge lengths varying by a factor of several
    (coefficient of variation ~0.43 on Spot), which VNC-soft reads as curvature (see the module
    docstring). Each of ``relax_iterations`` iterations pairs collapses of edges shorter than 4/5
    of the target length with splits of edges longer than 4/3 of it (so vertex and face counts stay
    exactly those of the decimation), flips edges toward valence 6, and moves every vertex
    tangentially toward the area-weighted centroid of its one-ring, then back onto the
    marching-cubes surface; finally vertices move along their normals so faces straddle that
    surface instead of cutting under it. Tips, creases and parts thinner than two edges are held
    (see :class:`_Regularizer`). Measured on Spot: edge-length variation 0.43 -> 0.11, 1st
    percentile of the smallest face angle 3 -> 38 degrees; a remeshed sphere's total VNC-AUC drops
    to 1.5x an icosphere's (from 4.5x). All Warp kernels on ``device``.

    Args:
        mesh: a :class:`~vnc_warp.mesh.Mesh`, or anything :func:`~vnc_warp.mesh.load_mesh` accepts;
            need not be watertight with ``sign="winding"``.
        faces: target face count; None means the input's. The output is within 2% of it.
        resolution: grid nodes along the longest bounding-box side; None chooses it (see above).
        device: where the signed distances, Warp marching cubes and the regularization run; None
            means Warp's preferred device. Decimation and checks run on the host.
        keep_area: scale the result about its area centroid to the input's surface area.
        sign: ``"winding"`` (default; open meshes too) or ``"normal"`` (faster, watertight input).
        marching_cubes: ``"skimage"``, ``"warp"`` (``warp.geometry.IsoSurfaceMarchingCubes``, on the
            grid's device) or ``"auto"``: Warp's on CUDA, scikit-image's on the CPU.
        relax_iterations: iterations of the isotropic regularization; 0 returns the decimated
            surface as it is (the behaviour before the regularization existed).

    Returns:
        A new :class:`~vnc_warp.mesh.Mesh` named ``"<name>:remeshed"``: watertight, manifold,
        outward, no degenerate faces.

    Raises:
        ValueError: bad ``faces``, ``resolution``, ``sign``, ``marching_cubes`` or
            ``relax_iterations``; ``sign="normal"`` with an open mesh.
        MeshError: the input cannot be loaded, or no attempt produced a valid surface of the
            requested size (the message lists what went wrong in each attempt).
    """
    import fast_simplification

    use_winding = sign_flag(sign)
    if marching_cubes not in ("auto", "skimage", "warp"):
        raise ValueError(f"sdf_remesh: marching_cubes must be 'auto', 'skimage' or 'warp', got {marching_cubes!r}")
    m = load_mesh(mesh)
    if sign == "normal" and not m.is_watertight:
        raise ValueError(f"sdf_remesh: {m.name} has {m.topology.boundary.shape[0]} boundary edge(s); the normal "
                         "sign is only right for watertight meshes, use sign='winding'")
    target = m.num_faces if faces is None else int(faces)
    if target < 8:
        raise ValueError(f"sdf_remesh: target face count must be at least 8, got {faces!r}")
    if resolution is not None and int(resolution) < 8:
        raise ValueError(f"sdf_remesh: resolution must be at least 8 nodes, got {resolution!r}")
    if int(relax_iterations) != relax_iterations or relax_iterations < 0:
        raise ValueError(f"sdf_remesh: relax_iterations must be a non-negative integer, got {relax_iterations!r}")
    dev = get_device(device)
    method = marching_cubes if marching_cubes != "auto" else ("warp" if dev.is_cuda else "skimage")
    wm = warp_mesh(m, dev, winding=bool(use_winding))
    area_in = m.area()
    lo = m.vertices.min(0).astype(np.float64)
    hi = m.vertices.max(0).astype(np.float64)
    side = float((hi - lo).max())
    base = side / (int(resolution) - 1) if resolution is not None else auto_spacing(m, target, wm, dev)

    failures = []
    for shift, refine in _GRIDS:
        h = base * refine
        for _ in range(3):
            origin = lo - (2.0 - np.asarray(shift)) * h
            shape = tuple(int(n) for n in np.ceil((hi - origin) / h).astype(int) + 3)
            grid = sample_grid(wm, origin, h, shape, band_factor=choose_band_factor(shape, area_in, h),
                               use_winding=use_winding, device=dev)
            wp.launch(_k.push_off_zero, dim=shape, inputs=[grid, _MIN_ABS_SDF * h], device=dev)
            v_mc, f_mc = _marching_cubes(grid, origin, h, method)
            if f_mc.shape[0]:
                v_mc, f_mc = _largest_component(v_mc, f_mc)
            if f_mc.shape[0] >= 1.2 * target or resolution is not None:
                break
            # aim at the oversampled count again, refining at most 4x per step and never past the cap
            finer = max(h * 0.9 * np.sqrt(f_mc.shape[0] / (_OVERSAMPLE * target)), 0.25 * h,
                        side / (_MAX_NODES - 1))
            if finer >= h:
                break
            h = finer
        if f_mc.shape[0] < (1.0 + _FACE_COUNT_TOLERANCE) * target:
            failures.append(f"marching cubes gave {f_mc.shape[0]} faces at spacing {h:.4g}, fewer than the "
                            f"{target} asked for; raise `resolution`")
            if resolution is not None:
                break
            continue
        regularizer = _Regularizer(v_mc, f_mc, dev) if relax_iterations else None
        finish = dict(target=target, area=area_in if keep_area else None, name=f"{m.name}:remeshed",
                      regularizer=regularizer, iterations=int(relax_iterations))
        for agg in _AGGRESSIVENESS:
            v, f = fast_simplification.simplify(v_mc, f_mc, target_count=target, agg=agg)
            f = _drop_double_faces(f)
            out, problem = _finish(v, f, **finish)
            if problem is None:
                return out
            # cut what the decimation pinched, drop parts it cut off, and check once more
            v, f = _largest_component(*_split_fans(v, f))
            out, after_cut = _finish(v, f, **finish)
            if after_cut is None:
                return out
            failures.append(f"spacing {h:.4g}, agg {agg:g}: {problem} (after cutting pinched fans: {after_cut})")
    raise MeshError(f"sdf_remesh: {m.name}: no valid surface after {len(failures)} attempt(s): "
                    + " | ".join(failures))
