"""What a run shows while it works: log lines above the progress bars, the demo tile's progress, the fits."""

import io
import time

import numpy as np
from tqdm.auto import tqdm

import comest_bayes.pipeline.progress as P
from comest_bayes.cli import _write_line, main
from comest_bayes.sim.demo import make_demo_tile


def _last_line_drawn(text: str, line: str) -> str:
    """What a terminal shows on the row where ``line`` was written: the text after the row's last ``\\r``."""
    row = next(r for r in text.split("\n") if line in r)
    return row.split("\r")[-1]


def test_log_lines_go_above_an_active_progress_bar():
    line = "inject: 8 realizations in 13.7 s"
    screen = io.StringIO()
    with tqdm(total=8, desc="realizations", file=screen, ncols=80, mininterval=0, disable=False) as bar:
        bar.update(3)
        _write_line(line, screen)
        bar.update(1)
    # the bar is cleared first, so the row holds the line alone, and the bar is drawn again below it
    assert _last_line_drawn(screen.getvalue(), line) == line
    assert "4/8" in screen.getvalue().split(line)[1]
    # the control: a plain print lands after the bar's text on the same row (the "6.02s/task]f")
    screen = io.StringIO()
    with tqdm(total=8, desc="realizations", file=screen, ncols=80, mininterval=0, disable=False) as bar:
        bar.update(3)
        print(line, file=screen)
    assert _last_line_drawn(screen.getvalue(), line) != line
    # without a bar it is an ordinary line
    screen = io.StringIO()
    _write_line(line, screen)
    assert screen.getvalue() == line + "\n"


def test_demo_tile_synthesis_reports_its_progress():
    calls = []
    tile = make_demo_tile(seed=1, size=256, progress=lambda done, total: calls.append((done, total)))
    n = len(tile.truth)
    assert calls[0] == (0, n) and calls[-1] == (n, n)
    done = [c[0] for c in calls]
    assert done == sorted(done) and all(c[1] == n for c in calls)
    assert len(calls) <= 202  # about 200 updates, however many sources
    np.testing.assert_array_equal(tile.image, make_demo_tile(seed=1, size=256).image)  # progress changes nothing


def _task(kind, quantity="completeness"):
    return {"kind": kind, "quantity": quantity}


def test_fit_progress_names_each_fit_as_it_starts_and_those_still_running(monkeypatch):
    monkeypatch.setattr(P, "HEARTBEAT_SECONDS", 0.05)
    lines = []
    tasks = [_task("point"), _task("point", "purity"), _task("buldisk")]
    progress = P.FitProgress(tasks, lines.append, describe=lambda t: f"fitting {t['kind']}", workers=2)
    progress.start()
    try:
        # two workers: the first two fits start at once, the third when one of them ends
        assert lines == ["fit: point completeness: started: fitting point", "fit: point purity: started: fitting point"]
        deadline = time.monotonic() + 5.0
        while not any(s.startswith("fit: still running:") for s in lines) and time.monotonic() < deadline:
            time.sleep(0.01)
        beat = next(s for s in lines if s.startswith("fit: still running:"))
        assert beat.startswith("fit: still running: point completeness (") and "point purity (" in beat
        progress.finished(tasks[1])
        assert "fit: buldisk completeness: started: fitting buldisk" in lines
    finally:
        progress.stop()
    n = len(lines)
    time.sleep(0.2)
    assert len(lines) == n  # stopped: no more lines
    # where the scheduler decides the order (Dask) only the number still running is known
    lines.clear()
    progress = P.FitProgress(tasks, lines.append, describe=str, workers=2, known_order=False)
    progress.start()
    try:
        deadline = time.monotonic() + 5.0
        while not lines and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        progress.stop()
    assert lines and lines[0].startswith("fit: 3 fits still running (")


def test_quiet_demo_prints_nothing(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path / "demo"), "--size", "256", "--nsims", "1", "--kinds", "point",
                 "--model", "logistic", "--set", "fit.purity_model=none", "--no-report", "--executor", "serial",
                 "--quiet"]) == 0
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err == ""
    assert (tmp_path / "demo" / "summary.json").is_file()


def test_a_realizations_warnings_come_back_to_the_main_process_once_each(monkeypatch):
    import warnings

    import comest_bayes.recover.realization as recovery

    def noisy(task):
        for n in (49, 49, 52):
            warnings.warn(f"only {n} of 132 injections fit", UserWarning)
        return ("result of", task)

    monkeypatch.setattr(recovery, "run_realization", noisy)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # nothing escapes to the worker's stderr
        result, caught = P.realization_with_warnings("task 3")
    assert result == ("result of", "task 3")
    assert caught == ["only 49 of 132 injections fit", "only 52 of 132 injections fit"]


def test_fit_progress_gives_a_group_one_worker_and_names_its_later_fits_as_following():
    lines = []
    a, b, c, d = _task("point"), _task("buldisk"), _task("point", "purity"), _task("galaxy")
    progress = P.FitProgress([a, b, c, d], lines.append, describe=lambda t: "x", workers=2, groups=[[a, b], [c], [d]])
    progress.start()
    try:
        # two workers: the group of two and the next group start; the third group waits for a worker
        assert lines == ["fit: point completeness: started: x",
                         "fit: buldisk completeness: next in the same worker, after point completeness: x",
                         "fit: point purity: started: x"]
        progress.finished(a)  # the group still runs: no new start
        assert len(lines) == 3
        progress.finished(b)
        assert lines[-1] == "fit: galaxy completeness: started: x"
    finally:
        progress.stop()
