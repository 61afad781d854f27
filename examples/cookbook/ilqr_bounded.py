"""Reaching an object with prismatic boundaries inside joint limits, by iLQR (seed 004 §9.2-9.3.1; the
cookbook's ``iLQR_manipulator.py`` with bounding boxes).

The cookbook's 3-link planar arm (lengths 2, 2, 1) under joint-velocity commands, ``x_{t+1} = x_t + Δt u_t``,
starts from ``x_1 = (3π/4, -π/2, -π/4)``.  Its end effector must end inside a rotated rectangular object
(centre ``μ``, axes ``U``, half-sizes ``h``): with ``e = Uᵀ(f^ee(x_T) - μ)`` the residual is ``f^cut(e)`` —
zero anywhere inside the object, the signed distance outside (§9.3.1, :func:`controllers.task_costs.cut` with
``center`` and ``frame``).  The joint angles must stay inside ``[x^min, x^max]`` at every step: ``f^cut(x_t)``
(§9.2).  Weights: object ``10⁴ I`` at ``T``, joint box ``10⁴ I`` at every step, ``R = 10⁻² I``.

A batch of 4 objects (positions and orientations) is solved at once, in two stages: the object alone, then
with the joint limits from that plan (a continuation).  Checks: the end effector ends inside every object
(within 10⁻³ of its boundary), the joint angles leave their box by at most 10⁻² at any step, and — the regime
— the plan without the joint limits leaves the box by more than 0.1 for at least half of the objects.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch

from controllers.dynamics import LinearDynamics
from controllers.ilqr import ILQROptions, ILQRProblem, ilqr
from controllers.task_costs import cut, planar_ee, residual_cost, state

SECTION = "9.3.1"
TITLE = "Joint limits and an object's prismatic boundaries (manipulator, iLQR)"

LENGTHS = (2.0, 2.0, 1.0)
X0 = (3 * math.pi / 4, -math.pi / 2, -math.pi / 4)
T, DT = 40, 0.05
HALF = (0.4, 0.15)  # object half-sizes along its axes
X_MIN = (1.6, -1.72, -0.82)
X_MAX = (2.6, 0.2, 0.6)


def objects(dtype=torch.float64) -> tuple[torch.Tensor, torch.Tensor]:
    """Centres ``(4, 2)`` and axes ``U (4, 2, 2)`` (columns) of the objects."""
    mu = torch.tensor([[2.0, 1.5], [2.5, 0.8], [1.5, 2.2], [3.0, 1.6]], dtype=dtype)
    a = torch.tensor([0.3, -0.6, 1.0, 0.0], dtype=dtype)
    U = torch.stack([torch.stack([a.cos(), -a.sin()], -1), torch.stack([a.sin(), a.cos()], -1)], -2)
    return mu, U


def problem(with_limits: bool = True, dtype=torch.float64) -> ILQRProblem:
    kw = dict(dtype=dtype)
    mu, U = objects(dtype)
    half = torch.tensor(HALF, **kw)
    Qobj = torch.zeros(T + 1, 2, 2, **kw)
    Qobj[-1] = 1e4 * torch.eye(2, **kw)
    ee = planar_ee(LENGTHS, orientation=False)
    terms = [(cut(ee, -half, half, center=mu[:, None, :], frame=U[:, None]), Qobj)]
    if with_limits:
        terms.append((cut(state(3), list(X_MIN), list(X_MAX)), 1e4 * torch.eye(3, **kw)))
    eye = torch.eye(3, **kw)
    x0 = torch.tensor(X0, **kw).expand(mu.shape[0], 3)
    return ILQRProblem(LinearDynamics(eye, DT * eye), residual_cost(terms, 1e-2 * eye), x0, T)


def outside_object(x_T: torch.Tensor) -> torch.Tensor:
    """How far the end effector is outside each object (0 inside), ``(B,)``."""
    mu, U = objects(x_T.dtype)
    e = ((planar_ee(LENGTHS, orientation=False).f(x_T) - mu).unsqueeze(-2) @ U).squeeze(-2)
    return torch.relu(e.abs() - torch.tensor(HALF, dtype=x_T.dtype)).norm(dim=-1)


def joint_excess(x: torch.Tensor) -> torch.Tensor:
    lo, hi = torch.tensor(X_MIN, dtype=x.dtype), torch.tensor(X_MAX, dtype=x.dtype)
    return torch.maximum(lo - x, x - hi).clamp_min(0).amax((-1, -2))


def run(out: Path | None = None) -> dict:
    free = ilqr(problem(with_limits=False), grad="none", options=ILQROptions(max_iter=60))
    sol = ilqr(problem(), free.u, grad="none", options=ILQROptions(max_iter=60))
    miss, excess, excess_free = outside_object(sol.x[:, -1]), joint_excess(sol.x), joint_excess(free.x)
    if out is not None:
        _plot(out, sol.x)
    return {"checks": {"inside_every_object": bool((miss <= 1e-3).all()),
                       "joint_limits_kept": bool((excess <= 1e-2).all()),
                       "without_limits_they_are_violated": bool((excess_free > 0.1).sum() >= 2)},
            "values": {"max_outside_object": float(miss.max()), "max_joint_excess": float(excess.max()),
                       "objects_violating_without_limits": int((excess_free > 0.1).sum()),
                       "certified_at_1e-6": int(sol.status.converged.sum()),
                       "max_kkt_residual": float(sol.kkt_residual.max())}}


def _plot(out: Path, x: torch.Tensor) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from controllers.systems.arm import PlanarArm

    out.mkdir(parents=True, exist_ok=True)
    arm = PlanarArm(links=3, lengths=LENGTHS)
    mu, U = objects(x.dtype)
    corners = torch.tensor([[1, 1], [-1, 1], [-1, -1], [1, -1], [1, 1]], dtype=x.dtype) * torch.tensor(HALF)
    fig, ax = plt.subplots(figsize=(4, 4))
    for b in range(x.shape[0]):
        c = mu[b] + corners @ U[b].mT
        ax.fill(c[:, 0], c[:, 1], color="tab:green", alpha=0.3)
        p = arm.fk(x[b, -1])
        ax.plot(p[:, 0], p[:, 1], "-o", color="0.2", ms=2, lw=1)
        tip = planar_ee(LENGTHS, orientation=False).f(x[b])
        ax.plot(tip[:, 0], tip[:, 1], color="tab:blue", lw=0.8)
    p = arm.fk(x[0, 0])
    ax.plot(p[:, 0], p[:, 1], "-o", color="0.7", ms=2, lw=1)
    ax.set_aspect("equal")
    ax.set_title("§9.2-9.3.1 joint limits, object boundaries", fontsize=9)
    fig.tight_layout()
    fig.savefig(out / f"{Path(__file__).stem}.png", dpi=80)
    plt.close(fig)


if __name__ == "__main__":
    import json

    print(json.dumps(run(Path("out/cookbook")), indent=1))
