"""Same as diag.py (truth width_logplane, logistic_depth_width_uv, 300k) with the compression refined:
argv[1] = 'nuv32' (position blocks 32 x 32 instead of 16 x 16) or 'fine' (magnitude and depth steps halved)."""
import sys, runpy
sys.path.insert(0, "/work/wt-width2")
from comest_bayes.pipeline import runtime
runtime.configure(threads=1)
import comest_bayes.bayes.fit as F
import comest_bayes.bayes.outcomes as O
variant = sys.argv[1]
orig = F.compress_for
def patched(specs, cov, det, **kw):
    if variant == "nuv32":
        kw["nuv"] = 32
    elif variant == "fine":
        shrink = min(1.0, (O.DM_REFERENCE_N / max(len(cov), 1)) ** 0.25)
        kw.setdefault("dm", 0.5 * O.DM_TRANSITION * shrink)
        kw.setdefault("ddepth", 0.5 * O.DDEPTH * shrink)
    return orig(specs, cov, det, **kw)
F.compress_for = patched
sys.argv = ["diag2.py", "300000", sys.argv[2], "logistic_depth_width_uv", "width_logplane"]
runpy.run_path(str(__import__("pathlib").Path(__file__).with_name("diag.py")), run_name="__main__")
