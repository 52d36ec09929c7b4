"""Photometric transfer: the distribution of measured magnitude given true magnitude, for detected sources.

``K(m_obs | m) = p(m_obs | m, detected)``, measured from the matched injections as an empirical
kernel on a grid of true magnitudes, for the forward model of :mod:`comest_bayes.lf`.  The
estimator: ``docs/lf.md`` ("Photometric transfer").
"""

from __future__ import annotations

from dataclasses import dataclass, field
import json

import numpy as np
from scipy.special import ndtr

from comest_bayes.errors import InputError
from comest_bayes.io.jsonio import dumps

__all__ = ["PhotometricTransfer", "measure_transfer", "transfer_from_outcomes"]

_SQRT2PI = np.sqrt(2.0 * np.pi)


@dataclass
class PhotometricTransfer:
    """Tabulated kernel ``K(m_obs | m_true, detected)``.

    Attributes
    ----------
    nodes : ndarray, shape (T,)
        True-magnitude nodes, increasing (mag).
    dm : ndarray, shape (D,)
        Uniform grid of ``m_obs - m_true`` (mag).
    density : ndarray, shape (T, D)
        Kernel density of ``dm`` at each node, per mag; integrates over
        ``dm`` to ``finite_fraction``.
    cdf : ndarray, shape (T, D)
        Its cumulative integral from ``-inf``.
    finite_fraction : ndarray, shape (T,)
        Weighted fraction of the node's detections with a finite measured magnitude.
    n_eff : ndarray, shape (T,)
        Kish effective number of injections behind each node.
    bandwidth : ndarray, shape (T,)
        KDE bandwidth of each node (mag).
    meta : dict
        ``true_range`` (injected true magnitudes of the matched sample),
        ``n_matched``, ``n_nonfinite``, ``window``, ``min_count``.
    """

    nodes: np.ndarray
    dm: np.ndarray
    density: np.ndarray
    cdf: np.ndarray
    finite_fraction: np.ndarray
    n_eff: np.ndarray
    bandwidth: np.ndarray
    meta: dict = field(default_factory=dict)

    # ---- interpolation helpers ---------------------------------------------------
    def _node_weights(self, t):
        t = np.asarray(t, float)
        if self.nodes.size == 1:
            z = np.zeros(t.shape, int)
            return z, z, np.zeros(t.shape)
        u = np.clip(np.interp(t, self.nodes, np.arange(self.nodes.size)), 0, self.nodes.size - 1)
        k0 = np.minimum(np.floor(u).astype(int), self.nodes.size - 2)
        return k0, k0 + 1, u - k0

    def _table(self, table, k, d, outside_hi: float):
        """Linear interpolation of ``table[k]`` at dm values ``d`` (same shape as k); 0 below, outside_hi above."""
        step = self.dm[1] - self.dm[0]
        u = (d - self.dm[0]) / step
        i = np.floor(u).astype(int)
        frac = u - i
        ok = (i >= 0) & (i < self.dm.size - 1)
        ic = np.clip(i, 0, self.dm.size - 2)
        val = table[k, ic] * (1.0 - frac) + table[k, ic + 1] * frac
        hi = u >= self.dm.size - 1
        return np.where(ok, val, np.where(hi, outside_hi[k] if np.ndim(outside_hi) else outside_hi, 0.0))

    def pdf(self, m_obs, m_true) -> np.ndarray:
        """``K(m_obs | m_true)`` per mag, broadcasting ``m_obs`` and ``m_true`` together."""
        m_obs, m_true = np.broadcast_arrays(np.asarray(m_obs, float), np.asarray(m_true, float))
        k0, k1, w = self._node_weights(m_true)
        d = m_obs - m_true
        zero = np.zeros(self.nodes.size)
        return (1.0 - w) * self._table(self.density, k0, d, zero) + w * self._table(self.density, k1, d, zero)

    def cdf_at(self, m_obs, m_true) -> np.ndarray:
        """``P(measured <= m_obs | m_true, detected)``, broadcasting."""
        m_obs, m_true = np.broadcast_arrays(np.asarray(m_obs, float), np.asarray(m_true, float))
        k0, k1, w = self._node_weights(m_true)
        d = m_obs - m_true
        ff = self.finite_fraction
        return (1.0 - w) * self._table(self.cdf, k0, d, ff) + w * self._table(self.cdf, k1, d, ff)

    def matrix(self, m_obs, true_grid) -> np.ndarray:
        """Kernel at objects' measured magnitudes on a true grid: shape (N, M), per mag."""
        return self.pdf(np.asarray(m_obs, float)[:, None], np.asarray(true_grid, float)[None, :])

    def bin_matrix(self, obs_edges, true_grid) -> np.ndarray:
        """Probability of measuring a magnitude in each bin: shape (K, M) for K = len(obs_edges) - 1."""
        c = self.cdf_at(np.asarray(obs_edges, float)[:, None], np.asarray(true_grid, float)[None, :])
        return np.clip(np.diff(c, axis=0), 0.0, None)

    def quantiles(self, q=(0.16, 0.5, 0.84)) -> np.ndarray:
        """Quantiles of ``dm`` at each node (of the finite part), shape (len(q), T)."""
        out = np.empty((len(q), self.nodes.size))
        for j in range(self.nodes.size):
            c = self.cdf[j] / max(self.finite_fraction[j], 1e-300)
            for i, qq in enumerate(q):
                out[i, j] = np.interp(qq, c, self.dm)
        return out

    # ---- persistence ---------------------------------------------------------------
    def to_arrays(self, prefix: str = "transfer_") -> dict:
        """Arrays for ``np.savez`` (keys prefixed), meta as JSON text."""

        return {f"{prefix}nodes": self.nodes, f"{prefix}dm": self.dm, f"{prefix}density": self.density,
                f"{prefix}cdf": self.cdf, f"{prefix}finite_fraction": self.finite_fraction,
                f"{prefix}n_eff": self.n_eff, f"{prefix}bandwidth": self.bandwidth,
                f"{prefix}meta": np.array(dumps(self.meta))}

    @classmethod
    def from_arrays(cls, z, prefix: str = "transfer_") -> "PhotometricTransfer":

        return cls(nodes=np.array(z[f"{prefix}nodes"]), dm=np.array(z[f"{prefix}dm"]),
                   density=np.array(z[f"{prefix}density"]), cdf=np.array(z[f"{prefix}cdf"]),
                   finite_fraction=np.array(z[f"{prefix}finite_fraction"]), n_eff=np.array(z[f"{prefix}n_eff"]),
                   bandwidth=np.array(z[f"{prefix}bandwidth"]), meta=json.loads(str(z[f"{prefix}meta"])))


