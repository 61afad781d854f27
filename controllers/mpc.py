"""Receding-horizon MPC on top of :func:`controllers.ilqr.ilqr`, and the :class:`MPCPolicy` module.

At every control step the finite-horizon problem is solved from the current state, the first control is
applied and the rest of the plan, shifted by one step (the last control repeated), warm-starts the next
solve.  The warm start is *explicit state*: :class:`MPCState` goes in and comes out of every call and is
never kept on the solver or the module (DESIGN §2), so one policy can serve many independent rollouts.

:class:`MPCPolicy` maps a ``(*B, n)`` observation to a ``(*B, m)`` action.  Its cost is any ``nn.Module``
that turns the observation into a :class:`~controllers.costs.Cost` (e.g.
:class:`~controllers.costs.DiagonalQuadraticCost`, learnable diagonal weights and target; or a network
that predicts a goal), tensor parameters of the system model (e.g. a pendulum length given as an
``nn.Parameter``) are registered too, and gradients reach them through the implicit iLQR gradients
(:mod:`controllers.implicit`), so the policy can be trained end to end or used as the action head of a
network.  In a vector environment, :meth:`MPCState.reset` cold-starts the elements whose episode ended.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, is_dataclass

import torch
from torch import Tensor, nn

from controllers._validate import enum_arg
from controllers.costs import Cost
from controllers.dynamics import System
from controllers.ilqr import ILQRMethod, ILQROptions, ILQRProblem, ILQRSolution, ilqr
from controllers.problem import GradMode

__all__ = ["MPCState", "MPCRollout", "shift", "mpc_step", "run_mpc", "MPCPolicy"]


@dataclass(frozen=True, eq=False)
class MPCState:
    """Warm start carried from one MPC step to the next (immutable: every method returns a new state).

    Attributes:
        u: ``(*B, T, m)`` controls for the next solve (the previous plan shifted by one step), no graph.
        converged: ``(*B,)`` bool, whether the solve that produced this state converged.
        iterations: ``(*B,)`` int64 iterations of that solve.
    """

    u: Tensor
    converged: Tensor
    iterations: Tensor

    @staticmethod
    def cold(batch_shape: int | tuple[int, ...] | torch.Size, horizon: int, m: int, *,
             dtype: torch.dtype | None = None, device: torch.device | str | None = None) -> MPCState:
        """A cold start (zero controls, nothing converged) for a batch of shape ``batch_shape``."""
        bs = (batch_shape,) if isinstance(batch_shape, int) else tuple(batch_shape)
        if any(not isinstance(b, int) or b < 0 for b in bs):
            raise ValueError(f"MPCState.cold: argument 'batch_shape' must be an int or a tuple of "
                             f"non-negative ints, got {batch_shape!r}")
        return MPCState(u=torch.zeros(*bs, horizon, m, dtype=dtype, device=device),
                        converged=torch.zeros(bs, dtype=torch.bool, device=device),
                        iterations=torch.zeros(bs, dtype=torch.int64, device=device))

    @property
    def batch_shape(self) -> torch.Size:
        return self.converged.shape

    def reset(self, done: Tensor) -> MPCState:
        """Cold-start the elements where ``done`` (bool, the batch shape) is True — e.g. the environments
        whose episode just ended — and keep the others' warm start.  No host synchronization."""
        if not isinstance(done, Tensor) or done.dtype != torch.bool:
            raise TypeError("MPCState.reset: argument 'done' must be a bool tensor of the batch shape "
                            f"{tuple(self.batch_shape)}")
        if done.shape != self.batch_shape:
            raise ValueError(f"MPCState.reset: argument 'done' has shape {tuple(done.shape)}, expected the "
                             f"batch shape {tuple(self.batch_shape)}")
        done = done.to(self.u.device)
        zero = torch.zeros((), dtype=self.u.dtype, device=self.u.device)
        return MPCState(u=torch.where(done[..., None, None], zero, self.u),
                        converged=self.converged & ~done,
                        iterations=torch.where(done, 0, self.iterations))


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


