"""The SMPL fit's parameters (:class:`FitParams`) and what it gives (:class:`SmplFit`),
apart from the fit itself (pipeline/fit/smpl.py, torch).

Configs and results files hold these; reading one must not import torch (the viewer's
start), so they live here, numpy only. Millimetres, world (z up).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from pipeline.body import pose_limits
from pipeline.core.units import MM_PER_M
from pipeline.data.joint_sets import SMPL24, get_joint_set, mapping_indices

if TYPE_CHECKING:
    from pipeline.body.arrays import BodyModelData
    from pipeline.body.model import BodyModel



@dataclass(frozen=True)
class FitParams:
    """Weights, iterations and learning rates of the fit; losses are means, metres."""

    smooth_l1_beta_m: float = 0.05
    """Smooth L1 switch point, metres: quadratic below, linear above."""
    iters: int = 120
    """Adam iterations of step I."""
    iters_warm: int = 120
    """Adam iterations of step I from a warm start (a chunk whose betas, offsets and
    overlap frames come from the previous chunk, :mod:`pipeline.fit.chunks`)."""
    lr_rot: float = 0.04
    """Learning rate of the 6D rotations (unit-scale vectors)."""
    lr_transl_m: float = 0.01
    lr_betas: float = 0.05
    w_smooth: float = 2.0
    """Squared joint acceleration (m/frame^2)^2 over consecutive frames of a track whose
    raw joints lie ``smooth_reference_mm`` from its smoothed ones; other tracks' weight
    follows the square of their own distance (``smpl.smoothing_factors``)."""
    smooth_reference_mm: float = 25.0
    """The input noise at which ``w_smooth`` applies (0: ``w_smooth`` for every track).
    On the noisy twin (25 mm) the fit is best at a weight of 2; on the clean sample, CMU
    motion and Pose2Sim's real trial (7-12 mm) at 0.15-0.3: step I 7.0 -> 6.4 mm on the
    sample, 15.7 -> 12.7 mm on CMU walking (Pose2Sim rig)."""
    w_betas: float = 1e-5
    w_pose: float = 2e-5
    """|R - I|_F^2 of every non-root joint."""
    w_free: float = 2e-4
    """|R - I|_F^2 of the joints the target set leaves free (``body_keypoints.free_joints``)."""
    iters_refine: int = 60
    """Adam iterations of the prior's joint refinement (:mod:`pipeline.fit.prior_correction`)."""
    lr_refine: float = 0.2
    """Factor on ``lr_rot`` and ``lr_transl_m`` in the refinement: it starts at step I's
    optimum, and a full first Adam step throws the body off it (noisy sample, the former
    pull: 14.7 mm with 1.0, 13.8 with 0.1, step I 13.8; with the pull below 13.6 with 0.1
    and 0.2, 0.2 removing more limit violations)."""
    lr_latent: float = 0.05
    w_latent: float = 1e-4
    """|z|^2 of the latent code (the VAE's N(0, I) prior)."""
    w_anchor: float = 3e-4
    """|R_j - decoded_j|_F^2 on the joints the targets constrain, for a pose the prior knows
    (scaled down for one it does not: ``in_distribution_rec``)."""
    w_anchor_free: float = 3e-3
    """|R_j - decoded_j|_F^2 on the joints the targets leave free (scaled likewise)."""
    in_distribution_rec: float = 1.0
    """The anchors of a person-frame are multiplied by ``in_distribution_rec / max(rec,
    in_distribution_rec)``, ``rec`` the prior's reconstruction error of its step-I pose
    (sum over the 21 body joints of |R - decoded(encoded(R))|_F^2; 0 = no scaling)."""
    w_limit_prior: float = 3e-2
    """Squared excess over the joint limits in the prior's refinement."""
    max_extra_residual_mm: float = 1.0
    """A person-frame the correction leaves farther than this (mean residual) beyond step
    I's keeps step I's pose."""
    w_offset: float = 0.3
    """Mean |offset|^2 (m^2) of the per-track keypoint offsets (0 = no offsets)."""
    lr_offset_m: float = 0.005
    foot_offsets: bool = True
    """Whether heels and toes (foot points that are not joints) learn offsets too, in
    their ankle or foot frame (``smpl_kinematics.FOOT_OFFSET_FRAMES``)."""
    limb_offsets: bool = False
    """Whether every fitted keypoint learns an offset, limb joints (knees, ankles, elbows,
    wrists) too, each in its parent body part's frame (MoSh's markers). Off by default:
    on the shipped scenes, whose keypoints are exactly the model's, the limb offsets
    absorb noise and regulariser bias (up to 30 mm) and the SMPL joints drift from the
    truth (clean 13.3 -> 17.2 mm, noisy 15.8 -> 21.9 mm, keypoints within 0.15 mm), while
    on Pose2Sim's balancing trial they bring the body keypoints only 6.0 / 4.7 / 6.0 / 5.9
    -> 5.7 / 4.6 / 5.6 / 5.5 px nearer the RTS joints (``bench/bench_peer_pose2sim.py``
    reports the floor with them)."""
    w_bone_scale: float = 1e-2
    """Sum over the bone groups of (log scale)^2, mean over tracks (0 = bones keep the
    shape space's lengths): each group of a track (hips and shoulders wide, thighs,
    shins, upper arms, forearms: ``kinematics.SCALED_BONES``) may take a length the 10
    betas cannot reach. On CMU motion synthesised on the Campus and Pose2Sim rigs step I
    comes 0.3-0.5 mm nearer the truth and its SMPL joints ~1.2 mm; on the sample 0.1 mm
    (SMPL joints 0.3 mm). Weaker (1e-3) gains 0.4 mm more on CMU but costs the noisy
    twin's SMPL joints 1.4 mm (the scales take up noise): ``bench/bench_bodies.py``."""
    lr_bone_scale: float = 0.1
    floor_iterations: int = 150
    """Adam steps of the constant-bone-length skeleton that a fit is judged by
    (:mod:`pipeline.fit.floor`; 0 = not computed)."""
    w_limit: float = 1e-3
    """Squared excess (rad^2) over the joint limits (:mod:`pipeline.fit.limit_penalty`), step I."""
    min_torso_points: int = 3
    num_threads: int = 1
    """torch intra-op threads during the fit (restored after). The work per op is small
    (about 1000 x 24 3x3 matrices), so on a busy 2-core machine one thread is both
    faster and steadier than two; 0 leaves torch's setting alone."""


