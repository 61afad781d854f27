"""Evaluate any policy on a batched task: the MPC expert against a hand-written energy controller.

Story. ``learning.evaluate`` runs a policy on many episodes of a task at once (one batched
environment) and measures the same things for every policy: success, return, final error, time per
control step. A policy can be a trained agent, a torch module, the string ``"mpc"`` (the task's own
MPC expert) or any callable from a batch of observations to a batch of actions — here a classic
energy-pumping swing-up rule written in a few lines, against the iLQR MPC on the same seeds.

Steps:
1. parameters — the number of episodes (all run in one batch) and the first seed;
2. system — the ``PendulumSwingUp`` task (gymnasium's Pendulum-v1 physics and reward; observation
   ``[cos φ, sin φ, ω]`` with φ the angle from upright, torque limit 2);
3. solve — ``learning.evaluate`` of ``energy_pumping`` and of ``"mpc"`` on the same episodes;
4. report — each policy's success rate and mean return (``EvalResult.summary``).

Run:  python examples/evaluate_policy.py [--episodes 16]
"""

from __future__ import annotations

import argparse

import torch

import learning

__all__ = ["main", "energy_pumping"]


def energy_pumping(obs: torch.Tensor, gain: float = 2.0) -> torch.Tensor:
    """Push along the swing while the energy is below upright's, then a PD hold near the top.

    Energy of the unit rod pendulum of Pendulum-v1 relative to upright: ``E = ω²/6 + 5 (cos φ − 1)``
    (g = 10, m = l = 1); pumping ``u = k ω (−E)`` raises E to 0, the energy of the upright rest.
    """
    cos_phi, sin_phi, omega = obs.unbind(-1)
    energy = omega**2 / 6 + 5 * (cos_phi - 1)
    pump = gain * omega * (-energy)
    phi = torch.atan2(sin_phi, cos_phi)
    hold = -20.0 * phi - 4.0 * omega
    return torch.where(cos_phi > 0.9, hold, pump).clamp(-2.0, 2.0).unsqueeze(-1)


def main(episodes: int = 16, seed: int = 0) -> dict:
    """Run the example; returns each policy's success rate and mean return (also printed)."""
    out = {}
    for name, policy in (("energy pumping", energy_pumping), ("mpc", "mpc")):
        res = learning.evaluate(policy, "PendulumSwingUp", num_envs=episodes, seed=seed, progress=False,
                                timing_batch1=False)
        s = res.summary()
        out[name] = {"success_rate": s["success_rate"], "return_mean": s["return"]["mean"]}
        print(f"{name:<15} success {100 * s['success_rate']:5.1f} %   mean return {s['return']['mean']:8.1f}"
              f"   ({episodes} episodes, seeds {seed}..{seed + episodes - 1})")
    return out


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=16)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    main(episodes=args.episodes, seed=args.seed)
