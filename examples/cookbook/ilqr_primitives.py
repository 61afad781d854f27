"""iLQR with control primitives and a coordination matrix (seed 004 §9.12; the cookbook's
``iLQR_manipulator_CP.py``).

The cookbook manipulator (§9.1: 3 links of lengths 2, 2, 1, velocity commands, Δt = 0.01, two end-effector
via points at ``t = 25`` and ``t = 50``, ``R = 10⁻⁶ I``) is solved three ways by the batch iLQR of §8.1
(:func:`controllers.ilqr_lifted.ilqr_lifted`):

* on the whole control sequence (``Ψ = I``, 147 decision variables: Algorithm 4 itself);
* on ``K = 6`` radial basis functions per joint, ``u = Ψ w`` with ``Ψ = φ ⊗ I`` (Eq. 66 with
  :func:`controllers.basis.rbf` and :func:`controllers.lifted.control_primitives`): 18 variables;
* with a coordination matrix ``C`` that drives the last two joints with one command in opposite
  directions, ``Ψ = φ ⊗ C`` (12 variables): a synergy, which cannot reach both via points exactly.

The step in ``w`` is Eq. 108 with ``S_u`` replaced by ``S_u Ψ``.  Checks: every solve CONVERGED (gradient
in ``w`` certified at the returned point); the restricted solutions cost no less than the full one (they
optimize over a subspace) and the 6-primitive one at most 10 % more; every via point reached within 0.05
in position by the full and 6-primitive solutions (the orientation is traded against it by the cost);
the coordinated solution's last two joint velocities are opposite to 10⁻¹² and it costs more than the
uncoordinated one.  A batch of three starting poses is solved in one call per formulation.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch

from controllers.basis import rbf
from controllers.dynamics import LinearDynamics
from controllers.ilqr import ILQRProblem
from controllers.ilqr_lifted import ilqr_lifted
from controllers.lifted import control_primitives
from controllers.task_costs import planar_ee, residual_cost, track

SECTION = "9.12"
TITLE = "iLQR with control primitives and a coordination matrix (manipulator)"

LENGTHS = (2.0, 2.0, 1.0)
T, DT, K = 49, 1e-2, 6
VIA_T = (24, 49)
VIA = ((2.0, 1.0, -math.pi / 6), (3.0, 1.0, -math.pi / 3))


def starts(dtype=torch.float64) -> torch.Tensor:
    base = torch.tensor([3 * math.pi / 4, -math.pi / 2, -math.pi / 4], dtype=dtype)
    return torch.stack([base, base + torch.tensor([0.2, 0.0, 0.0], dtype=dtype),
                        base + torch.tensor([-0.2, 0.2, 0.0], dtype=dtype)])


def problem(dtype=torch.float64) -> ILQRProblem:
    kw = dict(dtype=dtype)
    mu = torch.zeros(T + 1, 3, **kw)
    Q = torch.zeros(T + 1, 3, 3, **kw)
    for t, v in zip(VIA_T, VIA):
        mu[t] = torch.tensor(v, **kw)
        Q[t] = torch.eye(3, **kw)
    eye = torch.eye(3, **kw)
    cost = residual_cost([(track(planar_ee(LENGTHS), mu), Q)], 1e-6 * eye)
    return ILQRProblem(LinearDynamics(eye, DT * eye), cost, starts(dtype), T)


def via_errors(x: torch.Tensor) -> torch.Tensor:
    """Position error at each via point, ``(B, 2)``."""
    ee = planar_ee(LENGTHS, orientation=False).f(x)
    return torch.stack([(ee[:, t] - torch.tensor(v[:2], dtype=x.dtype)).norm(dim=-1)
                        for t, v in zip(VIA_T, VIA)], -1)


def run(out: Path | None = None) -> dict:
    prob = problem()
    phi = rbf(T, K)
    C = torch.tensor([[1.0, 0.0], [0.0, 1.0], [0.0, -1.0]], dtype=torch.float64)
    sols = {"full": ilqr_lifted(prob), "primitives": ilqr_lifted(prob, control_primitives(phi, 3)),
            "coordinated": ilqr_lifted(prob, control_primitives(phi, 3, C))}
    cost = {k: s.cost for k, s in sols.items()}
    errs = torch.stack([via_errors(sols[k].x) for k in ("full", "primitives")])
    coupled = (sols["coordinated"].u[..., 1] + sols["coordinated"].u[..., 2]).abs().max()
    if out is not None:
        _plot(out, sols)
    return {"checks": {"all_converged": all(bool(s.status.converged.all()) for s in sols.values()),
                       "subspaces_cost_no_less": all(bool((cost[k] >= cost["full"] * (1 - 1e-12)).all())
                                                     for k in ("primitives", "coordinated")),
                       "primitives_within_10_percent": bool((cost["primitives"] <= 1.1 * cost["full"]).all()),
                       "via_points_reached": bool((errs < 0.05).all()),
                       "coordination_exact": bool(coupled <= 1e-12),
                       "coordination_costs_more": bool((cost["coordinated"] > cost["primitives"]).all())},
            "values": {"cost_full": float(cost["full"][0]), "cost_primitives": float(cost["primitives"][0]),
                       "cost_coordinated": float(cost["coordinated"][0]), "max_via_error": float(errs.max()),
                       "max_via_error_coordinated": float(via_errors(sols["coordinated"].x).max()),
                       "variables_full": T * 3, "variables_primitives": K * 3,
                       "variables_coordinated": K * 2}}


def _plot(out: Path, sols: dict) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    fig, axes = plt.subplots(1, 3, figsize=(7.5, 2.6), sharey=True)
    for ax, (name, s) in zip(axes, sols.items()):
        ax.plot(s.u[0].numpy())
        ax.set_title(f"§9.12 {name}", fontsize=9)
        ax.set_xlabel("t", fontsize=8)
    axes[0].set_ylabel("u (joint velocities)", fontsize=8)
    fig.tight_layout()
    fig.savefig(out / f"{Path(__file__).stem}.png", dpi=80)
    plt.close(fig)


if __name__ == "__main__":
    import json

    print(json.dumps(run(Path("out/cookbook")), indent=1))
