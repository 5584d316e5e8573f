"""Calibration judged in time: a late camera is out of sync, not miscalibrated.

A camera whose frames lag the others by a few frames sees every person where they were
a few frames ago: against the joints the other cameras triangulate *now* its residual is
as large and as systematic (people walk the same way through the same part of its image)
as a rotated camera's, and the calibration check alone would name it. So when the sync
estimate is confident about offsets, the stages are re-run with those cameras' 2D
re-timed (``sync.offsets``, as ``--set`` would apply them) and the calibration is judged
on that run. A camera that was a suspect as recorded and is not once re-timed is reported
*out of sync*: its residual was its time offset. A camera that is both late and off is
still a suspect, and its bundle adjustment works on 2D that is in time. The other way
round, a miscalibrated camera can hide another's offset (it is in that camera's sync
reference): the suspects are left out of the references and the offsets estimated again.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

from pipeline.config import SyncParams
from pipeline.data.scene import Scene
from pipeline.diagnose.calibration import CalibrationFinding, check_calibration
from pipeline.diagnose.sync import MAX_SHIFT, SyncEstimate, estimate_offsets
from pipeline.results.store import PipelineResults
from pipeline.run.frames import select_2d
from pipeline.run.pipeline import run_stages


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


@dataclass(frozen=True, eq=False)
class InSyncCalibration:
    """The calibration check judged in time (:func:`check_calibration_in_sync`)."""

    findings: dict[str, CalibrationFinding]
    run: PipelineResults  # the run judged: the given one, or it re-timed
    sync: dict[str, SyncEstimate]  # the sync estimate whose confident offsets were applied
    sync_without: tuple[str, ...] = ()  # calibration suspects left out of its references


def check_calibration_in_sync(
    scene: Scene,
    results: PipelineResults,
    sync: dict[str, SyncEstimate],
    *,
    refine: bool = True,
    refine_focal: bool = False,
    max_shift: int = MAX_SHIFT,
    cancelled: Callable[[], bool] | None = None,
) -> InSyncCalibration | None:
    """The calibration check on the run re-timed by ``sync``'s confident offsets (on
    ``results`` itself when there are none). Each re-timed camera's finding says by how
    much it was re-timed, its systematic residual as recorded, and whether it is out of
    sync rather than miscalibrated.

    A miscalibrated camera spoils the other cameras' sync references too (a late camera
    beside it can be missed): when the check names suspects, the offsets are estimated
    again with them left out of the references; if that finds a confident offset of a
    suspect the first estimate did not, and re-timed by it that camera is no longer a
    suspect, that estimate and its judgement are kept. The bundle adjustment runs once,
    on the final run. None if ``cancelled()``."""
    stop = lambda: cancelled is not None and cancelled()  # noqa: E731
    judged = _judge(scene, results, sync, cancelled)
    if judged is None:
        return None
    found, run = judged
    recorded = found if run is results else None
    without: tuple[str, ...] = ()
    suspects = tuple(k for k, f in found.items() if f.suspect)
    if suspects and not stop():
        left_out = frozenset(scene.rig.index_of(k) for k in suspects)
        again = estimate_offsets(scene, results, max_shift=max_shift, reference_exclude=left_out)
        new = set(confident_offsets(again)) - set(confident_offsets(sync))
        if new:
            retry = _judge(scene, results, again, cancelled)
            if retry is None:
                return None
            # Adopted only if it explains a suspect by time (a newly re-timed suspect is
            # one no longer): a small offset the thinner references find on their own
            # would otherwise re-time a camera that nothing was wrong with.
            if any(not retry[0][k].suspect for k in new & set(suspects)):
                sync, without = again, suspects
                found, run = retry
    if stop():
        return None
    if refine and any(f.suspect for f in found.values()):
        found = check_calibration(scene, run, refine=True, refine_focal=refine_focal)
    if run is not results:
        # As recorded, without the bundle adjustment (it would fit a pose to 2D of other
        # instants): only to say whether the time offset explains the residual.
        recorded = recorded or check_calibration(scene, results, refine=False)
        for name, d in confident_offsets(sync).items():
            f, before = found[name], recorded[name]
            found[name] = dataclasses.replace(
                f,
                retimed_by_frames=d,
                systematic_as_recorded_px=before.systematic_px,
                out_of_sync=before.suspect and not f.suspect,
            )
    return InSyncCalibration(found, run, sync, without)


def _judge(scene, results, sync, cancelled):
    """(findings without refinement, the run judged) on ``results`` re-timed by
    ``sync``'s confident offsets; None if cancelled."""
    offsets = confident_offsets(sync)
    run = results if not offsets else retimed_run(scene, results, offsets, cancelled=cancelled)
    if run is None or (cancelled is not None and cancelled()):
        return None
    return check_calibration(scene, run, refine=False), run
