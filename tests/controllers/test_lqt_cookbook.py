"""controllers.lqt_cookbook against dense least-squares / null-space oracles (scipy), Riccati, brute force."""

import dataclasses
import math

import pytest
import scipy.linalg
import torch

from controllers import lifted, lqt_cookbook, riccati
from controllers.costs import QuadraticCost
from controllers.dynamics import rollout
from controllers.problem import LQProblem

D = torch.float64


def _via_point_problem(b=(), T=12, dtype=D, seed=0):
    """Double integrator in 2-D through two via points (a sparse Q: a large null space)."""
    g = torch.Generator().manual_seed(seed)
    dyn = lqt_cookbook.double_integrator(2, 0.1, dtype)
    targets = torch.randn(*b, 2, 4, dtype=D, generator=g).to(dtype)
    prec = torch.diag(torch.tensor([1e2, 1e2, 0.0, 0.0], dtype=dtype))  # positions only
    cost = QuadraticCost.via_points(T, [T // 2, T], targets, prec, 1e-3 * torch.eye(2, dtype=dtype))
    x0 = torch.randn(*b, 4, dtype=D, generator=g).to(dtype)
    return LQProblem(dyn, cost, x0)


def _dense(p):
    """Dense Suᵀ Q Su, H, g, Su, s0 of a problem without N/q/r, from blockdiag matrices."""
    T = p.T
    cc = p.cost.canonical(T)
    Sx, Su, _ = lifted.transfer_matrices(p.dynamics.A, p.dynamics.B, None, T)
    Qb, Rb = lifted.block_diag_time(cc.Q, T + 1), lifted.block_diag_time(cc.R, T)
    s0 = (Sx @ p.x0.unsqueeze(-1)).squeeze(-1)
    G = Su.mT @ Qb @ Su
    g = (Su.mT @ (Qb @ s0.unsqueeze(-1) + cc.q.flatten(-2).unsqueeze(-1))).squeeze(-1)
    if cc.r is not None:
        g = g + cc.r.flatten(-2)
    return G, G + Rb, g, Su, s0


def _secondary(T, b=(), dtype=D, seed=1):
    g = torch.Generator().manual_seed(seed)
    ref = torch.randn(*b, T + 1, 4, dtype=D, generator=g).to(dtype)
    return QuadraticCost(torch.eye(4, dtype=dtype), 1e-2 * torch.eye(2, dtype=dtype), x_ref=ref)


# ---------------------------------------------------------------------------------------------- nullspace


def test_nullspace_matches_scipy_null_space_and_lstsq():
    p = _via_point_problem()
    sec = _secondary(p.T)
    res = lqt_cookbook.nullspace_lqt(p, secondary=sec)
    G, H, g, Su, s0 = (t.numpy() for t in _dense(p))
    u_hat = scipy.linalg.lstsq(H, -g)[0]
    Z = scipy.linalg.null_space(G, rcond=1e-9)
    assert res.rank.item() == G.shape[0] - Z.shape[1] == 4  # two via points x two positions
    _, H2, g2, _, _ = (t.numpy() for t in _dense(LQProblem(p.dynamics, sec, p.x0, horizon=p.T)))
    z = scipy.linalg.lstsq(Z.T @ H2 @ Z, -Z.T @ (H2 @ u_hat + g2))[0]
    u_ref = u_hat + Z @ z
    torch.testing.assert_close(res.u_primary.flatten(), torch.from_numpy(u_hat), atol=1e-8, rtol=0)
    torch.testing.assert_close(res.u.flatten(), torch.from_numpy(u_ref), atol=1e-7, rtol=0)
    torch.testing.assert_close(res.N, torch.from_numpy(Z @ Z.T), atol=1e-8, rtol=0)
    assert res.status.all_converged


def test_nullspace_motion_keeps_the_tracking_residual():
    p = _via_point_problem(b=(3,))
    g = torch.Generator().manual_seed(2)
    base = lqt_cookbook.nullspace_lqt(p)
    v = 5.0 * torch.randn(3, p.T, 2, dtype=D, generator=g)
    moved = lqt_cookbook.nullspace_lqt(p, v=v)
    T = p.T
    for t in (T // 2, T):  # via-point positions unchanged, the rest of the path moved
        torch.testing.assert_close(moved.x[:, t, :2], base.x[:, t, :2], atol=1e-8, rtol=0)
    assert (moved.x - base.x).abs().max() > 0.1
    # the secondary objective is lowered by the null-space motion, the primary one is not changed
    sec = _secondary(T, b=(3,))
    with_sec = lqt_cookbook.nullspace_lqt(p, secondary=sec)
    assert bool((sec.evaluate(with_sec.x, with_sec.u) < sec.evaluate(base.x, base.u)).all())
    prim = dataclasses.replace(p.cost, R=torch.zeros_like(p.cost.R), check=False)
    torch.testing.assert_close(prim.evaluate(with_sec.x, with_sec.u), prim.evaluate(base.x, base.u),
                               atol=1e-8, rtol=1e-8)
    # x consistent with the dynamics
    torch.testing.assert_close(with_sec.x, rollout(p.dynamics, p.x0, with_sec.u))


def test_nullspace_batched_equals_loop_float32_and_nan_isolation():
    p = _via_point_problem(b=(3,), seed=3)
    sec = _secondary(p.T, b=(3,))
    res = lqt_cookbook.nullspace_lqt(p, secondary=sec)
    for i in range(3):
        pi = LQProblem(p.dynamics, dataclasses.replace(p.cost, Q=p.cost.Q[i], x_ref=p.cost.x_ref[i]), p.x0[i])
        si = dataclasses.replace(sec, x_ref=sec.x_ref[i])
        ui = lqt_cookbook.nullspace_lqt(pi, secondary=si).u
        torch.testing.assert_close(ui, res.u[i], atol=1e-9, rtol=0)
    # only x0 batched (the normal matrix is shared): broadcasting == manual expansion
    x0s = torch.randn(2, 4, dtype=D, generator=torch.Generator().manual_seed(9))
    p1 = LQProblem(p.dynamics, dataclasses.replace(p.cost, Q=p.cost.Q[0], x_ref=p.cost.x_ref[0]), x0s)
    r1 = lqt_cookbook.nullspace_lqt(p1, secondary=dataclasses.replace(sec, x_ref=sec.x_ref[0]))
    assert r1.u.shape == (2, p.T, 2)
    for i in range(2):
        ri = lqt_cookbook.nullspace_lqt(dataclasses.replace(p1, x0=x0s[i]),
                                        secondary=dataclasses.replace(sec, x_ref=sec.x_ref[0]))
        torch.testing.assert_close(ri.u, r1.u[i], atol=1e-9, rtol=0)
    p32 = _via_point_problem(b=(3,), seed=3, dtype=torch.float32)
    r32 = lqt_cookbook.nullspace_lqt(p32, secondary=_secondary(p.T, b=(3,), dtype=torch.float32))
    assert r32.u.dtype == torch.float32 and r32.rank.tolist() == [4, 4, 4]
    torch.testing.assert_close(r32.x.double(), res.x, atol=5e-3, rtol=0)
    x0 = p.x0.clone()
    x0[1, 0] = torch.nan
    bad = lqt_cookbook.nullspace_lqt(dataclasses.replace(p, x0=x0), secondary=sec)
    assert bad.status.converged.tolist() == [True, False, True]
    assert torch.isnan(bad.u[1]).all()
    torch.testing.assert_close(bad.u[[0, 2]], res.u[[0, 2]])


def test_nullspace_gradcheck_and_errors():
    p = _via_point_problem(T=6)
    sec = _secondary(6)

    def f(x0, ref):
        return lqt_cookbook.nullspace_lqt(dataclasses.replace(p, x0=x0),
                                          secondary=dataclasses.replace(sec, x_ref=ref)).u

    args = (p.x0.clone().requires_grad_(True), sec.x_ref.clone().requires_grad_(True))
    assert torch.autograd.gradcheck(f, args)
    with pytest.raises(ValueError, match="either 'v' or 'secondary'"):
        lqt_cookbook.nullspace_lqt(p, v=torch.zeros(6, 2, dtype=D), secondary=sec)
    with pytest.raises(ValueError, match="'v' must have shape"):
        lqt_cookbook.nullspace_lqt(p, v=torch.zeros(6, 3, dtype=D))
    with pytest.raises(TypeError, match="'problem'"):
        lqt_cookbook.nullspace_lqt("p")
    with pytest.raises(ValueError, match="'secondary'"):
        lqt_cookbook.nullspace_lqt(p, secondary=QuadraticCost(torch.eye(3, dtype=D), torch.eye(2, dtype=D)))


# ---------------------------------------------------------------------------------------------- DMP


def _demo(T=40, b=(), dtype=D):
    s = torch.linspace(0, 1, T + 1, dtype=dtype)
    h = 3 * s**2 - 2 * s**3
    d = torch.stack([0.5 * torch.sin(2 * math.pi * h), h], -1)
    scale = torch.linspace(1.0, 1.5, math.prod(b), dtype=dtype).reshape(*b, 1, 1) if b else 1.0
    return d * scale


def test_dmp_plan_matches_dense_least_squares():
    T, dt = 40, 0.025
    demo = _demo(T)
    dm = lqt_cookbook.dmp_lqt(demo, dt, n_basis=8, goal_weight=1e4)
    p = dm.problem
    # dense: min (x_T - μ)ᵀ W (x_T - μ) + (Ψw - a)ᵀ R (Ψw - a) as an ordinary least-squares problem
    Sx, Su, _ = lifted.transfer_matrices(p.dynamics.A, p.dynamics.B, None, T)
    n = 4
    rowsT = slice(T * n, (T + 1) * n)
    A_ls = torch.cat([100.0 * Su[rowsT] @ dm.Psi, dm.Psi], 0)
    b_ls = torch.cat([100.0 * (dm.demo_x[T] - Sx[rowsT] @ p.x0), dm.demo_u.flatten()], 0)
    w = torch.linalg.lstsq(A_ls, b_ls).solution
    torch.testing.assert_close(dm.plan.w, w, atol=1e-8, rtol=1e-8)
    # the demo itself is reproduced (up to the primitives' resolution) from the nominal start
    assert (dm.plan.x[..., :2] - demo).norm(dim=-1).max() < 2e-2


def test_dmp_feedback_is_the_optimal_lq_correction():
    """u*(x_t + δ) - u*(x_t) = K_t δ for the tail problem from t (an independent lifted solve)."""
    T, dt, t = 30, 0.03, 8
    dm = lqt_cookbook.dmp_lqt(_demo(T), dt, n_basis=6)
    p = dm.problem
    c = p.cost
    tail = lambda x: LQProblem(p.dynamics, QuadraticCost(c.Q[t:], c.R, x_ref=c.x_ref[t:], u_ref=c.u_ref[t:]),
                               x, horizon=T - t)
    xt = dm.plan.x[t]
    delta = torch.tensor([0.1, -0.2, 0.3, 0.05], dtype=D)
    du = lifted.solve_lifted(tail(xt + delta)).u[0] - lifted.solve_lifted(tail(xt)).u[0]
    torch.testing.assert_close(du, dm.K[t] @ delta, atol=1e-9, rtol=0)
    # the closed loop without perturbation is the plan; with one it ends near the goal
    x, _ = lqt_cookbook.dmp_rollout(dm)
    torch.testing.assert_close(x, dm.plan.x, atol=1e-10, rtol=0)
    x, _ = lqt_cookbook.dmp_rollout(dm, perturbation=delta, at=t)
    torch.testing.assert_close(x[t], dm.plan.x[t] + delta)
    assert (x[-1, :2] - dm.demo_x[-1, :2]).norm() < 0.05


def test_dmp_batched_float32_gradcheck_and_errors():
    demo = _demo(20, b=(3,))
    dm = lqt_cookbook.dmp_lqt(demo, 0.05, n_basis=5)
    for i in range(3):
        di = lqt_cookbook.dmp_lqt(demo[i], 0.05, n_basis=5)
        torch.testing.assert_close(di.plan.u, dm.plan.u[i], atol=1e-9, rtol=0)
        torch.testing.assert_close(di.K, dm.K[i], atol=1e-9, rtol=0)
    pert = torch.tensor([[0.1, 0, 0, 0], [0, 0.1, 0, 0], [0, 0, 0.1, 0]], dtype=D)
    xb, _ = lqt_cookbook.dmp_rollout(dm, perturbation=pert, at=5)
    d1 = lqt_cookbook.dmp_lqt(demo[1], 0.05, n_basis=5)
    x1, _ = lqt_cookbook.dmp_rollout(d1, perturbation=pert[1], at=5)
    torch.testing.assert_close(xb[1], x1, atol=1e-9, rtol=0)
    d32 = lqt_cookbook.dmp_lqt(demo.float(), 0.05, n_basis=5)
    assert d32.plan.x.dtype == torch.float32 and d32.K.dtype == torch.float32
    torch.testing.assert_close(d32.plan.x.double(), dm.plan.x, atol=2e-3, rtol=0)
    small = _demo(8).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda d: lqt_cookbook.dmp_lqt(d, 0.1, n_basis=3).plan.x, (small,))
    with pytest.raises(ValueError, match="'demo'"):
        lqt_cookbook.dmp_lqt(torch.zeros(2, 2, dtype=D), 0.1)
    with pytest.raises(ValueError, match="'dt'"):
        lqt_cookbook.dmp_lqt(demo, -1.0)
    with pytest.raises(TypeError, match="'demo'"):
        lqt_cookbook.dmp_lqt(torch.zeros(5, 2, dtype=torch.int64), 0.1)
    with pytest.raises(ValueError, match="'at'"):
        lqt_cookbook.dmp_rollout(dm, perturbation=pert, at=99)


# ---------------------------------------------------------------------------------------------- meeting


def test_meeting_riccati_equals_lifted_and_agents_meet():
    x0 = torch.tensor([[[0.0, 0, 0, 0], [1.0, 0, 0, 0], [0.5, -1, 0, 0]]], dtype=D).expand(2, 3, 4).clone()
    x0[1, 2, 0] = 2.0
    tg = torch.tensor([[1.0, 1], [0.0, 1], [0.5, 2]], dtype=D).expand(2, 3, 2)
    res = lqt_cookbook.meeting_lqt(x0, tg, 30, 0.05, meet_weight=1e4)
    assert res.Qbig is None and res.solution.status.all_converged
    ref = lifted.solve_lifted(res.problem)
    torch.testing.assert_close(res.solution.u, ref.u, atol=1e-8, rtol=0)
    P = res.positions[:, 15]
    assert (P[:, 0] - P[:, 1]).norm(dim=-1).max() < 1e-2 and (P[:, 0] - P[:, 2]).norm(dim=-1).max() < 1e-2
    assert (res.positions[:, -1] - tg).norm(dim=-1).max() < 1e-2
    for i in range(2):
        ri = lqt_cookbook.meeting_lqt(x0[i], tg[i], 30, 0.05, meet_weight=1e4)
        torch.testing.assert_close(ri.solution.u, res.solution.u[i], atol=1e-9, rtol=0)


def test_meeting_at_different_times_is_stationary_for_the_brute_force_cost():
    x0 = torch.tensor([[0.0, 0, 0, 0], [1.0, 0, 0, 0]], dtype=D)
    tg = torch.tensor([[1.0, 1], [0.0, 1]], dtype=D)
    T = 12
    res = lqt_cookbook.meeting_lqt(x0, tg, T, 0.1, meet_times=[4, 8])
    assert res.Qbig is not None
    p = res.problem

    def f(uv):
        u = uv.reshape(T, 4)
        x = rollout(p.dynamics, p.x0, u)
        pos = x.reshape(T + 1, 2, 4)[..., :2]
        tgt = (x[-1] - p.cost.x_ref[-1])
        return (1e3 * (pos[4, 0] - pos[8, 1]).pow(2).sum() + 1e3 * tgt.pow(2).sum()
                + 1e-2 * u.pow(2).sum())

    uv = res.solution.u.flatten()
    assert torch.func.grad(f)(uv).abs().max() < 1e-7
    torch.testing.assert_close(res.solution.cost, f(uv))
    with pytest.raises(ValueError, match="'meet_times'"):
        lqt_cookbook.meeting_lqt(x0, tg, T, 0.1, meet_times=[4])
    with pytest.raises(ValueError, match="A >= 2"):
        lqt_cookbook.meeting_lqt(x0[:1], tg[:1], T, 0.1)


@pytest.mark.parametrize("times", [12, [12, 12], [12, 6], [6, 12]])
def test_meeting_at_the_horizon_penalizes_the_gap_itself(times):
    """A meeting time equal to T (where the reference holds the targets) must still penalize p_i - p_j:
    the brute-force cost (positions from a rollout) is minimal at the solution and equals ``res.cost``."""
    x0 = torch.tensor([[0.0, 0, 0, 0], [1.0, 0, 0, 0]], dtype=D)
    tg = torch.tensor([[0.0, 1], [1.0, 1]], dtype=D)
    T = 12
    tt = [times] * 2 if isinstance(times, int) else times
    res = lqt_cookbook.meeting_lqt(x0, tg, T, 0.1, meet_times=times)
    p = res.problem

    def f(uv):
        u = uv.reshape(T, 4)
        x = rollout(p.dynamics, p.x0, u)
        pos = x.reshape(T + 1, 2, 4)[..., :2]
        end = x[-1].reshape(2, 4) - torch.cat([tg, torch.zeros_like(tg)], -1)
        return (1e3 * (pos[tt[0], 0] - pos[tt[1], 1]).pow(2).sum() + 1e3 * end.pow(2).sum()
                + 1e-2 * u.pow(2).sum())

    # the exact minimizer of the brute-force quadratic (Newton from zero)
    z = torch.zeros(T * 4, dtype=D)
    H = torch.func.hessian(f)(z)
    u_star = z - torch.linalg.solve(H, torch.func.grad(f)(z))
    torch.testing.assert_close(res.solution.u.flatten(), u_star, atol=1e-8, rtol=0)
    torch.testing.assert_close(res.cost, f(u_star))
    # the gap at the meeting is pulled in (was ignored: 1.0)
    gap = (res.positions[tt[0], 0] - res.positions[tt[1], 1]).norm()
    assert gap < 0.5


def test_meeting_at_time_zero_is_rejected():
    x0 = torch.tensor([[0.0, 0, 0, 0], [1.0, 0, 0, 0]], dtype=D)
    tg = torch.tensor([[0.0, 1], [1.0, 1]], dtype=D)
    with pytest.raises(ValueError, match="'meet_times'"):
        lqt_cookbook.meeting_lqt(x0, tg, 10, 0.1, meet_times=0)
    with pytest.raises(ValueError, match="'meet_times'"):
        lqt_cookbook.meeting_lqt(x0, tg, 10, 0.1, meet_times=[0, 0])
    lqt_cookbook.meeting_lqt(x0, tg, 10, 0.1, meet_times=[0, 5])  # one agent goes where the other started


# ---------------------------------------------------------------------------------------------- tennis


def test_tennis_serve_model_and_solution():
    hands = torch.tensor([[[-0.3, 0.0], [0.3, 0.0]], [[-0.4, 0.1], [0.2, 0.0]]], dtype=D)
    target = torch.tensor([[3.0, 1.0], [2.5, 1.5]], dtype=D)
    r = lqt_cookbook.tennis_serve_lqt(hands, target, T=40, dt=0.04)
    assert r.solution.status.all_converged
    ric = riccati.solve(r.problem, grad="none")  # a different formulation of the same problem (Eq. 64)
    torch.testing.assert_close(r.solution.u, ric.u, atol=1e-6, rtol=1e-6)
    P, x = r.positions, r.solution.x
    # carried: the ball moves with the left hand until the release
    torch.testing.assert_close(P[:, :r.t_release + 1, 2], P[:, :r.t_release + 1, 0], atol=1e-12, rtol=0)
    # hit: the ball takes the right hand's velocity (plus gravity over the step)
    th = r.t_hit
    torch.testing.assert_close(x[:, th + 1, 14:16], x[:, th, 8:10] + 0.04 * x[:, th, 16:18])
    # free flight: gravity only
    acc = (x[:, th + 3, 14:16] - x[:, th + 2, 14:16]) / 0.04
    torch.testing.assert_close(acc, torch.tensor([0.0, -9.81], dtype=D).expand(2, 2))
    assert (P[:, th, 1] - P[:, th, 2]).norm(dim=-1).max() < 1e-2
    assert (P[:, -1, 2] - target).norm(dim=-1).max() < 1e-2
    r1 = lqt_cookbook.tennis_serve_lqt(hands[1], target[1], T=40, dt=0.04)
    torch.testing.assert_close(r1.solution.u, r.solution.u[1], atol=1e-9, rtol=0)
    with pytest.raises(ValueError, match="multiple of 4"):
        lqt_cookbook.tennis_serve_lqt(hands, target, T=42)
    with pytest.raises(ValueError, match="'hands0'"):
        lqt_cookbook.tennis_serve_lqt(hands[..., :1], target)
    with pytest.raises(TypeError, match="dtypes"):
        lqt_cookbook.tennis_serve_lqt(hands, target.float())
