"""Image cutouts with sources marked, as in Figure 3 of Chiu, Desai & Liu (2016).

Three panels on one intensity scale: the observed image with its detections,
the source-free image, and one simulated image (injections on the source-free
image) with recovered injections, missed injections and false detections
marked differently.  The stretch is the asinh stretch of
:mod:`astropy.visualization` over the zscale interval of the observed cutout.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from comest_bayes.report.plots import COLORS, new_axes, new_figure
from comest_bayes.report.plots.data import Cutout
from comest_bayes.report.plots.completeness import outside_legend

__all__ = ["choose_region", "cut", "image_norm", "show_cutout", "mark", "Markers", "figure3"]


def choose_region(shape, size: int = 400, center=None) -> tuple[int, int, int, int]:
    """A square region of side ``size`` pixels, clipped to the image.

    Parameters
    ----------
    shape : (ny, nx)
        Image shape.
    size : int
        Side, pixels (default 400; smaller images give their whole extent).
    center : (x, y), optional
        0-based pixel centre (default the image centre).

    Returns
    -------
    (x0, x1, y0, y1) : int
        Slice bounds: the region is ``image[y0:y1, x0:x1]``.
    """
    ny, nx = int(shape[0]), int(shape[1])
    sx, sy = min(int(size), nx), min(int(size), ny)
    cx, cy = ((nx - 1) / 2.0, (ny - 1) / 2.0) if center is None else (float(center[0]), float(center[1]))
    x0 = int(np.clip(round(cx - sx / 2.0), 0, nx - sx))
    y0 = int(np.clip(round(cy - sy / 2.0), 0, ny - sy))
    return x0, x0 + sx, y0, y0 + sy


def cut(image: np.ndarray, region, mask: np.ndarray | None = None) -> Cutout:
    """The ``region`` (from :func:`choose_region`) of ``image``; masked pixels become NaN."""
    x0, x1, y0, y1 = region
    data = np.array(image[y0:y1, x0:x1], dtype=float)
    if mask is not None:
        data[np.asarray(mask[y0:y1, x0:x1], bool)] = np.nan
    return Cutout(data=data, x0=x0, y0=y0)


def image_norm(data: np.ndarray, *, stretch: str = "asinh", a: float = 0.1):
    """An :class:`astropy.visualization.ImageNormalize`: zscale interval of ``data``, then the stretch.

    Parameters
    ----------
    data : ndarray
        Pixels the interval is computed from (NaN ignored).
    stretch : {"asinh", "linear", "sqrt", "log"}
    a : float
        Parameter of the asinh stretch (smaller: more compression of bright values).
    """
    from astropy.visualization import (AsinhStretch, ImageNormalize, LinearStretch, LogStretch, SqrtStretch,
                                       ZScaleInterval)

    stretches = {"asinh": lambda: AsinhStretch(a), "linear": LinearStretch, "sqrt": SqrtStretch,
                 "log": LogStretch}
    if stretch not in stretches:
        raise ValueError(f"stretch {stretch!r} is not one of {sorted(stretches)}")
    finite = np.asarray(data, float)
    finite = finite[np.isfinite(finite)]
    if finite.size == 0:
        finite = np.zeros(1)
    vmin, vmax = ZScaleInterval().get_limits(finite)
    if not vmax > vmin:
        vmin, vmax = float(finite.min()), float(finite.max()) + 1e-12
    # zscale clips bright sources hard; widen the top so the asinh stretch shows their cores
    vmax = vmin + 4.0 * (vmax - vmin)
    return ImageNormalize(vmin=vmin, vmax=vmax, stretch=stretches[stretch](), clip=True)


def show_cutout(cutout: Cutout, *, ax=None, norm=None, title: str | None = None, cmap: str = "gray"):
    """Draw a cutout in image pixel coordinates; masked (NaN) pixels in dark blue.

    Returns
    -------
    matplotlib.axes.Axes
    """
    import matplotlib

    ax = new_axes(ax, (5.0, 5.0))
    norm = norm if norm is not None else image_norm(cutout.data)
    cm = matplotlib.colormaps[cmap].with_extremes(bad="#1f2a44")
    ax.imshow(np.ma.masked_invalid(cutout.data), origin="lower", cmap=cm, norm=norm, extent=cutout.extent,
              interpolation="nearest")
    ax.set_xlabel("x (pixel)")
    ax.set_ylabel("y (pixel)")
    if title:
        ax.set_title(title)
    return ax


@dataclass
class Markers:
    """Positions to mark on a cutout, with their legend label and style.

    ``role`` picks the style: ``detection``, ``recovered``, ``missed`` or
    ``false`` (see :data:`comest_bayes.report.plots.COLORS`).
    """

    x: np.ndarray
    y: np.ndarray
    label: str
    role: str


_STYLE = {
    "detection": dict(marker="o", s=70, facecolors="none", linewidths=1.0),
    "recovered": dict(marker="o", s=70, facecolors="none", linewidths=1.2),
    "missed": dict(marker="s", s=70, facecolors="none", linewidths=1.2),
    "false": dict(marker="D", s=60, facecolors="none", linewidths=1.2),
}


def mark(ax, cutout: Cutout, markers: Markers):
    """Mark the positions of ``markers`` that fall in ``cutout``; the count goes into the label."""
    x, y = np.asarray(markers.x, float), np.asarray(markers.y, float)
    inside = cutout.contains(x, y)
    style = _STYLE[markers.role]
    ax.scatter(x[inside], y[inside], edgecolors=COLORS[markers.role], label=f"{markers.label} ({int(inside.sum())})",
               **style)
    return ax


def _legend(ax):
    """The markers' legend under the panel: over the image it hid the markers of its corner."""

    outside_legend(ax, ncol=2)


