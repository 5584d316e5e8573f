"""Synthetic multi-view scenes with ground truth: people with different body shapes move
in the area a real rig sees; every view is rendered with a z-buffer (the same z-buffer
decides which joints are occluded) and fed to the simulated detectors.

Deterministic for a seed. World mm, z up.
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch

from pipeline.body.keypoints import KeypointRegressor, keypoint_regressor, layout_keypoints
from pipeline.body.model import BodyModel
from pipeline.core.progress import track
from pipeline.core.torch_threads import torch_threads
from pipeline.data.cameras import Camera, CameraRig
from pipeline.data.joint_sets import SMPL24, JointSet, get_joint_set
from pipeline.data.scene import Detections, GroundTruth, write_scene
from pipeline.synth.detection_rows import DetectionRows
from pipeline.synth.detectors import DetectorNoise, simulate_keypoints, simulate_regressor
from pipeline.synth.motion import (
    PersonMotion,
    plan_people,
    pose_from_params,
    root_to_world,
    sample_pose_library,
)
from pipeline.synth.occlusion import point_occlusion
from pipeline.synth.proxy import pose_proxy, proxy_bodies, proxy_for
from pipeline.synth.render import (
    MeshInstance,
    Render,
    occluded_by_other,
    render_background,
    render_meshes,
    visible_mask,
)

# Clothing colours (RGB), one per person; the viewer uses its own palette.
PERSON_COLOURS = (
    (200, 70, 60), (60, 120, 200), (80, 170, 90), (210, 170, 60),
    (150, 90, 190), (60, 180, 180), (220, 120, 170), (130, 130, 130),
)  # fmt: skip


@dataclass(frozen=True)
class SynthConfig:
    """What to synthesise. ``video_scale`` < 1 writes smaller videos (detection always
    runs on full-resolution renders)."""

    num_people: int = 4
    num_frames: int = 250
    fps: float = 25.0
    seed: int = 0
    render_video: bool = True
    video_scale: float = 1.0
    noise: DetectorNoise = field(default_factory=DetectorNoise)
    min_views: int = 3
    """Waypoints lie where at least this many cameras see a whole standing person."""
    joint_set: str = "coco17"
    """Layout of the ground-truth keypoints and the simulated 2D detections, read off the
    mesh by the table of :mod:`pipeline.body.keypoints` (keypoints it cannot give are
    NaN in the truth and never detected)."""
    area_radius_mm: float | None = None
    """People stand within this distance (floor plane) of the mean of the camera
    centres, e.g. a dome's capture circle; None: anywhere ``min_views`` cameras see."""
    occlusion: str = "render"
    """How occluded keypoints are found: ``"render"`` reads the z-buffer of each view's
    full render (the mesh at full resolution); ``"proxy"`` evaluates the depth of a
    50 mm decimated body at the keypoints' pixels only, all views at once
    (:mod:`pipeline.synth.occlusion`; dome:16 x 10 people ~0.06 CPU s a frame against
    ~3 for renders, the same statistics within about a percent, see
    bench/bench_synth.py and tests/pipeline/synth); ``"auto"``: render when videos are
    written (the render is made anyway), proxy otherwise (``mvviz synth``'s default).
    The library default stays ``"render"``: scenes made by code keep their numbers."""
    torch_threads: int = 1
    """Torch intra-op threads while synthesising (restored after); 0 keeps torch's own
    setting. The tensors are small (a frame's people, a few hundred detections): extra
    threads only wait on each other, and on a loaded 2-core machine torch's default made
    a dome:16 x 10 frame 3.5 times slower (bench/bench_synth.py); outputs are the same."""
    batch_frames: int = 16
    """Proxy occlusion only: the monocular regressor runs once per this many frames (the
    people and ghosts of all their views in one call; a call costs ~15 ms besides its
    rows). 1: frame by frame, the random draws, and so the detections, of the path
    before batching (the statistics are the same, tests/pipeline/synth)."""


