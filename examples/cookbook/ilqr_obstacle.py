"""Reaching around ellipsoid obstacles by iLQR (seed 004 §9.7; the cookbook's ``iLQR_obstacle.py``).

A point mass in the plane under velocity commands, ``x_{t+1} = x_t + Δt u_t`` (§9.1 with ``A = I``, ``B = Δt
I``), starts from ``x_1`` and must reach ``μ_T`` at the last step.  Two ellipsoids ``(μ_k, Σ_k = V_k V_kᵀ)``
lie between.  The cost is Eq. 108's with three residuals:

* reaching, ``f = x_T - μ_T``, weight ``Q_T = 10² I`` at the end only;
* avoidance, ``f_k = max(0, 1 - e_k)``, ``e_k = (x_t - μ_k)ᵀ Σ_k⁻¹ (x_t - μ_k)``, weight ``10⁴`` at every step
  (:func:`controllers.task_costs.avoid`);
* control, ``uᵀ R u`` with ``R = 10⁻³ I``.

A batch of 12 starts (a line of them left of the obstacles) is solved at once by the recursive iLQR.  The
avoidance cost is soft (a penalty), so a path may graze an ellipsoid: the check allows a depth of ``1 - e ≤
0.02`` (2 % of the way from the boundary to the centre in the ellipsoid's metric).

Checks: every final position within 10⁻² of ``μ_T``, no state deeper than 0.02 in either obstacle, the
straight line from each start to ``μ_T`` *does* cross an obstacle for most starts (so the avoidance did
something).  Certification is *not* a check here, and the values record how far it got: the hinge makes the
Gauss-Newton curvature switch on and off as states cross an obstacle's boundary, so the model mispredicts,
steps are rejected and convergence turns slow (linear) after the first ten iterations — most elements end with
``MAX_ITERATIONS`` after 50 iterations and a relative KKT residual near 10⁻² (their cost within 10⁻⁴ of its
value after 100), honestly reported per element.
"""

from __future__ import annotations

from pathlib import Path

import torch

from controllers.dynamics import LinearDynamics
from controllers.ilqr import ILQROptions, ILQRProblem, ilqr
from controllers.task_costs import avoid, residual_cost, state, track

SECTION = "9.7"
TITLE = "Obstacle avoidance with ellipsoids (point mass, iLQR)"

T, DT = 50, 0.04
TARGET = (3.0, 3.0)
CENTERS = ((1.0, 1.2), (2.2, 2.0))
AXES = (((0.6, 0.3), (-0.15, 0.3)), ((0.5, -0.2), (0.1, 0.25)))  # columns of V_k: principal axes


def problem(batch: int = 12, dtype: torch.dtype = torch.float64):
    """The batch of reaching problems and the obstacles ``(μ (2, 2), Σ (2, 2, 2))``."""
    kw = dict(dtype=dtype)
    mu = torch.tensor(CENTERS, **kw)
    V = torch.tensor(AXES, **kw).mT  # the rows above are the axes; V has them as columns
    Sigma = V @ V.mT
    x0 = torch.stack([torch.zeros(batch, **kw), torch.linspace(-0.5, 1.5, batch, **kw)], -1)
    x0 = x0 + torch.stack([torch.linspace(0.0, 0.6, batch, **kw).flip(0), torch.zeros(batch, **kw)], -1)
    Qreach = torch.zeros(T + 1, 2, 2, **kw)
    Qreach[-1] = 1e2 * torch.eye(2, **kw)
    Qavoid = 1e4 * torch.eye(2, **kw)
    cost = residual_cost([(track(state(2), torch.tensor(TARGET, **kw)), Qreach),
                          (avoid(state(2), mu, Sigma), Qavoid)], 1e-3 * torch.eye(2, **kw))
    eye = torch.eye(2, **kw)
    return ILQRProblem(LinearDynamics(eye, DT * eye), cost, x0, T), mu, Sigma


def depth(x: torch.Tensor, mu: torch.Tensor, Sigma: torch.Tensor) -> torch.Tensor:
    """``max(0, 1 - e_k(x))`` per point and obstacle: 0 outside, 1 at a centre."""
    d = x.unsqueeze(-2) - mu
    e = (d * torch.linalg.solve(Sigma, d.unsqueeze(-1)).squeeze(-1)).sum(-1)
    return torch.relu(1 - e)


def run(out: Path | None = None) -> dict:
    prob, mu, Sigma = problem()
    sol = ilqr(prob, grad="none", options=ILQROptions(max_iter=50))
    final_err = (sol.x[:, -1] - torch.tensor(TARGET, dtype=sol.x.dtype)).norm(dim=-1)
    deepest = depth(sol.x, mu, Sigma).amax((-1, -2))
    s = torch.linspace(0, 1, 200, dtype=sol.x.dtype)[:, None]
    lines = prob.x0[:, None, :] * (1 - s) + torch.tensor(TARGET, dtype=sol.x.dtype) * s
    straight_hits = (depth(lines, mu, Sigma).amax((-1, -2)) > 0.02)
    if out is not None:
        _plot(out, sol.x, mu, Sigma)
    return {"checks": {                       "target_reached": bool((final_err < 1e-2).all()),
                       "obstacles_avoided": bool((deepest <= 0.02).all()),
                       "straight_line_would_collide": bool(straight_hits.float().mean() > 0.5)},
            "values": {"batch": int(prob.x0.shape[0]), "max_final_error": float(final_err.max()),
                       "max_depth": float(deepest.max()),
                       "straight_line_collisions": int(straight_hits.sum()),
                       "certified_at_1e-6": int(sol.status.converged.sum()),
                       "max_kkt_residual": float(sol.kkt_residual.max())}}


def _plot(out: Path, x: torch.Tensor, mu: torch.Tensor, Sigma: torch.Tensor) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(4, 4))
    th = torch.linspace(0, 2 * torch.pi, 100, dtype=mu.dtype)
    circle = torch.stack([th.cos(), th.sin()], -1)
    for k in range(mu.shape[0]):
        pts = mu[k] + circle @ torch.linalg.cholesky(Sigma[k]).mT
        ax.fill(pts[:, 0], pts[:, 1], color="tab:red", alpha=0.3)
    for b in range(x.shape[0]):
        ax.plot(x[b, :, 0], x[b, :, 1], color="k", lw=0.8)
    ax.plot(*TARGET, "o", color="tab:green")
    ax.set_aspect("equal")
    ax.set_title("§9.7 iLQR around ellipsoids", fontsize=9)
    fig.tight_layout()
    fig.savefig(out / f"{Path(__file__).stem}.png", dpi=80)
    plt.close(fig)


if __name__ == "__main__":
    import json

    print(json.dumps(run(Path("out/cookbook")), indent=1))
