"""Differentiability of VNC-soft (Eq. 3) and VNC-hard (Eq. 2): the PyTorch ops and the wp.Tape path against float64
dense PyTorch references (autograd; their signed angle is smooth through flat edges) and central finite
differences."""

import numpy as np
import pytest
import torch
import trimesh
import warp as wp
from reference import dense_hard, dense_soft

import vnc_warp as vw
from vnc_warp.kernels import vnc_sums
from vnc_warp.torch import vnc_hard, vnc_soft
from vnc_warp.tuning import Tuning


CUDA = wp.is_cuda_available() and torch.cuda.is_available()


@pytest.fixture(params=["cpu", pytest.param("cuda:0", marks=pytest.mark.skipif(
    not CUDA, reason="needs a CUDA device (Warp and torch): the gradients are checked there too"))])
def device(request):
    """Every gradient test that takes ``device`` runs on the CPU and on CUDA (skipped, saying so, without CUDA)."""
    return request.param


def _mesh(seed=0):
    tm = trimesh.creation.icosphere(2, radius=1.0)
    rng = np.random.default_rng(seed)
    tm.vertices *= (1.0 + 0.08 * rng.standard_normal(len(tm.vertices)))[:, None]
    return vw.load_mesh(tm)


def _objective_weights(V, seed=1):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(V, generator=g, dtype=torch.float64), torch.randn(V, 3, generator=g, dtype=torch.float64)


def _assert_fd(f, x0: np.ndarray, grad: torch.Tensor, eps: float, rtol: float) -> None:
    """Central finite differences of ``f`` at every 17th vertex of ``x0`` ((V, 3) float64) against ``grad``."""
    for i in range(0, x0.shape[0], 17):
        for d in range(3):
            xp, xm = x0.copy(), x0.copy()
            xp[i, d] += eps
            xm[i, d] -= eps
            fd = (f(xp) - f(xm)) / (2 * eps)
            assert abs(grad[i, d].item() - fd) < rtol * max(1.0, abs(fd)), (i, d, grad[i, d].item(), fd)


def _assert_soft_matches_dense(H, grad, x64: np.ndarray, faces, wH, wn, k: int) -> None:
    """VNC-soft values and the gradient of the weighted objective equal the float64 dense reference's at ``x64``
    to 1e-5 of their largest entry (``k`` names the call in the message)."""
    v64 = torch.tensor(x64, requires_grad=True)
    H64, n64 = dense_soft(v64, faces, 0.6)
    ((H64 * wH).sum() + (n64 * wn).sum()).backward()
    np.testing.assert_allclose(H.detach().cpu().numpy(), H64.detach().numpy(),
                               atol=1e-5 * np.abs(H64.detach().numpy()).max())
    g, g64 = grad.cpu().numpy(), v64.grad.numpy()
    assert np.abs(g - g64).max() < 1e-5 * np.abs(g64).max(), (k, np.abs(g - g64).max() / np.abs(g64).max())


@pytest.mark.parametrize("per_vertex", [False, True])
def test_torch_gradient_matches_dense_float64(per_vertex, device):
    """d(sum wH H + sum wn . n)/dv from the Warp op equals autograd through the float64 dense reference to 1e-5 of
    its largest entry (measured: under 1e-6 on 30 meshes, scales and weights)."""
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
    assert np.abs(g - g64).max() < 1e-5 * np.abs(g64).max()


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

    _assert_fd(f, mesh.vertices.astype(np.float64), v.grad, eps=1e-5, rtol=2e-3)


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


def _hard_case(kappa, per_vertex, seed, device):
    """The torch VNC-hard gradient of ``sum wH H + sum wn . n`` and the float64 dense reference's (autograd)."""
    mesh = _mesh(seed)
    V = mesh.num_vertices
    rng = np.random.default_rng(seed + 3)
    tau = 0.7 * (rng.uniform(0.7, 1.3, V) if per_vertex else 1.0)
    wH, wn = _objective_weights(V, seed + 1)
    v = torch.tensor(mesh.vertices, device=device, requires_grad=True)
    tau_arg = torch.as_tensor(tau, dtype=torch.float32, device=device) if per_vertex else tau
    H, n = vnc_hard(v, mesh, tau_arg, kappa=kappa)
    assert H.device == v.device and H.dtype == torch.float32 and n.shape == (V, 3)
    ((H.double().cpu() * wH).sum() + (n.double().cpu() * wn).sum()).backward()
    v64 = torch.tensor(mesh.vertices, dtype=torch.float64, requires_grad=True)
    H64, n64 = dense_hard(v64, mesh.faces, tau, kappa)
    ((H64 * wH).sum() + (n64 * wn).sum()).backward()
    np.testing.assert_allclose(H.detach().cpu().numpy(), H64.detach().numpy(), atol=1e-5 * np.abs(H64.detach().numpy()).max())
    return mesh, v.grad.cpu().numpy(), v64.grad.numpy()


