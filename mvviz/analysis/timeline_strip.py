"""The timeline's failure strip: frame ticks and a mark per failure span, one lane per
criterion in its colour, drawn as an image as wide as the right-hand panel; and the
playhead above it, a few dozen bytes of HTML placed at the same x (a frame change never
re-sends the marks, and draws and encodes no image).

Images are (height, width, 3) uint8 RGB on the panel's white, drawn at :data:`SCALE`
times the size they are shown at (crisp on any screen). Frame ``f`` of ``num_frames``
sits at :func:`frame_x` in both images, so the playhead points at the marks under it.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from mvviz.analysis.failures import CRITERIA, Failure, rank

SCALE = 2  # image pixels per screen pixel
STRIP_WIDTH = 600  # image pixels: the ~300 px wide right-hand panel at SCALE
PAD = 12  # image pixels left and right of frame 0 and the last frame
LANE_HEIGHT = 10  # image pixels per criterion lane (5 on screen)
LANE_GAP = 2
TICK_MINOR, TICK_MAJOR = 6, 12
LABEL_HEIGHT = 22
PLAYHEAD_HEIGHT = 14
MIN_MARK_WIDTH = 4  # a one-frame failure is still visible
TOP = 15  # per criterion, the worst this many are solid (the Failures list's length)
FAINT = 0.3  # the others: this much of the colour over the lane's background
BACKGROUND = (255, 255, 255)
LANE_BACKGROUND = (243, 244, 246)
AXIS_RGB = (150, 150, 150)
TEXT_RGB = (90, 90, 90)
PLAYHEAD_RGB = (25, 25, 25)
# One colour per criterion ("kind" of failure), shared by the marks and the legend.
CRITERION_RGB: dict[str, tuple[int, int, int]] = {
    "reprojection": (220, 38, 38),
    "mpjpe": (124, 58, 237),
    "association": (234, 128, 0),
    "id": (37, 99, 235),
    "kalman": (13, 148, 136),
    "proportions": (101, 163, 13),
    "smpl": (146, 84, 30),
    "labels": (219, 39, 119),
    "protocol": (71, 85, 105),
}
assert set(CRITERION_RGB) == set(CRITERIA)


def frame_x(frame: float, num_frames: int, width: int = STRIP_WIDTH) -> float:
    """Image x (pixels) of ``frame``'s centre in a strip ``width`` pixels wide."""
    span = max(num_frames - 1, 1)
    return PAD + (width - 2 * PAD) * float(frame) / span


def tick_steps(num_frames: int, width: int = STRIP_WIDTH) -> tuple[int, int]:
    """(minor, labelled) frame steps: minor ticks at least 10 image pixels apart, labels
    at least 90 (room for "1250")."""
    per_frame = (width - 2 * PAD) / max(num_frames - 1, 1)
    nice = [1, 2, 5, 10, 20, 25, 50, 100, 200, 250, 500, 1000, 2000, 5000, 10000]
    minor = next((s for s in nice if s * per_frame >= 10), nice[-1])
    label = next(s for s in nice if s >= minor and s % minor == 0 and s * per_frame >= 90)
    return minor, label


def strip_height(num_lanes: int) -> int:
    """Image height of a strip with ``num_lanes`` lanes."""
    return num_lanes * (LANE_HEIGHT + LANE_GAP) + TICK_MAJOR + LABEL_HEIGHT


def draw_failure_strip(
    num_frames: int,
    failures: Sequence[Failure],
    *,
    criteria: Sequence[str] = CRITERIA,
    width: int = STRIP_WIDTH,
    top: int = TOP,
) -> np.ndarray:
    """(strip_height(len(criteria)), width, 3) uint8: one lane per criterion (top to
    bottom in ``criteria``'s order) with a bar over each failure's span ``first..last``
    in :data:`CRITERION_RGB`, then the frame axis with ticks and frame numbers. The
    ``top`` worst of each criterion are solid with a darker tick at their worst frame,
    the others faint (where the many small problems are). Failures of other criteria
    are left out."""
    lanes = {c: i for i, c in enumerate(criteria)}
    worst = {id(f) for c in lanes for f in rank([f for f in failures if f.criterion == c], top)}
    img = np.full((strip_height(len(lanes)), width, 3), BACKGROUND, np.uint8)
    x_lo, x_hi = (
        int(frame_x(0, num_frames, width)),
        int(round(frame_x(num_frames - 1, num_frames, width))),
    )
    for i in range(len(lanes)):
        y = i * (LANE_HEIGHT + LANE_GAP)
        img[y : y + LANE_HEIGHT, x_lo - 2 : x_hi + 3] = LANE_BACKGROUND
    half = 0.5 * (width - 2 * PAD) / max(num_frames - 1, 1)  # half a frame, pixels
    solid_last = sorted(failures, key=lambda f: id(f) in worst)  # solid over faint
    for f in solid_last:
        lane = lanes.get(f.criterion)
        if lane is None:
            continue
        y = lane * (LANE_HEIGHT + LANE_GAP)
        rgb = np.array(CRITERION_RGB[f.criterion], float)
        if id(f) not in worst:
            rgb = FAINT * rgb + (1 - FAINT) * np.array(LANE_BACKGROUND)
        x0 = frame_x(f.first, num_frames, width) - half
        x1 = frame_x(f.last, num_frames, width) + half
        grow = max(0.0, MIN_MARK_WIDTH - (x1 - x0)) / 2
        c0, c1 = int(np.floor(x0 - grow)), int(np.ceil(x1 + grow))
        img[y : y + LANE_HEIGHT, max(c0, 0) : min(c1, width)] = rgb.astype(np.uint8)
        if id(f) not in worst:
            continue
        xw = int(round(frame_x(f.frame, num_frames, width)))
        img[y : y + LANE_HEIGHT, max(xw - 1, 0) : xw + 1] = (rgb * 0.55).astype(np.uint8)
    _draw_axis(img, num_frames, len(lanes) * (LANE_HEIGHT + LANE_GAP))
    return img


