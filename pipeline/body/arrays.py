"""The body model as numpy arrays: loading, checking, fingerprint, forward kinematics.

What every stage that does not optimise needs from an SMPL-format model, without torch
(``import torch`` is ~3-7 s on the build machines): the viewer's cache key and skinned
bodies read this; the fit and the restoration build :class:`pipeline.body.model.BodyModel`
(torch) from it when they run (:func:`pipeline.body.model.torch_body_model`).

Files: any file in the standard SMPL layout (``v_template, shapedirs, posedirs,
J_regressor, weights, kintree_table, faces``) from ``.npz`` or from ``.pkl`` (without
chumpy). The shipped default is ``sample_data/body_models/open_body_24.npz``; a licensed
SMPL file is used instead when its path is passed or set in ``MVVIZ_SMPL_MODEL``.
Units and frames: metres, the model's canonical frame (y up, facing +z). Shapes use B
for batch, V vertices, J = 24 joints, nb betas.
"""

from __future__ import annotations

import hashlib
import os
import pickle
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.core.files import SceneFormatError
from pipeline.core.units import SAMPLE_DATA

DEFAULT_MODEL_PATH = SAMPLE_DATA / "body_models" / "open_body_24.npz"
MODEL_ENV_VAR = "MVVIZ_SMPL_MODEL"
NUM_JOINTS = 24
NUM_BETAS = 10
REQUIRED_KEYS = ("v_template", "shapedirs", "J_regressor", "weights", "kintree_table", "faces")


def kinematic_levels(parents: np.ndarray) -> list[np.ndarray]:
    """Group joints by depth in the tree, so a chain can be composed level by level."""
    depth = np.zeros(len(parents), int)
    for j, p in enumerate(parents):
        if p >= 0:
            if p >= j:
                raise ValueError("kintree parents must precede their children")
            depth[j] = depth[p] + 1
    return [np.flatnonzero(depth == d) for d in range(depth.max() + 1)]


