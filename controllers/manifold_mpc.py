"""Error-state MPC on manifolds (seed 003 §IV–V, Algorithm 1), batched and differentiable.

A **manifold system** (:class:`ManifoldSystem`) is a discrete system in the canonical form of Eq. 14,
``x_{k+1} = x_k ⊕ Δt f(x_k, u_k)``, on any :mod:`torchlie.manifolds` space with ⊞/⊟/⊕ (a
:class:`~torchlie.manifolds.ProductManifold` of Rⁿ, SO(2), SO(3), SE(3), S², surfaces …):

=================================  =================================================================
``manifold``                       the state space (points are tensors or ``ProductState``)
``n``, ``m``, ``dt``               tangent dimension (``manifold.dim``), control dimension, Δt
``f(x, u) -> (*B, l)``             the perturbation rate (``l = manifold.ext_dim``)
``f_jacobians(x, u)``              *optional*: the system-specific parts ``∂f(x ⊞ δx, u)/∂δx (*B, l, n)``
                                   and ``∂f(x, u + δu)/∂δu (*B, l, m)`` at 0 (e.g. Eq. 34); without it
                                   they come from ``torch.func`` (``f`` must not mix batch elements)
``step(x, u, t=0)``                ``x ⊕ Δt f(x, u)`` (what :func:`manifold_step` computes)
``u_lower``, ``u_upper``           *optional* ``(m,)`` limits, the defaults of :class:`ErrorStateMPC`
=================================  =================================================================

**The error system** (Eq. 17–23).  Around a linearization trajectory ``(x̄_k, ū_k)`` the deviation
``δx_k = x_k ⊟ x̄_k`` obeys ``δx_{k+1} ≈ F_x δx_k + F_u δu_k + c_k`` with ``F_x = G_x + Δt G_f ∂f/∂δx``,
``F_u = Δt G_f ∂f/∂δu`` (Eq. 21–22; the manifold parts ``G_x``, ``G_f`` in closed form from Table I, the
system parts analytic or by autograd) and ``c_k = (x̄_k ⊕ Δt f(x̄_k, ū_k)) ⊟ x̄_{k+1}``.  Algorithm 1
linearizes about the reference itself (``x̄ = x^d``): then the tracking error is ``δx`` and ``c_k`` is the
reference's own infeasibility, zero for a reference that satisfies the model (the paper's assumption;
kept here so that a reference from continuous-time flatness, say, is followed without bias).

**The MPC problem** (Eq. 15, 24) in this library's cost convention (no ½, :mod:`controllers.costs`)::

    min_u  Σ_{k<N} ‖x_k ⊟ x^d_k‖²_Q + ‖u_k − u^d_k‖²_R  +  ‖x_N ⊟ x^d_N‖²_P     u_lower ≤ u_k ≤ u_upper

is solved on the linearized error system either

* in the **condensed** form (Eq. 25–28): ``δX = S_x δx_0 + S_u δU + s_c`` (``M`` = ``S_u``, ``H`` =
  ``S_x`` of :func:`controllers.lifted.transfer_matrices`), a batched box QP in the ``N m`` controls
  (:func:`controllers.boxqp.box_qp`; the closed form of Eq. 31, one Cholesky solve, when there are no
  limits), or
* by the **Riccati** recursion (:func:`controllers.riccati.solve`, the equivalent O(N) form) when there
  are no limits.

``solver="auto"`` takes the Riccati form without limits and the QP with them.  ``u = ū + δu`` (Eq. 30).

**Iterated variant** (§V-D, :meth:`ErrorStateMPC.iterate`): when no feasible reference exists, the
linearization trajectory is a rollout of the current controls; the cost is expanded to first order in
``δx`` (``x ⊟ x^d ≈ ē + J δx`` with ``J = ∂((x̄ ⊞ δ) ⊟ x^d)/∂δ`` by autograd, a Gauss–Newton model),
the QP gives a step, a backtracking line search on the true cost accepts it, and iterations stop when the
model about the current point can lower the cost, within the limits, by at most ``tol`` times the cost (a
duality bound, :func:`_gap_bound`: invariant under a common scaling of the weights, zero at a KKT point):
only then is an element ``CONVERGED``.

**Gradients.**  Every output is a differentiable function of ``x0``, the references, the weights, the
limits and any tensor the model's ``f`` closes over: the linearization is autograd through the model
and the closed-form G's; the Riccati path uses the implicit LQ gradient; the QP path re-solves, with
autograd, the equality-constrained QP on the active set that :func:`box_qp` found (clamped controls
fixed at their bounds): the implicit-function gradient of the box QP wherever strict complementarity
holds.  In :meth:`~ErrorStateMPC.iterate` the same is done at the returned point, with the
Gauss–Newton Hessian (``x0`` entering as the model's initial deviation), as a step whose value is
cancelled: the returned values are the same with and without gradients.

**Status** per element (:class:`~controllers.problem.Reason`): ``NONFINITE_INPUT`` for a NaN/inf in one
element's state, reference, batched weight or tensor limit, ``NOT_POSITIVE_DEFINITE`` for a batched weight
that is not PSD (Q, P) / PD (R), ``INFEASIBLE_BOUNDS`` where ``u_lower > u_upper``, ``u_lower = +inf`` or
``u_upper = -inf`` (such an element's outputs are NaN, the others are solved as if alone), ``SINGULAR_QUU``
where the QP Hessian is not positive definite, ``MAX_ITERATIONS``/``STALLED`` where the box QP or the
iteration did not certify its point.
Each element keeps its first failure in that order (:func:`first_failure`): no later stage overwrites it.
A state off the manifold, a shared weight that is not finite and symmetric PSD/PD, and an argument of the
wrong type or shape are a ``TypeError``/``ValueError`` naming the argument.
"""

from __future__ import annotations

import inspect
import math
import time
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import torch
from torch import Tensor

from controllers._compiled import scan
from controllers._validate import all_finite, broadcast_batch, check_limit, check_weight, enum_arg
from controllers.boxqp import BoxQPStatus, at_lower, box_qp, masked_hessian
from controllers.costs import QuadraticCost
from controllers.dynamics import LinearDynamics
from controllers.problem import GradMode, LQProblem, Reason, SolverStatus
from torchlie._batch import broadcast_shapes, check_tensor

__all__ = [
    "ManifoldSystem",
    "manifold_step",
    "manifold_rollout",
    "system_jacobians",
    "ErrorSystem",
    "error_system",
    "ErrorStateSolution",
    "ErrorStateMPC",
    "time_index",
    "time_slice",
    "riccati_terminal_weight",
    "TrackingRun",
    "track",
]


@runtime_checkable
class ManifoldSystem(Protocol):
    """A system ``x_{k+1} = x_k ⊕ Δt f(x_k, u_k)`` on a manifold (module docstring)."""

    manifold: Any
    n: int
    m: int
    dt: float

    def f(self, x, u: Tensor) -> Tensor: ...


# --------------------------------------------------------------------------------------------------
# points with a time dim: tensors (event dims trailing) or ProductStates (batch dims only)
# --------------------------------------------------------------------------------------------------


def _event_ndim(M) -> int:
    return len(M.event_shape) if not hasattr(M, "components") else 0


def time_slice(M, x, sl: slice):
    """``x[..., sl]`` along the last batch dim (time) of a point (a tensor or a ``ProductState``) of ``M``."""
    k = _event_ndim(M)
    if k == 0:
        return x[..., sl] if not isinstance(x, Tensor) else x[(..., sl)]
    return x[(..., sl) + (slice(None),) * k]


def time_index(M, x, i: int):
    """The point at time ``i`` (the last batch dim removed)."""
    k = _event_ndim(M)
    if isinstance(x, Tensor):
        return x[(..., i) + (slice(None),) * k]
    return x[..., i]


def _batch_shape(M, x) -> torch.Size:
    return M._batch_shape(x)


def _leaves(x):
    return list(x.values()) if not isinstance(x, Tensor) else [x]


def _point_finite(M, x) -> Tensor:
    """``(*B,)`` bool: every entry of the point finite."""
    out = None
    for leaf, k in _leaf_ndims(M, x):
        f = all_finite(leaf, k)
        out = f if out is None else out & f
    return out


def _leaf_ndims(M, x):
    if isinstance(x, Tensor):
        return [(x, len(M.event_shape))]
    out = []
    for name, t in x.items():
        if isinstance(t, Tensor):
            out.append((t, x.event_ndims[name]))
        else:
            out.extend(_leaf_ndims(M.components[name], t))
    return out


def _where_point(M, mask: Tensor, a, b):
    """Elementwise ``a if mask else b`` over the batch dims of two points."""
    if isinstance(a, Tensor):
        k = len(M.event_shape)
        return torch.where(mask.reshape(*mask.shape, *([1] * k)), a, b)
    data = {}
    for name in a.keys():
        data[name] = _where_point(M.components[name], mask, a[name], b[name])
    return type(a)._make(data, a.event_ndims)


def _flatten_point(M, x, nd: int):
    """The first ``nd`` batch dims flattened into one."""
    k = _event_ndim(M)
    if isinstance(x, Tensor):
        return x.reshape(-1, *x.shape[x.dim() - k:])
    return x.reshape(-1)


def _expand_point(M, x, batch):
    k = _event_ndim(M)
    if isinstance(x, Tensor):
        return x.expand(*batch, *x.shape[x.dim() - k:])
    return x.expand(*batch)


# --------------------------------------------------------------------------------------------------
# stepping and the system-specific Jacobians
# --------------------------------------------------------------------------------------------------


def manifold_step(system: ManifoldSystem, x, u: Tensor):
    """``x ⊕ Δt f(x, u)`` (Eq. 14), unchecked (the caller checked ``x``)."""
    return system.manifold.oplus(x, system.dt * system.f(x, u), check=False)


