"""SMPL fit to tracked 3D joints by gradient descent, and its correction by a pose prior.

Input: tracks of 3D joints ``(num_tracks, num_frames, num_joints, 3)`` in world
millimetres (z up), NaN where a joint or a whole person-frame is missing, in any joint
set the body model is tied to (:mod:`pipeline.body.keypoints`: COCO-17, BODY_25,
BODY_25B, Halpe-26, COCO-23/WholeBody, BlazePose-33, ..., SMPL-24); keypoints the table
marks "not fitted" (face contour, fingers) are ignored. Output: per track a body shape,
and per frame a pose and a translation (:class:`SmplFit`). Internally everything is in
metres, the body model's unit, so that the switch of the Smooth L1 loss at
``|x| = beta`` means something: ``beta = 0.05 m`` by default (residuals below 5 cm are
penalised quadratically, larger ones, e.g. a mis-triangulated joint, linearly).

The model ``body = 1000 * model(pose, betas) + transl`` (the convention of
:class:`pipeline.data.scene.GroundTruth`) has SMPL's canonical frame (y up); the root
rotation carries it into the z-up world.

What the model predicts for each target set:

* SMPL-24 targets: the posed joints (forward kinematics of the shaped rest joints).
* Other targets: ``vertex_weights @ vertices + joint_weights @ joints`` from the table of
  :mod:`pipeline.body.keypoints` (COCO-17: the ``coco_regressor``, which reads 4,465 of
  the open model's 13,348 vertices; feet, head top, hands: landmark vertices; mid-hip,
  OpenPose's neck: means). Rather than skinning those vertices, the fit uses that the
  regressor and linear blend skinning are both linear, so for keypoint ``k``::

      kp_k = sum_j G_j (D0_kj + Dbeta_kj @ betas [+ E_kj @ posefeat]) + sum_j A_kj p_j + s_k t

  with ``G_j, p_j`` the global rotation and position of joint ``j``, ``A = R W`` the
  regressor-blended skinning weights (17, 24), ``D = R W (v_shaped) - A * rest_joints``
  precomputed once per model (:class:`KeypointBuffers`). That is exactly the regressor
  applied to the full LBS mesh (a test checks it to 1e-6 m) at the cost of T x 24
  "virtual vertices". A joint row of the table adds a one-hot to ``A`` (``D = 0``, row
  sum 1), so any mix of vertex rows and joint rows takes the same path.

Optimisation (all person-frames of all tracks in one batch, Adam):

* Phase 0, closed form, per frame (no gradient; the global initialisation every frame
  starts from, so no frame waits for its predecessor): betas per track from the median
  bone lengths of its targets (rest joints are linear in betas: a few Gauss-Newton
  steps of ridge least squares, :func:`initial_betas`); root rotation by weighted
  Kabsch of the rest body's torso points (targets anchored at pelvis, hips, spine3,
  neck or shoulders, :func:`pipeline.body.keypoints.torso_points`: shoulders and hips
  for COCO-17, plus pelvis, spine3 and neck for SMPL-24) onto the targets, translation
  following from it (:func:`initial_alignment`; a frame without three torso points
  copies the nearest frame of its track); limbs by analytic hinge IK
  (:func:`analytic_pose`: the upper joint points the bone and the knee/elbow axis at the
  limb plane, the hinge bends about its flexion axis; where targets are anchored at
  both ends, as for SMPL-24, spine, neck, collars, ankles and wrists also swing).
* Phase 1, step I (``iters``): optimised: all 24 joint rotations per frame in the 6D
  representation of Zhou et al. 2019 (root included), translation per frame, betas
  per track (shared by all its frames) and per-track keypoint offsets (below). Loss =
  weighted Smooth L1 data term (NaN target = weight 0) + ``w_smooth`` * squared second
  differences of the 24 model joints over consecutive frames of a track + ``w_betas`` *
  |betas|^2 + ``w_offset`` * |offsets|^2 + ``w_limit`` * squared excess over the joint
  limits (:mod:`pipeline.fit.limit_penalty`) + ``w_pose`` * |R - I|^2 over all non-root
  joints + ``w_free`` * |R - I|^2 over the joints the target set does not constrain
  (the rule of :func:`pipeline.body.keypoints.free_joints`; COCO-17: spine, neck, head,
  collars, wrists, hands, ankles, feet; SMPL-24: head, hands, feet, whose rotations move
  no joint; layouts with feet or hand points also pin ankles or wrists). Learning rates
  decay by a cosine schedule to 5% (:class:`FitParams`).
* Keypoint offsets: another person's (or a mocap skeleton's, or a detector's) hips,
  shoulders and face points do not sit where the body model's regressor puts them, and
  the 10 betas cannot move them there (a CMU subject's hip centres are 137 mm apart, the
  open model's 224 mm). Each track therefore learns one offset per keypoint in the frame
  of its anchor's parent joint (``KeypointBuffers.offset_joint``; trunk and head frames,
  ``smpl_kinematics.OFFSET_FRAMES``, and the ankle or foot frame of the foot points that
  are not joints, heels and toes, ``FOOT_OFFSET_FRAMES``), shared by all its frames,
  L2-regularised: ``SmplFit.keypoints`` include them, the mesh and ``SmplFit.joints`` are
  the plain body. Limb joints (knees, ankles, elbows, wrists) get one only with
  ``FitParams.limb_offsets`` (measured there: it costs the SMPL joints 4-6 mm on the
  shipped scenes).
  Measured on a CMU mocap scene (campus rig, 2 people, 40 frames): step I fitted to the
  *true* keypoints misses them by 18.4 mm without offsets, 8.6 mm with them; step I on
  the RTS tracks 23.1 -> 15.3 mm against the truth (RTS itself 11.0 mm).
* Joint correction with the VAE prior (Eq. 11; only with ``prior``), starting from step
  I, betas and offsets fixed: :mod:`pipeline.fit.prior_correction` (encode; refine pose and
  latent code together with the data term dominant; no person-frame ends farther from
  its targets than step I).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch

from pipeline.body.kinematics import (
    NUM_JOINTS,
    KeypointBuffers,
    bone_scale_matrix,
    keypoint_buffers,
    matrix_to_rot6d,
    matrix_to_rotvec,
    predict_targets,
    rot6d_to_matrix,
    rotvec_to_matrix,
)
from pipeline.body.model import BodyModel
from pipeline.core.progress import Progress
from pipeline.core.torch_threads import torch_threads
from pipeline.core.units import MM_PER_M
from pipeline.data.joint_sets import SMPL24, get_joint_set
from pipeline.fit.limit_penalty import limit_penalty
from pipeline.fit.optim import adam_cosine
from pipeline.fit.prior_correction import correct_with_prior
from pipeline.fit.types import (  # noqa: F401  (re-exported)
    FitParams,
    SmplFit,
    plausibility,
    target_slots,
)

if TYPE_CHECKING:
    from pipeline.fit.prior import PosePrior

_J = SMPL24.index


# --------------------------------------------------------------------------- problem


@dataclass(frozen=True, eq=False)
class _Problem:
    """The person-frames to fit, packed into rows. N rows, T target joints, metres."""

    K: int
    F: int
    track: np.ndarray  # (N,)
    frame: np.ndarray  # (N,)
    target: torch.Tensor  # (N, T, 3), zeros where missing
    weight: torch.Tensor  # (N, T)
    triples: torch.Tensor  # (M, 3) rows (t-1, t, t+1) of the same track
    track_rows: torch.Tensor  # (N,) = track, as a tensor for gathering betas
    rows_per_track: tuple[int, ...]  # (K,) rows of each track: the rows are by track
    smooth_weight: torch.Tensor | None = None  # (M,) each triple's factor on w_smooth


def _pack(
    tracks_mm: np.ndarray,
    weights: np.ndarray | None,
    fitted: np.ndarray | None = None,
    smooth_factor: np.ndarray | None = None,
) -> _Problem:
    """Pack the observed person-frames; targets the model cannot give (``fitted`` False,
    (T,)) count as missing; ``smooth_factor`` (K,) each track's factor on the smoothness."""
    K, F, T, _ = tracks_mm.shape
    finite = np.isfinite(tracks_mm).all(-1)  # (K, F, T)
    if fitted is not None:
        finite &= np.asarray(fitted, bool)
    w = finite.astype(float) if weights is None else np.where(finite, weights, 0.0)
    present = (w > 0).any(-1)
    track, frame = np.nonzero(present)
    row = np.full((K, F), -1)
    row[track, frame] = np.arange(len(track))
    prev = np.where(frame > 0, row[track, np.maximum(frame - 1, 0)], -1)
    nxt = np.where(frame < F - 1, row[track, np.minimum(frame + 1, F - 1)], -1)
    ok = (prev >= 0) & (nxt >= 0)
    triples = np.stack([prev[ok], np.flatnonzero(ok), nxt[ok]], 1)
    target = np.where(finite[track, frame][..., None], tracks_mm[track, frame], 0.0) / MM_PER_M
    return _Problem(
        K=K,
        F=F,
        track=track,
        frame=frame,
        target=torch.as_tensor(target, dtype=torch.float32),
        weight=torch.as_tensor(w[track, frame], dtype=torch.float32),
        triples=torch.as_tensor(triples, dtype=torch.long).reshape(-1, 3),
        track_rows=torch.as_tensor(track, dtype=torch.long),
        rows_per_track=tuple(int(c) for c in np.bincount(track, minlength=K)),
        smooth_weight=None
        if smooth_factor is None
        else torch.as_tensor(np.asarray(smooth_factor)[track[triples[:, 1]]], dtype=torch.float32),
    )


