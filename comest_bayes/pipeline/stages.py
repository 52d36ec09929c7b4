"""Orchestration: run the stages of the data flow into a run directory.

image -> detection -> seeing FWHM -> source-free (and BnB) image -> ...

Each stage is a call into a numerics module; this module only validates,
sequences, times, writes and resumes.  All input validation (files, header
facts, configuration, optional backends) happens before the run directory is
touched.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Callable
import json
import math

import numpy as np
from astropy.io import fits
from astropy.table import Table

from comest_bayes.config import RunConfig
from comest_bayes.detect.base import weight_agreement
from comest_bayes.detect.catalog import set_image_units
from comest_bayes.detect.sep_backend import DetectionResult, detect, filter_kernel, detect_with_backend
from comest_bayes.errors import ComestError, ConfigError, DetectionOverflowError, InputError
from comest_bayes.io.image import ImageData, load_image
from comest_bayes.io.rundir import RunDirectory, file_checksum, atomic_path
from comest_bayes.seeding import Stream, seed_sequence, int_seed_for
from comest_bayes.io.jsonio import dumps
from comest_bayes.io import layout
from comest_bayes.pipeline.preflight import SMALLEST_SEEING_PIX, budget_warnings, check_injection_count, check_memory, choose_densities, FEW_USABLE_INJECTIONS
from comest_bayes.pipeline.preflight import BRIGHT_NEIGHBOUR_WARN, bright_neighbours, choose_density
from comest_bayes.pipeline.preflight import CONFUSION_SPAN, confused_bright_end, footprint_cover
from comest_bayes.detect.psf import injection_psf, measure_seeing, BAD_FLAGS, point_size_check, select_stars
from comest_bayes.sourcefree import build_source_free, format_percent, judge_replacement
from comest_bayes.pipeline.executors import TaskRunner, run_tasks
from comest_bayes.detect.sextractor import find_sextractor
from comest_bayes.inject.cosmos import load_cosmos
from comest_bayes.bayes.spec import load_spec
from comest_bayes.inject.psfmodel import make_psf, psf_image_fwhm_pix
from comest_bayes.ratios.depth import isophote_radius_pix, noise_equivalent_area, point_source_depth_nea
from comest_bayes.ratios import binned as R
from comest_bayes.pipeline.progress import realization_with_warnings, FitProgress, describe_fit
from comest_bayes.recover.realization import RealizationTask, SimContext, merge_realizations, realization_file, write_realization
from comest_bayes.ratios.summary import SUMMARY_FORMAT, depth_summary, kind_binned, kind_summary, maps_hdulist
from comest_bayes.pipeline.adaptive import after_batch, check_recorded, package_fitter
from comest_bayes.inject.design import MagnitudeDesign, uniform_design
from comest_bayes.bayes.fit import footprint_grid, needs_smooth, shared_maps
from comest_bayes.pipeline.fits import FitFailure, fit_task, fit_tasks

__all__ = ["ImageOptions", "ComputeOptions", "RunResult", "run_pipeline", "output_header"]

#: The file injections are drawn on, by ``injection.on``.
_BASE_FILES = layout.BASE_IMAGES

#: Narrowest target PSF (FWHM, arcsec) COSMOS galaxies may be drawn with: the HST/ACS F814W PSF is
#: about 0.12" FWHM (Koekemoer et al. 2007) and must be deconvolved (GalSim RealGalaxy).
COSMOS_MIN_FWHM_ARCSEC = 0.15

#: The ratios stage warns when the brightest 0.5 mag of injections (at least BRIGHT_END_MIN_N of them)
#: is less complete than this: the injected range starts inside the transition, not on its plateau.
BRIGHT_END_MIN = 0.8
BRIGHT_END_MIN_N = 50

#: The run warns that a weight map may be of another type (--weight-type) when its sigma and the measured
#: background RMS rank the background meshes in opposite order: Spearman r at most minus this, p < 1e-3
#: (``detect.base.weight_agreement``).
WEIGHT_REVERSED_R = 0.3


@dataclass(frozen=True)
class ImageOptions:
    """Where the image is and the facts a user may give about it (see :func:`load_image`)."""

    path: str
    hdu: int | None = None
    zp: float | None = None
    pixel_scale: float | None = None
    fwhm: float | None = None
    gain: float | None = None
    saturation: float | None = None
    weight: str | None = None
    weight_type: str = "ivar"
    weight_hdu: int | None = None
    mask: str | None = None
    mask_hdu: int | None = None
    mask_bits: int | None = None

    def load(self) -> ImageData:
        """Read and validate the image and its companions (:func:`~comest_bayes.io.image.load_image`).

        A file astropy cannot decode (cut short, a corrupt header, a data
        size that does not match the header) raises
        :class:`~comest_bayes.errors.InputError` naming the file, whatever
        astropy raised, and astropy's own warnings about it become part of the
        message instead of lines of their own.
        """
        kw = asdict(self)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                image = load_image(kw.pop("path"), **kw)
            except ComestError:
                raise
            except (ValueError, TypeError, OSError, IndexError, KeyError, EOFError) as exc:
                role, path = self._unreadable()
                said = "; ".join(dict.fromkeys(" ".join(str(w.message).split()) for w in caught
                                               if "truncat" in str(w.message).lower()))
                raise InputError(
                    f"{role} file {path!r} cannot be read as FITS: {' '.join(str(exc).split()) or type(exc).__name__}"
                    + (f" ({said})" if said else "") + ". Is the file complete (an interrupted copy or download)?"
                ) from None
        for w in caught:  # not about a failure: show them as they came
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
        return image

    def _unreadable(self) -> tuple[str, str]:
        """(role, path) of the first input whose HDUs' data cannot all be read (the image when none fails)."""
        for role, path in (("image", self.path), ("weight", self.weight), ("mask", self.mask)):
            if path is None:
                continue
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    with fits.open(path, memmap=False, lazy_load_hdus=False) as hdul:
                        for hdu in hdul:
                            _ = hdu.data
            except Exception:  # whatever astropy raises marks the culprit
                return role, str(path)
        return "image", str(self.path)

    def located(self) -> dict:
        """The options with the input files' resolved absolute paths (where this run found them)."""
        return {k: (str(Path(v).resolve()) if k in ("path", "weight", "mask") and v is not None else v)
                for k, v in asdict(self).items()}

    def fingerprint(self) -> dict:
        """Options plus the checksum of every input file.

        Files are identified by their content (SHA-256) and name, not by the
        path as typed: ``./in/image.fits``, ``/data/in/image.fits`` and the
        same file moved to another folder name the same run.
        """
        out = {"options": {k: (Path(v).name if k in ("path", "weight", "mask") and v is not None else v)
                           for k, v in asdict(self).items()}, "files": {}}
        for role in ("path", "weight", "mask"):
            value = getattr(self, role)
            if value is not None:
                out["files"][role] = {"name": Path(value).name, "sha256": file_checksum(value)}
        return out


@dataclass
class RunResult:
    """What :func:`run_pipeline` produced."""

    out_dir: Path
    image: ImageData
    detection: DetectionResult
    fwhm: dict
    resumed: bool
    timings: dict
    summary: dict | None = None


@dataclass(frozen=True)
class ComputeOptions:
    """Where realizations run; results do not depend on these (so they are not part of a run's identity).

    executor : {"serial", "processes", "dask"}; workers : local processes; scheduler : a Dask
    scheduler address (``dask`` only; default a local cluster); progress : show a progress bar.
    """

    executor: str = "processes"
    workers: int = 1
    scheduler: str | None = None
    progress: bool = False
    #: An open :class:`~comest_bayes.pipeline.executors.TaskRunner` the stages share (set by the pipeline).
    runner: Any = field(default=None, compare=False, repr=False)

    def describe(self) -> str:
        if self.executor == "dask":
            return f"Dask ({self.scheduler or f'local cluster of {self.workers} workers'})"
        if self.executor == "processes" and self.workers > 1:
            return f"{self.workers} local processes"
        return "1 process"


def output_header(image: ImageData, extra: dict | None = None, *, image_units: bool = False) -> fits.Header:
    """Header for an output image: the input's WCS plus provenance keywords.

    ``image_units=True`` (an image in the input's pixel unit: the source-free
    and bright-and-big images, the background, RMS and noise maps) also
    carries the input's ``BUNIT`` when it has one.
    """
    header = fits.Header()
    if image.wcs is not None:
        header.update(image.wcs.to_header(relax=True))
    if image_units and image.bunit:
        header["BUNIT"] = (str(image.bunit), "pixel unit, as in the input image")
    header["MAGZERO"] = (image.zeropoint, "photometric zero point (mag)")
    header["ORIGIN"] = "comest-bayes"
    for key, value in (extra or {}).items():
        header[key] = value
    return header


