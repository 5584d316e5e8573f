"""What the simulated detectors' users see, summed up per scene: the figures two ways of
synthesising a scene must agree on (bench/bench_synth.py, tests/pipeline/synth).

World mm, pixels.
"""

from __future__ import annotations

import numpy as np

from pipeline.data.cameras import CameraRig
from pipeline.data.scene import Detections
from pipeline.synth.detectors import DetectorNoise

__all__ = ["detection_statistics"]


def detection_statistics(
    rig: CameraRig, keypoints: np.ndarray, det: Detections, noise: DetectorNoise
) -> dict[str, float | np.ndarray]:
    """Per-scene statistics of simulated detections.

    Args:
        keypoints: (P, F, T, 3) the true keypoints, world mm (NaN where undefined).
        det: the detections of those people (``gt_person_id`` -1 for ghosts).
        noise: the detector model (its occlusion penalties set the low-confidence cut).
    Returns:
        scalars: ``detections_per_view_frame``, ``people_per_view_frame`` (true people
        reported), ``keypoints_detected`` (of the true keypoints inside the image, of the
        people reported), ``keypoints_low_confidence`` (of the detected: below
        ``confidence_visible - other_occlusion_penalty / 2``, mostly occluded ones),
        ``confidence_mean`` / ``_p10`` / ``_p50`` / ``_p90`` (detected true keypoints),
        ``error_px_median`` / ``_p90`` (against the true projection),
        ``ghosts_per_view_frame``; and ``missing_by_view`` (V,) the fraction of the
        in-image keypoints of reported people not detected, per view.
    """
    P, F = keypoints.shape[:2]
    V = len(rig)
    real = det.gt_person_id >= 0
    view = det.view[real]
    true = np.zeros((0, keypoints.shape[2], 2))
    if real.any():
        true = np.empty((int(real.sum()), keypoints.shape[2], 2))
        for v in np.unique(view):  # one projection per view
            rows = view == v
            pts = keypoints[det.gt_person_id[real][rows], det.frame[real][rows]]
            true[rows] = rig[int(v)].project(pts)
    k = det.keypoints[real]
    found = np.isfinite(k[..., 0]) & (k[..., 2] > 0)
    w, h = np.array([c.width for c in rig])[view], np.array([c.height for c in rig])[view]
    with np.errstate(invalid="ignore"):
        in_img = (
            np.isfinite(true).all(-1)
            & (true[..., 0] >= 0) & (true[..., 0] < w[:, None])
            & (true[..., 1] >= 0) & (true[..., 1] < h[:, None])
        )  # fmt: skip
    err = np.linalg.norm(k[..., :2] - true, axis=-1)[found]
    conf = k[..., 2][found]
    cut = noise.confidence_visible - noise.other_occlusion_penalty / 2
    in_per_view = np.bincount(view, in_img.sum(1), minlength=V)
    missed_per_view = np.bincount(view, (in_img & ~found).sum(1), minlength=V)

    def q(x: np.ndarray, p: float) -> float:
        return float(np.percentile(x, p)) if x.size else float("nan")

    return {
        "detections_per_view_frame": len(det.frame) / (F * V),
        "people_per_view_frame": float(real.sum()) / (F * V),
        "keypoints_detected": float((found & in_img).sum() / max(in_img.sum(), 1)),
        "keypoints_low_confidence": float((conf < cut).sum() / max(conf.size, 1)),
        "confidence_mean": float(conf.mean()) if conf.size else float("nan"),
        "confidence_p10": q(conf, 10),
        "confidence_p50": q(conf, 50),
        "confidence_p90": q(conf, 90),
        "error_px_median": q(err, 50),
        "error_px_p90": q(err, 90),
        "ghosts_per_view_frame": float((~real).sum()) / (F * V),
        "missing_by_view": missed_per_view / np.maximum(in_per_view, 1),
    }
