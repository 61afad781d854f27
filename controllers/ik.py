"""Differential and batched inverse kinematics for serial arms (seed 004 §5; issue 11 §4).

* :func:`dls_joint_velocity` — resolved-rate control: a twist ``ξ (*B, 6)`` to joint velocities by damped
  least squares, ``q̇ = Jᵀ (J Jᵀ + λ² I)⁻¹ ξ``, plus a joint-limit-avoidance velocity projected into the
  null space of ``J`` (``(I − J⁺ J) k ∇h(q)``), so it does not change the end-effector twist.
* :func:`solve_ik` — batched Levenberg–Marquardt on the pose error, with per-element adaptive damping,
  joint limits (2π wrapping, active set, clamping), per-element freezing once converged, and optional
  per-goal multi-start (extra starting configurations solved as parallel lanes of the same batch);
  returns an :class:`IKResult` with per-element status.

The robot is anything with ``dof``, ``fk_and_jacobian(q, frame) -> (T (*B, 4, 4), J (*B, 6, dof))`` whose
``"world"`` Jacobian maps ``q̇`` to ``[ṗ, ω]`` in base coordinates (``ṗ`` of the end-effector origin; the
convention of pytorch-kinematics), ``joint_limits(dtype, device) -> (q_min, q_max)``, ``home(dtype, device)``
and ``random_q(n, generator, dtype, device)`` — e.g. :class:`controllers.systems.panda.Panda`.

Pose error used by :func:`solve_ik` (world frame, the frame of that Jacobian)::

    e = [p* − p,  φ],   φ = log(R* Rᵀ) ∈ so(3)   (torchlie.so3.log),
    e(q + δ) ≈ e − Ĵ δ,  Ĵ = [J_v; J_r⁻¹(φ) J_ω]   (from R(q + δ) ≈ exp(J_ω δ) R and torchlie's J_r),

so the solver's success test (``|p* − p| < pos_tol``, ``|φ| < rot_tol`` — ``|φ|`` is the angle of the
rotation between the poses) is a test on the very residual it minimizes.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from controllers._validate import all_finite
from controllers.problem import Reason, SolverStatus
from torchlie import so3
from torchlie._batch import broadcast_shapes
from torchlie.manifolds import SE3

__all__ = ["IKResult", "dls_joint_velocity", "joint_limit_gradient", "pose_error", "resolved_rate_step",
           "solve_ik"]


# --------------------------------------------------------------------------------------------------
# differential IK
# --------------------------------------------------------------------------------------------------

def joint_limit_gradient(q: Tensor, q_min: Tensor, q_max: Tensor) -> Tensor:
    """``−∇h(q)`` for ``h(q) = (1/2n) Σ ((q_i − q̄_i)/(q_max,i − q_min,i))²`` (Liégeois), ``q̄`` the mid-range.

    A joint velocity along this vector moves every joint towards the middle of its range, faster the nearer it
    is to a limit (relative to the range).  A joint with an infinite limit (a continuous joint) gets 0, the
    limit of the term as the range grows.  ``(*B, n)``.
    """
    bounded = torch.isfinite(q_min) & torch.isfinite(q_max)
    lo, hi = torch.where(bounded, q_min, 0.0), torch.where(bounded, q_max, 1.0)
    rng = hi - lo
    return torch.where(bounded, -(q - 0.5 * (lo + hi)) / (rng * rng * q.shape[-1]), 0.0)


def _broadcasts(a, b) -> bool:
    try:
        broadcast_shapes(a, b)
    except RuntimeError:
        return False
    return True


def _as_batch_arg(v, name: str, J: Tensor, batch: tuple[int, ...]) -> Tensor:
    """``damping``/``nullspace_gain``: a real number or a tensor ``(*B,)`` broadcasting with the batch."""
    if isinstance(v, Tensor):
        if not v.is_floating_point() or v.dtype != J.dtype or v.device != J.device:
            raise TypeError(f"dls_joint_velocity: argument '{name}' must be a float or a {J.dtype} tensor on "
                            f"{J.device} (as J), got a {v.dtype} tensor on {v.device}")
    elif isinstance(v, bool) or not isinstance(v, (int, float)):
        raise TypeError(f"dls_joint_velocity: argument '{name}' must be a float or a tensor (*B,), "
                        f"got {type(v).__name__}")
    t = torch.as_tensor(v, dtype=J.dtype, device=J.device)
    if not _broadcasts(t.shape, batch):
        raise ValueError(f"dls_joint_velocity: argument '{name}' must be a float or a tensor (*B,) "
                         f"broadcasting with the batch {batch} of J and twist, got shape {tuple(t.shape)}")
    return t


def _check_dls_args(J, twist, damping, q, q_limits, nullspace_gain, check_limits: bool = True):
    """The argument checks of :func:`dls_joint_velocity`; returns ``(λ, k)`` as tensors."""
    for name, t in (("J", J), ("twist", twist)):
        if not isinstance(t, Tensor) or not t.is_floating_point():
            what = f"a {t.dtype} tensor" if isinstance(t, Tensor) else type(t).__name__
            raise TypeError(f"dls_joint_velocity: argument '{name}' must be a floating-point torch.Tensor, "
                            f"got {what}")
    if twist.dtype != J.dtype or twist.device != J.device:
        raise TypeError(f"dls_joint_velocity: argument 'twist' ({twist.dtype}, {twist.device}) must have J's "
                        f"dtype and device ({J.dtype}, {J.device}); cast it explicitly")
    if J.ndim < 2 or twist.ndim < 1 or twist.shape[-1] != J.shape[-2]:
        raise ValueError(f"dls_joint_velocity: J (*B, m, n) and twist (*B, m) do not match: "
                         f"{tuple(J.shape)} and {tuple(twist.shape)}")
    if not _broadcasts(J.shape[:-2], twist.shape[:-1]):
        raise ValueError(f"dls_joint_velocity: the batch dims of J {tuple(J.shape)} and twist "
                         f"{tuple(twist.shape)} do not broadcast")
    batch = tuple(broadcast_shapes(J.shape[:-2], twist.shape[:-1]))
    lam = _as_batch_arg(damping, "damping", J, batch)
    gain = _as_batch_arg(nullspace_gain, "nullspace_gain", J, batch)
    if q is None or q_limits is None:
        return lam, gain
    n = J.shape[-1]
    if not (isinstance(q_limits, (tuple, list)) and len(q_limits) == 2):
        raise TypeError("dls_joint_velocity: argument 'q_limits' must be a pair (q_min, q_max) of tensors")
    for name, t in (("q", q), ("q_limits[0]", q_limits[0]), ("q_limits[1]", q_limits[1])):
        if not isinstance(t, Tensor) or t.dtype != J.dtype or t.device != J.device:
            what = f"{t.dtype} on {t.device}" if isinstance(t, Tensor) else type(t).__name__
            raise TypeError(f"dls_joint_velocity: argument '{name}' must be a {J.dtype} tensor on {J.device} "
                            f"(as J), got {what}")
        if t.ndim < 1 or t.shape[-1] != n or not _broadcasts(t.shape[:-1], batch):
            raise ValueError(f"dls_joint_velocity: argument '{name}' must be (*B, {n}) (J has {n} columns, "
                             f"*B broadcasting with the batch {batch} of J and twist), got {tuple(t.shape)}")
    if check_limits:  # one host synchronization
        lo, hi = q_limits
        if not bool((lo < hi).all()):
            raise ValueError("dls_joint_velocity: argument 'q_limits' must have q_min < q_max for every "
                             "joint (±inf allowed, no NaN); got crossed, equal or NaN limits at joints "
                             f"{torch.nonzero(~(lo < hi).reshape(-1, n).all(0)).flatten().tolist()}")
    return lam, gain


class _DampedPinv(torch.autograd.Function):
    """``(J⁺_λ ξ, (I − J⁺ J) z)`` from one SVD of ``J``, with the derivatives in closed form.

    ``J⁺_λ = Jᵀ (J Jᵀ + λ² I)⁻¹ = V Σ (Σ² + λ²)⁻¹ Uᵀ`` where ``λ² > 0`` and the (rank-truncated)
    pseudo-inverse ``J⁺`` where ``λ = 0``.  Autograd through the SVD divides by differences of singular values
    and is NaN for a rank-deficient ``J`` (or repeated singular values) although ``J⁺_λ`` is smooth for
    ``λ > 0``.  The backward uses instead, with ``g`` the output gradient, ``w = (J Jᵀ + λ² I)⁻¹ ξ``,
    ``h = (J Jᵀ + λ² I)⁻¹ J g`` and ``y = J⁺_λ ξ``:

    * ``λ > 0``: ``∂J = w (g − Jᵀ h)ᵀ − h yᵀ``, ``∂ξ = h``, ``∂λ = −2λ hᵀ w``;
    * ``λ = 0``: the derivative of ``J⁺`` at constant rank (Golub & Pereyra 1973),
      ``dJ⁺ = −J⁺ dJ J⁺ + J⁺ J⁺ᵀ dJᵀ (I − J J⁺) + (I − J⁺ J) dJᵀ J⁺ᵀ J⁺`` — the derivative for a full-rank
      ``J`` (and along rank-preserving changes of a rank-deficient one, where ``J⁺`` jumps otherwise);
    * the projector ``N = I − J⁺ J`` at constant rank: ``dN = −N dJᵀ J⁺ᵀ − J⁺ dJ N``.

    First derivatives only (a second backward raises).  Inputs broadcast; the SVD is taken on ``J``'s own
    batch.
    """

    @staticmethod
    def forward(ctx, J, xi, lam, z):
        m, n = J.shape[-2:]
        U, S, Vh = torch.linalg.svd(J, full_matrices=False)
        rank = S > max(m, n) * torch.finfo(J.dtype).eps * S.amax(-1, keepdim=True)  # what J⁺ keeps
        lam2 = (lam * lam)[..., None]
        d = 1.0 / (S * S + lam2).clamp_min(torch.finfo(J.dtype).tiny)
        gain = torch.where(rank | (lam2 > 0), S * d, 0.0)
        c = _mv(U.mT, xi)
        y = _mv(Vh.mT, gain * c)
        zn = z - _mv(Vh.mT, rank * _mv(Vh, z))
        ctx.save_for_backward(J, xi, lam, z, U, S, Vh, rank, y, zn)
        return y, zn

    @staticmethod
    @once_differentiable
    def backward(ctx, gy, gz):
        J, xi, lam, z, U, S, Vh, rank, y, zn = ctx.saved_tensors
        m, k = U.shape[-2:]
        V = Vh.mT
        lam2 = (lam * lam)[..., None]
        damped = lam2 > 0
        d = 1.0 / (S * S + lam2).clamp_min(torch.finfo(J.dtype).tiny)
        sinv = torch.where(rank, 1.0 / torch.where(rank, S, 1.0), 0.0)
        c, Vg, Vz, Vgz = _mv(U.mT, xi), _mv(Vh, gy), _mv(Vh, z), _mv(Vh, gz)
        # λ > 0
        w = _mv(U, d * c)
        if m > k:  # the part of ξ outside the range of U, where J Jᵀ + λ² I is λ² I
            w = w + torch.where(damped, (xi - _mv(U, c)) / lam2.clamp_min(torch.finfo(J.dtype).tiny), 0.0)
        h = _mv(U, S * d * Vg)
        gJ_d = _outer(w, gy - _mv(V, S * S * d * Vg)) - _outer(h, y)
        # λ = 0 (J⁺ at constant rank)
        a = _mv(U, sinv * Vg)  # J⁺ᵀ g
        r = xi - _mv(U, rank * c)  # (I − J J⁺) ξ
        gJ_p = (-_outer(a, y) + _outer(r, _mv(V, sinv * sinv * Vg))
                + _outer(_mv(U, sinv * sinv * c), gy - _mv(V, rank * Vg)))
        dmp = damped[..., None]
        gJ = torch.where(dmp, gJ_d, gJ_p)
        gxi = torch.where(damped, h, a)
        glam = torch.where(damped[..., 0], -2.0 * lam * (h * w).sum(-1), 0.0)
        # the null-space projector
        Ngz = gz - _mv(V, rank * Vgz)
        gJ = gJ - _outer(_mv(U, sinv * Vz), Ngz) - _outer(_mv(U, sinv * Vgz), zn)
        return (gJ.sum_to_size(J.shape), gxi.sum_to_size(xi.shape), glam.sum_to_size(lam.shape),
                Ngz.sum_to_size(z.shape))


def _mv(A: Tensor, v: Tensor) -> Tensor:
    return (A @ v.unsqueeze(-1)).squeeze(-1)


def _outer(a: Tensor, b: Tensor) -> Tensor:
    return a.unsqueeze(-1) * b.unsqueeze(-2)


def dls_joint_velocity(J: Tensor, twist: Tensor, damping: Tensor | float = 1e-2, q: Tensor | None = None,
                       q_limits: tuple[Tensor, Tensor] | None = None, nullspace_gain: Tensor | float = 1.0
                       ) -> Tensor:
    """Joint velocities ``(*B, n)`` for a twist ``(*B, 6)``: damped least squares + joint-limit avoidance.

    ``q̇ = Jᵀ (J Jᵀ + λ² I)⁻¹ ξ + (I − J⁺ J) k (−∇h(q))`` with ``λ = damping`` (float or ``(*B,)``),
    ``k = nullspace_gain`` and ``h`` of :func:`joint_limit_gradient`.  The second term is added only when both
    ``q (*B, n)`` and ``q_limits = (q_min, q_max)`` are given.  Both terms come from one SVD
    ``J = U Σ Vᵀ``: the first is ``V Σ (Σ² + λ²)⁻¹ Uᵀ ξ`` (the same matrix), and at ``λ = 0`` it is its limit
    ``J⁺ ξ``, the minimum-norm least-squares velocity, also for a rank-deficient ``J`` (where
    ``J Jᵀ`` is singular and the formula undefined).  ``J⁺`` drops the singular values below
    ``max(m, n) · eps · σ_max`` (as :func:`torch.linalg.pinv`), so ``J`` times the null-space term is zero up
    to rounding: the joint-limit motion never changes the end-effector twist.  ``J (*B, 6, n)`` and
    ``twist`` must be in the same frame (both "world" or both "body" for a
    :class:`~controllers.systems.panda.Panda`).  Batch dims broadcast; dtype and device follow ``J``.  An
    element with a non-finite ``J``, twist, ``λ``, ``k`` or ``q`` gets NaN joint velocities; the others are
    computed as if it were absent (no element's linear algebra can fail the batch, and its gradient is zero).

    Gradients (with respect to ``J``, the twist, ``λ``, ``q``, ``k``) are finite: the closed forms of
    :class:`_DampedPinv` replace autograd through the SVD (NaN for a rank-deficient ``J``).  For ``λ > 0``
    they are the derivatives of the DLS term, also at a singular ``J``; at ``λ = 0`` and for the null-space
    projector they are the derivatives at constant rank (both jump where the rank changes).

    Raises, at entry: ``TypeError`` for a ``J``/``twist`` that is not a floating tensor, a twist, ``q`` or
    limit of another dtype or device than ``J``, or a ``damping``/``nullspace_gain`` that is neither a float
    nor such a tensor; ``ValueError`` for shapes that do not match or broadcast, and for ``q_limits`` with
    ``q_min < q_max`` false at some joint (crossed, equal or NaN; ``±inf`` is allowed: no avoidance on that
    joint).  Checking the limits is the only host synchronization.
    """
    lam, gain = _check_dls_args(J, twist, damping, q, q_limits, nullspace_gain)
    return _dls(J, twist, lam, q, q_limits, gain)


def _dls(J: Tensor, twist: Tensor, lam: Tensor, q: Tensor | None, q_limits, gain: Tensor) -> Tensor:
    """:func:`dls_joint_velocity` on checked arguments."""
    ok = all_finite(J, 2) & all_finite(twist, 1) & torch.isfinite(lam.detach())
    J = torch.where(all_finite(J, 2)[..., None, None], J, 0.0)  # harmless stand-ins, masked below
    twist = torch.where(all_finite(twist, 1)[..., None], twist, 0.0)
    lam = torch.where(torch.isfinite(lam.detach()), lam, 0.0)
    if q is None or q_limits is None:
        z = torch.zeros((), dtype=J.dtype, device=J.device).expand(J.shape[-1])
    else:
        z = gain[..., None] * joint_limit_gradient(q, *q_limits)
        ok = ok & all_finite(z, 1)
        z = torch.where(all_finite(z, 1)[..., None], z, 0.0)
    qd, z_null = _DampedPinv.apply(J, twist, lam, z)
    return torch.where(ok[..., None], qd + z_null, torch.nan)


def resolved_rate_step(robot, q: Tensor, twist: Tensor, dt: float, *, frame: str = "body",
                       damping: Tensor | float = 1e-2, nullspace_gain: Tensor | float = 1.0,
                       dq_max: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """One step of a velocity-controlled arm asked for an end-effector ``twist (*B, 6)`` in ``frame``.

    ``q̇`` from :func:`dls_joint_velocity` (with joint-limit avoidance in the null space), scaled down
    uniformly (direction kept) where a joint would exceed ``dq_max`` (default ``robot.velocity_limits``
    when the robot has them), held for ``dt`` and clipped to the position limits:
    ``q⁺ = clip(q + Δt q̇, q_min, q_max)``.  Returns ``(q⁺, q̇)``.  The arm's real motion is whatever the
    forward kinematics of ``q⁺`` says: the DLS damping, the saturation and the Jacobian changing within the
    step all make it differ from ``X exp(Δt twist)`` — the model error a Cartesian controller lives with.
    """
    q_min, q_max = robot.joint_limits(q.dtype, q.device)
    J = robot.jacobian(q, frame)
    lam, gain = _check_dls_args(J, twist, damping, q, (q_min, q_max), nullspace_gain, check_limits=False)
    qd = _dls(J, twist, lam, q, (q_min, q_max), gain)  # the robot's limits: no host synchronization
    if dq_max is None and hasattr(robot, "velocity_limits"):
        dq_max = robot.velocity_limits(q.dtype, q.device)
    if dq_max is not None:
        scale = (qd.abs() / dq_max).amax(-1, keepdim=True).clamp(min=1.0)
        qd = qd / scale
    q_next = torch.minimum(torch.maximum(q + dt * qd, q_min), q_max)
    return q_next, qd


# --------------------------------------------------------------------------------------------------
# batched IK
# --------------------------------------------------------------------------------------------------

def pose_error(T: Tensor, target: Tensor) -> Tensor:
    """World-frame pose error ``[p* − p, log(R* Rᵀ)]`` ``(*B, 6)`` of ``T`` to ``target`` ``(*B, 4, 4)``."""
    R, p = T[..., :3, :3], T[..., :3, 3]
    Rt, pt = target[..., :3, :3], target[..., :3, 3]
    phi = so3.log(Rt @ R.transpose(-1, -2))
    return torch.cat((pt - p, phi), -1)


@dataclass(frozen=True, eq=False)
class IKResult:
    """Per-element outcome of :func:`solve_ik` (batch shape ``*B`` of the target).

    Attributes:
        q: ``(*B, n)`` the best configuration found (inside the joint limits).
        success: ``(*B,)`` bool — ``pos_err < pos_tol`` and ``rot_err < rot_tol`` at ``q``.
        iterations: ``(*B,)`` int64 — iterations spent on this goal (at most ``max_iter``; ``0`` if a start
            already solved it).  One iteration is one damped solve and one pose + Jacobian evaluation per
            active lane, the step accepted or rejected.
        evaluations: ``(*B,)`` int64 — pose + Jacobian evaluations over all lanes (``iterations`` when
            single-start).
        pos_err: ``(*B,)`` position error ``|p* − p(q)|`` (m).
        rot_err: ``(*B,)`` rotation error, the angle of ``R* R(q)ᵀ`` (rad).
        reason: ``(*B,)`` int64 codes of :class:`controllers.problem.Reason`: ``CONVERGED``,
            ``NONFINITE_INPUT`` (NaN/inf in the target or a per-goal start of this element),
            ``MAX_ITERATIONS``.
        lane: ``(*B,)`` int64 — which start the result comes from (0: ``q0``, ``k``: ``seeds[k − 1]``).
    """

    q: Tensor
    success: Tensor
    iterations: Tensor
    evaluations: Tensor
    pos_err: Tensor
    rot_err: Tensor
    reason: Tensor
    lane: Tensor

    @property
    def status(self) -> SolverStatus:
        return SolverStatus(converged=self.success, iterations=self.iterations, reason=self.reason)


def _linearized(J: Tensor, e: Tensor) -> Tensor:
    """``Ĵ = [J_v; J_r⁻¹(φ) J_ω]`` ``(N, 6, n)``."""
    return torch.cat((J[:, :3], so3.right_jacobian_inv(e[:, 3:]) @ J[:, 3:]), 1)


def _wrap(x: Tensor, lo: Tensor, hi: Tensor) -> Tensor:
    """Revolute joints: a value past a limit moves by ∓2π where that lands inside the range (same pose)."""
    two_pi = 2 * torch.pi
    x = torch.where((x > hi) & (x - two_pi >= lo), x - two_pi, x)
    return torch.where((x < lo) & (x + two_pi <= hi), x + two_pi, x)


def _cost(e: Tensor, w: Tensor) -> Tensor:
    return (e * e * w).sum(-1)


def _solve_spd(A: Tensor, b: Tensor) -> Tensor:
    """``A⁻¹ b`` for a batch of SPD ``A``; a zero step where the factorization fails (then rejected)."""
    L, info = torch.linalg.cholesky_ex(A)
    x = torch.cholesky_solve(b.unsqueeze(-1), L).squeeze(-1)
    return torch.where((info == 0)[:, None] & torch.isfinite(x), x, 0.0)


def _check_start(t, name: str, k: int, robot, target: Tensor) -> None:
    """``q0`` (``k = 1``) or ``seeds`` (``k = 2``): a tensor ``(*B, [K,] n)`` like ``target``."""
    n, batch = robot.dof, tuple(target.shape[:-2])
    want = f"({n},) or (*B, {n})" if k == 1 else f"(K, {n}) or (*B, K, {n})"
    if not isinstance(t, Tensor):
        raise TypeError(f"solve_ik: argument '{name}' must be a torch.Tensor {want}, got {type(t).__name__}")
    if t.dtype != target.dtype or t.device != target.device:
        raise TypeError(f"solve_ik: {name} ({t.dtype}, {t.device}) must match target ({target.dtype}, "
                        f"{target.device})")
    lead = tuple(t.shape[:max(t.ndim - k, 0)])
    fits = len(lead) <= len(batch) and all(a in (1, b) for a, b in zip(lead[::-1], batch[::-1]))
    if t.ndim < k or t.shape[-1] != n or not fits:
        raise ValueError(f"solve_ik: argument '{name}' must have shape {want} (robot.dof = {n} joints, *B "
                         f"broadcasting to the target's batch {batch}), got {tuple(t.shape)}")
    # a start shared by every goal is the caller's input, not one element's: NaN/inf there is an error (a
    # per-goal start keeps the per-element status NONFINITE_INPUT, as the target)
    if t.ndim == k and not bool(torch.isfinite(t).all()):
        raise ValueError(f"solve_ik: argument '{name}' {tuple(t.shape)} (shared by every goal) has NaN or "
                         "inf entries; pass finite starts (a non-finite per-goal start fails its goal only)")


def _check_ik_args(robot, target, q0, seeds, max_iter, rot_scale, damping, pos_tol, rot_tol) -> None:
    """The argument checks of :func:`solve_ik` (a ValueError/TypeError naming the argument)."""
    if not isinstance(target, Tensor):
        raise TypeError(f"solve_ik: argument 'target' must be a torch.Tensor (*B, 4, 4), "
                        f"got {type(target).__name__}")
    if target.ndim < 2 or target.shape[-2:] != (4, 4):
        raise ValueError(f"solve_ik: argument 'target' must be (*B, 4, 4), got {tuple(target.shape)}")
    if not target.is_floating_point():
        raise TypeError(f"solve_ik: argument 'target' must be floating point, got {target.dtype}")
    for name, t, k in (("q0", q0, 1), ("seeds", seeds, 2)):
        if t is not None:
            _check_start(t, name, k, robot, target)
    if isinstance(max_iter, bool) or not isinstance(max_iter, int) or max_iter < 0:
        raise ValueError(f"solve_ik: argument 'max_iter' must be an int >= 0, got {max_iter!r}")
    if not (math.isfinite(rot_scale) and rot_scale > 0):
        raise ValueError(f"solve_ik: argument 'rot_scale' must be a finite float > 0, got {rot_scale!r}")
    if not (math.isfinite(damping) and damping >= 0):
        raise ValueError(f"solve_ik: argument 'damping' must be a finite float >= 0, got {damping!r}")
    for name, tol in (("pos_tol", pos_tol), ("rot_tol", rot_tol)):
        if isinstance(tol, bool) or not isinstance(tol, numbers.Real) or not tol > 0:
            raise ValueError(f"solve_ik: argument '{name}' must be a float > 0 (inf: not tested), got "
                             f"{tol!r} (an error must be < it to succeed)")
    # rigid motions only: the pose error (log of R* Rᵀ) and the success test assume R* is a rotation.  The
    # tolerance is torchlie's manifold_tolerance; non-finite elements get their per-element status instead.
    finite = torch.isfinite(target).flatten(-2).all(-1)
    eye = torch.eye(4, dtype=target.dtype, device=target.device)
    try:
        SE3().check(torch.where(finite[..., None, None], target, eye), "target")
    except ValueError as e:
        msg = str(e).split("; pass project=True")[0]
        raise ValueError(f"solve_ik: {msg}; project it first: torchlie.manifolds.SE3().check(target, "
                         "project=True)") from None


def solve_ik(robot, target: Tensor, q0: Tensor | None = None, *, max_iter: int = 30, pos_tol: float = 1e-3,
             rot_tol: float = 1e-2, seeds: Tensor | None = None, rot_scale: float = 0.2,
             damping: float = 1e-3, wrap: bool = True) -> IKResult:
    """Batched IK: ``q`` with ``fk(q) ≈ target (*B, 4, 4)`` to ``pos_tol`` (m) and ``rot_tol`` (rad).

    Levenberg–Marquardt on the world-frame pose error of :func:`pose_error`, weighted
    ``‖e_p‖² + rot_scale² ‖φ‖²`` (``rot_scale`` in metres per radian), with the damping
    ``λ = μ (E + damping)`` (Sugihara's error-proportional damping, ``E`` the weighted squared error) and a
    per-element factor ``μ`` divided by 3 after an accepted step and multiplied by 4 after a rejected one
    (a step is accepted when it decreases ``E``).  Joint limits: with ``wrap`` (revolute joints), a joint
    value that would leave its range moves by ∓2π where that lands inside the range (same pose — this frees a
    joint such as the Panda's q7 that would otherwise be pinned at a limit); a joint on a limit whose step
    still points outwards is frozen for that step (its column removed), and the step is clamped into range.
    Every element stops as soon as it meets both tolerances; the loop runs on the still-active elements only
    (gathered into one batch), so the work per iteration shrinks as elements converge.

    Multi-start: ``seeds (K, n)`` (or ``(*B, K, n)``) adds ``K`` starts per goal, solved as ``K + 1`` lanes in
    the same batch (lane 0 starts from ``q0``).  A goal stops when any of its lanes meets the tolerances, and
    its result is that lane's (the lowest-index one on a tie; the lane with the smallest error if none did).
    ``iterations`` counts the iterations of that goal (the depth, at most ``max_iter``); ``evaluations``
    counts every pose + Jacobian evaluation spent on it over all lanes (at most ``(K + 1) · max_iter``).

    Args:
        robot: see the module docstring (e.g. :class:`controllers.systems.panda.Panda`).
        target: ``(*B, 4, 4)`` goal poses (their dtype and device are the solve's).
        q0: start configurations ``(n,)`` or ``(*B, n)``; default ``robot.home()`` for every goal.
        max_iter: iteration budget per goal (one iteration: one damped solve and one pose + Jacobian
            evaluation per active lane, accepted or rejected).

    Returns:
        :class:`IKResult`.  Non-finite values in an element's target or in its own (per-goal) ``q0`` or
        ``seeds`` make that element fail with ``NONFINITE_INPUT`` and leave the others untouched.

    Raises:
        ValueError / TypeError naming the argument, at entry: a ``target`` that is not a floating
        ``(*B, 4, 4)`` tensor, or whose finite elements are not rigid motions (off SE(3) by more than
        :func:`torchlie.manifolds.manifold_tolerance`: a scaled or sheared rotation block, a wrong last
        row — a caller's error like a wrong shape, as in every manifold check of the project, not a
        per-element status); a ``q0``/``seeds`` of the wrong dtype, device, joint count or batch;
        ``max_iter`` not an int ``>= 0``; ``rot_scale <= 0``, ``damping < 0``, ``pos_tol``/``rot_tol``
        not ``> 0`` (or NaN: never met); NaN/inf in a ``q0 (n,)`` or ``seeds (K, n)`` shared by every goal
        (a shared input's defect is the caller's, as for the weights of the solvers; an ignored lane would
        hide it).
    """
    _check_ik_args(robot, target, q0, seeds, max_iter, rot_scale, damping, pos_tol, rot_tol)
    dtype, device = target.dtype, target.device
    n = robot.dof
    batch = target.shape[:-2]
    lo, hi = robot.joint_limits(dtype, device)
    home = robot.home(dtype, device)
    if q0 is None:
        q0 = home
    starts = q0.expand(*batch, n).unsqueeze(-2)
    if seeds is not None:
        starts = torch.cat((starts, seeds.expand(*batch, *seeds.shape[-2:])), -2)
    L = starts.shape[-2]
    N = math.prod(batch)
    tgt = target.reshape(N, 1, 4, 4).expand(N, L, 4, 4).reshape(N * L, 4, 4)
    q = starts.reshape(N * L, n).clone()
    finite = (torch.isfinite(target.reshape(N, 16)).all(-1)
              & torch.isfinite(starts.reshape(N, L * n)).all(-1))  # (N,)
    finite_l = finite.repeat_interleave(L)
    # non-finite elements are solved on a harmless stand-in (and reported as NONFINITE_INPUT)
    tgt = torch.where(finite_l[:, None, None], tgt, torch.eye(4, dtype=dtype, device=device))
    q = torch.where(finite_l[:, None], q, home).clamp(lo, hi)
    w = torch.tensor((1.0,) * 3 + (rot_scale ** 2,) * 3, dtype=dtype, device=device)
    margin = 16 * torch.finfo(dtype).eps
    eye_n = torch.eye(n, dtype=dtype, device=device)

    def solved(err):
        return (err[..., :3].norm(dim=-1) < pos_tol) & (err[..., 3:].norm(dim=-1) < rot_tol)

    T, J = robot.fk_and_jacobian(q, "world")
    e = pose_error(T, tgt)
    E = _cost(e, w)
    mu = torch.ones(N * L, dtype=dtype, device=device)
    evals = torch.zeros(N * L, dtype=torch.int64, device=device)
    depth = torch.zeros(N, dtype=torch.int64, device=device)
    goal_done = solved(e).view(N, L).any(-1) | ~finite
    done = goal_done.repeat_interleave(L)
    for _ in range(max_iter):
        idx = torch.nonzero(~done).squeeze(-1)
        if idx.numel() == 0:
            break
        qa, ea, Ea, mua = q[idx], e[idx], E[idx], mu[idx]
        Jh = _linearized(J[idx], ea)
        JW = Jh.transpose(-1, -2) * w
        g = (JW @ ea.unsqueeze(-1)).squeeze(-1)
        H = JW @ Jh
        lamI = (mua * (Ea + damping))[:, None, None] * eye_n
        d = _solve_spd(H + lamI, g)
        # active set: joints on a limit whose step points outwards (and cannot wrap) are frozen for this step
        x = _wrap(qa + d, lo, hi) if wrap else qa + d
        blocked = ((qa <= lo + margin) & (x < lo)) | ((qa >= hi - margin) & (x > hi))
        if bool(blocked.any()):
            keep = (~blocked).to(dtype)
            d = _solve_spd(H * keep[:, :, None] * keep[:, None, :] + lamI, g * keep)
            x = _wrap(qa + d, lo, hi) if wrap else qa + d
        qn = x.clamp(lo, hi)

        Tn, Jn = robot.fk_and_jacobian(qn, "world")
        en = pose_error(Tn, tgt[idx])
        En = _cost(en, w)
        accept = En < Ea  # False for a non-finite En
        evals[idx] += 1
        mu[idx] = torch.where(accept, (mua / 3).clamp_min(1e-6), (mua * 4).clamp_max(1e12))
        q[idx] = torch.where(accept[:, None], qn, qa)
        T[idx] = torch.where(accept[:, None, None], Tn, T[idx])
        J[idx] = torch.where(accept[:, None, None], Jn, J[idx])
        e[idx] = torch.where(accept[:, None], en, ea)
        E[idx] = torch.where(accept, En, Ea)
        active_goal = ~goal_done
        depth += active_goal.to(torch.int64)
        goal_done = goal_done | solved(e).view(N, L).any(-1)
        done = goal_done.repeat_interleave(L)

    # per goal: the first solved lane, else the lane with the smallest error
    ok = solved(e).view(N, L)
    score = torch.where(ok, -1.0, E.view(N, L).nan_to_num(torch.inf))
    lane = torch.argmin(score, -1)  # argmin returns the first minimal index
    pick = torch.arange(N, device=device) * L + lane
    q_best, e_best = q[pick], e[pick]
    success = ok.any(-1) & finite
    reason = torch.where(success, int(Reason.CONVERGED), int(Reason.MAX_ITERATIONS))
    reason = torch.where(finite, reason, int(Reason.NONFINITE_INPUT))
    nan = torch.full((N,), torch.nan, dtype=dtype, device=device)
    pos_err = torch.where(finite, e_best[:, :3].norm(dim=-1), nan)
    rot_err = torch.where(finite, e_best[:, 3:].norm(dim=-1), nan)
    return IKResult(
        q=q_best.reshape(*batch, n), success=success.reshape(batch), iterations=depth.reshape(batch),
        evaluations=evals.view(N, L).sum(-1).reshape(batch), pos_err=pos_err.reshape(batch),
        rot_err=rot_err.reshape(batch), reason=reason.to(torch.int64).reshape(batch),
        lane=lane.reshape(batch))
