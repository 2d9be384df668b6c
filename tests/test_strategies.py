"""The pair-traversal strategies of the VNC operator ("grid", "dense", "bvh", "auto") give the same results,
equal to float64 dense references, for values, scale curves and gradients; the CUDA launch shape (warp-sized
query groups, candidates split over several threads) is exercised on the CPU device too."""

import numpy as np
import pytest
import torch
import trimesh
import warp as wp
from conftest import mesh_path
from reference import dense_ball_sums, dense_soft

import vnc_warp as vw
from vnc_warp import _pairs
from vnc_warp.kernels import vnc as _k
from vnc_warp.operators import _tier_sizes

STRATEGIES = ["grid", "dense", "bvh"]


def _bumpy_sphere(subdiv=3, seed=0):
    tm = trimesh.creation.icosphere(subdiv, radius=1.0)
    rng = np.random.default_rng(seed)
    tm.vertices *= (1.0 + 0.05 * rng.standard_normal(len(tm.vertices)))[:, None]
    return vw.load_mesh(tm)


@pytest.fixture
def cuda_launch_shape(monkeypatch):
    """Groups of 32 threads of QB queries each, split over 3 threads per box, as on a GPU, on whatever device runs."""
    monkeypatch.setattr(_pairs, "launch_shape", lambda device, count, per_thread=1, work=0.0: (32 * per_thread, 3))
    monkeypatch.setattr(_pairs, "queries_per_thread", lambda device, work, most: most)


def _taus(mesh):
    rng = np.random.default_rng(4)
    return {
        "small": 2.5 * mesh.mean_edge_length,
        "per-vertex": mesh.mean_edge_length * rng.uniform(1.5, 12.0, mesh.num_vertices),
        "whole mesh": 1.2 * mesh.bbox_diagonal,
    }


@pytest.mark.parametrize("strategy", STRATEGIES)
def test_soft_matches_dense_float64_every_strategy(strategy, device):
    """Eq. (3) from every strategy equals the float64 dense (V x E) reference at a small, a per-vertex and a
    whole-mesh scale."""
    mesh = _bumpy_sphere()
    v64 = torch.tensor(mesh.vertices, dtype=torch.float64)
    for name, tau in _taus(mesh).items():
        H, n = vw.vnc_soft(mesh, tau, device=device, strategy=strategy)
        Hr, nr = dense_soft(v64, mesh.faces, tau)
        np.testing.assert_allclose(H.numpy(), Hr.numpy(), rtol=1e-4, atol=1e-5 * np.abs(Hr.numpy()).max(),
                                   err_msg=f"{strategy}, {name}")
        np.testing.assert_allclose(n.numpy(), nr.numpy(), atol=2e-5, err_msg=f"{strategy}, {name}")


def test_soft_far_from_the_origin(cuda_launch_shape, device):
    """VNC-soft equals the float64 dense reference on a mesh 500 units across and 800 units from the origin, at
    scales from 1.5 mean edge lengths to the whole mesh (float32 offsets of nearby points lose digits there)."""
    base = _bumpy_sphere()
    mesh = vw.from_arrays(base.vertices * 250.0 + np.float32(800.0), base.faces)
    v64 = torch.tensor(mesh.vertices, dtype=torch.float64)
    l = mesh.mean_edge_length
    for tau in (1.5 * l, 4.0 * l, 0.7 * mesh.bbox_diagonal):
        Hr, nr = dense_soft(v64, mesh.faces, tau)
        for s in ("grid", "dense"):
            H, n = vw.vnc_soft(mesh, tau, device=device, strategy=s)
            np.testing.assert_allclose(H.numpy(), Hr.numpy(), rtol=1e-4, atol=1e-5 * np.abs(Hr.numpy()).max(),
                                       err_msg=f"{s}, tau={tau / l:.1f} l")
            np.testing.assert_allclose(n.numpy(), nr.numpy(), atol=2e-5, err_msg=f"{s}, tau={tau / l:.1f} l")


@pytest.mark.parametrize("shape", ["device", "warps", "warps, own boxes"])
def test_culled_row_walk(shape, monkeypatch, device):
    """The row walk of one query per thread that reads only the cells of a row some ball reaches (``walk_span``; on
    CUDA always, on the CPU with ``CULL_CPU``) misses no pair: VNC-soft and VNC-hard through the grid equal their
    float64 dense references, on a unit-sized mesh and on one 500 units across and 800 from the origin, from 1.5
    mean edge lengths to most of the mesh, with the device's launch shape and with groups of 32 threads split 3 ways
    (as on a GPU) sharing boxes or (``SPREAD`` 1.01) walking their own."""
    monkeypatch.setattr(_k, "CULL_CPU", True)
    if shape != "device":
        monkeypatch.setattr(_pairs, "launch_shape", lambda device, count, per_thread=1, work=0.0: (32 * per_thread, 3))
        monkeypatch.setattr(_pairs, "queries_per_thread", lambda device, work, most: 1)
    if shape == "warps, own boxes":
        monkeypatch.setattr(_pairs, "SPREAD", 1.01)
    base = _bumpy_sphere()
    for mesh in (base, vw.from_arrays(base.vertices * 250.0 + np.float32(800.0), base.faces)):
        v64 = torch.tensor(mesh.vertices, dtype=torch.float64)
        idx = np.arange(0, mesh.num_vertices, 7)
        l = mesh.mean_edge_length
        for tau in (1.5 * l, 4.0 * l, 0.7 * mesh.bbox_diagonal):
            H, n = vw.vnc_soft(mesh, tau, device=device, strategy="grid")
            Hr, nr = dense_soft(v64, mesh.faces, tau)
            np.testing.assert_allclose(H.numpy(), Hr.numpy(), rtol=1e-4, atol=1e-5 * np.abs(Hr.numpy()).max(),
                                       err_msg=f"soft, tau={tau / l:.1f} l")
            np.testing.assert_allclose(n.numpy(), nr.numpy(), atol=2e-5, err_msg=f"soft, tau={tau / l:.1f} l")
            h = vw.vnc_hard(mesh, tau, device=device, strategy="grid")[0].numpy()
            num, den = dense_ball_sums(mesh.vertices, mesh.faces, mesh.vertices[idx], tau, 6.0)
            np.testing.assert_allclose(h[idx], num / (2 * den), rtol=2e-4, atol=2e-6 * np.abs(num / den).max(),
                                       err_msg=f"hard, tau={tau / l:.1f} l")


