"""The front door: run the whole measurement from Python, fit an outcome table, read a finished run.

``comest_bayes.run(image, out=..., **options)`` does what ``comest-bayes run``
does, with the command's options as keywords (``--pixel-scale`` is
``pixel_scale=``, ``--set`` is ``overrides=``), and returns a :class:`Run`: a
frozen view of the run directory with the per-kind results as typed values
and accessors for the merged catalogs and the posteriors.
``comest_bayes.fit_completeness`` fits the completeness model to an outcome
table from any injection pipeline (``comest-bayes fit``).

The shortcut options shared by the command line and :func:`run` are turned
into a :class:`~comest_bayes.config.RunConfig` in one place,
:func:`config_from_options`; the command line calls it too.  Nothing heavy
is imported here at module level: JAX and GalSim load only when a run or a
fit needs them.
"""

from __future__ import annotations

import dataclasses
import difflib
import tempfile
import warnings
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import Callable, Mapping

from comest_bayes.errors import ComestError, ConfigError, InputError
from comest_bayes.io import layout
from comest_bayes.io.run import Interval, KindSummary, ModelSummary, Run

__all__ = ["run", "fit_completeness", "Run", "KindSummary", "ModelSummary", "Interval", "CompletenessFit",
           "config_from_options", "compute_from_options", "SHORTCUTS", "CATALOGS"]

#: Shortcut options of ``comest-bayes run``/``demo`` and :func:`run` -> the configuration key each sets.
SHORTCUTS = {"backend": "detection.backend", "thresh": "detection.thresh", "minarea": "detection.minarea",
             "kinds": "injection.kinds", "nsims": "injection.nsims", "density": "injection.density",
             "model": "fit.model", "precision": "adaptive.precision", "max_nsims": "adaptive.max_nsims"}
#: Options of :func:`config_from_options` besides the shortcuts.
CONFIG_OPTIONS = ("config", "overrides", "seed", "no_bnb", "precision_at")
#: Options of :func:`compute_from_options` (where realizations run; results do not depend on them).
COMPUTE_OPTIONS = ("ncpu", "executor", "scheduler")
#: The merged catalogs a run writes per kind, ``catalogs/<kind>_<name>.fits``.
CATALOGS = layout.CATALOGS


def _listed(value) -> str:
    """A CLI-style value: lists and tuples become comma-separated text."""
    if isinstance(value, (list, tuple)):
        return ",".join(str(v) for v in value)
    return str(value)


def config_from_options(*, config=None, overrides=None, seed: int | None = None, no_bnb: bool = False,
                        precision_at=None, **shortcuts):
    """The :class:`~comest_bayes.config.RunConfig` of ``comest-bayes run`` for these options.

    Parameters
    ----------
    config : str or Path, optional
        TOML configuration file (``--config``).
    overrides : str, list of str or mapping, optional
        ``--set``: ``["detection.thresh=2", ...]``, ``{"detection.thresh": 2}`` or
        ``{"detection": {"thresh": 2}}`` (:func:`comest_bayes.config.override_items`); the
        shortcuts below are applied after them.
    seed : int, optional
        Root seed of every random draw (default 0, or the file's).
    no_bnb : bool
        Do not make the bright-and-big image (``--no-bnb``).
    precision_at : str or sequence of float, optional
        Adaptive injection aimed at f at these magnitudes (``--precision-at``).
    **shortcuts
        Any of :data:`SHORTCUTS` (``thresh``, ``nsims``, ``kinds``, ``model``,
        ...); None means not given.

    Raises
    ------
    ConfigError
        An unknown shortcut, or a value the configuration refuses.
    """
    from comest_bayes.config import load_config, override_items

    unknown = sorted(set(shortcuts) - set(SHORTCUTS))
    if unknown:
        raise ConfigError(f"unknown configuration option(s) {unknown}; the shortcuts are {sorted(SHORTCUTS)} "
                          f"(anything else: overrides=['section.key=value']).")
    texts = []
    for option, key in SHORTCUTS.items():
        value = shortcuts.get(option)
        if value is not None:
            texts.append(f"{key}={_listed(value)}")
    if no_bnb:
        texts.append("sourcefree.bnb=false")
    if precision_at:
        texts += ["adaptive.target=f", f"adaptive.magnitudes={_listed(precision_at)}"]
    # the overrides in any of their forms, then the shortcuts (which win), as one table per section
    tables: dict = {}
    for section, key, value, _ in override_items(overrides) + override_items(texts):
        tables.setdefault(section, {})[key] = value
    out = load_config(config, tables, seed=seed)
    # options of the adaptive design given while it is off would be silently unused: refused
    stray = [f"--{flag}" for flag, given in (("precision-at", precision_at), ("max-nsims", shortcuts.get("max_nsims")))
             if given is not None and given != () and given != []]
    if stray and not out.adaptive.enabled:
        raise ConfigError(f"{' and '.join(stray)} given without --precision (adaptive.precision): the adaptive "
                          "design is off, so they would be ignored. Give --precision (a target 68% half-width of "
                          "m50 in mag, e.g. 0.02, or with --precision-at a target sd of f), or leave them out.")
    return out


