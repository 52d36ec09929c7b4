"""Maps over the image: binned completeness and purity at chosen magnitudes, the posterior m50(x, y).

Maps are drawn in image pixel coordinates (x, y, 0-based, pixel centres at
integers), one map cell covering ``bin_pix`` x ``bin_pix`` image pixels; cells
without data (no injections, masked) are grey.
"""

from __future__ import annotations

import numpy as np

from comest_bayes.report.plots import new_axes, new_figure
from comest_bayes.report.plots.data import MapPlane

__all__ = ["value_map", "ratio_map", "ratio_maps_figure", "m50_map_figure"]

_EMPTY = "#bdbdbd"


def value_map(values: np.ndarray, bin_pix: float, *, ax=None, cmap: str = "viridis", vmin=None, vmax=None,
              colorbar_label: str | None = None, title: str | None = None, colorbar: bool = True):
    """Draw a binned map (shape (gy, gx)) over the image's pixel frame.

    Returns
    -------
    matplotlib.axes.Axes
    """
    import matplotlib

    ax = new_axes(ax, (5.2, 4.6))
    values = np.asarray(values, float)
    gy, gx = values.shape
    cm = matplotlib.colormaps[cmap].with_extremes(bad=_EMPTY)
    im = ax.imshow(np.ma.masked_invalid(values), origin="lower", cmap=cm, vmin=vmin, vmax=vmax,
                   extent=(-0.5, gx * bin_pix - 0.5, -0.5, gy * bin_pix - 0.5), interpolation="nearest")
    ax.set_xlabel("x (pixel)")
    ax.set_ylabel("y (pixel)")
    if title:
        ax.set_title(title, fontsize=10)
    if colorbar:
        ax.figure.colorbar(im, ax=ax, label=colorbar_label, shrink=0.9)
    return ax


def ratio_map(plane: MapPlane, *, ax=None, quantity: str = "completeness", colorbar: bool = True):
    """One magnitude plane of a completeness or purity map, on the fixed scale 0-1.

    Returns
    -------
    matplotlib.axes.Axes
    """
    rng = "" if not np.isfinite(plane.mag_lo) else f"{plane.mag_lo:.2f} < m < {plane.mag_hi:.2f}"
    return value_map(plane.values, plane.bin_pix, ax=ax, cmap="viridis", vmin=0.0, vmax=1.0,
                     colorbar_label=quantity, title=f"{quantity}, {rng}" if rng else quantity, colorbar=colorbar)


def ratio_maps_figure(kind: str, completeness: list, purity: list | None = None, *, bin_arcmin: float | None = None):
    """Completeness (top row) and purity (bottom row) maps, one column per magnitude plane.

    Parameters
    ----------
    kind : str
        Source kind (titles).
    completeness, purity : list of MapPlane
        Planes in magnitude order; ``purity`` may be None or empty.
    bin_arcmin : float, optional
        Cell size, for the figure title.

    Returns
    -------
    matplotlib.figure.Figure
    """
    rows = [("completeness", completeness)] + ([("purity", purity)] if purity else [])
    ncol = max(len(completeness), len(purity or []), 1)
    fig = new_figure((3.6 * ncol + 1.0, 3.5 * len(rows) + 0.4))
    axes = np.atleast_2d(fig.subplots(len(rows), ncol, squeeze=False))
    for r, (quantity, planes) in enumerate(rows):
        for c in range(ncol):
            ax = axes[r, c]
            if c >= len(planes):
                ax.set_visible(False)
                continue
            ratio_map(planes[c], ax=ax, quantity=quantity, colorbar=False)
            if c:
                ax.set_ylabel("")
        fig.colorbar(axes[r, 0].images[0], ax=list(axes[r, :len(planes)]), label=quantity, shrink=0.9)
    title = f"{kind}: binned maps"
    if bin_arcmin:
        title += (f" ({bin_arcmin:g}' cells; grey: no injections" + ("; in the purity row, no detections" if purity
                                                                     else "") + ")")
    fig.suptitle(title)
    return fig


def m50_map_figure(kind: str, median: np.ndarray, sd: np.ndarray, bin_pix: float, *, model: str | None = None):
    """Posterior median of m50(x, y) and its standard deviation, side by side.

    Parameters
    ----------
    median, sd : ndarray, shape (gy, gx)
        Posterior median and standard deviation of m50 per cell, mag.
    bin_pix : float
        Cell side, image pixels.
    model : str, optional
        Model name for the title.

    Returns
    -------
    matplotlib.figure.Figure
    """
    fig = new_figure((11.0, 4.6))
    axes = fig.subplots(1, 2)
    value_map(median, bin_pix, ax=axes[0], cmap="magma", colorbar_label="m50 (mag)",
              title=f"{kind}: posterior median of m50(x, y)")
    value_map(sd, bin_pix, ax=axes[1], cmap="cividis", colorbar_label="standard deviation of m50 (mag)",
              title=f"{kind}: posterior uncertainty of m50(x, y)")
    if model:
        fig.suptitle(f"model {model}")
    return fig
