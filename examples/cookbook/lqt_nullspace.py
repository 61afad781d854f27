"""Nullspace LQT: many ways through the same via points (seed 004 §7; the cookbook's ``LQT_nullspace.py``).

Parameters: a point mass in the plane with acceleration commands, ``x = [p; ṗ]``, ``A = I + A^c Δt``,
``B = B^c Δt`` (Eq. 192), ``Δt = 0.05``, ``T = 40`` steps, from ``x_0 = 0``.  The primary task is Eq. 59
with two via points: the position must pass ``μ_1`` at ``T/2`` and ``μ_2`` at ``T`` (precision ``10³ I`` on
the position, zero elsewhere) with a small control weight ``R = 10⁻³ I``.

Solve: the batch LQT ``û`` (Eq. 62), then ``u = û + N v`` with ``N = I - (S_uᵀQS_u)⁺ S_uᵀQS_u``, the
projector of §5.2 applied to the tracking objective: any ``v`` leaves the via-point positions as they are.
Eight random ``v`` (one batch, an explicit ``torch.Generator``) draw a family of paths, and a secondary
objective — stay near the point ``c`` during the whole motion — picks ``v`` by least squares in the null
space (:func:`controllers.lqt_cookbook.nullspace_lqt`).

Plot: the family (grey), ``û`` (black), the secondary solution (blue), via points (red), ``c`` (green).

Checks: ``û`` passes both via points within 10⁻² (the primary task); every null-space path (random and
secondary) has the same via-point positions as ``û`` within 10⁻⁸; the family is not trivial (paths spread
by more than 0.1 somewhere); the secondary cost of the secondary solution is below ``û``'s.
"""

from __future__ import annotations

from pathlib import Path

import torch

from controllers.costs import QuadraticCost
from controllers.lqt_cookbook import double_integrator, nullspace_lqt
from controllers.problem import LQProblem

SECTION = "7"
TITLE = "Nullspace LQT: a secondary objective through the same via points"

T, DT = 40, 0.05
VIA = ((1.0, 1.5), (2.0, 0.0))
CENTER = (1.5, -0.5)


def problem(dtype: torch.dtype = torch.float64) -> tuple[LQProblem, QuadraticCost]:
    """The primary via-point problem and the secondary cost ``Σ_t ‖p_t - c‖² + 10⁻² ‖u_t‖²``."""
    kw = dict(dtype=dtype)
    targets = torch.cat([torch.tensor(VIA, **kw), torch.zeros(2, 2, **kw)], -1)
    prec = torch.diag(torch.tensor([1e3, 1e3, 0.0, 0.0], **kw))
    cost = QuadraticCost.via_points(T, [T // 2, T], targets, prec, 1e-3 * torch.eye(2, **kw))
    prob = LQProblem(double_integrator(2, DT, dtype), cost, torch.zeros(4, **kw))
    c = torch.tensor([*CENTER, 0.0, 0.0], **kw)
    Qc = torch.diag(torch.tensor([1.0, 1.0, 0.0, 0.0], **kw))
    sec = QuadraticCost(Qc, 1e-2 * torch.eye(2, **kw), x_ref=c)
    return prob, sec


def run(out: Path | None = None) -> dict:
    prob, sec = problem()
    g = torch.Generator().manual_seed(0)
    v = 20.0 * torch.randn(8, T, 2, dtype=torch.float64, generator=g)
    fam = nullspace_lqt(prob, v=v)  # (8, ...) : a family of paths
    best = nullspace_lqt(prob, secondary=sec)
    base = nullspace_lqt(prob)
    via = torch.tensor(VIA, dtype=torch.float64)
    ts = [T // 2, T]
    primary_err = (base.x[ts, :2] - via).norm(dim=-1).max()
    same = max(float((fam.x[:, ts, :2] - base.x[ts, :2]).abs().max()),
               float((best.x[ts, :2] - base.x[ts, :2]).abs().max()))
    spread = (fam.x[..., :2] - base.x[..., :2]).norm(dim=-1).max()
    c_base, c_best = sec.evaluate(base.x, base.u), sec.evaluate(best.x, best.u)
    if out is not None:
        _plot(out, fam.x, base.x, best.x)
    return {"checks": {"via_points_reached": bool(primary_err < 1e-2),
                       "nullspace_keeps_via_points": bool(same < 1e-8),
                       "family_is_diverse": bool(spread > 0.1),
                       "secondary_cost_lowered": bool(c_best < c_base)},
            "values": {"via_point_error": float(primary_err), "max_via_point_change": same,
                       "family_spread": float(spread), "null_space_dim": int(T * 2 - base.rank),
                       "secondary_cost_primary": float(c_base), "secondary_cost_nullspace": float(c_best)}}


def _plot(out: Path, fam: torch.Tensor, base: torch.Tensor, best: torch.Tensor) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(4, 3))
    for b in range(fam.shape[0]):
        ax.plot(fam[b, :, 0], fam[b, :, 1], color="0.7", lw=0.8)
    ax.plot(base[:, 0], base[:, 1], color="k", lw=1.5, label="û")
    ax.plot(best[:, 0], best[:, 1], color="tab:blue", lw=1.5, label="û + N v (secondary)")
    ax.plot(*zip(*VIA), "o", color="tab:red")
    ax.plot(*CENTER, "s", color="tab:green")
    ax.set_aspect("equal")
    ax.legend(fontsize=7)
    ax.set_title("§7 nullspace LQT", fontsize=9)
    fig.tight_layout()
    fig.savefig(out / f"{Path(__file__).stem}.png", dpi=80)
    plt.close(fig)


if __name__ == "__main__":
    import json

    print(json.dumps(run(Path("out/cookbook")), indent=1))