def compute_from_options(*, ncpu: int | None = None, executor: str = "processes", scheduler: str | None = None,
                         progress: bool = False):
    """Where realizations run (:class:`~comest_bayes.pipeline.stages.ComputeOptions`); ``ncpu`` None: every core.

    A ``scheduler`` address implies the Dask executor, as ``--scheduler`` does.
    """
    from comest_bayes.pipeline.executors import default_workers
    from comest_bayes.pipeline.stages import ComputeOptions

    workers = ncpu if ncpu is not None else default_workers()
    if isinstance(workers, bool) or not isinstance(workers, int):
        raise ConfigError(f"ncpu={workers!r} must be an integer of at least 1.")
    if workers < 1:
        raise ConfigError(f"--ncpu {workers} must be at least 1.")
    if executor not in ("processes", "serial", "dask"):
        raise ConfigError(f"executor {executor!r} is not one of processes, serial, dask.")
    return ComputeOptions(executor="dask" if scheduler else executor, workers=workers, scheduler=scheduler,
                          progress=progress)


# --------------------------------------------------------------------------- typed results


# --------------------------------------------------------------------------- run


def _image_fields() -> tuple:
    from comest_bayes.pipeline.stages import ImageOptions

    return tuple(f.name for f in dataclasses.fields(ImageOptions) if f.name != "path")


def _refuse_worker_reimport() -> None:
    """Raise when a worker process is re-importing the user's script (whose top level calls :func:`run`).

    Worker processes start by importing the main script again (the ``spawn``
    and ``forkserver`` start methods; JAX forbids ``fork``).  A script that
    calls :func:`run` at its top level would then start the run again in
    every worker, where it meets the parent's lock.  Without this check the
    parent only sees a ``BrokenProcessPool``.
    """
    import sys

    caller = sys._getframe(2)  # the frame that called run()
    if caller.f_code.co_name == "<module>" and caller.f_globals.get("__name__") == "__mp_main__":
        raise ComestError("comest_bayes.run was called while a worker process re-imported your script: put the "
                          "call under `if __name__ == \"__main__\":` (worker processes import the main script "
                          "again), or pass ncpu=1 to run without worker processes.")


def image_options_from(image, **facts) -> "ImageOptions":
    """The image facts of a run (``hdu``, ``zp``, ..., ``mask_bits``) as ``ImageOptions``: one path for
    the command line and :func:`run`.  Options of a weight map or a mask given without the map are
    refused (they would be ignored), and ``weight_type`` None is ``ivar``."""
    from comest_bayes.io.image import WEIGHT_TYPES
    from comest_bayes.pipeline.stages import ImageOptions

    if facts.get("weight_type") is not None and facts["weight_type"] not in WEIGHT_TYPES:
        raise InputError(f"weight_type={facts['weight_type']!r} is not one of {WEIGHT_TYPES}; "
                         "use ivar (inverse variance), rms (sigma) or var (variance).")
    for companion, options in (("weight", ("weight_type", "weight_hdu")), ("mask", ("mask_hdu", "mask_bits"))):
        stray = [o for o in options if facts.get(o) is not None]
        if stray and facts.get(companion) is None:
            said = ", ".join(f"{o} (--{o.replace('_', '-')})" for o in stray)
            raise ConfigError(f"{said} given without a {companion} map: pass the map with {companion}= "
                              f"(--{companion} FILE), or leave {'them' if len(stray) > 1 else 'it'} out.")
    for name in ("weight", "mask"):
        if facts.get(name) is not None:
            facts[name] = str(facts[name])
    if facts.get("weight_type") is None:
        facts.pop("weight_type", None)
    return ImageOptions(path=str(image), **facts)