@pytest.mark.parametrize("per_vertex", [False, True])
@pytest.mark.parametrize("seed", [0, 2])
def test_hard_torch_gradient_matches_dense_float64(per_vertex, seed, device):
    """VNC-hard (Eq. 2, kappa = 6) is differentiable: the torch op's gradient, every chord differentiated with respect
    to the ball's centre and both ends of its edge, equals autograd through the float64 dense reference (exact
    segment/ball roots clipped to the edge) to 1e-5 of its largest entry (measured: under 1.1e-6 on 30 cases)."""
    _, g, g64 = _hard_case(6.0, per_vertex, seed, device)
    assert np.abs(g - g64).max() < 1e-5 * np.abs(g64).max(), np.abs(g - g64).max() / np.abs(g64).max()


@pytest.mark.parametrize("seed", [0, 2])
def test_unweighted_hard_gradient_matches_dense_float64(seed, device):
    """Unweighted VNC-hard (w = 1) too, to 1e-4 of the gradient's norm: there a ball that an edge barely grazes
    (a chord of a hundredth of the radius) contributes a derivative ~1/chord that no Gaussian damps, so the float32
    rounding of the forward sums shows (measured: 6e-5 at worst on 30 cases, 1e-6 typical; finite differences of
    the float64 reference agree with the reference, test below)."""
    _, g, g64 = _hard_case(None, False, seed, device)
    assert np.linalg.norm(g - g64) < 1e-4 * np.linalg.norm(g64)


@pytest.mark.parametrize("kappa", [6.0, None])
def test_hard_torch_gradient_finite_differences(kappa):
    """The VNC-hard op's gradient agrees with central finite differences of the float64 dense reference."""
    mesh = _mesh(5)
    wH, wn = _objective_weights(mesh.num_vertices, 7)
    v = torch.tensor(mesh.vertices, requires_grad=True)
    H, n = vnc_hard(v, mesh, 0.8, kappa=kappa)
    ((H.double() * wH).sum() + (n.double() * wn).sum()).backward()

    def f(x):
        H64, n64 = dense_hard(torch.tensor(x), mesh.faces, 0.8, kappa)
        return float((H64 * wH).sum() + (n64 * wn).sum())

    _assert_fd(f, mesh.vertices.astype(np.float64), v.grad, eps=1e-6, rtol=1e-3)


def test_hard_adjoint_grid_equals_bvh(device):
    """The adjoint of VNC-hard through the grid (pieces of the edges, split rows, warp-sized groups) equals the
    reference's through the BVH (whole edges), and the torch op's forward equals ``vw.vnc_hard``."""
    mesh = _mesh(3)
    V = mesh.num_vertices
    wH, wn = _objective_weights(V, 4)
    gH = wp.array(wH.numpy().astype(np.float32), device=device)
    gn = wp.array(wn.numpy().astype(np.float32), dtype=wp.vec3, device=device)
    tau = wp.full(V, 0.6, dtype=wp.float32, device=device)
    grads = []
    for tuning, strategy in ((Tuning(group=32, splits=3, per_thread=4), "grid"), (Tuning(), "bvh")):
        eng = vw.engine(mesh, device, tuning=tuning)
        x = wp.array(mesh.local_vertices, dtype=wp.vec3, device=device)
        radius = wp.full(V, 0.6, dtype=wp.float32, device=device)
        g = wp.empty(V, dtype=wp.float32, device=device)
        wp.launch(vnc_sums.gaussian_factors, dim=V, inputs=[radius, 6.0], outputs=[g], device=device)
        outs = eng._ball(x, radius, g, strategy, None, None, True, x=x, save=True)
        outs[5].update(radius=radius, g=g)
        grads.append(eng.hard_gradient(outs, gH, gn).numpy())
    np.testing.assert_allclose(grads[0], grads[1], rtol=1e-4, atol=1e-5 * np.abs(grads[1]).max())
    v = torch.tensor(mesh.vertices, device=device)
    H = vnc_hard(v, mesh, tau.numpy())[0].cpu().numpy()
    np.testing.assert_allclose(H, vw.vnc_hard(mesh, tau, device=device)[0].numpy(), atol=1e-6)


