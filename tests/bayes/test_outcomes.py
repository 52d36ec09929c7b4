"""Covariates from outcome tables and the binomial compression (comest_bayes.bayes.outcomes): exactness,
cell means, agreement with the unbinned likelihood, bounded cell counts, NaN handling and clear errors.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
from astropy.table import Table

from comest_bayes.errors import ConfigError, InputError
from comest_bayes.bayes.model import CompletenessModel
from comest_bayes.bayes.outcomes import Covariates, compress, compress_for, covariates_from_outcomes, uncompressed
from comest_bayes.bayes.spec import ModelSpec
from outcome_truths import synthetic


# --------------------------------------------------------------------------- helpers


# --------------------------------------------------------------------------- compression

def test_compression_is_exact_for_shared_covariates():
    rng = np.random.default_rng(10)
    base = Covariates(rng.uniform(22, 26, 50), rng.normal(0, 0.2, 50), rng.uniform(-1, 1, 50),
                      rng.uniform(-1, 1, 50), np.zeros(50))
    rep = rng.integers(1, 30, 50)
    cov = base.take(np.repeat(np.arange(50), rep))
    y = rng.uniform(size=len(cov)) < 0.5
    comp = compress(cov, y)
    assert comp.ncells <= 100 and comp.ntotal == len(cov) == comp.meta["N"]
    np.testing.assert_array_equal(np.bincount(comp.index), comp.n)
    assert comp.k.sum() == y.sum()
    for spec in ("logistic_depth_smooth", ModelSpec(name="p", link="pritchet", spatial="depth")):
        mc, mu = CompletenessModel(spec, comp), CompletenessModel(spec, uncompressed(cov, y))
        theta = mu.initial() + 0.05
        assert mc.log_likelihood(theta) == pytest.approx(mu.log_likelihood(theta), rel=1e-12)


def test_compression_cells_hold_member_means():
    cov, y = synthetic(5000, 11)
    comp = compress(cov, y, dm=0.1, ddepth=0.1, nuv=4)
    idx = comp.index
    for c in (0, comp.ncells // 2, comp.ncells - 1):
        members = idx == c
        assert comp.n[c] == members.sum() and comp.k[c] == y[members].sum()
        assert comp.cov.m[c] == pytest.approx(cov.m[members].mean(), rel=1e-13)
        assert comp.cov.u[c] == pytest.approx(cov.u[members].mean(), abs=1e-13)
    assert np.all(np.abs(np.diff(cov.m[idx == 0])) < 0.1 + 1e-12) or comp.n[0] == 1


@pytest.fixture(scope="module")
def big():
    return synthetic(200_000, 12)


@pytest.mark.parametrize("spec", ["logistic", "logistic_depth"])
def test_compressed_likelihood_agrees_with_unbinned(big, spec):
    cov, y = big
    full = CompletenessModel(spec, uncompressed(cov, y))
    comp_data = compress_for(spec, cov, y)
    comp = CompletenessModel(spec, comp_data)
    theta_true = full.inverse_transform(dict(m50_0=24.0, w=0.2, A=0.95, floor=0.01, beta_depth=1.0))
    # The binning error is second order in the steps: about -1/2 sum g(1-g) (dm^2 + (beta - 1)^2
    # ddepth^2) / (12 w^2) over the ~2e4 outcomes in the transition, ~1.7 nat for the default
    # magnitude step 0.02 (the depth grid, laid along m - depth, adds little).  An offset that is
    # nearly the same at every theta does not move the posterior; required: below 3 nat at the truth
    # and several posterior sigmas away.
    tol = 3.0
    for shift in (0.0, 0.03):
        theta = theta_true + shift
        assert abs(comp.log_likelihood(theta) - full.log_likelihood(theta)) < tol
    # MAP-relevant: the gradient difference moves the optimum by H^-1 dg.  Cells hold both outcomes at
    # their members' mean covariates (cells do not depend on the outcomes), so the compressed likelihood
    # is that of slightly coarsened data: the MAP moves by a random amount whose sd is about the square
    # root of the fraction of information lost (for beta_depth ~ (0.1 / 0.18)^2 / 12 of the depth
    # spread: ~0.1 sigma) plus a second-order bias (log w by ~dm^2 / (8 pi^2 w^2) of itself).  Measured
    # at 200,000 injections: at most 0.035 (logistic) and 0.057 (logistic_depth, beta_depth) sigma.
    # Required: < 0.15 sigma, below the third of a sigma at which an offset would matter to intervals.
    _, g_full = full.value_and_grad(theta_true)
    _, g_comp = comp.value_and_grad(theta_true)
    hess = full.hessian(theta_true)
    cov_post = np.linalg.inv(-hess)
    shift = cov_post @ (g_comp - g_full)
    assert np.all(np.abs(shift) / np.sqrt(np.diag(cov_post)) < 0.15)
    if spec == "logistic":
        assert comp_data.ncells <= 351  # 7 mag / 0.02 = 350 magnitude bins at most


def test_cell_count_is_bounded_independently_of_n():
    # 7 mag range / dm = 0.02 -> at most 350 cells (fewer: the step grows to dm_max on the plateau
    # and the floor), whatever N.
    small = compress_for("logistic", *synthetic(10_000, 13))
    large = compress_for("logistic", *synthetic(1_000_000, 14))
    assert large.ncells <= 351 and small.ncells <= 351
    assert large.ntotal == 1_000_000
    # with depth resolved too, cells are bounded by the occupied (m - depth, depth) grid, not by N
    cov14 = synthetic(1_000_000, 14)[0]
    lo, hi = cov14.depth.min(), cov14.depth.max()
    span = (cov14.m - cov14.depth).max() - (cov14.m - cov14.depth).min()
    large_d = compress_for("logistic_depth", *synthetic(1_000_000, 14))
    assert large_d.ncells <= (math.ceil(span / 0.02) + 1) * (math.ceil((hi - lo) / 0.1) + 1)
    assert set(large_d.meta["binned"]) == {"m", "depth"}


def test_magnitude_step_grows_where_outcomes_do_not_mix():
    # Truth: m50 = 24 (+ depth), w = 0.2, plateau 0.95, floor 0.01, injected over 20-27 mag; the magnitude grid
    # alone (no depth resolved).  The step is dm sqrt(0.25 / p(1 - p)) of the local detected fraction p,
    # within [dm, dm_max]: ~0.046 mag on the plateau (p = 0.95), the full 0.1 on the floor (p = 0.01), and
    # dm = 0.02 through the transition.  Measured as the span of each cell's members, so a cell spans at
    # most its step.
    cov, y = synthetic(200_000, 21)
    fine = compress(cov, y, dm=0.02, ddepth=None, nuv=None, dsize=None)
    grown = compress(cov, y, dm=0.02, ddepth=None, nuv=None, dsize=None, dm_max=0.1)
    assert grown.meta["dm_max"] == 0.1 and grown.ntotal == fine.ntotal == 200_000
    assert grown.ncells < 0.5 * fine.ncells

    def spans(data, lo, hi):
        sel = (cov.m >= lo) & (cov.m < hi)
        idx, m = data.index[sel], cov.m[sel]
        return np.array([np.ptp(m[idx == c]) for c in np.unique(idx)])

    # the transition keeps the fine step (a cell across a coarse-bin edge takes a little of the next step)
    assert spans(grown, 23.9, 24.1).max() <= 1.05 * 0.02
    plateau = spans(grown, 20.5, 22.5)
    assert plateau.max() <= 0.1 + 1e-9 and np.median(plateau) > 0.035
    floor = spans(grown, 25.8, 26.8)
    assert floor.max() <= 0.1 + 1e-9 and np.median(floor) > 0.08
    with pytest.raises(InputError, match="dm_max"):
        compress(cov, y, dm_max=-1.0)


def test_compression_arguments_are_checked():
    cov, y = synthetic(100, 15)
    with pytest.raises(InputError, match="dm"):
        compress(cov, y, dm=None)
    with pytest.raises(InputError, match="nuv"):
        compress(cov, y, nuv=0)
    with pytest.raises(InputError, match="detected"):
        compress(cov, y[:-1])
    coarse = compress(cov, y, nuv=None)
    with pytest.raises(InputError, match="uv"):
        CompletenessModel("logistic_smooth", coarse)
    with pytest.raises(ConfigError, match="selection spec"):
        CompletenessModel("auto", coarse)


# --------------------------------------------------------------------------- covariates from the outcome table

def outcome_table(n=200, seed=16, shape=(100, 300)):
    rng = np.random.default_rng(seed)
    ny, nx = shape
    return Table({"x": rng.uniform(0, nx - 1, n), "y": rng.uniform(0, ny - 1, n), "mag": rng.uniform(20, 26, n),
                  "noise": rng.uniform(1.0, 3.0, n), "hlr_arcsec": rng.uniform(0.2, 1.0, n),
                  "detected": rng.uniform(size=n) < 0.5})


def test_covariates_from_outcomes_known_values():
    t = outcome_table()
    t["x"][:2] = [0.0, 299.0]
    t["y"][:2] = [99.0, 0.0]
    cov, det, meta = covariates_from_outcomes(t, image_shape=(100, 300), sigma_ref=2.0, hlr_ref=0.5)
    np.testing.assert_allclose(cov.u[:2], [-1.0, 1.0])
    np.testing.assert_allclose(cov.v[:2], [1.0, -1.0])
    np.testing.assert_allclose(cov.depth, -2.5 * np.log10(np.asarray(t["noise"]) / 2.0))
    np.testing.assert_allclose(cov.size, np.log10(np.asarray(t["hlr_arcsec"]) / 0.5))
    np.testing.assert_array_equal(det, np.asarray(t["detected"]))
    assert meta["N"] == 200 and meta["image_shape"] == (100, 300)
    assert set(meta["available"]) == {"m", "uv", "depth", "size"}
    _, _, meta2 = covariates_from_outcomes(t, image_shape=(100, 300))
    assert meta2["sigma_ref"] == pytest.approx(np.median(t["noise"]))


def test_nan_positions_and_magnitudes_are_dropped_with_a_count():
    t = outcome_table()
    t["x"][3] = np.nan
    t["mag"][[5, 7]] = np.nan
    with pytest.warns(UserWarning, match="dropped 3 of 200"):
        cov, det, meta = covariates_from_outcomes(t, image_shape=(100, 300))
    assert len(cov) == 197 and det.shape == (197,)
    np.testing.assert_array_equal(meta["dropped_rows"], [3, 5, 7])
    t["mag"][:] = np.nan
    with pytest.raises(InputError, match="all 200 rows"):
        covariates_from_outcomes(t, image_shape=(100, 300))


def test_nan_noise_gives_reference_depth_with_a_warning():
    t = outcome_table()
    t["noise"][[1, 2]] = [np.nan, 0.0]
    with pytest.warns(UserWarning, match="2 of 200 outcome rows have a non-finite or non-positive noise"):
        cov, _, _ = covariates_from_outcomes(t, image_shape=(100, 300))
    assert cov.depth[1] == 0.0 and cov.depth[2] == 0.0
    assert np.all(np.isfinite(cov.depth))


def test_point_sources_get_size_zero_without_nan():
    t = outcome_table()
    t["hlr_arcsec"] = np.nan
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        cov, _, meta = covariates_from_outcomes(t, image_shape=(100, 300))
    assert np.all(cov.size == 0) and "size" not in meta["available"]
    # the warning must say what is wrong and what follows, not merely mention the size
    with pytest.warns(UserWarning, match=r"uses the size \(no half-light radii\); that covariate is 0 for every "
                                         r"injection, so its slope is constrained by its prior only"):
        CompletenessModel("logistic_depth_size", compress_for("logistic_depth_size", cov, _, meta=meta))


def test_outcome_table_errors_are_clear():
    t = outcome_table()
    with pytest.raises(InputError, match="outside the image"):
        covariates_from_outcomes(t, image_shape=(300, 100))  # transposed
    with pytest.raises(InputError, match="image_shape"):
        covariates_from_outcomes(t, image_shape=None)
    with pytest.raises(InputError, match="no column 'detected'"):
        covariates_from_outcomes(Table({"mag": [1.0]}), image_shape=None)
    bad = outcome_table()
    bad["detected"] = np.where(bad["detected"], 2, 0)
    with pytest.raises(InputError, match="0/1"):
        covariates_from_outcomes(bad, image_shape=(100, 300))
    with pytest.raises(InputError, match="non-finite"):
        Covariates.make([1.0, np.nan])
    # purity: measured magnitude, real-or-false outcome, no positions needed
    pur = Table({"det_mag_auto": [20.0, 21.0, 25.0], "real": [1, 1, 0]})
    cov, real, meta = covariates_from_outcomes(pur, image_shape=None, mag_column="det_mag_auto",
                                               outcome_column="real")
    np.testing.assert_array_equal(real, [True, True, False])
    assert meta["available"] == ("m",)


def test_the_one_covariate_transform_of_positions_and_noise():
    from comest_bayes.bayes.outcomes import depth_covariate, image_coordinate

    # first and last pixel centres map to -1 and +1; a one-pixel axis does not divide by zero
    np.testing.assert_allclose(image_coordinate([0.0, 49.5, 99.0], 100), [-1.0, 0.0, 1.0])
    assert image_coordinate(0.0, 1) == -1.0
    # half the reference noise is 2.5 log10(2) = 0.753 mag deeper
    np.testing.assert_allclose(depth_covariate([1.0, 2.0, 4.0], 2.0), [2.5 * np.log10(2.0), 0.0, -2.5 * np.log10(2.0)])


def test_column_floats_reads_masked_entries_as_missing_not_as_their_fill():
    from comest_bayes.bayes.outcomes import column_floats
    from comest_bayes.errors import InputError

    col = np.ma.MaskedArray([24.0, 0.0, 25.5, 99.0], mask=[False, True, False, True])
    got = column_floats(col, "mag")
    assert got[0] == 24.0 and got[2] == 25.5 and np.isnan(got[1]) and np.isnan(got[3])
    np.testing.assert_array_equal(column_floats(np.array([1, 2], np.int16)), [1.0, 2.0])
    with pytest.raises(InputError, match=r"cat: column 'mag' must hold numbers, got dtype <U2 \(e.g. \['ab'"):
        column_floats(np.array(["ab", "cd"]), "mag", "cat")
