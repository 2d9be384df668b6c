"""The paper's figures (vnc_warp.figures): framing, PNG files, content and input checks.

Oracles: the camera convention of the Camera docstring (every vertex must project inside the frame, the
silhouette must fill it), scale and translation invariance of the framing, Pillow reading back the PNG
that was written, and known properties of the inputs (a colour scale shared across frames, the number of
frames asked for).
"""

import math
from types import SimpleNamespace

import numpy as np
import pytest
from PIL import Image

import vnc_warp as vw
from vnc_warp import figures
from vnc_warp.data import mesh_path

WHITE = 255


def _png(path, image):
    """The PNG at ``path`` read back with Pillow: a real PNG holding exactly ``image``."""
    with Image.open(path) as im:
        assert im.format == "PNG"
        pixels = np.asarray(im.convert("RGB"))
    assert pixels.shape == image.shape and image.dtype == np.uint8
    np.testing.assert_array_equal(pixels, image)
    return pixels


def _not_blank(image, min_fraction=0.02):
    """Some share of the pixels differ from the white background, in more than one colour."""
    ink = np.any(image < 250, axis=2)
    assert ink.mean() > min_fraction, f"only {ink.mean():.3%} non-white pixels"
    assert len(np.unique(image.reshape(-1, 3)[ink.reshape(-1)], axis=0)) > 20


def _mask(image):
    return np.any(image < 250, axis=2)


def _blobs(image, min_area=300):
    """Solid non-white regions (rendered frames, colour bars), after an opening that erases thin text strokes."""
    from scipy import ndimage

    solid = ndimage.binary_opening(np.any(image < 235, axis=2), iterations=2)
    labels, _ = ndimage.label(solid, structure=np.ones((3, 3)))
    return int(np.sum(np.bincount(labels.ravel())[1:] >= min_area))


@pytest.fixture(scope="module")
def spot():
    return vw.load_mesh(mesh_path("spot"))


@pytest.fixture(scope="module")
def shapes():
    return [vw.random_shape(s, subdivisions=2) for s in range(4)]


def test_auto_camera_projects_every_vertex_inside_a_filled_frame(spot):
    """With the camera auto_camera returns, every vertex of Spot lies within the field of view (computed here
    from the Camera convention), and the outermost one sits at ``1 / margin`` of the half-width: tight framing."""
    for up in ("x", "y", "z"):
        cam = figures.auto_camera(spot, up=up, margin=1.1, fov=30.0)
        eye, forward, right, upward = cam.basis()
        rel = spot.vertices.astype(np.float64) - eye
        depth = rel @ forward
        assert np.all(depth > 0)
        extent = np.maximum(np.abs(rel @ right), np.abs(rel @ upward)) / depth
        tan_half = math.tan(math.radians(15.0))
        assert extent.max() <= tan_half / 1.1 * (1 + 1e-6)
        assert extent.max() >= tan_half / 1.1 * (1 - 1e-3)


def test_auto_camera_frames_any_scale_and_position_alike(spot):
    """Spot at 0.15 and at 658 units, moved far from the origin, renders to the same silhouette as Spot itself
    (framing comes from the vertices only), and that silhouette fills the frame without touching its border."""
    ref = vw.render_mesh(spot, camera=figures.auto_camera(spot), width=96, height=96, device="cpu")
    for scale, offset in [(0.15 / spot.bbox_diagonal, (5.0, -3.0, 2.0)), (658.0 / spot.bbox_diagonal, (1e3, 0, -4e3))]:
        moved = spot.with_vertices(spot.vertices * scale + np.asarray(offset, np.float32))
        img = vw.render_mesh(moved, camera=figures.auto_camera(moved), width=96, height=96, device="cpu")
        a, b = _mask(ref), _mask(img)
        assert (a & b).sum() / (a | b).sum() > 0.97
    rows, cols = np.nonzero(_mask(ref))
    assert rows.min() > 0 and cols.min() > 0 and rows.max() < 95 and cols.max() < 95
    assert max(rows.max() - rows.min(), cols.max() - cols.min()) > 0.85 * 96


def test_auto_camera_rejects_bad_input():
    """Empty lists, non-finite points, unknown up axes and non-positive margins are errors."""
    with pytest.raises(ValueError):
        figures.auto_camera([])
    with pytest.raises(ValueError):
        figures.auto_camera(np.array([[0.0, 0.0, np.nan]]))
    with pytest.raises(ValueError):
        figures.auto_camera(np.zeros((4, 3)), up="w")
    with pytest.raises(ValueError):
        figures.auto_camera(np.eye(3), margin=0.0)


