"""Run independent tasks serially, in local processes, or on Dask.

Every task carries its own seed, so the results do not depend on the executor; results reach
``on_result`` in the main process as they arrive.  Workers are started with ``forkserver``,
pinned to a core each, and exit with the main process.  Details: ``docs/compute.md``.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import signal
import sys
import threading
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from typing import Any, Callable, Iterable, Sequence

from comest_bayes.errors import BackendUnavailableError, ConfigError
from comest_bayes.pipeline.runtime import one_core, pin_to_one_core

__all__ = ["run_tasks", "TaskRunner", "EXECUTORS", "default_workers"]

EXECUTORS = ("serial", "processes", "dask")


def default_workers() -> int:
    """Cores available to this process."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def _progress(total: int, desc: str, enabled: bool):
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=desc, unit="task", disable=not enabled or total == 0, leave=False)


#: How often (seconds) a worker checks that the main process still runs.
PARENT_POLL_SECONDS = 1.0
_PR_SET_PDEATHSIG = 1


def _alive(pid: int) -> bool:
    """True while process ``pid`` runs (a killed process not yet reaped by its parent counts as gone)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().rsplit(")", 1)[-1].split()[0] != "Z"
    except (OSError, IndexError):
        return True


def _worker_init(main_pid: int, counter) -> None:
    """Worker initializer: one core of its own (worker k on core k), exit with the main process, and a
    Ctrl-C that interrupts a running task but leaves an idle worker to the pool's shutdown."""
    with counter.get_lock():
        index = counter.value
        counter.value += 1
    pin_to_one_core(index)
    _die_with_parent(main_pid)
    signal.signal(signal.SIGINT, _on_interrupt)


#: True while this worker process runs a task (:func:`_tracked`).
_BUSY = [False]


def _on_interrupt(signum, frame) -> None:
    """SIGINT in a worker: a running task stops (as by default); an idle worker, waiting for the next task
    between batches, ignores it, so that it leaves with the pool's shutdown instead of printing a
    traceback from the queue it waits on."""
    if _BUSY[0]:
        raise KeyboardInterrupt


def _tracked(fn: Callable[[Any], Any], task):
    """``fn(task)`` in a worker, marked busy while it runs (see :func:`_on_interrupt`)."""
    _BUSY[0] = True
    try:
        return fn(task)
    finally:
        _BUSY[0] = False


def _die_with_parent(main_pid: int) -> None:
    """End this worker when the main process ``main_pid`` is gone."""
    if sys.platform.startswith("linux"):
        try:
            import ctypes

            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
        except (OSError, AttributeError):  # no prctl: the watchdog below still works
            pass
    parent = os.getppid()

    def watch():
        while True:
            time.sleep(PARENT_POLL_SECONDS)
            if not _alive(main_pid) or os.getppid() != parent:
                os._exit(1)  # nobody waits for this worker's results; no clean-up to run

    threading.Thread(target=watch, name="comest-bayes-parent-watch", daemon=True).start()
    if not _alive(main_pid):  # died before the watch began
        os._exit(1)


def _mp_context():
    methods = mp.get_all_start_methods()
    return mp.get_context("forkserver" if "forkserver" in methods else "spawn")


