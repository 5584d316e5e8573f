"""What the pose prior learns from: its training sources, the mixes held-out splits train
on, and the broadest mix, which is shipped (``sample_data/priors/pose_vae.pt``:
``train_on(sources_for())``).

Sources (:data:`SOURCE_NAMES`), each a :class:`PoseSource`: poses (N, 72) axis-angle and
the record that goes into a checkpoint's ``info["sources"]`` (file, frames, activities,
licence; :mod:`pipeline.prior.heldout` reads it back):

* ``library``: the synthetic motion library (:mod:`pipeline.synth.motion`: walk, reach,
  crouch, stand, wave, in equal parts) plus its perturbations inside the joint limits
  (:func:`pipeline.prior.training.default_training_poses`); generated, no licence needed.
* ``cmu``: the CMU 131 clips of ``sample_data/mocap/cmu131`` (131_01, 131_02 walking,
  131_03 hopping; real motion capture of one person), our body model fitted to their
  joints at 30 fps (:func:`pipeline.mocap.clips.bvh_training_poses`); CMU's terms (NOTICE).
* ``balancing``: the Pose2Sim balancing trial (``sample_data/pose2sim_balancing``: real
  video, real OpenPose 2D of one person balancing), the step-I SMPL poses
  the pipeline fits to its subject (no prior: a prior's output would be the prior
  learning from itself), 100 frames at 60 fps; stored in
  ``sample_data/mocap/pose2sim_balancing/balancing_trial_poses.npz`` by
  :func:`make_balancing_poses`; BSD-3-Clause.
* ``demo``: the Pose2Sim multi-person demo (``sample_data/pose2sim_demo``: real video,
  BlazePose 2D of two people, 100 frames at 60 fps), the step-I poses of both people the
  same way: one stands almost still (pelvis median speed 0.20 m/s, knees bent 16-19 deg
  on average), the other walks across (0.58 m/s) and lifts a leg; the only real source of
  someone standing upright (the CMU 131 subject stands and walks with the knees bent
  29-55 deg). ``sample_data/mocap/pose2sim_demo/demo_people_poses.npz`` by
  :func:`make_demo_poses`; BSD-3-Clause.

The real sources are few poses beside the library's 42,000, so :func:`mix_poses` repeats
each to at least ``min_real_poses`` (the record says how often: ``repeat``).
"""

from __future__ import annotations

import functools
import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.core.units import REPO_ROOT, SAMPLE_DATA
from pipeline.fit.prior import PosePrior
from pipeline.prior.training import default_training_poses, train_prior
from pipeline.synth.motion import LIBRARY_ACTIVITIES

CMU_DIR = SAMPLE_DATA / "mocap" / "cmu131"
BALANCING_DIR = SAMPLE_DATA / "mocap" / "pose2sim_balancing"
BALANCING_POSES = BALANCING_DIR / "balancing_trial_poses.npz"
DEMO_DIR = SAMPLE_DATA / "mocap" / "pose2sim_demo"
DEMO_POSES = DEMO_DIR / "demo_people_poses.npz"
DEMO_ACTIVITIES = ("stand", "walk")
SOURCE_NAMES = ("library", "cmu", "balancing", "demo")
CMU_CLIPS = {"131_01.bvh": ("walk",), "131_02.bvh": ("walk",), "131_03.bvh": ("hop",)}
BALANCING_LICENCE = (
    "BSD-3-Clause (Pose2Sim demo data, credited to @aaiaueil, Universite Gustave Eiffel; "
    "sample_data/pose2sim_balancing/NOTICE.txt)"
)
DEMO_LICENCE = (
    "BSD-3-Clause (Pose2Sim 0.10.49 Demo_MultiPerson; "
    "sample_data/pose2sim_demo/LICENSE-pose2sim.txt)"
)


@dataclass(frozen=True, eq=False)
class PoseSource:
    """Training poses of one source. N poses.

    Attributes:
        name: ``library``, ``cmu``, ``balancing`` or ``demo`` (:data:`SOURCE_NAMES`).
        poses: (N, 72) axis-angle, SMPL layout (root included, the prior ignores it).
        record: the checkpoint record (``file``, ``frames``, ``activities``, ``licence``;
            a recorded source also ``source_frames``, what :mod:`pipeline.prior.heldout` checks).
    """

    name: str
    poses: np.ndarray
    record: dict

    @property
    def real(self) -> bool:
        return self.name != "library"


