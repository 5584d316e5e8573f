"""Joint limits as a differentiable penalty: :mod:`pipeline.body.pose_limits` in torch.

:func:`pipeline.body.pose_limits.swing_twist` splits each local rotation into swing and twist
in the joint's anatomical frame; :func:`swing_twist` here computes the same angles from
rotation matrices in torch (a test checks them against the numpy reference), so the
SMPL fit can penalise how far a joint is outside its box (:func:`limit_penalty`)
instead of counting violations afterwards. Radians.
"""

from __future__ import annotations

import torch

from pipeline.body import pose_limits

_AXES = torch.as_tensor(pose_limits.AXES, dtype=torch.float32)  # (24, 3, 3)
_LOW = torch.as_tensor(pose_limits.LOW.clip(-10, 10), dtype=torch.float32)  # (24, 3)
_HIGH = torch.as_tensor(pose_limits.HIGH.clip(-10, 10), dtype=torch.float32)
_MIRROR = torch.as_tensor(pose_limits.MIRROR)
_LIMITED = torch.as_tensor(pose_limits.LIMITED)
_FLIP = torch.tensor([1.0, -1.0, -1.0])
_LIMITED_JOINTS = torch.nonzero(_LIMITED)[:, 0]  # all but the root
# Per limited joint: the mirror (right onto left) then the anatomical frame, one matrix.
_FRAME = (_AXES * torch.where(_MIRROR[:, None], _FLIP, 1.0)[:, None, :])[_LIMITED_JOINTS]
# Per axis (swing_a, swing_b, twist), the limited joints' bounds as (L, 1) columns
_HIGH_ROWS = tuple(_HIGH[_LIMITED_JOINTS].t()[:, :, None])
_LOW_ROWS = tuple(_LOW[_LIMITED_JOINTS].t()[:, :, None])


