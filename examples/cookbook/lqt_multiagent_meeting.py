"""Agents that meet: LQT with a precision coupling agents and time steps (seed 004 §7.6, Fig. 19; the
cookbook's ``LQT_recursive_LS_multiAgents.py``).

Parameters: two point masses in the plane with acceleration commands, stacked in one state
``x = [p_1; ṗ_1; p_2; ṗ_2]`` (each ``A = I + A^c Δt``, ``B = B^c Δt``, Eq. 192), ``T = 60`` steps of
``Δt = 0.05``.  Each agent must reach its target (at rest) at ``T`` (precision ``10³``); and the two must
meet — the precision ``10³ [[I, -I], [-I, I]]`` on ``(p_1, p_2)`` (the seed's footnote 3), so the meeting
point is optimized, not given.  Control weight ``10⁻² I``.  A batch of four scenarios (different starts
and targets) is solved at once.

Two variants (:func:`controllers.lqt_cookbook.meeting_lqt`):

* handover — both at ``T/2``: a per-step precision with off-diagonal agent blocks, solved by Riccati
  (§7.4-7.5), whose gains ``u_t = K_t x_t + k_t`` are then run in closed loop with agent 1 pushed by
  ``(0.3, -0.3)`` at ``T/4`` (Fig. 19's perturbation);
* drop and pick up — agent 1 at ``T/3`` where agent 2 is at ``2T/3``: a full precision coupling two time
  steps (``Qbig``), solved in batch form (Eq. 62).

Plot: the handover paths (dashed: nominal, solid: perturbed) with the meeting points, for scenario 0.

Checks: in every scenario the agents meet within 10⁻² (handover, nominal), within 2·10⁻² after the push
(closed loop), and within 10⁻² at their two times (drop and pick up); every agent ends within 10⁻² of its
target in all three runs; the push was real (it moved agent 1 by more than 0.1 from its nominal path).
"""

from __future__ import annotations

from pathlib import Path

import torch

from controllers.lqt_cookbook import meeting_lqt

SECTION = "7.6"
TITLE = "Multi-agent meeting (handover, drop and pick up)"

T, DT = 60, 0.05


def scenarios(dtype: torch.dtype = torch.float64) -> tuple[torch.Tensor, torch.Tensor]:
    """Starts ``(4, 2, 4)`` (at rest) and targets ``(4, 2, 2)``."""
    kw = dict(dtype=dtype)
    p0 = torch.tensor([[[0.0, 0.0], [2.0, 0.0]], [[0.0, 1.0], [2.0, -1.0]],
                       [[-1.0, 0.0], [1.0, 1.0]], [[0.0, -1.0], [0.5, 1.5]]], **kw)
    tg = torch.tensor([[[2.0, 2.0], [0.0, 2.0]], [[1.0, -1.0], [1.0, 1.5]],
                       [[1.5, 1.5], [-1.0, 2.0]], [[2.0, 0.0], [-1.0, 0.0]]], **kw)
    return torch.cat([p0, torch.zeros_like(p0)], -1), tg


def run(out: Path | None = None) -> dict:
    x0, tg = scenarios()
    tm = T // 2
    hand = meeting_lqt(x0, tg, T, DT, meet_times=tm)
    sol = hand.solution
    # closed loop with the Riccati gains; agent 1 pushed at T/4
    push = torch.tensor([0.3, -0.3, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0], dtype=x0.dtype)
    d = hand.problem.dynamics
    x = hand.problem.x0
    xs = [x]
    for t in range(T):
        if t == T // 4:
            x = x + push
            xs[-1] = x
        u = (sol.K[:, t] @ x.unsqueeze(-1)).squeeze(-1) + sol.k[:, t]
        x = d.step(x, u, t)
        xs.append(x)
    xp = torch.stack(xs, -2).unflatten(-1, (2, 4))[..., :2]  # (4, T+1, 2, 2)
    drop = meeting_lqt(x0, tg, T, DT, meet_times=[T // 3, 2 * T // 3])
    P, Pd = hand.positions, drop.positions
    meet_nom = (P[:, tm, 0] - P[:, tm, 1]).norm(dim=-1).max()
    meet_pert = (xp[:, tm, 0] - xp[:, tm, 1]).norm(dim=-1).max()
    meet_drop = (Pd[:, T // 3, 0] - Pd[:, 2 * T // 3, 1]).norm(dim=-1).max()
    final = max(float((p[:, -1] - tg).norm(dim=-1).max()) for p in (P, xp, Pd))
    moved = (xp[:, T // 4, 0] - P[:, T // 4, 0]).norm(dim=-1).min()
    if out is not None:
        _plot(out, P[0], xp[0], tg[0], tm)
    return {"checks": {"handover_meet": bool(meet_nom < 1e-2),
                       "handover_meet_after_push": bool(meet_pert < 2e-2),
                       "drop_and_pickup_meet": bool(meet_drop < 1e-2),
                       "targets_reached": bool(final < 1e-2),
                       "push_was_real": bool(moved > 0.1)},
            "values": {"scenarios": int(x0.shape[0]), "meet_distance_nominal": float(meet_nom),
                       "meet_distance_pushed": float(meet_pert),
                       "meet_distance_drop_pickup": float(meet_drop),
                       "max_final_error": final}}


def _plot(out: Path, P: torch.Tensor, Pp: torch.Tensor, tg: torch.Tensor, tm: int) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(4, 3))
    for i, c in enumerate(("tab:orange", "tab:purple")):
        ax.plot(P[:, i, 0], P[:, i, 1], "--", color=c, lw=1)
        ax.plot(Pp[:, i, 0], Pp[:, i, 1], color=c, lw=1.5)
        ax.plot(P[0, i, 0], P[0, i, 1], "ko", ms=4)
        ax.plot(tg[i, 0], tg[i, 1], "o", color="tab:red")
    ax.plot(P[tm, 0, 0], P[tm, 0, 1], "o", color="tab:blue")
    ax.plot(Pp[tm, 0, 0], Pp[tm, 0, 1], "o", color="tab:blue", mfc="none")
    ax.plot(Pp[T // 4, 0, 0], Pp[T // 4, 0, 1], "o", color="tab:green", ms=4)
    ax.set_aspect("equal")
    ax.set_title("§7.6 two agents meet at T/2", fontsize=9)
    fig.tight_layout()
    fig.savefig(out / f"{Path(__file__).stem}.png", dpi=80)
    plt.close(fig)


if __name__ == "__main__":
    import json

    print(json.dumps(run(Path("out/cookbook")), indent=1))
