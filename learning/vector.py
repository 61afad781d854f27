"""A task as a natively batched :class:`gymnasium.vector.VectorEnv`: N environments in one tensor.

:class:`TaskVectorEnv` steps every environment with one call of the task's torch code on CPU or CUDA — no
Python loop over environments anywhere (not in step, not in autoreset, not in seeding).

* **Outputs**: numpy arrays by default (what stock gymnasium/SB3 wrappers expect), torch tensors on the
  env's device with ``output="torch"``.  Every call returns fresh buffers.  Rewards have the env's dtype.
* **Truncation** is enforced by the env itself after ``max_episode_steps`` (``make_vec`` passes the
  registered value); an *invalid* step (non-finite action or state) truncates too, flagged in
  ``infos["invalid"]`` with the mask ``infos["_invalid"]``.  Actions outside ``[-1, 1]`` are clipped.
* **Autoreset** (:class:`gymnasium.vector.AutoresetMode`, fixed at construction, in
  ``metadata["autoreset_mode"]``), with the semantics of gymnasium's ``SyncVectorEnv``:

  - ``NEXT_STEP`` (default): the step that ends an episode returns its last observation; the next step
    ignores that environment's action and returns the first observation of a new episode with reward 0
    and both flags False.
  - ``SAME_STEP``: the step that ends an episode returns the first observation of the next one, the last
    observation of the ended one in ``infos["final_obs"]`` (an ``(N, obs_dim)`` array, rows valid where
    ``infos["_final_obs"]``; not an object array) and its step infos in ``infos["final_info"]``.
  - ``DISABLED``: nothing resets by itself; stepping an environment whose episode ended raises an error
    until ``reset(options={"reset_mask": mask})`` resets it (the other environments keep running).
* **Seeding**: ``reset(seed=s)`` gives environment ``i`` the seed ``s + i`` (as ``SyncVectorEnv``);
  ``seed`` may also be a list of ints/None.  Environment ``i`` is then identical, step for step and
  across autoresets, to ``TaskEnv`` reset with ``seed=s + i`` (see :mod:`learning.envs.single`).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode
from gymnasium.vector.utils import batch_space

from learning._counter_rng import keys_of_seeds, uniforms
from learning.envs.single import as_dtype, make_task
from learning.envs.task import Task

__all__ = ["TaskVectorEnv", "as_autoreset_mode"]


def as_autoreset_mode(mode) -> AutoresetMode:
    """An :class:`AutoresetMode` from the enum, its value (``"NextStep"``) or its name (``"next_step"``)."""
    if isinstance(mode, AutoresetMode):
        return mode
    if isinstance(mode, str):
        for m in AutoresetMode:
            if mode in (m.value, m.name, m.name.lower()):
                return m
    raise ValueError(f"argument 'autoreset_mode' must be an AutoresetMode or one of "
                     f"{[m.name.lower() for m in AutoresetMode]}, got {mode!r}")


class TaskVectorEnv(gym.vector.VectorEnv):
    """``num_envs`` environments of a :class:`Task` stepped as one batch (module docstring).

    Args:
        task: a :class:`Task`, a Task class or a registered task name; ``task_kwargs`` its arguments.
        num_envs: number of environments N.
        max_episode_steps: truncation horizon (default: the task's).
        autoreset_mode: see the module docstring.
        device: torch device of the simulation (``"cpu"``, ``"cuda"``...).
        dtype: ``torch.float32`` (default) or ``torch.float64``.
        output: ``"numpy"`` (default) or ``"torch"``.
        render_mode: ``None`` or ``"rgb_array"`` (``render()`` returns one frame per environment).
        compile: run the pure part of the step (dynamics, reward, observation, flags) through
            ``torch.compile`` — one fused loop instead of ~60 small kernels, several times faster for
            large N; the first step then takes seconds to compile (CPU needs a C++ compiler).
    """

    def __init__(self, task: Task | str | type = "PendulumSwingUp", num_envs: int = 1, *,
                 task_kwargs: dict | None = None, max_episode_steps: int | None = None,
                 autoreset_mode=AutoresetMode.NEXT_STEP, device: torch.device | str = "cpu",
                 dtype=torch.float32, output: str = "numpy", render_mode: str | None = None,
                 compile: bool = False):
        self.task = make_task(task, task_kwargs)
        if isinstance(num_envs, np.integer):
            num_envs = int(num_envs)
        if not isinstance(num_envs, int) or isinstance(num_envs, bool) or num_envs < 1:
            raise ValueError(f"TaskVectorEnv: argument 'num_envs' must be a positive int, got {num_envs!r}")
        if output not in ("numpy", "torch"):
            raise ValueError(f"TaskVectorEnv: argument 'output' must be 'numpy' or 'torch', got {output!r}")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"TaskVectorEnv: render_mode must be None or 'rgb_array', got {render_mode!r}")
        steps = self.task.max_episode_steps if max_episode_steps is None else max_episode_steps
        if not isinstance(steps, int) or isinstance(steps, bool) or steps < 1:
            raise ValueError(f"TaskVectorEnv: argument 'max_episode_steps' must be a positive int, "
                             f"got {steps!r}")
        if steps != self.task.max_episode_steps:
            # the observation bounds are proven for the task's horizon: a longer one needs the task's
            self.task = dataclasses.replace(self.task, max_episode_steps=steps)
        self.num_envs, self.max_episode_steps, self.output = num_envs, steps, output
        self.device, self.dtype = torch.device(device), as_dtype(dtype)
        self.autoreset_mode = autoreset_mode_ = as_autoreset_mode(autoreset_mode)
        self.render_mode = render_mode
        self.metadata = {"render_modes": ["rgb_array"], "autoreset_mode": autoreset_mode_,
                         "render_fps": int(round(1.0 / float(self.task.system.dt)))}
        np_dtype = np.float32 if self.dtype == torch.float32 else np.float64
        high = self.task.obs_high().astype(np_dtype)
        self.single_observation_space = gym.spaces.Box(-high, high, dtype=np_dtype)
        self.single_action_space = gym.spaces.Box(-1.0, 1.0, (self.task.m,), dtype=np_dtype)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        kw = dict(device=self.device)
        self._scale = self.task.u_scale(self.dtype, self.device)
        self._x = torch.zeros(num_envs, self.task.n, dtype=self.dtype, **kw)
        self._key = torch.zeros(num_envs, dtype=torch.int64, **kw)
        self._episode = torch.full((num_envs,), -1, dtype=torch.int64, **kw)
        self._t = torch.zeros(num_envs, dtype=torch.int64, **kw)
        self._ended = torch.zeros(num_envs, dtype=torch.bool, **kw)
        self._has_key = torch.zeros(num_envs, dtype=torch.bool, **kw)
        self._started = False
        self._core = torch.compile(self._advance, dynamic=False) if compile else self._advance

    # ------------------------------------------------------------------------------------------ state
    @property
    def state(self) -> torch.Tensor:
        """The full states ``(N, n)`` of the systems (a copy, on the env's device)."""
        return self._x.clone()

    @property
    def elapsed_steps(self) -> torch.Tensor:
        """Steps taken in the current episode of each environment ``(N,)`` (a copy)."""
        return self._t.clone()

    def _initial(self, which: torch.Tensor) -> None:
        """Start a new episode (the next one of each key) where ``which``; the others are untouched."""
        self._episode = torch.where(which, self._episode + 1, self._episode)
        x0 = self.task.initial_state(uniforms(self._key, self._episode, self.task.n_noise, self.dtype))
        self._x = torch.where(which[:, None], x0, self._x)
        self._t = torch.where(which, 0, self._t)
        self._ended = self._ended & ~which

    def _out(self, v: torch.Tensor):
        return v if self.output == "torch" else v.cpu().numpy()

    # ------------------------------------------------------------------------------------------ API
    @torch.no_grad()
    def reset(self, *, seed: int | list[int | None] | None = None, options: dict[str, Any] | None = None):
        N = self.num_envs
        mask = None if options is None else options.get("reset_mask")
        if mask is None:
            which = torch.ones(N, dtype=torch.bool, device=self.device)
        else:
            which = torch.as_tensor(np.asarray(mask.cpu() if isinstance(mask, torch.Tensor) else mask))
            if which.dtype != torch.bool or which.shape != (N,):
                raise ValueError(f"TaskVectorEnv.reset: options['reset_mask'] must be a bool array of shape "
                                 f"({N},), got {getattr(mask, 'dtype', type(mask))} {tuple(np.shape(mask))}")
            which = which.to(self.device)
            if not bool(which.any()):
                raise ValueError("TaskVectorEnv.reset: options['reset_mask'] must select at least one "
                                 "environment (as SyncVectorEnv requires)")
            if not self._started and not bool(which.all()):
                raise ValueError("TaskVectorEnv.reset: the first reset must reset every environment "
                                 "(options['reset_mask'] is only for environments that have started)")
        if seed is not None:
            if isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer, list, tuple)):
                raise ValueError(f"TaskVectorEnv.reset: argument 'seed' must be an int or a list of {N} "
                                 f"non-negative ints or None, got {seed!r}")
            if isinstance(seed, (int, np.integer)):
                if seed < 0:
                    raise ValueError(f"TaskVectorEnv.reset: argument 'seed' must be >= 0, got {seed}")
                self._np_random, self._np_random_seed = seeding.np_random(int(seed))
                seeds = torch.arange(N, dtype=torch.int64) + int(seed) % 2**62
                given = torch.ones(N, dtype=torch.bool)
            else:
                seed = list(seed)
                if len(seed) != N or any(s is not None and (not isinstance(s, (int, np.integer))
                                                            or isinstance(s, (bool, np.bool_)) or s < 0)
                                         for s in seed):
                    raise ValueError(f"TaskVectorEnv.reset: argument 'seed' must be an int or a list of {N} "
                                     f"non-negative ints or None, got {seed!r}")
                seeds = torch.tensor([0 if s is None else int(s) % 2**62 for s in seed], dtype=torch.int64)
                given = torch.tensor([s is not None for s in seed])
            given = given.to(self.device) & which
            self._key = torch.where(given, keys_of_seeds(seeds.to(self.device)), self._key)
            self._episode = torch.where(given, -1, self._episode)
            self._has_key |= given
        fresh = which & ~self._has_key
        if bool(fresh.any()):
            drawn = torch.as_tensor(self.np_random.integers(0, 2**62, size=N), dtype=torch.int64)
            self._key = torch.where(fresh, keys_of_seeds(drawn.to(self.device)), self._key)
            self._episode = torch.where(fresh, -1, self._episode)
            self._has_key |= fresh
        self._initial(which)
        self._started = True
        return self._out(self.task.observe(self._x)), {}

    @torch.no_grad()
    def step(self, actions):
        if not self._started:
            raise RuntimeError("TaskVectorEnv: call reset() before step()")
        a = torch.as_tensor(actions.detach() if isinstance(actions, torch.Tensor) else np.asarray(actions))
        if a.shape != (self.num_envs, self.task.m):
            raise ValueError(f"TaskVectorEnv.step: actions must have shape ({self.num_envs}, {self.task.m}), "
                             f"got {tuple(a.shape)}")
        if a.is_floating_point() and a.dtype != self.dtype:
            a = torch.where(torch.isfinite(a), a.clamp(-2.0, 2.0), a)  # a cast to float32 cannot make an inf
        a = a.to(device=self.device, dtype=self.dtype)
        mode = self.autoreset_mode
        if mode == AutoresetMode.DISABLED and bool(self._ended.any()):
            idx = torch.nonzero(self._ended).flatten().tolist()
            raise RuntimeError(f"TaskVectorEnv.step: environments {idx[:10]}{'...' if len(idx) > 10 else ''} "
                               "ended and autoreset is disabled; reset them with "
                               "reset(options={'reset_mask': mask})")
        x1, t1, obs, r, term, trunc, invalid = self._core(self._x, self._t, a)
        self._x, self._t = x1, t1
        infos: dict[str, Any] = {}
        if mode == AutoresetMode.NEXT_STEP:
            ar = self._ended
            any_ar = any_bad = bool((ar | invalid).any())  # one host sync when nothing happened
            if any_ar:
                any_ar, any_bad = bool(ar.any()), bool(invalid.any())
            if any_ar:
                self._initial(ar)
                keep = ~ar
                r = torch.where(ar, 0.0, r)
                term, trunc, invalid = term & keep, trunc & keep, invalid & keep
                any_bad = bool(invalid.any())
                obs = self.task.observe(self._x)
            if any_bad:
                infos = {"invalid": self._out(invalid), "_invalid": self._out(invalid.clone())}
        else:
            bad = {"invalid": self._out(invalid), "_invalid": self._out(invalid.clone())} \
                if bool(invalid.any()) else {}
            if mode == AutoresetMode.SAME_STEP:
                ended = term | trunc
                if bool(ended.any()):  # an invalid step is truncated, so its flags are in final_info
                    infos = {"final_obs": self._out(obs), "_final_obs": self._out(ended),
                             "final_info": bad, "_final_info": self._out(ended.clone())}
                    self._initial(ended)
                    obs = self.task.observe(self._x)
            else:
                infos = bad
        self._ended = term | trunc
        return self._out(obs), self._out(r), self._out(term), self._out(trunc), infos

    def _advance(self, x: torch.Tensor, t: torch.Tensor, a: torch.Tensor):
        """The pure part of a step (no host synchronization, no autoreset; compiled with
        ``compile=True``): ``(x_next, t_next, obs, reward, terminated, truncated, invalid)``."""
        x1, _, r, term, invalid = self.task.transition(x, a, self._scale)
        t1 = t + 1
        return x1, t1, self.task.observe(x1), r, term, (t1 >= self.max_episode_steps) | invalid, invalid

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        xs = self._x.detach().double().cpu().numpy()
        return tuple(self.task.frame(x) for x in xs)

    def close_extras(self, **kwargs: Any) -> None:
        pass

