"""Worker for tests/learning/test_distributed.py (issue 26 §6): run under torchrun, e.g.

    python -m torch.distributed.run --standalone --nproc_per_node=2 tests/learning/_ddp_worker.py --out r.pt

Fits the cost of a small known problem with :func:`learning.ioc.fit_cost` (L-BFGS through the implicit
Riccati gradients, and Adam through the lifted solve; 5 demos, so the 2 ranks hold 3 and 2) and runs
:func:`learning.evaluate.evaluate` on 7 seeds, then rank 0 writes the learned parameters, histories,
per-demo results, evaluation returns and the largest parameter difference between the ranks to ``--out``
(``torch.save``).  ``--device cuda`` (one GPU per rank) with ``--backend nccl`` runs the GPU path.  Without
torchrun it runs in one process (the reference the test compares with, via :func:`run`).
"""

from __future__ import annotations

import argparse
import json
import math

import numpy as np
import torch

from controllers.dynamics import LinearDynamics
from controllers.lqt_cookbook import double_integrator
from controllers.problem import LQProblem
from controllers.riccati import solve
from learning import distributed as dist_helpers
from learning.evaluate import evaluate, jsonable
from learning.ioc import LQTCostModel, SPDWeight, fit_cost

D64 = torch.float64
N_DEMOS, T, SEEDS = 5, 20, list(range(11, 18))


def problem(device: torch.device):
    """(dynamics, demos (5, T+1, 4), initial model) of a rotated planar double integrator (as in test_ioc)."""
    di = double_integrator(2, 0.1, D64)
    c, s = math.cos(0.5), math.sin(0.5)
    dyn = LinearDynamics(di.A, di.B @ torch.tensor([[c, -s], [s, c]], dtype=D64))
    dyn = LinearDynamics(dyn.A.to(device), dyn.B.to(device))
    target = torch.tensor([1.0, -0.5, 0.0, 0.0], dtype=D64, device=device)

    def model(q, r, tf, learn):
        return LQTCostModel(SPDWeight(q.to(device), learn=learn), SPDWeight(r.to(device), fix_first=True,
                            learn=learn), T, target=target, terminal_factor=tf, learn_terminal=learn)

    truth = model(torch.tensor([2.0, 0.5, 0.3, 0.1], dtype=D64), torch.tensor([1.0, 3.0], dtype=D64), 5.0,
                  False)
    x0 = torch.randn(N_DEMOS, 4, generator=torch.Generator().manual_seed(0), dtype=D64).to(device)
    with torch.no_grad():
        xd = solve(LQProblem(dyn, truth(), x0, horizon=T), grad="none").x
    init = model(torch.ones(4, dtype=D64), torch.ones(2, dtype=D64), 1.0, True)
    return dyn, xd, init


def _policy(obs: torch.Tensor) -> torch.Tensor:
    """A deterministic per-element feedback (each episode's actions depend on its own observation only)."""
    return torch.tanh(-2.0 * obs[..., 1:2] - 0.5 * obs[..., -1:])


def run(device: torch.device) -> dict:
    """Both fits and the evaluation; every rank returns the same dict."""
    dyn, xd, init = problem(device)
    out = {}
    for name, kw in (("lbfgs", dict(steps=15, optimizer="lbfgs", solver="riccati")),
                     ("adam", dict(steps=25, optimizer="adam", lr=0.1, solver="lifted"))):
        res = fit_cost(xd, dyn, init, **kw)
        flat = torch.cat([p.detach().reshape(-1) for p in res.model.parameters()])
        out[name] = {"params": {k: p.detach().cpu() for k, p in res.model.named_parameters()},
                     "flat": flat, "history": res.history, "loss": res.loss, "x": res.x.cpu(),
                     "usable": res.usable.cpu(), "reason": res.status.reason.cpu(),
                     "iterations": res.status.iterations.cpu()}
    ev = evaluate(_policy, "PendulumSwingUp", seeds=SEEDS, num_envs=2, max_episode_steps=15, device=device,
                  progress=False, timing_batch1=False)
    out["eval"] = {k: getattr(ev, k) for k in ("seeds", "returns", "final_error", "length", "success")}
    out["eval"]["error_curve"] = ev.error_curve
    out["eval"]["meta"] = ev.meta
    return out


def _rank_spread(flat: torch.Tensor) -> float:
    """Largest |difference| of the parameter vector between any rank and rank 0 (0.0 in one process)."""
    parts = dist_helpers.gather_objects(flat.cpu())
    return max(float((p - parts[0]).abs().max()) for p in parts)


def saveable(out: dict) -> dict:
    """``out`` with only tensors and plain values (``torch.load(..., weights_only=True)`` reads it): the
    evaluation's arrays as tensors, its ``meta`` as a JSON string."""
    ev = {k: torch.from_numpy(v) if isinstance(v, np.ndarray) else v for k, v in out["eval"].items()}
    ev["meta"] = json.dumps(jsonable(ev["meta"]))
    return {**out, "eval": ev}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", required=True)
    ap.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    ap.add_argument("--backend", default=None, choices=("gloo", "nccl"))
    a = ap.parse_args()
    torch.set_num_threads(1)
    device = dist_helpers.init_from_env(a.backend, a.device)
    try:
        out = run(device)
        spread = {k: _rank_spread(out[k]["flat"]) for k in ("lbfgs", "adam")}
        if dist_helpers.is_main():
            out["rank_spread"] = spread
            out["world_size"] = dist_helpers.world_size()
            out["backend"] = torch.distributed.get_backend() if dist_helpers.is_distributed() else None
            for k in ("lbfgs", "adam"):
                out[k]["flat"] = out[k]["flat"].cpu()
            torch.save(saveable(out), a.out)
    finally:
        dist_helpers.shutdown()


if __name__ == "__main__":
    main()
