"""Model specifications: the shipped TOML files, loading by name or path, validation."""

from __future__ import annotations

import math

import pytest

from comest_bayes.errors import ConfigError
from comest_bayes.bayes.spec import (DEFAULT_PRIORS, ModelSpec, list_specs, load_spec, resolve_candidates, spec_from_mapping, with_priors)
from conftest import REPO_ROOT

SHIPPED = ["auto", "auto_smooth", "logistic", "logistic_depth", "logistic_depth_size", "logistic_depth_smooth",
           "logistic_depth_width_uv", "logistic_smooth", "pritchet", "probit", "probit_depth", "purity", "richards_depth", "spline_depth",
           "spline_depth_width", "spline_depth_width_uv"]


def test_list_specs_finds_every_shipped_file():
    from comest_bayes.io.specfiles import models_dir

    assert list_specs() == sorted(SHIPPED)
    files = {p.name for p in models_dir().iterdir()}
    assert {f"{n}.toml" for n in SHIPPED} <= files
    assert "README.md" in files  # the format documentation ships with the package


def test_the_wheel_maps_models_into_the_package():
    """models/ (top level, as the user asked) is installed as comest_bayes.models with its files."""
    import sys

    tomllib = pytest.importorskip("tomllib") if sys.version_info >= (3, 11) else pytest.importorskip("tomli")
    root = REPO_ROOT
    setup = tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"]
    assert "comest_bayes.models" in setup["packages"]
    assert setup["package-dir"]["comest_bayes.models"] == "models"
    assert {"*.toml", "*.md"} <= set(setup["package-data"]["comest_bayes.models"])
    assert (root / "models" / "__init__.py").is_file()