def _load_detection(run: RunDirectory, image: ImageData) -> DetectionResult:
    cat = Table.read(run.file(layout.DETECTION))
    info = run.stage_info("detect")
    arrays = {name: fits.getdata(run.file(file)) for name, file in (("segmentation", layout.SEGMENTATION),
                                                                   ("background", layout.BACKGROUND),
                                                                   ("rms", layout.RMS), ("noise", layout.NOISE))}
    return DetectionResult(catalog=cat, segmentation=arrays["segmentation"].astype(np.int32),
                           background=arrays["background"].astype(np.float32),
                           rms=arrays["rms"].astype(np.float32), noise=arrays["noise"].astype(np.float32),
                           meta=info.get("meta", {}))


def run_pipeline(options: ImageOptions, config: RunConfig, out_dir, *,
                 log: Callable[[str], None] = print, compute: ComputeOptions | None = None,
                 fwhm_fallback: tuple[float, str] | None = None) -> RunResult:
    """Run every stage on one image, resuming a matching run in ``out_dir``.

    Parameters
    ----------
    options : ImageOptions
        The input image and the facts given about it.
    config : RunConfig
        Resolved configuration (seed included).
    out_dir : str or Path
        Run directory (see :class:`~comest_bayes.io.rundir.RunDirectory`).
    log : callable
        Receives one human-readable line per stage.
    compute : ComputeOptions, optional
        Executor for the realizations (default: one local process).
    fwhm_fallback : (float, str), optional
        Seeing FWHM in pixels, and where it comes from, used when it cannot
        be measured on the image (the demo knows its own seeing).

    Returns
    -------
    RunResult

    Raises
    ------
    ComestError
        Before anything is written, for every input that cannot give an
        answer (see :mod:`comest_bayes.pipeline.preflight`); a directory in use by a
        live run is refused with its holder named.
    """
    opened: list[RunDirectory] = []
    try:
        return _run_pipeline(options, config, out_dir, log=log, compute=compute, fwhm_fallback=fwhm_fallback,
                             opened=opened)
    finally:
        for run in opened:
            run.release()


