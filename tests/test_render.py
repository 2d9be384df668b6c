"""Headless ray-cast renderer, colour maps and image assembly, against analytic scenes.

Oracles: a sphere's projected disc and ray-sphere depths (perspective and orthographic), a flat square
whose colours are linear in position (barycentric interpolation reproduces them exactly), the
documented shading formula under an exact headlight, and known end colours of the standard maps.
"""

import math

import numpy as np
import pytest
import torch
import trimesh
import warp as wp
from PIL import Image

from vnc_warp import from_arrays
from vnc_warp.render import Camera, colorbar, colormap, montage, render_mesh, save_png

CENTRE = np.array([0.3, -0.2, 0.5])


def _sphere(radius: float, centre=CENTRE, subdivisions: int = 4):
    """Icosphere (2562 vertices at level 4) of ``radius`` around ``centre * radius``."""
    tm = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return from_arrays(tm.vertices + centre * radius, tm.faces, name="sphere")


def _square(z: float = 0.0):
    """The square [-1, 1]^2 at height z, two triangles wound towards +z, corners coloured
    ((x+1)/2, (y+1)/2, 0): a colour field linear in position."""
    v = np.array([[-1, -1, z], [1, -1, z], [1, 1, z], [-1, 1, z]], np.float64)
    f = np.array([[0, 1, 2], [0, 2, 3]], np.int32)
    colors = np.stack([(v[:, 0] + 1) / 2, (v[:, 1] + 1) / 2, np.zeros(4)], axis=1)
    return v, f, colors


def _ndc(width: int, height: int):
    """Normalised device coordinates of pixel centres, (H, W) each: x right, y up."""
    j = (np.arange(width) + 0.5) / width * 2.0 - 1.0
    i = 1.0 - (np.arange(height) + 0.5) / height * 2.0
    return np.meshgrid(j, i)


def _eye_from_angles(cam: Camera):
    """Eye position for up='y' straight from the angle convention in the Camera docstring."""
    az, el = math.radians(cam.azimuth), math.radians(cam.elevation)
    offset = np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])
    return np.asarray(cam.target) + cam.distance * offset


