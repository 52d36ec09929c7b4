"""Sampler and model-selection diagnostics (comest_bayes.report.plots.diagnostics): the chosen model at its
delta, autocorrelation bars and their flags.
"""

import pytest

from comest_bayes.report.plots.diagnostics import autocorrelation_plot, selection_plot


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
