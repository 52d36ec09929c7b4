"""The Bayesian completeness model: its parameter layout, priors and JAX log density.

:class:`CompletenessModel` evaluates ``f = floor + (A - floor) g((m50 - m) / w)`` (with the
depth, size and smooth spatial terms its :class:`~comest_bayes.bayes.spec.ModelSpec` names) on
compressed binomial cells, with value, gradient and Hessian compiled once per model structure and
cell-count bucket.  Parameters, priors and numerics are documented in ``docs/bayesian.md``
("The likelihood").
"""

from __future__ import annotations

import math
import warnings
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Mapping, NamedTuple
import numpy as np
from comest_bayes.jaxnum import jax, jnp, stored_jit
from scipy import special as _sp
from comest_bayes.errors import ConfigError, InputError
from comest_bayes.bayes.spec import ModelSpec, load_spec
from comest_bayes.bayes import links as _links, shapes as _shapes
from comest_bayes.bayes.shapes import SPLINE_H0, full_eta, spline_knots, monotone_spline, richards_logs
from comest_bayes.bayes.bases import smooth_basis, smooth_basis_names
from comest_bayes.bayes.links import Z_CLIP, safe_logaddexp, softplus, link_logs, logistic_mixture_logs, mixture_logs
from comest_bayes.bayes.outcomes import BinomialData, Covariates, _COVARIATE_GROUPS, covariates_needed

__all__ = ['CompletenessModel', 'THETA_BOUND', 'LOG_W_CLIP']

#: The density is -inf outside |theta_i| <= THETA_BOUND (and for NaN theta).  Every
#: meaningful value lies far inside (logit 1e4 is A = 1 - e^-10000, 1e4 mag is no
#: magnitude); the box keeps overflow, and NaN gradients, out of the arithmetic.
THETA_BOUND = 1e4

#: The total log w (log_w + w_depth * d) is clipped to +-LOG_W_CLIP before use
#: (w between 2e-22 and 5e21 mag), so that z stays finite.
LOG_W_CLIP = 50.0


# ---------------------------------------------------------------------------
# The model: static structure + pure jitted functions
# ---------------------------------------------------------------------------

class _Structure(NamedTuple):
    """Hashable layout of the full parameter vector (a static jit argument).

    Every model of one structure shares one compiled likelihood: which
    parameters are free is data (a mask), so the rungs of a model selection
    (logistic, Richards, spline; with or without depth and width terms) all
    run through the same compiled functions.
    """

    family: str       # "logistic", "probit", "pritchet", or "flex" (Richards link and monotone spline)
    free_A: bool
    free_floor: bool
    n_knots: int      # free knot log-rates of the monotone spline (0: no spline compiled in)
    n_smooth: int     # columns of the smooth spatial basis
    n_wfield: int = 0  # columns of the Legendre field of log w in (u, v) (width_order > 0)


#: Families of the links: the flexible rungs share the "flex" code path.
_FAMILY = {"logistic": "logistic", "probit": "probit", "pritchet": "pritchet", "richards": "flex", "spline": "flex"}

#: Number of times the log-probability has been traced (compiled), for tests.
TRACE_COUNT = {"log_prob": 0}


def _slots(st: _Structure) -> dict:
    """Static positions of every parameter group in the full vector."""
    i = 2 + int(st.free_A) + int(st.free_floor)
    return {"A": 2 if st.free_A else None, "floor": 2 + int(st.free_A) if st.free_floor else None,
            "beta_depth": i, "w_depth": i + 1, "beta_size": i + 2, "log_nu": i + 3,
            "eta": (i + 4, i + 4 + st.n_knots), "coef": (i + 4 + st.n_knots, i + 4 + st.n_knots + st.n_smooth),
            "wcoef": (i + 4 + st.n_knots + st.n_smooth, i + 4 + st.n_knots + st.n_smooth + st.n_wfield),
            "ndim": i + 4 + st.n_knots + st.n_smooth + st.n_wfield}


def _layout_names(st: _Structure, smooth_names, width_names=()) -> list[str]:
    names = ["m50_0", "log_w"]
    if st.free_A:
        names.append("logit_A")
    if st.free_floor:
        names.append("logit_floor")
    names += ["beta_depth", "w_depth", "beta_size", "log_nu"] + [f"eta_{k}" for k in range(st.n_knots)]
    return names + list(smooth_names) + list(width_names)


def _unpack(st: _Structure, theta):
    """Named quantities from the full unconstrained vector (JAX)."""
    sl = _slots(st)
    p = {"m50_0": theta[0], "log_w": theta[1], "log_A": None, "log_1mA": None,
         "log_floor": None, "log_1mfloor": None}
    if st.free_A:
        a = theta[sl["A"]]
        p["log_A"] = -softplus(-a)
        p["log_1mA"] = -softplus(a)
    if st.free_floor:
        b = theta[sl["floor"]]
        log_r, log_1mr = -softplus(-b), -softplus(b)
        if p["log_A"] is None:
            p["log_floor"], p["log_1mfloor"] = log_r, log_1mr
        else:
            # 1 - floor = (1 - A) + A (1 - r): a sum of positive terms, finite for any finite theta
            p["log_floor"] = p["log_A"] + log_r
            p["log_1mfloor"] = safe_logaddexp(p["log_1mA"], p["log_A"] + log_1mr)
    for key in ("beta_depth", "w_depth", "beta_size", "log_nu"):
        p[key] = theta[sl[key]]
    p["eta"] = theta[sl["eta"][0]:sl["eta"][1]]
    p["coef"] = theta[sl["coef"][0]:sl["coef"][1]]
    p["wcoef"] = theta[sl["wcoef"][0]:sl["wcoef"][1]]
    return p


def _m50_and_logw(st: _Structure, p, depth, size, basis):
    # basis columns: the smooth field of m50 (n_smooth), then the field of log w (n_wfield)
    m50 = p["m50_0"] + p["beta_depth"] * depth + p["beta_size"] * size
    if st.n_smooth:
        m50 = m50 + basis[..., :st.n_smooth] @ p["coef"]
    log_w = p["log_w"] + p["w_depth"] * depth
    if st.n_wfield:
        log_w = log_w + basis[..., st.n_smooth:st.n_smooth + st.n_wfield] @ p["wcoef"]
    return m50, jnp.clip(log_w, -LOG_W_CLIP, LOG_W_CLIP)


def cell_logs(st: _Structure, theta, m, depth, size, basis):
    """``log f`` and ``log(1 - f)`` at covariates, for the *full* parameter vector ``theta``."""
    p = _unpack(st, theta)
    m50, log_w = _m50_and_logw(st, p, depth, size, basis)
    logs = dict(log_A=p["log_A"], log_1mA=p["log_1mA"], log_floor=p["log_floor"], log_1mfloor=p["log_1mfloor"])
    if st.family == "flex":
        t = jnp.clip((m - m50) * jnp.exp(-log_w), -Z_CLIP, Z_CLIP)
        s = monotone_spline(t, jnp.clip(p["eta"], -50.0, 50.0)) if st.n_knots else -t
        log_g, log_1mg = richards_logs(s, jnp.clip(p["log_nu"], -20.0, 20.0))
        return mixture_logs(log_g, log_1mg, **logs)
    z = (m50 - m) * jnp.exp(-log_w)
    if st.family == "logistic":
        return logistic_mixture_logs(z, **logs)
    log_g, log_1mg = link_logs(z, st.family)
    return mixture_logs(log_g, log_1mg, **logs)


