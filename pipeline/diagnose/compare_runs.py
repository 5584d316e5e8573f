"""Whole-run A/B: two complete configurations of one scene, compared side by side.

Each side is a full run (every stage, the whole sequence), read from the scene's cache
when that configuration was run before (:func:`run_cached`: the file ``mvviz run``
writes, or one file per configuration in ``SCENE/.mvviz/runs/``). The comparison has
two parts:

- the per-stage figures of each run (:func:`run_figures`, from
  :func:`pipeline.evaluation.evaluate.evaluate`: association precision / recall, tracks, ID
  switches, MPJPE / PCK / PCP / acceleration error per stage where there is ground
  truth, reprojection per camera, the SMPL fits' residual), as rows ``(name, a, b)``;
- where the two runs put people differently (:func:`differences`): per frame, A's
  people (the configured filter's joints of each track present) are matched one-to-one
  to B's by mean joint distance (a track that B splits or renumbers still matches); a
  matched pair farther apart than ``min_mm`` over consecutive frames is one span, a
  person only one run has is another, and the spans are ranked (largest distance first,
  then the longest ones only one run has).

Matching per frame rather than track to track keeps the distance about *where* the
runs put a person, which is what the viewer shows; a change of identity is counted by
the ID switches of the figures.

Units: mm, frames, pixels.
"""

from __future__ import annotations

import math
import os
import shlex
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from pipeline.config import PipelineConfig
from pipeline.core.assignment import gated_assignment
from pipeline.core.files import SceneFormatError, scene_cache_dir
from pipeline.core.progress import Progress
from pipeline.data.scene import Scene
from pipeline.evaluation.evaluate import evaluate
from pipeline.evaluation.metrics import MATCH_GATE_MM
from pipeline.results.store import PipelineResults, cache_key, default_results_path, load_results
from pipeline.run.pipeline import run_or_load

RUNS_DIR = "runs"  # SCENE/.mvviz/runs/results_<cache key>.npz, one per configuration
MIN_DIFF_MM = 20.0
"""Two runs' joints of one person closer than this (mean over joints) are "the same":
a few times the detector noise a triangulated joint keeps (~5-10 mm on the samples)."""
MERGE_GAP = 2  # spans of one person this many frames apart are one span

if TYPE_CHECKING:
    from pipeline.body.arrays import BodyModelData
    from pipeline.body.model import BodyModel


def run_cached(
    scene: Scene,
    config: PipelineConfig,
    model: BodyModel | BodyModelData,
    *,
    progress: Progress = True,
    force: bool = False,
) -> tuple[PipelineResults, bool, Path]:
    """The complete run of ``config`` on ``scene``: the cached one if that configuration
    (same scene files, config, body model, prior and code: ``results.cache_key``) was run
    before, else run and saved. Returns (results, reused, file)."""
    key = cache_key(scene, config, model)
    keyed = scene_cache_dir(scene.root) / RUNS_DIR / f"results_{key}.npz"
    default = default_results_path(scene)
    if not force and not keyed.is_file() and default.is_file():
        try:  # what `mvviz run` or the viewer left there, if it is this configuration
            res = load_results(default, model=model)
            if res.cache_key == key:
                return res, True, default
        except SceneFormatError:
            pass
    res, cached = run_or_load(scene, config, model, out=keyed, progress=progress, force=force)
    return res, cached, keyed


# --------------------------------------------------------------------------- figures


def run_figures(scene: Scene, results: PipelineResults) -> dict[str, float]:
    """One run's figures by name, in display order (NaN where not measurable; the pose
    rows only with ground truth, association only with ``gt_person_id``)."""
    ev = evaluate(scene, results)
    out: dict[str, float] = {}
    for k in ("precision", "recall"):
        if k in ev.association:
            out[f"association {k}"] = float(ev.association[k])
    out["people per frame"] = len(results.person_frame) / max(results.num_frames, 1)
    out["tracks"] = float(results.num_tracks)
    if scene.gt is not None:
        out["ID switches"] = float(len(ev.id_switch_events))
    for stage, m in ev.stages.items():
        out[f"{stage} MPJPE mm"] = m["mpjpe"]
        out[f"{stage} PCK@160"] = m["pck"]
        out[f"{stage} PCP"] = m["pcp"]
        out[f"{stage} accel error mm"] = m["accel"]
    for name, px in zip(scene.rig.names, ev.reprojection_view_mean, strict=True):
        out[f"reprojection {name} px"] = float(px)
    for name in ("smpl", "smpl_vae"):
        fit = getattr(results, name)
        if fit is not None and np.isfinite(fit.residual).any():
            out[f"{name} fit residual mm"] = float(np.nanmedian(fit.residual))
    return {k: float(v) for k, v in out.items()}


# --------------------------------------------------------------------------- where


