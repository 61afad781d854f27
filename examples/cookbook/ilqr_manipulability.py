"""Manipulability tracking with a geodesic cost on SPD matrices, by iLQR (seed 004 §9.9; the cookbook's
``iLQR_bimanual_manipulability.py``).

The bimanual robot of §9.6 (:func:`controllers.task_costs.bimanual_com`, the example ``ilqr_bimanual``) must
reach, at the end of the motion, a desired manipulability ``S`` of its centre of mass: ``M(x) = J^CoM(x)
J^CoM(x)ᵀ``, the ellipse of CoM velocities that unit joint velocities produce (Fig. 29).  The residual is Eq.
111's ``f = vec(log(S^{-1/2} M(x_T) S^{-1/2}))`` (:func:`controllers.task_costs.manipulability`: the whitened
Mandel coordinates of the SPD logarithm, so ``‖f‖`` is the affine-invariant geodesic distance), with ``Q_T =
10 I`` and ``R = 10⁻³ I``; its Jacobian is taken by autograd (the seed's script uses finite differences).
Each desired ``S`` is the manipulability of a pose the robot can take, so the optimum reaches it; a batch of 4
such targets is solved at once.

Checks: every element CONVERGED (12 to 35 iterations, one target 91: its last digits come slowly), the final
geodesic distance to ``S`` is below 10⁻² and below 1 % of the initial one.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch

from controllers.dynamics import LinearDynamics
from controllers.ilqr import ILQROptions, ILQRProblem, ilqr
from controllers.task_costs import BIMANUAL_LEFT, BIMANUAL_RIGHT, bimanual_com, manipulability, residual_cost
from torchlie.manifolds import spd_dist

SECTION = "9.9"
TITLE = "Manipulability tracking with an SPD geodesic cost (bimanual robot, iLQR)"

T, DT = 30, 0.05
LENGTHS = (1.5, 1.0, 1.0, 1.0, 1.0)  # torso, left upper and lower arm, right upper and lower arm
X0 = (math.pi / 2, math.pi / 2, math.pi / 4, -math.pi / 2, -math.pi / 4)


def desired(dtype=torch.float64) -> torch.Tensor:
    """``S (4, 2, 2)``: the CoM manipulability of 4 poses away from the start."""
    x0 = torch.tensor(X0, dtype=dtype)
    d = torch.tensor([[0.3, -0.8, 0.6, 0.9, -0.5], [-0.4, 0.5, 0.9, -0.6, 0.7],
                      [0.2, 0.9, -0.7, -0.3, 0.4], [-0.2, -0.6, -0.5, 1.0, 0.8]], dtype=dtype)
    J = bimanual_com(LENGTHS).J(x0 + d)
    return J @ J.mT


def problem(dtype=torch.float64) -> ILQRProblem:
    kw = dict(dtype=dtype)
    S = desired(dtype)
    x0 = torch.tensor(X0, **kw).expand(S.shape[0], 5)
    Q = torch.zeros(T + 1, 3, 3, **kw)
    Q[-1] = 10 * torch.eye(3, **kw)
    term = manipulability(bimanual_com(LENGTHS), S[:, None])
    eye = torch.eye(5, **kw)
    return ILQRProblem(LinearDynamics(eye, DT * eye), residual_cost([(term, Q)], 1e-3 * eye), x0, T)


def geodesic(x: torch.Tensor) -> torch.Tensor:
    J = bimanual_com(LENGTHS).J(x)
    return spd_dist(desired(x.dtype), J @ J.mT)


def run(out: Path | None = None) -> dict:
    prob = problem()
    sol = ilqr(prob, grad="none", options=ILQROptions(max_iter=100))
    d0, dT = geodesic(prob.x0), geodesic(sol.x[:, -1])
    if out is not None:
        _plot(out, sol.x)
    return {"checks": {"all_converged": bool(sol.status.converged.all()),
                       "reached": bool((dT < 1e-2).all()),
                       "reduced_100x": bool((dT < 1e-2 * d0).all())},
            "values": {"max_final_distance": float(dT.max()), "min_initial_distance": float(d0.min()),
                       "max_iterations": int(sol.status.iterations.max())}}


def _ellipse(M: torch.Tensor, c: torch.Tensor, scale: float = 0.5) -> torch.Tensor:
    th = torch.linspace(0, 2 * torch.pi, 60, dtype=M.dtype)
    return c + scale * torch.stack([th.cos(), th.sin()], -1) @ torch.linalg.cholesky(M).mT


def _chains(x: torch.Tensor) -> list[torch.Tensor]:
    from controllers.systems.arm import PlanarArm

    return [PlanarArm(links=3, lengths=[LENGTHS[j] for j in idx]).fk(x[list(idx)])
            for idx in (BIMANUAL_LEFT, BIMANUAL_RIGHT)]


def _plot(out: Path, x: torch.Tensor) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    S = desired(x.dtype)
    fig, axes = plt.subplots(1, x.shape[0], figsize=(2.2 * x.shape[0], 2.6))
    for b, ax in enumerate(axes):
        for t, shade in ((0, "0.75"), (-1, "0.2")):
            for pts in _chains(x[b, t]):
                ax.plot(pts[:, 0], pts[:, 1], "-o", color=shade, ms=2, lw=1)
        c = bimanual_com(LENGTHS).f(x[b, -1])
        J = bimanual_com(LENGTHS).J(x[b, -1])
        e = _ellipse(J @ J.mT, c)
        ax.plot(e[:, 0], e[:, 1], color="0.3")
        e = _ellipse(S[b], c)
        ax.plot(e[:, 0], e[:, 1], color="tab:red", ls="--")
        ax.set_aspect("equal")
        ax.set_xticks([])
        ax.set_yticks([])
    axes[0].set_title("§9.9 manipulability (red: desired)", fontsize=8, loc="left")
    fig.tight_layout()
    fig.savefig(out / f"{Path(__file__).stem}.png", dpi=80)
    plt.close(fig)


if __name__ == "__main__":
    import json

    print(json.dumps(run(Path("out/cookbook")), indent=1))
