r"""Model comparison by leave-one-out cross-validation (PSIS-LOO) on grouped outcomes.

Grouped PSIS-LOO
----------------
The completeness likelihood is a product of Bernoulli terms, one per
injection.  After exact compression into binomial cells (``n_c`` injections
in cell ``c`` with identical covariates, ``k_c`` of them detected) every
detected injection of cell ``c`` has the *same* pointwise log-likelihood
draws :math:`\log f_c(\theta_s)` and every undetected one the same
:math:`\log(1 - f_c(\theta_s))`.  Pareto-smoothed importance sampling LOO
(Vehtari, Gelman & Gabry 2017, Stat. Comput. 27, 1413; Vehtari et al. 2024,
JMLR 25(72)) treats each observation separately, but its importance ratios
:math:`1 / p(y_i \mid \theta_s)` depend on the observation only through those
draws, so identical observations get identical smoothed weights, k-hat and
:math:`{\rm elpd}_i`.  The leave-one-*injection*-out estimate is therefore
computed exactly once per group ``g = (cell, outcome)`` and weighted by the
group size :math:`n_g` (``k_c`` or ``n_c - k_c``):

.. math::

    {\rm elpd}_g = \log \sum_s \tilde w_{gs}\, p_{gs}, \qquad
    {\rm elpd}_{\rm loo} = \sum_g n_g\, {\rm elpd}_g ,

with :math:`\tilde w_{gs}` the normalized smoothed weights of
:func:`arviz.psislw` applied to :math:`-\log p_{gs}`.  As in
:func:`arviz.loo`, :math:`{\rm SE} = \sqrt{N\, {\rm Var}_i({\rm elpd}_i)}`
over the ``N`` injections (population variance, here weighted by the group
sizes), :math:`{\rm lppd} = \sum_g n_g \log(\frac1S \sum_s p_{gs})` and
:math:`p_{\rm loo} = {\rm lppd} - {\rm elpd}_{\rm loo}`.  The result equals
``arviz.loo`` on the expanded ``(S, N)`` pointwise log-likelihood matrix
(tested) at a cost that depends on the number of cells, not of injections.

Selection rule
--------------
See :func:`select_model`.
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass, field

import numpy as np
from scipy.special import logsumexp

from .errors import InputError
from .inference import FitResult, InferenceWarning, fit
from .seeding import int_seed_for

__all__ = ["LooWarning", "LooResult", "SelectionResult", "loo_grouped", "compare_loo", "select_model",
           "KHAT_THRESHOLD"]

#: Pareto k-hat above which the PSIS estimate of an observation is unreliable
#: (Vehtari et al. 2024: above 0.7 the importance-sampling error converges too slowly).
KHAT_THRESHOLD = 0.7


class LooWarning(InferenceWarning):
    """PSIS-LOO diagnostics indicate unreliable estimates (large Pareto k-hat)."""


def _psislw(neg_loglik: np.ndarray, reff: float):
    """arviz's PSIS on ``(M, S)`` log ratios (samples last); arviz's import-time notices silenced."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)
        import arviz as az

        return az.psislw(neg_loglik, reff=reff)


@dataclass
class LooResult:
    """Grouped PSIS-LOO of one model (see the module docstring).

    Readable as a mapping with the contract's keys ``elpd``, ``se``,
    ``p_loo``, ``khat_max``, ``n_bad_k``.

    Attributes
    ----------
    elpd : float
        ``elpd_loo``, sum over all ``N`` injections (nats).
    se : float
        Its standard error ``sqrt(N Var(elpd_i))``.
    p_loo : float
        Effective number of parameters ``lppd - elpd``.
    lppd : float
        Log pointwise predictive density of the full posterior.
    khat_max : float
        Largest Pareto k-hat over the non-empty groups.
    n_bad_k : int
        Number of *injections* in groups with k-hat > ``khat_threshold``.
    khat_threshold : float
    n : int
        Number of injections ``N = sum(n_c)``.
    nsamples : int
        Posterior draws used ``S``.
    reff : float
        Relative efficiency passed to PSIS.
    elpd_groups : ndarray, shape (G, 2)
        ``elpd_g`` of the detected (``[:, 0]``) and undetected (``[:, 1]``)
        injections of every cell; 0 for empty groups.
    khat_groups : ndarray, shape (G, 2)
        k-hat of every group; NaN for empty groups.
    counts : ndarray, shape (G, 2)
        Group sizes ``k_c`` and ``n_c - k_c``.
    """

    elpd: float
    se: float
    p_loo: float
    lppd: float
    khat_max: float
    n_bad_k: int
    khat_threshold: float
    n: int
    nsamples: int
    reff: float
    elpd_groups: np.ndarray
    khat_groups: np.ndarray
    counts: np.ndarray

    def __getitem__(self, key):
        return getattr(self, key)

    def to_dict(self) -> dict:
        """JSON-ready scalars (no per-group arrays)."""
        return {"elpd": float(self.elpd), "se": float(self.se), "p_loo": float(self.p_loo),
                "lppd": float(self.lppd), "khat_max": float(self.khat_max), "n_bad_k": int(self.n_bad_k),
                "khat_threshold": float(self.khat_threshold), "n": int(self.n), "nsamples": int(self.nsamples),
                "reff": float(self.reff)}


