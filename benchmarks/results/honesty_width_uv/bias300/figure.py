"""Figure of the bias300 diagnostics: running mean of the MAP m50 error over the replicates (with the
+-2 se band of a calibrated posterior, sd / sqrt(R)), and the errors' histogram against N(0, sd)."""
import glob, json, math
import numpy as np
import matplotlib
matplotlib.use("Agg")
import matplotlib.pyplot as plt

SD = 1.95  # mmag, the 300k posterior sd of m50 (1.85-2.02 in diag_300k and exp2)
runs = {}
for path in sorted(glob.glob("exp3_*_300000_0_72_*.json")):
    rows = json.load(open(path))
    truth = path[len("exp3_"):path.index("_300000")]
    for model in [k for k in rows[0] if k != "rep"]:
        runs[f"{truth} / {model}"] = np.array([r[model]["m50_err"] for r in rows])
bench = json.load(open("width_varies_300k_24reps/raw.json"))["records"]
bk = sorted(bench, key=lambda k: int(k.split("|")[2]))
runs["width_varies / auto (bench_honesty)"] = np.array(
    [1e3 * (bench[k]["posterior"]["m50"]["median"] - 23.956444) for k in bk])
fig, (a1, a2) = plt.subplots(1, 2, figsize=(12, 4.5))
for label, e in runs.items():
    r = np.arange(1, e.size + 1)
    a1.plot(r, np.cumsum(e) / r, label=f"{label}: {e.mean():+.2f} +- {e.std(ddof=1) / math.sqrt(e.size):.2f}")
r = np.arange(1, 73)
a1.fill_between(r, -2 * SD / np.sqrt(r), 2 * SD / np.sqrt(r), color="0.85", label="+-2 sd/sqrt(R)")
a1.axhline(0, color="k", lw=0.5); a1.axvline(8, color="0.5", ls=":")
a1.set_xlabel("replicates R (same draw seeds as bench_honesty's width_varies)")
a1.set_ylabel("running mean of m50 error (mmag)"); a1.set_xscale("log"); a1.set_ylim(-3, 3)
a1.legend(fontsize=7); a1.set_title("300k injections: the mean error of the first 8 tables is chance")
allerr = np.concatenate([e for k, e in runs.items() if "width_uv" in k])
a2.hist(allerr, bins=30, density=True, alpha=0.6, label=f"width rung MAP errors, {allerr.size} fits")
x = np.linspace(-7, 7, 200)
a2.plot(x, np.exp(-0.5 * (x / SD) ** 2) / (SD * math.sqrt(2 * math.pi)), "k", label=f"N(0, {SD}) (posterior sd)")
a2.set_xlabel("m50 error (mmag)"); a2.legend(fontsize=8)
fig.tight_layout(); fig.savefig("bias300.png", dpi=110)
for label, e in runs.items():
    print(f"{label:45s} R={e.size:3d} mean {e.mean():+.3f} se {e.std(ddof=1)/math.sqrt(e.size):.3f} spread {e.std(ddof=1):.3f} first8 {e[:8].mean():+.3f}")
