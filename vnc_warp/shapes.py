"""Procedural shapes for VNC-Flow trajectories and the C-VAE: genus-0 blobs and humanoids.

**Blobs** (:func:`random_shape`, :func:`shape_family`): genus-0 shapes with multi-frequency detail.

A shape is a star-shaped radial graph over an icosphere: every unit direction ``u`` is moved to
``r(u) u`` with ``r(u) = 1 + d(u)``, where ``d`` sums random real spherical harmonics over several
bands (amplitudes decaying with the band) and a smooth 3D noise (random Fourier waves over a few
octaves). While ``r > 0`` at every vertex, each flat triangle stays inside the cone of its
icosphere face and the cones tile the sphere, so the mesh is embedded (no self-intersection) and of
genus 0; :func:`random_shape` enforces ``r >= min_radius`` by shrinking ``d``. A random anisotropic
scale and a random rotation follow (both keep the surface embedded).

Every random draw is keyed by ``(seed, purpose, band or octave)``, so a shape is a pure function of its
seed and adding bands adds detail without changing the coarser ones.

**Humanoids** (:func:`humanoid`, :func:`humanoid_family`): the body domain of the paper's C-VAE experiments
(Sec. 4.3), whose scans cannot be downloaded here. A body is the zero level set of a signed distance built from
ellipsoids (pelvis, abdomen, chest, head, hands, feet) and tapered capsules (neck, limbs), joined by a smooth
minimum so that joints blend; proportions, arm poses (from along the body to overhead, elbows bent or straight),
leg poses (together or apart, knees bent) and a surface relief (folds of a few millimetres) are random. Marching
cubes meshes it; a body whose surface is not one closed genus-0 piece (a hand grazing a hip) is drawn again.
Lengths are in metres, y up, the body facing +z.
"""

from __future__ import annotations

import numpy as np

from .mesh import Mesh, from_arrays

__all__ = ["icosphere", "radial_field", "random_rotation", "random_shape", "shape_family", "humanoid_sdf",
           "humanoid", "humanoid_family", "family_seeds"]

_SH_STREAM, _NOISE_STREAM, _AUGMENT_STREAM, _BODY_STREAM = 1, 2, 3, 4


def icosphere(subdivisions: int = 4, *, radius: float = 1.0, name: str = "icosphere") -> Mesh:
    """Unit icosphere scaled to ``radius``: ``10 * 4**subdivisions + 2`` vertices on the sphere.

    Args:
        subdivisions: loop subdivisions of the icosahedron, 0 to 7.
        radius: sphere radius (model units).
        name: mesh name.

    Raises:
        ValueError: subdivisions outside [0, 7] or radius not positive.
    """
    import trimesh

    if not 0 <= int(subdivisions) <= 7:
        raise ValueError(f"icosphere: subdivisions must be in [0, 7], got {subdivisions}")
    if not radius > 0.0:
        raise ValueError(f"icosphere: radius must be positive, got {radius}")
    tm = trimesh.creation.icosphere(subdivisions=int(subdivisions), radius=float(radius))
    return from_arrays(tm.vertices, tm.faces, name=name)


def _real_sh_band(l: int, directions: np.ndarray) -> np.ndarray:
    """Orthonormal real spherical harmonics of band ``l`` at unit directions: (N, 2l+1) float64."""
    import scipy.special as sps

    polar = np.arccos(np.clip(directions[:, 2], -1.0, 1.0))
    azimuth = np.arctan2(directions[:, 1], directions[:, 0])
    ms = np.arange(0, l + 1)
    if hasattr(sps, "sph_harm_y"):
        y = sps.sph_harm_y(l, ms[None, :], polar[:, None], azimuth[:, None])
    else:  # SciPy < 1.15 spells it sph_harm(m, l, azimuth, polar)
        y = sps.sph_harm(ms[None, :], l, azimuth[:, None], polar[:, None])
    cols = [y[:, 0].real]
    for m in range(1, l + 1):
        cols.append(np.sqrt(2.0) * y[:, m].real)
        cols.append(np.sqrt(2.0) * y[:, m].imag)
    return np.stack(cols, axis=1)


