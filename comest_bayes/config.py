"""Declarative configuration: documented defaults, a TOML file, CLI overrides.

A run is configured by a :class:`RunConfig`, made of one dataclass per stage of the data flow.
Each can be built directly from Python with keyword arguments, read from a TOML file whose tables
are named after the sections (``[detection]``, ``[sourcefree]``), and patched with
``section.key=value`` overrides from the command line.  Unknown keys and wrongly typed values are
rejected with a message that names the key, the value received and the fix.  The detection
defaults are SExtractor's (the table: ``docs/detection.md``).
"""

from __future__ import annotations

import dataclasses
import difflib
import sys
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, Mapping

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - exercised on Python 3.10 only
    import tomli as tomllib

from comest_bayes.bayes.samples import SAMPLERS
from comest_bayes.errors import ConfigError
from comest_bayes.io.jsonio import jsonable

__all__ = [
    "AdaptiveConfig",
    "DetectionConfig",
    "SourceFreeConfig",
    "InjectionConfig",
    "MatchingConfig",
    "RatiosConfig",
    "FitConfig",
    "RunConfig",
    "load_config",
    "parse_override",
]

NOISE_MODES = ("auto", "background", "global", "weight")
#: Where the re-detection of an injected image takes its noise *level* (``detection.noise_level``).
NOISE_LEVELS = ("per_image", "observed")
BACKENDS = ("sep", "sextractor")


