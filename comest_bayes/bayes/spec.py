"""Declarative specifications of the Bayesian completeness (and purity) models.

A :class:`ModelSpec` says which model to fit (link, spatial term, width and size terms, plateau
and floor, priors, or the candidates of a selection); :func:`load_spec` reads one by name from
the shipped ``models/`` or from any TOML file.  The fields: ``docs/bayesian.md``
("Specifications"); the file format: ``models/README.md``.
"""

from __future__ import annotations

import difflib
import math
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any, Mapping

from comest_bayes.errors import ConfigError
from comest_bayes.io.specfiles import list_spec_names, read_spec_toml

__all__ = [
    "ModelSpec",
    "load_spec",
    "list_specs",
    "resolve_candidates",
    "resolve_width_candidates",
    "spec_from_mapping",
    "with_priors",
    "DEFAULT_PRIORS",
    "LINKS",
    "SPATIAL",
]

LINKS = ("logistic", "probit", "pritchet", "richards", "spline")
SPATIAL = ("none", "depth", "smooth", "depth+smooth")
SMOOTH_BASES = ("poly", "bspline")
FREE_FIXED = ("free", "fixed")
KINDS = ("completeness", "purity")
MAGNITUDES = ("true", "measured")

#: Allowed range of ``smooth_order`` per basis: polynomial total degree, or
#: cubic B-spline basis functions per axis.
SMOOTH_ORDER_RANGE = {"poly": (1, 4), "bspline": (4, 8)}

#: Default priors, keyed by parameter.  ``normal`` takes ``mu`` and ``sigma``
#: (same units as the parameter); ``beta`` takes ``a`` and ``b``.
#:
#: * ``m50_0``: magnitude where f is half-way between floor and plateau, at the
#:   reference depth (d = 0), size and field average; wide and data-independent.
#: * ``log_w``: natural log of the transition width w (mag); w = 0.2 mag
#:   expected, a factor e either way at 1 sigma.
#: * ``A``: bright-end plateau, Beta(20, 1) (mean 0.95, 1 % below 0.8).
#: * ``floor``: prior on the *ratio* floor / A (equal to the floor when the
#:   plateau is fixed to 1), Beta(1, 50) (mean 0.02).
#: * ``beta_depth``: slope of m50 on d; 1 is the background-limited expectation
#:   (m50 moves with -2.5 log10 sigma).
#: * ``w_depth``: slope of log w on d (only with ``width_depth``).
#: * ``w_uv``: every coefficient of the Legendre field of log w in ``(u, v)``
#:   (only with ``width_order > 0``); 0.5 lets the width change by a factor
#:   e^0.5 from the image centre to an edge at 1 sigma.
#: * ``beta_size``: slope of m50 on log10(hlr / hlr_ref) (galaxies).
#: * ``smooth``: every coefficient of the smooth spatial basis (mag), shrinkage
#:   towards a flat field.
#: * ``log_nu``: log of the Richards shape ``nu`` (``link = "richards"``);
#:   ``nu = 1`` is the logistic, a factor e either way at 1 sigma.
DEFAULT_PRIORS: dict[str, dict[str, Any]] = {
    "m50_0": {"dist": "normal", "mu": 25.0, "sigma": 5.0},
    "log_w": {"dist": "normal", "mu": math.log(0.2), "sigma": 1.0},
    "A": {"dist": "beta", "a": 20.0, "b": 1.0},
    "floor": {"dist": "beta", "a": 1.0, "b": 50.0},
    "beta_depth": {"dist": "normal", "mu": 1.0, "sigma": 1.0},
    "w_depth": {"dist": "normal", "mu": 0.0, "sigma": 0.5},
    "w_uv": {"dist": "normal", "mu": 0.0, "sigma": 0.5},
    "beta_size": {"dist": "normal", "mu": 0.0, "sigma": 2.0},
    "smooth": {"dist": "normal", "mu": 0.0, "sigma": 0.3},
    "log_nu": {"dist": "normal", "mu": 0.0, "sigma": 1.0},
}

