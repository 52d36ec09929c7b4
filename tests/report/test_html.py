"""The HTML report of a run: self-contained, one embedded image per expected figure, right numbers, partial runs,
rendering in headless Chromium, and the ``report`` subcommand."""

import base64
import json
import re
import shutil
import struct
import subprocess

import numpy as np
import pytest
from astropy.io import fits

from comest_bayes.cli import main
from comest_bayes.config import load_config
from comest_bayes.sim.demo import MASK_GAP, make_demo_tile, write_demo_tile
from comest_bayes.errors import RunDirectoryError
from comest_bayes.pipeline.stages import ImageOptions, run_pipeline
from comest_bayes.report.plots import new_axes
from comest_bayes.report import rundata as RD
from comest_bayes.report.html import write_report
from comest_bayes.io.run import Run

FIGURE_RE = re.compile(r'<figure id="fig-([^"]+)"><img alt="[^"]*" src="data:image/png;base64,([A-Za-z0-9+/=]+)">')


@pytest.fixture(scope="module")
def tile(tmp_path_factory):
    d = tmp_path_factory.mktemp("tile")
    return write_demo_tile(make_demo_tile(seed=3, size=500, star_density=6.0), d)


def _options(paths):
    return ImageOptions(path=str(paths["image"]), weight=str(paths["weight"]), mask=str(paths["mask"]),
                        mask_bits=MASK_GAP)


@pytest.fixture(scope="module")
def report_run(tile, tmp_path_factory):
    """A small complete run (two kinds, two realizations, logistic fits, images saved) and its report."""
    out = tmp_path_factory.mktemp("run") / "run"
    config = load_config(overrides=["injection.nsims=2", "fit.model=logistic", "fit.min_ess=100",
                                    "injection.write_images=true"], seed=2)
    run_pipeline(_options(tile), config, out, log=lambda s: None)
    lines = []
    path = write_report(out, log=lines.append)
    return out, path, lines


@pytest.fixture(scope="module")
def report_figures(report_run):
    """The report's matplotlib figures by name (the report is written again, keeping them)."""
    from comest_bayes.report import html as R

    figures = {}
    original = R._Report.figure

    def keep(self, name, title, caption, make):
        def made():
            fig = make()
            figures[name] = (fig, caption)
            return fig
        return original(self, name, title, caption, made)

    R._Report.figure = keep
    try:
        write_report(report_run[0], out=report_run[0] / "again.html")
    finally:
        R._Report.figure = original
    return figures


@pytest.fixture(scope="module")
def partial_run(report_run, tmp_path_factory):
    """The same run with its posteriors removed and one kind only (as a run with fit.model=none, kinds=point)."""
    src = report_run[0]
    out = tmp_path_factory.mktemp("partial") / "run"
    shutil.copytree(src, out, ignore=shutil.ignore_patterns("figures", "report.html", "posterior"))
    summary = json.loads((out / "summary.json").read_text())
    first = next(iter(summary["kinds"]))
    summary["kinds"] = {first: {k: v for k, v in summary["kinds"][first].items()
                                if k not in ("model", "purity_model")}}
    (out / "summary.json").write_text(json.dumps(summary))
    return out, first


def _figures(html: str) -> dict:
    return {name: base64.b64decode(b64) for name, b64 in FIGURE_RE.findall(html)}


def _png_size(png: bytes) -> tuple[int, int]:
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    return struct.unpack(">II", png[16:24])


def _expected_figures(summary: dict, run_dir) -> set:
    names = {"images", "magnitudes"}
    for kind, k in summary["kinds"].items():
        names |= {f"ratios_{kind}", f"maps_{kind}"}
        for q, key in (("completeness", "model"), ("purity", "purity_model")):
            entry = k.get(key) or {}
            if entry.get("name"):
                if (entry.get("diagnostics") or {}).get("method") not in ("importance", "nuts"):  # emcee's chains
                    names.add(f"sampler_{kind}_{q}")
                if entry.get("selection"):
                    names.add(f"selection_{kind}_{q}")
        if (k.get("model") or {}).get("m50_map_file"):
            names.add(f"m50map_{kind}")
    return names


def _assert_self_contained(html: str) -> None:
    low = html.lower()
    for bad in ("http://", "https://", "<script", "<link", "@import", "url(", "<iframe"):
        assert bad not in low, bad
    srcs = re.findall(r'src="([^"]*)"', html)
    assert all(s.startswith("data:image/png;base64,") for s in srcs)


