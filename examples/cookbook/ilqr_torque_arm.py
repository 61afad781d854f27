"""iLQR with torque commands on a planar arm's forward dynamics (seed 004 §11.3 and Appendix E; the cookbook's
``iLQR_manipulator_dynamics.py``).

Parameters: a 2-link planar arm (links 0.6 m, point masses 1 kg at their tips, joint friction 0.1, gravity
9.81 along ``-y``), time step ``Δt = 0.05``, horizon ``T = 30`` (1.5 s); four end-effector targets ``μ`` (a
batch); the arm starts hanging down at rest, ``x = (-π/2, 0)``.

System: the forward dynamics of Appendix E (Eq. 196-199, point masses at the link tips, in the absolute
angles ``q = Lx`` with torques ``u = L⁻ᵀ τ``): :class:`controllers.systems.PlanarArm`, state ``[x, ẋ]``,
control ``τ`` (joint torques), its discrete step (semi-implicit Euler, Eq. 199) with analytic Jacobians —
the same model the MPC and the environments use.

Solve: :func:`controllers.ilqr.ilqr` (Algorithm 5) on a :class:`~controllers.costs.ResidualCost`
``Σ_t f(x_t)ᵀ Q_t f(x_t) + Σ_t τ_tᵀ R τ_t`` with ``f(x) = [f^ee(x) - μ, ẋ]``, ``Q_t`` zero except at
``t = T`` (``10³`` on the position, ``10`` on the velocities: reach and stop) and ``R = 10⁻³ I`` (torques,
gravity included: nothing compensates it here, the plan holds the arm up by itself); 25 iterations from
zero torques.

Plot: the arm along each plan; the torques.

Checks:
  * ``targets_reached``: ``‖f^ee(x_T) - μ‖ < 1e-2`` m for every target;
  * ``stopped``: ``|ẋ_T| < 0.1`` rad/s;
  * ``torques_finite``: every torque finite (and the plan's states are the rollout of its torques through the
    arm's step, to ``1e-9``).
"""

from __future__ import annotations

import math
from pathlib import Path

import torch

SECTION = "11.3"
TITLE = "iLQR with torque commands (planar arm forward dynamics)"


def run(out: Path | None = None) -> dict:
    """Solve; write ``out / "ilqr_torque_arm.png"`` when ``out`` is given; return the outcomes."""
    from controllers.costs import ResidualCost
    from controllers.dynamics import rollout
    from controllers.ilqr import ILQROptions, ILQRProblem, ilqr
    from controllers.systems import PlanarArm

    f64 = torch.float64
    k, T = 2, 30
    arm = PlanarArm(links=k, lengths=0.6, masses=1.0, damping=0.1, gravity=9.81, dt=0.05)
    mu = torch.tensor([[0.8, 0.6], [-0.6, 0.7], [0.7, -0.4], [0.2, 0.9]], dtype=f64)
    x0 = torch.tensor([-math.pi / 2, 0.0, 0.0, 0.0], dtype=f64).expand(4, 2 * k)

    def residual(x):  # (*B, T+1, 2k) -> (*B, T+1, 2 + k)
        return torch.cat([arm.end_effector(x[..., :k]) - mu[:, None, :], x[..., k:]], -1)

    def jacobian(x):  # ∂f/∂x = [[J^ee, 0], [0, I]]
        top = torch.cat([arm.ee_jacobian(x[..., :k]), torch.zeros(*x.shape[:-1], 2, k, dtype=f64)], -1)
        eye = torch.cat([torch.zeros(k, k, dtype=f64), torch.eye(k, dtype=f64)], -1)
        return torch.cat([top, eye.expand(*x.shape[:-1], k, 2 * k)], -2)

    Q = torch.zeros(T + 1, 2 + k, 2 + k, dtype=f64)
    Q[-1] = torch.diag(torch.tensor([1e3, 1e3] + [10.0] * k, dtype=f64))
    cost = ResidualCost(residual=residual, Q=Q, R=1e-3 * torch.eye(k, dtype=f64), jacobian=jacobian)
    sol = ilqr(ILQRProblem(arm, cost, x0, T), grad="none", options=ILQROptions(max_iter=25))

    err = (arm.end_effector(sol.x[:, -1, :k]) - mu).norm(dim=-1)
    speed = sol.x[:, -1, k:].abs().max()
    replay = (rollout(arm, x0, sol.u) - sol.x).abs().max()
    if out is not None:
        _plot(out, arm, sol.x, sol.u, mu)
    return {"checks": {"targets_reached": bool((err < 1e-2).all()),
                       "stopped": bool(speed < 0.1),
                       "torques_finite": bool(torch.isfinite(sol.u).all() and replay < 1e-9)},
            "values": {"max_reach_error": float(err.max()), "max_final_speed": float(speed),
                       "max_abs_torque": float(sol.u.abs().max()),
                       "final_cost_mean": float(sol.cost.mean()),
                       "initial_cost_mean": float(sol.cost_history[0].mean()),
                       "certified": int(sol.status.converged.sum())}}


def _plot(out: Path, arm, x: torch.Tensor, u: torch.Tensor, mu: torch.Tensor) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    k = arm.links
    fig, axes = plt.subplots(1, 2, figsize=(6.5, 3))
    colors = plt.cm.tab10.colors
    for b in range(x.shape[0]):
        for t in range(0, x.shape[1], 8):
            p = arm.fk(x[b, t, :k])
            axes[0].plot(p[:, 0], p[:, 1], "-", color=colors[b], lw=0.8, alpha=0.3 + 0.7 * t / x.shape[1])
        axes[0].plot(mu[b, 0], mu[b, 1], "x", color=colors[b])
        axes[1].plot(u[b, :, 0], color=colors[b], lw=1)
    axes[0].set_aspect("equal")
    axes[0].set_title("§11.3 iLQR, torque control", fontsize=9)
    axes[1].set_xlabel("t")
    axes[1].set_ylabel("τ₁ [N m]")
    fig.tight_layout()
    fig.savefig(out / f"{Path(__file__).stem}.png", dpi=80)
    plt.close(fig)


if __name__ == "__main__":
    import json

    print(json.dumps(run(Path("out/cookbook")), indent=1))
