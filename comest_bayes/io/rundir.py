"""The run directory: where every output of a run lives, written atomically.

:class:`RunDirectory` checks that ``--out`` is writable, takes the ``run.lock``, records the
run's fingerprint and finished stages in ``run.json`` (resuming a run of the same fingerprint,
refusing any other) and writes every file atomically.  The rules: ``docs/usage.md`` ("The run
directory").
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import hashlib
import json
import os
import platform
import shutil
import socket
import uuid
from pathlib import Path

import numpy as np
from astropy.io import fits

from comest_bayes.errors import OutputWriteError, RunDirectoryError
from comest_bayes.io.jsonio import dumps
from comest_bayes.io import layout

__all__ = ["RunDirectory", "atomic_path", "file_checksum", "versions", "check_writable", "os_reason",
           "lock_holder"]

#: Subfolders a run directory may hold besides its own files (the demo's synthetic inputs).
ALLOWED_FOREIGN = {layout.INPUTS_DIR}
#: Prefix of every temporary name a run writes; what a killed run leaves is removed on resume.
TMP_PREFIX = ".tmp-"


def os_reason(exc: BaseException) -> str:
    """The operating system's reason for a failed file operation, in one line.

    ``strerror`` of the errno when there is one ("No space left on device");
    otherwise the first sentence of the message (astropy reports a full disk
    as ``OSError("Not enough space on disk: requested ...")`` without an errno).
    """
    errno_ = getattr(exc, "errno", None)
    if errno_:
        return os.strerror(errno_)
    text = " ".join(str(exc).split()) or type(exc).__name__
    first = text.split(". ")[0].rstrip(".")
    return first[:200]


@contextlib.contextmanager
def atomic_path(final: Path):
    """Yield a temporary path next to ``final``; move it into place on success.

    Raises
    ------
    OutputWriteError
        When the operating system refuses the write or the move (disk full,
        read-only file system, quota): one message naming ``final`` and the
        reason, instead of the writer's own (astropy's runs to dozens of lines).
    """
    final = Path(final)
    tmp = final.with_name(f"{TMP_PREFIX}{os.getpid()}-{final.name}")
    try:
        yield tmp
        os.replace(tmp, final)
    except OutputWriteError:
        raise
    except OSError as exc:
        raise OutputWriteError(f"could not write {str(final)!r}: {os_reason(exc)}. Free some space or choose "
                               f"another --out, then rerun the same command to resume.") from None
    finally:
        with contextlib.suppress(OSError):
            if tmp.exists():
                tmp.unlink()


def _nearest_existing(path: Path) -> Path:
    p = path
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def check_writable(path, what: str = "--out") -> None:
    """Raise :class:`RunDirectoryError` unless files can be created in ``path`` (or where it would be made).

    A probe directory is created and removed in ``path`` when it exists, else
    in its nearest existing ancestor; nothing is left behind.
    """
    path = Path(path).absolute()
    where = _nearest_existing(path)
    if not where.is_dir():
        raise RunDirectoryError(f"{what} {str(path)!r} cannot be created: {str(where)!r} is a file, not a folder; "
                                f"choose another {what}.")
    probe = where / f"{TMP_PREFIX}probe-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    try:
        os.mkdir(probe)
    except OSError as exc:
        place = "" if where == path else f" (its nearest existing folder {str(where)!r} refuses new entries)"
        raise RunDirectoryError(f"{what} {str(path)!r} is not writable{place}: {os_reason(exc)}. Nothing was "
                                f"written; choose a writable {what}.") from None
    with contextlib.suppress(OSError):
        os.rmdir(probe)


def _process_start(pid: int) -> str | None:
    """Start time of a process (clock ticks since boot, Linux ``/proc``), or None where unknown."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            text = fh.read()
    except OSError:
        return None
    fields = text.rsplit(")", 1)[-1].split()
    return fields[19] if len(fields) > 19 else None


