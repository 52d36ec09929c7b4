"""Tests of comest_bayes.ratios.binned: binned completeness, purity, detection rate, maps and map WCS."""

import json
import warnings

import numpy as np
import pytest
from astropy.stats import binom_conf_interval
from astropy.wcs import WCS, Sip
from scipy.special import ndtri
from scipy.stats import binom

from comest_bayes.errors import InputError
from comest_bayes.ratios.binned import (binned_ratio, completeness, completeness_map, default_map_mag_edges, transition_map_mag_edges, detection_rate, magnitude_at, magnitude_at_sd, magnitude_edges, map_bin_pixels, map_wcs, purity, purity_map, ratio_maps)


def _wilson(k, n, confidence):
    """Wilson score interval written out (Wilson 1927), independent of astropy."""
    z = ndtri(0.5 + confidence / 2)
    p = k / n
    centre = (p + z**2 / (2 * n)) / (1 + z**2 / n)
    half = z * np.sqrt(p * (1 - p) / n + z**2 / (4 * n**2)) / (1 + z**2 / n)
    return centre - half, centre + half


def test_all_matched_none_matched_and_30_of_100():
    edges = np.array([18.0, 19.0, 20.0, 21.0])
    mags = np.r_[np.full(40, 18.5), np.full(25, 19.5), np.full(100, 20.5)]
    matched = np.r_[np.ones(40, bool), np.zeros(25, bool), np.arange(100) < 30]
    res = completeness(mags, matched, edges)
    assert res.n.tolist() == [40, 25, 100]
    assert res.k.tolist() == [40, 0, 30]
    assert res.ratio.tolist() == [1.0, 0.0, 0.3]
    # all bright injections found: completeness 1, interval containing 1
    assert res.lower[0] < 1.0 and res.upper[0] == pytest.approx(1.0, abs=1e-12)
    # none found: 0, interval containing 0
    assert res.lower[1] == pytest.approx(0.0, abs=1e-12) and res.upper[1] > 0.0
    # 30/100: Wilson interval equal to astropy's and to the closed form
    ref = binom_conf_interval(30, 100, confidence_level=0.6827, interval="wilson")
    assert res.lower[2] == pytest.approx(ref[0], rel=1e-12)
    assert res.upper[2] == pytest.approx(ref[1], rel=1e-12)
    lo, hi = _wilson(30, 100, 0.6827)
    assert res.lower[2] == pytest.approx(lo, rel=1e-9) and res.upper[2] == pytest.approx(hi, rel=1e-9)
    # the other methods are passed through
    jef = completeness(mags, matched, edges, interval="jeffreys", confidence=0.9)
    ref = binom_conf_interval(30, 100, confidence_level=0.9, interval="jeffreys")
    assert (jef.lower[2], jef.upper[2]) == pytest.approx(tuple(ref), rel=1e-12)


def test_masked_injections_are_left_out():
    mags = np.full(10, 22.1)
    matched = np.arange(10) < 4
    masked = np.arange(10) >= 8  # two unmatched ones fell on masked pixels
    res = completeness(mags, matched, [22.0, 22.2], masked=masked)
    assert res.n.tolist() == [8] and res.k.tolist() == [4] and res.ratio[0] == 0.5


def test_empty_bins_are_nan_without_warnings():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        res = completeness([20.1, 20.3], [True, False], [20.0, 20.5, 21.0, 21.5])
        dr = detection_rate([20.2], [20.1, 20.3], [20.0, 20.5, 21.0, 21.5])
        maps = ratio_maps([1.0], [1.0], [20.2], [True], image_shape=(10, 20), bin_pix=5, mag_edges=[20, 21])
    assert res.n.tolist() == [2, 0, 0]
    assert np.isnan(res.ratio[1:]).all() and np.isnan(res.lower[1:]).all() and np.isnan(res.upper[1:]).all()
    assert np.isnan(dr.ratio[1:]).all()
    assert maps.n.sum() == 1 and np.isnan(maps.ratio).sum() == maps.ratio.size - 1