def radial_field(
    directions,
    seed: int,
    *,
    bands: tuple[int, int] = (2, 8),
    amplitude: float = 0.12,
    decay: float = 1.0,
    noise_amplitude: float = 0.02,
    noise_octaves: int = 3,
    noise_frequency: float = 2.0,
    noise_waves: int = 16,
) -> np.ndarray:
    """Random radial displacement ``d(u)`` at unit directions (before the positivity guard).

    ``d = sum_l sum_m c_lm Y_lm(u) + sum_o sum_j a_o sqrt(2/J) sin(f_o k_j . u + phi_j)``: band ``l``
    has root-mean-square ``amplitude * (l / l_min) ** -decay`` over the sphere (coefficients
    ``c_lm ~ N(0, 4 pi rms_l^2 / (2l + 1))``); noise octave ``o`` has frequency
    ``noise_frequency * 2**o`` (radians per unit length, random unit wave vectors ``k_j``) and RMS
    ``noise_amplitude * 2**-o``.

    Args:
        directions: (N, 3) unit vectors.
        seed: the shape's seed; band ``l`` and octave ``o`` draw from their own keyed streams.
        bands: inclusive range ``(l_min, l_max)`` of spherical-harmonic bands, ``l_min >= 1``.
        amplitude: RMS of band ``l_min`` (relative to the unit radius); 0 disables the harmonics.
        decay: power-law decay exponent of the band amplitudes.
        noise_amplitude: RMS of the first noise octave; 0 disables the noise.
        noise_octaves: number of noise octaves.
        noise_frequency: frequency of the first octave.
        noise_waves: random waves per octave.

    Returns:
        (N,) float64 displacement.

    Raises:
        ValueError: bad shapes or parameter ranges.
    """
    u = np.asarray(directions, dtype=np.float64)
    if u.ndim != 2 or u.shape[1] != 3:
        raise ValueError(f"radial_field: directions must be (N, 3), got {u.shape}")
    l_min, l_max = int(bands[0]), int(bands[1])
    if l_min < 1 or l_max < l_min:
        raise ValueError(f"radial_field: bands must satisfy 1 <= l_min <= l_max, got {bands}")
    if amplitude < 0.0 or noise_amplitude < 0.0 or noise_octaves < 0 or noise_waves < 1:
        raise ValueError("radial_field: amplitudes and octave counts must be non-negative, waves >= 1")
    d = np.zeros(u.shape[0])
    if amplitude > 0.0:
        for l in range(l_min, l_max + 1):
            rms = amplitude * (l / l_min) ** (-decay)
            rng = np.random.default_rng([int(seed), _SH_STREAM, l])
            coeff = rng.normal(0.0, rms * np.sqrt(4.0 * np.pi / (2 * l + 1)), size=2 * l + 1)
            d += _real_sh_band(l, u) @ coeff
    if noise_amplitude > 0.0:
        for o in range(int(noise_octaves)):
            rng = np.random.default_rng([int(seed), _NOISE_STREAM, o])
            k = rng.normal(size=(noise_waves, 3))
            k /= np.linalg.norm(k, axis=1, keepdims=True)
            phase = rng.uniform(0.0, 2.0 * np.pi, size=noise_waves)
            waves = np.sin(noise_frequency * 2.0**o * (u @ k.T) + phase)
            d += noise_amplitude * 2.0 ** (-o) * np.sqrt(2.0 / noise_waves) * waves.sum(axis=1)
    return d


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A uniformly random rotation matrix (3, 3) float64 (QR of a Gaussian matrix, det +1)."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0.0:
        q[:, 0] = -q[:, 0]
    return q


