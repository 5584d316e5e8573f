"""Procedural human motion for synthetic scenes: walking with turns, reaching, crouching,
waving and standing, as SMPL poses with limits respected.

A pose is first described by a few interpretable parameters (:data:`PARAM_NAMES`,
radians, clipped to :data:`PARAM_LIMITS`), then turned into SMPL axis-angle by
:func:`pose_from_params`. SMPL's canonical frame: y up, facing +z, the person's left
on +x. The world is z up, millimetres; a person's heading is the world angle of
their facing direction in the floor plane.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import PchipInterpolator
from scipy.spatial.transform import Rotation

from pipeline.data.joint_sets import SMPL24

PARAM_LIMITS: dict[str, tuple[float, float]] = {
    "hip_flex_l": (-0.6, 2.1), "hip_flex_r": (-0.6, 2.1),  # + leg forward
    "hip_abd_l": (-0.3, 0.7), "hip_abd_r": (-0.3, 0.7),  # + leg outward
    "knee_l": (0.0, 2.4), "knee_r": (0.0, 2.4),  # + flexion
    "ankle_l": (-0.6, 0.7), "ankle_r": (-0.6, 0.7),  # + toes down
    "spine_bend": (-0.4, 1.0), "spine_twist": (-0.6, 0.6), "spine_side": (-0.35, 0.35),
    "arm_elev_l": (0.0, 2.9), "arm_elev_r": (0.0, 2.9),  # 0 arm down, pi/2 sideways
    "arm_fwd_l": (-0.9, 2.9), "arm_fwd_r": (-0.9, 2.9),  # + arm forward/up
    "elbow_l": (0.0, 2.5), "elbow_r": (0.0, 2.5),  # + flexion
    "head_pitch": (-0.6, 0.7), "head_yaw": (-1.0, 1.0),  # + looks down / to the left
    "root_pitch": (-0.3, 0.8),  # + whole body leans forward
}  # fmt: skip
PARAM_NAMES = tuple(PARAM_LIMITS)
P = {n: i for i, n in enumerate(PARAM_NAMES)}
LOW = np.array([v[0] for v in PARAM_LIMITS.values()])
HIGH = np.array([v[1] for v in PARAM_LIMITS.values()])
J = SMPL24.index


def _rx(a):
    return Rotation.from_rotvec(np.stack([a, 0 * a, 0 * a], -1))


def _ry(a):
    return Rotation.from_rotvec(np.stack([0 * a, a, 0 * a], -1))


def _rz(a):
    return Rotation.from_rotvec(np.stack([0 * a, 0 * a, a], -1))


def _align(src: np.ndarray, dst: np.ndarray) -> Rotation:
    """Minimal rotations taking unit vector ``src`` (3,) to each of ``dst`` (N, 3)."""
    axis = np.cross(src, dst)
    s = np.linalg.norm(axis, axis=-1, keepdims=True)
    c = dst @ src
    angle = np.arctan2(s[:, 0], c)
    axis = np.where(s > 1e-9, axis / np.maximum(s, 1e-12), np.array([0.0, 0.0, 1.0]))
    return Rotation.from_rotvec(axis * angle[:, None])


def pose_from_params(params: np.ndarray) -> np.ndarray:
    """(N, num_params) interpretable parameters -> (N, 24, 3) SMPL axis-angle.

    The root rotation holds only ``root_pitch`` (canonical frame); the caller puts the
    body into the world with :func:`root_to_world`.
    """
    p = np.clip(np.atleast_2d(params), LOW, HIGH)
    n = p.shape[0]
    g = {name: p[:, i] for name, i in P.items()}
    out = np.zeros((n, 24, 3))
    out[:, J["pelvis"]] = _rx(g["root_pitch"]).as_rotvec()
    for side, sign in (("l", 1.0), ("r", -1.0)):
        name = "left" if side == "l" else "right"
        hip = _rx(-g[f"hip_flex_{side}"]) * _rz(sign * g[f"hip_abd_{side}"])
        out[:, J[f"{name}_hip"]] = hip.as_rotvec()
        out[:, J[f"{name}_knee"]] = _rx(g[f"knee_{side}"]).as_rotvec()
        out[:, J[f"{name}_ankle"]] = _rx(g[f"ankle_{side}"]).as_rotvec()
        # Arm direction in the body frame, then the minimal rotation from the T-pose arm.
        elev, fwd = g[f"arm_elev_{side}"], g[f"arm_fwd_{side}"]
        d = np.stack([sign * np.sin(elev), -np.cos(elev), np.zeros(n)], -1)
        d = (_rx(-fwd)).apply(d)
        out[:, J[f"{name}_shoulder"]] = _align(np.array([sign, 0.0, 0.0]), d).as_rotvec()
        out[:, J[f"{name}_elbow"]] = _ry(-sign * g[f"elbow_{side}"]).as_rotvec()
    spine = _rx(g["spine_bend"] / 3) * _ry(g["spine_twist"] / 3) * _rz(g["spine_side"] / 3)
    for j in ("spine1", "spine2", "spine3"):
        out[:, J[j]] = spine.as_rotvec()
    out[:, J["neck"]] = (_rx(g["head_pitch"] / 2) * _ry(g["head_yaw"] / 2)).as_rotvec()
    out[:, J["head"]] = out[:, J["neck"]]
    return out


# SMPL canonical (y up, facing +z) -> world (z up), for a heading angle in the floor plane.
def root_to_world(heading: np.ndarray, root_local: np.ndarray) -> np.ndarray:
    """(N,) heading, (N, 3) canonical root axis-angle -> (N, 3) world root axis-angle."""
    h = np.asarray(heading, float)
    c, s = np.cos(h), np.sin(h)
    z = np.zeros_like(h)
    # Columns: the images of canonical x (the person's left), y (up), z (facing).
    M = np.stack(
        [np.stack([-s, z, c], -1), np.stack([c, z, s], -1), np.stack([z, z + 1, z], -1)], -2
    )  # (N, 3 world rows, 3 canonical columns)
    return (Rotation.from_matrix(M) * Rotation.from_rotvec(root_local)).as_rotvec()


# --------------------------------------------------------------------------- activities

STAND = np.zeros(len(PARAM_NAMES))
STAND[[P["arm_elev_l"], P["arm_elev_r"]]] = 0.12
STAND[[P["elbow_l"], P["elbow_r"]]] = 0.15
STAND[[P["knee_l"], P["knee_r"]]] = 0.05


# The ankle's sagittal angle over a gait cycle, at the ends of the Rancho Los Amigos
# phases (% of the cycle from initial contact, degrees, + plantarflexion as ``ankle_*``):
# Perry J, Burnfield JM, "Gait Analysis: Normal and Pathological Function", 2nd ed., 2010,
# ch. 4 (Ankle-Foot Complex): neutral at initial contact, 10 deg plantarflexion in loading
# response (heel rocker, 0-12 %), 5 deg dorsiflexion by the end of mid stance (31 %), 10
# deg at the end of terminal stance (heel off, 50 %), 20 deg plantarflexion at toe off
# (62 %), 10 deg at the end of initial swing (75 %), neutral from mid swing (87 %) on.
# Inside PARAM_LIMITS["ankle_*"] and pose_limits' ankle box even at walk_params' largest
# amplitude (1.3 x: 26 deg plantarflexion, 13 deg dorsiflexion).
GAIT_ANKLE_DEG = ((0, 0.0), (12, 10.0), (31, -5.0), (50, -10.0), (62, 20.0), (75, 10.0),
                  (87, 0.0), (100, 0.0))  # fmt: skip
# Where initial contact falls in walk_params' phase: its knee term peaks at -0.35 rad
# (-0.056 cycles) and the knee's peak flexion is at 73 % of the cycle (Perry, ch. 5), so
# contact comes 0.27 cycles later; the hip term's peak extension (0.75 cycles) then falls
# at 54 % (Perry: 50 %).
GAIT_CONTACT_PHASE = -0.35 / (2 * np.pi) + 0.27


def _periodic_pchip(keys: tuple[tuple[float, float], ...]) -> PchipInterpolator:
    """Shape-preserving interpolation (no overshoot past the keyframes) of a 100-periodic
    curve: the keyframes repeated one period either side."""
    x = np.array([k[0] for k in keys[:-1]], float)
    y = np.array([k[1] for k in keys[:-1]], float)
    return PchipInterpolator(np.concatenate([x - 100, x, x + 100]), np.tile(y, 3))


_GAIT_ANKLE = _periodic_pchip(GAIT_ANKLE_DEG)


def gait_ankle(cycles: np.ndarray) -> np.ndarray:
    """Ankle sagittal angle (radians, + plantarflexion) at ``cycles`` (N,) of the gait
    cycle counted from initial contact (:data:`GAIT_ANKLE_DEG`)."""
    return np.deg2rad(_GAIT_ANKLE(100.0 * np.mod(np.asarray(cycles, float), 1.0)))


def walk_params(phase: np.ndarray, speed: np.ndarray, *, gait_ankles: bool = False) -> np.ndarray:
    """Gait cycle. phase: (N,) cycles; speed: (N,) m/s -> (N, num_params).

    ``gait_ankles``: the ankles follow the measured gait curve (:func:`gait_ankle`, its
    amplitude scaled with speed like every joint here) instead of the +-8.6 deg sine
    that the shipped samples and the shipped prior's library were made with (the default,
    so they stay reproducible)."""
    a = np.clip(np.asarray(speed, float) / 1.3, 0, 1.3)[:, None]
    w = 2 * np.pi * np.asarray(phase, float)
    out = np.tile(STAND, (len(w), 1))
    for side, off in (("l", 0.0), ("r", np.pi)):
        ph = w + off
        out[:, P[f"hip_flex_{side}"]] += a[:, 0] * (0.12 + 0.38 * np.sin(ph))
        swing = np.maximum(0.0, np.cos(ph + 0.35)) ** 2  # knee flexes early in the swing
        out[:, P[f"knee_{side}"]] += a[:, 0] * (0.1 + 0.95 * swing)
        if gait_ankles:
            ankle = gait_ankle(ph / (2 * np.pi) - GAIT_CONTACT_PHASE)
        else:
            ankle = 0.15 * np.sin(ph - 0.6)
        out[:, P[f"ankle_{side}"]] += a[:, 0] * ankle
        out[:, P[f"arm_fwd_{side}"]] += a[:, 0] * 0.4 * np.sin(ph + np.pi)
        out[:, P[f"elbow_{side}"]] += a[:, 0] * (0.2 + 0.15 * np.sin(ph + np.pi))
    out[:, P["spine_twist"]] += a[:, 0] * 0.12 * np.sin(w)
    out[:, P["root_pitch"]] += a[:, 0] * 0.05
    return out


def activity_params(kind: str, t: np.ndarray, rng_vals: np.ndarray) -> np.ndarray:
    """Parameters of a static-ish activity over local time ``t`` (N,) seconds.

    ``rng_vals`` (8,) uniform numbers fixed per segment pick the variant (which arm, how far).
    """
    n = len(t)
    out = np.tile(STAND, (n, 1))
    sway = 0.04 * np.sin(2 * np.pi * (0.25 * t + rng_vals[0]))
    out[:, P["spine_side"]] += sway
    out[:, P["head_yaw"]] += 0.4 * np.sin(2 * np.pi * (0.1 * t + rng_vals[1]))
    ramp = np.clip(t / 0.8, 0, 1)
    ramp = ramp * ramp * (3 - 2 * ramp)
    if kind == "stand":
        return out
    if kind == "reach":
        sides = ["l", "r"] if rng_vals[2] < 0.35 else (["l"] if rng_vals[2] < 0.7 else ["r"])
        height = 1.5 + 0.9 * rng_vals[3]  # how high on the shelf
        for s in sides:
            out[:, P[f"arm_fwd_{s}"]] = ramp * height
            out[:, P[f"arm_elev_{s}"]] = 0.12 + ramp * 0.25
            out[:, P[f"elbow_{s}"]] = 0.15 + ramp * (0.2 + 0.3 * np.sin(1.5 * t) ** 2)
        out[:, P["head_pitch"]] = -ramp * 0.35 * rng_vals[3]
        out[:, P["spine_bend"]] = -ramp * 0.08
        return out
    if kind == "crouch":
        depth = 0.7 + 0.3 * rng_vals[2]
        out[:, P["root_pitch"]] = ramp * 0.45 * depth
        for s in ("l", "r"):
            out[:, P[f"hip_flex_{s}"]] = ramp * 1.55 * depth
            out[:, P[f"knee_{s}"]] = ramp * 2.1 * depth
            out[:, P[f"ankle_{s}"]] = -ramp * 0.45 * depth
            out[:, P[f"hip_abd_{s}"]] = ramp * 0.15
            out[:, P[f"arm_fwd_{s}"]] = ramp * (0.7 + 0.4 * rng_vals[3])
            out[:, P[f"elbow_{s}"]] = 0.15 + ramp * 0.6
        out[:, P["spine_bend"]] = ramp * 0.35 * depth
        out[:, P["head_pitch"]] = ramp * 0.3
        return out
    if kind == "wave":
        s = "l" if rng_vals[2] < 0.5 else "r"
        out[:, P[f"arm_elev_{s}"]] = 0.12 + ramp * 2.3
        out[:, P[f"arm_fwd_{s}"]] = ramp * 0.3
        out[:, P[f"elbow_{s}"]] = 0.2 + ramp * (0.6 + 0.45 * np.sin(2 * np.pi * 1.5 * t))
        return out
    raise ValueError(f"unknown activity {kind!r}")


# --------------------------------------------------------------------------- planning


@dataclass(frozen=True, eq=False)
class PersonMotion:
    """One person's motion over a scene.

    Attributes:
        params: (F, num_params) pose parameters.
        heading: (F,) world yaw of the facing direction, radians.
        position: (F, 2) pelvis floor position, world mm.
        betas: (10,) body shape.
        activity: (F,) activity name per frame (for the README / debugging).
    """

    params: np.ndarray
    heading: np.ndarray
    position: np.ndarray
    betas: np.ndarray
    activity: np.ndarray


def _smooth(x: np.ndarray, frames: int) -> np.ndarray:
    """Moving average over ``frames`` along axis 0 (edge-padded); blends activity changes."""
    if frames <= 1:
        return x
    k = np.ones(frames) / frames
    pad = frames // 2
    xp = np.pad(x, [(pad, frames - 1 - pad)] + [(0, 0)] * (x.ndim - 1), mode="edge")
    return np.apply_along_axis(lambda c: np.convolve(c, k, mode="valid"), 0, xp)


@dataclass(frozen=True)
class PathState:
    """Where a planned path ends: the next window's plan starts there."""

    position: np.ndarray  # (2,) floor mm
    heading: float
    phase: float  # gait phase, cycles