def manifold_rollout(system: ManifoldSystem, x0, u: Tensor):
    """States ``x_0 .. x_T`` from ``x0`` (batch ``*B``) and controls ``u (*B, T, m)``; a point with batch
    ``(*B, T+1)``."""
    M = system.manifold
    xs = [x0]
    for k in range(u.shape[-2]):
        xs.append(manifold_step(system, xs[-1], u[..., k, :]))
    return _stack_points(M, xs)


def _stack_points(M, xs: list):
    if isinstance(xs[0], Tensor):
        k = len(M.event_shape)
        batch = broadcast_shapes(*(x.shape[:x.dim() - k] for x in xs))
        return torch.stack([x.expand(*batch, *x.shape[x.dim() - k:]) for x in xs], -k - 1)
    batch = broadcast_shapes(*(x.batch_shape for x in xs))
    return type(xs[0]).stack([x.expand(*batch) for x in xs], dim=len(batch))


def system_jacobians(system: ManifoldSystem, x, u: Tensor, method: str = "auto"
                     ) -> tuple[Tensor, Tensor, Tensor]:
    """``(f(x, u) (*B, l), ∂f(x ⊞ δx, u)/∂δx (*B, l, n), ∂f(x, u + δu)/∂δu (*B, l, m))`` at δ = 0.

    ``method``: ``"auto"`` (the system's ``f_jacobians`` when it has one), ``"analytic"`` or
    ``"autograd"`` (``torch.func.jacrev`` of the batch sum, so ``f`` must not mix batch elements).
    """
    if method not in ("auto", "analytic", "autograd"):
        raise ValueError(f"system_jacobians: argument 'method' must be 'auto', 'analytic' or 'autograd', "
                         f"got {method!r}")
    M = system.manifold
    analytic = getattr(system, "f_jacobians", None)
    if method == "analytic" and analytic is None:
        raise ValueError("system_jacobians: method='analytic' needs a system with 'f_jacobians'")
    fv = system.f(x, u)
    batch = broadcast_shapes(fv.shape[:-1], u.shape[:-1], _batch_shape(M, x))
    if analytic is not None and method != "autograd":
        Jx, Ju = analytic(x, u)
    else:
        n, m, l = M.dim, u.shape[-1], fv.shape[-1]
        xb = _expand_point(M, x, batch)
        ub = u.expand(*batch, m)

        def fx(d):
            return system.f(M.boxplus(xb, d, check=False), ub).reshape(-1, l).sum(0)

        def fu(d):
            return system.f(xb, ub + d).reshape(-1, l).sum(0)

        Jx = torch.func.jacrev(fx)(fv.new_zeros(*batch, n)).movedim(0, -2)
        Ju = torch.func.jacrev(fu)(fv.new_zeros(*batch, m)).movedim(0, -2)
    l = fv.shape[-1]
    return fv.expand(*batch, l), Jx.expand(*batch, *Jx.shape[-2:]), Ju.expand(*batch, *Ju.shape[-2:])


# --------------------------------------------------------------------------------------------------
# the linearized error system
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class ErrorSystem:
    """``δx_{k+1} = A_k δx_k + B_k δu_k + c_k`` about ``(x̄, ū)``: ``A (*B, N, n, n)``, ``B (*B, N, n, m)``,
    ``c (*B, N, n)``."""

    A: Tensor
    B: Tensor
    c: Tensor


def error_system(system: ManifoldSystem, x_bar, u_bar: Tensor, *, jacobians: str = "auto",
                 exact_G: bool = False, exact_reference: bool = False) -> ErrorSystem:
    """Linearize the canonical system about ``x̄`` (a point with batch ``(*B, N+1)``) and ``ū (*B, N, m)``
    (Eq. 20–23); ``c_k = (x̄_k ⊕ Δt f(x̄_k, ū_k)) ⊟ x̄_{k+1}``.

    ``A = F_x``, ``B = F_u`` of Eq. 21–22 are the exact derivatives of the error map
    ``δx_{k+1} = ((x̄_k ⊞ δx) ⊕ Δt f(x̄_k ⊞ δx, ū_k + δu)) ⊟ x̄_{k+1}`` when ``x̄`` is a trajectory of the
    model (``c = 0``, the paper's assumption, and the case of :meth:`ErrorStateMPC.iterate`).  For an
    infeasible ``x̄`` they are exact up to a factor ``I + O(‖c‖)`` (the derivative of ``⊟`` at ``c``);
    ``exact_reference=True`` includes that factor (by autograd, one more Jacobian per step).
    """
    M = system.manifold
    N = u_bar.shape[-2]
    xk = time_slice(M, x_bar, slice(0, N))
    fv, Jx, Ju = system_jacobians(system, xk, u_bar, jacobians)
    v = system.dt * fv
    A, B = M.linearize(xk, v, system.dt, Jx, Ju, exact=exact_G, check=False)
    nxt = M.oplus(xk, v, check=False)
    target = time_slice(M, x_bar, slice(1, N + 1))
    c = M.boxminus(nxt, target, check=False)
    if exact_reference:
        Dm = _boxminus_jacobian(M, nxt, target)
        A, B = Dm @ A, Dm @ B
    return ErrorSystem(A=A, B=B, c=c)


def riccati_terminal_weight(system: ManifoldSystem, x_d, u_d: Tensor, Q: Tensor, R: Tensor, *,
                            max_iter: int = 5000, tol: float | None = None) -> tuple[Tensor, Tensor]:
    """The infinite-horizon LQR weight ``P = Q + AᵀPA − AᵀPB (R + BᵀPB)⁻¹ BᵀPA`` of the error system at
    a trim point ``(x_d, u_d)`` with ``x_d ⊕ Δt f(x_d, u_d) = x_d`` (e.g. hover), by the Riccati
    iteration from ``P = Q``.

    A short horizon sees little of a slow mode (the quadrotor's position reacts to a body rate through
    three integrations: over the paper's 8 steps of 10 ms hardly at all); this ``P`` as the terminal
    weight makes the MPC behave like the infinite-horizon LQR near the trim point.  Returns ``(P, done)``
    with ``done`` ``(*B,)`` bool: the relative change fell below ``tol`` (default ``sqrt(eps)``).
    ``Q``, ``R`` are checked as in :class:`ErrorStateMPC`; an element whose ``R + BᵀPB`` is singular (a
    batched ``R`` that is not PD) ends with ``done`` False and never stops the others.
    """
    M = system.manifold
    n, m = M.dim, u_d.shape[-1]
    Q = _checked_weight(Q, n, "Q", "riccati_terminal_weight", strict=False)
    R = _checked_weight(R, m, "R", "riccati_terminal_weight", strict=True)
    xs = _stack_points(M, [x_d, x_d])
    es = error_system(system, xs, u_d.unsqueeze(-2))
    A, B = es.A[..., 0, :, :], es.B[..., 0, :, :]
    tol = torch.finfo(A.dtype).eps ** 0.5 if tol is None else tol
    P = Q.expand(*A.shape[:-2], n, n)
    done = torch.zeros(A.shape[:-2], dtype=torch.bool, device=A.device)
    for _ in range(max_iter):
        PB = P @ B
        K = torch.linalg.solve_ex(R + B.transpose(-1, -2) @ PB, PB.transpose(-1, -2) @ A)[0]
        Pn = Q + A.transpose(-1, -2) @ P @ A - (A.transpose(-1, -2) @ PB) @ K
        Pn = 0.5 * (Pn + Pn.transpose(-1, -2))
        done = ((Pn - P).flatten(-2).norm(dim=-1) <= tol * Pn.flatten(-2).norm(dim=-1))
        P = Pn
        if bool(done.all()):
            break
    return P, done


# --------------------------------------------------------------------------------------------------
# the controller
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class ErrorStateSolution:
    """One error-state MPC solve.

    Attributes:
        u: ``(*B, m)`` the control to apply (Eq. 30).
        U: ``(*B, N, m)`` the planned controls.
        dx: ``(*B, N+1, n)`` predicted errors ``x_k ⊟ x^d_k`` (on the linear model; in
            :meth:`ErrorStateMPC.iterate`, of the rolled-out trajectory).
        cost: ``(*B,)`` the objective of the predicted plan (Eq. 15 on the linear model; the true cost in
            :meth:`~ErrorStateMPC.iterate`).
        status: per-element :class:`~controllers.problem.SolverStatus`.
        kkt_residual: ``(*B,)`` the QP's certificate residual (0 for the unconstrained closed forms); in
            :meth:`~ErrorStateMPC.iterate`, the gap bound relative to the cost at the returned point.
        clamped: ``(*B, N, m)`` bool, controls held at a limit.
        x: in :meth:`~ErrorStateMPC.iterate`, the rolled-out states (batch ``(*B, N+1)``); else None.
    """

    u: Tensor
    U: Tensor
    dx: Tensor
    cost: Tensor
    status: SolverStatus
    kkt_residual: Tensor
    clamped: Tensor
    x: Any = None


def _weight(W, size: int, name: str, fn: str) -> Tensor:
    if not isinstance(W, Tensor) or not W.dtype.is_floating_point:
        raise TypeError(f"{fn}: argument '{name}' must be a floating tensor, got {type(W).__name__}")
    if W.dim() >= 1 and W.shape[-1] == size and (W.dim() == 1 or W.shape[-2] != size):
        return torch.diag_embed(W)  # a diagonal given as a vector
    if W.dim() >= 2 and W.shape[-2:] == (size, size):
        return W
    raise ValueError(f"{fn}: argument '{name}' must be ({size},) (a diagonal) or (*B, {size}, {size}), "
                     f"got {tuple(W.shape)}")


def _checked_weight(W, size: int, name: str, fn: str, strict: bool) -> Tensor:
    """:func:`_weight`, validated by the one weight rule of every solver
    (:func:`controllers._validate.check_weight`): a weight shared by the batch (no batch dims) that is not
    finite and symmetric positive (semi-)definite (``strict``: definite) is a ``ValueError`` naming it;
    batched weights are checked per element at solve time (:func:`_weight_reason`)."""
    W = _weight(W, size, name, fn)
    check_weight(W, name, fn, strict=strict, shared=W.dim() == 2)
    return W


