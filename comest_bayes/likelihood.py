"""Likelihood of the Bayesian completeness model (pure JAX numerics, float64).

Model
-----
Every injection ``i`` has an outcome ``y_i`` (detected or not) and covariates:
its true magnitude ``m``, the depth ``d = -2.5 log10(sigma / sigma_ref)`` at its
position (``sigma`` the detection noise there), the normalised image
coordinates ``u = 2 x / (nx - 1) - 1`` and ``v = 2 y / (ny - 1) - 1`` in
``[-1, 1]``, and for galaxies the size ``s = log10(hlr / hlr_ref)``.  The
probability of detection is::

    f = floor + (A - floor) * g(z),      z = (m50 - m) / w,
    m50 = m50_0 + beta_depth d + beta_size s + sum_j c_j B_j(u, v),
    log w = log_w + w_depth d,

with ``g`` the logistic ``1 / (1 + exp(-z))``, the standard normal CDF
(``probit``), or ``0.5 (1 + z / sqrt(1 + z^2))`` (``pritchet``).  Which terms
exist is set by a :class:`~comest_bayes.modelspec.ModelSpec`.

Unconstrained parameters
------------------------
The sampler and optimiser work on an unconstrained vector ``theta``, in this
order (absent terms are skipped)::

    m50_0, log_w, logit_A, logit_floor, beta_depth, w_depth, beta_size, c_...

with ``A = sigmoid(logit_A)`` and ``floor = A * sigmoid(logit_floor)``, so that
``0 < floor < A < 1`` for every finite ``theta``.  With ``plateau = "fixed"``
``A = 1`` (and ``floor = sigmoid(logit_floor)``); with ``floor = "fixed"``
``floor = 0``.  The priors of :data:`comest_bayes.modelspec.DEFAULT_PRIORS` are
densities of ``m50_0``, ``log w``, ``A``, ``floor / A``, ``beta_depth``,
``w_depth``, ``beta_size`` and each ``c_j``; :meth:`CompletenessModel.log_prior`
is their density *in theta space*: the Beta priors on ``A`` and
``r = floor / A`` carry the Jacobian of the logit, which turns
``Beta(a, b)`` into ``a log s + b log(1 - s) - log B(a, b)`` with
``s = sigmoid(theta)``.  Every prior is proper and normalised, so the
posterior in theta is proper even where the data leave a direction flat
(``A -> 1`` when every bright injection is found, ``floor -> 0``).

Numerics
--------
``log f`` and ``log(1 - f)`` are computed in log space, never as ``log`` of a
difference.  For the probit (``log_ndtr(+-z)``) and the Pritchet form (whose
small tail ``q = 0.5 / (r (r + |z|))``, ``r = sqrt(1 + z^2)``, is formed
directly) :func:`mixture_logs` combines ``log g`` and ``log(1 - g)`` as
``log f = logaddexp(log floor + log(1 - g), log A + log g)`` and
``log(1 - f) = logaddexp(log(1 - A) + log g, log(1 - floor) + log(1 - g))``.
For the logistic (``log g = -softplus(-z)``, ``log(1 - g) = log g - z``) the
same quantities are obtained by :func:`logistic_mixture_logs` from one ``exp``,
one ``log1p`` and two ``log`` per cell, using ``(1 - g) / g = exp(-z)``
(value and gradient about 1.6 times faster than the log-add-exp form on CPU,
and equal to it to rounding: tested).
A fixed ``A = 1`` or ``floor = 0`` drops the vanishing term; a numeric ``-inf``
is also safe (guarded log-add-exp).  ``log(1 - floor)`` is formed as
``logaddexp(log(1 - A), log A + log(1 - r))``, finite for any finite theta.

The density is ``-inf`` (with zero gradient) outside the box
``|theta_i| <= THETA_BOUND`` and for NaN entries, and is evaluated at a safe
point there, so absurd parameters give ``-inf`` and never NaN; inside the box
the total ``log w`` is clipped to ``+-LOG_W_CLIP``.  All of this only touches
parameters hundreds of prior sigmas away from any plausible value.

Binomial cells
--------------
The data are cells of ``n`` trials with ``k`` successes sharing covariates; the
log-likelihood is ``sum k log f + (n - k) log(1 - f)``.  The binomial
coefficient ``log C(n, k)`` does not depend on the parameters and is dropped,
so a cell of ``n`` identical injections contributes exactly what its ``n``
Bernoulli terms contribute: :func:`compress` and :func:`uncompressed` give the
same likelihood when members of a cell share covariates.  :func:`compress`
bins the covariates on a fine grid and gives each cell the *mean* covariates of
its members; by default it also separates detected from undetected members of
a grid cell, which cancels the first-order term of the binning error exactly
(the derivative of the log-likelihood is the same for all members of a cell,
and their covariates average to the cell's), so the difference to the unbinned
likelihood is second order in the grid step.
"""

from __future__ import annotations

import math
import os
import warnings
from dataclasses import dataclass, field
from typing import Mapping, NamedTuple

import numpy as np
from .jaxnum import jax, jnp, stored_jit  # float64 on (the one place that sets it)
from jax.scipy.special import log_ndtr  # noqa: E402
from scipy import special as _sp  # noqa: E402

from .errors import ConfigError, InputError  # noqa: E402
from .modelspec import ModelSpec, load_spec, resolve_candidates  # noqa: E402
from .shapes import __file__ as _shapes_file  # noqa: E402
from .shapes import (SPLINE_H, SPLINE_T0, full_eta, logaddexp, monotone_spline, richards_logs,  # noqa: E402
                     softplus)

__all__ = [
    "Covariates",
    "BinomialData",
    "CompletenessModel",
    "covariates_from_outcomes",
    "compress",
    "compress_for",
    "uncompressed",
    "covariates_needed",
    "covariate_warnings",
    "link_logs",
    "mixture_logs",
    "logistic_mixture_logs",
    "smooth_basis",
    "smooth_basis_names",
    "Z_CLIP",
    "THETA_BOUND",
    "LOG_W_CLIP",
]

#: |z| is clipped to this value before the link, so that absurd parameters give
#: finite or -inf log-probabilities, never NaN (z^2 stays representable).
Z_CLIP = 1e100

#: The density is -inf outside |theta_i| <= THETA_BOUND (and for NaN theta).  Every
#: meaningful value lies far inside (logit 1e4 is A = 1 - e^-10000, 1e4 mag is no
#: magnitude); the box keeps overflow, and NaN gradients, out of the arithmetic.
THETA_BOUND = 1e4

#: The total log w (log_w + w_depth * d) is clipped to +-LOG_W_CLIP before use
#: (w between 2e-22 and 5e21 mag), so that z stays finite.
LOG_W_CLIP = 50.0

_COVARIATE_GROUPS = ("m", "depth", "uv", "size")


# ---------------------------------------------------------------------------
# Data containers
# ---------------------------------------------------------------------------

def _as_float_array(name: str, value, n: int | None = None) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim == 0 and n is not None:
        arr = np.full(n, float(arr))
    if arr.ndim != 1:
        raise InputError(f"covariate {name!r} must be 1-D, got shape {arr.shape}.")
    return arr


@dataclass(frozen=True)
class Covariates:
    """Covariates of injections (or of compressed cells), one row each.

    Parameters
    ----------
    m : ndarray, shape (N,)
        Magnitude (true magnitude for completeness, measured for purity).
    depth : ndarray, shape (N,)
        ``d = -2.5 log10(sigma / sigma_ref)`` (mag; 0 where unknown).
    u, v : ndarray, shape (N,)
        Normalised image coordinates in [-1, 1]: ``u = 2 x / (nx - 1) - 1``.
    size : ndarray, shape (N,)
        ``log10(hlr / hlr_ref)`` (0 for point sources or unknown).

    All arrays are stored as float64 and must be finite; use
    :meth:`make` to broadcast scalars.
    """

    m: np.ndarray
    depth: np.ndarray
    u: np.ndarray
    v: np.ndarray
    size: np.ndarray

    def __post_init__(self):
        m = _as_float_array("m", self.m)
        n = m.shape[0]
        object.__setattr__(self, "m", m)
        for name in ("depth", "u", "v", "size"):
            arr = _as_float_array(name, getattr(self, name), n)
            if arr.shape[0] != n:
                raise InputError(f"covariate {name!r} has {arr.shape[0]} rows but m has {n}.")
            object.__setattr__(self, name, arr)
        for name in ("m", "depth", "u", "v", "size"):
            bad = ~np.isfinite(getattr(self, name))
            if bad.any():
                raise InputError(f"covariate {name!r} has {int(bad.sum())} non-finite values; build covariates "
                                 "with covariates_from_outcomes, which drops or replaces them with a warning.")

    @classmethod
    def make(cls, m, depth=0.0, u=0.0, v=0.0, size=0.0) -> "Covariates":
        """Covariates with scalars broadcast to the length of ``m``."""
        m = np.atleast_1d(np.asarray(m, dtype=np.float64))
        b = np.broadcast_arrays(m, *(np.asarray(a, dtype=np.float64) for a in (depth, u, v, size)))
        return cls(*(np.ascontiguousarray(a).ravel() for a in b))

    def __len__(self) -> int:
        return int(self.m.shape[0])

    def take(self, index) -> "Covariates":
        """Rows ``index`` (any numpy index)."""
        return Covariates(self.m[index], self.depth[index], self.u[index], self.v[index], self.size[index])


@dataclass(frozen=True)
class BinomialData:
    """Outcomes grouped into binomial cells.

    Parameters
    ----------
    cov : Covariates
        Covariates of each of the G cells.
    n : ndarray of int64, shape (G,)
        Trials per cell (>= 1).
    k : ndarray of int64, shape (G,)
        Successes (detections) per cell, ``0 <= k <= n``.
    index : ndarray of int64, shape (N,), or None
        Cell of every original injection (so ``np.bincount(index) == n``).
    meta : dict
        ``sigma_ref``, ``hlr_ref``, ``image_shape``, ``N``, ``ncells``,
        ``compressed``, ``binned`` (covariate groups resolved by the cells:
        subset of ``("m", "depth", "uv", "size")``) and the grid steps.
    """

    cov: Covariates
    n: np.ndarray
    k: np.ndarray
    index: np.ndarray | None = None
    meta: dict = field(default_factory=dict)

    def __post_init__(self):
        n = np.asarray(self.n)
        k = np.asarray(self.k)
        if n.shape != (len(self.cov),) or k.shape != n.shape:
            raise InputError(f"n and k must have one entry per cell ({len(self.cov)}), got {n.shape} and {k.shape}.")
        if not (np.all(n == np.round(n)) and np.all(k == np.round(k))):
            raise InputError("n and k must be whole numbers.")
        n = n.astype(np.int64)
        k = k.astype(np.int64)
        if np.any(n < 1) or np.any(k < 0) or np.any(k > n):
            raise InputError("cells need n >= 1 and 0 <= k <= n.")
        object.__setattr__(self, "n", n)
        object.__setattr__(self, "k", k)
        if self.index is not None:
            object.__setattr__(self, "index", np.asarray(self.index, dtype=np.int64))

    @property
    def ncells(self) -> int:
        return int(self.n.shape[0])

    @property
    def ntotal(self) -> int:
        """Number of injections (sum of n)."""
        return int(self.n.sum())


