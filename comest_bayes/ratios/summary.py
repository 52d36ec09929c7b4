"""The raw binned ratios of a run and the ``summary.json`` they go into.

The format of ``summary.json`` (version 1; keys are stable, new keys may be added):
``docs/ratios.md``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from astropy.io import fits

from comest_bayes.ratios import binned as R
from comest_bayes.config import RunConfig
from comest_bayes.ratios.depth import histogram_completeness, limiting_magnitude, point_source_depth, point_source_depth_nea

if TYPE_CHECKING:
    from comest_bayes.recover.realization import MergedCatalogs

__all__ = ["kind_summary", "maps_hdulist", "map_cube_header", "depth_summary", "SUMMARY_FORMAT"]

SUMMARY_FORMAT = 1


def _flat(prefix: str, br: R.BinnedRatio) -> dict:
    d = br.to_dict()
    out = {prefix: d["ratio"], f"{prefix}_lower": d["lower"], f"{prefix}_upper": d["upper"]}
    if prefix != "detection_rate":
        out[f"{prefix}_n"] = d["n"]
        out[f"{prefix}_k"] = d["k"]
    return out


def _none_if_nan(v):
    return None if v is None or not np.isfinite(v) else float(v)


def _uncounted(det) -> np.ndarray:
    """Detections left out of purity: pre-existing sources and light of unusable injections."""
    out = np.asarray(det["preexisting"], bool).copy()
    if "near_unusable" in det.colnames:
        out |= np.asarray(det["near_unusable"], bool)
    return out


def kind_binned(merged: "MergedCatalogs", edges: np.ndarray, config: RunConfig) -> dict:
    """Completeness, purity and detection rate of one kind (``BinnedRatio`` objects)."""
    truth, det = merged.injected, merged.detections
    conf, interval = config.ratios.confidence, config.ratios.interval
    usable = np.asarray(truth["usable"], bool)
    detected = np.asarray(truth["detected"], bool)
    comp = R.completeness(np.asarray(truth["mag"], float), detected, edges, masked=~usable,
                          confidence=conf, interval=interval)
    det_mag = np.asarray(det[config.matching.mag_column], float)
    if det_mag.ndim == 2:
        det_mag = det_mag[:, 0]
    pre = _uncounted(det)
    matched = np.asarray(det["matched"], bool)
    pur = R.purity(det_mag, matched, edges, excluded=pre, confidence=conf, interval=interval)
    rate = R.detection_rate(det_mag, np.asarray(truth["mag"], float), edges, det_excluded=pre,
                            truth_masked=~usable, confidence=conf)
    return {"completeness": comp, "purity": pur, "detection_rate": rate}


def kind_summary(merged: "MergedCatalogs", edges: np.ndarray, config: RunConfig, *, nreal: int, maps_file: str | None,
                 map_edges=None) -> dict:
    """The ``summary.json`` entry of one kind."""
    truth, det = merged.injected, merged.detections
    b = kind_binned(merged, edges, config)
    binned = {"mag_edges": b["completeness"].to_dict()["edges"], "mag_centers": b["completeness"].to_dict()["centers"]}
    for name, br in b.items():
        binned.update(_flat(name, br))
    binned["confidence"] = config.ratios.confidence
    binned["interval"] = config.ratios.interval
    usable = np.asarray(truth["usable"], bool)
    counts = {
        "realizations": int(nreal),
        "injected": int(len(truth)),
        "usable": int(usable.sum()),
        "detected": int((np.asarray(truth["detected"], bool) & usable).sum()),
        "false": int(np.asarray(det["false"], bool).sum()),
        "preexisting": int(np.asarray(det["preexisting"], bool).sum()),
        "near_unusable": int(np.asarray(det["near_unusable"], bool).sum()) if "near_unusable" in det.colnames else 0,
    }
    out = {"counts": counts, "mag_range": [float(edges[0]), float(edges[-1])], "binned": binned,
           "m50_binned": _none_if_nan(R.magnitude_at(b["completeness"], 0.5)),
           "m50_binned_sd": _none_if_nan(R.magnitude_at_sd(b["completeness"], 0.5, seed=config.seed))}
    if maps_file is not None:
        out["maps"] = {"file": maps_file, "mag_edges": [float(v) for v in map_edges],
                       "bin_arcmin": config.ratios.map_bin_arcmin}
    return out


def maps_hdulist(merged: "MergedCatalogs", *, image_shape, pixel_scale: float, wcs, config: RunConfig, mag_edges) -> fits.HDUList:
    """Completeness and purity maps f(x, y, m) as FITS cubes with the binned grid's WCS.

    HDUs: ``COMPLETENESS``, ``COMPLETENESS_N``, ``COMPLETENESS_LO``,
    ``COMPLETENESS_HI``, ``PURITY``, ``PURITY_N``; each is a cube
    (nmag, ny_bins, nx_bins) whose first two axes carry the celestial WCS of the
    binned grid (rotation included) and whose third is the magnitude
    (:func:`map_cube_header`): plane ``i`` covers magnitudes
    ``MAGLO{i}``-``MAGHI{i}`` (header keywords).  A last table HDU,
    ``MAG_EDGES``, lists the planes' edges (columns ``plane``, ``mag_lo``,
    ``mag_hi``).
    """
    truth, det = merged.injected, merged.detections
    bin_pix = R.map_bin_pixels(config.ratios.map_bin_arcmin, pixel_scale)
    conf, interval = config.ratios.confidence, config.ratios.interval
    usable = np.asarray(truth["usable"], bool)
    comp = R.completeness_map(np.asarray(truth["x"], float), np.asarray(truth["y"], float),
                              np.asarray(truth["mag"], float), np.asarray(truth["detected"], bool),
                              image_shape=image_shape, bin_pix=bin_pix, mag_edges=mag_edges, masked=~usable,
                              confidence=conf, interval=interval)
    det_mag = np.asarray(det[config.matching.mag_column], float)
    if det_mag.ndim == 2:
        det_mag = det_mag[:, 0]
    pur = R.purity_map(np.asarray(det["xwin"], float), np.asarray(det["ywin"], float), det_mag,
                       np.asarray(det["matched"], bool), image_shape=image_shape, bin_pix=bin_pix,
                       mag_edges=mag_edges, excluded=_uncounted(det), confidence=conf,
                       interval=interval)
    header = map_cube_header(wcs, bin_pix, comp.shape, mag_edges)
    hdus = [fits.PrimaryHDU()]
    for name, arr in (("COMPLETENESS", comp.ratio), ("COMPLETENESS_N", comp.n), ("COMPLETENESS_LO", comp.lower),
                      ("COMPLETENESS_HI", comp.upper), ("PURITY", pur.ratio), ("PURITY_N", pur.n)):
        hdus.append(fits.ImageHDU(np.asarray(arr, dtype=np.float32 if arr.dtype.kind == "f" else np.int32),
                                  header=header, name=name))
    edges = np.asarray(mag_edges, dtype=float)
    planes = fits.BinTableHDU.from_columns([
        fits.Column(name="plane", format="J", array=np.arange(edges.size - 1, dtype=np.int32)),
        fits.Column(name="mag_lo", format="D", unit="mag", array=edges[:-1]),
        fits.Column(name="mag_hi", format="D", unit="mag", array=edges[1:]),
    ], name="MAG_EDGES")
    planes.header["COMMENT"] = "Magnitude range of each plane (third axis, 0-based) of the map cubes."
    hdus.append(planes)
    return fits.HDUList(hdus)


def map_cube_header(wcs, bin_pix: float, grid_shape, mag_edges) -> fits.Header:
    """Header of a map cube (nmag, ny_bins, nx_bins): a 3-D WCS and the plane edges as keywords.

    Axes 1 and 2 are the celestial WCS of the binned grid (:func:`ratios.map_wcs`)
    or, without an image WCS, the 0-based image pixel position of each bin's
    centre (``CTYPE`` ``X``/``Y``, unit pixel).  Axis 3 is the magnitude:
    ``CTYPE3 = 'MAG'`` with the centre of plane ``k`` at ``CRVAL3 + k CDELT3``
    when the planes are equally wide; unequal planes cannot be a linear axis,
    so it is then the plane index (``CTYPE3 = 'PLANE'``).  Either way
    ``MAGLOk``/``MAGHIk`` give plane ``k``'s edges (and the ``MAG_EDGES`` table
    of :func:`maps_hdulist`).  A WCS with SIP distortion stays 2-D (astropy
    refuses SIP in more than two dimensions).
    """
    edges = np.asarray(mag_edges, dtype=float)
    header = fits.Header()
    if wcs is not None:
        header.update(R.map_wcs(wcs, bin_pix, tuple(grid_shape)).to_header(relax=True))
    else:
        for axis, name in ((1, "X"), (2, "Y")):
            header[f"CTYPE{axis}"] = (name, f"image {name.lower()} of the bin centre, 0-based")
            header[f"CUNIT{axis}"] = ("pixel", "image pixels")
            header[f"CRPIX{axis}"] = 1.0
            header[f"CRVAL{axis}"] = (0.5 * float(bin_pix) - 0.5, "0-based image position of the first bin centre")
            header[f"CDELT{axis}"] = (float(bin_pix), "bin side in image pixels")
    if wcs is not None and getattr(wcs, "sip", None) is not None:
        # astropy reads SIP distortions only in 2-D WCSs (WCS(header) would fail on every read)
        header["COMMENT"] = "No magnitude WCS axis: SIP distortion is 2-D only; planes in MAGLOk/MAGHIk."
    else:
        _magnitude_axis(header, edges)
    header["BINPIX"] = (float(bin_pix), "side of a map bin in image pixels")
    for i, (lo, hi) in enumerate(zip(edges[:-1], edges[1:])):
        header[f"MAGLO{i}"] = (float(lo), f"bright edge of plane {i} (mag)")
        header[f"MAGHI{i}"] = (float(hi), f"faint edge of plane {i} (mag)")
    return header


def _magnitude_axis(header: fits.Header, edges: np.ndarray) -> None:
    """Make ``header`` a 3-D WCS whose third axis is the magnitude (or the plane index), in place."""
    if "WCSAXES" in header:
        header["WCSAXES"] = 3
    else:
        header.insert(0, ("WCSAXES", 3, "Number of coordinate axes"))  # before every other WCS keyword
    widths = np.diff(edges)
    equal = widths.size >= 1 and np.allclose(widths, widths[0], rtol=0.0, atol=1e-9 * max(1.0, abs(widths[0])))
    if equal:
        header["CTYPE3"] = ("MAG", "magnitude at the centre of the plane")
        header["CUNIT3"] = ("mag", "magnitudes")
        header["CRPIX3"] = (1.0, "the first plane")
        header["CRVAL3"] = (float(0.5 * (edges[0] + edges[1])), "centre of the first plane (mag)")
        header["CDELT3"] = (float(widths[0]), "magnitude width of a plane")
    else:
        header["CTYPE3"] = ("PLANE", "plane index: unequal bins, see MAGLOk/MAGHIk")
        header["CRPIX3"] = 1.0
        header["CRVAL3"] = 0.0
        header["CDELT3"] = 1.0
    if "CD1_1" in header:  # a CD matrix overrides CDELT: the third axis needs its own element
        header["CD3_3"] = header["CDELT3"]


def _faint_crossing(h, level: float) -> float:
    """Where the histogram completeness first falls below ``level`` faintward of the fitted range.

    Brightward of it the counts are sparse and star-dominated, so the ratio to
    the galaxy power law means nothing there.
    """
    sel = h.centers > h.fit_range[1]
    return R.first_crossing(h.centers[sel], h.completeness[sel], level)


def depth_summary(noise: np.ndarray, mask: np.ndarray, *, zeropoint: float, fwhm: float, det_mags,
                  psf_nea: float | None = None) -> dict:
    """Depth references: N-sigma limiting magnitudes and the histogram-count completeness.

    ``point_source_5sigma`` uses the noise-equivalent area of the injection PSF
    when ``psf_nea`` is given (else a Gaussian of the FWHM);
    ``point_source_5sigma_gaussian`` is always the Gaussian value.
    """

    sigma = float(np.median(noise[~mask])) if (~mask).any() else float(np.median(noise))
    diam = 2.0 * fwhm
    gauss = float(point_source_depth(sigma, zeropoint, fwhm, 5.0))
    out = {
        "noise_median": sigma,
        "point_source_5sigma": gauss if psf_nea is None else point_source_depth_nea(sigma, zeropoint, psf_nea, 5.0),
        "point_source_5sigma_gaussian": gauss,
        "psf_nea_pix": psf_nea,
        "aperture_5sigma": float(limiting_magnitude(sigma, zeropoint, aperture_diameter_pix=diam, nsigma=5.0)),
        "aperture_diameter_pix": diam,
        "histogram": None,
    }
    mags = np.asarray(det_mags, float)
    mags = mags[np.isfinite(mags)]
    if mags.size >= 50:
        edges = R.magnitude_edges(np.floor(mags.min()), np.ceil(mags.max()), 0.25)
        try:
            h = histogram_completeness(mags, edges)
        except ValueError as exc:  # too few sources in the fit range
            out["histogram_error"] = str(exc)
        else:
            out["histogram"] = {"slope": float(h.slope), "slope_err": float(h.slope_err),
                                "fit_range": [float(v) for v in h.fit_range],
                                "mag_centers": [float(v) for v in h.centers],
                                "completeness": [_none_if_nan(v) for v in h.completeness],
                                "m50": _none_if_nan(_faint_crossing(h, 0.5))}
    return out
