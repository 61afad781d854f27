"""A task as a single :class:`gymnasium.Env` (numpy at the boundary, the task's torch code inside).

Randomness: ``reset(seed=s)`` seeds ``self.np_random`` through ``super().reset`` and makes ``s`` the
environment's *key*; the initial state of its k-th episode since then is the counter-based draw
:func:`learning._counter_rng.uniforms` of ``(key, k)``.  Without a seed at the first reset the key is
drawn from ``self.np_random``.  This is what makes environment ``i`` of a
:class:`learning.vector.TaskVectorEnv` reset with ``seed=s`` identical, step for step and episode after
episode, to this env reset with ``seed=s + i`` (the conformance tests check it to 1e-12 in float64).

Time limits are gymnasium's: :func:`gymnasium.make` wraps the env in ``TimeLimit`` from the registered
``max_episode_steps``; the env itself truncates only an *invalid* step (a non-finite action or state,
flagged ``info["invalid"] = True``).  The observation bounds are proven for the task's own horizon: for
longer episodes pass ``task_kwargs={"max_episode_steps": K}`` as well as ``max_episode_steps=K`` (a
``TimeLimit`` alone cannot tell the task; :class:`learning.vector.TaskVectorEnv` does this itself).
Actions outside ``[-1, 1]`` are clipped (see :mod:`learning.envs.task`; :func:`as_action` is how every
action enters); complex actions are a ``TypeError``.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import torch

from learning._counter_rng import keys_of_seeds, uniforms
from learning.envs.task import Task

__all__ = ["TaskEnv", "make_task", "as_dtype", "as_action", "as_device", "int_arg"]


def make_task(task: Task | str | type, task_kwargs: dict | None = None) -> Task:
    """A :class:`Task` from an instance, a class, or a registered name (with constructor kwargs)."""
    if isinstance(task, Task):
        if task_kwargs:
            raise ValueError("make_task: 'task_kwargs' given with a Task instance; pass one or the other")
        return task
    if isinstance(task, str):
        from learning.envs import TASKS

        if task not in TASKS:
            raise ValueError(f"make_task: unknown task {task!r}; known: {sorted(TASKS)}")
        task = TASKS[task]
    if isinstance(task, type) and issubclass(task, Task):
        return task(**(task_kwargs or {}))
    raise TypeError(f"make_task: argument 'task' must be a Task, a Task class or a task name, got {task!r}")


def as_dtype(dtype) -> torch.dtype:
    if isinstance(dtype, str):
        dtype = getattr(torch, dtype, None)
    if dtype not in (torch.float32, torch.float64):
        raise ValueError(f"argument 'dtype' must be torch.float32 or torch.float64 (or their names), "
                         f"got {dtype!r}")
    return dtype


def int_arg(value, name: str, owner: str, minimum: int = 1) -> int:
    """``value`` as an int ``>= minimum`` (numpy ints too), else a ``ValueError`` naming the argument — a
    float is refused, not truncated (``2.7`` steps would silently be 2)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ValueError(f"{owner}: argument '{name}' must be an int >= {minimum}, got {value!r}")
    return int(value)


def as_device(device, owner: str) -> torch.device:
    """``torch.device(device)``, checked usable here (a CUDA device on a torch without CUDA, a device index
    that does not exist, or the data-less ``"meta"`` device is a ``ValueError`` naming the argument instead
    of an error deep inside)."""
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError) as e:
        raise ValueError(f"{owner}: argument 'device' must be a torch device, got {device!r} ({e})") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"{owner}: argument 'device' is {str(dev)!r} but this torch has no CUDA "
                         f"(torch {torch.__version__}, torch.cuda.is_available() is False); use 'cpu'")
    if dev.type == "meta":
        raise ValueError(f"{owner}: argument 'device' is 'meta', which holds shapes but no values; a "
                         "simulation needs a device with data ('cpu', 'cuda', ...)")
    try:
        torch.empty(0, device=dev)
    except (RuntimeError, AssertionError) as e:
        raise ValueError(f"{owner}: argument 'device' {str(dev)!r} is not usable here: {e}") from None
    return dev


