"""The Diagnose panel's pictures: one camera's sync residual curve over candidate shifts,
its calibration residual over time (a step marked where it moved), and its residual
vector field over the image. Matplotlib's Agg canvas (no pyplot) for the plots, cv2
for the arrows; each function returns an (h, w, 3) uint8 RGB image.

Units: frames, pixels (the camera's full-resolution image), as the diagnoses give them.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import cv2
import numpy as np

from pipeline.data.cameras import Camera
from pipeline.diagnose.calibration import CameraResidual, StepChange
from pipeline.diagnose.sync import SyncEstimate

if TYPE_CHECKING:
    from matplotlib.backends.backend_agg import FigureCanvasAgg

PLOT_SIZE, PLOT_DPI = (680, 330), 200  # px; shown ~300 px wide in the panel
CURVE, MARK, SPAN = "#1f77b4", "#d62728", "#7f7f7f"
ARROW_RGB, CELL_RGB = (255, 200, 40), (90, 90, 90)


def _figure(size: tuple[int, int] = PLOT_SIZE, dpi: int = PLOT_DPI):
    # matplotlib (~0.5 s to import) loads with the first plot, not with the viewer
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(size[0] / dpi, size[1] / dpi), dpi=dpi, facecolor="white")
    canvas = FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    ax.tick_params(labelsize=6.5, length=2, pad=1.5)
    ax.grid(True, lw=0.3, color="#dddddd")
    fig.subplots_adjust(left=0.14, right=0.97, top=0.83, bottom=0.2)
    return fig, canvas, ax


def _pixels(canvas: FigureCanvasAgg) -> np.ndarray:
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()


def sync_curve_image(est: SyncEstimate) -> np.ndarray:
    """The mean capped residual at each whole-frame shift tried, the estimated offset
    (sub-frame) marked, and the residual as recorded (shift 0)."""
    fig, canvas, ax = _figure()
    ok = np.isfinite(est.residual_px)
    ax.plot(est.shifts[ok], est.residual_px[ok], ".-", lw=0.9, ms=3, color=CURVE)
    ax.axvline(0.0, lw=0.6, color=SPAN, ls=":")
    ax.axvline(est.offset_frames, lw=1.0, color=MARK)
    ax.set_xlabel("shift of the camera's frames (frames)", fontsize=6.5, labelpad=1)
    ax.set_ylabel("residual (px)", fontsize=6.5, labelpad=1)
    ax.set_title(
        f"camera {est.camera}: {est.offset_frames:+.2f} frames ± {est.offset_std_frames:.2f}, "
        f"confidence {est.confidence:.2f}",
        fontsize=7, loc="left", pad=3,
    )  # fmt: skip
    return _pixels(canvas)


def residual_series_image(
    camera: str, series: np.ndarray, step: StepChange | None, *, frame: int | None = None
) -> np.ndarray:
    """(F,) median residual per frame (NaN: nobody seen); the step's frame and its
    before / after levels marked; ``frame`` (the viewer's) as a thin line."""
    fig, canvas, ax = _figure()
    t = np.arange(len(series))
    ax.plot(t, series, "-", lw=0.7, color=CURVE)
    title = f"camera {camera}: residual vs the others' joints"
    if step is not None:
        ax.axvline(step.frame, lw=1.1, color=MARK)
        ax.hlines([step.before_px, step.after_px], [0, step.frame], [step.frame, len(series)],
                  colors=MARK, lw=0.8, ls="--")  # fmt: skip
        title += f"; step at {step.frame}"
    if frame is not None:
        ax.axvline(frame, lw=0.6, color=SPAN)
    ax.set_xlim(0, max(len(series) - 1, 1))
    ax.set_xlabel("frame", fontsize=6.5, labelpad=1)
    ax.set_ylabel("median (px)", fontsize=6.5, labelpad=1)
    ax.set_title(title, fontsize=7, loc="left", pad=3)
    return _pixels(canvas)


def field_scale(field: dict, width: int, *, target: float = 0.06) -> float:
    """How much the arrows are lengthened: the longest mean vector drawn ``target`` of
    the image width, a whole number (1, 2, 5, 10, 20, ...) so the legend reads plainly."""
    longest = float(np.max(np.linalg.norm(field["mean"], axis=-1), initial=0.0))
    if longest <= 0:
        return 1.0
    want = target * width / longest
    steps = np.array([1, 2, 5, 10, 20, 50, 100, 200, 500])
    return float(steps[steps <= max(want, 1)].max())


def residual_field_image(
    res: CameraResidual, camera: Camera, *, width: int = 400, base: np.ndarray | None = None
) -> tuple[np.ndarray, float]:
    """The mean residual vector of each image cell (:meth:`CameraResidual.field`) as an
    arrow from the cell's centre, lengthened by :func:`field_scale`, on ``base`` (the
    camera's picture, any size) or a dark frame ``width`` px wide. Returns the image and
    the scale."""
    h = max(1, round(camera.height * width / camera.width))
    img = np.full((h, width, 3), 40, np.uint8) if base is None else cv2.resize(base, (width, h))
    img = np.ascontiguousarray(img)
    f = res.field(camera.width, camera.height)
    scale = field_scale(f, camera.width)
    s = width / camera.width
    for c, m, n in zip(f["centers"], f["mean"], f["count"], strict=True):
        a = tuple(int(round(x)) for x in c * s)
        b = tuple(int(round(x)) for x in (c + m * scale) * s)
        cv2.circle(img, a, 2, CELL_RGB if n < 20 else ARROW_RGB, -1, cv2.LINE_AA)
        if a != b:
            cv2.arrowedLine(img, a, b, ARROW_RGB, 1, cv2.LINE_AA, tipLength=0.25)
    label = f"{camera.name}: residual x{scale:g} (reprojected minus own 2D)"
    cv2.putText(img, label, (4, h - 6), cv2.FONT_HERSHEY_SIMPLEX, 0.38, (255, 255, 255), 1,
                cv2.LINE_AA)  # fmt: skip
    return img, scale
