"""Triangle meshes as the VNC operator sees them: merged vertices, checked topology, outward winding.

Everything in vnc-warp runs on a :class:`Mesh`. :func:`load_mesh` builds one from a file, a ``trimesh.Trimesh``
or a ``(vertices, faces)`` pair and refuses, with a message that says what and where, the inputs on which
Eqs. (1)-(3) are undefined: empty meshes, NaN coordinates, out-of-range indices, degenerate faces,
non-manifold edges (three or more faces) and inconsistent winding. Vertices at one position (texture seams) are
merged so that the surface is one piece; ``Mesh.source_index`` keeps the map from the input's vertices to the
mesh's.

:func:`mesh_input` is the thin layer at the top of every public operator: it turns what a user holds (a
:class:`Mesh`, a ``trimesh.Trimesh``, a ``(V, F)`` pair of NumPy arrays or torch tensors, or a path) into a
:class:`MeshInput`, which hands per-vertex results back the way the user gave the mesh:

========================================  =====================================================================
the caller gave                           per-vertex results come back as
========================================  =====================================================================
a :class:`Mesh`                           Warp arrays on the device that computed them, one row per mesh vertex
a ``trimesh.Trimesh``, a path, or a       NumPy arrays, one row per input vertex (``trimesh.vertices``, the
``(V, F)`` pair of NumPy arrays           file's vertices, ``V``); vertices no face uses get NaN
a ``(V, F)`` pair with ``V`` a tensor     torch tensors on ``V.device``, one row per row of ``V``
========================================  =====================================================================

Numerics do not depend on where a mesh sits: the operators read :attr:`Mesh.local_vertices`, float32 positions
relative to the mesh's own centre :attr:`Mesh.origin`, taken from the input's float64 coordinates.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["Mesh", "EdgeTopology", "MeshError", "MeshInput", "load_mesh", "from_arrays", "mesh_input"]


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
    # one int64 key per undirected edge, min * V + max: it sorts as the (min, max) rows do, so the edges come out
    # in the lexicographic order a row-wise unique gives, without its sort of structured rows (10x slower)
    nv = int(faces.max()) + 1 if faces.size else 1
    lo = np.minimum(a, b).astype(np.int64)
    hi = np.maximum(a, b).astype(np.int64)
    key = lo * nv + hi
    # one stable sort serves both the unique edges and the half-edges of each edge, in face order
    order = np.argsort(key, kind="stable")
    sorted_key = key[order]
    first = np.ones(key.size, dtype=bool)
    first[1:] = sorted_key[1:] != sorted_key[:-1]
    starts = np.nonzero(first)[0]
    counts = np.diff(np.append(starts, key.size))
    ukey = sorted_key[starts]
    uniq = np.stack([ukey // nv, ukey % nv], axis=1)
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
    interior_ids = np.nonzero(counts == 2)[0]
    h0 = order[starts[interior_ids]]
    h1 = order[starts[interior_ids] + 1]
    # consistent winding: the two half-edges of an interior edge run in opposite directions
    inconsistent = int(np.count_nonzero(a[h0] == a[h1]))
    interior = np.stack([a[h0], b[h0], c[h0], c[h1]], axis=1).astype(np.int32)
    boundary = uniq[counts == 1].astype(np.int32)
    return EdgeTopology(uniq.astype(np.int32), interior, boundary), inconsistent


@dataclass(eq=False)
class Mesh:
    """A checked triangle mesh: the data every operator reads (they keep their own state in the mesh's
    :class:`~vnc_warp.Engine`). Two meshes are equal only when they are the same object.

    Attributes:
        vertices: (V, 3) float32 positions, in the mesh's own units.
        faces: (F, 3) int32 vertex indices, outward winding when the mesh is closed.
        topology: the mesh's :class:`EdgeTopology`.
        name: where it came from, for messages and file names.
        source_index: (V_in,) int64, for each vertex of the input the mesh was built from (the file's, the
            trimesh's, the ``V`` of a pair), the mesh vertex it became; -1 for a vertex no face uses. None when
            the input's vertices are the mesh's, in the same order (nothing merged or dropped).
        origin: (3,) float64 centre of the bounding box, the origin of :attr:`local_vertices`; None: computed
            from ``vertices`` when first needed.
    """

    vertices: np.ndarray
    faces: np.ndarray
    topology: EdgeTopology
    name: str = "mesh"
    source_index: np.ndarray | None = field(default=None, repr=False)
    origin: np.ndarray | None = field(default=None, repr=False)
    _derived: dict = field(default_factory=dict, init=False, repr=False)

    def __post_init__(self):
        if self.origin is None:
            v = np.asarray(self.vertices)
            self.origin = 0.5 * (v.min(0).astype(np.float64) + v.max(0).astype(np.float64))

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

    def _derive(self, name: str, compute):
        """``compute()`` once per vertex array: kept while ``self.vertices`` is the same array object (the arrays
        of a Mesh are treated as immutable; assigning a new array recomputes)."""
        hit = self._derived.get(name)
        if hit is None or hit[0] is not self.vertices:
            hit = (self.vertices, compute())
            self._derived[name] = hit
        return hit[1]

    @property
    def local_vertices(self) -> np.ndarray:
        """(V, 3) float32 positions relative to :attr:`origin`: what the operators compute on, so that a mesh far
        from the coordinate origin (a scan in survey coordinates, a part at 1e6 units) loses no precision. Taken
        from the input's float64 coordinates when the mesh was built from them (:func:`from_arrays`)."""
        return self._derive("local_vertices", lambda: (self.vertices.astype(np.float64) - self.origin).astype(np.float32))

    @property
    def mean_edge_length(self) -> float:
        e = self.topology.edges
        return self._derive("mean_edge_length", lambda: float(np.linalg.norm(
            self.local_vertices[e[:, 0]].astype(np.float64) - self.local_vertices[e[:, 1]], axis=1).mean()))

    @property
    def bbox_diagonal(self) -> float:
        v = self.local_vertices
        return self._derive("bbox_diagonal",
                          lambda: float(np.linalg.norm(v.max(0).astype(np.float64) - v.min(0))))

    def area(self) -> float:
        v = self.local_vertices.astype(np.float64)
        f = self.faces
        return float(0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1).sum())

    def volume(self) -> float:
        """Signed volume (positive for outward winding of a closed mesh)."""
        v = self.local_vertices.astype(np.float64)
        f = self.faces
        return float(np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum() / 6.0)

    def with_vertices(self, vertices: Any) -> "Mesh":
        """The same connectivity with new positions (e.g. a flow step); the topology and ``source_index`` are
        shared."""
        v64 = _host_array(vertices).astype(np.float64)
        if v64.shape != self.vertices.shape:
            raise MeshError(f"with_vertices: expected shape {self.vertices.shape}, got {v64.shape}")
        _check_finite(v64, self.name)
        return _mesh(v64, self.faces, self.topology, self.name, self.source_index)

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