def test_report_embeds_one_image_per_expected_figure_and_nothing_external(report_run):
    out, path, lines = report_run
    assert path == out / "report.html"
    html = path.read_text()
    _assert_self_contained(html)
    summary = json.loads((out / "summary.json").read_text())
    figs = _figures(html)
    assert set(figs) == _expected_figures(summary, out)
    assert html.count("<img ") == len(figs)
    for name, png in figs.items():
        # the embedded image is the saved PNG, and the PDF is next to it
        assert (out / "figures" / f"{name}.png").read_bytes() == png
        assert (out / "figures" / f"{name}.pdf").read_bytes()[:5] == b"%PDF-"
        w, h = _png_size(png)
        assert w >= 300 and h >= 200
    assert not list(out.glob(".tmp-*")) and not list((out / "figures").glob(".tmp-*"))
    assert "warn" not in html.split("<main>")[1].split("<h2")[0]  # no failed figure
    assert any(f"{len(figs)} figures" in s for s in lines)


def test_report_tables_hold_the_numbers_of_the_run(report_run):
    out, path, _ = report_run
    html = path.read_text()
    summary = json.loads((out / "summary.json").read_text())
    state = json.loads((out / "run.json").read_text())
    for kind, k in summary["kinds"].items():
        row = re.search(rf"<tr><td>{kind}</td>(.*?)</tr>", html).group(1)
        assert f"{k['m50_binned']:.2f}" in row
        m50 = k["model"]["m50"]
        assert f"{m50['median']:.2f} [{m50['lo68']:.2f}, {m50['hi68']:.2f}]" in row
        assert f">{k['counts']['usable']}<" in row
        # the binned table: the first bin's completeness with its interval and counts
        b = k["binned"]
        i = next(j for j, n in enumerate(b["completeness_n"]) if n)
        assert (f"{b['completeness'][i]:.3f} [{b['completeness_lower'][i]:.3f}, {b['completeness_upper'][i]:.3f}] "
                f"({b['completeness_k'][i]}/{b['completeness_n'][i]})") in html
        if not (k.get("purity_model") or {}).get("name"):
            assert f"{kind} purity: no posterior curve" in html
    facts = state["image"]
    assert f"{facts['zeropoint']:.3f} mag" in html and facts["provenance"]["zeropoint"] in html
    assert f"{facts['fwhm_pix']:.2f} pixel = {facts['fwhm_pix'] * facts['pixel_scale_arcsec']:.2f} arcsec" in html
    assert "Moffat" in html  # where the FWHM came from
    # how many injections per realization, and why (the automatic density rule or the user's)
    for kind, choice in state["injection_density"].items():
        assert f"injections ({kind})" in html and choice["reason"] in html
        assert f"{choice['per_realization']:.0f} per realization" in html
    assert f"{summary['depth']['point_source_5sigma']:.2f}" in html
    # stage timings and the configuration
    for stage in ("detect", "sourcefree", "baseline", "inject", "ratios", "fit"):
        assert f"<td>{stage}</td>" in html
    assert 'model = "logistic"' in html and "[detection]" in html


def test_measured_versus_true_panel_spans_the_faintest_injection(report_run, report_figures):
    from astropy.table import Table

    out = report_run[0]
    fig, caption = report_figures["magnitudes"]
    summary = json.loads((out / "summary.json").read_text())
    for ax, kind in zip([a for a in fig.axes if a.get_title()], summary["kinds"]):
        assert ax.get_title() == f"{kind}: recovered injections"
        injected = np.asarray(Table.read(out / "catalogs" / f"{kind}_outcomes.fits")["mag"], float)
        lo, hi = ax.get_xlim()
        # the whole injected range, not only where recovered pairs are dense
        assert lo <= injected.min() and hi >= injected.max()
        assert ax.get_ylim() == (lo, hi)
        r = summary["kinds"][kind]["mag_range"]
        assert f"{kind}: {r[0]:.2f}-{r[1]:.2f} mag" in caption