#: Allowed total degree of the positional field of log w (0: none).
WIDTH_ORDER_RANGE = (0, 2)

#: Allowed number of free knots of the monotone spline (shapes.spline_knots: 24 on the bright side of
#: the anchor at t = 0, at least two on the faint side).
SPLINE_KNOTS_RANGE = (26, 60)

#: Distribution family allowed for each prior key and its arguments.
_PRIOR_FAMILY = {"A": "beta", "floor": "beta"}
_DIST_ARGS = {"normal": ("mu", "sigma"), "beta": ("a", "b")}


@dataclass(frozen=True)
class ModelSpec:
    """One completeness-model specification (or a selection over several).

    Parameters
    ----------
    name : str
        Label of the model (the file stem for the shipped specs).
    link : {"logistic", "probit", "pritchet"}
        Shape ``g`` of the transition.  Default ``"logistic"``.
    spatial : {"none", "depth", "smooth", "depth+smooth"}
        Spatial term of m50.  Default ``"none"``.
    smooth_basis : {"poly", "bspline"}
        Basis of the smooth term: Legendre polynomials ``P_i(u) P_j(v)`` with
        ``1 <= i + j <= smooth_order`` (5 terms for order 2, 9 for 3), or a
        tensor cubic B-spline with ``smooth_order`` functions per axis,
        constrained to zero field average (``smooth_order**2 - 1`` terms).
    smooth_order : int
        Polynomial total degree (1-4) or B-spline functions per axis (4-8).
        Default 2.
    width_depth : bool
        If True, ``log w = log_w + w_depth * d``.  Default False.
    width_order : int
        Total degree (0-2) of a Legendre field in ``(u, v)`` added to ``log w``:
        0 (default) none, 1 a plane ``w_10 P_1(u) + w_01 P_1(v)``, 2 adds the
        three second-degree products.  Every term averages to zero over the
        image, so ``log_w`` stays the field-average log width.
    size_covariate : bool
        If True, ``m50 += beta_size * log10(hlr / hlr_ref)``.  Default False.
    plateau : {"free", "fixed"}
        ``"fixed"`` sets ``A = 1``.  Default ``"free"``.
    floor : {"free", "fixed"}
        ``"fixed"`` sets ``floor = 0``.  Default ``"free"``.
    priors : dict
        Overrides of :data:`DEFAULT_PRIORS`, ``{param: {"dist": ..., args}}``;
        keys not given keep their defaults.
    candidates : tuple of str
        Non-empty for a selection spec: the specs (names or paths) to fit,
        simplest first.
    width_candidates : tuple of str
        Selection specs only: positional-width rungs (``width_order > 0``)
        fitted after the selection, with the chosen rung, when the width test
        of the chosen rung says the transition width differs across the image
        (``docs/bayesian.md``, "Positional width").  Default none.
    description : str
        Free text.
    kind : {"completeness", "purity"}
        What the outcome is: detected-or-not of injections (completeness), or
        real-or-false of detections (purity).  Default ``"completeness"``.
    magnitude : {"true", "measured"}
        Which magnitude is the covariate ``m``: the injected one (completeness)
        or the measured one (purity).  Default ``"true"``.
    spline_knots : int
        Free knots of the monotone spline (``link = "spline"``) in
        ``t = (m - m50) / w``: 24 on the bright side of the anchor at ``t = 0``
        (reaching ``t = -41``), the rest on the faint side, a quarter unit
        apart at ``t = 0`` and wider outward (:func:`comest_bayes.bayes.shapes.spline_knots`);
        default 44 (up to ``t = 21``).
    spline_tau : "evidence" or float
        Smoothness scale of the spline's random walk on the knot log-rates:
        a number, or ``"evidence"`` (default) to choose it by the Laplace
        approximation of the marginal likelihood over a grid.
    source : str
        Path of the file the spec was read from ("" when built in Python).
    """

    name: str
    link: str = "logistic"
    spatial: str = "none"
    smooth_basis: str = "poly"
    smooth_order: int = 2
    width_depth: bool = False
    width_order: int = 0
    size_covariate: bool = False
    plateau: str = "free"
    floor: str = "free"
    priors: dict = field(default_factory=dict)
    candidates: tuple = ()
    width_candidates: tuple = ()
    description: str = ""
    kind: str = "completeness"
    magnitude: str = "true"
    spline_knots: int = 44
    spline_tau: Any = "evidence"
    source: str = ""

    def __post_init__(self):
        _check(isinstance(self.name, str) and self.name != "", "name", self.name, "a non-empty string")
        _check(self.link in LINKS, "link", self.link, f"one of {list(LINKS)}")
        _check(self.spatial in SPATIAL, "spatial", self.spatial, f"one of {list(SPATIAL)}")
        _check(self.smooth_basis in SMOOTH_BASES, "smooth_basis", self.smooth_basis,
               f"one of {list(SMOOTH_BASES)}")
        lo, hi = SMOOTH_ORDER_RANGE[self.smooth_basis]
        _check(isinstance(self.smooth_order, int) and not isinstance(self.smooth_order, bool)
               and lo <= self.smooth_order <= hi, "smooth_order", self.smooth_order,
               f"an integer in [{lo}, {hi}] for smooth_basis = {self.smooth_basis!r}")
        _check(isinstance(self.width_depth, bool), "width_depth", self.width_depth, "true or false")
        lo_w, hi_w = WIDTH_ORDER_RANGE
        _check(isinstance(self.width_order, int) and not isinstance(self.width_order, bool)
               and lo_w <= self.width_order <= hi_w, "width_order", self.width_order,
               f"an integer in [{lo_w}, {hi_w}] (0: no positional width, 1: a plane in (u, v), 2: degree 2)")
        _check(isinstance(self.size_covariate, bool), "size_covariate", self.size_covariate, "true or false")
        _check(self.plateau in FREE_FIXED, "plateau", self.plateau, f"one of {list(FREE_FIXED)}")
        _check(self.floor in FREE_FIXED, "floor", self.floor, f"one of {list(FREE_FIXED)}")
        _check(self.kind in KINDS, "kind", self.kind, f"one of {list(KINDS)}")
        _check(self.magnitude in MAGNITUDES, "magnitude", self.magnitude, f"one of {list(MAGNITUDES)}")
        _check(isinstance(self.description, str), "description", self.description, "a string")
        lo_k, hi_k = SPLINE_KNOTS_RANGE
        _check(isinstance(self.spline_knots, int) and not isinstance(self.spline_knots, bool)
               and lo_k <= self.spline_knots <= hi_k, "spline_knots", self.spline_knots,
               f"an integer in [{lo_k}, {hi_k}]")
        tau = self.spline_tau
        if isinstance(tau, int) and not isinstance(tau, bool):
            object.__setattr__(self, "spline_tau", float(tau))
            tau = self.spline_tau
        _check(tau == "evidence" or (isinstance(tau, float) and math.isfinite(tau) and tau > 0), "spline_tau",
               tau, "\"evidence\" or a positive number")
        cands = self._tuple_field("candidates")
        _check(isinstance(cands, tuple) and all(isinstance(c, str) and c for c in cands),
               "candidates", cands, "a list of spec names or paths")
        if len(set(cands)) != len(cands):
            raise ConfigError(f"invalid candidates = {list(cands)!r}: a candidate is listed twice.")
        wc = self._tuple_field("width_candidates")
        _check(isinstance(wc, tuple) and all(isinstance(c, str) and c for c in wc),
               "width_candidates", wc, "a list of spec names or paths")
        if wc and not cands:
            raise ConfigError(f"invalid width_candidates = {list(wc)!r}: only a selection spec (with candidates) "
                              "takes width_candidates.")
        if set(wc) & set(cands) or len(set(wc)) != len(wc):
            raise ConfigError(f"invalid width_candidates = {list(wc)!r}: a spec is listed twice (or is also one of "
                              f"the candidates {list(cands)}).")
        if not isinstance(self.priors, Mapping):
            raise ConfigError(f"invalid priors = {self.priors!r}: expected a table {{param: {{dist = ...}}}}.")
        object.__setattr__(self, "priors", _validate_priors(dict(self.priors), self))

    def _tuple_field(self, name: str):
        """The field ``name``, a list read from TOML stored as a tuple (the spec is frozen and hashed)."""
        value = getattr(self, name)
        if isinstance(value, list):
            value = tuple(value)
            object.__setattr__(self, name, value)
        return value

    def __hash__(self):
        priors = tuple(sorted((k, tuple(sorted(v.items()))) for k, v in self.priors.items()))
        return hash(tuple(priors if f.name == "priors" else getattr(self, f.name) for f in fields(self)))

    # -- derived properties -------------------------------------------------
    @property
    def is_selection(self) -> bool:
        """True for a selection spec (``candidates`` non-empty)."""
        return len(self.candidates) > 0

    @property
    def uses_depth(self) -> bool:
        """True when m50 or w depends on the depth covariate."""
        return self.spatial in ("depth", "depth+smooth") or self.width_depth

    @property
    def uses_smooth(self) -> bool:
        """True when m50 has a smooth 2-D spatial term."""
        return self.spatial in ("smooth", "depth+smooth")

    @property
    def uses_width_position(self) -> bool:
        """True when log w has a field in the image coordinates ``(u, v)`` (``width_order > 0``)."""
        return self.width_order > 0

    @property
    def uses_position(self) -> bool:
        """True when f depends on the image coordinates ``(u, v)`` (smooth m50 or positional width)."""
        return self.uses_smooth or self.uses_width_position

    @property
    def is_spatial(self) -> bool:
        """True when f varies over the image at all (depth, smooth or positional-width terms)."""
        return self.spatial != "none" or self.width_depth or self.uses_width_position

    def parameters(self) -> list[str]:
        """Prior keys of this model's parameters (smooth coefficients as ``"smooth"``)."""
        keys = ["m50_0", "log_w"]
        if self.plateau == "free":
            keys.append("A")
        if self.floor == "free":
            keys.append("floor")
        if self.spatial in ("depth", "depth+smooth"):
            keys.append("beta_depth")
        if self.width_depth:
            keys.append("w_depth")
        if self.uses_width_position:
            keys.append("w_uv")
        if self.size_covariate:
            keys.append("beta_size")
        if self.link == "richards":
            keys.append("log_nu")
        if self.uses_smooth:
            keys.append("smooth")
        return keys

    def prior(self, key: str) -> dict:
        """The prior of parameter ``key``: the override if given, else the default."""
        if key not in DEFAULT_PRIORS:
            raise ConfigError(f"unknown prior key {key!r}; valid keys: {sorted(DEFAULT_PRIORS)}.")
        return dict(self.priors.get(key, DEFAULT_PRIORS[key]))

    def to_dict(self) -> dict:
        """Plain-data view (JSON/TOML friendly)."""
        out = {f.name: getattr(self, f.name) for f in fields(self)}
        out["candidates"] = list(self.candidates)
        out["width_candidates"] = list(self.width_candidates)
        out["priors"] = {k: dict(v) for k, v in self.priors.items()}
        return out


