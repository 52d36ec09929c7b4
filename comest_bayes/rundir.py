"""The run directory: where every output of a run lives, written atomically.

Rules
-----
* A file appears under its final name only when it is complete: it is
  written to a hidden temporary name in the same directory and moved into
  place with :func:`os.replace` (atomic on POSIX).  A crash leaves at most a
  ``.tmp-*`` file, which the next run removes.
* ``run.json`` records the run's *fingerprint* (input file checksums, image
  options, resolved configuration, seed) and which stages are done.  Opening
  a directory that holds the same fingerprint resumes it: finished stages are
  skipped.  A different fingerprint is refused with the list of differences;
  nothing is overwritten silently.  A non-empty directory that is not a run
  is refused too.
* Inputs are only ever read; output names are fixed and the directory must
  be empty or a run, so no input can be overwritten.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import hashlib
import json
import os
import platform
from pathlib import Path

import numpy as np
from astropy.io import fits

from .errors import RunDirectoryError

__all__ = ["RunDirectory", "atomic_path", "file_checksum", "versions"]

RUN_FILE = "run.json"
#: Subfolders a run directory may hold besides its own files (the demo's synthetic inputs).
ALLOWED_FOREIGN = {"inputs"}


@contextlib.contextmanager
def atomic_path(final: Path):
    """Yield a temporary path next to ``final``; move it into place on success."""
    final = Path(final)
    tmp = final.with_name(f".tmp-{os.getpid()}-{final.name}")
    try:
        yield tmp
        os.replace(tmp, final)
    finally:
        if tmp.exists():
            tmp.unlink()


def file_checksum(path, chunk: int = 1 << 22) -> str:
    """SHA-256 of a file's content (hex)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            h.update(block)
    return h.hexdigest()


def versions() -> dict:
    """Versions of Python and the numerical libraries a run depends on."""
    from importlib.metadata import PackageNotFoundError, version

    out = {"python": platform.python_version()}
    for pkg in ("comest-bayes", "numpy", "scipy", "astropy", "galsim", "sep", "jax", "emcee"):
        try:
            out[pkg] = version(pkg)
        except PackageNotFoundError:
            out[pkg] = None
    return out


def _diff(a, b, prefix=""):
    """Keys whose values differ between two nested dicts (dotted paths)."""
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for key in sorted(set(a) | set(b)):
            out += _diff(a.get(key), b.get(key), f"{prefix}{key}.")
        return out
    return [] if a == b else [prefix.rstrip(".")]


def _json_default(obj):
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (np.floating,)):
        return float(obj)
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


class RunDirectory:
    """A run's output directory.

    Parameters
    ----------
    path : str or Path
        The directory (created if missing).
    fingerprint : dict
        JSON-ready description of what defines the run; compared on resume.
    """

    def __init__(self, path, fingerprint: dict):
        self.path = Path(path)
        self.fingerprint = json.loads(json.dumps(fingerprint, default=_json_default))
        self.resumed = False
        self._state: dict = {}

    # -- opening -----------------------------------------------------------------
    def check(self) -> None:
        """Decide between new run, resume and refusal without writing anything."""
        p = self.path
        if p.exists() and not p.is_dir():
            raise RunDirectoryError(f"--out {str(p)!r} is an existing file, not a directory; choose another --out.")
        run_file = p / RUN_FILE
        if run_file.exists():
            try:
                state = json.loads(run_file.read_text())
            except (OSError, json.JSONDecodeError) as exc:
                raise RunDirectoryError(
                    f"{str(run_file)!r} is unreadable ({exc}); this directory does not hold a usable run. "
                    f"Choose another --out or remove the directory."
                ) from None
            old = state.get("fingerprint", {})
            diffs = _diff(old, self.fingerprint)
            if diffs:
                shown = ", ".join(diffs[:8]) + (" ..." if len(diffs) > 8 else "")
                raise RunDirectoryError(
                    f"{str(p)!r} holds a different run (differs in: {shown}). Nothing was overwritten. "
                    f"Choose another --out, or remove {str(p)!r} to start again."
                )
            self._state = state
            self.resumed = True
        elif p.exists():
            foreign = [c.name for c in p.iterdir()
                       if c.name not in ALLOWED_FOREIGN and not c.name.startswith(".tmp-")]
            if foreign:
                raise RunDirectoryError(
                    f"--out {str(p)!r} is not empty and is not a comest-bayes run (found {sorted(foreign)[:5]}); "
                    f"choose an empty or new directory so nothing in it is overwritten."
                )

    def open(self) -> "RunDirectory":
        """Create or resume the directory (after :meth:`check`)."""
        self.check()
        try:
            self.path.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise RunDirectoryError(f"cannot create --out {str(self.path)!r}: {exc}.") from None
        for stale in self.path.glob(".tmp-*"):
            stale.unlink()
        if not self.resumed:
            self._state = {
                "fingerprint": self.fingerprint,
                "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                "versions": versions(),
                "stages": {},
            }
            self._save()
        return self

    # -- state ---------------------------------------------------------------------
    @property
    def state(self) -> dict:
        return self._state

    def _save(self) -> None:
        with atomic_path(self.path / RUN_FILE) as tmp:
            tmp.write_text(json.dumps(self._state, indent=2, default=_json_default) + "\n")

    def update(self, **items) -> None:
        """Set top-level entries of ``run.json`` (e.g. ``image=...``) and save."""
        self._state.update(json.loads(json.dumps(items, default=_json_default)))
        self._save()

    def stage_done(self, stage: str) -> bool:
        """True when ``stage`` was recorded as done and all its files exist."""
        info = self._state.get("stages", {}).get(stage)
        if not info or info.get("status") != "done":
            return False
        return all((self.path / f).exists() for f in info.get("files", []))

    def stage_info(self, stage: str) -> dict:
        return dict(self._state.get("stages", {}).get(stage, {}))

    def record_stage(self, stage: str, *, files=(), seconds: float = 0.0, **info) -> None:
        """Mark ``stage`` done with its output files, wall time and extra facts."""
        entry = {"status": "done", "files": [str(f) for f in files], "seconds": round(float(seconds), 3)}
        entry.update(json.loads(json.dumps(info, default=_json_default)))
        self._state.setdefault("stages", {})[stage] = entry
        self._save()

    # -- writers -------------------------------------------------------------------
    def file(self, name: str) -> Path:
        return self.path / name

    def write_image(self, name: str, array: np.ndarray, header: fits.Header | None = None) -> str:
        with atomic_path(self.file(name)) as tmp:
            fits.PrimaryHDU(data=array, header=header).writeto(tmp)
        return name

    def write_table(self, name: str, table) -> str:
        with atomic_path(self.file(name)) as tmp:
            table.write(tmp, format="fits")
        return name

    def write_json(self, name: str, obj) -> str:
        with atomic_path(self.file(name)) as tmp:
            tmp.write_text(json.dumps(obj, indent=2, default=_json_default) + "\n")
        return name
