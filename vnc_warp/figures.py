"""The paper's figures from data: one function per figure, each returning an image and writing a PNG.

Every function takes what its figure shows (meshes, per-vertex fields, curves, a trajectory, latents),
returns the picture as an ``(H, W, 3) uint8`` array and, given ``path``, also writes it as PNG. The plots (Figs. 6,
8a, 11) are drawn with matplotlib in the style of :mod:`vnc_warp.plot` (STIX text and mathematics) and written as a
PDF beside the PNG as well (``vector="svg"`` for SVG, None for none).

==========================  ===========  ==========================================================
function                    figure       data
==========================  ===========  ==========================================================
:func:`curvature_scales`    Fig. 5       a mesh and its VNC at several scales
:func:`scale_stability`     Fig. 6       per-vertex VNC and Eq. (1) baseline values at several scales
:func:`flow_comparison`     Fig. 7       meshes of VNC-Flow and of its baselines, per stage
:func:`flow_auc`            Fig. 8a      a VNC-Flow trajectory (its per-iteration total VNC-AUC)
:func:`adaptive_scales`     Fig. 8b      meshes and their adaptive scales (Eq. 6)
:func:`filmstrip`           Fig. 9a      the meshes of a trajectory and their times t (Eq. 7)
:func:`decoded_trajectory`  Fig. 9b      C-VAE decoded meshes across t
:func:`latent_space`        Fig. 11      C-VAE latents and their t
==========================  ===========  ==========================================================

Meshes are rendered headless by :func:`vnc_warp.render.render_mesh`; one camera per figure comes from
:func:`auto_camera`, fitted to the bounds of all the figure's meshes, so any mesh at any scale is framed
without options (pass ``camera`` to choose the view).
"""

from __future__ import annotations

import dataclasses
import os
from typing import Any, Mapping, Sequence

import numpy as np

from .mesh import Mesh
from . import plot
from .render import Camera, _as_rgb8, _font, _host, _text_size, colorbar, render_mesh, save_png

__all__ = [
    "auto_camera",
    "curvature_scales",
    "scale_stability",
    "flow_comparison",
    "flow_auc",
    "adaptive_scales",
    "filmstrip",
    "decoded_trajectory",
    "latent_space",
]

_WHITE = (255, 255, 255)
_PLACEHOLDER_RGB = (244, 244, 244)
_TEXT_RGB = (0, 0, 0)
_NOTE_RGB = (110, 110, 110)
# (front axis, side axis) of the Camera's azimuth convention for each up axis
_HORIZONTAL_AXES = {"y": (2, 0), "z": (1, 0), "x": (2, 1)}


def auto_camera(meshes: Any, *, up: str = "y", elevation: float = 20.0, fov: float = 30.0,
                margin: float = 1.06) -> Camera:
    """One camera for a whole figure of square frames, from the vertices of all its meshes.

    The view is three-quarter: when the shape is longer front-to-back than side-to-side (an animal in
    profile) the camera looks at its long side, 35 degrees off the side axis (azimuth 125), otherwise at
    its front, 35 degrees off the front axis (azimuth 35). The target is the centre of the silhouette and
    the distance the smallest at which every vertex projects inside a square frame (times ``margin``), so
    meshes of any size fill the frame, and a figure's meshes share one scale.

    Args:
        meshes: a :class:`~vnc_warp.Mesh`, ``(vertices, faces)`` pair, (N, 3) points, or a list of these.
        up: world up axis of the meshes, ``"x"``, ``"y"`` or ``"z"``.
        elevation: degrees above the horizontal plane.
        fov: field of view, degrees.
        margin: size factor of the frame around the silhouette (> 1 leaves a border).

    Returns:
        A :class:`~vnc_warp.render.Camera` with ``distance`` and ``target`` set.

    Raises:
        ValueError: nothing to frame, non-finite points, a bad ``up`` or ``margin``.
    """
    if up not in _HORIZONTAL_AXES:
        raise ValueError(f"auto_camera: up must be 'x', 'y' or 'z', got {up!r}")
    if not margin > 0.0:
        raise ValueError(f"auto_camera: margin must be positive, got {margin}")
    pts = _points(meshes)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    front, side = _HORIZONTAL_AXES[up]
    azimuth = 125.0 if hi[front] - lo[front] >= hi[side] - lo[side] else 35.0
    centre = 0.5 * (lo + hi)
    base = Camera(azimuth=azimuth, elevation=elevation, fov=fov, up=up, distance=1.0, target=tuple(centre))
    _, forward, right, upward = base.basis()
    rel = pts - centre
    x, y = rel @ right, rel @ upward
    # moving the target across the view keeps the view direction: centre the silhouette
    shift = 0.5 * (x.max() + x.min()) * right + 0.5 * (y.max() + y.min()) * upward
    rel = rel - shift
    x, y, toward_eye = rel @ right, rel @ upward, -(rel @ forward)
    # a point at lateral offset e and depth z towards the eye fits when e / (d - z) <= tan(fov / 2) / margin
    need = toward_eye + margin * np.maximum(np.abs(x), np.abs(y)) / np.tan(np.radians(fov) / 2.0)
    span = float(np.linalg.norm(hi - lo)) or 1.0
    return dataclasses.replace(base, distance=max(float(need.max()), 1e-6 * span), target=tuple(centre + shift))


