"""Feedback gains of a batch iLQR plan by least squares (seed 004 §8.3; the cookbook's
``iLQR_manipulator_recursive_LS.py``).

Parameters and system: the cookbook manipulator (a planar 3-link arm, lengths 2, 2, 1, velocity commands
``x_{t+1} = x_t + Δt u_t``, ``Δt = 10⁻²``, ``T = 49``) must bring its end effector (position and
orientation) to a via point at ``t = 24`` and another at ``t = 49``, with control weight ``r = 10⁻⁶``
(:func:`liecontrol.bench.solver.cookbook_problem`).

Solve: the plan ``(x̂, û)`` is the batch (open-loop) Gauss-Newton iLQR of Algorithm 4
(:func:`controllers.ilqr_lifted.ilqr_lifted`).  Its Hessian ``C`` and gradient ``c`` give the least-squares
map ``Δu = -F [Δx_1; 1]`` (Eq. 96-98, for a basis of initial deviations), and the forward recursion
``P_t = P_{t-1} (Ã_{t-1} - B̃_{t-1} K̃_{t-1})⁻¹``, ``K̃_t = F_t P_t`` (Eq. 99) turns it into time-varying
feedback gains (:func:`controllers.ilqr_lifted.lifted_feedback_gains`), used as the controller of Eq. 94,
``u_t = û_t + K_t (x_t - x̂_t)`` (our sign of ``K``).  Four perturbed starts ``x_1 + δ`` (``|δ_i| ≤ 0.25``
rad) are then run, batched, with that controller and with the plan's open-loop ``û``.

Checks: the plan is CONVERGED; the LS gains equal the Riccati gains of
:func:`controllers.ilqr.ilqr` (``method="recursive"``) at the same point within 1e-6 (relative to
``max |K|``); for every perturbed start the closed loop ends closer to the final via point than the open
loop, and within 0.01 of it (the plan itself ends 9e-4 away; open loop: > 0.3), and it is closer at the
first via point too.
The plot shows the end-effector paths: plan, open loop and closed loop from the perturbed starts.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import torch

from controllers.ilqr import ilqr
from controllers.ilqr_lifted import ilqr_lifted, lifted_feedback_gains
from liecontrol.bench.solver import cookbook_problem

SECTION = "8.3"
TITLE = "Least-squares feedback gains of batch iLQR (manipulator)"

PERTURBATIONS = ((0.25, -0.2, 0.1), (-0.2, 0.25, -0.15), (0.15, 0.15, 0.2), (-0.25, -0.1, -0.2))


def run(out: Path | None = None) -> dict:
    p = cookbook_problem()
    sol = ilqr_lifted(p)
    # Riccati gains (Algorithm 5's backward pass) at the plan, and the LS gains at the very same point
    ric = ilqr(p, sol.u, method="recursive", grad="none")
    same = dataclasses.replace(sol, x=ric.x.detach(), u=ric.u.detach(), w=ric.u.detach().flatten(-2))
    check = lifted_feedback_gains(p, same)
    gain_err = float((check.K - ric.K).abs().max() / ric.K.abs().max())
    K, k, amp = lifted_feedback_gains(p, sol)
    # perturbed starts, batched: closed loop (Eq. 94) against the open-loop plan
    x0 = p.x0 + torch.tensor(PERTURBATIONS, dtype=p.dtype)
    xc, xo = x0, x0
    path_c, path_o = [xc], [xo]
    for t in range(p.T):
        uc = (K[t] @ xc.unsqueeze(-1)).squeeze(-1) + k[t]
        xc = p.dynamics.step(xc, uc, t)
        xo = p.dynamics.step(xo, sol.u[t].expand_as(xo), t)
        path_c.append(xc)
        path_o.append(xo)
    Xc, Xo = torch.stack(path_c, -2), torch.stack(path_o, -2)
    # end effector (x, y) and orientation minus the via points, at t = 24 and t = T: (4, 2)
    via = [24, p.T]
    err_c = p.cost.residual(Xc)[:, via].norm(dim=-1)
    err_o = p.cost.residual(Xo)[:, via].norm(dim=-1)
    plan_err = p.cost.residual(sol.x)[via].norm(dim=-1)
    if out is not None:
        _plot(out, sol.x, Xo, Xc)
    return {"checks": {"plan_converged": bool(sol.status.converged.all()),
                       "ls_gains_equal_riccati_1e-6": gain_err < 1e-6,
                       "closed_loop_closer_at_final_via_point": bool((err_c[:, 1] < err_o[:, 1]).all()),
                       "closed_loop_within_0.01_of_final_via_point": bool((err_c[:, 1] < 0.01).all()),
                       "closed_loop_closer_at_first_via_point": bool((err_c[:, 0] < err_o[:, 0]).all())},
            "values": {"gain_rel_error_vs_riccati": gain_err, "eq99_amplification": float(amp),
                       "plan_first_via_error": float(plan_err[0]), "plan_final_via_error": float(plan_err[1]),
                       "max_final_error_closed_loop": float(err_c[:, 1].max()),
                       "min_final_error_open_loop": float(err_o[:, 1].min()),
                       "max_first_error_closed_loop": float(err_c[:, 0].max()),
                       "min_first_error_open_loop": float(err_o[:, 0].min())}}


def _plot(out: Path, plan: torch.Tensor, Xo: torch.Tensor, Xc: torch.Tensor) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from controllers.systems.arm import PlanarArm

    out.mkdir(parents=True, exist_ok=True)
    arm = PlanarArm(links=3, lengths=(2.0, 2.0, 1.0))
    fig, ax = plt.subplots(figsize=(4, 4))
    for t, shade in ((0, "0.7"), (24, "0.45"), (plan.shape[0] - 1, "0.1")):
        q = arm.fk(plan[t])
        ax.plot(q[:, 0], q[:, 1], "-o", color=shade, ms=2, lw=1)
    ee = arm.end_effector(plan)
    ax.plot(ee[:, 0], ee[:, 1], "k-", lw=1.5, label="plan")
    for b in range(Xo.shape[0]):
        eo, ec = arm.end_effector(Xo[b]), arm.end_effector(Xc[b])
        ax.plot(eo[:, 0], eo[:, 1], ":", color="tab:red", lw=1, label="open loop" if b == 0 else None)
        ax.plot(ec[:, 0], ec[:, 1], "-", color="tab:blue", lw=1, label="LS gains" if b == 0 else None)
    via = torch.tensor([[2.0, 1.0], [3.0, 1.0]])
    ax.plot(via[:, 0], via[:, 1], "x", color="tab:green", ms=8)
    ax.set_aspect("equal")
    ax.legend(fontsize=7)
    ax.set_title("§8.3 LS feedback gains, perturbed starts", fontsize=9)
    fig.tight_layout()
    fig.savefig(out / f"{Path(__file__).stem}.png", dpi=80)
    plt.close(fig)


if __name__ == "__main__":
    import json

    print(json.dumps(run(Path("out/cookbook")), indent=1))
