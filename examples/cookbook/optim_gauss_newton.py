"""Gauss–Newton: inverse kinematics of a planar 2-link arm as residual minimization (seed 004 §3.3).

Parameters: a 2-link planar arm with link lengths ``ℓ = (1, 0.7)``
(:class:`controllers.systems.arm.PlanarArm`); a batch of 24 target positions ``μ`` spread over the annulus
``0.35 ≤ ‖μ‖ ≤ 1.65`` (inside the workspace ``0.3 ≤ ‖μ‖ ≤ 1.7``, away from its singular boundary).

System: the residual ``f(x) = f^ee(x) − μ ∈ R²`` of the joint angles ``x ∈ R²`` (``f^ee`` the forward
kinematics of §4, ``PlanarArm.end_effector``), the cost ``c(x) = f(x)ᵀ f(x)``.

Solve: :func:`controllers.optim.gauss_newton`, ``x_{k+1} = x_k − α J(x_k)† f(x_k)`` (Eq. 10) with the
backtracking line search of Algorithm 1, all 24 targets in one batched call from the same start
``x_1 = (0.3, 0.3)``; once with the Jacobian by :mod:`torch.func`, once with the analytic
``PlanarArm.ee_jacobian``, and once with a Levenberg damping ``λ = 1e-3`` (``Δx = −(JᵀJ + λI)⁻¹ Jᵀ f``).

Reference: the closed-form IK of a 2-link arm (law of cosines), whose two elbow branches are
``x₂ = ±acos((‖μ‖² − ℓ₁² − ℓ₂²)/(2ℓ₁ℓ₂))``, ``x₁ = atan2(μ_y, μ_x) − atan2(ℓ₂ sin x₂, ℓ₁ + ℓ₂ cos x₂)``.

Plot: the arm at every solution with its target.

Checks:
  * ``residual_below_tol``: every element of the batch is certified (``converged``: ``‖2Jᵀf‖ ≤ 1e-12`` at the
    returned ``x``) and its residual ``‖f(x)‖`` is below ``1e-10``, in all three runs;
  * ``matches_closed_form``: every solution equals one of the two closed-form branches within ``1e-8`` rad
    (angles compared modulo 2π);
  * ``analytic_jacobian_agrees``: the run with the analytic Jacobian returns the same joint angles within
    ``1e-9`` rad.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch

SECTION = "3.3"
TITLE = "Gauss–Newton: planar 2-link inverse kinematics"

F64 = torch.float64
LENGTHS = (1.0, 0.7)


def targets(n: int = 24) -> torch.Tensor:
    """``μ (n, 2)``: radii and angles on a deterministic spiral through the annulus."""
    k = torch.arange(n, dtype=F64)
    rad = 0.35 + 1.3 * (k + 0.5) / n
    ang = 2.399963 * k  # golden angle
    return torch.stack([rad * ang.cos(), rad * ang.sin()], -1)


def closed_form(mu: torch.Tensor) -> torch.Tensor:
    """Both elbow branches ``(2, n, 2)`` of the 2-link IK."""
    l1, l2 = LENGTHS
    c2 = ((mu ** 2).sum(-1) - l1 ** 2 - l2 ** 2) / (2 * l1 * l2)
    sols = []
    for sign in (1.0, -1.0):
        q2 = sign * torch.acos(c2.clamp(-1, 1))
        q1 = torch.atan2(mu[:, 1], mu[:, 0]) - torch.atan2(l2 * q2.sin(), l1 + l2 * q2.cos())
        sols.append(torch.stack([q1, q2], -1))
    return torch.stack(sols)


def _angle_gap(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    d = torch.remainder(a - b + math.pi, 2 * math.pi) - math.pi
    return d.abs().amax(-1)


def run(out: Path | None = None) -> dict:
    """Solve; write ``out / "optim_gauss_newton.png"`` when ``out`` is given; return the outcomes."""
    from controllers.optim import gauss_newton
    from controllers.systems.arm import PlanarArm

    arm = PlanarArm(links=2, lengths=LENGTHS)
    mu = targets()
    x0 = torch.tensor([0.3, 0.3], dtype=F64).expand(mu.shape[0], 2)

    def residual(x: torch.Tensor) -> torch.Tensor:
        return arm.end_effector(x) - mu

    runs = {
        "autodiff": gauss_newton(residual, x0, tol=1e-12),
        "analytic": gauss_newton(residual, x0, tol=1e-12, jacobian=arm.ee_jacobian),
        "damped": gauss_newton(residual, x0, tol=1e-12, damping=1e-3, max_iter=200),
    }
    res_norm = {k: float(residual(r.x).norm(dim=-1).max()) for k, r in runs.items()}
    ok = all(bool(r.converged.all()) for r in runs.values()) and max(res_norm.values()) < 1e-10
    branches = closed_form(mu)
    gaps = {k: float(torch.minimum(_angle_gap(r.x, branches[0]), _angle_gap(r.x, branches[1])).max())
            for k, r in runs.items()}
    agree = float(_angle_gap(runs["autodiff"].x, runs["analytic"].x).max())
    x = runs["autodiff"].x
    if out is not None:
        _plot(out, arm, x, mu)
    return {
        "checks": {
            "residual_below_tol": ok,
            "matches_closed_form": max(gaps.values()) <= 1e-8,
            "analytic_jacobian_agrees": agree <= 1e-9,
        },
        "values": {
            "batch": int(mu.shape[0]),
            "max_residual": max(res_norm.values()),
            "max_closed_form_gap": max(gaps.values()),
            "analytic_vs_autodiff": agree,
            "max_iterations": int(runs["autodiff"].iterations.max()),
            "max_iterations_damped": int(runs["damped"].iterations.max()),
            "elbow_up_count": int((x[:, 1] > 0).sum()),
        },
    }


def _plot(out: Path, arm, x: torch.Tensor, mu: torch.Tensor) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(4, 4))
    pts = arm.fk(x)
    for p in pts:
        ax.plot(p[:, 0], p[:, 1], "-", color="0.5", lw=0.8)
    ax.plot(pts[:, -1, 0], pts[:, -1, 1], "o", color="tab:blue", ms=3, label="end effector")
    ax.plot(mu[:, 0], mu[:, 1], "x", color="tab:red", ms=6, label="targets μ")
    t = torch.linspace(0, 2 * math.pi, 200)
    for r in (0.3, 1.7):
        ax.plot(r * t.cos(), r * t.sin(), "k:", lw=0.6)
    ax.set(aspect="equal", title="Gauss–Newton IK, 24 targets in one batch")
    ax.legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    fig.savefig(out / f"{Path(__file__).stem}.png", dpi=80)
    plt.close(fig)


if __name__ == "__main__":
    import json

    print(json.dumps(run(Path("out/cookbook")), indent=1))