def library_source(
    *, num_poses: int = 60000, seed: int = 0, kinds: tuple[str, ...] = LIBRARY_ACTIVITIES
) -> PoseSource:
    """The synthetic library of the activities ``kinds`` plus perturbations."""
    poses = default_training_poses(num_poses, seed=seed, kinds=tuple(kinds))
    return PoseSource(
        "library",
        poses,
        {
            "source": "library",
            "file": f"synthetic library ({num_poses} poses, seed {seed}) + perturbations",
            "frames": int(len(poses)),
            "activities": list(kinds),
            "activity": ", ".join(kinds) + " (pipeline/synth/motion.py)",
            "licence": "generated",
        },
    )


@functools.cache
def _bvh_poses(path: str) -> tuple[np.ndarray, dict]:
    from pipeline.mocap.clips import bvh_training_poses  # mocap imports smpl_fit

    poses, info, _ = bvh_training_poses(path)
    return poses, info


def cmu_source(clip: str) -> PoseSource:
    """One CMU 131 clip (``"131_01.bvh"``), fitted at 30 fps (cached per process)."""
    path = CMU_DIR / clip
    poses, info = _bvh_poses(str(path))
    rec = dict(info, source="cmu", file=str(path.relative_to(REPO_ROOT)))
    rec["activities"] = list(CMU_CLIPS[clip])
    return PoseSource("cmu", poses, rec)


def _fitted_pose_source(name: str, path: str | os.PathLike) -> PoseSource:
    """A source of fitted poses stored as ``poses`` (N, 72) and a JSON ``meta``."""
    path = Path(path)
    with np.load(path, allow_pickle=False) as z:
        poses = np.asarray(z["poses"], float)
        meta = json.loads(str(z["meta"]))
    rec = dict(meta, source=name, file=str(path.relative_to(REPO_ROOT)))
    rec.update(frames=int(len(poses)), source_frames=int(len(poses)))
    return PoseSource(name, poses, rec)


def balancing_source(path: str | os.PathLike = BALANCING_POSES) -> PoseSource:
    """The balancing trial's fitted poses (:func:`make_balancing_poses`)."""
    return _fitted_pose_source("balancing", path)


def demo_source(path: str | os.PathLike = DEMO_POSES) -> PoseSource:
    """Both people of the Pose2Sim demo, their fitted poses (:func:`make_demo_poses`)."""
    return _fitted_pose_source("demo", path)


def _step_one_fit(scene_dir: Path):
    """The scene and the pipeline's step-I SMPL fit of it (no prior: a prior's output would
    be the prior learning from itself)."""
    from pipeline.body.model import load_body_model  # heavy imports
    from pipeline.config import PipelineConfig
    from pipeline.data.scene import load_scene
    from pipeline.run.pipeline import run_pipeline

    scene = load_scene(scene_dir)
    results = run_pipeline(
        scene, PipelineConfig(use_pose_prior=False), load_body_model(), progress=False
    )
    return scene, results.smpl


def make_balancing_poses(
    scene_dir: str | os.PathLike = SAMPLE_DATA / "pose2sim_balancing",
    out: str | os.PathLike = BALANCING_POSES,
) -> Path:
    """Run the pipeline (no prior) on the balancing trial and store its subject's step-I
    poses as an AMASS-style npz: ``poses`` (F, 72), ``trans`` (F, 3) m, ``betas`` (10,),
    ``mocap_framerate``, ``meta`` (JSON: activity, licence, how it was made, fit residual).
    The subject is the track with the most fitted frames."""
    scene, fit = _step_one_fit(Path(scene_dir))
    k = int(fit.present.sum(1).argmax())
    rows = fit.present[k]
    meta = {
        "activity": "balance (Pose2Sim's BalancingTrial: one person, real video)",
        "activities": ["balance"],
        "licence": BALANCING_LICENCE,
        "made_by": "pipeline.prior.sources.make_balancing_poses: mvviz run (no prior), "
        "step-I SMPL fit of the longest track",
        "scene": "sample_data/pose2sim_balancing",
        "track": k,
        "fps": float(scene.fps),
        "fit_residual_mm": round(float(np.nanmean(fit.residual[k][rows])), 1),
    }
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(
        out,
        poses=fit.pose_rotvecs[k][rows].reshape(-1, 72),
        trans=fit.transl[k][rows] / 1000.0,
        betas=fit.betas[k],
        mocap_framerate=np.float64(scene.fps),
        meta=np.array(json.dumps(meta)),
    )
    return out