def _check(ok: bool, key: str, value: Any, expected: str) -> None:
    if not ok:
        raise ConfigError(f"invalid {key} = {value!r}: expected {expected}.")


def _number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _validate_priors(priors: dict, spec: ModelSpec) -> dict:
    out = {}
    model_keys = None if spec.candidates else set(spec.parameters())
    for key, value in priors.items():
        if key not in DEFAULT_PRIORS:
            close = difflib.get_close_matches(str(key), list(DEFAULT_PRIORS), n=1)
            hint = f" Did you mean {close[0]!r}?" if close else ""
            raise ConfigError(f"unknown prior key priors.{key}; valid keys: {sorted(DEFAULT_PRIORS)}.{hint}")
        if model_keys is not None and key not in model_keys:
            raise ConfigError(
                f"prior given for priors.{key}, but this model has no such parameter (its parameters: "
                f"{sorted(model_keys)}); remove the prior or enable the term it belongs to.")
        if not isinstance(value, Mapping):
            raise ConfigError(f"invalid priors.{key} = {value!r}: expected a table such as "
                              f"{{dist = \"normal\", mu = 0.0, sigma = 1.0}}.")
        value = dict(value)
        dist = value.pop("dist", None)
        family = _PRIOR_FAMILY.get(key, "normal")
        if dist != family:
            raise ConfigError(f"invalid priors.{key}.dist = {dist!r}: the only distribution supported for "
                              f"{key} is {family!r} (arguments {list(_DIST_ARGS[family])}).")
        args = _DIST_ARGS[family]
        extra = sorted(set(value) - set(args))
        if extra:
            raise ConfigError(f"unknown argument(s) {extra} in priors.{key}; a {family} prior takes {list(args)}.")
        missing = [a for a in args if a not in value]
        if missing:
            raise ConfigError(f"priors.{key} is missing {missing}; a {family} prior takes {list(args)}.")
        for a in args:
            v = value[a]
            positive = not (family == "normal" and a == "mu")
            if not _number(v) or (positive and v <= 0):
                raise ConfigError(f"invalid priors.{key}.{a} = {v!r}: expected a finite "
                                  f"{'positive ' if positive else ''}number.")
        out[key] = {"dist": family, **{a: float(value[a]) for a in args}}
    return out