@pytest.mark.parametrize("spread", [None, 1.01])
def test_strategies_agree_with_cuda_launch_shape(cuda_launch_shape, spread, monkeypatch, device):
    """With warp-sized groups and split candidates (the CUDA shape, V not a multiple of 32), "grid" and "dense"
    equal the per-thread BVH for VNC-soft, VNC-hard and Eq. (1); ``spread=1.01`` makes most groups walk per-thread
    boxes."""
    if spread is not None:
        monkeypatch.setattr(_pairs, "SPREAD", spread)
    mesh = _bumpy_sphere()
    assert mesh.num_vertices % 32 != 0
    for name, tau in _taus(mesh).items():
        Hb, nb = vw.vnc_soft(mesh, tau, device=device, strategy="bvh")
        hb = vw.vnc_hard(mesh, tau, device=device, strategy="bvh")[0].numpy()
        ib = vw.integrated_mean_curvature(mesh, tau, device=device, strategy="bvh").numpy()
        for s in ("grid", "dense"):
            H, n = vw.vnc_soft(mesh, tau, device=device, strategy=s)
            np.testing.assert_allclose(H.numpy(), Hb.numpy(), atol=2e-6, err_msg=f"soft {s}, {name}")
            np.testing.assert_allclose(n.numpy(), nb.numpy(), atol=5e-5, err_msg=f"soft {s}, {name}")
            h = vw.vnc_hard(mesh, tau, device=device, strategy=s)[0].numpy()
            np.testing.assert_allclose(h, hb, atol=2e-6, err_msg=f"hard {s}, {name}")
            i = vw.integrated_mean_curvature(mesh, tau, device=device, strategy=s).numpy()
            np.testing.assert_allclose(i, ib, rtol=1e-5, atol=1e-5 * np.abs(ib).max(), err_msg=f"Eq. 1 {s}, {name}")


@pytest.mark.parametrize("strategy", STRATEGIES)
@pytest.mark.parametrize("kappa", [6.0, None])
def test_hard_matches_dense_float64_every_strategy(strategy, kappa, device):
    """Eq. (2) from every strategy equals the float64 dense reference on trimesh's exact segment/ball lengths."""
    mesh = vw.load_mesh(mesh_path("penguin.obj"))
    idx = np.arange(0, mesh.num_vertices, 11)
    for tau in (3.0 * mesh.mean_edge_length, 0.6 * mesh.bbox_diagonal):
        H = vw.vnc_hard(mesh, tau, kappa=kappa, device=device, strategy=strategy)[0].numpy()
        num, den = dense_ball_sums(mesh.vertices, mesh.faces, mesh.vertices[idx], tau, kappa)
        np.testing.assert_allclose(H[idx], num / (2 * den), rtol=2e-4, atol=2e-6)


@pytest.mark.parametrize("form", ["unit", "half", "pieces"])
@pytest.mark.parametrize("runs", ["chords", "chunks", "chunks-no-vote"])
@pytest.mark.parametrize("prefilter", [False, True], ids=["all", "prefilter"])
def test_every_ball_kernel_variant(form, runs, prefilter, cuda_launch_shape, monkeypatch, device):
    """Each variant of the ball kernel (``bench/tune.py`` times them all; ``ball_variant`` picks one per traversal):
    edge records ("unit" or "half" whole edges through edge-length tiers, or "pieces" of the edges, in unit
    records), chunked runs (with and without the warp vote that sends a run some threads of a CUDA warp need the
    chords of to all of them: kernels.vnc.VOTE), prefilter, 4 queries per thread over 3 splits; Eq. (2) with and
    without the Gaussian equals the float64 dense reference from a ball of one edge length (no run inside it) to the
    whole mesh (every run inside), through the grid (scan-like long edges) and densely."""
    monkeypatch.setattr(_pairs, "PIECES", form == "pieces")
    monkeypatch.setattr(_k, "BALL_VARIANT", {"prefilter": prefilter, "form": "unit" if form == "pieces" else form,
                                             "chunks": runs != "chords"})
    monkeypatch.setattr(_k, "VOTE", runs != "chunks-no-vote")
    mesh = _bumpy_sphere(subdiv=3, seed=3)
    v = mesh.vertices.copy()
    v[::7] *= 1.25  # spikes: long edges, several length tiers
    mesh = vw.load_mesh(trimesh.Trimesh(v, mesh.faces, process=False))
    idx = np.arange(0, mesh.num_vertices, 13)
    for tau in (1.0 * mesh.mean_edge_length, 7.0 * mesh.mean_edge_length, 1.2 * mesh.bbox_diagonal):
        for kappa in (None, 6.0):
            num, den = dense_ball_sums(mesh.vertices, mesh.faces, mesh.vertices[idx], tau, kappa)
            for strategy in ("grid", "dense"):
                H = vw.vnc_hard(mesh, tau, kappa=kappa, device=device, strategy=strategy)[0].numpy()
                np.testing.assert_allclose(H[idx], num / (2 * den), rtol=2e-4, atol=2e-6,
                                           err_msg=f"{strategy}, tau={tau:.3g}, kappa={kappa}")


def test_ball_variant_rule():
    """The kernel variant each ball traversal takes (``kernels.vnc.ball_variant``): the midpoint prefilter, with
    "half" records, for every grid traversal on the CPU and never on CUDA (the row walk already skips the cells
    beyond a warp's balls) nor in a dense traversal; "unit" records otherwise and for several queries per thread;
    runs of records from CHUNK_REACH (per device kind) and over one cell."""
    v = _k.ball_variant
    for reach in (1.0, 2.0, 8.0, 40.0):
        assert v("grid", 1, reach, cuda=False)["prefilter"]
        assert v("grid", 1, reach, cuda=False)["form"] == "half"
        assert not v("dense", 1, reach, cuda=False)["prefilter"]
        for per_thread in (1, 4):
            chosen = v("grid", per_thread, reach)
            assert not chosen["prefilter"] and chosen["form"] == "unit"
    assert v("grid", 4, 2.0, cuda=False)["form"] == "unit"
    for cuda in (False, True):
        reach = _k.CHUNK_REACH["cuda" if cuda else "cpu"]
        assert not v("grid", 1, 0.99 * reach, cuda=cuda)["chunks"]
        assert v("grid", 1, reach, cuda=cuda)["chunks"]
    assert v("grid", 1, 2.0, one_cell=True)["chunks"]


def _numpy_group_boxes(x, radius, order, size, per_thread, margin, pad, origin, inv_h, dims):
    """float32 reference of build_groups' boxes: per group of ``size`` sorted queries, the cells reached by its threads'
    balls (``per_thread`` queries each), marked ``lo.x = -1`` when that box holds more than SPREAD times the cells of
    the largest box of one thread."""
    f32 = np.float32
    los, his = [], []
    for g0 in range(0, len(order), size):
        clos, chis = [], []
        for t0 in range(g0, min(g0 + size, len(order)), per_thread):
            k = order[t0:min(t0 + per_thread, g0 + size, len(order))]
            e = (radius[k] + f32(margin)).astype(f32)[:, None]
            lo = (x[k] - e).min(0) - f32(pad)
            hi = (x[k] + e).max(0) + f32(pad)
            cell = lambda q: np.clip(np.floor((q - origin) * f32(inv_h)), 0, dims - 1).astype(int)  # noqa: E731
            clos.append(cell(lo))
            chis.append(cell(hi))
        clos, chis = np.array(clos), np.array(chis)
        lo, hi = clos.min(0), chis.max(0)
        most = np.prod(chis - clos + 1, axis=1).max()
        if np.prod(hi - lo + 1) > _pairs.SPREAD * most:
            lo = lo.copy()
            lo[0] = -1
        los.append(lo)
        his.append(hi)
    return np.array(los), np.array(his)