def test_binning_convention():
    edges = [0.0, 1.0, 2.0]
    # 2.0 (the last edge) is in the last bin; 1.0 in the second; outside and NaN in none
    res = binned_ratio([0.0, 1.0, 2.0, -0.1, 2.1, np.nan], np.ones(6, bool), edges)
    assert res.n.tolist() == [1, 2]
    np.testing.assert_allclose(res.centers, [0.5, 1.5])


def test_purity_excludes_kept_and_counts_false():
    # bin 1: 10 matched + 5 false; bin 2: 3 matched + 0 false + 4 on kept real sources
    det_mag = np.r_[np.full(15, 21.5), np.full(7, 22.5)]
    matched = np.r_[np.ones(10, bool), np.zeros(5, bool), np.ones(3, bool), np.zeros(4, bool)]
    kept = np.r_[np.zeros(18, bool), np.ones(4, bool)]
    res = purity(det_mag, matched, [21.0, 22.0, 23.0], excluded=kept)
    assert res.n.tolist() == [15, 3]
    assert res.k.tolist() == [10, 3]
    np.testing.assert_allclose(res.ratio, [10 / 15, 1.0])
    assert res.quantity == "mag_meas"


def test_detection_rate_can_exceed_one():
    edges = [20.0, 21.0, 22.0]
    truth = np.r_[np.full(10, 20.5), np.full(4, 21.5)]
    det = np.r_[np.full(8, 20.5), np.full(9, 21.5), [21.6]]
    det_excluded = np.r_[np.zeros(17, bool), [True]]
    res = detection_rate(det, truth, edges, det_excluded=det_excluded)
    assert res.k.tolist() == [8, 9] and res.n.tolist() == [10, 4]
    np.testing.assert_allclose(res.ratio, [0.8, 2.25])
    assert np.all(res.lower < res.ratio) and np.all(res.ratio < res.upper)
    assert res.interval == "poisson"


def test_to_dict_and_to_table():
    res = completeness([20.1, 20.2], [True, False], [20.0, 20.5, 21.0])
    d = res.to_dict()
    text = json.dumps(d, allow_nan=False)  # NaN would make this raise
    assert json.loads(text)["ratio"] == [0.5, None]
    assert d["n"] == [2, 0] and d["name"] == "completeness"
    t = res.to_table()
    assert t.colnames == ["mag_lo", "mag_hi", "mag_center", "n", "k", "ratio", "lower", "upper"]
    assert str(t["mag_center"].unit) == "mag"
    assert t["k"][0] == 1 and t.meta["interval"] == "wilson"


def test_input_errors():
    with pytest.raises(InputError, match="strictly increasing"):
        completeness([20.0], [True], [21.0, 20.0])
    with pytest.raises(InputError, match="interval"):
        completeness([20.0], [True], [19.0, 21.0], interval="wald-ish")
    with pytest.raises(InputError, match="boolean"):
        completeness([20.0], [1], [19.0, 21.0])
    with pytest.raises(InputError, match="confidence"):
        purity([20.0], [True], [19.0, 21.0], confidence=68.0)


