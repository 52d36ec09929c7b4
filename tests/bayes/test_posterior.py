"""Posterior products (comest_bayes.bayes.posterior): the exact footprint average, crossings, extrapolation
flags, save/load, sky-coordinate queries and the two-pass crossing search."""

import warnings

import numpy as np
import pytest

from comest_bayes.bayes.fit import fit_kind
from comest_bayes.bayes.outcomes import BinomialData, Covariates
from comest_bayes.bayes.model import CompletenessModel
from comest_bayes.config import load_config
from comest_bayes.errors import InputError
from comest_bayes.bayes.posterior import (CompletenessPosterior, ExtrapolationWarning, Footprint, FootprintHistogram, average_crossings, average_prob)
from outcome_truths import SHAPE as FIT_SHAPE, depth_split_outcomes, fit_depth_split

SHAPE = (120, 160)


def _maps(seed=0):
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:SHAPE[0], 0:SHAPE[1]]
    noise = 5.0 * 10 ** (0.4 * (0.5 * xx / SHAPE[1] + 0.05 * np.sin(yy / 9.0))) * (1 + 0.02 * rng.random(SHAPE))
    mask = np.zeros(SHAPE, bool)
    mask[:, 70:75] = True
    mask[10:30, 100:130] = True
    return noise, mask


def _model(spec="logistic_depth"):
    data = BinomialData(cov=Covariates.make([24.0]), n=np.array([1]), k=np.array([1]),
                        meta={"binned": ("m", "depth", "uv", "size")})
    return CompletenessModel(spec, data)


def test_footprint_average_equals_the_average_over_every_pixel():
    noise, mask = _maps()
    sigma_ref = float(np.median(noise[~mask]))
    fp = Footprint.from_maps(noise, mask, sigma_ref)
    assert fp.npix == int((~mask).sum()) and fp.weight.sum() == pytest.approx(1.0)
    model = _model()
    theta = model.inverse_transform(dict(m50_0=24.0, w=0.15, A=0.97, floor=0.01, beta_depth=1.0))
    mags = np.linspace(22.5, 25.5, 31)
    # brute force: f at every unmasked pixel, averaged
    jj, ii = np.nonzero(~mask)
    d = -2.5 * np.log10(noise[jj, ii] / sigma_ref)
    cov = Covariates.make(np.repeat(mags[None, :], d.size, 0).ravel(), np.repeat(d, mags.size))
    brute = model.prob(theta, cov).reshape(d.size, mags.size).mean(axis=0)
    cells = average_prob(model, theta[None, :], mags, fp)[0]
    # grouping into 0.01-mag depth cells at their mean depth: error second order, measured 1.1e-5 in f,
    # i.e. ~1e-5 mag on m50 where the curve falls by ~1.5 per mag -- a hundredth of the smallest
    # posterior sd the benchmarks reach
    np.testing.assert_allclose(cells, brute, atol=3e-5)
    assert len(fp) < d.size / 20


def test_one_footprint_histogram_serves_every_reference_noise():
    # The run computes the pixel pass once; each fit shifts it to its own sigma_ref.  The cells must be
    # exactly those of a direct pass with that sigma_ref: the same pixels in each cell (counts and
    # positions), depths shifted by 2.5 log10 of the ratio of reference noises.
    noise, mask = _maps(2)
    noise[5:9, 5:40] = np.nan  # pixels without a valid noise sit at depth 0 whatever sigma_ref
    noise[40:42, 10:20] = 0.0
    for ddepth, nuv in ((0.01, 1), (0.02, 8)):
        hist = FootprintHistogram.from_maps(noise, mask, ddepth=ddepth, nuv=nuv)
        assert hist.n.sum() == (~mask).sum() == hist.npix
        assert hist.n[~hist.valid].sum() == 35 * 4 + 2 * 10
        for sigma_ref in (4.0, 7.5):
            fp = Footprint.from_histogram(hist, sigma_ref)
            jj, ii = np.nonzero(~mask)
            sig = noise[jj, ii]
            ok = np.isfinite(sig) & (sig > 0)
            depth = np.zeros(sig.size)
            depth[ok] = -2.5 * np.log10(sig[ok] / sigma_ref)
            # the footprint's weighted moments equal the pixels' own
            assert np.sum(fp.weight * fp.depth) == pytest.approx(depth.mean(), abs=1e-12)
            u = 2.0 * ii / (SHAPE[1] - 1) - 1.0
            assert np.sum(fp.weight * fp.u) == pytest.approx(u.mean(), abs=1e-12)
            # and every cell is narrower than its depth step (pixels grouped by depth, not merged across it)
            assert np.all(fp.depth[hist.valid] <= depth[ok].max() + 1e-12)
            assert np.all(fp.depth[~hist.valid] == 0.0)
        shifted = Footprint.from_histogram(hist, 7.5).depth - Footprint.from_histogram(hist, 4.0).depth
        np.testing.assert_allclose(shifted[hist.valid], 2.5 * np.log10(7.5 / 4.0), rtol=0, atol=1e-12)
    # no noise map: one cell per position block, at depth 0
    hist = FootprintHistogram.from_maps(None, mask, nuv=4)
    fp = Footprint.from_histogram(hist, 3.0)
    assert len(fp.weight) == 16 and np.all(fp.depth == 0.0) and fp.weight.sum() == pytest.approx(1.0)