# ---------------------------------------------------------------------------
# From the outcome table to covariates
# ---------------------------------------------------------------------------

def _colnames(table) -> list[str]:
    if hasattr(table, "colnames"):
        return list(table.colnames)
    if isinstance(table, Mapping):
        return list(table.keys())
    names = getattr(getattr(table, "dtype", None), "names", None)
    if names:
        return list(names)
    raise InputError(f"outcomes must be an astropy Table, a mapping of columns or a structured array, "
                     f"got {type(table).__name__}.")


def covariates_from_outcomes(outcomes, *, image_shape, sigma_ref: float | None = None,
                             hlr_ref: float | None = None, mag_column: str = "mag",
                             outcome_column: str = "detected") -> tuple[Covariates, np.ndarray, dict]:
    """Covariates and outcomes of the completeness model from an outcome table.

    Parameters
    ----------
    outcomes : astropy.table.Table or mapping of columns
        One row per injection, with columns ``mag_column`` (default ``mag``)
        and ``outcome_column`` (default ``detected``, bool or 0/1), and
        optionally ``x``, ``y`` (0-based pixels), ``noise`` (detection noise
        sigma at the position, image units) and ``hlr_arcsec`` (half-light
        radius, NaN for point sources).  Missing optional columns give
        covariates of 0; ``meta["available"]`` lists the ones present.
    image_shape : tuple (ny, nx) or None
        Shape of the image, to normalise ``x, y`` to ``u, v`` in [-1, 1].
        Needed when the table has ``x`` and ``y``.
    sigma_ref : float, optional
        Reference noise of the depth covariate (default: median of the finite,
        positive ``noise`` values), so ``d = 0`` at the median depth.
    hlr_ref : float, optional
        Reference half-light radius (arcsec; default: median of the finite,
        positive ``hlr_arcsec``).
    mag_column, outcome_column : str
        Column names of the magnitude and the outcome (for purity: the
        measured magnitude and real-or-false).

    Returns
    -------
    cov : Covariates
        Covariates of the kept rows.
    detected : ndarray of bool, shape (N,)
        Outcome of the kept rows.
    meta : dict
        ``sigma_ref``, ``hlr_ref``, ``image_shape``, ``N`` (kept rows),
        ``n_input``, ``dropped_rows`` (indices into the input of the rows
        left out), ``available`` (covariate groups with data),
        ``mag_column``, ``outcome_column``.

    Notes
    -----
    * Rows whose magnitude, or (when present) ``x`` or ``y``, is not finite
      are dropped with a warning giving their number; if no row is left,
      :class:`InputError` is raised.
    * A non-finite or non-positive ``noise`` gives ``d = 0`` (the reference
      depth) with a warning giving the number of such rows.
    * A non-finite or non-positive ``hlr_arcsec`` (point sources) gives
      ``size = 0``; when the table mixes such rows with sized ones a warning
      says how many.
    * Positions more than one pixel outside the image raise
      :class:`InputError` (usually a transposed ``image_shape``).
    """
    names = _colnames(outcomes)
    for col in (mag_column, outcome_column):
        if col not in names:
            raise InputError(f"outcome table has no column {col!r}; columns present: {names}.")
    n_input = len(np.asarray(outcomes[mag_column]))
    if n_input == 0:
        raise InputError("outcome table is empty: there is nothing to fit.")
    mag = np.asarray(outcomes[mag_column], dtype=np.float64)
    raw = np.asarray(outcomes[outcome_column])
    if raw.dtype.kind == "b":
        det = raw.astype(bool)
    else:
        try:
            vals = raw.astype(np.float64)
        except (TypeError, ValueError):
            raise InputError(f"column {outcome_column!r} must be boolean or 0/1, got dtype {raw.dtype}.") from None
        if not np.all(np.isin(vals, (0.0, 1.0))):
            raise InputError(f"column {outcome_column!r} must be boolean or 0/1; found other values "
                             f"(e.g. {vals[~np.isin(vals, (0.0, 1.0))][:3].tolist()}).")
        det = vals.astype(bool)

    has_xy = "x" in names and "y" in names
    keep = np.isfinite(mag)
    reasons = [f"{int((~np.isfinite(mag)).sum())} with non-finite {mag_column}"]
    if has_xy:
        if image_shape is None:
            raise InputError("the outcome table has x and y, so image_shape=(ny, nx) is needed to normalise them.")
        x = np.asarray(outcomes["x"], dtype=np.float64)
        y = np.asarray(outcomes["y"], dtype=np.float64)
        bad_xy = ~(np.isfinite(x) & np.isfinite(y))
        reasons.append(f"{int(bad_xy.sum())} with non-finite x or y")
        keep &= ~bad_xy
    ndrop = int((~keep).sum())
    if ndrop == n_input:
        raise InputError(f"all {n_input} rows of the outcome table have non-finite {mag_column} or position; "
                         "nothing to fit.")
    if ndrop:
        warnings.warn(f"dropped {ndrop} of {n_input} outcome rows with non-finite covariates "
                      f"({', '.join(reasons)}).", UserWarning, stacklevel=2)
    rows = np.flatnonzero(keep)
    mag = mag[rows]
    det = det[rows]
    n = rows.size
    available = ["m"]

    if has_xy:
        shape = tuple(int(s) for s in image_shape)
        if len(shape) != 2 or min(shape) < 2:
            raise InputError(f"image_shape must be (ny, nx) with both >= 2, got {image_shape!r}.")
        ny, nx = shape
        x, y = x[rows], y[rows]
        out = (x < -1.0) | (x > nx) | (y < -1.0) | (y > ny)
        if out.any():
            raise InputError(f"{int(out.sum())} injection positions lie outside the image of shape (ny, nx) = "
                             f"{shape} (x in [{x.min():.1f}, {x.max():.1f}], y in [{y.min():.1f}, {y.max():.1f}]); "
                             "check image_shape (it is (ny, nx)).")
        u = np.clip(2.0 * x / (nx - 1) - 1.0, -1.0, 1.0)
        v = np.clip(2.0 * y / (ny - 1) - 1.0, -1.0, 1.0)
        available.append("uv")
    else:
        shape = None if image_shape is None else tuple(int(s) for s in image_shape)
        u = np.zeros(n)
        v = np.zeros(n)

    depth = np.zeros(n)
    if "noise" in names:
        noise = np.asarray(outcomes["noise"], dtype=np.float64)[rows]
        good = np.isfinite(noise) & (noise > 0)
        if not good.any():
            warnings.warn(f"no finite positive noise value in the outcome table ({n} rows); the depth covariate "
                          "is 0 everywhere.", UserWarning, stacklevel=2)
        else:
            if sigma_ref is None:
                sigma_ref = float(np.median(noise[good]))
            if not (np.isfinite(sigma_ref) and sigma_ref > 0):
                raise InputError(f"sigma_ref must be a finite positive noise level, got {sigma_ref!r}.")
            if not good.all():
                warnings.warn(f"{int((~good).sum())} of {n} outcome rows have a non-finite or non-positive noise; "
                              "their depth covariate is set to 0 (the reference depth).", UserWarning, stacklevel=2)
            depth[good] = -2.5 * np.log10(noise[good] / sigma_ref)
            available.append("depth")

    size = np.zeros(n)
    if "hlr_arcsec" in names:
        hlr = np.asarray(outcomes["hlr_arcsec"], dtype=np.float64)[rows]
        good = np.isfinite(hlr) & (hlr > 0)
        if good.any():
            if hlr_ref is None:
                hlr_ref = float(np.median(hlr[good]))
            if not (np.isfinite(hlr_ref) and hlr_ref > 0):
                raise InputError(f"hlr_ref must be a finite positive radius (arcsec), got {hlr_ref!r}.")
            if not good.all():
                warnings.warn(f"{int((~good).sum())} of {n} outcome rows have no positive half-light radius "
                              "(point sources or unknown); their size covariate is 0.", UserWarning, stacklevel=2)
            size[good] = np.log10(hlr[good] / hlr_ref)
            available.append("size")

    meta = {
        "sigma_ref": None if sigma_ref is None else float(sigma_ref),
        "hlr_ref": None if hlr_ref is None else float(hlr_ref),
        "image_shape": shape,
        "N": int(n),
        "n_input": int(n_input),
        "dropped_rows": np.flatnonzero(~keep),
        "available": tuple(available),
        "mag_column": mag_column,
        "outcome_column": outcome_column,
    }
    return Covariates(mag, depth, u, v, size), det, meta


# ---------------------------------------------------------------------------
# Compression into binomial cells
# ---------------------------------------------------------------------------

def _check_outcomes(cov: Covariates, detected) -> np.ndarray:
    if not isinstance(cov, Covariates):
        raise InputError(f"cov must be a Covariates, got {type(cov).__name__}.")
    det = np.asarray(detected)
    if det.shape != (len(cov),):
        raise InputError(f"detected must have one entry per injection ({len(cov)}), got shape {det.shape}.")
    if det.dtype.kind != "b":
        if not np.all(np.isin(det, (0, 1))):
            raise InputError("detected must be boolean or 0/1.")
        det = det.astype(bool)
    if len(cov) == 0:
        raise InputError("no outcomes: there is nothing to fit.")
    return det


def uncompressed(cov: Covariates, detected, meta: dict | None = None) -> BinomialData:
    """One cell per injection (n = 1): the unbinned Bernoulli likelihood.

    Parameters
    ----------
    cov : Covariates
        Covariates of the N injections.
    detected : array of bool, shape (N,)
        Outcomes.
    meta : dict, optional
        Metadata to carry (e.g. from :func:`covariates_from_outcomes`).
    """
    det = _check_outcomes(cov, detected)
    n = len(cov)
    out_meta = dict(meta or {})
    out_meta.update({"N": n, "ncells": n, "compressed": False, "binned": _COVARIATE_GROUPS})
    return BinomialData(cov=cov, n=np.ones(n, np.int64), k=det.astype(np.int64), index=np.arange(n), meta=out_meta)


def _bin_index(x: np.ndarray, step: float) -> np.ndarray:
    return np.floor((x - x.min()) / step).astype(np.int64)


#: Width (mag) of the coarse bins in which :func:`compress` measures how mixed the outcomes are.
MIX_BIN = 0.1


