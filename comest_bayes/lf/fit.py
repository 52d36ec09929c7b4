"""Fit number counts to a run's catalog (``comest-bayes lf``): read the run, fit, write the result.

:func:`run_lf` reads the run directory (catalog, completeness posterior, transfer, mask), calls
:func:`comest_bayes.lf.model.fit_counts`, and writes ``DIR/lf/<name>/`` and the ``lf.<name>``
entry of ``summary.json``.  The forward model is described in ``docs/lf.md``.
"""

from __future__ import annotations

import json
import math
import re
import warnings
from pathlib import Path
from typing import Callable
import numpy as np
from comest_bayes.lf.counts import CountModel, load_count_spec
from comest_bayes.errors import ConfigError, InputError, InputFileError
from comest_bayes.lf import MODES, SAMPLERS
from comest_bayes.lf.model import LFWarning, build_inputs, effective_area, fit_counts
from comest_bayes.lf.result import LFResult
from comest_bayes.io.jsonio import dumps
from comest_bayes.io import layout
from comest_bayes.io.run import Run
from comest_bayes.io.rundir import atomic_path
from comest_bayes.bayes.outcomes import column_floats
from comest_bayes.bayes.posterior import CompletenessPosterior
from comest_bayes.recover.transfer import transfer_from_outcomes
from comest_bayes.report.plots import save_figure
from comest_bayes.report.plots.lf import corner_figure, counts_figure

__all__ = ['run_lf']


# --------------------------------------------------------------------------- run directory


def _read_catalog(path: Path, mag_column: str):
    from astropy.table import Table

    try:
        try:
            table = Table.read(path, mask_invalid=False)  # FITS: NaN stays NaN, not a masked entry
        except TypeError:  # the other readers (CSV, ECSV, VOTable, ...) take no mask_invalid
            table = Table.read(path)
    except Exception as exc:  # astropy raises many kinds for unreadable files
        first = " ".join(str(exc).split())[:300]
        raise InputFileError(f"catalog {str(path)!r} cannot be read as a table (FITS, or a format astropy knows by "
                             f"the file's extension: .csv, .ecsv, .vot, ...): {first}") from None
    if mag_column not in table.colnames:
        raise InputError(f"catalog {str(path)!r} has no column {mag_column!r}; columns present: {table.colnames}. "
                         f"Pass the magnitude column with --mag-column.")
    if len(table) == 0:
        raise InputError(f"catalog {str(path)!r} is empty: there are no sources to count.")
    return table


def _positions(table, wcs_post):
    """0-based pixel positions from ``xwin, ywin`` or ``x, y`` (any case), else ``ra, dec`` through the WCS."""
    by_lower = {name.lower(): name for name in table.colnames}
    for cx, cy in (("xwin", "ywin"), ("x", "y")):
        if cx in by_lower and cy in by_lower:
            return tuple(column_floats(table[by_lower[c]], by_lower[c], "catalog") for c in (cx, cy))
    if "ra" in by_lower and "dec" in by_lower and wcs_post is not None:
        ra, dec = (column_floats(table[by_lower[c]], by_lower[c], "catalog") for c in ("ra", "dec"))
        x, y = wcs_post.all_world2pix(ra, dec, 0)
        return np.asarray(x, float), np.asarray(y, float)
    return None, None


def _default_range(run_state: dict, post) -> tuple[float, float]:
    inj = run_state.get("stages", {}).get("baseline", {}).get("mag_range")
    if not inj:
        inj = post.meta.get("mag_range", (18.0, 26.0))
    lo, hi = float(inj[0]) + 1.0, float(inj[1]) - 1.0
    grid = np.arange(lo, hi, 0.02)
    f = np.median(post.average_curve(grid, nsamples=200), axis=0)
    below = np.flatnonzero(f < 0.1)
    if below.size:
        hi = min(hi, float(grid[below[0]]))
    if hi <= lo:
        raise InputError(f"cannot choose a default magnitude range from the injected range {inj}: give --mag-range.")
    return round(lo, 2), round(hi, 2)


def _kinds_with_posteriors(run: Path) -> list[str]:
    """The kinds whose completeness posterior the run saved."""
    suffix = "_completeness.npz"
    return [p.name[: -len(suffix)] for p in (run / layout.POSTERIOR_DIR).glob("*" + suffix)]


def _update_summary(run_dir: Path, name: str, entry: dict) -> None:

    path = run_dir / layout.SUMMARY
    data = json.loads(path.read_text()) if path.is_file() else {}
    data.setdefault("lf", {})[name] = entry
    with atomic_path(path) as tmp:
        tmp.write_text(dumps(data, indent=2))


