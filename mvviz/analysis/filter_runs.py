"""Kalman filter runs over a whole sequence, tracks first: filter A (the results' own
arrays) and re-filters with other parameters (the Filter A/B panel's B), as one data
class, :class:`FilterRun`, that the panel, its trace plot and the live rerun export read.

Units: millimetres and frames, as in the results. Pure: no GUI, no viewer state.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from pipeline.results.store import PipelineResults
from pipeline.stages.kalman import KalmanParams, kalman_filter


@dataclass(frozen=True, eq=False)
class FilterRun:
    """One filter over the whole sequence, tracks first. K tracks, F frames, J joints; mm."""

    params: KalmanParams
    forward: np.ndarray  # (K, F, J, 3) forward posterior mean
    smoothed: np.ndarray  # (K, F, J, 3) RTS
    prior: np.ndarray  # (K, F, J, 3) predicted mean before each update
    innovation: np.ndarray  # (K, F, J, 3)
    mahalanobis: np.ndarray  # (K, F, J)
    rejected: np.ndarray  # (K, F, J) bool, measurement rejected by the gate

    @property
    def shown(self) -> np.ndarray:
        """(K, F, J, 3) the configured output: smoothed if ``params.smoother``."""
        return self.smoothed if self.params.smoother else self.forward


RUN_FIELDS = {  # FilterRun field -> FilterResult field
    "forward": "forward", "smoothed": "filtered", "prior": "prior_mean",
    "innovation": "innovation", "mahalanobis": "mahalanobis", "rejected": "rejected",
}  # fmt: skip
BLOCK_STEPS = 1 << 17  # frames x joints x tracks filtered at once (see below)


def run_filter(
    track_raw: np.ndarray, params: KalmanParams, *, skip: np.ndarray | None = None
) -> FilterRun:
    """Filter ``track_raw`` (K, F, J, 3) mm as the pipeline does (forward and RTS at once),
    not taking the measurements ``skip`` (K, F, J) marks (the results' ``track_contradicted``).

    Over blocks of tracks: every joint trajectory is filtered on its own, so the numbers
    are those of one call, but the filter's ~25 (F, tracks x J, 3) working arrays are a
    block's (at 10,000 frames x 20 tracks, ~2 GB for all tracks at once)."""
    if track_raw.ndim != 4 or track_raw.shape[-1] != 3:
        raise ValueError(f"track_raw must be (num_tracks, num_frames, J, 3), got {track_raw.shape}")
    K, F, J = track_raw.shape[:3]
    block = max(1, BLOCK_STEPS // max(F * J, 1))
    smooth = dataclasses.replace(params, smoother=True)
    out: dict[str, np.ndarray] = {}
    for k0 in range(0, max(K, 1), block):
        raw = np.asarray(track_raw[k0 : k0 + block], float)
        skipped = None if skip is None else np.moveaxis(np.asarray(skip[k0 : k0 + block]), 1, 0)
        fr = kalman_filter(np.moveaxis(raw, 1, 0), smooth, skip=skipped)
        for name, field in RUN_FIELDS.items():
            a = np.moveaxis(getattr(fr, field), 0, 1)  # (F, k, ...) -> (k, F, ...)
            if name not in out:
                out[name] = np.empty((K, *a.shape[1:]), a.dtype)
            out[name][k0 : k0 + block] = a
    return FilterRun(params=params, **out)


def results_run(results: PipelineResults) -> FilterRun:
    """Filter A: the results' own arrays."""
    return FilterRun(
        params=results.config.kalman,
        forward=results.track_forward,
        smoothed=results.track_smoothed,
        prior=results.track_prior,
        innovation=results.track_innovation,
        mahalanobis=results.track_mahalanobis,
        rejected=results.track_rejected,
    )


def with_filter(results: PipelineResults, run: FilterRun) -> PipelineResults:
    """``results`` with ``run``'s arrays and parameters as its Kalman stage."""
    return dataclasses.replace(
        results,
        track_forward=run.forward,
        track_smoothed=run.smoothed,
        track_prior=run.prior,
        track_innovation=run.innovation,
        track_mahalanobis=run.mahalanobis,
        track_rejected=run.rejected,
        config=dataclasses.replace(results.config, kalman=run.params),
        cache_key="",  # no longer what a pipeline run with the old key produced
    )