def figure3(observed: Cutout | None, sourcefree: Cutout, simulated: Cutout, *, detections: Markers,
            recovered: Markers, missed: Markers, false: Markers, sim_title: str = "simulated image",
            stretch: str = "asinh"):
    """Observed, source-free and simulated cutouts side by side, sources marked.

    All three panels share the intensity scale of the observed cutout (zscale
    interval, ``stretch``), so the source-free and simulated images compare
    with the observed one directly.

    Parameters
    ----------
    observed, sourcefree, simulated : Cutout
        The same region of the three images; ``observed`` may be None (its
        panel is then left blank and the scale is the source-free image's).
    detections : Markers
        Detections on the observed image.
    recovered, missed, false : Markers
        On the simulated image: injections matched to a detection (at their true
        positions), injections not detected (true positions), and false detections
        (measured positions).
    sim_title : str
        Title of the third panel.

    Returns
    -------
    matplotlib.figure.Figure
    """
    fig = new_figure((15.0, 6.0))  # room for the legends under the panels
    axes = fig.subplots(1, 3, sharex=True, sharey=True)
    reference = observed if observed is not None else sourcefree
    norm = image_norm(reference.data, stretch=stretch)
    if observed is not None:
        show_cutout(observed, ax=axes[0], norm=norm, title="observed image")
    else:
        show_cutout(Cutout(np.full(sourcefree.data.shape, np.nan), sourcefree.x0, sourcefree.y0), ax=axes[0],
                    norm=norm, title="observed image (not available)")
    mark(axes[0], reference, detections)
    show_cutout(sourcefree, ax=axes[1], norm=norm, title="source-free image")
    show_cutout(simulated, ax=axes[2], norm=norm, title=sim_title)
    for m in (recovered, missed, false):
        mark(axes[2], simulated, m)
    _legend(axes[0])
    _legend(axes[2])
    for ax in axes[1:]:
        ax.set_ylabel("")
    ext = reference.extent
    axes[0].set_xlim(ext[0], ext[1])
    axes[0].set_ylim(ext[2], ext[3])
    return fig
