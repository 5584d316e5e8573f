"""pipeline.batch without Ray: frame chunks, the join, the summary, sweeps, stored keys."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest

from pipeline.batch.jobs import (
    _finite_mean,
    chunk_bounds,
    join_chunks,
    run_chunk,
    scene_inputs,
    stored_key,
    summarize,
    worst_moments,
)
from pipeline.batch.sweep import parse_sweep, setting_slug, sweep_grid
from pipeline.body.model import load_body_model
from pipeline.config import PipelineConfig
from pipeline.core.files import SceneFormatError
from pipeline.data.scene import load_scene
from pipeline.evaluation.evaluate import evaluate
from pipeline.importers.calibration import read_voxelpose_calibration
from pipeline.results.store import PipelineResults, save_results
from pipeline.run.pipeline import run_pipeline
from pipeline.synth.scene_gen import SynthConfig, write_synth_scene
from tests.conftest import CAMPUS_CALIB

NO_FIT = PipelineConfig().with_overrides(["fit_smpl=false"])


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """(scene, model): 2 people, 14 frames on the 3-camera campus rig, no videos."""
    root = tmp_path_factory.mktemp("batch") / "scene"
    model = load_body_model()
    cfg = SynthConfig(num_people=2, num_frames=14, seed=5, render_video=False)
    write_synth_scene(root, read_voxelpose_calibration(CAMPUS_CALIB), model, cfg, progress=False)
    return load_scene(root), model


def assert_same_results(a: PipelineResults, b: PipelineResults) -> None:
    """Every field equal, arrays bit for bit (NaN where NaN), fits included."""
    for f in dataclasses.fields(PipelineResults):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray):
            assert x.dtype == y.dtype and x.shape == y.shape, f.name
            assert np.array_equal(x, y, equal_nan=x.dtype.kind == "f"), f.name
        elif f.name in ("smpl", "smpl_vae"):
            assert (x is None) == (y is None), f.name
            if x is not None:
                for k, v in x.arrays("").items():
                    assert np.array_equal(v, y.arrays("")[k], equal_nan=True), f"{f.name}.{k}"
        else:
            assert x == y, f.name


def test_chunk_bounds_cover_every_frame_once():
    assert chunk_bounds(10, 4) == [(0, 3), (3, 7), (7, 10)]
    assert chunk_bounds(10, 0) == [(0, 10)]
    assert chunk_bounds(10, 100) == [(0, 10)]
    assert chunk_bounds(0, 5) == [(0, 0)]
    for n in range(1, 60):
        for size in (1, 2, 7, 25):
            b = chunk_bounds(n, size)
            assert b[0][0] == 0 and b[-1][1] == n
            assert all(p[1] == q[0] for p, q in zip(b[:-1], b[1:], strict=True))
            assert max(stop - start for start, stop in b) <= size
            assert len(b) == -(-n // size)


@pytest.mark.parametrize("chunk_frames", [1, 5, 14])
def test_chunked_run_equals_run_pipeline(tiny, chunk_frames):
    scene, model = tiny
    whole = run_pipeline(scene, NO_FIT, model, progress=False)
    inputs = scene_inputs(scene, NO_FIT, model)
    chunks = [
        run_chunk(scene, NO_FIT, inputs, a, b)
        for a, b in chunk_bounds(scene.num_frames, chunk_frames)
    ]
    joined = join_chunks(scene, NO_FIT, model, inputs, chunks[::-1][::-1], whole.cache_key)
    assert len(chunks) == -(-scene.num_frames // chunk_frames)
    assert_same_results(joined, whole)


def test_join_refuses_missing_frames(tiny):
    scene, model = tiny
    inputs = scene_inputs(scene, NO_FIT, model)
    first = run_chunk(scene, NO_FIT, inputs, 0, 5)
    with pytest.raises(ValueError, match="do not cover"):
        join_chunks(scene, NO_FIT, model, inputs, [first], "")


def test_summary_matches_the_evaluation(tiny):
    scene, model = tiny
    results = run_pipeline(scene, NO_FIT, model, progress=False)
    s = summarize(scene, results)
    ev = evaluate(scene, results)
    stage = "rts" if NO_FIT.kalman.smoother else "kalman"
    assert s["stage"] == stage and s["has_gt"]
    assert s["mpjpe_mm"] == pytest.approx(ev.stages[stage]["mpjpe"])
    assert 0 < s["mpjpe_mm"] < 100  # mm: a tiny synthetic scene is well reconstructed
    assert s["assoc_precision"] == pytest.approx(ev.association["precision"])
    assert s["id_switches"] == ev.association["id_switches"]
    assert list(s["reprojection_px"]) == scene.rig.names
    assert s["worst"] and s["worst"][0]["metric"] == "mpjpe_mm"
    values = [m["value"] for m in s["worst"]]
    assert values == sorted(values, reverse=True)
    frames = [m["frame"] for m in s["worst"]]
    assert all(abs(a - b) >= 10 for i, a in enumerate(frames) for b in frames[i + 1 :])
    # the worst frame's person is at least as far off as the scene's mean
    assert values[0] >= s["mpjpe_mm"]


def test_worst_moments_without_ground_truth_rank_reprojection(tiny):
    scene, model = tiny
    results = run_pipeline(scene, NO_FIT, model, progress=False)
    worst = worst_moments(dataclasses.replace(scene, gt=None), results, count=3)
    assert worst and all(m["metric"] == "reprojection_px" for m in worst)
    # recomputed by hand: per person-frame mean reprojection over the views it used
    err = np.array(
        [
            np.nanmean(np.where(u, r, np.nan))
            for u, r in zip(results.person_used, results.person_reproj, strict=True)
        ]
    )
    top = worst[0]
    rows = np.flatnonzero(results.person_frame == top["frame"])
    assert top["value"] == pytest.approx(np.nanmax(err[rows]))
    assert top["value"] == pytest.approx(np.nanmax(err))  # the first is the scene's worst
    assert top["track"] == results.person_track[rows[np.nanargmax(err[rows])]]


def test_finite_mean_skips_nan_rows_without_a_warning():
    x = np.array([[1.0, np.nan, 3.0], [np.nan, np.nan, np.nan], [np.inf, 4.0, 8.0]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # np.nanmean warned "Mean of empty slice" here
        got = _finite_mean(x)
    np.testing.assert_array_equal(got, [2.0, np.nan, 6.0])
    assert _finite_mean(np.zeros((0, 5))).shape == (0,)


def test_sweep_grid_is_the_product_in_order():
    grid = sweep_grid(["kalman.q=10,50,100", "association.max_distance_mm=80,120"])
    assert len(grid) == 6
    assert grid[0] == ("kalman.q=10", "association.max_distance_mm=80")
    assert grid[-1] == ("kalman.q=100", "association.max_distance_mm=120")
    assert sweep_grid([]) == [()]
    assert parse_sweep("kalman.q= 1 ,2") == ("kalman.q", ["1", "2"])
    assert setting_slug(grid[0]) == "kalman.q-10__association.max_distance_mm-80"
    assert setting_slug(()) == "default"


@pytest.mark.parametrize(
    "bad, says",
    [
        ("kalman.nope=1,2", "nope"),
        ("kalman.q=1,abc", "kalman.q=abc"),
        ("kalman.q", "SECTION.FIELD=V1,V2"),
        ("kalman.q=1,,2", "SECTION.FIELD=V1,V2"),
    ],
)
def test_sweep_errors_name_the_field(bad, says):
    with pytest.raises(SceneFormatError, match="--sweep") as info:
        sweep_grid([bad])
    assert says in str(info.value)


def test_a_field_swept_twice_is_refused():
    with pytest.raises(SceneFormatError, match="swept twice"):
        sweep_grid(["kalman.q=1,2", "kalman.q=3"])


def test_stored_key(tiny, tmp_path):
    scene, model = tiny
    assert stored_key(tmp_path / "none.npz") is None
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    assert stored_key(tmp_path / "junk.npz") is None
    results = run_pipeline(scene, NO_FIT, model, progress=False)
    save_results(results, tmp_path / "r.npz")
    assert stored_key(tmp_path / "r.npz") == results.cache_key != ""


def _timed_row(label, pid, start, end, fit):
    parts = {"started_at": start, "ended_at": end, "pid": pid, "load_s": 0.1,
             "frames_s": 0.4, "sequence_fit_s": fit, "summary_save_s": 0.5}  # fmt: skip
    return {"label": label, "scene": f"/d/{label}", "results": f"/d/{label}.npz",
            "status": "computed", "summary": None, "task_seconds": parts}  # fmt: skip


def test_task_timeline_numbers_the_workers_and_measures_their_busy_share():
    from pipeline.batch.report import build_report, render_html, task_timeline

    rows = [
        _timed_row("b", 77, 1000.0, 1004.0, 3.0),
        _timed_row("a", 55, 1000.5, 1006.0, 4.5),
        _timed_row("c", 77, 1004.0, 1008.0, 3.0),
        {
            "label": "chunked",
            "scene": "/d/c",
            "results": "/d/c.npz",
            "status": "computed",
            "summary": None,
            "task_seconds": None,
        },
        {
            "label": "reused",
            "scene": "/d/r",
            "results": "/d/r.npz",
            "status": "cached",
            "summary": None,
        },
    ]
    tl = task_timeline(rows)
    assert tl["workers"] == 2 and tl["span_s"] == pytest.approx(8.0)
    # busy: (4 + 5.5 + 4) s of 2 workers x 8 s
    assert tl["busy"] == pytest.approx(13.5 / 16, abs=1e-3)
    assert [(t["label"], t["worker"], t["start_s"]) for t in tl["tasks"]] == [
        ("b", 0, 0.0), ("a", 1, 0.5), ("c", 0, 4.0)
    ]  # fmt: skip
    assert tl["tasks"][1]["stages_s"]["sequence_fit"] == 4.5
    assert task_timeline(rows[3:]) is None  # no one-task scene: no timeline
    page = render_html(build_report(rows))
    assert "Where the time went" in page and "3 tasks on 2 workers, busy 84 %" in page
    assert "Where the time went" not in render_html(build_report(rows[3:]))
    assert tl["startup_s"] is None  # the command's start not given
    started = build_report(rows, started_at=997.0)
    assert started["timeline"]["startup_s"] == pytest.approx(3.0)
    assert "after 3.0 s of start-up" in render_html(started)


def test_timeline_labels_are_shortened_to_their_bars():
    """A task's label is drawn inside its bar: whole where it fits, cut short with an
    ellipsis where it does not, left out where not three letters fit (the labels of
    short scenes with a sweep setting ran over their neighbours')."""
    import base64
    import re

    from pipeline.batch.report import build_report, render_html

    long = "shelf_synth_noisy [kalman.q=100, association.max_distance_mm=120]"
    rows = [
        _timed_row("whole", 77, 1000.0, 1010.0, 8.0),  # 10 s of a 20 s span
        _timed_row(long, 55, 1000.0, 1006.0, 4.0),
        _timed_row("tiny", 55, 1006.0, 1006.05, 0.0),
        _timed_row("pose2sim_demo [kalman.q=10]", 55, 1006.05, 1020.0, 12.0),
    ]
    page = render_html(build_report(rows, started_at=999.0))
    svg = base64.b64decode(re.findall(r'src="data:image/svg\+xml;base64,([^"]+)"', page)[-1])
    texts = re.findall(r"<text[^>]*>([^<]*)</text>", svg.decode())
    assert "whole" in texts and "pose2sim_demo [kalman.q=10]" in texts
    assert long not in texts and "tiny" not in texts and "t\u2026" not in texts
    cut = [t for t in texts if t.endswith("\u2026")]
    assert len(cut) == 1 and long.startswith(cut[0][:-1]) and 3 <= len(cut[0]) - 1 < len(long)


def test_report_figures_are_inline_svg_with_their_text_as_text():
    """The figures are vector images inside the page (nothing fetched), and their words
    are text a browser lays out and a reader can search, not glyph outlines."""
    import base64
    import re

    from pipeline.batch.report import build_report, render_html

    rows = [
        _timed_row("b", 77, 1000.0, 1004.0, 3.0),
        _timed_row("a", 55, 1000.5, 1006.0, 4.5),
    ]
    for row, mpjpe in zip(rows, (31.5, 12.0), strict=True):
        row["summary"] = {"mpjpe_mm": mpjpe}
    page = render_html(build_report(rows, started_at=999.0))
    assert "data:image/png" not in page
    images = re.findall(r'src="data:image/svg\+xml;base64,([^"]+)"', page)
    assert len(images) == 2  # MPJPE per scene, the timeline
    svgs = [base64.b64decode(x).decode() for x in images]
    assert all(s.lstrip().startswith("<?xml") and "<svg" in s for s in svgs)
    bars, timeline = svgs
    assert re.search(r"<text[^>]*>MPJPE mm per scene</text>", bars)
    assert re.search(r"<text[^>]*>worker 1</text>", timeline)
