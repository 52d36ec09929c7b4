"""Fit the completeness and purity models of one source kind (orchestration of the numerics).

From the per-injection outcome table (and the matched and false detections for purity) to a
saved :class:`~comest_bayes.bayes.posterior.CompletenessPosterior` and the JSON-ready entry that
``summary.json`` gains under ``kinds.<kind>.model`` and ``kinds.<kind>.purity_model``.  The
entry's format: ``docs/ratios.md``; the fit itself: ``docs/bayesian.md``.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field

import numpy as np
from astropy.table import Table

from comest_bayes.ratios import binned as R
from comest_bayes.bayes.checks import (CovariateCheck, ShapeCheck, cell_probabilities, covariate_check, covariate_warning,
                                      shape_check, shape_warning, thin_draws)
from comest_bayes.config import RunConfig
from comest_bayes.errors import InputError
from comest_bayes.bayes.inference import IdentifiabilityWarning, fit, fit_map
from comest_bayes.bayes.model import CompletenessModel
from comest_bayes.bayes.outcomes import (compress_for, covariate_warnings, covariates_from_outcomes,
                                         covariates_needed)
from comest_bayes.bayes.spec import load_spec, resolve_candidates, resolve_width_candidates
from comest_bayes.bayes.posterior import (CompletenessPosterior, Footprint, FootprintHistogram, average_crossings, average_prob, coarse_noise_map, footprint_sample)
from comest_bayes.seeding import Stream, int_seed_for, rng_for
from comest_bayes.bayes.selection import WIDTH_TEST_P, choose_tau, select_model, width_position_test

__all__ = ["fit_kind", "FitEntry", "purity_outcomes", "warm_state", "shared_maps", "footprint_grid", "needs_smooth",
           "MIN_OUTCOMES", "MIN_CLASS"]

#: Fewer usable outcomes than this: the fit still runs but warns that the prior dominates.
MIN_OUTCOMES = 20
#: Offset of the probe magnitudes of the targeted quantities from the data's m50 (mag).
PROBE_OFFSET = 0.3


@dataclass(frozen=True)
class FitEntry:
    """What the fit of one kind and quantity reports: the ``summary.json`` entry before files are added.

    :func:`fit_kind` makes it; the fit stage adds its CPU time (``cpu_seconds``), the adaptive
    design whether the fit was a warm refit (``warm_refit``), and a fit that was not run is
    ``skipped``.  :meth:`to_dict` is the JSON form, to which the caller adds the names of the files
    it wrote (``posterior_file``, ``m50_map_file``, ``footprint``; ``docs/ratios.md``).

    Attributes
    ----------
    name : str or None
        The fitted model (the chosen one of a selection); None when skipped.
    requested : str
        The model or selection asked for.
    selection : dict or None
        The selection's table and rule (:meth:`SelectionResult.to_dict` without its diagnostics);
        None for one model.
    magnitudes : dict
        ``{"m50": {...}, "m80": {...}, "m90": {...}}``: medians and 68% / 95% intervals
        (:meth:`CompletenessPosterior.summary_magnitudes`); their keys are top-level keys of the
        JSON form.
    parameters : dict
        Per physical parameter, ``median``, ``lo68``, ``hi68``.
    curve : dict
        The posterior curve on the run's magnitude bin centres (lists of floats).
    diagnostics : dict
        The sampler's diagnostics (``PosteriorDiagnostics.to_dict``); empty without sampling.
    tau : float or None
        The spline's smoothness; None for other links.
    shape_check : ShapeCheck or None
        The posterior predictive check per magnitude bin.
    covariate_check : CovariateCheck or None
        The same check per tile of the image and per depth bin.
    warnings : tuple of str
        What the fit warned about.
    n_outcomes, n_cells : int or None
        Outcomes fitted, and the binomial cells they were compressed into.
    seconds : float or None
        Wall time of the fit.
    warm_refit : bool or None
        Adaptive design fits only: refitted from the previous posterior (not in the JSON form when None).
    cpu_seconds : float or None
        CPU time of the fit task (not in the JSON form when None).
    skipped : str or None
        Why no model was fitted; the JSON form is then ``name``, ``requested``, ``cpu_seconds`` and this.
    """

    name: str | None
    requested: str
    selection: dict | None = None
    magnitudes: dict = field(default_factory=dict)
    parameters: dict = field(default_factory=dict)
    curve: dict = field(default_factory=dict)
    diagnostics: dict = field(default_factory=dict)
    tau: float | None = None
    shape_check: ShapeCheck | None = None
    covariate_check: CovariateCheck | None = None
    warnings: tuple[str, ...] = ()
    n_outcomes: int | None = None
    n_cells: int | None = None
    seconds: float | None = None
    warm_refit: bool | None = None
    cpu_seconds: float | None = None
    skipped: str | None = None

    def to_dict(self) -> dict:
        """The JSON form: ``kinds.<kind>.model`` (or ``purity_model``) of ``summary.json``, without file names."""
        if self.skipped is not None:
            return {"name": self.name, "requested": self.requested,
                    **({} if self.cpu_seconds is None else {"cpu_seconds": self.cpu_seconds}), "skipped": self.skipped}
        out = {"name": self.name, "requested": self.requested, "selection": self.selection, **self.magnitudes,
               "parameters": self.parameters, "curve": self.curve, "diagnostics": self.diagnostics, "tau": self.tau,
               "shape_check": None if self.shape_check is None else self.shape_check.to_dict(),
               "covariate_check": None if self.covariate_check is None else self.covariate_check.to_dict(),
               "warnings": list(self.warnings), "n_outcomes": self.n_outcomes, "n_cells": self.n_cells,
               "seconds": self.seconds}
        if self.warm_refit is not None:
            out["warm_refit"] = self.warm_refit
        if self.cpu_seconds is not None:
            out["cpu_seconds"] = self.cpu_seconds
        return out


def purity_outcomes(matched: Table, false: Table, mag_column: str = "mag_auto") -> Table:
    """One row per counted detection: measured position and magnitude, ``real`` (matched) or not."""
    mm = np.asarray(matched[f"det_{mag_column}"], float)
    fm = np.asarray(false[mag_column], float)
    if mm.ndim == 2:
        mm = mm[:, 0]
    if fm.ndim == 2:
        fm = fm[:, 0]
    return Table({
        "x": np.concatenate([np.asarray(matched["det_xwin"], float), np.asarray(false["xwin"], float)]),
        "y": np.concatenate([np.asarray(matched["det_ywin"], float), np.asarray(false["ywin"], float)]),
        "mag": np.concatenate([mm, fm]),
        "real": np.concatenate([np.ones(len(mm), bool), np.zeros(len(fm), bool)]),
    })


def _param_summary(model: CompletenessModel, draws: np.ndarray) -> dict:
    phys = model.transform(draws)
    out = {}
    for name, values in phys.items():
        values = np.atleast_1d(np.asarray(values, float))
        q = np.percentile(values, [16, 50, 84])
        out[name] = {"median": float(q[1]), "lo68": float(q[0]), "hi68": float(q[2])}
    return out


def _json_curve(curve: dict) -> dict:
    return {k: [bool(v) if k == "extrapolated" else float(v) for v in np.asarray(arr)] for k, arr in curve.items()}


#: A purity model needs at least this many detections of each class (real and false); with fewer,
#: the binned purity and its binomial interval say all there is to say.
MIN_CLASS = 25


def _probe_magnitudes(m: np.ndarray, detected: np.ndarray) -> tuple[float, float]:
    """A rough m50 of the outcomes (0.1-mag bins, first fall below half) -+ PROBE_OFFSET."""
    lo, hi = float(np.min(m)), float(np.max(m))
    edges = np.arange(lo, hi + 0.1, 0.1)
    if edges.size < 3:
        mid = 0.5 * (lo + hi)
    else:
        n, _ = np.histogram(m, edges)
        k, _ = np.histogram(m[detected], edges)
        with np.errstate(invalid="ignore", divide="ignore"):
            frac = np.where(n > 0, k / np.maximum(n, 1), np.nan)
        top = np.nanmax(frac) if np.isfinite(frac).any() else 1.0
        below = np.flatnonzero(frac < 0.5 * top)
        mid = float(0.5 * (edges[below[0]] + edges[below[0] + 1])) if below.size else 0.5 * (lo + hi)
    return mid - PROBE_OFFSET, mid + PROBE_OFFSET


#: Position blocks per axis of the cells an escalated width selection fits: a plane in log w
#: needs little spatial resolution, and 8 x 8 blocks hold about a quarter of the 16 x 16 cells.
WIDTH_NUV = 8


def targeted_quantities(cells: Footprint, probes, lo: float, hi: float):
    """The quantities the selection's adequacy check compares: ``(model, draws) -> {name: (S,)}``.

    The image-average m50 and m90 (exact over the footprint) and the
    image-average f at the two probe magnitudes.
    """
    def fn(model, draws):
        cross = average_crossings(model, draws, cells, (0.5, 0.9), lo, hi)
        f = average_prob(model, draws, np.asarray(probes, float), cells)
        return {"m50": cross[0.5], "m90": cross[0.9], "f_bright": f[:, 0], "f_faint": f[:, 1]}
    return fn


def footprint_grid(smooth: bool) -> tuple[float, int]:
    """``(ddepth, nuv)`` of the footprint cells of a fit: finer in depth without a term in the image
    coordinates (smooth m50 or positional width), 8 x 8 position blocks with one."""
    return (0.02, 8) if smooth else (0.01, 1)


def needs_smooth(requested: str) -> bool:
    """Whether the model (or any candidate of the selection) ``requested`` has a term in the image
    coordinates (smooth m50 or positional width; the width candidates of a selection are fitted only
    when its width test asks, and take their footprint cells then)."""
    spec = load_spec(requested)
    return any(c.uses_position for c in (resolve_candidates(spec) if spec.is_selection else [spec]))


def footprint_histograms(noise: np.ndarray | None, mask: np.ndarray, requested) -> dict:
    """The footprint histograms the fits of ``requested`` models need, keyed by ``(ddepth, nuv)``.

    One pass over the pixels per grid (about half a second on 3000 x 3000), shared by every kind
    and quantity of a run instead of repeated by each fit.
    """
    grids = {footprint_grid(needs_smooth(r)) for r in requested}
    return {g: FootprintHistogram.from_maps(noise, mask, ddepth=g[0], nuv=g[1]) for g in sorted(grids)}


def shared_maps(noise: np.ndarray, mask: np.ndarray, requested) -> dict:
    """What every fit of a run takes from its noise map and mask: footprint histograms and the noise grid.

    Small arrays (a few thousand cells), cheap to send to the fit workers; computing them once
    instead of in each fit saves about a second per fit on a 3000 x 3000 image.
    """
    return {"footprints": footprint_histograms(noise, mask, requested), "noise_grid": coarse_noise_map(noise, mask)}


def warm_state(post: CompletenessPosterior) -> dict:
    """What a warm refit of the same model needs: parameter names, the posterior median, the spline's tau."""
    return {"model": post.spec.name, "names": list(post.names),
            "theta": [float(v) for v in np.median(np.asarray(post.samples, float), axis=0)],
            "tau": None if post.meta.get("tau") is None else float(post.meta["tau"])}


