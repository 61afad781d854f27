"""stable-baselines3 adapter: :class:`SB3VecEnv` exposes a :class:`learning.vector.TaskVectorEnv` — or any
gymnasium ``VectorEnv`` — as an SB3 ``VecEnv`` (SB3 does not accept gymnasium vector envs).

It converts to SB3's conventions: ``dones = terminated | truncated``, and for every environment whose
episode ended the info dict carries ``"terminal_observation"`` (the last observation of the ended episode;
the returned observation is already the first of the next one) and ``"TimeLimit.truncated"`` (truncated
and not terminated) — without them PPO/SAC bootstrap wrongly at time limits.  A task's env runs in
``SAME_STEP`` autoreset mode with numpy outputs.  A gymnasium vector env runs in the mode it was built with:
``SAME_STEP`` gives the ended episodes' last observations in ``info["final_obs"]``; under ``NEXT_STEP``
(gymnasium's default) and ``DISABLED`` the step's observation is the last one, and the ended sub-envs are
reset at once (``reset(options={"reset_mask": ended})``, without seeds: they go on from their own
generators), so no step of an episode is lost or invented.  An invalid step of a task (non-finite action)
adds ``"invalid": True``; the env truncates such an episode, so it also carries
``"TimeLimit.truncated": True`` — SB3 then bootstraps from the last valid observation, as it would at a
time limit (filter on ``"invalid"`` to treat it otherwise).  Works with PPO, SAC, ``VecMonitor``,
``VecNormalize`` and ``evaluate_policy``.  Seeds set by ``VecEnv.seed(s)`` give environment ``i`` the
seed ``s + i``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode
from stable_baselines3.common.vec_env import VecEnv

from learning.vector import TaskVectorEnv

__all__ = ["SB3VecEnv"]


class SB3VecEnv(VecEnv):
    """An SB3 ``VecEnv`` over ``num_envs`` environments of a task (module docstring).

    Args:
        task: a :class:`TaskVectorEnv` built with ``autoreset_mode=SAME_STEP`` and ``output="numpy"``, any
            other gymnasium ``VectorEnv`` (any autoreset mode), or a task (instance, class or name) to
            build a :class:`TaskVectorEnv` from.
        num_envs, **kwargs: passed to :class:`TaskVectorEnv` when ``task`` is not an env.
    """

    def __init__(self, task: Any = "PendulumSwingUp", num_envs: int = 1, **kwargs):
        if isinstance(task, gym.vector.VectorEnv):
            if kwargs:
                raise ValueError("SB3VecEnv: extra arguments given with an existing vector env")
            base = task.unwrapped
            if isinstance(base, TaskVectorEnv) and (base.autoreset_mode != AutoresetMode.SAME_STEP
                                                    or base.output != "numpy"):
                raise ValueError("SB3VecEnv: the TaskVectorEnv must use autoreset_mode=SAME_STEP and "
                                 f"output='numpy', got {base.autoreset_mode} and {base.output!r}")
            venv = task
        else:
            venv = TaskVectorEnv(task, num_envs, autoreset_mode=AutoresetMode.SAME_STEP, output="numpy",
                                 **kwargs)
        self.venv = venv
        self.autoreset_mode = AutoresetMode(venv.metadata.get("autoreset_mode", AutoresetMode.NEXT_STEP))
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
        term, trunc = np.asarray(term, dtype=bool), np.asarray(trunc, dtype=bool)
        dones = term | trunc
        infos: list[dict[str, Any]] = [{} for _ in range(self.num_envs)]
        ended = np.flatnonzero(dones)
        if ended.size:
            if self.autoreset_mode == AutoresetMode.SAME_STEP:
                final, final_info = info["final_obs"], info.get("final_info", {})
            else:  # the step's observations end the episodes: reset the ended sub-envs now
                final, final_info = np.array(obs, copy=True), info
                fresh, _ = self.venv.reset(options={"reset_mask": dones})
                obs = np.array(obs, copy=True)
                obs[ended] = np.asarray(fresh)[ended]
            for i in ended:  # only the environments whose episode ended (SB3's API is a list of dicts)
                infos[i] = {"terminal_observation": final[i],
                            "TimeLimit.truncated": bool(trunc[i] and not term[i])}
            bad = final_info.get("invalid") if isinstance(final_info, dict) else None
            if bad is not None:
                for i in np.flatnonzero(np.asarray(bad, dtype=bool) & dones):
                    infos[i]["invalid"] = True
        return obs, np.asarray(rew).astype(np.float32, copy=False), dones, infos

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
