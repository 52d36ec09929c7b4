"""The completeness and purity panels (comest_bayes.report.plots.completeness): what they draw matches the data
given (bins, bands, depth lines, counts), and no legend covers a plotted point.
"""

import numpy as np
import pytest
from matplotlib.axes import Axes

from comest_bayes.report.plots import new_axes
from comest_bayes.report.plots.completeness import magnitude_comparison, ratio_curve, ratios_figure
from comest_bayes.report.plots.data import BinnedCurve, DepthLine, PosteriorBand
from comest_bayes.report.plots.diagnostics import autocorrelation_plot, selection_plot


# ----------------------------------------------------------------------------- ratios

def _binned():
    centers = np.array([20.0, 21.0, 22.0, 23.0, 24.0])
    ratio = np.array([1.0, 0.95, 0.6, 0.1, np.nan])
    return BinnedCurve(centers=centers, ratio=ratio, lower=ratio - 0.05, upper=np.minimum(ratio + 0.03, 1.0),
                       n=np.array([40, 40, 40, 40, 0]), confidence=0.6827, interval="wilson")


def _band(mag):
    med = 1.0 / (1.0 + np.exp((mag - 22.3) / 0.3))
    return PosteriorBand(mag, med, med - 0.02, med + 0.02, med - 0.05, med + 0.05, label="posterior (logistic)")


def test_ratio_curve_draws_non_empty_bins_the_bands_and_the_depth_lines():
    b = _binned()
    mag = np.linspace(19.5, 24.5, 51)
    ax = ratio_curve(b, posterior=_band(mag), depth=[DepthLine(23.5, "5σ depth"), DepthLine(float("nan"), "none")])
    assert isinstance(ax, Axes)
    # the binned points: the empty last bin (n = 0) is left out
    points = [ln for ln in ax.lines if ln.get_marker() == "o"]
    assert len(points) == 1
    np.testing.assert_allclose(points[0].get_xdata(), b.centers[:4])
    np.testing.assert_allclose(points[0].get_ydata(), b.ratio[:4])
    # posterior median line on the grid; two bands (68% and 95%)
    med = [ln for ln in ax.lines if ln.get_label() == "posterior (logistic): median"]
    np.testing.assert_allclose(med[0].get_xdata(), mag)
    assert len(ax.collections) >= 2
    # one depth line at its magnitude, the NaN one is skipped
    vlines = [ln for ln in ax.lines if ln.get_linestyle() == "--"]
    assert len(vlines) == 1 and vlines[0].get_xdata()[0] == 23.5
    labels = ax.get_legend_handles_labels()[1]
    assert "5σ depth = 23.50" in labels and "binned (68% wilson interval)" in labels
    assert ax.get_xlabel() == "true magnitude (mag)" and ax.get_ylabel() == "completeness"
    ax2 = ratio_curve(b, quantity="purity")
    assert ax2.get_xlabel() == "measured magnitude (mag)" and ax2.get_ylabel() == "purity"


def test_ratio_curve_draws_into_the_given_axes():
    ax = new_axes()
    assert ratio_curve(_binned(), ax=ax) is ax


def test_ratios_figure_writes_the_reason_for_a_missing_posterior():
    fig = ratios_figure("point", _binned(), _binned(), completeness_posterior=_band(np.linspace(20, 24, 9)),
                        notes={"purity": "no posterior curve: 3 false detections"})
    # completeness and purity panels, each over its band-width panel
    assert len(fig.axes) == 4
    comp, comp_w, pur, pur_w = fig.axes
    assert comp.get_title() == "point: completeness" and pur.get_title() == "point: purity"
    # the reason is the title of the purity legend (outside the data), and the purity has no band panel
    assert "3 false detections" in pur_w.get_legend().get_title().get_text()
    assert comp_w.get_legend().get_title().get_text() == ""
    assert any("no posterior bands" in t.get_text() for t in pur_w.texts)


def _along(xy, n: int = 20):
    """Points every 1/n of the way along each segment of a polyline (error bars are two-vertex lines)."""
    if len(xy) < 2:
        return xy
    f = np.linspace(0.0, 1.0, n, endpoint=False)[:, None, None]
    return np.concatenate([(xy[:-1] + f * (xy[1:] - xy[:-1])).reshape(-1, 2), xy[-1:]])


