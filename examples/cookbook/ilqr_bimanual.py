"""A bimanual robot reaching with one hand while its centre of mass stays put, by iLQR (seed 004 §9.6; the
cookbook's ``iLQR_bimanual.py``).

The 5-link planar bimanual robot of Fig. 26: a torso link (joint 1) shared by a left arm (joints 2-3) and a
right arm (joints 4-5), velocity commands ``x_{t+1} = x_t + Δt u_t``.  Its hands are two planar chains on the
joints ``[1, 2, 3]`` and ``[1, 4, 5]`` (:func:`controllers.task_costs.bimanual_hands`).  With unit masses at
the joints and two at the torso's tip, the centre of mass is ``f^CoM = (2 p_1 + p_2 + p_3 + p_4 + p_5) / 6``,
the average of the two chains' centres of mass (:func:`controllers.task_costs.bimanual_com`).

The task (Fig. 26, right): the left hand reaches a target at the end, ``Q_T = 10³ I``, while the CoM tracks
its initial location at every step, ``Q = 10⁴ I``; ``R = 10⁻² I``.  A batch of 5 targets is solved at once.

Checks: every element CONVERGED, every target reached within 10⁻², the CoM never more than 10⁻² from where it
started, and — the regime — without the CoM term it moves by more than 0.04 for every target.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch

from controllers.dynamics import LinearDynamics
from controllers.ilqr import ILQROptions, ILQRProblem, ilqr
from controllers.task_costs import (
    BIMANUAL_LEFT,
    BIMANUAL_RIGHT,
    Map,
    bimanual_com,
    bimanual_hands,
    residual_cost,
    track,
)

SECTION = "9.6"
TITLE = "Bimanual robot: one hand reaches, the centre of mass stays (iLQR)"

LENGTHS = (1.5, 1.0, 1.0, 1.0, 1.0)  # torso, left upper and lower arm, right upper and lower arm
T, DT = 40, 0.05
X0 = (math.pi / 2, math.pi / 2, math.pi / 4, -math.pi / 2, -math.pi / 4)


def left_hand() -> Map:
    both = bimanual_hands(LENGTHS)
    return Map(lambda x: both.f(x)[..., :2], lambda x: both.J(x)[..., :2, :], 2)


def targets(dtype=torch.float64) -> torch.Tensor:
    return torch.tensor([[-1.2, 1.2], [-1.9, 1.4], [-1.4, 0.4], [-1.8, 1.0], [-1.0, 0.8]], dtype=dtype)


def problem(with_com: bool = True, dtype=torch.float64) -> ILQRProblem:
    kw = dict(dtype=dtype)
    mu = targets(dtype)
    x0 = torch.tensor(X0, **kw).expand(mu.shape[0], 5)
    Qh = torch.zeros(T + 1, 2, 2, **kw)
    Qh[-1] = 1e3 * torch.eye(2, **kw)
    terms = [(track(left_hand(), mu[:, None, :]), Qh)]
    if with_com:
        com = bimanual_com(LENGTHS)
        terms.append((track(com, com.f(x0)[:, None, :]), 1e4 * torch.eye(2, **kw)))
    eye = torch.eye(5, **kw)
    return ILQRProblem(LinearDynamics(eye, DT * eye), residual_cost(terms, 1e-2 * eye), x0, T)


def run(out: Path | None = None) -> dict:
    opts = ILQROptions(max_iter=60)
    sol = ilqr(problem(), grad="none", options=opts)
    free = ilqr(problem(with_com=False), grad="none", options=opts)
    err = (left_hand().f(sol.x[:, -1]) - targets()).norm(dim=-1)
    c = bimanual_com(LENGTHS).f(sol.x)
    drift = (c - c[:, :1]).norm(dim=-1).amax(-1)
    cf = bimanual_com(LENGTHS).f(free.x)
    drift_free = (cf - cf[:, :1]).norm(dim=-1).amax(-1)
    if out is not None:
        _plot(out, sol.x)
    return {"checks": {"all_converged": bool(sol.status.converged.all()),
                       "target_reached": bool((err < 1e-2).all()),
                       "com_kept": bool((drift <= 1e-2).all()),
                       "without_com_term_it_moves": bool((drift_free > 0.04).all())},
            "values": {"max_target_error": float(err.max()), "max_com_drift": float(drift.max()),
                       "min_com_drift_without_term": float(drift_free.min()),
                       "max_iterations": int(sol.status.iterations.max())}}


def joints_xy(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Polylines of the left and right chains (base, joints, hand) for a pose ``x (5,)``."""
    from controllers.systems.arm import PlanarArm

    out = []
    for idx in (BIMANUAL_LEFT, BIMANUAL_RIGHT):
        out.append(PlanarArm(links=3, lengths=[LENGTHS[j] for j in idx]).fk(x[list(idx)]))
    return out[0], out[1]


def _plot(out: Path, x: torch.Tensor) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(4, 4))
    for b in range(x.shape[0]):
        for t, shade in ((0, "0.75"), (-1, "0.2")):
            if t == 0 and b > 0:
                continue
            for pts in joints_xy(x[b, t]):
                ax.plot(pts[:, 0], pts[:, 1], "-o", color=shade, ms=2, lw=1)
        c = bimanual_com(LENGTHS).f(x[b])
        ax.plot(c[:, 0], c[:, 1], ".", color="tab:blue", ms=2)
    ax.plot(targets()[:, 0], targets()[:, 1], "x", color="tab:red")
    ax.set_aspect("equal")
    ax.set_title("§9.6 bimanual reach, CoM kept (blue)", fontsize=9)
    fig.tight_layout()
    fig.savefig(out / f"{Path(__file__).stem}.png", dpi=80)
    plt.close(fig)


if __name__ == "__main__":
    import json

    print(json.dumps(run(Path("out/cookbook")), indent=1))
