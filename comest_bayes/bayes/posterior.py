"""Products of a fitted completeness model: curves, characteristic magnitudes, maps, queries.

A :class:`CompletenessPosterior` holds the posterior draws of one model with what it needs to be
evaluated anywhere on the image, and saves to (and loads from) one ``.npz`` file.  Conventions
(draw-first axis, the exact image average through :class:`Footprint`, extrapolation warnings):
``docs/bayesian.md``.
"""

from __future__ import annotations

import dataclasses
import json
import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from comest_bayes.errors import InputError
from comest_bayes.io.jsonio import dumps
from comest_bayes.ratios.binned import first_crossings, map_wcs
from comest_bayes.bayes.outcomes import BinomialData, Covariates, depth_covariate, image_coordinate
from comest_bayes.bayes.model import CompletenessModel
from comest_bayes.bayes.spec import ModelSpec, spec_from_mapping
from comest_bayes.io.rundir import atomic_path

__all__ = ["CompletenessPosterior", "Footprint", "FootprintHistogram", "ExtrapolationWarning", "average_prob", "average_crossings", "coarse_noise_map", "footprint_sample",
           "crossing_magnitudes"]

#: Largest number of (draw, position, magnitude) values evaluated at once by image averages.
AVERAGE_ELEMENTS = 4_000_000

#: (Draw, magnitude) pairs per call of the footprint averages: every call has this one shape.
AVERAGE_ROWS = 256

#: Draws whose whole grid brackets the crossings of :func:`average_crossings`.
PILOT_DRAWS = 16

#: Pixels per block of rows that :meth:`Footprint.from_maps` groups at a time (bounds its memory).
FOOTPRINT_CHUNK = 1 << 20

#: Percentiles reported for the 68% and 95% bands.
BANDS = (2.5, 16.0, 50.0, 84.0, 97.5)


class ExtrapolationWarning(UserWarning):
    """A query or summary lies outside the magnitudes or depths the injections covered."""


@dataclass(frozen=True)
class Footprint:
    """Every unmasked pixel of an image, grouped into weighted covariate cells.

    Attributes
    ----------
    depth, u, v : ndarray, shape (P,)
        Mean depth covariate ``d = -2.5 log10(sigma / sigma_ref)`` and mean
        normalised coordinates of the pixels of each cell.
    weight : ndarray, shape (P,)
        Fraction of the unmasked pixels in each cell (sums to 1).
    npix : int
        Number of unmasked pixels.
    """

    depth: np.ndarray
    u: np.ndarray
    v: np.ndarray
    weight: np.ndarray
    npix: int

    @classmethod
    def from_maps(cls, noise: np.ndarray | None, mask: np.ndarray, sigma_ref: float | None, *,
                  ddepth: float = 0.01, nuv: int = 1) -> "Footprint":
        """Group the unmasked pixels by depth (steps of ``ddepth`` mag) and ``nuv`` x ``nuv`` blocks.

        Parameters
        ----------
        noise : ndarray (ny, nx) or None
            Detection noise sigma per pixel; None (or no ``sigma_ref``) gives
            depth 0 everywhere.  Pixels with a non-finite or non-positive
            noise count at the reference depth (as the outcome table does).
        mask : ndarray of bool (ny, nx)
            True where masked.
        sigma_ref : float or None
            Reference noise of the depth covariate (the fit's).
        ddepth : float
            Depth step, mag (default 0.01).
        nuv : int
            Blocks per image side (1 when the model has no smooth term).

        Notes
        -----
        The one pass over the pixels is :meth:`FootprintHistogram.from_maps`,
        which does not depend on ``sigma_ref``: a run computes it once and
        every fit takes its cells with :meth:`from_histogram`.
        """
        return cls.from_histogram(FootprintHistogram.from_maps(noise, mask, ddepth=ddepth, nuv=nuv), sigma_ref)

    @classmethod
    def from_histogram(cls, hist: "FootprintHistogram", sigma_ref: float | None) -> "Footprint":
        """The cells of a :class:`FootprintHistogram` at the depth covariate of ``sigma_ref``.

        The depth of a pixel is ``-2.5 log10(sigma / sigma_ref) = l + 2.5 log10(sigma_ref)`` with
        ``l = -2.5 log10(sigma)``: a shift of the histogram's mean ``l`` per cell.  Pixels without a valid
        noise (and every pixel when there is no noise map or no ``sigma_ref``) sit at depth 0.
        """
        if sigma_ref and hist.has_noise:
            depth = np.where(hist.valid, hist.level + 2.5 * math.log10(float(sigma_ref)), 0.0)
            n, u, v = hist.n, hist.u, hist.v
        else:
            # depth 0 everywhere: the cells of one (u, v) block merge
            blocks, inv = np.unique(hist.block, return_inverse=True)
            n = np.bincount(inv, weights=hist.n)
            u = np.bincount(inv, weights=hist.n * hist.u) / n
            v = np.bincount(inv, weights=hist.n * hist.v) / n
            depth = np.zeros(blocks.size)
        return cls(depth=np.asarray(depth, np.float64), u=u, v=v, weight=n / n.sum(), npix=hist.npix)

    @classmethod
    def from_points(cls, x, y, noise, sigma_ref: float | None, shape, *, ddepth: float | None = 0.01,
                    nuv: int = 1) -> "Footprint":
        """The footprint as sampled by a set of positions (e.g. the injections), each of equal weight.

        Depth follows the rule of the outcome table (non-finite or non-positive
        noise counts at the reference depth).  The points are grouped as the
        pixels of :meth:`from_maps` are: by depth in steps of ``ddepth`` mag and
        in ``nuv`` x ``nuv`` blocks, each cell at its members' mean covariates
        and weighted by their number (``ddepth=None``: one cell per point).
        12,000 injections take a few dozen cells instead of 12,000, and every
        image average costs that much less.
        """
        x, y, sig = (np.asarray(a, np.float64) for a in (x, y, noise))
        ny, nx = shape
        depth = np.zeros(sig.size)
        good = np.isfinite(sig) & (sig > 0)
        if sigma_ref:
            depth[good] = depth_covariate(sig[good], sigma_ref)
        u, v = image_coordinate(x, nx), image_coordinate(y, ny)
        if ddepth is None or sig.size == 0:
            return cls(depth=depth, u=u, v=v, weight=np.full(sig.size, 1.0 / max(sig.size, 1)), npix=int(sig.size))
        nuv = int(nuv)
        dkey = np.floor((depth - depth.min()) / float(ddepth)).astype(np.int64)
        bu = np.clip(np.floor((u + 1.0) * 0.5 * nuv), 0, nuv - 1).astype(np.int64)
        bv = np.clip(np.floor((v + 1.0) * 0.5 * nuv), 0, nuv - 1).astype(np.int64)
        _, cell = np.unique((dkey * nuv + bu) * nuv + bv, return_inverse=True)
        cell = np.asarray(cell).ravel()
        n = np.bincount(cell).astype(np.float64)
        return cls(depth=np.bincount(cell, weights=depth) / n, u=np.bincount(cell, weights=u) / n,
                   v=np.bincount(cell, weights=v) / n, weight=n / n.sum(), npix=int(sig.size))

    def __len__(self) -> int:
        return int(self.weight.size)

    def to_arrays(self) -> dict:
        return {"fp_depth": self.depth, "fp_u": self.u, "fp_v": self.v, "fp_weight": self.weight,
                "fp_npix": np.array(self.npix)}

    @classmethod
    def from_arrays(cls, z) -> "Footprint | None":
        if "fp_weight" not in z:
            return None
        return cls(depth=np.array(z["fp_depth"]), u=np.array(z["fp_u"]), v=np.array(z["fp_v"]),
                   weight=np.array(z["fp_weight"]), npix=int(z["fp_npix"]))