def test_points_grouped_into_cells_average_as_the_points_themselves():
    # A footprint sampled by 5000 positions (the injections of an outcome table without maps): grouped by depth
    # (0.01 mag) into cells at their members' mean depth, weighted by their number, the image average of f is
    # the points' own average to second order (measured ~1e-6 in f) with a few dozen cells instead of 5000.
    noise, mask = _maps(4)
    rng = np.random.default_rng(9)
    jj, ii = np.nonzero(~mask)
    pick = rng.choice(jj.size, 5000, replace=False)
    x, y, sig = ii[pick].astype(float), jj[pick].astype(float), noise[jj[pick], ii[pick]]
    sigma_ref = float(np.median(sig))
    each = Footprint.from_points(x, y, sig, sigma_ref, SHAPE, ddepth=None)
    grouped = Footprint.from_points(x, y, sig, sigma_ref, SHAPE)
    assert len(each) == 5000 and len(grouped) < 100 and grouped.weight.sum() == pytest.approx(1.0)
    model = _model()
    theta = model.inverse_transform(dict(m50_0=24.0, w=0.15, A=0.97, floor=0.01, beta_depth=1.0))
    mags = np.linspace(22.5, 25.5, 31)
    np.testing.assert_allclose(average_prob(model, theta[None, :], mags, grouped),
                               average_prob(model, theta[None, :], mags, each), atol=3e-5)


def test_crossings_are_exact_roots_of_the_average_curve():
    noise, mask = _maps(1)
    fp = Footprint.from_maps(noise, mask, float(np.median(noise[~mask])))
    model = _model()
    rng = np.random.default_rng(3)
    base = model.inverse_transform(dict(m50_0=24.0, w=0.2, A=0.96, floor=0.01, beta_depth=0.9))
    thetas = base + 0.02 * rng.standard_normal((7, base.size))
    cross = average_crossings(model, thetas, fp, (0.5, 0.9), 21.0, 26.0)
    for lev, m in cross.items():
        f = np.array([average_prob(model, t[None, :], [mm], fp)[0, 0] for t, mm in zip(thetas, m)])
        np.testing.assert_allclose(f, lev, atol=2e-6)
    # a plateau below the level: no crossing (NaN), not a number made up
    low = model.inverse_transform(dict(m50_0=24.0, w=0.2, A=0.85, floor=0.01, beta_depth=1.0))
    assert np.isnan(average_crossings(model, low[None, :], fp, (0.9,), 21.0, 26.0)[0.9][0])


def _posterior(noise, mask, injected=(22.0, 25.0)):
    model = _model()
    theta = model.inverse_transform(dict(m50_0=24.0, w=0.15, A=0.97, floor=0.01, beta_depth=1.0))
    draws = theta + 0.005 * np.random.default_rng(4).standard_normal((50, theta.size))
    sigma_ref = float(np.median(noise[~mask]))
    return CompletenessPosterior(
        spec=model.spec, samples=draws, names=list(model.names),
        meta={"sigma_ref": sigma_ref, "hlr_ref": None, "image_shape": SHAPE, "mag_range": [21.0, 26.0],
              "injected_range": list(injected), "depth_range": [-0.3, 0.3], "kind": "point",
              "quantity": "completeness"},
        noise_grid=noise[::8, ::8], grid_step=8, footprint=np.array([[10.0, 10.0]]),
        cells=Footprint.from_maps(noise, mask, sigma_ref))


