"""stable-baselines3 adapter: :class:`SB3VecEnv` exposes a :class:`learning.vector.TaskVectorEnv` as an SB3
``VecEnv`` (SB3 does not accept gymnasium vector envs).

It runs the batched env in ``SAME_STEP`` autoreset mode with numpy outputs and converts to SB3's
conventions: ``dones = terminated | truncated``, and for every environment whose episode ended the info
dict carries ``"terminal_observation"`` (the last observation of the ended episode; the returned
observation is already the first of the next one) and ``"TimeLimit.truncated"`` (truncated and not
terminated) — without them PPO/SAC bootstrap wrongly at time limits.  An invalid step (non-finite action)
adds ``"invalid": True``; the env truncates such an episode, so it also carries
``"TimeLimit.truncated": True`` — SB3 then bootstraps from the last valid observation, as it would at a
time limit (filter on ``"invalid"`` to treat it otherwise).  Works with PPO, SAC, ``VecMonitor``,
``VecNormalize`` and ``evaluate_policy``.  Seeds set by ``VecEnv.seed(s)`` give environment ``i`` the
seed ``s + i``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from gymnasium.vector import AutoresetMode
from stable_baselines3.common.vec_env import VecEnv

from learning.vector import TaskVectorEnv

__all__ = ["SB3VecEnv"]


class SB3VecEnv(VecEnv):
    """An SB3 ``VecEnv`` over ``num_envs`` environments of a task (module docstring).

    Args:
        task: a :class:`TaskVectorEnv` built with ``autoreset_mode=SAME_STEP`` and ``output="numpy"``, or
            a task (instance, class or name) to build one from.
        num_envs, **kwargs: passed to :class:`TaskVectorEnv` when ``task`` is not an env.
    """

    def __init__(self, task: Any = "PendulumSwingUp", num_envs: int = 1, **kwargs):
        if isinstance(task, TaskVectorEnv):
            if kwargs:
                raise ValueError("SB3VecEnv: extra arguments given with an existing TaskVectorEnv")
            if task.autoreset_mode != AutoresetMode.SAME_STEP or task.output != "numpy":
                raise ValueError("SB3VecEnv: the TaskVectorEnv must use autoreset_mode=SAME_STEP and "
                                 f"output='numpy', got {task.autoreset_mode} and {task.output!r}")
            venv = task
        else:
            venv = TaskVectorEnv(task, num_envs, autoreset_mode=AutoresetMode.SAME_STEP, output="numpy",
                                 **kwargs)
        self.venv = venv
        self._actions: np.ndarray | None = None
        super().__init__(venv.num_envs, venv.single_observation_space, venv.single_action_space)

    # ------------------------------------------------------------------------------------- VecEnv API
    def reset(self):
        seeds = None if all(s is None for s in self._seeds) else list(self._seeds)
        obs, _ = self.venv.reset(seed=seeds)
        self._reset_seeds()
        self._reset_options()
        return obs

    def step_async(self, actions: np.ndarray) -> None:
        a = np.asarray(actions)
        # one action per environment; a wrong size is left whole for the env's error, which names it
        self._actions = a.reshape(self.num_envs, -1) if a.size and a.size % self.num_envs == 0 else a

    def step_wait(self):
        obs, rew, term, trunc, info = self.venv.step(self._actions)
        dones = term | trunc
        infos: list[dict[str, Any]] = [{} for _ in range(self.num_envs)]
        ended = np.flatnonzero(dones)
        if ended.size:
            final = info["final_obs"]
            for i in ended:  # only the environments whose episode ended (SB3's API is a list of dicts)
                infos[i] = {"terminal_observation": final[i],
                            "TimeLimit.truncated": bool(trunc[i] and not term[i])}
            bad = info["final_info"].get("invalid")
            if bad is not None:
                for i in np.flatnonzero(bad):
                    infos[i]["invalid"] = True
        return obs, rew.astype(np.float32, copy=False), dones, infos

    def close(self) -> None:
        self.venv.close()

    def get_attr(self, attr_name: str, indices=None) -> list[Any]:
        value = getattr(self.venv, attr_name)
        return [value for _ in self._get_indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices=None) -> None:
        if indices is not None and list(self._get_indices(indices)) != list(range(self.num_envs)):
            raise ValueError("SB3VecEnv.set_attr: the environments share one batched object; "
                             "attributes can only be set for all of them (indices=None)")
        setattr(self.venv, attr_name, value)

    def env_method(self, method_name: str, *method_args, indices=None, **method_kwargs) -> list[Any]:
        out = getattr(self.venv, method_name)(*method_args, **method_kwargs)
        return [out for _ in self._get_indices(indices)]

    def env_is_wrapped(self, wrapper_class, indices=None) -> list[bool]:
        return [False for _ in self._get_indices(indices)]

    def get_images(self) -> Sequence[np.ndarray | None]:
        frames = self.venv.render()
        return [None] * self.num_envs if frames is None else list(frames)
