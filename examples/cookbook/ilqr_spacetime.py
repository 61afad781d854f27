"""Spacetime optimization: path and duration at once, by iLQR with a phase variable (seed 004 §9.13; the
cookbook's ``iLQR_spacetime.py``).

The augmented system of §9.13 (:class:`controllers.task_costs_ext.SpacetimeDynamics`): state ``[x, s]``,
control ``[u^x, u^s]``, ``x_{t+1} = A x_t + B u^x_t u^s_t``, ``s_{t+1} = s_t + u^s_t``, ``s_0 = 0``.  Here
``A = I``, ``B = I`` in the plane (the seed's example uses a double integrator; with a velocity-controlled
point mass ``u^x`` is a velocity, ``u^s_t`` the duration of step ``t`` and ``s_T`` the movement's duration,
exactly, which gives the closed-form reference below).  ``T = 20`` steps, two via points ``μ_1``, ``μ_2`` at
``t = 10`` and ``t = 20``.  The cost:

* via points ``Σ (x_t - μ)ᵀ 10³ (x_t - μ)`` at ``t = 10, 20`` (:func:`controllers.task_costs.track`);
* duration ``λ s_T²``, ``λ = 0.1`` (a residual on the phase);
* effort over scaled time ``Σ_t r ‖u^x_t‖² u^s_t``, ``r = 1`` (:class:`controllers.task_costs_ext.
  PhaseEffortCost`, Gauss-Newton derivatives), and ``Σ_t ρ (u^s_t)²``, ``ρ = 10`` (spreads the time evenly
  within a segment);
* ``u^s`` limited to ``[10⁻³, 1]``.

It is solved by the batch iLQR (Algorithm 4, ``method="batch"``, the limits as a box QP over the whole
control sequence), which converges here in 13-24 iterations where the recursive form takes 60-90.

Reference: at the optimum each segment (length ``L_i``, duration ``D_i``, ``N = 10`` steps) is straight at
constant speed with equal steps (for given durations that minimizes the convex ``Σ r d_k²/Δt_k + ρ Δt_k²``),
so the problem reduces to two numbers, ``min r (L_1²/D_1 + L_2²/D_2) + λ (D_1 + D_2)² + ρ (D_1² + D_2²)/N``,
solved by scipy.  A batch of two via-point pairs is solved from ``u^s = 0.1``, ``u^x = 0``, and again with the
timing fixed (``u^s = 0.15`` per step, duration 3).

Checks: every element CONVERGED; the via points reached within 10⁻²; each segment's duration within 1 % of
the reference; the steps even within a segment (largest over smallest ≤ 1.01); and the optimized timing
costs less than the fixed one.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch

from controllers.ilqr import ILQROptions, ILQRProblem, ilqr
from controllers.task_costs import on_joints, residual_cost, state, track
from controllers.task_costs_ext import CostSum, PhaseEffortCost, SpacetimeDynamics

SECTION = "9.13"
TITLE = "Spacetime optimization with a phase variable (iLQR)"

T, N = 20, 10
R_EFFORT, LAM, RHO = 1.0, 0.1, 10.0
VIAS = (((1.0, 0.5), (2.0, -0.5)), ((0.5, 1.5), (1.5, 1.0)))
FIXED_STEP = 0.15


def problem(fixed_timing: bool = False, dtype: torch.dtype = torch.float64) -> ILQRProblem:
    kw = dict(dtype=dtype)
    vias = torch.tensor(VIAS, **kw)
    mu = torch.zeros(vias.shape[0], T + 1, 2, **kw)
    Q = torch.zeros(T + 1, 2, 2, **kw)
    for k, t in enumerate((N, T)):
        mu[:, t] = vias[:, k]
        Q[t] = 1e3 * torch.eye(2, **kw)
    Qs = torch.zeros(T + 1, 1, 1, **kw)
    Qs[-1] = LAM
    R = torch.diag(torch.tensor([1e-8, 1e-8, RHO], **kw))
    cost = CostSum([residual_cost([(track(on_joints(state(2), [0, 1], 3), mu), Q),
                                   (on_joints(state(1), [2], 3), Qs)], R), PhaseEffortCost(R_EFFORT)])
    lo, hi = (FIXED_STEP, FIXED_STEP) if fixed_timing else (1e-3, 1.0)
    eye = torch.eye(2, **kw)
    return ILQRProblem(SpacetimeDynamics(eye, eye), cost, torch.zeros(vias.shape[0], 3, **kw), T,
                       u_lower=torch.tensor([-math.inf, -math.inf, lo], **kw),
                       u_upper=torch.tensor([math.inf, math.inf, hi], **kw))


def reference_durations() -> torch.Tensor:
    """``(B, 2)`` segment durations minimizing the reduced two-variable problem (module docstring), by
    scipy."""
    from scipy.optimize import minimize

    out = []
    for (a, b) in VIAS:
        L1, L2 = math.dist((0.0, 0.0), a), math.dist(a, b)

        def fun(d, L1=L1, L2=L2):
            return (R_EFFORT * (L1**2 / d[0] + L2**2 / d[1]) + LAM * (d[0] + d[1]) ** 2
                    + RHO * (d[0] ** 2 + d[1] ** 2) / N)

        out.append(minimize(fun, [1.0, 1.0], bounds=[(1e-3 * N, 1.0 * N)] * 2, method="L-BFGS-B",
                            options={"ftol": 1e-15, "gtol": 1e-12}).x.tolist())
    return torch.tensor(out, dtype=torch.float64)


def run(out: Path | None = None) -> dict:
    prob = problem()
    u0 = torch.zeros(len(VIAS), T, 3, dtype=torch.float64)
    u0[..., 2] = 0.1
    opts = ILQROptions(max_iter=150)
    sol = ilqr(prob, u0, method="batch", grad="none", options=opts)
    fixed = ilqr(problem(fixed_timing=True), method="batch", grad="none", options=opts)
    vias = torch.tensor(VIAS, dtype=sol.x.dtype)
    err = torch.stack([(sol.x[:, t, :2] - vias[:, k]).norm(dim=-1) for k, t in enumerate((N, T))], -1)
    s = sol.x[..., 2]
    dur = torch.stack([s[:, N], s[:, T] - s[:, N]], -1)
    ref = reference_durations()
    rel = ((dur - ref).abs() / ref).amax(-1)
    steps = sol.u[..., 2].reshape(len(VIAS), 2, N)
    spread = (steps.amax(-1) / steps.amin(-1)).amax(-1)
    if out is not None:
        _plot(out, sol, fixed)
    return {"checks": {"all_converged": bool(sol.status.converged.all() and fixed.status.converged.all()),
                       "via_points_reached": bool((err < 1e-2).all()),
                       "durations_match_reference": bool((rel <= 1e-2).all()),
                       "steps_even_within_segments": bool((spread <= 1.01).all()),
                       "optimized_timing_costs_less": bool((sol.cost < fixed.cost).all())},
            "values": {"max_via_error": float(err.max()), "max_duration_rel_error": float(rel.max()),
                       "duration": float(s[0, T]), "reference_duration": float(ref[0].sum()),
                       "max_step_spread": float(spread.max()),
                       "max_cost_ratio_to_fixed_timing": float((sol.cost / fixed.cost).max()),
                       "max_iterations": int(sol.status.iterations.max())}}


def _plot(out: Path, sol, fixed) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(7, 3.2))
    for b in range(sol.x.shape[0]):
        ax.plot(fixed.x[b, :, 0], fixed.x[b, :, 1], ":", color="0.6")
        ax.plot(sol.x[b, :, 0], sol.x[b, :, 1], "k.-", ms=3, lw=1)
        ax2.plot(sol.x[b, :, 2], label=f"via pair {b + 1}")
    v = torch.tensor(VIAS).reshape(-1, 2)
    ax.plot(v[:, 0], v[:, 1], "o", color="tab:red", ms=4)
    ax.set_aspect("equal")
    ax.set_title("§9.13 paths (dots: steps)", fontsize=8)
    ax2.plot(fixed.x[0, :, 2], ":", color="0.6", label="fixed timing")
    ax2.set_xlabel("t", fontsize=8)
    ax2.set_ylabel("phase s (time)", fontsize=8)
    ax2.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / f"{Path(__file__).stem}.png", dpi=80)
    plt.close(fig)


if __name__ == "__main__":
    import json

    print(json.dumps(run(Path("out/cookbook")), indent=1))