def _mesh(v64: np.ndarray, faces: np.ndarray, topology: EdgeTopology, name: str,
          source_index: np.ndarray | None) -> Mesh:
    """A Mesh of float64 positions ``v64``: float32 ``vertices`` and, from the float64 values, the float32
    :attr:`Mesh.local_vertices` about the bounding-box centre."""
    origin = 0.5 * (v64.min(0) + v64.max(0))
    vertices = np.ascontiguousarray(v64, dtype=np.float32)
    mesh = Mesh(vertices, faces, topology, name, source_index, origin)
    mesh._derived["local_vertices"] = (vertices, np.ascontiguousarray(v64 - origin, dtype=np.float32))
    return mesh


def framed_mesh(local: np.ndarray, faces: np.ndarray, topology: EdgeTopology, name: str,
                origin: np.ndarray) -> Mesh:
    """A Mesh of float32 positions ``local`` relative to ``origin`` (a state computed in a frame, as VNC-Flow and
    the remesher do): ``vertices`` are the absolute float32 positions and :attr:`Mesh.local_vertices` is ``local``
    itself, not a float32 round trip through them."""
    origin = np.asarray(origin, dtype=np.float64)
    vertices = np.ascontiguousarray(local.astype(np.float64) + origin, dtype=np.float32)
    mesh = Mesh(vertices, faces, topology, name, origin=origin)
    mesh._derived["local_vertices"] = (vertices, np.ascontiguousarray(local, dtype=np.float32))
    return mesh


def _host_array(a: Any) -> np.ndarray:
    """A NumPy view or copy of an array-like: NumPy, lists, torch tensors on any device, Warp arrays."""
    if hasattr(a, "detach") and hasattr(a, "cpu"):  # torch.Tensor
        return a.detach().cpu().numpy()
    if hasattr(a, "numpy") and hasattr(a, "device") and hasattr(a, "dtype") and not isinstance(a, np.ndarray):
        return a.numpy()  # wp.array
    return np.asarray(a)


def _is_scalar(a: Any) -> bool:
    return a.ndim == 0 if hasattr(a, "ndim") else np.ndim(a) == 0