@dataclass(frozen=True, eq=False)
class SynthPeople:
    """Ground-truth bodies. pose (P, F, 24, 3) world root; betas (P, 10); transl (P, F, 3) mm;
    joints (P, F, 24, 3) mm; keypoints (P, F, T, 3) in ``joint_set`` (default COCO-17)
    read off the mesh, mm, NaN where the body model cannot give them."""

    pose: np.ndarray
    betas: np.ndarray
    transl: np.ndarray
    joints: np.ndarray
    keypoints: np.ndarray
    joint_set: str = "coco17"


def visible_floor_area(
    rig: CameraRig,
    *,
    min_views: int = 3,
    spacing_mm: float = 200.0,
    margin_px: float = 10.0,
    within_mm: float | None = None,
) -> np.ndarray:
    """(K, 2) floor points where a standing person (feet, pelvis and head) is inside the
    image of at least ``min_views`` cameras, 1.2 m or more away from each of them (and
    within ``within_mm`` of the cameras' mean centre on the floor, when given)."""
    centres = rig.centers[:, :2]
    lo, hi = centres.min(0) - 3000, centres.max(0) + 3000
    gx, gy = np.meshgrid(np.arange(lo[0], hi[0], spacing_mm), np.arange(lo[1], hi[1], spacing_mm))
    pts = np.stack([gx.ravel(), gy.ravel()], -1)
    if within_mm is not None:
        pts = pts[np.linalg.norm(pts - centres.mean(0), axis=1) <= within_mm]
    count = np.zeros(len(pts), int)
    for cam in rig:
        ok = np.linalg.norm(pts - cam.center[:2], axis=1) > 1200
        for h in (0.0, 900.0, 1700.0):  # feet, pelvis, head
            uv = cam.project(np.column_stack([pts, np.full(len(pts), h)]))
            ok &= (
                np.isfinite(uv).all(1)
                & (uv[:, 0] > margin_px)
                & (uv[:, 0] < cam.width - margin_px)
                & (uv[:, 1] > margin_px)
                & (uv[:, 1] < cam.height - margin_px)
            )
        count += ok
    area = pts[count >= min(min_views, len(rig))]
    if len(area) < 10:
        raise ValueError(
            f"fewer than 10 floor points are seen by {min_views} cameras; "
            "is the rig's world z axis up, in millimetres?"
        )
    return area


def bodies_from_motion(
    motions: list[PersonMotion], model: BodyModel, *, chunk: int = 64, joint_set: str = "coco17"
) -> SynthPeople:
    """Turn planned motions into world poses with feet on the floor (z = 0); keypoints in
    ``joint_set``."""
    reg = keypoint_regressor(model, joint_set)
    P, F = len(motions), len(motions[0].heading)
    pose = np.zeros((P, F, 24, 3))
    transl = np.zeros((P, F, 3))
    joints = np.zeros((P, F, 24, 3))
    keypoints = np.zeros((P, F, len(reg.fitted), 3))
    for p, m in enumerate(motions):
        local = pose_from_params(m.params)
        local[:, 0] = root_to_world(m.heading, local[:, 0])
        pose[p] = local
        betas = torch.as_tensor(np.tile(m.betas, (F, 1)), dtype=torch.float32)
        for s in range(0, F, chunk):
            sl = slice(s, s + chunk)
            with torch.no_grad():
                out = model(torch.as_tensor(local[sl], dtype=torch.float32), betas[sl])
                coco = layout_keypoints(reg, out.vertices, out.joints).numpy() * 1000
            v = out.vertices.numpy() * 1000
            j = out.joints.numpy() * 1000
            # Lowest vertex on the floor; pelvis over the planned floor position.
            t = np.zeros((v.shape[0], 3))
            t[:, 2] = -v[..., 2].min(1)
            t[:, :2] = m.position[sl] - j[:, 0, :2]
            transl[p, sl] = t
            joints[p, sl] = j + t[:, None]
            keypoints[p, sl] = coco + t[:, None]
    return SynthPeople(
        pose=pose,
        betas=np.stack([m.betas for m in motions]),
        transl=transl,
        joints=joints,
        keypoints=keypoints,
        joint_set=reg.joint_set,
    )


