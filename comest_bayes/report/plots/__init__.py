"""Figures of a run (matplotlib), in modules by topic: images, completeness, maps, diagnostics, lf.

Every plotting function takes plain arrays or the containers of
:mod:`comest_bayes.report.plots.data`, draws into ``ax=`` (or a new figure) and returns the Axes
(or the Figure); none reads or writes files.  The modules and their figures: ``docs/usage.md``
("The report").
"""

from __future__ import annotations

from pathlib import Path

from matplotlib.figure import Figure
from comest_bayes.io.rundir import atomic_path

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

    stem = Path(stem)
    stem.parent.mkdir(parents=True, exist_ok=True)
    out = []
    for fmt in formats:
        path = stem.with_name(f"{stem.name}.{fmt}")
        with atomic_path(path) as tmp:
            fig.savefig(tmp, format=fmt, dpi=dpi)
        out.append(path)
    return out
