"""MPC on gymnasium's own ``Pendulum-v1``, zero training (issue 27 §1, §3).

The env is gymnasium's, untouched; the MPC is given what an RL agent is not — the model
(:mod:`learning.env_models`: the pendulum's equations of motion with Pendulum-v1's parameters, and the
reward as the planning cost) — and acts through the env's own observations and action box.
:class:`learning.model_mpc.ModelMPC` solves each step's problem from several initial guesses at once
(:func:`controllers.multistart.ilqr_multistart`: the previous plan, zero, each torque limit held, the
closed-loop LQR "hold") and keeps the best certified plan.  The plain warm-started MPC
(``multistart=False``) starts each episode from zero controls only, and certified local minima then cost it
dearly: from a start a few degrees off upright it plans a full swing.

:func:`learning.evaluate` runs both on the same seeds; its returns equal a hand-written
``env.reset(seed=s)`` / ``env.step`` loop (tested).  The rl-baselines3-zoo's best published Pendulum-v1
score is TD3's −151.9 (benchmark.md; SAC −157.0, PPO −172.2).

Outcome checks: ``holds_near_upright`` — from a start 4° off upright the multi-start MPC keeps the
pendulum within 10° of upright (a braking plan), ``single_start_swings`` — where the single-start MPC's plan
from that start swings the pendulum through the bottom, at a cost over 100 times the multi-start plan's;
``certified`` — every multi-start solve of the evaluation ended CONVERGED.  The returns of both on the
seeds (the full 200-step episodes by default) are reported, with the zoo's figure.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from learning import evaluate
from learning.model_mpc import ModelMPC
from learning.zoo import zoo_best


def _from_4_degrees(steps: int, horizon: int) -> dict:
    """The first plan of both MPCs from 4° off upright at rest, and the multi-start MPC's largest angle from
    upright (degrees) over ``steps`` steps of the model."""
    multi = ModelMPC("Pendulum-v1", horizon=horizon)
    single = ModelMPC("Pendulum-v1", horizon=horizon, multistart=False)
    x = torch.tensor([[math.pi - math.radians(4.0), 0.0]], dtype=torch.float64)

    def obs(x):
        return torch.stack([-torch.cos(x[:, 0]), -torch.sin(x[:, 0]), x[:, 1]], -1)

    single.act(obs(x))
    worst, first = 4.0, None
    for _ in range(steps):
        x = multi.model.system.step(x, multi.act(obs(x)))
        first = multi.last_cost if first is None else first
        worst = max(worst, math.degrees(abs(math.remainder(float(x[0, 0]) - math.pi, 2 * math.pi))))
    return {"multistart_plan_cost": first, "single_start_plan_cost": single.last_cost,
            "multistart_max_angle_deg": worst}


def main(episodes: int = 10, steps: int | None = None, horizon: int = 40, hold_steps: int = 20) -> dict:
    seeds = list(range(episodes))
    runs = {}
    for name, multi in (("multistart", True), ("single_start", False)):
        r = evaluate(ModelMPC("Pendulum-v1", horizon=horizon, multistart=multi), "Pendulum-v1", seeds=seeds,
                     num_envs=episodes, max_episode_steps=steps, progress=False, timing_batch1=False)
        runs[name] = {"return_mean": float(np.mean(r.returns)), "return_std": float(np.std(r.returns)),
                      "returns": r.returns.round(1).tolist(),
                      "nonconverged": float(np.nanmean(r.nonconverged)),
                      "ms_per_step": float(np.median(r.step_ms))}
    near = _from_4_degrees(hold_steps, 40)
    algo, best = zoo_best("Pendulum-v1")
    return {**runs, "zoo_best": {"algo": algo, "return": best}, "from_4_degrees": near,
            "checks": {"holds_near_upright": near["multistart_max_angle_deg"] < 10.0,
                       "single_start_swings":
                       near["single_start_plan_cost"] > 100 * near["multistart_plan_cost"],
                       "certified": runs["multistart"]["nonconverged"] == 0.0}}


if __name__ == "__main__":
    import json

    print(json.dumps(main(), indent=1))
