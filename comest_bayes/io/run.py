"""Reading a run directory: the one typed view of what a run holds.

:class:`Run` reads ``run.json`` and ``summary.json`` and gives typed values (per-kind
:class:`KindSummary`, :class:`ModelSummary`, :class:`Interval`) and accessors for the merged
catalogs, the posteriors and the image facts; :func:`run_info` is the record ``comest-bayes info``
prints.  File names come from :mod:`comest_bayes.io.layout`; writing is
:class:`comest_bayes.io.rundir.RunDirectory`.
"""

from __future__ import annotations

import dataclasses
import difflib
import json
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from types import MappingProxyType
from typing import Mapping

from comest_bayes.errors import InputError, InputFileError, RunDirectoryError
from comest_bayes.io import layout

__all__ = ["Run", "KindSummary", "ModelSummary", "Interval", "run_info", "model_facts", "read_record"]

#: Stages in the order of the data flow (fits follow, one per kind and quantity).
STAGE_ORDER = ("detect", "fwhm", "sourcefree", "baseline")


def read_record(path: Path, what: str) -> dict:
    """A JSON record of the run (``run.json``, ``summary.json``) as a dict, or a clear error."""
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise RunDirectoryError(f"{what} {str(path)!r} cannot be read ({exc}); is this a complete comest-bayes "
                                f"run directory?") from None
    if not isinstance(data, dict):
        raise RunDirectoryError(f"{what} {str(path)!r} is not a comest-bayes record.")
    return data


def _interval(q: dict | None) -> dict | None:
    if not q or q.get("median") is None:
        return None
    keys = ("median", "lo68", "hi68", "lo95", "hi95")
    out = {k: q.get(k) for k in keys}
    out["extrapolated"] = bool(q.get("extrapolated"))
    return out


def model_facts(entry: dict | None) -> dict | None:
    """The facts of one model entry of ``summary.json`` (chosen model, candidates, m50/m80/m90, sampler, warnings)."""
    if not entry:
        return None
    if entry.get("skipped"):
        return {"name": entry.get("name"), "requested": entry.get("requested"), "skipped": entry["skipped"]}
    selection = entry.get("selection") or {}
    candidates = [row.get("name") for row in selection.get("table", []) if isinstance(row, dict)]
    diag = entry.get("diagnostics") or {}
    return {
        "name": entry.get("name"),
        "requested": entry.get("requested"),
        "candidates": candidates,
        "m50": _interval(entry.get("m50")),
        "m80": _interval(entry.get("m80")),
        "m90": _interval(entry.get("m90")),
        # runs before 2026-11-29 stored emcee's diagnostics without the method's name
        "sampler": diag.get("method") or ("emcee" if "nwalkers" in diag else None),
        "converged": diag.get("converged"),
        "warnings": list(entry.get("warnings") or []),
        "posterior_file": entry.get("posterior_file"),
    }


def _files(root: Path) -> list[dict]:
    """Top-level files with their sizes and folders with their file counts and total sizes."""
    out = []
    for item in sorted(root.iterdir()):
        if item.name.startswith(".tmp-"):
            continue
        if item.is_dir():
            files = [f for f in item.rglob("*") if f.is_file()]
            out.append({"name": item.name + "/", "files": len(files), "bytes": sum(f.stat().st_size for f in files)})
        elif item.is_file():
            out.append({"name": item.name, "files": 1, "bytes": item.stat().st_size})
    return out


@dataclass(frozen=True)
class Interval:
    """A posterior quantity (mag): median, 68% and 95% intervals; ``extrapolated`` when outside the injections."""

    median: float
    lo68: float | None
    hi68: float | None
    lo95: float | None = None
    hi95: float | None = None
    extrapolated: bool = False

    @classmethod
    def from_dict(cls, d: Mapping | None) -> "Interval | None":
        if not d or d.get("median") is None:
            return None
        return cls(**{f.name: d.get(f.name) for f in dataclasses.fields(cls) if f.name != "extrapolated"},
                   extrapolated=bool(d.get("extrapolated")))