def _weighted_sum_se(values: np.ndarray, counts: np.ndarray) -> tuple[float, float]:
    """Sum and ``sqrt(N * Var)`` of per-injection values given once per group with its count."""
    n = float(counts.sum())
    total = float(np.sum(counts * values))
    mean = total / n
    var = float(np.sum(counts * (values - mean) ** 2)) / n
    return total, math.sqrt(n * var)


def loo_grouped(model, theta_samples, *, reff: float = 1.0, max_draws: int | None = None,
                khat_threshold: float = KHAT_THRESHOLD, warn: bool = True) -> LooResult:
    """PSIS-LOO of a binomial-cell model, exact per injection (see the module docstring).

    Parameters
    ----------
    model : CompletenessModel-like
        Needs ``cell_loglik(thetas (S, D)) -> (S, G, 2)`` (``log f`` and
        ``log(1 - f)`` per cell) and ``data.n``, ``data.k`` (shape (G,)).
    theta_samples : array_like, shape (S, D)
        Posterior draws in theta space (e.g. ``PosteriorSamples.samples``).
    reff : float, default 1.0
        Relative MCMC efficiency ``ESS / S`` of the draws used (sets the
        length of the Pareto tail fitted by PSIS, as in :func:`arviz.loo`).
    max_draws : int, optional
        Use at most this many draws, evenly spaced through ``theta_samples``
        (memory is ``S * G * 2`` float64 numbers).
    khat_threshold : float, default 0.7
        k-hat above which a group's estimate is counted as unreliable.
    warn : bool, default True
        Issue a :class:`LooWarning` when any group exceeds ``khat_threshold``.

    Returns
    -------
    LooResult

    Raises
    ------
    InputError
        For draws of the wrong shape, fewer than 2 draws, or non-finite
        pointwise log-likelihoods in a non-empty group.
    """
    thetas = np.asarray(theta_samples, dtype=np.float64)
    if thetas.ndim != 2 or thetas.shape[1] != model.ndim:
        raise InputError(f"loo_grouped: theta_samples must have shape (S, {model.ndim}), got {thetas.shape}")
    if max_draws is not None and thetas.shape[0] > max_draws:
        keep = np.unique(np.round(np.linspace(0, thetas.shape[0] - 1, int(max_draws))).astype(np.int64))
        thetas = thetas[keep]
    s = thetas.shape[0]
    if s < 2:
        raise InputError(f"loo_grouped: need at least 2 posterior draws, got {s}")
    if not 0.0 < reff <= 1.0 or not math.isfinite(reff):
        raise InputError(f"loo_grouped: reff must be in (0, 1], got {reff}")
    n_cell = np.asarray(model.data.n, dtype=np.int64)
    k_cell = np.asarray(model.data.k, dtype=np.int64)
    counts = np.stack([k_cell, n_cell - k_cell], axis=1)  # (G, 2)
    if np.any(counts < 0):
        raise InputError("loo_grouped: the model's data has cells with k > n or negative counts")
    ll = np.asarray(model.cell_loglik(thetas), dtype=np.float64)  # (S, G, 2)
    if ll.shape != (s,) + counts.shape:
        raise InputError(f"loo_grouped: model.cell_loglik returned shape {ll.shape}, expected {(s,) + counts.shape}")
    used = counts.reshape(-1) > 0
    ll_used = ll.reshape(s, -1)[:, used].T  # (M, S): samples last, as arviz wants
    del ll
    if not np.all(np.isfinite(ll_used)):
        raise InputError("loo_grouped: non-finite pointwise log-likelihood (log f or log(1-f)) for an observed "
                         "outcome; the model gives probability 0 to some observed outcome")
    c = counts.reshape(-1)[used].astype(np.float64)

    log_w, khat = _psislw(-ll_used, reff)
    log_w = np.asarray(log_w, dtype=np.float64)
    khat = np.asarray(khat, dtype=np.float64)
    elpd_g = logsumexp(log_w + ll_used, axis=1)
    lppd_g = logsumexp(ll_used, axis=1) - math.log(s)

    elpd, se = _weighted_sum_se(elpd_g, c)
    lppd = float(np.sum(c * lppd_g))
    bad = khat > khat_threshold
    n_bad = int(c[bad].sum())
    khat_max = float(np.max(khat))

    elpd_groups = np.zeros(counts.size)
    elpd_groups[used] = elpd_g
    khat_groups = np.full(counts.size, np.nan)
    khat_groups[used] = khat
    if warn and n_bad:
        warnings.warn(f"PSIS-LOO: {n_bad} of {int(c.sum())} injections ({int(bad.sum())} groups) have Pareto "
                      f"k-hat > {khat_threshold} (max {khat_max:.2f}); their leave-one-out estimates are "
                      f"unreliable (a few injections dominate the posterior: too few draws, or an influential "
                      f"cell). Use more posterior draws or check those cells.", LooWarning, stacklevel=2)
    return LooResult(elpd=elpd, se=se, p_loo=lppd - elpd, lppd=lppd, khat_max=khat_max, n_bad_k=n_bad,
                     khat_threshold=float(khat_threshold), n=int(c.sum()), nsamples=s, reff=float(reff),
                     elpd_groups=elpd_groups.reshape(counts.shape), khat_groups=khat_groups.reshape(counts.shape),
                     counts=counts)