def test_curvature_scales_writes_frames_on_one_colour_scale(tmp_path, spot):
    """Fig. 5: the PNG holds the returned image, one frame per requested scale side by side; with limits far
    wider than the field every frame is the map's neutral middle, with limits equal to the field the two
    diverging ends appear."""
    taus = vw.default_scales(spot, 6)
    H = vw.scale_curve(spot, taus, device="cpu").H
    img = figures.curvature_scales(spot, H, taus, tmp_path / "fig5.png", frames=3, frame_size=80, device="cpu")
    _png(tmp_path / "fig5.png", img)
    _not_blank(img)
    assert _blobs(img) == 3 + 1  # three frames and the colour bar
    h = H.numpy()
    wide = figures.curvature_scales(spot, h, taus, frames=2, frame_size=64, limits=(-50.0, 50.0), device="cpu")
    tight = figures.curvature_scales(spot, h, taus, frames=2, frame_size=64, device="cpu")
    neutral = vw.colormap(np.array([0.0]), "coolwarm", -1.0, 1.0)[0]

    def saturated(image, channel):
        px = image.reshape(-1, 3).astype(int)
        others = [c for c in range(3) if c != channel]
        return np.sum((px[:, channel] > 150) & (px[:, others].max(1) < 90))

    assert saturated(tight, 0) > 20 and saturated(tight, 2) > 20
    body = wide[:-120]  # above the colour bar, whose ramp shows both ends by design
    assert saturated(body, 0) == 0 and saturated(body, 2) == 0
    assert np.any(np.all(np.abs(body.astype(int) - np.round(neutral * 255 * 0.95)) < 40, axis=2))


def test_curvature_scales_rejects_mismatched_shapes(spot):
    """H must be (S, V) for the given scales and mesh."""
    taus = vw.default_scales(spot, 4)
    with pytest.raises(ValueError, match="curvature_scales"):
        figures.curvature_scales(spot, np.zeros((3, spot.num_vertices)), taus)
    with pytest.raises(ValueError, match="curvature_scales"):
        figures.curvature_scales(spot, np.zeros((4, 10)), taus)


def test_scale_stability_plots_and_validates(tmp_path, shapes):
    """Fig. 6 from VNC-soft and the Eq. (1) baseline of a small shape: a valid non-blank PNG of three panels;
    series of the wrong length are rejected."""
    m = shapes[0]
    taus = vw.default_scales(m, 5)
    soft = vw.scale_curve(m, taus, device="cpu").H.numpy()
    base = np.stack([vw.integrated_mean_curvature(m, float(t), device="cpu").numpy() for t in taus])
    img = figures.scale_stability(taus, {"VNC-soft": soft}, {"baseline": base}, tmp_path / "fig6.png",
                                  edge_length=m.mean_edge_length, size=(1200, 400))
    _png(tmp_path / "fig6.png", img)
    _not_blank(img)
    assert img.shape == (400, 1200, 3) and (tmp_path / "fig6.pdf").read_bytes().startswith(b"%PDF")
    with pytest.raises(ValueError):
        figures.scale_stability(taus, {"VNC-soft": soft[:3]})
    with pytest.raises(ValueError):
        figures.scale_stability(taus, {})


def _trajectory(history: bool):
    """A three-stage trajectory record as vnc_warp.flow writes it (S falls within stages, rebounds at remesh)."""
    records = [{"S": 10.0, "t": 1.0, "vertices": 100, "iterations": 0}]
    for i, (it, hist) in enumerate([(3, [[0, 10.0], [1, 8.0], [2, 7.0], [3, 6.5]]),
                                    (2, [[0, 7.0], [1, 4.0], [2, 3.2]])], start=1):
        rec = {"S": hist[-1][1], "t": hist[-1][1] / 10.0, "target_t": 1 - i / 3, "vertices": 100, "iterations": it}
        if history:
            rec["history"] = hist
        records.append(rec)
    return SimpleNamespace(records=records, info={"S_init": 10.0, "source": "test"})


