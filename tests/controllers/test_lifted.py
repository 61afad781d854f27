"""Batch least-squares LQT (controllers.lifted) against a dense KKT solve and the seed's variants."""

import dataclasses

import pytest
import torch
from lq_oracle import D, dense_kkt, random_problem, spd

from controllers import basis, lifted
from controllers.costs import QuadraticCost
from controllers.dynamics import LinearDynamics, rollout
from controllers.problem import LQProblem


@pytest.mark.parametrize("features", [dict(), dict(drift=False, cross=False, refs=False, linear=False),
                                      dict(tv=False, cross=False)])
def test_lifted_matches_dense_kkt(features):
    g = torch.Generator().manual_seed(0)
    p = random_problem(g, **features)
    sol = lifted.solve_lifted(p)
    x, u = dense_kkt(p)
    torch.testing.assert_close(sol.u, u, atol=1e-9, rtol=0)
    torch.testing.assert_close(sol.x, x, atol=1e-9, rtol=0)
    torch.testing.assert_close(sol.cost, p.cost.evaluate(x, u), atol=1e-9, rtol=0)
    assert sol.status.all_converged


def test_transfer_matrices_reproduce_rollout():
    g = torch.Generator().manual_seed(1)
    p = random_problem(g, b=(2,), T=5)
    Sx, Su, sc = lifted.transfer_matrices(p.dynamics.A, p.dynamics.B, p.dynamics.c, p.T)
    u = torch.randn(2, 5, p.m, dtype=D, generator=g)
    x = (Sx @ p.x0.unsqueeze(-1)).squeeze(-1) + (Su @ u.flatten(-2).unsqueeze(-1)).squeeze(-1) + sc
    torch.testing.assert_close(x.reshape(2, 6, p.n), rollout(p.dynamics, p.x0, u))


def test_optimal_cost_is_minimal_and_covariance_is_inverse_hessian():
    g = torch.Generator().manual_seed(2)
    p = random_problem(g, b=(), T=4, cross=False)
    sol = lifted.solve_lifted(p, covariance=True)
    # the cost as a function of the stacked controls; its Hessian is 2 Σ_u⁻¹ (Eq. 63, no factor 1/2)
    f = lambda uv: p.cost.evaluate(rollout(p.dynamics, p.x0, uv.reshape(4, p.m)), uv.reshape(4, p.m))
    uv = sol.u.flatten()
    H = torch.autograd.functional.hessian(f, uv)
    torch.testing.assert_close(torch.linalg.inv(H / 2), sol.cov, atol=1e-9, rtol=1e-7)
    gr = torch.func.grad(f)(uv)
    assert gr.abs().max() < 1e-9
    for _ in range(5):
        du = 1e-2 * torch.randn(uv.shape, dtype=D, generator=g)
        assert f(uv + du) > f(uv)


def test_initial_state_optimization_eq65():
    g = torch.Generator().manual_seed(3)
    p = random_problem(g, b=(2,), T=5, cross=False)
    sol = lifted.solve_lifted(p, optimize_x0=True)
    # at the optimum, re-solving from the optimized x0 gives the same controls, and x0 is stationary
    p2 = dataclasses.replace(p, x0=sol.x0)
    sol2 = lifted.solve_lifted(p2)
    torch.testing.assert_close(sol2.u, sol.u, atol=1e-9, rtol=0)
    f = lambda x0: lifted.solve_lifted(dataclasses.replace(p, x0=x0)).cost.sum()
    gr = torch.func.grad(f)(sol.x0)
    assert gr.abs().max() < 1e-8
    # and it beats the given x0
    assert bool((sol.cost <= lifted.solve_lifted(p).cost + 1e-12).all())


