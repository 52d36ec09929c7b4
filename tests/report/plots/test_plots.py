"""The shared figure helpers of comest_bayes.report.plots (its __init__): saving PNG and PDF atomically, PNG bytes."""

import numpy as np
from matplotlib.figure import Figure

from comest_bayes.report.plots import figure_png, save_figure
from comest_bayes.report.plots.completeness import ratio_curve
from comest_bayes.report.plots.data import BinnedCurve


# ----------------------------------------------------------------------------- ratios

def _binned():
    centers = np.array([20.0, 21.0, 22.0, 23.0, 24.0])
    ratio = np.array([1.0, 0.95, 0.6, 0.1, np.nan])
    return BinnedCurve(centers=centers, ratio=ratio, lower=ratio - 0.05, upper=np.minimum(ratio + 0.03, 1.0),
                       n=np.array([40, 40, 40, 40, 0]), confidence=0.6827, interval="wilson")


# ----------------------------------------------------------------------------- saving

def test_save_figure_writes_png_and_pdf(tmp_path):
    ax = ratio_curve(_binned())
    paths = save_figure(ax.figure, tmp_path / "sub" / "curve")
    assert [p.name for p in paths] == ["curve.png", "curve.pdf"]
    assert paths[0].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and paths[1].read_bytes()[:5] == b"%PDF-"
    png = figure_png(ax.figure, dpi=50)
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    assert isinstance(ax.figure, Figure) and not list(tmp_path.glob("sub/.tmp-*"))
