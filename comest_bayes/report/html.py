"""The self-contained HTML report of a run: ``comest-bayes report DIR``.

:func:`write_report` reads a run directory and writes ``DIR/report.html``: one file with every
figure embedded as a PNG (also saved under ``DIR/figures/``), no JavaScript and no external
resource.  A partial run gives a partial report.  The sections: ``docs/usage.md`` ("The
report").
"""

from __future__ import annotations

import base64
import datetime as _dt
import html
import re
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Callable
import json
import time

import numpy as np

from comest_bayes.report.plots import figure_png, save_figure, new_axes
from comest_bayes.report import rundata as RD
from comest_bayes.io.rundir import atomic_path
from comest_bayes.io import layout
from comest_bayes.io.run import Run
from comest_bayes.errors import InputError, RunDirectoryError
from comest_bayes.report.plots.images import figure3
from comest_bayes.report.plots.data import PosteriorBand
from comest_bayes.report.plots.completeness import band_caption, ratios_figure, magnitude_comparison_figure
from comest_bayes.report.plots.maps import m50_map_figure, ratio_maps_figure
from comest_bayes.report.plots.diagnostics import sampler_figure, selection_plot
from comest_bayes.lf.result import LFResult
from comest_bayes.report.plots.lf import corner_figure, counts_figure

__all__ = ["write_report", "ReportFigure", "lf_figures"]

#: Default side of the Figure-3 cutouts, pixels.
CUTOUT_SIZE = 400

_CSS = """
body { font-family: -apple-system, "Segoe UI", Helvetica, Arial, sans-serif; color: #222; margin: 0;
       background: #fafafa; line-height: 1.45; }
main { max-width: 1240px; margin: 0 auto; padding: 1.5em 2em 4em; background: #fff; }
h1 { font-size: 1.7em; margin-bottom: 0.2em; }
h2 { border-bottom: 2px solid #0072B2; padding-bottom: 0.2em; margin-top: 2.2em; }
h3 { margin-top: 1.6em; }
.meta { color: #555; font-size: 0.92em; }
nav { background: #f0f4f8; padding: 0.6em 1em; border-radius: 6px; font-size: 0.93em; }
nav a { margin-right: 1.1em; color: #0a4f82; text-decoration: none; }
table { border-collapse: collapse; margin: 0.8em 0; font-size: 0.9em; }
th, td { border: 1px solid #d0d7de; padding: 0.28em 0.6em; text-align: left; vertical-align: top; }
th { background: #f0f4f8; }
td.num { text-align: right; font-variant-numeric: tabular-nums; white-space: nowrap; }
tr.chosen td { background: #e6f4ea; font-weight: 600; }
figure { margin: 1.2em 0; }
figure img { max-width: 100%; height: auto; border: 1px solid #e1e4e8; }
figcaption { font-size: 0.9em; color: #444; margin-top: 0.3em; }
.note { background: #fff8e1; border-left: 4px solid #f0b400; padding: 0.45em 0.8em; margin: 0.8em 0;
        font-size: 0.92em; }
.warn { background: #fdecea; border-left: 4px solid #d93025; padding: 0.45em 0.8em; margin: 0.8em 0;
        font-size: 0.92em; }
pre { background: #f6f8fa; padding: 0.8em; overflow-x: auto; font-size: 0.85em; }
details summary { cursor: pointer; color: #0a4f82; margin: 0.4em 0; }
"""


@dataclass
class ReportFigure:
    """One figure of the report.

    Attributes
    ----------
    name : str
        File stem under ``DIR/figures/`` (``<name>.png``, ``<name>.pdf``).
    title, caption : str
    png : bytes
        The embedded image.
    """

    name: str
    title: str
    caption: str
    png: bytes


def _esc(text) -> str:
    return html.escape(str(text), quote=True)


def _num(value, fmt: str = "{:.2f}", missing: str = "n/a") -> str:
    if value is None:
        return missing
    try:
        v = float(value)
    except (TypeError, ValueError):
        return _esc(value)
    return missing if not np.isfinite(v) else fmt.format(v)


def _interval(entry: dict | None, fmt: str = "{:.2f}", *, purity: bool = False) -> str:
    """``median [lo68, hi68]`` of a posterior summary entry (of a purity model: its range is the detections')."""
    if not entry or entry.get("median") is None:
        frac = (entry or {}).get("defined_fraction")
        return "n/a" + (f" (defined in {100 * frac:.0f}% of draws)" if frac is not None else "")
    text = f"{fmt.format(entry['median'])} [{fmt.format(entry['lo68'])}, {fmt.format(entry['hi68'])}]"
    if entry.get("extrapolated"):
        text += (" extrapolated: outside the measured magnitudes of the detections" if purity
                 else " extrapolated: outside the injected magnitudes")
    return text


