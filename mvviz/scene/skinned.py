"""Posing viser skinned meshes: every bone of a mesh in one vectorised pass.

viser 1.1 poses a skinned mesh bone by bone: ``mesh.bones[i].wxyz = q`` casts the value,
compares it with ``np.allclose`` and queues one message. That is ~70 µs a call here, and the
viewer makes 2 x 24 calls per body per frame change (8 bodies on the sample scene:
~27 ms, more than the rest of a frame change together). viser has no batched bone
message, so :class:`BonePoser` does the same thing in bulk: one array comparison finds
the bones that moved, and only those get their (unchanged) viser messages, queued the
way the setters queue them. The handles' own pose arrays are kept in step, so the public
setters and ``bone.wxyz`` reads stay valid alongside.

Values are rounded before they are compared and sent: quaternion components to
:data:`WXYZ_DECIMALS` places (< 0.01 degrees), positions (metres) to
:data:`POSITION_DECIMALS` (0.5 mm at most, well below the fits' ~10 mm errors). Jitter
below that is not sent again, and the rounded floats compress ~25 % better on the wire.
This is display only: the results keep full precision.

It uses viser internals (``bone._impl``, ``SceneApi._queue_scene_message``, the bone
message classes). :func:`fast_path_available` checks they are there; when they are not
(another viser), :class:`BonePoser` falls back to the public setters, which gives the
same messages more slowly. ``tests/mvviz/scene/test_skinned.py`` checks both paths send the
same messages on the installed viser.
"""

from __future__ import annotations

import numpy as np
import viser

try:  # viser internals (see the module docstring); absent: the public setters are used
    from viser._messages import SetBoneOrientationMessage, SetBonePositionMessage
except ImportError:  # pragma: no cover - another viser
    SetBoneOrientationMessage = SetBonePositionMessage = None

WXYZ_DECIMALS = 4
POSITION_DECIMALS = 3


def fast_path_available(mesh: viser.MeshSkinnedHandle) -> bool:
    """Whether ``mesh``'s bones can be posed through :class:`BonePoser`'s bulk path."""
    if SetBoneOrientationMessage is None or not mesh.bones:
        return False
    impl = getattr(mesh.bones[0], "_impl", None)
    api = getattr(getattr(impl, "mesh_impl", None), "api", None)
    return (
        hasattr(api, "_queue_scene_message")
        and isinstance(getattr(impl, "wxyz", None), np.ndarray)
        and isinstance(getattr(impl, "position", None), np.ndarray)
    )


class BonePoser:
    """Poses one skinned mesh: :meth:`pose` sends the bones that moved.

    Use from one thread at a time (the viewer's render thread)."""

    def __init__(self, mesh: viser.MeshSkinnedHandle, *, fast: bool | None = None) -> None:
        self.mesh = mesh
        self.fast = fast_path_available(mesh) if fast is None else fast
        bones = mesh.bones
        # What the client has: the poses given at creation (the bind pose), in the
        # handles' own arrays.
        self._wxyz = np.array([b.wxyz for b in bones], np.float64).reshape(-1, 4)
        self._position = np.array([b.position for b in bones], np.float64).reshape(-1, 3)
        if self.fast:
            self._impls = [b._impl for b in bones]
            self._queue = self._impls[0].mesh_impl.api._queue_scene_message if bones else None

    def pose(self, wxyz: np.ndarray, position: np.ndarray) -> int:
        """Set bone orientations ``wxyz`` (B, 4) and positions ``position`` (B, 3), in the
        mesh's frame. Returns the number of bone messages queued."""
        B = len(self.mesh.bones)
        q = np.round(np.asarray(wxyz, np.float64).reshape(B, 4), WXYZ_DECIMALS)
        p = np.round(np.asarray(position, np.float64).reshape(B, 3), POSITION_DECIMALS)
        if not (np.isfinite(q).all() and np.isfinite(p).all()):
            raise ValueError(f"{self.mesh.name}: bone poses must be finite")
        moved_q = np.flatnonzero((q != self._wxyz).any(1))
        moved_p = np.flatnonzero((p != self._position).any(1))
        if self.fast:
            self._send_fast(q, p, moved_q, moved_p)
        else:
            bones = self.mesh.bones
            for i in moved_q:
                bones[i].wxyz = q[i]
            for i in moved_p:
                bones[i].position = p[i]
        self._wxyz[moved_q] = q[moved_q]
        self._position[moved_p] = p[moved_p]
        return len(moved_q) + len(moved_p)

    def _send_fast(self, q, p, moved_q, moved_p) -> None:
        if self.mesh._impl.removed:
            # As the public setters: a bone message for a removed mesh would linger
            # under its name and corrupt a re-added mesh of that name.
            raise RuntimeError(f"{self.mesh.name}: cannot pose a removed skinned mesh")
        name, queue, impls = self.mesh.name, self._queue, self._impls
        for i, values in zip(moved_q.tolist(), q[moved_q].tolist(), strict=True):
            impls[i].wxyz[:] = values
            queue(SetBoneOrientationMessage(name, i, tuple(values)))
        for i, values in zip(moved_p.tolist(), p[moved_p].tolist(), strict=True):
            impls[i].position[:] = values
            queue(SetBonePositionMessage(name, i, tuple(values)))
