"""Train an RL agent on an environment you built yourself — an ``Env`` instance, not a registered id — and
score it on fresh copies next to a hand-written controller.

Story. ``learning.baselines.train`` takes a gymnasium ``Env`` (or a ``VectorEnv``, or a factory) as well
as an id.  The agent trains on the very env you pass, as stable-baselines3 does; its learning curve and
every evaluation run on fresh copies (``learning.env_source``: ``gymnasium.make(env.spec)`` where the spec
rebuilds the env, else ``copy.deepcopy``), so evaluating never resets or steps the env being trained on.
Here the env is a point mass pushed towards the origin, a class that is not registered anywhere.

Steps:
1. parameters — the training budget (environment steps) and the evaluation episodes;
2. system — ``PointMass``: a 1-d point mass (position, velocity), force in [-1, 1], reward −(x² + 0.1 v²)
   per step, 100 steps per episode;
3. solve — PPO trained on the instance by ``learning.baselines.train``; a PD controller and the agent
   evaluated by ``learning.evaluate`` on copies, the same seeds for both;
4. report — mean returns before and after training, the PD controller's, and checks: the instance was
   stepped exactly as many times as the agent trained, and the curve's last point equals the final
   evaluation.

Run:  python examples/learning/sb3_on_your_env.py [--steps 20000] [--episodes 8]
"""

from __future__ import annotations

import argparse

import gymnasium as gym
import numpy as np
import torch

import learning
from learning import baselines as bl
from learning.env_source import env_source

__all__ = ["main", "PointMass", "pd_controller"]


class PointMass(gym.Env):
    """A 1-d point mass, ``x'' = u`` (time step 0.1), started at rest at ``x ~ U(-1, 1)``."""

    dt = 0.1

    def __init__(self):
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (2,), np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)
        self.steps = 0  # counts the steps of this instance
        self.state = np.zeros(2)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.state = np.array([self.np_random.uniform(-1.0, 1.0), 0.0])
        return self.state.astype(np.float32), {}

    def step(self, action):
        self.steps += 1
        u = float(np.clip(np.asarray(action).reshape(-1)[0], -1.0, 1.0))
        x, v = self.state
        v = v + self.dt * u
        x = x + self.dt * v
        self.state = np.array([x, v])
        return self.state.astype(np.float32), -float(x * x + 0.1 * v * v), False, False, {}


def pd_controller(obs: torch.Tensor) -> torch.Tensor:
    """``u = −2x − 2v`` (clipped by the evaluation to the action box)."""
    return (-2.0 * obs[:, :1] - 2.0 * obs[:, 1:2])


def main(steps: int = 20_000, episodes: int = 8, seed: int = 0) -> dict:
    """Run the example; returns the mean returns and the checks (also printed)."""
    env = gym.wrappers.TimeLimit(PointMass(), 100)
    params = dict(bl.hyperparams("ppo", env), n_envs=1, n_steps=min(512, steps), batch_size=64)
    res = bl.train("ppo", env, steps, seed=seed, eval_every=max(steps // 4, 1), eval_episodes=episodes,
                   params=params, tensorboard=False)
    copies = env_source(env)
    seeds = bl.eval_seeds(episodes)
    agent = learning.evaluate(res.model, copies, seeds=seeds, num_envs=episodes, dtype=torch.float32,
                              progress=False, timing_batch1=False)
    pd, zero = (learning.evaluate(p, copies, seeds=seeds, num_envs=episodes, progress=False,
                                  timing_batch1=False).returns.mean()
                for p in (pd_controller, lambda obs: torch.zeros_like(obs[:, :1])))
    out = {"untrained": res.returns[0], "trained": float(agent.returns.mean()), "pd": float(pd),
           "zero": float(zero), "curve": res.curve(), "copies": copies.how,
           "checks": {"the instance trained every step": env.unwrapped.steps == res.num_timesteps,
                      "the curve ends at the final evaluation": bool(np.isclose(res.returns[-1],
                                                                                agent.returns.mean())),
                      "PD beats doing nothing": bool(pd > zero)}}
    print(f"PointMass (unregistered), copies by {copies.how}; PPO {res.num_timesteps} steps on the instance")
    print(f"mean return on {episodes} held-out episodes: untrained PPO {out['untrained']:.2f}, "
          f"trained PPO {out['trained']:.2f}, PD controller {out['pd']:.2f}, no force {out['zero']:.2f}")
    for name, ok in out["checks"].items():
        print(f"  {'ok ' if ok else 'FAIL'} {name}")
    return out


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=20_000)
    parser.add_argument("--episodes", type=int, default=8)
    parser.add_argument("--seed", type=int, default=0)
    a = parser.parse_args()
    main(a.steps, a.episodes, a.seed)
