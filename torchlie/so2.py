"""SO(2): planar rotations as ``(*, 2, 2)`` rotation matrices, tangent ``x = [θ]`` of shape ``(*, 1)``.

The functional contract (shapes, broadcasting, dtype/device, Jacobian conventions) is the one in
:mod:`torchlie`'s docstring; this page only records what is specific to SO(2).

- ``exp([θ]) = [[cos θ, −sin θ], [sin θ, cos θ]]``.
- ``log(R)`` is principal: ``θ ∈ (−π, π]``, computed as ``atan2(R₁₀ − R₀₁, R₀₀ + R₁₁)`` (the angle of the
  rotation nearest to ``R``), with the ``−π`` that ``atan2`` returns on its cut mapped to ``+π``.
  Its gradient is finite everywhere, also at ``θ = π`` (one-sided there, since ``log`` jumps by 2π).
- SO(2) is abelian, so ``adjoint`` and every Jacobian are the ``(*, 1, 1)`` identity and ``ad`` is the
  ``(*, 1, 1)`` zero (Solà et al., *A micro Lie theory*, Ex. 5).
- ``vee`` returns the antisymmetric part ``(M₁₀ − M₀₁) / 2`` (exact on the algebra, the orthogonal
  projection elsewhere).
- ``random`` draws θ uniformly in ``[−π, π)`` (the Haar measure).
"""

from __future__ import annotations

import math

import torch