class _Report:
    """Accumulates HTML parts and figures."""

    def __init__(self, run: Run, figdir: Path, dpi: int, log: Callable[[str], None]):
        self.run = run
        self.figdir = figdir
        self.dpi = dpi
        self.log = log
        self.parts: list[str] = []
        self.toc: list[tuple[str, str]] = []
        self.figures: list[ReportFigure] = []
        self.missing: list[str] = []
        self.failed: list[str] = []

    # -- building blocks ------------------------------------------------------------
    def h2(self, anchor: str, title: str) -> None:
        self.toc.append((anchor, title))
        self.parts.append(f'<h2 id="{_esc(anchor)}">{_esc(title)}</h2>')

    def h3(self, title: str) -> None:
        self.parts.append(f"<h3>{_esc(title)}</h3>")

    def p(self, text: str, cls: str | None = None, raw: bool = False) -> None:
        body = text if raw else _esc(text)
        self.parts.append(f'<p class="{cls}">{body}</p>' if cls else f"<p>{body}</p>")

    def note(self, text: str, *, missing: bool = True) -> None:
        """A visible note; ``missing`` ones are also listed at the top of the report."""
        self.p(text, "note")
        if missing:
            self.missing.append(text)

    def table(self, header, rows, *, numeric=(), row_classes=None, details: str | None = None) -> None:
        out = ["<table><thead><tr>" + "".join(f"<th>{_esc(h)}</th>" for h in header) + "</tr></thead><tbody>"]
        for i, row in enumerate(rows):
            cls = (row_classes or {}).get(i)
            cells = "".join(f'<td class="num">{_esc(c)}</td>' if j in numeric else f"<td>{_esc(c)}</td>"
                            for j, c in enumerate(row))
            out.append(f'<tr class="{cls}">{cells}</tr>' if cls else f"<tr>{cells}</tr>")
        out.append("</tbody></table>")
        text = "".join(out)
        if details:
            text = f"<details><summary>{_esc(details)}</summary>{text}</details>"
        self.parts.append(text)

    def figure(self, name: str, title: str, caption: str, make: Callable) -> bool:
        """Draw a figure with ``make()``, save it as PNG and PDF, embed the PNG; a failure becomes a warning."""
        try:
            fig = make()
            png = figure_png(fig, dpi=self.dpi)
            save_figure(fig, self.figdir / name, dpi=self.dpi, formats=("pdf",))
            with atomic_path(self.figdir / f"{name}.png") as tmp:
                tmp.write_bytes(png)
        except Exception as exc:  # one broken figure must not cost the whole report
            msg = f"the figure '{title}' could not be drawn: {type(exc).__name__}: {exc}"
            self.failed.append(msg)
            self.parts.append(f'<p class="warn">{_esc(msg)}</p>'
                              f"<details><summary>details</summary><pre>{_esc(traceback.format_exc())}</pre>"
                              f"</details>")
            self.log(f"warning: report: {msg}")
            return False
        self.figures.append(ReportFigure(name, title, caption, png))
        b64 = base64.b64encode(png).decode("ascii")
        self.parts.append(f'<figure id="fig-{_esc(name)}"><img alt="{_esc(title)}" '
                          f'src="data:image/png;base64,{b64}"><figcaption><b>{_esc(title)}.</b> {_esc(caption)} '
                          f"(<code>figures/{_esc(name)}.png</code>, <code>.pdf</code>)</figcaption></figure>")
        return True

    # -- assembly ---------------------------------------------------------------------
    def html(self) -> str:
        run = self.run
        created = run.state.get("created", "?")
        now = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
        facts = run.image_facts
        head = [f"<h1>comest-bayes report: {_esc(run.path.name or run.path)}</h1>",
                f'<p class="meta">run directory <code>{_esc(run.path.resolve())}</code>; image '
                f"<code>{_esc(facts.get('path', '?'))}</code>; run created {_esc(created)}; report written "
                f"{_esc(now)}; comest-bayes {_esc((run.state.get('versions') or {}).get('comest-bayes', '?'))}</p>"]
        nav = "<nav>" + "".join(f'<a href="#{_esc(a)}">{_esc(t)}</a>' for a, t in self.toc) + "</nav>"
        top = []
        if self.missing:
            top.append('<div class="note"><b>Not in this report</b> (the run does not hold it):<ul>'
                       + "".join(f"<li>{_esc(m)}</li>" for m in self.missing) + "</ul></div>")
        if self.failed:
            top.append('<div class="warn"><b>Figures that failed</b>:<ul>'
                       + "".join(f"<li>{_esc(m)}</li>" for m in self.failed) + "</ul></div>")
        return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
                f"<title>comest-bayes report: {_esc(run.path.name)}</title><style>{_CSS}</style></head>"
                "<body><main>" + "".join(head) + nav + "".join(top) + "\n".join(self.parts)
                + "</main></body></html>\n")


# ------------------------------------------------------------------------------- sections

def _summary_section(r: _Report) -> None:
    run = r.run
    r.h2("summary", "Summary")
    if run.summary_record is None:
        r.note(f"{layout.SUMMARY} is missing: the injection stages of this run have not finished (rerun the same "
               "command to resume); the report shows the stages done so far.")
        return
    rows = []
    for kind in run.kind_names:
        k = run.kind_entry(kind)
        c = k.get("counts", {})
        model = k.get("model") or {}
        pmodel = k.get("purity_model") or {}
        rows.append([kind, c.get("usable", "?"), c.get("realizations", "?"), c.get("detected", "?"),
                     c.get("false", "?"), _num(k.get("m50_binned")) + (
                         f" ± {k['m50_binned_sd']:.3f}" if k.get("m50_binned_sd") is not None
                         else ""),
                     _interval(model.get("m50")) if model.get("name") else "no model",
                     _interval(model.get("m80")) if model.get("name") else "",
                     _interval(model.get("m90")) if model.get("name") else "",
                     model.get("name") or model.get("skipped") or "none",
                     pmodel.get("name") or ("skipped" if pmodel.get("skipped") else "none")])
    r.table(["kind", "usable injections", "realizations", "detected", "false detections", "binned m50 (mag)",
             "posterior m50 (mag) [68%]", "m80 (mag) [68%]", "m90 (mag) [68%]", "completeness model",
             "purity model"], rows, numeric=(1, 2, 3, 4, 5, 6, 7, 8))
    r.p("Binned m50: where the binned completeness first falls below 0.5. Posterior mN: image-average "
        "completeness falls to N%; median and central 68% interval over the posterior draws.", "meta")


