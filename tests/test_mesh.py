"""load_mesh / from_arrays: checked topology and clear errors that say what is wrong and where."""

import numpy as np
import pytest
import trimesh
from conftest import mesh_path, open_scan

import vnc_warp as vw


def test_texture_seams_are_merged():
    """trimesh splits spot.obj's vertices at its texture seams (3,225 rows); load_mesh merges them into a closed
    mesh with the documented counts, and source_index maps every trimesh row to the vertex at its position."""
    tm = trimesh.load(mesh_path("spot_lowres.obj"), process=False, force="mesh")
    assert len(tm.vertices) == 3225
    mesh = vw.load_mesh(tm)
    assert (mesh.num_vertices, mesh.num_faces) == (2930, 5856)
    assert mesh.source_index.shape == (3225,) and mesh.source_index.min() == 0
    np.testing.assert_array_equal(mesh.vertices[mesh.source_index], np.asarray(tm.vertices, np.float32))
    assert vw.load_mesh(mesh_path("spot_lowres.obj")).source_index is None  # the file's own vertices: no map
    assert mesh.is_watertight and mesh.volume() > 0
    assert mesh.vertices.dtype == np.float32 and mesh.faces.dtype == np.int32
    assert mesh.topology.num_interior == 3 * mesh.num_faces // 2


def test_interior_edge_layout_is_consistent():
    """Each interior edge (a, b, c0, c1) has face (a, b, c0) and face (b, a, c1) in the mesh's winding."""
    mesh = vw.load_mesh(mesh_path("penguin.obj"))
    faces = {tuple(np.roll(f, -i)) for f in mesh.faces.tolist() for i in range(3)}
    for a, b, c0, c1 in mesh.topology.interior[::97].tolist():
        assert (a, b, c0) in faces and (b, a, c1) in faces


def test_open_mesh_loads_with_boundary():
    """A scan with holes loads (boundary edges counted, not interior) and is reported as not watertight."""
    mesh = vw.load_mesh(open_scan())
    assert not mesh.is_watertight
    assert mesh.topology.boundary.shape[0] > 0


def test_empty_mesh():
    """An empty mesh is refused with 'empty'."""
    with pytest.raises(vw.MeshError, match="empty"):
        vw.from_arrays(np.zeros((0, 3)), np.zeros((0, 3), int))
    with pytest.raises(vw.MeshError, match="empty"):
        vw.load_mesh(trimesh.Trimesh())


def test_nan_coordinates_are_located():
    """NaN coordinates are refused with their count and vertex indices."""
    tm = trimesh.creation.icosphere(1)
    v = tm.vertices.copy()
    v[[4, 9]] = np.nan
    with pytest.raises(vw.MeshError, match=r"2 vertex .*NaN.*4, 9"):
        vw.from_arrays(v, tm.faces)


def test_non_manifold_edge_is_counted():
    """Three faces on one edge: refused, naming the count and the vertex pair."""
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1]], float)
    f = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])
    with pytest.raises(vw.MeshError, match=r"non-manifold: 1 edge.*at \[0\., 0\., 0\.\] - \[1\., 0\., 0\.\]"):
        vw.from_arrays(v, f)


def test_inconsistent_winding_is_counted():
    """One face flipped inside a closed mesh: refused with the number of inconsistent edges."""
    tm = trimesh.creation.icosphere(1)
    f = tm.faces.copy()
    f[0] = f[0][::-1]
    with pytest.raises(vw.MeshError, match=r"inconsistent winding: 3 interior edge"):
        vw.from_arrays(tm.vertices, f)


def test_degenerate_faces_are_located():
    """Faces repeating an index or with zero area are refused with their indices."""
    tm = trimesh.creation.icosphere(1)
    f = tm.faces.copy()
    f[5] = [f[5][0], f[5][0], f[5][1]]
    with pytest.raises(vw.MeshError, match=r"degenerate.*repeat.*faces 5"):
        vw.from_arrays(tm.vertices, f)
    v = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0]], float)
    with pytest.raises(vw.MeshError, match=r"zero area.*faces 0"):
        vw.from_arrays(v, np.array([[0, 1, 2], [0, 1, 3]]))