def _log_prior(st: _Structure, theta, prior):
    """Log prior of the free entries of the full vector.

    ``prior = (a, b, lnorm, active, log_tau)``: per slot the two arguments of
    its prior (``mu, sigma`` of a normal, ``a, b`` of a Beta on the sigmoid),
    its log normalising constant, 1 for free slots (0 for pinned ones, which
    contribute nothing), and the log smoothness scale of the spline's random
    walk.
    """
    a, b, lnorm, active, log_tau = prior
    sl = _slots(st)
    beta_slots = [j for j in (sl["A"], sl["floor"]) if j is not None]
    e0, e1 = sl["eta"]
    normal = np.array([j for j in range(sl["ndim"]) if j not in beta_slots and not e0 <= j < e1], dtype=np.int64)
    t = theta[normal]
    total = jnp.sum(active[normal] * (-0.5 * ((t - a[normal]) / b[normal]) ** 2 - lnorm[normal]))
    for j in beta_slots:  # Beta(a, b) on sigmoid(theta_j), with the Jacobian of the logit
        total = total + active[j] * (-a[j] * softplus(-theta[j]) - b[j] * softplus(theta[j]) - lnorm[j])
    if st.n_knots:
        # first-order random walk of the knot log-rates outward from the anchor (eta = 0 at t = 0), one
        # step per knot: increments ~ N(0, tau^2 h0), a walk in the warped coordinate s of the knots
        # (shapes.spline_knots), so its roughness per knot is the same near m50 and far out
        _, k0 = spline_knots(st.n_knots)
        eta = full_eta(theta[e0:e1], k0)
        var = jnp.exp(2.0 * log_tau) * SPLINE_H0
        rw = -0.5 * jnp.sum(jnp.diff(eta) ** 2) / var - 0.5 * st.n_knots * jnp.log(2.0 * math.pi * var)
        total = total + active[e0] * rw
    return total


def _log_likelihood(st: _Structure, theta, data):
    m, depth, size, basis, n, k = data
    log_f, log_1mf = cell_logs(st, theta, m, depth, size, basis)
    nk = n - k
    # 0 * (-inf) must count as 0: a cell with no failures does not care about log(1 - f);
    # padding cells (n = k = 0) contribute nothing.
    terms = jnp.where(k > 0, k * log_f, 0.0) + jnp.where(nk > 0, nk * log_1mf, 0.0)
    return jnp.sum(terms)


def _sanitize(x):
    return jnp.where(jnp.isnan(x) | (x == jnp.inf), -jnp.inf, x)


def _in_box(theta):
    return jnp.all(jnp.abs(theta) <= THETA_BOUND)  # False for NaN too


def _log_prob(st: _Structure, theta, data, prior):
    TRACE_COUNT["log_prob"] += 1  # runs at trace time only
    ok = _in_box(theta)
    safe = jnp.where(ok, theta, 0.0)  # evaluate at a harmless point outside the box: no NaN gradients
    return jnp.where(ok, _sanitize(_log_prior(st, safe, prior) + _log_likelihood(st, safe, data)), -jnp.inf)


def _log_prob_free(st, theta, pinned, free_idx, data, prior):
    """:func:`_log_prob` of the free parameters ``theta`` (the pinned ones set from ``pinned``): traceable."""
    return _log_prob(st, pinned.at[free_idx].set(theta), data, prior)


def _value_and_grad(st, theta, data, prior):
    v, g = jax.value_and_grad(_log_prob, argnums=1)(st, theta, data, prior)
    g = jnp.where(jnp.isfinite(v), g, jnp.where(jnp.isfinite(g), g, 0.0))
    return v, g


def _log_prob_batch(st, thetas, data, prior, batch):
    # lax.map with batch_size = W is vmap; smaller batches keep W * G temporaries in cache for large G.
    return jax.lax.map(lambda t: _log_prob(st, t, data, prior), thetas, batch_size=batch)


def _cell_logs_batch(st, thetas, m, depth, size, basis):
    lf, l1 = jax.vmap(lambda t: cell_logs(st, t, m, depth, size, basis))(thetas)
    return jnp.stack([lf, l1], axis=-1)


def _prob_m50_batch(st, thetas, m, depth, size, basis):
    def one(t):
        p = _unpack(st, t)
        m50, _ = _m50_and_logw(st, p, depth, size, basis)
        log_f, _ = cell_logs(st, t, m, depth, size, basis)
        return jnp.exp(log_f), m50
    return jax.vmap(one)(thetas)


def _average_batch(st, thetas, mags, depth, size, basis, weight):
    """Weighted footprint average of f, shape (S, M); cells (P,) broadcast against magnitudes (M,)."""
    def one(t):
        log_f, _ = cell_logs(st, t, mags[None, :], depth[:, None], size[:, None], basis[:, None, :])
        return weight @ jnp.exp(log_f)
    return jax.vmap(one)(thetas)


def _average_at_batch(st, thetas, mags, depth, size, basis, weight):
    """Weighted footprint average of f for each (draw, magnitude) pair: shape (S,)."""
    def one(t, mag):
        log_f, _ = cell_logs(st, t, mag, depth, size, basis)
        return weight @ jnp.exp(log_f)
    return jax.vmap(one)(thetas, mags)


def _cell_grads(st, theta, m, depth, size, basis):
    """Gradients of every cell's log f and log(1 - f) with respect to the full theta: (G, 2, D)."""
    def logs(t):
        lf, l1 = cell_logs(st, t, m, depth, size, basis)
        return jnp.stack([lf, l1], axis=-1)
    return jax.jacfwd(logs)(theta), logs(theta)


# stored_jit: jax.jit whose traced programs later processes load from disk (comest_bayes.jaxnum); the
# stored programs are keyed on a digest of every file whose code they trace
_SOURCES = (__file__, _links.__file__, _shapes.__file__)
_jit_average_batch = stored_jit(_average_batch, 0, sources=_SOURCES)
_jit_average_at_batch = stored_jit(_average_at_batch, 0, sources=_SOURCES)
_jit_cell_grads = stored_jit(_cell_grads, 0, sources=_SOURCES)
_jit_log_prob = stored_jit(_log_prob, 0, sources=_SOURCES)
_jit_log_prior = jax.jit(lambda st, theta, prior: jnp.where(_in_box(theta), _sanitize(_log_prior(st, theta, prior)),
                                                            -jnp.inf), static_argnums=0)
_jit_log_likelihood = jax.jit(
    lambda st, theta, data: jnp.where(_in_box(theta), _sanitize(_log_likelihood(st, theta, data)), -jnp.inf),
    static_argnums=0)
