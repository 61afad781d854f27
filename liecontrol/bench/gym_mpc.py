"""``liecontrol bench gym``: the MPC step on gymnasium's MuJoCo environments against issue 27's targets, in
one run.

Each row runs a policy on ``--steps`` steps of real episodes (``learning.evaluate`` on the env's own id,
seeds 0…N−1, ``N`` environments in lockstep) and reports the median wall time of one batched policy call
(``step_ms``: observation in, actions out — the MuJoCo calls for the model's Jacobians and rollouts
included, the env's own step excluded) with the return of those steps.  Policies:

* ``linear`` — :class:`learning.model_mpc.LinearModelMPC`: one finite-difference linearization a step and
  one Riccati recursion (no iterations, no certificate);
* ``ilqr`` — :class:`learning.model_mpc.ModelMPC` with the model's settings (iLQR on the MuJoCo model: its
  rollouts and finite-difference Jacobians through ``mujoco.rollout``; ``--compile``: the solver's sweeps
  as compiled programs, built once and cached on disk).

``step_ms`` is the median over the episode's steps; ``first_ms`` the first step alone (where the model's
settings solve an episode's start with more iterations or guesses: Reacher-v5's multi-start).

The targets (``target_ms``) are the issue's: InvertedPendulum-v5 (horizon 25) 5 ms at batch 1 and 50 ms for
64 environments, Reacher-v5 20 ms at batch 1; ``vs_target`` = step_ms / target (below 1 meets it).  MuJoCo
runs on the CPU: states cross from torch to numpy float64 for every ``mujoco.rollout`` call and back (a
copy each way, also from CUDA tensors).
"""

from __future__ import annotations

import argparse
import math

import numpy as np
import torch

from liecontrol import _options
from liecontrol.report import print_table, restores_threads, write_json

__all__ = ["add_arguments", "run", "measure", "COLUMNS", "TARGETS"]

COLUMNS = ["env", "policy", "batch", "horizon", "steps", "step_ms", "first_ms", "target_ms", "vs_target",
           "return_mean", "status"]
#: issue 27 §4: (env, batch) -> milliseconds per MPC step
TARGETS = {("InvertedPendulum-v5", 1): 5.0, ("InvertedPendulum-v5", 64): 50.0, ("Reacher-v5", 1): 20.0}

add_arguments = _options.bench_gym


def _policy(kind: str, env_id: str, horizon: int | None, compile: bool = False):
    from learning.model_mpc import LinearModelMPC, ModelMPC

    if kind == "linear":
        return LinearModelMPC(env_id, horizon=horizon)
    return ModelMPC(env_id, horizon=horizon, compile=compile)


def _row(env_id: str, kind: str, N: int, steps: int, horizon: int | None, compile: bool = False) -> dict:
    from learning import evaluate

    rec = {"env": env_id, "policy": kind, "batch": N, "steps": steps, "target_ms": TARGETS.get((env_id, N))}
    try:
        pol = _policy(kind, env_id, horizon, compile)
        rec["horizon"] = pol.horizon
        r = evaluate(pol, env_id, seeds=list(range(N)), num_envs=N, max_episode_steps=steps, progress=False,
                     timing_batch1=False)
        if r.invalid.any():
            raise RuntimeError(next(e for e in r.errors if e) or "an invalid episode")
        rec["step_ms"] = float(np.median(r.step_ms))
        rec["first_ms"] = float(r.step_ms[0])
        rec["return_mean"] = float(r.returns.mean())
        rec["status"] = "ok"
    except (ValueError, ImportError, RuntimeError) as e:
        rec["status"] = f"{type(e).__name__}: {e}"[:160]
    t, ms = rec["target_ms"], rec.get("step_ms")
    rec["vs_target"] = ms / t if t and ms is not None and math.isfinite(ms) else None
    return rec


@restores_threads
def measure(args: argparse.Namespace) -> list[dict]:
    torch.set_num_threads(args.threads)
    rows = []
    for env_id in args.envs:
        for kind in args.policies:
            for N in args.batch:
                rows.append(_row(env_id, kind, N, args.steps, args.horizon, args.compile))
    return rows


def run(args: argparse.Namespace) -> int:
    rows = measure(args)
    print(f"MPC step on gymnasium MuJoCo envs, torch {torch.__version__}, {args.threads} thread(s); "
          "vs_target = step_ms / issue 27's target (below 1 meets it)")
    print_table(rows, COLUMNS)
    if args.json:
        write_json(args.json, rows)
        print(f"wrote {args.json}")
    return 0
