"""The viewer shows a re-timed camera's 2D where the pipeline used it: with
``sync.offsets`` a camera's row recorded at frame g + n is drawn at frame g, with the
interpolated joints the stages used (results.det_joints2d)."""

from __future__ import annotations

import numpy as np

from mvviz.scene.geometry import LayerToggles, prepare
from mvviz.scene.images import image_overlay
from pipeline.config import PipelineConfig
from pipeline.diagnose.perturb import delay_camera
from pipeline.results import run_pipeline


def test_the_viewer_draws_the_rows_the_pipeline_used(viewer_scene):
    scene, _, model = viewer_scene
    cam = scene.rig.names[1]
    late = delay_camera(scene, cam, 1)  # its frame g shows time g - 1
    # 1.4, not the true 1: what is checked is which rows are drawn, and a fraction
    cfg = PipelineConfig(fit_smpl=False).with_overrides([f"sync.offsets={cam}:+1.4"])
    res = run_pipeline(late, cfg, model, progress=False)
    data = prepare(late, res, None)
    det, f = late.detections, 8
    rows = data.rows_per_frame[f]
    mine = rows[det.view[rows] == 1]
    assert len(mine) and (det.frame[mine] == f + 1).all()  # round(1.4) = 1 frame later
    others = rows[det.view[rows] != 1]
    assert (det.frame[others] == f).all()
    over = image_overlay(data, 1, f, LayerToggles())
    np.testing.assert_array_equal(over.detections, res.det_joints2d[mine])
    # The 0.4 of a frame: the drawn 2D is not the recorded one, it moved toward the
    # detection of frame f + 2 (the same person), which the stages used.
    moved = np.nanmax(np.abs(over.detections[..., :2] - det.keypoints[mine, :, :2]))
    assert moved > 0.1
    assert (res.det_person[mine] >= 0).any()
