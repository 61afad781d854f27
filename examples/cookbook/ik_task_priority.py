"""Inverse kinematics with task prioritization (seed 004 §5.2; the cookbook's ``IK_nullspace.py``).

Parameters: a 4-link planar arm, ``ℓ = (1, 1, 1, 1)``; 6 reachable end-effector positions ``μ`` (primary
task, 2 equations for 4 joints: a 2-dimensional null space); a preferred posture ``x_ref = (0.6, -0.4, 0.4,
-0.4)`` (secondary task ``f2 = x - x_ref``, ``J2 = I``); all solves start from the same ``x0``.

System: the planar forward kinematics and Jacobian of §4-§5
(:mod:`controllers.planar_ik`).

Solve:
  1. prioritized IK, :func:`controllers.planar_ik.task_priority_ik`: iterations of
     ``Δx = -J1⁺ f1 + N1 g`` (Eq. 22) with ``N1 = I - J1⁺ J1`` (the SVD form of §5.2) and
     ``g = -(J2 N1)⁺ (f2 - J2 J1⁺ f1)``, the secondary task's step inside the null space, until the primary
     residual is below ``1e-9`` and the secondary gradient projected into the null space below ``1e-8``;
  2. the same goals without the null-space term (:func:`controllers.planar_ik.planar_ik`, Eq. 19), for
     comparison;
  3. the controller of Fig. 12a: keep the end effector still (Eq. 21 on the current error) while the
     null space moves the first joint, ``u = -J⁺ f α/Δt + N [1, 0, 0, 0]ᵀ`` (``α = 0.5``), 150 steps of
     ``Δt = 0.01`` from the IK solution for the point ``(1, 0.8)``.

Plot: solutions with and without the secondary task; the Fig. 12a motion.

Checks:
  * ``primary_reached``: every goal certified, primary residual ``≤ 1e-9`` — with and without the
    secondary task (``primary_not_degraded``: with it, the residual is no larger than ``1e-9`` either);
  * ``secondary_improved``: ``‖x - x_ref‖`` is smaller with the null-space term than without, for every goal;
  * ``step_keeps_primary``: in one step from ``x0``, ``J1 Δx`` with and without the secondary term agree
    to ``1e-12`` (the secondary term lies in the null space);
  * ``fig12a_end_effector_still``: in the Fig. 12a motion the first joint turns by more than 0.5 rad while
    the end effector moves by less than ``1e-4``.
"""

from __future__ import annotations

from pathlib import Path

import torch

SECTION = "5.2"
TITLE = "Inverse kinematics with task prioritization (null space)"

LENGTHS = (1.0, 1.0, 1.0, 1.0)


def run(out: Path | None = None) -> dict:
    """Solve; write ``out / "ik_task_priority.png"`` when ``out`` is given; return the outcomes."""
    from controllers.planar_ik import (
        planar_fk,
        planar_ik,
        planar_residual,
        task_priority_ik,
        task_priority_ik_step,
    )

    f64 = torch.float64
    g = torch.Generator().manual_seed(5)
    qt = 2 * torch.rand(6, 4, generator=g, dtype=f64) - 1
    mu = planar_fk(qt, LENGTHS)[:, :2]
    x_ref = torch.tensor([0.6, -0.4, 0.4, -0.4], dtype=f64)
    x0 = torch.tensor([0.2, 0.2, 0.2, 0.2], dtype=f64)
    tol = 1e-9

    pri = task_priority_ik(LENGTHS, mu, x0, x_ref, tol=tol, tol_secondary=1e-8)
    plain = planar_ik(LENGTHS, mu, x0, tol=tol)
    d_pri, d_plain = (pri.q - x_ref).norm(dim=-1), (plain.q - x_ref).norm(dim=-1)

    f1, J1 = planar_residual(x0.expand(6, 4), LENGTHS, mu)
    eye = torch.eye(4, dtype=f64).expand(6, 4, 4)
    dq = task_priority_ik_step(J1, f1, eye, x0 - x_ref)
    dq0 = task_priority_ik_step(J1, f1)
    step_gap = (J1 @ (dq - dq0)[..., None]).abs().max()

    # Fig. 12a: hold the end effector, move the first joint (velocity commands, Eq. 21-22)
    dt, alpha, e1 = 0.01, 0.5, torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=f64)
    hold = torch.tensor([1.0, 0.8], dtype=f64)
    x = planar_ik(LENGTHS, hold, x0, tol=tol).q
    path = [x]
    for _ in range(150):
        f, J = planar_residual(x, LENGTHS, hold)
        u = task_priority_ik_step(J, f * alpha / dt, g=e1)
        x = x + dt * u
        path.append(x)
    path = torch.stack(path)
    drift = (planar_fk(path, LENGTHS)[:, :2] - hold).norm(dim=-1).max()
    turn = (path[-1, 0] - path[0, 0]).abs()

    if out is not None:
        _plot(out, pri.q, plain.q, mu, path)
    return {"checks": {"primary_reached": bool(pri.converged.all() and plain.converged.all()),
                       "primary_not_degraded": bool((pri.primary_residual <= tol).all()),
                       "secondary_improved": bool((d_pri < d_plain).all()),
                       "step_keeps_primary": bool(step_gap < 1e-12),
                       "fig12a_end_effector_still": bool(turn > 0.5 and drift < 1e-4)},
            "values": {"max_primary_residual": float(pri.primary_residual.max()),
                       "mean_secondary_distance_with": float(d_pri.mean()),
                       "mean_secondary_distance_without": float(d_plain.mean()),
                       "max_iterations": int(pri.iterations.max()),
                       "fig12a_joint1_turn": float(turn), "fig12a_drift": float(drift)}}


def _plot(out: Path, q_pri, q_plain, mu, path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from controllers.planar_ik import planar_fk_links

    out.mkdir(parents=True, exist_ok=True)
    fig, axes = plt.subplots(1, 2, figsize=(6, 3))

    def draw(ax, qi, color, lw=1.0):
        p = planar_fk_links(qi, LENGTHS)[:, :2]
        p = torch.cat([torch.zeros(1, 2, dtype=p.dtype), p])
        ax.plot(p[:, 0], p[:, 1], "-o", color=color, lw=lw, ms=2)

    for i in range(q_pri.shape[0]):
        draw(axes[0], q_plain[i], "0.6")
        draw(axes[0], q_pri[i], "tab:blue")
    axes[0].plot(mu[:, 0], mu[:, 1], "x", color="tab:red")
    axes[0].set_title("§5.2 with (blue) / without null space", fontsize=8)
    for t in range(0, path.shape[0], 20):
        draw(axes[1], path[t], plt.cm.viridis(t / path.shape[0]))
    axes[1].set_title("Fig. 12a: end effector still, joint 1 moves", fontsize=8)
    for ax in axes:
        ax.set_aspect("equal")
    fig.tight_layout()
    fig.savefig(out / f"{Path(__file__).stem}.png", dpi=80)
    plt.close(fig)


if __name__ == "__main__":
    import json

    print(json.dumps(run(Path("out/cookbook")), indent=1))