@dataclass(frozen=True, eq=False)
class _Path:
    """One person's planned frames before the seams are blended and a body is drawn."""

    params: np.ndarray  # (F, num_params)
    heading: np.ndarray  # (F,)
    position: np.ndarray  # (F, 2)
    activity: np.ndarray  # (F,)
    end: PathState


def plan_person(
    rng: np.random.Generator,
    area: np.ndarray,
    num_frames: int,
    fps: float,
    *,
    meet: list[np.ndarray] | None = None,
) -> PersonMotion:
    """Plan one person's activities inside ``area``.

    Args:
        area: (K, 2) floor points (mm) where a person is seen well; waypoints come from it.
        meet: positions (F, 2) of people planned before; some waypoints go next to them
            so that people stand close and occlude each other.
    """
    path = _plan_path(rng, area, num_frames, fps, meet=meet)
    return _person(rng, [path], fps)


def _person(rng: np.random.Generator, paths: list[_Path], fps: float) -> PersonMotion:
    """Consecutive paths of one person as a motion: the seams between activities (and
    between windows) blended over 0.3 s, a body shape drawn."""
    params = np.concatenate([p.params for p in paths])
    # Blend the seams between activities (0.3 s); the gait itself is smooth already.
    params = _smooth(params, max(1, int(0.3 * fps)))
    betas = np.clip(rng.normal(0, 1, 10), -2.5, 2.5)
    return PersonMotion(
        params=params,
        heading=np.concatenate([p.heading for p in paths]),
        position=np.concatenate([p.position for p in paths]),
        betas=betas,
        activity=np.concatenate([p.activity for p in paths]),
    )