def _weight_reason(W: Tensor, strict: bool) -> tuple[Tensor, Tensor]:
    """A batched weight ``(*Bw, k, k)`` with its failing elements replaced by the identity, and the
    ``(*Bw,)`` :class:`Reason` codes (``NONFINITE_INPUT``, ``NOT_POSITIVE_DEFINITE`` — not symmetric
    positive (semi-)definite — or 0)."""
    fin, sound = check_weight(W, "W", "ErrorStateMPC", strict=strict, shared=False)
    good = fin & sound
    reason = torch.where(fin, torch.where(good, 0, int(Reason.NOT_POSITIVE_DEFINITE)),
                         int(Reason.NONFINITE_INPUT))
    eye = torch.eye(W.shape[-1], dtype=W.dtype, device=W.device)
    return torch.where(good[..., None, None], W, eye), reason


def first_failure(*reasons: Tensor) -> Tensor:
    """Merge per-element :class:`Reason` codes: each element keeps the first failure (non-zero code) in
    the order given, so that no later stage overwrites an earlier failure."""
    out = reasons[0]
    for r in reasons[1:]:
        out = torch.where(out != 0, out, r)
    return out


#: the options of :func:`box_qp` that ``qp_options`` may set: its parameters other than the problem data and
#: ``check`` (the MPC's own business), read from its signature
_QP_KEYS = tuple(k for k, v in inspect.signature(box_qp).parameters.items()
                 if k not in ("H", "g", "lower", "upper", "x0", "check")
                 and v.kind in (inspect.Parameter.KEYWORD_ONLY, inspect.Parameter.POSITIONAL_OR_KEYWORD))

#: dtypes whose condensed QP is built and solved in float64 (cond(H) of a horizon of 40 exceeds 1/eps)
_REFINE_DTYPES = (torch.float16, torch.bfloat16, torch.float32)


def _limit(b, name: str, fn: str, N: int, m: int, own: bool):
    """A limit argument checked by the one rule (:func:`controllers._validate.check_limit`): ``None``, a float
    or a tensor broadcastable to ``(*B, N, m)`` (``own``: a limit of the system, a sequence or tensor cast to
    the data's dtype at solve time)."""
    if own and b is not None and not isinstance(b, (int, float, Tensor)):
        b = torch.as_tensor(b, dtype=torch.float64)
    return check_limit(b, name, fn, N, m)


def _check_options(fn: str, *, tol, **counts) -> None:
    """The iteration options of :meth:`ErrorStateMPC.iterate`: counts are ints (``TypeError``) ≥ 1, ``tol``
    None or a positive finite real (``ValueError`` naming the argument)."""
    for name, v in counts.items():
        if isinstance(v, bool) or not isinstance(v, int):
            raise TypeError(f"{fn}: argument '{name}' must be an int, got {type(v).__name__}")
        if v < 1:
            raise ValueError(f"{fn}: argument '{name}' must be >= 1, got {v}")
    if tol is None:
        return
    if isinstance(tol, bool) or not isinstance(tol, (int, float)):
        raise TypeError(f"{fn}: argument 'tol' must be None or a real number, got {type(tol).__name__}")
    if not (0 < tol < math.inf):
        raise ValueError(f"{fn}: argument 'tol' must be positive and finite, got {tol!r}")