from torchlie._batch import (
    batch_shape,
    broadcast_leading,
    check_same_device,
    check_tensor,
    float_dtype,
    rng_device,
    scalar_param,
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


def _principal(theta: torch.Tensor) -> torch.Tensor:
    # atan2 returns −π for (−0.0, negative); the principal range is (−π, π]. The +2π is exact in floating
    # point, so the result is exactly the float nearest π.
    return torch.where(theta <= -math.pi, theta + 2 * math.pi, theta)


def _rot(c: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
    return torch.stack((c, -s, s, c), dim=-1).unflatten(-1, (2, 2))


def _angle(R: torch.Tensor) -> torch.Tensor:
    """Principal angle of the rotation nearest to the ``(*, 2, 2)`` matrix ``R``, shape ``(*)``."""
    return _principal(torch.atan2(R[..., 1, 0] - R[..., 0, 1], R[..., 0, 0] + R[..., 1, 1]))


def exp(x: torch.Tensor) -> torch.Tensor:
    """Rotation matrix ``(*, 2, 2)`` of the angle ``x = [θ]`` of shape ``(*, 1)``."""
    x = check_tensor(x, (1,), "x", "so2.exp")
    th = x[..., 0]
    return _rot(torch.cos(th), torch.sin(th))


def log(X: torch.Tensor) -> torch.Tensor:
    """Principal angle ``[θ]``, θ ∈ (−π, π], of the rotation ``X`` ``(*, 2, 2)``; shape ``(*, 1)``."""
    X = check_tensor(X, (2, 2), "X", "so2.log")
    return _angle(X).unsqueeze(-1)


def hat(x: torch.Tensor) -> torch.Tensor:
    """Algebra matrix ``[[0, −θ], [θ, 0]]`` ``(*, 2, 2)`` of ``x = [θ]`` ``(*, 1)``."""
    x = check_tensor(x, (1,), "x", "so2.hat")
    th = x[..., 0]
    z = torch.zeros_like(th)
    return torch.stack((z, -th, th, z), dim=-1).unflatten(-1, (2, 2))


def vee(M: torch.Tensor) -> torch.Tensor:
    """``[θ]`` ``(*, 1)`` of an algebra matrix ``M`` ``(*, 2, 2)``: the part ``(M₁₀ − M₀₁)/2``."""
    M = check_tensor(M, (2, 2), "M", "so2.vee")
    return (0.5 * (M[..., 1, 0] - M[..., 0, 1])).unsqueeze(-1)


def compose(X: torch.Tensor, Y: torch.Tensor) -> torch.Tensor:
    """Group product ``X @ Y`` of rotations ``(*, 2, 2)``, broadcasting the batch dims."""
    X = check_tensor(X, (2, 2), "X", "so2.compose")
    Y = check_tensor(Y, (2, 2), "Y", "so2.compose")
    check_same_device("so2.compose", X=X, Y=Y)
    X, Y = broadcast_leading(X, 2, Y, 2, "so2.compose", ("X", "Y"))
    return X @ Y


def inverse(X: torch.Tensor) -> torch.Tensor:
    """Inverse rotation (the transpose) ``(*, 2, 2)``."""
    X = check_tensor(X, (2, 2), "X", "so2.inverse")
    return X.transpose(-1, -2)


def act(X: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """Rotate points ``p`` ``(*, 2)`` by ``X`` ``(*, 2, 2)``; batch dims broadcast. Returns ``(*, 2)``."""
    X = check_tensor(X, (2, 2), "X", "so2.act")
    p = check_tensor(p, (2,), "p", "so2.act")
    check_same_device("so2.act", X=X, p=p)
    X, p = broadcast_leading(X, 2, p, 1, "so2.act", ("X", "p"))
    return (X @ p.unsqueeze(-1)).squeeze(-1)


def _ones11(t: torch.Tensor, k: int) -> torch.Tensor:
    return t.new_ones(t.shape[: t.dim() - k] + (1, 1))


def adjoint(X: torch.Tensor) -> torch.Tensor:
    """Ad_X of a rotation ``(*, 2, 2)``: SO(2) is abelian, so the ``(*, 1, 1)`` identity."""
    X = check_tensor(X, (2, 2), "X", "so2.adjoint")
    return _ones11(X, 2)


def ad(x: torch.Tensor) -> torch.Tensor:
    """ad_x of ``x = [θ]`` ``(*, 1)``: the ``(*, 1, 1)`` zero (so(2) is abelian)."""
    x = check_tensor(x, (1,), "x", "so2.ad")
    return x.new_zeros(x.shape[:-1] + (1, 1))


def left_jacobian(x: torch.Tensor) -> torch.Tensor:
    """Left Jacobian J_l(x) of ``x = [θ]`` ``(*, 1)``: the ``(*, 1, 1)`` identity."""
    x = check_tensor(x, (1,), "x", "so2.left_jacobian")
    return _ones11(x, 1)


def left_jacobian_inv(x: torch.Tensor) -> torch.Tensor:
    """Inverse left Jacobian of ``x = [θ]`` ``(*, 1)``: the ``(*, 1, 1)`` identity."""
    x = check_tensor(x, (1,), "x", "so2.left_jacobian_inv")
    return _ones11(x, 1)


def right_jacobian(x: torch.Tensor) -> torch.Tensor:
    """Right Jacobian J_r(x) of ``x = [θ]`` ``(*, 1)``: the ``(*, 1, 1)`` identity."""
    x = check_tensor(x, (1,), "x", "so2.right_jacobian")
    return _ones11(x, 1)


def right_jacobian_inv(x: torch.Tensor) -> torch.Tensor:
    """Inverse right Jacobian of ``x = [θ]`` ``(*, 1)``: the ``(*, 1, 1)`` identity."""
    x = check_tensor(x, (1,), "x", "so2.right_jacobian_inv")
    return _ones11(x, 1)


def identity(*batch: int, dtype: torch.dtype | None = None, device=None) -> torch.Tensor:
    """Identity rotation of shape ``(*batch, 2, 2)`` (``identity(2, 3)`` or ``identity((2, 3))``)."""
    shape = batch_shape(batch, "so2.identity")
    dtype = float_dtype(dtype, "so2.identity")
    return torch.eye(2, dtype=dtype, device=device).expand(*shape, 2, 2).clone()


def random(*batch: int, generator: torch.Generator | None = None, dtype: torch.dtype | None = None,
           device=None) -> torch.Tensor:
    """Haar-uniform rotations ``(*batch, 2, 2)``: θ uniform in ``[−π, π)`` drawn from ``generator``.

    The samples are made on ``device``, or on the generator's device when ``device`` is not given.
    """
    shape = batch_shape(batch, "so2.random")
    dtype = float_dtype(dtype, "so2.random")
    u = torch.rand(*shape, 1, generator=generator, dtype=dtype, device=rng_device(generator, device))
    return exp((2 * u - 1) * math.pi)


def interpolate(X: torch.Tensor, Y: torch.Tensor, t) -> torch.Tensor:
    """Geodesic ``X exp(t log(X⁻¹ Y))`` between rotations ``(*, 2, 2)``.

    ``t`` is a float or a tensor of ``X``'s dtype and device (nothing is cast), of shape ``(*T)``, that
    broadcasts with the batch dims of ``X`` and ``Y`` (e.g. ``X`` ``(B, 2, 2)`` and ``t`` ``(T, 1)`` give
    ``(T, B, 2, 2)``); ``t = 0`` gives ``X``, ``t = 1`` gives ``Y``. Between antipodal rotations (relative
    angle π) the path turns by +π.
    """
    X = check_tensor(X, (2, 2), "X", "so2.interpolate")
    Y = check_tensor(Y, (2, 2), "Y", "so2.interpolate")
    check_same_device("so2.interpolate", X=X, Y=Y)
    t = scalar_param(t, X, "so2.interpolate")
    d = log(compose(inverse(X), Y))
    return compose(X, exp(d * t.unsqueeze(-1)))