def _run_pipeline(options: ImageOptions, config: RunConfig, out_dir, *, log, compute, fwhm_fallback,
                  opened: list) -> RunResult:

    # ---- validation: nothing is written before all of this passes -------------
    image = options.load()
    log(image.gain_summary())  # which gain sets the injections' photon noise, and why (run.json: image.gain_decision)
    # injections too few to give an answer, before the detection (the count without stamps)
    check_injection_count(shape=image.shape, mask=image.mask, pixel_scale=image.pixel_scale, fwhm_pix=None,
                          injection=config.injection,
                          densities=choose_densities(shape=image.shape, pixel_scale=image.pixel_scale, fwhm_pix=None,
                                                     injection=config.injection, back_size=config.detection.back_size))
    filter_kernel(config.detection.filter)
    if config.detection.backend == "sextractor":

        find_sextractor()
    if "cosmos" in config.injection.kinds:

        load_cosmos(config.injection)  # a missing or broken catalog directory is an error now, not later
    if config.injection.psf not in ("moffat", "gaussian", "kolmogorov") and not Path(config.injection.psf).is_file():
        raise ConfigError(f"injection.psf={config.injection.psf!r} is neither moffat, gaussian, kolmogorov nor an "
                          f"existing FITS PSF image.")
    if config.injection.on == "bnb" and not config.sourcefree.bnb:
        raise ConfigError("injection.on='bnb' needs the bright-and-big image, which sourcefree.bnb=false (--no-bnb) "
                          "does not make; set sourcefree.bnb=true or injection.on='sfi' or 'observed'.")
    if config.fit.model != "none":

        load_spec(config.fit.model)  # an unknown model name is an error now, not after the injections
        if config.fit.purity_model != "none":
            load_spec(config.fit.purity_model)
    fingerprint = {"input": options.fingerprint(), "config": config.to_dict()}
    run = RunDirectory(out_dir, fingerprint)
    run.check()  # read-only: new run, resume, or refusal (in use, another run, not writable)
    timings = {}
    header = output_header(image)

    # ---- detection and seeing: measured before anything is written, so that an image whose
    # seeing cannot be measured leaves no run behind (the user reruns with --fwhm) ------------
    det = None
    det_seconds = None
    if not run.stage_done("detect"):
        t0 = time.perf_counter()
        try:
            det = detect(image, config.detection, workdir=None)
        except DetectionOverflowError as exc:
            raise DetectionOverflowError(f"{image.path}: {exc}") from None
        det_seconds = time.perf_counter() - t0
    # ---- seeing and injection PSF: the stars are fitted even when the FWHM is given (for their
    # beta); when they cannot be, the header's seeing keywords are the fallback ------------------
    fwhm_seconds = None
    if run.stage_done("fwhm") and "psf" in run.stage_info("fwhm"):
        fwhm = run.stage_info("fwhm")["estimate"]
        psf_choice = run.stage_info("fwhm")["psf"]
    else:
        if det is None:
            det = _load_detection(run, image)
        t0 = time.perf_counter()
        if fwhm_fallback is None:
            # an injection PSF image the user gave: its FWHM when neither the stars nor the header give one
            psf_fwhm = psf_image_fwhm_pix(config.injection, image.pixel_scale)
            if psf_fwhm is not None:
                fwhm_fallback = (psf_fwhm, f"the FWHM of the injection PSF image {config.injection.psf} "
                                           "(injection.psf), as the stars and header gave none")
        try:
            fwhm = measure_seeing(image.data - det.background, det.catalog, mask=image.mask,
                                  saturation_flagged=image.saturation is not None, headers=_headers(image),
                                  pixel_scale=image.pixel_scale, user_fwhm=image.fwhm, fallback=fwhm_fallback)
        except InputError:
            # an image too small for any injection says so, rather than that its seeing is unknown
            check_injection_count(shape=image.shape, mask=image.mask, pixel_scale=image.pixel_scale,
                                  fwhm_pix=SMALLEST_SEEING_PIX, injection=config.injection, fwhm_assumed=True)
            raise
        psf_choice = injection_psf(config.injection, fwhm, pixel_scale=image.pixel_scale)
        fwhm_seconds = time.perf_counter() - t0

    fwhm_arcsec = float(fwhm["fwhm"]) * image.pixel_scale
    if "cosmos" in config.injection.kinds and fwhm_arcsec < COSMOS_MIN_FWHM_ARCSEC:
        raise ConfigError(
            f"injection kind 'cosmos' cannot be drawn on this image: COSMOS galaxies are HST/ACS F814W images "
            f"whose own PSF (FWHM about 0.12\") must be deconvolved, so the target PSF must be broader than "
            f"{COSMOS_MIN_FWHM_ARCSEC}\" but this image's FWHM is {fwhm_arcsec:.3f}\". Use the sersic or buldisk kinds.")

    # ---- the injections can give an answer, in the memory there is ------------------------
    # how many injections per realization: the user's density, or chosen per kind from the image
    densities = choose_densities(shape=image.shape, pixel_scale=image.pixel_scale, fwhm_pix=float(fwhm["fwhm"]),
                                 injection=config.injection, back_size=config.detection.back_size)
    # the magnitude range: the user's, or from the depth (brighter on a confused field); a resumed run keeps its own
    if run.stage_done("baseline"):
        mag_range = tuple(run.stage_info("baseline")["mag_range"])
        range_record = (run.stage_info("baseline").get("range")
                        or {"rule": "user" if config.injection.mag_range else "m5"})
    else:
        if det is None:
            det = _load_detection(run, image)
        mag_range, range_record = _injection_range(config, image, det, psf_choice, float(fwhm["fwhm"]))
    _check_precision_magnitudes(config, mag_range)  # before anything is written: a typo must not leave a run
    # the injections of a range far brighter than the detection limit keep the brightest one's reach apart
    if config.injection.min_sep <= 0 and range_record["rule"] != "m5":
        if det is None:
            det = _load_detection(run, image)
        radius_at = _isophote_radii(config, image, det, psf_choice, float(fwhm["fwhm"]))
        for kind, choice in list(densities.items()):
            sep = _bright_separation(image, choice, mag_range, radius_at)
            if sep is not None:
                densities[kind] = _separated_choice(kind, choice, sep, config, image, float(fwhm["fwhm"]))
    budgets = check_injection_count(shape=image.shape, mask=image.mask, pixel_scale=image.pixel_scale,
                                    fwhm_pix=float(fwhm["fwhm"]), injection=config.injection,
                                    fwhm_given=image.fwhm is not None, densities=densities)
    compute = compute or ComputeOptions()
    check_memory(budgets, npix=int(np.prod(image.shape)),
                 nsims=config.adaptive.max_nsims if config.adaptive.enabled else config.injection.nsims,
                 workers=compute.workers if compute.executor != "serial" else 1)

    # ---- the source-free image, judged before anything is written: where it would replace most
    # of the image (a crowded field), the run is refused with the alternatives ------------------
    sf = replacement = None
    if not run.stage_done("sourcefree"):
        if det is None:
            det = _load_detection(run, image)
        t0 = time.perf_counter()
        sf = build_source_free(image.data, det, mask=image.mask, fwhm=float(fwhm["fwhm"]), config=config.sourcefree,
                               seed=seed_sequence(config.seed, Stream.SOURCEFREE))
        sf_seconds = time.perf_counter() - t0
        replacement = judge_replacement(sf.meta, on=config.injection.on, warn_fraction=config.sourcefree.warn_replaced,
                                        max_fraction=config.sourcefree.max_replaced)
        if replacement["refusal"]:
            raise InputError(replacement["refusal"])

    run.open()
    opened.append(run)
    if run.lock_note:
        log(f"note: {run.lock_note}")
    if run.resumed:
        log(f"resuming the run in {run.path} (finished stages are skipped)")
    if det_seconds is not None:
        if image.noise is not None:
            agree = weight_agreement(image.noise, det.rms, image.mask, config.detection.back_size)
            if agree is not None:
                agree["warning"] = _reversed_weight(agree, options.weight_type)
            det.meta["weight_agreement"] = agree
        files = [run.write_table(layout.DETECTION, set_image_units(det.catalog, image.bunit), extname="DETECTIONS")]
        files.append(run.write_image(layout.SEGMENTATION, det.segmentation, header))
        for name, file in (("background", layout.BACKGROUND), ("rms", layout.RMS), ("noise", layout.NOISE)):
            files.append(run.write_image(file, getattr(det, name), output_header(image, image_units=True)))
        run.record_stage("detect", files=files, seconds=det_seconds, meta=det.meta, nsources=len(det.catalog))
        if det.meta.get("backend") == "sextractor":  # the binary is software of the run too (its version, path)
            run.update(versions={**(run.state.get("versions") or {}), "source-extractor": det.meta.get("sexver"),
                                 "source-extractor path": find_sextractor()})
        log(f"detect: {len(det.catalog)} sources with {config.detection.backend} "
            f"(threshold {config.detection.thresh} x {det.meta.get('noisemod', 'sigma')} noise) in {det_seconds:.1f} s")
    else:
        if det is None:
            det = _load_detection(run, image)
        log(f"detect: done earlier ({len(det.catalog)} sources)")
    timings["detect"] = run.stage_info("detect").get("seconds")
    agree = (run.stage_info("detect").get("meta") or {}).get("weight_agreement") or {}
    if agree.get("warning"):
        log(f"warning: weight map: {agree['warning']}")
    if fwhm_seconds is not None:
        run.record_stage("fwhm", seconds=fwhm_seconds, estimate=fwhm, psf=psf_choice)
    image.fwhm = float(fwhm["fwhm"])
    image.provenance.setdefault("fwhm", fwhm["method"])
    log(f"fwhm: {image.fwhm:.2f} px = {image.fwhm * image.pixel_scale:.2f} arcsec ({fwhm['method']})")
    log(f"psf: injecting a {psf_choice['description']}; FWHM: {psf_choice['fwhm_source']}"
        + (f"; beta: {psf_choice['beta_source']}" if psf_choice.get("beta_source") else ""))
    for line in psf_choice["warnings"]:
        log(f"warning: psf: {line}")
    # the injection range and density per kind, and why (the injection stage reads them back from run.json)
    run.update(injection_range={"mag_range": list(mag_range), **range_record},
               injection_density={kind: choice.to_dict() for kind, choice in densities.items()})
    if range_record.get("rule") == "confused":
        log(f"range: {range_record['reason']}")
    for kind, choice in densities.items():
        log(f"density: {kind}: {choice.reason}")
        if choice.warning:
            log(f"warning: density: {kind}: {choice.warning}")
    for line in budget_warnings(budgets, config.adaptive.max_nsims if config.adaptive.enabled
                                else config.injection.nsims):
        log(f"warning: density: {line}")
    # where the inputs are now (the fingerprint names them by content): the report reopens them from here
    run.update(image=image.facts(), psf=psf_choice, input_options=options.located())

    # ---- source-free and bright-and-big images (built above) ----------------------------
    if sf is None:
        log("sourcefree: done earlier")
    else:
        files = [run.write_image(layout.SFI, sf.sfi, output_header(image, {"IMAGETYP": "source-free"},
                                                                   image_units=True))]
        if sf.bnb is not None:
            files.append(run.write_image(layout.BNB, sf.bnb, output_header(image, {"IMAGETYP": "bright-and-big"},
                                                                           image_units=True)))
        if config.injection.on == "observed":  # the base of the injections, read like the others
            files.append(run.write_image(layout.OBSERVED, image.data.astype(np.float32),
                                         output_header(image, {"IMAGETYP": "observed"}, image_units=True)))
        run.record_stage("sourcefree", files=files, seconds=sf_seconds, meta=sf.meta, kept_ids=sf.kept_ids,
                         replacement=replacement)
        bnb_frac = sf.meta.get("bnb_fraction_replaced")
        log(f"sourcefree: replaced {format_percent(sf.meta['fraction_replaced'])} of the unmasked pixels"
            + (f"; BnB keeps {len(sf.kept_ids)} sources (replaces {format_percent(bnb_frac)})" if sf.bnb is not None
               else "") + f" in {sf_seconds:.1f} s; injecting on {_BASE_FILES[config.injection.on]}")
    for line in (run.stage_info("sourcefree").get("replacement") or {}).get("warnings", []):
        log(f"warning: sourcefree: {line}")
    timings["sourcefree"] = run.stage_info("sourcefree").get("seconds")

    # ---- injection and recovery, then the fits: one set of workers for every batch of tasks ----

    with TaskRunner(compute.executor, compute.workers, compute.scheduler) as runner:
        summary = _injection_stages(run, image, det, config, replace(compute, runner=runner), log, timings)

    # a resumed run keeps the times of the stages it did not redo
    run.update(timings={**run.state.get("timings", {}), **timings})
    return RunResult(out_dir=run.path, image=image, detection=det, fwhm=fwhm, resumed=run.resumed, timings=timings,
                     summary=summary)


def _check_precision_magnitudes(config: RunConfig, mag_range) -> None:
    """The magnitudes of ``--precision-at`` must lie inside the injected range (else ConfigError)."""
    ad = config.adaptive
    lo, hi = float(mag_range[0]), float(mag_range[1])
    mags = [float(m) for m in ad.magnitudes]
    if ad.enabled and ad.target == "f" and not all(lo <= m <= hi for m in mags):
        raise ConfigError(f"adaptive.magnitudes {mags} (--precision-at) must lie inside the injected "
                          f"range [{lo:.2f}, {hi:.2f}] mag: no injection can make f precise outside it. Choose "
                          "magnitudes inside it or widen injection.mag_range.")


def _reversed_weight(agree: dict, weight_type: str) -> str | None:
    """The warning for a weight map whose sigma ranks the background meshes against the measured RMS, or None."""
    if not (agree["spearman"] <= -WEIGHT_REVERSED_R and agree["p"] < 1e-3):
        return None
    return (f"the noise it implies as {weight_type} falls where the image's measured background RMS rises "
            f"(Spearman r = {agree['spearman']:.2f} over {agree['meshes']} background meshes), as a weight map "
            "of another type would: pass --weight-type rms for 1-sigma errors, var for variances, ivar for "
            "inverse variances")


def _headers(image: ImageData) -> list:
    """The image HDU's header, then the primary header when the image sits in an extension."""
    headers = [image.header]
    if image.hdu and image.path:
        try:
            headers.append(fits.getheader(image.path, 0))
        except (OSError, IndexError, ValueError):  # the image was read; a broken primary header is no error
            pass
    return headers