# ---------------------------------------------------------------------------
# Loading
# ---------------------------------------------------------------------------

_SPEC_KEYS = {f.name for f in fields(ModelSpec)} - {"source"}


def list_specs() -> list[str]:
    """Names of the specifications shipped with the package (sorted): the stems of ``models/*.toml``."""
    return list_spec_names()


def spec_from_mapping(mapping: Mapping[str, Any], *, name: str | None = None, source: str = "") -> ModelSpec:
    """Build a :class:`ModelSpec` from a parsed TOML table.

    Parameters
    ----------
    mapping : mapping
        Top-level keys of a spec file.
    name : str, optional
        Name used when the mapping has no ``name`` key.
    source : str
        Where the mapping came from, for error messages.

    Raises
    ------
    ConfigError
        Unknown keys or invalid values, naming the key and the file.
    """
    where = f" in {source}" if source else ""
    data = dict(mapping)
    unknown = sorted(set(data) - _SPEC_KEYS)
    if unknown:
        hints = []
        for key in unknown:
            close = difflib.get_close_matches(key, sorted(_SPEC_KEYS), n=1)
            hints.append(f"{key!r}" + (f" (did you mean {close[0]!r}?)" if close else ""))
        raise ConfigError(f"unknown key(s) {', '.join(hints)}{where}; valid keys: {sorted(_SPEC_KEYS)}.")
    if "candidates" in data:
        cands = data["candidates"]
        if not isinstance(cands, list):
            raise ConfigError(f"invalid candidates = {cands!r}{where}: expected a list of spec names or paths.")
        data["candidates"] = tuple(cands)
        model_keys = sorted(set(data) - {"name", "candidates", "width_candidates", "description", "kind", "magnitude"})
        if model_keys:
            raise ConfigError(f"a selection spec (with candidates) takes no model keys, got {model_keys}{where}; "
                              "put them in the candidate specs instead.")
    if "width_candidates" in data:
        wc = data["width_candidates"]
        if not isinstance(wc, list):
            raise ConfigError(f"invalid width_candidates = {wc!r}{where}: expected a list of spec names or paths.")
        data["width_candidates"] = tuple(wc)
    if "name" not in data:
        if name is None:
            raise ConfigError(f"missing key 'name'{where}.")
        data["name"] = name
    try:
        return ModelSpec(**data, source=source)
    except ConfigError as exc:
        raise ConfigError(f"{exc}".rstrip(".") + f"{where}.") from None


