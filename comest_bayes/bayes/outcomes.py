"""Injection outcomes as the model sees them: covariates, compressed binomial cells, warnings.

:func:`covariates_from_outcomes` turns an outcome table (magnitude, detected, position, local
noise, size) into :class:`Covariates`; :func:`compress` / :func:`compress_for` group them into
:class:`BinomialData` cells (a magnitude step grown where outcomes do not mix);
:func:`covariate_warnings` says when a covariate cannot be constrained.
"""

from __future__ import annotations

import math
import os
import warnings
from dataclasses import dataclass, field
from typing import Mapping
import numpy as np
from comest_bayes.errors import InputError
from comest_bayes.bayes.spec import ModelSpec, load_spec, resolve_candidates

__all__ = ['image_coordinate', 'depth_covariate', 'Covariates', 'BinomialData', 'covariates_from_outcomes', 'column_floats', 'outcome_flags', 'compress', 'compress_for', 'uncompressed', 'covariates_needed', 'covariate_warnings']

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

def image_coordinate(x, n: int) -> np.ndarray:
    """The normalised image coordinate of pixel positions ``x`` along an axis of ``n`` pixels:
    ``2 x / (n - 1) - 1``, -1 and +1 at the first and last pixel centres (the one definition the
    fit and every query of a posterior use)."""
    return 2.0 * np.asarray(x, np.float64) / max(int(n) - 1, 1) - 1.0


def depth_covariate(sigma, sigma_ref: float) -> np.ndarray:
    """The depth covariate ``d = -2.5 log10(sigma / sigma_ref)`` (mag; positive where the detection
    noise is below the reference); ``sigma`` must be finite and positive."""
    return -2.5 * np.log10(np.asarray(sigma, np.float64) / float(sigma_ref))


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


def column_floats(values, column: str = "", what: str = "table") -> np.ndarray:
    """A numeric table column as float64, its masked (missing) entries NaN (not their fill values)."""
    try:
        out = np.asarray(np.ma.getdata(values), dtype=np.float64)
    except (TypeError, ValueError):
        raw = np.asarray(values)
        raise InputError(f"{what}: column {column!r} must hold numbers, got dtype {raw.dtype} "
                         f"(e.g. {raw[:3].tolist()}).") from None
    if np.ma.is_masked(values):
        out = np.where(np.ma.getmaskarray(values), np.nan, out)
    return out


def outcome_flags(values, column: str = "detected") -> np.ndarray:
    """The outcome column as booleans: a boolean column, or numbers that are all 0 or 1 (else :class:`InputError`)."""
    if np.ma.is_masked(values):
        n_masked = int(np.count_nonzero(np.ma.getmaskarray(values)))
        raise InputError(f"column {column!r} has {n_masked} masked (missing) entr{'y' if n_masked == 1 else 'ies'} "
                         f"of {np.size(values)}: every injection was either detected or not; drop those rows or "
                         "fill them with 0 or 1.")
    raw = np.asarray(np.ma.getdata(values))
    if raw.dtype.kind == "b":
        return raw.astype(bool)
    if raw.dtype.kind in "US":  # a CSV written from booleans holds the words True / False
        words = np.char.lower(np.char.strip(raw.astype(str)))
        if np.all(np.isin(words, ("true", "false"))):
            return words == "true"
    try:
        vals = raw.astype(np.float64)
    except (TypeError, ValueError):
        raise InputError(f"column {column!r} must be boolean, 0/1 or the words True/False, got dtype {raw.dtype} "
                         f"(e.g. {raw[:3].tolist()}).") from None
    if not np.all(np.isin(vals, (0.0, 1.0))):
        raise InputError(f"column {column!r} must be boolean or 0/1; found other values "
                         f"(e.g. {vals[~np.isin(vals, (0.0, 1.0))][:3].tolist()}).")
    return vals.astype(bool)


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
    det = outcome_flags(outcomes[outcome_column], outcome_column)

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
        u = np.clip(image_coordinate(x, nx), -1.0, 1.0)
        v = np.clip(image_coordinate(y, ny), -1.0, 1.0)
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
            depth[good] = depth_covariate(noise[good], sigma_ref)
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
             along_depth: bool = False, dm_max: float | None = None) -> BinomialData:
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
    The number of cells is bounded by the number of occupied grid cells,
    whatever N, so the cost of a likelihood call stops growing with N once N
    exceeds the grid.  Every cell holds its detected and missed members at
    the same (mean) covariates: cells of members with identical covariates
    reproduce the unbinned likelihood exactly (up to rounding of the mean);
    otherwise the binning loses the outcomes' correlation with position
    inside a cell, an error second order in the steps (about
    ``g(1-g) dm^2 / (12 w^2)`` per member for the magnitude step).  Cells
    split by outcome (each outcome at its own members' mean) were tried and
    dropped: they hand the fit an outcome-dependent covariate, and a depth
    slope steep enough to separate the two means at a narrow width won the
    likelihood where the depth barely varies within a cell (``beta_depth``
    8-22 instead of 1 on white noise at 300k injections).
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
                     "along_depth": bool(along_depth), "dm_max": dm_max,
                     **steps})
    return BinomialData(cov=cells, n=n, k=np.round(k).astype(np.int64), index=index, meta=out_meta)