def test_flow_auc_with_and_without_history(tmp_path):
    """Fig. 8a draws per-iteration histories (with stage boundaries) and falls back to one point per stage when
    a trajectory has no history; an empty trajectory is an error."""
    img = figures.flow_auc(_trajectory(True), tmp_path / "a.png", size=(500, 300))
    _png(tmp_path / "a.png", img)
    _not_blank(img)
    assert (tmp_path / "a.pdf").exists()
    img2 = figures.flow_auc(_trajectory(False), size=(500, 300))
    _not_blank(img2)
    assert not np.array_equal(img[-300:], img2[-300:])
    with pytest.raises(ValueError):
        figures.flow_auc(SimpleNamespace(records=[], info={}))


def test_adaptive_scales_and_filmstrip(tmp_path, shapes):
    """Fig. 8b and 9a: one frame per mesh (max_frames picks the first and the last of a longer list) in one
    shared camera; lengths that disagree are errors."""
    fields = [np.linalg.norm(m.vertices, axis=1) for m in shapes[:2]]
    img = figures.adaptive_scales(shapes[:2], fields, tmp_path / "b.png", frame_size=72, device="cpu")
    _png(tmp_path / "b.png", img)
    _not_blank(img)
    film = figures.filmstrip(shapes, [1.0, 0.6, 0.3, 0.1], tmp_path / "c.png", max_frames=2, frame_size=72,
                             device="cpu")
    _png(tmp_path / "c.png", film)
    _not_blank(film)
    ends = figures.filmstrip([shapes[0], shapes[3]], [1.0, 0.1], max_frames=None, frame_size=72, device="cpu")
    np.testing.assert_array_equal(film, ends)
    all4 = figures.filmstrip(shapes, [1.0, 0.6, 0.3, 0.1], max_frames=None, frame_size=72, device="cpu")
    assert _blobs(film) == 2 and _blobs(all4) == 4
    assert _blobs(img) == 2 + 1  # two frames and the colour bar
    with pytest.raises(ValueError):
        figures.filmstrip(shapes, [1.0, 0.5])
    with pytest.raises(ValueError):
        figures.adaptive_scales(shapes[:2], fields[:1])


def test_flow_comparison_and_decoded_trajectory_mark_missing_states(tmp_path, shapes):
    """Fig. 7 pads a row that stopped early with grey "(stopped)" cells; Fig. 9b draws a grey cell for a time
    that decoded no surface, and a reference row under the predictions."""
    comp = figures.flow_comparison({"a": shapes[:3], "b": shapes[:1]}, {"a": [1, .5, .2], "b": [1]},
                                   tmp_path / "d.png", frame_size=64, device="cpu")
    _png(tmp_path / "d.png", comp)
    _not_blank(comp)
    grey = np.all(comp == np.array(figures._PLACEHOLDER_RGB, np.uint8), axis=2)
    assert grey.sum() > 2 * 0.8 * 64 * 64  # two placeholder cells
    dec = figures.decoded_trajectory([shapes[0], None], [1.0, 0.0], tmp_path / "e.png", reference=shapes[:2],
                                     reference_t=[1.0, 0.0], frame_size=64, device="cpu")
    _png(tmp_path / "e.png", dec)
    grey = np.all(dec == np.array(figures._PLACEHOLDER_RGB, np.uint8), axis=2)
    assert 0.8 * 64 * 64 < grey.sum() < 1.2 * 64 * 64
    with pytest.raises(ValueError):
        figures.decoded_trajectory([None], [0.5])
    with pytest.raises(ValueError):
        figures.decoded_trajectory([shapes[0]], [0.5, 0.2])


def test_latent_space_scatter(tmp_path):
    """Fig. 11 from (N, M, C) latents whose mean grows with t: a valid two-panel PNG; too few samples or a
    t of the wrong length are errors."""
    rng = np.random.default_rng(0)
    t = np.linspace(0.0, 1.0, 12)
    z = rng.normal(size=(12, 8, 4)) * 0.1 + t[:, None, None]
    img = figures.latent_space(z, t, tmp_path / "f.png", size=(900, 400))
    _png(tmp_path / "f.png", img)
    _not_blank(img)
    assert img.shape == (400, 900, 3) and (tmp_path / "f.pdf").exists()
    with pytest.raises(ValueError):
        figures.latent_space(z[:2], t[:2])
    with pytest.raises(ValueError):
        figures.latent_space(z, t[:5])
