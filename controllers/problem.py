"""LQ problems, solutions, per-element status and gradient modes shared by every solver.

Conventions (shared by every solver in :mod:`controllers`)
---------------------------------------------------------
* Time index ``t = 0 .. T``: states ``x_0 .. x_T`` (``(*B, T+1, n)``), controls ``u_0 .. u_{T-1}``
  (``(*B, T, m)``).  The seed (cookbook 004 §7) counts from 1; ``x_1`` there is ``x_0`` here.
* Linear dynamics ``x_{t+1} = A_t x_t + B_t u_t + c_t`` with ``A (*B, T, n, n)``, ``B (*B, T, n, m)``,
  ``c (*B, T, n)``.  Batch dims broadcast like torch; a time dim of size 1 broadcasts over time; a
  matrix without a time dim (``A (n, n)``, ``c (n,)``) is time-invariant and shared by the batch.
  To give a time-invariant matrix *per batch element* use a time dim of 1: ``A (B, 1, n, n)``.
  **One broadcasting rule for every entry point** (``riccati.solve``/``lqr``, ``lifted``, ``ilqr``
  in both formulations and all gradient modes, ``box_qp``, ``mpc``): the batch dims of every field,
  of ``x0`` and of control limits (``(*B, T, m)``) broadcast against each other like torch shapes,
  right-aligned; the solution has the broadcast batch shape, and a gradient has its input's own shape
  (summed over the dims it was broadcast along).  Shapes that do not broadcast are a ``ValueError``
  naming the fields (``tests/controllers/test_broadcasting.py``).
* Costs follow one convention (seed Eq. 59, no factor ½), stated once in :mod:`controllers.costs`;
  dynamics and the :class:`~controllers.dynamics.System` protocol are in :mod:`controllers.dynamics`.
* Solutions (:class:`LQSolution`) carry the trajectory, the affine policy ``u_t = K_t x_t + k_t`` and
  per-batch-element :class:`SolverStatus` (converged, iterations, reason code from :class:`Reason`).

Module map: :mod:`controllers.dynamics` (systems), :mod:`controllers.costs` (costs and their
derivatives), this module (LQ problems, solutions, status codes, :class:`GradMode`); argument checks
are in the private ``controllers._validate``.  Every input error names the owner and the field.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import torch

from controllers._validate import all_finite, broadcast_batch, check_tensor, same_dtype_device
from controllers.costs import QuadraticCost
from controllers.dynamics import LinearDynamics

__all__ = [
    "Reason",
    "SolverStatus",
    "GradMode",
    "LQProblem",
    "LQSolution",
    "cost_status_of",
]


# --------------------------------------------------------------------------------------------------
# status
# --------------------------------------------------------------------------------------------------


class Reason(enum.IntEnum):
    """Why a solver stopped, per batch element (stored as int64 codes in :attr:`SolverStatus.reason`)."""

    #: solved: an LQ problem in one pass; an iterative solver only where its optimality (KKT) residual was
    #: checked below tolerance at the returned point
    CONVERGED = 0
    NONFINITE_INPUT = 1  #: NaN/inf in x0 or in the problem data of this element
    NOT_POSITIVE_DEFINITE = 2  #: Q not PSD or R not PD for this element
    SINGULAR_QUU = 3  #: Q_uu (or the lifted normal matrix) not PD in the backward pass
    MAX_ITERATIONS = 4  #: iterative solver hit its iteration limit
    LINE_SEARCH_FAILED = 5  #: no step length decreased the cost
    DIVERGED = 6  #: non-finite values appeared while iterating
    #: no progress (a negligible step or cost decrease) at a point whose KKT residual is above tolerance:
    #: not a certified optimum (e.g. the inner QP could not find a descent direction)
    STALLED = 7
    INFEASIBLE_BOUNDS = 8  #: a control's lower limit is above its upper limit for this element
    #: a certified KKT point where the exact reduced Hessian (free controls, dynamics eliminated) is not
    #: positive definite: a saddle or a maximum, not a local minimum (iLQR with ``second_order=True``)
    NOT_A_MINIMUM = 9


@dataclass(frozen=True, eq=False)
class SolverStatus:
    """Per-batch-element outcome: ``converged (*B,) bool``, ``iterations (*B,) int64``,
    ``reason (*B,) int64`` (codes of :class:`Reason`)."""

    converged: torch.Tensor
    iterations: torch.Tensor
    reason: torch.Tensor

    @staticmethod
    def from_reason(reason: torch.Tensor, iterations: torch.Tensor | int = 1) -> SolverStatus:
        reason = reason.to(torch.int64)
        it = torch.as_tensor(iterations, dtype=torch.int64, device=reason.device).expand(reason.shape)
        return SolverStatus(converged=reason == int(Reason.CONVERGED), iterations=it.clone(), reason=reason)

    @property
    def all_converged(self) -> bool:
        return bool(self.converged.all())

    def reason_names(self) -> list[str]:
        """The reasons as names, flattened over the batch in row-major order."""
        return [Reason(int(c)).name for c in self.reason.reshape(-1).tolist()]


class GradMode(str, enum.Enum):
    """How gradients reach the inputs of a solver (one spelling for every solver)."""

    #: implicit function theorem at the solution: one extra LQ (backward Riccati) pass, O(T) memory,
    #: independent of how the solution was found (:mod:`controllers.implicit`)
    IMPLICIT = "implicit"
    UNROLLED = "unrolled"  #: autograd through every step (and every iteration) of the solver
    NONE = "none"  #: no graph at all (inference)


# --------------------------------------------------------------------------------------------------
# problem and solution
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class LQProblem:
    """A batched linear-quadratic (tracking) problem.

    Args:
        dynamics: :class:`LinearDynamics`.
        cost: :class:`QuadraticCost`.
        x0: initial state ``(*B, n)`` or ``(n,)``.
        horizon: ``T``; may be omitted when some field is time-varying (then it must agree).
    """

    dynamics: LinearDynamics
    cost: QuadraticCost
    x0: torch.Tensor
    horizon: int | None = None

    def __post_init__(self) -> None:
        own = "LQProblem"
        if not isinstance(self.dynamics, LinearDynamics):
            raise TypeError(f"{own}: field 'dynamics' must be a LinearDynamics, "
                            f"got {type(self.dynamics).__name__}")
        if not isinstance(self.cost, QuadraticCost):
            raise TypeError(f"{own}: field 'cost' must be a QuadraticCost, got {type(self.cost).__name__}")
        n, m = self.dynamics.n, self.dynamics.m
        if self.cost.n != n or self.cost.m != m:
            raise ValueError(f"{own}: cost is for n={self.cost.n}, m={self.cost.m} "
                             f"but dynamics has n={n}, m={m}")
        check_tensor(self.x0, "x0", own)
        if self.x0.dim() < 1 or self.x0.shape[-1] != n:
            raise ValueError(f"{own}: field 'x0' must have shape (*B, {n}), got {tuple(self.x0.shape)}")
        same_dtype_device(own, A=self.dynamics.A, Q=self.cost.Q, x0=self.x0)
        hs = {k: v for k, v in (("dynamics", self.dynamics.horizon), ("cost", self.cost.horizon))
              if v is not None}
        T = self.horizon
        if T is None:
            if not hs:
                raise ValueError(f"{own}: cannot infer the horizon (every field is time-invariant); "
                                 "pass horizon=T")
            T = max(hs.values())
        if not isinstance(T, int) or isinstance(T, bool) or T < 1:
            raise ValueError(f"{own}: field 'horizon' must be a positive int, got {T!r}")
        for k, h in hs.items():
            if h != T:
                raise ValueError(f"{own}: {k} has horizon {h} but the problem horizon is {T}")
        object.__setattr__(self, "horizon", T)
        self.batch_shape  # noqa: B018  (a ValueError naming the fields when they do not broadcast)

    @property
    def T(self) -> int:
        return self.horizon  # type: ignore[return-value]

    @property
    def n(self) -> int:
        return self.dynamics.n

    @property
    def m(self) -> int:
        return self.dynamics.m

    @property
    def batch_shape(self) -> torch.Size:
        return broadcast_batch("LQProblem", {"x0": self.x0.shape[:-1], "dynamics": self.dynamics.batch_shape,
                                             "cost": self.cost.batch_shape})

    @property
    def dtype(self) -> torch.dtype:
        return self.x0.dtype

    @property
    def device(self) -> torch.device:
        return self.x0.device

    def input_status(self, cost_status: torch.Tensor | None = None) -> torch.Tensor:
        """``(*B,)`` int64 :class:`Reason` codes from the inputs alone (non-finite data, bad definiteness).

        ``cost_status``: the cost's part, :func:`cost_status`, when the caller already holds it (a
        :class:`~controllers.riccati.PreparedCost`); computed here otherwise.
        """
        bs = self.batch_shape
        reason = cost_status_of(self.cost) if cost_status is None else cost_status
        reason = reason.expand(bs)
        fin = all_finite(self.x0, 1).expand(bs) & self.dynamics.finite_mask().expand(bs)
        return torch.where(fin, reason, int(Reason.NONFINITE_INPUT))


def cost_status_of(cost: QuadraticCost) -> torch.Tensor:
    """``(*B,)`` :class:`Reason` codes of a cost alone: ``NONFINITE_INPUT`` where a field has NaN/inf,
    else ``NOT_POSITIVE_DEFINITE`` where (batched) Q is not PSD or R not PD, else 0."""
    reason = torch.zeros(cost.batch_shape, dtype=torch.int64, device=cost.device)
    if cost.Q.dim() > 3 or cost.R.dim() > 3:
        reason = torch.where(cost.definite_mask(), reason, int(Reason.NOT_POSITIVE_DEFINITE))
    return torch.where(cost.finite_mask(), reason, int(Reason.NONFINITE_INPUT))


@dataclass(frozen=True, eq=False)
class LQSolution:
    """Solution of an LQ problem (or of iLQR at its last iterate).

    Attributes:
        x: ``(*B, T+1, n)`` optimal states.
        u: ``(*B, T, m)`` optimal controls.
        K: ``(*B, T, m, n)`` feedback gains, ``k``: ``(*B, T, m)`` feedforward: ``u_t = K_t x_t + k_t``
            (sign convention: *plus*; the seed's ``-K_t`` is ``K`` here).
        cost: ``(*B,)`` optimal total cost.
        status: per-element :class:`SolverStatus`.
        V, v: optional value function ``x_tᵀ V_t x_t + 2 v_tᵀ x_t + const`` (``(*B, T+1, n, n)``,
            ``(*B, T+1, n)``) when the solver computes it.
    """

    x: torch.Tensor
    u: torch.Tensor
    K: torch.Tensor
    k: torch.Tensor
    cost: torch.Tensor
    status: SolverStatus
    V: torch.Tensor | None = None
    v: torch.Tensor | None = None
