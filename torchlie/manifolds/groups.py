"""Euclidean space and the Lie groups as manifolds: Rⁿ, SO(2), SO(3), SE(3) (seed 003 Eq. 4-8, 41-44;
seed 004 §12).

On these spaces the two vocabularies are the same maps in the same coordinates, so each class has
one implementation of them: ``exp_at(x, δ) = x ⊞ δ = x ⊕ δ`` and ``log_at(x, y) = y ⊟ x``, with δ the
body-frame tangent vector (``x·Exp(δ)``, ``Log(x⁻¹y)``) — ω for the rotations, ``[ρ, ω]``
(translation first, :mod:`torchlie.se3`) for SE(3), the plain difference for Rⁿ.

==================  ============  ====  ====  ====================================  =====================
manifold            point         n     l     G_x / G_f (closed form)               transport (Exp/Log)
==================  ============  ====  ====  ====================================  =====================
``Rn(n)``           ``(*, n)``    n     n     I / I                       (Eq. 41)  identity
``SO2()``           ``(*, 2, 2)`` 1     1     1 / 1                       (Eq. 42)  identity (abelian)
``SO3()``           ``(*, 3, 3)`` 3     3     Exp(-v) / A(v)ᵀ = J_r(v)    (Eq. 43)  Ad_{Exp(−u/2)}
``SE3()``           ``(*, 4, 4)`` 6     6     Ad_{Exp(-v)} / J_r(v)                 Ad_{Exp(−u/2)}
==================  ============  ====  ====  ====================================  =====================

``Euclidean`` (the Exp/Log vocabulary's name) is ``Rn``.

Exactness of Table I.  Every closed form above is the *exact* derivative of Eq. 23 at δ = 0, not a
first-order approximation of it: the conjugation ``Exp(-v) Exp(δ) Exp(v) = Exp(Ad_{Exp(-v)} δ)`` is
exact, and ``Exp(v + δ) = Exp(v) Exp(J_r(v) δ + O(δ²))``.

Transport.  Along ``X exp(t u)`` (u = Log_X(Y)) the transport is ``Ad_{exp(−u/2)}`` on body-frame
coordinates: the Levi-Civita transport of the bi-invariant metric for SO(3) (an isometry), and the
transport of the symmetric Cartan–Schouten connection (whose geodesics are these one-parameter
curves) for SE(3), which has no bi-invariant metric: there it is not an isometry of the
left-invariant metric, and ``dist = ‖log(X⁻¹Y)‖`` is symmetric but not a true geodesic distance (no
triangle inequality).

Membership and projection.  A rotation is off SO(n) by ``max(max|RᵀR − I|, |det R − 1|)``; an SE(3)
matrix also by its last row's distance to ``[0, 0, 0, 1]``.  ``project=True`` takes the nearest
rotation in Frobenius norm (:func:`torchlie.so3.project`: SVD value, exact first derivative also at
rotations themselves and for det < 0 inputs) and resets the last row.
"""

from __future__ import annotations

import dataclasses
import math

import torch

from torchlie._batch import broadcast_shapes
from torchlie.manifolds.base import Manifold, _eye, _group

__all__ = ["Rn", "Euclidean", "SO2", "SO3", "SE3"]


def _rotation_error(R: torch.Tensor) -> torch.Tensor:
    n = R.shape[-1]
    eye = torch.eye(n, dtype=R.dtype, device=R.device)
    orth = (R.transpose(-1, -2) @ R - eye).abs().amax(dim=(-1, -2))
    det = torch.linalg.det(R) if n != 2 else R[..., 0, 0] * R[..., 1, 1] - R[..., 0, 1] * R[..., 1, 0]
    return torch.maximum(orth, (det - 1).abs())


def _project_rotation(M: torch.Tensor) -> torch.Tensor:
    """Nearest rotation to ``M`` (see :func:`torchlie.so3.project`, exact first derivative)."""
    return _group("so3").project(M)