def test_smoothness_cost_matches_brute_force():
    g = torch.Generator().manual_seed(4)
    T, n = 8, 2
    A, B = torch.eye(n, dtype=D), 0.1 * torch.eye(n, dtype=D)  # single integrator (§7.2)
    cost = QuadraticCost.via_points(T, [4, 8], torch.randn(2, n, dtype=D, generator=g),
                                    100.0 * torch.eye(n, dtype=D), 1e-3 * torch.eye(n, dtype=D))
    p = LQProblem(LinearDynamics(A, B), cost, torch.zeros(n, dtype=D))
    Rb = 1e-2 * lifted.smoothness_precision(T, n, dtype=D)
    assert Rb[0, 0] == 2e-2 and Rb[0, n] == -1e-2 and Rb[0, 2 * n] == 0
    sol = lifted.solve_lifted(p, Rbig=Rb)
    f = lambda uv: (cost.evaluate(rollout(p.dynamics, p.x0, uv.reshape(T, n)), uv.reshape(T, n) * 0)
                    + uv @ Rb @ uv)
    gr = torch.func.grad(f)(sol.u.flatten())
    assert gr.abs().max() < 1e-8
    torch.testing.assert_close(sol.cost, f(sol.u.flatten()))
    # smoother than with the plain diagonal weight of the same trace
    plain = lifted.solve_lifted(p, Rbig=2e-2 * torch.eye(T * n, dtype=D))
    rough = lambda u: (u[1:] - u[:-1]).pow(2).sum()
    assert rough(sol.u) < rough(plain.u)


def test_full_precision_coupling_time_steps():
    """A precision coupling x_2 and x_5 (cross-time, 'meet in the middle'), vs the dense solve."""
    g = torch.Generator().manual_seed(5)
    p = random_problem(g, b=(), T=5, n=2, m=2, cross=False, linear=False)
    n, T = 2, 5
    Qb = lifted.block_diag_time(p.cost.Q, T + 1).clone()
    Jm = torch.zeros(n, (T + 1) * n, dtype=D)
    Jm[:, 2 * n:3 * n] = torch.eye(n, dtype=D)
    Jm[:, 5 * n:6 * n] = -torch.eye(n, dtype=D)
    Qb = Qb + 10.0 * Jm.T @ Jm  # penalizes x_2 - x_5
    sol = lifted.solve_lifted(p, Qbig=Qb)
    mu = p.cost.x_ref.flatten()

    def f(uv):
        u = uv.reshape(T, 2)
        x = rollout(p.dynamics, p.x0, u).flatten() - mu
        du = u - p.cost.u_ref
        return x @ Qb @ x + (du.unsqueeze(-2) @ p.cost.R @ du.unsqueeze(-1)).sum()

    assert torch.func.grad(f)(sol.u.flatten()).abs().max() < 1e-8
    torch.testing.assert_close(sol.cost, f(sol.u.flatten()))


def test_control_primitives_lqt():
    g = torch.Generator().manual_seed(6)
    p = random_problem(g, b=(), T=12, n=3, m=2, cross=False)
    phi = basis.rbf(12, 4, dtype=D)
    Psi = lifted.control_primitives(phi, 2)
    sol = lifted.solve_lifted(p, Psi=Psi, covariance=True)
    assert sol.w.shape == (8,) and sol.cov.shape == (8, 8)
    torch.testing.assert_close(sol.u.flatten(-2), Psi @ sol.w)

    def f(w):
        u = (Psi @ w).reshape(12, 2)
        return p.cost.evaluate(rollout(p.dynamics, p.x0, u), u)

    assert torch.func.grad(f)(sol.w).abs().max() < 1e-8
    # restricted to a subspace: never better than the unrestricted optimum
    assert bool((sol.cost >= lifted.solve_lifted(p).cost - 1e-10).all())
    # with Ψ = I the primitives solution is the plain one
    eye = lifted.solve_lifted(p, Psi=torch.eye(24, dtype=D))
    torch.testing.assert_close(eye.u, lifted.solve_lifted(p).u)


def test_lifted_batched_equals_loop_and_bad_shapes():
    g = torch.Generator().manual_seed(7)
    p = random_problem(g, b=(3,), T=4)
    sol = lifted.solve_lifted(p)
    for i in range(3):
        pi = LQProblem(
            LinearDynamics(p.dynamics.A[i], p.dynamics.B[i], p.dynamics.c[i]),
            QuadraticCost(*(getattr(p.cost, k)[i] for k in ("Q", "R", "x_ref", "u_ref", "N", "q", "r"))),
            p.x0[i])
        torch.testing.assert_close(lifted.solve_lifted(pi).u, sol.u[i])
    with pytest.raises(ValueError, match="'Rbig'.*\\(\\*B, 8, 8\\)"):
        lifted.solve_lifted(p, Rbig=torch.eye(7, dtype=D))
    with pytest.raises(ValueError, match="'Psi'"):
        lifted.solve_lifted(p, Psi=torch.eye(7, dtype=D))


