"""BVH motion capture files (Biovision Hierarchy): read, forward kinematics, our world.

A BVH file is text in two sections::

    HIERARCHY
    ROOT Hips
    {
        OFFSET 0 0 0
        CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation
        JOINT LeftHip
        {
            OFFSET 1.2 -1.6 0.7
            CHANNELS 3 Zrotation Yrotation Xrotation
            End Site
            {
                OFFSET 0 -7 0
            }
        }
    }
    MOTION
    Frames: 2
    Frame Time: 0.0083333
    <one row per frame: every joint's channel values, in hierarchy order>

Conventions (those of Biovision's format, as Blender, bvh11 and the CMU cgspeed
conversions use them):

* A joint's ``OFFSET`` is its origin in its parent's frame, in file units. Its local
  transform is a translation by ``OFFSET`` (plus its position channels, if it has any:
  usually only the root) followed by its rotation channels.
* The local rotation is the product of the channel rotations in the order they are
  listed (intrinsic): ``CHANNELS 3 Zrotation Xrotation Yrotation`` means
  ``R = Rz(z) @ Rx(x) @ Ry(y)``; angles in degrees. Any order, any subset, 0 to 6
  channels, position channels anywhere in the list.
* World pose of joint j: ``G_j = G_parent @ [R_j | OFFSET_j + p_j]``; its position is
  the translation of ``G_j``. An ``End Site`` is a joint without channels (named
  ``<parent>_end`` here), kept because it marks the end of its parent's bone (e.g.
  the top of the head).

:class:`BvhMotion` keeps the file's units and axes. Our world is millimetres, z up,
right-handed; :func:`bvh_to_world_mm` takes a Y-up file there by the cyclic
permutation ``world = (z, x, y)`` (matrix :data:`Y_UP_TO_WORLD`, a rotation: det +1,
so a person's left stays on their left), the same mapping
:func:`pipeline.importers.trc.trc_to_world_mm` applies to OpenSim's Y-up files. (The
other obvious choice, ``(x, -z, y)``, is also a rotation and differs only by a turn
about the vertical; the scene generators place and turn people anyway.)

Every malformed input raises :class:`~pipeline.core.files.SceneFormatError` naming the file
and the line (and keyword) at fault: unbalanced braces, a ``CHANNELS`` count that does
not match its names, unknown channels, non-numbers, a frame row with the wrong number
of values, ``Frames:`` against the rows present.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.core.files import SceneFormatError, read_text_lines

CHANNEL_NAMES = (
    "Xposition", "Yposition", "Zposition", "Xrotation", "Yrotation", "Zrotation",
)  # fmt: skip
_CANONICAL = {c.lower(): c for c in CHANNEL_NAMES}

Y_UP_TO_WORLD = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
"""(3, 3) rotation taking a Y-up file's axes to our z-up world: ``world = A @ (x, y, z)
= (z, x, y)``."""


@dataclass(frozen=True, eq=False)
class BvhMotion:
    """One BVH file: J joints (End Sites included), F frames, file units and axes.

    Attributes:
        path: where it was read from.
        names: (J,) joint names as in the file; End Sites are ``<parent>_end``.
        parents: (J,) index of each joint's parent, -1 for a root; parents come first.
        offsets: (J, 3) ``OFFSET`` of each joint in its parent's frame, file units.
        channels: (J,) tuple of channel names per joint (``()`` for an End Site).
        end_site: (J,) True for End Sites.
        frame_time: seconds per frame (``Frame Time:``).
        values: (F, C) the MOTION rows, C = total channel count; rotations in degrees.
        positions: (F, J, 3) joint world positions, file units and axes.
        rotations: (F, J, 3, 3) joint world rotations (file axes; an End Site has its
            parent's).
    """

    path: Path
    names: tuple[str, ...]
    parents: tuple[int, ...]
    offsets: np.ndarray
    channels: tuple[tuple[str, ...], ...]
    end_site: tuple[bool, ...]
    frame_time: float
    values: np.ndarray
    positions: np.ndarray
    rotations: np.ndarray

    @property
    def num_frames(self) -> int:
        return int(self.values.shape[0])

    @property
    def num_joints(self) -> int:
        """Joints with channels or not, End Sites excluded."""
        return int(sum(not e for e in self.end_site))

    @property
    def fps(self) -> float:
        return 1.0 / self.frame_time

    @property
    def index(self) -> dict[str, int]:
        return {n: i for i, n in enumerate(self.names)}

    def bone_lengths(self) -> dict[str, float]:
        """Length of the bone ending at each non-root joint (|OFFSET|), file units."""
        return {
            n: float(np.linalg.norm(self.offsets[j]))
            for j, n in enumerate(self.names)
            if self.parents[j] >= 0
        }


# --------------------------------------------------------------------------- parsing


def _float(path: Path, lineno: int, what: str, text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise SceneFormatError(
            path, f"line {lineno} ({what})", f"expected a number, got {text!r}"
        ) from None
    if not math.isfinite(value):
        raise SceneFormatError(
            path, f"line {lineno} ({what})", f"expected a finite number, got {text!r}"
        )
    return value


def _joint_name(
    path: Path,
    lineno: int,
    tok: list[str],
    stack: list[int],
    names: list[str],
    end_site: list[bool],
) -> str:
    """The name a ``ROOT``, ``JOINT`` or ``End Site`` line declares (an End Site: its
    parent's name + ``_end``), after checking where it stands."""
    key = tok[0].upper()
    where = f"line {lineno} ({tok[0]})"
    if key == "ROOT" and stack:
        raise SceneFormatError(path, f"line {lineno} (ROOT)", "ROOT inside another joint")
    if key != "ROOT" and not stack:
        raise SceneFormatError(path, where, f"{tok[0]} outside any ROOT's braces")
    if stack and end_site[stack[-1]]:
        raise SceneFormatError(path, where, "a joint inside an End Site")
    if key == "END":
        name = f"{names[stack[-1]]}_end"
    elif len(tok) < 2:
        raise SceneFormatError(path, where, "joint without a name")
    else:
        name = " ".join(tok[1:])
    if name in names:
        raise SceneFormatError(path, where, f"joint {name!r} named twice")
    return name


def _open_joint(path: Path, lineno: int, what: str, stack: list[int]) -> int:
    """The innermost open joint, which a ``what`` line (OFFSET, CHANNELS) belongs to."""
    if not stack:
        raise SceneFormatError(path, f"line {lineno} ({what})", f"{what} outside a joint")
    return stack[-1]


def _offset(path: Path, lineno: int, tok: list[str]) -> list[float]:
    """The three numbers of an ``OFFSET x y z`` line."""
    if len(tok) != 4:
        raise SceneFormatError(
            path, f"line {lineno} (OFFSET)", f"expected 3 numbers, got {len(tok) - 1}"
        )
    return [_float(path, lineno, "OFFSET", t) for t in tok[1:]]


def _channels(path: Path, lineno: int, tok: list[str]) -> tuple[str, ...]:
    """The canonical channel names of a ``CHANNELS n name...`` line."""
    where = f"line {lineno} (CHANNELS)"
    if len(tok) < 2:
        raise SceneFormatError(path, where, "missing channel count")
    try:
        n = int(tok[1])
    except ValueError:
        raise SceneFormatError(path, where, f"expected a channel count, got {tok[1]!r}") from None
    given = tok[2:]
    if n != len(given) or not 0 <= n <= 6:
        raise SceneFormatError(
            path, where,
            f"count says {n} channels, {len(given)} are named" if n != len(given)
            else f"expected 0 to 6 channels, got {n}",
        )  # fmt: skip
    bad = [c for c in given if c.lower() not in _CANONICAL]
    if bad:
        raise SceneFormatError(
            path, where, f"unknown channel {bad[0]!r}; expected {', '.join(CHANNEL_NAMES)}"
        )
    canon = tuple(_CANONICAL[c.lower()] for c in given)
    if len(set(canon)) != len(canon):
        raise SceneFormatError(path, where, "a channel listed twice")
    return canon


def _check_closed(
    path: Path, lineno: int, names: list[str], stack: list[int], pending: int | None
) -> None:
    """At ``MOTION``: every joint closed, and there is one."""
    if stack or pending is not None:
        open_name = names[stack[-1] if stack else pending]
        raise SceneFormatError(
            path, f"line {lineno} (MOTION)",
            f"unbalanced braces: joint {open_name!r} is not closed before MOTION",
        )  # fmt: skip
    if not names:
        raise SceneFormatError(path, f"line {lineno} (MOTION)", "no ROOT in HIERARCHY")


def _parse_hierarchy(path: Path, lines: list[str]) -> tuple[dict, int]:
    """Joints of the HIERARCHY section and the index of the ``MOTION`` line."""
    names: list[str] = []
    parents: list[int] = []
    offsets: list[list[float] | None] = []
    channels: list[tuple[str, ...]] = []
    end_site: list[bool] = []
    stack: list[int] = []  # open joints, innermost last
    pending: int | None = None  # a joint declared, waiting for its "{"
    seen_hierarchy = False
    for i, raw in enumerate(lines):
        lineno = i + 1
        tok = raw.split()
        if not tok:
            continue
        key = tok[0].upper()
        if not seen_hierarchy:
            if key != "HIERARCHY":
                raise SceneFormatError(
                    path, f"line {lineno}", f"expected 'HIERARCHY' first, got {raw.strip()[:40]!r}"
                )
            seen_hierarchy = True
            continue
        if key == "MOTION":
            _check_closed(path, lineno, names, stack, pending)
            return {
                "names": names, "parents": parents, "offsets": offsets,
                "channels": channels, "end_site": end_site,
            }, i  # fmt: skip
        if pending is not None and key != "{":
            raise SceneFormatError(
                path,
                f"line {lineno}",
                f"expected '{{' after joint {names[pending]!r}, got {tok[0]!r}",
            )
        if key in ("ROOT", "JOINT") or (key == "END" and len(tok) > 1 and tok[1].upper() == "SITE"):
            is_end = key == "END"
            name = _joint_name(path, lineno, tok, stack, names, end_site)
            names.append(name)
            parents.append(stack[-1] if stack else -1)
            offsets.append(None)
            channels.append(())
            end_site.append(is_end)
            pending = len(names) - 1
        elif key == "{":
            if pending is None:
                raise SceneFormatError(
                    path, f"line {lineno}", "unbalanced braces: '{' without a joint"
                )
            stack.append(pending)
            pending = None
        elif key == "}":
            if not stack:
                raise SceneFormatError(path, f"line {lineno}", "unbalanced braces: '}' without '{'")
            j = stack.pop()
            if offsets[j] is None:
                raise SceneFormatError(path, f"line {lineno}", f"joint {names[j]!r} has no OFFSET")
        elif key == "OFFSET":
            offsets[_open_joint(path, lineno, "OFFSET", stack)] = _offset(path, lineno, tok)
        elif key == "CHANNELS":
            j = _open_joint(path, lineno, "CHANNELS", stack)
            if end_site[j]:
                raise SceneFormatError(
                    path, f"line {lineno} (CHANNELS)", "an End Site has no channels"
                )
            channels[j] = _channels(path, lineno, tok)
        else:
            raise SceneFormatError(path, f"line {lineno}", f"unexpected {tok[0]!r} in HIERARCHY")
    if not seen_hierarchy:
        raise SceneFormatError(path, "HIERARCHY", "empty file (expected 'HIERARCHY')")
    inside = stack or pending is not None
    raise SceneFormatError(
        path, "HIERARCHY" if inside else "MOTION",
        "unbalanced braces: the file ends inside a joint (no MOTION)" if inside
        else "missing MOTION section",
    )  # fmt: skip


def _header_value(path: Path, lines: list[str], i: int, label: str) -> tuple[str, int]:
    """The value after ``label:`` on the next non-empty line from ``i``."""
    while i < len(lines) and not lines[i].strip():
        i += 1
    if i >= len(lines):
        raise SceneFormatError(path, label, f"missing '{label}:' line after MOTION")
    text = lines[i].strip()
    head, sep, value = text.partition(":")
    if not sep or head.strip().lower() != label.lower():
        raise SceneFormatError(
            path, f"line {i + 1} ({label})", f"expected '{label}: ...', got {text[:40]!r}"
        )
    return value.strip(), i + 1


def read_bvh(path: str | os.PathLike) -> BvhMotion:
    """Read a BVH file and run forward kinematics (see the module docstring)."""
    path = Path(path)
    lines = read_text_lines(path)
    h, motion_line = _parse_hierarchy(path, lines)
    rest = lines[motion_line].split(None, 1)
    if len(rest) > 1:
        raise SceneFormatError(
            path, f"line {motion_line + 1} (MOTION)", "unexpected text after MOTION"
        )
    text, i = _header_value(path, lines, motion_line + 1, "Frames")
    try:
        num_frames = int(text)
    except ValueError:
        raise SceneFormatError(
            path, f"line {i} (Frames)", f"expected an integer, got {text!r}"
        ) from None
    if num_frames < 0:
        raise SceneFormatError(
            path, f"line {i} (Frames)", f"expected >= 0 frames, got {num_frames}"
        )
    text, i = _header_value(path, lines, i, "Frame Time")
    frame_time = _float(path, i, "Frame Time", text)
    if frame_time <= 0:
        raise SceneFormatError(path, f"line {i} (Frame Time)", f"expected > 0 seconds, got {text}")
    num_channels = sum(len(c) for c in h["channels"])
    rows: list[np.ndarray] = []
    for k in range(i, len(lines)):
        tok = lines[k].split()
        if not tok:
            continue
        if len(rows) == num_frames:
            raise SceneFormatError(
                path, f"line {k + 1}", f"more frame rows than 'Frames: {num_frames}' says"
            )
        if len(tok) != num_channels:
            raise SceneFormatError(
                path, f"line {k + 1} (frame {len(rows)})",
                f"expected {num_channels} values (the channels of the HIERARCHY), got {len(tok)}",
            )  # fmt: skip
        try:
            row = np.array(tok, dtype=float)
        except ValueError:
            bad = next(t for t in tok if not _is_number(t))
            col = tok.index(bad)
            raise SceneFormatError(
                path, f"line {k + 1} (frame {len(rows)}, column {col})",
                f"expected a number, got {bad!r}",
            ) from None  # fmt: skip
        if not np.isfinite(row).all():
            col = int(np.flatnonzero(~np.isfinite(row))[0])
            raise SceneFormatError(
                path, f"line {k + 1} (frame {len(rows)}, column {col})", f"not finite: {tok[col]!r}"
            )
        rows.append(row)
    if len(rows) != num_frames:
        raise SceneFormatError(
            path, "Frames", f"'Frames: {num_frames}' but the file has {len(rows)} frame rows"
        )
    values = np.stack(rows) if rows else np.zeros((0, num_channels))
    offsets = np.asarray(h["offsets"], dtype=float).reshape(-1, 3)
    channels = tuple(h["channels"])
    positions, rotations = forward_kinematics(offsets, tuple(h["parents"]), channels, values)
    return BvhMotion(
        path=path,
        names=tuple(h["names"]),
        parents=tuple(h["parents"]),
        offsets=offsets,
        channels=channels,
        end_site=tuple(h["end_site"]),
        frame_time=frame_time,
        values=values,
        positions=positions,
        rotations=rotations,
    )


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


# --------------------------------------------------------------------------- kinematics


def axis_rotation(axis: str, degrees: np.ndarray) -> np.ndarray:
    """(...,) angles in degrees about ``axis`` ('X', 'Y' or 'Z') -> (..., 3, 3) matrices."""
    a = np.deg2rad(np.asarray(degrees, dtype=float))
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    if axis == "X":
        m = [[o, z, z], [z, c, -s], [z, s, c]]
    elif axis == "Y":
        m = [[c, z, s], [z, o, z], [-s, z, c]]
    elif axis == "Z":
        m = [[c, -s, z], [s, c, z], [z, z, o]]
    else:
        raise ValueError(f"axis must be X, Y or Z, got {axis!r}")
    return np.stack([np.stack(r, -1) for r in m], -2)


def forward_kinematics(
    offsets: np.ndarray,
    parents: tuple[int, ...],
    channels: tuple[tuple[str, ...], ...],
    values: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """World positions and rotations of every joint.

    Args:
        offsets: (J, 3) joint origins in their parents' frames.
        parents: (J,) parent index (-1 root), parents before children.
        channels: per joint its channel names, in file order.
        values: (F, C) channel values, joints in order, rotations in degrees.
    Returns:
        positions (F, J, 3) and rotations (F, J, 3, 3), in the file's units and axes.
    """
    F, J = values.shape[0], len(parents)
    pos = np.zeros((F, J, 3))
    rot = np.zeros((F, J, 3, 3))
    col = 0
    for j in range(J):
        R = np.broadcast_to(np.eye(3), (F, 3, 3)).copy()
        t = np.broadcast_to(offsets[j], (F, 3)).copy()
        for name in channels[j]:
            v = values[:, col]
            col += 1
            axis = name[0]
            if name.endswith("position"):
                t[:, "XYZ".index(axis)] += v
            else:
                R = R @ axis_rotation(axis, v)
        p = parents[j]
        if p < 0:
            pos[:, j], rot[:, j] = t, R
        else:
            pos[:, j] = pos[:, p] + np.einsum("fab,fb->fa", rot[:, p], t)
            rot[:, j] = rot[:, p] @ R
    return pos, rot


def world_axes(*, y_up: bool = True) -> np.ndarray:
    """(3, 3) rotation from the file's axes to our world (z up): :data:`Y_UP_TO_WORLD`
    for a Y-up file, the identity for one already z up."""
    return Y_UP_TO_WORLD.copy() if y_up else np.eye(3)


def bvh_to_world_mm(motion: BvhMotion, *, scale_to_m: float, y_up: bool = True) -> np.ndarray:
    """(F, J, 3) joint positions in our world: millimetres, z up.

    Args:
        scale_to_m: metres per file unit (CMU cgspeed files: 0.056444).
        y_up: the file is Y up (BVH's usual axes); False for a file already z up.
    """
    if not scale_to_m > 0:
        raise ValueError(f"scale_to_m must be > 0, got {scale_to_m}")
    return 1000.0 * scale_to_m * motion.positions @ world_axes(y_up=y_up).T
