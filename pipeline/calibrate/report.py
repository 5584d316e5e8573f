"""A calibration's report page: per camera, the board corners over the image (coverage)
coloured by their bundle-adjustment error, and the figures of
:class:`~pipeline.calibrate.calibrate.CameraReport`. One self-contained HTML file (inline
SVG)."""

from __future__ import annotations

import html
import io
import math
import os
from collections.abc import Sequence

import numpy as np

from pipeline.calibrate.extrinsics import View
from pipeline.core.files import atomic_write

REPORT_HTML = "calibration_report.html"


def coverage_svg(
    views: Sequence[View], residuals: Sequence[np.ndarray], image_size: tuple[int, int]
) -> str:
    """One camera's corners (all its views) over its image, coloured by reprojection error
    (px; grey where not adjusted), as an SVG string."""
    from matplotlib.figure import Figure  # with the report, not at the command's start
    from matplotlib.patches import Rectangle

    w, h = image_size
    fig = Figure(figsize=(4.0, 4.0 * h / w + 0.4))
    ax = fig.add_subplot()
    ax.add_patch(Rectangle((0, 0), w, h, fill=False, edgecolor="black"))
    px = [v.pixels for v in views]
    err = [np.linalg.norm(r, axis=1) if len(r) else np.full(len(v.ids), np.nan)
           for v, r in zip(views, residuals, strict=True)]  # fmt: skip
    if px:
        p, e = np.concatenate(px), np.concatenate(err)
        known = np.isfinite(e)
        ax.scatter(p[~known, 0], p[~known, 1], s=4, c="0.6")
        top = max(2.0, float(np.nanpercentile(e, 95))) if known.any() else 2.0
        dots = ax.scatter(p[known, 0], p[known, 1], s=4, c=e[known], cmap="viridis", vmin=0,
                          vmax=top)  # fmt: skip
        fig.colorbar(dots, ax=ax, label="reprojection error, px", shrink=0.8)
    ax.set_xlim(0, w)
    ax.set_ylim(h, 0)
    ax.set_aspect("equal")
    ax.set_xticks([0, w])
    ax.set_yticks([0, h])
    fig.tight_layout()
    buffer = io.StringIO()
    fig.savefig(buffer, format="svg")
    return "<svg" + buffer.getvalue().split("<svg", 1)[1]


def write_report(calibration, path: str | os.PathLike) -> None:
    """Write ``calibration``'s report page (see the module docstring) atomically."""

    def num(x: float, unit: str = "") -> str:
        return "-" if math.isnan(x) else f"{x:.3f}{unit}"

    def offset(r) -> str:
        if math.isnan(r.sync_offset_frames):
            return "-"
        ms = ("" if math.isnan(r.sync_offset_s)
              else f" ({round(1000 * r.sync_offset_s) + 0.0:+.0f} ms)")  # fmt: skip
        return f"{round(r.sync_offset_frames, 2) + 0.0:+.2f} frames{ms}"  # + 0.0: no "-0.00"

    parts = ["<!doctype html><meta charset='utf-8'><title>Calibration report</title>",
             "<style>body{font-family:sans-serif} td,th{padding:2px 8px;text-align:right}"
             " .cam{display:inline-block;vertical-align:top;margin:8px}</style>",
             "<h1>Calibration report</h1><table><tr><th>camera</th><th>frames</th>"
             "<th>with the board</th><th>views for intrinsics</th><th>intrinsic RMS</th>"
             "<th>BA RMS</th><th>time offset</th><th>problem</th></tr>"]  # fmt: skip
    for r in calibration.reports:
        parts.append(
            f"<tr><td>{html.escape(r.name)}</td><td>{r.frames}</td><td>{r.board_frames}</td>"
            f"<td>{r.intrinsic_views}</td><td>{num(r.intrinsic_rms, ' px')}</td>"
            f"<td>{num(r.ba_rms, ' px')}</td><td>{offset(r)}</td>"
            f"<td>{html.escape(r.problem or '')}</td></tr>"
        )
    parts.append("</table><h2>Board corners over each image</h2>")
    for c, r in enumerate(calibration.reports):
        mine = [k for k, v in enumerate(calibration.views) if v.camera == c]
        svg = coverage_svg([calibration.views[k] for k in mine],
                           [calibration.residuals[k] for k in mine], r.image_size)  # fmt: skip
        parts.append(f"<div class='cam'><h3>{html.escape(r.name)}</h3>{svg}</div>")
    with atomic_write(path, "w") as fh:
        fh.write("\n".join(parts) + "\n")