def _magnitude_index(x: np.ndarray, det: np.ndarray, dm: float, dm_max: float | None) -> np.ndarray:
    """Magnitude bin of every injection: step ``dm`` where outcomes are mixed, up to ``dm_max`` where not.

    The binning error of a cell is second order, about ``g (1 - g) dm^2 / (12 w^2)`` per member
    (``g`` the link's value): it vanishes where nearly every injection is detected or nearly every
    one missed.  Per coarse bin of :data:`MIX_BIN` mag the step is ``dm sqrt(0.25 / q)``, clipped to
    ``[dm, dm_max]``, with ``q = p (1 - p)`` of the shrunk fraction ``p = (k + 1/2) / (n + 1)`` (a bin
    of few outcomes never looks pure) and the largest ``q`` of the bin and its two neighbours (the
    step near a transition stays fine).  ``p (1 - p)`` bounds ``g (1 - g)`` from above on a plateau or
    floor (where ``p`` is the plateau's or floor's level), so every member's error stays at most that
    of the transition's.  The bins are unit steps of the warped coordinate ``W(x) = int dx / step``.
    """
    if dm_max is None or dm_max <= dm:
        return _bin_index(x, dm)
    lo = float(x.min())
    j = np.floor((x - lo) / MIX_BIN).astype(np.int64)
    nb = int(j.max()) + 1
    n = np.bincount(j, minlength=nb).astype(np.float64)
    k = np.bincount(j, weights=det.astype(np.float64), minlength=nb)
    p = (k + 0.5) / (n + 1.0)
    q = p * (1.0 - p)
    q = np.maximum(q, np.maximum(np.concatenate([q[1:], q[-1:]]), np.concatenate([q[:1], q[:-1]])))
    step = np.clip(dm * np.sqrt(0.25 / q), dm, dm_max)
    start = np.concatenate([[0.0], np.cumsum(MIX_BIN / step)])[:-1]  # W at each coarse bin's left edge
    return np.floor(start[j] + (x - lo - j * MIX_BIN) / step[j]).astype(np.int64)


def compress(cov: Covariates, detected, *, dm: float | None = 0.005, ddepth: float | None = 0.005,
             nuv: int | None = 64, dsize: float | None = 0.01, meta: dict | None = None,
             split_outcomes: bool = True, along_depth: bool = False, dm_max: float | None = None) -> BinomialData:
    """Group injections into binomial cells on a fine covariate grid.

    Parameters
    ----------
    cov : Covariates
        Covariates of the N injections.
    detected : array of bool, shape (N,)
        Outcomes.
    dm, ddepth, dsize : float or None
        Grid steps in magnitude, depth (mag) and log10 size (dex).  Defaults
        0.005, 0.005, 0.01.  ``None`` leaves the covariate unresolved (cells
        merge across it): only for models that do not use it, which
        :class:`CompletenessModel` checks through ``meta["binned"]``.
    nuv : int or None
        Cells per axis of the grid in ``(u, v)`` over [-1, 1] (default 64);
        ``None`` leaves position unresolved.
    meta : dict, optional
        Metadata to carry (e.g. from :func:`covariates_from_outcomes`).
    split_outcomes : bool
        If True (default), detected and undetected members of a grid cell
        form two cells, each with the mean covariates of its own members.
        This makes the first-order binning error vanish identically (see the
        module notes) at the cost of at most doubling the cells in the
        transition region.
    dm_max : float or None
        Largest magnitude step (default None: ``dm`` everywhere).  With it,
        the step grows from ``dm`` where detected and missed injections mix
        to ``dm_max`` where nearly all are detected or all missed, keeping
        every member's binning error at most the transition's
        (:func:`_magnitude_index`): the plateau and floor take a few cells
        instead of hundreds.
    along_depth : bool
        If True (with ``ddepth``), the magnitude grid is laid along
        ``m - depth`` instead of ``m``.  Detection at fixed signal-to-noise
        moves m50 one-for-one with the depth, so the model's ``z`` varies
        within a cell only through ``m - depth`` (step ``dm``) and through
        ``(beta_depth - 1) * depth`` (small): the depth step can then be
        several times coarser for the same binning error.

    Returns
    -------
    BinomialData
        Cells sorted by grid key, with ``n``, ``k``, mean covariates,
        ``index`` (the cell of every injection) and ``meta`` (``N``,
        ``ncells``, steps, ``binned``).

    Notes
    -----
    The number of cells is bounded by the number of occupied grid cells
    (times two with ``split_outcomes``), whatever N, so the cost of a
    likelihood call stops growing with N once N exceeds the grid.  Cells of
    members with identical covariates reproduce the unbinned likelihood
    exactly (up to rounding of the mean); otherwise the difference is second
    order in the steps: about ``-1/2 sum_i g(1-g) var(z)`` per cell, with
    ``var(z) = dm^2 / (12 w^2)`` for the magnitude step.
    """
    det = _check_outcomes(cov, detected)
    digits: list[np.ndarray] = []
    binned = ["m"]
    steps = {"dm": dm, "ddepth": ddepth, "nuv": nuv, "dsize": dsize}
    for name, value in steps.items():
        if value is None:
            continue
        if name == "nuv":
            if not (isinstance(value, (int, np.integer)) and not isinstance(value, bool) and value >= 1):
                raise InputError(f"nuv must be a positive integer or None, got {value!r}.")
        elif not (isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
                  and value > 0):
            raise InputError(f"{name} must be a positive step or None, got {value!r}.")
    if dm is None:
        raise InputError("dm cannot be None: the magnitude is used by every model.")
    if dm_max is not None and not (isinstance(dm_max, (int, float)) and math.isfinite(dm_max) and dm_max > 0):
        raise InputError(f"dm_max must be a positive step or None, got {dm_max!r}.")
    digits.append(_magnitude_index(cov.m - cov.depth if (along_depth and ddepth is not None) else cov.m, det, dm,
                                   dm_max))
    if ddepth is not None:
        digits.append(_bin_index(cov.depth, ddepth))
        binned.append("depth")
    if nuv is not None:
        for c in (cov.u, cov.v):
            digits.append(np.clip(np.floor((c + 1.0) * 0.5 * nuv), 0, nuv - 1).astype(np.int64))
        binned.append("uv")
    if dsize is not None:
        digits.append(_bin_index(cov.size, dsize))
        binned.append("size")
    if split_outcomes:
        digits.append(det.astype(np.int64))

    radices = [int(d.max()) + 1 for d in digits]
    if math.prod(radices) < 2 ** 62:
        key = np.zeros(len(cov), np.int64)
        for d, r in zip(digits, radices):
            key = key * r + d
        _, index = np.unique(key, return_inverse=True)
    else:  # pragma: no cover - only for absurdly wide covariate ranges
        _, index = np.unique(np.stack(digits, axis=1), axis=0, return_inverse=True)
    index = np.asarray(index).ravel().astype(np.int64)
    g = int(index.max()) + 1
    n = np.bincount(index, minlength=g)
    k = np.bincount(index, weights=det.astype(np.float64), minlength=g)

    def mean(x):
        return np.bincount(index, weights=x, minlength=g) / n

    cells = Covariates(mean(cov.m), mean(cov.depth), mean(cov.u), mean(cov.v), mean(cov.size))
    out_meta = dict(meta or {})
    out_meta.update({"N": len(cov), "ncells": g, "compressed": True, "binned": tuple(binned),
                     "split_outcomes": bool(split_outcomes), "along_depth": bool(along_depth), "dm_max": dm_max,
                     **steps})
    return BinomialData(cov=cells, n=n, k=np.round(k).astype(np.int64), index=index, meta=out_meta)


def covariates_needed(spec: ModelSpec) -> tuple[str, ...]:
    """Covariate groups a model uses: a subset of ``("m", "depth", "uv", "size")``."""
    spec = load_spec(spec)
    need = ["m"]
    if spec.uses_depth:
        need.append("depth")
    if spec.uses_smooth:
        need.append("uv")
    if spec.size_covariate:
        need.append("size")
    return tuple(need)


#: Below these extents a covariate is "constant" for the fit (its slope is set by the prior):
#: depth in mag, size in dex, and the side of the box holding every injection in (u, v) units
#: (0.25 = one eighth of the image side).
SPREAD_MIN = {"depth": 0.02, "size": 0.01, "uv": 0.25}


def covariate_warnings(spec, data: BinomialData) -> list[str]:
    """Messages for covariates that a model uses but the injections do not vary.

    Parameters
    ----------
    spec : ModelSpec or str
        The model to be fitted (a selection spec counts as its most complex
        candidate: every covariate any candidate uses).
    data : BinomialData
        The cells it is fitted to.

    Returns
    -------
    list of str
        One message per covariate group (``depth``, ``uv``, ``size``) that the
        model uses and whose range over the injections is below
        :data:`SPREAD_MIN`; the matching slopes (``beta_depth``, ``w_depth``,
        the smooth coefficients, ``beta_size``) are then set by their priors,
        and maps or queries away from the sampled range are the prior's
        extrapolation.  Empty when every used covariate varies.
    """
    spec = load_spec(spec)
    specs = resolve_candidates(spec) if spec.is_selection else [spec]
    need = set()
    for s in specs:
        need.update(covariates_needed(s))
    cov = data.cov
    out = []
    if "depth" in need:
        span = float(cov.depth.max() - cov.depth.min())
        if span < SPREAD_MIN["depth"]:
            out.append(f"the depth covariate spans only {span:.3g} mag over the {data.ntotal} injections (noise "
                       f"uniform, or all injections in one place): the depth slope of {spec.name!r} is set by its "
                       "prior; use a model without a depth term or inject over the whole image.")
    if "uv" in need:
        su = float(cov.u.max() - cov.u.min())
        sv = float(cov.v.max() - cov.v.min())
        if max(su, sv) < SPREAD_MIN["uv"]:
            out.append(f"all {data.ntotal} injections lie in one small spatial cell (u in [{cov.u.min():.3f}, "
                       f"{cov.u.max():.3f}], v in [{cov.v.min():.3f}, {cov.v.max():.3f}] of [-1, 1]): the smooth "
                       f"spatial terms of {spec.name!r} are set by their prior, and the m50 map away from that cell "
                       "is the prior's extrapolation; inject over the whole image.")
    if "size" in need:
        span = float(cov.size.max() - cov.size.min())
        if span < SPREAD_MIN["size"]:
            out.append(f"the size covariate spans only {span:.3g} dex over the {data.ntotal} injections: the size "
                       f"slope of {spec.name!r} is set by its prior.")
    return out


