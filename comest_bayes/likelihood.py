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
import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
from jax.scipy.special import log_ndtr  # noqa: E402
from scipy import special as _sp  # noqa: E402

from .errors import ConfigError, InputError  # noqa: E402
from .modelspec import ModelSpec, load_spec, resolve_candidates  # noqa: E402

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


def compress(cov: Covariates, detected, *, dm: float | None = 0.005, ddepth: float | None = 0.005,
             nuv: int | None = 64, dsize: float | None = 0.01, meta: dict | None = None,
             split_outcomes: bool = True) -> BinomialData:
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
    digits.append(_bin_index(cov.m, dm))
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
                     "split_outcomes": bool(split_outcomes), **steps})
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
    # depth step 0.02 mag: the binning error ~ ddepth^2 beta^2 / (12 w^2) is about 1e-3 nat per cell
    # for w >= 0.15, while the cell count (and the emcee cost) drops 3x against 0.005
    steps = {"ddepth": ("depth", 0.02), "nuv": ("uv", 16), "dsize": ("size", 0.01)}
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

def _softplus(x):
    """log(1 + exp(x)), stable; written out because jax.nn.softplus is several times slower on CPU."""
    pos = x > 0
    return jnp.where(pos, x, 0.0) + jnp.log1p(jnp.exp(jnp.where(pos, -x, x)))


def _logaddexp(a, b):
    """log(exp(a) + exp(b)) that gives -inf (not NaN) and finite gradients when a term is -inf."""
    first = a >= b
    m = jnp.where(first, a, b)
    ok = m > -jnp.inf
    d = jnp.where(ok, jnp.where(first, b - a, a - b), 0.0)  # <= 0
    return jnp.where(ok, m + jnp.log1p(jnp.exp(d)), -jnp.inf)


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
    """Hashable description of a model's parameter layout (a static jit argument)."""

    link: str
    free_A: bool
    free_floor: bool
    depth: bool
    width_depth: bool
    size: bool
    n_smooth: int
    priors: tuple  # per theta entry: ("normal", mu, sigma) or ("beta", a, b)


#: Number of times the log-probability has been traced (compiled), for tests.
TRACE_COUNT = {"log_prob": 0}


def _unpack(st: _Structure, theta):
    """Named quantities from the unconstrained vector (JAX)."""
    i = 2
    p = {"m50_0": theta[0], "log_w": theta[1], "log_A": None, "log_1mA": None,
         "log_floor": None, "log_1mfloor": None}
    if st.free_A:
        a = theta[i]
        i += 1
        p["log_A"] = -_softplus(-a)
        p["log_1mA"] = -_softplus(a)
    if st.free_floor:
        b = theta[i]
        i += 1
        log_r, log_1mr = -_softplus(-b), -_softplus(b)
        if p["log_A"] is None:
            p["log_floor"], p["log_1mfloor"] = log_r, log_1mr
        else:
            # 1 - floor = (1 - A) + A (1 - r): a sum of positive terms, finite for any finite theta
            p["log_floor"] = p["log_A"] + log_r
            p["log_1mfloor"] = _logaddexp(p["log_1mA"], p["log_A"] + log_1mr)
    p["beta_depth"] = theta[i] if st.depth else None
    i += int(st.depth)
    p["w_depth"] = theta[i] if st.width_depth else None
    i += int(st.width_depth)
    p["beta_size"] = theta[i] if st.size else None
    i += int(st.size)
    p["coef"] = theta[i:i + st.n_smooth]
    return p


def _m50_and_logw(st: _Structure, p, depth, size, basis):
    m50 = p["m50_0"] + jnp.zeros_like(depth)
    if st.depth:
        m50 = m50 + p["beta_depth"] * depth
    if st.size:
        m50 = m50 + p["beta_size"] * size
    if st.n_smooth:
        m50 = m50 + basis @ p["coef"]
    log_w = p["log_w"] + (p["w_depth"] * depth if st.width_depth else 0.0)
    return m50, jnp.clip(log_w, -LOG_W_CLIP, LOG_W_CLIP)


def _cell_logs(st: _Structure, theta, m, depth, size, basis):
    p = _unpack(st, theta)
    m50, log_w = _m50_and_logw(st, p, depth, size, basis)
    z = (m50 - m) * jnp.exp(-log_w)
    logs = dict(log_A=p["log_A"], log_1mA=p["log_1mA"], log_floor=p["log_floor"], log_1mfloor=p["log_1mfloor"])
    if st.link == "logistic":
        return logistic_mixture_logs(z, **logs)
    log_g, log_1mg = link_logs(z, st.link)
    return mixture_logs(log_g, log_1mg, **logs)


