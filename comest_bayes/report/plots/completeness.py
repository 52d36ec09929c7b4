"""Completeness and purity versus magnitude; measured versus true magnitude.

Binned ratios are drawn as points with their binomial intervals (bins with
``n = 0`` are left out), the posterior median curve as a line with its 68% and
95% bands, and reference magnitudes (N-sigma depths, m50) as vertical lines.
"""

from __future__ import annotations

import textwrap

import numpy as np

from comest_bayes.report.plots import COLORS, new_axes, new_figure
from comest_bayes.report.plots.data import BinnedCurve, PosteriorBand

__all__ = ["ratio_curve", "ratios_figure", "magnitude_comparison", "magnitude_comparison_figure", "band_width",
           "band_caption", "band_width_panel", "outside_legend"]

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
        outside_legend(ax)
    return ax


def outside_legend(ax, handles=None, labels=None, *, title: str | None = None, below: bool = True, ncol: int = 2):
    """The legend of ``ax`` outside its data area (below it, or to its right), so it hides no marker.

    ``loc="best"`` still covers points on dense panels; constrained layout makes room for a legend
    anchored outside the axes.
    """
    from matplotlib.transforms import offset_copy

    if handles is None:
        handles, labels = ax.get_legend_handles_labels()
    if below:  # a fixed distance in points under the axes: clear of the tick labels and the x label
        below_axes = offset_copy(ax.transAxes, fig=ax.figure, y=-34, units="points")
        return ax.legend(handles, labels, loc="upper center", bbox_to_anchor=(0.5, 0.0), bbox_transform=below_axes,
                         ncol=ncol, fontsize=8, frameon=False, title=title, title_fontsize=8)
    return ax.legend(handles, labels, loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8, frameon=False,
                     title=title, title_fontsize=8)


def band_width(posterior: PosteriorBand) -> dict:
    """Widths of the posterior bands: ``{"w68", "w95"}`` arrays against ``posterior.mag``, and their maxima.

    Returns
    -------
    dict
        ``w68``, ``w95`` (arrays, shape (M,)), ``max68``, ``max95`` (floats) and ``mag_max95`` (the magnitude
        of the widest 95% band).
    """
    w68 = np.asarray(posterior.hi68, float) - np.asarray(posterior.lo68, float)
    w95 = np.asarray(posterior.hi95, float) - np.asarray(posterior.lo95, float)
    j = int(np.nanargmax(w95)) if np.isfinite(w95).any() else 0
    return {"w68": w68, "w95": w95, "max68": float(np.nanmax(w68)) if np.isfinite(w68).any() else float("nan"),
            "max95": float(w95[j]), "mag_max95": float(np.asarray(posterior.mag, float)[j])}


def band_caption(posterior: PosteriorBand, quantity: str = "completeness") -> str:
    """One sentence stating how wide the 68% and 95% bands are (and whether they show at full scale)."""
    b = band_width(posterior)
    sym = "f" if quantity == "completeness" else "purity"
    text = (f"{posterior.label}: widest 95% band {b['max95']:.3f} in {sym} (at {b['mag_max95']:.2f} mag), "
            f"widest 68% band {b['max68']:.3f}")
    if b["max95"] < 0.05:  # under 5% of the axis: a few pixels at most
        text += "; narrower than 0.05, hardly visible at the 0-1 scale: see the band-width panel"
    return text


def band_width_panel(posterior: PosteriorBand, *, ax, color: str | None = None):
    """Width of the 68% and 95% bands (hi - lo) against magnitude, on its own y scale."""
    color = color or COLORS["posterior"]
    b = band_width(posterior)
    ax.fill_between(posterior.mag, 0.0, b["w95"], color=color, alpha=0.18, lw=0)
    ax.fill_between(posterior.mag, 0.0, b["w68"], color=color, alpha=0.38, lw=0)
    ax.plot(posterior.mag, b["w95"], color=color, lw=1.0)
    ax.set_ylim(0.0, 1.15 * b["max95"] if np.isfinite(b["max95"]) and b["max95"] > 0 else 1.0)
    ax.set_ylabel("band width", fontsize=8)
    ax.tick_params(labelsize=7)
    ax.grid(alpha=0.25)
    ax.text(0.01, 0.95, f"95% (light), 68% (dark); widest 95%: {b['max95']:.3f} at {b['mag_max95']:.2f} mag",
            transform=ax.transAxes, ha="left", va="top", fontsize=7, color="0.25")
    return ax


