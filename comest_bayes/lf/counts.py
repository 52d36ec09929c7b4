"""Number-count (luminosity-function) models, declared in TOML like the completeness models.

A count model ``phi(m)`` (deg^-2 mag^-1, true magnitude) takes its form from the fixed registry
:data:`FORMS` (``powerlaw``, ``schechter``, ``double_powerlaw``); a TOML specification picks a
form, fixes its constants and gives every free parameter a prior, and nothing in it is executed.
Forms and file format: ``docs/lf.md`` ("Count-model specifications").
"""

from __future__ import annotations

import difflib
import math
from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np

from comest_bayes.jaxnum import jnp  # float64 on (the one place that sets it)

from comest_bayes.errors import ConfigError  # noqa: E402
from comest_bayes.io.specfiles import list_spec_names, read_spec_toml  # noqa: E402

__all__ = ["FORMS", "CountSpec", "CountModel", "list_count_specs", "load_count_spec", "count_spec_from_mapping",
           "log_phi"]

LN10 = math.log(10.0)

#: Registered forms: parameter names (sampling order) and constants with their defaults.
FORMS: dict[str, dict] = {
    "powerlaw": {"params": ("log_n", "slope"), "constants": {"m_ref": 23.0}},
    "schechter": {"params": ("log_phi_star", "m_star", "alpha"), "constants": {}},
    "double_powerlaw": {"params": ("log_n_b", "m_b", "slope_bright", "slope_faint"), "constants": {}},
}

_DIST_ARGS = {"normal": ("mu", "sigma"), "uniform": ("lo", "hi")}
_SPEC_KEYS = {"name", "description", "form", "constants", "priors", "sampler"}
#: What a count spec's ``sampler`` may say: the sampler ``--sampler auto`` uses for it ("" = the default rule).
SPEC_SAMPLERS = ("", "emcee")


def log_phi(form: str, params, m, constants: Mapping[str, float]):
    """Natural log of ``phi(m)`` (deg^-2 mag^-1) for one registered form (JAX, differentiable).

    Parameters
    ----------
    form : str
        A key of :data:`FORMS`.
    params : array, shape (P,)
        Parameters in the order of ``FORMS[form]["params"]``.
    m : array, shape (M,)
        True magnitudes.
    constants : mapping
        The form's constants (e.g. ``m_ref``).

    Returns
    -------
    jax array, shape (M,)
    """
    m = jnp.asarray(m, dtype=jnp.float64)
    if form == "powerlaw":
        log_n, slope = params[0], params[1]
        return LN10 * (log_n + slope * (m - constants["m_ref"]))
    if form == "schechter":
        log_phi_star, m_star, alpha = params[0], params[1], params[2]
        log_x = 0.4 * LN10 * (m_star - m)  # ln x
        return math.log(0.4 * LN10) + LN10 * log_phi_star + (alpha + 1.0) * log_x - jnp.exp(log_x)
    if form == "double_powerlaw":
        log_n_b, m_b, s_b, s_f = params[0], params[1], params[2], params[3]
        d = LN10 * (m - m_b)
        # log of the sum of two exponentials, computed stably
        return math.log(2.0) + LN10 * log_n_b - jnp.logaddexp(-s_b * d, -s_f * d)
    raise ConfigError(f"unknown count-model form {form!r}; registered forms: {sorted(FORMS)}.")


@dataclass(frozen=True)
class CountSpec:
    """A validated count-model specification.

    Attributes
    ----------
    name : str
    form : str
        Key of :data:`FORMS`.
    constants : dict
        Fixed constants of the form (defaults filled in).
    priors : dict
        ``{param: {"dist": "normal"|"uniform", ...}}`` for every parameter.
    description : str
    source : str
        Where the spec was read from.
    sampler : str
        The sampler ``--sampler auto`` uses for this model: ``"emcee"`` for a model whose posterior can
        have several modes (the double power law's break), which importance sampling of one Laplace
        approximation cannot see and its Pareto k-hat cannot flag; ``""`` for the default rule.
    """

    name: str
    form: str
    constants: dict
    priors: dict
    description: str = ""
    source: str = ""
    sampler: str = ""

    @property
    def params(self) -> tuple:
        """Free parameter names, in sampling order."""
        return FORMS[self.form]["params"]

    def to_dict(self) -> dict:
        """Plain-data view (JSON/TOML friendly)."""
        out = {"name": self.name, "form": self.form, "description": self.description,
               "constants": dict(self.constants), "priors": {k: dict(v) for k, v in self.priors.items()}}
        if self.sampler:
            out["sampler"] = self.sampler
        return out