def _facts_section(r: _Report) -> None:
    run = r.run
    facts = run.image_facts
    prov = facts.get("provenance") or {}
    r.h2("inputs", "Input facts")
    if not facts:
        r.note("the image facts are not recorded yet (the run stopped before the seeing was measured).")
        return
    fwhm = facts.get("fwhm_pix")
    scale = facts.get("pixel_scale_arcsec")
    rows = [
        ["zero point", _num(facts.get("zeropoint"), "{:.3f}") + " mag", prov.get("zeropoint", "?")],
        ["pixel scale", _num(scale, "{:.4f}") + " arcsec/pixel", prov.get("pixel_scale", "?")],
        ["seeing FWHM", (_num(fwhm) + " pixel" + (f" = {fwhm * scale:.2f} arcsec" if fwhm and scale else "")),
         prov.get("fwhm", "?")],
        ["gain", _num(facts.get("gain"), "{:.3g}", "unknown") + (" e-/unit" if facts.get("gain") else ""),
         prov.get("gain", "not given: no photon noise added to injections")],
        ["saturation", _num(facts.get("saturation"), "{:.6g}", "unknown"), prov.get("saturation", "not given")],
        ["image", f"{facts.get('path', '?')} (HDU {facts.get('hdu', '?')}), shape {facts.get('shape', '?')}",
         "WCS " + ("/".join(facts["wcs"]) if facts.get("wcs") else "none")],
        ["weight map", "yes" if facts.get("has_weight") else "none", prov.get("weight", "")],
        ["mask", f"{100 * float(facts.get('masked_fraction', 0.0)):.2f}% of the pixels masked",
         prov.get("mask", "NaN/inf pixels only")],
    ]
    psf = (run.summary_record or {}).get("psf") or run.state.get("psf")
    if psf:
        where = f"FWHM: {psf.get('fwhm_source', '?')}"
        if psf.get("beta_source"):
            where += f"; beta: {psf['beta_source']}"
        rows.append(["injected PSF", psf.get("description", psf.get("model", "?")), where])
        for line in psf.get("warnings") or []:
            rows.append(["injected PSF", "warning", line])
    check = ((run.summary_record or {}).get("kinds") or {}).get("point", {}).get("size_check")
    if check and check.get("ratio") is not None:
        rows.append(["point-source size check",
                     f"median flux_radius {check['injected']:.3f} px (injections) vs {check['stars']:.3f} px (stars): "
                     f"ratio {check['ratio']:.3f} ± {check['ratio_err']:.3f}, {check['status']}",
                     f"{check['ninjected']} detected point-source injections and {check['nstars']} stars with "
                     f"SNR >= {check.get('snr_min', 20):g}; tolerance {100 * check['tolerance']:.0f}%"])
    elif check:
        rows.append(["point-source size check", "not enough sources",
                     f"{check['ninjected']} detected point-source injections, {check['nstars']} stars"])
    rng = run.state.get("injection_range") or {}
    if rng.get("mag_range"):
        rows.append(["injected magnitudes", f"{rng['mag_range'][0]:.2f} to {rng['mag_range'][1]:.2f}",
                     rng.get("reason", "")])
    for kind, choice in (run.state.get("injection_density") or {}).items():
        rows.append([f"injections ({kind})",
                     f"{choice.get('density', float('nan')):.3g} per arcmin^2, "
                     f"{choice.get('per_realization', float('nan')):.0f} per realization",
                     (choice.get("reason") or choice.get("source", ""))
                     + (f"; warning: {choice['warning']}" if choice.get("warning") else "")])
        sizing = choice.get("sizing") or {}
        if sizing:
            rows.append([f"separation and stamps ({kind})", sizing.get("separation", ""), sizing.get("stamp", "")])
    det = (run.state.get("stages", {}).get("detect") or {})
    if det:
        cfg = run.config.detection
        rows.append(["detection", f"{det.get('nsources', '?')} sources with {cfg.backend}, threshold {cfg.thresh} "
                     f"sigma, minarea {cfg.minarea} pixels", f"noise: {(det.get('meta') or {}).get('noisemod', '?')}"])
    r.table(["quantity", "value", "where it came from"], rows)
    depth = (run.summary_record or {}).get("depth")
    if depth:
        hist = depth.get("histogram") or {}
        drows = [["5σ point-source depth (injection PSF, optimal photometry)", _num(depth.get("point_source_5sigma"))],
                 ["5σ point-source depth (Gaussian PSF of the FWHM)", _num(depth.get("point_source_5sigma_gaussian"))],
                 [f"5σ depth in a {_num(depth.get('aperture_diameter_pix'), '{:.1f}')} pixel aperture",
                  _num(depth.get("aperture_5sigma"))],
                 ["50% completeness from the detected number counts", _num(hist.get("m50"))],
                 ["median detection noise (image units)", _num(depth.get("noise_median"), "{:.4g}")]]
        r.h3("Depth references (median noise)")
        r.table(["reference", "magnitude (mag)"], drows, numeric=(1,))


