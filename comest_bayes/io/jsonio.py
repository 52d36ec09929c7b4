"""The package's one rule for writing JSON (``run.json``, ``summary.json``, posterior metadata, designs).

Strict JSON: a value that is not a finite number (NaN, infinity) is written as ``null``, never as
the ``NaN`` token that Python's :mod:`json` writes by default and that other readers reject.
NumPy scalars and arrays become plain numbers and lists, tuples become lists, paths become strings
and mapping keys become strings.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import PurePath
from collections.abc import Mapping
from typing import Any, Callable

__all__ = ["jsonable", "json_float", "dumps"]


def json_float(x) -> float | None:
    """``float(x)``, or None when it is not finite."""
    x = float(x)
    return x if math.isfinite(x) else None


def jsonable(obj: Any, *, fallback: Callable[[Any], Any] | None = None) -> Any:
    """``obj`` with every container, NumPy value and non-finite number made strict-JSON ready.

    Parameters
    ----------
    obj : any
        Nested dicts, lists, tuples, NumPy arrays and scalars, numbers, strings, booleans, None,
        paths.
    fallback : callable, optional
        Applied to any other object (e.g. ``str``); without it such an object raises ``TypeError``.
    """
    if obj is None or isinstance(obj, (str, bool)):
        return obj
    # NumPy values can only exist once NumPy is imported; not importing it here keeps `import
    # comest_bayes.config` (and the front door) free of it
    np = sys.modules.get("numpy")
    if isinstance(obj, Mapping):
        return {str(k): jsonable(v, fallback=fallback) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v, fallback=fallback) for v in obj]
    if np is not None:
        if isinstance(obj, np.ndarray):
            return jsonable(obj.tolist(), fallback=fallback)
        if isinstance(obj, np.bool_):
            return bool(obj)
        if isinstance(obj, np.integer):
            return int(obj)
        if isinstance(obj, np.floating):
            return json_float(obj)
    if isinstance(obj, int):
        return int(obj)
    if isinstance(obj, float):
        return json_float(obj)
    if isinstance(obj, PurePath):
        return str(obj)
    if fallback is not None:
        return fallback(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def dumps(obj: Any, *, fallback: Callable[[Any], Any] | None = None, **kwargs) -> str:
    """:func:`json.dumps` of :func:`jsonable` ``(obj)``, refusing any non-finite number that slipped through."""
    return json.dumps(jsonable(obj, fallback=fallback), allow_nan=False, **kwargs)
