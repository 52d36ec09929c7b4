"""Tests of comest_bayes.sim.synthetic: scenes, known completeness truths, outcome tables, binned estimate."""

import math

import numpy as np
import pytest

from comest_bayes.sim import synthetic as S
from comest_bayes.errors import InputError


@pytest.fixture(scope="module")
def scene():
    """The default 512 x 512 scene (about 0.2 s to build)."""
    return S.make_scene(seed=7)


@pytest.fixture(scope="module")
def small_scene():
    return S.make_scene((96, 128), seed=3)


# ---------------------------------------------------------------- scene

def test_scene_depth_mask_and_reference(scene):
    assert scene.shape == (512, 512)
    assert scene.noise.shape == scene.mask.shape == scene.shape
    assert scene.mask.dtype == bool
    # a chip gap of ~3% of the columns plus a few blobs: a few % masked
    assert 0.03 <= scene.masked_fraction <= 0.08
    gap = scene.mask.all(axis=0)
    assert 10 <= gap.sum() <= 20
    # the depth is referenced to the median unmasked noise, so its unmasked median is 0
    d = scene.depth[~scene.mask]
    assert scene.sigma_ref == pytest.approx(np.median(scene.noise[~scene.mask]))
    assert abs(np.median(d)) < 1e-6
    # the linear gradient is along y (default angle 90 deg) and spans ~0.6 mag; a mild smooth part on top
    rows = np.nanmean(np.where(scene.mask, np.nan, scene.depth), axis=1)
    assert 0.45 < rows[0] - rows[-1] < 0.75 or 0.45 < rows[-1] - rows[0] < 0.75
    assert 0.5 < d.max() - d.min() < 1.0
    # read-only, frozen
    with pytest.raises(ValueError, match="read-only"):
        scene.noise[0, 0] = 1.0


def test_scene_without_gap_or_gradient():
    sc = S.make_scene((64, 64), gradient=0.0, smooth_rms=0.0, chip_gap=False, n_blobs=0, seed=1)
    assert not sc.mask.any()
    np.testing.assert_allclose(sc.depth, 0.0, atol=1e-12)


def test_scene_bad_arguments():
    with pytest.raises(InputError, match=r"shape must be at least \(16, 16\), got \(8, 8\)"):
        S.make_scene((8, 8), seed=1)
    with pytest.raises(InputError, match="seed must be a non-negative integer, got -1"):
        S.make_scene(seed=-1)
    with pytest.raises(InputError, match="gradient = -0.1 must be a finite non-negative"):
        S.make_scene(gradient=-0.1, seed=1)
    with pytest.raises(InputError, match="the mask covers the whole scene"):
        S.Scene(shape=(4, 4), noise=np.ones((4, 4)), mask=np.ones((4, 4), bool))
    with pytest.raises(InputError, match="noise must be finite and positive at every pixel"):
        S.Scene(shape=(4, 4), noise=np.zeros((4, 4)), mask=np.zeros((4, 4), bool))


# ---------------------------------------------------------------- truths

def test_at_least_seven_named_truths_with_one_line_descriptions():
    required = {"skew_faint", "skew_bright", "long_tail", "two_populations", "plateau_slow", "width_varies",
                "logistic"}
    assert required <= set(S.TRUTHS)
    for name, truth in S.TRUTHS.items():
        assert truth.name == name
        assert truth.description and "\n" not in truth.description
        assert S.get_truth(name) is truth
    with pytest.raises(InputError, match="unknown truth 'no_such_truth'; use a Truth instance or one of"):
        S.get_truth("no_such_truth")


@pytest.mark.parametrize("name", sorted(S.TRUTHS))
def test_truth_monotone_bounded_and_m50_follows_depth(name):
    truth = S.TRUTHS[name]
    m = np.linspace(truth.m50_0 - 6, truth.m50_0 + 6, 2401)[:, None]
    d = np.array([-0.4, 0.0, 0.35])[None, :]
    for u, v in ((-1.0, 0.0), (0.0, 0.5), (1.0, -1.0)):
        f = truth.prob(m, d, u, v)
        assert f.shape == (m.size, d.size)
        assert np.all((f >= 0) & (f <= 1))
        assert np.all(np.diff(f, axis=0) <= 1e-15), "not non-increasing in m"
        assert np.all(f >= truth.floor - 1e-12) and np.all(f <= truth.plateau + 1e-12)
        # m50 (half-way between floor and plateau) sits at m50_0 + d, one for one
        half = truth.prob(truth.m50_0 + d, d, u, v)
        np.testing.assert_allclose(half, 0.5 * (truth.plateau + truth.floor), atol=1e-9)
    # broadcasting of u, v alone
    assert truth.prob(24.0, 0.0, np.zeros(5), 0.0).shape == (5,)


