"""The fits around the numerics: the fit stage's worker task, and ``comest-bayes fit`` on an outcome table.

:func:`fit_task` reads one kind's catalogs and maps from a run directory and calls
:func:`comest_bayes.bayes.fit.fit_kind` (a picklable task for the executors);
:func:`fit_outcome_file` reads an outcome table made by any injection pipeline (and optionally its
noise map and mask), fits it, and writes ``summary.json``, the posterior and a figure.
"""

from __future__ import annotations

import math
import time
import traceback
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
from astropy.io import fits
from astropy.table import Table

from comest_bayes.bayes.fit import MIN_CLASS, FitEntry, fit_kind, purity_outcomes
from comest_bayes.bayes.model import padded_size, padding_floor
from comest_bayes.bayes.outcomes import compress_for, covariates_from_outcomes, outcome_flags
from comest_bayes.bayes.spec import load_spec
from comest_bayes.config import RunConfig
from comest_bayes.errors import InputError
from comest_bayes.io import layout
from comest_bayes.io.jsonio import dumps
from comest_bayes.ratios import binned as R
from comest_bayes.config import FitConfig
from comest_bayes.io.rundir import atomic_path
from comest_bayes.report.plots import save_figure
from comest_bayes.report.plots.completeness import ratio_curve
from comest_bayes.report.plots.data import BinnedCurve, PosteriorBand

__all__ = ["fit_task", "fit_tasks", "FitFailure", "fit_outcome_file", "OUTCOME_COLUMNS"]


def fit_task(task: dict) -> tuple:
    """Run :func:`~comest_bayes.bayes.fit.fit_kind` from file paths (a picklable task for the executors).

    ``task`` holds ``run_dir``, ``kind``, ``quantity``, ``requested``, ``config``, ``image_shape``,
    ``wcs_header``, ``mag_range``, ``mag_centers`` and optionally ``shared_maps``
    (:func:`comest_bayes.bayes.fit.shared_maps`: what every fit of the run takes from the noise map and mask, computed
    once).  Returns ``(posterior or None, FitEntry)``; the posterior is returned without its compiled
    model, the entry with the task's warnings and CPU seconds.
    """
    c0 = time.process_time()
    run = Path(task["run_dir"])
    kind, quantity, config = task["kind"], task["quantity"], task["config"]
    table, outcome_column, skipped = _task_table(task)
    if skipped:
        return None, FitEntry(name=None, requested=task["requested"], cpu_seconds=0.0, skipped=skipped)
    shared = task.get("shared_maps") or {}
    footprints, noise_grid = shared.get("footprints") or {}, shared.get("noise_grid")
    # the noise map is read only if the fit needs a footprint histogram or grid the run did not pass (e.g. the
    # position-resolved cells of an escalated width selection)
    def noise():
        return fits.getdata(run / layout.NOISE).astype(np.float32)
    mask = fits.getdata(run / layout.MASK).astype(bool)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        post, entry = fit_kind(table, kind=kind, quantity=quantity, requested=task["requested"], config=config,
                               image_shape=task["image_shape"], noise=noise, mask=mask,
                               wcs_header=task["wcs_header"], mag_range=task["mag_range"],
                               mag_centers=task["mag_centers"], outcome_column=outcome_column,
                               footprints=footprints, noise_grid=noise_grid)
    entry = replace(entry, warnings=tuple(sorted(set(entry.warnings) | {str(w.message) for w in caught})),
                    cpu_seconds=round(time.process_time() - c0, 3))
    post.use_model(None)  # the compiled model stays in this process
    return post, entry


def _task_table(task: dict):
    """The outcome table of a fit task: ``(table, outcome column, None)``, or ``(None, None, why)`` for a purity
    fit with too few detections of a class."""
    run, kind = Path(task["run_dir"]), task["kind"]
    if task["quantity"] == "completeness":
        return Table.read(run / layout.catalog(kind, "outcomes"), mask_invalid=False), "detected", None
    table = purity_outcomes(Table.read(run / layout.catalog(kind, "matched"), mask_invalid=False),
                            Table.read(run / layout.catalog(kind, "false"), mask_invalid=False),
                            task["config"].matching.mag_column)
    nreal = int(np.sum(table["real"]))
    nfalse = len(table) - nreal
    if min(nreal, nfalse) < MIN_CLASS:
        return None, None, (f"{nreal} real and {nfalse} false detections: a purity model needs at least {MIN_CLASS} "
                            f"of each; see the binned purity")
    return table, "real", None


