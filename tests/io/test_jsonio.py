"""jsonio: one strict rule for every JSON file the package writes."""

import json
import math
from pathlib import Path

import numpy as np
import pytest

from comest_bayes.io.jsonio import dumps, json_float, jsonable


def test_non_finite_numbers_become_null_everywhere():
    obj = {"a": float("nan"), "b": np.float32("inf"), "c": [1.5, -np.inf, np.float64(2.0)],
           "d": np.array([[1.0, np.nan], [3.0, 4.0]]), 5: (np.int64(7), np.bool_(True))}
    out = json.loads(dumps(obj))
    assert out == {"a": None, "b": None, "c": [1.5, None, 2.0], "d": [[1.0, None], [3.0, 4.0]], "5": [7, True]}
    assert json_float(np.float32(0.25)) == 0.25 and json_float(math.nan) is None


def test_types_are_kept_exactly():
    out = jsonable({"i": np.int32(3), "f": np.float32(0.5), "b": np.bool_(False), "p": Path("/x/y"), "s": "t",
                    "n": None})
    assert out == {"i": 3, "f": 0.5, "b": False, "p": "/x/y", "s": "t", "n": None}
    assert type(out["i"]) is int and type(out["f"]) is float and type(out["b"]) is bool


def test_unknown_objects_are_refused_unless_a_fallback_is_given():
    class Thing:
        def __str__(self):
            return "thing"

    with pytest.raises(TypeError, match="Thing"):
        dumps({"x": Thing()})
    assert json.loads(dumps({"x": Thing()}, fallback=str)) == {"x": "thing"}


def test_run_json_uses_the_rule(tmp_path):
    # a NaN reaching run.json is written as null (Python's json would write the invalid token NaN)
    from comest_bayes.io.rundir import RunDirectory

    run = RunDirectory(tmp_path / "run", {"image": "x", "value": np.float64(1.0)}).open()
    run.update(timings={"fit": float("nan"), "inject": np.float32(2.5)})
    text = (tmp_path / "run" / "run.json").read_text()
    assert "NaN" not in text
    state = json.loads(text)
    assert state["timings"] == {"fit": None, "inject": 2.5}
