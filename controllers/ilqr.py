"""Batched iLQR with control limits and implicit gradients (seed 004 §8, §9).

Problem (conventions of :mod:`controllers.problem`: ``x_0 .. x_T``, ``u_0 .. u_{T-1}``, batch first)::

    minimize_u   J(x, u) = Σ_t l_t(x_t, u_t) + l_T(x_T)
    subject to   x_{t+1} = f(x_t, u_t, t),   x_0 given,   u_lower ≤ u_t ≤ u_upper.

Two formulations of the same Gauss–Newton iteration, both with the backtracking line search of
Algorithm 1 (all candidate step sizes rolled out at once, one accepted step size per batch element):

* :attr:`ILQRMethod.RECURSIVE` — Algorithm 5 (Eq. 89–94): backward Riccati pass on the linearization
  (Eq. 91), feedforward ``k_t`` and gains ``K_t`` (Eq. 92), value update (Eq. 93), forward pass with
  ``u_t ← û_t + α k_t + K_t (x_t - x̂_t)`` (Eq. 101).  Control limits as in control-limited DDP (Tassa,
  Mansard & Todorov 2014): the feedforward step solves the box QP of :mod:`controllers.boxqp` on
  ``Q_uu``, and the rows of ``K_t`` of clamped controls are zero.
* :attr:`ILQRMethod.BATCH` — Algorithm 4 (Eq. 87 / 108): the whole control sequence is one decision
  variable; the Gauss–Newton step uses the transfer matrix ``S_u`` (Appendix A, ``Δx = S_u Δu``, from
  :func:`controllers.lifted.transfer_matrices`) and, with control limits, a box QP over all ``T·m``
  controls.  (Open-loop Gauss–Newton converges more slowly than the recursive form on strongly
  nonlinear problems, and may settle in another local minimum.)

Both regularize ``Q_uu`` (resp. the Gauss–Newton matrix) Levenberg–Marquardt style, ``+ μ I`` with the
per-element schedule of Tassa et al., stop per element on a small step (``‖Δu‖∞ ≤ tol (1 + ‖u‖∞)``,
the Δ_min of Algorithms 4–5) or a small relative cost decrease, and record the cost history.

**Status is a certificate.**  A small step or decrease only says that the iteration stopped moving (a
box QP with no descent direction returns a zero step, a large μ shrinks every step).  ``CONVERGED`` is
reported only where the projected reduced gradient ``u − clip(u − ∇_u J)`` — the KKT residual of the
control-limited problem, with ``∇_u J`` through the dynamics by the costates — is below
:attr:`ILQROptions.tol_kkt` relative to its scale (there: the gradient's terms plus the curvature times the
controls, so that the test is scale-invariant and does not depend on how small ``R`` is) at the returned
point; an element that stopped elsewhere is ``STALLED``, and the residual itself is returned
(:attr:`ILQRSolution.kkt_residual`).

Gradients (:class:`~controllers.problem.GradMode`). ``IMPLICIT`` (default): the solver runs without a
graph; at the returned point ``z* = (x*, u*)`` with costates ``λ*`` the stationarity conditions ``∇_z
L(z*, λ*; θ) = 0`` and the dynamics ``c(z*; θ) = 0`` (clamped controls fixed on their bounds) define
``z*(θ)`` implicitly, and

    dz*/dθ = -K⁻¹ [∂∇_z L/∂θ ; ∂c/∂θ],      K = [[∇²_zz L, ∇_z cᵀ], [∇_z c, 0]],

which is the derivative of one Newton step on the KKT system — an LQ problem on the linearization with the
exact Lagrangian Hessian, solved by :func:`controllers.implicit.ilqr_implicit` with the LQ kernels (and their
own implicit backward).  Memory is O(T) and the cost is independent of the number of iLQR iterations; θ is
anything ``x0``, the cost or the dynamics depend on (references, weights, a pendulum's length...).
``UNROLLED``: autograd through every iteration.  ``NONE``: no graph.  Elements that did not converge still get
the implicit formula at their last iterate and are flagged in ``status`` — never detached.
"""

from __future__ import annotations

import contextlib
import dataclasses
import enum
import math
from dataclasses import dataclass

import torch
from torch import Tensor

from controllers import _compiled
from controllers._ilqr_step import (
    Iterate,
    Settings,
    grow,
    kkt_floor,
    kkt_relative,
    line_search,
    linearize,
    mark_certified,
    program_iteration,
    program_supported,
    stop_checks,
)
from controllers._ilqr_sweeps import backward_pass
from controllers._validate import broadcast_batch, check_limit, enum_arg
from controllers.boxqp import box_qp
from controllers.costs import Cost, PeriodicQuadraticCost, QuadraticCost, stand_in_cost
from controllers.dynamics import (
    LinearDynamics,
    System,
    check_system,
    has_analytic_jacobian,
    is_time_invariant,
    rollout,
)
from controllers.implicit import ilqr_implicit, reduced_hessian_pd
from controllers.lifted import transfer_matrices
from controllers.problem import GradMode, Reason, SolverStatus, cost_status_of
from torchlie._batch import broadcast_shapes