@dataclass(frozen=True)
class DetectionConfig:
    """Detection settings, with SExtractor's meaning.

    Parameters
    ----------
    thresh : float
        Detection threshold per pixel of the *filtered* image, in units of the
        noise sigma of the *unfiltered* image at that pixel (DETECT_THRESH).
    minarea : int
        Minimum number of connected pixels above threshold (DETECT_MINAREA).
    filter : str
        Convolution kernel applied before thresholding: ``"default"``
        (SExtractor's 3x3 ``default.conv``), ``"gauss_<fwhm>_<n>x<n>"`` (a
        normalised Gaussian of that FWHM in pixels), ``"none"``, or the path of
        a SExtractor ``.conv`` file.  The kernel is normalised to unit sum, as
        SExtractor's ``CONV NORM`` does, so the threshold keeps its meaning.
    back_size, back_filtersize : int
        Background mesh size in pixels and median-filter size in meshes.
    noise : {"auto", "background", "global", "weight"}
        Which sigma the threshold is relative to. ``"background"``: the
        local background RMS map (SExtractor ``WEIGHT_TYPE BACKGROUND``);
        ``"global"``: one global RMS (SExtractor's default ``WEIGHT_TYPE
        NONE``); ``"weight"``: the user's weight map, rescaled to the measured
        background RMS (``MAP_WEIGHT``/``MAP_RMS``/``MAP_VAR``); ``"auto"``:
        ``weight`` when a weight map is given, else ``background``.
    noise_level : {"per_image", "observed"}
        Which image sets the level of that sigma when an *injected* image (and
        the bare base image of the baseline detection) is re-detected.
        ``"per_image"``: measured again on every image, as SExtractor would
        (the ``background`` RMS map, or the weight map rescaled to the median
        background RMS); the injected sources raise it, and with it the
        threshold, more at higher injection densities.  ``"observed"``: the
        first detection's noise map on the observed image is used as it is
        (the weight map keeps the observed rescaling factor; the
        ``background`` mode uses the observed RMS map), so every injected
        image is thresholded at the observed image's noise.  The observed
        image's own detection is the same either way.  See
        ``docs/injection.md`` ("The injection density changes what is
        measured").
    background_level : {"per_image", "observed"}
        The same choice for the background *level* subtracted before
        thresholding: measured again on every injected image in meshes of
        ``back_size`` (``"per_image"``, SExtractor's way; the injections'
        light lifts it), or the observed image's background map
        (``"observed"``; SEP backend only, since SExtractor always measures
        its own).
    deblend_nthresh, deblend_mincont : int, float
        Deblending levels and minimum contrast.
    clean, clean_param : bool, float
        Cleaning of spurious detections near bright objects.
    phot_autoparams : (float, float)
        Kron factor and minimum radius (in units of the Kron ellipse axes) of
        the AUTO aperture.
    phot_apertures : tuple of float
        Circular aperture *diameters* in pixels.
    phot_fluxfrac : float
        Light fraction for FLUX_RADIUS.
    pixstack, sub_object_limit : int
        SEP's buffers (SExtractor's MEMORY_PIXSTACK and deblending limit).
        SEP keeps these per process; comest-bayes sets them before every
        extraction so worker processes agree.
    backend : {"sep", "sextractor"}
        The detector: SEP (library, default) or the SExtractor binary.
    """

    thresh: float = 1.5
    minarea: int = 5
    filter: str = "default"
    back_size: int = 64
    back_filtersize: int = 3
    noise: str = "auto"
    noise_level: str = "per_image"
    background_level: str = "per_image"
    deblend_nthresh: int = 32
    deblend_mincont: float = 0.005
    clean: bool = True
    clean_param: float = 1.0
    phot_autoparams: tuple = (2.5, 3.5)
    phot_apertures: tuple = (5.0,)
    phot_fluxfrac: float = 0.5
    pixstack: int = 3_000_000
    sub_object_limit: int = 4096
    backend: str = "sep"

    def __post_init__(self):
        _check(self.thresh > 0, "detection.thresh", self.thresh, "a positive number of sigma, e.g. 1.5")
        _check(self.minarea >= 1, "detection.minarea", self.minarea, "an integer >= 1, e.g. 5")
        _check(self.back_size >= 4, "detection.back_size", self.back_size, "a mesh size >= 4 pixels, e.g. 64")
        _check(self.back_filtersize >= 1 and self.back_filtersize % 2 == 1,
               "detection.back_filtersize", self.back_filtersize, "an odd integer >= 1, e.g. 3")
        _check(self.noise in NOISE_MODES, "detection.noise", self.noise, f"one of {NOISE_MODES}")
        _check(self.noise_level in NOISE_LEVELS, "detection.noise_level", self.noise_level,
               f"one of {NOISE_LEVELS}: 'per_image' re-measures the noise on every injected image, 'observed' "
               f"keeps the observed image's")
        _check(self.background_level in NOISE_LEVELS, "detection.background_level", self.background_level,
               f"one of {NOISE_LEVELS}: 'per_image' re-measures the background on every injected image, "
               f"'observed' subtracts the observed image's")
        _check(self.background_level == "per_image" or self.backend == "sep", "detection.background_level",
               self.background_level, "'per_image' with detection.backend='sextractor', which always measures "
               "its own background map (BACK_TYPE MANUAL takes one constant); use the SEP backend for 'observed'")
        _check(1 <= self.deblend_nthresh <= 64, "detection.deblend_nthresh", self.deblend_nthresh,
               "an integer from 1 to 64, e.g. 32")
        _check(0.0 <= self.deblend_mincont <= 1.0, "detection.deblend_mincont", self.deblend_mincont,
               "a contrast in [0, 1], e.g. 0.005 (1 disables deblending)")
        _check(self.clean_param > 0, "detection.clean_param", self.clean_param, "a positive number, e.g. 1.0")
        _check(len(self.phot_autoparams) == 2 and all(v > 0 for v in self.phot_autoparams),
               "detection.phot_autoparams", self.phot_autoparams, "two positive numbers, e.g. [2.5, 3.5]")
        _check(len(self.phot_apertures) >= 1 and all(v > 0 for v in self.phot_apertures),
               "detection.phot_apertures", self.phot_apertures, "positive diameters in pixels, e.g. [5.0, 10.0]")
        _check(0.0 < self.phot_fluxfrac < 1.0, "detection.phot_fluxfrac", self.phot_fluxfrac,
               "a fraction in (0, 1), e.g. 0.5")
        _check(self.pixstack >= 10_000, "detection.pixstack", self.pixstack, "an integer >= 10000, e.g. 3000000")
        _check(self.sub_object_limit >= 64, "detection.sub_object_limit", self.sub_object_limit,
               "an integer >= 64, e.g. 4096")
        _check(self.backend in BACKENDS, "detection.backend", self.backend, f"one of {BACKENDS}")


