"""Adaptive magnitude designs (comest_bayes.inject.design): densities, draws, where the gain lies, and the
adaptive benchmark's pool that feeds a design.
"""

import math

import numpy as np
import pytest

from comest_bayes.pipeline.adaptive import AdaptiveSettings
from comest_bayes.inject.design import (MagnitudeDesign, curves_at, design_from_draws, uniform_design, variance_reduction)
from comest_bayes.errors import InputError
from conftest import load_benchmark


def logistic_draws(grid, m50=24.0, sd_m50=0.05, w=0.2, n=2000, seed=0):
    """Posterior-like draws of a logistic curve whose m50 is uncertain (sd_m50) and width known."""
    rng = np.random.default_rng(seed)
    m = rng.normal(m50, sd_m50, n)
    curves = 1.0 / (1.0 + np.exp((grid[None, :] - m[:, None]) / w))
    return curves, m


def test_uniform_design_is_flat_and_draws_inside_the_range():
    d = uniform_design(20.0, 26.0)
    np.testing.assert_allclose(d.density([20.5, 23.0, 25.9]), 1.0 / 6.0)
    assert d.density([19.0, 26.5]).tolist() == [0.0, 0.0]
    m = d.sample(5000, np.random.default_rng(1))
    assert m.min() >= 20.0 and m.max() <= 26.0
    assert d.fraction_within(23.0, 24.2) == pytest.approx(0.2)


def test_draws_follow_the_design_probabilities():
    # 20000 draws from a two-level density: bin counts within 4 binomial sigma of their expectation
    edges = np.linspace(0.0, 1.0, 5)
    d = MagnitudeDesign(edges, np.array([0.1, 0.4, 0.4, 0.1]), target="m50", uniform_share=0.0)
    m = d.sample(20000, np.random.default_rng(2))
    counts, _ = np.histogram(m, edges)
    expect = 20000 * d.prob
    assert np.all(np.abs(counts - expect) < 4 * np.sqrt(expect * (1 - d.prob)))
    # same generator state, same magnitudes
    np.testing.assert_array_equal(d.sample(10, np.random.default_rng(3)), d.sample(10, np.random.default_rng(3)))


def test_the_m50_gain_sits_at_m50_and_vanishes_on_the_plateau():
    # For a logistic of known width whose m50 is uncertain, an injection at m changes the m50 posterior by
    # Cov(m50, f(m))^2 / (p(1-p)) ~ f'(m)^2 Var(m50)^2 / (f(1-f)), which is symmetric about m50 and largest
    # within a width or two of it; on the plateau (5 widths away) it is negligible.
    grid = np.linspace(21.0, 27.0, 601)
    curves, m = logistic_draws(grid)
    gain = variance_reduction(grid, curves, target="m50", m50=m)
    peak = grid[np.argmax(gain)]
    assert abs(peak - 24.0) < 0.3
    assert gain[np.abs(grid - 22.0) < 0.05].max() < 1e-3 * gain.max()  # 10 widths: ~4 e^-10 of the peak
    # the linearised gain at m50 itself: f' = -1/(4w), p = 1/2 -> Var(m50)^2 / (16 w^2) / (1/4) = Var^2/(4 w^2)
    expected = (0.05 ** 2) ** 2 / (4 * 0.2 ** 2)
    assert gain[np.argmin(np.abs(grid - 24.0))] == pytest.approx(expected, rel=0.25)


def test_the_curve_gain_covers_the_transition():
    grid = np.linspace(21.0, 27.0, 301)
    curves, m = logistic_draws(grid, sd_m50=0.1)
    gain = variance_reduction(grid, curves, target="curve")
    inside = np.abs(grid - 24.0) < 0.4
    assert gain[inside].min() > 0.1 * gain.max()
    assert gain[np.abs(grid - 24.0) > 2.0].max() < 1e-2 * gain.max()


def test_the_f_gain_at_m50_matches_the_linearised_answer():
    # Width known, m50 uncertain (sd s): f(m) ~ f(m) + f'(m) dm50, so Cov(f(m), f(m0)) = f'(m) f'(m0) s^2 and the
    # gain at m = m0 = m50 is (f'^2 s^2)^2 / (1/4) with f' = 1/(4w): s^4 / (64 w^4).  The draws are Monte Carlo
    # (2000) and the linearisation is approximate at sd 0.05 = w/4: 25% as for the m50 gain.
    grid = np.linspace(21.0, 27.0, 601)
    curves, m = logistic_draws(grid)
    gain = variance_reduction(grid, curves, target="f", magnitudes=[24.0])
    assert gain[np.argmin(np.abs(grid - 24.0))] == pytest.approx(0.05 ** 4 / (64 * 0.2 ** 4), rel=0.25)
    # curves_at reads a grid magnitude exactly and interpolates linearly between
    i = int(np.argmin(np.abs(grid - 24.0)))
    np.testing.assert_array_equal(curves_at(grid, curves, [grid[i]])[:, 0], curves[:, i])
    mid = 0.5 * (grid[i] + grid[i + 1])
    np.testing.assert_allclose(curves_at(grid, curves, [mid])[:, 0], 0.5 * (curves[:, i] + curves[:, i + 1]))