def random_shape(
    seed: int,
    *,
    subdivisions: int = 4,
    bands: tuple[int, int] = (2, 8),
    amplitude: float = 0.12,
    decay: float = 1.0,
    noise_amplitude: float = 0.02,
    noise_octaves: int = 3,
    noise_frequency: float = 2.0,
    min_radius: float = 0.3,
    anisotropy: tuple[float, float] = (0.75, 1.25),
    rotate: bool = True,
    name: str | None = None,
) -> Mesh:
    """A random genus-0 shape with multi-frequency detail; a pure function of ``seed`` and the options.

    Args:
        seed: non-negative integer.
        subdivisions: icosphere subdivisions (4: 2562 vertices, 5: 10242).
        bands, amplitude, decay, noise_amplitude, noise_octaves, noise_frequency: see :func:`radial_field`.
        min_radius: smallest allowed radius ``1 + d`` (0 < min_radius < 1); a field dipping below is
            shrunk toward the sphere until its minimum equals ``min_radius`` (star-shaped, embedded).
        anisotropy: range of the per-axis scale factors, drawn log-uniformly; ``(1, 1)`` disables it.
        rotate: apply a uniformly random rotation.
        name: mesh name, default ``"shape_<seed>"``.

    Returns:
        A watertight, manifold, outward-wound :class:`Mesh` centred near the origin with radius ~1.

    Raises:
        ValueError: negative seed or parameters out of range.
    """
    if int(seed) < 0:
        raise ValueError(f"random_shape: seed must be non-negative, got {seed}")
    if not 0.0 < min_radius < 1.0:
        raise ValueError(f"random_shape: min_radius must be in (0, 1), got {min_radius}")
    lo, hi = float(anisotropy[0]), float(anisotropy[1])
    if not 0.0 < lo <= hi:
        raise ValueError(f"random_shape: anisotropy must be 0 < low <= high, got {anisotropy}")
    sphere = icosphere(subdivisions)
    u = sphere.vertices.astype(np.float64)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    d = radial_field(u, seed, bands=bands, amplitude=amplitude, decay=decay, noise_amplitude=noise_amplitude,
                     noise_octaves=noise_octaves, noise_frequency=noise_frequency)
    if 1.0 + d.min() < min_radius:
        d *= (1.0 - min_radius) / (-d.min())
    v = u * (1.0 + d)[:, None]
    rng = np.random.default_rng([int(seed), _AUGMENT_STREAM])
    v = v * np.exp(rng.uniform(np.log(lo), np.log(hi), size=3))
    if rotate:
        v = v @ random_rotation(rng).T
    return from_arrays(v, sphere.faces, name=name or f"shape_{int(seed)}", merge=False)


def shape_family(n: int, seed: int, **kwargs) -> list[Mesh]:
    """``n`` independent random shapes, named ``family<seed>_<i>``; deterministic per ``seed``.

    Args:
        n: number of shapes (>= 1).
        seed: family seed; shape ``i`` uses a seed spawned from ``(seed, i)``.
        **kwargs: options of :func:`random_shape` (except ``seed`` and ``name``).
    """
    if int(n) < 1:
        raise ValueError(f"shape_family: n must be >= 1, got {n}")
    return [random_shape(s, name=f"family{int(seed)}_{i:04d}", **kwargs) for i, s in enumerate(family_seeds(n, seed))]


def family_seeds(n: int, seed: int) -> list[int]:
    """The member seeds of a family: member ``i`` of family ``seed`` gets one spawned from ``(seed, i)``."""
    return [int(np.random.SeedSequence([int(seed), i]).generate_state(1, np.uint64)[0] >> np.uint64(1))
            for i in range(int(n))]