def group_padding(tasks: list) -> int:
    """The padded cell count the fits of ``tasks`` (one model, one worker) can share: the largest of their own.

    Each task's outcomes are compressed as its fit will compress them (a few tens of ms); a task
    that cannot be read counts for nothing (its fit reports the error).
    """
    size = 0
    for task in tasks:
        try:
            table, column, skipped = _task_table(task)
            if skipped:
                continue
            cov, outcome, meta = covariates_from_outcomes(table, image_shape=task["image_shape"], outcome_column=column)
            size = max(size, padded_size(compress_for(load_spec(task["requested"]), cov, outcome, meta=meta).ncells))
        except Exception:  # the fit itself raises it, with its context
            continue
    return size


def fit_tasks(tasks: list) -> list:
    """:func:`fit_task` of each task in turn, in this one process: a list of their results.

    A worker process traces (and compiles, or loads from the compilation cache) the programs of a
    model layout once per padded cell count, at its first fit; fits that share the layout (the
    completeness of every kind of a run) therefore cost less CPU in one worker than in several (on
    the demo about 1.4 CPU-s of a 3 CPU-s fit is that first trace).  Their cells are padded to one
    size where the padding stays within a power of two (:func:`group_padding`,
    :func:`comest_bayes.bayes.model.padding_floor`): kinds whose cell counts straddle a step (710 and
    831 cells: 768 and 1024) then load one set of programs, not two.  Empty cells add nothing to a
    likelihood, so the numbers are those of each fit alone (to rounding).
    """
    results = []
    with padding_floor(group_padding(tasks) if len(tasks) > 1 else 0):
        for task in tasks:
            try:
                results.append(fit_task(task))
            except Exception as exc:
                # the fits done before it are returned with the error (the caller records them, then raises it):
                # a failing fit must not take its group's finished fits with it
                exc.add_note("".join(traceback.format_exception(exc)).rstrip())
                results.append(FitFailure(exc))
                break
    return results


class FitFailure:
    """What :func:`fit_tasks` returns in place of a fit that raised: the exception, to raise in the caller."""

    def __init__(self, exc: BaseException):
        self.exc = exc


#: Default column names of an outcome table (this package's own ``catalogs/<kind>_outcomes.fits``).
OUTCOME_COLUMNS = {"mag": "mag", "detected": "detected", "x": "x", "y": "y", "noise": "noise"}


def _read_map(path, name: str) -> np.ndarray:
    try:
        with fits.open(path) as hdul:
            for hdu in hdul:
                if hdu.data is not None and getattr(hdu.data, "ndim", 0) == 2:
                    return np.asarray(hdu.data)
    except (OSError, ValueError, TypeError) as exc:
        raise InputError(f"{name} {str(path)!r} cannot be read as FITS: {exc}") from None
    raise InputError(f"{name} {str(path)!r} holds no 2-D image HDU.")


def noise_at_positions(noise: np.ndarray, x, y, *, what: str) -> np.ndarray:
    """The noise map at each position's nearest pixel (0-based), as a run's outcome table records it.

    Non-finite positions give NaN (their rows are dropped by the fit with a warning).  Positions more
    than half a pixel outside the map are an error: they are not pixels of this image (1-based
    positions from SExtractor's ``X_IMAGE`` need 1 subtracted).
    """
    x = np.asarray(x, float)
    y = np.asarray(y, float)
    ny, nx = noise.shape
    ok = np.isfinite(x) & np.isfinite(y)
    outside = ok & ((x < -0.5) | (y < -0.5) | (x >= nx - 0.5) | (y >= ny - 0.5))
    if outside.any():
        raise InputError(f"{what}: {int(outside.sum())} of {x.size} positions lie outside the noise map "
                         f"({ny} x {nx} pixels; x in [{np.min(x[ok]):.1f}, {np.max(x[ok]):.1f}], y in "
                         f"[{np.min(y[ok]):.1f}, {np.max(y[ok]):.1f}]). Positions must be 0-based pixels of that "
                         "map (subtract 1 from SExtractor's X_IMAGE / Y_IMAGE), or give a noise column.")
    out = np.full(x.size, np.nan)
    iy = np.floor(y[ok] + 0.5).astype(int)
    ix = np.floor(x[ok] + 0.5).astype(int)
    out[ok] = noise[np.clip(iy, 0, ny - 1), np.clip(ix, 0, nx - 1)]
    return out


