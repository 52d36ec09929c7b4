"""Binned completeness, purity and detection rate, and their maps.

The raw, model-free ratios of the ComEst method (Chiu, Desai & Liu 2016), from the matched
injection and detection tables of one realization or of all realizations merged, with binomial
(Poisson for the detection rate) intervals.  Definitions, intervals and the binning convention:
``docs/ratios.md``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from astropy.stats import binom_conf_interval, poisson_conf_interval
from astropy.table import Table
from astropy.wcs import WCS, Sip
from scipy.special import ndtri

from comest_bayes.errors import InputError
from comest_bayes.io.jsonio import jsonable
from comest_bayes.seeding import Seed, Stream, rng_for

__all__ = [
    "BinnedRatio",
    "bright_end",
    "RatioMaps",
    "magnitude_edges",
    "binomial_interval",
    "binned_ratio",
    "completeness",
    "purity",
    "detection_rate",
    "first_crossing",
    "first_crossings",
    "magnitude_at",
    "magnitude_at_sd",
    "default_map_mag_edges",
    "transition_map_mag_edges",
    "map_bin_pixels",
    "ratio_maps",
    "completeness_map",
    "purity_map",
    "map_wcs",
]

INTERVALS = ("wilson", "jeffreys", "flat")


# --------------------------------------------------------------------------
# containers
# --------------------------------------------------------------------------

@dataclass(frozen=True)
class BinnedRatio:
    """A ratio k/n in magnitude bins, with its confidence interval.

    Attributes
    ----------
    edges : ndarray, shape (nbin + 1,)
        Bin edges, mag.
    centers : ndarray, shape (nbin,)
        Bin centres, mag.
    n : ndarray of int64, shape (nbin,)
        Denominator counts.
    k : ndarray of int64, shape (nbin,)
        Numerator counts.
    ratio : ndarray, shape (nbin,)
        ``k / n``; NaN where ``n == 0``.
    lower, upper : ndarray, shape (nbin,)
        Interval bounds; NaN where ``n == 0``.
    name : str
        ``"completeness"``, ``"purity"``, ``"detection_rate"`` or a custom name.
    quantity : str
        What was binned (``"mag_true"``, ``"mag_meas"``, or
        ``"mag_meas/mag_true"`` for the detection rate).
    confidence : float
        Probability content of the intervals.
    interval : str
        Interval method (``"wilson"``, ``"jeffreys"``, ``"flat"`` or
        ``"poisson"``).
    """

    edges: np.ndarray
    centers: np.ndarray
    n: np.ndarray
    k: np.ndarray
    ratio: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    name: str = ""
    quantity: str = ""
    confidence: float = 0.6827
    interval: str = "wilson"

    def to_dict(self) -> dict:
        """JSON-ready form: plain lists, NaN written as None."""
        return {
            "name": self.name,
            "quantity": self.quantity,
            "confidence": float(self.confidence),
            "interval": self.interval,
            "edges": _floats(self.edges),
            "centers": _floats(self.centers),
            "n": [int(v) for v in self.n],
            "k": [int(v) for v in self.k],
            "ratio": _floats(self.ratio),
            "lower": _floats(self.lower),
            "upper": _floats(self.upper),
        }

    def to_table(self) -> Table:
        """An :class:`astropy.table.Table` with one row per bin.

        Columns: ``mag_lo``, ``mag_hi``, ``mag_center`` (mag), ``n``, ``k``,
        ``ratio``, ``lower``, ``upper`` (dimensionless).  The name, binned
        quantity, confidence and interval method are in ``meta``.
        """
        table = Table(meta={"name": self.name, "quantity": self.quantity,
                            "confidence": float(self.confidence), "interval": self.interval})
        cols = [
            ("mag_lo", self.edges[:-1], "mag", "lower bin edge"),
            ("mag_hi", self.edges[1:], "mag", "upper bin edge"),
            ("mag_center", self.centers, "mag", "bin centre"),
            ("n", self.n, None, "denominator count"),
            ("k", self.k, None, "numerator count"),
            ("ratio", self.ratio, "", "k / n (NaN for empty bins)"),
            ("lower", self.lower, "", f"lower bound of the {self.confidence:.4g} {self.interval} interval"),
            ("upper", self.upper, "", f"upper bound of the {self.confidence:.4g} {self.interval} interval"),
        ]
        for name, values, unit, desc in cols:
            table[name] = np.asarray(values)
            table[name].unit = unit
            table[name].description = desc
        return table


@dataclass(frozen=True)
class RatioMaps:
    """Ratios in spatial bins, per magnitude bin.

    Attributes
    ----------
    n, k, ratio, lower, upper : ndarray, shape (nmag, ny_bins, nx_bins)
        As in :class:`BinnedRatio`, per spatial bin (axis 1 is y, axis 2 is x,
        numpy image order).
    mag_edges : ndarray, shape (nmag + 1,)
        Magnitude bin edges.
    bin_pix : float
        Side of a spatial bin, image pixels.
    image_shape : (int, int)
        ``(ny, nx)`` of the image.
    x_edges, y_edges : ndarray, shapes (nx_bins + 1,), (ny_bins + 1,)
        Spatial bin edges in 0-based image pixel coordinates
        (``i*bin_pix - 0.5``).
    name, confidence, interval : str, float, str
        As in :class:`BinnedRatio`.
    """

    n: np.ndarray
    k: np.ndarray
    ratio: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    mag_edges: np.ndarray
    bin_pix: float
    image_shape: tuple
    x_edges: np.ndarray
    y_edges: np.ndarray
    name: str = ""
    confidence: float = 0.6827
    interval: str = "wilson"

    @property
    def shape(self) -> tuple:
        """``(ny_bins, nx_bins)`` of one map."""
        return tuple(self.n.shape[1:])


def _floats(values) -> list:
    """JSON-ready list of floats (None where not finite)."""
    return jsonable(np.asarray(values, dtype=float))


# --------------------------------------------------------------------------
# validation and binning helpers
# --------------------------------------------------------------------------

def _check_edges(edges, name="edges") -> np.ndarray:
    e = np.asarray(edges, dtype=float)
    if e.ndim != 1 or e.size < 2 or not np.all(np.isfinite(e)) or np.any(np.diff(e) <= 0):
        raise InputError(f"{name} must be a 1-d array of at least two finite, strictly increasing values, "
                         f"got {np.asarray(edges)!r}; build them e.g. with magnitude_edges(bright, faint, 0.2).")
    return e


def _check_interval(confidence, interval) -> tuple[float, str]:
    try:
        c = float(confidence)
    except (TypeError, ValueError):
        c = float("nan")
    if not 0.0 < c < 1.0:
        raise InputError(f"confidence = {confidence!r} is not a probability in (0, 1); use e.g. 0.6827 (1 sigma).")
    if interval not in INTERVALS:
        raise InputError(f"interval = {interval!r} is not a supported binomial interval; use one of {INTERVALS}.")
    return c, interval


def _values(name, values, n=None) -> np.ndarray:
    arr = np.asarray(values, dtype=float)
    if arr.ndim != 1:
        raise InputError(f"{name} must be 1-d (one value per source), got shape {arr.shape}.")
    if n is not None and arr.size != n:
        raise InputError(f"{name} has {arr.size} values, expected {n} (one per source).")
    return arr


def _flags(name, values, n, default) -> np.ndarray:
    if values is None:
        return np.full(n, default, dtype=bool)
    arr = np.asarray(values)
    if arr.dtype != bool or arr.shape != (n,):
        raise InputError(f"{name} must be a boolean array of shape ({n},), got dtype {arr.dtype} and shape "
                         f"{arr.shape}; convert it with np.asarray(..., dtype=bool).")
    return arr


def _bin_index(values: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Bin index of each value (numpy.histogram convention), -1 outside or NaN."""
    idx = np.searchsorted(edges, values, side="right") - 1
    nbin = edges.size - 1
    idx[values == edges[-1]] = nbin - 1
    idx[(idx < 0) | (idx >= nbin) | ~np.isfinite(values)] = -1
    return idx


