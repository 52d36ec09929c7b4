"""What a run directory holds, read from its ``run.json`` and ``summary.json`` alone.

``comest-bayes info DIR`` prints it: the input and its facts, the stages done
with their times, per source kind the binned and the model 50% completeness
magnitudes with their intervals, the chosen model, the warnings, and the files.
Nothing is recomputed and nothing is written, so it is instant on a finished
run and works on a partial one (a run still going, or one that was stopped).

From Python, :func:`run_info` returns the same as a JSON-ready dict and
:func:`format_info` turns that into the printed text.
"""

from __future__ import annotations

import json
from pathlib import Path

from comest_bayes.errors import InputFileError, RunDirectoryError
from comest_bayes.io.rundir import LOCK_FILE, RUN_FILE, lock_holder
from comest_bayes.io import layout

__all__ = ["run_info", "format_info", "model_facts"]

SUMMARY_FILE = layout.SUMMARY
#: Stages in the order of the data flow (fits follow, one per kind and quantity).
STAGE_ORDER = ("detect", "fwhm", "sourcefree", "baseline")


def _read_json(path: Path, what: str) -> dict:
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
        "sampler": diag.get("method"),
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


def run_info(run_dir) -> dict:
    """Facts about a run directory (finished or partial), from its records only.

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
    root = Path(run_dir)
    if not root.is_dir():
        raise InputFileError(f"run directory {str(root)!r} does not exist; give the --out of a comest-bayes run.")
    if not (root / RUN_FILE).is_file():
        raise RunDirectoryError(f"{str(root)!r} is not a comest-bayes run directory (no {RUN_FILE}); give the --out "
                                f"of comest-bayes run or demo.")
    state = _read_json(root / RUN_FILE, "run record")
    summary = _read_json(root / SUMMARY_FILE, "summary") if (root / SUMMARY_FILE).is_file() else None
    fingerprint = state.get("fingerprint") or {}
    config = fingerprint.get("config") or {}
    injection = config.get("injection") or {}
    image = (summary or {}).get("image") or state.get("image") or {}
    options = state.get("input_options") or (fingerprint.get("input") or {}).get("options") or {}
    holder = lock_holder(root) if (root / LOCK_FILE).exists() else None

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
        kinds[kind] = {"counts": counts, "m50_binned": entry.get("m50_binned"), "mag_range": entry.get("mag_range"),
                       "model": model, "purity_model": purity}
        for label, m in (("completeness", model), ("purity", purity)):
            for w in (m or {}).get("warnings", []):
                warnings_.append(f"{kind} {label}: {w}")
            if m and m.get("converged") is False:
                warnings_.append(f"{kind} {label}: the {m.get('sampler')} sampler did not converge")
        if not counts.get("usable"):
            warnings_.append(f"{kind}: no usable injection")
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
                   "density": injection.get("density"), "model": (config.get("fit") or {}).get("model"),
                   "seed": config.get("seed")},
        "stages": stages,
        "realizations": realizations,
        "kinds": kinds,
        "depth_5sigma": depth,
        "adaptive": (summary or {}).get("adaptive"),
        "warnings": warnings_,
        "files": _files(root),
    }


def _num(value) -> str:
    return "n/a" if value is None else f"{value:.4f}"


def _mag(value) -> str:
    return "n/a" if value is None else f"{value:.2f}"


def _q(q: dict | None) -> str:
    if not q:
        return "n/a"
    text = f"{q['median']:.3f} [68%: {q['lo68']:.3f}, {q['hi68']:.3f}]"
    if q.get("lo95") is not None and q.get("hi95") is not None:
        text += f" [95%: {q['lo95']:.3f}, {q['hi95']:.3f}]"
    return text + (" (extrapolated)" if q.get("extrapolated") else "")


def _size(n: int) -> str:
    for unit in ("B", "kB", "MB", "GB"):
        if n < 1000 or unit == "GB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000.0
    return f"{n:.1f} GB"  # pragma: no cover


def format_info(info: dict) -> str:
    """The text ``comest-bayes info`` prints for :func:`run_info`'s result."""
    lines = [f"run: {info['path']} ({info['status']}"
             + (f"; created {info['created']}" if info.get("created") else "")
             + (f"; comest-bayes {info['version']}" if info.get("version") else "") + ")"]
    if info.get("running"):
        h = info["running"]
        lines.append(f"  in use by process {h.get('pid')} on {h.get('host')} since {h.get('started')}")
    inp = info["input"]
    lines.append(f"image: {inp['image']}" + (f"  (weight {inp['weight']})" if inp.get("weight") else "")
                 + (f"  (mask {inp['mask']})" if inp.get("mask") else ""))
    prov = inp.get("provenance") or {}
    if inp.get("shape"):
        ny, nx = inp["shape"]
        lines.append(f"  {nx}x{ny} px; zero point {inp['zeropoint']:g} ({prov.get('zeropoint', '?')}); "
                     f"pixel scale {inp['pixel_scale_arcsec']:.4g}\" ({prov.get('pixel_scale', '?')})")
    if inp.get("fwhm_pix"):
        how = prov.get("fwhm", "?")
        how = how if len(how) <= 80 else how[:77] + "..."
        lines.append(f"  seeing FWHM {inp['fwhm_pix']:.2f} px ({how})")
    cfg = info["config"]
    lines.append(f"config: kinds {', '.join(cfg.get('kinds') or [])}; {cfg.get('nsims')} realizations per kind; "
                 f"{cfg.get('density')} per arcmin^2; model {cfg.get('model')}; seed {cfg.get('seed')}")
    if info["stages"]:
        lines.append("stages done: " + ", ".join(f"{k} ({v:.1f} s)" if isinstance(v, (int, float)) else k
                                                  for k, v in info["stages"].items()))
    else:
        lines.append("stages done: none")
    if info["realizations"]:
        nsims = cfg.get("nsims")
        lines.append("realizations on disk: " + ", ".join(f"{k} {n}/{nsims}" for k, n in info["realizations"].items()))
    if not info["kinds"]:
        lines.append("results: none yet (no summary.json); rerun the same command to finish the run")
    for kind, k in info["kinds"].items():
        c = k.get("counts") or {}
        lines.append(f"{kind}: {c.get('detected', 0)}/{c.get('usable', 0)} usable injections detected in "
                     f"{c.get('realizations', 0)} realizations, {c.get('false', 0)} false detections")
        lines.append(f"  m50 binned: {_mag(k.get('m50_binned'))}")
        m = k.get("model")
        if m and m.get("skipped"):
            lines.append(f"  completeness model: skipped ({m['skipped']})")
        elif m:
            chosen = m["name"]
            if m.get("candidates") and len(m["candidates"]) > 1:
                chosen += f" (chosen among {', '.join(m['candidates'])})"
            lines.append(f"  completeness model: {chosen}")
            for q in ("m50", "m80", "m90"):
                lines.append(f"    {q}: {_q(m.get(q))}")
        p = k.get("purity_model")
        if p and p.get("skipped"):
            lines.append(f"  purity model: skipped ({p['skipped']})")
        elif p:
            q = next((q for q in ("m50", "m80", "m90") if p.get(q)), None)
            lines.append(f"  purity model: {p['name']}; "
                         + (f"{q[1:]}% purity at {_q(p[q])}" if q else "no purity crossing in the range"))
    ad = info.get("adaptive")
    if ad:
        at_f = ad.get("target") == "f"
        mags = ", ".join(f"{m:.2f}" for m in ad.get("magnitudes") or [])
        lines.append(f"adaptive injection: target sd of f {ad.get('precision')} at {mags} mag" if at_f
                     else f"adaptive injection: target m50 half-width {ad.get('precision')} mag")
        for kind, a in (ad.get("kinds") or {}).items():
            last = (a.get("batches") or [{}])[-1]
            reached = (f"sd of f {', '.join(_num(v) for v in last.get('f_sd') or [])}" if at_f
                       else f"half-width {_num(last.get('halfwidth'))}")
            lines.append(f"  {kind}: {'reached' if a.get('reached') else 'NOT reached'} in {len(a.get('batches') or [])} "
                         f"batches, {a.get('realizations')} realizations, {last.get('injections')} injections "
                         f"({reached})")
    if info.get("depth_5sigma") is not None:
        lines.append(f"5-sigma point-source depth: {info['depth_5sigma']:.2f} mag")
    if info["warnings"]:
        lines.append(f"warnings ({len(info['warnings'])}):")
        lines += [f"  - {w}" for w in info["warnings"]]
    else:
        lines.append("warnings: none")
    lines.append("files:")
    for f in info["files"]:
        lines.append(f"  {f['name']:<24} {_size(f['bytes']):>9}" + (f"  ({f['files']} files)" if f["name"].endswith("/")
                                                                     else ""))
    return "\n".join(lines)