def _log_prior(st: _Structure, theta):
    total = 0.0
    for j, (dist, a, b) in enumerate(st.priors):
        t = theta[j]
        if dist == "normal":
            total = total - 0.5 * ((t - a) / b) ** 2 - math.log(b) - 0.5 * math.log(2.0 * math.pi)
        else:  # Beta(a, b) on sigmoid(t), with the Jacobian s (1 - s) of the logit
            # log B(a, b) from scipy at trace time (a, b are static): jax's betaln is good to ~1e-8 only
            total = total - a * _softplus(-t) - b * _softplus(t) - float(_sp.betaln(a, b))
    return total


def _log_likelihood(st: _Structure, theta, data):
    m, depth, size, basis, n, k = data
    log_f, log_1mf = _cell_logs(st, theta, m, depth, size, basis)
    nk = n - k
    # 0 * (-inf) must count as 0: a cell with no failures does not care about log(1 - f).
    terms = jnp.where(k > 0, k * log_f, 0.0) + jnp.where(nk > 0, nk * log_1mf, 0.0)
    return jnp.sum(terms)


def _sanitize(x):
    return jnp.where(jnp.isnan(x) | (x == jnp.inf), -jnp.inf, x)


def _in_box(theta):
    return jnp.all(jnp.abs(theta) <= THETA_BOUND)  # False for NaN too


def _log_prob(st: _Structure, theta, data):
    TRACE_COUNT["log_prob"] += 1  # runs at trace time only
    ok = _in_box(theta)
    safe = jnp.where(ok, theta, 0.0)  # evaluate at a harmless point outside the box: no NaN gradients
    return jnp.where(ok, _sanitize(_log_prior(st, safe) + _log_likelihood(st, safe, data)), -jnp.inf)


def _value_and_grad(st, theta, data):
    v, g = jax.value_and_grad(_log_prob, argnums=1)(st, theta, data)
    g = jnp.where(jnp.isfinite(v), g, jnp.where(jnp.isfinite(g), g, 0.0))
    return v, g


_jit_log_prob = jax.jit(_log_prob, static_argnums=0)
_jit_log_prior = jax.jit(lambda st, theta: jnp.where(_in_box(theta), _sanitize(_log_prior(st, theta)), -jnp.inf),
                         static_argnums=0)
_jit_log_likelihood = jax.jit(
    lambda st, theta, data: jnp.where(_in_box(theta), _sanitize(_log_likelihood(st, theta, data)), -jnp.inf),
    static_argnums=0)
_jit_value_and_grad = jax.jit(_value_and_grad, static_argnums=0)
def _log_prob_batch(st, thetas, data, batch):
    # lax.map with batch_size = W is vmap; smaller batches keep W * G temporaries in cache for large G.
    return jax.lax.map(lambda t: _log_prob(st, t, data), thetas, batch_size=batch)


_jit_log_prob_batch = jax.jit(_log_prob_batch, static_argnums=(0, 3))

#: log_prob_batch vectorises over at most this many (walker, cell) pairs at once.
BATCH_ELEMENTS = 1 << 20
_jit_hessian = jax.jit(jax.hessian(_log_prob, argnums=1), static_argnums=0)


def _cell_logs_batch(st, thetas, m, depth, size, basis):
    lf, l1 = jax.vmap(lambda t: _cell_logs(st, t, m, depth, size, basis))(thetas)
    return jnp.stack([lf, l1], axis=-1)


_jit_cell_logs_batch = jax.jit(_cell_logs_batch, static_argnums=0)


def _prob_m50_batch(st, thetas, m, depth, size, basis):
    def one(t):
        p = _unpack(st, t)
        m50, _ = _m50_and_logw(st, p, depth, size, basis)
        log_f, _ = _cell_logs(st, t, m, depth, size, basis)
        return jnp.exp(log_f), m50
    return jax.vmap(one)(thetas)


_jit_prob_m50_batch = jax.jit(_prob_m50_batch, static_argnums=0)


def _prior_tuple(spec_prior: dict) -> tuple:
    if spec_prior["dist"] == "normal":
        return ("normal", float(spec_prior["mu"]), float(spec_prior["sigma"]))
    return ("beta", float(spec_prior["a"]), float(spec_prior["b"]))