def _count(idx: np.ndarray, nbin: int) -> np.ndarray:
    return np.bincount(idx[idx >= 0], minlength=nbin).astype(np.int64)


def magnitude_edges(bright: float, faint: float, width: float) -> np.ndarray:
    """Equal-width magnitude bin edges starting at ``bright`` and covering ``faint``.

    Parameters
    ----------
    bright, faint : float
        Range to cover, mag (``bright < faint``).
    width : float
        Bin width, mag (``RatiosConfig.mag_bin``, default 0.2).

    Returns
    -------
    ndarray, shape (nbin + 1,)
        ``bright + width * arange(nbin + 1)`` with the last edge >= ``faint``.
    """
    if not (np.isfinite(bright) and np.isfinite(faint) and bright < faint):
        raise InputError(f"magnitude range ({bright!r}, {faint!r}) must be finite with bright < faint.")
    if not (np.isfinite(width) and width > 0):
        raise InputError(f"bin width {width!r} must be a positive number of magnitudes, e.g. 0.2.")
    nbin = max(1, int(math.ceil((faint - bright) / width - 1e-9)))
    return bright + width * np.arange(nbin + 1)


def binomial_interval(k, n, *, confidence: float = 0.6827, interval: str = "wilson"):
    """Binomial confidence interval of k successes in n trials, NaN where n == 0.

    Parameters
    ----------
    k, n : array_like of int, same shape
        Successes and trials (``0 <= k <= n``).
    confidence : float
        Probability content (default 0.6827, one sigma).
    interval : {"wilson", "jeffreys", "flat"}
        Method of :func:`astropy.stats.binom_conf_interval`.

    Returns
    -------
    lower, upper : ndarray, shape of ``k``
    """
    confidence, interval = _check_interval(confidence, interval)
    k = np.asarray(k, dtype=np.int64)
    n = np.asarray(n, dtype=np.int64)
    if k.shape != n.shape:
        raise InputError(f"k and n must have the same shape, got {k.shape} and {n.shape}.")
    if np.any(k < 0) or np.any(k > n):
        raise InputError("binomial counts need 0 <= k <= n in every bin; a numerator exceeds its denominator "
                         "(for the detection rate use detection_rate(), which uses a Poisson interval).")
    lower = np.full(k.shape, np.nan)
    upper = np.full(k.shape, np.nan)
    ok = n > 0
    if np.any(ok):
        lo_hi = binom_conf_interval(k[ok], n[ok], confidence_level=confidence, interval=interval)
        lower[ok] = lo_hi[0]
        upper[ok] = lo_hi[1]
    return lower, upper


