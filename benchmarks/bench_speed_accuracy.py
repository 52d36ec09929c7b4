"""Speed against accuracy: what the Bayesian model buys over the binned method, at each cost.

For a range of injection budgets (a few thousand to a few hundred thousand
injections) four estimators of the completeness curve are compared:

``binned``
    the published method: 0.1-mag bins, completeness = detected / injected,
    m50 by linear interpolation at the first crossing of 0.5 (no interval
    for m50; Wilson intervals per bin for f);
``map``
    the logistic completeness model, maximum a posteriori: ``logistic`` on
    the analytic scene (uniform depth), ``logistic_depth`` on the demo tile
    (the model ``auto`` selects there: its depth varies);
``laplace``
    the same model, Gaussian approximation at the MAP (intervals from
    draws of that Gaussian);
``emcee``
    the same model, emcee posterior (to an effective sample size of 1000);
``auto``
    what a user gets by default: :func:`comest_bayes.bayes.fit.fit_kind` with
    ``--model auto`` (the ladder logistic -> logistic_depth ->
    richards_depth -> spline_depth chosen by Laplace LOO and the adequacy
    check, then the chosen model's importance-sampled posterior), called as
    the pipeline's fit stage calls it: the subset's rows of the run's
    outcome table (every column), the image shape, the mask and the
    footprint histograms and noise grid of
    :func:`comest_bayes.bayes.fit.shared_maps` computed once from the run's
    ``noise.fits`` (the detection noise map) and ``mask.fits``.  This is
    the headline model.

Every model curve is the completeness averaged over the footprint as a run
averages it: over every unmasked pixel of the run's noise map and mask (the
footprint cells of ``shared_maps``), weighted by their pixel counts.

Two scenes:

``analytic``
    point sources with a Gaussian PSF injected on pure white Gaussian
    noise.  The reference is exact: the closed-form detection probability of
    :mod:`comest_bayes.sim.analytic` (SEP's filtered-threshold semantics,
    averaged over sub-pixel positions); the benchmark also reports the m50
    of a very large injection pool, which checks the prediction.
``demo``
    the built-in demo tile (depth gradient, chip gap, real-looking galaxy
    population); the reference is a very large injection pool held out from
    the budgets: its binned curve (0.05-mag bins) and its m50 by local
    likelihood (``local_m50``, unbiased where binning is not; see
    ``bench_reference_m50.py``).

How a budget is measured.  One large pool of realizations is injected and
detected once per scene by the package's own pipeline (``run_pipeline``);
budgets are disjoint random subsets of the pool's injections, so replicates
at one budget are independent and each costs what a run of that size costs:
injection and detection CPU seconds per injection are measured on the pool
(from the per-realization timings), fitting CPU seconds are measured per fit.

Accuracy: the error of m50 against the reference; the RMS error of the whole
curve f(m) over the transition (m50 - 1.5 to m50 + 1.0 mag, on a 0.02-mag
grid); calibration, the fraction of replicates whose 68% and 95% intervals
(m50 for laplace and emcee; for every method, f at the three probe
magnitudes where the reference curve passes 0.9, 0.5 and 0.1) contain the
reference.  The headline is the relative efficiency (RMSE_binned /
RMSE_model)^2 per budget: how many times fewer injections the model needs for
the binned method's accuracy while errors fall as N^-1/2.

Outputs (``--out``, default ``benchmarks/results``): ``speed_accuracy.json``
with every number, ``speed_accuracy.png`` with the chart.  The pools are
kept under ``--work`` (default a temporary directory) and reused when the
command is repeated with the same ``--work``.

Run: ``python benchmarks/bench_speed_accuracy.py --work DIR``; a rerun with
the same ``--work`` reuses the pools; ``--quick`` for a small smoke run.  The
default pools (400 analytic and 100 demo realizations, about 920,000 and
980,000 injections) keep about 610,000 and 650,000 injections outside the
held-out third: two disjoint replicates at the largest default budget,
300,000.  ``--estimators`` runs a subset (the binned method always runs);
the other estimators' numbers already in ``--out``'s ``speed_accuracy.json``
are kept, each row marked with the command that produced it and scored
against that run's binned errors.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
from scipy.special import expit
from astropy.io import fits
from astropy.table import Table

from comest_bayes.ratios import binned as R
from comest_bayes.config import load_config
from comest_bayes.bayes.inference import fit_map, laplace, sample_posterior
from comest_bayes.bayes.model import CompletenessModel
from comest_bayes.bayes.outcomes import Covariates, compress_for, covariates_from_outcomes
from comest_bayes.bayes.spec import load_spec
from comest_bayes.pipeline.stages import ComputeOptions, ImageOptions, run_pipeline
from comest_bayes.bayes.posterior import crossing_magnitudes

HERE = Path(__file__).resolve().parent
METHODS = ("binned", "auto", "map", "laplace", "emcee")
BIN_WIDTH = 0.1          # the published method's bins (mag)
BIN_PHASES = 10          # grid offsets (0, 0.01, ..., 0.09 mag) the binned m50 is also scored at
REF_BIN_WIDTH = 0.05     # reference curve of the held-out pool (mag)
REF_LOCAL_WINDOW = 1.0   # half-width of the held-out pool's local-likelihood m50 fit, in units of its m10 - m90
REF_LOCAL_DEGREE = 4     # degree of that fit's polynomial in logit f
CURVE_WINDOW = (-1.5, 1.0)  # curve error window around the reference m50 (mag)
GRID_STEP = 0.02
PROBE_LEVELS = (0.9, 0.5, 0.1)   # f is checked where the reference curve passes these values
SUMMARY_DRAWS = 1000   # posterior draws summarised per estimate


# --------------------------------------------------------------------------- scenes


def analytic_scene(work: Path, *, size: int, sigma: float, fwhm_pix: float, zeropoint: float,
                   pixel_scale: float, seed: int) -> dict:
    """Write a pure white-noise image with a TAN WCS; return its facts."""
    path = work / "analytic_image.fits"
    if not path.exists():
        rng = np.random.default_rng(seed)
        data = (rng.standard_normal((size, size)) * sigma).astype(np.float32)
        h = fits.Header()
        h["CTYPE1"], h["CTYPE2"] = "RA---TAN", "DEC--TAN"
        h["CRPIX1"], h["CRPIX2"] = size / 2 + 0.5, size / 2 + 0.5
        h["CRVAL1"], h["CRVAL2"] = 150.0, 2.0
        h["CD1_1"], h["CD2_2"] = -pixel_scale / 3600.0, pixel_scale / 3600.0
        h["CD1_2"], h["CD2_1"] = 0.0, 0.0
        h["MAGZERO"] = zeropoint
        tmp = path.with_name(".tmp-" + path.name)
        fits.PrimaryHDU(data, h).writeto(tmp, overwrite=True)
        os.replace(tmp, path)
    return {"image": ImageOptions(path=str(path), fwhm=fwhm_pix),
            # the injected range stays within ~1.4 mag of m50 (25.40): brighter injections would raise the
            # background RMS each realization re-measures, hence its threshold, and move m50 off the closed form
            "overrides": ["injection.psf=gaussian", "detection.backend=sep", "detection.thresh=5",
                          "detection.minarea=1", "injection.mag_range=[24.0,26.8]"], "model": "logistic",
            "facts": {"sigma": sigma, "fwhm_pix": fwhm_pix, "zeropoint": zeropoint, "pixel_scale": pixel_scale,
                      "size": size}}


def demo_scene(work: Path, *, size: int, seed: int) -> dict:
    from comest_bayes.sim.demo import MASK_GAP, make_demo_tile, write_demo_tile

    d = work / "demo_tile"
    if not (d / "done").exists():
        d.mkdir(parents=True, exist_ok=True)
        paths = write_demo_tile(make_demo_tile(seed=seed, size=size), d)
        (d / "paths.json").write_text(json.dumps({k: str(v) for k, v in paths.items()}))
        (d / "done").write_text("")
    paths = json.loads((d / "paths.json").read_text())
    return {"image": ImageOptions(path=paths["image"], weight=paths["weight"], mask=paths["mask"],
                                  mask_bits=MASK_GAP),
            "overrides": [], "model": "logistic_depth", "facts": {"size": size}}


def build_pool(scene: dict, out: Path, *, nsims: int, density: float, seed: int, workers: int, log) -> dict:
    """Inject and detect ``nsims`` realizations of point sources (resumable); return the pool."""
    overrides = ["injection.kinds=point", f"injection.nsims={nsims}", f"injection.density={density}",
                 "fit.model=none", "fit.purity_model=none", *scene["overrides"]]
    config = load_config(overrides=overrides, seed=seed)
    t0 = time.perf_counter()
    run_pipeline(scene["image"], config, out, log=log,
                 compute=ComputeOptions(executor="processes" if workers > 1 else "serial", workers=workers,
                                        progress=False))
    wall = time.perf_counter() - t0
    summary = json.loads((out / "summary.json").read_text())
    state = json.loads((out / "run.json").read_text())
    outcomes = Table.read(out / "catalogs" / "point_outcomes.fits")
    # seconds per step summed over realizations (wall seconds in the worker; ``cpu``: the
    # realizations' CPU seconds, see injection_cpu)
    seconds = summary["kinds"]["point"]["seconds"]
    n_all = summary["kinds"]["point"]["counts"]["injected"]
    per_inj = {k: float(v) / max(n_all, 1) for k, v in seconds.items()}
    return {"outcomes": outcomes, "seconds_per_injection": per_inj, "wall": wall,
            "mag_range": tuple(state["stages"]["baseline"]["mag_range"]), "summary": summary}


# --------------------------------------------------------------------------- estimators


def _grid(m50_ref: float) -> np.ndarray:
    return np.arange(m50_ref + CURVE_WINDOW[0], m50_ref + CURVE_WINDOW[1] + 1e-9, GRID_STEP)


def binned_estimate(mag, det, mag_range) -> dict:
    edges = R.magnitude_edges(mag_range[0], mag_range[1], BIN_WIDTH)
    out = {}
    for conf, tag in ((0.6827, "68"), (0.9545, "95")):
        br = R.binned_ratio(mag, det, edges, confidence=conf)
        out[tag] = br
    br = out["68"]
    centers = 0.5 * (edges[:-1] + edges[1:])
    return {"edges": edges, "centers": centers, "value": np.asarray(br.ratio, float), "n": np.asarray(br.n),
            "lo68": np.asarray(out["68"].lower, float), "hi68": np.asarray(out["68"].upper, float),
            "lo95": np.asarray(out["95"].lower, float), "hi95": np.asarray(out["95"].upper, float),
            "m50": R.magnitude_at(br, 0.5)}


def binned_m50_at_phase(mag, det, mag_range, phase: float, width: float = BIN_WIDTH) -> float:
    """Binned m50 on the grid whose edges sit at ``mag_range[0] + phase + k * width``.

    ``phase`` = 0 is :func:`binned_estimate`'s grid; otherwise the first bin starts
    ``width - phase`` brighter than the injected range (partly empty, as on a grid fixed in
    advance).  When the transition is narrower than a bin, the interpolated m50's error depends
    on where the nearest edge falls relative to m50, and a user cannot choose that phase without
    knowing m50: the benchmark scores the binned method at every phase as well as at its own.
    """
    return float(R.magnitude_at(R.binned_ratio(mag, det, phase_edges(mag_range, phase, width)), 0.5))


def phase_edges(mag_range, phase: float, width: float = BIN_WIDTH) -> np.ndarray:
    """Bin edges at ``mag_range[0] + phase + k * width`` covering ``mag_range`` (0 <= phase < width)."""
    lo, hi = mag_range
    return R.magnitude_edges(lo if phase == 0 else lo + phase - width, hi, width)


def binned_curve(est: dict, grid: np.ndarray) -> np.ndarray:
    """The binned curve on ``grid`` by linear interpolation between filled bin centres."""
    ok = np.isfinite(est["value"]) & (est["n"] > 0)
    if ok.sum() < 2:
        return np.full(grid.shape, np.nan)
    return np.interp(grid, est["centers"][ok], est["value"][ok])


def _bin_of(est: dict, m: float) -> int:
    i = int(np.searchsorted(est["edges"], m, side="right") - 1)
    return min(max(i, 0), len(est["centers"]) - 1)


def run_maps(run_dir: Path, requested) -> dict:
    """What a run's fit stage takes from its maps, read from the pool's run directory.

    The detection noise map (``noise.fits``: the detection's noise, which is
    also what the outcome table's ``noise`` column samples at each true
    position) and the mask (``mask.fits``), and
    :func:`comest_bayes.bayes.fit.shared_maps` of them for the ``requested``
    models: the footprint histograms and the noise grid that the pipeline
    computes once and passes to every ``fit_kind``.  ``cpu`` is the CPU
    seconds of that one pass, which a run spends once in its fit stage.
    """
    from comest_bayes.bayes.fit import shared_maps

    noise = fits.getdata(run_dir / "noise.fits").astype(np.float32)
    mask = fits.getdata(run_dir / "mask.fits").astype(bool)
    c0 = time.process_time()
    shared = shared_maps(noise, mask, sorted(set(requested)))
    return {"shape": tuple(noise.shape), "noise": noise, "mask": mask, "shared": shared,
            "cpu": time.process_time() - c0}


def _footprint_cells(maps: dict, spec, sigma_ref):
    """The footprint cells a run's fit of ``spec`` averages over (``fit_kind`` without footprint points)."""
    from comest_bayes.bayes.fit import footprint_grid
    from comest_bayes.bayes.posterior import Footprint

    hist = maps["shared"]["footprints"][footprint_grid(spec.uses_smooth)]
    return Footprint.from_histogram(hist, sigma_ref)


