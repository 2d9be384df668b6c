"""Small line and scatter plots for the paper's charts (Figs. 6, 8a, 11), with or without matplotlib.

Both functions draw with matplotlib (Agg, no pyplot state) when it is importable and otherwise with
Pillow alone: axes, numbered ticks, axis labels, title, legend, colours per series, dashed stage
boundaries, shaded spreads and per-point colours. ``backend="pil"`` forces the Pillow path.
Both return the picture as an ``(H, W, 3) uint8`` array and can write it as PNG.
"""

from __future__ import annotations

import importlib.util
import os
from typing import Any, Mapping, Sequence

import numpy as np

from .render import _as_rgb8, _font, _host, _nice_ticks, _text_size, _tick_format, colorbar, colormap, save_png

__all__ = ["line_plot", "scatter_plot", "SERIES_COLORS"]

#: Series colours in order (matplotlib's "tab10" cycle), RGB uint8.
SERIES_COLORS = [
    (31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189),
    (140, 86, 75), (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207),
]
_VLINE_RGB = (110, 110, 110)
_GRID_RGB = (228, 228, 228)


def _use_matplotlib(backend: str) -> bool:
    if backend not in ("auto", "matplotlib", "pil"):
        raise ValueError(f"backend must be 'auto', 'matplotlib' or 'pil', got {backend!r}")
    if backend == "pil":
        return False
    if importlib.util.find_spec("matplotlib") is None:
        if backend == "matplotlib":
            raise ImportError("backend='matplotlib' needs matplotlib (pip install 'vnc-warp[plot]')")
        return False
    return True


def _check_size(size: Sequence[int]) -> tuple[int, int]:
    w, h = (int(s) for s in size)
    if w < 120 or h < 100:
        raise ValueError(f"plot size must be at least (120, 100) pixels, got {tuple(size)}")
    return w, h


def _series_arrays(series: Mapping[str, Any]) -> list[tuple[str, np.ndarray, np.ndarray, np.ndarray | None]]:
    """``(name, x, y, spread or None)`` per series, all (N,) float64, validated."""
    if not series:
        raise ValueError("line_plot: no series")
    out = []
    for name, data in series.items():
        if len(data) not in (2, 3):
            raise ValueError(f"line_plot: series {name!r} must be (x, y) or (x, y, spread)")
        arrays = [np.asarray(_host(d), dtype=np.float64).reshape(-1) for d in data]
        if any(a.shape != arrays[0].shape for a in arrays):
            raise ValueError(f"line_plot: series {name!r} has arrays of lengths {[a.size for a in arrays]}")
        out.append((str(name), arrays[0], arrays[1], arrays[2] if len(arrays) == 3 else None))
    return out


def _limits(values: list[np.ndarray], pad: float) -> tuple[float, float]:
    """Finite range of the values, widened by ``pad`` of its span (or by 0.5 / 5 % when it is a point)."""
    v = np.concatenate([a[np.isfinite(a)] for a in values]) if values else np.zeros(0)
    if v.size == 0:
        raise ValueError("plot: no finite data to draw")
    lo, hi = float(v.min()), float(v.max())
    if hi == lo:
        d = 0.05 * abs(lo) if lo != 0.0 else 0.5
        return lo - d, hi + d
    d = (hi - lo) * pad
    return lo - d, hi + d