def covariates_needed(spec: ModelSpec) -> tuple[str, ...]:
    """Covariate groups a model uses: a subset of ``("m", "depth", "uv", "size")``."""
    spec = load_spec(spec)
    need = ["m"]
    if spec.uses_depth:
        need.append("depth")
    if spec.uses_position:
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
        extrapolation.  Empty when every used covariate varies.  Groups listed
        in ``data.meta["inert"]`` are skipped: the caller knows they change no
        output (``fit_kind`` marks the depth so when no injection has a noise
        value, as every footprint pixel then sits at depth 0 too).
    """
    spec = load_spec(spec)
    specs = resolve_candidates(spec) if spec.is_selection else [spec]
    need = set()
    for s in specs:
        need.update(covariates_needed(s))
    cov = data.cov
    out = []
    if "depth" in need and "depth" not in tuple(data.meta.get("inert", ())):
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


#: Magnitude step of the cells in the transition (mag), up to :data:`DM_REFERENCE_N` injections.
DM_TRANSITION = 0.015
#: Depth step of the cells (mag), up to :data:`DM_REFERENCE_N` injections.
DDEPTH = 0.1
#: Beyond this many injections both steps shrink as N^(-1/4) (a binning shift of a few hundredths of a sd).
DM_REFERENCE_N = 200_000


def compress_for(specs, cov: Covariates, detected, **kwargs) -> BinomialData:
    """:func:`compress` resolving only the covariates that the model(s) use.

    Parameters
    ----------
    specs : ModelSpec, str or sequence of them
        Model(s) that will be fitted to the result (a selection spec counts
        as all its candidates).
    cov, detected, kwargs
        As for :func:`compress` (grid steps, ``meta``).
    """
    if isinstance(specs, (ModelSpec, str, os.PathLike)):
        specs = [specs]
    need = set()
    for s in specs:
        s = load_spec(s)
        for child in (resolve_candidates(s) if s.is_selection else [s]):
            need.update(covariates_needed(child))
    # Steps 0.015 mag in m - depth (the grid is laid along the direction in which m50 moves with the
    # depth) and 0.1 mag in depth; the binning error is second order, ~ (dm^2 + (beta - 1)^2
    # ddepth^2) / (12 w^2) of the curvature per injection, and the number of cells -- the cost of
    # every likelihood call -- stays at a few thousand whatever N (the MAP shift against the
    # unbinned likelihood is measured in the tests).  On the plateau and the floor the magnitude step
    # grows to 0.1 mag (see compress's dm_max): the error per member stays at most the transition's.
    # the MAP shift from the binning grows as step^2 sqrt(N): past DM_REFERENCE_N injections both steps
    # shrink as N^(-1/4), holding it at its value there (at most ~0.06 posterior sd, tests/bayes/test_outcomes.py)
    shrink = min(1.0, (DM_REFERENCE_N / max(len(cov), 1)) ** 0.25)
    steps = {"ddepth": ("depth", DDEPTH * shrink), "nuv": ("uv", 16), "dsize": ("size", 0.01)}
    kwargs.setdefault("dm", DM_TRANSITION * shrink)
    kwargs.setdefault("dm_max", 0.1)
    kwargs.setdefault("along_depth", True)
    for key, (group, default) in steps.items():
        if group not in need:
            kwargs[key] = None
        else:
            kwargs.setdefault(key, default)
    return compress(cov, detected, **kwargs)