def compress_for(specs, cov: Covariates, detected, **kwargs) -> BinomialData:
    """:func:`compress` resolving only the covariates that the model(s) use.

    Parameters
    ----------
    specs : ModelSpec, str or sequence of them
        Model(s) that will be fitted to the result (a selection spec counts
        as all its candidates).
    cov, detected, kwargs
        As for :func:`compress` (grid steps, ``meta``, ``split_outcomes``).
    """
    if isinstance(specs, (ModelSpec, str, os.PathLike)):
        specs = [specs]
    need = set()
    for s in specs:
        s = load_spec(s)
        for child in (resolve_candidates(s) if s.is_selection else [s]):
            need.update(covariates_needed(child))
    # Steps 0.02 mag in m - depth (the grid is laid along the direction in which m50 moves with the
    # depth) and 0.1 mag in depth: with detected and undetected members in separate cells (each at
    # its members' mean covariates) the binning error is second order, ~ (dm^2 + (beta - 1)^2
    # ddepth^2) / (12 w^2) of the curvature per injection, and the number of cells -- the cost of
    # every likelihood call -- stays at a few thousand whatever N (the MAP shift against the
    # unbinned likelihood is measured in tests/test_likelihood.py).
    # On the plateau and the floor the magnitude step grows to 0.1 mag (see compress's dm_max): the
    # error per member stays at most the transition's, and those ranges take a few cells instead of
    # hundreds (the demo tile's point outcomes: 2169 cells at a uniform 0.02 mag, 768 with the grown step;
    # its buldisk m50 moved by 3e-6 mag).
    steps = {"ddepth": ("depth", 0.1), "nuv": ("uv", 16), "dsize": ("size", 0.01)}
    kwargs.setdefault("dm", 0.02)
    kwargs.setdefault("dm_max", 0.1)
    kwargs.setdefault("along_depth", True)
    for key, (group, default) in steps.items():
        if group not in need:
            kwargs[key] = None
        else:
            kwargs.setdefault(key, default)
    return compress(cov, detected, **kwargs)


# ---------------------------------------------------------------------------
# Link functions and the floor/plateau mixture (JAX, elementwise)
# ---------------------------------------------------------------------------

# The branch selections below use jnp.where rather than jnp.maximum / jnp.abs:
# JAX gives max(x, 0) and |x| a zero derivative at the kink, which would make
# the derivative of softplus wrong at exactly 0; with where, each branch is a
# smooth formula valid on its side, so derivatives are right everywhere.

_softplus = softplus
_logaddexp = logaddexp


def link_logs(z, link: str):
    """``log g(z)`` and ``log(1 - g(z))`` of a link, stable for any z.

    Parameters
    ----------
    z : array_like
        Standardised distance ``(m50 - m) / w`` (positive = brighter than m50).
        Clipped to ``[-Z_CLIP, Z_CLIP]``.
    link : {"logistic", "probit", "pritchet"}
        The transition shape.

    Returns
    -------
    log_g, log_1mg : jax arrays, shape of z
    """
    z = jnp.clip(jnp.asarray(z, dtype=jnp.float64), -Z_CLIP, Z_CLIP)
    if link == "logistic":
        log_g = -_softplus(-z)
        return log_g, log_g - z
    if link == "probit":
        return log_ndtr(z), log_ndtr(-z)
    if link == "pritchet":
        # g = 0.5 (1 + z / r), r = sqrt(1 + z^2).  The smaller of g and 1 - g is
        # q = 0.5 (1 - |z| / r) = 0.5 / (r (r + |z|)), without cancellation.
        a = jnp.where(z >= 0, z, -z)  # |z| whose derivative at 0 matches the z >= 0 branch
        # With |z| <= Z_CLIP = 1e100, r (r + |z|) <= 2e200: neither overflows nor underflows.
        r = jnp.sqrt(1.0 + a * a)
        q = 0.5 / (r * (r + a))
        log_q = jnp.log(q)
        log_1mq = jnp.log1p(-q)
        return jnp.where(z >= 0, log_1mq, log_q), jnp.where(z >= 0, log_q, log_1mq)
    raise ConfigError(f"unknown link {link!r}; valid links: logistic, probit, pritchet.")


def mixture_logs(log_g, log_1mg, *, log_A=None, log_1mA=None, log_floor=None, log_1mfloor=None):
    """``log f`` and ``log(1 - f)`` for ``f = floor + (A - floor) g``.

    ``1 - f = (1 - A) g + (1 - floor)(1 - g)``.  ``log_A=None`` means a fixed
    plateau ``A = 1`` and ``log_floor=None`` a fixed ``floor = 0``; the
    vanishing terms are then left out.  Numeric ``-inf`` arguments (for
    example ``log_floor = log 0``) are also safe: they give the same values
    and no NaN in values or gradients.

    Parameters
    ----------
    log_g, log_1mg : arrays
        From :func:`link_logs`.
    log_A, log_1mA : scalar or None
        ``log A`` and ``log(1 - A)``.
    log_floor, log_1mfloor : scalar or None
        ``log floor`` and ``log(1 - floor)``.
    """
    if log_floor is None:
        if log_A is None:
            return log_g, log_1mg
        return log_A + log_g, _logaddexp(log_1mA + log_g, log_1mg)
    la = 0.0 if log_A is None else log_A
    log_f = _logaddexp(log_floor + log_1mg, la + log_g)
    if log_A is None:
        return log_f, log_1mfloor + log_1mg
    return log_f, _logaddexp(log_1mA + log_g, log_1mfloor + log_1mg)


def _safe_log(x):
    """log(x) for x >= 0 whose gradient at x = 0 is 0 instead of NaN (the value is -inf)."""
    ok = x > 0
    return jnp.where(ok, jnp.log(jnp.where(ok, x, 1.0)), -jnp.inf)


def logistic_mixture_logs(z, *, log_A=None, log_1mA=None, log_floor=None, log_1mfloor=None):
    """:func:`mixture_logs` of :func:`link_logs` for the logistic link, in fewer operations.

    With ``e = exp(-|z|)``, ``L = log(1 + e)``, ``r = floor / A`` and
    ``q = (1 - A) / (1 - floor)`` (both in [0, 1) because floor < A)::

        log f       = log A       - L + log(1 + r e)   (z >= 0),   log(r + e)   (z < 0)
        log(1 - f)  = log(1-floor) - L + log(e + q)     (z >= 0),   log(1 + q e) (z < 0)

    which follow from ``(1 - g) / g = exp(-z)``: every sum is of non-negative
    terms (no cancellation) and the cost is one exp, one log1p and two logs
    per cell instead of a softplus and two log-add-exps.  ``None`` arguments mean ``A = 1``
    or ``floor = 0`` as in :func:`mixture_logs`, with which the result agrees
    to rounding (see the tests); only when ``r`` or ``q`` underflows to 0
    *and* ``|z| > 745`` (parameters far outside any posterior) does it give
    ``-inf`` where the log-add-exp form stays finite.
    """
    z = jnp.clip(jnp.asarray(z, dtype=jnp.float64), -Z_CLIP, Z_CLIP)
    pos = z >= 0
    a = jnp.where(pos, z, -z)  # |z|, with the derivative of the branch in use at z = 0
    e = jnp.exp(-a)
    big_l = jnp.log1p(e)
    if log_floor is None:
        log_f = -big_l - jnp.where(pos, 0.0, a)  # log g
    else:
        r = jnp.exp(log_floor if log_A is None else log_floor - log_A)
        log_f = -big_l + _safe_log(jnp.where(pos, 1.0 + r * e, r + e))
    if log_A is not None:
        log_f = log_f + log_A
    if log_A is None:
        log_1mf = -big_l - jnp.where(pos, a, 0.0)  # log(1 - g)
    else:
        q = jnp.exp(log_1mA if log_1mfloor is None else log_1mA - log_1mfloor)
        log_1mf = -big_l + _safe_log(jnp.where(pos, e + q, 1.0 + q * e))
    if log_1mfloor is not None:
        log_1mf = log_1mf + log_1mfloor
    return log_f, log_1mf


# ---------------------------------------------------------------------------
# Smooth spatial bases (numpy; evaluated once per data set)
# ---------------------------------------------------------------------------

def _poly_terms(order: int) -> list[tuple[int, int]]:
    return [(t - j, j) for t in range(1, order + 1) for j in range(t + 1)]


def _bspline_1d(x: np.ndarray, nbasis: int) -> np.ndarray:
    """Cubic B-splines on uniform knots covering [-1, 1]; shape (len(x), nbasis), rows sum to 1."""
    deg = 3
    h = 2.0 / (nbasis - deg)
    knots = -1.0 + h * (np.arange(nbasis + deg + 1) - deg)
    x = np.clip(x, -1.0, 1.0 - 1e-12)
    # Cox-de Boor recursion (de Boor 1978), degree 0 to 3, uniform spacing h.
    b = ((x[:, None] >= knots[None, :-1]) & (x[:, None] < knots[None, 1:])).astype(np.float64)
    for p in range(1, deg + 1):
        left = (x[:, None] - knots[None, : -(p + 1)]) / (p * h)
        right = (knots[None, p + 1:] - x[:, None]) / (p * h)
        b = left * b[:, :-1] + right * b[:, 1:]
    return b


def _bspline_constraint(nbasis: int) -> np.ndarray:
    """Orthonormal basis (K^2, K^2 - 1) of tensor coefficients whose field integrates to 0 over [-1, 1]^2."""
    deg = 3
    h = 2.0 / (nbasis - deg)
    # Integral of each 1-D function over [-1, 1]: Gauss-Legendre with 4 nodes per
    # knot interval is exact for the cubic pieces.
    nodes, weights = np.polynomial.legendre.leggauss(4)
    edges = -1.0 + h * np.arange(nbasis - deg + 1)
    xs = (edges[:-1, None] + h * 0.5 * (nodes[None, :] + 1.0)).ravel()
    ws = np.tile(weights * h * 0.5, nbasis - deg)
    integral = ws @ _bspline_1d(xs, nbasis)
    c = np.outer(integral, integral).ravel()
    q, _ = np.linalg.qr(c[:, None], mode="complete")
    return q[:, 1:]


def smooth_basis_names(basis: str, order: int) -> list[str]:
    """Names of the smooth coefficients: ``c_ij`` (Legendre degrees in u, v) or ``s_k``."""
    if basis == "poly":
        return [f"c_{i}{j}" for i, j in _poly_terms(order)]
    if basis == "bspline":
        return [f"s_{k}" for k in range(order * order - 1)]
    raise ConfigError(f"unknown smooth basis {basis!r}; valid: poly, bspline.")


