"""Object affordance: the same grasp at picking and placing, by iLQR (seed 004 §9.14; the cookbook's
``iLQR_manipulator_object_affordance.py``).

The cookbook manipulator (3 links of lengths 2, 2, 1, velocity commands ``q_{t+1} = q_t + Δt u_t``, ``Δt =
0.05``, ``T = 50``) picks up a box (half sizes 0.6 × 0.2) lying at the pose ``(μ_A, θ_A)`` at ``t_1 = 25`` and
puts it down at ``(μ_B, θ_B)`` at ``T``.  Where on the box to grasp is not given: the grasp offset — the end
effector's pose in the object's frame, ``o_t = [R(θ)ᵀ (p_t - μ), φ_t - θ]``
(:func:`controllers.task_costs_ext.object_frame`) — must only be the *same* at both steps.  In the seed's
formulation that is a precision with off-diagonal blocks, ``[o_{t_1}; o_T]ᵀ [[W, -W], [-W, W]] [o_{t_1}; o_T]
= (o_{t_1} - o_T)ᵀ W (o_{t_1} - o_T)`` (:func:`controllers.task_costs_ext.coupling_precision`), which couples
two time steps.  The iLQR solvers take per-step costs, so it is solved in its equivalent separable form: an
auxiliary constant state ``z`` (the offset, ``z_{t+1} = z_t``) appended to the joint angles, with residuals
``o_{t_1} - z`` and ``o_T - z`` (:func:`controllers.task_costs_ext.minus_state`) of precision ``2W`` each
(minimizing over ``z`` gives back the coupled cost, at ``z = (o_{t_1} + o_T)/2``), ``W = 500 I``.  The initial
``z`` is a decision variable of the batch iLQR (:func:`controllers.ilqr_lifted.ilqr_lifted` with a zero
``x0_weight`` on ``z`` and ``10⁸`` pinning the joint angles, Eq. 109-110), and the grasp must lie on the box:
``|z_xy| ≤`` the half sizes (:func:`controllers.task_costs.cut`, weight 10³).  ``R = 10⁻² I``.  Two
pick-and-place situations are solved at once, and again with a predetermined grasp (``z`` pinned to the
centre of the box, with the relative orientation the free solution chose).

Checks: every solve CONVERGED; the arm's start pose kept (``‖q_0 - q̄_0‖ ≤ 10⁻⁴``); the offsets at picking and
placing equal, ``√((o_{t_1} - o_T)ᵀ(o_{t_1} - o_T)) ≤ 10⁻²`` (the coupled cost with ``W = I``, evaluated on
the trajectory); the grasp point on the box (within the half sizes + 10⁻²) and off its centre (by more than
0.1: the choice mattered); and the free grasp costs less than the predetermined one in every situation — the
robot anticipates what it will do with the object.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch

from controllers.dynamics import LinearDynamics
from controllers.ilqr import ILQRProblem
from controllers.ilqr_lifted import ilqr_lifted
from controllers.task_costs import cut, on_joints, planar_ee, residual_cost, state
from controllers.task_costs_ext import coupled_cost, coupling_precision, minus_state, object_frame

SECTION = "9.14"
TITLE = "Object affordance: one grasp offset at picking and placing (iLQR)"

LENGTHS = (2.0, 2.0, 1.0)
T, DT, T1 = 50, 0.05, 25
HALF = (0.6, 0.2)
Q0 = (math.pi / 2, -math.pi / 4, -math.pi / 4)
PICK = (((3.0, 1.0), 0.3), ((2.5, -1.0), -0.5))  # (μ_A, θ_A) per situation
PLACE = (((0.5, 3.0), 1.2), ((-1.0, 2.5), 2.0))  # (μ_B, θ_B)


def object_poses(dtype=torch.float64) -> tuple[torch.Tensor, torch.Tensor]:
    """The object's pose per step ``(B, T+1, 2)``, ``(B, T+1)``: at A until ``t_1``, at B after."""
    kw = dict(dtype=dtype)
    at_a = (torch.arange(T + 1) <= T1)[None, :]
    pa, pb = torch.tensor([p for p, _ in PICK], **kw), torch.tensor([p for p, _ in PLACE], **kw)
    ta, tb = torch.tensor([a for _, a in PICK], **kw), torch.tensor([a for _, a in PLACE], **kw)
    return torch.where(at_a[..., None], pa[:, None], pb[:, None]), torch.where(at_a, ta[:, None], tb[:, None])


def offset_map(dtype=torch.float64):
    """The grasp offset ``o_t`` as a map of the augmented state ``[q (3), z (3)]``."""
    mu, th = object_poses(dtype)
    return object_frame(on_joints(planar_ee(LENGTHS), [0, 1, 2], 6), mu, th)


