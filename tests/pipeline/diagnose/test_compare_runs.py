"""pipeline.diagnose.compare_runs: where two runs put people differently, on hand-made
tracks whose differences are known (a displaced span, a renumbered track, a person only
one run has), and the config fields that differ."""

from __future__ import annotations

import math

import numpy as np

from pipeline.config import PipelineConfig
from pipeline.diagnose.compare_runs import (
    Difference,
    config_changes,
    differences,
    match_frames,
    view_command,
)


def _tracks(K=3, F=60, J=4, seed=0):
    """(K, F, J, 3) people 1.5 m apart walking along x, mm."""
    rng = np.random.default_rng(seed)
    t = np.arange(F)[None, :, None]
    x = 1500.0 * np.arange(K)[:, None, None] + 10.0 * t + 50 * np.arange(J)[None, None]
    pts = np.stack([x, np.full_like(x, 200.0), np.full_like(x, 1000.0)], -1)
    return pts + rng.normal(0, 1, pts.shape)


def test_a_displaced_span_is_found_with_its_peak():
    a = _tracks()
    b = a.copy()
    b[1, 40:51] += np.array([0.0, 60.0, 0.0])  # 60 mm
    b[1, 45] += np.array([0.0, 40.0, 0.0])  # 100 mm at frame 45
    diffs, m = differences(a, b, min_mm=20)
    assert len(diffs) == 1
    d = diffs[0]
    assert (d.kind, d.track_a, d.track_b, d.start, d.stop, d.peak_frame) == (
        "moved", 1, 1, 40, 50, 45
    )  # fmt: skip
    assert abs(d.peak_mm - 100) < 2 and abs(d.mean_mm - (60 * 10 + 100) / 11) < 2
    assert np.nanmax(m.distance[:, [0, 2]]) < 5  # the others agree (noise ~1.6 mm)


def test_renumbered_tracks_still_match_and_nearby_spans_merge():
    a = _tracks()
    b = a[[2, 0, 1]].copy()  # B numbers the same people differently
    b[0, 10:13] += 30.0  # A's track 2, 52 mm
    b[0, 15:17] += 30.0  # 2 frames later: the same span
    b[0, 30] += 30.0  # far: its own span
    diffs, _ = differences(a, b, min_mm=20)
    assert [(d.track_a, d.track_b, d.start, d.stop) for d in diffs] == [
        (2, 0, 10, 16), (2, 0, 30, 30)
    ]  # fmt: skip


def test_a_person_only_one_run_has():
    a = _tracks()
    b = a.copy()
    b[2, 20:35] = np.nan  # B loses A's track 2 for 15 frames
    extra = np.full((1,) + a.shape[1:], np.nan)
    extra[0, 5:9] = a[0, 5:9] + 5000.0  # a ghost only B has
    b = np.concatenate([b, extra])
    diffs, m = differences(a, b, min_mm=20)
    kinds = [(d.kind, d.track_a, d.track_b, d.start, d.stop) for d in diffs]
    assert kinds == [("only in A", 2, -1, 20, 34), ("only in B", -1, 3, 5, 8)]
    assert math.isnan(diffs[0].peak_mm)
    assert m.b_unmatched[5:9, 3].all() and not m.b_unmatched[:, :3].any()


def test_unmeasured_frames_are_counted():
    a = _tracks()
    b = a.copy()
    b[0, 20:30] += 50.0
    measured = np.ones(a.shape[:2], bool)
    measured[0, 22:25] = False  # A's filter coasted 3 frames there
    d = differences(a, b, measured_a=measured)[0][0]
    assert (d.start, d.stop, d.unmeasured_a, d.unmeasured_b) == (20, 29, 3, 0)


def test_empty_runs():
    a = np.full((0, 10, 4, 3), np.nan)
    diffs, m = differences(a, _tracks(K=1, F=10))
    assert [(d.kind, d.start, d.stop) for d in diffs] == [("only in B", 0, 9)]
    assert match_frames(a, a).distance.shape == (10, 0)


def test_config_changes_and_view_command():
    a = PipelineConfig()
    b = a.with_overrides(["kalman.q=5000", "disabled_views=cam1", "sync.offsets=cam2:1.5"])
    assert config_changes(a, b) == [
        ("disabled_views", (), ("cam1",)), ("kalman.q", 100.0, 5000.0),
        ("sync.offsets", {}, {"cam2": 1.5}),
    ]  # fmt: skip
    d = Difference("moved", 3, 1, 10, 20, 15, 80.0, 40.0)
    assert view_command("my scene", d, config_args=["--set", "kalman.q=5"]) == (
        "mvviz view 'my scene' --set kalman.q=5 --frame 15 --track 3"
    )
