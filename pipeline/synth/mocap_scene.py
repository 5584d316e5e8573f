"""Synthetic multi-view scenes from real motion capture: the truth is the mocap skeleton.

Where :mod:`pipeline.synth.scene_gen` makes people with our own body model and our
own motion generator (so a fit with that model can be exact: circular evidence), this
generator takes people from BVH clips (:mod:`pipeline.mocap.clips`): another skeleton, other
proportions, real motion. What the scene holds:

* **People**: person ``p`` plays clip ``p mod num_clips`` (resampled to the scene's
  fps); a clip used by several people is played from different start frames, spread
  evenly over the clip. Each person's clip segment is turned about the vertical and
  shifted on the floor (never scaled, never lifted: the capture's floor stays z = 0)
  so that its pelvis path lies in the floor area at least ``min_views`` cameras see
  (:func:`pipeline.synth.scene_gen.visible_floor_area`), keeping pelvises 650 mm apart
  where it can (the best of ``placement_tries`` random placements). A segment shorter
  than the scene ends the person: no truth, no detections after it.
* **Ground truth** (``gt.npz``): ``joints3d`` the mocap joints in SMPL-24 slots
  (:data:`pipeline.mocap.clips.CMU_TO_SMPL24`; NaN for pelvis, spine1-3, collars and hands,
  which the skeleton lacks), ``keypoints3d`` COCO-17 (twelve mocap joints and five face
  points derived from the head, :data:`pipeline.mocap.clips.FACE_OFFSETS_MM`). No
  ``smpl_pose``: no body model made these people.
* **Detections**: the 2D detector sees the COCO-17 points above, projected, with the
  noise of :class:`pipeline.synth.detectors.DetectorNoise` (defaults: the shipped
  sample's). Occlusion is decided by a z-buffer of *proxy bodies*: our body model
  fitted to each person's mocap joints (:func:`pipeline.mocap.clips.fit_clips`), rendered at
  ``render_scale`` of the image size; the monocular SMPL regressor is simulated from
  that proxy fit too. Ghost detections (``false_positives_per_view``) are mocap poses
  of the scene's clips at random places and headings, in one view only, without
  regressor output (NaN SMPL rows).
* No videos: the proxy body is not the person, so rendering it would show the wrong
  silhouette.

``scene.json`` records under ``synth`` the clips (file, frames, activity, licence)
and, per person, the clip, its start frame (scene fps) and the floor transform
(``heading_rad``, ``shift_mm``), so the truth can be recomputed from the BVH:
``gt = R_z(heading) @ clip_joints + shift``.

World mm, z up.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from pipeline.body.model import BodyModel
from pipeline.core.progress import track
from pipeline.data.cameras import CameraRig
from pipeline.data.joint_sets import COCO17, SMPL24
from pipeline.data.scene import SMPL_FIELD_WIDTH, SMPL_FIELDS, Detections, GroundTruth, write_scene
from pipeline.mocap.clips import FitParams, MocapClip, fit_clips, load_mocap_clip
from pipeline.synth.detectors import DetectorNoise, simulate_keypoints, simulate_regressor
from pipeline.synth.render import MeshInstance, occluded_by_other, render_meshes, visible_mask
from pipeline.synth.scene_gen import visible_floor_area

MIN_PELVIS_DISTANCE_MM = 650.0
_PELVIS_PROXY = ("Hips", "pelvis")  # the root (BVH, body-model clip), placed in the visible area


@dataclass(frozen=True)
class MocapSceneConfig:
    """What to synthesise from motion capture (see the module docstring)."""

    motions: tuple[str, ...]
    """BVH files; person p plays ``motions[p % len(motions)]``."""
    num_people: int = 2
    num_frames: int = 250
    fps: float = 25.0
    seed: int = 0
    noise: DetectorNoise = field(default_factory=DetectorNoise)
    min_views: int = 3
    render_scale: float = 0.5
    """Size of the occlusion z-buffer relative to each image."""
    placement_tries: int = 300
    fit: FitParams = field(default_factory=lambda: FitParams(iters=200))
    """The proxy bodies' fit (occlusion and the simulated regressor only)."""


@dataclass(frozen=True, eq=False)
class MocapPeople:
    """P people over F frames, world mm; NaN where a person is absent.

    Attributes:
        joints: (P, F, 24, 3) mocap joints in SMPL-24 slots (NaN where unmapped).
        keypoints: (P, F, 17, 3) COCO-17 (mocap joints, derived face).
        present: (P, F) bool.
        proxy_pose: (P, F, 24, 3), proxy_betas (P, 10), proxy_transl (P, F, 3): our
            body model fitted to ``joints`` (occlusion, regressor).
        people: per person the record written to scene.json.
    """

    joints: np.ndarray
    keypoints: np.ndarray
    present: np.ndarray
    proxy_pose: np.ndarray
    proxy_betas: np.ndarray
    proxy_transl: np.ndarray
    people: list[dict]