def test_wilson_coverage_by_simulation():
    # 2000 independent bins of n = 200 Bernoulli(p = 0.7) trials (fixed seed).
    # The exact coverage of the discrete Wilson interval at n = 200 is computed
    # from the binomial pmf (0.684, within 0.01 of the nominal 0.6827).  The
    # simulated coverage is a binomial proportion over 2000 bins with sd
    # sqrt(c (1 - c) / 2000) ~ 0.010; we allow 3.5 sd.
    rng = np.random.default_rng(2016)
    p, n, nbins, conf = 0.7, 200, 2000, 0.6827
    mags = np.repeat(np.arange(nbins) + 0.5, n)
    matched = rng.uniform(size=mags.size) < p
    res = completeness(mags, matched, np.arange(nbins + 1.0), confidence=conf)
    assert np.all(res.n == n)
    covered = (res.lower <= p) & (p <= res.upper)
    mc = covered.mean()
    k = np.arange(n + 1)
    lo, hi = binom_conf_interval(k, np.full(n + 1, n), confidence_level=conf, interval="wilson")
    exact = binom.pmf(k, n, p)[(lo <= p) & (p <= hi)].sum()
    assert abs(exact - conf) < 0.01
    sd = np.sqrt(exact * (1 - exact) / nbins)
    assert abs(mc - exact) < 3.5 * sd


def test_magnitude_edges_and_m50():
    e = magnitude_edges(20.0, 21.0, 0.2)
    np.testing.assert_allclose(e, [20.0, 20.2, 20.4, 20.6, 20.8, 21.0])
    assert magnitude_edges(20.0, 21.05, 0.2)[-1] == pytest.approx(21.2)
    # a known falling completeness: 1.0, 0.8, 0.4, 0.0 at centres 20.5..23.5 -> 50% at 22.25
    mags = np.repeat([20.5, 21.5, 22.5, 23.5], 10)
    matched = np.r_[np.ones(10, bool), np.arange(10) < 8, np.arange(10) < 4, np.zeros(10, bool)]
    res = completeness(mags, matched, [20.0, 21.0, 22.0, 23.0, 24.0])
    assert magnitude_at(res, 0.5) == pytest.approx(22.25)
    np.testing.assert_allclose(default_map_mag_edges(22.25), [20.75, 21.75, 22.75, 23.75])
    with pytest.raises(InputError, match="map_mag_edges"):
        default_map_mag_edges(np.nan)


def test_m50_sd_is_the_delta_method_with_many_injections_per_bin():
    # 1.0, 0.8, 0.4, 0.0 with 1000 per bin: m50 = 22.25 interpolates the 0.8 and 0.4 bins (1 mag apart);
    # dm/df_i = (0.5 - 0.4) / 0.4^2 = 0.625, dm/df_j = (0.8 - 0.5) / 0.4^2 = 1.875 (mag per unit f).  With so
    # many injections the drawn curves all cross between those two bins, nearly linearly in their ratios:
    # the spread is the delta method's sd to within the Monte Carlo error of 2,000 draws (about 2%; 5% allowed)
    n = 1000
    mags = np.repeat([20.5, 21.5, 22.5, 23.5], n)
    matched = np.r_[np.ones(n, bool), np.arange(n) < 0.8 * n, np.arange(n) < 0.4 * n, np.zeros(n, bool)]
    res = completeness(mags, matched, [20.0, 21.0, 22.0, 23.0, 24.0])
    assert magnitude_at(res, 0.5) == pytest.approx(22.25)
    delta = np.sqrt(0.625 ** 2 * 0.8 * 0.2 / n + 1.875 ** 2 * 0.4 * 0.6 / n)
    assert magnitude_at_sd(res, 0.5) == pytest.approx(delta, rel=0.05)
    # seeded: the same seed gives the same spread, another seed one within the Monte Carlo error
    assert magnitude_at_sd(res, 0.5, seed=3) == magnitude_at_sd(res, 0.5, seed=3)
    assert magnitude_at_sd(res, 0.5, seed=3) == pytest.approx(magnitude_at_sd(res, 0.5), rel=0.08)
    # no crossing: NaN, like magnitude_at
    flat = completeness(mags, np.ones(4 * n, bool), [20.0, 21.0, 22.0, 23.0, 24.0])
    assert np.isnan(magnitude_at(flat, 0.5)) and np.isnan(magnitude_at_sd(flat, 0.5))