@dataclass(frozen=True)
class Difference:
    """A span of frames where the runs disagree about one person.

    ``kind``: ``"moved"`` (both have the person, ``peak_mm`` apart at ``peak_frame``),
    ``"only in A"`` / ``"only in B"`` (one run has no one within the match gate there;
    ``peak_mm`` is NaN). ``track_a`` / ``track_b``: the person's track in each run at
    ``peak_frame`` (-1: none). Frames ``start``..``stop`` inclusive."""

    kind: str
    track_a: int
    track_b: int
    start: int
    stop: int
    peak_frame: int
    peak_mm: float
    mean_mm: float
    unmeasured_a: int = 0  # frames of the span where A's track has no triangulation
    unmeasured_b: int = 0  # (the filter coasts there: a gap, where runs drift apart)

    @property
    def frames(self) -> int:
        return self.stop - self.start + 1

    def to_dict(self) -> dict:
        r = lambda x: None if not math.isfinite(x) else round(float(x), 1)  # noqa: E731
        return {
            "kind": self.kind, "track_a": self.track_a, "track_b": self.track_b,
            "start": self.start, "stop": self.stop, "peak_frame": self.peak_frame,
            "peak_mm": r(self.peak_mm), "mean_mm": r(self.mean_mm),
            "unmeasured_a": self.unmeasured_a, "unmeasured_b": self.unmeasured_b,
        }  # fmt: skip


@dataclass(frozen=True, eq=False)
class FrameMatch:
    """Per frame, A's tracks matched to B's.

    Attributes:
        partner: (F, K_a) int, B's track matched to each present A track (-1: none, or
            A's track absent).
        distance: (F, K_a) mm, mean joint distance to that partner (NaN without one).
        a_present: (F, K_a) bool; b_unmatched: (F, K_b) bool, B's present tracks no A
            track matched.
    """

    partner: np.ndarray
    distance: np.ndarray
    a_present: np.ndarray
    b_unmatched: np.ndarray


def _present(points: np.ndarray) -> np.ndarray:
    """(F, K) tracks with at least one finite joint; ``points`` (K, F, J, 3)."""
    return np.isfinite(points).all(-1).any(-1).T


def match_frames(a: np.ndarray, b: np.ndarray, *, gate_mm: float = MATCH_GATE_MM) -> FrameMatch:
    """Match A's people to B's in every frame (:class:`FrameMatch`).

    Args:
        a: (K_a, F, J, 3), b: (K_b, F, J, 3) each run's track joints, mm, NaN = absent.
    """
    F = a.shape[1]
    pa, pb = _present(a), _present(b)
    partner = np.full(pa.shape, -1)
    distance = np.full(pa.shape, np.nan)
    b_unmatched = pb.copy()
    for f in range(F):
        ka, kb = np.flatnonzero(pa[f]), np.flatnonzero(pb[f])
        if not len(ka) or not len(kb):
            continue
        d = np.linalg.norm(a[ka, f][:, None] - b[kb, f][None], axis=-1)  # (A, B, J)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # no joint both have: NaN
            cost = np.nanmean(d, axis=-1)
        cost = np.where(cost < gate_mm, cost, np.inf)
        ia, ib = gated_assignment(cost)
        partner[f, ka[ia]] = kb[ib]
        distance[f, ka[ia]] = cost[ia, ib]
        b_unmatched[f, kb[ib]] = False
    return FrameMatch(partner, distance, pa, b_unmatched)


def _spans(mask: np.ndarray, gap: int) -> list[tuple[int, int]]:
    """Runs of True in (F,) ``mask`` as (start, stop) inclusive, runs at most ``gap``
    frames apart merged."""
    idx = np.flatnonzero(mask)
    if not len(idx):
        return []
    cuts = np.flatnonzero(np.diff(idx) > gap + 1)
    starts = np.r_[idx[0], idx[cuts + 1]]
    stops = np.r_[idx[cuts], idx[-1]]
    return list(zip(starts.tolist(), stops.tolist(), strict=True))


