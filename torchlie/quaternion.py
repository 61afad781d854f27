"""Quaternions stored as ``(w, x, y, z)`` — scalar first — in tensors of shape ``(*, 4)``.

Every function here reads and writes the ``(w, x, y, z)`` order (scipy and ROS use ``(x, y, z, w)``:
convert with :func:`to_xyzw` / :func:`from_xyzw`). Unit quaternions represent rotations, ``q`` and
``−q`` the same one. Functions that only depend on the rotation (``to_matrix``, ``act``, ``log``,
``to_axis_angle``) accept any non-zero quaternion and use the rotation of ``q/|q|``; ``multiply``,
``conjugate``, ``inverse`` and ``normalize`` are plain quaternion algebra.

The exponential follows the rotation-vector convention of Solà et al., *A micro Lie theory* (Ex. 6):
``exp(ω) = (cos(|ω|/2), sin(|ω|/2) ω/|ω|)`` is the rotation by ``|ω|`` about ``ω/|ω|`` (the quaternion
exponential of the pure quaternion ``ω/2``), so ``to_matrix(exp(ω))`` equals the SO(3) exponential of ``ω``;
``log`` is its principal inverse (``|ω| ≤ π``, same result for ``q`` and ``−q``). Removable singularities at
``ω = 0`` use Taylor series behind the safe-``where`` pattern (``log`` needs none, see its docstring), so
values and gradients are exact and finite there. Batch dims are arbitrary and broadcast in binary
operations; dtype and device follow the inputs.
"""

from __future__ import annotations

import math

import torch

from torchlie._batch import (
    _plain,
    batch_shape,
    broadcast_leading,
    check_same_device,
    check_tensor,
    float_dtype,
    horner,
    rng_device,
    scalar_param,
    series_switch,
)

__all__ = [
    "identity",
    "random",
    "multiply",
    "conjugate",
    "inverse",
    "normalize",
    "canonicalize",
    "to_matrix",
    "from_matrix",
    "exp",
    "log",
    "act",
    "slerp",
    "from_axis_angle",
    "to_axis_angle",
    "to_xyzw",
    "from_xyzw",
]

# Taylor coefficients in θ² of cos(θ/2) and sin(θ/2)/θ.
_COS_HALF = tuple((-1) ** k / (4**k * math.factorial(2 * k)) for k in range(6))
_SIN_HALF_OVER = tuple(0.5 * (-1) ** k / (4**k * math.factorial(2 * k + 1)) for k in range(6))
_TINY: dict = {}  # dtype -> √(smallest normal number): log's floor for |v|