__all__ = [
    "ILQRMethod",
    "ILQRProblem",
    "ILQRSolution",
    "ILQROptions",
    "ilqr",
]


class ILQRMethod(str, enum.Enum):
    """Which formulation of iLQR (seed 004 §8)."""

    RECURSIVE = "recursive"  #: Algorithm 5: backward Riccati pass, gains, forward pass (Eq. 89-94)
    BATCH = "batch"  #: Algorithm 4: Gauss-Newton over the whole control sequence (Eq. 87 / 108)


@dataclass(frozen=True)
class ILQROptions:
    """Solver settings (all per element except ``max_iter``).

    Attributes:
        max_iter: iterations at most.
        tol: a step with ``max_t ‖k_t‖∞ ≤ tol · (1 + ‖u‖∞)`` (Δ_min of Algorithms 4-5) is negligible: the
            element stops (``STALLED`` unless certified, below); default by dtype.
        tol_cost: an accepted step that lowers the cost by less than ``tol_cost · |J|`` stops the element
            if the new point is certified (below); otherwise it goes on to a negligible step.
        tol_kkt: the certificate behind ``CONVERGED``, checked at the returned point: the projected reduced
            gradient ``max_t ‖u_t − clip(u_t − ∇_{u_t} J)‖∞`` (``∇_u J = ∂l/∂u_t + B_tᵀ λ_{t+1}`` through the
            dynamics, by the costates ``λ``) is at most ``tol_kkt`` times the scale
            ``max_t ‖|∂l/∂u_t| + |B_tᵀ λ_{t+1}|‖∞ + c · ‖u‖∞``, with ``c = max_t max_i |(Q_uu,t)_ii|`` the
            curvature of the Riccati pass at that point (``Q_uu,t = H_uu,t + B_tᵀ V_{t+1} B_t``: the cost's
            curvature in ``u_t`` with the later controls re-optimized, the pivots of the reduced Hessian).
            Why both: the terms that cancel in the gradient at a free optimum balance ``2 R u`` there, so
            they shrink with ``R``, while a negligible step ``k`` (``tol``, above) leaves a gradient of
            about ``Q_uu k`` — the state cost's curvature, which does not.  Measured against the terms
            alone the residual was unattainable for a small ``R`` (cookbook manipulator, ``R = 1e-6``:
            ``|∇J|∞ = 4e-11``, ratio 1.8e-6 at an optimum; ``R = 1e-10``: most starts), and in floating
            point the rounding of ``u`` alone moves the gradient by ``~ Q_uu ε ‖u‖``.  The ratio is
            a backward error (that of a linear system, ``‖r‖ / (‖b‖ + ‖H‖ ‖x‖)``): invariant to scaling the
            cost, attainable in floating point, and without ``R`` in it; the scale is at least
            ``c · tol / tol_kkt``, so a residual whose Newton step ``|∇J| / c`` is below ``tol`` passes (at an
            optimum where the terms and the controls are ~0, a pendulum held exactly upright, the ratio
            was rounding over rounding: it reported the optimal hold STALLED, and a multi-start then
            chose a certified full swing over it); the Riccati curvature (bounded
            for a stabilizable linearization) rather than the open-loop Hessian, whose norm grows like
            ``‖A‖^{2T}`` on an unstable system (1e18 on the cart-pole benchmark).  Default ``1e-6``
            (float64) or ``1e-3`` (lower precisions).
        mu_init, mu_min, mu_max, mu_factor: Levenberg-Marquardt regularization ``Q_uu + μ I`` with the
            schedule of Tassa et al. (μ below ``mu_min`` becomes 0; above ``mu_max`` the element fails).
        line_search_steps: candidate step sizes ``1, ½, ¼, ...`` (Algorithm 1, α_min = 2^-(steps-1)).
        armijo: accept a step when the decrease reaches this fraction of the predicted one.
        second_order: also check, at every ``CONVERGED`` point, that the exact reduced Hessian (free
            controls, dynamics eliminated, second derivatives of the dynamics included) is positive
            definite (:func:`controllers.implicit.reduced_hessian_pd`, one Riccati sweep on the
            Lagrangian's Hessian by autograd); where it is not, the point is a saddle or maximum and the
            status is ``NOT_A_MINIMUM``.  Off by default: ``CONVERGED`` then certifies a KKT point (first
            order), which the Gauss-Newton model cannot tell from a saddle (a unicycle from rest with
            ``R = 1e-12`` stops on one, J = 3.75 against 1.65).
        compile: run the time sweeps of each iteration (the backward Riccati pass, the costates of the
            certificate, the rollouts of the line search) as compiled programs
            (:mod:`controllers._compiled`): built once per problem structure (1-6 minutes on a 2-core
            machine, then cached on disk across processes), any batch size.  Same numbers as the eager path
            up to round-off.  Sweeps the compiler cannot take run eagerly: three or more limited controls
            (the backward pass's inner box QP), time-varying dynamics, or dynamics whose parameters are
            batched tensors or require grad (the rollouts); ``grad="unrolled"`` runs eagerly.
    """

    max_iter: int = 100
    tol: float | None = None
    tol_cost: float | None = None
    tol_kkt: float | None = None
    mu_init: float = 0.0
    mu_min: float = 1e-6
    mu_max: float = 1e10
    mu_factor: float = 1.6
    line_search_steps: int = 10
    armijo: float = 1e-4
    second_order: bool = False
    compile: bool = False


