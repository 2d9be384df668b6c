"""Plots for the paper's charts (Figs. 6, 8a, 11), drawn with matplotlib, ready for a paper.

One style for every plot (:data:`STYLE`): STIX for text and mathematics alike (``$\\tau$``, ``$\\hat{H}$``,
``$t$`` set in the same face as the words around them), small print sizes, the fonts embedded in the PDF as
TrueType. Every plot is written twice, as a PNG (to look at, :data:`DPI` pixels per inch) and as a vector PDF (or
SVG) beside it for the paper. Figures are made on matplotlib's Agg canvas, never through ``pyplot``, so nothing
global changes and no window opens.

Meshes are not plots: they are ray-cast by :mod:`vnc_warp.render` and tiled by :mod:`vnc_warp.figures`.
"""

from __future__ import annotations

import os
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

__all__ = ["line_plot", "scatter_plot", "figure", "save_figure", "style", "log_axis", "rgb", "SERIES_COLORS", "STYLE",
           "DPI"]

#: Pixels per inch of the PNGs; a plot of ``size=(w, h)`` pixels is ``w / DPI`` by ``h / DPI`` inches.
DPI = 200

#: Series colours in order (matplotlib's "tab10" cycle), RGB uint8.
SERIES_COLORS = [
    (31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189),
    (140, 86, 75), (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207),
]

#: matplotlib settings of every plot: one face (STIX) for text and mathematics, print sizes, embedded fonts.
STYLE = {
    "font.family": "STIXGeneral",
    "mathtext.fontset": "stix",
    "font.size": 9.0,
    "axes.titlesize": 9.0,
    "axes.labelsize": 9.0,
    "legend.fontsize": 8.0,
    "xtick.labelsize": 8.0,
    "ytick.labelsize": 8.0,
    "figure.titlesize": 10.0,
    "axes.linewidth": 0.6,
    "lines.linewidth": 1.4,
    "xtick.major.width": 0.6,
    "ytick.major.width": 0.6,
    "axes.grid": True,
    "grid.color": "#e4e4e4",
    "grid.linewidth": 0.5,
    "axes.axisbelow": True,
    "axes.spines.top": False,
    "axes.spines.right": False,
    "legend.frameon": False,
    "pdf.fonttype": 42,
    "svg.fonttype": "none",
    "savefig.dpi": DPI,
    "figure.dpi": DPI,
}

_VECTOR = (None, "pdf", "svg")


@contextmanager
def style():
    """Draw inside ``with style():`` to get :data:`STYLE` (a figure must also be saved inside it: mathematics is
    typeset when it is drawn)."""
    import matplotlib

    with matplotlib.rc_context(STYLE):
        yield


def figure(size: tuple[float, float], *, nrows: int = 1, ncols: int = 1, **subplots):
    """A matplotlib ``Figure`` on the Agg canvas (no pyplot state) of ``size`` pixels at :data:`DPI`, and its
    axes (``Figure.subplots(nrows, ncols, **subplots)``). Call inside :func:`style`."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    w, h = _check_size(size)
    fig = Figure(figsize=(w / DPI, h / DPI), dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    return fig, fig.subplots(nrows, ncols, squeeze=True, **subplots)


def save_figure(fig, path: str | os.PathLike | None = None, *, vector: str | None = "pdf") -> np.ndarray:
    """Draw ``fig``; write it to ``path`` as PNG and, with ``vector``, as a PDF or SVG beside it (the same name
    with that suffix). Call inside :func:`style`.

    Returns:
        The picture, ``(H, W, 3) uint8``, as the PNG holds it.
    """
    if vector not in _VECTOR:
        raise ValueError(f"vector must be 'pdf', 'svg' or None, got {vector!r}")
    fig.canvas.draw()
    img = np.asarray(fig.canvas.buffer_rgba())[:, :, :3].copy()
    if path is not None:
        png = Path(path)
        if png.suffix.lower() not in (".png", ""):
            raise ValueError(f"path names the PNG (the {vector or 'vector'} copy goes beside it), got {png}")
        from PIL import Image

        png = png.with_suffix(".png")
        png.parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(img).save(png, dpi=(DPI, DPI))  # the pixels returned, not a second layout
        if vector is not None:
            fig.savefig(png.with_suffix("." + vector))
    return img


def log_axis(ax, which: str = "x") -> None:
    """A logarithmic x or y axis labelled with plain numbers (1, 2, 5, 10, ...; not ``2 x 10^0``), no minor
    labels."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    axis = ax.xaxis if which == "x" else ax.yaxis
    (ax.set_xscale if which == "x" else ax.set_yscale)("log")
    lo, hi = (ax.get_xlim() if which == "x" else ax.get_ylim())
    # few decades: 1-2-5 steps, so that a short axis still has several labels
    subs = (1.0, 2.0, 5.0) if hi / max(lo, 1e-300) < 1e3 else (1.0,)
    axis.set_major_locator(LogLocator(base=10.0, subs=subs))
    axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    axis.set_minor_formatter(NullFormatter())


