"""The text ``comest-bayes info DIR`` prints: :func:`format_info` of the record
:func:`comest_bayes.io.run.run_info` reads from ``run.json`` and ``summary.json`` alone (input facts,
stages and their times, per-kind m50 with intervals, the chosen model, warnings, files)."""

from __future__ import annotations

from comest_bayes.io import layout

__all__ = ["format_info"]


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
    used = cfg.get("density_used") or {}
    if cfg.get("density"):
        density = f"{cfg['density']:g} per arcmin^2"
    elif used:
        density = "density automatic (" + ", ".join(f"{k} {v:.3g}" for k, v in used.items() if v is not None) \
            + " per arcmin^2)"
    else:
        density = "density automatic"
    adaptive = cfg.get("adaptive")
    count = (f"adaptive batches of at most {adaptive.get('max_nsims')} realizations per kind" if adaptive
             else f"{cfg.get('nsims')} realizations per kind")
    lines.append(f"config: kinds {', '.join(cfg.get('kinds') or [])}; {count}; "
                 f"{density}; detector {cfg.get('backend') or 'sep'}; model {cfg.get('model')}; seed {cfg.get('seed')}")
    rng = cfg.get("range") or {}
    if rng.get("mag_range"):
        lo, hi = rng["mag_range"]
        how = {"user": "as set", "m5": "automatic: m5 - 5 to m5 + 1.5",
               "confused": (f"automatic, a confused field: from where brighter sources cover "
                            f"{100 * (rng.get('cover_bright') or 0):.0f}% of the image, instead of m5 - 5 = "
                            f"{rng.get('usual_bright', float('nan')):.2f}")}.get(rng.get("rule"))
        lines.append(f"injected magnitudes: {lo:.2f}-{hi:.2f}" + (f" ({how})" if how else ""))
    if info["stages"]:
        lines.append("stages done: " + ", ".join(f"{k} ({v:.1f} s)" if isinstance(v, (int, float)) else k
                                                  for k, v in info["stages"].items()))
    else:
        lines.append("stages done: none")
    if info["realizations"]:
        if adaptive:  # the batches stop at the precision or at the cap: no count is the "whole"
            lines.append("realizations on disk: " + ", ".join(f"{k} {n}" for k, n in info["realizations"].items())
                         + f" (adaptive; at most {adaptive.get('max_nsims')} per kind)")
        else:
            nsims = cfg.get("nsims")
            lines.append("realizations on disk: " + ", ".join(f"{k} {n}/{nsims}" for k, n in info["realizations"].items()))
    if not info["kinds"]:
        advice = ("the run is still going" if info.get("status") == "running"
                  else "rerun the same command to finish the run")
        lines.append(f"results: none yet (no {layout.SUMMARY}); {advice}")
    for kind, k in info["kinds"].items():
        c = k.get("counts") or {}
        lines.append(f"{kind}: {c.get('detected', 0)}/{c.get('usable', 0)} usable injections detected in "
                     f"{c.get('realizations', 0)} realizations, {c.get('false', 0)} false detections")
        sd = k.get("m50_binned_sd")
        lines.append(f"  m50 binned: {_mag(k.get('m50_binned'))}"
                     + (f" +- {sd:.3f} (spread of the first crossing under the bins' binomial noise)"
                        if sd is not None else ""))
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
            rep = a.get("reported") or {}
            if rep.get("m50_halfwidth") is not None:
                lines.append(f"    reported fit {rep.get('model')}: m50 half-width {_num(rep['m50_halfwidth'])}"
                             + ("" if rep.get("meets_target") is None
                                else " (within the target)" if rep["meets_target"] else " (wider than the target)"))
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