def _rot(axis: str, angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    if axis == "x":
        return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    if axis == "y":
        return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _capsule(p: np.ndarray, a, b, ra: float, rb: float) -> np.ndarray:
    """Distance bound to a capsule from ``a`` (radius ``ra``) to ``b`` (radius ``rb``), radius linear along it."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    ba = b - a
    h = np.clip((p - a) @ ba / float(ba @ ba), 0.0, 1.0)
    return np.linalg.norm(p - a - h[:, None] * ba, axis=1) - (ra + (rb - ra) * h)


def _ellipsoid(p: np.ndarray, center, radii, rotation: np.ndarray | None = None) -> np.ndarray:
    """Signed distance bound to an ellipsoid (``k0 (k0 - 1) / k1``, exact on its surface and axes)."""
    q = p - np.asarray(center, np.float64)
    if rotation is not None:
        q = q @ rotation  # into the ellipsoid's frame: rows of q times R = R^T q
    r = np.asarray(radii, np.float64)
    k0 = np.linalg.norm(q / r, axis=1)
    k1 = np.maximum(np.linalg.norm(q / (r * r), axis=1), 1e-12)
    return k0 * (k0 - 1.0) / k1


def _smooth_union(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth minimum: ``min(a, b)`` blended over a width ``k``."""
    h = np.maximum(k - np.abs(a - b), 0.0) / k
    return np.minimum(a, b) - h * h * k * 0.25


def _limb(rng: np.random.Generator, root: np.ndarray, frame: np.ndarray, lengths, radii, bend: float,
          bend_axis: str) -> list[tuple[np.ndarray, np.ndarray, float, float]]:
    """Two capsules: ``root`` -> joint along ``frame``'s -y axis, then bent by ``bend`` about ``bend_axis``."""
    joint = root + frame @ np.array([0.0, -lengths[0], 0.0])
    end = joint + frame @ _rot(bend_axis, bend) @ np.array([0.0, -lengths[1], 0.0])
    return [(root, joint, radii[0], radii[1]), (joint, end, radii[1], radii[2])]


def _body_plan(seed: int) -> dict:
    """The primitives of body ``seed``: random proportions and pose."""
    rng = np.random.default_rng([int(seed), _BODY_STREAM])
    u = lambda lo, hi: float(rng.uniform(lo, hi))  # noqa: E731
    h = u(1.55, 1.95)          # standing height
    girth = u(0.8, 1.3)        # slim to heavy
    hip_y, chest_y = 0.53 * h, 0.72 * h
    shoulder_w, hip_w = u(0.19, 0.24) * h / 1.75, u(0.085, 0.11) * h / 1.75
    torso = [("pelvis", [0.0, hip_y, 0.0], [0.165 * girth ** 0.8, 0.14, 0.11 * girth], None),
             ("abdomen", [0.0, 0.625 * h, 0.01 * girth], [0.15 * girth ** 0.8, 0.15, 0.11 * girth ** 1.3], None),
             ("chest", [0.0, chest_y, 0.0], [shoulder_w * 0.8, 0.17, 0.115 * girth ** 0.7], None)]
    ell = [("head", [0.0, 0.93 * h, 0.015], [0.075, 0.105, 0.095] * np.array([u(0.92, 1.08)] * 3), None)]
    caps = [([0.0, 0.80 * h, 0.0], [0.0, 0.88 * h, 0.01], 0.055, 0.05)]
    arm_l, fore_l = u(0.16, 0.19) * h, u(0.14, 0.17) * h
    arm_r = 0.05 * girth ** 0.7
    raise_both = u(0.2, 2.9)   # abduction in the frontal plane: ~11 deg (along the body) to ~166 deg (overhead)
    for side in (-1.0, 1.0):
        abduct = np.clip(raise_both + u(-0.35, 0.35), 0.2, 2.95)
        flex = u(-0.35, 0.6)     # forward (+) or backward (-)
        root = np.array([side * shoulder_w, 0.81 * h, 0.0])
        frame = _rot("x", -flex) @ _rot("z", side * abduct)
        caps += [(a, b, ra, rb) for a, b, ra, rb in
                 _limb(rng, root, frame, (arm_l, fore_l), (arm_r, arm_r * 0.78, arm_r * 0.6), -u(0.0, 1.2), "x")]
        hand_at = caps[-1][1]
        hand_dir = caps[-1][1] - caps[-1][0]
        hand_dir = hand_dir / np.linalg.norm(hand_dir)
        ell.append((f"hand{side:+.0f}", hand_at + 0.07 * hand_dir, [0.045, 0.085, 0.022],
                    _align_y(hand_dir)))
        ell.append((f"shoulder{side:+.0f}", root + [-side * 0.01, -0.01, 0.0], [arm_r * 1.35] * 3, None))
    thigh_l, shin_l = u(0.235, 0.26) * h, u(0.23, 0.255) * h
    leg_r = 0.075 * girth ** 0.8
    spread = u(0.0, 0.42)      # legs together (0) to apart (~24 deg)
    for side in (-1.0, 1.0):
        root = np.array([side * hip_w, hip_y - 0.03, 0.0])
        frame = _rot("x", u(-0.25, 0.3)) @ _rot("z", side * (spread + u(-0.05, 0.05)) * 0.5 + side * 0.02)
        legs = _limb(rng, root, frame, (thigh_l, shin_l), (leg_r, leg_r * 0.62, leg_r * 0.42), u(0.0, 0.5), "x")
        caps += legs
        ankle = legs[-1][1]
        ell.append((f"foot{side:+.0f}", ankle + [side * 0.005, -0.035, 0.06], [0.045, 0.035, 0.12], None))
    waves = rng.normal(size=(24, 3))
    waves /= np.linalg.norm(waves, axis=1, keepdims=True)
    freqs = rng.uniform(25.0, 90.0, size=24)
    return {"height": h, "torso": torso, "ellipsoids": ell, "capsules": caps, "blend": u(0.02, 0.035),
            "torso_blend": u(0.06, 0.1),
            "relief": (waves * freqs[:, None], rng.uniform(0.0, 2.0 * np.pi, 24), u(0.0008, 0.0025))}


def _align_y(direction: np.ndarray) -> np.ndarray:
    """A rotation taking +y to ``direction`` (unit)."""
    y = np.array([0.0, 1.0, 0.0])
    v = np.cross(y, direction)
    c = float(y @ direction)
    if np.linalg.norm(v) < 1e-9:
        return np.eye(3) if c > 0 else _rot("x", np.pi)
    vx = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def humanoid_sdf(points, seed: int) -> np.ndarray:
    """Signed distance bound (metres, negative inside) of humanoid ``seed`` at ``points``.

    Args:
        points: (N, 3) positions in metres (y up, the feet near y = 0).
        seed: the body's seed.

    Returns:
        (N,) float64.
    """
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"humanoid_sdf: points must be (N, 3), got {p.shape}")
    plan = _body_plan(seed)
    k = plan["blend"]
    d = np.full(p.shape[0], np.inf)
    for _, c, r, rot in plan["torso"]:
        d = _smooth_union(d, _ellipsoid(p, c, r, rot), plan["torso_blend"])
    for _, c, r, rot in plan["ellipsoids"]:
        d = _smooth_union(d, _ellipsoid(p, c, r, rot), k)
    for a, b, ra, rb in plan["capsules"]:
        d = _smooth_union(d, _capsule(p, a, b, ra, rb), k)
    wave, phase, amp = plan["relief"]
    return d + amp * np.sqrt(2.0 / len(phase)) * np.sin(p @ wave.T + phase).sum(axis=1)