def _plan_path(
    rng: np.random.Generator,
    area: np.ndarray,
    num_frames: int,
    fps: float,
    *,
    meet: list[np.ndarray] | None = None,
    start: PathState | None = None,
) -> _Path:
    """:func:`plan_person`'s frames, from ``start`` (None: a random place, heading and
    gait phase, drawn first)."""
    dt = 1.0 / fps
    if start is None:
        pos = area[rng.integers(len(area))].astype(float)
        heading = rng.uniform(-np.pi, np.pi)
    else:
        pos, heading = start.position.astype(float), start.heading
    params = np.zeros((num_frames, len(PARAM_NAMES)))
    head = np.zeros(num_frames)
    xy = np.zeros((num_frames, 2))
    act = np.empty(num_frames, dtype=object)
    f = 0
    phase = rng.uniform() if start is None else start.phase
    while f < num_frames:
        kind = rng.choice(
            ["walk", "reach", "crouch", "stand", "wave"], p=[0.5, 0.2, 0.13, 0.1, 0.07]
        )
        if kind == "walk":
            if meet and rng.uniform() < 0.35:
                other = meet[rng.integers(len(meet))][min(f + int(2.5 * fps), num_frames - 1)]
                off = rng.normal(0, 1, 2)
                target = other + 800 * off / np.linalg.norm(off)
            else:
                cand = area[rng.integers(len(area), size=16)]
                dist = np.linalg.norm(cand - pos, axis=1)
                ok = cand[(dist > 1000) & (dist < 4000)]
                target = ok[0] if len(ok) else cand[np.argmax(dist)]
            speed_max = rng.uniform(0.9, 1.5) * 1000  # mm/s
            steps = 0
            while f < num_frames and steps < 8 * fps:
                delta = target - pos
                dist = np.linalg.norm(delta)
                if dist < 150:
                    break
                want = np.arctan2(delta[1], delta[0])
                err = (want - heading + np.pi) % (2 * np.pi) - np.pi
                heading += np.clip(err, -2.5 * dt, 2.5 * dt)  # turn rate limit
                speed = speed_max * max(0.25, np.cos(err)) * min(1.0, dist / 600 + 0.3)
                pos = pos + speed * dt * np.array([np.cos(heading), np.sin(heading)])
                phase += speed / 1000 / 1.35 * dt  # ~1.35 m per gait cycle
                params[f] = walk_params(np.array([phase]), np.array([speed / 1000]))[0]
                head[f], xy[f], act[f] = heading, pos, "walk"
                f += 1
                steps += 1
        else:
            n = int(rng.uniform(1.5, 3.0) * fps)
            t = np.arange(n) * dt
            block = activity_params(kind, t, rng.uniform(size=8))
            m = min(n, num_frames - f)
            params[f : f + m] = block[:m]
            head[f : f + m], xy[f : f + m], act[f : f + m] = heading, pos, kind
            f += m
    return _Path(params, head, xy, act, PathState(pos, float(heading), float(phase)))


