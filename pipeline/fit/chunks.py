"""The SMPL fit of a long sequence in chunks of frames, each warm-started by the last.

:func:`pipeline.fit.smpl.fit_sequence` fits all person-frames in one batch: its autograd
graph and its (N, 24, 3, 3) tensors grow with the sequence (10,000 frames x 20 people
is 200,000 rows). :func:`fit_in_chunks` fits ``chunk_frames`` frames at a time; chunk
``c`` covers frames ``[c C - overlap, (c + 1) C)``:

* its ``overlap`` first frames start from the previous chunk's fit of them (pose and
  translation), so the smoothness term sees the trajectory go on across the seam;
* a track the previous chunks saw keeps their betas and keypoint offsets (held, not
  re-learnt: every frame of a track is one body); a track new in the chunk learns its
  own from phase 0, as in the whole-sequence fit;
* frames ``[c C, (c + 1) C)`` of its result are kept (the overlap's refit is dropped).

With the VAE prior, each chunk is corrected after its step I (the correction's
smoothness term sees the chunk's own frames). Memory beyond the output arrays is one
chunk's; person-frames per second equal the batch fit's at chunks of >= ~1,000 rows
(bench/bench_fit.py --chunk).
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import numpy as np

from pipeline.core.progress import Progress, StageBar
from pipeline.core.torch_threads import torch_threads
from pipeline.fit.smpl import FitParams, SmplFit, WarmStart, _check_tracks, _fit, keypoint_buffers

if TYPE_CHECKING:
    from pipeline.body.model import BodyModel
    from pipeline.fit.prior import PosePrior

PER_FRAME = ("pose_rotvecs", "transl", "joints", "keypoints", "residual")  # (K, F, ...)


def _blank(fit: SmplFit, num_frames: int) -> dict[str, np.ndarray]:
    """NaN (K, num_frames, ...) arrays shaped like ``fit``'s per-frame fields."""
    return {
        k: np.full((fit.betas.shape[0], num_frames) + getattr(fit, k).shape[2:], np.nan)
        for k in PER_FRAME
    }


def fit_in_chunks(
    tracks_mm: np.ndarray,
    joint_set: str,
    model: BodyModel,
    *,
    prior: PosePrior | None = None,
    params: FitParams = FitParams(),  # noqa: B008  (frozen dataclass)
    chunk_frames: int = 200,
    overlap: int = 2,
    noise_mm: np.ndarray | None = None,
    progress: Progress = True,
) -> tuple[SmplFit, SmplFit | None]:
    """:func:`pipeline.fit.smpl.fit_sequence` in chunks of ``chunk_frames`` frames (module
    docstring). Same arguments and results; ``seconds`` is the sum over chunks."""
    if chunk_frames < 1 or not 0 <= overlap < chunk_frames:
        raise ValueError(
            f"need chunk_frames >= 1 and 0 <= overlap < chunk_frames, got {chunk_frames}, "
            f"{overlap}"
        )
    x = _check_tracks(tracks_mm, joint_set)
    K, F = x.shape[:2]
    buf = keypoint_buffers(model, joint_set)
    if params.limb_offsets:
        import torch

        buf = dataclasses.replace(buf, offset_mask=torch.as_tensor(buf.fitted, dtype=torch.float32))
    out: list[dict[str, np.ndarray] | None] = [None, None]
    # betas, offsets (mm), bone scales (None: the fit learns none)
    shape: list[tuple[np.ndarray, np.ndarray, np.ndarray | None] | None] = [None, None]
    last: list[SmplFit | None] = [None, None]
    seconds = [0.0, 0.0]
    starts = range(0, max(F, 1), chunk_frames)
    with torch_threads(params.num_threads), StageBar("SMPL fit (chunks)", len(starts),
                                                      progress, unit="chunk") as bar:  # fmt: skip
        for s in starts:
            e, ws = min(s + chunk_frames, F), max(s - overlap, 0)
            warm = None
            if shape[0] is not None:
                pose = np.full((K, e - ws, 24, 3), np.nan)
                transl = np.full((K, e - ws, 3), np.nan)
                pose[:, : s - ws] = out[0]["pose_rotvecs"][:, ws:s]
                transl[:, : s - ws] = out[0]["transl"][:, ws:s]
                warm = WarmStart(shape[0][0], shape[0][1], pose, transl, shape[0][2])
            fits = _fit(x[:, ws:e], buf, model, prior, params, None, False, warm, noise_mm)
            for i, fit in enumerate(fits):
                if fit is None:
                    continue
                if out[i] is None:
                    out[i] = _blank(fit, F)
                    scales = None if fit.bone_scales is None else fit.bone_scales.copy()
                    shape[i] = (fit.betas.copy(), fit.keypoint_offsets.copy(), scales)
                for k in PER_FRAME:
                    out[i][k][:, s:e] = getattr(fit, k)[:, s - ws :]
                if fit.prior_reverted is not None:
                    out[i].setdefault("prior_reverted", np.zeros((K, F), bool))
                    out[i]["prior_reverted"][:, s:e] = fit.prior_reverted[:, s - ws :]
                new = ~np.isfinite(shape[i][0]).all(1) & np.isfinite(fit.betas).all(1)
                shape[i][0][new], shape[i][1][new] = fit.betas[new], fit.keypoint_offsets[new]
                if shape[i][2] is not None and fit.bone_scales is not None:
                    shape[i][2][new] = fit.bone_scales[new]
                seconds[i] += fit.seconds
                last[i] = fit
            bar.update()
    results = []
    for i in range(2):
        if last[i] is None:
            results.append(None)
            continue
        results.append(
            dataclasses.replace(
                last[i], betas=shape[i][0], keypoint_offsets=shape[i][1],
                bone_scales=shape[i][2], seconds=seconds[i],
                **out[i],
            )  # fmt: skip
        )
    return results[0], results[1]