def make_demo_poses(
    scene_dir: str | os.PathLike = SAMPLE_DATA / "pose2sim_demo",
    out: str | os.PathLike = DEMO_POSES,
    *,
    min_frames: int = 50,
) -> Path:
    """Run the pipeline (no prior) on the Pose2Sim demo and store the step-I poses of every
    track fitted in at least ``min_frames`` frames (both people): ``poses`` (N, 72) and
    ``trans`` (N, 3) m, the tracks one after the other; ``track`` and ``frame`` (N,) say
    whose and which scene frame each row is; ``betas`` (K, 10) per kept track;
    ``mocap_framerate``; ``meta`` (JSON, as :func:`make_balancing_poses`'s)."""
    scene, fit = _step_one_fit(Path(scene_dir))
    kept = [k for k in range(fit.present.shape[0]) if fit.present[k].sum() >= min_frames]
    if not kept:
        raise ValueError(f"{scene_dir}: no track fitted in {min_frames} frames or more")
    rows = [np.flatnonzero(fit.present[k]) for k in kept]
    pairs = list(zip(kept, rows, strict=True))
    meta = {
        "activity": "stand, walk (Pose2Sim's Demo_MultiPerson: two people, real video; one "
        "stands almost still, the other walks across and lifts a leg)",
        "activities": list(DEMO_ACTIVITIES),
        "licence": DEMO_LICENCE,
        "made_by": "pipeline.prior.sources.make_demo_poses: mvviz run (no prior), step-I "
        f"SMPL fit of every track with >= {min_frames} fitted frames",
        "scene": "sample_data/pose2sim_demo",
        "tracks": kept,
        "fps": float(scene.fps),
        "fit_residual_mm": [round(float(np.nanmean(fit.residual[k][r])), 1) for k, r in pairs],
    }
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(
        out,
        poses=np.concatenate([fit.pose_rotvecs[k][r].reshape(-1, 72) for k, r in pairs]),
        trans=np.concatenate([fit.transl[k][r] / 1000.0 for k, r in pairs]),
        track=np.concatenate([np.full(len(r), k) for k, r in pairs]),
        frame=np.concatenate(rows),
        betas=fit.betas[kept],
        mocap_framerate=np.float64(scene.fps),
        meta=np.array(json.dumps(meta)),
    )
    return out


def sources_for(
    *,
    exclude_sources: tuple[str, ...] = (),
    exclude_activities: tuple[str, ...] = (),
    num_poses: int = 60000,
    seed: int = 0,
) -> list[PoseSource]:
    """Every source but ``exclude_sources``, each without the motion of
    ``exclude_activities`` (library activities dropped from the sampler, CMU clips and the
    balancing trial and the demo dropped whole)."""
    bad = set(exclude_sources) - set(SOURCE_NAMES)
    if bad:
        raise ValueError(f"unknown sources {sorted(bad)}; known {SOURCE_NAMES}")
    out = []
    if "library" not in exclude_sources:
        kinds = tuple(k for k in LIBRARY_ACTIVITIES if k not in exclude_activities)
        if kinds:
            out.append(library_source(num_poses=num_poses, seed=seed, kinds=kinds))
    if "cmu" not in exclude_sources:
        out += [
            cmu_source(c)
            for c, acts in CMU_CLIPS.items()
            if not set(acts) & set(exclude_activities)
        ]
    if "balancing" not in exclude_sources and "balance" not in exclude_activities:
        out.append(balancing_source())
    if "demo" not in exclude_sources and not set(DEMO_ACTIVITIES) & set(exclude_activities):
        out.append(demo_source())
    return out


def mix_poses(
    sources: list[PoseSource], *, min_real_poses: int = 3000
) -> tuple[np.ndarray, list[dict]]:
    """(M, 72) poses of all sources, each real one repeated ``ceil(min_real_poses / N)``
    times; and their records (with ``repeat``)."""
    parts, records = [], []
    for s in sources:
        rep = int(np.ceil(min_real_poses / len(s.poses))) if s.real and len(s.poses) else 1
        parts.append(np.tile(s.poses.reshape(-1, 72), (rep, 1)))
        records.append(dict(s.record, repeat=rep))
    return np.concatenate(parts), records


def train_on(sources: list[PoseSource], *, min_real_poses: int = 3000, **train_kwargs) -> PosePrior:
    """Train a prior (:func:`pipeline.prior.training.train_prior`) on the mix of ``sources``;
    the records go into ``info["sources"]``."""
    poses, records = mix_poses(sources, min_real_poses=min_real_poses)
    name = "; ".join(f"{r['file']} x{r['repeat']}" for r in records)
    return train_prior(poses, data_name=name, sources=records, **train_kwargs)