def rotate_z(points: np.ndarray, heading: float) -> np.ndarray:
    """(..., 3) points turned by ``heading`` radians about the world z axis."""
    c, s = np.cos(heading), np.sin(heading)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return points @ R.T


def place_on_floor(clip_points: np.ndarray, heading: float, shift_xy: np.ndarray) -> np.ndarray:
    """(..., 3) clip points -> world: turned by ``heading`` about z, then shifted in x, y."""
    return rotate_z(clip_points, heading) + np.array([shift_xy[0], shift_xy[1], 0.0])


def _segments(clips: list[MocapClip], num_people: int, num_frames: int) -> list[tuple[int, int]]:
    """(clip index, start frame) per person: clips in turn, starts spread over a clip."""
    uses: dict[int, int] = {}
    out = []
    for p in range(num_people):
        c = p % len(clips)
        uses[c] = uses.get(c, 0) + 1
    seen: dict[int, int] = {}
    for p in range(num_people):
        c = p % len(clips)
        k = seen.get(c, 0)
        seen[c] = k + 1
        slack = max(clips[c].num_frames - num_frames, 0)
        out.append((c, int(round(slack * (k + 1) / (uses[c] + 1)))))
    return out


def _inside(area: np.ndarray, xy: np.ndarray, spacing: float) -> np.ndarray:
    """(N,) whether each floor point lies within a grid cell of the visible area."""
    d = np.abs(xy[:, None, :] - area[None, :, :]).max(-1)
    return (d <= 0.5 * spacing + 1e-6).any(1)


def plan_placements(
    rng: np.random.Generator,
    area: np.ndarray,
    paths: list[np.ndarray],
    *,
    tries: int = 300,
    spacing_mm: float = 200.0,
) -> list[tuple[float, np.ndarray]]:
    """A heading and floor shift per person so that each pelvis path (F_p, 2) lies in the
    visible ``area`` and people keep :data:`MIN_PELVIS_DISTANCE_MM` apart.

    Person by person, the best of ``tries`` random placements (heading uniform, path
    centre on a random area point): most frames inside, then fewest frames too close to
    people already placed.
    """
    placed: list[np.ndarray] = []
    out = []
    for path in paths:
        centre = 0.5 * (path.min(0) + path.max(0))
        best, best_score = None, None
        for _ in range(tries):
            heading = float(rng.uniform(-np.pi, np.pi))
            spot = area[rng.integers(len(area))]
            c, s = np.cos(heading), np.sin(heading)
            xy = (path - centre) @ np.array([[c, -s], [s, c]]).T + spot
            inside = _inside(area, xy, spacing_mm).mean()
            close = 0
            for other in placed:
                n = min(len(other), len(xy))
                close += int(
                    (np.linalg.norm(other[:n] - xy[:n], axis=1) < MIN_PELVIS_DISTANCE_MM).sum()
                )
            score = (round(inside, 2), -close)
            if best_score is None or score > best_score:
                shift = spot - np.array([[c, -s], [s, c]]) @ centre
                best, best_score = (heading, shift, xy), score
        heading, shift, xy = best
        placed.append(xy)
        out.append((heading, shift))
    return out


