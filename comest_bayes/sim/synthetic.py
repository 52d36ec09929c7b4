"""Known completeness truths, synthetic outcome tables, and the binned estimate, for validation.

The numerical half of the honesty benchmark (``benchmarks/bench_honesty.py``): outcome tables
drawn from a known completeness function on a synthetic detection-noise field (:class:`Scene`,
:data:`TRUTHS`, :func:`draw_outcomes`, :func:`truth_curve`).  Plain numpy, seeded.  Scene, depth
covariate, truths and pixels: ``docs/bayesian.md`` ("Calibration").
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from functools import cached_property

import numpy as np
from astropy.table import Table

from comest_bayes.ratios import binned as R
from comest_bayes.errors import InputError
from comest_bayes.seeding import rng_for

__all__ = [
    "Scene",
    "make_scene",
    "Truth",
    "LogisticTruth",
    "GumbelTruth",
    "InverseFluxTruth",
    "LongTailTruth",
    "TwoPopulationTruth",
    "StudentTruth",
    "VaryingWidthTruth",
    "LogPlaneWidthTruth",
    "RadialWidthTruth",
    "TRUTHS",
    "get_truth",
    "draw_outcomes",
    "truth_curve",
    "truth_quantities",
    "BinnedEstimate",
    "binned_estimate",
    "PROBE_OFFSET",
]

#: The probe magnitudes of :func:`truth_quantities` are the image-average m50 -/+ this (mag).
PROBE_OFFSET = 0.3
#: Largest number of (pixel, magnitude) values evaluated at once by :func:`truth_curve`.
_CHUNK_ELEMENTS = 2_000_000
#: Root-finding tolerance of :func:`truth_quantities`, mag.
_XTOL = 1e-10


# --------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------

def _expit(x):
    """Logistic function 1 / (1 + exp(-x)), overflow-free (via tanh)."""
    return 0.5 * (1.0 + np.tanh(0.5 * np.asarray(x, dtype=float)))


def _logit(p: float) -> float:
    return math.log(p / (1.0 - p))


def _check_seed(seed) -> int:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InputError(f"seed must be a non-negative integer, got {seed!r}.")
    return int(seed)


def _check_range(mag_range, name="mag_range") -> tuple[float, float]:
    try:
        lo, hi = (float(v) for v in mag_range)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a pair (bright, faint) of magnitudes, got {mag_range!r}.") from None
    if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
        raise InputError(f"{name} = ({lo!r}, {hi!r}) must be finite with bright < faint.")
    return lo, hi


# --------------------------------------------------------------------------
# scene
# --------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class Scene:
    """A synthetic image footprint: detection-noise map and mask.

    Attributes
    ----------
    shape : (int, int)
        ``(ny, nx)`` of the image.
    noise : ndarray of float, shape ``shape``
        Detection noise sigma per pixel (image units, finite and positive
        everywhere, masked pixels included).
    mask : ndarray of bool, shape ``shape``
        True where the pixel is masked (no injection lands there).

    Notes
    -----
    The arrays are made read-only.  Derived quantities (:attr:`sigma_ref`,
    :attr:`depth`, :meth:`pixels`) are computed once and cached.
    """

    shape: tuple
    noise: np.ndarray = field(repr=False)
    mask: np.ndarray = field(repr=False)

    def __post_init__(self):
        try:
            shape = tuple(int(s) for s in self.shape)
        except (TypeError, ValueError):
            raise InputError(f"Scene shape must be (ny, nx), got {self.shape!r}.") from None
        if len(shape) != 2 or min(shape) < 2:
            raise InputError(f"Scene shape must be (ny, nx) with both >= 2, got {self.shape!r}.")
        noise = np.array(self.noise, dtype=float)
        mask = np.array(self.mask)
        if noise.shape != shape or mask.shape != shape:
            raise InputError(f"noise {noise.shape} and mask {mask.shape} must both have the scene shape {shape}.")
        if mask.dtype != bool:
            raise InputError(f"mask must be boolean (True = masked), got dtype {mask.dtype}.")
        if not np.all(np.isfinite(noise) & (noise > 0)):
            raise InputError("noise must be finite and positive at every pixel (masked ones included).")
        if mask.all():
            raise InputError("the mask covers the whole scene: there is nowhere to inject.")
        noise.setflags(write=False)
        mask.setflags(write=False)
        object.__setattr__(self, "shape", shape)
        object.__setattr__(self, "noise", noise)
        object.__setattr__(self, "mask", mask)

    @cached_property
    def sigma_ref(self) -> float:
        """Median noise over the unmasked pixels: the reference of the truths' depth covariate."""
        return float(np.median(self.noise[~self.mask]))

    @cached_property
    def depth(self) -> np.ndarray:
        """Depth map ``d = -2.5 log10(noise / sigma_ref)`` (mag; positive = deeper), read-only."""
        d = -2.5 * np.log10(self.noise / self.sigma_ref)
        d.setflags(write=False)
        return d

    @property
    def masked_fraction(self) -> float:
        """Fraction of the pixels that are masked."""
        return float(self.mask.mean())

    def uv(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """Normalised coordinates ``u = 2 x / (nx - 1) - 1``, ``v = 2 y / (ny - 1) - 1`` of 0-based pixels."""
        ny, nx = self.shape
        return (2.0 * np.asarray(x, float) / (nx - 1) - 1.0, 2.0 * np.asarray(y, float) / (ny - 1) - 1.0)

    @cached_property
    def _unmasked(self) -> tuple:
        iy, ix = np.nonzero(~self.mask)
        u, v = self.uv(ix, iy)
        arrays = (iy, ix, self.depth[iy, ix], u, v)
        for a in arrays:
            a.setflags(write=False)
        return arrays

    def pixels(self, positions=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Depth and normalised coordinates of pixels.

        Parameters
        ----------
        positions : array_like, shape (P, 2), optional
            ``(x, y)`` 0-based pixel positions (rounded to the nearest pixel,
            as the package looks up the noise).  Default: every unmasked pixel.

        Returns
        -------
        d, u, v : ndarray, shape (P,)
        """
        if positions is None:
            _, _, d, u, v = self._unmasked
            return d, u, v
        pos = np.asarray(positions, dtype=float)
        if pos.ndim != 2 or pos.shape[1] != 2 or pos.shape[0] == 0 or not np.all(np.isfinite(pos)):
            raise InputError(f"positions must be a non-empty (P, 2) array of finite (x, y), got shape {pos.shape}.")
        ny, nx = self.shape
        ix = np.floor(pos[:, 0] + 0.5).astype(int)
        iy = np.floor(pos[:, 1] + 0.5).astype(int)
        if ix.min() < 0 or iy.min() < 0 or ix.max() >= nx or iy.max() >= ny:
            raise InputError(f"positions lie outside the scene of shape (ny, nx) = {self.shape}.")
        u, v = self.uv(ix, iy)
        return self.depth[iy, ix], u, v


def make_scene(shape=(512, 512), *, gradient: float = 0.6, chip_gap: bool = True, seed: int,
               gradient_angle: float = 90.0, smooth_rms: float = 0.05, n_blobs: int = 5,
               sigma0: float = 1.0) -> Scene:
    """A synthetic detection-noise map and mask with a smoothly varying depth.

    The depth (in mag, before referencing to the median) is::

        depth_raw(x, y) = gradient * p(x, y) + smooth(x, y)

    where ``p`` is the position along the direction ``gradient_angle``
    (degrees from the x axis; 90 = along y), scaled to run from -1/2 to +1/2
    between opposite corners or edges, so the linear part changes by exactly
    ``gradient`` mag end to end; ``smooth`` is a random sum of low-frequency
    cosines (0.5 to 1.5 cycles across the image, wavelengths of hundreds of
    pixels for the default shape) with an rms of ``smooth_rms`` mag.  The
    noise is ``sigma0 * 10**(-0.4 * depth_raw)``, so the scene's depth map
    ``-2.5 log10(noise / median)`` is ``depth_raw`` minus its median.

    Parameters
    ----------
    shape : (int, int)
        ``(ny, nx)``, at least 16 x 16.  The default 512 x 512 takes about 2 MB.
    gradient : float
        End-to-end depth change of the linear part, mag (>= 0).
    chip_gap : bool
        Mask a vertical strip of about 3% of the columns at the centre.
    seed : int
        Seed of the smooth component and the blobs.
    gradient_angle : float
        Direction of the gradient, degrees from the x axis (default 90: the
        depth changes along y, so it is not confounded with ``u``).
    smooth_rms : float
        rms of the random smooth depth component, mag (>= 0).
    n_blobs : int
        Number of masked discs ("bright stars"), radii 1-4% of the smaller side.
    sigma0 : float
        Noise scale, image units.

    Returns
    -------
    Scene
    """
    seed = _check_seed(seed)
    try:
        ny, nx = (int(s) for s in shape)
    except (TypeError, ValueError):
        raise InputError(f"shape must be (ny, nx), got {shape!r}.") from None
    if ny < 16 or nx < 16:
        raise InputError(f"shape must be at least (16, 16), got {shape!r}.")
    for name, val in (("gradient", gradient), ("smooth_rms", smooth_rms)):
        if not (np.isfinite(val) and val >= 0):
            raise InputError(f"{name} = {val!r} must be a finite non-negative number of magnitudes.")
    if not (np.isfinite(sigma0) and sigma0 > 0):
        raise InputError(f"sigma0 = {sigma0!r} must be a positive noise level.")
    if isinstance(n_blobs, bool) or not isinstance(n_blobs, (int, np.integer)) or n_blobs < 0:
        raise InputError(f"n_blobs = {n_blobs!r} must be a non-negative integer.")
    if not np.isfinite(gradient_angle):
        raise InputError(f"gradient_angle = {gradient_angle!r} must be a finite angle in degrees.")

    rng = rng_for(seed)
    xn = (np.arange(nx) / (nx - 1) - 0.5)[None, :]
    yn = (np.arange(ny) / (ny - 1) - 0.5)[:, None]
    c, s = math.cos(math.radians(gradient_angle)), math.sin(math.radians(gradient_angle))
    p = (c * xn + s * yn) / (abs(c) + abs(s))
    depth = gradient * p

    if smooth_rms > 0:
        smooth = np.zeros((ny, nx))
        for fx in (0.0, 0.5, 1.0, 1.5):
            for fy in (0.0, 0.5, 1.0, 1.5):
                if fx == 0.0 and fy == 0.0:
                    continue
                amp = rng.normal() / math.hypot(fx, fy)
                phase = rng.uniform(0.0, 2.0 * math.pi)
                smooth += amp * np.cos(2.0 * math.pi * (fx * xn + fy * yn) + phase)
        smooth -= smooth.mean()
        depth = depth + smooth * (smooth_rms / max(float(smooth.std()), 1e-300))
    noise = sigma0 * 10.0 ** (-0.4 * depth)

    mask = np.zeros((ny, nx), dtype=bool)
    if chip_gap:
        width = max(2, int(round(0.03 * nx)))
        start = nx // 2 - width // 2
        mask[:, start:start + width] = True
    yy, xx = np.mgrid[0:ny, 0:nx]
    side = min(ny, nx)
    for _ in range(int(n_blobs)):
        r = rng.uniform(0.01, 0.04) * side
        cx, cy = rng.uniform(0, nx - 1), rng.uniform(0, ny - 1)
        mask |= (xx - cx) ** 2 + (yy - cy) ** 2 <= r * r
    return Scene(shape=(ny, nx), noise=noise, mask=mask)


# --------------------------------------------------------------------------
# truths
# --------------------------------------------------------------------------

@dataclass(frozen=True)
class Truth:
    """A known completeness ``f = floor + (plateau - floor) * S(m - m50_0 - d; u, v)``.

    Subclasses define the transition :meth:`transition` (``S``: 1 at the
    bright end, 0 at the faint end, ``S(0) = 1/2``, non-increasing in ``t``).

    Attributes
    ----------
    name : str
        Short identifier (the key in :data:`TRUTHS`).
    description : str
        One line saying what the truth is.
    m50_0 : float
        m50 at the reference depth ``d = 0`` (the scene's median depth), mag.
    plateau, floor : float
        Bright-end and faint-end limits of ``f`` (``0 <= floor < plateau <= 1``).
    window : (float, float)
        Default injection range relative to ``m50_0`` (mag), wide enough for
        the curve to reach its plateau and floor over the scene's depths.
    """

    name: str = ""
    description: str = ""
    m50_0: float = 24.0
    plateau: float = 0.98
    floor: float = 0.005
    window: tuple = (-2.5, 1.5)

    def __post_init__(self):
        if not (0.0 <= self.floor < self.plateau <= 1.0):
            raise InputError(f"truth {self.name!r}: need 0 <= floor < plateau <= 1, got floor = {self.floor!r}, "
                             f"plateau = {self.plateau!r}.")
        if not np.isfinite(self.m50_0):
            raise InputError(f"truth {self.name!r}: m50_0 = {self.m50_0!r} must be finite.")
        _check_range(self.window, "window")

    def transition(self, t, u, v) -> np.ndarray:
        """``S(t; u, v)``: the transition at standardised position ``t = m - m50(x, y)`` (mag)."""
        raise NotImplementedError

    def prob(self, m, d, u=0.0, v=0.0) -> np.ndarray:
        """Detection probability.

        Parameters
        ----------
        m : array_like
            True magnitudes.
        d : array_like
            Depth covariate ``-2.5 log10(sigma / sigma_ref)`` (mag).
        u, v : array_like
            Normalised image coordinates in [-1, 1].

        Returns
        -------
        ndarray
            ``f``, with the broadcast shape of ``m, d, u, v``.
        """
        m = np.asarray(m, dtype=float)
        d = np.asarray(d, dtype=float)
        u = np.asarray(u, dtype=float)
        v = np.asarray(v, dtype=float)
        shape = np.broadcast_shapes(m.shape, d.shape, u.shape, v.shape)
        s = self.transition(m - (self.m50_0 + d), u, v)
        f = self.floor + (self.plateau - self.floor) * s
        if f.shape != shape:
            f = np.broadcast_to(f, shape).copy()
        return f

    def m50_at(self, d) -> np.ndarray:
        """m50 (half-way between floor and plateau) at depth ``d``: ``m50_0 + d``."""
        return self.m50_0 + np.asarray(d, dtype=float)

    def default_mag_range(self) -> tuple[float, float]:
        """Injection magnitude range ``m50_0 + window``."""
        return (self.m50_0 + float(self.window[0]), self.m50_0 + float(self.window[1]))

    def to_dict(self) -> dict:
        """JSON-ready parameters (class name and every field)."""
        out = {"class": type(self).__name__}
        for f in fields(self):
            v = getattr(self, f.name)
            out[f.name] = list(v) if isinstance(v, tuple) else v
        return out


@dataclass(frozen=True)
class LogisticTruth(Truth):
    """Control: ``S(t) = 1 / (1 + exp(t / w))``, the package's own logistic family."""

    name: str = "logistic"
    description: str = "control: plain logistic, w = 0.2 mag, plateau 0.98, floor 0.005"
    w: float = 0.2

    def transition(self, t, u, v):
        return _expit(-t / self.w)


@dataclass(frozen=True)
class GumbelTruth(Truth):
    """Complementary log-log transition ``S(t) = 1 - exp(-ln2 * exp(-t / s))``.

    The bright shoulder is double-exponential (sharp); the faint side decays
    as ``ln2 * exp(-t / s)``, a slow roll-off relative to the core.
    """

    name: str = "skew_faint"
    description: str = ("slow faint-end roll-off: complementary log-log (Gumbel) transition, s = 0.25 mag, "
                        "plateau 0.97, floor 0.01")
    plateau: float = 0.97
    floor: float = 0.01
    s: float = 0.25

    def transition(self, t, u, v):
        z = np.minimum(-t / self.s, 700.0)
        return -np.expm1(-math.log(2.0) * np.exp(z))


@dataclass(frozen=True)
class InverseFluxTruth(Truth):
    """Logistic in inverse flux (noise-to-signal): ``S(t) = L(k (1 - 10^(0.4 (t + t0)))) / L(k)``.

    ``L`` is the logistic function and ``10^(0.4 t)`` is ``F50 / F``.  The
    plateau is approached slowly on the bright side (as ``10^(0.4 t)``, an
    e-folding of 1.09 mag); the faint side falls double-exponentially.
    ``t0`` (closed form) puts ``S(0) = 1/2``.
    """

    name: str = "skew_bright"
    description: str = ("slow bright-side approach, sharp faint cut: logistic in inverse flux, k = 3.5, "
                        "plateau 0.98, floor 0.005")
    window: tuple = (-3.0, 1.5)
    k: float = 3.5

    @property
    def t0(self) -> float:
        """Shift putting ``S(0) = 1/2``, mag."""
        q = 1.0 - _logit(0.5 * float(_expit(self.k))) / self.k
        return 2.5 * math.log10(q)

    def transition(self, t, u, v):
        z = np.minimum(0.4 * math.log(10.0) * (t + self.t0), 700.0)
        return _expit(self.k * (1.0 - np.exp(z))) / float(_expit(self.k))


@dataclass(frozen=True)
class LongTailTruth(Truth):
    """Narrow logistic plus a fainter, much wider one.

    ``S(t) = (1 - a) L(-(t + t0) / w1) + a L(-(t + t0 - delta) / w2)``
    with ``t0`` found numerically (once) so that ``S(0) = 1/2``.
    """

    name: str = "long_tail"
    description: str = ("long faint tail: 0.85 logistic (w = 0.15) + 0.15 logistic (w = 0.8, 0.5 mag fainter), "
                        "plateau 0.97, floor 0.005")
    plateau: float = 0.97
    window: tuple = (-2.5, 2.0)
    a: float = 0.15
    w1: float = 0.15
    w2: float = 0.8
    delta: float = 0.5

    def _raw(self, t):
        return (1.0 - self.a) * _expit(-t / self.w1) + self.a * _expit(-(t - self.delta) / self.w2)

    @cached_property
    def t0(self) -> float:
        """Shift putting ``S(0) = 1/2``, mag."""
        return _solve_half(self._raw)

    def transition(self, t, u, v):
        return self._raw(t + self.t0)


@dataclass(frozen=True)
class TwoPopulationTruth(Truth):
    """50/50 mixture of two logistics whose m50 differ by ``sep`` mag (``S(0) = 1/2`` by symmetry)."""

    name: str = "two_populations"
    description: str = ("two populations: 50/50 mixture of logistics (w = 0.15) with m50 0.7 mag apart, "
                        "plateau 0.98, floor 0.005")
    sep: float = 0.7
    w: float = 0.15

    def transition(self, t, u, v):
        h = 0.5 * self.sep
        return 0.5 * _expit(-(t + h) / self.w) + 0.5 * _expit(-(t - h) / self.w)


@dataclass(frozen=True)
class StudentTruth(Truth):
    """Student-t (2 degrees of freedom) survival function, heavy power-law tails.

    ``S(t) = 1/2 - x / (2 sqrt(2 + x^2))`` with ``x = t / s``: both tails
    fall as ``1 / x^2``, a wide, gently curved roll-off.
    """

    name: str = "plateau_slow"
    description: str = ("plateau 0.9 with a slow roll-off: Student-t (2 dof) transition, s = 0.35 mag, "
                        "power-law tails, floor 0.01")
    plateau: float = 0.9
    floor: float = 0.01
    window: tuple = (-3.0, 2.0)
    s: float = 0.35

    def transition(self, t, u, v):
        x = np.asarray(t, float) / self.s
        return 0.5 - x / (2.0 * np.sqrt(2.0 + x * x))


@dataclass(frozen=True)
class VaryingWidthTruth(Truth):
    """Logistic whose width varies across the image with ``u`` (not with depth).

    ``S(t; u) = L(-t / w(u))``, ``w(u) = w_left + (w_right - w_left) (u + 1) / 2``.
    """

    name: str = "width_varies"
    description: str = ("logistic whose width runs from 0.1 mag (u = -1) to 0.35 mag (u = +1), "
                        "plateau 0.97, floor 0.01")
    plateau: float = 0.97
    floor: float = 0.01
    w_left: float = 0.1
    w_right: float = 0.35

    def width(self, u) -> np.ndarray:
        """``w(u)``, mag."""
        u = np.clip(np.asarray(u, float), -1.0, 1.0)
        return self.w_left + (self.w_right - self.w_left) * 0.5 * (u + 1.0)

    def transition(self, t, u, v):
        return _expit(-t / self.width(u))


@dataclass(frozen=True)
class LogPlaneWidthTruth(VaryingWidthTruth):
    """:class:`VaryingWidthTruth` with ``log w`` a plane in ``u`` (same end widths): inside the family of the
    positional-width rungs, a control for them (not in :data:`TRUTHS`, which holds truths outside every rung).

    ``w(u) = w_left (w_right / w_left)^((u + 1) / 2)``.
    """

    name: str = "width_logplane"
    description: str = "logistic whose log width is a plane in u: 0.1 mag (u = -1) to 0.35 mag (u = +1)"

    def width(self, u) -> np.ndarray:
        """``w(u)``, mag."""
        u = np.clip(np.asarray(u, float), -1.0, 1.0)
        return self.w_left * np.exp(math.log(self.w_right / self.w_left) * 0.5 * (u + 1.0))


@dataclass(frozen=True)
class RadialWidthTruth(Truth):
    """Logistic whose ``log w`` is quadratic in the distance from the image centre: inside the family of the
    positional-width rungs (``width_order = 2``), with no plane component (a PSF that degrades off-axis).
    Not in :data:`TRUTHS` (a control of those rungs, as :class:`LogPlaneWidthTruth`).

    ``w(u, v) = w_centre (w_corner / w_centre)^(r^2 / 2)``, ``r^2 = u^2 + v^2`` (2 at the corners).
    """

    name: str = "width_radial"
    description: str = ("logistic whose log width is quadratic in the distance from the centre: 0.12 mag at the "
                        "centre, 0.36 mag at the corners, plateau 0.97, floor 0.01")
    plateau: float = 0.97
    floor: float = 0.01
    w_centre: float = 0.12
    w_corner: float = 0.36

    def __post_init__(self):
        super().__post_init__()
        if not (self.w_centre > 0 and self.w_corner > 0):
            raise InputError(f"truth {self.name!r}: widths must be positive, got w_centre = {self.w_centre!r}, "
                             f"w_corner = {self.w_corner!r}.")

    def width(self, u, v) -> np.ndarray:
        """``w(u, v)``, mag."""
        u = np.clip(np.asarray(u, float), -1.0, 1.0)
        v = np.clip(np.asarray(v, float), -1.0, 1.0)
        return self.w_centre * np.exp(math.log(self.w_corner / self.w_centre) * 0.5 * (u * u + v * v))

    def transition(self, t, u, v):
        return _expit(-t / self.width(u, v))


def _solve_half(fn, lo: float = -10.0, hi: float = 10.0) -> float:
    """``t0`` with ``fn(t0) = 1/2`` for a decreasing ``fn`` (bisection to 1e-13)."""
    flo, fhi = float(fn(lo)), float(fn(hi))
    if not (flo >= 0.5 > fhi):
        raise InputError("transition does not cross 1/2 in [-10, 10] mag.")
    while hi - lo > 1e-13:
        mid = 0.5 * (lo + hi)
        if float(fn(mid)) >= 0.5:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


#: The registered truths by name, control last.
TRUTHS: dict[str, Truth] = {t.name: t for t in (
    GumbelTruth(),
    InverseFluxTruth(),
    LongTailTruth(),
    TwoPopulationTruth(),
    TwoPopulationTruth(name="shoulder", sep=0.8, w=0.08,
                       description=("a flat shoulder at m50: 50/50 mixture of narrow logistics (w = 0.08) with m50 "
                                    "0.8 mag apart (two depths of a mosaic without a weight map), plateau 0.98, "
                                    "floor 0.005")),
    StudentTruth(),
    VaryingWidthTruth(),
    LogisticTruth(),
)}


def get_truth(truth) -> Truth:
    """A :class:`Truth` from itself or its name in :data:`TRUTHS`."""
    if isinstance(truth, Truth):
        return truth
    if isinstance(truth, str) and truth in TRUTHS:
        return TRUTHS[truth]
    raise InputError(f"unknown truth {truth!r}; use a Truth instance or one of {sorted(TRUTHS)}.")


# --------------------------------------------------------------------------
# outcomes
# --------------------------------------------------------------------------

def draw_outcomes(truth, scene: Scene, n: int | None = None, *, mag_range=None, seed: int, mags=None) -> Table:
    """Draw an injection outcome table from a known completeness.

    Parameters
    ----------
    truth : Truth or str
        The completeness (or its name in :data:`TRUTHS`).
    scene : Scene
        Noise map and mask.
    n : int
        Number of injections (>= 1).
    mag_range : (float, float), optional
        Magnitudes are uniform in it; default ``truth.default_mag_range()``.
    mags : array, optional
        The injected magnitudes themselves (e.g. drawn from an adaptive
        design); ``n`` is then their number.
    seed : int
        Seed of the positions, magnitudes and outcomes.

    Returns
    -------
    astropy.table.Table
        Columns as the package's outcome table (:data:`comest_bayes.recover.realization.OUTCOME_COLUMNS`)
        reads them: ``mag`` (true magnitude), ``detected`` (bool), ``x``,
        ``y`` (0-based pixels, uniform within a uniformly drawn unmasked
        pixel) and ``noise`` (the scene's noise at the pixel, which is where
        ``floor(x + 0.5), floor(y + 0.5)`` points).  ``meta`` holds the truth
        name, the magnitude range, ``n`` and the seed.
    """
    truth = get_truth(truth)
    if not isinstance(scene, Scene):
        raise InputError(f"scene must be a Scene (see make_scene), got {type(scene).__name__}.")
    if mags is not None:
        mags = np.asarray(mags, dtype=np.float64).ravel()
        if mags.size < 1 or not np.isfinite(mags).all():
            raise InputError("mags must be a non-empty array of finite magnitudes.")
        n = int(mags.size)
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise InputError(f"n = {n!r} must be a positive integer number of injections.")
    seed = _check_seed(seed)
    lo, hi = _check_range(truth.default_mag_range() if mag_range is None else mag_range)
    rng = rng_for(seed)
    iy_all, ix_all, d_all, u_all, v_all = scene._unmasked
    pick = rng.integers(0, iy_all.size, size=int(n))
    iy, ix = iy_all[pick], ix_all[pick]
    # offsets in [-0.5, 0.5): floor(x + 0.5) is the drawn pixel, as the package looks it up
    x = ix + rng.random(n) - 0.5
    y = iy + rng.random(n) - 0.5
    mag = rng.uniform(lo, hi, size=int(n)) if mags is None else mags
    f = truth.prob(mag, d_all[pick], u_all[pick], v_all[pick])
    detected = rng.random(n) < f
    table = Table({"mag": mag, "detected": detected, "x": x, "y": y,
                   "noise": np.asarray(scene.noise[iy, ix], dtype=float)},
                  meta={"truth": truth.name, "mag_range": [lo, hi], "n": int(n), "seed": seed})
    return table


def truth_curve(truth, scene: Scene, mags, *, positions=None) -> np.ndarray:
    """Exact image-average completeness ``<f>(m)`` over the unmasked pixels.

    Parameters
    ----------
    truth : Truth or str
    scene : Scene
    mags : array_like
        Magnitudes (any shape).
    positions : array_like, shape (P, 2), optional
        Average over these ``(x, y)`` pixel positions instead of every
        unmasked pixel (e.g. a posterior's footprint sample).

    Returns
    -------
    ndarray, shape of ``mags``
    """
    truth = get_truth(truth)
    if not isinstance(scene, Scene):
        raise InputError(f"scene must be a Scene (see make_scene), got {type(scene).__name__}.")
    m = np.asarray(mags, dtype=float)
    if not np.all(np.isfinite(m)):
        raise InputError("truth_curve needs finite magnitudes.")
    d, u, v = scene.pixels(positions)
    flat = m.ravel()
    out = np.empty(flat.size)
    chunk = max(1, _CHUNK_ELEMENTS // d.size)
    for start in range(0, flat.size, chunk):
        mm = flat[start:start + chunk]
        out[start:start + chunk] = truth.prob(mm[None, :], d[:, None], u[:, None], v[:, None]).mean(axis=0)
    return out.reshape(m.shape)


def truth_quantities(truth, scene: Scene, *, positions=None) -> dict:
    """Image-average m50, m90 and the curve at m50 -/+ 0.3 mag.

    m50 and m90 are where the (monotone) image-average curve falls to 0.5 and
    0.9, found by bisection to 1e-10 mag; NaN where the curve never reaches
    the level (e.g. m90 of a truth with a plateau <= 0.9).

    Parameters
    ----------
    truth : Truth or str
    scene : Scene
    positions : array_like, shape (P, 2), optional
        Average over these pixel positions instead (see :func:`truth_curve`).

    Returns
    -------
    dict
        ``m50``, ``m90``, ``mag_bright`` (= m50 - 0.3), ``mag_faint``
        (= m50 + 0.3), ``f_bright``, ``f_faint`` (the curve there),
        ``plateau`` and ``floor`` of the truth.
    """
    truth = get_truth(truth)
    lo0, hi0 = truth.default_mag_range()
    levels = np.array([0.5, 0.9])
    lo = np.full(levels.size, lo0 - 5.0)
    hi = np.full(levels.size, hi0 + 5.0)
    ok = (truth_curve(truth, scene, lo, positions=positions) >= levels) & \
         (truth_curve(truth, scene, hi, positions=positions) < levels)
    while np.any(hi - lo > _XTOL):
        mid = 0.5 * (lo + hi)
        above = truth_curve(truth, scene, mid, positions=positions) >= levels
        lo = np.where(above, mid, lo)
        hi = np.where(above, hi, mid)
    roots = np.where(ok, 0.5 * (lo + hi), np.nan)
    m50, m90 = (float(r) for r in roots)
    out = {"m50": m50, "m90": m90, "mag_bright": m50 - PROBE_OFFSET, "mag_faint": m50 + PROBE_OFFSET,
           "f_bright": float("nan"), "f_faint": float("nan"),
           "plateau": float(truth.plateau), "floor": float(truth.floor)}
    if np.isfinite(m50):
        fb, ff = truth_curve(truth, scene, [m50 - PROBE_OFFSET, m50 + PROBE_OFFSET], positions=positions)
        out["f_bright"], out["f_faint"] = float(fb), float(ff)
    return out


# --------------------------------------------------------------------------
# the published binned estimate
# --------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class BinnedEstimate:
    """The ComEst binned completeness and the numbers read off it.

    Attributes
    ----------
    edges, centers : ndarray
        Magnitude bin edges and centres.
    n, k : ndarray of int
        Injections and detections per bin.
    ratio : ndarray
        ``k / n`` (NaN for empty bins).
    m50, m90 : float
        Where the binned curve first falls below 0.5 / 0.9 (linear
        interpolation between bin centres, :func:`comest_bayes.ratios.binned.first_crossing`);
        NaN when it does not cross.
    probes : ndarray
        Probe magnitudes.
    f_probe : ndarray
        The binned curve interpolated at ``probes`` (:meth:`curve`).
    """

    edges: np.ndarray
    centers: np.ndarray
    n: np.ndarray
    k: np.ndarray
    ratio: np.ndarray
    m50: float
    m90: float
    probes: np.ndarray
    f_probe: np.ndarray

    def curve(self, mags) -> np.ndarray:
        """The binned curve at ``mags``: linear interpolation between the centres of non-empty bins.

        Constant beyond the outermost non-empty centres; all NaN with fewer
        than two non-empty bins.
        """
        m = np.asarray(mags, dtype=float)
        ok = (self.n > 0) & np.isfinite(self.ratio)
        if ok.sum() < 2:
            return np.full(m.shape, np.nan)
        return np.interp(m, self.centers[ok], self.ratio[ok])

    def to_dict(self) -> dict:
        """JSON-ready form (NaN as None)."""
        def num(v):
            return None if not np.isfinite(v) else float(v)

        return {"m50": num(self.m50), "m90": num(self.m90), "probes": [num(v) for v in self.probes],
                "f_probe": [num(v) for v in self.f_probe], "centers": [float(v) for v in self.centers],
                "n": [int(v) for v in self.n], "k": [int(v) for v in self.k]}


def binned_estimate(table, *, mag_bin: float = 0.1, mag_range, probes=()) -> BinnedEstimate:
    """The published (ComEst) estimate: detected / injected per magnitude bin.

    Parameters
    ----------
    table : astropy.table.Table or mapping
        Outcome table with ``mag`` and ``detected`` columns.
    mag_bin : float
        Bin width, mag (default 0.1).
    mag_range : (float, float)
        Range binned, from its bright end (:func:`comest_bayes.ratios.binned.magnitude_edges`).
    probes : array_like
        Magnitudes at which to read the binned curve.

    Returns
    -------
    BinnedEstimate
    """
    lo, hi = _check_range(mag_range)
    if not (np.isfinite(mag_bin) and mag_bin > 0):
        raise InputError(f"mag_bin = {mag_bin!r} must be a positive bin width in mag.")
    try:
        mag = np.asarray(table["mag"], dtype=float)
        det = np.asarray(table["detected"])
    except (KeyError, TypeError, ValueError):
        raise InputError("the outcome table needs 'mag' and 'detected' columns.") from None
    if det.dtype != bool:
        if not np.all(np.isin(det, (0, 1))):
            raise InputError("column 'detected' must be boolean or 0/1.")
        det = det.astype(bool)
    edges = R.magnitude_edges(lo, hi, mag_bin)
    br = R.completeness(mag, det, edges)
    ratio = np.asarray(br.ratio, dtype=float)
    probes = np.atleast_1d(np.asarray(probes, dtype=float))
    est = BinnedEstimate(edges=edges, centers=np.asarray(br.centers, float), n=np.asarray(br.n),
                         k=np.asarray(br.k), ratio=ratio, m50=R.magnitude_at(br, 0.5), m90=R.magnitude_at(br, 0.9),
                         probes=probes, f_probe=np.empty(0))
    object.__setattr__(est, "f_probe", est.curve(probes))
    return est
