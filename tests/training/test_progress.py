"""Progress of imitation and evaluation: a bar with the time left, or the same figures logged."""

from __future__ import annotations

import io

from training.progress import Progress


def test_the_bar_counts_and_estimates_the_time_left():
    out = io.StringIO()
    with Progress(10, "episodes", "episode", file=out) as progress:
        for _ in range(4):
            progress.update()
    shown = out.getvalue()  # closing draws the bar as it stands
    assert "episodes" in shown and "4/10" in shown and "<" in shown  # tqdm: elapsed<left
    assert "10/10" not in shown


def test_without_a_bar_the_estimate_is_logged_every_interval(caplog):
    now = [0.0]
    with caplog.at_level("INFO", logger="training.progress"):
        progress = Progress(100, "dagger steps", "step", bar=False, interval=30.0, clock=lambda: now[0])
        now[0] = 10.0
        progress.update(10)  # before the interval: nothing logged
        now[0] = 40.0
        progress.update(30)
    assert [r.getMessage() for r in caplog.records] == [
        "dagger steps: 40/100 (40%), 00:40 spent, about 01:00 left"]  # fmt: skip


def test_nothing_done_yet_has_no_estimate():
    progress = Progress(5, "episodes", "episode", bar=False, clock=lambda: 3.0)
    assert progress.line() == "episodes: 0/5 (0%), 00:00 spent, about unknown left"
