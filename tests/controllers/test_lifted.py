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