def _check_size(size: Sequence[float]) -> tuple[int, int]:
    w, h = (int(round(s)) for s in size)
    if w < 120 or h < 100:
        raise ValueError(f"plot size must be at least (120, 100) pixels, got {tuple(size)}")
    return w, h


def _host(a: Any) -> np.ndarray:
    if hasattr(a, "detach"):
        a = a.detach().cpu().numpy()
    elif hasattr(a, "numpy") and not isinstance(a, np.ndarray):
        a = a.numpy()
    return np.asarray(a, dtype=np.float64)


def _series_arrays(series: Mapping[str, Any]) -> list[tuple[str, np.ndarray, np.ndarray, np.ndarray | None]]:
    """``(name, x, y, spread or None)`` per series, all (N,) float64, validated."""
    if not series:
        raise ValueError("line_plot: no series")
    out = []
    for name, data in series.items():
        if len(data) not in (2, 3):
            raise ValueError(f"line_plot: series {name!r} must be (x, y) or (x, y, spread)")
        arrays = [_host(d).reshape(-1) for d in data]
        if any(a.shape != arrays[0].shape for a in arrays):
            raise ValueError(f"line_plot: series {name!r} has arrays of lengths {[a.size for a in arrays]}")
        out.append((str(name), arrays[0], arrays[1], arrays[2] if len(arrays) == 3 else None))
    if not any(np.isfinite(x).any() and np.isfinite(y).any() for _, x, y, _ in out):
        raise ValueError("line_plot: no finite data to draw")
    return out


def rgb(k: int) -> tuple[float, float, float]:
    """Series colour ``k`` (cycling) as matplotlib takes it."""
    return tuple(c / 255.0 for c in SERIES_COLORS[k % len(SERIES_COLORS)])


