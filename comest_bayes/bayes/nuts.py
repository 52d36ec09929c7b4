"""Posterior draws with the No-U-Turn sampler (BlackJAX), for posteriors the Laplace approximation misses.

:func:`comest_bayes.bayes.inference.fit` samples a model first by importance sampling from its Laplace
approximation.  When that fails (Pareto k-hat above 0.7), the posterior is far from Gaussian: on the
spline rung of a few thousand injections the typical case is a curved ridge along which the width
and the knot log-rates grow together (``benchmarks/README.md``, "The spline's scale identified by the
mean of its rates").  emcee's ensemble moves cross such a ridge slowly (5000 steps, 30-50 CPU-s, and
still short of its 50-tau rule); Hamiltonian Monte Carlo follows it with the gradient.

The sampler works in the Laplace approximation's whitened coordinates ``z`` (``theta = mean + L z``
with ``L L^T`` the Laplace covariance), so every chain starts from a well-scaled problem.  Each chain
adapts its step size and a dense mass matrix with Stan's windowed adaptation
(:func:`blackjax.window_adaptation`), then draws.  The log posterior comes from the model's
:meth:`~comest_bayes.bayes.model.CompletenessModel.log_density` (a JAX function with the data as
arguments), so one compiled program serves every data set of a structure and padded size.

Diagnostics follow Vehtari, Gelman, Simpson, Carpenter & Bürkner (2021, Bayesian Analysis 16, 667):
rank-normalised split R-hat at most 1.01 and bulk and tail effective sample sizes of at least
``min_ess`` for every parameter, computed by :mod:`arviz`; and no divergent transition (a divergence
means the integrator met curvature it cannot follow, and the draws near it may be biased).  Details:
``docs/bayesian.md`` ("Inference").
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass

import numpy as np

from comest_bayes.bayes.samples import PosteriorSamples
from comest_bayes.errors import InputError
from comest_bayes.io.jsonio import json_float
from comest_bayes.seeding import Stream, rng_for

__all__ = ["NutsDiagnostics", "nuts_posterior", "supports_nuts", "RHAT_MAX", "NUTS_CHAINS", "NUTS_WARMUP",
           "NUTS_DRAWS", "MAX_DOUBLINGS", "MAX_GRADIENTS"]

#: Largest rank-normalised split R-hat of a converged run (Vehtari et al. 2021).
RHAT_MAX = 1.01

#: Chains per run (R-hat compares them; they run side by side in one compiled program).
NUTS_CHAINS = 4

#: Warm-up iterations per chain (step size and dense mass matrix adaptation).  Fewer than Stan's 1000: the
#: chains start in the Laplace approximation's whitened coordinates, already well scaled.  On three honesty
#: tables whose importance sampling failed, runs with 200, 300 and 500 gave posterior means within about
#: 0.1 sd of each other.
NUTS_WARMUP = 300

#: Draws per chain and round; rounds continue every chain until the effective sample size is reached
#: or ``max_draws`` per chain are drawn.
NUTS_DRAWS = 250

#: Step-size adaptation's target acceptance; a run with divergences is repeated once at
#: :data:`TARGET_ACCEPT_RETRY` (a smaller step follows sharper curvature).  0.9 rather than Stan's 0.8: the
#: spline posteriors that reach NUTS have a curved ridge; on those three tables 4 of 10 runs at 0.8 diverged
#: and ran again, 1 of 12 at 0.9.
TARGET_ACCEPT = 0.9
TARGET_ACCEPT_RETRY = 0.97

#: Most trajectory doublings per iteration (at most 2^8 - 1 = 255 leapfrog steps; BlackJAX's default is 10).
MAX_DOUBLINGS = 8

#: Gradient evaluations (leapfrog steps over all chains, warm-up included) after which no further round of
#: draws starts.  The curved ridges NUTS is for took 100,000-300,000 in the honesty benchmark (the most, a
#: 30,000-injection long tail: 250,000 left it at ESS 183).  A posterior that needs far more (a fixed rough
#: spline's, whose knot rates beyond the data are held only by the prior: 40-200 leapfrog steps per draw)
#: stops here unconverged, with a warning, instead of running for ten minutes.
MAX_GRADIENTS = 400_000


@dataclass
class NutsDiagnostics:
    """Diagnostics of :func:`nuts_posterior`.

    Attributes
    ----------
    names : list of str
    ess_bulk, ess_tail : ndarray, shape (D,)
        Bulk and tail effective sample sizes of every parameter over all chains.
    rhat : ndarray, shape (D,)
        Rank-normalised split R-hat of every parameter.
    divergences : int
        Divergent transitions among the kept draws.
    step_size : list of float
        Adapted step size of every chain (in the whitened coordinates).
    mean_leapfrog : float
        Mean number of leapfrog steps per draw (the cost of a draw in gradient evaluations).
    gradients : int
        Gradient evaluations of the whole run, warm-up (and a repeated run) included.
    nchains, nwarmup, ndraws : int
        Chains, warm-up iterations and kept draws per chain.
    target_accept : float
        The step-size adaptation's target (raised after divergences).
    min_ess : float
    converged : bool
        ``min(ess_bulk, ess_tail) >= min_ess``, ``max(rhat) <= RHAT_MAX`` and no divergence.
    warnings : list of str
    seconds : float
    """

    names: list
    ess_bulk: np.ndarray
    ess_tail: np.ndarray
    rhat: np.ndarray
    divergences: int
    step_size: list
    mean_leapfrog: float
    gradients: int
    nchains: int
    nwarmup: int
    ndraws: int
    target_accept: float
    min_ess: float
    converged: bool
    warnings: list
    seconds: float
    method: str = "nuts"

    def __getitem__(self, key):
        return getattr(self, key)

    @property
    def ess(self) -> np.ndarray:
        """The smaller of the bulk and tail effective sample size of every parameter."""
        return np.minimum(self.ess_bulk, self.ess_tail)

    def to_dict(self) -> dict:
        """JSON-ready dict (non-finite numbers become ``None``)."""
        return {"method": self.method, "names": list(self.names),
                "ess_bulk": [json_float(e) for e in self.ess_bulk], "ess_tail": [json_float(e) for e in self.ess_tail],
                "rhat": [json_float(r) for r in self.rhat], "divergences": int(self.divergences),
                "step_size": [json_float(s) for s in self.step_size], "mean_leapfrog": json_float(self.mean_leapfrog),
                "gradients": int(self.gradients),
                "nchains": int(self.nchains), "nwarmup": int(self.nwarmup), "ndraws": int(self.ndraws),
                "target_accept": float(self.target_accept), "min_ess": json_float(self.min_ess),
                "converged": bool(self.converged), "warnings": list(self.warnings),
                "seconds": json_float(self.seconds)}


def supports_nuts(model) -> bool:
    """Whether ``model`` gives a traceable log posterior (:meth:`log_density`) for NUTS."""
    return callable(getattr(model, "log_density", None))


_PROGRAMS: dict = {}


def _programs():
    """The two jitted programs (warm-up, draws), built once per process (BlackJAX imported on first use)."""
    if not _PROGRAMS:
        import blackjax
        from blackjax.adaptation.base import get_filter_adapt_info_fn

        from comest_bayes.jaxnum import jax

        def density(fn, static, mean, chol, args):
            return lambda z: fn(static, mean + chol @ z, *args)

        def warmup(fn, static, nwarm, target, key, z0, mean, chol, args):
            adapt = blackjax.window_adaptation(blackjax.nuts, density(fn, static, mean, chol, args),
                                               is_mass_matrix_diagonal=False, initial_step_size=0.5,
                                               target_acceptance_rate=target,
                                               adaptation_info_fn=get_filter_adapt_info_fn(
                                                   info_keys={"num_integration_steps"}),
                                               max_num_doublings=MAX_DOUBLINGS)
            (state, params), info = adapt.run(key, z0, num_steps=nwarm)
            return (state.position, params["step_size"], params["inverse_mass_matrix"],
                    jax.numpy.sum(info.info.num_integration_steps))

        def draws(fn, static, ndraws, key, z0, step_size, inv_mass, mean, chol, args):
            kernel = blackjax.nuts(density(fn, static, mean, chol, args), step_size=step_size,
                                   inverse_mass_matrix=inv_mass, max_num_doublings=MAX_DOUBLINGS)

            def one(state, k):
                state, info = kernel.step(k, state)
                return state, (state.position, state.logdensity, info.num_integration_steps, info.is_divergent)

            _, out = jax.lax.scan(one, kernel.init(z0), jax.random.split(key, ndraws))
            return out

        # the chains run side by side (vmap): one compiled program and one call for all of them (measured on a
        # 21-parameter spline fit of 929 cells, as fast as running them one after another, not faster)
        def warmup_chains(fn, static, nwarm, target, keys, z0, mean, chol, args):
            return jax.vmap(lambda k, z: warmup(fn, static, nwarm, target, k, z, mean, chol, args))(keys, z0)

        def draws_chains(fn, static, ndraws, keys, z0, step_size, inv_mass, mean, chol, args):
            return jax.vmap(lambda k, z, e, m: draws(fn, static, ndraws, k, z, e, m, mean, chol, args))(
                keys, z0, step_size, inv_mass)

        _PROGRAMS["warmup"] = jax.jit(warmup_chains, static_argnums=(0, 1, 2))
        _PROGRAMS["draws"] = jax.jit(draws_chains, static_argnums=(0, 1, 2))
        _PROGRAMS["key"] = jax.random.key
        _PROGRAMS["split"] = jax.random.split
    return _PROGRAMS


def _diagnose(draws: np.ndarray):
    """Bulk and tail ESS and R-hat of every coordinate of draws (chain, draw, D), with arviz."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        import arviz as az

        ds = az.convert_to_dataset({"x": draws})
        bulk = np.asarray(az.ess(ds, method="bulk")["x"].values, float)
        tail = np.asarray(az.ess(ds, method="tail")["x"].values, float)
        rhat = np.asarray(az.rhat(ds)["x"].values, float)
    return bulk, tail, rhat