@dataclass(frozen=True, eq=False)
class SmplFit:
    """SMPL bodies fitted to tracks. K tracks, F frames, T target joints; NaN where a
    track is absent. Millimetres, world (z up).

    Attributes:
        joint_set: the target joint set (any of
            :data:`pipeline.body.keypoints.FITTABLE_JOINT_SETS`).
        pose_rotvecs: (K, F, 24, 3) local axis-angle, root in the world frame.
        betas: (K, 10) shape, shared over a track's frames.
        transl: (K, F, 3) mm; the body is ``1000 * model(pose, betas) + transl``.
        joints: (K, F, 24, 3) SMPL-24 joints, mm.
        keypoints: (K, F, T, 3) the model's prediction of the targets, mm (NaN for
            targets the body model cannot give).
        residual: (K, F, T) |keypoints - target| mm, NaN where the target is.
        seconds: wall time of the fit (the phases that produced it).
        stage: ``"smpl"`` (step I) or ``"smpl_vae"`` (corrected with the prior).
        keypoint_offsets: (K, T, 3) mm, per track: where its observed keypoints sit
            relative to the body model's, in the frame of each keypoint's joint
            (``KeypointBuffers.offset_joint``); ``keypoints`` include them, the mesh and
            ``joints`` do not (the body stays a plain SMPL body). None: zero.
        bone_scales: (K, 24) per track, each bone's length (joint minus its parent) as a
            factor of the shaped body's; ``joints``, ``keypoints`` and the mesh follow
            them (the skinning carries the surface with its joints). None: all 1.
        prior_reverted: (K, F) bool, the SMPL + VAE fit only: person-frames where the
            prior's correction would have moved the body more than
            ``FitParams.max_extra_residual_mm`` farther from its targets, so it kept step
            I's pose. None: not a corrected fit.
    """

    joint_set: str
    pose_rotvecs: np.ndarray
    betas: np.ndarray
    transl: np.ndarray
    joints: np.ndarray
    keypoints: np.ndarray
    residual: np.ndarray
    seconds: float
    stage: str
    model: BodyModel | BodyModelData = field(repr=False)
    keypoint_offsets: np.ndarray | None = None
    bone_scales: np.ndarray | None = None
    prior_reverted: np.ndarray | None = None

    @property
    def present(self) -> np.ndarray:
        """(K, F) bool: person-frames with a fitted body."""
        return np.isfinite(self.transl).all(-1)

    def vertices(self, k: int, f: int) -> np.ndarray:
        """(V, 3) mesh vertices of track ``k`` at frame ``f``, world mm (NaN if absent)."""
        if not self.present[k, f]:
            return np.full((self.model.num_vertices, 3), np.nan)
        # torch only here (exports): loading a results file must not import it
        import torch

        from pipeline.body.model import torch_body_model

        scales = None if self.bone_scales is None else self.bone_scales[k][None]
        with torch.no_grad():
            out = torch_body_model(self.model)(
                torch.as_tensor(self.pose_rotvecs[k, f][None], dtype=torch.float32),
                torch.as_tensor(self.betas[k][None], dtype=torch.float32),
                bone_scales=None if scales is None else np.nan_to_num(scales, nan=1.0),
            )
        return MM_PER_M * out.vertices[0].double().numpy() + self.transl[k, f]

    def arrays(self, prefix: str = "") -> dict[str, np.ndarray]:
        """The arrays to store (e.g. in results.npz), keys prefixed."""
        keys = ("pose_rotvecs", "betas", "transl", "joints", "keypoints", "residual")
        out = {prefix + k: getattr(self, k) for k in keys}
        if self.keypoint_offsets is not None:
            out[prefix + "keypoint_offsets"] = self.keypoint_offsets
        if self.bone_scales is not None:
            out[prefix + "bone_scales"] = self.bone_scales
        if self.prior_reverted is not None:
            out[prefix + "prior_reverted"] = self.prior_reverted
        return out

    @classmethod
    def from_arrays(
        cls,
        arrays: dict,
        prefix: str,
        *,
        joint_set: str,
        model: BodyModel | BodyModelData,
        stage: str = "smpl",
    ) -> SmplFit:
        """Inverse of :meth:`arrays` (``seconds`` is not stored: NaN)."""
        keys = ("pose_rotvecs", "betas", "transl", "joints", "keypoints", "residual")
        off = arrays.get(prefix + "keypoint_offsets") if hasattr(arrays, "get") else None
        scales = arrays.get(prefix + "bone_scales") if hasattr(arrays, "get") else None
        reverted = arrays.get(prefix + "prior_reverted") if hasattr(arrays, "get") else None
        return cls(
            joint_set=joint_set,
            model=model,
            stage=stage,
            seconds=float("nan"),
            keypoint_offsets=None if off is None else np.asarray(off),
            bone_scales=None if scales is None else np.asarray(scales),
            prior_reverted=None if reverted is None else np.asarray(reverted, bool),
            **{k: np.asarray(arrays[prefix + k]) for k in keys},
        )


