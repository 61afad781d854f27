"""SE(2): planar rigid motions as ``(*, 3, 3)`` homogeneous matrices, tangent ``x = [vx, vy, θ]`` ``(*, 3)``.

The functional contract (shapes, broadcasting, dtype/device, Jacobian conventions) is the one in
:mod:`torchlie`'s docstring; formulas are from Solà, Deray, Atchuthan, *A micro Lie theory for state
estimation in robotics* (2018), Example 7 and Appendix C (with ρ = ``[vx, vy]``):

- ``exp(x) = [[R(θ), V(θ) ρ], [0, 1]]`` with ``V = [[a, −b], [b, a]]``, ``a = sin θ/θ``,
  ``b = (1 − cos θ)/θ``;
- ``log`` is principal (θ ∈ (−π, π], as :func:`torchlie.so2.log`) and ``ρ = V⁻¹ t`` with
  ``V⁻¹ = [[α, β], [−β, α]]``, ``α = (θ/2) cot(θ/2)``, ``β = θ/2``;
- ``Ad_X = [[R, [t_y, −t_x]ᵀ], [0, 1]]`` and ``ad_x = [[0, −θ, vy], [θ, 0, −vx], [0, 0, 0]]``;
- ``J_l(x) = [[V, q], [0, 1]]`` with ``q = [e vx + g vy, −g vx + e vy]``, ``e = (θ − sin θ)/θ²``,
  ``g = (1 − cos θ)/θ²`` (Solà Eq. 164); ``J_r(x) = J_l(−x)``; ``J_l⁻¹ = [[V⁻¹, −V⁻¹ q], [0, 1]]``.

Every coefficient is written without cancellation (``1 − cos θ = 2 sin²(θ/2)``, ``α = cos(θ/2)/sinc(θ/2)``)
and the two with a removable singularity, ``sinc`` and ``(1 − sinc θ)/θ²``, switch to their Taylor series
near 0 with the safe-``where`` pattern, so values and gradients are exact and finite at ``θ = 0``.

``random`` draws θ uniformly in ``[−π, π)`` and the translation from a **standard normal** (SE(2) is not
compact and has no uniform distribution).
"""

from __future__ import annotations

import math

import torch

from torchlie import so2
from torchlie._batch import (
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
    "exp",
    "log",
    "hat",
    "vee",
    "compose",
    "inverse",
    "act",
    "adjoint",
    "ad",
    "left_jacobian",
    "left_jacobian_inv",
    "right_jacobian",
    "right_jacobian_inv",
    "identity",
    "random",
    "interpolate",
]

# Taylor coefficients (in θ²) of sinc θ = Σ (−1)^k θ^{2k} / (2k+1)! and of
# (1 − sinc θ)/θ² = (θ − sin θ)/θ³ = Σ (−1)^k θ^{2k} / (2k+3)!.
_SINC = tuple((-1) ** k / math.factorial(2 * k + 1) for k in range(6))
_SINC_DEFECT = tuple((-1) ** k / math.factorial(2 * k + 3) for k in range(10))
# The defect's closed form loses ~eps/θ² to cancellation, so its series (exact to 1e-19 at |θ| = 1)
# is used on |θ| < 1 in every dtype.
_DEFECT_TAU = 1.0


def _sinc(th: torch.Tensor) -> torch.Tensor:
    """sin θ / θ with exact value and gradient at 0."""
    small = th.abs() < series_switch(th.dtype)
    safe = torch.where(small, torch.ones_like(th), th)
    return torch.where(small, horner(th * th, _SINC), torch.sin(safe) / safe)


def _sinc_defect(th: torch.Tensor) -> torch.Tensor:
    """(1 − sin θ/θ)/θ² = (θ − sin θ)/θ³, exact near 0 (no cancellation)."""
    small = th.abs() < _DEFECT_TAU
    safe = torch.where(small, torch.ones_like(th), th)
    return torch.where(small, horner(th * th, _SINC_DEFECT), (1 - torch.sin(safe) / safe) / (safe * safe))


def _coeffs(th: torch.Tensor):
    """a = sin θ/θ, b = (1 − cos θ)/θ, g = (1 − cos θ)/θ², e = (θ − sin θ)/θ²."""
    a = _sinc(th)
    sh = _sinc(0.5 * th)
    g = 0.5 * sh * sh
    return a, th * g, g, th * _sinc_defect(th)


def _mat3(*entries: torch.Tensor) -> torch.Tensor:
    return torch.stack(entries, dim=-1).unflatten(-1, (3, 3))


