"""The viewer shows a re-timed camera's 2D where the pipeline used it: with
``sync.offsets`` a camera's row recorded at frame g + n is drawn at frame g, with the
interpolated joints the stages used (results.det_joints2d), on that camera's picture of
frame g + n (the nearest whole frame)."""

from __future__ import annotations

import cv2
import numpy as np

from mvviz.app import ViewerApp
from mvviz.scene.geometry import LayerToggles, prepare
from mvviz.scene.images import blank_frame, draw_overlay, image_overlay, video_frame
from mvviz.state import ViewerState
from pipeline.config import PipelineConfig
from pipeline.diagnose.perturb import delay_camera
from pipeline.run.pipeline import run_pipeline
from tests.mvviz.conftest import free_port


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


def _panel_picture(st, frame_store, view: int, video_frame_: int) -> np.ndarray:
    """The camera panel's picture at ``st``'s frame drawn on video frame ``video_frame_``
    (as ViewerApp._frame_images resizes and draws it; blank past the video)."""
    cam = st.scene.rig[view]
    w = st.panel_image_width
    h = max(1, round(cam.height * w / cam.width))
    base = frame_store.frame(cam.name, video_frame_)
    if base is None:
        base = blank_frame(w, h)
    elif base.shape[1] != w:
        interp = cv2.INTER_AREA if base.shape[1] > 2 * w else cv2.INTER_LINEAR
        base = cv2.resize(base, (w, h), interpolation=interp)
    return draw_overlay(base, image_overlay(st.data, view, st.frame, st.layers))


def test_the_camera_picture_follows_the_offset(viewer_scene, frame_store):
    """Camera 1 re-timed by +1.4 frames, camera 2 by -2.6: at frame 8 the camera panel
    and the frustums show camera 1's video frame 9 and camera 2's frame 5 (round half up,
    as the rows move), camera 0's frame 8; past the end of its video, a blank picture."""
    scene, _, model = viewer_scene
    names = scene.rig.names
    cfg = PipelineConfig(fit_smpl=False).with_overrides(
        [f"sync.offsets={names[1]}:+1.4,{names[2]}:-2.6"]
    )
    late = delay_camera(scene, names[1], 1)
    res = run_pipeline(late, cfg, model, progress=False)
    data = prepare(late, res, None)
    assert [video_frame(data, n, 8) for n in names] == [8, 9, 5]
    assert video_frame(data, names[1], 19) == 20  # past the clip
    app = ViewerApp(ViewerState.create(late, res, model), port=free_port(), frames=frame_store)
    try:
        assert app.wait_idle(60)
        for view, shown in ((1, 9), (0, 8), (2, 5)):
            app.jump_to(frame=8, view=view)
            assert app.wait_idle(30)
            st = app.state.snapshot()
            assert (st.frame, st.camera) == (8, view)
            images, panel, _ = app._frame_images(st)
            np.testing.assert_array_equal(panel, _panel_picture(st, frame_store, view, shown))
            if shown != 8:  # the recorded frame would be another picture
                assert not np.array_equal(panel, _panel_picture(st, frame_store, view, 8))
            for name, (key, thumb) in images.items():  # every frustum's picture
                want = video_frame(data, name, 8)
                assert thumb is not None and key[0] == want
                fw = st.layers.frustum_image_width
                np.testing.assert_array_equal(thumb, frame_store.small(name, want, fw))
        app.jump_to(frame=19, view=1)  # camera 1's frame 20 was never recorded
        assert app.wait_idle(30)
        st = app.state.snapshot()
        _, panel, _ = app._frame_images(st)
        np.testing.assert_array_equal(panel, _panel_picture(st, frame_store, 1, 20))
        assert frame_store.frame(names[1], 20) is None
    finally:
        app.stop()
