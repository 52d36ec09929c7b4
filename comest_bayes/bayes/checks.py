"""Does the fitted model's shape describe the outcomes?  A posterior predictive check by magnitude.

:func:`shape_check` compares, per magnitude bin, the observed detections with those the
posterior predicts for the same injections and sums the differences into a chi-square; below
:data:`P_WARN` the fit warns.  Formulas and measurements: ``docs/bayesian.md`` ("Shape check").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import special
from comest_bayes.bayes.model import padded_size

__all__ = ["shape_check", "ShapeCheck", "ShapeBin", "P_WARN", "shape_warning"]

#: A p-value below this makes the fit warn that the model's form, not its statistics, limits it.
P_WARN = 1e-3
#: Bins whose predictive variance is below this (in detections^2) are left out of chi2.
MIN_VARIANCE = 0.25
#: Posterior draws used (spread evenly over the chain).
MAX_DRAWS = 200


@dataclass(frozen=True)
class ShapeBin:
    """One magnitude bin of a :class:`ShapeCheck`.

    Attributes
    ----------
    mag : float
        The bin's centre.
    n : int
        Injections in the bin.
    observed : int
        Of them, detected (positive outcomes).
    expected : float
        Detections the posterior predicts for the same injections.
    z : float or None
        ``(observed - expected) / sd``; None when the bin is left out (predictive variance below
        :data:`MIN_VARIANCE`).
    """

    mag: float
    n: int
    observed: int
    expected: float
    z: float | None

    def to_dict(self) -> dict:
        """The JSON form: keys ``mag``, ``n``, ``observed``, ``expected``, ``z``."""
        return {"mag": self.mag, "n": self.n, "observed": self.observed, "expected": self.expected, "z": self.z}


@dataclass(frozen=True)
class ShapeCheck:
    """The posterior predictive check of a fit's detections per magnitude bin (:func:`shape_check`).

    Attributes
    ----------
    chi2 : float or None
        Sum of ``z**2`` over the bins used; None when no bin qualifies.
    dof : int
        Bins used.
    p_value : float or None
        Chi-square tail probability of ``chi2`` for ``dof``; None when no bin qualifies.
    max_abs_z : float or None
        The largest ``|z|``; None when no bin qualifies.
    mag_at_max : float or None
        Centre of that bin; None when no bin qualifies.
    bins : tuple of ShapeBin
        Every bin, in magnitude order.
    """

    chi2: float | None
    dof: int
    p_value: float | None
    max_abs_z: float | None
    mag_at_max: float | None
    bins: tuple[ShapeBin, ...]

    def to_dict(self) -> dict:
        """The JSON form (``summary.json``: ``kinds.<kind>.model.shape_check``)."""
        return {"chi2": self.chi2, "dof": self.dof, "p_value": self.p_value, "max_abs_z": self.max_abs_z,
                "mag_at_max": self.mag_at_max, "bins": [b.to_dict() for b in self.bins]}

    @classmethod
    def from_dict(cls, d: dict) -> "ShapeCheck":
        """The check from its JSON form (:meth:`to_dict`)."""
        return cls(chi2=d["chi2"], dof=d["dof"], p_value=d["p_value"], max_abs_z=d["max_abs_z"],
                   mag_at_max=d["mag_at_max"], bins=tuple(ShapeBin(**b) for b in d["bins"]))


def shape_check(model, draws, mag_edges) -> ShapeCheck:
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
    ShapeCheck
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
    return ShapeCheck(
        chi2=chi2,
        dof=dof,
        p_value=float(special.chdtrc(dof, chi2)) if dof else None,
        max_abs_z=float(abs(z[worst])) if dof else None,
        mag_at_max=float(centres[worst]) if dof else None,
        bins=tuple(ShapeBin(mag=float(c), n=int(round(nn)), observed=int(round(o)), expected=float(e),
                            z=None if not u else float(zz))
                   for c, nn, o, e, u, zz in zip(centres, count, observed, expected, used, z)),
    )


def shape_warning(check: ShapeCheck, *, name: str, kind: str, quantity: str) -> str | None:
    """The warning text for a failed check, or None when the model describes the outcomes."""
    p = check.p_value
    if p is None or p >= P_WARN:
        return None
    what = f"the {quantity} curve" if name == quantity else f"the {name} {quantity} curve"
    # completeness has more flexible rungs to offer; purity has one model
    remedy = ("trust the binned ratios, or fit a more flexible model (--model)" if quantity == "completeness"
              else f"trust the binned {quantity} ratios")
    return (f"{what} of {kind} does not describe the binned outcomes (chi2 = {check.chi2:.1f} "
            f"for {check.dof} magnitude bins, p = {p:.1e}; worst bin at {check.mag_at_max:.2f} mag, "
            f"{check.max_abs_z:.1f} sigma): with this many injections the model's form, not its statistics, "
            f"limits it and its intervals are too narrow; {remedy}")