def _on_demand(noise):
    """``noise`` (an array, None, or a zero-argument loader of the array) as a function that gives the
    array, calling a loader at most once and only when asked."""
    if not callable(noise):
        return lambda: noise
    got = []

    def get():
        if not got:
            got.append(noise())
        return got[0]
    return get


def fit_kind(outcomes: Table, *, kind: str, quantity: str, requested: str, config: RunConfig, image_shape,
             noise, mask: np.ndarray, wcs_header: str | None, mag_range, mag_centers,
             outcome_column: str = "detected", footprint_points=None, warm: dict | None = None,
             footprints: dict | None = None, noise_grid: np.ndarray | None = None,
             products: bool = True, map_starts: int = 6, most_flexible: bool = False,
             log=lambda s: None) -> tuple[CompletenessPosterior, FitEntry]:
    """Fit (or select and fit) the model of one kind and quantity.

    Parameters
    ----------
    outcomes : Table
        Rows with ``mag``, ``outcome_column`` and optionally ``x``, ``y``,
        ``noise``, ``hlr_arcsec``.
    kind, quantity : str
        Source kind and ``"completeness"`` or ``"purity"`` (names the seed stream).
    requested : str
        Spec name or path, or a selection spec such as ``auto``.
    noise : ndarray, or a callable returning it
        Detection noise map of the image (depth covariate, footprint).  A
        zero-argument callable is called only when a footprint histogram or
        the noise grid must be computed here (not given in ``footprints`` /
        ``noise_grid``): e.g. when a selection escalates to a positional
        width, whose position-resolved cells a run does not compute upfront.
    mask : ndarray
        Mask of the image.
    footprint_points : (x, y, noise) arrays, optional
        Average over these positions instead of every unmasked pixel of the
        maps (:meth:`Footprint.from_points`; e.g. the injections themselves
        when no noise map is known).
    warm : dict, optional
        A refit of the same kind with more data (the adaptive design's next
        batch): ``{"names": [...], "theta": [...], "tau": float | None}``
        from the previous posterior (:func:`warm_state`).  ``requested``
        must then name one model (no selection); the MAP starts from
        ``theta`` with Newton steps and a spline keeps the previous ``tau``.
    footprints : dict, optional
        Footprint histograms of ``noise`` and ``mask`` already computed
        (:func:`footprint_histograms`, keyed by ``(ddepth, nuv)``): the one
        pass over the pixels that every fit of a run shares.  A histogram
        computed here because it is absent (e.g. the position blocks of an
        escalated width selection) is added to the dict, so a caller that
        fits again with the same dict (the adaptive design's refits) makes
        that pass once.
    noise_grid : ndarray, optional
        :func:`~comest_bayes.bayes.posterior.coarse_noise_map` of the maps, likewise.
    products : bool, default True
        Compute the entry's summaries (m50/m80/m90 intervals, the curve on ``mag_centers``, the
        shape check).  False for a fit whose posterior is only queried by its caller (the adaptive
        design's refits): the entry then has empty ``magnitudes`` and ``curve`` and no
        ``shape_check``; the posterior is the same.
    most_flexible : bool, default False
        With a selection, fit only its most flexible candidate (the spline rung of ``auto``), with
        the same smoothness choice and positional-width test, and when that test fires only the
        most flexible positional-width rung: no simpler rung is compared.  The adaptive design's
        fits use it (``docs/adaptive.md``, "The design's model"): a simpler rung that the
        comparison found adequate at the last selection can drift from the truth by more than its
        shrinking interval as the design concentrates the injections, and the design then follows it.
    map_starts : int, default 6
        Optimizer starts of the MAP of one model fitted from scratch (not a selection, not a warm
        refit; :func:`comest_bayes.bayes.inference.fit_map`): the adaptive design's pilot of its
        design rung uses 2, as every candidate of a selection does.

    Returns
    -------
    (CompletenessPosterior, FitEntry)
        The posterior (not yet saved) and its ``summary.json`` entry (:meth:`FitEntry.to_dict`).
    """
    t0 = time.perf_counter()
    noise = _on_demand(noise)
    spec = load_spec(requested)
    n_rows = len(outcomes)
    if n_rows == 0:
        raise InputError(f"no {quantity} outcomes for kind {kind!r}: nothing to fit.")
    cov, outcome, meta = covariates_from_outcomes(outcomes, image_shape=image_shape, outcome_column=outcome_column)
    warn = []
    if n_rows < MIN_OUTCOMES:
        warn.append(f"only {n_rows} outcomes: the posterior of the {kind} {quantity} is dominated by the priors")
    if outcome.all() or not outcome.any():
        warn.append(f"every {kind} outcome is {'positive' if outcome.all() else 'negative'}: the "
                    f"{quantity} curve is not constrained on one side (its posterior there is the prior)")
    for w in warn:
        warnings.warn(w, UserWarning, stacklevel=2)
    if outcome.any() and not outcome.all():
        m_pos, m_neg = cov.m[outcome], cov.m[~outcome]
        if m_pos.max() < m_neg.min() or m_neg.max() < m_pos.min():
            warnings.warn(f"the {kind} {quantity} outcomes are perfectly separated in magnitude (every injection "
                          f"on one side of a magnitude is positive, every one on the other negative): the data "
                          f"only bound the transition width from above, and its value (and the posterior's "
                          f"lower tail) is set by the prior on w. Inject more sources around m50 or treat w as "
                          f"an upper limit.", IdentifiabilityWarning, stacklevel=2)
    candidates = resolve_candidates(spec) if spec.is_selection else [spec]
    if "depth" not in (meta.get("available") or ()):
        # no injection carries a noise value: the depth covariate is 0 for every injection, and with no
        # reference noise every footprint pixel sits at depth 0 as well (Footprint.from_histogram), so a
        # depth term multiplies 0 everywhere: it changes no output, and its prior-only slope is no caveat
        meta = {**meta, "inert": ("depth",)}
        if any("depth" in covariates_needed(c) for c in candidates):
            log(f"fit: {kind} {quantity}: the injections carry no detection noise, so the models' depth terms are "
                "inert (depth 0 everywhere); give a noise column, or positions and a noise map, to let m50 "
                "follow the depth")
    data = compress_for(spec, cov, outcome, meta=meta)
    has_uv = "uv" in (meta.get("available") or ())  # the injections have positions
    seed = int_seed_for(config.seed, Stream.FIT, quantity, kind)
    if most_flexible:
        candidates = candidates[-1:]

    def footprint_cells(position: bool) -> Footprint:
        # every unmasked pixel, grouped into weighted covariate cells: the exact image average
        grid = footprint_grid(position)
        if footprint_points is not None:
            return Footprint.from_points(*footprint_points, data.meta.get("sigma_ref"), image_shape, ddepth=grid[0],
                                         nuv=grid[1])
        hist = (footprints or {}).get(grid)
        if hist is None:
            noise_map = noise()
            if noise_map is None:
                # a histogram without the noise map would put every pixel at the reference depth: an image
                # average that silently ignores the depth field
                raise InputError(f"fit_kind: the {kind} {quantity} fit needs the footprint cells {grid} (ddepth, nuv), "
                                 "which are neither in `footprints` nor computable without the noise map; pass "
                                 "`noise` (or the histogram in `footprints`).")
            hist = FootprintHistogram.from_maps(noise_map, mask, ddepth=grid[0], nuv=grid[1])
            if footprints is not None:
                footprints[grid] = hist  # the caller's next fit with this dict reuses the pass
        return Footprint.from_histogram(hist, data.meta.get("sigma_ref"))

    cells = footprint_cells(any(c.uses_position for c in candidates))
    mag_lo, mag_hi = float(mag_range[0]), float(mag_range[1])
    edges = R.magnitude_edges(mag_lo, mag_hi, config.ratios.mag_bin)
    selection = None
    if warm is not None and spec.is_selection:
        raise InputError(f"a warm refit needs one model, not the selection {requested!r}.")
    if spec.is_selection:
        probes = _probe_magnitudes(cov.m, outcome)
        quantities = targeted_quantities(cells, probes, mag_lo, mag_hi)
        sel = select_model(data, candidates, seed=seed, quantities=quantities, mag_edges=edges)
        chosen_spec = next(c for c in candidates if c.name == sel.chosen)
        tested = None
        width_cands = resolve_width_candidates(spec)
        if width_cands and not chosen_spec.uses_position and has_uv:
            # the width test of the chosen rung: one Jacobian of its cells, no refit (docs/bayesian.md,
            # "Positional width"); a plane and the rungs' quadratic field in log w, Bonferroni-combined;
            # only a scene whose width differs across the image pays for position
            test = width_position_test(sel.models[sel.chosen], sel.fits[sel.chosen].map.theta, cov.u, cov.v,
                                       outcome)
            tested = {**test.to_dict(), "threshold": WIDTH_TEST_P, "escalated": bool(test.p_value < WIDTH_TEST_P)}
            if tested["escalated"]:
                first = {"chosen": sel.chosen, "table": sel.to_dict()["table"]}
                candidates = width_cands[-1:] if most_flexible else [chosen_spec] + width_cands
                data = compress_for(candidates, cov, outcome, meta=meta, nuv=WIDTH_NUV)
                cells = footprint_cells(True)
                quantities = targeted_quantities(cells, probes, mag_lo, mag_hi)
                # the chosen rung starts from its MAP on the coarser cells (the same parameters)
                warm_from = (list(sel.models[sel.chosen].names), sel.fits[sel.chosen].map.theta)
                # the magnitude shape's smoothness was chosen by the evidence on these outcomes already: the
                # chosen spline rung keeps it on the finer cells, and so does the spline rung with a width field
                first_tau = sel.models[sel.chosen].tau if chosen_spec.link == "spline" else None
                keep = {c.name: first_tau for c in candidates if c.link == "spline"} if first_tau else None
                sel = select_model(data, candidates, seed=seed, quantities=quantities, mag_edges=edges,
                                   start=warm_from, taus=keep)
                chosen_spec = next(c for c in candidates if c.name == sel.chosen)
                tested["first_selection"] = first
                log(f"fit: {kind} {quantity}: the width varies across the image (score test p = "
                    f"{test.p_value:.2g}, {test.alternative} in log w); selection escalated to "
                    f"{[c.name for c in candidates]}")
        model = sel.models[sel.chosen]
        mp = sel.fits[sel.chosen].map
        selection = {k: v for k, v in sel.to_dict().items() if k != "diagnostics"}
        if tested is not None:
            selection["width_test"] = tested
        chosen_loo = sel.loo[sel.chosen]
        if chosen_loo.n_bad_k:
            warn.append(f"leave-one-out of the chosen model {sel.chosen}: {chosen_loo.n_bad_k} of {chosen_loo.n} "
                        f"injections have a leverage above {chosen_loo.khat_threshold} (max {chosen_loo.khat_max:.2f}); "
                        "its leave-one-out score is approximate (the choice between models may be affected)")
        log(f"fit: {kind} {quantity}: selected {sel.chosen} among {[c.name for c in candidates]}")
    elif warm is not None:
        chosen_spec = spec
        model = CompletenessModel(spec, data)
        if warm.get("tau") is not None and spec.link == "spline":
            model.tau = float(warm["tau"])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            mp = fit_map(model, nstarts=1, seed=seed, method="newton",
                         start=model.warm_start(warm["names"], np.asarray(warm["theta"], float)))
    else:
        chosen_spec = spec
        model = CompletenessModel(spec, data)
        mp = None
        if spec.link == "spline" and spec.spline_tau == "evidence":
            _, mp, _ = choose_tau(model, seed=seed)
    result = fit(model, seed=seed, sampler=config.fit.sampler, min_ess=config.fit.min_ess,
                 max_steps=config.fit.max_steps, mp=mp, nstarts=map_starts)
    for w in covariate_warnings(chosen_spec, data):
        warnings.warn(w, UserWarning, stacklevel=2)
        warn.append(w)
    draws = result.draws()
    # the cells' predictions per draw, shared by the two checks; the shape check uses the run's ratio bins,
    # so that it speaks of the same bins as the binned table
    cell_p = cell_probabilities(model, thin_draws(draws)) if products else None
    check = shape_check(model, draws, edges, p=cell_p) if products else None
    msg = shape_warning(check, name=chosen_spec.name, kind=kind, quantity=quantity) if check is not None else None
    if msg:
        warnings.warn(msg, UserWarning, stacklevel=2)
        warn.append(msg)
    # the same check per tile of the image and per depth bin: what the magnitude bins average away
    cov_check = covariate_check(model, draws, u=cov.u if has_uv else None, v=cov.v if has_uv else None,
                                depth=cov.depth, detected=outcome, image_shape=image_shape, p=cell_p) if products else None
    msg = covariate_warning(cov_check, name=chosen_spec.name, kind=kind, quantity=quantity) if cov_check else None
    if msg:
        warnings.warn(msg, UserWarning, stacklevel=2)
        warn.append(msg)
    diagnostics = result.posterior.diagnostics.to_dict() if result.posterior is not None else {}
    injected = [float(np.min(cov.m)), float(np.max(cov.m))]
    post = CompletenessPosterior(
        spec=chosen_spec, samples=draws, names=list(model.names),
        meta={"sigma_ref": data.meta.get("sigma_ref"), "hlr_ref": data.meta.get("hlr_ref"),
              "image_shape": tuple(int(v) for v in image_shape), "mag_range": [mag_lo, mag_hi],
              "injected_range": injected, "depth_range": [float(np.min(cov.depth)), float(np.max(cov.depth))],
              "kind": kind, "quantity": quantity, "tau": model.tau},
        noise_grid=coarse_noise_map(noise(), mask) if noise_grid is None else noise_grid, footprint=footprint_sample(mask, 2000, rng_for(seed, Stream.FOOTPRINT)),
        wcs_header=wcs_header, diagnostics={"sampler": diagnostics, "selection": selection, "warnings": warn},
        cells=cells,
    )
    post.use_model(model)  # the compiled model (same parameters as the spec's own layout): no second compile
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        mags = post.summary_magnitudes() if products else {}
    for w in caught:
        warn.append(str(w.message))
    if np.ptp(cov.m) < 2.0 * config.ratios.mag_bin:
        who = "injections" if kind == "injections" else f"{kind} injections"
        text = (f"all {who} lie within {np.ptp(cov.m):.2f} mag (less than two {config.ratios.mag_bin}-mag "
                f"bins): the shape of the {quantity} curve (its width, m80, m90) is not constrained by the data but by "
                "the model's form and priors; inject over a range that brackets the transition")
        warnings.warn(text, UserWarning, stacklevel=2)
        warn.append(text)
    entry = FitEntry(
        name=chosen_spec.name,
        requested=requested,
        selection=selection,
        magnitudes=mags,
        parameters=_param_summary(model, draws),
        curve=_json_curve(post.curve(np.asarray(mag_centers, float), warn=False)) if products else {},
        diagnostics=diagnostics,
        tau=model.tau,
        shape_check=check,
        covariate_check=cov_check,
        warnings=tuple(warn + list(diagnostics.get("warnings", []))),
        n_outcomes=int(data.ntotal),
        n_cells=int(data.ncells),
        seconds=round(time.perf_counter() - t0, 2),
    )
    return post, entry
