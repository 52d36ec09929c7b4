"""Benchmark: detection + source-free image on a large image, SEP versus SExtractor.

Makes a synthetic SIZE x SIZE image (default 8192, float32, 0.26"/px sky noise,
~15 galaxies/arcmin^2-like Gaussian blobs and stars), then in a *fresh
process per backend* times the detection (background, extraction, photometry)
and the source-free image, and records the peak resident memory (of the Python
process; for SExtractor also of the binary, a child process).

Usage::

    python benchmarks/bench_detection.py [--size 8192] [--out benchmarks/results/detection.json]

Prints a table and writes the numbers as JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def make_image(size: int, seed: int = 1) -> np.ndarray:
    """Sky 1000 ADU, sigma 10, point sources and round/elliptical blobs, fast (numpy stamps)."""
    rng = np.random.default_rng(seed)
    img = rng.normal(1000.0, 10.0, (size, size)).astype(np.float32)
    area_arcmin2 = (size * 0.26 / 60.0) ** 2
    n = int(20 * area_arcmin2)
    x = rng.uniform(10, size - 10, n)
    y = rng.uniform(10, size - 10, n)
    # power-law fluxes: many faint, few bright
    flux = 10 ** rng.uniform(2.0, 5.0, n) * (rng.random(n) ** 2 + 0.05)
    sig = rng.uniform(1.3, 4.0, n)
    half = 12
    yy, xx = np.mgrid[-half:half + 1, -half:half + 1]
    for xi, yi, fi, si in zip(x, y, flux, sig):
        ix, iy = int(xi), int(yi)
        x0, x1 = max(ix - half, 0), min(ix + half + 1, size)
        y0, y1 = max(iy - half, 0), min(iy + half + 1, size)
        g = np.exp(-((xx - (xi - ix)) ** 2 + (yy - (yi - iy)) ** 2) / (2 * si * si))
        g *= fi / (2 * np.pi * si * si)
        img[y0:y1, x0:x1] += g[y0 - iy + half:y1 - iy + half, x0 - ix + half:x1 - ix + half].astype(np.float32)
    return img


def child(backend: str, path: str, out_json: str) -> None:
    """Run in a fresh process: time detection and SFI, record peak memory."""
    from comest_bayes.config import DetectionConfig, SourceFreeConfig
    from comest_bayes.detect.sep_backend import detect_array
    from comest_bayes.sourcefree import build_source_free

    data = np.load(path)
    mask = np.zeros(data.shape, bool)
    cfg = DetectionConfig(backend=backend)
    t0 = time.perf_counter()
    cpu0 = time.process_time()
    if backend == "sep":
        det = detect_array(data, mask=mask, zeropoint=30.0, config=cfg)
    else:
        from comest_bayes.detect.sextractor import detect_sextractor

        det = detect_sextractor(data, mask=mask, zeropoint=30.0, config=cfg)
    t_det = time.perf_counter() - t0
    t1 = time.perf_counter()
    sf = build_source_free(data, det, mask=mask, fwhm=3.0, config=SourceFreeConfig(bnb=False), seed=1)
    t_sfi = time.perf_counter() - t1
    self_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    child_kb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    res = {
        "backend": backend, "nsources": len(det.catalog), "detect_wall_s": round(t_det, 2),
        "sfi_wall_s": round(t_sfi, 2), "python_cpu_s": round(time.process_time() - cpu0, 2),
        "peak_rss_python_mb": round(self_kb / 1024, 1), "peak_rss_binary_mb": round(child_kb / 1024, 1),
        "replaced_fraction": round(float(sf.removed.mean()), 4),
    }
    Path(out_json).write_text(json.dumps(res))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=8192)
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "detection.json"))
    ap.add_argument("--child", nargs=3, metavar=("BACKEND", "NPY", "JSON"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        child(*args.child)
        return 0
    backends = ["sep"] + (["sextractor"] if (shutil.which("source-extractor") or shutil.which("sex")) else [])
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        img = make_image(args.size)
        print(f"synthetic {args.size}x{args.size} image made in {time.perf_counter() - t0:.1f} s")
        npy = os.path.join(tmp, "img.npy")
        np.save(npy, img)
        del img
        results = []
        for backend in backends:
            out_json = os.path.join(tmp, f"{backend}.json")
            subprocess.run([sys.executable, __file__, "--child", backend, npy, out_json], check=True)
            results.append(json.loads(Path(out_json).read_text()))
    if len(backends) == 1:
        print("SExtractor binary not found: only SEP measured (apt-get install source-extractor)")
    info = {"size": args.size, "cores": os.cpu_count(), "results": results}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(info, indent=2) + "\n")
    print(f"{'backend':<11} {'sources':>8} {'detect s':>9} {'SFI s':>7} {'peak MB (py)':>13} {'peak MB (bin)':>14}")
    for r in results:
        print(f"{r['backend']:<11} {r['nsources']:>8} {r['detect_wall_s']:>9} {r['sfi_wall_s']:>7} "
              f"{r['peak_rss_python_mb']:>13} {r['peak_rss_binary_mb']:>14}")
    print(f"written {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