def plan_people_from_mocap(
    clips: list[MocapClip],
    rig: CameraRig,
    model: BodyModel,
    config: MocapSceneConfig,
    rng: np.random.Generator,
    *,
    progress: bool = False,
) -> MocapPeople:
    """Segments, placements, truth and proxy bodies of every person."""
    P, F = config.num_people, config.num_frames
    area = visible_floor_area(rig, min_views=config.min_views)
    segs = _segments(clips, P, F)
    root = [next(c.joint_names.index(n) for n in _PELVIS_PROXY if n in c.joint_names)
            for c in clips]  # fmt: skip
    paths = [clips[c].skeleton[s : s + F, root[c], :2] for c, s in segs]
    places = plan_placements(rng, area, paths, tries=config.placement_tries)
    joints = np.full((P, F, SMPL24.num_joints, 3), np.nan)
    keypoints = np.full((P, F, COCO17.num_joints, 3), np.nan)
    present = np.zeros((P, F), bool)
    people = []
    for p, ((c, s), (heading, shift)) in enumerate(zip(segs, places, strict=True)):
        clip = clips[c]
        n = min(F, clip.num_frames - s)
        joints[p, :n] = place_on_floor(clip.smpl24[s : s + n], heading, shift)
        keypoints[p, :n] = place_on_floor(clip.coco17[s : s + n], heading, shift)
        present[p, :n] = True
        people.append(
            {
                "person_id": p,
                "clip": clip.path.name,
                "start_frame": s,
                "num_frames": int(n),
                "heading_rad": heading,
                "shift_mm": [float(shift[0]), float(shift[1])],
            }
        )
    # Proxy bodies: our model fitted to every person's mocap joints (one batch).
    proxies = [
        replace(clips[c], smpl24=joints[p, :n], skeleton=joints[p, :n], name=str(p))
        for p, (c, _) in enumerate(segs)
        for n in [people[p]["num_frames"]]
    ]
    fits = fit_clips(proxies, model, params=config.fit, progress=progress)
    pose = np.full((P, F, 24, 3), np.nan)
    transl = np.full((P, F, 3), np.nan)
    betas = np.stack([f.betas for f in fits])
    for p, f in enumerate(fits):
        n = people[p]["num_frames"]
        pose[p, :n], transl[p, :n] = f.pose_rotvecs, f.transl
        people[p]["proxy_fit_residual_mm"] = round(float(np.nanmean(f.residual)), 1)
    return MocapPeople(joints, keypoints, present, pose, betas, transl, people)


def _ghost_rows(
    rng: np.random.Generator, cam, area: np.ndarray, pool: np.ndarray, n: int
) -> np.ndarray:
    """(m <= n, 17, 3) ghost keypoints in one view: mocap COCO-17 poses from ``pool``
    (K, 17, 3), re-centred on random floor points with random headings, noisy, low
    confidence; those with fewer than 8 keypoints in the image are dropped."""
    out = []
    for _ in range(n):
        kp = pool[rng.integers(len(pool))]
        centre = np.nanmean(kp[[COCO17.index["left_hip"], COCO17.index["right_hip"]]], 0)
        spot = area[rng.integers(len(area))]
        world = rotate_z(kp - [centre[0], centre[1], 0.0], rng.uniform(-np.pi, np.pi))
        world[:, :2] += spot
        uv = cam.project(world)
        in_img = (
            np.isfinite(uv).all(1) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width)
            & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        )  # fmt: skip
        if in_img.sum() < 8:
            continue
        conf = rng.uniform(0.25, 0.55, len(uv))
        g = np.concatenate([uv + rng.normal(0, 3, uv.shape), conf[:, None]], 1)
        off = (g[:, 0] < 0) | (g[:, 0] >= cam.width) | (g[:, 1] < 0) | (g[:, 1] >= cam.height)
        g[off | ~np.isfinite(g[:, :2]).all(1)] = (np.nan, np.nan, 0.0)
        out.append(g)
    return np.stack(out) if out else np.zeros((0, COCO17.num_joints, 3))


