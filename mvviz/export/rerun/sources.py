"""The scene's pictures for a recording: each camera's video or image folder, read in
frame order and placed on the calibrated image as the viewer shows it."""

from __future__ import annotations

import cv2
import numpy as np

from pipeline.data.scene import Scene
from pipeline.detect.video_crop import CalibratedFrames


class FrameSource:
    """Frames of one camera (BGR uint8) from its video or image folder; reading in
    increasing frame order is cheapest (a video is decoded forward, seeking on jumps).
    ``place`` puts each frame on the calibrated image, as the viewer shows it."""

    def __init__(
        self, video=None, image_dir=None, place: CalibratedFrames | None = None, camera: str = ""
    ) -> None:
        self.video, self.image_dir, self._place, self.camera = video, image_dir, place, camera
        self._cap = cv2.VideoCapture(str(video)) if video is not None else None
        self._next = 0

    def read(self, frame: int) -> np.ndarray | None:
        img = self._read(frame)
        return img if img is None or self._place is None else self._place(img)

    def _read(self, frame: int) -> np.ndarray | None:
        if frame < 0:  # before the recording (a re-timed camera's first frames)
            return None
        if self._cap is not None:
            if frame < self._next or frame - self._next > 50:
                self._cap.set(cv2.CAP_PROP_POS_FRAMES, frame)
                self._next = frame
            while self._next < frame:
                self._cap.grab()
                self._next += 1
            ok, img = self._cap.read()
            self._next += 1
            return img if ok else None
        if self.image_dir is not None:
            for ext in (".jpg", ".png", ".jpeg"):
                p = self.image_dir / f"{frame:06d}{ext}"
                if p.is_file():
                    return cv2.imread(str(p), cv2.IMREAD_COLOR)
        return None

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()


def scene_frame_sources(scene: Scene) -> dict[str, FrameSource]:
    """Camera name -> a :class:`FrameSource` on the calibrated image, for each camera
    with a video or an image folder."""
    crops = scene.meta.get("video_crop") or {}  # what each video does not show
    out = {}
    for cam in scene.rig:
        if cam.name in scene.videos or cam.name in scene.image_dirs:
            size, crop = (cam.width, cam.height), crops.get(cam.name)
            out[cam.name] = FrameSource(
                scene.videos.get(cam.name),
                scene.image_dirs.get(cam.name),
                CalibratedFrames(cam.name, size, crop=crop),
                camera=cam.name,
            )
    return out
