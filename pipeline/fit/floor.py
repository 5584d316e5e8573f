"""The floor a body fit is judged by: the best skeleton of constant bone lengths.

A body of fixed proportions (SMPL with one shape per track, any bone scales held over
the track) cannot follow joints whose distances change from frame to frame; triangulated
and smoothed joints are not rigid (on Pose2Sim's real balancing trial the RTS bone
lengths vary with a median std of 18 mm). How close a constant-proportion skeleton can
come is measured here: per track, the skeleton of the joint set's bones (a spanning tree
of them, from the joint of most bones) with one length per bone for the whole track and a
free 3D direction per bone and frame, fitted to the joints with the body fit's own
robust data term (Smooth L1). Its residual is the input's own non-rigidity, the mark a
fit's distance to its input is read against: a fit far above it has something left to
gain. A body's keypoints are not quite a rigid stick skeleton (regressed from the skinned
surface, their distances change a little with the pose), so a fit can land somewhat
under it, as on synthetic scenes whose keypoints are the body model's own.

Solved for all tracks at once by Adam on the root positions, bone directions and
lengths, started from the step-I body's keypoints where given (else the measured joints)
and the track's median bone lengths, which is most of the way. Units: mm outside,
metres inside.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from pipeline.body.arrays import ancestry
from pipeline.core.progress import Progress
from pipeline.core.torch_threads import torch_threads
from pipeline.fit.optim import adam_cosine

FLOOR_ITERATIONS = 150  # converged on the samples and the real trials' subjects


@dataclass(frozen=True, eq=False)
class RigidFloor:
    """Per track, the best constant-bone-length skeleton fitted to its joints.

    Attributes:
        joints: (K, F, J, 3) mm, the skeleton's joints (NaN where the track is absent).
        distance: (K, F) mm, mean distance of the skeleton's joints to the input's
            (over the joints the input has).
        bone_lengths: (K, B) mm, one per bone of the spanning tree ``bones``.
        bones: (B, 2) (parent, child) joint indices of the tree.
    """

    joints: np.ndarray
    distance: np.ndarray
    bone_lengths: np.ndarray
    bones: np.ndarray

    def median(self) -> np.ndarray:
        """(K,) each track's median over frames of :attr:`distance`, mm (NaN: no frame)."""
        d = self.distance
        out = np.full(d.shape[0], np.nan)
        for k in range(d.shape[0]):
            v = d[k][np.isfinite(d[k])]
            if v.size:
                out[k] = float(np.median(v))
        return out


def spanning_tree(bones: np.ndarray, num_joints: int) -> tuple[np.ndarray, np.ndarray]:
    """The joint set's bones as a tree rooted at its joint of most bones (joints no bone
    reaches are roots of their own): (J,) parents (-1 at roots) and (B, 2) (parent,
    child) pairs, breadth first."""
    bones = np.asarray(bones, int).reshape(-1, 2)
    neighbours: list[list[int]] = [[] for _ in range(num_joints)]
    for a, b in bones:
        neighbours[a].append(b)
        neighbours[b].append(a)
    parent = np.full(num_joints, -1)
    seen = np.zeros(num_joints, bool)
    pairs = []
    for root in sorted(range(num_joints), key=lambda j: -len(neighbours[j])):
        if seen[root]:
            continue
        seen[root] = True
        todo = [root]
        while todo:
            j = todo.pop(0)
            for n in neighbours[j]:
                if not seen[n]:
                    seen[n] = True
                    parent[n] = j
                    pairs.append((j, n))
                    todo.append(n)
    return parent, np.array(pairs, int).reshape(-1, 2)


def _initial_skeleton(y, w, k_idx, f_idx, parent, pairs, num_tracks):
    """Where the fit starts: (N, J, 3) the joints (each where measured, else its parent's,
    a root the frame's mean), (N, B, 3) unit bone directions (a bone not measured in a
    frame as in the track's nearest frame that has it) and (K, B) each track's median
    bone lengths, metres."""
    B = len(pairs)
    filled = np.where(w[..., None], y, np.nan)
    centre = np.nanmean(filled, axis=1)  # (N, 3)
    for root in np.flatnonzero(parent < 0):
        miss = ~w[:, root]
        filled[miss, root] = centre[miss]
    for p, c in pairs:
        miss = ~w[:, c]
        filled[miss, c] = filled[miss, p]  # pairs are breadth first: p is filled
    vec = filled[:, pairs[:, 1]] - filled[:, pairs[:, 0]]  # (N, B, 3)
    length = np.linalg.norm(vec, axis=-1)  # (N, B)
    measured = w[:, pairs[:, 0]] & w[:, pairs[:, 1]]
    lengths0 = np.full((num_tracks, B), 0.05)
    unit = vec / np.maximum(length, 1e-9)[..., None]
    direction0 = np.zeros_like(unit)
    for k in np.unique(k_idx):
        sel = np.flatnonzero(k_idx == k)
        for b in range(B):
            m = measured[sel, b]
            if not m.any():
                direction0[sel, b] = (0.0, 0.0, 1.0)
                continue
            have = sel[m]
            near = np.abs(f_idx[sel][:, None] - f_idx[have][None]).argmin(1)
            direction0[sel, b] = unit[have[near], b]
            lengths0[k, b] = np.median(length[have, b])
    return filled, direction0, lengths0