def run_mpc(system: System, cost: Cost, x0: Tensor, horizon: int, steps: int, *,
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


class MPCPolicy(nn.Module):
    """A differentiable MPC policy: observation ``(*B, n)`` → action ``(*B, m)``.

    ``forward(obs, state)`` builds the cost ``cost(obs)``, solves the control-limited problem from ``obs``
    warm-started by ``state`` and returns ``(action, next_state)``: the warm start is passed in and
    returned, never stored on the module.

    Args:
        system: a :class:`~controllers.dynamics.System` (e.g. a model from :mod:`controllers.systems`);
            its tensor fields that are ``nn.Parameter``s are registered.
        horizon: planning horizon ``T``.
        cost: an ``nn.Module`` with ``forward(obs (*B, n)) -> Cost`` over ``T`` steps, e.g.
            :class:`~controllers.costs.DiagonalQuadraticCost`; its parameters are the policy's.
        u_lower, u_upper: control limits (floats, or tensors of shape ``()``, ``(m,)`` or ``(T, m)`` per step:
            buffers of the module).
        grad: gradient mode of the solver (implicit by default).
        options: :class:`~controllers.ilqr.ILQROptions`.
    """

    def __init__(self, system: System, horizon: int, cost: nn.Module, *, u_lower=None, u_upper=None,
                 grad: GradMode | str = GradMode.IMPLICIT, options: ILQROptions | None = None):
        super().__init__()
        if not isinstance(cost, nn.Module):
            raise TypeError(f"MPCPolicy: argument 'cost' must be an nn.Module mapping the observation to a "
                            f"cost (e.g. controllers.costs.DiagonalQuadraticCost), got {type(cost).__name__}")
        if not isinstance(horizon, int) or isinstance(horizon, bool) or horizon < 1:
            raise ValueError(f"MPCPolicy: argument 'horizon' must be a positive int, got {horizon!r}")
        self.system = system
        self.horizon = horizon
        self.cost = cost
        self.grad = enum_arg(GradMode, grad, "grad", "MPCPolicy")
        self.options = options
        for name, v in (("u_lower", u_lower), ("u_upper", u_upper)):
            if isinstance(v, Tensor):
                if not v.dtype.is_floating_point:
                    raise TypeError(f"MPCPolicy: argument '{name}' must be a float or a floating tensor")
                m = int(system.m)
                if v.dim() > 2 or (v.dim() >= 1 and v.shape[-1] not in (1, m)) or (
                        v.dim() == 2 and v.shape[0] not in (1, horizon)):
                    raise ValueError(f"MPCPolicy: argument '{name}' must be a float or a tensor of shape (), "
                                     f"({m},) or ({horizon}, {m}) (per step), got {tuple(v.shape)}")
                self.register_buffer(name, v.detach().clone())  # moves with .to()
            elif v is None or isinstance(v, (int, float)):
                setattr(self, name, None if v is None else float(v))  # a float takes the problem's dtype
            else:
                raise TypeError(f"MPCPolicy: argument '{name}' must be None, a float or a floating tensor, "
                                f"got {type(v).__name__}")
        if is_dataclass(system):
            for f in fields(system):
                v = getattr(system, f.name)
                if isinstance(v, nn.Parameter):
                    self.register_parameter(f"system_{f.name}", v)

    def _dtype_device(self) -> tuple[torch.dtype, torch.device] | None:
        """The dtype and device of the module's floating tensors; None when it has none (a policy with a
        parameter-free cost and float limits then follows its observations)."""
        for t in (*self.parameters(), *self.buffers()):
            if t.dtype.is_floating_point:
                return t.dtype, t.device
        return None

    def initial_state(self, batch_shape: int | tuple[int, ...] | torch.Size, *,
                      dtype: torch.dtype | None = None,
                      device: torch.device | str | None = None) -> MPCState:
        """A cold start (zero controls) for a batch of environments, in the module's dtype and device
        (for a module without tensors: ``dtype``/``device``, default torch's default dtype on CPU)."""
        own = self._dtype_device()
        if own is not None:
            if dtype is not None and dtype != own[0]:
                raise TypeError(f"MPCPolicy.initial_state: argument 'dtype' is {dtype} but the policy is "
                                f"{own[0]}")
            dtype, device = own[0], own[1] if device is None else device
        return MPCState.cold(batch_shape, self.horizon, self.system.m,
                             dtype=torch.get_default_dtype() if dtype is None else dtype, device=device)

    def forward(self, obs: Tensor, state: MPCState | None = None) -> tuple[Tensor, MPCState]:
        """``(action (*B, m), next_state)`` for observations ``obs (*B, n)``."""
        n = self.system.n
        if not isinstance(obs, Tensor) or obs.dim() < 1 or obs.shape[-1] != n:
            raise ValueError(f"MPCPolicy: obs must have shape (*B, {n}), got "
                             f"{tuple(obs.shape) if isinstance(obs, Tensor) else type(obs).__name__}")
        own = self._dtype_device()
        if own is not None and obs.dtype != own[0]:
            raise TypeError(f"MPCPolicy: obs has dtype {obs.dtype} but the policy is {own[0]}; "
                            "use policy.to(dtype) or cast the observation")
        if state is not None and state.u.dtype != obs.dtype:
            raise TypeError(f"MPCPolicy: the warm start has dtype {state.u.dtype} but obs is {obs.dtype}; "
                            "make it with policy.initial_state(..., dtype=obs.dtype)")
        cost = self.cost(obs)
        if not callable(getattr(cost, "evaluate", None)):
            raise TypeError(f"MPCPolicy: the cost module must return a cost with evaluate(x, u) "
                            f"(controllers.costs.Cost), got {type(cost).__name__}")
        prob = ILQRProblem(self.system, cost, obs, self.horizon, u_lower=self.u_lower, u_upper=self.u_upper)
        action, nxt, _ = mpc_step(prob, state, grad=self.grad, options=self.options)
        return action, nxt

    def extra_repr(self) -> str:
        return f"system={type(self.system).__name__}, horizon={self.horizon}, grad={self.grad.value}"