@dataclass(frozen=True)
class ModelSummary:
    """The model fitted to one kind's completeness (or purity), as ``summary.json`` records it.

    ``name`` is the chosen model and ``candidates`` the rungs it was chosen
    among (empty for a single requested model); ``skipped`` says why no model
    was fitted (the other fields are then empty).
    """

    name: str | None
    requested: str | None = None
    candidates: tuple = ()
    m50: Interval | None = None
    m80: Interval | None = None
    m90: Interval | None = None
    sampler: str | None = None
    converged: bool | None = None
    warnings: tuple = ()
    posterior_file: str | None = None
    skipped: str | None = None

    @classmethod
    def from_info(cls, d: Mapping | None) -> "ModelSummary | None":
        """From the facts of :func:`model_facts`."""
        if not d:
            return None
        return cls(name=d.get("name"), requested=d.get("requested"), candidates=tuple(d.get("candidates") or ()),
                   m50=Interval.from_dict(d.get("m50")), m80=Interval.from_dict(d.get("m80")),
                   m90=Interval.from_dict(d.get("m90")), sampler=d.get("sampler"), converged=d.get("converged"),
                   warnings=tuple(d.get("warnings") or ()), posterior_file=d.get("posterior_file"),
                   skipped=d.get("skipped"))


@dataclass(frozen=True)
class KindSummary:
    """One source kind's results: binned and model 50% completeness magnitudes, the models, the counts."""

    kind: str
    m50_binned: float | None
    model: ModelSummary | None
    purity_model: ModelSummary | None
    counts: Mapping
    mag_range: tuple | None = None
    #: sd of ``m50_binned`` from the binomial noise of the two bins it interpolates (not its bias)
    m50_binned_sd: float | None = None

    @property
    def m50_model(self) -> Interval | None:
        """The completeness model's image-average m50 (None without a fitted model)."""
        return None if self.model is None else self.model.m50


