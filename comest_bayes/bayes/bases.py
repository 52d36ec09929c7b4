"""Smooth spatial bases of the completeness model over the normalised image coordinates ``(u, v)``:
polynomials and tensor B-splines (with the constraint that removes their mean).
"""

from __future__ import annotations

import numpy as np
from comest_bayes.errors import ConfigError

__all__ = ['smooth_basis', 'smooth_basis_names']


# ---------------------------------------------------------------------------
# Smooth spatial bases (numpy; evaluated once per data set)
# ---------------------------------------------------------------------------

def _poly_terms(order: int) -> list[tuple[int, int]]:
    return [(t - j, j) for t in range(1, order + 1) for j in range(t + 1)]


def _bspline_1d(x: np.ndarray, nbasis: int) -> np.ndarray:
    """Cubic B-splines on uniform knots covering [-1, 1]; shape (len(x), nbasis), rows sum to 1."""
    deg = 3
    h = 2.0 / (nbasis - deg)
    knots = -1.0 + h * (np.arange(nbasis + deg + 1) - deg)
    x = np.clip(x, -1.0, 1.0 - 1e-12)
    # Cox-de Boor recursion (de Boor 1978), degree 0 to 3, uniform spacing h.
    b = ((x[:, None] >= knots[None, :-1]) & (x[:, None] < knots[None, 1:])).astype(np.float64)
    for p in range(1, deg + 1):
        left = (x[:, None] - knots[None, : -(p + 1)]) / (p * h)
        right = (knots[None, p + 1:] - x[:, None]) / (p * h)
        b = left * b[:, :-1] + right * b[:, 1:]
    return b


def _bspline_constraint(nbasis: int) -> np.ndarray:
    """Orthonormal basis (K^2, K^2 - 1) of tensor coefficients whose field integrates to 0 over [-1, 1]^2."""
    deg = 3
    h = 2.0 / (nbasis - deg)
    # Integral of each 1-D function over [-1, 1]: Gauss-Legendre with 4 nodes per
    # knot interval is exact for the cubic pieces.
    nodes, weights = np.polynomial.legendre.leggauss(4)
    edges = -1.0 + h * np.arange(nbasis - deg + 1)
    xs = (edges[:-1, None] + h * 0.5 * (nodes[None, :] + 1.0)).ravel()
    ws = np.tile(weights * h * 0.5, nbasis - deg)
    integral = ws @ _bspline_1d(xs, nbasis)
    c = np.outer(integral, integral).ravel()
    q, _ = np.linalg.qr(c[:, None], mode="complete")
    return q[:, 1:]


def smooth_basis_names(basis: str, order: int) -> list[str]:
    """Names of the smooth coefficients: ``c_ij`` (Legendre degrees in u, v) or ``s_k``."""
    if basis == "poly":
        return [f"c_{i}{j}" for i, j in _poly_terms(order)]
    if basis == "bspline":
        return [f"s_{k}" for k in range(order * order - 1)]
    raise ConfigError(f"unknown smooth basis {basis!r}; valid: poly, bspline.")


def smooth_basis(u, v, basis: str, order: int) -> np.ndarray:
    """Smooth spatial basis at normalised coordinates.

    Parameters
    ----------
    u, v : array_like, shape (N,)
        Normalised image coordinates, clipped to [-1, 1].
    basis : {"poly", "bspline"}
        ``poly``: Legendre products ``P_i(u) P_j(v)``, ``1 <= i + j <= order``,
        ordered by total degree then falling power of u.  ``bspline``: tensor
        cubic B-splines with ``order`` functions per axis, projected onto the
        ``order**2 - 1`` dimensional space of fields with zero mean over the
        image (orthonormal projection, so iid coefficient priors stay iid).
    order : int
        Polynomial total degree or B-spline functions per axis.

    Returns
    -------
    ndarray, shape (N, J)
        Every column averages to zero over [-1, 1]^2, so the constant m50_0
        is the field average.
    """
    u = np.clip(np.asarray(u, dtype=np.float64).ravel(), -1.0, 1.0)
    v = np.clip(np.asarray(v, dtype=np.float64).ravel(), -1.0, 1.0)
    if basis == "poly":
        cols = []
        for i, j in _poly_terms(order):
            pu = np.polynomial.legendre.legval(u, [0.0] * i + [1.0])
            pv = np.polynomial.legendre.legval(v, [0.0] * j + [1.0])
            cols.append(pu * pv)
        return np.stack(cols, axis=1) if cols else np.zeros((u.size, 0))
    if basis == "bspline":
        bu = _bspline_1d(u, order)
        bv = _bspline_1d(v, order)
        tensor = (bu[:, :, None] * bv[:, None, :]).reshape(u.size, order * order)
        return tensor @ _bspline_constraint(order)
    raise ConfigError(f"unknown smooth basis {basis!r}; valid: poly, bspline.")
