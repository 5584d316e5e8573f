"""Every fitted track as a skinned, animated body in one binary glTF (``.glb``).

Blender's glTF importer, three.js's ``GLTFLoader`` (and so viser's ``add_glb``),
Unity's glTFast and trimesh (static) open it. glTF's axes are **Y up**, metres, as the
body model's canonical frame, so each body is the skeleton of
:mod:`pipeline.exports.skeleton`:

* per track: a node ``track<k>`` holding the joint hierarchy (24 nodes named
  ``track<k>_<joint>``, translations = the fitted betas' bone offsets), and a mesh node
  ``track<k>_body`` (at the scene root, as glTF asks of skinned meshes) whose mesh is
  the shaped rest body (bind pose: the rest joints, inverse bind matrices
  ``T(-rest_joint)``), 8 skinning influences per vertex (``JOINTS_0/WEIGHTS_0`` the 4
  largest, ``JOINTS_1/WEIGHTS_1`` the next 4, renormalised; loaders that read only the
  first set, three.js, renormalise those 4), a material in the track's viewer colour.
  Pose correctives (``posedirs``, zero in the shipped open model) are not represented.
* one animation ``motion``: per track the root joint's translation and every joint's
  rotation at each scene frame (time = frame / fps, LINEAR), and, when a track starts
  late or ends early, the ``track<k>`` node's scale (STEP: 0 outside the track's span,
  so the body is not drawn before it appears or after it is lost). Inside a gap the
  last fitted pose is held (``extras.held_frames`` on the track node lists them).

The scene's ``extras`` record the stage, the fps, the body model and the world
convention (``world = (z, x, y)`` of a glTF point, times 1000 for mm).
"""

from __future__ import annotations

import json
import os
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import trimesh
from scipy.spatial.transform import Rotation

from pipeline.body.model import torch_body_model
from pipeline.core.files import atomic_write
from pipeline.core.palette import track_rgb
from pipeline.exports.common import gap_note
from pipeline.exports.skeleton import TrackSkeleton, track_skeleton
from pipeline.fit.types import SmplFit

FLOAT, UINT, UBYTE = 5126, 5125, 5121
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963
_GLB_MAGIC, _JSON_CHUNK, _BIN_CHUNK = 0x46546C67, 0x4E4F534A, 0x004E4942
INFLUENCES = 8
WORLD_NOTE = (
    "glTF axes (y up, metres) = our world (z up, mm) by world_mm = 1000 * (z, x, y) of a "
    "glTF point; bodies are 1000 * body_model(pose, betas) + transl of the fit"
)


class _Buffer:
    """The GLB's binary chunk, built view by view (4-byte aligned), with accessors."""

    def __init__(self) -> None:
        self.chunks: list[bytes] = []
        self.size = 0
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def accessor(self, data: np.ndarray, ctype: int, kind: str, *, target: int | None = None,
                 minmax: bool = False) -> int:  # fmt: skip
        raw = np.ascontiguousarray(data).tobytes()
        pad = (-self.size) % 4
        if pad:
            self.chunks.append(b"\0" * pad)
            self.size += pad
        view = {"buffer": 0, "byteOffset": self.size, "byteLength": len(raw)}
        if target is not None:
            view["target"] = target
        self.views.append(view)
        self.chunks.append(raw)
        self.size += len(raw)
        count = data.shape[0]
        acc = {"bufferView": len(self.views) - 1, "componentType": ctype, "count": int(count),
               "type": kind}  # fmt: skip
        if minmax:
            flat = np.asarray(data, float).reshape(count, -1)
            acc["min"] = flat.min(0).tolist()
            acc["max"] = flat.max(0).tolist()
        self.accessors.append(acc)
        return len(self.accessors) - 1

    def blob(self) -> bytes:
        data = b"".join(self.chunks)
        return data + b"\0" * ((-len(data)) % 4)


