"""A fitted SMPL track as an AMASS-style ``.npz`` (the layout training code reads).

Keys AMASS's loaders read:

* ``poses``: (F, 72) float64 axis-angle, joint-major (``poses[:, 3*j:3*j+3]`` is joint
  j; joint 0 the root orientation in the world, as AMASS's ``root_orient``);
* ``trans``: (F, 3) metres; ``betas``: (B,) (10 here); ``gender``: ``"neutral"``;
  ``mocap_framerate``: the scene's fps.

Convention (the same as AMASS's and smplx's): world **z up**, metres,
``vertices = body_model(poses, betas) + trans``, the model's canonical frame y up and
the root rotation carrying it into the world. Exactly our fit's, in metres.

What the body model is (AMASS assumes SMPL / SMPL+H; ours may be another model in the
SMPL file layout, e.g. the shipped open body model, whose betas mean other shapes):
``surface_model_type`` (``"smpl"`` for a licensed SMPL file, else
``"smpl-format:<file name>"``), ``body_model_file`` and ``body_model_sha256`` (the
model's content hash, :attr:`pipeline.body.model.BodyModel.fingerprint`), ``num_betas``
and ``world_convention`` (the text above).

Frames: the track's span, from its first to its last fitted frame
(``frame_offset`` = the scene frame of row 0); a gap inside it holds the last fitted
pose, and ``present`` (F,) says which rows were fitted. Also ``joints`` (F, 24, 3)
metres (the fitted joints), ``track``, ``stage`` and ``joint_set`` (what was fitted to),
and ``bone_scales`` (24,): the fit's bone length factors on top of the betas
(``SmplFit.bone_scales``, 1 = the shape space's length). AMASS's loaders do not know
them: posed by ``poses`` and ``betas`` alone, the body has the shape space's proportions
and ``joints`` differ from its joints where a factor is not 1.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from pipeline.core.files import save_npz_atomic
from pipeline.core.units import MM_PER_M
from pipeline.exports.common import gap_note, hold_indices
from pipeline.fit.types import SmplFit

WORLD_CONVENTION = (
    "world z up, metres; vertices = body_model(poses, betas) + trans (AMASS / smplx); "
    "the model's canonical frame is y up and poses[:, :3] (the root) rotates it into "
    "the world; the root joint sits at its rest position + trans"
)


def model_identity(fit: SmplFit) -> dict[str, str]:
    """``surface_model_type``, ``body_model_file``, ``body_model_sha256`` of the fit's model."""
    src = Path(str(fit.model.source))
    is_open = src.name.startswith("open_body")
    return {
        "surface_model_type": f"smpl-format:{src.name}" if is_open else "smpl",
        "body_model_file": src.name,
        "body_model_sha256": fit.model.fingerprint,
    }


def smpl_npz_arrays(fit: SmplFit, k: int, *, fps: float) -> dict[str, np.ndarray]:
    """The arrays of track ``k``'s file (see the module docstring)."""
    present = fit.present[k]
    if not present.any():
        raise ValueError(f"track {k} has no fitted frame")
    frames = np.flatnonzero(present)
    lo, hi = int(frames[0]), int(frames[-1]) + 1
    span = present[lo:hi]
    held = lo + hold_indices(span)
    F = hi - lo
    ident = model_identity(fit)
    return {
        "poses": np.asarray(fit.pose_rotvecs[k][held], np.float64).reshape(F, 72),
        "trans": np.asarray(fit.transl[k][held], np.float64) / MM_PER_M,
        "betas": np.asarray(fit.betas[k], np.float64),
        "num_betas": np.array(fit.betas.shape[-1]),
        "gender": np.array("neutral"),
        "mocap_framerate": np.array(float(fps)),
        "joints": np.asarray(fit.joints[k][held], np.float64) / MM_PER_M,
        "bone_scales": (
            np.ones(fit.pose_rotvecs.shape[2])
            if fit.bone_scales is None
            else np.nan_to_num(np.asarray(fit.bone_scales[k], np.float64), nan=1.0)
        ),
        "present": span.copy(),
        "frame_offset": np.array(lo),
        "track": np.array(k),
        "stage": np.array(fit.stage),
        "joint_set": np.array(fit.joint_set),
        "world_convention": np.array(WORLD_CONVENTION),
        **{key: np.array(v) for key, v in ident.items()},
        "mvviz_meta": np.array(json.dumps({"format": "mvviz smpl-npz", "version": 2})),
    }


def write_smpl_npz_track(path: str | os.PathLike, fit: SmplFit, k: int, *, fps: float) -> list[str]:
    """Write track ``k`` of ``fit`` as an AMASS-style npz, atomically; returns notes."""
    if not fps > 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    arrays = smpl_npz_arrays(fit, k, fps=fps)
    save_npz_atomic(path, **arrays)
    lo = int(arrays["frame_offset"])
    notes = [f"track {k}: scene frames {lo}-{lo + len(arrays['present']) - 1}"]
    note = gap_note(arrays["present"], "the last fitted pose is held ('present' says which)")
    if note:
        notes.append(f"track {k}: {note} (frame numbers from frame_offset)")
    return notes