def solve(grasp: torch.Tensor | None = None, dtype=torch.float64):
    """The free-grasp problem, or with ``grasp (B, 3)`` a predetermined offset ``z`` (pinned)."""
    kw = dict(dtype=dtype)
    Q = torch.zeros(T + 1, 3, 3, **kw)
    Q[T1] = Q[T] = 2 * 500.0 * torch.eye(3, **kw)
    box = cut(on_joints(state(2), [3, 4], 6), [-HALF[0], -HALF[1]], list(HALF))
    cost = residual_cost([(minus_state(offset_map(dtype), [3, 4, 5], 6), Q), (box, 1e3 * torch.eye(2, **kw))],
                         1e-2 * torch.eye(3, **kw))
    A = torch.eye(6, **kw)
    B = torch.cat([DT * torch.eye(3, **kw), torch.zeros(3, 3, **kw)], 0)
    z0 = torch.zeros(len(PICK), 3, **kw) if grasp is None else grasp
    x0 = torch.cat([torch.tensor(Q0, **kw).expand(len(PICK), 3), z0], -1)
    w = torch.tensor([1e8] * 3 + ([0.0] * 3 if grasp is None else [1e8] * 3), **kw)
    return ilqr_lifted(ILQRProblem(LinearDynamics(A, B), cost, x0, T), x0_weight=w, max_iter=100)


def run(out: Path | None = None) -> dict:
    sol = solve()
    centre = sol.x0[:, 3:].clone()
    centre[:, :2] = 0.0  # the box's centre, with the relative orientation the free grasp chose
    fixed = solve(centre)
    o = offset_map().f(sol.x)
    mismatch = coupled_cost(o, coupling_precision(T, 3, [(T1, T)], 1.0)).sqrt()
    grasp = o[:, T1, :2]
    excess = (grasp.abs() - torch.tensor(HALF, dtype=o.dtype)).amax(-1)
    start = (sol.x0[:, :3] - torch.tensor(Q0, dtype=o.dtype)).norm(dim=-1)
    if out is not None:
        _plot(out, sol.x, fixed.x)
    return {"checks": {"all_converged": bool(sol.status.converged.all() and fixed.status.converged.all()),
                       "start_kept": bool((start <= 1e-4).all()),
                       "same_offset_at_pick_and_place": bool((mismatch <= 1e-2).all()),
                       "grasp_on_the_object": bool((excess <= 1e-2).all()),
                       "grasp_off_centre": bool((grasp.norm(dim=-1) > 0.1).all()),
                       "free_grasp_costs_less": bool((sol.cost < fixed.cost).all())},
            "values": {"max_offset_mismatch": float(mismatch.max()),
                       "max_boundary_excess": float(excess.max()),
                       "min_grasp_offset": float(grasp.norm(dim=-1).min()),
                       "max_cost_ratio_free_over_predetermined": float((sol.cost / fixed.cost).max()),
                       "max_iterations": int(sol.status.iterations.max())}}


def _plot(out: Path, x: torch.Tensor, x_fixed: torch.Tensor) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from controllers.systems.arm import PlanarArm

    out.mkdir(parents=True, exist_ok=True)
    arm = PlanarArm(links=3, lengths=list(LENGTHS))
    mu, th = object_poses(x.dtype)
    corners = torch.tensor([[-1, -1], [1, -1], [1, 1], [-1, 1], [-1, -1]], dtype=x.dtype) * torch.tensor(HALF)
    fig, axes = plt.subplots(1, x.shape[0], figsize=(7, 3.4))
    for b, ax in enumerate(axes):
        for t, shade in ((0, "0.8"), (T1, "0.45"), (T, "0.1")):
            pts = arm.fk(x[b, t, :3])
            ax.plot(pts[:, 0], pts[:, 1], "-o", color=shade, ms=2, lw=1.2)
        for t, col in ((T1, "tab:blue"), (T, "tab:green")):
            c, s = math.cos(float(th[b, t])), math.sin(float(th[b, t]))
            R = torch.tensor([[c, -s], [s, c]], dtype=x.dtype)
            box = corners @ R.mT + mu[b, t]
            ax.fill(box[:, 0], box[:, 1], color=col, alpha=0.3)
        ee = planar_ee(LENGTHS).f(x_fixed[b, :, :3])
        ax.plot(ee[:, 0], ee[:, 1], ":", color="tab:red", lw=0.8)
        ee = planar_ee(LENGTHS).f(x[b, :, :3])
        ax.plot(ee[:, 0], ee[:, 1], "-", color="k", lw=0.8)
        ax.set_aspect("equal")
        ax.set_title(f"§9.14 situation {b + 1} (dotted: centre grasp)", fontsize=8)
    fig.tight_layout()
    fig.savefig(out / f"{Path(__file__).stem}.png", dpi=80)
    plt.close(fig)


if __name__ == "__main__":
    import json

    print(json.dumps(run(Path("out/cookbook")), indent=1))
