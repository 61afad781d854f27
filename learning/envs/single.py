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
Actions outside ``[-1, 1]`` are clipped (see :mod:`learning.envs.task`).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import torch

from learning._counter_rng import keys_of_seeds, uniforms
from learning.envs.task import Task

__all__ = ["TaskEnv", "make_task", "as_dtype"]


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
        a = np.asarray(action, dtype=np.float64)
        a = torch.as_tensor(np.where(np.isfinite(a), np.clip(a, -2.0, 2.0), a))  # a cast cannot make an inf
        a = a.to(self.dtype).reshape(1, -1)
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