def test_band_widths_are_drawn_and_stated_from_the_posterior(report_run, report_figures):
    out, path, _ = report_run
    run = Run.open(out)
    html = path.read_text()
    for kind in run.kind_names:
        fig, caption = report_figures[f"ratios_{kind}"]
        k = run.kind_entry(kind)
        lo, hi = k["mag_range"]
        mags = np.linspace(lo - 0.3, hi + 0.3, 141)
        band = RD.posterior_band(RD.load_posterior(run, kind, "completeness"), mags, label="x")
        w95 = np.asarray(band.hi95) - np.asarray(band.lo95)
        j = int(np.argmax(w95))
        # the caption's numbers are the posterior's widest 95% and 68% bands and where the 95% one is
        assert f"widest 95% band {w95[j]:.3f} in f (at {mags[j]:.2f} mag)" in caption
        w68 = np.max(np.asarray(band.hi68) - np.asarray(band.lo68))
        assert f"widest 68% band {w68:.3f}" in caption
        assert f"widest 95% band {w95[j]:.3f} in f" in html
        # bands under 0.05 wide are said to be hardly visible at full scale, wider ones are not
        assert ("hardly visible" in caption.split("Purity:")[0]) == bool(w95[j] < 0.05)
        # the band-width panel under the completeness panel draws hi95 - lo95 against magnitude
        low = fig.axes[1]
        assert low.get_ylabel() == "band width"
        np.testing.assert_allclose(low.lines[0].get_xdata(), mags)
        np.testing.assert_allclose(low.lines[0].get_ydata(), w95, rtol=1e-6, atol=1e-9)


def test_rerendered_realization_is_the_saved_simulated_image(report_run):
    out = report_run[0]
    run = Run.open(out)
    kind = run.kind_names[0]
    saved = fits.getdata(out / "sims" / kind / "image_r00000.fits")
    image, how = RD.simulated_image(run, kind, 0, prefer_saved=False)
    assert how == "re-rendered"
    np.testing.assert_array_equal(image, saved)  # same truth, same seed: identical pixels
    assert RD.simulated_image(run, kind, 0)[1] == "saved"


def test_figure3_markers_are_the_realization_outcomes(report_run):
    out = report_run[0]
    run = Run.open(out)
    d = RD.figure3_data(run, size=200, center=(250, 250))
    assert d.sourcefree.data.shape == (200, 200) and (d.sourcefree.x0, d.sourcefree.y0) == (150, 150)
    assert d.observed is not None and not d.notes
    with fits.open(out / "sims" / d.kind / f"r{d.index:05d}.fits") as h:
        truth, dets = h["TRUTH"].data, h["DETECTIONS"].data
    usable = truth["usable"].astype(bool)
    assert len(d.recovered.x) + len(d.missed.x) == usable.sum()
    assert len(d.recovered.x) == (usable & truth["detected"].astype(bool)).sum()
    assert len(d.false.x) == dets["false"].astype(bool).sum()
    det = fits.getdata(out / "detection.fits", 1)
    assert len(d.detections.x) == len(det)
    # the observed cutout is the input image there, masked pixels blank
    image = fits.getdata(run.state["input_options"]["path"])  # where the run found its input
    good = np.isfinite(d.observed.data)
    np.testing.assert_allclose(d.observed.data[good], image[150:350, 150:350][good])


def test_a_posterior_sampled_by_nuts_gets_its_diagnostics_table(report_run, tmp_path):
    # The run's completeness entry given NUTS diagnostics (as a fit whose importance sampling failed writes
    # them): the report states chains, draws, the smallest ESS, the largest R-hat and the divergences, and
    # draws no emcee autocorrelation figure for it.
    out = tmp_path / "run"
    shutil.copytree(report_run[0], out, ignore=shutil.ignore_patterns("figures", "report.html", "again.html"))
    summary = json.loads((out / "summary.json").read_text())
    kind = next(iter(summary["kinds"]))
    summary["kinds"][kind]["model"]["diagnostics"] = {
        "method": "nuts", "names": ["m50_0", "log_w"], "ess_bulk": [812.0, 655.0], "ess_tail": [590.0, 701.0],
        "rhat": [1.002, 1.007], "divergences": 0, "step_size": [0.21, 0.25, 0.19, 0.22], "mean_leapfrog": 27.5,
        "gradients": 120000, "nchains": 4, "ndraws": 500, "nwarmup": 300, "target_accept": 0.9, "min_ess": 400.0,
        "converged": True, "warnings": [], "seconds": 21.0}
    (out / "summary.json").write_text(json.dumps(summary))
    html = write_report(out).read_text()
    row = html.split("NUTS, preconditioned by the Laplace approximation")[1].split("</tr>")[0]
    cells = re.findall(r"<td[^>]*>([^<]*)</td>", row)
    assert cells[:7] == ["4", "500", "590", "1.007", "0", "27.5", "yes"], cells
    assert f"sampler_{kind}_completeness" not in _figures(html)


