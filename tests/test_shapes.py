"""Procedural genus-0 shapes: validity, embedding, determinism and multi-frequency detail."""

import numpy as np
import pytest
import trimesh

from vnc_warp import load_mesh
from vnc_warp.shapes import icosphere, radial_field, random_shape, shape_family


def _solid_angles(v, f):
    """Signed solid angle of every face seen from the origin (Van Oosterom-Strackee), float64."""
    a, b, c = (v[f[:, k]].astype(np.float64) for k in range(3))
    la, lb, lc = (np.linalg.norm(x, axis=1) for x in (a, b, c))
    num = np.einsum("ij,ij->i", a, np.cross(b, c))
    den = la * lb * lc + np.einsum("ij,ij->i", a, b) * lc + np.einsum("ij,ij->i", a, c) * lb \
        + np.einsum("ij,ij->i", b, c) * la
    return 2.0 * np.arctan2(num, den)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_shape_is_valid_embedded_genus0(seed, tmp_path):
    """Watertight, manifold, one component, Euler characteristic 2, and star-shaped about the origin
    (every face sees the origin with positive solid angle summing to 4 pi: a fold-free, embedded
    radial graph); survives a save/load round trip."""
    m = random_shape(seed, subdivisions=3)
    assert m.is_watertight
    v, e, f = m.num_vertices, m.topology.edges.shape[0], m.num_faces
    assert v - e + f == 2
    assert len(m.to_trimesh().split(only_watertight=False)) == 1
    omega = _solid_angles(m.vertices, m.faces)
    assert omega.min() > 0.0
    assert omega.sum() == pytest.approx(4.0 * np.pi, rel=1e-6)
    assert m.volume() > 0.0
    path = tmp_path / "s.ply"
    m.save(path)
    back = load_mesh(path)
    assert back.is_watertight and back.num_faces == m.num_faces and back.num_vertices == m.num_vertices
    assert trimesh.Trimesh(back.vertices, back.faces).is_winding_consistent


def test_random_shape_deterministic_and_seed_dependent():
    """The same seed gives bit-identical vertices; different seeds give different shapes."""
    a, b, c = random_shape(11, subdivisions=3), random_shape(11, subdivisions=3), random_shape(12, subdivisions=3)
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.faces, b.faces)
    assert np.abs(a.vertices - c.vertices).max() > 0.05


def test_min_radius_is_enforced():
    """A displacement that would turn the radius negative is scaled so its minimum is exactly min_radius."""
    m = random_shape(3, subdivisions=3, amplitude=2.0, anisotropy=(1.0, 1.0), rotate=False, min_radius=0.4)
    r = np.linalg.norm(m.vertices.astype(np.float64), axis=1)
    d = radial_field(m.vertices / r[:, None], 3, amplitude=2.0)
    assert 1.0 + d.min() < 0.0
    np.testing.assert_allclose(r, 1.0 + d * (0.6 / -d.min()), atol=1e-5)
    assert r.min() == pytest.approx(0.4, abs=1e-5)
    assert _solid_angles(m.vertices, m.faces).min() > 0.0


def test_band_one_is_linear_and_detail_grows_with_bands():
    """Band 1 alone is a linear function of the direction (real l=1 harmonics are x, y, z); the
    variance of the harmonic field over the sphere grows strictly as bands are added (new bands are
    orthogonal and keep the coarser coefficients), and the noise alone has positive variance."""
    u = icosphere(4).vertices.astype(np.float64)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    d1 = radial_field(u, 5, bands=(1, 1), noise_amplitude=0.0)
    w, *_ = np.linalg.lstsq(u, d1, rcond=None)
    assert np.abs(u @ w - d1).max() < 1e-10 and np.linalg.norm(w) > 0.0
    var = [radial_field(u, 5, bands=(2, lmax), noise_amplitude=0.0).var() for lmax in range(2, 9)]
    assert all(b > a for a, b in zip(var, var[1:]))
    assert var[0] > 1e-4
    noise1 = radial_field(u, 5, amplitude=0.0, noise_octaves=1).var()
    noise3 = radial_field(u, 5, amplitude=0.0, noise_octaves=3).var()
    assert 0.0 < noise1 < noise3


def test_shape_detail_present_in_mesh():
    """Without augmentation the vertex radii are 1 + d: they vary, and match radial_field exactly."""
    m = random_shape(4, subdivisions=3, anisotropy=(1.0, 1.0), rotate=False)
    r = np.linalg.norm(m.vertices.astype(np.float64), axis=1)
    u = m.vertices / r[:, None]
    np.testing.assert_allclose(r, 1.0 + radial_field(u, 4), atol=1e-5)
    assert r.std() > 0.05


def test_shape_family():
    """A family is deterministic per seed, has distinct members and distinct names."""
    fam = shape_family(3, 7, subdivisions=2)
    again = shape_family(3, 7, subdivisions=2)
    assert [m.name for m in fam] == ["family7_0000", "family7_0001", "family7_0002"]
    for a, b in zip(fam, again):
        np.testing.assert_array_equal(a.vertices, b.vertices)
    assert np.abs(fam[0].vertices - fam[1].vertices).max() > 0.05
    with pytest.raises(ValueError, match="n must be"):
        shape_family(0, 1)


def test_humanoids_are_closed_genus0_bodies():
    """Humanoids (the C-VAE's body domain): watertight, one component, Euler characteristic 2, outward, 1.5-2 m
    tall standing on y ~ 0, a pure function of the seed; the SDF is negative in the pelvis and positive far away."""
    from vnc_warp.shapes import humanoid, humanoid_family, humanoid_sdf

    bodies = humanoid_family(3, 7, voxel=0.03)
    for m in bodies:
        assert m.is_watertight and m.volume() > 0.0
        assert m.num_vertices - m.topology.edges.shape[0] + m.num_faces == 2
        assert len(m.to_trimesh().split(only_watertight=False)) == 1
        lo, hi = m.vertices.min(0), m.vertices.max(0)
        assert -0.1 < lo[1] < 0.05 and 1.45 < hi[1] < 2.6  # raised hands may reach above the head
    again = humanoid(int(np.random.SeedSequence([7, 1]).generate_state(1, np.uint64)[0] >> np.uint64(1)), voxel=0.03)
    assert np.array_equal(again.vertices, bodies[1].vertices)
    assert not np.array_equal(bodies[0].vertices[:50], bodies[2].vertices[:50])
    d = humanoid_sdf(np.array([[0.0, 0.9, 0.0], [3.0, 1.0, 0.0]]), 5)
    assert d[0] < -0.05 and d[1] > 2.0


def test_humanoid_poses_cover_the_range():
    """Over 60 bodies the arms go from along the body (hand below the shoulder) to overhead (hand above the head)
    and the legs from together to apart (feet more than 0.4 m apart)."""
    from vnc_warp.shapes import _body_plan, family_seeds

    hands, feet = [], []
    for seed in family_seeds(60, 3):
        plan = _body_plan(seed)
        ell = {name: c for name, c, _, _ in plan["ellipsoids"]}
        hands.append(ell["hand+1"][1] - plan["height"] * 0.81)
        feet.append(abs(ell["foot+1"][0] - ell["foot-1"][0]))
    assert min(hands) < -0.4 and max(hands) > 0.45
    assert min(feet) < 0.3 and max(feet) > 0.4
