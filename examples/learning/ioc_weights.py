"""Inverse optimal control: recover LQT cost weights and a via point from demonstrations (issue 26 §2;
seed 004 §7.1-7.2, Eq. 59-62).

Parameters: a planar double integrator ``x = [p; ṗ]``, ``u = p̈`` (Eq. 192, ``Δt = 0.1``, ``T = 30``) whose
control axes are rotated by 0.5 rad (so that a diagonal cost does not split it into two independent axes,
each with its own unidentifiable cost scale).  The expert's cost (Eq. 59)::

    Σ_t (x_t - g)ᵀ Q_t (x_t - g) + Σ_t u_tᵀ R u_t + Σ_t κ(t) (x_t - m)ᵀ P (x_t - m)

with ``Q = diag(2, 0.5, 0.3, 0.1)`` for ``t < T``, ``Q_T = 5 Q``, ``R = diag(1, 3)``, a goal ``g``, and a
via point ``m = (0.6, 1.1)`` (positions, ``P = diag(40, 40, 0, 0)``) at the continuous time ``τ = 12.4``
spread by a normalized Gaussian kernel ``κ`` of width 1.5 steps.

Demos: 8 optimal trajectories from random starts (one batched Riccati solve, :mod:`controllers.riccati`).

Learning (:func:`learning.ioc.fit_cost`): a cost model started at ``Q = I``, ``R = I``, ``ρ = 1``, the via
point at the origin and ``τ = 10``; ``R_00 = 1`` fixed (the whole cost's scale is unidentifiable: scaling
it changes no optimal trajectory); L-BFGS on the mean squared state error between the model's optimal
trajectories (batch least squares, Eq. 62, autograd through its Cholesky solve) and the demos.

Plot: the demos (grey), the learned cost's reproductions (dashed), the true and learned via points; the
loss per evaluation.

Outcome checks: ``weights_recovered`` — the relative error of ``(diag Q, diag R, ρ)`` below ``10⁻³``;
``via_point_recovered`` — the via point's target within ``10⁻³`` and its time within ``0.05`` step;
``reproduction_matches_demos`` — the learned cost's optimal trajectories within an RMS of ``10⁻⁴`` of the
demos; ``all_solves_converged`` — every demo's final solve succeeded.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch

from controllers.dynamics import LinearDynamics
from controllers.lqt_cookbook import double_integrator
from controllers.problem import LQProblem
from controllers.riccati import solve
from learning.ioc import LQTCostModel, SPDWeight, ViaPoints, fit_cost

SECTION = "7.1"
TITLE = "Inverse optimal control: LQT weights and a via point from demos"


def _model(q, r, tf, m, tau, learn, T, goal, P):
    vp = ViaPoints(m, torch.tensor([tau], dtype=m.dtype), P, kernel="gaussian", width=1.5,
                   learn_targets=learn, learn_times=learn)
    return LQTCostModel(SPDWeight(q, learn=learn), SPDWeight(r, fix_first=True, learn=learn), T, target=goal,
                        terminal_factor=tf, learn_terminal=learn, via_points=vp)


def run(out: Path | None = None) -> dict:
    """Generate demos, fit the cost, write ``out / "ioc_weights.png"`` when ``out`` is given."""
    dt, T, N = 0.1, 30, 8
    kw = dict(dtype=torch.float64)
    di = double_integrator(2, dt)
    c, s = math.cos(0.5), math.sin(0.5)
    dyn = LinearDynamics(di.A, di.B @ torch.tensor([[c, -s], [s, c]], **kw))
    goal = torch.tensor([1.0, -0.5, 0.0, 0.0], **kw)
    P = torch.diag(torch.tensor([40.0, 40.0, 0.0, 0.0], **kw))
    q_true, r_true, tf_true = torch.tensor([2.0, 0.5, 0.3, 0.1], **kw), torch.tensor([1.0, 3.0], **kw), 5.0
    m_true, tau_true = torch.tensor([[0.6, 1.1, 0.0, 0.0]], **kw), 12.4
    truth = _model(q_true, r_true, tf_true, m_true, tau_true, False, T, goal, P)
    g = torch.Generator().manual_seed(0)
    x0 = 0.5 * torch.randn(N, 4, generator=g, **kw)
    with torch.no_grad():
        demo = solve(LQProblem(dyn, truth(), x0, horizon=T), grad="none")
    init = _model(torch.ones(4, **kw), torch.ones(2, **kw), 1.0, torch.zeros(1, 4, **kw), 10.0, True, T, goal,
                  P)
    res = fit_cost(demo.x, dyn, init, steps=80, solver="lifted")
    w = res.model.weights()
    est = torch.cat([w["Q"].diagonal(), w["R"].diagonal(), w["terminal_factor"].reshape(1)])
    ref = torch.cat([q_true, r_true, torch.tensor([tf_true], **kw)])
    rel = float((est - ref).norm() / ref.norm())
    t_err = abs(float(w["via_times"][0]) - tau_true)
    m_err = float((w["via_targets"][0, :2] - m_true[0, :2]).abs().max())
    rmse = float(((res.x - demo.x) ** 2).mean().sqrt())
    if out is not None:
        _plot(out, demo.x, res.x, m_true[0, :2], w["via_targets"][0, :2], res.history["loss"])
    return {"checks": {"weights_recovered": rel < 1e-3,
                       "via_point_recovered": m_err < 1e-3 and t_err < 0.05,
                       "reproduction_matches_demos": rmse < 1e-4,
                       "all_solves_converged": bool(res.status.converged.all())},
            "values": {"weight_rel_error": rel, "via_time_error_steps": t_err, "via_target_error": m_err,
                       "reproduction_rmse": rmse, "final_loss": res.loss,
                       "evaluations": len(res.history["loss"]),
                       "learned_tau": float(w["via_times"][0])}}


def _plot(out: Path, xd, xr, m_true, m_learn, loss) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    fig, (a, b) = plt.subplots(1, 2, figsize=(8, 3.2))
    for i in range(xd.shape[0]):
        a.plot(xd[i, :, 0], xd[i, :, 1], color="0.6", lw=2.5)
        a.plot(xr[i, :, 0], xr[i, :, 1], "k--", lw=1)
    a.plot(*m_true.tolist(), "o", color="tab:red", ms=9, mfc="none", label="true via point")
    a.plot(*m_learn.tolist(), "x", color="tab:blue", ms=8, label="learned via point")
    a.set_aspect("equal")
    a.set_title("demos (grey) and learned-cost optima (dashed)", fontsize=8)
    a.legend(fontsize=7)
    b.semilogy(torch.tensor(loss).clamp_min(1e-32))
    b.set_xlabel("evaluation")
    b.set_ylabel("imitation loss")
    fig.tight_layout()
    fig.savefig(out / f"{Path(__file__).stem}.png", dpi=80)
    plt.close(fig)


if __name__ == "__main__":
    import json

    print(json.dumps(run(Path("out/learning")), indent=1))