_jit_value_and_grad = stored_jit(_value_and_grad, 0, sources=_SOURCES)
# evaluated at every step of emcee's walkers: XLA's default options, which run it faster (jaxnum)
_jit_log_prob_batch = stored_jit(_log_prob_batch, (0, 4), sources=_SOURCES, quick_compile=False)
_jit_cell_logs_batch = stored_jit(_cell_logs_batch, 0, sources=_SOURCES)
_jit_prob_m50_batch = stored_jit(_prob_m50_batch, 0, sources=_SOURCES)

#: log_prob_batch vectorises over at most this many (walker, cell) pairs at once.
BATCH_ELEMENTS = 1 << 20

#: Predictions (:meth:`CompletenessModel.prob`, ``m50``) evaluate the draws in blocks of this many.
PREDICT_DRAWS = 256

#: From this many cells on, :func:`padded_size` grows in quarter steps (of the power of two below).
LARGE_PAD = 4096

#: Cell counts are padded up to the next of these sizes (cells with n = 0), so that data sets of
#: similar size share one compiled likelihood: the steps waste at most a third of the work.
def padded_size(g: int) -> int:
    """Smallest of 256, 384, 512, 768, 1024, 1536, ..., 4096 (``256 * 2^j`` and ``384 * 2^j``), then 5120,
    6144, 7168, 8192, 10240, ... (quarters of the power of two below) that holds ``g`` cells.

    Steps of 1.5 and 4/3 rather than finer ones: a process loads each compiled program once (25-45 ms
    each, some fifteen per model layout), so data sets of similar size should share one size.  Against
    powers of two alone, every likelihood evaluation of the demo's fits runs over 768 instead of 1024
    cells (empty ones, n = k = 0, add nothing).  Inside :func:`padding_floor` a larger size is used
    when it is no larger than the power of two that holds ``g``: the fits of one worker (the kinds of a
    run, whose cell counts may straddle a step) then share one size, as they did with powers of two.
    """
    size = 256
    while size < g:
        if size >= LARGE_PAD:
            # large cell counts (position-resolved fits): steps of a quarter of the power of two below, so
            # that at most a fifth of the work is padding; their programs are traced once per fit anyway
            size += (1 << (size.bit_length() - 1)) // 4
        else:
            size = size * 3 // 2 if size & (size - 1) == 0 else size * 4 // 3
    floor = _PAD_FLOOR[0]
    if size < floor:
        pow2 = 256
        while pow2 < g:
            pow2 *= 2
        if floor <= pow2:
            return floor
    return size


_PAD_FLOOR = [0]


@contextmanager
def padding_floor(size: int):
    """Within the block, :func:`padded_size` pads to ``size`` any cell count it may hold without more
    padding than the power of two above it would add (see there); ``size`` 0 changes nothing."""
    before = _PAD_FLOOR[0]
    _PAD_FLOOR[0] = int(size)
    try:
        yield
    finally:
        _PAD_FLOOR[0] = before


def _prior_args(spec_prior: dict) -> tuple[float, float, float]:
    """(a, b, log normalising constant) of one prior."""
    if spec_prior["dist"] == "normal":
        mu, sigma = float(spec_prior["mu"]), float(spec_prior["sigma"])
        return mu, sigma, math.log(sigma) + 0.5 * math.log(2.0 * math.pi)
    a, b = float(spec_prior["a"]), float(spec_prior["b"])
    # log B(a, b) from scipy (jax's betaln is good to ~1e-8 only)
    return a, b, float(_sp.betaln(a, b))


def _np_link_logs(z: np.ndarray, link: str):
    z = np.clip(z, -Z_CLIP, Z_CLIP)
    if link in ("logistic", "richards", "spline"):
        log_g = -np.logaddexp(0.0, -z)
        return log_g, log_g - z
    if link == "probit":
        return _sp.log_ndtr(z), _sp.log_ndtr(-z)
    a = np.abs(z)
    r = np.sqrt(1.0 + a * a)
    q = 0.5 / (r * (r + a))
    log_q = np.log(q)
    log_1mq = np.log1p(-q)
    return np.where(z >= 0, log_1mq, log_q), np.where(z >= 0, log_q, log_1mq)


@dataclass(frozen=True)
class ModelLayout:
    """The compiled structure several specs share (see :func:`shared_layout`).

    Attributes
    ----------
    structure : _Structure
        Family, free plateau/floor, spline knots, smooth and width-field columns.
    smooth_basis, smooth_order : str, int
        The smooth basis of the layout (used by every spec with a smooth term).
    width_order : int
        Total degree of the Legendre field of log w (used by every spec with ``width_order > 0``).
    """

    structure: _Structure
    smooth_basis: str = "poly"
    smooth_order: int = 2
    width_order: int = 0

    @property
    def smooth_names(self) -> list[str]:
        return smooth_basis_names(self.smooth_basis, self.smooth_order) if self.structure.n_smooth else []

    @property
    def width_names(self) -> list[str]:
        return width_field_names(self.width_order) if self.structure.n_wfield else []


def width_field_names(order: int) -> list[str]:
    """Names of the coefficients of the Legendre field of log w: ``w_ij`` (degrees in u, v)."""
    return ["w_" + name[2:] for name in smooth_basis_names("poly", order)] if order > 0 else []


def _spec_layout(spec: ModelSpec) -> ModelLayout:
    n_smooth = len(smooth_basis_names(spec.smooth_basis, spec.smooth_order)) if spec.uses_smooth else 0
    st = _Structure(family=_FAMILY[spec.link], free_A=spec.plateau == "free", free_floor=spec.floor == "free",
                    n_knots=spec.spline_knots if spec.link == "spline" else 0, n_smooth=n_smooth,
                    n_wfield=len(width_field_names(spec.width_order)))
    return ModelLayout(st, spec.smooth_basis, spec.smooth_order, spec.width_order)


def shared_layout(specs) -> ModelLayout:
    """One layout that every spec of ``specs`` fits into, so all of them share one compile.

    Specs of the logistic, Richards and spline links with the same plateau,
    floor and smooth basis share the "flex" family (a logistic is its member
    with ``nu = 1`` and a straight spline); other combinations raise
    :class:`ConfigError` (fit those separately).
    """
    specs = [load_spec(s) for s in specs]
    layouts = [_spec_layout(s) for s in specs]
    if len(layouts) == 1:
        return layouts[0]
    sts = [lay.structure for lay in layouts]
    families = {st.family for st in sts}
    if not families <= {"logistic", "flex"}:
        raise ConfigError(f"specs {[s.name for s in specs]} mix links of different families "
                          f"({sorted(families)}); only logistic, richards and spline specs share a layout.")
    if len({(st.free_A, st.free_floor) for st in sts}) != 1:
        raise ConfigError(f"specs {[s.name for s in specs]} differ in a fixed plateau or floor; they cannot share "
                          "a layout.")
    knots = {st.n_knots for st in sts if st.n_knots}
    if len(knots) > 1:
        raise ConfigError(f"spline specs with different numbers of knots {sorted(knots)} cannot share a layout.")
    smooth = {(lay.smooth_basis, lay.smooth_order) for lay in layouts if lay.structure.n_smooth}
    if len(smooth) > 1:
        raise ConfigError(f"specs with different smooth bases {sorted(smooth)} cannot share a layout.")
    basis, order = next(iter(smooth)) if smooth else ("poly", 2)
    worders = {lay.width_order for lay in layouts if lay.structure.n_wfield}
    if len(worders) > 1:
        raise ConfigError(f"specs with different width_order {sorted(worders)} cannot share a layout.")
    worder = next(iter(worders)) if worders else 0
    st = _Structure(family="flex", free_A=sts[0].free_A, free_floor=sts[0].free_floor,
                    n_knots=next(iter(knots)) if knots else 0, n_smooth=max(st.n_smooth for st in sts),
                    n_wfield=len(width_field_names(worder)))
    return ModelLayout(st, basis, order, worder)


