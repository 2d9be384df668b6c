"""The operators take what users hold and answer per input vertex; results do not depend on where the mesh sits;
degenerate calls warn once with the reason.

Oracles: a per-position lookup (a vertex's value is the value at its position on the merged mesh, found without
``source_index``), the Mesh path itself for the kinds of result, a merged-mesh torch computation for gradients
on a seamed mesh, and the untranslated, unscaled unit sphere for the invariance tests.
"""

import warnings

import numpy as np
import pytest
import torch
import trimesh
import warp as wp
from conftest import mesh_path

import vnc_warp as vw
import vnc_warp.torch as vt
from vnc_warp._checks import _warned
from vnc_warp.operators import DegenerateResultWarning


@pytest.fixture(scope="module")
def seamed():
    """The bundled Spot as trimesh loads it by default: its vertices split at texture seams (3,225 rows, 2,930
    positions), and its merged Mesh."""
    tm = trimesh.load(mesh_path("spot_lowres.obj"), process=False, force="mesh")
    assert len(tm.vertices) == 3225
    return tm, vw.load_mesh(tm)


def _by_position(tm, mesh, values):
    """Per trimesh row, the value of the merged mesh's vertex at the same position (a dictionary lookup)."""
    at = {tuple(p): k for k, p in enumerate(mesh.vertices.tolist())}
    rows = [at[tuple(p)] for p in np.asarray(tm.vertices, np.float32).tolist()]
    return values[rows]


def test_trimesh_gets_one_numpy_row_per_vertex(seamed):
    """vnc_soft, vnc_hard, Eq. (1) and scale_curve of a trimesh return NumPy arrays with one row per
    trimesh.vertices row: the merged mesh's value at that row's position."""
    tm, mesh = seamed
    tau = 4 * mesh.mean_edge_length
    H, n = vw.vnc_soft(tm, tau, device="cpu")
    assert isinstance(H, np.ndarray) and H.shape == (3225,) and n.shape == (3225, 3)
    Hm, nm = vw.vnc_soft(mesh, tau, device="cpu")
    np.testing.assert_array_equal(H, _by_position(tm, mesh, Hm.numpy()))
    np.testing.assert_array_equal(n, _by_position(tm, mesh, nm.numpy()))
    Hh, _ = vw.vnc_hard(tm, tau, device="cpu")
    np.testing.assert_array_equal(Hh, _by_position(tm, mesh, vw.vnc_hard(mesh, tau, device="cpu")[0].numpy()))
    I = vw.integrated_mean_curvature(tm, tau, device="cpu")
    np.testing.assert_array_equal(I, _by_position(tm, mesh, vw.integrated_mean_curvature(mesh, tau, device="cpu").numpy()))
    taus = vw.default_scales(tm, 4)
    np.testing.assert_array_equal(taus, vw.default_scales(mesh, 4))
    curve = vw.scale_curve(tm, taus, device="cpu")
    ref = vw.scale_curve(mesh, taus, device="cpu")
    assert isinstance(curve.H, np.ndarray) and curve.H.shape == (4, 3225)
    np.testing.assert_array_equal(curve.H, _by_position(tm, mesh, ref.H.numpy().T).T)
    np.testing.assert_array_equal(curve.mean, ref.mean.numpy())
    s = vw.vnc_auc(curve)
    assert isinstance(s, np.ndarray) and s.shape == (3225,)
    np.testing.assert_array_equal(s, _by_position(tm, mesh, vw.vnc_auc(ref).numpy()))
    phi = 0.5 * float(s.mean())
    np.testing.assert_array_equal(vw.adaptive_scale(curve, phi=phi),
                                  _by_position(tm, mesh, vw.adaptive_scale(ref, phi=phi).numpy()))


