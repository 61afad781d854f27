"""An MPC head on the manifold inside PPO: the quadrotor's error-state MPC, re-weighted by a cost network
(issue 26 §7; seed 003's MPC, the cost map of Actor-Critic MPC, Romero et al., TRO 2025).

:class:`learning.mpc_policy.MPCActorCriticPolicy` on ``QuadrotorCircle`` builds
:class:`learning.mpc_head_quadrotor.ErrorStateMPCExtractor`: observation → a network that scales the
expert's state and control weights and moves its position target (per knot: ``per_step``) → the error-state
MPC on ``R³ × R³ × SO(3)`` (a box QP under the thrust and rate limits) → PPO's mean action.  The network's
last layer starts at zero, so the untrained policy is the task's expert; PPO then trains the cost through
the QP's implicit gradient.

Outcome checks: ``untrained_head_is_the_expert`` — its return on the held-out episodes equals the expert's
(same horizon) within 1e-3; ``trained_head_still_tracks`` — after ``steps`` PPO steps every held-out episode
still ends on the circle (the task's success); ``gradient_reached_the_cost`` — training moved the cost
network's output layer; ``no_failed_solves`` — no solve returned a non-finite action; and the head, planning
with the nominal model, is evaluated on a vehicle 30 % heavier (reported, not checked).
"""

from __future__ import annotations

import numpy as np
import torch

from learning.baselines import eval_seeds
from learning.envs.single import make_task
from learning.evaluate import evaluate
from learning.mpc_policy import make_mpc_ppo
from learning.robustness import robustness_study


def _score(policy, task, seeds) -> dict:
    r = evaluate(policy, task, seeds=seeds, num_envs=len(seeds), dtype=torch.float32, progress=False,
                 timing_batch1=False)
    return {"return_mean": float(np.mean(r.returns)), "success_rate": float(np.mean(r.success))}


def main(steps: int = 512, episodes: int = 4, horizon: int = 10, seed: int = 0) -> dict:
    torch.manual_seed(seed)
    task = make_task("QuadrotorCircle")
    seeds = eval_seeds(episodes)
    model = make_mpc_ppo(task, num_envs=4, n_steps=32, batch_size=64, n_epochs=2, seed=seed,
                         policy_kwargs={"horizon": horizon, "per_step": True})
    head = model.policy.mlp_extractor
    expert = _score(task.expert(horizon=horizon), task, seeds)
    untrained = _score(model, task, seeds)
    before = head.net[-1].weight.detach().clone()
    model.learn(steps)
    trained = _score(model, task, seeds)
    moved = float((head.net[-1].weight.detach() - before).abs().max())
    heavy = robustness_study({"head": model}, task, {"mass×1.3": {"mass": 1.3}}, seeds=seeds,
                             dtype=torch.float32)[0]
    return {"expert": expert, "untrained": untrained, "trained": trained, "output_layer_moved": moved,
            "heavier_vehicle": {k: heavy[k] for k in ("return_mean", "success_rate", "final_error")},
            "checks": {"untrained_head_is_the_expert":
                       abs(untrained["return_mean"] - expert["return_mean"]) < 1e-3,
                       "trained_head_still_tracks": trained["success_rate"] == 1.0,
                       "gradient_reached_the_cost": moved > 0,
                       "no_failed_solves": int(head.nonfinite_actions) == 0}}


if __name__ == "__main__":
    import json

    print(json.dumps(main(), indent=1))