def _draw_axis(img: np.ndarray, num_frames: int, y: int) -> None:
    """The frame axis from row ``y`` down: a line, ticks, labelled frame numbers."""
    width = img.shape[1]
    x_lo, x_hi = frame_x(0, num_frames, width), frame_x(num_frames - 1, num_frames, width)
    img[y, int(x_lo) : int(round(x_hi)) + 1] = AXIS_RGB
    minor, label = tick_steps(num_frames, width)
    last = num_frames - 1
    for f in range(0, num_frames, minor):
        x = int(round(frame_x(f, num_frames, width)))
        img[y : y + (TICK_MAJOR if f % label == 0 else TICK_MINOR), x] = AXIS_RGB
    for f in [*range(0, num_frames, label), last]:
        x = frame_x(f, num_frames, width)
        if f == last and f % label and x - frame_x(f - f % label, num_frames, width) < 70:
            continue  # too close to the previous label
        text = str(f)
        (tw, _), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.6, 1)
        tx = int(np.clip(x - tw / 2, 0, width - tw))
        cv2.putText(
            img, text, (tx, y + TICK_MAJOR + 16), cv2.FONT_HERSHEY_SIMPLEX, 0.6, TEXT_RGB, 1,
            cv2.LINE_AA,
        )  # fmt: skip
    if last % label:
        x = int(round(x_hi))
        img[y : y + TICK_MAJOR, x] = AXIS_RGB


def draw_playhead(num_frames: int, frame: int, *, width: int = STRIP_WIDTH) -> np.ndarray:
    """(PLAYHEAD_HEIGHT, width, 3) uint8: a downward triangle over ``frame``'s x in the
    failure strip below it; flat colours, a few hundred bytes as PNG."""
    strip = np.full((PLAYHEAD_HEIGHT, width, 3), BACKGROUND, np.uint8)
    x = int(round(frame_x(frame, num_frames, width)))
    tri = np.array([[x - 8, 1], [x + 8, 1], [x, PLAYHEAD_HEIGHT - 1]], np.int32)
    cv2.fillPoly(strip, [tri], PLAYHEAD_RGB)
    return strip


def playhead_html(num_frames: int, frame: int, *, width: int = STRIP_WIDTH) -> str:
    """The playhead as HTML: the downward triangle of :func:`draw_playhead` at
    ``frame``'s x, in a box as wide as the strip image is shown (viser shows an image as
    wide as the panel, at most its own pixel width, inside ``xs`` padding, as here)."""
    x_pct = 100.0 * frame_x(frame, num_frames, width) / width
    half, height = 8 // SCALE, (PLAYHEAD_HEIGHT - 1) // SCALE
    r, g, b = PLAYHEAD_RGB
    return (
        '<div style="padding:0 var(--mantine-spacing-xs)">'
        f'<div style="position:relative;max-width:{width}px;height:{height + 1}px">'
        f'<div style="position:absolute;top:0;left:calc({x_pct:.3f}% - {half}px);width:0;'
        f"height:0;border-left:{half}px solid transparent;border-right:{half}px solid "
        f'transparent;border-top:{height}px solid rgb({r},{g},{b})"></div></div></div>'
    )


def next_failure(failures: Sequence[Failure], frame: int, direction: int) -> Failure | None:
    """The failure whose span starts nearest after (``direction`` > 0) or before (< 0)
    ``frame``; of those starting on the same frame, the highest score. None: no more."""
    if direction > 0:
        later = [f for f in failures if f.first > frame]
        if not later:
            return None
        start = min(f.first for f in later)
    else:
        earlier = [f for f in failures if f.first < frame]
        if not earlier:
            return None
        start = max(f.first for f in earlier)
    same = [f for f in failures if f.first == start]
    return max(same, key=lambda f: f.score if np.isfinite(f.score) else -np.inf)


def legend_html(counts: dict[str, int], labels: dict[str, str]) -> str:
    """One coloured square, name and count per criterion (``counts``: criterion ->
    entries), as the HTML under the strip."""
    parts = []
    for c, n in counts.items():
        r, g, b = CRITERION_RGB[c]
        parts.append(
            f'<span style="white-space:nowrap"><span style="color:rgb({r},{g},{b})">■</span>'
            f" {labels.get(c, c)} {n}</span>"
        )
    return '<div style="font-size:0.75em;line-height:1.4">' + " · ".join(parts) + "</div>"
