"""The plain data records the figures draw (comest_bayes.report.plots.data)."""

import numpy as np

from comest_bayes.report.plots.data import BinnedCurve


def test_binned_curve_reads_summary_nulls_as_nan():
    binned = {"mag_centers": [20.0, 21.0], "completeness": [1.0, None], "completeness_lower": [0.9, None],
              "completeness_upper": [1.0, None], "completeness_n": [10, 0], "confidence": 0.9, "interval": "jeffreys"}
    b = BinnedCurve.from_summary(binned, "completeness")
    assert np.isnan(b.ratio[1]) and b.n.tolist() == [10, 0] and b.confidence == 0.9
