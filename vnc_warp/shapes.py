"""Procedural genus-0 test shapes with multi-frequency detail, for VNC-Flow trajectories and the C-VAE.

A shape is a star-shaped radial graph over an icosphere: every unit direction ``u`` is moved to
``r(u) u`` with ``r(u) = 1 + d(u)``, where ``d`` sums random real spherical harmonics over several
bands (amplitudes decaying with the band) and a smooth 3D noise (random Fourier waves over a few
octaves). While ``r > 0`` at every vertex, each flat triangle stays inside the cone of its
icosphere face and the cones tile the sphere, so the mesh is embedded (no self-intersection) and of
genus 0; :func:`random_shape` enforces ``r >= min_radius`` by shrinking ``d``. A random anisotropic
scale and a random rotation follow (both keep the surface embedded).

Every random draw is keyed by ``(seed, purpose, band or octave)``, so a shape is a pure function of its
seed and adding bands adds detail without changing the coarser ones.
"""

from __future__ import annotations

import numpy as np

from .mesh import Mesh, from_arrays

__all__ = ["icosphere", "radial_field", "random_rotation", "random_shape", "shape_family"]

_SH_STREAM, _NOISE_STREAM, _AUGMENT_STREAM = 1, 2, 3


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
    seeds = [int(np.random.SeedSequence([int(seed), i]).generate_state(1, np.uint64)[0] >> np.uint64(1))
             for i in range(int(n))]
    return [random_shape(s, name=f"family{int(seed)}_{i:04d}", **kwargs) for i, s in enumerate(seeds)]