@dataclass(frozen=True)
class SourceFreeConfig:
    """How the source-free (SFI) and bright-and-big (BnB) images are made.

    Every detected segment is grown by its own radius before its pixels are
    replaced by sky draws, so that the PSF wings and galaxy outskirts below the
    detection isophote go too::

        r_i = max(dilate * fwhm, dilate_min_pix) + dilate_size * sqrt(area_i / pi)

    with ``area_i`` the segment's area in pixels.  The defaults (1.5 FWHM plus
    one isophotal radius) were chosen by measuring the mean residual in rings
    around the replaced pixels on simulated fields with known sky: +0.01 to
    +0.02 sigma per pixel against +0.5 to +0.7 sigma for the bare segments, with
    25-33 % of the pixels replaced (``docs/sourcefree.md``).

    Parameters
    ----------
    dilate : float
        Fixed part of the growth radius in units of the seeing FWHM.
    dilate_size : float
        Part of the growth radius proportional to the object's isophotal
        radius ``sqrt(area / pi)``: the wings of bright objects reach further
        beyond their isophote.
    dilate_min_pix : int
        Lower bound of the fixed part, pixels.
    kron_mask : float
        Additionally replace, for every source, the ellipse of ``kron_mask``
        times its Kron radius (0 disables; the default, since growing by
        ``dilate_size`` removes the wings with fewer pixels).
    reestimate_background : bool
        Estimate the background level and RMS again with the replaced pixels
        masked before drawing the sky (a background estimated with the sources
        present is biased high).
    back_size, back_filtersize : int
        Mesh size (pixels) and median-filter size (meshes) of that re-estimate;
        0 takes the detection's values when its metadata records them, else
        SExtractor's defaults 64 and 3.
    bnb : bool
        Also make the "bright and big" image.
    bnb_snr_min, bnb_area_min : float, int
        Sources with AUTO signal-to-noise >= ``bnb_snr_min`` *and* isophotal
        area >= ``bnb_area_min`` pixels are kept (with their grown footprint)
        in the BnB image; all others are replaced as in the SFI.
    warn_replaced, max_replaced : float
        Fractions of the unmasked pixels of the image injected on
        (``injection.on``) that may be replaced by sky draws before the run
        warns (default 0.5) and before it is refused (default 0.9; 1 never
        refuses): beyond them the completeness is measured on a fitted sky
        rather than the observed noise (crowded fields).  The refusal comes
        before anything is written and names the alternatives
        (``injection.on = "observed"`` or ``"bnb"``).
    """

    dilate: float = 1.5
    dilate_size: float = 1.0
    dilate_min_pix: int = 2
    kron_mask: float = 0.0
    reestimate_background: bool = True
    back_size: int = 0
    back_filtersize: int = 0
    bnb: bool = True
    bnb_snr_min: float = 50.0
    bnb_area_min: int = 100
    warn_replaced: float = 0.5
    max_replaced: float = 0.9

    def __post_init__(self):
        _check(self.dilate >= 0, "sourcefree.dilate", self.dilate, "a non-negative multiple of the FWHM, e.g. 1.5")
        _check(self.dilate_size >= 0, "sourcefree.dilate_size", self.dilate_size,
               "a non-negative multiple of the isophotal radius, e.g. 1.0")
        _check(self.dilate_min_pix >= 0, "sourcefree.dilate_min_pix", self.dilate_min_pix,
               "a non-negative integer, e.g. 2")
        _check(self.kron_mask >= 0, "sourcefree.kron_mask", self.kron_mask,
               "a non-negative factor, e.g. 2.5 (0 disables)")
        _check(self.back_size == 0 or self.back_size >= 4, "sourcefree.back_size", self.back_size,
               "0 (the detection's mesh) or a mesh size >= 4 pixels, e.g. 64")
        _check(self.back_filtersize == 0 or (self.back_filtersize >= 1 and self.back_filtersize % 2 == 1),
               "sourcefree.back_filtersize", self.back_filtersize,
               "0 (the detection's) or an odd integer >= 1, e.g. 3")
        _check(self.bnb_snr_min > 0, "sourcefree.bnb_snr_min", self.bnb_snr_min, "a positive SNR, e.g. 50")
        _check(self.bnb_area_min >= 1, "sourcefree.bnb_area_min", self.bnb_area_min,
               "an integer >= 1 pixel, e.g. 100")
        _check(0 < self.warn_replaced <= 1, "sourcefree.warn_replaced", self.warn_replaced,
               "a fraction in (0, 1], e.g. 0.5")
        _check(self.max_replaced <= 1, "sourcefree.max_replaced", self.max_replaced,
               "a fraction up to 1 (never refuse), e.g. 0.9")
        if self.warn_replaced > self.max_replaced:
            raise ConfigError(f"sourcefree.warn_replaced = {self.warn_replaced} is above sourcefree.max_replaced = "
                              f"{self.max_replaced}: a run warns from the first fraction and refuses from the second, "
                              "so warn_replaced must not exceed max_replaced; lower warn_replaced or raise "
                              "max_replaced (at most 1).")


KINDS = ("point", "buldisk", "sersic", "cosmos", "observed")
PLACEMENTS = ("uniform", "grid", "halton")
PSF_KINDS = ("moffat", "gaussian", "kolmogorov")
#: Images injections may be drawn on: source-free, bright-and-big, the observed image itself.
INJECTION_TARGETS = ("sfi", "bnb", "observed")


