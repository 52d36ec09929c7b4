"""Executors: worker processes end with the process that started them."""

import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from comest_bayes.pipeline.executors import run_tasks

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads process states from /proc")


def _running(pid: int) -> bool:
    """True while ``pid`` exists and is not a zombie (a finished process its parent has not reaped)."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().rsplit(")", 1)[-1].split()[0] != "Z"
    except OSError:
        return False


def test_workers_exit_when_only_the_main_process_is_killed(tmp_path):
    marks = tmp_path / "pids"
    marks.mkdir()
    (tmp_path / "slow_task.py").write_text(textwrap.dedent('''
        import os, time

        def task(folder):
            open(os.path.join(folder, str(os.getpid())), "w").close()
            time.sleep(300)
    '''))
    main = textwrap.dedent(f'''
        import slow_task
        from comest_bayes.pipeline.executors import run_tasks
        run_tasks(slow_task.task, [{str(marks)!r}] * 2, on_result=lambda t, r: None, executor="processes", workers=2)
    ''')
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")]))
    proc = subprocess.Popen([sys.executable, "-c", main], env=env, stderr=subprocess.DEVNULL)
    workers = []
    try:
        deadline = time.monotonic() + 60
        while len(workers) < 2:
            assert time.monotonic() < deadline, "the two workers did not start within 60 s"
            assert proc.poll() is None, "the main process ended early"
            time.sleep(0.1)
            workers = [int(p.name) for p in marks.iterdir()]
        assert all(_running(pid) for pid in workers)
        proc.send_signal(signal.SIGKILL)  # only the main process, as an out-of-memory kill would
        proc.wait()
        deadline = time.monotonic() + 15  # the watchdog looks every second
        while any(_running(pid) for pid in workers) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not [pid for pid in workers if _running(pid)], "workers outlived the main process"
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        for pid in workers:
            if _running(pid):
                os.kill(pid, signal.SIGKILL)


def test_results_arrive_for_every_task_with_worker_processes():
    got = {}
    run_tasks(abs, [-1, -2, -3], on_result=lambda task, result: got.__setitem__(task, result), executor="processes",
              workers=2)
    assert got == {-1: 1, -2: 2, -3: 3}


def _cores_of_this_process(delay):
    time.sleep(delay)  # long enough that both workers take a task
    return os.getpid(), sorted(os.sched_getaffinity(0))


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="needs two cores to tell pinning from the default")
def test_each_worker_runs_on_a_core_of_its_own_and_one_worker_keeps_the_main_process_on_one():
    before = os.sched_getaffinity(0)
    seen = {}
    run_tasks(_cores_of_this_process, [0.5] * 4, on_result=lambda t, r: seen.__setitem__(r[0], r[1]),
              executor="processes", workers=2)
    assert len(seen) == 2  # two workers
    cores = list(seen.values())
    assert all(len(c) == 1 for c in cores) and cores[0] != cores[1]
    # --ncpu 1: the tasks run in this process, on one core, and its cores are given back afterwards
    inside = []
    run_tasks(_cores_of_this_process, [0.0], on_result=lambda t, r: inside.append(r[1]), executor="processes",
              workers=1)
    assert len(inside[0]) == 1
    assert os.sched_getaffinity(0) == before


def _pid_after(seconds):
    time.sleep(seconds)
    return os.getpid()


def test_a_runner_keeps_its_workers_across_batches():
    # One pool for every batch of a run (injection, adaptive batches, fits): the second batch runs in the
    # same worker processes as the first, none of them this process; a closed runner has no workers left.
    from comest_bayes.pipeline.executors import TaskRunner

    seen = []
    with TaskRunner("processes", 2) as runner:
        for _ in range(2):
            batch = []
            runner.run(_pid_after, [0.3, 0.3], on_result=lambda t, pid: batch.append(pid))
            seen.append(set(batch))
        workers = set(runner._pool._processes)
    assert os.getpid() not in seen[0] | seen[1]
    assert seen[1] <= seen[0] | workers and seen[0] <= workers
    deadline = time.monotonic() + 10
    while any(_running(pid) for pid in workers) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(_running(pid) for pid in workers)


def test_ctrl_c_stops_a_busy_worker_and_leaves_an_idle_one_to_the_next_batch():
    # Found by a new user: a Ctrl-C between adaptive batches made the idle workers print tracebacks from the
    # queue they wait on.  An idle worker now ignores it; a worker running a task stops it, as before, and the
    # interrupt reaches the main process through the task's result.
    import threading

    from comest_bayes.pipeline.executors import TaskRunner

    with TaskRunner("processes", 2) as runner:
        first = []
        runner.run(_pid_after, [0.2, 0.2], on_result=lambda t, pid: first.append(pid))
        workers = set(runner._pool._processes)
        for pid in workers:  # both idle now
            os.kill(pid, signal.SIGINT)
        time.sleep(0.5)
        assert all(_running(pid) for pid in workers)
        second = []
        runner.run(_pid_after, [0.2, 0.2], on_result=lambda t, pid: second.append(pid))
        assert set(second) <= workers and len(second) == 2

        def interrupt_the_busy_ones():
            time.sleep(1.0)
            for pid in workers:
                os.kill(pid, signal.SIGINT)

        threading.Thread(target=interrupt_the_busy_ones, daemon=True).start()
        t0 = time.monotonic()
        with pytest.raises(KeyboardInterrupt):
            runner.run(_pid_after, [30.0, 30.0], on_result=lambda t, pid: None)
        assert time.monotonic() - t0 < 15  # the 30-s tasks stopped at the interrupt


def test_serial_runner_runs_here_in_order():
    from comest_bayes.pipeline.executors import TaskRunner

    out = []
    with TaskRunner("serial") as runner:
        runner.run(_pid_after, [0.0, 0.0, 0.0], on_result=lambda t, pid: out.append(pid))
    assert out == [os.getpid()] * 3
