"""Headless mesh rendering and image assembly: ray casting on Warp, no display, no OpenGL.

:func:`render_mesh` casts one ray per pixel sample with ``wp.mesh_query_ray`` (CPU or CUDA) and shades
the hit with a camera-attached light; per-vertex colours or a scalar field (through :func:`colormap`)
are interpolated with the hit's barycentrics. :func:`montage`, :func:`colorbar` and :func:`save_png`
assemble the paper's figures (Figs. 5, 7, 8b, 9) from such frames with Pillow only.

Images are ``(H, W, 3) uint8`` NumPy arrays throughout.
"""

from __future__ import annotations

import dataclasses
import math
import os
from typing import Any, Sequence

import numpy as np
import warp as wp

from vnc_warp.kernels import render as _k

from ._device import get_device
from .mesh import Mesh

__all__ = ["Camera", "colormap", "colorbar", "montage", "render_mesh", "save_png", "COLORMAPS"]

# Key colours at positions in [0, 1], linearly interpolated in between. viridis and magma (CC0, van der
# Walt & Smith) are sampled every 16th entry of their 256-entry definitions; coolwarm is every other entry
# of Moreland's 33-entry "CoolWarmFloat33" table ("Diverging Color Maps for Scientific Visualization").
_VIRIDIS = (
    np.array([0, 16, 32, 48, 64, 80, 96, 112, 128, 144, 160, 176, 192, 208, 224, 240, 255]) / 255.0,
    [
        (0.2670, 0.0049, 0.3294), (0.2823, 0.0950, 0.4173), (0.2788, 0.1755, 0.4834), (0.2590, 0.2515, 0.5247),
        (0.2297, 0.3224, 0.5457), (0.1994, 0.3876, 0.5546), (0.1727, 0.4488, 0.5579), (0.1490, 0.5081, 0.5573),
        (0.1276, 0.5669, 0.5506), (0.1206, 0.6258, 0.5335), (0.1579, 0.6838, 0.5017), (0.2461, 0.7389, 0.4520),
        (0.3692, 0.7889, 0.3829), (0.5160, 0.8312, 0.2943), (0.6785, 0.8637, 0.1895), (0.8456, 0.8873, 0.0997),
        (0.9932, 0.9062, 0.1439),
    ],
)
_MAGMA = (
    _VIRIDIS[0],
    [
        (0.0015, 0.0005, 0.0139), (0.0396, 0.0311, 0.1335), (0.1131, 0.0655, 0.2768), (0.2117, 0.0620, 0.4186),
        (0.3167, 0.0717, 0.4854), (0.4147, 0.1104, 0.5047), (0.5128, 0.1482, 0.5076), (0.6136, 0.1818, 0.4985),
        (0.7164, 0.2150, 0.4753), (0.8169, 0.2559, 0.4365), (0.9043, 0.3196, 0.3881), (0.9609, 0.4183, 0.3596),
        (0.9867, 0.5356, 0.3822), (0.9961, 0.6537, 0.4462), (0.9969, 0.7696, 0.5349), (0.9924, 0.8843, 0.6401),
        (0.9871, 0.9914, 0.7495),
    ],
)
_COOLWARM = (
    np.linspace(0.0, 1.0, 17),
    [
        (0.2298, 0.2987, 0.7537), (0.3039, 0.4065, 0.8450), (0.3830, 0.5094, 0.9174), (0.4667, 0.6046, 0.9682),
        (0.5530, 0.6889, 0.9954), (0.6392, 0.7596, 0.9982), (0.7222, 0.8140, 0.9766), (0.7987, 0.8498, 0.9317),
        (0.8654, 0.8654, 0.8654), (0.9241, 0.8274, 0.7745), (0.9589, 0.7698, 0.6780), (0.9700, 0.6943, 0.5794),
        (0.9580, 0.6028, 0.4818), (0.9239, 0.4973, 0.3880), (0.8692, 0.3783, 0.3003), (0.7956, 0.2413, 0.2205),
        (0.7057, 0.0156, 0.1502),
    ],
)
_GRAY = (np.array([0.0, 1.0]), [(0.0, 0.0, 0.0), (1.0, 1.0, 1.0)])

#: Colour maps known to :func:`colormap`; append ``"_r"`` to a name for the reversed map.
COLORMAPS = {"coolwarm": _COOLWARM, "viridis": _VIRIDIS, "magma": _MAGMA, "gray": _GRAY}

_NAN_RGB = (0.5, 0.5, 0.5)
_DEFAULT_ALBEDO = (0.78, 0.78, 0.80)
_LUT_SIZE = 256
# shading: albedo * (AMBIENT + DIFFUSE max(n.l, 0)) + SPECULAR max(n.h, 0)^SHININESS
_AMBIENT, _DIFFUSE, _SPECULAR, _SHININESS = 0.25, 0.7, 0.15, 32.0