def test_m50_sd_of_a_few_noisy_bins_holds_the_randomness_of_the_first_crossing():
    # a small run's bins (a 3-realization run on a real image): 1 of 1 detected, then 1 of 3, 7 of 8, 2 of 2,
    # 0 of 2.  The first crossing falls between the first two bins (m50 = 21.425), but a curve this noisy
    # could as well cross after the 7-of-8 bin, 0.2-0.3 mag fainter.  The delta method on the two bins
    # interpolated said 0.097 mag; the spread of the drawn crossings must reach further (measured 0.150).
    centres = np.array([21.35, 21.45, 21.55, 21.65, 21.75])
    mags = np.repeat(centres, [1, 3, 8, 2, 2])
    matched = np.r_[True, True, False, False, np.arange(8) < 7, True, True, False, False]
    res = completeness(mags, matched, np.arange(21.3, 21.801, 0.1))
    np.testing.assert_array_equal(res.k, [1, 1, 7, 2, 0])
    m50 = magnitude_at(res, 0.5)
    assert m50 == pytest.approx(21.35 + 0.5 / (1 - 1 / 3) * 0.1)
    assert magnitude_at_sd(res, 0.5) > 0.12


def test_m50_sd_covers_the_truth_with_few_injections():
    """150 injections over 21-26 mag in 0.1-mag bins (3 per bin) from a logistic with m50 24, w 0.15, plateau
    0.97, floor 0.01: over 200 seeded tables |m50 - truth| <= sd must hold in at least 0.6 (measured 0.91;
    the delta method on the two bins interpolated held in 0.31).  Binomial sd of a coverage of 0.68 at 200
    tables: 0.033."""
    from scipy import special

    rng = np.random.default_rng(20261129)
    edges = np.arange(21.0, 26.0001, 0.1)
    truth = 24.0 + 0.15 * np.log((0.97 - 0.5) / (0.5 - 0.01))  # f = 0.5
    hits = []
    for _ in range(200):
        m = rng.uniform(21.0, 26.0, 150)
        det = rng.random(150) < 0.01 + 0.96 * special.expit((24.0 - m) / 0.15)
        res = completeness(m, det, edges)
        hits.append(abs(magnitude_at(res, 0.5) - truth) <= magnitude_at_sd(res, 0.5))
    assert np.mean(hits) >= 0.6


def test_m50_sd_matches_the_scatter_of_m50():
    """Over 400 seeded tables from a logistic (m50 24, w 0.1, 0.1-mag bins, 4000 injections over 3 mag),
    the rms of (m50 - truth) / sd is 1 to within 0.1: its sampling sd at 400 replicates is 0.035, and
    the interpolation bias of the binned m50 on this truth is below 0.1 sd (checked: mean z -0.01)."""
    rng = np.random.default_rng(20261128)
    edges = np.arange(22.5, 25.5001, 0.1)
    z = []
    for _ in range(400):
        m = rng.uniform(22.5, 25.5, 4000)
        det = rng.random(4000) < 1.0 / (1.0 + np.exp((m - 24.0) / 0.1))
        res = completeness(m, det, edges)
        z.append((magnitude_at(res, 0.5) - 24.0) / magnitude_at_sd(res, 0.5))
    z = np.asarray(z)
    assert abs(np.sqrt(np.mean(z ** 2)) - 1.0) < 0.1
    assert abs(np.mean(z)) < 0.2


