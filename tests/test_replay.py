"""Graph replay of repeated operator calls (vnc_warp._replay) and the host-side bounds that make it possible, for
the mesh's own vertices and for positions given on the device (the engine's plans).

Replay is on for CUDA by default; here an engine's tuning turns it on for the CPU device too (Warp records CPU graphs
as well), so the capture, the replay, the copies out and the invalidation run in CI. Oracles: the same call with
replay off (bit-identical: same kernels, same order of sums) and the BVH strategy (an independent traversal).
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
import warp as wp

import vnc_warp as vw
from vnc_warp import _plan, _replay
from vnc_warp.tuning import DEFAULT, Tuning

#: replay on every device kind, and off
EVERYWHERE = Tuning(replay=("cpu", "cuda"))
NOWHERE = Tuning(replay=())


def _mesh(scale=1.0, offset=0.0):
    tm = trimesh.creation.icosphere(3, radius=1.0)
    rng = np.random.default_rng(7)
    tm.vertices *= (1.0 + 0.08 * rng.standard_normal(len(tm.vertices)))[:, None]
    tm.vertices = tm.vertices * scale + offset
    return vw.load_mesh(tm)


def _graphs(mesh, device, tuning=EVERYWHERE):
    return vw.engine(mesh, device, tuning=tuning).graphs()


@pytest.mark.parametrize("op", ["soft", "hard", "hard_unweighted", "eq1", "curve", "hard_curve"])
def test_repeated_calls_replay_and_match_plain_calls(op, device):
    """The third call of one key captures a graph and every later one replays it: the results equal a call run as
    usual (bit for bit) and the BVH reference, and every call returns arrays of its own."""
    mesh = _mesh(scale=37.0, offset=120.0)
    tau = 3.0 * mesh.mean_edge_length
    taus = [tau, 2.0 * tau]
    call = {
        "soft": lambda **kw: vw.vnc_soft(mesh, tau, device=device, **kw)[0],
        "hard": lambda **kw: vw.vnc_hard(mesh, tau, device=device, **kw)[0],
        "hard_unweighted": lambda **kw: vw.vnc_hard(mesh, tau, kappa=None, device=device, **kw)[0],
        "eq1": lambda **kw: vw.integrated_mean_curvature(mesh, tau, device=device, **kw),
        "curve": lambda **kw: vw.scale_curve(mesh, taus, device=device, **kw).H,
        "hard_curve": lambda **kw: vw.scale_curve(mesh, taus, "hard", device=device, **kw).H,
    }[op]
    outs = [call(tuning=EVERYWHERE) for _ in range(5)]  # plain, on the graph's scratch, capture + replay, replay x2
    assert len(_graphs(mesh, device)) == 1
    assert len({id(o) for o in outs}) == 5  # every call returns arrays of its own
    oracle = call(strategy="bvh").numpy()
    plain = call(tuning=NOWHERE).numpy()
    assert not _graphs(mesh, device, NOWHERE)
    for o in outs:
        np.testing.assert_array_equal(o.numpy(), plain)
    np.testing.assert_allclose(plain, oracle, rtol=1e-4, atol=1e-5 * np.abs(oracle).max())


def test_replayed_outputs_are_not_aliased(device):
    """A replayed call's arrays are copies: writing into one changes no other call's result."""
    mesh = _mesh()
    tau = 2.5 * mesh.mean_edge_length
    kw = dict(device=device, tuning=EVERYWHERE)
    H1, n1 = vw.vnc_soft(mesh, tau, **kw)
    vw.vnc_soft(mesh, tau, **kw)  # on the graph's scratch
    H2, n2 = vw.vnc_soft(mesh, tau, **kw)  # captured and replayed
    ref = H2.numpy().copy()
    H2.fill_(123.0)
    n2.zero_()
    H3, n3 = vw.vnc_soft(mesh, tau, **kw)  # replayed: must not see the writes above, nor undo them
    np.testing.assert_array_equal(H3.numpy(), ref)
    np.testing.assert_array_equal(H1.numpy(), ref)
    assert (H2.numpy() == 123.0).all() and not n2.numpy().any()
    assert np.allclose(np.linalg.norm(n3.numpy(), axis=1), 1.0, atol=1e-5)


def test_new_vertices_invalidate_the_graphs(device):
    """Replacing a mesh's vertex array gives it a new engine: nothing kept for the old vertices is used."""
    mesh = _mesh()
    tau = 3.0 * mesh.mean_edge_length
    for _ in range(4):
        vw.vnc_soft(mesh, tau, device=device, tuning=EVERYWHERE)
    assert _graphs(mesh, device)
    moved = mesh.vertices * np.float32(1.5)
    mesh.vertices = moved  # a new array: everything kept for the old one is dropped
    assert not _graphs(mesh, device)
    H = vw.vnc_soft(mesh, tau, device=device, tuning=EVERYWHERE)[0].numpy()
    H_again = vw.vnc_soft(mesh, tau, device=device, tuning=EVERYWHERE)[0].numpy()
    ref = vw.vnc_soft(vw.from_arrays(moved, mesh.faces), tau, device=device, strategy="bvh")[0].numpy()
    np.testing.assert_allclose(H, ref, rtol=1e-4, atol=1e-5)
    np.testing.assert_array_equal(H_again, H)