def ratios_figure(kind: str, completeness: BinnedCurve | None, purity: BinnedCurve | None, *,
                  completeness_posterior: PosteriorBand | None = None, purity_posterior: PosteriorBand | None = None,
                  depth=(), notes: dict | None = None):
    """Completeness (left) and purity (right) of one source kind, each over the width of its bands.

    The lower panels show the width of the 68% and 95% posterior bands
    (:func:`band_width_panel`) on their own scale: on a well-measured run the bands are far narrower
    than the 0-1 axis of the upper panels shows.  The legends sit below the panels (outside the data);
    ``notes`` maps ``"completeness"``/``"purity"`` to a short text written as the legend's title
    (e.g. why there is no posterior curve).

    Returns
    -------
    matplotlib.figure.Figure
    """
    fig = new_figure((12.0, 6.4))
    grid = fig.add_gridspec(2, 2, height_ratios=[3.2, 1.0])
    posts = {"completeness": completeness_posterior, "purity": purity_posterior}
    curves = {"completeness": completeness, "purity": purity}
    for col, key in enumerate(("completeness", "purity")):
        ax = fig.add_subplot(grid[0, col])
        ratio_curve(curves[key], posterior=posts[key], depth=depth, quantity=key, ax=ax, legend=False)
        ax.set_title(f"{kind}: {key}")
        ax.set_xlabel("")
        low = fig.add_subplot(grid[1, col], sharex=ax)
        if posts[key] is not None:
            band_width_panel(posts[key], ax=low)
        else:
            low.set_yticks([])
            low.text(0.5, 0.5, "no posterior bands", transform=low.transAxes, ha="center", va="center",
                     fontsize=8, color="0.4")
        low.set_xlabel(_XLABEL[key])
        text = (notes or {}).get(key)
        handles, labels = ax.get_legend_handles_labels()
        if handles or text:
            outside_legend(low, handles, labels, title=textwrap.fill(text, 70) if text else None)
    return fig


def magnitude_comparison(true_mag, measured_mag, *, ax=None, bins: int = 60, label: str | None = None,
                         true_range=None):
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
    true_range : (lo, hi), optional
        The injected magnitude range: both axes span at least it, so the faint injections that
        were rarely recovered still show (default: the 0.2-99.8 percentiles of the pairs).

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
        if true_range is not None:
            lo = min(lo, float(true_range[0]) - 0.2)
            hi = max(hi, float(true_range[1]) + 0.2)
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
        outside_legend(ax)
    ax.set_xlabel("true magnitude (mag)")
    ax.set_ylabel("measured magnitude (mag)")
    if label:
        ax.set_title(label)
    return ax


def magnitude_comparison_figure(pairs: dict, *, measured_label: str = "MAG_AUTO", ranges: dict | None = None):
    """One :func:`magnitude_comparison` panel per kind: ``pairs = {kind: (true_mag, measured_mag)}``.

    ``ranges`` maps a kind to its injected magnitude range (the axes span it).

    Returns
    -------
    matplotlib.figure.Figure
    """
    n = max(1, len(pairs))
    fig = new_figure((5.4 * n, 5.4))
    axes = np.atleast_1d(fig.subplots(1, n))
    for ax, (kind, (t, m)) in zip(axes, pairs.items()):
        magnitude_comparison(t, m, ax=ax, label=f"{kind}: recovered injections",
                             true_range=(ranges or {}).get(kind))
        ax.set_ylabel(f"measured magnitude, {measured_label} (mag)")
    return fig