def exp(x: torch.Tensor) -> torch.Tensor:
    """Homogeneous matrix ``(*, 3, 3)`` of ``x = [vx, vy, θ]`` ``(*, 3)``."""
    x = check_tensor(x, (3,), "x", "se2.exp")
    vx, vy, th = x.unbind(-1)
    a = _sinc(th)
    sh = _sinc(0.5 * th)
    b = 0.5 * th * sh * sh
    c, s = torch.cos(th), torch.sin(th)
    z, o = torch.zeros_like(th), torch.ones_like(th)
    return _mat3(c, -s, a * vx - b * vy, s, c, b * vx + a * vy, z, z, o)


def log(X: torch.Tensor) -> torch.Tensor:
    """Principal tangent ``[vx, vy, θ]`` ``(*, 3)`` (θ ∈ (−π, π]) of a homogeneous matrix ``(*, 3, 3)``."""
    X = check_tensor(X, (3, 3), "X", "se2.log")
    th = so2._angle(X[..., :2, :2])
    tx, ty = X[..., 0, 2], X[..., 1, 2]
    alpha = torch.cos(0.5 * th) / _sinc(0.5 * th)
    beta = 0.5 * th
    return torch.stack((alpha * tx + beta * ty, -beta * tx + alpha * ty, th), dim=-1)


def hat(x: torch.Tensor) -> torch.Tensor:
    """Algebra matrix ``[[0, −θ, vx], [θ, 0, vy], [0, 0, 0]]`` ``(*, 3, 3)`` of ``x`` ``(*, 3)``."""
    x = check_tensor(x, (3,), "x", "se2.hat")
    vx, vy, th = x.unbind(-1)
    z = torch.zeros_like(th)
    return _mat3(z, -th, vx, th, z, vy, z, z, z)


def vee(M: torch.Tensor) -> torch.Tensor:
    """``[vx, vy, θ]`` ``(*, 3)`` of an algebra matrix ``(*, 3, 3)``; θ from the antisymmetric part."""
    M = check_tensor(M, (3, 3), "M", "se2.vee")
    return torch.stack((M[..., 0, 2], M[..., 1, 2], 0.5 * (M[..., 1, 0] - M[..., 0, 1])), dim=-1)


def compose(X: torch.Tensor, Y: torch.Tensor) -> torch.Tensor:
    """Group product ``X @ Y`` of homogeneous matrices ``(*, 3, 3)``, broadcasting the batch dims."""
    X = check_tensor(X, (3, 3), "X", "se2.compose")
    Y = check_tensor(Y, (3, 3), "Y", "se2.compose")
    check_same_device("se2.compose", X=X, Y=Y)
    X, Y = broadcast_leading(X, 2, Y, 2, "se2.compose", ("X", "Y"))
    return X @ Y


def inverse(X: torch.Tensor) -> torch.Tensor:
    """Closed-form inverse ``[[Rᵀ, −Rᵀ t], [0, 1]]`` ``(*, 3, 3)``."""
    X = check_tensor(X, (3, 3), "X", "se2.inverse")
    Rt = X[..., :2, :2].transpose(-1, -2)
    t = -(Rt @ X[..., :2, 2:])
    top = torch.cat((Rt, t), dim=-1)
    return torch.cat((top, X[..., 2:, :]), dim=-2)