# --------------------------------------------------------------------------------------------------
# problem and solution
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class ILQRProblem:
    """A batched nonlinear optimal-control problem with box control limits.

    Args:
        dynamics: a :class:`~controllers.dynamics.System`: :class:`~controllers.dynamics.LinearDynamics`,
            :class:`~controllers.dynamics.NonlinearDynamics`, a model from :mod:`controllers.systems`
            or any object with ``n``, ``m``, ``step`` (and optionally ``jacobian``, ``time_invariant``).
        cost: a :class:`~controllers.costs.Cost`: :class:`~controllers.costs.QuadraticCost` (analytic
            derivatives), :class:`~controllers.costs.ResidualCost`, or any object with
            ``evaluate(x (*B, T+1, n), u (*B, T, m)) -> (*B,)`` that is a sum of per-step terms
            (derivatives by autograd unless it has ``derivatives(x, u)``).
        x0: ``(*B, n)`` initial states.
        horizon: ``T``.
        u_lower, u_upper: control limits, ``None`` (unbounded), a float, or tensors broadcastable to
            ``(*B, T, m)`` (0-d, ``(m,)``, ``(T, m)``, ...: time dim 1 or ``T``, control dim 1 or ``m``,
            else a ``ValueError`` naming the field and the expected shape); ``±inf`` entries are unbounded;
            differentiable (a clamped control's derivative w.r.t. its limit is 1, and the rest of the plan
            responds: :func:`ilqr`).  Floats with ``u_lower > u_upper`` are a ``ValueError``; crossed
            tensor limits are checked per element by the solver (``Reason.INFEASIBLE_BOUNDS``, likewise a
            lower limit of +inf or an upper of -inf), so that building a problem never waits for the device
            on batched data.  NaN: a ``ValueError`` in a limit shared by the batch (a float, or a tensor
            without batch dims, checked here), the element's ``NONFINITE_INPUT`` in a batched one.
    """

    dynamics: System
    cost: Cost
    x0: Tensor
    horizon: int
    u_lower: Tensor | float | None = None
    u_upper: Tensor | float | None = None

    def __post_init__(self) -> None:
        own = "ILQRProblem"
        d = self.dynamics
        check_system(d, own)
        if not callable(getattr(self.cost, "evaluate", None)):
            raise TypeError(f"{own}: field 'cost' must have evaluate(x, u), got {type(self.cost).__name__}")
        if not isinstance(self.x0, Tensor) or not self.x0.dtype.is_floating_point:
            raise TypeError(f"{own}: field 'x0' must be a floating tensor (*B, n)")
        n, m = self.n, self.m
        if self.x0.dim() < 1 or self.x0.shape[-1] != n:
            raise ValueError(f"{own}: field 'x0' must have shape (*B, {n}), got {tuple(self.x0.shape)}")
        T = self.horizon
        if not isinstance(T, int) or isinstance(T, bool) or T < 1:
            raise ValueError(f"{own}: field 'horizon' must be a positive int, got {T!r}")
        if isinstance(self.cost, QuadraticCost):
            if self.cost.n != n or self.cost.m != m:
                raise ValueError(f"{own}: cost is for n={self.cost.n}, m={self.cost.m} but dynamics has "
                                 f"n={n}, m={m}")
            if self.cost.horizon not in (None, T):
                raise ValueError(f"{own}: cost has horizon {self.cost.horizon} but the problem has {T}")
            if self.cost.dtype != self.x0.dtype:
                raise TypeError(f"{own}: cost dtype {self.cost.dtype} differs from x0 dtype {self.x0.dtype}")
        if isinstance(d, LinearDynamics):
            if d.horizon not in (None, T):
                raise ValueError(f"{own}: dynamics has horizon {d.horizon} but the problem has {T}")
            if d.dtype != self.x0.dtype:
                raise TypeError(f"{own}: dynamics dtype {d.dtype} differs from x0 dtype {self.x0.dtype}")
        self._check_limits(own)
        self.batch_shape  # noqa: B018  (a ValueError naming the fields when they do not broadcast)
        lo, hi = self.u_lower, self.u_upper
        if isinstance(lo, (int, float)) and isinstance(hi, (int, float)) and lo > hi:
            raise ValueError(f"{own}: u_lower ({lo}) must be <= u_upper ({hi})")

    def _check_limits(self, own: str) -> None:
        """Limits: ``None``, a real number or a tensor broadcastable to ``(*B, T, m)`` (0-d included); a NaN
        in a limit shared by the batch (a number, or a tensor without batch dims) is a ``ValueError`` here,
        one in a batched limit the element's ``NONFINITE_INPUT`` (:func:`ilqr`)."""
        T, m = self.horizon, self.m
        for name in ("u_lower", "u_upper"):
            v = getattr(self, name)
            check_limit(v, name, own, T, m, what="field", batch=tuple(self._batch_shape(limits=False)))
            if not isinstance(v, Tensor):
                continue
            if v.dtype != self.x0.dtype:
                raise TypeError(f"{own}: field '{name}' has dtype {v.dtype}, x0 has {self.x0.dtype}")
            if v.dim() <= 2 and bool(torch.isnan(v).any()):
                raise ValueError(f"{own}: field '{name}' (shared by the batch) has NaN entries "
                                 "(use ±inf for no limit)")

    @property
    def n(self) -> int:
        return self.dynamics.n

    @property
    def m(self) -> int:
        return self.dynamics.m

    @property
    def T(self) -> int:
        return self.horizon

    @property
    def dtype(self) -> torch.dtype:
        return self.x0.dtype

    @property
    def device(self) -> torch.device:
        return self.x0.device

    @property
    def batch_shape(self) -> torch.Size:
        return self._batch_shape(limits=True)

    def _batch_shape(self, limits: bool) -> torch.Size:
        shapes = {"x0": self.x0.shape[:-1]}
        if isinstance(self.cost, QuadraticCost):
            shapes["cost"] = self.cost.batch_shape
        if isinstance(self.dynamics, LinearDynamics):
            shapes["dynamics"] = self.dynamics.batch_shape
        for k in ("u_lower", "u_upper") if limits else ():
            v = getattr(self, k)
            if isinstance(v, Tensor) and v.dim() > 2:
                shapes[k] = v.shape[:-2]
        return broadcast_batch("ILQRProblem", shapes, " (limits are (*B, T, m))")

    def bounds(self) -> tuple[Tensor | None, Tensor | None]:
        """``(lower, upper)`` as tensors broadcastable to ``(*B, T, m)``, or ``(None, None)``."""
        if self.u_lower is None and self.u_upper is None:
            return None, None
        kw = dict(dtype=self.dtype, device=self.device)
        lo = torch.as_tensor(-math.inf if self.u_lower is None else self.u_lower, **kw)
        hi = torch.as_tensor(math.inf if self.u_upper is None else self.u_upper, **kw)
        return lo, hi


