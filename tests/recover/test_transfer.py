"""Photometric transfer: kernels recovered from synthetic matched injections with known bias and scatter."""

import numpy as np
import pytest

from comest_bayes.errors import InputError
from comest_bayes.recover.transfer import PhotometricTransfer, measure_transfer, transfer_from_outcomes


def _sample(n, rng, bias=0.05, sigma=lambda m: 0.05 + 0.05 * (m - 20.0), lo=20.0, hi=25.0):
    true = rng.uniform(lo, hi, n)
    obs = true + bias + sigma(true) * rng.standard_normal(n)
    return true, obs


def test_bias_and_magnitude_dependent_scatter_are_recovered():
    rng = np.random.default_rng(4)
    true, obs = _sample(40000, rng)
    tr = measure_transfer(true, obs)
    q16, q50, q84 = tr.quantiles()
    for t in (21.0, 23.0, 24.5):
        j = int(np.argmin(np.abs(tr.nodes - t)))
        sig = 0.05 + 0.05 * (tr.nodes[j] - 20.0)
        # with ~2000 injections per window the median and half 16-84 width have standard errors of
        # ~1.25 sig / sqrt(2000) ~ 0.03 sig; the KDE bandwidth widens the width by ~ +1% (h ~ 0.15 sig),
        # and the 0.25-mag window mixes scatters differing by +-0.0125 mag: 10% tolerance on the width.
        assert q50[j] == pytest.approx(0.05, abs=0.1 * sig)
        assert 0.5 * (q84[j] - q16[j]) == pytest.approx(sig, rel=0.10)


def test_kernel_integrates_to_the_finite_fraction():
    rng = np.random.default_rng(5)
    true, obs = _sample(5000, rng)
    obs[rng.random(obs.size) < 0.1] = np.nan  # 10% detections with no finite magnitude
    tr = measure_transfer(true, obs)
    assert tr.meta["n_nonfinite"] == int(np.isnan(obs).sum())
    m_obs = np.arange(15.0, 30.0, 0.005)
    for t in (20.5, 22.0, 24.7):
        area = np.sum(tr.pdf(m_obs, t)) * 0.005
        # binomial sd of a 10% fraction from the ~500 injections of a window is ~0.013
        assert area == pytest.approx(0.9, abs=0.04)
        assert area == pytest.approx(float(tr.cdf_at(40.0, t)), abs=2e-3)
    # bin probabilities are differences of the cumulative
    edges = np.array([19.0, 21.0, 22.0, 26.0])
    b = tr.bin_matrix(edges, np.array([21.0, 22.0]))
    np.testing.assert_allclose(b.sum(axis=0), tr.cdf_at(26.0, np.array([21.0, 22.0])) - tr.cdf_at(19.0, np.array([21.0, 22.0])),
                               atol=1e-12)


def test_sparse_faint_end_widens_the_window_and_tails_are_kept():
    rng = np.random.default_rng(6)
    true = np.concatenate([rng.uniform(20, 24, 3000), rng.uniform(24, 25, 30)])
    obs = true + 0.03 * rng.standard_normal(true.size)
    obs[:150] -= 1.0  # 5% blended: measured 1 mag too bright
    tr = measure_transfer(true, obs, min_count=40)
    j = int(np.argmin(np.abs(tr.nodes - 24.8)))
    assert tr.n_eff[j] >= 15  # the window reached back for at least min_count injections (weighted)
    k = int(np.argmin(np.abs(tr.nodes - 22.0)))
    tail = tr.cdf_at(22.0 - 0.5, 22.0)
    assert tail == pytest.approx(0.05, abs=0.02)  # the blend tail carries its 5% (150 of 3000)
    assert tr.density[k].max() > 5.0  # and the core stays narrow


def test_save_load_roundtrip_and_outcome_table(tmp_path):
    from astropy.table import Table

    rng = np.random.default_rng(7)
    n = 2000
    t = Table({"mag": rng.uniform(20, 25, n), "detected": rng.random(n) < 0.7})
    t["det_mag_auto"] = np.where(t["detected"], t["mag"] + 0.1 * rng.standard_normal(n), np.nan)
    tr = transfer_from_outcomes(t)
    assert tr.meta["n_matched"] == int(t["detected"].sum()) and tr.meta["n_nonfinite"] == 0
    np.savez(tmp_path / "t.npz", **tr.to_arrays())
    with np.load(tmp_path / "t.npz") as z:
        back = PhotometricTransfer.from_arrays(z)
    np.testing.assert_array_equal(back.density, tr.density)
    assert back.meta == tr.meta


def test_no_detection_is_a_clear_error():
    with pytest.raises(InputError, match="no detected injection"):
        measure_transfer([], [])
    with pytest.raises(InputError, match="finite measured magnitude"):
        measure_transfer([20.0, 21.0], [np.nan, np.nan])