def nuts_posterior(model, lap, *, seed: int, min_ess: float = 400.0, nchains: int = NUTS_CHAINS,
                   nwarmup: int = NUTS_WARMUP, ndraws: int = NUTS_DRAWS, max_draws: int = 8 * NUTS_DRAWS):
    """Posterior draws of ``model`` with NUTS, started and preconditioned by its Laplace approximation.

    Parameters
    ----------
    model : CompletenessModel-like
        Needs :meth:`log_density` (see :func:`supports_nuts`) and ``names``.
    lap : LaplaceResult
        Mean and covariance that define the whitened coordinates; the chains start at
        ``mean + L z0`` with ``z0`` standard normal (dispersed as R-hat needs).
    seed : int
        Root seed (stream ``"nuts"``): starting points and the chains' keys.
    min_ess : float
        Bulk and tail effective sample size every parameter must reach.
    nchains, nwarmup, ndraws : int
        Chains, warm-up iterations per chain, draws per chain and round.
    max_draws : int
        Most draws per chain (rounds of ``ndraws`` continue while the ESS falls short).

    Returns
    -------
    PosteriorSamples
        ``samples`` (nchains * kept draws, D), step-major like emcee's (row ``s * nchains + c``);
        ``chain`` (draws, nchains, D) and ``log_prob`` (draws, nchains) hold the kept draws;
        ``diagnostics`` a :class:`NutsDiagnostics`.  A run with divergences is repeated once with a
        higher target acceptance (smaller steps) before it is reported, if the first used less than
        half of :data:`MAX_GRADIENTS`; no round of draws starts after that budget is spent (the first
        always runs), and a run stopped there warns.
    """
    if not supports_nuts(model):
        raise InputError(f"nuts_posterior: {type(model).__name__} has no log_density(); use emcee or importance "
                         "sampling for it")
    if nchains < 2 or nwarmup < 50 or ndraws < 50 or max_draws < ndraws:
        raise InputError(f"nuts_posterior: need nchains >= 2, nwarmup >= 50, ndraws >= 50 and max_draws >= ndraws; "
                         f"got {nchains}, {nwarmup}, {ndraws}, {max_draws}")
    t0 = time.perf_counter()
    prog = _programs()
    fn, static, args = model.log_density()
    mean = np.asarray(lap.mean, np.float64)
    chol = np.linalg.cholesky(np.asarray(lap.cov, np.float64))
    d = mean.size
    rng = rng_for(seed, Stream.NUTS)
    z_start = rng.standard_normal((nchains, d))
    keys = rng.integers(0, 2**31 - 1, size=2)
    result = None
    gradients = 0  # leapfrog steps of every chain so far, warm-up included
    for target in (TARGET_ACCEPT, TARGET_ACCEPT_RETRY):
        if result is not None and gradients > MAX_GRADIENTS // 2:
            break  # no budget left for a second run: report the first
        pos, step, inv_mass, nwarm_leap = prog["warmup"](fn, static, int(nwarmup), np.float64(target),
                                                         prog["split"](prog["key"](int(keys[0])), nchains), z_start,
                                                         mean, chol, args)
        gradients += int(np.sum(np.asarray(nwarm_leap)))
        key = prog["key"](int(keys[1]))
        parts = []  # (z, logdensity, leapfrog, divergent) per round, each (nchains, ndraws, ...)
        while True:
            key, sub = prog["split"](key)
            z, lp, nleap, div = (np.asarray(x) for x in prog["draws"](fn, static, int(ndraws), prog["split"](sub, nchains),
                                                                      pos, step, inv_mass, mean, chol, args))
            pos = z[:, -1]
            gradients += int(np.sum(nleap))
            parts.append((z, lp, nleap, div))
            # judged in theta, the parameters a user reads (ESS is not invariant under the whitening's rotation)
            theta = mean + np.einsum("ij,csj->csi", chol, np.concatenate([p[0] for p in parts], axis=1))
            bulk, tail, rhat = _diagnose(theta)
            kept = theta.shape[1]
            # the next round would cost about as much as this one
            over_budget = gradients + int(np.sum(nleap)) > MAX_GRADIENTS
            if (min(bulk.min(), tail.min()) >= min_ess and rhat.max() <= RHAT_MAX) or kept + ndraws > max_draws \
                    or over_budget:
                break
        lp_all = np.concatenate([p[1] for p in parts], axis=1)
        nleap = np.concatenate([p[2] for p in parts], axis=1)
        ndiv = int(np.sum(np.concatenate([p[3] for p in parts], axis=1)))
        result = (theta, lp_all, nleap, ndiv, [float(e) for e in np.asarray(step)], bulk, tail, rhat, target,
                  over_budget)
        if ndiv == 0:
            break
    theta, lp_all, nleap, ndiv, steps, bulk, tail, rhat, target, over_budget = result
    issued = []
    converged = bool(min(bulk.min(), tail.min()) >= min_ess and rhat.max() <= RHAT_MAX and ndiv == 0)
    if not converged:
        worst = int(np.argmin(np.minimum(bulk, tail)))
        failed = []  # only the criteria that failed
        if min(bulk.min(), tail.min()) < min_ess:
            failed.append(f"smallest ESS {min(bulk.min(), tail.min()):.0f} ({model.names[worst]}; wanted >= "
                          f"{min_ess:.0f})")
        if rhat.max() > RHAT_MAX:
            failed.append(f"largest R-hat {rhat.max():.3f} (wanted <= {RHAT_MAX})")
        if ndiv:
            failed.append(f"{ndiv} divergent transition(s) in {theta.shape[0] * theta.shape[1]} draws (wanted none)")
        issued.append("NUTS did not converge: " + ", ".join(failed)
                      + (f"; stopped at its budget of {MAX_GRADIENTS} gradient evaluations ({gradients} used: "
                         f"{np.mean(nleap):.0f} leapfrog steps per draw, a posterior far from any Gaussian)"
                         if over_budget else ""))
    diag = NutsDiagnostics(names=list(model.names), ess_bulk=bulk, ess_tail=tail, rhat=rhat, divergences=ndiv,
                           step_size=steps, mean_leapfrog=float(np.mean(nleap)), gradients=int(gradients),
                           nchains=int(nchains), nwarmup=int(nwarmup), ndraws=int(theta.shape[1]),
                           target_accept=float(target),
                           min_ess=float(min_ess), converged=converged, warnings=issued,
                           seconds=time.perf_counter() - t0)
    chain = np.transpose(theta, (1, 0, 2))  # (draws, chains, D), step-major as emcee's
    return PosteriorSamples(samples=chain.reshape(-1, d).copy(), chain=chain, log_prob=lp_all.T.copy(),
                            diagnostics=diag)