def _kabsch(src: np.ndarray, dst: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted rigid alignment: R (N, 3, 3), t (N, 3) minimising sum w |R src + t - dst|^2.

    Args:
        src: (P, 3) model points; dst: (N, P, 3); w: (N, P) weights (> 0 somewhere).
    """
    wn = w / w.sum(1, keepdims=True)
    cs = np.einsum("np,pc->nc", wn, src)
    cd = np.einsum("np,npc->nc", wn, dst)
    H = np.einsum("np,npa,npb->nab", wn, src[None] - cs[:, None], dst - cd[:, None])
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.swapaxes(Vt, 1, 2) @ np.swapaxes(U, 1, 2)))
    S = np.tile(np.eye(3), (len(H), 1, 1))
    S[:, 2, 2] = d
    R = np.swapaxes(Vt, 1, 2) @ S @ np.swapaxes(U, 1, 2)
    t = cd - np.einsum("nab,nb->na", R, cs)
    return R, t


# canonical (y up) -> world (z up) with the person facing world -y: used without torso.
_UPRIGHT = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


def initial_alignment(
    prob: _Problem, buf: KeypointBuffers, *, min_points: int = 3
) -> tuple[np.ndarray, np.ndarray]:
    """Phase 0: root rotation (N, 3, 3) and translation (N, 3) m for the rest body.

    Weighted Kabsch of the rest body's torso points onto the targets'; rows without
    ``min_points`` torso targets copy the nearest aligned row of their track (or stand
    upright at the targets' centroid when the track has none).
    """
    N = len(prob.track)
    with torch.no_grad():
        zero = torch.zeros(1, NUM_JOINTS, 3, 3) + torch.eye(3)
        rest_kp, _ = predict_targets(
            zero, torch.zeros(1, buf.J_shapedirs.shape[-1]), torch.zeros(1, 3), buf
        )
    src = rest_kp[0, buf.torso].double().numpy()
    dst = prob.target[:, buf.torso].double().numpy()
    w = prob.weight[:, buf.torso].double().numpy()
    ok = (w > 0).sum(1) >= min_points
    R = np.tile(_UPRIGHT, (N, 1, 1))
    t = np.zeros((N, 3))
    if ok.any():
        R[ok], t[ok] = _kabsch(src, dst[ok], w[ok])
    for k in np.unique(prob.track):
        rows = np.flatnonzero(prob.track == k)
        good = rows[ok[rows]]
        bad = rows[~ok[rows]]
        if len(bad) == 0:
            continue
        if len(good):
            pos = np.searchsorted(prob.frame[good], prob.frame[bad]).clip(0, len(good) - 1)
            alt = (pos - 1).clip(0)
            d1 = np.abs(prob.frame[good][pos] - prob.frame[bad])
            d0 = np.abs(prob.frame[good][alt] - prob.frame[bad])
            near = good[np.where(d0 <= d1, alt, pos)]
            R[bad], t[bad] = R[near], t[near]
        else:
            wb = prob.weight[bad].double().numpy()
            tb = prob.target[bad].double().numpy()
            centroid = (wb[..., None] * tb).sum(1) / wb.sum(1, keepdims=True).clip(1e-9)
            R[bad] = _UPRIGHT
            t[bad] = centroid - src.mean(0) @ _UPRIGHT.T
    # The root rotates about the rest pelvis: kp = R (x - p0) + p0 + transl = R x + t.
    p0 = buf.J_template[0].double().numpy()
    transl = t - p0 + np.einsum("nab,b->na", R, p0)
    return R, transl


def initial_betas(prob: _Problem, buf: KeypointBuffers, *, ridge: float = 1e-3) -> np.ndarray:
    """Phase 0: betas (K, B) whose rest bone lengths match each track's median bone lengths.

    The rest target joints are linear in betas, ``x(b) = x0 + X b``, so a bone's length
    is linearised about the current estimate, ``|v(b)| ~ n . v(b)``, ``n = v/|v|``, and
    the ridge-regularised least squares (``ridge`` m^2 per unit beta^2) is solved three
    times (Gauss-Newton). Bones: the target joint set's drawing bones.
    """
    nb = buf.J_shapedirs.shape[-1]
    js = get_joint_set(buf.joint_set)
    with torch.no_grad():
        eye = torch.eye(3).repeat(nb + 1, NUM_JOINTS, 1, 1)
        basis = torch.cat([torch.zeros(1, nb), torch.eye(nb)])
        rest, _ = predict_targets(eye, basis, torch.zeros(nb + 1, 3), buf)
    rest = rest.double().numpy()
    x0, X = rest[0], np.moveaxis(rest[1:] - rest[0], 0, -1)  # (T, 3), (T, 3, B)
    bones = np.asarray(js.bones)
    a, b = bones[:, 0], bones[:, 1]
    d0, dX = x0[a] - x0[b], X[a] - X[b]  # (nbones, 3), (nbones, 3, B)
    # Bones between points the model puts (nearly) together, e.g. WholeBody's body and
    # hand wrists, carry no length: leave them out (they would divide by zero).
    long = np.linalg.norm(d0, axis=-1) > 0.01
    tgt = prob.target.double().numpy()
    ok = (prob.weight.numpy() > 0)[:, a] & (prob.weight.numpy() > 0)[:, b]
    length = np.where(ok, np.linalg.norm(tgt[:, a] - tgt[:, b], axis=-1), np.nan)
    out = np.zeros((prob.K, nb))
    for k in np.unique(prob.track):
        rows = prob.track == k
        col = length[rows]
        has = (np.isfinite(col).sum(0) > 0) & long
        if not has.any():
            continue
        L = np.nanmedian(col[:, has], axis=0)
        beta = np.zeros(nb)
        for _ in range(3):
            v = d0[has] + dX[has] @ beta
            n = v / np.linalg.norm(v, axis=-1, keepdims=True)
            Jm = np.einsum("bc,bck->bk", n, dX[has])  # (nbones, B)
            r = L - np.einsum("bc,bc->b", n, d0[has])
            beta = np.linalg.solve(Jm.T @ Jm + ridge * np.eye(nb), Jm.T @ r)
        out[k] = beta
    return out


# Limbs for the analytic initialisation: (upper joint, hinge joint, end joint) by SMPL
# name (target joints of the same name) and the hinge's flexion axis in the rest frame.
LIMBS: tuple[tuple[str, str, str, tuple[float, float, float]], ...] = (
    ("left_hip", "left_knee", "left_ankle", (1.0, 0.0, 0.0)),
    ("right_hip", "right_knee", "right_ankle", (1.0, 0.0, 0.0)),
    ("left_shoulder", "left_elbow", "left_wrist", (0.0, -1.0, 0.0)),
    ("right_shoulder", "right_elbow", "right_wrist", (0.0, 1.0, 0.0)),
)
# SMPL-24 targets only: joints turned (swing only) to point at one child.
SWING_CHILD: tuple[tuple[str, str], ...] = (
    ("spine1", "spine2"), ("spine2", "spine3"), ("spine3", "neck"), ("neck", "head"),
    ("left_collar", "left_shoulder"), ("right_collar", "right_shoulder"),
    ("left_ankle", "left_foot"), ("right_ankle", "right_foot"),
    ("left_wrist", "left_hand"), ("right_wrist", "right_hand"),
)  # fmt: skip


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True).clip(1e-12)


def _frame(u: np.ndarray, h: np.ndarray) -> np.ndarray:
    """(..., 3) direction u and a second direction h -> (..., 3, 3) orthonormal columns
    (u, h orthogonalised, u x h)."""
    u = _unit(u)
    h = _unit(h - (h * u).sum(-1, keepdims=True) * u)
    return np.stack([u, h, np.cross(u, h)], -1)


def _min_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(..., 3, 3) smallest rotations taking unit a to unit b (antiparallel: about any
    perpendicular axis)."""
    a, b = np.broadcast_arrays(_unit(a), _unit(b))
    axis = np.cross(a, b)
    s = np.linalg.norm(axis, axis=-1)
    c = (a * b).sum(-1)
    perp = np.cross(a, np.where(np.abs(a[..., :1]) < 0.9, [1.0, 0, 0], [0, 1.0, 0]))
    axis = np.where((s > 1e-9)[..., None], axis, perp)
    return rotvec_to_matrix(_unit(axis) * np.arctan2(s, c)[..., None])


def analytic_pose(
    prob: _Problem, buf: KeypointBuffers, root: np.ndarray, *, bend_blend: float = 0.25
) -> np.ndarray:
    """Closed-form local rotations (N, 24, 3, 3) of the rest body towards the targets.

    Each limb (hip-knee-ankle, shoulder-elbow-wrist) is solved as a hinge: the upper
    joint turns the rest bone onto the target bone and the hinge axis onto the normal of
    the limb's plane, the hinge then bends about its flexion axis (so knees and elbows
    start bent the anatomical way). The plane's normal (length = sine of the bend) is
    blended with the parent's axis (weight ``bend_blend``): a nearly straight limb, whose
    plane is noise, keeps the parent's twist. Spine, neck, collars, ankles and wrists
    swing towards their child where targets are anchored at both (SMPL-24 targets).
    Missing targets leave a joint at rest.
    """
    N = len(prob.track)
    with torch.no_grad():
        eye = torch.eye(3).repeat(1, NUM_JOINTS, 1, 1)
        rest_t, _ = predict_targets(eye, torch.zeros(1, buf.J_shapedirs.shape[-1]),
                                    torch.zeros(1, 3), buf)  # fmt: skip
    rest_t = rest_t[0].double().numpy()  # (T, 3)
    tgt = prob.target.double().numpy()
    ok = prob.weight.numpy() > 0
    local = np.tile(np.eye(3), (N, NUM_JOINTS, 1, 1))
    glob = np.tile(np.eye(3), (N, NUM_JOINTS, 1, 1))
    glob[:, 0] = local[:, 0] = root
    parents = buf.parents
    limbs = {_J[p]: (p, h, e, np.asarray(a)) for p, h, e, a in LIMBS}
    swings = dict(SWING_CHILD)
    at = buf.anchors  # SMPL-24 joint -> the target anchored there
    for j in range(1, NUM_JOINTS):
        G_par = glob[:, parents[j]]
        name = SMPL24.names[j]
        if j in limbs and all(n in at for n in limbs[j][:3]):
            p, h, e, axis = limbs[j]
            ip, ih, ie = at[p], at[h], at[e]
            u_r, f_r = rest_t[ih] - rest_t[ip], rest_t[ie] - rest_t[ih]
            u_w, f_w = tgt[:, ih] - tgt[:, ip], tgt[:, ie] - tgt[:, ih]
            has_u = ok[:, ip] & ok[:, ih]
            has_f = has_u & ok[:, ie]
            # Hinge direction: the limb plane's normal (length sin(bend)) blended with the
            # parent's axis carried by the minimal swing (weight bend_blend), so a nearly
            # straight limb, whose plane is noise, keeps its parent's twist.
            cross = np.cross(_unit(u_w), _unit(f_w))
            swing = _min_rotation(np.einsum("nab,b->na", G_par, u_r), u_w)
            h_fb = np.einsum("nab,nbc,c->na", swing, G_par, axis)
            h_w = np.where(has_f[:, None], cross, 0.0) + bend_blend * h_fb
            G = _frame(u_w, h_w) @ _frame(u_r, axis).T  # rest (bone, axis) -> target
            local[has_u, j] = (np.swapaxes(G_par, 1, 2) @ G)[has_u]
            # the hinge: angle from the rest lower bone to the target's, about the axis
            f_loc = np.einsum("nba,nb->na", G, f_w)  # target lower bone in G's frame
            f_r0 = f_r - (f_r @ axis) * axis
            phi = np.arctan2(np.cross(f_r0, f_loc) @ axis, f_loc @ f_r0)
            hinge = rotvec_to_matrix(axis[None] * phi[:, None])
            local[has_f, _J[h]] = hinge[has_f]
        elif name in swings and name in at and swings[name] in at:
            i0, i1 = at[name], at[swings[name]]
            has = ok[:, i0] & ok[:, i1]
            d_r = np.einsum("nab,b->na", G_par, rest_t[i1] - rest_t[i0])
            sw = _min_rotation(d_r, tgt[:, i1] - tgt[:, i0])  # world swing
            loc = np.swapaxes(G_par, 1, 2) @ sw @ G_par
            local[has, j] = loc[has]
        glob[:, j] = G_par @ local[:, j]
    return local


# --------------------------------------------------------------------------- losses


def _data_loss(pred: torch.Tensor, prob: _Problem, beta: float) -> torch.Tensor:
    """Weighted Smooth L1 (per coordinate, metres), mean over weighted coordinates."""
    r = torch.nn.functional.smooth_l1_loss(pred, prob.target, reduction="none", beta=beta)
    return (r.sum(-1) * prob.weight).sum() / (3.0 * prob.weight.sum()).clamp_min(1e-9)


def _smooth_loss(joints: torch.Tensor, prob: _Problem) -> torch.Tensor:
    """Mean squared second difference of the model joints over consecutive frames, each
    triple weighted by its track's factor (:func:`smoothing_factors`)."""
    if len(prob.triples) == 0:
        return joints.new_zeros(())
    a, b, c = prob.triples.unbind(1)
    acc = joints[a] - 2.0 * joints[b] + joints[c]
    sq = (acc * acc).sum(-1)  # (M, 24)
    if prob.smooth_weight is not None:
        sq = sq * prob.smooth_weight[:, None]
    return sq.mean()


def smoothing_factors(noise_mm: np.ndarray | None, reference_mm: float) -> np.ndarray | None:
    """(K,) each track's factor on ``w_smooth``: (noise / reference)^2, within [1/16, 4]
    (1 where the noise is unknown; None: no noise given or ``reference_mm`` 0).

    The data term should weigh a track by the inverse of its input's noise variance; with
    the data term's weight fixed, that is the smoothness term's weight growing with it.
    ``noise_mm`` is how far a track's raw joints lie from its RTS path (median): ~25 mm
    on the noisy twin, whose fit is best at ``w_smooth`` 2, 7-12 mm on the clean sample,
    CMU motion and Pose2Sim's real trial, whose fits are best at 0.15-0.3."""
    if noise_mm is None or not reference_mm > 0:
        return None
    f = (np.asarray(noise_mm, float) / reference_mm) ** 2
    return np.where(np.isfinite(f), np.clip(f, 1.0 / 16.0, 4.0), 1.0)


def _objective(R, betas, transl, prob, buf, params, offsets=None, scales=None) -> torch.Tensor:
    """Data term + temporal smoothness for local rotations R (N, 24, 3, 3), betas (K, B)
    and bone scales (K, 24) one per track."""
    kp, joints = predict_targets(
        R, betas, transl, buf, offsets, rows_per_body=prob.rows_per_track, bone_scales=scales
    )
    loss = _data_loss(kp, prob, params.smooth_l1_beta_m)
    return loss + params.w_smooth * _smooth_loss(joints, prob)


def _rest_distance(rotmats: torch.Tensor) -> torch.Tensor:
    """(N, J, 3, 3) -> (N, J) |R - I|_F^2."""
    return ((rotmats - torch.eye(3, dtype=rotmats.dtype)) ** 2).sum((-1, -2))


# --------------------------------------------------------------------------- the fit


def _make_fit(
    prob, buf, model, rotmats, betas, transl, *, seconds, stage, offsets=None, scales=None
) -> SmplFit:
    """Scatter the fitted rows (metres) back into (K, F, ...) arrays in mm, NaN elsewhere;
    ``offsets`` (K, T, 3) m or None; ``scales`` (K, 24) or None."""
    with torch.no_grad():
        off = None if offsets is None else offsets[prob.track_rows]
        kp, joints = predict_targets(
            rotmats, betas, transl, buf, off, rows_per_body=prob.rows_per_track,
            bone_scales=scales,
        )  # fmt: skip
    err = (kp - prob.target).norm(dim=-1).double().numpy()
    kp_mm = MM_PER_M * kp.double().numpy()
    kp_mm[:, ~buf.fitted] = np.nan  # keypoints the body model cannot give
    rows = {
        "pose_rotvecs": matrix_to_rotvec(rotmats.double().numpy()),
        "transl": MM_PER_M * transl.double().numpy(),
        "joints": MM_PER_M * joints.double().numpy(),
        "keypoints": kp_mm,
        "residual": np.where(prob.weight.numpy() > 0, MM_PER_M * err, np.nan),
    }
    out = {}
    for name, x in rows.items():
        out[name] = np.full((prob.K, prob.F) + x.shape[1:], np.nan)
        out[name][prob.track, prob.frame] = x
    out_b = np.full((prob.K, betas.shape[1]), np.nan)
    seen = np.unique(prob.track)
    out_b[seen] = betas.detach().double().numpy()[seen]
    out_o = np.zeros((prob.K, buf.num_targets, 3))
    if offsets is not None:
        out_o = MM_PER_M * offsets.detach().double().numpy()
    out_o[np.setdiff1d(np.arange(prob.K), seen)] = np.nan
    out_s = None
    if scales is not None:
        out_s = np.full((prob.K, NUM_JOINTS), np.nan)
        out_s[seen] = scales.detach().double().numpy()[seen]
    return SmplFit(
        joint_set=buf.joint_set, betas=out_b, seconds=seconds, stage=stage, model=model,
        keypoint_offsets=out_o, bone_scales=out_s, **out,
    )  # fmt: skip


def _check_tracks(tracks_mm: np.ndarray, joint_set: str) -> np.ndarray:
    x = np.asarray(tracks_mm, dtype=float)
    js = get_joint_set(joint_set)
    if x.ndim != 4 or x.shape[-1] != 3 or x.shape[2] != js.num_joints:
        raise ValueError(
            f"expected tracks (num_tracks, num_frames, {js.num_joints}, 3) in {js.name}, "
            f"got {x.shape}"
        )
    return x


def fit_sequence(
    tracks_mm: np.ndarray,
    joint_set: str,
    model: BodyModel,
    *,
    prior: PosePrior | None = None,
    params: FitParams = FitParams(),  # noqa: B008  (frozen dataclass)
    weights: np.ndarray | None = None,
    noise_mm: np.ndarray | None = None,
    progress: Progress = True,
) -> tuple[SmplFit, SmplFit | None]:
    """Fit SMPL bodies to 3D joint tracks; see the module docstring for the phases.

    Args:
        tracks_mm: (num_tracks, num_frames, num_joints, 3) world mm, NaN = missing.
        joint_set: the set of ``tracks_mm``, one of
            :data:`pipeline.body.keypoints.FITTABLE_JOINT_SETS`.
        model: the body model.
        prior: a trained :class:`~pipeline.fit.prior.PosePrior`; with it the
            corrected fit (phases 2a-2c) is returned too.
        weights: optional (num_tracks, num_frames, num_joints) confidences in [0, 1].
        noise_mm: optional (num_tracks,) how far each track's raw joints lie from these
            (smoothed) ones, mm: its smoothness weight follows (:func:`smoothing_factors`).
    Returns:
        ``(step I fit, step I + VAE fit or None)``.
    """
    x = _check_tracks(tracks_mm, joint_set)
    if weights is not None and np.shape(weights) != x.shape[:3]:
        raise ValueError(f"weights must have shape {x.shape[:3]}, got {np.shape(weights)}")
    buf = keypoint_buffers(model, joint_set)
    if params.limb_offsets:  # every fitted target may carry an offset (FitParams.limb_offsets)
        buf = dataclasses.replace(buf, offset_mask=torch.as_tensor(buf.fitted, dtype=torch.float32))
    with torch_threads(params.num_threads):
        return _fit(x, buf, model, prior, params, weights, progress, noise_mm=noise_mm)


@dataclass(frozen=True, eq=False)
class WarmStart:
    """Where a fit starts instead of phase 0: what an earlier fit (the previous chunk of
    the same tracks, :mod:`pipeline.fit.chunks`) found. K tracks, F frames, mm.

    Attributes:
        betas: (K, B) per track, NaN for a track the earlier fit did not see (phase 0's
            betas then).
        keypoint_offsets: (K, T, 3) mm per track, NaN likewise (then zero).
        bone_scales: (K, 24) per track, NaN likewise (then 1); None: all 1.
        pose_rotvecs: (K, F, 24, 3) local axis-angle per person-frame, NaN where phase 0
            starts (frames the earlier fit did not cover).
        transl: (K, F, 3) mm, NaN likewise.
    """

    betas: np.ndarray
    keypoint_offsets: np.ndarray
    pose_rotvecs: np.ndarray
    transl: np.ndarray
    bone_scales: np.ndarray | None = None


def _fit(
    x: np.ndarray,
    buf: KeypointBuffers,
    model: BodyModel,
    prior: PosePrior | None,
    params: FitParams,
    weights: np.ndarray | None,
    progress: Progress,
    warm: WarmStart | None = None,
    noise_mm: np.ndarray | None = None,
) -> tuple[SmplFit, SmplFit | None]:
    prob = _pack(
        x, None if weights is None else np.asarray(weights, float), buf.fitted,
        smoothing_factors(noise_mm, params.smooth_reference_mm),
    )  # fmt: skip
    nb = buf.J_shapedirs.shape[-1]
    t0 = time.perf_counter()
    if len(prob.track) == 0:
        empty = _make_fit(
            prob, buf, model, torch.zeros(0, NUM_JOINTS, 3, 3), torch.zeros(prob.K, nb),
            torch.zeros(0, 3), seconds=0.0, stage="smpl",
        )  # fmt: skip
        return empty, (None if prior is None else dataclasses.replace(empty, stage="smpl_vae"))
    R1, betas, transl, off1, scales = _step_one(prob, buf, params, progress, warm)
    fit1 = _make_fit(
        prob, buf, model, R1, betas, transl, seconds=time.perf_counter() - t0, stage="smpl",
        offsets=off1, scales=scales,
    )  # fmt: skip
    if prior is None:
        return fit1, None
    corr = _prior_correction(prob, buf, prior, params, R1, betas, transl, off1, scales, progress)
    fit2 = _make_fit(
        prob, buf, model, corr.rotmats, betas, corr.transl, seconds=corr.seconds,
        stage="smpl_vae", offsets=off1, scales=scales,
    )  # fmt: skip
    reverted = np.zeros((prob.K, prob.F), bool)
    reverted[prob.track, prob.frame] = corr.reverted
    return fit1, dataclasses.replace(fit2, prior_reverted=reverted)


def _phase_zero(prob: _Problem, buf: KeypointBuffers, params: FitParams, warm: WarmStart | None):
    """Initial rotations (N, 24, 3, 3), translations (N, 3), betas (K, nb), keypoint
    offsets (K, T, 3) and bone scales (K, 24), metres, numpy: phase 0's closed forms,
    replaced by ``warm``'s values where it has them; and (K,) bool, the tracks whose
    betas and offsets ``warm`` holds."""
    R0, transl = initial_alignment(prob, buf, min_points=params.min_torso_points)
    rotmats = analytic_pose(prob, buf, R0)
    betas = initial_betas(prob, buf)
    offsets = np.zeros((prob.K, buf.num_targets, 3))
    scales = np.ones((prob.K, NUM_JOINTS))
    if warm is None:
        return rotmats, transl, betas, offsets, scales, np.zeros(prob.K, bool)
    seen = np.isfinite(warm.betas).all(1) & np.isfinite(warm.keypoint_offsets).all((1, 2))
    betas[seen] = warm.betas[seen]
    offsets[seen] = warm.keypoint_offsets[seen] / MM_PER_M
    if warm.bone_scales is not None:
        known = seen & np.isfinite(warm.bone_scales).all(1)
        scales[known] = warm.bone_scales[known]
    pose = warm.pose_rotvecs[prob.track, prob.frame]  # (N, 24, 3)
    posed = np.isfinite(pose).all((1, 2)) & np.isfinite(warm.transl[prob.track, prob.frame]).all(1)
    rotmats[posed] = rotvec_to_matrix(pose[posed])
    transl[posed] = warm.transl[prob.track[posed], prob.frame[posed]] / MM_PER_M
    return rotmats, transl, betas, offsets, scales, seen


def _step_one(
    prob: _Problem, buf: KeypointBuffers, params: FitParams, progress: Progress,
    warm: WarmStart | None = None,
):  # fmt: skip
    """Phase 0 (closed-form root, translation, limbs and betas; or ``warm``'s values),
    then step I by Adam (``params.iters``, or ``params.iters_warm`` from a warm start).
    The betas and offsets of the tracks ``warm`` holds stay as they are (a track's body is
    the one of its first chunk, so all its frames share one shape).
    Returns rotations (N, 24, 3, 3), betas (K, nb), translations (N, 3), the learnt
    keypoint offsets (K, T, 3) or None and bone scales (K, 24) or None, all detached."""
    rotmats0, t_init, betas0, offsets0, scales0, held = _phase_zero(prob, buf, params, warm)
    held_t = torch.as_tensor(held)
    rot6d = matrix_to_rot6d(torch.as_tensor(rotmats0, dtype=torch.float32)).requires_grad_(True)
    transl = torch.as_tensor(t_init, dtype=torch.float32).requires_grad_(True)
    betas = torch.as_tensor(betas0, dtype=torch.float32).requires_grad_(True)
    w_joint = params.w_pose + params.w_free * buf.free_weight  # (24,)
    w_joint[0] = 0.0
    offsets = torch.as_tensor(offsets0, dtype=torch.float32).requires_grad_(True)
    use_offsets = params.w_offset > 0
    use_scales = params.w_bone_scale > 0
    # one log scale per bone group and track (kinematics.SCALED_BONES), from the start's
    # per-joint scales (a group's bones share theirs)
    groups_of = torch.as_tensor(bone_scale_matrix(), dtype=torch.float32)  # (G, 24)
    per_group = np.log(scales0) @ bone_scale_matrix().T / bone_scale_matrix().sum(1)
    log_scales = torch.as_tensor(per_group, dtype=torch.float32).requires_grad_(True)
    # (T, 1): the targets whose offsets this fit learns (the others stay zero)
    learnt = (buf.offset_mask - (0.0 if params.foot_offsets else buf.foot_offset))[:, None]

    def loss_step1() -> torch.Tensor:
        R = rot6d_to_matrix(rot6d)
        b = torch.where(held_t[:, None], betas.detach(), betas) if held.any() else betas
        o = torch.where(held_t[:, None, None], offsets.detach(), offsets) if held.any() else offsets
        off = (o * learnt)[prob.track_rows] if use_offsets else None
        sc = None
        if use_scales:
            ls = log_scales
            if held.any():
                ls = torch.where(held_t[:, None], log_scales.detach(), log_scales)
            sc = torch.exp(ls @ groups_of)  # (K, 24), 1 for the bones no group scales
        loss = _objective(R, b, transl, prob, buf, params, off, sc)
        loss = loss + params.w_betas * (b * b).mean()
        if use_offsets:
            loss = loss + params.w_offset * (o * o).sum(-1).mean()
        if use_scales:
            loss = loss + params.w_bone_scale * (ls * ls).sum(-1).mean()
        if params.w_limit > 0:
            loss = loss + params.w_limit * limit_penalty(R).mean()
        return loss + (_rest_distance(R) * w_joint).sum(1).mean()

    groups = [([rot6d], params.lr_rot), ([transl], params.lr_transl_m), ([betas], params.lr_betas)]
    if use_offsets:
        groups.append(([offsets], params.lr_offset_m))
    if use_scales:
        groups.append(([log_scales], params.lr_bone_scale))
    iters = params.iters if warm is None else params.iters_warm
    adam_cosine(groups, loss_step1, iters, progress=progress, desc="SMPL fit (step I)")
    with torch.no_grad():
        R1 = rot6d_to_matrix(rot6d)
    off1 = (offsets * learnt).detach() if use_offsets else None
    scales1 = torch.exp(log_scales @ groups_of).detach() if use_scales else None
    return R1, betas.detach(), transl.detach(), off1, scales1


def _prior_correction(prob, buf, prior, params, R1, betas, transl, off1, scales, progress):
    """Step I corrected by the VAE pose prior (:func:`correct_with_prior`), the data
    term the same as step I's with its betas, offsets and bone scales held."""
    off_rows = None if off1 is None else off1[prob.track_rows]
    observed = prob.weight > 0

    def objective(R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        return _objective(R, betas, t, prob, buf, params, off_rows, scales)

    def row_residual(R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        kp, _ = predict_targets(
            R, betas, t, buf, off_rows, rows_per_body=prob.rows_per_track, bone_scales=scales
        )
        err = (kp - prob.target).norm(dim=-1) * observed
        return err.sum(1) / observed.sum(1).clamp_min(1)

    return correct_with_prior(
        prior, R1, transl, objective=objective, row_residual=row_residual,
        free_weight=buf.free_weight, params=params, progress=progress,
    )  # fmt: skip


# --------------------------------------------------------------------------- evaluation