@dataclass(frozen=True, eq=False)
class ILQRSolution:
    """Result of :func:`ilqr`.

    Attributes:
        x: ``(*B, T+1, n)`` states, ``u``: ``(*B, T, m)`` controls (differentiable per :class:`GradMode`).
        K: ``(*B, T, m, n)`` feedback gains at the solution (rows of clamped controls are zero) and
            ``k``: ``(*B, T, m)`` such that the local policy is ``u_t = clip(K_t x_t + k_t)``, i.e.
            ``k_t = û_t - K_t x̂_t`` (Eq. 94 with the sign convention of :mod:`controllers.problem`).
        cost: ``(*B,)`` total cost at the solution (differentiable).
        status: per-element :class:`~controllers.problem.SolverStatus` (``Reason`` codes).
        clamped: ``(*B, T, m)`` bool, controls on a bound with an active limit at the solution.
        cost_history: ``(iterations+1, *B)`` cost after each iteration (first row: initial guess).
        mu: ``(*B,)`` final regularization.
        kkt_residual: ``(*B,)`` relative projected-gradient residual at the returned point, over the scale of
            :attr:`ILQROptions.tol_kkt`; ``CONVERGED`` exactly where it is at most ``tol_kkt``.
    """

    x: Tensor
    u: Tensor
    K: Tensor
    k: Tensor
    cost: Tensor
    status: SolverStatus
    clamped: Tensor
    cost_history: Tensor
    mu: Tensor
    kkt_residual: Tensor


# --------------------------------------------------------------------------------------------------
# backward pass (Eq. 91-93 with the box-QP feedforward of control-limited DDP)
# --------------------------------------------------------------------------------------------------


# --------------------------------------------------------------------------------------------------
# batch formulation (Algorithm 4)
# --------------------------------------------------------------------------------------------------


