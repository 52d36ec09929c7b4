"""Sequential injection: batches whose magnitudes follow the current posterior, until a precision target.

The loop of :func:`run_sequential` is independent of how injections are
made: it asks a ``simulate(mags, batch)`` callable for the outcomes of a
batch of magnitudes (the pipeline renders and detects them; the benchmarks
and tests draw them from a known curve) and a ``fit(table, batch)``
callable for the posterior of the accumulated outcomes.  Between batches it
builds the next :class:`~comest_bayes.inject.design.MagnitudeDesign` with
:func:`comest_bayes.inject.design.design_from_draws`.

Reproducibility: the magnitudes of batch ``k`` come from the stream
``(seed, "design", k)`` and the design built from the outcomes of batches
``< k`` only, so the same seed gives the same batches whatever executes
them, and a run resumed after batch ``k`` (its outcomes and designs
recorded) continues exactly as an uninterrupted one.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
import warnings

import numpy as np
from astropy.table import Table, vstack

from comest_bayes.inject.design import (DEFAULT_UNIFORM_SHARE, TARGETS, MagnitudeDesign, curves_at, design_from_draws, uniform_design)
from comest_bayes.errors import InputError
from comest_bayes.seeding import Stream, rng_for, int_seed_for
from comest_bayes.ratios import binned as R
from comest_bayes.config import RunConfig
from comest_bayes.bayes.fit import fit_kind, shared_maps, warm_state
from comest_bayes.bayes.spec import load_spec, resolve_candidates

__all__ = ["AdaptiveSettings", "BatchRecord", "SequentialResult", "run_sequential", "PosteriorView",
           "after_batch", "attained", "check_recorded", "check_magnitudes", "package_fitter", "design_rung"]


@dataclass(frozen=True)
class AdaptiveSettings:
    """How a sequential design proceeds.

    Attributes
    ----------
    precision : float
        Target half-width of the 68% interval of the image-average m50 (mag);
        with ``target="f"``, the largest posterior standard deviation of the
        image-average f at ``magnitudes`` (a fraction, below 0.5).
    pilot : int
        Injections of the first (uniform) batch.  Default 100: with 1000 the
        pilot alone was most of what an m50 RMSE of 0.02 mag needs, and a
        pilot of 100 reached 13-17x fewer injections than uniform + binned
        for it on every scene of ``benchmarks/bench_adaptive.py`` (7-8x with
        1000), with the stopping intervals' coverage inside its binomial range.
    growth : float
        Each later batch holds ``growth`` times the injections so far (at
        least ``min_batch``): the number of refits grows only as the log of
        the injections.
    min_batch : int
        Smallest batch (default 50).
    max_injections : int
        Stop here even if the precision is not reached (and say so).
    uniform_share : float
        Share of every adaptive batch drawn uniformly over the range.
    target : {"m50", "curve", "f"}
        What the design aims at (``"curve"`` still stops on the m50 half-width;
        ``"f"`` aims at, and stops on, f at ``magnitudes``).
    magnitudes : tuple of float
        For ``target="f"``: the magnitudes at which f must be precise.
    """

    precision: float = 0.02
    pilot: int = 100
    growth: float = 0.5
    min_batch: int = 50
    max_injections: int = 100_000
    uniform_share: float = DEFAULT_UNIFORM_SHARE
    target: str = "m50"
    magnitudes: tuple = ()

    def __post_init__(self):
        if not (self.precision > 0 and math.isfinite(self.precision)):
            raise InputError(f"precision = {self.precision} must be a positive number of magnitudes.")
        if self.pilot < 1 or self.min_batch < 1 or self.max_injections < self.pilot:
            raise InputError(f"pilot ({self.pilot}), min_batch ({self.min_batch}) must be >= 1 and "
                             f"max_injections ({self.max_injections}) >= pilot.")
        if not self.growth > 0:
            raise InputError(f"growth = {self.growth} must be positive.")
        if not 0.0 <= self.uniform_share <= 1.0:
            raise InputError(f"uniform_share = {self.uniform_share} must lie in [0, 1].")
        if self.target not in TARGETS:
            raise InputError(f"target must be one of {TARGETS}, got {self.target!r}.")
        object.__setattr__(self, "magnitudes", tuple(float(m) for m in self.magnitudes))
        if self.target == "f":
            if not self.magnitudes or not all(math.isfinite(m) for m in self.magnitudes):
                raise InputError(f"target 'f' needs finite magnitudes at which f must be precise, got "
                                 f"{list(self.magnitudes)}; e.g. magnitudes=(23.5, 24.0).")
            if not self.precision < 0.5:
                raise InputError(f"precision = {self.precision} is a standard deviation of f with target 'f': "
                                 "it must lie below 0.5 (e.g. 0.02).")
        elif self.magnitudes:
            raise InputError(f"magnitudes {list(self.magnitudes)} are used only by target 'f' (target is "
                             f"{self.target!r}); set target='f' or drop them.")

    def batch_size(self, done: int) -> int:
        """Injections of the next batch after ``done`` so far (the pilot first)."""
        if done == 0:
            return int(self.pilot)
        size = max(int(self.min_batch), int(math.ceil(self.growth * done)))
        return int(min(size, self.max_injections - done))


@dataclass(frozen=True)
class PosteriorView:
    """What the design needs of a posterior: draws of the image-average curve on a grid and of m50."""

    grid: np.ndarray
    curves: np.ndarray   # (S, G)
    m50: np.ndarray      # (S,)
    #: The sampler's own convergence verdict: a precision read off draws that did not converge is not
    #: a precision reached (the loop goes on).
    converged: bool = True
    #: m50 of the draws whose curves are in ``curves`` (S_curves,), when those are fewer than the draws
    #: of ``m50`` (the precision is read off ``m50``, the design pairs ``curves`` with these); None:
    #: ``curves`` and ``m50`` are the same draws.
    curve_m50: np.ndarray | None = None

    @property
    def paired_m50(self) -> np.ndarray:
        """m50 of the same draws as ``curves`` (what the design's covariances pair)."""
        return self.m50 if self.curve_m50 is None else self.curve_m50

    @property
    def m50_halfwidth(self) -> float:
        """Half-width of the central 68% interval of m50 (inf when under half the draws define it)."""
        ok = np.isfinite(self.m50)
        if ok.mean() < 0.5:
            return math.inf
        lo, hi = np.percentile(self.m50[ok], [15.865, 84.135])
        return float(0.5 * (hi - lo))

    @property
    def m50_median(self) -> float:
        ok = np.isfinite(self.m50)
        return float(np.median(self.m50[ok])) if ok.any() else math.nan

    def f_sd(self, magnitudes) -> np.ndarray:
        """Posterior standard deviation of the image-average f at each of ``magnitudes``."""
        return curves_at(self.grid, self.curves, magnitudes).std(axis=0, ddof=1)

    def f_median(self, magnitudes) -> np.ndarray:
        """Posterior median of the image-average f at each of ``magnitudes``."""
        return np.median(curves_at(self.grid, self.curves, magnitudes), axis=0)


def attained(view: PosteriorView, target: str, magnitudes=()) -> float:
    """The number compared with the precision target: the m50 half-width, or with ``target="f"`` the
    largest posterior sd of f at ``magnitudes``."""
    if target == "f":
        return float(np.max(view.f_sd(magnitudes)))
    return view.m50_halfwidth


def check_magnitudes(magnitudes, lo: float, hi: float) -> None:
    """Refuse target magnitudes outside the injected range (no injection could make f precise there)."""
    bad = [m for m in magnitudes if not lo <= m <= hi]
    if bad:
        raise InputError(f"the magnitudes {bad} at which f must be precise lie outside the injected range "
                         f"[{lo:.2f}, {hi:.2f}]; choose magnitudes inside it or widen injection.mag_range.")


@dataclass
class BatchRecord:
    """One batch: its design, size, and the precision reached after fitting everything up to it."""

    index: int
    n: int
    total: int
    design: MagnitudeDesign
    m50: float
    halfwidth: float
    fit_seconds: float
    simulate_seconds: float
    f_sd: tuple = ()

    def to_dict(self) -> dict:
        out = {"index": self.index, "n": self.n, "total": self.total, "design": self.design.to_dict(),
               "m50": None if not math.isfinite(self.m50) else self.m50,
               "halfwidth": None if not math.isfinite(self.halfwidth) else self.halfwidth,
               "fit_seconds": round(self.fit_seconds, 3), "simulate_seconds": round(self.simulate_seconds, 3)}
        if self.f_sd:
            out["f_sd"] = [float(v) for v in self.f_sd]
        return out


@dataclass
class SequentialResult:
    """Outcome of :func:`run_sequential`."""

    table: Table
    batches: list = field(default_factory=list)
    reached: bool = False
    reason: str = ""
    posterior: object = None

    def to_dict(self) -> dict:
        return {"reached": self.reached, "reason": self.reason, "injections": len(self.table),
                "batches": [b.to_dict() for b in self.batches]}


def check_recorded(recorded: MagnitudeDesign, design: MagnitudeDesign, k: int) -> None:
    """Refuse a resume whose recorded design of batch ``k`` is not the one this run builds."""
    if not np.allclose(recorded.prob, design.prob, rtol=1e-9, atol=1e-12):
        raise InputError(f"batch {k} was recorded with another design than this run builds: the earlier run used "
                         "other settings, code or outcomes; start a new output folder.")


def after_batch(view: PosteriorView, lo: float, hi: float, *, precision: float, at_cap: bool, spent: str,
                target: str, uniform_share: float, magnitudes=()):
    """What follows a batch: ``(reached, reason, next design)``.

    ``reached`` when the m50 half-width (with ``target="f"``: the posterior
    sd of f at every one of ``magnitudes``) is at most ``precision`` and
    the posterior's sampler converged (a width read off unconverged draws
    is no precision: the loop goes on);
    otherwise stopped (with the reason) ``at_cap``, or the design of the next
    batch.  With ``target="f"`` that design aims only at the magnitudes whose
    f is not yet precise enough.  ``spent`` words the effort so far for the
    reason (e.g. ``"3375 injections"``).
    """
    unconverged = "" if view.converged else " but the posterior sampler did not converge"
    if target == "f":
        sd = view.f_sd(magnitudes)
        worst = float(np.max(sd))
        said = "sd of f at " + ", ".join(f"{m:.2f}" for m in magnitudes) + " " + ", ".join(f"{v:.4f}" for v in sd)
        if worst <= precision and view.converged:
            return True, f"{said} <= {precision} after {spent}", None
        if at_cap:
            return False, (f"stopped at the cap of {spent} with {said}"
                           + (f" (largest > {precision})" if worst > precision else unconverged)), None
        unmet = [m for m, v in zip(magnitudes, sd) if v > precision] or list(magnitudes)
        return False, "", design_from_draws(view.grid, view.curves, lo, hi, target="f", magnitudes=unmet,
                                            uniform_share=uniform_share)
    half = view.m50_halfwidth
    if half <= precision and view.converged:
        return True, f"m50 half-width {half:.4f} <= {precision} after {spent}", None
    if at_cap:
        return False, (f"stopped at the cap of {spent} with m50 half-width {half:.4f}"
                       + (f" > {precision}" if half > precision else f" <= {precision}{unconverged}")), None
    return False, "", design_from_draws(view.grid, view.curves, lo, hi, target=target, m50=view.paired_m50,
                                        uniform_share=uniform_share)


def _stack(tables: list) -> Table:
    return tables[0] if len(tables) == 1 else vstack(tables, metadata_conflicts="silent")


def run_sequential(simulate, fit, lo: float, hi: float, settings: AdaptiveSettings, *, seed: int,
                   log=lambda s: None, done: list | None = None) -> SequentialResult:
    """Inject in batches, each designed from the posterior of the ones before, until the precision target.

    Parameters
    ----------
    simulate : callable ``(mags, batch_index) -> Table``
        Outcomes (at least ``mag`` and ``detected``) of injecting ``mags``.
    fit : callable ``(table, batch_index) -> (PosteriorView, posterior)``
        The posterior of all outcomes so far.
    lo, hi : float
        The injected magnitude range (every design lives on it).
    settings : AdaptiveSettings
    seed : int
        Root seed; batch ``k`` draws its magnitudes from stream ``("design", k)``.
    done : list of (Table, MagnitudeDesign), optional
        Batches finished earlier (a resume): their outcomes are reused, not
        simulated again; their designs must be what this loop would build
        (they are, for the same seed and outcomes).

    Returns
    -------
    SequentialResult
    """
    if settings.target == "f":
        check_magnitudes(settings.magnitudes, lo, hi)
    done = list(done or [])
    tables, batches = [], []
    design = uniform_design(lo, hi)
    view, post, total = None, None, 0
    reached, reason = False, ""
    k = 0
    while True:
        n = settings.batch_size(total)
        if n <= 0:
            reason = f"stopped at the cap of {settings.max_injections} injections"
            break
        t0 = time.perf_counter()
        if k < len(done):
            table, recorded = done[k]
            check_recorded(recorded, design, k)
        else:
            mags = design.sample(n, rng_for(seed, Stream.DESIGN, k))
            table = simulate(mags, k)
        t_sim = time.perf_counter() - t0
        tables.append(table)
        total += len(table)
        t1 = time.perf_counter()
        view, post = fit(_stack(tables), k)
        t_fit = time.perf_counter() - t1
        f_sd = tuple(float(v) for v in view.f_sd(settings.magnitudes)) if settings.target == "f" else ()
        rec = BatchRecord(index=k, n=len(table), total=total, design=design, m50=view.m50_median,
                          halfwidth=view.m50_halfwidth, fit_seconds=t_fit, simulate_seconds=t_sim, f_sd=f_sd)
        batches.append(rec)
        log(f"design: batch {k} ({design.target}, {len(table)} injections, "
            f"{100 * design.fraction_within(rec.m50 - 0.6, rec.m50 + 0.6) if math.isfinite(rec.m50) else 0:.0f}% "
            f"within 0.6 mag of m50): {total} in all, m50 {rec.m50:.3f} +- {rec.halfwidth:.4f}"
            + (", sd of f " + ", ".join(f"{v:.4f}" for v in f_sd) if f_sd else "")
            + f" (target {settings.precision})")
        reached, reason, design = after_batch(view, lo, hi, precision=settings.precision,
                                              at_cap=total >= settings.max_injections, spent=f"{total} injections",
                                              target=settings.target, uniform_share=settings.uniform_share,
                                              magnitudes=settings.magnitudes)
        if design is None:
            break
        k += 1
    table = _stack(tables)
    return SequentialResult(table=table, batches=batches, reached=reached, reason=reason, posterior=post)


#: MAP starts of a design fit of one model from scratch (the design rung's pilot), as for every
#: candidate of a selection (the package's one-model fits use 6).
DESIGN_MAP_STARTS = 2


def design_rung(spec):
    """The model a selection's design fits use before its first selection: its most flexible candidate
    whose link is not a spline (``richards_depth`` for ``auto``), or its last candidate.

    A spline rung chooses its smoothness over a grid of scales (several MAPs) and carries some twenty
    parameters; the rung below it keeps an asymmetric transition and the depth term at a fraction of
    that cost.  ``spec``: a selection :class:`~comest_bayes.bayes.spec.ModelSpec` (or its name).
    """
    candidates = resolve_candidates(load_spec(spec))
    plain = [c for c in candidates if c.link != "spline"]
    return (plain or candidates)[-1]


def package_fitter(*, image_shape, noise, mask, lo: float, hi: float, seed: int, model: str = "auto",
                   kind: str = "point", ngrid: int = 121, nsamples: int = 1000, mag_bin: float = 0.1,
                   reselect: float = 4.0, magnitudes=(), maps: dict | None = None, design_samples: int = 200,
                   defer_selection: bool = True, most_flexible: bool = True):
    """A ``fit`` callable for :func:`run_sequential` that runs the package's own completeness fit.

    Each call fits every outcome so far with :func:`comest_bayes.bayes.fit.fit_kind`
    (seed stream ``("design-fit", k)``) and returns the :class:`PosteriorView`
    on ``ngrid`` magnitudes over ``[lo, hi]`` (plus ``magnitudes``, so that f
    there is read without interpolation) and the ``(posterior, entry)``
    pair.

    With a selection such as ``auto`` the models are compared once the
    outcomes have grown ``reselect`` times since the pilot, and again whenever
    they have grown ``reselect`` times since the last comparison.  With
    ``most_flexible`` (the default) a comparison fits only the selection's most
    flexible candidate (``spline_depth`` for ``auto``, its smoothness chosen
    by the evidence) and its positional-width test, not the simplest adequate
    rung: a simple rung that was adequate at the comparison drifts from a
    truth outside its family as the design concentrates the injections, and
    the design follows it (``docs/adaptive.md``, "The design's model").  Before the
    first comparison (``defer_selection``) the design fits one fixed rung,
    :func:`design_rung` (``richards_depth`` for ``auto``); without
    ``defer_selection`` the pilot is compared as well.  Every other call
    refits the current model from the previous posterior
    (:func:`comest_bayes.bayes.fit.warm_state`: Newton steps from its median,
    the spline's smoothness kept), which costs a fraction of a selection.  A
    comparison runs the positional-width test of the package's fit and
    escalates when it fires (without it, on a scene whose width varies
    across the image, the design's m50 carried the misfit).  Why a selection is deferred and what it costs:
    ``docs/adaptive.md``.

    ``maps``: :func:`comest_bayes.bayes.fit.shared_maps` of ``noise`` and
    ``mask`` for ``model`` (computed on the first call when not given): the
    pass over the pixels is made once, not once per refit (a grid a fit
    needs beyond it, e.g. an escalated width selection's position blocks,
    is added to it by the first fit that makes it).  The entry is made with
    ``products=False`` (no m50/m80/m90 summaries, curve or shape check: the
    view carries what the design needs, and the run's fit stage fits the
    final outcomes with every product).  With an m50 target the curves that
    shape the design are evaluated for ``design_samples`` draws (with their
    own m50, :attr:`PosteriorView.curve_m50`) while the precision is read off
    ``nsamples`` draws.
    """
    edges = R.magnitude_edges(lo, hi, mag_bin)
    centers = 0.5 * (edges[:-1] + edges[1:])
    grid = np.union1d(np.linspace(lo, hi, int(ngrid)), np.asarray(magnitudes, dtype=np.float64))
    spec = load_spec(model)
    selecting = spec.is_selection
    state = {"warm": None, "spec": None, "selected_at": 0, "first": None, "maps": maps}

    def fit(table, k):
        n = len(table)
        if state["maps"] is None:
            state["maps"] = shared_maps(noise, mask, [model])
        if state["first"] is None:
            state["first"] = n
        warm, requested = state["warm"], state["spec"]
        if selecting:
            since = state["selected_at"] or (state["first"] if defer_selection else 0)
            if since == 0 or n >= reselect * since:  # a comparison of the candidates, from scratch
                warm, requested = None, spec
            elif warm is None:  # the pilot before the first comparison: the design rung, from scratch
                requested = design_rung(spec)
        elif warm is None:
            requested = spec
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            post, entry = fit_kind(table, kind=kind, quantity="completeness", requested=requested,
                                   config=RunConfig(seed=int_seed_for(seed, Stream.DESIGN_FIT, k)),
                                   image_shape=image_shape, noise=noise, mask=mask, wcs_header=None,
                                   mag_range=(lo, hi), mag_centers=centers, warm=warm,
                                   footprints=state["maps"]["footprints"], noise_grid=state["maps"]["noise_grid"],
                                   products=False, map_starts=DESIGN_MAP_STARTS,
                                   most_flexible=most_flexible and selecting and requested is spec)
            m50 = post.magnitudes_at((0.5,), nsamples=nsamples)[0.5]
            if len(magnitudes):  # the precision on f is read off the curves: all the draws
                curves, curve_m50 = post.average_curve(grid, nsamples=nsamples), None
            else:  # the curves only shape the design: fewer draws, with their own m50
                curves = post.average_curve(grid, nsamples=design_samples)
                curve_m50 = post.magnitudes_at((0.5,), nsamples=design_samples)[0.5]
        if requested is spec and selecting:
            state["selected_at"] = n
        state["warm"], state["spec"] = warm_state(post), post.spec
        entry = replace(entry, warm_refit=warm is not None)
        converged = bool(entry.diagnostics.get("converged", True))
        return (PosteriorView(grid=grid, curves=curves, m50=np.asarray(m50, float), converged=converged,
                              curve_m50=None if curve_m50 is None else np.asarray(curve_m50, float)),
                (post, entry))

    return fit