def test_only_the_control_is_a_logistic():
    """Fit floor + (A - floor) expit((m50 - m) / w) by least squares on a dense grid: only the control fits."""
    from scipy.optimize import least_squares
    from scipy.special import expit

    m = np.linspace(21.0, 26.0, 501)
    for name, truth in S.TRUTHS.items():
        f = truth.prob(m, 0.0, 0.9, 0.0)  # at u = 0.9 the varying width is 0.34 mag

        def resid(p):
            return p[3] + (p[2] - p[3]) * expit((p[0] - m) / p[1]) - f

        fit = least_squares(resid, [24.0, 0.2, truth.plateau, truth.floor], bounds=([20, 0.01, 0, 0], [28, 2, 1, 1]))
        worst = np.max(np.abs(fit.fun))
        if name == "logistic":
            assert worst < 1e-8
        elif name != "width_varies":  # that one is a logistic at any single position; its average is not
            assert worst > 0.004, f"{name} is within {worst:.4f} of a logistic"


def test_control_average_curve_equals_direct_average(small_scene):
    truth = S.TRUTHS["logistic"]
    mags = np.array([23.0, 23.8, 24.0, 24.2, 25.1])
    ny, nx = small_scene.shape
    yy, xx = np.mgrid[0:ny, 0:nx]
    u, v = 2 * xx / (nx - 1) - 1, 2 * yy / (ny - 1) - 1
    d = -2.5 * np.log10(small_scene.noise / np.median(small_scene.noise[~small_scene.mask]))
    good = ~small_scene.mask
    direct = []
    for m in mags:
        f = truth.floor + (truth.plateau - truth.floor) / (1.0 + np.exp((m - truth.m50_0 - d) / truth.w))
        direct.append(f[good].mean())
    np.testing.assert_allclose(S.truth_curve(truth, small_scene, mags), direct, rtol=0, atol=1e-13)
    # the same for a position-dependent truth through the positions argument
    tw = S.TRUTHS["width_varies"]
    pos = np.column_stack([xx[good], yy[good]])[::7]
    w = tw.w_left + (tw.w_right - tw.w_left) * (u[good][::7] + 1) / 2
    f = tw.floor + (tw.plateau - tw.floor) / (1.0 + np.exp((24.1 - tw.m50_0 - d[good][::7]) / w))
    assert S.truth_curve(tw, small_scene, 24.1, positions=pos) == pytest.approx(f.mean(), abs=1e-13)


@pytest.mark.parametrize("name", sorted(S.TRUTHS))
def test_truth_quantities_are_roots(name, small_scene):
    truth = S.TRUTHS[name]
    q = S.truth_quantities(truth, small_scene)
    c = S.truth_curve(truth, small_scene, [q["m50"], q["mag_bright"], q["mag_faint"]])
    assert abs(c[0] - 0.5) < 1e-6
    assert q["f_bright"] == pytest.approx(c[1], abs=1e-12)
    assert q["f_faint"] == pytest.approx(c[2], abs=1e-12)
    assert q["mag_bright"] == pytest.approx(q["m50"] - 0.3) and q["mag_faint"] == pytest.approx(q["m50"] + 0.3)
    if truth.plateau > 0.9:
        assert abs(S.truth_curve(truth, small_scene, q["m90"]) - 0.9) < 1e-6
        assert q["m90"] < q["m50"]
    else:  # plateau_slow: the curve never reaches 0.9
        assert math.isnan(q["m90"])


# ---------------------------------------------------------------- outcome tables

def test_draw_outcomes_columns_and_positions(small_scene):
    t = S.draw_outcomes("two_populations", small_scene, 5000, seed=11)
    assert t.colnames == ["mag", "detected", "x", "y", "noise"]
    assert t["detected"].dtype == bool
    lo, hi = S.TRUTHS["two_populations"].default_mag_range()
    assert lo <= t["mag"].min() and t["mag"].max() <= hi
    ix = np.floor(np.asarray(t["x"]) + 0.5).astype(int)
    iy = np.floor(np.asarray(t["y"]) + 0.5).astype(int)
    assert not small_scene.mask[iy, ix].any()
    np.testing.assert_array_equal(t["noise"], small_scene.noise[iy, ix])
    # the package reads the table as it is
    from comest_bayes.bayes.outcomes import covariates_from_outcomes

    cov, det, meta = covariates_from_outcomes(t, image_shape=small_scene.shape)
    assert meta["N"] == 5000 and set(meta["available"]) >= {"m", "uv", "depth"}


