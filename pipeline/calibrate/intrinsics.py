"""Each camera's intrinsics (K and OpenCV distortion k1 k2 p1 p2 k3) from its board views.

Not every view goes in: views are picked greedily for coverage of the image (a grid of
cells; each pick adds the most cells not yet covered, ties to the view with more corners),
then filled up to ``max_views`` with views spread over the footage, so a board held still
for many frames does not outweigh the rest of the image. A view that fits far worse than
the others is left out and the rest fitted again. Pixels in, pixels out.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from pipeline.calibrate.board import Board

MIN_VIEWS = 4
"""Views of the board a camera needs for its intrinsics (more give a better K)."""
K3_VIEWS = 60
"""Views below which k3 is held at 0: on fewer views of a small board it fits noise (on
the shared 4-webcam session, focal lengths 1-3 % nearer the peer's with k3 held)."""
OUTLIER_VIEW_PX = 0.5
OUTLIER_VIEW_FACTOR = 3.0
"""A view whose RMS error in the first fit is above both OUTLIER_VIEW_PX and
OUTLIER_VIEW_FACTOR times the median view's is left out of the second."""
MIN_INTRINSIC_CORNERS = 6
"""Corners (not all on one line) a view needs to take part in the intrinsics."""


@dataclass(frozen=True)
class Intrinsics:
    """One camera's intrinsics.

    Attributes:
        K: (3, 3) intrinsic matrix, pixels.
        dist: (5,) OpenCV distortion k1, k2, p1, p2, k3.
        rms: RMS reprojection error of the calibration, px (NaN when given, not fitted).
        views: indices (into the camera's views) of the views used (empty when given).
    """

    K: np.ndarray
    dist: np.ndarray
    rms: float
    views: tuple[int, ...]


def spans_plane(board: Board, ids: np.ndarray) -> bool:
    """Whether the corners ``ids`` (N,) are not all on one line of the board."""
    if len(ids) < 3:
        return False
    pts = board.object_points[ids, :2]
    return np.linalg.matrix_rank(pts - pts.mean(0), tol=1e-6 * board.square_mm) == 2


def select_views(
    pixels: list[np.ndarray],
    image_size: tuple[int, int],
    *,
    max_views: int = 30,
    grid: tuple[int, int] = (8, 6),
) -> list[int]:
    """Indices of the views chosen for the intrinsics (see the module docstring).

    Args:
        pixels: per view, (N_i, 2) corner pixels.
        image_size: (width, height).
    Returns:
        chosen indices, in the order picked.
    """
    w, h = image_size
    cells = []
    for p in pixels:
        cx = np.clip((p[:, 0] / w * grid[0]).astype(int), 0, grid[0] - 1)
        cy = np.clip((p[:, 1] / h * grid[1]).astype(int), 0, grid[1] - 1)
        cells.append(set((cy * grid[0] + cx).tolist()))
    covered: set[int] = set()
    chosen: list[int] = []
    left = set(range(len(pixels)))
    while left and len(chosen) < max_views:
        best = max(left, key=lambda i: (len(cells[i] - covered), len(pixels[i]), -i))
        if not cells[best] - covered:
            break
        chosen.append(best)
        covered |= cells[best]
        left.discard(best)
    rest = sorted(left)
    room = max_views - len(chosen)
    if room > 0 and rest:
        picks = np.unique(np.linspace(0, len(rest) - 1, min(room, len(rest))).round().astype(int))
        chosen += [rest[k] for k in picks]
    return chosen


def calibrate_intrinsics(
    board: Board,
    ids: list[np.ndarray],
    pixels: list[np.ndarray],
    image_size: tuple[int, int],
    *,
    max_views: int = 50,
) -> Intrinsics:
    """``cv2.calibrateCamera`` on the views chosen by :func:`select_views`.

    Args:
        ids: per view, (N_i,) corner ids; pixels: per view, (N_i, 2) pixels.
        image_size: (width, height).
    Raises:
        ValueError: fewer than :data:`MIN_VIEWS` usable views.
    """
    usable = [
        i
        for i in range(len(ids))
        if len(ids[i]) >= MIN_INTRINSIC_CORNERS and spans_plane(board, ids[i])
    ]
    if len(usable) < MIN_VIEWS:
        raise ValueError(
            f"the board spans the image in {len(usable)} views (>= {MIN_INTRINSIC_CORNERS} "
            f"corners, not on one line); the intrinsics need {MIN_VIEWS}"
        )
    chosen = [usable[k] for k in select_views([pixels[i] for i in usable], image_size,
                                               max_views=max_views)]  # fmt: skip
    obj = [board.object_points[ids[i]].astype(np.float32) for i in chosen]
    img = [pixels[i].astype(np.float32).reshape(-1, 1, 2) for i in chosen]
    w, h = image_size
    K0 = cv2.initCameraMatrix2D(obj, img, (w, h))  # from the views' homographies
    flags = cv2.CALIB_USE_INTRINSIC_GUESS
    if len(chosen) < K3_VIEWS:  # too few views to pin down a sixth-order radial term
        flags |= cv2.CALIB_FIX_K3
    rms, K, dist, per_view = _calibrate(obj, img, (w, h), K0, flags)
    # a view whose corners were found off (a board seen nearly edge-on: the corner
    # refinement's window takes in the next corners) is left out, and the rest refitted
    limit = max(OUTLIER_VIEW_PX, OUTLIER_VIEW_FACTOR * float(np.median(per_view)))
    keep = [k for k in range(len(chosen)) if per_view[k] <= limit]
    if len(keep) < len(chosen) and len(keep) >= MIN_VIEWS:
        chosen = [chosen[k] for k in keep]
        rms, K, dist, _ = _calibrate([obj[k] for k in keep], [img[k] for k in keep], (w, h),
                                     K, flags)  # fmt: skip
    return Intrinsics(K=np.asarray(K, float), dist=np.asarray(dist, float).ravel()[:5],
                      rms=float(rms), views=tuple(chosen))  # fmt: skip


def _calibrate(obj, img, size, K0, flags) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """``cv2.calibrateCameraExtended``: (RMS, K, dist, (V,) each view's RMS error)."""
    out = cv2.calibrateCameraExtended(obj, img, size, K0.copy(), np.zeros(5), flags=flags)
    rms, K, dist, per_view = out[0], out[1], out[2], out[7]
    return float(rms), K, dist, np.ravel(per_view)