def _images_section(r: _Report, center, size: int) -> None:

    run = r.run
    r.h2("images", "Images")
    if not run.file(layout.SIMS_DIR).is_dir() or not any(run.file(layout.SIMS_DIR).glob(layout.realization_glob())):
        r.note("no realization is on disk yet, so there are no image panels.")
        return
    holder = {}

    def make():
        d = RD.figure3_data(run, center=center, size=size)
        holder["d"] = d
        return figure3(d.observed, d.sourcefree, d.simulated, detections=d.detections, recovered=d.recovered,
                       missed=d.missed, false=d.false,
                       sim_title=f"simulated image ({d.kind} #{d.index}, {d.how})")

    ok = r.figure("images", "Observed, source-free and simulated image",
                  f"A {size}x{size} pixel cutout (or the whole image if smaller) of the observed image with its "
                  "detections (orange circles), the same cutout of the source-free image, and of one simulated "
                  "image: injections that were recovered (green circles, at their true positions), missed (red "
                  "squares) and false detections (yellow diamonds). One asinh stretch over the zscale interval of "
                  "the observed cutout for all three panels; masked pixels in dark blue. The simulated image is "
                  "read from disk when the run saved it, else drawn again from its truth table with the "
                  "realization's own seed (identical pixels).", make)
    if ok:
        for n in holder["d"].notes:
            r.note(n)


def _curve_for(run: Run, kind: str, quantity: str, mags):
    """Posterior band from the saved posterior, else from the summary's curve, else None (with a reason)."""
    key = "model" if quantity == "completeness" else "purity_model"
    entry = run.kind_entry(kind).get(key) or {}
    if not entry.get("name"):
        setting = "fit.model" if key == "model" else "fit.purity_model"
        return None, entry.get("skipped") or f"no {quantity} model was fitted ({setting} = none)"
    label = f"posterior ({entry['name']})"
    try:
        post = RD.load_posterior(run, kind, quantity)
        if post is not None:
            return RD.posterior_band(post, mags, label=label), None
    except Exception as exc:  # a damaged or incompatible posterior file: fall back to the summary's curve
        if not entry.get("curve"):
            return None, f"the {quantity} posterior could not be evaluated ({type(exc).__name__}: {exc})"
    if entry.get("curve"):

        return PosteriorBand.from_dict(entry["curve"], label=label), None
    return None, f"the {quantity} posterior file is missing"


def _binned_table(r: _Report, kind: str) -> None:
    b = r.run.kind_entry(kind).get("binned") or {}
    if not b:
        return
    edges = b["mag_edges"]
    rows = []

    def cell(q, i):
        n = (b.get(f"{q}_n") or [0] * len(edges))[i]
        if not n or b[q][i] is None:
            return "-"
        return f"{b[q][i]:.3f} [{b[f'{q}_lower'][i]:.3f}, {b[f'{q}_upper'][i]:.3f}] ({b[f'{q}_k'][i]}/{n})"

    for i in range(len(edges) - 1):
        dr = b.get("detection_rate", [None] * len(edges))[i]
        rows.append([f"{edges[i]:.2f}-{edges[i + 1]:.2f}", cell("completeness", i), cell("purity", i),
                     _num(dr, "{:.3f}", "-")])
    conf = f"{100 * float(b.get('confidence', 0.6827)):.0f}%"
    r.table(["magnitude bin (mag)", f"completeness [{conf} {b.get('interval', '')}] (k/n)",
             f"purity [{conf}] (k/n)", "detection rate"], rows, numeric=(1, 2, 3),
            details=f"table of the binned ratios of {kind} ({len(rows)} bins)")


def _kind_sections(r: _Report) -> None:

    run = r.run
    depth = RD.depth_lines(run.summary_record)
    for kind in run.kind_names:
        k = run.kind_entry(kind)
        r.h2(f"kind-{kind}", f"Completeness and purity: {kind}")
        lo, hi = k.get("mag_range", [None, None])
        mags = np.linspace(lo - 0.3, hi + 0.3, 141) if lo is not None else None
        bands, notes = {}, {}
        for q in ("completeness", "purity"):
            bands[q], why = _curve_for(run, kind, q, mags) if mags is not None else (None, "no range")
            if why:
                notes[q] = "no posterior curve: " + why
                r.note(f"{kind} {q}: no posterior curve ({why}).")
        comp, pur = RD.binned_curve(run, kind, "completeness"), RD.binned_curve(run, kind, "purity")
        widths = " ".join(f"{q.capitalize()}: {band_caption(bands[q], q)}." for q in ("completeness", "purity")
                          if bands[q] is not None)
        r.figure(f"ratios_{kind}", f"Completeness and purity of {kind} injections",
                 "Left: completeness (fraction of usable injections detected) versus true magnitude; right: purity "
                 "(fraction of counted detections that are injections) versus measured magnitude. Points: binned "
                 "ratios with their binomial intervals; line and bands: posterior median with 68% and 95% "
                 "bands of the image-average model; dashed lines: 5σ depths of the median noise. Lower panels: "
                 "the width (upper minus lower limit) of the 68% and 95% bands, on their own scale. "
                 + widths,
                 lambda: ratios_figure(kind, comp, pur, completeness_posterior=bands["completeness"],
                                       purity_posterior=bands["purity"], depth=depth, notes=notes))
        _binned_table(r, kind)
        _characteristic_table(r, kind)


