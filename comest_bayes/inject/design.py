"""Adaptive injection design: where the next batch of injections teaches the curve the most.

Pure numerics (no I/O): a design is a density over the injected magnitude range, piecewise
constant on fine bins, built from posterior draws of the image-average completeness curve
(:func:`variance_reduction`, :func:`design_from_draws`).  The targets, the gain and why the
inference stays valid: ``docs/adaptive.md``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from comest_bayes.errors import InputError

__all__ = ["MagnitudeDesign", "uniform_design", "variance_reduction", "design_from_draws", "curves_at",
           "TARGETS", "DEFAULT_UNIFORM_SHARE", "DESIGN_BINS"]

#: Quantities a design can aim at: the m50, the whole transition, or f at chosen magnitudes.
TARGETS = ("m50", "curve", "f")

#: Share of every adaptive batch drawn uniformly over the whole magnitude range.
DEFAULT_UNIFORM_SHARE = 0.15

#: Bins of the piecewise-constant design density over the magnitude range.
DESIGN_BINS = 100


@dataclass(frozen=True)
class MagnitudeDesign:
    """A piecewise-constant density over magnitudes from which injections are drawn.

    Attributes
    ----------
    edges : ndarray (B + 1,)
        Bin edges, increasing, spanning the injected range.
    prob : ndarray (B,)
        Probability of each bin (non-negative, sums to 1); uniform within a bin.
    target : str
        What the design aims at (``"uniform"`` for the published design).
    uniform_share : float
        Share of the density spread uniformly over the range.
    """

    edges: np.ndarray
    prob: np.ndarray
    target: str = "uniform"
    uniform_share: float = 1.0

    def __post_init__(self):
        edges = np.asarray(self.edges, dtype=np.float64)
        prob = np.asarray(self.prob, dtype=np.float64)
        if edges.ndim != 1 or edges.size < 2 or not np.all(np.diff(edges) > 0):
            raise InputError("a magnitude design needs increasing bin edges.")
        if prob.shape != (edges.size - 1,) or np.any(prob < 0) or not np.isfinite(prob).all() or prob.sum() <= 0:
            raise InputError("a magnitude design needs one non-negative probability per bin.")
        object.__setattr__(self, "edges", edges)
        object.__setattr__(self, "prob", prob / prob.sum())

    @property
    def range(self) -> tuple[float, float]:
        return float(self.edges[0]), float(self.edges[-1])

    def density(self, mags) -> np.ndarray:
        """Probability density (per mag) at ``mags``; 0 outside the range."""
        m = np.asarray(mags, dtype=np.float64)
        i = np.searchsorted(self.edges, m, side="right") - 1
        inside = (i >= 0) & (i < self.prob.size)
        out = np.zeros(m.shape)
        ii = i[inside]
        out[inside] = self.prob[ii] / np.diff(self.edges)[ii]
        return out

    def sample(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """``n`` magnitudes: a bin by its probability, then uniform within it."""
        n = int(n)
        if n < 0:
            raise InputError(f"cannot draw {n} magnitudes.")
        b = rng.choice(self.prob.size, size=n, p=self.prob)
        return self.edges[b] + rng.random(n) * np.diff(self.edges)[b]

    def fraction_within(self, lo: float, hi: float) -> float:
        """Probability that a drawn magnitude lies in ``[lo, hi]``."""
        e = self.edges
        overlap = np.clip(np.minimum(e[1:], hi) - np.maximum(e[:-1], lo), 0.0, None) / np.diff(e)
        return float(np.sum(self.prob * overlap))

    def to_dict(self) -> dict:
        return {"edges": [float(v) for v in self.edges], "prob": [float(v) for v in self.prob],
                "target": self.target, "uniform_share": float(self.uniform_share)}

    @classmethod
    def from_dict(cls, d: dict) -> "MagnitudeDesign":
        return cls(edges=np.asarray(d["edges"], float), prob=np.asarray(d["prob"], float),
                   target=str(d.get("target", "uniform")), uniform_share=float(d.get("uniform_share", 1.0)))


def uniform_design(lo: float, hi: float, nbins: int = DESIGN_BINS) -> MagnitudeDesign:
    """The published design: magnitudes uniform over ``[lo, hi]``."""
    if not (np.isfinite(lo) and np.isfinite(hi) and hi > lo):
        raise InputError(f"magnitude range [{lo}, {hi}] must be finite and increasing.")
    return MagnitudeDesign(np.linspace(lo, hi, int(nbins) + 1), np.full(int(nbins), 1.0 / int(nbins)))


def curves_at(grid, curves, magnitudes) -> np.ndarray:
    """Draws of the curve at ``magnitudes``, linearly interpolated between the ``grid`` points.

    Parameters
    ----------
    grid : array (G,)
        Increasing magnitudes.
    curves : array (S, G)
        Draws of the curve on ``grid``.
    magnitudes : array (J,)
        Magnitudes inside ``[grid[0], grid[-1]]`` (exact where they are grid points).

    Returns
    -------
    ndarray (S, J)
    """
    grid = np.asarray(grid, dtype=np.float64)
    f = np.asarray(curves, dtype=np.float64)
    m = np.atleast_1d(np.asarray(magnitudes, dtype=np.float64))
    if m.size == 0 or not np.isfinite(m).all() or m.min() < grid[0] or m.max() > grid[-1]:
        raise InputError(f"magnitudes {m.tolist()} must be finite and inside the curve's range "
                         f"[{grid[0]:.2f}, {grid[-1]:.2f}].")
    i = np.clip(np.searchsorted(grid, m, side="right") - 1, 0, grid.size - 2)
    w = (m - grid[i]) / (grid[i + 1] - grid[i])
    return f[:, i] * (1.0 - w) + f[:, i + 1] * w


def variance_reduction(grid, curves, *, target: str = "m50", m50=None, magnitudes=None,
                       window=(0.05, 0.95)) -> np.ndarray:
    """Expected reduction of the target's posterior variance per injection at each ``grid`` magnitude.

    Parameters
    ----------
    grid : array (G,)
        Magnitudes.
    curves : array (S, G)
        Posterior draws of the image-average completeness on ``grid``.
    target : {"m50", "curve", "f"}
    m50 : array (S,), optional
        The draws' m50 (needed for ``target="m50"``; NaN draws are dropped).
    magnitudes : array (J,), optional
        For ``"f"``: the magnitudes whose ``Var f`` reductions are summed.
    window : (float, float)
        For ``"curve"``: the posterior-median curve levels that bound the
        magnitudes whose variance is summed.

    Returns
    -------
    ndarray (G,)
        ``Cov(Q, f(m))^2 / (p (1 - p))`` (see ``docs/adaptive.md``); 0 where
        ``p`` is 0 or 1.
    """
    if target not in TARGETS:
        raise InputError(f"design target must be one of {TARGETS}, got {target!r}.")
    f = np.asarray(curves, dtype=np.float64)
    if f.ndim != 2 or f.shape[1] != np.size(grid) or f.shape[0] < 2:
        raise InputError("curves must be (draws >= 2, len(grid)) posterior draws.")
    p = f.mean(axis=0)
    var_y = p * (1.0 - p)
    dev = f - p
    if target == "m50":
        if m50 is None:
            raise InputError("target 'm50' needs the draws' m50.")
        q = np.asarray(m50, dtype=np.float64)
        ok = np.isfinite(q)
        if ok.sum() < 2:
            raise InputError("fewer than two draws have a defined m50: the design cannot aim at it.")
        cq = (q[ok] - q[ok].mean()) @ (f[ok] - f[ok].mean(axis=0)) / (ok.sum() - 1)
        num = cq ** 2
    elif target == "f":
        if magnitudes is None or np.size(magnitudes) == 0:
            raise InputError("target 'f' needs the magnitudes at which f must be precise.")
        fj = curves_at(grid, f, magnitudes)
        cov = dev.T @ (fj - fj.mean(axis=0)) / (f.shape[0] - 1)  # (G, J): Cov(f(m), f(m_j))
        num = np.sum(cov ** 2, axis=1)
    else:
        med = np.median(f, axis=0)
        sel = (med >= window[0]) & (med <= window[1])
        if not sel.any():  # no transition inside the range: the whole range counts
            sel = np.ones_like(sel)
        cov = dev.T @ dev[:, sel] / (f.shape[0] - 1)  # (G, G_sel): Cov(f(m), f(m'))
        num = np.sum(cov ** 2, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        gain = np.where(var_y > 1e-12, num / var_y, 0.0)
    return np.nan_to_num(gain, nan=0.0, posinf=0.0)


def design_from_draws(grid, curves, lo: float, hi: float, *, target: str = "m50", m50=None, magnitudes=None,
                      uniform_share: float = DEFAULT_UNIFORM_SHARE, nbins: int = DESIGN_BINS) -> MagnitudeDesign:
    """The next batch's design from posterior draws of the image-average curve.

    The gain of :func:`variance_reduction` is averaged over each of ``nbins``
    bins of ``[lo, hi]`` and normalised; ``uniform_share`` of the density
    is spread uniformly.  With no gain anywhere (a posterior that no
    injection can sharpen) the design is uniform.
    """
    if not 0.0 <= uniform_share <= 1.0:
        raise InputError(f"uniform_share = {uniform_share} must lie in [0, 1].")
    grid = np.asarray(grid, dtype=np.float64)
    base = uniform_design(lo, hi, nbins)
    gain = variance_reduction(grid, curves, target=target, m50=m50, magnitudes=magnitudes)
    # the gain per design bin: linear interpolation of the gain at each bin's centre and edges
    edges = base.edges
    fine = np.linspace(lo, hi, 4 * nbins + 1)
    g_fine = np.interp(fine, grid, gain, left=0.0, right=0.0)
    g_bin = 0.5 * (g_fine[0:-1:4] + g_fine[4::4]) * 0.25 + 0.25 * (g_fine[1::4] + g_fine[2::4] + g_fine[3::4])
    total = g_bin.sum()
    # identical draws leave only rounding noise (~1e-34); a real posterior's gain is many orders above
    if not np.isfinite(total) or total <= 1e-30:
        return MagnitudeDesign(edges, base.prob, target=target, uniform_share=1.0)
    prob = (1.0 - uniform_share) * g_bin / total + uniform_share * base.prob
    return MagnitudeDesign(edges, prob, target=target, uniform_share=float(uniform_share))
