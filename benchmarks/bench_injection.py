"""Benchmark: injection-recovery realizations at the published scale.

Builds a source-free-like SIZE x SIZE base image (default 8192, 0.26"/px;
sky 1000 ADU plus Gaussian noise of sigma 10 ADU, a TAN WCS), a zero mask, a
constant noise map and the baseline detection catalog of the bare image, all
as files in a temporary directory, exactly as the pipeline hands them to its
workers (:class:`comest_bayes.recover.realization.SimContext`).  It then runs NSIMS
realizations per source kind -- 15 injections per arcmin^2 (about 19,000 per
realization at 8192 px), magnitudes 20-26, Moffat PSF of FWHM 3.5 px, photon
noise with a gain of 4 e-/ADU, SEP re-detection with the default detection
settings, one-to-one matching, each result written to disk as the pipeline
does -- through :func:`comest_bayes.pipeline.executors.run_tasks`, once per worker
count (1 and 2 by default), each in a fresh Python process.

Measured per run: wall time per realization (total wall time / NSIMS, pool
start-up included), the per-realization breakdown from
``RealizationResult.seconds`` (make / render / detect / match, plus writing
in the main process), injections per CPU-second (drawn injections over the
CPU time of the realizations), and peak resident memory: of the main process,
and of every worker after each of its realizations (each worker reports its
own ``ru_maxrss``; with the ``forkserver`` start method the workers are not
children of the main process, so ``RUSAGE_CHILDREN`` there does not see
them).  The per-realization peaks show whether memory grows with the number
of realizations.  The load average is recorded at the start and end of every
run, since the machine may be shared.

Usage::

    python benchmarks/bench_injection.py [--size 8192] [--nsims 10] [--kinds buldisk[,point]]
        [--workers 1 2] [--quick] [--profile] [--wait-load 1.0] [--out benchmarks/results/injection.json]

``--quick`` is a smoke run (1024 px, 2 realizations) that writes to a
scratch file unless ``--out`` is given.  ``--profile`` also runs one
realization under cProfile in a fresh process and prints where the time goes.
``--wait-load`` waits before each run until the machine is quiet.  Prints a
table and writes the numbers as JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

# Measure this checkout's package, not an installed copy (workers inherit sys.path from this process).
_REPO = str(Path(__file__).resolve().parents[1])
if _REPO not in sys.path:
    sys.path.insert(0, _REPO)

import comest_bayes  # noqa: E402
from comest_bayes.recover.realization import RealizationTask, run_realization  # noqa: E402

PIXEL_SCALE = 0.26  # arcsec / px
SKY = 1000.0  # ADU
SIGMA = 10.0  # ADU, per-pixel noise
# 5-sigma point-source depth with an optimal aperture: 5 sigma sqrt(4 pi s^2), s = FWHM / 2.355,
# gives ~264 ADU at FWHM 3.5 px; with this zero point m5 ~ 24.95, so 20-26 mag spans m5 - 5 to m5 + 1.
ZEROPOINT = 31.0
GAIN = 4.0  # e- / ADU, so the injections get photon noise as in a real run
FWHM_PIX = 3.5
DENSITY = 15.0  # per arcmin^2
MAG_RANGE = (20.0, 26.0)
ROOT_SEED = 2016


def _rss_now_mb() -> float:
    """Current resident set size of this process (VmRSS), MB."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float("nan")


def _maxrss_mb(who=resource.RUSAGE_SELF) -> float:
    return resource.getrusage(who).ru_maxrss / 1024.0  # Linux: kB


def _wcs_header(size: int) -> str:
    from astropy.wcs import WCS

    w = WCS(naxis=2)
    w.wcs.ctype = ["RA---TAN", "DEC--TAN"]
    w.wcs.crpix = [size / 2.0 + 0.5, size / 2.0 + 0.5]
    w.wcs.crval = [150.0, 2.2]
    w.wcs.cdelt = [-PIXEL_SCALE / 3600.0, PIXEL_SCALE / 3600.0]
    return w.to_header().tostring()


