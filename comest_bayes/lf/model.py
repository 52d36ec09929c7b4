"""The forward model of number counts through completeness and photometric transfer, and its fit.

An extended Poisson likelihood of the detections' measured magnitudes (and positions) for a count
model ``phi(m | theta)``, the completeness posterior ``f(m, x)`` and the transfer ``K(m_obs | m)``,
with the completeness uncertainty sampled jointly, marginalised, or fixed (``docs/lf.md``).
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass
from typing import Callable
import numpy as np
from comest_bayes.jaxnum import jax, jnp
from comest_bayes.lf.counts import CountModel
from comest_bayes.errors import ConfigError, InputError
from comest_bayes.recover.transfer import PhotometricTransfer
from comest_bayes.lf import MODES
from comest_bayes.lf.result import LFResult, PERCENTILES
from comest_bayes.bayes.outcomes import Covariates
from comest_bayes.bayes.inference import fit
from comest_bayes.seeding import Stream, int_seed_for, rng_for
from comest_bayes.bayes.model import cell_logs

__all__ = ['LFInputs', 'LFModel', 'build_inputs', 'completeness_arrays', 'expected_bins', 'fit_counts', 'effective_area', 'LFWarning']

#: Grid defaults (mag).
GRID_STEP = 0.02
GRID_BELOW = 1.0
GRID_ABOVE = 2.0
#: The pooled draws of the marginal mode are thinned to at most this many.
MAX_POOLED = 20000
#: Completeness below this at the faint end of the range triggers the "completeness ~0" warning.
LOW_COMPLETENESS = 0.05
#: Joint mode, completeness depending on position through the depth only: ``f`` is evaluated on this many
#: depth nodes spanning the objects' depths and interpolated linearly to each object (instead of at every
#: object: N x M link evaluations per walker, which cost minutes and gigabytes on a 3000^2 tile).
DEPTH_NODES = 49


class LFWarning(UserWarning):
    """A luminosity-function fit ran but something deserves attention."""


# --------------------------------------------------------------------------- inputs


@dataclass
class LFInputs:
    """Arrays of one fit (pure data).

    Attributes
    ----------
    mags : ndarray, shape (N,)
        Measured magnitudes of the catalog objects in range.
    x, y : ndarray, shape (N,), or None
        Their 0-based pixel positions (None when unknown).
    area_deg2 : float
        Effective (unmasked) area, deg^2.
    mag_range : (float, float)
        Measured-magnitude range ``[lo, hi)``.
    grid : ndarray, shape (M,)
        True-magnitude grid (uniform step ``dt``).
    dt : float
    kernel : ndarray, shape (N, M)
        ``K(m_obs_i | grid_j)`` per mag.
    p_in : ndarray, shape (M,)
        ``P(lo <= m_obs < hi | grid_j, detected)``.
    obs_edges : ndarray, shape (K + 1,)
        Bin edges of the observed-counts plot.
    bin_kernel : ndarray, shape (K, M)
        Probability of each observed bin given ``grid_j``.
    transfer : PhotometricTransfer or None
        None for the identity transfer.
    """

    mags: np.ndarray
    x: np.ndarray | None
    y: np.ndarray | None
    area_deg2: float
    mag_range: tuple
    grid: np.ndarray
    dt: float
    kernel: np.ndarray
    p_in: np.ndarray
    obs_edges: np.ndarray
    bin_kernel: np.ndarray
    transfer: PhotometricTransfer | None = None

    @property
    def n(self) -> int:
        return int(self.mags.size)


def _identity_kernel(m_obs, grid, dt):
    """Linear-interpolation weights per mag: ``sum_j K_ij g_j dt = g(m_obs_i)`` (piecewise linear)."""
    u = (np.asarray(m_obs, float)[:, None] - grid[None, :]) / dt
    return np.clip(1.0 - np.abs(u), 0.0, None) / dt


def build_inputs(mags, *, area_deg2: float, mag_range, transfer: PhotometricTransfer | None, x=None, y=None,
                 dt: float = GRID_STEP, below: float = GRID_BELOW, above: float = GRID_ABOVE,
                 bin_width: float = 0.25) -> LFInputs:
    """Grid, kernels and acceptance for a catalog.

    Parameters
    ----------
    mags : array, shape (N0,)
        Measured magnitudes; those outside ``[lo, hi)`` or not finite are dropped
        (with their positions).
    area_deg2 : float
        Effective area, deg^2 (> 0).
    mag_range : (lo, hi)
        Measured-magnitude range fitted.
    transfer : PhotometricTransfer or None
        None: identity transfer (``m_obs = m``), for comparisons.
    x, y : array, shape (N0,), optional
        Pixel positions (needed for a spatial completeness at each object).
    dt, below, above : float
        Grid step and extent below ``lo`` / above ``hi`` (mag).
    bin_width : float
        Width of the observed-count bins (plots and binned comparisons).

    Raises
    ------
    InputError
        Bad range or area; no object in range.
    """
    lo, hi = (float(v) for v in mag_range)
    if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
        raise InputError(f"magnitude range must be two finite numbers lo < hi, got {mag_range!r}.")
    if not (area_deg2 > 0 and math.isfinite(area_deg2)):
        raise InputError(f"effective area must be a positive number of deg^2, got {area_deg2!r}.")
    m = np.asarray(mags, float).ravel()
    keep = np.isfinite(m) & (m >= lo) & (m < hi)
    if not keep.any():
        raise InputError(f"no catalog object has a magnitude in [{lo}, {hi}) ({m.size} objects, "
                         f"{int(np.isfinite(m).sum())} with a finite magnitude"
                         + (f", spanning {np.nanmin(m):.2f}-{np.nanmax(m):.2f}" if np.isfinite(m).any() else "")
                         + "); choose a range that contains the catalog's magnitudes.")
    xs = None if x is None else np.asarray(x, float).ravel()[keep]
    ys = None if y is None else np.asarray(y, float).ravel()[keep]
    m = m[keep]
    grid = np.arange(lo - below, hi + above + 0.5 * dt, dt)
    nb = max(1, int(round((hi - lo) / bin_width)))
    edges = np.linspace(lo, hi, nb + 1)
    if transfer is None:
        kernel = _identity_kernel(m, grid, dt)
        # fraction of the trapezoid cell of node j inside [lo, hi): the integral of the hat function
        cdf = lambda e: np.clip(  # noqa: E731 - integral of the hat of node j up to e
            np.where(e[:, None] <= grid[None, :], 0.5 * np.clip(1 + (e[:, None] - grid[None, :]) / dt, 0, 1) ** 2,
                     1.0 - 0.5 * np.clip(1 - (e[:, None] - grid[None, :]) / dt, 0, 1) ** 2), 0, 1)
        c = cdf(edges)
        bin_kernel = np.diff(c, axis=0)
        p_in = c[-1] - c[0]
    else:
        kernel = transfer.matrix(m, grid)
        bin_kernel = transfer.bin_matrix(edges, grid)
        p_in = (transfer.cdf_at(np.array([hi]), grid) - transfer.cdf_at(np.array([lo]), grid)).ravel()
    return LFInputs(mags=m, x=xs, y=ys, area_deg2=float(area_deg2), mag_range=(lo, hi), grid=grid, dt=float(dt),
                    kernel=kernel, p_in=np.clip(p_in, 0.0, None), obs_edges=edges, bin_kernel=bin_kernel,
                    transfer=transfer)


# --------------------------------------------------------------------------- completeness on the grid


def _spatial(post) -> bool:
    """True when the completeness varies over the image (depth or smooth spatial term)."""
    return post is not None and bool(post.spec.uses_depth or post.spec.uses_position)


def _positions_cov(post, x, y):
    """Depth (P, 1), size (P, 1) and smooth basis (P, 1, J) at pixel positions, for the JAX link."""
    cov = post.covariates(np.zeros(len(x)), x, y)
    basis = post.model.basis(cov)
    return cov.depth[:, None], np.zeros((len(x), 1)), basis[:, None, :]


def _cells_cov(post):
    """The posterior's footprint cells as JAX-link covariates: depth (P, 1), size (P, 1), basis (P, 1, J), weight (P,).

    The cells cover every unmasked pixel (:class:`comest_bayes.bayes.posterior.Footprint`), so a weighted sum over them
    is the exact footprint average; a model with no spatial term needs one cell.
    """

    cells = post.footprint_cells()
    if not _spatial(post):
        depth, u, v, weight = cells.depth[:1], cells.u[:1], cells.v[:1], np.ones(1)
    else:
        depth, u, v, weight = cells.depth, cells.u, cells.v, np.asarray(cells.weight, float)
    cov = Covariates.make(np.zeros(len(depth)), depth, u, v)
    basis = post.model.basis(cov)
    return cov.depth[:, None], np.zeros((len(depth), 1)), basis[:, None, :], weight / weight.sum()


def _depth_nodes(depth, n: int = 0):
    """Nodes spanning ``depth`` and each value's linear-interpolation place on them.

    Returns
    -------
    nodes : ndarray, shape (G,)
    index : ndarray of int, shape (N,)
        Lower node of each value (``index + 1`` is the upper one).
    frac : ndarray, shape (N,)
        Weight of the upper node (0 at the lower node, 1 at the upper).
    """
    n = n or DEPTH_NODES
    depth = np.asarray(depth, float)
    lo, hi = float(depth.min()), float(depth.max())
    if hi - lo < 1e-6:
        hi = lo + 1e-6
    nodes = np.linspace(lo, hi, max(2, int(n)))
    index = np.clip(np.searchsorted(nodes, depth, side="right") - 1, 0, nodes.size - 2)
    frac = np.clip((depth - nodes[index]) / (nodes[index + 1] - nodes[index]), 0.0, 1.0)
    return nodes, index, frac


def completeness_arrays(post, thetas, inputs: LFInputs, *, objects: bool = True, chunk: int = 64):
    """Completeness of each draw on the grid: at the objects and averaged over the footprint.

    Parameters
    ----------
    post : CompletenessPosterior
    thetas : array, shape (S, D)
        Completeness parameters (unconstrained).
    inputs : LFInputs
    objects : bool, default True
        Also evaluate ``f`` at each object (else ``f_obj`` is None): that array
        holds S x N x M numbers, so ask for it only for a few draws.

    Returns
    -------
    f_obj : ndarray, shape (S, N, M) or (S, 1, M), or None
        ``f(grid_j, x_i)``; one row for all objects when the model has no
        spatial term or the positions are unknown.
    f_bar : ndarray, shape (S, M)
        Footprint average (exact over the posterior's footprint cells).
    """
    thetas = np.atleast_2d(np.asarray(thetas, float))
    grid = inputs.grid
    if not _spatial(post):
        f = post.model.prob(thetas, post.covariates(grid, 0.0, 0.0)).reshape(len(thetas), 1, grid.size)
        return (f if objects else None), f[:, 0, :].copy()
    fb = post.average_of(thetas, grid)
    if not objects:
        return None, fb
    if inputs.x is None:
        return fb[:, None, :].copy(), fb
    n = inputs.n
    out = np.empty((len(thetas), n, grid.size))
    for s in range(0, n, chunk):
        xs, ys = inputs.x[s:s + chunk], inputs.y[s:s + chunk]
        cov = post.covariates(grid[None, :], xs[:, None], ys[:, None])
        out[:, s:s + chunk] = post.model.prob(thetas, cov).reshape(len(thetas), len(xs), grid.size)
    return out, fb


def _median_completeness(post, draws, inputs: LFInputs, *, chunk: int = 64):
    """Pointwise posterior median of f on the grid (objects, footprint): shapes (N or 1, M) and (M,).

    Objects are taken ``chunk`` at a time, so no draws x objects x grid array is ever held.
    """
    draws = np.atleast_2d(np.asarray(draws, float))
    grid = inputs.grid
    if not _spatial(post):
        f = post.model.prob(draws, post.covariates(grid, 0.0, 0.0)).reshape(len(draws), grid.size)
        med = np.median(f, axis=0)
        return med[None, :], med
    fbar_med = np.median(completeness_arrays(post, draws, inputs, objects=False)[1], axis=0)
    if inputs.x is None:  # no positions: every object sees the footprint average
        return fbar_med[None, :], fbar_med
    med = np.empty((inputs.n, grid.size))
    if not post.spec.uses_position:  # depth only: f on DEPTH_NODES depths, linear in between (as the joint mode)

        depth = post.covariates(np.zeros(inputs.n), inputs.x, inputs.y).depth
        nodes, idx, frac = _depth_nodes(depth)
        cov = Covariates.make(np.tile(grid, nodes.size), np.repeat(nodes, grid.size))
        f_nodes = post.model.prob(draws, cov).reshape(len(draws), nodes.size, grid.size)  # (S, G, M)
        for s in range(0, inputs.n, chunk):
            i, u = idx[s:s + chunk], frac[s:s + chunk, None]
            med[s:s + chunk] = np.median((1.0 - u) * f_nodes[:, i] + u * f_nodes[:, i + 1], axis=0)
        return med, fbar_med
    for s in range(0, inputs.n, chunk):
        xs, ys = inputs.x[s:s + chunk], inputs.y[s:s + chunk]
        cov = post.covariates(grid[None, :], xs[:, None], ys[:, None])
        med[s:s + chunk] = np.median(post.model.prob(draws, cov).reshape(len(draws), len(xs), grid.size), axis=0)
    return med, fbar_med


# --------------------------------------------------------------------------- the model (inference contract)


class LFModel:
    """Posterior of the count parameters (and, in joint mode, the completeness parameters).

    Satisfies the model contract of :mod:`comest_bayes.bayes.inference` (``names``,
    ``ndim``, ``initial``, ``log_prob``, ``value_and_grad``,
    ``log_prob_batch``, ``hessian``), so :func:`comest_bayes.bayes.inference.fit`
    finds the MAP, the Laplace approximation and emcee draws.

    Parameters
    ----------
    counts : CountModel
    inputs : LFInputs
    f_obj, f_bar : ndarray, shapes (N or 1, M) and (M,), optional
        Fixed completeness (modes ``fixed`` and ``marginal``).
    post : CompletenessPosterior, optional
        Joint mode: the completeness model, with ``prior_mean`` (D,) and
        ``prior_cov`` (D, D) of its unconstrained parameters.
    seed : int
        Seed of :meth:`initial`'s search.
    depth_nodes : int or None, default DEPTH_NODES
        Joint mode with a completeness that depends on position through the depth only: evaluate it
        on this many depth nodes and interpolate linearly to the objects (None or 0: at every object,
        exact and far slower).
    """

    def __init__(self, counts: CountModel, inputs: LFInputs, *, f_obj=None, f_bar=None, post=None,
                 prior_mean=None, prior_cov=None, seed: int = 0, depth_nodes: int | None = DEPTH_NODES):

        self.counts = counts
        self.inputs = inputs
        self.joint = post is not None
        self.depth_nodes = None
        self._per_object = False
        self._rng = rng_for(seed, Stream.LF_INITIAL)
        lo_b, hi_b = counts.prior_box()
        self._lo_b, self._hi_b = lo_b, hi_b
        dt = inputs.dt
        pc = counts.ndim
        log_area = math.log(inputs.area_deg2)
        grid = jnp.asarray(inputs.grid)
        lp_count = counts.log_prior
        lphi = counts.log_phi
        if not self.joint:
            if f_obj is None or f_bar is None:
                raise InputError("LFModel needs f_obj and f_bar (fixed completeness) or post (joint mode).")
            self.names = list(counts.names)
            self.comp_names = []
            self._data = (jnp.asarray(inputs.kernel * dt * np.asarray(f_obj, float)),
                          jnp.asarray(np.asarray(f_bar, float) * inputs.p_in * dt))

            def lam(theta, data):
                return jnp.exp(log_area) * jnp.sum(jnp.exp(lphi(theta, grid)) * data[1])

            def loglike(theta, data):
                kf, w_in = data
                lp = lphi(theta, grid)
                mx = jnp.max(lp)
                e = jnp.exp(lp - mx)  # phi / max(phi): lambda_i = max(phi) (K f dt e)_i, a matrix-vector product
                s = jnp.log(kf @ e) + mx
                return jnp.sum(s) + s.shape[0] * log_area - jnp.exp(log_area + mx) * jnp.sum(e * w_in)

            def logprior(theta):
                return lp_count(theta)
        else:

            st = post.model.structure
            # the sampled completeness parameters are the model's free ones (as in its posterior draws);
            # the link takes the full layout, with pinned slots (e.g. beta_depth of a model without depth)
            full = post.model.full_jax
            self.comp_names = [f"c:{n}" for n in post.names]
            self.names = list(counts.names) + self.comp_names
            mu = np.asarray(prior_mean, float)
            cov = np.asarray(prior_cov, float)
            d = mu.size
            cov = 0.5 * (cov + cov.T) + 1e-10 * np.eye(d) * max(1.0, float(np.trace(cov)) / d)
            chol = np.linalg.cholesky(cov)
            prec_chol = np.linalg.inv(chol)
            log_norm = -np.sum(np.log(np.diag(chol))) - 0.5 * d * math.log(2.0 * math.pi)
            fd, fs, fb, fw = _cells_cov(post)  # exact footprint average: weighted cells
            per_object = _spatial(post) and inputs.x is not None
            self._per_object = per_object
            avg_objects = _spatial(post) and inputs.x is None
            # depth-only models: f at the objects from DEPTH_NODES depth nodes, linear in between
            nodes = per_object and not post.spec.uses_position and bool(depth_nodes)
            if nodes:

                obj_depth = post.covariates(np.zeros(inputs.n), inputs.x, inputs.y).depth
                dnodes, idx, frac = _depth_nodes(obj_depth, depth_nodes)
                ncov = Covariates.make(np.zeros(dnodes.size), dnodes, 0.0, 0.0)
                od, os_ = dnodes[:, None], np.zeros((dnodes.size, 1))
                ob = post.model.basis(ncov)[:, None, :]
                interp = (jnp.asarray(idx), jnp.asarray(frac))
                self.depth_nodes = dnodes
            elif per_object:
                od, os_, ob = _positions_cov(post, inputs.x, inputs.y)
            else:  # not spatial (one row serves all), or no positions (objects see the footprint average)
                od, os_, ob = fd[:1], fs[:1], fb[:1]
            self._data = (jnp.asarray(inputs.kernel * dt), jnp.asarray(inputs.p_in * dt), jnp.asarray(od),
                          jnp.asarray(os_), jnp.asarray(ob), jnp.asarray(fd), jnp.asarray(fs), jnp.asarray(fb),
                          jnp.asarray(mu), jnp.asarray(prec_chol), jnp.asarray(fw))
            mrow = grid[None, :]

            def lam(theta, data):
                w_in, fd, fs, fb, fw = data[1], data[5], data[6], data[7], data[10]
                logf_foot, _ = cell_logs(st, full(theta[pc:]), mrow, fd, fs, fb)
                f_bar = fw @ jnp.exp(logf_foot)
                return jnp.exp(log_area) * jnp.sum(jnp.exp(lphi(theta[:pc], grid)) * f_bar * w_in)

            def loglike(theta, data):
                k_dt, w_in, od, os_, ob, fd, fs, fb, mu, pc_, fw = data
                t, c = theta[:pc], full(theta[pc:])
                lp = lphi(t, grid)
                mx = jnp.max(lp)
                e = jnp.exp(lp - mx)
                logf_foot, _ = cell_logs(st, c, mrow, fd, fs, fb)  # (P, M)
                f_bar = fw @ jnp.exp(logf_foot)
                if nodes:
                    f_nodes = jnp.exp(cell_logs(st, c, mrow, od, os_, ob)[0])  # (G, M)
                    i, u = interp
                    f_obj = (1.0 - u)[:, None] * f_nodes[i] + u[:, None] * f_nodes[i + 1]  # (N, M)
                    s = jnp.log(jnp.sum(k_dt * f_obj * e[None, :], axis=1)) + mx
                elif per_object:
                    f_obj = jnp.exp(cell_logs(st, c, mrow, od, os_, ob)[0])  # (N, M)
                    s = jnp.log(jnp.sum(k_dt * f_obj * e[None, :], axis=1)) + mx
                else:
                    f_row = f_bar if avg_objects else jnp.exp(logf_foot[0])
                    s = jnp.log(k_dt @ (f_row * e)) + mx
                return jnp.sum(s) + s.shape[0] * log_area - jnp.exp(log_area + mx) * jnp.sum(e * f_bar * w_in)

            def logprior(theta):
                c = theta[pc:]
                z = self._data[9] @ (c - self._data[8])
                return lp_count(theta[:pc]) + log_norm - 0.5 * jnp.sum(z * z)

            self._prior_mean = mu
        self.ndim = len(self.names)
        self._pc = pc
        #: Rows per compiled batch call (fixed: one compiled shape).  Vectorised rows hold about 2^22 values
        #: (32 MB) of an objects x grid array together; per-object models run their rows one at a time.
        self.chunk = 64 if self._per_object else int(max(8, min(256, (1 << 22) // (inputs.n + inputs.grid.size))))

        def log_prob(theta, data):
            v = logprior(theta) + loglike(theta, data)
            return jnp.where(jnp.isnan(v) | (v == jnp.inf), -jnp.inf, v)

        def value_and_grad(theta, data):
            v, g = jax.value_and_grad(log_prob)(theta, data)
            return v, jnp.where(jnp.isfinite(g), g, 0.0)

        self._lp = jax.jit(log_prob)
        self._lam = jax.jit(lam)
        self._lam_batch = jax.jit(jax.vmap(lam, in_axes=(0, None)))
        self._ll = jax.jit(loglike)
        self._vg = jax.jit(value_and_grad)
        if self._per_object:
            # N x M values per row: vectorising over rows would hold rows x N x M of them, and XLA vectorises
            # the per-object gathers poorly (2x slower per row on a demo tile); one row after another instead
            self._batch = jax.jit(lambda ts, data: jax.lax.map(lambda t: log_prob(t, data), ts))
        else:
            self._batch = jax.jit(jax.vmap(log_prob, in_axes=(0, None)))
        self._hess = jax.jit(jax.hessian(log_prob))

    def with_completeness(self, f_obj, f_bar) -> "LFModel":
        """Same compiled functions, another fixed completeness (marginal mode)."""
        if self.joint:
            raise InputError("with_completeness applies to fixed-completeness models only.")
        other = object.__new__(LFModel)
        other.__dict__.update(self.__dict__)
        other._data = (jnp.asarray(self.inputs.kernel * self.inputs.dt * np.asarray(f_obj, float)),
                       jnp.asarray(np.asarray(f_bar, float) * self.inputs.p_in * self.inputs.dt))
        return other

    # -- contract -------------------------------------------------------------------
    def log_prob(self, theta) -> float:
        return float(self._lp(jnp.asarray(theta, dtype=jnp.float64), self._data))

    def log_likelihood(self, theta) -> float:
        return float(self._ll(jnp.asarray(theta, dtype=jnp.float64), self._data))

    def value_and_grad(self, theta):
        v, g = self._vg(jnp.asarray(theta, dtype=jnp.float64), self._data)
        return float(v), np.array(g)

    def _chunked(self, fn, thetas) -> np.ndarray:
        """``fn`` over the rows of ``thetas`` in blocks of :attr:`chunk` rows (the last one padded).

        A vectorised call holds a few arrays of rows x objects x grid values: unbounded, 600 starting draws on
        a demo tile's 1500 objects took gigabytes.  Fixed-size blocks bound that and compile once.
        """
        thetas = np.atleast_2d(np.asarray(thetas, float))
        n, c = len(thetas), self.chunk
        if n <= c:
            return np.asarray(fn(jnp.asarray(thetas), self._data))
        out = np.empty(n)
        for s in range(0, n, c):
            block = thetas[s:s + c]
            nb = len(block)
            if nb < c:
                block = np.concatenate([block, np.repeat(block[-1:], c - nb, axis=0)])
            out[s:s + nb] = np.asarray(fn(jnp.asarray(block), self._data))[:nb]
        return out

    def log_prob_batch(self, thetas) -> np.ndarray:
        return self._chunked(self._batch, thetas)

    def hessian(self, theta) -> np.ndarray:
        return np.array(self._hess(jnp.asarray(theta, dtype=jnp.float64), self._data))

    def initial(self, ndraws: int | None = None) -> np.ndarray:
        """Best of ``ndraws`` prior draws of the shape parameters, each with its normalisation set so that
        the expected number equals the observed one (the first parameter is the log10 normalisation).

        Default 600 draws, 200 for a per-object joint model (each costs an objects x grid evaluation; the
        shape parameters of a count model are few)."""
        ndraws = ndraws or (200 if self._per_object else 600)
        rng = self._rng
        draws = self.counts.prior_draws(ndraws, rng)
        tail = self._prior_mean if self.joint else np.zeros(0)
        full = np.column_stack([draws, np.tile(tail, (ndraws, 1))]) if self.joint else draws
        lo_b, hi_b = self._lo_b, self._hi_b
        # expected count at the draw, then shift log10 norm to match N
        with np.errstate(over="ignore"):
            nexp = self._chunked(self._lam_batch, full)
        with np.errstate(divide="ignore", invalid="ignore"):
            shift = np.log10(self.inputs.n / nexp)
        full[:, 0] = np.clip(full[:, 0] + np.where(np.isfinite(shift), shift, 0.0), lo_b[0] + 1e-9, hi_b[0] - 1e-9)
        lp = self.log_prob_batch(full)
        best = int(np.argmax(np.where(np.isfinite(lp), lp, -np.inf)))
        if not np.isfinite(lp[best]):
            raise InputError("could not find any count-model parameters with a finite posterior density; check the "
                             "priors of the count model against the catalog (e.g. the normalisation range).")
        return full[best]

    def expected_number(self, theta) -> float:
        """Expected number of detections in range, ``A int phi f_bar P_in dm``, at ``theta``."""
        with np.errstate(over="ignore"):
            return float(self._lam(jnp.asarray(theta, dtype=jnp.float64), self._data))


def effective_area(mask, pixel_scale_arcsec: float) -> float:
    """Unmasked area in deg^2: ``count(~mask) * (pixel_scale / 3600)**2``.

    Parameters
    ----------
    mask : ndarray of bool, shape (ny, nx)
        True = masked.
    pixel_scale_arcsec : float
        Pixel side (arcsec), e.g. from the WCS at the image centre.
    """
    mask = np.asarray(mask, bool)
    if not (pixel_scale_arcsec > 0):
        raise InputError(f"pixel scale must be positive, got {pixel_scale_arcsec!r}.")
    n = int((~mask).sum())
    if n == 0:
        raise InputError("the mask leaves no unmasked pixel: the effective area is 0.")
    return n * (float(pixel_scale_arcsec) / 3600.0) ** 2


def expected_bins(counts: CountModel, params, inputs: LFInputs, f_bar) -> np.ndarray:
    """Expected counts per observed bin, ``A dt sum_j phi_j f_bar_j B_kj``.

    Parameters
    ----------
    params : array, shape (P,) or (S, P)
    f_bar : array, shape (M,) or (S, M)

    Returns
    -------
    ndarray, shape (K,) or (S, K)
    """
    phi = counts.phi(params, inputs.grid)
    return inputs.area_deg2 * inputs.dt * (phi * np.asarray(f_bar)) @ inputs.bin_kernel.T


def _support_check(inputs: LFInputs, f_obj, f_bar, warn: list):
    """Drop objects no true magnitude can produce (their ln lambda would be -inf for every theta)."""
    f = np.asarray(f_obj)
    support = np.sum(inputs.kernel * (f if f.shape[0] == inputs.n else f[:1]), axis=1) * inputs.dt
    bad = ~(support > 1e-300)
    keep = ~bad
    if bad.any():
        msg = (f"{int(bad.sum())} of {inputs.n} objects have measured magnitudes (e.g. "
               f"{np.round(inputs.mags[bad][:3], 2).tolist()}) that no true magnitude on the grid can produce "
               f"through the measured transfer and completeness; they are left out of the fit.")
        warnings.warn(msg, LFWarning, stacklevel=3)
        warn.append(msg)
        if not keep.any():
            raise InputError("no catalog object in the range can be explained by the completeness and transfer of "
                             "this run (the range lies outside what the injections measured).")
        inputs = LFInputs(mags=inputs.mags[keep], x=None if inputs.x is None else inputs.x[keep],
                          y=None if inputs.y is None else inputs.y[keep], area_deg2=inputs.area_deg2,
                          mag_range=inputs.mag_range, grid=inputs.grid, dt=inputs.dt, kernel=inputs.kernel[keep],
                          p_in=inputs.p_in, obs_edges=inputs.obs_edges, bin_kernel=inputs.bin_kernel,
                          transfer=inputs.transfer)
    return inputs, keep


def _range_warnings(inputs: LFInputs, fbar_med, warn: list) -> None:
    lo, hi = inputs.mag_range
    f_hi = float(np.interp(hi, inputs.grid, fbar_med))
    if f_hi < LOW_COMPLETENESS:
        msg = (f"the completeness at the faint end of the range (m = {hi:.2f}) is {f_hi:.3f} < {LOW_COMPLETENESS}: "
               f"the counts there are barely observed, and the constraint comes from brighter magnitudes and the "
               f"model's form (no infinities arise; consider a brighter limit).")
        warnings.warn(msg, LFWarning, stacklevel=3)
        warn.append(msg)
    tr = inputs.transfer
    if tr is not None:
        t_lo, t_hi = tr.meta.get("true_range", [np.nan, np.nan])
        weight = fbar_med * inputs.p_in
        outside = ((inputs.grid < t_lo - 0.25) | (inputs.grid > t_hi + 0.25)) & (weight > 0.05 * weight.max())
        if outside.any():
            msg = (f"the fit uses true magnitudes {inputs.grid[outside].min():.2f}-{inputs.grid[outside].max():.2f} "
                   f"outside {t_lo:.2f}-{t_hi:.2f}, the true magnitudes of the detected injections that measured "
                   f"the photometric transfer, which is extrapolated there; inject over a wider range or narrow "
                   f"--mag-range.")
            warnings.warn(msg, LFWarning, stacklevel=3)
            warn.append(msg)


#: A count fit warns when the posterior predictive p-value of its binned counts (:func:`counts_check`) is
#: below this: the threshold of the completeness model's shape check (``bayes.checks``).
COUNTS_CHECK_P = 1e-3


def counts_check(observed, expected_draws, rng, *, replicates: int = 10) -> dict:
    """Posterior predictive check of the binned counts (Gelman, Meng & Stern 1996).

    For every posterior draw ``s`` the Poisson deviance ``2 sum_k [n_k ln(n_k / mu_sk) - (n_k - mu_sk)]``
    of the observed counts ``n`` against the draw's expected counts ``mu_s`` is compared with the
    deviance of ``replicates`` Poisson draws of ``mu_s`` against the same ``mu_s``; ``p_value`` is the
    fraction of replicates at least as far from their expectation as the data are.  A count model
    that cannot follow the counts (or a completeness of the wrong kind of source, which bends them)
    gives a small p.

    Parameters
    ----------
    observed : array, shape (K,)
    expected_draws : array, shape (S, K)
    rng : numpy.random.Generator
    replicates : int
        Poisson replicates per draw.

    Returns
    -------
    dict
        ``p_value``, ``deviance`` (median over the draws), ``bins`` (K) and ``replicates`` (total).
    """
    n = np.asarray(observed, float)
    mu = np.clip(np.asarray(expected_draws, float), 1e-300, None)

    def deviance(counts, means):
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(counts > 0, counts * np.log(counts / means), 0.0)
        return 2.0 * np.sum(t - (counts - means), axis=-1)

    d_obs = deviance(n[None, :], mu)                                    # (S,)
    rep = rng.poisson(np.broadcast_to(mu, (replicates,) + mu.shape))    # (R, S, K)
    d_rep = deviance(rep, mu[None])                                     # (R, S)
    return {"p_value": float(np.mean(d_rep >= d_obs[None, :])), "deviance": float(np.median(d_obs)),
            "bins": int(n.size), "replicates": int(d_rep.size)}


def fit_counts(inputs: LFInputs, counts, *, mode: str = "joint", post=None, f_fixed=None, seed: int = 0,
               ncomp: int = 16, min_ess: float = 400, max_steps: int = 20000, npred: int = 400,
               name: str = "lf", kind: str = "", log: Callable[[str], None] | None = None,
               sampler: str = "auto") -> LFResult:
    """Fit a count model to the catalog in ``inputs``.

    Parameters
    ----------
    inputs : LFInputs
        From :func:`build_inputs`.
    counts : CountModel, CountSpec or str
    mode : {"joint", "marginal", "fixed"}
        See ``docs/lf.md`` ("Completeness uncertainty").
    post : CompletenessPosterior, optional
        Required unless ``f_fixed`` is given (then only ``mode="fixed"``).
    f_fixed : (f_obj, f_bar), optional
        A known completeness on the grid: shapes (N or 1, M) and (M,).
    seed : int
        Root seed (MAP starts, walkers, emcee, completeness draws).
    ncomp : int, default 16
        Completeness draws of the marginal mode.
    min_ess : float, default 400
        Effective sample size of the count parameters (split over the
        ``ncomp`` fits in marginal mode, at least 100 each).
    max_steps : int
    npred : int, default 400
        Posterior draws used for the predicted counts and bands.
    sampler : {"auto", "emcee", "importance"}, default "auto"
        Passed to :func:`comest_bayes.bayes.inference.fit`: ``auto`` importance-samples the Laplace
        approximation and falls back to emcee when its Pareto k-hat or effective sample size fails
        (the joint mode has 20+ parameters with a spline completeness, where emcee alone needs
        thousands of steps); ``emcee`` is the reference.

    Returns
    -------
    LFResult
    """

    log = log or (lambda s: None)
    t0 = time.perf_counter()
    if mode not in MODES:
        raise ConfigError(f"mode must be one of {list(MODES)}, got {mode!r}.")
    counts = counts if isinstance(counts, CountModel) else CountModel(counts)
    if sampler == "auto" and counts.spec.sampler:
        sampler = counts.spec.sampler
        log(f"lf: sampler {sampler}, as the {counts.spec.name} specification asks for --sampler auto (its posterior "
            "can have several modes)")
    if post is None and f_fixed is None:
        raise InputError("fit_counts needs a completeness posterior (post=) or a known completeness (f_fixed=).")
    if post is None and mode != "fixed":
        raise InputError(f"mode {mode!r} needs a completeness posterior; with a known completeness use mode='fixed'.")
    warn: list[str] = []
    if post is not None and _spatial(post) and inputs.x is None:
        msg = ("the completeness model has a spatial term but the catalog has no positions: every object is given "
               "the footprint-average completeness.")
        warnings.warn(msg, LFWarning, stacklevel=2)
        warn.append(msg)
    if post is not None and post.spec.size_covariate:
        msg = ("the completeness model has a size term; catalog objects are given the reference size (the size "
               "covariate is set to 0).")
        warnings.warn(msg, LFWarning, stacklevel=2)
        warn.append(msg)

    if f_fixed is not None:
        f_obj_med, fbar_med = (np.asarray(a, float) for a in f_fixed)
        if f_obj_med.ndim == 1:
            f_obj_med = f_obj_med[None, :]
    else:
        sub = post.samples[np.linspace(0, len(post.samples) - 1, min(200, len(post.samples))).astype(int)]
        f_obj_med, fbar_med = _median_completeness(post, sub, inputs)
    n_before = inputs.n
    inputs, keep = _support_check(inputs, f_obj_med, fbar_med, warn)
    if f_obj_med.shape[0] == n_before and n_before > 1:
        f_obj_med = f_obj_med[keep]
    f_bright_end = float(np.interp(inputs.mag_range[0], inputs.grid, fbar_med))
    if f_bright_end < LOW_COMPLETENESS:
        # counts where almost nothing is detected constrain the counts model through its form and prior only
        # (a joint fit over such a range ran 14 minutes to warn of it at the end)
        raise InputError(f"the completeness is below {LOW_COMPLETENESS} over the whole magnitude range "
                         f"{inputs.mag_range[0]:.2f}-{inputs.mag_range[1]:.2f} ({f_bright_end:.3f} at its bright end): "
                         "the counts there say next to nothing about the number counts. Choose a range that starts "
                         "where the sources are detected (--mag-range; the default starts inside the injected range).")
    _range_warnings(inputs, fbar_med, warn)

    comp_samples = None
    comp_index = None
    diag: dict = {}
    if mode == "fixed":
        model = LFModel(counts, inputs, f_obj=f_obj_med, f_bar=fbar_med, seed=seed)
        res = fit(model, seed=int_seed_for(seed, Stream.LF, Stream.LF_FIXED), min_ess=min_ess, max_steps=max_steps,
                  sampler=sampler)
        samples = res.draws()
        diag = res.posterior.diagnostics.to_dict() if res.posterior is not None else {}
        log(f"lf: fixed completeness: {len(samples)} draws, {res.seconds:.1f} s")
    elif mode == "joint":
        mu = post.samples.mean(axis=0)
        cov = np.cov(post.samples, rowvar=False).reshape(len(mu), len(mu))
        model = LFModel(counts, inputs, post=post, prior_mean=mu, prior_cov=cov, seed=seed)
        # two MAP starts (as each fit of the marginal mode): initial() sits at the completeness prior's mean,
        # near the joint MAP; six (the default) cost a minute on a demo tile for the same optimum
        res = fit(model, seed=int_seed_for(seed, Stream.LF, Stream.LF_JOINT), nstarts=2, min_ess=min_ess, max_steps=max_steps,
                  sampler=sampler)
        draws = res.draws()
        samples, comp_samples = draws[:, :counts.ndim], draws[:, counts.ndim:]
        diag = res.posterior.diagnostics.to_dict() if res.posterior is not None else {}
        log(f"lf: joint with {len(mu)} completeness parameters: {len(samples)} draws, {res.seconds:.1f} s")
    else:
        rng = rng_for(seed, Stream.LF, Stream.LF_MARGINAL_DRAWS)
        pick = rng.choice(len(post.samples), size=min(ncomp, len(post.samples)), replace=False)
        base = None
        per, per_diag = [], []
        for k, idx in enumerate(pick):
            f_obj, f_bar = completeness_arrays(post, post.samples[idx][None, :], inputs)
            if base is None:
                base = LFModel(counts, inputs, f_obj=f_obj[0], f_bar=f_bar[0], seed=seed)
                model = base
            else:
                model = base.with_completeness(f_obj[0], f_bar[0])
            res = fit(model, seed=int_seed_for(seed, Stream.LF, Stream.LF_MARGINAL, k), nstarts=2,
                      min_ess=max(100.0, min_ess / len(pick)), max_steps=max_steps, sampler=sampler)
            per.append(res.draws())
            if res.posterior is not None:
                per_diag.append(res.posterior.diagnostics.to_dict())
        n_each = min(min(len(p) for p in per), max(1, MAX_POOLED // len(per)))
        take = [p[np.linspace(0, len(p) - 1, n_each).astype(int)] for p in per]
        samples = np.concatenate(take)
        comp_index = np.repeat(pick, n_each)
        diag = {"ncomp": int(len(pick)), "per_draw": per_diag,
                "converged": bool(all(d.get("converged", False) for d in per_diag))}
        log(f"lf: marginal over {len(pick)} completeness draws: {len(samples)} pooled draws")

    # ---- predictions ------------------------------------------------------------------
    sel = np.linspace(0, len(samples) - 1, min(npred, len(samples))).astype(int)
    phi_draws = counts.phi(samples[sel], inputs.grid)
    if mode == "fixed":
        fbar_draws = np.broadcast_to(fbar_med, phi_draws.shape)
    elif mode == "joint":
        fbar_draws = completeness_arrays(post, comp_samples[sel], inputs, objects=False)[1]
    else:
        uniq, inv = np.unique(comp_index[sel], return_inverse=True)
        fb_u = completeness_arrays(post, post.samples[uniq], inputs, objects=False)[1]
        fbar_draws = fb_u[inv]
    exp_draws = inputs.area_deg2 * inputs.dt * (phi_draws * fbar_draws) @ inputs.bin_kernel.T
    observed = np.histogram(inputs.mags, bins=inputs.obs_edges)[0].astype(float)
    spec = counts.spec
    check = counts_check(observed, exp_draws, rng_for(seed, Stream.LF, Stream.LF_CHECK))
    diag = {**diag, "counts_check": check}
    if check["p_value"] < COUNTS_CHECK_P:
        said = (f"p = {check['p_value']:.2g}" if check["p_value"] > 0 else f"p < {1 / check['replicates']:.2g}")
        msg = (f"the counts do not follow the fitted {spec.name} model: posterior predictive {said} (Poisson "
               f"deviance {check['deviance']:.1f} over {check['bins']} bins; see counts.png). Check the count model "
               "and the magnitude range, and that the completeness is that of sources like those counted (--kind): "
               "another kind's completeness bends the counts.")
        warnings.warn(msg, LFWarning, stacklevel=2)
        warn.append(msg)
    # the sampler's own warnings (not converged, ...) are the fit's warnings too, not only its diagnostics'
    sampler_said = diag.get("warnings", []) if mode != "marginal" else [w for d in per_diag for w in d.get("warnings", [])]
    for text in dict.fromkeys(sampler_said):
        if text not in warn:
            warn.append(text)
    meta = {"seed": int(seed), "seconds": round(time.perf_counter() - t0, 2),
            "completeness_model": None if post is None else post.spec.name,
            "transfer": "identity" if inputs.transfer is None else "measured",
            "grid_step": inputs.dt, "n_dropped": int(n_before - inputs.n)}
    return LFResult(name=name, kind=kind, mode=mode, spec=spec.to_dict(), names=list(counts.names),
                    samples=np.asarray(samples), comp_samples=comp_samples, grid=inputs.grid,
                    phi_bands=np.percentile(phi_draws, PERCENTILES, axis=0), obs_edges=inputs.obs_edges,
                    observed=observed, expected_bands=np.percentile(exp_draws, PERCENTILES, axis=0),
                    expected_draws=exp_draws, fbar_median=np.median(fbar_draws, axis=0),
                    area_deg2=inputs.area_deg2, mag_range=inputs.mag_range, n_objects=inputs.n, diagnostics=diag,
                    warnings=warn, meta=meta, transfer=inputs.transfer)