def test_ratio_maps_known_counts():
    b = map_bin_pixels(0.5, 0.3)  # 0.5 arcmin at 0.3"/px = 100 px
    assert b == 100.0
    assert map_bin_pixels(0.5, 0.3, integer=False) == pytest.approx(100.0)
    shape = (250, 120)  # ny, nx -> 3 x 2 bins
    # bin (iy=0, ix=0): x = -0.5 is its left edge; x = 99.49 still inside
    # bin (iy=2, ix=1): y = 200.0, x = 99.5 (the edge between bins 0 and 1)
    # outside the image: x = 119.5, y = -0.6
    x = np.array([-0.5, 99.49, 99.5, 119.5, 10.0, 10.0, 10.0])
    y = np.array([0.0, 50.0, 200.0, 10.0, -0.6, 10.0, 10.0])
    mag = np.array([20.5, 20.5, 21.5, 20.5, 20.5, 20.5, 25.0])  # the last is outside the mag edges
    ok = np.array([True, False, True, True, True, True, True])
    maps = ratio_maps(x, y, mag, ok, image_shape=shape, bin_pix=b, mag_edges=[20, 21, 22])
    assert maps.n.shape == (2, 3, 2) and maps.shape == (3, 2)
    assert maps.n[0, 0, 0] == 3 and maps.k[0, 0, 0] == 2
    assert maps.ratio[0, 0, 0] == pytest.approx(2 / 3)
    assert maps.n[1, 2, 1] == 1 and maps.k[1, 2, 1] == 1
    assert maps.n.sum() == 4
    np.testing.assert_allclose(maps.x_edges, [-0.5, 99.5, 199.5])
    ref = binom_conf_interval(2, 3, confidence_level=0.6827, interval="wilson")
    assert maps.lower[0, 0, 0] == pytest.approx(ref[0])
    # wrappers: masked injections and excluded detections are left out
    cm = completeness_map(x, y, mag, ok, image_shape=shape, bin_pix=b, mag_edges=[20, 21, 22],
                          masked=np.r_[True, np.zeros(6, bool)])
    assert cm.n[0, 0, 0] == 2 and cm.name == "completeness"
    pm = purity_map(x, y, mag, ok, image_shape=shape, bin_pix=b, mag_edges=[20, 21, 22],
                    excluded=np.r_[False, True, np.zeros(5, bool)])
    assert pm.n[0, 0, 0] == 2 and pm.k[0, 0, 0] == 2


def _rotated_wcs(angle_deg, use_cd=True, sip=False):
    w = WCS(naxis=2)
    w.wcs.ctype = ["RA---TAN-SIP", "DEC--TAN-SIP"] if sip else ["RA---TAN", "DEC--TAN"]
    w.wcs.crval = [150.1, 2.2]
    w.wcs.crpix = [1023.7, 511.2]
    t = np.deg2rad(angle_deg)
    scale = 0.2 / 3600.0
    matrix = scale * np.array([[-np.cos(t), np.sin(t)], [np.sin(t), np.cos(t)]])
    if use_cd:
        w.wcs.cd = matrix
    else:
        w.wcs.cdelt = [scale, scale]
        w.wcs.pc = matrix / scale
    if sip:
        a = np.zeros((4, 4))
        bb = np.zeros((4, 4))
        a[2, 0], a[1, 1], a[0, 3] = 3e-6, -2e-6, 1e-9
        bb[0, 2], bb[2, 1] = 4e-6, 2e-9
        w.sip = Sip(a, bb, None, None, w.wcs.crpix)
    w.wcs.set()
    return w


@pytest.mark.parametrize("use_cd,sip", [(True, False), (False, False), (True, True)])
@pytest.mark.parametrize("bin_pix", [100.0, 37.3])
def test_map_wcs_bin_centres(use_cd, sip, bin_pix):
    image = _rotated_wcs(30.0, use_cd=use_cd, sip=sip)
    crpix_before = image.wcs.crpix.copy()
    mw = map_wcs(image, bin_pix, shape=(20, 30))
    assert mw.pixel_shape == (30, 20)
    i, j = np.meshgrid(np.arange(30), np.arange(20))
    sky_map = mw.pixel_to_world(i, j)
    sky_img = image.pixel_to_world((i + 0.5) * bin_pix - 0.5, (j + 0.5) * bin_pix - 0.5)
    assert sky_map.separation(sky_img).deg.max() < 1e-6
    np.testing.assert_array_equal(image.wcs.crpix, crpix_before)  # input untouched
    # the header round-trips
    again = WCS(mw.to_header(relax=True))
    assert again.pixel_to_world(i, j).separation(sky_img).deg.max() < 1e-6


