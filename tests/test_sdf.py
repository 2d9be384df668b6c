"""Signed distance queries (vnc_warp.sdf) against analytic spheres and trimesh closest points."""

import numpy as np
import pytest
import trimesh
import warp as wp

from vnc_warp.sdf import sdf_grid, signed_distance


def _sphere(radius: float) -> trimesh.Trimesh:
    return trimesh.creation.icosphere(subdivisions=4, radius=radius)


def _points(radius: float, n: int = 1500, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    box = rng.uniform(-2.0 * radius, 2.0 * radius, (n, 3))
    # half of them within 5% of the surface, where sign and distance are hardest
    dirs = rng.normal(size=(n, 3))
    shell = dirs / np.linalg.norm(dirs, axis=1, keepdims=True) * radius * rng.uniform(0.95, 1.05, (n, 1))
    return np.concatenate([box, shell])


@pytest.mark.parametrize("radius", [0.15, 500.0])
@pytest.mark.parametrize("sign", ["winding", "normal"])
def test_sphere_matches_analytic(device, radius, sign):
    """|d - (|p| - r)| is within the icosphere's deviation from the sphere, with the right sign, at two scales."""
    s = _sphere(radius)
    p = _points(radius)
    d = signed_distance((s.vertices, s.faces), p, device=device, sign=sign)
    assert isinstance(d, wp.array) and d.dtype == wp.float32 and d.device == wp.get_device(device)
    d = d.numpy()
    ref = np.linalg.norm(p, axis=1) - radius
    # the subdivision-4 icosphere lies within 0.2% of r of the true sphere
    tol = 2e-3 * radius
    assert np.abs(d - ref).max() < tol
    clear = np.abs(ref) > tol
    assert np.array_equal(np.sign(d[clear]), np.sign(ref[clear]))


def test_max_dist_clamps_but_keeps_sign(device):
    """With max_dist, far points get +-max_dist with the exact sign and near points are unchanged."""
    r = 1.0
    s = _sphere(r)
    p = _points(r, n=500)
    d = signed_distance((s.vertices, s.faces), p, device=device, max_dist=0.1).numpy()
    ref = np.clip(np.linalg.norm(p, axis=1) - r, -0.1, 0.1)
    assert np.abs(d - ref).max() < 2e-3
    assert np.abs(d).max() <= 0.1 + 1e-6
    centre = signed_distance((s.vertices, s.faces), np.zeros((1, 3)), device=device, max_dist=0.1).numpy()
    assert centre[0] == pytest.approx(-0.1)


def test_winding_sign_through_a_hole(device):
    """A sphere with a cap cut away (open): the winding sign still puts the inside ball negative and the
    outside positive, and the magnitudes equal trimesh's closest-point distances."""
    r = 1.0
    s = _sphere(r)
    keep = s.triangles_center[:, 2] < 0.8 * r
    open_sphere = trimesh.Trimesh(s.vertices, s.faces[keep], process=True)
    assert not open_sphere.is_watertight
    rng = np.random.default_rng(1)
    dirs = rng.normal(size=(1200, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    inside = dirs[:600] * rng.uniform(0.0, 0.6 * r, (600, 1))
    outside = dirs[600:] * rng.uniform(1.2 * r, 2.0 * r, (600, 1))
    # the points nearest the hole, on its axis, are the ones the hole makes ambiguous
    axis = np.array([[0.0, 0.0, z] for z in np.linspace(0.0, 0.6 * r, 7)]
                    + [[0.0, 0.0, z] for z in np.linspace(1.2 * r, 2.0 * r, 5)])
    p = np.concatenate([inside, axis[:7], outside, axis[7:]])
    n_in = 607
    d = signed_distance((open_sphere.vertices, open_sphere.faces), p, device=device, sign="winding").numpy()
    assert (d[:n_in] < 0.0).all()
    assert (d[n_in:] > 0.0).all()
    _, dist, _ = trimesh.proximity.closest_point(open_sphere, p)
    np.testing.assert_allclose(np.abs(d), dist, rtol=1e-4, atol=1e-5 * r)


def test_torch_in_torch_out(device):
    """A float32 torch tensor is read in place and a torch tensor on its device comes back; other dtypes raise."""
    torch = pytest.importorskip("torch")
    if device.startswith("cuda") and not torch.cuda.is_available():
        pytest.skip("torch has no CUDA here")
    r = 0.5
    s = _sphere(r)
    p = _points(r, n=300)
    t = torch.tensor(p, dtype=torch.float32, device=device)
    d = signed_distance((s.vertices, s.faces), t)
    assert isinstance(d, torch.Tensor) and d.dtype == torch.float32 and d.shape == (p.shape[0],)
    assert d.device == t.device
    ref = np.linalg.norm(p.astype(np.float32), axis=1) - r
    assert np.abs(d.cpu().numpy() - ref).max() < 2e-3 * r
    # a strided view (every other point) is consumed too
    d2 = signed_distance((s.vertices, s.faces), t[::2])
    np.testing.assert_array_equal(d2.cpu().numpy(), d.cpu().numpy()[::2])
    with pytest.raises(TypeError, match="float32"):
        signed_distance((s.vertices, s.faces), t.double())


def test_warp_array_inputs(device):
    """(N, 3) float32 and (N,) vec3 Warp arrays give the same distances as NumPy input; bad arguments raise."""
    r = 2.0
    s = _sphere(r)
    mesh = (s.vertices, s.faces)
    p = _points(r, n=200).astype(np.float32)
    ref = signed_distance(mesh, p, device=device).numpy()
    a = wp.array(p, dtype=wp.float32, device=device)
    b = wp.array(p, dtype=wp.vec3, device=device)
    np.testing.assert_array_equal(signed_distance(mesh, a).numpy(), ref)
    np.testing.assert_array_equal(signed_distance(mesh, b).numpy(), ref)
    with pytest.raises(ValueError, match="sign"):
        signed_distance(mesh, p, device=device, sign="parity")
    with pytest.raises(ValueError, match="max_dist"):
        signed_distance(mesh, p, device=device, max_dist=0.0)
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        signed_distance(mesh, p[:, :2], device=device)


@pytest.mark.parametrize("narrow_band", [False, True])
def test_sdf_grid_sphere(device, narrow_band):
    """Grid nodes at origin + spacing * (i, j, k) hold |p| - r: exact near the surface, right sign everywhere."""
    r = 3.0
    s = _sphere(r)
    res = 40
    grid, origin, spacing = sdf_grid((s.vertices, s.faces), res, padding=0.1, device=device, narrow_band=narrow_band)
    assert grid.shape == (res, res, res) and grid.dtype == wp.float32
    side = 2.0 * r * 1.2
    assert spacing == pytest.approx(side / (res - 1), rel=1e-6)
    np.testing.assert_allclose(origin, -0.5 * side * np.ones(3), rtol=1e-3, atol=1e-3 * r)
    g = grid.numpy()
    x = origin[:, None] + spacing * np.arange(res)[None, :]
    ref = np.sqrt(x[0][:, None, None] ** 2 + x[1][None, :, None] ** 2 + x[2][None, None, :] ** 2) - r
    tol = 2e-3 * r
    near = np.abs(ref) < spacing
    assert np.abs(g - ref)[near].max() < tol
    clear = np.abs(ref) > tol
    assert np.array_equal(np.sign(g[clear]), np.sign(ref[clear]))
    if not narrow_band:
        assert np.abs(g - ref).max() < tol