def _check_finite(v: np.ndarray, name: str) -> None:
    bad = np.nonzero(~np.isfinite(v).all(axis=1))[0]
    if bad.size:
        raise MeshError(f"{name}: {bad.size} vertex coordinate row(s) are NaN or infinite, e.g. vertices {_first(bad)}")


def from_arrays(vertices: Any, faces: Any, *, name: str = "mesh", merge: bool = True) -> Mesh:
    """Build a checked :class:`Mesh` from (V, 3) positions and (F, 3) indices.

    Vertices at identical positions are merged (``merge=True``) so texture seams do not read as
    boundaries; unreferenced vertices are dropped; a closed mesh with negative volume is flipped so
    that its normals point outward (the convexity sign of Eq. (1) needs that). ``Mesh.source_index`` maps each
    input vertex to the mesh vertex it became (-1: dropped).

    Raises:
        MeshError: empty mesh, wrong shapes, NaN/inf coordinates, indices out of range, degenerate
            faces (repeated indices or zero area), non-manifold edges, inconsistent winding.
    """
    v = _host_array(vertices).astype(np.float64)
    f = _host_array(faces)
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
    index = np.arange(v.shape[0], dtype=np.int64)  # input vertex -> mesh vertex
    if merge:
        # keep the first occurrence's order, so a mesh without duplicates keeps its vertex order
        uniq, first, inv = np.unique(v, axis=0, return_index=True, return_inverse=True)
        order = np.argsort(first)
        rank = np.empty_like(order)
        rank[order] = np.arange(order.size)
        index = rank[inv.reshape(-1)]
        f = index[f]
        v = uniq[order]
    used = np.unique(f)
    if used.size < v.shape[0]:
        remap = np.full(v.shape[0], -1, dtype=np.int64)
        remap[used] = np.arange(used.size)
        v = v[used]
        f = remap[f]
        index = remap[index]
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
    identity = index.size == v.shape[0] and bool((index == np.arange(index.size)).all())
    mesh = _mesh(v, np.ascontiguousarray(f), topo, name, None if identity else index)
    if mesh.is_watertight and mesh.volume() < 0.0:
        f = np.ascontiguousarray(f[:, ::-1])
        topo, _ = _build_topology(f)
        mesh = _mesh(v, f, topo, name, mesh.source_index)
    return mesh


def load_mesh(source: Any, *, name: str | None = None, merge: bool = True) -> Mesh:
    """Load a :class:`Mesh` from a path (any format trimesh reads), a ``trimesh.Trimesh`` or a Mesh.

    Args:
        source: file path, ``trimesh.Trimesh``, ``(vertices, faces)`` pair (NumPy arrays, lists or torch
            tensors), or :class:`Mesh` (returned as it is).
        name: label used in messages; defaults to the file name.
        merge: merge vertices at identical positions (texture seams).

    Returns:
        The checked mesh; see :func:`from_arrays` for what is checked and repaired. ``mesh.source_index`` maps
        the source's vertices (the file's, in the file's order) to the mesh's.
    """
    if isinstance(source, Mesh):
        return source
    if isinstance(source, (tuple, list)) and len(source) == 2:
        return from_arrays(source[0], source[1], name=name or "mesh", merge=merge)
    import trimesh

    if isinstance(source, (str, os.PathLike)):
        path = os.fspath(source)
        if not os.path.exists(path):
            raise FileNotFoundError(f"mesh file not found: {path}")
        try:
            # maintain_order: the file's own vertices, in its order (OBJ texture seams are not split)
            tm = trimesh.load(path, process=False, force="mesh", maintain_order=True)
        except Exception as exc:  # trimesh raises many types for unreadable files
            raise MeshError(f"{path}: cannot read mesh ({type(exc).__name__}: {exc})") from exc
        name = name or os.path.basename(path)
    elif isinstance(source, trimesh.Trimesh):
        tm = source
        name = name or "trimesh"
    else:
        raise TypeError(f"expected a vw.Mesh, a trimesh.Trimesh, a (vertices, faces) pair or a path, "
                        f"got {type(source).__name__}")
    if not isinstance(tm, trimesh.Trimesh) or len(tm.faces) == 0:
        raise MeshError(f"{name}: empty mesh (no triangles)")
    return from_arrays(np.asarray(tm.vertices), np.asarray(tm.faces), name=name, merge=merge)


KINDS = ("warp", "numpy", "torch")


