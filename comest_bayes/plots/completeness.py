"""Completeness and purity versus magnitude; measured versus true magnitude.

Binned ratios are drawn as points with their binomial intervals (bins with
``n = 0`` are left out), the posterior median curve as a line with its 68% and
95% bands, and reference magnitudes (N-sigma depths, m50) as vertical lines.
"""

from __future__ import annotations

import textwrap

import numpy as np

from . import COLORS, new_axes, new_figure
from .data import BinnedCurve, PosteriorBand

__all__ = ["ratio_curve", "ratios_figure", "magnitude_comparison", "magnitude_comparison_figure"]

_YLABEL = {"completeness": "completeness", "purity": "purity"}
_XLABEL = {"completeness": "true magnitude (mag)", "purity": "measured magnitude (mag)"}


def ratio_curve(binned: BinnedCurve | None, *, posterior: PosteriorBand | None = None, depth=(),
                quantity: str = "completeness", ax=None, label: str = "binned", color: str | None = None,
                xlabel: str | None = None, legend: bool = True):
    """Completeness (or purity) versus magnitude.

    Parameters
    ----------
    binned : BinnedCurve or None
        Binned ratios: points with error bars (the interval of ``binned.confidence``).
    posterior : PosteriorBand, optional
        Posterior median (line) with 68% (dark) and 95% (light) bands.
    depth : sequence of DepthLine
        Reference magnitudes, drawn as dashed vertical lines.
    quantity : {"completeness", "purity"}
        Sets the axis labels (true versus measured magnitude).
    ax : matplotlib.axes.Axes, optional
    label : str
        Legend text of the binned points.
    color : str, optional
        Colour of the posterior curve (default blue).
    xlabel : str, optional
        Overrides the x label.
    legend : bool
        Draw the legend (default True).

    Returns
    -------
    matplotlib.axes.Axes
    """
    ax = new_axes(ax, (6.4, 4.4))
    color = color or COLORS["posterior"]
    if posterior is not None:
        ax.fill_between(posterior.mag, posterior.lo95, posterior.hi95, color=color, alpha=0.18, lw=0,
                        label=f"{posterior.label}: 95%")
        ax.fill_between(posterior.mag, posterior.lo68, posterior.hi68, color=color, alpha=0.38, lw=0,
                        label=f"{posterior.label}: 68%")
        ax.plot(posterior.mag, posterior.median, color=color, lw=1.8, label=f"{posterior.label}: median")
    if binned is not None:
        ok = (np.asarray(binned.n) > 0) & np.isfinite(binned.ratio)
        c, r = binned.centers[ok], binned.ratio[ok]
        yerr = np.vstack([r - binned.lower[ok], binned.upper[ok] - r])
        interval = " ".join(filter(None, [f"{100 * binned.confidence:.0f}%", binned.interval, "interval"]))
        ax.errorbar(c, r, yerr=np.clip(yerr, 0, None), fmt="o", ms=3.5, color=COLORS["binned"], ecolor="0.35",
                    elinewidth=1.0, capsize=0, label=f"{label} ({interval})", zorder=5)
    for i, d in enumerate(depth):
        if d.mag is not None and np.isfinite(d.mag):
            dc = COLORS["depth"][i % len(COLORS["depth"])]
            ax.axvline(d.mag, color=dc, ls="--", lw=1.2, label=f"{d.label} = {d.mag:.2f}")
    ax.axhline(0.5, color="0.7", lw=0.8, ls=":")
    ax.set_ylim(-0.03, 1.05)
    ax.set_xlabel(xlabel or _XLABEL.get(quantity, "magnitude (mag)"))
    ax.set_ylabel(_YLABEL.get(quantity, quantity))
    ax.grid(alpha=0.25)
    if legend and ax.get_legend_handles_labels()[0]:
        ax.legend(loc="lower left", fontsize=8, framealpha=0.9)
    return ax