def _number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def count_spec_from_mapping(mapping: Mapping[str, Any], *, name: str | None = None, source: str = "") -> CountSpec:
    """Validate a parsed TOML table into a :class:`CountSpec`.

    Raises
    ------
    ConfigError
        Unknown keys, unknown form, missing or invalid priors or constants;
        the message names the key and the file.
    """
    where = f" in {source}" if source else ""
    data = dict(mapping)
    unknown = sorted(set(data) - _SPEC_KEYS)
    if unknown:
        raise ConfigError(f"unknown key(s) {unknown}{where}; valid keys: {sorted(_SPEC_KEYS)}.")
    form = data.get("form")
    if form not in FORMS:
        close = difflib.get_close_matches(str(form), list(FORMS), n=1)
        hint = f" Did you mean {close[0]!r}?" if close else ""
        raise ConfigError(f"invalid form = {form!r}{where}: expected one of {sorted(FORMS)} (formulas are taken "
                          f"from this fixed registry; a spec cannot define new code).{hint}")
    nm = data.get("name", name)
    if not nm:
        raise ConfigError(f"missing key 'name'{where}.")
    consts = dict(FORMS[form]["constants"])
    given = data.get("constants", {})
    if not isinstance(given, Mapping):
        raise ConfigError(f"invalid constants = {given!r}{where}: expected a table such as {{m_ref = 23.0}}.")
    extra = sorted(set(given) - set(consts))
    if extra:
        raise ConfigError(f"unknown constant(s) {extra}{where}; form {form!r} has constants {sorted(consts)}.")
    for k, v in given.items():
        if not _number(v):
            raise ConfigError(f"invalid constants.{k} = {v!r}{where}: expected a finite number.")
        consts[k] = float(v)
    priors_in = data.get("priors", {})
    if not isinstance(priors_in, Mapping):
        raise ConfigError(f"invalid priors = {priors_in!r}{where}: expected a table of parameter priors.")
    params = FORMS[form]["params"]
    extra = sorted(set(priors_in) - set(params))
    if extra:
        raise ConfigError(f"prior(s) given for unknown parameter(s) {extra}{where}; form {form!r} has parameters "
                          f"{list(params)}.")
    missing = [p for p in params if p not in priors_in]
    if missing:
        raise ConfigError(f"no prior for parameter(s) {missing}{where}; every parameter of form {form!r} needs a "
                          f"proper prior, e.g. {missing[0]} = {{dist = \"normal\", mu = 0.0, sigma = 1.0}}.")
    priors = {}
    for p in params:
        value = priors_in[p]
        if not isinstance(value, Mapping):
            raise ConfigError(f"invalid priors.{p} = {value!r}{where}: expected a table such as "
                              f"{{dist = \"normal\", mu = 0.0, sigma = 1.0}}.")
        value = dict(value)
        dist = value.pop("dist", None)
        if dist not in _DIST_ARGS:
            raise ConfigError(f"invalid priors.{p}.dist = {dist!r}{where}: expected one of {sorted(_DIST_ARGS)}.")
        args = _DIST_ARGS[dist]
        if sorted(value) != sorted(args):
            raise ConfigError(f"priors.{p}{where}: a {dist} prior takes exactly {list(args)}, got {sorted(value)}.")
        if not all(_number(value[a]) for a in args):
            raise ConfigError(f"priors.{p}{where}: {list(args)} must be finite numbers, got {value}.")
        if dist == "normal" and value["sigma"] <= 0:
            raise ConfigError(f"priors.{p}.sigma = {value['sigma']}{where} must be positive.")
        if dist == "uniform" and not value["hi"] > value["lo"]:
            raise ConfigError(f"priors.{p}{where}: uniform needs hi > lo, got lo={value['lo']}, hi={value['hi']}.")
        priors[p] = {"dist": dist, **{a: float(value[a]) for a in args}}
    desc = data.get("description", "")
    sampler = data.get("sampler", "")
    if sampler not in SPEC_SAMPLERS:
        raise ConfigError(f"invalid sampler = {sampler!r}{where}: expected \"emcee\" (the sampler --sampler auto "
                          "uses for this model) or no key.")
    return CountSpec(name=str(nm), form=form, constants=consts, priors=priors, description=str(desc), source=source,
                     sampler=sampler)