@dataclass(frozen=True)
class Run:
    """A run directory, read from its records: ``run.json`` and (once the injection stages finished)
    ``summary.json``.  Nothing is recomputed.

    Build it with :meth:`open` (or get it from :func:`comest_bayes.run`).  The pipeline writes the
    directory through :class:`comest_bayes.io.rundir.RunDirectory`; everything that reads it (the
    front door, ``comest-bayes info``, the report, the number-count fit) reads it through this class.

    Attributes
    ----------
    path : Path
        The run directory.
    state : mapping
        ``run.json``: configuration fingerprint, stages done, image facts, timings.
    summary_record : mapping or None
        ``summary.json``; None while the injection stages have not finished.
    """

    path: Path
    state: Mapping
    summary_record: Mapping | None = None

    @classmethod
    def open(cls, path) -> "Run":
        """Read a run directory (finished or partial).

        Raises
        ------
        InputFileError
            ``path`` does not exist.
        RunDirectoryError
            It holds no ``run.json``, or an unreadable one.
        """
        root = Path(path)
        if root.exists() and not root.is_dir():
            raise RunDirectoryError(f"{str(root)!r} is a file, not a run directory; give the --out directory of a "
                                    f"comest-bayes run.")
        if not root.is_dir():
            raise InputFileError(f"run directory {str(root)!r} does not exist; give the --out of a comest-bayes run.")
        if not (root / layout.RUN).is_file():
            raise RunDirectoryError(f"{str(root)!r} is not a comest-bayes run directory (no {layout.RUN}); give the "
                                    f"--out of comest-bayes run or demo.")
        state = read_record(root / layout.RUN, "run record")
        summary = read_record(root / layout.SUMMARY, "summary") if (root / layout.SUMMARY).is_file() else None
        return cls(path=root, state=state, summary_record=summary)

    # ---- raw records
    def file(self, name: str) -> Path:
        """The path of one of the run's files (a name of :mod:`comest_bayes.io.layout`, or a path under one of
        its folders); it need not exist yet.  A name that is neither is refused."""
        known = {v for k, v in vars(layout).items() if k.isupper() and isinstance(v, str)}
        parts = Path(name).parts
        if not parts or ".." in parts or Path(name).is_absolute() or (name not in known and parts[0] not in known):
            raise InputError(f"{name!r} is not a file of a comest-bayes run; the run's files and folders are "
                             f"{sorted(known)} (comest_bayes.io.layout).")
        return self.path / name

    @cached_property
    def config(self):
        """The run's :class:`~comest_bayes.config.RunConfig`, rebuilt from ``run.json``."""
        from comest_bayes.config import load_config

        fingerprint = self.state.get("fingerprint")
        if not fingerprint:
            raise RunDirectoryError(f"{str(self.file(layout.RUN))!r} is not a comest-bayes run record (no fingerprint).")
        cfg = dict(fingerprint.get("config", {}))
        seed = cfg.pop("seed", 0)
        return load_config(overrides=cfg, seed=seed)

    @property
    def kind_names(self) -> list:
        """Source kinds with results in ``summary.json`` (in run order)."""
        return list(((self.summary_record or {}).get("kinds") or {}).keys())

    def kind_entry(self, kind: str) -> dict:
        """One kind's entry of ``summary.json`` (empty when it has none)."""
        return ((self.summary_record or {}).get("kinds") or {}).get(kind, {})

    @property
    def image_facts(self) -> dict:
        """The image's facts (shape, zero point, pixel scale, FWHM and their provenance)."""
        return (self.summary_record or {}).get("image") or self.state.get("image") or {}

    # ---- typed facts
    @cached_property
    def info(self) -> Mapping:
        """The whole record :func:`run_info` returns (what ``comest-bayes info`` prints)."""
        return MappingProxyType(_facts(self))

    @property
    def status(self) -> str:
        """``finished``, ``running`` or ``partial``."""
        return self.info["status"]

    @property
    def warnings(self) -> tuple:
        """Every warning the run recorded (model fits, failed realizations, the source-free image)."""
        return tuple(self.info["warnings"])

    @cached_property
    def kinds(self) -> Mapping:
        """Per source kind, a :class:`KindSummary` (in the run's order)."""
        kinds = {}
        for kind, k in self.info["kinds"].items():
            rng = k.get("mag_range")
            kinds[kind] = KindSummary(kind=kind, m50_binned=k.get("m50_binned"),
                                      model=ModelSummary.from_info(k.get("model")),
                                      purity_model=ModelSummary.from_info(k.get("purity_model")),
                                      counts=MappingProxyType(dict(k.get("counts") or {})),
                                      mag_range=None if rng is None else tuple(rng),
                                      m50_binned_sd=k.get("m50_binned_sd"))
        return MappingProxyType(kinds)

    def _kind(self, kind: str) -> KindSummary:
        if kind not in self.kinds:
            hint = difflib.get_close_matches(str(kind), list(self.kinds), n=1)
            raise InputError(f"the run in {str(self.path)!r} has no results for kind {kind!r}"
                             + (f"; did you mean {hint[0]!r}?" if hint else "")
                             + f" Its kinds: {list(self.kinds) or 'none yet'}.")
        return self.kinds[kind]

    def summary(self, kind: str) -> KindSummary:
        """The results of one source kind (``InputError`` naming the run's kinds when it has none)."""
        return self._kind(kind)

    def catalog(self, kind: str, name: str = "matched"):
        """A merged catalog of one kind as an astropy Table.

        ``name`` is one of :data:`comest_bayes.io.layout.CATALOGS`: ``injected`` (every injection),
        ``matched`` (injection-detection pairs), ``unmatched``, ``false``
        (detections matching no source) or ``outcomes`` (one row per
        injection: true magnitude, position, detected).
        """
        from astropy.table import Table

        self._kind(kind)
        if name not in layout.CATALOGS:
            raise InputError(f"unknown catalog {name!r}; a run holds {', '.join(layout.CATALOGS)} per kind.")
        path = self.file(layout.catalog(kind, name))
        if not path.is_file():
            raise InputFileError(f"{str(path)!r} does not exist; the run may be partial (rerun it to finish).")
        return Table.read(path)

    def posterior(self, kind: str, quantity: str = "completeness"):
        """The saved posterior of one kind's completeness (or ``quantity="purity"``) model.

        Returns
        -------
        comest_bayes.bayes.posterior.CompletenessPosterior
        """
        from comest_bayes.bayes.posterior import CompletenessPosterior

        entry = self._kind(kind)
        if quantity not in ("completeness", "purity"):
            raise InputError(f"quantity {quantity!r} must be 'completeness' or 'purity'.")
        model = entry.model if quantity == "completeness" else entry.purity_model
        if model is None or model.skipped or not model.posterior_file:
            if model is not None and model.skipped:
                why = f": the model was skipped ({model.skipped})"
            else:
                option = "fit.model" if quantity == "completeness" else "fit.purity_model"
                why = f"; it was run without one ({option} = 'none', or stopped before the fits)"
            raise InputFileError(f"the run in {str(self.path)!r} holds no {quantity} posterior for kind {kind!r}{why}.")
        return CompletenessPosterior.load(self.path / model.posterior_file)

    def summary_json(self) -> dict:
        """The run's ``summary.json`` as a dict (every number the run wrote)."""
        if self.summary_record is None:
            raise InputFileError(f"{str(self.file(layout.SUMMARY))!r} does not exist; the run is {self.status}.")
        return json.loads(json.dumps(self.summary_record))  # a copy the caller may change


