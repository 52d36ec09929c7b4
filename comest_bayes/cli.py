"""The ``comest-bayes`` command line: ``run``, ``demo``, ``report``, ``lf``, ``info`` and ``fit``.

User mistakes are one ``error:`` line and exit status 2, operating-system failures exit status 1;
``--debug`` shows the traceback.  The commands and their options: ``docs/usage.md``.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
import time
import warnings
from pathlib import Path

from comest_bayes import __version__
from comest_bayes.pipeline import runtime
from comest_bayes.errors import ComestError
from comest_bayes.lf import MODES, SAMPLERS
from comest_bayes.io.jsonio import dumps
from comest_bayes.io import layout

__all__ = ["main", "build_parser"]

#: Options of ``comest-bayes lf DIR ...`` (argparse-style: flag -> keyword of
#: :func:`comest_bayes.lf.fit.run_lf`).
LF_OPTIONS = {
    "--kind": {"dest": "kind", "default": "point", "help": "source kind whose completeness is used (a kind of "
                                                            "the run, e.g. point or buldisk)"},
    "--model": {"dest": "model", "default": "powerlaw", "help": "count model: powerlaw, schechter, "
                                                                "double_powerlaw or the path of a TOML spec"},
    "--mag-range": {"dest": "mag_range", "nargs": 2, "type": float, "default": None, "metavar": ("LO", "HI"),
                    "help": "measured-magnitude range fitted (default: the run's injected range, faint end "
                            "cut where the completeness falls below 10%%)"},
    "--mode": {"dest": "mode", "choices": list(MODES), "default": "joint",
               "help": "completeness uncertainty: joint (sampled with the counts), marginal (pooled over "
                       "completeness draws) or fixed (posterior median; too-narrow intervals)"},
    "--catalog": {"dest": "catalog", "default": None, "help": "FITS table of sources (default: the run's "
                                                              f"{layout.DETECTION})"},
    "--mag-column": {"dest": "mag_column", "default": "mag_auto", "help": "magnitude column of the catalog"},
    "--seed": {"dest": "seed", "type": int, "default": None,
               "help": "root seed of the sampler (default: the run's own root seed)"},
    "--sampler": {"dest": "sampler", "choices": list(SAMPLERS), "default": "auto",
                  "help": "posterior sampler: auto (importance sampling of the Laplace approximation, emcee when "
                          "its k-hat or ESS fails), or emcee (the reference; slow in joint mode)"},
    "--name": {"dest": "name", "default": None, "help": "output name under DIR/lf/ (default kind_model_mode)"},
}


def _add_config_options(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("configuration")
    g.add_argument("--config", metavar="TOML", help="TOML file with [detection] and [sourcefree] tables")
    g.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="override one setting, e.g. --set detection.thresh=2.0 (repeatable)")
    g.add_argument("--seed", type=int, default=None, help="root seed of every random draw (default 0)")
    g.add_argument("--backend", choices=("sep", "sextractor"), default=None,
                   help="detector: SEP (default) or the SExtractor binary")
    g.add_argument("--thresh", type=float, default=None, help="detection threshold in sigma (DETECT_THRESH, 1.5)")
    g.add_argument("--minarea", type=int, default=None, help="minimum area in pixels (DETECT_MINAREA, 5)")
    g.add_argument("--no-bnb", action="store_true", help="do not make the bright-and-big image")
    g.add_argument("--kinds", default=None,
                   help="source kinds to inject, comma-separated: point, buldisk, sersic, cosmos, observed "
                        "(default point,buldisk)")
    g.add_argument("--nsims", type=int, default=None, help="realizations per kind (default 10)")
    g.add_argument("--density", type=float, default=None, help="injections per arcmin^2 (default 0: automatic, from the image; "
                        "15 where that gives at least 100 per realization)")
    g.add_argument("--precision", type=float, default=None, metavar="MAG",
                   help="adaptive injection: add batches of realizations, their magnitudes where the posterior is "
                        "most uncertain, until the 68%% half-width of every kind's m50 is at most MAG "
                        "(e.g. 0.02; docs/adaptive.md); --nsims is then not used")
    g.add_argument("--precision-at", default=None, metavar="MAGS",
                   help="adaptive injection aimed at f at these comma-separated magnitudes (e.g. 23.5,24.0): "
                        "--precision is then the posterior sd of the image-average f there (e.g. 0.02)")
    g.add_argument("--max-nsims", type=int, default=None,
                   help="adaptive injection: most realizations per kind (default 40)")
    g.add_argument("--model", default=None,
                   help="completeness model: a name from models/ (logistic, logistic_depth, ...), a TOML path, "
                        "'auto' (default: select the simplest the scene supports) or 'none'")
    c = p.add_argument_group("compute (results do not depend on these)")
    c.add_argument("--ncpu", type=int, default=None, help="worker processes (default: all cores)")
    c.add_argument("--executor", choices=("processes", "serial", "dask"), default="processes",
                   help="where realizations run (default local processes)")
    c.add_argument("--scheduler", default=None,
                   help="Dask scheduler address, e.g. tcp://host:8786 (implies --executor dask); "
                        "--executor dask without it starts a local cluster")
    o = p.add_argument_group("output")
    o.add_argument("--no-report", action="store_true",
                   help=f"do not write {layout.REPORT} at the end (write it later with: comest-bayes report DIR)")
    _add_output_options(o)


def _add_output_options(group) -> None:
    group.add_argument("--quiet", action="store_true", help="print only errors")
    group.add_argument("--debug", action="store_true", help="show tracebacks of errors")


def _write_line(line: str, file) -> None:
    """Print one line; while a progress bar is on screen, above it (a plain print would cut through it)."""
    from tqdm.auto import tqdm

    if getattr(tqdm, "_instances", None):
        tqdm.write(line, file=file)
        file.flush()
    else:
        print(line, file=file, flush=True)


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """``warnings.showwarning`` for a terminal: one ``warning:`` line that keeps the progress bars whole."""
    _write_line(f"warning: {message}", file or sys.stderr)


def _progress_enabled(args) -> bool:
    """Progress bars only for a person watching: not with --quiet, not into a file or pipe."""
    return not getattr(args, "quiet", False) and sys.stderr.isatty()


def _center(text: str) -> tuple[float, float]:
    try:
        x, y = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X,Y in pixels (e.g. 1500,800), got {text!r}") from None
    return x, y


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="comest-bayes",
        description="Completeness and purity of source detection on an astronomical image, by "
                    "injection and recovery (ComEst method) with Bayesian uncertainties.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    run = sub.add_parser("run", help="run every stage on an image",
                         description="Detect sources, build the source-free image and continue through "
                                     "every stage, writing all outputs under --out.")
    run.add_argument("image", help="FITS image")
    run.add_argument("--out", required=True, help="run directory (new, empty, or a run to resume)")
    img = run.add_argument_group("image facts")
    img.add_argument("--hdu", type=int, default=None, help="HDU of the image (default: first 2-D image)")
    img.add_argument("--zp", type=float, default=None,
                     help="zero point: magnitude of one image unit (default: header MAGZERO, MAGZPT, ...)")
    img.add_argument("--pixel-scale", type=float, default=None,
                     help="arcsec per pixel (default: from the WCS; required without one)")
    img.add_argument("--fwhm", type=float, default=None,
                     help="seeing FWHM in pixels (default: estimated from stars on the image)")
    img.add_argument("--gain", type=float, default=None, help="e-/image unit (default: header GAIN)")
    img.add_argument("--saturation", type=float, default=None, help="saturation level (default: header SATURATE)")
    img.add_argument("--weight", default=None, help="weight map FITS of the same shape")
    img.add_argument("--weight-type", choices=("ivar", "rms", "var"), default=None,
                     help="what the weight map holds (default ivar = inverse variance)")
    img.add_argument("--weight-hdu", type=int, default=None,
                     help="HDU of the weight map (default: first 2-D image)")
    img.add_argument("--mask", default=None, help="mask FITS of the same shape (non-zero = bad)")
    img.add_argument("--mask-hdu", type=int, default=None,
                     help="HDU of the mask (default: first 2-D image)")
    img.add_argument("--mask-bits", type=int, default=None, help="only these bits of the mask mark bad pixels")
    _add_config_options(run)

    demo = sub.add_parser("demo", help="synthesize the built-in demo tile and run every stage on it",
                          description="Make a realistic synthetic survey tile with GalSim (TAN WCS, zero point, "
                                      "gain, galaxies, stars incl. saturated ones, a weight map with a depth "
                                      "gradient and a chip gap) and run the whole pipeline on it.")
    demo.add_argument("--out", default="comest-demo", help="run directory (default ./comest-demo)")
    demo.add_argument("--size", type=int, default=3000, help="tile size in pixels (default 3000)")
    _add_config_options(demo)

    rep = sub.add_parser("report", help="write the self-contained HTML report of a run",
                         description="Read a run directory and write one HTML file with every figure embedded "
                                     "(also saved as PNG and PDF under DIR/figures/), the tables, the configuration, "
                                     "the input facts and the stage timings. It needs no network to view.")
    rep.add_argument("dir", help="run directory (the --out of comest-bayes run or demo)")
    rep.add_argument("--out", default=None, help=f"HTML file to write (default DIR/{layout.REPORT})")
    rep.add_argument("--center", type=_center, default=None, metavar="X,Y",
                     help="centre of the image cutouts, 0-based pixels (default the image centre)")
    rep.add_argument("--size", type=int, default=400, help="side of the image cutouts in pixels (default 400)")
    _add_output_options(rep.add_argument_group("output"))

    lf = sub.add_parser("lf", help="fit number counts through the measured completeness and photometric transfer",
                        description="Fit a count model (power law, Schechter, double power law, or a TOML spec) to the "
                                    "run's detection catalog or a user catalog with an extended Poisson likelihood, "
                                    "forward-modelling the completeness posterior and the magnitude transfer of the "
                                    "injections; the completeness uncertainty is sampled jointly, marginalized over "
                                    "posterior draws, or held fixed (for comparison). The run's report is rewritten "
                                    "with the LF section unless --no-report.")
    lf.add_argument("dir", help="run directory with a completeness posterior (comest-bayes run or demo)")
    for flag, kw in LF_OPTIONS.items():
        lf.add_argument(flag, **kw)
    lf.add_argument("--no-report", action="store_true", help=f"do not rewrite {layout.REPORT}")
    _add_output_options(lf.add_argument_group("output"))

    info = sub.add_parser("info", help="show what a run holds: inputs, stages done, m50 with intervals, model, "
                                       "warnings, files",
                          description=f"Print a run directory's facts from its {layout.RUN} and {layout.SUMMARY} alone, without "
                                      "recomputing or writing anything: the input and where its zero point, pixel scale "
                                      "and seeing came from, the stages done and their times, per source kind the "
                                      "binned and the model 50%% completeness magnitude with 68%% and 95%% intervals, "
                                      "the chosen model, the warnings and the files. Works on a partial run too.")
    info.add_argument("dir", help="run directory (the --out of comest-bayes run or demo)")
    info.add_argument("--json", action="store_true", help="print the facts as JSON instead of text")
    _add_output_options(info.add_argument_group("output"))

    fit = sub.add_parser("fit", help="fit the completeness model to an outcome table from any injection pipeline",
                         description="Run the model selection and posterior of comest-bayes on a table of injection "
                                     "outcomes made elsewhere (Balrog, LSST source_injection, an earlier run): one row "
                                     "per injection with its true magnitude and whether it was detected, optionally "
                                     "its pixel position and the local detection noise. Writes the posterior, "
                                     f"{layout.SUMMARY} and a figure to --out.")
    fit.add_argument("outcomes", help="outcome table (FITS, or any format astropy reads)")
    fit.add_argument("--out", required=True, help="output folder (new or empty)")
    fit.add_argument("--kind", default="injections", help="label of the injected population (default injections)")
    fit.add_argument("--model", default="auto", help="model spec name or TOML path, or auto (default)")
    for name, default in (("mag", "mag"), ("detected", "detected"), ("x", "x"), ("y", "y"), ("noise", "noise")):
        fit.add_argument(f"--{name}-column", default=None, metavar="NAME",
                         help=f"column of the {name} (default {default}"
                              + (")" if name in ("mag", "detected") else "; optional, but a name you give must exist)"))
    fit.add_argument("--noise-map", default=None, metavar="FITS",
                     help="detection noise map of the image: the image average then covers every unmasked pixel")
    fit.add_argument("--mask", default=None, metavar="FITS", help="bad-pixel mask of the image (non-zero = bad)")
    fit.add_argument("--image-shape", default=None, metavar="NY,NX",
                     help="image shape in pixels, when the table has positions but no map is given")
    fit.add_argument("--seed", type=int, default=0, help="root seed of the fit (default 0)")
    _add_output_options(fit.add_argument_group("output"))
    return parser


def _config_from_args(args):
    """The run's configuration: one path for the command line and comest_bayes.run (api.config_from_options)."""
    from comest_bayes.api import SHORTCUTS, config_from_options

    return config_from_options(config=args.config, overrides=args.overrides, seed=args.seed, no_bnb=args.no_bnb,
                               precision_at=getattr(args, "precision_at", None),
                               **{option: getattr(args, option) for option in SHORTCUTS})


