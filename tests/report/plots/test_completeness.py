"""The plotting functions: what they draw matches the data given (positions, counts, scales, labels)."""

import numpy as np
import pytest
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from comest_bayes.bayes.spec import load_spec
from comest_bayes.report.plots import figure_png, new_axes, save_figure
from comest_bayes.report.plots.completeness import magnitude_comparison, ratio_curve, ratios_figure
from comest_bayes.report.plots.data import BinnedCurve, Cutout, DepthLine, MapPlane, PosteriorBand
from comest_bayes.report.plots.diagnostics import autocorrelation_plot, sampler_figure, selection_plot, trace_plot
from comest_bayes.report.plots.images import Markers, choose_region, cut, figure3, image_norm, mark, show_cutout
from comest_bayes.report.plots.maps import m50_map_figure, ratio_map, ratio_maps_figure
from comest_bayes.report.rundata import chain_samples
from comest_bayes.bayes.posterior import CompletenessPosterior


# ----------------------------------------------------------------------------- images

@pytest.mark.parametrize("shape, size, center, expected", [
    ((1000, 2000), 400, None, (800, 1200, 300, 700)),          # centred on (999.5, 499.5)
    ((1000, 2000), 400, (10.0, 990.0), (0, 400, 600, 1000)),   # clipped into the image at a corner
    ((300, 250), 400, None, (0, 250, 0, 300)),                 # larger than the image: the whole image
    ((1000, 1000), 100, (500.0, 200.0), (450, 550, 150, 250)),
])
def test_choose_region_centres_and_clips(shape, size, center, expected):
    assert choose_region(shape, size, center) == expected


def test_cut_keeps_the_offset_and_blanks_masked_pixels():
    image = np.arange(50 * 60, dtype=float).reshape(50, 60)
    mask = np.zeros(image.shape, bool)
    mask[12, 25] = True
    c = cut(image, (20, 40, 10, 30), mask)
    assert c.data.shape == (20, 20) and (c.x0, c.y0) == (20, 10)
    assert c.data[0, 0] == image[10, 20] and c.data[19, 19] == image[29, 39]
    assert np.isnan(c.data[2, 5]) and np.isfinite(c.data).sum() == 399
    # pixel centres at integers: the extent runs half a pixel beyond the first and last pixel
    assert c.extent == (19.5, 39.5, 9.5, 29.5)
    assert c.contains([19.6, 19.4, 39.4, 39.6], [10, 10, 29.4, 20]).tolist() == [True, False, True, False]


def test_image_norm_spans_the_noise_and_keeps_bright_cores_below_saturation():
    rng = np.random.default_rng(4)
    data = rng.normal(100.0, 5.0, (200, 200))
    data[100, 100] = 1e4
    norm = image_norm(data)
    # zscale of Gaussian noise spans a few sigma around the mean; the top is widened by 4x
    assert 70 < norm.vmin < 100 < norm.vmax < 220
    out = norm(np.array([norm.vmin, norm.vmax, 1e4, 100.0]))
    assert out[0] == pytest.approx(0.0) and out[1] == pytest.approx(1.0) and out[2] == pytest.approx(1.0)
    assert 0.0 < out[3] < 1.0
    with pytest.raises(ValueError, match="stretch"):
        image_norm(data, stretch="bogus")


def test_markers_outside_the_cutout_are_not_drawn_and_the_label_counts_the_inside_ones():
    c = Cutout(np.zeros((100, 100)), x0=200, y0=300)
    ax = show_cutout(c, norm=image_norm(np.random.default_rng(1).normal(size=(10, 10))))
    x = np.array([210.0, 250.0, 150.0, 299.0, 305.0])
    y = np.array([310.0, 399.0, 350.0, 301.0, 350.0])
    mark(ax, c, Markers(x, y, "recovered injections", "recovered"))
    coll = ax.collections[-1]
    np.testing.assert_array_equal(coll.get_offsets(), np.column_stack([x[[0, 1, 3]], y[[0, 1, 3]]]))
    assert coll.get_label() == "recovered injections (3)"
    assert ax.get_xlabel() == "x (pixel)" and ax.get_ylabel() == "y (pixel)"