class ErrorStateMPC:
    """Algorithm 1 of seed 003 (module docstring) for a batch of systems.

    Args:
        system: a :class:`ManifoldSystem`.
        horizon: N.
        Q, R: stage weights, ``(n,)``/``(m,)`` diagonals or ``(*B, n, n)``/``(*B, m, m)`` matrices (Q PSD,
            R PD); P: terminal weight (default Q).  Checked by the one rule of every solver
            (:func:`controllers._validate.check_weight`): a weight without batch dims that is not finite
            and symmetric PSD (Q, P) / PD (R) is a ``ValueError`` naming it; a batched weight's failing
            elements (NaN, not symmetric, not PSD/PD) get the status ``NONFINITE_INPUT``/
            ``NOT_POSITIVE_DEFINITE`` (NaN outputs), the others are solved as if alone.
        u_lower, u_upper: limits broadcastable to ``(*B, N, m)`` (default the system's ``u_lower``/
            ``u_upper`` when it has them, else none); ``None`` or ±inf for no limit.  A float limit that
            is NaN, ``u_lower = +inf``, ``u_upper = -inf``, or float limits with ``u_lower > u_upper``,
            are a ``ValueError``; tensor limits are checked per element at solve time (as
            :func:`~controllers.ilqr.ilqr` does, no host sync): a NaN entry makes that element
            ``NONFINITE_INPUT``; ``u_lower > u_upper``, ``u_lower = +inf`` or ``u_upper = -inf`` anywhere
            makes it ``INFEASIBLE_BOUNDS`` (NaN outputs either way).
        solver: ``"auto"``, ``"qp"`` (condensed, Eq. 28/31) or ``"riccati"`` (no limits only).
        grad: :class:`~controllers.problem.GradMode` (``"implicit"``, ``"none"``; ``"unrolled"`` is
            accepted by the Riccati path and treated as implicit by the QP path).
        jacobians: ``"auto"``, ``"analytic"`` or ``"autograd"`` (:func:`system_jacobians`).
        qp_options: keyword arguments for :func:`~controllers.boxqp.box_qp` (an unknown key is a
            ``ValueError``).
        compile: run :meth:`solve`'s numeric core (statuses of the inputs, manifold membership,
            linearization, condensed QP or Riccati form, the box QP, its certificate, the NaN-ing of failed
            elements) as one program built by :func:`controllers._compiled.build` (``torch.export`` +
            AOTInductor, a dynamic batch, cached on disk: the first solve of a shape/dtype/device builds it,
            seconds; later processes load it) with one host read per solve.  The values and statuses
            equal the eager path's (to round-off).  The box QP runs a fixed budget of active-set steps
            with :func:`~controllers.boxqp.box_qp`'s certificate; an element it does not certify (rare:
            an ill-conditioned or not convex QP, or non-finite data) is solved again eagerly, as are all
            elements of a batch with a state off the manifold or without a finite element (for the
            error the eager path raises).  Large bounded batches (the eager path's Riccati-first rule)
            run the Riccati program and condense only the elements that break a limit (one more host
            read when some do).  Stays eager: gradients (``grad`` not ``"none"`` with autograd
            enabled), :meth:`iterate`, systems that are not dataclasses of plain numbers and their
            manifold, points whose ProductState nests another, batched weights' checks (computed
            eagerly, then passed in), ``exact_G``-style options.  Default False (no build).

    With float32 (or half) data the condensed QP is built and solved in float64 and the result cast back
    (differentiably): the condensed Hessian of a long horizon is too ill-conditioned for float32 to find
    or certify its minimizer.
    """

    def __init__(self, system: ManifoldSystem, horizon: int, Q: Tensor, R: Tensor, P: Tensor | None = None, *,
                 u_lower: Tensor | float | None = None, u_upper: Tensor | float | None = None,
                 solver: str = "auto", grad: GradMode | str = GradMode.IMPLICIT, jacobians: str = "auto",
                 qp_options: dict | None = None, compile: bool = False):
        fn = "ErrorStateMPC"
        if not isinstance(compile, bool):
            raise TypeError(f"{fn}: argument 'compile' must be a bool, got {type(compile).__name__}")
        self.compile = compile
        self._cache: dict = {}
        M = getattr(system, "manifold", None)
        if M is None or not getattr(M, "has_boxplus", False):
            raise TypeError(f"{fn}: argument 'system' must have a 'manifold' with ⊞/⊟/⊕ "
                            f"(a torchlie.manifolds space), got {type(system).__name__}")
        for attr in ("m", "dt", "f"):
            if not hasattr(system, attr):
                raise TypeError(f"{fn}: argument 'system' lacks '{attr}' (see ManifoldSystem)")
        if not isinstance(horizon, int) or isinstance(horizon, bool) or horizon < 1:
            raise ValueError(f"{fn}: argument 'horizon' must be a positive int, got {horizon!r}")
        if solver not in ("auto", "qp", "riccati"):
            raise ValueError(f"{fn}: argument 'solver' must be 'auto', 'qp' or 'riccati', got {solver!r}")
        if jacobians not in ("auto", "analytic", "autograd"):
            raise ValueError(f"{fn}: argument 'jacobians' must be 'auto', 'analytic' or 'autograd', "
                             f"got {jacobians!r}")
        qp_options = {} if qp_options is None else qp_options
        if not isinstance(qp_options, dict):
            raise TypeError(f"{fn}: argument 'qp_options' must be a dict, got {type(qp_options).__name__}")
        unknown = sorted(set(qp_options) - set(_QP_KEYS))
        if unknown:
            raise ValueError(f"{fn}: argument 'qp_options' has unknown keys {unknown}; box_qp accepts "
                             f"{list(_QP_KEYS)}")
        self.system, self.manifold, self.N = system, M, horizon
        self.n, self.m = M.dim, int(system.m)
        self.Q = _checked_weight(Q, self.n, "Q", fn, strict=False)
        self.R = _checked_weight(R, self.m, "R", fn, strict=True)
        self.P = self.Q if P is None else _checked_weight(P, self.n, "P", fn, strict=False)
        # the system's own limits follow the data's dtype/device; limits passed here must match them
        self._own_limits = (u_lower is None, u_upper is None)
        if u_lower is None:
            u_lower = getattr(system, "u_lower", None)
        if u_upper is None:
            u_upper = getattr(system, "u_upper", None)
        u_lower = _limit(u_lower, "u_lower", fn, horizon, self.m, self._own_limits[0])
        u_upper = _limit(u_upper, "u_upper", fn, horizon, self.m, self._own_limits[1])
        if isinstance(u_lower, float) and isinstance(u_upper, float) and u_lower > u_upper:
            raise ValueError(f"{fn}: u_lower ({u_lower}) must be <= u_upper ({u_upper})")
        self.u_lower, self.u_upper = u_lower, u_upper
        self.bounded = any(b is not None and bool(torch.isfinite(torch.as_tensor(b)).any())
                           for b in (u_lower, u_upper))
        if solver == "riccati" and self.bounded:
            raise ValueError(f"{fn}: solver='riccati' cannot enforce control limits; use solver='qp', or "
                             "u_lower=-inf and u_upper=inf to drop the system's limits")
        self.solver = solver if solver != "auto" else ("qp" if self.bounded else "riccati")
        self.grad = enum_arg(GradMode, grad, "grad", fn)
        self.jacobians = jacobians
        self.qp_options = dict(qp_options)

    # -- helpers ---------------------------------------------------------------------------------
    def _limits(self, like: Tensor) -> tuple[Tensor, Tensor]:
        """The absolute limits as tensors of ``like``'s dtype/device, broadcastable to ``(*B, N, m)``."""
        def as_t(b, inf, own, name):
            if b is None:
                return torch.full((), inf, dtype=like.dtype, device=like.device)
            if isinstance(b, Tensor) and own:
                return b.to(dtype=like.dtype, device=like.device)
            if isinstance(b, Tensor):
                if b.dtype != like.dtype or b.device != like.device:
                    raise TypeError(f"ErrorStateMPC: argument '{name}' must have u_ref's dtype and device "
                                    f"({like.dtype}, {like.device}), got {b.dtype} on {b.device}")
                return b
            return torch.full((), b, dtype=like.dtype, device=like.device)
        return (as_t(self.u_lower, -torch.inf, self._own_limits[0], "u_lower"),
                as_t(self.u_upper, torch.inf, self._own_limits[1], "u_upper"))

    def _bounds(self, u_bar: Tensor, batch) -> tuple[Tensor, Tensor, Tensor]:
        """Limits on ``δu = u − ū``, ``(*B, N, m)`` each (±inf where unbounded), and the ``(*B,)`` reason
        codes of the limits: ``NONFINITE_INPUT`` where an entry is NaN, ``INFEASIBLE_BOUNDS`` where
        ``u_lower > u_upper``, ``u_lower = +inf`` or ``u_upper = -inf`` (no feasible control); such an element
        gets open limits (its outputs are NaN-ed by the caller)."""
        lo, hi = self._limits(u_bar)
        shape = (*batch, self.N, self.m)
        lo, hi = lo.expand(shape), hi.expand(shape)
        nan = (torch.isnan(lo) | torch.isnan(hi)).flatten(-2).any(-1)
        crossed = ((lo > hi) | (lo == math.inf) | (hi == -math.inf)).flatten(-2).any(-1)  # as ilqr's rule
        reason = torch.where(nan, int(Reason.NONFINITE_INPUT),
                             torch.where(crossed, int(Reason.INFEASIBLE_BOUNDS), 0))
        bad = (reason != 0)[..., None, None]
        lo = torch.where(bad, -torch.inf, lo)
        hi = torch.where(bad, torch.inf, hi)
        return lo - u_bar, hi - u_bar, reason

    def _limit_batch(self) -> dict:
        out = {}
        for name, b in (("u_lower", self.u_lower), ("u_upper", self.u_upper)):
            if isinstance(b, Tensor) and b.dim() > 2:
                out[name] = b.shape[:-2]
        return out

    def _prepare(self, x0, x_ref, u_ref: Tensor, fn: str):
        batch = self._check_args(x0, x_ref, u_ref, fn)
        return (*self._sanitized(x0, x_ref, u_ref, batch, fn), batch)

    def _check_args(self, x0, x_ref, u_ref: Tensor, fn: str):
        """The Python-level checks of a solve's arguments (types, shapes, dtypes, devices; no tensor is
        read): the broadcast batch shape, or a ``TypeError``/``ValueError`` naming the argument."""
        M, N, m = self.manifold, self.N, self.m
        product = hasattr(M, "components")
        for name, v in (("x0", x0), ("x_ref", x_ref)):
            if (not product and not isinstance(v, Tensor)) or (product and not hasattr(v, "batch_shape")):
                kind = "a ProductState" if product else "a torch.Tensor"
                raise TypeError(f"{fn}: argument '{name}' must be a point of {M!r} ({kind}), "
                                f"got {type(v).__name__}")
            if not product:
                check_tensor(v, tuple(M.event_shape), name, fn)  # floating, trailing shape of one point
            elif not all(leaf.dtype.is_floating_point for leaf in _leaves(v)):
                raise TypeError(f"{fn}: argument '{name}' must have floating components, got "
                                f"{[leaf.dtype for leaf in _leaves(v)]}")
        if not isinstance(u_ref, Tensor):
            raise TypeError(f"{fn}: argument 'u_ref' must be a torch.Tensor, got {type(u_ref).__name__}")
        if u_ref.dim() < 2 or u_ref.shape[-2:] != (N, m):
            raise ValueError(f"{fn}: argument 'u_ref' must have shape (*B, {N}, {m}) (horizon N={N}), "
                             f"got {tuple(u_ref.shape)}")
        rb = _batch_shape(M, x_ref)
        if len(rb) < 1 or rb[-1] != N + 1:
            raise ValueError(f"{fn}: argument 'x_ref' must be a point of {M!r} with batch (*B, {N + 1}) "
                             f"(N+1 reference states), got batch {tuple(rb)}")
        x0b = _batch_shape(M, x0)
        batch = broadcast_batch(fn, {"x0": x0b, "x_ref": rb[:-1], "u_ref": u_ref.shape[:-2],
                                     "Q": self.Q.shape[:-2], "R": self.R.shape[:-2], "P": self.P.shape[:-2],
                                     **self._limit_batch()})
        leaf = _leaves(x0)[0]
        for name, t in (("x_ref", _leaves(x_ref)[0]), ("u_ref", u_ref), ("Q", self.Q), ("R", self.R),
                        ("P", self.P)):
            if t.dtype != leaf.dtype or t.device != leaf.device:
                raise TypeError(f"{fn}: argument '{name}' must have x0's dtype and device ({leaf.dtype}, "
                                f"{leaf.device}), got {t.dtype} on {t.device}")
        return batch

    def _sanitized(self, x0, x_ref, u_ref: Tensor, batch, fn: str):
        """The inputs expanded to the batch, bad elements replaced by stand-ins, the states checked on the
        manifold: ``(x0, x_ref, u_ref, ok)``."""
        M, N, m = self.manifold, self.N, self.m
        x0 = _expand_point(M, x0, batch)
        x_ref = _expand_point(M, x_ref, (*batch, N + 1))
        u_ref = u_ref.expand(*batch, N, m)
        # one bad element never poisons the batch: replace it by its reference, report it, NaN its output
        ok = _point_finite(M, x0) & _point_finite(M, x_ref).all(-1) & all_finite(u_ref, 2)
        if not bool(ok.all()):
            if not bool(ok.any()):
                raise ValueError(f"{fn}: every element of the batch has a NaN/inf in x0, x_ref or u_ref")
            # stand-ins from a good element (any point of M will do: the outputs are NaN-ed afterwards)
            good = int(ok.reshape(-1).nonzero()[0, 0])
            flat_ref = _flatten_point(M, x_ref, len(batch) + 1)
            stand = _expand_point(M, time_slice(M, flat_ref, slice(good * (N + 1), (good + 1) * (N + 1))),
                                  (*batch, N + 1))
            x_ref = _where_point(M, ok.unsqueeze(-1).expand(*batch, N + 1), x_ref, stand)
            x0 = _where_point(M, ok, x0, time_index(M, x_ref, 0))
            u_ref = torch.where(ok[..., None, None], u_ref, torch.zeros((), dtype=u_ref.dtype))
        M.check(x0, "x0")
        M.check(x_ref, "x_ref")
        return x0, x_ref, u_ref, ok

    def _weights(self, batch) -> tuple[Tensor, Tensor, Tensor]:
        """``(Qs (*B, N+1, n, n), R (m, m) or (*B, m, m), reason (*B,))``: the stage and terminal weights,
        with the failing elements of batched weights replaced (and reported, :func:`_weight_reason`)."""
        N, n = self.N, self.n
        reason = torch.zeros(batch, dtype=torch.int64, device=self.Q.device)
        ws = []
        for W, strict in ((self.Q, False), (self.R, True), (self.P, False)):
            if W.dim() > 2:
                W, r = _weight_reason(W, strict)
                reason = first_failure(reason, r.expand(batch))
            ws.append(W)
        Q, R, P = ws
        Qs = torch.cat([Q.expand(*batch, n, n).unsqueeze(-3).expand(*batch, N, n, n),
                        P.expand(*batch, n, n).unsqueeze(-3)], -3)
        return Qs, R, reason

    def _warm(self, warm, u_ref: Tensor, batch, fn: str, name: str = "warm") -> Tensor | None:
        """``warm − u_ref`` (detached), after checking the type and shape of ``warm`` (argument ``name``)."""
        if warm is None:
            return None
        N, m = self.N, self.m
        if not isinstance(warm, Tensor):
            raise TypeError(f"{fn}: argument '{name}' must be a torch.Tensor, got {type(warm).__name__}")
        if warm.dtype != u_ref.dtype or warm.device != u_ref.device:
            raise TypeError(f"{fn}: argument '{name}' must have u_ref's dtype and device ({u_ref.dtype}, "
                            f"{u_ref.device}), got {warm.dtype} on {warm.device}")
        ok = warm.dim() >= 2 and warm.shape[-2:] == (N, m)
        if ok:
            try:
                ok = broadcast_shapes(warm.shape[:-2], batch) == batch
            except RuntimeError:
                ok = False
        if not ok:
            raise ValueError(f"{fn}: argument '{name}' must have shape (*B, {N}, {m}) with batch dims "
                             f"broadcastable to {tuple(batch)}, got {tuple(warm.shape)}")
        return warm.detach() - u_ref.detach()

    def _inputs(self, x0, x_ref, u_ref, warm, fn: str):
        """Checked and sanitized inputs of a solve: ``(x0, x_ref, u_ref, batch, Qs, R, lo, hi, warm,
        reason)`` with ``reason`` the per-element codes of the inputs (non-finite state or reference,
        then weights, then limits: the first failure wins)."""
        x0, x_ref, u_ref, ok, batch = self._prepare(x0, x_ref, u_ref, fn)
        w = self._warm(warm, u_ref, batch, fn)
        Qs, R, wreason = self._weights(batch)
        lo, hi, lreason = self._bounds(u_ref, batch)
        reason = first_failure(torch.where(ok, 0, int(Reason.NONFINITE_INPUT)), wreason, lreason)
        return x0, x_ref, u_ref, batch, Qs, R, lo, hi, w, reason

    # -- one linear-quadratic solve on an error system ---------------------------------------------
    def _solve_lq(self, es: ErrorSystem, dx0: Tensor, Qs: Tensor, R: Tensor, q: Tensor | None,
                  r: Tensor | None, lo: Tensor, hi: Tensor, warm: Tensor | None, *, solver: str,
                  grad: GradMode, riccati_first: bool = True):
        """Minimize Σ δxᵀQ_kδx + 2q_kᵀδx + δuᵀRδu + 2r_kᵀδu on the error system (δx_0 given); ``R`` is
        ``(m, m)`` or ``(*B, m, m)``.  The QP form runs in float64 for float32/half data (class docstring).

        Returns ``(δU (*B, N, m), δX (*B, N+1, n), cost (*B,), reason (*B,), kkt (*B,), clamped)``."""
        N, m = self.N, self.m
        batch = dx0.shape[:-1]
        dtype, dev = dx0.dtype, dx0.device
        n = dx0.shape[-1]
        if solver == "qp" and dtype in _REFINE_DTYPES:
            def f64(t):
                return None if t is None else t.to(torch.float64)
            out = self._solve_lq(ErrorSystem(f64(es.A), f64(es.B), f64(es.c)), f64(dx0), f64(Qs), f64(R),
                                 f64(q), f64(r), f64(lo), f64(hi), f64(warm), solver=solver, grad=grad,
                                 riccati_first=riccati_first)
            dU, dX, cost, reason, kkt, clamped = out
            return dU.to(dtype), dX.to(dtype), cost.to(dtype), reason, kkt.to(dtype), clamped
        if (solver == "qp" and riccati_first and self.bounded and R.dim() == 2
                and batch.numel() * (N * m) ** 2 * (N + 1) * n > _RICCATI_FIRST_FLOPS):
            # a big condensed QP (O(N³) per element): solve all by Riccati (O(N)), which is the answer for
            # every element whose controls respect the limits, and condense only the others
            out = self._solve_lq(es, dx0, Qs, R, q, r, lo, hi, warm, solver="riccati", grad=grad)
            with torch.no_grad():
                viol = ((out[0] < lo) | (out[0] > hi)).flatten(-2).any(-1)
            if not bool(viol.any()):
                return out
            idx = viol.reshape(-1).nonzero().squeeze(-1)

            def sub(t, k):  # the violating elements of a tensor with k event dims (batch first)
                if t is None:
                    return None
                t = t.expand(*batch, *t.shape[t.dim() - k:])
                return t.reshape(-1, *t.shape[len(batch):])[idx]

            es_v = ErrorSystem(A=sub(es.A, 3), B=sub(es.B, 3), c=sub(es.c, 2))
            res = self._solve_lq(es_v, sub(dx0, 1), sub(Qs, 3), R, sub(q, 2), sub(r, 2), sub(lo, 2),
                                 sub(hi, 2), sub(warm, 2), solver="qp", grad=grad, riccati_first=False)
            merged = []
            for full, part in zip(out, res):
                flat = full.reshape(-1, *full.shape[len(batch):])
                merged.append(flat.index_copy(0, idx, part.to(flat.dtype)).reshape(full.shape))
            return tuple(merged)
        if solver == "riccati":
            from controllers import riccati  # noqa: PLC0415  (riccati imports implicit; keep import cost lazy)

            Rt = R if R.dim() == 2 else R.unsqueeze(-3)  # (*B, 1, m, m): one R for all t
            cost = QuadraticCost(Q=Qs, R=Rt, q=q, r=r, check=False)
            prob = LQProblem(LinearDynamics(es.A, es.B, es.c), cost, dx0, horizon=N)
            sol = riccati.solve(prob, grad=grad, check=False)
            reason = sol.status.reason
            zeros = torch.zeros(batch, dtype=dtype, device=dev)
            clamped = torch.zeros(*batch, N, m, dtype=torch.bool, device=dev)
            return sol.u, sol.x, sol.cost, reason, zeros, clamped
        Su, free_x, H, g = _condensed_qp(es, dx0, Qs, R, q, r)
        dU, reason, kkt, clamped = self._qp_solve(H, g, lo, hi, warm, grad)
        dUr, dX, cost = _plan(Su, free_x, dU, Qs, R, q, r)
        return dUr, dX, cost, reason.to(torch.int64), kkt, clamped.reshape(*batch, N, m)

    def _qp_solve(self, H: Tensor, g: Tensor, lo: Tensor, hi: Tensor, warm: Tensor | None, grad: GradMode):
        """``min δUᵀHδU + 2gᵀδU`` over ``lo ≤ δU ≤ hi`` (``(*B, N, m)`` limits): the closed form (Eq. 31)
        where it respects the limits, the certified box QP (:meth:`_box`) for the elements where it does not.

        Returns ``(δU (*B, N m), reason (*B,), kkt (*B,), clamped (*B, N m))``."""
        N, m = self.N, self.m
        batch = g.shape[:-1]
        L, info = torch.linalg.cholesky_ex(H)
        dU = -torch.cholesky_solve(g.unsqueeze(-1), L).squeeze(-1)
        reason = torch.where(info == 0, 0, int(Reason.SINGULAR_QUU))
        clamped = torch.zeros(*batch, N * m, dtype=torch.bool, device=g.device)
        with torch.no_grad():
            kkt = (H @ dU.unsqueeze(-1)).squeeze(-1).add_(g).norm(dim=-1)
        if not self.bounded:
            return dU, reason, kkt, clamped
        lo = lo.expand(*batch, N, m).reshape(*batch, N * m)
        hi = hi.expand(*batch, N, m).reshape(*batch, N * m)
        with torch.no_grad():
            viol = ((dU < lo) | (dU > hi)).any(-1)  # (*B,): elements whose Eq. 31 breaks a limit
        if bool(viol.all()):
            dU, rbox, kkt, clamped = self._box(H, g, lo, hi, dU, warm, grad)
            return dU, first_failure(reason, rbox), kkt, clamped
        if bool(viol.any()):  # the box QP only for those; the others keep the closed form
            idx = viol.reshape(-1).nonzero().squeeze(-1)
            nb = idx.shape[0]

            def sub(t):
                return t.expand(*batch, *t.shape[len(batch):]).reshape(-1, *t.shape[len(batch):])[idx]
            w = None if warm is None else sub(warm.reshape(*warm.shape[:-2], N * m))
            dUs, rs, ks, cs = self._box(sub(H), sub(g), sub(lo), sub(hi), sub(dU), w, grad)
            dU = dU.reshape(-1, N * m).index_copy(0, idx, dUs).reshape(*batch, N * m)
            rs = first_failure(reason.reshape(-1)[idx], rs.to(reason.dtype).reshape(nb))
            reason = reason.reshape(-1).index_copy(0, idx, rs).reshape(batch)
            kkt = kkt.reshape(-1).index_copy(0, idx, ks.to(kkt.dtype).reshape(nb)).reshape(batch)
            clamped = clamped.reshape(-1, N * m).index_copy(0, idx, cs).reshape(*batch, N * m)
        return dU, reason, kkt, clamped

    def _box(self, H, g, lo, hi, start, warm, grad):
        """The box QP (28) from the clipped unconstrained minimizer (or the warm start), certified by
        :func:`box_qp`; differentiable through the active set it found."""
        batch, Nm = g.shape[:-1], g.shape[-1]
        with torch.no_grad():
            x0 = start.detach() if warm is None else warm.reshape(*batch, Nm)
            x0 = torch.nan_to_num(x0, nan=0.0)
            res = box_qp(H.detach(), g.detach(), lo.detach(), hi.detach(), x0, check=False, **self.qp_options)
        st = res.status
        failed = torch.where(st == BoxQPStatus.MAX_ITERATIONS, int(Reason.MAX_ITERATIONS),
                             int(Reason.STALLED))
        failed = torch.where(st == BoxQPStatus.NOT_POSITIVE_DEFINITE, int(Reason.SINGULAR_QUU), failed)
        reason = torch.where(res.converged, 0, failed)
        reason = torch.where(st == BoxQPStatus.NON_FINITE, int(Reason.NONFINITE_INPUT), reason)
        dU = res.x
        if grad is not GradMode.NONE and torch.is_grad_enabled() and (
                H.requires_grad or g.requires_grad or lo.requires_grad or hi.requires_grad):
            dU = _active_set_solve(H, g, lo, hi, res.clamped, dU)
        return dU, reason, res.kkt_residual, res.clamped

    # -- Algorithm 1 ---------------------------------------------------------------------------------
    def solve(self, x0, x_ref, u_ref: Tensor, *, warm: Tensor | None = None) -> ErrorStateSolution:
        """One MPC step (Algorithm 1): linearize about the reference, solve, return ``u = u^d_0 + δu_0``.

        Args:
            x0: the current state, a point with batch ``*B``.
            x_ref: N+1 reference states, a point with batch ``(*B, N+1)``.
            u_ref: ``(*B, N, m)`` reference controls.
            warm: optional ``(*B, N, m)`` controls (absolute) to warm-start the box QP, e.g. the previous
                plan shifted (:func:`controllers.mpc.shift`).
        """
        if self.compile and (self.grad is GradMode.NONE or not torch.is_grad_enabled()):
            sol = self._solve_compiled(x0, x_ref, u_ref, warm)
            if sol is not None:
                return sol
        return self._solve_eager(x0, x_ref, u_ref, warm)

    def _solve_eager(self, x0, x_ref, u_ref: Tensor, warm: Tensor | None) -> ErrorStateSolution:
        fn = "ErrorStateMPC.solve"
        x0, x_ref, u_ref, batch, Qs, R, lo, hi, w, reason0 = self._inputs(x0, x_ref, u_ref, warm, fn)
        M = self.manifold
        es = error_system(self.system, x_ref, u_ref, jacobians=self.jacobians)
        dx0 = M.boxminus(x0, time_index(M, x_ref, 0), check=False)
        dU, dX, cost, reason, kkt, clamped = self._solve_lq(es, dx0, Qs, R, None, None, lo, hi, w,
                                                            solver=self.solver, grad=self.grad)
        U = u_ref + dU
        reason = first_failure(reason0, reason)
        ok = reason0 == 0
        nan = torch.full((), torch.nan, dtype=U.dtype, device=U.device)
        U = torch.where(ok[..., None, None], U, nan)
        return ErrorStateSolution(u=U[..., 0, :], U=U, dx=torch.where(ok[..., None, None], dX, nan),
                                  cost=torch.where(ok, cost, nan), status=SolverStatus.from_reason(reason),
                                  kkt_residual=torch.where(ok, kkt, nan),
                                  clamped=clamped & ok[..., None, None])

    __call__ = solve

    # -- the compiled step (compile=True) ---------------------------------------------------------------
    def _program_inputs(self, x0, x_ref, u_ref: Tensor, warm: Tensor | None):
        """The flat, batch-first arguments of :func:`controllers._esmpc_core.step` after the Python-level
        checks: ``(spec, args, batch_dims, batch)``, or None where the compiled path does not apply."""
        from controllers._esmpc_core import Spec  # noqa: PLC0415

        fn = "ErrorStateMPC.solve"
        M, N, n, m = self.manifold, self.N, self.n, self.m
        batch = self._check_args(x0, x_ref, u_ref, fn)
        if warm is not None:
            self._warm(warm, u_ref, batch, fn)
        name = f"{M._name}.check"
        M._check_point(x0, "x0", name, False, False)  # structure and shapes (membership: in the program)
        M._check_point(x_ref, "x_ref", name, False, False)
        if self._system_key() is None or batch.numel() == 0:
            return None
        if isinstance(x0, Tensor):
            names, l0, lr = None, [x0], [x_ref]
        else:
            if not all(isinstance(t, Tensor) for t in list(x0.values()) + list(x_ref.values())):
                return None  # a nested ProductState
            names, l0, lr = tuple(x0.keys()), list(x0.values()), list(x_ref.values())
        ndims = tuple(len(M.event_shape) for _ in l0) if names is None else \
            tuple(x0.event_ndims[c] for c in names)
        B = batch.numel()
        args = [t.expand(*batch, *t.shape[t.dim() - k:]).reshape(B, *t.shape[t.dim() - k:])
                for t, k in zip(l0, ndims)]
        args += [t.expand(*batch, N + 1, *t.shape[t.dim() - k:]).reshape(B, N + 1, *t.shape[t.dim() - k:])
                 for t, k in zip(lr, ndims)]
        args.append(u_ref.expand(*batch, N, m).reshape(B, N, m))
        dims = [0] * len(args)
        lo, hi = self._limits(u_ref)
        lb = lo.dim() > 2 or hi.dim() > 2
        if lb:
            args += [lo.expand(*batch, N, m).reshape(B, N, m), hi.expand(*batch, N, m).reshape(B, N, m)]
        else:
            args += [lo.expand(N, m), hi.expand(N, m)]
        dims += [0 if lb else None] * 2
        wb = max(self.Q.dim(), self.R.dim(), self.P.dim()) > 2
        if wb:  # checked eagerly (the PSD test reads the host), passed in
            Qs, R, wr = self._weights(batch)
            args += [Qs.reshape(B, N + 1, n, n), R.expand(*batch, m, m).reshape(B, m, m), wr.reshape(B)]
            dims += [0, 0, 0]
        else:
            key = ("weights", u_ref.dtype, u_ref.device)
            if key not in self._cache:
                Qs, R, _ = self._weights(())
                self._cache[key] = (Qs.contiguous(), R.contiguous())
            args += list(self._cache[key])
            dims += [None, None]
        if warm is not None:
            args.append(warm.expand(*batch, N, m).reshape(B, N, m))
            dims.append(0)
        form = "qp" if self.solver == "qp" and not self._riccati_first(B) else "riccati"
        opts = self.qp_options
        spec = Spec(self.system, N, form, self.bounded, self.jacobians, names, ndims, wb, lb,
                    warm is not None, _QP_ITERS, opts.get("tol"), opts.get("gap_tol"))
        return spec, [a.contiguous() for a in args], dims, batch

    def _riccati_first(self, nb: int) -> bool:
        """The eager path's rule (:meth:`_solve_lq`): a big bounded batch goes through the Riccati form."""
        N, m, n = self.N, self.m, self.n
        return self.bounded and self.R.dim() == 2 and nb * (N * m) ** 2 * (N + 1) * n > _RICCATI_FIRST_FLOPS

    def _system_key(self) -> str | None:
        if "system" not in self._cache:
            from controllers._esmpc_core import system_key  # noqa: PLC0415

            self._cache["system"] = system_key(self.system)
        return self._cache["system"]

    def _program(self, spec, args, dims):
        import functools  # noqa: PLC0415

        from controllers import _compiled  # noqa: PLC0415
        from controllers._esmpc_core import step  # noqa: PLC0415

        return _compiled.build(f"esmpc_{spec.form}", spec.key(self._system_key()),
                               functools.partial(step, spec), tuple(args), dims)

    def _solve_compiled(self, x0, x_ref, u_ref: Tensor, warm: Tensor | None) -> ErrorStateSolution | None:
        """:meth:`solve` through the program (class docstring, ``compile``); None: take the eager path."""
        import dataclasses as dc  # noqa: PLC0415

        prep = self._program_inputs(x0, x_ref, u_ref, warm)
        if prep is None:
            return None
        spec, args, dims, batch = prep
        out = list(self._program(spec, args, dims)(*args))
        flags = out[-1].tolist()  # the one host read
        if flags[0] or flags[1]:
            return None  # no finite element / a state off the manifold: the eager path raises its error
        if flags[2] and spec.form == "riccati":  # elements that break a limit: condense those
            idx = out[6].nonzero().squeeze(-1)
            sub = [a if d is None else a.index_select(0, idx) for a, d in zip(args, dims)]
            qspec = dc.replace(spec, form="qp")
            part = list(self._program(qspec, sub, dims)(*sub))
            for i in range(6):
                out[i] = out[i].index_copy(0, idx, part[i])
            flags = part[-1].tolist()
            if flags[2]:
                j = part[6].nonzero().squeeze(-1)
                self._eager_subset(spec, args, dims, out, idx.index_select(0, j), batch)
        elif flags[2]:
            self._eager_subset(spec, args, dims, out, out[6].nonzero().squeeze(-1), batch)
        U, dX, cost, reason, kkt, clamped = (t.reshape((*batch, *t.shape[1:])) for t in out[:6])
        return ErrorStateSolution(u=U[..., 0, :], U=U, dx=dX, cost=cost,
                                  status=SolverStatus.from_reason(reason), kkt_residual=kkt, clamped=clamped)

    def _eager_subset(self, spec, args, dims, out: list, idx: Tensor, batch) -> None:
        """Solve the elements ``idx`` of the flat batch eagerly (the program's box QP did not certify them)
        and write them into ``out`` (the program's outputs)."""
        import copy  # noqa: PLC0415

        from torchlie.manifolds import ProductState  # noqa: PLC0415

        k = len(spec.ndims)
        sub = [a if d is None else a.index_select(0, idx) for a, d in zip(args, dims)]

        def point(leaves):
            if spec.names is None:
                return leaves[0]
            return ProductState(dict(zip(spec.names, leaves)), dict(zip(spec.names, spec.ndims)))

        mpc = copy.copy(self)
        mpc.compile = False
        if spec.limits_batched:
            mpc.u_lower, mpc.u_upper, mpc._own_limits = sub[2 * k + 1], sub[2 * k + 2], (False, False)
        if spec.weights_batched:
            def part(W):
                s = W.shape[-1]
                return W.expand(*batch, s, s).reshape(-1, s, s).index_select(0, idx) if W.dim() > 2 else W
            mpc.Q, mpc.R, mpc.P = part(self.Q), part(self.R), part(self.P)
        warm = sub[-1] if spec.warm else None
        sol = mpc._solve_eager(point(sub[:k]), point(sub[k:2 * k]), sub[2 * k], warm)
        for i, v in enumerate((sol.U, sol.dx, sol.cost, sol.status.reason, sol.kkt_residual, sol.clamped)):
            out[i] = out[i].index_copy(0, idx, v.to(out[i].dtype))

    # -- §V-D: iterate about rollouts ------------------------------------------------------------------
    def iterate(self, x0, x_ref, u_ref: Tensor, *, u_init: Tensor | None = None, max_iter: int = 50,
                tol: float | None = None, line_search_steps: int = 12) -> ErrorStateSolution:
        """The iterated variant of §V-D (module docstring): returns a point certified by the relative
        objective gap of its Gauss–Newton model (``CONVERGED``), or ``MAX_ITERATIONS``/``STALLED`` honestly.

        The certificate at the returned controls ``U``: with ``J(U)`` the true cost and ``γ``, ``H`` the
        gradient and Gauss–Newton Hessian of the model about ``U``'s rollout, the bound of
        :func:`_gap_bound` on how much the model can still decrease inside the limits is at most
        ``tol · J(U)`` (``kkt_residual`` is that ratio).  It is invariant under a common scaling of the
        weights and attainable in floating point (zero at a KKT point of the model).  With gradients
        enabled the returned values are the same (bit for bit): the derivative is that of one more
        Gauss–Newton step at ``U``, whose value is cancelled (an implicit-function step; the model's
        Hessian stands for the true one).

        ``u_init`` ``(*B, N, m)``: the first linearization controls (default ``u_ref`` clipped to the
        limits); ``tol``: the relative gap tolerance (default ``1e3 eps`` of the dtype: the cost is optimal
        to a thousand units of rounding); ``max_iter``
        Gauss–Newton steps at most, each with ``line_search_steps`` step lengths ``1, ½, …`` at most."""
        fn = "ErrorStateMPC.iterate"
        _check_options(fn, max_iter=max_iter, line_search_steps=line_search_steps, tol=tol)
        x0, x_ref, u_ref, batch, Qs, R, lo_abs, hi_abs, _, reason0 = self._inputs(x0, x_ref, u_ref, None, fn)
        ok = reason0 == 0
        lo_abs, hi_abs = lo_abs + u_ref, hi_abs + u_ref  # absolute (±inf stays ±inf)
        dtype, dev = u_ref.dtype, u_ref.device
        tol = 1e3 * torch.finfo(dtype).eps if tol is None else tol
        if u_init is not None:
            u_init = self._warm(u_init, u_ref, batch, fn, "u_init") + u_ref.detach()
        with torch.no_grad():
            U = (u_ref if u_init is None else u_init).detach()
            U = torch.minimum(torch.maximum(U, lo_abs.detach()), hi_abs.detach())
            U, reason, iters, kkt = self._gauss_newton(_detach(x0), _detach(x_ref), u_ref.detach(), U,
                                                       lo_abs.detach(), hi_abs.detach(), Qs.detach(),
                                                       R.detach(), ~ok, max_iter, tol, line_search_steps)
        if self.grad is not GradMode.NONE and torch.is_grad_enabled():
            # the implicit step: its value is cancelled, its derivative is the model's dU*/d(inputs)
            xd = manifold_rollout(self.system, _detach(x0), U)
            dU, _ = self._gn_step(xd, U, x0, x_ref, u_ref, lo_abs, hi_abs, Qs, R, grad_mode=True)
            dU = torch.where(torch.isfinite(dU), dU, torch.zeros((), dtype=dtype, device=dev))
            U = U + (dU - dU.detach())
        x = manifold_rollout(self.system, x0, U)
        Jfin, e = self._true_cost(x, U, x_ref, u_ref, Qs, R)
        reason = first_failure(reason0, reason)
        nan = torch.full((), torch.nan, dtype=dtype, device=dev)
        U = torch.where(ok[..., None, None], U, nan)
        clamped = (U <= lo_abs) | (U >= hi_abs)
        return ErrorStateSolution(u=U[..., 0, :], U=U, dx=torch.where(ok[..., None, None], e, nan),
                                  cost=torch.where(ok, Jfin, nan),
                                  status=SolverStatus.from_reason(reason, iters),
                                  kkt_residual=torch.where(ok, kkt, nan), clamped=clamped, x=x)

    def _true_cost(self, x, U, x_ref, u_ref, Qs, R):
        """``(J (*B,), e (*B, N+1, n))``: the cost of Eq. 15 of the rollout ``x`` of ``U``, and its errors."""
        e = self.manifold.boxminus(x, x_ref, check=False)
        du = U - u_ref
        Rb = R.expand(*U.shape[:-2], self.m, self.m)
        return ((e.unsqueeze(-2) @ Qs @ e.unsqueeze(-1)).sum((-3, -2, -1))
                + (du.unsqueeze(-2) @ Rb.unsqueeze(-3) @ du.unsqueeze(-1)).sum((-3, -2, -1))), e

    def _gauss_newton(self, x0, x_ref, u_ref, U, lo_abs, hi_abs, Qs, R, done, max_iter, tol, ls_steps):
        """The Gauss–Newton iteration of :meth:`iterate` (no graph): the certificate at every point it
        reaches (the last one included), steps by the model's QP and a backtracking line search on the true
        cost (all step lengths of the batch at once per trial).  Returns ``(U, reason, iters, kkt)``."""
        M, N = self.manifold, self.N
        batch = U.shape[:-2]
        dtype, dev = U.dtype, U.device
        x = manifold_rollout(self.system, x0, U)
        J, _ = self._true_cost(x, U, x_ref, u_ref, Qs, R)
        reason = torch.full(batch, int(Reason.MAX_ITERATIONS), dtype=torch.int64, device=dev)
        iters = torch.zeros(batch, dtype=torch.int64, device=dev)
        kkt = torch.full(batch, torch.inf, dtype=dtype, device=dev)
        tiny = torch.finfo(dtype).tiny
        for it in range(max_iter + 1):
            dU, gap = self._gn_step(x, U, x0, x_ref, u_ref, lo_abs, hi_abs, Qs, R, grad_mode=False)
            kkt = torch.where(done, kkt, gap / J.clamp_min(tiny))
            conv = (gap <= tol * J) & ~done
            reason = torch.where(conv, int(Reason.CONVERGED), reason)
            done = done | conv
            if it == max_iter or bool(done.all()):
                break
            alpha = torch.ones(batch, dtype=dtype, device=dev)
            accepted = torch.zeros(batch, dtype=torch.bool, device=dev)
            newU, newx, newJ = U, x, J
            for _ls in range(ls_steps):
                Ut = torch.minimum(torch.maximum(U + alpha[..., None, None] * dU, lo_abs), hi_abs)
                xt = manifold_rollout(self.system, x0, Ut)
                Jt, _ = self._true_cost(xt, Ut, x_ref, u_ref, Qs, R)
                good = (Jt < J) & ~accepted & ~done & torch.isfinite(Jt)
                newU = torch.where(good[..., None, None], Ut, newU)
                newx = _where_point(M, good.unsqueeze(-1).expand(*batch, N + 1), xt, newx)
                newJ = torch.where(good, Jt, newJ)
                accepted = accepted | good
                if bool((accepted | done).all()):
                    break
                alpha = torch.where(accepted, alpha, alpha * 0.5)
            stalled = ~accepted & ~done
            reason = torch.where(stalled, int(Reason.STALLED), reason)
            done = done | stalled
            iters = iters + accepted.to(torch.int64)
            U, x, J = newU, newx, newJ
        return U, reason, iters, kkt

    def _gn_step(self, x, U, x0, x_ref, u_ref, lo_abs, hi_abs, Qs, R, *, grad_mode: bool):
        """The Gauss–Newton model about the rollout ``(x, U)`` (``δx_0 = x0 ⊟ x_0``: zero, but it carries
        ``x0``'s derivative): its QP step ``δU (*B, N, m)`` and the bound of :func:`_gap_bound` at ``U``
        (the certificate, without a graph).  Built and solved in float64 for float32/half data."""
        M, N, m = self.manifold, self.N, self.m
        batch, dtype = U.shape[:-2], U.dtype
        es = error_system(self.system, x, U, jacobians=self.jacobians)
        e = M.boxminus(x, x_ref, check=False)  # (*B, N+1, n)
        Jm = _boxminus_jacobian(M, x, x_ref)  # (*B, N+1, n, n): the first order of the errors, exact
        Qt = Jm.transpose(-1, -2) @ Qs @ Jm
        q = (Jm.transpose(-1, -2) @ (Qs @ e.unsqueeze(-1))).squeeze(-1)
        r = (R.expand(*batch, m, m).unsqueeze(-3) @ (U - u_ref).unsqueeze(-1)).squeeze(-1)
        dx0 = M.boxminus(x0, time_index(M, x, 0), check=False).expand(*batch, self.n)
        lo, hi = lo_abs - U, hi_abs - U
        data = (es.A, es.B, es.c, dx0, Qt, R, q, r, lo, hi)
        if dtype in _REFINE_DTYPES:
            data = tuple(t.to(torch.float64) for t in data)
        A, B, c, dx0, Qt, R, q, r, lo, hi = data
        _, _, H, g = _condensed_qp(ErrorSystem(A, B, c), dx0, Qt, R, q, r)
        dU = self._qp_solve(H, g, lo, hi, None, self.grad if grad_mode else GradMode.NONE)[0]
        with torch.no_grad():
            gap = _gap_bound(H.detach(), g.detach(), lo.detach().reshape(g.shape),
                             hi.detach().reshape(g.shape))
        return dU.reshape(*batch, N, m).to(dtype), gap.to(dtype)


