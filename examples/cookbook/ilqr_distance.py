"""Reaching a distance to a target, or an ellipse's contour, by iLQR (seed 004 §9.8; the cookbook's
``iLQR_distMaintenance.py``).

A point mass in the plane under velocity commands (``x_{t+1} = x_t + Δt u_t``) must end on the circle of
radius ``r`` around ``μ`` — no particular point of it — and stay on it for the last 10 steps.  The residual is
``f = 1 - e``, ``e = ‖x_t - μ‖² / r²`` (0 on the circle, :func:`controllers.task_costs.distance`), with ``Q =
10³`` on the last 10 steps and ``R = 10⁻² I``.  A second batch asks for the contour of an ellipse ``(x - μ)ᵀ
Σ⁻¹ (x - μ) = 1`` instead.  8 starts around the target (inside and outside) are solved at once per batch.

Checks: every element CONVERGED (KKT residual certified; two ellipse starts, outside and off the axes, slide
slowly along the contour and take 120 iterations, the others 5 to 40); over the last 10 steps ``|‖x_t - μ‖ -
r| ≤ 10⁻³`` (circle) and ``|e(x_t) - 1| ≤ 2·10⁻³`` (ellipse); and each final point is the circle point nearest
its start within 0.05 (the cheapest motion under ``R``: the distance term has no preferred point).
"""

from __future__ import annotations

import math
from pathlib import Path

import torch

from controllers.dynamics import LinearDynamics
from controllers.ilqr import ILQROptions, ILQRProblem, ilqr
from controllers.task_costs import distance, residual_cost, state

SECTION = "9.8"
TITLE = "Reaching a distance to a target or an ellipse contour (point mass, iLQR)"

T, DT, HOLD = 40, 0.05, 10
MU = (1.0, 1.0)
RADIUS = 0.8
SIGMA = ((0.9, 0.3), (0.3, 0.25))


def starts(dtype=torch.float64) -> torch.Tensor:
    a = torch.arange(8, dtype=dtype) * (2 * math.pi / 8)
    rad = torch.tensor([0.2, 2.0] * 4, dtype=dtype)
    return torch.tensor(MU, dtype=dtype) + rad[:, None] * torch.stack([a.cos(), a.sin()], -1)


def problem(ellipse: bool, dtype=torch.float64) -> ILQRProblem:
    kw = dict(dtype=dtype)
    mu = torch.tensor(MU, **kw)
    if ellipse:
        term = distance(state(2), mu, Sigma=torch.tensor(SIGMA, **kw))
    else:
        term = distance(state(2), mu, RADIUS)
    Q = torch.zeros(T + 1, 1, 1, **kw)
    Q[-HOLD:] = 1e3
    eye = torch.eye(2, **kw)
    cost = residual_cost([(term, Q)], 1e-2 * eye)
    return ILQRProblem(LinearDynamics(eye, DT * eye), cost, starts(dtype), T)


def run(out: Path | None = None) -> dict:
    opts = ILQROptions(max_iter=150)
    circ = ilqr(problem(False), grad="none", options=opts)
    ell = ilqr(problem(True), grad="none", options=opts)
    mu = torch.tensor(MU, dtype=torch.float64)
    d = (circ.x[:, -HOLD:] - mu).norm(dim=-1)
    circle_err = (d - RADIUS).abs().amax(-1)
    P = torch.linalg.inv(torch.tensor(SIGMA, dtype=torch.float64))
    z = ell.x[:, -HOLD:] - mu
    ellipse_err = ((z @ P) * z).sum(-1).sub(1).abs().amax(-1)
    x0 = starts()
    nearest = mu + RADIUS * (x0 - mu) / (x0 - mu).norm(dim=-1, keepdim=True)
    off_nearest = (circ.x[:, -1] - nearest).norm(dim=-1)
    if out is not None:
        _plot(out, circ.x, ell.x)
    return {"checks": {"all_converged": bool(circ.status.converged.all() & ell.status.converged.all()),
                       "on_circle": bool((circle_err <= 1e-3).all()),
                       "on_ellipse": bool((ellipse_err <= 2e-3).all()),
                       "nearest_point_of_circle": bool((off_nearest <= 0.05).all())},
            "values": {"max_circle_error": float(circle_err.max()),
                       "max_ellipse_error": float(ellipse_err.max()),
                       "max_off_nearest": float(off_nearest.max()),
                       "max_iterations": int(max(circ.status.iterations.max(), ell.status.iterations.max()))}}


def _plot(out: Path, xc: torch.Tensor, xe: torch.Tensor) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    fig, axes = plt.subplots(1, 2, figsize=(6, 3))
    th = torch.linspace(0, 2 * math.pi, 100, dtype=torch.float64)
    ring = torch.stack([th.cos(), th.sin()], -1)
    mu = torch.tensor(MU, dtype=torch.float64)
    chol = torch.linalg.cholesky(torch.tensor(SIGMA, dtype=torch.float64))
    shapes = (mu + RADIUS * ring, mu + ring @ chol.mT)
    for ax, x, c, title in ((axes[0], xc, shapes[0], "circle"), (axes[1], xe, shapes[1], "ellipse")):
        ax.plot(c[:, 0], c[:, 1], color="tab:red")
        for b in range(x.shape[0]):
            ax.plot(x[b, :, 0], x[b, :, 1], color="k", lw=0.8)
            ax.plot(x[b, 0, 0], x[b, 0, 1], ".", color="0.5")
        ax.set_aspect("equal")
        ax.set_title(f"§9.8 {title}", fontsize=9)
    fig.tight_layout()
    fig.savefig(out / f"{Path(__file__).stem}.png", dpi=80)
    plt.close(fig)


if __name__ == "__main__":
    import json

    print(json.dumps(run(Path("out/cookbook")), indent=1))