def line_plot(
    series: Mapping[str, Any],
    *,
    title: str = "",
    xlabel: str = "",
    ylabel: str = "",
    vlines: Sequence[float] | None = None,
    logx: bool = False,
    logy: bool = False,
    path: str | os.PathLike | None = None,
    vector: str | None = "pdf",
    size: tuple[int, int] = (1000, 620),
    legend: str = "best",
) -> np.ndarray:
    """Lines for several named series, e.g. mean VNC against scale (Fig. 6) or against flow step (Fig. 8a).

    Args:
        series: name -> ``(x, y)`` or ``(x, y, spread)``, each (N,) array-like (NumPy, Warp or torch); a spread is a
            translucent band ``y +- spread``. Non-finite points break the line. Names may hold mathematics
            (``"$\\hat{H}$"``); series with an empty name stay out of the legend.
        title, xlabel, ylabel: texts (mathematics in ``$...$``).
        vlines: x positions of dashed vertical markers (e.g. stage boundaries).
        logx, logy: logarithmic axes.
        path: write the PNG there, and the ``vector`` copy beside it.
        vector: "pdf", "svg" or None.
        size: ``(width, height)`` of the PNG in pixels (:data:`DPI` per inch).
        legend: a Matplotlib legend location inside the axes, or ``"outside"``: right of the axes, where no line
            can run under it (many series, or lines that fill the axes).

    Returns:
        ``(height, width, 3) uint8``.

    Raises:
        ValueError: no series, mismatched lengths, no finite data, a bad size or vector format.
    """
    data = _series_arrays(series)
    with style():
        fig, ax = figure(size)
        for k, (name, x, y, spread) in enumerate(data):
            ax.plot(x, y, color=rgb(k), label=name or "_nolegend_")
            if spread is not None:
                ax.fill_between(x, y - spread, y + spread, color=rgb(k), alpha=0.22, lw=0)
        for v in vlines or []:
            ax.axvline(float(v), color="0.45", ls=(0, (4, 3)), lw=0.7)
        ax.set(title=title, xlabel=xlabel, ylabel=ylabel)
        if logx:
            log_axis(ax, "x")
        if logy:
            log_axis(ax, "y")
        if any(name for name, *_ in data):
            if legend == "outside":
                ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0.0)
            else:
                ax.legend(loc=legend)
        return save_figure(fig, path, vector=vector)


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
    marker_size: float = 12.0,
    path: str | os.PathLike | None = None,
    vector: str | None = "pdf",
    size: tuple[int, int] = (1000, 620),
) -> np.ndarray:
    """Points, optionally coloured by a scalar with a colour bar, e.g. latent codes coloured by ``t`` (Fig. 11).

    A stable entry point for any scatter plot of the package (``vnc_warp.training`` included).

    Args:
        x, y: (N,) coordinates; points with a non-finite coordinate are skipped.
        c: (N,) scalar per point (colour map ``cmap`` from ``vmin`` to ``vmax``, default its finite range), or
            None for one colour.
        clabel: colour bar caption (e.g. ``"$t$"``).
        title, xlabel, ylabel: texts (mathematics in ``$...$``).
        marker_size: marker area in points squared (matplotlib's ``s``).
        path, vector, size: as for :func:`line_plot`.

    Returns:
        ``(height, width, 3) uint8``.

    Raises:
        ValueError: mismatched lengths, a bad size, colour map or vector format.
    """
    xa, ya = _host(x).reshape(-1), _host(y).reshape(-1)
    ca = None if c is None else _host(c).reshape(-1)
    if ya.shape != xa.shape or (ca is not None and ca.shape != xa.shape):
        raise ValueError(f"scatter_plot: x, y{', c' if ca is not None else ''} must have one length, got "
                         f"{xa.size}, {ya.size}" + (f", {ca.size}" if ca is not None else ""))
    with style():
        fig, ax = figure(size)
        _scatter(fig, ax, xa, ya, ca, cmap=cmap, vmin=vmin, vmax=vmax, clabel=clabel, marker_size=marker_size)
        ax.set(title=title, xlabel=xlabel, ylabel=ylabel)
        return save_figure(fig, path, vector=vector)


def _scatter(fig, ax, x, y, c, *, cmap: str, vmin, vmax, clabel: str, marker_size: float, colorbar: bool = True):
    """Points on ``ax``: coloured by ``c`` (sorted so that high values are drawn last) with a colour bar, or in
    series colour 0. Returns the mappable (or None)."""
    import matplotlib

    if cmap not in matplotlib.colormaps:
        raise ValueError(f"unknown colour map {cmap!r}")
    ok = np.isfinite(x) & np.isfinite(y)
    if c is None:
        ax.scatter(x[ok], y[ok], s=marker_size, color=rgb(0), lw=0)
        return None
    finite = c[np.isfinite(c)]
    lo = vmin if vmin is not None else (float(finite.min()) if finite.size else 0.0)
    hi = vmax if vmax is not None else (float(finite.max()) if finite.size else 1.0)
    order = np.argsort(np.where(np.isfinite(c), c, -np.inf)[ok], kind="stable")
    sc = ax.scatter(x[ok][order], y[ok][order], s=marker_size, c=c[ok][order], cmap=cmap, vmin=lo,
                    vmax=hi if hi > lo else lo + 1.0, lw=0)
    if colorbar:
        fig.colorbar(sc, ax=ax, label=clabel)
    return sc