def test_the_wheel_lists_every_subpackage_of_the_library():
    """A subpackage missing from [tool.setuptools] packages is left out of a wheel install (the report's
    ``comest_bayes.report.plots`` once was), while tests run from the checkout still import it."""
    import sys

    tomllib = pytest.importorskip("tomllib") if sys.version_info >= (3, 11) else pytest.importorskip("tomli")
    root = REPO_ROOT
    listed = set(tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    on_disk = {".".join(p.parent.relative_to(root).parts) for p in (root / "comest_bayes").rglob("__init__.py")}
    assert on_disk, "no package found under comest_bayes/"
    assert on_disk <= listed, f"subpackages not installed by pyproject.toml: {sorted(on_disk - listed)}"


@pytest.mark.parametrize("name", SHIPPED)
def test_every_shipped_spec_loads_and_is_self_consistent(name):
    spec = load_spec(name)
    assert spec.name == name
    assert spec.description
    assert spec.source.endswith(f"{name}.toml")
    if spec.is_selection:
        for child in resolve_candidates(spec):
            assert not child.is_selection
    else:
        # every prior override in a shipped file must belong to a parameter of the model
        assert set(spec.priors) <= set(spec.parameters())


def test_shipped_specs_have_the_documented_content():
    assert load_spec("logistic") == ModelSpec(name="logistic", description=load_spec("logistic").description,
                                              source=load_spec("logistic").source)
    smooth = load_spec("logistic_smooth")
    assert (smooth.spatial, smooth.smooth_basis, smooth.smooth_order) == ("smooth", "poly", 2)
    assert smooth.prior("smooth") == {"dist": "normal", "mu": 0.0, "sigma": 0.3}
    assert load_spec("logistic_depth_smooth").spatial == "depth+smooth"
    assert load_spec("probit_depth").link == "probit" and load_spec("probit_depth").spatial == "depth"
    assert load_spec("pritchet").link == "pritchet"
    size = load_spec("logistic_depth_size")
    assert size.size_covariate and size.spatial == "depth"
    purity = load_spec("purity")
    assert (purity.kind, purity.magnitude, purity.spatial, purity.link) == ("purity", "measured", "none", "logistic")
    auto = load_spec("auto")
    assert auto.candidates == ("logistic", "logistic_depth", "richards_depth", "spline_depth")
    assert [c.name for c in resolve_candidates("auto")] == list(auto.candidates)
    # simplest first: parameter counts never decrease along the candidate list (a spline adds its knot log-rates)
    counts = [len(c.parameters()) + (c.spline_knots if c.link == "spline" else 0) for c in resolve_candidates("auto")]
    assert counts == sorted(counts) and counts == [4, 5, 6, 49]
    spline = load_spec("spline_depth")
    assert (spline.link, spline.spatial, spline.spline_knots, spline.spline_tau) == ("spline", "depth", 44, "evidence")
    assert load_spec("auto_smooth").candidates[-1] == "spline_depth"


def test_default_priors_are_the_documented_ones():
    assert DEFAULT_PRIORS["log_w"]["mu"] == pytest.approx(math.log(0.2))
    assert DEFAULT_PRIORS["A"] == {"dist": "beta", "a": 20.0, "b": 1.0}
    assert DEFAULT_PRIORS["floor"] == {"dist": "beta", "a": 1.0, "b": 50.0}
    assert DEFAULT_PRIORS["beta_depth"]["mu"] == 1.0
    spec = load_spec("logistic")
    assert spec.prior("m50_0") == DEFAULT_PRIORS["m50_0"]


def test_unknown_name_lists_specs_and_suggests():
    with pytest.raises(ConfigError) as err:
        load_spec("logistic_dpth")
    msg = str(err.value)
    assert "logistic_dpth" in msg and "Did you mean 'logistic_depth'" in msg
    for name in SHIPPED:
        assert name in msg


def test_missing_file_is_a_config_error(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        load_spec(tmp_path / "nope.toml")


def test_load_by_path_with_prior_override(tmp_path):
    path = tmp_path / "mine.toml"
    path.write_text('link = "probit"\nspatial = "depth"\nwidth_depth = true\n'
                    '[priors.beta_depth]\ndist = "normal"\nmu = 0.8\nsigma = 0.2\n')
    spec = load_spec(str(path))
    assert spec.name == "mine"  # defaults to the file stem
    assert spec.link == "probit" and spec.width_depth
    assert spec.prior("beta_depth") == {"dist": "normal", "mu": 0.8, "sigma": 0.2}
    assert spec.prior("w_depth") == DEFAULT_PRIORS["w_depth"]
    assert spec.parameters() == ["m50_0", "log_w", "A", "floor", "beta_depth", "w_depth"]


@pytest.mark.parametrize("text, key", [
    ('lnk = "logistic"\n', "lnk"),
    ('link = "cauchy"\n', "link"),
    ('spatial = "depth+size"\n', "spatial"),
    ('smooth_order = 2.5\nspatial = "smooth"\n', "smooth_order"),
    ('smooth_basis = "bspline"\nsmooth_order = 2\n', "smooth_order"),
    ('plateau = "one"\n', "plateau"),
    ('width_depth = "yes"\n', "width_depth"),
    ('[priors.m50]\ndist = "normal"\nmu = 1.0\nsigma = 1.0\n', "m50"),
    ('[priors.A]\ndist = "normal"\nmu = 1.0\nsigma = 1.0\n', "priors.A.dist"),
    ('[priors.m50_0]\ndist = "normal"\nmu = 1.0\nsigma = -1.0\n', "priors.m50_0.sigma"),
    ('[priors.m50_0]\ndist = "normal"\nmu = 1.0\n', "priors.m50_0"),
    ('[priors.m50_0]\ndist = "normal"\nmu = 1.0\nsigma = 1.0\nnu = 3\n', "priors.m50_0"),
    ('[priors.beta_depth]\ndist = "normal"\nmu = 1.0\nsigma = 1.0\n', "beta_depth"),  # no depth term
    ('candidates = ["logistic"]\nlink = "probit"\n', "link"),
    ('link = [1, 2\n', "not valid TOML"),
])
def test_invalid_files_name_the_key_and_the_file(tmp_path, text, key):
    path = tmp_path / "bad_spec.toml"
    path.write_text(text)
    with pytest.raises(ConfigError) as err:
        load_spec(path)
    msg = str(err.value)
    assert key in msg
    assert "bad_spec.toml" in msg


def test_unknown_key_suggests_the_right_one():
    with pytest.raises(ConfigError, match="did you mean 'spatial'"):
        spec_from_mapping({"spatal": "depth"}, name="x")


def test_selection_spec_candidates_resolved_relative_to_file(tmp_path):
    (tmp_path / "a.toml").write_text('spatial = "depth"\n')
    (tmp_path / "sel.toml").write_text('candidates = ["logistic", "a.toml"]\n')
    cands = resolve_candidates(str(tmp_path / "sel.toml"))
    assert [c.name for c in cands] == ["logistic", "a"]
    assert cands[1].spatial == "depth"
    (tmp_path / "nested.toml").write_text('candidates = ["auto"]\n')
    with pytest.raises(ConfigError, match="itself a selection"):
        resolve_candidates(str(tmp_path / "nested.toml"))
    with pytest.raises(ConfigError, match="not a selection spec"):
        resolve_candidates("logistic")
    (tmp_path / "badc.toml").write_text('candidates = ["logistc"]\n')
    with pytest.raises(ConfigError, match="Did you mean 'logistic'"):
        resolve_candidates(str(tmp_path / "badc.toml"))


def test_python_construction_validates_and_hashes():
    spec = ModelSpec(name="m", spatial="smooth", smooth_basis="bspline", smooth_order=4)
    assert spec.parameters()[-1] == "smooth"
    assert hash(spec) == hash(ModelSpec(name="m", spatial="smooth", smooth_basis="bspline", smooth_order=4))
    with pytest.raises(ConfigError, match="smooth_order"):
        ModelSpec(name="m", smooth_order=True)
    changed = with_priors(spec, smooth={"dist": "normal", "mu": 0.0, "sigma": 0.1})
    assert changed.prior("smooth")["sigma"] == 0.1 and spec.prior("smooth")["sigma"] == 0.3
    assert ModelSpec(name="f", plateau="fixed", floor="fixed").parameters() == ["m50_0", "log_w"]
    with pytest.raises(ConfigError, match="no such parameter"):
        ModelSpec(name="f", floor="fixed", priors={"floor": {"dist": "beta", "a": 1, "b": 9}})
