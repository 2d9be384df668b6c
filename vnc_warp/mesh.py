"""Triangle meshes as the VNC operator sees them: merged vertices, checked topology, outward winding.

Everything in vnc-warp runs on a :class:`Mesh`. :func:`load_mesh` builds one from a file or a
``trimesh.Trimesh`` and refuses, with a message that says what and where, the inputs on which
Eqs. (1)-(3) are undefined: empty meshes, NaN coordinates, out-of-range indices, degenerate faces,
non-manifold edges (three or more faces) and inconsistent winding.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["Mesh", "EdgeTopology", "MeshError", "load_mesh", "from_arrays"]


class MeshError(ValueError):
    """A mesh that vnc-warp cannot compute on; the message says what is wrong and where."""


def _first(idx: np.ndarray, k: int = 5) -> str:
    idx = np.asarray(idx).ravel()
    head = ", ".join(str(int(i)) for i in idx[:k])
    return head + (", ..." if idx.size > k else "")


@dataclass(frozen=True)
class EdgeTopology:
    """Edge adjacency of a manifold triangle mesh.

    Attributes:
        edges: (E, 2) int32, every unique undirected edge, sorted endpoints.
        interior: (Ei, 4) int32, per interior edge ``(a, b, c0, c1)``: face ``(a, b, c0)`` traverses
            ``a -> b`` in its winding and face ``(b, a, c1)`` traverses ``b -> a``.
        boundary: (Eb, 2) int32, edges with exactly one face.
    """

    edges: np.ndarray
    interior: np.ndarray
    boundary: np.ndarray

    @property
    def num_interior(self) -> int:
        return int(self.interior.shape[0])


def _build_topology(faces: np.ndarray, vertices: np.ndarray | None = None) -> tuple[EdgeTopology, int]:
    """Edge topology and the number of interior edges whose two faces disagree on winding.

    Raises:
        MeshError: non-manifold edges (three or more faces), with their count and first vertex pairs.
    """
    # directed half-edges (a -> b) of every face, and the opposite corner c
    a = faces.reshape(-1)
    b = np.roll(faces, -1, axis=1).reshape(-1)
    c = np.roll(faces, -2, axis=1).reshape(-1)
    key = np.sort(np.stack([a, b], axis=1), axis=1)
    uniq, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    bad = np.nonzero(counts > 2)[0]
    if bad.size:
        def where(u):
            at = "" if vertices is None else " at {} - {}".format(*(np.array2string(vertices[i], precision=4, separator=", ") for i in u))
            return f"({int(u[0])}, {int(u[1])}){at}"

        pairs = "; ".join(where(u) for u in uniq[bad[:5]])
        raise MeshError(
            f"mesh is non-manifold: {bad.size} edge(s) are shared by three or more faces "
            f"(max {int(counts.max())}), e.g. between vertices {pairs}"
            + ("; ..." if bad.size > 5 else "")
        )
    order = np.argsort(inverse, kind="stable")
    sorted_edge = inverse[order]
    starts = np.searchsorted(sorted_edge, np.arange(uniq.shape[0]))
    interior_ids = np.nonzero(counts == 2)[0]
    h0 = order[starts[interior_ids]]
    h1 = order[starts[interior_ids] + 1]
    # consistent winding: the two half-edges of an interior edge run in opposite directions
    inconsistent = int(np.count_nonzero(a[h0] == a[h1]))
    interior = np.stack([a[h0], b[h0], c[h0], c[h1]], axis=1).astype(np.int32)
    boundary = uniq[counts == 1].astype(np.int32)
    return EdgeTopology(uniq.astype(np.int32), interior, boundary), inconsistent


@dataclass
class Mesh:
    """A checked triangle mesh.

    Attributes:
        vertices: (V, 3) float32 positions, in the mesh's own units.
        faces: (F, 3) int32 vertex indices, outward winding when the mesh is closed.
        topology: the mesh's :class:`EdgeTopology`.
        name: where it came from, for messages and file names.
    """

    vertices: np.ndarray
    faces: np.ndarray
    topology: EdgeTopology
    name: str = "mesh"
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    @property
    def num_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def num_faces(self) -> int:
        return int(self.faces.shape[0])

    @property
    def is_watertight(self) -> bool:
        """True when every edge has exactly two faces."""
        return self.topology.boundary.shape[0] == 0

    def _memo(self, name: str, compute):
        """``compute()`` once per vertex array: kept while ``self.vertices`` is the same array object (the arrays
        of a Mesh are treated as immutable; assigning a new array recomputes)."""
        hit = self._cache.get(name)
        if hit is None or hit[0] is not self.vertices:
            hit = (self.vertices, compute())
            self._cache[name] = hit
        return hit[1]

    def _kept(self, name: str):
        """What ``_memo(name, ...)`` keeps for the current vertex array, or None (nothing computed)."""
        hit = self._cache.get(name)
        return hit[1] if hit is not None and hit[0] is self.vertices else None

    @property
    def mean_edge_length(self) -> float:
        e = self.topology.edges
        return self._memo("mean_edge_length", lambda: float(
            np.linalg.norm(self.vertices[e[:, 0]] - self.vertices[e[:, 1]], axis=1).mean()))

    @property
    def bbox_diagonal(self) -> float:
        return self._memo("bbox_diagonal",
                          lambda: float(np.linalg.norm(self.vertices.max(0) - self.vertices.min(0))))

    def area(self) -> float:
        v = self.vertices.astype(np.float64)
        f = self.faces
        return float(0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1).sum())

    def volume(self) -> float:
        """Signed volume (positive for outward winding of a closed mesh)."""
        v = self.vertices.astype(np.float64)
        f = self.faces
        return float(np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum() / 6.0)

    def with_vertices(self, vertices: Any) -> "Mesh":
        """The same connectivity with new positions (e.g. a flow step); the topology is shared."""
        v = np.asarray(vertices, dtype=np.float32)
        if v.shape != self.vertices.shape:
            raise MeshError(f"with_vertices: expected shape {self.vertices.shape}, got {v.shape}")
        _check_finite(v, self.name)
        return Mesh(np.ascontiguousarray(v), self.faces, self.topology, self.name)

    def to_trimesh(self):
        import trimesh

        return trimesh.Trimesh(self.vertices.astype(np.float64), self.faces.astype(np.int64), process=False)

    def save(self, path: str | os.PathLike, vertex_colors: np.ndarray | None = None) -> None:
        """Write the mesh (PLY, OBJ, ... by extension); ``vertex_colors`` is (V, 3|4) uint8."""
        tm = self.to_trimesh()
        if vertex_colors is not None:
            tm.visual.vertex_colors = vertex_colors
        tm.export(os.fspath(path))

    def __repr__(self) -> str:
        return f"Mesh({self.name!r}, V={self.num_vertices}, F={self.num_faces}, watertight={self.is_watertight})"


def _check_finite(v: np.ndarray, name: str) -> None:
    bad = np.nonzero(~np.isfinite(v).all(axis=1))[0]
    if bad.size:
        raise MeshError(f"{name}: {bad.size} vertex coordinate row(s) are NaN or infinite, e.g. vertices {_first(bad)}")


def from_arrays(vertices: Any, faces: Any, *, name: str = "mesh", merge: bool = True) -> Mesh:
    """Build a checked :class:`Mesh` from (V, 3) positions and (F, 3) indices.

    Vertices at identical positions are merged (``merge=True``) so texture seams do not read as
    boundaries; unreferenced vertices are dropped; a closed mesh with negative volume is flipped so
    that its normals point outward (the convexity sign of Eq. (1) needs that).

    Raises:
        MeshError: empty mesh, wrong shapes, NaN/inf coordinates, indices out of range, degenerate
            faces (repeated indices or zero area), non-manifold edges, inconsistent winding.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces)
    if v.size == 0 or f.size == 0:
        raise MeshError(f"{name}: empty mesh ({v.reshape(-1, 3).shape[0] if v.size else 0} vertices, "
                        f"{f.reshape(-1, 3).shape[0] if f.size else 0} faces)")
    if v.ndim != 2 or v.shape[1] != 3:
        raise MeshError(f"{name}: vertices must be (V, 3), got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3:
        raise MeshError(f"{name}: faces must be (F, 3) triangles, got {f.shape}")
    if not np.issubdtype(f.dtype, np.integer):
        raise MeshError(f"{name}: faces must be integer indices, got {f.dtype}")
    _check_finite(v, name)
    out = np.nonzero((f < 0).any(1) | (f >= v.shape[0]).any(1))[0]
    if out.size:
        raise MeshError(f"{name}: {out.size} face(s) index vertices outside [0, {v.shape[0]}), e.g. faces {_first(out)}")
    f = f.astype(np.int64)
    if merge:
        # keep the first occurrence's order, so a mesh without duplicates keeps its vertex order
        uniq, first, inv = np.unique(v, axis=0, return_index=True, return_inverse=True)
        order = np.argsort(first)
        rank = np.empty_like(order)
        rank[order] = np.arange(order.size)
        f = rank[inv.reshape(-1)][f]
        v = uniq[order]
    used = np.unique(f)
    if used.size < v.shape[0]:
        remap = np.full(v.shape[0], -1, dtype=np.int64)
        remap[used] = np.arange(used.size)
        v = v[used]
        f = remap[f]
    rep = np.nonzero((f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 2] == f[:, 0]))[0]
    if rep.size:
        raise MeshError(f"{name}: {rep.size} degenerate face(s) repeat a vertex index, e.g. faces {_first(rep)}; "
                        "remove them first (trimesh: mesh.update_faces(mesh.nondegenerate_faces()))")
    scale = float(np.linalg.norm(v.max(0) - v.min(0)))
    area2 = np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    zero = np.nonzero(area2 <= 1e-12 * scale * scale)[0]
    if zero.size:
        raise MeshError(f"{name}: {zero.size} degenerate face(s) have zero area, e.g. faces {_first(zero)}; "
                        "remove them first (trimesh: mesh.update_faces(mesh.nondegenerate_faces()))")
    f = f.astype(np.int32)
    try:
        topo, inconsistent = _build_topology(f, v)
    except MeshError as exc:
        raise MeshError(f"{name}: {exc}") from None
    if inconsistent:
        raise MeshError(f"{name}: inconsistent winding: {inconsistent} interior edge(s) are traversed in the same "
                        "direction by both their faces; fix it first (trimesh.repair.fix_winding)")
    mesh = Mesh(np.ascontiguousarray(v, dtype=np.float32), np.ascontiguousarray(f), topo, name)
    if mesh.is_watertight and mesh.volume() < 0.0:
        f = np.ascontiguousarray(f[:, ::-1])
        topo, _ = _build_topology(f)
        mesh = Mesh(mesh.vertices, f, topo, name)
    return mesh