def test_torch_op_replays_and_interleaves(device):
    """The torch op's forward and backward replay captured graphs once their shapes repeat (here on the CPU too), and
    stay right when calls interleave: two forwards at different positions, then their backwards in reverse order,
    each giving the gradient of its own positions: on the CPU the bit-identical gradient of a call run as usual; on
    CUDA, whose adjoint scatters with float32 atomics in no fixed order, that gradient to 1e-5 of its largest
    entry (an H200 differed by 9.5e-7 absolute)."""
    mesh = _mesh(4)
    V = mesh.num_vertices
    wH, wn = _objective_weights(V, 5)
    wH, wn = wH.to(torch.float32).to(device), wn.to(torch.float32).to(device)
    replay = Tuning(replay=("cpu", "cuda"))

    def grad_of(v0, tuning):
        v = v0.clone().requires_grad_(True)
        H, n = vnc_soft(v, mesh, 0.6, tuning=tuning)
        return v, (H * wH).sum() + (n * wn).sum()

    base = torch.tensor(mesh.vertices, device=device)
    moved = [base * (1.0 + 0.01 * k) for k in range(5)]
    plain = []
    for v0 in moved:
        v, loss = grad_of(v0, Tuning(replay=()))
        loss.backward()
        plain.append(v.grad.clone())

    def same(got, want):
        atol = 0.0 if torch.device(device).type == "cpu" else 1e-5 * float(want.abs().max())
        torch.testing.assert_close(got, want, rtol=0, atol=atol)

    for k, v0 in enumerate(moved):  # calls 3 on replay one graph each for the forward and the backward
        v, loss = grad_of(v0, replay)
        loss.backward()
        same(v.grad, plain[k])
    assert len(vw.engine(mesh, device, tuning=replay).graphs()) == 2
    (va, la), (vb, lb) = grad_of(moved[1], replay), grad_of(moved[3], replay)
    lb.backward()
    la.backward()
    same(va.grad, plain[1])
    same(vb.grad, plain[3])


def test_torch_gradient_backward_twice_and_after_a_forward_without_gradient():
    """The backward pass reads the moments its forward pass left (on the device while no other VNC-soft call ran
    since, else from the op's saved state): a backward pass run twice (``retain_graph``) adds the same gradient
    twice, and a forward pass under ``torch.no_grad`` at other positions (which leaves no moments) between a replayed
    forward pass and its backward pass changes nothing: on the CPU both equal a call run as usual, bit for bit."""
    mesh = _mesh(3)
    V = mesh.num_vertices
    wH, wn = (w.to(torch.float32) for w in _objective_weights(V, 4))
    replay = Tuning(replay=("cpu", "cuda"))
    base = torch.tensor(mesh.vertices, dtype=torch.float32)

    def loss_of(v, tuning):
        H, n = vnc_soft(v, mesh, 0.6, tuning=tuning)
        return (H * wH).sum() + (n * wn).sum()

    plain = []
    for k in range(5):
        v = (base * (1.0 + 0.01 * k)).requires_grad_(True)
        loss_of(v, Tuning(replay=())).backward()
        plain.append(v.grad.clone())
    for k in range(5):  # graphs captured from the third call on
        v = (base * (1.0 + 0.01 * k)).requires_grad_(True)
        loss = loss_of(v, replay)
        loss.backward(retain_graph=True)
        torch.testing.assert_close(v.grad, plain[k], rtol=0, atol=0)
        loss.backward()
        torch.testing.assert_close(v.grad, 2 * plain[k], rtol=0, atol=0)
    for k in range(5):
        v = (base * (1.0 + 0.01 * k)).requires_grad_(True)
        loss = loss_of(v, replay)
        with torch.no_grad():
            H, _ = vnc_soft(base * 1.07, mesh, 0.6, tuning=replay)
        loss.backward()
        torch.testing.assert_close(v.grad, plain[k], rtol=0, atol=0)
    assert len(vw.engine(mesh, "cpu", tuning=replay).graphs()) == 4  # forward with and without moments, 2 backwards
    H_plain, _ = vnc_soft(base * 1.07, mesh, 0.6, tuning=Tuning(replay=()))
    torch.testing.assert_close(H, H_plain, rtol=0, atol=0)