def model_estimates(rows: Table, *, spec_name: str, seed: int, wide, maps: dict, methods) -> dict:
    """MAP, Laplace and (optionally) emcee of one model on one subset.

    Every estimate refers to the same quantity as the binned method: the
    completeness averaged over the footprint, f(m) = sum_c w_c f(m, d_c) over
    the footprint cells of the run's noise map and mask (what ``fit_kind``
    averages over in a run), and m50 = where that average curve crosses 0.5
    (per posterior draw).  ``rows`` are the subset's rows of the outcome
    table; the model sees the columns it uses (``mag``, ``detected`` and, for
    a model with depth, ``noise``), as in a run.
    Returns, per method in ``methods`` (of map, laplace, emcee), the draws of
    the average curve on ``wide`` (S, G), their m50 (S,) and the CPU seconds
    of the fit (cumulative: Laplace includes the MAP, emcee both).
    """
    spec = load_spec(spec_name)
    cols = {"mag": np.asarray(rows["mag"], float), "detected": np.asarray(rows["detected"], bool)}
    if spec.spatial != "none":
        cols["noise"] = np.asarray(rows["noise"], float)
    cov, outcome, meta = covariates_from_outcomes(cols, image_shape=None)
    data = compress_for(spec, cov, outcome, meta=meta)
    model = CompletenessModel(spec, data)
    rng = np.random.default_rng(seed)
    if spec.spatial == "none":
        depths, weights = np.zeros(1), np.ones(1)
    else:
        cells = _footprint_cells(maps, spec, meta["sigma_ref"])
        depths, weights = np.asarray(cells.depth, float), np.asarray(cells.weight, float)
    cov_avg = Covariates.make(m=np.repeat(wide, len(depths)), depth=np.tile(depths, len(wide)))

    def summarize(thetas, seconds):
        thetas = np.atleast_2d(thetas)
        f = np.asarray(model.prob(thetas, cov_avg)).reshape(len(thetas), len(wide), len(depths))
        curves = f @ (weights / weights.sum())
        return {"curves": curves, "m50s": crossing_magnitudes(wide, curves, 0.5), "cpu": seconds}

    res = {}
    c0 = time.process_time()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        mp = fit_map(model, seed=seed)
    t_map = time.process_time() - c0
    if "map" in methods:
        res["map"] = summarize(mp.theta, t_map)
    if "laplace" not in methods and "emcee" not in methods:
        return res
    c0 = time.process_time()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        lap = laplace(model, mp.theta)
    draws = rng.multivariate_normal(lap.mean, lap.cov, size=SUMMARY_DRAWS)
    t_lap = t_map + time.process_time() - c0
    if "laplace" in methods:
        res["laplace"] = summarize(draws, t_lap)
    if "emcee" in methods:
        c0 = time.process_time()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            post = sample_posterior(model, lap, seed=seed, min_ess=1000, max_steps=20000)
        t_mc = t_lap + time.process_time() - c0
        smp = post.samples
        smp = smp[np.linspace(0, len(smp) - 1, min(SUMMARY_DRAWS, len(smp))).astype(int)]
        res["emcee"] = summarize(smp, t_mc)
    return res


