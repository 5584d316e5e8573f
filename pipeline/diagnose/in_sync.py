"""Calibration judged in time: a late camera is out of sync, not miscalibrated.

A camera whose frames lag the others by a few frames sees every person where they were
a few frames ago: against the joints the other cameras triangulate *now* its residual is
as large and as systematic (people walk the same way through the same part of its image)
as a rotated camera's, and the calibration check alone would name it. So when the sync
estimate is confident about offsets, the stages are re-run with those cameras' 2D
re-timed (``sync.offsets``, as ``--set`` would apply them) and the calibration is judged
on that run. A camera that was a suspect as recorded and is not once re-timed is reported
*out of sync*: its residual was its time offset. A camera that is both late and off is
still a suspect, and its bundle adjustment works on 2D that is in time.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

from pipeline.config import SyncParams
from pipeline.diagnose.calibration import CalibrationFinding, check_calibration
from pipeline.diagnose.sync import SyncEstimate
from pipeline.results import PipelineResults, run_stages
from pipeline.run import select_2d
from pipeline.scene import Scene


def confident_offsets(sync: dict[str, SyncEstimate]) -> dict[str, float]:
    """Camera -> offset (frames) of the trusted, non-zero offsets of a sync estimate."""
    return {name: float(e.offset_frames) for name, e in sync.items() if e.offset}


def retimed_run(
    scene: Scene,
    results: PipelineResults,
    offsets: dict[str, float],
    *,
    cancelled: Callable[[], bool] | None = None,
) -> PipelineResults | None:
    """The per-frame and sequence stages of ``results``' config re-run with ``offsets``
    added to its ``sync.offsets`` (no SMPL fit: the calibration check needs the people's
    joints and who was seen where, not bodies). None if ``cancelled()``."""
    total = results.config.sync.by_camera()
    for name, d in offsets.items():
        total[name] = total.get(name, 0.0) + d
    sync = SyncParams(offsets=tuple(sorted((k, v) for k, v in total.items() if v != 0)))
    config = dataclasses.replace(results.config, sync=sync, fit_smpl=False)
    joints2d = select_2d(scene, config, results.det_restored)
    return run_stages(
        scene, config, joints2d, restored=results.det_restored, cancelled=cancelled,
        progress=False,
    )  # fmt: skip


def check_calibration_in_sync(
    scene: Scene,
    results: PipelineResults,
    sync: dict[str, SyncEstimate],
    *,
    refine: bool = True,
    refine_focal: bool = False,
    cancelled: Callable[[], bool] | None = None,
) -> tuple[dict[str, CalibrationFinding], PipelineResults] | None:
    """The calibration check on the run re-timed by ``sync``'s confident offsets (on
    ``results`` itself when there are none), and the run it judged. Each re-timed
    camera's finding says by how much it was re-timed, its systematic residual as
    recorded, and whether it is out of sync rather than miscalibrated. None if
    ``cancelled()``."""
    offsets = confident_offsets(sync)
    if not offsets:
        return check_calibration(scene, results, refine=refine, refine_focal=refine_focal), results
    judged = retimed_run(scene, results, offsets, cancelled=cancelled)
    if judged is None or (cancelled is not None and cancelled()):
        return None
    # As recorded, without the bundle adjustment (it would fit a pose to 2D of other
    # instants): only to say whether the time offset explains the residual.
    recorded = check_calibration(scene, results, refine=False)
    found = check_calibration(scene, judged, refine=refine, refine_focal=refine_focal)
    for name, d in offsets.items():
        f, before = found[name], recorded[name]
        found[name] = dataclasses.replace(
            f,
            retimed_by_frames=d,
            systematic_as_recorded_px=before.systematic_px,
            out_of_sync=before.suspect and not f.suspect,
        )
    return found, judged
