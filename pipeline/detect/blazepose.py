"""BlazePose, multi-person: Google MediaPipe's person detector and 33-landmark model.

Two TFLite models ship in ``sample_data/models/blazepose/`` (Apache-2.0; see its
README): ``pose_detection.tflite`` finds people (an SSD over a letterboxed 224x224
image; each detection is a face box plus 4 alignment keypoints) and
``pose_landmark_full.tflite`` puts 33 landmarks on one person's rotated 256x256 crop,
with a 3D "world" copy in metres. MediaPipe runs the landmark model on one person and
tracks it; here every detection of every frame gets its own crop, so any number of
people is found, frame by frame (no tracking).

The steps, as MediaPipe's graphs (``pose_detection_cpu.pbtxt``,
``pose_detection_to_roi.pbtxt``, ``pose_landmark_by_roi_cpu.pbtxt``) define them:

1. letterbox the image to 224x224, RGB scaled to [-1, 1], black padding;
2. decode the 2254 SSD anchors' boxes and keypoints, sigmoid scores, threshold;
3. weighted non-maximum suppression (IoU 0.3);
4. ROI per person: centred on keypoint 0 (hip centre), side twice the distance to
   keypoint 1 (the "full body" point above the head), rotated so that keypoint 1 is
   straight above keypoint 0, scaled by 1.25;
5. crop the ROI to 256x256, RGB in [0, 1]; run the landmark model; refine the
   landmarks with its heatmap (7x7 weighted mean); map them back to the image;
   sigmoid visibility and presence; rotate the world landmarks by the ROI's angle.

Everything but the interpreter calls is a pure function over arrays; :class:`BlazePose`
holds the two interpreters and the anchors.

Conventions: pixels as OpenCV's, (x, y) = (column, row), the centre of the top-left
pixel is (0, 0); images are RGB uint8 (height, width, 3). World landmarks in metres,
origin between the hips, axes of the camera: x right, y down, z forward (away from the
camera).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from pipeline.core.units import SAMPLE_DATA
from pipeline.data.joint_sets import BLAZEPOSE33, blazepose33_to_smpl24_matrix

MODEL_DIR = SAMPLE_DATA / "models" / "blazepose"
DETECTOR_FILE = "pose_detection.tflite"
LANDMARK_FILE = "pose_landmark_full.tflite"

DETECTOR_SIZE = 224
LANDMARK_SIZE = 256
NUM_LANDMARKS = BLAZEPOSE33.num_joints  # 33 of the model's 39 (the rest are auxiliary)
DETECTOR_STRIDES = (8, 16, 32, 32, 32)

# Detection keypoints (MediaPipe's order).
KP_HIP_CENTRE, KP_FULL_BODY, KP_SHOULDER_CENTRE, KP_UPPER_BODY = range(4)
HIPS = np.array([BLAZEPOSE33.index["left_hip"], BLAZEPOSE33.index["right_hip"]])


class InterpreterMissingError(ImportError):
    """No LiteRT / TFLite interpreter package is installed."""


def load_interpreter_class():
    """The first TFLite interpreter class found: ``ai_edge_litert`` (the ``[video]`` extra),
    ``tflite_runtime`` or ``tensorflow.lite``."""
    try:
        from ai_edge_litert.interpreter import Interpreter  # optional

        return Interpreter
    except ImportError:
        pass
    try:
        from tflite_runtime.interpreter import Interpreter  # optional

        return Interpreter
    except ImportError:
        pass
    try:
        import tensorflow as tf  # optional

        return tf.lite.Interpreter
    except ImportError:
        pass
    raise InterpreterMissingError(
        "running BlazePose needs a TFLite interpreter: pip install 'mvviz[video]' "
        "(or pip install ai-edge-litert)"
    )


def sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-np.asarray(x, float)))


def wrap_angle(a: np.ndarray) -> np.ndarray:
    """Angles in radians wrapped to [-pi, pi)."""
    return (np.asarray(a, float) + np.pi) % (2 * np.pi) - np.pi


# --------------------------------------------------------------------------- detector


def ssd_anchors(
    *,
    input_size: int = DETECTOR_SIZE,
    strides: tuple[int, ...] = DETECTOR_STRIDES,
    anchors_per_layer: int = 2,
    offset: float = 0.5,
) -> np.ndarray:
    """Anchor centres of MediaPipe's SSD layout (``SsdAnchorsCalculator``, fixed size).

    Consecutive layers of equal stride share one grid of ``ceil(input_size / stride)``
    cells a side; each cell holds ``anchors_per_layer`` anchors per layer (aspect ratio 1
    and the interpolated scale; all of unit size, so only centres matter). Order: layer
    group, row, column, anchor. For the pose detector: 28x28x2 + 14x14x2 + 7x7x6 = 2254.

    Returns:
        (num_anchors, 2) x, y normalised to [0, 1] over the detector input.
    """
    out, i = [], 0
    while i < len(strides):
        j = i
        while j < len(strides) and strides[j] == strides[i]:
            j += 1
        n = math.ceil(input_size / strides[i])
        ys, xs = np.meshgrid(
            (np.arange(n) + offset) / n, (np.arange(n) + offset) / n, indexing="ij"
        )
        cells = np.stack([xs.ravel(), ys.ravel()], -1)
        out.append(np.repeat(cells, anchors_per_layer * (j - i), axis=0))
        i = j
    return np.concatenate(out)


def decode_detections(
    raw_boxes: np.ndarray,
    raw_scores: np.ndarray,
    anchors: np.ndarray,
    *,
    input_size: int = DETECTOR_SIZE,
    score_clip: float = 100.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Decode the detector's raw outputs (``TensorsToDetectionsCalculator``).

    Args:
        raw_boxes: (num_anchors, 12) per anchor: box centre offset (dx, dy), box size
            (w, h), then 4 keypoint offsets (dx, dy), in input pixels, offsets relative
            to the anchor centre.
        raw_scores: (num_anchors,) or (num_anchors, 1) logits.
        anchors: (num_anchors, 2) from :func:`ssd_anchors`.
    Returns:
        boxes (num_anchors, 4) x0, y0, x1, y1; keypoints (num_anchors, 4, 2) x, y; both
        normalised to [0, 1] over the detector input; scores (num_anchors,) in [0, 1].
    """
    raw_boxes = np.asarray(raw_boxes, float).reshape(len(anchors), -1)
    centre = anchors + raw_boxes[:, 0:2] / input_size
    half = 0.5 * raw_boxes[:, 2:4] / input_size
    boxes = np.concatenate([centre - half, centre + half], -1)
    keypoints = anchors[:, None, :] + raw_boxes[:, 4:12].reshape(-1, 4, 2) / input_size
    scores = sigmoid(np.clip(np.asarray(raw_scores, float).reshape(-1), -score_clip, score_clip))
    return boxes, keypoints, scores