@dataclasses.dataclass(frozen=True)
class Rn(Manifold):
    """Euclidean space Rⁿ ``(*, n)``: ⊞ = ⊕ = Exp = +, ⊟ = Log = − (seed 003 Eq. 4), G_x = G_f = Iₙ
    (Eq. 41); transport = identity (seed 004 §2, the product of Gaussians)."""

    n: int

    def __post_init__(self):
        if isinstance(self.n, bool) or not isinstance(self.n, int) or self.n < 1:
            raise ValueError(f"Rn: argument 'n' must be a positive int, got {self.n!r}")

    @property
    def dim(self) -> int:
        return self.n

    @property
    def ext_dim(self) -> int:
        return self.n

    @property
    def event_shape(self) -> tuple[int, ...]:
        return (self.n,)

    def _describe(self) -> str:
        return f"R^{self.n} (finite entries)"

    def _membership_error(self, x):
        return torch.where(torch.isfinite(x).all(-1), 0.0, math.inf).to(x.dtype)

    def _project(self, x, name, fn):
        return x

    def _boxplus(self, x, delta):
        return x + delta

    def _boxminus(self, y, x):
        return y - x

    _oplus = _exp = _boxplus

    def _log(self, x, y):
        return self._boxminus(y, x)

    def _tm(self, x, y):
        return _eye(self.n, broadcast_shapes(x.shape[:-1], y.shape[:-1]), x)

    _G_identity = True

    def _G_x(self, x_d, v):
        return _eye(self.n, broadcast_shapes(x_d.shape[:-1], v.shape[:-1]), v)

    def _G_f(self, x_d, v):
        return self._G_x(x_d, v)

    def _random(self, batch, generator, dtype, device):
        return torch.randn(*batch, self.n, generator=generator, dtype=dtype, device=device)

    def _identity(self, batch, dtype, device):
        return torch.zeros(*batch, self.n, dtype=dtype, device=device)


Euclidean = Rn  # the name torchlie.riemannian used for the same space


@dataclasses.dataclass(frozen=True)
class SO2(Manifold):
    """SO(2) as 2×2 rotation matrices, tangent θ ``(*, 1)``: ⊞ = ⊕ = Exp_x = x·Exp(δ), y ⊟ x =
    Log_x(y) = Log(x⁻¹y) (Eq. 5, 7); G_x = G_f = 1 (Eq. 42, exact because SO(2) is abelian), and for
    the same reason the transport is the identity."""

    @property
    def dim(self) -> int:
        return 1

    @property
    def ext_dim(self) -> int:
        return 1

    @property
    def event_shape(self) -> tuple[int, ...]:
        return (2, 2)

    def _describe(self) -> str:
        return "SO(2) (rotation matrices: orthogonal 2x2 with det +1)"

    def _membership_error(self, x):
        return _rotation_error(x)

    def _project(self, x, name, fn):
        # nearest rotation in Frobenius norm: angle atan2(c - b, a + d) of M = [[a, b], [c, d]]
        th = torch.atan2(x[..., 1, 0] - x[..., 0, 1], x[..., 0, 0] + x[..., 1, 1])
        return _group("so2").exp(th.unsqueeze(-1))

    def _boxplus(self, x, delta):
        return x @ _group("so2").exp(delta)

    def _boxminus(self, y, x):
        return _group("so2").log(x.transpose(-1, -2) @ y)

    _oplus = _exp = _boxplus

    def _log(self, x, y):
        return self._boxminus(y, x)

    def _tm(self, x, y):
        return _eye(1, broadcast_shapes(x.shape[:-2], y.shape[:-2]), x)

    _G_identity = True

    def _G_x(self, x_d, v):
        batch = broadcast_shapes(x_d.shape[:-2], v.shape[:-1])
        return torch.ones(*batch, 1, 1, dtype=v.dtype, device=v.device)

    def _G_f(self, x_d, v):
        return self._G_x(x_d, v)

    def _random(self, batch, generator, dtype, device):
        return _group("so2").random(*batch, generator=generator, dtype=dtype, device=device)

    def _identity(self, batch, dtype, device):
        return torch.eye(2, dtype=dtype, device=device).expand(*batch, 2, 2).clone()