@dataclass
class SelectionResult:
    """Result of :func:`select_model`.

    Attributes
    ----------
    table : list of dict
        One row per candidate, in the given (simplest-first) order, with keys
        ``name``, ``nparams``, ``elpd_loo``, ``se``, ``delta_elpd`` (to the
        best, <= 0), ``se_delta`` (paired SE of that difference), ``p_loo``,
        ``khat_max``, ``n_bad_k``, ``seconds``, ``chosen``.
    chosen : str
        Name of the selected candidate.
    best : str
        Name of the candidate with the highest ``elpd_loo``.
    rule : str
        The rule applied, with its numbers.
    fits : dict
        ``name -> FitResult`` of every candidate.
    loo : dict
        ``name -> LooResult``.
    models : dict
        ``name -> model`` (the fitted model objects).
    seconds : float
        Total wall time.
    """

    table: list
    chosen: str
    best: str
    rule: str
    fits: dict
    loo: dict
    models: dict = field(default_factory=dict)
    seconds: float = 0.0

    def to_dict(self) -> dict:
        """JSON-ready summary: table, chosen, best, rule, per-candidate sampler diagnostics."""
        diag = {name: (f.posterior.diagnostics.to_dict() if f.posterior is not None else None)
                for name, f in self.fits.items()}
        return {"table": [dict(r) for r in self.table], "chosen": self.chosen, "best": self.best,
                "rule": self.rule, "diagnostics": diag, "seconds": float(self.seconds)}

    def format_table(self) -> str:
        """The table as aligned plain text."""
        head = f"{'model':<24s} {'D':>3s} {'elpd_loo':>12s} {'se':>8s} {'delta':>9s} {'se_d':>7s} " \
               f"{'p_loo':>7s} {'khat':>5s}  chosen"
        lines = [head]
        for r in self.table:
            lines.append(f"{r['name']:<24s} {r['nparams']:>3d} {r['elpd_loo']:>12.2f} {r['se']:>8.2f} "
                         f"{r['delta_elpd']:>9.2f} {r['se_delta']:>7.2f} {r['p_loo']:>7.2f} "
                         f"{r['khat_max']:>5.2f}  {'*' if r['chosen'] else ''}")
        return "\n".join(lines)


