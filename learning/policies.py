"""One interface for every kind of policy that :func:`learning.evaluate.evaluate` runs.

A :class:`Policy` maps a batch of observations ``(N, obs_dim)`` to *normalized* actions ``(N, m)`` (the
env's action space ``[-1, 1]^m``; the env clips outside it) in one call, with no loop over the batch:

* ``act(obs)``: the actions, a tensor of the observation's dtype and device;
* ``reset(done=None)``: forget whatever the policy carries from step to step (a warm start, a recurrent
  state) for the elements where the bool mask ``done (N,)`` is True — their episode ended — or for all
  of them, batch size included, with ``None``;
* ``info()``: per-element statistics of the last ``act`` call, or ``None``: ``{"iterations": (N,) int64,
  "converged": (N,) bool}`` for solver-based policies.

:func:`as_policy` wraps what a user has:

* an object with ``act`` and ``reset``: itself (already a :class:`Policy`);
* a :class:`controllers.mpc.MPCPolicy`: :class:`MPCAdapter` (observation → state → MPC → ``u / u_max``);
* an object with ``predict`` (a stable-baselines3 model): :class:`SB3Adapter`;
* a ``torch.nn.Module``: :class:`ModuleAdapter` (``module(obs)`` under ``no_grad``);
* any other callable: :class:`CallableAdapter` (``fn(obs)``);
* ``"mpc"``: the task's expert (:func:`task_expert`).

The MPC expert (:class:`MPCExpert`) solves the task with iLQR MPC on the task's own model and cost
(``task.system``, ``task.mpc_cost``) under the limits ``±u_max``, warm-started from step to step; a task
whose MPC is something else (the quadrotor's error-state MPC on R³×R³×SO(3)) gives its own through
:meth:`learning.envs.task.Task.expert`.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import Tensor, nn

from learning.envs.single import as_action, make_task
from learning.envs.task import Task

__all__ = ["Policy", "MPCAdapter", "angle_dims", "DEFAULT_HORIZON", "MPCExpert", "task_expert", "SB3Adapter",
           "ModuleAdapter", "CallableAdapter", "as_policy"]


class Policy:
    """Base class of the adapters (module docstring); any object with ``act`` and ``reset`` (and
    optionally ``info``) is accepted in its place."""

    def act(self, obs: Tensor) -> Tensor:
        raise NotImplementedError

    def reset(self, done: Tensor | None = None) -> None:
        """Forget the carried state where ``done`` (all of it, batch size included, for ``None``)."""

    def info(self) -> dict[str, Tensor] | None:
        """Per-element statistics of the last :meth:`act` (``iterations``, ``converged``), or ``None``."""
        return None


def _like(a: Any, obs: Tensor) -> Tensor:
    """``a`` (tensor, array, list) as a tensor in the dtype and on the device of ``obs``
    (:func:`learning.envs.single.as_action`: real numbers only, clipped before the cast)."""
    return as_action(a, obs.dtype, "the policy's action", obs.device)


def _batched(a: Tensor, N: int, m: int | None) -> Tensor:
    """Bring an ``(N,)`` action of a one-control task to ``(N, 1)``; other shapes are left for the caller
    to check."""
    if m == 1 and a.shape == (N,):
        return a.reshape(N, 1)
    return a


class _FixedCost(nn.Module):
    """The same :class:`~controllers.costs.QuadraticCost` for every observation (a cost module for
    :class:`~controllers.mpc.MPCPolicy`), rebuilt for each dtype it is asked for."""

    def __init__(self, task: Task, horizon: int):
        super().__init__()
        self.task, self.horizon = task, horizon
        self._costs: dict[tuple[torch.dtype, torch.device], Any] = {}

    def forward(self, obs: Tensor):
        key = (obs.dtype, obs.device)
        if key not in self._costs:
            self._costs[key] = self.task.mpc_cost(self.horizon, dtype=obs.dtype, device=obs.device)
        return self._costs[key]


def angle_dims(task: Task) -> list[int]:
    """The state components that are angles: those whose shift by ``2π`` leaves the observation
    unchanged (checked on a few initial states of the task)."""
    u = torch.linspace(0.1, 0.9, 5, dtype=torch.float64)[:, None].expand(5, task.n_noise)
    x = task.initial_state(u)
    o = task.observe(x)
    dims = []
    for i in range(task.n):
        shifted = x.clone()
        shifted[:, i] += 2 * math.pi
        if torch.allclose(task.observe(shifted), o, rtol=0, atol=1e-9):
            dims.append(i)
    return dims


class MPCAdapter(Policy):
    """A :class:`controllers.mpc.MPCPolicy` as a :class:`Policy` on a task.

    The observation is mapped to the state the MPC plans from by ``task.state_from_obs``.  With ``center``
    (for a tracking cost, its target) the angle components of that state (:func:`angle_dims`) are then
    taken on a branch chosen per element with hysteresis: the angle continues the previous step's (no jump
    of 2π as the pendulum crosses upright, where ``state_from_obs`` cuts at ±π) as long as it stays within
    ``π + hysteresis`` of the center, else it is taken in ``[c − π, c + π)``.  Without the hysteresis the
    branch would flip back and forth for a pendulum hanging at the cut opposite the target, and the MPC
    would push it one way and then the other.  The MPC's physical control ``u``
    becomes the normalized action ``u / u_max``, clipped to the task's one-step safety box
    (:meth:`~learning.envs.task.Task.safe_action_box`) where it has one.  The warm start
    (:class:`~controllers.mpc.MPCState`) is kept here, one per batch element, and cold-started per element
    by :meth:`reset` (``MPCState.reset``).  :meth:`info` gives the iterations and the certified
    convergence (``status.converged``: KKT residual checked below tolerance) of each element's last solve.

    Args:
        mpc: the policy; it is run under ``torch.no_grad``.
        task: a :class:`Task` (or its name).
        follow_dtype: convert ``mpc`` to the observation's dtype (and device) when they differ (the
            module is changed in place); otherwise the state is cast to the module's dtype and the action
            cast back.
        center: ``(n,)`` state around which angles are taken (only its angle components matter); ``None``
            keeps ``task.state_from_obs`` as it is.
        hysteresis: see above (radians).
    """

    def __init__(self, mpc: nn.Module, task: Task | str, *, follow_dtype: bool = False,
                 center: Tensor | None = None, hysteresis: float = math.pi / 2):
        self.mpc, self.task, self.follow_dtype = mpc, make_task(task), follow_dtype
        self._wrap = None
        if center is not None:
            center = torch.as_tensor(center, dtype=torch.float64).reshape(-1, self.task.n)[-1]
            mask = torch.zeros(self.task.n, dtype=torch.bool)
            mask[angle_dims(self.task)] = True
            if bool(mask.any()):
                self._wrap = (mask, torch.where(mask, center, 0.0))
        self.hysteresis = float(hysteresis)
        self._prev: Tensor | None = None  # the last state planned from (angles on their chosen branch)
        self._state = None
        self._info: dict[str, Tensor] | None = None
        self._scale: Tensor | None = None

    def _module_dtype(self) -> tuple[torch.dtype, torch.device]:
        return self.mpc._dtype_device()

    @torch.no_grad()
    def act(self, obs: Tensor) -> Tensor:
        x = self.task.state_from_obs(obs)
        if self._wrap is not None:
            x = self._branch(x)
        dtype, device = self._module_dtype()
        if (dtype, device) != (x.dtype, x.device):
            if self.follow_dtype:
                self.mpc.to(device=x.device, dtype=x.dtype)
                self._state = None
                dtype, device = x.dtype, x.device
            else:
                x = x.to(device=device, dtype=dtype)
        if self._state is not None and self._state.batch_shape != x.shape[:-1]:
            self._state = None
        if self._state is None:
            self._state = self.mpc.initial_state(x.shape[:-1])
        u, self._state = self.mpc(x, self._state)
        self._info = {"iterations": self._state.iterations.to(obs.device),
                      "converged": self._state.converged.to(obs.device)}
        if self._scale is None or self._scale.dtype != obs.dtype or self._scale.device != obs.device:
            self._scale = self.task.u_scale(obs.dtype, obs.device)
        a = u.detach().to(device=obs.device, dtype=obs.dtype) / self._scale
        box = self.task.safe_action_box(self.task.state_from_obs(obs))
        return a if box is None else torch.minimum(torch.maximum(a, box[0]), box[1])

    def _branch(self, x: Tensor) -> Tensor:
        mask, c = (v.to(device=x.device) for v in self._wrap)
        c = c.to(x.dtype)
        two_pi = 2 * math.pi
        centered = torch.remainder(x - c + math.pi, two_pi) - math.pi + c
        prev = self._prev
        if prev is not None and prev.shape == x.shape and prev.dtype == x.dtype:
            cont = prev + torch.remainder(x - prev + math.pi, two_pi) - math.pi
            keep = torch.isfinite(prev) & ((cont - c).abs() <= math.pi + self.hysteresis)
            centered = torch.where(keep, cont, centered)
        x = torch.where(mask, centered, x)
        self._prev = x
        return x

    def reset(self, done: Tensor | None = None) -> None:
        if self._prev is not None:
            if done is None or done.shape != self._prev.shape[:-1]:
                self._prev = None
            else:
                self._prev = torch.where(done.to(self._prev.device)[:, None], math.nan, self._prev)
        if done is None or self._state is None:
            self._state = None
        elif done.shape == self._state.batch_shape:
            self._state = self._state.reset(done)
        else:
            self._state = None
        self._info = None

    def info(self) -> dict[str, Tensor] | None:
        return self._info


#: planning horizons of :class:`MPCExpert` by task name
DEFAULT_HORIZON = {"PendulumSwingUp": 40, "CartPoleSwingUp": 30, "CarParking": 40, "BicopterHover": 20,
                   "ArmReach": 25}


class MPCExpert(MPCAdapter):
    """The MPC that solves a task: iLQR MPC on ``task.system`` with ``task.mpc_cost(horizon)`` and the
    control limits ``±u_max``, warm-started from step to step (see :class:`MPCAdapter`).

    It follows the observation's dtype (a float64 observation is solved in float64).

    Angles are taken around the cost's target ``x_ref`` when it has one (``center`` of
    :class:`MPCAdapter`); ``wrap_angles=False`` plans from ``task.state_from_obs`` as it is.

    Args:
        task: a :class:`Task` or its name.
        horizon: planning horizon (steps); default per task (:data:`DEFAULT_HORIZON`, else 30).
        max_iter: iLQR iterations at most per control step.
        options: a full :class:`~controllers.ilqr.ILQROptions` (overrides ``max_iter``).
        method: ``"recursive"`` or ``"batch"`` iLQR.
    """

    def __init__(self, task: Task | str = "PendulumSwingUp", horizon: int | None = None, max_iter: int = 20,
                 *, options=None, method: str = "recursive", wrap_angles: bool = True):
        from controllers.ilqr import ILQROptions
        from controllers.mpc import MPCPolicy

        task = make_task(task)
        if horizon is None:
            horizon = DEFAULT_HORIZON.get(task.name, 30)
        if options is None:
            options = ILQROptions(max_iter=max_iter)
        umax = torch.tensor(task.u_max(), dtype=torch.float64)
        mpc = MPCPolicy(task.system, horizon, _FixedCost(task, horizon), u_lower=-umax, u_upper=umax,
                        grad="none", options=options)
        if method != "recursive":
            mpc = _MethodMPC(mpc, method)
        center = getattr(task.mpc_cost(horizon), "x_ref", None) if wrap_angles else None
        super().__init__(mpc, task, follow_dtype=True, center=center)
        self.horizon, self.options, self.method = horizon, options, method


class _MethodMPC(nn.Module):
    """An :class:`~controllers.mpc.MPCPolicy` run with another iLQR method (MPCPolicy always uses the
    recursive one)."""

    def __init__(self, mpc: nn.Module, method: str):
        super().__init__()
        self.inner, self.method = mpc, method

    def _dtype_device(self):
        return self.inner._dtype_device()

    def initial_state(self, batch_shape):
        return self.inner.initial_state(batch_shape)

    def forward(self, x: Tensor, state):
        from controllers.ilqr import ILQRProblem
        from controllers.mpc import mpc_step

        p = self.inner
        prob = ILQRProblem(p.system, p.cost(x), x, p.horizon, u_lower=p.u_lower, u_upper=p.u_upper)
        u, nxt, _ = mpc_step(prob, state, method=self.method, grad="none", options=p.options)
        return u, nxt


def task_expert(task: Task | str, horizon: int | None = None, **kwargs) -> Policy:
    """The MPC that solves ``task``: its own (:meth:`~learning.envs.task.Task.expert`) where it has one, else
    the iLQR :class:`MPCExpert`.  The result has a ``horizon`` attribute."""
    t = make_task(task)
    own = t.expert(horizon, **kwargs)
    return own if own is not None else MPCExpert(t, horizon, **kwargs)


class SB3Adapter(Policy):
    """A stable-baselines3 model (anything with ``predict(obs: ndarray, deterministic=True)`` returning
    ``(actions, state)`` or the actions alone); the observation goes to numpy and back."""

    def __init__(self, model: Any, m: int | None = None, *, deterministic: bool = True):
        self.model, self.m, self.deterministic = model, m, deterministic

    def act(self, obs: Tensor) -> Tensor:
        out = self.model.predict(obs.detach().cpu().numpy(), deterministic=self.deterministic)
        a = out[0] if isinstance(out, tuple) else out
        return _batched(_like(a, obs), obs.shape[0], self.m)


class ModuleAdapter(Policy):
    """A ``torch.nn.Module`` ``obs (N, obs_dim) -> action (N, m)`` run under ``no_grad``.  The observation
    is cast to the module's dtype and device (those of its first parameter or buffer) and the action back
    to the observation's; a tuple output gives its first element."""

    def __init__(self, module: nn.Module, m: int | None = None):
        self.module, self.m = module, m

    @torch.no_grad()
    def act(self, obs: Tensor) -> Tensor:
        t = next(iter(self.module.parameters()), None)
        if t is None:
            t = next(iter(self.module.buffers()), None)
        x = obs if t is None else obs.to(device=t.device, dtype=t.dtype)
        a = self.module(x)
        if isinstance(a, tuple):
            a = a[0]
        return _batched(_like(a, obs), obs.shape[0], self.m)


