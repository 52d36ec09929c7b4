"""The declarative specifications in ``models/``: where they are found, and reading one TOML file.

The repository's top-level ``models/`` folder (completeness models) and ``models/counts/``
(number-count models) are installed as the package ``comest_bayes.models``, so one rule finds them
in a wheel and in a source checkout alike: :func:`models_dir` asks :mod:`importlib.resources` for
``comest_bayes.models`` and, when ``comest_bayes`` is imported from a checkout that was not
installed (e.g. ``PYTHONPATH=.``), falls back to the checkout's ``models/`` beside the package.
:func:`read_spec_toml` is the one reader both kinds of specification go through.
"""

from __future__ import annotations

import difflib
from importlib import resources
from pathlib import Path

from comest_bayes.errors import ConfigError

try:  # Python >= 3.11
    import tomllib
except ModuleNotFoundError:  # pragma: no cover - Python 3.10
    import tomli as tomllib

__all__ = ["models_dir", "list_spec_names", "read_spec_toml"]


def models_dir(sub: str = ""):
    """The folder of the shipped specifications (``sub``: a subfolder such as ``"counts"``).

    When ``comest_bayes`` is imported from a source checkout (its parent folder holds
    ``pyproject.toml`` and ``models/``), that checkout's ``models/``: the specs then always match
    the code that reads them, also when a second checkout (a git worktree on ``PYTHONPATH``) is
    imported while the editable install points at another.
    """
    checkout = Path(__file__).resolve().parents[2]
    if (checkout / "pyproject.toml").is_file() and (checkout / "models" / "logistic.toml").is_file():
        root = checkout / "models"
        return root / sub if sub else root
    try:
        root = resources.files("comest_bayes.models")
    except ModuleNotFoundError:
        root = Path(__file__).resolve().parents[2] / "models"
        if not root.is_dir():
            raise
    return root / sub if sub else root


def list_spec_names(sub: str = "") -> list[str]:
    """Names (file stems) of the shipped ``*.toml`` specifications of a folder, sorted."""
    return sorted(p.name[:-5] for p in models_dir(sub).iterdir() if p.name.endswith(".toml"))


def read_spec_toml(name_or_path, *, what: str, sub: str = "") -> tuple[dict, str, str]:
    """Read a specification by shipped name or from a TOML file.

    Parameters
    ----------
    name_or_path : str or os.PathLike
        A shipped name (a stem of :func:`list_spec_names`), or a path: anything that is a
        :class:`~pathlib.Path`, ends in ``.toml``, holds a path separator, or names an existing file
        that is not also a shipped name.
    what : str
        What a specification is called in error messages (``"model spec"``, ``"count model"``).
    sub : str
        The subfolder of ``models/`` holding the shipped ones (``""`` or ``"counts"``).

    Returns
    -------
    data : dict
        The parsed TOML.
    name : str
        The shipped name or the file's stem (used when the file has no ``name`` key).
    source : str
        Where it came from, for messages and records (``models/<sub>/<name>.toml`` or the path).

    Raises
    ------
    ConfigError
        Not a name or path; a missing or unreadable file; an unknown name (listing the shipped
        ones and suggesting the closest); invalid TOML.
    """
    if not isinstance(name_or_path, (str, Path)):
        raise ConfigError(f"{what} must be a name or the path of a TOML file, got {name_or_path!r}.")
    text = str(name_or_path)
    shipped = list_spec_names(sub)
    looks_like_path = isinstance(name_or_path, Path) or text.endswith(".toml") or "/" in text or "\\" in text
    if looks_like_path or (Path(text).is_file() and text not in shipped):
        path = Path(text)
        if not path.is_file():
            raise ConfigError(f"{what} file {text!r} does not exist; give an existing TOML file or one of the "
                              f"shipped {what}s {shipped}.")
        try:
            raw = path.read_bytes()
        except OSError as exc:
            raise ConfigError(f"{what} file {text!r} cannot be read: {exc}.") from None
        name, source = path.stem, str(path)
    else:
        if text not in shipped:
            close = difflib.get_close_matches(text, shipped, n=1)
            hint = f" Did you mean {close[0]!r}?" if close else ""
            raise ConfigError(f"unknown {what} {text!r}; available: {shipped} (or give the path of a TOML "
                              f"file).{hint}")
        raw, name = (models_dir(sub) / f"{text}.toml").read_bytes(), text
        source = "/".join(["models", *([sub] if sub else []), f"{text}.toml"])
    try:
        data = tomllib.loads(raw.decode("utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{what} file {source!r} is not valid TOML: {exc}.") from None
    return data, name, source
