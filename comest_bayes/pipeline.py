"""Orchestration: run the stages of the data flow into a run directory.

image -> detection -> seeing FWHM -> source-free (and BnB) image -> ...

Each stage is a call into a numerics module; this module only validates,
sequences, times, writes and resumes.  All input validation (files, header
facts, configuration, optional backends) happens before the run directory is
touched.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import numpy as np
from astropy.io import fits
from astropy.table import Table

from .config import RunConfig
from .detection import DetectionResult, detect, filter_kernel
from .errors import DetectionOverflowError
from .image import ImageData, load_image
from .rundir import RunDirectory, file_checksum
from .seeding import seed_sequence

__all__ = ["ImageOptions", "RunResult", "run_pipeline", "output_header"]


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
        kw = asdict(self)
        return load_image(kw.pop("path"), **kw)

    def fingerprint(self) -> dict:
        """Options plus the checksum of every input file."""
        out = {"options": {k: (str(v) if k in ("path", "weight", "mask") and v is not None else v)
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


def output_header(image: ImageData, extra: dict | None = None) -> fits.Header:
    """Header for an output image: the input's WCS plus provenance keywords."""
    header = fits.Header()
    if image.wcs is not None:
        header.update(image.wcs.to_header(relax=True))
    header["MAGZERO"] = (image.zeropoint, "photometric zero point (mag)")
    header["ORIGIN"] = "comest-bayes"
    for key, value in (extra or {}).items():
        header[key] = value
    return header


def _load_detection(run: RunDirectory, image: ImageData) -> DetectionResult:
    cat = Table.read(run.file("detection.fits"))
    info = run.stage_info("detect")
    arrays = {name: fits.getdata(run.file(f"{name}.fits")) for name in ("segmentation", "background", "rms", "noise")}
    return DetectionResult(catalog=cat, segmentation=arrays["segmentation"].astype(np.int32),
                           background=arrays["background"].astype(np.float32),
                           rms=arrays["rms"].astype(np.float32), noise=arrays["noise"].astype(np.float32),
                           meta=info.get("meta", {}))


def run_pipeline(options: ImageOptions, config: RunConfig, out_dir, *,
                 log: Callable[[str], None] = print) -> RunResult:
    """Run every stage on one image, resuming a matching run in ``out_dir``.

    Parameters
    ----------
    options : ImageOptions
        The input image and the facts given about it.
    config : RunConfig
        Resolved configuration (seed included).
    out_dir : str or Path
        Run directory (see :class:`~comest_bayes.rundir.RunDirectory`).
    log : callable
        Receives one human-readable line per stage.

    Returns
    -------
    RunResult
    """
    from .psf import estimate_fwhm
    from .sourcefree import build_source_free

    # ---- validation: nothing is written before all of this passes -------------
    image = options.load()
    filter_kernel(config.detection.filter)
    if config.detection.backend == "sextractor":
        from .sextractor import find_sextractor

        find_sextractor()
    fingerprint = {"input": options.fingerprint(), "config": config.to_dict()}
    run = RunDirectory(out_dir, fingerprint)
    run.check()
    run.open()
    if run.resumed:
        log(f"resuming the run in {run.path} (finished stages are skipped)")
    timings = {}
    header = output_header(image)

    # ---- detection ----------------------------------------------------------------
    if run.stage_done("detect"):
        det = _load_detection(run, image)
        log(f"detect: done earlier ({len(det.catalog)} sources)")
    else:
        t0 = time.perf_counter()
        try:
            det = detect(image, config.detection, workdir=run.path)
        except DetectionOverflowError as exc:
            raise DetectionOverflowError(f"{image.path}: {exc}") from None
        files = [run.write_table("detection.fits", det.catalog)]
        for name in ("segmentation", "background", "rms", "noise"):
            files.append(run.write_image(f"{name}.fits", getattr(det, name), header))
        dt = time.perf_counter() - t0
        run.record_stage("detect", files=files, seconds=dt, meta=det.meta, nsources=len(det.catalog))
        log(f"detect: {len(det.catalog)} sources with {config.detection.backend} "
            f"(threshold {config.detection.thresh} x {det.meta.get('noisemod', 'sigma')} noise) in {dt:.1f} s")
    timings["detect"] = run.stage_info("detect").get("seconds")

    # ---- seeing FWHM ----------------------------------------------------------------
    if image.fwhm is not None:
        fwhm = {"fwhm": image.fwhm, "fwhm_err": 0.0, "nstars": 0, "method": "given by the user (--fwhm)"}
    elif run.stage_done("fwhm"):
        fwhm = run.stage_info("fwhm")["estimate"]
    else:
        t0 = time.perf_counter()
        data_sub = image.data - det.background
        est = estimate_fwhm(data_sub, det.catalog, mask=image.mask, saturation_flagged=image.saturation is not None)
        fwhm = est.as_dict()
        run.record_stage("fwhm", seconds=time.perf_counter() - t0, estimate=fwhm)
    image.fwhm = float(fwhm["fwhm"])
    image.provenance.setdefault("fwhm", fwhm["method"])
    log(f"fwhm: {image.fwhm:.2f} px = {image.fwhm * image.pixel_scale:.2f} arcsec ({fwhm['method']})")
    run.update(image=image.facts())

    # ---- source-free and bright-and-big images --------------------------------------
    if run.stage_done("sourcefree"):
        log("sourcefree: done earlier")
    else:
        t0 = time.perf_counter()
        sf = build_source_free(image.data, det, mask=image.mask, fwhm=image.fwhm, config=config.sourcefree,
                               seed=seed_sequence(config.seed, "sourcefree"))
        files = [run.write_image("sfi.fits", sf.sfi, output_header(image, {"IMAGETYP": "source-free"}))]
        if sf.bnb is not None:
            files.append(run.write_image("bnb.fits", sf.bnb, output_header(image, {"IMAGETYP": "bright-and-big"})))
        dt = time.perf_counter() - t0
        run.record_stage("sourcefree", files=files, seconds=dt, meta=sf.meta, kept_ids=sf.kept_ids)
        log(f"sourcefree: replaced {100 * sf.removed.mean():.1f}% of the pixels"
            + (f"; BnB keeps {len(sf.kept_ids)} sources" if sf.bnb is not None else "") + f" in {dt:.1f} s")
    timings["sourcefree"] = run.stage_info("sourcefree").get("seconds")

    run.update(timings=timings)
    return RunResult(out_dir=run.path, image=image, detection=det, fwhm=fwhm, resumed=run.resumed, timings=timings)
