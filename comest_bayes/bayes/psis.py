"""Pareto-smoothed importance sampling (PSIS) of one set of log importance ratios.

The method of Vehtari, Simpson, Gelman, Yao & Gabry (2024, JMLR 25(72)):
the ``M`` largest ratios are replaced by the expected order statistics of a
generalized Pareto distribution fitted to them, which stabilises the
weights, and the fitted shape ``k-hat`` says how far the estimate can be
trusted (at most 0.7: the error falls at the usual rate).  The shape and
scale are estimated as Zhang & Stephens (2009, Technometrics 51, 316)
propose, with the weakly informative pull of ``k`` towards 0.5 of Vehtari
et al. (weight of 10 observations).

It does what :func:`arviz.psislw` does for one row (the tests compare the
two); written here because importing arviz costs about a second per
process, more than the importance sampling it would smooth.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["psis_log_weights", "gpd_fit"]

#: Weight (in observations) of the prior that pulls the fitted shape towards 0.5.
SHAPE_PRIOR_WEIGHT = 10.0


def gpd_fit(excess: np.ndarray) -> tuple[float, float]:
    """Shape ``k`` and scale ``sigma`` of a generalized Pareto fitted to sorted positive excesses.

    Zhang & Stephens (2009): the profile likelihood of ``theta = -k / sigma``
    is averaged over a grid of ``30 + sqrt(n)`` values with weights
    proportional to it; ``k`` follows from the averaged ``theta``; then
    ``k`` is pulled towards 0.5 with weight :data:`SHAPE_PRIOR_WEIGHT`.
    """
    x = np.asarray(excess, dtype=np.float64)
    n = x.size
    m = 30 + int(math.sqrt(n))
    j = np.arange(1, m + 1, dtype=np.float64)
    quartile = x[max(int(n / 4.0 + 0.5) - 1, 0)]
    theta = 1.0 / x[-1] + (1.0 - np.sqrt(m / (j - 0.5))) / (3.0 * quartile)
    # shape as a function of theta (positive for heavy tails); theta = -shape / sigma
    k = np.mean(np.log1p(-theta[:, None] * x[None, :]), axis=1)
    profile = n * (np.log(-theta / k) - k - 1.0)  # profile log-likelihood of theta
    weights = 1.0 / np.sum(np.exp(profile[None, :] - profile[:, None]), axis=1)
    keep = weights >= 10.0 * np.finfo(float).eps
    weights, theta = weights[keep], theta[keep]
    theta_hat = float(np.sum(weights * theta) / np.sum(weights))
    shape = float(np.mean(np.log1p(-theta_hat * x)))
    sigma = -shape / theta_hat
    shape = (n * shape + SHAPE_PRIOR_WEIGHT * 0.5) / (n + SHAPE_PRIOR_WEIGHT)
    return shape, sigma


def _gpd_quantile(p: np.ndarray, shape: float, sigma: float) -> np.ndarray:
    if abs(shape) < 1e-12:
        return -sigma * np.log1p(-p)
    return sigma * np.expm1(-shape * np.log1p(-p)) / shape


def psis_log_weights(log_ratios: np.ndarray, reff: float = 1.0) -> tuple[np.ndarray, float]:
    """Smoothed, normalised log weights and the Pareto k-hat of one vector of log ratios.

    Parameters
    ----------
    log_ratios : array (S,)
        Log importance ratios (target over proposal, any constant); ``-inf``
        marks draws of zero weight.
    reff : float
        Relative efficiency of the draws (1 for independent draws).

    Returns
    -------
    (log_weights, khat)
        ``log_weights`` sum to one in the linear scale; ``khat`` is ``inf``
        when the tail is too short or degenerate to fit.
    """
    lw = np.array(log_ratios, dtype=np.float64)
    finite = np.isfinite(lw)
    s = int(finite.sum())
    lw = lw - np.max(lw[finite])
    tail_len = int(math.ceil(min(0.2 * lw.size, 3.0 * math.sqrt(lw.size / reff))))
    khat = math.inf
    if tail_len >= 5 and s > tail_len + 1:
        order = np.argsort(np.where(finite, lw, -np.inf))
        tail_idx = order[-tail_len:]
        cutoff = lw[order[-tail_len - 1]]
        excess = np.exp(lw[tail_idx]) - math.exp(cutoff)
        if np.all(np.isfinite(excess)) and excess[-1] > excess[0]:
            shape, sigma = gpd_fit(excess)
            if np.isfinite(shape):
                p = (np.arange(1, tail_len + 1) - 0.5) / tail_len
                smoothed = np.log(_gpd_quantile(p, shape, sigma) + math.exp(cutoff))
                lw[tail_idx] = np.minimum(smoothed, 0.0)  # never above the largest raw ratio
                khat = float(shape)
    lw[~finite] = -np.inf
    lw -= np.logaddexp.reduce(lw[finite])
    return lw, khat