class CallableAdapter(Policy):
    """A plain callable ``fn(obs: Tensor (N, obs_dim)) -> actions`` (a tensor, an array or a list)."""

    def __init__(self, fn, m: int | None = None):
        self.fn, self.m = fn, m

    def act(self, obs: Tensor) -> Tensor:
        return _batched(_like(self.fn(obs), obs), obs.shape[0], self.m)


def as_policy(obj: Any, task: Task | str | None = None) -> Policy:
    """A :class:`Policy` for ``obj`` (table in the module docstring).  ``task`` is needed for an
    :class:`~controllers.mpc.MPCPolicy` and for ``"mpc"``, and lets ``(N,)`` actions of a one-control task
    be read as ``(N, 1)``."""
    from controllers.mpc import MPCPolicy

    t = None if task is None else make_task(task)
    m = None if t is None else t.m
    if callable(getattr(obj, "act", None)) and callable(getattr(obj, "reset", None)):
        return obj
    if isinstance(obj, str):
        if obj.lower() not in ("mpc", "expert", "mpc_expert"):
            raise ValueError(f"as_policy: unknown policy name {obj!r} (known: 'mpc')")
        if t is None:
            raise ValueError("as_policy: the 'mpc' expert needs the task")
        return task_expert(t)
    if isinstance(obj, MPCPolicy):
        if t is None:
            raise ValueError("as_policy: an MPCPolicy needs the task (to map observations to states)")
        return MPCAdapter(obj, t)
    if callable(getattr(obj, "predict", None)):
        return SB3Adapter(obj, m)
    if isinstance(obj, nn.Module):
        return ModuleAdapter(obj, m)
    if callable(obj):
        return CallableAdapter(obj, m)
    raise TypeError(f"as_policy: cannot run {type(obj).__name__} as a policy: expected an object with "
                    "act/reset, an MPCPolicy, an SB3 model (predict), an nn.Module or a callable")
