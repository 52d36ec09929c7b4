"""Model selection and sampler diagnostics.

* :func:`selection_plot`: the PSIS-LOO comparison of the candidate models
  (difference in expected log predictive density to the best, with its
  standard error), the chosen model marked, and the selection margin
  ``max(4, 2 se)`` nats of :mod:`comest_bayes.bayes.selection`;
* :func:`autocorrelation_plot`: integrated autocorrelation time per parameter
  against the ``nsteps / 50`` convergence limit (emcee's authors' advice,
  used by :mod:`comest_bayes.bayes.inference`);
* :func:`trace_plot`: post-burn-in traces of the key parameters, walker by walker.
"""

from __future__ import annotations

import numpy as np

from comest_bayes.report.plots import COLORS, new_axes, new_figure
from comest_bayes.report.plots.completeness import outside_legend
from comest_bayes.report.plots.data import ChainSamples

__all__ = ["selection_plot", "autocorrelation_plot", "trace_plot", "sampler_figure"]

#: Axis labels of the physical parameters of the completeness models.
PARAM_LABELS = {
    "m50_0": "m50 at the reference (mag)",
    "w": "width w (mag)",
    "A": "plateau A",
    "floor": "floor",
    "beta_depth": "depth slope",
    "w_depth": "depth width slope",
    "beta_size": "size slope",
}


def selection_plot(table: list, *, ax=None, margin: float = 4.0, margin_se: float = 2.0):
    """PSIS-LOO comparison: delta elpd (+- se of the difference) per candidate model.

    Parameters
    ----------
    table : list of dict
        Rows of the selection table (``name``, ``nparams``, ``delta_elpd``,
        ``se_delta``, ``chosen``), simplest model first.
    margin, margin_se : float
        The selection rule keeps the simplest model within
        ``max(margin, margin_se * se_delta)`` nats of the best; the fixed part
        is shaded.

    Returns
    -------
    matplotlib.axes.Axes
    """
    ax = new_axes(ax, (6.4, 0.6 * max(len(table), 2) + 1.4))
    names = [f"{r['name']} ({r['nparams']} par.)" for r in table]
    y = np.arange(len(table))[::-1]
    d = np.array([np.nan if r.get("delta_elpd") is None else r["delta_elpd"] for r in table], float)
    se = np.array([0.0 if r.get("se_delta") is None else r["se_delta"] for r in table], float)
    ax.axvspan(-margin, 0.0, color="#009E73", alpha=0.12, lw=0, label=f"within {margin:g} nats of the best")
    ax.axvline(0.0, color="0.5", lw=0.8)
    ax.errorbar(d, y, xerr=margin_se * se, fmt="none", ecolor="0.6", elinewidth=1.0, capsize=3,
                label=f"+- {margin_se:g} se of the difference")
    ax.errorbar(d, y, xerr=se, fmt="o", color="black", ms=5, elinewidth=2.0, capsize=0, label="delta elpd +- se")
    chosen = np.array([bool(r.get("chosen")) for r in table])
    if chosen.any():
        ax.plot(d[chosen], y[chosen], marker="*", ms=16, color=COLORS["posterior"], ls="none", label="chosen")
    ax.set_yticks(y, names)
    ax.set_xlabel("elpd_loo difference to the best model (nats)")
    ax.set_title("PSIS-LOO comparison of the candidate models", fontsize=10)
    if np.isfinite(d).any():
        lo = float(np.nanmin(np.concatenate([d - margin_se * se, [-margin]])))
        hi = float(np.nanmax(np.concatenate([d + margin_se * se, [0.0]])))
    else:
        lo, hi = -margin, 0.0
    pad = 0.08 * (hi - lo) + 0.5
    ax.set_xlim(lo - pad, hi + pad)
    ax.set_ylim(-0.7, len(table) - 0.3)
    outside_legend(ax, below=False, ncol=1)  # outside the data: a legend inside hid rows' markers
    ax.grid(axis="x", alpha=0.25)
    return ax


