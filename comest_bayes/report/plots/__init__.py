"""Figures of a run (matplotlib).

Modules by topic; every plotting function takes plain arrays or the small data
containers of :mod:`comest_bayes.report.plots.data`, draws into the ``ax=`` it is given
(or into a new figure when ``ax`` is None) and returns the Axes (or the Figure
for multi-panel figures).  None of them reads or writes files: the readers of a
run directory live in :mod:`comest_bayes.report.rundata`, and
:mod:`comest_bayes.report.html` assembles the figures into the HTML report.

=================================  ===============================================
module                             figures
=================================  ===============================================
:mod:`~.images`                    image cutouts with detections, injections,
                                   missed injections and false detections marked
                                   (ComEst paper, Figure 3)
:mod:`~.completeness`              completeness and purity versus magnitude
                                   (binned points, posterior bands, depth lines);
                                   measured versus true magnitude
:mod:`~.maps`                      binned completeness / purity maps, m50(x, y)
:mod:`~.diagnostics`               model-selection comparison, autocorrelation
                                   times, traces
=================================  ===============================================

Figures are made with :class:`matplotlib.figure.Figure` directly (no pyplot
state), so they can be drawn in worker threads and never open a window.
"""

from __future__ import annotations

from pathlib import Path

from matplotlib.figure import Figure

__all__ = ["new_axes", "new_figure", "save_figure", "figure_png", "COLORS"]

#: Colours used across figures (colour-blind-safe Okabe-Ito palette), by role.
COLORS = {
    "detection": "#E69F00",   # orange: detections on the observed image
    "recovered": "#00D084",   # green: recovered injections
    "missed": "#FF3B30",      # red: missed injections
    "false": "#FFD60A",       # yellow: false detections
    "binned": "#000000",      # binned ratios
    "posterior": "#0072B2",   # posterior median and bands
    "depth": ("#D55E00", "#CC79A7", "#009E73", "#56B4E9"),
    "kinds": ("#0072B2", "#D55E00", "#009E73", "#CC79A7", "#E69F00"),
}


def new_figure(figsize=(6.4, 4.8)) -> Figure:
    """A new Figure with constrained layout (not registered with pyplot)."""
    return Figure(figsize=figsize, layout="constrained")


def new_axes(ax=None, figsize=(6.4, 4.8)):
    """``ax`` itself, or the single Axes of a new :func:`new_figure`.

    Returns
    -------
    matplotlib.axes.Axes
    """
    if ax is not None:
        return ax
    return new_figure(figsize).subplots()


def figure_png(fig: Figure, dpi: int = 110) -> bytes:
    """The figure as PNG bytes."""
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    return buf.getvalue()


def save_figure(fig: Figure, stem, *, dpi: int = 150, formats=("png", "pdf")) -> list[Path]:
    """Write ``stem.png`` and ``stem.pdf`` atomically; returns the paths written."""
    from comest_bayes.io.rundir import atomic_path

    stem = Path(stem)
    stem.parent.mkdir(parents=True, exist_ok=True)
    out = []
    for fmt in formats:
        path = stem.with_name(f"{stem.name}.{fmt}")
        with atomic_path(path) as tmp:
            fig.savefig(tmp, format=fmt, dpi=dpi)
        out.append(path)
    return out
