# Per-step m50 / curve RMSE and mean half-width of two bench_adaptive.py runs (before / after), from their raw.json.
# Usage: python compare_steps.py BEFORE/raw.json AFTER/raw.json
import sys, json, numpy as np, collections
B = json.load(open(sys.argv[1]))["adaptive"]
A = json.load(open(sys.argv[2]))["adaptive"]
for sc in ("white", "demo", "varying"):
    print("==", sc)
    for tag, R in (("before", B), ("after", A)):
        by = collections.defaultdict(list)
        models = collections.defaultdict(collections.Counter)
        cpu = []
        for key, res in R.items():
            if not key.startswith(sc + "|"): continue
            cpu.append(sum(s["cpu_fit"] for s in res["steps"]))
            for s in res["steps"]:
                by[s["n"]].append((s["m50_err"], s["curve_rms"], s["halfwidth"]))
                models[s["n"]][s["model"]] += 1
        ns = sorted(by)
        line = []
        for n in ns:
            a = np.array(by[n])
            if len(a) < 4: continue
            line.append(f"{n}:{np.sqrt(np.nanmean(a[:,0]**2))*1000:.1f}/{np.sqrt(np.mean(a[:,1]**2))*1000:.1f}")
        print(f" {tag:6s} refit CPU/run {np.mean(cpu):.1f}s  n:m50rmse/curvermse (mmag, 1e-3):", " ".join(line))
        print("        models:", {n: dict(models[n]) for n in ns[:6]})
print("mean half-width (mmag) per step")
for sc in ("white", "demo", "varying"):
    for tag, R in (("before", B), ("after", A)):
        by = collections.defaultdict(list)
        for key, res in R.items():
            if key.startswith(sc + "|"):
                for s in res["steps"]:
                    by[s["n"]].append(s["halfwidth"])
        print(sc, tag, " ".join(f"{n}:{np.mean(v)*1000:.1f}" for n, v in sorted(by.items()) if len(v) >= 4))
