"""Configuration: SExtractor's defaults, TOML files, CLI overrides, validation, JSON round trip."""

import dataclasses
import json
import re
import shutil
import subprocess

import pytest

from comest_bayes.config import DetectionConfig, RunConfig, SourceFreeConfig, load_config, parse_override
from comest_bayes.errors import ConfigError

#: SExtractor's built-in defaults (SExtractor manual; ``source-extractor -dd``), by our key.
SEXTRACTOR_DEFAULTS = {
    "thresh": ("DETECT_THRESH", 1.5),
    "minarea": ("DETECT_MINAREA", 5),
    "deblend_nthresh": ("DEBLEND_NTHRESH", 32),
    "deblend_mincont": ("DEBLEND_MINCONT", 0.005),
    "clean": ("CLEAN", True),
    "clean_param": ("CLEAN_PARAM", 1.0),
    "back_size": ("BACK_SIZE", 64),
    "back_filtersize": ("BACK_FILTERSIZE", 3),
    "phot_autoparams": ("PHOT_AUTOPARAMS", (2.5, 3.5)),
    "phot_apertures": ("PHOT_APERTURES", (5.0,)),
    "phot_fluxfrac": ("PHOT_FLUXFRAC", 0.5),
}


@pytest.mark.parametrize("key", sorted(SEXTRACTOR_DEFAULTS))
def test_detection_defaults_are_sextractors(key):
    assert getattr(DetectionConfig(), key) == SEXTRACTOR_DEFAULTS[key][1]


def test_detection_defaults_filter_and_noise():
    cfg = DetectionConfig()
    assert cfg.filter == "default"  # FILTER_NAME default.conv
    assert cfg.noise == "auto" and cfg.backend == "sep"


def _sextractor_builtin_defaults():
    exe = shutil.which("source-extractor") or shutil.which("sex")
    if exe is None:
        pytest.skip("SExtractor binary (source-extractor) not installed; cannot read its built-in defaults")
    out = subprocess.run([exe, "-dd"], capture_output=True, text=True, timeout=30).stdout
    values = {}
    for line in out.splitlines():
        m = re.match(r"^([A-Z_]+)\s+([^#]+?)\s*(#.*)?$", line)
        if m:
            values[m.group(1)] = m.group(2)
    return values


def test_defaults_agree_with_the_installed_sextractor():
    builtin = _sextractor_builtin_defaults()
    cfg = DetectionConfig()
    for key, (keyword, _) in SEXTRACTOR_DEFAULTS.items():
        text = builtin[keyword]
        ours = getattr(cfg, key)
        if isinstance(ours, bool):
            assert ours == (text.strip().upper() == "Y"), keyword
        elif isinstance(ours, tuple):
            assert ours == tuple(float(v) for v in text.split(",")), keyword
        else:
            assert ours == type(ours)(float(text)), keyword
    assert builtin["FILTER_NAME"] == "default.conv"


def test_run_config_defaults():
    cfg = load_config()
    assert cfg == RunConfig()
    assert cfg.seed == 0
    assert cfg.detection == DetectionConfig() and cfg.sourcefree == SourceFreeConfig()


def test_toml_file_is_loaded(tmp_path):
    path = tmp_path / "run.toml"
    path.write_text(
        "seed = 42\n"
        "[detection]\n"
        "thresh = 3.0\n"
        "minarea = 7\n"
        "clean = false\n"
        "phot_apertures = [4, 8.5]\n"
        "filter = \"gauss_3.0_5x5\"\n"
        "[sourcefree]\n"
        "dilate = 2\n"  # an integer where a float is expected is accepted
    )
    cfg = load_config(path)
    assert cfg.seed == 42
    assert cfg.detection.thresh == 3.0 and cfg.detection.minarea == 7 and cfg.detection.clean is False
    assert cfg.detection.phot_apertures == (4.0, 8.5)
    assert cfg.detection.filter == "gauss_3.0_5x5"
    assert cfg.sourcefree.dilate == 2.0 and isinstance(cfg.sourcefree.dilate, float)
    # Everything not in the file keeps its default.
    assert cfg.detection.deblend_nthresh == 32 and cfg.sourcefree.bnb is True
    # Overrides and the seed argument apply after the file.
    cfg2 = load_config(path, overrides=["detection.thresh=5"], seed=7)
    assert cfg2.detection.thresh == 5.0 and cfg2.detection.minarea == 7 and cfg2.seed == 7


@pytest.mark.parametrize("text, key, expected", [
    ("detection.thresh=2.5", "thresh", 2.5),
    ("detection.thresh=3", "thresh", 3.0),
    ("detection.minarea=8", "minarea", 8),
    ("detection.clean=false", "clean", False),
    ("detection.clean=No", "clean", False),
    ("detection.clean=1", "clean", True),
    ("detection.phot_autoparams=[2.0, 4.0]", "phot_autoparams", (2.0, 4.0)),
    ("detection.phot_apertures=3,6,12", "phot_apertures", (3.0, 6.0, 12.0)),
    ("detection.phot_apertures=7", "phot_apertures", (7.0,)),
    ("detection.noise=global", "noise", "global"),
    (" detection.thresh = 4.5 ", "thresh", 4.5),
])
def test_string_overrides_are_coerced(text, key, expected):
    value = getattr(load_config(overrides=[text]).detection, key)
    assert value == expected
    assert type(value) is type(expected)


