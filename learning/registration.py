"""Gymnasium registration of the tasks under the ``liecontrol/`` namespace (nothing happens at import).

>>> import gymnasium as gym, learning
>>> learning.register_envs()
>>> env = gym.make("liecontrol/PendulumSwingUp-v0")                      # TaskEnv in a TimeLimit
>>> venv = gym.make_vec("liecontrol/PendulumSwingUp-v0", num_envs=4096)  # one TaskVectorEnv
"""

from __future__ import annotations

import gymnasium as gym

from learning.envs import TASKS

__all__ = ["register_envs", "env_id"]

NAMESPACE = "liecontrol"
VERSION = 0


def env_id(task_name: str) -> str:
    """The gymnasium id of a task, e.g. ``liecontrol/PendulumSwingUp-v0``."""
    return f"{NAMESPACE}/{task_name}-v{VERSION}"


def register_envs() -> list[str]:
    """Register every task (idempotent) with both a single-env and a vector entry point; returns the ids."""
    ids = []
    for name, cls in TASKS.items():
        i = env_id(name)
        if i not in gym.registry:
            gym.register(id=i, entry_point="learning.envs.single:TaskEnv",
                         vector_entry_point="learning.vector:TaskVectorEnv",
                         max_episode_steps=cls().max_episode_steps, kwargs={"task": name})
        ids.append(i)
    return ids