def _np_link_logs(z: np.ndarray, link: str):
    z = np.clip(z, -Z_CLIP, Z_CLIP)
    if link == "logistic":
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

    Attributes
    ----------
    names : list of str
        Names of the entries of the unconstrained vector ``theta``.
    ndim : int
        Its length.

    Notes
    -----
    All methods taking ``theta`` accept a sequence or ndarray of length
    ``ndim`` (float64).  :meth:`log_prob`, :meth:`value_and_grad`,
    :meth:`log_prob_batch` and :meth:`hessian` run functions compiled once
    per model structure and data shape (the data are arguments, not baked-in
    constants, so calls with new ``theta`` never recompile).  They return
    ``-inf`` rather than NaN for parameters where the density is not
    defined or underflows (NaN entries, ``|theta_i| > THETA_BOUND``); a
    ``-inf`` value comes with a finite gradient (0 where undefined).

    ``kind = "purity"`` specs are fitted the same way: build the data from a
    table of detections with ``covariates_from_outcomes(...,
    mag_column="det_mag_auto", outcome_column=<real or false>)``.
    """

    def __init__(self, spec: ModelSpec | str, data: BinomialData):
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
        self.spec = spec
        self.data = data
        names = ["m50_0", "log_w"]
        priors = [_prior_tuple(spec.prior("m50_0")), _prior_tuple(spec.prior("log_w"))]
        free_A = spec.plateau == "free"
        free_floor = spec.floor == "free"
        if free_A:
            names.append("logit_A")
            priors.append(_prior_tuple(spec.prior("A")))
        if free_floor:
            names.append("logit_floor")
            priors.append(_prior_tuple(spec.prior("floor")))
        has_depth = spec.spatial in ("depth", "depth+smooth")
        for flag, key in ((has_depth, "beta_depth"), (spec.width_depth, "w_depth"),
                          (spec.size_covariate, "beta_size")):
            if flag:
                names.append(key)
                priors.append(_prior_tuple(spec.prior(key)))
        self.smooth_names = smooth_basis_names(spec.smooth_basis, spec.smooth_order) if spec.uses_smooth else []
        names.extend(self.smooth_names)
        priors.extend([_prior_tuple(spec.prior("smooth"))] * len(self.smooth_names))
        self.names = names
        self.ndim = len(names)
        self._st = _Structure(link=spec.link, free_A=free_A, free_floor=free_floor, depth=has_depth,
                              width_depth=spec.width_depth, size=spec.size_covariate,
                              n_smooth=len(self.smooth_names), priors=tuple(priors))
        cov = data.cov
        self._data = (jnp.asarray(cov.m), jnp.asarray(cov.depth), jnp.asarray(cov.size),
                      jnp.asarray(self._basis(cov)), jnp.asarray(data.n, dtype=jnp.float64),
                      jnp.asarray(data.k, dtype=jnp.float64))

    # -- helpers ------------------------------------------------------------
    def _basis(self, cov: Covariates) -> np.ndarray:
        if not self.spec.uses_smooth:
            return np.zeros((len(cov), 0))
        return smooth_basis(cov.u, cov.v, self.spec.smooth_basis, self.spec.smooth_order)

    def _theta(self, theta) -> jnp.ndarray:
        t = np.asarray(theta, dtype=np.float64)
        if t.shape != (self.ndim,):
            raise InputError(f"theta must have shape ({self.ndim},) for model {self.spec.name!r} "
                             f"(parameters {self.names}), got {t.shape}.")
        return jnp.asarray(t)

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
        return float(_jit_log_prior(self._st, self._theta(theta)))

    def log_likelihood(self, theta) -> float:
        """``sum k log f + (n - k) log(1 - f)`` over cells (binomial coefficients dropped)."""
        return float(_jit_log_likelihood(self._st, self._theta(theta), self._data))

    def log_prob(self, theta) -> float:
        """Log posterior density (up to the evidence); -inf, never NaN, where undefined."""
        return float(_jit_log_prob(self._st, self._theta(theta), self._data))

    def value_and_grad(self, theta) -> tuple[float, np.ndarray]:
        """:meth:`log_prob` and its gradient, shape (ndim,)."""
        v, g = _jit_value_and_grad(self._st, self._theta(theta), self._data)
        return float(v), np.array(g)

    def log_prob_batch(self, thetas) -> np.ndarray:
        """:meth:`log_prob` of each row of ``thetas`` (W, ndim) -> (W,), for emcee ``vectorize=True``.

        A jitted vectorised map over the rows (``vmap`` in batches of at most
        :data:`BATCH_ELEMENTS` / G rows, which is faster than one ``vmap``
        over all walkers when the number of cells G is large).
        """
        t = self._thetas(thetas)
        batch = int(max(1, min(t.shape[0], BATCH_ELEMENTS // max(1, self.data.ncells))))
        return np.asarray(_jit_log_prob_batch(self._st, jnp.asarray(t), self._data, batch))

    def hessian(self, theta) -> np.ndarray:
        """Hessian of :meth:`log_prob`, shape (ndim, ndim)."""
        return np.array(_jit_hessian(self._st, self._theta(theta), self._data))

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
        t = self._thetas(thetas)
        s, g = t.shape[0], self.data.ncells
        out = np.empty((s, g, 2))
        chunk = max(1, min(s, int(max_elements // max(1, 2 * g))))
        m, depth, size, basis = self._data[:4]
        for start in range(0, s, chunk):
            block = t[start:start + chunk]
            nb = block.shape[0]
            if nb < chunk:  # pad to one compiled shape
                block = np.concatenate([block, np.repeat(block[-1:], chunk - nb, axis=0)])
            res = _jit_cell_logs_batch(self._st, jnp.asarray(block), m, depth, size, basis)
            out[start:start + nb] = np.asarray(res)[:nb]
        return out

    # -- predictions --------------------------------------------------------
    def _predict(self, theta, cov: Covariates):
        if not isinstance(cov, Covariates):
            raise InputError(f"cov must be a Covariates (use Covariates.make), got {type(cov).__name__}.")
        t = np.asarray(theta, dtype=np.float64)
        single = t.ndim == 1
        t2 = self._thetas(t[None, :] if single else t)
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
            ``beta_size`` and the smooth coefficients (their own names);
            floats for one theta, arrays of shape (S,) for several.
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
        if t.ndim == 1:
            out = {k: float(v) for k, v in out.items()}
        return out

    def inverse_transform(self, params: Mapping[str, float]) -> np.ndarray:
        """theta from physical parameters (``m50_0``, ``w``, ``A``, ``floor``, slopes, coefficients).

        Missing slopes and coefficients are 0; ``A`` and ``floor`` default to
        0.97 and 0.01 (ignored when fixed).  Raises InputError for values
        outside their ranges (``0 < floor < A < 1``, ``w > 0``).
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
            else:
                theta[i] = float(params.get(name, 0.0))
        return theta

    def initial(self) -> np.ndarray:
        """A sensible starting theta from the data (no optimisation of the full model).

        A coarse grid search of the model *without* spatial terms (m50, w, A,
        floor) on the magnitude histogram of the cells, maximising likelihood
        times prior; slopes start at their prior means, smooth coefficients
        at 0.  Works for any data (all or no detections, separated outcomes,
        a handful of injections), where it lands on the prior-preferred edge.
        """
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
        p_m50 = st.priors[0]
        p_logw = st.priors[1]
        m50_grid = np.linspace(lo - 1.5, hi + 1.5, 91)
        w_grid = np.array([0.03, 0.06, 0.1, 0.15, 0.2, 0.3, 0.5, 0.8])
        a_grid = np.array([0.8, 0.9, 0.95, 0.98, 0.995]) if st.free_A else np.array([1.0])
        r_grid = np.array([0.001, 0.01, 0.03, 0.1]) if st.free_floor else np.array([0.0])
        z = (m50_grid[:, None, None] - mb[None, None, :]) / w_grid[None, :, None]  # (M, W, B)
        lg, l1g = _np_link_logs(z, st.link)
        g = np.exp(lg)
        best, best_val = None, -np.inf
        with np.errstate(divide="ignore", invalid="ignore"):
            for a in a_grid:
                for r in r_grid:
                    fl = a * r
                    f = np.clip(fl + (a - fl) * g, 1e-300, 1.0 - 1e-16)
                    ll = (k * np.log(f) + (n - k) * np.log1p(-f)).sum(axis=-1)
                    lp = (ll - 0.5 * ((m50_grid[:, None] - p_m50[1]) / p_m50[2]) ** 2
                          - 0.5 * ((np.log(w_grid)[None, :] - p_logw[1]) / p_logw[2]) ** 2)
                    if st.free_A:
                        pa = st.priors[2]
                        lp = lp + pa[1] * math.log(a) + pa[2] * math.log1p(-a)
                    if st.free_floor:
                        pr = st.priors[2 + int(st.free_A)]
                        lp = lp + pr[1] * math.log(r) + pr[2] * math.log1p(-r)
                    idx = np.unravel_index(np.nanargmax(np.where(np.isfinite(lp), lp, -np.inf)), lp.shape)
                    if lp[idx] > best_val:
                        best_val = lp[idx]
                        best = (m50_grid[idx[0]], w_grid[idx[1]], a, a * r)
        if best is None:  # pragma: no cover - every grid point non-finite cannot happen with clipped f
            best = (0.5 * (lo + hi), 0.2, 0.97, 0.01)
        m50, w, a, fl = best
        params = {"m50_0": m50, "w": w, "A": min(a, 0.995), "floor": fl}
        for j, name in enumerate(self.names):
            if name in ("beta_depth", "w_depth", "beta_size"):
                params[name] = st.priors[j][1]
        theta = self.inverse_transform(params)
        return theta