def _batch_step(A, B, gx, gu, Hxx, Hux, Huu, mu, lo, hi, k_warm, bs):
    """Gauss-Newton step over the whole control sequence (Eq. 87), a box QP when limited.

    Time-major inputs; returns ``(Δu (T, *B, m), ok (*B,), dV1, dV2)``.
    """
    T, n, m = A.shape[0], A.shape[-1], B.shape[-1]
    dtype, device = A.dtype, A.device

    Su = transfer_matrices(A.movedim(0, -3), B.movedim(0, -3), None, T)[1].expand(*bs, (T + 1) * n, T * m)
    Suk = Su.reshape(*bs, T + 1, n, T * m)
    gxf = gx.movedim(0, -2).expand(*bs, T + 1, n).reshape(*bs, (T + 1) * n)
    guf = gu.movedim(0, -2).expand(*bs, T, m).reshape(*bs, T * m)
    # S_uᵀ H_xx S_u with the block-diagonal H_xx
    HxxS = torch.einsum("t...ij,...tjk->...tik", Hxx.expand(T + 1, *bs, n, n), Suk)
    H = torch.einsum("...tik,...til->...kl", Suk, HxxS)
    if Hux is not None:
        # cross terms Σ_t Δx_tᵀ H_xu,t Δu_t with Δx_t = S_t Δu: rows of control t get H_ux,t S_t
        C = torch.einsum("...tik,t...mi->...tmk", Suk[..., :T, :, :], Hux.expand(T, *bs, m, n))
        C = C.reshape(*bs, T * m, T * m)
        H = H + C + C.mT
    Hb = torch.zeros(*bs, T, m, T, m, dtype=dtype, device=device)
    idx = torch.arange(T, device=device)
    Hb[..., idx, :, idx, :] = Huu.expand(T, *bs, m, m)
    H = H + Hb.reshape(*bs, T * m, T * m)
    H = 0.5 * (H + H.mT)
    g = (Su.mT @ gxf.unsqueeze(-1)).squeeze(-1) + guf  # S_uᵀ g_x + g_u
    eye = torch.eye(T * m, dtype=dtype, device=device)
    Hreg = H + mu[..., None, None] * eye
    if lo is None:
        L, info = torch.linalg.cholesky_ex(Hreg)
        ok = info == 0
        L = torch.where(ok[..., None, None], L, eye)
        du = -torch.cholesky_solve(g.unsqueeze(-1), L).squeeze(-1)
    else:
        lof = lo.movedim(0, -2).expand(*bs, T, m).reshape(*bs, T * m)
        hif = hi.movedim(0, -2).expand(*bs, T, m).reshape(*bs, T * m)
        warm = None if k_warm is None else k_warm.movedim(0, -2).reshape(*bs, T * m)
        res = box_qp(Hreg, g, lof, hif, x0=warm)
        ok = res.converged  # an uncertified QP step (e.g. no descent) is a failed step: μ grows
        du = res.x
    du = torch.where(ok.unsqueeze(-1), du, torch.zeros((), dtype=dtype, device=device))
    dV1 = (du * g).sum(-1)
    dV2 = 0.5 * (du * (H @ du.unsqueeze(-1)).squeeze(-1)).sum(-1)
    return du.reshape(*bs, T, m).movedim(-2, 0), ok, dV1, dV2


# --------------------------------------------------------------------------------------------------
# forward pass with a vectorized backtracking line search (Algorithm 1)
# --------------------------------------------------------------------------------------------------


def _clip(u: Tensor, lo: Tensor | None, hi: Tensor | None) -> Tensor:
    if lo is None:
        return u
    return torch.minimum(torch.maximum(u, lo), hi)


# --------------------------------------------------------------------------------------------------
# solver
# --------------------------------------------------------------------------------------------------


def _defaults(opts: ILQROptions, dtype: torch.dtype) -> tuple[float, float, float]:
    single = dtype in (torch.float32, torch.float16, torch.bfloat16)
    tol = opts.tol if opts.tol is not None else (1e-4 if single else 1e-8)
    tol_cost = opts.tol_cost if opts.tol_cost is not None else (1e-6 if single else 1e-12)
    tol_kkt = opts.tol_kkt if opts.tol_kkt is not None else (1e-3 if single else 1e-6)
    return tol, tol_cost, tol_kkt


def _input_status(cost, x0: Tensor, u_init: Tensor, lo: Tensor | None, hi: Tensor | None, bs: torch.Size
                  ) -> tuple[Tensor, Tensor | None, Tensor | None]:
    """Per-element :class:`Reason` codes ``(*B,)`` from the inputs alone (0 where sound), and the limits
    with those of failed elements opened (such an element is solved with open limits, zeros, and returned
    as NaN; no host sync).  Precedence (the first failure is the one reported): ``NONFINITE_INPUT`` (NaN/inf
    in ``x0``, ``u_init`` or a batched weight of a :class:`QuadraticCost`, NaN in a limit), then
    ``INFEASIBLE_BOUNDS`` (crossed limits, a lower limit of +inf or an upper one of -inf: no finite
    control satisfies them), then ``NOT_POSITIVE_DEFINITE`` (a batched weight that is not symmetric PSD /
    PD: :func:`controllers._validate.check_weight`; a shared one was a ``ValueError`` already)."""
    reason = torch.zeros(bs, dtype=torch.int64, device=x0.device)
    base = cost.base if isinstance(cost, PeriodicQuadraticCost) else cost
    nonfinite = ~torch.isfinite(x0).all(-1) | ~torch.isfinite(u_init).flatten(-2).all(-1)
    if isinstance(base, QuadraticCost):
        w = cost_status_of(base).expand(bs)
        reason = torch.where(w == int(Reason.NOT_POSITIVE_DEFINITE), w, reason)
        nonfinite = nonfinite | (w == int(Reason.NONFINITE_INPUT))
    if lo is not None:
        nonfinite = nonfinite | (torch.isnan(lo) | torch.isnan(hi)).flatten(-2).any(-1)
        crossed = ((lo > hi) | (lo == math.inf) | (hi == -math.inf)).flatten(-2).any(-1)
        reason = torch.where(crossed, int(Reason.INFEASIBLE_BOUNDS), reason)
    reason = torch.where(nonfinite, int(Reason.NONFINITE_INPUT), reason)
    if lo is not None:
        opened = (reason != 0)[..., None, None]
        lo, hi = torch.where(opened, -math.inf, lo), torch.where(opened, math.inf, hi)
    return reason, lo, hi