def _bone_paths(parent: np.ndarray, pairs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(J, B) 1.0 where bone ``b`` lies between joint ``j``'s root and ``j`` (a joint is
    its root plus those bone vectors), and (J,) each joint's root."""
    J, B = len(parent), len(pairs)
    anc = np.zeros((J, B))
    child_bone = {int(c): b for b, c in enumerate(pairs[:, 1])}
    root_of = np.zeros(J, int)
    A = ancestry(parent)  # (J, J): joint j's ancestors-or-self
    for j in range(J):
        for a in np.flatnonzero(A[j]):
            if a in child_bone:
                anc[j, child_bone[a]] = 1.0
            elif parent[a] < 0:
                root_of[j] = a
    return anc, root_of


def rigid_floor(
    tracks_mm: np.ndarray,
    bones: np.ndarray,
    *,
    iterations: int = FLOOR_ITERATIONS,
    beta_m: float = 0.05,
    start_mm: np.ndarray | None = None,
    progress: Progress = False,
) -> RigidFloor:
    """Fit every track's constant-bone-length skeleton (module docstring).

    Args:
        tracks_mm: (K, F, J, 3) joints, mm, NaN where absent (the fit's input: the
            RTS-smoothed tracks).
        bones: (B0, 2) the joint set's bones (any graph; its spanning tree is used).
        beta_m: the Smooth L1 switch point, metres (the fit's ``smooth_l1_beta_m``).
        start_mm: optional (K, F, J, 3) joints to start from where they are finite (a
            body fit's keypoints: a body of constant proportions, so the floor starts at
            or under the fit and only goes down; without it, a partly seen person's
            skeleton started from its noisy joints stopped above the fit, 37.9 against
            27.5 mm on the balancing trial's second person).
    """
    x = np.asarray(tracks_mm, float)
    K, F, J = x.shape[:3]
    parent, pairs = spanning_tree(bones, J)
    B = len(pairs)
    observed = np.isfinite(x).all(-1)  # (K, F, J)
    rows = observed.any(-1)  # (K, F) person-frames
    out_joints = np.full(x.shape, np.nan)
    out_dist = np.full((K, F), np.nan)
    out_len = np.full((K, B), np.nan)
    k_idx, f_idx = np.nonzero(rows)
    if len(k_idx) == 0 or B == 0:
        return RigidFloor(out_joints, out_dist, out_len, pairs)
    y = x[k_idx, f_idx] / 1000.0  # (N, J, 3) m
    w = observed[k_idx, f_idx]  # (N, J)
    y0, w0 = y, w
    if start_mm is not None:
        s0 = np.asarray(start_mm, float)[k_idx, f_idx] / 1000.0
        have = np.isfinite(s0).all(-1)
        y0, w0 = np.where(have[..., None], s0, y), have | w
    filled, direction0, lengths0 = _initial_skeleton(y0, w0, k_idx, f_idx, parent, pairs, K)
    anc, root_of = _bone_paths(parent, pairs)
    anc_t = torch.as_tensor(anc)
    track_t = torch.as_tensor(k_idx)
    # NaN x 0 is NaN: missing joints enter as zeros of zero weight
    y_t = torch.as_tensor(np.where(w[..., None], y, 0.0))
    w_t = torch.as_tensor(w, dtype=torch.float64)
    root_pos = torch.tensor(np.ascontiguousarray(filled[:, parent < 0])).requires_grad_(True)
    roots = np.flatnonzero(parent < 0)
    root_slot = torch.as_tensor(np.searchsorted(roots, root_of))
    direction = torch.as_tensor(direction0).requires_grad_(True)
    log_len = torch.as_tensor(np.log(np.maximum(lengths0, 1e-4))).requires_grad_(True)

    def joints_now() -> torch.Tensor:
        unit = direction / direction.norm(dim=-1, keepdim=True).clamp_min(1e-9)
        bone_vec = unit * torch.exp(log_len)[track_t][..., None]  # (N, B, 3)
        return root_pos[:, root_slot] + torch.einsum("jb,nbc->njc", anc_t, bone_vec)

    def loss_fn() -> torch.Tensor:
        # the body fit's robust data term (Smooth L1, quadratic below ``beta_m``), so that
        # a joint far off in some frames weighs on the floor as it does on the fit
        r = torch.nn.functional.smooth_l1_loss(joints_now(), y_t, reduction="none", beta=beta_m)
        return (r.sum(-1) * w_t).sum() / w_t.sum()

    with torch_threads(1):  # small ops: one thread is faster and steadier (FitParams)
        adam_cosine(
            [([root_pos], 0.002), ([direction], 0.02), ([log_len], 0.01)],
            loss_fn, iterations, progress=progress, desc="rigid floor",
        )  # fmt: skip
    with torch.no_grad():
        fitted = joints_now().numpy() * 1000.0
        lengths = np.exp(log_len.numpy()) * 1000.0
    dist = np.linalg.norm(fitted - np.where(w[..., None], y, 0.0) * 1000.0, axis=-1)  # (N, J)
    dist = np.where(w, dist, 0.0).sum(1) / np.maximum(w.sum(1), 1)
    out_joints[k_idx, f_idx] = fitted
    out_dist[k_idx, f_idx] = dist
    seen = np.unique(k_idx)
    out_len[seen] = lengths[seen]
    return RigidFloor(out_joints, out_dist, out_len, pairs)
