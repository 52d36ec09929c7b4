"""The fits around the numerics: the fit stage's worker task, and ``comest-bayes fit`` on an outcome table.

:func:`fit_task` reads one kind's catalogs and maps from a run directory and calls
:func:`comest_bayes.bayes.fit.fit_kind` (a picklable task for the executors);
:func:`fit_outcome_file` reads an outcome table made by any injection pipeline (and optionally its
noise map and mask), fits it, and writes ``summary.json``, the posterior and a figure.
"""

from __future__ import annotations

import math
import os
import re
import shutil
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
from comest_bayes.bayes.outcomes import column_floats, compress_for, covariates_from_outcomes, outcome_flags
from comest_bayes.bayes.spec import load_spec
from comest_bayes.config import RunConfig
from comest_bayes.errors import InputError, OutputWriteError
from comest_bayes.io import layout
from comest_bayes.io.jsonio import dumps
from comest_bayes.ratios import binned as R
from comest_bayes.config import FitConfig
from comest_bayes.io.rundir import TMP_PREFIX, os_reason
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


def _pixels(shape, x, y, *, what: str, name: str, advice: str):
    """Nearest pixel (0-based) of each finite position: ``(ok, iy, ix)``; positions off the map are an error."""
    x = np.asarray(x, float)
    y = np.asarray(y, float)
    ny, nx = shape
    ok = np.isfinite(x) & np.isfinite(y)
    outside = ok & ((x < -0.5) | (y < -0.5) | (x >= nx - 0.5) | (y >= ny - 0.5))
    if outside.any():
        raise InputError(f"{what}: {int(outside.sum())} of {x.size} positions lie outside the {name} "
                         f"({ny} x {nx} pixels; x in [{np.min(x[ok]):.1f}, {np.max(x[ok]):.1f}], y in "
                         f"[{np.min(y[ok]):.1f}, {np.max(y[ok]):.1f}]). Positions must be 0-based pixels of that "
                         f"map (subtract 1 from SExtractor's X_IMAGE / Y_IMAGE){advice}.")
    iy = np.clip(np.floor(y[ok] + 0.5).astype(int), 0, ny - 1)
    ix = np.clip(np.floor(x[ok] + 0.5).astype(int), 0, nx - 1)
    return ok, iy, ix


def noise_at_positions(noise: np.ndarray, x, y, *, what: str) -> np.ndarray:
    """The noise map at each position's nearest pixel (0-based), as a run's outcome table records it.

    Non-finite positions give NaN (their rows are dropped by the fit with a warning).  Positions more
    than half a pixel outside the map are an error: they are not pixels of this image (1-based
    positions from SExtractor's ``X_IMAGE`` need 1 subtracted).
    """
    ok, iy, ix = _pixels(noise.shape, x, y, what=what, name="noise map", advice=", or give a noise column")
    out = np.full(ok.size, np.nan)
    out[ok] = noise[iy, ix]
    return out


