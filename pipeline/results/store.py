"""One results file per run: everything the viewer and the evaluation need, per frame.

Results are columnar: per detection row (N), per person-frame (Q, the people the
per-frame stages found), per affinity edge (E), per track (K x F). They are written
atomically, and keyed by a hash of the scene's files and the configuration so a re-run
with the same inputs reuses them. Two layouts hold the same arrays and meta: a ``.npz``
path one compressed file (``results.npz``, read whole), any other path a directory of
uncompressed ``.npy`` files that :func:`load_results` memory-maps
(:mod:`pipeline.results.array_dir`): a viewer of a long, large scene reads only the frames it
shows.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from pipeline.association.associate import Association
from pipeline.body.arrays import BodyModelData, load_body_model_data
from pipeline.config import PipelineConfig
from pipeline.core.files import (
    SceneFormatError,
    load_npz,
    save_npz_atomic,
    scene_cache_dir,
)
from pipeline.core.units import PIPELINE_DIR
from pipeline.data.scene import Scene
from pipeline.fit.prior_path import resolve_prior_path
from pipeline.fit.types import SmplFit
from pipeline.results.array_dir import open_array_dir, write_array_dir
from pipeline.stages.kalman import FilterResult
from pipeline.stages.track import Tracks
from pipeline.stages.triangulate import Triangulation

if TYPE_CHECKING:
    from pipeline.body.model import BodyModel

STAGES = ("raw", "kalman", "rts", "smpl", "smpl_vae")
"""The stages whose joints results hold: raw triangulation, Kalman forward filter, RTS
smoother, SMPL fit (step I) and SMPL fit corrected by the VAE pose prior (the names of
``--stage``, of the evaluation's rows and of the exports)."""
BODY_STAGES = ("smpl", "smpl_vae")
"""The stages that give bodies: :class:`PipelineResults` fields holding a ``SmplFit``."""
RESULTS_VERSION = 7  # 7: joints checked by the tracks' bones (track_resolved,
# track_contradicted, the latter also in track_rejected); 6: edges only where a reader
# uses them, int32 / float32 (5: track_rejected)
RESULTS_FILE = "results.npz"  # in the scene's cache folder (SCENE/.mvviz)
RESULTS_DIR = "results"  # ... for a long scene: a directory of memory-mapped columns
LONG_SCENE_VIEW_FRAMES = 50_000
"""Frames x cameras from which a scene's default results are a directory (written by the
stages as they go, opened lazily; :mod:`pipeline.run.streamed`) rather than one
compressed file: a 10,000-frame dome:31 x 20 run in memory took ~11 GB, streamed 1.8 GB,
and its compressed file alone would take longer to write than the run."""


@dataclass(frozen=True, eq=False)
class FrameResult:
    """Per-frame stages of one frame.

    Attributes:
        frame: the frame index.
        rows: (n,) detection rows (into the scene's detections) of this frame.
        joints2d: (n, J, 3) the 2D joints that fed association and triangulation.
        association: clusters, affinities and members.
        triangulation: (num_people, J, ...) 3D joints, reprojection errors, used views.
    """

    frame: int
    rows: np.ndarray
    joints2d: np.ndarray
    association: Association
    triangulation: Triangulation


@dataclass(frozen=True, eq=False)
class SequenceResult:
    """Sequence-wide stages: tracks and their filtered trajectories.

    Attributes:
        person_track: (Q,) track of each person-frame (rows of the per-frame people).
        tracks: raw joints per track (K, F, J, 3) and lifetimes.
        filtered: Kalman result over (F, K, J, 3) measurements; ``forward`` is the
            forward filter, ``filtered`` the RTS-smoothed one.
        track_resolved: (K, F, J) bool, joints re-solved from the views that fit the
            track's bones (:mod:`pipeline.stages.proportions`); None: not checked.
        track_contradicted: (K, F, J) bool, joints kept but not filtered: they contradict
            the track's bones and no views fit them.
    """

    person_track: np.ndarray
    tracks: Tracks
    filtered: FilterResult
    track_resolved: np.ndarray | None = None
    track_contradicted: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class PipelineResults:
    """A run, as arrays. Shapes: N detection rows, Q person-frames, E affinity edges
    (:func:`pack_frame`: a person's own pairs and the compatible pairs across people),
    K tracks, F frames, V views, J joints of the source joint set."""

    config: PipelineConfig
    joint_set: str
    num_frames: int
    num_views: int
    det_joints2d: np.ndarray  # (N, J, 3) the 2D joints that fed the stages
    det_restored: np.ndarray | None  # (N, 24, 3) restored SMPL 2D joints, if the scene has them
    det_person: np.ndarray  # (N,) person-frame row (into the Q arrays), -1 unassigned
    person_frame: np.ndarray  # (Q,)
    person_joints: np.ndarray  # (Q, J, 3) raw triangulation, mm
    person_reproj: np.ndarray  # (Q, J, V) reprojection error px, NaN where unobserved
    person_used: np.ndarray  # (Q, J, V) bool
    person_members: np.ndarray  # (Q, V) detection row per view, -1
    person_linkage: np.ndarray  # (Q,) mean affinity inside the cluster
    person_track: np.ndarray  # (Q,) track index, -1
    edge_a: np.ndarray  # (E,) int32 detection row
    edge_b: np.ndarray  # (E,) int32 detection row
    edge_affinity: np.ndarray  # (E,) float32
    edge_distance: np.ndarray  # (E,) float32 mean ray distance, mm
    track_raw: np.ndarray  # (K, F, J, 3)
    track_forward: np.ndarray  # (K, F, J, 3) Kalman forward filter
    track_smoothed: np.ndarray  # (K, F, J, 3) RTS
    track_prior: np.ndarray  # (K, F, J, 3) predicted mean before each update
    track_innovation: np.ndarray  # (K, F, J, 3)
    track_mahalanobis: np.ndarray  # (K, F, J)
    track_rejected: np.ndarray  # (K, F, J) bool: measurement present, rejected by the gate
    smpl: SmplFit | None = None  # step I fit to track_smoothed
    smpl_vae: SmplFit | None = None  # step I corrected by the VAE pose prior
    cache_key: str = ""
    det_flipped: np.ndarray | None = None  # (N,) bool: left/right swapped in the input,
    # un-mirrored by association (det_joints2d holds the un-mirrored joints)
    track_resolved: np.ndarray | None = None  # (K, F, J) bool: re-solved from the views
    # that fit the track's bones (pipeline.stages.proportions)
    fit_floor: np.ndarray | None = None  # (K, F) mm: how near the best skeleton of constant
    # bone lengths comes to the fits' input (track_smoothed), pipeline.fit.floor
    track_contradicted: np.ndarray | None = None  # (K, F, J) bool: contradicts the track's
    # bones, kept in track_raw, skipped by the filter where it can coast (track_rejected)

    @property
    def num_tracks(self) -> int:
        return int(self.track_raw.shape[0])

    @property
    def track_filtered(self) -> np.ndarray:
        """The configured filter's output: smoothed if the config asks for RTS."""
        return self.track_smoothed if self.config.kalman.smoother else self.track_forward

    def people_in_frame(self, frame: int) -> np.ndarray:
        return np.flatnonzero(self.person_frame == frame)


# Per person-frame (Q) and per affinity edge (E) fields, in the order of the class.
PERSON_FIELDS = (
    "person_frame", "person_joints", "person_reproj", "person_used", "person_members",
    "person_linkage",
)  # fmt: skip
EDGE_FIELDS = ("edge_a", "edge_b", "edge_affinity", "edge_distance")


@dataclass(frozen=True, eq=False)
class FrameColumns:
    """One frame's rows of the :class:`PipelineResults` person (Q) and edge (E) arrays;
    P people, n detection rows, E edges (see :func:`pack_frame`)."""

    person_frame: np.ndarray  # (P,) int
    person_joints: np.ndarray  # (P, J, 3) mm
    person_reproj: np.ndarray  # (P, J, V) px
    person_used: np.ndarray  # (P, J, V) bool
    person_members: np.ndarray  # (P, V) detection row per view, -1
    person_linkage: np.ndarray  # (P,)
    edge_a: np.ndarray  # (E,) int32 detection row
    edge_b: np.ndarray  # (E,) int32 detection row
    edge_affinity: np.ndarray  # (E,) float32
    edge_distance: np.ndarray  # (E,) float32 mm


def pack_frame(fr: FrameResult, num_views: int, num_joints: int) -> FrameColumns:
    """``fr``'s association and triangulation as rows of the results' Q and E arrays
    (detection indices are the scene's rows, ``fr.rows[...]``).

    The edges kept are the pairs a reader of the results uses: each person's own pairs
    (a detection's affinity to its own person) and the compatible pairs (affinity > 0:
    a detection close to two people). The incompatible rest, most pairs once there are
    many people (~30x the kept ones on a 31-camera dome with 20 people), would be most
    of the results' size and is the association's business only."""
    a, t = fr.association, fr.triangulation
    P, V, J = a.num_people, num_views, num_joints
    members = np.where(a.members >= 0, fr.rows[np.maximum(a.members, 0)], -1)
    ia, ib = np.triu_indices(len(fr.rows), 1)
    aff = a.affinity[ia, ib]
    same = (a.cluster[ia] >= 0) & (a.cluster[ia] == a.cluster[ib])
    keep = np.isfinite(aff) & ((aff > 0) | same)
    ia, ib, aff = ia[keep], ib[keep], aff[keep]
    return FrameColumns(
        person_frame=np.full(P, fr.frame, int),
        person_joints=t.points.reshape(P, J, 3).astype(float),
        person_reproj=t.reprojection_error.reshape(P, J, V).astype(float),
        person_used=t.used.reshape(P, J, V).astype(bool),
        person_members=members.reshape(P, V).astype(int),
        person_linkage=np.asarray(a.linkage, float).reshape(P),
        edge_a=fr.rows[ia].astype(np.int32),
        edge_b=fr.rows[ib].astype(np.int32),
        edge_affinity=aff.astype(np.float32),
        edge_distance=a.ray_distance[ia, ib].astype(np.float32),
    )


def join_columns(cols: list[FrameColumns], num_views: int, num_joints: int) -> FrameColumns:
    """One FrameColumns of many frames' (in order); an empty one for no frames."""
    empty = empty_columns(num_views, num_joints)
    return FrameColumns(
        **{
            f.name: np.concatenate([getattr(c, f.name) for c in [empty, *cols]])
            for f in dataclasses.fields(FrameColumns)
        }
    )


def empty_columns(num_views: int, num_joints: int) -> FrameColumns:
    """No rows, with the dtypes and row shapes every :class:`FrameColumns` has."""
    V, J = num_views, num_joints
    return FrameColumns(
        np.zeros(0, int), np.zeros((0, J, 3)), np.zeros((0, J, V)), np.zeros((0, J, V), bool),
        np.zeros((0, V), int), np.zeros(0), np.zeros(0, np.int32), np.zeros(0, np.int32),
        np.zeros(0, np.float32), np.zeros(0, np.float32),
    )  # fmt: skip


class DetectionLabels:
    """Per detection row, filled frame by frame in order: the person-frame it was
    associated to (-1: none), whether the association flipped its left/right, and its 2D
    joints (``joints2d_all`` until the first flip, then a copy holding the flipped rows;
    with ``writable``, ``joints2d_all`` is the caller's own copy, written into)."""

    def __init__(self, joints2d_all: np.ndarray, *, writable: bool = False):
        n = len(joints2d_all)
        self.person = np.full(n, -1)
        self.flipped = np.zeros(n, bool)
        self.joints2d = joints2d_all
        self._given = None if writable else joints2d_all
        self.num_people = 0  # person-frames so far: the next frame's first index

    def add(self, fr: FrameResult) -> None:
        a = fr.association
        assigned = a.cluster >= 0
        self.person[fr.rows[assigned]] = self.num_people + a.cluster[assigned]
        if a.flipped.any():
            if self.joints2d is self._given:
                self.joints2d = self._given.copy()
            rows = fr.rows[a.flipped]
            self.flipped[rows] = True
            self.joints2d[rows] = fr.joints2d[a.flipped]
        self.num_people += a.num_people


def assemble_results(
    labels: DetectionLabels,
    columns: FrameColumns,
    seq: SequenceResult,
    *,
    config: PipelineConfig,
    joint_set: str,
    num_frames: int,
    num_views: int,
    restored: np.ndarray | None,
    cache_key: str = "",
) -> PipelineResults:
    """:class:`PipelineResults` from the per-detection labels, the frames' joined
    columns and the sequence stages."""
    return PipelineResults(
        config=config,
        joint_set=joint_set,
        num_frames=num_frames,
        num_views=num_views,
        det_joints2d=labels.joints2d,
        det_restored=restored,
        det_person=labels.person,
        det_flipped=labels.flipped,
        **{k: getattr(columns, k) for k in PERSON_FIELDS + EDGE_FIELDS},
        person_track=seq.person_track,
        track_raw=seq.tracks.joints,
        **filter_arrays(seq.filtered),
        track_resolved=seq.track_resolved,
        track_contradicted=seq.track_contradicted,
        cache_key=cache_key,
    )


def filter_arrays(filtered: FilterResult) -> dict[str, np.ndarray]:
    """The ``track_*`` arrays of a Kalman run over (F, K, J, 3), tracks first."""
    to_tracks = lambda x: np.moveaxis(x, 0, 1)  # (F, K, ...) -> (K, F, ...)  # noqa: E731
    return {
        "track_forward": to_tracks(filtered.forward),
        "track_smoothed": to_tracks(filtered.filtered),
        "track_prior": to_tracks(filtered.prior_mean),
        "track_innovation": to_tracks(filtered.innovation),
        "track_mahalanobis": to_tracks(filtered.mahalanobis),
        "track_rejected": to_tracks(filtered.rejected),
    }


def pack(
    frames: list[FrameResult],
    seq: SequenceResult,
    *,
    config: PipelineConfig,
    joint_set: str,
    num_frames: int,
    num_views: int,
    restored: np.ndarray | None,
    joints2d_all: np.ndarray,
    cache_key: str = "",
) -> PipelineResults:
    """Flatten per-frame results and the sequence stages into :class:`PipelineResults`."""
    labels = DetectionLabels(joints2d_all)
    cols = []
    for fr in frames:
        labels.add(fr)
        cols.append(pack_frame(fr, num_views, joints2d_all.shape[1]))
    return assemble_results(
        labels, join_columns(cols, num_views, joints2d_all.shape[1]), seq, config=config,
        joint_set=joint_set, num_frames=num_frames, num_views=num_views, restored=restored,
        cache_key=cache_key,
    )  # fmt: skip


def scene_fingerprint(scene: Scene) -> str:
    """Hash of the scene files that feed the pipeline (content of the small ones)."""
    h = hashlib.sha256()
    for name in ("scene.json", "cameras.json", scene.meta.get("detections", "detections.npz")):
        p = scene.root / name
        if p.is_file():
            h.update(name.encode())
            h.update(p.read_bytes())
        elif p.is_dir():
            # A detections directory (a long scene: 1.9 GB at 10,000 frames x 31 x 20, 2 s
            # to hash at every start) by each column file's size and modification time:
            # any rewrite of a file changes them.
            for f in sorted(p.glob("*.npy")):
                st = f.stat()
                h.update(f"{name}/{f.name}:{st.st_size}:{st.st_mtime_ns}".encode())
    return h.hexdigest()


def cache_key(scene: Scene, config: PipelineConfig, model: BodyModel | BodyModelData) -> str:
    h = hashlib.sha256()
    h.update(scene_fingerprint(scene).encode())
    h.update(dataclasses.replace(config, pose_prior="").to_json().encode())  # its content below
    h.update(model.fingerprint.encode())  # the model's content, not its path
    if config.fit_smpl and config.use_pose_prior:
        prior = resolve_prior_path(config.pose_prior or None)
        if prior.is_file():
            h.update(hashlib.sha256(prior.read_bytes()).digest())
    h.update(str(RESULTS_VERSION).encode())
    h.update(code_digest().encode())
    return h.hexdigest()[:16]


@functools.cache
def code_digest() -> str:
    """A digest of the pipeline's own source: results made by other code are recomputed
    (a cache that outlives an upgrade of the stages would show the old stages' numbers)."""
    h = hashlib.sha256()
    root = PIPELINE_DIR
    for path in sorted(root.rglob("*.py")):
        h.update(path.relative_to(root).as_posix().encode())
        h.update(path.read_bytes())
    return h.hexdigest()[:16]


# --------------------------------------------------------------------------- file io

# Fields stored as one array each; the others go into the file's JSON meta or, for the
# optional arrays and the fits, are handled one by one.
OPTIONAL_ARRAYS = (
    "det_restored", "det_flipped", "track_resolved", "track_contradicted", "fit_floor",
)  # fmt: skip
_NOT_ARRAYS = {
    "config", "joint_set", "num_frames", "num_views", "cache_key", *OPTIONAL_ARRAYS,
}  # fmt: skip
_ARRAY_FIELDS = [
    f.name
    for f in dataclasses.fields(PipelineResults)
    if f.name not in _NOT_ARRAYS | {"smpl", "smpl_vae"}
]
_FIT_PREFIXES = {"smpl": "smpl_", "smpl_vae": "smplvae_"}


def results_meta(
    config: PipelineConfig,
    *,
    joint_set: str,
    num_frames: int,
    num_views: int,
    cache_key: str,
    body_model: str | None,
) -> dict:
    """What a results file holds besides its arrays (``meta`` of either layout)."""
    return {
        "version": RESULTS_VERSION,
        "config": config.to_dict(),
        "joint_set": joint_set,
        "num_frames": num_frames,
        "num_views": num_views,
        "cache_key": cache_key,
        "body_model": body_model,
    }


def _file_contents(results: PipelineResults) -> tuple[dict, dict[str, np.ndarray]]:
    """(meta, arrays) of ``results`` as either layout stores them."""
    meta = results_meta(
        results.config, joint_set=results.joint_set, num_frames=results.num_frames,
        num_views=results.num_views, cache_key=results.cache_key,
        body_model=str(results.smpl.model.source) if results.smpl is not None else None,
    )  # fmt: skip
    arrays = {k: getattr(results, k) for k in _ARRAY_FIELDS}
    for optional in OPTIONAL_ARRAYS:
        if getattr(results, optional) is not None:
            arrays[optional] = getattr(results, optional)
    arrays.update(fit_arrays(results))
    return meta, arrays


def fit_arrays(results: PipelineResults) -> dict[str, np.ndarray]:
    """The arrays a results file stores of ``results``' SMPL fits (none without fits)."""
    arrays: dict[str, np.ndarray] = {}
    for name, prefix in _FIT_PREFIXES.items():
        fit = getattr(results, name)
        if fit is not None:
            arrays.update(fit.arrays(prefix))
    if results.fit_floor is not None:
        arrays["fit_floor"] = results.fit_floor
    return arrays


def is_npz_path(path: str | os.PathLike) -> bool:
    """A ``.npz`` path holds the one-file layout; any other path the lazy directory."""
    return Path(path).suffix.lower() == ".npz"


def save_results(results: PipelineResults, path: str | os.PathLike) -> None:
    """Write ``results`` atomically: one compressed ``.npz`` file if ``path`` ends in
    ``.npz`` (read whole), else a directory of memory-mappable ``.npy`` arrays
    (:mod:`pipeline.results.array_dir`, which the viewer opens without reading it)."""
    meta, arrays = _file_contents(results)
    if is_npz_path(path):
        save_npz_atomic(path, meta=np.array(json.dumps(meta)), **arrays)
    else:
        write_array_dir(path, meta, arrays)


def _read_contents(path: Path) -> tuple[dict, dict[str, np.ndarray]]:
    if path.is_dir():
        return open_array_dir(path)  # memory-mapped: nothing read yet
    a = load_npz(path)
    try:
        meta = json.loads(str(a.pop("meta")))
    except KeyError:
        raise SceneFormatError(path, "meta", "missing: not an mvviz results file") from None
    return meta, a


def load_results(
    path: str | os.PathLike, *, model: BodyModel | BodyModelData | None = None
) -> PipelineResults:
    """Read a results file, or open a results directory (its arrays memory-mapped, read
    as they are indexed); SMPL fits are bound to ``model`` (default: the one they used)."""
    path = Path(path)
    if not path.exists():
        raise SceneFormatError(path, None, "file not found")
    meta, a = _read_contents(path)
    if meta.get("version") != RESULTS_VERSION:
        raise SceneFormatError(path, "meta.version", f"expected {RESULTS_VERSION}")
    missing = [k for k in _ARRAY_FIELDS if k not in a]
    if missing:
        raise SceneFormatError(path, missing[0], "missing array")
    fits: dict[str, SmplFit | None] = dict.fromkeys(_FIT_PREFIXES)
    for name, prefix in _FIT_PREFIXES.items():
        if prefix + "transl" in a:
            if model is None:
                model = load_body_model_data(meta.get("body_model"))
            fits[name] = SmplFit.from_arrays(
                a, prefix, joint_set=meta["joint_set"], model=model, stage=name
            )
    return PipelineResults(
        **fits,
        config=PipelineConfig.from_dict(meta["config"], source=str(path)),
        joint_set=meta["joint_set"],
        num_frames=int(meta["num_frames"]),
        num_views=int(meta["num_views"]),
        cache_key=meta.get("cache_key", ""),
        **{k: a.get(k) for k in OPTIONAL_ARRAYS},
        **{k: a[k] for k in _ARRAY_FIELDS},
    )


def default_results_path(scene: Scene) -> Path:
    """Where a scene's results go unless told (``--out``): ``results.npz`` in the scene's
    cache folder (:func:`~pipeline.core.files.scene_cache_dir`: ``SCENE/.mvviz``, or the
    user's cache for a folder that cannot be written), or for a long scene
    (:data:`LONG_SCENE_VIEW_FRAMES`), or where such a directory is already, the
    directory ``results`` there."""
    return results_path_in(scene, scene_cache_dir(scene.root))


def results_path_in(scene: Scene, folder: Path) -> Path:
    """:func:`default_results_path` in the cache folder ``folder``."""
    long = scene.num_frames * len(scene.rig) >= LONG_SCENE_VIEW_FRAMES
    if long or (folder / RESULTS_DIR).is_dir():
        return folder / RESULTS_DIR
    return folder / RESULTS_FILE
