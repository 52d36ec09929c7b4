"""What a run says while it works, besides its log lines: which fits run, and what the workers warned.

A completeness fit can take minutes, during which a progress bar of fits stands still:
:class:`FitProgress` says when each fit starts what it does (:func:`describe_fit`) and every
:data:`HEARTBEAT_SECONDS` which fits are still running.  Worker processes cannot write to the
terminal without cutting through the progress bars: :func:`realization_with_warnings` runs a
realization and hands its Python warnings back to the main process, which logs them.

Nothing here changes a result; the lines go through the run's ``log``.
"""

from __future__ import annotations

import threading
import time
import warnings
from comest_bayes.bayes.spec import load_spec, resolve_candidates
from comest_bayes.recover import realization

__all__ = ["FitProgress", "describe_fit", "realization_with_warnings", "HEARTBEAT_SECONDS"]


#: Seconds between the lines that say which fits are still running (a fit can take minutes).
HEARTBEAT_SECONDS = 60.0


def describe_fit(task: dict, counts_entry: dict, config) -> str:
    """What one fit does, in words: the model or the selection among models, the sampler, the data."""

    sampler = {"auto": "importance sampling (NUTS if that fails)", "importance": "importance sampling",
               "nuts": "NUTS", "emcee": "emcee"}.get(config.fit.sampler, config.fit.sampler)
    spec = load_spec(task["requested"])
    if spec.is_selection:
        names = [c.name for c in resolve_candidates(spec)]
        what = f"selecting among {', '.join(names)} (MAP + Laplace each), then {sampler} of the chosen one"
    else:
        what = f"{spec.name} (MAP + Laplace), then {sampler}"
    if task["quantity"] == "completeness":
        return f"{what}; {(counts_entry.get('counts') or {}).get('usable', 0)} injections"
    return f"{what}; matched against false detections in measured magnitude"


class FitProgress:
    """Says which fits start and, every :data:`HEARTBEAT_SECONDS`, which are still running.

    The executors start tasks in the order given as workers free up (``known_order``; a Dask
    scheduler decides its own order, so then only the number still running is known).  With
    ``groups`` (lists of tasks that one worker runs one after the other) a group takes one worker
    and its later fits are announced as following the first.  Lines go through ``log``, which
    keeps them above any progress bar.
    """

    def __init__(self, tasks: list, log, *, describe, workers: int, known_order: bool = True, groups=None):
        self._pending = [list(g) for g in groups] if groups is not None else [[t] for t in tasks]
        self._running: dict[int, tuple[list, float]] = {}  # id of a group -> (group, start)
        self._group_of: dict[int, list] = {}  # id of a task of a running group -> its group
        self._left: dict[int, int] = {}  # id of a running group -> its fits not yet finished
        self._log, self._describe = log, describe
        self._slots = max(1, int(workers)) if known_order else sum(len(g) for g in self._pending)
        self._known = known_order
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = None

    @staticmethod
    def _name(task: dict) -> str:
        return f"{task['kind']} {task['quantity']}"

    def _start_next(self) -> None:
        while self._pending and len(self._running) < self._slots:
            group = self._pending.pop(0)
            self._running[id(group)] = (group, time.monotonic())
            self._left[id(group)] = len(group)
            for i, task in enumerate(group):
                self._group_of[id(task)] = group
                if not self._known:
                    continue
                if i == 0:
                    self._log(f"fit: {self._name(task)}: started: {self._describe(task)}")
                else:
                    self._log(f"fit: {self._name(task)}: next in the same worker, after "
                              f"{self._name(group[i - 1])}: {self._describe(task)}")

    def start(self) -> None:
        if not self._pending:
            return
        with self._lock:
            self._start_next()
        self._thread = threading.Thread(target=self._beat, name="comest-bayes-fit-progress", daemon=True)
        self._thread.start()

    def finished(self, task: dict) -> None:
        with self._lock:
            group = self._group_of.pop(id(task), None)
            if group is not None:
                self._left[id(group)] -= 1
                if self._left[id(group)] <= 0:
                    self._running.pop(id(group), None)
                    self._left.pop(id(group), None)
            self._start_next()

    def _beat(self) -> None:
        while not self._stop.wait(HEARTBEAT_SECONDS):
            now = time.monotonic()
            with self._lock:
                running = list(self._running.values())
            if not running:
                continue
            if self._known:
                self._log("fit: still running: " + ", ".join(
                    f"{' then '.join(self._name(t) for t in g)} ({_duration(now - t0)})" for g, t0 in running))
            else:
                self._log(f"fit: {sum(len(g) for g, _ in running)} fits still running "
                          f"({_duration(now - running[0][1])})")

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)


def _duration(seconds: float) -> str:
    seconds = int(round(seconds))
    return f"{seconds // 60} min {seconds % 60:02d} s" if seconds >= 60 else f"{seconds} s"


def realization_with_warnings(task) -> tuple:
    """:func:`comest_bayes.recover.realization.run_realization` with the warnings it raised: ``(result, [text, ...])``.

    A module-level function, so that the executors can send it to worker processes.
    """

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = realization.run_realization(task)  # looked up at call time (tests replace it)
    return result, list(dict.fromkeys(" ".join(str(w.message).split()) for w in caught))
