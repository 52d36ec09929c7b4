"""Figures of a number-count (luminosity-function) fit: observed versus forward-modelled counts, corner plot.

:func:`counts_figure` shows the catalog counts per measured-magnitude bin
(points with Poisson ``sqrt(N)`` bars) against the forward model (median and
68% / 95% bands of the expected counts over posterior draws), and, on a
second panel, the fitted intrinsic counts ``phi(m)`` with the posterior-median
footprint-average completeness on a twin axis.  :func:`corner_figure` is a
small corner plot of the count parameters (histograms on the diagonal,
68% / 95% highest-density contours of a 2-D histogram below it).
The report loads the fits under a run's ``lf/`` folder (:func:`comest_bayes.report.html.lf_figures`);
this module only draws, so it never imports :mod:`comest_bayes.lf.fit`.
"""

from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure

from comest_bayes.report.plots import COLORS, new_figure
from comest_bayes.report.plots.completeness import outside_legend

__all__ = ["counts_figure", "corner_figure"]


def counts_figure(result, *, truth_phi=None) -> Figure:
    """Observed counts versus the forward model, and the fitted ``phi(m)``.

    Parameters
    ----------
    result : comest_bayes.lf.result.LFResult
    truth_phi : callable, optional
        ``m -> phi`` (deg^-2 mag^-1) of a known truth, drawn dashed (mocks).

    Returns
    -------
    matplotlib.figure.Figure
    """
    fig = new_figure((6.4, 7.8))
    ax1, ax2 = fig.subplots(2, 1, sharex=True)
    e = np.asarray(result.obs_edges)
    c = 0.5 * (e[:-1] + e[1:])
    b = np.asarray(result.expected_bands)
    color = COLORS["posterior"]
    ax1.fill_between(c, b[0], b[4], step="mid", color=color, alpha=0.18, lw=0, label="forward model 95%")
    ax1.fill_between(c, b[1], b[3], step="mid", color=color, alpha=0.38, lw=0, label="forward model 68%")
    ax1.step(c, b[2], where="mid", color=color, lw=1.6, label="forward model median")
    obs = np.asarray(result.observed)
    ax1.errorbar(c, obs, yerr=np.sqrt(np.maximum(obs, 1.0)), fmt="o", ms=3.5, color=COLORS["binned"],
                 label=f"catalog ({result.n_objects})")
    ax1.set_yscale("log")
    ax1.set_ylabel("detections per bin")
    ax1.set_title(f"{result.kind} {result.spec.get('name', '')}, mode {result.mode}", fontsize=10)
    g = np.asarray(result.grid)
    p = np.asarray(result.phi_bands)
    lo, hi = result.mag_range
    ax2.fill_between(g, p[0], p[4], color=color, alpha=0.18, lw=0)
    ax2.fill_between(g, p[1], p[3], color=color, alpha=0.38, lw=0)
    ax2.plot(g, p[2], color=color, lw=1.6, label=r"fitted $\phi(m)$")
    if truth_phi is not None:
        ax2.plot(g, truth_phi(g), "k--", lw=1.2, label="truth")
    ax2.set_yscale("log")
    ax2.set_xlabel("magnitude (measured above, true below)")
    ax2.set_ylabel(r"$\phi$ (deg$^{-2}$ mag$^{-1}$)")
    ax2.axvspan(lo, hi, color="0.9", zorder=0)
    tw = ax2.twinx()
    tw.plot(g, result.fbar_median, color=COLORS["depth"][0], lw=1.0, label="completeness (median)")
    tw.set_ylim(0, 1.05)
    tw.set_ylabel("completeness", color=COLORS["depth"][0])
    # one legend for both panels, under them: inside, it hid catalog points and the completeness curve
    handles, labels = [], []
    for a in (ax1, ax2, tw):
        h, lab = a.get_legend_handles_labels()
        handles += h
        labels += lab
    outside_legend(ax2, handles, labels, ncol=2)
    ax2.set_xlim(g[0], g[-1])
    return fig


def _hpd_levels(h, fractions=(0.68, 0.95)):
    flat = np.sort(h.ravel())[::-1]
    cum = np.cumsum(flat) / max(flat.sum(), 1e-300)
    return sorted({float(flat[min(np.searchsorted(cum, f), flat.size - 1)]) for f in fractions})


def corner_figure(result, *, truths=None, bins: int = 30) -> Figure:
    """Corner plot of the count parameters.

    Parameters
    ----------
    result : comest_bayes.lf.result.LFResult
    truths : sequence of float, optional
        True values (mocks), drawn as lines.
    bins : int
        Histogram bins per axis.
    """
    s = np.asarray(result.samples)
    names = list(result.names)
    d = len(names)
    fig = new_figure((2.2 * d + 1, 2.2 * d + 1))
    axes = np.atleast_2d(fig.subplots(d, d, squeeze=False))
    color = COLORS["posterior"]
    for i in range(d):
        for j in range(d):
            ax = axes[i, j]
            if j > i:
                ax.set_visible(False)
                continue
            if i == j:
                ax.hist(s[:, i], bins=bins, color=color, histtype="stepfilled", alpha=0.6)
                q = np.percentile(s[:, i], [16, 50, 84])
                for v in q:
                    ax.axvline(v, color="k", lw=0.8, ls="--" if v != q[1] else "-")
                ax.set_yticks([])
                ax.set_title(f"{names[i]} = {q[1]:.3g}$^{{+{q[2] - q[1]:.2g}}}_{{-{q[1] - q[0]:.2g}}}$", fontsize=8)
                if truths is not None:
                    ax.axvline(truths[i], color=COLORS["depth"][0], lw=1.2)
            else:
                h, xe, ye = np.histogram2d(s[:, j], s[:, i], bins=bins)
                levels = _hpd_levels(h)
                xc, yc = 0.5 * (xe[:-1] + xe[1:]), 0.5 * (ye[:-1] + ye[1:])
                ax.plot(s[::max(1, len(s) // 2000), j], s[::max(1, len(s) // 2000), i], ",", color="0.6")
                if len(levels) >= 1 and np.ptp(h) > 0:
                    ax.contour(xc, yc, h.T, levels=levels, colors=[color], linewidths=1.0)
                if truths is not None:
                    ax.axvline(truths[j], color=COLORS["depth"][0], lw=1.0)
                    ax.axhline(truths[i], color=COLORS["depth"][0], lw=1.0)
            if i == d - 1:
                ax.set_xlabel(names[j], fontsize=9)
            else:
                ax.set_xticklabels([])
            if j == 0 and i > 0:
                ax.set_ylabel(names[i], fontsize=9)
            elif j > 0:
                ax.set_yticklabels([])
    return fig