def test_index_out_of_range_and_bad_shapes():
    """Indices outside the vertex range and non-triangle faces are refused."""
    v = np.eye(3)
    with pytest.raises(vw.MeshError, match="outside"):
        vw.from_arrays(v, np.array([[0, 1, 3]]))
    with pytest.raises(vw.MeshError, match=r"\(F, 3\)"):
        vw.from_arrays(v, np.array([[0, 1, 2, 0]]))


def test_missing_file_and_unreadable_file(tmp_path):
    """A missing path raises FileNotFoundError; a garbage file raises MeshError naming the file."""
    with pytest.raises(FileNotFoundError):
        vw.load_mesh(tmp_path / "nope.obj")
    p = tmp_path / "junk.ply"
    p.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 99\nend_header\n\x00")
    with pytest.raises((vw.MeshError, FileNotFoundError), match="junk.ply"):
        vw.load_mesh(p)


def test_no_interior_edges():
    """A single triangle has no interior edge: VNC refuses it with a clear message."""
    mesh = vw.from_arrays(np.eye(3), np.array([[0, 1, 2]]))
    with pytest.raises(vw.MeshError, match="no interior edges"):
        vw.vnc_soft(mesh, 1.0, device="cpu")


def test_merging_keeps_vertex_order():
    """A mesh without duplicate vertices keeps its vertex order (per-vertex results map back to the file);
    duplicates are merged into their first occurrence."""
    tm = trimesh.creation.icosphere(2)
    perm = np.random.default_rng(0).permutation(len(tm.vertices))
    v, f = tm.vertices[perm], np.argsort(perm)[tm.faces]
    mesh = vw.from_arrays(v, f)
    np.testing.assert_array_equal(mesh.vertices, v.astype(np.float32))
    dup = np.concatenate([v, v[:1]])
    f2 = f.copy()
    f2[f2 == 0] = len(v)
    np.testing.assert_array_equal(vw.from_arrays(dup, f2).vertices, v.astype(np.float32))


def _row_unique_topology(faces):
    """The edge topology as a row-wise ``np.unique`` over sorted vertex pairs gives it (the reference)."""
    a = faces.reshape(-1)
    b = np.roll(faces, -1, axis=1).reshape(-1)
    c = np.roll(faces, -2, axis=1).reshape(-1)
    uniq, inverse, counts = np.unique(np.sort(np.stack([a, b], 1), 1), axis=0, return_inverse=True,
                                      return_counts=True)
    order = np.argsort(inverse.reshape(-1), kind="stable")
    starts = np.searchsorted(inverse.reshape(-1)[order], np.arange(uniq.shape[0]))
    ids = np.nonzero(counts == 2)[0]
    h0, h1 = order[starts[ids]], order[starts[ids] + 1]
    return uniq, np.stack([a[h0], b[h0], c[h0], c[h1]], 1), uniq[counts == 1], int(np.count_nonzero(a[h0] == a[h1]))


@pytest.mark.parametrize("case", ["closed", "open", "inconsistent"])
def test_edge_topology_matches_row_unique(case):
    """_build_topology's single 1-D sort gives the edges, interior layout, boundary and inconsistent count in the
    same order as a row-wise unique (the order VNC-Flow's sums over edges and its resumed runs depend on)."""
    from vnc_warp.mesh import _build_topology

    f = np.asarray(trimesh.creation.icosphere(2).faces, np.int32)
    if case == "open":
        f = f[7:]
    elif case == "inconsistent":
        f = f.copy()
        f[[3, 50, 200]] = f[[3, 50, 200], ::-1]
    topo, inconsistent = _build_topology(f)
    edges, interior, boundary, bad = _row_unique_topology(f)
    np.testing.assert_array_equal(topo.edges, edges)
    np.testing.assert_array_equal(topo.interior, interior)
    np.testing.assert_array_equal(topo.boundary, boundary)
    assert inconsistent == bad and (bad > 0) == (case == "inconsistent") and (boundary.size > 0) == (case == "open")


@pytest.mark.parametrize("offset", [0, 2**22])
def test_double_faces_dropped_at_any_index_range(offset):
    """_drop_double_faces removes both faces of every vertex triple used twice (either winding) and keeps the
    rest, with indices small enough for its one-key path and beyond it."""
    from vnc_warp.remesh import _drop_double_faces

    f = np.array([[0, 1, 2], [2, 1, 0], [1, 2, 3], [3, 4, 5], [4, 5, 3], [0, 4, 6]], np.int64) + offset
    np.testing.assert_array_equal(_drop_double_faces(f), f[[2, 5]])