@dataclass(frozen=True)
class InjectionConfig:
    """What is injected, where, and how many times.

    Parameters
    ----------
    kinds : tuple of str
        Source kinds, each run separately: ``point`` (the PSF), ``buldisk``
        (de Vaucouleurs bulge + exponential disk), ``sersic``, ``cosmos`` (real
        COSMOS galaxies from ``cosmos_dir``), ``observed`` (magnitudes and sizes
        drawn from the image's own detection catalog).
    nsims : int
        Realizations (simulated images) per kind.
    density : float
        Mean number of injections per arcmin^2 of unmasked area (Poisson-drawn);
        0 (default) for automatic, per kind from the image
        (:func:`comest_bayes.pipeline.preflight.choose_density`): ComEst's published 15,
        raised on a small field of fine pixels towards 100 per realization (at
        most a quarter injection per background mesh and half of what random
        packing holds at the minimum separation), lowered to what the placement
        holds where 15 is more; the choice goes to the log and ``run.json``.
    mag_range : tuple of float
        (bright, faint) limits of the uniform magnitude distribution; empty for
        automatic: from the image's 5-sigma point-source depth m5 as
        (m5 - 5, m5 + 1.5).
    placement : {"uniform", "grid", "halton"}
        Uniform random with a minimum separation, a jittered grid, or the
        quasi-random Halton sequence.
    min_sep : float
        Minimum separation between injections in arcsec, so injections do not
        blend with each other; 0 (default) for automatic: 4 FWHM for point
        sources (with a ``mag_range`` set far brighter than the detection
        limit, the reach of its brightest injection: ``docs/injection.md``),
        max(4 FWHM, 8 x the largest half-light radius) for galaxies.
    psf : str
        ``moffat``, ``gaussian``, ``kolmogorov`` (of the image FWHM) or the path
        of a FITS PSF image.
    psf_pixel_scale : float
        Pixel scale (arcsec) of a FITS PSF image; 0 means the image's.
    moffat_beta : float
        Moffat beta; 0 (default) for the median beta of the Moffat fits to
        the image's stars, or 3 when they could not be fitted (see
        :func:`comest_bayes.detect.psf.injection_psf`).
    hlr_range, q_range, bulge_fraction_range, sersic_n_range : tuple of float
        Uniform ranges of half-light radius (arcsec), axis ratio, bulge flux
        fraction and Sersic index.
    cosmos_dir, cosmos_file : str
        GalSim RealGalaxyCatalog directory and catalog file name (``cosmos``).
    on : {"sfi", "bnb", "observed"}
        Inject onto the source-free image (default), the bright-and-big image,
        or the observed image itself (as Balrog does: injections then meet the
        real sources, which the baseline detection marks as pre-existing; the
        choice for crowded fields, where the source-free image would replace
        most of the pixels).
    photon_noise : bool
        Add the sources' Poisson noise when the gain is known.
    write_images : bool
        Also write every simulated image (large!).
    """

    kinds: tuple = ("point", "buldisk")
    nsims: int = 10
    density: float = 0.0
    mag_range: tuple = ()
    placement: str = "uniform"
    min_sep: float = 0.0
    psf: str = "moffat"
    psf_pixel_scale: float = 0.0
    moffat_beta: float = 0.0
    hlr_range: tuple = (0.35, 0.75)
    q_range: tuple = (0.4, 1.0)
    bulge_fraction_range: tuple = (0.0, 1.0)
    sersic_n_range: tuple = (0.5, 4.0)
    cosmos_dir: str = ""
    cosmos_file: str = "real_galaxy_catalog_26_extension_example.fits"
    on: str = "sfi"
    photon_noise: bool = True
    write_images: bool = False

    def __post_init__(self):
        _check(len(self.kinds) >= 1 and all(k in KINDS for k in self.kinds), "injection.kinds", self.kinds,
               f"a list of kinds from {KINDS}")
        _check(self.nsims >= 1, "injection.nsims", self.nsims, "an integer >= 1")
        _check(0 <= self.density < float("inf"), "injection.density", self.density,
               "0 (automatic) or a positive density per arcmin^2, e.g. 15")
        _check(len(self.mag_range) == 0 or (len(self.mag_range) == 2 and self.mag_range[0] < self.mag_range[1]),
               "injection.mag_range", self.mag_range, "[] (automatic) or [bright, faint] with bright < faint")
        _check(self.placement in PLACEMENTS, "injection.placement", self.placement, f"one of {PLACEMENTS}")
        _check(self.min_sep >= 0, "injection.min_sep", self.min_sep, "a non-negative separation in arcsec")
        _check(self.moffat_beta == 0 or self.moffat_beta > 1.1, "injection.moffat_beta", self.moffat_beta,
               "0 (the stars' fitted beta) or a Moffat beta > 1.1, e.g. 3")
        for name in ("hlr_range", "q_range", "bulge_fraction_range", "sersic_n_range"):
            value = getattr(self, name)
            _check(len(value) == 2 and 0 <= value[0] <= value[1], f"injection.{name}", value,
                   "[low, high] with 0 <= low <= high")
        _check(0 < self.q_range[0] and self.q_range[1] <= 1, "injection.q_range", self.q_range,
               "axis ratios in (0, 1]")
        _check(self.bulge_fraction_range[1] <= 1, "injection.bulge_fraction_range", self.bulge_fraction_range,
               "fractions in [0, 1]")
        _check(0.3 <= self.sersic_n_range[0] and self.sersic_n_range[1] <= 6.2, "injection.sersic_n_range",
               self.sersic_n_range, "indices within GalSim's supported 0.3-6.2")
        _check(self.hlr_range[0] > 0, "injection.hlr_range", self.hlr_range, "positive radii in arcsec")
        _check(self.on in INJECTION_TARGETS, "injection.on", self.on, "'sfi', 'bnb' or 'observed'")