def run_info(run_dir) -> dict:
    """Facts about a run directory (finished or partial), from its records only (``comest-bayes info``).

    Returns
    -------
    dict
        ``path``, ``status`` (``finished``, ``running`` or ``partial``),
        ``running`` (the live lock holder or None), ``created``, ``version``,
        ``input`` (image path, shape, zero point, pixel scale, FWHM and where
        each came from), ``config`` (kinds, realizations, density, model,
        seed), ``stages`` (name -> seconds), ``realizations`` (kind -> files
        on disk), ``kinds`` (kind -> counts, ``m50_binned``, ``model``,
        ``purity_model``), ``depth_5sigma``, ``warnings`` and ``files``.

    Raises
    ------
    InputFileError
        ``run_dir`` does not exist.
    RunDirectoryError
        It holds no ``run.json``, or an unreadable one.
    """
    return _facts(Run.open(run_dir))


def _facts(run: "Run") -> dict:
    root, state, summary = run.path, dict(run.state), run.summary_record
    fingerprint = state.get("fingerprint") or {}
    config = fingerprint.get("config") or {}
    injection = config.get("injection") or {}
    image = run.image_facts
    options = state.get("input_options") or (fingerprint.get("input") or {}).get("options") or {}
    from comest_bayes.io.rundir import lock_holder  # (NumPy and astropy: not for `import comest_bayes`)

    holder = lock_holder(root) if (root / layout.LOCK).exists() else None

    stages = {}
    recorded = state.get("stages") or {}
    timings = state.get("timings") or {}
    for name in STAGE_ORDER:
        if (recorded.get(name) or {}).get("status") == "done":
            stages[name] = recorded[name].get("seconds")
    for name in ("inject", "ratios"):  # not checkpointed as stages: their time says they ran to the end
        if name in timings:
            stages[name] = timings[name]
    for name in sorted(set(recorded) - set(STAGE_ORDER)):
        if recorded[name].get("status") == "done":
            stages[name] = recorded[name].get("seconds")

    realizations = {}
    for kind in injection.get("kinds") or []:
        sims = root / layout.SIMS_DIR
        realizations[kind] = len(list(sims.glob(layout.realization_glob(kind)))) if sims.is_dir() else 0

    warnings_ = []
    kinds = {}
    for kind, entry in ((summary or {}).get("kinds") or {}).items():
        model = model_facts(entry.get("model"))
        purity = model_facts(entry.get("purity_model"))
        counts = entry.get("counts") or {}
        kinds[kind] = {"counts": counts, "m50_binned": entry.get("m50_binned"),
                       "m50_binned_sd": entry.get("m50_binned_sd"), "mag_range": entry.get("mag_range"),
                       "model": model, "purity_model": purity}
        for label, m in (("completeness", model), ("purity", purity)):
            for w in (m or {}).get("warnings", []):
                warnings_.append(f"{kind} {label}: {w}")
            if m and m.get("converged") is False:
                warnings_.append(f"{kind} {label}: the {m.get('sampler')} sampler did not converge")
        if not counts.get("usable"):
            warnings_.append(f"{kind}: no usable injection")
        if (entry.get("bright_end") or {}).get("warning"):
            warnings_.append(f"{kind} ratios: {entry['bright_end']['warning']}")
    for kind, choice in (state.get("injection_density") or {}).items():
        if isinstance(choice, dict) and choice.get("warning"):
            warnings_.append(f"density ({kind}): {choice['warning']}")
    reach = (recorded.get("baseline") or {}).get("bright_neighbours") or {}
    if reach.get("warning"):
        warnings_.append(f"injection: {reach['warning']}")
    agree = ((recorded.get("detect") or {}).get("meta") or {}).get("weight_agreement") or {}
    if agree.get("warning"):
        warnings_.append(f"weight map: {agree['warning']}")
    replacement = (recorded.get("sourcefree") or {}).get("replacement") or {}
    for w in replacement.get("warnings") or []:
        warnings_.append(f"source-free image: {w}")
    for failed in (summary or {}).get("failed_realizations") or []:
        warnings_.append(f"realization {failed} failed (rerun the same command to retry it)")

    if summary is not None and holder is None:
        status = "finished"
    elif holder is not None:
        status = "running"
    else:
        status = "partial"
    depth = ((summary or {}).get("depth") or {}).get("point_source_5sigma")
    adaptive_cfg = config.get("adaptive") or {}
    return {
        "path": str(root),
        "status": status,
        "running": holder,
        "created": state.get("created"),
        "version": (state.get("versions") or {}).get("comest-bayes"),
        "input": {
            "image": options.get("path") or image.get("path"),
            "weight": options.get("weight"),
            "mask": options.get("mask"),
            "shape": image.get("shape"),
            "zeropoint": image.get("zeropoint"),
            "pixel_scale_arcsec": image.get("pixel_scale_arcsec"),
            "fwhm_pix": image.get("fwhm_pix"),
            "provenance": image.get("provenance") or {},
        },
        "config": {"kinds": injection.get("kinds"), "nsims": injection.get("nsims"),
                   "backend": (config.get("detection") or {}).get("backend"),
                   # an adaptive run's realizations are its batches', up to max_nsims (its nsims is unused)
                   "adaptive": ({k: adaptive_cfg.get(k) for k in ("precision", "target", "magnitudes", "max_nsims")}
                                if (adaptive_cfg.get("precision") or 0) > 0 else None),
                   "density": injection.get("density"), "model": (config.get("fit") or {}).get("model"),
                   "seed": config.get("seed"),
                   # the density each kind was injected at (the automatic choice when ``density`` is 0)
                   "density_used": {k: d.get("density") for k, d in (state.get("injection_density") or {}).items()
                                    if isinstance(d, dict)},
                   # the magnitude range and how it was chosen (runs before 2026-11-29: the baseline's range only)
                   "range": state.get("injection_range")
                   or ({"mag_range": (recorded.get("baseline") or {}).get("mag_range")}
                       if (recorded.get("baseline") or {}).get("mag_range") else None)},
        "stages": stages,
        "realizations": realizations,
        "kinds": kinds,
        "depth_5sigma": depth,
        "adaptive": (summary or {}).get("adaptive"),
        "warnings": warnings_,
        "files": _files(root),
    }