def fit_outcome_file(path, out, *, kind: str = "injections", model: str = "auto", columns: dict | None = None,
                     noise_map=None, mask=None, image_shape=None, seed: int = 0, mag_bin: float = 0.1,
                     log=lambda s: None, label: str | None = None) -> dict:
    """Fit the completeness model to an outcome table made by any injection pipeline.

    Parameters
    ----------
    path : str or Path
        FITS (or any format astropy's Table reads) with one row per
        injection: true magnitude, detected (bool or 0/1) and optionally
        pixel position and the local detection noise.
    out : str or Path
        Output folder: new or empty.  Receives ``posterior/<kind>_completeness.npz``,
        ``summary.json`` (``kinds.<kind>.model`` and the binned completeness)
        and ``figures/<kind>_completeness.png``.
    kind : str
        Label of the injected population.
    model : str
        A spec name or path, or ``auto`` (the selection).
    columns : dict, optional
        Column names for ``mag``, ``detected``, ``x``, ``y``, ``noise``
        (defaults :data:`OUTCOME_COLUMNS`; None keeps the default).  ``x``,
        ``y`` and ``noise`` are optional under their default names; a name
        given here must be in the table.
    noise_map, mask : str or Path, optional
        FITS maps of the detection noise and bad pixels (non-zero = bad) of
        the image: the image average then runs over every unmasked pixel.
        Without them it runs over the injections' own positions and noise
        values (the footprint as the injections sampled it).  With a noise
        map and positions but no noise column, each injection's noise is
        read from the map at its nearest pixel (:func:`noise_at_positions`).
    image_shape : (ny, nx), optional
        Needed with positions but without a noise map or mask (default:
        from the maps, else the largest position + 1).
    seed : int
        Root seed of the fit.
    label : str, optional
        What error messages call the table (default ``outcome table '<path>'``; the Python API names a
        table given in memory so, rather than by the scratch file it writes).

    Returns
    -------
    dict
        The summary written to ``summary.json``.
    """


    path, out = Path(path), Path(out)
    what = label or f"outcome table {str(path)!r}"
    named = {key: value for key, value in (columns or {}).items() if value is not None}
    unknown = sorted(set(named) - set(OUTCOME_COLUMNS))
    if unknown:
        raise InputError(f"unknown column role(s) {unknown}; the roles are {sorted(OUTCOME_COLUMNS)}.")
    cols = dict(OUTCOME_COLUMNS, **named)
    # -- validate everything before writing anything
    if not path.is_file():
        raise InputError(f"{what} does not exist.")
    try:
        raw = Table.read(path)
    except Exception as exc:  # astropy raises many types for unreadable tables
        raise InputError(f"{what} cannot be read: {exc}") from None
    # mag and detected are needed; x, y and noise are optional, but a name given for one must exist
    required = [c for c in OUTCOME_COLUMNS if c in ("mag", "detected") or c in named]
    missing = [c for c in required if cols[c] not in raw.colnames]
    if missing:
        raise InputError(f"{what} has no column(s) {[cols[c] for c in missing]}; its columns are {raw.colnames}. "
                         "Name yours with " + " / ".join(f"--{c}-column" for c in missing)
                         + " (in Python: columns={" + ", ".join(f"{c!r}: ..." for c in missing) + "}).")
    if ("x" in named) != ("y" in named) and not (cols["x"] in raw.colnames and cols["y"] in raw.colnames):
        raise InputError(f"positions need both an x and a y column; {cols['x']!r} and {cols['y']!r} are not both "
                         "in the table: name both with --x-column and --y-column.")
    if len(raw) == 0:
        raise InputError(f"{what} has no rows.")
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise InputError(f"output folder {str(out)!r} exists and is not empty; give a new or empty folder "
                         "(nothing is overwritten).")
    load_spec(model)
    table = Table({"mag": np.asarray(raw[cols["mag"]], float),
                   "detected": outcome_flags(raw[cols["detected"]], cols["detected"])})
    has_xy = cols["x"] in raw.colnames and cols["y"] in raw.colnames
    if has_xy:
        table["x"] = np.asarray(raw[cols["x"]], float)
        table["y"] = np.asarray(raw[cols["y"]], float)
    if cols["noise"] in raw.colnames:
        table["noise"] = np.asarray(raw[cols["noise"]], float)
    noise = None if noise_map is None else _read_map(noise_map, "noise map").astype(np.float32)
    bad = None if mask is None else _read_map(mask, "mask") != 0
    if noise is not None and bad is not None and noise.shape != bad.shape:
        raise InputError(f"noise map {noise.shape} and mask {bad.shape} differ in shape.")
    shape = None
    for arr in (noise, bad):
        if arr is not None:
            shape = arr.shape
    if image_shape is not None:
        if shape is not None and tuple(image_shape) != tuple(shape):
            raise InputError(f"--image-shape {tuple(image_shape)} differs from the maps' shape {shape}.")
        shape = tuple(int(v) for v in image_shape)
    if shape is None and has_xy:
        shape = (int(np.nanmax(table["y"])) + 2, int(np.nanmax(table["x"])) + 2)
    noise_from_map = noise is not None and has_xy and "noise" not in table.colnames
    if noise_from_map:
        table["noise"] = noise_at_positions(noise, table["x"], table["y"], what=what)
    if shape is None:
        shape = (2, 2)  # no positions: the image plays no role
    config = RunConfig(seed=int(seed), fit=FitConfig(model=model))
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"output folder {str(out)!r} cannot be created: {exc}") from None

    # -- fit
    mags = np.asarray(table["mag"], float)
    good = np.isfinite(mags)
    lo = math.floor(np.min(mags[good]) / mag_bin) * mag_bin
    hi = math.ceil(np.max(mags[good]) / mag_bin) * mag_bin
    edges = R.magnitude_edges(lo, hi, mag_bin)
    centers = 0.5 * (edges[:-1] + edges[1:])
    if bad is None:
        bad = np.zeros(shape, bool)
    if noise is None and "noise" in table.colnames and has_xy:
        footprint = "injections"  # the injections' own positions sample the footprint
    else:
        footprint = "maps" if noise is not None or mask is not None else "uniform"
    where = {"maps": "every unmasked pixel of the maps", "injections": "the injections' positions and noise",
             "uniform": "a uniform footprint"}[footprint]
    log(f"fit: {len(table)} outcomes of {kind} from {path.name}; model {model}; image average over {where}")
    if noise_from_map:
        log(f"fit: no {cols['noise']!r} column: each injection's detection noise is read from the noise map at its "
            "position (nearest pixel, as a run's outcome table records it)")
    points = (table["x"], table["y"], table["noise"]) if footprint == "injections" else None
    post, entry = fit_kind(table, kind=kind, quantity="completeness", requested=model, config=config,
                           image_shape=shape, noise=noise if noise is not None else np.ones(shape, np.float32),
                           mask=bad, wcs_header=None, mag_range=(lo, hi), mag_centers=centers,
                           footprint_points=points, log=log)
    binned = R.completeness(mags, np.asarray(table["detected"]).astype(bool), edges)
    (out / layout.POSTERIOR_DIR).mkdir(exist_ok=True)
    post.save(out / layout.posterior(kind))
    record = {**entry.to_dict(), "posterior_file": layout.posterior(kind), "footprint": footprint}
    summary = {"source": str(path), "kinds": {kind: {"completeness": binned.to_dict(), "model": record}}}

    ax = ratio_curve(BinnedCurve(binned.centers, binned.ratio, binned.lower, binned.upper, binned.n),
                     posterior=PosteriorBand.from_dict(entry.curve, label=entry.name))
    ax.set_title(f"{kind}: {len(table)} injections from {path.name}")
    (out / layout.FIGURES_DIR).mkdir(exist_ok=True)
    save_figure(ax.figure, out / layout.FIGURES_DIR / f"{kind}_completeness")
    with atomic_path(out / layout.SUMMARY) as tmp:
        tmp.write_text(dumps(summary, indent=2, fallback=str) + "\n")
    return summary