def _ratio(k: np.ndarray, n: np.ndarray) -> np.ndarray:
    out = np.full(k.shape, np.nan)
    ok = n > 0
    out[ok] = k[ok] / n[ok]
    return out


# --------------------------------------------------------------------------
# one-dimensional ratios
# --------------------------------------------------------------------------

def binned_ratio(values, success, edges, *, include=None, confidence: float = 0.6827,
                 interval: str = "wilson", name: str = "", quantity: str = "") -> BinnedRatio:
    """Fraction of successes in bins of ``values``, with binomial intervals.

    Parameters
    ----------
    values : array_like, shape (N,)
        The binned quantity (a magnitude) of each trial.
    success : array_like of bool, shape (N,)
        Outcome of each trial.
    edges : array_like, shape (nbin + 1,)
        Bin edges.
    include : array_like of bool, shape (N,), optional
        Trials to count (default all).
    confidence, interval :
        See :func:`binomial_interval`.
    name, quantity : str
        Labels stored in the result.

    Returns
    -------
    BinnedRatio
    """
    edges = _check_edges(edges)
    confidence, interval = _check_interval(confidence, interval)
    v = _values("values", values)
    ok = _flags("success", success, v.size, False)
    inc = _flags("include", include, v.size, True)
    idx = _bin_index(v, edges)
    idx[~inc] = -1
    nbin = edges.size - 1
    n = _count(idx, nbin)
    k = _count(np.where(ok, idx, -1), nbin)
    lower, upper = binomial_interval(k, n, confidence=confidence, interval=interval)
    return BinnedRatio(edges=edges, centers=0.5 * (edges[:-1] + edges[1:]), n=n, k=k, ratio=_ratio(k, n),
                       lower=lower, upper=upper, name=name, quantity=quantity, confidence=confidence,
                       interval=interval)


def completeness(truth_mag, matched, edges, *, masked=None, confidence: float = 0.6827,
                 interval: str = "wilson") -> BinnedRatio:
    """Completeness f_com(m) in bins of true magnitude.

    Parameters
    ----------
    truth_mag : array_like, shape (ntruth,)
        Injected magnitudes.
    matched : array_like of bool, shape (ntruth,)
        The injection was recovered (``MatchResult.truth_matched``).
    edges : array_like, shape (nbin + 1,)
        Magnitude bin edges.
    masked : array_like of bool, shape (ntruth,), optional
        Injections to leave out (on masked pixels, or failed).
    confidence, interval :
        See :func:`binomial_interval`.

    Returns
    -------
    BinnedRatio
        ``n`` = non-masked injections, ``k`` = those matched, per bin.
    """
    tm = _values("truth_mag", truth_mag)
    inc = ~_flags("masked", masked, tm.size, False)
    return binned_ratio(tm, matched, edges, include=inc, confidence=confidence, interval=interval,
                        name="completeness", quantity="mag_true")


