"""Why is this joint here: each view's part in one triangulated joint, from the results.

For a track, joint and frame, every camera's row: its 2D (the detection the run gave the
person, as it fed the stages), confidence, the distance of its ray to the triangulated
point, its weight in the solve, its reprojection residual and, when the view was not
used, why (camera disabled, no detection, confidence under the threshold, dropped as an
outlier, too few views). Nothing is re-solved: the point, residuals and used flags are
the results' (``person_joints``, ``person_reproj``, ``person_used``), the reasons follow
from the run's config the way :func:`pipeline.stages.triangulate.triangulate_people` applies it.

The weight: the triangulation solves in pixel units (each view's DLT rows scaled by
confidence x focal / depth, which turns its residual into confidence x pixel error), so
a view's pixel error weighs confidence^2 in the least squares; ``weight`` is that share
over the views used (sums to 1).

Units: pixels, millimetres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mvviz.scene.geometry import ViewerData


@dataclass(frozen=True)
class ViewRow:
    """One camera's part in a triangulated joint (NaN where it has none)."""

    camera: str
    u: float  # px, its 2D (NaN: no detection)
    v: float
    confidence: float
    ray_mm: float  # distance of the ray through (u, v) to the triangulated point
    weight: float  # share of the least-squares weight, 0 if not used
    residual_px: float  # the point reprojected minus (u, v)
    used: bool
    reason: str  # why it was not used ("" if used)


@dataclass(frozen=True)
class JointViews:
    track: int
    joint: str
    frame: int
    point_mm: np.ndarray  # (3,) the triangulated (raw) joint; NaN if none
    rows: tuple[ViewRow, ...]


def joint_views(data: ViewerData, track: int, joint: int, frame: int) -> JointViews | None:
    """Each view of ``track``'s ``joint`` at ``frame``; None when the track has no person
    there (nothing was triangulated)."""
    res, scene = data.results, data.scene
    if not (0 <= track < data.num_tracks and 0 <= frame < data.num_frames):
        return None
    q = int(data.track_person[track, frame])
    if q < 0 or not 0 <= joint < data.joint_set.num_joints:
        return None
    tp = res.config.triangulation
    X = res.person_joints[q, joint]
    used = res.person_used[q, joint]
    kp = np.full((len(scene.rig), 3), np.nan)
    rows = res.person_members[q]
    kp[rows >= 0] = res.det_joints2d[rows[rows >= 0], joint]
    conf = np.nan_to_num(kp[:, 2])
    w2 = np.where(used, conf**2, 0.0)
    share = w2 / w2.sum() if w2.sum() > 0 else w2
    n_ok = int((np.isfinite(kp[:, :2]).all(1) & (conf >= tp.min_confidence) & (conf > 0)).sum())
    # every view's ray at once, from the viewer's cached rays of the detection rows (one
    # undistortion per view and joint was ~3 ms a frame change at 31 cameras)
    ray = np.full(len(kp), np.nan)
    seen = np.flatnonzero((rows >= 0) & np.isfinite(kp[:, :2]).all(1))
    if len(seen) and np.isfinite(X).all():
        d = np.asarray(data.det_rays[rows[seen], joint], float)  # (n, 3) unit
        to_x = X - np.asarray(scene.rig.centers, float)[seen]
        s = np.maximum(np.einsum("nc,nc->n", to_x, d), 0.0)[:, None]
        ray[seen] = np.linalg.norm(to_x - s * d, axis=1)
    reproj = res.person_reproj[q, joint]
    out = []
    for v, cam in enumerate(scene.rig):
        reason = "" if used[v] else _why_unused(
            cam.name, rows[v], kp[v], reproj[v], X, n_ok, res.config
        )  # fmt: skip
        out.append(ViewRow(
            camera=cam.name, u=float(kp[v, 0]), v=float(kp[v, 1]), confidence=float(kp[v, 2]),
            ray_mm=float(ray[v]), weight=float(share[v]), residual_px=float(reproj[v]),
            used=bool(used[v]), reason=reason,
        ))  # fmt: skip
    return JointViews(track, data.joint_set.names[joint], frame, X.copy(), tuple(out))


def _why_unused(camera, row, kp, residual, X, n_ok, config) -> str:
    tp = config.triangulation
    if camera in config.disabled_views:
        return "camera disabled in the config"
    if row < 0:
        return "no detection of this person"
    if not np.isfinite(kp[:2]).all():
        return "joint not detected"
    if not (kp[2] >= tp.min_confidence and kp[2] > 0):
        return f"confidence {kp[2]:.2f} < {tp.min_confidence:g}"
    if not np.isfinite(X).all():
        return (
            f"too few views ({n_ok} < {tp.min_views})" if n_ok < tp.min_views else "rays parallel"
        )
    if np.isinf(residual):
        return "point behind the camera"
    return f"outlier: {residual:.1f} px > {tp.outlier_threshold_px:g} px, dropped"


def _num(x: float, fmt: str) -> str:
    return "—" if not np.isfinite(x) else format(x, fmt)


def joint_views_markdown(jv: JointViews | None) -> str:
    """The table the Selection tab shows under "Why is this joint here"."""
    if jv is None:
        return "_Why is this joint here: the selected track has no person in this frame._"
    head = (
        f"**Why is this joint here** · track {jv.track} · {jv.joint} · frame {jv.frame}\n\n"
        "| camera | 2D (px) | conf | ray (mm) | weight | resid. (px) | used |\n"
        "|---|---|---|---|---|---|---|"
    )
    lines = [head]
    for r in jv.rows:
        uv = "—" if not np.isfinite(r.u) else f"{r.u:.0f}, {r.v:.0f}"
        used = "yes" if r.used else f"**no**: {r.reason}"
        lines.append(
            f"| {r.camera} | {uv} | {_num(r.confidence, '.2f')} | {_num(r.ray_mm, '.0f')} | "
            f"{r.weight:.0%} | {_num(r.residual_px, '.1f')} | {used} |"
        )
    return "\n".join(lines)
