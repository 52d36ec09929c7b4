"""bench_honesty.py replicates split by the model the selection chose: bias / sd and 68% coverage per quantity.

usage: python benchmarks/honesty_by_model.py raw.json[,raw2.json]

Rows "ALL" are every replicate of a truth and N; the other rows the replicates that chose that model.
A subset chosen by the selection is not a random sample: its bias says what the selection let through.
"""
import json, sys, collections, numpy as np
recs = {}
for f in sys.argv[1].split(","):
    recs.update(json.load(open(f))["records"])
g = collections.defaultdict(list)
for k, r in recs.items():
    if "posterior" not in r: continue
    g[(r["truth"], r["n"], r["model"])].append(r); g[(r["truth"], r["n"], "ALL")].append(r)
qs = ["m50", "m90", "f_bright", "f_faint"]
print(f"{'truth':16s} {'N':>6s} {'model':22s} {'R':>3s}  " + "  ".join(f"{q:>22s}" for q in qs) + "   cpu-s  sampler")
for key in sorted(g):
    rs = g[key]
    cells = []
    for q in qs:
        z = []; c68 = []; sdr = []
        for r in rs:
            p = r["posterior"][q]; t = r["truth_footprint"][q]
            if p.get("median") is None or t is None or not p.get("sd"): continue
            z.append((p["median"] - t) / p["sd"]); c68.append(p["lo68"] <= t <= p["hi68"])
        if z:
            cells.append(f"b/sd {np.mean(z):+.2f} c68 {np.mean(c68):.2f}")
        else:
            cells.append(" " * 22)
    cpu = np.mean([r["cpu_seconds"] for r in rs])
    samp = collections.Counter(r.get("sampler") for r in rs)
    print(f"{key[0]:16s} {key[1]:6d} {key[2]:22s} {len(rs):3d}  " + "  ".join(cells) + f"  {cpu:6.1f}  {dict(samp)}")
