"""Progress reporting: callbacks hear every step; a log gets one line per stage."""

from __future__ import annotations

import io
import sys

from pipeline.core.progress import LatestProgress, StageBar, track


class _Log(io.StringIO):
    def isatty(self) -> bool:
        return False


def test_a_callback_hears_every_step():
    heard: list[tuple[str, int, int]] = []
    out = list(track(range(3), "stage", lambda *a: heard.append(a)))
    assert out == [0, 1, 2]
    assert heard == [("stage", 1, 3), ("stage", 2, 3), ("stage", 3, 3)]


def test_a_log_gets_one_line_per_stage(monkeypatch):
    log = _Log()
    monkeypatch.setattr(sys, "stderr", log)
    for _ in track(range(500), "associate+triangulate", True, unit="frame"):
        pass
    with StageBar("fit", 10, True, initial=4) as bar:
        bar.update(6)
    lines = log.getvalue().splitlines()
    assert "\r" not in log.getvalue() and len(lines) == 2
    assert lines[0].startswith("associate+triangulate: 500/500 frame in ")
    assert lines[1].startswith("fit: 10/10 it in ")


def test_silent_and_latest():
    log = _Log()
    latest = LatestProgress()
    with StageBar("empty", 0, latest) as bar:
        bar.update(0)
    assert latest.value is None  # a stage without steps is not reported
    for _ in track([1, 2], "two", latest):
        pass
    assert latest.value == ("two", 2, 2)
    for _ in track([1], "quiet", False):
        pass
    assert log.getvalue() == ""