def run_lf(run_dir, *, kind: str = "point", catalog=None, mag_column: str = "mag_auto", model="powerlaw",
           mag_range=None, mode: str = "joint", seed: int | None = None, name: str | None = None,
           log: Callable[[str], None] | None = None, ncomp: int = 16, min_ess: float = 400,
           max_steps: int = 20000, figures: bool = True, sampler: str = "auto") -> LFResult:
    """Fit number counts to a run's catalog, forward-modelling completeness and transfer.

    Parameters
    ----------
    run_dir : str or Path
        A finished run directory with ``posterior/<kind>_completeness.npz``,
        ``catalogs/<kind>_outcomes.fits``, ``mask.fits`` and ``run.json``.
    kind : str, default "point"
        Injection kind whose completeness and transfer describe the sources.
    catalog : str or Path, optional
        FITS table of sources (default ``DIR/detection.fits``); positions from
        ``xwin/ywin``, ``x/y`` or ``ra/dec``.  Objects whose centre pixel is masked
        are dropped (the area excludes masked pixels).
    mag_column : str, default "mag_auto"
    model : str or path, default "powerlaw"
        Count model (:func:`comest_bayes.lf.counts.load_count_spec`).
    mag_range : (lo, hi), optional
        Measured magnitudes fitted; default: the injected range less 1 mag at
        each end, cut where the median completeness falls below 10%.
    mode : {"joint", "marginal", "fixed"}, default "joint"
    seed : int, optional
        Root seed of the sampler (default: the run's root seed).
    name : str, optional
        Output folder ``DIR/lf/<name>`` (default ``<kind>_<model>_<mode>``).
    log : callable, optional
        Receives progress lines.
    ncomp, min_ess, max_steps, sampler
        See :func:`fit_counts`.
    figures : bool, default True
        Write ``counts.png`` and ``corner.png``.

    Returns
    -------
    LFResult

    Raises
    ------
    InputError, InputFileError, ConfigError
        Before any work: missing run products or completeness posterior, unknown
        model or mode, unreadable or empty catalog, missing column, bad or empty range.
    """
    from astropy.io import fits


    log = log or (lambda s: None)
    run = Path(run_dir)
    # ---- validation: nothing is computed before all of this passes ----------------------
    if mode not in MODES:
        raise ConfigError(f"mode (--mode) must be one of {list(MODES)}, got {mode!r}.")
    if sampler not in SAMPLERS:
        raise ConfigError(f"sampler (--sampler) must be one of {list(SAMPLERS)}, got {sampler!r}.")
    if isinstance(ncomp, bool) or not isinstance(ncomp, (int, np.integer)) or ncomp < 1:
        raise ConfigError(f"ncomp, the completeness draws of the marginal mode, must be a positive "
                          f"integer (12 or more keeps their noise small: docs/lf.md), got {ncomp!r}.")
    if name is not None and (not isinstance(name, str) or not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._-]*", name)):
        raise ConfigError(f"name (--name) is the folder lf/<name> of the run: letters, digits, '.', '_' and '-', "
                          f"starting with a letter or digit (no path), got {name!r}.")
    record = Run.open(run)  # a clear error when it is not a run directory
    post_path = run / layout.posterior(kind)
    if not post_path.is_file():
        have = sorted(k for k in _kinds_with_posteriors(run))
        raise InputFileError(f"the run has no completeness posterior for kind {kind!r} ({post_path} is missing); "
                             f"kinds with one: {have or 'none (run with fit.model set, not none)'}.")
    outcomes_path = run / layout.catalog(kind, "outcomes")
    for p in (outcomes_path, run / layout.MASK):
        if not p.is_file():
            raise InputFileError(f"the run directory lacks {p.relative_to(run)}; rerun `comest-bayes run` to finish it.")
    spec = load_count_spec(model)
    if mag_range is not None:
        if len(mag_range) != 2 or not all(math.isfinite(float(v)) for v in mag_range) or \
                not float(mag_range[1]) > float(mag_range[0]):
            raise InputError(f"mag_range (--mag-range) must be two finite magnitudes LO < HI, got {list(mag_range)}.")
    cat_path = Path(catalog) if catalog is not None else run / layout.DETECTION
    if not cat_path.is_file():
        raise InputFileError(f"catalog {str(cat_path)!r} does not exist.")
    table = _read_catalog(cat_path, mag_column)
    state = record.state
    scale = record.image_facts.get("pixel_scale_arcsec")
    if not scale:
        raise InputError(f"{layout.RUN} records no pixel scale (image.pixel_scale_arcsec); the area cannot be computed.")

    # ---- inputs ------------------------------------------------------------------------
    from astropy.table import Table

    post = CompletenessPosterior.load(post_path)
    mask = fits.getdata(run / layout.MASK).astype(bool)
    area = effective_area(mask, float(scale))
    mags = column_floats(table[mag_column], mag_column, f"catalog {str(cat_path)!r}")
    if mags.ndim == 2:
        mags = mags[:, 0]
    x, y = _positions(table, post.wcs)
    input_warnings = []

    def say(text):
        warnings.warn(text, LFWarning, stacklevel=3)
        input_warnings.append(text)

    if x is not None:
        unplaced = ~(np.isfinite(x) & np.isfinite(y))
        if unplaced.any():
            raise InputError(f"catalog {str(cat_path)!r}: {int(unplaced.sum())} of {len(x)} objects have no finite "
                             "position, so the mask cannot be applied to them: fix or drop those rows.")
        ny, nx = mask.shape
        off = (x < -0.5) | (y < -0.5) | (x >= nx - 0.5) | (y >= ny - 0.5)
        if off.all():
            raise InputError(f"catalog {str(cat_path)!r}: all {len(x)} objects lie outside the run's {nx} x {ny}-pixel "
                             "image; is it the catalog of this image (0-based pixel positions, or ra/dec)?")
        if off.any():
            say(f"{int(off.sum())} of {len(x)} catalog objects lie outside the run's image: they are not counted "
                "(the area is the image's unmasked pixels).")
        ix = np.floor(x + 0.5).astype(int)
        iy = np.floor(y + 0.5).astype(int)
        inside = ~off
        inside[inside] = ~mask[iy[inside], ix[inside]]
        mags, x, y = mags[inside], x[inside], y[inside]
    nonfinite = ~np.isfinite(mags)
    if nonfinite.any():
        say(f"{int(nonfinite.sum())} of {len(mags)} catalog objects have a non-finite {mag_column} (NaN, infinite or "
            "masked): they are not counted.")
    rng_ = tuple(float(v) for v in mag_range) if mag_range is not None else _default_range(state, post)
    transfer = transfer_from_outcomes(Table.read(outcomes_path, mask_invalid=False))
    inputs = build_inputs(mags, area_deg2=area, mag_range=rng_, transfer=transfer, x=x, y=y)
    name = name or f"{kind}_{spec.name}_{mode}"
    log(f"lf: {inputs.n} objects with {rng_[0]} <= {mag_column} < {rng_[1]} on {area * 3600:.2f} arcmin^2; "
        f"model {spec.name}, mode {mode}")
    if seed is None:  # the run's own root seed, so a run and its LF fit come from one seed
        seed = int(((record.state.get("fingerprint") or {}).get("config") or {}).get("seed", 0))
    res = fit_counts(inputs, CountModel(spec), mode=mode, post=post, seed=seed, ncomp=ncomp, min_ess=min_ess,
                     max_steps=max_steps, name=name, kind=kind, log=log, sampler=sampler)
    res.warnings[:0] = input_warnings
    res.meta.update({"catalog": str(cat_path), "mag_column": mag_column, "run_dir": str(run),
                     "area_source": f"unmasked pixels of {layout.MASK} x (pixel scale from {layout.RUN}, WCS at the centre)^2"})
    out = run / layout.lf_dir(name)
    res.save(out)
    files = [layout.LF_POSTERIOR, layout.LF_JSON]
    if figures:

        save_figure(counts_figure(res), out / "counts", formats=("png",))
        save_figure(corner_figure(res), out / "corner", formats=("png",))
        files += ["counts.png", "corner.png"]
    entry = {k: v for k, v in res.to_json().items() if k not in ("observed", "diagnostics")}
    entry["files"] = [f"{layout.lf_dir(name)}/{f}" for f in files]
    entry["converged"] = bool(res.diagnostics.get("converged", False))
    _update_summary(run, name, entry)
    # the warnings were raised as LFWarning while fitting (the command line prints each once); they are in lf.json
    pars = res.parameter_summary()
    log("lf: " + ", ".join(f"{k} = {v['median']:.3f} (+{v['hi68'] - v['median']:.3f}/-{v['median'] - v['lo68']:.3f})"
                           for k, v in pars.items()))
    return res
