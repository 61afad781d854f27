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

__all__ = ["ModelMPC", "LinearModelMPC", "model_policy"]


def model_policy(model: EnvModel | Any, horizon: int | None = None) -> Policy:
    """The MPC of a model (or of an id / env with a registered one) by its ``planner``: :class:`ModelMPC`
    (``"ilqr"``) or :class:`~learning.sampling_mpc.SamplingModelMPC` (``"sampling"``), with the model's
    settings (``horizon``: another horizon)."""
    md = env_model(model)
    if md.planner == "ilqr":
        return ModelMPC(md, horizon=horizon)
    if md.planner == "sampling":
        from learning.sampling_mpc import SamplingModelMPC

        return SamplingModelMPC(md, horizon=horizon)
    raise ValueError(f"model_policy: the model of {md.env_id} names planner {md.planner!r}; expected 'ilqr' "
                     "or 'sampling'")


def _int(v, name: str, minimum: int) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or v < minimum:
        raise ValueError(f"ModelMPC: argument '{name}' must be an int >= {minimum}, got {v!r}")
    return v


class ModelMPC(Policy):
    """Multi-start iLQR MPC on an :class:`~learning.env_models.EnvModel` (module docstring).

    Args:
        model: an :class:`EnvModel`, or a gymnasium id / ``Env`` / ``VectorEnv`` with a registered model.
        horizon, max_iter, random_starts: override the model's defaults.
        multistart: ``True``: every step solves from the multi-start set; ``False``: from the previous plan
            only (zero at an episode's start), the plain warm-started MPC; ``"start"``: the multi-start set at
            an episode's first step, the previous plan alone after it (default: the model's ``multistart``).
        seed: of the generator of the random starts.
        options: an :class:`~controllers.ilqr.ILQROptions` (default: the model's; ``max_iter``, where
            given, replaces its ``max_iter``).
        start_iter: iterations of an episode's first solve (default: the larger of ``max_iter`` and the
            model's ``start_iter``).  With a small ``max_iter`` this is the usual real-time scheme: one full
            solve from cold, then a few iterations a step from the shifted plan (a plan that is not
            certified after them says so in :meth:`info`).  Elements of a batch at their first step and the
            others are solved separately, each with its own settings.
        compile: run the solver's sweeps as compiled programs (``ILQROptions.compile``: built once per
            problem structure and cached on disk; the MuJoCo calls stay in Python).
        sampling_start: add the sampling planner's plan (:func:`learning.sampling_mpc.sampling_guess`: MPPI
            from the first guess, the previous plan or zero) to the multi-start set — a derivative-free
            initializer that can cross a local minimum's basin, where the other guesses cannot.
    """

    def __init__(self, model: EnvModel | Any, *, horizon: int | None = None, max_iter: int | None = None,
                 random_starts: int | None = None, multistart: bool | str | None = None, seed: int = 0,
                 options: ILQROptions | None = None, start_iter: int | None = None, compile: bool = False,
                 sampling_start: bool = False):
        self.model = env_model(model)
        md = self.model
        self.horizon = _int(md.horizon if horizon is None else horizon, "horizon", 1)
        rs = md.random_starts if random_starts is None else random_starts
        self.random_starts = _int(rs, "random_starts", 0)
        its = _int(md.max_iter if max_iter is None else max_iter, "max_iter", 1)
        if options is None:
            options = ILQROptions(**{**md.options, "max_iter": its})
        if not isinstance(options, ILQROptions):
            raise TypeError(f"ModelMPC: argument 'options' must be an ILQROptions, got "
                            f"{type(options).__name__}")
        if max_iter is not None:  # given with options too: max_iter wins (not silently dropped)
            options = dataclasses.replace(options, max_iter=its)
        self.options = dataclasses.replace(options, compile=bool(compile or options.compile))
        if start_iter is None:  # the first solve has at least the running budget
            si = max(self.options.max_iter, md.start_iter or 0)
        else:
            si = _int(start_iter, "start_iter", 1)
        self.start_options = dataclasses.replace(self.options, max_iter=si)
        ms = md.multistart if multistart is None else multistart
        if ms not in (True, False, "start"):
            raise ValueError(f"ModelMPC: argument 'multistart' must be True, False or 'start', got {ms!r}")
        self.multistart = ms
        self.seed = int(seed)
        self.sampling_start = bool(sampling_start)
        self._calls = 0
        self._gen: torch.Generator | None = None
        self._plan: Tensor | None = None
        self._fresh: Tensor | None = None  # (N,) bool: elements at an episode's first step (no plan yet)
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

    def _guesses(self, x: Tensor, lo: Tensor, hi: Tensor, prev: Tensor | None, many: bool) -> Tensor:
        """``(N, K, T, m)`` initial guesses: the previous plan (zero without one) alone, or (``many``) the
        multi-start set."""
        N, T = x.shape[0], self.horizon
        if not many:
            return (torch.zeros(N, T, self.model.m, dtype=x.dtype, device=x.device) if prev is None
                    else prev)[:, None]
        if self._gen is None or self._gen.device != x.device:
            self._gen = torch.Generator(device=x.device).manual_seed(self.seed)
        U = guesses((N,), T, lo, hi, previous=prev, random=self.random_starts, generator=self._gen)
        hold = lqr_guess(self.model.system, self._cost_for(x), x, T, lo, hi)
        extra = [] if hold is None else [hold[:, None]]
        if self.sampling_start:
            from learning.sampling_mpc import sampling_guess

            self._calls += 1  # fresh draws every call (element b of call c: seed + c·N + b)
            extra.append(sampling_guess(self.model, x, T, u_init=U[:, 0].contiguous(),
                                        seed=self.seed + self._calls * N)[:, None])
        return torch.cat([U, *extra], 1) if extra else U

    def _solve(self, x: Tensor, prev: Tensor | None, start: bool):
        """The chosen plan's solution for states ``x (N, n)``: an episode's first solve (``start``) with the
        start settings, the others with the running ones."""
        lo, hi = self._limits(x)
        many = self.multistart is True or (self.multistart == "start" and start)
        U = self._guesses(x, lo, hi, prev, many)
        prob = ILQRProblem(self.model.system, self._cost_for(x), x, self.horizon, u_lower=lo, u_upper=hi)
        opts = self.start_options if start else self.options
        return ilqr_multistart(prob, U, grad="none", options=opts).best

    @torch.no_grad()
    def act(self, obs: Tensor) -> Tensor:
        if not isinstance(obs, Tensor) or obs.dim() != 2 or not obs.is_floating_point():
            got = f"{tuple(obs.shape)} {obs.dtype}" if isinstance(obs, Tensor) else type(obs).__name__
            raise ValueError(f"ModelMPC.act: argument 'obs' must be a floating tensor (N, obs_dim), got "
                             f"{got}")
        k = self.model.obs_dim
        if k is not None and obs.shape[1] != k:
            raise ValueError(f"ModelMPC.act: argument 'obs' must have shape (N, {k}) (the observations of "
                             f"{self.model.env_id}), got {tuple(obs.shape)}")
        x = self.model.state_from_obs(obs)
        N = x.shape[0]
        prev, fresh = self._plan, self._fresh
        if prev is None or prev.shape[0] != N or prev.dtype != x.dtype or fresh is None:
            prev, fresh = None, torch.ones(N, dtype=torch.bool)
        split = self.start_options != self.options or self.multistart == "start"
        if not split or bool(fresh.all()) or not bool(fresh.any()):
            sols = [(None, self._solve(x, prev, bool(fresh.all())))]
        else:  # some elements start an episode: two solves, each with its own settings
            idx = [torch.nonzero(f).squeeze(-1).to(x.device) for f in (fresh, ~fresh)]
            sols = [(i, self._solve(x[i], prev[i], start)) for i, start in zip(idx, (True, False))]
        kw = dict(dtype=x.dtype, device=x.device)
        u = torch.zeros(N, self.horizon, self.model.m, **kw)
        its = torch.zeros(N, dtype=torch.int64, device=x.device)
        conv = torch.zeros(N, dtype=torch.bool, device=x.device)
        cost = torch.zeros(N, **kw)
        for i, sol in sols:
            sel = slice(None) if i is None else i
            u[sel], its[sel], conv[sel], cost[sel] = (sol.u, sol.status.iterations, sol.status.converged,
                                                      sol.cost)
        self._plan = shift(torch.where(torch.isfinite(u), u, torch.zeros((), **kw)))
        self._fresh = torch.zeros(N, dtype=torch.bool)
        self._info = {"iterations": its, "converged": conv}
        self.last_cost = float(cost[0]) if N == 1 else cost
        return u[:, 0].to(dtype=obs.dtype)

    def reset(self, done: Tensor | None = None) -> None:
        if done is not None and (not isinstance(done, Tensor) or done.dtype != torch.bool or done.dim() != 1):
            raise TypeError("ModelMPC.reset: argument 'done' must be None or a bool tensor (N,)")
        if done is None or self._plan is None or done.shape != self._plan.shape[:1]:
            self._plan, self._fresh = None, None  # all, or a batch of another size: every plan starts afresh
        else:
            d = done.cpu()
            self._plan = torch.where(d.to(self._plan.device)[:, None, None], 0.0, self._plan)
            self._fresh = d | (self._fresh if self._fresh is not None else d)
        self._info = None

    def info(self) -> dict[str, Tensor] | None:
        return self._info

    def replace(self, **changes: Any) -> ModelMPC:
        """A new policy on ``dataclasses.replace(model, **changes)`` with this one's settings."""
        md = dataclasses.replace(self.model, **changes)
        return ModelMPC(md, horizon=self.horizon, random_starts=self.random_starts,
                        multistart=self.multistart, seed=self.seed, options=self.options,
                        start_iter=self.start_options.max_iter, sampling_start=self.sampling_start)

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