def _host(x: Any) -> Any:
    """NumPy view or copy of a Warp array or a torch tensor (on any device); anything else unchanged."""
    if isinstance(x, wp.array):
        return x.numpy()
    if hasattr(x, "detach") and hasattr(x, "cpu"):
        return x.detach().cpu().numpy()
    return x


def _cmap_table(cmap: str) -> tuple[np.ndarray, np.ndarray]:
    """Key positions (K,) and colours (K, 3) of a named map, reversed for a ``"_r"`` suffix."""
    if not isinstance(cmap, str):
        raise ValueError(f"colormap: cmap must be a name, one of {sorted(COLORMAPS)}, got {cmap!r}")
    name, reverse = (cmap[:-2], True) if cmap.endswith("_r") else (cmap, False)
    if name not in COLORMAPS:
        raise ValueError(f"colormap: unknown cmap {cmap!r}; known: {sorted(COLORMAPS)} (and their '_r' reversals)")
    pos, rgb = COLORMAPS[name]
    pos, rgb = np.asarray(pos, np.float64), np.asarray(rgb, np.float64)
    if reverse:
        pos, rgb = 1.0 - pos[::-1], rgb[::-1]
    return pos, rgb


def _normalize(values: np.ndarray, vmin: float | None, vmax: float | None) -> np.ndarray:
    """``(values - vmin) / (vmax - vmin)`` clipped to [0, 1], NaN kept; limits default to the finite range."""
    finite = values[np.isfinite(values)]
    lo = float(finite.min()) if vmin is None and finite.size else (0.0 if vmin is None else float(vmin))
    hi = float(finite.max()) if vmax is None and finite.size else (1.0 if vmax is None else float(vmax))
    if hi < lo:
        raise ValueError(f"colormap: vmax ({hi}) is below vmin ({lo})")
    if hi == lo:
        return np.where(np.isnan(values), np.nan, 0.5)
    with np.errstate(invalid="ignore"):
        return np.clip((values - lo) / (hi - lo), 0.0, 1.0)


def colormap(values: Any, cmap: str = "coolwarm", vmin: float | None = None, vmax: float | None = None) -> np.ndarray:
    """Map scalars to RGB.

    Args:
        values: array-like of any shape ``S``, e.g. (N,) per-vertex curvature.
        cmap: ``"coolwarm"`` (diverging), ``"viridis"``, ``"magma"`` or ``"gray"``; ``"_r"`` reverses.
        vmin, vmax: values mapped to the two ends; default the finite minimum and maximum. Values
            outside are clipped; when ``vmin == vmax`` everything maps to the middle colour.

    Returns:
        ``S + (3,)`` float32 in [0, 1]; NaN values are grey.

    Raises:
        ValueError: unknown ``cmap`` or ``vmax < vmin``.
    """
    pos, rgb = _cmap_table(cmap)
    v = np.asarray(_host(values), dtype=np.float64)
    t = _normalize(v, vmin, vmax)
    out = np.empty(v.shape + (3,), np.float32)
    nan = np.isnan(t)
    tt = np.where(nan, 0.0, t).ravel()
    for ch in range(3):
        out[..., ch] = np.interp(tt, pos, rgb[:, ch]).reshape(v.shape)
    out[nan] = _NAN_RGB
    return out


_UP_AXES = ("x", "y", "z")


