"""The files of a run directory: the one place their names are spelled.

Every name is relative to the run directory (POSIX separators); join it with the directory
(:meth:`comest_bayes.io.rundir.RunDirectory.file`, :meth:`comest_bayes.io.run.Run.file`).
What each file holds is described in the README ("What a run produces").
"""

from __future__ import annotations

__all__ = [
    "RUN", "LOCK", "SUMMARY", "REPORT", "DETECTION", "SEGMENTATION", "BACKGROUND", "RMS", "NOISE", "MASK",
    "BASELINE", "BASELINE_SEGMENTATION", "SFI", "BNB", "OBSERVED", "BASE_IMAGES", "CATALOGS", "CATALOG_DIR",
    "POSTERIOR_DIR", "MAPS_DIR",
    "SIMS_DIR", "DESIGNS_DIR", "FIGURES_DIR", "LF_DIR", "INPUTS_DIR",
    "catalog", "posterior", "binned_maps", "m50_map", "realization", "realization_image", "realization_glob", "design", "figure",
    "lf_dir", "LF_POSTERIOR", "LF_JSON",
]

#: The run's record: configuration fingerprint, stages done, image facts, CPU times.
RUN = "run.json"
#: Held while a process works on the run (pid, host, start time).
LOCK = "run.lock"
#: Every number of the run: binned ratios, models, intervals, warnings.
SUMMARY = "summary.json"
#: The self-contained HTML report.
REPORT = "report.html"

# --- detection on the observed image
DETECTION = "detection.fits"
SEGMENTATION = "segmentation.fits"
BACKGROUND = "background.fits"
RMS = "rms.fits"
NOISE = "noise.fits"
MASK = "mask.fits"
#: Detection on the image the injections go onto (the baseline that false detections are judged against).
BASELINE = "baseline.fits"
#: Its segmentation, when the injections go onto the observed image and the baseline is not the first
#: detection itself (which is ``SEGMENTATION``).
BASELINE_SEGMENTATION = "baseline_segmentation.fits"

# --- the images injections go onto
SFI = "sfi.fits"
BNB = "bnb.fits"
OBSERVED = "observed.fits"
#: Base image name -> file.
BASE_IMAGES = {"sfi": SFI, "bnb": BNB, "observed": OBSERVED}

# --- folders
CATALOG_DIR = "catalogs"
POSTERIOR_DIR = "posterior"
MAPS_DIR = "maps"
SIMS_DIR = "sims"
DESIGNS_DIR = "designs"
FIGURES_DIR = "figures"
LF_DIR = "lf"
#: Inputs a command made itself (the demo tile), kept inside the run directory.
INPUTS_DIR = "inputs"

#: The merged catalogs of each kind: every injection, matched pairs, unmatched injections, false
#: detections, and the per-injection outcome table the model is fitted to.
CATALOGS = ("injected", "matched", "unmatched", "false", "outcomes")

# --- number-count fits (under lf/<name>/)
LF_POSTERIOR = "lf_posterior.npz"
LF_JSON = "lf.json"


def catalog(kind: str, name: str) -> str:
    """A merged catalog of one kind (``name`` one of :data:`CATALOGS`)."""
    return f"{CATALOG_DIR}/{kind}_{name}.fits"


def posterior(kind: str, quantity: str = "completeness") -> str:
    """The saved posterior of one kind's completeness (or purity) model."""
    return f"{POSTERIOR_DIR}/{kind}_{quantity}.npz"


def binned_maps(kind: str) -> str:
    """The binned completeness and purity maps of one kind."""
    return f"{MAPS_DIR}/{kind}_maps.fits"


def m50_map(kind: str) -> str:
    """The posterior m50(x, y) map of one kind (spatial models only)."""
    return f"{MAPS_DIR}/{kind}_m50.fits"


def realization(kind: str, index: int) -> str:
    """The result table of one realization (truth and detections), relative to :data:`SIMS_DIR`."""
    return f"{kind}/r{index:05d}.fits"


def realization_image(kind: str, index: int) -> str:
    """The injected image of one realization (kept only when asked for), relative to :data:`SIMS_DIR`."""
    return f"{kind}/image_r{index:05d}.fits"


def realization_glob(kind: str = "*") -> str:
    """Glob of the realization tables of one kind (default every kind) under :data:`SIMS_DIR`."""
    return f"{kind}/r[0-9]*.fits"


def design(kind: str, batch: int) -> str:
    """The magnitude design of one adaptive batch."""
    return f"{DESIGNS_DIR}/{kind}_batch{batch}.json"


def figure(name: str) -> str:
    """A figure of the report."""
    return f"{FIGURES_DIR}/{name}.png"


def lf_dir(name: str) -> str:
    """The folder of one number-count fit."""
    return f"{LF_DIR}/{name}"