class TaskRunner:
    """Where tasks run, kept open across several batches of tasks.

    One pool of local worker processes (or one Dask client) serves every :meth:`run` until
    :meth:`close`: a run's injection, its adaptive batches and its fits share the workers instead of
    starting a pool (processes that import NumPy, GalSim, JAX anew) for each.  Use as a context
    manager.  The pool starts at the first :meth:`run` that needs it.

    Parameters
    ----------
    executor : {"serial", "processes", "dask"}
    workers : int
        Local worker processes (``processes`` and a local Dask cluster).
    scheduler : str, optional
        A Dask scheduler address (``dask`` only; default a local cluster of ``workers``).
    """

    def __init__(self, executor: str = "serial", workers: int = 1, scheduler: str | None = None):
        if executor not in EXECUTORS:
            raise ConfigError(f"unknown executor {executor!r}; use one of {EXECUTORS}.")
        self.executor, self.workers, self.scheduler = executor, int(workers), scheduler
        self._pool = None
        self._client = None
        self._cluster = None

    @property
    def serial(self) -> bool:
        """Tasks run in this process (``serial``, or ``processes`` with one worker)."""
        return self.executor == "serial" or (self.executor == "processes" and self.workers <= 1)

    def __enter__(self) -> "TaskRunner":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Stop the workers (cancelling tasks not yet started)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
        import logging

        # a local cluster stopped by an interrupt logs each worker it has to kill: not the user's concern
        quiet = logging.getLogger("distributed")
        level = quiet.level
        if self._cluster is not None:
            quiet.setLevel(logging.ERROR)
        try:
            if self._client is not None:
                self._client.close()
                self._client = None
            if self._cluster is not None:
                self._cluster.close()
                self._cluster = None
        finally:
            quiet.setLevel(level)

    def run(self, fn: Callable[[Any], Any], tasks: Sequence, *, on_result: Callable[[Any, Any], None],
            progress: bool = False, desc: str = "tasks") -> None:
        """Apply ``fn`` to every task and pass ``(task, result)`` to ``on_result`` (see :func:`run_tasks`)."""
        tasks = list(tasks)
        if not tasks:
            return
        with _progress(len(tasks), desc, progress) as bar:
            if self.serial:
                # one worker: the tasks run here, on one core (XLA would otherwise spread over every core)
                with one_core():
                    for task in tasks:
                        on_result(task, fn(task))
                        bar.update()
            elif self.executor == "processes":
                if self._pool is None:
                    ctx = _mp_context()
                    self._pool = ProcessPoolExecutor(max_workers=self.workers, mp_context=ctx,
                                                     initializer=_worker_init,
                                                     initargs=(os.getpid(), ctx.Value("i", 0)))
                futures = {self._pool.submit(_tracked, fn, task): task for task in tasks}
                try:
                    for fut in as_completed(list(futures)):
                        # pop: a finished future holds its result, so keeping it would grow the
                        # main process with the number of tasks
                        on_result(futures.pop(fut), fut.result())
                        bar.update()
                except BaseException:
                    for fut in futures:
                        fut.cancel()
                    raise
            else:
                _run_dask(fn, tasks, on_result, self._dask_client(), bar)

    def _dask_client(self):
        if self._client is None:
            try:
                from distributed import Client, LocalCluster
            except ImportError:
                raise BackendUnavailableError(
                    "the Dask executor needs dask.distributed: pip install 'comest-bayes[dask]' "
                    "(or pip install 'dask[distributed]')."
                ) from None
            if self.scheduler:
                self._client = Client(self.scheduler)
            else:
                self._cluster = LocalCluster(n_workers=max(1, self.workers), threads_per_worker=1, processes=True,
                                             dashboard_address=None)
                self._client = Client(self._cluster)
        return self._client


def run_tasks(fn: Callable[[Any], Any], tasks: Sequence, *, on_result: Callable[[Any, Any], None],
              executor: str = "serial", workers: int = 1, scheduler: str | None = None,
              progress: bool = False, desc: str = "tasks", runner: TaskRunner | None = None) -> None:
    """Apply ``fn`` to every task and pass ``(task, result)`` to ``on_result``.

    Parameters
    ----------
    fn : callable
        A module-level (picklable) function of one task.
    tasks : sequence
        Picklable task descriptions.
    on_result : callable
        Called in the main process, in completion order.
    executor : {"serial", "processes", "dask"}
        Where tasks run.  ``dask`` connects to ``scheduler`` (an address such
        as ``tcp://host:8786``) or starts a local cluster of ``workers``
        single-threaded worker processes.  Dask workers must see the same
        filesystem as the main process (the run directory's inputs).
    workers : int
        Local worker processes (``processes`` and a local Dask cluster).
    progress : bool
        Show a progress bar.
    runner : TaskRunner, optional
        An open :class:`TaskRunner` to run on (its workers are kept for the
        next call); ``executor``, ``workers`` and ``scheduler`` are then
        ignored.  Without one, a runner is opened for these tasks and closed.
    """
    if runner is not None:
        runner.run(fn, tasks, on_result=on_result, progress=progress, desc=desc)
        return
    if executor not in EXECUTORS:
        raise ConfigError(f"unknown executor {executor!r}; use one of {EXECUTORS}.")
    tasks = list(tasks)
    if not tasks:
        return
    with TaskRunner(executor, min(int(workers), len(tasks)) if executor == "processes" else workers,
                    scheduler) as one:
        one.run(fn, tasks, on_result=on_result, progress=progress, desc=desc)


def _run_dask(fn, tasks: Iterable, on_result, client, bar) -> None:
    from distributed import as_completed as dask_completed

    futures = client.map(fn, tasks, pure=False)
    index = {f.key: t for f, t in zip(futures, tasks)}
    completed = dask_completed(futures)
    del futures  # as_completed holds them until they finish; released one by one below
    for fut in completed:
        on_result(index.pop(fut.key), fut.result())
        fut.release()
        bar.update()