def _characteristic_table(r: _Report, kind: str) -> None:
    k = r.run.kind_entry(kind)
    rows = []
    for q, key in (("completeness", "model"), ("purity", "purity_model")):
        e = k.get(key) or {}
        if e.get("name"):
            rows.append([q, e["name"], *(_interval(e.get(m), purity=q == "purity") for m in ("m50", "m80", "m90"))])
    if rows:
        r.table(["quantity", "model", "m50 (mag) [68%]", "m80 (mag) [68%]", "m90 (mag) [68%]"], rows,
                numeric=(2, 3, 4))


def _magnitudes_section(r: _Report) -> None:

    run = r.run
    if not run.kind_names:
        return
    r.h2("magnitudes", "Measured versus true magnitude")
    pairs = {}
    for kind in run.kind_names:
        mm = RD.matched_magnitudes(run, kind)
        if mm is not None:
            pairs[kind] = mm
    if not pairs:
        r.note("no matched catalogs (catalogs/<kind>_matched.fits) in this run.")
        return
    col = run.config.matching.mag_column.upper()
    ranges = {kind: run.kind_entry(kind).get("mag_range") for kind in pairs}
    ranges = {k: v for k, v in ranges.items() if v and None not in v}
    r.figure("magnitudes", "Measured versus true magnitude of recovered injections",
             f"Density of recovered injections (log colour scale) in measured {col} versus injected magnitude, "
             "with the 1:1 line and the running median; the axes span the whole injected range ("
             + "; ".join(f"{k}: {v[0]:.2f}-{v[1]:.2f} mag" for k, v in ranges.items())
             + "), so the faint end, where few injections are recovered, shows too.",
             lambda: magnitude_comparison_figure(pairs, measured_label=col, ranges=ranges))


def _maps_section(r: _Report) -> None:

    run = r.run
    if not run.kind_names:
        return
    r.h2("maps", "Maps")
    bin_arcmin = run.config.ratios.map_bin_arcmin
    for kind in run.kind_names:
        planes = RD.map_planes(run, kind)
        if planes is None:
            r.note(f"{kind}: no binned maps (maps/{kind}_maps.fits).")
        else:
            comp, pur = planes
            r.figure(f"maps_{kind}", f"Binned completeness and purity maps of {kind}",
                     "Completeness (top) and purity (bottom) in spatial cells over the image, one column per "
                     "magnitude range (true magnitude for completeness, measured for purity); colour scale 0-1, "
                     "grey cells hold no injections (completeness) or no detections (purity).",
                     lambda comp=comp, pur=pur, kind=kind: ratio_maps_figure(kind, comp, pur, bin_arcmin=bin_arcmin))
        model = run.kind_entry(kind).get("model") or {}
        m50 = RD.m50_map(run, kind)
        if m50 is None:
            if model.get("name"):
                r.note(f"{kind}: the selected completeness model ({model['name']}) has no spatial term, so m50 is "
                       f"the same everywhere (no m50(x, y) map).", missing=False)
            continue
        med, sd, bin_pix = m50
        r.figure(f"m50map_{kind}", f"Posterior m50(x, y) of {kind}",
                 "Left: posterior median of the 50% completeness magnitude over the image; right: its posterior "
                 "standard deviation. Cells of "
                 f"{bin_pix:.0f} pixels.",
                 lambda med=med, sd=sd, bin_pix=bin_pix, kind=kind: m50_map_figure(kind, med, sd, bin_pix,
                                                                                   model=model.get("name")))