def load_spec(name_or_path) -> ModelSpec:
    """Read a model specification by name or from a TOML file.

    Parameters
    ----------
    name_or_path : str, os.PathLike or ModelSpec
        A name from :func:`list_specs` (``"logistic_depth"``), or the path of a
        TOML file (anything ending in ``.toml``, containing a path separator,
        or naming an existing file).  A :class:`ModelSpec` is returned as is.

    Returns
    -------
    ModelSpec

    Raises
    ------
    ConfigError
        Unknown name (the message lists the available specs and suggests the
        closest), missing file, invalid TOML, unknown keys or invalid values
        (the message names the key and the file).
    """
    if isinstance(name_or_path, ModelSpec):
        return name_or_path
    data, name, source = read_spec_toml(name_or_path, what="model spec")
    return spec_from_mapping(data, name=name, source=source)


def resolve_candidates(spec: ModelSpec | str) -> list[ModelSpec]:
    """The candidate specs of a selection spec, in order (simplest first).

    Candidates given as relative paths are resolved against the directory of
    the selection spec's file.

    Raises
    ------
    ConfigError
        ``spec`` is not a selection spec, a candidate is unknown, or a
        candidate is itself a selection spec.
    """
    spec = load_spec(spec)
    if not spec.is_selection:
        raise ConfigError(f"model spec {spec.name!r} is not a selection spec (it has no candidates).")
    return _resolve(spec, spec.candidates, "candidate")