@dataclass(frozen=True)
class FootprintHistogram:
    """Every unmasked pixel grouped by noise level and position block: the one pass over the maps.

    Independent of the depth covariate's reference noise, so one histogram serves the fits of
    every kind and quantity of a run (:meth:`Footprint.from_histogram`).

    Attributes
    ----------
    n : ndarray (P,)
        Pixels per cell.
    level : ndarray (P,)
        Mean ``-2.5 log10(sigma)`` of the cell's pixels (0 for cells without a valid noise).
    valid : ndarray of bool (P,)
        The cell's pixels have a finite positive noise.
    u, v : ndarray (P,)
        Mean normalised coordinates.
    block : ndarray of int (P,)
        The ``nuv`` x ``nuv`` position block of the cell.
    npix : int
        Unmasked pixels.
    has_noise : bool
        A noise map was given.
    ddepth : float
    nuv : int
    """

    n: np.ndarray
    level: np.ndarray
    valid: np.ndarray
    u: np.ndarray
    v: np.ndarray
    block: np.ndarray
    npix: int
    has_noise: bool
    ddepth: float
    nuv: int

    @classmethod
    def from_maps(cls, noise: np.ndarray | None, mask: np.ndarray, *, ddepth: float = 0.01,
                  nuv: int = 1) -> "FootprintHistogram":
        """Bin the unmasked pixels in steps of ``ddepth`` mag of ``-2.5 log10(sigma)`` and ``nuv`` blocks a side.

        Pixels whose noise is not finite and positive form cells of their own (``valid`` False).
        Rows are read in blocks of :data:`FOOTPRINT_CHUNK` pixels (bounded memory).
        """
        mask = np.asarray(mask, bool)
        ny, nx = mask.shape
        if not (ddepth > 0 and int(nuv) >= 1):
            raise InputError(f"footprint histogram: ddepth must be > 0 and nuv >= 1, got {ddepth} and {nuv}.")
        nuv = int(nuv)
        has_noise = noise is not None
        if has_noise:
            noise = np.asarray(noise)
            if noise.shape != mask.shape:
                raise InputError(f"noise map {noise.shape} and mask {mask.shape} differ in shape.")
        good_px = ~mask
        npix = int(np.count_nonzero(good_px))
        if npix == 0:
            raise InputError("the mask leaves no unmasked pixel to average over.")
        # the level range from the noise extremes (linear-time integer keys for bincount, no sort)
        lmin = lmax = 0.0
        if has_noise:
            with np.errstate(invalid="ignore"):
                valid_px = good_px & np.isfinite(noise) & (noise > 0)
            if np.any(valid_px):
                lmin = -2.5 * math.log10(float(np.max(noise[valid_px])))
                lmax = -2.5 * math.log10(float(np.min(noise[valid_px])))
        nl = int(np.floor((lmax - lmin) / ddepth)) + 2  # the last key holds the pixels without a valid noise
        size = nl * nuv * nuv
        cnt, sl, su, sv = (np.zeros(size) for _ in range(4))
        rows = max(1, FOOTPRINT_CHUNK // max(nx, 1))
        for j0 in range(0, ny, rows):
            # flat indices of the block's good pixels (one pass, where a 2-D nonzero makes two index arrays)
            block_px = good_px[j0:j0 + rows]
            flat = np.flatnonzero(block_px)
            # each pixel's row from the rows' counts and its column by one subtraction: the same integers as
            # divmod(flat, nx), whose integer division took a third of the pass
            jj = np.repeat(np.arange(j0, j0 + block_px.shape[0]), np.count_nonzero(block_px, axis=1))
            ii = flat - (jj - j0) * nx
            if has_noise:
                sig = noise[j0:j0 + rows].reshape(-1)[flat].astype(np.float64)
                ok = valid_px[j0:j0 + rows].reshape(-1)[flat]
                with np.errstate(invalid="ignore", divide="ignore"):
                    level = np.where(ok, -2.5 * np.log10(sig), 0.0)
                # clipped: the extremes above may differ from the per-pixel values by a rounding error
                key = np.where(ok, np.clip(np.floor((level - lmin) / ddepth), 0, nl - 2), nl - 1).astype(np.int64)
            else:
                level = np.zeros(flat.size)
                key = np.full(flat.size, nl - 1, dtype=np.int64)
            if nuv > 1:
                key = (key * nuv + np.minimum(ii * nuv // nx, nuv - 1)) * nuv + np.minimum(jj * nuv // ny, nuv - 1)
            cnt += np.bincount(key, minlength=size)
            sl += np.bincount(key, weights=level, minlength=size)
            su += np.bincount(key, weights=image_coordinate(ii, nx), minlength=size)
            sv += np.bincount(key, weights=image_coordinate(jj, ny), minlength=size)
        used = np.flatnonzero(cnt > 0)
        n = cnt[used]
        lkey = used // (nuv * nuv)
        return cls(n=n, level=sl[used] / n, valid=lkey < nl - 1, u=su[used] / n, v=sv[used] / n,
                   block=used % (nuv * nuv), npix=npix, has_noise=has_noise, ddepth=float(ddepth), nuv=nuv)


def _average_pairs(model, thetas: np.ndarray, mags: np.ndarray, footprint: Footprint) -> np.ndarray:
    """Footprint average of f for each (draw, magnitude) pair (rows of ``thetas`` with ``mags``): shape (N,).

    Evaluated in calls of exactly :data:`AVERAGE_ROWS` pairs (the last one padded), so that every
    footprint average of a process runs through one compiled program whatever the number of draws
    and magnitudes (each new shape costs a trace and a compile, or a cache load, of about 0.1 s).
    """
    n = len(thetas)
    out = np.empty(n)
    args = (footprint.depth, footprint.u, footprint.v, footprint.weight)
    rows = AVERAGE_ROWS
    for start in range(0, n, rows):
        th, mg = thetas[start:start + rows], mags[start:start + rows]
        nb = len(th)
        if nb < rows:
            th = np.concatenate([th, np.repeat(th[-1:], rows - nb, axis=0)])
            mg = np.concatenate([mg, np.full(rows - nb, mg[-1])])
        out[start:start + nb] = model.average_prob_at(th, mg, *args)[:nb]
    return out


def _distinct(thetas: np.ndarray):
    """The distinct rows of ``thetas`` and the index of each row among them (resampled draws repeat)."""
    uniq, inverse = np.unique(thetas, axis=0, return_inverse=True)
    return uniq, np.asarray(inverse).reshape(-1)


def average_prob(model, thetas: np.ndarray, mags, footprint: Footprint) -> np.ndarray:
    """Footprint average of f per draw: shape (S, M), exact over the footprint's cells.

    ``model`` is a :class:`~comest_bayes.bayes.model.CompletenessModel` and
    ``thetas`` its free parameters, shape (S, D) or (D,).  Identical draws
    (importance-sampled posteriors repeat draws) are evaluated once.
    """
    thetas = np.atleast_2d(np.asarray(thetas, float))
    mags = np.atleast_1d(np.asarray(mags, float))
    uniq, inverse = _distinct(thetas)
    u, m = len(uniq), mags.size
    f = _average_pairs(model, np.repeat(uniq, m, axis=0), np.tile(mags, u), footprint).reshape(u, m)
    return f[inverse]


def average_crossings(model, thetas, footprint: Footprint, levels, lo: float, hi: float, *,
                      xtol: float = 1e-4) -> dict:
    """Per draw, the magnitudes where the image-average f falls to each level.

    The first crossing on a 0.25-mag grid over ``[lo - 1, hi + 1]`` (NaN where
    a draw never reaches the level, e.g. a plateau below it, or starts below
    it); the Illinois variant of regula falsi then refines each bracket with
    exact footprint averages to ``xtol`` mag (default 1e-4, a tenth or less of
    any posterior sd).

    The image-average curve of every draw is monotone, so its crossing is its
    only one, and the grid is needed only for draws far from the others: the
    grid is evaluated for up to 16 pilot draws; a bracket around their
    crossings (widened by half their spread, at least 0.05 mag, inside the
    grid) is tested for every draw, and only draws it does not bracket are
    evaluated on the whole grid.  Identical draws are evaluated once.

    Returns
    -------
    dict
        ``{level: ndarray (S,)}``, NaN where a draw never reaches the level
        (e.g. a plateau below it) or starts below it.
    """
    thetas = np.atleast_2d(np.asarray(thetas, float))
    uniq, inverse = _distinct(thetas)
    nu = len(uniq)
    grid = np.arange(lo - 1.0, hi + 1.0 + 0.25, 0.25)
    ng = grid.size
    pilot = np.unique(np.linspace(0, nu - 1, min(nu, PILOT_DRAWS)).astype(int))
    f_pilot = _average_pairs(model, np.repeat(uniq[pilot], ng, axis=0), np.tile(grid, pilot.size),
                             footprint).reshape(pilot.size, ng)
    full = {}  # the whole grid of the draws no pilot bracket holds, computed once for every level

    def on_grid(rows):
        need = np.array([r for r in rows if r not in full], dtype=np.int64)
        if need.size:
            f = _average_pairs(model, np.repeat(uniq[need], ng, axis=0), np.tile(grid, need.size),
                               footprint).reshape(need.size, ng)
            full.update(zip(need.tolist(), f))
        return np.array([full[r] for r in rows]).reshape(len(rows), ng)

    out = {}
    for lev in levels:
        lev = float(lev)
        m = np.full(nu, np.nan)
        a = np.full(nu, np.nan)
        b = np.full(nu, np.nan)
        fa = np.full(nu, np.nan)
        fb = np.full(nu, np.nan)
        pc = crossing_magnitudes(grid, f_pilot, lev)
        pc = pc[np.isfinite(pc)]
        held = np.zeros(nu, bool)
        if pc.size:
            half = max(0.05, 0.5 * float(np.ptp(pc)))
            a0, b0 = max(grid[0], float(pc.min()) - half), min(grid[-1], float(pc.max()) + half)
            if a0 < b0:
                ends = _average_pairs(model, np.concatenate([uniq, uniq]),
                                      np.concatenate([np.full(nu, a0), np.full(nu, b0)]), footprint) - lev
                held = (ends[:nu] >= 0) & (ends[nu:] < 0)
                a[held], b[held], fa[held], fb[held] = a0, b0, ends[:nu][held], ends[nu:][held]
        rest = np.flatnonzero(~held)
        if rest.size:
            fc = on_grid(rest.tolist())
            mr = crossing_magnitudes(grid, fc, lev)
            ok = np.isfinite(mr)
            rows = rest[ok]
            j = np.clip(np.searchsorted(grid, mr[ok]), 1, ng - 1)  # grid[j-1] <= crossing <= grid[j]
            a[rows], b[rows] = grid[j - 1], grid[j]
            fa[rows], fb[rows] = fc[ok, j - 1] - lev, fc[ok, j] - lev  # fa >= 0 > fb (falling curve)
            held[rows] = True
        rows = np.flatnonzero(held)
        if rows.size:
            a, b, fa, fb = a[rows], b[rows], fa[rows], fb[rows]
            th = uniq[rows]
            c = np.clip(a + fa * (b - a) / np.where(fa != fb, fa - fb, 1.0), a, b)
            side = np.zeros(rows.size)
            active = np.ones(rows.size, bool)
            for _ in range(60):
                act = np.flatnonzero(active)
                den = np.where(fa[act] != fb[act], fa[act] - fb[act], 1.0)
                c[act] = np.clip(a[act] + fa[act] * (b[act] - a[act]) / den, a[act], b[act])
                fcur = _average_pairs(model, th[act], c[act], footprint) - lev
                left = fcur >= 0  # the crossing lies right of c
                sd = side[act]
                # Illinois: halve the retained end's value when the same end is kept twice
                fb_, fa_ = fb[act], fa[act]
                fb_ = np.where(left & (sd == 1), 0.5 * fb_, fb_)
                fa_ = np.where(~left & (sd == -1), 0.5 * fa_, fa_)
                a[act], fa[act] = np.where(left, c[act], a[act]), np.where(left, fcur, fa_)
                b[act], fb[act] = np.where(left, b[act], c[act]), np.where(left, fb_, fcur)
                side[act] = np.where(left, 1, -1)
                active[act] = (b[act] - a[act] >= xtol) & (np.abs(fcur) >= 1e-10)
                if not active.any():
                    break
            m[rows] = c
        out[lev] = m[inverse]
    return out


def coarse_noise_map(noise: np.ndarray, mask: np.ndarray, step: int = 32) -> np.ndarray:
    """Median noise sigma in ``step`` x ``step`` blocks (NaN where all masked)."""
    ny, nx = noise.shape
    gy, gx = -(-ny // step), -(-nx // step)
    # pad to whole blocks with NaN, then one median per block over its good pixels
    padded = np.full((gy * step, gx * step), np.nan, dtype=np.float32)
    with np.errstate(invalid="ignore"):
        good = ~np.asarray(mask, bool) & np.isfinite(noise) & (noise > 0)
    padded[:ny, :nx] = np.where(good, noise, np.nan)
    blocks = padded.reshape(gy, step, gx, step).transpose(0, 2, 1, 3).reshape(gy, gx, step * step)
    # nanmedian by one sort (NaN sorts last): the mean of the middle good values, in the map's float32 as
    # np.nanmedian computes it (identical values; np.nanmedian loops over the blocks and took 3x as long)
    s = np.sort(blocks, axis=-1)
    n = np.count_nonzero(~np.isnan(s), axis=-1)
    lo = np.take_along_axis(s, np.maximum((n - 1) // 2, 0)[..., None], -1)[..., 0]
    hi = np.take_along_axis(s, np.minimum(n // 2, s.shape[-1] - 1)[..., None], -1)[..., 0]
    out = ((lo + hi) / np.float32(2)).astype(np.float64)
    out[n == 0] = np.nan  # a fully masked block
    return out


def footprint_sample(mask: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` uniformly drawn unmasked pixel positions, shape (n, 2) as (x, y)."""
    idx = np.flatnonzero(~mask.ravel())
    if idx.size == 0:
        raise InputError("the mask leaves no unmasked pixel to average over.")
    pick = rng.choice(idx, size=min(n, idx.size), replace=False)
    y, x = np.divmod(pick, mask.shape[1])
    return np.column_stack([x, y]).astype(float)


def crossing_magnitudes(mags: np.ndarray, curves: np.ndarray, level: float) -> np.ndarray:
    """Per draw, the magnitude where a curve first falls below ``level``: the binned ratios' rule
    (:func:`comest_bayes.ratios.binned.first_crossings`) on the grid ``mags``; ``curves`` has shape (S, M).
    NaN for draws that never reach ``level`` (e.g. a plateau below it) or never fall below it."""
    return first_crossings(mags, curves, level)


@dataclass
class CompletenessPosterior:
    """Posterior completeness (or purity) of one source kind.

    Attributes
    ----------
    spec : ModelSpec
        The fitted model.
    samples : ndarray, shape (S, D)
        Posterior draws of the unconstrained parameters (``names``).
    names : list of str
        Parameter names, in the model's order.
    meta : dict
        Covariate normalisation (``sigma_ref``, ``hlr_ref``, ``image_shape``),
        ``kind``, ``quantity`` ("completeness" or "purity") and ``mag_range``.
    noise_grid : ndarray or None
        Median detection noise in blocks of ``grid_step`` pixels.
    grid_step : int
        Block size of ``noise_grid``, pixels.
    footprint : ndarray, shape (P, 2)
        A seeded sample of unmasked (x, y) positions (used by the luminosity-
        function model's per-position terms).
    cells : Footprint or None
        Every unmasked pixel as weighted covariate cells: the exact image
        average (posteriors saved before this existed fall back to the
        position sample).
    wcs_header : str or None
        The image WCS (FITS header text), for sky-coordinate queries and maps.
    diagnostics : dict
        Sampler diagnostics and the model-selection table.
    """

    spec: ModelSpec
    samples: np.ndarray
    names: list
    meta: dict
    noise_grid: np.ndarray | None = None
    grid_step: int = 32
    footprint: np.ndarray = field(default_factory=lambda: np.zeros((1, 2)))
    wcs_header: str | None = None
    diagnostics: dict = field(default_factory=dict)
    cells: Footprint | None = None
    _model: CompletenessModel | None = field(default=None, repr=False, compare=False)

    def use_model(self, model: CompletenessModel | None) -> None:
        """Evaluate with an already compiled ``model`` (its parameters must be the spec's); None drops it
        (e.g. before the posterior is sent to another process, which rebuilds it on first use)."""
        if model is not None and list(model.names) != list(self.names):
            raise InputError(f"the model's parameters {model.names} are not the posterior's {self.names}.")
        self._model = model

    # ---- evaluation -------------------------------------------------------------
    @property
    def model(self) -> CompletenessModel:
        """The model, rebuilt on a one-cell placeholder (only its structure is used)."""
        if self._model is None:
            cov = Covariates.make([20.0])
            data = BinomialData(cov=cov, n=np.array([1]), k=np.array([1]),
                                meta={**self.meta, "binned": ("m", "depth", "uv", "size")})
            self._model = CompletenessModel(self.spec, data)
            if list(self._model.names) != list(self.names):
                raise InputError(f"saved parameter names {self.names} do not match the model's {self._model.names}.")
        return self._model

    @property
    def wcs(self):
        if self.wcs_header is None:
            return None
        from comest_bayes.io.image import wcs_from_stored_header

        return wcs_from_stored_header(self.wcs_header)

    def _depth(self, x, y) -> np.ndarray:
        if self.noise_grid is None or self.meta.get("sigma_ref") in (None, 0):
            return np.zeros(np.shape(x))
        gy, gx = self.noise_grid.shape
        j = np.clip((np.asarray(y) // self.grid_step).astype(int), 0, gy - 1)
        i = np.clip((np.asarray(x) // self.grid_step).astype(int), 0, gx - 1)
        sigma = self.noise_grid[j, i]
        sigma = np.where(np.isfinite(sigma), sigma, self.meta["sigma_ref"])
        return depth_covariate(sigma, self.meta["sigma_ref"])

    def covariates(self, m, x, y, hlr_arcsec=None) -> Covariates:
        """Covariates of magnitudes ``m`` at pixel positions ``x, y`` (broadcast together)."""
        ny, nx = self.meta["image_shape"]
        hlr = np.nan if hlr_arcsec is None else hlr_arcsec
        m, x, y, hlr = np.broadcast_arrays(np.asarray(m, float), np.asarray(x, float), np.asarray(y, float),
                                           np.asarray(hlr, float))
        for name, arr in (("magnitude", m), ("x", x), ("y", y)):
            if not np.all(np.isfinite(arr)):
                raise InputError(f"completeness query with {int((~np.isfinite(arr)).sum())} non-finite {name} "
                                 "value(s); give finite magnitudes and positions (drop NaN rows first).")
        href = self.meta.get("hlr_ref")
        with np.errstate(divide="ignore", invalid="ignore"):
            size = np.where(np.isfinite(hlr) & (hlr > 0) & bool(href), np.log10(hlr / (href or 1.0)), 0.0)
        return Covariates.make(m.ravel(), self._depth(x, y).ravel(),
                               image_coordinate(x, nx).ravel(), image_coordinate(y, ny).ravel(),
                               size.ravel())

    def _draws(self, nsamples: int | None):
        s = self.samples
        if nsamples is not None and (isinstance(nsamples, bool) or not isinstance(nsamples, (int, np.integer))
                                     or nsamples < 1):
            raise InputError(f"nsamples must be a positive integer (or None for every draw), got {nsamples!r}.")
        if nsamples is not None and nsamples < len(s):
            s = s[np.linspace(0, len(s) - 1, nsamples).astype(int)]
        return s

    def _spatial(self) -> bool:
        return self.spec.is_spatial

    def _to_pixels(self, x, y, ra, dec):
        """Pixel positions of a query, or ``(None, None)`` for the image average; checked and warned about."""
        pixel, sky = (x is not None, y is not None), (ra is not None, dec is not None)
        if pixel[0] != pixel[1] or sky[0] != sky[1]:
            raise InputError("a position needs both coordinates: give x and y (0-based pixels), or ra and dec "
                             "(degrees); give neither for the image average.")
        if all(pixel) and all(sky):
            raise InputError("give the position as x, y or as ra, dec, not both.")
        if all(sky):
            if self.wcs is None:
                raise InputError("sky coordinates need the image WCS, and this posterior has none.")
            ra, dec = np.asarray(ra, float), np.asarray(dec, float)
            for name, arr in (("ra", ra), ("dec", dec)):
                if not np.all(np.isfinite(arr)):
                    raise InputError(f"completeness query with {int((~np.isfinite(arr)).sum())} non-finite {name} "
                                     "value(s); give finite sky positions (drop NaN rows first).")
            x, y = self.wcs.all_world2pix(ra, dec, 0)
            off = ~(np.isfinite(x) & np.isfinite(y))
            if np.any(off):
                raise InputError(f"{int(off.sum())} sky position(s) have no pixel position in the image's WCS (too far "
                                 "from the image for its projection): query positions on or near the image.")
        elif not all(pixel):
            return None, None
        self._need_positions()
        ny, nx = self.meta["image_shape"]
        xa, ya = np.asarray(x, float), np.asarray(y, float)
        with np.errstate(invalid="ignore"):
            out = (xa < -0.5) | (xa > nx - 0.5) | (ya < -0.5) | (ya > ny - 0.5)
        if np.any(out):
            warnings.warn(f"{int(np.sum(out))} queried position(s) lie outside the {nx}x{ny}-pixel image: the model "
                          "extrapolates there (its depth is that of the nearest edge, its spatial terms continue "
                          "past the edge).", ExtrapolationWarning, stacklevel=3)
        return x, y

    def _need_positions(self) -> None:
        if self.meta.get("positions") is False:
            raise InputError("this posterior was fitted to outcomes without positions (comest-bayes fit on a table "
                             "with no x, y columns): its completeness is the same everywhere. Query it without a "
                             "position, or fit a table with x and y columns.")

    @staticmethod
    def _magnitudes(m) -> np.ndarray:
        m = np.asarray(m, float)
        if not np.all(np.isfinite(m)):
            raise InputError(f"completeness query with {int((~np.isfinite(m)).sum())} non-finite magnitude value(s); "
                             "give finite magnitudes (drop NaN rows first).")
        return m

    def completeness(self, m, x=None, y=None, *, ra=None, dec=None, hlr_arcsec=None,
                     nsamples: int | None = None) -> np.ndarray:
        """Posterior draws of f at magnitudes ``m`` and a position.

        Parameters
        ----------
        m : float or array
            Magnitudes.
        x, y : float or array, optional
            0-based pixel position(s), broadcast with ``m``; or give ``ra``,
            ``dec`` in degrees.  Without a position: the image average.
        hlr_arcsec : float, optional
            Half-light radius (models with a size term).
        nsamples : int, optional
            Thin the draws to this many.

        Returns
        -------
        ndarray, shape (S,) + broadcast shape (of ``m`` alone for the image average)

        Magnitudes outside the injected range, and positions outside the image, warn
        (:class:`ExtrapolationWarning`); non-finite values are refused.
        """
        thetas = self._draws(nsamples)
        m = self._magnitudes(m)
        x, y = self._to_pixels(x, y, ra, dec)
        if x is None:
            self._warn_extrapolation(m)
            return self.average_of(thetas, m.ravel()).reshape((len(thetas),) + m.shape)
        cov = self.covariates(m, x, y, hlr_arcsec)
        self._warn_extrapolation(cov.m, cov.depth)
        shape = np.broadcast_shapes(np.shape(m), np.shape(x), np.shape(y))
        return self.model.prob(thetas, cov).reshape((len(thetas),) + shape)

    def _range_label(self) -> str:
        if self.meta.get("quantity") == "purity":
            return "measured magnitudes of the detections"
        return "injected magnitudes"

    def extrapolated(self, m) -> np.ndarray:
        """True where a magnitude lies outside the injected range (the model's extrapolation)."""
        lo, hi = self.meta.get("injected_range") or (-np.inf, np.inf)
        m = np.asarray(m, float)
        return (m < lo) | (m > hi)

    def _warn_extrapolation(self, m, depth=None) -> None:
        out = self.extrapolated(m)
        if np.any(out):
            lo, hi = self.meta["injected_range"]
            warnings.warn(f"{int(out.sum())} queried magnitude(s) lie outside the {self._range_label()} range "
                          f"[{lo:.2f}, {hi:.2f}]: there the {self.meta.get('quantity', 'completeness')} is the "
                          "model's extrapolation, not a measurement.", ExtrapolationWarning, stacklevel=3)
        dr = self.meta.get("depth_range")
        if depth is not None and dr is not None and self.spec.uses_depth:
            d = np.asarray(depth, float)
            bad = (d < dr[0] - 0.05) | (d > dr[1] + 0.05)
            if np.any(bad):
                warnings.warn(f"{int(bad.sum())} queried position(s) have a depth covariate outside the injected "
                              f"range [{dr[0]:.2f}, {dr[1]:.2f}] mag: the model extrapolates there.",
                              ExtrapolationWarning, stacklevel=3)

    def average_curve(self, mags, *, nsamples: int | None = 1000) -> np.ndarray:
        """Image-average f(m) per draw, shape (S, M): exact over every unmasked pixel (:class:`Footprint`)."""
        return self.average_of(self._draws(nsamples), mags)

    def footprint_cells(self) -> Footprint:
        """Every unmasked pixel as weighted covariate cells (the exact image average)."""
        if self.cells is not None:
            return self.cells
        # a posterior saved before footprints were exact: the mean over its position sample
        pos = self.footprint if self._spatial() else self.footprint[:1]
        ny, nx = self.meta["image_shape"]
        return Footprint(depth=self._depth(pos[:, 0], pos[:, 1]), u=image_coordinate(pos[:, 0], nx),
                         v=image_coordinate(pos[:, 1], ny), weight=np.full(len(pos), 1.0 / len(pos)),
                         npix=len(pos))

    def average_of(self, thetas, mags) -> np.ndarray:
        """Image-average f(m) for given parameter draws ``thetas`` (S, D), shape (S, M)."""
        return average_prob(self.model, thetas, np.atleast_1d(np.asarray(mags, float)), self.footprint_cells())

    def curve(self, mags, *, x=None, y=None, ra=None, dec=None, nsamples: int | None = 1000,
              warn: bool = True) -> dict:
        """Median and 68% / 95% bands of f(m) (image average, or at a position); every entry of shape (M,).

        ``extrapolated`` flags the magnitudes outside the injected range.  They warn
        (:class:`ExtrapolationWarning`) unless ``warn`` is False, for a curve drawn over a fixed grid
        on purpose (the run's magnitude bins, a figure), whose flags say it instead.
        """
        mags = np.atleast_1d(self._magnitudes(mags)).ravel()
        with warnings.catch_warnings():
            if not warn:
                warnings.simplefilter("ignore", ExtrapolationWarning)
            f = self.completeness(mags, x, y, ra=ra, dec=dec, nsamples=nsamples)
        q = np.percentile(f, BANDS, axis=0)
        return {"mag": mags, "lo95": q[0], "lo68": q[1], "median": q[2], "hi68": q[3], "hi95": q[4],
                "extrapolated": self.extrapolated(mags)}

    def magnitudes_at(self, levels=(0.5, 0.8, 0.9), *, nsamples: int | None = 1000, step: float = 0.01) -> dict:
        """Posterior draws of the magnitudes where the image-average f falls to each level.

        Returns ``{level: ndarray (S,)}``; NaN where a draw never reaches the
        level (e.g. a plateau A below it).  ``levels``: one level or several, each in (0, 1).
        """
        levels = [float(v) for v in np.atleast_1d(np.asarray(levels, float))]
        if not all(0.0 < v < 1.0 for v in levels):
            raise InputError(f"levels must lie strictly between 0 and 1 (fractions, e.g. 0.5), got {levels}.")
        thetas = self._draws(nsamples)
        lo, hi = self.meta.get("mag_range", (15.0, 30.0))
        return average_crossings(self.model, thetas, self.footprint_cells(), levels, lo, hi, xtol=min(step, 1e-3))

    def summary_magnitudes(self, levels=(0.5, 0.8, 0.9)) -> dict:
        """JSON-ready medians, 68% and 95% intervals of m50, m80, m90.

        ``extrapolated`` is True when the median lies outside the injected
        magnitude range (the value is then the model's extrapolation; a
        warning says so).
        """
        out = {}
        for lev, draws in self.magnitudes_at(levels).items():
            ok = np.isfinite(draws)
            key = f"m{int(round(100 * lev))}"
            if ok.mean() < 0.5:
                out[key] = {"median": None, "lo68": None, "hi68": None, "lo95": None, "hi95": None,
                            "defined_fraction": float(ok.mean()), "extrapolated": None}
                continue
            q = np.percentile(draws[ok], BANDS)
            extra = bool(self.extrapolated(q[2]))
            out[key] = {"median": float(q[2]), "lo68": float(q[1]), "hi68": float(q[3]), "lo95": float(q[0]),
                        "hi95": float(q[4]), "defined_fraction": float(ok.mean()), "extrapolated": extra}
            if extra:
                lo, hi = self.meta["injected_range"]
                warnings.warn(f"{key} of the {self.meta.get('kind', '')} {self.meta.get('quantity', 'completeness')} "
                              f"= {q[2]:.2f} lies outside the {self._range_label()} [{lo:.2f}, {hi:.2f}]: it is the "
                              "model's extrapolation, not a measurement.", ExtrapolationWarning, stacklevel=2)
        return out

    def m50_map(self, step_pix: int = 64, *, nsamples: int | None = 500):
        """Posterior median and standard deviation of the m50 field on a grid.

        Returns ``(median, sd, header)``: arrays of shape (ny/step, nx/step)
        and a FITS header with the binned grid's WCS (if the image has one).
        """
        from astropy.io import fits

        self._need_positions()
        ny, nx = self.meta["image_shape"]
        if isinstance(step_pix, bool) or not isinstance(step_pix, (int, np.integer)) or not 1 <= step_pix <= max(ny, nx):
            raise InputError(f"step_pix must be a whole number of pixels from 1 to {max(ny, nx)} (the image is "
                             f"{nx}x{ny}), got {step_pix!r}.")
        gy, gx = -(-ny // step_pix), -(-nx // step_pix)
        yc = (np.arange(gy) + 0.5) * step_pix - 0.5
        xc = (np.arange(gx) + 0.5) * step_pix - 0.5
        yy, xx = np.meshgrid(yc, xc, indexing="ij")
        cov = self.covariates(np.zeros(xx.shape), xx, yy)
        m50 = self.model.m50(self._draws(nsamples), cov).reshape(-1, gy, gx)
        header = fits.Header()
        if self.wcs is not None:

            header.update(map_wcs(self.wcs, float(step_pix), (gy, gx)).to_header(relax=True))
        header["BINPIX"] = (step_pix, "side of a map bin in image pixels")
        header["BUNIT"] = "mag"
        return np.median(m50, axis=0), np.std(m50, axis=0), header

    # ---- persistence --------------------------------------------------------------
    def save(self, path) -> Path:
        """Write everything to one ``.npz`` (atomically)."""

        path = Path(path)
        spec_d = dataclasses.asdict(self.spec)
        spec_d.pop("source", None)
        # keys at their defaults are left out, so files of models without them read as before
        for key in ("candidates", "width_candidates", "width_order"):
            if not spec_d.get(key):
                spec_d.pop(key, None)
        spec = dumps(spec_d)
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as fh:
                np.savez_compressed(
                    fh, samples=self.samples, names=np.array(self.names), spec=np.array(spec),
                    meta=np.array(dumps(self.meta)),
                    noise_grid=np.array([]) if self.noise_grid is None else self.noise_grid,
                    grid_step=np.array(self.grid_step), footprint=self.footprint,
                    wcs_header=np.array(self.wcs_header or ""),
                    diagnostics=np.array(dumps(self.diagnostics)),
                    **(self.cells.to_arrays() if self.cells is not None else {}))
        return path

    @classmethod
    def load(cls, path) -> "CompletenessPosterior":
        """Read a posterior written by :meth:`save`."""
        path = Path(path)
        if not path.is_file():
            raise InputError(f"posterior file {str(path)!r} does not exist.")
        with np.load(path, allow_pickle=False) as z:
            spec_d = json.loads(str(z["spec"]))
            spec = spec_from_mapping(spec_d, name=spec_d.get("name"), source=str(path))
            meta = json.loads(str(z["meta"]))
            meta["image_shape"] = tuple(meta["image_shape"])
            grid = z["noise_grid"]
            return cls(spec=spec, samples=np.array(z["samples"]), names=[str(n) for n in z["names"]], meta=meta,
                       noise_grid=None if grid.size == 0 else np.array(grid), grid_step=int(z["grid_step"]),
                       footprint=np.array(z["footprint"]), wcs_header=str(z["wcs_header"]) or None,
                       diagnostics=json.loads(str(z["diagnostics"])), cells=Footprint.from_arrays(z))


