"""Planar kinematic chains: forward kinematics, Jacobians and inverse kinematics (seed 004 §4-§5).

Joint angles ``x = q (*B, k)`` (relative, ``q = 0`` stretches the chain along ``+x``, the convention of
:class:`controllers.systems.PlanarArm`), link lengths ``ℓ`` (a float, a sequence of ``k`` floats or a
tensor ``(*P, k)``/``(*P, 1)`` broadcasting against the batch), ``L`` the lower-triangular matrix of ones
(``Lq`` are the absolute link angles, a cumulative sum)::

    f^ee  = [ℓᵀ cos(Lq), ℓᵀ sin(Lq), 1ᵀ q]                                   (§4)
    f̃^ee = [L diag(ℓ) cos(Lq), L diag(ℓ) sin(Lq), Lq]ᵀ   every articulation (Eq. 18)
    J     = [-sin(Lq)ᵀ diag(ℓ) L;  cos(Lq)ᵀ diag(ℓ) L;  1ᵀ]                     (§5)

Inverse kinematics (:func:`planar_ik`) is Gauss–Newton on the residual ``f(q) = f^ee(q) - μ`` (Eq. 19,
``q ← q - J⁺ f``), the orientation part being the geodesic residual ``wrap(θ - θ*)`` (the logarithmic map of
SO(2)), optionally expressed in an object frame ``U`` (Eq. 20: ``f = Uᵀ (f^ee - μ)``, ``J = Uᵀ J^ee``) and
weighted there.  :func:`task_priority_ik` adds a secondary task in the null space ``N = I - J⁺ J`` of the
primary one (Eq. 22, §5.2); :func:`nullspace_projector` gives ``N`` from the SVD (§5.2).
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from controllers._validate import all_finite
from controllers.ik import _DampedPinv
from controllers.problem import Reason, SolverStatus
from torchlie._batch import broadcast_shapes

__all__ = [
    "PlanarIKResult",
    "TaskPriorityIKResult",
    "damped_pinv",
    "nullspace_projector",
    "planar_fk",
    "planar_fk_links",
    "planar_ik",
    "planar_jacobian",
    "planar_residual",
    "task_priority_ik",
    "task_priority_ik_step",
]


# --------------------------------------------------------------------------------------------------
# argument checks
# --------------------------------------------------------------------------------------------------

def _check_q(q, fn: str, name: str = "q") -> Tensor:
    if not isinstance(q, Tensor) or not q.is_floating_point():
        what = f"a {q.dtype} tensor" if isinstance(q, Tensor) else type(q).__name__
        raise TypeError(f"{fn}: argument '{name}' must be a floating-point torch.Tensor (*B, k), got {what}")
    if q.ndim < 1 or q.shape[-1] < 1:
        raise ValueError(f"{fn}: argument '{name}' must have shape (*B, k) with k >= 1 joints, "
                         f"got {tuple(q.shape)}")
    return q


def _lengths(lengths, like: Tensor, fn: str) -> Tensor:
    """Link lengths as a tensor ``(*P, k)`` in the dtype/device of ``like (*B, k)``."""
    k = like.shape[-1]
    if isinstance(lengths, Tensor):
        if lengths.dtype != like.dtype:
            raise TypeError(f"{fn}: argument 'lengths' has dtype {lengths.dtype} but q has {like.dtype}; "
                            "cast one of them explicitly")
        if lengths.ndim > 0 and lengths.shape[-1] not in (1, k):
            raise ValueError(f"{fn}: argument 'lengths' must have shape (*P, {k}) or (*P, 1) for {k} joints, "
                             f"got {tuple(lengths.shape)}")
        lv = lengths.to(like.device)
        return lv.expand(k) if lv.ndim == 0 else lv.expand(*lv.shape[:-1], k)
    if isinstance(lengths, numbers.Real) and not isinstance(lengths, bool):
        return torch.full((k,), float(lengths), dtype=like.dtype, device=like.device)
    if isinstance(lengths, Sequence) and all(isinstance(v, numbers.Real) for v in lengths):
        if len(lengths) != k:
            raise ValueError(f"{fn}: argument 'lengths' has {len(lengths)} values for {k} joints")
        return torch.tensor([float(v) for v in lengths], dtype=like.dtype, device=like.device)
    raise TypeError(f"{fn}: argument 'lengths' must be a float, a sequence of {k} floats or a tensor "
                    f"(*P, {k}), got {type(lengths).__name__}")


def _angle_arg(v, name: str, like: Tensor, fn: str) -> Tensor | None:
    """An optional angle: ``None``, a float or a tensor ``(*B,)`` of ``like``'s dtype."""
    if v is None:
        return None
    if isinstance(v, Tensor):
        if v.dtype != like.dtype:
            raise TypeError(f"{fn}: argument '{name}' has dtype {v.dtype}, expected {like.dtype}")
        return v.to(like.device)
    if isinstance(v, numbers.Real) and not isinstance(v, bool):
        return torch.tensor(float(v), dtype=like.dtype, device=like.device)
    raise TypeError(f"{fn}: argument '{name}' must be None, a float or a tensor (*B,) of angles, "
                    f"got {type(v).__name__}")


def _wrap(a: Tensor) -> Tensor:
    """Angle to ``(-π, π]``: the logarithmic map of SO(2) applied to a difference of angles."""
    return torch.atan2(torch.sin(a), torch.cos(a))


# --------------------------------------------------------------------------------------------------
# forward kinematics and Jacobians (§4, §5)
# --------------------------------------------------------------------------------------------------