def _data_points_px(ax):
    """Display coordinates of every plotted data point of ``ax``: line vertices and markers, error bars,
    filled bands, histogram cells (their centres) and bars (their corners)."""
    pts = []
    for ln in ax.lines:
        if ln.get_linestyle() in ("--", ":") and len(ln.get_xdata()) == 2:
            continue  # reference lines spanning the axes (depths, 0.5): not data
        xy = np.column_stack([ln.get_xdata(), ln.get_ydata()]).astype(float)
        pts.append(ax.transData.transform(_along(xy[np.isfinite(xy).all(axis=1)])))
    for coll in ax.collections:
        if hasattr(coll, "get_coordinates"):  # a QuadMesh (hist2d): centres of the filled cells
            c = coll.get_coordinates()
            centres = 0.25 * (c[:-1, :-1] + c[1:, :-1] + c[:-1, 1:] + c[1:, 1:]).reshape(-1, 2)
            filled = ~np.ma.getmaskarray(coll.get_array()).ravel()
            pts.append(ax.transData.transform(centres[filled]))
            continue
        for path in coll.get_paths():
            xy = path.vertices[np.isfinite(path.vertices).all(axis=1)]
            pts.append(coll.get_transform().transform(_along(xy)))
    for patch in ax.patches:
        e = patch.get_window_extent()
        pts.append(np.array([[e.x0, e.y0], [e.x1, e.y1], [e.x0, e.y1], [e.x1, e.y0]]))
    pts = [p for p in pts if len(p)]
    assert pts, "nothing plotted"
    return np.concatenate(pts)


def _renderer(fig):
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    canvas = FigureCanvasAgg(fig)
    canvas.draw()  # runs the constrained layout: positions are final
    return canvas.get_renderer()


def _assert_legend_covers_no_point(ax, fig, legend=None):
    renderer = _renderer(fig)
    legend = legend or ax.get_legend()
    box = legend.get_window_extent(renderer)
    px = _data_points_px(ax)
    inside = (px[:, 0] > box.x0) & (px[:, 0] < box.x1) & (px[:, 1] > box.y0) & (px[:, 1] < box.y1)
    assert not inside.any(), f"{int(inside.sum())} plotted points under the legend"
    return box


def test_legends_cover_no_plotted_point():
    # a dense panel: 40 bins across the whole axis, bands, two depth lines; a legend inside the axes
    # (matplotlib's loc="best" or "lower left") would sit on the plateau or the floor
    mag = np.linspace(18.0, 26.0, 161)
    centers = np.linspace(18.1, 25.9, 40)
    r = 1.0 / (1.0 + np.exp((centers - 22.3) / 0.3))
    # few injections per bin: intervals that reach across most of the axis, so every corner holds data
    lo, hi = np.clip(r - 0.7, 0, 1), np.clip(r + 0.7, 0, 1)
    lo[::3], hi[::3] = 0.0, 1.0  # bins with one or two injections: intervals over the whole axis
    b = BinnedCurve(centers, r, lo, hi, np.full(40, 3), 0.6827, "wilson")
    depth = [DepthLine(23.5, "5σ depth"), DepthLine(23.7, "5σ aperture depth")]
    ax = ratio_curve(b, posterior=_band(mag), depth=depth)
    _assert_legend_covers_no_point(ax, ax.figure)
    fig = ratios_figure("point", b, b, completeness_posterior=_band(mag), purity_posterior=_band(mag), depth=depth)
    for top, low in ((fig.axes[0], fig.axes[1]), (fig.axes[2], fig.axes[3])):
        box = _assert_legend_covers_no_point(top, fig, low.get_legend())
        _assert_legend_covers_no_point(low, fig)
        # and it sits below the band panel's x label, not on it
        label = low.xaxis.label.get_window_extent(_renderer(fig))
        assert box.y1 <= label.y0 + 1.0
    rng = np.random.default_rng(5)
    t = rng.uniform(19, 25, 4000)
    m = t + rng.normal(0, 0.1, t.size)
    m[:1500] = rng.uniform(19, 25, 1500)  # outliers anywhere in the panel
    ax = magnitude_comparison(t, m)
    _assert_legend_covers_no_point(ax, ax.figure)
    ax = selection_plot([{"name": f"m{i}", "nparams": i + 3, "delta_elpd": -3.0 * i, "se_delta": 1.0,
                          "chosen": i == 1} for i in range(5)])
    _assert_legend_covers_no_point(ax, ax.figure)
    ax = autocorrelation_plot(["a", "b", "c"], [30.0, 60.0, 90.0], 5000)
    _assert_legend_covers_no_point(ax, ax.figure)