def test_torch_gradient_when_the_forward_state_is_saved_late_or_prepared_again(device):
    """A replayed forward pass copies out only H and n: the moments its backward pass reads stay in the graph's
    arrays until the engine's next VNC-soft call, which saves them first. Each way a backward pass can get them gives
    the gradient of its own positions (that of a call run as usual; bit for bit on the CPU, to 1e-5 of the largest
    entry on CUDA): read on the device; saved by a later forward pass at other positions; read on the device, then
    (``retain_graph``, after a forward pass at other positions overwrote them) prepared again; and with two meshes
    alternating forward and backward passes (one engine each), their positions moving every call."""
    meshes = [_mesh(6), _mesh(7)]
    wts = [tuple(w.to(torch.float32).to(device) for w in _objective_weights(m.num_vertices, 8 + i))
           for i, m in enumerate(meshes)]
    replay = Tuning(replay=("cpu", "cuda"))

    def loss_of(m, v, tuning):
        H, n = vnc_soft(v, meshes[m], 0.6, tuning=tuning)
        return (H * wts[m][0]).sum() + (n * wts[m][1]).sum()

    def at(m, k):
        base = torch.tensor(meshes[m].vertices, dtype=torch.float32, device=device)
        return (base * (1.0 + 0.01 * k)).requires_grad_(True)

    def plain(m, k):
        v = at(m, k)
        loss_of(m, v, Tuning(replay=())).backward()
        return v.grad

    def same(got, want):
        atol = 0.0 if torch.device(device).type == "cpu" else 1e-5 * float(want.abs().max())
        torch.testing.assert_close(got, want, rtol=0, atol=atol)

    for k in range(3):  # the plan, the graphs' scratch, the captures
        v = at(0, k)
        loss_of(0, v, replay).backward()
        same(v.grad, plain(0, k))
    va, vb = at(0, 4), at(0, 5)
    la = loss_of(0, va, replay)
    lb = loss_of(0, vb, replay)  # saves the state of la before overwriting it
    la.backward()
    same(va.grad, plain(0, 4))
    lb.backward(retain_graph=True)  # on the device, releasing the state
    same(vb.grad, plain(0, 5))
    loss_of(0, at(0, 6), replay).backward()  # overwrites what lb's forward pass left
    lb.backward()  # prepared again at vb
    same(vb.grad, 2 * plain(0, 5))
    for k in range(6):
        for m in (0, 1):
            v = at(m, 10 + k)
            loss_of(m, v, replay).backward()
            same(v.grad, plain(m, 10 + k))
    vs = [at(m, 20 + m) for m in (0, 1)]
    losses = [loss_of(m, vs[m], replay) for m in (0, 1)]
    for m in (1, 0):
        losses[m].backward()
        same(vs[m].grad, plain(m, 20 + m))
    for m in (0, 1):  # the later calls were replayed
        assert {k[0] for k in vw.engine(meshes[m], device, tuning=replay).graphs()} >= {"soft-x", "soft-grad-reuse"}


def test_torch_gradient_as_positions_and_scales_change(device):
    """The torch op's plan outlives its positions and per-vertex scales (a flow's iterations): calls at moved
    positions, and with a few scales grown threefold (the largest radius past the plan's, the mean within its
    tolerance), each give the float64 dense reference's gradient to 1e-5 of its largest entry."""
    mesh = _mesh(6)
    V = mesh.num_vertices
    wH, wn = _objective_weights(V, 8)
    rng = np.random.default_rng(9)
    tau = 0.5 * rng.uniform(0.8, 1.2, V)
    replay = Tuning(replay=("cpu", "cuda"))
    eng = vw.engine(mesh, device, tuning=replay)
    for k in range(5):
        t = tau.copy()
        if k >= 3:
            t[::40] *= 3.0
        x0 = mesh.vertices.astype(np.float64) * (1.0 + 0.02 * k)
        v = torch.tensor(x0, dtype=torch.float32, device=device, requires_grad=True)
        H, n = vnc_soft(v, mesh, torch.as_tensor(t, dtype=torch.float32, device=device), tuning=replay)
        ((H.double().cpu() * wH).sum() + (n.double().cpu() * wn).sum()).backward()
        v64 = torch.tensor(v.detach().cpu().numpy().astype(np.float64), requires_grad=True)
        H64, n64 = dense_soft(v64, mesh.faces, t)
        ((H64 * wH).sum() + (n64 * wn).sum()).backward()
        g, g64 = v.grad.cpu().numpy(), v64.grad.numpy()
        assert np.abs(g - g64).max() < 1e-5 * np.abs(g64).max(), (k, np.abs(g - g64).max() / np.abs(g64).max())
    assert len(eng._plans) == 1


