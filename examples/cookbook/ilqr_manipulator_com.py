"""Reaching while keeping the centre of mass inside a box, by iLQR (seed 004 §9.5; the cookbook's
``iLQR_manipulator_CoM.py``).

A planar 4-link chain (a humanoid seen from the side, unit links standing upright from its foot at the origin)
is controlled by joint velocities, ``x_{t+1} = x_t + Δt u_t`` (§9.1).  With equal masses at the joints its
centre of mass is ``f^CoM = (1/D) Σ_j p_j`` (:func:`controllers.task_costs.planar_com`).  The task: the end
effector reaches ``μ_T`` (in front, 1.2 to 1.4 away, low: the body must lean back) at the end, while the CoM
stays over the feet, inside the box ``|f^CoM_1| ≤ 0.2`` (the transparent rectangle of Fig. 25), at every step.
Three residuals:

* reaching, ``f = f^ee(x_T) - μ_T`` with ``Q_T = 10³ I`` (position only);
* the CoM box, ``f = f^cut(f^CoM(x_t))`` with ``Q = 10⁴ I`` at every step (§9.3's bounded task space on the
  CoM map);
* control, ``R = 10⁻² I``.

A batch of 6 targets is solved at once, in two stages: the reach alone, then the whole cost from that plan (a
continuation: from the upright start the hinge residual holds some elements in poor local minima, 0.77 from
their target after 60 iterations; from the reaching plan all come within 2·10⁻⁴).  Checks: every target
reached within 2·10⁻², the CoM out of its box by at most 10⁻² at any time (a soft penalty), and — the regime —
the same reach without the CoM term takes the CoM out of the box by more than 0.05 for at least half of the
targets.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch

from controllers.dynamics import LinearDynamics
from controllers.ilqr import ILQROptions, ILQRProblem, ilqr
from controllers.task_costs import cut, planar_com, planar_ee, residual_cost, track

SECTION = "9.5"
TITLE = "Centre of mass kept in a box while reaching (planar humanoid, iLQR)"

LENGTHS = (1.0, 1.0, 1.0, 1.0)
T, DT = 30, 0.066
COM_HALF_WIDTH = 0.2


def targets(dtype=torch.float64) -> torch.Tensor:
    """Six end-effector targets in front of the chain, ``(6, 2)``."""
    x = torch.linspace(1.2, 1.4, 6, dtype=dtype)
    return torch.stack([x, torch.linspace(2.0, 1.2, 6, dtype=dtype)], -1)


def problem(with_com: bool = True, dtype=torch.float64) -> ILQRProblem:
    kw = dict(dtype=dtype)
    mu = targets(dtype)
    k = len(LENGTHS)
    x0 = torch.tensor([math.pi / 2, 0.0, 0.0, 0.0], **kw).expand(mu.shape[0], k)
    Qreach = torch.zeros(T + 1, 2, 2, **kw)
    Qreach[-1] = 1e3 * torch.eye(2, **kw)
    terms = [(track(planar_ee(LENGTHS, orientation=False), mu[:, None, :]), Qreach)]
    if with_com:
        box = cut(planar_com(LENGTHS), [-COM_HALF_WIDTH, -math.inf], [COM_HALF_WIDTH, math.inf])
        terms.append((box, 1e4 * torch.eye(2, **kw)))
    eye = torch.eye(k, **kw)
    return ILQRProblem(LinearDynamics(eye, DT * eye), residual_cost(terms, 1e-2 * eye), x0, T)


def com_excess(x: torch.Tensor) -> torch.Tensor:
    """How far the CoM is out of its box, worst time step, ``(B,)``."""
    c = planar_com(LENGTHS).f(x)[..., 0]
    return torch.relu(c.abs() - COM_HALF_WIDTH).amax(-1)


def run(out: Path | None = None) -> dict:
    free = ilqr(problem(with_com=False), grad="none", options=ILQROptions(max_iter=60))
    sol = ilqr(problem(), free.u, grad="none", options=ILQROptions(max_iter=60))
    ee = planar_ee(LENGTHS, orientation=False).f(sol.x[:, -1])
    err = (ee - targets()).norm(dim=-1)
    excess, excess_free = com_excess(sol.x), com_excess(free.x)
    if out is not None:
        _plot(out, sol.x, free.x)
    return {"checks": {"targets_reached": bool((err < 2e-2).all()),
                       "com_in_box": bool((excess <= 1e-2).all()),
                       "without_com_cost_com_leaves_box": bool((excess_free > 0.05).sum() >= 3)},
            "values": {"max_reach_error": float(err.max()), "max_com_excess": float(excess.max()),
                       "targets_com_out_without_com_cost": int((excess_free > 0.05).sum()),
                       "certified_at_1e-6": int(sol.status.converged.sum()),
                       "max_kkt_residual": float(sol.kkt_residual.max())}}


def _plot(out: Path, x: torch.Tensor, x_free: torch.Tensor) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from controllers.systems.arm import PlanarArm

    out.mkdir(parents=True, exist_ok=True)
    arm = PlanarArm(links=len(LENGTHS), lengths=LENGTHS)
    fig, axes = plt.subplots(1, 2, figsize=(6, 3), sharey=True)
    for ax, xs, title in ((axes[0], x, "with CoM box"), (axes[1], x_free, "without")):
        ax.axvspan(-COM_HALF_WIDTH, COM_HALF_WIDTH, color="tab:red", alpha=0.15)
        for b in (0, xs.shape[0] - 1):
            for t, shade in ((0, "0.7"), (-1, "0.2")):
                p = arm.fk(xs[b, t])
                ax.plot(p[:, 0], p[:, 1], "-o", color=shade, ms=2, lw=1)
            com = planar_com(LENGTHS).f(xs[b])
            ax.plot(com[:, 0], com[:, 1], color="tab:blue", lw=1)
        ax.plot(targets()[:, 0], targets()[:, 1], "x", color="tab:green")
        ax.set_aspect("equal")
        ax.set_title(f"§9.5 {title}", fontsize=9)
    fig.tight_layout()
    fig.savefig(out / f"{Path(__file__).stem}.png", dpi=80)
    plt.close(fig)


if __name__ == "__main__":
    import json

    print(json.dumps(run(Path("out/cookbook")), indent=1))