def _process_alive(pid: int, start: str | None) -> bool:
    """True when process ``pid`` runs (and, where known, is the one that started at ``start``)."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    except OSError:
        return False
    try:
        with open(f"/proc/{pid}/stat") as fh:
            if fh.read().rsplit(")", 1)[-1].split()[0] == "Z":  # a zombie has finished
                return False
    except (OSError, IndexError):
        pass
    now = _process_start(pid)
    return start is None or now is None or now == start


def lock_holder(run_dir) -> dict | None:
    """The live holder of ``run_dir``'s lock (``pid``, ``host``, ``started``), or None when free or stale.

    A lock written on another host cannot be checked and counts as live.
    """
    holder = _read_lock(Path(run_dir) / layout.LOCK)
    if holder is None:
        return None
    if holder.get("host") != socket.gethostname():
        return holder
    return holder if _process_alive(int(holder.get("pid", -1)), holder.get("proc_start")) else None


def _read_lock(path: Path) -> dict | None:
    """The lock's content; an unreadable lock reads as a dead holder (pid -1)."""
    try:
        text = path.read_text()
    except FileNotFoundError:
        return None
    except OSError:
        return {"pid": -1, "host": socket.gethostname()}
    try:
        holder = json.loads(text)
        int(holder["pid"])
        return holder
    except (ValueError, KeyError, TypeError):
        return {"pid": -1, "host": socket.gethostname()}