def _injection_psf_profile(config: RunConfig, image: ImageData, psf_choice: dict | None, fwhm: float | None = None):
    """The GalSim profile (arcsec) the injections use, as decided by :func:`comest_bayes.detect.psf.injection_psf`
    (``fwhm`` in pixels, default ``image.fwhm``)."""

    psf_choice = psf_choice or {}
    return make_psf(config.injection, image.fwhm if fwhm is None else fwhm, image.pixel_scale, beta=psf_choice.get("beta"),
                    pixel_integrated=bool(psf_choice.get("pixel_integrated", False)))


def _psf_nea(config: RunConfig, image: ImageData, psf_choice: dict | None = None, fwhm: float | None = None) -> float:
    """Noise-equivalent area (pixels) of the injection PSF on the image's pixel grid (``fwhm`` as
    :func:`_injection_psf_profile` takes it)."""

    psf = _injection_psf_profile(config, image, psf_choice, fwhm)
    return noise_equivalent_area(psf.drawImage(nx=64, ny=64, scale=image.pixel_scale, method="no_pixel").array)


def _auto_mag_range(image: ImageData, det: DetectionResult, nea: float) -> tuple[tuple[float, float], dict]:
    """(m5 - 5, m5 + 1.5) around the 5-sigma point-source depth of the median noise, and how it was chosen.

    On a confused field (the detected sources of the range's first 2 mag cover more than
    ``CONFUSION_RISE`` of the image, :func:`confused_bright_end`) the range starts brighter, where the
    sources brighter than it cover ``CONFUSION_COVER``: the completeness falls from far above m5 there,
    and a range from m5 - 5 would never see its plateau.  The record holds ``rule`` ("m5" or
    "confused"), ``m5``, ``confusion_rise`` and, when confused, ``usual_bright`` and ``cover_bright``.
    """

    sigma = float(np.median(det.noise[~image.mask]))
    m5 = point_source_depth_nea(sigma, image.zeropoint, nea, 5.0)
    lo, hi = round(m5 - 5.0, 2), round(m5 + 1.5, 2)
    record = {"rule": "m5", "m5": round(float(m5), 3)}
    if det.segmentation is not None and len(det.catalog) and "mag_auto" in det.catalog.colnames:
        mag, share = footprint_cover(det.segmentation, det.catalog["id"], det.catalog["mag_auto"], image.mask)
        conf = confused_bright_end(mag, share, lo)
        record["confusion_rise"] = round(conf["rise"], 4)
        if conf["confused"]:
            record.update(rule="confused", usual_bright=lo, cover_bright=round(conf["cover_bright"], 4))
            lo = round(conf["bright"], 2)
    return (lo, hi), record


def _injection_range(config: RunConfig, image: ImageData, det: DetectionResult, psf_choice: dict | None,
                     fwhm: float) -> tuple[tuple[float, float], dict]:
    """The magnitude range of the injections and how it was chosen (``rule`` "user", "m5" or "confused");
    ``fwhm`` (pixels) of the injection PSF (measured before ``image.fwhm`` is set)."""
    if config.injection.mag_range:
        return (tuple(float(v) for v in config.injection.mag_range),
                {"rule": "user", "reason": "injection.mag_range as set"})
    mag_range, record = _auto_mag_range(image, det, _psf_nea(config, image, psf_choice, fwhm))
    record["reason"] = _range_reason(mag_range, record)
    return mag_range, record


def _range_reason(mag_range, record: dict) -> str:
    """Why the automatic range is what it is (for a confused field, the text of its log line)."""
    if record.get("rule") != "confused":
        return f"m5 - 5 to m5 + 1.5 around the 5-sigma point-source depth m5 = {record['m5']:.2f} of the injection PSF"
    return (f"a confused field: the sources detected at {record['usual_bright']:.2f}-"
            f"{record['usual_bright'] + CONFUSION_SPAN:.2f} mag (m5 - 5 and the next {CONFUSION_SPAN:g} mag) cover "
            f"{100 * record['confusion_rise']:.1f}% of the image, so injections there land on sources as bright as "
            f"themselves and the completeness falls from the first magnitude; the injections start at "
            f"{mag_range[0]:.2f} mag instead, where brighter sources cover {100 * record['cover_bright']:.0f}% "
            f"(docs/injection.md; set injection.mag_range to choose)")


def _isophote_radii(config: RunConfig, image: ImageData, det: DetectionResult, psf_choice: dict | None,
                    fwhm: float | None = None):
    """``radius_at(mags)``: detection isophote radii (pixels) of point injections of these magnitudes.

    The injection PSF (of ``fwhm`` pixels, default ``image.fwhm``) filtered with the detection
    kernel, at the detection threshold on the median detection noise
    (:func:`comest_bayes.ratios.depth.isophote_radius_pix`).
    """
    fwhm = float(image.fwhm if fwhm is None else fwhm)
    sigma = float(np.median(det.noise[~image.mask]))
    size = int(min(401, max(65, 2 * math.ceil(15.0 * fwhm) + 1)))
    psf = _injection_psf_profile(config, image, psf_choice, fwhm).drawImage(nx=size, ny=size, scale=image.pixel_scale,
                                                                            method="no_pixel").array
    kernel = filter_kernel(config.detection.filter)

    def radius_at(mags):
        return isophote_radius_pix(psf, 10.0 ** (-0.4 * (np.asarray(mags) - image.zeropoint)), sigma,
                                   config.detection.thresh, kernel)

    return radius_at


def _bright_separation(image: ImageData, choice, mag_range, radius_at) -> float | None:
    """A kind's separation (arcsec) for a range far brighter than the detection limit, or None.

    ``radius_at``: the point injections' detection isophote radii (:func:`_isophote_radii`).

    The caller asks only for an automatic separation (``injection.min_sep = 0``) and a range the
    user set or a confused field's (the usual automatic range, from m5 - 5, puts about 0.01% of the
    injections within a brighter one's reach): when more than ``BRIGHT_NEIGHBOUR_WARN`` of them
    would be, the separation becomes the reach of the brightest injection, as a point source.  For
    the sized kinds that reach is an estimate (a bright galaxy's isophote is usually the larger),
    and their separation never falls below their largest pair's (``choice.min_sep_pix``).
    """
    rec = bright_neighbours(mag_range, choice.per_realization, float((~image.mask).sum()), choice.min_sep_pix,
                            radius_at)
    if rec["fraction"] <= BRIGHT_NEIGHBOUR_WARN:
        return None
    # galaxies: the point source's reach estimates theirs; never closer than their largest pair was
    return round(max(rec["reach_bright"], choice.min_sep_pix) * image.pixel_scale, 4)


def _separated_choice(kind: str, choice, sep: float, config: RunConfig, image: ImageData, fwhm: float):
    """The density choice of ``kind`` with every pair kept ``sep`` arcsec apart (:func:`_bright_separation`)."""
    wide = choose_density(kind, shape=image.shape, pixel_scale=image.pixel_scale, fwhm_pix=fwhm,
                          injection=replace(config.injection, min_sep=sep), back_size=config.detection.back_size)
    usual = "4 FWHM" if kind == "point" else "each pair's size-based separation"
    return replace(wide, min_sep_arcsec=sep, sizing={
        **(wide.sizing or {}), "separation": f"{sep:.3g}\" between all pairs: the reach of the range's brightest "
                                             f"point source (twice its detection isophote's radius)"},
        reason=(f"{wide.reason}; separation {sep:.3g}\" ({sep / image.pixel_scale:.1f} px) instead of {usual}: the "
                f"range's brightest injections reach that far above the detection threshold, and a fainter one "
                f"nearer is lost in them (docs/injection.md)"))


def _bright_neighbour_check(config: RunConfig, image: ImageData, det: DetectionResult, psf_choice: dict | None,
                            mag_range, choice: dict | None) -> tuple[dict | None, str | None]:
    """:func:`bright_neighbours` of the point injections of a run, and the warning when their share is large.

    Returns ``(record, warning or None)``; ``(None, None)`` without point injections or a density
    choice.  With the separation :func:`_bright_separation` chose, the share is near 0; the warning
    is left for a separation the user set too small.
    """
    if "point" not in config.injection.kinds or not choice:
        return None, None
    rec = bright_neighbours(mag_range, float(choice["per_realization"]), float((~image.mask).sum()),
                            float(choice["min_sep_pix"]), _isophote_radii(config, image, det, psf_choice))
    if rec["fraction"] <= BRIGHT_NEIGHBOUR_WARN:
        return rec, None
    sep_arcsec = rec["reach_bright"] * image.pixel_scale
    return rec, (f"point injections brighter than {rec['mag_reach']:.1f} mag spread above the detection threshold "
                 f"over more than half their {rec['min_sep_pix']:.1f} px separation (the brightest, "
                 f"{mag_range[0]:.2f} mag, over {rec['radius_bright']:.1f} px), and a fainter injection that close is "
                 f"usually lost in them: about {100 * rec['fraction']:.0f}% of the injections are expected that "
                 f"close to a brighter one, which lowers the completeness measured; keep them apart with "
                 f"--set injection.min_sep={sep_arcsec:.3g} (arcsec), or inject fainter (injection.mag_range)")