def _compute_from_args(args):
    from comest_bayes.api import compute_from_options

    return compute_from_options(ncpu=args.ncpu, executor=args.executor, scheduler=args.scheduler,
                                progress=_progress_enabled(args))


def _bin_width(kind_summary: dict) -> str:
    """The bin width of a ``comest-bayes fit`` summary's binned completeness, for its log line."""
    edges = kind_summary["completeness"]["edges"]
    return f"{edges[1] - edges[0]:.1f}"


def _cmd_fit(args, log) -> int:
    from comest_bayes.pipeline.fits import fit_outcome_file

    shape = None
    if args.image_shape:
        try:
            shape = tuple(int(v) for v in args.image_shape.split(","))
            assert len(shape) == 2 and min(shape) >= 2
        except (ValueError, AssertionError):
            raise ComestError(f"--image-shape must be NY,NX (two integers >= 2), got {args.image_shape!r}.") from None
    columns = {name: getattr(args, f"{name}_column") for name in ("mag", "detected", "x", "y", "noise")}
    summary = fit_outcome_file(args.outcomes, args.out, kind=args.kind, model=args.model, columns=columns,
                               noise_map=args.noise_map, mask=args.mask, image_shape=shape, seed=args.seed, log=log)
    kind_summary = summary["kinds"][args.kind]
    entry = kind_summary["model"]
    m50 = entry.get("m50") or {}
    if kind_summary.get("m50_binned") is not None:
        sd = kind_summary.get("m50_binned_sd")
        log(f"{args.kind}: binned ({_bin_width(kind_summary)}-mag bins): m50 = {kind_summary['m50_binned']:.3f}"
            + (f" +- {sd:.3f}" if sd is not None else ""))
    if m50.get("median") is not None:
        log(f"{args.kind}: {entry['name']}: m50 = {m50['median']:.3f} [68%: {m50['lo68']:.3f}, {m50['hi68']:.3f}]"
            + (" (extrapolated)" if m50.get("extrapolated") else ""))
    log(f"wrote {args.out}/{layout.SUMMARY}, {layout.posterior(args.kind)}, {layout.FIGURES_DIR}/{args.kind}_completeness.png")
    return 0