def _model_sections(r: _Report) -> None:

    run = r.run
    entries = [(kind, q, run.kind_entry(kind).get(key)) for kind in run.kind_names
               for q, key in (("completeness", "model"), ("purity", "purity_model"))]
    if not any(e for _, _, e in entries):
        if run.summary_record is not None:
            r.h2("models", "Models")
            r.note("no completeness or purity model was fitted in this run (fit.model = none): the report shows the "
                   "binned ratios only.")
        return
    r.h2("models", "Model selection and sampler diagnostics")
    for kind, q, e in entries:
        if not e:
            continue
        r.h3(f"{kind} {q}")
        if not e.get("name"):
            r.note(f"{kind} {q}: model skipped: {e.get('skipped', 'not fitted')}.", missing=False)
            continue
        sel = e.get("selection")
        if sel and sel.get("table"):
            rows, classes = [], {}
            for i, t in enumerate(sel["table"]):
                worst = max((v.get("diff_over_sd") or 0.0 for v in (t.get("quantities") or {}).values()), default=None)
                rows.append([t["name"], t["nparams"], _num(t.get("elpd_loo")), _num(t.get("se")),
                             _num(t.get("delta_elpd")), _num(t.get("se_delta")), _num(t.get("p_loo")),
                             _num(worst), {True: "yes", False: "no"}.get(t.get("adequate"), "not checked"),
                             "yes" if t.get("chosen") else ""])
                if t.get("chosen"):
                    classes[i] = "chosen"
            r.p(f"Requested '{e.get('requested')}': selected <b>{_esc(e['name'])}</b>. "
                f"Rule: {_esc(sel.get('rule', ''))}.", raw=True)
            r.table(["model", "parameters", "elpd_loo", "se", "Δ elpd", "se Δ", "p_loo",
                     "largest |Δ quantity| / sd", "adequate", "chosen"], rows,
                    numeric=(1, 2, 3, 4, 5, 6, 7), row_classes=classes)
            table = sel["table"]
            r.figure(f"selection_{kind}_{q}", f"Model selection for the {kind} {q}",
                     "Difference in expected log predictive density (leave-one-out) of each candidate to the best one, "
                     "with its standard error; the simplest adequate model within max(4, 2 se) nats of the best is "
                     "chosen.",
                     lambda table=table: selection_plot(table, ax=new_axes(None, (7.5, 0.55 * len(table) + 1.8)))
                     .figure)
        else:
            r.p(f"Model <b>{_esc(e['name'])}</b> (requested '{_esc(e.get('requested'))}', no selection).", raw=True)
        params = e.get("parameters") or {}
        if params:
            r.table(["parameter", "median", "68% interval"],
                    [[n, _num(v.get("median"), "{:.4g}"), f"[{_num(v.get('lo68'), '{:.4g}')}, "
                      f"{_num(v.get('hi68'), '{:.4g}')}]"] for n, v in params.items()], numeric=(1, 2))
        diag = e.get("diagnostics") or {}
        if diag and diag.get("method") == "importance":
            r.table(["posterior draws", "proposal draws", "Pareto k̂", "ESS", "converged", "fit time (s)"],
                    [["importance sampling from the Laplace approximation", diag.get("ndraws"),
                      _num(diag.get("khat")), _num(diag.get("ess"), "{:.0f}"),
                      "yes" if diag.get("converged") else "NO", _num(e.get("seconds"), "{:.1f}")]],
                    numeric=(1, 2, 3, 5))
        elif diag and diag.get("method") == "nuts":
            ess = [min(b, t) for b, t in zip(diag.get("ess_bulk", []), diag.get("ess_tail", []))
                   if b is not None and t is not None]
            rhat = [v for v in diag.get("rhat", []) if v is not None]
            r.table(["posterior draws", "chains", "draws per chain", "min ESS (bulk, tail)", "max R̂",
                     "divergences", "leapfrog steps per draw", "converged", "fit time (s)"],
                    [["NUTS, preconditioned by the Laplace approximation", diag.get("nchains"), diag.get("ndraws"),
                      _num(min(ess) if ess else None, "{:.0f}"), _num(max(rhat) if rhat else None, "{:.3f}"),
                      diag.get("divergences"), _num(diag.get("mean_leapfrog"), "{:.1f}"),
                      "yes" if diag.get("converged") else "NO", _num(e.get("seconds"), "{:.1f}")]],
                    numeric=(1, 2, 3, 4, 5, 6, 8))
        elif diag:
            ess = [v for v in diag.get("ess", []) if v is not None]
            tau = [v for v in diag.get("tau", []) if v is not None]
            r.table(["walkers", "steps", "burn-in", "mean acceptance", "max τ (steps)", "min ESS", "converged",
                     "fit time (s)"],
                    [[diag.get("nwalkers", "?"), diag.get("nsteps", "?"), diag.get("burn", "?"),
                      _num(diag.get("acceptance_mean")), _num(max(tau) if tau else None, "{:.1f}"),
                      _num(min(ess) if ess else None, "{:.0f}"), "yes" if diag.get("converged") else "NO",
                      _num(e.get("seconds"), "{:.1f}")]], numeric=(0, 1, 2, 3, 4, 5, 7))
        check = e.get("shape_check") or {}
        if check.get("p_value") is not None:
            r.p(f"Shape check against the binned outcomes (comest_bayes.bayes.checks): chi2 = {check['chi2']:.1f} for "
                f"{check['dof']} magnitude bins, p = {check['p_value']:.2g}; largest deviation "
                f"{check['max_abs_z']:.1f} sigma at {check['mag_at_max']:.2f} mag. A p below 0.001 means the "
                "model's form, not its statistics, limits it: then trust the binned ratios.")
        cc = e.get("covariate_check") or {}
        parts = [(key, label, cc[key]) for key, label in (("position", "image tiles"), ("depth", "depth bins"))
                 if cc.get(key)]
        if parts:
            combined = f"; combined p = {cc['p_value']:.2g}" if len(parts) > 1 else ""
            r.p("Covariate check (the same comparison per " + " and per ".join(
                f"{label}, split by predicted {q}: chi2 = {t['chi2']:.1f} for {t['dof']} groups, "
                f"p = {t['p_value']:.2g}" for _, label, t in parts)
                + f"{combined}). A p below 0.001 means the {q} varies with "
                + " or ".join(key for key, _, _ in parts)
                + " in a way the model does not follow; the warning below names where.")
        for w in e.get("warnings") or []:
            r.p(f"warning: {w}", "warn")
        if diag and diag.get("method") not in ("importance", "nuts"):  # emcee's autocorrelation and traces

            def make(diag=diag, kind=kind, q=q, name=e["name"]):
                post = RD.load_posterior(run, kind, q)
                chain = RD.chain_samples(post) if post is not None else None
                return sampler_figure(f"{kind} {q} ({name})", diag, chain)

            r.figure(f"sampler_{kind}_{q}", f"Sampler diagnostics of the {kind} {q} model",
                     "Left: integrated autocorrelation time of each (unconstrained) parameter against the "
                     "nsteps/50 limit used to declare convergence. Right: post-burn-in traces of the key physical "
                     "parameters, one thin line per walker, black: median over walkers (no traces when the "
                     "posterior file is absent).", make)