@dataclass(frozen=True)
class MeshInput:
    """A public function's mesh argument as a :class:`Mesh`, and the way its per-vertex results go back.

    Made by :func:`mesh_input`; see the module docstring for the rule.

    Attributes:
        mesh: the checked mesh the computation runs on (vertices merged, unused ones dropped).
        index: (V_in,) int64: for each of the caller's vertices the mesh vertex it became (-1: no face uses it);
            None when the caller's vertices are the mesh's.
        kind: "warp" (the caller gave a :class:`Mesh`), "numpy" or "torch".
        torch_device: the device of the caller's tensor (kind "torch"), else None.
    """

    mesh: Mesh
    index: np.ndarray | None
    kind: str
    torch_device: Any = None

    @property
    def device(self):
        """The device to compute on when the caller names none: the tensor's (kind "torch"), else None."""
        return self.torch_device

    @property
    def num_input_vertices(self) -> int:
        return self.mesh.num_vertices if self.index is None else int(self.index.size)

    def to_mesh_vertices(self, values: Any, what: str) -> Any:
        """Per-vertex values given per caller vertex ((V_in,) array-like) as (V,) per mesh vertex (the first input
        vertex of each merged one speaks for it); scalars, Warp arrays and per-mesh-vertex arrays pass as they are."""
        import warp as wp

        if self.index is None or values is None or isinstance(values, wp.array) or _is_scalar(values):
            return values
        arr = _host_array(values)
        if arr.shape[:1] == (self.mesh.num_vertices,) and arr.shape[0] != self.index.size:
            return arr
        if arr.shape[:1] != (self.index.size,):
            raise ValueError(f"{what}: expected a scalar or one value per vertex ({self.index.size},), got "
                             f"shape {arr.shape}")
        valid = np.nonzero(self.index >= 0)[0]
        _, first = np.unique(self.index[valid], return_index=True)
        return arr[valid[first]]

    def per_point(self, values):
        """A result with one row per query point (no vertex map), in the caller's kind."""
        return self._answer(values, None, 0)

    def per_vertex(self, values, *, axis: int = 0):
        """A result computed per mesh vertex (a Warp array whose ``axis`` runs over the vertices) as the caller
        gets it: the Warp array itself (kind "warp"), or one row per caller vertex as NumPy or torch, NaN for
        vertices no face uses."""
        return self._answer(values, self.index, axis)

    def _answer(self, values, index: np.ndarray | None, axis: int):
        if self.kind == "warp":
            return values
        if self.kind == "numpy":
            a = values.numpy()
            if index is None:
                return a.copy() if values.device.is_cpu else a  # a CPU array's .numpy() is a view of it
            out = np.take(a, np.maximum(index, 0), axis=axis)
            if (index < 0).any():
                out[(slice(None),) * (axis % out.ndim) + (index < 0,)] = np.nan
            return out
        import torch
        import warp as wp

        t = wp.to_torch(values) if values.device.is_cuda else torch.from_numpy(values.numpy())
        if index is None:
            return t.to(self.torch_device).clone()
        idx = torch.as_tensor(index, device=t.device)
        out = torch.index_select(t, axis, idx.clamp(min=0))
        if (index < 0).any():
            shape = [1] * out.ndim
            shape[axis] = -1
            out = torch.where((idx < 0).reshape(shape), torch.full_like(out, float("nan")), out)
        return out.to(self.torch_device)


def mesh_input(source: Any, *, name: str | None = None) -> MeshInput:
    """What a user holds, as a :class:`MeshInput`: the :class:`Mesh` to compute on and how results go back.

    Args:
        source: a :class:`Mesh`; a ``trimesh.Trimesh``; a ``(V, F)`` pair of (V, 3) positions and (F, 3) indices
            (NumPy arrays, lists or torch tensors); or a path to any file trimesh reads (its vertices in the file's
            order).
        name: label used in messages.

    Returns:
        The :class:`MeshInput`; kind "warp" for a Mesh, "torch" for a pair whose ``V`` is a tensor, else "numpy".

    Raises:
        TypeError: anything else. MeshError, FileNotFoundError: see :func:`load_mesh`.
    """
    if isinstance(source, Mesh):
        return MeshInput(source, None, "warp")
    if isinstance(source, (tuple, list)) and len(source) == 2 and hasattr(source[0], "detach"):
        mesh = from_arrays(source[0], source[1], name=name or "tensor mesh")
        return MeshInput(mesh, mesh.source_index, "torch", source[0].device)
    mesh = load_mesh(source, name=name)
    return MeshInput(mesh, mesh.source_index, "numpy")