@dataclass(frozen=True)
class MatchingConfig:
    """One-to-one matching of injections to detections.

    Parameters
    ----------
    radius_fwhm : float
        Positional tolerance in units of the seeing FWHM (default 1).
    mag_tol : float
        Largest accepted ``|measured - true|`` magnitude difference (default 1.5).
    mag_column : str
        Detection-catalog magnitude compared with the truth (default mag_auto).
    exclude_clean_zone : bool
        Leave out of the usable injections (truth flag 8) every injection
        lying within SExtractor's cleaning reach, ``10 x (a_i + sigma_PSF)``
        pixels, of a detected injection ``i`` of larger true flux, so that no
        counted injection can have been removed by the cleaning of another
        injection's wings (``detection.clean``; without cleaning nothing is
        left out).  See ``docs/injection.md`` ("The injection density changes
        what is measured").
    """

    radius_fwhm: float = 1.0
    mag_tol: float = 1.5
    mag_column: str = "mag_auto"
    exclude_clean_zone: bool = False

    def __post_init__(self):
        _check(self.radius_fwhm > 0, "matching.radius_fwhm", self.radius_fwhm, "a positive multiple of the FWHM")
        _check(self.mag_tol > 0, "matching.mag_tol", self.mag_tol, "a positive magnitude tolerance, e.g. 1.5")


@dataclass(frozen=True)
class RatiosConfig:
    """Binning of the raw ratios (the paper's Eq. 1-4).

    Parameters
    ----------
    mag_bin : float
        Magnitude bin width for f_com(m), f_pur(m), f_dr(m).
    map_bin_arcmin : float
        Spatial bin size of the maps, arcmin.
    map_mag_edges : tuple of float
        Magnitude bin edges of the maps; empty for automatic (three bins
        centred where the binned completeness crosses 0.9, 0.5 and 0.1).
    confidence : float
        Probability content of the binomial intervals (0.6827 = 1 sigma).
    interval : {"wilson", "jeffreys", "flat"}
        Binomial interval method (astropy.stats.binom_conf_interval).
    """

    mag_bin: float = 0.2
    map_bin_arcmin: float = 1.0
    map_mag_edges: tuple = ()
    confidence: float = 0.6827
    interval: str = "wilson"

    def __post_init__(self):
        _check(self.mag_bin > 0, "ratios.mag_bin", self.mag_bin, "a positive bin width in mag")
        _check(self.map_bin_arcmin > 0, "ratios.map_bin_arcmin", self.map_bin_arcmin, "a positive size in arcmin")
        _check(0 < self.confidence < 1, "ratios.confidence", self.confidence, "a probability in (0, 1)")
        _check(self.interval in ("wilson", "jeffreys", "flat"), "ratios.interval", self.interval,
               "wilson, jeffreys or flat")