def test_partial_run_without_posteriors_and_one_kind(partial_run):
    out, kind = partial_run
    html = write_report(out).read_text()
    _assert_self_contained(html)
    assert set(_figures(html)) == {"images", "magnitudes", f"ratios_{kind}", f"maps_{kind}"}
    assert "no completeness or purity model was fitted" in html
    assert f"{kind} completeness: no posterior curve (no completeness model was fitted" in html
    assert "Not in this report" in html


def test_run_stopped_before_the_injections(partial_run, tmp_path):
    out = tmp_path / "run"
    shutil.copytree(partial_run[0], out, ignore=shutil.ignore_patterns("figures", "report.html", "sims", "catalogs",
                                                                       "maps", "summary.json"))
    html = write_report(out).read_text()
    _assert_self_contained(html)
    assert not _figures(html)
    assert "summary.json is missing" in html and "no realization is on disk yet" in html
    assert "zero point" in html and "<td>detect</td>" in html


def test_lf_section_calls_the_lf_figures_when_present(partial_run, monkeypatch):
    out, _ = partial_run
    (out / "lf" / "r_band").mkdir(parents=True, exist_ok=True)
    calls = []

    def lf_figures(lf_dir):
        calls.append(lf_dir)
        ax = new_axes()
        ax.plot([20, 21, 22], [1, 10, 100])
        return [("r band: counts", ax.figure), ("r band: counts", ax.figure)]

    import comest_bayes.report.html as report_module

    monkeypatch.setattr(report_module, "lf_figures", lf_figures)
    target = out / "lf_report.html"
    try:
        html = write_report(out, target).read_text()
    finally:
        shutil.rmtree(out / "lf")
    assert calls == [out / "lf"] and target.is_file()
    # titles become safe, distinct file names
    assert {"lf_r_band_counts", "lf_r_band_counts_1"} <= set(_figures(html)) and "Luminosity function" in html
    assert (out / "figures" / "lf_r_band_counts.pdf").is_file()


@pytest.mark.skipif(shutil.which("chromium") is None,
                    reason="chromium is not installed (apt-get install chromium); .ci/run installs it")
def test_report_renders_in_headless_chromium(report_run, tmp_path):
    out, path, _ = report_run
    html = path.read_text()
    figs = _figures(html)
    # A copy with a probe script that writes every image's decoded size into the DOM after loading.
    probe = ("<script>window.addEventListener('load', function () {var r = [];"
             "for (const im of document.images) {r.push(im.complete && im.naturalWidth > 0 ? "
             "im.naturalWidth + 'x' + im.naturalHeight : 'broken');}"
             "var p = document.createElement('pre'); p.id = 'probe'; p.textContent = r.join(' ');"
             "document.body.appendChild(p);});</script>")
    probed = tmp_path / "probe.html"
    probed.write_text(html.replace("</body>", probe + "</body>"))
    flags = ["--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars"]
    dom = subprocess.run(["chromium", *flags, "--virtual-time-budget=10000", "--dump-dom", probed.as_uri()],
                         capture_output=True, text=True, timeout=180).stdout
    found = re.search(r'<pre id="probe">([^<]*)</pre>', dom)
    assert found, dom[-500:]
    sizes = found.group(1).split()
    assert sizes == [f"{w}x{h}" for w, h in (_png_size(png) for png in figs.values())]

    shot = tmp_path / "shot.png"
    subprocess.run(["chromium", *flags, f"--screenshot={shot}", "--window-size=1280,2400", path.as_uri()],
                   capture_output=True, timeout=180)
    import matplotlib.image as mpimg

    pixels = mpimg.imread(shot)[..., :3]
    assert pixels.shape[:2] == (2400, 1280)
    # not blank: plenty of non-white pixels (text, tables, the image panels) and real contrast
    assert (pixels.mean(axis=2) < 0.9).mean() > 0.05 and pixels.std() > 0.1