def test_figure3_has_three_panels_on_one_scale_and_a_legend_per_marked_panel():
    rng = np.random.default_rng(2)
    region = (0, 80, 0, 60)
    obs = cut(rng.normal(10, 1, (60, 80)) + 50 * (np.hypot(*np.mgrid[-30:30, -40:40]) < 3), region)
    sfi = cut(rng.normal(10, 1, (60, 80)), region)
    sim = cut(rng.normal(10, 1, (60, 80)), region)
    m = lambda role, n: Markers(rng.uniform(0, 80, n), rng.uniform(0, 60, n), role, role)  # noqa: E731
    fig = figure3(obs, sfi, sim, detections=m("detection", 3), recovered=m("recovered", 4), missed=m("missed", 2),
                  false=m("false", 1))
    axes = fig.axes
    assert len(axes) == 3
    norms = [ax.images[0].norm for ax in axes]
    assert all(n.vmin == norms[0].vmin and n.vmax == norms[0].vmax for n in norms)
    assert [ax.get_title() for ax in axes][:2] == ["observed image", "source-free image"]
    labels = [t.get_text() for t in axes[2].get_legend().get_texts()]
    assert labels == ["recovered (4)", "missed (2)", "false (1)"]
    assert axes[0].get_legend() is not None and axes[1].get_legend() is None
    # the legends sit under the images, not over their markers
    renderer = _renderer(fig)
    for ax in (axes[0], axes[2]):
        box, panel = ax.get_legend().get_window_extent(renderer), ax.get_window_extent(renderer)
        assert box.y1 < panel.y0
    # without the observed image the first panel is blank and the scale is the source-free image's
    fig2 = figure3(None, sfi, sim, detections=m("detection", 3), recovered=m("recovered", 4),
                   missed=m("missed", 2), false=m("false", 1))
    assert "not available" in fig2.axes[0].get_title()
    assert fig2.axes[0].images[0].get_array().mask.all()


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


def test_binned_curve_reads_summary_nulls_as_nan():
    binned = {"mag_centers": [20.0, 21.0], "completeness": [1.0, None], "completeness_lower": [0.9, None],
              "completeness_upper": [1.0, None], "completeness_n": [10, 0], "confidence": 0.9, "interval": "jeffreys"}
    b = BinnedCurve.from_summary(binned, "completeness")
    assert np.isnan(b.ratio[1]) and b.n.tolist() == [10, 0] and b.confidence == 0.9


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


# ----------------------------------------------------------------------------- maps

def test_ratio_map_covers_the_image_pixels_of_its_cells():
    vals = np.array([[0.2, np.nan, 1.0], [0.5, 0.7, 0.9]])
    ax = ratio_map(MapPlane(vals, bin_pix=100.0, mag_lo=23.0, mag_hi=24.0))
    im = ax.images[0]
    assert im.get_extent() == [-0.5, 299.5, -0.5, 199.5]
    assert im.get_clim() == (0.0, 1.0)
    assert im.get_array().mask[0, 1] and not im.get_array().mask[0, 0]
    assert "23.00 < m < 24.00" in ax.get_title()


def test_ratio_maps_figure_one_column_per_plane_and_a_colorbar_per_row():
    planes = [MapPlane(np.full((2, 2), v), 50.0, 22.0 + i, 23.0 + i) for i, v in enumerate((0.9, 0.5, 0.1))]
    fig = ratio_maps_figure("point", planes, planes[:2], bin_arcmin=1.0)
    visible = [ax for ax in fig.axes if ax.get_visible() and ax.images]
    assert len(visible) == 5
    assert sum(1 for ax in fig.axes if ax.get_ylabel() in ("completeness", "purity")) == 2  # the colorbars
    fig2 = m50_map_figure("point", np.full((3, 3), 24.0), np.full((3, 3), 0.05), 64.0, model="logistic_depth")
    labels = {ax.get_ylabel() for ax in fig2.axes}
    assert "m50 (mag)" in labels and "standard deviation of m50 (mag)" in labels


# ----------------------------------------------------------------------------- diagnostics

