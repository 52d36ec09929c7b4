"""Placement of injections: counts, minimum separation, masks, methods, reproducibility."""

import time
import warnings

import numpy as np
import pytest
from scipy import stats
from scipy.spatial import cKDTree

from comest_bayes.errors import InputError
from comest_bayes.inject.placement import draw_count, masked_at, pixel_index, place_sources, placement_area_arcmin2


METHODS = ("uniform", "grid", "halton")


def nearest_neighbour_distances(x, y):
    pts = np.column_stack([x, y])
    d, _ = cKDTree(pts).query(pts, k=2)
    return d[:, 1]


@pytest.mark.parametrize("method", METHODS)
def test_minimum_separation_count_and_region(method):
    shape = (400, 600)
    p = place_sources(300, shape, np.random.default_rng(3), method=method, min_sep_pix=12.0, border_pix=5.0)
    assert p.n == 300 and p.complete and p.message == ""
    assert nearest_neighbour_distances(p.x, p.y).min() >= 12.0
    # inside the half-open region [border - 0.5, n - 0.5 - border)
    assert p.x.min() >= 4.5 and p.x.max() < 600 - 0.5 - 5.0
    assert p.y.min() >= 4.5 and p.y.max() < 400 - 0.5 - 5.0


@pytest.mark.parametrize("method", METHODS)
def test_same_seed_same_positions_other_seed_different(method):
    a = place_sources(200, (300, 300), np.random.default_rng(11), method=method, min_sep_pix=8.0)
    b = place_sources(200, (300, 300), np.random.default_rng(11), method=method, min_sep_pix=8.0)
    c = place_sources(200, (300, 300), np.random.default_rng(12), method=method, min_sep_pix=8.0)
    np.testing.assert_array_equal(a.x, b.x)
    np.testing.assert_array_equal(a.y, b.y)
    assert not np.allclose(a.x, c.x)


def test_impossible_density_warns_and_places_as_many_as_possible():
    # 10 px separation on 100x100: random packing holds ~ 0.547 * 1e4 / (pi 25) ~ 70 points
    with pytest.warns(UserWarning, match="only .* of 1000 injections fit"):
        p = place_sources(1000, (100, 100), np.random.default_rng(0), method="uniform", min_sep_pix=10.0)
    assert not p.complete
    assert "injection.density" in p.message
    assert 30 < p.n < 1000
    assert nearest_neighbour_distances(p.x, p.y).min() >= 10.0


def test_grid_reduces_count_when_cells_would_be_too_small():
    with pytest.warns(UserWarning, match=r"only 25 of 500 injections fit with a minimum separation of 20\.00 pixels"):
        p = place_sources(500, (100, 100), np.random.default_rng(0), method="grid", min_sep_pix=20.0)
    assert p.n == 25  # 5 x 5 cells of 20 px
    assert nearest_neighbour_distances(p.x, p.y).min() >= 20.0 - 1e-9


def test_masked_flag_matches_the_pixel_under_each_position():
    shape = (200, 300)
    mask = np.zeros(shape, dtype=bool)
    mask[:, :100] = True          # left third
    mask[150:170, 200:260] = True  # a small rectangle
    p = place_sources(2000, shape, np.random.default_rng(5), mask=mask, method="uniform")
    ix = np.floor(p.x + 0.5).astype(int)
    iy = np.floor(p.y + 0.5).astype(int)
    np.testing.assert_array_equal(p.masked, mask[iy, ix])
    # positions are not avoided on masked pixels: the masked fraction follows the masked area
    # (binomial sd for n=2000, p=0.35: 0.011; tolerance 0.04 is > 3.5 sd)
    assert abs(p.masked.mean() - mask.mean()) < 0.04


def test_pixel_index_uses_half_pixel_boundaries():
    ix, iy = pixel_index([-0.5, -0.49, 0.49, 0.5, 9.49], [0.0, 0.0, 0.0, 0.0, 0.0], (1, 10))
    np.testing.assert_array_equal(ix, [0, 0, 0, 1, 9])
    mask = np.zeros((1, 10), dtype=bool)
    mask[0, 1] = True
    np.testing.assert_array_equal(masked_at([0.49, 0.5, 1.49, 1.5], [0, 0, 0, 0], mask), [False, True, True, False])


def test_uniform_positions_are_uniform():
    p = place_sources(3000, (500, 500), np.random.default_rng(8), method="uniform", min_sep_pix=3.0)
    # KS test against U(-0.5, 499.5); with a fixed seed the p-value is a fixed number; a
    # non-uniform placement (e.g. a bias towards early-accepted regions) gives p << 1e-3
    for v in (p.x, p.y):
        assert stats.kstest(v, stats.uniform(loc=-0.5, scale=500).cdf).pvalue > 1e-3


def test_halton_covers_the_image_more_evenly_than_uniform():
    # counts in a 10x10 grid of cells: the Halton sequence's spread is far below Poisson's
    shape = (1000, 1000)
    h = place_sources(2000, shape, np.random.default_rng(1), method="halton")
    u = place_sources(2000, shape, np.random.default_rng(1), method="uniform")
    def cell_sd(p):
        counts, _, _ = np.histogram2d(p.x, p.y, bins=10, range=[[-0.5, 999.5], [-0.5, 999.5]])
        return counts.std()
    assert cell_sd(h) < 0.5 * cell_sd(u)  # Poisson sd ~ sqrt(20) = 4.5; Halton ~ 1