def _cmd_run(args, log) -> int:
    from comest_bayes.api import image_options_from
    from comest_bayes.pipeline.stages import run_pipeline

    config = _config_from_args(args)
    options = image_options_from(args.image, hdu=args.hdu, zp=args.zp, pixel_scale=args.pixel_scale, fwhm=args.fwhm,
                                 gain=args.gain, saturation=args.saturation, weight=args.weight,
                                 weight_type=args.weight_type, weight_hdu=args.weight_hdu, mask=args.mask,
                                 mask_hdu=args.mask_hdu, mask_bits=args.mask_bits)
    result = run_pipeline(options, config, args.out, log=log, compute=_compute_from_args(args))
    _final_summary(result, log, _report_after_run(result.out_dir, args, log))
    return 0


def _report_after_run(out_dir, args, log):
    """Write the report at the end of run/demo; its failure does not fail the finished run."""
    if args.no_report:
        return None
    from comest_bayes.report.html import write_report

    try:
        return write_report(out_dir, log=log)
    except Exception as exc:
        if args.debug:
            raise
        log(f"warning: the report could not be written ({type(exc).__name__}: {exc}); the run's outputs are "
            f"complete. Retry with: comest-bayes report {out_dir} --debug")
        return None


def _final_summary(result, log, report=None) -> None:
    """A concise end-of-run summary: binned and posterior m50 per kind and where the outputs are."""
    kinds = (result.summary or {}).get("kinds", {})
    for kind, info in kinds.items():
        m50 = info.get("m50_binned")
        model = info.get("model") or {}
        fitted = (model.get("m50") or {}).get("median")
        text = (f"  {kind:<9} 50% completeness: binned {'n/a' if m50 is None else f'{m50:.2f}'} mag")
        if fitted is not None:
            text += (f"; {model['name']} posterior {fitted:.2f} "
                     f"[{model['m50']['lo68']:.2f}, {model['m50']['hi68']:.2f}] (68%)")
        nreal = info['counts']['realizations']
        log(text + f"  ({info['counts']['usable']} injections, {nreal} realization{'' if nreal == 1 else 's'})")
    log(f"done: outputs in {result.out_dir} ({layout.SUMMARY}, catalogs/, maps/)")
    if report is not None:
        log(f"report: {report}")


