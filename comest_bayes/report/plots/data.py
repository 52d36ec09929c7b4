"""Small typed containers the plotting functions take (no I/O here).

They hold exactly what a figure needs, so the figures can be drawn from a run
directory (:mod:`comest_bayes.report.rundata` builds them) or from arrays a user
has in hand.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["BinnedCurve", "PosteriorBand", "DepthLine", "Cutout", "MapPlane", "ChainSamples"]


def _arr(values) -> np.ndarray:
    """Float array with ``None`` read as NaN."""
    return np.array([np.nan if v is None else v for v in np.ravel(np.asarray(values, dtype=object))], dtype=float)


@dataclass
class BinnedCurve:
    """A binned ratio (completeness, purity) with its binomial interval.

    Attributes
    ----------
    centers : ndarray, shape (B,)
        Bin centres, mag.
    ratio, lower, upper : ndarray, shape (B,)
        Ratio and its interval bounds; NaN in empty bins.
    n : ndarray, shape (B,)
        Trials per bin (0 for an empty bin).
    confidence : float
        Probability content of the interval (default 0.6827).
    interval : str
        Interval method (e.g. ``"wilson"``).
    """

    centers: np.ndarray
    ratio: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    n: np.ndarray
    confidence: float = 0.6827
    interval: str = "wilson"

    @classmethod
    def from_summary(cls, binned: dict, quantity: str) -> "BinnedCurve":
        """From the ``binned`` entry of a kind in ``summary.json`` (``quantity``: completeness or purity)."""
        return cls(centers=_arr(binned["mag_centers"]), ratio=_arr(binned[quantity]),
                   lower=_arr(binned[f"{quantity}_lower"]), upper=_arr(binned[f"{quantity}_upper"]),
                   n=np.asarray(binned.get(f"{quantity}_n", np.zeros(len(binned["mag_centers"]))), dtype=float),
                   confidence=float(binned.get("confidence", 0.6827)), interval=str(binned.get("interval", "")))


@dataclass
class PosteriorBand:
    """Posterior median curve with its central 68% and 95% bands.

    Attributes
    ----------
    mag : ndarray, shape (M,)
        Magnitude grid, mag.
    median, lo68, hi68, lo95, hi95 : ndarray, shape (M,)
        Percentiles 50, 16, 84, 2.5 and 97.5 of f(m) over posterior draws.
    label : str
        Legend text (e.g. the model name).
    """

    mag: np.ndarray
    median: np.ndarray
    lo68: np.ndarray
    hi68: np.ndarray
    lo95: np.ndarray
    hi95: np.ndarray
    label: str = "posterior"

    @classmethod
    def from_dict(cls, curve: dict, label: str = "posterior") -> "PosteriorBand":
        """From a ``curve`` dict (``mag``, ``median``, ``lo68``, ``hi68``, ``lo95``, ``hi95``)."""
        return cls(*(_arr(curve[k]) for k in ("mag", "median", "lo68", "hi68", "lo95", "hi95")), label=label)


@dataclass
class DepthLine:
    """A reference magnitude drawn as a vertical line (e.g. the 5-sigma depth)."""

    mag: float
    label: str


@dataclass
class Cutout:
    """A rectangular piece of an image and where it sits.

    Attributes
    ----------
    data : ndarray, shape (ny, nx)
        Pixel values (NaN where masked, if the caller wants them blank).
    x0, y0 : int
        0-based image pixel of ``data[0, 0]``.
    """

    data: np.ndarray
    x0: int = 0
    y0: int = 0

    @property
    def extent(self) -> tuple:
        """``imshow`` extent in image pixel coordinates (pixel centres at integers)."""
        ny, nx = self.data.shape
        return (self.x0 - 0.5, self.x0 + nx - 0.5, self.y0 - 0.5, self.y0 + ny - 0.5)

    def contains(self, x, y) -> np.ndarray:
        """Which of the positions ``x, y`` (0-based image pixels) fall inside the cutout."""
        ny, nx = self.data.shape
        x, y = np.asarray(x, float), np.asarray(y, float)
        return (x >= self.x0 - 0.5) & (x < self.x0 + nx - 0.5) & (y >= self.y0 - 0.5) & (y < self.y0 + ny - 0.5)


@dataclass
class MapPlane:
    """One magnitude plane of a binned map.

    Attributes
    ----------
    values : ndarray, shape (gy, gx)
        Ratio per spatial bin (NaN where empty).
    bin_pix : float
        Side of a bin, image pixels (bin ``(j, i)`` covers x in
        ``[i b, (i+1) b)`` and y in ``[j b, (j+1) b)``, 0-based, pixel edges
        at half-integers).
    mag_lo, mag_hi : float
        Magnitude range of the plane (NaN when not binned in magnitude).
    n : ndarray or None, shape (gy, gx)
        Trials per bin.
    """

    values: np.ndarray
    bin_pix: float
    mag_lo: float = float("nan")
    mag_hi: float = float("nan")
    n: np.ndarray | None = None

    @property
    def extent(self) -> tuple:
        gy, gx = self.values.shape
        return (-0.5, gx * self.bin_pix - 0.5, -0.5, gy * self.bin_pix - 0.5)


@dataclass
class ChainSamples:
    """Post-burn-in emcee draws of physical parameters, walker by walker.

    Attributes
    ----------
    values : ndarray, shape (T, W, P)
        ``T`` kept steps of ``W`` walkers for ``P`` parameters.
    names : list of str
        Parameter names (length P).
    burn : int
        Steps discarded before the first kept one.
    tau : ndarray, shape (P,) or None
        Integrated autocorrelation times of the parameters, steps.
    """

    values: np.ndarray
    names: list
    burn: int = 0
    tau: np.ndarray | None = field(default=None)
