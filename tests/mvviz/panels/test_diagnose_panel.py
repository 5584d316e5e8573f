"""The Diagnose panel on a fake host (no ViewerApp): the shipped Shelf scene with camera
"1" recording 4 frames late (pipeline.diagnose.perturb.delay_camera), the pipeline re-run
on it. The panel finds the offset, shows it with the numbers the diagnosis computed,
draws the camera's plots and field, jumps to its step, cancels and goes stale."""

from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest

from mvviz.analysis.diagnose_plots import field_scale
from mvviz.panels.diagnose_panel import GO_STEP, GO_WORST, NOT_RUN, make_diagnose_panel
from mvviz.state import ViewerState
from pipeline.body.model import load_body_model
from pipeline.config import PipelineConfig
from pipeline.data.scene import load_scene
from pipeline.diagnose.calibration import GRID
from pipeline.diagnose.perturb import delay_camera
from pipeline.run.pipeline import run_pipeline
from tests.mvviz.panels.test_contract import FakeHost
from tests.pipeline.helpers import REPO

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")
DELAY, LATE = 4, "1"


@pytest.fixture(scope="module")
def late_scene():
    model = load_body_model()
    scene = delay_camera(load_scene(REPO / "sample_data" / "shelf_synth"), LATE, DELAY)
    results = run_pipeline(scene, PipelineConfig(fit_smpl=False), model, progress=False)
    return scene, results, model


@pytest.fixture(scope="module")
def diagnosed(late_scene):
    """A fake host and its panel after one complete run."""
    host = FakeHost(ViewerState.create(*late_scene))
    panel = make_diagnose_panel(host)
    assert panel.gui.status.content == NOT_RUN
    panel.run()
    assert panel.wait(300) and panel.findings is not None
    yield host, panel
    panel.stop()
    host.stop()


@pytest.mark.slow
def test_the_late_camera_shows_its_offset(diagnosed):
    host, panel = diagnosed
    d = panel.findings.diagnosis
    e = d.sync[LATE]
    assert abs(e.offset_frames - DELAY) < 0.15 and e.offset
    for name, other in d.sync.items():
        if name != LATE:
            assert abs(other.offset_frames) < 0.15, name
    # the table row says what the diagnosis says, to the shown precision
    row = next(r for r in panel.gui.summary.content.splitlines() if r.startswith(f"| {LATE} |"))
    assert f"**{e.offset_frames:+.2f} late**" in row and f"| {e.confidence:.2f} |" in row
    shown = float(re.search(r"\*\*([+-][0-9.]+) late", row).group(1))
    assert abs(shown - DELAY) < 0.15
    assert f"--set sync.offsets={LATE}:{e.offset_frames:+.2f}" in panel.gui.commands.content
    assert "ok" in panel.gui.floor.content and d.floor is not None and d.floor.ok
    assert panel.camera == LATE  # the camera shown first is the one at fault
    # its calibration is judged with its 2D re-timed: late, not miscalibrated
    c = d.calibration[LATE]
    assert not c.suspect and c.retimed_by_frames == pytest.approx(e.offset_frames)
    assert c.systematic_px < c.systematic_as_recorded_px
    summary = panel.gui.summary.content
    assert f"offsets found applied ({LATE} {e.offset_frames:+.2f})" in summary
    assert ("out of sync, not miscalibrated" in summary) == c.out_of_sync
    assert "suspect" not in summary
    assert "Diagnosed in" in panel.gui.status.content and not panel.gui.progress.visible


def test_the_camera_pictures(diagnosed):
    host, panel = diagnosed
    cam = host.state.scene.rig[host.state.scene.rig.index_of(LATE)]
    for image in (panel.gui.sync_plot.image, panel.gui.series_plot.image):
        assert image.ndim == 3 and image.shape[1] >= 600 and (image < 128).any()
    field = panel.gui.field.image
    assert field.shape[:2] == (round(cam.height * 400 / cam.width), 400)
    # the field's arrows: each cell's mean residual, recomputed here from the observations
    res = panel.findings.residuals[LATE]
    f = res.field(cam.width, cam.height)
    gx = np.clip((res.pixel[:, 0] / cam.width * GRID[0]).astype(int), 0, GRID[0] - 1)
    gy = np.clip((res.pixel[:, 1] / cam.height * GRID[1]).astype(int), 0, GRID[1] - 1)
    busiest = np.argmax(f["count"])
    cx, cy = (f["centers"][busiest] / [cam.width, cam.height] * GRID).astype(int)
    mine = (gx == cx) & (gy == cy)
    assert mine.sum() == f["count"][busiest]
    assert np.allclose(res.vector[mine].mean(0), f["mean"][busiest])
    assert field_scale(f, cam.width) >= 1
    # the table's median residual is this camera's, as check_calibration found it
    assert res.median_px == pytest.approx(panel.findings.diagnosis.calibration[LATE].residual_px)
    # another camera: redrawn
    before = panel.gui.field.image.copy()
    panel.show_camera("0")
    assert panel.gui.camera.value == "0" and not np.array_equal(before, panel.gui.field.image)
    panel.show_camera(LATE)


def test_go_to_jumps_through_the_host(diagnosed):
    host, panel = diagnosed
    step = panel.findings.diagnosis.calibration[LATE].step
    frame = panel.go_to(GO_STEP)
    if step is None:
        assert frame is None
    else:
        assert frame == step.frame and host.asked("jump_to")[-1] == (step.frame, None, None, LATE)
    worst = panel.go_to(GO_WORST)
    series = panel.findings.series(LATE)
    assert series[worst] == np.nanmax(series)
    assert host.asked("jump_to")[-1] == (worst, None, None, LATE)


def test_new_results_make_the_findings_stale(diagnosed):
    host, panel = diagnosed
    shown = panel.findings.results
    host.set_results(dataclasses.replace(shown))  # other results (a re-run)
    assert host.wait_idle() and panel.stale and "Stale" in panel.gui.status.content
    host.set_results(shown)


def test_cancel_stops_a_run_between_steps(late_scene):
    host = FakeHost(ViewerState.create(*late_scene))
    panel = make_diagnose_panel(host)
    try:
        panel.run()
        panel.cancel()
        assert panel.wait(120)
        assert panel.findings is None and panel.gui.status.content.startswith("cancelled")
        assert not panel.gui.progress.visible
    finally:
        panel.stop()
        host.stop()