def _two_parameter_draws(grid, n=4000, seed=0):
    """Draws of a logistic whose m50 (24 +- 0.04) and width (0.25 +- 0.02) are both uncertain."""
    rng = np.random.default_rng(seed)
    m50, w = rng.normal(24.0, 0.04, n), rng.normal(0.25, 0.02, n)
    return 1.0 / (1.0 + np.exp((grid[None, :] - m50[:, None]) / w[:, None])), m50


def test_the_f_design_moves_towards_the_chosen_magnitude():
    # With the width uncertain too, f on the shoulder (23.4 mag, f = 0.9) is learnt best near 23.4, not at m50:
    # the f design must put over twice the m50 design's share within 0.3 mag of 23.4 (measured: 42% against
    # 19%) and its gain must peak between 23.4 and m50, nearer 23.4 than the m50 gain (which peaks at 24.0).
    grid = np.linspace(21.0, 27.0, 601)
    curves, m50 = _two_parameter_draws(grid)
    at_f = design_from_draws(grid, curves, 21.0, 27.0, target="f", magnitudes=[23.4])
    at_m50 = design_from_draws(grid, curves, 21.0, 27.0, target="m50", m50=m50)
    assert at_f.target == "f"
    assert at_f.fraction_within(23.1, 23.7) > 2 * at_m50.fraction_within(23.1, 23.7)
    peak = grid[np.argmax(variance_reduction(grid, curves, target="f", magnitudes=[23.4]))]
    assert 23.4 <= peak < 23.8
    with pytest.raises(InputError, match="magnitudes"):
        variance_reduction(grid, curves, target="f")
    with pytest.raises(InputError, match="inside the curve's range"):
        variance_reduction(grid, curves, target="f", magnitudes=[27.5])


def test_design_keeps_its_uniform_share_everywhere():
    grid = np.linspace(21.0, 27.0, 301)
    curves, m = logistic_draws(grid)
    d = design_from_draws(grid, curves, 21.0, 27.0, target="m50", m50=m, uniform_share=0.15)
    assert d.prob.sum() == pytest.approx(1.0)
    # far from m50 the density is the uniform share alone: 0.15 / 6 mag
    assert d.density([21.1, 26.9]) == pytest.approx([0.15 / 6.0, 0.15 / 6.0], rel=1e-3)
    # most of the rest lies near m50
    assert d.fraction_within(23.5, 24.5) > 0.7
    # a posterior no injection can sharpen (every draw identical) gives the uniform design
    flat = design_from_draws(grid, np.repeat(curves[:1], 10, axis=0), 21.0, 27.0, target="curve")
    np.testing.assert_allclose(flat.prob, uniform_design(21.0, 27.0).prob)


def test_bad_design_inputs_are_refused():
    with pytest.raises(InputError, match="increasing"):
        MagnitudeDesign(np.array([1.0, 1.0]), np.array([1.0]))
    with pytest.raises(InputError, match="target"):
        variance_reduction(np.arange(3.0), np.ones((4, 3)), target="m90")
    with pytest.raises(InputError, match="m50"):
        variance_reduction(np.arange(3.0), np.ones((4, 3)), target="m50")
    with pytest.raises(InputError, match="precision"):
        AdaptiveSettings(precision=0.0)
    with pytest.raises(InputError, match="uniform_share"):
        AdaptiveSettings(uniform_share=1.5)
    with pytest.raises(InputError, match="needs finite magnitudes"):
        AdaptiveSettings(target="f")
    with pytest.raises(InputError, match="below 0.5"):
        AdaptiveSettings(target="f", magnitudes=(24.0,), precision=0.5)
    with pytest.raises(InputError, match="used only by target 'f'"):
        AdaptiveSettings(target="m50", magnitudes=(24.0,))


def _bench_adaptive():
    """benchmarks/bench_adaptive.py as a module."""
    return load_benchmark("bench_adaptive")


