"""``mvviz compare`` through the command line, on a copy of the shipped Shelf scene:
A = the defaults, B = a Kalman q 1000 times larger, or a camera disabled. The figures
that must differ differ, those that must not do not, and the differences listed are
where the change acts; a second compare reuses the cached runs."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from mvviz.cli import main
from pipeline.core.files import CACHE_DIR
from pipeline.results.store import load_results
from tests.pipeline.helpers import REPO

SHELF = REPO / "sample_data" / "shelf_synth"
FAST = ["--set", "fit_smpl=false"]


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("compare") / "shelf"
    shutil.copytree(SHELF, root, ignore=shutil.ignore_patterns(CACHE_DIR, "videos"))
    return root


def _compare(scene, tmp_path, capsys, *args):
    out = tmp_path / "ab.json"
    assert main(["compare", str(scene), *FAST, "--json", str(out), *args]) == 0
    return json.loads(out.read_text()), capsys.readouterr().out


@pytest.mark.slow
def test_a_larger_kalman_q_changes_the_filter_only(scene, tmp_path, capsys):
    ab, text = _compare(scene, tmp_path, capsys, "--b-set", "kalman.q=100000", "--top", "3")
    fig = ab["figures"]
    assert ab["config_changes"] == [{"field": "kalman.q", "a": 100.0, "b": 100000.0}]
    # Triangulation and association do not see q: identical figures.
    for name in ("raw MPJPE mm", "association recall", "tracks", "reprojection 0 px"):
        assert fig[name]["a"] == fig[name]["b"], name
    # The filter follows the noisy raw joints: its MPJPE and acceleration error rise
    # (measured: kalman 11.5 -> 12.7 mm, rts 7.4 -> 11.6 mm, rts accel 4.2 -> 23.2 mm).
    assert fig["kalman MPJPE mm"]["b"] > fig["kalman MPJPE mm"]["a"] + 0.5
    assert fig["rts accel error mm"]["b"] > 3 * fig["rts accel error mm"]["a"]
    assert abs(fig["kalman MPJPE mm"]["b"] - fig["raw MPJPE mm"]["b"]) < 0.5
    moved = [d for d in ab["differences"] if d["kind"] == "moved"]
    assert len(moved) == 3 and moved[0]["peak_mm"] >= moved[1]["peak_mm"] >= 20
    # Each listed distance is the one between the two runs' filtered joints there.
    runs = sorted((scene / CACHE_DIR / "runs").glob("results_*.npz"))
    res = {r.config.kalman.q: r for r in map(load_results, runs)}
    a, b = res[100.0].track_filtered, res[100000.0].track_filtered
    for d in moved:
        f = d["peak_frame"]
        dist = np.nanmean(np.linalg.norm(a[d["track_a"], f] - b[d["track_b"], f], axis=-1))
        assert abs(dist - d["peak_mm"]) < 0.1
        assert f"--frame {f} --track {d['track_a']}" in text
    # The largest is where the filter coasts through a gap in the measurements.
    assert moved[0]["unmeasured_a"] > 0
    assert "run A: computed" in text and "run B: computed" in text
    # Run again: both runs come from the cache.
    _, again = _compare(scene, tmp_path, capsys, "--b-set", "kalman.q=100000")
    assert "run A: reused cached" in again and "run B: reused cached" in again


@pytest.mark.slow
def test_a_disabled_camera_shows_where_it_was_used(scene, tmp_path, capsys):
    # without camera 0 the filtered tracks move at most ~13 mm (measured 10.3-12.8 where
    # they move most), under the default threshold of 20 mm: 10 mm lists those spans
    ab, text = _compare(scene, tmp_path, capsys, "--b-set", "disabled_views=0", "--min-mm", "10")
    fig = ab["figures"]
    assert fig["reprojection 0 px"]["a"] > 0 and fig["reprojection 0 px"]["b"] is None
    # Camera 0's detections go unassigned: a third of the true pairs are missed
    # (measured recall 1.0 -> 0.664) and the raw joints are worse (12.7 -> 13.5 mm).
    assert fig["association recall"]["b"] < fig["association recall"]["a"] - 0.2
    assert fig["raw MPJPE mm"]["b"] > fig["raw MPJPE mm"]["a"]
    runs = {tuple(r.config.disabled_views): r for r in map(
        load_results, (scene / CACHE_DIR / "runs").glob("results_*.npz"))}  # fmt: skip
    a = runs[()]
    moved = [d for d in ab["differences"] if d["kind"] == "moved"]
    assert moved
    for d in moved:  # A used camera 0 for that person at that frame
        f, k = d["peak_frame"], d["track_a"]
        q = np.flatnonzero((a.person_frame == f) & (a.person_track == k))
        assert len(q) == 1 and a.person_used[q[0], :, 0].any(), d


def test_bad_arguments_are_one_line_errors(scene, capsys):
    cases = [
        (["--b-set", "sync.offsets=9:1"], "unknown ['9']"),
        (["--a-set", "kalman.q=fast"], "--a-set"),
        (["--b-set", "sync.offsets=0=1"], "CAMERA:FRAMES"),
        (["--top", "0"], "--top"),
        (["--a", str(scene / "nope.json")], "config file not found"),
    ]
    for args, needle in cases:
        assert main(["compare", str(scene), *FAST, *args]) == 2, args
        err = capsys.readouterr().err
        assert needle in err and len(err.strip().splitlines()) == 1, (args, err)


def test_view_opens_at_the_frame_and_track_compare_prints():
    from argparse import Namespace

    from mvviz.cli.view import _open_at
    from pipeline.core.files import SceneFormatError

    calls = []

    class App:
        def jump_to(self, **kw):
            calls.append(kw)

    _open_at(App(), Namespace(frame=144, track=2), 250, 4)
    _open_at(App(), Namespace(frame=None, track=None), 250, 4)
    assert calls == [{"frame": 144, "track": 2}]
    for frame, track, needle in ((250, None, "--frame"), (3, 4, "--track")):
        with pytest.raises(SceneFormatError, match=needle):
            _open_at(App(), Namespace(frame=frame, track=track), 250, 4)
