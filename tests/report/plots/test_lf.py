"""The luminosity-function figures (comest_bayes.report.plots.lf): the counts panel draws the catalog counts,
the forward-model median and the fitted phi of the result it is given; the corner plot has one panel per
pair of parameters with the posterior percentiles in its titles."""

import numpy as np
import pytest

from comest_bayes.lf.result import LFResult
from comest_bayes.report.plots.lf import corner_figure, counts_figure


def _result(seed=0) -> LFResult:
    rng = np.random.default_rng(seed)
    grid = np.linspace(18.0, 25.0, 15)
    phi = 10 ** (0.3 * (grid - 20.0)) * 100.0
    edges = np.arange(20.0, 23.01, 0.5)
    observed = np.array([12, 20, 31, 45, 52, 40])
    expected = np.array([observed * f for f in (0.7, 0.85, 1.0, 1.15, 1.3)], float)
    samples = np.column_stack([rng.normal(4.0, 0.05, 3000), rng.normal(0.3, 0.02, 3000)])
    return LFResult(name="main", kind="point", mode="fixed", spec={"name": "powerlaw"}, names=["log_n", "slope"],
                    samples=samples, comp_samples=None, grid=grid, phi_bands=np.array([phi * f for f in
                                                                                      (0.8, 0.9, 1.0, 1.1, 1.2)]),
                    obs_edges=edges, observed=observed, expected_bands=expected, expected_draws=expected[1:4],
                    fbar_median=np.linspace(1.0, 0.1, 15), area_deg2=0.01, mag_range=(20.0, 23.0),
                    n_objects=int(observed.sum()))


def test_counts_figure_draws_the_catalog_the_model_and_phi():
    res = _result()
    fig = counts_figure(res, truth_phi=lambda m: 10 ** (0.3 * (m - 20.0)) * 100.0)
    top, bottom = fig.axes[0], fig.axes[1]
    centres = 0.5 * (res.obs_edges[:-1] + res.obs_edges[1:])
    # the catalog points: at the bin centres, the observed counts
    points = [line for line in top.lines if line.get_marker() == "o"]
    assert len(points) == 1
    np.testing.assert_allclose(points[0].get_xdata(), centres)
    np.testing.assert_allclose(points[0].get_ydata(), res.observed)
    # the forward-model median as a step line, the fitted phi median and the truth below
    steps = [line for line in top.lines if line.get_drawstyle() == "steps-mid"]
    np.testing.assert_allclose(steps[0].get_ydata(), res.expected_bands[2])
    phi_lines = [line for line in bottom.lines if line.get_linestyle() == "-"]
    np.testing.assert_allclose(phi_lines[0].get_ydata(), res.phi_bands[2])
    truth = [line for line in bottom.lines if line.get_linestyle() == "--"]
    np.testing.assert_allclose(truth[0].get_ydata(), res.phi_bands[2], rtol=1e-12)
    assert top.get_yscale() == "log" and bottom.get_yscale() == "log"
    assert "point powerlaw, mode fixed" in top.get_title()
    # the completeness on the twin axis, and one legend for all, naming the catalog size
    twin = fig.axes[2]
    np.testing.assert_allclose(twin.lines[0].get_ydata(), res.fbar_median)
    labels = [t.get_text() for legend in fig.legends + [a.get_legend() for a in fig.axes if a.get_legend()]
              for t in legend.get_texts()]
    assert f"catalog ({res.n_objects})" in labels and "truth" in labels


def test_corner_figure_has_a_lower_triangle_and_the_percentiles_in_the_titles():
    res = _result()
    fig = corner_figure(res, truths=[4.0, 0.3])
    visible = [a for a in fig.axes if a.get_visible()]
    assert len(fig.axes) == 4 and len(visible) == 3  # 2 x 2, the upper right hidden
    q = np.percentile(res.samples[:, 0], [16, 50, 84])
    assert visible[0].get_title().startswith(f"log_n = {q[1]:.3g}")
    diag_lines = [line.get_xdata()[0] for line in visible[0].lines]
    for v in q:
        assert any(x == pytest.approx(v) for x in diag_lines)
    assert any(x == pytest.approx(4.0) for x in diag_lines)  # the truth
    assert visible[1].get_xlabel() == "log_n" and visible[1].get_ylabel() == "slope"