def purity(det_mag, matched, edges, *, excluded=None, confidence: float = 0.6827,
           interval: str = "wilson") -> BinnedRatio:
    """Purity f_pur(m) in bins of measured magnitude.

    Parameters
    ----------
    det_mag : array_like, shape (ndet,)
        Measured magnitudes; NaN ones are in no bin.
    matched : array_like of bool, shape (ndet,)
        The detection is a recovered injection (``MatchResult.det_matched``).
    edges : array_like, shape (nbin + 1,)
        Magnitude bin edges.
    excluded : array_like of bool, shape (ndet,), optional
        Detections left out of both counts: those coincident with kept real
        sources (``DetectionClasses.kept``).
    confidence, interval :
        See :func:`binomial_interval`.

    Returns
    -------
    BinnedRatio
        ``n`` = matched + false detections, ``k`` = matched ones, per bin.
    """
    dm = _values("det_mag", det_mag)
    inc = ~_flags("excluded", excluded, dm.size, False)
    return binned_ratio(dm, matched, edges, include=inc, confidence=confidence, interval=interval,
                        name="purity", quantity="mag_meas")


def detection_rate(det_mag, truth_mag, edges, *, det_excluded=None, truth_masked=None,
                   confidence: float = 0.6827) -> BinnedRatio:
    """Detection rate f_dr(m) = N_detected(m_meas) / N_injected(m_true).

    Parameters
    ----------
    det_mag : array_like, shape (ndet,)
        Measured magnitudes of the detections.
    truth_mag : array_like, shape (ntruth,)
        Injected magnitudes.
    edges : array_like, shape (nbin + 1,)
        Magnitude bin edges (used for both).
    det_excluded : array_like of bool, shape (ndet,), optional
        Detections left out (coincident with kept real sources).
    truth_masked : array_like of bool, shape (ntruth,), optional
        Injections left out (masked).
    confidence : float
        Probability content of the Poisson interval on the numerator
        (frequentist-confidence, :func:`astropy.stats.poisson_conf_interval`
        with ``sigma`` the normal quantile of ``confidence``), divided by
        ``n``.

    Returns
    -------
    BinnedRatio
        ``k`` = detections per measured-magnitude bin, ``n`` = injections
        per true-magnitude bin; ``interval = "poisson"``.  ``ratio`` may
        exceed 1.
    """
    edges = _check_edges(edges)
    confidence, _ = _check_interval(confidence, "wilson")
    dm = _values("det_mag", det_mag)
    tm = _values("truth_mag", truth_mag)
    d_idx = _bin_index(dm, edges)
    d_idx[_flags("det_excluded", det_excluded, dm.size, False)] = -1
    t_idx = _bin_index(tm, edges)
    t_idx[_flags("truth_masked", truth_masked, tm.size, False)] = -1
    nbin = edges.size - 1
    k = _count(d_idx, nbin)
    n = _count(t_idx, nbin)
    sigma = float(ndtri(0.5 + 0.5 * confidence))
    lower = np.full(nbin, np.nan)
    upper = np.full(nbin, np.nan)
    ok = n > 0
    if np.any(ok):
        lo_hi = poisson_conf_interval(k[ok], interval="frequentist-confidence", sigma=sigma)
        lower[ok] = lo_hi[0] / n[ok]
        upper[ok] = lo_hi[1] / n[ok]
    return BinnedRatio(edges=edges, centers=0.5 * (edges[:-1] + edges[1:]), n=n, k=k, ratio=_ratio(k, n),
                       lower=lower, upper=upper, name="detection_rate", quantity="mag_meas/mag_true",
                       confidence=confidence, interval="poisson")


def first_crossings(centers, curves, level: float) -> np.ndarray:
    """:func:`first_crossing` of every row of ``curves`` (S, M) on the increasing grid ``centers`` (M,).

    The package's one crossing rule, for binned curves and posterior draws alike: from the
    brightest point at or above ``level``, the first fainter point below it, and linear
    interpolation between that point and the one before it.  NaN where a row never reaches
    ``level`` or never falls below it afterwards.  Rows must be finite (see :func:`first_crossing`
    for a curve with empty bins).
    """
    c = np.asarray(centers, dtype=float)
    r = np.atleast_2d(np.asarray(curves, dtype=float))
    out = np.full(r.shape[0], np.nan)
    rows, i, j = _crossing_points(r, level)
    ri, rj = r[rows, i], r[rows, j]
    out[rows] = c[i] + (ri - level) / np.where(ri != rj, ri - rj, 1.0) * (c[j] - c[i])
    return out