#: active-set steps of the compiled box QP (:func:`controllers.boxqp.box_qp_fixed`); an element they do not
#: certify is solved again eagerly
_QP_ITERS = 8

#: above this many multiply-adds for the condensed Hessians of a batch (``B (N m)² (N+1) n``) a bounded
#: solve goes through the Riccati form first and condenses only the elements that break a limit
_RICCATI_FIRST_FLOPS = 3e7


def _condensed_qp(es: ErrorSystem, dx0: Tensor, Qs: Tensor, R: Tensor, q: Tensor | None, r: Tensor | None):
    """The condensed QP (Eq. 28) of Σ δxᵀQ_kδx + 2q_kᵀδx + δuᵀRδu + 2r_kᵀδu on the error system:
    ``(S_u, free_x, H, g)`` with the cost ``δUᵀHδU + 2gᵀδU + const`` (:func:`_condense` for ``S_u``,
    ``free_x``)."""
    N, n, m = es.B.shape[-3], dx0.shape[-1], R.shape[-1]
    batch = dx0.shape[:-1]
    Su, free_x = _condense(es, dx0)  # (*B, N+1, n, Nm), (*B, N+1, n): δX = Su δU + free_x
    QSu = (Qs @ Su).reshape(*batch, (N + 1) * n, N * m)  # Q̄ S_u, block rows
    SuT = Su.reshape(*batch, (N + 1) * n, N * m).transpose(-1, -2)
    Rb = R.expand(*batch, m, m)
    eyeN = torch.eye(N, dtype=dx0.dtype, device=dx0.device)
    Rbar = (eyeN[:, None, :, None] * Rb[..., None, :, None, :]).reshape(*batch, N * m, N * m)
    H = SuT @ QSu + Rbar
    Qe = (Qs @ free_x.unsqueeze(-1)).squeeze(-1)
    if q is not None:
        Qe = Qe + q
    g = (SuT @ Qe.reshape(*batch, (N + 1) * n, 1)).squeeze(-1)
    if r is not None:
        g = g + r.reshape(*batch, N * m)
    return Su, free_x, H, g