def test_singular_normal_matrix_is_flagged_per_element():
    g = torch.Generator().manual_seed(8)
    n, m, T = 2, 1, 3
    Q = spd(2, 1, k=n, g=g)
    Q[1] = 0.0  # element 1: Q = 0
    R = torch.ones(2, 1, m, m, dtype=D)
    R[1] = 0.0  # and R = 0: the normal matrix is singular
    p = LQProblem(LinearDynamics(torch.eye(n, dtype=D), torch.ones(n, m, dtype=D)),
                  QuadraticCost(Q, R, check=False), torch.ones(2, n, dtype=D), horizon=T)
    sol = lifted.solve_lifted(p)
    assert sol.status.converged.tolist() == [True, False]
    assert torch.isfinite(sol.u[0]).all()


def _dense_normal_equations(p):
    """The pre-block formulation written out: blockdiag(Q_t), blockdiag(R_t) and the stacked cross term
    as dense matrices, H = Suᵀ Q Su + R + Suᵀ N + Nᵀ Su, g = Suᵀ (Q s0 + q) + r + Nᵀ s0 (Eq. 62)."""
    T, n, m = p.T, p.n, p.m
    cc = p.cost.canonical(T)
    Sx, Su, sc = lifted.transfer_matrices(p.dynamics.A, p.dynamics.B, p.dynamics.c, T)
    Qb, Rb = lifted.block_diag_time(cc.Q, T + 1), lifted.block_diag_time(cc.R, T)
    Nb = torch.cat([lifted.block_diag_time(cc.N, T), torch.zeros(*cc.N.shape[:-3], n, T * m, dtype=D)], -2)
    s0 = (Sx @ p.x0.unsqueeze(-1)).squeeze(-1) + sc
    H = Su.mT @ Qb @ Su + Rb + Su.mT @ Nb + Nb.mT @ Su
    g = (Su.mT @ (Qb @ s0.unsqueeze(-1))).squeeze(-1) + (Su.mT @ cc.q.flatten(-2).unsqueeze(-1)).squeeze(-1)
    g = g + cc.r.flatten(-2) + (Nb.mT @ s0.unsqueeze(-1)).squeeze(-1)
    return H, g, Su, s0


def test_block_lifted_equals_dense_formulation_and_riccati_batched_time_varying():
    from controllers import riccati
    g = torch.Generator().manual_seed(11)
    p = random_problem(g, b=(5,), T=7, n=4, m=2)  # time-varying A, B, c, Q, R, N, refs, linear terms
    H, gv, Su, s0 = _dense_normal_equations(p)
    lq = lifted.lifted_quadratic(p)
    torch.testing.assert_close(lq.H, 0.5 * (H + H.mT), atol=1e-10, rtol=1e-12)
    torch.testing.assert_close(lq.g, gv, atol=1e-10, rtol=1e-12)
    u_dense = torch.linalg.solve(H, -gv)
    sol = lifted.solve_lifted(p)
    torch.testing.assert_close(sol.u.flatten(-2), u_dense, atol=1e-9, rtol=0)
    x_dense = ((Su @ u_dense.unsqueeze(-1)).squeeze(-1) + s0).reshape(5, 8, 4)
    torch.testing.assert_close(sol.x, x_dense, atol=1e-9, rtol=0)
    ric = riccati.solve(p, grad="none")
    torch.testing.assert_close(sol.u, ric.u, atol=1e-9, rtol=0)
    torch.testing.assert_close(sol.cost, ric.cost, atol=1e-8, rtol=1e-10)
    torch.testing.assert_close(sol.cost, p.cost.evaluate(sol.x, sol.u), atol=1e-9, rtol=1e-12)
    # the state part alone is Suᵀ Q Su
    cc = p.cost.canonical(p.T)
    Qb = lifted.block_diag_time(cc.Q, p.T + 1)
    torch.testing.assert_close(lifted.lifted_quadratic(p, state_part=True).Hx, Su.mT @ Qb @ Su,
                               atol=1e-10, rtol=1e-12)