def act(X: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """Apply ``X`` ``(*, 3, 3)`` to points ``p`` ``(*, 2)``: ``R p + t``; batch dims broadcast."""
    X = check_tensor(X, (3, 3), "X", "se2.act")
    p = check_tensor(p, (2,), "p", "se2.act")
    check_same_device("se2.act", X=X, p=p)
    X, p = broadcast_leading(X, 2, p, 1, "se2.act", ("X", "p"))
    return (X[..., :2, :2] @ p.unsqueeze(-1)).squeeze(-1) + X[..., :2, 2]


def adjoint(X: torch.Tensor) -> torch.Tensor:
    """Ad_X ``(*, 3, 3)`` = ``[[R, [t_y, −t_x]ᵀ], [0, 1]]``, so that ``X exp(x) X⁻¹ = exp(Ad_X x)``."""
    X = check_tensor(X, (3, 3), "X", "se2.adjoint")
    R = X[..., :2, :2]
    t = torch.stack((X[..., 1, 2], -X[..., 0, 2]), dim=-1).unsqueeze(-1)
    return torch.cat((torch.cat((R, t), dim=-1), X[..., 2:, :]), dim=-2)


def ad(x: torch.Tensor) -> torch.Tensor:
    """ad_x ``(*, 3, 3)`` = ``[[0, −θ, vy], [θ, 0, −vx], [0, 0, 0]]``: ``ad_x y = vee([hat x, hat y])``."""
    x = check_tensor(x, (3,), "x", "se2.ad")
    vx, vy, th = x.unbind(-1)
    z = torch.zeros_like(th)
    return _mat3(z, -th, vy, th, z, -vx, z, z, z)


def _jl(x: torch.Tensor) -> torch.Tensor:
    vx, vy, th = x.unbind(-1)
    a, b, g, e = _coeffs(th)
    z, o = torch.zeros_like(th), torch.ones_like(th)
    return _mat3(a, -b, e * vx + g * vy, b, a, -g * vx + e * vy, z, z, o)


def _jl_inv(x: torch.Tensor) -> torch.Tensor:
    vx, vy, th = x.unbind(-1)
    _, _, g, e = _coeffs(th)
    q1, q2 = e * vx + g * vy, -g * vx + e * vy
    alpha = torch.cos(0.5 * th) / _sinc(0.5 * th)
    beta = 0.5 * th
    z, o = torch.zeros_like(th), torch.ones_like(th)
    return _mat3(alpha, beta, -(alpha * q1 + beta * q2), -beta, alpha, beta * q1 - alpha * q2, z, z, o)


def left_jacobian(x: torch.Tensor) -> torch.Tensor:
    """Left Jacobian J_l(x) ``(*, 3, 3)`` of ``x`` ``(*, 3)``: ``exp(x + δ) ≈ exp(J_l δ) exp(x)``."""
    x = check_tensor(x, (3,), "x", "se2.left_jacobian")
    return _jl(x)


def left_jacobian_inv(x: torch.Tensor) -> torch.Tensor:
    """Closed-form inverse of the left Jacobian ``(*, 3, 3)`` (singular only at θ = ±2π, ±4π, …)."""
    x = check_tensor(x, (3,), "x", "se2.left_jacobian_inv")
    return _jl_inv(x)


def right_jacobian(x: torch.Tensor) -> torch.Tensor:
    """Right Jacobian J_r(x) = J_l(−x) ``(*, 3, 3)``: ``exp(x + δ) ≈ exp(x) exp(J_r δ)``."""
    x = check_tensor(x, (3,), "x", "se2.right_jacobian")
    return _jl(-x)


def right_jacobian_inv(x: torch.Tensor) -> torch.Tensor:
    """Closed-form inverse of the right Jacobian, J_l⁻¹(−x) ``(*, 3, 3)``."""
    x = check_tensor(x, (3,), "x", "se2.right_jacobian_inv")
    return _jl_inv(-x)


def identity(*batch: int, dtype: torch.dtype | None = None, device=None) -> torch.Tensor:
    """Identity motion of shape ``(*batch, 3, 3)`` (``identity(2, 3)`` or ``identity((2, 3))``)."""
    shape = batch_shape(batch, "se2.identity")
    dtype = float_dtype(dtype, "se2.identity")
    return torch.eye(3, dtype=dtype, device=device).expand(*shape, 3, 3).clone()


def random(*batch: int, generator: torch.Generator | None = None, dtype: torch.dtype | None = None,
           device=None) -> torch.Tensor:
    """Random motions ``(*batch, 3, 3)`` drawn from ``generator``.

    The rotation angle is uniform in ``[−π, π)`` (Haar on SO(2)); the translation is **standard normal**
    ``N(0, I₂)``, since SE(2) has no uniform distribution. Samples are made on ``device``, or on the
    generator's device when ``device`` is not given.
    """
    shape = batch_shape(batch, "se2.random")
    dtype = float_dtype(dtype, "se2.random")
    device = rng_device(generator, device)
    u = torch.rand(*shape, generator=generator, dtype=dtype, device=device)
    t = torch.randn(*shape, 2, generator=generator, dtype=dtype, device=device)
    th = (2 * u - 1) * math.pi
    c, s = torch.cos(th), torch.sin(th)
    z, o = torch.zeros_like(th), torch.ones_like(th)
    return _mat3(c, -s, t[..., 0], s, c, t[..., 1], z, z, o)


def interpolate(X: torch.Tensor, Y: torch.Tensor, t) -> torch.Tensor:
    """Geodesic ``X exp(t log(X⁻¹ Y))`` between motions ``(*, 3, 3)`` (a constant-twist screw path).

    ``t`` is a float or a tensor of ``X``'s dtype and device (nothing is cast), of shape ``(*T)``, that
    broadcasts with the batch dims of ``X`` and ``Y``; ``t = 0`` gives ``X``, ``t = 1`` gives ``Y``.
    """
    X = check_tensor(X, (3, 3), "X", "se2.interpolate")
    Y = check_tensor(Y, (3, 3), "Y", "se2.interpolate")
    check_same_device("se2.interpolate", X=X, Y=Y)
    t = scalar_param(t, X, "se2.interpolate")
    d = log(compose(inverse(X), Y))
    return compose(X, exp(d * t.unsqueeze(-1)))
