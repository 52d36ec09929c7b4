"""Reading a run's data for the report (comest_bayes.report.rundata): curves and depth lines from the
summary.json of a run directory made by hand, and the sampler chains of a posterior."""

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


# --------------------------------------------------------------------------- a run directory made by hand

def _write_run(path, summary=None, state=None):
    import json

    path.mkdir(parents=True, exist_ok=True)
    state = state if state is not None else {
        "fingerprint": {"config": {"seed": 5, "injection": {"nsims": 3}}},
        "image": {"shape": [100, 200], "zeropoint": 30.0}}
    (path / "run.json").write_text(json.dumps(state))
    if summary is not None:
        (path / "summary.json").write_text(json.dumps(summary))
    return path


SUMMARY = {
    "depth": {"point_source_5sigma": 24.2, "aperture_5sigma": 23.9, "aperture_diameter_pix": 6.0},
    "kinds": {"sersic": {"binned": {"mag_centers": [21.5, 22.5, 23.5], "completeness": [0.9, 0.4, None],
                                    "completeness_lower": [0.8, 0.3, None], "completeness_upper": [0.95, 0.5, None],
                                    "completeness_n": [10, 10, 0], "confidence": 0.6827, "interval": "wilson"}},
              "point": {}},
}


def test_binned_curves_and_depth_lines_from_summary_json(tmp_path):
    from comest_bayes.io.run import Run
    from comest_bayes.report.rundata import binned_curve, depth_lines

    run = Run.open(_write_run(tmp_path / "run", SUMMARY))
    curve = binned_curve(run, "sersic", "completeness")
    np.testing.assert_array_equal(curve.centers, [21.5, 22.5, 23.5])
    np.testing.assert_array_equal(curve.ratio[:2], [0.9, 0.4])
    assert np.isnan(curve.ratio[2]) and list(curve.n) == [10, 10, 0] and curve.interval == "wilson"
    assert binned_curve(run, "sersic", "purity") is None and binned_curve(run, "point", "completeness") is None
    lines = depth_lines(run.summary_record)
    assert [(d.mag, d.label) for d in lines] == [(24.2, "5σ point-source depth"), (23.9, "5σ depth, 6.0 px aperture")]
    assert depth_lines(None) == [] and depth_lines({"depth": {"aperture_5sigma": 23.0}})[0].label == "5σ depth, aperture"
