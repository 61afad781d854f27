"""Tracking a curvature by iLQR (seed 004 §9.11; the cookbook's ``iLQR_curvature.py``).

A point mass in the plane with state ``x = [x, ẋ, ẍ]`` (Eq. 113, ``n = 6``) driven by its jerk, the
triple integrator discretized exactly for a piecewise-constant jerk (``Δt = 0.05``, ``T = 50``)::

    x_{t+1} = [[I, Δt I, Δt²/2 I], [0, I, Δt I], [0, 0, I]] x_t + [Δt³/6 I; Δt²/2 I; Δt I] u_t.

The cost asks the path to have the curvature ``κ_d`` at every step,

    c = Σ_t 10² (κ(x_t) - κ_d)² + Σ_t u_tᵀ R u_t,    R = 10⁻⁶ I,

with ``κ(x) = (xᵀ S_B x)^{-3/2} xᵀ S_A x`` (Eq. 112-115) and its Jacobian (Eq. 116) from
:func:`controllers.task_costs_ext.curvature`, composed with :func:`controllers.task_costs.track`.  A batch of
four curvatures ``κ_d ∈ {0.5, 1, -1, 2}`` is solved at once, each from the origin heading along ``x₁`` at unit
speed with the centripetal acceleration ``κ_d`` (so the curvature is already ``κ_d`` at the fixed first step).
A path of constant curvature is a circle: of radius ``1/|κ_d|`` about ``(0, 1/κ_d)``.

Checks: every element CONVERGED; ``|κ(x_t) - κ_d| ≤ 10⁻⁴`` at every step; the positions on that circle,
``max_t | ‖p_t - c‖ - r | ≤ 10⁻² r`` (a geometric check independent of the curvature formula); the speed never
below 0.3 (the curvature stays well defined); and without the curvature term (zero jerk, the initial
acceleration kept: a parabola) the path leaves the circle by more than ``5·10⁻² r`` for every ``κ_d``.
"""

from __future__ import annotations

from pathlib import Path

import torch

from controllers.dynamics import LinearDynamics, rollout
from controllers.ilqr import ILQROptions, ILQRProblem, ilqr
from controllers.task_costs import residual_cost, track
from controllers.task_costs_ext import curvature

SECTION = "9.11"
TITLE = "Curvature tracking (point mass with jerk control, iLQR)"

T, DT = 50, 0.05
KAPPA = (0.5, 1.0, -1.0, 2.0)


def triple_integrator(dtype: torch.dtype = torch.float64) -> LinearDynamics:
    kw = dict(dtype=dtype)
    I, Z = torch.eye(2, **kw), torch.zeros(2, 2, **kw)
    A = torch.cat([torch.cat([I, DT * I, DT**2 / 2 * I], 1), torch.cat([Z, I, DT * I], 1),
                   torch.cat([Z, Z, I], 1)], 0)
    B = torch.cat([DT**3 / 6 * I, DT**2 / 2 * I, DT * I], 0)
    return LinearDynamics(A, B)


def problem(dtype: torch.dtype = torch.float64) -> ILQRProblem:
    kw = dict(dtype=dtype)
    kd = torch.tensor(KAPPA, **kw)
    x0 = torch.zeros(kd.shape[0], 6, **kw)
    x0[:, 2] = 1.0  # unit speed along x₁
    x0[:, 5] = kd  # centripetal acceleration κ_d v²
    cost = residual_cost([(track(curvature(), kd[:, None, None]), 1e2 * torch.eye(1, **kw))],
                         1e-6 * torch.eye(2, **kw))
    return ILQRProblem(triple_integrator(dtype), cost, x0, T)


def circle_error(x: torch.Tensor, kd: torch.Tensor) -> torch.Tensor:
    """``max_t | ‖p_t - c‖ - r | / r`` per element, ``c = (0, 1/κ_d)``, ``r = 1/|κ_d|``."""
    c = torch.stack([torch.zeros_like(kd), 1 / kd], -1)
    return ((x[..., :2] - c[:, None]).norm(dim=-1) - 1 / kd.abs()[:, None]).abs().amax(-1) * kd.abs()


def run(out: Path | None = None) -> dict:
    prob = problem()
    sol = ilqr(prob, grad="none", options=ILQROptions(max_iter=100))
    kd = torch.tensor(KAPPA, dtype=sol.x.dtype)
    kappa = curvature().f(sol.x)[..., 0]
    k_err = (kappa - kd[:, None]).abs().amax(-1)
    c_err = circle_error(sol.x, kd)
    speed = sol.x[..., 2:4].norm(dim=-1).amin(-1)
    x_free = rollout(prob.dynamics, prob.x0, torch.zeros_like(sol.u))  # zero jerk
    c_err_free = circle_error(x_free, kd)
    if out is not None:
        _plot(out, sol.x, x_free, kd)
    return {"checks": {"all_converged": bool(sol.status.converged.all()),
                       "curvature_tracked": bool((k_err <= 1e-4).all()),
                       "path_on_circle": bool((c_err <= 1e-2).all()),
                       "speed_kept": bool((speed >= 0.3).all()),
                       "off_circle_without_term": bool((c_err_free > 5e-2).all())},
            "values": {"max_curvature_error": float(k_err.max()), "max_circle_error": float(c_err.max()),
                       "min_speed": float(speed.min()),
                       "min_circle_error_without_term": float(c_err_free.min()),
                       "max_iterations": int(sol.status.iterations.max())}}


def _plot(out: Path, x: torch.Tensor, x_free: torch.Tensor, kd: torch.Tensor) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(4, 4))
    th = torch.linspace(0, 2 * torch.pi, 200, dtype=x.dtype)
    for b in range(x.shape[0]):
        r = 1 / float(kd[b].abs())
        ax.plot(r * th.cos(), 1 / float(kd[b]) + r * th.sin(), ":", color="0.7", lw=0.8)
        ax.plot(x_free[b, :, 0], x_free[b, :, 1], "--", color="tab:orange", lw=0.8)
        ax.plot(x[b, :, 0], x[b, :, 1], "k-", lw=1.2)
    ax.plot(0, 0, "ko", ms=4)
    ax.set_aspect("equal")
    ax.set_title("§9.11 curvature tracking (dashed: zero jerk)", fontsize=8)
    fig.tight_layout()
    fig.savefig(out / f"{Path(__file__).stem}.png", dpi=80)
    plt.close(fig)


if __name__ == "__main__":
    import json

    print(json.dumps(run(Path("out/cookbook")), indent=1))