def test_draw_count_mean_is_density_times_area():
    shape, scale, density = (600, 900), 0.2, 15.0
    area = placement_area_arcmin2(shape, scale)
    assert area == pytest.approx(600 * 900 * 0.04 / 3600)
    rng = np.random.default_rng(2)
    counts = np.array([draw_count(density, shape, scale, rng) for _ in range(400)])
    mean = density * area  # 90
    # sd of the mean of 400 Poisson(90) draws: sqrt(90/400) = 0.47; tolerance 2.0 > 4 sd
    assert abs(counts.mean() - mean) < 2.0
    assert abs(counts.var() / mean - 1.0) < 0.3  # Poisson: variance = mean (sd of ratio ~0.07)


def test_twenty_thousand_points_on_8k_image_are_fast():
    t0 = time.perf_counter()
    p = place_sources(20000, (8192, 8192), np.random.default_rng(0), method="uniform", min_sep_pix=19.0)
    dt = time.perf_counter() - t0
    assert p.n == 20000
    assert nearest_neighbour_distances(p.x, p.y).min() >= 19.0
    assert dt < 2.0  # typically 0.02 s; generous for a loaded machine


def test_zero_and_invalid_inputs():
    p = place_sources(0, (50, 50), np.random.default_rng(0))
    assert p.n == 0 and p.complete and p.masked.shape == (0,)
    with pytest.raises(InputError, match="placement method"):
        place_sources(5, (50, 50), np.random.default_rng(0), method="spiral")
    with pytest.raises(InputError, match="mask shape"):
        place_sources(5, (50, 50), np.random.default_rng(0), mask=np.zeros((5, 5), bool))
    with pytest.raises(InputError, match="placement region is empty"):
        place_sources(5, (50, 50), np.random.default_rng(0), border_pix=30)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        place_sources(5, (50, 50), np.random.default_rng(0), min_sep_pix=2.0)  # no warning when it fits


def test_an_unresolved_automatic_density_draws_at_the_published_density():
    # a bare make_truth call with the default (automatic) density draws Poisson(15 x area)
    from comest_bayes.config import InjectionConfig
    from comest_bayes.inject.render import make_truth

    config = InjectionConfig(kinds=("point",), mag_range=(20.0, 24.0))
    assert config.density == 0.0
    counts = [len(make_truth("point", shape=(600, 600), pixel_scale=0.5, fwhm_pix=3.0, config=config,
                             rng=np.random.default_rng(s), zeropoint=30.0)) for s in range(40)]
    mean = 15.0 * (600 * 0.5 / 60) ** 2  # 375
    # 40 Poisson draws of mean 375: the sample mean has sd 3.1; 4 sd
    assert abs(np.mean(counts) - mean) < 4 * np.sqrt(mean / 40)


# --------------------------------------------------------------------------- sized placement
# comest_bayes.inject.placement.place_sized_sources: each pair keeps the sum of its radii, each centre its
# stamp's half-size from the edges.

def test_sized_placement_keeps_each_pair_the_sum_of_its_radii_and_every_stamp_on_the_image():
    from comest_bayes.inject.placement import place_sized_sources

    rng = np.random.default_rng(5)
    n = 60
    radius = np.where(np.arange(n) < 10, 40.0, 8.0)  # 10 large galaxies, 50 small ones
    half = np.where(np.arange(n) < 10, 60.0, 15.0)
    p = place_sized_sources(radius, half, (400, 500), rng)
    assert p.complete and p.n == n and np.array_equal(p.index, np.arange(n))
    r = radius[p.index]
    d = np.hypot(p.x[:, None] - p.x[None, :], p.y[:, None] - p.y[None, :])
    need = r[:, None] + r[None, :]
    off = ~np.eye(n, dtype=bool)
    assert np.all(d[off] >= need[off])
    # small pairs sit closer than the 80 px two large ones need: the separation is not one for all
    small = r < 10
    assert np.min(d[np.ix_(small, small)][~np.eye(small.sum(), dtype=bool)]) < 80.0
    # every stamp's pixels [ix - h, ix + h] lie on the image
    ix, iy = np.floor(p.x + 0.5), np.floor(p.y + 0.5)
    h = half[p.index]
    assert np.all(ix - h >= 0) and np.all(ix + h <= 499) and np.all(iy - h >= 0) and np.all(iy + h <= 399)


def test_sized_placement_leaves_out_what_cannot_fit_and_says_so():
    from comest_bayes.inject.placement import place_sized_sources

    # 200x200: a stamp of half-size 120 cannot lie on it; two of radius 60 with stamps of half-size 70 need
    # 120 px between centres confined to a 60x60 square (diagonal 85 px): only one fits
    with pytest.warns(UserWarning, match="only 1 of 3 galaxies fit"):
        p = place_sized_sources([60.0, 60.0, 10.0], [70.0, 70.0, 120.0], (200, 200), np.random.default_rng(0))
    assert not p.complete and p.n == 1 and p.index[0] in (0, 1)
    assert "stamps wider than the image" in p.message


def test_sized_placement_is_reproducible():
    from comest_bayes.inject.placement import place_sized_sources

    rad, half = np.linspace(3, 12, 40), np.linspace(5, 20, 40)
    a = place_sized_sources(rad, half, (300, 300), np.random.default_rng(2))
    b = place_sized_sources(rad, half, (300, 300), np.random.default_rng(2))
    c = place_sized_sources(rad, half, (300, 300), np.random.default_rng(3))
    assert np.array_equal(a.x, b.x) and np.array_equal(a.y, b.y) and not np.array_equal(a.x, c.x)