def _points(obj: Any, limit: int = 200_000) -> np.ndarray:
    """(N, 3) float64 vertices of a mesh, pair, point array or list of them (evenly thinned to ``limit``)."""
    if isinstance(obj, Mesh):
        pts = np.asarray(obj.vertices, np.float64)
    elif isinstance(obj, (tuple, list)) and len(obj) == 2 and np.asarray(obj[1]).dtype.kind in "iu":
        pts = np.asarray(_host(obj[0]), np.float64)
    elif isinstance(obj, (tuple, list)):
        if not obj:
            raise ValueError("auto_camera: empty list, nothing to frame")
        pts = np.concatenate([_points(o, limit) for o in obj])
    else:
        pts = np.asarray(_host(obj), np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or pts.shape[0] == 0:
        raise ValueError(f"auto_camera: expected (N, 3) points, a Mesh or a list of them, got shape {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise ValueError("auto_camera: points contain NaN or inf")
    return pts[:: -(-pts.shape[0] // limit)]


# ---------------------------------------------------------------------------------------------- assembly


def _text_image(lines: Sequence[str], width: int, size: int, *, color=_TEXT_RGB, align: str = "center") -> np.ndarray:
    """White strip ``width`` wide holding the lines of text at ``size`` pixels, centred (or left-aligned)."""
    from PIL import Image, ImageDraw

    font = _font(size)
    probe = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    line_h = int(round(size * 1.3))
    widest = max((_text_size(probe, s, font)[0] for s in lines), default=0)
    width = max(int(width), widest + 8)
    img = Image.new("RGB", (width, line_h * len(lines) + size // 2), _WHITE)
    draw = ImageDraw.Draw(img)
    for i, s in enumerate(lines):
        y = size // 4 + i * line_h + line_h // 2
        if align == "left":
            draw.text((4, y), s, fill=color, font=font, anchor="lm")
        else:
            draw.text((width / 2, y), s, fill=color, font=font, anchor="mm")
    return np.asarray(img)


def _placeholder(size: int, text: str) -> np.ndarray:
    """A light grey square frame with a short note in it (a missing or failed state)."""
    from PIL import Image, ImageDraw

    img = Image.new("RGB", (size, size), _PLACEHOLDER_RGB)
    draw = ImageDraw.Draw(img)
    font = _font(max(size // 14, 12))
    for i, s in enumerate(text.split("\n")):
        draw.text((size / 2, size / 2 + (i - 0.5 * text.count("\n")) * size / 11), s, fill=_NOTE_RGB, font=font,
                  anchor="mm")
    return np.asarray(img)


def _vstack(images: Sequence[np.ndarray], pad: int = 0) -> np.ndarray:
    """Images one under the other, each centred horizontally on a white canvas."""
    ims = [_as_rgb8(im, "figure") for im in images]
    w = max(im.shape[1] for im in ims)
    h = sum(im.shape[0] for im in ims) + pad * (len(ims) - 1)
    out = np.full((h, w, 3), 255, np.uint8)
    y = 0
    for im in ims:
        x = (w - im.shape[1]) // 2
        out[y:y + im.shape[0], x:x + im.shape[1]] = im
        y += im.shape[0] + pad
    return out


def _hstack(images: Sequence[np.ndarray], pad: int = 0) -> np.ndarray:
    """Images side by side, each centred vertically on a white canvas."""
    ims = [_as_rgb8(im, "figure") for im in images]
    h = max(im.shape[0] for im in ims)
    w = sum(im.shape[1] for im in ims) + pad * (len(ims) - 1)
    out = np.full((h, w, 3), 255, np.uint8)
    x = 0
    for im in ims:
        y = (h - im.shape[0]) // 2
        out[y:y + im.shape[0], x:x + im.shape[1]] = im
        x += im.shape[1] + pad
    return out


def _grid(cells: Sequence[Sequence[Any]], *, frame: int, labels: Sequence[Sequence[str]] | None = None,
          row_labels: Sequence[str] | None = None, pad: int = 10) -> np.ndarray:
    """Square frames on a grid with a label under each and an optional label column on the left.

    ``cells[r][c]`` is an image (``frame`` x ``frame``) or a string, drawn as a placeholder note. Row labels
    may hold ``\\n`` for several lines.
    """
    font_size = max(14, min(22, frame // 13))
    rows = []
    for r, row in enumerate(cells):
        tiles = []
        for c, cell in enumerate(row):
            img = _placeholder(frame, cell) if isinstance(cell, str) else _as_rgb8(cell, "figure")
            text = labels[r][c] if labels is not None and c < len(labels[r]) else ""
            tiles.append(_vstack([img, _text_image([text], frame, font_size)]) if labels is not None else img)
        rows.append(_hstack(tiles, pad))
    if row_labels is not None:
        texts = [_text_image(str(s).split("\n"), 0, font_size + 1, align="left") for s in row_labels]
        width = max(t.shape[1] for t in texts)
        texts = [_text_image(str(s).split("\n"), width, font_size + 1, align="left") for s in row_labels]
        rows = [_hstack([t, r], pad) for t, r in zip(texts, rows)]
    body = _vstack(rows, pad)
    out = np.full((body.shape[0] + 2 * pad, body.shape[1] + 2 * pad, 3), 255, np.uint8)
    out[pad:pad + body.shape[0], pad:pad + body.shape[1]] = body
    return out


def _titled(img: np.ndarray, title: str | None, note: str | None = None) -> np.ndarray:
    """A title (and a smaller grey note) above the picture."""
    parts = []
    width = img.shape[1]
    size = max(18, min(28, width // 45))
    if title:
        parts.append(_text_image([title], width, size))
    if note:
        parts.append(_text_image(note.split("\n"), width, max(14, size - 8), color=_NOTE_RGB))
    return _vstack(parts + [img], 4) if parts else img


def _finish(img: np.ndarray, path: str | os.PathLike | None) -> np.ndarray:
    img = _as_rgb8(img, "figure")
    if path is not None:
        save_png(path, img)
    return img


def _frame(mesh: Any, camera: Camera, size: int, device, **shade) -> np.ndarray:
    return render_mesh(mesh, camera=camera, width=size, height=size, samples=2, device=device, **shade)


def _evenly(n: int, k: int | None) -> list[int]:
    """``k`` indices of ``range(n)`` spread evenly, first and last included (all when ``k`` is None or >= n)."""
    if k is None or k >= n:
        return list(range(n))
    if k < 2:
        raise ValueError(f"need at least 2 frames, got {k}")
    return sorted({int(round(v)) for v in np.linspace(0, n - 1, k)})


def _shared_limits(values: Sequence[np.ndarray], *, centre: bool, quantile: float = 0.98) -> tuple[float, float]:
    """Colour limits shared by several per-vertex fields: symmetric about the pooled mean (``centre``) or the
    pooled ``(1 - quantile, quantile)`` range; robust to a few extreme vertices."""
    v = np.concatenate([np.asarray(a, np.float64).ravel() for a in values])
    v = v[np.isfinite(v)]
    if v.size == 0:
        return 0.0, 1.0
    if centre:
        c = float(v.mean())
        half = float(np.quantile(np.abs(v - c), quantile)) or 1.0
        return c - half, c + half
    lo, hi = float(np.quantile(v, 1.0 - quantile)), float(np.quantile(v, quantile))
    return (lo, hi) if hi > lo else (lo - 0.5, lo + 0.5)


def _colorbar_row(cmap: str, limits: tuple[float, float], label: str, grid_width: int) -> np.ndarray:
    """A horizontal colour bar with its caption above, sized to the grid it explains."""
    width = int(min(max(grid_width * 0.6, 420), 760))
    bar = colorbar(cmap, limits[0], limits[1], width=width, height=84)
    return _vstack([_text_image([label], width, 17), bar])


# ---------------------------------------------------------------------------------------------- figures


def curvature_scales(
    mesh: Mesh,
    H: Any,
    taus: Any,
    path: str | os.PathLike | None = None,
    *,
    frames: int | None = 5,
    limits: tuple[float, float] | None = None,
    cmap: str = "coolwarm",
    camera: Camera | None = None,
    frame_size: int = 320,
    title: str | None = None,
    device=None,
) -> np.ndarray:
    """Fig. 5: VNC of one mesh at several scales, side by side, on one colour scale.

    Small scales show high-frequency detail, large ones the shape's coarse structure.

    Args:
        mesh: the mesh.
        H: (S, V) VNC per scale and vertex (NumPy, Warp or torch), e.g. ``scale_curve(mesh, taus).H``.
        taus: (S,) scales of the rows of ``H`` (mesh units).
        path: also write the PNG there.
        frames: how many scales to show, spread evenly from the smallest to the largest (None: all).
        limits: ``(vmin, vmax)`` of the colour scale; default symmetric about the pooled mean of the shown
            frames, covering 98 % of their values.
        cmap: colour map (diverging by default).
        camera: view; default :func:`auto_camera`.
        frame_size: pixels per (square) frame.
        title: default names the mesh.
        device: Warp device for rendering.

    Returns:
        (H, W, 3) uint8.

    Raises:
        ValueError: ``H`` and ``taus`` disagree with each other or with the mesh.
    """
    h = np.asarray(_host(H), np.float64)
    t = np.asarray(_host(taus), np.float64).reshape(-1)
    if h.ndim != 2 or h.shape != (t.size, mesh.num_vertices):
        raise ValueError(f"curvature_scales: H must be (S, V) = ({t.size}, {mesh.num_vertices}), got {h.shape}")
    idx = _evenly(t.size, frames)
    lim = tuple(limits) if limits is not None else _shared_limits([h[i] for i in idx], centre=True)
    cam = camera or auto_camera(mesh)
    edge = mesh.mean_edge_length
    tiles = [_frame(mesh, cam, frame_size, device, scalars=h[i], cmap=cmap, vmin=lim[0], vmax=lim[1]) for i in idx]
    labels = [f"τ = {t[i]:.3g}  ({t[i] / edge:.1f} × mean edge)" for i in idx]
    grid = _grid([tiles], frame=frame_size, labels=[labels])
    bar = _colorbar_row(cmap, lim, "VNC Ĥ (dimensionless), one colour scale for all frames", grid.shape[1])
    img = _titled(_vstack([grid, bar], 6), title or f"Fig. 5  VNC across scales: {mesh.name}",
                  "small scales: fine detail; large scales: coarse structure\n"
                  "red: more convex than the mean, blue: less")
    return _finish(img, path)


def scale_stability(
    taus: Any,
    vnc: Mapping[str, Any],
    baseline: Mapping[str, Any] | None = None,
    path: str | os.PathLike | None = None,
    *,
    edge_length: float | None = None,
    title: str | None = None,
    size: tuple[int, int] = (1400, 520),
    vector: str | None = "pdf",
) -> np.ndarray:
    """Fig. 6: vertex mean and variance of VNC and of the un-normalized baseline across scales.

    Three panels over a logarithmic scale axis: (a) the mean of each VNC operator, with a +-1 standard deviation
    band over vertices for the first (dimensionless: the mean stays put while the band narrows); (b) and (c) the
    mean and the variance of every operator relative to their values at the smallest scale, on logarithmic axes,
    so the dimensionless VNC and the baseline of Eq. (1) (length x angle, growing with the ball) share one axis.
    Earlier series are drawn wider, so curves that coincide (VNC-soft and -hard at r = 6 sigma) stay visible.

    Args:
        taus: (S,) scales (mesh units).
        vnc: name -> (S, V) per-vertex values of a normalized operator (Eq. 2 or 3) at each scale.
        baseline: name -> (S, V) per-vertex values of an un-normalized operator (Eq. 1), or None.
        path: also write the PNG there, and the ``vector`` copy beside it.
        edge_length: when given, scales are shown in mean edge lengths.
        title: figure title ("" for none).
        size: ``(width, height)`` of the PNG in pixels (:data:`vnc_warp.plot.DPI` per inch).
        vector: "pdf", "svg" or None.

    Returns:
        (H, W, 3) uint8.

    Raises:
        ValueError: no VNC series or arrays that are not (S, V).
    """
    t = np.asarray(_host(taus), np.float64).reshape(-1)
    if not vnc:
        raise ValueError("scale_stability: need at least one VNC series")
    stats = {}
    for group, series in (("vnc", vnc), ("baseline", baseline or {})):
        for name, values in series.items():
            v = np.asarray(_host(values), np.float64)
            if v.ndim != 2 or v.shape[0] != t.size:
                raise ValueError(f"scale_stability: {name!r} must be (S, V) with S = {t.size}, got {v.shape}")
            stats[name] = (group, v.mean(axis=1), v.var(axis=1))
    x = t / edge_length if edge_length else t
    xlabel = r"scale $\tau$ / mean edge length" if edge_length else r"scale $\tau$ (mesh units)"
    names = list(stats)
    widths = {n: 1.3 + 1.2 * (len(names) - 1 - k) for k, n in enumerate(names)}

    def ratio(a: np.ndarray) -> np.ndarray:
        with np.errstate(divide="ignore", invalid="ignore"):
            r = a / a[0]
        return np.where(r > 0, r, np.nan)

    vnc_names = [n for n, (g, _, _) in stats.items() if g == "vnc"]
    with plot.style():
        fig, (pa, pb, pc) = plot.figure(size, ncols=3)
        for k, n in enumerate(names):
            group, mean, var = stats[n]
            color = plot.rgb(k)
            if group == "vnc":
                pa.plot(x, mean, color=color, lw=widths[n], label=n)
                if n == vnc_names[0]:
                    sd = np.sqrt(var)
                    pa.fill_between(x, mean - sd, mean + sd, color=color, alpha=0.18, lw=0)
            pb.plot(x, ratio(mean), color=color, lw=widths[n], label=n)
            pc.plot(x, ratio(var), color=color, lw=widths[n], label=n)
        pa.set(title=r"(a) vertex mean of $\hat{H}$ $\pm$ 1 std", ylabel=r"$\hat{H}$ (dimensionless)")
        pb.set(title=r"(b) mean, relative to $\tau_{\min}$", ylabel=r"mean$(\tau)$ / mean$(\tau_{\min})$")
        pc.set(title=r"(c) variance, relative to $\tau_{\min}$", ylabel=r"var$(\tau)$ / var$(\tau_{\min})$")
        for ax in (pa, pb, pc):
            plot.log_axis(ax, "x")
            ax.set_xlabel(xlabel)
        plot.log_axis(pb, "y")
        plot.log_axis(pc, "y")
        handles, labels = pb.get_legend_handles_labels()
        fig.legend(handles, labels, loc="outside lower center", ncols=len(labels))
        fig.suptitle("Fig. 6  Scale stability of VNC and of the Eq. (1) baseline" if title is None else title)
        return plot.save_figure(fig, path, vector=vector)


def flow_auc(
    trajectory: Any,
    path: str | os.PathLike | None = None,
    *,
    title: str | None = None,
    size: tuple[int, int] = (1400, 560),
    vector: str | None = "pdf",
) -> np.ndarray:
    """Fig. 8a: mean VNC-AUC per vertex across the flow's iterations, with the stage boundaries.

    Each stage's ``history`` (``[iteration, S]`` pairs, the first measured right after the stage's SDF
    remesh) is laid end to end on one iteration axis; the vertical jump at a dashed boundary is the remesh
    rebound of the paper. A step line shows each stage's budget ``S_init - i S_init / N`` (Algorithm 1,
    line 14). Records without ``history`` are drawn one point per stage.

    Args:
        trajectory: a :class:`vnc_warp.flow.Trajectory` (its ``records`` and ``info["S_init"]``).
        path: also write the PNG there, and the ``vector`` copy beside it.
        title: figure title ("" for none).
        size: ``(width, height)`` of the PNG in pixels.
        vector: "pdf", "svg" or None.

    Returns:
        (H, W, 3) uint8.

    Raises:
        ValueError: a trajectory without records.
    """
    records = list(trajectory.records)
    if not records:
        raise ValueError("flow_auc: the trajectory has no records")
    s_init = float(trajectory.info.get("S_init", records[0]["S"]))
    v0 = float(records[0]["vertices"])
    name = trajectory.info.get("source", "")
    with plot.style():
        fig, ax = plot.figure(size)
        if all("history" in r for r in records[1:]) and len(records) > 1:
            xs, ys, bx, by = [0.0], [s_init / v0], [], []
            offset = 0
            for r in records[1:]:
                nv = float(r["vertices"])
                hist = np.asarray(r["history"], np.float64).reshape(-1, 2)
                xs += (offset + hist[:, 0]).tolist()
                ys += (hist[:, 1] / nv).tolist()
                budget = r.get("target_t", r["t"]) * s_init / nv
                bx += [offset, offset + r["iterations"], np.nan]
                by += [budget, budget, np.nan]
                if offset > 0:
                    ax.axvline(offset, color="0.55", ls=(0, (4, 3)), lw=0.6)
                offset += int(r["iterations"])
            ax.plot(xs, ys, color=plot.rgb(0), marker="o", ms=2.0, label=r"mean VNC-AUC $\bar{s}$ (Eq. 4)")
            ax.plot(bx, by, color=plot.rgb(1), lw=1.0, label="stage budget (Algorithm 1)")
            ax.set_xlabel("flow iteration (stages end to end; dashed: SDF remesh)")
        else:
            stages = np.arange(len(records), dtype=np.float64)
            ax.plot(stages, [r["S"] / r["vertices"] for r in records], color=plot.rgb(0), marker="o", ms=3.0,
                    label=r"mean VNC-AUC $\bar{s}$ (Eq. 4)")
            ax.set_xlabel("stage (no per-iteration history recorded)")
        ax.set_ylabel(r"$\bar{s}$ per vertex (mesh units)")
        ax.legend(loc="upper right")
        fig.suptitle((f"Fig. 8a  Spacetime balance of VNC-Flow{': ' + name if name else ''}") if title is None
                     else title)
        return plot.save_figure(fig, path, vector=vector)


def adaptive_scales(
    meshes: Sequence[Mesh],
    scales: Sequence[Any],
    path: str | os.PathLike | None = None,
    *,
    labels: Sequence[str] | None = None,
    limits: tuple[float, float] | None = None,
    cmap: str = "viridis",
    camera: Camera | None = None,
    frame_size: int = 320,
    title: str | None = None,
    device=None,
) -> np.ndarray:
    """Fig. 8b: adaptive-scale maps (Eq. 6) on meshes: small scales on complex regions, large on smooth ones.

    Args:
        meshes: meshes to show (e.g. a few stages of a trajectory).
        scales: one (V_i,) field of adaptive scales per mesh (mesh units), from
            :func:`vnc_warp.adaptive_scale`.
        path: also write the PNG there.
        labels: one caption per mesh.
        limits: ``(vmin, vmax)`` of the colour scale; default the pooled 2-98 % range.
        cmap: colour map.
        camera: view; default :func:`auto_camera` over all meshes.
        frame_size: pixels per frame.
        title: figure title.
        device: Warp device for rendering.

    Returns:
        (H, W, 3) uint8.

    Raises:
        ValueError: counts or sizes that do not match.
    """
    fields = [np.asarray(_host(s), np.float64).reshape(-1) for s in scales]
    if len(fields) != len(meshes) or not meshes:
        raise ValueError(f"adaptive_scales: {len(meshes)} meshes and {len(fields)} scale fields")
    for m, f in zip(meshes, fields):
        if f.size != m.num_vertices:
            raise ValueError(f"adaptive_scales: {m.name} has {m.num_vertices} vertices, its field {f.size} values")
    lim = tuple(limits) if limits is not None else _shared_limits(fields, centre=False)
    cam = camera or auto_camera(list(meshes))
    tiles = [_frame(m, cam, frame_size, device, scalars=f, cmap=cmap, vmin=lim[0], vmax=lim[1])
             for m, f in zip(meshes, fields)]
    grid = _grid([tiles], frame=frame_size, labels=[list(labels) if labels else [m.name for m in meshes]])
    bar = _colorbar_row(cmap, lim, "adaptive scale τ (Eq. 6, mesh units)", grid.shape[1])
    img = _titled(_vstack([grid, bar], 6), title or "Fig. 8b  Adaptive scales (Eq. 6)",
                  "complex regions get small scales (dark), smooth regions large ones (bright)")
    return _finish(img, path)


def filmstrip(
    meshes: Sequence[Mesh],
    t: Sequence[float],
    path: str | os.PathLike | None = None,
    *,
    max_frames: int | None = 9,
    scalars: Sequence[Any] | None = None,
    cmap: str = "coolwarm",
    limits: tuple[float, float] | None = None,
    camera: Camera | None = None,
    frame_size: int = 256,
    cols: int | None = None,
    title: str | None = None,
    device=None,
) -> np.ndarray:
    """Fig. 9a: a trajectory as a filmstrip, the normalized time ``t`` (Eq. 7) under each frame.

    All frames share one camera, so the shapes keep their relative size.

    Args:
        meshes: the trajectory's meshes, first (t = 1) to last.
        t: their normalized times.
        path: also write the PNG there.
        max_frames: show at most this many, spread evenly, first and last included (None: all).
        scalars: optional (V_i,) field per mesh to colour the frames (shared ``limits``).
        cmap, limits: colour map and ``(vmin, vmax)`` for ``scalars``.
        camera: view; default :func:`auto_camera` over all meshes.
        frame_size: pixels per frame.
        cols: frames per row (default: all in one row).
        title: figure title.
        device: Warp device for rendering.

    Returns:
        (H, W, 3) uint8.

    Raises:
        ValueError: ``meshes`` and ``t`` (or ``scalars``) differ in length, or no meshes.
    """
    tt = [float(v) for v in t]
    if not meshes or len(tt) != len(meshes) or (scalars is not None and len(scalars) != len(meshes)):
        raise ValueError(f"filmstrip: {len(meshes)} meshes, {len(tt)} times"
                         + (f", {len(scalars)} fields" if scalars is not None else ""))
    idx = _evenly(len(meshes), max_frames)
    cam = camera or auto_camera([meshes[i] for i in idx])
    shade: list[dict] = [{} for _ in idx]
    lim = None
    if scalars is not None:
        fields = [np.asarray(_host(scalars[i]), np.float64) for i in idx]
        lim = tuple(limits) if limits is not None else _shared_limits(fields, centre=True)
        shade = [dict(scalars=f, cmap=cmap, vmin=lim[0], vmax=lim[1]) for f in fields]
    tiles = [_frame(meshes[i], cam, frame_size, device, **s) for i, s in zip(idx, shade)]
    labels = [f"t = {tt[i]:.3f}" for i in idx]
    cols = cols or len(tiles)
    cells = [tiles[k:k + cols] for k in range(0, len(tiles), cols)]
    grid = _grid(cells, frame=frame_size, labels=[labels[k:k + cols] for k in range(0, len(labels), cols)])
    parts = [grid]
    if lim is not None:
        parts.append(_colorbar_row(cmap, lim, "VNC Ĥ (dimensionless)", grid.shape[1]))
    img = _titled(_vstack(parts, 6), title or "Fig. 9a  VNC-Flow trajectory",
                  "t (Eq. 7): remaining share of the initial total VNC-AUC, 1 = input, 0 = base shape")
    return _finish(img, path)


def _row_grid(rows: Sequence[tuple[str, Sequence[Any], Sequence[str]]], frame_size: int, camera: Camera | None,
              device, missing: str) -> np.ndarray:
    """Rows of meshes under a label column, a caption under each frame.

    None entries become ``missing`` placeholders and short rows are padded with "(stopped)". The default
    camera frames the first mesh of every row (all rows start from the same input), so a state that blows
    up is cropped instead of shrinking every other frame.
    """
    starts = [next((m for m in ms if m is not None), None) for _, ms, _ in rows]
    if all(m is None for m in starts):
        raise ValueError("no mesh to draw")
    cam = camera or auto_camera([m for m in starts if m is not None])
    cols = max(len(ms) for _, ms, _ in rows)
    cells, labels = [], []
    for _, ms, captions in rows:
        row = []
        for c in range(cols):
            if c >= len(ms):
                row.append("(stopped)")
            elif ms[c] is None:
                row.append(missing)
            else:
                row.append(_frame(ms[c], cam, frame_size, device))
        cells.append(row)
        labels.append(list(captions) + [""] * (cols - len(captions)))
    return _grid(cells, frame=frame_size, labels=labels, row_labels=[name for name, _, _ in rows])


def _captions(t: Sequence[float] | None, count: int, status: Sequence[str] | None = None) -> list[str]:
    """``t = 0.650`` under each frame, with the stage status appended where it is ``collapsed``."""
    out = []
    for c in range(count):
        text = f"t = {float(t[c]):.3f}" if t is not None and c < len(t) else ""
        if status is not None and c < len(status) and status[c] == "collapsed":
            text = f"{text}, collapsed" if text else "collapsed"
        out.append(text)
    return out


def flow_comparison(
    rows: Mapping[str, Sequence[Mesh]],
    t: Mapping[str, Sequence[float]] | None = None,
    path: str | os.PathLike | None = None,
    *,
    status: Mapping[str, Sequence[str]] | None = None,
    camera: Camera | None = None,
    frame_size: int = 200,
    title: str | None = None,
    device=None,
) -> np.ndarray:
    """Fig. 7: VNC-Flow next to its ablations and classical mean-curvature flow, one row per method.

    Column ``c`` holds stage ``c`` of every method (stage 0 is the common remeshed input); a method that
    stopped early (e.g. a collapsing baseline) leaves its remaining cells marked "(stopped)".

    Args:
        rows: row label -> the method's meshes by stage (labels may hold ``\\n``).
        t: row label -> normalized times of those meshes, printed under the frames.
        path: also write the PNG there.
        status: row label -> stage status (``records[i]["status"]`` of the flow); "collapsed" is printed.
        camera: view; default :func:`auto_camera` over the first mesh of every row.
        frame_size: pixels per frame.
        title: figure title.
        device: Warp device for rendering.

    Returns:
        (H, W, 3) uint8.

    Raises:
        ValueError: no rows or no meshes.
    """
    if not rows:
        raise ValueError("flow_comparison: no rows")
    grid = _row_grid([(name, list(ms), _captions(None if t is None else t.get(name), len(ms),
                                                 None if status is None else status.get(name)))
                      for name, ms in rows.items()], frame_size, camera, device, "(missing)")
    img = _titled(grid, title or "Fig. 7  VNC-Flow vs. fixed scales and mean curvature flow",
                  "first column: (a) the remeshed input; then stages 1 to N; one camera, fitted to the input")
    return _finish(img, path)


def decoded_trajectory(
    meshes: Sequence[Mesh | None],
    t: Sequence[float],
    path: str | os.PathLike | None = None,
    *,
    reference: Sequence[Mesh] | None = None,
    reference_t: Sequence[float] | None = None,
    camera: Camera | None = None,
    frame_size: int = 220,
    title: str | None = None,
    device=None,
) -> np.ndarray:
    """Fig. 9b: meshes a C-VAE decoded at several times ``t``, optionally above a reference trajectory.

    Args:
        meshes: decoded meshes, one per time; None marks a time whose decoding gave no surface.
        t: the times they were decoded at.
        path: also write the PNG there.
        reference: e.g. the VNC-Flow stages of the same input, drawn as a second row.
        reference_t: the reference's times (required with ``reference``).
        camera: view; default :func:`auto_camera` over the reference (else over the decoded meshes).
        frame_size: pixels per frame.
        title: figure title.
        device: Warp device for rendering.

    Returns:
        (H, W, 3) uint8.

    Raises:
        ValueError: lengths that differ, ``reference`` without ``reference_t``, or no mesh at all.
    """
    if len(meshes) != len(t):
        raise ValueError(f"decoded_trajectory: {len(meshes)} meshes and {len(t)} times")
    rows = [("C-VAE decoded", list(meshes), _captions(t, len(t)))]
    if reference is not None:
        if reference_t is None or len(reference_t) != len(reference):
            raise ValueError("decoded_trajectory: reference needs reference_t of the same length")
        rows.append(("VNC-Flow\n(reference)", list(reference), _captions(reference_t, len(reference_t))))
    if camera is None:
        # the reference is trustworthy geometry; decoded meshes may carry stray blobs that would move the view
        frame_on = list(reference) if reference is not None else [m for m in meshes if m is not None]
        camera = auto_camera(frame_on) if frame_on else None
    grid = _row_grid(rows, frame_size, camera, device, "no surface\ndecoded")
    img = _titled(grid, title or "Fig. 9b  C-VAE predictions across t",
                  "the shape at each t is decoded from the input and the time condition alone")
    return _finish(img, path)


def latent_space(
    latents: Any,
    t: Any,
    path: str | os.PathLike | None = None,
    *,
    use_umap: bool = True,
    seed: int = 0,
    title: str | None = None,
    size: tuple[int, int] = (1400, 600),
    vector: str | None = "pdf",
) -> np.ndarray:
    """Fig. 11: C-VAE latents in two dimensions, coloured by the normalized time ``t``.

    (a) max-pooled latents through UMAP when ``umap-learn`` is installed (else PCA, and the panel says so):
    the radial structure; (b) mean-pooled latents through PCA: the parallel structure along ``t``.
    Panel titles give the Pearson correlation that quantifies each structure.

    Args:
        latents: (N, M, C) latent sets or (N, C) vectors (NumPy or torch).
        t: (N,) normalized times.
        path: also write the PNG there, and the ``vector`` copy beside it.
        use_umap: try UMAP for panel (a).
        seed: UMAP random state.
        title: figure title ("" for none).
        size: ``(width, height)`` of the PNG in pixels.
        vector: "pdf", "svg" or None.

    Returns:
        (H, W, 3) uint8.

    Raises:
        ValueError: fewer than 3 samples or shapes that do not match.
    """
    from .stats import pca, pearson

    z = np.asarray(_host(latents), np.float64)
    tt = np.asarray(_host(t), np.float64).reshape(-1)
    if z.ndim == 2:
        z = z[:, None, :]
    if z.ndim != 3 or z.shape[0] != tt.size or tt.size < 3:
        raise ValueError(f"latent_space: need (N, M, C) or (N, C) latents with N >= 3 and (N,) t, "
                         f"got {z.shape} and {tt.shape}")
    max_pooled, mean_pooled = z.max(axis=1), z.mean(axis=1)
    k = 2 if min(mean_pooled.shape) >= 2 else 1

    def two_d(scores: np.ndarray) -> np.ndarray:
        return scores if scores.shape[1] == 2 else np.concatenate([scores, np.zeros_like(scores)], axis=1)

    embedding, method = None, "PCA"
    if use_umap and tt.size >= 4:
        try:
            import umap
        except ImportError:
            umap = None
        if umap is not None:
            reducer = umap.UMAP(n_components=2, n_neighbors=min(15, tt.size - 1), random_state=seed)
            embedding, method = np.asarray(reducer.fit_transform(max_pooled)), "UMAP"
    if embedding is None:
        embedding = two_d(pca(max_pooled, k)["scores"])
    radius = np.linalg.norm(embedding - embedding.mean(axis=0), axis=1)
    p = pca(mean_pooled, k)
    scores = two_d(p["scores"])
    with plot.style():
        fig, (pa, pb) = plot.figure(size, ncols=2)
        sc = plot._scatter(fig, pa, embedding[:, 0], embedding[:, 1], tt, cmap="viridis", vmin=0.0, vmax=1.0,
                           clabel="", marker_size=14.0, colorbar=False)
        plot._scatter(fig, pb, scores[:, 0], scores[:, 1], tt, cmap="viridis", vmin=0.0, vmax=1.0, clabel="",
                      marker_size=14.0, colorbar=False)
        pa.set(title=f"(a) {method} of max-pooled latents" + ("" if method == "UMAP" else " (no umap-learn)")
                     + f"\n$r$(radius, $t$) = {pearson(radius, tt):+.2f}", xlabel=f"{method} 1", ylabel=f"{method} 2")
        pb.set(title=f"(b) PCA of mean-pooled latents\n$|r$(PC1, $t$)$|$ = {abs(pearson(scores[:, 0], tt)):.2f}",
               xlabel=f"PC1 ({100 * p['explained_variance_ratio'][0]:.0f} % of the variance)", ylabel="PC2")
        fig.colorbar(sc, ax=[pa, pb], label="$t$ (Eq. 7)", shrink=0.9)
        fig.suptitle(f"Fig. 11  Latent space of the C-VAE: {tt.size} latents" if title is None else title)
        return plot.save_figure(fig, path, vector=vector)
