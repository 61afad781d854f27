"""Movement primitives as LQT (issue 26 §3; seed 004 §7, Eq. 59-63, §7.3 Eq. 66, §7.7).

Two learning-from-demonstration encodings, both linear quadratic tracking with control primitives:

* :class:`DMP` (:func:`fit_dmp`) — DMP-like reproduction of *one* demonstration (§7.7, Fig. 20): a thin
  batched wrapper over :func:`controllers.lqt_cookbook.dmp_lqt` and
  :func:`~controllers.lqt_cookbook.dmp_rollout`.
  ``N`` demos give ``N`` independent DMPs solved as one batch (``dmp_lqt`` batches over leading dims);
  :meth:`DMP.reproduce` replays them from another start, towards another goal, or through a push.
* :class:`ProMP` (:func:`fit_promp`) — ProMP-like trajectory distribution from *many* demonstrations
  (§7.3, "a covariance matrix on w can be converted to a covariance on u and on x"): an integrator chain of
  order ``k`` per demo dimension, ``x_{t+1} = A x_t + B u_t`` (Eq. 60, Euler discretization as Eq. 192),
  controls ``u = Ψ w`` on ``K`` basis functions per dimension (``Ψ = φ ⊗ I_D``, Eq. 66), so that the whole
  state trajectory is linear in the parameters ``z = [x_1; w]``::

      x = S_x x_1 + S_u Ψ w = S z,        S = [S_x, S_u Ψ]            (Eq. 61 with Eq. 65's S)

  Each demo ``i`` gives ``z_i``: ``x_{1,i}`` from its first samples (position and forward differences, so
  that the first ``k`` samples are matched exactly) and ``w_i`` by ridge least squares of its positions
  (§7.3's solution with ``Q`` selecting positions and ``R = reg I``; one batched solve for all demos).
  The demos' sample mean and covariance of ``z`` (``+ reg I``) is a Gaussian ``N(μ_z, Σ_z)`` that the
  linear maps turn into distributions of controls (``u = [0, Ψ] z``, the role of Eq. 63's ``Σ̂ᵘ``) and of
  states (``μ_x = S μ_z``, ``Σ_x = S Σ_z Sᵀ``).  Via points condition it (Gaussian conditioning of ``z`` on
  linear observations ``y = C x_t + ε``), and :meth:`ProMP.track` turns it back into an LQT whose precision
  at each step is the inverse of the state covariance (§7.7: high gains where the demos agree, low where
  they vary — minimal intervention).

Metric helpers for comparisons with other movement-primitive libraries (arrays from numpy are accepted):
:func:`reproduction_error`, :func:`via_point_error`, :func:`perturbation_recovery`.

Time convention of :mod:`learning.demos`: ``T`` samples ``x_0 .. x_{T-1}`` (the seed's ``x_1 .. x_T``) and
``T-1`` controls.  Everything is batched over leading dims, differentiable (plain torch ops), and keeps the
dtype and device of its inputs.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
import torch
from torch import Tensor

from controllers import basis
from controllers.costs import QuadraticCost
from controllers.dynamics import LinearDynamics
from controllers.lifted import control_primitives, solve_lifted, transfer_matrices
from controllers.lqt_cookbook import DMPLQT, dmp_lqt, dmp_rollout, double_integrator
from controllers.problem import LQProblem, SolverStatus
from controllers.riccati import solve as riccati_solve
from learning._checks import float_tensor
from learning.demos import Demonstrations

__all__ = ["DMP", "fit_dmp", "Reproduction", "ProMP", "fit_promp", "Tracking", "integrator_chain",
           "reproduction_error", "via_point_error", "perturbation_recovery", "Recovery"]



# --------------------------------------------------------------------------------------------------
# input helpers
# --------------------------------------------------------------------------------------------------


def _tensor(v: Any, name: str, own: str, like: Tensor | None = None, min_dim: int = 1) -> Tensor:
    """``v`` as a floating tensor (numpy arrays are converted; ``like`` fixes dtype/device of plain data)."""
    return float_tensor(v, name, own, like, min_dim=min_dim, numpy=True, whose="the model's")


def _pos_int(v: Any, name: str, own: str, least: int = 1) -> int:
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or int(v) < least:
        raise ValueError(f"{own}: argument '{name}' must be an int >= {least}, got {v!r}")
    return int(v)


def _nonneg(v: Any, name: str, own: str, positive: bool = False) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float, np.floating, np.integer)):
        raise TypeError(f"{own}: argument '{name}' must be a number, got {type(v).__name__}")
    v = float(v)
    if not (np.isfinite(v) and (v > 0 if positive else v >= 0)):
        raise ValueError(f"{own}: argument '{name}' must be {'positive' if positive else 'non-negative'} "
                         f"and finite, got {v!r}")
    return v


def _positions(demos: Any, dt: Any, own: str, min_T: int) -> tuple[Tensor, float]:
    """``(x (*B, N, T, D), dt)`` from a :class:`Demonstrations` or a tensor with ``dt``."""
    if isinstance(demos, Demonstrations):
        if dt is not None and abs(float(dt) - demos.dt) > 1e-12 * demos.dt:
            raise ValueError(f"{own}: argument 'dt' = {dt} disagrees with the demonstrations' dt = "
                             f"{demos.dt}")
        x, dt = demos.x, demos.dt
    else:
        x = _tensor(demos, "demos", own, min_dim=3)
        if dt is None:
            raise ValueError(f"{own}: argument 'dt' is required when 'demos' is a tensor (*B, N, T, D)")
        dt = _nonneg(dt, "dt", own, positive=True)
    if x.shape[-2] < min_T or x.shape[-1] < 1 or x.shape[-3] < 1:
        raise ValueError(f"{own}: argument 'demos' must be (*B, N, T, D) with T >= {min_T}, got "
                         f"{tuple(x.shape)}")
    return x, dt


def _steps(t_idx: Any, T: int, own: str, device) -> Tensor:
    """Time indices as a long tensor ``(*B, V)`` (or ``(V,)``), each in ``[0, T-1]`` (from ints, a sequence of
    ints, an integer numpy array or a long tensor)."""
    if isinstance(t_idx, (int, np.integer)) and not isinstance(t_idx, bool):
        t_idx = [int(t_idx)]
    if isinstance(t_idx, np.ndarray) and t_idx.dtype.kind in "iu":
        t_idx = torch.from_numpy(t_idx.astype(np.int64))
    if isinstance(t_idx, Tensor):
        if t_idx.dtype.is_floating_point or t_idx.dtype == torch.bool or t_idx.dim() < 1:
            raise TypeError(f"{own}: argument 't_idx' must be ints (V,) or a long tensor (*B, V), got "
                            f"{t_idx.dtype} {tuple(t_idx.shape)}")
        t = t_idx.to(device=device, dtype=torch.int64)
    else:
        if not isinstance(t_idx, Sequence) or len(t_idx) == 0 or not all(
                isinstance(i, (int, np.integer)) and not isinstance(i, bool) for i in t_idx):
            raise TypeError(f"{own}: argument 't_idx' must be a non-empty sequence of ints or a long tensor, "
                            f"got {t_idx!r}")
        t = torch.tensor([int(i) for i in t_idx], dtype=torch.int64, device=device)
    if t.numel() == 0:
        raise ValueError(f"{own}: argument 't_idx' is empty")
    if int(t.min()) < 0 or int(t.max()) >= T:
        raise ValueError(f"{own}: argument 't_idx' must lie in [0, {T - 1}], got {t.tolist()}")
    return t


def _finite(M: Tensor) -> Tensor:
    """``(...)`` whether each matrix of ``M (..., m, m)`` is finite."""
    return torch.isfinite(M).all(-1).all(-1)


def _eye_where(ok: Tensor, M: Tensor) -> Tensor:
    """``M (..., m, m)`` with the identity for the matrices where ``ok (...)`` is False (stand-in data, so
    that a decomposition of the batch never fails because of one bad element)."""
    eye = torch.eye(M.shape[-1], dtype=M.dtype, device=M.device)
    return torch.where(ok[..., None, None], M, eye)


#: eigenvalues of an innovation covariance below this · q · ε · scale count as zero (:func:`_psd_pinv`)
_PINV_RTOL = 100.0


def _psd_pinv(W: Tensor, scale: Tensor) -> Tensor:
    """Pseudo-inverse ``W⁺`` of symmetric PSD matrices ``W (*B, q, q)``; eigenvalues ``≤ tol · scale``
    (``scale (*B,)``, ``tol = _PINV_RTOL q ε = 100 q ε``) count as zero, i.e. as directions without variance.

    The range basis ``V_r`` (eigenvectors of the kept eigenvalues) is taken without a graph and
    ``W⁺ = V_r (V_rᵀ W V_r)⁻¹ V_rᵀ`` is differentiated through a Cholesky inverse: for a full-rank ``W`` this
    is ``W⁻¹`` with its exact gradient (whatever orthogonal ``V``), for a rank-deficient one the gradient at
    a fixed range.  A non-finite ``W`` gives NaN for that element only.
    """
    ok = _finite(W) & torch.isfinite(scale)
    Wf = _eye_where(ok, W)
    with torch.no_grad():
        lam, V = torch.linalg.eigh(Wf)
        tol = _PINV_RTOL * W.shape[-1] * torch.finfo(W.dtype).eps
        keep = lam > tol * torch.where(ok, scale, torch.ones_like(scale)).unsqueeze(-1)
        block = keep.unsqueeze(-1) & keep.unsqueeze(-2)  # the kept x kept block of Vᵀ W V
    M = torch.where(block, V.mT @ Wf @ V, torch.eye(W.shape[-1], dtype=W.dtype, device=W.device))
    Minv = torch.where(block, torch.cholesky_inverse(torch.linalg.cholesky_ex(M)[0]), 0.0)
    return torch.where(ok[..., None, None], V @ Minv @ V.mT, torch.nan)


def _check_noise(noise: Tensor, own: str) -> None:
    """Refuse a (finite) noise covariance ``(..., d, d)`` that is not symmetric positive semi-definite."""
    ok = _finite(noise)
    Nf = torch.where(ok[..., None, None], noise, 0.0).detach()
    mag = Nf.abs().amax(dim=(-2, -1), keepdim=True)
    tol = 100 * noise.shape[-1] * torch.finfo(noise.dtype).eps * mag
    if bool(((Nf - Nf.mT).abs() > tol).any()):
        raise ValueError(f"{own}: argument 'noise' must be symmetric (a covariance (*B, V, d, d))")
    if bool((torch.linalg.eigvalsh(Nf) < -tol.squeeze(-1)).any()):
        raise ValueError(f"{own}: argument 'noise' must be positive semi-definite (a covariance)")


def _push_step(at: Any, T: int, own: str) -> int:
    """``at`` (a Python or numpy int in ``[0, T-1]``) as an int."""
    if isinstance(at, bool) or not isinstance(at, (int, np.integer)) or not 0 <= int(at) < T:
        raise ValueError(f"{own}: argument 'at' must be an int in [0, {T - 1}], got {at!r}")
    return int(at)


# --------------------------------------------------------------------------------------------------
# DMP-like: one demo -> one LQT with control primitives (§7.7)
# --------------------------------------------------------------------------------------------------


class Reproduction(NamedTuple):
    """A closed-loop reproduction: ``x (*B, T, 2D)`` states ``[p; ṗ]`` (positions ``x[..., :D]``) and
    ``u (*B, T-1, D)`` accelerations."""

    x: Tensor
    u: Tensor


@dataclass(frozen=True, eq=False)
class DMP:
    """``N`` DMP-like primitives, one per demo (seed §7.7), solved as one batch (:func:`fit_dmp`).

    Attributes:
        lqt: the batched :class:`~controllers.lqt_cookbook.DMPLQT` (problem, primitives ``Ψ``, open-loop plan
            of Eq. 62 with ``u = Ψ w``, feedback gains ``K_t`` of the same cost, Eq. 78); batch ``(*B, N)``.
        dt: time step; D: position dimension.
    """

    lqt: DMPLQT
    dt: float
    D: int

    @property
    def T(self) -> int:
        """Number of samples (``T-1`` controls)."""
        return self.lqt.problem.T + 1

    def plan(self) -> Tensor:
        """``(*B, N, T, 2D)`` the open-loop plan from the demonstrated start."""
        return self.lqt.plan.x

    def reproduce(self, x0: Tensor | None = None, goal: Tensor | None = None,
                  perturbation: Tensor | None = None, at: int | None = None) -> Reproduction:
        """Closed-loop reproduction ``u_t = û_t + K_t (x_t - x̂_t)`` (:func:`dmp_rollout`).

        Args:
            x0: start ``(..., 2D)`` (state) or ``(..., D)`` (positions; the velocity is the plan's); default
                the demonstrated start.  Leading dims broadcast with the DMPs' ``(*B, N)``.
            goal: new end point ``(..., D)`` (reached at rest) or ``(..., 2D)``: the plan is re-solved with
                this reference at ``T-1`` (the gains ``K_t`` do not depend on references and are kept).
            perturbation: a push ``(..., D)`` (positions) or ``(..., 2D)`` added to the state at step ``at``.
            at: the step of the push (a Python or numpy int), default ``T // 2`` (mid-course).
        Returns:
            :class:`Reproduction` with batch ``broadcast((*B, N), ...)``.
        """
        own = "DMP.reproduce"
        lq, D = self.lqt, self.D
        n = 2 * D
        like = lq.plan.x

        def full(v: Tensor | None, name: str, fill: Tensor | None) -> Tensor | None:
            if v is None:
                return None
            v = _tensor(v, name, own, like=like)
            if v.shape[-1] == n:
                return v
            if v.shape[-1] != D:
                raise ValueError(f"{own}: argument '{name}' must have last dim {D} (positions) or {n} "
                                 f"(states), got {tuple(v.shape)}")
            if fill is None:
                return torch.cat([v, torch.zeros_like(v)], -1)
            bs = torch.broadcast_shapes(v.shape[:-1], fill.shape[:-1])
            return torch.cat([v.expand(*bs, D), fill.expand(*bs, D)], -1)

        x0 = full(x0, "x0", like[..., 0, D:])
        goal = full(goal, "goal", None)
        perturbation = full(perturbation, "perturbation", None)
        if perturbation is not None and at is None:
            at = (self.T - 1) // 2
        if at is not None and perturbation is None:
            raise ValueError(f"{own}: argument 'at' needs a 'perturbation'")
        if at is not None:
            at = _push_step(at, self.T, own)
        if goal is not None:
            p = lq.problem
            Tc = p.T
            x_ref = goal.unsqueeze(-2).expand(*goal.shape[:-1], Tc + 1, n)
            cost = QuadraticCost(p.cost.Q, p.cost.R, x_ref=x_ref, u_ref=p.cost.u_ref, check=False)
            prob = LQProblem(p.dynamics, cost, p.x0, horizon=Tc)
            lq = lq._replace(problem=prob, plan=solve_lifted(prob, Psi=lq.Psi))
        x, u = dmp_rollout(lq, x0=x0, perturbation=perturbation, at=at)
        return Reproduction(x=x, u=u)


def fit_dmp(demos: Demonstrations | Tensor, *, dt: float | None = None, n_basis: int = 20,
            goal_weight: float = 1e6, accel_weight: float = 1.0) -> DMP:
    """DMP-like primitives (seed §7.7) of every demo at once: :func:`~controllers.lqt_cookbook.dmp_lqt` on the
    positions ``(*B, N, T, D)`` (a :class:`Demonstrations`' ``x``, or a tensor with ``dt``), batched over the
    demos (``dmp_lqt`` batches over leading dims; no loop here).  Each demo: a double integrator tracking
    its accelerations with ``u = Ψ w`` (``n_basis`` normalized RBFs per dimension) and reaching its end
    point at rest with precision ``goal_weight``."""
    own = "fit_dmp"
    x, dt = _positions(demos, dt, own, min_T=3)
    _pos_int(n_basis, "n_basis", own)
    _nonneg(goal_weight, "goal_weight", own, positive=True)
    _nonneg(accel_weight, "accel_weight", own, positive=True)
    lq = dmp_lqt(x, dt, n_basis=int(n_basis), goal_weight=float(goal_weight),
                 accel_weight=float(accel_weight))
    return DMP(lqt=lq, dt=float(dt), D=int(x.shape[-1]))


# --------------------------------------------------------------------------------------------------
# ProMP-like: many demos -> a Gaussian on z = [x_1; w] (§7.3)
# --------------------------------------------------------------------------------------------------


def integrator_chain(D: int, order: int, dt: float, dtype: torch.dtype = torch.float64,
                     device: torch.device | str | None = None) -> LinearDynamics:
    """``x = [p; ṗ; ...; p^(k-1)]`` ``(k D)``, ``u = p^(k)`` ``(D)``, ``A = I + A^c Δt``, ``B = B^c Δt``
    (Eq. 192 generalized to order ``k``; ``k = 2`` is :func:`~controllers.lqt_cookbook.double_integrator`)."""
    own = "integrator_chain"
    D, order = _pos_int(D, "D", own), _pos_int(order, "order", own)
    dt = _nonneg(dt, "dt", own, positive=True)
    if order == 2:
        return double_integrator(D, dt, dtype, device)
    n = order * D
    shift = torch.diag(torch.ones(n - D, dtype=dtype, device=device), D)
    A = torch.eye(n, dtype=dtype, device=device) + dt * shift
    B = torch.zeros(n, D, dtype=dtype, device=device)
    B[n - D:] = dt * torch.eye(D, dtype=dtype, device=device)
    return LinearDynamics(A, B)


class Tracking(NamedTuple):
    """Result of :meth:`ProMP.track`.

    Attributes:
        x: ``(*B, T, n)`` closed-loop states; u: ``(*B, T-1, D)`` controls (``u_t = K_t x_t + k_t``).
        K: ``(*B, T-1, D, n)``, k: ``(*B, T-1, D)`` the LQT's feedback law.
        precision: ``(*B, T, n, n)`` the tracking precisions ``(Σ_t + floor I)⁻¹``.
        status: per-element :class:`~controllers.problem.SolverStatus` of the Riccati solve.
    """

    x: Tensor
    u: Tensor
    K: Tensor
    k: Tensor
    precision: Tensor
    status: SolverStatus


@dataclass(frozen=True, eq=False)
class ProMP:
    """A Gaussian trajectory distribution from an LQT with control primitives (seed §7.3; :func:`fit_promp`).

    Attributes:
        mean: ``(*B, P)`` mean of ``z = [x_1; w]`` (``P = n + K D``, ``n = order · D``).
        cov: ``(*B, P, P)`` its covariance (the demos' sample covariance ``+ reg I``, or a conditioned one).
        S: ``(T n, P)`` the map ``x = S z`` (``[S_x, S_u Ψ]``, time-major stacked states).
        Psi: ``((T-1) D, K D)`` control primitives (Eq. 66).
        dynamics: the integrator chain; dt, D, order, T (samples).
        params: ``(*B, N, P)`` the demos' own ``z_i`` (``None`` after conditioning).
    """

    mean: Tensor
    cov: Tensor
    S: Tensor
    Psi: Tensor
    dynamics: LinearDynamics
    dt: float
    D: int
    order: int
    T: int
    params: Tensor | None = None

    # --- sizes ------------------------------------------------------------------------------------------
    @property
    def n(self) -> int:
        """State dimension ``order · D``."""
        return self.order * self.D

    @property
    def batch_shape(self) -> torch.Size:
        return self.mean.shape[:-1]

    def _rows(self) -> Tensor:
        return self.S.reshape(self.T, self.n, -1)

    # --- distributions ------------------------------------------------------------------------------------
    def state_mean(self) -> Tensor:
        """``(*B, T, n)``: ``S μ_z``."""
        return (self.mean @ self.S.mT).reshape(*self.batch_shape, self.T, self.n)

    def state_cov(self) -> Tensor:
        """``(*B, T n, T n)``: ``S Σ_z Sᵀ`` over the whole trajectory (time-major)."""
        return self.S @ self.cov @ self.S.mT

    def state_marginal_cov(self) -> Tensor:
        """``(*B, T, n, n)``: the per-step blocks ``S_t Σ_z S_tᵀ`` of :meth:`state_cov`."""
        Sr = self._rows()
        return torch.einsum("tip,...pq,tjq->...tij", Sr, self.cov, Sr)

    def control_mean(self) -> Tensor:
        """``(*B, T-1, D)``: ``Ψ μ_w``."""
        return (self.mean[..., self.n:] @ self.Psi.mT).reshape(*self.batch_shape, self.T - 1, self.D)

    def control_cov(self) -> Tensor:
        """``(*B, (T-1) D, (T-1) D)``: ``Ψ Σ_w Ψᵀ`` (the control-space covariance, cf. Eq. 63)."""
        return self.Psi @ self.cov[..., self.n:, self.n:] @ self.Psi.mT

    def reproductions(self) -> Tensor:
        """``(*B, N, T, n)``: each demo's fitted trajectory ``S z_i``."""
        if self.params is None:
            raise ValueError("ProMP.reproductions: this distribution has no per-demo parameters "
                             "(it was conditioned)")
        return (self.params @ self.S.mT).unflatten(-1, (self.T, self.n))

    # --- conditioning ---------------------------------------------------------------------------------------
    def _start_observation(self, x1: Tensor, own: str) -> tuple[Tensor, Tensor]:
        x1 = _tensor(x1, "x1", own, like=self.mean)
        if x1.shape[-1] == self.n:
            C = torch.eye(self.n, dtype=x1.dtype, device=x1.device)
        elif x1.shape[-1] == self.D:
            C = torch.eye(self.D, self.n, dtype=x1.dtype, device=x1.device)
        else:
            raise ValueError(f"{own}: argument 'x1' must have last dim {self.n} (state) or {self.D} "
                             f"(positions), got {tuple(x1.shape)}")
        return x1, C

    def condition(self, t_idx: Sequence[int] | Tensor, targets: Tensor, noise: float | Tensor = 0.0,
                  C: Tensor | None = None) -> ProMP:
        """The distribution conditioned on via points ``y_v = C x_{t_v} + ε_v``, ``ε_v ~ N(0, noise)``.

        Gaussian conditioning in ``z``-space (``H = C S_t`` stacked over the via points)::

            K = Σ Hᵀ (H Σ Hᵀ + Σ_ε)⁻¹,   μ' = μ + K (y - H μ),   Σ' = (I - K H) Σ (I - K H)ᵀ + K Σ_ε Kᵀ

        (Joseph's form of ``Σ - K H Σ``: symmetric and PSD by construction).  The inverse is the
        pseudo-inverse of the PSD innovation covariance ``H Σ Hᵀ + Σ_ε`` (eigenvalues below ``100 q ε`` times
        the scale ``max_i (Σ_j |H_ij| √Σ_jj)² + max_i (Σ_ε)_ii`` count as zero; ``q`` observations), so that
        noiseless observations that are redundant (a via point given twice, a rank-deficient ``C``, a point
        already conditioned on) give the same result as the independent ones alone.  Inconsistent noiseless
        observations of the same quantity give their least-squares compromise (e.g. the same step twice with
        targets ``a``, ``b``: the mean passes through ``(a + b) / 2``), not an error.

        Args:
            t_idx: ``V`` steps in ``[0, T-1]`` (ints), or a long tensor ``(*B', V)`` (per via-point set).
            targets: ``(*B', V, d)``; ``*B'`` broadcasts with the distribution's batch (several via-point
                sets at once).
            noise: observation variance ``σ² ≥ 0`` (``σ² I``), or a symmetric PSD covariance
                ``(*B', V, d, d)`` (else ``ValueError``).  ``0`` passes exactly through the via points.
            C: ``(d, n)`` observed linear function of the state; default the positions ``[I_D, 0]``.
        Returns:
            a :class:`ProMP` with batch ``broadcast(*B, *B')`` and ``params=None``.
        """
        own = "ProMP.condition"
        like = self.mean
        if C is None:
            C = torch.eye(self.D, self.n, dtype=like.dtype, device=like.device)
        C = _tensor(C, "C", own, like=like, min_dim=2)
        if C.dim() != 2 or C.shape[1] != self.n:
            raise ValueError(f"{own}: argument 'C' must be (d, {self.n}), got {tuple(C.shape)}")
        d = C.shape[0]
        t = _steps(t_idx, self.T, own, like.device)
        V = t.shape[-1]
        targets = _tensor(targets, "targets", own, like=like, min_dim=2)
        if tuple(targets.shape[-2:]) != (V, d):
            raise ValueError(f"{own}: argument 'targets' must be (*B, {V}, {d}) for {V} via point(s) of "
                             f"dimension {d}, got {tuple(targets.shape)}")
        if isinstance(noise, Tensor):
            noise = _tensor(noise, "noise", own, like=like, min_dim=2)
            if noise.dim() < 3 or tuple(noise.shape[-3:]) != (V, d, d):
                raise ValueError(f"{own}: argument 'noise' must be a float or (*B, {V}, {d}, {d}), got "
                                 f"{tuple(noise.shape)}")
            _check_noise(noise, own)
            R = torch.zeros(*noise.shape[:-3], V * d, V * d, dtype=like.dtype, device=like.device)
            for v in range(V):  # block diagonal over the via points (a loop over V, not over the batch)
                R[..., v * d:(v + 1) * d, v * d:(v + 1) * d] = noise[..., v, :, :]
        else:
            R = _nonneg(noise, "noise", own) * torch.eye(V * d, dtype=like.dtype, device=like.device)
        H = (C @ self._rows()[t]).flatten(-3, -2)  # (*B', V d, P)
        return self._update(H, targets.flatten(-2), R)

    def _update(self, H: Tensor, y: Tensor, R: Tensor) -> ProMP:
        """Condition on ``y = H z + ε``, ``ε ~ N(0, R)`` (``H (*B', q, P)``, ``y (*B', q)``, ``R (*B', q, q)``
        PSD; the formulas and the pseudo-inverse of :meth:`condition`)."""
        mu, Sig = self.mean, self.cov
        SHt = Sig @ H.mT  # (*B, P, q)
        Syy = H @ SHt + R
        Syy = 0.5 * (Syy + Syy.mT)
        with torch.no_grad():  # bound on H Σ Hᵀ's entries (Cauchy-Schwarz, |Σ_jk| ≤ s_j s_k) plus the noise's
            s = Sig.diagonal(dim1=-2, dim2=-1).clamp_min(0).sqrt()
            scale = (((H.abs() @ s.unsqueeze(-1)).squeeze(-1) ** 2).amax(-1)
                     + R.diagonal(dim1=-2, dim2=-1).amax(-1))
        K = SHt @ _psd_pinv(Syy, scale)  # (*B, P, q)
        r = y - (H @ mu.unsqueeze(-1)).squeeze(-1)
        mean = mu + (K @ r.unsqueeze(-1)).squeeze(-1)
        eye = torch.eye(Sig.shape[-1], dtype=Sig.dtype, device=Sig.device)
        IKH = eye - K @ H
        cov = IKH @ Sig @ IKH.mT + K @ R @ K.mT
        cov = 0.5 * (cov + cov.mT)
        bs = torch.broadcast_shapes(mean.shape[:-1], cov.shape[:-2])
        return ProMP(mean=mean.expand(*bs, mean.shape[-1]), cov=cov.expand(*bs, *cov.shape[-2:]), S=self.S,
                     Psi=self.Psi, dynamics=self.dynamics, dt=self.dt, D=self.D, order=self.order, T=self.T,
                     params=None)

    def given_start(self, x1: Tensor) -> ProMP:
        """Conditioned on the start ``x_0 = x1`` exactly (``x1 (*B', n)`` state or ``(*B', D)`` positions)."""
        x1, C = self._start_observation(x1, "ProMP.given_start")
        H = C @ self._rows()[0]
        R = torch.zeros(C.shape[0], C.shape[0], dtype=x1.dtype, device=x1.device)
        return self._update(H, x1, R)

    def mean_trajectory(self, x1: Tensor | None = None) -> Tensor:
        """``(*B, T, n)`` the mean states; with ``x1`` the mean given that start (:meth:`given_start`)."""
        return (self if x1 is None else self.given_start(x1)).state_mean()

    def sample(self, n: int, generator: torch.Generator, x1: Tensor | None = None) -> Tensor:
        """``(n, *B, T, n_x)`` state trajectories ``S z`` with ``z ~ N(μ, Σ)`` (given ``x1`` when passed).

        ``z = μ + L ε`` with the Cholesky factor ``L`` of ``Σ`` (reparameterized: differentiable in ``μ`` and
        ``Σ``); an element whose ``Σ`` is only semi-definite (e.g. after noiseless conditioning) uses the
        factor ``V √max(λ, 0)`` of its eigendecomposition instead.  An element with a non-finite ``Σ`` gives
        NaN samples and leaves the others unchanged.
        """
        own = "ProMP.sample"
        n = _pos_int(n, "n", own)
        if not isinstance(generator, torch.Generator):
            raise TypeError(f"{own}: argument 'generator' must be a torch.Generator, got "
                            f"{type(generator).__name__}")
        dist = self if x1 is None else self.given_start(x1)
        cov = dist.cov
        ok = _finite(cov)
        L = self._factor(_eye_where(ok, cov))
        L = torch.where(ok[..., None, None], L, torch.nan)
        P = cov.shape[-1]
        eps = torch.randn(n, *dist.batch_shape, P, generator=generator, dtype=cov.dtype,
                          device=generator.device).to(cov.device)
        z = dist.mean + (L @ eps.unsqueeze(-1)).squeeze(-1)
        return (z @ self.S.mT).unflatten(-1, (self.T, self.n))

    @staticmethod
    def _factor(cov: Tensor) -> Tensor:
        """``L`` with ``L Lᵀ = cov`` for finite PSD ``cov (*B, P, P)``: Cholesky, or ``V √max(λ, 0)`` from the
        eigendecomposition for the elements where it fails."""
        L, info = torch.linalg.cholesky_ex(cov)
        bad = info != 0
        if bool(bad.any()):
            lam, Vec = torch.linalg.eigh(_eye_where(bad, cov))
            Le = Vec * lam.clamp_min(0).sqrt().unsqueeze(-2)
            L = torch.where(bad[..., None, None], Le, L)
        return L

    # --- minimal intervention tracking (§7.7) -------------------------------------------------------------
    def _precisions(self, floor: float, own: str) -> Tensor:
        """``(*B, T, n, n)`` the precisions ``(Σ_t + floor I)⁻¹`` (NaN where ``Σ_t`` is not finite)."""
        eye = torch.eye(self.n, dtype=self.mean.dtype, device=self.mean.device)
        Sig = self.state_marginal_cov() + floor * eye
        ok = _finite(Sig)
        L, info = torch.linalg.cholesky_ex(_eye_where(ok, Sig))
        if bool((info != 0).any()):
            raise ValueError(f"{own}: argument 'floor' = {floor} leaves a state covariance Σ_t + floor I "
                             f"that is not positive definite (Σ_0 = 0 after given_start?); use floor > 0")
        Q = torch.cholesky_inverse(L)
        return torch.where(ok[..., None, None], 0.5 * (Q + Q.mT), torch.nan)

    def track(self, x0: Tensor | None = None, *, control_weight: float = 1e-6, floor: float = 1e-6,
              perturbation: Tensor | None = None, at: int | None = None) -> Tracking:
        """LQT tracking the mean with precision ``Q_t = (Σ_t + floor I)⁻¹`` per step (seed §7.7: stiff where
        the demos agree, compliant where they vary), control weight ``R = control_weight I``, from ``x0``
        (``(*B', n)`` state or ``(*B', D)`` positions with the mean start velocity; default the mean start),
        solved by Riccati (:func:`controllers.riccati.solve`) and rolled out in closed loop with an optional
        push ``perturbation`` (``(*B', D)`` or ``(*B', n)``) added at step ``at`` (default ``T // 2``).

        Differentiable: the Riccati recursion is unrolled (``grad="unrolled"``), so that the gains ``K_t``,
        ``k_t`` of the rollout carry the gradient of the demos, via points and ``x0``.  An element with a
        non-finite covariance or mean gets NaN outputs and a failed ``status``, the others are unchanged; a
        finite ``Σ_t + floor I`` that is not positive definite (e.g. ``floor = 0`` after an exact
        :meth:`given_start`, where ``Σ_0 = 0``) raises a ``ValueError`` naming ``floor``."""
        own = "ProMP.track"
        control_weight = _nonneg(control_weight, "control_weight", own, positive=True)
        floor = _nonneg(floor, "floor", own)
        like = self.mean
        mu = self.state_mean()
        if x0 is None:
            x0 = mu[..., 0, :]
        else:
            x0 = _tensor(x0, "x0", own, like=like)
            if x0.shape[-1] == self.D:
                x0 = torch.cat([x0, mu[..., 0, self.D:].expand(*x0.shape[:-1], self.n - self.D)], -1)
            elif x0.shape[-1] != self.n:
                raise ValueError(f"{own}: argument 'x0' must have last dim {self.D} or {self.n}, got "
                                 f"{tuple(x0.shape)}")
        if perturbation is not None:
            perturbation = _tensor(perturbation, "perturbation", own, like=like)
            if perturbation.shape[-1] == self.D:
                perturbation = torch.cat([perturbation, perturbation.new_zeros(
                    *perturbation.shape[:-1], self.n - self.D)], -1)
            elif perturbation.shape[-1] != self.n:
                raise ValueError(f"{own}: argument 'perturbation' must have last dim {self.D} or {self.n}, "
                                 f"got {tuple(perturbation.shape)}")
            at = (self.T - 1) // 2 if at is None else at
        if at is not None and perturbation is None:
            raise ValueError(f"{own}: argument 'at' needs a 'perturbation'")
        if at is not None:
            at = _push_step(at, self.T, own)
        Q = self._precisions(floor, own)
        Rw = control_weight * torch.eye(self.D, dtype=like.dtype, device=like.device)
        cost = QuadraticCost(Q, Rw, x_ref=mu, check=False)
        sol = riccati_solve(LQProblem(self.dynamics, cost, x0, horizon=self.T - 1), grad="unrolled")
        A, B = self.dynamics.A[0], self.dynamics.B[0]
        x = sol.x[..., 0, :]
        xs, us = [], []
        for t in range(self.T):
            if at == t:
                x = x + perturbation
            xs.append(x)
            if t == self.T - 1:
                break
            u = (sol.K[..., t, :, :] @ x.unsqueeze(-1)).squeeze(-1) + sol.k[..., t, :]
            us.append(u)
            x = x @ A.mT + u @ B.mT
        bs = torch.broadcast_shapes(*(v.shape[:-1] for v in xs + us))
        return Tracking(x=torch.stack([v.expand(*bs, self.n) for v in xs], -2),
                        u=torch.stack([v.expand(*bs, self.D) for v in us], -2), K=sol.K, k=sol.k, precision=Q,
                        status=sol.status)


def _start_states(p: Tensor, order: int, dt: float) -> Tensor:
    """``[p_0; Δp_0/Δt; ...; Δ^{k-1}p_0/Δt^{k-1}]`` from positions ``p (..., T, D)`` (forward differences):
    from this state the integrator chain passes through ``p_0 .. p_{k-1}`` whatever the inputs (an input
    reaches the position only ``k`` steps later)."""
    parts, d = [], p
    for _ in range(order):
        parts.append(d[..., 0, :])
        d = (d[..., 1:, :] - d[..., :-1, :]) / dt
    return torch.cat(parts, -1)


def fit_promp(demos: Demonstrations | Tensor, *, dt: float | None = None, n_basis: int = 10, order: int = 2,
              reg: float | None = None, basis_fn: str = "rbf") -> ProMP:
    """Fit the ProMP-like distribution of :class:`ProMP` to demos (seed §7.3, module docstring).

    Args:
        demos: a :class:`Demonstrations` (positions ``x (N, T, D)``) or a tensor ``(*B, N, T, D)`` (several
            sets of demos at once, e.g. several letters; then ``dt`` is required).  ``N >= 2``.
        n_basis: ``K`` basis functions per dimension for the controls ``u = Ψ w``.
        order: ``k`` of the integrator chain (``2``: double integrator, accelerations as controls).
        reg: relative ridge of the weight fit and of the covariance (below); default ``1e-8`` in float64,
            ``1e-5`` in float32.
        basis_fn: ``"rbf"`` (normalized Gaussian RBFs), ``"bernstein"`` or ``"fourier"``
            (:mod:`controllers.basis`).

    The weights solve ``min_w ‖p_i - P(S_x x_{1,i} + S_u Ψ w)‖² + λ ‖w‖²`` (``P`` keeps the positions) for
    all demos at once, by one QR factorization of ``[M; √λ I]`` with ``M = P S_u Ψ`` (shared) and
    ``λ = reg · tr(MᵀM) / (K D)`` (relative to the scale of ``MᵀM``).  The covariance is
    ``Σ_z = Σ̂ + reg · tr(Σ̂)/P · I`` (``Σ̂`` the demos' sample covariance, ``ddof = 1``; ``+ reg I`` when
    ``Σ̂ = 0``).
    """
    own = "fit_promp"
    x, dt = _positions(demos, dt, own, min_T=2)
    order = _pos_int(order, "order", own)
    K = _pos_int(n_basis, "n_basis", own)
    *bs, N, T, D = x.shape
    if N < 2:
        raise ValueError(f"{own}: argument 'demos' needs N >= 2 demonstrations for a covariance, got N = {N}")
    if T < order + 1:
        raise ValueError(f"{own}: argument 'demos' needs T >= order + 1 = {order + 1} samples, got T = {T}")
    if reg is None:
        reg = 1e-8 if x.dtype == torch.float64 else 1e-5
    reg = _nonneg(reg, "reg", own)
    fns = {"rbf": lambda: basis.rbf(T - 1, K, normalized=True, dtype=x.dtype, device=x.device),
           "bernstein": lambda: basis.bernstein(T - 1, K, dtype=x.dtype, device=x.device),
           "fourier": lambda: basis.fourier(T - 1, K, dtype=x.dtype, device=x.device)}
    if basis_fn not in fns:
        raise ValueError(f"{own}: argument 'basis_fn' must be one of {sorted(fns)}, got {basis_fn!r}")
    n = order * D
    dyn = integrator_chain(D, order, dt, x.dtype, x.device)
    Psi = control_primitives(fns[basis_fn](), D)  # ((T-1) D, K D)
    Sx, Su, _ = transfer_matrices(dyn.A, dyn.B, None, T - 1)
    S = torch.cat([Sx, Su @ Psi], -1)  # (T n, P)
    Sp = S.reshape(T, n, -1)[:, :D, :].reshape(T * D, -1)  # position rows
    M = Sp[:, n:]
    x1 = _start_states(x, order, dt)  # (*B, N, n)
    r = x.reshape(*bs, N, T * D) - x1 @ Sp[:, :n].mT  # (*B, N, T D)
    # ridge least squares by QR of [M; √λ I] (better conditioned than the normal equations in float32)
    lam = reg * (M * M).sum(0).mean()  # ridge relative to the scale of MᵀM (its mean diagonal)
    Kd = M.shape[1]
    Qm, Rm = torch.linalg.qr(torch.cat([M, lam.sqrt() * torch.eye(Kd, dtype=x.dtype, device=x.device)], 0))
    if not bool((Rm.diagonal().abs() > Rm.diagonal().abs().amax() * torch.finfo(x.dtype).eps * Kd).all()):
        raise ValueError(f"{own}: the weight fit is singular (n_basis = {K} for T = {T} samples with "
                         f"reg = {reg}); pass reg > 0 or fewer basis functions")
    rhs = (r @ Qm[:T * D]).unsqueeze(-1)
    W = torch.linalg.solve_triangular(Rm, rhs, upper=True).squeeze(-1)  # (*B, N, K D)
    Z = torch.cat([x1, W], -1)  # (*B, N, P)
    mean = Z.mean(-2)
    Zc = Z - mean.unsqueeze(-2)
    P = Z.shape[-1]
    cov = Zc.mT @ Zc / (N - 1)
    scale = cov.diagonal(dim1=-2, dim2=-1).mean(-1)  # (*B,) the mean variance
    lam = reg * torch.where(scale > 0, scale, torch.ones_like(scale))
    cov = cov + lam[..., None, None] * torch.eye(P, dtype=x.dtype, device=x.device)
    return ProMP(mean=mean, cov=cov, S=S, Psi=Psi, dynamics=dyn, dt=float(dt), D=D, order=order, T=T,
                 params=Z)


# --------------------------------------------------------------------------------------------------
# metrics (shared with the benchmark against other movement-primitive packages)
# --------------------------------------------------------------------------------------------------


def _traj(v: Any, name: str, own: str) -> Tensor:
    if isinstance(v, Demonstrations):
        return v.x
    if isinstance(v, np.ndarray):
        v = torch.from_numpy(np.asarray(v, dtype=np.float64))
    return _tensor(v, name, own, min_dim=2)


def _common(a: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:
    dt = torch.promote_types(a.dtype, b.dtype)
    return a.to(dt), b.to(device=a.device, dtype=dt)


def reproduction_error(demos: Demonstrations | Tensor | np.ndarray, generated: Tensor | np.ndarray) -> Tensor:
    """RMS over time of the Euclidean position error, per trajectory:
    ``sqrt(mean_t ‖g_t[:d] - x_t‖²)`` for demos ``(*B, T, d)`` (a :class:`Demonstrations`' ``x``) and
    generated trajectories ``(*B', T, ≥ d)`` (states whose first ``d`` components are positions); the batch
    dims broadcast.  Returns ``(broadcast(*B, *B'),)``."""
    own = "reproduction_error"
    x, g = _common(_traj(demos, "demos", own), _traj(generated, "generated", own))
    d = x.shape[-1]
    if g.shape[-2] != x.shape[-2] or g.shape[-1] < d:
        raise ValueError(f"{own}: argument 'generated' must be (*B, {x.shape[-2]}, >= {d}), got "
                         f"{tuple(g.shape)} for demos {tuple(x.shape)}")
    return ((g[..., :d] - x) ** 2).sum(-1).mean(-1).sqrt()


def via_point_error(traj: Tensor | np.ndarray, t_idx: Sequence[int] | Tensor, targets: Tensor | np.ndarray
                    ) -> Tensor:
    """``(*B, V)`` Euclidean distances ``‖traj[t_v, :d] - target_v‖`` for ``traj (*B, T, ≥ d)``, steps
    ``t_idx`` (``V`` ints or a long tensor ``(*B, V)``) and ``targets (*B, V, d)`` (batch dims broadcast)."""
    own = "via_point_error"
    x, y = _common(_traj(traj, "traj", own), _traj(targets, "targets", own))
    t = _steps(t_idx, x.shape[-2], own, x.device)
    d = y.shape[-1]
    if x.shape[-1] < d or y.shape[-2] != t.shape[-1]:
        raise ValueError(f"{own}: 'traj' (*B, T, >= d), 't_idx' (V,) and 'targets' (*B, V, d) disagree: "
                         f"{tuple(x.shape)}, {tuple(t.shape)}, {tuple(y.shape)}")
    bs = torch.broadcast_shapes(x.shape[:-2], t.shape[:-1])
    idx = t.expand(*bs, t.shape[-1]).unsqueeze(-1).expand(*bs, t.shape[-1], x.shape[-1])
    pts = x.expand(*bs, *x.shape[-2:]).gather(-2, idx)[..., :d]
    return (pts - y).norm(dim=-1)


class Recovery(NamedTuple):
    """Result of :func:`perturbation_recovery` (all ``(*B,)``).

    Attributes:
        final: distance between the perturbed and the unperturbed run at the last step.
        peak: largest distance from step ``at`` on (the push's effect; ``final / peak`` is the fraction left).
        ratio: ``final / peak`` (0 when ``peak`` is 0).
    """

    final: Tensor
    peak: Tensor
    ratio: Tensor


def perturbation_recovery(nominal: Tensor | np.ndarray, perturbed: Tensor | np.ndarray, at: int,
                          d: int | None = None) -> Recovery:
    """How well a push at step ``at`` (mid-course in the benchmark) is recovered: distances between the
    first ``d`` components (positions; default all) of ``perturbed (*B, T, ·)`` and ``nominal (*B', T, ·)``,
    at the end and at worst from ``at`` on."""
    own = "perturbation_recovery"
    a, b = _common(_traj(nominal, "nominal", own), _traj(perturbed, "perturbed", own))
    if a.shape[-2] != b.shape[-2]:
        raise ValueError(f"{own}: 'nominal' and 'perturbed' must have the same T, got {tuple(a.shape)} and "
                         f"{tuple(b.shape)}")
    T = a.shape[-2]
    if isinstance(at, bool) or not isinstance(at, (int, np.integer)) or not 0 <= int(at) < T:
        raise ValueError(f"{own}: argument 'at' must be an int in [0, {T - 1}], got {at!r}")
    d = min(a.shape[-1], b.shape[-1]) if d is None else _pos_int(d, "d", own)
    if d > min(a.shape[-1], b.shape[-1]):
        raise ValueError(f"{own}: argument 'd' = {d} exceeds the trajectories' last dims")
    dist = (b[..., :d] - a[..., :d]).norm(dim=-1)
    final = dist[..., -1]
    peak = dist[..., int(at):].amax(-1)
    ratio = torch.where(peak > 0, final / torch.where(peak > 0, peak, torch.ones_like(peak)),
                        torch.zeros_like(peak))
    return Recovery(final=final, peak=peak, ratio=ratio)