def as_action(action, dtype: torch.dtype, what: str, device=None) -> torch.Tensor:
    """An action (tensor, array, sequence) as a real tensor of ``dtype`` (on ``device``), the one entry
    path of actions into the envs, the evaluation and the demonstrations.

    A complex or non-numeric action is a ``TypeError`` naming ``what`` (a cast would silently drop the
    imaginary part).  Before the cast, finite values are clipped to ``±2`` *in the action's own dtype*, so
    that a value the target dtype cannot hold (a float64 ``1e39`` for a float32 env) is an out-of-box
    action like any other — clipped to the bound by the env, counted as a violation by
    :func:`learning.evaluate` — and not an ``inf`` that ends the episode as invalid.  NaN and ±inf stay.
    """
    if isinstance(action, torch.Tensor):
        a = action.detach()
        kind = "c" if a.is_complex() else ("f" if a.is_floating_point() else "i")
    else:
        arr = np.asarray(action)
        kind = arr.dtype.kind if arr.dtype.kind in "biufc" else "other"
        if kind == "f" and arr.dtype.itemsize > np.dtype(np.float64).itemsize:  # long double
            arr = np.where(np.isfinite(arr), np.clip(arr, -2.0, 2.0), arr).astype(np.float64)
        a = torch.as_tensor(arr) if kind in "biuf" else None
    if kind not in "biuf":
        raise TypeError(f"{what} must be real numbers, got {getattr(action, 'dtype', type(action).__name__)}"
                        + (" (the imaginary part would be dropped)" if kind == "c" else ""))
    if a.is_floating_point() and a.dtype != dtype:
        a = torch.where(torch.isfinite(a), a.clamp(-2.0, 2.0), a)
    return a.to(device=device, dtype=dtype)


class TaskEnv(gym.Env):
    """One environment of a :class:`Task`.

    Args:
        task: a :class:`Task`, a Task class or a registered task name.
        task_kwargs: constructor arguments when ``task`` is a class or a name.
        dtype: ``torch.float32`` (default) or ``torch.float64``: the dtype of the simulation and of the
            observation space.
        render_mode: ``None`` or ``"rgb_array"``.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 20}

    def __init__(self, task: Task | str | type = "PendulumSwingUp", task_kwargs: dict | None = None, *,
                 dtype=torch.float32, render_mode: str | None = None):
        super().__init__()
        self.task = make_task(task, task_kwargs)
        self.dtype = as_dtype(dtype)
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"TaskEnv: render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.render_mode = render_mode
        np_dtype = np.float32 if self.dtype == torch.float32 else np.float64
        high = self.task.obs_high().astype(np_dtype)
        self.observation_space = gym.spaces.Box(-high, high, dtype=np_dtype)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (self.task.m,), dtype=np_dtype)
        self.metadata = dict(self.metadata, render_fps=int(round(1.0 / float(self.task.system.dt))))
        self._scale = self.task.u_scale(self.dtype, "cpu")
        self._key: torch.Tensor | None = None
        self._episode = -1
        self._x: torch.Tensor | None = None

    @property
    def state(self) -> np.ndarray:
        """The full state ``(n,)`` of the system (a copy)."""
        if self._x is None:
            raise RuntimeError("TaskEnv: call reset() first")
        return self._x[0].numpy().copy()

    @torch.no_grad()
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        if isinstance(seed, (bool, np.bool_)):
            raise ValueError(f"TaskEnv.reset: argument 'seed' must be a non-negative int or None, "
                             f"got {seed!r}")
        super().reset(seed=seed)
        if seed is not None:
            self._key, self._episode = keys_of_seeds(torch.tensor([int(seed) % 2**62])), 0
        elif self._key is None:
            drawn = int(self.np_random.integers(0, 2**62))
            self._key, self._episode = keys_of_seeds(torch.tensor([drawn])), 0
        else:
            self._episode += 1
        noise = uniforms(self._key, torch.tensor([self._episode]), self.task.n_noise, self.dtype)
        self._x = self.task.initial_state(noise)
        return self._obs(), {}

    def _obs(self) -> np.ndarray:
        return self.task.observe(self._x)[0].numpy().astype(self.observation_space.dtype, copy=True)

    @torch.no_grad()
    def step(self, action):
        if self._x is None:
            raise RuntimeError("TaskEnv: call reset() before step()")
        a = as_action(action, self.dtype, "TaskEnv.step: action").reshape(1, -1)
        if a.shape[-1] != self.task.m:
            raise ValueError(f"TaskEnv.step: action must have shape ({self.task.m},), got {np.shape(action)}")
        x1, _, r, term, invalid = self.task.transition(self._x, a, self._scale)
        self._x = x1
        bad = bool(invalid[0])
        info = {"invalid": True} if bad else {}
        return self._obs(), float(r[0]), bool(term[0]), bad, info

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        if self._x is None:
            raise RuntimeError("TaskEnv: call reset() before render()")
        return self.task.frame(self._x[0].double().numpy())