def autocorrelation_plot(names, tau, nsteps: int, *, ax=None, converge_factor: float = 50.0):
    """Integrated autocorrelation time per parameter against ``nsteps / converge_factor``.

    Parameters
    ----------
    names : sequence of str
        Parameter names.
    tau : array_like, shape (P,)
        Autocorrelation times, steps (None or non-finite: not estimated).
    nsteps : int
        Steps run per walker.

    Returns
    -------
    matplotlib.axes.Axes
    """
    ax = new_axes(ax, (5.0, 3.6))
    t = np.array([np.nan if v is None else v for v in tau], float)
    limit = nsteps / converge_factor
    colors = [COLORS["posterior"] if np.isfinite(v) and v < limit else "#D55E00" for v in t]
    x = np.arange(len(names))
    ax.bar(x, np.where(np.isfinite(t), t, 0.0), color=colors)
    ax.axhline(limit, color="black", ls="--", lw=1.2, label=f"nsteps / {converge_factor:g} = {limit:.0f}")
    ax.set_xticks(x, list(names), rotation=30, ha="right")
    ax.set_ylabel("autocorrelation time (steps)")
    ax.set_title(f"autocorrelation ({nsteps} steps per walker)", fontsize=10)
    outside_legend(ax, below=False, ncol=1)
    ax.grid(axis="y", alpha=0.25)
    return ax


def trace_plot(chain: ChainSamples, *, axes=None, max_walkers: int = 32, max_points: int = 600):
    """Traces of each parameter: one thin line per walker over the kept steps.

    Parameters
    ----------
    chain : ChainSamples
        Post-burn-in values, shape (T, W, P).
    axes : sequence of Axes, optional
        One per parameter (default: a new figure with P rows).
    max_walkers : int
        Draw at most this many walkers (default 32).
    max_points : int
        Thin the steps to at most this many points per line (default 600).

    Returns
    -------
    list of matplotlib.axes.Axes
    """
    values = np.asarray(chain.values, float)
    ntot, nw, npar = values.shape
    if axes is None:
        fig = new_figure((7.0, 1.7 * npar + 0.6))
        axes = np.atleast_1d(fig.subplots(npar, 1, sharex=True))
    stride = max(1, int(np.ceil(ntot / max_points)))
    steps = chain.burn + np.arange(ntot)[::stride]
    for p, ax in enumerate(axes):
        ax.plot(steps, values[::stride, :max_walkers, p], lw=0.4, alpha=0.35, color=COLORS["posterior"])
        ax.plot(steps, np.median(values[::stride, :, p], axis=1), lw=1.0, color="black")
        ax.set_ylabel(PARAM_LABELS.get(chain.names[p], chain.names[p]), fontsize=8)
        ax.ticklabel_format(axis="y", useOffset=False)
        ax.grid(alpha=0.25)
    axes[-1].set_xlabel("step (after burn-in); black: median over walkers")
    return list(axes)


def sampler_figure(title: str, diagnostics: dict, chain: ChainSamples | None):
    """Autocorrelation times (left) and traces of the key parameters (right).

    Parameters
    ----------
    title : str
    diagnostics : dict
        Sampler diagnostics (``names``, ``tau``, ``nsteps``, ``acceptance_mean``, ``converged``).
    chain : ChainSamples or None
        Traces; without them only the autocorrelation panel is drawn.

    Returns
    -------
    matplotlib.figure.Figure
    """
    npar = 0 if chain is None else chain.values.shape[2]
    fig = new_figure((12.0, max(3.8, 1.6 * npar + 0.8)))
    grid = fig.add_gridspec(max(npar, 1), 2, width_ratios=[1.0, 1.6])
    ax0 = fig.add_subplot(grid[:, 0])
    autocorrelation_plot(diagnostics.get("names", []), diagnostics.get("tau", []), int(diagnostics.get("nsteps", 0)),
                         ax=ax0)
    if chain is not None:
        axes = [fig.add_subplot(grid[p, 1]) for p in range(npar)]
        for a in axes[1:]:
            a.sharex(axes[0])
        for a in axes[:-1]:
            a.tick_params(labelbottom=False)
        trace_plot(chain, axes=axes)
    acc = diagnostics.get("acceptance_mean")
    conv = "converged" if diagnostics.get("converged") else "NOT converged"
    fig.suptitle(f"{title}: {conv}" + (f", mean acceptance {acc:.2f}" if acc is not None else ""))
    return fig