def make_context(tmp: str, size: int, kinds: tuple, nsims: int):
    """The SimContext of the benchmark (files under ``tmp``, written by :func:`_setup`)."""
    from comest_bayes.config import DetectionConfig, InjectionConfig, MatchingConfig
    from comest_bayes.recover.realization import SimContext

    tmp = Path(tmp)
    inj = InjectionConfig(kinds=tuple(kinds), nsims=nsims, density=DENSITY, mag_range=MAG_RANGE)
    return SimContext(
        base_path=str(tmp / "base.fits"), mask_path=str(tmp / "mask.fits"), noise_path=str(tmp / "noise.fits"),
        baseline_path=str(tmp / "baseline.fits"), detection_path=str(tmp / "baseline.fits"),
        shape=(size, size), wcs_header=_wcs_header(size), zeropoint=ZEROPOINT, gain=GAIN, saturation=None,
        pixel_scale=PIXEL_SCALE, fwhm=FWHM_PIX, mag_range=MAG_RANGE, noise_mode="background",
        detection=DetectionConfig(), injection=inj, matching=MatchingConfig(), root_seed=ROOT_SEED)


def _setup(tmp: str, size: int, out_json: str) -> None:
    """Fresh process: write the base image, mask, noise map and baseline catalog."""
    from astropy.io import fits

    from comest_bayes.detect.sep_backend import detect_array

    t0 = time.perf_counter()
    rng = np.random.default_rng(1)
    base = rng.standard_normal((size, size), dtype=np.float32)
    base *= np.float32(SIGMA)
    base += np.float32(SKY)
    t_make = time.perf_counter() - t0
    tmp = Path(tmp)
    fits.PrimaryHDU(base).writeto(tmp / "base.fits", overwrite=True)
    fits.PrimaryHDU(np.zeros((size, size), np.uint8)).writeto(tmp / "mask.fits", overwrite=True)
    fits.PrimaryHDU(np.full((size, size), SIGMA, np.float32)).writeto(tmp / "noise.fits", overwrite=True)
    ctx = make_context(str(tmp), size, ("buldisk",), 1)
    t1 = time.perf_counter()
    det = detect_array(base, mask=np.zeros(base.shape, bool), zeropoint=ZEROPOINT, gain=GAIN, wcs=ctx.wcs,
                       config=ctx.detection)
    t_det = time.perf_counter() - t1
    det.catalog.write(tmp / "baseline.fits", overwrite=True)
    Path(out_json).write_text(json.dumps({
        "image_seconds": round(t_make, 2), "baseline_detect_seconds": round(t_det, 2),
        "baseline_detections": len(det.catalog), "noise_mode": det.meta.get("noisemod"),
    }))


def timed_realization(task: RealizationTask):
    """run_realization plus this worker's CPU time and memory, attached as ``result.bench``."""
    t0 = time.perf_counter()
    c0 = time.process_time()
    s0 = resource.getrusage(resource.RUSAGE_SELF).ru_stime
    result = run_realization(task)
    result.bench = {
        "pid": os.getpid(), "wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0,
        "sys_s": resource.getrusage(resource.RUSAGE_SELF).ru_stime - s0,
        "maxrss_mb": _maxrss_mb(), "rss_end_mb": _rss_now_mb(), "package": os.path.dirname(comest_bayes.__file__),
    }
    return result


def _run(tmp: str, size: int, kind: str, nsims: int, workers: int, out_json: str) -> None:
    """Fresh process: NSIMS realizations of one kind on ``workers`` processes."""
    from comest_bayes.pipeline.executors import run_tasks
    from comest_bayes.inject.render import FLAG_DRAW_ERROR
    from comest_bayes.recover.realization import write_realization

    load_start = os.getloadavg()
    ctx = make_context(tmp, size, (kind,), nsims)
    tasks = [RealizationTask(ctx, kind, i) for i in range(nsims)]
    sims = Path(tmp) / f"sims_w{workers}"
    rows = []

    packages = set()  # where each worker imported comest_bayes from: must be this checkout

    def on_result(task, result):
        if result.error is not None:
            raise RuntimeError(f"realization {task.index} failed:\n{result.error}")
        packages.add(result.bench["package"])
        tw = time.perf_counter()
        write_realization(result, sims)
        flag = np.asarray(result.truth["flag"])
        drawn = int(((flag & FLAG_DRAW_ERROR) == 0).sum())  # positions are inside the image: none wholly off
        rows.append({
            "index": task.index, "pid": result.bench["pid"], "finished_s": round(time.perf_counter() - t0, 2),
            "n_injected": len(result.truth), "n_drawn": drawn,
            "n_detected": int(np.asarray(result.truth["detected"]).sum()), "n_detections": len(result.detections),
            **{k: round(v, 3) for k, v in result.seconds.items()}, "write": round(time.perf_counter() - tw, 3),
            "task_wall": round(result.bench["wall_s"], 3), "task_cpu": round(result.bench["cpu_s"], 3),
            "task_sys": round(result.bench["sys_s"], 3),
            "worker_maxrss_mb": round(result.bench["maxrss_mb"], 1),
            "worker_rss_end_mb": round(result.bench["rss_end_mb"], 1),
            "main_rss_mb": round(_rss_now_mb(), 1), "load1": round(os.getloadavg()[0], 2),
        })

    t0 = time.perf_counter()
    c0 = time.process_time()
    run_tasks(timed_realization, tasks, on_result=on_result, executor="processes", workers=workers)
    wall = time.perf_counter() - t0
    main_cpu = time.process_time() - c0
    load_end = os.getloadavg()
    Path(out_json).write_text(json.dumps({
        "kind": kind, "workers": workers, "nsims": nsims, "wall_s": wall, "main_cpu_s": main_cpu,
        "main_maxrss_mb": _maxrss_mb(), "children_maxrss_mb": _maxrss_mb(resource.RUSAGE_CHILDREN),
        "load_start": load_start, "load_end": load_end, "tasks": rows, "worker_packages": sorted(packages),
    }))