def _ghosts(
    rng: np.random.Generator,
    cam,
    area: np.ndarray,
    library: np.ndarray,
    model: BodyModel,
    n: int,
    reg: KeypointRegressor,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``n`` phantom people for one view: (n, T, 2) keypoints, (n, 24, 2) SMPL joints, poses."""
    pose = library[rng.integers(len(library), size=n)].reshape(n, 24, 3).copy()
    pose[:, 0] = root_to_world(rng.uniform(-np.pi, np.pi, n), np.zeros((n, 3)))
    betas = rng.normal(0, 1, (n, 10))
    with torch.no_grad():
        out = model(torch.as_tensor(pose, dtype=torch.float32), torch.as_tensor(betas).float())
    v = out.vertices.numpy() * 1000
    spot = area[rng.integers(len(area), size=n)]
    shift = np.column_stack([spot - out.joints.numpy()[:, 0, :2] * 1000, -v[..., 2].min(1)])
    coco = layout_keypoints(reg, out.vertices, out.joints).numpy() * 1000 + shift[:, None]
    smpl = out.joints.numpy() * 1000 + shift[:, None]
    return cam.project(coco), cam.project(smpl), (pose, betas)


@dataclass(frozen=True, eq=False)
class _Simulation:
    """What every view of every frame needs to simulate its detections."""

    model: BodyModel
    kreg: KeypointRegressor
    js: JointSet
    defined: np.ndarray  # (T,) bool: keypoints the body model gives; the others never detected
    noise: DetectorNoise
    area: np.ndarray  # floor points where ghosts may stand, mm
    library: np.ndarray  # poses ghosts take


def _open_writers(
    rig: CameraRig, config: SynthConfig, video_dir: Path | None
) -> dict[str, tuple[cv2.VideoWriter, tuple[int, int]]]:
    """camera name -> (video writer, frame size) when videos are asked for."""
    writers = {}
    if video_dir is None or not config.render_video:
        return writers
    for cam in rig:
        size = (int(round(cam.width * config.video_scale)) // 2 * 2,
                int(round(cam.height * config.video_scale)) // 2 * 2)  # fmt: skip
        w = cv2.VideoWriter(
            str(video_dir / f"{cam.name}.mp4"),
            cv2.VideoWriter_fourcc(*"mp4v"),
            config.fps,
            size,
        )
        if not w.isOpened():
            raise RuntimeError(f"cannot open a video writer for {video_dir / cam.name}.mp4")
        writers[cam.name] = (w, size)
    return writers


def _detect_view(
    rng: np.random.Generator,
    sim: _Simulation,
    cam: Camera,
    render: Render,
    coco: np.ndarray,
    people: SynthPeople,
    f: int,
    v: int,
    rows: DetectionRows,
) -> None:
    """Simulated detections of frame ``f`` in view ``v`` appended to ``rows``: the people
    the render shows (``coco`` (P, T, 3) mm their keypoints), then ghosts."""
    P, js, defined = coco.shape[0], sim.js, sim.defined
    pts = coco[:, defined].reshape(-1, 3)
    ids = np.repeat(np.arange(P), int(defined.sum()))
    vis = np.zeros((P, js.num_joints), bool)
    other = np.zeros((P, js.num_joints), bool)
    vis[:, defined] = visible_mask(
        render, cam, pts, ids, tolerance_mm=sim.noise.self_occlusion_tolerance_mm
    ).reshape(P, -1)
    other[:, defined] = occluded_by_other(render, cam, pts, ids).reshape(P, -1)
    self_occ = ~vis & ~other
    true_2d = cam.project(coco)
    kp, detected = simulate_keypoints(
        rng, cam, true_2d, self_occ, other, sim.noise, joint_set=js, defined=defined
    )
    order = rng.permutation(np.flatnonzero(detected))  # detector order is arbitrary
    n_ghost = rng.poisson(sim.noise.false_positives_per_view)
    if order.size:
        smpl2d = cam.project(people.joints[order, f])
        reg = simulate_regressor(
            rng, cam, people.pose[order, f], people.betas[order], smpl2d, sim.model, sim.noise
        )
        rows.append(f, v, kp[order], order, reg)
    if n_ghost:
        _detect_ghosts(rng, sim, cam, n_ghost, f, v, rows)


def _detect_ghosts(
    rng: np.random.Generator,
    sim: _Simulation,
    cam: Camera,
    n_ghost: int,
    f: int,
    v: int,
    rows: DetectionRows,
) -> None:
    """``n_ghost`` false detections (person -1) in the view, those at least 8 of whose
    keypoints land in the image, appended to ``rows``."""
    ghosts = _ghost_keypoints(rng, sim, cam, n_ghost)
    if ghosts is None:
        return
    g_kp, g_pose, g_betas, g_smpl = ghosts
    reg = simulate_regressor(rng, cam, g_pose, g_betas, g_smpl, sim.model, sim.noise)
    rows.append(f, v, g_kp, np.full(len(g_kp), -1), reg)


def _ghost_keypoints(
    rng: np.random.Generator, sim: _Simulation, cam: Camera, n_ghost: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """The 2D detections of ``n_ghost`` phantom people in the view, those at least 8 of
    whose keypoints land in the image: keypoints (n, T, 3), pose (n, 24, 3), betas
    (n, 10), SMPL joints (n, 24, 2) px; None if none lands."""
    g_coco, g_smpl, (g_pose, g_betas) = _ghosts(
        rng, cam, sim.area, sim.library, sim.model, n_ghost, sim.kreg
    )
    in_img = (
        (g_coco[..., 0] >= 0) & (g_coco[..., 0] < cam.width)
        & (g_coco[..., 1] >= 0) & (g_coco[..., 1] < cam.height)
    )  # fmt: skip
    inside = in_img.sum(1) >= 8
    if not inside.any():
        return None
    g_coco, g_smpl = g_coco[inside], g_smpl[inside]
    conf = np.clip(rng.uniform(0.25, 0.55, g_coco.shape[:2]), 0, 1)
    g_kp = np.concatenate([g_coco + rng.normal(0, 3, g_coco.shape), conf[..., None]], -1)
    off = (
        (g_kp[..., 0] < 0)
        | (g_kp[..., 0] >= cam.width)
        | (g_kp[..., 1] < 0)
        | (g_kp[..., 1] >= cam.height)
    )
    g_kp[off] = (np.nan, np.nan, 0.0)
    g_kp[:, ~sim.defined] = (np.nan, np.nan, 0.0)
    return g_kp, g_pose[inside], g_betas[inside], g_smpl


def synthesize(
    rig: CameraRig,
    model: BodyModel,
    config: SynthConfig,
    *,
    video_dir: Path | None = None,
    progress: bool = True,
    detections_dir: Path | None = None,
) -> tuple[SynthPeople, Detections]:
    """Plan, pose, render and detect. Writes ``video_dir/<camera>.mp4`` when given;
    with ``detections_dir`` (a new directory) the detection rows are streamed to its
    ``.npy`` columns as they are made and come back memory-mapped
    (:class:`~pipeline.synth.detection_rows.DetectionRows`)."""
    rows = DetectionRows(get_joint_set(config.joint_set).num_joints, detections_dir)
    try:
        with torch_threads(config.torch_threads):
            people = _synthesize(rig, model, config, video_dir, progress, rows)
    except BaseException:
        rows.discard()
        raise
    return people, rows.detections()


def _synthesize(
    rig: CameraRig,
    model: BodyModel,
    config: SynthConfig,
    video_dir: Path | None,
    progress: bool,
    rows: DetectionRows,
) -> SynthPeople:
    rng = np.random.default_rng(config.seed)
    area = visible_floor_area(rig, min_views=config.min_views, within_mm=config.area_radius_mm)
    motions = plan_people(rng, area, config.num_people, config.num_frames, config.fps)
    people = bodies_from_motion(motions, model, joint_set=config.joint_set)
    kreg = keypoint_regressor(model, config.joint_set)
    sim = _Simulation(
        model=model, kreg=kreg, js=get_joint_set(config.joint_set), defined=kreg.fitted,
        noise=config.noise, area=area, library=sample_pose_library(200, seed=config.seed),
    )  # fmt: skip
    if config.occlusion not in ("auto", "render", "proxy"):
        raise ValueError(f"occlusion: expected auto, render or proxy, got {config.occlusion!r}")
    use_proxy = config.occlusion == "proxy" or (
        config.occlusion == "auto" and (video_dir is None or not config.render_video)
    )
    if use_proxy:
        if video_dir is not None and config.render_video:
            raise ValueError("occlusion='proxy' renders no images: pass render_video=False")
        if config.batch_frames < 1:
            raise ValueError(f"batch_frames: expected >= 1, got {config.batch_frames}")
        detect = _detect_proxy if config.batch_frames == 1 else _detect_proxy_batched
        detect(rng, sim, rig, people, config, progress, rows)
        return people
    faces = model.faces.numpy()
    writers = _open_writers(rig, config, video_dir)
    # the backdrop only shows in videos; detections never look at it
    backgrounds = [render_background(cam) if writers else None for cam in rig]
    betas_t = torch.as_tensor(people.betas, dtype=torch.float32)
    frames = range(config.num_frames)
    for f in track(frames, "synth frames", progress, unit="frame"):
        # 1. pose the bodies, 2. render each view (and write its video frame), 3. detect
        with torch.no_grad():
            out = model(torch.as_tensor(people.pose[:, f], dtype=torch.float32), betas_t)
            coco_m = layout_keypoints(kreg, out.vertices, out.joints)
        verts = out.vertices.numpy() * 1000 + people.transl[:, f, None]
        coco = coco_m.numpy() * 1000 + people.transl[:, f, None]
        meshes = [
            MeshInstance(
                vertices=verts[p], faces=faces, color=PERSON_COLOURS[p % len(PERSON_COLOURS)]
            )
            for p in range(config.num_people)
        ]
        for v, cam in enumerate(rig):
            render = render_meshes(cam, meshes, background=backgrounds[v])
            if cam.name in writers:
                w, size = writers[cam.name]
                img = render.image
                if size != (cam.width, cam.height):
                    img = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
                w.write(cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
            _detect_view(rng, sim, cam, render, coco, people, f, v, rows)
    for w, _ in writers.values():
        w.release()
    return people


def _proxy_masks(
    sim: _Simulation, bodies, people: SynthPeople, f: int, cams: list
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Frame ``f``'s occlusion from the posed proxy bodies: per view, (P, J) bool masks
    (visible, hidden by another person) over the joint set, False on undefined joints."""
    P, defined = people.keypoints.shape[0], sim.defined
    ids = np.repeat(np.arange(P), int(defined.sum()))
    verts = pose_proxy(bodies, people.pose[:, f]) * 1000 + people.transl[:, f, None]
    points = people.keypoints[:, f][:, defined].reshape(-1, 3)
    occ = point_occlusion(cams, verts, bodies.faces, points, cull_back_faces=True)
    tol = sim.noise.self_occlusion_tolerance_mm
    vis_all, other_all = occ.visible(ids, tolerance_mm=tol), occ.hidden_by_other(ids)
    out = []
    for v in range(len(cams)):
        vis = np.zeros((P, sim.js.num_joints), bool)
        other = np.zeros((P, sim.js.num_joints), bool)
        vis[:, defined] = vis_all[v].reshape(P, -1)
        other[:, defined] = other_all[v].reshape(P, -1)
        out.append((vis, other))
    return out


def _detect_proxy(
    rng: np.random.Generator,
    sim: _Simulation,
    rig: CameraRig,
    people: SynthPeople,
    config: SynthConfig,
    progress: bool,
    rows: DetectionRows,
) -> None:
    """Detections of every frame with occlusion from the proxy body: per frame, pose the
    proxies, find the surface at every keypoint's pixel in all views at once, simulate
    the 2D detector per view and the monocular regressor for all views in one call."""
    defined = sim.defined
    bodies = proxy_bodies(sim.model, proxy_for(sim.model), people.betas)
    cams = list(rig)
    R_all = np.stack([c.R for c in cams])
    for f in track(range(config.num_frames), "synth frames", progress, unit="frame"):
        coco = people.keypoints[:, f]  # (P, T, 3) mm
        masks = _proxy_masks(sim, bodies, people, f, cams)
        found = []  # per view: (view, people in detector order, their keypoints)
        for v, (cam, (vis, other)) in enumerate(zip(cams, masks, strict=True)):
            kp, detected = simulate_keypoints(
                rng, cam, cam.project(coco), ~vis & ~other, other, sim.noise,
                joint_set=sim.js, defined=defined,
            )  # fmt: skip
            order = rng.permutation(np.flatnonzero(detected))  # detector order is arbitrary
            found.append((v, order, kp[order], rng.poisson(sim.noise.false_positives_per_view)))
        who = np.concatenate([o for _, o, _, _ in found])
        reg = {}
        if who.size:
            view = np.concatenate([np.full(o.size, v) for v, o, _, _ in found])
            smpl2d = np.concatenate([cams[v].project(people.joints[o, f]) for v, o, _, _ in found])
            reg = simulate_regressor(
                rng, R_all[view], people.pose[who, f], people.betas[who], smpl2d, sim.model,
                sim.noise,
            )  # fmt: skip
        start = 0
        for v, o, kp, n_ghost in found:  # rows by view, people then ghosts, as render's
            if o.size:
                rows.append(f, v, kp, o, {k: x[start : start + o.size] for k, x in reg.items()})
                start += o.size
            if n_ghost:
                _detect_ghosts(rng, sim, cams[v], n_ghost, f, v, rows)


def _detect_proxy_batched(
    rng: np.random.Generator,
    sim: _Simulation,
    rig: CameraRig,
    people: SynthPeople,
    config: SynthConfig,
    progress: bool,
    rows: DetectionRows,
) -> None:
    """:func:`_detect_proxy` with the regressor run once per ``config.batch_frames``
    frames, for the people and the ghosts of all their views: the rows wait in
    ``pending`` (frame, view, keypoints, person ids, pose, betas, SMPL joints px) in the
    order they are appended."""
    defined = sim.defined
    bodies = proxy_bodies(sim.model, proxy_for(sim.model), people.betas)
    cams = list(rig)
    pending: list[tuple] = []
    for f in track(range(config.num_frames), "synth frames", progress, unit="frame"):
        coco = people.keypoints[:, f]  # (P, T, 3) mm
        masks = _proxy_masks(sim, bodies, people, f, cams)
        for v, (cam, (vis, other)) in enumerate(zip(cams, masks, strict=True)):
            kp, detected = simulate_keypoints(
                rng, cam, cam.project(coco), ~vis & ~other, other, sim.noise,
                joint_set=sim.js, defined=defined,
            )  # fmt: skip
            o = rng.permutation(np.flatnonzero(detected))  # detector order is arbitrary
            if o.size:
                smpl2d = cam.project(people.joints[o, f])
                pending.append((f, v, kp[o], o, people.pose[o, f], people.betas[o], smpl2d))
            n_ghost = rng.poisson(sim.noise.false_positives_per_view)
            ghosts = _ghost_keypoints(rng, sim, cam, n_ghost) if n_ghost else None
            if ghosts is not None:
                pending.append((f, v, ghosts[0], np.full(len(ghosts[0]), -1)) + ghosts[1:])
        if (f + 1) % config.batch_frames == 0 or f + 1 == config.num_frames:
            _regress_pending(rng, sim, np.stack([c.R for c in cams]), pending, rows)
            pending = []


def _regress_pending(
    rng: np.random.Generator,
    sim: _Simulation,
    R_all: np.ndarray,
    pending: list[tuple],
    rows: DetectionRows,
) -> None:
    """One regressor call for the ``pending`` rows of :func:`_detect_proxy_batched`
    (their views' rotations from ``R_all``), appended to ``rows`` in their order."""
    if not pending:
        return
    view = np.concatenate([np.full(len(p[3]), p[1]) for p in pending])
    pose, betas, smpl2d = (np.concatenate([p[k] for p in pending]) for k in (4, 5, 6))
    reg = simulate_regressor(rng, R_all[view], pose, betas, smpl2d, sim.model, sim.noise)
    start = 0
    for f, v, kp, person, *_ in pending:
        n = len(person)
        rows.append(f, v, kp, person, {k: x[start : start + n] for k, x in reg.items()})
        start += n


def ground_truth(people: SynthPeople) -> GroundTruth:
    P, F = people.joints.shape[:2]
    return GroundTruth(
        frame=np.tile(np.arange(F), P),
        person_id=np.repeat(np.arange(P), F),
        joints3d=people.joints.reshape(P * F, SMPL24.num_joints, 3),
        smpl_pose=people.pose.reshape(P * F, 72),
        smpl_betas=np.repeat(people.betas, F, axis=0),
        transl=people.transl.reshape(P * F, 3),
        keypoints3d=people.keypoints.reshape(P * F, people.keypoints.shape[2], 3),
    )


STREAM_VIEW_FRAMES = 50_000
"""Scenes of at least this many frames x cameras (1,613 frames of a 31-camera dome) are
synthesised with their detections streamed to a directory of ``.npy`` columns: in memory
a 10,000-frame dome of 20 people held ~5 GB of rows."""


def write_synth_scene(
    out_dir: str | os.PathLike,
    rig: CameraRig,
    model: BodyModel,
    config: SynthConfig,
    *,
    name: str | None = None,
    overwrite: bool = False,
    progress: bool = True,
    detections_file: str | None = None,
) -> Path:
    """Synthesise and write a native scene directory atomically.

    ``detections_file``: ``detections.npz`` (one file, read whole), a directory name
    (``.npy`` columns, streamed while synthesising and read lazily), or None: the
    directory for scenes of at least :data:`STREAM_VIEW_FRAMES` view-frames."""
    out_dir = Path(out_dir)
    if out_dir.exists() and any(out_dir.iterdir()) and not overwrite:
        raise FileExistsError(f"{out_dir} exists and is not empty (pass --overwrite to replace it)")
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=out_dir.parent, prefix=f".{out_dir.name}.videos.") as tmp:
        video_dir = Path(tmp) if config.render_video else None
        if detections_file is None:
            long = config.num_frames * len(rig) >= STREAM_VIEW_FRAMES
            detections_file = "detections" if long else "detections.npz"
        columns = None if detections_file.endswith(".npz") else Path(tmp) / "detections"
        people, detections = synthesize(rig, model, config, video_dir=video_dir,
                                        progress=progress, detections_dir=columns)  # fmt: skip
        videos = {c.name: Path(tmp) / f"{c.name}.mp4" for c in rig} if video_dir else None
        noise = {k: getattr(config.noise, k) for k in config.noise.__dataclass_fields__}
        return write_scene(
            out_dir,
            name=name or out_dir.name,
            fps=config.fps,
            num_frames=config.num_frames,
            joint_set=get_joint_set(config.joint_set),
            rig=rig,
            detections=None if columns else detections,
            detection_columns=columns,
            detections_file=detections_file,
            gt=ground_truth(people),
            videos=videos,
            extra_meta={
                "synth": {
                    "seed": config.seed,
                    "num_people": config.num_people,
                    "video_scale": config.video_scale,
                    "body_model": os.path.basename(model.source),
                    "noise": noise,
                }
            },
            overwrite=overwrite,
        )
