"""VNC-Flow repeats itself bit for bit on any device: nothing between two recorded stages adds floats in the order
threads happen to finish (an ``atomic_add`` of floats on CUDA), and every device reduction adds in a fixed order.

On the CPU Warp runs a kernel on one thread, so a timing-dependent sum cannot show there; these tests check instead
that the flow's kernels use no float atomics (a check the old kernels fail), that the fixed-order forms give what
they promise against independent float64 oracles, and that they depend on the mesh only as the algorithm says.
"""

import ast
from pathlib import Path

import numpy as np
import pytest
import trimesh
import warp as wp

from vnc_warp._reduce import face_measures, ordered_sum, vertex_normals

KERNELS = Path(__file__).resolve().parents[1] / "kernels"

#: Kernel modules that ``vnc_warp.flow`` launches between two recorded stages (remesh, SDF, flow step, VNC-soft and
#: its scale curves, the planner's statistics, the sums).
FLOW_MODULES = ["remesh.py", "sdf.py", "flow.py", "reduce.py", "vnc_scale.py", "vnc_grid.py", "vnc_terms.py",
                "vnc_sums.py", "vnc_reference.py"]

#: Adjoint kernels: they scatter gradients (for ``wp.Tape`` / torch autograd) and the flow, which computes none,
#: never runs them.
ADJOINTS = {"ball_adjoint_cells", "soft_backward", "ball_backward", "soft_edge_adjoint_kernel", "soft_edge_adjoint"}

#: Float atomic adds that are exact whatever the order: counts of integer value (below 2^24) kept in a float array.
EXACT_FLOAT_COUNTS = {("vnc_grid.py", "point_stats", "bad_x"), ("vnc_grid.py", "point_stats", "bad_r")}


def _float_atomic_adds(source: str, module: str) -> list[str]:
    """``module:kernel:target`` of every ``wp.atomic_add``/``atomic_sub`` on an array whose dtype is not an integer."""
    found = []
    for fn in ast.walk(ast.parse(source)):
        if not isinstance(fn, ast.FunctionDef) or fn.name in ADJOINTS:
            continue
        dtypes = {a.arg: ast.unparse(a.annotation) for a in fn.args.args if a.annotation is not None}
        for call in ast.walk(fn):
            if not (isinstance(call, ast.Call) and isinstance(call.func, ast.Attribute)
                    and call.func.attr in ("atomic_add", "atomic_sub") and call.args):
                continue
            target = ast.unparse(call.args[0])
            value = ast.unparse(call.args[-1])
            annotation = dtypes.get(target, "")
            if "int" in annotation.split("dtype=")[-1]:
                continue
            if (module, fn.name, value) in EXACT_FLOAT_COUNTS:
                continue
            found.append(f"{module}:{fn.name}:{target} += {value} ({annotation or 'not a parameter'})")
    return found


def test_flow_kernels_add_no_floats_atomically():
    """No kernel the flow runs adds floats with an atomic (order-dependent on CUDA): integer counters, atomic
    min/max and exact integer-valued counts only. The kernels before this change fail it (vertex normals, face
    measures, the relaxation's moved distance, the mean scale curve, the planner's mean radius)."""
    found = []
    for module in FLOW_MODULES:
        found += _float_atomic_adds((KERNELS / module).read_text(), module)
    assert found == []


def test_the_float_atomic_check_catches_a_float_scatter():
    """The check above is not vacuous: a float scatter like the old vertex-normal kernel is reported."""
    old = ("def vertex_normals(x: wp.array(dtype=wp.vec3), tri: wp.array(dtype=wp.int32), "
           "out: wp.array(dtype=wp.vec3)):\n    wp.atomic_add(out, tri[0], x[0])\n"
           "def counts(c: wp.array(dtype=wp.int32)):\n    wp.atomic_add(c, 0, 1)\n")
    assert _float_atomic_adds(old, "m.py") == ["m.py:vertex_normals:out += x[0] (wp.array(dtype=wp.vec3))"]


def _sphere_with_bump():
    """An icosphere with one pulled vertex (normals that are not all radial), float32, and its faces."""
    tm = trimesh.creation.icosphere(subdivisions=3, radius=3.7)
    v = tm.vertices.copy() + np.array([120.0, -40.0, 7.0])
    v[0] += 0.8 * (v[0] - v.mean(0))
    return v.astype(np.float32), tm.faces.astype(np.int32)