def _profile(tmp: str, size: int, kind: str, out_txt: str) -> None:
    """Fresh process: one realization under cProfile (serially), stats written as text."""
    import cProfile
    import io
    import pstats

    import importlib

    from comest_bayes.recover.realization import _arrays

    for name in ("comest_bayes.detect.sep_backend", "comest_bayes.inject.render"):
        importlib.import_module(name)  # imports are not what we profile

    ctx = make_context(tmp, size, (kind,), 1)
    _arrays(ctx.base_path, ctx.mask_path, ctx.noise_path)  # nor is reading the files
    prof = cProfile.Profile()
    t0 = time.perf_counter()
    prof.enable()
    result = run_realization(RealizationTask(ctx, kind, 0))
    prof.disable()
    wall = time.perf_counter() - t0
    if result.error:
        raise RuntimeError(result.error)
    buf = io.StringIO()
    buf.write(f"one {kind} realization, {len(result.truth)} injections, {wall:.2f} s under cProfile; "
              f"stages: {', '.join(f'{k} {v:.2f} s' for k, v in result.seconds.items())}\n")
    stats = pstats.Stats(prof, stream=buf)
    stats.sort_stats("tottime").print_stats(30)
    stats.sort_stats("cumulative").print_stats(40)
    Path(out_txt).write_text(buf.getvalue())


def summarize(run: dict) -> dict:
    """Per-run figures from the per-realization rows."""
    rows = sorted(run["tasks"], key=lambda r: r["finished_s"])
    n = len(rows)
    stages = ("make", "render", "detect", "match", "write")
    mean = {s: round(float(np.mean([r[s] for r in rows])), 3) for s in stages}
    task_cpu = float(sum(r["task_cpu"] for r in rows))
    task_wall = float(sum(r["task_wall"] for r in rows))
    drawn = int(sum(r["n_drawn"] for r in rows))
    # memory growth: each worker's high-water mark after its first and after its last realization
    per_worker = {}
    for r in rows:
        per_worker.setdefault(r["pid"], []).append(r["worker_maxrss_mb"])
    workers_mem = [{"realizations": len(v), "maxrss_after_first_mb": v[0], "maxrss_after_last_mb": v[-1],
                    "maxrss_sequence_mb": v} for v in per_worker.values()]
    peak_after_2 = max(r["worker_maxrss_mb"] for r in rows[:2])
    peak_after_all = max(r["worker_maxrss_mb"] for r in rows)
    worker_peak_sum = sum(max(v) for v in per_worker.values())
    main_peak = run["main_maxrss_mb"]
    total_peak = main_peak if run["workers"] <= 1 else main_peak + worker_peak_sum
    return {
        "kind": run["kind"], "workers": run["workers"], "nsims": n,
        "wall_s": round(run["wall_s"], 2), "wall_per_realization_s": round(run["wall_s"] / n, 2),
        "task_wall_mean_s": round(task_wall / n, 2), "task_cpu_mean_s": round(task_cpu / n, 2),
        # kernel part of the CPU time (page faults into fresh full-size arrays, mostly)
        "task_sys_mean_s": round(float(np.mean([r["task_sys"] for r in rows])), 2),
        # CPU time / wall time of the realizations: below 1 when other processes took the cores
        "task_cpu_share": round(task_cpu / task_wall, 3),
        "mean_seconds": mean,
        "render_fraction_of_task": round(mean["render"] / (task_wall / n), 3),
        "injections_per_realization": round(float(np.mean([r["n_injected"] for r in rows])), 1),
        "drawn_total": drawn,
        "injections_per_cpu_s": round(drawn / task_cpu, 1),
        "injections_per_wall_s": round(drawn / run["wall_s"], 1),
        "detected_fraction": round(sum(r["n_detected"] for r in rows) / max(1, sum(r["n_injected"] for r in rows)), 4),
        "main_peak_rss_mb": round(main_peak, 1), "main_cpu_s": round(run["main_cpu_s"], 2),
        "children_maxrss_mb_seen_by_main": round(run["children_maxrss_mb"], 1),
        "worker_peak_rss_after_2_realizations_mb": peak_after_2,
        "worker_peak_rss_after_all_realizations_mb": peak_after_all,
        "workers_memory": workers_mem,
        "total_peak_rss_mb": round(total_peak, 1),
        # the main process's RSS after handing each result to on_result: flat unless results are retained
        "main_rss_during_run_mb": [r["main_rss_mb"] for r in rows],
        "main_rss_growth_mb": round(rows[-1]["main_rss_mb"] - rows[0]["main_rss_mb"], 1),
        "load_start": [round(v, 2) for v in run["load_start"]],
        "load_end": [round(v, 2) for v in run["load_end"]],
        "worker_packages": run.get("worker_packages", []),
        "realizations": rows,
    }