def _cross(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    a0, a1, a2 = a.unbind(-1)
    b0, b1, b2 = b.unbind(-1)
    return torch.stack((a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0), dim=-1)


def identity(*batch: int, dtype: torch.dtype | None = None, device=None) -> torch.Tensor:
    """Identity quaternion ``(w, x, y, z) = (1, 0, 0, 0)`` of shape ``(*batch, 4)``."""
    shape = batch_shape(batch, "quaternion.identity")
    dtype = float_dtype(dtype, "quaternion.identity")
    q = torch.zeros(*shape, 4, dtype=dtype, device=device)
    q[..., 0] = 1
    return q


def random(*batch: int, generator: torch.Generator | None = None, dtype: torch.dtype | None = None,
           device=None) -> torch.Tensor:
    """Unit quaternions ``(w, x, y, z)`` ``(*batch, 4)`` uniform on S³ (so Haar-uniform rotations).

    Shoemake's subgroup algorithm (*Uniform random rotations*, Graphics Gems III, 1992) on three
    uniforms from ``generator``; no sign canonicalisation (``w`` takes both signs). Samples are made on
    ``device``, or on the generator's device when ``device`` is not given.
    """
    shape = batch_shape(batch, "quaternion.random")
    dtype = float_dtype(dtype, "quaternion.random")
    u = torch.rand(*shape, 3, generator=generator, dtype=dtype, device=rng_device(generator, device))
    u1, u2, u3 = u.unbind(-1)
    r1, r2 = torch.sqrt(1 - u1), torch.sqrt(u1)
    a, b = 2 * math.pi * u2, 2 * math.pi * u3
    return torch.stack((r1 * torch.sin(a), r1 * torch.cos(a), r2 * torch.sin(b), r2 * torch.cos(b)), dim=-1)


def multiply(p: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """Hamilton product ``p ⊗ q`` of ``(w, x, y, z)`` quaternions ``(*, 4)``, broadcasting batch dims.

    For unit quaternions ``to_matrix(multiply(p, q)) = to_matrix(p) @ to_matrix(q)``.
    """
    p = check_tensor(p, (4,), "p", "quaternion.multiply")
    q = check_tensor(q, (4,), "q", "quaternion.multiply")
    check_same_device("quaternion.multiply", p=p, q=q)
    p, q = broadcast_leading(p, 1, q, 1, "quaternion.multiply", ("p", "q"))
    pw, px, py, pz = p.unbind(-1)
    qw, qx, qy, qz = q.unbind(-1)
    return torch.stack((
        pw * qw - px * qx - py * qy - pz * qz,
        pw * qx + px * qw + py * qz - pz * qy,
        pw * qy - px * qz + py * qw + pz * qx,
        pw * qz + px * qy - py * qx + pz * qw,
    ), dim=-1)


def conjugate(q: torch.Tensor) -> torch.Tensor:
    """Conjugate ``(w, −x, −y, −z)`` of a ``(w, x, y, z)`` quaternion ``(*, 4)``."""
    q = check_tensor(q, (4,), "q", "quaternion.conjugate")
    return torch.cat((q[..., :1], -q[..., 1:]), dim=-1)


def inverse(q: torch.Tensor) -> torch.Tensor:
    """Multiplicative inverse ``conj(q)/|q|²`` of a non-zero ``(w, x, y, z)`` quaternion ``(*, 4)``."""
    q = check_tensor(q, (4,), "q", "quaternion.inverse")
    return conjugate(q) / (q * q).sum(-1, keepdim=True)


def normalize(q: torch.Tensor) -> torch.Tensor:
    """``q/|q|`` for a non-zero ``(w, x, y, z)`` quaternion ``(*, 4)`` (a zero quaternion gives NaN)."""
    q = check_tensor(q, (4,), "q", "quaternion.normalize")
    return q / torch.sqrt((q * q).sum(-1, keepdim=True))


def canonicalize(q: torch.Tensor) -> torch.Tensor:
    """The representative of ``±q`` with ``w ≥ 0`` (``(w, x, y, z)`` order, shape ``(*, 4)``)."""
    q = check_tensor(q, (4,), "q", "quaternion.canonicalize")
    return torch.where(q[..., :1] < 0, -q, q)


def to_matrix(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrix ``(*, 3, 3)`` of a ``(w, x, y, z)`` quaternion ``(*, 4)``.

    Uses ``s = 2/|q|²``, so any non-zero ``q`` gives the rotation of ``q/|q|`` (exact for unit ``q``).
    """
    q = check_tensor(q, (4,), "q", "quaternion.to_matrix")
    w, x, y, z = q.unbind(-1)
    s = 2 / (q * q).sum(-1)
    xx, yy, zz = s * x * x, s * y * y, s * z * z
    xy, xz, yz = s * x * y, s * x * z, s * y * z
    wx, wy, wz = s * w * x, s * w * y, s * w * z
    return torch.stack((
        1 - yy - zz, xy - wz, xz + wy,
        xy + wz, 1 - xx - zz, yz - wx,
        xz - wy, yz + wx, 1 - xx - yy,
    ), dim=-1).unflatten(-1, (3, 3))


def from_matrix(R: torch.Tensor) -> torch.Tensor:
    """Unit quaternion ``(w, x, y, z)`` ``(*, 4)`` with ``w ≥ 0`` of a rotation matrix ``(*, 3, 3)``.

    Shepperd's method (*Quaternion from rotation matrix*, J. Guidance and Control 1(3), 1978), batched:
    the symmetric matrix ``K = 4 q qᵀ`` is built linearly from ``R``; its row with the largest diagonal
    entry (``4 q_k² ≥ 1``) is selected per element with ``gather`` and normalised, which never divides by
    less than 2, so the result is accurate and its gradient finite for every rotation (including angle π).
    For a slightly non-orthogonal ``R`` the result is still a unit quaternion of a nearby rotation.
    At angle exactly π (``w = 0``) the sign choice makes the map — and so its derivative — one-sided.
    """
    R = check_tensor(R, (3, 3), "R", "quaternion.from_matrix")
    r00, r01, r02 = R[..., 0, 0], R[..., 0, 1], R[..., 0, 2]
    r10, r11, r12 = R[..., 1, 0], R[..., 1, 1], R[..., 1, 2]
    r20, r21, r22 = R[..., 2, 0], R[..., 2, 1], R[..., 2, 2]
    dw = 1 + r00 + r11 + r22
    dx = 1 + r00 - r11 - r22
    dy = 1 - r00 + r11 - r22
    dz = 1 - r00 - r11 + r22
    wx, wy, wz = r21 - r12, r02 - r20, r10 - r01
    xy, xz, yz = r01 + r10, r02 + r20, r12 + r21
    K = torch.stack((
        dw, wx, wy, wz,
        wx, dx, xy, xz,
        wy, xy, dy, yz,
        wz, xz, yz, dz,
    ), dim=-1).unflatten(-1, (4, 4))
    k = torch.stack((dw, dx, dy, dz), dim=-1).argmax(dim=-1, keepdim=True)
    row = K.gather(-2, k.unsqueeze(-1).expand(*k.shape[:-1], 1, 4)).squeeze(-2)
    q = row / torch.sqrt((row * row).sum(-1, keepdim=True))
    return torch.where(q[..., :1] < 0, -q, q)


def exp(omega: torch.Tensor) -> torch.Tensor:
    """Unit quaternion ``(w, x, y, z)`` ``(*, 4)`` of the rotation vector ``omega`` ``(*, 3)``.

    ``(cos(θ/2), sin(θ/2) ω/θ)`` with ``θ = |ω|``: the rotation by θ about ``ω/θ``.
    """
    omega = check_tensor(omega, (3,), "omega", "quaternion.exp")
    t2 = (omega * omega).sum(-1)
    sw = series_switch(omega.dtype) ** 2
    # safe-where with 0/1 lerp weights (exact selection, cheaper than torch.where on CPU): the closed
    # forms see θ² + 1 where the series is taken, the series θ² clamped to the switch elsewhere
    small = (t2 < sw).to(t2.dtype)
    th = torch.sqrt(t2 + small)
    x = torch.clamp(t2, max=sw)
    c = torch.lerp(torch.cos(0.5 * th), horner(x, _COS_HALF), small)
    s = torch.lerp(torch.sin(0.5 * th) / th, horner(x, _SIN_HALF_OVER), small)
    if _plain(omega):  # written in place: no concatenation
        out = omega.new_empty(*omega.shape[:-1], 4)
        out[..., 0] = c
        torch.mul(omega, s.unsqueeze(-1), out=out[..., 1:])
        return out
    return torch.cat((c.unsqueeze(-1), s.unsqueeze(-1) * omega), dim=-1)


def log(q: torch.Tensor) -> torch.Tensor:
    """Principal rotation vector ``(*, 3)`` (angle in ``[0, π]``) of a ``(w, x, y, z)`` quaternion ``(*, 4)``.

    ``q`` and ``−q`` (and any positive multiple of either) give the same result:
    ``ω = ±2 atan2(|v|, |w|) v/|v|`` with the sign of ``w``, accurate to the dtype's resolution at every
    angle (at ``w = ±0``, angle π, the zero's sign picks the branch and the derivative is that branch's).
    No series is needed at small angles: ``atan2(n, |w|)/n`` and its autograd derivative are accurate for
    every ``n = |v| > 0`` (to the dtype's absolute resolution), so ``n`` is only kept from 0 — at
    ``√tiny``, where ``atan2(n, |w|)/n = 1/|w|`` to far below ε — which keeps values and gradients finite
    and exact at ``ω = 0``.
    """
    q = check_tensor(q, (4,), "q", "quaternion.log")
    w, v = q[..., 0], q[..., 1:]
    floor = _TINY.get(q.dtype)
    if floor is None:
        floor = _TINY[q.dtype] = torch.finfo(q.dtype).tiny ** 0.5
    n = torch.linalg.vector_norm(v, dim=-1).clamp_min(floor)
    s = torch.copysign(w.new_ones(()), w)  # ±1, +1 at w = +0: the branch returned at angle π, and
    f = torch.atan2(n, w * s).div_(n).mul_(2).mul_(s)  # its derivative (|w|'s would vanish at w = 0)
    return v * f.unsqueeze(-1)


def act(q: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """Rotate points ``p`` ``(*, 3)`` by the ``(w, x, y, z)`` quaternion ``q`` ``(*, 4)`` (``q p q⁻¹``).

    Evaluated as ``p + w t + v × t`` with ``t = (2/|q|²) v × p``; batch dims broadcast.
    """
    q = check_tensor(q, (4,), "q", "quaternion.act")
    p = check_tensor(p, (3,), "p", "quaternion.act")
    check_same_device("quaternion.act", q=q, p=p)
    q, p = broadcast_leading(q, 1, p, 1, "quaternion.act", ("q", "p"))
    w, v = q[..., :1], q[..., 1:]
    t = (2 / (q * q).sum(-1, keepdim=True)) * _cross(v, p)
    return p + w * t + _cross(v, t)


def slerp(p: torch.Tensor, q: torch.Tensor, t) -> torch.Tensor:
    """Shortest-path spherical interpolation between unit ``(w, x, y, z)`` quaternions ``(*, 4)``.

    ``p ⊗ exp(t · log(p* ⊗ q))``: ``log`` picks the sign of ``q`` nearer to ``p``, so the path turns by at
    most π, and its small-angle series keeps values and gradients exact when ``p ≈ q``. ``t`` is a float or
    a tensor of ``p``'s dtype and device, of shape ``(*T)``, broadcasting with the batch dims; ``t = 0``
    gives ``p`` and ``t = 1`` gives ``±q`` (the sign nearer to ``p``).
    """
    p = check_tensor(p, (4,), "p", "quaternion.slerp")
    q = check_tensor(q, (4,), "q", "quaternion.slerp")
    check_same_device("quaternion.slerp", p=p, q=q)
    t = scalar_param(t, p, "quaternion.slerp", "t", "p")
    d = log(multiply(conjugate(p), q))
    return multiply(p, exp(d * t.unsqueeze(-1)))


def from_axis_angle(axis: torch.Tensor, angle) -> torch.Tensor:
    """Unit quaternion ``(w, x, y, z)`` ``(*, 4)`` of the rotation by ``angle`` about ``axis``.

    ``axis`` ``(*, 3)`` is any non-zero vector (normalised here); ``angle`` is a float or a tensor of shape
    ``(*B,)`` in radians, broadcasting with the batch dims of ``axis``.
    """
    axis = check_tensor(axis, (3,), "axis", "quaternion.from_axis_angle")
    angle = scalar_param(angle, axis, "quaternion.from_axis_angle", "angle", "axis")
    u = axis / torch.sqrt((axis * axis).sum(-1, keepdim=True))
    half = 0.5 * angle.unsqueeze(-1)
    u, half = broadcast_leading(u, 1, half, 1, "quaternion.from_axis_angle", ("axis", "angle"))
    return torch.cat((torch.cos(half), torch.sin(half) * u), dim=-1)


def to_axis_angle(q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Unit axis ``(*, 3)`` and angle ``(*,)`` in ``[0, π]`` of a ``(w, x, y, z)`` quaternion ``(*, 4)``.

    ``q`` and ``−q`` give the same pair. For the identity rotation the axis is ``(1, 0, 0)`` by convention
    (its gradient there is zero).
    """
    q = check_tensor(q, (4,), "q", "quaternion.to_axis_angle")
    q = torch.where(q[..., :1] < 0, -q, q)
    w, v = q[..., 0], q[..., 1:]
    n2 = (v * v).sum(-1)
    zero = n2 == 0
    n = torch.sqrt(torch.where(zero, torch.ones_like(n2), n2))
    angle = torch.where(zero, torch.zeros_like(n2), 2 * torch.atan2(n, w))
    ex = torch.cat((torch.ones_like(v[..., :1]), torch.zeros_like(v[..., 1:])), dim=-1)
    axis = torch.where(zero.unsqueeze(-1), ex, v / n.unsqueeze(-1))
    return axis, angle


def to_xyzw(q: torch.Tensor) -> torch.Tensor:
    """Reorder a ``(w, x, y, z)`` quaternion ``(*, 4)`` to scipy/ROS order ``(x, y, z, w)``."""
    q = check_tensor(q, (4,), "q", "quaternion.to_xyzw")
    return torch.cat((q[..., 1:], q[..., :1]), dim=-1)


def from_xyzw(q: torch.Tensor) -> torch.Tensor:
    """Reorder a scipy/ROS ``(x, y, z, w)`` quaternion ``(*, 4)`` to this module's ``(w, x, y, z)``."""
    q = check_tensor(q, (4,), "q", "quaternion.from_xyzw")
    return torch.cat((q[..., 3:], q[..., :3]), dim=-1)
