"""Fourier transforms of the unit ``buldisk`` profile and the shear and WCS algebra that let
:mod:`comest_bayes.inject.render` draw ``point`` and ``buldisk`` stamps in NumPy batches
(``docs/sources.md``, "Fourier transforms for batched drawing").
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache
import galsim
import numpy as np
from comest_bayes.inject.profiles import growth_curve, unit_exponential, unit_sersic

__all__ = ['BATCHED_KINDS', 'DEV_K_STEP', 'RadialKTable', 'devaucouleurs_k_table', 'exponential_k', 'buldisk_k', 'buldisk_radius_per_hlr', 'shear_matrices', 'kspace_quadratic_forms']


# --------------------------------------------------------------------------- Fourier transforms (batched drawing)

#: Kinds whose stamps are drawn in batches from the transforms below (others: one GalSim call each).
BATCHED_KINDS = ("point", "buldisk")
#: Grid step of the tabulated de Vaucouleurs transform, in inverse half-light radii.
DEV_K_STEP = 0.0025
#: The table always reaches at least this |k| (inverse half-light radii); larger on demand.
_DEV_K_MIN_EXTENT = 64.0


@dataclass(frozen=True)
class RadialKTable:
    """A radial Fourier transform tabulated on a uniform grid, interpolated linearly.

    Attributes
    ----------
    step : float
        Grid step in ``|k|``.
    values : ndarray of float64, shape (m,)
        ``F(i * step)`` for ``i = 0 .. m-1``.
    """

    step: float
    values: np.ndarray = field(repr=False)

    @property
    def kmax(self) -> float:
        """Largest ``|k|`` the table covers."""
        return self.step * (self.values.size - 1)

    def __call__(self, k: np.ndarray) -> np.ndarray:
        """``F(k)`` by linear interpolation; ``k`` must lie in ``[0, kmax]`` (any shape)."""
        x = np.multiply(k, 1.0 / self.step)
        i = x.astype(np.intp)
        np.minimum(i, self.values.size - 2, out=i)
        x -= i  # fractional part
        lo = self.values[i]
        hi = self.values[i + 1]
        hi -= lo
        hi *= x
        hi += lo
        return hi


@lru_cache(maxsize=4)
def _dev_k_table(kmax: float) -> RadialKTable:
    m = int(np.ceil(kmax / DEV_K_STEP)) + 2
    kimage = galsim.ImageCD(galsim.BoundsI(0, m - 1, 0, 0), scale=DEV_K_STEP)  # kx = i * step, ky = 0
    unit_sersic(4.0, True).drawKImage(image=kimage, recenter=False)
    values = np.ascontiguousarray(kimage.array[0].real, dtype=np.float64)
    values.setflags(write=False)
    return RadialKTable(DEV_K_STEP, values)


def devaucouleurs_k_table(kmax: float = _DEV_K_MIN_EXTENT) -> RadialKTable:
    """Radial Fourier transform of the unit ``buldisk`` bulge, tabulated from GalSim.

    The bulge is our de Vaucouleurs profile (:func:`bulge_disk_components`:
    truncated at :data:`TRUNC_HLR` half-light radii) with half-light radius 1
    and flux 1; its transform is real and depends on ``|k|`` only.  Tables are
    built once per process for extents rounded up to a power of two times
    64 (about 14 ms and 200 kB for the smallest).

    Parameters
    ----------
    kmax : float
        Largest ``|k|`` needed, in inverse half-light radii.

    Returns
    -------
    RadialKTable
        Step :data:`DEV_K_STEP`, extent >= ``kmax``.
    """
    extent = _DEV_K_MIN_EXTENT
    while extent < kmax:
        extent *= 2.0
    return _dev_k_table(extent)


def exponential_k(ksq: np.ndarray) -> np.ndarray:
    """Fourier transform of the unit-flux exponential disk of half-light radius 1.

    ``(1 + ksq r_s^2)^(-3/2)`` with ``r_s`` GalSim's scale radius of
    :class:`galsim.Exponential` (half_light_radius=1).

    Parameters
    ----------
    ksq : ndarray
        Squared wavenumbers ``|k|^2`` in inverse half-light radii squared (any shape).

    Returns
    -------
    ndarray of float64, same shape
    """
    r_s = unit_exponential().scale_radius
    t = np.multiply(ksq, r_s * r_s)
    t += 1.0
    root = np.sqrt(t)
    t *= root
    return np.reciprocal(t, out=t)


def buldisk_k(ksq: np.ndarray, bulge_fraction, table: RadialKTable | None = None) -> np.ndarray:
    """Fourier transform of a circular unit ``buldisk`` source (half-light radius 1, flux 1).

    ``B F_deV(k) + (1 - B) F_exp(k)`` (see ``docs/sources.md``).

    Parameters
    ----------
    ksq : ndarray
        ``|k|^2`` in inverse half-light radii squared, any shape broadcasting
        against ``bulge_fraction``.
    bulge_fraction : float or ndarray
        Bulge flux fraction ``B`` in [0, 1].
    table : RadialKTable, optional
        De Vaucouleurs table (:func:`devaucouleurs_k_table`); built to cover
        ``ksq`` when not given.

    Returns
    -------
    ndarray of float64, the broadcast shape
    """
    ksq = np.asarray(ksq, dtype=float)
    bulge_fraction = np.asarray(bulge_fraction, dtype=float)
    shape = np.broadcast_shapes(ksq.shape, bulge_fraction.shape)
    if ksq.shape != shape:
        ksq = np.broadcast_to(ksq, shape)
    kmax = float(np.sqrt(ksq.max())) if ksq.size else 0.0
    if table is None or table.kmax < kmax:
        table = devaucouleurs_k_table(kmax)
    disk = exponential_k(ksq)
    bulge = table(np.sqrt(ksq))
    # B F_deV + (1 - B) F_exp = F_exp + B (F_deV - F_exp), in place
    bulge -= disk
    bulge *= bulge_fraction
    bulge += disk
    return bulge


def buldisk_radius_per_hlr(bulge_fraction, fraction: float = 0.995) -> np.ndarray:
    """Radius enclosing ``fraction`` of circular bulge + disk sources, in half-light radii.

    The same numbers as the scalar helper behind :func:`source_profile` (the
    first radius of a 0.01-step grid where the combined growth curve reaches
    ``fraction``), for many bulge fractions at once.

    Parameters
    ----------
    bulge_fraction : array_like, shape (n,)
        Bulge flux fractions in [0, 1].
    fraction : float
        Enclosed flux fraction in (0, 1).

    Returns
    -------
    ndarray, shape (n,)
    """
    bf = np.atleast_1d(np.asarray(bulge_fraction, dtype=float))
    x, fb = growth_curve(4.0)
    _, fd = growth_curve(1.0)
    # vectorised binary search for the first index with bf * fb + (1 - bf) * fd >= fraction: the
    # combined curve is non-decreasing, so this is np.searchsorted(combined, fraction) per source
    lo = np.zeros(bf.shape, dtype=np.intp)
    hi = np.full(bf.shape, x.size, dtype=np.intp)
    while True:
        active = lo < hi
        if not active.any():
            break
        mid = (lo + hi) // 2
        midc = np.minimum(mid, x.size - 1)
        below = (bf * fb[midc] + (1.0 - bf) * fd[midc]) < fraction
        lo = np.where(active & below, mid + 1, lo)
        hi = np.where(active & ~below, mid, hi)
    return x[np.minimum(lo, x.size - 1)]


def shear_matrices(q, pa_deg) -> np.ndarray:
    """GalSim's shear matrices for axis ratios ``q`` and position angles ``pa_deg``.

    ``galsim.Shear(q=q, beta=pa_deg * degrees).getMatrix()``:
    ``(1 - g^2)^(-1/2) [[1 + g1, g2], [g2, 1 - g1]]`` with
    ``g = (1 - q) / (1 + q)``, ``g1 = g cos 2 beta``, ``g2 = g sin 2 beta``
    (area-preserving, symmetric).

    Parameters
    ----------
    q, pa_deg : array_like, shape (n,)
        Axis ratio in (0, 1] and angle in degrees.

    Returns
    -------
    ndarray, shape (n, 2, 2)
    """
    q = np.atleast_1d(np.asarray(q, dtype=float))
    beta = np.deg2rad(np.atleast_1d(np.asarray(pa_deg, dtype=float)))
    g = (1.0 - q) / (1.0 + q)
    g1, g2 = g * np.cos(2.0 * beta), g * np.sin(2.0 * beta)
    norm = 1.0 / np.sqrt(1.0 - g * g)
    out = np.empty(q.shape + (2, 2))
    out[:, 0, 0] = norm * (1.0 + g1)
    out[:, 1, 1] = norm * (1.0 - g1)
    out[:, 0, 1] = out[:, 1, 0] = norm * g2
    return out


def kspace_quadratic_forms(hlr_arcsec, q, pa_deg, jacobians) -> np.ndarray:
    """Quadratic forms giving each source's unit-profile ``|k|^2`` from pixel wavenumbers.

    A source of half-light radius ``r``, shear ``S`` (:func:`shear_matrices`)
    mapped to pixels by the local Jacobian ``J`` (arcsec per pixel, see
    :func:`comest_bayes.inject.render.local_jacobians`) has the transform
    ``flux F_unit(M k)`` with ``M = r S J^-T`` and ``k`` in radians per pixel.
    Returns ``Q = M^T M``, so that ``|M k|^2 = k^T Q k``.

    Parameters
    ----------
    hlr_arcsec, q, pa_deg : array_like, shape (n,)
        Circularised half-light radius (arcsec), axis ratio, position angle (deg).
    jacobians : ndarray, shape (n, 2, 2)
        Local pixel-to-world Jacobians, arcsec per pixel.

    Returns
    -------
    ndarray, shape (n, 2, 2)
        Symmetric positive definite, in pixels squared.
    """
    hlr = np.atleast_1d(np.asarray(hlr_arcsec, dtype=float))
    shear = shear_matrices(q, pa_deg)
    jinv_t = np.linalg.inv(np.asarray(jacobians, dtype=float)).transpose(0, 2, 1)
    m = hlr[:, None, None] * (shear @ jinv_t)
    return m.transpose(0, 2, 1) @ m