def planar_fk_links(q: Tensor, lengths) -> Tensor:
    """Pose ``[x, y, θ]`` of the tip of every link ``(*B, k, 3)`` (Eq. 18, one row per articulation).

    Row ``j`` is ``[Σ_{i≤j} ℓ_i cos φ_i, Σ_{i≤j} ℓ_i sin φ_i, φ_j]`` with ``φ = Lq`` the absolute angles;
    the last row is :func:`planar_fk`.  Equal to :meth:`controllers.systems.PlanarArm.fk` without its base
    row, plus the angles.  Batch dims of ``q (*B, k)`` and ``lengths`` broadcast; differentiable.
    """
    fn = "planar_fk_links"
    q = _check_q(q, fn)
    ell = _lengths(lengths, q, fn)
    phi = q.cumsum(-1)
    px = (ell * torch.cos(phi)).cumsum(-1)
    py = (ell * torch.sin(phi)).cumsum(-1)
    return torch.stack([px, py, phi.expand_as(px)], -1)


def planar_fk(q: Tensor, lengths) -> Tensor:
    """End-effector pose ``f^ee = [ℓᵀ cos(Lq), ℓᵀ sin(Lq), 1ᵀ q]`` ``(*B, 3)`` (§4) from ``q (*B, k)``."""
    return planar_fk_links(q, lengths)[..., -1, :]


def planar_jacobian(q: Tensor, lengths, link: int = -1) -> Tensor:
    """Jacobian ``∂f̃_link / ∂q`` ``(*B, 3, k)`` of the pose of link ``link``'s tip (default: end effector).

    Column ``a`` is ``[-Σ_{a≤i≤j} ℓ_i sin φ_i, Σ_{a≤i≤j} ℓ_i cos φ_i, 1]`` for ``a ≤ j = link`` and zero for
    the joints after that link (they do not move it); for the end effector this is
    ``[-sin(Lq)ᵀ diag(ℓ) L; cos(Lq)ᵀ diag(ℓ) L; 1ᵀ]`` (§5).  Rows: ``x, y, θ`` (``[..., :2, :]``: position).
    Equal to :meth:`controllers.systems.PlanarArm.ee_jacobian` in its position rows.
    """
    fn = "planar_jacobian"
    q = _check_q(q, fn)
    k = q.shape[-1]
    if isinstance(link, bool) or not isinstance(link, int) or not -k <= link < k:
        raise ValueError(f"{fn}: argument 'link' must be an int in [-{k}, {k}) for {k} joints, got {link!r}")
    j = link % k
    ell = _lengths(lengths, q, fn)
    phi = q.cumsum(-1)
    upto = torch.arange(k, device=q.device) <= j  # links 0..j move the tip of link j
    lx = torch.where(upto, -ell * torch.sin(phi), 0.0)
    ly = torch.where(upto, ell * torch.cos(phi), 0.0)
    jx = lx.flip(-1).cumsum(-1).flip(-1)
    jy = ly.flip(-1).cumsum(-1).flip(-1)
    jt = upto.to(q.dtype).expand_as(jx)
    return torch.stack([jx, jy, jt], -2)


# --------------------------------------------------------------------------------------------------
# pseudo-inverse and null space (§5.2)
# --------------------------------------------------------------------------------------------------

def _check_J(J, fn: str) -> Tensor:
    if not isinstance(J, Tensor) or not J.is_floating_point():
        raise TypeError(f"{fn}: argument 'J' must be a floating-point torch.Tensor (*B, m, n)")
    if J.ndim < 2:
        raise ValueError(f"{fn}: argument 'J' must have shape (*B, m, n), got {tuple(J.shape)}")
    return J


def _rank_mask(S: Tensor, m: int, n: int, rcond: float | None) -> Tensor:
    tol = max(m, n) * torch.finfo(S.dtype).eps if rcond is None else rcond
    return S > tol * S.amax(-1, keepdim=True)


def _standin(J: Tensor) -> tuple[Tensor, Tensor | None]:
    """``J`` with its non-finite batch elements replaced by zeros (so no SVD sees NaN), and their mask."""
    bad = ~torch.isfinite(J).flatten(-2).all(-1)
    if not bool(bad.any()):
        return J, None
    return torch.where(bad[..., None, None], 0.0, J), bad


def _nan_out(M: Tensor, bad: Tensor | None) -> Tensor:
    return M if bad is None else torch.where(bad[..., None, None], math.nan, M)


def damped_pinv(J: Tensor, damping: float = 0.0, rcond: float | None = None) -> Tensor:
    """Damped pseudo-inverse ``J⁺_λ = V Σ (Σ² + λ²)⁻¹ Uᵀ = Jᵀ (J Jᵀ + λ² I)⁻¹`` ``(*B, n, m)``.

    ``J (*B, m, n)``.  ``damping = λ = 0`` gives the Moore–Penrose pseudo-inverse ``J⁺`` of Eq. 19, the
    singular values at most ``rcond · σ_max`` (default ``max(m, n) · eps``, as :func:`torch.linalg.pinv`)
    dropped: finite at a singular ``J``.  ``λ > 0`` bounds the gain ``σ / (σ² + λ²) ≤ 1 / (2λ)`` near
    singularities.  An element of the batch with a non-finite entry gives NaN (only that element).
    """
    fn = "damped_pinv"
    J = _check_J(J, fn)
    if not (math.isfinite(damping) and damping >= 0):
        raise ValueError(f"{fn}: argument 'damping' must be a finite float >= 0, got {damping!r}")
    J, bad = _standin(J)
    m, n = J.shape[-2:]
    U, S, Vh = torch.linalg.svd(J, full_matrices=False)
    keep = _rank_mask(S, m, n, rcond)
    if damping > 0:
        gain = S / (S * S + damping * damping)
    else:
        gain = torch.where(keep, 1.0 / torch.where(keep, S, 1.0), 0.0)
    return _nan_out((Vh.mT * gain[..., None, :]) @ U.mT, bad)


