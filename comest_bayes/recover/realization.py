"""Injection and recovery: one realization, and the merge of many.

A realization injects one Poisson-drawn set of sources of one kind onto the base image,
re-detects with the identical configuration and matches one-to-one, with randomness only from
its own seed streams; :func:`merge_realizations` merges the output tables.  Classes of
detections, usable injections and the tables: ``docs/injection.md``.
"""

from __future__ import annotations

import functools
import os
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from astropy.io import fits
from astropy.table import Table, vstack

from comest_bayes.config import DetectionConfig, InjectionConfig, MatchingConfig
from comest_bayes.errors import InputError
from comest_bayes.constants import FWHM_PER_SIGMA
from comest_bayes.recover.matching import classify_detections, in_clean_zone, match_one_to_one
from comest_bayes.seeding import Stream, int_seed_for, rng_for
from comest_bayes.io import layout
from comest_bayes.io.image import wcs_from_stored_header
from comest_bayes.inject.psfmodel import make_psf
from comest_bayes.inject.cosmos import load_cosmos
from comest_bayes.detect.sep_backend import detect_with_backend
from comest_bayes.inject.render import FLAG_CLEAN_ZONE, make_truth, render_truth
from comest_bayes.inject.design import MagnitudeDesign
from comest_bayes.io.rundir import atomic_path

__all__ = ["SimContext", "RealizationTask", "RealizationResult", "MergedCatalogs", "run_realization", "merge_realizations",
           "realization_file", "OUTCOME_COLUMNS"]

#: Measured columns copied from the detection catalog next to each injection (prefixed ``det_``).
MEASURED = ("id", "xwin", "ywin", "mag_auto", "magerr_auto", "mag_aper", "flux_auto", "snr_auto",
            "flux_radius", "a", "b", "npix", "flags")

#: Columns of the outcome table read by the completeness model.
OUTCOME_COLUMNS = {
    "realization": "index of the realization (simulated image)",
    "injection_id": "index of the injection within its realization",
    "x": "true x, 0-based pixel",
    "y": "true y, 0-based pixel",
    "ra": "true right ascension (deg)",
    "dec": "true declination (deg)",
    "mag": "true magnitude",
    "hlr_arcsec": "true half-light radius (arcsec; NaN for point sources)",
    "noise": "detection noise sigma at the true position (image units)",
    "detected": "True when matched one-to-one to a detection",
    "det_mag_auto": "measured MAG_AUTO (NaN when not detected)",
    "det_flux_radius": "measured FLUX_RADIUS in pixels (NaN when not detected)",
    "det_flags": "detection FLAGS (-1 when not detected)",
    "separation": "distance between true and measured position, pixels (NaN when not detected)",
}


@dataclass(frozen=True)
class SimContext:
    """Everything a realization needs, by value or by path (picklable, small).

    Large arrays travel as file paths and are read once per worker process.
    """

    base_path: str
    mask_path: str
    noise_path: str
    baseline_path: str
    detection_path: str
    shape: tuple
    wcs_header: str | None
    zeropoint: float
    gain: float | None
    saturation: float | None
    pixel_scale: float
    fwhm: float
    mag_range: tuple
    noise_mode: str
    detection: DetectionConfig
    injection: InjectionConfig
    matching: MatchingConfig
    root_seed: int
    image_dir: str | None = None
    #: Moffat beta of the injection PSF (0: ``injection.moffat_beta``, or 3 when that is 0 too).
    psf_beta: float = 0.0
    #: The analytic PSF is convolved with the pixel (its FWHM and beta were fitted pixel-integrated).
    psf_pixel_integrated: bool = False
    #: The observed detection's background map (``detection.background_level = "observed"``).
    background_path: str = ""
    #: Segmentation of the baseline detection; when given, a detection whose centre lies in a baseline
    #: source's footprint is pre-existing too (injections on the observed image: docs/injection.md).
    baseline_segmentation_path: str = ""

    @property
    def wcs(self):
        return None if self.wcs_header is None else _wcs_from_text(self.wcs_header)


@dataclass(frozen=True)
class RealizationTask:
    """One realization to run; ``design`` (a :meth:`MagnitudeDesign.to_dict`) draws an adaptive batch's magnitudes."""

    context: SimContext
    kind: str
    index: int
    design: dict | None = None