@dataclass(frozen=True)
class FitConfig:
    """The Bayesian completeness model fitted to the per-injection outcomes.

    Parameters
    ----------
    model : str
        A specification in ``models/`` by name (``logistic``,
        ``logistic_depth``, ...) or a path to a TOML file; ``auto`` (default)
        fits the candidates of ``models/auto.toml`` from the simplest upward
        and keeps the simplest whose PSIS-LOO score is within the margin of the
        best; ``none`` skips the fit (binned ratios only).
    purity_model : str
        Specification of the purity model fitted to the counted detections
        (matched vs false) in measured magnitude; ``none`` to skip.
    sampler : {"auto", "importance", "nuts", "emcee"}
        How the chosen model's posterior is drawn: ``importance`` sampling
        from its Laplace approximation (PSIS-checked), ``nuts`` (BlackJAX's
        No-U-Turn sampler, preconditioned by the Laplace approximation),
        ``emcee`` (the reference), or ``auto`` (default): importance sampling;
        when its Pareto k-hat exceeds 0.7 or its effective sample size is
        below ``min_ess``, importance sampling again with heavier tails, and
        NUTS when that fails too.
    min_ess : float
        Effective sample size the posterior draws must reach (per parameter
        for emcee and NUTS).
    max_steps : int
        Longest emcee run (steps per walker); a shorter convergence warns.
    map_step_arcmin : float
        Bin of the posterior m50(x, y) map, arcmin.
    """

    model: str = "auto"
    purity_model: str = "purity"
    sampler: str = "auto"
    min_ess: float = 1000.0
    max_steps: int = 20000
    map_step_arcmin: float = 0.5

    def __post_init__(self):
        _check(bool(self.model), "fit.model", self.model, "a model name, a TOML path, 'auto' or 'none'")
        _check(self.sampler in SAMPLERS, "fit.sampler", self.sampler, ", ".join(SAMPLERS))
        _check(self.min_ess >= 10, "fit.min_ess", self.min_ess, "an effective sample size >= 10, e.g. 1000")
        _check(self.max_steps >= 100, "fit.max_steps", self.max_steps, "an integer >= 100")
        _check(self.map_step_arcmin > 0, "fit.map_step_arcmin", self.map_step_arcmin, "a positive size in arcmin")


@dataclass(frozen=True)
class AdaptiveConfig:
    """Adaptive injection (``docs/adaptive.md``): batches designed from the posterior until a precision.

    Off unless ``precision`` is set.  The first ``pilot_nsims`` realizations
    of each kind inject uniformly (the published design); each later batch
    of ``ceil(growth x realizations so far)`` realizations draws its
    magnitudes from the design built from the current posterior, with
    ``uniform_share`` of them uniform, until the 68% half-width of the kind's
    image-average m50 (with ``target = "f"``: the posterior standard
    deviation of the image-average f at each of ``magnitudes``) is at most
    ``precision`` or ``max_nsims`` realizations ran.  ``injection.nsims`` is
    then not used.

    Parameters
    ----------
    precision : float
        Target 68% half-width of m50 (mag), or with ``target = "f"`` the
        target sd of f (a fraction below 0.5); 0 (default) turns adaptive
        injection off.
    pilot_nsims : int
        Uniform realizations per kind before the first design.
    growth : float
        Each batch holds this fraction of the realizations so far (at least 1).
    max_nsims : int
        Most realizations per kind.
    uniform_share : float
        Share of each adaptive batch drawn uniformly over the magnitude range.
    target : {"m50", "curve", "f"}
        What the design aims at: the m50, the whole transition (both stop on
        the m50 half-width), or f at ``magnitudes`` (and stops on it).
    magnitudes : tuple of float
        With ``target = "f"`` (CLI ``--precision-at``): the magnitudes at
        which f must be precise, inside the injected range.
    """

    precision: float = 0.0
    pilot_nsims: int = 2
    growth: float = 0.5
    max_nsims: int = 40
    uniform_share: float = 0.15
    target: str = "m50"
    magnitudes: tuple = ()

    @property
    def enabled(self) -> bool:
        return self.precision > 0

    def __post_init__(self):
        _check(self.precision >= 0 and self.precision < float("inf"), "adaptive.precision", self.precision,
               "a finite target half-width of m50 in mag (e.g. 0.02), or 0 for the uniform design")
        _check(isinstance(self.pilot_nsims, int) and self.pilot_nsims >= 1, "adaptive.pilot_nsims",
               self.pilot_nsims, "an integer >= 1")
        _check(self.growth > 0, "adaptive.growth", self.growth, "a positive fraction, e.g. 0.5")
        _check(isinstance(self.max_nsims, int) and self.max_nsims >= self.pilot_nsims, "adaptive.max_nsims",
               self.max_nsims, "an integer >= adaptive.pilot_nsims")
        _check(0.0 <= self.uniform_share <= 1.0, "adaptive.uniform_share", self.uniform_share, "a fraction in [0, 1]")
        _check(self.target in ("m50", "curve", "f"), "adaptive.target", self.target, "m50, curve or f")
        if self.target == "f":
            _check(len(self.magnitudes) > 0 and all(-float("inf") < m < float("inf") for m in self.magnitudes),
                   "adaptive.magnitudes", list(self.magnitudes),
                   "with adaptive.target = 'f', the finite magnitudes at which f must be precise, e.g. [23.5, 24.0]")
            _check(self.precision < 0.5, "adaptive.precision", self.precision,
                   "with adaptive.target = 'f', a target sd of f below 0.5 (e.g. 0.02)")
        else:
            _check(not self.magnitudes, "adaptive.magnitudes", list(self.magnitudes),
                   f"no magnitudes with adaptive.target = {self.target!r} (they are read only with target 'f')")