def _injection_stages(run: RunDirectory, image: ImageData, det: DetectionResult, config: RunConfig,
                      compute: "ComputeOptions", log, timings: dict) -> dict:

    inj = config.injection
    psf_choice = run.state.get("psf") or {}
    base_name = _BASE_FILES[inj.on]
    if not run.file(base_name).exists():
        raise ConfigError(f"injection.on={inj.on!r} needs {base_name}, which this run did not make; "
                          f"set sourcefree.bnb=true or injection.on='sfi'.")
    header = output_header(image)

    # ---- baseline: what the detector finds on the bare base image ------------------
    if not run.stage_done("baseline"):
        t0 = time.perf_counter()
        base = fits.getdata(run.file(base_name)).astype(np.float32)
        fixed = config.detection.noise_level == "observed"  # the injected images' threshold noise, as observed
        weight_noise = det.noise if det.meta.get("noisemod") == "weight" and not fixed else None
        bdet = _observed_baseline(image, det, base, weight_noise, inj.on, fixed=fixed) \
            if config.detection.background_level == "per_image" else None
        reused = bdet is not None
        if not reused:
            observed_back = config.detection.background_level == "observed"
            bdet = detect_with_backend(base, mask=image.mask, weight_noise=weight_noise, zeropoint=image.zeropoint,
                                       gain=image.gain, saturation=image.saturation, wcs=image.wcs,
                                       config=config.detection, threshold_noise=det.noise if fixed else None,
                                       threshold_background=det.background if observed_back else None)
        files = [run.write_table(layout.BASELINE, set_image_units(bdet.catalog, image.bunit)),
                 run.write_image(layout.MASK, image.mask.astype(np.uint8), header)]
        # On the observed image the baseline holds every real source, and on a crowded one the re-detection of
        # a realization splits, merges and shifts their blends: an unmatched detection whose centre lies in a
        # baseline source's footprint is that source, not a false detection (docs/injection.md).
        footprints = None
        if inj.on == "observed":
            footprints = layout.SEGMENTATION if reused else layout.BASELINE_SEGMENTATION
            if not reused:
                files.append(run.write_image(layout.BASELINE_SEGMENTATION, bdet.segmentation.astype(np.int32), header))
        # the range the run chose before its first byte (_run_pipeline records it at every start)
        range_record = dict(run.state["injection_range"])
        mag_range = tuple(range_record.pop("mag_range"))
        reach, reach_warning = _bright_neighbour_check(config, image, det, psf_choice, mag_range,
                                                       (run.state.get("injection_density") or {}).get("point"))
        run.record_stage("baseline", files=files, seconds=time.perf_counter() - t0, nsources=len(bdet.catalog),
                         mag_range=list(mag_range), range=range_record, base=base_name, reused_detection=reused,
                         preexisting_footprints=footprints,
                         bright_neighbours=None if reach is None else {**reach, "warning": reach_warning})
        log(f"baseline: {len(bdet.catalog)} sources detected on the bare {base_name} "
            + ("(the first detection's, on the same pixels and noise) " if reused else "")
            + f"(counted as pre-existing, not false); injections span {mag_range[0]:.2f}-{mag_range[1]:.2f} mag")
        if reach_warning:
            log(f"warning: injection: {reach_warning}")
    mag_range = tuple(run.stage_info("baseline")["mag_range"])
    timings["baseline"] = run.stage_info("baseline").get("seconds")

    ctx = SimContext(
        base_path=str(run.file(base_name)), mask_path=str(run.file(layout.MASK)), noise_path=str(run.file(layout.NOISE)),
        baseline_path=str(run.file(layout.BASELINE)), detection_path=str(run.file(layout.DETECTION)),
        shape=tuple(image.shape), wcs_header=None if image.wcs is None else image.wcs.to_header(relax=True).tostring(),
        zeropoint=image.zeropoint, gain=image.gain, saturation=image.saturation, pixel_scale=image.pixel_scale,
        fwhm=float(image.fwhm), mag_range=mag_range, noise_mode=str(det.meta.get("noisemod", "background")), detection=config.detection, injection=inj,
        matching=config.matching, root_seed=config.seed,
        image_dir=str(run.file(layout.SIMS_DIR)) if inj.write_images else None,
        psf_beta=float(psf_choice.get("beta") or 0.0),
        psf_pixel_integrated=bool(psf_choice.get("pixel_integrated", False)),
        background_path=str(run.file(layout.BACKGROUND)),
        baseline_segmentation_path=str(run.file(run.stage_info("baseline")["preexisting_footprints"]))
        if run.stage_info("baseline").get("preexisting_footprints") else "")
    ctx = _contexts_by_kind(ctx, run.state.get("injection_density") or {})

    sims = run.file(layout.SIMS_DIR)
    for stale in sims.glob("*/.tmp-*"):  # a killed run's half-written realization files
        stale.unlink()
    failures: list[str] = []
    cpu = {"inject": 0.0}
    nsims = {kind: inj.nsims for kind in inj.kinds}
    adaptive_summary = None
    design_maps = {}  # the adaptive design's pass over the maps, which the fit stage reuses
    if config.adaptive.enabled:
        t0 = time.perf_counter()
        earlier = sum(1 for kind in inj.kinds for _ in sims.glob(layout.realization_glob(kind)))
        nsims, adaptive_summary = _adaptive_injection(run, ctx, config, compute, log, det.noise, image.mask,
                                                      mag_range, cpu, maps_out=design_maps)
        timings["inject"] = round(time.perf_counter() - t0, 3)
        timings["inject_cpu"] = round(cpu["inject"], 3)
        timings["design_fit_cpu"] = round(cpu.get("design_fit", 0.0), 3)
    todo = [RealizationTask(ctx[kind], kind, i) for kind in inj.kinds for i in range(nsims[kind])
            if not realization_file(sims, kind, i).exists()]
    ndone = sum(nsims.values()) - len(todo)
    if todo:
        t0 = time.perf_counter()
        log(f"inject: {len(todo)} realizations to run ({ndone} done earlier) of kinds {', '.join(inj.kinds)} "
            f"on {compute.describe()}")

        def failed(name, last_line):
            failures.append(name)
            log(f"warning: realization {name} failed; it will be retried on the next run:\n{last_line}")

        on_result = _realization_recorder(sims, cpu, log, set(), failed)

        run_tasks(realization_with_warnings, todo, on_result=on_result, executor=compute.executor,
                  workers=compute.workers, scheduler=compute.scheduler, progress=compute.progress,
                  runner=compute.runner, desc="realizations")
        timings["inject"] = round(time.perf_counter() - t0, 3)
        timings["inject_cpu"] = round(cpu["inject"], 3)
        log(f"inject: {len(todo) - len(failures)} realizations in {timings['inject']:.1f} s"
            + (f"; {len(failures)} failed" if failures else ""))
    elif adaptive_summary is not None:
        log(f"inject: {ndone} realizations in adaptive batches ("
            + ", ".join(f"{k} {n}" for k, n in nsims.items()) + f") in {timings['inject']:.1f} s"
            + (f" ({earlier} done earlier)" if earlier else ""))
    else:
        log(f"inject: all {ndone} realizations done earlier")

    # ---- merge, ratios, summary --------------------------------------------------------
    t0 = time.perf_counter()
    edges = R.magnitude_edges(mag_range[0], mag_range[1], config.ratios.mag_bin)
    kinds = {}
    run.file(layout.CATALOG_DIR).mkdir(exist_ok=True)
    run.file(layout.MAPS_DIR).mkdir(exist_ok=True)
    stage_seconds = {}
    for kind in inj.kinds:
        done = [i for i in range(nsims[kind]) if realization_file(sims, kind, i).exists()]
        if not done:
            log(f"warning: no realization of kind {kind!r} finished; it is left out of {layout.SUMMARY}")
            continue
        merged = merge_realizations(sims, kind, done)
        stage_seconds[kind] = merged.seconds
        for name in layout.CATALOGS:
            run.write_table(layout.catalog(kind, name), set_image_units(merged.table(name), image.bunit))
        comp = kind_binned(merged, edges, config)["completeness"]
        m50 = R.magnitude_at(comp, 0.5)
        map_edges = (np.asarray(config.ratios.map_mag_edges, float) if config.ratios.map_mag_edges
                     else R.transition_map_mag_edges(comp) if np.isfinite(m50)
                     else R.default_map_mag_edges(float(np.mean(mag_range))))
        maps_name = layout.binned_maps(kind)
        hdul = maps_hdulist(merged, image_shape=image.shape, pixel_scale=image.pixel_scale, wcs=image.wcs,
                            config=config, mag_edges=map_edges)
        with atomic_path(run.file(maps_name)) as tmp:
            hdul.writeto(tmp)
        kinds[kind] = kind_summary(merged, edges, config, nreal=len(done), maps_file=maps_name, map_edges=map_edges)
        kinds[kind]["seconds"] = {k: round(v, 2) for k, v in stage_seconds[kind].items()}
        if kind == "point":
            stars = (run.stage_info("fwhm").get("estimate") or {}).get("star_rows")
            kinds[kind]["size_check"] = _point_size_check(image, det, merged.matched, log, star_rows=stars)
        c = kinds[kind]["counts"]
        # a realization may draw no injection at all (small field, low density): a valid result
        nempty = len(done) - len(np.unique(np.asarray(merged.injected["realization"]))) \
            if len(merged.injected) else len(done)
        log(f"ratios: {kind}: {c['detected']}/{c['usable']} usable injections detected, {c['false']} false "
            f"detections; binned m50 = {'undefined' if kinds[kind]['m50_binned'] is None else format(kinds[kind]['m50_binned'], '.2f')}"
            + (f"; {nempty} of {len(done)} realizations held no injection" if nempty else ""))
        if 0 < c["usable"] < FEW_USABLE_INJECTIONS:  # the preflight expected more, or warned already
            log(f"warning: ratios: {kind}: only {c['usable']} usable injections: its completeness and m50 are "
                f"loose (their intervals say how much); more realizations (--nsims) tighten them")
        bright = R.bright_end(comp)
        if bright["n"] >= BRIGHT_END_MIN_N and bright["ratio"] < BRIGHT_END_MIN:
            text = (f"the brightest injections ({bright['mag_lo']:.2f}-{bright['mag_hi']:.2f} mag) are only "
                    f"{bright['ratio']:.0%} complete ({bright['k']}/{bright['n']}): the injected range starts inside "
                    "the transition (crowding or blending can make the completeness fall far brighter than the "
                    "5-sigma depth), so the bright plateau was never measured and the models' plateau and bright side "
                    "are their priors' extrapolation; inject brighter (--set injection.mag_range=[BRIGHT,FAINT]; the "
                    "run then keeps the injections further apart, as their light reaches their neighbours, "
                    "docs/injection.md)")
            kinds[kind]["bright_end"] = {**bright, "warning": text}
            log(f"warning: ratios: {kind}: {text}")
    timings["ratios"] = round(time.perf_counter() - t0, 3)

    # ---- the Bayesian completeness and purity models ---------------------------------
    t0 = time.perf_counter()
    if _fit_stages(run, image, det, config, kinds, edges, mag_range, log, compute, cpu, maps=design_maps):
        timings["fit"] = round(time.perf_counter() - t0, 3)
        timings["fit_cpu"] = round(cpu.get("fit", 0.0), 3)

    summary = {
        "format": SUMMARY_FORMAT,
        "image": image.facts(),
        "depth": depth_summary(det.noise, image.mask, zeropoint=image.zeropoint, fwhm=image.fwhm,
                               det_mags=det.catalog["mag_auto"], psf_nea=_psf_nea(config, image, psf_choice)),
        "psf": psf_choice,
        "kinds": kinds,
        "failed_realizations": failures,
        "sourcefree": run.stage_info("sourcefree").get("replacement"),
    }
    if adaptive_summary is not None:
        summary["adaptive"] = adaptive_summary
        _adaptive_reported(adaptive_summary, kinds, log)
    run.write_json(layout.SUMMARY, summary)
    return summary


