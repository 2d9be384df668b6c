"""Line and scatter plots (matplotlib, the paper style of vnc_warp.plot): PNG and PDF written, data where it belongs.

Oracles: the stated image size, series colours found where the data put them (a rising line's pixels
rise to the right, a falling one's fall), a dashed marker where the stage boundary is, colour-map
end colours on the side of the points that carry them, the PDF's own header and embedded fonts.
"""

import re

import numpy as np
import pytest
from PIL import Image

from vnc_warp import plot
from vnc_warp.plot import SERIES_COLORS, line_plot, scatter_plot


def _pixels_near(img: np.ndarray, rgb, tol: int = 40):
    """(rows, cols) of pixels within ``tol`` (sum of channel differences) of ``rgb``."""
    d = np.abs(img.astype(int) - np.asarray(rgb, int)).sum(axis=2)
    return np.nonzero(d <= tol)


def test_line_plot_draws_series_where_the_data_are_and_writes_png_and_pdf(tmp_path):
    """Size as asked; the first series (rising) has pixels whose row falls as the column grows, the second
    (falling) the opposite; the PNG holds the returned picture and a PDF with embedded TrueType STIX fonts sits
    beside it."""
    x = np.linspace(0.0, 1.0, 50)
    path = tmp_path / "plots" / "line.png"
    img = line_plot({"rise": (x, x), "fall": (x, 1.0 - x)}, title=r"$\hat{H}$ against $\tau$", xlabel=r"$\tau$",
                    ylabel=r"$\hat{H}$", path=path, size=(640, 400))
    assert img.shape == (400, 640, 3) and img.dtype == np.uint8
    for k, sign in ((0, -1), (1, 1)):
        rows, cols = _pixels_near(img, SERIES_COLORS[k])
        keep = (cols > 0.15 * 640) & (cols < 0.6 * 640)  # away from the legend and the axis labels
        rows, cols = rows[keep], cols[keep]
        assert rows.size > 150
        assert sign * np.corrcoef(cols, rows)[0, 1] > 0.9
    back = np.asarray(Image.open(path).convert("RGB"))
    np.testing.assert_array_equal(back, img)
    pdf = path.with_suffix(".pdf").read_bytes()
    assert pdf.startswith(b"%PDF")
    fonts = set(re.findall(rb"/BaseFont /([A-Za-z0-9+-]+)", pdf))
    assert fonts and all(b"STIX" in f for f in fonts), fonts
    assert b"/FontFile2" in pdf  # TrueType embedded (pdf.fonttype 42)


def test_vector_format_choice(tmp_path):
    """vector='svg' writes an SVG beside the PNG, None writes the PNG alone; a path that is not a PNG and an
    unknown vector format are refused."""
    x = np.arange(5.0)
    line_plot({"a": (x, x)}, path=tmp_path / "a.png", vector="svg", size=(300, 200))
    assert (tmp_path / "a.svg").read_text().lstrip().startswith("<?xml")
    line_plot({"a": (x, x)}, path=tmp_path / "b.png", vector=None, size=(300, 200))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.png", "a.svg", "b.png"]
    with pytest.raises(ValueError, match="PNG"):
        line_plot({"a": (x, x)}, path=tmp_path / "c.jpg", size=(300, 200))
    with pytest.raises(ValueError, match="vector"):
        line_plot({"a": (x, x)}, path=tmp_path / "d.png", vector="eps", size=(300, 200))


def test_line_plot_vlines_spreads_and_gaps():
    """A dashed marker at the middle of x changes only a narrow, dashed column near the image middle (compared
    with the same plot without it); a spread draws a translucent band of the series colour around the line; NaN
    points break the line without error."""
    x = np.linspace(0.0, 10.0, 101)
    y = np.sin(x)
    y[40:45] = np.nan
    series = {"s": (x, y, np.full_like(x, 0.3))}
    img = line_plot(series, vlines=[5.0], size=(600, 360))
    ref = line_plot(series, size=(600, 360))
    rows, cols = np.nonzero(np.abs(img.astype(int) - ref.astype(int)).sum(axis=2) > 30)
    assert cols.max() - cols.min() <= 4
    assert 0.4 * 600 < cols.mean() < 0.65 * 600
    assert 0.3 * 360 < np.unique(rows).size < 0.9 * 360  # dashes: a good part of the height, with gaps
    band = (0.22 * np.asarray(SERIES_COLORS[0]) + 0.78 * 255).astype(int)
    assert _pixels_near(img, band, tol=24)[0].size > 2000


def test_log_axis_labels_plain_numbers():
    """A logarithmic axis over 2..16 carries plain labels (2, 5, 10), not powers of ten."""
    with plot.style():
        fig, ax = plot.figure((400, 300))
        ax.plot([2.0, 16.0], [1.0, 2.0])
        plot.log_axis(ax, "x")
        fig.canvas.draw()
        labels = [t.get_text() for t in ax.get_xticklabels() if 2.0 <= t.get_position()[0] <= 16.0]
    assert labels == ["2", "5", "10"], labels


def test_plots_reject_bad_input():
    """No series, mismatched lengths, no finite data, too small a size and an unknown colour map raise
    ValueError."""
    with pytest.raises(ValueError, match="no series"):
        line_plot({})
    with pytest.raises(ValueError, match="lengths"):
        line_plot({"a": ([0, 1, 2], [0, 1])})
    with pytest.raises(ValueError, match="finite"):
        line_plot({"a": ([np.nan], [np.nan])})
    with pytest.raises(ValueError, match="size"):
        line_plot({"a": ([0, 1], [0, 1])}, size=(50, 50))
    with pytest.raises(ValueError, match="one length"):
        scatter_plot([0, 1], [0])
    with pytest.raises(ValueError, match="colour map"):
        scatter_plot([0, 1], [0, 1], c=[0, 1], cmap="no-such-map")


def test_scatter_plot_colours_points_by_scalar(tmp_path):
    """With c = x, the low end colour of the map sits left of the high end colour among the points; size as
    asked; without c the points take series colour 0; PNG and PDF are written."""
    import matplotlib

    rng = np.random.default_rng(3)
    x, y = rng.random(300), rng.random(300)
    img = scatter_plot(x, y, c=x, cmap="viridis", clabel="$t$", title="latent", xlabel="PC1", ylabel="PC2",
                       path=tmp_path / "s.png", size=(700, 450))
    assert img.shape == (450, 700, 3)
    plot_area = img[:, : int(0.8 * 700)]  # the colour bar is on the right
    lo, hi = (np.rint(np.asarray(matplotlib.colormaps["viridis"]([0.0, 1.0]))[:, :3] * 255)).astype(int)
    cols_lo = _pixels_near(plot_area, lo)[1]
    cols_hi = _pixels_near(plot_area, hi)[1]
    assert cols_lo.size > 20 and cols_hi.size > 20
    assert cols_lo.mean() + 150 < cols_hi.mean()
    assert _pixels_near(img[:, int(0.82 * 700):], hi)[0].size > 20  # the colour bar
    plain = scatter_plot(x, y, size=(500, 300))
    assert plain.shape == (300, 500, 3)
    assert _pixels_near(plain, SERIES_COLORS[0], tol=30)[0].size > 300
    assert (tmp_path / "s.png").exists() and (tmp_path / "s.pdf").exists()