def auto_estimate(rows: Table, *, seed: int, wide, maps: dict, mag_range) -> dict:
    """The package's default fit (``auto``) of one subset, as the pipeline's fit stage makes it.

    ``rows``: the subset's rows of the run's outcome table, every column (``fit_task`` reads the
    whole table).  The footprint histograms and noise grid come from ``maps`` (:func:`run_maps`),
    as ``shared_maps`` hands them to ``fit_task``; the noise map is passed as well (``fit_task``
    hands it over as a loader): an escalated width selection builds its position cells from it.
    Returns the curves of the footprint average on ``wide``, their m50, the CPU seconds (the fit, the summary draws and the one pass over the
    maps a run makes), the chosen model and the selection table.
    """
    from comest_bayes.config import RunConfig
    from comest_bayes.bayes.fit import fit_kind

    edges = R.magnitude_edges(mag_range[0], mag_range[1], BIN_WIDTH)
    c0 = time.process_time()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        post, entry = fit_kind(rows, kind="point", quantity="completeness", requested="auto",
                               config=RunConfig(seed=int(seed)), image_shape=maps["shape"], noise=maps["noise"],
                               mask=maps["mask"], wcs_header=None, mag_range=tuple(mag_range),
                               mag_centers=0.5 * (edges[:-1] + edges[1:]),
                               footprints=maps["shared"]["footprints"], noise_grid=maps["shared"]["noise_grid"])
        curves = post.average_curve(wide, nsamples=SUMMARY_DRAWS)
    cpu = time.process_time() - c0 + maps["cpu"]
    entry = entry.to_dict()
    sel = entry.get("selection") or {}
    return {"curves": curves, "m50s": crossing_magnitudes(wide, curves, 0.5), "cpu": cpu, "chosen": entry["name"],
            "selection": sel.get("table"), "rule": sel.get("rule"), "n_cells": entry.get("n_cells")}


def probe_magnitudes(ref: dict) -> np.ndarray:
    """Magnitudes where the reference curve first falls through each of PROBE_LEVELS."""
    curve = np.asarray(ref["curve"], float)[None, :]
    return np.array([crossing_magnitudes(np.asarray(ref["grid"], float), curve, lvl)[0] for lvl in PROBE_LEVELS])