def model_fingerprint(arrays: dict[str, np.ndarray]) -> str:
    """What a model is, not where it lives: results cached with one install are reused by
    another (pipeline/results/store.py's cache key)."""
    h = hashlib.sha256()
    for k in sorted(k for k in arrays if arrays[k] is not None):
        a = arrays[k]
        h.update(k.encode() + str(a.shape).encode() + np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


@dataclass(frozen=True, eq=False)
class BodyModelData:
    """A checked SMPL-format model as numpy arrays (float64 where it computes)."""

    source: str
    fingerprint: str
    arrays: dict[str, np.ndarray]  # the checked file arrays (what BodyModel's buffers hold)
    parents: np.ndarray  # (J,) parent joint, -1 for the root
    levels: tuple[np.ndarray, ...]  # joints of each depth of the tree
    v_template: np.ndarray  # (V, 3)
    shapedirs: np.ndarray  # (V, 3, nb)
    weights: np.ndarray  # (V, J)
    faces: np.ndarray  # (T, 3) int64
    J_template: np.ndarray  # (J, 3) J_regressor @ v_template
    J_shapedirs: np.ndarray  # (J, 3, nb) J_regressor @ shapedirs
    joint_names: list[str] | None = None

    @classmethod
    def from_arrays(cls, arrays: dict[str, Any], *, source: str = "<memory>") -> BodyModelData:
        a = _check_model_arrays(arrays, source)
        parents = a["kintree_table"][0].astype(np.int64)
        parents[0] = -1
        f64 = lambda k: np.asarray(a[k], np.float64)  # noqa: E731
        J_reg = f64("J_regressor")
        names = a.get("joint_names")
        return cls(
            source=source, fingerprint=model_fingerprint(a), arrays=a, parents=parents,
            levels=tuple(kinematic_levels(parents)), v_template=f64("v_template"),
            shapedirs=f64("shapedirs"), weights=f64("weights"),
            faces=a["faces"].astype(np.int64), J_template=J_reg @ f64("v_template"),
            J_shapedirs=np.einsum("jv,vcb->jcb", J_reg, f64("shapedirs")),
            joint_names=None if names is None else [str(n) for n in names],
        )  # fmt: skip

    @property
    def num_vertices(self) -> int:
        return int(self.v_template.shape[0])

    @property
    def num_betas(self) -> int:
        return int(self.shapedirs.shape[-1])

    def padded_betas(self, betas: np.ndarray) -> np.ndarray:
        """(B, <= or > nb) -> (B, nb): missing betas are zero, extra ones dropped."""
        b = np.asarray(betas, np.float64).reshape(len(betas), -1)[:, : self.num_betas]
        return np.pad(b, ((0, 0), (0, self.num_betas - b.shape[1])))

    def rest_joints(self, betas: np.ndarray) -> np.ndarray:
        """(B, nb) betas -> (B, J, 3) rest-pose joints, m."""
        b = self.padded_betas(betas)
        return self.J_template + np.einsum("jcb,nb->njc", self.J_shapedirs, b)

    def shaped_vertices(self, betas: np.ndarray) -> np.ndarray:
        """(B, nb) betas -> (B, V, 3) rest-pose vertices with the shape blend shapes, m."""
        return self.v_template + np.einsum("vcb,nb->nvc", self.shapedirs, self.padded_betas(betas))

    def pose_chain(
        self, pose_rotvecs: np.ndarray, betas: np.ndarray, bone_scales: np.ndarray | None = None
    ):
        """Forward kinematics (no translation; the root stays at its rest position).

        Args: pose_rotvecs (B, J, 3) local axis-angle; betas (B, nb); bone_scales
            (B, J) each bone's length factor (:func:`scale_bones_np`), None: 1.
        Returns: global rotations (B, J, 3, 3) of the joint frames, posed joints (B, J, 3) m.
        """
        # scipy.spatial loads ~0.3 s of modules: only where a pose is posed, not in every
        # process that reads a body model (the batch's driver, the viewer's start)
        from scipy.spatial.transform import Rotation

        B = len(pose_rotvecs)
        rot = Rotation.from_rotvec(np.asarray(pose_rotvecs, np.float64).reshape(-1, 3))
        rest = self.rest_joints(betas)
        if bone_scales is not None:
            rest = scale_bones_np(rest, bone_scales, self.parents)
        return forward_kinematics_np(rot.as_matrix().reshape(B, NUM_JOINTS, 3, 3), rest, self)


def ancestry(parents: np.ndarray) -> np.ndarray:
    """(J,) parents -> (J, J) 1.0 where column ``a`` is joint ``j`` (row) or one of its
    ancestors: a joint's position is the sum of the bone vectors of its row."""
    J = len(parents)
    out = np.zeros((J, J))
    for j in range(J):
        a = j
        while a >= 0:
            out[j, a] = 1.0
            a = parents[a]
    return out


def scale_bones_np(rest: np.ndarray, bone_scales: np.ndarray, parents: np.ndarray) -> np.ndarray:
    """Rest joints (B, J, 3) with each bone (joint minus parent) scaled by ``bone_scales``
    (B, J) (a root's entry unused; NaN counts as 1): a skeleton of other proportions whose
    joints still carry the body's surface, as the skinning attaches it to them."""
    parents = np.asarray(parents, int)
    s = np.where(np.isfinite(bone_scales), bone_scales, 1.0)
    s = np.where(parents[None] >= 0, s, 1.0)
    local = rest - np.where((parents >= 0)[:, None], rest[:, np.maximum(parents, 0)], 0.0)
    return np.einsum("ja,nac->njc", ancestry(parents), local * s[..., None])


def forward_kinematics_np(
    rot_mats: np.ndarray, rest_joints: np.ndarray, model: BodyModelData
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`pipeline.body.model.forward_kinematics` in numpy, one tree level at a time.

    Args: rot_mats (B, J, 3, 3) local rotations; rest_joints (B, J, 3).
    Returns: global rotations (B, J, 3, 3), posed joints (B, J, 3).
    """
    R = np.empty_like(rot_mats)
    pos = np.empty_like(rest_joints)
    for d, lv in enumerate(model.levels):
        if d == 0:
            R[:, lv], pos[:, lv] = rot_mats[:, lv], rest_joints[:, lv]
            continue
        p = model.parents[lv]
        offset = rest_joints[:, lv] - rest_joints[:, p]
        R[:, lv] = R[:, p] @ rot_mats[:, lv]
        pos[:, lv] = pos[:, p] + (R[:, p] @ offset[..., None])[..., 0]
    return R, pos


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


_DATA_CACHE: dict[Path, BodyModelData] = {}


def load_body_model_data(path: str | os.PathLike | None = None) -> BodyModelData:
    """Load (once per process) the arrays of the body model that every stage uses."""
    p = resolve_model_path(path).resolve()
    if p not in _DATA_CACHE:
        _DATA_CACHE[p] = BodyModelData.from_arrays(load_body_model_arrays(p), source=str(p))
    return _DATA_CACHE[p]


def body_data(model) -> BodyModelData:
    """The numpy arrays of ``model``: a :class:`BodyModelData` or a torch ``BodyModel``."""
    return model if isinstance(model, BodyModelData) else model.data