def smooth_basis(u, v, basis: str, order: int) -> np.ndarray:
    """Smooth spatial basis at normalised coordinates.

    Parameters
    ----------
    u, v : array_like, shape (N,)
        Normalised image coordinates, clipped to [-1, 1].
    basis : {"poly", "bspline"}
        ``poly``: Legendre products ``P_i(u) P_j(v)``, ``1 <= i + j <= order``,
        ordered by total degree then falling power of u.  ``bspline``: tensor
        cubic B-splines with ``order`` functions per axis, projected onto the
        ``order**2 - 1`` dimensional space of fields with zero mean over the
        image (orthonormal projection, so iid coefficient priors stay iid).
    order : int
        Polynomial total degree or B-spline functions per axis.

    Returns
    -------
    ndarray, shape (N, J)
        Every column averages to zero over [-1, 1]^2, so the constant m50_0
        is the field average.
    """
    u = np.clip(np.asarray(u, dtype=np.float64).ravel(), -1.0, 1.0)
    v = np.clip(np.asarray(v, dtype=np.float64).ravel(), -1.0, 1.0)
    if basis == "poly":
        cols = []
        for i, j in _poly_terms(order):
            pu = np.polynomial.legendre.legval(u, [0.0] * i + [1.0])
            pv = np.polynomial.legendre.legval(v, [0.0] * j + [1.0])
            cols.append(pu * pv)
        return np.stack(cols, axis=1) if cols else np.zeros((u.size, 0))
    if basis == "bspline":
        bu = _bspline_1d(u, order)
        bv = _bspline_1d(v, order)
        tensor = (bu[:, :, None] * bv[:, None, :]).reshape(u.size, order * order)
        return tensor @ _bspline_constraint(order)
    raise ConfigError(f"unknown smooth basis {basis!r}; valid: poly, bspline.")


# ---------------------------------------------------------------------------
# The model: static structure + pure jitted functions
# ---------------------------------------------------------------------------

class _Structure(NamedTuple):
    """Hashable layout of the full parameter vector (a static jit argument).

    Every model of one structure shares one compiled likelihood: which
    parameters are free is data (a mask), so the rungs of a model selection
    (logistic, Richards, spline; with or without depth and width terms) all
    run through the same compiled functions.
    """

    family: str       # "logistic", "probit", "pritchet", or "flex" (Richards link and monotone spline)
    free_A: bool
    free_floor: bool
    n_knots: int      # free knot log-rates of the monotone spline (0: no spline compiled in)
    n_smooth: int     # columns of the smooth spatial basis


#: Families of the links: the flexible rungs share the "flex" code path.
_FAMILY = {"logistic": "logistic", "probit": "probit", "pritchet": "pritchet", "richards": "flex", "spline": "flex"}

#: Number of times the log-probability has been traced (compiled), for tests.
TRACE_COUNT = {"log_prob": 0}


def _slots(st: _Structure) -> dict:
    """Static positions of every parameter group in the full vector."""
    i = 2 + int(st.free_A) + int(st.free_floor)
    return {"A": 2 if st.free_A else None, "floor": 2 + int(st.free_A) if st.free_floor else None,
            "beta_depth": i, "w_depth": i + 1, "beta_size": i + 2, "log_nu": i + 3,
            "eta": (i + 4, i + 4 + st.n_knots), "coef": (i + 4 + st.n_knots, i + 4 + st.n_knots + st.n_smooth),
            "ndim": i + 4 + st.n_knots + st.n_smooth}


def _layout_names(st: _Structure, smooth_names) -> list[str]:
    names = ["m50_0", "log_w"]
    if st.free_A:
        names.append("logit_A")
    if st.free_floor:
        names.append("logit_floor")
    names += ["beta_depth", "w_depth", "beta_size", "log_nu"] + [f"eta_{k}" for k in range(st.n_knots)]
    return names + list(smooth_names)


def _unpack(st: _Structure, theta):
    """Named quantities from the full unconstrained vector (JAX)."""
    sl = _slots(st)
    p = {"m50_0": theta[0], "log_w": theta[1], "log_A": None, "log_1mA": None,
         "log_floor": None, "log_1mfloor": None}
    if st.free_A:
        a = theta[sl["A"]]
        p["log_A"] = -_softplus(-a)
        p["log_1mA"] = -_softplus(a)
    if st.free_floor:
        b = theta[sl["floor"]]
        log_r, log_1mr = -_softplus(-b), -_softplus(b)
        if p["log_A"] is None:
            p["log_floor"], p["log_1mfloor"] = log_r, log_1mr
        else:
            # 1 - floor = (1 - A) + A (1 - r): a sum of positive terms, finite for any finite theta
            p["log_floor"] = p["log_A"] + log_r
            p["log_1mfloor"] = _logaddexp(p["log_1mA"], p["log_A"] + log_1mr)
    for key in ("beta_depth", "w_depth", "beta_size", "log_nu"):
        p[key] = theta[sl[key]]
    p["eta"] = theta[sl["eta"][0]:sl["eta"][1]]
    p["coef"] = theta[sl["coef"][0]:sl["coef"][1]]
    return p


def _m50_and_logw(st: _Structure, p, depth, size, basis):
    m50 = p["m50_0"] + p["beta_depth"] * depth + p["beta_size"] * size
    if st.n_smooth:
        m50 = m50 + basis @ p["coef"]
    log_w = p["log_w"] + p["w_depth"] * depth
    return m50, jnp.clip(log_w, -LOG_W_CLIP, LOG_W_CLIP)


def _cell_logs(st: _Structure, theta, m, depth, size, basis):
    """``log f`` and ``log(1 - f)`` at covariates, for the *full* parameter vector ``theta``."""
    p = _unpack(st, theta)
    m50, log_w = _m50_and_logw(st, p, depth, size, basis)
    logs = dict(log_A=p["log_A"], log_1mA=p["log_1mA"], log_floor=p["log_floor"], log_1mfloor=p["log_1mfloor"])
    if st.family == "flex":
        t = jnp.clip((m - m50) * jnp.exp(-log_w), -Z_CLIP, Z_CLIP)
        s = monotone_spline(t, jnp.clip(p["eta"], -50.0, 50.0)) if st.n_knots else -t
        log_g, log_1mg = richards_logs(s, jnp.clip(p["log_nu"], -20.0, 20.0))
        return mixture_logs(log_g, log_1mg, **logs)
    z = (m50 - m) * jnp.exp(-log_w)
    if st.family == "logistic":
        return logistic_mixture_logs(z, **logs)
    log_g, log_1mg = link_logs(z, st.family)
    return mixture_logs(log_g, log_1mg, **logs)


def _log_prior(st: _Structure, theta, prior):
    """Log prior of the free entries of the full vector.

    ``prior = (a, b, lnorm, active, log_tau)``: per slot the two arguments of
    its prior (``mu, sigma`` of a normal, ``a, b`` of a Beta on the sigmoid),
    its log normalising constant, 1 for free slots (0 for pinned ones, which
    contribute nothing), and the log smoothness scale of the spline's random
    walk.
    """
    a, b, lnorm, active, log_tau = prior
    sl = _slots(st)
    beta_slots = [j for j in (sl["A"], sl["floor"]) if j is not None]
    e0, e1 = sl["eta"]
    normal = np.array([j for j in range(sl["ndim"]) if j not in beta_slots and not e0 <= j < e1], dtype=np.int64)
    t = theta[normal]
    total = jnp.sum(active[normal] * (-0.5 * ((t - a[normal]) / b[normal]) ** 2 - lnorm[normal]))
    for j in beta_slots:  # Beta(a, b) on sigmoid(theta_j), with the Jacobian of the logit
        total = total + active[j] * (-a[j] * _softplus(-theta[j]) - b[j] * _softplus(theta[j]) - lnorm[j])
    if st.n_knots:
        # first-order random walk of the knot log-rates outward from the anchor (eta = 0 at t = 0):
        # increments ~ N(0, tau^2 h); a proper Gaussian whose log-determinant is K log(tau^2 h)
        k0 = int(round(-SPLINE_T0 / SPLINE_H))
        eta = full_eta(theta[e0:e1], k0)
        var = jnp.exp(2.0 * log_tau) * SPLINE_H
        rw = -0.5 * jnp.sum(jnp.diff(eta) ** 2) / var - 0.5 * st.n_knots * jnp.log(2.0 * math.pi * var)
        total = total + active[e0] * rw
    return total


def _log_likelihood(st: _Structure, theta, data):
    m, depth, size, basis, n, k = data
    log_f, log_1mf = _cell_logs(st, theta, m, depth, size, basis)
    nk = n - k
    # 0 * (-inf) must count as 0: a cell with no failures does not care about log(1 - f);
    # padding cells (n = k = 0) contribute nothing.
    terms = jnp.where(k > 0, k * log_f, 0.0) + jnp.where(nk > 0, nk * log_1mf, 0.0)
    return jnp.sum(terms)


def _sanitize(x):
    return jnp.where(jnp.isnan(x) | (x == jnp.inf), -jnp.inf, x)


def _in_box(theta):
    return jnp.all(jnp.abs(theta) <= THETA_BOUND)  # False for NaN too


def _log_prob(st: _Structure, theta, data, prior):
    TRACE_COUNT["log_prob"] += 1  # runs at trace time only
    ok = _in_box(theta)
    safe = jnp.where(ok, theta, 0.0)  # evaluate at a harmless point outside the box: no NaN gradients
    return jnp.where(ok, _sanitize(_log_prior(st, safe, prior) + _log_likelihood(st, safe, data)), -jnp.inf)


def _value_and_grad(st, theta, data, prior):
    v, g = jax.value_and_grad(_log_prob, argnums=1)(st, theta, data, prior)
    g = jnp.where(jnp.isfinite(v), g, jnp.where(jnp.isfinite(g), g, 0.0))
    return v, g


def _log_prob_batch(st, thetas, data, prior, batch):
    # lax.map with batch_size = W is vmap; smaller batches keep W * G temporaries in cache for large G.
    return jax.lax.map(lambda t: _log_prob(st, t, data, prior), thetas, batch_size=batch)


def _cell_logs_batch(st, thetas, m, depth, size, basis):
    lf, l1 = jax.vmap(lambda t: _cell_logs(st, t, m, depth, size, basis))(thetas)
    return jnp.stack([lf, l1], axis=-1)


def _prob_m50_batch(st, thetas, m, depth, size, basis):
    def one(t):
        p = _unpack(st, t)
        m50, _ = _m50_and_logw(st, p, depth, size, basis)
        log_f, _ = _cell_logs(st, t, m, depth, size, basis)
        return jnp.exp(log_f), m50
    return jax.vmap(one)(thetas)


def _average_batch(st, thetas, mags, depth, size, basis, weight):
    """Weighted footprint average of f, shape (S, M); cells (P,) broadcast against magnitudes (M,)."""
    def one(t):
        log_f, _ = _cell_logs(st, t, mags[None, :], depth[:, None], size[:, None], basis[:, None, :])
        return weight @ jnp.exp(log_f)
    return jax.vmap(one)(thetas)


def _average_at_batch(st, thetas, mags, depth, size, basis, weight):
    """Weighted footprint average of f for each (draw, magnitude) pair: shape (S,)."""
    def one(t, mag):
        log_f, _ = _cell_logs(st, t, mag, depth, size, basis)
        return weight @ jnp.exp(log_f)
    return jax.vmap(one)(thetas, mags)


