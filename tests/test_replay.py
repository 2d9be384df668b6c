"""Graph replay of repeated operator calls (vnc_warp._replay) and the host-side bounds that make it possible.

Replay is on for CUDA by default; here it is turned on for the CPU device too (Warp records CPU graphs as well), so
the capture, the replay, the copies out and the invalidation run in CI. Oracles: the same call with replay off
(bit-identical: same kernels, same order of sums) and the BVH strategy (an independent traversal).
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
import warp as wp

import vnc_warp as vw
from vnc_warp import _pairs, _replay
from vnc_warp.operators import _host_bounds, _mesh_vertices


@pytest.fixture
def replay_everywhere(monkeypatch):
    monkeypatch.setattr(_replay, "DEVICES", {"cpu", "cuda"})


def _mesh(scale=1.0, offset=0.0):
    tm = trimesh.creation.icosphere(3, radius=1.0)
    rng = np.random.default_rng(7)
    tm.vertices *= (1.0 + 0.08 * rng.standard_normal(len(tm.vertices)))[:, None]
    tm.vertices = tm.vertices * scale + offset
    return vw.load_mesh(tm)


def _graphs(mesh, device):
    table = _replay._table(mesh, wp.get_device(device))
    return [k for k, v in table.entries.items() if isinstance(v, tuple)]


@pytest.mark.parametrize("op", ["soft", "hard", "hard_unweighted", "eq1"])
def test_repeated_calls_replay_and_match_plain_calls(op, replay_everywhere, device, monkeypatch):
    mesh = _mesh(scale=37.0, offset=120.0)
    tau = 3.0 * mesh.mean_edge_length
    call = {
        "soft": lambda **kw: vw.vnc_soft(mesh, tau, device=device, **kw)[0],
        "hard": lambda **kw: vw.vnc_hard(mesh, tau, device=device, **kw)[0],
        "hard_unweighted": lambda **kw: vw.vnc_hard(mesh, tau, kappa=None, device=device, **kw)[0],
        "eq1": lambda **kw: vw.integrated_mean_curvature(mesh, tau, device=device, **kw),
    }[op]
    outs = [call() for _ in range(5)]  # plain, on the graph's scratch, capture + replay, replay, replay
    assert len(_graphs(mesh, device)) == 1
    assert len({id(o) for o in outs}) == 5  # every call returns arrays of its own
    oracle = call(strategy="bvh").numpy()
    monkeypatch.setattr(_replay, "DEVICES", set())
    plain = call().numpy()
    for o in outs:
        np.testing.assert_array_equal(o.numpy(), plain)
    np.testing.assert_allclose(plain, oracle, rtol=1e-4, atol=1e-5 * np.abs(oracle).max())


def test_replayed_outputs_are_not_aliased(replay_everywhere, device):
    mesh = _mesh()
    tau = 2.5 * mesh.mean_edge_length
    H1, n1 = vw.vnc_soft(mesh, tau, device=device)
    vw.vnc_soft(mesh, tau, device=device)  # on the graph's scratch
    H2, n2 = vw.vnc_soft(mesh, tau, device=device)  # captured and replayed
    ref = H2.numpy().copy()
    H2.fill_(123.0)
    n2.zero_()
    H3, n3 = vw.vnc_soft(mesh, tau, device=device)  # replayed: must not see the writes above, nor undo them
    np.testing.assert_array_equal(H3.numpy(), ref)
    np.testing.assert_array_equal(H1.numpy(), ref)
    assert (H2.numpy() == 123.0).all() and not n2.numpy().any()
    assert np.allclose(np.linalg.norm(n3.numpy(), axis=1), 1.0, atol=1e-5)


def test_new_vertices_invalidate_the_graphs(replay_everywhere, device):
    mesh = _mesh()
    tau = 3.0 * mesh.mean_edge_length
    for _ in range(4):
        vw.vnc_soft(mesh, tau, device=device)
    assert _graphs(mesh, device)
    moved = mesh.vertices * np.float32(1.5)
    mesh.vertices = moved  # a new array: everything kept for the old one is dropped
    H = vw.vnc_soft(mesh, tau, device=device)[0].numpy()
    H_again = vw.vnc_soft(mesh, tau, device=device)[0].numpy()
    ref = vw.vnc_soft(vw.from_arrays(moved, mesh.faces), tau, device=device, strategy="bvh")[0].numpy()
    np.testing.assert_allclose(H, ref, rtol=1e-4, atol=1e-5)
    np.testing.assert_array_equal(H_again, H)


def test_graph_count_is_bounded(replay_everywhere, device, monkeypatch):
    monkeypatch.setattr(_replay, "MAX_GRAPHS", 2)
    mesh = _mesh()
    taus = [k * mesh.mean_edge_length for k in (2.0, 3.0, 4.0, 5.0)]
    for t in taus:
        for _ in range(3):
            vw.vnc_soft(mesh, t, device=device)
    kept = _graphs(mesh, device)
    assert len(kept) == 2
    assert {k[1] for k in kept} == {taus[2], taus[3]}  # the least recently used went first
    for t in taus:  # the graphs kept still replay right; the others run again as at first
        H = vw.vnc_soft(mesh, t, device=device)[0].numpy()
        Hb = vw.vnc_soft(mesh, t, device=device, strategy="bvh")[0].numpy()
        np.testing.assert_allclose(H, Hb, atol=2e-6)


def test_no_replay_inside_a_users_capture(replay_everywhere, device):
    mesh = _mesh()
    tau = 3.0 * mesh.mean_edge_length
    ref = vw.vnc_soft(mesh, tau, device=device, strategy="bvh")[0].numpy()
    with wp.ScopedCapture(device=device) as capture:
        H, _ = vw.vnc_soft(mesh, tau, device=device)
    assert not _graphs(mesh, device)
    wp.capture_launch(capture.graph)
    np.testing.assert_allclose(H.numpy(), ref, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("scale, offset", [(0.15, 0.0), (500.0, -250.0)])
def test_host_bounds_match_the_device_bounds(scale, offset, device):
    mesh = _mesh(scale, offset)
    dev = wp.get_device(device)
    x = _mesh_vertices(mesh, dev)
    tau = np.linspace(1.0, 2.0, mesh.num_vertices).astype(np.float32) * mesh.mean_edge_length
    tau_wp = wp.array(tau, dtype=wp.float32, device=dev)
    length = vw.edge_fields(mesh, device=dev).length
    host = _host_bounds(mesh, x, (float(tau.max()), float(tau.astype(np.float64).mean())), lengths=True)
    ref = _pairs.bounds(x, tau_wp, length)
    np.testing.assert_array_equal(host.lo, ref.lo)
    np.testing.assert_array_equal(host.hi, ref.hi)
    assert host.rmax == pytest.approx(ref.rmax, rel=1e-6)
    assert host.rmean == pytest.approx(ref.rmean, rel=1e-5)
    assert host.lmax >= ref.lmax and host.lmax == pytest.approx(ref.lmax, rel=2e-6)
    assert host.lmean == pytest.approx(ref.lmean, rel=1e-5)
    # positions that are not the mesh's own, or radii that live on the device: the bounds must be read back
    other = wp.array(mesh.vertices, dtype=wp.vec3, device=dev)
    assert _host_bounds(mesh, other, (1.0, 1.0)) is None
    assert _host_bounds(mesh, x, None) is None


def test_replay_can_be_turned_off_and_on(device):
    mesh = _mesh()
    tau = 3.0 * mesh.mean_edge_length
    old = vw.set_graph_replay()
    try:
        for _ in range(4):
            vw.vnc_soft(mesh, tau, device=device)
        assert not _graphs(mesh, device)
        vw.set_graph_replay("cpu", "cuda")
        for _ in range(3):
            vw.vnc_soft(mesh, tau, device=device)
        assert len(_graphs(mesh, device)) == 1
        with pytest.raises(ValueError, match="device kinds"):
            vw.set_graph_replay("tpu")
    finally:
        vw.set_graph_replay(*old)
    assert _replay.DEVICES == old
