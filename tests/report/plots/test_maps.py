"""Ratio and m50 maps (comest_bayes.report.plots.maps): cells cover their image pixels, one column per plane."""

import numpy as np

from comest_bayes.report.plots.data import MapPlane
from comest_bayes.report.plots.maps import m50_map_figure, ratio_map, ratio_maps_figure


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
