"""The shipped example configuration loads, and its values arrive where documented."""

from pathlib import Path

import dataclasses

from comest_bayes.config import RunConfig, load_config

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "config.toml"


def test_example_config_loads_and_differs_from_defaults_only_where_it_says():
    cfg = load_config(EXAMPLE)
    default = RunConfig()
    assert cfg.seed == 1
    assert cfg.detection.phot_apertures == (5.0, 10.0)
    # everything else in the file restates a default
    assert dataclasses.replace(cfg.detection, phot_apertures=default.detection.phot_apertures) == default.detection
    for section in ("sourcefree", "injection", "matching", "ratios", "adaptive"):
        assert getattr(cfg, section) == getattr(default, section), section


def test_command_line_override_beats_the_file():
    cfg = load_config(EXAMPLE, ["detection.thresh=3", "injection.kinds=sersic"], seed=9)
    assert cfg.detection.thresh == 3.0 and cfg.injection.kinds == ("sersic",) and cfg.seed == 9