def _observed_baseline(image: ImageData, det: DetectionResult, base: np.ndarray, weight_noise, on: str,
                       fixed: bool = False):
    """The first detection, when the baseline detection on the observed image would only repeat it.

    Injecting on the observed image (``injection.on = "observed"``), the baseline's input is the
    image the first detection ran on: the same pixels (``observed.fits``, written from them), mask,
    zero point, gain, saturation, WCS and detection settings.  When its noise map is the same too
    (the weight map's noise, or none for both; or, ``fixed``, the first detection's own noise map,
    ``detection.noise_level = "observed"``), the detection is deterministic and gives the same
    catalog, so it is reused (about 11 s on the shared 2MASS field).  Anything else: None (detect).
    """
    if on != "observed" or base.shape != image.data.shape:
        return None
    if not np.array_equal(base, image.data, equal_nan=True):
        return None
    if fixed:  # the threshold noise given is the first detection's, measured on these same pixels
        return det
    first = getattr(image, "noise", None)  # the noise map the first detection was given
    if (weight_noise is None) != (first is None):
        return None
    if first is not None and not np.array_equal(np.asarray(weight_noise, np.float32), np.asarray(first, np.float32),
                                                equal_nan=True):
        return None
    return det


def _contexts_by_kind(ctx, densities: dict) -> dict:
    """``{kind: SimContext}`` whose injection density is the one chosen for the kind (run.json's
    ``injection_density``; a kind without a recorded choice keeps ``ctx``'s)."""
    out = {}
    for kind in ctx.injection.kinds:
        choice = densities.get(kind) or {}
        density = choice.get("density")
        inj = ctx.injection if not density else replace(ctx.injection, density=float(density))
        if choice.get("min_sep_arcsec"):  # a separation the run chose for this kind (_bright_separation)
            inj = replace(inj, min_sep=float(choice["min_sep_arcsec"]))
        out[kind] = ctx if inj is ctx.injection else replace(ctx, injection=inj)
    return out


#: Signal-to-noise above which the sizes of stars and injected point sources are compared.
SIZE_CHECK_SNR = 20.0


def _point_size_check(image: ImageData, det: DetectionResult, matched, log, star_rows=None) -> dict:
    """Median flux_radius of detected point-source injections against the image's stars (SNR >= 20 both).

    The stars are those whose Moffat fits gave the seeing (``star_rows`` of the detection catalog);
    without them (the fits failed, or a run older than them), the candidates on the stellar locus.
    """

    if star_rows:
        rows = np.asarray(star_rows, dtype=np.int64)
    else:
        rows = select_stars(det.catalog, shape=image.shape, saturation_flagged=image.saturation is not None,
                            snr_min=SIZE_CHECK_SNR).index
    stars = np.asarray(det.catalog["flux_radius"], dtype=float)[rows]
    star_snr = np.asarray(det.catalog["snr_auto"], dtype=float)[rows]
    if len(matched):
        ok = (np.asarray(matched["det_snr_auto"], dtype=float) >= SIZE_CHECK_SNR) \
            & ((np.asarray(matched["det_flags"], dtype=np.int64) & BAD_FLAGS) == 0) \
            & np.asarray(matched["usable"], dtype=bool)
        injected = np.asarray(matched["det_flux_radius"], dtype=float)[ok]
        injected_snr = np.asarray(matched["det_snr_auto"], dtype=float)[ok]
    else:
        injected = injected_snr = np.zeros(0)
    check = point_size_check(stars, injected, star_snr=star_snr, injected_snr=injected_snr)
    check["snr_min"] = SIZE_CHECK_SNR
    if check["status"] == "not enough":
        log(f"psf check: point: too few to compare the sizes of injected point sources and stars "
            f"({check['ninjected']} detected injections and {check['nstars']} stars with SNR >= {SIZE_CHECK_SNR:g})")
        return check
    said = (f"median flux_radius {check['injected']:.3f} px of {check['ninjected']} detected point-source "
            f"injections against {check['stars']:.3f} px of {check['nstars']} stars (ratio {check['ratio']:.3f} "
            f"+- {check['ratio_err']:.3f}")
    same = check.get("matched")
    said += (f"; at the same SNR {same['ratio']:.3f} +- {same['ratio_err']:.3f})" if same else ")")
    if check["status"] == "agree":
        log(f"psf check: point: {said}: they agree within {100 * check['tolerance']:.0f}%")
    elif check["status"] == "uncertain":
        log(f"psf check: point: {said}: too few or too scattered sizes to tell whether they agree within "
            f"{100 * check['tolerance']:.0f}%")
    else:
        log(f"warning: psf check: point: {said}: the injected point sources do not look like the image's stars; "
            f"the completeness of point sources may be biased (see the 'psf' entry of {layout.RUN})")
    return check