def _crossing_points(r: np.ndarray, level: float):
    """The rows of ``r`` (S, M) that cross ``level`` and, per such row, the two points interpolated.

    From the brightest point at or above ``level``, ``j`` is the first fainter point below it and
    ``i = j - 1`` the one before it (``r[i] >= level``).  Returns ``(rows, i, j)``.
    """
    above = r >= level
    start = np.argmax(above, axis=1)
    after = ~above & (np.arange(r.shape[1])[None, :] > start[:, None])
    rows = np.flatnonzero(above.any(axis=1) & after.any(axis=1))
    j = np.argmax(after[rows], axis=1)
    return rows, j - 1, j


def first_crossing(centers, values, level: float) -> float:
    """Magnitude where a falling curve first drops below ``level``.

    Starting at the brightest point whose value is >= ``level``, finds the
    first fainter finite point whose value is < ``level`` and interpolates
    linearly between the two (:func:`first_crossings`, after dropping
    non-finite values such as empty bins).

    Parameters
    ----------
    centers : array_like, shape (nbin,)
        Bin centres, increasing (mag).
    values : array_like, shape (nbin,)
        The curve (completeness, purity...).
    level : float
        The level, e.g. 0.5.

    Returns
    -------
    float
        The magnitude, or NaN when the curve never reaches ``level`` or
        never falls below it afterwards.
    """
    r = np.asarray(values, dtype=float)
    c = np.asarray(centers, dtype=float)
    good = np.isfinite(r)
    if not good.any():
        return float("nan")
    return float(first_crossings(c[good], r[good][None, :], level)[0])


def bright_end(ratio: BinnedRatio, width: float = 0.5) -> dict:
    """The pooled ratio of the brightest ``width`` mag of populated bins.

    Returns ``{"mag_lo", "mag_hi", "n", "k", "ratio"}``: the bins whose lower edge lies within
    ``width`` of the first populated bin's lower edge, pooled (``ratio`` NaN when none is populated).
    A completeness well below 1 there says the injections start inside the transition: the bright
    plateau was never measured.
    """
    n = np.asarray(ratio.n)
    filled = np.flatnonzero(n > 0)
    if filled.size == 0:
        return {"mag_lo": float("nan"), "mag_hi": float("nan"), "n": 0, "k": 0, "ratio": float("nan")}
    lo = float(ratio.edges[filled[0]])
    sel = (np.asarray(ratio.edges[:-1]) < lo + width - 1e-6) & (n > 0)
    nn, kk = int(n[sel].sum()), int(np.asarray(ratio.k)[sel].sum())
    return {"mag_lo": lo, "mag_hi": float(ratio.edges[np.flatnonzero(sel)[-1] + 1]), "n": nn, "k": kk,
            "ratio": kk / nn}


def magnitude_at(ratio: BinnedRatio, level: float = 0.5) -> float:
    """Magnitude where ``ratio.ratio`` first drops below ``level`` (see :func:`first_crossing`).

    ``magnitude_at(completeness(...), 0.5)`` is the 50% completeness
    magnitude m50; NaN when the curve does not cross ``level``.
    """
    return first_crossing(ratio.centers, ratio.ratio, level)


#: Draws of the bins' ratios behind :func:`magnitude_at_sd` (its Monte Carlo error is about 2% of the
#: spread at 2,000 draws).
CROSSING_DRAWS = 2000


