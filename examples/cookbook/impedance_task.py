"""Impedance control in task space with gravity compensation (seed 004 §11.2; the cookbook's
``impedance_control.py``, task-space part).

Parameters: a 2-link planar arm (lengths 0.5 and 0.4 m, point masses 1 and 0.8 kg, joint friction 0.1,
gravity 9.81 along ``-y``, ``Δt = 0.02``, :class:`controllers.systems.PlanarArm`); three end-effector set
points ``f^d`` (a batch); the arm starts at rest at ``x = (0.3, 0.8)``.

System: the torque-controlled robot of Eq. 169 simulated by :func:`controllers.impedance.simulate`.

Solve: the control law of Eq. 172 for a set point (``ḟ^d = f̈^d = 0``),
``τ = Jᵀ (K^P (f^d - f) - K^V ḟ) + ĝ(x)`` with ``f`` the end-effector position, ``ḟ = J ẋ``,
``K^P = 200 I``, ``K^V = 30 I`` (:func:`controllers.impedance.task_impedance_torque`: the wrench ``w`` maps to
joint torques ``Jᵀ w``, the principle of virtual work); once with ``ĝ = g``, once without.

Plot: end-effector paths with and without gravity compensation.

Checks:
  * ``set_point_reached``: with gravity compensation ``‖f - f^d‖ < 1e-6`` m and ``|ẋ| < 1e-6`` after 6 s;
  * ``steady_state_error_without_compensation``: without it the arm rests (``|ẋ| < 1e-4``) more than 1 cm
    below the set point, where the task-space spring balances gravity, ``‖Jᵀ K^P (f^d - f) - g(x)‖ < 1e-4``.
"""

from __future__ import annotations

from pathlib import Path

import torch

SECTION = "11.2"
TITLE = "Impedance control in task space (gravity compensation)"


def run(out: Path | None = None) -> dict:
    """Simulate; write ``out / "impedance_task.png"`` when ``out`` is given; return the outcomes."""
    from controllers.impedance import simulate, task_impedance_torque
    from controllers.systems import PlanarArm

    f64 = torch.float64
    arm = PlanarArm(links=2, lengths=(0.5, 0.4), masses=(1.0, 0.8), damping=0.1, gravity=9.81, dt=0.02)
    f_ref = torch.tensor([[0.5, 0.3], [0.2, 0.6], [-0.3, 0.4]], dtype=f64)
    x0 = torch.tensor([0.3, 0.8, 0.0, 0.0], dtype=f64)
    KP, KV, steps = 200.0, 30.0, 300
    comp = simulate(arm, x0, lambda x, t: task_impedance_torque(arm, x, f_ref, KP, KV), steps)
    free = simulate(arm, x0, lambda x, t: task_impedance_torque(arm, x, f_ref, KP, KV,
                                                                gravity_compensation=False), steps)
    err_c = (arm.end_effector(comp.x[:, -1, :2]) - f_ref).norm(dim=-1)
    q_f = free.x[:, -1, :2]
    fee = arm.end_effector(q_f)
    err_f = (fee - f_ref).norm(dim=-1)
    J = arm.ee_jacobian(q_f)
    balance = ((J.mT @ (KP * (f_ref - fee))[..., None])[..., 0] - arm.gravity_torque(q_f)).norm(dim=-1)
    if out is not None:
        _plot(out, arm, comp.x, free.x, f_ref)
    still = comp.x[:, -1, 2:].abs().max() < 1e-6
    return {"checks": {"set_point_reached": bool((err_c < 1e-6).all() and still),
                       "steady_state_error_without_compensation": bool(
                           (err_f > 1e-2).all() and (fee[:, 1] < f_ref[:, 1]).all()
                           and free.x[:, -1, 2:].abs().max() < 1e-4 and (balance < 1e-4).all())},
            "values": {"final_error_compensated": float(err_c.max()),
                       "final_error_uncompensated": float(err_f.min()),
                       "spring_gravity_balance": float(balance.max()),
                       "max_torque": float(comp.u.abs().max())}}


def _plot(out: Path, arm, xc: torch.Tensor, xf: torch.Tensor, f_ref: torch.Tensor) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(4, 3))
    for b in range(xc.shape[0]):
        pc, pf = arm.end_effector(xc[b, :, :2]), arm.end_effector(xf[b, :, :2])
        ax.plot(pc[:, 0], pc[:, 1], color="tab:blue", lw=1, label="with ĝ" if b == 0 else None)
        ax.plot(pf[:, 0], pf[:, 1], color="tab:red", lw=1, label="without ĝ" if b == 0 else None)
        p = arm.fk(xc[b, -1, :2])
        ax.plot(p[:, 0], p[:, 1], "-o", color="0.5", ms=2, lw=1)
    ax.plot(f_ref[:, 0], f_ref[:, 1], "x", color="k")
    ax.set_aspect("equal")
    ax.set_title("§11.2 task-space impedance (Eq. 172)", fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / f"{Path(__file__).stem}.png", dpi=80)
    plt.close(fig)


if __name__ == "__main__":
    import json

    print(json.dumps(run(Path("out/cookbook")), indent=1))