@dataclass
class RealizationResult:
    """Tables of one realization; ``error`` is set (and tables are None) if it failed."""

    kind: str
    index: int
    truth: Table | None
    detections: Table | None
    seconds: dict = field(default_factory=dict)
    error: str | None = None


@functools.lru_cache(maxsize=4)
def _wcs_from_text(text: str):
    return wcs_from_stored_header(text)


def _file_key(path: str) -> tuple:
    """A cache key naming a file's content: a file rewritten under the same path is read again.

    The caches below live as long as the process (a notebook, a serial run, a long-lived Dask
    worker); keyed by path alone, a second run into a removed and recreated run directory would
    silently reuse the first run's images.
    """
    st = os.stat(path)
    return (str(path), st.st_mtime_ns, st.st_size, st.st_ino)


def _arrays(base_path: str, mask_path: str, noise_path: str):
    return _arrays_cached(_file_key(base_path), _file_key(mask_path), _file_key(noise_path))


@functools.lru_cache(maxsize=2)
def _arrays_cached(base_key: tuple, mask_key: tuple, noise_key: tuple):
    base = fits.getdata(base_key[0]).astype(np.float32)
    mask = fits.getdata(mask_key[0]).astype(bool)
    noise = fits.getdata(noise_key[0]).astype(np.float32)
    # Checked once per process and file: realizations add finite stamps to this base and then skip
    # the check (detect_array(check_finite=False)), which would otherwise cost a full-image pass each.
    if mask.shape != base.shape:
        raise InputError(f"the mask {mask_key[0]} has shape {mask.shape} but the base image {base_key[0]} "
                         f"{base.shape}; rerun the pipeline's stages that write them.")
    if (~np.isfinite(base) & ~mask).any():
        raise InputError(f"the base image {base_key[0]} holds NaN or infinite values in unmasked pixels; "
                         f"mask them (load_image does this) and rerun the pipeline's stages that write it.")
    return base, mask, noise


def _table(path: str) -> Table:
    return _table_cached(_file_key(path))


@functools.lru_cache(maxsize=2)
def _table_cached(key: tuple) -> Table:
    return Table.read(key[0])


@functools.lru_cache(maxsize=2)
def _psf(injection: InjectionConfig, fwhm: float, pixel_scale: float, beta: float = 0.0,
         pixel_integrated: bool = False):

    return make_psf(injection, fwhm, pixel_scale, beta=beta if beta > 0 else None, pixel_integrated=pixel_integrated)


@functools.lru_cache(maxsize=1)
def _cosmos(injection: InjectionConfig):

    return load_cosmos(injection)


def realization_file(directory, kind: str, index: int) -> Path:
    """The result table of one realization under ``directory`` (the run's :data:`~comest_bayes.io.layout.SIMS_DIR`)."""
    return Path(directory) / layout.realization(kind, index)


def _detect(image, mask, noise, ctx: SimContext):
    """Re-detect with the run's detection configuration and resolved noise mode.

    ``image`` is the realization's private rendered copy and is consumed: SEP
    subtracts the background in it (``inplace=True``).  No segmentation map
    is built, and the finiteness check was made once on the base image
    (:func:`_arrays_cached`).  The catalog is the same as
    :func:`~comest_bayes.detect.sep_backend.detect_array`'s default path gives.
    ``detection.background_level = "observed"`` subtracts the observed
    detection's background map (``ctx.background_path``) instead of one
    measured on ``image``.  ``noise`` is the observed detection's noise map: with
    ``detection.noise_level = "observed"`` it is the threshold's sigma as it
    is; with ``"per_image"`` it is the weight-map shape rescaled again to this
    image's background RMS (weight mode) or unused (the RMS of this image).
    """
    fixed = ctx.detection.noise_level == "observed"
    background = None
    if ctx.detection.background_level == "observed":
        background = _image(ctx.background_path, np.float32)
    return detect_with_backend(image, mask=mask,
                               weight_noise=noise if ctx.noise_mode == "weight" and not fixed else None,
                               threshold_noise=noise if fixed else None, threshold_background=background,
                               zeropoint=ctx.zeropoint, gain=ctx.gain, saturation=ctx.saturation, wcs=ctx.wcs,
                               config=ctx.detection, segmentation=False, inplace=True, check_finite=False)


def _image(path: str, dtype) -> np.ndarray:
    """A run image a worker reads for every realization (the background, the baseline segmentation), once."""
    return _image_cached(_file_key(path), np.dtype(dtype).str)