def magnitude_at_sd(ratio: BinnedRatio, level: float = 0.5, *, seed: Seed = 0) -> float:
    """The uncertainty of :func:`magnitude_at`: the spread of the first crossing under the bins' noise.

    Every non-empty bin's ratio is drawn :data:`CROSSING_DRAWS` times from its Jeffreys posterior,
    ``Beta(k + 1/2, n - k + 1/2)``, and :func:`first_crossings` is taken of each drawn curve; the
    result is half the width of the central 68% of those crossings (an sd for a normal spread).
    NaN where :func:`magnitude_at` is, or where fewer than half the drawn curves cross.  The draws
    come from stream ``Stream.CROSSING`` of ``seed`` (a run passes its root seed).

    Why not the delta method on the two bins interpolated (the rule until 2026-11-29): it treats
    the crossing as falling between the same two bins whatever the noise, which holds only when
    the bins near the crossing hold many injections.  With few, the first crossing of a noisy
    curve is itself random (a 1-of-3 bin on the bright side of a 7-of-8 one makes it), and the
    delta sd was far too small: on a logistic truth (m50 24, w 0.15 mag, injections uniform over
    21-26 mag in 0.1-mag bins, 300 tables per N) ``|m50 - truth| <= sd`` held in 0.27, 0.31,
    0.44, 0.58 of the tables at 50, 150, 500 and 1,500 injections, against 0.80, 0.91, 0.83 and
    0.67 with this spread; from 5,000 injections the two agree (20.4 and 22.8 mmag at 5,000,
    11.7 and 11.9 at 20,000; coverage 0.67-0.73) (``benchmarks/bench_binned_m50_interval.py``).
    The drawn crossings are not centred on the observed one (noise makes a first crossing
    brighter, and the draws add noise to the data's), so their spread, not their percentiles,
    is the interval's width around :func:`magnitude_at`.

    Like the delta method it describes the noise only, not the interpolation's bias, which grows
    with the bin width against the transition's curvature (``benchmarks/README.md``, speed
    against accuracy).
    """
    if not np.isfinite(magnitude_at(ratio, level)):
        return float("nan")
    n = np.asarray(ratio.n, float)
    k = np.asarray(ratio.k, float)
    ok = n > 0
    c, n, k = np.asarray(ratio.centers, float)[ok], n[ok], k[ok]
    rng = rng_for(seed, Stream.CROSSING)
    drawn = rng.beta(k + 0.5, n - k + 0.5, size=(CROSSING_DRAWS, len(n)))
    m = first_crossings(c, drawn, level)
    m = m[np.isfinite(m)]
    if m.size < CROSSING_DRAWS / 2:
        return float("nan")
    lo, hi = np.percentile(m, [15.865, 84.135])
    return float(0.5 * (hi - lo))


def default_map_mag_edges(m50: float, width: float = 1.0) -> np.ndarray:
    """Three magnitude bins of ``width`` centred on ``m50``, ``m50 -/+ width``.

    The automatic ``RatiosConfig.map_mag_edges``: one bin around the 50%
    completeness magnitude and one on each side.

    Returns
    -------
    ndarray, shape (4,)
        ``m50 + width * [-1.5, -0.5, 0.5, 1.5]``.
    """
    if not np.isfinite(m50):
        raise InputError(f"the 50% completeness magnitude is {m50!r}; the completeness curve never crosses 0.5 "
                         f"in the injected range, so set ratios.map_mag_edges explicitly.")
    if not (np.isfinite(width) and width > 0):
        raise InputError(f"width = {width!r} must be a positive number of magnitudes.")
    return m50 + width * np.array([-1.5, -0.5, 0.5, 1.5])


def transition_map_mag_edges(comp: BinnedRatio, width: float = 1.0) -> np.ndarray:
    """Three magnitude bins centred where the binned completeness crosses 0.9, 0.5 and 0.1.

    The automatic map slices: one bin where most sources are found, one at the
    transition, one where most are lost, so that every panel of the maps shows
    where the completeness changes (fixed 1-mag slices around m50 put two
    panels on the plateau and the floor when the transition is narrow).  The
    bins meet half-way between the crossings; the outer ones are as wide as
    their inner halves.  Falls back to :func:`default_map_mag_edges` (around
    m50, ``width``) when the curve does not cross all three levels in order.

    Returns
    -------
    ndarray, shape (4,)
    """
    m90, m50, m10 = (magnitude_at(comp, level) for level in (0.9, 0.5, 0.1))
    if np.all(np.isfinite([m90, m50, m10])) and m90 < m50 < m10:
        lo, hi = 0.5 * (m90 + m50), 0.5 * (m50 + m10)
        return np.array([m90 - (lo - m90), lo, hi, m10 + (m10 - hi)])
    return default_map_mag_edges(m50, width)


# --------------------------------------------------------------------------
# maps
# --------------------------------------------------------------------------

def map_bin_pixels(map_bin_arcmin: float, pixel_scale: float, *, integer: bool = True) -> float:
    """Side of a map bin in image pixels.

    Parameters
    ----------
    map_bin_arcmin : float
        Bin size, arcmin (``RatiosConfig.map_bin_arcmin``).
    pixel_scale : float
        Image pixel scale, arcsec per pixel.
    integer : bool
        Round to the nearest whole number of pixels (at least 1), so bins hold
        whole pixels (default True).

    Returns
    -------
    float
        ``60 * map_bin_arcmin / pixel_scale``, rounded if ``integer``.
    """
    if not (np.isfinite(map_bin_arcmin) and map_bin_arcmin > 0):
        raise InputError(f"map_bin_arcmin = {map_bin_arcmin!r} must be a positive size in arcmin.")
    if not (np.isfinite(pixel_scale) and pixel_scale > 0):
        raise InputError(f"pixel_scale = {pixel_scale!r} must be a positive number of arcsec per pixel; "
                         f"give the image a WCS or set the pixel scale.")
    b = 60.0 * float(map_bin_arcmin) / float(pixel_scale)
    return float(max(1, round(b))) if integer else b