def target_slots(fit: SmplFit) -> np.ndarray:
    """(K, F, 24, 3) the fit's keypoints laid out in SMPL-24 slots (NaN where the target
    set has no counterpart), the layout :func:`pipeline.evaluation.evaluate.stage_metrics`
    scores."""
    js = get_joint_set(fit.joint_set)
    if js.name == SMPL24.name:
        return fit.keypoints
    src, dst = mapping_indices(js, SMPL24)
    out = np.full(fit.keypoints.shape[:2] + (SMPL24.num_joints, 3), np.nan)
    out[:, :, dst] = fit.keypoints[:, :, src]
    return out


def plausibility(fit: SmplFit, *, tol_deg: float = pose_limits.DEFAULT_TOL_DEG) -> dict:
    """Local plausibility of a fit.

    Returns:
        ``limit_violations_per_1000`` (joint rotations outside
        :data:`pipeline.body.pose_limits.LIMITS` by more than ``tol_deg``, per 1000 bodies),
        and, on the fit's keypoints in SMPL-24 slots (comparable with a triangulation's
        rows): ``bone_length_std_mm``, ``hinge_violations_per_1000``, ``foot_jitter``,
        ``wrist_jitter`` (mm/frame^2); see :func:`pipeline.body.pose_limits.skeleton_plausibility`.
    """
    limits = pose_limits.violations_per_1000(fit.pose_rotvecs, tol_deg=tol_deg)
    out = {"limit_violations_per_1000": limits}
    out.update(pose_limits.skeleton_plausibility(target_slots(fit), tol_deg=tol_deg))
    return out