@pytest.mark.parametrize("per_thread,size", [(1, 32), (4, 128), (1, 16), (2, 8)])
def test_group_boxes_match_numpy(per_thread, size, monkeypatch, device):
    """The group boxes of two traversals at once (two pads, each on a grid of its own), gathered by per-warp maxima
    and atomics on CUDA (kernels.vnc.group_max; groups of fewer than 32 threads share a warp), equal a float32 numpy
    reference: two clusters of balls of random radii, so that some groups span both and walk per-thread boxes, and
    a count that leaves the last group partial."""
    monkeypatch.setattr(_pairs, "launch_shape", lambda device, count, per_thread=1, work=0.0: (size, 1))
    rng = np.random.default_rng(11)
    n = 1000
    pts = np.concatenate([rng.normal(0.0, 0.3, (n // 2, 3)), rng.normal(4.0, 0.3, (n - n // 2, 3))]).astype(np.float32)
    rad = rng.uniform(0.05, 0.4, n).astype(np.float32)
    x = wp.array(pts, dtype=wp.vec3, device=device)
    radius = wp.array(rad, dtype=wp.float32, device=device)
    b = _pairs.bounds(x, radius)
    pads, hs = [0.1, 0.7], [0.15, 0.45]
    cells = []
    for h in hs:
        dims = np.floor((b.hi - b.lo) / h).astype(int) + 1
        cells.append(_pairs.Cells(None, None, wp.vec3(*b.lo), 1.0 / h, wp.vec3i(*[int(d) for d in dims])))
    groups = _pairs.build_groups(x, radius, pads, cells, b, spatial_order=True, per_thread=per_thread)
    order = groups[0].order.numpy()
    assert sorted(order.tolist()) == list(range(n))
    margin = 1e-6 * max(float(np.abs(np.concatenate([b.lo, b.hi])).max()), b.rmax)
    for grp, pad, c in zip(groups, pads, cells):
        lo, hi = _numpy_group_boxes(pts, rad, order, size, per_thread, margin, pad, np.asarray(b.lo, np.float32),
                                    c.inv_h, np.array(tuple(c.dims)))
        got_lo = np.array([tuple(v) for v in grp.box_lo.numpy()])
        got_hi = np.array([tuple(v) for v in grp.box_hi.numpy()])
        assert (lo[:, 0] == -1).any() and (lo[:, 0] >= 0).any()  # both kinds of group
        np.testing.assert_array_equal(got_hi, hi, err_msg=f"pad {pad}")
        np.testing.assert_array_equal(got_lo, lo, err_msg=f"pad {pad}")


@pytest.mark.parametrize("dense_tier_pairs", [0, 1 << 40], ids=["grid-tiers", "dense-tiers"])
def test_long_edges_are_traversed_in_tiers(cuda_launch_shape, dense_tier_pairs, monkeypatch, device):
    """A mesh whose edges span 0.1 to 3 units (a cylinder's sides and rings) is traversed by the ball kernels in
    edge-length tiers (after the first, each through the grid or, when it has few pairs, densely); Eqs. (1)-(2)
    (unweighted, where a long edge far from its midpoint still counts) equal the dense float64 reference for every
    strategy (with the tiers, not pieces of the edges: PIECES off)."""
    monkeypatch.setattr(_pairs, "DENSE_TIER_PAIRS", {"cuda": dense_tier_pairs, "cpu": dense_tier_pairs})
    monkeypatch.setattr(_pairs, "PIECES", False)
    tm = trimesh.creation.cylinder(radius=1.0, height=3.0, sections=48)
    mesh = vw.load_mesh(tm)
    x = wp.array(mesh.vertices, dtype=wp.vec3, device=device)
    f = vw.edge_fields(mesh, positions=x)
    tau = wp.full(mesh.num_vertices, 0.4, dtype=wp.float32, device=device)
    b = _pairs.bounds(x, tau, f.length)
    plans = _pairs.ball_plans(x, tau, f.mid, f.length, b, "grid", tier_size=lambda lo, hi: 1)
    assert len(plans) > 1
    dense_tiers = [tuple(c.dims) == (1, 1, 1) for c, _ in plans[1:]]
    assert all(dense_tiers) if dense_tier_pairs else not any(dense_tiers)
    if not dense_tier_pairs:  # each grid tier's cells in proportion to its reach: coarser for longer edges
        inv_h = [c.inv_h for c, _ in plans]
        assert all(a > b for a, b in zip(inv_h, inv_h[1:])), inv_h
    for r in (0.4, 1.5):
        num, den = dense_ball_sums(mesh.vertices, mesh.faces, mesh.vertices, r, None)
        for s in STRATEGIES:
            H = vw.vnc_hard(mesh, r, kappa=None, device=device, strategy=s)[0].numpy()
            np.testing.assert_allclose(H, num / (2 * den), rtol=2e-4, atol=2e-6, err_msg=f"{s}, r={r}")
            got = vw.integrated_mean_curvature(mesh, r, device=device, strategy=s).numpy()
            np.testing.assert_allclose(got, 0.5 * num, rtol=2e-4, atol=1e-5, err_msg=f"Eq. 1 {s}, r={r}")


@pytest.mark.parametrize("pieces", [False, True], ids=["tiers", "pieces"])
def test_first_tier_takes_all_edges_when_balls_barely_grow(pieces, monkeypatch, device):
    """An icosphere with one vertex pulled out (its edges up to ~1.7 mean lengths, just past the first tier): at a
    radius of many edge lengths the longest edge widens the balls by under TIER_GROW, so one traversal takes every
    edge whole; at one edge length it takes tiers, or pieces of the edges (PIECES). Both equal the float64 reference
    of Eqs. (1)-(2)."""
    monkeypatch.setattr(_pairs, "PIECES", pieces)
    tm = trimesh.creation.icosphere(subdivisions=3, radius=40.0)
    v = tm.vertices.copy()
    v[0] *= 1.2
    mesh = vw.load_mesh(trimesh.Trimesh(v, tm.faces, process=False))
    x = wp.array(mesh.vertices, dtype=wp.vec3, device=device)
    f = vw.edge_fields(mesh, positions=x)
    L = f.length.numpy()
    assert 1.6 < L.max() / L.mean() < 2.0
    idx = np.arange(0, mesh.num_vertices, 5)
    for mult, tiers in ((1.0, True), (40.0, False)):
        r = mult * float(L.mean())
        tau = wp.full(mesh.num_vertices, r, dtype=wp.float32, device=device)
        b = _pairs.bounds(x, tau, f.length)
        plans = _pairs.ball_plans(x, tau, f.mid, f.length, b, "grid")
        assert (len(plans) > 1) == tiers, (mult, len(plans))
        assert _pairs.uses_pieces("grid", b) == (tiers and pieces)
        num, den = dense_ball_sums(mesh.vertices, mesh.faces, mesh.vertices[idx], r, None)
        H = vw.vnc_hard(mesh, r, kappa=None, device=device, strategy="grid")[0].numpy()
        np.testing.assert_allclose(H[idx], num / (2 * den), rtol=2e-4, atol=2e-6, err_msg=f"r={mult} l")


@pytest.mark.parametrize("dense_tier_pairs", [0, 1 << 40], ids=["grid-tiers", "dense-tiers"])
@pytest.mark.parametrize("busy", [True, False], ids=["busy", "light"])
def test_later_tiers_take_fewer_splits(dense_tier_pairs, busy, monkeypatch, device):
    """Splits that follow each traversal's expected work (as on a GPU): the long-edge tiers of the cylinder take fewer
    than the first, add their partial sums to its first rows, and Eqs. (1)-(2) still equal the float64 reference.
    Busy (several queries per thread) or light (one), every tier like the first (tiers, not pieces: PIECES off)."""
    monkeypatch.setattr(_pairs, "DENSE_TIER_PAIRS", {"cuda": dense_tier_pairs, "cpu": dense_tier_pairs})
    monkeypatch.setattr(_pairs, "PIECES", False)
    monkeypatch.setattr(_pairs, "launch_shape", lambda device, count, per_thread=1, work=0.0:
                        (32 * per_thread, int(np.clip(work / 20.0, 1, 6))))
    monkeypatch.setattr(_pairs, "queries_per_thread",
                        lambda device, work, most: most if busy else 1)
    mesh = vw.load_mesh(trimesh.creation.cylinder(radius=1.0, height=3.0, sections=48))
    x = wp.array(mesh.vertices, dtype=wp.vec3, device=device)
    f = vw.edge_fields(mesh, positions=x)
    tau = wp.full(mesh.num_vertices, 0.4, dtype=wp.float32, device=device)
    b = _pairs.bounds(x, tau, f.length)
    plans = _pairs.ball_plans(x, tau, f.mid, f.length, b, "grid", tier_size=_tier_sizes(mesh),
                              max_per_thread=_k.QB)
    splits = [g.splits for _, g in plans]
    assert len(plans) > 1 and max(splits[1:]) < splits[0], splits
    assert {g.per_thread for _, g in plans} == {_k.QB if busy else 1}
    assert any(tuple(c.dims) == (1, 1, 1) for c, _ in plans) == bool(dense_tier_pairs)
    for r in (0.4, 1.5):
        num, den = dense_ball_sums(mesh.vertices, mesh.faces, mesh.vertices, r, None)
        H = vw.vnc_hard(mesh, r, kappa=None, device=device, strategy="grid")[0].numpy()
        np.testing.assert_allclose(H, num / (2 * den), rtol=2e-4, atol=2e-6, err_msg=f"r={r}")
        got = vw.integrated_mean_curvature(mesh, r, device=device, strategy="grid").numpy()
        np.testing.assert_allclose(got, 0.5 * num, rtol=2e-4, atol=1e-5, err_msg=f"Eq. 1, r={r}")


def _cylinder(scale: float):
    """A cylinder of radius ``scale`` whose sides are single edges 3 x ``scale`` long and whose rings' edges are
    short: edges of 0.1 to 3 x ``scale``."""
    tm = trimesh.creation.cylinder(radius=1.0, height=3.0, sections=48)
    tm.vertices *= scale
    return vw.load_mesh(tm)


def _spiky(scale: float):
    """An icosphere of radius ``scale`` (mean edge ~0.1 ``scale``) with every 40th vertex pulled out to 2.5 ``scale``:
    spikes whose edges are up to 7 mean edge lengths long."""
    tm = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    v = tm.vertices.copy()
    v[::40] *= 2.5
    return vw.load_mesh(trimesh.Trimesh(v * scale, tm.faces, process=False))


def _piece_records(mesh, r, device):
    """piece_plan of the mesh's vertices at radius ``r`` and its records (pack_piece_sources):
    ``(cells, pieces, seg_m, seg_h, val, edge fields, bounds)``."""
    x = wp.array(mesh.vertices, dtype=wp.vec3, device=device)
    f = vw.edge_fields(mesh, positions=x)
    tau = wp.full(mesh.num_vertices, r, dtype=wp.float32, device=device)
    b = _pairs.bounds(x, tau, f.length)
    assert _pairs.uses_pieces("grid", b)
    cells, groups, pieces = _pairs.piece_plan(x, tau, x, f.edges, f.length, b, "grid")
    seg_m, seg_h, val = (wp.empty(pieces.capacity, dtype=wp.vec4, device=device) for _ in range(3))
    wp.launch(_k.pack_piece_sources, dim=pieces.capacity,
              inputs=[cells.order, pieces.piece_edge, pieces.piece_index, pieces.counts, x, f.edges, f.angle,
                      f.normal], outputs=[seg_m, seg_h, val], device=device)
    return cells, pieces, seg_m, seg_h, val, f, b


@pytest.mark.parametrize("scale", [0.15, 500.0])
def test_pieces_tile_every_edge(scale, device):
    """piece_plan (kernels.vnc.piece_counts, piece_keys, pack_piece_sources) against NumPy: edge j is cut into
    ceil(L_j / P) pieces (float32, as on the device), the pieces' intervals ``[-b, a]`` along the edge's unit direction
    from its midpoint meet end to end from ``-L_j / 2`` to ``L_j / 2``, none longer than P, every record holds its
    edge's midpoint, direction, angle and normal, each piece sits in the grid cell its sorted position says (its
    centre within that cell), the slots past the last piece hold nothing, and the host's capacity is enough."""
    mesh = _cylinder(scale)
    cells, pieces, seg_m, seg_h, val, f, b = _piece_records(mesh, 0.4 * scale, device)
    L = f.length.numpy()
    P = np.float32(pieces.length)
    k = np.maximum(np.ceil(L * (np.float32(1.0) / P)), 1).astype(int)
    np.testing.assert_array_equal(pieces.counts.numpy(), k)
    assert k.max() > 1 and (k == 1).any()
    first = cells.first.numpy()
    n = int(first[-1])
    assert n == k.sum() and pieces.capacity == n  # capacity=None: the count read back
    assert _pairs.piece_capacity(np.sort(L), pieces.length) >= n
    order = cells.order.numpy()
    edge = pieces.piece_edge.numpy()[order[:n]]
    sm, sh, sv = seg_m.numpy()[:n], seg_h.numpy()[:n], val.numpy()[:n]
    ev = f.edges.numpy()
    xa, xb = mesh.vertices[ev[:, 0]].astype(np.float64), mesh.vertices[ev[:, 1]].astype(np.float64)
    tol = 1e-6 * scale
    np.testing.assert_allclose(sm[:, :3], (0.5 * (xa + xb))[edge], atol=tol)
    np.testing.assert_allclose(sh[:, :3], ((xb - xa) / np.linalg.norm(xb - xa, axis=1)[:, None])[edge], atol=1e-6)
    np.testing.assert_array_equal(sv[:, 0], f.angle.numpy()[edge])
    np.testing.assert_array_equal(sv[:, 1:], f.normal.numpy()[edge])
    assert (sm[:, 3] + sh[:, 3] <= P * (1 + 1e-5)).all()
    for j in range(len(L)):
        a, bb = sm[edge == j, 3], sh[edge == j, 3]
        s_ = np.argsort(-bb)
        a, bb = a[s_], bb[s_]
        assert len(a) == k[j]
        np.testing.assert_allclose([-bb[0], a[-1]], [-0.5 * L[j], 0.5 * L[j]], atol=tol)
        np.testing.assert_array_equal(a[:-1], -bb[1:])  # end to end, no gap or overlap
    # each piece's centre inside the cell of its sorted position
    centre = sm[:, :3].astype(np.float64) + sh[:, :3] * (0.5 * (sm[:, 3] - sh[:, 3]))[:, None]
    cell = np.searchsorted(first, np.arange(n), side="right") - 1
    dims = np.array(tuple(cells.dims))
    cz, rest = np.divmod(cell, dims[0] * dims[1])
    cy, cx = np.divmod(rest, dims[0])
    lo = np.asarray(b.lo) + np.stack([cx, cy, cz], 1) / cells.inv_h
    assert (centre >= lo - tol).all() and (centre <= lo + 1.0 / cells.inv_h + tol).all()
    assert (pieces.piece_edge.numpy()[order[n:]] == -1).all()


@pytest.mark.parametrize("scale", [0.15, 500.0])
def test_chunk_boxes_hold_every_piece(scale, device):
    """kernels.vnc.chunk_boxes over the unit records of pieces (a piece ``m + u d``, ``u`` in ``[-b, a]``, a != b off
    the edge's middle) equals the NumPy box of both ends of every piece in each run of CHUNK sorted records, and
    leaves out the slots past the last piece."""
    mesh = _spiky(scale)
    cells, pieces, seg_m, seg_h = _piece_records(mesh, 2.0 * mesh.mean_edge_length, device)[:4]
    n = int(cells.first.numpy()[-1])
    assert pieces.counts.numpy().max() >= 5
    chunk = int(_k.CHUNK)
    nchunks = -(-pieces.capacity // chunk)
    lo, hi = (wp.empty(nchunks, dtype=wp.vec3, device=device) for _ in range(2))
    wp.launch(_k.chunk_boxes, dim=nchunks, inputs=[seg_m, seg_h, 1, cells.first, cells.first], outputs=[lo, hi],
              device=device)
    sm, sh = seg_m.numpy()[:n].astype(np.float64), seg_h.numpy()[:n].astype(np.float64)
    assert (np.abs(sm[:, 3] - sh[:, 3]) > 1e-3 * sm[:, 3]).any()
    ends = np.stack([sm[:, :3] + sh[:, :3] * sm[:, 3:], sm[:, :3] - sh[:, :3] * sh[:, 3:]], 1)
    for c in range(-(-n // chunk)):
        e = ends[c * chunk:(c + 1) * chunk].reshape(-1, 3)
        np.testing.assert_allclose(lo.numpy()[c], e.min(0), atol=1e-6 * scale, err_msg=f"run {c}")
        np.testing.assert_allclose(hi.numpy()[c], e.max(0), atol=1e-6 * scale, err_msg=f"run {c}")


@pytest.mark.parametrize("scale", [0.15, 500.0])
@pytest.mark.parametrize("kappa", [None, 6.0])
def test_pieces_match_float64(scale, kappa, monkeypatch, device):
    """VNC-hard and Eq. (1) through pieces of the edges (spikes up to 7 mean edge lengths long, cut into up to 4-5
    pieces), with the host's capacity (a scalar radius) and the device's count (per-vertex radii), equal the float64
    dense reference on trimesh's segment/ball lengths, and trimesh's own measure of Eq. (1). Fine cells (a tenth of
    the reach) and, on the CPU, each thread walking its own ball's box: a pad short of half a piece misses pieces
    (0.3 of a piece fails here, unweighted; 0.4 hides in the boxes' rounding to whole cells)."""
    monkeypatch.setattr(_pairs, "CELL_FRACTION", 0.1)
    monkeypatch.setattr(_pairs, "CELLS_PER_SOURCE", 1000)
    monkeypatch.setattr(_pairs, "CPU_PIECES", None)  # pieces sorted per call (test_kept_pieces_serve_every_radius)
    mesh = _spiky(scale)
    tm = mesh.to_trimesh()
    for mult in (2.0, 4.0):
        r = mult * mesh.mean_edge_length
        assert _piece_records(mesh, r, device)[1].counts.numpy().max() >= 4
        num, den = dense_ball_sums(mesh.vertices, mesh.faces, mesh.vertices, r, kappa)
        for tau in (r, wp.full(mesh.num_vertices, r, dtype=wp.float32, device=device)):
            H = vw.vnc_hard(mesh, tau, kappa=kappa, device=device, strategy="grid")[0].numpy()
            np.testing.assert_allclose(H, num / (2 * den), rtol=2e-4, atol=2e-6, err_msg=f"r={mult} l x {scale}")
        if kappa is None:
            pts = mesh.vertices[::3]
            got = vw.integrated_mean_curvature(mesh, r, pts, device=device, strategy="grid").numpy()
            ref = trimesh.curvature.discrete_mean_curvature_measure(tm, pts, r)
            np.testing.assert_allclose(got, ref, rtol=2e-4, atol=1e-5 * np.abs(ref).max())


@pytest.mark.parametrize("cpu_pieces", [None, (1.0, 0.2)], ids=["shipped", "fine-cells"])
@pytest.mark.parametrize("scale", [0.15, 500.0])
def test_kept_pieces_serve_every_radius(scale, cpu_pieces, monkeypatch):
    """On the CPU the pieces of a mesh's own edges are sorted once and kept with it (CPU_PIECES): calls at 1.5, 4 and
    9 mean edge lengths (the last testing runs of records, CHUNK_REACH) all read the one kept grid, and Eq. (1) at
    off-vertex centres equals trimesh's measure, VNC-hard at the vertices (a scalar radius, and per-vertex radii on
    the device, Gaussian-weighted) the float64 reference. With pieces of one edge length in cells of a fifth (a
    ball's box then hugs it), a pad of 0.3 of a piece misses pieces. The public edge_fields are the caller's own:
    writing into them changes no later call. New vertices get new pieces."""
    if cpu_pieces is not None:
        monkeypatch.setattr(_pairs, "CPU_PIECES", cpu_pieces)
        monkeypatch.setattr(_pairs, "CELLS_PER_SOURCE", 1000)
    device = wp.get_device("cpu")
    mesh = _spiky(scale)
    tm = mesh.to_trimesh()
    f = vw.edge_fields(mesh, device=device)
    for a in (f.mid, f.length, f.angle, f.normal):
        a.zero_()
    rng = np.random.default_rng(7)
    pts = mesh.vertices[::4] + rng.normal(scale=0.3 * mesh.mean_edge_length, size=(len(mesh.vertices[::4]), 3))
    kept = []
    for mult in (1.5, 4.0, 9.0):
        r = mult * mesh.mean_edge_length
        got = vw.integrated_mean_curvature(mesh, r, pts, device=device, strategy="grid").numpy()
        ref = trimesh.curvature.discrete_mean_curvature_measure(tm, pts, r)
        np.testing.assert_allclose(got, ref, rtol=2e-4, atol=1e-5 * np.abs(ref).max(), err_msg=f"r={mult} l")
        # unweighted: at a spike's tip every edge's midpoint is 3.5 l away, and the weights of Eq. (2) at 1.5 l
        # (e^-98) are float32 denormals, 2e-4 off whatever the traversal
        num, den = dense_ball_sums(mesh.vertices, mesh.faces, mesh.vertices, r, None)
        H = vw.vnc_hard(mesh, r, kappa=None, device=device, strategy="grid")[0].numpy()
        np.testing.assert_allclose(H, num / (2 * den), rtol=2e-4, atol=2e-6, err_msg=f"r={mult} l")
        if mult < 9.0:
            # per-vertex radii on the device (the bounds read back), weighted: away from the spikes' tips, whose
            # weights are float32 denormals (above)
            radii = r * rng.uniform(0.8, 1.2, mesh.num_vertices)
            num, den = dense_ball_sums(mesh.vertices, mesh.faces, mesh.vertices, radii, 6.0)
            tau = wp.array(radii.astype(np.float32), dtype=wp.float32, device=device)
            H = vw.vnc_hard(mesh, tau, device=device, strategy="grid")[0].numpy()
            ok = den > 1e-30
            assert ok.mean() > 0.9
            np.testing.assert_allclose(H[ok], (num / (2 * den))[ok], rtol=2e-4, atol=2e-6, err_msg=f"r={mult} l")
        kept.append([v for k, v in mesh._cache.items() if isinstance(k, tuple) and k[0] == "cpu_pieces"])
    assert len(kept[0]) == 1 and all(len(k) == 1 and k[0][1] is kept[0][0][1] for k in kept)
    pieces = kept[0][0][1].grid.pieces
    assert pieces.counts.numpy().max() >= 3 and pieces.length == pytest.approx(
        _pairs.CPU_PIECES[0] * mesh.mean_edge_length, rel=1e-3)
    # the same mesh with new vertices (a mesh's arrays are replaced, never written): new pieces
    mesh.vertices = (mesh.vertices * np.array([1.3, 1.0, 0.8], np.float32)).astype(np.float32)
    r = 4.0 * mesh.mean_edge_length
    got = vw.integrated_mean_curvature(mesh, r, pts, device=device, strategy="grid").numpy()
    ref = trimesh.curvature.discrete_mean_curvature_measure(mesh.to_trimesh(), pts, r)
    np.testing.assert_allclose(got, ref, rtol=2e-4, atol=1e-5 * np.abs(ref).max(), err_msg="new vertices")


def test_kept_pieces_not_made_inside_a_capture():
    """Arrays made while a graph is captured hold their values only once it runs: a CPU call inside a user's capture
    keeps no pieces (a later call, the graph never launched, is still right), and uses pieces kept before."""
    device = wp.get_device("cpu")
    mesh = _spiky(1.0)
    tm = mesh.to_trimesh()
    pts = mesh.vertices[::3]
    r = 3.0 * mesh.mean_edge_length
    ref = trimesh.curvature.discrete_mean_curvature_measure(tm, pts, r)
    vw.integrated_mean_curvature(mesh, r, pts, device=device, strategy="bvh")  # the vertices' copy, outside
    for k in [k for k in mesh._cache if isinstance(k, tuple) and k[0] in ("cpu_pieces", "edge_fields")]:
        del mesh._cache[k]
    with wp.ScopedCapture(device=device):
        vw.integrated_mean_curvature(mesh, r, pts, device=device, strategy="grid")
        kept = set(mesh._cache)
    assert not [k for k in kept if isinstance(k, tuple) and k[0] in ("cpu_pieces", "edge_fields")], kept
    got = vw.integrated_mean_curvature(mesh, r, pts, device=device, strategy="grid").numpy()
    np.testing.assert_allclose(got, ref, rtol=2e-4, atol=1e-5 * np.abs(ref).max())
    # at the vertices (whose call's scratch the device's pool keeps alive for the graph)
    with wp.ScopedCapture(device=device) as capture:
        out = vw.integrated_mean_curvature(mesh, 2.0 * r, device=device, strategy="grid")
    wp.capture_launch(capture.graph)
    ref2 = trimesh.curvature.discrete_mean_curvature_measure(tm, mesh.vertices, 2.0 * r)
    np.testing.assert_allclose(out.numpy(), ref2, rtol=2e-4, atol=1e-5 * np.abs(ref2).max())


def test_threads_with_far_apart_balls(cuda_launch_shape, device):
    """Ball centres in two clusters at opposite ends of a mesh, so that one thread holds queries from both (its box
    would span the mesh): it walks each ball's box in turn, and Eq. (1) still equals trimesh's measure, every edge
    counted once per ball."""
    mesh = vw.load_mesh(mesh_path("spot_lowres.obj"))
    tm = mesh.to_trimesh()
    v = mesh.vertices
    ends = [np.argmin(v[:, 2]), np.argmax(v[:, 2])]
    # three vertices at each end (overlapping balls: a ball walked twice would be counted twice)
    pts = np.concatenate([v[np.argsort(np.linalg.norm(v - v[e], axis=1))[:3]] for e in ends])
    r = 2.0 * mesh.mean_edge_length
    got = vw.integrated_mean_curvature(mesh, r, pts, device=device, strategy="grid").numpy()
    ref = np.array([trimesh.curvature.discrete_mean_curvature_measure(tm, p[None], r)[0] for p in pts])
    assert np.abs(ref).min() > 1e-4
    np.testing.assert_allclose(got, ref, rtol=2e-4, atol=2e-5 * np.abs(ref).max())


@pytest.mark.parametrize("strategy", STRATEGIES)
def test_integrated_mean_curvature_every_strategy(strategy, device):
    """Eq. (1) at off-surface centres with per-point radii (some centres outside the mesh's box) equals trimesh
    for every strategy."""
    mesh = vw.load_mesh(mesh_path("spot_lowres.obj"))
    tm = mesh.to_trimesh()
    rng = np.random.default_rng(5)
    pts = mesh.vertices[rng.choice(mesh.num_vertices, 30, replace=False)] * 1.05
    radii = mesh.mean_edge_length * rng.uniform(1.0, 30.0, 30)
    got = vw.integrated_mean_curvature(mesh, radii, pts, device=device, strategy=strategy).numpy()
    ref = np.array([trimesh.curvature.discrete_mean_curvature_measure(tm, p[None], r)[0] for p, r in zip(pts, radii)])
    np.testing.assert_allclose(got, ref, rtol=2e-4, atol=2e-5 * np.abs(ref).max())


@pytest.mark.parametrize("variant,kappa", [("soft", 6.0), ("hard", 6.0), ("hard", None)])
def test_scale_curve_every_strategy(variant, kappa, cuda_launch_shape, device):
    """One-traversal scale curves (18 scales: a chunk of 16 and one of 2) equal separate single-scale BVH calls
    for every strategy, with the CUDA launch shape."""
    mesh = _bumpy_sphere()
    taus = vw.default_scales(mesh, 18)
    op = vw.vnc_soft if variant == "soft" else vw.vnc_hard
    ref = np.stack([op(mesh, t, kappa=kappa, device=device, strategy="bvh")[0].numpy() for t in taus])
    for s in ("grid", "dense", "bvh", "auto"):
        curve = vw.scale_curve(mesh, taus, variant, kappa=kappa, device=device, strategy=s)
        np.testing.assert_allclose(curve.H.numpy(), ref, atol=2e-6, err_msg=s)
        np.testing.assert_allclose(curve.mean.numpy(), ref.mean(1), rtol=1e-5, atol=1e-7, err_msg=s)


@pytest.mark.parametrize("strategy", STRATEGIES)
def test_gradient_every_strategy(strategy, cuda_launch_shape, device):
    """The tape gradient of sum(wH H) + sum(wn . n) through each strategy's forward and backward equals autograd
    through the float64 dense reference (scalar and per-vertex scales, CUDA launch shape)."""
    mesh = _bumpy_sphere(2, seed=3)
    V = mesh.num_vertices
    rng = np.random.default_rng(6)
    wH = rng.standard_normal(V)
    wn = rng.standard_normal((V, 3))
    for tau in (0.5, rng.uniform(0.3, 1.2, V), 5.0):
        x = wp.array(mesh.vertices, dtype=wp.vec3, device=device, requires_grad=True)
        tape = wp.Tape()
        with tape:
            H, n = vw.vnc_soft(mesh, tau, positions=x, tape=tape, strategy=strategy)
        tape.backward(grads={H: wp.array(wH.astype(np.float32), device=device),
                             n: wp.array(wn.astype(np.float32), dtype=wp.vec3, device=device)})
        v64 = torch.tensor(mesh.vertices, dtype=torch.float64, requires_grad=True)
        H64, n64 = dense_soft(v64, mesh.faces, tau)
        ((H64 * torch.as_tensor(wH)).sum() + (n64 * torch.as_tensor(wn)).sum()).backward()
        g, g64 = x.grad.numpy(), v64.grad.numpy()
        assert np.abs(g - g64).max() < 1e-3 * np.abs(g64).max(), (strategy, np.abs(g - g64).max())


def test_cell_index_matches_numpy(device):
    """The cell list (sorted sources and first[] offsets) equals a NumPy sort of the same cell indices."""
    mesh = vw.load_mesh(mesh_path("penguin.obj"))
    pts = wp.array(mesh.vertices, dtype=wp.vec3, device=device)
    b = _pairs.bounds(pts, wp.full(mesh.num_vertices, 0.1, dtype=wp.float32, device=device))
    h = 3.0 * mesh.mean_edge_length
    cells = _pairs.build_cells(pts, b, h)
    dims = np.array([cells.dims[0], cells.dims[1], cells.dims[2]])
    c = np.clip(np.floor((mesh.vertices.astype(np.float32) - b.lo.astype(np.float32)) * np.float32(1.0 / h)), 0,
                dims - 1).astype(np.int64)
    key = c[:, 0] + dims[0] * (c[:, 1] + dims[1] * c[:, 2])
    order = cells.order.numpy()
    np.testing.assert_array_equal(key[order], np.sort(key))
    np.testing.assert_array_equal(np.sort(order), np.arange(mesh.num_vertices))
    first = cells.first.numpy()
    np.testing.assert_array_equal(first, np.searchsorted(np.sort(key), np.arange(dims.prod() + 1)))


@wp.kernel
def _ball_row_cells_kernel(balls: wp.array(dtype=wp.vec4), lo: wp.array(dtype=wp.vec3i), hi: wp.array(dtype=wp.vec3i),
                           rows: wp.array(dtype=int), out: wp.array(dtype=wp.vec2i)):
    i = wp.tid()
    out[i] = _k.ball_row_cells(rows[i], lo[i], hi[i], balls[i])


def test_row_cells_of_a_ball_match_float64(device):
    """``ball_row_cells`` (the row walk reads only these cells of a row: ``walk_span``) equals the float64 interval
    ``floor(cx -+ sqrt(R^2 - dy^2 - dz^2))`` of the ball over the row's slab, clamped to the box, and is empty where
    the ball misses the slab; and it holds every cell of a point inside the ball."""
    rng = np.random.default_rng(5)
    n = 4000
    c = rng.uniform(0.0, 40.0, (n, 3))
    R = rng.uniform(0.2, 6.0, n)
    R[::17] = -1.0  # a thread with no query
    lo = np.floor(c - np.abs(R)[:, None] - rng.integers(0, 3, (n, 3))).astype(np.int64)
    hi = np.floor(c + np.abs(R)[:, None] + rng.integers(0, 3, (n, 3))).astype(np.int64)
    ny, nz = hi[:, 1] - lo[:, 1] + 1, hi[:, 2] - lo[:, 2] + 1
    rows = (rng.uniform(size=n) * ny * nz).astype(np.int64)
    y, z = lo[:, 1] + rows % ny, lo[:, 2] + rows // ny
    balls = np.concatenate([c, R[:, None]], axis=1).astype(np.float32)

    def row_cells(rows):
        out = wp.zeros(n, dtype=wp.vec2i, device=device)
        wp.launch(_ball_row_cells_kernel, dim=n,
                  inputs=[wp.array(balls, dtype=wp.vec4, device=device), wp.array(lo, dtype=wp.vec3i, device=device),
                          wp.array(hi, dtype=wp.vec3i, device=device), wp.array(rows, dtype=wp.int32, device=device)],
                  outputs=[out], device=device)
        return out.numpy()

    got = row_cells(rows)
    b = balls.astype(np.float64)
    dy = np.maximum(np.maximum(y - b[:, 1], b[:, 1] - (y + 1)), 0.0)
    dz = np.maximum(np.maximum(z - b[:, 2], b[:, 2] - (z + 1)), 0.0)
    w2 = b[:, 3] ** 2 - dy ** 2 - dz ** 2
    hit = (b[:, 3] >= 0) & (w2 >= 0)
    w = np.sqrt(np.maximum(w2, 0.0))
    first = np.floor(np.clip(b[:, 0] - w, lo[:, 0], hi[:, 0] + 1))
    last = np.floor(np.clip(b[:, 0] + w, lo[:, 0] - 1, hi[:, 0]))
    # away from float32 rounding at a cell boundary or a ball barely touching the slab
    sure = (np.abs(b[:, 0] - w - np.round(b[:, 0] - w)) > 1e-3) & (np.abs(b[:, 0] + w - np.round(b[:, 0] + w)) > 1e-3)
    sure &= np.abs(w2) > 1e-3
    assert sure.mean() > 0.9 and hit.sum() > n // 4 and (~hit).sum() > n // 10
    np.testing.assert_array_equal(got[sure & hit, 0], first[sure & hit])
    np.testing.assert_array_equal(got[sure & hit, 1], last[sure & hit])
    assert np.all(got[sure & ~hit, 0] > got[sure & ~hit, 1])
    # the reach of a ball over a row is narrower than the box's row for most rows
    assert np.mean((got[:, 1] - got[:, 0]) < (hi[:, 0] - lo[:, 0])) > 0.5
    # every point inside a ball (in a row of the box) lies in the cells returned for its row
    u = rng.normal(size=(n, 3))
    p = c + u / np.linalg.norm(u, axis=1, keepdims=True) * (np.abs(R) * rng.uniform(0, 1, n) ** (1 / 3))[:, None]
    cell = np.floor(p).astype(np.int64)
    inside = (R > 0) & np.all((cell >= lo) & (cell <= hi), axis=1)
    prow = (cell[:, 1] - lo[:, 1]) + ny * (cell[:, 2] - lo[:, 2])
    cells = row_cells(prow)
    assert inside.sum() > n // 2
    assert np.all((cells[inside, 0] <= cell[inside, 0]) & (cell[inside, 0] <= cells[inside, 1]))


def test_auto_choice_and_bad_strategy(device):
    """"auto" prunes with the grid at small scales and reads all pairs when every ball covers the mesh; an unknown
    strategy is rejected with the list of valid ones."""
    mesh = vw.load_mesh(mesh_path("wingnut.obj"))
    assert vw.choose_strategy(mesh, 3.0 * mesh.mean_edge_length, device=device) == "grid"
    assert vw.choose_strategy(mesh, 3.0 * mesh.mean_edge_length, variant="hard", device=device) == "grid"
    assert vw.choose_strategy(mesh, 2.0 * mesh.bbox_diagonal, device=device) == "dense"
    with pytest.raises(ValueError, match="grid, dense"):
        vw.vnc_soft(mesh, 1.0, device=device, strategy="kd-tree")
    with pytest.raises(ValueError, match="grid, dense"):
        vw.scale_curve(mesh, vw.default_scales(mesh, 4), device=device, strategy="octree")


def test_group_modes_both_exercised(cuda_launch_shape, monkeypatch, device):
    """With the CUDA launch shape, groups whose shared box is larger than their threads' own boxes walk per-thread
    boxes (``box_lo.x = -1``; the threshold lowered here so that a small mesh shows it) and groups of balls that
    cover the mesh a shared box; both give the BVH's result."""
    monkeypatch.setattr(_pairs, "SPREAD", 1.01)
    mesh = _bumpy_sphere()
    x = wp.array(mesh.vertices, dtype=wp.vec3, device=device)
    f = vw.edge_fields(mesh, positions=x)
    for factor, expect_per_thread in ((2.0, True), (30.0, False)):
        tau = factor * mesh.mean_edge_length
        radius = wp.full(mesh.num_vertices, tau, dtype=wp.float32, device=device)
        b = _pairs.bounds(x, radius)
        _, groups = _pairs.plan(x, radius, f.mid, b, "grid", b.rmean, max_per_thread=4)
        flagged = groups.box_lo.numpy()[:, 0] < 0
        assert flagged.any() == expect_per_thread, (factor, flagged.mean())
        H = vw.vnc_soft(mesh, tau, device=device, strategy="grid")[0].numpy()
        Hb = vw.vnc_soft(mesh, tau, device=device, strategy="bvh")[0].numpy()
        np.testing.assert_allclose(H, Hb, atol=2e-6)


def test_busy_traversals_take_more_queries_per_thread_and_splits():
    """The launch heuristics follow the expected work: a busy traversal (many candidates per query) takes QB queries
    per thread and more splits on a GPU; a light one, and any on the CPU device, one query per thread."""
    class FakeGPU:
        is_cuda, is_cpu, sm_count = True, False, 132

    light, busy = 0.1 * _pairs.BUSY_SOURCES, 10.0 * _pairs.BUSY_SOURCES
    assert _pairs.queries_per_thread(FakeGPU, light, 4) == 1
    assert _pairs.queries_per_thread(FakeGPU, busy, 4) == 4
    assert _pairs.queries_per_thread(wp.get_device("cpu"), busy, 4) == 1
    assert _pairs.launch_shape(FakeGPU, 50_000, 4, busy)[1] > _pairs.launch_shape(FakeGPU, 50_000, 4, light)[1]
    assert _pairs.launch_shape(wp.get_device("cpu"), 50_000, 4, busy) == (4, 1)
    # light traversals: fewer splits for more queries, but more than one while the threads fill the device only a
    # few times over (shorter threads, shorter tail)
    light_splits = [_pairs.launch_shape(FakeGPU, n, 1, light)[1] for n in (10_000, 50_000, 200_000, 800_000)]
    assert light_splits == sorted(light_splits, reverse=True) and light_splits[-1] >= 2, light_splits