def nullspace_projector(J: Tensor, rcond: float | None = None, method: str = "svd") -> Tensor:
    """Null-space projector ``N = I - J⁺ J`` ``(*B, n, n)`` of ``J (*B, m, n)`` (§5.2).

    ``method="svd"`` (default, the numerically robust form of §5.2): with the SVD ``J⁺ = U Σ Vᵀ``,
    ``N = Ũ Ũᵀ`` where ``Ũ`` are the columns of ``U`` whose singular values are zero (below
    ``rcond · σ_max``) — computed as ``I - U_r U_rᵀ`` with the complementary columns ``U_r`` from the thin
    SVD of ``J`` (``U`` of ``J⁺`` is ``V`` of ``J``), which is the same matrix and differentiable where the
    kept singular values are distinct.  ``method="pinv"``: ``I - J⁺ J`` with :func:`damped_pinv` (``λ = 0``).
    ``N`` is symmetric and idempotent, ``J N = 0``; zero when ``J`` has full column rank.  An element of the
    batch with a non-finite entry gives NaN (only that element).
    """
    fn = "nullspace_projector"
    J = _check_J(J, fn)
    m, n = J.shape[-2:]
    eye = torch.eye(n, dtype=J.dtype, device=J.device)
    if method == "pinv":
        return eye - damped_pinv(J, 0.0, rcond) @ J
    if method != "svd":
        raise ValueError(f"{fn}: argument 'method' must be 'svd' or 'pinv', got {method!r}")
    J, bad = _standin(J)
    _, S, Vh = torch.linalg.svd(J, full_matrices=False)
    keep = _rank_mask(S, m, n, rcond).to(J.dtype)
    Vr = Vh * keep[..., :, None]
    return _nan_out(eye - Vr.mT @ Vr, bad)


# --------------------------------------------------------------------------------------------------
# residuals (Eq. 19, 20)
# --------------------------------------------------------------------------------------------------

def planar_residual(q: Tensor, lengths, target: Tensor, orientation: Tensor | float | None = None,
                    object_angle: Tensor | float | None = None) -> tuple[Tensor, Tensor]:
    """IK residual ``f (*B, p)`` and its Jacobian ``J (*B, p, k)`` (Eq. 19-20), ``p = 2`` or ``3``.

    ``f = Uᵀ (f^ee_xy(q) - μ)`` and ``J = Uᵀ J^ee_xy`` (Eq. 20), ``U`` the rotation by ``object_angle`` (the
    object/landmark frame; the robot frame, ``U = I``, when ``None``) and ``μ = target (*B, 2)``; with
    ``orientation = θ* (*B,)`` a third row ``wrap(θ(q) - θ*)`` (the geodesic residual ``Log``, frame
    invariant in the plane) with Jacobian row ``1ᵀ``.
    """
    fn = "planar_residual"
    q = _check_q(q, fn)
    if not isinstance(target, Tensor) or target.dtype != q.dtype or target.ndim < 1 or target.shape[-1] != 2:
        raise ValueError(f"{fn}: argument 'target' must be a {q.dtype} tensor (*B, 2), got "
                         f"{tuple(target.shape) if isinstance(target, Tensor) else type(target).__name__}")
    ori = _angle_arg(orientation, "orientation", q, fn)
    obj = _angle_arg(object_angle, "object_angle", q, fn)
    pose = planar_fk(q, lengths)
    J = planar_jacobian(q, lengths)
    fp, Jp = pose[..., :2] - target.to(q.device), J[..., :2, :]
    if obj is not None:  # Uᵀ v with U = [[c, -s], [s, c]]
        c, s = torch.cos(obj)[..., None], torch.sin(obj)[..., None]
        fp = torch.stack([c[..., 0] * fp[..., 0] + s[..., 0] * fp[..., 1],
                          -s[..., 0] * fp[..., 0] + c[..., 0] * fp[..., 1]], -1)
        Jp = torch.stack([c * Jp[..., 0, :] + s * Jp[..., 1, :], -s * Jp[..., 0, :] + c * Jp[..., 1, :]], -2)
    if ori is None:
        return fp, Jp
    fo = _wrap(pose[..., 2] - ori)
    bs = broadcast_shapes(fp.shape[:-1], fo.shape)
    f = torch.cat([fp.expand(*bs, 2), fo.expand(bs)[..., None]], -1)
    Jf = torch.cat([Jp.expand(*bs, *Jp.shape[-2:]), J[..., 2:, :].expand(*bs, 1, J.shape[-1])], -2)
    return f, Jf


def _weight_factor(weight, p: int, like: Tensor, fn: str) -> Tensor | None:
    """``R (*B, p, p)`` with ``W = Rᵀ R`` from a weight ``(*B, p)`` (diagonal) or ``(*B, p, p)`` (SPD)."""
    if weight is None:
        return None
    if not isinstance(weight, Tensor) or weight.dtype != like.dtype:
        raise TypeError(f"{fn}: argument 'weight' must be a {like.dtype} tensor (*B, {p}) or (*B, {p}, {p})")
    weight = weight.to(like.device)
    if weight.ndim >= 2 and weight.shape[-2:] == (p, p):
        if not bool(torch.allclose(weight, weight.mT)):
            raise ValueError(f"{fn}: argument 'weight' (*B, {p}, {p}) must be symmetric")
        L, info = torch.linalg.cholesky_ex(weight)
        if bool((info != 0).any()):
            raise ValueError(f"{fn}: argument 'weight' (*B, {p}, {p}) must be positive definite "
                             "(use the diagonal form (*B, p) for zero weights)")
        return L.mT
    if weight.ndim >= 1 and weight.shape[-1] == p:
        if bool((weight < 0).any()) or not bool(torch.isfinite(weight).all()):
            raise ValueError(f"{fn}: argument 'weight' (*B, {p}) must be finite and >= 0")
        return torch.diag_embed(torch.sqrt(weight))
    raise ValueError(f"{fn}: argument 'weight' must have shape (*B, {p}) or (*B, {p}, {p}) (p = 2 for "
                     f"position, 3 with orientation), got {tuple(weight.shape)}")


