"""The analytic detection probability of point sources on white noise, and the pipeline against it."""

import math
import warnings

import numpy as np
import pytest
from scipy import special

from comest_bayes.analytic import (detection_probability, detection_probability_mc, filtered_noise_covariance,
                                   filtered_peak, kernel_norm, peak_probability, predict, predicted_m50,
                                   psf_image)
from comest_bayes.config import DetectionConfig, InjectionConfig
from comest_bayes.detection import detect_array, filter_kernel
from comest_bayes.errors import InputError
from comest_bayes.inference import fit_map, laplace
from comest_bayes.injection import make_truth, render_truth
from comest_bayes.likelihood import CompletenessModel, Covariates, compress
from comest_bayes.matching import match_one_to_one
from comest_bayes.seeding import rng_for
from comest_bayes.sources import make_psf

DEFAULT = filter_kernel("default")


def test_kernel_norm_and_noise_covariance_of_the_default_kernel():
    # [1 2 1; 2 4 2; 1 2 1] / 16: sum of squares 36 / 256, so ||k|| = 6 / 16
    assert kernel_norm(DEFAULT) == pytest.approx(0.375, rel=1e-6)
    assert kernel_norm(None) == 1.0
    cov = filtered_noise_covariance(DEFAULT, [(0, 0), (0, 1), (1, 1), (0, 3)])
    # separable 1-D autocorrelation of [1 2 1]/4: lag 0 -> 6/16, lag 1 -> 4/16, lag 2 -> 1/16
    a0, a1 = 6 / 16, 4 / 16
    np.testing.assert_allclose(cov[0], [a0 * a0, a0 * a1, a1 * a1, 0.0], rtol=1e-6)
    np.testing.assert_allclose(cov, cov.T)


def test_psf_image_has_unit_flux_and_the_requested_centre():
    img = psf_image(3.0, 0.3, -0.2, pixel_integrated=True)
    assert img.sum() == pytest.approx(1.0, abs=1e-9)
    h = img.shape[0] // 2
    r = np.arange(-h, h + 1)
    assert (img.sum(axis=0) * r).sum() == pytest.approx(0.3, abs=1e-6)
    assert (img.sum(axis=1) * r).sum() == pytest.approx(-0.2, abs=1e-6)
    # sampled at pixel centres: the centre pixel of a centred source is 1 / (2 pi s^2)
    s = 3.0 / (2 * math.sqrt(2 * math.log(2)))
    assert psf_image(3.0)[h, h] == pytest.approx(1 / (2 * math.pi * s * s), rel=1e-12)


def test_peak_probability_is_half_at_the_closed_form_m50():
    s0 = filtered_peak(3.0, DEFAULT)
    m50 = 30.0 - 2.5 * math.log10(1.5 * 10.0 / s0)
    kw = dict(zeropoint=30.0, sigma=10.0, fwhm_pix=3.0, kernel=DEFAULT, thresh=1.5)
    assert peak_probability(m50, **kw) == pytest.approx(0.5, abs=1e-12)
    # one filtered-noise sigma brighter in flux: Phi(1)
    f50 = 10 ** (-0.4 * (m50 - 30.0))
    m_up = 30.0 - 2.5 * math.log10(f50 + 10.0 * 0.375 / s0)
    assert peak_probability(m_up, **kw) == pytest.approx(special.ndtr(1.0), abs=1e-12)
    pred = predict(mc=False, **kw)
    assert pred.m50_centred == pytest.approx(m50, abs=1e-9) and pred.nu_thresh == pytest.approx(4.0)
    # an off-centre source has a lower peak: the sub-pixel average is brighter than the centred m50
    assert pred.m50_peak < pred.m50_centred


def test_monte_carlo_bounds_and_limits():
    kw = dict(zeropoint=30.0, sigma=10.0, fwhm_pix=3.0, kernel=DEFAULT)
    m = np.array([22.8, 22.9, 23.0])
    # minarea 1: any pixel near the source may cross, so the probability is at least the peak pixel's
    # (MC standard error <= 0.008 at 4000 samples, hence the 0.02 slack)
    p_peak = detection_probability(m, thresh=5.0, **kw)
    p_mc = detection_probability_mc(m, thresh=5.0, seed=1, **kw)
    assert np.all(p_mc >= p_peak - 0.02)
    # at a high threshold (13 filtered sigma) the neighbours rarely cross first: the m50 of the two agree
    # within 0.02 mag (measured 0.007; the transition is 0.08 mag wide)
    pred = predict(thresh=5.0, seed=1, **kw)
    assert 0.0 <= pred.m50_mc - pred.m50_peak < 0.02
    # minarea 5 needs more light than minarea 1
    p5 = detection_probability_mc(m, thresh=5.0, minarea=5, seed=1, **kw)
    assert np.all(p5 <= p_mc) and p5[1] < p_mc[1] - 0.05
    # the same seed gives the same numbers (common random numbers)
    np.testing.assert_array_equal(p_mc, detection_probability_mc(m, thresh=5.0, seed=1, **kw))
    with pytest.raises(InputError, match="cross"):
        predicted_m50(lambda x: detection_probability(x, thresh=5.0, **kw), lo=10.0, hi=11.0)


