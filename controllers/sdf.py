"""Signed distance fields (SDFs) encoded with basis functions: fitting with the eikonal cost and closest
points between two shapes (seed 004 §6.3-6.4, §6.8).

An SDF on a box ``[lower, upper] ⊂ R^d`` is the field ``f(p) = Ψ(u) w`` of :mod:`controllers.basis` with the
normalized input ``u = (p - lower) / (upper - lower) ∈ [0, 1]^d`` and ``Ψ(u) = φ(u_1) ⊗ … ⊗ φ(u_d)``
(Eq. 30, 33); its gradient is ``∇f(p) = diag(upper - lower)⁻¹ ∇Ψ(u) w`` (Eq. 35-37).  The default dictionary
is the concatenation of 5 cubic Bézier curves with C¹ joints per input (``basis.spline``, §6.5, Fig. 14).

* :func:`fit_sdf` — the weights ``w`` from contour points (and optionally observed distances) with the
  eikonal term, Eq. (58), by Gauss–Newton (:func:`controllers.optim.gauss_newton` with the analytic Jacobian
  ``J_1 = Ψ(t_m)``, ``J_2 = 2 ∇xᵀ ∇Ψ(t_n)``), batched over shapes.
* :func:`closest_points` — the two contour points with closest distance, Eq. (40)-(42) (plain Gauss–Newton);
  :func:`closest_points_prioritized` — Eq. (43)-(44) (points on the contours first, then closer).

Batch conventions: an :class:`SDF` has batch shape ``w.shape[:-1]`` (several shapes at once); the batch dims
of query points ``p (*B, d)`` broadcast against it (for ``N`` points per shape of ``S`` shapes use points
``(N, S, d)``, or an SDF whose ``w`` is ``(S, 1, P)`` with points ``(S, N, d)``).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

from controllers import basis as _basis
from controllers.optim import OptimResult, gauss_newton
from controllers.problem import Reason, SolverStatus

__all__ = ["SDF", "SDFFitResult", "ClosestPointsResult", "default_sdf_basis", "sdf_value",
           "sdf_value_and_grad", "fit_sdf", "closest_points", "closest_points_prioritized"]


def default_sdf_basis(n_segments: int = 5, degree: int = 3, continuity: int = 1) -> Callable[..., Tensor]:
    """The 1-D dictionary ``basis(t, order=j)`` of concatenated Bézier curves (§6.5, :func:`basis.spline`)."""
    return functools.partial(_basis.spline, n_segments=n_segments, degree=degree, continuity=continuity)


@dataclass(frozen=True, eq=False)
class SDF:
    """A field ``f(p) = Ψ((p - lower)/(upper - lower)) w`` (§6.3).

    Attributes:
        w: ``(*S, P)`` weights (``P = K_1 … K_d``), one row per shape.
        lower, upper: ``(*S, d)`` or ``(d,)`` corners of the box that ``[0, 1]^d`` is mapped to.
        basis: the 1-D dictionary ``basis(t, order=j) -> (*T, K)``, or one per input dimension.
    """

    w: Tensor
    lower: Tensor
    upper: Tensor
    basis: Callable[..., Tensor] | Sequence[Callable[..., Tensor]]

    def __post_init__(self) -> None:
        w, lo, hi = self.w, self.lower, self.upper
        if not isinstance(w, Tensor) or not w.dtype.is_floating_point or w.dim() < 1:
            raise TypeError(f"SDF: 'w' must be a floating tensor (*S, P), got "
                            f"{type(w).__name__ if not isinstance(w, Tensor) else (w.dtype, tuple(w.shape))}")
        for name, v in (("lower", lo), ("upper", hi)):
            if not isinstance(v, Tensor) or v.dim() < 1 or v.dtype != w.dtype:
                raise TypeError(f"SDF: '{name}' must be a tensor (*S, d) or (d,) of the dtype of 'w' "
                                f"({w.dtype})")
        if lo.shape[-1] != hi.shape[-1]:
            raise ValueError(f"SDF: 'lower' and 'upper' must have the same last dim, got {tuple(lo.shape)} "
                             f"and {tuple(hi.shape)}")
        b = self.basis
        if not (callable(b) or (isinstance(b, Sequence) and len(b) == lo.shape[-1]
                                and all(callable(f) for f in b))):
            raise TypeError("SDF: 'basis' must be a callable basis(t, order=j) or one such callable per "
                            "input")

    @property
    def dim(self) -> int:
        return self.lower.shape[-1]


class SDFFitResult(NamedTuple):
    """Outcome of :func:`fit_sdf`: the fitted ``sdf`` and the Gauss–Newton status (batch ``*S``):
    ``cost`` (Eq. 58 at the returned ``w``), ``grad_norm`` (``‖2 Jᵀ f‖``, what ``converged`` checks),
    ``converged``, ``iterations``, ``reason`` (codes of :class:`controllers.problem.Reason`)."""

    sdf: SDF
    cost: Tensor
    grad_norm: Tensor
    converged: Tensor
    iterations: Tensor
    reason: Tensor

    @property
    def status(self) -> SolverStatus:
        return SolverStatus(converged=self.converged, iterations=self.iterations, reason=self.reason)


class ClosestPointsResult(NamedTuple):
    """Outcome of :func:`closest_points` / :func:`closest_points_prioritized` (batch ``*B``).

    Attributes:
        p1: ``(*B, d)`` the point of shape 1, in the frame of shape 1 (``t_1``).
        p2: ``(*B, d)`` the point of shape 2, in the frame of shape 2 (``t_2``).
        p2_in_1: ``(*B, d)`` ``A t_2 + b``, the point of shape 2 in the frame of shape 1.
        distance: ``(*B,)`` ``‖A t_2 + b - t_1‖``.
        f1, f2: ``(*B,)`` the SDF values at the points (``0`` on the contours).
        residual: ``(*B,)`` the optimality residual that ``converged`` checks (see each solver).
        converged, iterations, reason: per-element status.
    """

    p1: Tensor
    p2: Tensor
    p2_in_1: Tensor
    distance: Tensor
    f1: Tensor
    f2: Tensor
    residual: Tensor
    converged: Tensor
    iterations: Tensor
    reason: Tensor


# --------------------------------------------------------------------------------------------------
# evaluation
# --------------------------------------------------------------------------------------------------


def _check_sdf(sdf, name: str, fn: str) -> None:
    if not isinstance(sdf, SDF):
        raise TypeError(f"{fn}: '{name}' must be an SDF, got {type(sdf).__name__}")


def _check_points(p, d: int, dtype, name: str, fn: str) -> Tensor:
    if not isinstance(p, Tensor) or p.dim() < 1 or p.shape[-1] != d:
        got = tuple(p.shape) if isinstance(p, Tensor) else type(p).__name__
        raise ValueError(f"{fn}: '{name}' must be points of shape (*B, {d}), got {got}")
    if p.dtype != dtype:
        raise TypeError(f"{fn}: '{name}' has dtype {p.dtype}, expected {dtype} (the SDF weights' dtype)")
    return p


def sdf_value(sdf: SDF, p: Tensor) -> Tensor:
    """``f(p) (*B',)`` at points ``p (*B, d)`` (batch dims broadcast against the SDF's)."""
    _check_sdf(sdf, "sdf", "sdf_value")
    p = _check_points(p, sdf.dim, sdf.w.dtype, "p", "sdf_value")
    u = (p - sdf.lower) / (sdf.upper - sdf.lower)
    return _basis.tensor_eval(u, sdf.w, sdf.basis)


def sdf_value_and_grad(sdf: SDF, p: Tensor) -> tuple[Tensor, Tensor]:
    """``f(p) (*B',)`` and ``∇f(p) (*B', d)`` (Eq. 37, chain rule through the box normalization)."""
    _check_sdf(sdf, "sdf", "sdf_value_and_grad")
    p = _check_points(p, sdf.dim, sdf.w.dtype, "p", "sdf_value_and_grad")
    scale = sdf.upper - sdf.lower
    f, g = _basis.tensor_grad((p - sdf.lower) / scale, sdf.w, sdf.basis)
    return f, g / scale


# --------------------------------------------------------------------------------------------------
# fitting with the eikonal cost (§6.8)
# --------------------------------------------------------------------------------------------------


def _box(lower, upper, d: int, dtype, device, fn: str) -> tuple[Tensor, Tensor]:
    lo = torch.as_tensor(lower, dtype=dtype, device=device)
    hi = torch.as_tensor(upper, dtype=dtype, device=device)
    if lo.dim() < 1 or lo.shape[-1] != d or hi.dim() < 1 or hi.shape[-1] != d:
        raise ValueError(f"{fn}: 'lower' and 'upper' must have shape (*S, {d}) or ({d},), got "
                         f"{tuple(lo.shape)} and {tuple(hi.shape)}")
    if not bool((hi > lo).all()):
        raise ValueError(f"{fn}: 'upper' must be larger than 'lower' in every coordinate")
    return lo, hi


def _grid(n: int, d: int, dtype, device) -> Tensor:
    """``(n^d, d)`` cell centres of a regular grid on ``[0, 1]^d``."""
    c = (torch.arange(n, dtype=dtype, device=device) + 0.5) / n
    return torch.stack(torch.meshgrid(*([c] * d), indexing="ij"), -1).reshape(-1, d)


def fit_sdf(boundary: Tensor, lower, upper, *, basis: Callable[..., Tensor] | Sequence[Callable[..., Tensor]]
            | None = None, distances: Tensor | None = None, eikonal_points: Tensor | None = None,
            eikonal_grid: int = 16, eikonal_weight: float = 0.01, w0: Tensor | None = None,
            tol: float | None = None, max_iter: int = 100, damping: float = 1e-9) -> SDFFitResult:
    """Fit the weights of an SDF to observed distances with the eikonal cost, Eq. (58), by Gauss–Newton.

    ``min_w Σ_m (Ψ(t_m) w - x_m)² + λ Σ_n (∇x_nᵀ ∇x_n - 1)²`` with ``∇x_n = ∇Ψ(t_n) w`` (in the coordinates of
    ``p``), residuals ``f_1 = Ψ(t_m) w - x_m``, ``f_2 = √λ (∇x_nᵀ∇x_n - 1)`` and Jacobians ``J_1 = Ψ(t_m)``,
    ``J_2 = 2 √λ ∇x_nᵀ ∇Ψ(t_n)`` (§6.8), solved by :func:`controllers.optim.gauss_newton` (line search of
    Algorithm 1, optional Levenberg ``damping``), batched over shapes.

    Args:
        boundary: ``(*S, M, d)`` locations ``t_m`` (contour points of each shape).
        lower, upper: ``(*S, d)`` or ``(d,)`` the box of the SDF (should contain the shape with a margin).
        basis: the 1-D dictionary per input (default :func:`default_sdf_basis`).
        distances: ``(*S, M)`` observed distances ``x_m`` (default ``0``: contour points).
        eikonal_points: ``(N, d)`` or ``(*S, N, d)`` locations ``t_n`` of the eikonal term; default the
            centres of an ``eikonal_grid^d`` grid over the box.  It should sample every segment of the
            dictionary a few times (≥ 3 points per segment and input), else weights that no point sees are
            left to the damping and Gauss–Newton crawls.
        eikonal_weight: ``λ ≥ 0``.
        w0: ``(*S, P)`` initial weights; default the least-squares fit of the SDF of a circle/sphere centred
            at the mean of the boundary points with their mean distance to it as radius (negative inside;
            the prior shape of Fig. 15).  The sign convention (negative inside) comes from this start.
        tol, max_iter, damping: of :func:`controllers.optim.gauss_newton` (``converged``: ``‖2Jᵀf‖ ≤ tol``).
            The default ``tol = None`` is dtype-aware (the rule of :func:`~controllers.optim.gauss_newton`):
            ``τ · max(1, ‖2Jᵀf‖ at w0)`` per shape with ``τ = 10⁻⁸`` in float64 and ``10⁻⁴`` in float32, so a
            float32 fit that reaches the float64 optimum to its precision is reported converged.

    Returns:
        :class:`SDFFitResult`.
    """
    fn = "fit_sdf"
    if not isinstance(boundary, Tensor) or not boundary.dtype.is_floating_point or boundary.dim() < 2:
        got = tuple(boundary.shape) if isinstance(boundary, Tensor) else type(boundary).__name__
        raise ValueError(f"{fn}: 'boundary' must be a floating tensor (*S, M, d), got {got}")
    if boundary.shape[-2] == 0:
        raise ValueError(f"{fn}: 'boundary' must hold at least one contour point (*S, M >= 1, d), got "
                         f"{tuple(boundary.shape)}")
    dt, dev = boundary.dtype, boundary.device
    d = boundary.shape[-1]
    S = boundary.shape[:-2]
    lo, hi = _box(lower, upper, d, dt, dev, fn)
    lam = float(eikonal_weight)
    if not math.isfinite(lam) or lam < 0:
        raise ValueError(f"{fn}: 'eikonal_weight' must be a finite number >= 0, got {eikonal_weight!r}")
    if basis is None:
        basis = default_sdf_basis()
    scale = hi - lo
    lo_p, scale_p = lo.unsqueeze(-2), scale.unsqueeze(-2)  # broadcast over the point dim
    Psi_b = _basis.tensor_basis((boundary - lo_p) / scale_p, basis)  # (*S, M, P)
    P = Psi_b.shape[-1]
    if distances is None:
        x_m = torch.zeros(boundary.shape[:-1], dtype=dt, device=dev)
    else:
        if not isinstance(distances, Tensor) or distances.shape != boundary.shape[:-1]:
            got = tuple(distances.shape) if isinstance(distances, Tensor) else type(distances).__name__
            raise ValueError(f"{fn}: 'distances' must have shape {tuple(boundary.shape[:-1])} (*S, M), "
                             f"got {got}")
        if distances.dtype != dt:
            raise TypeError(f"{fn}: 'distances' has dtype {distances.dtype}, expected {dt} (of 'boundary')")
        x_m = distances
    if eikonal_points is None:
        if not isinstance(eikonal_grid, int) or eikonal_grid < 1:
            raise ValueError(f"{fn}: 'eikonal_grid' must be a positive int, got {eikonal_grid!r}")
        u_e = _grid(eikonal_grid, d, dt, dev)
        e_pts = lo_p + scale_p * u_e  # (*S?, N, d)
    else:
        e_pts = _check_points(eikonal_points, d, dt, "eikonal_points", fn)
        if e_pts.dim() < 2:
            raise ValueError(f"{fn}: 'eikonal_points' must have shape (N, {d}) or (*S, N, {d})")
        u_e = (e_pts - lo_p) / scale_p
    G_e = _basis.tensor_basis_grad(u_e, basis) / scale_p.unsqueeze(-1)  # (*, N, d, P): ∇Ψ in p-coordinates
    Psi_e = _basis.tensor_basis(u_e, basis)  # for the initial circle fit
    if w0 is None:
        c = boundary.mean(-2, keepdim=True)  # (*S, 1, d)
        r = torch.linalg.vector_norm(boundary - c, dim=-1).mean(-1, keepdim=True)  # (*S, 1)
        target = torch.linalg.vector_norm(e_pts - c, dim=-1) - r  # (*S, N)
        A = torch.cat([Psi_e.expand(*target.shape, P), Psi_b.expand(*S, -1, P)], -2)
        y = torch.cat([target, torch.zeros(*S, Psi_b.shape[-2], dtype=dt, device=dev)], -1)
        w0 = _basis.fit(A, y, ridge=1e-8)
    elif not isinstance(w0, Tensor) or w0.shape[-1] != P:
        got = tuple(w0.shape) if isinstance(w0, Tensor) else type(w0).__name__
        raise ValueError(f"{fn}: 'w0' must have shape (*S, {P}), got {got}")
    elif w0.dtype != dt:
        raise TypeError(f"{fn}: 'w0' has dtype {w0.dtype}, expected {dt} (that of 'boundary')")
    batch = _broadcast(fn, S, w0.shape[:-1], G_e.shape[:-3])
    w0 = w0.expand(*batch, P).clone()
    sq = math.sqrt(lam)

    def _grad_x(w: Tensor) -> Tensor:  # ∇x_n (*S, N, d)
        return (G_e @ w[..., None, :, None]).squeeze(-1)

    def residual(w: Tensor) -> Tensor:
        f1 = (Psi_b @ w.unsqueeze(-1)).squeeze(-1) - x_m
        gx = _grad_x(w)
        f2 = sq * ((gx * gx).sum(-1) - 1.0)
        return torch.cat([f1.expand(*batch, -1), f2.expand(*batch, -1)], -1)

    def jacobian(w: Tensor) -> Tensor:
        gx = _grad_x(w)
        J2 = 2.0 * sq * (gx.unsqueeze(-2) @ G_e).squeeze(-2)  # (*S, N, P)
        return torch.cat([Psi_b.expand(*batch, -1, P), J2.expand(*batch, -1, P)], -2)

    res: OptimResult = gauss_newton(residual, w0, tol=tol, max_iter=max_iter, jacobian=jacobian,
                                    damping=damping)
    sdf = SDF(w=res.x, lower=lo, upper=hi, basis=basis)
    return SDFFitResult(sdf=sdf, cost=res.cost, grad_norm=res.grad_norm, converged=res.converged,
                        iterations=res.iterations, reason=res.reason)


# --------------------------------------------------------------------------------------------------
# closest points between two shapes (§6.4, Eq. 40-44)
# --------------------------------------------------------------------------------------------------


def _pair_inputs(sdf1, sdf2, A, b, p1_0, p2_0, fn: str):
    _check_sdf(sdf1, "sdf1", fn)
    _check_sdf(sdf2, "sdf2", fn)
    d = sdf1.dim
    if sdf2.dim != d:
        raise ValueError(f"{fn}: both SDFs must have the same input dimension, got {d} and {sdf2.dim}")
    dt = sdf1.w.dtype
    if sdf2.w.dtype != dt:
        raise TypeError(f"{fn}: 'sdf2' has dtype {sdf2.w.dtype} but 'sdf1' has {dt}")
    if not isinstance(A, Tensor) or A.dim() < 2 or A.shape[-2:] != (d, d):
        raise ValueError(f"{fn}: 'A' must be a rotation matrix (*B, {d}, {d}), got "
                         f"{tuple(A.shape) if isinstance(A, Tensor) else type(A).__name__}")
    b = _check_points(b, d, dt, "b", fn)
    if A.dtype != dt:
        raise TypeError(f"{fn}: 'A' has dtype {A.dtype}, expected {dt}")
    c1 = 0.5 * (sdf1.lower + sdf1.upper)
    c2 = (A @ (0.5 * (sdf2.lower + sdf2.upper)).unsqueeze(-1)).squeeze(-1) + b  # in frame 1
    mid = 0.5 * (c1 + c2)
    if p1_0 is None:
        p1_0 = mid
    if p2_0 is None:
        p2_0 = (A.mT @ (mid - b).unsqueeze(-1)).squeeze(-1)
    p1_0 = _check_points(p1_0, d, dt, "p1_0", fn)
    p2_0 = _check_points(p2_0, d, dt, "p2_0", fn)
    batch = _broadcast(fn, sdf1.w.shape[:-1], sdf2.w.shape[:-1], sdf1.lower.shape[:-1],
                                   sdf2.lower.shape[:-1], A.shape[:-2], b.shape[:-1], p1_0.shape[:-1],
                                   p2_0.shape[:-1])
    return d, batch, b, p1_0.expand(*batch, d), p2_0.expand(*batch, d)


def closest_points(sdf1: SDF, sdf2: SDF, A: Tensor, b: Tensor, *, p1_0: Tensor | None = None,
                   p2_0: Tensor | None = None, weight: float = 0.1, tol: float = 1e-10, max_iter: int = 100,
                   damping: float = 0.1) -> ClosestPointsResult:
    """Two contour points with closest distance by Gauss–Newton on Eq. (40)-(42).

    ``t = [t_1; t_2]`` (each in its shape's frame), residuals ``[f_1(t_1); f_2(t_2); √β (A t_2 + b - t_1)]``
    with the Jacobian of Eq. (41) (``β = weight``; the seed writes ``β = 1``), solved by
    :func:`controllers.optim.gauss_newton` with the Levenberg ``damping`` (``converged``: ``‖2Jᵀf‖ ≤ tol``,
    reported as ``residual``).

    This is a penalty formulation: the three terms are traded off, so for shapes a distance ``d`` apart each
    point stops about ``a = β d / (1 + 2β)`` off its contour (for locally straight contours with
    ``‖∇f‖ = 1``), and the returned ``distance`` is about ``d - 2a``; :func:`closest_points_prioritized` puts
    the points exactly on the contours.  ``J`` is square, so the undamped step is Newton's step towards the
    intersection of the two linearized contours, which is ill-conditioned when the contours are nearly
    parallel (facing each other), and singular at a minimum with a non-zero residual (separated shapes:
    ``Jᵀf = 0`` with ``f ≠ 0``), where Gauss–Newton only converges linearly: keep ``damping > 0`` and expect
    tens to hundreds of iterations.

    Args:
        sdf1, sdf2: the two shapes (2-D or 3-D SDFs with the same input dimension ``d``).
        A, b: ``(*B, d, d)``, ``(*B, d)``: a point ``t_2`` of shape 2 is ``A t_2 + b`` in the frame of
            shape 1.
        p1_0, p2_0: initial points (default: the midpoint of the two box centres, in each frame).
    """
    fn = "closest_points"
    d, batch, b, p1_0, p2_0 = _pair_inputs(sdf1, sdf2, A, b, p1_0, p2_0, fn)
    beta = float(weight)
    if not math.isfinite(beta) or beta <= 0:
        raise ValueError(f"{fn}: 'weight' must be a positive number, got {weight!r}")
    sb = math.sqrt(beta)
    eye = torch.eye(d, dtype=b.dtype, device=b.device)

    def parts(t):
        t1, t2 = t[..., :d], t[..., d:]
        f1, g1 = sdf_value_and_grad(sdf1, t1)
        f2, g2 = sdf_value_and_grad(sdf2, t2)
        r = (A @ t2.unsqueeze(-1)).squeeze(-1) + b - t1
        return f1, g1, f2, g2, r

    def residual(t):
        f1, _, f2, _, r = parts(t)
        return torch.cat([f1.unsqueeze(-1), f2.unsqueeze(-1), sb * r], -1).expand(*batch, 2 + d)

    def jacobian(t):
        _, g1, _, g2, _ = parts(t)
        z = torch.zeros_like(g1)
        row1 = torch.cat([g1, z], -1).unsqueeze(-2)
        row2 = torch.cat([z, g2], -1).unsqueeze(-2)
        J3 = sb * torch.cat([-eye.expand(*batch, d, d), A.expand(*batch, d, d)], -1)
        return torch.cat([row1.expand(*batch, 1, 2 * d), row2.expand(*batch, 1, 2 * d), J3], -2)

    res = gauss_newton(residual, torch.cat([p1_0, p2_0], -1), tol=tol, max_iter=max_iter, jacobian=jacobian,
                       damping=damping)
    f1, _, f2, _, r = parts(res.x)
    t1, t2 = res.x[..., :d], res.x[..., d:]
    return ClosestPointsResult(p1=t1, p2=t2, p2_in_1=t1 + r, distance=torch.linalg.vector_norm(r, dim=-1),
                               f1=f1, f2=f2, residual=res.grad_norm, converged=res.converged,
                               iterations=res.iterations, reason=res.reason)


def _proj(v1: Tensor, v2: Tensor, g1: Tensor, n1: Tensor, g2: Tensor, n2: Tensor) -> tuple[Tensor, Tensor]:
    """``N_12 [v1; v2]`` with ``N_12 = I - J_12† J_12``: remove the components along ``∇f_1``, ``∇f_2``
    (``n_i = ∇f_i / ‖∇f_i‖²``)."""
    return v1 - n1 * (g1 * v1).sum(-1, keepdim=True), v2 - n2 * (g2 * v2).sum(-1, keepdim=True)


def _broadcast(fn: str, *shapes) -> tuple[int, ...]:
    """``torch.broadcast_shapes`` without its first-call import cost."""
    nd = max(len(s) for s in shapes)
    out = []
    for i in range(nd):
        dims = {s[len(s) - nd + i] for s in shapes if len(s) - nd + i >= 0} - {1}
        if len(dims) > 1:
            raise ValueError(f"{fn}: the batch shapes of the inputs {[tuple(s) for s in shapes]} do not "
                             f"broadcast")
        out.append(dims.pop() if dims else 1)
    return tuple(out)


def _sdf_hessian(sdf: SDF, p: Tensor) -> tuple[Tensor, Tensor]:
    """``∇f(p) (*B, d)`` and ``∇²f(p) (*B, d, d)`` (autograd through the analytic gradient, Eq. 37)."""
    with torch.enable_grad():
        x = p.detach().requires_grad_(True)
        _, g = sdf_value_and_grad(sdf, x)
        g = g.expand(*x.shape)
        rows = [torch.autograd.grad(g[..., j].sum(), x, retain_graph=True)[0] for j in range(x.shape[-1])]
    return g.detach(), torch.stack(rows, -2)


def _second_order_ok(sdf1: SDF, sdf2: SDF, A: Tensor, t1: Tensor, t2: Tensor, r: Tensor, active: Tensor
                     ) -> Tensor:
    """``(*B,)`` bool: the Hessian of the Lagrangian of ``min ½‖r‖²`` s.t. ``f_1 = f_2 = 0`` is positive
    semi-definite on the tangent space of the contours (second-order necessary condition of a minimum)."""
    d = t1.shape[-1]
    dt, dev = t1.dtype, t1.device
    g1, H1 = _sdf_hessian(sdf1, t1)
    g2, H2 = _sdf_hessian(sdf2, t2)
    tiny = torch.finfo(dt).tiny
    n1 = (g1 * g1).sum(-1).clamp_min(tiny)
    n2 = (g2 * g2).sum(-1).clamp_min(tiny)
    Atr = (A.mT @ r.unsqueeze(-1)).squeeze(-1)
    mu1 = -(r * g1).sum(-1) / n1
    mu2 = (Atr * g2).sum(-1) / n2
    eye = torch.eye(d, dtype=dt, device=dev)
    top = torch.cat([eye - mu1[..., None, None] * H1, -A], -1)
    bot = torch.cat([-A.mT, A.mT @ A - mu2[..., None, None] * H2], -1)
    HL = torch.cat([top, bot], -2)
    HL = 0.5 * (HL + HL.mT)
    z = torch.zeros_like(H1)
    # N_12: projector onto the tangent space; the normal directions get a large positive stand-in
    P1 = eye - g1.unsqueeze(-1) * g1.unsqueeze(-2) / n1[..., None, None]
    P2 = eye - g2.unsqueeze(-1) * g2.unsqueeze(-2) / n2[..., None, None]
    N = torch.cat([torch.cat([P1, z], -1), torch.cat([z, P2], -1)], -2)
    scale = 1.0 + torch.linalg.matrix_norm(HL)
    eye2 = torch.eye(2 * d, dtype=dt, device=dev)
    M = N @ HL @ N + scale[..., None, None] * (eye2 - N)
    M = 0.5 * (M + M.mT)
    good = active & torch.isfinite(M).flatten(-2).all(-1)
    M = torch.where(good[..., None, None], M, eye2)
    lam = torch.linalg.eigvalsh(M)[..., 0]
    return good & (lam >= -math.sqrt(torch.finfo(dt).eps) * scale)


def closest_points_prioritized(sdf1: SDF, sdf2: SDF, A: Tensor, b: Tensor, *, p1_0: Tensor | None = None,
                               p2_0: Tensor | None = None, alpha1: float = 1.0, alpha2: float = 0.5,
                               tol: float = 1e-10, max_iter: int = 200) -> ClosestPointsResult:
    """Two contour points with closest distance by the prioritized Gauss–Newton step of Eq. (43)-(44).

    ``t ← t - α_1 J_12† [f_1; f_2] - α_2 N_12 J_3† (A t_2 + b - t_1)`` with ``J_12 = blkdiag(∇f_1ᵀ, ∇f_2ᵀ)``,
    ``N_12 = I - J_12† J_12`` and ``J_3 = [-I, A]``: the points are moved onto the contours first, and closer
    to each other only within the nullspace of that task.  (The seed prints ``+ α_2 …``; the step that
    decreases ``½‖A t_2 + b - t_1‖²`` is the one with ``-``, used here.)

    ``converged`` where, at the returned points, ``|f_1|, |f_2| ≤ tol`` and the projected gradient of the
    secondary task ``‖N_12 J_3ᵀ (A t_2 + b - t_1)‖ ≤ tol`` (reported as ``residual``, the max of the three):
    the points are on the contours and the segment between them is normal to both — a stationary pair of
    ``½‖A t_2 + b - t_1‖²`` subject to ``f_1 = f_2 = 0`` — *and* the second-order condition of a local minimum
    holds there: the Hessian of the Lagrangian
    ``[[I, -A], [-Aᵀ, AᵀA]] - blkdiag(μ_1 ∇²f_1, μ_2 ∇²f_2)`` (multipliers ``μ_1 = -rᵀ∇f_1/‖∇f_1‖²``,
    ``μ_2 = rᵀA∇f_2/‖∇f_2‖²``, ``r = A t_2 + b - t_1``; ``∇²f`` by autograd through the basis) is positive
    semi-definite on the tangent space of the two contours (eigenvalues ``≥ -√eps (1 + ‖·‖)``).  A
    stationary pair that fails it (a saddle or a maximum of the distance, e.g. two far sides facing away) is
    reported ``NOT_A_MINIMUM`` (not converged).  ``reason``: ``CONVERGED``, ``NOT_A_MINIMUM``,
    ``MAX_ITERATIONS``, ``NONFINITE_INPUT`` or ``DIVERGED`` (non-finite values at an iterate; that element
    stops there).  Arguments as :func:`closest_points`.
    """
    fn = "closest_points_prioritized"
    d, batch, b, p1, p2 = _pair_inputs(sdf1, sdf2, A, b, p1_0, p2_0, fn)
    for name, v in (("alpha1", alpha1), ("alpha2", alpha2)):
        if not isinstance(v, (int, float)) or not 0 < v <= 1:
            raise ValueError(f"{fn}: '{name}' must be in (0, 1], got {v!r}")
    if not isinstance(max_iter, int) or max_iter < 0:
        raise ValueError(f"{fn}: 'max_iter' must be a non-negative int, got {max_iter!r}")
    dev = b.device
    Ab = A.expand(*batch, d, d)
    eye = torch.eye(d, dtype=b.dtype, device=dev)
    # J_3 J_3ᵀ = I + A Aᵀ (2 I for a rotation); J_3† = J_3ᵀ (J_3 J_3ᵀ)⁻¹
    M = torch.linalg.inv(eye + Ab @ Ab.mT)
    t1, t2 = p1.clone(), p2.clone()
    finite_in = torch.isfinite(t1).all(-1) & torch.isfinite(t2).all(-1)
    reason = torch.where(finite_in, int(Reason.MAX_ITERATIONS), int(Reason.NONFINITE_INPUT))
    active = finite_in.clone()
    iterations = torch.zeros(batch, dtype=torch.int64, device=dev)
    tiny = torch.finfo(b.dtype).tiny
    for k in range(max_iter + 1):
        f1, g1 = sdf_value_and_grad(sdf1, t1)
        f2, g2 = sdf_value_and_grad(sdf2, t2)
        f1, f2 = f1.expand(batch), f2.expand(batch)
        g1, g2 = g1.expand(*batch, d), g2.expand(*batch, d)
        r = (Ab @ t2.unsqueeze(-1)).squeeze(-1) + b - t1
        n1 = g1 / (g1 * g1).sum(-1, keepdim=True).clamp_min(tiny)  # ∇f₁ / ‖∇f₁‖² = (∇f₁ᵀ)†
        n2 = g2 / (g2 * g2).sum(-1, keepdim=True).clamp_min(tiny)

        pg1, pg2 = _proj(-r, (Ab.mT @ r.unsqueeze(-1)).squeeze(-1), g1, n1, g2, n2)  # N_12 J_3ᵀ r
        resid = torch.stack([f1.abs(), f2.abs(), torch.linalg.vector_norm(torch.cat([pg1, pg2], -1), dim=-1)],
                            -1).amax(-1)
        ok = torch.isfinite(resid)
        reason = torch.where(active & ~ok, int(Reason.DIVERGED), reason)
        active = active & ok
        done = active & (resid <= tol)
        reason = torch.where(done, int(Reason.CONVERGED), reason)
        active = active & ~done
        if k == max_iter or not bool(active.any()):
            break
        y = (M @ r.unsqueeze(-1)).squeeze(-1)  # (J_3 J_3ᵀ)⁻¹ r
        s1, s2 = _proj(-y, (Ab.mT @ y.unsqueeze(-1)).squeeze(-1), g1, n1, g2, n2)  # N_12 J_3† r
        d1 = -alpha1 * n1 * f1.unsqueeze(-1) - alpha2 * s1
        d2 = -alpha1 * n2 * f2.unsqueeze(-1) - alpha2 * s2
        step_ok = active & torch.isfinite(d1).all(-1) & torch.isfinite(d2).all(-1)
        reason = torch.where(active & ~step_ok, int(Reason.DIVERGED), reason)
        active = step_ok
        t1 = torch.where(active[..., None], t1 + d1, t1)
        t2 = torch.where(active[..., None], t2 + d2, t2)
        iterations = iterations + active.to(torch.int64)
    f1 = sdf_value(sdf1, t1).expand(batch)
    f2 = sdf_value(sdf2, t2).expand(batch)
    r = (Ab @ t2.unsqueeze(-1)).squeeze(-1) + b - t1
    stat = reason == int(Reason.CONVERGED)
    if bool(stat.any()):
        second = _second_order_ok(sdf1, sdf2, Ab, t1, t2, r, stat)
        reason = torch.where(stat & ~second, int(Reason.NOT_A_MINIMUM), reason)
    return ClosestPointsResult(p1=t1, p2=t2, p2_in_1=t1 + r, distance=torch.linalg.vector_norm(r, dim=-1),
                               f1=f1, f2=f2, residual=resid, converged=reason == int(Reason.CONVERGED),
                               iterations=iterations, reason=reason)