def resolve_width_candidates(spec: ModelSpec | str) -> list[ModelSpec]:
    """The positional-width candidates of a selection spec (``width_candidates``), in order.

    Raises
    ------
    ConfigError
        As :func:`resolve_candidates`, and for a width candidate without a
        positional width (``width_order = 0``).
    """
    spec = load_spec(spec)
    out = _resolve(spec, spec.width_candidates, "width candidate") if spec.is_selection else []
    for child in out:
        if not child.uses_width_position:
            raise ConfigError(f"width candidate {child.name!r} of selection spec {spec.name!r} has no positional "
                              "width (width_order = 0); list specs with width_order = 1 or 2.")
    return out


def _resolve(spec: ModelSpec, names, what: str) -> list[ModelSpec]:
    base = Path(spec.source).parent if spec.source and Path(spec.source).is_file() else None
    out = []
    for cand in names:
        target = cand
        if base is not None and (cand.endswith(".toml") or "/" in cand) and not Path(cand).is_absolute():
            target = str(base / cand)
        try:
            child = load_spec(target)
        except ConfigError as exc:
            raise ConfigError(f"{what} {cand!r} of selection spec {spec.name!r}: {exc}") from None
        if child.is_selection:
            raise ConfigError(f"{what} {cand!r} of selection spec {spec.name!r} is itself a selection spec; "
                              "list model specs only.")
        if child.kind != spec.kind:
            raise ConfigError(f"{what} {cand!r} is a {child.kind} model but selection spec {spec.name!r} is "
                              f"for {spec.kind}.")
        out.append(child)
    return out


def with_priors(spec: ModelSpec, **priors) -> ModelSpec:
    """Copy of ``spec`` with some priors replaced (validated)."""
    merged = dict(spec.priors)
    merged.update(priors)
    return replace(spec, priors=merged)