def test_extrapolated_magnitudes_are_flagged_and_warned(tmp_path):
    noise, mask = _maps(2)
    post = _posterior(noise, mask, injected=(22.0, 24.2))  # m50 ~ 24: m50 inside, the faint side outside
    with pytest.warns(ExtrapolationWarning, match="outside the injected magnitudes range"):
        post.completeness([24.5, 25.0], x=20.0, y=20.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error", ExtrapolationWarning)
        post.completeness([23.0, 24.0], x=20.0, y=20.0)  # inside: no warning
    post2 = _posterior(noise, mask, injected=(21.0, 23.7))  # m50 itself lies beyond the injections
    with pytest.warns(ExtrapolationWarning, match="m50"):
        summary = post2.summary_magnitudes()
    assert summary["m50"]["extrapolated"] is True and summary["m90"]["extrapolated"] is False
    # the footprint cells survive save and load
    again = CompletenessPosterior.load(post.save(tmp_path / "p.npz"))
    np.testing.assert_array_equal(again.cells.weight, post.cells.weight)
    np.testing.assert_allclose(again.average_curve([23.5, 24.0]), post.average_curve([23.5, 24.0]))


def test_image_average_queries_warn_refuse_and_keep_the_shape_of_their_magnitudes():
    # found by a new user: the image average skipped the extrapolation warning, read NaN as a magnitude of
    # completeness 0, returned (S, 1) for one magnitude and failed on a 2-D array
    noise, mask = _maps(2)
    post = _posterior(noise, mask, injected=(22.0, 24.2))
    with pytest.warns(ExtrapolationWarning, match="2 queried magnitude"):
        f = post.completeness([24.5, 30.0])
    assert f.shape == (50, 2)
    with warnings.catch_warnings():
        warnings.simplefilter("error", ExtrapolationWarning)
        one = post.completeness(23.5)
        grid = post.completeness(np.array([[22.5, 23.0], [23.5, 24.0]]))
        band = post.curve(np.array([22.5, 23.0, 24.5]), warn=False)  # a fixed grid on purpose: flagged, not warned
    assert one.shape == (50,) and grid.shape == (50, 2, 2)
    np.testing.assert_allclose(grid[:, 1, 0], one)
    np.testing.assert_allclose(grid.reshape(50, 4), post.average_curve([22.5, 23.0, 23.5, 24.0]))
    assert band["extrapolated"].tolist() == [False, False, True] and band["median"].shape == (3,)
    assert post.curve(23.5)["mag"].shape == (1,)
    for bad in (np.nan, np.inf, [23.0, np.nan]):
        with pytest.raises(InputError, match="non-finite magnitude"):
            post.completeness(bad)
    with pytest.raises(InputError, match="non-finite magnitude"):
        post.curve([23.0, np.nan])


def test_position_queries_need_both_coordinates_and_warn_off_the_image():
    noise, mask = _maps(2)
    post = _posterior(noise, mask)
    ny, nx = SHAPE
    for kwargs in ({"x": 10.0}, {"y": 10.0}, {"ra": 150.0}, {"dec": 2.0}):
        with pytest.raises(InputError, match="needs both coordinates"):
            post.completeness(23.0, **kwargs)
    with pytest.raises(InputError, match="not both"):
        post.completeness(23.0, 10.0, 10.0, ra=150.0, dec=2.0)
    with pytest.raises(InputError, match="need the image WCS"):
        post.completeness(23.0, ra=150.0, dec=2.0)  # this posterior has no WCS
    with pytest.warns(ExtrapolationWarning, match=f"1 queried position.*outside the {nx}x{ny}-pixel image"):
        post.completeness(23.0, [10.0, nx + 50.0], [10.0, 10.0])
    with warnings.catch_warnings():
        warnings.simplefilter("error", ExtrapolationWarning)
        post.completeness(23.0, [-0.5, nx - 0.5], [ny - 0.5, -0.5])  # the image's outer pixel edges: inside
    for bad in ({"nsamples": 0}, {"nsamples": -1}, {"nsamples": 2.5}):
        with pytest.raises(InputError, match="nsamples"):
            post.completeness(23.0, **bad)
    for step in (0, -1, 64.5, 10 * max(SHAPE)):
        with pytest.raises(InputError, match="step_pix"):
            post.m50_map(step)
    assert list(post.magnitudes_at(0.5)) == [0.5]
    with pytest.raises(InputError, match="between 0 and 1"):
        post.magnitudes_at(50)


# --------------------------------------------------------------------------- posteriors from the fit stage
# A known logistic completeness with a depth step, fitted by comest_bayes.bayes.fit.fit_kind; the tests
# below check what the resulting CompletenessPosterior answers.


def test_posterior_saves_and_reloads(tmp_path):
    table, noise_map = depth_split_outcomes(4000, seed=5)
    post, _ = fit_depth_split(table, noise_map, "logistic_depth")
    path = post.save(tmp_path / "p.npz")
    again = CompletenessPosterior.load(path)
    np.testing.assert_array_equal(again.samples, post.samples)
    np.testing.assert_allclose(again.completeness([23.0, 24.0], 50.0, 50.0), post.completeness([23.0, 24.0], 50.0, 50.0))
    med, sd, header = again.m50_map(100)
    assert med.shape == (4, 6) and np.all(sd >= 0)
    # the shallow part of the m50 map (x >= 330: map columns 4, 5) is brighter by the depth slope x 0.5 mag
    assert med[:, :3].mean() - med[:, 4:].mean() == pytest.approx(0.5, abs=0.1)


def test_sky_coordinate_query_equals_the_pixel_query():
    from astropy.wcs import WCS

    w = WCS(naxis=2)
    w.wcs.ctype = ["RA---TAN", "DEC--TAN"]
    w.wcs.crval = [150.0, 2.0]
    w.wcs.crpix = [300.0, 200.0]
    w.wcs.cd = np.array([[-0.2, 0.05], [0.05, 0.2]]) / 3600.0
    table, noise_map = depth_split_outcomes(3000, seed=6)
    config = load_config(overrides=["fit.model=logistic_depth", "fit.min_ess=100"], seed=3)
    post, _ = fit_kind(table, kind="point", quantity="completeness", requested="logistic_depth", config=config,
                       image_shape=FIT_SHAPE, noise=noise_map, mask=np.zeros(FIT_SHAPE, bool),
                       wcs_header=w.to_header().tostring(), mag_range=(21.0, 26.5),
                       mag_centers=np.arange(21.1, 26.5, 0.2))
    (ra, dec), = [w.all_pix2world([[500.0, 100.0]], 0)[0]]
    np.testing.assert_allclose(post.completeness(24.0, ra=ra, dec=dec), post.completeness(24.0, 500.0, 100.0),
                               rtol=1e-6)
    # and a sky position in the deep part differs from one in the shallow part
    (ra2, dec2), = [w.all_pix2world([[100.0, 100.0]], 0)[0]]
    assert post.completeness(24.0, ra=ra2, dec=dec2).mean() > post.completeness(24.0, ra=ra, dec=dec).mean() + 0.2
    # a sky position the tangent projection cannot place (more than 90 degrees away) is refused, not read as NaN
    with pytest.raises(InputError, match="1 sky position.*no pixel position"):
        post.completeness(24.0, ra=[ra, 10.0], dec=[dec, -50.0])


def test_two_pass_crossing_magnitudes_equal_the_full_fine_grid():
    # magnitudes_at locates the crossings on a 0.1 mag grid, then refines on a 0.01 mag grid over the window
    # they span only; the result must equal the crossing on the fine grid over the whole range (the two fine
    # grids are offset from each other, so linear interpolation differs by < ~1e-4 mag near m80/m90)
    from comest_bayes.bayes.posterior import crossing_magnitudes

    table, noise_map = depth_split_outcomes(3000, seed=9)
    post, _ = fit_depth_split(table, noise_map, "logistic_depth", min_ess=100)
    got = post.magnitudes_at((0.5, 0.8, 0.9), nsamples=200)
    grid = np.arange(21.0 - 2.0, 26.5 + 2.0 + 0.01, 0.01)
    f = post.average_curve(grid, nsamples=200)
    for level, values in got.items():
        want = crossing_magnitudes(grid, f, level)
        np.testing.assert_allclose(values, want, atol=2e-3)
        assert np.all(np.isfinite(values))


def test_footprint_histogram_in_row_blocks_equals_one_pass(monkeypatch):
    """The pixel pass reads the maps in blocks of rows; each pixel's row and column must be its own in
    every block (blocks of 7 rows, an odd size, against one block holding the whole image)."""
    import comest_bayes.bayes.posterior as P

    noise, mask = _maps(4)
    for nuv in (1, 8):
        whole = FootprintHistogram.from_maps(noise, mask, ddepth=0.02, nuv=nuv)
        monkeypatch.setattr(P, "FOOTPRINT_CHUNK", 7 * SHAPE[1])
        blocks = FootprintHistogram.from_maps(noise, mask, ddepth=0.02, nuv=nuv)
        monkeypatch.undo()
        np.testing.assert_array_equal(blocks.n, whole.n)
        np.testing.assert_array_equal(blocks.block, whole.block)
        np.testing.assert_allclose(blocks.u, whole.u, rtol=0, atol=1e-12)
        np.testing.assert_allclose(blocks.v, whole.v, rtol=0, atol=1e-12)
        np.testing.assert_allclose(blocks.level, whole.level, rtol=0, atol=1e-12)
        # and the mean position of the unmasked pixels is theirs
        jj, ii = np.nonzero(~mask)
        assert np.sum(blocks.n * blocks.v) / blocks.npix == pytest.approx(np.mean(2.0 * jj / (SHAPE[0] - 1) - 1.0),
                                                                           abs=1e-12)