def _plan(Su: Tensor, free_x: Tensor, dU: Tensor, Qs: Tensor, R: Tensor, q: Tensor | None, r: Tensor | None
          ) -> tuple[Tensor, Tensor, Tensor]:
    """The plan of a condensed solve ``δU (*B, N m)``: ``(δU (*B, N, m), δX (*B, N+1, n), cost (*B,))``."""
    batch, N, m = dU.shape[:-1], Su.shape[-3] - 1, R.shape[-1]
    dX = free_x + (Su @ dU.unsqueeze(-1).unsqueeze(-3)).squeeze(-1)
    dUr = dU.reshape(*batch, N, m)
    return dUr, dX, _plan_cost(dX, dUr, Qs, R, q, r)


def _plan_cost(dX: Tensor, dU: Tensor, Qs: Tensor, R: Tensor, q: Tensor | None, r: Tensor | None) -> Tensor:
    """``Σ δxᵀQ_kδx + 2q_kᵀδx + δuᵀRδu + 2r_kᵀδu`` of a plan ``δX (*B, N+1, n)``, ``δU (*B, N, m)``."""
    m = dU.shape[-1]
    Rb = R.expand(*dU.shape[:-2], m, m)
    cost = ((dX.unsqueeze(-2) @ Qs @ dX.unsqueeze(-1)).squeeze(-1).squeeze(-1)).sum(-1) \
        + ((dU.unsqueeze(-2) @ Rb.unsqueeze(-3) @ dU.unsqueeze(-1)).squeeze(-1).squeeze(-1)).sum(-1)
    if q is not None:
        cost = cost + 2 * (q * dX).sum((-2, -1))
    if r is not None:
        cost = cost + 2 * (r * dU).sum((-2, -1))
    return cost