@dataclasses.dataclass(frozen=True)
class SO3(Manifold):
    """SO(3) as rotation matrices ``(*, 3, 3)``, tangent = body-frame ω ``(*, 3)`` (bi-invariant
    metric): ⊞ = ⊕ = Exp_x = x·Exp(δ), y ⊟ x = Log_x(y) = Log(x⁻¹y) (Eq. 5, 8); G_x = Exp(-v)
    (Eq. 43a) and G_f = A(v)ᵀ (Eq. 43b-44), where A(v) of Eq. 44 is the left Jacobian, so
    A(v)ᵀ = J_l(-v) = J_r(v); transport along x·Exp(tu): Ad_{Exp(−u/2)} = Exp(−u/2)."""

    @property
    def dim(self) -> int:
        return 3

    @property
    def ext_dim(self) -> int:
        return 3

    @property
    def event_shape(self) -> tuple[int, ...]:
        return (3, 3)

    def _describe(self) -> str:
        return "SO(3) (rotation matrices: orthogonal 3x3 with det +1)"

    def _membership_error(self, x):
        return _rotation_error(x)

    def _project(self, x, name, fn):
        return _project_rotation(x)

    def _boxplus(self, x, delta):
        return x @ _group("so3").exp(delta)

    def _boxminus(self, y, x):
        return _group("so3").log(x.transpose(-1, -2) @ y)

    _oplus = _exp = _boxplus

    def _log(self, x, y):
        return self._boxminus(y, x)

    def _tm(self, x, y):
        return _group("so3").exp(-0.5 * self._log(x, y))

    def _G_x(self, x_d, v):
        G = _group("so3").exp(-v)
        return G.expand(*broadcast_shapes(x_d.shape[:-2], v.shape[:-1]), 3, 3)

    def _G_f(self, x_d, v):
        J = _group("so3").right_jacobian(v)
        return J.expand(*broadcast_shapes(x_d.shape[:-2], v.shape[:-1]), 3, 3)

    def _random(self, batch, generator, dtype, device):
        return _group("so3").random(*batch, generator=generator, dtype=dtype, device=device)

    def _identity(self, batch, dtype, device):
        return torch.eye(3, dtype=dtype, device=device).expand(*batch, 3, 3).clone()


@dataclasses.dataclass(frozen=True)
class SE3(Manifold):
    """SE(3) as homogeneous 4×4 matrices, tangent = body-frame ``[ρ, ω]`` ``(*, 6)`` (translation
    first): ⊞ = ⊕ = Exp_x = x·Exp(δ), y ⊟ x = Log_x(y) = Log(x⁻¹y) (Eq. 5); G_x = Ad_{Exp(-v)},
    G_f = J_r(v) (the SE(3) counterparts of Eq. 43, both exact: ``Exp(-v) Exp(δ) Exp(v) =
    Exp(Ad_{Exp(-v)} δ)`` and ``Exp(v + δ) = Exp(v) Exp(J_r(v) δ + O(δ²))``); transport
    Ad_{Exp(−u/2)} (Cartan–Schouten (0) connection; not an isometry of the left-invariant metric —
    see the module docstring)."""

    @property
    def dim(self) -> int:
        return 6

    @property
    def ext_dim(self) -> int:
        return 6

    @property
    def event_shape(self) -> tuple[int, ...]:
        return (4, 4)

    def _describe(self) -> str:
        return "SE(3) (homogeneous 4x4 matrices: rotation block in SO(3), last row [0, 0, 0, 1])"

    def _membership_error(self, x):
        last = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=x.dtype, device=x.device)
        row = (x[..., 3, :] - last).abs().amax(-1)
        return torch.maximum(_rotation_error(x[..., :3, :3]), row)

    def _project(self, x, name, fn):
        R = _project_rotation(x[..., :3, :3])
        top = torch.cat((R, x[..., :3, 3:]), -1)
        last = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=x.dtype, device=x.device).expand(*x.shape[:-2], 1, 4)
        return torch.cat((top, last), -2)

    def _boxplus(self, x, delta):
        return x @ _group("se3").exp(delta)

    def _boxminus(self, y, x):
        se3 = _group("se3")
        return se3.log(se3.inverse(x) @ y)

    _oplus = _exp = _boxplus

    def _log(self, x, y):
        return self._boxminus(y, x)

    def _tm(self, x, y):
        se3 = _group("se3")
        return se3.adjoint(se3.exp(-0.5 * self._log(x, y)))

    def _G_x(self, x_d, v):
        se3 = _group("se3")
        G = se3.adjoint(se3.exp(-v))
        return G.expand(*broadcast_shapes(x_d.shape[:-2], v.shape[:-1]), 6, 6)

    def _G_f(self, x_d, v):
        J = _group("se3").right_jacobian(v)
        return J.expand(*broadcast_shapes(x_d.shape[:-2], v.shape[:-1]), 6, 6)

    def _random(self, batch, generator, dtype, device):
        return _group("se3").random(*batch, generator=generator, dtype=dtype, device=device)

    def _identity(self, batch, dtype, device):
        return torch.eye(4, dtype=dtype, device=device).expand(*batch, 4, 4).clone()