def _cmd_demo(args, log) -> int:
    from comest_bayes.io.rundir import RunDirectory

    config = _config_from_args(args)
    if args.size < 256:
        raise ComestError(f"--size {args.size} is too small for a meaningful demo; use at least 256.")
    out = Path(args.out)
    guard = RunDirectory(out, {})
    if not (out / layout.RUN).exists():
        guard.check()  # refuses a non-empty directory that is not a run, one in use, an unwritable place
    else:
        guard.refuse_if_in_use()
    compute = _compute_from_args(args)
    guard.acquire()  # the tile is written under the run's lock too
    try:
        return _demo_locked(args, config, out, compute, log)
    finally:
        guard.release()


def _demo_locked(args, config, out: Path, compute, log) -> int:
    from comest_bayes.sim.demo import DEMO_FILES, MASK_GAP, demo_seeing_pix, make_demo_tile, write_demo_tile
    from comest_bayes.pipeline.stages import ImageOptions, run_pipeline

    inputs = out / layout.INPUTS_DIR
    image_path = inputs / DEMO_FILES["image"]
    marker = inputs / f"demo_seed{config.seed}_size{args.size}.done"
    if not marker.exists():
        if inputs.exists() and any(inputs.glob("demo_seed*.done")):
            raise ComestError(f"{str(inputs)!r} holds a demo tile made with other --seed/--size; "
                              f"choose another --out or remove it.")
        from tqdm.auto import tqdm

        t0 = time.perf_counter()
        log(f"demo: synthesizing a {args.size}x{args.size} tile (seed {config.seed}) ...")
        with tqdm(desc="demo tile", unit="source", disable=not _progress_enabled(args), leave=False) as bar:
            def drawn(done: int, total: int) -> None:
                bar.total = total
                bar.update(done - bar.n)

            tile = make_demo_tile(seed=config.seed, size=args.size, progress=drawn)
        inputs.mkdir(parents=True, exist_ok=True)
        write_demo_tile(tile, inputs)
        marker.write_text("complete\n")
        log(f"demo: tile with {len(tile.truth)} true sources written to {inputs} in {time.perf_counter() - t0:.1f} s")
    options = ImageOptions(path=str(image_path), weight=str(inputs / DEMO_FILES["weight"]), weight_type="ivar",
                           mask=str(inputs / DEMO_FILES["mask"]), mask_bits=MASK_GAP)
    # a small tile may hold too few stars to measure the seeing; the demo knows the seeing it drew
    fallback = (demo_seeing_pix(image_path), "the demo tile's own seeing (too few stars on it to measure)")
    result = run_pipeline(options, config, out, log=log, compute=compute, fwhm_fallback=fallback)
    _final_summary(result, log, _report_after_run(result.out_dir, args, log))
    return 0