def test_cli_report_writes_where_asked_and_prints_the_path(partial_run, tmp_path, capsys):
    out, _ = partial_run
    target = tmp_path / "elsewhere" / "r.html"
    assert main(["report", str(out), "--out", str(target), "--size", "120", "--center", "200,260"]) == 0
    printed = capsys.readouterr().out
    assert f"report: {target}" in printed and target.is_file()
    assert main(["report", str(out), "--out", str(tmp_path / "q.html"), "--quiet"]) == 0
    assert capsys.readouterr().out == ""


@pytest.mark.parametrize("make", ["missing", "not_a_run", "a_file"])
def test_cli_report_on_a_non_run_gives_one_error_line(tmp_path, capsys, make):
    target = tmp_path / "dir"
    if make == "not_a_run":
        target.mkdir()
        (target / "something.fits").write_bytes(b"")
    elif make == "a_file":
        target.write_text("x")
    assert main(["report", str(target)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error:") and len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert "comest-bayes run" in err
    with pytest.raises(RunDirectoryError, match="comest-bayes run"):  # --debug: the same error, raised
        main(["report", str(target), "--debug"])


@pytest.mark.slow
def test_cli_run_writes_the_report_unless_told_not_to(tile, tmp_path, capsys):
    out = tmp_path / "run"
    args = ["run", str(tile["image"]), "--out", str(out), "--weight", str(tile["weight"]), "--mask",
            str(tile["mask"]), "--mask-bits", str(MASK_GAP), "--nsims", "1", "--kinds", "point", "--model", "none",
            "--set", "fit.purity_model=none", "--ncpu", "1"]
    assert main(args + ["--no-report"]) == 0
    assert not (out / "report.html").exists()
    capsys.readouterr()
    assert main(args) == 0  # resumes the finished run and writes the report
    printed = capsys.readouterr().out
    assert (out / "report.html").is_file()
    last = printed.strip().splitlines()
    assert last[-1] == f"report: {out / 'report.html'}"
    assert any(line.strip().startswith("point") and "50% completeness: binned" in line for line in last)


def test_report_options_and_the_extrapolation_label_of_a_purity_model(tmp_path):
    from comest_bayes.errors import InputError
    from comest_bayes.report.html import _interval

    for bad in ({"size": 0}, {"size": 12.5}, {"dpi": 0}):
        with pytest.raises(InputError, match="must be a whole number of at least"):
            write_report(tmp_path, **bad)
    from comest_bayes.errors import RunDirectoryError
    with pytest.raises(RunDirectoryError, match="'.*nowhere' does not exist; give the --out directory"):
        write_report(tmp_path / "nowhere")
    entry = {"median": 26.1, "lo68": 25.9, "hi68": 26.3, "extrapolated": True}
    assert _interval(entry).endswith("extrapolated: outside the injected magnitudes")
    assert _interval(entry, purity=True).endswith("extrapolated: outside the measured magnitudes of the detections")


def test_the_covariate_check_paragraph_speaks_of_the_quantity_and_of_the_parts_it_ran(report_run, tmp_path):
    # A completeness check with both parts gives a combined p; a purity check with its depth part alone
    # gives none and speaks of purity, not completeness (the report said "completeness" and "combined" for both).
    out = tmp_path / "run"
    shutil.copytree(report_run[0], out, ignore=shutil.ignore_patterns("figures", "report.html", "again.html"))
    summary = json.loads((out / "summary.json").read_text())
    kind = next(iter(summary["kinds"]))
    part = {"chi2": 71.3, "dof": 60, "p_value": 0.151, "worst": {}}
    summary["kinds"][kind]["model"]["covariate_check"] = {"p_value": 0.302, "position": part, "depth": dict(part)}
    summary["kinds"][kind]["purity_model"] = {**summary["kinds"][kind]["model"], "covariate_check": {
        "p_value": 0.044, "position": None, "depth": {"chi2": 51.2, "dof": 31, "p_value": 0.044, "worst": {}}}}
    (out / "summary.json").write_text(json.dumps(summary))
    html = write_report(out).read_text()
    both = html.split("Covariate check (the same comparison per image tiles")[1].split("</p>")[0]
    assert "split by predicted completeness" in both and "combined p = 0.3)" in both
    assert "the completeness varies with position or depth" in both
    depth_only = html.split("Covariate check (the same comparison per depth bins")[1].split("</p>")[0]
    assert "split by predicted purity: chi2 = 51.2 for 31 groups, p = 0.044)" in depth_only
    assert "combined" not in depth_only and "the purity varies with depth in a way" in depth_only