def _describe_holder(holder: dict) -> str:
    return (f"process {holder.get('pid')} on {holder.get('host')}"
            + (f", started {holder['started']}" if holder.get("started") else ""))


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
        self.fingerprint = json.loads(dumps(fingerprint))
        self.resumed = False
        self._state: dict = {}
        self._locked = False
        #: Set by :meth:`open` when it took over the lock of a process that no longer runs.
        self.lock_note: str | None = None

    # -- opening -----------------------------------------------------------------
    def check(self) -> None:
        """Decide between new run, resume and refusal without writing anything.

        Refuses a directory in use by a live process, a directory holding
        another run or foreign files, and a location that cannot be written.
        """
        p = self.path
        if p.exists() and not p.is_dir():
            raise RunDirectoryError(f"--out {str(p)!r} is an existing file, not a directory; choose another --out.")
        self.refuse_if_in_use()
        run_file = p / layout.RUN
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
                       if c.name not in ALLOWED_FOREIGN | {layout.LOCK} and not c.name.startswith(TMP_PREFIX)]
            if foreign:
                raise RunDirectoryError(
                    f"--out {str(p)!r} is not empty and is not a comest-bayes run (found {sorted(foreign)[:5]}); "
                    f"choose an empty or new directory so nothing in it is overwritten."
                )
        check_writable(p)

    def refuse_if_in_use(self) -> None:
        """Raise :class:`RunDirectoryError` naming the holder when another live process holds the lock."""
        holder = lock_holder(self.path)
        if holder is not None and not self._held_by_me(holder):
            raise RunDirectoryError(
                f"--out {str(self.path)!r} is in use by another comest-bayes run ({_describe_holder(holder)}). "
                f"Wait for it to finish or stop it, then rerun the same command to resume; if that process is "
                f"gone (e.g. on another host), remove {str(self.path / layout.LOCK)!r}.")

    @staticmethod
    def _held_by_me(holder: dict) -> bool:
        """This process holds the lock (reentrant: a Python session may open the same run again)."""
        return holder.get("pid") == os.getpid() and holder.get("host") == socket.gethostname()

    def acquire(self) -> "RunDirectory":
        """Create the directory and take ``run.lock`` (done by :meth:`open`; reentrant in one process).

        The lock appears atomically with its content (a hard link of a
        complete file); a stale lock is taken over.
        """
        try:
            self.path.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise RunDirectoryError(f"cannot create --out {str(self.path)!r}: {os_reason(exc)}.") from None
        self._acquire()
        return self

    def _acquire(self) -> None:
        lock = self.path / layout.LOCK
        me = {"pid": os.getpid(), "host": socket.gethostname(), "proc_start": _process_start(os.getpid()),
              "started": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")}
        tmp = self.path / f"{TMP_PREFIX}lock-{os.getpid()}-{uuid.uuid4().hex[:8]}"
        try:
            tmp.write_text(dumps(me) + "\n")
        except OSError as exc:
            raise OutputWriteError(f"could not write {str(lock)!r}: {os_reason(exc)}.") from None
        try:
            for _ in range(5):
                try:
                    os.link(tmp, lock)
                    self._locked = True
                    return
                except FileExistsError:
                    pass
                except OSError:  # no hard links on this file system: exclusive create instead
                    try:
                        fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
                    except FileExistsError:
                        pass
                    else:
                        with os.fdopen(fd, "w") as fh:
                            fh.write(dumps(me) + "\n")
                        self._locked = True
                        return
                holder = _read_lock(lock)
                if holder is None:
                    continue  # released in the meantime
                if self._held_by_me(holder):
                    self._locked = True
                    return
                if lock_holder(self.path) is not None:
                    self.refuse_if_in_use()
                # stale: move it aside atomically; of two processes taking it over, one rename wins
                aside = self.path / f"{TMP_PREFIX}stale-lock-{os.getpid()}"
                try:
                    os.rename(lock, aside)
                except FileNotFoundError:
                    continue
                if _read_lock(aside) != holder:  # another process took it over first: give its lock back
                    with contextlib.suppress(OSError):
                        os.link(aside, lock)
                    with contextlib.suppress(OSError):
                        aside.unlink()
                    continue
                with contextlib.suppress(OSError):
                    aside.unlink()
                self.lock_note = (f"took over the lock of {_describe_holder(holder)}, which is no longer running "
                                  f"(an interrupted run)")
            raise RunDirectoryError(f"could not take the lock {str(lock)!r}: other processes keep taking it.")
        finally:
            with contextlib.suppress(OSError):
                tmp.unlink()

    def release(self) -> None:
        """Remove ``run.lock`` if this process holds it (safe to call more than once)."""
        if not self._locked:
            return
        self._locked = False
        lock = self.path / layout.LOCK
        holder = _read_lock(lock)
        if holder is not None and holder.get("pid") == os.getpid() and holder.get("host") == socket.gethostname():
            with contextlib.suppress(OSError):
                lock.unlink()

    def open(self) -> "RunDirectory":
        """Create or resume the directory (after :meth:`check`), take its lock and clear leftovers.

        Every ``.tmp-*`` file or folder a killed run left, at any depth, is
        removed (the lock guarantees no live run is writing them).  Call
        :meth:`release` when done.
        """
        self.check()
        self.acquire()
        try:
            self._remove_leftovers()
            if not self.resumed:
                self._state = {
                    "fingerprint": self.fingerprint,
                    "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                    "versions": versions(),
                    "stages": {},
                }
                self._save()
        except BaseException:
            self.release()
            raise
        return self

    def _remove_leftovers(self) -> None:
        for stale in sorted(self.path.rglob(f"{TMP_PREFIX}*"), key=lambda q: len(q.parts), reverse=True):
            with contextlib.suppress(OSError):
                if stale.is_dir() and not stale.is_symlink():
                    shutil.rmtree(stale)
                else:
                    stale.unlink()

    # -- state ---------------------------------------------------------------------
    @property
    def state(self) -> dict:
        return self._state

    def _save(self) -> None:
        with atomic_path(self.path / layout.RUN) as tmp:
            tmp.write_text(dumps(self._state, indent=2) + "\n")

    def update(self, **items) -> None:
        """Set top-level entries of ``run.json`` (e.g. ``image=...``) and save."""
        self._state.update(json.loads(dumps(items)))
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
        entry.update(json.loads(dumps(info)))
        self._state.setdefault("stages", {})[stage] = entry
        self._save()

    # -- writers -------------------------------------------------------------------
    def file(self, name: str) -> Path:
        return self.path / name

    def write_image(self, name: str, array: np.ndarray, header: fits.Header | None = None) -> str:
        with atomic_path(self.file(name)) as tmp:
            fits.PrimaryHDU(data=array, header=header).writeto(tmp)
        return name

    def write_table(self, name: str, table, extname: str | None = None) -> str:
        """Write ``table`` as the binary-table HDU 1 of the FITS file ``name`` (after an empty primary HDU).

        The table HDU is named ``extname`` (default: the file name's stem in
        capitals, ``catalogs/point_matched.fits`` -> ``POINT_MATCHED``); column
        units are written as ``TUNITn`` and ``table.meta`` as header keywords,
        as :meth:`astropy.table.Table.write` does.
        """
        hdu = fits.table_to_hdu(table, character_as_bytes=True)
        hdu.name = (extname or Path(name).stem).upper()
        with atomic_path(self.file(name)) as tmp:
            fits.HDUList([fits.PrimaryHDU(), hdu]).writeto(tmp)
        return name

    def write_json(self, name: str, obj) -> str:
        with atomic_path(self.file(name)) as tmp:
            tmp.write_text(dumps(obj, indent=2) + "\n")
        return name
