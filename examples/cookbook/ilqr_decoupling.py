"""Decoupling of control commands by iLQR (seed 004 §9.10; the cookbook's ``iLQR_decoupling.py``).

A point mass in the plane under velocity commands, ``x_{t+1} = x_t + Δt u_t`` (``A = I``, ``B = Δt I``,
``Δt = 0.1``, ``T = 50``), starts at the origin and must reach a target ``μ`` at the last step.  The cost is

    c = (x_T - μ)ᵀ Q_T (x_T - μ) + Σ_t u_tᵀ R u_t + w Σ_t (u_{1,t} u_{2,t})²,

``Q_T = 10³ I``, ``R = 10⁻² I``, ``w = 10³``: the last term (:class:`controllers.task_costs_ext.
ControlProductCost`, residual ``f_t = u_{1,t} u_{2,t}``, Jacobian ``J_t = [u_{2,t}, u_{1,t}]``, Gauss-Newton
derivatives) asks that the two commands are never active together, so the point moves along one axis, then
the other.  It is added to the reaching cost (:func:`controllers.task_costs.residual_cost`) by
:class:`controllers.task_costs_ext.CostSum`.  From zero commands the decoupling term has zero gradient, so the
first iteration heads straight for the target and the later ones split the motion.  A batch of four targets is
solved at once, and again without the decoupling term.

Checks: every element CONVERGED (certified KKT residual), every target reached within 10⁻², the decoupling
ratio ``max_t |u_{1,t} u_{2,t}| / (max_t |u_{1,t}| · max_t |u_{2,t}|)`` below 10⁻² for every target, and
without the term that ratio is above 0.5 (the straight-line solution moves both axes at once, ratio 1), so
the term made it at least 50 times smaller.
"""

from __future__ import annotations

from pathlib import Path

import torch

from controllers.dynamics import LinearDynamics
from controllers.ilqr import ILQROptions, ILQRProblem, ilqr
from controllers.task_costs import residual_cost, state, track
from controllers.task_costs_ext import ControlProductCost, CostSum

SECTION = "9.10"
TITLE = "Decoupling of control commands (point mass, iLQR)"

T, DT = 50, 0.1
W = 1e3
TARGETS = ((2.0, 1.0), (1.0, 2.5), (-1.5, 2.0), (2.5, -0.5))


def problem(decouple: bool = True, dtype: torch.dtype = torch.float64) -> ILQRProblem:
    kw = dict(dtype=dtype)
    mu = torch.tensor(TARGETS, **kw)
    Q = torch.zeros(T + 1, 2, 2, **kw)
    Q[-1] = 1e3 * torch.eye(2, **kw)
    eye = torch.eye(2, **kw)
    cost = residual_cost([(track(state(2), mu[:, None, :]), Q)], 1e-2 * eye)
    if decouple:
        cost = CostSum([cost, ControlProductCost([(0, 1)], W)])
    return ILQRProblem(LinearDynamics(eye, DT * eye), cost, torch.zeros(mu.shape[0], 2, **kw), T)


def coupling_ratio(u: torch.Tensor) -> torch.Tensor:
    """``max_t |u_1 u_2| / (max_t |u_1| max_t |u_2|)`` per element: 0 when decoupled, 1 on a straight line."""
    prod = (u[..., 0] * u[..., 1]).abs().amax(-1)
    return prod / (u[..., 0].abs().amax(-1) * u[..., 1].abs().amax(-1))


def run(out: Path | None = None) -> dict:
    opts = ILQROptions(max_iter=60)
    sol = ilqr(problem(), grad="none", options=opts)
    free = ilqr(problem(decouple=False), grad="none", options=opts)
    err = (sol.x[:, -1] - torch.tensor(TARGETS, dtype=sol.x.dtype)).norm(dim=-1)
    ratio, ratio_free = coupling_ratio(sol.u), coupling_ratio(free.u)
    if out is not None:
        _plot(out, sol, free)
    return {"checks": {"all_converged": bool(sol.status.converged.all()),
                       "target_reached": bool((err < 1e-2).all()),
                       "commands_decoupled": bool((ratio < 1e-2).all()),
                       "coupled_without_term": bool((ratio_free > 0.5).all())},
            "values": {"max_target_error": float(err.max()), "max_coupling_ratio": float(ratio.max()),
                       "min_coupling_ratio_without_term": float(ratio_free.min()),
                       "max_iterations": int(sol.status.iterations.max())}}


def _plot(out: Path, sol, free) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(7, 3.2))
    for b in range(sol.x.shape[0]):
        ax.plot(free.x[b, :, 0], free.x[b, :, 1], ":", color="0.6", lw=1)
        ax.plot(sol.x[b, :, 0], sol.x[b, :, 1], "k-", lw=1)
    mu = torch.tensor(TARGETS)
    ax.plot(mu[:, 0], mu[:, 1], "o", color="tab:red", ms=4)
    ax.plot(0, 0, "ko", ms=4)
    ax.set_aspect("equal")
    ax.set_title("§9.10 paths (dotted: without the term)", fontsize=8)
    ax2.plot(sol.u[0, :, 0], label="u1")
    ax2.plot(sol.u[0, :, 1], label="u2")
    ax2.set_xlabel("t", fontsize=8)
    ax2.legend(fontsize=7)
    ax2.set_title("commands, first target", fontsize=8)
    fig.tight_layout()
    fig.savefig(out / f"{Path(__file__).stem}.png", dpi=80)
    plt.close(fig)


if __name__ == "__main__":
    import json

    print(json.dumps(run(Path("out/cookbook")), indent=1))