def score_model(est: dict, ref: dict, wide: np.ndarray) -> dict:
    """Errors and interval hits of one model estimate against one reference."""
    m50_ref = ref["m50"]
    grid = _grid(m50_ref)
    f_ref = np.interp(grid, ref["grid"], ref["curve"])
    probes = ref["probes"]
    f_probe_ref = np.interp(probes, ref["grid"], ref["curve"])
    curves, m50s = est["curves"], est["m50s"]
    med_curve = np.median(curves, axis=0)
    probe = np.stack([np.interp(probes, wide, c) for c in curves])
    q = lambda a, p: np.nanquantile(a, p, axis=0)
    out = {"m50_err": float(np.nanmedian(m50s)) - m50_ref if np.isfinite(m50s).any() else float("nan"),
           "curve_rms": float(np.sqrt(np.mean((np.interp(grid, wide, med_curve) - f_ref) ** 2))), "cpu": est["cpu"]}
    if len(curves) > 1:
        for lvl, lo, hi in ((68, 0.15865, 0.84135), (95, 0.02275, 0.97725)):
            out[f"m50_cover{lvl}"] = bool(q(m50s, lo) <= m50_ref <= q(m50s, hi))
            out[f"f_cover{lvl}"] = list((q(probe, lo) <= f_probe_ref) & (f_probe_ref <= q(probe, hi)))
    return out


def score_binned(b: dict, ref: dict, cpu: float) -> dict:
    """Errors and interval hits of the binned estimate against one reference."""
    m50_ref = ref["m50"]
    grid = _grid(m50_ref)
    f_ref = np.interp(grid, ref["grid"], ref["curve"])
    out = {"m50_err": b["m50"] - m50_ref, "m50_err_phases": [v - m50_ref for v in b.get("m50_phases", [])],
           "curve_rms": float(np.sqrt(np.nanmean((binned_curve(b, grid) - f_ref) ** 2))),
           "cpu": cpu, "f_cover68": [], "f_cover95": []}
    # the bins holding the probe magnitudes, against the reference averaged over each bin
    for pm in ref["probes"]:
        i = _bin_of(b, pm)
        sel = (ref["grid"] >= b["edges"][i]) & (ref["grid"] < b["edges"][i + 1])
        fr = (float(np.mean(ref["curve"][sel])) if sel.any()
              else float(np.interp(b["centers"][i], ref["grid"], ref["curve"])))
        out["f_cover68"].append(bool(b["lo68"][i] <= fr <= b["hi68"][i]))
        out["f_cover95"].append(bool(b["lo95"][i] <= fr <= b["hi95"][i]))
    return out


# --------------------------------------------------------------------------- references


def analytic_reference(facts: dict, mag_range, detection, noise_sigma: float) -> dict:
    """Exact curve of the analytic scene: the closed form of :mod:`comest_bayes.sim.analytic`.

    The closed form (peak pixel of the filtered image above DETECT_THRESH times
    the unfiltered sigma, averaged over the sub-pixel centre) is exact for
    MINAREA = 1 and a high threshold, which is why this scene detects with
    DETECT_THRESH = 5, MINAREA = 1 (docs/analytic.md: within 0.01 mag of the
    measured m50 there).  ``noise_sigma`` is the sigma the detector measured.
    """
    from comest_bayes.sim import analytic
    from comest_bayes.detect.sep_backend import filter_kernel

    grid = np.arange(mag_range[0] - 1.0, mag_range[1] + 1.0 + 1e-9, 0.005)
    kernel = filter_kernel(detection.filter)
    p = analytic.detection_probability(grid, zeropoint=facts["zeropoint"], sigma=noise_sigma,
                                       fwhm_pix=facts["fwhm_pix"], kernel=kernel, thresh=detection.thresh)
    p = np.asarray(p, float)
    m50 = analytic.predicted_m50(
        lambda m: analytic.detection_probability(m, zeropoint=facts["zeropoint"], sigma=noise_sigma,
                                                 fwhm_pix=facts["fwhm_pix"], kernel=kernel,
                                                 thresh=detection.thresh),
        lo=float(grid[0]), hi=float(grid[-1]))
    return {"grid": grid, "curve": p, "m50": float(m50), "noise_sigma": noise_sigma,
            "source": "comest_bayes.sim.analytic.detection_probability (closed form, sub-pixel average)"}


def local_m50(mag, det, center: float, *, half_width: float,
              degree: int = REF_LOCAL_DEGREE) -> tuple[float, float]:
    """m50 of unbinned outcomes by local likelihood: a polynomial in logit f near ``center``.

    The outcomes with ``|mag - center| < half_width`` are fitted by maximum likelihood (Newton's
    method) with ``logit f = sum_k b_k t^k``, ``t = (mag - center) / half_width``; m50 is the root of
    the polynomial nearest ``center``.  Returns ``(m50, sd)``, ``sd`` from the fit's Fisher
    information by the delta method.

    Why not the binned ratio: interpolating bin averages linearly puts m50 off by an amount set by
    where the grid falls when the transition is not much wider than a bin.  On the narrow
    white-noise pool that is +0.5 mmag for 0.05-mag bins (+1.7 for the published 0.1), the same
    sign as the 0.1-mag grid under test, so a binned reference forgives most of the binned method's
    own error.  The local fit has no grid; ``bench_reference_m50.py`` measures its bias and scatter
    on stand-in truths of each pool's shape.
    """
    mag = np.asarray(mag, float)
    sel = np.abs(mag - center) < half_width
    t = (mag[sel] - center) / half_width
    y = np.asarray(det, float)[sel]
    if sel.sum() < 10 * (degree + 1) or y.min() == y.max():
        return float("nan"), float("nan")
    X = np.vander(t, degree + 1, increasing=True)
    b = np.zeros(degree + 1)
    converged = False
    for _ in range(50):
        p = expit(X @ b)
        H = (X * (p * (1 - p))[:, None]).T @ X
        try:
            step = np.linalg.solve(H, X.T @ (y - p))
        except np.linalg.LinAlgError:
            break
        b = b + step
        if np.max(np.abs(step)) < 1e-10:
            converged = True
            break
    if not converged:  # outcomes separated within the window: the likelihood has no maximum, no m50
        return float("nan"), float("nan")
    roots = np.roots(b[::-1])
    roots = roots[np.abs(roots.imag) < 1e-9].real
    roots = roots[np.abs(roots) <= 1.0]
    if roots.size == 0:
        return float("nan"), float("nan")
    r = float(roots[np.argmin(np.abs(roots))])
    # delta method: d r / d b_k = -r^k / P'(r)
    dpoly = sum(k * b[k] * r ** (k - 1) for k in range(1, degree + 1))
    g = -np.array([r ** k for k in range(degree + 1)]) / dpoly
    p = expit(X @ b)
    cov = np.linalg.inv((X * (p * (1 - p))[:, None]).T @ X)
    return center + r * half_width, float(np.sqrt(g @ cov @ g)) * half_width


