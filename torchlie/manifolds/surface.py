"""Height surfaces S = {x ∈ R³ : z = F(x, y)} (seed 003 Eq. 12, 37-40, 46): :class:`Surface`, the
quadratic patch of Eq. 40 (:func:`quadratic_surface`) and its least-squares fit
(:func:`fit_quadratic_surface`).

A surface has the ⊞ vocabulary only (n = l = 2, perturbations in the x-y plane, G_x = G_f = I₂
exactly, Eq. 46); it has no Exp/Log (its geodesics have no closed form; ``has_exp_log`` is False).
Membership: the height error ``|z − F(x, y)| / (1 + |z|)`` against
:func:`~torchlie.manifolds.manifold_tolerance`; ``project=True`` lifts ``(x, y)`` onto the surface.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import NamedTuple

import torch

from torchlie._batch import broadcast_shapes, check_same_device, check_tensor
from torchlie.manifolds.base import Manifold, _eye

__all__ = ["Surface", "SurfaceFit", "quadratic_surface", "fit_quadratic_surface"]


def _autograd_gradient(F: Callable, xy: torch.Tensor) -> torch.Tensor:
    def f(p):
        return F(p).sum()

    return torch.func.grad(f)(xy)


@dataclasses.dataclass(frozen=True)
class Surface(Manifold):
    """2-D height surface S = {x ∈ R³ : z = F(x, y)} (Eq. 12, 46), points ``(*, 3)``, n = l = 2.

    ``x ⊞ δ = x ⊕ δ = [E₁₂ᵀx + δ; F(E₁₂ᵀx + δ)]``, ``y ⊟ x = E₁₂ᵀ(y − x)`` (perturbations in the
    x-y plane); G_x = G_f = I₂ (Eq. 46).

    ``F(xy)`` maps ``(*, 2)`` to ``(*,)``; ``grad_F(xy)`` -> ``(*, 2)`` = [F'_x, F'_y] and
    ``hess_F(xy)`` -> ``(*, 2, 2)`` are the derivatives the system-specific parts need (Eq. 37-39);
    when omitted they are computed from F by autograd.  :func:`quadratic_surface` builds all three
    from the coefficients of Eq. 40.  The callables must be torch functions of their argument
    (they are differentiated through by ``exact=True`` and by autograd users); tensors they close
    over do not move with ``.to()`` of the points.
    """

    F: Callable[[torch.Tensor], torch.Tensor] = dataclasses.field(repr=False)
    grad_F: Callable[[torch.Tensor], torch.Tensor] | None = dataclasses.field(default=None, repr=False)
    hess_F: Callable[[torch.Tensor], torch.Tensor] | None = dataclasses.field(default=None, repr=False)
    name: str = "F"

    def __post_init__(self):
        for field in ("F", "grad_F", "hess_F"):
            f = getattr(self, field)
            if (field == "F" or f is not None) and not callable(f):
                raise TypeError(f"Surface: argument '{field}' must be callable, got {type(f).__name__}")

    @property
    def dim(self) -> int:
        return 2

    @property
    def ext_dim(self) -> int:
        return 2

    @property
    def event_shape(self) -> tuple[int, ...]:
        return (3,)

    def _describe(self) -> str:
        return f"the surface z = {self.name}(x, y) (|z - F| / (1 + |z|))"

    def height(self, xy: torch.Tensor) -> torch.Tensor:
        """F(x, y) for ``xy`` ``(*, 2)``: shape ``(*,)`` (broadcast with F's own batch, if any)."""
        z = self.F(xy)
        if not isinstance(z, torch.Tensor):
            raise TypeError(f"Surface: F must return a tensor, got {type(z).__name__}")
        batch = xy.shape[:-1]
        if z.dim() == len(batch) + 1 and z.shape[-1] == 1:
            z = z.squeeze(-1)
        try:
            out = broadcast_shapes(z.shape, batch)
        except RuntimeError:
            out = None
        if out is None or len(out) != max(len(batch), z.dim()):
            raise ValueError(f"Surface: F(xy) must return shape {tuple(batch)} for xy of shape "
                             f"{tuple(xy.shape)}, got {tuple(z.shape)}")
        return z.expand(out)

    def _grad_xy(self, xy: torch.Tensor) -> torch.Tensor:
        g = self.grad_F(xy) if self.grad_F is not None else _autograd_gradient(self.height, xy)
        if not isinstance(g, torch.Tensor) or g.shape[-1:] != (2,):
            raise ValueError("Surface: grad_F(xy) must return shape (*, 2), "
                             f"got {tuple(getattr(g, 'shape', ()))}")
        return g.expand(*broadcast_shapes(g.shape[:-1], xy.shape[:-1]), 2)

    def gradient(self, x: torch.Tensor) -> torch.Tensor:
        """g = [F'_x, F'_y] ``(*, 2)`` at ``x`` ``(*, 3)`` or ``(*, 2)`` (only x, y are used; Eq. 37b)."""
        return self._grad_xy(x[..., :2])

    def hessian(self, x: torch.Tensor) -> torch.Tensor:
        """∇²F ``(*, 2, 2)`` = [[F''_xx, F''_xy], [F''_yx, F''_yy]] at ``x`` (Eq. 39d)."""
        xy = x[..., :2]
        if self.hess_F is not None:
            H = self.hess_F(xy)
        else:
            flat = xy.reshape(-1, 2)
            H = torch.func.vmap(torch.func.jacrev(self._grad_xy))(flat).reshape(*xy.shape[:-1], 2, 2)
        if not isinstance(H, torch.Tensor) or H.shape[-2:] != (2, 2):
            raise ValueError("Surface: hess_F(xy) must return shape (*, 2, 2), "
                             f"got {tuple(getattr(H, 'shape', ()))}")
        return H.expand(*broadcast_shapes(H.shape[:-2], xy.shape[:-1]), 2, 2)

    def normal(self, x: torch.Tensor) -> torch.Tensor:
        """Unit upward normal ``(−F'_x, −F'_y, 1)/√(1 + gᵀg)`` ``(*, 3)`` (the z_b axis of Eq. 35)."""
        g = self.gradient(x)
        n = torch.cat((-g, torch.ones_like(g[..., :1])), -1)
        return n / torch.linalg.vector_norm(n, dim=-1, keepdim=True)

    def _membership_error(self, x):
        z = x[..., 2]
        return (z - self.height(x[..., :2])).abs() / (1 + z.abs())

    def _project(self, x, name, fn):
        return self._lift(x[..., :2])

    def _lift(self, xy):
        z = self.height(xy)
        return torch.cat((xy.expand(*z.shape, 2), z.unsqueeze(-1)), -1)

    def _boxplus(self, x, delta):
        return self._lift(x[..., :2] + delta)

    def _boxminus(self, y, x):
        return y[..., :2] - x[..., :2]

    def _oplus(self, x, delta_e):
        return self._lift(x[..., :2] + delta_e)

    _G_identity = True

    def _G_x(self, x_d, v):
        return _eye(2, broadcast_shapes(x_d.shape[:-1], v.shape[:-1]), v)

    def _G_f(self, x_d, v):
        return self._G_x(x_d, v)

    def _random(self, batch, generator, dtype, device):
        return self._lift(torch.randn(*batch, 2, generator=generator, dtype=dtype, device=device))

    def _identity(self, batch, dtype, device):
        return self._lift(torch.zeros(*batch, 2, dtype=dtype, device=device))


# ------------------------------------------------------------------------------------------------
# quadratic surface patch (Eq. 40)
# ------------------------------------------------------------------------------------------------

def quadratic_surface(gamma: torch.Tensor, name: str = "quadratic") -> Surface:
    """Surface of Eq. 40, ``F = γ₁x² + γ₂xy + γ₃y² + γ₄x + γ₅y + γ₆``, with analytic ∇F and ∇²F.

    ``gamma`` ``(*G, 6)``; ``*G`` broadcasts with the batch of the points the surface is used on
    by torch's (right-aligned) rules, so one patch per batch element (e.g. one per reference point
    as in seed 003 §VII-B-4) needs ``*G`` equal to the points' batch shape; for fitted patches
    ``(P, 6)`` evaluated on points ``(P, N, 2)`` pass ``gamma.unsqueeze(-2)``.
    """
    check_tensor(gamma, (6,), "gamma", "quadratic_surface")
    g1, g2, g3, g4, g5, g6 = gamma.unbind(-1)

    def F(xy):
        x, y = xy[..., 0], xy[..., 1]
        return g1 * x * x + g2 * x * y + g3 * y * y + g4 * x + g5 * y + g6

    def grad_F(xy):
        x, y = xy[..., 0], xy[..., 1]
        return torch.stack((2 * g1 * x + g2 * y + g4, g2 * x + 2 * g3 * y + g5), -1)

    def hess_F(xy):
        H = torch.stack((2 * g1, g2, g2, 2 * g3), -1).reshape(*gamma.shape[:-1], 2, 2)
        return H.expand(*broadcast_shapes(gamma.shape[:-1], xy.shape[:-1]), 2, 2)

    return Surface(F, grad_F, hess_F, name=name)


class SurfaceFit(NamedTuple):
    """Result of :func:`fit_quadratic_surface` (per batch element)."""

    coefficients: torch.Tensor  # (*, 6) γ of Eq. 40 in the points' own coordinates
    rms: torch.Tensor  # (*,) weighted RMS of the height residuals
    well_posed: torch.Tensor  # (*,) bool: the design matrix has full rank 6 (to dtype tolerance)

    def surface(self, name: str = "quadratic") -> Surface:
        """The fitted :class:`Surface` (see :func:`quadratic_surface`)."""
        return quadratic_surface(self.coefficients, name=name)


def fit_quadratic_surface(points: torch.Tensor, weights: torch.Tensor | None = None) -> SurfaceFit:
    """Least-squares fit of the quadratic patch of Eq. 40 to 3-D points, batched.

    ``points`` ``(*, N, 3)`` (N ≥ 6), optional ``weights`` ``(*, N)`` ≥ 0.  Minimizes
    ``Σ w_i (z_i − F(x_i, y_i))²``.  For conditioning the x-y coordinates are centred and scaled
    per batch element, the problem is solved by SVD there and the coefficients are mapped back
    exactly.  A degenerate layout (all points on a line, fewer than 6 with positive weight) gives
    ``well_posed = False`` and the minimum-norm solution for that element only; the rest of the
    batch is unaffected.  Differentiable w.r.t. points and weights for well-posed elements.
    """
    fn = "fit_quadratic_surface"
    check_tensor(points, (3,), "points", fn)
    if points.dim() < 2:
        raise ValueError(f"{fn}: argument 'points' must have shape (*, N, 3), got {tuple(points.shape)}")
    N = points.shape[-2]
    if N < 6:
        raise ValueError(f"{fn}: argument 'points' needs N ≥ 6 points to fit 6 coefficients, got {N}")
    if not bool(torch.isfinite(points).all()):
        raise ValueError(f"{fn}: argument 'points' contains non-finite entries")
    if weights is None:
        weights = torch.ones(points.shape[:-1], dtype=points.dtype, device=points.device)
    else:
        check_tensor(weights, (N,), "weights", fn)
        check_same_device(fn, points=points, weights=weights)
        if not bool(((weights >= 0) & torch.isfinite(weights)).all()):
            raise ValueError(f"{fn}: argument 'weights' must be finite and nonnegative")
    batch = broadcast_shapes(points.shape[:-2], weights.shape[:-1])
    points = points.expand(*batch, N, 3)
    w = weights.expand(*batch, N)
    wsum = w.sum(-1, keepdim=True)
    wn = w / torch.where(wsum > 0, wsum, torch.ones_like(wsum))
    xy, z = points[..., :2], points[..., 2]
    center = (wn.unsqueeze(-1) * xy).sum(-2)  # (*, 2)
    d = xy - center.unsqueeze(-2)
    scale2 = (wn * (d * d).sum(-1)).sum(-1)
    s = torch.sqrt(torch.where(scale2 > 0, scale2, torch.ones_like(scale2)))  # (*,)
    X, Y = (d / s[..., None, None]).unbind(-1)
    A = torch.stack((X * X, X * Y, Y * Y, X, Y, torch.ones_like(X)), -1)  # (*, N, 6)
    sw = torch.sqrt(w)
    Aw, zw = A * sw.unsqueeze(-1), z * sw
    U, S, Vh = torch.linalg.svd(Aw, full_matrices=False)
    cut = S[..., :1] * (max(N, 6) * torch.finfo(points.dtype).eps * 10)
    keep = S > cut
    Sinv = torch.where(keep, 1 / torch.where(keep, S, torch.ones_like(S)), torch.zeros_like(S))
    g = (Vh.transpose(-1, -2) @ (Sinv.unsqueeze(-1) * (U.transpose(-1, -2) @ zw.unsqueeze(-1)))).squeeze(-1)
    well_posed = keep.all(-1)
    res = z - (A @ g.unsqueeze(-1)).squeeze(-1)
    rms = torch.sqrt((wn * res * res).sum(-1))
    # back to the original coordinates: X = (x - cx)/s, Y = (y - cy)/s
    a1, a2, a3, a4, a5, a6 = g.unbind(-1)
    cx, cy = center.unbind(-1)
    s2 = s * s
    gamma = torch.stack((
        a1 / s2,
        a2 / s2,
        a3 / s2,
        (-2 * a1 * cx - a2 * cy) / s2 + a4 / s,
        (-a2 * cx - 2 * a3 * cy) / s2 + a5 / s,
        (a1 * cx * cx + a2 * cx * cy + a3 * cy * cy) / s2 - (a4 * cx + a5 * cy) / s + a6,
    ), -1)
    return SurfaceFit(gamma, rms, well_posed)