def run(image, *, out, log: Callable[[str], None] | None = None, **options) -> Run:
    """Run every stage on an image, as ``comest-bayes run IMAGE --out OUT`` does, and return the run.

    Parameters
    ----------
    image : str or Path
        FITS image.
    out : str or Path
        Run directory: new, empty, or a run of the same inputs to resume.
    log : callable, optional
        Receives one line per stage (default: ``print``; ``quiet=True`` silences it).
    **options
        The options of ``comest-bayes run`` by their Python names:

        * image facts: ``hdu``, ``zp``, ``pixel_scale``, ``fwhm``, ``gain``,
          ``saturation``, ``weight``, ``weight_type``, ``weight_hdu``,
          ``mask``, ``mask_hdu``, ``mask_bits``;
        * configuration: ``config`` (TOML path), ``overrides``
          (``--set``: a list of ``"section.key=value"`` or a mapping), ``seed``,
          ``no_bnb``, ``precision_at`` and the shortcuts of :data:`SHORTCUTS`
          (``backend``, ``thresh``, ``minarea``, ``kinds``, ``nsims``,
          ``density``, ``model``, ``precision``, ``max_nsims``);
        * compute (results do not depend on them): ``ncpu`` (default every
          core), ``executor``, ``scheduler``;
        * ``no_report`` (do not write ``report.html``), ``quiet``.

    Returns
    -------
    Run

    Raises
    ------
    ConfigError
        An unknown option or a value the configuration refuses, before
        anything is written.
    ComestError
        Every input error ``comest-bayes run`` reports (see the README), also
        before anything is written.
    """
    from comest_bayes.pipeline.stages import run_pipeline

    _refuse_worker_reimport()
    facts = _image_fields()
    known = set(facts) | set(CONFIG_OPTIONS) | set(SHORTCUTS) | set(COMPUTE_OPTIONS) | {"no_report", "quiet"}
    unknown = sorted(set(options) - known)
    if unknown:
        hints = {u: difflib.get_close_matches(u, sorted(known), n=1) for u in unknown}
        said = ", ".join(f"{u!r}" + (f" (did you mean {h[0]!r}?)" if h else "") for u, h in hints.items())
        raise ConfigError(f"unknown option(s) of comest_bayes.run: {said}; valid options: {', '.join(sorted(known))}.")
    if options.get("quiet"):
        log = lambda line: None  # noqa: E731
    elif log is None:
        log = print
    config = config_from_options(**{k: options[k] for k in (*CONFIG_OPTIONS, *SHORTCUTS) if k in options})
    compute = compute_from_options(**{k: options[k] for k in COMPUTE_OPTIONS if k in options})
    image_options = image_options_from(image, **{k: options[k] for k in facts if k in options})
    result = run_pipeline(image_options, config, out, log=log, compute=compute)
    if not options.get("no_report"):
        from comest_bayes.report.html import write_report

        try:  # as the command line does: a finished run stays finished when its report fails
            write_report(result.out_dir, log=log)  # logs where it wrote
        except Exception as exc:
            warnings.warn(f"the report could not be written ({type(exc).__name__}: {exc}); the run's outputs are "
                          f"complete. Retry with comest_bayes.write_report({str(result.out_dir)!r}).", stacklevel=2)
    return Run.open(result.out_dir)


# --------------------------------------------------------------------------- fit an outcome table


