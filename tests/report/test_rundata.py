"""Reading a run's data for the report (comest_bayes.report.rundata)."""

import numpy as np

from comest_bayes.bayes.spec import load_spec
from comest_bayes.report.plots.diagnostics import sampler_figure, trace_plot
from comest_bayes.report.rundata import chain_samples
from comest_bayes.bayes.posterior import CompletenessPosterior


def test_chain_samples_unflattens_step_major_draws():
    """Row s * W + w of the stored draws is walker w at kept step s (inference.PosteriorSamples)."""
    spec = load_spec("logistic")
    nsteps, nw = 30, 8
    s_idx, w_idx = np.divmod(np.arange(nsteps * nw), nw)
    meta = {"sigma_ref": 1.0, "hlr_ref": None, "image_shape": (100, 100), "mag_range": [20.0, 25.0]}
    probe = CompletenessPosterior(spec=spec, samples=np.zeros((1, 4)), names=["m50_0", "log_w", "logit_A",
                                                                              "logit_floor"], meta=meta)
    names = list(probe.model.names)
    samples = np.zeros((nsteps * nw, len(names)))
    samples[:, names.index("m50_0")] = 20.0 + s_idx + w_idx / 100.0   # encodes (step, walker)
    samples[:, names.index("log_w")] = np.log(0.2 + 0.001 * s_idx)
    post = CompletenessPosterior(spec=spec, samples=samples, names=names, meta=meta,
                                 diagnostics={"sampler": {"nwalkers": nw, "burn": 40}})
    chain = chain_samples(post)
    assert chain.names[:2] == ["m50_0", "w"] and chain.burn == 40
    assert chain.values.shape[:2] == (nsteps, nw)
    np.testing.assert_allclose(chain.values[:, :, 0], 20.0 + np.arange(nsteps)[:, None] + np.arange(nw) / 100.0)
    # constant parameters (A, floor: all samples at the same value) are not traced
    assert "A" not in chain.names
    # a walker count that does not divide the draws: no traces
    post.diagnostics = {"sampler": {"nwalkers": 7}}
    assert chain_samples(post) is None

    lines = trace_plot(chain)
    assert len(lines) == 2 and lines[0].lines[0].get_xdata()[0] == 40
    fig = sampler_figure("point completeness", {"names": names, "tau": [5, 6, 7, 8], "nsteps": 70,
                                                "acceptance_mean": 0.3, "converged": True}, chain)
    assert "converged" in fig._suptitle.get_text() and len(fig.axes) == 3