def _normals64(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Float64 oracle: unit sum of the faces' cross products at each vertex."""
    v = v.astype(np.float64)
    cr = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    n = np.zeros_like(v)
    for c in range(3):
        np.add.at(n, f[:, c], cr)
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def test_vertex_normals_match_float64_and_follow_face_order(device):
    """Vertex normals match a float64 oracle; with the faces permuted they still do, and they equal a float32 sum
    in ascending face order exactly (the order the gather promises, whatever the thread timing)."""
    v, f = _sphere_with_bump()
    perm = np.random.default_rng(3).permutation(f.shape[0])
    for faces in (f, f[perm]):
        x = wp.array(v, dtype=wp.vec3, device=device)
        tri = wp.array(faces.reshape(-1), dtype=wp.int32, device=device)
        got = vertex_normals(x, tri).numpy()
        np.testing.assert_allclose(got, _normals64(v, faces), atol=2e-6)
        cr = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]]).astype(np.float32)
        acc = np.zeros_like(v)
        for i, face in enumerate(faces):  # one face after the other, in float32: the promised order
            for c in face:
                acc[c] += cr[i]
        assert np.max(np.abs(got - acc / np.linalg.norm(acc, axis=1, keepdims=True))) <= 2 * np.finfo(np.float32).eps


def test_face_measures_match_trimesh_in_any_face_order(device):
    """Area, volume and centroid of a shifted, bumped sphere agree with trimesh (float64) for two face orders."""
    v, f = _sphere_with_bump()
    tm = trimesh.Trimesh(v.astype(np.float64), f, process=False)
    perm = np.random.default_rng(5).permutation(f.shape[0])
    for faces in (f, f[perm]):
        x = wp.array(v, dtype=wp.vec3, device=device)
        tri = wp.array(faces.reshape(-1), dtype=wp.int32, device=device)
        area, volume, centroid_sum, bad = face_measures(x, tri)
        assert area == pytest.approx(tm.area, rel=1e-12)
        assert volume == pytest.approx(tm.volume, rel=1e-9)
        np.testing.assert_allclose(centroid_sum / area, tm.triangles_center.T @ tm.area_faces / tm.area, rtol=1e-12)
        assert list(bad) == [0, 0]


def test_ordered_sum_adds_in_a_fixed_order(device):
    """``ordered_sum`` of float32, float64 and vec3d arrays equals the sum of its 256 strided index-order partials,
    added in order, exactly; and is within float64 rounding of the exact (fsum) total."""
    rng = np.random.default_rng(11)
    vals = rng.normal(size=10_007) * 10.0 ** rng.integers(-3, 4, size=10_007)
    for dtype, host in ((wp.float64, vals), (wp.float32, vals.astype(np.float32))):
        got = ordered_sum(wp.array(host, dtype=dtype, device=device))
        partial = np.zeros(256)
        for t in range(256):
            for k in range(t, host.shape[0], 256):
                partial[t] += np.float64(host[k])
        assert got == float(np.sum(partial))
        assert got == pytest.approx(np.sum(host.astype(np.float64)), rel=1e-12)
    vecs = rng.normal(size=(999, 3))
    np.testing.assert_allclose(ordered_sum(wp.array(vecs, dtype=wp.vec3d, device=device)), vecs.sum(0), rtol=1e-12)


def test_compaction_keeps_input_order(device):
    """The relocation lists are compacted by an exclusive scan, so they hold the flagged half-edges in ascending
    order (not in the order threads claimed a slot), and the count is exact."""
    from vnc_warp.kernels import remesh as _kr

    flags = (np.random.default_rng(2).random(5000) < 0.3).astype(np.int32)
    f = wp.array(flags, dtype=wp.int32, device=device)
    offsets = wp.empty_like(f)
    wp.utils.array_scan(f, offsets, inclusive=False)
    out = wp.full(flags.shape[0], -1, dtype=wp.int32, device=device)
    count = wp.zeros(1, dtype=wp.int32, device=device)
    wp.launch(_kr.compact, dim=flags.shape[0], inputs=[f, offsets], outputs=[out, count], device=device)
    n = int(count.numpy()[0])
    assert n == int(flags.sum())
    assert np.array_equal(out.numpy()[:n], np.nonzero(flags)[0])


def test_mean_scale_curve_matches_float64(device):
    """The global mean curve of the VNC-Scale curves (Eq. 4's ``mean(x)``), added in a fixed order, matches a
    float64 mean of the curves at every scale."""
    from vnc_warp.mesh import from_arrays
    from vnc_warp.scale import scale_curve

    v, f = _sphere_with_bump()
    curve = scale_curve(from_arrays(v, f), [0.5, 1.0, 2.0, 4.0], "soft", device=device)
    H = curve._H.numpy().astype(np.float64)
    np.testing.assert_allclose(curve._mean.numpy(), H.mean(axis=1), rtol=1e-5, atol=1e-7)