def load_mesh(source: Any, *, name: str | None = None, merge: bool = True) -> Mesh:
    """Load a :class:`Mesh` from a path (any format trimesh reads), a ``trimesh.Trimesh`` or a Mesh.

    Args:
        source: file path, ``trimesh.Trimesh``, ``(vertices, faces)`` tuple, or :class:`Mesh`.
        name: label used in messages; defaults to the file name.
        merge: merge vertices at identical positions (texture seams).

    Returns:
        The checked mesh; see :func:`from_arrays` for what is checked and repaired.
    """
    if isinstance(source, Mesh):
        return source
    if isinstance(source, tuple) and len(source) == 2:
        return from_arrays(source[0], source[1], name=name or "mesh", merge=merge)
    import trimesh

    if isinstance(source, (str, os.PathLike)):
        path = os.fspath(source)
        if not os.path.exists(path):
            raise FileNotFoundError(f"mesh file not found: {path}")
        try:
            tm = trimesh.load(path, process=False, force="mesh")
        except Exception as exc:  # trimesh raises many types for unreadable files
            raise MeshError(f"{path}: cannot read mesh ({type(exc).__name__}: {exc})") from exc
        name = name or os.path.basename(path)
    elif isinstance(source, trimesh.Trimesh):
        tm = source
        name = name or "trimesh"
    else:
        raise TypeError(f"load_mesh: expected a path, trimesh.Trimesh, (vertices, faces) or Mesh, got {type(source).__name__}")
    if not isinstance(tm, trimesh.Trimesh) or len(tm.faces) == 0:
        raise MeshError(f"{name}: empty mesh (no triangles)")
    return from_arrays(np.asarray(tm.vertices), np.asarray(tm.faces), name=name, merge=merge)