def test_block_lifted_variants_equal_dense_formulation():
    """Eq. 65 (optimized x0) and §7.3 (primitives) with block precisions against dense products."""
    g = torch.Generator().manual_seed(12)
    p = random_problem(g, b=(3,), T=6, n=3, m=2, cross=False, linear=False)
    T, n, m = p.T, p.n, p.m
    cc = p.cost.canonical(T)
    Sx, Su, sc = lifted.transfer_matrices(p.dynamics.A, p.dynamics.B, p.dynamics.c, T)
    Qb, Rb = lifted.block_diag_time(cc.Q, T + 1), lifted.block_diag_time(cc.R, T)
    S = torch.cat([Sx, Su], -1)
    Rz = torch.zeros(3, n + T * m, n + T * m, dtype=D)
    Rz[:, n:, n:] = Rb
    H = S.mT @ Qb @ S + Rz
    gv = (S.mT @ (Qb @ sc.unsqueeze(-1) + cc.q.flatten(-2).unsqueeze(-1))).squeeze(-1)
    gv[:, n:] += cc.r.flatten(-2)
    z = torch.linalg.solve(H, -gv)
    sol = lifted.solve_lifted(p, optimize_x0=True)
    torch.testing.assert_close(sol.x0, z[:, :n], atol=1e-9, rtol=0)
    torch.testing.assert_close(sol.u.flatten(-2), z[:, n:], atol=1e-9, rtol=0)
    Psi = lifted.control_primitives(basis.rbf(T, 3, dtype=D), m)
    s0 = (Sx @ p.x0.unsqueeze(-1)).squeeze(-1) + sc
    Hw = Psi.T @ (Su.mT @ Qb @ Su + Rb) @ Psi
    gw = Psi.T @ (Su.mT @ (Qb @ s0.unsqueeze(-1) + cc.q.flatten(-2).unsqueeze(-1))
                  + cc.r.flatten(-2).unsqueeze(-1))
    w = torch.linalg.solve(Hw, -gw.squeeze(-1))
    torch.testing.assert_close(lifted.solve_lifted(p, Psi=Psi).w, w, atol=1e-9, rtol=0)


def test_block_lifted_float32_and_gradients():
    g = torch.Generator().manual_seed(13)
    p = random_problem(g, b=(2,), T=4, n=3, m=2)
    p32 = LQProblem(LinearDynamics(p.dynamics.A.float(), p.dynamics.B.float(), p.dynamics.c.float()),
                    QuadraticCost(*(getattr(p.cost, k).float() for k in ("Q", "R", "x_ref", "u_ref", "N", "q",
                                                                          "r"))), p.x0.float())
    s32 = lifted.solve_lifted(p32)
    assert s32.u.dtype == torch.float32
    torch.testing.assert_close(s32.u.double(), lifted.solve_lifted(p).u, atol=1e-3, rtol=1e-3)
    # gradients of the optimal controls w.r.t. x0 and the time-varying Q through the block path
    Q0 = p.cost.Q.detach().clone().requires_grad_(True)
    x0 = p.x0.detach().clone().requires_grad_(True)

    def f(Q, x0):
        c = dataclasses.replace(p.cost, Q=0.5 * (Q + Q.mT), check=False)
        return lifted.solve_lifted(dataclasses.replace(p, cost=c, x0=x0)).u

    assert torch.autograd.gradcheck(f, (Q0, x0))


def test_full_matrices_equal_to_the_blocks_give_the_block_solution():
    """Qbig = blockdiag(Q_t), Rbig = blockdiag(R_t), Ψ = I (the generic dense code paths, cross term N
    included) reproduce the block-structured solve."""
    g = torch.Generator().manual_seed(14)
    p = random_problem(g, b=(2,), T=5, n=3, m=2)
    ref = lifted.solve_lifted(p)
    Qb = lifted.block_diag_time(p.cost.Q, p.T + 1)
    Rb = lifted.block_diag_time(p.cost.R, p.T)
    for kw in (dict(Qbig=Qb), dict(Rbig=Rb), dict(Qbig=Qb, Rbig=Rb), dict(Psi=torch.eye(10, dtype=D))):
        sol = lifted.solve_lifted(p, **kw)
        torch.testing.assert_close(sol.u, ref.u, atol=1e-9, rtol=0)
        torch.testing.assert_close(sol.cost, ref.cost, atol=1e-9, rtol=1e-12)