def _realization_recorder(sims, cpu: dict, log, said: set, on_failure, *, label: str = ""):
    """The ``on_result`` of realization tasks, for the uniform injection and the adaptive batches alike.

    Each distinct worker warning is logged once (``said`` holds those logged already, so a caller
    can share it across batches), a failed realization goes to ``on_failure(name, last line of its
    error)``, and a finished one is written and its CPU seconds added to ``cpu["inject"]``.
    """

    def on_result(task, packed):
        result, caught = packed
        name = f"{result.kind} #{result.index}"
        for text in caught:  # the workers' warnings, once each, above the progress bar
            if text not in said:
                said.add(text)
                log(f"warning: realization {name}{label}: {text}")
        if result.error is not None:
            on_failure(name, result.error.strip().splitlines()[-1])
            return
        cpu["inject"] = cpu.get("inject", 0.0) + float(result.seconds.get("cpu", 0.0))
        write_realization(result, sims)
    return on_result


def _adaptive_injection(run: RunDirectory, ctx, config: RunConfig, compute: "ComputeOptions", log,
                        noise: np.ndarray, mask: np.ndarray, mag_range, cpu: dict,
                        maps_out: dict | None = None) -> tuple[dict, dict]:
    """Realizations in batches designed from the posterior, per kind, until the precision (docs/adaptive.md).

    Batch ``k`` of a kind draws its magnitudes from the design built from the outcomes of its batches
    before ``k`` (:mod:`comest_bayes.inject.design`), recorded in ``designs/<kind>_batch<k>.json`` before any of
    its realizations runs.  A resumed run recomputes the same fits (seeded) and checks its designs
    against the recorded ones; finished realizations are not run again.

    Returns the number of realizations per kind and the ``summary.json`` entry ``adaptive``.  The
    design's :func:`~comest_bayes.bayes.fit.shared_maps` (one pass over the noise map and mask, timed
    with the design fits) is added to ``maps_out``, for the fit stage to reuse.
    """

    from astropy.table import vstack


    ad = config.adaptive
    lo, hi = float(mag_range[0]), float(mag_range[1])
    sims = run.file(layout.SIMS_DIR)
    designs = run.file(layout.DESIGNS_DIR)
    designs.mkdir(exist_ok=True)
    at_f = ad.target == "f"
    mags_f = tuple(float(m) for m in ad.magnitudes)
    model = config.fit.model if config.fit.model != "none" else "auto"
    # one pass over the pixels for every design fit of every kind, timed with them
    c0 = time.process_time()
    # (the fit stage's own casts, so that a fit stage reusing it computes exactly what it would compute)
    maps = shared_maps(np.asarray(noise, np.float32), np.asarray(mask, bool), [model])
    cpu["design_fit"] = cpu.get("design_fit", 0.0) + time.process_time() - c0
    if maps_out is not None:
        maps_out.update(maps)
    state = {}
    for kind in config.injection.kinds:
        state[kind] = {"n": 0, "design": uniform_design(lo, hi), "batches": [], "done": False, "reached": False,
                       "reason": "", "outcomes": [],
                       "fit": package_fitter(image_shape=noise.shape, noise=noise, mask=mask, lo=lo, hi=hi,
                                             seed=int_seed_for(config.seed, Stream.ADAPTIVE, kind), model=model, kind=kind,
                                             mag_bin=config.ratios.mag_bin, magnitudes=mags_f, maps=maps)}
    goal = (f"the posterior sd of f at {', '.join(f'{m:.2f}' for m in mags_f)} mag is <= {ad.precision}" if at_f
            else f"the 68% half-width of m50 is <= {ad.precision} mag")
    log(f"adaptive: batches until {goal} per kind (pilot "
        f"{ad.pilot_nsims} uniform realizations, then +{ad.growth:.0%} per batch, {ad.uniform_share:.0%} uniform, "
        f"at most {ad.max_nsims} realizations)")
    said = set()  # each distinct worker warning is logged once per run, as in the uniform injection
    k = 0
    while not all(st["done"] for st in state.values()):
        tasks, span = [], {}
        for kind, st in state.items():
            if st["done"]:
                continue
            size = ad.pilot_nsims if st["n"] == 0 else max(1, math.ceil(ad.growth * st["n"]))
            size = min(size, ad.max_nsims - st["n"])
            design = st["design"]
            path = run.file(layout.design(kind, k))
            if path.exists():
                check_recorded(MagnitudeDesign.from_dict(json.loads(path.read_text())), design, k)
            else:
                with atomic_path(path) as tmp:
                    tmp.write_text(dumps(design.to_dict()))
            span[kind] = (st["n"], st["n"] + size)
            for i in range(*span[kind]):
                if not realization_file(sims, kind, i).exists():
                    # the pilot keeps the published uniform draws (identical to a run without --precision)
                    tasks.append(RealizationTask(ctx[kind], kind, i, design=None if k == 0 else design.to_dict()))
        failed = []
        on_result = _realization_recorder(sims, cpu, log, said, lambda name, last: failed.append(f"{name}: {last}"),
                                          label=f" (adaptive batch {k})")

        if tasks:
            run_tasks(realization_with_warnings, tasks, on_result=on_result, executor=compute.executor,
                      workers=compute.workers, scheduler=compute.scheduler, progress=compute.progress,
                      runner=compute.runner, desc=f"batch {k}")
        if failed:
            raise ComestError(f"adaptive batch {k}: {len(failed)} realization(s) failed ({failed[0]}); the design of "
                              "the next batch needs them all. Rerun the same command to retry them (finished "
                              "work is kept).")
        for kind, (start, end) in span.items():
            st = state[kind]
            st["n"] = end
            # only this batch's realizations are read; the outcome table is the stack of every batch's
            st["outcomes"].append(merge_realizations(sims, kind, range(start, end)).outcomes)
            outcomes = vstack(st["outcomes"], metadata_conflicts="silent")
            c0 = time.process_time()
            view, (post, entry) = st["fit"](outcomes, k)
            cpu["design_fit"] = cpu.get("design_fit", 0.0) + time.process_time() - c0
            half = view.m50_halfwidth
            rec = {"batch": k, "realizations": [start, end], "injections": int(len(outcomes)),
                   "design": st["design"].target, "model": entry.name, "warm_refit": entry.warm_refit,
                   "within_0.6_of_m50": (round(st["design"].fraction_within(view.m50_median - 0.6,
                                                                            view.m50_median + 0.6), 3)
                                         if math.isfinite(view.m50_median) else None),
                   "m50": view.m50_median if math.isfinite(view.m50_median) else None,
                   "halfwidth": half if math.isfinite(half) else None}
            if at_f:
                rec["f"] = [float(v) for v in view.f_median(mags_f)]
                rec["f_sd"] = [float(v) for v in view.f_sd(mags_f)]
            st["batches"].append(rec)
            log(f"adaptive: {kind} batch {k} ({rec['design']} design, {end - start} realizations): {end} in all, "
                f"{rec['injections']} injections, m50 "
                + ("undefined" if rec["m50"] is None else f"{rec['m50']:.3f} +- {half:.4f}")
                + ("; f " + ", ".join(f"{v:.3f} +- {e:.4f}" for v, e in zip(rec["f"], rec["f_sd"])) if at_f else "")
                + f" (target {ad.precision}; {entry.name})")
            reached, reason, nxt = after_batch(view, lo, hi, precision=ad.precision, at_cap=end >= ad.max_nsims,
                                               spent=f"{end} realizations, {rec['injections']} injections",
                                               target=ad.target, uniform_share=ad.uniform_share, magnitudes=mags_f)
            if nxt is None:
                st.update(done=True, reached=reached,
                          reason=reason if reached else reason + "; for more, run again into a new --out with a "
                          "higher --max-nsims or a looser --precision (a run keeps the settings it started with)")
            else:
                st["design"] = nxt
            if st["done"]:
                log(f"adaptive: {kind}: {'precision reached' if st['reached'] else 'precision NOT reached'}: "
                    f"{st['reason']}")
        k += 1
    summary = {"precision": ad.precision, "target": ad.target, "uniform_share": ad.uniform_share,
               "max_nsims": ad.max_nsims,
               **({"magnitudes": list(mags_f)} if at_f else {}),
               "kinds": {kind: {"reached": st["reached"], "reason": st["reason"], "realizations": st["n"],
                                "batches": st["batches"]} for kind, st in state.items()}}
    return {kind: st["n"] for kind, st in state.items()}, summary