def _cell_grads(st, theta, m, depth, size, basis):
    """Gradients of every cell's log f and log(1 - f) with respect to the full theta: (G, 2, D)."""
    def logs(t):
        lf, l1 = _cell_logs(st, t, m, depth, size, basis)
        return jnp.stack([lf, l1], axis=-1)
    return jax.jacfwd(logs)(theta), logs(theta)


# stored_jit: jax.jit whose traced programs later processes load from disk (comest_bayes.jaxnum)
_SOURCES = (__file__, _shapes_file)
_jit_average_batch = stored_jit(_average_batch, 0, sources=_SOURCES)
_jit_average_at_batch = stored_jit(_average_at_batch, 0, sources=_SOURCES)
_jit_cell_grads = stored_jit(_cell_grads, 0, sources=_SOURCES)
_jit_log_prob = stored_jit(_log_prob, 0, sources=_SOURCES)
_jit_log_prior = jax.jit(lambda st, theta, prior: jnp.where(_in_box(theta), _sanitize(_log_prior(st, theta, prior)),
                                                            -jnp.inf), static_argnums=0)
_jit_log_likelihood = jax.jit(
    lambda st, theta, data: jnp.where(_in_box(theta), _sanitize(_log_likelihood(st, theta, data)), -jnp.inf),
    static_argnums=0)
_jit_value_and_grad = stored_jit(_value_and_grad, 0, sources=_SOURCES)
_jit_log_prob_batch = stored_jit(_log_prob_batch, (0, 4), sources=_SOURCES)
_jit_hessian = stored_jit(jax.hessian(_log_prob, argnums=1), 0, sources=_SOURCES, name="_hessian")
_jit_cell_logs_batch = stored_jit(_cell_logs_batch, 0, sources=_SOURCES)
_jit_prob_m50_batch = stored_jit(_prob_m50_batch, 0, sources=_SOURCES)

#: log_prob_batch vectorises over at most this many (walker, cell) pairs at once.
BATCH_ELEMENTS = 1 << 20

#: Cell counts are padded up to the next of these sizes (cells with n = 0), so that data sets of
#: similar size share one compiled likelihood: 2^(k/2) steps waste at most 41% of the work.
def padded_size(g: int) -> int:
    """Smallest ``round(256 * 2^(j/2))`` (j = 0, 1, ...) that holds ``g`` cells."""
    j = 0
    while True:
        size = int(round(256 * 2.0 ** (j / 2.0)))
        if size >= g:
            return size
        j += 1


def _prior_args(spec_prior: dict) -> tuple[float, float, float]:
    """(a, b, log normalising constant) of one prior."""
    if spec_prior["dist"] == "normal":
        mu, sigma = float(spec_prior["mu"]), float(spec_prior["sigma"])
        return mu, sigma, math.log(sigma) + 0.5 * math.log(2.0 * math.pi)
    a, b = float(spec_prior["a"]), float(spec_prior["b"])
    # log B(a, b) from scipy (jax's betaln is good to ~1e-8 only)
    return a, b, float(_sp.betaln(a, b))


def _np_link_logs(z: np.ndarray, link: str):
    z = np.clip(z, -Z_CLIP, Z_CLIP)
    if link in ("logistic", "richards", "spline"):
        log_g = -np.logaddexp(0.0, -z)
        return log_g, log_g - z
    if link == "probit":
        return _sp.log_ndtr(z), _sp.log_ndtr(-z)
    a = np.abs(z)
    r = np.sqrt(1.0 + a * a)
    q = 0.5 / (r * (r + a))
    log_q = np.log(q)
    log_1mq = np.log1p(-q)
    return np.where(z >= 0, log_1mq, log_q), np.where(z >= 0, log_q, log_1mq)


@dataclass(frozen=True)
class ModelLayout:
    """The compiled structure several specs share (see :func:`shared_layout`).

    Attributes
    ----------
    structure : _Structure
        Family, free plateau/floor, spline knots and smooth columns.
    smooth_basis, smooth_order : str, int
        The smooth basis of the layout (used by every spec with a smooth term).
    """

    structure: _Structure
    smooth_basis: str = "poly"
    smooth_order: int = 2

    @property
    def smooth_names(self) -> list[str]:
        return smooth_basis_names(self.smooth_basis, self.smooth_order) if self.structure.n_smooth else []


def _spec_layout(spec: ModelSpec) -> ModelLayout:
    n_smooth = len(smooth_basis_names(spec.smooth_basis, spec.smooth_order)) if spec.uses_smooth else 0
    st = _Structure(family=_FAMILY[spec.link], free_A=spec.plateau == "free", free_floor=spec.floor == "free",
                    n_knots=spec.spline_knots if spec.link == "spline" else 0, n_smooth=n_smooth)
    return ModelLayout(st, spec.smooth_basis, spec.smooth_order)


def shared_layout(specs) -> ModelLayout:
    """One layout that every spec of ``specs`` fits into, so all of them share one compile.

    Specs of the logistic, Richards and spline links with the same plateau,
    floor and smooth basis share the "flex" family (a logistic is its member
    with ``nu = 1`` and a straight spline); other combinations raise
    :class:`ConfigError` (fit those separately).
    """
    specs = [load_spec(s) for s in specs]
    layouts = [_spec_layout(s) for s in specs]
    if len(layouts) == 1:
        return layouts[0]
    sts = [lay.structure for lay in layouts]
    families = {st.family for st in sts}
    if not families <= {"logistic", "flex"}:
        raise ConfigError(f"specs {[s.name for s in specs]} mix links of different families "
                          f"({sorted(families)}); only logistic, richards and spline specs share a layout.")
    if len({(st.free_A, st.free_floor) for st in sts}) != 1:
        raise ConfigError(f"specs {[s.name for s in specs]} differ in a fixed plateau or floor; they cannot share "
                          "a layout.")
    knots = {st.n_knots for st in sts if st.n_knots}
    if len(knots) > 1:
        raise ConfigError(f"spline specs with different numbers of knots {sorted(knots)} cannot share a layout.")
    smooth = {(lay.smooth_basis, lay.smooth_order) for lay in layouts if lay.structure.n_smooth}
    if len(smooth) > 1:
        raise ConfigError(f"specs with different smooth bases {sorted(smooth)} cannot share a layout.")
    basis, order = next(iter(smooth)) if smooth else ("poly", 2)
    st = _Structure(family="flex", free_A=sts[0].free_A, free_floor=sts[0].free_floor,
                    n_knots=next(iter(knots)) if knots else 0, n_smooth=max(st.n_smooth for st in sts))
    return ModelLayout(st, basis, order)