def _grid(image_shape, bin_pix) -> tuple[int, int, float]:
    try:
        ny, nx = (int(v) for v in image_shape)
    except (TypeError, ValueError):
        raise InputError(f"image_shape must be (ny, nx), got {image_shape!r}.") from None
    if ny < 1 or nx < 1:
        raise InputError(f"image_shape must be positive (ny, nx), got {image_shape!r}.")
    b = float(bin_pix)
    if not (np.isfinite(b) and b > 0):
        raise InputError(f"bin_pix = {bin_pix!r} must be a positive number of pixels (see map_bin_pixels).")
    return ny, nx, b


def _nbins(npix: int, b: float) -> int:
    # tolerance so that e.g. 1000 / 100.0000001 gives 10 bins, not 11
    return max(1, int(math.ceil(npix / b - 1e-9)))


def ratio_maps(x, y, mag, success, *, image_shape, bin_pix: float, mag_edges, include=None,
               confidence: float = 0.6827, interval: str = "wilson", name: str = "") -> RatioMaps:
    """Binomial ratio in spatial bins and magnitude bins.

    Parameters
    ----------
    x, y : array_like, shape (N,)
        Positions, 0-based image pixels; those outside the image
        (``-0.5 <= x < nx - 0.5``) or not finite are in no bin.
    mag : array_like, shape (N,)
        Magnitude of each trial (true for completeness, measured for purity).
    success : array_like of bool, shape (N,)
        Outcome of each trial.
    image_shape : (int, int)
        ``(ny, nx)`` of the image.
    bin_pix : float
        Side of a spatial bin in image pixels (:func:`map_bin_pixels`).  The
        last row and column of bins may extend beyond the image.
    mag_edges : array_like, shape (nmag + 1,)
        Magnitude bin edges (``RatiosConfig.map_mag_edges`` or
        :func:`default_map_mag_edges`).
    include : array_like of bool, shape (N,), optional
        Trials to count.
    confidence, interval :
        See :func:`binomial_interval`.

    Returns
    -------
    RatioMaps
        Arrays of shape ``(nmag, ny_bins, nx_bins)`` with
        ``ny_bins = ceil(ny / bin_pix)``, ``nx_bins = ceil(nx / bin_pix)``.
    """
    ny, nx, b = _grid(image_shape, bin_pix)
    mag_edges = _check_edges(mag_edges, "mag_edges")
    confidence, interval = _check_interval(confidence, interval)
    xv = _values("x", x)
    yv = _values("y", y, xv.size)
    mv = _values("mag", mag, xv.size)
    ok = _flags("success", success, xv.size, False)
    inc = _flags("include", include, xv.size, True)

    nmag = mag_edges.size - 1
    nyb, nxb = _nbins(ny, b), _nbins(nx, b)
    im = _bin_index(mv, mag_edges)
    with np.errstate(invalid="ignore"):
        inside = (xv >= -0.5) & (xv < nx - 0.5) & (yv >= -0.5) & (yv < ny - 0.5)
    valid = inc & inside & (im >= 0)
    ix = np.zeros(xv.size, dtype=np.int64)
    iy = np.zeros(xv.size, dtype=np.int64)
    ix[valid] = np.minimum(np.floor((xv[valid] + 0.5) / b).astype(np.int64), nxb - 1)
    iy[valid] = np.minimum(np.floor((yv[valid] + 0.5) / b).astype(np.int64), nyb - 1)
    flat = np.where(valid, (im * nyb + iy) * nxb + ix, -1)
    size = nmag * nyb * nxb
    n = _count(flat, size).reshape(nmag, nyb, nxb)
    k = _count(np.where(ok, flat, -1), size).reshape(nmag, nyb, nxb)
    lower, upper = binomial_interval(k, n, confidence=confidence, interval=interval)
    return RatioMaps(n=n, k=k, ratio=_ratio(k, n), lower=lower, upper=upper, mag_edges=mag_edges, bin_pix=b,
                     image_shape=(ny, nx), x_edges=np.arange(nxb + 1) * b - 0.5,
                     y_edges=np.arange(nyb + 1) * b - 0.5, name=name, confidence=confidence, interval=interval)