def _adaptive_reported(adaptive_summary: dict, kinds: dict, log) -> None:
    """Add to each kind of ``adaptive_summary`` the m50 interval the run reports, and say when it is wider.

    The batches stop on the design fits' half-width (the selection's most flexible rung,
    docs/adaptive.md); the fit stage then selects the simplest adequate rung on every outcome, whose
    interval is what ``kinds.<kind>.model.m50`` reports.  ``reported`` records that model and its
    68% half-width and whether it meets an m50 target (None for a target on f, or with no fit);
    a run whose design reached the target but whose reported interval is wider says so.
    """
    at_f = adaptive_summary.get("target") == "f"
    for kind, info in (adaptive_summary.get("kinds") or {}).items():
        entry = (kinds.get(kind) or {}).get("model") or {}
        m50 = entry.get("m50") or {}
        if m50.get("hi68") is None or m50.get("lo68") is None:
            info["reported"] = {"model": entry.get("name"), "m50_halfwidth": None, "meets_target": None}
            continue
        half = 0.5 * (m50["hi68"] - m50["lo68"])
        meets = None if at_f else bool(half <= adaptive_summary["precision"] * (1.0 + 1e-9))
        info["reported"] = {"model": entry.get("name"), "m50_halfwidth": half, "meets_target": meets}
        if info.get("reached") and meets is False:
            log(f"warning: adaptive: {kind}: the design fits reached the m50 half-width "
                f"{adaptive_summary['precision']}, but the reported fit ({entry.get('name')}) has {half:.4f}; "
                "a smaller --precision makes the batches go on until the reported interval is within the target")


def _fit_stages(run: RunDirectory, image: ImageData, det: DetectionResult, config: RunConfig, kinds: dict,
                edges, mag_range, log, compute: "ComputeOptions", cpu: dict | None = None,
                maps: dict | None = None) -> int:
    """Fit completeness (and purity) per kind, in parallel; add their entries to ``kinds`` (resumable).

    Returns the number of fits run now (0 when all were done earlier or no model is fitted); their
    CPU seconds (as measured in the workers) are added to ``cpu["fit"]``.  ``maps``: a
    :func:`~comest_bayes.bayes.fit.shared_maps` of this run's noise map and mask made earlier (the
    adaptive design's), used when it holds every footprint grid the fits need.
    """
    cpu = {} if cpu is None else cpu

    if config.fit.model == "none":
        return 0
    run.file(layout.POSTERIOR_DIR).mkdir(exist_ok=True)
    centers = 0.5 * (edges[:-1] + edges[1:])
    wcs_header = None if image.wcs is None else image.wcs.to_header(relax=True).tostring()
    jobs = [("completeness", config.fit.model)]
    if config.fit.purity_model != "none":
        jobs.append(("purity", config.fit.purity_model))
    tasks = []
    for kind in kinds:
        for quantity, requested in jobs:
            stage = f"fit_{quantity}_{kind}"
            key = "model" if quantity == "completeness" else "purity_model"
            # a fit is kept only for the outcomes it was fitted to: a realization that failed before and
            # has run since changes the merged catalogs, and the fit is redone
            if run.stage_done(stage) and run.stage_info(stage).get("counts") == kinds[kind].get("counts"):
                kinds[kind][key] = run.stage_info(stage)["entry"]
                continue
            tasks.append({"run_dir": str(run.path), "kind": kind, "quantity": quantity, "requested": requested,
                          "config": config, "image_shape": tuple(image.shape), "wcs_header": wcs_header,
                          "mag_range": tuple(mag_range), "mag_centers": centers})
    if tasks:
        log(f"fit: {len(tasks)} model fits ({', '.join(t['kind'] + ' ' + t['quantity'] for t in tasks)}) "
            f"on {compute.describe()}")
        # one pass over the maps (in memory: the noise.fits and mask.fits the fits would read) for every fit
        # (footprint cells, noise grid), timed as part of the fit stage
        c0 = time.process_time()
        requested = sorted({t["requested"] for t in tasks})
        if not (maps and all(footprint_grid(needs_smooth(r)) in maps["footprints"] for r in requested)):
            maps = shared_maps(np.asarray(det.noise, np.float32), np.asarray(image.mask, bool), requested)
        cpu["fit"] = cpu.get("fit", 0.0) + time.process_time() - c0
        for t in tasks:
            t["shared_maps"] = maps
    serial = compute.executor == "serial" or (compute.executor == "processes" and compute.workers <= 1)
    # fits of one model (the completeness of every kind; the purity of every kind) run one after the other
    # in one worker: a process traces a model's programs once, and on small runs that trace costs about
    # as much CPU as the fit itself.  In one process (serial) every fit shares it anyway.
    groups = None
    if not serial:
        by_model = {}
        for t in tasks:
            by_model.setdefault((t["quantity"], t["requested"]), []).append(t)
        groups = list(by_model.values())
    progress = FitProgress(tasks, log, describe=lambda t: describe_fit(t, kinds[t["kind"]], config),
                           workers=1 if serial else compute.workers, known_order=compute.executor != "dask",
                           groups=groups)

    def on_result(task, result):
        try:
            record(task, result)
        finally:
            progress.finished(task)  # after the finished fit's line: then the next one's start

    def record(task, result):
        post, entry = result
        kind, quantity = task["kind"], task["quantity"]
        cpu["fit"] = cpu.get("fit", 0.0) + float(entry.cpu_seconds or 0.0)
        key = "model" if quantity == "completeness" else "purity_model"
        files = []
        record = entry.to_dict()  # the summary.json entry: the fit's, and the files written here
        if post is not None:
            files.append(str(post.save(run.file(layout.posterior(kind, quantity))).relative_to(run.path)))
            record["posterior_file"] = files[0]
            record["m50_map_file"] = None
            if quantity == "completeness" and post.spec.spatial != "none":
                step = max(1, int(round(config.fit.map_step_arcmin * 60.0 / image.pixel_scale)))
                med, sd, header = post.m50_map(step)
                header["BUNIT"] = ("mag", "50% completeness magnitude")
                hdul = fits.HDUList([fits.PrimaryHDU(), fits.ImageHDU(med.astype(np.float32), header, name="M50"),
                                     fits.ImageHDU(sd.astype(np.float32), header, name="M50_SD")])
                name = layout.m50_map(kind)
                with atomic_path(run.file(name)) as tmp:
                    hdul.writeto(tmp)
                record["m50_map_file"] = name
                files.append(name)
        run.record_stage(f"fit_{quantity}_{kind}", files=files, seconds=entry.seconds or 0.0, entry=record,
                         counts=kinds[kind].get("counts"))
        kinds[kind][key] = record
        if post is None:
            log(f"fit: {kind} {quantity}: skipped ({entry.skipped})")
            return
        for w in entry.warnings:
            log(f"warning: {kind} {quantity}: {w}")
        m50 = entry.magnitudes.get("m50", {})
        med = m50.get("median")
        chosen = entry.name + (" (selected)" if entry.selection else "")
        log(f"fit: {kind} {quantity}: {chosen}, m50 = "
            + ("n/a" if med is None else f"{med:.2f} (+{m50['hi68'] - med:.2f}/-{med - m50['lo68']:.2f})")
            + f", ESS {float(np.min(entry.diagnostics.get('ess') or [0])):.0f}, {entry.seconds:.1f} s")

    def on_group(group, results):
        for task, result in zip(group, results):
            if isinstance(result, FitFailure):
                raise result.exc
            on_result(task, result)

    progress.start()
    try:
        if groups is None:
            run_tasks(fit_task, tasks, on_result=on_result, executor=compute.executor, workers=compute.workers,
                      scheduler=compute.scheduler, progress=compute.progress, desc="fits", runner=compute.runner)
        else:
            run_tasks(fit_tasks, groups, on_result=on_group, executor=compute.executor, workers=compute.workers,
                      scheduler=compute.scheduler, progress=compute.progress, desc="fit groups", runner=compute.runner)
    finally:
        progress.stop()
    return len(tasks)
