"""The MPC policy of a gymnasium environment the project did not write: :class:`ModelMPC`.

At every step the observation is mapped to the model's state (:class:`learning.env_models.EnvModel`) and
the control-limited problem over the horizon is solved by :func:`controllers.multistart.ilqr_multistart`
from several initial guesses at once — the previous plan shifted, zero controls, each limit held,
``random_starts`` smooth random sequences (:func:`controllers.multistart.guesses`) and the closed-loop
"hold" guess (:func:`controllers.multistart.lqr_guess`, when the cost is quadratic about a fixed target)
— keeping the best certified plan.  Its first control is the action, in the env's units; the plan,
shifted, is the next step's first guess.  So an episode never starts from one guess only: a start near
the goal is not planned as a full swing because zero controls happened to lead there.

:meth:`ModelMPC.info` gives the iterations and the certificate (``converged``: the KKT residual checked at
the returned point) of each element's chosen plan; :func:`learning.evaluate` counts them.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import torch
from torch import Tensor

from controllers.ilqr import ILQROptions, ILQRProblem
from controllers.mpc import shift
from controllers.multistart import guesses, ilqr_multistart, lqr_guess
from learning.env_models import EnvModel, env_model
from learning.policies import Policy

__all__ = ["ModelMPC", "LinearModelMPC"]


def _int(v, name: str, minimum: int) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or v < minimum:
        raise ValueError(f"ModelMPC: argument '{name}' must be an int >= {minimum}, got {v!r}")
    return v


class ModelMPC(Policy):
    """Multi-start iLQR MPC on an :class:`~learning.env_models.EnvModel` (module docstring).

    Args:
        model: an :class:`EnvModel`, or a gymnasium id / ``Env`` / ``VectorEnv`` with a registered model.
        horizon, max_iter, random_starts: override the model's defaults.
        multistart: ``False`` solves from the previous plan only (zero at an episode's start): the plain
            warm-started MPC (default: the model's ``multistart``).
        seed: of the generator of the random starts.
        options: an :class:`~controllers.ilqr.ILQROptions` (default: the model's, ``max_iter`` set).
    """

    def __init__(self, model: EnvModel | Any, *, horizon: int | None = None, max_iter: int | None = None,
                 random_starts: int | None = None, multistart: bool | None = None, seed: int = 0,
                 options: ILQROptions | None = None):
        self.model = env_model(model)
        md = self.model
        self.horizon = _int(md.horizon if horizon is None else horizon, "horizon", 1)
        rs = md.random_starts if random_starts is None else random_starts
        self.random_starts = _int(rs, "random_starts", 0)
        its = int(md.max_iter if max_iter is None else max_iter)
        self.options = options if options is not None else ILQROptions(**{**md.options, "max_iter": its})
        self.multistart = bool(md.multistart if multistart is None else multistart)
        self.seed = int(seed)
        self._gen: torch.Generator | None = None
        self._plan: Tensor | None = None
        self._info: dict[str, Tensor] | None = None
        self._cost: dict[tuple, Any] = {}
        #: the chosen plans' costs of the last act (a float at batch 1)
        self.last_cost: float | Tensor | None = None

    def _limits(self, x: Tensor) -> tuple[Tensor, Tensor]:
        kw = dict(dtype=x.dtype, device=x.device)
        return torch.tensor(self.model.action_low, **kw), torch.tensor(self.model.action_high, **kw)

    def _cost_for(self, x: Tensor):
        key = (x.dtype, x.device)
        if key not in self._cost:  # one cost object per dtype/device, built from the model's factory
            self._cost[key] = self.model.cost(self.horizon, dtype=x.dtype, device=x.device)
        return self._cost[key]

    def _guesses(self, x: Tensor, lo: Tensor, hi: Tensor) -> Tensor:
        N, T = x.shape[0], self.horizon
        prev = self._plan
        if prev is not None and (prev.shape[0] != N or prev.dtype != x.dtype):
            prev = None
        if not self.multistart:
            return (torch.zeros(N, T, self.model.m, dtype=x.dtype, device=x.device) if prev is None
                    else prev)[:, None]
        if self._gen is None or self._gen.device != x.device:
            self._gen = torch.Generator(device=x.device).manual_seed(self.seed)
        U = guesses((N,), T, lo, hi, previous=prev, random=self.random_starts, generator=self._gen)
        hold = lqr_guess(self.model.system, self._cost_for(x), x, T, lo, hi)
        return U if hold is None else torch.cat([U, hold[:, None]], 1)

    @torch.no_grad()
    def act(self, obs: Tensor) -> Tensor:
        if not isinstance(obs, Tensor) or obs.dim() != 2 or not obs.is_floating_point():
            got = f"{tuple(obs.shape)} {obs.dtype}" if isinstance(obs, Tensor) else type(obs).__name__
            raise ValueError(f"ModelMPC.act: argument 'obs' must be a floating tensor (N, obs_dim), got "
                             f"{got}")
        x = self.model.state_from_obs(obs)
        lo, hi = self._limits(x)
        U = self._guesses(x, lo, hi)
        prob = ILQRProblem(self.model.system, self._cost_for(x), x, self.horizon, u_lower=lo, u_upper=hi)
        sol = ilqr_multistart(prob, U, grad="none", options=self.options).best
        u = torch.where(torch.isfinite(sol.u), sol.u, torch.zeros((), dtype=x.dtype, device=x.device))
        self._plan = shift(u)
        self._info = {"iterations": sol.status.iterations, "converged": sol.status.converged}
        self.last_cost = float(sol.cost[0]) if sol.cost.shape[0] == 1 else sol.cost
        return sol.u[:, 0].to(dtype=obs.dtype)

    def reset(self, done: Tensor | None = None) -> None:
        if done is not None and (not isinstance(done, Tensor) or done.dtype != torch.bool or done.dim() != 1):
            raise TypeError("ModelMPC.reset: argument 'done' must be None or a bool tensor (N,)")
        if done is None or self._plan is None or done.shape != self._plan.shape[:1]:
            self._plan = None  # all, or a batch of another size: every plan starts afresh
        else:
            self._plan = torch.where(done.to(self._plan.device)[:, None, None], 0.0, self._plan)
        self._info = None

    def info(self) -> dict[str, Tensor] | None:
        return self._info

    def replace(self, **changes: Any) -> ModelMPC:
        """A new policy on ``dataclasses.replace(model, **changes)`` with this one's settings."""
        md = dataclasses.replace(self.model, **changes)
        return ModelMPC(md, horizon=self.horizon, random_starts=self.random_starts,
                        multistart=self.multistart, seed=self.seed, options=self.options)

    def __repr__(self) -> str:
        return (f"ModelMPC({self.model.env_id}, horizon={self.horizon}, random_starts={self.random_starts}, "
                f"multistart={self.multistart})")



class LinearModelMPC(Policy):
    """Linear MPC on an :class:`~learning.env_models.EnvModel` (:mod:`controllers.linear_mpc`): each step the
    model is linearized once at the current state and the last action (one batched ``jacobian`` call — on a
    MuJoCo model one rollout call for all environments), the horizon's LQ problem is solved by one backward
    Riccati recursion, and its first control, clipped to the action box, is the action.  No iterations, so
    no certificate: :meth:`info` reports none.  For balancing tasks near a trim point (InvertedPendulum)
    this is the MPC at the cost of a handful of model steps; away from one, use :class:`ModelMPC`.

    The model's cost must be quadratic about a fixed target (a ``QuadraticCost`` or a periodic one), else
    a ``ValueError``.
    """

    def __init__(self, model: EnvModel | Any, *, horizon: int | None = None):
        from controllers.multistart import quadratic_parts

        self.model = env_model(model)
        self.horizon = _int(self.model.horizon if horizon is None else horizon, "horizon", 1)
        parts = quadratic_parts(self.model.cost(self.horizon, dtype=torch.float64))
        if parts is None:
            raise ValueError(f"LinearModelMPC: the cost of {self.model.env_id} is not quadratic about a "
                             "fixed target; use ModelMPC")
        self._parts = parts
        self._u: Tensor | None = None

    def act(self, obs: Tensor) -> Tensor:
        from controllers.linear_mpc import linear_mpc_action

        x = self.model.state_from_obs(obs)
        Q, R, xr, ur, wrap = (v.to(device=x.device, dtype=x.dtype) if isinstance(v, Tensor) else v
                              for v in self._parts)
        if wrap is not None:
            x = wrap(x)
        N, m = x.shape[0], self.model.m
        if self._u is None or self._u.shape[0] != N or self._u.dtype != x.dtype:
            self._u = ur.expand(N, m).clone()
        kw = dict(dtype=x.dtype, device=x.device)
        lo, hi = torch.tensor(self.model.action_low, **kw), torch.tensor(self.model.action_high, **kw)
        with torch.no_grad():
            u = linear_mpc_action(self.model.system, x, self._u, Q, R, xr, ur, self.horizon, lo, hi)
        self._u = torch.where(torch.isfinite(u), u, ur.expand(N, m))
        return u.to(obs.dtype)

    def reset(self, done: Tensor | None = None) -> None:
        if done is None or self._u is None or done.shape != self._u.shape[:1]:
            self._u = None
        else:
            self._u = torch.where(done.to(self._u.device)[:, None], 0.0, self._u)

    def info(self) -> None:
        return None