def test_camera_basis_follows_its_convention():
    """Eye at the documented spherical position, orthonormal right-handed frame looking at the target,
    screen-up along the world up projected; z-up puts azimuth 0 on -y."""
    cam = Camera(azimuth=35.0, elevation=-20.0, distance=7.0, target=(1.0, 2.0, 3.0))
    eye, fwd, right, up = cam.basis()
    np.testing.assert_allclose(eye, _eye_from_angles(cam), atol=1e-12)
    np.testing.assert_allclose(fwd, (np.array(cam.target) - eye) / 7.0, atol=1e-12)
    frame = np.stack([right, up, -fwd])
    np.testing.assert_allclose(frame @ frame.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(frame) == pytest.approx(1.0)
    assert up[1] > 0.0 and abs(right[1]) < 1e-12
    eye_z, fwd_z, _, up_z = Camera(azimuth=0.0, elevation=0.0, distance=2.0, target=(0, 0, 0), up="z").basis()
    np.testing.assert_allclose(eye_z, [0.0, -2.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(up_z, [0.0, 0.0, 1.0], atol=1e-12)


@pytest.mark.parametrize("up", ["x", "y", "z"])
def test_camera_azimuth_turns_right_handed_about_up(up):
    """For every up axis, +90 degrees of azimuth turns the eye by the right-hand rule about that axis
    (eye(90) = up x eye(0)), elevation lifts it along up, and the screen frame is right-handed."""
    axis = np.eye(3)["xyz".index(up)]

    def eye(az, el):
        return Camera(azimuth=az, elevation=el, distance=1.0, target=(0, 0, 0), up=up).basis()[0]

    np.testing.assert_allclose(eye(90.0, 0.0), np.cross(axis, eye(0.0, 0.0)), atol=1e-12)
    assert eye(0.0, 30.0) @ axis == pytest.approx(0.5)
    _, fwd, right, screen_up = Camera(azimuth=20.0, elevation=10.0, distance=1.0, target=(0, 0, 0), up=up).basis()
    assert np.linalg.det(np.stack([right, screen_up, -fwd])) == pytest.approx(1.0)
    assert screen_up @ axis > 0.9


def test_camera_rejects_bad_parameters():
    """Invalid angles, fov, distance, target and up axis raise ValueError with the field's name."""
    for kwargs, word in [({"elevation": 90.0}, "elevation"), ({"fov": 0.0}, "fov"), ({"distance": -1.0}, "distance"),
                         ({"target": (0, 0)}, "target"), ({"up": "w"}, "up")]:
        with pytest.raises(ValueError, match=word):
            Camera(**kwargs)
    with pytest.raises(ValueError, match="distance and target"):
        Camera().basis()
    with pytest.raises(ValueError, match="fit computes"):
        Camera.fit(np.zeros((2, 3)), distance=3.0)


def test_camera_fit_frames_bounding_sphere_and_unions():
    """fit(tight=False) puts the target at the box centre and the box's bounding sphere exactly at the
    view edge (times the margin); a list of meshes is framed by the union of their boxes."""
    a, b = _sphere(1.0, centre=np.zeros(3)), _sphere(2.0, centre=np.array([3.0, 0.0, 0.0]))
    cam = Camera.fit([a, b], fov=40.0, margin=1.0, tight=False)
    lo = np.minimum(a.vertices.min(0), b.vertices.min(0)).astype(np.float64)
    hi = np.maximum(a.vertices.max(0), b.vertices.max(0)).astype(np.float64)
    np.testing.assert_allclose(cam.target, (lo + hi) / 2, atol=1e-6)
    radius = np.linalg.norm(hi - lo) / 2
    assert math.degrees(math.asin(radius / cam.distance)) == pytest.approx(20.0, rel=1e-9)
    same = Camera.fit(np.stack([lo, hi]), fov=40.0, margin=1.0, tight=False)
    assert same.distance == pytest.approx(cam.distance) and np.allclose(same.target, cam.target)


@pytest.mark.parametrize("orthographic", [False, True])
def test_camera_fit_tight_projects_box_corners_inside(orthographic):
    """fit(tight=True) keeps all eight box corners in front of the eye and inside the view (NDC within
    1 / margin on both axes of a square image) with at least one corner on that border, and is closer
    than the bounding-sphere framing."""
    lo, hi = np.array([-0.9, 0.0, -0.1]), np.array([0.9, 1.8, 0.2])  # a T-posed human's box
    margin, fov = 1.1, 35.0
    cam = Camera.fit(np.stack([lo, hi]), fov=fov, margin=margin, azimuth=-40.0, elevation=25.0,
                     orthographic=orthographic)
    eye, fwd, right, up = cam.basis()
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    rel = corners - eye
    depth = rel @ fwd
    assert np.all(depth > 0.0)
    half = math.tan(math.radians(fov) / 2)
    if orthographic:
        ndc = np.abs(np.stack([rel @ right, rel @ up], axis=1)) / (cam.distance * half)
    else:
        ndc = np.abs(np.stack([rel @ right, rel @ up], axis=1)) / (depth[:, None] * half)
    assert ndc.max() == pytest.approx(1.0 / margin, rel=1e-9)
    loose = Camera.fit(np.stack([lo, hi]), fov=fov, margin=margin, azimuth=-40.0, elevation=25.0, tight=False)
    assert cam.distance < loose.distance


@pytest.mark.parametrize("radius", [0.15, 500.0])
@pytest.mark.parametrize("orthographic", [False, True])
def test_sphere_silhouette_area_and_depth(device, radius, orthographic):
    """Hit pixels of a sphere match the analytic projected disc (perspective: tan(asin(R/d)) in focal
    units; orthographic: R) within 2 %, at radius 0.15 and 500; every well-covered pixel's depth
    matches the analytic ray-sphere z-depth (up to the facets), and the centre pixel's depth is
    distance - radius."""
    size, fov, dist = 129, 40.0, 4.0 * radius
    mesh = _sphere(radius)
    target = tuple(CENTRE * radius)
    cam = Camera(azimuth=25.0, elevation=15.0, fov=fov, distance=dist, target=target, orthographic=orthographic)
    img, depth = render_mesh(mesh, camera=cam, width=size, height=size, samples=1, return_depth=True, device=device)
    assert img.shape == (size, size, 3) and img.dtype == np.uint8
    assert depth.shape == (size, size) and depth.dtype == np.float32
    half = math.tan(math.radians(fov) / 2)
    disc_focal = radius if orthographic else math.tan(math.asin(radius / dist))
    scale = dist * half if orthographic else half
    disc_px = math.pi * (disc_focal / scale * size / 2) ** 2
    hits = np.isfinite(depth)
    assert hits.sum() == pytest.approx(disc_px, rel=0.02)
    assert np.all(img[~hits] == 255)

    eye, fwd, right, up = cam.basis()
    x, y = _ndc(size, size)
    c = np.asarray(target)
    if orthographic:
        origins = eye + (x[..., None] * scale) * right + (y[..., None] * scale) * up
        dirs = np.broadcast_to(fwd, origins.shape)
    else:
        origins = np.broadcast_to(eye, (size, size, 3))
        d = fwd + (x[..., None] * half) * right + (y[..., None] * half) * up
        dirs = d / np.linalg.norm(d, axis=-1, keepdims=True)
    oc = origins - c
    b = np.einsum("hwk,hwk->hw", oc, dirs)
    disc = b * b - (np.einsum("hwk,hwk->hw", oc, oc) - radius * radius)
    inside = disc > (0.2 * radius) ** 2  # away from the silhouette, where facets differ most from the sphere
    t = -b - np.sqrt(np.where(inside, disc, 0.0))
    z = t * (dirs @ fwd)
    assert inside.sum() > 0.5 * disc_px and np.all(hits[inside])
    # a level-4 icosphere lies inside the sphere, at most 1.14e-3 R below it; along a ray meeting the
    # surface at cos = sqrt(disc) / R the gap grows by 1 / cos
    gap = depth[inside] - z[inside]
    assert np.all(gap >= -1e-6 * dist)
    assert np.all(gap <= 1.2e-3 * radius * radius / np.sqrt(disc[inside]))
    assert depth[size // 2, size // 2] == pytest.approx(dist - radius, abs=1.5e-3 * radius)


@pytest.mark.parametrize("orthographic", [False, True])
def test_square_colours_are_barycentric_and_shaded_by_formula(device, orthographic):
    """A square facing the camera under an exact headlight: every covered pixel equals
    albedo * (0.25 + 0.7) + 0.15 (n.h)^32 with the albedo ((x+1)/2, (y+1)/2, 0) of the hit point (linear
    colours are reproduced exactly by barycentric interpolation), +x is right and +y up in the
    image, and uncovered pixels are exactly the background."""
    v, f, colors = _square()
    size, fov, dist = 101, 60.0, 3.0
    cam = Camera(azimuth=0.0, elevation=0.0, fov=fov, distance=dist, target=(0, 0, 0), orthographic=orthographic)
    bg = (0.2, 0.4, 0.6)
    img = render_mesh((v, f), colors=colors, camera=cam, width=size, height=size, background=bg, samples=1,
                      light=(0.0, 0.0, 1.0), device=device)
    x, y = _ndc(size, size)
    scale = math.tan(math.radians(fov) / 2) * dist  # the plane z=0 lies at the target, for both projections
    wx, wy = x * scale, y * scale
    covered = (np.abs(wx) < 0.98) & (np.abs(wy) < 0.98)
    outside = (np.abs(wx) > 1.02) | (np.abs(wy) > 1.02)
    albedo = np.stack([(wx + 1) / 2, (wy + 1) / 2, np.zeros_like(wx)], axis=-1)
    # Blinn-Phong half vector between the light (+z) and the direction back to the eye
    to_eye = np.stack([np.zeros_like(wx), np.zeros_like(wx), np.ones_like(wx)], axis=-1)
    if not orthographic:
        to_eye = np.stack([-wx, -wy, np.full_like(wx, dist)], axis=-1)
        to_eye /= np.linalg.norm(to_eye, axis=-1, keepdims=True)
    h = to_eye + np.array([0.0, 0.0, 1.0])
    nh = h[..., 2] / np.linalg.norm(h, axis=-1)
    expected = np.clip(np.rint((albedo * 0.95 + 0.15 * nh[..., None] ** 32) * 255), 0, 255)
    assert covered.sum() > 1000 and outside.sum() > 1000
    assert np.abs(img[covered].astype(int) - expected[covered]).max() <= 2
    assert np.all(img[outside] == np.array([51, 102, 153]))


def test_red_square_centre_and_background(device):
    """A red square under the default (slightly offset) camera light: the centre pixel is clearly red,
    a corner pixel is exactly the white background."""
    v, f, _ = _square()
    cam = Camera(azimuth=0.0, elevation=0.0, fov=50.0, distance=4.0, target=(0, 0, 0))
    img = render_mesh((v, f), colors=(1.0, 0.0, 0.0), camera=cam, width=64, height=48, device=device)
    r, g, b = img[24, 32].astype(int)
    assert r > 200 and g < 60 and b < 60 and g == b
    assert np.all(img[0, 0] == 255)


def test_scalars_use_colormap_per_pixel_and_nan_faces_grey(device):
    """A scalar equal to x on the square, drawn in 'gray' with limits [-2, 2], gives every pixel the
    grey level 0.5 + x/4 shaded as above (the scalar is interpolated, then looked up), also when the
    scalars come as a torch tensor or a Warp array; a NaN vertex turns the faces around it grey (albedo 0.5)."""
    v, f, _ = _square()
    size, scale = 81, math.tan(math.radians(50.0) / 2) * 3.0
    cam = Camera(azimuth=0.0, elevation=0.0, fov=50.0, distance=3.0, target=(0, 0, 0), orthographic=True)
    kw = dict(camera=cam, width=size, height=size, samples=1, light=(0.0, 0.0, 1.0), device=device)
    img = render_mesh((v, f), scalars=v[:, 0], cmap="gray", vmin=-2.0, vmax=2.0, **kw)
    x, y = _ndc(size, size)
    covered = (np.abs(x * scale) < 0.97) & (np.abs(y * scale) < 0.97)
    grey = 0.5 + x * scale / 4.0
    expected = np.clip(np.rint((grey * 0.95 + 0.15) * 255), 0, 255)
    assert np.abs(img[covered][:, 0].astype(int) - expected[covered]).max() <= 2
    assert np.all(img[covered][:, 0] == img[covered][:, 2])
    for other in (torch.as_tensor(v[:, 0]), wp.array(v[:, 0].astype(np.float32), device=device)):
        same = render_mesh((v, f), scalars=other, cmap="gray", vmin=-2.0, vmax=2.0, **kw)
        np.testing.assert_array_equal(same, img)
    s = v[:, 0].copy()
    s[0] = np.nan  # vertex 0 is on both faces
    img_nan = render_mesh((v, f), scalars=s, cmap="viridis", **kw)
    assert np.all(np.abs(img_nan[covered].astype(int) - round((0.5 * 0.95 + 0.15) * 255)) <= 1)


def test_smooth_shading_matches_analytic_sphere(device):
    """Under an exact headlight with an orthographic view, smooth shading of an icosphere follows the
    analytic sphere, a (0.25 + 0.7 n.l) + 0.15 (n.l)^32 with n.l the sphere normal's view component,
    within 2 levels on average; flat shading is visibly faceted (larger error)."""
    radius, size = 1.0, 97
    mesh = _sphere(radius, centre=np.zeros(3))
    cam = Camera(azimuth=10.0, elevation=5.0, fov=60.0, distance=3.0, target=(0, 0, 0), orthographic=True)
    kw = dict(camera=cam, width=size, height=size, samples=1, light=(0.0, 0.0, 1.0), colors=(0.6, 0.6, 0.6),
              device=device)
    smooth = render_mesh(mesh, **kw).astype(float)
    faceted = render_mesh(mesh, flat=True, **kw).astype(float)
    x, y = _ndc(size, size)
    scale = math.tan(math.radians(30.0)) * 3.0
    r2 = (x * scale) ** 2 + (y * scale) ** 2
    inside = r2 < 0.9**2
    nl = np.sqrt(np.clip(1.0 - r2, 0.0, 1.0))
    expected = np.clip(255 * (0.6 * (0.25 + 0.7 * nl) + 0.15 * nl**32), 0, 255)
    err_smooth = np.abs(smooth[..., 0] - expected)[inside].mean()
    err_flat = np.abs(faceted[..., 0] - expected)[inside].mean()
    assert err_smooth < 2.0
    assert err_flat > err_smooth


def test_default_framing_is_scale_invariant(device):
    """camera=None frames the mesh from its bounds: a sphere of radius 0.15 and one of radius 500 give
    the same picture, fully inside the image and filling most of its height."""
    small = render_mesh(_sphere(0.15), width=96, height=80, device=device)
    large = render_mesh(_sphere(500.0), width=96, height=80, device=device)
    assert np.abs(small.astype(int) - large.astype(int)).mean() < 0.5
    fg = np.any(small < 250, axis=2)
    rows, cols = np.nonzero(fg)
    assert rows.min() > 0 and rows.max() < 79 and cols.min() > 0 and cols.max() < 95
    assert rows.max() - rows.min() > 0.5 * 80


def test_supersampling_softens_edges_only(device):
    """2x2 supersampling keeps interior and background pixels and puts intermediate values on the
    silhouette; the hit count of its depth buffer covers the single-sample one."""
    v, f, _ = _square()
    c, s = math.cos(0.5), math.sin(0.5)
    v = v @ np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])  # oblique edges cross sub-pixels
    cam = Camera(azimuth=0.0, elevation=0.0, fov=50.0, distance=4.0, target=(0, 0, 0))
    kw = dict(colors=(1.0, 0.0, 0.0), camera=cam, width=60, height=60, light=(0.0, 0.0, 1.0), device=device)
    one, d1 = render_mesh((v, f), samples=1, return_depth=True, **kw)
    four, d4 = render_mesh((v, f), samples=2, return_depth=True, **kw)
    assert np.array_equal(one[30, 30], four[30, 30]) and np.array_equal(one[0, 0], four[0, 0])
    g = four[..., 1].astype(int)
    assert np.any((g > 40) & (g < 250))
    assert np.all(np.isfinite(d4[np.isfinite(d1)]))


def test_render_mesh_rejects_bad_inputs():
    """Both colours and scalars, wrong lengths, bad sizes or samples, and out-of-range faces raise ValueError."""
    v, f, colors = _square()
    with pytest.raises(ValueError, match="not both"):
        render_mesh((v, f), colors=colors, scalars=v[:, 0], device="cpu")
    with pytest.raises(ValueError, match="scalars"):
        render_mesh((v, f), scalars=np.zeros(3), device="cpu")
    with pytest.raises(ValueError, match="colors"):
        render_mesh((v, f), colors=np.zeros((5, 3)), device="cpu")
    with pytest.raises(ValueError, match="samples"):
        render_mesh((v, f), samples=0, device="cpu")
    with pytest.raises(ValueError, match="width and height"):
        render_mesh((v, f), width=0, device="cpu")
    with pytest.raises(ValueError, match="face indices"):
        render_mesh((v, f + 2), device="cpu")


@pytest.mark.parametrize(
    "cmap, low, high",
    [
        ("viridis", "#440154", "#fde725"),
        ("magma", "#000004", "#fcfdbf"),
        ("coolwarm", "#3b4cc0", "#b40426"),
        ("gray", "#000000", "#ffffff"),
    ],
)
def test_colormap_endpoints(cmap, low, high):
    """vmin and vmax map to the published end colours of each map (within one 8-bit level); values
    beyond the limits clip to them; '_r' swaps them."""
    def rgb(h):
        return np.array([int(h[k:k + 2], 16) for k in (1, 3, 5)]) / 255.0

    out = colormap([-5.0, 0.0, 1.0, 7.0], cmap, vmin=0.0, vmax=1.0)
    assert out.shape == (4, 3) and out.dtype == np.float32
    np.testing.assert_allclose(out[1], rgb(low), atol=1.5 / 255)
    np.testing.assert_allclose(out[2], rgb(high), atol=1.5 / 255)
    np.testing.assert_array_equal(out[0], out[1])
    np.testing.assert_array_equal(out[3], out[2])
    rev = colormap([0.0, 1.0], cmap + "_r", vmin=0.0, vmax=1.0)
    np.testing.assert_allclose(rev, out[[2, 1]], atol=1e-6)


def test_colormap_ramps_are_monotonic():
    """Sequential maps rise strictly in luminance; coolwarm moves strictly from blue to red
    (R / (R + B) increasing) and is brightest near the middle; NaN is grey; default limits span the data."""
    t = np.linspace(0.0, 1.0, 256)
    lum = np.array([0.2126, 0.7152, 0.0722])
    for name in ("viridis", "magma", "gray"):
        assert np.all(np.diff(colormap(t, name, 0.0, 1.0) @ lum) > 0), name
    cw = colormap(t, "coolwarm", 0.0, 1.0).astype(np.float64)
    assert np.all(np.diff(cw[:, 0] / (cw[:, 0] + cw[:, 2])) > 0)
    assert abs(np.argmax(cw @ lum) - 128) < 40
    np.testing.assert_allclose(colormap([np.nan], "viridis")[0], [0.5, 0.5, 0.5])
    np.testing.assert_allclose(colormap([3.0, 5.0], "gray"), [[0, 0, 0], [1, 1, 1]], atol=1e-6)
    with pytest.raises(ValueError, match="unknown cmap"):
        colormap([0.0], "jet")


def test_save_png_roundtrip(tmp_path, device):
    """A rendered frame saved as PNG reads back with the stated size, identical pixels, not constant."""
    img = render_mesh(_sphere(1.0), width=70, height=50, device=device)
    path = tmp_path / "sub" / "frame.png"
    save_png(path, img)
    back = np.asarray(Image.open(path).convert("RGB"))
    assert back.shape == (50, 70, 3)
    np.testing.assert_array_equal(back, img)
    assert back.std() > 1.0


def test_montage_size_and_placement():
    """The grid is sum(column widths) + (cols + 1) * pad wide and sum(row heights) + rows * label + (rows + 1)
    * pad high, columns and rows sized by their largest frame; frames land in their cells, smaller ones
    centred; labels draw dark pixels under frames; cols=1 stacks frames of different widths."""
    a = np.full((30, 40, 3), (255, 0, 0), np.uint8)
    b = np.full((20, 50, 3), (0, 0, 255), np.uint8)
    c = np.zeros((36, 30), np.float64)
    out = montage([a, b, c], cols=2, pad=5, label_height=12, labels=["a", "b", "c"])
    # columns: max(40, 30) = 40 and 50; rows: max(30, 20) = 30 and 36
    assert out.shape == ((30 + 36) + 2 * 12 + 3 * 5, (40 + 50) + 3 * 5, 3)
    np.testing.assert_array_equal(out[5 + 15, 5 + 20], (255, 0, 0))
    col_b = 5 + 40 + 5 + 25  # b is 20 high in a 30-high row: rows 5..24 of the cell
    np.testing.assert_array_equal(out[5 + 4, col_b], (255, 255, 255))
    np.testing.assert_array_equal(out[5 + 5, col_b], (0, 0, 255))
    np.testing.assert_array_equal(out[5 + 24, col_b], (0, 0, 255))
    np.testing.assert_array_equal(out[5 + 25, col_b], (255, 255, 255))
    row_c = 5 + 30 + 12 + 5  # c (30 wide) centred in the 40-wide first column: columns 5..34 of the cell
    np.testing.assert_array_equal(out[row_c, 5 + 4], (255, 255, 255))
    np.testing.assert_array_equal(out[row_c, 5 + 5], (0, 0, 0))
    np.testing.assert_array_equal(out[row_c + 35, 5 + 34], (0, 0, 0))
    label_band = out[5 + 30:5 + 42, 5:5 + 40]
    assert label_band.min() < 128
    assert montage([a, b, c], pad=0).shape == (36, 120, 3)
    assert montage([a, b], cols=1, pad=0).shape == (50, 50, 3)
    with pytest.raises(ValueError, match="labels"):
        montage([a, b], labels=["x"])


@pytest.mark.parametrize("width, height", [(400, 70), (90, 300)])
def test_colorbar_image(width, height):
    """A colour bar has the stated size and shows both end colours of its map (horizontal and vertical)."""
    bar = colorbar("viridis", -1.0, 3.0, label="VNC", width=width, height=height)
    assert bar.shape == (height, width, 3) and bar.dtype == np.uint8
    ends = np.rint(colormap([0.0, 1.0], "viridis", 0.0, 1.0) * 255).astype(int)
    flat = bar.reshape(-1, 3).astype(int)
    for end in ends:
        assert np.min(np.abs(flat - end).sum(axis=1)) <= 9
    with pytest.raises(ValueError, match="vmin < vmax"):
        colorbar("viridis", 1.0, 1.0)