def test_mapping_overrides():
    cfg = load_config(overrides={"detection": {"thresh": 2, "clean": False, "minarea": 8.0},
                                 "sourcefree": {"bnb": False}})
    assert cfg.detection.thresh == 2.0 and isinstance(cfg.detection.thresh, float)
    assert cfg.detection.minarea == 8 and isinstance(cfg.detection.minarea, int)  # a whole float is an int
    assert cfg.detection.clean is False and cfg.sourcefree.bnb is False


@pytest.mark.parametrize("text, pattern", [
    ("detection.minarea=2.5", r"invalid detection\.minarea = '2\.5'.*type int"),
    ("detection.clean=maybe", r"invalid detection\.clean = 'maybe'.*type bool"),
    ("detection.thresh=abc", r"invalid detection\.thresh = 'abc'.*type float"),
    ("detection.phot_apertures=a,b", r"invalid detection\.phot_apertures"),
])
def test_uncoercible_overrides(text, pattern):
    with pytest.raises(ConfigError, match=pattern):
        load_config(overrides=[text])


def test_bool_is_not_taken_as_a_number():
    with pytest.raises(ConfigError, match=r"detection\.thresh"):
        load_config(overrides={"detection": {"thresh": True}})
    with pytest.raises(ConfigError, match=r"detection\.minarea"):
        load_config(overrides={"detection": {"minarea": True}})


def test_unknown_key_suggests_the_close_match(tmp_path):
    with pytest.raises(ConfigError,
                       match=r"unknown setting 'detection\.treshold'\. Did you mean 'detection\.thresh'\?"):
        load_config(overrides=["detection.treshold=2"])
    path = tmp_path / "c.toml"
    path.write_text("[detection]\nminaera = 4\n")
    with pytest.raises(ConfigError, match=r"Did you mean 'detection\.minarea'\?.*Valid keys of \[detection\]"):
        load_config(path)


def test_unknown_key_without_a_close_match_lists_the_valid_keys():
    with pytest.raises(ConfigError) as info:
        load_config(overrides=["detection.zzzzzz=1"])
    assert "Did you mean" not in str(info.value)
    assert "back_filtersize" in str(info.value) and "thresh" in str(info.value)


def test_overrides_in_every_documented_form_give_the_same_configuration():
    # found by a new user: load_config took nested tables but not dotted keys, comest_bayes.run the reverse
    from comest_bayes.api import config_from_options

    want = load_config(overrides=["detection.thresh=2.5", "injection.nsims=7"])
    assert want.detection.thresh == 2.5 and want.injection.nsims == 7
    forms = ({"detection.thresh": 2.5, "injection.nsims": 7}, {"detection": {"thresh": 2.5}, "injection.nsims": 7},
             {"detection": {"thresh": 2.5}, "injection": {"nsims": 7}})
    for form in forms:
        assert load_config(overrides=form) == want
        assert config_from_options(overrides=form) == want
    assert load_config(overrides="detection.thresh=2.5").detection.thresh == 2.5
    assert config_from_options(overrides=["detection.thresh=2.5"], nsims=7) == want
    assert config_from_options(overrides={"injection.nsims": 3}, nsims=7).injection.nsims == 7  # the shortcut wins
    with pytest.raises(ConfigError, match=r"cannot read the override 'thresh': 2\.5"):
        load_config(overrides={"thresh": 2.5})
    with pytest.raises(ConfigError, match=r"adaptive.magnitudes = \['foo'\]: expected a comma-separated list of numbers"):
        load_config(overrides={"adaptive.magnitudes": "foo"})


def test_unknown_section(tmp_path):
    with pytest.raises(ConfigError, match=r"unknown section 'detect' in override 'detect\.thresh=2'.*'detection'"):
        load_config(overrides=["detect.thresh=2"])
    with pytest.raises(ConfigError, match=r"unknown section 'photometry'"):
        load_config(overrides={"photometry": {"x": 1}})
    path = tmp_path / "c.toml"
    path.write_text("[detecton]\nthresh = 2\n")
    with pytest.raises(ConfigError, match=r"unknown table\(s\) \['detecton'\].*valid tables"):
        load_config(path)


@pytest.mark.parametrize("text", ["thresh=2", "detection.thresh", "detection thresh 2"])
def test_malformed_override(text):
    with pytest.raises(ConfigError, match=r"write it as section\.key=value"):
        load_config(overrides=[text])


def test_parse_override_splits_at_the_first_dot_and_equals():
    assert parse_override("detection.filter=/a/b.c=d.conv") == ("detection", "filter", "/a/b.c=d.conv")