def lf_figures(lf_dir) -> list:
    """Figures of every number-count fit under ``lf_dir`` (a run's ``lf/`` folder, or one fit's folder).

    Returns
    -------
    list of (title, matplotlib.figure.Figure)
        Two per fit (counts, corner), in name order; empty when there is no fit.
    """

    root = Path(lf_dir)
    if (root / layout.LF_POSTERIOR).is_file():
        dirs = [root]
    elif root.is_dir():
        dirs = sorted(p.parent for p in root.glob("*/" + layout.LF_POSTERIOR))
    else:
        return []
    out = []
    for d in dirs:
        res = LFResult.load(d)
        out.append((f"Number counts {res.name}: catalog versus forward model", counts_figure(res)))
        out.append((f"Number counts {res.name}: parameter posterior", corner_figure(res)))
    return out


def _lf_section(r: _Report) -> None:
    lf_dir = r.run.file(layout.LF_DIR)
    if not lf_dir.is_dir():
        return
    r.h2("lf", "Luminosity function")
    try:
        figs = list(lf_figures(lf_dir))
    except Exception as exc:
        r.p(f"the luminosity-function figures could not be made: {type(exc).__name__}: {exc}", "warn")
        r.failed.append(f"luminosity-function figures: {exc}")
        return
    used = set()
    for i, (title, fig) in enumerate(figs):
        stem = "lf_" + (re.sub(r"[^A-Za-z0-9_.-]+", "_", str(title)).strip("_") or str(i))
        if stem in used:
            stem = f"{stem}_{i}"
        used.add(stem)
        r.figure(stem, f"Luminosity function: {title}", "From the fits under lf/ (comest_bayes.report.plots.lf).",
                 lambda fig=fig: fig)


def _adaptive_section(r: _Report) -> None:
    ad = (r.run.summary_record or {}).get("adaptive")
    if not ad:
        return
    at_f = ad.get("target") == "f"
    mags = ", ".join(f"{m:.2f}" for m in ad.get("magnitudes") or [])
    goal = (f"the posterior sd of the image-average f at {mags} mag reaches {ad.get('precision')}" if at_f
            else f"the 68% half-width of m50 reaches {ad.get('precision')} mag")
    r.h2("adaptive", "Adaptive injection")
    r.p(f"Batches of realizations whose magnitudes follow the current posterior (docs/adaptive.md), "
        f"{ad.get('uniform_share', 0):.0%} of each uniform, until {goal}. The binned ratios stay valid per bin, "
        "but bins far from the design's target hold fewer injections than a uniform run's, so their intervals are "
        "wider (see the counts per bin above).")
    rows = []
    for kind, info in (ad.get("kinds") or {}).items():
        for b in info.get("batches", []):
            rows.append([kind, str(b["batch"]), b["design"], f"{b['realizations'][0]}-{b['realizations'][1] - 1}",
                         str(b["injections"]), _num(b.get("m50"), "{:.3f}"), _num(b.get("halfwidth"), "{:.4f}"),
                         _num(b.get("within_0.6_of_m50"), "{:.0%}")]
                        + ([", ".join(f"{v:.4f}" for v in b.get("f_sd") or [])] if at_f else []))
    r.table(["kind", "batch", "design", "realizations", "injections so far", "m50", "68% half-width",
             "batch within 0.6 mag of m50"] + ([f"sd of f at {mags}"] if at_f else []), rows,
            numeric=(1, 4, 5, 6, 7))
    for kind, info in (ad.get("kinds") or {}).items():
        r.p(f"{kind}: {'precision reached' if info.get('reached') else 'precision NOT reached'}: "
            f"{info.get('reason', '')}", None if info.get("reached") else "warn")
        rep = info.get("reported") or {}
        if rep.get("m50_halfwidth") is not None:
            wider = rep.get("meets_target") is False
            r.p(f"{kind}: the batches stop on the design fits (the most flexible model); the fit reported above "
                f"({rep.get('model')}) has an m50 68% half-width of {rep['m50_halfwidth']:.4f} mag"
                + (", wider than the target" if wider else "") + ".", "warn" if wider else None)

    def make():
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(6, 4))
        for kind, info in (ad.get("kinds") or {}).items():
            if at_f:  # the largest sd over the chosen magnitudes: the number the target is compared with
                pts = [(b["injections"], max(b["f_sd"])) for b in info.get("batches", []) if b.get("f_sd")]
            else:
                pts = [(b["injections"], b["halfwidth"]) for b in info.get("batches", []) if b.get("halfwidth")]
            if pts:
                ax.loglog(*zip(*pts), "o-", label=kind)
        ax.axhline(ad.get("precision"), color="k", lw=0.8, ls=":", label="target")
        ax.set_xlabel("injections")
        ax.set_ylabel(f"largest posterior sd of f at {mags} mag" if at_f else "68% half-width of m50 (mag)")
        ax.grid(alpha=0.3, which="both")
        ax.legend()
        return fig

    r.figure("adaptive_precision", "Precision against injections",
             (f"The largest posterior sd of the image-average f at {mags} mag after each batch." if at_f
              else "The 68% half-width of the image-average m50 after each batch."), make)


