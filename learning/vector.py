"""A task as a natively batched :class:`gymnasium.vector.VectorEnv`: N environments in one tensor.

:class:`TaskVectorEnv` steps every environment with one call of the task's torch code on CPU or CUDA — no
Python loop over environments anywhere (not in step, not in autoreset, not in seeding).

* **Outputs**: numpy arrays by default (what stock gymnasium/SB3 wrappers expect), torch tensors on the
  env's device with ``output="torch"``.  Every call returns fresh buffers.  Rewards have the env's dtype.
* **Truncation** is enforced by the env itself after ``max_episode_steps`` (``make_vec`` passes the
  registered value); an *invalid* step (non-finite action or state) truncates too, flagged in
  ``infos["invalid"]`` with the mask ``infos["_invalid"]``.  Actions outside ``[-1, 1]`` are clipped (in
  their own dtype first: :func:`~learning.envs.single.as_action`); complex actions are a ``TypeError``.
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
import warnings
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode
from gymnasium.vector.utils import batch_space

from learning._counter_rng import keys_of_seeds, uniforms
from learning.envs.single import as_action, as_device, as_dtype, make_task
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


def _as_compile_mode(compile) -> str | None:
    if compile is False or compile is None:
        return None
    if compile is True or compile == "inductor":
        return "inductor"
    if compile == "aot":
        return "aot"
    raise ValueError(f"TaskVectorEnv: argument 'compile' must be False, True, 'inductor' or 'aot', "
                     f"got {compile!r}")


def _restart(task: Task, which, x, t, key, episode):
    """``(x, t, episode)`` with the next episode of each key started where ``which`` (the others as given)."""
    episode = episode + which.to(episode.dtype)
    x0 = task.initial_state(uniforms(key, episode, task.n_noise, x.dtype))
    return torch.where(which[:, None], x0, x), torch.where(which, 0, t), episode


class _StepCore(torch.nn.Module):
    """The pure part of a step: no host synchronization, no branch on data, nothing stored (what the
    compiled modes compile).

    ``(x, t, a, ended, key, episode) -> (x, t, episode, obs, reward, terminated, truncated, invalid,
    ended, flags[, final_obs])`` after the step, with ``flags = [ended_before.any(), invalid.any(),
    ended_after.any()]`` in one tensor (the env reads all three with one synchronization).  With
    ``autoreset`` NEXT_STEP or SAME_STEP the reset is done here too, for every environment at once: the
    next episode's initial state is drawn for all and selected where one starts (a few fused operations
    per environment; the env runs this variant only at a step where a reset is due, the ``autoreset=None``
    one otherwise).  SAME_STEP returns the ended episodes' last observations as ``final_obs``.
    """

    def __init__(self, task: Task, scale: torch.Tensor, max_episode_steps: int,
                 autoreset: AutoresetMode | None):
        super().__init__()
        self.task, self.max_episode_steps = task, max_episode_steps
        self.autoreset = None if autoreset == AutoresetMode.DISABLED else autoreset
        self.register_buffer("scale", scale)

    def forward(self, x, t, a, ended, key, episode):
        task = self.task
        x1, _, r, term, invalid = task.transition(x, a, self.scale)
        t1 = t + 1
        trunc = (t1 >= self.max_episode_steps) | invalid
        final = None
        if self.autoreset == AutoresetMode.NEXT_STEP:  # an ended environment restarts; its action is ignored
            x1, t1, episode = _restart(task, ended, x1, t1, key, episode)
            keep = ~ended
            r = torch.where(ended, 0.0, r)
            term, trunc, invalid = term & keep, trunc & keep, invalid & keep
        done = term | trunc
        if self.autoreset == AutoresetMode.SAME_STEP:
            final = task.observe(x1)
            x1, t1, episode = _restart(task, done, x1, t1, key, episode)
        flags = torch.stack([ended.any(), invalid.any(), done.any()])
        out = (x1, t1, episode, task.observe(x1), r, term, trunc, invalid, done, flags)
        return out if final is None else (*out, final)


class _AotStep:
    """A :class:`_StepCore` exported with a dynamic batch size and built by AOTInductor."""

    def __init__(self, core: _StepCore):
        import os
        import tempfile

        kw = dict(device=core.scale.device)
        f = dict(dtype=core.scale.dtype, **kw)
        i64 = torch.zeros(8, dtype=torch.int64, **kw)
        ex = (torch.zeros(8, core.task.n, **f), i64, torch.zeros(8, core.task.m, **f),
              torch.zeros(8, dtype=torch.bool, **kw), i64.clone(), i64.clone())
        N = torch.export.Dim("num_envs", min=1)
        with torch.no_grad(), warnings.catch_warnings(), tempfile.TemporaryDirectory() as d:
            warnings.filterwarnings("ignore", message=".*LeafSpec.*", category=FutureWarning)  # torch's own
            ep = torch.export.export(core, ex, dynamic_shapes=tuple({0: N} for _ in ex))
            path = torch._inductor.aoti_compile_and_package(ep, package_path=os.path.join(d, "step.pt2"))
            self._model = torch._inductor.aoti_load_package(path)
        # the loader's flat entry point skips the pytree wrapper (~50 µs a call on CPU)
        self._run = getattr(getattr(self._model, "loader", None), "run", None)

    def __call__(self, *args):
        if self._run is not None:
            return tuple(self._run(list(args)))
        return tuple(self._model(*args))


# AOT-built steps of tasks given by name, shared by every env of the process (one build per key)
_AOT_STEPS: dict[tuple, _AotStep] = {}


def _aot_core(core: _StepCore, name: str | None) -> _AotStep:
    """The AOT-built step of ``core``; a task given by name (no kwargs) is built once per process for its
    dtype, device and horizon (a Task instance is built every time: its fields are not a safe key)."""
    if name is None:
        return _AotStep(core)
    key = (name, core.scale.dtype, str(core.scale.device), core.max_episode_steps, core.autoreset)
    if key not in _AOT_STEPS:
        _AOT_STEPS[key] = _AotStep(core)
    return _AOT_STEPS[key]


class TaskVectorEnv(gym.vector.VectorEnv):
    """``num_envs`` environments of a :class:`Task` stepped as one batch (module docstring).

    Args:
        task: a :class:`Task`, a Task class or a registered task name; ``task_kwargs`` its arguments.
        num_envs: number of environments N.
        max_episode_steps: truncation horizon (default: the task's).
        autoreset_mode: see the module docstring.
        device: torch device of the simulation (``"cpu"``, ``"cuda"``...); one this torch cannot use (CUDA
            on a CPU-only build, a missing device index) is a ``ValueError`` here, in the constructor.
        dtype: ``torch.float32`` (default) or ``torch.float64``.
        output: ``"numpy"`` (default) or ``"torch"``.
        render_mode: ``None`` or ``"rgb_array"`` (``render()`` returns one frame per environment).
        compile: how the pure part of the step (dynamics, reward, observation, flags) runs — one fused
            loop instead of ~60 small kernels.  ``False`` (default): eager PyTorch.  ``True`` or
            ``"inductor"``: through ``torch.compile`` (the first step compiles, ~5 s; every call then
            pays TorchDynamo's guards, ~60 µs on CPU).  ``"aot"``: exported with ``torch.export`` and
            built by AOTInductor into a shared library at construction (~40 s on CPU, once per process
            for a task given by name: the library is shared by every env of that task, dtype, device
            and horizon, whatever ``num_envs``), then called with ~10 µs of overhead: the fastest at
            every N.  Both compiled modes need a C++ compiler on CPU.  The compiled step fuses
            operations (and may contract them into FMAs), so it rounds differently from eager: equal to
            1e-12 in float64 (tested); in float32 one ulp at the first step, which a swing-up's
            dynamics grow to ~3e-3 in the observations after 300 steps (flags still equal).
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
        self.device, self.dtype = as_device(device, "TaskVectorEnv"), as_dtype(dtype)
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
        self.compile = _as_compile_mode(compile)
        # the step without resets, and (unless autoreset is disabled) the step with this mode's resets,
        # run only when one is due: drawing every environment's next initial state costs more than the step
        name = task if isinstance(task, str) and not task_kwargs else None
        self._core = self._build(_StepCore(self.task, self._scale, steps, None), name)
        self._core_reset = None if autoreset_mode_ == AutoresetMode.DISABLED else \
            self._build(_StepCore(self.task, self._scale, steps, autoreset_mode_), name)
        self._pending = False  # an episode ended at the last step (NEXT_STEP resets it at this one)

    def _build(self, core: _StepCore, name: str | None):
        if self.compile == "aot":
            return _aot_core(core, name)
        if self.compile == "inductor":
            return torch.compile(core, dynamic=False)
        return core

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
        self._x, self._t, self._episode = _restart(self.task, which, self._x, self._t,
                                                   self._key, self._episode)
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
        self._pending = bool(self._ended.any())  # environments a partial reset left ended
        return self._out(self.task.observe(self._x)), {}

    @torch.no_grad()
    def step(self, actions):
        if not self._started:
            raise RuntimeError("TaskVectorEnv: call reset() before step()")
        a = as_action(actions, self.dtype, "TaskVectorEnv.step: actions", self.device)
        if a.shape != (self.num_envs, self.task.m):
            raise ValueError(f"TaskVectorEnv.step: actions must have shape ({self.num_envs}, {self.task.m}), "
                             f"got {tuple(a.shape)}")
        a = a.contiguous()  # the AOT build reads its inputs as dense rows (a strided view would be misread)
        mode = self.autoreset_mode
        args = (self._x, self._t, a, self._ended, self._key, self._episode)
        core = self._core_reset if mode == AutoresetMode.NEXT_STEP and self._pending else self._core
        x1, t1, episode, obs, r, term, trunc, invalid, ended, flags, *final = core(*args)
        any_ended_before, any_bad, any_ended = flags.tolist()  # the step's one host synchronization
        if mode == AutoresetMode.DISABLED and any_ended_before:
            idx = torch.nonzero(self._ended).flatten().tolist()
            raise RuntimeError(f"TaskVectorEnv.step: environments {idx[:10]}{'...' if len(idx) > 10 else ''} "
                               "ended and autoreset is disabled; reset them with "
                               "reset(options={'reset_mask': mask})")
        if mode == AutoresetMode.SAME_STEP and any_ended:  # the same step again, with the resets
            x1, t1, episode, obs, r, term, trunc, invalid, ended, flags, *final = self._core_reset(*args)
        self._x, self._t, self._episode, self._ended, self._pending = x1, t1, episode, ended, any_ended
        bad = {"invalid": self._out(invalid), "_invalid": self._out(invalid.clone())} if any_bad else {}
        infos: dict[str, Any] = bad
        if final:  # an invalid step is truncated: its flags are in final_info
            infos = {"final_obs": self._out(final[0]), "_final_obs": self._out(ended.clone()),
                     "final_info": bad, "_final_info": self._out(ended.clone())}
        return self._out(obs), self._out(r), self._out(term), self._out(trunc), infos

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        xs = self._x.detach().double().cpu().numpy()
        return tuple(self.task.frame(x) for x in xs)

    def close_extras(self, **kwargs: Any) -> None:
        pass