def _banded_grid(sdf, lo: np.ndarray, hi: np.ndarray, voxel: float, *, coarse: int = 4) -> np.ndarray:
    """``sdf`` on the grid ``lo + voxel * (i, j, k)`` covering ``[lo, hi]``: exact within two coarse cell
    diagonals of its zero level, trilinear from a grid ``coarse`` times coarser elsewhere (sign kept, no
    crossing added: enough for marching cubes, for a distance bound of slope <= 1)."""
    from scipy.ndimage import map_coordinates

    n = np.ceil((hi - lo) / (coarse * voxel)).astype(int) * coarse + 1
    c_axes = [lo[i] + coarse * voxel * np.arange((n[i] - 1) // coarse + 1) for i in range(3)]
    c_grid = np.stack(np.meshgrid(*c_axes, indexing="ij"), axis=-1).reshape(-1, 3)
    c_sdf = sdf(c_grid).reshape([len(a) for a in c_axes])
    idx = np.stack(np.meshgrid(*[np.arange(k) / coarse for k in n], indexing="ij"), axis=0)
    fine = map_coordinates(c_sdf, idx.reshape(3, -1), order=1).reshape(n)
    near = np.abs(fine) < 2.0 * np.sqrt(3.0) * coarse * voxel
    pts = lo + voxel * np.argwhere(near)
    fine[near] = np.concatenate([sdf(chunk) for chunk in np.array_split(pts, max(1, len(pts) // 400_000))])
    return fine


def humanoid(seed: int, *, voxel: float = 0.008, name: str | None = None, max_tries: int = 8) -> Mesh:
    """A random humanoid body: marching cubes of :func:`humanoid_sdf` on a ``voxel``-spaced grid.

    Args:
        seed: non-negative integer; the body is a pure function of it.
        voxel: grid spacing in metres (0.008: ~60k faces).
        name: mesh name, default ``"humanoid_<seed>"``.
        max_tries: draws (seeds ``seed``, then ones spawned from it) before giving up on a closed genus-0 body.

    Returns:
        A watertight, outward-wound, genus-0 :class:`Mesh` in metres.

    Raises:
        ValueError: bad arguments, or no genus-0 body in ``max_tries`` draws.
    """
    from skimage.measure import marching_cubes
    import trimesh

    if int(seed) < 0 or not voxel > 0.0 or max_tries < 1:
        raise ValueError(f"humanoid: need seed >= 0, voxel > 0 and max_tries >= 1, got {seed}, {voxel}, {max_tries}")
    draw = int(seed)
    for attempt in range(int(max_tries)):
        plan = _body_plan(draw)
        pts = np.concatenate([np.asarray([c for _, c, _, _ in plan["ellipsoids"] + plan["torso"]]),
                              np.asarray([x for a, b, _, _ in plan["capsules"] for x in (a, b)])])
        lo = pts.min(0) - 0.2
        sdf = _banded_grid(lambda x: humanoid_sdf(x, draw), lo, pts.max(0) + 0.2, voxel)
        # nodes on the level set make zero-area triangles; a nudge of 1e-3 voxel keeps them off it
        sdf = np.where(np.abs(sdf) < 1e-3 * voxel, 1e-3 * voxel, sdf)
        verts, faces, _, _ = marching_cubes(sdf.astype(np.float32), 0.0, spacing=(voxel,) * 3)
        tm = trimesh.Trimesh((verts + lo).astype(np.float32).astype(np.float64), faces, process=True)
        tm.update_faces(tm.nondegenerate_faces())
        if tm.is_watertight and tm.euler_number == 2 and len(tm.split(only_watertight=False)) == 1:
            if tm.volume < 0:
                tm.invert()
            return from_arrays(tm.vertices, tm.faces, name=name or f"humanoid_{int(seed)}")
        draw = family_seeds(1, draw + attempt + 1)[0]
    raise ValueError(f"humanoid: no closed genus-0 body in {max_tries} draws from seed {seed}")


def humanoid_family(n: int, seed: int, **kwargs) -> list[Mesh]:
    """``n`` random humanoids named ``human<seed>_<i>``; member ``i`` is :func:`humanoid` of
    ``family_seeds(n, seed)[i]``.

    Args:
        n: number of bodies (>= 1).
        seed: family seed.
        **kwargs: options of :func:`humanoid` (except ``seed`` and ``name``).
    """
    if int(n) < 1:
        raise ValueError(f"humanoid_family: n must be >= 1, got {n}")
    return [humanoid(s, name=f"human{int(seed)}_{i:04d}", **kwargs) for i, s in enumerate(family_seeds(n, seed))]
