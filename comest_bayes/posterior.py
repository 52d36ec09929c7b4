"""Products of a fitted completeness model: curves, characteristic magnitudes, maps, queries.

A :class:`CompletenessPosterior` holds posterior draws of the unconstrained
parameters of one :class:`~comest_bayes.modelspec.ModelSpec`, plus what is
needed to evaluate the model anywhere on the image: the normalisation of the
covariates (image shape, reference noise and size) and a coarse map of the
detection noise (for the depth covariate).  It saves to one ``.npz`` file
(specification, draws, diagnostics, noise map, footprint sample, WCS) and loads
back without the outcome table.

Conventions
-----------
Draw-first axis: every query returns an array of shape ``(S, ...)`` with one
row per posterior draw.  "Image average" means the mean of f over a fixed,
seeded sample of unmasked pixel positions of the footprint.  Bands are the
central 68% and 95% intervals over draws.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import InputError
from .likelihood import BinomialData, CompletenessModel, Covariates
from .modelspec import ModelSpec, spec_from_mapping

__all__ = ["CompletenessPosterior", "coarse_noise_map", "footprint_sample", "crossing_magnitudes"]

#: Largest number of (draw, position, magnitude) values evaluated at once by image averages.
AVERAGE_ELEMENTS = 4_000_000

#: Percentiles reported for the 68% and 95% bands.
BANDS = (2.5, 16.0, 50.0, 84.0, 97.5)


def coarse_noise_map(noise: np.ndarray, mask: np.ndarray, step: int = 32) -> np.ndarray:
    """Median noise sigma in ``step`` x ``step`` blocks (NaN where all masked)."""
    ny, nx = noise.shape
    gy, gx = -(-ny // step), -(-nx // step)
    out = np.full((gy, gx), np.nan)
    for j in range(gy):
        for i in range(gx):
            blk = noise[j * step:(j + 1) * step, i * step:(i + 1) * step]
            good = ~mask[j * step:(j + 1) * step, i * step:(i + 1) * step] & np.isfinite(blk) & (blk > 0)
            if good.any():
                out[j, i] = float(np.median(blk[good]))
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
    """Per draw, the magnitude where a curve first falls below ``level`` (linear interpolation).

    ``curves`` has shape (S, M) on the increasing grid ``mags``; NaN for draws
    that never reach ``level`` (e.g. a plateau below it) or start below it.
    """
    above = curves >= level
    out = np.full(curves.shape[0], np.nan)
    # first index where the curve is below the level, after being above it at the bright end
    below = ~above
    first = np.argmax(below, axis=1)
    ok = above[:, 0] & below.any(axis=1)
    rows = np.flatnonzero(ok)
    j = first[rows]
    c0, c1 = curves[rows, j - 1], curves[rows, j]
    m0, m1 = mags[j - 1], mags[j]
    out[rows] = m0 + (c0 - level) / np.where(c0 != c1, c0 - c1, 1.0) * (m1 - m0)
    return out


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
        Unmasked (x, y) positions for image averages.
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
    _model: CompletenessModel | None = field(default=None, repr=False, compare=False)

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
        from astropy.io import fits
        from astropy.wcs import WCS

        return WCS(fits.Header.fromstring(self.wcs_header), relax=True)

    def _depth(self, x, y) -> np.ndarray:
        if self.noise_grid is None or self.meta.get("sigma_ref") in (None, 0):
            return np.zeros(np.shape(x))
        gy, gx = self.noise_grid.shape
        j = np.clip((np.asarray(y) // self.grid_step).astype(int), 0, gy - 1)
        i = np.clip((np.asarray(x) // self.grid_step).astype(int), 0, gx - 1)
        sigma = self.noise_grid[j, i]
        sigma = np.where(np.isfinite(sigma), sigma, self.meta["sigma_ref"])
        return -2.5 * np.log10(sigma / self.meta["sigma_ref"])

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
                               (2.0 * x / max(nx - 1, 1) - 1.0).ravel(), (2.0 * y / max(ny - 1, 1) - 1.0).ravel(),
                               size.ravel())

    def _draws(self, nsamples: int | None):
        s = self.samples
        if nsamples is not None and nsamples < len(s):
            s = s[np.linspace(0, len(s) - 1, nsamples).astype(int)]
        return s

    def _spatial(self) -> bool:
        return self.spec.spatial != "none"

    def _to_pixels(self, x, y, ra, dec):
        if ra is not None or dec is not None:
            if self.wcs is None:
                raise InputError("sky coordinates need the image WCS, and this posterior has none.")
            x, y = self.wcs.all_world2pix(np.asarray(ra, float), np.asarray(dec, float), 0)
        return x, y

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
        ndarray, shape (S,) + broadcast shape
        """
        thetas = self._draws(nsamples)
        x, y = self._to_pixels(x, y, ra, dec)
        if x is None or y is None:
            return self.average_curve(np.asarray(m, float), nsamples=nsamples)
        cov = self.covariates(m, x, y, hlr_arcsec)
        shape = np.broadcast_shapes(np.shape(m), np.shape(x), np.shape(y))
        return self.model.prob(thetas, cov).reshape((len(thetas),) + shape)

    def average_curve(self, mags, *, nsamples: int | None = 1000, npos: int = 400) -> np.ndarray:
        """Image-average f(m) per draw, shape (S, M)."""
        thetas = self._draws(nsamples)
        mags = np.atleast_1d(np.asarray(mags, float))
        pos = self.footprint if self._spatial() else self.footprint[:1]
        pos = pos[:npos]
        cov = self.covariates(mags[None, :], pos[:, 0:1], pos[:, 1:2])
        # draws in chunks of at most AVERAGE_ELEMENTS numbers (memory), padded to one compiled shape
        per_draw = len(pos) * len(mags)
        chunk = int(max(1, min(len(thetas), AVERAGE_ELEMENTS // max(1, per_draw))))
        out = np.empty((len(thetas), len(mags)))
        for start in range(0, len(thetas), chunk):
            block = thetas[start:start + chunk]
            nb = len(block)
            if nb < chunk:
                block = np.concatenate([block, np.repeat(block[-1:], chunk - nb, axis=0)])
            f = self.model.prob(block, cov).reshape(chunk, len(pos), len(mags))
            out[start:start + nb] = f[:nb].mean(axis=1)
        return out

    def curve(self, mags, *, x=None, y=None, ra=None, dec=None, nsamples: int | None = 1000) -> dict:
        """Median and 68% / 95% bands of f(m) (image average, or at a position)."""
        mags = np.asarray(mags, float)
        if x is None and ra is None:
            f = self.average_curve(mags, nsamples=nsamples)
        else:
            f = self.completeness(mags, x, y, ra=ra, dec=dec, nsamples=nsamples)
        q = np.percentile(f, BANDS, axis=0)
        return {"mag": mags, "lo95": q[0], "lo68": q[1], "median": q[2], "hi68": q[3], "hi95": q[4]}

    def magnitudes_at(self, levels=(0.5, 0.8, 0.9), *, nsamples: int | None = 1000, step: float = 0.01) -> dict:
        """Posterior draws of the magnitudes where the image-average f falls to each level.

        Returns ``{level: ndarray (S,)}``; NaN where a draw never reaches the
        level (e.g. a plateau A below it).
        """
        lo, hi = self.meta.get("mag_range", (15.0, 30.0))
        # Two passes (the image-average curve is monotone in m): a coarse grid locates every draw's
        # crossings, then the fine grid covers only the window spanned by them.  For spatial models
        # this is ~10 times less work than the fine grid over the whole range, for the same numbers.
        coarse_step = max(float(step), 0.1)
        coarse = np.arange(lo - 2.0, hi + 2.0 + coarse_step, coarse_step)
        fc = self.average_curve(coarse, nsamples=nsamples)
        first = {float(lev): crossing_magnitudes(coarse, fc, lev) for lev in levels}
        found = np.concatenate([c[np.isfinite(c)] for c in first.values()])
        if found.size == 0 or coarse_step <= step:
            return first
        w_lo, w_hi = float(found.min()) - coarse_step, float(found.max()) + coarse_step
        grid = np.arange(w_lo, w_hi + step, step)
        f = self.average_curve(grid, nsamples=nsamples)
        out = {}
        for lev, c in first.items():
            fine = crossing_magnitudes(grid, f, lev)
            out[lev] = np.where(np.isfinite(c), fine, np.nan)
        return out

    def summary_magnitudes(self, levels=(0.5, 0.8, 0.9)) -> dict:
        """JSON-ready medians and 68% intervals of m50, m80, m90."""
        out = {}
        for lev, draws in self.magnitudes_at(levels).items():
            ok = np.isfinite(draws)
            key = f"m{int(round(100 * lev))}"
            if ok.mean() < 0.5:
                out[key] = {"median": None, "lo68": None, "hi68": None, "defined_fraction": float(ok.mean())}
                continue
            q = np.percentile(draws[ok], [16, 50, 84])
            out[key] = {"median": float(q[1]), "lo68": float(q[0]), "hi68": float(q[2]),
                        "defined_fraction": float(ok.mean())}
        return out

    def m50_map(self, step_pix: int = 64, *, nsamples: int | None = 500):
        """Posterior median and standard deviation of the m50 field on a grid.

        Returns ``(median, sd, header)``: arrays of shape (ny/step, nx/step)
        and a FITS header with the binned grid's WCS (if the image has one).
        """
        from astropy.io import fits

        ny, nx = self.meta["image_shape"]
        gy, gx = -(-ny // step_pix), -(-nx // step_pix)
        yc = (np.arange(gy) + 0.5) * step_pix - 0.5
        xc = (np.arange(gx) + 0.5) * step_pix - 0.5
        yy, xx = np.meshgrid(yc, xc, indexing="ij")
        cov = self.covariates(np.zeros(xx.shape), xx, yy)
        m50 = self.model.m50(self._draws(nsamples), cov).reshape(-1, gy, gx)
        header = fits.Header()
        if self.wcs is not None:
            from .ratios import map_wcs

            header.update(map_wcs(self.wcs, float(step_pix), (gy, gx)).to_header(relax=True))
        header["BINPIX"] = (step_pix, "side of a map bin in image pixels")
        header["BUNIT"] = "mag"
        return np.median(m50, axis=0), np.std(m50, axis=0), header

    # ---- persistence --------------------------------------------------------------
    def save(self, path) -> Path:
        """Write everything to one ``.npz`` (atomically)."""
        from .rundir import atomic_path

        path = Path(path)
        spec_d = dataclasses.asdict(self.spec)
        spec_d.pop("source", None)
        if not spec_d.get("candidates"):
            spec_d.pop("candidates", None)
        spec = json.dumps(_jsonable(spec_d))
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as fh:
                np.savez_compressed(
                    fh, samples=self.samples, names=np.array(self.names), spec=np.array(spec),
                    meta=np.array(json.dumps(_jsonable(self.meta))),
                    noise_grid=np.array([]) if self.noise_grid is None else self.noise_grid,
                    grid_step=np.array(self.grid_step), footprint=self.footprint,
                    wcs_header=np.array(self.wcs_header or ""),
                    diagnostics=np.array(json.dumps(_jsonable(self.diagnostics))))
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
                       diagnostics=json.loads(str(z["diagnostics"])))


def _jsonable(obj):
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (np.floating, float)):
        return None if not np.isfinite(obj) else float(obj)
    return obj
