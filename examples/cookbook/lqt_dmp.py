"""DMP reformulated as LQT with control primitives (seed 004 §7.7, Fig. 20; the cookbook's ``LQT_CP_DMP.py``).

Parameters: one demonstration of an "S" shape in the plane, ``T + 1 = 101`` samples at ``Δt = 0.01``; its
velocities and accelerations by finite differences (the movement ends at rest).  System: a point mass
with acceleration commands, ``x = [p; ṗ]``, ``A = I + A^c Δt``, ``B = B^c Δt`` (Eq. 192).

Cost (Eq. 59, as in §7.7): the end point ``[p_T; 0]`` with precision ``10⁶ I`` and the demonstrated
acceleration profile tracked with weight ``I`` on ``u_t - a_t``; the controls are ``u = Ψ w`` with 20
normalized radial basis functions per dimension (Eq. 66).  Solve: the open-loop plan is Eq. 62 with
primitives (:func:`controllers.lifted.solve_lifted` with ``Psi``); the feedback gains of the same cost
(Riccati on the augmented state, §7.5, Eq. 78) correct deviations from it:
``u_t = û_t + K_t (x_t - x̂_t)`` (:func:`controllers.lqt_cookbook.dmp_rollout`).

One batch of three reproductions: from the demonstrated start; from a start moved by ``(0.3, -0.2)``; and
from the demonstrated start with a push of ``(0.2, 0.2)`` (and a velocity kick) at ``T/4`` (Fig. 20).

Plot: demonstration (blue), nominal reproduction (dashed), the shifted start and the perturbed run (solid),
the perturbation (green), the goal (red).

Checks: the nominal reproduction follows the demonstration within 2·10⁻² everywhere (the basis functions'
resolution); the shifted start and the perturbed run end within 10⁻² of the demonstrated end point; and
the perturbation was real (the perturbed run left the nominal one by more than 0.2).
"""

from __future__ import annotations

import math
from pathlib import Path

import torch

from controllers.lqt_cookbook import dmp_lqt, dmp_rollout

SECTION = "7.7"
TITLE = "DMP as LQT with control primitives"

T, DT = 100, 0.01


def demonstration(dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """An "S" shape ``(T+1, 2)`` with a smooth (zero end velocity) time law."""
    s = torch.linspace(0.0, 1.0, T + 1, dtype=dtype)
    h = 10 * s**3 - 15 * s**4 + 6 * s**5
    return torch.stack([0.5 * torch.sin(2 * math.pi * h), 1.5 * h], -1)


def run(out: Path | None = None) -> dict:
    demo = demonstration()
    dmp = dmp_lqt(demo, DT, n_basis=20, goal_weight=1e6, accel_weight=1.0)
    x_nom, _ = dmp_rollout(dmp)
    start = dmp.plan.x[0] + torch.tensor([0.3, -0.2, 0.0, 0.0], dtype=demo.dtype)
    x0 = torch.stack([dmp.plan.x[0], start, dmp.plan.x[0]])  # a batch of three runs
    push = torch.tensor([[0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0], [0.2, 0.2, 0.5, -0.5]], dtype=demo.dtype)
    x, _ = dmp_rollout(dmp, x0=x0, perturbation=push, at=T // 4)
    reprod = (x_nom[:, :2] - demo).norm(dim=-1).max()
    final = (x[:, -1, :2] - demo[-1]).norm(dim=-1)
    deviation = (x[2, :, :2] - x_nom[:, :2]).norm(dim=-1).max()  # how far the push threw the run off
    if out is not None:
        _plot(out, demo, x_nom, x)
    return {"checks": {"reproduces_demo": bool(reprod < 2e-2),
                       "recovers_from_shifted_start": bool(final[1] < 1e-2),
                       "recovers_from_perturbation": bool(final[2] < 1e-2),
                       "perturbation_moved_the_run": bool(deviation > 0.2)},
            "values": {"max_reproduction_error": float(reprod), "final_error_nominal": float(final[0]),
                       "final_error_shifted_start": float(final[1]),
                       "final_error_perturbed": float(final[2]), "max_deviation_perturbed": float(deviation),
                       "n_basis": 20}}


def _plot(out: Path, demo: torch.Tensor, x_nom: torch.Tensor, x: torch.Tensor) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(4, 3))
    ax.plot(demo[:, 0], demo[:, 1], color="tab:blue", lw=3, alpha=0.4, label="demonstration")
    ax.plot(x_nom[:, 0], x_nom[:, 1], "k--", lw=1, label="reproduction")
    for b in (1, 2):
        ax.plot(x[b, :, 0], x[b, :, 1], color="k", lw=1)
        ax.plot(x[b, 0, 0], x[b, 0, 1], "ko", ms=3)
    ax.plot(x[2, T // 4 - 1:T // 4 + 1, 0], x[2, T // 4 - 1:T // 4 + 1, 1], color="tab:green", lw=2)
    ax.plot(demo[-1, 0], demo[-1, 1], "o", color="tab:red")
    ax.set_aspect("equal")
    ax.legend(fontsize=7)
    ax.set_title("§7.7 DMP as LQT with control primitives", fontsize=9)
    fig.tight_layout()
    fig.savefig(out / f"{Path(__file__).stem}.png", dpi=80)
    plt.close(fig)


if __name__ == "__main__":
    import json

    print(json.dumps(run(Path("out/cookbook")), indent=1))