def _srgb_to_linear(c: np.ndarray) -> np.ndarray:
    c = np.asarray(c, float) / 255.0
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def _influences(weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(V, J) skinning weights -> joints (V, 8) uint8 and weights (V, 8) float32, the 8
    largest per vertex, renormalised to sum 1."""
    order = np.argsort(-weights, axis=1)[:, :INFLUENCES]
    w = np.take_along_axis(weights, order, axis=1)
    w = w / w.sum(1, keepdims=True)
    return order.astype(np.uint8), w.astype(np.float32)


def _continuous(q: np.ndarray) -> np.ndarray:
    """(F, 4) quaternions with signs flipped so consecutive ones have a positive dot."""
    q = q.copy()
    for f in range(1, len(q)):
        if np.dot(q[f], q[f - 1]) < 0:
            q[f] = -q[f]
    return q


@dataclass
class _Gltf:
    """The glTF document being built: its lists, in the order the indices refer to."""

    buf: _Buffer
    times: int  # accessor of the animation's frame times
    nodes: list[dict] = field(default_factory=list)
    meshes: list[dict] = field(default_factory=list)
    skins: list[dict] = field(default_factory=list)
    materials: list[dict] = field(default_factory=list)
    samplers: list[dict] = field(default_factory=list)
    channels: list[dict] = field(default_factory=list)
    roots: list[int] = field(default_factory=list)

    def animate(self, node: int, path: str, values: np.ndarray, kind: str, interp: str = "LINEAR"):
        out = self.buf.accessor(values.astype(np.float32), FLOAT, kind)
        self.samplers.append({"input": self.times, "output": out, "interpolation": interp})
        self.channels.append(
            {"sampler": len(self.samplers) - 1, "target": {"node": node, "path": path}}
        )


def _add_joint_nodes(g: _Gltf, k: int, skel: TrackSkeleton, quats: np.ndarray) -> list[int]:
    """1. The track node, then its joint nodes, parents before children (the root joint
    under the track node), posed at the first present frame; returns the joint nodes.
    ``quats`` (F, J, 4) x, y, z, w local rotations."""
    J = len(skel.parents)
    track_node = len(g.nodes)
    g.nodes.append({"name": f"track{k}", "children": []})
    joint_nodes = list(range(len(g.nodes), len(g.nodes) + J))
    first = int(np.argmax(skel.present))
    for j in range(J):
        t = skel.root_position[first] if j == 0 else skel.offsets[j]
        g.nodes.append({
            "name": f"track{k}_{skel.names[j]}",
            "translation": [float(v) for v in t],
            "rotation": [float(v) for v in quats[first, j]],
        })  # fmt: skip
    for j in range(1, J):
        g.nodes[joint_nodes[skel.parents[j]]].setdefault("children", []).append(joint_nodes[j])
    g.nodes[track_node]["children"] = [joint_nodes[0]]
    return joint_nodes


def _add_skinned_mesh(
    g: _Gltf,
    k: int,
    skel: TrackSkeleton,
    joint_nodes: list[int],
    rest: tuple[np.ndarray, np.ndarray, int],
    influences: tuple[np.ndarray, np.ndarray],
) -> int:
    """2. The skinned mesh: rest body (``rest``: (V, 3) vertices and normals, the face
    index accessor), inverse bind matrices T(-rest_joint), the track's colour; returns
    its node."""
    verts, normals, indices = rest
    joints8, weights8 = influences
    ibm = np.tile(np.eye(4), (len(joint_nodes), 1, 1))
    ibm[:, :3, 3] = -skel.rest_joints
    buf = g.buf
    g.skins.append({
        "name": f"track{k}_skin",
        "joints": joint_nodes,
        "skeleton": joint_nodes[0],
        "inverseBindMatrices": buf.accessor(
            np.transpose(ibm, (0, 2, 1)).astype(np.float32), FLOAT, "MAT4"
        ),  # column-major
    })  # fmt: skip
    rgb = track_rgb(k)
    g.materials.append({
        "name": f"track{k}",
        "pbrMetallicRoughness": {
            "baseColorFactor": [*_srgb_to_linear(rgb).tolist(), 1.0],
            "metallicFactor": 0.0, "roughnessFactor": 0.8,
        },
        "doubleSided": True,
    })  # fmt: skip
    attributes = {
        "POSITION": buf.accessor(verts.astype(np.float32), FLOAT, "VEC3",
                                 target=ARRAY_BUFFER, minmax=True),
        "NORMAL": buf.accessor(normals.astype(np.float32), FLOAT, "VEC3",
                               target=ARRAY_BUFFER),
        "JOINTS_0": buf.accessor(joints8[:, :4], UBYTE, "VEC4", target=ARRAY_BUFFER),
        "WEIGHTS_0": buf.accessor(weights8[:, :4], FLOAT, "VEC4", target=ARRAY_BUFFER),
        "JOINTS_1": buf.accessor(joints8[:, 4:], UBYTE, "VEC4", target=ARRAY_BUFFER),
        "WEIGHTS_1": buf.accessor(weights8[:, 4:], FLOAT, "VEC4", target=ARRAY_BUFFER),
    }  # fmt: skip
    g.meshes.append({
        "name": f"track{k}_body",
        "primitives": [{"attributes": attributes, "indices": indices,
                        "material": len(g.materials) - 1, "mode": 4}],
    })  # fmt: skip
    mesh_node = len(g.nodes)
    g.nodes.append({"name": f"track{k}_body", "mesh": len(g.meshes) - 1, "skin": len(g.skins) - 1})
    return mesh_node


def _add_animation(
    g: _Gltf,
    k: int,
    skel: TrackSkeleton,
    quats: np.ndarray,
    track_node: int,
    joint_nodes: list[int],
) -> list[str]:
    """3. The animation: root translation, every rotation, the span as a scale; the
    track node's extras. Returns notes on the track's gaps and span."""
    F = len(skel.present)
    g.animate(joint_nodes[0], "translation", skel.root_position, "VEC3")
    for j in range(len(joint_nodes)):
        g.animate(joint_nodes[j], "rotation", _continuous(quats[:, j]), "VEC4")
    frames = np.flatnonzero(skel.present)
    inside = np.zeros(F, bool)
    inside[frames[0] : frames[-1] + 1] = True
    if not inside.all():
        scale = np.repeat(inside[:, None].astype(float), 3, axis=1)
        g.animate(track_node, "scale", scale, "VEC3", "STEP")
    held = np.flatnonzero(inside & ~skel.present)
    g.nodes[track_node]["extras"] = {
        "track": int(k),
        "first_frame": int(frames[0]),
        "last_frame": int(frames[-1]),
        "held_frames": held.tolist(),
    }
    notes = []
    gap = gap_note(skel.present[inside], "the last fitted pose is held")
    if gap:
        notes.append(f"track {k}: {gap} (frames counted from {frames[0]})")
    if not inside.all():
        notes.append(f"track {k}: hidden (scale 0) outside frames {frames[0]}-{frames[-1]}")
    return notes


def _glb_container(doc: dict, blob: bytes) -> bytes:
    """The binary glTF: header, the JSON chunk (space padded), the BIN chunk."""
    doc["buffers"] = [{"byteLength": len(blob)}]
    text = json.dumps(doc, separators=(",", ":")).encode()
    text += b" " * ((-len(text)) % 4)
    total = 12 + 8 + len(text) + 8 + len(blob)
    out = struct.pack("<III", _GLB_MAGIC, 2, total)
    out += struct.pack("<II", len(text), _JSON_CHUNK) + text
    out += struct.pack("<II", len(blob), _BIN_CHUNK) + blob
    return out


def glb_bytes(fit: SmplFit, tracks: list[int], *, fps: float) -> tuple[bytes, list[str]]:
    """The GLB of ``tracks`` of ``fit`` (see the module docstring), and notes."""
    if not fps > 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    model = torch_body_model(fit.model)  # a loaded run's fit holds the numpy arrays
    faces = model.faces.numpy().astype(np.uint32)
    influences = _influences(model.weights.numpy().astype(np.float64))
    buf = _Buffer()
    F = fit.transl.shape[1]
    times = buf.accessor((np.arange(F) / fps).astype(np.float32), FLOAT, "SCALAR", minmax=True)
    g = _Gltf(buf, times)
    indices = buf.accessor(faces.reshape(-1), UINT, "SCALAR", target=ELEMENT_ARRAY_BUFFER)
    notes: list[str] = []
    for k in tracks:
        skel = track_skeleton(fit, k)
        with torch.no_grad():
            rest = model(torch.zeros(1, 72), torch.as_tensor(skel.betas[None], dtype=torch.float32))
        verts = rest.vertices[0].double().numpy()
        normals = trimesh.Trimesh(verts, faces, process=False).vertex_normals
        quats = Rotation.from_matrix(skel.local_rotations.reshape(-1, 3, 3)).as_quat()
        quats = quats.reshape(F, len(skel.parents), 4)  # x, y, z, w: glTF's order
        track_node = len(g.nodes)
        joint_nodes = _add_joint_nodes(g, k, skel, quats)
        mesh_node = _add_skinned_mesh(
            g, k, skel, joint_nodes, (verts, normals, indices), influences
        )
        g.roots += [track_node, mesh_node]
        notes += _add_animation(g, k, skel, quats, track_node, joint_nodes)
    doc = {
        "asset": {"version": "2.0", "generator": "mvviz export (pipeline/exports/gltf.py)"},
        "scene": 0,
        "scenes": [{
            "name": "mvviz",
            "nodes": g.roots,
            "extras": {
                "stage": fit.stage, "fps": float(fps), "frames": int(F),
                "body_model": Path(str(model.source)).name,
                "body_model_sha256": model.fingerprint, "convention": WORLD_NOTE,
            },
        }],
        "nodes": g.nodes,
        "meshes": g.meshes,
        "skins": g.skins,
        "materials": g.materials,
        "animations": [{"name": "motion", "samplers": g.samplers, "channels": g.channels}],
        "accessors": buf.accessors,
        "bufferViews": buf.views,
    }  # fmt: skip
    return _glb_container(doc, buf.blob()), notes


def write_glb(path: str | os.PathLike, fit: SmplFit, tracks: list[int], *, fps: float) -> list[str]:
    """Write ``tracks`` of ``fit`` into one ``.glb``, atomically; returns notes."""
    data, notes = glb_bytes(fit, tracks, fps=fps)
    with atomic_write(Path(path), "wb") as fh:
        fh.write(data)
    return notes


def read_glb(path_or_bytes: str | os.PathLike | bytes) -> tuple[dict, bytes]:
    """(glTF JSON, binary chunk) of a GLB: for tests and checks."""
    data = path_or_bytes if isinstance(path_or_bytes, bytes) else Path(path_or_bytes).read_bytes()
    magic, version, total = struct.unpack_from("<III", data, 0)
    if magic != _GLB_MAGIC or version != 2 or total != len(data):
        raise ValueError("not a glTF 2 binary file")
    jlen, jtype = struct.unpack_from("<II", data, 12)
    doc = json.loads(data[20 : 20 + jlen])
    blen, btype = struct.unpack_from("<II", data, 20 + jlen)
    if jtype != _JSON_CHUNK or btype != _BIN_CHUNK:
        raise ValueError("unexpected GLB chunk types")
    return doc, data[28 + jlen : 28 + jlen + blen]


def accessor_array(doc: dict, blob: bytes, index: int) -> np.ndarray:
    """The array of accessor ``index`` (tightly packed views, as :func:`glb_bytes` writes)."""
    acc = doc["accessors"][index]
    view = doc["bufferViews"][acc["bufferView"]]
    dtype = {FLOAT: np.float32, UINT: np.uint32, UBYTE: np.uint8}[acc["componentType"]]
    width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4, "MAT4": 16}[acc["type"]]
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    a = np.frombuffer(blob, dtype, acc["count"] * width, start)
    return a.reshape(acc["count"], width) if width > 1 else a
