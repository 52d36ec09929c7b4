"""Readers of a run directory for the figures and the report (all the I/O of :mod:`comest_bayes.report.plots`).

Each reader returns the data container a plotting function takes, or None when
the run does not hold that product (a run without a model fit, a kind without
maps, a partial run), so the caller can say what is missing instead of failing.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import warnings

import numpy as np
from astropy.io import fits
from astropy.table import Table

from comest_bayes.errors import InputFileError
from comest_bayes.report.plots.data import BinnedCurve, ChainSamples, Cutout, DepthLine, MapPlane, PosteriorBand
from comest_bayes.io import layout
from comest_bayes.io.run import Run
from comest_bayes.bayes.posterior import CompletenessPosterior
from comest_bayes.recover.realization import realization_file
from comest_bayes.inject.render import render_truth
from comest_bayes.seeding import Stream, int_seed_for
from comest_bayes.inject.cosmos import load_cosmos
from comest_bayes.inject.psfmodel import make_psf
from comest_bayes.pipeline.stages import ImageOptions
from comest_bayes.report.plots.images import Markers, choose_region, cut

__all__ = ["binned_curve", "depth_lines", "load_posterior", "posterior_band",
           "chain_samples", "map_planes", "m50_map", "matched_magnitudes", "Figure3Data", "figure3_data",
           "simulated_image", "KEY_PARAMETERS"]

#: Physical parameters shown in trace plots, in this order, when the model has them.
KEY_PARAMETERS = ("m50_0", "w", "beta_depth", "beta_size", "A", "floor")


# --------------------------------------------------------------------------- ratios and curves

def binned_curve(run: Run, kind: str, quantity: str) -> BinnedCurve | None:
    """Binned completeness or purity of ``kind`` from ``summary.json``."""
    binned = run.kind_entry(kind).get("binned")
    if not binned or quantity not in binned:
        return None
    return BinnedCurve.from_summary(binned, quantity)


def depth_lines(summary: dict | None) -> list:
    """The 5-sigma depth references of ``summary.json`` as :class:`DepthLine` objects."""
    depth = (summary or {}).get("depth") or {}
    out = []
    if depth.get("point_source_5sigma") is not None:
        out.append(DepthLine(float(depth["point_source_5sigma"]), "5σ point-source depth"))
    if depth.get("aperture_5sigma") is not None:
        d = depth.get("aperture_diameter_pix")
        out.append(DepthLine(float(depth["aperture_5sigma"]),
                             "5σ depth, " + (f"{d:.1f} px aperture" if d else "aperture")))
    return out


def load_posterior(run: Run, kind: str, quantity: str = "completeness"):
    """The saved :class:`~comest_bayes.bayes.posterior.CompletenessPosterior`, or None when there is none."""

    key = "model" if quantity == "completeness" else "purity_model"
    entry = run.kind_entry(kind).get(key) or {}
    name = entry.get("posterior_file") or layout.posterior(kind, quantity)
    path = run.file(name)
    if not path.is_file():
        return None
    return CompletenessPosterior.load(path)


def posterior_band(post, mags, *, nsamples: int = 400, label: str | None = None) -> PosteriorBand:
    """Image-average median and 68% / 95% bands of a posterior on the grid ``mags``."""
    curve = post.curve(np.asarray(mags, float), nsamples=nsamples, warn=False)  # a figure's grid: no warning
    return PosteriorBand.from_dict(curve, label=label or f"posterior ({post.spec.name})")


def chain_samples(post, *, max_params: int = 4) -> ChainSamples | None:
    """Walker-by-walker post-burn-in draws of the key physical parameters, or None.

    The posterior's draws are stored flattened step-major (row ``s * W + w`` is
    walker ``w`` at kept step ``s``, see :class:`comest_bayes.bayes.inference.PosteriorSamples`);
    None when the number of walkers is unknown or does not divide the draws
    (e.g. a MAP-only fit).
    """
    diag = (post.diagnostics or {}).get("sampler") or {}
    nw = int(diag.get("nwalkers") or 0)
    s = np.asarray(post.samples)
    if nw < 1 or s.shape[0] < 2 * nw or s.shape[0] % nw:
        return None
    phys = post.model.transform(s)
    names = [n for n in KEY_PARAMETERS if n in phys and np.std(np.asarray(phys[n], float)) > 0][:max_params]
    if not names:
        return None
    values = np.stack([np.asarray(phys[n], float).reshape(-1, nw) for n in names], axis=-1)
    return ChainSamples(values=values, names=names, burn=int(diag.get("burn") or 0))


# --------------------------------------------------------------------------- maps

def _map_planes(hdul, name: str, nname: str | None) -> list:
    if name not in hdul:
        return []
    hdu = hdul[name]
    cube = np.asarray(hdu.data, float)
    if cube.ndim == 2:
        cube = cube[None]
    counts = np.asarray(hdul[nname].data) if nname and nname in hdul else None
    if counts is not None and counts.ndim == 2:
        counts = counts[None]
    h = hdu.header
    planes = []
    for i in range(cube.shape[0]):
        planes.append(MapPlane(values=cube[i], bin_pix=float(h.get("BINPIX", 1.0)),
                               mag_lo=float(h.get(f"MAGLO{i}", np.nan)), mag_hi=float(h.get(f"MAGHI{i}", np.nan)),
                               n=None if counts is None else counts[i]))
    return planes


def map_planes(run: Run, kind: str) -> tuple[list, list] | None:
    """Completeness and purity planes of ``maps/<kind>_maps.fits``, or None when absent."""
    name = (run.kind_entry(kind).get("maps") or {}).get("file") or layout.binned_maps(kind)
    path = run.file(name)
    if not path.is_file():
        return None
    with fits.open(path) as hdul:
        return _map_planes(hdul, "COMPLETENESS", "COMPLETENESS_N"), _map_planes(hdul, "PURITY", "PURITY_N")


def m50_map(run: Run, kind: str) -> tuple[np.ndarray, np.ndarray, float] | None:
    """``(median, sd, bin_pix)`` of ``maps/<kind>_m50.fits``, or None (model without a spatial term)."""
    name = (run.kind_entry(kind).get("model") or {}).get("m50_map_file") or layout.m50_map(kind)
    path = run.file(name)
    if not path.is_file():
        return None
    with fits.open(path) as hdul:
        return (np.asarray(hdul["M50"].data, float), np.asarray(hdul["M50_SD"].data, float),
                float(hdul["M50"].header.get("BINPIX", 1.0)))


# --------------------------------------------------------------------------- catalogs

def _first_column(values) -> np.ndarray:
    v = np.asarray(values, float)
    return v[:, 0] if v.ndim == 2 else v


def matched_magnitudes(run: Run, kind: str) -> tuple[np.ndarray, np.ndarray] | None:
    """True and measured (``matching.mag_column``) magnitudes of the recovered injections of ``kind``."""
    path = run.file(layout.catalog(kind, "matched"))
    if not path.is_file():
        return None
    t = Table.read(path, mask_invalid=False)
    col = f"det_{run.config.matching.mag_column}"
    if col not in t.colnames:
        col = "det_mag_auto"
    keep = np.asarray(t["usable"], bool) if "usable" in t.colnames else np.ones(len(t), bool)
    return np.asarray(t["mag"], float)[keep], _first_column(t[col])[keep]


# --------------------------------------------------------------------------- images (Figure 3)

def _decode(table: Table) -> Table:
    for name in table.colnames:
        if table[name].dtype.kind == "S":
            table[name] = np.char.decode(table[name])
    return table


def _realization_tables(run: Run, kind: str, index: int) -> tuple[Table, Table]:

    path = realization_file(run.file(layout.SIMS_DIR), kind, index)
    if not path.is_file():
        raise InputFileError(f"realization {kind} #{index} ({path}) does not exist in this run.")
    with fits.open(path) as hdul:
        return _decode(Table(hdul["TRUTH"].data)), _decode(Table(hdul["DETECTIONS"].data))


def _base_name(run: Run) -> str:
    return (run.state.get("stages", {}).get("baseline") or {}).get("base") or layout.SFI


def simulated_image(run: Run, kind: str, index: int = 0, *, prefer_saved: bool = True) -> tuple[np.ndarray, str]:
    """The simulated image of one realization and how it was obtained.

    A saved image (``sims/<kind>/image_rNNNNN.fits``, written with
    ``injection.write_images``) is read when present and ``prefer_saved``;
    otherwise the realization is drawn again from its stored truth table onto
    the run's base image with the realization's own photon-noise seed
    (``("render", kind, index)`` of the root seed), which reproduces the
    injected image exactly (:func:`comest_bayes.inject.render.render_truth` is
    deterministic given its seed).

    Returns
    -------
    image : ndarray, shape (ny, nx), float32
    how : str
        ``"saved"`` or ``"re-rendered"``.
    """

    saved = run.file(layout.SIMS_DIR) / layout.realization_image(kind, index)
    if prefer_saved and saved.is_file():
        return fits.getdata(saved).astype(np.float32), "saved"
    truth, _ = _realization_tables(run, kind, index)
    config = run.config
    facts = run.image_facts
    base_path = run.file(_base_name(run))
    base = fits.getdata(base_path).astype(np.float32)
    wcs = None
    header = fits.getheader(base_path)
    if facts.get("wcs"):

        from astropy.wcs import WCS, FITSFixedWarning

        # The run's copy of the image's header: astropy's fixes to it (e.g. 'obsfix' setting OBSGEO-B/L/H
        # on JWST) were judged when the run read the image (comest_bayes.io.image: harmless ones dropped, the
        # others a warning line in the run's log), so they are not repeated on the terminal here.
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", FITSFixedWarning)
            wcs = WCS(header, relax=True)
    choice = (run.summary_record or {}).get("psf") or run.state.get("psf") or {}  # the run's injection PSF
    psf = make_psf(config.injection, float(facts["fwhm_pix"]), float(facts["pixel_scale_arcsec"]),
                   beta=choice.get("beta"), pixel_integrated=bool(choice.get("pixel_integrated", False)))
    cosmos = load_cosmos(config.injection) if kind == "cosmos" else None
    image, _ = render_truth(base, truth, psf=psf, config=config.injection,
                            pixel_scale=float(facts["pixel_scale_arcsec"]), gain=facts.get("gain"),
                            zeropoint=facts.get("zeropoint"), rng_seed=int_seed_for(config.seed, Stream.RENDER, kind, index),
                            cosmos=cosmos, wcs=wcs)
    return image, "re-rendered"


@dataclass
class Figure3Data:
    """Inputs of :func:`comest_bayes.report.plots.images.figure3` read from a run.

    ``observed`` is None (with ``notes`` saying why) when the input image
    cannot be read any more.
    """

    observed: Cutout | None
    sourcefree: Cutout
    simulated: Cutout
    detections: object
    recovered: object
    missed: object
    false: object
    kind: str
    index: int
    how: str
    base: str
    notes: list = field(default_factory=list)


def figure3_data(run: Run, *, kind: str | None = None, index: int | None = None, center=None,
                 size: int = 400) -> Figure3Data:
    """Read the three cutouts and the marker positions of the Figure-3 panels.

    Parameters
    ----------
    kind : str, optional
        Source kind of the simulated image (default the first kind of the run).
    index : int, optional
        Realization (default the first one on disk).
    center : (x, y), optional
        Cutout centre, 0-based pixels (default the image centre).
    size : int
        Cutout side, pixels.
    """

    kinds = run.kind_names or list(run.config.injection.kinds)
    kind = kind or kinds[0]
    if index is None:
        done = sorted(run.file(layout.SIMS_DIR).glob(layout.realization_glob(kind)))
        if not done:
            raise InputFileError(f"no realization of kind {kind!r} is on disk in {run.path}/sims.")
        index = int(done[0].stem[1:])
    elif not realization_file(run.file(layout.SIMS_DIR), kind, index).is_file():
        raise InputFileError(f"realization {kind} #{index} does not exist in this run.")
    base_name = _base_name(run)
    sfi = fits.getdata(run.file(base_name)).astype(np.float32)
    mask = fits.getdata(run.file(layout.MASK)).astype(bool) if run.file(layout.MASK).is_file() else None
    region = choose_region(sfi.shape, size, center)
    notes = []
    observed = None
    try:
        opts = ImageOptions(**(run.state.get("input_options") or run.state["fingerprint"]["input"]["options"]))
        image = opts.load()
        observed = cut(image.data, region, image.mask)
    except Exception as exc:  # the input image moved or changed; the other panels still stand
        notes.append(f"the observed image could not be read again ({exc}); its panel is left empty")
    sim, how = simulated_image(run, kind, index)
    truth, dets = _realization_tables(run, kind, index)
    det = Table.read(run.file(layout.DETECTION), mask_invalid=False)
    usable = np.asarray(truth["usable"], bool)
    detected = np.asarray(truth["detected"], bool)
    false = np.asarray(dets["false"], bool)
    tx, ty = np.asarray(truth["x"], float), np.asarray(truth["y"], float)
    return Figure3Data(
        observed=observed, sourcefree=cut(sfi, region, mask), simulated=cut(sim, region, mask),
        detections=Markers(np.asarray(det["xwin"], float), np.asarray(det["ywin"], float), "detections", "detection"),
        recovered=Markers(tx[usable & detected], ty[usable & detected], "recovered injections", "recovered"),
        missed=Markers(tx[usable & ~detected], ty[usable & ~detected], "missed injections", "missed"),
        false=Markers(np.asarray(dets["xwin"], float)[false], np.asarray(dets["ywin"], float)[false],
                      "false detections", "false"),
        kind=kind, index=index, how=how, base=base_name, notes=notes)