def _gap_bound(H: Tensor, g: Tensor, lo: Tensor, hi: Tensor) -> Tensor:
    """An upper bound on ``q(0) − min q`` for the convex QP ``q(d) = dᵀHd + 2gᵀd`` over ``lo ≤ d ≤ hi``
    (``lo ≤ 0 ≤ hi``; ``(*B, k)`` vectors, ``H`` positive definite), by weak duality: with bound multipliers
    ``λ`` taken from ``g`` at the bounds that ``0`` touches (``λ_i = g_i > 0`` where ``lo_i = 0``,
    ``λ_i = g_i < 0`` where ``hi_i = 0``, else 0), ``q(d) ≥ −ρᵀH⁻¹ρ`` for every feasible ``d``, ``ρ = g − λ``
    (the complementarity terms ``λ_i·(distance to its bound)`` vanish).  The bound is 0 exactly at a KKT
    point and shrinks quadratically with the distance to it; it scales like the objective (so
    ``bound ≤ tol · cost`` is invariant under a common scaling of the weights).  ``inf`` where ``H`` is not
    positive definite."""
    lam = torch.where((lo >= 0) & (g > 0), g, torch.zeros((), dtype=g.dtype, device=g.device))
    lam = torch.where((hi <= 0) & (g < 0), g, lam)
    rho = g - lam
    L, info = torch.linalg.cholesky_ex(H)
    z = torch.linalg.solve_triangular(L, rho.unsqueeze(-1), upper=False).squeeze(-1)
    return torch.where(info == 0, (z * z).sum(-1), torch.inf)