@dataclass(frozen=True)
class RunConfig:
    """All settings of one run; one attribute per stage section."""

    detection: DetectionConfig = field(default_factory=DetectionConfig)
    sourcefree: SourceFreeConfig = field(default_factory=SourceFreeConfig)
    injection: InjectionConfig = field(default_factory=InjectionConfig)
    matching: MatchingConfig = field(default_factory=MatchingConfig)
    ratios: RatiosConfig = field(default_factory=RatiosConfig)
    fit: FitConfig = field(default_factory=FitConfig)
    adaptive: AdaptiveConfig = field(default_factory=AdaptiveConfig)
    seed: int = 0

    def __post_init__(self):
        _check(isinstance(self.seed, int) and not isinstance(self.seed, bool) and self.seed >= 0,
               "seed", self.seed, "a non-negative integer")

    def to_dict(self) -> dict:
        """Plain-JSON form (tuples become lists), as written to ``run.json``."""
        return jsonable(dataclasses.asdict(self))

    def replace(self, **sections) -> "RunConfig":
        return dataclasses.replace(self, **sections)


_SECTIONS = {"detection": DetectionConfig, "sourcefree": SourceFreeConfig, "injection": InjectionConfig,
             "matching": MatchingConfig, "ratios": RatiosConfig, "fit": FitConfig, "adaptive": AdaptiveConfig}


def _check(ok: bool, key: str, value: Any, expected: str) -> None:
    if not ok:
        raise ConfigError(f"invalid {key} = {value!r}: expected {expected}.")


def _coerce(section: str, name: str, default: Any, value: Any) -> Any:
    """Convert a TOML/CLI value to the type of the field's default."""
    key = f"{section}.{name}"
    try:
        if isinstance(default, bool):
            if isinstance(value, str):
                low = value.strip().lower()
                if low in ("true", "yes", "y", "1", "on"):
                    return True
                if low in ("false", "no", "n", "0", "off"):
                    return False
                raise ValueError
            if isinstance(value, bool):
                return value
            raise ValueError
        if isinstance(default, int):
            if isinstance(value, bool):
                raise ValueError
            number = float(value) if isinstance(value, str) else value
            if isinstance(number, float) and not number.is_integer():
                raise ValueError
            return int(number)
        if isinstance(default, float):
            if isinstance(value, bool):
                raise ValueError
            return float(value)
        if isinstance(default, tuple):
            if isinstance(value, str):
                value = [v for v in value.replace("[", "").replace("]", "").split(",") if v.strip()]
            if not isinstance(value, (list, tuple)):
                value = [value]
            if default and isinstance(default[0], str):
                return tuple(str(v).strip() for v in value)
            return tuple(float(v) for v in value)
        if isinstance(default, str):
            if not isinstance(value, str):
                raise ValueError
            return value
    except (TypeError, ValueError):
        if isinstance(default, tuple):
            want = ("a comma-separated list of names, e.g. point,buldisk" if default and isinstance(default[0], str)
                    else "a comma-separated list of numbers, e.g. 23.5,24.0")
            raise ConfigError(f"invalid {key} = {value!r}: expected {want}.") from None
        raise ConfigError(
            f"invalid {key} = {value!r}: expected a value of type {type(default).__name__} "
            f"like the default {default!r}."
        ) from None
    return value


def _section_from_mapping(section: str, cls, mapping: Mapping[str, Any], base=None):
    base = base if base is not None else cls()
    names = {f.name: f for f in fields(cls)}
    values = {}
    for key, value in mapping.items():
        if key not in names:
            close = difflib.get_close_matches(key, names, n=1)
            hint = f" Did you mean '{section}.{close[0]}'?" if close else ""
            raise ConfigError(
                f"unknown setting '{section}.{key}'.{hint} Valid keys of [{section}]: "
                f"{', '.join(sorted(names))}."
            )
        values[key] = _coerce(section, key, getattr(base, key), value)
    return dataclasses.replace(base, **values)


def _require_table(section: str, cls, value: Any, where: str) -> None:
    """A section must be a table of settings, not a value (``detection = 5``)."""
    if isinstance(value, Mapping):
        return
    example = fields(cls)[0]
    raise ConfigError(
        f"'{section}' {where} is a value ({value!r}), but it names a section of settings: write them under a "
        f"[{section}] table, e.g. [{section}] then {example.name} = {_toml_value(example.default)}."
    )


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return f'"{value}"'
    if isinstance(value, tuple):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    return repr(value)