def _bcast(v: Tensor | None, shape) -> Tensor | None:
    return None if v is None else v.expand(shape)


def ilqr(
    problem: ILQRProblem,
    u_init: Tensor | None = None,
    *,
    method: ILQRMethod | str = ILQRMethod.RECURSIVE,
    grad: GradMode | str = GradMode.IMPLICIT,
    options: ILQROptions | None = None,
) -> ILQRSolution:
    """Solve a batch of control-limited nonlinear optimal-control problems by iLQR.

    Args:
        problem: :class:`ILQRProblem`.
        u_init: ``(*B, T, m)`` or ``(T, m)`` initial controls (projected onto the limits); zeros by default.
            For receding-horizon use pass the shifted previous solution (:mod:`controllers.mpc`).
        method: :class:`ILQRMethod` (``"recursive"``, Algorithm 5, or ``"batch"``, Algorithm 4).
        grad: :class:`~controllers.problem.GradMode` (``"implicit"``, ``"unrolled"`` or ``"none"``).
        options: :class:`ILQROptions`.

    Returns:
        :class:`ILQRSolution`; per-element ``status.reason`` is ``CONVERGED`` (certified: KKT residual
        at most ``tol_kkt`` at the returned point), ``STALLED`` (stopped moving at a point that is not
        certified), ``MAX_ITERATIONS``, ``LINE_SEARCH_FAILED`` (μ exceeded ``mu_max``), ``SINGULAR_QUU``
        (no μ up to ``mu_max`` gave a positive-definite ``Q_uu`` and a certified inner box QP),
        ``NONFINITE_INPUT`` (NaN/inf in ``x0``, ``u_init`` or a batched weight of a ``QuadraticCost``, NaN
        in a batched limit: that element's trajectory, gains, cost and KKT residual are NaN),
        ``INFEASIBLE_BOUNDS`` (``u_lower > u_upper``, ``u_lower = +inf`` or ``u_upper = -inf`` somewhere:
        NaN likewise), ``NOT_POSITIVE_DEFINITE`` (a batched ``Q``/``R`` of a ``QuadraticCost`` not
        symmetric PSD/PD for that element: NaN likewise) or ``DIVERGED`` (the initial rollout is not
        finite: NaN likewise).  An input failure is reported before anything the iteration finds (first
        failure wins).  Every other element is solved as if alone, in values and in the gradients of shared
        parameters.

        Gradients reach the limits too (when they are tensors with a graph): a clamped control is held on
        its limit in the implicit Newton step, so its derivative w.r.t. that limit is 1 and the free controls
        and states respond through the step (``grad="unrolled"``: through the clipping of every iterate).
    """
    if not isinstance(problem, ILQRProblem):
        raise TypeError(f"ilqr: argument 'problem' must be an ILQRProblem, got {type(problem).__name__}")
    method = enum_arg(ILQRMethod, method, "method", "ilqr")
    grad = enum_arg(GradMode, grad, "grad", "ilqr")
    opts = options if options is not None else ILQROptions()
    if opts.second_order and torch.is_inference_mode_enabled():
        raise ValueError("ilqr: ILQROptions(second_order=True) differentiates the Lagrangian twice and "
                         "cannot run under torch.inference_mode(); use torch.no_grad() (or grad='none')")
    T, n, m = problem.T, problem.n, problem.m
    dtype, device = problem.dtype, problem.device
    bs = problem.batch_shape
    kw = dict(dtype=dtype, device=device)
    if u_init is None:
        u_init = torch.zeros(*bs, T, m, **kw)
    else:
        if not isinstance(u_init, Tensor) or u_init.dtype != dtype:
            raise TypeError(f"ilqr: u_init must be a tensor of dtype {dtype}")
        if u_init.dim() < 2 or tuple(u_init.shape[-2:]) != (T, m):
            raise ValueError(f"ilqr: u_init must have shape (*B, {T}, {m}), got {tuple(u_init.shape)}")
        bs = broadcast_shapes(bs, u_init.shape[:-2])
        u_init = u_init.expand(*bs, T, m)
    lo, hi = problem.bounds()
    lo, hi = _bcast(lo, (*bs, T, m)), _bcast(hi, (*bs, T, m))
    x0 = problem.x0.expand(*bs, n)
    inp, lo, hi = _input_status(problem.cost, x0, u_init, lo, hi, bs)
    bad = inp != int(Reason.CONVERGED)
    problem = dataclasses.replace(problem, cost=stand_in_cost(problem.cost, bad))
    zero = torch.zeros((), **kw)
    x0s = torch.where(bad.unsqueeze(-1), zero, x0)
    u0 = _clip(torch.where(bad[..., None, None], zero, u_init), lo, hi)

    if grad is GradMode.UNROLLED:
        with torch.enable_grad():
            out = _solve(problem, x0s, u0, lo, hi, bad, bs, method, opts)
    else:
        # no graph while iterating; inference mode (less overhead per kernel) when no derivative inside the
        # loop needs autograd, results cloned out of it
        d = problem.dynamics
        analytic = isinstance(problem.cost, QuadraticCost) and has_analytic_jacobian(d)
        with torch.inference_mode() if analytic else torch.no_grad():
            out = _solve(problem, x0s.detach(), u0.detach(), lo, hi, bad, bs, method, opts)
        if analytic:
            out = tuple(v.clone() for v in out)
    x, u, K, kff, free, reason, iters, hist, mu, kkt = out
    if opts.second_order:
        pd = reduced_hessian_pd(problem, x, u, free, bs)
        reason = torch.where((reason == int(Reason.CONVERGED)) & ~pd, int(Reason.NOT_A_MINIMUM), reason)
    diverged = reason == int(Reason.DIVERGED)
    x0s = torch.where(diverged.unsqueeze(-1), zero, x0s)  # as _solve carried it on
    if grad is GradMode.IMPLICIT and torch.is_grad_enabled():
        x, u = _implicit_finite(problem, x0s, x, u, free, bs, lo, hi, zero, bool(opts.compile))
    with torch.no_grad() if grad is GradMode.NONE else contextlib.nullcontext():
        cost = problem.cost.evaluate(x, u).expand(bs)
    nanv = torch.full((), math.nan, **kw)
    bad = bad | diverged
    b1 = bad.unsqueeze(-1).unsqueeze(-1)
    x = torch.where(b1, nanv, x)
    u = torch.where(b1, nanv, u)
    cost = torch.where(bad, nanv, cost)
    K = torch.where(b1.unsqueeze(-1), nanv, K)
    kff = torch.where(b1, nanv, kff)
    kkt = torch.where(bad, nanv, kkt)
    reason = torch.where(inp != int(Reason.CONVERGED), inp, reason)  # the first failure wins: the inputs'
    status = SolverStatus(converged=reason == int(Reason.CONVERGED), iterations=iters, reason=reason)
    return ILQRSolution(x=x, u=u, K=K, k=kff, cost=cost, status=status, clamped=~free, cost_history=hist,
                        mu=mu, kkt_residual=kkt)