def _two_pass_sum(values: np.ndarray, threads: int, parts: int) -> np.float32:
    """Float32 oracle of the planner's fixed order: ``threads`` strided sums in index order, folded in ``parts``
    strided sums in index order, added in order."""
    per_thread = [np.float32(0.0)] * threads
    for t in range(threads):
        for k in range(t, values.shape[0], threads):
            per_thread[t] = np.float32(per_thread[t] + values[k])
    total = np.float32(0.0)
    for p in range(parts):
        part = np.float32(0.0)
        for t in range(p, threads, parts):
            part = np.float32(part + per_thread[t])
        total = np.float32(total + part)
    return total


def _planner_sums(n: int, device, parts: int | None = None):
    """``(stats[7], stats[9], radii, lengths)``: the radius and length sums of :func:`vnc_warp._plan.launch_stats`
    over ``n`` random points, or with ``parts`` given, of its two kernels run with ``fold_stats`` in ``parts``
    lanes."""
    from vnc_warp import _plan
    from vnc_warp.kernels import reduce as _r

    rng = np.random.default_rng(n)
    x = wp.array(rng.normal(size=(n, 3)) * 40.0 + 300.0, dtype=wp.vec3, device=device)
    radii = (rng.random(n) * 10.0 ** rng.uniform(-3, 3, n)).astype(np.float32)
    lengths = (rng.random(n // 2 + 1) * 7.0).astype(np.float32)
    stats = _plan.stats_init(device)
    r, ln = wp.array(radii, device=device), wp.array(lengths, device=device)
    if parts is None:
        _plan.launch_stats(x, r, ln, stats)
    else:
        partial = _plan.stats_partial(device)
        threads = min(n, _plan.STATS_THREADS)
        wp.launch(_plan._g.point_stats, dim=threads, inputs=[x, r, ln, threads], outputs=[stats, partial],
                  device=device)
        wp.launch_tiled(_r.fold_stats, dim=1, inputs=[partial[:threads], parts], outputs=[stats], block_dim=parts,
                        device=device)
    s = stats.numpy()
    return s[7], s[9], radii, lengths


@pytest.mark.parametrize("n", [7, 4096, 9001])
def test_planner_sums_add_in_a_fixed_order(device, n):
    """The sums of radii and edge lengths the planner's means come from (one launch to measure, one to fold) equal
    the float32 two-pass order bit for bit (64 parts on CUDA, one on the CPU) and the float64 sums to 1e-5."""
    from vnc_warp import _plan
    from vnc_warp.kernels import reduce as _r

    rsum, lsum, radii, lengths = _planner_sums(n, device)
    parts = _r.FOLD if wp.get_device(device).is_cuda else 1
    threads = min(n, _plan.STATS_THREADS)
    assert rsum.tobytes() == _two_pass_sum(radii, threads, parts).tobytes()
    assert lsum.tobytes() == _two_pass_sum(lengths, threads, parts).tobytes()
    assert rsum == pytest.approx(radii.astype(np.float64).sum(), rel=1e-5)
    assert lsum == pytest.approx(lengths.astype(np.float64).sum(), rel=1e-5)


def test_planner_fold_in_one_block_of_lanes():
    """The fold CUDA runs (one block of ``FOLD`` lanes sharing their sums through shared memory), run on CPU lanes
    (Warp's ``enable_cpu_blocks``), adds in the two-pass order bit for bit; and the other sum kernels still build
    for blocks of 256 lanes, as on CUDA (a tile of one value per lane sized to another block does not fit)."""
    from vnc_warp import _plan
    from vnc_warp.kernels import reduce as _r

    before = wp.config.enable_cpu_blocks
    wp.config.enable_cpu_blocks = True
    try:
        rsum, lsum, radii, lengths = _planner_sums(9001, "cpu", parts=_r.FOLD)
        index = wp.empty(300, dtype=wp.int32, device="cpu")
        wp.launch(_r.iota, dim=300, outputs=[index], device="cpu", block_dim=256)
    finally:
        wp.config.enable_cpu_blocks = before
    assert rsum.tobytes() == _two_pass_sum(radii, _plan.STATS_THREADS, _r.FOLD).tobytes()
    assert lsum.tobytes() == _two_pass_sum(lengths, _plan.STATS_THREADS, _r.FOLD).tobytes()
    assert np.array_equal(index.numpy(), np.arange(300))