def test_band_width_panel_and_caption_give_the_posterior_widths():
    from comest_bayes.report.plots.completeness import band_caption, band_width

    mag = np.linspace(20.0, 24.0, 81)
    med = 1.0 / (1.0 + np.exp((mag - 22.3) / 0.3))
    # a band 0.004 wide (95%) and 0.0016 (68%) at 22.3 mag, narrower elsewhere: invisible on a 0-1 axis
    half95 = 0.002 * np.exp(-0.5 * ((mag - 22.3) / 0.3) ** 2)
    band = PosteriorBand(mag, med, med - 0.4 * half95, med + 0.4 * half95, med - half95, med + half95,
                         label="posterior (logistic)")
    w = band_width(band)
    assert w["max95"] == pytest.approx(0.004) and w["max68"] == pytest.approx(0.0016)
    assert w["mag_max95"] == pytest.approx(22.3)
    text = band_caption(band)
    assert "widest 95% band 0.004 in f (at 22.30 mag)" in text and "widest 68% band 0.002" in text
    assert "narrower than 0.05, hardly visible at the 0-1 scale" in text
    wide = PosteriorBand(mag, med, med - 0.02, med + 0.02, med - 0.05, med + 0.05, label="p")
    assert "hardly visible" not in band_caption(wide) and "widest 95% band 0.100" in band_caption(wide)
    fig = ratios_figure("point", _binned(), None, completeness_posterior=band)
    low = fig.axes[1]
    # the panel draws hi95 - lo95 on its own scale: the top of its y axis is just above the widest band
    assert low.get_ylim()[1] == pytest.approx(1.15 * 0.004)
    line = low.lines[0]
    np.testing.assert_allclose(line.get_ydata(), 2 * half95, atol=1e-12)
    assert "widest 95%: 0.004 at 22.30 mag" in low.texts[0].get_text()


def test_magnitude_comparison_spans_the_whole_injected_range():
    # few faint injections are recovered: percentiles of the recovered pairs alone stop near 24
    rng = np.random.default_rng(6)
    t = rng.uniform(19.0, 24.0, 3000)
    m = t + rng.normal(0, 0.05, t.size)
    t = np.append(t, [25.4])
    m = np.append(m, [25.1])
    ax = magnitude_comparison(t, m, true_range=(19.16, 26.0))
    lo, hi = ax.get_xlim()
    assert lo <= 19.16 and hi >= 26.0
    assert ax.get_ylim() == ax.get_xlim()
    ax2 = magnitude_comparison(t, m)
    assert ax2.get_xlim()[1] < 26.0  # without the range, the axes end at the recovered pairs


def test_magnitude_comparison_counts_every_finite_pair_once():
    rng = np.random.default_rng(3)
    t = rng.uniform(19, 24, 3000)
    m = t + rng.normal(0, 0.05, t.size)
    m[:5] = np.nan
    ax = magnitude_comparison(t, m)
    mesh = ax.collections[0]
    assert np.nansum(mesh.get_array()) == pytest.approx(t.size - 5)
    one = [ln for ln in ax.lines if ln.get_label() == "1:1"][0]
    np.testing.assert_allclose(one.get_xdata(), one.get_ydata())
    # the running median follows the 1:1 relation within the scatter
    med = [ln for ln in ax.lines if ln.get_label() == "running median"][0]
    np.testing.assert_allclose(med.get_ydata(), med.get_xdata(), atol=0.03)
    empty = magnitude_comparison([], [])
    assert "no recovered" in empty.texts[0].get_text()
