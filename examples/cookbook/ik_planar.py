"""Inverse kinematics of a planar arm, position and orientation (seed 004 §4-§5; the cookbook's
``IK_manipulator.py``).

Parameters: a 3-link planar arm with link lengths ``ℓ = (2, 2, 1)`` (reach 5); a batch of 12 goals, each
an end-effector position ``μ`` and angle ``θ*``: 8 reachable poses (the forward kinematics of random joint
angles, so a solution exists) and 4 positions beyond the reach (distance 5.5 to 7 from the base).

System: the forward kinematics ``f^ee = [ℓᵀ cos(Lx), ℓᵀ sin(Lx), 1ᵀ x]`` (§4) and its Jacobian (§5),
:func:`controllers.planar_ik.planar_fk` / :func:`~controllers.planar_ik.planar_jacobian`.

Solve: :func:`controllers.planar_ik.planar_ik`, Gauss–Newton ``x ← x - J⁺ f(x)`` (Eq. 19) on the residual
``f = [f^ee_xy - μ, wrap(θ - θ*)]`` (the orientation part a geodesic residual, the log map of SO(2)), all 12
goals in one batch from the same start ``x0 = (0.3, 0.3, 0.3)``.

Plot: the arm at the start and at the solution of every goal, goals marked (reachable: green, unreachable:
red).

Checks:
  * ``reachable_reached``: every reachable goal is certified (``converged``) with position error and angle
    error below ``1e-6`` at the returned joint angles;
  * ``unreachable_flagged``: no unreachable goal is reported converged;
  * ``unreachable_near_boundary``: for those the position error equals the distance to the workspace
    (distance to the goal minus the reach) within ``1e-6``: the arm ends stretched towards the goal, at a
    stationary point of the cost (``STALLED``: a least-squares optimum with a non-zero residual; the
    Levenberg–Marquardt safeguard of the solver handles these large-residual, singular minima).
"""

from __future__ import annotations

import math
from pathlib import Path

import torch

SECTION = "5"
TITLE = "Inverse kinematics of a planar arm (position and orientation)"

LENGTHS = (2.0, 2.0, 1.0)


def goals() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(μ (12, 2), θ* (12,), reachable (12,))``."""
    from controllers.planar_ik import planar_fk

    f64 = torch.float64
    g = torch.Generator().manual_seed(4)
    q = math.pi * (2 * torch.rand(8, 3, generator=g, dtype=f64) - 1)
    pose = planar_fk(q, LENGTHS)
    ang = torch.tensor([0.3, 1.7, -2.2, 3.0], dtype=f64)
    rad = torch.tensor([5.5, 6.0, 6.5, 7.0], dtype=f64)
    far = torch.stack([rad * ang.cos(), rad * ang.sin()], -1)
    mu = torch.cat([pose[:, :2], far])
    theta = torch.cat([pose[:, 2], ang])
    reachable = torch.arange(12) < 8
    return mu, theta, reachable


def run(out: Path | None = None) -> dict:
    """Solve; write ``out / "ik_planar.png"`` when ``out`` is given; return the outcomes."""
    from controllers.planar_ik import planar_ik

    mu, theta, reachable = goals()
    q0 = torch.full((3,), 0.3, dtype=torch.float64)
    res = planar_ik(LENGTHS, mu, q0, orientation=theta, tol=1e-9, max_iter=100)
    r, u = reachable, ~reachable
    gap = res.pos_err[u] - (mu[u].norm(dim=-1) - sum(LENGTHS))
    if out is not None:
        _plot(out, res.q, q0, mu, reachable)
    return {"checks": {"reachable_reached": bool(res.converged[r].all() and (res.pos_err[r] < 1e-6).all()
                                                 and (res.rot_err[r] < 1e-6).all()),
                       "unreachable_flagged": bool(not res.converged[u].any()),
                       "unreachable_near_boundary": bool((gap.abs() < 1e-6).all())},
            "values": {"max_pos_err_reachable": float(res.pos_err[r].max()),
                       "max_rot_err_reachable": float(res.rot_err[r].max()),
                       "max_iterations_reachable": int(res.iterations[r].max()),
                       "max_gap_unreachable": float(gap.abs().max())}}


def _plot(out: Path, q: torch.Tensor, q0: torch.Tensor, mu: torch.Tensor, reachable: torch.Tensor) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from controllers.planar_ik import planar_fk_links

    out.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(4, 4))

    def draw(qi, color, lw):
        p = planar_fk_links(qi, LENGTHS)[:, :2]
        p = torch.cat([torch.zeros(1, 2, dtype=p.dtype), p])
        ax.plot(p[:, 0], p[:, 1], "-o", color=color, lw=lw, ms=2)

    draw(q0, "0.7", 2)
    for i in range(q.shape[0]):
        draw(q[i], "tab:green" if reachable[i] else "tab:red", 1)
    ax.plot(mu[reachable, 0], mu[reachable, 1], "x", color="tab:green")
    ax.plot(mu[~reachable, 0], mu[~reachable, 1], "x", color="tab:red")
    ax.add_patch(plt.Circle((0, 0), sum(LENGTHS), fill=False, ls="--", color="0.5"))
    ax.set_aspect("equal")
    ax.set_title("§5 Gauss-Newton IK (Eq. 19)", fontsize=9)
    fig.tight_layout()
    fig.savefig(out / f"{Path(__file__).stem}.png", dpi=80)
    plt.close(fig)


if __name__ == "__main__":
    import json

    print(json.dumps(run(Path("out/cookbook")), indent=1))
