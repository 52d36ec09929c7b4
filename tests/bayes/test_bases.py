"""The spatial bases of the smooth m50 field (comest_bayes.bayes.bases)."""

from __future__ import annotations

import numpy as np
import pytest

from comest_bayes.bayes.bases import smooth_basis


# --------------------------------------------------------------------------- smooth bases

def test_smooth_bases_have_zero_field_average():
    # Composite Gauss-Legendre, 4 nodes on each of 12 equal sub-intervals per axis: exact for the
    # polynomials and for the piecewise-cubic B-splines (whose knots, spacing 2 or 2/3, fall on
    # sub-interval edges), so the field averages must vanish to rounding.
    nodes, weights = np.polynomial.legendre.leggauss(4)
    edges = np.linspace(-1, 1, 13)
    half = 0.5 * (edges[1] - edges[0])
    x = (edges[:-1, None] + half * (nodes[None, :] + 1)).ravel()
    wx = np.tile(weights * half, 12)
    uu, vv = np.meshgrid(x, x)
    ww = np.outer(wx, wx).ravel() / 4.0  # mean over the square [-1, 1]^2
    assert ww.sum() == pytest.approx(1.0, rel=1e-14)
    for basis, order, ncol in (("poly", 2, 5), ("poly", 3, 9), ("bspline", 4, 15), ("bspline", 6, 35)):
        b = smooth_basis(uu.ravel(), vv.ravel(), basis, order)
        assert b.shape[1] == ncol
        np.testing.assert_allclose(ww @ b, 0.0, atol=1e-13)
        assert np.linalg.matrix_rank(b) == ncol  # no column is a combination of the others
    # the 1-D B-splines behind the tensor basis are a partition of unity
    from comest_bayes.bayes.bases import _bspline_1d
    np.testing.assert_allclose(_bspline_1d(np.linspace(-1, 1, 101), 6).sum(axis=1), 1.0, atol=1e-14)
