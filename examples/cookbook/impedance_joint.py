"""Impedance control in joint space with gravity compensation (seed 004 §11.1; the cookbook's
``impedance_control.py``).

Parameters: a 3-link planar arm, links of 0.5 m with 1 kg point masses at their tips, joint friction
``b = 0.1``, gravity ``9.81`` along ``-y``, ``Δt = 0.02`` (:class:`controllers.systems.PlanarArm`: the model
of Appendix E, the one the MPC uses); two set points ``x^d`` (a batch); the arm starts stretched
horizontally at rest.

System: the torque-controlled robot of Eq. 169, ``τ = M(x) ẍ + c(x, ẋ) + g(x) + h(x, ẋ)``, simulated by
:func:`controllers.impedance.simulate` (semi-implicit Euler of the forward dynamics).

Solve: the control law of Eq. 170 for a set point (``ẋ^d = ẍ^d = 0``),
``τ = K^JP (x^d - x) - K^JV ẋ + ĝ(x)`` (:func:`controllers.impedance.joint_impedance_torque`), with the
stiffness and damping matrices ``K^JP = 100 M(x^d)``, ``K^JV = 20 M(x^d)`` (critically damped at
10 rad/s); once with ``ĝ = g`` (:meth:`PlanarArm.gravity_torque`), once without.

Plot: joint errors over time, with and without gravity compensation.

Checks:
  * ``set_point_reached``: with gravity compensation, ``|x - x^d| < 1e-6`` rad and ``|ẋ| < 1e-6`` after 4 s
    (the closed loop of Eq. 171 rests at ``e = 0``);
  * ``steady_state_error_without_compensation``: without it, the arm comes to rest (``|ẋ| < 1e-4``) more than
    0.1 rad from ``x^d`` where the spring balances gravity, ``‖K^JP (x^d - x) - g(x)‖ < 1e-4``.
"""

from __future__ import annotations

from pathlib import Path

import torch

SECTION = "11.1"
TITLE = "Impedance control in joint space (gravity compensation)"


def run(out: Path | None = None) -> dict:
    """Simulate; write ``out / "impedance_joint.png"`` when ``out`` is given; return the outcomes."""
    from controllers.impedance import joint_impedance_torque, simulate
    from controllers.systems import PlanarArm

    f64 = torch.float64
    arm = PlanarArm(links=3, lengths=0.5, masses=1.0, damping=0.1, gravity=9.81, dt=0.02)
    q_ref = torch.tensor([[0.5, -0.3, 0.4], [1.2, 0.6, -0.9]], dtype=f64)
    M = arm.mass_matrix(q_ref)
    K, D = 100 * M, 20 * M
    x0 = torch.zeros(2, 6, dtype=f64)
    steps = 200
    comp = simulate(arm, x0, lambda x, t: joint_impedance_torque(arm, x, q_ref, K, D), steps)
    free = simulate(arm, x0, lambda x, t: joint_impedance_torque(arm, x, q_ref, K, D,
                                                                 gravity_compensation=False), steps)
    err_c = (comp.x[:, -1, :3] - q_ref).abs().max()
    vel_c = comp.x[:, -1, 3:].abs().max()
    q_f = free.x[:, -1, :3]
    err_f = (q_f - q_ref).norm(dim=-1)
    balance = ((K @ (q_ref - q_f)[..., None])[..., 0] - arm.gravity_torque(q_f)).norm(dim=-1)
    if out is not None:
        _plot(out, comp.x, free.x, q_ref, arm.dt)
    return {"checks": {"set_point_reached": bool(err_c < 1e-6 and vel_c < 1e-6),
                       "steady_state_error_without_compensation": bool(
                           (err_f > 0.1).all() and free.x[:, -1, 3:].abs().max() < 1e-4
                           and (balance < 1e-4).all())},
            "values": {"final_error_compensated": float(err_c),
                       "final_error_uncompensated": float(err_f.min()),
                       "spring_gravity_balance": float(balance.max()),
                       "max_torque": float(comp.u.abs().max())}}


def _plot(out: Path, xc: torch.Tensor, xf: torch.Tensor, q_ref: torch.Tensor, dt: float) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(4, 3))
    t = torch.arange(xc.shape[1]) * dt
    for b in range(xc.shape[0]):
        ax.semilogy(t, (xc[b, :, :3] - q_ref[b]).norm(dim=-1), color="tab:blue",
                    label="with ĝ" if b == 0 else None)
        ax.semilogy(t, (xf[b, :, :3] - q_ref[b]).norm(dim=-1), color="tab:red",
                    label="without ĝ" if b == 0 else None)
    ax.set_xlabel("t [s]")
    ax.set_ylabel("‖x - x^d‖ [rad]")
    ax.set_title("§11.1 joint impedance (Eq. 170)", fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / f"{Path(__file__).stem}.png", dpi=80)
    plt.close(fig)


if __name__ == "__main__":
    import json

    print(json.dumps(run(Path("out/cookbook")), indent=1))