@functools.lru_cache(maxsize=2)
def _image_cached(key: tuple, dtype: str) -> np.ndarray:
    return fits.getdata(key[0]).astype(dtype)


def run_realization(task: RealizationTask) -> RealizationResult:
    """Inject, re-detect and match one realization (runs in a worker).

    Never raises for a failure inside the realization: the error and its
    traceback are returned so one bad realization does not stop a run.
    """
    try:
        return _run_realization(task)
    except Exception:  # one bad realization never kills a run
        return RealizationResult(task.kind, task.index, None, None, error=traceback.format_exc(limit=8))


def _run_realization(task: RealizationTask) -> RealizationResult:

    ctx, kind, index = task.context, task.kind, task.index
    t0 = time.perf_counter()
    c0 = time.process_time()
    base, mask, noise = _arrays(ctx.base_path, ctx.mask_path, ctx.noise_path)
    cosmos = _cosmos(ctx.injection) if kind == "cosmos" else None
    observed = _table(ctx.detection_path) if kind == "observed" else None
    psf = _psf(ctx.injection, ctx.fwhm, ctx.pixel_scale, ctx.psf_beta, ctx.psf_pixel_integrated)
    design = None
    if task.design is not None:

        design = MagnitudeDesign.from_dict(task.design)
    truth = make_truth(kind, shape=base.shape, mask=mask, pixel_scale=ctx.pixel_scale, fwhm_pix=ctx.fwhm,
                       config=ctx.injection, mag_range=ctx.mag_range, rng=rng_for(ctx.root_seed, Stream.INJECT, kind, index),
                       wcs=ctx.wcs, zeropoint=ctx.zeropoint, observed_catalog=observed, cosmos=cosmos, psf=psf,
                       mag_design=design)
    t1 = time.perf_counter()
    image, truth = render_truth(base, truth, psf=psf, config=ctx.injection,
                                pixel_scale=ctx.pixel_scale, gain=ctx.gain, zeropoint=ctx.zeropoint,
                                rng_seed=int_seed_for(ctx.root_seed, Stream.RENDER, kind, index), cosmos=cosmos,
                                wcs=ctx.wcs)
    t2 = time.perf_counter()
    seconds = {"make": t1 - t0, "render": t2 - t1}
    if ctx.image_dir:  # before detection, which subtracts the background in place

        path = Path(ctx.image_dir) / layout.realization_image(kind, index)
        path.parent.mkdir(parents=True, exist_ok=True)
        # the base image's header (its WCS, BUNIT, zero point) says what the pixels are, as sfi.fits does
        header = fits.getheader(ctx.base_path)
        header["INJKIND"] = (kind, "kind of the injected sources (truth: sims/<kind>/rNNNNN.fits)")
        header["INJREAL"] = (int(index), "realization index")
        with atomic_path(path) as tmp:
            fits.PrimaryHDU(image, header=header).writeto(tmp)
        seconds["image"] = time.perf_counter() - t2
        t2 = time.perf_counter()
    det = _detect(image, mask, noise, ctx)
    t3 = time.perf_counter()
    del image
    kept = _image(ctx.baseline_segmentation_path, np.int32) if ctx.baseline_segmentation_path else None
    truth, dets = match_realization(truth, det.catalog, _table(ctx.baseline_path), noise, ctx, kept_segmentation=kept)
    truth["realization"] = np.full(len(truth), index, dtype=np.int32)
    dets["realization"] = np.full(len(dets), index, dtype=np.int32)
    seconds.update(detect=t3 - t2, match=time.perf_counter() - t3, cpu=time.process_time() - c0)
    return RealizationResult(kind, index, truth, dets, seconds=seconds)