def pool_reference(mag, det, mag_range) -> dict:
    """The held-out pool's reference: its binned curve (0.05-mag bins) and its local-likelihood m50."""
    edges = R.magnitude_edges(mag_range[0], mag_range[1], REF_BIN_WIDTH)
    br = R.binned_ratio(mag, det, edges)
    centers = 0.5 * (edges[:-1] + edges[1:])
    ok = np.asarray(br.n) > 0
    m50_binned = float(R.magnitude_at(br, 0.5))
    grid, curve = centers[ok], np.asarray(br.ratio, float)[ok]
    m90, m10 = (float(crossing_magnitudes(grid, curve[None, :], lvl)[0]) for lvl in (0.9, 0.1))
    half_width = REF_LOCAL_WINDOW * (m10 - m90)
    m50, m50_sd = local_m50(mag, det, m50_binned, half_width=half_width)
    return {"grid": grid, "curve": curve, "m50": m50, "m50_sd": m50_sd, "m50_binned": m50_binned,
            "local_half_width": half_width,
            "source": f"{len(mag)} held-out pool injections: curve by {REF_BIN_WIDTH}-mag bins; m50 by local "
                      f"likelihood (degree-{REF_LOCAL_DEGREE} polynomial in logit f within {half_width:.3f} mag "
                      f"= {REF_LOCAL_WINDOW} x (m10 - m90) of the binned m50)"}


# --------------------------------------------------------------------------- the study


def injection_cpu(spi: dict) -> tuple[float, float]:
    """CPU seconds per injection of (injection, detection) from a pool's per-step seconds.

    The steps (make, render, detect, match) are wall seconds in the worker; ``cpu``, when the
    summary has it, is the realization's CPU time, which is then split between injection and
    detection in the proportion of their wall seconds (summing both with ``cpu`` would count
    every second twice).  Without ``cpu`` the wall seconds stand for CPU seconds.
    """
    steps = {k: float(v) for k, v in spi.items() if k != "cpu"}
    wall = sum(steps.values())
    det_share = steps.get("detect", 0.0) / wall if wall > 0 else 0.0
    total = float(spi["cpu"]) if "cpu" in spi else wall
    return total * (1.0 - det_share), total * det_share


