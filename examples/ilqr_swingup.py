"""iLQR swing-up under a torque limit, and the gradient of the optimum with respect to the model.

Story. A pendulum hangs at rest; its motor (|τ| ≤ 3 N m) is too weak to lift it straight up, so the
plan must pump energy by swinging back and forth. iLQR with control limits (Math Cookbook §8) finds
that plan for a whole batch of pendulums at once. Because the solver is differentiable, the optimal
cost's derivative with respect to each pendulum's length comes out of one backward pass (the
implicit gradient at the converged plan), which we check against central finite differences.

Steps:
1. parameters — the batch, the horizon, the torque limit;
2. system — ``controllers.systems.Pendulum`` with one length per pendulum (a tensor that requires
   grad, so each pendulum gets its own derivative), a quadratic cost towards upright (θ = π) with a
   heavy terminal weight;
3. solve — ``controllers.ilqr.ilqr`` on an ``ILQRProblem`` with ``u_lower``/``u_upper``;
4. report — how many end upright, the fraction of controls on the limit (the pumping), and the
   implicit gradient against finite differences.

Run:  python examples/ilqr_swingup.py [--batch 8]
"""

from __future__ import annotations

import argparse
import math

import torch

from controllers.costs import QuadraticCost
from controllers.ilqr import ILQROptions, ILQRProblem, ilqr
from controllers.systems import Pendulum

__all__ = ["main"]


def _problem(length: torch.Tensor, x0: torch.Tensor, horizon: int, u_max: float) -> ILQRProblem:
    f64 = dict(dtype=torch.float64)
    Q = torch.diag(torch.tensor([1.0, 0.1], **f64)).expand(horizon + 1, 2, 2).clone()
    Q[-1] *= 100                                               # upright and still at the end
    cost = QuadraticCost(Q=Q, R=torch.tensor([[0.01]], **f64), x_ref=torch.tensor([math.pi, 0.0], **f64))
    system = Pendulum(length=length, damping=0.1, dt=0.05)
    return ILQRProblem(system, cost, x0, horizon, u_lower=-u_max, u_upper=u_max)


def main(batch: int = 8, horizon: int = 100, u_max: float = 3.0, seed: int = 0) -> dict:
    """Run the example; returns the outcome of the swing-up and of the gradient check (also printed)."""
    g = torch.Generator().manual_seed(seed)
    x0 = 0.25 * (torch.rand(batch, 2, generator=g, dtype=torch.float64) - 0.5)  # near hanging, at rest
    length = torch.ones(batch, dtype=torch.float64, requires_grad=True)  # one (leaf) length per pendulum
    options = ILQROptions(max_iter=300, tol=1e-11, tol_cost=0.0)   # converged far below the FD step
    sol = ilqr(_problem(length, x0, horizon, u_max), options=options)
    (grad,) = torch.autograd.grad(sol.cost.sum(), length)
    h = 1e-5
    with torch.no_grad():
        plus, minus = (ilqr(_problem(length.detach() + s * h, x0, horizon, u_max), options=options,
                            grad="none").cost for s in (1, -1))
    fd = (plus - minus) / (2 * h)
    x = sol.x.detach()
    out = {
        "batch": batch,
        "upright": int((((x[:, -1, 0] - math.pi).abs() < 0.1) & (x[:, -1, 1].abs() < 0.5)).sum()),
        "converged": int(sol.status.converged.sum()),
        "max_abs_u": float(sol.u.detach().abs().max()),
        "on_limit_fraction": float(sol.clamped.double().mean()),
        "grad_rel_err_median": float(((grad - fd).abs() / fd.abs()).median()),
    }
    print(f"{out['upright']}/{batch} pendulums upright at the end ({out['converged']} converged); "
          f"max |u| {out['max_abs_u']:.3f} <= {u_max}, {100 * out['on_limit_fraction']:.0f} % of controls on "
          f"the limit; d(cost)/d(length): implicit vs finite differences, median relative error "
          f"{out['grad_rel_err_median']:.1e}")
    return out


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    main(batch=args.batch, seed=args.seed)
