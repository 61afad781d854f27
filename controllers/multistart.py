"""Multi-start iLQR: solve one problem from ``K`` initial guesses at once and keep the best certified plan.

iLQR converges — certifiably, its KKT residual checked — to *a* local minimum, the one its initial guess
leads to.  On a swing-up that is often a poor one: a pendulum started 4° from upright, planned from zero
controls, converges to a full swing (cost 370.8) where braking costs 0.37.  :func:`ilqr_multistart` runs
the guesses as one batched solve (the problem's batch ``(*B,)`` becomes ``(*B, K)``) and keeps, per
element, the lowest-cost guess among those that ended ``CONVERGED``; where none did, the lowest finite cost
(its status then says why it is not certified).  So the plan returned is never worse than the plan of any
certified guess, the zero start included when it is one.

:func:`guesses` builds the usual set for receding-horizon control: the previous plan shifted, zero
controls, each limit held ("bang" starts that brake or push), and smooth random sequences from an explicit
generator; :func:`lqr_guess` adds the closed-loop "hold" guess (the model under the LQR about the cost's
target), the one that finds the braking plan of that pendulum: open-loop guesses of an unstable system
all fall away from the target and lead iLQR to the swing.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch
from torch import Tensor

from controllers.costs import QuadraticCost
from controllers.ilqr import ILQRMethod, ILQROptions, ILQRProblem, ILQRSolution, ilqr
from controllers.problem import GradMode, SolverStatus

__all__ = ["MultiStartSolution", "ilqr_multistart", "select_best", "guesses", "lqr_guess", "quadratic_parts"]


@dataclass(frozen=True, eq=False)
class MultiStartSolution:
    """Result of :func:`ilqr_multistart`.

    Attributes:
        best: the :class:`~controllers.ilqr.ILQRSolution` of the chosen guess per element (batch ``(*B,)``).
        choice: ``(*B,)`` int64 index of the chosen guess.
        costs: ``(*B, K)`` the cost each guess converged to (NaN for a failed element).
        converged: ``(*B, K)`` bool, which guesses ended certified ``CONVERGED``.
    """

    best: ILQRSolution
    choice: Tensor
    costs: Tensor
    converged: Tensor


def select_best(cost: Tensor, converged: Tensor) -> Tensor:
    """``(*B,)`` index over the last dim of ``cost (*B, K)``: the lowest cost among the ``converged`` entries
    where there is one, else the lowest finite cost, else 0."""
    c = cost.detach()
    finite = torch.isfinite(c)
    inf = torch.full((), math.inf, dtype=c.dtype, device=c.device)
    ok = converged & finite
    best_ok = torch.where(ok, c, inf).argmin(-1)
    best_any = torch.where(finite, c, inf).argmin(-1)
    return torch.where(ok.any(-1), best_ok, best_any)


def _take(v: Tensor, idx: Tensor) -> Tensor:
    """``v (K, *B, ...)`` at guess ``idx (*B,)`` per element: ``(*B, ...)``."""
    i = idx.reshape(1, *idx.shape, *[1] * (v.dim() - 1 - idx.dim())).expand(1, *v.shape[1:])
    return v.gather(0, i).squeeze(0)


def _expand_problem(problem: ILQRProblem, K: int) -> ILQRProblem:
    """The problem with a guess dim ``K`` *in front of* its batch dims: ``x0 (K, *B, n)``.  Leading, so that
    anything batched over ``(*B,)`` — a cost's targets and weights, the limits — broadcasts against
    ``(K, *B)`` as it did against ``(*B,)``."""
    x0 = problem.x0.expand(K, *problem.x0.shape)
    return dataclasses.replace(problem, x0=x0)


def ilqr_multistart(problem: ILQRProblem, u_inits: Tensor, *, method: ILQRMethod | str = ILQRMethod.RECURSIVE,
                    grad: GradMode | str = GradMode.NONE,
                    options: ILQROptions | None = None) -> MultiStartSolution:
    """Solve ``problem`` from each of ``K`` initial guesses in one batched :func:`~controllers.ilqr.ilqr` call
    and keep the best certified plan per element (module docstring).

    Args:
        problem: an :class:`~controllers.ilqr.ILQRProblem` with batch ``(*B,)`` (the guesses run as a batch
            ``(K, *B)``, so a cost or limits batched over ``(*B,)`` stay with their elements).
        u_inits: ``(*B, K, T, m)`` or ``(K, T, m)`` guesses (projected onto the limits by the solver).
        method, grad, options: as :func:`~controllers.ilqr.ilqr`; gradients flow through the chosen guess's
            solution (the choice itself is piecewise constant).

    Returns:
        :class:`MultiStartSolution`.
    """
    T, m = problem.T, problem.m
    if not isinstance(u_inits, Tensor) or u_inits.dtype != problem.dtype:
        raise TypeError(f"ilqr_multistart: argument 'u_inits' must be a tensor of dtype {problem.dtype}")
    if u_inits.dim() < 3 or tuple(u_inits.shape[-2:]) != (T, m):
        raise ValueError(f"ilqr_multistart: argument 'u_inits' must have shape (*B, K, {T}, {m}) or "
                         f"(K, {T}, {m}), got {tuple(u_inits.shape)}")
    K = u_inits.shape[-3]
    if K < 1:
        raise ValueError("ilqr_multistart: argument 'u_inits' has no guess (K = 0)")
    bs = problem.batch_shape
    try:
        U = u_inits.movedim(-3, 0).expand(K, *torch.broadcast_shapes(bs, u_inits.shape[:-3]), T, m)
    except RuntimeError:
        raise ValueError(f"ilqr_multistart: argument 'u_inits' has batch dims {tuple(u_inits.shape[:-3])} "
                         f"that do not broadcast with the problem's {tuple(bs)}") from None
    sol = ilqr(_expand_problem(problem, K), U, method=method, grad=grad, options=options)
    costs = sol.cost.movedim(0, -1)
    conv = sol.status.converged.movedim(0, -1)
    idx = select_best(costs, conv)
    st = sol.status
    status = SolverStatus(converged=_take(st.converged, idx), iterations=_take(st.iterations, idx),
                          reason=_take(st.reason, idx))
    best = ILQRSolution(x=_take(sol.x, idx), u=_take(sol.u, idx), K=_take(sol.K, idx), k=_take(sol.k, idx),
                        cost=_take(sol.cost, idx), status=status, clamped=_take(sol.clamped, idx),
                        cost_history=_take(sol.cost_history.movedim(0, -1), idx).movedim(-1, 0),
                        mu=_take(sol.mu, idx), kkt_residual=_take(sol.kkt_residual, idx))
    return MultiStartSolution(best=best, choice=idx, costs=costs.detach(), converged=conv)


def guesses(batch_shape: tuple[int, ...] | torch.Size, horizon: int, lower: Tensor, upper: Tensor, *,
            previous: Tensor | None = None, random: int = 0, knots: int = 4,
            generator: torch.Generator | None = None) -> Tensor:
    """The standard initial guesses ``(*B, K, T, m)`` for a receding-horizon solve.

    In order: ``previous`` (``(*B, T, m)``, the last plan shifted; omitted when ``None``), zero controls
    (clipped into the box), each of the ``2m`` constant sequences with one control on a limit and the others
    zero (the "bang" starts: braking, pushing), then ``random`` smooth sequences: uniform values in the box at
    ``knots`` evenly spaced times, linearly interpolated (from ``generator``).  ``lower``/``upper`` are the
    finite ``(m,)`` limits (dtype and device of the result).
    """
    bs = tuple(batch_shape)
    lo, hi = lower.reshape(-1), upper.reshape(-1)
    m = lo.shape[0]
    kw = dict(dtype=lo.dtype, device=lo.device)
    if not (torch.isfinite(lo).all() and torch.isfinite(hi).all()) or bool((lo > hi).any()):
        raise ValueError("guesses: arguments 'lower' and 'upper' must be finite (m,) limits, lower <= upper")
    if random > 0 and generator is None:
        raise ValueError("guesses: random starts need an explicit 'generator' (torch.Generator)")
    zero = torch.zeros(m, **kw).clamp(lo, hi)
    bang = zero.expand(2 * m, m).clone()
    ar = torch.arange(m, device=lo.device)
    bang[ar, ar] = lo
    bang[m + ar, ar] = hi
    fixed = torch.cat([zero[None], bang], 0)[:, None, :].expand(-1, horizon, m)  # (1 + 2m, T, m)
    parts = [] if previous is None else [previous.unsqueeze(-3)]
    parts.append(fixed.expand(*bs, *fixed.shape))
    if random > 0:
        k = max(int(knots), 2)
        v = torch.rand(*bs, random, k, m, generator=generator, **kw) * (hi - lo) + lo
        s = torch.linspace(0, k - 1, horizon, **kw)
        i0 = s.floor().long().clamp(max=k - 2)
        w = (s - i0.to(s.dtype))[:, None]
        parts.append(v[..., i0, :] * (1 - w) + v[..., i0 + 1, :] * w)
    return torch.cat(parts, -3)


def quadratic_parts(cost):
    """``(Q (T+1|1, n, n), R (T|1, m, m), x_ref (n,), u_ref (m,), wrap)`` of a quadratic cost (or a periodic
    one: ``wrap`` maps a state to its branch nearest the target), ``None`` for any other cost or one with
    batch dims or a time-varying target."""
    from controllers.costs import PeriodicQuadraticCost

    wrap = None
    if isinstance(cost, PeriodicQuadraticCost):
        wrap, cost = cost.wrapped, cost.base
    if not isinstance(cost, QuadraticCost) or len(cost.batch_shape) > 0:
        return None
    kw = dict(dtype=cost.Q.dtype, device=cost.Q.device)
    xr = torch.zeros(cost.n, **kw) if cost.x_ref is None else cost.x_ref
    ur = torch.zeros(cost.m, **kw) if cost.u_ref is None else cost.u_ref
    if xr.dim() > 1 and xr.shape[-2] > 1 or ur.dim() > 1 and ur.shape[-2] > 1:
        return None
    Q = cost.Q if cost.Q.dim() == 3 else cost.Q[None]
    R = cost.R if cost.R.dim() == 3 else cost.R[None]
    return Q, R, xr.reshape(-1), ur.reshape(-1), wrap


def lqr_guess(system, cost, x0: Tensor, horizon: int, lower: Tensor | None = None,
              upper: Tensor | None = None) -> Tensor | None:
    """The "hold" guess ``(*B, T, m)``: the model rolled out from ``x0`` under the finite-horizon LQR about
    the cost's target ``(x_ref, u_ref)`` (the system linearized there, the cost's ``Q_t``, ``R_t``), each
    control clamped to the limits — a closed-loop guess, so that on an unstable system it still brakes
    towards the target where open-loop guesses all fall away.  ``None`` when the cost is not a quadratic
    cost (or a periodic one) with a constant target shared by the batch.
    """
    from controllers.dynamics import jacobians

    parts = quadratic_parts(cost)
    if parts is None:
        return None
    Q, R, xr, ur, wrap = (v.to(x0.dtype) if isinstance(v, Tensor) else v for v in parts)
    A, B = jacobians(system, xr[None], ur[None])[1:]
    A, B = A[0], B[0]
    P = Q[-1]
    gains = []
    for t in reversed(range(horizon)):
        Qt, Rt = Q[min(t, Q.shape[0] - 1)], R[min(t, R.shape[0] - 1)]
        BtP = B.T @ P
        Kt = torch.linalg.solve(Rt + BtP @ B, BtP @ A)
        P = Qt + A.T @ P @ (A - B @ Kt)
        P = 0.5 * (P + P.T)
        gains.append(Kt)
    gains.reverse()
    x, us = x0, []
    for t in range(horizon):
        dx = (x if wrap is None else wrap(x)) - xr
        u = ur - dx @ gains[t].T
        if lower is not None:
            u = torch.maximum(u, lower)
        if upper is not None:
            u = torch.minimum(u, upper)
        us.append(u)
        x = system.step(x, u, t)
    return torch.stack(us, -2)
