"""Image cut-outs and the three-panel figure (comest_bayes.report.plots.images): regions, offsets, masked
pixels, the colour scale, and markers.
"""

import numpy as np
import pytest

from comest_bayes.report.plots.data import Cutout
from comest_bayes.report.plots.images import Markers, choose_region, cut, figure3, image_norm, mark, show_cutout


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


def _renderer(fig):
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    canvas = FigureCanvasAgg(fig)
    canvas.draw()  # runs the constrained layout: positions are final
    return canvas.get_renderer()