def test_torch_gradient_after_a_plain_call_of_the_same_plan(device):
    """A call with ``positions=`` of the same plan between the torch op's replayed forward pass and its backward pass
    (a flow's own step beside a loss) does not lend the backward pass its traversal: the gradient stays the float64
    dense reference's to 1e-5 of its largest entry."""
    mesh = _mesh(4)
    V = mesh.num_vertices
    wH, wn = _objective_weights(V, 5)
    replay = Tuning(replay=("cpu", "cuda"))
    eng = vw.engine(mesh, device, tuning=replay)
    v = torch.tensor(mesh.vertices, dtype=torch.float32, device=device, requires_grad=True)
    for _ in range(3):  # the forward pass alone, until it is replayed from a graph
        vnc_soft(v, mesh, 0.5, tuning=replay)
    centred = mesh.vertices - 0.5 * (mesh.vertices.min(0) + mesh.vertices.max(0))
    other = wp.array((1.03 * centred).astype(np.float32), dtype=wp.vec3, device=device)
    eng.vnc_soft(0.5, positions=other)
    assert len(eng._plans) == 1  # the same plan as the torch op's
    H, n = vnc_soft(v, mesh, 0.5, tuning=replay)
    ((H.double().cpu() * wH).sum() + (n.double().cpu() * wn).sum()).backward()
    v64 = torch.tensor(mesh.vertices, dtype=torch.float64, requires_grad=True)
    H64, n64 = dense_soft(v64, mesh.faces, 0.5)
    ((H64 * wH).sum() + (n64 * wn).sum()).backward()
    g, g64 = v.grad.cpu().numpy(), v64.grad.numpy()
    assert np.abs(g - g64).max() < 1e-5 * np.abs(g64).max(), np.abs(g - g64).max() / np.abs(g64).max()


@pytest.mark.parametrize("per_thread", [1, 4])
@pytest.mark.parametrize("per_vertex", [False, True])
@pytest.mark.parametrize("op, scatter", [("soft", ()), ("soft", ("cpu",)), ("hard", ())])
def test_torch_gradient_with_the_cuda_launch_shape(op, scatter, per_vertex, per_thread):
    """On the CPU with CUDA's launch shape (the culled row walk, warp-sized groups sharing boxes, rows split over
    threads, one or four queries per thread as in a busy traversal; graph replay), the torch ops' gradients
    (VNC-soft's edge adjoint walks the culled rows too, one or four edges per thread; the query vertices' part from
    the forward's moments, or added by the edge adjoint's pairs: ``Tuning.vertex_scatter``) equal the float64 dense
    references' to 1e-5 of their largest entry, at moved positions too."""
    torch_op, dense = (vnc_soft, dense_soft) if op == "soft" else (vnc_hard, dense_hard)
    mesh = _mesh(7)
    V = mesh.num_vertices
    wH, wn = _objective_weights(V, 11)
    rng = np.random.default_rng(12)
    tau = 0.6 * (rng.uniform(0.6, 1.4, V) if per_vertex else 1.0)
    shape = Tuning(replay=("cpu", "cuda"), cull_cpu=True, group=32, splits=3, per_thread=per_thread,
                   vertex_scatter=scatter)
    for k in range(4):
        x0 = mesh.vertices.astype(np.float64) * (1.0 + 0.01 * k)
        v = torch.tensor(x0, dtype=torch.float32, requires_grad=True)
        tau_arg = torch.as_tensor(tau, dtype=torch.float32) if per_vertex else tau
        H, n = torch_op(v, mesh, tau_arg, tuning=shape)
        ((H.double() * wH).sum() + (n.double() * wn).sum()).backward()
        v64 = torch.tensor(v.detach().numpy().astype(np.float64), requires_grad=True)
        H64, n64 = dense(v64, mesh.faces, tau)
        ((H64 * wH).sum() + (n64 * wn).sum()).backward()
        g, g64 = v.grad.numpy(), v64.grad.numpy()
        assert np.abs(g - g64).max() < 1e-5 * np.abs(g64).max(), (k, np.abs(g - g64).max() / np.abs(g64).max())