def match_realization(truth: Table, catalog: Table, baseline: Table, noise: np.ndarray, ctx: SimContext,
                      kept_segmentation: np.ndarray | None = None):
    """Attach outcome columns to the truth and class columns to the detections.

    Returns the truth (with ``usable``, ``detected``, ``separation``,
    ``noise`` and the ``det_*`` measured columns) and the detection catalog
    (with ``matched``, ``injection_id``, ``preexisting``, ``near_unusable`` and ``false``).
    An unmatched detection is pre-existing when it lies within the matching radius of a
    ``baseline`` source or, with ``kept_segmentation`` (the baseline detection's segmentation),
    when its centre pixel lies in a baseline source's footprint.
    """
    radius = ctx.matching.radius_fwhm * ctx.fwhm
    magcol = ctx.matching.mag_column
    if magcol not in catalog.colnames:
        raise KeyError(f"matching.mag_column={magcol!r} is not a detection column")
    det_mag = np.asarray(catalog[magcol], dtype=float)
    if det_mag.ndim == 2:
        det_mag = det_mag[:, 0]
    res = match_one_to_one(np.asarray(truth["x"], float), np.asarray(truth["y"], float),
                           np.asarray(truth["mag"], float), np.asarray(catalog["xwin"], float),
                           np.asarray(catalog["ywin"], float), det_mag, radius=radius, mag_tol=ctx.matching.mag_tol)
    dx, dy = np.asarray(catalog["xwin"], float), np.asarray(catalog["ywin"], float)
    cls = classify_detections(dx, dy, res.det_matched, kept_x=np.asarray(baseline["xwin"], float),
                              kept_y=np.asarray(baseline["ywin"], float), kept_segmentation=kept_segmentation,
                              radius=radius)
    flag = np.asarray(truth["flag"], dtype=np.int64)
    usable = ~np.asarray(truth["masked"], bool) & (flag == 0)
    # Light of an unusable injection (centre masked, stamp cut by the border) can still be detected,
    # with a magnitude spoiled by the mask; such detections are neither real false detections nor
    # countable matches, so they are left out of purity like pre-existing sources.
    near_unusable = classify_detections(dx, dy, res.det_matched, kept_x=np.asarray(truth["x"], float)[~usable],
                                        kept_y=np.asarray(truth["y"], float)[~usable], radius=radius).kept
    n = len(truth)
    out = truth.copy(copy_data=False)
    out.meta = {}  # per-realization facts (placement, timings) are not catalog columns
    if ctx.matching.exclude_clean_zone and ctx.detection.clean and n:
        # after the classes above: the injections left out here are real injections whose light and
        # detections are counted as before; only their outcome is not (docs/injection.md)
        cleaner_a = np.full(n, np.nan)
        cleaner_a[res.truth_index] = np.asarray(catalog["a"], float)[res.det_index]
        zone = in_clean_zone(np.asarray(truth["x"], float), np.asarray(truth["y"], float),
                             np.asarray(truth["flux"], float), cleaner_a, a_other=ctx.fwhm / FWHM_PER_SIGMA)
        out["flag"] = np.where(zone, flag | FLAG_CLEAN_ZONE, flag)
        out["flag"].description = truth["flag"].description
        usable = usable & ~zone
    out["usable"] = usable
    out["detected"] = res.det_of_truth >= 0
    sep = np.full(n, np.nan)
    sep[res.truth_index] = res.separation
    out["separation"] = sep
    out["separation"].unit = "pix"
    iy = np.clip(np.floor(np.asarray(truth["y"]) + 0.5).astype(int), 0, noise.shape[0] - 1)
    ix = np.clip(np.floor(np.asarray(truth["x"]) + 0.5).astype(int), 0, noise.shape[1] - 1)
    out["noise"] = noise[iy, ix].astype(float)
    for name in MEASURED:
        col = np.asarray(catalog[name])
        fill = -1 if col.dtype.kind in "iu" else np.nan
        values = np.full((n,) + col.shape[1:], fill, dtype=col.dtype if col.dtype.kind in "iu" else float)
        values[res.truth_index] = col[res.det_index]
        out[f"det_{name}"] = values
        if catalog[name].unit is not None:
            out[f"det_{name}"].unit = catalog[name].unit
    dets = catalog.copy(copy_data=False)
    dets.meta = {}
    dets["matched"] = res.det_matched
    # A realization may hold no injection at all (a small field at a low density draws zero from the
    # Poisson distribution): every detection is then unmatched, and there is no id to look up.
    ids = np.asarray(truth["injection_id"], dtype=np.int64)
    injection_id = np.full(len(catalog), -1, dtype=np.int64)
    hit = res.truth_of_det >= 0
    injection_id[hit] = ids[res.truth_of_det[hit]]
    dets["injection_id"] = injection_id
    dets["preexisting"] = cls.kept
    dets["near_unusable"] = near_unusable & ~cls.kept
    dets["false"] = cls.false & ~near_unusable
    return out, dets