def matrix_to_quaternion(R: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotations -> (..., 4) unit quaternions (w, x, y, z), w >= 0.

    The branch with the largest denominator (Shepperd's method), so the gradient is finite
    at every rotation."""
    m00, m11, m22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    q_abs = torch.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22,
                         1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)  # fmt: skip
    q_abs = q_abs.clamp_min(1e-8).sqrt()  # 2|q_i|
    d21, d02, d10 = (
        R[..., 2, 1] - R[..., 1, 2],
        R[..., 0, 2] - R[..., 2, 0],
        R[..., 1, 0] - R[..., 0, 1],
    )
    s21, s02, s10 = (
        R[..., 2, 1] + R[..., 1, 2],
        R[..., 0, 2] + R[..., 2, 0],
        R[..., 1, 0] + R[..., 0, 1],
    )
    cand = torch.stack(
        [
            torch.stack([q_abs[..., 0] ** 2, d21, d02, d10], -1),
            torch.stack([d21, q_abs[..., 1] ** 2, s10, s02], -1),
            torch.stack([d02, s10, q_abs[..., 2] ** 2, s21], -1),
            torch.stack([d10, s02, s21, q_abs[..., 3] ** 2], -1),
        ],
        -2,
    ) / (2.0 * q_abs[..., None])  # (..., 4 candidates, 4)
    best = q_abs.argmax(-1)
    q = torch.gather(cand, -2, best[..., None, None].expand(best.shape + (1, 4)))[..., 0, :]
    q = q / q.norm(dim=-1, keepdim=True)
    return torch.where(q[..., :1] < 0, -q, q)


def small_angle_quaternion(R: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotations -> (..., 4) unit quaternions (w, x, y, z), w >= 0: the
    quaternion of :func:`matrix_to_quaternion`, by its w branch alone wherever that is the
    well-conditioned one (angle <= 120 degrees: 4 w^2 = 1 + trace >= 1, so the division
    is by at least 2), Shepperd's method for the other rotations only. Joint rotations of
    a fit are nearly all below 120 degrees (27 of 22,471 at the start of the sample's
    fit). With the single unbind and the einsum of :func:`swing_twist`, the limit penalty
    of 977 x 24 rotations, forward and backward, took 5.5 ms CPU instead of 15.8."""
    # one unbind, not nine selects: each select's backward fills a zero tensor of R's size
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = R.flatten(-2).unbind(-1)
    tr1 = 1.0 + m00 + m11 + m22
    w = 0.5 * tr1.clamp_min(1.0).sqrt()
    inv = 0.25 / w
    # unit already for an orthonormal R (the fit's Gram-Schmidt rotations): not normalised
    q = torch.stack([w, (m21 - m12) * inv, (m02 - m20) * inv, (m10 - m01) * inv], -1)
    far = torch.nonzero((tr1 < 1.0).reshape(-1))[:, 0]
    if len(far) == 0:
        return q
    flat = q.reshape(-1, 4).index_put((far,), matrix_to_quaternion(R.reshape(-1, 3, 3)[far]))
    return flat.reshape(q.shape)


def swing_twist(rotmats: torch.Tensor) -> torch.Tensor:
    """(N, 24, 3, 3) local rotations -> (N, 24, 3) (swing_a, swing_b, twist) radians in
    each joint's anatomical frame (right joints mirrored onto the left), as
    :func:`pipeline.body.pose_limits.swing_twist`; unlimited joints (the root) give 0."""
    out = torch.stack(swing_twist_rows(rotmats), -1).permute(1, 0, 2)  # (N, L, 3)
    full = rotmats.new_zeros(rotmats.shape[:-2] + (3,))
    return full.index_copy(1, _LIMITED_JOINTS, out)


def swing_twist_rows(rotmats: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(N, 24, 3, 3) -> swing_a, swing_b, twist, each (L, N) over the limited joints
    (``_LIMITED_JOINTS``, all but the root), radians: :func:`swing_twist` component-major.

    Every step is an elementwise operation on contiguous (L, N) rows. On (N, L) slices of
    (N, L, 4) and (N, L, 3) arrays (stride 3 or 4), each ran unvectorised, and the
    backward of every slice, stack and unbind moved whole arrays: the fit's limit penalty
    of 4,885 x 24 rotations, forward and backward, took ~29 ms, 3/10 of an iteration."""
    lim = _LIMITED_JOINTS
    n = rotmats.shape[0]
    c = rotmats.permute(2, 3, 1, 0)[:, :, lim].reshape(9, len(lim), n)  # row-major entries
    w, vx, vy, vz = _quaternion_rows(c)
    # the vector part in the joint's frame (mirror, then anatomical axes), per joint
    F = _FRAME[..., None]  # (L, 3, 3, 1)
    x = F[:, 0, 0] * vx + F[:, 0, 1] * vy + F[:, 0, 2] * vz
    y = F[:, 1, 0] * vx + F[:, 1, 1] * vy + F[:, 1, 2] * vz
    z = F[:, 2, 0] * vx + F[:, 2, 1] * vy + F[:, 2, 2] * vz
    twist = 2.0 * torch.atan2(z, w)
    ct, st = torch.cos(0.5 * twist), torch.sin(0.5 * twist)
    sw, sx, sy = ct * w + st * z, ct * x - st * y, ct * y + st * x
    sign = torch.where(sw < 0, -1.0, 1.0)
    sw, sx, sy = sw * sign, sx * sign, sy * sign
    vnorm = (sx * sx + sy * sy + 1e-12).sqrt()
    k = 2.0 * torch.atan2(vnorm, sw) / vnorm
    return k * sx, k * sy, twist


def _quaternion_rows(c: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """(9, ...) row-major rotation entries -> w, x, y, z (...) of
    :func:`small_angle_quaternion`: the w branch, Shepperd's method where the rotation
    is beyond 120 degrees."""
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = c.unbind(0)
    tr1 = 1.0 + m00 + m11 + m22
    w = 0.5 * tr1.clamp_min(1.0).sqrt()
    inv = 0.25 / w
    q = [w, (m21 - m12) * inv, (m02 - m20) * inv, (m10 - m01) * inv]
    far = torch.nonzero((tr1 < 1.0).reshape(-1))[:, 0]
    if len(far) == 0:
        return tuple(q)
    exact = matrix_to_quaternion(c.reshape(9, -1)[:, far].t().reshape(-1, 3, 3))  # (m, 4)
    return tuple(qi.reshape(-1).index_put((far,), e).reshape(qi.shape)
                 for qi, e in zip(q, exact.unbind(1), strict=True))  # fmt: skip


def limit_excess(rotmats: torch.Tensor, *, margin_deg: float = 0.0) -> torch.Tensor:
    """(N, 24, 3, 3) -> (N, 24, 3) radians outside :data:`pipeline.body.pose_limits.LIMITS`
    (per swing/twist axis, 0 inside the box shrunk by ``margin_deg``; 0 for the root)."""
    ang = swing_twist(rotmats)
    m = margin_deg * torch.pi / 180.0
    over = torch.relu(ang - (_HIGH - m)) + torch.relu((_LOW + m) - ang)
    return torch.where(_LIMITED[:, None], over, torch.zeros_like(over))


def limit_penalty(rotmats: torch.Tensor, *, margin_deg: float = 0.0) -> torch.Tensor:
    """(N, 24, 3, 3) -> (N,) sum over joints of the squared excess (radians^2): the sum of
    :func:`limit_excess` squared, over :func:`swing_twist_rows` (no (N, 24, 3) array)."""
    m = margin_deg * torch.pi / 180.0
    total = rotmats.new_zeros(rotmats.shape[0])
    for ang, high, low in zip(swing_twist_rows(rotmats), _HIGH_ROWS, _LOW_ROWS, strict=True):
        over = torch.relu(ang - (high - m)) + torch.relu((low + m) - ang)  # (L, N)
        total = total + (over * over).sum(0)
    return total