def _wait_for_quiet(limit: float | None, max_wait: float) -> None:
    """Wait (at most ``max_wait`` s) until the 1-minute load average is below ``limit``."""
    if limit is None:
        return
    t0 = time.monotonic()
    while os.getloadavg()[0] >= limit and time.monotonic() - t0 < max_wait:
        time.sleep(15)
    load = os.getloadavg()[0]
    if load >= limit:
        print(f"  load {load:.2f} still >= {limit} after {max_wait:.0f} s: running anyway")


def _child(args: list[str]) -> None:
    subprocess.run([sys.executable, __file__, *args], check=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=None, help="image side in pixels (default 8192; 1024 with --quick)")
    ap.add_argument("--nsims", type=int, default=None, help="realizations per kind (default 10; 2 with --quick)")
    ap.add_argument("--kinds", default="buldisk", help="comma-separated source kinds, e.g. buldisk,point")
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2], help="worker counts to run (default 1 2)")
    ap.add_argument("--quick", action="store_true", help="smoke run: 1024 px, 2 realizations")
    ap.add_argument("--profile", action="store_true", help="also profile one realization with cProfile")
    ap.add_argument("--wait-load", type=float, default=None, metavar="LOAD",
                    help="before each run wait until the 1-minute load average is below LOAD (shared machines)")
    ap.add_argument("--wait-max", type=float, default=1800.0, metavar="S", help="longest wait per run (s)")
    ap.add_argument("--out", default=None, help="JSON output (default benchmarks/results/injection.json)")
    ap.add_argument("--child-setup", nargs=3, metavar=("TMP", "SIZE", "JSON"), help=argparse.SUPPRESS)
    ap.add_argument("--child-run", nargs=6, metavar=("TMP", "SIZE", "KIND", "NSIMS", "WORKERS", "JSON"),
                    help=argparse.SUPPRESS)
    ap.add_argument("--child-profile", nargs=4, metavar=("TMP", "SIZE", "KIND", "TXT"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child_setup:
        tmp, size, out = args.child_setup
        _setup(tmp, int(size), out)
        return 0
    if args.child_run:
        tmp, size, kind, nsims, workers, out = args.child_run
        _run(tmp, int(size), kind, int(nsims), int(workers), out)
        return 0
    if args.child_profile:
        tmp, size, kind, out = args.child_profile
        _profile(tmp, int(size), kind, out)
        return 0

    size = args.size or (1024 if args.quick else 8192)
    nsims = args.nsims or (2 if args.quick else 10)
    kinds = [k.strip() for k in args.kinds.split(",") if k.strip()]
    default_out = Path(tempfile.gettempdir()) / "injection_quick.json" if args.quick else \
        Path(__file__).parent / "results" / "injection.json"
    out_path = Path(args.out) if args.out else default_out
    area = (size * PIXEL_SCALE / 60.0) ** 2
    print(f"{size}x{size} px at {PIXEL_SCALE}\"/px = {area:.0f} arcmin^2; {DENSITY:g}/arcmin^2 -> "
          f"~{DENSITY * area:.0f} injections per realization; {nsims} realizations; kinds {kinds}; "
          f"workers {args.workers}")
    load_start = os.getloadavg()
    runs, profiles = [], {}
    with tempfile.TemporaryDirectory(prefix="bench_injection_") as tmp:
        setup_json = os.path.join(tmp, "setup.json")
        _child(["--child-setup", tmp, str(size), setup_json])
        setup_info = json.loads(Path(setup_json).read_text())
        print(f"setup: image {setup_info['image_seconds']} s, baseline detection "
              f"{setup_info['baseline_detect_seconds']} s ({setup_info['baseline_detections']} detections)")
        for kind in kinds:
            for workers in args.workers:
                out_json = os.path.join(tmp, f"run_{kind}_{workers}.json")
                _wait_for_quiet(args.wait_load, args.wait_max)
                _child(["--child-run", tmp, str(size), kind, str(nsims), str(workers), out_json])
                run = summarize(json.loads(Path(out_json).read_text()))
                runs.append(run)
                print(f"  {kind} on {workers} worker(s): {run['wall_per_realization_s']} s per realization, "
                      f"load {run['load_start'][0]} -> {run['load_end'][0]}")
            if args.profile:
                txt = os.path.join(tmp, f"profile_{kind}.txt")
                _wait_for_quiet(args.wait_load, args.wait_max)
                _child(["--child-profile", tmp, str(size), kind, txt])
                profiles[kind] = Path(txt).read_text()
    load_end = os.getloadavg()

    import galsim
    import sep

    info = {
        "benchmark": "injection", "size": size, "pixel_scale": PIXEL_SCALE, "area_arcmin2": round(area, 1),
        "density_per_arcmin2": DENSITY, "mag_range": MAG_RANGE, "fwhm_pix": FWHM_PIX, "psf": "moffat beta 3",
        "zeropoint": ZEROPOINT, "gain": GAIN, "photon_noise": True, "sky_adu": SKY, "sigma_adu": SIGMA,
        "nsims": nsims, "kinds": kinds, "workers": args.workers, "cores": os.cpu_count(),
        "executor": "processes (forkserver)", "python": platform.python_version(), "numpy": np.__version__,
        "galsim": galsim.__version__, "sep": sep.__version__, "machine": platform.machine(),
        "package": os.path.dirname(comest_bayes.__file__),
        "load_start": [round(v, 2) for v in load_start], "load_end": [round(v, 2) for v in load_end],
        "wait_load": args.wait_load, "setup": setup_info,
        "profile_headlines": {k: v.splitlines()[0] for k, v in profiles.items()}, "runs": runs,
    }
    out_path.parent.mkdir(parents=True, exist_ok=True)
    out_path.write_text(json.dumps(info, indent=2) + "\n")

    print()
    head = (f"{'kind':<8} {'wrk':>3} {'s/real':>7} {'CPU s':>6} {'make':>6} {'render':>7} {'detect':>7} "
            f"{'match':>6} {'write':>6} {'inj/real':>9} {'inj/CPU-s':>10} {'worker MB 2->N':>15} "
            f"{'main MB 1st->Nth':>17} {'total MB':>9} {'load':>11}")
    print(head)
    for r in runs:
        m = r["mean_seconds"]
        worker_mb = f"{r['worker_peak_rss_after_2_realizations_mb']:.0f}->{r['worker_peak_rss_after_all_realizations_mb']:.0f}"
        main_mb = f"{r['main_rss_during_run_mb'][0]:.0f}->{r['main_rss_during_run_mb'][-1]:.0f}"
        load = f"{r['load_start'][0]:.1f}->{r['load_end'][0]:.1f}"
        print(f"{r['kind']:<8} {r['workers']:>3} {r['wall_per_realization_s']:>7} {r['task_cpu_mean_s']:>6} "
              f"{m['make']:>6} {m['render']:>7} {m['detect']:>7} {m['match']:>6} {m['write']:>6} "
              f"{r['injections_per_realization']:>9} {r['injections_per_cpu_s']:>10} {worker_mb:>15} "
              f"{main_mb:>17} {r['total_peak_rss_mb']:>9} {load:>11}")
    print("(s/real: total wall / N; CPU s, make..match: mean per realization inside a worker; write: in the main "
          "process; worker MB: peak RSS after 2 and after N realizations; main MB: RSS after the 1st and Nth "
          "result; total MB: main + workers' peaks)")
    for kind, text in profiles.items():
        print(f"\n---- cProfile, {kind} ----\n{text}")
    used = sorted({p for r in runs for p in r["worker_packages"]})
    print(f"workers imported comest_bayes from {used}" + ("" if used == [info["package"]] else
                                                          f" -- NOT only this checkout's {info['package']}"))
    print(f"written {out_path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
