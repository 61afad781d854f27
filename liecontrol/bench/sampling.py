"""``liecontrol bench sampling``: our batched sampling planners (:mod:`controllers.sampling`) against the
``pytorch_mppi`` package on one pendulum swing-up, measured in the same run.

The problem is shared exactly: the dynamics are :class:`controllers.systems.Pendulum` (``dt = 0.05``,
damping 0.1; pytorch_mppi calls ``Pendulum.step`` through a ``dynamics(state, action)`` wrapper) and the
cost is one :class:`~controllers.costs.QuadraticCost` ``Σ_t (x_t - x*)ᵀQ(x_t - x*) + u_tᵀRu_t`` with
``x* = [π, 0]`` (pytorch_mppi's ``running_cost(state, action)`` is its per-step term evaluated on the
next state; the constant ``x_0`` term is the only difference).  Both use the same ``K`` samples,
horizon ``T``, iterations per MPC step, temperature ``λ``, noise standard deviation ``σ`` (pytorch_mppi
takes the covariance ``σ²``), control limits, zero initial plan and zero fill of the shifted plan.

Rows (per implementation and batch size):

* ``plan_cost`` — the cost (ours, on our rollout, for both) of the plan made by one MPC step from the
  batch of start states near the bottom and a zero nominal, mean over ``--seeds`` repeats and the batch;
* ``step_ms`` — wall time of one MPC step for the whole batch (median, :func:`liecontrol.report.time_ms`);
* ``episode_return`` — closed loop over ``--steps`` steps from the same start states, the return
  ``-Σ_t (wrap(θ_t - π)² + 0.1 ω_t² + 0.001 u_t²)`` (Pendulum-v1's reward on our pendulum), mean over the
  batch, and ``final_err`` = max ``|wrap(θ - π)|`` at the end.

Ratios ``ours / pytorch_mppi`` at the same batch size (``cost_ratio``, ``time_ratio``,
``return_ratio``; returns are negative, so for every ratio below 1 is better for ours).  Batch 1 uses
``pytorch_mppi.MPPI``; batch > 1 its ``MPPI_Batched`` (one dynamics call for all environments, noise shared
across them).  Algorithmic differences kept as they are: pytorch_mppi adds its information-theoretic
control cost ``λ Uᵀ Σ⁻¹ ε`` to each sample's cost and returns the weighted update unconditionally; ours
includes the current plan as a candidate and falls back to the best candidate when the update is
worse.  ``ours-*-knots`` rows sample the noise on 6 knots (piecewise linear).  pytorch_mppi draws from
torch's global generator (seeded here); ours from an explicit ``torch.Generator``.  When pytorch_mppi is
not importable its rows say so and the ratios are empty.
"""

from __future__ import annotations

import argparse
import math

import torch

from liecontrol import _options
from liecontrol.report import print_table, restores_threads, time_ms, write_json

__all__ = ["add_arguments", "run", "measure", "COLUMNS"]

add_arguments = _options.bench_sampling

COLUMNS = ["impl", "batch", "K", "T", "iters", "plan_cost", "step_ms", "episode_return", "final_err",
           "cost_ratio", "time_ratio", "return_ratio", "status"]
OURS = {"ours-mppi": ("mppi", "none"), "ours-mppi-knots": ("mppi", "knots"),
        "ours-predictive-knots": ("predictive", "knots")}
ANCHOR = "pytorch_mppi"


def _problem(dtype: torch.dtype) -> dict:
    from controllers.costs import QuadraticCost
    from controllers.systems import Pendulum

    cost = QuadraticCost(Q=torch.diag(torch.tensor([1.0, 0.1], dtype=dtype)),
                         R=torch.tensor([[0.001]], dtype=dtype),
                         x_ref=torch.tensor([math.pi, 0.0], dtype=dtype))
    return {"system": Pendulum(dt=0.05, damping=0.1), "cost": cost, "sigma": 3.0, "lam": 0.1, "umax": 8.0}


def _x0(B: int, dtype: torch.dtype) -> torch.Tensor:
    """Start states near the bottom (the first exactly hanging at rest), the same for every impl."""
    g = torch.Generator().manual_seed(1234)
    x = 0.3 * (torch.rand(B, 2, generator=g, dtype=torch.float64) * 2 - 1)
    x[0] = 0.0
    return x.to(dtype)