def test_torch_op_outputs_survive_later_replayed_calls(device):
    """The torch op's forward and backward replay graphs that write into the same device arrays on every call; the
    tensors it returned (H, n and the gradient) must be copies of their own. Five replayed calls at different
    positions: each gives its own positions' float64 dense reference values and gradient, and after all of them the
    tensors of the first call still hold the first call's values (a cache that served the graph's arrays, or stale
    positions, fails here)."""
    mesh = _mesh(2)
    V = mesh.num_vertices
    wH, wn = _objective_weights(V, 3)
    replay = Tuning(replay=("cpu", "cuda"))
    kept = []
    for k in range(6):
        v = torch.tensor(mesh.vertices * (1.0 + 0.05 * k), dtype=torch.float32, device=device, requires_grad=True)
        H, n = vnc_soft(v, mesh, 0.6, tuning=replay)
        ((H.double().cpu() * wH).sum() + (n.double().cpu() * wn).sum()).backward()
        kept.append((H.detach(), n.detach(), v.grad, H.detach().clone(), n.detach().clone(), v.grad.clone()))
        _assert_soft_matches_dense(H, v.grad, v.detach().cpu().numpy().astype(np.float64), mesh.faces, wH, wn, k)
    assert len(vw.engine(mesh, device, tuning=replay).graphs()) == 2  # the later calls were replayed
    for H, n, g, H0, n0, g0 in kept:
        assert torch.equal(H, H0) and torch.equal(n, n0) and torch.equal(g, g0)
    assert not torch.equal(kept[-1][0], kept[-2][0])  # different positions gave different curvature


def test_torch_op_float64_input_replayed_matches_dense(device):
    """A float64 input goes through the replayed path (centred in float64, written into the plan's float32 positions
    by one torch op, the gradient cast back): values and gradient equal the float64 dense reference's to 1e-5 of
    their largest entry on the third and later calls, for a mesh moved 1e4 units from the origin."""
    mesh = _mesh(5)
    V = mesh.num_vertices
    wH, wn = _objective_weights(V, 6)
    replay = Tuning(replay=("cpu", "cuda"))
    for k in range(4):
        x0 = mesh.vertices.astype(np.float64) * (1.0 + 0.03 * k) + 1e4
        v = torch.tensor(x0, dtype=torch.float64, device=device, requires_grad=True)
        H, n = vnc_soft(v, mesh, 0.6, tuning=replay)
        ((H.double().cpu() * wH).sum() + (n.double().cpu() * wn).sum()).backward()
        assert v.grad.dtype == torch.float64
        _assert_soft_matches_dense(H, v.grad, x0 - 1e4, mesh.faces, wH, wn, k)


def test_torch_op_refuses_positions_changed_before_backward():
    """The backward pass reads the positions of its forward call: changing the input in place between the two is
    refused by autograd (a backward over other positions would be silently wrong), and a NaN in the input is refused
    on the CPU at the call, on the replayed path too."""
    mesh = _mesh(2)
    replay = Tuning(replay=("cpu", "cuda"))
    v = torch.tensor(mesh.vertices, dtype=torch.float32, requires_grad=True)
    for _ in range(3):
        vnc_soft(v, mesh, 0.6, tuning=replay)
    leaf = v.detach().clone().requires_grad_(True)
    w = leaf * 1.0
    H, n = vnc_soft(w, mesh, 0.6, tuning=replay)
    with torch.no_grad():
        w.mul_(1.1)
    with pytest.raises(RuntimeError, match="modified by an inplace operation"):
        H.sum().backward()
    bad = v.detach().clone()
    bad[3, 1] = float("nan")
    with pytest.raises(ValueError, match="NaN or infinite"):
        vnc_soft(bad, mesh, 0.6, tuning=replay)
