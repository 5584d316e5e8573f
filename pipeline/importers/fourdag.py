"""4D Association's skeleton text files: its 3D results and its copies of the Shelf and
Campus ground truth (Zhang et al., CVPR 2020, the ``data/`` folder of its repository).

Layout: a header line ``J F`` (joints per person, frames), then per frame the number
of people and, per person, its id and a 4 x J matrix (one line per row) whose columns
are homogeneous points in metres (x, y, z, then a confidence or 1). Whitespace separates
numbers; line breaks are not significant beyond that.

:data:`SKEL19` is the joint set of its results (19 joints: pelvis, neck, hips, nose,
shoulders, knees, ears, elbows, ankles, wrists, big toes); its copies of the truth hold
the Shelf / Campus protocol's 14 joints and the pelvis (:mod:`pipeline.evaluation.protocol`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.core.files import SceneFormatError
from pipeline.data.joint_sets import JointSet

SKEL19 = JointSet(
    "skel19",
    (
        "pelvis", "neck", "right_hip", "left_hip", "nose", "right_shoulder",
        "left_shoulder", "right_knee", "left_knee", "right_ear", "left_ear", "right_elbow",
        "left_elbow", "right_ankle", "left_ankle", "right_wrist", "left_wrist",
        "right_big_toe", "left_big_toe",
    ),
    bones=(
        (0, 1), (0, 2), (0, 3), (1, 4), (1, 5), (1, 6), (2, 7), (3, 8), (4, 9), (4, 10),
        (5, 11), (6, 12), (7, 13), (8, 14), (11, 15), (12, 16), (13, 17), (14, 18),
    ),
)  # fmt: skip
"""4D Association's SKEL19 (its ``SKEL19`` type), names as our joint sets spell them."""


@dataclass(frozen=True, eq=False)
class FourDagSkeletons:
    """The people of every frame of a 4D Association skeleton file.

    Attributes:
        frame: (N,) frame index (0 = the file's first frame).
        person_id: (N,) the file's id of each person.
        joints: (N, J, 3) mm.
        confidence: (N, J) the fourth row of each person's matrix.
        num_frames: frames the file declares.
    """

    frame: np.ndarray
    person_id: np.ndarray
    joints: np.ndarray
    confidence: np.ndarray
    num_frames: int


def read_fourdag_skeletons(path: str | os.PathLike) -> FourDagSkeletons:
    """Read ``path`` (module docstring); a SceneFormatError naming the file and the frame
    that breaks the layout."""
    path = Path(path)
    try:
        tokens = path.read_text().split()
    except (OSError, UnicodeDecodeError) as exc:
        raise SceneFormatError(path, None, f"not a readable text file ({exc})") from None
    pos = 0

    def take(n: int, field: str) -> list[str]:
        nonlocal pos
        if pos + n > len(tokens):
            raise SceneFormatError(path, field, "the file ends early")
        out = tokens[pos : pos + n]
        pos += n
        return out

    def integer(field: str) -> int:
        (tok,) = take(1, field)
        try:
            value = int(tok)
        except ValueError:
            raise SceneFormatError(path, field, f"expected an integer, got {tok!r}") from None
        if value < 0:
            raise SceneFormatError(path, field, f"expected an integer >= 0, got {value}")
        return value

    num_joints, num_frames = integer("header joints"), integer("header frames")
    frames, ids, mats = [], [], []
    for f in range(num_frames):
        for _ in range(integer(f"frame {f} people")):
            pid = integer(f"frame {f} person id")
            field = f"frame {f} person {pid}"
            try:
                m = np.array(take(4 * num_joints, field), dtype=float).reshape(4, num_joints)
            except ValueError:
                raise SceneFormatError(path, field, "expected 4 x J numbers") from None
            frames.append(f)
            ids.append(pid)
            mats.append(m)
    if pos != len(tokens):
        raise SceneFormatError(path, None, f"{len(tokens) - pos} numbers after the last frame")
    m = np.stack(mats) if mats else np.zeros((0, 4, num_joints))
    return FourDagSkeletons(
        frame=np.asarray(frames, np.int64),
        person_id=np.asarray(ids, np.int64),
        joints=np.swapaxes(m[:, :3], 1, 2) * 1000.0,
        confidence=m[:, 3],
        num_frames=num_frames,
    )
