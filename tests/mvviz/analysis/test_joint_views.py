"""Why is this joint here: each view's row equals what is computed independently from
the scene's cameras and the results, and a view pushed off is shown dropped, with why."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from mvviz.analysis.joint_views import joint_views, joint_views_markdown
from mvviz.scene.geometry import prepare
from pipeline.config import PipelineConfig
from pipeline.run.pipeline import run_pipeline


@pytest.fixture(scope="module")
def spoiled(viewer_scene):
    """The tiny scene with one joint of one detection moved 150 px (an outlier view) and
    another's confidence under the threshold, and its fresh results (no bodies)."""
    scene, results, model = viewer_scene
    frame, view, joint, low_joint = 5, 1, 9, 10
    row = next(
        int(r) for r in np.flatnonzero((scene.detections.frame == frame)
                                       & (scene.detections.view == view))
        if results.det_person[r] >= 0
    )  # fmt: skip
    kp = scene.detections.keypoints.copy()
    kp[row, joint, 0] += 150.0
    kp[row, low_joint, 2] = 0.05
    bad = dataclasses.replace(scene, detections=dataclasses.replace(scene.detections, keypoints=kp))
    config = dataclasses.replace(PipelineConfig(), fit_smpl=False)
    res = run_pipeline(bad, config, model, progress=False)
    q = res.det_person[row]
    return prepare(bad, res, None), int(res.person_track[q]), frame, view, joint, low_joint, row


@pytest.mark.slow
def test_rows_equal_an_independent_computation(viewer_state):
    data = viewer_state.data
    k, f = 0, 7
    for j in (0, 5, 9):
        jv = joint_views(data, k, j, f)
        assert jv is not None and len(jv.rows) == len(data.scene.rig)
        X = jv.point_mm
        assert np.allclose(X, data.results.track_raw[k, f, j])
        used = [r for r in jv.rows if r.used]
        assert len(used) >= 2 and abs(sum(r.weight for r in used) - 1.0) < 1e-9
        for cam, r in zip(data.scene.rig, jv.rows, strict=True):
            if not np.isfinite(r.u):
                continue
            uv = np.array([r.u, r.v])
            px = cam.project(X[None])[0]  # the residual: the point reprojected minus the 2D
            assert r.residual_px == pytest.approx(np.linalg.norm(px - uv), abs=1e-6)
            # the ray: a point 5 m along the ray through (u, v), and the distance of X to
            # that line by the cross product (a different formula from the module's)
            d = cam.pixels_to_rays(uv)
            dist = np.linalg.norm(np.cross(X - cam.center, d))
            assert r.ray_mm == pytest.approx(dist, abs=1e-6)
            assert r.ray_mm < 60.0  # a clean synthetic scene: rays pass close by


def test_an_outlier_view_is_shown_dropped_with_why(spoiled):
    data, k, f, view, joint, low_joint, row = spoiled
    jv = joint_views(data, k, joint, f)
    r = jv.rows[view]
    assert not r.used and r.weight == 0.0
    assert r.reason.startswith("outlier: ") and r.residual_px > 20.0
    assert r.u == pytest.approx(data.results.det_joints2d[row, joint, 0])
    assert all(o.used for i, o in enumerate(jv.rows) if i != view and np.isfinite(o.u))
    low = joint_views(data, k, low_joint, f).rows[view]
    assert not low.used and low.reason == "confidence 0.05 < 0.1"
    text = joint_views_markdown(jv)
    assert f"| {r.camera} |" in text and "**no**: outlier" in text


def test_no_person_no_table(viewer_state):
    data = viewer_state.data
    assert joint_views(data, data.num_tracks, 0, 0) is None
    assert "no person" in joint_views_markdown(None)