def test_every_input_kind(seamed, tmp_path, device):
    """A Mesh gets Warp arrays (as before), a trimesh, a (V, F) NumPy pair and a path get NumPy, a (V, F) pair of
    tensors gets tensors on V's device; all hold the same values per input vertex."""
    tm, mesh = seamed
    tau = 3 * mesh.mean_edge_length
    path = tmp_path / "spot.ply"
    tm.export(path)  # PLY keeps trimesh's 3,225 rows in order
    H_mesh = vw.vnc_soft(mesh, tau, device=device)[0]
    assert isinstance(H_mesh, wp.array) and str(H_mesh.device) == device
    expect = _by_position(tm, mesh, H_mesh.numpy())
    for given in (tm, (np.asarray(tm.vertices), np.asarray(tm.faces)), str(path), path):
        H = vw.vnc_soft(given, tau, device=device)[0]
        assert isinstance(H, np.ndarray)
        np.testing.assert_allclose(H, expect, atol=1e-6)  # the PLY holds float32 positions
    tdev = torch.device("cuda:0" if device.startswith("cuda") else "cpu")
    V = torch.tensor(tm.vertices, device=tdev)
    F = torch.tensor(tm.faces, device=tdev)
    for op in (vw.vnc_soft, vw.vnc_hard):
        H, n = op((V, F), tau)
        assert isinstance(H, torch.Tensor) and H.device == V.device and H.shape == (3225,) and n.shape == (3225, 3)
    I = vw.integrated_mean_curvature((V, F), tau)
    assert isinstance(I, torch.Tensor) and I.device == V.device
    curve = vw.scale_curve((V, F), [tau, 2 * tau])
    assert isinstance(curve.H, torch.Tensor) and curve.H.shape == (2, 3225) and curve.H.device == V.device
    s = vw.vnc_auc(curve)
    assert isinstance(s, torch.Tensor) and s.shape == (3225,) and s.device == V.device
    np.testing.assert_allclose(curve.H[0].cpu().numpy(), vw.vnc_soft((V, F), tau)[0].cpu().numpy(), atol=1e-6)
    np.testing.assert_allclose(vw.vnc_soft((V, F), tau)[0].cpu().numpy(), expect, atol=1e-6)


def test_numpy_and_torch_paths_agree_on_a_seamed_mesh(seamed):
    """On the seamed Spot the differentiable torch op and the NumPy path give the same H and n per input row to
    1e-5 (before the merge the torch op saw a mesh cut open at the seams)."""
    tm, mesh = seamed
    for k in (2.0, 6.0, 20.0):
        tau = k * mesh.mean_edge_length
        H, n = vw.vnc_soft(tm, tau, device="cpu")
        Ht, nt = vt.vnc_soft(torch.tensor(tm.vertices, dtype=torch.float32), tm.faces, tau)
        assert Ht.shape == (3225,)
        np.testing.assert_allclose(Ht.numpy(), H, atol=1e-5, rtol=0)
        np.testing.assert_allclose(nt.numpy(), n, atol=1e-5, rtol=0)


def test_torch_gradient_is_shared_by_seam_rows(seamed):
    """The gradient through the seamed rows equals the merged mesh's gradient split equally among the rows of each
    vertex, and the answer is the same for a Mesh given by its merged or its input rows."""
    tm, mesh = seamed
    tau = 4 * mesh.mean_edge_length
    rows = torch.tensor(tm.vertices, dtype=torch.float32, requires_grad=True)
    H, _ = vt.vnc_soft(rows, tm, tau)
    (H ** 2).sum().backward()
    merged = torch.tensor(mesh.vertices, requires_grad=True)
    Hm, _ = vt.vnc_soft(merged, mesh, tau)
    counts = np.bincount(mesh.source_index, minlength=mesh.num_vertices)
    (Hm[torch.as_tensor(mesh.source_index)] ** 2).sum().backward()
    expect = merged.grad.numpy()[mesh.source_index] / counts[mesh.source_index, None]
    np.testing.assert_allclose(rows.grad.numpy(), expect, rtol=1e-4, atol=1e-6 * np.abs(expect).max())
    H2, _ = vt.vnc_soft(rows.detach(), mesh, tau)  # a Mesh with its input's rows
    np.testing.assert_allclose(H2.numpy(), H.detach().numpy(), atol=1e-6)


