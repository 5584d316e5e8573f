"""Video frames for the viewer, and the 2D overlays drawn on them with cv2.

Seeking an mp4 with ``cv2.VideoCapture`` costs tens of milliseconds, so each video is
decoded once, sequentially, in a background thread, into a compact in-memory list of
JPEG-encoded frames downscaled to ``width`` pixels (a few kB each), and cached on disk
under ``SCENE/.mvviz/frames/`` for the next start. A frame request decodes one JPEG
(about a millisecond) through a small LRU cache. ``images/<camera>/<frame:06d>.jpg``
scenes are read lazily instead.

The frustums' small images (:data:`THUMBNAIL_WIDTH` px) are decoded for every frame
once the videos are in (~0.6 ms a frame, in the background), within a memory budget
(:data:`THUMBNAIL_BUDGET_BYTES`): a frame change then shows them without decoding.

Pixels: OpenCV convention, (u, v) = (column, row); arrays are RGB uint8. Every stored
frame is a uniform scale of its camera's calibrated image: a video an encoder cropped or
padded by a few pixels, or one whose crop ``scene.json`` records (``video_crop``), is
placed on the calibrated image first (:mod:`pipeline.detect.video_crop`), so the overlays (in
calibrated pixels) and the frustums (the calibrated aspect) line up with it.
"""

from __future__ import annotations

import functools
import re
import threading
import weakref
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import scipy.sparse
import viser.transforms as vtf
from scipy.spatial import ConvexHull, QhullError

from mvviz.scene.bodies import Bodies
from mvviz.scene.geometry import FRUSTUM_WIDTHS, UNASSIGNED, LayerToggles, ViewerData, track_color
from pipeline.core.files import save_npz_atomic
from pipeline.data.scene import Scene
from pipeline.detect.video_crop import CalibratedFrames
from pipeline.stages.retime import picture_frame

CACHE_VERSION = 3  # 3: frames placed on the calibrated image
THUMBNAIL_WIDTH = FRUSTUM_WIDTHS[0]  # the frustums' default width, px
THUMBNAIL_BUDGET_BYTES = 256 * 2**20  # 5 cameras x ~7,000 frames at 128 x 96 px


@dataclass(frozen=True)
class _Source:
    kind: str  # "video" | "images"
    path: Path