def write_realization(result: RealizationResult, directory) -> Path:
    """Write one realization's two tables atomically as ``<kind>/rNNNNN.fits``."""

    path = realization_file(directory, result.kind, result.index)
    path.parent.mkdir(parents=True, exist_ok=True)
    hdus = fits.HDUList([fits.PrimaryHDU(), fits.table_to_hdu(result.truth), fits.table_to_hdu(result.detections)])
    hdus[1].name, hdus[2].name = "TRUTH", "DETECTIONS"
    for key, value in result.seconds.items():
        hdus[0].header[f"T_{key[:6].upper()}"] = (round(value, 4), f"seconds spent in {key}")
    with atomic_path(path) as tmp:
        hdus.writeto(tmp)
    return path


def _table_with_units(hdu) -> Table:
    """The rows of a realization's table HDU as they were written, with the column units (TUNITn) it carries."""
    table = Table(hdu.data)
    for col in hdu.columns:
        if col.unit:
            table[col.name].unit = col.unit
    return table


@dataclass(frozen=True)
class MergedCatalogs:
    """The tables of one kind over its realizations: what the recover stage hands to the ratios and the fits.

    Made by :func:`merge_realizations` (or :meth:`from_tables`).  The five catalogs of
    :data:`comest_bayes.io.layout.CATALOGS` are written as ``catalogs/<kind>_<name>.fits``
    (:meth:`table`); classes of detections and usable injections: ``docs/injection.md``.

    Attributes
    ----------
    injected : Table
        Every injection (truth rows with ``detected``, ``usable`` and the measured ``det_*`` columns).
    matched : Table
        The injections matched one to one to a detection.
    unmatched : Table
        The injections not detected.
    false : Table
        Detections matched to no injection, neither pre-existing nor near an unusable injection.
    outcomes : Table
        One row per usable injection with the columns of :data:`OUTCOME_COLUMNS`: what the
        completeness model fits.
    detections : Table
        Every detection of every realization (with ``matched``, ``preexisting``, ``near_unusable``,
        ``false``).
    seconds : dict
        Seconds the realizations spent per step (their ``T_*`` header cards, summed).
    """

    injected: Table
    matched: Table
    unmatched: Table
    false: Table
    outcomes: Table
    detections: Table
    seconds: dict = field(default_factory=dict)

    @classmethod
    def from_tables(cls, truth: Table, detections: Table, seconds: dict | None = None) -> "MergedCatalogs":
        """The catalogs of stacked truth and detection tables (as a realization writes them)."""
        detected = np.asarray(truth["detected"], bool)
        usable = np.asarray(truth["usable"], bool)
        keep = [c for c in OUTCOME_COLUMNS if c in truth.colnames]
        outcomes = truth[usable][keep]
        for name, desc in OUTCOME_COLUMNS.items():
            if name in outcomes.colnames:
                outcomes[name].description = desc
        return cls(injected=truth, matched=truth[detected], unmatched=truth[~detected],
                   false=detections[np.asarray(detections["false"], bool)], outcomes=outcomes,
                   detections=detections, seconds=dict(seconds or {}))

    def table(self, name: str) -> Table:
        """The catalog ``name`` (one of :data:`comest_bayes.io.layout.CATALOGS`)."""
        if name not in layout.CATALOGS:
            raise KeyError(f"no merged catalog {name!r}; the catalogs are {layout.CATALOGS}")
        return getattr(self, name)


def merge_realizations(directory, kind: str, indices) -> MergedCatalogs:
    """Read the realizations of one kind and build the four catalogs plus the outcome table."""
    truths, dets, seconds = [], [], {}
    for i in indices:
        path = realization_file(directory, kind, i)
        with fits.open(path) as hdul:
            truths.append(_table_with_units(hdul["TRUTH"]))
            dets.append(_table_with_units(hdul["DETECTIONS"]))
            for key, value in hdul[0].header.items():
                if key.startswith("T_"):
                    seconds[key[2:].lower()] = seconds.get(key[2:].lower(), 0.0) + float(value)
    truth = vstack(truths, metadata_conflicts="silent") if truths else Table()
    det = vstack(dets, metadata_conflicts="silent") if dets else Table()
    for t in (truth, det):
        for name in t.colnames:
            if t[name].dtype.kind == "S":
                t[name] = np.char.decode(t[name])
    return MergedCatalogs.from_tables(truth, det, seconds)