class CompletenessModel:
    """Posterior of a completeness (or purity) model on binomial cells.

    Parameters
    ----------
    spec : ModelSpec or str
        The model (a name or path is loaded with :func:`load_spec`); not a
        selection spec.
    data : BinomialData
        From :func:`compress`, :func:`compress_for` or :func:`uncompressed`;
        must resolve every covariate the model uses (``meta["binned"]``).
    layout : ModelLayout, optional
        A layout shared with other specs (:func:`shared_layout`), so that
        they all run through one compiled likelihood; default: the spec's own.

    Attributes
    ----------
    names : list of str
        Names of the entries of the unconstrained vector ``theta`` (the free
        parameters).
    ndim : int
        Its length.
    tau : float or None
        Smoothness scale of the spline's random walk (spline models only);
        settable.

    Notes
    -----
    All methods taking ``theta`` accept a sequence or ndarray of length
    ``ndim`` (float64).  Internally ``theta`` is placed into the layout's full
    vector, whose other entries are pinned at 0 (no depth slope, ``nu = 1``,
    a straight spline, a flat field).  :meth:`log_prob`,
    :meth:`value_and_grad`, :meth:`log_prob_batch` and :meth:`hessian` run
    functions compiled once per layout and padded cell count (data, priors
    and the free-parameter mask are arguments, not baked-in constants, so
    new data of a similar size, other priors and other rungs of the same
    layout never recompile; :func:`padded_size`).  They return ``-inf``
    rather than NaN for parameters where the density is not defined or
    underflows (NaN entries, ``|theta_i| > THETA_BOUND``); a ``-inf`` value
    comes with a finite gradient (0 where undefined).

    ``kind = "purity"`` specs are fitted the same way: build the data from a
    table of detections with ``covariates_from_outcomes(...,
    mag_column="det_mag_auto", outcome_column=<real or false>)``.
    """

    def __init__(self, spec: ModelSpec | str, data: BinomialData, *, layout: ModelLayout | None = None):
        spec = load_spec(spec)
        if spec.is_selection:
            raise ConfigError(f"model spec {spec.name!r} is a selection spec (candidates {list(spec.candidates)}); "
                              "fit its candidates with comest_bayes.selection.select_model instead.")
        if not isinstance(data, BinomialData):
            raise InputError(f"data must be a BinomialData (from compress or uncompressed), got "
                             f"{type(data).__name__}.")
        if data.ncells == 0:
            raise InputError("no cells in the data: there is nothing to fit.")
        need = covariates_needed(spec)
        binned = tuple(data.meta.get("binned", _COVARIATE_GROUPS))
        missing = [g for g in need if g not in binned]
        if missing:
            raise InputError(f"model {spec.name!r} uses the covariate(s) {missing}, but the data were compressed "
                             f"without resolving them (binned: {list(binned)}); compress with their grid steps, "
                             "or use compress_for(spec, ...).")
        available = data.meta.get("available")
        for group, label in (("depth", "depth (no usable noise column)"), ("size", "size (no half-light radii)")):
            if group in need and available is not None and group not in available:
                warnings.warn(f"model {spec.name!r} uses the {label}; that covariate is 0 for every injection, "
                              "so its slope is constrained by its prior only.", UserWarning, stacklevel=2)
        own = _spec_layout(spec)
        layout = own if layout is None else layout
        st = layout.structure
        if own.structure.family != st.family and not (st.family == "flex" and own.structure.family == "logistic"):
            raise ConfigError(f"model {spec.name!r} (link {spec.link}) does not fit the layout of family {st.family}.")
        if (own.structure.free_A, own.structure.free_floor) != (st.free_A, st.free_floor):
            raise ConfigError(f"model {spec.name!r} has another plateau/floor setting than the layout.")
        if own.structure.n_knots and own.structure.n_knots != st.n_knots:
            raise ConfigError(f"model {spec.name!r} has {own.structure.n_knots} spline knots, the layout {st.n_knots}.")
        if spec.uses_smooth and (own.smooth_names != layout.smooth_names):
            raise ConfigError(f"model {spec.name!r} has another smooth basis than the layout.")
        self.spec = spec
        self.data = data
        self.layout = layout
        self._st = st
        self.full_names = _layout_names(st, layout.smooth_names)
        sl = _slots(st)
        free = {"m50_0": "m50_0", "log_w": "log_w"}
        if st.free_A:
            free["logit_A"] = "A"
        if st.free_floor:
            free["logit_floor"] = "floor"
        if spec.spatial in ("depth", "depth+smooth"):
            free["beta_depth"] = "beta_depth"
        if spec.width_depth:
            free["w_depth"] = "w_depth"
        if spec.size_covariate:
            free["beta_size"] = "beta_size"
        if spec.link == "richards":
            free["log_nu"] = "log_nu"
        if spec.link == "spline":
            free.update({f"eta_{k}": None for k in range(st.n_knots)})
        self.smooth_names = smooth_basis_names(spec.smooth_basis, spec.smooth_order) if spec.uses_smooth else []
        free.update({name: "smooth" for name in self.smooth_names})
        self.names = [n for n in self.full_names if n in free]
        self.ndim = len(self.names)
        self._free_idx = np.array([self.full_names.index(n) for n in self.names], dtype=np.int64)
        nfull = sl["ndim"]
        a, b, lnorm, active = np.zeros(nfull), np.ones(nfull), np.zeros(nfull), np.zeros(nfull)
        for name in self.names:
            j = self.full_names.index(name)
            active[j] = 1.0
            key = free[name]
            if key is not None:
                a[j], b[j], lnorm[j] = _prior_args(spec.prior(key))
        self._prior_arrays = (a, b, lnorm, active)
        self.tau = spec.spline_tau if isinstance(spec.spline_tau, float) else DEFAULT_SPLINE_TAU
        self._pinned = np.zeros(nfull)
        cov = data.cov
        g = data.ncells
        size = padded_size(g)
        pad = size - g

        def padded(x, fill=None):
            x = np.asarray(x, dtype=np.float64)
            if not pad:
                return jnp.asarray(x)
            tail = np.repeat(x[-1:], pad, axis=0) if fill is None else np.full((pad,) + x.shape[1:], fill)
            return jnp.asarray(np.concatenate([x, tail]))

        self._data = (padded(cov.m), padded(cov.depth), padded(cov.size), padded(self._basis(cov)),
                      padded(data.n, 0.0), padded(data.k, 0.0))
        self._ncells = g

    # -- helpers ------------------------------------------------------------
    @property
    def tau(self) -> float | None:
        """Smoothness scale of the spline random walk (per unit of t); None for models without a spline."""
        return self._tau if self.spec.link == "spline" else None

    @tau.setter
    def tau(self, value: float) -> None:
        value = float(value)
        if not (math.isfinite(value) and value > 0):
            raise InputError(f"the spline smoothness tau must be a positive number, got {value!r}.")
        self._tau = value

    @property
    def _prior(self):
        a, b, lnorm, active = self._prior_arrays
        return (jnp.asarray(a), jnp.asarray(b), jnp.asarray(lnorm), jnp.asarray(active),
                jnp.asarray(math.log(self._tau)))

    def _basis(self, cov: Covariates) -> np.ndarray:
        n_smooth = self._st.n_smooth if hasattr(self, "_st") else 0
        if not n_smooth:
            return np.zeros((len(cov), 0))
        return smooth_basis(cov.u, cov.v, self.layout.smooth_basis, self.layout.smooth_order)

    def full(self, theta) -> np.ndarray:
        """The layout's full parameter vector(s) for free parameters ``theta`` (D,) or (S, D)."""
        t = np.asarray(theta, dtype=np.float64)
        out = np.broadcast_to(self._pinned, t.shape[:-1] + self._pinned.shape).copy()
        out[..., self._free_idx] = t
        return out

    def full_jax(self, theta):
        """:meth:`full` for a JAX array (traceable: usable inside jitted code)."""
        return jnp.asarray(self._pinned).at[self._free_idx].set(theta)

    def cell_logs(self, theta, m, depth, size, basis):
        """Traceable ``(log f, log(1 - f))`` at covariates for free parameters ``theta`` (JAX arrays)."""
        return _cell_logs(self._st, self.full_jax(theta), m, depth, size, basis)

    def basis_at(self, cov: Covariates) -> np.ndarray:
        """The smooth basis columns of the layout at covariates (N, J)."""
        return self._basis(cov)

    def _theta(self, theta) -> jnp.ndarray:
        t = np.asarray(theta, dtype=np.float64)
        if t.shape != (self.ndim,):
            raise InputError(f"theta must have shape ({self.ndim},) for model {self.spec.name!r} "
                             f"(parameters {self.names}), got {t.shape}.")
        return jnp.asarray(self.full(t))

    def _thetas(self, thetas) -> np.ndarray:
        t = np.asarray(thetas, dtype=np.float64)
        if t.ndim != 2 or t.shape[1] != self.ndim:
            raise InputError(f"thetas must have shape (S, {self.ndim}) for model {self.spec.name!r}, got {t.shape}.")
        return t

    def __repr__(self) -> str:
        return (f"CompletenessModel({self.spec.name!r}, ndim={self.ndim}, cells={self.data.ncells}, "
                f"N={self.data.ntotal})")

    # -- densities ----------------------------------------------------------
    def log_prior(self, theta) -> float:
        """Log prior density in theta space (normalised, Jacobians included)."""
        return float(_jit_log_prior(self._st, self._theta(theta), self._prior))

    def log_likelihood(self, theta) -> float:
        """``sum k log f + (n - k) log(1 - f)`` over cells (binomial coefficients dropped)."""
        return float(_jit_log_likelihood(self._st, self._theta(theta), self._data))

    def log_prob(self, theta) -> float:
        """Log posterior density (up to the evidence); -inf, never NaN, where undefined."""
        return float(_jit_log_prob(self._st, self._theta(theta), self._data, self._prior))

    def value_and_grad(self, theta) -> tuple[float, np.ndarray]:
        """:meth:`log_prob` and its gradient, shape (ndim,)."""
        v, g = _jit_value_and_grad(self._st, self._theta(theta), self._data, self._prior)
        return float(v), np.asarray(g)[self._free_idx]

    def log_prob_batch(self, thetas) -> np.ndarray:
        """:meth:`log_prob` of each row of ``thetas`` (W, ndim) -> (W,), for emcee ``vectorize=True``.

        A jitted vectorised map over the rows (``vmap`` in batches of at most
        :data:`BATCH_ELEMENTS` / G rows, which is faster than one ``vmap``
        over all walkers when the number of cells G is large).
        """
        t = self.full(self._thetas(thetas))
        w = t.shape[0]
        # rows in blocks of one fixed size (a power of two, at most LOG_PROB_ROWS): one compiled shape serves
        # importance-sampling batches of any length; emcee's fixed walker count gets its own
        rows = min(LOG_PROB_ROWS, 1 << max(0, int(math.ceil(math.log2(max(w, 1))))))
        batch = int(max(1, min(rows, BATCH_ELEMENTS // max(1, self._data[0].shape[0]))))
        out = np.empty(w)
        for start in range(0, w, rows):
            block = t[start:start + rows]
            nb = block.shape[0]
            if nb < rows:
                block = np.concatenate([block, np.repeat(block[-1:], rows - nb, axis=0)])
            out[start:start + nb] = np.asarray(_jit_log_prob_batch(self._st, jnp.asarray(block), self._data,
                                                                   self._prior, batch))[:nb]
        return out

    def hessian(self, theta) -> np.ndarray:
        """Hessian of :meth:`log_prob`, shape (ndim, ndim)."""
        h = np.asarray(_jit_hessian(self._st, self._theta(theta), self._data, self._prior))
        return h[np.ix_(self._free_idx, self._free_idx)]

    def cell_loglik(self, thetas, *, max_elements: int = 20_000_000) -> np.ndarray:
        """Per-cell ``log f`` and ``log(1 - f)`` for each parameter vector.

        Parameters
        ----------
        thetas : array, shape (S, ndim)
        max_elements : int
            Work in chunks of samples so that one chunk holds at most this many
            numbers (memory guard); the output itself is S * G * 2 float64.

        Returns
        -------
        ndarray, shape (S, G, 2)
            ``[..., 0] = log f`` (weight ``k`` per cell) and
            ``[..., 1] = log(1 - f)`` (weight ``n - k``): the pointwise
            log-likelihood of the groups (cell, outcome) for PSIS-LOO.
        """
        t = self.full(self._thetas(thetas))
        s, g = t.shape[0], self._ncells
        gp = self._data[0].shape[0]
        out = np.empty((s, g, 2))
        chunk = max(1, min(s, int(max_elements // max(1, 2 * gp))))
        m, depth, size, basis = self._data[:4]
        for start in range(0, s, chunk):
            block = t[start:start + chunk]
            nb = block.shape[0]
            if nb < chunk:  # pad to one compiled shape
                block = np.concatenate([block, np.repeat(block[-1:], chunk - nb, axis=0)])
            res = _jit_cell_logs_batch(self._st, jnp.asarray(block), m, depth, size, basis)
            out[start:start + nb] = np.asarray(res)[:nb, :g]
        return out

    def cell_gradients(self, theta) -> tuple[np.ndarray, np.ndarray]:
        """Per-cell log-likelihood terms and their gradients at one theta.

        Returns
        -------
        grads : ndarray, shape (G, 2, ndim)
            d log f / d theta (``[:, 0]``) and d log(1 - f) / d theta
            (``[:, 1]``) of every cell.
        logs : ndarray, shape (G, 2)
            ``log f`` and ``log(1 - f)``.
        """
        jac, logs = _jit_cell_grads(self._st, self._theta(theta), *self._data[:4])
        g = self._ncells
        return np.asarray(jac)[:g][:, :, self._free_idx], np.asarray(logs)[:g]

    def average_prob(self, thetas, mags, depth, u, v, weight, *, max_elements: int = 4_000_000) -> np.ndarray:
        """Weighted average of f over covariate cells, per draw: shape (S, M).

        Parameters
        ----------
        thetas : array, shape (S, ndim)
        mags : array, shape (M,)
        depth, u, v, weight : arrays, shape (P,)
            Footprint cells (:class:`comest_bayes.posterior.Footprint`);
            ``weight`` sums to 1.
        """
        t = self.full(self._thetas(np.atleast_2d(thetas)))
        mags = np.atleast_1d(np.asarray(mags, np.float64))
        nm = mags.size
        size = 16 * -(-nm // 16)  # pad the magnitudes to a multiple of 16: few compiled shapes
        mags = jnp.asarray(np.concatenate([mags, np.full(size - nm, mags[-1])]))
        p = len(weight)
        cov = Covariates.make(np.zeros(p), depth, u, v)
        args = (jnp.asarray(cov.depth), jnp.asarray(cov.size), jnp.asarray(self._basis(cov)),
                jnp.asarray(np.asarray(weight, np.float64)))
        chunk = int(max(1, min(len(t), max_elements // max(1, p * mags.shape[0]))))
        chunk = 1 << int(math.floor(math.log2(chunk)))  # a power of two: few compiled shapes
        out = np.empty((len(t), nm))
        for start in range(0, len(t), chunk):
            block = t[start:start + chunk]
            nb = len(block)
            if nb < chunk:  # pad to one compiled shape
                block = np.concatenate([block, np.repeat(block[-1:], chunk - nb, axis=0)])
            out[start:start + nb] = np.asarray(_jit_average_batch(self._st, jnp.asarray(block), mags, *args))[:nb, :nm]
        return np.clip(out, 0.0, 1.0)

    def average_prob_at(self, thetas, mags, depth, u, v, weight) -> np.ndarray:
        """Weighted average of f over covariate cells for draw ``s`` at magnitude ``mags[s]``: shape (S,)."""
        t = self.full(self._thetas(np.atleast_2d(thetas)))
        cov = Covariates.make(np.zeros(len(weight)), depth, u, v)
        s = len(t)
        size = 16
        while size < s:  # pad the draws to a power of two: few compiled shapes
            size *= 2
        mags = np.asarray(mags, np.float64)
        tp = np.concatenate([t, np.repeat(t[-1:], size - s, axis=0)])
        mp = np.concatenate([mags, np.full(size - s, mags[-1])])
        out = _jit_average_at_batch(self._st, jnp.asarray(tp), jnp.asarray(mp), jnp.asarray(cov.depth),
                                    jnp.asarray(cov.size), jnp.asarray(self._basis(cov)),
                                    jnp.asarray(np.asarray(weight, np.float64)))
        return np.clip(np.asarray(out)[:s], 0.0, 1.0)

    # -- predictions --------------------------------------------------------
    def _predict(self, theta, cov: Covariates):
        if not isinstance(cov, Covariates):
            raise InputError(f"cov must be a Covariates (use Covariates.make), got {type(cov).__name__}.")
        t = np.asarray(theta, dtype=np.float64)
        single = t.ndim == 1
        t2 = self.full(self._thetas(t[None, :] if single else t))
        basis = jnp.asarray(self._basis(cov))
        f, m50 = _jit_prob_m50_batch(self._st, jnp.asarray(t2), jnp.asarray(cov.m), jnp.asarray(cov.depth),
                                     jnp.asarray(cov.size), basis)
        f, m50 = np.asarray(f), np.asarray(m50)
        return (f[0], m50[0]) if single else (f, m50)

    def prob(self, theta, cov: Covariates) -> np.ndarray:
        """Completeness f at arbitrary covariates.

        Parameters
        ----------
        theta : array, shape (ndim,) or (S, ndim)
        cov : Covariates, N rows

        Returns
        -------
        ndarray, shape (N,) or (S, N), values in [0, 1]
        """
        return np.clip(self._predict(theta, cov)[0], 0.0, 1.0)

    def m50(self, theta, cov: Covariates) -> np.ndarray:
        """The m50 field at arbitrary covariates, shape (N,) or (S, N) (mag)."""
        return self._predict(theta, cov)[1]

    # -- parameters ---------------------------------------------------------
    def transform(self, theta) -> dict:
        """Physical parameters from theta of shape (ndim,) or (S, ndim).

        Returns
        -------
        dict
            ``m50_0``, ``w`` (mag), ``log_w``, ``A``, ``floor`` (1 and 0 when
            fixed), and when present ``beta_depth``, ``w_depth``,
            ``beta_size``, ``nu`` (Richards shape, with ``log_nu``), the
            spline's knot log-rates ``eta_k`` and the smooth coefficients
            (their own names); floats for one theta, arrays of shape (S,) for
            several.
        """
        t = np.asarray(theta, dtype=np.float64)
        if t.shape[-1:] != (self.ndim,) or t.ndim > 2:
            raise InputError(f"theta must have shape ({self.ndim},) or (S, {self.ndim}), got {t.shape}.")
        col = {name: t[..., i] for i, name in enumerate(self.names)}
        out = {"m50_0": col["m50_0"], "log_w": col["log_w"], "w": np.exp(col["log_w"])}
        a = _sp.expit(col["logit_A"]) if "logit_A" in col else np.ones_like(col["m50_0"])
        out["A"] = a
        out["floor"] = a * _sp.expit(col["logit_floor"]) if "logit_floor" in col else np.zeros_like(a)
        for name in self.names[2:]:
            if name not in ("logit_A", "logit_floor"):
                out[name] = col[name]
            if name == "log_nu":
                out["nu"] = np.exp(col[name])
        if t.ndim == 1:
            out = {k: float(v) for k, v in out.items()}
        return out

    def inverse_transform(self, params: Mapping[str, float]) -> np.ndarray:
        """theta from physical parameters (``m50_0``, ``w``, ``A``, ``floor``, slopes, coefficients).

        Missing slopes and coefficients are 0; ``A`` and ``floor`` default to
        0.97 and 0.01 (ignored when fixed); ``nu`` (or ``log_nu``) defaults to
        1.  Raises InputError for values outside their ranges
        (``0 < floor < A < 1``, ``w > 0``, ``nu > 0``).
        """
        w = float(params.get("w", math.exp(params.get("log_w", math.log(0.2)))))
        a = float(params.get("A", 0.97))
        fl = float(params.get("floor", 0.01))
        if not w > 0:
            raise InputError(f"w must be positive, got {w}.")
        theta = np.zeros(self.ndim)
        for i, name in enumerate(self.names):
            if name == "m50_0":
                theta[i] = float(params["m50_0"])
            elif name == "log_w":
                theta[i] = math.log(w)
            elif name == "logit_A":
                if not 0 < a < 1:
                    raise InputError(f"A must lie in (0, 1), got {a}.")
                theta[i] = math.log(a) - math.log1p(-a)
            elif name == "logit_floor":
                top = a if "logit_A" in self.names else 1.0
                if not 0 < fl < top:
                    raise InputError(f"floor must lie in (0, A) = (0, {top}), got {fl}.")
                r = fl / top
                theta[i] = math.log(r) - math.log1p(-r)
            elif name == "log_nu" and "nu" in params and "log_nu" not in params:
                nu = float(params["nu"])
                if not nu > 0:
                    raise InputError(f"nu must be positive, got {nu}.")
                theta[i] = math.log(nu)
            else:
                theta[i] = float(params.get(name, 0.0))
        return theta

    def warm_start(self, names, theta) -> np.ndarray:
        """A starting theta that takes the values of ``names`` from ``theta`` (another rung's MAP).

        Parameters this model has and the other lacks start where
        :meth:`initial` puts them (slopes at their prior means, a straight
        spline, ``nu = 1``, a flat field).
        """
        start = self.initial()
        other = dict(zip(list(names), np.asarray(theta, dtype=np.float64)))
        for i, name in enumerate(self.names):
            if name in other and np.isfinite(other[name]):
                start[i] = other[name]
        return start

    def initial(self) -> np.ndarray:
        """A sensible starting theta from the data (no optimisation of the full model).

        A coarse grid search of the model *without* spatial terms (m50, w, A,
        floor) on the magnitude histogram of the cells, maximising likelihood
        times prior (the flexible links are searched as the logistic they
        contain); slopes start at their prior means, ``nu`` at 1, the spline
        straight and smooth coefficients at 0.  Works for any data (all or no
        detections, separated outcomes, a handful of injections), where it
        lands on the prior-preferred edge.
        """
        if getattr(self, "_initial", None) is None:
            self._initial = self._grid_initial()
        return self._initial.copy()

    def _grid_initial(self) -> np.ndarray:
        data = self.data
        m = data.cov.m
        lo, hi = float(m.min()), float(m.max())
        nbins = int(min(400, max(1, math.ceil((hi - lo) / 0.02))))
        edges = np.linspace(lo, hi + 1e-9, nbins + 1)
        which = np.clip(np.searchsorted(edges, m, side="right") - 1, 0, nbins - 1)
        n = np.bincount(which, weights=data.n, minlength=nbins)
        k = np.bincount(which, weights=data.k, minlength=nbins)
        msum = np.bincount(which, weights=data.n * m, minlength=nbins)
        occ = n > 0
        n, k, mb = n[occ], k[occ], msum[occ] / n[occ]

        st = self._st
        pa, pb, _, _ = self._prior_arrays
        fn = self.full_names
        m50_grid = np.linspace(lo - 1.5, hi + 1.5, 91)
        w_grid = np.array([0.03, 0.06, 0.1, 0.15, 0.2, 0.3, 0.5, 0.8])
        a_grid = np.array([0.8, 0.9, 0.95, 0.98, 0.995]) if st.free_A else np.array([1.0])
        r_grid = np.array([0.001, 0.01, 0.03, 0.1]) if st.free_floor else np.array([0.0])
        z = (m50_grid[:, None, None] - mb[None, None, :]) / w_grid[None, :, None]  # (M, W, B)
        lg, _ = _np_link_logs(z, self.spec.link)
        g = np.exp(lg)
        i_m, i_w = fn.index("m50_0"), fn.index("log_w")
        best, best_val = None, -np.inf
        with np.errstate(divide="ignore", invalid="ignore"):
            for a in a_grid:
                for r in r_grid:
                    fl = a * r
                    f = np.clip(fl + (a - fl) * g, 1e-300, 1.0 - 1e-16)
                    ll = (k * np.log(f) + (n - k) * np.log1p(-f)).sum(axis=-1)
                    lp = (ll - 0.5 * ((m50_grid[:, None] - pa[i_m]) / pb[i_m]) ** 2
                          - 0.5 * ((np.log(w_grid)[None, :] - pa[i_w]) / pb[i_w]) ** 2)
                    if st.free_A:
                        j = fn.index("logit_A")
                        lp = lp + pa[j] * math.log(a) + pb[j] * math.log1p(-a)
                    if st.free_floor:
                        j = fn.index("logit_floor")
                        lp = lp + pa[j] * math.log(r) + pb[j] * math.log1p(-r)
                    idx = np.unravel_index(np.nanargmax(np.where(np.isfinite(lp), lp, -np.inf)), lp.shape)
                    if lp[idx] > best_val:
                        best_val = lp[idx]
                        best = (m50_grid[idx[0]], w_grid[idx[1]], a, a * r)
        if best is None:  # pragma: no cover - every grid point non-finite cannot happen with clipped f
            best = (0.5 * (lo + hi), 0.2, 0.97, 0.01)
        m50, w, a, fl = best
        params = {"m50_0": m50, "w": w, "A": min(a, 0.995), "floor": fl}
        for name in self.names:
            if name in ("beta_depth", "w_depth", "beta_size", "log_nu"):
                params[name] = pa[fn.index(name)]
        return self.inverse_transform(params)


#: Rows of parameter vectors per compiled call of :meth:`CompletenessModel.log_prob_batch`.
LOG_PROB_ROWS = 1024

#: Smoothness scale of the spline's random walk before it is chosen by the evidence
#: (:func:`comest_bayes.selection.choose_tau`), per unit of standardised magnitude.
DEFAULT_SPLINE_TAU = 0.3