TABLE = [
    {"name": "logistic", "nparams": 4, "delta_elpd": -2.3, "se_delta": 3.2, "chosen": True},
    {"name": "logistic_depth", "nparams": 5, "delta_elpd": 0.0, "se_delta": 0.0, "chosen": False},
]


def test_selection_plot_marks_the_chosen_model_at_its_delta():
    ax = selection_plot(TABLE)
    star = [ln for ln in ax.lines if ln.get_marker() == "*"][0]
    assert star.get_xdata()[0] == -2.3
    ticks = [t.get_text() for t in ax.get_yticklabels()]
    assert ticks == ["logistic (4 par.)", "logistic_depth (5 par.)"]
    lo, hi = ax.get_xlim()
    assert lo < -2.3 - 2 * 3.2 and hi > -2.3 + 2 * 3.2  # the 2-se bars are not cut


def test_autocorrelation_bars_are_the_taus_and_long_ones_are_flagged():
    ax = autocorrelation_plot(["m50_0", "log_w", "logit_A"], [10.0, 35.0, None], nsteps=1500)
    heights = [p.get_height() for p in ax.patches]
    assert heights == [10.0, 35.0, 0.0]
    limit = [ln for ln in ax.lines if ln.get_linestyle() == "--"][0]
    assert limit.get_ydata()[0] == pytest.approx(30.0)
    colors = [p.get_facecolor() for p in ax.patches]
    assert colors[0] != colors[1]  # 35 > 1500 / 50: drawn in the warning colour


def test_chain_samples_unflattens_step_major_draws():
    """Row s * W + w of the stored draws is walker w at kept step s (inference.PosteriorSamples)."""
    spec = load_spec("logistic")
    nsteps, nw = 30, 8
    s_idx, w_idx = np.divmod(np.arange(nsteps * nw), nw)
    meta = {"sigma_ref": 1.0, "hlr_ref": None, "image_shape": (100, 100), "mag_range": [20.0, 25.0]}
    probe = CompletenessPosterior(spec=spec, samples=np.zeros((1, 4)), names=["m50_0", "log_w", "logit_A",
                                                                              "logit_floor"], meta=meta)
    names = list(probe.model.names)
    samples = np.zeros((nsteps * nw, len(names)))
    samples[:, names.index("m50_0")] = 20.0 + s_idx + w_idx / 100.0   # encodes (step, walker)
    samples[:, names.index("log_w")] = np.log(0.2 + 0.001 * s_idx)
    post = CompletenessPosterior(spec=spec, samples=samples, names=names, meta=meta,
                                 diagnostics={"sampler": {"nwalkers": nw, "burn": 40}})
    chain = chain_samples(post)
    assert chain.names[:2] == ["m50_0", "w"] and chain.burn == 40
    assert chain.values.shape[:2] == (nsteps, nw)
    np.testing.assert_allclose(chain.values[:, :, 0], 20.0 + np.arange(nsteps)[:, None] + np.arange(nw) / 100.0)
    # constant parameters (A, floor: all samples at the same value) are not traced
    assert "A" not in chain.names
    # a walker count that does not divide the draws: no traces
    post.diagnostics = {"sampler": {"nwalkers": 7}}
    assert chain_samples(post) is None

    lines = trace_plot(chain)
    assert len(lines) == 2 and lines[0].lines[0].get_xdata()[0] == 40
    fig = sampler_figure("point completeness", {"names": names, "tau": [5, 6, 7, 8], "nsteps": 70,
                                                "acceptance_mean": 0.3, "converged": True}, chain)
    assert "converged" in fig._suptitle.get_text() and len(fig.axes) == 3


# ----------------------------------------------------------------------------- saving

def test_save_figure_writes_png_and_pdf(tmp_path):
    ax = ratio_curve(_binned())
    paths = save_figure(ax.figure, tmp_path / "sub" / "curve")
    assert [p.name for p in paths] == ["curve.png", "curve.pdf"]
    assert paths[0].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and paths[1].read_bytes()[:5] == b"%PDF-"
    png = figure_png(ax.figure, dpi=50)
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    assert isinstance(ax.figure, Figure) and not list(tmp_path.glob("sub/.tmp-*"))
