"""Bimanual tennis serve (seed 004 §7 and Appendix C, Fig. 17; the cookbook's ``LQT_tennisServe.py``).

Parameters: three agents in the vertical plane — left hand, right hand (the racket) and ball — each with
state ``[p_i; ṗ_i; f_i]``, where ``f_i = g = (0, -9.81)`` is gravity carried as a constant state; only the
hands are driven by acceleration commands.  ``T = 100`` steps of ``Δt = 0.02`` (2 s).  The system matrices
change with the phase (Eq. 189-191, discretized with Eq. 192): until ``T/4`` the left hand carries the
ball (the ball moves as the hand does); then the ball flies under gravity; at ``T/2`` the right hand hits
it (over that step the ball takes the racket's velocity); then it flies again.

Cost (Eq. 64): the ball at its target at ``T`` (precision ``10⁴ I``); both hands back at their initial
positions from ``3T/4`` to ``T``; and at ``T/2`` the precision ``10⁴ [[I, -I], [-I, I]]`` on the positions
of racket and ball, so that they coincide at a point the solver chooses.  Control weight ``10⁻⁴ I``.
Solve: Eq. 62 on the transfer matrices of the time-varying system
(:func:`controllers.lqt_cookbook.tennis_serve_lqt`), for a batch of four ball targets at once.

Plot: hands and ball for every target; ball targets in red, hit points in blue.

Checks: in every case the racket meets the ball at ``T/2`` within 10⁻² (the hit), the ball lands within
10⁻² of its target at ``T``, the ball is really thrown and hit (it leaves the left hand at ``T/4`` moving
up faster than 0.5, and its velocity changes by more than 1 over the hit step), and the hands are back
within 10⁻² of their initial positions at ``T``.  (The least-effort solution throws the ball only a little
and meets it on its way down, below the hands' starting height: nothing in Eq. 64 asks for a high hit.)
"""

from __future__ import annotations

from pathlib import Path

import torch

from controllers.lqt_cookbook import tennis_serve_lqt

SECTION = "C"
TITLE = "Bimanual tennis serve (LQT with time-varying linear systems)"

T, DT = 100, 0.02


def run(out: Path | None = None) -> dict:
    kw = dict(dtype=torch.float64)
    hands0 = torch.tensor([[-0.3, 0.0], [0.3, 0.0]], **kw)
    targets = torch.tensor([[3.0, 1.0], [3.5, 0.0], [2.5, 2.0], [-2.5, 1.0]], **kw)
    r = tennis_serve_lqt(hands0, targets, T=T, dt=DT)
    P, x = r.positions, r.solution.x  # (4, T+1, 3, 2)
    th = r.t_hit
    hit = (P[:, th, 1] - P[:, th, 2]).norm(dim=-1).max()
    land = (P[:, -1, 2] - targets).norm(dim=-1).max()
    up = x[:, r.t_release, 15].min()  # the ball's vertical velocity when the left hand lets it go
    dv = (x[:, th + 1, 14:16] - x[:, th, 14:16]).norm(dim=-1).min()
    back = (P[:, -1, :2] - hands0).norm(dim=-1).max()
    if out is not None:
        _plot(out, P, targets, th)
    return {"checks": {"ball_hit": bool(hit < 1e-2), "ball_reaches_target": bool(land < 1e-2),
                       "ball_thrown_and_hit": bool(up > 0.5 and dv > 1.0),
                       "hands_back": bool(back < 1e-2),
                       "solved": bool(r.solution.status.all_converged)},
            "values": {"targets": int(targets.shape[0]), "max_hit_distance": float(hit),
                       "max_target_error": float(land), "min_release_upward_speed": float(up),
                       "min_hit_velocity_change": float(dv), "max_hands_error": float(back)}}


def _plot(out: Path, P: torch.Tensor, targets: torch.Tensor, th: int) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(5, 3))
    for b in range(P.shape[0]):
        ax.plot(P[b, :, 0, 0], P[b, :, 0, 1], color="tab:orange", lw=0.8)
        ax.plot(P[b, :, 1, 0], P[b, :, 1, 1], color="tab:purple", lw=0.8)
        ax.plot(P[b, :, 2, 0], P[b, :, 2, 1], ":", color="k", lw=0.8)
        ax.plot(P[b, th, 2, 0], P[b, th, 2, 1], "o", color="tab:blue", ms=4)
    ax.plot(targets[:, 0], targets[:, 1], "o", color="tab:red")
    ax.set_aspect("equal")
    ax.set_title("App. C bimanual tennis serve (hands: orange/purple, ball: dotted)", fontsize=8)
    fig.tight_layout()
    fig.savefig(out / f"{Path(__file__).stem}.png", dpi=80)
    plt.close(fig)


if __name__ == "__main__":
    import json

    print(json.dumps(run(Path("out/cookbook")), indent=1))