def encode_detections(
    boxes: np.ndarray,
    keypoints: np.ndarray,
    anchors: np.ndarray,
    *,
    input_size: int = DETECTOR_SIZE,
) -> np.ndarray:
    """Inverse of :func:`decode_detections` for boxes and keypoints: (num_anchors, 12)."""
    centre = 0.5 * (boxes[:, :2] + boxes[:, 2:])
    size = boxes[:, 2:] - boxes[:, :2]
    kp = (keypoints - anchors[:, None, :]).reshape(len(anchors), -1)
    return np.concatenate([centre - anchors, size, kp], -1) * input_size


def box_iou(box: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """IoU of one (4,) x0, y0, x1, y1 box with (M, 4) boxes -> (M,); 0 for empty unions."""
    lo = np.maximum(box[:2], boxes[:, :2])
    hi = np.minimum(box[2:], boxes[:, 2:])
    inter = np.prod(np.clip(hi - lo, 0, None), -1)
    area = lambda b: np.prod(np.clip(b[..., 2:] - b[..., :2], 0, None), -1)  # noqa: E731
    union = area(box) + area(boxes) - inter
    return np.where(union > 0, inter / np.where(union > 0, union, 1), 0.0)


def non_max_suppression(
    boxes: np.ndarray,
    keypoints: np.ndarray,
    scores: np.ndarray,
    *,
    iou_threshold: float = 0.3,
    weighted: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Non-maximum suppression, MediaPipe's weighted variant by default.

    Going down the scores, the best remaining detection and every remaining one that
    overlaps it by IoU > ``iou_threshold`` form a cluster; ``weighted`` replaces the
    best one's box and keypoints by the cluster's score-weighted mean (its score stays
    the best score), plain NMS keeps the best one as it is.

    Args:
        boxes: (M, 4); keypoints: (M, K, 2); scores: (M,).
    Returns:
        boxes (P, 4), keypoints (P, K, 2), scores (P,), best first.
    """
    order = np.argsort(-np.asarray(scores), kind="stable")
    out_b, out_k, out_s = [], [], []
    while order.size:
        top = order[0]
        overlap = box_iou(boxes[top], boxes[order]) > iou_threshold
        overlap[0] = True
        cluster = order[overlap]
        if weighted:
            w = scores[cluster] / scores[cluster].sum()
            out_b.append(w @ boxes[cluster])
            out_k.append(np.einsum("m,mkc->kc", w, keypoints[cluster]))
        else:
            out_b.append(boxes[top])
            out_k.append(keypoints[top])
        out_s.append(scores[top])
        order = order[~overlap]
    k = keypoints.shape[1] if keypoints.ndim == 3 else 0
    if not out_s:
        return np.zeros((0, 4)), np.zeros((0, k, 2)), np.zeros(0)
    return np.stack(out_b), np.stack(out_k), np.asarray(out_s, float)


def letterbox(image: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Fit ``image`` into a ``size`` x ``size`` square, keeping its aspect, black borders.

    Args:
        image: (H, W, 3) uint8.
    Returns:
        the square (size, size, 3) uint8 and the (2, 3) affine matrix taking image
        pixels to square pixels.
    """
    h, w = image.shape[:2]
    s = size / max(h, w)
    nw, nh = max(1, round(w * s)), max(1, round(h * s))
    small = cv2.resize(image, (nw, nh), interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR)
    left, top = (size - nw) // 2, (size - nh) // 2
    out = cv2.copyMakeBorder(
        small, top, size - nh - top, left, size - nw - left, cv2.BORDER_CONSTANT, value=0
    )
    sx, sy = nw / w, nh / h
    # Edge-aligned resize: (x + 0.5) * sx - 0.5, then the border shift.
    matrix = np.array([[sx, 0.0, 0.5 * sx - 0.5 + left], [0.0, sy, 0.5 * sy - 0.5 + top]])
    return out, matrix


def apply_affine(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(2, 3) or (P, 2, 3) affine matrices applied to (..., 2) / (P, ..., 2) points."""
    points = np.asarray(points, float)
    if matrix.ndim == 2:
        return points @ matrix[:, :2].T + matrix[:, 2]
    lin = np.einsum("pab,p...b->p...a", matrix[:, :, :2], points)
    return lin + matrix[:, None, :, 2].reshape((matrix.shape[0],) + (1,) * (points.ndim - 2) + (2,))


def invert_affine(matrix: np.ndarray) -> np.ndarray:
    """Inverse of a (2, 3) affine matrix."""
    a = np.linalg.inv(matrix[:, :2])
    return np.concatenate([a, -(a @ matrix[:, 2])[:, None]], 1)


@dataclass(frozen=True, eq=False)
class PersonDetections:
    """People found by the detector in one image, best score first.

    Attributes:
        score: (P,) in [0, 1].
        box: (P, 4) x0, y0, x1, y1 pixels: the detector's box (it boxes the face).
        keypoints: (P, 4, 2) pixels: hip centre, full-body point (above the head at the
            body's scale), shoulder centre, upper-body point.
    """

    score: np.ndarray
    box: np.ndarray
    keypoints: np.ndarray

    def __len__(self) -> int:
        return int(self.score.shape[0])


def detections_to_image(
    boxes: np.ndarray, keypoints: np.ndarray, scores: np.ndarray, matrix: np.ndarray, size: int
) -> PersonDetections:
    """Normalised detector-input boxes/keypoints -> image pixels (``matrix``: image -> input)."""
    inv = invert_affine(matrix)
    # Normalised coordinates have 0 and 1 at the input's edges; pixel centres sit 0.5 in.
    corners = apply_affine(inv, boxes.reshape(-1, 2, 2) * size - 0.5).reshape(-1, 4)
    kp = apply_affine(inv, keypoints * size - 0.5)
    return PersonDetections(score=np.asarray(scores, float), box=corners, keypoints=kp)


def tile_windows(width: int, height: int, grid: int, *, overlap: float = 0.25) -> np.ndarray:
    """Square windows that tile an image so the detector sees people ``grid`` times larger.

    The detector sees the whole image shrunk to 224 pixels, where people a few hundred
    pixels tall are too small to be found; running it again on overlapping squares of
    side ``max(width, height) / grid * (1 + overlap)`` (at most the image's short side)
    finds them. ``grid`` <= 1 gives no windows.

    Returns:
        (T, 4) int x0, y0, x1, y1 (exclusive) pixel windows.
    """
    if grid <= 1:
        return np.zeros((0, 4), int)
    side = int(min(width, height, round(max(width, height) / grid * (1 + overlap))))
    step = side * (1 - overlap)

    def starts(length: int) -> np.ndarray:
        n = max(1, math.ceil((length - side) / step) + 1) if length > side else 1
        return np.linspace(0, length - side, n).round().astype(int)

    x0, y0 = np.meshgrid(starts(width), starts(height), indexing="xy")
    x0, y0 = x0.ravel(), y0.ravel()
    return np.stack([x0, y0, x0 + side, y0 + side], -1)


def merge_detections(
    parts: list[PersonDetections], *, iou_threshold: float = 0.3
) -> PersonDetections:
    """Detections of overlapping runs (whole image, tiles), all in image pixels, merged by
    weighted non-maximum suppression."""
    box = np.concatenate([p.box for p in parts])
    kp = np.concatenate([p.keypoints for p in parts])
    score = np.concatenate([p.score for p in parts])
    box, kp, score = non_max_suppression(box, kp, score, iou_threshold=iou_threshold)
    return PersonDetections(score=score, box=box, keypoints=kp)


def pose_nms(
    keypoints: np.ndarray,
    score: np.ndarray,
    size: np.ndarray,
    *,
    threshold: float = 0.1,
    flip: np.ndarray | None = None,
    centre: np.ndarray | None = None,
) -> np.ndarray:
    """Indices of the poses to keep, dropping duplicates of one person.

    Two detections of one person (e.g. from two tiles, one with the face cut) give two
    crops and similar landmarks, sometimes mirrored left/right (a person seen from
    behind) or garbled (a crop centred on the person's legs). Going down ``score``, a
    pose is dropped when, against a kept pose, either its median landmark distance
    (also to the kept pose's mirror, by ``flip``) or the distance between the two poses'
    ``centre`` (mean of those landmarks, e.g. the hips) is below ``threshold`` times the
    kept pose's crop ``size``. (Two real people that close in the image are one behind
    the other; the hidden one's landmarks are unreliable anyway.)

    Args:
        keypoints: (P, L, 2+) pixels; score: (P,); size: (P,) pixels.
        flip: (L,) index of each landmark's mirror, or None.
        centre: indices of the landmarks whose mean is a pose's centre, or None.
    Returns:
        (K,) kept indices, best score first.
    """
    xy = np.asarray(keypoints, float)[..., :2]
    keep: list[int] = []
    for i in np.argsort(-np.asarray(score), kind="stable"):
        dup = False
        for k in keep:
            d = np.median(np.linalg.norm(xy[i] - xy[k], axis=-1))
            if flip is not None:
                d = min(d, np.median(np.linalg.norm(xy[i] - xy[k][flip], axis=-1)))
            if centre is not None:
                d = min(d, np.linalg.norm(xy[i][centre].mean(0) - xy[k][centre].mean(0)))
            if d < threshold * size[k]:
                dup = True
                break
        if not dup:
            keep.append(int(i))
    return np.asarray(keep, int)


# --------------------------------------------------------------------------- ROI


@dataclass(frozen=True, eq=False)
class Rois:
    """Rotated square crops, one per person.

    Attributes:
        centre: (P, 2) pixels.
        size: (P,) side in pixels.
        angle: (P,) radians: a crop vector (u, v) lies along ``R(angle) @ (u, v)`` in the
            image, ``R = [[cos, -sin], [sin, cos]]`` in y-down pixels; 0 = the body upright,
            positive = its head turned clockwise on screen (pi/2: head to the right).
    """

    centre: np.ndarray
    size: np.ndarray
    angle: np.ndarray

    def __len__(self) -> int:
        return int(self.size.shape[0])

    def take(self, rows: np.ndarray) -> Rois:
        return Rois(centre=self.centre[rows], size=self.size[rows], angle=self.angle[rows])

    def array(self) -> np.ndarray:
        """(P, 4) centre x, centre y, size, angle."""
        return np.concatenate([self.centre, self.size[:, None], self.angle[:, None]], -1)

    @staticmethod
    def from_array(a: np.ndarray) -> Rois:
        a = np.asarray(a, float).reshape(-1, 4)
        return Rois(centre=a[:, :2], size=a[:, 2], angle=a[:, 3])


def alignment_rois(
    keypoints: np.ndarray,
    *,
    start: int = KP_HIP_CENTRE,
    end: int = KP_FULL_BODY,
    scale: float = 1.25,
    target_angle: float = np.pi / 2,
) -> Rois:
    """ROIs from detection keypoints (``AlignmentPointsRectsCalculator`` then
    ``RectTransformationCalculator``): centred on keypoint ``start``, side
    ``2 * |end - start| * scale``, rotated so that ``end`` is straight above ``start``
    in the crop.

    Args:
        keypoints: (P, K, 2) pixels.
    """
    kp = np.asarray(keypoints, float)
    d = kp[:, end] - kp[:, start]
    angle = wrap_angle(target_angle - np.arctan2(-d[:, 1], d[:, 0]))
    return Rois(
        centre=kp[:, start].copy(), size=2.0 * np.linalg.norm(d, axis=-1) * scale, angle=angle
    )


def rotation_2d(angle: np.ndarray) -> np.ndarray:
    """(P,) angles -> (P, 2, 2) ``[[cos, -sin], [sin, cos]]``."""
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def roi_matrices(rois: Rois, out_size: int) -> np.ndarray:
    """(P, 2, 3) affine matrices taking crop pixels (of an ``out_size`` square) to image
    pixels: ``image = centre + R(angle) @ ((crop + 0.5) / out_size - 0.5) * size``."""
    rot = rotation_2d(rois.angle)  # (P, 2, 2)
    lin = rot * (rois.size / out_size)[:, None, None]
    offset = rois.centre + np.einsum(
        "pab,pb->pa", rot, np.repeat(((0.5 / out_size - 0.5) * rois.size)[:, None], 2, 1)
    )
    return np.concatenate([lin, offset[:, :, None]], -1)


def crop_rois(
    image: np.ndarray, rois: Rois, out_size: int = LANDMARK_SIZE, *, pyramid: list | None = None
) -> np.ndarray:
    """Warp each ROI of ``image`` to an ``out_size`` square (bilinear, replicated border).

    Crops that shrink the image more than twice sample a Gaussian pyramid level instead
    (``pyramid``: a list to cache the levels in between calls on the same image), so
    that bilinear sampling does not alias.

    Returns:
        (P, out_size, out_size, 3) uint8.
    """
    levels = pyramid if pyramid is not None else []
    if not levels:
        levels.append(image)
    mats = roi_matrices(rois, out_size)
    out = np.empty((len(rois), out_size, out_size, image.shape[2]), image.dtype)
    for i, m in enumerate(mats):
        shrink = rois.size[i] / out_size
        level = max(0, math.ceil(math.log2(shrink / 2))) if shrink > 2 else 0
        while len(levels) <= level and min(levels[-1].shape[:2]) > 2 * out_size:
            levels.append(cv2.pyrDown(levels[-1]))  # level l pixel x <-> level 0 pixel 2^l x
        level = min(level, len(levels) - 1)
        out[i] = cv2.warpAffine(
            levels[level],
            m / (2**level),
            (out_size, out_size),
            flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
            borderMode=cv2.BORDER_REPLICATE,
        )
    return out


# --------------------------------------------------------------------------- landmarks


def refine_with_heatmap(
    xy_norm: np.ndarray, heatmap: np.ndarray, *, kernel_size: int = 7, min_confidence: float = 0.5
) -> np.ndarray:
    """Refine landmarks by their heatmaps (``RefineLandmarksFromHeatmapCalculator``).

    Each landmark inside the heatmap moves to the sigmoid-weighted mean cell of the
    ``kernel_size`` window around it, if the window's peak reaches ``min_confidence``.
    As in MediaPipe, cell ``c`` stands for the normalised coordinate ``c / width``.

    Args:
        xy_norm: (L, 2) x, y normalised over the crop; heatmap: (H, W, L) logits.
    Returns:
        (L, 2) refined x, y, normalised.
    """
    hh, hw, nl = heatmap.shape
    out = np.array(xy_norm, float, copy=True)
    r = (kernel_size - 1) // 2
    for i in range(min(nl, len(out))):
        if not np.isfinite(out[i]).all():
            continue
        col, row = int(out[i, 0] * hw), int(out[i, 1] * hh)
        if not (0 <= col < hw and 0 <= row < hh):
            continue
        r0, r1, c0, c1 = (
            max(0, row - r),
            min(hh, row + r + 1),
            max(0, col - r),
            min(hw, col + r + 1),
        )
        conf = sigmoid(heatmap[r0:r1, c0:c1, i])
        total = conf.sum()
        if conf.max() >= min_confidence and total > 0:
            rows, cols = np.mgrid[r0:r1, c0:c1]
            out[i] = ((conf * cols).sum() / total / hw, (conf * rows).sum() / total / hh)
    return out


@dataclass(frozen=True, eq=False)
class Poses:
    """33-landmark poses of the people in one image.

    Attributes:
        keypoints: (P, 33, 3) x px, y px, confidence = visibility * presence (each a
            sigmoid of the model's logit), BlazePose-33 order (``BLAZEPOSE33``).
        world: (P, 33, 3) metres, origin between the hips, camera axes (x right, y down,
            z forward).
        score: (P,) the person detector's score.
        presence: (P,) the landmark model's pose-presence score (rows below the
            runner's ``min_presence`` are dropped).
        rois: the crops the landmarks were read in.
    """

    keypoints: np.ndarray
    world: np.ndarray
    score: np.ndarray
    presence: np.ndarray
    rois: Rois

    def __len__(self) -> int:
        return int(self.score.shape[0])

    @staticmethod
    def empty() -> Poses:
        z = np.zeros(0)
        return Poses(
            keypoints=np.zeros((0, NUM_LANDMARKS, 3)),
            world=np.zeros((0, NUM_LANDMARKS, 3)),
            score=z,
            presence=z,
            rois=Rois(centre=np.zeros((0, 2)), size=z, angle=z),
        )


def decode_landmarks(
    raw_landmarks: np.ndarray,
    raw_world: np.ndarray,
    heatmap: np.ndarray | None,
    rois: Rois,
    *,
    input_size: int = LANDMARK_SIZE,
    refine: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Landmark-model outputs of P crops -> image keypoints and camera-axes world points.

    Args:
        raw_landmarks: (P, 39 * 5) x, y, z (crop input pixels), visibility and presence
            logits per landmark.
        raw_world: (P, 39 * 3) metres, in the crop's axes.
        heatmap: (P, 64, 64, 39) logits, or None to skip the refinement.
        rois: the P crops.
    Returns:
        keypoints (P, 33, 3) x px, y px, confidence; world (P, 33, 3) metres, camera axes.
    """
    p = len(rois)
    lm = np.asarray(raw_landmarks, float).reshape(p, -1, 5)[:, :NUM_LANDMARKS]
    world = np.asarray(raw_world, float).reshape(p, -1, 3)[:, :NUM_LANDMARKS]
    xy_norm = lm[..., :2] / input_size
    if refine and heatmap is not None:
        xy_norm = np.stack([refine_with_heatmap(xy_norm[i], heatmap[i]) for i in range(p)])
    crop_px = xy_norm * input_size - 0.5
    image_xy = apply_affine(roi_matrices(rois, input_size), crop_px)
    conf = sigmoid(lm[..., 3]) * sigmoid(lm[..., 4])
    rot = rotation_2d(rois.angle)
    world_cam = world.copy()
    world_cam[..., :2] = np.einsum("pab,pjb->pja", rot, world[..., :2])
    return np.concatenate([image_xy, conf[..., None]], -1), world_cam


# --------------------------------------------------------------------------- mono 3D


def mono_joints_smpl24(world: np.ndarray) -> np.ndarray:
    """(P, 33, 3) world landmarks -> (P, 24, 3) SMPL-24 joints (NaN where BlazePose has
    no counterpart; mapping in ``pipeline.data.joint_sets.BLAZEPOSE33_TO_SMPL24``)."""
    m = blazepose33_to_smpl24_matrix()
    have = np.isfinite(m).all(1)
    out = np.full(world.shape[:-2] + (m.shape[0], 3), np.nan)
    out[..., have, :] = np.einsum("sj,...jc->...sc", m[have], world)
    return out


def square_bbox(rois: Rois) -> np.ndarray:
    """(P, 4) x0, y0, x1, y1: the axis-aligned square of each ROI's centre and side."""
    half = 0.5 * rois.size[:, None]
    return np.concatenate([rois.centre - half, rois.centre + half], -1)


# --------------------------------------------------------------------------- runner


def _output_by_shape(details: list[dict], want: dict[str, tuple[int, ...]]) -> dict[str, int]:
    """Tensor indices of the outputs whose shapes match ``want`` (name -> shape)."""
    found = {}
    for name, shape in want.items():
        hits = [d["index"] for d in details if tuple(d["shape"]) == shape]
        if len(hits) != 1:
            have = [tuple(d["shape"]) for d in details]
            raise ValueError(f"expected one model output of shape {shape} ({name}), got {have}")
        found[name] = hits[0]
    return found


class BlazePose:
    """The two interpreters and the anchors; call it on an RGB image.

    Args:
        model_dir: directory holding the two ``.tflite`` files.
        num_threads: interpreter threads (None: the interpreter's default).
        min_score: detector score threshold.
        iou_threshold: non-maximum suppression overlap.
        min_presence: landmark model's pose-presence threshold; rows below it are dropped.
        max_people: keep at most this many detections (best scores) per image.
        roi_scale: ROI enlargement (MediaPipe: 1.25).
        refine: refine landmarks with the heatmap, as MediaPipe does.
        tiles: also run the detector on overlapping windows that show people ``tiles``
            times larger (:func:`tile_windows`; 1 = the whole image only, as MediaPipe).
            On the synthetic Shelf renders (people 250-600 px tall in 1032x776 images)
            recall goes from about a third with 1 to about two thirds with 2.
        duplicate_threshold: :func:`pose_nms` threshold between people's landmarks.
    """

    def __init__(
        self,
        model_dir: str | Path = MODEL_DIR,
        *,
        num_threads: int | None = None,
        min_score: float = 0.5,
        iou_threshold: float = 0.3,
        min_presence: float = 0.5,
        max_people: int | None = None,
        roi_scale: float = 1.25,
        refine: bool = True,
        tiles: int = 2,
        duplicate_threshold: float = 0.1,
    ) -> None:
        interpreter = load_interpreter_class()
        model_dir = Path(model_dir)
        self.min_score = min_score
        self.iou_threshold = iou_threshold
        self.min_presence = min_presence
        self.max_people = max_people
        self.roi_scale = roi_scale
        self.refine = refine
        self.tiles = tiles
        self.duplicate_threshold = duplicate_threshold
        self.detector = interpreter(
            model_path=str(model_dir / DETECTOR_FILE), num_threads=num_threads
        )
        self.landmarker = interpreter(
            model_path=str(model_dir / LANDMARK_FILE), num_threads=num_threads
        )
        self.detector.allocate_tensors()
        self.landmarker.allocate_tensors()
        self.anchors = ssd_anchors()
        n = len(self.anchors)
        self._det_in = self.detector.get_input_details()[0]["index"]
        self._det_out = _output_by_shape(
            self.detector.get_output_details(), {"boxes": (1, n, 12), "scores": (1, n, 1)}
        )
        self._lm_in = self.landmarker.get_input_details()[0]["index"]
        self._lm_out = _output_by_shape(
            self.landmarker.get_output_details(),
            {"landmarks": (1, 195), "flag": (1, 1), "heatmap": (1, 64, 64, 39), "world": (1, 117)},
        )

    def detect(self, image: np.ndarray) -> PersonDetections:
        """Stage 1: people in an (H, W, 3) RGB uint8 image (whole image and tiles)."""
        parts = [self.detect_once(image)]
        for x0, y0, x1, y1 in tile_windows(image.shape[1], image.shape[0], self.tiles):
            part = self.detect_once(np.ascontiguousarray(image[y0:y1, x0:x1]))
            off = np.array([x0, y0], float)
            parts.append(
                PersonDetections(
                    score=part.score, box=part.box + np.tile(off, 2), keypoints=part.keypoints + off
                )
            )
        people = (
            merge_detections(parts, iou_threshold=self.iou_threshold)
            if len(parts) > 1
            else parts[0]
        )
        if self.max_people is not None:
            n = self.max_people
            people = PersonDetections(
                score=people.score[:n], box=people.box[:n], keypoints=people.keypoints[:n]
            )
        return people

    def detect_once(self, image: np.ndarray) -> PersonDetections:
        """One detector run on an (H, W, 3) RGB uint8 image, letterboxed to 224x224."""
        square, matrix = letterbox(image, DETECTOR_SIZE)
        x = square.astype(np.float32)[None] * (2.0 / 255.0) - 1.0
        self.detector.set_tensor(self._det_in, x)
        self.detector.invoke()
        raw_boxes = self.detector.get_tensor(self._det_out["boxes"])[0]
        raw_scores = self.detector.get_tensor(self._det_out["scores"])[0]
        boxes, kps, scores = decode_detections(raw_boxes, raw_scores, self.anchors)
        keep = scores >= self.min_score
        boxes, kps, scores = non_max_suppression(
            boxes[keep], kps[keep], scores[keep], iou_threshold=self.iou_threshold
        )
        return detections_to_image(boxes, kps, scores, matrix, DETECTOR_SIZE)

    def landmarks(self, image: np.ndarray, rois: Rois) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Stage 2: 33 landmarks in each ROI of an RGB image.

        Returns:
            keypoints (P, 33, 3), world (P, 33, 3) (see :class:`Poses`), presence (P,).
        """
        p = len(rois)
        if p == 0:
            return np.zeros((0, NUM_LANDMARKS, 3)), np.zeros((0, NUM_LANDMARKS, 3)), np.zeros(0)
        crops = crop_rois(image, rois, LANDMARK_SIZE)
        raw_lm, raw_world, heat, flag = [], [], [], []
        for crop in crops:
            self.landmarker.set_tensor(self._lm_in, crop.astype(np.float32)[None] / 255.0)
            self.landmarker.invoke()
            raw_lm.append(self.landmarker.get_tensor(self._lm_out["landmarks"])[0])
            raw_world.append(self.landmarker.get_tensor(self._lm_out["world"])[0])
            heat.append(self.landmarker.get_tensor(self._lm_out["heatmap"])[0])
            flag.append(float(self.landmarker.get_tensor(self._lm_out["flag"])[0, 0]))
        kp, world = decode_landmarks(
            np.stack(raw_lm), np.stack(raw_world), np.stack(heat), rois, refine=self.refine
        )
        return kp, world, np.asarray(flag)

    def __call__(self, image: np.ndarray) -> Poses:
        """Both stages: every person's 33 landmarks in an (H, W, 3) RGB uint8 image."""
        people = self.detect(image)
        if len(people) == 0:
            return Poses.empty()
        rois = alignment_rois(people.keypoints, scale=self.roi_scale)
        kp, world, presence = self.landmarks(image, rois)
        keep = np.flatnonzero(presence >= self.min_presence)
        keep = keep[
            pose_nms(
                kp[keep],
                people.score[keep],
                rois.size[keep],
                threshold=self.duplicate_threshold,
                flip=BLAZEPOSE33.flip_index,
                centre=HIPS,
            )
        ]
        return Poses(
            keypoints=kp[keep],
            world=world[keep],
            score=people.score[keep],
            presence=presence[keep],
            rois=rois.take(keep),
        )