@pytest.mark.parametrize("batch, T", [((), 1), ((), 7), ((3,), 12)])
def test_time_invariant_transfer_matrices_equal_the_time_varying_recursion(batch, T):
    """Constant A, B, c take the doubling / block-Toeplitz path; the same matrices given per step take the
    recursion of Eq. 188: both must agree."""
    g = torch.Generator().manual_seed(5)
    eye = torch.eye(4, dtype=torch.float64)
    A = 0.3 * torch.randn(*batch, 1, 4, 4, generator=g, dtype=torch.float64) + eye
    B = torch.randn(*batch, 1, 4, 2, generator=g, dtype=torch.float64)
    c = torch.randn(*batch, 1, 4, generator=g, dtype=torch.float64)
    fast = lifted.transfer_matrices(A, B, c, T)
    slow = lifted.transfer_matrices(A.expand(*batch, T, 4, 4), B.expand(*batch, T, 4, 2),
                                    c.expand(*batch, T, 4), T)
    for a, b in zip(fast, slow):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("which", ["Psi", "Qbig", "Rbig", "Rbig_x0"])
def test_batched_extra_matrices_broadcast_with_an_unbatched_problem(which):
    g = torch.Generator().manual_seed(7)
    p = random_problem(g, b=(), T=4, cross=False)
    T, n, m = p.T, p.n, p.m
    if which == "Psi":
        M = torch.randn(3, T * m, 2, dtype=D, generator=g)
    elif which == "Qbig":
        M = spd(3, k=(T + 1) * n, g=g)
    else:
        M = spd(3, k=T * m, g=g)
    key = which.split("_")[0]
    kw = dict(optimize_x0=True) if which == "Rbig_x0" else {}
    if which == "Rbig_x0":  # a well-posed x_0 cost
        p = dataclasses.replace(p, cost=dataclasses.replace(p.cost, Q=p.cost.Q + torch.eye(n, dtype=D)))
    sol = lifted.solve_lifted(p, **{key: M}, **kw)
    assert sol.u.shape == (3, T, m) and sol.x.shape == (3, T + 1, n) and sol.x0.shape == (3, n)
    assert sol.status.reason.shape == (3,) and sol.cost.shape == (3,)
    for i in range(3):
        one = lifted.solve_lifted(p, **{key: M[i]}, **kw)
        torch.testing.assert_close(sol.u[i], one.u)
        torch.testing.assert_close(sol.cost[i], one.cost)
    with pytest.raises(ValueError, match=key):
        lifted.solve_lifted(dataclasses.replace(p, x0=p.x0.expand(2, n)), **{key: M}, **kw)


def test_transfer_matrices_zero_horizon():
    g = torch.Generator().manual_seed(8)
    A = torch.randn(2, 1, 3, 3, dtype=D, generator=g)
    B = torch.randn(1, 3, 2, dtype=D, generator=g)
    c = torch.randn(1, 3, dtype=D, generator=g)
    Sx, Su, sc = lifted.transfer_matrices(A, B, c, 0)
    torch.testing.assert_close(Sx, torch.eye(3, dtype=D).expand(2, 3, 3))
    assert Su.shape == (2, 3, 0)
    torch.testing.assert_close(sc, torch.zeros(2, 3, dtype=D))
    Sx, Su, sc = lifted.transfer_matrices(A.expand(2, 4, 3, 3), B, None, 0)  # time-varying path
    torch.testing.assert_close(Sx, torch.eye(3, dtype=D).expand(2, 3, 3))
    assert Su.shape == (2, 3, 0) and sc is None
    with pytest.raises(ValueError, match="'T'"):
        lifted.transfer_matrices(A, B, c, -1)