class CompletenessModel:
    """Posterior of a completeness (or purity) model on binomial cells.

    Parameters
    ----------
    spec : ModelSpec or str
        The model (a name or path is loaded with :func:`load_spec`); not a
        selection spec.
    data : BinomialData
        From :func:`compress`, :func:`compress_for` or :func:`uncompressed`;
        must resolve every covariate the model uses (``meta["binned"]``).
    layout : ModelLayout, optional
        A layout shared with other specs (:func:`shared_layout`), so that
        they all run through one compiled likelihood; default: the spec's own.

    Attributes
    ----------
    names : list of str
        Names of the entries of the unconstrained vector ``theta`` (the free
        parameters).
    ndim : int
        Its length.
    tau : float or None
        Smoothness scale of the spline's random walk (spline models only);
        settable.

    Notes
    -----
    All methods taking ``theta`` accept a sequence or ndarray of length
    ``ndim`` (float64).  Internally ``theta`` is placed into the layout's full
    vector, whose other entries are pinned at 0 (no depth slope, ``nu = 1``,
    a straight spline, a flat field).  :meth:`log_prob`,
    :meth:`value_and_grad`, :meth:`log_prob_batch` and :meth:`hessian` run
    functions compiled once per layout and padded cell count (data, priors
    and the free-parameter mask are arguments, not baked-in constants, so
    new data of a similar size, other priors and other rungs of the same
    layout never recompile; :func:`padded_size`).  They return ``-inf``
    rather than NaN for parameters where the density is not defined or
    underflows (NaN entries, ``|theta_i| > THETA_BOUND``); a ``-inf`` value
    comes with a finite gradient (0 where undefined).

    ``kind = "purity"`` specs are fitted the same way: build the data from a
    table of detections with ``covariates_from_outcomes(...,
    mag_column="det_mag_auto", outcome_column=<real or false>)``.
    """

    def __init__(self, spec: ModelSpec | str, data: BinomialData, *, layout: ModelLayout | None = None):
        spec = load_spec(spec)
        if spec.is_selection:
            raise ConfigError(f"model spec {spec.name!r} is a selection spec (candidates {list(spec.candidates)}); "
                              "fit its candidates with comest_bayes.bayes.selection.select_model instead.")
        if not isinstance(data, BinomialData):
            raise InputError(f"data must be a BinomialData (from compress or uncompressed), got "
                             f"{type(data).__name__}.")
        if data.ncells == 0:
            raise InputError("no cells in the data: there is nothing to fit.")
        need = covariates_needed(spec)
        binned = tuple(data.meta.get("binned", _COVARIATE_GROUPS))
        missing = [g for g in need if g not in binned]
        if missing:
            raise InputError(f"model {spec.name!r} uses the covariate(s) {missing}, but the data were compressed "
                             f"without resolving them (binned: {list(binned)}); compress with their grid steps, "
                             "or use compress_for(spec, ...).")
        available = data.meta.get("available")
        inert = tuple(data.meta.get("inert", ()))  # groups the caller knows change no output (fit_kind)
        for group, label in (("depth", "depth (no usable noise column)"), ("size", "size (no half-light radii)")):
            if group in need and available is not None and group not in available and group not in inert:
                warnings.warn(f"model {spec.name!r} uses the {label}; that covariate is 0 for every injection, "
                              "so its slope is constrained by its prior only.", UserWarning, stacklevel=2)
        own = _spec_layout(spec)
        layout = own if layout is None else layout
        st = layout.structure
        if own.structure.family != st.family and not (st.family == "flex" and own.structure.family == "logistic"):
            raise ConfigError(f"model {spec.name!r} (link {spec.link}) does not fit the layout of family {st.family}.")
        if (own.structure.free_A, own.structure.free_floor) != (st.free_A, st.free_floor):
            raise ConfigError(f"model {spec.name!r} has another plateau/floor setting than the layout.")
        if own.structure.n_knots and own.structure.n_knots != st.n_knots:
            raise ConfigError(f"model {spec.name!r} has {own.structure.n_knots} spline knots, the layout {st.n_knots}.")
        if spec.uses_smooth and (own.smooth_names != layout.smooth_names):
            raise ConfigError(f"model {spec.name!r} has another smooth basis than the layout.")
        if spec.uses_width_position and (own.width_names != layout.width_names):
            raise ConfigError(f"model {spec.name!r} has another width_order than the layout.")
        self.spec = spec
        self.data = data
        self.layout = layout
        self._st = st
        self.full_names = _layout_names(st, layout.smooth_names, layout.width_names)
        sl = _slots(st)
        free = {"m50_0": "m50_0", "log_w": "log_w"}
        if st.free_A:
            free["logit_A"] = "A"
        if st.free_floor:
            free["logit_floor"] = "floor"
        if spec.spatial in ("depth", "depth+smooth"):
            free["beta_depth"] = "beta_depth"
        if spec.width_depth:
            free["w_depth"] = "w_depth"
        if spec.size_covariate:
            free["beta_size"] = "beta_size"
        if spec.link == "richards":
            free["log_nu"] = "log_nu"
        if spec.link == "spline":
            free.update({f"eta_{k}": None for k in range(st.n_knots)})
        self.smooth_names = smooth_basis_names(spec.smooth_basis, spec.smooth_order) if spec.uses_smooth else []
        free.update({name: "smooth" for name in self.smooth_names})
        self.width_names = width_field_names(spec.width_order)
        free.update({name: "w_uv" for name in self.width_names})
        self.names = [n for n in self.full_names if n in free]
        self.ndim = len(self.names)
        self._free_idx = np.array([self.full_names.index(n) for n in self.names], dtype=np.int64)
        nfull = sl["ndim"]
        a, b, lnorm, active = np.zeros(nfull), np.ones(nfull), np.zeros(nfull), np.zeros(nfull)
        for name in self.names:
            j = self.full_names.index(name)
            active[j] = 1.0
            key = free[name]
            if key is not None:
                a[j], b[j], lnorm[j] = _prior_args(spec.prior(key))
        self._prior_arrays = (a, b, lnorm, active)
        self.tau = spec.spline_tau if isinstance(spec.spline_tau, float) else DEFAULT_SPLINE_TAU
        self._pinned = np.zeros(nfull)
        cov = data.cov
        g = data.ncells
        size = padded_size(g)
        pad = size - g

        def padded(x, fill=None):
            x = np.asarray(x, dtype=np.float64)
            if not pad:
                return jnp.asarray(x)
            tail = np.repeat(x[-1:], pad, axis=0) if fill is None else np.full((pad,) + x.shape[1:], fill)
            return jnp.asarray(np.concatenate([x, tail]))

        self._data = (padded(cov.m), padded(cov.depth), padded(cov.size), padded(self.basis(cov)),
                      padded(data.n, 0.0), padded(data.k, 0.0))
        self._ncells = g

    # -- helpers ------------------------------------------------------------
    @property
    def tau(self) -> float | None:
        """Smoothness scale of the spline random walk (per unit of t); None for models without a spline."""
        return self._tau if self.spec.link == "spline" else None

    @tau.setter
    def tau(self, value: float) -> None:
        value = float(value)
        if not (math.isfinite(value) and value > 0):
            raise InputError(f"the spline smoothness tau must be a positive number, got {value!r}.")
        self._tau = value

    @property
    def _prior(self):
        # the device copies of the prior's arrays, made once per tau: each jnp.asarray of a host array is an
        # eager conversion (about 0.1 ms), and every density, gradient and Hessian call takes these five
        cached = getattr(self, "_prior_device", None)
        if cached is None or cached[0] != self._tau:
            a, b, lnorm, active = self._prior_arrays
            cached = self._prior_device = (self._tau, (jnp.asarray(a), jnp.asarray(b), jnp.asarray(lnorm),
                                                       jnp.asarray(active), jnp.asarray(math.log(self._tau))))
        return cached[1]

    @property
    def structure(self) -> _Structure:
        """Which terms the compiled density has (shared by every model of one layout)."""
        return self._st

    def basis(self, cov: Covariates) -> np.ndarray:
        """The spatial basis columns at the covariates' ``(u, v)``, shape (N, J).

        The smooth field of m50 (``n_smooth`` columns), then the Legendre field of log w
        (``n_wfield`` columns); J = 0 without either term.
        """
        st = self._st if hasattr(self, "_st") else None
        cols = [np.zeros((len(cov), 0))]
        if st is not None and st.n_smooth:
            cols.append(smooth_basis(cov.u, cov.v, self.layout.smooth_basis, self.layout.smooth_order))
        if st is not None and st.n_wfield:
            cols.append(smooth_basis(cov.u, cov.v, "poly", self.layout.width_order))
        return np.concatenate(cols, axis=1) if len(cols) > 1 else cols[0]

    def full(self, theta) -> np.ndarray:
        """The layout's full parameter vector(s) for free parameters ``theta`` (D,) or (S, D)."""
        t = np.asarray(theta, dtype=np.float64)
        out = np.broadcast_to(self._pinned, t.shape[:-1] + self._pinned.shape).copy()
        out[..., self._free_idx] = t
        return out

    def full_jax(self, theta):
        """:meth:`full` for a JAX array (traceable: usable inside jitted code)."""
        return jnp.asarray(self._pinned).at[self._free_idx].set(theta)

    def cell_logs(self, theta, m, depth, size, basis):
        """Traceable ``(log f, log(1 - f))`` at covariates for free parameters ``theta`` (JAX arrays)."""
        return cell_logs(self._st, self.full_jax(theta), m, depth, size, basis)

    def basis_at(self, cov: Covariates) -> np.ndarray:
        """The smooth basis columns of the layout at covariates (N, J)."""
        return self.basis(cov)

    def _theta(self, theta) -> np.ndarray:
        # a host array: the compiled programs take it as it is (jnp.asarray would add an eager conversion,
        # about 0.1 ms, to every call of the optimizer's objective)
        t = np.asarray(theta, dtype=np.float64)
        if t.shape != (self.ndim,):
            raise InputError(f"theta must have shape ({self.ndim},) for model {self.spec.name!r} "
                             f"(parameters {self.names}), got {t.shape}.")
        return self.full(t)

    def _thetas(self, thetas) -> np.ndarray:
        t = np.asarray(thetas, dtype=np.float64)
        if t.ndim != 2 or t.shape[1] != self.ndim:
            raise InputError(f"thetas must have shape (S, {self.ndim}) for model {self.spec.name!r}, got {t.shape}.")
        return t

    def __repr__(self) -> str:
        return (f"CompletenessModel({self.spec.name!r}, ndim={self.ndim}, cells={self.data.ncells}, "
                f"N={self.data.ntotal})")

    # -- densities ----------------------------------------------------------
    def log_prior(self, theta) -> float:
        """Log prior density in theta space (normalised, Jacobians included)."""
        return float(_jit_log_prior(self._st, self._theta(theta), self._prior))

    def log_likelihood(self, theta) -> float:
        """``sum k log f + (n - k) log(1 - f)`` over cells (binomial coefficients dropped)."""
        return float(_jit_log_likelihood(self._st, self._theta(theta), self._data))

    def log_prob(self, theta) -> float:
        """Log posterior density (up to the evidence); -inf, never NaN, where undefined."""
        return float(_jit_log_prob(self._st, self._theta(theta), self._data, self._prior))

    def value_and_grad(self, theta) -> tuple[float, np.ndarray]:
        """:meth:`log_prob` and its gradient, shape (ndim,)."""
        v, g = _jit_value_and_grad(self._st, self._theta(theta), self._data, self._prior)
        return float(v), np.asarray(g)[self._free_idx]

    def log_density(self) -> tuple:
        """The log posterior as a traceable function, for gradient-based samplers.

        Returns ``(fn, static, args)``: ``fn(static, theta, *args)`` is :meth:`log_prob` of the free
        parameters ``theta`` (ndim,), written in JAX; ``static`` is hashable (a compiled sampler can
        be keyed on it) and ``args`` are arrays, so one compiled program serves every data set of the
        same structure and padded size.
        """
        args = (jnp.asarray(self._pinned), jnp.asarray(self._free_idx), self._data, self._prior)
        return _log_prob_free, self._st, args

    def log_prob_batch(self, thetas) -> np.ndarray:
        """:meth:`log_prob` of each row of ``thetas`` (W, ndim) -> (W,), for emcee ``vectorize=True``.

        A jitted vectorised map over the rows (``vmap`` in batches of at most
        :data:`BATCH_ELEMENTS` / G rows, which is faster than one ``vmap``
        over all walkers when the number of cells G is large).
        """
        t = self.full(self._thetas(thetas))
        w = t.shape[0]
        # rows in blocks of one fixed size (a power of two, at most LOG_PROB_ROWS): one compiled shape serves
        # importance-sampling batches of any length; emcee's fixed walker count gets its own
        rows = min(LOG_PROB_ROWS, 1 << max(0, int(math.ceil(math.log2(max(w, 1))))))
        batch = int(max(1, min(rows, BATCH_ELEMENTS // max(1, self._data[0].shape[0]))))
        out = np.empty(w)
        for start in range(0, w, rows):
            block = t[start:start + rows]
            nb = block.shape[0]
            if nb < rows:
                block = np.concatenate([block, np.repeat(block[-1:], rows - nb, axis=0)])
            out[start:start + nb] = np.asarray(_jit_log_prob_batch(self._st, block, self._data,
                                                                   self._prior, batch))[:nb]
        return out

    def hessian(self, theta) -> np.ndarray:
        """Hessian of :meth:`log_prob`, shape (ndim, ndim), from forward differences of its gradient.

        Column ``j`` is ``(grad(theta + h_j e_j) - grad(theta)) / h_j`` with the compiled gradient
        (:meth:`value_and_grad`), ``h_j = HESSIAN_STEP * max(1, |theta_j|)`` taken towards 0 (so
        the step never leaves the parameter box), then symmetrised.  Its relative error is about
        2e-6 (:data:`HESSIAN_STEP`; the tests compare it with ``jax.hessian``), far below what a
        Laplace approximation, an evidence or a Newton step can feel, and it costs ``ndim``
        gradients, about what the exact Hessian costs at run time.  The exact one (``jax.hessian``,
        forward over reverse) would be a program of its own: compiling it took 40% of a first run's
        fitting (docs/compute.md, "Compilation cache").  Where the log posterior is not finite at
        ``theta`` or at a step, the affected entries are NaN.

        The last few are remembered (keyed on the exact bits of ``theta`` and on ``tau``): a fit asks
        for the Hessian at one MAP up to three times (the Newton optimizer's last step, the evidence of
        the smoothness scale, the Laplace approximation).
        """
        full = self._theta(theta)
        key = (full.tobytes(), self._tau)
        memo = self.__dict__.setdefault("_hessians", {})
        h = memo.get(key)
        if h is None:
            h = self._difference_hessian(full)
            if len(memo) >= HESSIAN_MEMO:
                memo.pop(next(iter(memo)))
            memo[key] = h
        return h.copy()

    def _difference_hessian(self, full: np.ndarray) -> np.ndarray:
        free = self._free_idx
        d = len(free)
        value, grad = _jit_value_and_grad(self._st, full, self._data, self._prior)
        if not np.isfinite(float(value)):
            return np.full((d, d), np.nan)
        grad = np.asarray(grad)[free]
        cols = np.empty((d, d))
        for j, i in enumerate(free):
            moved = full.copy()
            moved[i] += (-1.0 if full[i] > 0 else 1.0) * HESSIAN_STEP * max(1.0, abs(full[i]))
            step = moved[i] - full[i]  # the step as represented
            v, g = _jit_value_and_grad(self._st, moved, self._data, self._prior)
            cols[:, j] = (np.asarray(g)[free] - grad) / step if np.isfinite(float(v)) else np.nan
        return 0.5 * (cols + cols.T)

    def cell_loglik(self, thetas, *, max_elements: int = 20_000_000) -> np.ndarray:
        """Per-cell ``log f`` and ``log(1 - f)`` for each parameter vector.

        Parameters
        ----------
        thetas : array, shape (S, ndim)
        max_elements : int
            Work in chunks of samples so that one chunk holds at most this many
            numbers (memory guard); the output itself is S * G * 2 float64.

        Returns
        -------
        ndarray, shape (S, G, 2)
            ``[..., 0] = log f`` (weight ``k`` per cell) and
            ``[..., 1] = log(1 - f)`` (weight ``n - k``): the pointwise
            log-likelihood of the groups (cell, outcome) for PSIS-LOO.
        """
        t = self.full(self._thetas(thetas))
        s, g = t.shape[0], self._ncells
        gp = self._data[0].shape[0]
        out = np.empty((s, g, 2))
        chunk = max(1, min(s, int(max_elements // max(1, 2 * gp))))
        m, depth, size, basis = self._data[:4]
        for start in range(0, s, chunk):
            block = t[start:start + chunk]
            nb = block.shape[0]
            if nb < chunk:  # pad to one compiled shape
                block = np.concatenate([block, np.repeat(block[-1:], chunk - nb, axis=0)])
            res = _jit_cell_logs_batch(self._st, block, m, depth, size, basis)
            out[start:start + nb] = np.asarray(res)[:nb, :g]
        return out

    def cell_gradients(self, theta) -> tuple[np.ndarray, np.ndarray]:
        """Per-cell log-likelihood terms and their gradients at one theta.

        Returns
        -------
        grads : ndarray, shape (G, 2, ndim)
            d log f / d theta (``[:, 0]``) and d log(1 - f) / d theta
            (``[:, 1]``) of every cell.
        logs : ndarray, shape (G, 2)
            ``log f`` and ``log(1 - f)``.
        """
        jac, logs = _jit_cell_grads(self._st, self._theta(theta), *self._data[:4])
        g = self._ncells
        return np.asarray(jac)[:g][:, :, self._free_idx], np.asarray(logs)[:g]

    def _footprint_args(self, depth, u, v, weight) -> tuple:
        """The footprint cells as the averaging programs take them (depth, size, basis, weight on the device).

        Kept for the last footprint seen: a posterior's summaries average over the same cells hundreds
        of times (one call per block of draws and magnitudes), and building the basis and copying the
        arrays each time cost as much as the averages themselves.
        """
        key = (id(depth), id(u), id(v), id(weight))
        cached = getattr(self, "_footprint_cache", None)
        if cached is not None and cached[0] == key:
            return cached[2]
        cov = Covariates.make(np.zeros(len(weight)), depth, u, v)
        args = (jnp.asarray(cov.depth), jnp.asarray(cov.size), jnp.asarray(self.basis(cov)),
                jnp.asarray(np.asarray(weight, np.float64)))
        # the arrays themselves are held so that their ids cannot be reused by other arrays
        self._footprint_cache = (key, (depth, u, v, weight), args)
        return args

    def average_prob(self, thetas, mags, depth, u, v, weight, *, max_elements: int = 4_000_000) -> np.ndarray:
        """Weighted average of f over covariate cells, per draw: shape (S, M).

        Parameters
        ----------
        thetas : array, shape (S, ndim)
        mags : array, shape (M,)
        depth, u, v, weight : arrays, shape (P,)
            Footprint cells (:class:`comest_bayes.bayes.posterior.Footprint`);
            ``weight`` sums to 1.
        """
        t = self.full(self._thetas(np.atleast_2d(thetas)))
        mags = np.atleast_1d(np.asarray(mags, np.float64))
        nm = mags.size
        size = 16 * -(-nm // 16)  # pad the magnitudes to a multiple of 16: few compiled shapes
        mags = jnp.asarray(np.concatenate([mags, np.full(size - nm, mags[-1])]))
        p = len(weight)
        args = self._footprint_args(depth, u, v, weight)
        chunk = int(max(1, min(len(t), max_elements // max(1, p * mags.shape[0]))))
        chunk = 1 << int(math.floor(math.log2(chunk)))  # a power of two: few compiled shapes
        out = np.empty((len(t), nm))
        for start in range(0, len(t), chunk):
            block = t[start:start + chunk]
            nb = len(block)
            if nb < chunk:  # pad to one compiled shape
                block = np.concatenate([block, np.repeat(block[-1:], chunk - nb, axis=0)])
            out[start:start + nb] = np.asarray(_jit_average_batch(self._st, block, mags, *args))[:nb, :nm]
        return np.clip(out, 0.0, 1.0)

    def average_prob_at(self, thetas, mags, depth, u, v, weight) -> np.ndarray:
        """Weighted average of f over covariate cells for draw ``s`` at magnitude ``mags[s]``: shape (S,)."""
        t = self.full(self._thetas(np.atleast_2d(thetas)))
        s = len(t)
        size = 16
        while size < s:  # pad the draws to a power of two: few compiled shapes
            size *= 2
        mags = np.asarray(mags, np.float64)
        tp = np.concatenate([t, np.repeat(t[-1:], size - s, axis=0)])
        mp = np.concatenate([mags, np.full(size - s, mags[-1])])
        out = _jit_average_at_batch(self._st, tp, mp,
                                    *self._footprint_args(depth, u, v, weight))
        return np.clip(np.asarray(out)[:s], 0.0, 1.0)

    # -- predictions --------------------------------------------------------
    def _predict(self, theta, cov: Covariates):
        if not isinstance(cov, Covariates):
            raise InputError(f"cov must be a Covariates (use Covariates.make), got {type(cov).__name__}.")
        t = np.asarray(theta, dtype=np.float64)
        single = t.ndim == 1
        t2 = self.full(self._thetas(t[None, :] if single else t))
        # padded to few compiled shapes (the rows repeat the last ones; each draw and row is computed
        # alone, so the padding changes no number): draws in blocks of PREDICT_DRAWS (fewer draws to
        # a power of two), rows to padded_size.  Without it every new (draws, rows) shape of a query,
        # a check or a map costs a trace and a compile (about 0.3 CPU-s) or a cache load.
        n, s = len(cov.m), len(t2)
        if n == 0:
            empty = np.empty((s, 0))
            return (empty[0], empty[0]) if single else (empty, empty.copy())
        rows = padded_size(n)

        def pad(x, size):
            x = np.asarray(x, np.float64)
            return jnp.asarray(np.concatenate([x, np.repeat(x[-1:], size - len(x), axis=0)]) if len(x) < size else x)

        args = tuple(pad(x, rows) for x in (cov.m, cov.depth, cov.size, self.basis(cov)))
        block = PREDICT_DRAWS if s >= PREDICT_DRAWS else 1 << max(0, (s - 1).bit_length())
        f, m50 = np.empty((s, n)), np.empty((s, n))
        for start in range(0, s, block):
            part = t2[start:start + block]
            nb = len(part)
            fb, mb = _jit_prob_m50_batch(self._st, pad(part, block), *args)
            f[start:start + nb], m50[start:start + nb] = np.asarray(fb)[:nb, :n], np.asarray(mb)[:nb, :n]
        return (f[0], m50[0]) if single else (f, m50)

    def prob(self, theta, cov: Covariates) -> np.ndarray:
        """Completeness f at arbitrary covariates.

        Parameters
        ----------
        theta : array, shape (ndim,) or (S, ndim)
        cov : Covariates, N rows

        Returns
        -------
        ndarray, shape (N,) or (S, N), values in [0, 1]
        """
        return np.clip(self._predict(theta, cov)[0], 0.0, 1.0)

    def m50(self, theta, cov: Covariates) -> np.ndarray:
        """The m50 field at arbitrary covariates, shape (N,) or (S, N) (mag)."""
        return self._predict(theta, cov)[1]

    # -- parameters ---------------------------------------------------------
    def transform(self, theta) -> dict:
        """Physical parameters from theta of shape (ndim,) or (S, ndim).

        Returns
        -------
        dict
            ``m50_0``, ``w`` (mag), ``log_w``, ``A``, ``floor`` (1 and 0 when
            fixed), and when present ``beta_depth``, ``w_depth``,
            ``beta_size``, ``nu`` (Richards shape, with ``log_nu``), the
            spline's knot log-rates ``eta_k`` and the smooth coefficients
            (their own names); floats for one theta, arrays of shape (S,) for
            several.
        """
        t = np.asarray(theta, dtype=np.float64)
        if t.shape[-1:] != (self.ndim,) or t.ndim > 2:
            raise InputError(f"theta must have shape ({self.ndim},) or (S, {self.ndim}), got {t.shape}.")
        col = {name: t[..., i] for i, name in enumerate(self.names)}
        out = {"m50_0": col["m50_0"], "log_w": col["log_w"], "w": np.exp(col["log_w"])}
        a = _sp.expit(col["logit_A"]) if "logit_A" in col else np.ones_like(col["m50_0"])
        out["A"] = a
        out["floor"] = a * _sp.expit(col["logit_floor"]) if "logit_floor" in col else np.zeros_like(a)
        for name in self.names[2:]:
            if name not in ("logit_A", "logit_floor"):
                out[name] = col[name]
            if name == "log_nu":
                out["nu"] = np.exp(col[name])
        if t.ndim == 1:
            out = {k: float(v) for k, v in out.items()}
        return out

    def inverse_transform(self, params: Mapping[str, float]) -> np.ndarray:
        """theta from physical parameters (``m50_0``, ``w``, ``A``, ``floor``, slopes, coefficients).

        Missing slopes and coefficients are 0; ``A`` and ``floor`` default to
        0.97 and 0.01 (ignored when fixed); ``nu`` (or ``log_nu``) defaults to
        1.  Raises InputError for values outside their ranges
        (``0 < floor < A < 1``, ``w > 0``, ``nu > 0``).
        """
        w = float(params.get("w", math.exp(params.get("log_w", math.log(0.2)))))
        a = float(params.get("A", 0.97))
        fl = float(params.get("floor", 0.01))
        if not w > 0:
            raise InputError(f"w must be positive, got {w}.")
        theta = np.zeros(self.ndim)
        for i, name in enumerate(self.names):
            if name == "m50_0":
                theta[i] = float(params["m50_0"])
            elif name == "log_w":
                theta[i] = math.log(w)
            elif name == "logit_A":
                if not 0 < a < 1:
                    raise InputError(f"A must lie in (0, 1), got {a}.")
                theta[i] = math.log(a) - math.log1p(-a)
            elif name == "logit_floor":
                top = a if "logit_A" in self.names else 1.0
                if not 0 < fl < top:
                    raise InputError(f"floor must lie in (0, A) = (0, {top}), got {fl}.")
                r = fl / top
                theta[i] = math.log(r) - math.log1p(-r)
            elif name == "log_nu" and "nu" in params and "log_nu" not in params:
                nu = float(params["nu"])
                if not nu > 0:
                    raise InputError(f"nu must be positive, got {nu}.")
                theta[i] = math.log(nu)
            else:
                theta[i] = float(params.get(name, 0.0))
        return theta

    def warm_start(self, names, theta) -> np.ndarray:
        """A starting theta that takes the values of ``names`` from ``theta`` (another rung's MAP).

        Parameters this model has and the other lacks start where
        :meth:`initial` puts them (slopes at their prior means, a straight
        spline, ``nu = 1``, a flat field).
        """
        other = dict(zip(list(names), np.asarray(theta, dtype=np.float64)))
        # the grid search of initial() only places m50_0, log_w, logit_A and logit_floor: when the other
        # rung supplies every one of them that this model has, its defaults suffice (same start, no search)
        searched = [n for n in ("m50_0", "log_w", "logit_A", "logit_floor") if n in self.names]
        if all(n in other and np.isfinite(other[n]) for n in searched):
            start = self._start_from((float(np.mean(self.data.cov.m)), 0.2, 0.97, 0.01))  # all four replaced below
        else:
            start = self.initial()
        for i, name in enumerate(self.names):
            if name in other and np.isfinite(other[name]):
                start[i] = other[name]
        return start

    def initial(self) -> np.ndarray:
        """A sensible starting theta from the data (no optimisation of the full model).

        A coarse grid search of the model *without* spatial terms (m50, w, A,
        floor) on the magnitude histogram of the cells, maximising likelihood
        times prior (the flexible links are searched as the logistic they
        contain); slopes start at their prior means, ``nu`` at 1, the spline
        straight and smooth coefficients at 0.  Works for any data (all or no
        detections, separated outcomes, a handful of injections), where it
        lands on the prior-preferred edge.
        """
        if getattr(self, "_initial", None) is None:
            self._initial = self._grid_initial()
        return self._initial.copy()

    def _grid_initial(self) -> np.ndarray:
        # the search depends only on the data, the link's family as searched, the plateau and floor settings
        # and the priors of (m50, w, A, floor): the rungs of a selection share it (kept on the data object,
        # which they share), and each would otherwise repeat about 60 ms of array work
        st = self._st
        pa, pb, _, _ = self._prior_arrays
        fn = self.full_names
        link = "logistic" if self.spec.link in ("logistic", "richards", "spline") else self.spec.link
        used = [fn.index(n) for n in ("m50_0", "log_w", "logit_A", "logit_floor") if n in fn]
        key = (link, bool(st.free_A), bool(st.free_floor), tuple(float(pa[j]) for j in used),
               tuple(float(pb[j]) for j in used))
        cache = self.data.__dict__.setdefault("_grid_starts", {})
        if key not in cache:
            cache[key] = self._grid_search()
        return self._start_from(cache[key])

    def _grid_search(self) -> tuple:
        """The grid values ``(m50, w, A, floor)`` of highest likelihood times prior (see :meth:`initial`)."""
        data = self.data
        m = data.cov.m
        lo, hi = float(m.min()), float(m.max())
        nbins = int(min(400, max(1, math.ceil((hi - lo) / 0.02))))
        edges = np.linspace(lo, hi + 1e-9, nbins + 1)
        which = np.clip(np.searchsorted(edges, m, side="right") - 1, 0, nbins - 1)
        n = np.bincount(which, weights=data.n, minlength=nbins)
        k = np.bincount(which, weights=data.k, minlength=nbins)
        msum = np.bincount(which, weights=data.n * m, minlength=nbins)
        occ = n > 0
        n, k, mb = n[occ], k[occ], msum[occ] / n[occ]

        st = self._st
        pa, pb, _, _ = self._prior_arrays
        fn = self.full_names
        m50_grid = np.linspace(lo - 1.5, hi + 1.5, 91)
        w_grid = np.array([0.03, 0.06, 0.1, 0.15, 0.2, 0.3, 0.5, 0.8])
        a_grid = np.array([0.8, 0.9, 0.95, 0.98, 0.995]) if st.free_A else np.array([1.0])
        r_grid = np.array([0.001, 0.01, 0.03, 0.1]) if st.free_floor else np.array([0.0])
        z = (m50_grid[:, None, None] - mb[None, None, :]) / w_grid[None, :, None]  # (M, W, B)
        lg, _ = _np_link_logs(z, self.spec.link)
        g = np.exp(lg)
        i_m, i_w = fn.index("m50_0"), fn.index("log_w")
        best, best_val = None, -np.inf
        with np.errstate(divide="ignore", invalid="ignore"):
            for a in a_grid:
                for r in r_grid:
                    fl = a * r
                    f = np.clip(fl + (a - fl) * g, 1e-300, 1.0 - 1e-16)
                    ll = (k * np.log(f) + (n - k) * np.log1p(-f)).sum(axis=-1)
                    lp = (ll - 0.5 * ((m50_grid[:, None] - pa[i_m]) / pb[i_m]) ** 2
                          - 0.5 * ((np.log(w_grid)[None, :] - pa[i_w]) / pb[i_w]) ** 2)
                    if st.free_A:
                        j = fn.index("logit_A")
                        lp = lp + pa[j] * math.log(a) + pb[j] * math.log1p(-a)
                    if st.free_floor:
                        j = fn.index("logit_floor")
                        lp = lp + pa[j] * math.log(r) + pb[j] * math.log1p(-r)
                    idx = np.unravel_index(np.nanargmax(np.where(np.isfinite(lp), lp, -np.inf)), lp.shape)
                    if lp[idx] > best_val:
                        best_val = lp[idx]
                        best = (m50_grid[idx[0]], w_grid[idx[1]], a, a * r)
        if best is None:  # pragma: no cover - every grid point non-finite cannot happen with clipped f
            best = (0.5 * (lo + hi), 0.2, 0.97, 0.01)
        return best

    def _start_from(self, best) -> np.ndarray:
        """The starting theta for grid values ``best = (m50, w, A, floor)``; other parameters at their defaults."""
        pa = self._prior_arrays[0]
        fn = self.full_names
        m50, w, a, fl = best
        params = {"m50_0": m50, "w": w, "A": min(a, 0.995), "floor": fl}
        for name in self.names:
            if name in ("beta_depth", "w_depth", "beta_size", "log_nu"):
                params[name] = pa[fn.index(name)]
        return self.inverse_transform(params)


#: Hessians a model remembers (:meth:`CompletenessModel.hessian`).
HESSIAN_MEMO = 4
#: Relative step of :meth:`CompletenessModel.hessian`'s forward differences.  Against ``jax.hessian``
#: on five rungs at 3k and 100k outcomes, the largest error in units of ``sqrt(|H_ii H_jj|)`` was
#: about 19 x the step for steps of 1e-5 to 1e-7 (truncation); at 1e-8 rounding began to show
#: (1.1e-6 on a spline at 100k outcomes), and at 1e-9 it dominated (up to 1.6e-5).
HESSIAN_STEP = 1e-7

#: Rows of parameter vectors per compiled call of :meth:`CompletenessModel.log_prob_batch`.
LOG_PROB_ROWS = 1024

#: Smoothness scale of the spline's random walk before it is chosen by the evidence
#: (:func:`comest_bayes.bayes.selection.choose_tau`), per unit of standardised magnitude.
DEFAULT_SPLINE_TAU = 0.3