@dataclasses.dataclass(frozen=True)
class Camera:
    """An orbit camera looking at ``target`` from ``distance`` away.

    Angles follow the up axis: for ``up="y"`` the eye sits at ``target + distance * (cos(el) sin(az),
    sin(el), cos(el) cos(az))``, so ``azimuth=0, elevation=0`` looks down ``-z`` (the front of a
    y-up human); ``up="z"`` puts ``azimuth=0`` on ``-y`` looking at ``+y``; ``up="x"`` on ``+z``.

    Attributes:
        azimuth: degrees about the up axis.
        elevation: degrees above the horizontal plane, in (-90, 90).
        fov: field of view across the shorter image side, degrees in (0, 180).
            For an orthographic camera the view spans ``2 * distance * tan(fov / 2)`` world units
            across that side, the extent a perspective camera has at the target.
        distance: eye-to-target distance in mesh units; ``None`` frames the rendered mesh (:meth:`fit`).
        target: look-at point (3,); ``None`` is the centre of the rendered mesh's bounding box.
        up: world up axis, ``"x"``, ``"y"`` or ``"z"``.
        orthographic: parallel projection instead of perspective.
    """

    azimuth: float = 30.0
    elevation: float = 20.0
    fov: float = 30.0
    distance: float | None = None
    target: tuple[float, float, float] | None = None
    up: str = "y"
    orthographic: bool = False

    def __post_init__(self):
        if self.up not in _UP_AXES:
            raise ValueError(f"Camera: up must be 'x', 'y' or 'z', got {self.up!r}")
        if not -90.0 < float(self.elevation) < 90.0:
            raise ValueError(f"Camera: elevation must be in (-90, 90) degrees, got {self.elevation}")
        if not 0.0 < float(self.fov) < 180.0:
            raise ValueError(f"Camera: fov must be in (0, 180) degrees, got {self.fov}")
        if self.distance is not None and not float(self.distance) > 0.0:
            raise ValueError(f"Camera: distance must be positive, got {self.distance}")
        if self.target is not None:
            t = np.asarray(self.target, dtype=np.float64)
            if t.shape != (3,) or not np.all(np.isfinite(t)):
                raise ValueError(f"Camera: target must be 3 finite numbers, got {self.target!r}")
            object.__setattr__(self, "target", tuple(float(c) for c in t))

    @classmethod
    def fit(cls, mesh_or_bounds: Any, *, margin: float = 1.05, tight: bool = True, **camera_args) -> "Camera":
        """A camera aimed at the centre of the bounding box of one or several meshes, framing all of it.

        Use one fitted camera for every frame of a filmstrip so that all share scale and framing.

        Args:
            mesh_or_bounds: a :class:`Mesh`, a ``(vertices, faces)`` pair, an (N, 3) point array, a
                (2, 3) ``[min, max]`` box, or a list of these (their union is framed).
            margin: size factor, > 1 leaves a border.
            tight: frame the eight box corners as seen from this view (fills more of the picture);
                ``False`` frames the box's bounding sphere, the same distance from every direction.
            **camera_args: the other :class:`Camera` fields (``azimuth``, ``elevation``, ``fov``, ``up``,
                ``orthographic``).

        Raises:
            ValueError: nothing to frame, non-finite points, ``margin <= 0`` or ``distance``/``target`` given.
        """
        if "distance" in camera_args or "target" in camera_args:
            raise ValueError("Camera.fit: distance and target are what fit computes; do not pass them")
        if not margin > 0.0:
            raise ValueError(f"Camera.fit: margin must be positive, got {margin}")
        lo, hi = _bounds(mesh_or_bounds)
        center = 0.5 * (lo + hi)
        radius = max(0.5 * float(np.linalg.norm(hi - lo)), 1e-12)
        base = cls(**camera_args)
        half = math.radians(base.fov) / 2.0
        if not tight:
            distance = radius * margin / math.sin(half)
        else:
            _, forward, right, up = dataclasses.replace(base, distance=1.0, target=tuple(center)).basis()
            corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
            rel = corners - center
            extent = margin * np.maximum(np.abs(rel @ right), np.abs(rel @ up))
            toward_eye = -(rel @ forward)
            if base.orthographic:
                # the view size follows the distance; the eye must also stay outside the box
                distance = max(float(extent.max()) / math.tan(half), 1.01 * float(toward_eye.max()))
            else:
                # a corner at height e and depth z towards the eye fits when e / (d - z) <= tan(half)
                distance = float(np.max(toward_eye + extent / math.tan(half)))
            distance = max(distance, 1e-12)
        return dataclasses.replace(base, distance=distance, target=tuple(center))

    def basis(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Eye position and unit ``forward``, ``right``, ``up`` vectors, each (3,) float64.

        Raises:
            ValueError: ``distance`` or ``target`` still unset (use :meth:`fit` or render with ``camera=None``).
        """
        if self.distance is None or self.target is None:
            raise ValueError("Camera.basis: distance and target must be set (see Camera.fit)")
        az, el = math.radians(self.azimuth), math.radians(self.elevation)
        # the eye direction in (side, vertical, front) components, rotated onto the world axes of each
        # up axis by a proper rotation (so no choice of up mirrors the picture)
        side, vert, front = math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)
        if self.up == "y":
            offset, world_up = np.array([side, vert, front]), np.array([0.0, 1.0, 0.0])
        elif self.up == "z":
            offset, world_up = np.array([side, -front, vert]), np.array([0.0, 0.0, 1.0])
        else:
            offset, world_up = np.array([vert, -side, front]), np.array([1.0, 0.0, 0.0])
        eye = np.asarray(self.target) + float(self.distance) * offset
        forward = -offset / np.linalg.norm(offset)
        right = np.cross(forward, world_up)
        right /= np.linalg.norm(right)
        up = np.cross(right, forward)
        return eye, forward, right, up


def _bounds(obj: Any) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned bounds ``(lo, hi)`` (3,) float64 of a mesh, point set, pair, box or list of them."""
    if isinstance(obj, Mesh):
        pts = obj.vertices
    elif isinstance(obj, (tuple, list)) and len(obj) == 2 and _is_faces(obj[1]):
        pts = obj[0]
    elif isinstance(obj, (tuple, list)):
        if not obj:
            raise ValueError("Camera.fit: empty list, nothing to frame")
        boxes = [_bounds(o) for o in obj]
        return np.min([b[0] for b in boxes], axis=0), np.max([b[1] for b in boxes], axis=0)
    else:
        pts = obj
    pts = np.asarray(pts, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or pts.shape[0] == 0:
        raise ValueError(f"Camera.fit: expected (N, 3) points, a Mesh or a list of them, got shape {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise ValueError("Camera.fit: points contain NaN or inf")
    return pts.min(axis=0), pts.max(axis=0)


def _is_faces(a: Any) -> bool:
    arr = np.asarray(a)
    return arr.ndim == 2 and arr.shape[1] == 3 and np.issubdtype(arr.dtype, np.integer)


def _mesh_arrays(mesh: Any) -> tuple[np.ndarray, np.ndarray]:
    """(V, 3) float32 vertices and (F, 3) int32 faces of a :class:`Mesh` or a ``(vertices, faces)`` pair."""
    if isinstance(mesh, Mesh):
        return mesh.vertices, mesh.faces
    if isinstance(mesh, (tuple, list)) and len(mesh) == 2:
        v = np.asarray(_host(mesh[0]), dtype=np.float32)
        f = np.asarray(_host(mesh[1]))
        if v.ndim != 2 or v.shape[1] != 3 or v.shape[0] == 0:
            raise ValueError(f"render_mesh: vertices must be (V, 3), got shape {v.shape}")
        if not np.all(np.isfinite(v)):
            raise ValueError("render_mesh: vertices contain NaN or inf")
        if f.ndim != 2 or f.shape[1] != 3 or f.shape[0] == 0 or not np.issubdtype(f.dtype, np.integer):
            raise ValueError(f"render_mesh: faces must be (F, 3) integers, got shape {f.shape}, dtype {f.dtype}")
        if f.min() < 0 or f.max() >= v.shape[0]:
            raise ValueError(f"render_mesh: face indices must lie in [0, {v.shape[0]}), got [{f.min()}, {f.max()}]")
        return v, f.astype(np.int32)
    raise ValueError(f"render_mesh: expected a Mesh or a (vertices, faces) pair, got {type(mesh).__name__}")


def _vertex_normals(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (V, 3) float32; zero for vertices on no face."""
    v64 = v.astype(np.float64)
    fn = np.cross(v64[f[:, 1]] - v64[f[:, 0]], v64[f[:, 2]] - v64[f[:, 0]])
    corner = f.reshape(-1)
    n = np.stack([np.bincount(corner, weights=np.repeat(fn[:, c], 3), minlength=v.shape[0]) for c in range(3)], 1)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return (n / np.where(length > 0.0, length, 1.0)).astype(np.float32)


def _vertex_colors(colors: Any, num_vertices: int) -> np.ndarray:
    """(V, 3) float32 in [0, 1] from (V, 3) floats, (V, 3|4) uint8 or a single (3,) colour."""
    c = np.asarray(_host(colors))
    if c.shape in ((3,), (4,)):
        c = np.broadcast_to(c[:3], (num_vertices, 3))
    if c.ndim != 2 or c.shape[0] != num_vertices or c.shape[1] not in (3, 4):
        raise ValueError(f"render_mesh: colors must be (V, 3) with V={num_vertices}, or one RGB colour; got {c.shape}")
    c = c[:, :3]
    if c.dtype == np.uint8:
        return c.astype(np.float32) / 255.0
    c = c.astype(np.float32)
    if not np.all(np.isfinite(c)):
        raise ValueError("render_mesh: colors contain NaN or inf")
    return np.clip(c, 0.0, 1.0)


def render_mesh(
    mesh: Any,
    *,
    colors: Any = None,
    scalars: Any = None,
    cmap: str = "coolwarm",
    vmin: float | None = None,
    vmax: float | None = None,
    camera: Camera | None = None,
    width: int = 512,
    height: int = 512,
    background: Sequence[float] = (1.0, 1.0, 1.0),
    samples: int = 2,
    flat: bool = False,
    light: Sequence[float] = (-0.3, 0.4, 1.0),
    return_depth: bool = False,
    device=None,
):
    """Ray-cast a shaded image of a triangle mesh.

    One Warp thread per pixel casts ``samples x samples`` rays (``wp.mesh_query_ray`` against a
    ``wp.Mesh`` built once per call) and averages them. A hit is coloured by interpolating per-vertex
    colours, or the per-vertex scalar (looked up in ``cmap`` per pixel), with the hit's barycentrics,
    then shaded as ``albedo * (0.25 + 0.7 max(n.l, 0)) + 0.15 max(n.h, 0)^32`` with a light fixed to
    the camera; ``n`` is the interpolated vertex normal (or the face normal when ``flat``).

    Args:
        mesh: a :class:`Mesh` or a ``(vertices (V, 3), faces (F, 3) int)`` pair.
        colors: (V, 3) float in [0, 1] or (V, 3|4) uint8 per-vertex colours, or one RGB colour.
            Arrays may also be Warp arrays or torch tensors on any device.
        scalars: (V,) per-vertex field drawn through :func:`colormap` (``cmap``, ``vmin``, ``vmax``);
            NaN marks missing values, whose faces are grey. Exclusive with ``colors``.
        cmap, vmin, vmax: colour map and its limits for ``scalars`` (limits default to the finite range).
        camera: a :class:`Camera`; ``None`` is ``Camera()`` fitted to this mesh. A camera without
            ``distance``/``target`` gets them from the mesh's bounds.
        width, height: image size in pixels.
        background: RGB in [0, 1].
        samples: rays per pixel side (1 = no anti-aliasing, 2 = 2x2 supersampling, ...); the time
            grows with its square.
        flat: face normals instead of interpolated vertex normals.
        light: direction towards the light in camera coordinates ``(right, up, back towards the eye)``;
            ``(0, 0, 1)`` is an exact headlight.
        return_depth: also return the depth buffer.
        device: Warp device (``None`` = preferred).

    Returns:
        ``(H, W, 3) uint8`` image; with ``return_depth`` also ``(H, W) float32`` view-space depth
        (distance along the viewing direction, mesh units) of the nearest sample per pixel, ``inf``
        where the pixel sees only background.

    Raises:
        ValueError: bad mesh arrays, colour/scalar shapes, sizes, ``samples < 1``, or both ``colors``
            and ``scalars``.
    """
    v, f = _mesh_arrays(mesh)
    width, height, samples = int(width), int(height), int(samples)
    if width < 1 or height < 1:
        raise ValueError(f"render_mesh: width and height must be positive, got {width}x{height}")
    if samples < 1:
        raise ValueError(f"render_mesh: samples must be >= 1, got {samples}")
    if colors is not None and scalars is not None:
        raise ValueError("render_mesh: pass colors or scalars, not both")
    bg = np.asarray(background, dtype=np.float32)
    if bg.shape != (3,):
        raise ValueError(f"render_mesh: background must be one RGB colour in [0, 1], got {background!r}")

    lut = np.zeros((0, 3), np.float32)
    values = np.zeros(0, np.float32)
    rgb = np.zeros((0, 3), np.float32)
    if scalars is not None:
        s = np.asarray(_host(scalars), dtype=np.float64).reshape(-1)
        if s.shape[0] != v.shape[0]:
            raise ValueError(f"render_mesh: scalars must be (V,) with V={v.shape[0]}, got {np.shape(scalars)}")
        t = _normalize(s, vmin, vmax)
        values = np.where(np.isnan(t), -1.0, t).astype(np.float32)
        lut = colormap(np.linspace(0.0, 1.0, _LUT_SIZE), cmap, 0.0, 1.0)
    else:
        rgb = _vertex_colors(_DEFAULT_ALBEDO if colors is None else colors, v.shape[0])

    cam = camera if camera is not None else Camera()
    if cam.distance is None or cam.target is None:
        fitted = Camera.fit(v, **{k: getattr(cam, k) for k in ("azimuth", "elevation", "fov", "up", "orthographic")})
        cam = dataclasses.replace(
            cam,
            distance=cam.distance if cam.distance is not None else fitted.distance,
            target=cam.target if cam.target is not None else fitted.target,
        )
    eye, forward, right, up = cam.basis()
    # fov spans the shorter side; the longer side extends by the aspect ratio
    half_short = math.tan(math.radians(cam.fov) / 2.0)
    if cam.orthographic:
        half_short *= float(cam.distance)
    half_x = half_short * max(width / height, 1.0)
    half_y = half_short * max(height / width, 1.0)
    lo, hi = v.min(axis=0).astype(np.float64), v.max(axis=0).astype(np.float64)
    # farthest possible hit: eye to the far corner of the bounding box, with room to spare
    max_t = 2.0 * (np.linalg.norm(eye - 0.5 * (lo + hi)) + np.linalg.norm(hi - lo)) + 1.0
    l_cam = np.asarray(light, dtype=np.float64)
    if l_cam.shape != (3,) or not np.linalg.norm(l_cam) > 0.0:
        raise ValueError(f"render_mesh: light must be a non-zero 3-vector, got {light!r}")
    l_world = l_cam[0] * right + l_cam[1] * up - l_cam[2] * forward
    l_world /= np.linalg.norm(l_world)

    dev = get_device(device)
    with wp.ScopedDevice(dev):
        points = wp.array(v, dtype=wp.vec3)
        indices = wp.array(f.reshape(-1), dtype=int)
        wmesh = wp.Mesh(points=points, indices=indices)
        normals = wp.array(np.zeros((0, 3), np.float32) if flat else _vertex_normals(v, f), dtype=wp.vec3)
        color = wp.empty((height, width), dtype=wp.vec3)
        depth = wp.empty((height, width), dtype=float)
        wp.launch(
            _k.render_pixels,
            dim=(height, width),
            inputs=[
                wmesh.id, indices, normals,
                wp.array(rgb, dtype=wp.vec3), wp.array(values, dtype=float), wp.array(lut, dtype=wp.vec3),
                wp.vec3(*_NAN_RGB),
                wp.vec3(*eye), wp.vec3(*forward), wp.vec3(*right), wp.vec3(*up),
                float(half_x), float(half_y), int(bool(cam.orthographic)), samples, float(max_t),
                wp.vec3(*l_world), wp.vec3(*bg), _AMBIENT, _DIFFUSE, _SPECULAR, _SHININESS, int(bool(flat)),
            ],
            outputs=[color, depth],
        )
        img = np.clip(np.rint(color.numpy() * 255.0), 0, 255).astype(np.uint8)
        if return_depth:
            return img, depth.numpy()
        return img


def _as_rgb8(img: Any, what: str) -> np.ndarray:
    """(H, W, 3) uint8 from uint8 or [0, 1] float images with 1, 3 or 4 channels or none."""
    a = np.asarray(img)
    if a.ndim == 2:
        a = a[:, :, None]
    if a.ndim != 3 or a.shape[2] not in (1, 3, 4) or a.shape[0] == 0 or a.shape[1] == 0:
        raise ValueError(f"{what}: expected an (H, W), (H, W, 3) or (H, W, 4) image, got shape {a.shape}")
    if a.dtype != np.uint8:
        a = np.clip(np.rint(np.nan_to_num(a.astype(np.float64)) * 255.0), 0, 255).astype(np.uint8)
    if a.shape[2] == 1:
        a = np.repeat(a, 3, axis=2)
    return np.ascontiguousarray(a[:, :, :3])


def save_png(path: str | os.PathLike, img: Any) -> None:
    """Write an image as PNG, creating missing parent folders.

    Args:
        path: output file.
        img: (H, W, 3|4) or (H, W) uint8, or floats in [0, 1].
    """
    from PIL import Image

    os.makedirs(os.path.dirname(os.path.abspath(os.fspath(path))), exist_ok=True)
    Image.fromarray(_as_rgb8(img, "save_png")).save(os.fspath(path), format="PNG")


def _font(size: int):
    """The face of the plots (STIX, shipped with matplotlib: Greek letters and the same look as the axes of
    :mod:`vnc_warp.plot`) at ``size`` pixels; Pillow's default font where it cannot be loaded."""
    from PIL import ImageFont

    size = max(int(size), 6)
    try:
        from matplotlib import font_manager

        path = font_manager.findfont(font_manager.FontProperties(family="STIXGeneral"), fallback_to_default=False)
        return ImageFont.truetype(path, size)
    except (ImportError, OSError, ValueError):
        pass
    try:
        return ImageFont.load_default(size=size)
    except (TypeError, ImportError, OSError):
        return ImageFont.load_default()


def _text_size(draw, text: str, font) -> tuple[int, int]:
    x0, y0, x1, y1 = draw.textbbox((0, 0), text, font=font)
    return x1 - x0, y1 - y0


def montage(
    images: Sequence[Any],
    *,
    labels: Sequence[str] | None = None,
    cols: int | None = None,
    pad: int = 8,
    label_height: int | None = None,
    background: Sequence[int] = (255, 255, 255),
) -> np.ndarray:
    """Tile frames on a grid, row by row, with optional labels under each frame.

    Column ``c`` is as wide as its widest frame and row ``r`` as high as its highest; smaller frames
    are centred in their cells. The result is ``sum(col_widths) + (cols + 1) * pad`` wide and
    ``sum(row_heights) + rows * label_height + (rows + 1) * pad`` high, ``rows = ceil(len(images) / cols)``.
    Frames of one size therefore tile evenly, and ``montage([grid, colorbar(...)], cols=1, pad=0)``
    stacks a colour bar under a grid without a gap.

    Args:
        images: frames, (H, W, 3|4) or (H, W) uint8, or floats in [0, 1].
        labels: one string per frame, centred under it in Pillow's default font.
        cols: frames per row; default all in one row (a filmstrip).
        pad: border and gap in pixels.
        label_height: pixels reserved under each row for labels; default 28 with labels, 0 without.
        background: RGB uint8 fill.

    Returns:
        (H, W, 3) uint8.

    Raises:
        ValueError: no images, a label count that differs from the image count, ``cols < 1`` or ``pad < 0``.
    """
    from PIL import Image, ImageDraw

    frames = [_as_rgb8(im, "montage") for im in images]
    if not frames:
        raise ValueError("montage: no images")
    if labels is not None and len(labels) != len(frames):
        raise ValueError(f"montage: {len(labels)} labels for {len(frames)} images")
    cols = len(frames) if cols is None else int(cols)
    if cols < 1 or pad < 0:
        raise ValueError(f"montage: need cols >= 1 and pad >= 0, got cols={cols}, pad={pad}")
    lh = (28 if labels is not None else 0) if label_height is None else int(label_height)
    rows = -(-len(frames) // cols)
    col_w = [max(fr.shape[1] for fr in frames[c::cols]) for c in range(min(cols, len(frames)))]
    row_h = [max(fr.shape[0] for fr in frames[r * cols:(r + 1) * cols]) for r in range(rows)]
    x_at = np.cumsum([pad] + [w + pad for w in col_w])
    y_at = np.cumsum([pad] + [h + lh + pad for h in row_h])
    canvas = Image.new("RGB", (int(x_at[-1]), int(y_at[-1])), tuple(background))
    draw = ImageDraw.Draw(canvas)
    font = _font(max(lh * 0.6, 8))
    for k, fr in enumerate(frames):
        r, c = divmod(k, cols)
        x0, y0, cw, ch = int(x_at[c]), int(y_at[r]), col_w[c], row_h[r]
        canvas.paste(Image.fromarray(fr), (x0 + (cw - fr.shape[1]) // 2, y0 + (ch - fr.shape[0]) // 2))
        if labels is not None and lh > 0 and labels[k]:
            tw, th = _text_size(draw, str(labels[k]), font)
            draw.text((x0 + (cw - tw) // 2, y0 + ch + (lh - th) // 2), str(labels[k]), fill=(0, 0, 0), font=font,
                      anchor="lt")
    return np.asarray(canvas)


def _nice_ticks(lo: float, hi: float, count: int = 5) -> np.ndarray:
    """Round-numbered ticks inside ``[lo, hi]``, about ``count`` of them.

    Steps are 1, 2, 2.5 or 5 times a power of ten; of those, the one whose tick count is closest to
    ``count`` wins (on a tie, one that is not 2.5, then the larger).
    """
    if not hi > lo:
        return np.array([lo])
    raw = (hi - lo) / max(count - 1, 1)
    exp = math.floor(math.log10(raw))
    best = None
    for e in (exp - 1, exp, exp + 1):
        for m in (1.0, 2.0, 2.5, 5.0):
            step = m * 10.0**e
            n = math.floor(hi / step + 1e-9) - math.ceil(lo / step - 1e-9) + 1
            key = (abs(n - count), m == 2.5, -step)
            if n >= 2 and (best is None or key < best[0]):
                best = (key, step)
    step = best[1] if best is not None else hi - lo
    start = math.ceil(lo / step - 1e-9) * step
    ticks = np.arange(start, hi + step * 1e-9, step)
    return np.where(np.abs(ticks) < step * 1e-9, 0.0, ticks)


def _decimals(step: float, ticks: np.ndarray) -> int:
    """Fewest decimals that print ticks ``step`` apart exactly (2.5 needs one, 0.25 two)."""
    d = max(0, -math.floor(math.log10(step) + 1e-9))
    while d < 12 and not np.allclose(np.round(ticks, d), ticks, rtol=0.0, atol=step * 1e-6):
        d += 1
    return d


def _tick_format(ticks: np.ndarray):
    """A formatter with just enough digits to tell the ticks apart; a shared exponent for tiny or huge values."""
    big = float(np.max(np.abs(ticks))) if ticks.size else 0.0
    step = float(np.min(np.diff(ticks))) if ticks.size > 1 else (abs(big) or 1.0)
    if big != 0.0 and (big >= 1e5 or big < 1e-3):
        scale = 10.0 ** math.floor(math.log10(big))
        d = _decimals(step / scale, ticks / scale)
        return lambda t: f"{t:.{d}e}"
    d = _decimals(step, ticks)
    return lambda t: f"{t:.{d}f}"


def _fit_font(draw, texts: Sequence[str], max_width: float, size: int):
    """The default font at ``size`` or smaller (down to 8 px) so that every text is at most ``max_width`` wide."""
    font = _font(size)
    while size > 8 and max(_text_size(draw, t, font)[0] for t in texts) > max_width:
        size -= 1
        font = _font(size)
    return font


def colorbar(
    cmap: str,
    vmin: float,
    vmax: float,
    *,
    label: str = "",
    height: int = 80,
    width: int = 512,
    ticks: int = 5,
) -> np.ndarray:
    """A colour scale with numbered ticks, to place beside frames rendered with the same limits.

    The bar runs left to right (``vmin`` to ``vmax``) when ``width >= height`` and bottom to top
    otherwise; ticks and the label are drawn inside the returned image.

    Args:
        cmap: a :func:`colormap` name.
        vmin, vmax: the limits the frames were rendered with (``vmin < vmax``).
        label: caption (e.g. the quantity and its unit), above the bar.
        height, width: image size in pixels (at least 40 x 40).
        ticks: about how many numbered ticks.

    Returns:
        (height, width, 3) uint8.

    Raises:
        ValueError: unknown ``cmap``, ``vmin >= vmax``, non-finite limits or an image too small.
    """
    from PIL import Image, ImageDraw

    _cmap_table(cmap)
    vmin, vmax = float(vmin), float(vmax)
    if not (math.isfinite(vmin) and math.isfinite(vmax) and vmin < vmax):
        raise ValueError(f"colorbar: need finite vmin < vmax, got {vmin}, {vmax}")
    width, height = int(width), int(height)
    if width < 40 or height < 40:
        raise ValueError(f"colorbar: image must be at least 40 x 40 pixels, got {width} x {height}")
    img = Image.new("RGB", (width, height), (255, 255, 255))
    draw = ImageDraw.Draw(img)
    tick_values = _nice_ticks(vmin, vmax, ticks)
    fmt = _tick_format(tick_values)
    texts = [fmt(t) for t in tick_values]
    black = (0, 0, 0)
    if width >= height:
        font = _fit_font(draw, texts + ([label] if label else []), width / max(len(texts), 1) - 4,
                         min(max(height // 5, 9), 24))
        _, text_h = _text_size(draw, "0.9", font)
        # room for the half of the end labels that hangs past the bar
        x0 = 2 + max(_text_size(draw, texts[0], font)[0] // 2, 4)
        x1 = width - 2 - max(_text_size(draw, texts[-1], font)[0] // 2, 4)
        y0 = 2 + (text_h + 6 if label else 0)
        y1 = max(y0 + 8, height - text_h - 10)
        ramp = colormap(np.linspace(vmin, vmax, x1 - x0), cmap, vmin, vmax)
        img.paste(Image.fromarray(_as_rgb8(np.broadcast_to(ramp[None], (y1 - y0, x1 - x0, 3)), "colorbar")), (x0, y0))
        for t, text in zip(tick_values, texts):
            x = x0 + (t - vmin) / (vmax - vmin) * (x1 - x0 - 1)
            draw.line([(x, y1), (x, y1 + 4)], fill=black)
            draw.text((x, y1 + 5), text, fill=black, font=font, anchor="mt")
        if label:
            draw.text((width / 2, 2), label, fill=black, font=font, anchor="mt")
    else:
        x0 = 4
        x1 = x0 + max(8, width // 4)
        size = min(max(width // 6, 9), 24)
        font = _fit_font(draw, texts, width - x1 - 10, size)
        label_font = _fit_font(draw, [label], width - 4, size) if label else font
        _, text_h = _text_size(draw, "0.9", font)
        y0 = max(text_h // 2 + 2, (_text_size(draw, label, label_font)[1] + 8) if label else 0)
        y1 = height - text_h // 2 - 2
        ramp = colormap(np.linspace(vmax, vmin, y1 - y0), cmap, vmin, vmax)
        img.paste(Image.fromarray(_as_rgb8(np.broadcast_to(ramp[:, None], (y1 - y0, x1 - x0, 3)), "colorbar")),
                  (x0, y0))
        for t, text in zip(tick_values, texts):
            y = y1 - 1 - (t - vmin) / (vmax - vmin) * (y1 - y0 - 1)
            draw.line([(x1, y), (x1 + 4, y)], fill=black)
            draw.text((x1 + 6, y), text, fill=black, font=font, anchor="lm")
        if label:
            draw.text((2, 2), label, fill=black, font=label_font, anchor="lt")
    draw.rectangle([x0 - 1, y0 - 1, x1, y1], outline=black)
    return np.asarray(img)