def _reward(x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    err = torch.remainder(x[..., 0], 2 * math.pi) - math.pi  # wrap(θ - π)
    return -(err**2 + 0.1 * x[..., 1] ** 2 + 0.001 * u[..., 0] ** 2)


def _angle_err(x: torch.Tensor) -> float:
    return float((torch.remainder(x[..., 0], 2 * math.pi) - math.pi).abs().max())


def _ours(prob: dict, method: str, smoothing: str, K: int, T: int, iters: int):
    from controllers.sampling import SamplingMPC, SamplingOptions

    opts = SamplingOptions(samples=K, iterations=iters, noise_sigma=prob["sigma"], temperature=prob["lam"],
                           method=method, smoothing=smoothing, knots=6)
    return SamplingMPC(prob["system"], prob["cost"], T, opts, u_lower=-prob["umax"], u_upper=prob["umax"],
                       fill="zero")


def _anchor(prob: dict, B: int, K: int, T: int, dtype: torch.dtype):
    """A fresh pytorch_mppi controller (MPPI at batch 1, MPPI_Batched above) on our dynamics and cost."""
    from pytorch_mppi import mppi as pm

    system, cost = prob["system"], prob["cost"]
    Q, R, ref = cost.Q[0], cost.R[0], cost.x_ref[0]

    def dynamics(state, action):
        return system.step(state, action)

    def running_cost(state, action):  # the per-step term of our QuadraticCost, on the next state
        dx = state - ref
        return ((dx @ Q) * dx).sum(-1) + ((action @ R) * action).sum(-1)

    kw = dict(nx=2, noise_sigma=prob["sigma"] ** 2 * torch.eye(1, dtype=dtype), num_samples=K, horizon=T,
              lambda_=prob["lam"], u_min=torch.tensor([-prob["umax"]], dtype=dtype),
              u_max=torch.tensor([prob["umax"]], dtype=dtype))
    if B == 1:
        return pm.MPPI(dynamics, running_cost, U_init=torch.zeros(T, 1, dtype=dtype), **kw)
    ctl = pm.MPPI_Batched(dynamics, running_cost, num_envs=B, **kw)
    ctl.U = torch.zeros(B, T, 1, dtype=dtype)  # its default initial plan is noise; ours starts at zero
    return ctl


def _anchor_step(ctl, x: torch.Tensor, iters: int, B: int) -> torch.Tensor:
    """One MPC step of pytorch_mppi: shift, then ``iters`` updates of the plan; returns ``u0 (B, 1)``."""
    state = x[0] if B == 1 else x
    a = ctl.command(state)
    for _ in range(iters - 1):
        a = ctl.command(state, shift_nominal_trajectory=False)
    return a.reshape(B, 1)


def _plan_cost(prob: dict, impl: str, B: int, K: int, T: int, iters: int, seeds: int, dtype) -> float:
    from controllers.dynamics import rollout

    x0, costs = _x0(B, dtype), []
    for s in range(seeds):
        if impl == ANCHOR:
            torch.manual_seed(s)
            ctl = _anchor(prob, B, K, T, dtype)
            _anchor_step(ctl, x0, iters, B)
            u = ctl.U.reshape(B, T, 1)
            costs.append(prob["cost"].evaluate(rollout(prob["system"], x0, u), u))
        else:
            mpc = _ours(prob, *OURS[impl], K, T, iters)
            _, _, res = mpc(x0, mpc.initial_state(B, dtype=dtype), torch.Generator().manual_seed(s))
            costs.append(res.cost)
    return float(torch.stack(costs).mean())


def _episode(prob: dict, impl: str, B: int, K: int, T: int, iters: int, steps: int, dtype):
    """Closed loop: ``(return per element (mean), final angle error, step timing closure)``."""
    x, total = _x0(B, dtype), torch.zeros(B, dtype=dtype)
    if impl == ANCHOR:
        torch.manual_seed(0)
        ctl = _anchor(prob, B, K, T, dtype)
        act = lambda x: _anchor_step(ctl, x, iters, B)  # noqa: E731
    else:
        mpc, g = _ours(prob, *OURS[impl], K, T, iters), torch.Generator().manual_seed(0)
        box = [mpc.initial_state(B, dtype=dtype)]

        def act(x):
            u, box[0], _ = mpc(x, box[0], g)
            return u
    for _ in range(steps):
        u = act(x)
        total += _reward(x, u)
        x = prob["system"].step(x, u)
    x_end = x
    return float(total.mean()), _angle_err(x_end), (lambda: act(x_end))


def _record(prob, impl: str, B: int, args, dtype) -> dict:
    K, T, it = args.samples, args.horizon, args.iterations
    rec = {"impl": impl, "batch": B, "K": K, "T": T, "iters": it, "dtype": str(dtype).removeprefix("torch."),
           "status": "ok"}
    try:
        with torch.no_grad():
            rec["plan_cost"] = _plan_cost(prob, impl, B, K, T, it, args.seeds, dtype)
            ret, err, step = _episode(prob, impl, B, K, T, it, args.steps, dtype)
            rec.update(episode_return=ret, final_err=err, step_ms=time_ms(step, repeats=args.repeats))
    except ImportError as e:
        rec["status"] = f"not installed ({e.name or e})"
    except Exception as e:  # an anchor's failure is its result
        rec["status"] = f"failed: {type(e).__name__}: {e}"
    return rec


@restores_threads
def measure(args: argparse.Namespace, log=lambda s: None) -> list[dict]:
    """Run the benchmark (module docstring) and return its records."""
    torch.set_num_threads(args.threads)
    dtype = getattr(torch, args.dtype)
    prob = _problem(dtype)
    records = []
    for B in args.batch:
        anchor = _record(prob, ANCHOR, B, args, dtype)
        for impl in OURS:
            rec = _record(prob, impl, B, args, dtype)
            for key, col in (("cost_ratio", "plan_cost"), ("time_ratio", "step_ms"),
                             ("return_ratio", "episode_return")):
                a, o = anchor.get(col), rec.get(col)
                rec[key] = o / a if a and o is not None else None
            records.append(rec)
            log(f"{impl} B={B}: {rec.get('step_ms')} ms")
        records.append(anchor)
    return records


def run(args: argparse.Namespace) -> int:
    records = measure(args)
    print(f"sampling MPC, pendulum swing-up, {args.dtype}, torch {torch.__version__}, "
          f"{args.threads} thread(s); *_ratio = ours / pytorch_mppi at the same batch "
          "(same run; below 1 is better for ours)")
    print_table(records, COLUMNS)
    if args.json:
        write_json(args.json, records)
        print(f"wrote {args.json}")
    return 0