def test_sep_thresholds_the_filtered_image_at_thresh_times_the_unfiltered_sigma():
    # On white noise of unit sigma, filtered by the default kernel (filtered sigma 0.375), the fraction
    # of pixels above DETECT_THRESH = 1 is P(N(0, 0.375) > 1) = 3.8e-3 under SExtractor's semantics, and
    # P(N(0, 1) > 1) = 0.16 if SEP compared with the filtered noise.  ~1000 expected pixels in clumps of a few
    # correlated pixels: the 25% tolerance is > 5 sigma of that count.
    rng = rng_for(11, "white")
    img = rng.standard_normal((512, 512)).astype(np.float32)
    res = detect_array(img, zeropoint=30.0, weight_noise=np.ones_like(img),
                       config=DetectionConfig(thresh=1.0, minarea=1, noise="weight", back_size=128))
    frac = float((res.segmentation > 0).mean())
    expected = special.ndtr(-1.0 / kernel_norm(DEFAULT))
    assert frac == pytest.approx(expected, rel=0.25)


def _simulate(fwhm, thresh, minarea, m_centre, *, nreal=3, n=1500, seed=7):
    """Point sources rendered by the package's injector on white noise, detected and matched.

    Returns magnitudes, outcomes and the median noise sigma the detector used.
    """
    zp, sigma, shape, scale = 30.0, 10.0, (1024, 1024), 0.2
    inj = InjectionConfig(kinds=("point",), psf="gaussian", photon_noise=False)
    psf = make_psf(inj, fwhm, scale)
    det_cfg = DetectionConfig(thresh=thresh, minarea=minarea, filter="default")
    mags, outcome, noise = [], [], []
    for r in range(nreal):
        base = (rng_for(seed, "noise", r).standard_normal(shape) * sigma).astype(np.float32)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            truth = make_truth("point", shape=shape, pixel_scale=scale, fwhm_pix=fwhm, config=inj,
                               mag_range=(m_centre - 1.5, m_centre + 1.5), rng=rng_for(seed, "inject", r),
                               zeropoint=zp, n=n, border_pix=10)
        img, truth = render_truth(base, truth, psf=psf, config=inj, pixel_scale=scale, rng_seed=r, zeropoint=zp)
        res = detect_array(img, zeropoint=zp, config=det_cfg)
        cat = res.catalog
        # mag_tol=None: the test is about detection, not about the magnitude cut of the matcher
        match = match_one_to_one(truth["x"], truth["y"], truth["mag"], cat["xwin"], cat["ywin"], cat["mag_auto"],
                                 radius=fwhm, mag_tol=None)
        mags.append(np.asarray(truth["mag"], float))
        outcome.append(match.det_of_truth >= 0)
        noise.append(float(np.median(res.noise)))
    return np.concatenate(mags), np.concatenate(outcome), float(np.mean(noise))


def _fit_m50(m, detected):
    # probit: the predicted curve is a normal CDF in flux, close to one in magnitude near m50
    model = CompletenessModel("probit", compress(Covariates.make(m), detected, ddepth=None, nuv=None, dsize=None))
    mp = fit_map(model, seed=1)
    lap = laplace(model, mp.theta)
    return float(model.transform(mp.theta)["m50_0"]), float(lap.sd[0])


@pytest.mark.slow  # ~10 s per case: three 1024^2 images rendered, detected and fitted
@pytest.mark.parametrize("case", ["closed form (thresh 5, minarea 1)", "defaults (thresh 1.5, minarea 5)"])
def test_pipeline_fit_recovers_the_predicted_m50(case):
    # 4500 injections over 3 mag give a statistical sd of m50 of 0.005-0.01 mag, so the 0.05 mag tolerance of
    # the issue is > 5 sd; the prediction uses the noise sigma the detector measured (the background RMS,
    # which differs from the true 10 by < 1%, i.e. < 0.01 mag).
    fwhm = 3.0
    if case.startswith("closed"):
        thresh, minarea = 5.0, 1
    else:
        thresh, minarea = 1.5, 5
    kw = dict(zeropoint=30.0, fwhm_pix=fwhm, kernel=DEFAULT, thresh=thresh)
    first = predict(sigma=10.0, mc=False, **kw)
    m, det, sigma = _simulate(fwhm, thresh, minarea, first.m50_peak)
    assert abs(sigma / 10.0 - 1.0) < 0.02
    m50_fit, sd = _fit_m50(m, det)
    assert sd < 0.015
    if case.startswith("closed"):
        # 13 filtered sigma: the peak-pixel normal CDF, averaged over the sub-pixel centre, is the prediction
        pred = predict(sigma=sigma, mc=False, **kw).m50_peak
    else:
        # 4 filtered sigma and minarea 5: neighbours and the area cut matter; the Monte Carlo over the
        # filtered noise field gives the prediction (its own error < 0.005 mag at 4000 samples)
        pred = predict(sigma=sigma, minarea=minarea, seed=3, **kw).m50_mc
    assert m50_fit == pytest.approx(pred, abs=0.05), (m50_fit, pred)