def _eager_iteration(dyn, cost, x0, it: Iterate, lo, hi, lo_tm, hi_tm, k_warm, bs, method, s: Settings, cc,
                     dyn_key, opts) -> tuple[Iterate, Tensor | None, bool]:
    """One iteration with its μ retries, eagerly (host reads decide the exits): ``(next iterate, the box QP's
    warm start, moved)``; ``moved`` False: no element was left to step (statuses final, iterate unchanged)."""
    lin = linearize(dyn, cost, it.x, it.u, lo_tm, hi_tm, bs, cc)
    it = mark_certified(it, lin, s)
    if not bool(it.active.any()):
        return it, k_warm, False
    dlo = None if lo is None else lo_tm - lin.u
    dhi = None if hi is None else hi_tm - lin.u
    mu, dmu, reason, active = it.mu, it.dmu, it.reason, it.active
    model = (lin.A, lin.B, lin.gx, lin.gu, lin.Hxx, lin.Hux, lin.Huu)
    first = True
    while True:
        if method is ILQRMethod.RECURSIVE:
            # compiled: the first pass may run two limited controls as a program too (rerun eagerly, warm
            # started, where its one-step box QPs leave an element uncertified); μ's retries run eagerly
            bw = backward_pass(*model, mu, dlo, dhi, k_warm, bs, cc, try_two=first)
            first = False
            K, k, ok, dV1, dV2, curv = bw.K, bw.k, bw.ok, bw.dV1, bw.dV2, bw.curv
        else:
            k, ok, dV1, dV2 = _batch_step(*model, mu, dlo, dhi, k_warm, bs)
            K, curv = None, None
        fail = active & ~ok
        if not bool(fail.any()):
            break
        mu, dmu = grow(mu, dmu, fail, s)
        over = fail & (mu > opts.mu_max)
        reason = torch.where(over, int(Reason.SINGULAR_QUU), reason)
        active = active & ~over
        if not bool((active & ~ok).any()):
            break
    it = stop_checks(it._replace(mu=mu, dmu=dmu, reason=reason, active=active), lin, k, curv, s)
    if not bool(it.active.any()):
        return it, k_warm, False
    it, accept = line_search(dyn, cost, x0, it, K, k, dV1, dV2, lo, hi, bs, s, dyn_key)
    return it, torch.where(accept.unsqueeze(-1), torch.zeros((), dtype=k.dtype, device=k.device), k), True


def _implicit_finite(problem, x0s, x, u, free, bs, lo, hi, zero, compile: bool):
    """:func:`~controllers.implicit.ilqr_implicit` for the elements whose trajectory is finite; an element
    whose iterate overflowed (e.g. ``SINGULAR_QUU`` at absurd parameters) keeps its values and gets no
    derivative.  Its Newton data are built at a zero trajectory instead: at the non-finite one the
    derivatives w.r.t. shared parameters are NaN even under a zero cotangent (0·NaN), and would reach
    every element's gradient through their sum."""
    fin = (torch.isfinite(x).flatten(-2).all(-1) & torch.isfinite(u).flatten(-2).all(-1))[..., None, None]
    xi, ui = ilqr_implicit(problem, x0s, torch.where(fin, x, zero), torch.where(fin, u, zero), free, bs, lo,
                           hi, compile=compile)
    return torch.where(fin, xi, x), torch.where(fin, ui, u)


