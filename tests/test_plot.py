"""Line and scatter plots: the Pillow path (forced, matplotlib may be absent) and matplotlib when present.

Oracles: the stated image size, series colours found where the data put them (a rising line's pixels
rise to the right, a falling one's fall), dashed markers where the stage boundary is, and colour-map
end colours on the side of the points that carry them.
"""

import importlib.util

import numpy as np
import pytest
from PIL import Image

from vnc_warp.plot import SERIES_COLORS, line_plot, scatter_plot
from vnc_warp.render import colormap


def _pixels_near(img: np.ndarray, rgb, tol: int = 40):
    """(rows, cols) of pixels within ``tol`` (sum of channel differences) of ``rgb``."""
    d = np.abs(img.astype(int) - np.asarray(rgb, int)).sum(axis=2)
    return np.nonzero(d <= tol)


def test_line_plot_pil_draws_series_where_the_data_are(tmp_path):
    """Size as asked; the first series (rising) has pixels whose row falls as the column grows, the
    second (falling) the opposite; the legend, ticks and text leave dark pixels; the PNG is written."""
    x = np.linspace(0.0, 1.0, 50)
    path = tmp_path / "plots" / "line.png"
    img = line_plot({"rise": (x, x), "fall": (x, 1.0 - x)}, title="T", xlabel="step", ylabel="value",
                    path=path, size=(640, 400), backend="pil")
    assert img.shape == (400, 640, 3) and img.dtype == np.uint8
    for k, sign in ((0, -1), (1, 1)):
        rows, cols = _pixels_near(img, SERIES_COLORS[k])
        below_legend = rows > 0.3 * 400
        rows, cols = rows[below_legend], cols[below_legend]
        assert rows.size > 150
        assert sign * np.corrcoef(cols, rows)[0, 1] > 0.9
    assert (img.sum(axis=2) < 150).sum() > 500  # frame, ticks and labels in black
    back = np.asarray(Image.open(path).convert("RGB"))
    np.testing.assert_array_equal(back, img)


def test_line_plot_pil_vlines_spreads_and_gaps():
    """A dashed marker at the middle of x changes only a narrow, dashed column near the image middle
    (compared with the same plot without it); a spread draws a translucent band of the series colour
    around the line; NaN points break the line without error."""
    x = np.linspace(0.0, 10.0, 101)
    y = np.sin(x)
    y[40:45] = np.nan
    series = {"s": (x, y, np.full_like(x, 0.3))}
    img = line_plot(series, vlines=[5.0], size=(600, 360), backend="pil")
    ref = line_plot(series, size=(600, 360), backend="pil")
    rows, cols = np.nonzero(np.abs(img.astype(int) - ref.astype(int)).sum(axis=2) > 30)
    assert cols.max() - cols.min() <= 3
    assert 0.4 * 600 < cols.mean() < 0.65 * 600
    assert 0.3 * 360 < np.unique(rows).size < 0.8 * 360  # dashes: a good part of the height, with gaps
    band = (0.25 * np.asarray(SERIES_COLORS[0]) + 0.75 * 255).astype(int)
    assert _pixels_near(img, band, tol=24)[0].size > 2000


def test_line_plot_rejects_bad_input():
    """No series, mismatched lengths, no finite data, too small a size and an unknown backend raise
    ValueError; forcing matplotlib where it is absent raises ImportError."""
    with pytest.raises(ValueError, match="no series"):
        line_plot({}, backend="pil")
    with pytest.raises(ValueError, match="lengths"):
        line_plot({"a": ([0, 1, 2], [0, 1])}, backend="pil")
    with pytest.raises(ValueError, match="finite"):
        line_plot({"a": ([np.nan], [np.nan])}, backend="pil")
    with pytest.raises(ValueError, match="size"):
        line_plot({"a": ([0, 1], [0, 1])}, size=(50, 50), backend="pil")
    with pytest.raises(ValueError, match="backend"):
        line_plot({"a": ([0, 1], [0, 1])}, backend="svg")
    if importlib.util.find_spec("matplotlib") is None:
        with pytest.raises(ImportError, match="matplotlib"):
            line_plot({"a": ([0, 1], [0, 1])}, backend="matplotlib")


def test_scatter_plot_pil_colours_points_by_scalar(tmp_path):
    """With c = x, the low end colour of the map sits left of the high end colour among the points
    (the colour bar on the right is excluded); size as asked; without c the points take series colour 0."""
    rng = np.random.default_rng(3)
    x, y = rng.random(300), rng.random(300)
    img = scatter_plot(x, y, c=x, cmap="viridis", clabel="t", title="latent", xlabel="PC1", ylabel="PC2",
                       path=tmp_path / "s.png", size=(700, 450), backend="pil")
    assert img.shape == (450, 700, 3)
    plot_area = img[:, : int(0.87 * 700)]  # the colour bar starts past 88 % of the width
    lo, hi = (np.rint(colormap([0.0, 1.0], "viridis", 0.0, 1.0) * 255)).astype(int)
    cols_lo = _pixels_near(plot_area, lo)[1]
    cols_hi = _pixels_near(plot_area, hi)[1]
    assert cols_lo.size > 20 and cols_hi.size > 20
    assert cols_lo.mean() + 150 < cols_hi.mean()
    assert _pixels_near(img[:, int(0.88 * 700):], hi)[0].size > 20  # the colour bar
    plain = scatter_plot(x, y, size=(500, 300), backend="pil")
    assert plain.shape == (300, 500, 3)
    assert _pixels_near(plain, SERIES_COLORS[0], tol=30)[0].size > 300
    assert (tmp_path / "s.png").exists()
    with pytest.raises(ValueError, match="one length"):
        scatter_plot(x, y[:10], backend="pil")


def test_auto_backend_gives_the_stated_size():
    """backend='auto' (matplotlib if present, Pillow otherwise) returns a non-blank image of the stated size."""
    x = np.arange(10.0)
    img = line_plot({"a": (x, x**2)}, title="auto", size=(500, 320))
    assert img.shape == (320, 500, 3) and img.std() > 5.0
    sc = scatter_plot(x, x, c=x, size=(500, 320))
    assert sc.shape == (320, 500, 3) and sc.std() > 5.0


def test_matplotlib_backend_when_present():
    """With matplotlib installed, the forced matplotlib path gives the stated size and draws series colour 0."""
    pytest.importorskip("matplotlib")
    x = np.linspace(0.0, 1.0, 20)
    img = line_plot({"a": (x, x, 0.1 + 0 * x)}, vlines=[0.5], size=(640, 400), backend="matplotlib")
    assert img.shape == (400, 640, 3)
    assert _pixels_near(img, SERIES_COLORS[0], tol=30)[0].size > 100
    sc = scatter_plot(x, x, c=x, size=(640, 400), backend="matplotlib")
    assert sc.shape == (400, 640, 3) and sc.std() > 5.0