#: What ``--kind`` may be: it names the posterior and figure files of ``comest-bayes fit``.
KIND_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]*")


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
    if not isinstance(kind, str) or not KIND_NAME.fullmatch(kind):
        raise InputError(f"kind (--kind) names the files posterior/<kind>_completeness.npz and figures/<kind>_*: "
                         f"letters, digits, '.', '_' and '-', starting with a letter or digit (no path), got {kind!r}.")
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
    table = Table({"mag": column_floats(raw[cols["mag"]], cols["mag"], what),
                   "detected": outcome_flags(raw[cols["detected"]], cols["detected"])})
    has_xy = cols["x"] in raw.colnames and cols["y"] in raw.colnames
    if has_xy:
        table["x"] = column_floats(raw[cols["x"]], cols["x"], what)
        table["y"] = column_floats(raw[cols["y"]], cols["y"], what)
    if cols["noise"] in raw.colnames:
        table["noise"] = column_floats(raw[cols["noise"]], cols["noise"], what)
    mags = np.asarray(table["mag"], float)
    good = np.isfinite(mags)
    if not good.any():
        raise InputError(f"{what}: none of its {len(table)} magnitudes (column {cols['mag']!r}) is a finite number "
                         "(NaN, infinite or masked): nothing to fit.")
    if np.ptp(mags[good]) == 0.0:
        raise InputError(f"{what}: all {int(good.sum())} finite magnitudes equal {mags[good][0]:g}: a completeness "
                         "curve needs injections spread over a range of magnitudes (a few tenths of a magnitude "
                         "at the least).")
    noise = None if noise_map is None else _read_map(noise_map, "noise map").astype(np.float32)
    bad = None if mask is None else _read_map(mask, "mask") != 0
    if noise is not None and bad is not None and noise.shape != bad.shape:
        raise InputError(f"noise map {noise.shape} and mask {bad.shape} differ in shape.")
    if noise is not None:
        unusable = ~(np.isfinite(noise) & (noise > 0))
        if unusable.any():
            n_new = int(np.count_nonzero(unusable & ~bad)) if bad is not None else int(np.count_nonzero(unusable))
            bad = unusable if bad is None else bad | unusable
            if n_new:
                warnings.warn(f"{n_new} pixels of the noise map are NaN, infinite or <= 0: they are left out of the "
                              "image average as if masked (a run masks them too).", UserWarning, stacklevel=2)
    shape = None
    for arr in (noise, bad):
        if arr is not None:
            shape = arr.shape
    if image_shape is not None:
        if shape is not None and tuple(image_shape) != tuple(shape):
            raise InputError(f"--image-shape {tuple(image_shape)} differs from the maps' shape {shape}.")
        shape = tuple(int(v) for v in image_shape)
    if shape is None and has_xy:
        if not np.any(np.isfinite(table["x"]) & np.isfinite(table["y"])):
            raise InputError(f"{what}: no row has a finite position ({cols['x']!r}, {cols['y']!r}); drop those "
                             "columns (name others with --x-column / --y-column) or fill them.")
        shape = (int(np.nanmax(table["y"])) + 2, int(np.nanmax(table["x"])) + 2)
    on_mask = None
    if bad is not None and has_xy:
        ok, iy, ix = _pixels(bad.shape, table["x"], table["y"], what=what, name="mask",
                             advice=", or give the mask of the image the positions belong to")
        on_mask = np.zeros(len(table), bool)
        on_mask[ok] = bad[iy, ix]
    noise_from_map = noise is not None and has_xy and "noise" not in table.colnames
    if noise_from_map:
        table["noise"] = noise_at_positions(noise, table["x"], table["y"], what=what)
    if on_mask is not None and on_mask.any():
        if on_mask.all():
            raise InputError(f"{what}: all {len(table)} injections lie on masked pixels of the mask (or on NaN or "
                             "<= 0 pixels of the noise map): check that the mask's non-zero pixels are the bad ones "
                             "and that the positions are 0-based pixels of that image.")
        warnings.warn(f"{int(on_mask.sum())} of {len(table)} injections lie on masked pixels (or on NaN or <= 0 pixels "
                      "of the noise map): left out of the fit, as a run never counts them.", UserWarning, stacklevel=2)
        table = table[~on_mask]
        mags = np.asarray(table["mag"], float)
        good = np.isfinite(mags)
        if not good.any() or np.ptp(mags[good]) == 0.0:
            raise InputError(f"{what}: after leaving out the injections on masked pixels, {int(good.sum())} with a "
                             "finite magnitude remain, too few magnitudes to fit a curve.")
    if has_xy:
        keys = np.stack([np.asarray(table[c], float) for c in ("mag", "x", "y")], axis=1)
        finite = np.all(np.isfinite(keys), axis=1)
        repeats = int(finite.sum() - len(np.unique(keys[finite], axis=0)))
        if repeats:
            warnings.warn(f"{repeats} of {len(table)} rows repeat another row's magnitude and position exactly: an "
                          "injection listed twice (a table stacked with itself?) counts twice and narrows the "
                          "intervals. Drop the repeats if they are not distinct injections.", UserWarning, stacklevel=2)
    positions = shape is not None
    if shape is None:
        shape = (2, 2)  # no positions: the image plays no role (the posterior refuses positional queries)
    config = RunConfig(seed=int(seed), fit=FitConfig(model=model))

    # -- fit
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
    if not positions:
        post.meta["positions"] = False
    record = {**entry.to_dict(), "posterior_file": layout.posterior(kind), "footprint": footprint}
    source = str(path) if label is None else label
    m50_binned = R.magnitude_at(binned, 0.5)
    m50_binned_sd = R.magnitude_at_sd(binned, 0.5, seed=int(seed))
    summary = {"source": source, "kinds": {kind: {
        "completeness": binned.to_dict(), "model": record,
        "m50_binned": None if not math.isfinite(m50_binned) else float(m50_binned),
        "m50_binned_sd": None if not math.isfinite(m50_binned_sd) else float(m50_binned_sd)}}}
    ax = ratio_curve(BinnedCurve(binned.centers, binned.ratio, binned.lower, binned.upper, binned.n),
                     posterior=PosteriorBand.from_dict(entry.curve, label=entry.name))
    ax.set_title(f"{kind}: {len(table)} injections from {path.name if label is None else label}")

    # -- write: everything goes to a hidden sibling folder that becomes ``out`` in one rename, so a crash
    # leaves no half-written folder that looks complete, and of two fits into one new folder only the
    # first to finish lands (the other is refused: a rename onto a non-empty folder fails)
    staging = out.parent / f"{TMP_PREFIX}{os.getpid()}-fit-{out.name}"  # no live process shares our pid
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        shutil.rmtree(staging, ignore_errors=True)  # what a killed process of the same pid left
        staging.mkdir()
    except OSError as exc:
        raise InputError(f"output folder {str(out)!r} cannot be created: {os_reason(exc)}.") from None
    try:
        (staging / layout.POSTERIOR_DIR).mkdir()
        post.save(staging / layout.posterior(kind))
        (staging / layout.FIGURES_DIR).mkdir()
        save_figure(ax.figure, staging / layout.FIGURES_DIR / f"{kind}_completeness")
        (staging / layout.SUMMARY).write_text(dumps(summary, indent=2, fallback=str) + "\n")
        try:
            os.rename(staging, out)  # replaces an empty folder; fails on a non-empty one
        except OSError as exc:
            if out.is_dir() and any(out.iterdir()):
                raise InputError(f"output folder {str(out)!r} was filled by another process while this fit ran; "
                                 "nothing was overwritten. Give a new or empty folder.") from None
            raise OutputWriteError(f"could not write {str(out)!r}: {os_reason(exc)}. Free some space or choose "
                                   "another --out.") from None
    except OutputWriteError:
        raise
    except OSError as exc:
        raise OutputWriteError(f"could not write {str(out)!r}: {os_reason(exc)}. Free some space or choose "
                               "another --out.") from None
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return summary