def test_detected_fraction_matches_truth_curve(small_scene):
    """In 0.2-mag slices of 200k injections the detected fraction is Binomial(n, <f>) / n.

    Tolerance: 4.5 binomial standard deviations sqrt(p (1 - p) / n) per slice (a false alarm
    about once in 1e5 per slice for a correct sampler); the seed is fixed, so the test is
    deterministic.  ``p`` is the truth curve averaged over the slice (the magnitudes are uniform).
    """
    truth = S.TRUTHS["skew_faint"]
    t = S.draw_outcomes(truth, small_scene, 200_000, seed=5)
    mag, det = np.asarray(t["mag"]), np.asarray(t["detected"])
    for a in np.arange(22.0, 25.4, 0.2):
        sel = (mag >= a) & (mag < a + 0.2)
        n = sel.sum()
        p = S.truth_curve(truth, small_scene, np.linspace(a, a + 0.2, 41)).mean()
        assert abs(det[sel].mean() - p) < 4.5 * math.sqrt(p * (1 - p) / n) + 1e-12, a


def test_same_seed_same_table(small_scene):
    a = S.draw_outcomes("long_tail", small_scene, 2000, seed=42)
    b = S.draw_outcomes("long_tail", small_scene, 2000, seed=42)
    c = S.draw_outcomes("long_tail", small_scene, 2000, seed=43)
    for col in a.colnames:
        np.testing.assert_array_equal(a[col], b[col])
    assert not np.array_equal(a["mag"], c["mag"])
    d = S.draw_outcomes("long_tail", small_scene, 2000, seed=42, mag_range=(20.0, 21.0))
    assert d["mag"].min() >= 20.0 and d["mag"].max() <= 21.0
    assert d["detected"].mean() > 0.9


def test_draw_outcomes_bad_arguments(small_scene):
    with pytest.raises(InputError, match="n = 0 must be a positive integer"):
        S.draw_outcomes("logistic", small_scene, 0, seed=1)
    with pytest.raises(InputError, match=r"mag_range = \(25.0, 24.0\) must be finite with bright < faint"):
        S.draw_outcomes("logistic", small_scene, 10, seed=1, mag_range=(25.0, 24.0))
    with pytest.raises(InputError, match="seed must be a non-negative integer, got None"):
        S.draw_outcomes("logistic", small_scene, 10, seed=None)
    with pytest.raises(InputError, match="scene must be a Scene"):
        S.draw_outcomes("logistic", np.ones((5, 5)), 10, seed=1)
    with pytest.raises(InputError, match="unknown truth 'nope'"):
        S.draw_outcomes("nope", small_scene, 10, seed=1)


# ---------------------------------------------------------------- binned estimate

def test_binned_estimate_recovers_control_m50(scene):
    """At n = 200k (5000 per 0.1-mag bin) the binned m50 and m90 are within 0.02 mag of the truth.

    The statistical error of the binned m50 is about sqrt(0.25 / 5000) / |slope| ~ 0.006 mag
    (slope ~ 1.1 per mag); linear interpolation and bin averaging add < 0.002 mag for this curve.
    """
    truth = S.TRUTHS["logistic"]
    q = S.truth_quantities(truth, scene)
    rng_range = truth.default_mag_range()
    t = S.draw_outcomes(truth, scene, 200_000, seed=9)
    b = S.binned_estimate(t, mag_range=rng_range, probes=[q["mag_bright"], q["mag_faint"]])
    assert b.edges[0] == rng_range[0] and b.edges[-1] >= rng_range[1] - 1e-9
    np.testing.assert_allclose(np.diff(b.edges), 0.1)
    assert b.n.sum() == 200_000
    assert abs(b.m50 - q["m50"]) < 0.02
    assert abs(b.m90 - q["m90"]) < 0.02
    np.testing.assert_allclose(b.f_probe, [q["f_bright"], q["f_faint"]], atol=0.03)
    # the interpolated curve passes through the bin values at the centres
    np.testing.assert_allclose(b.curve(b.centers), b.ratio)
    d = b.to_dict()
    assert d["m50"] == pytest.approx(b.m50) and len(d["n"]) == len(b.centers)


def test_binned_estimate_bad_arguments(small_scene):
    t = S.draw_outcomes("logistic", small_scene, 100, seed=1)
    with pytest.raises(InputError, match=r"mag_range = \(24.0, 23.0\) must be finite with bright < faint"):
        S.binned_estimate(t, mag_range=(24.0, 23.0))
    with pytest.raises(InputError, match="mag_bin = 0.0 must be a positive bin width"):
        S.binned_estimate(t, mag_range=(22.0, 26.0), mag_bin=0.0)
    with pytest.raises(InputError, match="needs 'mag' and 'detected' columns"):
        S.binned_estimate({"mag": [24.0]}, mag_range=(22.0, 26.0))
