"""Does the fitted model describe the outcomes?  Posterior predictive checks.

:func:`shape_check` compares, per magnitude bin, the observed detections with those the
posterior predicts for the same injections and sums the differences into a chi-square.
:func:`covariate_check` does the same per tile of the image and per depth bin, each split by
the predicted completeness: it sees what the magnitude bins average away (an m50 that moves
with position where the noise map does not say so, or with depth other than linearly).  Below
:data:`P_WARN` the fit warns.  Formulas and measurements: ``docs/bayesian.md`` ("Shape check",
"Covariate check").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse, special
from comest_bayes.bayes.model import padded_size

__all__ = ["thin_draws", "cell_probabilities", "shape_check", "ShapeCheck", "ShapeBin", "P_WARN", "shape_warning",
           "covariate_check", "CovariateCheck", "GroupTest", "covariate_warning"]

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


def thin_draws(draws, most: int = MAX_DRAWS) -> np.ndarray:
    """At most ``most`` rows of ``draws`` (posterior draws, or their predictions), spread evenly: shape (S, ...)."""
    theta = np.atleast_2d(np.asarray(draws, float))
    if theta.shape[0] > most:
        theta = theta[np.linspace(0, theta.shape[0] - 1, most).astype(int)]
    return theta


def cell_probabilities(model, theta) -> np.ndarray:
    """The completeness of every cell of ``model.data`` for each draw of ``theta`` (S, D): shape (S, G)."""
    cov, g = model.data.cov, model.data.ncells
    if hasattr(cov, "take"):
        # cells padded (repeating the last) to the likelihood's padded count: the kinds of a run, whose cell
        # counts differ a little, share one compiled prediction instead of tracing one each
        cov = cov.take(np.minimum(np.arange(padded_size(g)), g - 1))
    return np.atleast_2d(model.prob(np.atleast_2d(theta), cov))[:, :g]


def _group_z(counts, pt, observed):
    """Predicted detections per group and the z of the observed ones, under the posterior predictive.

    ``counts`` (sparse, groups x cells) holds the injections of each cell in each group, ``pt``
    (cells x draws) the cells' predicted completeness per draw.  Per group: the expected detections
    ``mean_s E_s``, ``E_s = sum_c counts f_cs``, and the predictive variance, binomial plus posterior,
    ``mean_s sum_c counts f (1 - f) + var_s E_s``.  ``z`` is NaN where that variance is below
    :data:`MIN_VARIANCE` (a group whose prediction is certain to well below one detection).
    """
    e_s = np.asarray(counts @ pt)                                                   # (groups, S)
    var = np.asarray(counts @ (pt * (1.0 - pt))).mean(axis=1) + (e_s.var(axis=1) if pt.shape[1] > 1 else 0.0)
    expected = e_s.mean(axis=1)
    used = var >= MIN_VARIANCE
    z = np.full(expected.shape, np.nan)
    z[used] = (observed[used] - expected[used]) / np.sqrt(var[used])
    return expected, z


def shape_check(model, draws, mag_edges, *, p=None) -> ShapeCheck:
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
    p : array, shape (S, G), optional
        :func:`cell_probabilities` of ``draws`` (thinned to at most :data:`MAX_DRAWS`), when the
        caller has them already.

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
    data = model.data
    m = np.asarray(data.cov.m, float)
    nb = edges.size - 1
    b = np.searchsorted(edges, m, side="right") - 1
    inside = np.flatnonzero((b >= 0) & (b < nb))
    p = cell_probabilities(model, thin_draws(draws)) if p is None else np.atleast_2d(p)
    counts = sparse.csr_matrix((np.asarray(data.n, float)[inside], (b[inside], inside)), shape=(nb, p.shape[1]))
    observed = np.bincount(b[inside], weights=np.asarray(data.k, float)[inside], minlength=nb)
    count = np.bincount(b[inside], weights=np.asarray(data.n, float)[inside], minlength=nb)
    expected, z = _group_z(counts, np.ascontiguousarray(p.T), observed)
    used = np.isfinite(z)
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


# --------------------------------------------------------------------------- the covariate check

#: Tiles per image axis of the positional part of :func:`covariate_check`.
CHECK_TILES = 4
#: Depth bins (equal numbers of injections) of its depth part.
CHECK_DEPTH_BINS = 8
#: Posterior draws used by :func:`covariate_check` (spread evenly): the posterior term of its variance
#: needs fewer than the magnitude bins' check, and its sums run over every injection.
COVARIATE_DRAWS = 64
#: Bands of predicted completeness each tile or depth bin is split into: a transition that sits too
#: bright in a region has too few detections on its bright side and too many on its faint side, which
#: one sum over the region would cancel.
CHECK_BANDS = (0.25, 0.5, 0.75)


@dataclass(frozen=True)
class GroupTest:
    """One part (position or depth) of a :class:`CovariateCheck`.

    Attributes
    ----------
    chi2, dof, p_value : float, int, float
        The chi-square over the groups used, their number, and its tail probability.
    worst : dict
        The group of largest ``|z|``: ``observed``, ``expected``, ``z``, ``n``, ``band`` (its range of
        predicted completeness) and where it is: ``x``, ``y`` (pixel centre of the tile) or ``depth``
        (the bin's range, mag).
    """

    chi2: float
    dof: int
    p_value: float
    worst: dict

    def to_dict(self) -> dict:
        """The JSON form: ``chi2``, ``dof``, ``p_value``, ``worst``."""
        return {"chi2": self.chi2, "dof": self.dof, "p_value": self.p_value, "worst": dict(self.worst)}


@dataclass(frozen=True)
class CovariateCheck:
    """The posterior predictive check of a fit's detections per tile of the image and per depth bin.

    Attributes
    ----------
    position, depth : GroupTest or None
        Each part, None where it does not apply (no positions; a depth that does not vary) or no group
        qualifies.
    p_value : float or None
        The smaller part's p-value times the number of parts (Bonferroni), at most 1.
    """

    position: GroupTest | None
    depth: GroupTest | None
    p_value: float | None

    def to_dict(self) -> dict:
        """The JSON form (``summary.json``: ``kinds.<kind>.model.covariate_check``)."""
        return {"p_value": self.p_value, "position": None if self.position is None else self.position.to_dict(),
                "depth": None if self.depth is None else self.depth.to_dict()}


def _group_test(group, ngroups, cell, detected, pt, where) -> GroupTest | None:
    """The chi-square of observed against predicted detections over ``ngroups`` groups of injections.

    ``group`` and ``cell`` give each injection's group and cell, ``pt`` (G, S) the cells' predicted
    completeness per draw (:func:`_group_z`); ``where(g)`` describes group ``g`` (a dict).
    """
    counts = sparse.csr_matrix((np.ones(cell.size), (group, cell)), shape=(ngroups, pt.shape[0]))
    observed = np.bincount(group, weights=detected.astype(float), minlength=ngroups)
    count = np.bincount(group, minlength=ngroups).astype(float)
    expected, z = _group_z(counts, pt, observed)
    used = np.isfinite(z)
    if not used.any():
        return None
    chi2 = float(np.sum(z[used] ** 2))
    dof = int(used.sum())
    w = int(np.nanargmax(np.abs(z)))
    worst = {"observed": int(round(observed[w])), "expected": float(expected[w]), "z": float(z[w]),
             "n": int(round(count[w])), **where(w)}
    return GroupTest(chi2=chi2, dof=dof, p_value=float(special.chdtrc(dof, chi2)), worst=worst)


def covariate_check(model, draws, *, u=None, v=None, depth=None, detected, image_shape=None,
                    tiles: int = CHECK_TILES, depth_bins: int = CHECK_DEPTH_BINS, p=None) -> CovariateCheck:
    """Posterior predictive check of the detections per tile of the image and per depth bin.

    The magnitude bins of :func:`shape_check` average over the image: an m50 that is brighter in one
    region (scattered light, a crowded patch) than the noise map says, or that follows the depth other
    than linearly, can leave every magnitude bin within its noise while the fit's intervals miss.  Here
    the injections are grouped by their tile of a ``tiles`` x ``tiles`` grid over the image, and
    separately by ``depth_bins`` bins of equal numbers of injections in depth; each group is split by
    the posterior-mean completeness of the injections into the bands of :data:`CHECK_BANDS`.  Per
    group, as in :func:`shape_check`, the observed detections are compared with the posterior's
    prediction for the same injections, with the binomial and posterior variance, into a chi-square.
    The two parts are combined by Bonferroni (twice the smaller p).  The parameters were fitted to the
    same outcomes, so the p-values are conservative.

    Parameters
    ----------
    model : CompletenessModel
        The fitted model; ``model.data.index`` maps every injection to its cell.
    draws : array, shape (S, D) or (D,)
        Posterior draws.
    u, v : array, shape (N,), optional
        The injections' normalised image coordinates (in the order of ``model.data.index``); the
        positional part is skipped without them.
    depth : array, shape (N,), optional
        Their depth covariate; the depth part is skipped without it or where it spans under 0.01 mag.
    detected : array of bool, shape (N,)
    image_shape : (ny, nx), optional
        For the tiles' pixel centres in the result.
    p : array, shape (S, G), optional
        :func:`cell_probabilities` of the draws, when the caller has them already (e.g. from the shape
        check); at most :data:`COVARIATE_DRAWS` of them, spread evenly, are used.

    Returns
    -------
    CovariateCheck
    """
    index = getattr(model.data, "index", None)
    detected = np.asarray(detected, bool)
    if index is None or index.shape != detected.shape:
        raise ValueError("covariate_check needs the model's cell of every injection (model.data.index) and one "
                         "outcome per injection")
    p = cell_probabilities(model, thin_draws(draws, COVARIATE_DRAWS)) if p is None else thin_draws(p, COVARIATE_DRAWS)
    band = np.searchsorted(np.asarray(CHECK_BANDS), p.mean(axis=0)[index], side="right")
    # per cell and draw, contiguous along the draws: every group's sums are then one sparse product
    pt = np.ascontiguousarray(p.T)
    nbands = len(CHECK_BANDS) + 1
    edges_band = (0.0,) + tuple(CHECK_BANDS) + (1.0,)

    def band_of(g):
        j = g % nbands
        return {"band": [edges_band[j], edges_band[j + 1]]}

    position = None
    if u is not None and v is not None:
        u, v = np.asarray(u, float), np.asarray(v, float)
        tu = np.clip(((u + 1.0) * 0.5 * tiles).astype(int), 0, tiles - 1)
        tv = np.clip(((v + 1.0) * 0.5 * tiles).astype(int), 0, tiles - 1)
        ny, nx = (image_shape if image_shape is not None else (2, 2))

        def where_tile(g):
            t = g // nbands
            iu, iv = t % tiles, t // tiles
            # the tile's centre, from normalised coordinates back to 0-based pixels
            cu, cv = -1.0 + (2 * iu + 1) / tiles, -1.0 + (2 * iv + 1) / tiles
            return {"x": float((cu + 1.0) * 0.5 * (nx - 1)), "y": float((cv + 1.0) * 0.5 * (ny - 1)), **band_of(g)}

        position = _group_test((tv * tiles + tu) * nbands + band, tiles * tiles * nbands, index, detected, pt,
                               where_tile)
    depth_test = None
    if depth is not None and np.ptp(np.asarray(depth, float)) >= 0.01:
        d = np.asarray(depth, float)
        qs = np.unique(np.quantile(d, np.linspace(0.0, 1.0, depth_bins + 1)))
        bins = np.clip(np.searchsorted(qs, d, side="right") - 1, 0, qs.size - 2)

        def where_depth(g):
            j = g // nbands
            return {"depth": [float(qs[j]), float(qs[j + 1])], **band_of(g)}

        depth_test = _group_test(bins * nbands + band, (qs.size - 1) * nbands, index, detected, pt, where_depth)
    parts = [t.p_value for t in (position, depth_test) if t is not None]
    return CovariateCheck(position=position, depth=depth_test,
                          p_value=min(1.0, len(parts) * min(parts)) if parts else None)


def covariate_warning(check: CovariateCheck, *, name: str, kind: str, quantity: str) -> str | None:
    """The warning text for a failed :func:`covariate_check`, or None when it passes."""
    if check.p_value is None or check.p_value >= P_WARN:
        return None
    parts = [t for t in (check.position, check.depth) if t is not None]
    worst = min(parts, key=lambda t: t.p_value)
    w = worst.worst
    what = f"the {quantity} curve" if name == quantity else f"the {name} {quantity} curve"
    band = f"predicted {quantity} {w['band'][0]:.2f}-{w['band'][1]:.2f}"
    combined = f"combined p = {check.p_value:.1e}" if len(parts) > 1 else f"p = {check.p_value:.1e}"
    counts = (f"{w['observed']} detections of {w['n']} against {w['expected']:.1f} predicted ({w['z']:+.1f} sigma; "
              f"chi2 = {worst.chi2:.1f} for {worst.dof} groups")
    if worst is check.position:
        place = (f"across the image: the tile centred near pixel ({w['x']:.0f}, {w['y']:.0f}), {band}, has {counts} "
                 f"of {CHECK_TILES}x{CHECK_TILES} tiles by {quantity} band, {combined})")
        cause = "varies with position in a way the noise map does not explain (scattered light, crowding, a PSF change)"
        remedy = ("give the run the weight or noise map that does, try --model auto_smooth, or use the binned ratios "
                  "of that region" if quantity == "completeness" else f"use the binned {quantity} ratios of that region")
    else:
        place = (f"with the local depth: at depth {w['depth'][0]:+.2f} to {w['depth'][1]:+.2f} mag, {band}, "
                 f"{counts} of depth bin by {quantity} band, {combined})")
        cause = "does not follow the depth as the model assumes"
        remedy = ("check the noise map, or use the binned ratios per depth range" if quantity == "completeness"
                  else f"use the binned {quantity} ratios per depth range")
    return (f"{what} of {kind} does not describe the outcomes {place}; its intervals are too narrow there. "
            f"The {quantity} {cause}: {remedy}")
