"""Does the fitted model's shape describe the outcomes?  A posterior predictive check by magnitude.

The completeness model's intervals carry the statistical uncertainty of its
parameters, not the error of its *form*.  With enough injections the form
dominates: on the demo tile ``logistic_depth`` stops improving at about
0.01 mag in m50 beyond ~3x10^4 injections while the binned ratio keeps
improving, and the model's intervals then miss the truth
(``benchmarks/bench_speed_accuracy.py``).  This check makes that visible in
every fit.

For magnitude bins ``b`` (the run's ratio bins), with the injections' own
covariates (so no assumption about the footprint enters), over posterior
draws ``s``:

* observed detections ``O_b = sum_c k_c`` over the binomial cells ``c`` in ``b``;
* expected ``E_bs = sum_c n_c f(theta_s; cov_c)``;
* predictive variance ``V_b = mean_s sum_c n_c f (1 - f) + var_s E_bs``
  (binomial noise plus the posterior's own uncertainty);
* ``z_b = (O_b - mean_s E_bs) / sqrt(V_b)`` and ``chi2 = sum_b z_b^2`` over
  the bins with ``V_b >= 0.25`` (a bin whose prediction is certain to well
  below one detection carries no information at this level).

Because the parameters were fitted to the same outcomes, ``chi2`` is slightly
smaller than a chi-square with ``dof`` = number of bins would give: the
p-value is conservative (a small p is a real misfit).  Below
:data:`P_WARN` the fit warns, and the binned ratios are the curve to trust
at that number of injections.
"""

from __future__ import annotations

import numpy as np
from scipy import stats

__all__ = ["shape_check", "P_WARN", "shape_warning"]

#: A p-value below this makes the fit warn that the model's form, not its statistics, limits it.
P_WARN = 1e-3
#: Bins whose predictive variance is below this (in detections^2) are left out of chi2.
MIN_VARIANCE = 0.25
#: Posterior draws used (spread evenly over the chain).
MAX_DRAWS = 200


def shape_check(model, draws, mag_edges) -> dict:
    """Posterior predictive check of the detections per magnitude bin.

    Parameters
    ----------
    model : CompletenessModel
        The fitted model; its compressed data (``model.data``) are the outcomes.
    draws : array, shape (S, ndim) or (ndim,)
        Posterior draws of the unconstrained parameters (a single MAP vector
        is accepted; the predictive variance then has no posterior term).
    mag_edges : array, shape (B + 1,)
        Increasing magnitude bin edges.

    Returns
    -------
    dict
        ``chi2``, ``dof``, ``p_value`` (None when no bin qualifies),
        ``max_abs_z`` and ``mag_at_max`` (the worst bin's centre), and
        ``bins``: per bin ``mag``, ``n``, ``observed``, ``expected``, ``z``
        (None where left out).
    """
    edges = np.asarray(mag_edges, float)
    if edges.ndim != 1 or edges.size < 2 or not np.all(np.diff(edges) > 0):
        raise ValueError("mag_edges must be a 1-D increasing array of at least two edges")
    theta = np.atleast_2d(np.asarray(draws, float))
    if theta.shape[0] > MAX_DRAWS:
        theta = theta[np.linspace(0, theta.shape[0] - 1, MAX_DRAWS).astype(int)]
    data = model.data
    m = np.asarray(data.cov.m, float)
    n = np.asarray(data.n, float)
    k = np.asarray(data.k, float)
    nb = edges.size - 1
    b = np.searchsorted(edges, m, side="right") - 1
    inside = (b >= 0) & (b < nb)
    b, n, k = b[inside], n[inside], k[inside]
    cov, g = data.cov, len(m)
    if hasattr(cov, "take"):
        from .likelihood import padded_size

        # cells padded (repeating the last) to the likelihood's padded count: the kinds of a run, whose cell
        # counts differ a little, share one compiled prediction instead of tracing one each
        cov = cov.take(np.minimum(np.arange(padded_size(g)), g - 1))
    p = np.atleast_2d(model.prob(theta, cov))[:, :g][:, inside]          # (S, G)
    e_bs = np.stack([np.bincount(b, weights=n * ps, minlength=nb) for ps in p])          # (S, B)
    v_bin = np.stack([np.bincount(b, weights=n * ps * (1.0 - ps), minlength=nb) for ps in p]).mean(axis=0)
    expected = e_bs.mean(axis=0)
    var = v_bin + (e_bs.var(axis=0) if len(theta) > 1 else 0.0)
    observed = np.bincount(b, weights=k, minlength=nb)
    count = np.bincount(b, weights=n, minlength=nb)
    used = var >= MIN_VARIANCE
    z = np.full(nb, np.nan)
    z[used] = (observed[used] - expected[used]) / np.sqrt(var[used])
    centres = 0.5 * (edges[:-1] + edges[1:])
    dof = int(used.sum())
    chi2 = float(np.sum(z[used] ** 2)) if dof else None
    worst = int(np.nanargmax(np.abs(z))) if dof else None
    return {
        "chi2": chi2,
        "dof": dof,
        "p_value": float(stats.chi2.sf(chi2, dof)) if dof else None,
        "max_abs_z": float(abs(z[worst])) if dof else None,
        "mag_at_max": float(centres[worst]) if dof else None,
        "bins": [{"mag": float(c), "n": int(round(nn)), "observed": int(round(o)), "expected": float(e),
                  "z": None if not u else float(zz)}
                 for c, nn, o, e, u, zz in zip(centres, count, observed, expected, used, z)],
    }


def shape_warning(check: dict, *, name: str, kind: str, quantity: str) -> str | None:
    """The warning text for a failed check, or None when the model describes the outcomes."""
    p = check.get("p_value")
    if p is None or p >= P_WARN:
        return None
    return (f"the {name} {quantity} curve of {kind} does not describe the binned outcomes (chi2 = {check['chi2']:.1f} "
            f"for {check['dof']} magnitude bins, p = {p:.1e}; worst bin at {check['mag_at_max']:.2f} mag, "
            f"{check['max_abs_z']:.1f} sigma): with this many injections the model's form, not its statistics, "
            f"limits it and its intervals are too narrow; trust the binned ratios, or fit a more flexible model "
            f"(--model)")