@pytest.mark.parametrize("kwargs, key", [
    ({"thresh": -1.0}, "detection.thresh"),
    ({"thresh": 0.0}, "detection.thresh"),
    ({"minarea": 0}, "detection.minarea"),
    ({"back_filtersize": 4}, "detection.back_filtersize"),
    ({"back_size": 2}, "detection.back_size"),
    ({"noise": "rms"}, "detection.noise"),
    ({"deblend_nthresh": 65}, "detection.deblend_nthresh"),
    ({"deblend_mincont": 1.5}, "detection.deblend_mincont"),
    ({"phot_autoparams": (2.5,)}, "detection.phot_autoparams"),
    ({"phot_apertures": (5.0, -1.0)}, "detection.phot_apertures"),
    ({"phot_fluxfrac": 1.0}, "detection.phot_fluxfrac"),
    ({"pixstack": 100}, "detection.pixstack"),
    ({"sub_object_limit": 10}, "detection.sub_object_limit"),
    ({"backend": "sextract"}, "detection.backend"),
])
def test_invalid_detection_values_name_the_key(kwargs, key):
    (name, value), = kwargs.items()
    with pytest.raises(ConfigError, match=rf"invalid {re.escape(key)} = {re.escape(repr(value))}: expected"):
        DetectionConfig(**kwargs)


@pytest.mark.parametrize("text, key", [
    ("detection.thresh=-1", "detection.thresh"),
    ("detection.back_filtersize=4", "detection.back_filtersize"),
    ("detection.noise=median", "detection.noise"),
    ("sourcefree.dilate=-0.5", "sourcefree.dilate"),
])
def test_invalid_values_from_overrides_name_the_key(text, key):
    with pytest.raises(ConfigError, match=rf"invalid {re.escape(key)} = "):
        load_config(overrides=[text])


def test_error_messages_say_what_is_expected():
    with pytest.raises(ConfigError, match=r"expected an odd integer >= 1, e\.g\. 3"):
        DetectionConfig(back_filtersize=4)
    with pytest.raises(ConfigError, match=r"expected one of \('auto', 'background', 'global', 'weight'\)"):
        DetectionConfig(noise="bad")


@pytest.mark.parametrize("seed", [-1, 1.5, "3", True])
def test_invalid_seed(seed):
    with pytest.raises(ConfigError, match="seed"):
        RunConfig(seed=seed)


def test_missing_and_invalid_config_files(tmp_path):
    with pytest.raises(ConfigError, match=r"does not exist; check the --config path"):
        load_config(tmp_path / "missing.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[detection\nthresh = \n")
    with pytest.raises(ConfigError, match="is not valid TOML"):
        load_config(bad)


def test_configs_are_immutable():
    cfg = DetectionConfig()
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.thresh = 3.0


def test_to_dict_json_round_trip():
    cfg = load_config(overrides=["detection.thresh=2.5", "detection.phot_apertures=3,6",
                                 "detection.clean=false", "sourcefree.dilate=1.5"], seed=11)
    text = json.dumps(cfg.to_dict())
    state = json.loads(text)
    assert state["detection"]["phot_apertures"] == [3.0, 6.0]  # tuples become lists
    assert state["seed"] == 11
    seed = state.pop("seed")
    again = load_config(overrides=state, seed=seed)
    assert again == cfg
    assert json.dumps(again.to_dict()) == text


def test_default_to_dict_round_trip():
    cfg = RunConfig()
    state = json.loads(json.dumps(cfg.to_dict()))
    assert load_config(overrides={k: v for k, v in state.items() if k != "seed"}, seed=state["seed"]) == cfg


def test_noise_level_and_clean_zone_settings():
    cfg = load_config(overrides=["detection.noise_level=observed", "matching.exclude_clean_zone=true"])
    assert cfg.detection.noise_level == "observed" and cfg.matching.exclude_clean_zone is True
    assert load_config().detection.noise_level == "per_image"
    with pytest.raises(ConfigError, match=r"invalid detection\.noise_level = 'measured': expected one of "
                                          r"\('per_image', 'observed'\)"):
        load_config(overrides=["detection.noise_level=measured"])
    with pytest.raises(ConfigError, match=r"invalid matching\.exclude_clean_zone = 'often'.*type bool"):
        load_config(overrides=["matching.exclude_clean_zone=often"])


def test_a_warning_fraction_above_the_refusal_names_both_settings():
    # found by a new user: --set sourcefree.warn_replaced=0.95 was blamed on max_replaced, which they had not set
    with pytest.raises(ConfigError, match=r"sourcefree.warn_replaced = 0.95 is above sourcefree.max_replaced = 0.9"):
        load_config(overrides=["sourcefree.warn_replaced=0.95"])
    with pytest.raises(ConfigError, match=r"invalid sourcefree.max_replaced = 1.5: expected a fraction up to 1"):
        load_config(overrides=["sourcefree.max_replaced=1.5"])
    both = load_config(overrides=["sourcefree.warn_replaced=0.95", "sourcefree.max_replaced=1"]).sourcefree
    assert (both.warn_replaced, both.max_replaced) == (0.95, 1.0)
