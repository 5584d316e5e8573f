"""The body stages of a run: the step-I SMPL fit to the smoothed tracks and its
VAE-corrected version, on results the earlier stages packed.

torch and the fit's modules are imported only once a fit runs: loading cached results
never needs them.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import numpy as np

from pipeline.body.keypoints import FITTABLE_JOINT_SETS
from pipeline.config import PipelineConfig
from pipeline.core.progress import Progress
from pipeline.results.store import PipelineResults

if TYPE_CHECKING:
    from pipeline.body.arrays import BodyModelData
    from pipeline.body.model import BodyModel


# A sequence of more frames is fit in chunks (pipeline.fit.chunks): the batch fit's
# graph grows with the person-frames (10,000 frames x 20 people: 200,000 rows, GBs); chunks
# of 125 frames cost 0.03 mm of MPJPE on the 250-frame sample (7.36 -> 7.39), longer ones
# have fewer seams.
LONG_FIT_FRAMES = 1000
LONG_FIT_CHUNK_FRAMES = 500


def input_noise(results: PipelineResults) -> np.ndarray:
    """(K,) how far each track's raw joints lie from its RTS path, mm (median over its
    joints and frames; NaN for a track without both): the noise the fit's smoothness
    weight follows (``FitParams.smooth_reference_mm``)."""
    K = results.num_tracks
    out = np.full(K, np.nan)
    for k in range(K):
        d = np.linalg.norm(
            np.asarray(results.track_raw[k]) - np.asarray(results.track_smoothed[k]), axis=-1
        )
        d = d[np.isfinite(d)]
        if d.size:
            out[k] = float(np.median(d))
    return out


def fit_bodies(
    results: PipelineResults,
    config: PipelineConfig,
    model: BodyModel | BodyModelData,
    *,
    progress: Progress = True,
) -> PipelineResults:
    """Step I SMPL fit to the RTS-smoothed tracks, its VAE-corrected version, and the floor
    they are judged by (:mod:`pipeline.fit.floor`: how near the best skeleton of constant
    bone lengths comes to the same tracks).

    The fit is a batch over the whole sequence (its smoothness term looks at t - 1 and
    t + 1), so it takes the smoothed tracks whatever ``kalman.smoother`` shows as "the"
    filtered ones: the forward filter lags (on a mocap walk 15.3 mm where RTS is 11.0).
    A sequence of more than :data:`LONG_FIT_FRAMES` frames is fit in chunks of
    :data:`LONG_FIT_CHUNK_FRAMES`, each warm-started by the last."""
    fittable = results.joint_set in FITTABLE_JOINT_SETS
    if not config.fit_smpl or not fittable or results.num_tracks == 0:
        return results
    # torch (~3-7 s to import) only once a fit runs: loading cached results never needs it
    from pipeline.body.model import torch_body_model
    from pipeline.fit.prior import load_prior
    from pipeline.fit.smpl import fit_sequence

    prior = load_prior(config.pose_prior or None) if config.use_pose_prior else None
    fit, chunks = fit_sequence, {}
    if results.num_frames > LONG_FIT_FRAMES:
        from pipeline.fit.chunks import fit_in_chunks

        fit, chunks = fit_in_chunks, {"chunk_frames": LONG_FIT_CHUNK_FRAMES}
    fit_i, fit_vae = fit(
        results.track_smoothed,
        results.joint_set,
        torch_body_model(model),
        prior=prior,
        params=config.smpl_fit,
        noise_mm=input_noise(results),
        progress=progress,
        **chunks,
    )
    floor = None
    if config.smpl_fit.floor_iterations > 0:
        from pipeline.data.joint_sets import get_joint_set
        from pipeline.fit.floor import rigid_floor

        bones = np.array(get_joint_set(results.joint_set).bones)
        floor = rigid_floor(
            results.track_smoothed, bones, iterations=config.smpl_fit.floor_iterations,
            beta_m=config.smpl_fit.smooth_l1_beta_m, start_mm=fit_i.keypoints,
            progress=progress,
        ).distance  # fmt: skip
    return dataclasses.replace(results, smpl=fit_i, smpl_vae=fit_vae, fit_floor=floor)