def _solve(problem, x0, u, lo, hi, bad, bs, method, opts):
    dyn, cost = problem.dynamics, problem.cost
    T = problem.T
    dtype, device = problem.dtype, problem.device
    tol, tol_cost, tol_kkt = _defaults(opts, dtype)
    s = Settings(tol, tol_cost, tol_kkt, float(opts.mu_factor), float(opts.mu_min), float(opts.mu_max),
                 float(opts.armijo), int(opts.line_search_steps))
    lo_tm = None if lo is None else lo.movedim(-2, 0)
    hi_tm = None if hi is None else hi.movedim(-2, 0)
    # compiled sweeps (ILQROptions.compile): never under a graph (grad="unrolled" differentiates the loop)
    cc = bool(opts.compile) and not torch.is_grad_enabled()
    dyn_key = _compiled.fingerprint(dyn) if cc and is_time_invariant(dyn) else None
    # the whole iteration as one program where the problem allows (controllers._ilqr_step)
    whole = cc and bs.numel() > 0 and program_supported(dyn, cost, dyn_key, problem.m, lo is not None,
                                                        method is ILQRMethod.RECURSIVE)

    x = rollout(dyn, x0, u)
    J = cost.evaluate(x, u).expand(bs)
    reason = torch.full(bs, int(Reason.MAX_ITERATIONS), dtype=torch.int64, device=device)
    diverged = ~torch.isfinite(J) & ~bad
    reason = torch.where(bad, int(Reason.NONFINITE_INPUT), reason)
    reason = torch.where(diverged, int(Reason.DIVERGED), reason)
    active = ~bad & ~diverged
    if bool(diverged.any()):
        # carried on from a zero start (its outputs are NaN-ed by the caller): an inf trajectory in the
        # graph would reach a shared parameter's gradient as 0·inf
        x0 = torch.where(diverged.unsqueeze(-1), 0.0, x0)
        u = torch.where(diverged[..., None, None], 0.0, u)
        x = rollout(dyn, x0, u)
        J = torch.where(diverged, cost.evaluate(x, u).expand(bs), J)
    kw = dict(dtype=dtype, device=device)
    zeros_i = torch.zeros(bs, dtype=torch.int64, device=device)
    it = Iterate(x, u, J, torch.full(bs, float(opts.mu_init), **kw), torch.ones(bs, **kw), zeros_i, zeros_i,
                 reason, active)
    hist = [J]
    k_warm = None
    any_active = bool(active.any())
    for _ in range(opts.max_iter):
        if not any_active:
            break
        if whole:
            nxt, flags = program_iteration(dyn, dyn_key, cost, x0, it, lo, hi, bs, s)
            pre, fail, stop, post = flags.tolist()  # the iteration's one host read
            if not fail:  # otherwise μ must grow and the pass be repeated: this iteration runs eagerly
                it = nxt
                if not (pre and stop):
                    break
                hist.append(it.J)
                any_active = bool(post)
                continue
        it, k_warm, moved = _eager_iteration(dyn, cost, x0, it, lo, hi, lo_tm, hi_tm, k_warm, bs, method, s,
                                             cc, dyn_key, opts)
        if not moved:
            break
        hist.append(it.J)
        any_active = bool(it.active.any())
    x, u, mu, reason, iters = it.x, it.u, it.mu, it.reason, it.iters

    # gains, clamped set and certificate at the returned point (one more backward pass)
    lin = linearize(dyn, cost, x, u, lo_tm, hi_tm, bs, cc)
    dlo = None if lo is None else lo_tm - lin.u
    dhi = None if hi is None else hi_tm - lin.u
    bw = backward_pass(lin.A, lin.B, lin.gx, lin.gu, lin.Hxx, lin.Hux, lin.Huu, mu, dlo, dhi, None, bs, cc,
                       try_two=True)
    kkt = kkt_relative(lin.pg, lin.terms, bw.curv, lin.umax, kkt_floor(tol, tol_kkt)).expand(bs)
    certified = kkt <= tol_kkt
    iterative = (reason == int(Reason.CONVERGED)) | (reason == int(Reason.MAX_ITERATIONS)) | (
        reason == int(Reason.STALLED))
    reason = torch.where(iterative & certified, int(Reason.CONVERGED), reason)
    reason = torch.where((reason == int(Reason.CONVERGED)) & ~certified, int(Reason.STALLED), reason)
    K = bw.K.movedim(0, -3)
    free = bw.free.movedim(0, -2)
    kff = u - (K @ x[..., :T, :].unsqueeze(-1)).squeeze(-1)
    return x, u, K, kff, free, reason, iters, torch.stack(hist), mu, kkt
