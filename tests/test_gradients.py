"""Differentiability of VNC-soft (Eq. 3): the PyTorch op and the wp.Tape path against a float64 dense
PyTorch reference and central finite differences."""

import numpy as np
import pytest
import torch
import trimesh
import warp as wp
from reference import dense_soft

import vnc_warp as vw
from vnc_warp.torch import vnc_soft


def _mesh(seed=0):
    tm = trimesh.creation.icosphere(2, radius=1.0)
    rng = np.random.default_rng(seed)
    tm.vertices *= (1.0 + 0.08 * rng.standard_normal(len(tm.vertices)))[:, None]
    return vw.load_mesh(tm)


def _objective_weights(V, seed=1):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(V, generator=g, dtype=torch.float64), torch.randn(V, 3, generator=g, dtype=torch.float64)


@pytest.mark.parametrize("per_vertex", [False, True])
def test_torch_gradient_matches_dense_float64(per_vertex, device):
    """d(sum wH H + sum wn . n)/dv from the Warp op equals autograd through the float64 dense reference."""
    mesh = _mesh()
    V = mesh.num_vertices
    tau = 0.7 * (np.random.default_rng(3).uniform(0.7, 1.3, V) if per_vertex else 1.0)
    wH, wn = _objective_weights(V)
    v = torch.tensor(mesh.vertices, device=device, requires_grad=True)
    H, n = vnc_soft(v, mesh, torch.as_tensor(tau, dtype=torch.float32, device=device) if per_vertex else tau)
    assert H.device == v.device and H.dtype == torch.float32 and n.shape == (V, 3)
    ((H.double().cpu() * wH).sum() + (n.double().cpu() * wn).sum()).backward()
    v64 = torch.tensor(mesh.vertices, dtype=torch.float64, requires_grad=True)
    H64, n64 = dense_soft(v64, mesh.faces, tau)
    ((H64 * wH).sum() + (n64 * wn).sum()).backward()
    g, g64 = v.grad.cpu().numpy(), v64.grad.numpy()
    np.testing.assert_allclose(H.detach().cpu().numpy(), H64.detach().numpy(), atol=1e-5 * np.abs(H64.detach().numpy()).max())
    assert np.abs(g - g64).max() < 1e-3 * np.abs(g64).max()


def test_torch_gradient_finite_differences():
    """The op's gradient agrees with central finite differences of the float64 dense reference."""
    mesh = _mesh(5)
    wH, wn = _objective_weights(mesh.num_vertices, 7)
    v = torch.tensor(mesh.vertices, requires_grad=True)
    H, n = vnc_soft(v, mesh, 0.8)
    ((H.double() * wH).sum() + (n.double() * wn).sum()).backward()

    def f(x):
        H64, n64 = dense_soft(torch.tensor(x), mesh.faces, 0.8)
        return float((H64 * wH).sum() + (n64 * wn).sum())

    x0 = mesh.vertices.astype(np.float64)
    eps = 1e-5
    for i in range(0, mesh.num_vertices, 17):
        for d in range(3):
            xp, xm = x0.copy(), x0.copy()
            xp[i, d] += eps
            xm[i, d] -= eps
            fd = (f(xp) - f(xm)) / (2 * eps)
            assert abs(v.grad[i, d].item() - fd) < 2e-3 * max(1.0, abs(fd))


def test_warp_tape_gradient_equals_torch_op(device):
    """Recording vnc_soft on a wp.Tape (positions with requires_grad) gives the same gradient as the torch op,
    and the edge-geometry kernel (dihedral via atan2) stays finite on a flat region."""
    mesh = _mesh(9)
    V = mesh.num_vertices
    wH, wn = _objective_weights(V, 11)
    x = wp.array(mesh.vertices, dtype=wp.vec3, device=device, requires_grad=True)
    tape = wp.Tape()
    with tape:
        H, n = vw.vnc_soft(mesh, 0.6, positions=x, tape=tape)
    tape.backward(grads={H: wp.array(wH.numpy().astype(np.float32), device=device),
                         n: wp.array(wn.numpy().astype(np.float32), dtype=wp.vec3, device=device)})
    g_tape = x.grad.numpy()
    v = torch.tensor(mesh.vertices, requires_grad=True)
    Ht, nt = vnc_soft(v, mesh, 0.6)
    ((Ht.double() * wH).sum() + (nt.double() * wn).sum()).backward()
    np.testing.assert_allclose(g_tape, v.grad.numpy(), rtol=1e-4, atol=1e-5 * np.abs(g_tape).max())


def test_gradient_finite_on_flat_region(device):
    """A mesh with a flat patch (zero dihedral angles) gets a finite gradient everywhere."""
    tm = trimesh.creation.box(extents=(1, 1, 1)).subdivide().subdivide()
    mesh = vw.load_mesh(tm)
    v = torch.tensor(mesh.vertices, device=device, requires_grad=True)
    H, n = vnc_soft(v, mesh, 0.4)
    (H.sum() + n[:, 2].sum()).backward()
    assert torch.isfinite(v.grad).all()
    assert v.grad.abs().max() > 0


def test_torch_wrapper_checks_inputs():
    """The public wrapper rejects wrong shapes, half precision, NaN, mismatched meshes and non-manifold faces
    clearly."""
    mesh = _mesh()
    v = torch.tensor(mesh.vertices)
    with pytest.raises(ValueError, match=r"\(V, 3\)"):
        vnc_soft(v[:, :2], mesh, 0.5)
    with pytest.raises(TypeError, match="float32 or float64"):
        vnc_soft(v.half(), mesh, 0.5)
    bad = v.clone()
    bad[3, 1] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        vnc_soft(bad, mesh, 0.5)
    with pytest.raises(ValueError, match="rows"):
        vnc_soft(v[:-1], mesh, 0.5)
    with pytest.raises(TypeError, match="torch.Tensor"):
        vnc_soft(mesh.vertices, mesh, 0.5)
    H, _ = vnc_soft(v, torch.as_tensor(mesh.faces.astype(np.int64)), 0.5)
    np.testing.assert_allclose(H.numpy(), vnc_soft(v, mesh, 0.5)[0].numpy(), atol=1e-6)