def _pinv_apply(J: Tensor, v: Tensor, lam: float | Tensor, z: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """``(J⁺_λ v, (I - J⁺ J) z)`` with finite, closed-form derivatives (:mod:`controllers.ik`)."""
    bs = broadcast_shapes(J.shape[:-2], v.shape[:-1])
    lam_t = lam.expand(bs) if isinstance(lam, Tensor) else torch.full(bs, float(lam), dtype=J.dtype,
                                                                        device=J.device)
    if z is None:
        z = torch.zeros((), dtype=J.dtype, device=J.device).expand(J.shape[-1])
    return _DampedPinv.apply(J, v, lam_t, z)


# --------------------------------------------------------------------------------------------------
# Gauss-Newton IK (Eq. 19)
# --------------------------------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class PlanarIKResult:
    """Per-element outcome of :func:`planar_ik` (batch ``*B``).

    Attributes:
        q: ``(*B, k)`` the returned joint angles.
        converged: ``(*B,)`` bool — ``residual ≤ tol``, checked at ``q``.
        iterations: ``(*B,)`` int64 Gauss–Newton iterations spent.
        reason: ``(*B,)`` int64 codes of :class:`controllers.problem.Reason`: ``CONVERGED``, ``STALLED`` (a
            stationary point of the cost, ``‖(RJ)ᵀ R f‖ ≤ tol²``, with ``residual > tol`` that the solver
            returned to after ``escape_tries`` deterministic perturbations of ``q`` — typically the minimum
            of an unreachable target, possibly a local minimum, never the zero-gradient saddle of a
            stretched or folded start; or no step lowered the cost up to a damping of ``1e8``),
            ``MAX_ITERATIONS`` or ``NONFINITE_INPUT`` (NaN/inf in this element's target, start, lengths or
            angles: its ``q`` and errors are NaN).
        residual: ``(*B,)`` weighted residual norm ``‖R f(q)‖`` (``W = Rᵀ R``) at ``q``.
        pos_err: ``(*B,)`` ``‖f^ee_xy(q) - μ‖``; ``rot_err``: ``(*B,)`` ``|wrap(θ(q) - θ*)|`` (0 without
            orientation).
    """

    q: Tensor
    converged: Tensor
    iterations: Tensor
    reason: Tensor
    residual: Tensor
    pos_err: Tensor
    rot_err: Tensor

    @property
    def status(self) -> SolverStatus:
        return SolverStatus(converged=self.converged, iterations=self.iterations, reason=self.reason)


def _default_tol(task: _Task, floor: float, factor: float) -> Tensor:
    """The dtype-aware default tolerance ``(*B,)``: ``max(floor, factor · eps · (1 + Σ_i |ℓ_i|))`` — the
    float64 value ``floor`` unless the dtype's rounding of a pose of size ``Σℓ`` is coarser (float32)."""
    eps = torch.finfo(task.q0.dtype).eps
    reach = task.ell.abs().sum(-1)
    return (factor * eps * (1.0 + reach)).clamp_min(floor).expand(task.bs)


def _check_solver_args(fn: str, max_iter, tol, damping) -> None:
    if isinstance(max_iter, bool) or not isinstance(max_iter, int) or max_iter < 0:
        raise ValueError(f"{fn}: argument 'max_iter' must be an int >= 0, got {max_iter!r}")
    if tol is None:
        return
    if isinstance(tol, bool) or not isinstance(tol, numbers.Real) or not tol > 0:
        raise ValueError(f"{fn}: argument 'tol' must be a float > 0, got {tol!r}")
    if isinstance(damping, bool) or not isinstance(damping, numbers.Real) or not (
            math.isfinite(damping) and damping >= 0):
        raise ValueError(f"{fn}: argument 'damping' must be a finite float >= 0, got {damping!r}")


class _Task:
    """The primary task of the solvers: checked arguments and a residual ``(R f, R J)`` on stand-ins."""

    def __init__(self, fn, lengths, target, q0, orientation, object_angle, weight):
        q0 = _check_q(q0, fn, "q0")
        if not isinstance(target, Tensor) or not target.is_floating_point():
            raise TypeError(f"{fn}: argument 'target' must be a floating-point torch.Tensor (*B, 2)")
        if target.dtype != q0.dtype:
            raise TypeError(f"{fn}: argument 'target' has dtype {target.dtype} but q0 has {q0.dtype}; "
                            "cast one of them explicitly")
        if target.ndim < 1 or target.shape[-1] != 2:
            raise ValueError(f"{fn}: argument 'target' must have shape (*B, 2) (end-effector positions), "
                             f"got {tuple(target.shape)}")
        k = q0.shape[-1]
        ell = _lengths(lengths, q0, fn)
        ori = _angle_arg(orientation, "orientation", q0, fn)
        obj = _angle_arg(object_angle, "object_angle", q0, fn)
        p = 2 if ori is None else 3
        R = _weight_factor(weight, p, q0, fn)
        shapes = [target.shape[:-1], q0.shape[:-1], ell.shape[:-1]]
        shapes += [v.shape for v in (ori, obj) if v is not None]
        shapes += [R.shape[:-2]] if R is not None else []
        try:
            bs = broadcast_shapes(*shapes)
        except RuntimeError:
            raise ValueError(f"{fn}: the batch dims of target {tuple(target.shape)}, q0 {tuple(q0.shape)}, "
                             f"lengths {tuple(ell.shape)} and the angles/weight do not broadcast") from None
        ok = all_finite(target, 1) & all_finite(q0, 1) & all_finite(ell, 1)
        for v in (ori, obj):
            if v is not None:
                ok = ok & torch.isfinite(v.detach())
        self.ok = ok.expand(bs)
        okx = self.ok[..., None]
        self.bs, self.k, self.p = bs, k, p
        # stand-ins for non-finite elements (reported NONFINITE_INPUT), so no SVD sees NaN
        self.target = torch.where(okx, target, 0.0)
        self.q0 = torch.where(okx, q0, 0.0)
        self.ell = torch.where(okx, ell, 1.0)
        self.ori = None if ori is None else torch.where(self.ok, ori, 0.0)
        self.obj = None if obj is None else torch.where(self.ok, obj, 0.0)
        self.R = R

    def residual(self, q: Tensor) -> tuple[Tensor, Tensor]:
        f, J = planar_residual(q, self.ell, self.target, self.ori, self.obj)
        if self.R is not None:
            f = (self.R @ f[..., None])[..., 0]
            J = self.R @ J
        return f, J

    def errors(self, q: Tensor) -> tuple[Tensor, Tensor]:
        pose = planar_fk(q, self.ell)
        pos = (pose[..., :2] - self.target).norm(dim=-1)
        rot = torch.zeros_like(pos) if self.ori is None else _wrap(pose[..., 2] - self.ori).abs()
        return pos, rot


def _attach(q: Tensor, task: _Task, damping: float) -> Tensor:
    """``q + (s - s.detach())`` with ``s = -J⁺ f`` at the solution: the value of ``q`` with the derivative of
    one more Gauss–Newton step (the implicit derivative ``dq = -J⁺ ∂f`` of a converged solution)."""
    f, J = task.residual(q)
    s, _ = _pinv_apply(J, -f, damping)
    return q + (s - s.detach())


def planar_ik(lengths, target: Tensor, q0: Tensor, *, orientation: Tensor | float | None = None,
              object_angle: Tensor | float | None = None, weight: Tensor | None = None, max_iter: int = 100,
              tol: float | None = None, damping: float = 1e-9, line_search_steps: int = 12,
              max_step: float = 0.5, escape_tries: int = 3) -> PlanarIKResult:
    """Batched planar IK by Gauss–Newton (Eq. 19): ``q ← q - α J⁺_λ f(q)`` on the residual of
    :func:`planar_residual`.

    Args:
        lengths: link lengths (float, ``k`` floats, or a tensor ``(*P, k)`` broadcasting with the batch).
        target: ``(*B, 2)`` end-effector positions ``μ`` (robot frame); dtype and device of the solve.
        q0: ``(*B, k)`` or ``(k,)`` starting joint angles.
        orientation: optional end-effector angles ``θ* (*B,)`` (or a float): adds the geodesic residual.
        object_angle: optional angle ``(*B,)`` of the object frame ``U`` in which the errors are expressed
            (Eq. 20) — and weighted: ``weight`` is in that frame.
        weight: ``(*B, p)`` (diagonal, ``≥ 0``) or ``(*B, p, p)`` (SPD) precision ``W`` of the residual
            (``p = 2``, or 3 with orientation); the cost is ``fᵀ W f``, solved as ``‖R f‖²``, ``W = Rᵀ R``.
        max_iter: iterations at most; ``tol``: the certificate ``‖R f(q)‖ ≤ tol`` at the returned ``q``;
            default (``None``) dtype-aware, per element: ``max(1e-9, 100 · eps · (1 + Σ|ℓ|))`` (``1e-9``
            in float64, about ``1e-5`` for a unit-size arm in float32, whose pose rounds at ``~eps Σℓ``).
        damping: the smallest ``λ`` of the damped pseudo-inverse (:func:`damped_pinv`).  Per element, ``λ`` is
            divided by 10 after a full step and multiplied by 10 (at least ``1e-12``) after a shortened or
            failed one (Levenberg–Marquardt): near singular, large-residual minima (an unreachable target,
            the arm stretched) the steps turn into gradient steps, which converge where Gauss–Newton crawls.
        max_step: a step is first scaled down (direction kept) to ``‖Δq‖∞ ≤ max_step`` (rad): near a
            singular ``J`` the pseudo-inverse step is huge and would wind the joints by many turns.
        line_search_steps: step sizes ``α = 1, ½, …`` tried (all at once, batched); the first that lowers the
            cost is taken (none: the damping grows).
        escape_tries: where the gradient ``(RJ)ᵀ R f`` vanishes with ``‖R f‖ > tol`` (e.g. the stretched home
            configuration ``q = 0``: a saddle of the cost for a reachable target), ``q`` is moved by a fixed
            perturbation (``0.25 (try+1) (-1)^j (j+1)/k`` rad on joint ``j``) and the iterations resume, at
            most this many times per element; an element that comes back to a stationary point after that is
            ``STALLED``.

    Returns:
        :class:`PlanarIKResult` (per-element status).  Elements stop as soon as they are certified (their
        ``q`` is frozen).  Gradients: ``q`` carries the implicit derivative of a converged solution with
        respect to ``target``, ``lengths`` and the angles (one Gauss–Newton step ``-J⁺ f`` differentiated at
        the returned ``q``; exact for a non-redundant chain at a regular solution; the minimum-norm joint
        motion otherwise); the iterations themselves run without a graph.

    Raises:
        TypeError/ValueError naming the argument: non-tensor or non-floating ``target``/``q0``, dtype
        mismatch, wrong trailing sizes, batch dims that do not broadcast, a weight that is not PSD
        (diagonal) / SPD, ``max_iter < 0``, ``tol ≤ 0``, ``damping < 0``.
    """
    fn = "planar_ik"
    task = _Task(fn, lengths, target, q0, orientation, object_angle, weight)
    _check_solver_args(fn, max_iter, tol, damping)
    if isinstance(escape_tries, bool) or not isinstance(escape_tries, int) or escape_tries < 0:
        raise ValueError(f"{fn}: argument 'escape_tries' must be an int >= 0, got {escape_tries!r}")
    if not (isinstance(max_step, numbers.Real) and max_step > 0):
        raise ValueError(f"{fn}: argument 'max_step' must be a float > 0, got {max_step!r}")
    if isinstance(line_search_steps, bool) or not isinstance(line_search_steps, int) or line_search_steps < 1:
        raise ValueError(f"{fn}: argument 'line_search_steps' must be an int >= 1, got {line_search_steps!r}")
    bs, k = task.bs, task.k
    dtype, device = task.q0.dtype, task.q0.device
    alphas = 0.5 ** torch.arange(line_search_steps, dtype=dtype, device=device)
    tol = _default_tol(task, 1e-9, 100.0) if tol is None else float(tol)
    jj = torch.arange(k, dtype=dtype, device=device)
    kick = 0.25 * (-1.0) ** jj * (jj + 1) / k  # the fixed escape direction
    with torch.no_grad():
        q = task.q0.detach().expand(*bs, k).clone()
        iters = torch.zeros(bs, dtype=torch.int64, device=device)
        stalled = torch.zeros(bs, dtype=torch.bool, device=device)
        tries = torch.zeros(bs, dtype=torch.int64, device=device)
        lam = torch.full(bs, float(damping), dtype=dtype, device=device)
        lam_floor = max(float(damping), 1e-12)
        f, J = task.residual(q)
        E = (f * f).sum(-1)
        for _ in range(max_iter):
            grad = (J.mT @ f[..., None])[..., 0].norm(dim=-1)
            flat = (E.sqrt() > tol) & (grad <= tol * tol) & task.ok & ~stalled
            escape = flat & (tries < escape_tries)
            if bool(escape.any()):  # a zero-gradient non-solution: perturb q and resume
                q = torch.where(escape[..., None], q + (tries + 1).to(dtype)[..., None] * kick, q)
                tries = tries + escape.to(torch.int64)
                lam = torch.where(escape, float(damping), lam)
                fn_, Jn = task.residual(q)
                f, J = torch.where(escape[..., None], fn_, f), torch.where(escape[..., None, None], Jn, J)
                E = (f * f).sum(-1)
                grad = (J.mT @ f[..., None])[..., 0].norm(dim=-1)
            stalled = stalled | ((E.sqrt() > tol) & (grad <= tol * tol) & task.ok & (tries >= escape_tries))
            done = (E.sqrt() <= tol) | stalled | ~task.ok
            if bool(done.all()):
                break
            step, _ = _pinv_apply(J, -f, lam)
            step = step / (step.abs().amax(-1, keepdim=True) / max_step).clamp_min(1.0)
            cand = q[..., None, :] + alphas[:, None] * step[..., None, :]  # (*B, A, k)
            better = _cand_cost(task, cand) < E[..., None]
            first = torch.argmax(better.to(torch.int8), -1)
            anyb = better.any(-1)
            qn = torch.gather(cand, -2, first[..., None, None].expand(*bs, 1, k))[..., 0, :]
            move = ~done & anyb
            # Levenberg-Marquardt safeguard: a full step accepted relaxes the damping; a step that had to be
            # shortened (or none found) raises it, towards gradient steps (large-residual, singular minima)
            full = anyb & (first == 0)
            lam = torch.where(done, lam, torch.where(full, (lam / 10).clamp_min(float(damping)),
                                                     (10 * lam).clamp_min(lam_floor)))
            stalled = stalled | (~done & (lam > 1e8))
            q = torch.where(move[..., None], qn, q)
            iters = iters + (~done).to(torch.int64)
            fn_, Jn = task.residual(q)
            f, J = torch.where(move[..., None], fn_, f), torch.where(move[..., None, None], Jn, J)
            E = (f * f).sum(-1)
        res = E.sqrt()
        conv = (res <= tol) & task.ok
    reason = torch.where(conv, int(Reason.CONVERGED),
                         torch.where(stalled, int(Reason.STALLED), int(Reason.MAX_ITERATIONS)))
    reason = torch.where(task.ok, reason, int(Reason.NONFINITE_INPUT)).to(torch.int64)
    if torch.is_grad_enabled() and any(isinstance(t, Tensor) and t.requires_grad
                                       for t in (lengths, target, orientation, object_angle, weight)):
        q = _attach(q, task, damping)
    pos, rot = task.errors(q.detach())
    nan = torch.full((), math.nan, dtype=dtype, device=device)
    return PlanarIKResult(q=torch.where(task.ok[..., None], q, nan), converged=conv, iterations=iters,
                          reason=reason, residual=torch.where(task.ok, res, nan),
                          pos_err=torch.where(task.ok, pos, nan), rot_err=torch.where(task.ok, rot, nan))


def _cand_cost(task: _Task, cand: Tensor) -> Tensor:
    """Cost at candidates ``(*B, A, k)`` (the task's batched data broadcast over the candidate dim)."""
    f, J = planar_residual(cand, task.ell[..., None, :] if task.ell.ndim > 1 else task.ell,
                           task.target[..., None, :], None if task.ori is None else task.ori[..., None],
                           None if task.obj is None else task.obj[..., None])
    if task.R is not None:
        R = task.R[..., None, :, :] if task.R.ndim > 2 else task.R
        f = (R @ f[..., None])[..., 0]
    return (f * f).sum(-1)


# --------------------------------------------------------------------------------------------------
# task prioritization (Eq. 22)
# --------------------------------------------------------------------------------------------------

def task_priority_ik_step(J1: Tensor, f1: Tensor, J2: Tensor | None = None, f2: Tensor | None = None, *,
                          g: Tensor | None = None, damping: float = 0.0,
                          secondary_damping: float | None = None) -> Tensor:
    """One prioritized IK step ``Δq = -J1⁺ f1 + N1 g`` ``(*B, n)`` (Eq. 22, ``ḟ = -f1``), ``N1 = I - J1⁺ J1``.

    The secondary term is either a given joint-space vector ``g (*B, n)`` (any desired gradient, e.g.
    ``[1, 0, 0]`` to move the first joint, §5.2) or a secondary task ``f2 (*B, p2)``, ``J2 (*B, p2, n)`` for
    which ``g = -(J2 N1)⁺ (f2 - J2 J1⁺ f1)``: the Gauss–Newton step of the secondary task restricted to the
    null space, after the primary step (projected once more, ``N1 g``, which is ``g`` in exact arithmetic).
    Either way ``J1 Δq = -J1 J1⁺ f1``: the secondary term never changes the primary task (to rounding).
    ``damping`` is ``λ`` of ``J1⁺``, ``secondary_damping`` that of ``(J2 N1)⁺``: ``J2 N1`` has singular values
    that are zero in exact arithmetic but a rounding error in floating point, which an undamped
    pseudo-inverse would amplify (the projector always uses the undamped ``J1⁺``); default ``10 √eps`` of the
    dtype, so that a rounding-level singular value ``σ ~ eps`` gets a negligible gain ``σ / λ² ≤ 1/100``.
    Differentiable (finite closed-form derivatives of :func:`controllers.ik.dls_joint_velocity`'s
    pseudo-inverse).
    """
    fn = "task_priority_ik_step"
    J1 = _check_J(J1, fn)
    n = J1.shape[-1]
    if not isinstance(f1, Tensor) or f1.dtype != J1.dtype or f1.ndim < 1 or f1.shape[-1] != J1.shape[-2]:
        raise ValueError(f"{fn}: argument 'f1' must be a {J1.dtype} tensor (*B, {J1.shape[-2]}) matching J1")
    if secondary_damping is None:
        secondary_damping = 10 * math.sqrt(torch.finfo(J1.dtype).eps)
    for name, v in (("damping", damping), ("secondary_damping", secondary_damping)):
        if not (math.isfinite(v) and v >= 0):
            raise ValueError(f"{fn}: argument '{name}' must be a finite float >= 0, got {v!r}")
    if (J2 is None) != (f2 is None):
        raise ValueError(f"{fn}: pass both J2 and f2 (a secondary task) or neither")
    if J2 is not None and g is not None:
        raise ValueError(f"{fn}: pass either a secondary task (J2, f2) or a joint-space vector g, not both")
    if g is not None and (not isinstance(g, Tensor) or g.dtype != J1.dtype or g.shape[-1] != n):
        raise ValueError(f"{fn}: argument 'g' must be a {J1.dtype} tensor (*B, {n})")
    if J2 is not None:
        J2 = _check_J(J2, fn)
        if (J2.dtype != J1.dtype or J2.shape[-1] != n or not isinstance(f2, Tensor)
                or f2.shape[-1] != J2.shape[-2]):
            raise ValueError(f"{fn}: arguments 'J2' (*B, p2, {n}) and 'f2' (*B, p2) must match each other "
                             "and J1")
    # a batch element with a non-finite input is solved on zeros and returned as NaN (the others unchanged)
    parts = [(J1, 2), (f1, 1)] + [(v, nd) for v, nd in ((J2, 2), (f2, 1), (g, 1)) if v is not None]
    bad = None
    for v, nd in parts:
        b = ~torch.isfinite(v).flatten(-nd).all(-1)
        bad = b if bad is None else bad | b
    if bool(bad.any()):
        def clean(v, nd):
            return None if v is None else torch.where(bad.reshape(*bad.shape, *([1] * nd)), 0.0, v)
        J1, f1, J2, f2, g = clean(J1, 2), clean(f1, 1), clean(J2, 2), clean(f2, 1), clean(g, 1)
        out = _tp_step(J1, f1, J2, f2, g, damping, secondary_damping)
        return torch.where(bad[..., None], math.nan, out)
    return _tp_step(J1, f1, J2, f2, g, damping, secondary_damping)


def _tp_step(J1, f1, J2, f2, g, damping, secondary_damping) -> Tensor:
    if J2 is None:
        step, ng = _pinv_apply(J1, -f1, damping, g)
        return step if g is None else step + ng
    step, _ = _pinv_apply(J1, -f1, damping)
    N1 = nullspace_projector(J1)
    rhs = -(f2 + (J2 @ step[..., None])[..., 0])
    g2, _ = _pinv_apply(J2 @ N1, rhs, secondary_damping)
    _, ng2 = _pinv_apply(J1, torch.zeros_like(f1), 0.0, g2)  # N1 g: (J2 N1)⁺ leaks by rounding otherwise
    return step + ng2


@dataclass(frozen=True, eq=False)
class TaskPriorityIKResult:
    """Per-element outcome of :func:`task_priority_ik` (batch ``*B``).

    Attributes:
        q: ``(*B, k)`` joint angles.
        converged: ``(*B,)`` bool, checked at ``q``: the primary residual ``≤ tol`` and the secondary task's
            gradient projected into the primary null space ``‖N1 J2ᵀ f2‖ ≤ tol_secondary`` (the first-order
            optimality of ``min ½‖f2‖²`` subject to ``f1 = 0``).
        iterations, reason: as :class:`PlanarIKResult` (``MAX_ITERATIONS``/``NONFINITE_INPUT``).
        primary_residual: ``(*B,)`` ``‖R f1(q)‖``; ``secondary_residual``: ``(*B,)`` ``‖f2(q)‖``;
        secondary_gradient: ``(*B,)`` ``‖N1 J2ᵀ f2‖`` at ``q``.
    """

    q: Tensor
    converged: Tensor
    iterations: Tensor
    reason: Tensor
    primary_residual: Tensor
    secondary_residual: Tensor
    secondary_gradient: Tensor

    @property
    def status(self) -> SolverStatus:
        return SolverStatus(converged=self.converged, iterations=self.iterations, reason=self.reason)


def task_priority_ik(lengths, target: Tensor, q0: Tensor, secondary: Tensor | Callable, *,
                     orientation: Tensor | float | None = None, object_angle: Tensor | float | None = None,
                     weight: Tensor | None = None, max_iter: int = 200, tol: float | None = None,
                     tol_secondary: float | None = None, damping: float = 1e-6,
                     secondary_damping: float | None = None,
                     max_step: float = 0.5) -> TaskPriorityIKResult:
    """Prioritized IK (§5.2): the primary task of :func:`planar_ik` exactly, a secondary task in its null
    space, iterating :func:`task_priority_ik_step` (full steps) until the certificate of
    :class:`TaskPriorityIKResult` holds at the returned ``q``.  Known limitation: full steps can fall into a
    period-2 cycle on some reachable problems (reported ``MAX_ITERATIONS``, never ``CONVERGED``).

    Args:
        secondary: a joint-space preference ``q_ref (*B, k)`` (``f2 = q - q_ref``, ``J2 = I``), or a
            callable ``q (*B, k) -> (f2 (*B, p2), J2 (*B, p2, k))`` (e.g. a link's position from
            :func:`planar_fk_links` and :func:`planar_jacobian`).
        max_step: a step is scaled down (direction kept) to ``‖Δq‖∞ ≤ max_step`` (rad).
        tol, tol_secondary: the certificate's tolerances; default (``None``) dtype-aware, per element:
            ``max(1e-9, 100 eps (1 + Σ|ℓ|))`` and ``max(1e-8, 1000 eps (1 + Σ|ℓ|))`` (the float64 values
            ``1e-9``/``1e-8``; in float32 the rounding level of the pose and of the projected gradient).
        damping, secondary_damping: of :func:`task_priority_ik_step`.
        the others: as :func:`planar_ik`.

    Converged elements are frozen.  The iterations run without a graph (``q`` carries no gradient).
    """
    fn = "task_priority_ik"
    task = _Task(fn, lengths, target, q0, orientation, object_angle, weight)
    _check_solver_args(fn, max_iter, tol, damping)
    if tol_secondary is not None and not (isinstance(tol_secondary, numbers.Real) and tol_secondary > 0):
        raise ValueError(f"{fn}: argument 'tol_secondary' must be a float > 0, got {tol_secondary!r}")
    bs, k = task.bs, task.k
    dtype, device = task.q0.dtype, task.q0.device
    tol = _default_tol(task, 1e-9, 100.0) if tol is None else float(tol)
    tol_secondary = _default_tol(task, 1e-8, 1000.0) if tol_secondary is None else float(tol_secondary)
    if isinstance(secondary, Tensor):
        if secondary.dtype != dtype or secondary.shape[-1] != k:
            raise ValueError(f"{fn}: argument 'secondary' as a tensor must be joint angles q_ref (*B, {k}) "
                             f"of dtype {dtype}, got {secondary.dtype} {tuple(secondary.shape)}")
        q_ref = secondary
        eye = torch.eye(k, dtype=dtype, device=device)

        def sec(q):
            return q - q_ref, eye.expand(*q.shape[:-1], k, k)
    elif callable(secondary):
        sec = secondary
    else:
        raise TypeError(f"{fn}: argument 'secondary' must be a tensor q_ref (*B, {k}) or a callable "
                        f"q -> (f2, J2), got {type(secondary).__name__}")

    def certificate(q):
        f1, J1 = task.residual(q)
        f2, J2 = sec(q)
        N1 = nullspace_projector(J1)
        pg = (N1 @ (J2.mT @ f2[..., None]))[..., 0].norm(dim=-1)
        return f1.norm(dim=-1), f2.norm(dim=-1), pg, (f1, J1, f2, J2)

    with torch.no_grad():
        q = task.q0.detach().expand(*bs, k).clone()
        iters = torch.zeros(bs, dtype=torch.int64, device=device)
        r1, r2, pg, (f1, J1, f2, J2) = certificate(q)
        for _ in range(max_iter):
            done = ((r1 <= tol) & (pg <= tol_secondary)) | ~task.ok
            if bool(done.all()):
                break
            dq = task_priority_ik_step(J1, f1, J2, f2, damping=damping, secondary_damping=secondary_damping)
            dq = dq / (dq.abs().amax(-1, keepdim=True) / max_step).clamp_min(1.0)
            q = torch.where(done[..., None], q, q + dq)
            iters = iters + (~done).to(torch.int64)
            r1, r2, pg, (f1, J1, f2, J2) = certificate(q)
        conv = (r1 <= tol) & (pg <= tol_secondary) & task.ok
    reason = torch.where(conv, int(Reason.CONVERGED), int(Reason.MAX_ITERATIONS))
    reason = torch.where(task.ok, reason, int(Reason.NONFINITE_INPUT)).to(torch.int64)
    nan = torch.full((), math.nan, dtype=dtype, device=device)
    return TaskPriorityIKResult(q=torch.where(task.ok[..., None], q, nan), converged=conv, iterations=iters,
                                reason=reason, primary_residual=torch.where(task.ok, r1, nan),
                                secondary_residual=torch.where(task.ok, r2, nan),
                                secondary_gradient=torch.where(task.ok, pg, nan))