def _cmd_report(args, log) -> int:
    from comest_bayes.report.html import write_report

    if args.size < 16:
        raise ComestError(f"--size {args.size} is too small for an image cutout; use at least 16 pixels.")
    write_report(args.dir, args.out, log=log, center=args.center, size=args.size)
    return 0


def _cmd_info(args, log) -> int:
    from comest_bayes.io.info import format_info
    from comest_bayes.io.run import run_info

    info = run_info(args.dir)
    print(dumps(info, indent=2) if args.json else format_info(info))
    return 0


def _cmd_lf(args, log) -> int:
    from comest_bayes.lf.fit import run_lf

    kwargs = {kw["dest"]: getattr(args, kw["dest"]) for kw in LF_OPTIONS.values()}
    if kwargs.get("mag_range") is not None:
        kwargs["mag_range"] = tuple(kwargs["mag_range"])
    t0 = time.perf_counter()
    result = run_lf(args.dir, log=log, **kwargs)
    log(f"lf: {result.name} done in {time.perf_counter() - t0:.1f} s")
    if not args.no_report:
        from comest_bayes.report.html import write_report

        try:
            log(f"report: {write_report(args.dir, log=lambda s: None)}")
        except Exception as exc:  # the fit is saved; a report failure must not hide it
            if args.debug:
                raise
            log(f"warning: the report could not be rewritten ({type(exc).__name__}: {exc}); "
                f"retry with: comest-bayes report {args.dir} --debug")
    return 0


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    # one numerical thread per process (--ncpu sets the number of processes) and the compilation cache
    runtime.configure(threads=1)
    quiet = getattr(args, "quiet", False)

    def log(line: str) -> None:
        if not quiet:
            _write_line(line, sys.stdout)

    # Warnings (unconverged samplers, prior-dominated fits) as one readable line each.
    warnings.formatwarning = lambda message, category, *rest, **kw: f"warning: {message}\n"
    shown = warnings.showwarning
    if _progress_enabled(args):  # on a terminal with progress bars: above them, not through them
        warnings.showwarning = _show_warning
    handler = {"run": _cmd_run, "demo": _cmd_demo, "report": _cmd_report, "lf": _cmd_lf, "fit": _cmd_fit,
               "info": _cmd_info}[args.command]
    unraisable = sys.unraisablehook

    def _quiet_interrupt(info) -> None:
        # a Ctrl-C that lands in a finalizer or a garbage-collection callback (JAX has one) cannot propagate:
        # Python would print it as "Exception ignored"; the interrupt itself is reported below
        if info.exc_type is not None and issubclass(info.exc_type, KeyboardInterrupt):
            return
        unraisable(info)

    sys.unraisablehook = _quiet_interrupt
    # SIGTERM (a batch scheduler's time limit, kill): unwind as an interrupt does, so that temporary
    # files and folders (SExtractor's working folder, half-written outputs) are removed on the way out
    terminate = signal.getsignal(signal.SIGTERM)
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _terminated)
    try:
        return handler(args, log)
    except ComestError as exc:
        if args.debug:
            raise
        print(f"error: {_one_line(exc)}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # the reader of the output went away (comest-bayes info DIR | head): nothing to say
        try:
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())  # so that flushing at exit does not fail again
        except (OSError, ValueError):
            pass
        return 1
    except OSError as exc:  # the operating system refused: a full disk, an unreadable file, a vanished folder
        if args.debug:
            raise
        from comest_bayes.io.rundir import os_reason

        where = f" ({exc.filename!r})" if getattr(exc, "filename", None) else ""
        print(f"error: {os_reason(exc)}{where}. Fix this, then rerun the same command to resume.", file=sys.stderr)
        return 1
    except MemoryError:
        if args.debug:
            raise
        print("error: out of memory; lower --ncpu or --density (or use a machine with more memory), then rerun "
              "the same command to resume.", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("interrupted: rerun the same command to resume where it stopped.", file=sys.stderr)
        return 130
    except _Terminated:
        print("terminated: rerun the same command to resume where it stopped.", file=sys.stderr)
        return 143
    finally:
        warnings.showwarning = shown
        sys.unraisablehook = unraisable
        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGTERM, terminate)


class _Terminated(BaseException):
    """Raised in the main process by SIGTERM (see :func:`main`)."""


def _terminated(signum, frame):
    raise _Terminated()


def _one_line(exc: BaseException) -> str:
    """An error message on one line (a message quoting a multi-line text keeps its words)."""
    return " ".join(str(exc).split())


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