def _weighted_quantile(x, w, q):
    order = np.argsort(x)
    xs, ws = x[order], w[order]
    c = np.cumsum(ws)
    c = (c - 0.5 * ws) / c[-1]
    return np.interp(q, c, xs)


def measure_transfer(true_mag, obs_mag, *, node_step: float = 0.1, window: float = 0.25, min_count: int = 40,
                     dm_step: float = 0.01, dm_pad: float = 0.5, dm_limit: float = 6.0) -> PhotometricTransfer:
    """Measure the transfer kernel from detected injections.

    Parameters
    ----------
    true_mag : array, shape (N,)
        True magnitudes of *detected* injections.
    obs_mag : array, shape (N,)
        Their measured magnitudes (NaN/inf allowed: counted as "no finite magnitude").
    node_step : float, default 0.1
        Spacing of the true-magnitude nodes (mag).
    window : float, default 0.25
        Smallest half-width of the true-magnitude window of a node (mag).
    min_count : int, default 40
        The window widens until it holds this many injections (or all).
    dm_step : float, default 0.01
        Step of the tabulated ``dm`` grid (mag).
    dm_pad : float, default 0.5
        The ``dm`` grid spans the observed ``dm`` plus this margin each side
        (and at least 5 bandwidths).
    dm_limit : float, default 6.0
        ``|dm|`` beyond this is clipped from the grid (such outliers are
        counted as not finite).

    Returns
    -------
    PhotometricTransfer

    Raises
    ------
    InputError
        No detected injection, or arrays of different lengths.
    """
    t = np.asarray(true_mag, float).ravel()
    o = np.asarray(obs_mag, float).ravel()
    if t.shape != o.shape:
        raise InputError(f"true_mag and obs_mag must have the same length, got {t.size} and {o.size}.")
    keep_t = np.isfinite(t)
    t, o = t[keep_t], o[keep_t]
    if t.size == 0:
        raise InputError("no detected injection with a finite true magnitude: the photometric transfer cannot be "
                         "measured; run more realizations or widen the injected magnitude range.")
    d_all = o - t
    finite = np.isfinite(d_all) & (np.abs(d_all) <= dm_limit)
    if not finite.any():
        raise InputError("no detected injection has a finite measured magnitude: the photometric transfer cannot "
                         "be measured.")
    lo_t, hi_t = float(t.min()), float(t.max())
    nn = max(1, int(np.ceil((hi_t - lo_t) / node_step)))
    nodes = lo_t + node_step * np.arange(nn + 1)
    min_count = int(max(2, min(min_count, t.size)))

    # bandwidths first (they set the dm grid)
    sel = []
    for c in nodes:
        dist = np.abs(t - c)
        h = max(window, float(np.partition(dist, min_count - 1)[min_count - 1]))
        idx = np.flatnonzero(dist <= h)
        w = 1.0 - (dist[idx] / (1.05 * h)) ** 2
        sel.append((idx, w))
    bws, neffs, ffs = [], [], []
    for idx, w in sel:
        fin = finite[idx]
        wf, df = w[fin], d_all[idx][fin]
        ffs.append(wf.sum() / w.sum())
        if df.size == 0:
            bws.append(np.nan)
            neffs.append(0.0)
            continue
        neff = wf.sum() ** 2 / np.sum(wf * wf)
        mean = np.sum(wf * df) / wf.sum()
        sd = np.sqrt(np.sum(wf * (df - mean) ** 2) / wf.sum())
        q25, q75 = _weighted_quantile(df, wf, [0.25, 0.75])
        scale = min(sd, (q75 - q25) / 1.34) if q75 > q25 else sd
        bws.append(max(0.9 * scale * neff ** -0.2, 2.0 * dm_step))
        neffs.append(neff)
    bws = np.asarray(bws)
    bws = np.where(np.isfinite(bws), bws, np.nanmax(bws) if np.isfinite(bws).any() else 0.05)
    dfin = d_all[finite]
    lo_d = max(-dm_limit, float(dfin.min()) - max(dm_pad, 5.0 * bws.max()))
    hi_d = min(dm_limit, float(dfin.max()) + max(dm_pad, 5.0 * bws.max()))
    dm = np.arange(lo_d, hi_d + dm_step, dm_step)

    dens = np.zeros((nodes.size, dm.size))
    cdf = np.zeros((nodes.size, dm.size))
    for j, (idx, w) in enumerate(sel):
        fin = finite[idx]
        wf, df = w[fin], d_all[idx][fin]
        if df.size == 0:
            continue
        z = (dm[None, :] - df[:, None]) / bws[j]
        norm = w.sum()
        dens[j] = (wf[:, None] * np.exp(-0.5 * z * z)).sum(axis=0) / (norm * bws[j] * _SQRT2PI)
        cdf[j] = (wf[:, None] * ndtr(z)).sum(axis=0) / norm
    meta = {"true_range": [lo_t, hi_t], "n_matched": int(t.size), "n_nonfinite": int((~finite).sum()),
            "window": float(window), "min_count": int(min_count), "node_step": float(node_step)}
    return PhotometricTransfer(nodes=nodes, dm=dm, density=dens, cdf=cdf, finite_fraction=np.asarray(ffs),
                               n_eff=np.asarray(neffs), bandwidth=bws, meta=meta)


def transfer_from_outcomes(outcomes, *, mag_column: str = "mag", obs_column: str = "det_mag_auto",
                           detected_column: str = "detected", **kwargs) -> PhotometricTransfer:
    """:func:`measure_transfer` from a run's outcome table (``catalogs/<kind>_outcomes.fits``).

    Uses the rows with ``detected`` true: true magnitude ``mag`` and measured ``det_mag_auto``.
    """
    names = list(getattr(outcomes, "colnames", None) or outcomes.keys())
    for col in (mag_column, obs_column, detected_column):
        if col not in names:
            raise InputError(f"outcome table has no column {col!r}; columns present: {names}.")
    det = np.asarray(outcomes[detected_column]).astype(bool)
    obs = np.asarray(outcomes[obs_column], float)
    if obs.ndim == 2:
        obs = obs[:, 0]
    return measure_transfer(np.asarray(outcomes[mag_column], float)[det], obs[det], **kwargs)
