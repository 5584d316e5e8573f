"""The ``protocol`` criterion: the limbs the Shelf / Campus protocol counts wrong, on the
filtered tracks, against the truth the scene stores (``mvviz convert --protocol-gt``);
and the per-actor PCP the failure panel shows beside them."""

from __future__ import annotations

from mvviz.analysis.failures.entries import Failure
from pipeline.data.joint_sets import get_joint_set
from pipeline.data.scene import Scene
from pipeline.evaluation.protocol import (
    PROTOCOL_TRUTH_FILE,
    estimates_by_frame,
    load_scene_protocol,
    score_protocol,
    wrong_limbs,
)
from pipeline.results.store import PipelineResults


def has_protocol(scene: Scene) -> bool:
    """Whether the scene stores a protocol truth (the file is read only when it is used)."""
    return (scene.root / PROTOCOL_TRUTH_FILE).is_file()


def protocol_failures(scene: Scene, results: PipelineResults) -> list[Failure]:
    """One entry per wrong limb and frame (merged into spans by the review), scored by
    its end points' mean error over the protocol's limit (half the limb's true length);
    an actor with no estimate scores 10."""
    stored = load_scene_protocol(scene.root)
    if stored is None or results.num_tracks == 0:
        return []
    protocol, truth = stored
    js = get_joint_set(results.joint_set)
    out = []
    for w in wrong_limbs(results.track_filtered, js, truth):
        missing = w.track < 0
        score = 10.0 if missing else w.error_mm / max(w.limit_mm, 1e-9)
        detail = (
            f"no estimate in this frame ({protocol})" if missing
            else f"off by {w.error_mm:.0f} mm (limit {w.limit_mm:.0f} mm, half its true "
            f"length; {protocol})"
        )  # fmt: skip
        where = f"actor {w.actor + 1} · " + ("no track" if missing else f"track {w.track}")
        out.append(Failure(
            criterion="protocol", score=score, frame=w.frame,
            track=None if missing else w.track, joint=None, view=None,
            where=f"{where} · {w.limb}", detail=detail, kind=w.limb, value=w.error_mm,
        ))  # fmt: skip
    return out


def protocol_summary(scene: Scene, results: PipelineResults) -> str:
    """``"**shelf PCP** (filtered): actor 1 99.7 % · actor 3 96.3 % · average 98.0 %"``
    (markdown), or "" without a stored truth."""
    stored = load_scene_protocol(scene.root)
    if stored is None or results.num_tracks == 0:
        return ""
    protocol, truth = stored
    estimates = estimates_by_frame(results.track_filtered, get_joint_set(results.joint_set))
    s = score_protocol(estimates, truth)
    actors = " · ".join(f"actor {a + 1} {100 * v:.1f} %" for a, v in s.per_actor.items())
    return f"**{protocol} PCP** (filtered): {actors} · average {100 * s.average:.1f} %"