def _config_text(config: dict) -> str:

    lines = []
    if "seed" in config:
        lines.append(f"seed = {config['seed']}")
    for section, table in config.items():
        if not isinstance(table, dict):
            continue
        lines.append(f"\n[{section}]")
        for key, value in table.items():
            lines.append(f"{key} = {json.dumps(value)}")
    return "\n".join(lines).strip()


def _config_section(r: _Report) -> None:
    run = r.run
    r.h2("config", "Configuration")
    r.p("The resolved configuration of the run (TOML; every setting, defaults included). Rerun with "
        "--config on this text to repeat the run.")
    r.parts.append(f"<pre>{html.escape(_config_text(run.state['fingerprint'].get('config', {})), quote=False)}</pre>")
    inputs = (run.state["fingerprint"].get("input") or {})
    files = inputs.get("files") or {}
    if files:
        r.table(["input", "file", "sha256"], [[role, f.get("name"), f.get("sha256")] for role, f in files.items()])
    versions = run.state.get("versions") or {}
    if versions:
        r.table(["software", "version"], [[k, v or "not installed"] for k, v in versions.items()])


def _timings_section(r: _Report) -> None:
    run = r.run
    r.h2("timings", "Stage timings")
    stages = run.state.get("stages") or {}
    timings = dict(run.state.get("timings") or {})
    rows = []
    names = ["detect", "fwhm", "sourcefree", "baseline", "inject", "ratios", "fit"]
    for name in names + [s for s in stages if s not in names and not s.startswith("fit_")]:
        sec = timings.get(name)
        if sec is None:
            sec = (stages.get(name) or {}).get("seconds")
        if sec is not None or name in stages:
            rows.append([name, _num(sec, "{:.1f}", "not recorded")])
    for s in sorted(stages):
        if s.startswith("fit_"):
            rows.append([f"  {s[4:].replace('_', ' ', 1)} (one fit)", _num(stages[s].get("seconds"), "{:.1f}")])
    if not rows:
        r.note("no stage has finished yet.")
        return
    r.table(["stage", "wall time (s)"], rows, numeric=(1,))
    r.p("Wall times of the last run that executed each stage; a resumed run keeps the times of the stages it did "
        "not redo. Realizations and fits run in parallel, so the per-fit times add up to more than the stage.",
        "meta")


def write_report(run_dir, out=None, *, log: Callable[[str], None] | None = None, center=None,
                 size: int = CUTOUT_SIZE, dpi: int = 100) -> Path:
    """Write the self-contained HTML report of a run.

    Parameters
    ----------
    run_dir : str or Path
        The run directory (``--out`` of ``comest-bayes run`` or ``demo``).
    out : str or Path, optional
        The HTML file (default ``run_dir/report.html``).  The figures are
        always saved under ``run_dir/figures/`` as PNG and PDF.
    log : callable, optional
        Receives progress lines (default: silent).
    center : (x, y), optional
        Centre of the image cutouts, 0-based pixels (default the image centre).
    size : int
        Side of the image cutouts, pixels (default 400).
    dpi : int
        Resolution of the embedded and saved PNGs (default 100).

    Returns
    -------
    Path
        The HTML file written.

    Raises
    ------
    RunDirectoryError
        When ``run_dir`` does not hold a comest-bayes run.
    """

    import matplotlib

    log = log or (lambda s: None)
    t0 = time.perf_counter()
    if not Path(run_dir).is_dir():
        what = "is not a directory" if Path(run_dir).exists() else "does not exist"
        raise RunDirectoryError(f"{str(run_dir)!r} {what}; give the --out directory of a comest-bayes run.")
    for name, value, least in (("size", size, 16), ("dpi", dpi, 10)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
            raise InputError(f"{name} must be a whole number of at least {least}, got {value!r}.")
    run = Run.open(run_dir)
    out = Path(out) if out is not None else run.path / layout.REPORT
    figdir = run.path / layout.FIGURES_DIR
    figdir.mkdir(exist_ok=True)
    r = _Report(run, figdir, dpi, log)
    with matplotlib.rc_context({"font.size": 10, "axes.titlesize": 11, "axes.labelsize": 10, "legend.fontsize": 8,
                                "figure.dpi": dpi, "savefig.dpi": dpi}):
        _summary_section(r)
        _facts_section(r)
        _images_section(r, center, size)
        _kind_sections(r)
        _magnitudes_section(r)
        _maps_section(r)
        _model_sections(r)
        _adaptive_section(r)
        _lf_section(r)
        _config_section(r)
        _timings_section(r)
    text = r.html()
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(out) as tmp:
        tmp.write_text(text, encoding="utf-8")
    log(f"report: {out} ({len(r.figures)} figures, also as PNG and PDF in {figdir}) in "
        f"{time.perf_counter() - t0:.1f} s")
    return out