def compare_loo(loos: dict, *, margin: float = 4.0, margin_se: float = 2.0) -> tuple[list, str, str]:
    r"""Compare LOO results of models fitted to the same cells and apply the selection rule.

    Parameters
    ----------
    loos : dict
        ``name -> LooResult`` in the candidates' order, simplest first; all
        from the same data (identical ``counts``).
    margin, margin_se : float
        The rule of :func:`select_model`: the first model with
        ``delta_elpd >= -max(margin, margin_se * se_delta)`` is chosen.

    Returns
    -------
    rows : list of dict
        Per model: ``name``, ``elpd_loo``, ``se``, ``delta_elpd`` (to the
        best), ``se_delta`` (paired, ``sqrt(N Var_i(e_i - e_best,i))``),
        ``p_loo``, ``khat_max``, ``n_bad_k``, ``chosen``.
    chosen : str
        The selected model.
    best : str
        The model with the highest ``elpd_loo``.
    """
    if not loos:
        raise InputError("compare_loo: no LOO results given")
    if margin < 0 or margin_se < 0:
        raise InputError(f"compare_loo: margin and margin_se must be >= 0, got {margin} and {margin_se}")
    names = list(loos)
    ref_counts = loos[names[0]].counts
    for name in names[1:]:
        if loos[name].counts.shape != ref_counts.shape or not np.array_equal(loos[name].counts, ref_counts):
            raise InputError(f"compare_loo: model {name!r} was scored on different cells than {names[0]!r}; "
                             f"all candidates must be fitted to the same BinomialData")
    weights = ref_counts.reshape(-1).astype(np.float64)
    used = weights > 0
    best = max(names, key=lambda nm: loos[nm].elpd)
    e_best = loos[best].elpd_groups.reshape(-1)[used]
    rows = []
    chosen = None
    for name in names:
        lo = loos[name]
        if name == best:
            delta, se_delta = 0.0, 0.0
        else:
            diff = lo.elpd_groups.reshape(-1)[used] - e_best
            delta, se_delta = _weighted_sum_se(diff, weights[used])
        if chosen is None and delta >= -max(margin, margin_se * se_delta):
            chosen = name
        rows.append({"name": name, "elpd_loo": float(lo.elpd), "se": float(lo.se), "delta_elpd": float(delta),
                     "se_delta": float(se_delta), "p_loo": float(lo.p_loo), "khat_max": float(lo.khat_max),
                     "n_bad_k": int(lo.n_bad_k), "chosen": False})
    for r in rows:
        r["chosen"] = r["name"] == chosen
    return rows, chosen, best


def _default_factory(spec, data):
    from .likelihood import CompletenessModel

    return CompletenessModel(spec, data)


def _spec_name(spec) -> str:
    name = getattr(spec, "name", None)
    if not isinstance(name, str) or not name:
        raise InputError(f"select_model: every candidate needs a non-empty .name, got {spec!r}")
    return name


