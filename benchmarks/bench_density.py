"""Benchmark: does the injection density change the measured completeness?

Runs ``comest-bayes demo`` at several injection densities with about the same number of injections
in all (``density x realizations`` held fixed), optionally with a detection or injection setting
switched off, and prints the binned and posterior m50 of every kind.  If the injections did not
affect each other's detection, every row would agree within its interval; they do not (see
``docs/injection.md``, "The injection density changes what is measured").

Usage::

    python benchmarks/bench_density.py [--pairs 15:10 5:30 2.5:60] [--set detection.clean=false ...]
                                       [--work DIR] [--out benchmarks/results/density.json]

Each run goes to ``<work>/d<density>_n<nsims>[_<label>]`` and is resumed there when it exists.
Every row also records the realizations' CPU per usable injection (robust to the machine's load,
which is recorded too).  The figures (demo tile, ~24,400 point and ~25,000 galaxy injections per
row; 2026-11-25 for the defaults and the switches of cleaning and photon noise, 2026-11-27 for
``detection.noise_level = "observed"`` and ``matching.exclude_clean_zone``) are in
``results/density.json``; the table is in ``benchmarks/README.md``.

    python benchmarks/bench_density.py --set detection.noise_level=observed --label obs
    python benchmarks/bench_density.py --set detection.noise_level=observed \
        --set matching.exclude_clean_zone=true --label obs_zone
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
# this checkout first: a non-editable install in site-packages may be an older copy
sys.path.insert(0, str(HERE.parent))


def parse_pair(text: str) -> tuple[float, int]:
    try:
        density, nsims = text.split(":")
        pair = float(density), int(nsims)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected DENSITY:NSIMS such as 15:10, got {text!r}") from None
    if pair[0] <= 0 or pair[1] < 1:
        raise argparse.ArgumentTypeError(f"density must be > 0 and nsims >= 1, got {text!r}")
    return pair


def m50s(run_dir: Path) -> dict:
    """Binned and posterior m50 of every kind of a finished run."""
    summary = json.loads((run_dir / "summary.json").read_text())
    out = {}
    for kind, entry in summary["kinds"].items():
        model = entry.get("model") or {}
        m50 = model.get("m50") or {}
        usable = (entry.get("counts") or {}).get("usable")
        cpu = (entry.get("seconds") or {}).get("cpu")
        out[kind] = {"binned": entry.get("m50_binned"), "median": m50.get("median"), "lo68": m50.get("lo68"),
                     "hi68": m50.get("hi68"), "model": model.get("name"), "injections": usable,
                     "injected": (entry.get("counts") or {}).get("injected"), "realization_cpu": cpu,
                     # CPU of the realizations (inject, detect, match) per usable injection: robust to load
                     "cpu_ms_per_usable": round(1000.0 * cpu / usable, 3) if cpu and usable else None}
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--pairs", nargs="+", type=parse_pair, default=[(15.0, 10), (5.0, 30), (2.5, 60)],
                   help="DENSITY:NSIMS pairs (injections per arcmin^2 and realizations)")
    p.add_argument("--set", dest="overrides", action="append", default=[],
                   help="a configuration override for every run, e.g. detection.clean=false (repeatable)")
    p.add_argument("--label", default="", help="suffix of the run folders for these overrides")
    p.add_argument("--work", default=None, help="folder of the runs (kept; resumed on a rerun)")
    p.add_argument("--out", default=None, help="JSON file for the figures")
    a = p.parse_args(argv)

    from comest_bayes.cli import main as cli

    work = Path(a.work) if a.work else Path(tempfile.mkdtemp(prefix="density_"))
    work.mkdir(parents=True, exist_ok=True)
    rows = []
    for density, nsims in a.pairs:
        name = f"d{density:g}_n{nsims}" + (f"_{a.label}" if a.label else "")
        out = work / name
        args = ["demo", "--out", str(out), "--density", f"{density:g}", "--nsims", str(nsims), "--no-report",
                "--quiet"]
        for o in a.overrides:
            args += ["--set", o]
        t0 = time.perf_counter()
        status = cli(args)
        if status != 0:
            print(f"{name}: the demo ended with status {status}", flush=True)
            return status
        row = {"density": density, "nsims": nsims, "overrides": list(a.overrides), "run": str(out),
               "wall": round(time.perf_counter() - t0, 1), "kinds": m50s(out)}
        rows.append(row)
        row["load"] = os.getloadavg()[0]
        text = "; ".join(f"{k} {v['binned']:.3f} / {v['median']:.3f} [{v['lo68']:.3f}, {v['hi68']:.3f}] "
                         f"({v['injections']} usable, {v['cpu_ms_per_usable']} CPU-ms each)"
                         for k, v in row["kinds"].items() if v["median"] is not None and v["binned"] is not None)
        print(f"density {density:g} x {nsims} realizations{' (' + ', '.join(a.overrides) + ')' if a.overrides else ''}: "
              f"m50 binned / posterior [68%]: {text} ({row['wall']:.0f} s)", flush=True)
    if a.out:
        path = Path(a.out)
        old = json.loads(path.read_text()) if path.exists() else {"rows": []}
        keep = [r for r in old.get("rows", []) if not any(r["density"] == n["density"] and r["nsims"] == n["nsims"]
                                                           and r["overrides"] == n["overrides"] for n in rows)]
        path.write_text(json.dumps({"rows": keep + rows}, indent=1))
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