def completeness_map(truth_x, truth_y, truth_mag, matched, *, image_shape, bin_pix: float, mag_edges,
                     masked=None, confidence: float = 0.6827, interval: str = "wilson") -> RatioMaps:
    """f_com(x, y, m): :func:`ratio_maps` of the non-masked injections at their true positions."""
    tm = _values("truth_mag", truth_mag)
    inc = ~_flags("masked", masked, tm.size, False)
    return ratio_maps(truth_x, truth_y, tm, matched, image_shape=image_shape, bin_pix=bin_pix,
                      mag_edges=mag_edges, include=inc, confidence=confidence, interval=interval,
                      name="completeness")


def purity_map(det_x, det_y, det_mag, matched, *, image_shape, bin_pix: float, mag_edges, excluded=None,
               confidence: float = 0.6827, interval: str = "wilson") -> RatioMaps:
    """f_pur(x, y, m): :func:`ratio_maps` of the counted detections at their measured positions."""
    dm = _values("det_mag", det_mag)
    inc = ~_flags("excluded", excluded, dm.size, False)
    return ratio_maps(det_x, det_y, dm, matched, image_shape=image_shape, bin_pix=bin_pix,
                      mag_edges=mag_edges, include=inc, confidence=confidence, interval=interval, name="purity")


def map_wcs(image_wcs: WCS, bin_pix: float, shape=None) -> WCS:
    """WCS of the binned map grid.

    Map pixel ``(i, j)`` (0-based, x then y) is the bin whose centre is the
    image pixel position ``((i + 0.5) b - 0.5, (j + 0.5) b - 0.5)``.  In FITS
    (1-based) terms the image pixel is ``P = b P' + (1 - b) / 2`` of the map
    pixel ``P'``, so the map keeps CRVAL and the projection, with

    * ``CRPIX' = (CRPIX - 0.5) / b + 0.5``;
    * the linear matrix scaled by ``b`` (CD, or CDELT with PC), which keeps
      any rotation or skew;
    * SIP coefficients ``A_pq`` (and ``B``, ``AP``, ``BP``) scaled by
      ``b**(p + q - 1)``, since the SIP offsets ``u = P - CRPIX`` become
      ``b u'``.

    This transformation is exact.  Lookup-table distortions (``CPDIS``,
    ``D2IM``) cannot be rebinned this way and are rejected.

    Parameters
    ----------
    image_wcs : astropy.wcs.WCS
        Two-dimensional celestial WCS of the image.
    bin_pix : float
        Bin side in image pixels (need not be an integer).
    shape : (int, int), optional
        ``(ny_bins, nx_bins)`` of the map; sets ``pixel_shape``.

    Returns
    -------
    astropy.wcs.WCS
        A new WCS (the input is not modified); ``to_header(relax=True)``
        keeps SIP terms.
    """
    if not isinstance(image_wcs, WCS):
        raise InputError(f"image_wcs must be an astropy.wcs.WCS, got {type(image_wcs).__name__}.")
    if image_wcs.naxis != 2:
        raise InputError(f"image_wcs must have 2 axes, got {image_wcs.naxis}; pass image_wcs.celestial.")
    b = float(bin_pix)
    if not (np.isfinite(b) and b > 0):
        raise InputError(f"bin_pix = {bin_pix!r} must be a positive number of pixels.")
    if any(getattr(image_wcs, attr, None) is not None for attr in ("cpdis1", "cpdis2", "det2im1", "det2im2")):
        raise InputError("image_wcs has lookup-table distortions (CPDIS/D2IM), which cannot be rebinned exactly; "
                         "fit a SIP or TAN WCS to the image first (astropy.wcs.utils.fit_wcs_from_points).")

    out = image_wcs.deepcopy()
    crpix = (np.asarray(image_wcs.wcs.crpix, dtype=float) - 0.5) / b + 0.5
    out.wcs.crpix = crpix
    if image_wcs.wcs.has_cd():
        out.wcs.cd = np.asarray(image_wcs.wcs.cd, dtype=float) * b
    else:
        out.wcs.cdelt = np.asarray(image_wcs.wcs.cdelt, dtype=float) * b
    sip = image_wcs.sip
    if sip is not None:
        def scaled(coeffs):
            if coeffs is None:
                return None
            c = np.asarray(coeffs, dtype=float)
            p, q = np.indices(c.shape)
            return c * b ** (p + q - 1.0)

        out.sip = Sip(scaled(sip.a), scaled(sip.b), scaled(sip.ap), scaled(sip.bp), crpix)
    if shape is not None:
        ny_bins, nx_bins = (int(v) for v in shape)
        out.pixel_shape = (nx_bins, ny_bins)
    out.wcs.set()
    return out