def select_model(data, candidates, *, seed: int, margin: float = 4.0, margin_se: float = 2.0,
                 min_ess: float = 400, max_steps: int = 20000, chunk: int = 500, nwalkers: int | None = None,
                 nstarts: int = 4, moves="de", loo_draws: int | None = 4000, model_factory=None,
                 progress: bool = False) -> SelectionResult:
    r"""Fit candidate models (simplest first) and keep the simplest one as good as the best.

    Every candidate is fitted by :func:`comest_bayes.inference.fit` (MAP,
    Laplace, emcee) and scored by :func:`loo_grouped`.  With ``best`` the
    candidate of highest ``elpd_loo``, each candidate ``c`` gets

    * :math:`\Delta_c = {\rm elpd}_c - {\rm elpd}_{\rm best} \le 0`;
    * :math:`{\rm SE}_\Delta = \sqrt{N\,{\rm Var}_i(e_{c,i} - e_{{\rm best},i})}`
      from the *paired* per-injection differences (the data are the same for
      all candidates, so most of the scatter of the individual ``elpd_i``
      cancels).

    **Rule**: choose the first candidate (in the given, simplest-first order)
    with

    .. math:: \Delta_c \ge -\max({\rm margin},\ {\rm margin\_se}\cdot{\rm SE}_\Delta),

    by default :math:`\Delta_c \ge -\max(4, 2\,{\rm SE}_\Delta)` nats.

    Why: a LOO difference is itself an estimate with sampling error.  A
    difference within about two standard errors is not distinguishable from
    zero, and below about 4 nats the standard error is itself unreliable
    (the normal approximation to the difference is poorly calibrated for
    small differences; Sivula, Magnusson, Matamoros & Vehtari 2020,
    arXiv:2008.10296, and the LOO FAQ of Vehtari).  A more complex model
    is therefore taken only when it beats every simpler one by a margin that
    is resolvable by both criteria; otherwise the simpler one wins, which
    keeps the parameter count (and the extrapolation risk of spatial terms)
    down.  The best model always satisfies the rule, so a choice always exists.

    Parameters
    ----------
    data : BinomialData
        Compressed outcomes resolving every covariate used by any candidate
        (e.g. from ``compress_for(candidates, ...)``); the same cells are used
        for every candidate, which makes the paired differences valid.
    candidates : sequence of ModelSpec or str, or a selection spec
        Simplest first; strings are loaded with
        :func:`comest_bayes.modelspec.load_spec`.  Names must be unique.  A
        single selection spec (or its name, e.g. ``"auto"``) stands for its
        candidates (:func:`comest_bayes.modelspec.resolve_candidates`).
    seed : int
        Root seed; candidate ``name`` is fitted with ``int_seed_for(seed,
        "select", name)``.
    margin : float, default 4.0
        Nats of elpd always considered unresolvable.
    margin_se : float, default 2.0
        Multiple of the paired SE considered unresolvable.
    min_ess : float, default 400
        ESS target of the sampler (lower than the final fit's 1000: LOO needs
        fewer effective draws than tail quantiles).
    max_steps, chunk, nwalkers, moves, progress
        Passed to :func:`comest_bayes.inference.sample_posterior`.
    nstarts : int, default 4
        MAP starts per candidate.
    loo_draws : int or None, default 4000
        Posterior draws used by PSIS-LOO (evenly thinned; None = all).
    model_factory : callable, optional
        ``model_factory(spec, data) -> model``; default
        :class:`comest_bayes.likelihood.CompletenessModel`.

    Returns
    -------
    SelectionResult
    """
    t0 = time.perf_counter()
    if margin < 0 or margin_se < 0:
        raise InputError(f"select_model: margin and margin_se must be >= 0, got {margin} and {margin_se}")
    if isinstance(candidates, str) or getattr(candidates, "is_selection", False):
        from .modelspec import resolve_candidates

        candidates = resolve_candidates(candidates)
    candidates = list(candidates)
    if not candidates:
        raise InputError("select_model: no candidate models given")
    if any(isinstance(c, str) for c in candidates):
        from .modelspec import load_spec

        candidates = [load_spec(c) if isinstance(c, str) else c for c in candidates]
    names = [_spec_name(c) for c in candidates]
    if len(set(names)) != len(names):
        raise InputError(f"select_model: candidate names must be unique, got {names}")
    factory = _default_factory if model_factory is None else model_factory

    fits, loos, models, seconds = {}, {}, {}, {}
    for spec, name in zip(candidates, names):
        t1 = time.perf_counter()
        model = factory(spec, data)
        result: FitResult = fit(model, seed=int_seed_for(seed, "select", name), sample=True, nstarts=nstarts,
                                min_ess=min_ess, max_steps=max_steps, chunk=chunk, nwalkers=nwalkers,
                                progress=progress, moves=moves)
        draws = result.posterior.samples
        s_used = draws.shape[0] if loo_draws is None else min(draws.shape[0], int(loo_draws))
        mean_ess = float(np.mean(result.posterior.diagnostics.ess))
        reff = min(1.0, mean_ess / s_used) if math.isfinite(mean_ess) and mean_ess > 0 else 1.0
        loos[name] = loo_grouped(model, draws, reff=reff, max_draws=loo_draws)
        fits[name], models[name] = result, model
        seconds[name] = time.perf_counter() - t1

    rows, chosen, best = compare_loo(loos, margin=margin, margin_se=margin_se)
    rows = [{"name": r["name"], "nparams": int(models[r["name"]].ndim),
             **{k: v for k, v in r.items() if k != "name"}, "seconds": float(seconds[r["name"]])} for r in rows]
    crow = next(r for r in rows if r["chosen"])
    rule = (f"simplest candidate with delta_elpd >= -max({margin:g}, {margin_se:g} * se_delta) nats relative to "
            f"the best ({best}); chosen {chosen}: delta_elpd = {crow['delta_elpd']:.2f}, "
            f"se_delta = {crow['se_delta']:.2f}")
    return SelectionResult(table=rows, chosen=chosen, best=best, rule=rule, fits=fits, loo=loos, models=models,
                           seconds=time.perf_counter() - t0)