def replicate_subsets(n: int, exclude: np.ndarray | None, *, seed: int, budget: int,
                      max_replicates: int) -> list[np.ndarray]:
    """The replicates' disjoint subsets of a pool of ``n`` injections (sorted row indices).

    One permutation of the rows not held out (``exclude``), seeded by ``seed``, cut into
    consecutive blocks of ``budget``; at most ``max_replicates`` blocks.  The same for every
    budget's first blocks, so rescoring scripts (``bench_binned_phase.py``) see the same subsets.
    """
    idx = np.arange(n) if exclude is None else np.flatnonzero(~exclude)
    idx = np.random.default_rng(seed).permutation(idx)
    nrep = min(max_replicates, len(idx) // budget)
    return [np.sort(idx[r * budget:(r + 1) * budget]) for r in range(nrep)]


def evaluate(pool: dict, refs: dict, *, spec_name: str, budgets, max_replicates: int, seed: int, emcee_max: int,
             log, maps: dict, methods=METHODS, exclude: np.ndarray | None = None, trace=None) -> dict:
    """Errors, calibration and costs per reference, method and budget.

    Returns ``{ref_name: {budget: {method: numbers}}}``; the fits are done
    once per replicate and scored against every reference.  ``methods``: the
    estimators to run (the binned method always runs).  Each row keeps the
    replicates' m50 errors (``m50_errors``), so bias and scatter can be read
    apart; ``auto`` keeps the model chosen per replicate.  ``trace``: a
    callable given one dict per replicate (m50 of every estimate, auto's
    selection table), for a closer look at a budget.
    """
    out = pool["outcomes"]
    mag = np.asarray(out["mag"], float)
    det = np.asarray(out["detected"], bool)
    fitted = [m for m in ("map", "laplace", "emcee") if m in methods]
    for r in refs.values():
        r["probes"] = probe_magnitudes(r)
    m50s = [r["m50"] for r in refs.values()]
    wide = np.arange(min(m50s) + CURVE_WINDOW[0] - 1.0, max(m50s) + CURVE_WINDOW[1] + 1.0 + 1e-9, GRID_STEP)
    inj_cost, det_cost = injection_cpu(pool["seconds_per_injection"])
    results = {name: {} for name in refs}
    for budget in budgets:
        subsets = replicate_subsets(len(mag), exclude, seed=seed, budget=budget, max_replicates=max_replicates)
        nrep = len(subsets)
        if nrep < 1:
            log(f"  budget {budget}: pool too small, skipped")
            continue
        scores = {name: {m: [] for m in METHODS} for name in refs}
        chosen = []
        t0 = time.perf_counter()
        for r, sub in enumerate(subsets):
            rows = out[sub]
            c0 = time.process_time()
            b = binned_estimate(mag[sub], det[sub], pool["mag_range"])
            t_b = time.process_time() - c0
            b["m50_phases"] = [b["m50"]] + [binned_m50_at_phase(mag[sub], det[sub], pool["mag_range"],
                                                                k * BIN_WIDTH / BIN_PHASES)
                                            for k in range(1, BIN_PHASES)]
            rseed = seed + 1000 * r + budget
            est = {}
            if fitted:
                est.update(model_estimates(rows, spec_name=spec_name, seed=rseed, wide=wide, maps=maps,
                                           methods=[m for m in fitted if m != "emcee" or r < emcee_max]))
            if "auto" in methods:
                est["auto"] = auto_estimate(rows, seed=rseed, wide=wide, maps=maps, mag_range=pool["mag_range"])
                chosen.append(est["auto"]["chosen"])
            if trace is not None:
                trace({"budget": budget, "replicate": r, "seed": rseed, "binned_m50": b["m50"],
                       **{f"{m}_m50": float(np.nanmedian(e["m50s"])) for m, e in est.items()},
                       **({} if "auto" not in est else
                          {k: est["auto"][k] for k in ("chosen", "rule", "selection", "n_cells")})})
            for name, ref in refs.items():
                scores[name]["binned"].append(score_binned(b, ref, t_b))
                for m, e in est.items():
                    scores[name][m].append(score_model(e, ref, wide))
        for name in refs:
            row = {}
            for m, lst in scores[name].items():
                if not lst:
                    continue
                err = np.array([d["m50_err"] for d in lst], float)
                cpu_fit = float(np.mean([d["cpu"] for d in lst]))
                frac = lambda key: _frac([d[key] for d in lst if key in d])
                row[m] = {
                    "replicates": int(len(err)),
                    "m50_rmse": float(np.sqrt(np.nanmean(err ** 2))),
                    "m50_bias": float(np.nanmean(err)),
                    "m50_sd": float(np.nanstd(err, ddof=1)) if np.isfinite(err).sum() > 1 else None,
                    "m50_failed": int(np.sum(~np.isfinite(err))),
                    "m50_errors": [float(v) for v in err],
                    "curve_rmse": float(np.sqrt(np.nanmean(np.square([d["curve_rms"] for d in lst])))),
                    "cpu_inject": budget * inj_cost,
                    "cpu_detect": budget * det_cost,
                    "cpu_fit": cpu_fit,
                    "cpu_total": budget * (inj_cost + det_cost) + cpu_fit,
                    "m50_coverage68": frac("m50_cover68"),
                    "m50_coverage95": frac("m50_cover95"),
                    "f_coverage68": frac("f_cover68"),
                    "f_coverage95": frac("f_cover95"),
                }
            phase_err = np.array([d["m50_err_phases"] for d in scores[name]["binned"]], float)
            if phase_err.size:
                # mean squared error over replicates and grid phases (see binned_m50_at_phase)
                row["binned"]["m50_rmse_phase_averaged"] = float(np.sqrt(np.nanmean(phase_err ** 2)))
                row["binned"]["m50_rmse_per_phase"] = [float(v) for v in np.sqrt(np.nanmean(phase_err ** 2, axis=0))]
            if "auto" in row:
                row["auto"]["chosen"] = {c: chosen.count(c) for c in sorted(set(chosen))}
                row["auto"]["chosen_per_replicate"] = list(chosen)
            results[name][str(budget)] = row
            log(f"  budget {budget:>7d} vs {name}: {nrep} replicates ({time.perf_counter() - t0:.0f} s); m50 RMSE "
                + ", ".join(f"{m} {row[m]['m50_rmse']:.4f}" for m in row)
                + ("" if "auto" not in row else
                   f"; auto bias {row['auto']['m50_bias']:+.4f}, chose "
                   + ", ".join(f"{c} x{k}" for c, k in row["auto"]["chosen"].items())
                   + f"; fit CPU auto {row['auto']['cpu_fit']:.1f} s"))
    return results


def _fmt(v) -> str:
    return "n/a" if v is None else f"{v:.2f}"


def _frac(values) -> float | None:
    a = np.asarray(values, bool).ravel()
    return None if a.size == 0 else float(a.mean())


def headline(results: dict) -> dict:
    """Relative efficiency of each model estimate against the binned method, per budget.

    ``efficiency = (RMSE_binned / RMSE_model)^2``.  For estimators whose error
    falls as N^-1/2 this is how many times more injections the binned method
    needs for the model's accuracy (equivalently, the model reaches the binned
    method's accuracy with 1/efficiency of its injections).  Given for m50 and
    for the whole curve.  Where an error stops falling with N (a bias floor of
    the model's shape, or of the reference), the ratio no longer converts into
    injections, and the JSON keeps the RMSEs to show it.  A row kept from an
    earlier run (``earlier_run``, see :func:`merge_earlier`) is compared with
    that run's binned errors, not with this run's.
    """
    out = {}
    for model in ("auto", "map", "laplace", "emcee"):
        rows = []
        for b in sorted(int(k) for k in results):
            row = results[str(b)]
            if model not in row or "binned" not in row:
                continue
            rb, rm = row.get(model, {}).get("earlier_run", {}).get("binned") or row["binned"], row[model]
            eff = lambda key: (float((rb[key] / rm[key]) ** 2)
                               if rm[key] and np.isfinite(rm[key]) and np.isfinite(rb[key]) else None)
            rows.append({"budget": b, "replicates": rm["replicates"], "binned_m50_rmse": rb["m50_rmse"],
                         **({"earlier_run": rm["earlier_run"]["command"]} if "earlier_run" in rm else {}),
                         "model_m50_rmse": rm["m50_rmse"], "m50_efficiency": eff("m50_rmse"),
                         **({} if "earlier_run" in rm or not rb.get("m50_rmse_phase_averaged") else
                            {"binned_m50_rmse_phase_averaged": rb["m50_rmse_phase_averaged"],
                             "m50_efficiency_phase_averaged": float((rb["m50_rmse_phase_averaged"]
                                                                     / rm["m50_rmse"]) ** 2)}),
                         "binned_curve_rmse": rb["curve_rmse"], "model_curve_rmse": rm["curve_rmse"],
                         "curve_efficiency": eff("curve_rmse")})
        out[model] = rows
    return out


def merge_earlier(report: dict, earlier: dict, methods) -> dict:
    """Keep the rows of the estimators this run did not run from an earlier ``speed_accuracy.json``.

    A kept row is marked ``earlier_run``: the earlier command, its pool size and the binned errors
    of that run at the same budget (its own pool and subsets), which its efficiency is computed
    against.  A scene this run did not evaluate is kept whole.  The headline is recomputed.
    """
    cmd = earlier.get("command")
    for m, text in earlier.get("methods", {}).items():
        if m not in methods:
            report["methods"][m] = text if "numbers from" in text else f"{text} (numbers from the earlier run: {cmd})"
    for scene, old in earlier.get("scenes", {}).items():
        new = report["scenes"].get(scene)
        if new is None:
            report["scenes"][scene] = {**old, "earlier_run": old.get("earlier_run", cmd)}
            continue
        scene_cmd = old.get("earlier_run", cmd)  # a scene kept whole by a merge names the run that made it
        for ref, res in old.get("results", {}).items():
            if ref not in new["results"]:
                continue
            for b, row in res.items():
                target = new["results"][ref].setdefault(b, {})
                for m, numbers in row.items():
                    if m == "binned" or m in methods or m in target:
                        continue
                    if "earlier_run" in numbers:
                        target[m] = numbers
                        continue
                    ob = row.get("binned") or {}
                    target[m] = {**numbers, "earlier_run": {
                        "command": scene_cmd, "pool_injections": old.get("pool_injections"),
                        "binned": {k: ob.get(k) for k in ("replicates", "m50_rmse", "curve_rmse")}}}
        new["headline"] = {k: headline(v) for k, v in new["results"].items()}
    return report


def chart(report: dict, path: Path) -> None:
    """Three rows per scene: m50 error and curve error against CPU seconds, and interval coverage."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    scenes = [s for s in ("analytic", "demo") if s in report["scenes"]]
    fig, axes = plt.subplots(3, len(scenes), figsize=(5.6 * len(scenes), 12), squeeze=False)
    colors = {"binned": "0.25", "auto": "tab:red", "map": "tab:blue", "laplace": "tab:orange", "emcee": "tab:green"}
    markers = {"binned": "s", "auto": "*", "map": "o", "laplace": "^", "emcee": "D"}
    for j, scene in enumerate(scenes):
        info = report["scenes"][scene]
        primary = info["primary_reference"]
        for ref_name, res in info["results"].items():
            main_ref = ref_name == primary
            budgets = sorted(int(b) for b in res)
            for m in METHODS:
                rows = [(b, res[str(b)][m]) for b in budgets if m in res[str(b)]]
                if not rows:
                    continue
                bb = np.array([b for b, _ in rows])
                get = lambda key: np.array([np.nan if r[key] is None else r[key] for _, r in rows], float)
                cpu = get("cpu_total")
                style = dict(color=colors[m], marker=markers[m], ms=5 if main_ref else 3)
                if any("earlier_run" in r for _, r in rows):
                    style.update(alpha=0.5)
                    m_label = f"{m} (earlier run)"
                else:
                    m_label = m
                if main_ref:
                    axes[0, j].loglog(cpu, get("m50_rmse"), label=m_label, **style)
                    axes[1, j].loglog(cpu, get("curve_rmse"), label=m_label, **style)
                    if m != "binned":
                        axes[2, j].semilogx(bb, get("m50_coverage68"), ls="-", label=f"{m_label}: m50", **style)
                    axes[2, j].semilogx(bb, get("f_coverage68"), ls=":", mfc="none",
                                        label=f"{m_label}: f at 3 probes", **style)
                    if m == "binned" and all(r.get("m50_rmse_phase_averaged") for _, r in rows):
                        axes[0, j].loglog(cpu, get("m50_rmse_phase_averaged"), ls=":", color=colors[m], marker="s",
                                          mfc="none", ms=5, label=f"binned, averaged over {BIN_PHASES} grid offsets")
                    if m == "binned":
                        for x, y, b in zip(cpu, get("m50_rmse"), bb):
                            axes[0, j].annotate(f"{b // 1000}k" if b >= 1000 else str(b), (x, y), fontsize=7,
                                                xytext=(-4, -11), textcoords="offset points", color=colors[m])
                elif m in ("binned", "emcee"):
                    axes[0, j].loglog(cpu, get("m50_rmse"), ls="--", lw=1,
                                      label=f"{m_label} vs {ref_name}", **{"alpha": 0.5, **style})
        refs = info["references"]
        title = (f"{scene} scene, model {info['model']}\nreference: {primary}, m50 = {refs[primary]['m50']:.3f}")
        if len(refs) > 1:
            other = [k for k in refs if k != primary][0]
            title += f" ({other}: {refs[other]['m50']:.3f})"
        axes[0, j].set_title(title, fontsize=10)
        for row in (0, 1):
            axes[row, j].set_xlabel("CPU seconds per estimate (injection + detection + fit)")
        axes[0, j].set_ylabel("RMS error of m50 (mag)")
        axes[1, j].set_ylabel("RMS error of f(m), m50-1.5 to m50+1 mag")
        axes[2, j].axhline(0.6827, color="k", lw=0.8)
        axes[2, j].set_ylim(0, 1.05)
        axes[2, j].set_xlabel("injections per estimate")
        axes[2, j].set_ylabel("coverage of the 68% intervals")
        for ax in axes[:, j]:
            ax.xaxis.set_major_formatter(matplotlib.ticker.FuncFormatter(lambda v, _: f"{v:g}"))
            ax.grid(alpha=0.3, which="both")
            ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenes", default="analytic,demo")
    p.add_argument("--budgets", default="1000,2000,5000,10000,30000,100000,300000")
    p.add_argument("--estimators", default=",".join(METHODS),
                   help="estimators to run (binned always runs); the others' rows already in --out are kept")
    p.add_argument("--replicates", type=int, default=16, help="max replicates per budget (disjoint subsets)")
    p.add_argument("--emcee-replicates", type=int, default=8, help="replicates per budget that run emcee")
    p.add_argument("--analytic-nsims", type=int, default=400)
    p.add_argument("--analytic-range", choices=("narrow", "auto"), default="narrow",
                   help="analytic scene's injected range: 'narrow' = 24.0-26.8 (within ~1.4 mag of m50, so that the "
                        "closed form applies), 'auto' = the range a default run chooses (m5 - 5 to m5 + 1.5; the "
                        "pool goes to <work>/analytic_autorange_run, and only the held-out pool is a reference: "
                        "bright injections raise the re-measured background and move m50 off the closed form)")
    p.add_argument("--demo-nsims", type=int, default=100)
    p.add_argument("--analytic-density", type=float, default=50.0,
                   help="injections per arcmin^2 per realization, analytic scene")
    p.add_argument("--demo-density", type=float, default=60.0, help="injections per arcmin^2 per realization, demo")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--seed", type=int, default=11)
    p.add_argument("--work", default=None, help="directory for the pools (kept; reused on a rerun)")
    p.add_argument("--out", default=str(HERE / "results"))
    p.add_argument("--quick", action="store_true", help="small smoke run")
    a = p.parse_args(argv)
    if a.quick:
        a.budgets, a.replicates, a.emcee_replicates = "1000,3000", 3, 2
        a.analytic_nsims, a.demo_nsims = 4, 4
    budgets = [int(b) for b in a.budgets.split(",")]
    methods = ["binned", *(m for m in a.estimators.split(",") if m and m != "binned")]
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        raise SystemExit(f"unknown estimator(s) {unknown}: choose among {list(METHODS)}")
    work = Path(a.work) if a.work else Path(tempfile.mkdtemp(prefix="speed_accuracy_"))
    work.mkdir(parents=True, exist_ok=True)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    log = lambda s: print(s, flush=True)
    report = {"command": " ".join([Path(sys.argv[0]).name, *(argv if argv is not None else sys.argv[1:])]),
              "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version()},
              "methods": {"binned": f"{BIN_WIDTH} mag bins, m50 by linear interpolation at the first 0.5 crossing",
                          "map": "logistic model (per scene), MAP, averaged over the run's footprint cells",
                          "laplace": "same model, Laplace approximation",
                          "emcee": "same model, emcee to ESS >= 1000",
                          "auto": "the default fit: fitting.fit_kind with --model auto (selection, then the chosen "
                                  "model's importance-sampled posterior), given the run's outcome rows, mask and "
                                  "fitting.shared_maps of its noise.fits and mask.fits, as the pipeline's fit stage"},
              "estimators_run": methods,
              "definition": "f(m) is the completeness averaged over the footprint; m50 is where it crosses 0.5; "
                            "model curves are averaged over every unmasked pixel of the run's noise map and mask "
                            "(the footprint cells a run's fit averages over), per draw",
              "scenes": {}}
    for scene in a.scenes.split(","):
        log(f"{scene}: building the injection pool in {work / scene}")
        auto_range = scene == "analytic" and a.analytic_range == "auto"
        if scene == "analytic":
            sc = analytic_scene(work, size=2048, sigma=1.0, fwhm_pix=3.0, zeropoint=30.0, pixel_scale=0.2,
                                seed=a.seed)
            if auto_range:
                sc = {**sc, "overrides": [o for o in sc["overrides"] if not o.startswith("injection.mag_range")]}
            pool = build_pool(sc, work / ("analytic_autorange_run" if auto_range else "analytic_run"),
                              nsims=a.analytic_nsims, density=a.analytic_density, seed=a.seed, workers=a.workers,
                              log=lambda s: None)
        elif scene == "demo":
            sc = demo_scene(work, size=3000, seed=a.seed)
            pool = build_pool(sc, work / "demo_run", nsims=a.demo_nsims, density=a.demo_density, seed=a.seed,
                              workers=a.workers, log=lambda s: None)
        else:
            raise SystemExit(f"unknown scene {scene!r}: use analytic and/or demo")
        o = pool["outcomes"]
        # a third of the realizations is held out as the empirical reference; budgets draw from the rest
        held = np.asarray(o["realization"]) % 3 == 0
        refs = {"held-out pool": pool_reference(np.asarray(o["mag"])[held], np.asarray(o["detected"])[held],
                                                pool["mag_range"])}
        primary = "held-out pool"
        if scene == "analytic" and not auto_range:
            detection = load_config(overrides=sc["overrides"]).detection
            noise_sigma = float(np.median(fits.getdata(work / "analytic_run" / "noise.fits")))
            refs = {"closed form": analytic_reference(sc["facts"], pool["mag_range"], detection, noise_sigma),
                    **refs}
            primary = "closed form"
        n = len(o)
        log(f"{scene}: pool of {n} injections ({int(held.sum())} held out) in {pool['wall']:.0f} s wall; per "
            "injection " + ", ".join(f"{k} {1e3 * v:.3f} ms" for k, v in pool["seconds_per_injection"].items())
            + "; reference m50: " + ", ".join(f"{k} {r['m50']:.3f}" for k, r in refs.items()))
        run_dir = work / ("analytic_autorange_run" if auto_range else f"{scene}_run")
        maps = run_maps(run_dir, ["auto", sc["model"]])
        trace_path = work / f"trace_{scene}.jsonl"
        with open(trace_path, "w") as trace_file:
            trace = lambda d: trace_file.write(json.dumps(d, default=float) + "\n")
            results = evaluate(pool, refs, spec_name=sc["model"], budgets=budgets, max_replicates=a.replicates,
                               seed=a.seed, emcee_max=a.emcee_replicates, log=log, maps=maps, methods=methods,
                               exclude=held, trace=trace)
        log(f"{scene}: per-replicate m50s and auto's selection tables in {trace_path}")
        report["scenes"][scene] = {
            "facts": sc["facts"], "model": sc["model"], "pool_injections": n, "held_out": int(held.sum()),
            "pool_wall_seconds": pool["wall"], "seconds_per_injection": pool["seconds_per_injection"],
            "mag_range": list(pool["mag_range"]), "primary_reference": primary,
            "footprint": {"image_shape": list(maps["shape"]), "unmasked_pixels": int((~maps["mask"]).sum()),
                          "shared_maps_cpu": maps["cpu"]},
            "references": {k: {**{kk: vv for kk, vv in r.items() if kk not in ("grid", "curve", "probes")},
                               "probe_levels": list(PROBE_LEVELS), "probe_mags": [float(v) for v in r["probes"]]}
                           for k, r in refs.items()},
            "results": results, "headline": {k: headline(v) for k, v in results.items()}}
    earlier_path = out / "speed_accuracy.json"
    if earlier_path.exists():
        report = merge_earlier(report, json.loads(earlier_path.read_text()), methods)
    (out / "speed_accuracy.json").write_text(json.dumps(report, indent=1, default=float))
    chart(report, out / "speed_accuracy.png")
    log(f"wrote {out / 'speed_accuracy.json'} and {out / 'speed_accuracy.png'}")
    for scene, s in report["scenes"].items():
        for model, rows in s["headline"][s["primary_reference"]].items():
            if model == "laplace":
                continue
            log(f"{scene} vs {s['primary_reference']}, {model}: relative efficiency (binned RMSE / model RMSE)^2 "
                "per budget, m50 | curve: " + "; ".join(
                    f"{r['budget']}: {_fmt(r['m50_efficiency'])} | {_fmt(r['curve_efficiency'])}" for r in rows))
            if any("m50_efficiency_phase_averaged" in r for r in rows):
                log(f"  {model}'s m50 efficiency against the binned m50 averaged over {BIN_PHASES} grid phases: "
                    + "; ".join(f"{r['budget']}: {_fmt(r.get('m50_efficiency_phase_averaged'))}" for r in rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