class FrameStore:
    """Downscaled RGB frames of every camera of a scene, decoded once.

    Args:
        scene: the scene (its ``videos`` or ``image_dirs``).
        width: stored width in pixels (height keeps the aspect ratio).
        cache_dir: where decoded videos are cached (None: memory only).
        cache_size: decoded frames kept in the LRU.
    """

    def __init__(
        self,
        scene: Scene,
        *,
        width: int = 640,
        cache_dir: Path | None = None,
        cache_size: int = 96,
        jpeg_quality: int = 85,
    ) -> None:
        self.width = int(width)
        self.num_frames = scene.num_frames
        self.cache_dir = cache_dir
        self.jpeg_quality = jpeg_quality
        self.sources: dict[str, _Source] = {}
        stated = scene.meta.get("video_crop")
        self._stated: dict = stated if isinstance(stated, dict) else {}
        self._placers = {
            c.name: CalibratedFrames(
                c.name, (c.width, c.height), crop=self._stated.get(c.name),
                note=lambda text: print(f"mvviz view: {text}"),
            )
            for c in scene.rig
        }  # fmt: skip
        for cam in scene.rig.names:
            if cam in scene.videos:
                self.sources[cam] = _Source("video", scene.videos[cam])
            elif cam in scene.image_dirs:
                self.sources[cam] = _Source("images", scene.image_dirs[cam])
        self._jpegs: dict[str, list[bytes | None]] = {}
        self._small: dict[tuple[str, int], np.ndarray] = {}  # (cam, width) -> (F, h, w, 3)
        self._small_ready: dict[tuple[str, int], np.ndarray] = {}  # -> (F,) bool
        self._lru: OrderedDict[tuple, np.ndarray] = OrderedDict()
        self._cache_size = cache_size
        self._lock = threading.Lock()
        self._done = threading.Event()
        self._stopping = threading.Event()
        self._thread: threading.Thread | None = None
        self.on_camera_ready: list[Callable[[str], None]] = []

    # ------------------------------------------------------------------ decoding

    def start(self) -> FrameStore:
        """Decode every video in a background thread (cached ones load from disk)."""
        videos = [c for c, s in self.sources.items() if s.kind == "video"]
        if not videos:
            self._done.set()
            return self
        self._thread = threading.Thread(
            target=self._decode_all, args=(videos,), name="mvviz-frames", daemon=True
        )
        self._thread.start()
        return self

    def stop(self, timeout: float = 30.0) -> None:
        """End the background decoding at the next frame (a process must not exit while
        OpenCV decodes on a daemon thread: the C++ runtime aborts it)."""
        self._stopping.set()
        if self._thread is not None:
            self._thread.join(timeout)

    def wait(self, timeout: float | None = None) -> bool:
        """Block until every video is decoded; False on timeout."""
        return self._done.wait(timeout)

    @property
    def ready(self) -> bool:
        return self._done.is_set()

    def _decode_all(self, cams: list[str]) -> None:
        try:
            for cam in cams:
                if self._stopping.is_set():
                    return
                try:
                    frames = self._load_cache(cam)
                    if frames is None:
                        frames = self._decode_video(self.sources[cam].path, cam)
                        self._save_cache(cam, frames)
                except InterruptedError:
                    return  # stop(): nothing half-decoded is kept or cached
                except Exception as exc:  # a broken video must not take the viewer down
                    print(f"mvviz view: cannot decode video of camera {cam}: {exc}")
                    frames = []
                with self._lock:
                    self._jpegs[cam] = frames
                for cb in list(self.on_camera_ready):
                    cb(cam)
            per_frame = THUMBNAIL_WIDTH * THUMBNAIL_WIDTH * 3  # at most square
            if len(cams) * self.num_frames * per_frame <= THUMBNAIL_BUDGET_BYTES:
                for cam in cams:
                    if self._stopping.is_set():
                        return
                    self._decode_small(cam, THUMBNAIL_WIDTH)
        finally:
            self._done.set()

    def _decode_small(self, cam: str, width: int) -> None:
        """Fill the (F, h, width, 3) array of ``cam``'s frames ``width`` px wide."""
        for f in range(self.num_frames):
            if self._stopping.is_set():
                return
            img = self._decode_small_frame(cam, f, width, cache=False)
            if img is None:
                continue
            with self._lock:
                arr = self._small.get((cam, width))
                if arr is None:
                    arr = np.zeros((self.num_frames,) + img.shape, np.uint8)
                    self._small[(cam, width)] = arr
                    self._small_ready[(cam, width)] = np.zeros(self.num_frames, bool)
                if arr.shape[1:] == img.shape:
                    arr[f] = img
                    self._small_ready[(cam, width)][f] = True

    def _decode_video(self, path: Path, cam: str) -> list[bytes | None]:
        cap = cv2.VideoCapture(str(path))
        if not cap.isOpened():
            raise OSError(f"cannot open {path}")
        out: list[bytes | None] = []
        params = [int(cv2.IMWRITE_JPEG_QUALITY), self.jpeg_quality]
        try:
            while len(out) < self.num_frames:
                if self._stopping.is_set():
                    raise InterruptedError("stopped")
                ok, bgr = cap.read()
                if not ok:
                    break
                bgr = self._to_calibrated(cam, bgr)
                ok, buf = cv2.imencode(".jpg", self._resize(bgr), params)
                out.append(buf.tobytes() if ok else None)
        finally:
            cap.release()
        return out

    def _to_calibrated(self, cam: str, img: np.ndarray) -> np.ndarray:
        """``img`` (h, w, 3) on ``cam``'s calibrated image (see the module docstring); as
        it is, with a message, when its size fits no rule."""
        return self._placers[cam](img)

    def _resize(self, img: np.ndarray) -> np.ndarray:
        h, w = img.shape[:2]
        if w <= self.width:  # never upscale
            return img
        size = (self.width, max(1, round(h * self.width / w)))
        return cv2.resize(img, size, interpolation=cv2.INTER_AREA)

    def _cache_path(self, cam: str) -> Path | None:
        return None if self.cache_dir is None else self.cache_dir / f"{cam}_w{self.width}.npz"

    def _stamp(self, cam: str) -> np.ndarray:
        st = self.sources[cam].path.stat()
        crop = self._stated.get(cam) or [0, 0, 0, 0]
        try:  # a stated crop changes the frames
            crop = [round(float(c) * 1000) for c in crop][:4]
        except (TypeError, ValueError):
            crop = []
        stamp = [CACHE_VERSION, st.st_size, st.st_mtime_ns, self.jpeg_quality, *crop]
        return np.array(stamp, np.int64)

    def _load_cache(self, cam: str) -> list[bytes | None] | None:
        path = self._cache_path(cam)
        if path is None or not path.is_file():
            return None
        try:
            with np.load(path) as z:
                if not np.array_equal(z["stamp"], self._stamp(cam)):
                    return None
                data, offsets = z["data"], z["offsets"]
        except (OSError, ValueError, KeyError):
            return None
        blob = data.tobytes()
        return [
            blob[a:b] if b > a else None for a, b in zip(offsets[:-1], offsets[1:], strict=True)
        ]

    def _save_cache(self, cam: str, frames: list[bytes | None]) -> None:
        path = self._cache_path(cam)
        if path is None or not frames:
            return
        sizes = [len(f) if f else 0 for f in frames]
        offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
        data = np.frombuffer(b"".join(f or b"" for f in frames), np.uint8)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            save_npz_atomic(path, data=data, offsets=offsets, stamp=self._stamp(cam))
        except OSError:
            pass  # read-only scene directory: keep the frames in memory only

    # ------------------------------------------------------------------ access

    def jpeg(self, cam: str, frame: int) -> bytes | None:
        """The stored JPEG of ``cam``'s video at ``frame`` (``width`` px wide, on the
        calibrated image); None for image folders or before the video is decoded."""
        with self._lock:
            jpegs = self._jpegs.get(cam)
        if jpegs is None or not 0 <= frame < len(jpegs):
            return None
        return jpegs[frame]

    def frame(self, cam: str, frame: int) -> np.ndarray | None:
        """(h, width, 3) RGB of ``cam`` at ``frame``; None if unavailable (yet)."""
        key = (cam, int(frame))
        with self._lock:
            img = self._lru.get(key)
            if img is not None:
                self._lru.move_to_end(key)
                return img
            src = self.sources.get(cam)
            jpegs = self._jpegs.get(cam)
        if src is None or not 0 <= frame < self.num_frames:
            return None
        if src.kind == "images":
            bgr = cv2.imread(str(src.path / f"{frame:06d}.jpg"), cv2.IMREAD_COLOR)
            if bgr is None:
                return None
            bgr = self._resize(self._to_calibrated(cam, bgr))
        else:
            if jpegs is None or frame >= len(jpegs) or jpegs[frame] is None:
                return None
            bgr = cv2.imdecode(np.frombuffer(jpegs[frame], np.uint8), cv2.IMREAD_COLOR)
        img = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        with self._lock:
            self._lru[key] = img
            while len(self._lru) > self._cache_size:
                self._lru.popitem(last=False)
        return img

    def thumbnail(
        self, cam: str, frame: int, reduce: int = 2, *, cache: bool = True
    ) -> np.ndarray | None:
        """The frame at 1/``reduce`` (2, 4 or 8) of the stored width, for a frustum's image
        plane. Decoded straight from the JPEG at the reduced size (no resize); kept in the
        LRU if ``cache``."""
        key = (cam, int(frame), reduce)
        with self._lock:
            img = self._lru.get(key)
            src, jpegs = self.sources.get(cam), self._jpegs.get(cam)
        if img is not None:
            return img
        if src is None or not 0 <= frame < self.num_frames:
            return None
        if src.kind == "video":
            if jpegs is None or frame >= len(jpegs) or jpegs[frame] is None:
                return None
            flag = {2: cv2.IMREAD_REDUCED_COLOR_2, 4: cv2.IMREAD_REDUCED_COLOR_4}.get(
                reduce, cv2.IMREAD_REDUCED_COLOR_8
            )
            bgr = cv2.imdecode(np.frombuffer(jpegs[frame], np.uint8), flag)
            img = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        else:
            full = self.frame(cam, frame)
            if full is None:
                return None
            h, w = full.shape[:2]
            size = (max(1, w // reduce), max(1, h // reduce))
            img = cv2.resize(full, size, interpolation=cv2.INTER_AREA)
        if not cache:
            return img
        with self._lock:
            self._lru[key] = img
            while len(self._lru) > self._cache_size:
                self._lru.popitem(last=False)
        return img

    def small(self, cam: str, frame: int, width: int) -> np.ndarray | None:
        """``cam``'s ``frame`` ``width`` px wide (a frustum's image): from the pre-decoded
        frames when there (resized if ``width`` is narrower), else decoded now at the
        smallest JPEG reduction at least that wide and resized. None if not available
        (yet)."""
        with self._lock:
            for w in (width, THUMBNAIL_WIDTH):
                ready = self._small_ready.get((cam, w))
                if ready is not None and 0 <= frame < len(ready) and ready[frame]:
                    img = self._small[(cam, w)][frame]
                    break
            else:
                img = None
        if img is None or img.shape[1] < width:
            return self._decode_small_frame(cam, frame, width)
        if img.shape[1] == width:
            return img
        # narrower than the pre-decoded ones (many cameras): a resize, not a JPEG decode
        h = max(1, round(img.shape[0] * width / img.shape[1]))
        return cv2.resize(img, (width, h), interpolation=cv2.INTER_AREA)

    def _decode_small_frame(
        self, cam: str, frame: int, width: int, *, cache: bool = True
    ) -> np.ndarray | None:
        reduce = max([r for r in (2, 4, 8) if self.width / r >= width] or [2])
        img = self.thumbnail(cam, frame, reduce, cache=cache)
        if img is None or img.shape[1] == width:
            return img
        h = max(1, round(img.shape[0] * width / img.shape[1]))
        return cv2.resize(img, (width, h), interpolation=cv2.INTER_AREA)

    def available(self, cam: str) -> bool:
        src = self.sources.get(cam)
        if src is None:
            return False
        return src.kind == "images" or bool(self._jpegs.get(cam))


# --------------------------------------------------------------------------- overlays


@dataclass(frozen=True, eq=False)
class Overlay2D:
    """What to draw on one camera's image, in that camera's full-resolution pixels.

    Shapes: n detections, K tracks, P ground-truth people, J / Jg joints.
    """

    camera: str
    image_size: tuple[int, int]  # full-resolution width, height
    detections: np.ndarray  # (n, J, 3) x, y, confidence
    detection_colors: np.ndarray  # (n, 3) uint8
    reprojections: np.ndarray  # (K', J, 2) the filtered tracks of this frame, projected
    reprojection_colors: np.ndarray  # (K', 3) uint8
    gt: np.ndarray  # (P, Jg, 2)
    bones: tuple[tuple[int, int], ...]
    gt_bones: tuple[tuple[int, int], ...]
    label: str
    bodies: BodyOutlines | None = None  # the fitted bodies reprojected (their layer on)


def video_frame(data: ViewerData, camera: str, frame: int) -> int:
    """The frame of ``camera``'s video (or image folder) shown at the pipeline's ``frame``.

    A camera re-timed by the results' ``sync.offsets`` (offset d; positive: it lags) has
    its 2D recorded at ``frame`` + round(d) used at ``frame`` (:mod:`pipeline.diagnose.
    retime`), so its picture is taken from there too, and the drawn 2D stays on the
    person it was detected on. Only the nearest whole frame: the sub-frame part of d
    moves the 2D (interpolated toward the neighbouring frame) but not the picture, which
    is never blended between frames; on a fast limb the 2D can then sit up to half a
    frame's motion off the picture. Outside the clip (the camera has no recording of that
    moment) the frame store gives no picture."""
    return picture_frame(data.results.config.sync.by_camera(), camera, frame)


def image_overlay(data: ViewerData, view: int, frame: int, lay: LayerToggles) -> Overlay2D:
    """2D overlay of one camera and frame: its detections (if the 2D layer is on), the
    filtered tracks reprojected (if the filtered layer is on), the ground truth projected
    (if the GT layer is on). Pixels of the full-resolution image."""
    cam, res, J = data.scene.rig[view], data.results, data.joint_set.num_joints
    rows = data.rows_per_frame[frame]
    r = rows[data.scene.detections.view[rows] == view] if lay.detections2d else rows[:0]
    det_col = np.where(
        (res.det_person[r] < 0)[:, None], UNASSIGNED, track_color(data.det_track[r])
    ).astype(np.uint8)
    reproj, reproj_col = np.zeros((0, J, 2)), np.zeros((0, 3), np.uint8)
    if lay.filtered:
        pts = data.filtered[:, frame]  # (K, J, 3) mm
        keep = np.flatnonzero(np.isfinite(pts).all(-1).any(-1))
        reproj, reproj_col = cam.project(pts[keep]), track_color(keep)
    gt_px = np.zeros((0, data.gt_joint_set.num_joints, 2))
    if lay.gt and data.gt_points is not None:
        gt_px = cam.project(data.gt_points[data.gt_rows_per_frame[frame]])
    return Overlay2D(
        camera=cam.name,
        image_size=(cam.width, cam.height),
        detections=res.det_joints2d[r],
        detection_colors=det_col,
        reprojections=reproj,
        reprojection_colors=reproj_col,
        gt=gt_px,
        bones=data.joint_set.bones,
        gt_bones=data.gt_joint_set.bones,
        label=f"{cam.name}  frame {frame}",
        bodies=body_outlines(data, view, frame) if lay.bodies_on_images else None,
    )


def blank_frame(width: int, height: int) -> np.ndarray:
    """A dark-grey frame for a camera without video."""
    return np.full((height, width, 3), 48, np.uint8)


def _pixels(p: np.ndarray, w: int, h: int) -> tuple[np.ndarray, np.ndarray]:
    """(n, 2) float pixels -> (n, 2) int pixels and (n,) bool "drawable" (finite, and
    not absurdly far outside the image, which cv2 would choke on)."""
    p = np.asarray(p, float).reshape(-1, 2)
    ok = np.isfinite(p).all(1)
    ok[ok] &= (np.abs(p[ok, 0] - w / 2) < 2 * w) & (np.abs(p[ok, 1] - h / 2) < 2 * h)
    return np.where(ok[:, None], np.round(np.nan_to_num(p)), 0).astype(int), ok


def _draw_skeletons(
    out: np.ndarray, p: np.ndarray, ok: np.ndarray, bones, colors, *, thickness: int,
    joint: str, radius: int,
) -> None:  # fmt: skip
    """Draw P skeletons in order: (P, J, 2) pixels ``p``, (P, J) ``ok``, (P, 3) colours.
    The pixels of the group are checked and rounded at once and the joints read as Python
    ints: per skeleton that was ~40 us of NumPy calls, 51 skeletons a frame at 20 people."""
    P, J = ok.shape
    if P == 0:
        return
    h, w = out.shape[:2]
    px, drawable = _pixels(p, w, h)
    px, ok = px.reshape(P, J, 2).astype(np.int32), ok & drawable.reshape(P, J)
    b = np.asarray(bones, int).reshape(-1, 2)
    keep = ok[:, b[:, 0]] & ok[:, b[:, 1]]  # (P, B)
    segs = px[:, b]  # (P, B, 2, 2)
    aa = cv2.LINE_AA
    cols = [tuple(int(x) for x in c) for c in np.asarray(colors).reshape(P, 3)]
    pts, oks, any_bone = px.tolist(), ok.tolist(), keep.any(1).tolist()
    for i in range(P):
        col = cols[i]
        if any_bone[i]:  # one call for every bone (a Python loop of cv2.line is ~3x slower)
            cv2.polylines(out, list(segs[i][keep[i]]), False, col, thickness, aa)
        for q, good in zip(pts[i], oks[i], strict=True):
            if not good:
                continue
            if joint == "cross":
                cv2.drawMarker(out, q, col, cv2.MARKER_CROSS, 2 * radius, 1, aa)
            elif joint == "ring":
                cv2.circle(out, q, radius + 1, col, 1, aa)
            else:
                cv2.circle(out, q, radius, col, -1, aa)


@functools.lru_cache(maxsize=256)
def _text_size_cached(pattern: str, font: int, scale: float) -> tuple[int, int]:
    (tw, th), _ = cv2.getTextSize(pattern, font, scale, 1)
    return tw, th


def _text_size(text: str, font: int, scale: float) -> tuple[int, int]:
    """cv2.getTextSize (~0.3 ms a call with OpenCV 5, ~1/3 of drawing an overlay),
    cached by the text with its digits as 0: Hershey digits are all equally wide."""
    return _text_size_cached(re.sub(r"[0-9]", "0", text), font, round(scale, 4))


def draw_overlay(image: np.ndarray, ov: Overlay2D) -> np.ndarray:
    """A copy of ``image`` (any size; overlay pixels are rescaled) with: ground truth
    (thin dark crosses), reprojected filtered joints (rings, track colour), detections
    (filled, person colour, unassigned grey) and the camera name."""
    out = np.ascontiguousarray(image.copy())
    w = out.shape[1]
    s = w / ov.image_size[0]
    r = max(2, round(3 * w / 640))
    if ov.bodies is not None:  # under the skeletons
        draw_bodies(out, ov.bodies, s)
    gt = np.asarray(ov.gt, float)
    _draw_skeletons(out, gt * s, np.ones(gt.shape[:2], bool), ov.gt_bones,
                    np.full((len(gt), 3), 30), thickness=1, joint="cross", radius=r)  # fmt: skip
    rp = np.asarray(ov.reprojections, float)
    _draw_skeletons(out, rp * s, np.ones(rp.shape[:2], bool), ov.bones,
                    ov.reprojection_colors, thickness=1, joint="ring", radius=r)  # fmt: skip
    det = np.asarray(ov.detections, float)
    _draw_skeletons(out, det[..., :2] * s, det[..., 2] > 0, ov.bones,
                    ov.detection_colors, thickness=2, joint="dot", radius=r)  # fmt: skip
    font, scale = cv2.FONT_HERSHEY_SIMPLEX, max(0.4, 0.55 * w / 640)
    tw, th = _text_size(ov.label, font, scale)
    cv2.rectangle(out, (0, 0), (tw + 10, th + 12), (0, 0, 0), -1)
    cv2.putText(out, ov.label, (5, th + 5), font, scale, (255, 255, 255), 1, cv2.LINE_AA)
    return out


# --------------------------------------------------------------------------- bodies
#
# The fitted SMPL bodies on a camera's image, as silhouettes: each body part (the
# vertices its bone weighs most) is close to convex, so the silhouette is drawn as the
# union of the parts' 2D convex hulls. Only the vertices on each part's 3D convex hull in
# the bind pose are posed and projected (the 2D hull of a projected convex set comes from
# its 3D hull; a part moves nearly rigidly): ~1/5 of the mesh, and ~24 cv2 polygons a
# body instead of its ~27k triangles (cv2.fillPoly of every face: ~100 ms a frame).
# Against every face filled, the silhouettes agree to IoU 0.97 on the shipped Shelf
# scene (tests/mvviz/scene/test_bodies_on_images.py). Bodies are posed as the browser
# skins them (:mod:`mvviz.scene.bodies`: linear blend skinning, no pose blend shapes)
# and projected with the camera model, distortion included.

BODY_ALPHA = 0.4  # opacity of a body's fill over the picture
BODY_PALE = 0.45  # the fill is the track colour this much toward white: the skeletons
# drawn over it in the full colour stay readable
BODY_CACHE_FRAMES = 64  # (camera, frame) outlines kept per bodies object


@dataclass(frozen=True, eq=False)
class _PartHulls:
    """What the silhouettes of one :class:`Bodies` need, computed once."""

    index: np.ndarray  # (U,) vertices on some part's 3D hull (of any body's bind shape)
    weights: scipy.sparse.csr_matrix  # (U, 24) their skin weights
    parts: tuple[np.ndarray, ...]  # per part, its rows into ``index``


_PART_HULLS: weakref.WeakKeyDictionary[Bodies, _PartHulls] = weakref.WeakKeyDictionary()
_OUTLINES: weakref.WeakKeyDictionary[Bodies, OrderedDict] = weakref.WeakKeyDictionary()
_BODY_LOCK = threading.Lock()


def _part_hulls(bodies: Bodies) -> _PartHulls:
    with _BODY_LOCK:
        found = _PART_HULLS.get(bodies)
    if found is not None:
        return found
    part = np.argmax(bodies.weights, axis=1)
    per_part = []
    for j in range(bodies.weights.shape[1]):
        members = np.flatnonzero(part == j)
        if len(members) < 4:
            per_part.append(members)
            continue
        keep = []
        for shape in bodies.vertices[:, members]:  # every body's bind shape
            try:
                keep.append(members[ConvexHull(shape).vertices])
            except QhullError:  # a flat part: keep all its vertices
                keep.append(members)
        per_part.append(np.unique(np.concatenate(keep)))
    index = np.unique(np.concatenate(per_part))
    found = _PartHulls(
        index=index,
        weights=scipy.sparse.csr_matrix(bodies.weights[index].astype(np.float64)),
        parts=tuple(np.searchsorted(index, p) for p in per_part),
    )
    with _BODY_LOCK:
        _PART_HULLS[bodies] = found
    return found


def posed_vertices(bodies: Bodies, body: int, frame: int, index: np.ndarray | None = None,
                   weights=None) -> np.ndarray:  # fmt: skip
    """(U, 3) world metres: body ``body``'s vertices ``index`` (None: all) at ``frame``,
    linear-blend skinned from its bone poses (what the browser draws). ``weights``: the
    rows ``index`` of the skin weights (sparse is fastest), None: taken here."""
    idx = slice(None) if index is None else index
    W = bodies.weights[idx] if weights is None else weights
    R = vtf.SO3(bodies.bone_wxyz[body, frame]).as_matrix()  # (24, 3, 3)
    t = bodies.bone_position[body, frame] - np.einsum("bij,bj->bi", R, bodies.rest_joints[body])
    M = W @ np.concatenate([R.reshape(-1, 9), t], axis=1)  # (U, 12): blended [R | t]
    v = bodies.vertices[body][idx]
    x, y, z = v[:, 0:1], v[:, 1:2], v[:, 2:3]
    return M[:, 0:9:3] * x + M[:, 1:9:3] * y + M[:, 2:9:3] * z + M[:, 9:]


@dataclass(frozen=True, eq=False)
class BodyOutlines:
    """The fitted bodies seen by one camera in one frame, full-resolution pixels. B
    bodies, far to near (nearer ones are drawn over farther ones)."""

    tracks: np.ndarray  # (B,) track of each body
    colors: np.ndarray  # (B, 3) uint8, the track's colour
    hulls: tuple[tuple[np.ndarray, ...], ...]  # per body, its parts' convex hulls (n, 2)
    residual_px: dict[int, float]  # track -> median |body keypoints reprojected - 2D|


def mesh_residuals(data: ViewerData, view: int, frame: int) -> dict[int, float]:
    """Per track seen by camera ``view`` at ``frame``: the median over joints of the
    distance between the fitted body's keypoints (what the fit matched to the joints:
    SMPL + VAE if present, else step I) reprojected and the track's own 2D detection in
    that camera (confidence >= the triangulation's minimum), px."""
    res = data.results
    fit = res.smpl_vae if res.smpl_vae is not None else res.smpl
    if fit is None:
        return {}
    cam, out = data.scene.rig[view], {}
    for k in np.flatnonzero(fit.present[:, frame]):
        q = data.track_person[k, frame]
        row = res.person_members[q, view] if q >= 0 else -1
        if row < 0:
            continue
        kp = res.det_joints2d[row]  # (J, 3)
        err = np.linalg.norm(cam.project(fit.keypoints[k, frame]) - kp[:, :2], axis=-1)
        ok = np.isfinite(err) & (np.nan_to_num(kp[:, 2]) >= data.min_confidence)
        if ok.any():
            out[int(k)] = float(np.median(err[ok]))
    return out


def body_outlines(data: ViewerData, view: int, frame: int) -> BodyOutlines | None:
    """The fitted bodies of ``frame`` reprojected into camera ``view`` (None: no fits);
    cached per frame and camera (a frame revisited, or another layer toggled, costs
    nothing)."""
    bodies = data.fit_bodies
    if bodies is None:
        return None
    key = (view, int(frame), id(data.scene.rig))
    with _BODY_LOCK:
        cache = _OUTLINES.setdefault(bodies, OrderedDict())
        if key in cache:
            cache.move_to_end(key)
            return cache[key]
    found = _body_outlines(data, bodies, view, frame)
    with _BODY_LOCK:
        cache[key] = found
        while len(cache) > BODY_CACHE_FRAMES:
            cache.popitem(last=False)
    return found


def _body_outlines(data: ViewerData, bodies: Bodies, view: int, frame: int) -> BodyOutlines:
    cam, ph = data.scene.rig[view], _part_hulls(bodies)
    far = 4.0 * max(cam.width, cam.height)  # cv2 chokes on absurd coordinates
    found = []
    for b in np.flatnonzero(bodies.present[:, frame]):
        v_mm = posed_vertices(bodies, b, frame, ph.index, ph.weights) * 1000.0
        depth = cam.world_to_camera(v_mm)[:, 2]
        if not (depth > 0).any():
            continue  # behind the camera
        px = cam.project(v_mm).astype(np.float32)
        good = (np.abs(np.nan_to_num(px, nan=np.inf)) < far).all(1)  # finite, not absurd
        hulls = []
        for rows in ph.parts:
            p = px[rows[good[rows]]]
            if len(p) >= 3:
                hulls.append(cv2.convexHull(p)[:, 0])
        if hulls:
            found.append((float(np.median(depth)), int(bodies.ids[b]), tuple(hulls)))
    found.sort(key=lambda x: -x[0])  # far first
    tracks = np.array([k for _, k, _ in found], int)
    return BodyOutlines(
        tracks=tracks,
        colors=track_color(tracks).reshape(-1, 3),
        hulls=tuple(h for _, _, h in found),
        residual_px=mesh_residuals(data, view, frame),
    )


def body_labels(bodies: BodyOutlines, shape: tuple[int, int], scale: float) -> np.ndarray:
    """(h, w) uint8 of ``shape``: 0 where no body is, i + 1 where body i is the nearest
    (pixels ``scale`` x full resolution): the silhouettes :func:`draw_bodies` fills."""
    label = np.zeros(shape, np.uint8)
    for i, hulls in enumerate(bodies.hulls):
        for hull in hulls:  # 3 bits of sub-pixel precision
            pts = np.round(hull * (scale * 8)).astype(np.int32)
            cv2.fillConvexPoly(label, pts, i + 1, cv2.LINE_8, 3)
    return label


def _box(pts: np.ndarray, w: int, h: int) -> tuple[np.ndarray, np.ndarray]:
    """Whole-pixel [lo, hi) box around (n, 2) points in 1/8 px, a margin for the
    outline's anti-aliasing, clipped to the w x h picture."""
    lo = np.maximum(pts.min(0) // 8 - 2, 0)
    hi = np.minimum(pts.max(0) // 8 + 3, [w, h])
    return lo, hi


def draw_bodies(out: np.ndarray, bodies: BodyOutlines, scale: float) -> None:
    """Fill each body's silhouette translucently in its track's colour, paled (nearer
    bodies over farther ones), and outline it in the colour, on ``out`` (pixels
    ``scale`` x full resolution). The fills go on a copy of the bodies' box blended back
    once (cv2.addWeighted: where no body is, the blend gives the picture back); each
    outline comes from its own body's mask."""
    h, w = out.shape[:2]
    polys = []  # per body: all its hulls' points (1/8 px), where each hull ends, colour
    for hulls, color in zip(bodies.hulls, bodies.colors, strict=True):
        if hulls:
            pts = np.round(np.concatenate(hulls) * (scale * 8)).astype(np.int32)
            polys.append((pts, np.cumsum([len(x) for x in hulls])[:-1], color))
    pale = lambda c: tuple(int(x) for x in c + (255 - c.astype(float)) * BODY_PALE)  # noqa: E731
    if not polys:
        return
    lo, hi = _box(np.concatenate([p for p, _, _ in polys]), w, h)
    if (hi <= lo).any():
        return  # every body outside the picture
    roi = out[lo[1] : hi[1], lo[0] : hi[0]]
    fills, outlines = roi.copy(), []
    for pts, ends, color in polys:  # far to near
        rgb = tuple(int(c) for c in color)
        pts = pts - lo * 8
        for p in np.split(pts, ends):
            cv2.fillConvexPoly(fills, p, pale(color), cv2.LINE_8, 3)
        a, b = _box(pts, hi[0] - lo[0], hi[1] - lo[1])
        if (b <= a).any():
            continue
        mask = np.zeros((b[1] - a[1], b[0] - a[0]), np.uint8)
        for p in np.split(pts - a * 8, ends):
            cv2.fillConvexPoly(mask, p, 1, cv2.LINE_8, 3)
        contours, _ = cv2.findContours(
            mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE, offset=(int(a[0]), int(a[1]))
        )
        outlines.append((contours, rgb))
    cv2.addWeighted(fills, BODY_ALPHA, roi, 1.0 - BODY_ALPHA, 0.0, dst=roi)
    for contours, rgb in outlines:
        cv2.drawContours(roi, contours, -1, rgb, 1, cv2.LINE_AA)


def bodies_text(bodies: BodyOutlines | None) -> str:
    """The camera panel's line about the bodies drawn: each track's mesh-vs-2D residual."""
    if bodies is None:
        return ""
    if not bodies.residual_px:
        return "<small>fitted bodies: none seen by this camera in this frame</small>"
    parts = " · ".join(f"track {k} {e:.1f} px" for k, e in sorted(bodies.residual_px.items()))
    return f"<small>fitted body vs 2D (median over joints): {parts}</small>"