class _Axes:
    """A Pillow canvas with one set of axes: data-to-pixel mapping and the frame, ticks and labels.

    Everything is drawn ``k`` times larger and shrunk at the end (:meth:`rgb`), which anti-aliases
    lines, markers and text; lengths given to the methods are in output pixels.
    """

    def __init__(self, size, xlim, ylim, *, title, xlabel, ylabel, right_margin=20, k=2):
        from PIL import Image, ImageDraw

        self.size, self.k = size, k
        self.w, self.h = size[0] * k, size[1] * k
        self.image = Image.new("RGBA", (self.w, self.h), (255, 255, 255, 255))
        self.draw = ImageDraw.Draw(self.image)
        base = max(10, round(min(size) / 38))
        self.font, self.label_font, self.title_font = _font(base * k), _font((base + 2) * k), _font((base + 4) * k)
        self.xlim, self.ylim = xlim, ylim
        self.xticks = _nice_ticks(*xlim, count=max(3, size[0] // 120))
        self.yticks = _nice_ticks(*ylim, count=max(3, size[1] // 80))
        self.xfmt, self.yfmt = _tick_format(self.xticks), _tick_format(self.yticks)
        _, th = _text_size(self.draw, "0.9", self.font)
        ytw = max(_text_size(self.draw, self.yfmt(t), self.font)[0] for t in self.yticks)
        _, lh = _text_size(self.draw, "Xg", self.label_font)
        self.left = 14 * k + ytw + 8 * k + (lh + 8 * k if ylabel else 0)
        self.bottom = self.h - (12 * k + th + 8 * k + (lh + 10 * k if xlabel else 0))
        self.top = 12 * k + (_text_size(self.draw, "Xg", self.title_font)[1] + 12 * k if title else 0)
        self.right = self.w - right_margin * k
        if self.right - self.left < 20 * k or self.bottom - self.top < 20 * k:
            raise ValueError(f"plot size {size} leaves no room for the axes")
        self.title, self.xlabel, self.ylabel = title, xlabel, ylabel

    def px(self, x):
        x0, x1 = self.xlim
        return self.left + (np.asarray(x, np.float64) - x0) / (x1 - x0) * (self.right - self.left)

    def py(self, y):
        y0, y1 = self.ylim
        return self.bottom - (np.asarray(y, np.float64) - y0) / (y1 - y0) * (self.bottom - self.top)

    def grid(self):
        for t in self.xticks:
            x = float(self.px(t))
            self.draw.line([(x, self.top), (x, self.bottom)], fill=_GRID_RGB, width=self.k)
        for t in self.yticks:
            y = float(self.py(t))
            self.draw.line([(self.left, y), (self.right, y)], fill=_GRID_RGB, width=self.k)

    def fill_alpha(self, polygon, rgb, alpha=0.25):
        """A translucent polygon (composited, so overlapping spreads stay visible)."""
        from PIL import Image, ImageDraw

        layer = Image.new("RGBA", self.image.size, (0, 0, 0, 0))
        ImageDraw.Draw(layer).polygon(polygon, fill=tuple(rgb) + (int(255 * alpha),))
        self.image.alpha_composite(layer)
        self.draw = ImageDraw.Draw(self.image)

    def dashed_vline(self, x, rgb=_VLINE_RGB, dash=7, gap=5):
        xp = float(self.px(x))
        y = float(self.top)
        while y < self.bottom:
            self.draw.line([(xp, y), (xp, min(y + dash * self.k, self.bottom))], fill=rgb, width=self.k)
            y += (dash + gap) * self.k

    def polyline(self, x, y, rgb, width=2):
        """A line through the points, broken at non-finite values; isolated points become dots."""
        width *= self.k
        ok = np.isfinite(x) & np.isfinite(y)
        xs, ys = self.px(np.where(ok, x, 0.0)), self.py(np.where(ok, y, 0.0))
        run = []
        for k in range(len(ok) + 1):
            if k < len(ok) and ok[k]:
                run.append((float(xs[k]), float(ys[k])))
                continue
            if len(run) > 1:
                self.draw.line(run, fill=rgb, width=width, joint="curve")
            elif len(run) == 1:
                cx, cy = run[0]
                self.draw.ellipse([cx - width, cy - width, cx + width, cy + width], fill=rgb)
            run = []

    def frame(self):
        """Axes box, ticks with numbers, axis labels and title (drawn last, over the data)."""
        from PIL import Image, ImageDraw

        d, k, black = self.draw, self.k, (0, 0, 0)
        d.rectangle([self.left, self.top, self.right, self.bottom], outline=black, width=k)
        for t in self.xticks:
            x = float(self.px(t))
            d.line([(x, self.bottom), (x, self.bottom + 5 * k)], fill=black, width=k)
            d.text((x, self.bottom + 8 * k), self.xfmt(t), fill=black, font=self.font, anchor="mt")
        for t in self.yticks:
            y = float(self.py(t))
            d.line([(self.left - 5 * k, y), (self.left, y)], fill=black, width=k)
            d.text((self.left - 8 * k, y), self.yfmt(t), fill=black, font=self.font, anchor="rm")
        if self.title:
            d.text((self.w / 2, 8 * k), self.title, fill=black, font=self.title_font, anchor="mt")
        if self.xlabel:
            d.text(((self.left + self.right) / 2, self.h - 8 * k), self.xlabel, fill=black, font=self.label_font,
                   anchor="mb")
        if self.ylabel:
            tw, th = _text_size(d, self.ylabel, self.label_font)
            label = Image.new("RGBA", (tw + 4 * k, th + 8 * k), (255, 255, 255, 0))
            ImageDraw.Draw(label).text((2 * k, 2 * k), self.ylabel, fill=black + (255,), font=self.label_font,
                                       anchor="lt")
            label = label.rotate(90, expand=True)
            y0 = int((self.top + self.bottom) / 2 - label.height / 2)
            self.image.alpha_composite(label, (6 * k, max(y0, 0)))

    def legend(self, entries: list[tuple[str, tuple[int, int, int]]]):
        """Names with line samples in a framed box at the top right inside the axes."""
        if not entries:
            return
        d, k = self.draw, self.k
        sizes = [_text_size(d, name, self.font) for name, _ in entries]
        row = max(h for _, h in sizes) + 8 * k
        box_w = 44 * k + max(w for w, _ in sizes) + 10 * k
        box_h = row * len(entries) + 8 * k
        x0, y0 = self.right - box_w - 8 * k, self.top + 8 * k
        d.rectangle([x0, y0, x0 + box_w, y0 + box_h], fill=(255, 255, 255), outline=(160, 160, 160), width=k)
        for i, (name, rgb) in enumerate(entries):
            yc = y0 + 4 * k + row * i + row / 2
            d.line([(x0 + 10 * k, yc), (x0 + 34 * k, yc)], fill=rgb, width=3 * k)
            d.text((x0 + 42 * k, yc), name, fill=(0, 0, 0), font=self.font, anchor="lm")

    def rgb(self) -> np.ndarray:
        """The picture at the requested size, (H, W, 3) uint8."""
        from PIL import Image

        return np.asarray(self.image.convert("RGB").resize(self.size, Image.Resampling.LANCZOS))


def _finish(img: np.ndarray, path: str | os.PathLike | None) -> np.ndarray:
    img = _as_rgb8(img, "plot")
    if path is not None:
        save_png(path, img)
    return img


def _mpl_figure(size):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(size[0] / 100.0, size[1] / 100.0), dpi=100)
    canvas = FigureCanvasAgg(fig)
    return fig, canvas


def _mpl_pixels(fig, canvas) -> np.ndarray:
    fig.tight_layout()
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[:, :, :3].copy()


def line_plot(
    series: Mapping[str, Any],
    *,
    title: str = "",
    xlabel: str = "",
    ylabel: str = "",
    vlines: Sequence[float] | None = None,
    path: str | os.PathLike | None = None,
    size: tuple[int, int] = (800, 500),
    backend: str = "auto",
) -> np.ndarray:
    """Lines for several named series, e.g. mean VNC against scale (Fig. 6) or against flow step (Fig. 8a).

    Args:
        series: name -> ``(x, y)`` or ``(x, y, spread)``, each (N,) array-like (NumPy, Warp or torch);
            a spread is drawn as a translucent band ``y +- spread``. Non-finite points break the line.
            Series with an empty name stay out of the legend.
        title, xlabel, ylabel: texts.
        vlines: x positions of dashed vertical markers (e.g. stage boundaries).
        path: also write the picture there as PNG.
        size: ``(width, height)`` in pixels.
        backend: ``"auto"`` (matplotlib if importable, else Pillow), ``"matplotlib"`` or ``"pil"``.

    Returns:
        ``(height, width, 3) uint8``.

    Raises:
        ValueError: no series, mismatched lengths, no finite data, a bad size or backend.
        ImportError: ``backend="matplotlib"`` without matplotlib.
    """
    w, h = _check_size(size)
    data = _series_arrays(series)
    vl = [float(v) for v in (vlines or [])]
    if _use_matplotlib(backend):
        fig, canvas = _mpl_figure((w, h))
        ax = fig.add_subplot()
        for k, (name, x, y, spread) in enumerate(data):
            rgb = np.asarray(SERIES_COLORS[k % len(SERIES_COLORS)]) / 255.0
            ax.plot(x, y, color=rgb, lw=2, label=name or "_nolegend_")
            if spread is not None:
                ax.fill_between(x, y - spread, y + spread, color=rgb, alpha=0.25, lw=0)
        for v in vl:
            ax.axvline(v, color=np.asarray(_VLINE_RGB) / 255.0, ls="--", lw=1)
        ax.set(title=title, xlabel=xlabel, ylabel=ylabel)
        ax.grid(True, color=np.asarray(_GRID_RGB) / 255.0)
        if any(name for name, *_ in data):
            ax.legend(loc="upper right")
        return _finish(_mpl_pixels(fig, canvas), path)

    xs = [x for _, x, _, _ in data] + ([np.asarray(vl)] if vl else [])
    ys = []
    for _, _, y, spread in data:
        ys += [y] if spread is None else [y - spread, y + spread]
    ax = _Axes((w, h), _limits(xs, 0.02), _limits(ys, 0.06), title=title, xlabel=xlabel, ylabel=ylabel)
    ax.grid()
    for k, (_, x, y, spread) in enumerate(data):
        if spread is not None:
            ok = np.isfinite(x) & np.isfinite(y) & np.isfinite(spread)
            if ok.sum() > 1:
                upper = list(zip(ax.px(x[ok]).tolist(), ax.py((y + spread)[ok]).tolist()))
                lower = list(zip(ax.px(x[ok]).tolist(), ax.py((y - spread)[ok]).tolist()))
                ax.fill_alpha(upper + lower[::-1], SERIES_COLORS[k % len(SERIES_COLORS)])
    for v in vl:
        ax.dashed_vline(v)
    for k, (_, x, y, _) in enumerate(data):
        ax.polyline(x, y, SERIES_COLORS[k % len(SERIES_COLORS)])
    ax.frame()
    ax.legend([(name, SERIES_COLORS[k % len(SERIES_COLORS)]) for k, (name, *_) in enumerate(data) if name])
    return _finish(ax.rgb(), path)


def scatter_plot(
    x: Any,
    y: Any,
    *,
    c: Any = None,
    cmap: str = "viridis",
    vmin: float | None = None,
    vmax: float | None = None,
    clabel: str = "",
    title: str = "",
    xlabel: str = "",
    ylabel: str = "",
    marker_size: float = 6.0,
    path: str | os.PathLike | None = None,
    size: tuple[int, int] = (800, 500),
    backend: str = "auto",
) -> np.ndarray:
    """Points, optionally coloured by a scalar with a colour bar, e.g. latent codes coloured by ``t`` (Fig. 11).

    Args:
        x, y: (N,) coordinates; points with a non-finite coordinate are skipped.
        c: (N,) scalar per point drawn through :func:`vnc_warp.render.colormap`, or ``None`` for one colour.
        cmap, vmin, vmax: colour map and its limits for ``c`` (default the finite range).
        clabel: colour bar caption.
        title, xlabel, ylabel: texts.
        marker_size: marker diameter in pixels.
        path: also write the picture there as PNG.
        size: ``(width, height)`` in pixels.
        backend: ``"auto"``, ``"matplotlib"`` or ``"pil"`` (see :func:`line_plot`).

    Returns:
        ``(height, width, 3) uint8``.

    Raises:
        ValueError: mismatched lengths, no finite point, a bad size, backend or cmap.
        ImportError: ``backend="matplotlib"`` without matplotlib.
    """
    w, h = _check_size(size)
    xa = np.asarray(_host(x), dtype=np.float64).reshape(-1)
    ya = np.asarray(_host(y), dtype=np.float64).reshape(-1)
    ca = None if c is None else np.asarray(_host(c), dtype=np.float64).reshape(-1)
    if ya.shape != xa.shape or (ca is not None and ca.shape != xa.shape):
        raise ValueError(f"scatter_plot: x, y{', c' if ca is not None else ''} must have one length, got "
                         f"{xa.size}, {ya.size}" + (f", {ca.size}" if ca is not None else ""))
    colors = None if ca is None else colormap(ca, cmap, vmin, vmax)
    if _use_matplotlib(backend):
        fig, canvas = _mpl_figure((w, h))
        ax = fig.add_subplot()
        s = (marker_size * 0.72) ** 2
        if ca is None:
            ax.scatter(xa, ya, s=s, color=np.asarray(SERIES_COLORS[0]) / 255.0, lw=0)
        else:
            finite = ca[np.isfinite(ca)]
            lo = vmin if vmin is not None else (finite.min() if finite.size else 0.0)
            hi = vmax if vmax is not None else (finite.max() if finite.size else 1.0)
            sc = ax.scatter(xa, ya, s=s, c=ca, cmap=cmap, vmin=lo, vmax=hi, lw=0)
            fig.colorbar(sc, ax=ax, label=clabel)
        ax.set(title=title, xlabel=xlabel, ylabel=ylabel)
        ax.grid(True, color=np.asarray(_GRID_RGB) / 255.0)
        ax.set_axisbelow(True)
        return _finish(_mpl_pixels(fig, canvas), path)

    bar_w = max(70, w // 9) if ca is not None else 0
    ok = np.isfinite(xa) & np.isfinite(ya)
    ax = _Axes((w, h), _limits([xa[ok]], 0.04), _limits([ya[ok]], 0.04), title=title, xlabel=xlabel, ylabel=ylabel,
               right_margin=20 + bar_w)
    ax.grid()
    r = max(marker_size / 2.0, 0.5) * ax.k
    px, py = ax.px(xa), ax.py(ya)
    for k in np.nonzero(ok)[0]:
        rgb = SERIES_COLORS[0] if colors is None else tuple(int(round(v * 255)) for v in colors[k])
        ax.draw.ellipse([px[k] - r, py[k] - r, px[k] + r, py[k] + r], fill=rgb)
    ax.frame()
    if ca is not None:
        from PIL import Image

        finite = ca[np.isfinite(ca)]
        lo = float(vmin) if vmin is not None else (float(finite.min()) if finite.size else 0.0)
        hi = float(vmax) if vmax is not None else (float(finite.max()) if finite.size else 1.0)
        if hi <= lo:
            hi = lo + 1.0
        bar = colorbar(cmap, lo, hi, label=clabel, width=(bar_w - 10) * ax.k, height=max(ax.bottom - ax.top, 40))
        ax.image.paste(Image.fromarray(bar).convert("RGBA"), (ax.right + 16 * ax.k, ax.top))
    return _finish(ax.rgb(), path)
