"""Reference tracks: another tool's 3D result for a scene (e.g. Pose2Sim's TRC), kept beside
ours to compare against. Part of the native scene format (sample_data/README.md).

On disk, per reference ``NAME``: ``references/NAME.npz`` with ``joints`` (F, J, 3), world
millimetres, z up, in the scene's joint set, NaN where the tool has no joint; and in
``scene.json``::

    "references": {"NAME": {"file": "references/NAME.npz", "joint_set": "body25b",
                            "source": "Pose2Sim TRC .../trial_0-100.trc"}}

Frames: row ``i`` of ``joints`` is scene frame ``i``; a stored reference has exactly the
scene's ``num_frames`` rows (anything else is an error on load). When a reference is
attached (:func:`fit_frames`), a shorter one is padded with NaN at the end and a longer
one refused: a reference that runs past the scene means the two are not the same clip.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.core.files import SceneFormatError, load_npz, save_npz_atomic

REFERENCES_DIR = "references"
_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}$")


@dataclass(frozen=True, eq=False)
class ReferenceTrack:
    """One reference result.

    Attributes:
        name: unique per scene; letters, digits, ``_``, ``.`` and ``-`` (a file name and a
            viewer node name).
        joints: (F, J, 3) world mm, z up, in the scene's joint set; NaN = no joint.
        source: where it came from (free text, e.g. the TRC file it was read from).
    """

    name: str
    joints: np.ndarray
    source: str = ""


def check_name(name: str, source: str | os.PathLike) -> str:
    """``name`` if it is a valid reference name, else a SceneFormatError."""
    if not isinstance(name, str) or not _NAME.match(name):
        raise SceneFormatError(
            source,
            "references",
            f"reference name {name!r}: expected 1-64 letters, digits, '_', '.' or '-', "
            "not starting with '.' or '-'",
        )
    return name


def fit_frames(joints: np.ndarray, num_frames: int, *, source: str | os.PathLike) -> np.ndarray:
    """(F_ref, J, 3) -> (num_frames, J, 3): NaN-padded at the end when shorter; a reference
    longer than the scene is an error (see the module docstring)."""
    j = np.asarray(joints, float)
    if j.shape[0] > num_frames:
        raise SceneFormatError(
            source,
            "num_frames",
            f"the reference has {j.shape[0]} frames, the scene {num_frames}: "
            "a reference may not run past the scene",
        )
    pad = np.full((num_frames - j.shape[0],) + j.shape[1:], np.nan)
    return np.concatenate([j, pad])


def check_joints(
    joints: np.ndarray, *, source: str | os.PathLike, num_frames: int, num_joints: int
) -> np.ndarray:
    """Validate a reference's (num_frames, num_joints, 3) world-mm array."""
    a = np.asarray(joints)
    if a.dtype.kind not in "fiu":
        raise SceneFormatError(source, "joints", f"expected a numeric array, got {a.dtype}")
    if a.shape != (num_frames, num_joints, 3):
        raise SceneFormatError(
            source,
            "joints",
            f"expected shape ({num_frames}, {num_joints}, 3) (scene frames, joints of the "
            f"scene's joint set, xyz mm), got {a.shape}",
        )
    if np.isinf(a).any():
        raise SceneFormatError(source, "joints", "infinite values (NaN marks a missing joint)")
    return a.astype(np.float64)


def load_references(
    root: Path, meta: dict, *, joint_set: str, num_frames: int, num_joints: int
) -> dict[str, ReferenceTrack]:
    """The references ``scene.json`` (``meta``) lists, validated against the scene."""
    meta_path = root / "scene.json"
    refs = meta.get("references") or {}
    if not isinstance(refs, dict):
        raise SceneFormatError(meta_path, "references", "expected an object {name: {...}}")
    out = {}
    for name, entry in refs.items():
        check_name(name, meta_path)
        field = f"references.{name}"
        if not isinstance(entry, dict):
            raise SceneFormatError(meta_path, field, "expected an object")
        file = entry.get("file", f"{REFERENCES_DIR}/{name}.npz")
        source = entry.get("source", "")
        if not isinstance(file, str) or not isinstance(source, str):
            raise SceneFormatError(meta_path, field, "'file' and 'source' must be strings")
        if entry.get("joint_set") != joint_set:
            raise SceneFormatError(
                meta_path,
                f"{field}.joint_set",
                f"expected the scene's joint set {joint_set!r}, got {entry.get('joint_set')!r}",
            )
        path = root / file
        arrays = load_npz(path)
        if "joints" not in arrays:
            raise SceneFormatError(path, "joints", "missing (required array)")
        joints = check_joints(
            arrays["joints"], source=path, num_frames=num_frames, num_joints=num_joints
        )
        out[name] = ReferenceTrack(name=name, joints=joints, source=source)
    return out


def reference_entry(track: ReferenceTrack, joint_set: str) -> dict:
    """The ``scene.json`` entry of ``track``."""
    return {
        "file": f"{REFERENCES_DIR}/{track.name}.npz",
        "joint_set": joint_set,
        "source": track.source,
    }


def save_reference(scene_dir: Path, track: ReferenceTrack) -> None:
    """Write ``scene_dir/references/NAME.npz`` atomically (scene.json is the caller's)."""
    save_npz_atomic(scene_dir / REFERENCES_DIR / f"{track.name}.npz", joints=track.joints)