def test_unused_vertices_get_nan_and_per_vertex_tau_maps():
    """A vertex no face uses gets NaN; a per-input-vertex tau is read at each merged vertex's first row."""
    sphere = trimesh.creation.icosphere(2)
    v = np.vstack([sphere.vertices, [[5.0, 5.0, 5.0]]])
    H, n = vw.vnc_soft((v, sphere.faces), 0.4, device="cpu")
    assert H.shape == (v.shape[0],) and np.isnan(H[-1]) and np.isnan(n[-1]).all() and np.isfinite(H[:-1]).all()
    tau = np.full(v.shape[0], 0.4)
    np.testing.assert_array_equal(vw.vnc_soft((v, sphere.faces), tau, device="cpu")[0][:-1], H[:-1])
    with pytest.raises(ValueError, match="one value per vertex"):
        vw.vnc_soft((v, sphere.faces), np.ones(5), device="cpu")
    with pytest.raises(TypeError, match="vw.Mesh"):
        vw.vnc_soft(sphere, 0.4, positions=wp.zeros(162, dtype=wp.vec3, device="cpu"))
    with pytest.raises(TypeError, match="trimesh.Trimesh"):
        vw.vnc_soft(42, 0.4)


def test_flow_takes_every_input_kind(tmp_path):
    """vw.flow accepts a Mesh, a trimesh, a (V, F) pair (NumPy and torch) and a path: the same stage 0. The file is
    a binary PLY, which stores the coordinates exactly: an OBJ rounds them in the 8th digit, enough to change the
    decimation's tie-breaks and with them stage 0's tessellation."""
    tm = trimesh.creation.icosphere(2)
    tm.vertices *= np.array([1.0, 0.7, 0.5])
    path = tmp_path / "ellipsoid.ply"
    tm.export(path)
    kw = dict(stages=1, faces=300, device="cpu", progress=False, max_iters=2, substage_budget=1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the single short stage stops at its iteration cap
        first = [vw.flow(given, **kw).meshes[0] for given in (
            vw.load_mesh(tm), tm, (tm.vertices, tm.faces), (torch.tensor(tm.vertices), torch.tensor(tm.faces)),
            str(path))]
    for m in first[1:]:
        np.testing.assert_allclose(m.vertices, first[0].vertices, atol=1e-5 * first[0].bbox_diagonal)
        np.testing.assert_array_equal(m.faces, first[0].faces)


def _sphere():
    tm = trimesh.creation.icosphere(3)
    return np.asarray(tm.vertices), np.asarray(tm.faces)


@pytest.mark.parametrize("offset", [1e4, 1e6, 1e7])
def test_translation_does_not_change_results(offset, device):
    """A unit sphere moved by ``offset`` along (1, -2, 3)/|.| gives the same VNC-soft, VNC-hard, Eq. (1) and scale
    curve as at the origin, to < 1e-4 relative (float32 absolute coordinates were off by 3.5 % at 1e4 and gave
    H in [-0.065, 0.132] instead of [0.0426, 0.0465] at 1e6); also through the torch op with a float64 tensor."""
    v, f = _sphere()
    shift = offset * np.array([1.0, -2.0, 3.0]) / np.sqrt(14.0)
    a, b = (vw.from_arrays(x, f) for x in (v, v + shift))
    tau = 4 * a.mean_edge_length
    assert abs(b.mean_edge_length - a.mean_edge_length) < 1e-6 * a.mean_edge_length
    for op in (lambda m: vw.vnc_soft(m, tau, device=device)[0], lambda m: vw.vnc_hard(m, tau, device=device)[0],
               lambda m: vw.integrated_mean_curvature(m, tau, device=device),
               lambda m: vw.scale_curve(m, [tau, 3 * tau], device=device).H):
        ref, got = op(a).numpy(), op(b).numpy()
        assert np.abs(got - ref).max() < 1e-4 * np.abs(ref).max()
    ref = vw.vnc_soft(a, tau, device=device)[0].numpy()
    assert 0.04 < ref.min() and ref.max() < 0.05
    pts = v[::7] + 0.01
    np.testing.assert_allclose(vw.integrated_mean_curvature(b, tau, pts + shift, device=device).numpy(),
                               vw.integrated_mean_curvature(a, tau, pts, device=device).numpy(),
                               rtol=1e-4, atol=1e-5 * tau)
    tdev = "cuda:0" if device.startswith("cuda") else "cpu"
    Ht, _ = vt.vnc_soft(torch.tensor(v + shift, device=tdev), torch.tensor(f, device=tdev), tau)
    assert np.abs(Ht.cpu().numpy() - ref).max() < 1e-4 * np.abs(ref).max()


@pytest.mark.parametrize("scale", [1e-6, 1e-3, 1e3, 1e6])
def test_scale_does_not_change_results(scale, device):
    """A unit sphere scaled by 1e-6 .. 1e6 (about a point far from the origin) gives the same dimensionless H and
    n, and Eq. (1) in proportion to the scale, to < 1e-4 relative."""
    v, f = _sphere()
    a, b = vw.from_arrays(v, f), vw.from_arrays((v + 10.0) * scale, f)
    tau = 4 * a.mean_edge_length
    for variant in (vw.vnc_soft, vw.vnc_hard):
        (Ha, na), (Hb, nb) = variant(a, tau, device=device), variant(b, tau * scale, device=device)
        assert np.abs(Hb.numpy() - Ha.numpy()).max() < 1e-4 * np.abs(Ha.numpy()).max()
        assert np.abs(nb.numpy() - na.numpy()).max() < 1e-4
    Ia = vw.integrated_mean_curvature(a, tau, device=device).numpy()
    Ib = vw.integrated_mean_curvature(b, tau * scale, device=device).numpy() / scale
    assert np.abs(Ib - Ia).max() < 1e-4 * np.abs(Ia).max()


def test_degenerate_calls_warn_once_with_the_reason():
    """A tau below every edge midpoint's distance, or kappa = 1000, gives H = 0 everywhere: one warning per operator
    and reason names it; a flat plane (H = 0 for a good reason) and ordinary calls do not warn."""
    _warned.clear()
    tm = trimesh.creation.icosphere(2)
    mesh = vw.load_mesh(tm)
    tiny = 0.05 * mesh.mean_edge_length
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        H, _ = vw.vnc_soft(tm, tiny, device="cpu")
        vw.vnc_soft(tm, tiny, device="cpu")
        vw.vnc_soft(mesh, 4 * mesh.mean_edge_length, kappa=1000.0, device="cpu")
        vw.vnc_hard(mesh, 4 * mesh.mean_edge_length, kappa=1000.0, device="cpu")
        vw.scale_curve(mesh, [tiny, 4 * mesh.mean_edge_length], device="cpu")
        vw.vnc_soft(mesh, 4 * mesh.mean_edge_length, device="cpu")
        x, y = np.meshgrid(np.linspace(0, 1, 12), np.linspace(0, 1, 12))
        plane = trimesh.Trimesh(np.c_[x.ravel(), y.ravel(), np.zeros(144)], _grid_faces(12), process=False)
        Hp, _ = vw.vnc_soft(plane, 0.3, device="cpu")
    assert not np.any(H) and not np.any(Hp)
    messages = [str(w.message) for w in caught if issubclass(w.category, DegenerateResultWarning)]
    assert len(messages) == 4, messages
    assert "vnc_soft" in messages[0] and "no edge is within reach" in messages[0]
    assert "vnc_soft" in messages[1] and "kappa = 1000" in messages[1] and "underflows" in messages[1]
    assert "vnc_hard" in messages[2] and "kappa = 1000" in messages[2]
    assert "scale_curve" in messages[3] and "taus[0]" in messages[3] and "no edge is within reach" in messages[3]


def _grid_faces(n: int) -> np.ndarray:
    """Two triangles per cell of an n x n grid of vertices (row-major), counter-clockwise seen from +z."""
    k = np.arange(n * n).reshape(n, n)[:-1, :-1].ravel()
    return np.concatenate([np.c_[k, k + 1, k + n + 1], np.c_[k, k + n + 1, k + n]])
