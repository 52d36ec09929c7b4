"""Posterior inference for the completeness (and purity) models.

:func:`fit` chains :func:`fit_map` (the MAP point), :func:`laplace` (the Gaussian approximation
there) and the posterior draws (:func:`importance_posterior`, once more with heavier tails where it fails;
NUTS in :func:`comest_bayes.bayes.nuts.nuts_posterior` where that fails too; emcee in
:func:`sample_posterior`, the reference), all in the model's unconstrained parameters.  The model contract, the
sampler's convergence rules and the seeding: ``docs/bayesian.md`` ("Inference").
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import solve_triangular
from scipy.optimize import minimize

from comest_bayes.errors import InputError
from comest_bayes.io.jsonio import json_float
from comest_bayes.bayes.psis import psis_log_weights
from comest_bayes.bayes.nuts import nuts_posterior, supports_nuts
from comest_bayes.bayes.samples import SAMPLERS, PosteriorSamples
from comest_bayes.seeding import Stream, int_seed_for, rng_for

__all__ = [
    "InferenceWarning",
    "ConvergenceWarning",
    "IdentifiabilityWarning",
    "MapResult",
    "LaplaceResult",
    "PosteriorDiagnostics",
    "PosteriorSamples",
    "FitResult",
    "fit_map",
    "laplace",
    "sample_posterior",
    "effective_sample_size",
    "importance_posterior",
    "ImportanceDiagnostics",
    "fit",
]

#: Value of ``-log_prob`` returned to the optimizer where the model is not finite:
#: large enough to be rejected by every line search, small enough to keep the
#: optimizer's interpolation arithmetic finite.
_PENALTY = 1.0e15

#: Acceptance fractions outside this range are reported (stretch move rule of thumb).
ACCEPTANCE_RANGE = (0.15, 0.8)


class InferenceWarning(UserWarning):
    """Base class of the warnings of :mod:`comest_bayes.bayes.inference`."""


class ConvergenceWarning(InferenceWarning):
    """An optimizer or sampler did not meet its convergence criteria."""


class IdentifiabilityWarning(InferenceWarning):
    """The data do not constrain a parameter: the prior does (e.g. perfectly separated outcomes)."""


# --------------------------------------------------------------------------- results


@dataclass
class MapResult:
    """Result of :func:`fit_map`.

    Attributes
    ----------
    theta : ndarray, shape (D,)
        Best (highest log posterior) optimum, unconstrained parameters.
    log_prob : float
        Log posterior at ``theta`` (nats, up to the model's constant).
    converged : bool
        True when at least two starts reached the best value within
        ``tol_nats`` or the optimizer reported success for the best start.
    nconverged : int
        Number of starts whose optimum is within ``tol_nats`` of the best.
    message : str
        Human-readable summary (optimizer message of the best start, counts).
    start_log_probs : ndarray, shape (nstarts,)
        Final log posterior of every start (``-inf`` for failed starts).
    warnings : list of str
        Messages of the warnings issued (collapsed width, ...).
    """

    theta: np.ndarray
    log_prob: float
    converged: bool
    nconverged: int
    message: str
    start_log_probs: np.ndarray = field(default_factory=lambda: np.zeros(0))
    warnings: list = field(default_factory=list)


@dataclass
class LaplaceResult:
    """Gaussian (Laplace) approximation of the posterior at the MAP.

    Attributes
    ----------
    mean : ndarray, shape (D,)
        The MAP, unconstrained parameters.
    cov : ndarray, shape (D, D)
        ``inv(-H)``, ``H`` the Hessian of the log posterior at ``mean``;
        regularized (eigenvalue floor) when ``-H`` is not positive definite.
    ok : bool
        False when ``-H`` was not finite or not positive definite and had to be
        regularized; ``cov`` is then only a rough scale for starting walkers.
    message : str
        What was done, and the condition number.
    condition : float
        Condition number (largest / smallest eigenvalue) of ``-H``; ``inf``
        when not positive definite.
    """

    mean: np.ndarray
    cov: np.ndarray
    ok: bool
    message: str
    condition: float = float("nan")

    @property
    def sd(self) -> np.ndarray:
        """Marginal standard deviations ``sqrt(diag(cov))``, shape (D,)."""
        return np.sqrt(np.diag(self.cov))


@dataclass
class PosteriorDiagnostics:
    """Convergence diagnostics of :func:`sample_posterior`.

    Also readable as a mapping (``diag["tau"]``) for the contract's dict form.

    Attributes
    ----------
    names : list of str
        Parameter names (the model's ``names``).
    tau : ndarray, shape (D,)
        Integrated autocorrelation time of every parameter, in steps.
    ess : ndarray, shape (D,)
        Effective sample size ``nwalkers * (nsteps - burn) / tau``.
    acceptance_mean, acceptance_min : float
        Mean and smallest acceptance fraction over the walkers.
    nsteps : int
        Steps run (per walker).
    burn : int
        Steps discarded as burn-in (``ceil(2 max tau)``, at most half the chain).
    nwalkers : int
    min_ess : float
        The requested minimum ESS.
    converged : bool
        ``nsteps > 50 max tau`` and ``ess >= min_ess`` for every parameter.
    warnings : list of str
        Messages of the warnings issued.
    seconds : float
        Wall time of the sampling, seconds.
    """

    names: list
    tau: np.ndarray
    ess: np.ndarray
    acceptance_mean: float
    acceptance_min: float
    nsteps: int
    burn: int
    nwalkers: int
    min_ess: float
    converged: bool
    warnings: list
    seconds: float

    def __getitem__(self, key):
        return getattr(self, key)

    def to_dict(self) -> dict:
        """JSON-ready dict (lists of floats; non-finite numbers become ``None``)."""
        return {
            "method": "emcee",
            "names": list(self.names),
            "tau": [json_float(t) for t in self.tau],
            "ess": [json_float(e) for e in self.ess],
            "acceptance_mean": json_float(self.acceptance_mean),
            "acceptance_min": json_float(self.acceptance_min),
            "nsteps": int(self.nsteps),
            "burn": int(self.burn),
            "nwalkers": int(self.nwalkers),
            "min_ess": json_float(self.min_ess),
            "converged": bool(self.converged),
            "warnings": list(self.warnings),
            "seconds": json_float(self.seconds),
        }


@dataclass
class FitResult:
    """Result of :func:`fit`: MAP, Laplace approximation and (optionally) posterior draws.

    ``seconds`` is the total wall time.
    """

    map: MapResult
    laplace: LaplaceResult
    posterior: PosteriorSamples | None
    seconds: float

    def draws(self) -> np.ndarray:
        """Posterior draws ``(S, D)`` (the emcee samples, or the MAP as one draw when not sampled)."""
        if self.posterior is not None:
            return self.posterior.samples
        return self.map.theta[None, :]


# --------------------------------------------------------------------------- MAP


def _objective(model):
    """``x -> (-log_prob, -grad)`` in float64, non-finite values replaced by a penalty."""

    def fun(x):
        value, grad = model.value_and_grad(np.asarray(x, dtype=np.float64))
        value = float(value)
        grad = np.asarray(grad, dtype=np.float64)
        if not math.isfinite(value) or not np.all(np.isfinite(grad)):
            return _PENALTY, np.zeros_like(x, dtype=np.float64)
        return -value, -grad

    return fun


def _finite_log_prob(model, theta) -> float:
    # through value_and_grad, which the optimizer compiles anyway: a separate log_prob program would cost
    # one more trace and compile per process for a handful of calls
    value = float(model.value_and_grad(np.asarray(theta, dtype=np.float64))[0])
    return value if math.isfinite(value) else -math.inf


#: Rows per call of ``model.log_prob_batch`` from the importance sampler and the selection's Laplace
#: draws: every call has this one shape (one compiled program), whatever the number of draws.
LOG_PROB_BLOCK = 256


def log_prob_rows(model, thetas) -> np.ndarray:
    """``model.log_prob_batch`` in calls of exactly :data:`LOG_PROB_BLOCK` rows (the last padded)."""
    thetas = np.asarray(thetas, dtype=np.float64)
    n = thetas.shape[0]
    out = np.empty(n)
    for start in range(0, n, LOG_PROB_BLOCK):
        block = thetas[start:start + LOG_PROB_BLOCK]
        nb = block.shape[0]
        if nb < LOG_PROB_BLOCK:
            block = np.concatenate([block, np.repeat(block[-1:], LOG_PROB_BLOCK - nb, axis=0)])
        out[start:start + nb] = np.asarray(model.log_prob_batch(block), dtype=np.float64)[:nb]
    return out


def _width_check(model, theta, w_min: float) -> str | None:
    """Message when the model's width parameter ``w`` collapsed below ``w_min`` mag, else None."""
    transform = getattr(model, "transform", None)
    if transform is None:
        return None
    try:
        params = transform(np.asarray(theta, dtype=np.float64))
    except Exception:  # a model without a usable transform: nothing to check
        return None
    if not isinstance(params, dict) or "w" not in params:
        return None
    w = np.asarray(params["w"], dtype=np.float64)
    if w.size and np.nanmin(w) < w_min:
        return (f"MAP width w = {float(np.nanmin(w)):.3g} mag is below {w_min} mag: the outcomes are (nearly) "
                f"perfectly separated in magnitude, so the data only bound the transition width from above and "
                f"its value (and the posterior's lower tail) is set by the prior on w. Inject more sources "
                f"around m50 or treat w as an upper limit.")
    return None


def fit_map(model, *, nstarts: int = 6, seed: int, jitter: float = 0.5, method: str = "L-BFGS-B",
            maxiter: int = 5000, tol_nats: float = 1e-3, w_min: float = 0.01, start=None) -> MapResult:
    """Maximum a posteriori parameters from several optimizer starts.

    Parameters
    ----------
    model : CompletenessModel-like
        See ``docs/bayesian.md`` ("Inference") for the contract.
    nstarts : int, default 6
        Number of starts: ``model.initial()`` and ``nstarts - 1`` jittered
        copies ``initial + jitter * N(0, 1)`` (per parameter, in the
        unconstrained space).  Jittered starts with non-finite log posterior
        are redrawn with half the jitter (up to 20 times).
    seed : int
        Root seed of the jitter (stream ``"map-starts"``).
    jitter : float, default 0.5
        Standard deviation of the start jitter, in unconstrained units.
    method : {"L-BFGS-B", "BFGS", "newton"}
        SciPy optimizer; all use the exact gradient ``model.value_and_grad``;
        ``newton`` is SciPy's ``trust-exact`` with the model's Hessian
        (``model.hessian``): few, costlier iterations, the fastest from a warm
        start.
    maxiter : int, default 5000
        Iteration limit per start.
    tol_nats : float, default 1e-3
        Two optima within this many nats of log posterior count as the same.
    w_min : float, default 0.01
        A MAP width ``w`` (from ``model.transform``) below this many magnitudes
        triggers an :class:`IdentifiabilityWarning` (perfect separation).
    start : array, optional
        A warm start (e.g. the MAP of a simpler model): when it has a finite
        log posterior it is the first of the ``nstarts`` starts, the second
        is ``initial()`` and jittered copies are drawn around the warm start.

    Returns
    -------
    MapResult

    Raises
    ------
    InputError
        When ``model.initial()`` has a non-finite log posterior, or every
        start failed.

    Warns
    -----
    ConvergenceWarning
        When only one start reached the best optimum and the optimizer did not
        report success there.
    IdentifiabilityWarning
        When the MAP width collapsed (see ``w_min``).
    """
    if method not in ("L-BFGS-B", "BFGS", "newton"):
        raise InputError(f"fit_map: method must be 'L-BFGS-B', 'BFGS' or 'newton', got {method!r}")
    if nstarts < 1:
        raise InputError(f"fit_map: nstarts must be >= 1, got {nstarts}")
    x0 = np.asarray(model.initial(), dtype=np.float64).reshape(-1)
    if x0.shape != (model.ndim,):
        raise InputError(f"fit_map: model.initial() has shape {x0.shape}, expected ({model.ndim},)")
    if not math.isfinite(_finite_log_prob(model, x0)):
        raise InputError(f"fit_map: the model's initial point {x0.tolist()} has a non-finite log posterior; "
                         f"check the data (empty?) and the priors of {list(model.names)}")
    rng = rng_for(seed, Stream.MAP_STARTS)
    starts = [x0]
    if start is not None:
        warm = np.asarray(start, dtype=np.float64).reshape(-1)
        if warm.shape == x0.shape and math.isfinite(_finite_log_prob(model, warm)):
            starts = [warm, x0][:nstarts]
            x0 = warm
    for _ in range(nstarts - len(starts)):
        scale = jitter
        for _attempt in range(20):
            x = x0 + scale * rng.standard_normal(x0.size)
            if math.isfinite(_finite_log_prob(model, x)):
                break
            scale *= 0.5
        starts.append(x)

    fun = _objective(model)
    def neg_hessian(x):
        h = -np.asarray(model.hessian(np.asarray(x, dtype=np.float64)), dtype=np.float64)
        return np.where(np.isfinite(h), h, 0.0)

    hess = neg_hessian if method == "newton" else None
    if method == "L-BFGS-B":
        options = {"maxiter": maxiter, "ftol": 1e-13, "gtol": 1e-7, "maxcor": 20}
    elif method == "newton":
        # trust-region Newton with the model's Hessian: a few iterations from a warm start
        options = {"maxiter": 200, "gtol": 1e-6}
    else:
        options = {"maxiter": maxiter, "gtol": 1e-6}
    results = []
    for x in starts:
        try:
            if hess is not None:
                res = minimize(fun, x, jac=True, hess=hess, method="trust-exact", options=options)
            else:
                res = minimize(fun, x, jac=True, method=method, options=options)
        except (ValueError, FloatingPointError, ArithmeticError) as err:  # pragma: no cover - defensive
            results.append((-math.inf, x, False, f"optimizer error: {err}"))
            continue
        lp = _finite_log_prob(model, res.x)
        results.append((lp, np.asarray(res.x, dtype=np.float64), bool(res.success), str(res.message)))

    lps = np.array([r[0] for r in results])
    if not np.any(np.isfinite(lps)):
        raise InputError(f"fit_map: all {nstarts} optimizer starts ended at a non-finite log posterior; "
                         f"messages: {[r[3] for r in results]}")
    ibest = int(np.argmax(lps))
    best_lp, best_theta, best_success, best_msg = results[ibest]
    nconv = int(np.sum(lps >= best_lp - tol_nats))
    converged = nconv >= 2 or best_success
    message = (f"best of {nstarts} starts: log_prob = {best_lp:.6f}; {nconv} start(s) within {tol_nats} nats; "
               f"optimizer ({method}): {best_msg}")
    issued = []
    if not converged:
        text = (f"MAP not confirmed: {message}. Increase nstarts or maxiter, or check the model's initial point.")
        warnings.warn(text, ConvergenceWarning, stacklevel=2)
        issued.append(text)
    width_msg = _width_check(model, best_theta, w_min)
    if width_msg is not None:
        warnings.warn(width_msg, IdentifiabilityWarning, stacklevel=2)
        issued.append(width_msg)
    return MapResult(theta=best_theta, log_prob=float(best_lp), converged=bool(converged), nconverged=nconv,
                     message=message, start_log_probs=lps, warnings=issued)


# --------------------------------------------------------------------------- Laplace


def laplace(model, theta_map, *, cond_warn: float = 1e10, rcond: float = 1e-12, max_sd: float = 1.0,
            w_min: float = 0.01) -> LaplaceResult:
    """Laplace (Gaussian) approximation of the posterior at the MAP.

    Parameters
    ----------
    model : CompletenessModel-like
        Needs ``hessian(theta) -> (D, D)`` of the log posterior.
    theta_map : array_like, shape (D,)
        The MAP (e.g. ``fit_map(...).theta``).
    cond_warn : float, default 1e10
        Condition number of ``-H`` above which an :class:`IdentifiabilityWarning`
        is issued (some direction is barely constrained).
    rcond : float, default 1e-12
        ``-H`` counts as positive definite when all eigenvalues exceed
        ``rcond`` times the largest.
    max_sd : float, default 1.0
        When ``-H`` is not positive definite, its eigenvalues below
        ``max(rcond * largest, 1 / max_sd**2)`` are raised to that floor, so
        the directions the curvature does not constrain get a standard
        deviation of at most ``max_sd`` (unconstrained units); ``ok`` is
        then False.
    w_min : float, default 0.01
        Collapsed-width check as in :func:`fit_map` (message only; the warning
        is issued by :func:`fit_map`).

    Returns
    -------
    LaplaceResult
        ``cov`` is symmetric positive definite in all cases.

    Warns
    -----
    IdentifiabilityWarning
        When ``-H`` is ill-conditioned or not positive definite.
    """
    theta = np.asarray(theta_map, dtype=np.float64).reshape(-1)
    d = theta.size
    hess = np.asarray(model.hessian(theta), dtype=np.float64)
    if hess.shape != (d, d):
        raise InputError(f"laplace: model.hessian returned shape {hess.shape}, expected ({d}, {d})")
    notes = []
    if not np.all(np.isfinite(hess)):
        bad = np.unique(np.nonzero(~np.isfinite(hess))[0])
        names = [model.names[i] for i in bad]
        notes.append(f"Hessian not finite in rows {names}; replaced by the prior-scale floor there")
        hess = np.where(np.isfinite(hess), hess, 0.0)
    prec = -0.5 * (hess + hess.T)
    lam, vec = np.linalg.eigh(prec)
    lam_max = float(lam[-1]) if lam.size else 1.0
    pd = lam_max > 0 and bool(np.all(lam > rcond * lam_max)) and not notes
    if pd:
        condition = float(lam[-1] / lam[0])
        cov = (vec / lam) @ vec.T
        ok = True
        notes.append(f"-H positive definite, condition number {condition:.3g}")
    else:
        condition = math.inf
        floor = max(rcond * max(lam_max, 0.0), 1.0 / max_sd**2)
        low = lam <= floor
        weak = [dict(zip(model.names, np.round(vec[:, i], 3).tolist())) for i in np.nonzero(low)[0]]
        lam_reg = np.where(low, floor, lam)
        cov = (vec / lam_reg) @ vec.T
        ok = False
        notes.append(f"-H not positive definite (eigenvalues {np.array2string(lam, precision=3)}); "
                     f"{int(low.sum())} eigenvalue(s) raised to {floor:.3g} (sd <= {max_sd} along them); "
                     f"unconstrained direction(s): {weak}")
    cov = 0.5 * (cov + cov.T)
    message = "; ".join(notes)
    width_msg = _width_check(model, theta, w_min)
    if width_msg is not None:
        message += "; " + width_msg
    if not ok or condition > cond_warn:
        warnings.warn(f"Laplace approximation: {message}. Some parameter combination is constrained by the "
                      f"prior, not the data.", IdentifiabilityWarning, stacklevel=2)
    return LaplaceResult(mean=theta, cov=cov, ok=ok, message=message, condition=condition)


# --------------------------------------------------------------------------- MCMC


def _integrated_time(chain: np.ndarray) -> np.ndarray:
    """Integrated autocorrelation time per parameter of ``chain`` (nsteps, nwalkers, D); inf when undefined."""
    import emcee

    if chain.shape[0] < 2:
        return np.full(chain.shape[-1], np.inf)
    with np.errstate(invalid="ignore", divide="ignore"):
        tau = np.asarray(emcee.autocorr.integrated_time(chain, c=5, tol=0, quiet=True), dtype=np.float64)
    # A parameter that never moved has a zero-variance chain: NaN tau, i.e. no information.
    return np.where(np.isfinite(tau) & (tau > 0), tau, np.inf)


def effective_sample_size(chain, discard: int = 0) -> np.ndarray:
    """Effective sample size of every parameter of an ensemble chain.

    Parameters
    ----------
    chain : array_like, shape (nsteps, nwalkers, D)
        Chain of an ensemble sampler (``sampler.get_chain()``).
    discard : int, default 0
        Leading steps to drop (burn-in) before estimating.

    Returns
    -------
    ndarray, shape (D,)
        ``nwalkers * n / tau_j`` with ``n`` the kept steps and ``tau_j`` the
        integrated autocorrelation time (:func:`emcee.autocorr.integrated_time`,
        ``c = 5``, no length check); 0 for a parameter that never moved.
    """
    chain = np.asarray(chain, dtype=np.float64)
    if chain.ndim != 3:
        raise InputError(f"effective_sample_size: chain must have shape (nsteps, nwalkers, D), got {chain.shape}")
    kept = chain[int(discard):]
    tau = _integrated_time(kept)
    return kept.shape[0] * kept.shape[1] / tau


def _default_nwalkers(ndim: int) -> int:
    n = 2 * ndim + 2
    n += n % 2
    return max(16, n)


def _initial_walkers(model, lap: LaplaceResult, nwalkers: int, rng: np.random.Generator, lp_fn):
    """Walkers drawn from the Laplace Gaussian; those with non-finite log posterior are redrawn."""
    d = lap.mean.size
    chol = np.linalg.cholesky(lap.cov)
    pos = lap.mean + rng.standard_normal((nwalkers, d)) @ chol.T
    lp = lp_fn(pos)
    scale = 1.0
    for _ in range(30):
        bad = ~np.isfinite(lp)
        if not bad.any():
            break
        scale *= 0.7
        pos[bad] = lap.mean + scale * (rng.standard_normal((int(bad.sum()), d)) @ chol.T)
        lp[bad] = lp_fn(pos[bad])
    if not np.all(np.isfinite(lp)):
        raise InputError(f"sample_posterior: could not place {int((~np.isfinite(lp)).sum())} of {nwalkers} walkers "
                         f"at a finite log posterior around the Laplace mean {lap.mean.tolist()}; check the MAP")
    return pos, lp


def _next_chunk(nsteps: int, tau_max: float, nwalkers: int, min_ess: float, chunk: int) -> int:
    """Steps to run before the next check: up to where the current tau says both criteria hold, +10%.

    At least ``max(20, nsteps // 10)`` (tau estimates from short chains are biased low, so a
    prediction can fall short) and at most ``chunk``.
    """
    if not math.isfinite(tau_max):
        return chunk
    needed = max(50.0 * tau_max + 1.0, math.ceil(2.0 * tau_max) + min_ess * tau_max / nwalkers)
    step = int(math.ceil(1.1 * needed)) - nsteps
    return int(min(chunk, max(step, 20, nsteps // 10)))


def _moves(moves):
    """emcee moves for the names ``"de"`` and ``"stretch"``; other values pass through."""
    import emcee

    if isinstance(moves, str):
        if moves == "de":
            return emcee.moves.DEMove()
        if moves == "stretch":
            return emcee.moves.StretchMove()
        raise InputError(f"sample_posterior: moves must be 'de', 'stretch' or emcee move objects, got {moves!r}")
    return moves


def sample_posterior(model, lap: LaplaceResult, *, seed: int, nwalkers: int | None = None,
                     min_ess: float = 1000, max_steps: int = 20000, chunk: int = 500, progress: bool = False,
                     moves="de") -> PosteriorSamples:
    """Posterior draws with emcee, run until the autocorrelation criteria hold.

    Parameters
    ----------
    model : CompletenessModel-like
        Needs ``log_prob_batch(thetas (W, D)) -> (W,)`` (emcee is run with
        ``vectorize=True``) and ``names``.
    lap : LaplaceResult
        Walkers start as independent draws from ``N(lap.mean, lap.cov)``
        (redrawn closer to the mean where the log posterior is not finite).
    seed : int
        Root seed: walker positions from stream ``"walkers"``, emcee's
        generator from ``int_seed_for(seed, Stream.EMCEE)``.
    nwalkers : int, optional
        Default ``2 D + 2`` rounded up to even, at least 16.
    min_ess : float, default 1000
        Required effective sample size of every parameter.
    max_steps : int, default 20000
        Hard limit on steps per walker.
    chunk : int, default 500
        Largest number of steps between convergence checks.  After the first
        chunk, the next check is placed where the current tau estimate says
        the criteria will hold (+10%, at least 20 steps and 10% of the chain),
        so the run overshoots the required length by little.
    progress : bool, default False
        emcee's progress bar.
    moves : {"de", "stretch"} or emcee move(s), default "de"
        Proposal: ``"de"`` is emcee's differential-evolution move
        (``DEMove``; ter Braak 2006, Stat. Comput. 16, 239), ``"stretch"``
        emcee's default stretch move (Goodman & Weare 2010); anything else
        is passed to :class:`emcee.EnsembleSampler` as is.  On the
        5-parameter completeness posteriors (near-Gaussian) DE had tau ~ 15-18
        steps against ~ 60 for the stretch move, so it reaches the stopping
        rule 3-4 times sooner, with the same (correct) posterior widths.
        emcee's ``DESnookerMove`` is deliberately not used: in emcee 3.1.6
        its Metropolis factor has the exponent ``(ndim - 1) / 2`` instead of
        ter Braak & Vrugt's (2008) ``ndim - 1``, and on a 5-D Gaussian it
        returned standard deviations ~12% too small.

    Returns
    -------
    PosteriorSamples
        See ``docs/bayesian.md`` ("Inference") for the stopping rule, burn-in and ESS.

    Warns
    -----
    ConvergenceWarning
        When ``max_steps`` was reached before the criteria held, and when the
        mean acceptance fraction is outside ``[0.15, 0.8]``.
    """
    import emcee

    t0 = time.perf_counter()
    d = int(model.ndim)
    nwalkers = _default_nwalkers(d) if nwalkers is None else int(nwalkers)
    if nwalkers < 2 * d or nwalkers % 2:
        raise InputError(f"sample_posterior: nwalkers must be even and >= 2 * ndim = {2 * d}, got {nwalkers}")
    if max_steps < 1 or chunk < 1:
        raise InputError(f"sample_posterior: max_steps and chunk must be >= 1, got {max_steps} and {chunk}")
    if lap.mean.shape != (d,) or lap.cov.shape != (d, d):
        raise InputError(f"sample_posterior: Laplace mean/cov shapes {lap.mean.shape}/{lap.cov.shape} do not match "
                         f"ndim = {d}")

    def lp_fn(thetas):
        out = np.array(model.log_prob_batch(np.ascontiguousarray(thetas, dtype=np.float64)), dtype=np.float64)
        out[~np.isfinite(out)] = -np.inf  # NaN / +inf are invalid points, emcee rejects NaN outright
        return out

    rng = rng_for(seed, Stream.WALKERS)
    pos, lp0 = _initial_walkers(model, lap, nwalkers, rng, lp_fn)
    random_state = np.random.RandomState(int_seed_for(seed, Stream.EMCEE)).get_state()
    state = emcee.State(pos, log_prob=lp0, random_state=random_state)
    sampler = emcee.EnsembleSampler(nwalkers, d, lp_fn, vectorize=True, moves=_moves(moves))

    nsteps = 0
    converged = False
    tau = np.full(d, np.inf)
    n = chunk
    while nsteps < max_steps:
        n = min(n, max_steps - nsteps)
        state = sampler.run_mcmc(state, n, progress=progress)
        nsteps += n
        tau = _integrated_time(sampler.get_chain())
        tau_max = float(np.max(tau))
        burn = int(math.ceil(2.0 * tau_max)) if math.isfinite(tau_max) else nsteps
        ess = nwalkers * max(nsteps - burn, 0) / tau
        if nsteps > 50.0 * tau_max and np.all(ess >= min_ess):
            converged = True
            break
        n = _next_chunk(nsteps, tau_max, nwalkers, min_ess, chunk)

    chain = sampler.get_chain()
    log_prob = sampler.get_log_prob()
    tau_max = float(np.max(tau))
    burn = int(math.ceil(2.0 * tau_max)) if math.isfinite(tau_max) else nsteps // 2
    burn = min(burn, nsteps // 2)
    ess = nwalkers * (nsteps - burn) / tau
    acc = np.asarray(sampler.acceptance_fraction, dtype=np.float64)
    acc_mean, acc_min = float(acc.mean()), float(acc.min())
    names = list(getattr(model, "names", [f"theta{i}" for i in range(d)]))

    issued = []
    if not converged:
        worst = int(np.argmin(ess))
        text = (f"emcee did NOT converge within max_steps = {max_steps}: nsteps = {nsteps}, "
                f"tau = {dict(zip(names, np.round(tau, 1).tolist()))} (need nsteps > 50 * max tau = "
                f"{50 * tau_max:.0f}), ESS = {dict(zip(names, np.round(ess, 0).tolist()))} (need >= {min_ess}; "
                f"worst {names[worst]} = {ess[worst]:.0f}), acceptance mean {acc_mean:.3f} (min {acc_min:.3f}), "
                f"nwalkers = {nwalkers}, burn = {burn}. The posterior summaries are unreliable: raise max_steps "
                f"(about {int(math.ceil(max(50 * tau_max, burn + min_ess * tau_max / nwalkers))) if math.isfinite(tau_max) else 'many more'} "
                f"steps needed) or reparametrize the model.")
        warnings.warn(text, ConvergenceWarning, stacklevel=2)
        issued.append(text)
    if not (ACCEPTANCE_RANGE[0] <= acc_mean <= ACCEPTANCE_RANGE[1]):
        text = (f"emcee mean acceptance fraction {acc_mean:.3f} (min {acc_min:.3f}) is outside "
                f"[{ACCEPTANCE_RANGE[0]}, {ACCEPTANCE_RANGE[1]}] after {nsteps} steps with {nwalkers} walkers: "
                f"the walkers are {'stuck' if acc_mean < ACCEPTANCE_RANGE[0] else 'taking tiny steps'}; "
                f"check the posterior for multimodality or a bad start.")
        warnings.warn(text, ConvergenceWarning, stacklevel=2)
        issued.append(text)

    diagnostics = PosteriorDiagnostics(
        names=names, tau=tau, ess=ess, acceptance_mean=acc_mean, acceptance_min=acc_min, nsteps=nsteps,
        burn=burn, nwalkers=nwalkers, min_ess=float(min_ess), converged=bool(converged), warnings=issued,
        seconds=time.perf_counter() - t0)
    samples = chain[burn:].reshape(-1, d).copy()
    return PosteriorSamples(samples=samples, chain=chain, log_prob=log_prob, diagnostics=diagnostics)


# --------------------------------------------------------------------------- importance sampling


#: Effective sample size the importance-sampled posterior must reach (at most ``min_ess``): with 400
#: effective draws the Monte Carlo error of a 95% interval's end is about a tenth of the posterior sd.
IS_MIN_ESS = 400.0

#: Longest emcee run (steps per walker) when importance sampling fails, ``sampler="auto"`` falls back and the
#: model has no traceable density for NUTS.
FALLBACK_MAX_STEPS = 5000

#: Moment matching estimates a full covariance only from at least this many effective draws per
#: parameter; with fewer it rescales the Laplace covariance's spreads and keeps its correlations.  At
#: 10 per parameter the estimated covariance's own error is about a third of its scale (relative
#: error ~ sqrt(d / ESS)).  A 6-parameter Richards posterior with a curved log-nu ridge (ESS ~ 500)
#: needs the full covariance; the demo's 49-parameter spline (ESS 239) cannot estimate it.
FULL_MATCH_ESS = 10.0

#: Rounds of moment matching after the first importance-sampling round (each only when the previous
#: round's k-hat exceeds 0.5 or its effective sample size falls short).
ADAPT_ROUNDS = 3

#: Pareto k-hat of the importance weights below which the importance-sampled posterior is
#: trusted (Vehtari et al. 2024, JMLR 25(72): above 0.7 the estimate's error converges too slowly).
IS_KHAT_MAX = 0.7

#: Degrees of freedom of ``fit``'s second importance sampler, tried before NUTS where the first (a t with 5)
#: fails: heavier tails cover the one-sided tails of a plateau or a floor near its bound.  On the 31 honesty
#: tables of 2026-11-29 whose first try failed it passed on 21, at 2-3 CPU-s each (NUTS took 11-84), with
#: the medians of m50, m90 and f at m50 -+ 0.3 within 0.21 posterior sd of NUTS's and the ends of their 95%
#: intervals within 0.40 (benchmarks/README.md, "bench_samplers.py").
IS_RETRY_DF = 3.0


@dataclass
class ImportanceDiagnostics:
    """Diagnostics of :func:`importance_posterior`.

    Attributes
    ----------
    khat : float
        Pareto k-hat of the importance weights (posterior over proposal).
    ess : float
        Effective sample size of the smoothed weights ``1 / sum w^2``.
    ndraws : int
        Proposal draws.
    nout : int
        Equal-weight draws returned (resampled).
    df : float
        Degrees of freedom of the Student-t proposal.
    converged : bool
        ``khat <= IS_KHAT_MAX`` and ``ess >= min_ess``.
    warnings : list of str
    seconds : float
    """

    khat: float
    ess: float
    ndraws: int
    nout: int
    df: float
    min_ess: float
    converged: bool
    warnings: list
    seconds: float
    method: str = "importance"

    def __getitem__(self, key):
        return getattr(self, key)

    def to_dict(self) -> dict:
        return {"method": self.method, "khat": json_float(self.khat), "ess": json_float(self.ess),
                "ndraws": int(self.ndraws), "nout": int(self.nout), "df": float(self.df),
                "min_ess": json_float(self.min_ess), "converged": bool(self.converged),
                "warnings": list(self.warnings), "seconds": json_float(self.seconds)}


def _t_draws(model, mean, chol, df, ndraws, rng):
    """Student-t proposal draws (scale ``chol @ chol.T``) and their log posterior (-inf where undefined)."""
    z = rng.standard_normal((ndraws, mean.size))
    chi2 = rng.chisquare(df, size=ndraws)
    draws = mean + (z @ chol.T) * np.sqrt(df / chi2)[:, None]
    log_p = log_prob_rows(model, draws)
    log_p[~np.isfinite(log_p)] = -np.inf
    return draws, log_p


def _mixture_log_q(x, components, df):
    """Log density at ``x`` (N, d) of the mixture of t proposals ``[mean, chol, n]`` weighted by their n.

    Constants shared by every component (same ``df`` and dimension) are dropped: they cancel when the
    importance weights are normalised.
    """
    d = x.shape[1]
    total = sum(c[2] for c in components)
    terms = []
    for mean, chol, n in components:
        z = solve_triangular(chol, (x - mean).T, lower=True)
        maha = np.sum(z * z, axis=0)
        terms.append(math.log(n / total) - np.sum(np.log(np.diag(chol))) - 0.5 * (df + d) * np.log1p(maha / df))
    terms = np.stack(terms)
    top = np.max(terms, axis=0)
    return top + np.log(np.sum(np.exp(terms - top), axis=0))


def _psis(lw_raw):
    """PSIS-smoothed normalised weights, their effective sample size and the Pareto k-hat."""
    finite = np.isfinite(lw_raw)
    if finite.sum() < 10:
        raise InputError(f"importance_posterior: only {int(finite.sum())} of {lw_raw.size} proposal draws have a "
                         "finite log posterior; check the MAP and the Laplace covariance.")
    lw_s, khat = psis_log_weights(lw_raw)
    w = np.exp(lw_s - np.max(lw_s))
    w /= w.sum()
    return w, float(1.0 / np.sum(w * w)), float(khat)


#: Largest number of proposal draws :func:`importance_posterior` pools from its final proposal
#: while the effective sample size falls short (and k-hat says the weights can be trusted).  Pooled
#: draws cost one likelihood evaluation each, far less than the emcee fallback: on a 300,000-outcome
#: spline fit (2686 cells) with ESS 383 of 8000 the fallback ran 5000 emcee steps (220,000
#: evaluations, 100 CPU-s) and still did not meet its own convergence rule.
IS_MAX_DRAWS = 32000


def importance_posterior(model, lap: LaplaceResult, *, seed: int, ndraws: int = 2000, nout: int = 2000,
                         df: float = 5.0, inflate: float = 1.3, min_ess: float = 1000.0,
                         adapt: bool = True, max_draws: int | None = None,
                         stream: str = Stream.IMPORTANCE) -> PosteriorSamples:
    """Posterior draws by Pareto-smoothed importance sampling from the Laplace approximation.

    Draws ``ndraws`` points from a multivariate Student-t with ``df``
    degrees of freedom centred on the MAP with the Laplace covariance times
    ``inflate**2`` (its heavier tails and larger scale cover a posterior a
    little wider or more skewed than the Gaussian), weights them by
    posterior over proposal, smooths the largest weights with PSIS
    (:func:`comest_bayes.bayes.psis.psis_log_weights`) and resamples ``nout`` equal-weight draws
    (systematic resampling, seeded).

    Two ways to a better estimate, each used only when needed:

    * **Moment matching** (``adapt``) when the proposal's shape is wrong
      (k-hat above 0.5): draw afresh from a t with the importance-weighted
      mean and covariance of the last round (at most :data:`ADAPT_ROUNDS`
      times); this recovers most of what a skewed posterior costs.  With
      fewer than :data:`FULL_MATCH_ESS` effective draws per parameter the
      match keeps the Laplace correlations and only moves the mean and
      rescales each parameter's spread to its weighted sd (the first two
      affine steps of Paananen, Piironen, Buerkner & Vehtari 2021,
      "Implicitly adaptive importance sampling"; the full covariance is
      their third).  The
      draws of every round are kept: each is weighted against the mixture
      of all proposals so far (multiple importance sampling with the
      balance heuristic, Veach & Guibas 1995), so a matched round adds to
      the earlier draws rather than replacing them.
    * **Pooling** when the shape is right but the effective sample size is
      short of ``min_ess``: add draws from the last proposal (as many as
      the current efficiency says are missing, +10%, at least ``ndraws / 4``)
      until it is reached, unless that would take more than ``max_draws``
      (they raise that proposal's share of the mixture, and all weights
      are smoothed again).
    * **Dilution** when the pooled k-hat exceeds 0.7 although the last
      proposal's own draws fit it (their k-hat at most 0.5): an earlier
      round's tail dominates the mixture, so batches of ``ndraws`` from the
      last proposal are added, at most as many draws as the rounds made.
      On an adaptive design fit of the spline rung (761 injections) the
      pooled k-hat was 0.82 after a moment-matched round whose own was
      0.21; one more batch gave 0.58, and the refit cost 1.7 CPU-s instead
      of emcee's 22.7.

    The Pareto k-hat of the final weights says whether the result can be
    trusted: at or below :data:`IS_KHAT_MAX` (0.7) the importance-sampling
    estimate converges at the usual rate; above, the caller should run MCMC
    (:func:`sample_posterior`).

    Parameters
    ----------
    model : CompletenessModel-like
        Needs ``log_prob_batch``.
    lap : LaplaceResult
    seed : int
        Root seed (stream ``"importance"``).
    ndraws, nout : int
        Proposal draws per batch and returned draws.
    df : float
        Degrees of freedom of the t proposal (default 5).
    inflate : float
        Scale factor of the proposal over the Laplace (or moment-matched)
        covariance (default 1.3).  On the 21-parameter spline posteriors of
        3000 injections, (df, inflate) = (5, 1.3) with moment matching kept
        k-hat below 0.5 in 7 of 8 seeds where (10, 1) exceeded 0.7 in 3.
    min_ess : float
        Effective sample size below which the result counts as not converged.
    adapt : bool, default True
        Allow moment-matching rounds.
    max_draws : int, optional
        Most draws pooled from the final proposal (default
        :data:`IS_MAX_DRAWS`, at least ``ndraws``).
    stream : str
        The random stream of the draws under ``seed`` (``fit``'s second
        try uses :attr:`~comest_bayes.seeding.Stream.IMPORTANCE_TAILS`).

    Returns
    -------
    PosteriorSamples
        ``samples`` (nout, D) equal-weight draws; ``chain`` holds the pooled
        proposal draws ``(N, 1, D)`` and ``log_prob`` their log posterior;
        ``diagnostics`` an :class:`ImportanceDiagnostics` (``ndraws`` counts
        every log-posterior evaluation, ``nout`` the returned draws).
    """
    t0 = time.perf_counter()
    rng = rng_for(seed, stream)
    max_draws = max(int(ndraws), IS_MAX_DRAWS if max_draws is None else int(max_draws))
    mean, chol = lap.mean, np.linalg.cholesky(lap.cov * inflate ** 2)
    # every round's draws are kept and weighted against the mixture of the proposals they came from
    # (the balance heuristic of multiple importance sampling): a moment-matched round adds to the draws
    # before it instead of replacing them, so no evaluation is thrown away
    components, draw_sets, logp_sets = [], [], []

    def weigh():
        x, lp = np.concatenate(draw_sets), np.concatenate(logp_sets)
        return x, lp, lp - _mixture_log_q(x, components, df)

    for round_ in range(1 + ADAPT_ROUNDS * int(adapt)):
        x, lp = _t_draws(model, mean, chol, df, ndraws, rng)
        components.append([mean, chol, ndraws])
        draw_sets.append(x)
        logp_sets.append(lp)
        draws, log_p, lw_raw = weigh()
        w, ess, khat = _psis(lw_raw)
        # the shape of this round's proposal is judged on its own draws (the mixture keeps the tails of
        # earlier, worse proposals in its k-hat)
        own_khat = khat if round_ == 0 else _psis(lp - _mixture_log_q(x, components[-1:], df))[2]
        if round_ < ADAPT_ROUNDS and adapt and own_khat > 0.5 and ess > 2 * lap.mean.size:
            # moment matching: the weighted mean and covariance of the draws so far are a better proposal
            # than the Laplace Gaussian when the posterior is skewed
            new_mean = w @ draws
            dev = draws - new_mean
            if ess < FULL_MATCH_ESS * lap.mean.size:
                # too few effective draws for a full covariance (in tens of dimensions it is mostly noise: on
                # the demo's 49-parameter spline, ESS 239 of 2000, it made proposals of own ESS 61 and 52): move
                # the mean and rescale each parameter's spread, keeping the Laplace correlations (ESS 286)
                scale = np.sqrt((w @ (dev * dev)) / np.diag(lap.cov))
                new_cov = lap.cov * np.outer(scale, scale) * inflate ** 2
            else:
                new_cov = (dev * w[:, None]).T @ dev * inflate ** 2  # as the t scale, inflated: wider than the target
            new_cov = 0.5 * (new_cov + new_cov.T)
            try:
                new_chol = np.linalg.cholesky(new_cov)
            except np.linalg.LinAlgError:
                break
            mean, chol = new_mean, new_chol
        else:
            break
    # more draws from the last proposal, in two cases:
    # - pooling: the weights are trustworthy but too few are effective; at least a quarter of a batch at a time
    #   and otherwise as many as the current efficiency says are missing (+10%); none when even max_draws would
    #   fall short at that efficiency;
    # - dilution: the pooled k-hat fails while the last proposal's own draws say it fits (k-hat <= 0.5), i.e. an
    #   earlier, worse round's tail dominates the mixture; a batch at a time, at most doubling the draws of the
    #   rounds (a real tail the last proposal misses keeps the pooled k-hat high: then emcee is the answer, and a
    #   bounded number of draws is all this costs; emcee costs some 40x a batch)
    rounds_draws = draws.shape[0]
    while ess < min_ess or khat > IS_KHAT_MAX:
        have = draws.shape[0]
        if khat > IS_KHAT_MAX:
            if not (own_khat <= 0.5 and len(components) > 1 and have + ndraws <= 2 * rounds_draws):
                break
            step = ndraws
        else:
            need = int(math.ceil(1.1 * have * min_ess / max(ess, 1e-12)))
            step = max(ndraws // 4, 1, need - have)
            if need > max_draws:
                break
        if have + step > max_draws:
            break
        x, lp = _t_draws(model, mean, chol, df, step, rng)  # the last round's proposal
        components[-1][2] += step
        draw_sets.append(x)
        logp_sets.append(lp)
        draws, log_p, lw_raw = weigh()
        w, ess, khat = _psis(lw_raw)
    evaluations = draws.shape[0]
    issued = []
    # systematic resampling: nout equally spaced points through the cumulative weights
    u = (rng.random() + np.arange(nout)) / nout
    idx = np.minimum(np.searchsorted(np.cumsum(w), u), draws.shape[0] - 1)
    converged = khat <= IS_KHAT_MAX and ess >= min_ess
    if not converged:
        issued.append(f"importance sampling from the Laplace approximation: Pareto k-hat = {khat:.2f} "
                      f"(trusted <= {IS_KHAT_MAX}), ESS = {ess:.0f} of {draws.shape[0]} (wanted >= {min_ess:.0f})")
    diag = ImportanceDiagnostics(khat=khat, ess=ess, ndraws=evaluations, nout=nout, df=float(df),
                                 min_ess=float(min_ess), converged=bool(converged), warnings=issued,
                                 seconds=time.perf_counter() - t0)
    return PosteriorSamples(samples=draws[idx].copy(), chain=draws[:, None, :], log_prob=log_p[:, None],
                            diagnostics=diag)


# --------------------------------------------------------------------------- all stages


def _nuts(model, lap, seed: int, min_ess: float, note: str | None = None, stacklevel: int = 3) -> PosteriorSamples:
    """:func:`~comest_bayes.bayes.nuts.nuts_posterior`, with ``note`` first in its warnings and a warning (at
    ``stacklevel``: the caller of :func:`fit`) if it did not converge."""
    post = nuts_posterior(model, lap, seed=seed, min_ess=min_ess)
    if note:
        post.diagnostics.warnings.insert(0, note)
    if not post.diagnostics.converged:
        warnings.warn(post.diagnostics.warnings[-1], ConvergenceWarning, stacklevel=stacklevel)
    return post


def _after_importance_failed(model, lap, failed: str, *, seed: int, min_ess: float, **emcee_kw) -> PosteriorSamples:
    """``fit(sampler="auto")``'s samplers after importance sampling failed (``failed``: its warning).

    Importance sampling once more, from its own stream with a t of :data:`IS_RETRY_DF` degrees of freedom:
    heavier tails pass on most of the posteriors whose one-sided tails the first proposal missed.  Where
    that fails too, NUTS, which follows a curved ridge or a skewed tail with the gradient; a model without
    a traceable density gets emcee instead, bounded by ``emcee_kw["max_steps"]`` (a chain shorter than
    emcee's 50-tau rule asks for warns with its numbers).  All to ESS ``min_ess``; the first warning of
    the result's diagnostics says what failed before it.
    """
    retry = importance_posterior(model, lap, seed=seed, min_ess=min_ess, df=IS_RETRY_DF,
                                 stream=Stream.IMPORTANCE_TAILS)
    rd = retry.diagnostics
    if rd.converged:
        rd.warnings.insert(0, failed + f"; sampled again from a t with {IS_RETRY_DF:g} degrees of freedom")
        return retry
    failed += f"; again from a t with {IS_RETRY_DF:g} degrees of freedom: k-hat = {rd.khat:.2f}, ESS = {rd.ess:.0f}"
    if supports_nuts(model):
        return _nuts(model, lap, seed, min_ess, note=failed + "; sampled with NUTS instead", stacklevel=4)
    post = sample_posterior(model, lap, seed=seed, min_ess=min_ess, **emcee_kw)
    post.diagnostics.warnings.insert(0, failed + "; sampled with emcee instead")
    return post


def fit(model, *, seed: int, sample: bool = True, nstarts: int = 6, min_ess: float = 1000,
        max_steps: int = 20000, chunk: int = 500, nwalkers: int | None = None, progress: bool = False,
        method: str = "L-BFGS-B", moves="de", sampler: str = "emcee", start=None,
        mp: MapResult | None = None) -> FitResult:
    """MAP, Laplace approximation and (``sample=True``) emcee posterior of ``model``.

    Parameters
    ----------
    model : CompletenessModel-like
    seed : int
        Root seed, shared by :func:`fit_map` and :func:`sample_posterior`
        (which draw from distinct named streams).
    sample : bool, default True
        Run the sampler; otherwise ``posterior`` is None.
    nstarts, method
        See :func:`fit_map`.
    min_ess, max_steps, chunk, nwalkers, progress, moves
        See :func:`sample_posterior`.
    sampler : {"emcee", "importance", "nuts", "auto"}
        ``emcee`` (the reference), ``importance``
        (:func:`importance_posterior` from the Laplace approximation, asking
        for an effective sample size of ``min(min_ess, IS_MIN_ESS)``, pooling
        up to :data:`IS_MAX_DRAWS` proposal draws if that falls short),
        ``nuts`` (:func:`comest_bayes.bayes.nuts.nuts_posterior`, to ESS
        ``min_ess``), or ``auto``: importance sampling; where its Pareto k-hat
        or effective sample size still fails (:data:`IS_KHAT_MAX`), importance
        sampling again from a t with :data:`IS_RETRY_DF` degrees of freedom,
        and where that fails too, NUTS to ESS ``min(min_ess, IS_MIN_ESS)``; a
        model without a traceable
        density (:func:`~comest_bayes.bayes.nuts.supports_nuts`) falls back to
        emcee instead, in at most :data:`FALLBACK_MAX_STEPS` steps.
    start : array, optional
        An extra first MAP start (a warm start, e.g. a simpler rung's MAP).
    mp : MapResult, optional
        A MAP found already (skips the optimisation).

    Returns
    -------
    FitResult
    """
    if sampler not in SAMPLERS:
        raise InputError(f"fit: sampler must be one of {', '.join(map(repr, SAMPLERS))}, got {sampler!r}")
    t0 = time.perf_counter()
    if mp is None:
        mp = fit_map(model, nstarts=nstarts, seed=seed, method=method, start=start)
    lap = laplace(model, mp.theta)
    post = None
    if sample and sampler in ("importance", "auto"):
        is_ess = min(min_ess, IS_MIN_ESS)
        post = importance_posterior(model, lap, seed=seed, min_ess=is_ess)
        if sampler == "auto" and not post.diagnostics.converged:
            post = _after_importance_failed(model, lap, post.diagnostics.warnings[-1], seed=seed, min_ess=is_ess,
                                            nwalkers=nwalkers, max_steps=min(max_steps, FALLBACK_MAX_STEPS),
                                            chunk=chunk, progress=progress, moves=moves)
        elif not post.diagnostics.converged:
            warnings.warn(post.diagnostics.warnings[-1], ConvergenceWarning, stacklevel=2)
    elif sample and sampler == "nuts":
        post = _nuts(model, lap, seed, min_ess)
    elif sample:
        post = sample_posterior(model, lap, seed=seed, nwalkers=nwalkers, min_ess=min_ess, max_steps=max_steps,
                                chunk=chunk, progress=progress, moves=moves)
    return FitResult(map=mp, laplace=lap, posterior=post, seconds=time.perf_counter() - t0)
