"""Paired comparison of two bench_honesty.py runs on the same seeds: before (A) and after (B) a change.

usage: python benchmarks/honesty_pair.py A_raw.json[,A2.json] B_raw.json

Per truth and N: how many replicates chose the same model, CPU seconds, samplers, unconverged fits;
per quantity: the shift of the posterior median in units of the A posterior sd (mean, rms, max), the
ratio of the posterior sds, |bias| / sd and the 68% coverage of each run.
"""
import json, sys, collections, numpy as np
def load(arg):
    out = {}
    for f in arg.split(","):
        out.update(json.load(open(f))["records"])
    return out
A, B = load(sys.argv[1]), load(sys.argv[2])
keys = sorted(set(A) & set(B))
g = collections.defaultdict(list)
for k in keys:
    a, b = A[k], B[k]
    if "posterior" not in a or "posterior" not in b: continue
    g[(a["truth"], a["n"])].append((a, b))
qs = ["m50", "m90", "f_bright", "f_faint"]
for key in sorted(g):
    pairs = g[key]
    same = sum(a["model"] == b["model"] for a, b in pairs)
    print(f"{key[0]} N={key[1]} R={len(pairs)} same model {same}/{len(pairs)}  cpu A {sum(a['cpu_seconds'] for a,b in pairs):.0f} B {sum(b['cpu_seconds'] for a,b in pairs):.0f}"
          f"  samplers A {dict(collections.Counter(a.get('sampler') for a,b in pairs))} B {dict(collections.Counter(b.get('sampler') for a,b in pairs))}"
          f"  unconverged A {sum(not a.get('converged') for a,b in pairs)} B {sum(not b.get('converged') for a,b in pairs)}")
    for q in qs:
        dm, sr, za, zb, ca, cb = [], [], [], [], [], []
        for a, b in pairs:
            pa, pb, t = a["posterior"][q], b["posterior"][q], a["truth_footprint"][q]
            if not pa.get("sd") or not pb.get("sd") or t is None or pa.get("median") is None or pb.get("median") is None: continue
            dm.append((pb["median"] - pa["median"]) / pa["sd"]); sr.append(pb["sd"] / pa["sd"])
            za.append((pa["median"] - t) / pa["sd"]); zb.append((pb["median"] - t) / pb["sd"])
            ca.append(pa["lo68"] <= t <= pa["hi68"]); cb.append(pb["lo68"] <= t <= pb["hi68"])
        if not dm: continue
        dm = np.array(dm)
        print(f"   {q:9s} median shift/sd: mean {dm.mean():+.3f} rms {np.sqrt(np.mean(dm**2)):.3f} max {np.max(np.abs(dm)):.2f}  sd ratio {np.median(sr):.3f} [{np.min(sr):.2f},{np.max(sr):.2f}]"
              f"  bias/sd A {np.mean(za):+.2f} B {np.mean(zb):+.2f}  cov68 A {np.mean(ca):.2f} B {np.mean(cb):.2f}")