def _condense(es: ErrorSystem, dx0: Tensor) -> tuple[Tensor, Tensor]:
    """``δX = S_u δU + (S_x δx_0 + s_c)`` (Eq. 25–27 with the drift): ``S_u (*B, N+1, n, N m)`` and the
    free response ``(*B, N+1, n)``, by one pass ``row_{k+1} = A_k row_k + [B_k E_k | c_k]`` over the
    augmented rows ``[S_u | free]``."""
    A, B, c = es.A, es.B, es.c
    N, n, m = B.shape[-3], B.shape[-2], B.shape[-1]
    batch = broadcast_shapes(A.shape[:-3], B.shape[:-3], c.shape[:-2], dx0.shape[:-1])
    eyeN = torch.eye(N, dtype=B.dtype, device=B.device)
    Bfull = (eyeN[:, None, :, None] * B.unsqueeze(-2)).reshape(*B.shape[:-3], N, n, N * m)
    add = torch.cat([Bfull.expand(*batch, N, n, N * m), c.expand(*batch, N, n).unsqueeze(-1)], -1)
    row = torch.cat([dx0.new_zeros(*batch, n, N * m), dx0.expand(*batch, n).unsqueeze(-1)], -1)
    A = A.expand(*batch, N, n, n)

    def step(t, carry, xs):  # one row block of [S_u | free] from the previous one
        nxt = xs[0] @ carry[0] + xs[1]
        return (nxt,), (nxt,)

    # a time loop the compiler sees once when traced (controllers._compiled.scan); a Python loop eagerly
    _, (rows,) = scan(step, (row,), [A.movedim(-3, 0), add.movedim(-3, 0)], N)
    Z = torch.cat([row.unsqueeze(-3), rows.movedim(0, -3)], -3)
    return Z[..., :-1], Z[..., -1]


def _detach(x):
    return x.detach()


def _boxminus_jacobian(M, x_bar, x_ref) -> Tensor:
    """``∂((x̄ ⊞ δ) ⊟ x^d)/∂δ`` at δ = 0, ``(*B, n, n)``, by ``jacrev`` of the batch sum."""
    n = M.dim
    batch = broadcast_shapes(_batch_shape(M, x_bar), _batch_shape(M, x_ref))
    xb = _expand_point(M, x_bar, batch)

    def expr(d):
        return M.boxminus(M.boxplus(xb, d, check=False), x_ref, check=False).reshape(-1, n).sum(0)

    leaf = _leaves(x_bar)[0]
    return torch.func.jacrev(expr)(leaf.new_zeros(*batch, n)).movedim(0, -2)


def _active_set_solve(H: Tensor, g: Tensor, lo: Tensor, hi: Tensor, clamped: Tensor, x: Tensor) -> Tensor:
    """The box-QP minimizer recomputed with autograd on the active set found by the solver: clamped
    components at their (differentiable) bounds, the free ones from ``H_ff x_f = −(g + H_fc x_c)``."""
    xd = x.detach()
    grad = g.detach() + (H.detach() @ xd.unsqueeze(-1)).squeeze(-1)
    at_lo = clamped & at_lower(xd, lo.detach(), hi.detach(), grad)
    xc = torch.where(clamped, torch.where(at_lo, lo, hi), torch.zeros((), dtype=H.dtype))
    free = ~clamped
    rhs = -(g + (H @ xc.unsqueeze(-1)).squeeze(-1))
    rhs = torch.where(free, rhs, torch.zeros((), dtype=H.dtype))
    L, _ = torch.linalg.cholesky_ex(masked_hessian(H, free))
    xf = torch.cholesky_solve(rhs.unsqueeze(-1), L).squeeze(-1)
    return torch.where(free, xf, xc)


# --------------------------------------------------------------------------------------------------
# closed loop
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class TrackingRun:
    """A closed-loop run of :func:`track`.

    Attributes:
        x: the simulated states, a point with batch ``(*B, steps+1)``.
        u: ``(*B, steps, m)`` applied controls (before the simulator's own saturation).
        solve_s: ``(steps,)`` wall-clock seconds of each MPC solve (the whole batch; ``time.perf_counter``,
            with a device synchronization on CUDA).
        reason: ``(*B, steps)`` the solve's :class:`~controllers.problem.Reason` codes.
    """

    x: Any
    u: Tensor
    solve_s: Tensor
    reason: Tensor


def track(mpc: ErrorStateMPC, simulate, x0, x_ref, u_ref: Tensor, steps: int, *, observe=None,
          warm_start: bool = True) -> TrackingRun:
    """Run Algorithm 1 in closed loop: at step k the MPC sees the reference window ``k .. k+N`` of
    ``x_ref`` (batch ``(*B, K)``, K ≥ steps + N + 1) and ``u_ref`` ``(*B, K-1, m)`` (or longer), and the
    simulator ``simulate(x, u) -> x_next`` (the "real" system, e.g. :class:`QuadrotorSimulator`) moves on.
    ``observe(x)`` maps a simulator state to the MPC's state space (default: identity; e.g. a projection
    onto the MPC's surface).  ``warm_start``: the box QP starts from the previous plan shifted.
    """
    M, N = mpc.manifold, mpc.N
    K = _batch_shape(M, x_ref)[-1]
    if K < steps + N + 1 or u_ref.shape[-2] < steps + N:
        raise ValueError(f"track: the reference must cover steps + N + 1 = {steps + N + 1} states and "
                         f"steps + N = {steps + N} controls, got {K} and {u_ref.shape[-2]}")
    xs, us, times, reasons = [x0], [], [], []
    x, warm = x0, None
    sync = _leaves(x0)[0].device.type == "cuda"
    for k in range(steps):
        xr = time_slice(M, x_ref, slice(k, k + N + 1))
        ur = u_ref[..., k:k + N, :]
        obs = x if observe is None else observe(x)
        if sync:
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        sol = mpc.solve(obs, xr, ur, warm=warm if warm_start else None)
        if sync:
            torch.cuda.synchronize()
        times.append(time.perf_counter() - t0)
        warm = torch.cat([sol.U[..., 1:, :], sol.U[..., -1:, :]], -2).detach()
        warm = torch.nan_to_num(warm)
        x = simulate(x, sol.u)
        xs.append(x)
        us.append(sol.u)
        reasons.append(sol.status.reason)
    return TrackingRun(x=_stack_points(M, xs), u=torch.stack(us, -2), solve_s=torch.tensor(times),
                       reason=torch.stack(reasons, -1))