def test_a_uniform_pool_feeds_a_design_exactly_without_reuse():
    """The adaptive benchmark's pool mode: per design bin, unused uniform-magnitude pool injections have
    the design's distribution and keep their own outcomes; none is used twice; a bin that runs dry stops
    the replicate before anything is taken."""
    from scipy import stats

    B = _bench_adaptive()
    lo, hi = 24.0, 26.8
    rng = np.random.default_rng(5)
    n_pool = 120_000
    mags = rng.uniform(lo, hi, n_pool)
    f = 1.0 / (1.0 + np.exp((mags - 25.4) / 0.08))
    det = rng.random(n_pool) < f
    edges = uniform_design(lo, hi).edges
    centres = 0.5 * (edges[:-1] + edges[1:])
    prob = 0.15 / centres.size + 0.85 * np.exp(-0.5 * ((centres - 25.4) / 0.15) ** 2)
    design = MagnitudeDesign(edges, prob, target="m50", uniform_share=0.15)
    sampler = B.PoolSampler(mags, np.arange(n_pool), edges, seed=3)
    req1 = design.sample(4000, np.random.default_rng(7))
    req2 = design.sample(6000, np.random.default_rng(8))
    rows = np.concatenate([sampler.take(req1), sampler.take(req2)])
    assert np.unique(rows).size == rows.size == 10_000
    # the same count per design bin as requested, hence the design's bin probabilities
    bins = lambda m: np.clip(np.searchsorted(edges, m, side="right") - 1, 0, centres.size - 1)
    np.testing.assert_array_equal(np.bincount(bins(mags[rows]), minlength=centres.size),
                                  np.bincount(bins(np.concatenate([req1, req2])), minlength=centres.size))
    # and the design's distribution within bins too: KS against the design's CDF (seeded, so this is
    # fixed; taking pool injections at random, ignoring bins, gives p ~ 0 here)
    cdf = lambda m: np.interp(m, edges, np.concatenate([[0.0], np.cumsum(design.prob)]))
    assert stats.kstest(mags[rows], cdf).pvalue > 0.01
    assert stats.kstest(rng.choice(mags, 10_000), cdf).pvalue < 1e-6
    # outcomes come with their injections: detections match the known f at the taken magnitudes
    # (sum of Bernoulli variances ~ 2000 here; 4 sigma)
    expected, var = f[rows].sum(), (f[rows] * (1 - f[rows])).sum()
    assert abs(det[rows].sum() - expected) < 4 * math.sqrt(var)
    # a bin that cannot feed the request: refused, nothing consumed
    used = sampler.used.copy()
    with pytest.raises(B.PoolExhausted, match="needs"):
        sampler.take(np.full(5000, 25.41))
    np.testing.assert_array_equal(sampler.used, used)


def test_pool_coverage_counts_steps_past_a_size_and_widens_by_the_reference_noise():
    """The adaptive benchmark's coverage over steps past 800 injections: only those steps count, the
    posterior's own interval flags are averaged as recorded, and a reference with noise of its own widens
    each (normal) interval to sqrt(h^2 + var): an error of 1.2 h is missed at 68% alone and covered once a
    reference sd of h is added (sqrt(2) h > 1.2 h)."""
    B = _bench_adaptive()
    step = lambda n, err, h, c68, c95: {"n": n, "halfwidth": h, "cover68": c68, "cover95": c95,
                                        "scores": {"ref": {"m50_err": err}}}
    ada = [{"steps": [step(500, 0.5, 0.01, False, False),        # before 800: ignored
                      step(900, 0.012, 0.01, False, True),
                      step(1300, 0.004, 0.01, True, True)]},
           {"steps": [step(900, -0.03, 0.01, False, False),
                      step(1300, float("nan"), 0.01, False, False)]}]   # no m50: ignored
    out = B._coverage_past(ada, 800, 1e-4, "ref")
    assert out["intervals"] == 3 and out["replicates"] == 2
    assert out["cov68"] == pytest.approx(1 / 3) and out["cov95"] == pytest.approx(2 / 3)
    assert out["normal_approximation"]["cov68"] == pytest.approx(1 / 3)
    assert out["with_reference_noise"]["cov68"] == pytest.approx(2 / 3)
    # -0.03 is 3 h alone and 2.1 sqrt(2) h with the reference's noise: missed at 95% either way
    assert out["with_reference_noise"]["cov95"] == pytest.approx(2 / 3)
    assert out["error_over_halfwidth"]["mean"] == pytest.approx((1.2 + 0.4 - 3.0) / 3)
    assert B._coverage_past(ada, 5000, 0.0, "ref") == {"intervals": 0}
