"""Receding-horizon MPC on top of :func:`controllers.ilqr.ilqr`, and the :class:`MPCPolicy` module.

At every control step the finite-horizon problem is solved from the current state, the first control is
applied and the rest of the plan, shifted by one step (the last control repeated), warm-starts the next
solve.  The warm start is *explicit state*: :class:`MPCState` goes in and comes out of every call and is
never kept on the solver or the module (DESIGN §2), so one policy can serve many independent rollouts.

:class:`MPCPolicy` maps a ``(B, n)`` observation to a ``(B, m)`` action.  Its cost weights and target are
``nn.Parameter``s (tensor parameters of the system model, e.g. a pendulum length given as an
``nn.Parameter``, are registered too), and gradients reach them through the implicit iLQR gradients
(:mod:`controllers.ilqr`), so the policy can be trained end to end or used as the action head of a network.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, is_dataclass

import torch
from torch import Tensor, nn

from controllers.ilqr import GradMode, ILQRMethod, ILQROptions, ILQRProblem, ILQRSolution, ilqr
from controllers.problem import QuadraticCost, enum_arg

__all__ = ["MPCState", "MPCRollout", "shift", "mpc_step", "run_mpc", "MPCPolicy"]


@dataclass(frozen=True, eq=False)
class MPCState:
    """Warm start carried from one MPC step to the next.

    Attributes:
        u: ``(*B, T, m)`` controls for the next solve (the previous plan shifted by one step), no graph.
        converged: ``(*B,)`` bool, whether the solve that produced this state converged.
        iterations: ``(*B,)`` int64 iterations of that solve.
    """

    u: Tensor
    converged: Tensor
    iterations: Tensor


def shift(u: Tensor, fill: str = "last") -> Tensor:
    """Shift a plan ``(*B, T, m)`` one step forward in time; the new last step repeats the old last one
    (``fill="last"``) or is zero (``fill="zero"``)."""
    if u.dim() < 2:
        raise ValueError(f"shift: u must have shape (*B, T, m), got {tuple(u.shape)}")
    if fill not in ("last", "zero"):
        raise ValueError(f"shift: fill must be 'last' or 'zero', got {fill!r}")
    tail = u[..., -1:, :] if fill == "last" else torch.zeros_like(u[..., -1:, :])
    return torch.cat([u[..., 1:, :], tail], dim=-2)


def mpc_step(problem: ILQRProblem, state: MPCState | None = None, *,
             method: ILQRMethod | str = ILQRMethod.RECURSIVE, grad: GradMode | str = GradMode.IMPLICIT,
             options: ILQROptions | None = None) -> tuple[Tensor, MPCState, ILQRSolution]:
    """One receding-horizon step: solve from ``problem.x0`` warm-started by ``state``.

    Returns ``(action (*B, m), next_state, solution)``; the action is ``solution.u[..., 0, :]`` and carries
    gradients per ``grad``.
    """
    u_init = None if state is None else state.u
    if u_init is not None and u_init.shape[-2] != problem.T:
        raise ValueError(f"mpc_step: warm start has horizon {u_init.shape[-2]} "
                         f"but the problem has {problem.T}")
    sol = ilqr(problem, u_init, method=method, grad=grad, options=options)
    u = sol.u.detach()
    u = torch.where(torch.isfinite(u), u, torch.zeros((), dtype=u.dtype, device=u.device))
    nxt = MPCState(u=shift(u), converged=sol.status.converged, iterations=sol.status.iterations)
    return sol.u[..., 0, :], nxt, sol


@dataclass(frozen=True, eq=False)
class MPCRollout:
    """Closed-loop trajectory of :func:`run_mpc`: ``x (*B, steps+1, n)``, ``u (*B, steps, m)``,
    ``converged (*B, steps)`` and ``iterations (*B, steps)`` of the solve at each step."""

    x: Tensor
    u: Tensor
    converged: Tensor
    iterations: Tensor


def run_mpc(system, cost: QuadraticCost, x0: Tensor, horizon: int, steps: int, *,
            u_lower=None, u_upper=None, simulator=None, warm_start: bool = True,
            options: ILQROptions | None = None) -> MPCRollout:
    """Run MPC in closed loop for ``steps`` steps (no gradients).

    Args:
        system: dynamics for the planner (see :class:`~controllers.ilqr.ILQRProblem`).
        cost: the planner's cost over ``horizon`` (time-invariant weights are re-used at every step).
        x0: ``(*B, n)`` initial states.
        simulator: ``step(x, u, t) -> x_next`` of the plant; the planner's own model by default.
        warm_start: shift the previous plan into the next solve (``False``: start from zeros each step).
    """
    sim = simulator if simulator is not None else system
    x = x0
    xs, us, conv, its = [x0], [], [], []
    state = None
    with torch.no_grad():
        for k in range(steps):
            prob = ILQRProblem(system, cost, x, horizon, u_lower=u_lower, u_upper=u_upper)
            a, nxt, _ = mpc_step(prob, state if warm_start else None, grad="none", options=options)
            state = nxt
            x = sim.step(x, a, k)
            xs.append(x)
            us.append(a)
            conv.append(nxt.converged)
            its.append(nxt.iterations)
    return MPCRollout(x=torch.stack(xs, -2), u=torch.stack(us, -2), converged=torch.stack(conv, -1),
                      iterations=torch.stack(its, -1))


def _inv_softplus(v: Tensor) -> Tensor:
    return v + torch.log(-torch.expm1(-v))


class MPCPolicy(nn.Module):
    """A differentiable MPC policy: observation ``(B, n)`` → action ``(B, m)``.

    The cost is ``Σ_t (x_t - x*)ᵀ diag(q) (x_t - x*) + uᵀ diag(r) u`` with terminal weight
    ``terminal_factor · diag(q)``; ``q``, ``r`` (positive through a softplus) and the target ``x*`` are
    ``nn.Parameter``s.  ``forward(obs, state)`` returns ``(action, next_state)``: the warm start is passed in
    and returned, never stored on the module.

    Args:
        system: a model from :mod:`controllers.systems` (or any dynamics accepted by
            :class:`~controllers.ilqr.ILQRProblem`); tensor fields that are ``nn.Parameter``s are registered.
        horizon: planning horizon ``T``.
        q, r: initial diagonal weights ``(n,)``, ``(m,)``; target: initial ``x*`` ``(n,)``.
        u_lower, u_upper: control limits (floats or ``(m,)`` tensors).
        grad: gradient mode of the solver (implicit by default).
    """

    def __init__(self, system, horizon: int, q: Tensor, r: Tensor, target: Tensor, *,
                 terminal_factor: float = 10.0, u_lower=None, u_upper=None,
                 grad: GradMode | str = GradMode.IMPLICIT, options: ILQROptions | None = None):
        super().__init__()
        n, m = system.n, system.m
        q, r, target = (torch.as_tensor(v) for v in (q, r, target))
        for name, v in (("r", r), ("target", target)):
            if v.dtype != q.dtype:
                raise TypeError(f"MPCPolicy: argument '{name}' has dtype {v.dtype} but 'q' has {q.dtype}; "
                                "give q, r and target one dtype")
        for name, v in (("u_lower", u_lower), ("u_upper", u_upper)):
            if isinstance(v, torch.Tensor) and v.dtype != q.dtype:
                raise TypeError(f"MPCPolicy: argument '{name}' has dtype {v.dtype} but 'q' has {q.dtype}")
        if q.shape != (n,) or target.shape != (n,):
            raise ValueError(f"MPCPolicy: q and target must have shape ({n},), got {tuple(q.shape)} and "
                             f"{tuple(target.shape)}")
        if r.shape != (m,):
            raise ValueError(f"MPCPolicy: r must have shape ({m},), got {tuple(r.shape)}")
        if bool((q <= 0).any()) or bool((r <= 0).any()):
            raise ValueError("MPCPolicy: initial weights q and r must be positive")
        if not isinstance(horizon, int) or horizon < 1:
            raise ValueError(f"MPCPolicy: horizon must be a positive int, got {horizon!r}")
        self.system = system
        self.horizon = horizon
        self.terminal_factor = float(terminal_factor)
        self.grad = enum_arg(GradMode, grad, "grad", "MPCPolicy")
        self.options = options
        self.q_raw = nn.Parameter(_inv_softplus(q.detach().clone()))
        self.r_raw = nn.Parameter(_inv_softplus(r.detach().clone()))
        self.target = nn.Parameter(target.detach().clone())
        for name, v in (("u_lower", u_lower), ("u_upper", u_upper)):
            self.register_buffer(name, None if v is None else torch.as_tensor(v, dtype=q.dtype).reshape(-1))
        if is_dataclass(system):
            for f in fields(system):
                v = getattr(system, f.name)
                if isinstance(v, nn.Parameter):
                    self.register_parameter(f"system_{f.name}", v)

    @property
    def q(self) -> Tensor:
        return nn.functional.softplus(self.q_raw)

    @property
    def r(self) -> Tensor:
        return nn.functional.softplus(self.r_raw)

    def cost(self) -> QuadraticCost:
        """The current :class:`~controllers.problem.QuadraticCost` (differentiable in the parameters)."""
        T = self.horizon
        Q = torch.diag_embed(self.q)
        Qs = torch.cat([Q.expand(T, *Q.shape), (self.terminal_factor * Q)[None]])
        return QuadraticCost(Q=Qs, R=torch.diag_embed(self.r), x_ref=self.target, check=False)

    def initial_state(self, batch: int) -> MPCState:
        """A cold start (zero controls) for ``batch`` environments."""
        p = self.q_raw
        return MPCState(u=torch.zeros(batch, self.horizon, self.system.m, dtype=p.dtype, device=p.device),
                        converged=torch.zeros(batch, dtype=torch.bool, device=p.device),
                        iterations=torch.zeros(batch, dtype=torch.int64, device=p.device))

    def forward(self, obs: Tensor, state: MPCState | None = None) -> tuple[Tensor, MPCState]:
        """``(action (B, m), next_state)`` for observations ``obs (B, n)``."""
        n = self.system.n
        if obs.dim() < 1 or obs.shape[-1] != n:
            raise ValueError(f"MPCPolicy: obs must have shape (B, {n}), got {tuple(obs.shape)}")
        if obs.dtype != self.q_raw.dtype:
            raise TypeError(f"MPCPolicy: obs has dtype {obs.dtype} but the policy is {self.q_raw.dtype}; "
                            "use policy.to(dtype) or cast the observation")
        lo = None if self.u_lower is None else self.u_lower
        hi = None if self.u_upper is None else self.u_upper
        prob = ILQRProblem(self.system, self.cost(), obs, self.horizon, u_lower=lo, u_upper=hi)
        action, nxt, _ = mpc_step(prob, state, grad=self.grad, options=self.options)
        return action, nxt

    def extra_repr(self) -> str:
        return f"system={type(self.system).__name__}, horizon={self.horizon}, grad={self.grad.value}"