def test_graph_count_is_bounded(device):
    """An engine keeps at most ``Tuning.max_graphs`` graphs, the least recently used going first; the graphs kept
    still replay right, and the others run again as at first."""
    tuning = Tuning(replay=("cpu", "cuda"), max_graphs=2)
    mesh = _mesh()
    taus = [k * mesh.mean_edge_length for k in (2.0, 3.0, 4.0, 5.0)]
    for t in taus:
        for _ in range(3):
            vw.vnc_soft(mesh, t, device=device, tuning=tuning)
    kept = _graphs(mesh, device, tuning)
    assert len(kept) == 2
    assert {k[1] for k in kept} == {taus[2], taus[3]}  # the least recently used went first
    for t in taus:
        H = vw.vnc_soft(mesh, t, device=device, tuning=tuning)[0].numpy()
        Hb = vw.vnc_soft(mesh, t, device=device, strategy="bvh")[0].numpy()
        np.testing.assert_allclose(H, Hb, atol=2e-6)


def test_no_replay_inside_a_users_capture(device):
    """A call made while the user captures a graph of their own is recorded into it, never replayed."""
    mesh = _mesh()
    tau = 3.0 * mesh.mean_edge_length
    ref = vw.vnc_soft(mesh, tau, device=device, strategy="bvh", tuning=EVERYWHERE)[0].numpy()
    with wp.ScopedCapture(device=device) as capture:
        H, _ = vw.vnc_soft(mesh, tau, device=device, tuning=EVERYWHERE)
    assert not _graphs(mesh, device)
    wp.capture_launch(capture.graph)
    np.testing.assert_allclose(H.numpy(), ref, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("scale, offset", [(0.15, 0.0), (500.0, -250.0)])
def test_host_bounds_match_the_device_bounds(scale, offset, device):
    """The bounds an engine takes from the host for its own vertices equal those measured on the device."""
    mesh = _mesh(scale, offset)
    eng = vw.engine(mesh, device)
    x = eng.x
    tau = np.linspace(1.0, 2.0, mesh.num_vertices).astype(np.float32) * mesh.mean_edge_length
    tau_wp = wp.array(tau, dtype=wp.float32, device=device)
    length = vw.edge_fields(mesh, device=device).length
    host = eng.host_bounds(x, (float(tau.max()), float(tau.astype(np.float64).mean())), lengths=True)
    ref = _plan.bounds(x, tau_wp, length)
    np.testing.assert_array_equal(host.lo, ref.lo)
    np.testing.assert_array_equal(host.hi, ref.hi)
    assert host.rmax == pytest.approx(ref.rmax, rel=1e-6)
    assert host.rmean == pytest.approx(ref.rmean, rel=1e-5)
    assert host.lmax >= ref.lmax and host.lmax == pytest.approx(ref.lmax, rel=2e-6)
    assert host.lmean == pytest.approx(ref.lmean, rel=1e-5)
    # positions that are not the mesh's own, or radii that live on the device: the bounds must be read back
    other = wp.array(mesh.vertices, dtype=wp.vec3, device=device)
    assert eng.host_bounds(other, (1.0, 1.0)) is None
    assert eng.host_bounds(x, None) is None


def test_replay_can_be_turned_off_and_on(device):
    """``vw.set_graph_replay`` sets the device kinds that replay for engines whose tuning leaves it unset."""
    mesh = _mesh()
    tau = 3.0 * mesh.mean_edge_length
    old = vw.set_graph_replay()
    try:
        for _ in range(4):
            vw.vnc_soft(mesh, tau, device=device)
        assert not _graphs(mesh, device, DEFAULT)
        vw.set_graph_replay("cpu", "cuda")
        for _ in range(3):
            vw.vnc_soft(mesh, tau, device=device)
        assert len(_graphs(mesh, device, DEFAULT)) == 1
        with pytest.raises(ValueError, match="device kinds"):
            vw.set_graph_replay("tpu")
    finally:
        vw.set_graph_replay(*old)
    assert _replay.replayed_kinds(None) == old


# --- positions given on the device: one plan, replayed while only the positions move ----------------------------


def _wobble(mesh, k: int, amount: float) -> np.ndarray:
    """The mesh's vertices moved smoothly (a flow step's worth per unit of ``amount`` mean edge lengths)."""
    v = mesh.vertices.astype(np.float64)
    phase = 0.7 * k
    d = np.stack([np.sin(3 * v[:, 1] + phase), np.cos(2 * v[:, 2] - phase), np.sin(v[:, 0] + 2 * phase)], 1)
    return (v + amount * mesh.mean_edge_length * d).astype(np.float32)


@pytest.mark.parametrize("per_vertex", [False, True])
def test_moving_positions_keep_one_plan_and_replay(per_vertex, device):
    """VNC-soft at positions given on the device, moved every call (a flow's steps; scalar or per-vertex scales on
    the device): one plan serves every call (its bounds are read from the device once), calls from the third on
    replay one graph, and every call equals the BVH reference at its own positions, the same call with replay off
    bit for bit."""
    mesh = _mesh(scale=20.0, offset=-40.0)
    rng = np.random.default_rng(2)
    tau = 3.0 * mesh.mean_edge_length * (rng.uniform(0.8, 1.2, mesh.num_vertices) if per_vertex else 1.0)
    tau_arg = wp.array(np.asarray(tau, np.float32), device=device) if per_vertex else float(tau)
    eng = vw.engine(mesh, device, tuning=EVERYWHERE)
    plans = set()
    for k in range(6):
        x = wp.array(_wobble(mesh, k, 0.3), dtype=wp.vec3, device=device)
        H, n = vw.vnc_soft(mesh, tau_arg, positions=x, tuning=EVERYWHERE)
        plans |= set(id(p) for p in eng._plans.values())
        Hp, n_p = vw.vnc_soft(mesh, tau_arg, positions=x, tuning=NOWHERE)
        Hb, nb = vw.vnc_soft(mesh, tau_arg, positions=x, strategy="bvh")
        np.testing.assert_array_equal(H.numpy(), Hp.numpy())
        np.testing.assert_array_equal(n.numpy(), n_p.numpy())
        np.testing.assert_allclose(H.numpy(), Hb.numpy(), rtol=1e-4, atol=2e-6, err_msg=f"step {k}")
        np.testing.assert_allclose(n.numpy(), nb.numpy(), atol=5e-5, err_msg=f"step {k}")
    assert len(plans) == 1
    assert len(eng.graphs()) == 1


def test_positions_far_outside_the_plan_stay_exact_and_replan(device):
    """Positions that leave the box a plan's grid was made for (moved by half the mesh, and shrunk) are still summed
    exactly (a stale grid clamps them into its boundary cells), and the next call makes a new plan, for its own
    positions; with the culled row walk of CUDA and warp-sized groups on the CPU too."""
    mesh = _mesh()
    tau = 2.5 * mesh.mean_edge_length
    for tuning in (EVERYWHERE, Tuning(replay=("cpu", "cuda"), cull_cpu=True, group=32, splits=3, per_thread=1)):
        eng = vw.engine(mesh, device, tuning=tuning)
        v = mesh.vertices.astype(np.float64)
        for k, moved in enumerate([v, v + 0.5 * np.ptp(v, 0), 0.6 * v - 0.4 * np.ptp(v, 0), v]):
            x = wp.array(moved.astype(np.float32), dtype=wp.vec3, device=device)
            before = list(eng._plans.values())
            H = vw.vnc_soft(mesh, tau, positions=x, tuning=tuning)[0].numpy()
            Hb = vw.vnc_soft(mesh, tau, positions=x, strategy="bvh")[0].numpy()
            np.testing.assert_allclose(H, Hb, rtol=1e-4, atol=2e-6, err_msg=f"move {k}")
            # call 0 makes the plan; call 1's positions left its box, so call 2 made a new one, for its own positions
            # (call 3's are outside that one's box: call 4 would make another)
            assert (list(eng._plans.values()) != before) == (k in (0, 2)), k


def test_invalid_positions_raise_at_a_plan_or_the_next_call(device):
    """NaN positions given on the device raise when a call makes a plan; once one exists, a call does not wait for
    its positions' check, and the next call raises (its own positions checked anew)."""
    mesh = _mesh()
    tau = 2.5 * mesh.mean_edge_length
    good = wp.array(mesh.vertices, dtype=wp.vec3, device=device)
    v = mesh.vertices.copy()
    v[7] = np.nan
    bad = wp.array(v, dtype=wp.vec3, device=device)
    with pytest.raises(ValueError, match="positions: 1 of"):
        vw.vnc_soft(mesh, tau, positions=bad, tuning=EVERYWHERE)
    vw.vnc_soft(mesh, tau, positions=good, tuning=EVERYWHERE)
    H = vw.vnc_soft(mesh, tau, positions=bad, tuning=EVERYWHERE)[0].numpy()
    assert np.isnan(H).any()
    with pytest.raises(ValueError, match="positions: 1 of"):
        vw.vnc_soft(mesh, tau, positions=bad, tuning=EVERYWHERE)
    np.testing.assert_allclose(vw.vnc_soft(mesh, tau, positions=good, tuning=EVERYWHERE)[0].numpy(),
                               vw.vnc_soft(mesh, tau, positions=good, strategy="bvh")[0].numpy(), atol=2e-6)


def test_moving_scale_curve_and_total_complexity(device):
    """The scale curve and the total complexity S (sum of Eq. (4)) at positions given on the device, through the
    engine a flow holds: one plan for moving positions, equal to the BVH curve and a NumPy trapezoid sum."""
    mesh = _mesh()
    taus = vw.default_scales(mesh, 6)
    eng = vw.engine(mesh, device, tuning=EVERYWHERE)
    for k in range(4):
        x = wp.array(_wobble(mesh, k, 0.3), dtype=wp.vec3, device=device)
        H, mean = eng.scale_curve(taus, positions=x)
        ref = vw.scale_curve(mesh, taus, positions=x, strategy="bvh").H.numpy()
        np.testing.assert_allclose(H.numpy(), ref, atol=2e-6, err_msg=f"step {k}")
        np.testing.assert_allclose(mean.numpy(), ref.mean(1), rtol=1e-5, atol=1e-7)
        S = eng.total_complexity(taus, positions=x)
        h = ref.astype(np.float64)
        expect = np.trapezoid(np.abs(h - h.mean(1, keepdims=True)), taus, axis=0).sum()
        assert S == pytest.approx(expect, rel=1e-4)
    assert len([k for k in eng._plans if k[0] == "curve"]) == 1


def test_a_failed_capture_is_recorded_warns_once_and_runs_plain():
    """A call whose launches cannot be captured (here: its third run, the capture, raises) is not lost: that call
    and every later one with its key run as usual with fresh outputs, the failure is recorded with its message for
    benchmarks (vnc_warp._replay.capture_failures) and one RuntimeWarning names it; a second such key warns no more."""
    import warnings

    from vnc_warp import _replay
    from vnc_warp._plan import Pool

    device = wp.get_device("cpu")
    table = _replay.Replay(device, max_graphs=4)
    plain = Pool(device, "test", {}, None)
    runs = []

    def run(pool, fresh):
        runs.append(fresh)
        if len(runs) == 3:
            raise RuntimeError("a launch that cannot be captured")
        return [len(runs)]

    before = len(_replay.capture_failures())
    assert table.call(("k",), "unit", run, plain) == ([1], True)
    assert table.call(("k",), "unit", run, plain) == ([2], False)
    with pytest.warns(RuntimeWarning, match="graph capture of a 'unit' call on cpu failed .*cannot be captured"):
        assert table.call(("k",), "unit", run, plain) == ([4], True)
    assert table.call(("k",), "unit", run, plain) == ([5], True)
    assert table.graphs() == []
    assert _replay.capture_failures()[before:] == [("unit", "RuntimeError: a launch that cannot be captured")]
    runs.clear()
    other = _replay.Replay(device, max_graphs=4)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for _ in range(3):
            other.call(("k2",), "unit", run, plain)
    assert len(_replay.capture_failures()) == before + 2


@pytest.mark.parametrize("op", ["soft", "hard"])
def test_auto_matches_the_strategy_it_chooses_bit_for_bit(op, device):
    """``strategy="auto"`` is the strategy :func:`vnc_warp.choose_strategy` names, not an approximation of it: at a
    scale where it takes the grid and at one where it reads all pairs, its results, run as usual and replayed from a
    graph, equal those of that strategy named explicitly, bit for bit (same launches, same order of sums)."""
    mesh = _mesh(scale=0.4, offset=-3.0)
    variant = "soft" if op == "soft" else "hard"
    fn = vw.vnc_soft if op == "soft" else vw.vnc_hard
    chosen = set()
    for tau in (2.0 * mesh.mean_edge_length, 1.5 * mesh.bbox_diagonal):
        strategy = vw.choose_strategy(mesh, tau, variant=variant, device=device)
        chosen.add(strategy)
        for tuning in (EVERYWHERE, NOWHERE):
            auto = [fn(mesh, tau, device=device, tuning=tuning) for _ in range(4)]
            named = [fn(mesh, tau, device=device, tuning=tuning, strategy=strategy) for _ in range(4)]
            for (Ha, na), (Hs, ns) in zip(auto, named):
                np.testing.assert_array_equal(Ha.numpy(), Hs.numpy())
                np.testing.assert_array_equal(na.numpy(), ns.numpy())
    assert chosen == {"grid", "dense"}