PLAN_WINDOW_S = 3.0
"""Seconds of the windows a long or crowded scene is planned in (see :func:`plan_people`)."""
PLAN_WHOLE_S = 10.0
"""Scenes up to this long are planned whole first."""


def plan_people(
    rng: np.random.Generator,
    area: np.ndarray,
    num_people: int,
    num_frames: int,
    fps: float,
    *,
    min_distance_mm: float = 650.0,
    max_tries: int = 200,
) -> list[PersonMotion]:
    """Plan ``num_people`` motions that never come closer than ``min_distance_mm``.

    Each person's path is drawn until it keeps its distance from the people planned
    before. Over a long scene a whole random path almost never does (at 600 frames, 10
    people on a 31-camera dome's floor failed 200 times), so scenes longer than
    :data:`PLAN_WHOLE_S`, and shorter ones where that fails, are planned a window of
    :data:`PLAN_WINDOW_S` at a time: every person's next window starts where their last
    ended and is drawn until it keeps its distance in that window. Scenes planned whole
    get the draws they always got.
    """
    if num_frames <= PLAN_WHOLE_S * fps:
        try:
            return _plan_whole(rng, area, num_people, num_frames, fps, min_distance_mm, max_tries)
        except RuntimeError:
            pass  # crowded: plan it by windows
    window = max(1, int(round(PLAN_WINDOW_S * fps)))
    paths: list[list[_Path]] = [[] for _ in range(num_people)]
    for w0 in range(0, num_frames, window):
        w1 = min(w0 + window, num_frames)
        placed: list[np.ndarray] = []  # this window's positions of the people placed
        for k in range(num_people):
            start = paths[k][-1].end if paths[k] else None
            # the people not planned yet keep their place free: whatever the others do in
            # this window, staying put is a way for each of them to keep their distance
            waiting = [p[-1].end.position[None] for p in paths[k + 1 :] if p]
            for _try in range(max_tries):
                cand = _plan_path(rng, area, w1 - w0, fps, meet=placed, start=start)
                if _keeps_distance(cand.position, placed + waiting, min_distance_mm):
                    break
            else:
                raise RuntimeError(_crowded(k, max_tries, f" in frames {w0}-{w1 - 1}"))
            placed.append(cand.position)
            paths[k].append(cand)
    return [_person(rng, p, fps) for p in paths]