@dataclass(frozen=True)
class CompletenessFit:
    """What :func:`fit_completeness` returns.

    Attributes
    ----------
    kind : str
    posterior : comest_bayes.bayes.posterior.CompletenessPosterior
        The fitted (or selected and fitted) model's posterior.
    model : ModelSummary
        The chosen model, m50/m80/m90 with intervals, sampler and warnings.
    entry : mapping
        The whole ``summary.json`` entry (curve, parameters, selection table,
        shape check; :mod:`comest_bayes.bayes.fit` documents it).
    out : Path or None
        The output folder, or None when none was asked for.
    """

    kind: str
    posterior: object
    model: ModelSummary
    entry: Mapping
    out: Path | None


def fit_completeness(outcomes, out=None, *, kind: str = "injections", model: str = "auto",
                     columns: Mapping | None = None, noise_map=None, mask=None, image_shape=None, seed: int = 0,
                     log: Callable[[str], None] | None = None) -> CompletenessFit:
    """Fit the completeness model to injection outcomes from any pipeline (``comest-bayes fit``).

    Parameters
    ----------
    outcomes : str, Path or astropy.table.Table
        One row per injection: true magnitude, detected (bool or 0/1) and
        optionally pixel position and local detection noise (column names:
        ``columns``, default ``mag``, ``detected``, ``x``, ``y``, ``noise``;
        a run's ``catalogs/<kind>_outcomes.fits`` matches them).
    out : str or Path, optional
        Folder (new or empty) for ``summary.json``, the posterior and a
        figure; by default nothing is kept on disk.
    kind, model, columns, image_shape, seed
        As :func:`comest_bayes.pipeline.fits.fit_outcome_file`.
    noise_map, mask : str, Path or 2-D array, optional
        Detection noise and bad pixels (non-zero = bad) of the image: the
        image average then covers every unmasked pixel.
    log : callable, optional
        Receives progress lines (default: silent).

    Returns
    -------
    CompletenessFit
    """
    import numpy as np

    from comest_bayes.pipeline.fits import fit_outcome_file
    from comest_bayes.io.run import model_facts
    from comest_bayes.bayes.posterior import CompletenessPosterior

    log = log or (lambda line: None)
    with tempfile.TemporaryDirectory(prefix="comest-fit-") as scratch:
        scratch = Path(scratch)

        def on_disk(value, name: str):
            """A path as given; a table or array written to the scratch folder."""
            if value is None or isinstance(value, (str, Path)):
                return value
            if name == "outcomes":
                from astropy.table import Table

                path = scratch / "outcomes.fits"
                try:
                    table = Table(value)
                    for name in table.colnames:  # FITS keeps no mask of a logical column: keep it as integers
                        col = table[name]
                        if col.dtype.kind == "b" and np.ma.is_masked(col):
                            table[name] = np.ma.MaskedArray(np.ma.getdata(col).astype(np.int16),
                                                            mask=np.ma.getmaskarray(col))
                    table.write(path)
                except Exception as exc:
                    raise InputError(f"outcomes must be a table file or a table (astropy Table, dict of columns); "
                                     f"got {type(value).__name__}: {exc}") from None
                return path
            from astropy.io import fits

            arr = np.asarray(value)
            if arr.ndim != 2:
                raise InputError(f"{name} must be a FITS path or a 2-D array; got an array of shape {arr.shape}.")
            path = scratch / f"{name}.fits"
            fits.PrimaryHDU(arr.astype(np.uint8) if arr.dtype == bool else arr).writeto(path)
            return path

        table = on_disk(outcomes, "outcomes")
        noise = on_disk(noise_map, "noise_map")
        bad = on_disk(mask, "mask")
        folder = Path(out) if out is not None else scratch / "fit"
        summary = fit_outcome_file(table, folder, kind=kind, model=model, columns=dict(columns or {}),
                                   noise_map=noise, mask=bad, image_shape=image_shape, seed=seed, log=log,
                                   label=None if table is outcomes else "the outcome table given")
        entry = summary["kinds"][kind]["model"]
        post = CompletenessPosterior.load(folder / entry["posterior_file"])
    return CompletenessFit(kind=kind, posterior=post, model=ModelSummary.from_info(model_facts(entry)),
                           entry=MappingProxyType(entry), out=None if out is None else Path(out))
