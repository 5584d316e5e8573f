"""All diagnoses of one run, composed in one place: what ``mvviz diagnose`` prints and
writes as JSON (``{"sync": {CAMERA: ...}, "calibration": {CAMERA: ...}, "floor": ...}``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

from pipeline.core.progress import ProgressFn
from pipeline.data.scene import Scene
from pipeline.diagnose.calibration import CalibrationFinding
from pipeline.diagnose.floor import FloorEstimate, estimate_floor
from pipeline.diagnose.in_sync import check_calibration_in_sync
from pipeline.diagnose.sync import MAX_SHIFT, SyncEstimate, estimate_offsets, offsets_over_windows
from pipeline.results.store import PipelineResults


@dataclass(frozen=True, eq=False)
class Diagnosis:
    sync: dict[str, SyncEstimate]
    calibration: dict[str, CalibrationFinding]
    floor: FloorEstimate | None
    sync_windows: list = field(default_factory=list)  # (start, stop, {camera: SyncEstimate})
    # The run the calibration was judged on: the given one, or it re-timed by the
    # confident sync offsets (pipeline.diagnose.in_sync); None when not known.
    calibration_run: PipelineResults | None = None
    sync_without: tuple[str, ...] = ()  # calibration suspects left out of sync's references

    @property
    def retimed(self) -> dict[str, float]:
        """Camera -> the offset (frames) its 2D was re-timed by before the calibration
        check judged it (empty: judged as recorded)."""
        c = self.calibration
        return {n: f.retimed_by_frames for n, f in c.items() if f.retimed_by_frames}

    def to_json(self) -> dict:
        out = {
            "sync": {k: e.to_dict() for k, e in self.sync.items()},
            "calibration": {k: f.to_dict() for k, f in self.calibration.items()},
            "floor": None if self.floor is None else self.floor.to_dict(),
        }
        if self.sync_without:
            out["sync_reference_exclude"] = list(self.sync_without)
        if self.retimed:  # the calibration was judged on the run re-timed by these
            out["calibration_retimed_by_frames"] = {
                k: round(v, 3) for k, v in self.retimed.items()
            }  # fmt: skip
        if self.sync_windows:
            out["sync_windows"] = [
                {"start": a, "stop": b, "offset_frames": {
                    k: round(e.offset_frames, 3) for k, e in est.items()}}
                for a, b, est in self.sync_windows
            ]  # fmt: skip
        return out

    def lines(self) -> list[str]:
        """The findings for a person: one line per camera and check, problems marked."""
        out = ["sync (positive: the camera's frames lag the others):"]
        for name, e in self.sync.items():
            verdict = (
                "LATE" if e.offset and e.offset_frames > 0
                else "EARLY" if e.offset
                else "in sync" if e.trusted
                else "cannot tell (too little motion or too few views)"
            )  # fmt: skip
            out.append(
                f"  {name:>10}: {e.offset_frames:+6.2f} frames +- {e.offset_std_frames:.2f}"
                f" (confidence {e.confidence:.2f}; residual {e.residual_zero_px:.1f} px as"
                f" recorded, {e.residual_best_px:.1f} px shifted)  {verdict}"
            )
        if self.sync_without:
            out.append(
                f"  (estimated again with the calibration suspects {', '.join(self.sync_without)}"
                " left out of the references)"
            )
        for a, b, est in self.sync_windows:
            offs = ", ".join(f"{k} {e.offset_frames:+.2f}" for k, e in est.items())
            out.append(f"  frames {a}-{b - 1}: {offs}")
        out.append("calibration (each camera against the joints the others triangulate):")
        if self.retimed:
            offs = ", ".join(f"{k} {v:+.2f}" for k, v in self.retimed.items())
            out.append(f"  (judged with the sync offsets found applied: {offs})")
        for name, f in self.calibration.items():
            line = (
                f"  {name:>10}: residual {f.residual_px:.1f} px, systematic "
                f"{f.systematic_px:.1f} px (others {f.others_systematic_px:.1f})"
            )
            if f.out_of_sync:
                line += (
                    f"  OUT OF SYNC, not miscalibrated: {f.systematic_as_recorded_px:.1f} px"
                    f" as recorded, {f.systematic_px:.1f} px re-timed by"
                    f" {f.retimed_by_frames:+.2f} frames"
                )
            if f.suspect:
                line += (
                    f"  SUSPECT: off by {f.rotation_error_deg:.2f} deg / "
                    f"{f.translation_error_mm:.0f} mm; refined: {f.residual_after_px:.1f} px"
                )
            if f.step is not None:
                line += (
                    f"  MOVED at frame {f.step.frame} ({f.step.before_px:.1f} -> "
                    f"{f.step.after_px:.1f} px)"
                )
            out.append(line)
        if self.floor is None:
            out.append("floor: cannot tell (no tracks with shoulders and ankles)")
        else:
            f = self.floor
            state = "ok" if f.ok else "NOT z-up with the floor at 0"
            out.append(
                f"floor ({f.method}, {f.points} samples): up {f.up.round(3).tolist()}, "
                f"{f.angle_to_z_deg:.1f} deg from +z, floor at {f.height_mm:.0f} mm: {state}"
            )
        return out


def diagnose(
    scene: Scene,
    results: PipelineResults,
    *,
    max_shift: int = MAX_SHIFT,
    window: int | None = None,
    refine: bool = True,
    refine_focal: bool = False,
    progress: ProgressFn | None = None,
    cancelled: Callable[[], bool] | None = None,
) -> Diagnosis | None:
    """Sync, calibration and floor of one run (``window``: also sync per window).

    ``progress(step, done, total)`` is called as each step starts ("sync", "sync windows",
    "calibration", "floor") and once at the end; ``cancelled()`` is asked between steps
    (the viewer's Diagnose panel): true returns None."""
    steps = ["sync"] + (["sync windows"] if window else []) + ["calibration", "floor"]

    def start(step: str) -> bool:
        if cancelled is not None and cancelled():
            return False
        if progress is not None:
            progress(step, steps.index(step), len(steps))
        return True

    if not start("sync"):
        return None
    sync = estimate_offsets(scene, results, max_shift=max_shift)
    windows = []
    if window:
        if not start("sync windows"):
            return None
        windows = offsets_over_windows(scene, results, window=window, max_shift=max_shift)
    if not start("calibration"):
        return None
    judged = check_calibration_in_sync(
        scene, results, sync, refine=refine, refine_focal=refine_focal, max_shift=max_shift,
        cancelled=cancelled,
    )  # fmt: skip
    if judged is None:
        return None
    if not start("floor"):
        return None
    floor = estimate_floor(results.track_smoothed, scene.joint_set.names)
    if progress is not None:
        progress("done", len(steps), len(steps))
    return Diagnosis(
        sync=judged.sync, calibration=judged.findings, floor=floor, sync_windows=windows,
        calibration_run=judged.run, sync_without=judged.sync_without,
    )  # fmt: skip