def list_count_specs() -> list[str]:
    """Names of the shipped count-model specifications (sorted): the stems of ``models/counts/*.toml``."""
    return list_spec_names("counts")


def load_count_spec(name_or_path) -> CountSpec:
    """A count-model specification by shipped name (``"powerlaw"``) or TOML path.

    Raises
    ------
    ConfigError
        Unknown name (lists the available ones), missing file, invalid TOML or content.
    """
    if isinstance(name_or_path, CountSpec):
        return name_or_path
    data, name, source = read_spec_toml(name_or_path, what="count model", sub="counts")
    return count_spec_from_mapping(data, name=name, source=source)


@dataclass
class CountModel:
    """A count model ready for evaluation: spec plus vectorised log-density and log-prior.

    Parameters
    ----------
    spec : CountSpec or str
        Spec or name/path for :func:`load_count_spec`.
    """

    spec: CountSpec
    _prior: tuple = field(init=False, repr=False)

    def __post_init__(self):
        self.spec = load_count_spec(self.spec)
        rows = []
        for p in self.spec.params:
            pr = self.spec.priors[p]
            rows.append((pr["dist"], pr.get("mu", pr.get("lo")), pr.get("sigma", pr.get("hi"))))
        self._prior = tuple(rows)

    @property
    def names(self) -> list[str]:
        return list(self.spec.params)

    @property
    def ndim(self) -> int:
        return len(self.spec.params)

    def log_phi(self, params, m):
        """``ln phi(m)`` (JAX), params shape (P,), m shape (M,)."""
        return log_phi(self.spec.form, params, m, self.spec.constants)

    def phi(self, params, m) -> np.ndarray:
        """``phi(m)`` in deg^-2 mag^-1 for params (P,) -> (M,) or (S, P) -> (S, M) (NumPy)."""
        p = np.asarray(params, float)
        m = np.asarray(m, float)
        if p.ndim == 1:
            return np.exp(np.asarray(self.log_phi(jnp.asarray(p), m)))
        return np.stack([np.exp(np.asarray(self.log_phi(jnp.asarray(row), m))) for row in p])

    def log_prior(self, params):
        """Log prior density (JAX; -inf outside uniform bounds), params shape (P,)."""
        total = 0.0
        for j, (dist, a, b) in enumerate(self._prior):
            t = params[j]
            if dist == "normal":
                total = total - 0.5 * ((t - a) / b) ** 2 - math.log(b) - 0.5 * math.log(2.0 * math.pi)
            else:
                total = total + jnp.where((t >= a) & (t <= b), -math.log(b - a), -jnp.inf)
        return total

    def prior_box(self) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper bounds of each parameter (+-inf for normal priors), shape (P,) each."""
        lo = np.array([a if d == "uniform" else -np.inf for d, a, b in self._prior])
        hi = np.array([b if d == "uniform" else np.inf for d, a, b in self._prior])
        return lo, hi

    def prior_draws(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """``n`` draws from the prior, shape (n, P)."""
        cols = []
        for dist, a, b in self._prior:
            cols.append(rng.normal(a, b, n) if dist == "normal" else rng.uniform(a, b, n))
        return np.column_stack(cols)
