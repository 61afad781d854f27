"""Where to put the robot: initial-state (base placement) optimization in iLQR (seed 004 §9.4; the
cookbook's ``iLQR_manipulator_initStateOptim.py``).

A planar 3-link arm (lengths 2, 2, 1) sits on a mobile base, modelled as two prismatic joints in front of
the revolute ones: ``x = [b_1, b_2, q_1, q_2, q_3]``, end effector ``b + f^ee(q)`` (§4), velocity commands
``x_{t+1} = x_t + Δt u_t``.  Two via points must be reached with the end effector (at ``t = T/2`` and
``t = T``), and they are out of reach from the base's initial guess ``b̄ = (0, 0)``.

Following Eq. 109-110, the decision vector is ``ũ = [x_1; u]`` (:func:`controllers.ilqr_lifted.ilqr_lifted`
with ``x0_weight``): the cost ``Σ_i w̄_i (x_1,i - x̄_1,i)²`` has ``w̄ = 0`` on the base (free) and ``10⁶`` on
the joints (their start is given), and the control weight is ``10³`` on the prismatic joints (the base
must not move *during* the task) and ``10⁻³`` on the revolute ones.  A batch of 4 via-point pairs is
solved at once.

Checks: every element CONVERGED (gradient certified at the returned ``[x_1; u]``), every via point reached
within 10⁻², the base moves by less than 10⁻² during the motion, it was placed more than 1 away from
``b̄``, and the same problem with the base fixed at ``b̄`` ends with a cost at least 100× higher (the via
points are out of its reach).
"""

from __future__ import annotations

import math
from pathlib import Path

import torch

from controllers.dynamics import LinearDynamics
from controllers.ilqr import ILQRProblem
from controllers.ilqr_lifted import ilqr_lifted
from controllers.task_costs import Map, planar_ee, residual_cost

SECTION = "9.4"
TITLE = "Initial-state optimization: placing a mobile base (iLQR)"

LENGTHS = (2.0, 2.0, 1.0)
T, DT = 40, 0.05
Q0 = (math.pi / 2, -math.pi / 4, -math.pi / 4)


def via_points(dtype=torch.float64) -> torch.Tensor:
    """``(4, 2, 2)``: per problem, the via points at ``T/2`` and ``T``."""
    return torch.tensor([[[6.0, 4.0], [7.0, 2.5]], [[-5.0, 5.0], [-6.5, 3.5]],
                         [[5.0, -5.0], [3.5, -6.0]], [[8.0, 0.5], [8.0, -1.0]]], dtype=dtype)


def end_effector() -> Map:
    """``b + f^ee(q)`` of the base-and-arm chain and its Jacobian ``[I, J^ee(q)]``."""
    arm = planar_ee(LENGTHS, orientation=False)

    def f(x):
        return x[..., :2] + arm.f(x[..., 2:])

    def J(x):
        eye = torch.eye(2, dtype=x.dtype, device=x.device).expand(*x.shape[:-1], 2, 2)
        return torch.cat([eye, arm.J(x[..., 2:])], -1)

    return Map(f, J, 2)


def problem(dtype=torch.float64) -> ILQRProblem:
    kw = dict(dtype=dtype)
    via = via_points(dtype)
    mu = torch.zeros(via.shape[0], T + 1, 2, **kw)
    Q = torch.zeros(T + 1, 2, 2, **kw)
    for k, t in enumerate((T // 2, T)):
        mu[:, t] = via[:, k]
        Q[t] = 1e2 * torch.eye(2, **kw)
    ee = end_effector()
    track = Map(lambda x: ee.f(x) - mu, ee.J, 2)
    R = torch.diag(torch.tensor([1e3, 1e3, 1e-3, 1e-3, 1e-3], **kw))
    x0 = torch.tensor([0.0, 0.0, *Q0], **kw).expand(via.shape[0], 5)
    eye = torch.eye(5, **kw)
    return ILQRProblem(LinearDynamics(eye, DT * eye), residual_cost([(track, Q)], R), x0, T)


def run(out: Path | None = None) -> dict:
    prob = problem()
    wbar = torch.tensor([0.0, 0.0, 1e6, 1e6, 1e6], dtype=torch.float64)
    sol = ilqr_lifted(prob, x0_weight=wbar)
    fixed = ilqr_lifted(prob)
    ee = end_effector().f(sol.x)
    via = via_points()
    err = torch.stack([(ee[:, T // 2] - via[:, 0]).norm(dim=-1), (ee[:, T] - via[:, 1]).norm(dim=-1)], -1)
    base_drift = (sol.x[..., :2] - sol.x0[:, None, :2]).norm(dim=-1).amax(-1)
    placed = sol.x0[:, :2].norm(dim=-1)
    if out is not None:
        _plot(out, sol.x, fixed.x)
    return {"checks": {"all_converged": bool(sol.status.converged.all()),
                       "via_points_reached": bool((err < 1e-2).all()),
                       "base_still_during_motion": bool((base_drift < 1e-2).all()),
                       "base_moved_from_guess": bool((placed > 1.0).all()),
                       "fixed_base_costs_100x_more": bool((fixed.cost > 100 * sol.cost).all())},
            "values": {"max_via_error": float(err.max()), "max_base_drift": float(base_drift.max()),
                       "min_base_displacement": float(placed.min()),
                       "min_cost_ratio_fixed_over_free": float((fixed.cost / sol.cost).min()),
                       "max_iterations": int(sol.status.iterations.max())}}


def _plot(out: Path, x: torch.Tensor, x_fixed: torch.Tensor) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from controllers.systems.arm import PlanarArm

    out.mkdir(parents=True, exist_ok=True)
    arm = PlanarArm(links=3, lengths=LENGTHS)
    fig, ax = plt.subplots(figsize=(4, 4))
    via = via_points()
    for b in range(x.shape[0]):
        for t, shade in ((0, "0.7"), (T // 2, "0.45"), (T, "0.1")):
            p = arm.fk(x[b, t, 2:]) + x[b, t, :2]
            ax.plot(p[:, 0], p[:, 1], "-o", color=shade, ms=2, lw=1)
        ax.plot(x[b, 0, 0], x[b, 0, 1], "s", color="tab:green", ms=5)
        ax.plot(via[b, :, 0], via[b, :, 1], "x", color="tab:red")
    p = arm.fk(x_fixed[0, 0, 2:])
    ax.plot(p[:, 0], p[:, 1], "-", color="tab:blue", lw=1, alpha=0.5)
    ax.plot(0, 0, "s", color="tab:blue", ms=5)
    ax.set_aspect("equal")
    ax.set_title("§9.4 base placed by iLQR (green)", fontsize=9)
    fig.tight_layout()
    fig.savefig(out / f"{Path(__file__).stem}.png", dpi=80)
    plt.close(fig)


if __name__ == "__main__":
    import json

    print(json.dumps(run(Path("out/cookbook")), indent=1))