def _plan_whole(rng, area, num_people, num_frames, fps, min_mm, max_tries) -> list[PersonMotion]:
    """Whole paths, each candidate with its body drawn (the draws plan_people always made)."""
    people: list[PersonMotion] = []
    for k in range(num_people):
        for _try in range(max_tries):
            cand = plan_person(rng, area, num_frames, fps, meet=[p.position for p in people])
            if _keeps_distance(cand.position, [p.position for p in people], min_mm):
                people.append(cand)
                break
        else:
            raise RuntimeError(_crowded(k, max_tries, ""))
    return people


def _keeps_distance(path: np.ndarray, others: list[np.ndarray], min_mm: float) -> bool:
    """Whether (F, 2) ``path`` stays ``min_mm`` from each of ``others`` at every frame."""
    return all(np.linalg.norm(path - p, axis=1).min() >= min_mm for p in others)


def _crowded(k: int, tries: int, where: str) -> str:
    return (
        f"could not place person {k} without collisions in {tries} tries{where}; "
        "the visible floor area is too small for this many people"
    )


LIBRARY_ACTIVITIES = ("walk", "reach", "crouch", "stand", "wave")


def sample_pose_library(
    num_poses: int, seed: int = 0, *, kinds: tuple[str, ...] = LIBRARY_ACTIVITIES
) -> np.ndarray:
    """(num_poses, 72) body poses drawn from the activities ``kinds`` (default all, in
    equal parts), root rotation zeroed.

    The default training data of the pose prior.
    """
    rng = np.random.default_rng(seed)
    out = []
    if not kinds or set(kinds) - set(LIBRARY_ACTIVITIES):
        raise ValueError(f"kinds must be among {LIBRARY_ACTIVITIES}, got {kinds}")
    per = int(np.ceil(num_poses / len(kinds)))
    for kind in kinds:
        if kind == "walk":
            p = walk_params(rng.uniform(size=per), rng.uniform(0.3, 1.6, per))
        else:
            t = rng.uniform(0, 3, per)
            p = np.concatenate(
                [activity_params(kind, t[i : i + 1], rng.uniform(size=8)) for i in range(per)]
            )
        p = p + rng.normal(0, 0.04, p.shape)  # small variety around the templates
        out.append(pose_from_params(p))
    poses = np.concatenate(out)[:num_poses]
    poses[:, 0] = 0
    return poses.reshape(len(poses), 72)