def ratios_figure(kind: str, completeness: BinnedCurve | None, purity: BinnedCurve | None, *,
                  completeness_posterior: PosteriorBand | None = None, purity_posterior: PosteriorBand | None = None,
                  depth=(), notes: dict | None = None):
    """Completeness (left) and purity (right) of one source kind.

    ``notes`` maps ``"completeness"``/``"purity"`` to a short text written in
    the panel (e.g. why there is no posterior curve).

    Returns
    -------
    matplotlib.figure.Figure
    """
    fig = new_figure((12.0, 4.6))
    axes = fig.subplots(1, 2)
    ratio_curve(completeness, posterior=completeness_posterior, depth=depth, quantity="completeness", ax=axes[0])
    axes[0].set_title(f"{kind}: completeness")
    ratio_curve(purity, posterior=purity_posterior, depth=depth, quantity="purity", ax=axes[1])
    axes[1].set_title(f"{kind}: purity")
    for ax, key in zip(axes, ("completeness", "purity")):
        text = (notes or {}).get(key)
        if text:
            ax.text(0.97, 0.6, textwrap.fill(text, 52), transform=ax.transAxes, ha="right", va="center", fontsize=8,
                    color="0.25", bbox=dict(boxstyle="round", fc="white", ec="0.8", alpha=0.9))
    return fig


def magnitude_comparison(true_mag, measured_mag, *, ax=None, bins: int = 60, label: str | None = None):
    """Measured versus true magnitude of recovered injections: 2-D histogram, 1:1 line, running median.

    The running median is the median (true, measured) pair in 24 bins of true
    magnitude holding at least 10 injections.

    Parameters
    ----------
    true_mag, measured_mag : array_like, shape (N,)
        Magnitudes of matched injections (non-finite pairs are dropped).
    ax : matplotlib.axes.Axes, optional
    bins : int
        Most histogram bins per axis (fewer for small samples: sqrt(N)/2, at least 20).
    label : str, optional
        Panel title.

    Returns
    -------
    matplotlib.axes.Axes
    """
    from matplotlib.colors import LogNorm
    from matplotlib.ticker import LogFormatter

    ax = new_axes(ax, (5.4, 4.8))
    t = np.asarray(true_mag, float)
    m = np.asarray(measured_mag, float)
    ok = np.isfinite(t) & np.isfinite(m)
    t, m = t[ok], m[ok]
    if t.size == 0:
        ax.text(0.5, 0.5, "no recovered injections", transform=ax.transAxes, ha="center", va="center")
    else:
        lo = float(np.percentile(np.concatenate([t, m]), 0.2)) - 0.2
        hi = float(np.percentile(np.concatenate([t, m]), 99.8)) + 0.2
        nb = int(np.clip(np.sqrt(t.size) / 2.0, 20, bins))
        h = ax.hist2d(t, m, bins=nb, range=[[lo, hi], [lo, hi]], cmap="viridis", norm=LogNorm(), cmin=1)
        ax.figure.colorbar(h[3], ax=ax, label="recovered injections per cell", shrink=0.85,
                           format=LogFormatter(labelOnlyBase=False, minor_thresholds=(3, 1)))
        ax.plot([lo, hi], [lo, hi], color="#D55E00", lw=1.2, label="1:1")
        edges = np.linspace(lo, hi, 25)
        idx = np.digitize(t, edges) - 1
        centers, medians = [], []
        for i in range(len(edges) - 1):
            sel = idx == i
            if sel.sum() >= 10:
                centers.append(np.median(t[sel]))
                medians.append(np.median(m[sel]))
        if centers:
            ax.plot(centers, medians, color="white", lw=2.4)
            ax.plot(centers, medians, color="black", lw=1.2, label="running median")
        ax.set_xlim(lo, hi)
        ax.set_ylim(lo, hi)
        ax.set_aspect("equal")
        ax.legend(loc="upper left", fontsize=8)
    ax.set_xlabel("true magnitude (mag)")
    ax.set_ylabel("measured magnitude (mag)")
    if label:
        ax.set_title(label)
    return ax


def magnitude_comparison_figure(pairs: dict, *, measured_label: str = "MAG_AUTO"):
    """One :func:`magnitude_comparison` panel per kind: ``pairs = {kind: (true_mag, measured_mag)}``.

    Returns
    -------
    matplotlib.figure.Figure
    """
    n = max(1, len(pairs))
    fig = new_figure((5.4 * n, 4.9))
    axes = np.atleast_1d(fig.subplots(1, n))
    for ax, (kind, (t, m)) in zip(axes, pairs.items()):
        magnitude_comparison(t, m, ax=ax, label=f"{kind}: recovered injections")
        ax.set_ylabel(f"measured magnitude, {measured_label} (mag)")
    return fig