def differences(
    a: np.ndarray,
    b: np.ndarray,
    *,
    min_mm: float = MIN_DIFF_MM,
    gap: int = MERGE_GAP,
    measured_a: np.ndarray | None = None,
    measured_b: np.ndarray | None = None,
) -> tuple[list[Difference], FrameMatch]:
    """Where A and B put people differently (see the module docstring), ranked: the
    ``moved`` spans by their peak distance, then the one-run-only spans by length.

    Args:
        a: (K_a, F, J, 3), b: (K_b, F, J, 3) track joints, mm.
        measured_a, measured_b: (K, F) bool, frames each track was triangulated in
            (default: all): the spans count the frames their filter coasted.
    """
    m = match_frames(a, b)
    ma = _present(a).T if measured_a is None else measured_a
    mb = _present(b).T if measured_b is None else measured_b
    moved, alone = [], []
    for k in range(a.shape[0]):
        d = m.distance[:, k]
        for s, e in _spans(np.nan_to_num(d, nan=0.0) > min_mm, gap):
            seg = d[s : e + 1]
            f = s + int(np.nanargmax(seg))
            kb = m.partner[s : e + 1, k]
            coast_b = int(sum(not mb[j, s + i] for i, j in enumerate(kb) if j >= 0))
            moved.append(Difference("moved", k, int(m.partner[f, k]), s, e, f,
                                    float(np.nanmax(seg)), float(np.nanmean(seg)),
                                    int((~ma[k, s : e + 1]).sum()), coast_b))  # fmt: skip
        lone = m.a_present[:, k] & (m.partner[:, k] < 0)
        for s, e in _spans(lone, gap):
            alone.append(Difference("only in A", k, -1, s, e, s, math.nan, math.nan))
    for k in range(b.shape[0]):
        for s, e in _spans(m.b_unmatched[:, k], gap):
            alone.append(Difference("only in B", -1, k, s, e, s, math.nan, math.nan))
    moved.sort(key=lambda x: -x.peak_mm)
    alone.sort(key=lambda x: (-x.frames, x.start))
    return moved + alone, m


# --------------------------------------------------------------------------- together


@dataclass(frozen=True, eq=False)
class RunComparison:
    """Runs A and B of one scene compared. ``rows``: (name, A, B) figures;
    ``differences``: ranked spans (:func:`differences`); ``distance``: (F, K_a) mm per
    frame from each of A's tracks to its match in B."""

    config_a: PipelineConfig
    config_b: PipelineConfig
    rows: list[tuple[str, float, float]]
    differences: list[Difference]
    distance: np.ndarray
    config_changes: list[tuple[str, object, object]]

    def top(self, n: int) -> list[Difference]:
        """The ``n`` largest moved spans and the ``n`` longest one-run-only spans."""
        moved = [d for d in self.differences if d.kind == "moved"][:n]
        alone = [d for d in self.differences if d.kind != "moved"][:n]
        return moved + alone

    def to_json(self, *, top: int = 10) -> dict:
        fin = lambda x: None if not math.isfinite(x) else x  # noqa: E731
        frames = np.isfinite(self.distance)
        return {
            "config_changes": [{"field": k, "a": a, "b": b} for k, a, b in self.config_changes],
            "figures": {name: {"a": fin(a), "b": fin(b)} for name, a, b in self.rows},
            "distance_mm": {
                "median": fin(float(np.nanmedian(self.distance))) if frames.any() else None,
                "max": fin(float(np.nanmax(self.distance))) if frames.any() else None,
                "person_frames_matched": int(frames.sum()),
            },
            "differences": [d.to_dict() for d in self.top(top)],
            "num_differences": {
                k: sum(d.kind == k for d in self.differences)
                for k in ("moved", "only in A", "only in B")
            },
        }


def config_changes(a: PipelineConfig, b: PipelineConfig) -> list[tuple[str, object, object]]:
    """The fields (dotted names) whose values differ between ``a`` and ``b``."""
    out: list[tuple[str, object, object]] = []

    def walk(x: dict, y: dict, prefix: str) -> None:
        for k in sorted(set(x) | set(y)):
            u, v = x.get(k), y.get(k)
            if isinstance(u, dict) and isinstance(v, dict) and k != "offsets":
                walk(u, v, f"{prefix}{k}.")
            elif u != v:
                out.append((prefix + k, u, v))

    walk(a.to_dict(), b.to_dict(), "")
    return out


def compare_runs(
    scene: Scene,
    a: PipelineResults,
    b: PipelineResults,
    *,
    min_mm: float = MIN_DIFF_MM,
) -> RunComparison:
    """A and B side by side (figures) and where they differ (filtered joints)."""
    fa, fb = run_figures(scene, a), run_figures(scene, b)
    names = list(fa) + [k for k in fb if k not in fa]
    rows = [(k, fa.get(k, math.nan), fb.get(k, math.nan)) for k in names]
    diffs, match = differences(
        a.track_filtered, b.track_filtered, min_mm=min_mm,
        measured_a=_present(a.track_raw).T, measured_b=_present(b.track_raw).T,
    )  # fmt: skip
    return RunComparison(
        config_a=a.config, config_b=b.config, rows=rows, differences=diffs,
        distance=match.distance, config_changes=config_changes(a.config, b.config),
    )  # fmt: skip


def view_command(
    scene_root: str | os.PathLike, d: Difference, *, config_args: list[str] = ()
) -> str:
    """The command that opens the viewer at ``d`` (run A's config, its track selected)."""
    parts = ["mvviz", "view", str(scene_root), *config_args, "--frame", str(d.peak_frame)]
    if d.track_a >= 0:
        parts += ["--track", str(d.track_a)]
    return shlex.join(parts)