def synthesize_from_mocap(
    rig: CameraRig,
    model: BodyModel,
    config: MocapSceneConfig,
    *,
    progress: bool = True,
    clips: list[MocapClip] | None = None,
) -> tuple[MocapPeople, list[MocapClip], Detections]:
    """Plan people from the clips, render the proxy bodies for occlusion, detect.

    ``clips``: already loaded clips (e.g. :func:`pipeline.mocap.clips.clip_from_body`) instead
    of ``config.motions``."""
    if clips is None and not config.motions:
        raise ValueError("no motion clips given")
    if config.num_people < 1 or config.num_frames < 1:
        raise ValueError("num_people and num_frames must be >= 1")
    rng = np.random.default_rng(config.seed)
    noise = config.noise
    if clips is None:
        clips = [load_mocap_clip(m, fps=config.fps) for m in config.motions]
    people = plan_people_from_mocap(clips, rig, model, config, rng, progress=False)
    area = visible_floor_area(rig, min_views=config.min_views)
    pool = np.concatenate([c.coco17[:: max(1, c.num_frames // 50)] for c in clips])
    faces = model.faces.numpy()
    betas_t = torch.as_tensor(people.proxy_betas, dtype=torch.float32)
    rows: dict[str, list] = {
        k: [] for k in ("frame", "view", "keypoints", "gt_person_id") + SMPL_FIELDS
    }
    for f in track(range(config.num_frames), "mocap synth", progress, unit="frame"):
        live = np.flatnonzero(people.present[:, f])
        if live.size == 0:
            continue
        with torch.no_grad():
            out = model(torch.as_tensor(people.proxy_pose[live, f], dtype=torch.float32),
                        betas_t[live])  # fmt: skip
        verts = out.vertices.double().numpy() * 1000 + people.proxy_transl[live, f, None]
        smpl_joints = out.joints.double().numpy() * 1000 + people.proxy_transl[live, f, None]
        meshes = [MeshInstance(vertices=v, faces=faces) for v in verts]
        kp3d = people.keypoints[live, f]  # (L, 17, 3)
        pts = kp3d.reshape(-1, 3)
        ids = np.repeat(np.arange(live.size), COCO17.num_joints)
        for v, cam in enumerate(rig):
            render = render_meshes(cam, meshes, scale=config.render_scale)
            vis = visible_mask(
                render, cam, pts, ids, tolerance_mm=noise.self_occlusion_tolerance_mm
            ).reshape(live.size, -1)
            other = occluded_by_other(render, cam, pts, ids).reshape(live.size, -1)
            self_occ = ~vis & ~other
            kp, detected = simulate_keypoints(
                rng, cam, cam.project(pts).reshape(live.size, -1, 2), self_occ, other, noise
            )
            order = rng.permutation(np.flatnonzero(detected))
            if order.size:
                reg = simulate_regressor(
                    rng, cam, people.proxy_pose[live[order], f], people.proxy_betas[live[order]],
                    cam.project(smpl_joints[order].reshape(-1, 3)).reshape(order.size, -1, 2),
                    model, noise,
                )  # fmt: skip
                _append(rows, f, v, kp[order], live[order], reg)
            n_ghost = rng.poisson(noise.false_positives_per_view)
            if n_ghost:
                g = _ghost_rows(rng, cam, area, pool, n_ghost)
                if len(g):
                    nan = {k: np.full((len(g), SMPL_FIELD_WIDTH[k]), np.nan) for k in SMPL_FIELDS}
                    _append(rows, f, v, g, np.full(len(g), -1), nan)
    n = sum(len(x) for x in rows["frame"])
    cat = {k: np.concatenate(v) if v else None for k, v in rows.items()}
    detections = Detections(
        frame=cat["frame"] if n else np.zeros(0, int),
        view=cat["view"] if n else np.zeros(0, int),
        keypoints=cat["keypoints"] if n else np.zeros((0, COCO17.num_joints, 3)),
        gt_person_id=cat["gt_person_id"] if n else np.zeros(0, int),
        smpl_pose=cat["smpl_pose"] if n else np.zeros((0, 72)),
        smpl_betas=cat["smpl_betas"] if n else np.zeros((0, 10)),
        cam_weak=cat["cam_weak"] if n else np.zeros((0, 3)),
        bbox=cat["bbox"] if n else np.zeros((0, 4)),
    )
    return people, clips, detections


def _append(rows: dict, frame: int, view: int, kp: np.ndarray, person: np.ndarray, reg: dict):
    m = kp.shape[0]
    rows["frame"].append(np.full(m, frame))
    rows["view"].append(np.full(m, view))
    rows["keypoints"].append(kp)
    rows["gt_person_id"].append(np.asarray(person))
    for k in SMPL_FIELDS:
        rows[k].append(reg[k])


def mocap_ground_truth(people: MocapPeople) -> GroundTruth:
    """The mocap truth of the present person-frames (no SMPL parameters)."""
    p, f = np.nonzero(people.present)
    return GroundTruth(
        frame=f, person_id=p, joints3d=people.joints[p, f], keypoints3d=people.keypoints[p, f]
    )


def write_mocap_scene(
    out_dir: str | os.PathLike,
    rig: CameraRig,
    model: BodyModel,
    config: MocapSceneConfig,
    *,
    name: str | None = None,
    overwrite: bool = False,
    progress: bool = True,
    clips: list[MocapClip] | None = None,
) -> Path:
    """Synthesise from motion capture (or ``clips``) and write a native scene directory
    atomically."""
    out_dir = Path(out_dir)
    people, clips, detections = synthesize_from_mocap(
        rig, model, config, progress=progress, clips=clips
    )
    return write_scene(
        out_dir,
        name=name or out_dir.name,
        fps=config.fps,
        num_frames=config.num_frames,
        joint_set=COCO17,
        rig=rig,
        detections=detections,
        gt=mocap_ground_truth(people),
        extra_meta={
            "synth": {
                "kind": "mocap",
                "seed": config.seed,
                "num_people": config.num_people,
                "clips": [dict(c.info(), file=str(c.path)) for c in clips],
                "people": people.people,
                "body_model": os.path.basename(model.source),
                "render_scale": config.render_scale,
                "noise": {k: getattr(config.noise, k) for k in config.noise.__dataclass_fields__},
            }
        },
        overwrite=overwrite,
    )