def test_map_wcs_sip_terms_are_needed():
    # Guard against a test that cannot fail: with SIP distortion, a map WCS
    # that only rescales the linear part is off by far more than 1e-6 deg.
    image = _rotated_wcs(30.0, sip=True)
    linear_only = _rotated_wcs(30.0, sip=False)
    mw = map_wcs(linear_only, 100.0)
    i, j = np.meshgrid(np.arange(30), np.arange(20))
    sky_img = image.pixel_to_world((i + 0.5) * 100.0 - 0.5, (j + 0.5) * 100.0 - 0.5)
    assert mw.pixel_to_world(i, j).separation(sky_img).deg.max() > 1e-4


def test_map_wcs_errors():
    with pytest.raises(InputError, match="bin_pix"):
        map_wcs(_rotated_wcs(0.0), 0.0)
    with pytest.raises(InputError, match="2 axes"):
        map_wcs(WCS(naxis=3), 10.0)


def test_map_slices_sit_where_the_completeness_changes():
    # a logistic with m50 = 24, w = 0.2 sampled exactly: crossings at 24 -/+ w ln 9 (0.44 mag)
    edges = np.arange(21.0, 27.01, 0.05)
    centers = 0.5 * (edges[:-1] + edges[1:])
    f = 1.0 / (1.0 + np.exp((centers - 24.0) / 0.2))
    n = np.full(centers.size, 10000)
    comp = completeness(np.repeat(centers, n), np.concatenate([np.arange(k) < round(p * k) for p, k in zip(f, n)]),
                        edges)
    e = transition_map_mag_edges(comp)
    d = 0.2 * np.log(9.0)
    np.testing.assert_allclose(e, [24 - 1.5 * d, 24 - 0.5 * d, 24 + 0.5 * d, 24 + 1.5 * d], atol=0.03)
    # each slice's mean completeness is high, about one half, and low
    mid = 0.5 * (e[:-1] + e[1:])
    fm = 1.0 / (1.0 + np.exp((mid - 24.0) / 0.2))
    assert fm[0] > 0.85 and abs(fm[1] - 0.5) < 0.05 and fm[2] < 0.15
    # a curve that never falls to 0.1: the fixed slices around m50
    comp2 = completeness(np.repeat(centers, n), np.concatenate([np.arange(k) < round((0.3 + 0.6 * p) * k)
                                                                 for p, k in zip(f, n)]), edges)
    np.testing.assert_allclose(transition_map_mag_edges(comp2), default_map_mag_edges(magnitude_at(comp2, 0.5)))


def test_bright_end_pools_the_brightest_half_magnitude_of_populated_bins():
    """Bins start at the first populated one (an empty brighter bin does not count) and cover 0.5 mag:
    with 0.1-mag bins, five of them; the pooled ratio is k / n over those bins."""
    from comest_bayes.ratios.binned import binned_ratio, bright_end, magnitude_edges

    edges = magnitude_edges(19.0, 22.0, 0.1)
    mags = np.concatenate([np.full(10, 20.05 + 0.1 * i) for i in range(10)])  # 10 per bin from 20.0 to 21.0
    det = np.concatenate([np.arange(10) < (6 if i < 5 else 10) for i in range(10)])  # 60% in the first five
    b = bright_end(binned_ratio(mags, det, edges))
    assert b["n"] == 50 and b["k"] == 30 and b["ratio"] == pytest.approx(0.6)
    assert b["mag_lo"] == pytest.approx(20.0) and b["mag_hi"] == pytest.approx(20.5)
    empty = bright_end(binned_ratio(np.array([]), np.array([], bool), edges))
    assert empty["n"] == 0 and np.isnan(empty["ratio"])