def parse_override(text: str) -> tuple[str, str, str]:
    """Split a ``section.key=value`` override into its three parts."""
    if "=" not in text or "." not in text.split("=", 1)[0]:
        raise ConfigError(
            f"cannot read the override {text!r}: write it as section.key=value, "
            f"e.g. detection.thresh=2.0."
        )
    lhs, value = text.split("=", 1)
    section, key = lhs.strip().split(".", 1)
    return section, key.strip(), value.strip()


def override_items(overrides) -> list[tuple[str, str, Any, str]]:
    """``(section, key, value, label)`` of overrides in any of their forms, in order (a later one wins).

    The forms: ``"detection.thresh=2"``, a list of such strings, a mapping of dotted keys
    ``{"detection.thresh": 2}``, or of sections ``{"detection": {"thresh": 2}}`` (the last two may mix).
    Text values are parsed later, as a TOML file's settings are; other values are taken as given.
    ``label`` is the override as given, for messages.
    """
    if overrides is None:
        return []
    if isinstance(overrides, str):
        overrides = [overrides]
    items = []
    if isinstance(overrides, Mapping):
        for name, value in overrides.items():
            if isinstance(value, Mapping):
                items += [(str(name), str(key), v, f"{name}.{key}") for key, v in value.items()]
            elif "." in str(name):
                section, key = str(name).split(".", 1)
                items.append((section.strip(), key.strip(), value, str(name)))
            else:
                raise ConfigError(f"cannot read the override {name!r}: {value!r}: give {{'section.key': value}} or "
                                  f"{{'section': {{'key': value}}}}, e.g. {{'detection.thresh': 2.0}}.")
        return items
    for text in overrides:
        if not isinstance(text, str):
            raise ConfigError(f"cannot read the override {text!r}: give 'section.key=value' strings, e.g. "
                              "'detection.thresh=2.0', or a mapping.")
        items.append((*parse_override(text), text))
    return items


def load_config(path: str | Path | None = None, overrides: list[str] | Mapping | None = None,
                seed: int | None = None) -> RunConfig:
    """Build a :class:`RunConfig` from defaults, an optional TOML file and overrides.

    Parameters
    ----------
    path : str or Path, optional
        TOML file with ``[detection]`` and ``[sourcefree]`` tables (and an
        optional top-level ``seed``).
    overrides : str, list of str or mapping, optional
        ``"detection.thresh=2"``, ``["detection.thresh=2", ...]``, ``{"detection.thresh": 2}`` or
        ``{"detection": {"thresh": 2}}`` (:func:`override_items`); applied after the file.
    seed : int, optional
        Root seed; overrides the file's.
    """
    data: dict[str, Any] = {}
    if path is not None:
        path = Path(path)
        if not path.is_file():
            what = "is a folder, not a file" if path.is_dir() else "does not exist"
            raise ConfigError(f"configuration file {str(path)!r} {what}; check the --config path.")
        try:
            data = tomllib.loads(path.read_text(encoding="utf-8"))
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"configuration file {str(path)!r} is not valid TOML: {exc}.") from None
        except UnicodeDecodeError:
            raise ConfigError(f"configuration file {str(path)!r} is not a text file (not UTF-8); "
                              f"give a TOML file.") from None
        except OSError as exc:
            raise ConfigError(f"configuration file {str(path)!r} cannot be read: {exc.strerror or exc}.") from None

    for name, cls in _SECTIONS.items():
        _require_table(name, cls, data.get(name, {}), f"in {str(path)!r}")
    merged: dict[str, dict] = {name: dict(data.get(name, {})) for name in _SECTIONS}
    top_seed = data.get("seed", 0)
    extra = set(data) - set(_SECTIONS) - {"seed"}
    if extra:
        raise ConfigError(
            f"unknown table(s) {sorted(extra)} in {str(path)!r}; valid tables: "
            f"{sorted(_SECTIONS)} and the top-level key 'seed'."
        )
    for section, key, value, label in override_items(overrides):
        if section not in _SECTIONS:
            raise ConfigError(f"unknown section {section!r} in override {label!r}; valid sections: "
                              f"{sorted(_SECTIONS)}.")
        merged[section][key] = value
    sections = {name: _section_from_mapping(name, cls, merged[name]) for name, cls in _SECTIONS.items()}
    final_seed = seed if seed is not None else top_seed
    if isinstance(final_seed, bool) or not isinstance(final_seed, int):
        raise ConfigError(f"invalid seed = {final_seed!r}: expected a non-negative integer.")
    return RunConfig(seed=final_seed, **sections)
