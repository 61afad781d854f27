"""Problem dataclasses: shape validation, canonical expansion of the cost, per-element input status."""

import pytest
import torch

from controllers.problem import (
    LinearDynamics,
    LQProblem,
    NonlinearDynamics,
    QuadraticCost,
    Reason,
    SolverStatus,
    rollout,
)

D = torch.float64


def _spd(*shape, k, g, eps=0.1):
    M = torch.randn(*shape, k, k, dtype=D, generator=g)
    return M @ M.mT + eps * torch.eye(k, dtype=D)


def _sym(*shape, k, g):
    M = torch.randn(*shape, k, k, dtype=D, generator=g)
    return M + M.mT


def test_dynamics_shapes_and_broadcasting():
    g = torch.Generator().manual_seed(0)
    A = torch.randn(4, 4, dtype=D, generator=g)
    B = torch.randn(3, 6, 4, 2, dtype=D, generator=g)
    d = LinearDynamics(A, B)
    assert d.A.shape == (1, 4, 4) and d.horizon == 6 and d.batch_shape == (3,)
    assert not d.time_invariant
    with pytest.raises(ValueError, match="'B'.*\\(\\*B, T, 4, m\\)"):
        LinearDynamics(A, torch.randn(3, 2, dtype=D))
    with pytest.raises(ValueError, match="'A' must be square"):
        LinearDynamics(torch.randn(4, 3, dtype=D), torch.randn(4, 2, dtype=D))
    with pytest.raises(ValueError, match="time steps"):
        LinearDynamics(torch.randn(5, 4, 4, dtype=D), torch.randn(6, 4, 2, dtype=D))
    with pytest.raises(ValueError, match="'c'"):
        LinearDynamics(A, B, torch.randn(3, dtype=D))
    with pytest.raises(TypeError, match="dtypes"):
        LinearDynamics(A, B.float())
    with pytest.raises(ValueError, match="do not broadcast"):
        LinearDynamics(torch.randn(2, 6, 4, 4, dtype=D), B)


def test_rollout_matches_manual_loop():
    g = torch.Generator().manual_seed(1)
    A = torch.randn(2, 5, 3, 3, dtype=D, generator=g)
    B = torch.randn(3, 2, dtype=D, generator=g)
    c = torch.randn(2, 5, 3, dtype=D, generator=g)
    x0 = torch.randn(2, 3, dtype=D, generator=g)
    u = torch.randn(2, 5, 2, dtype=D, generator=g)
    x = rollout(LinearDynamics(A, B, c), x0, u)
    xm = [x0]
    for t in range(5):
        xm.append(torch.einsum("bij,bj->bi", A[:, t], xm[-1]) + u[:, t] @ B.T + c[:, t])
    torch.testing.assert_close(x, torch.stack(xm, 1))
    # nonlinear wrapper around the same linear map
    f = lambda x, u, t: torch.einsum("bij,bj->bi", A[:, t], x) + u @ B.T + c[:, t]
    torch.testing.assert_close(rollout(NonlinearDynamics(f, 3, 2), x0, u), x)


@pytest.mark.parametrize("with_N", [False, True])
def test_canonical_expansion_equals_direct_evaluation(with_N):
    g = torch.Generator().manual_seed(2)
    n, m, T, b = 3, 2, 4, 5
    Q = _spd(b, T + 1, k=n, g=g)
    R = _spd(T, k=m, g=g)
    N = 0.1 * torch.randn(b, 1, n, m, dtype=D, generator=g) if with_N else None
    cost = QuadraticCost(Q, R, x_ref=torch.randn(b, T + 1, n, dtype=D, generator=g),
                         u_ref=torch.randn(m, dtype=D, generator=g), N=N,
                         q=torch.randn(b, T + 1, n, dtype=D, generator=g),
                         r=torch.randn(b, T, m, dtype=D, generator=g))
    x = torch.randn(b, T + 1, n, dtype=D, generator=g)
    u = torch.randn(b, T, m, dtype=D, generator=g)
    cc = cost.canonical(T)
    val = ((x.unsqueeze(-2) @ cc.Q @ x.unsqueeze(-1)).sum((-1, -2, -3)) +
           (u.unsqueeze(-2) @ cc.R @ u.unsqueeze(-1)).sum((-1, -2, -3)) +
           2 * (cc.q * x).sum((-1, -2)) + 2 * (cc.r * u).sum((-1, -2)) + cc.const)
    if with_N:
        val = val + 2 * (x[:, :-1].unsqueeze(-2) @ cc.N @ u.unsqueeze(-1)).sum((-1, -2, -3))
    # independent evaluation, one sample and one step at a time
    ref = torch.zeros(b, dtype=D)
    for i in range(b):
        for t in range(T + 1):
            dx = x[i, t] - cost.x_ref[i, t]
            ref[i] += dx @ Q[i, t] @ dx + 2 * cost.q[i, t] @ dx
            if t < T:
                du = u[i, t] - cost.u_ref[0]
                ref[i] += du @ R[t] @ du + 2 * cost.r[i, t] @ du
                if with_N:
                    ref[i] += 2 * dx @ N[i, 0] @ du
    torch.testing.assert_close(val, ref)
    torch.testing.assert_close(cost.evaluate(x, u), ref)


def test_cost_validation_errors():
    g = torch.Generator().manual_seed(3)
    R = torch.eye(2, dtype=D)
    with pytest.raises(ValueError, match="'Q' must be symmetric"):
        QuadraticCost(torch.randn(3, 3, dtype=D, generator=g) + 5 * torch.eye(3, dtype=D), R)
    with pytest.raises(ValueError, match="'Q' must be positive semi-definite"):
        QuadraticCost(-torch.eye(3, dtype=D), R)
    with pytest.raises(ValueError, match="'R' must be positive definite"):
        QuadraticCost(torch.eye(3, dtype=D), torch.zeros(2, 2, dtype=D))
    with pytest.raises(ValueError, match="'x_ref'.*\\(\\*B, T\\+1, 3\\)"):
        QuadraticCost(torch.eye(3, dtype=D), R, x_ref=torch.zeros(4, 2, dtype=D))
    with pytest.raises(ValueError, match="T\\+1 entries"):
        QuadraticCost(torch.eye(3, dtype=D).expand(5, 3, 3), R.expand(5, 2, 2))
    # PSD Q with a zero eigenvalue is fine
    QuadraticCost(torch.diag(torch.tensor([1.0, 0.0, 2.0], dtype=D)), R)


def test_problem_horizon_and_errors():
    A, B = torch.eye(3, dtype=D), torch.ones(3, 1, dtype=D)
    cost = QuadraticCost(torch.eye(3, dtype=D), torch.eye(1, dtype=D))
    with pytest.raises(ValueError, match="cannot infer the horizon"):
        LQProblem(LinearDynamics(A, B), cost, torch.zeros(3, dtype=D))
    p = LQProblem(LinearDynamics(A, B), cost, torch.zeros(3, dtype=D), horizon=7)
    assert p.T == 7 and p.batch_shape == ()
    with pytest.raises(ValueError, match="'x0' must have shape \\(\\*B, 3\\)"):
        LQProblem(LinearDynamics(A, B), cost, torch.zeros(2, dtype=D), horizon=7)
    with pytest.raises(ValueError, match="horizon 4 but the problem horizon is 7"):
        LQProblem(LinearDynamics(A.expand(4, 3, 3), B), cost, torch.zeros(3, dtype=D), horizon=7)
    cost2 = QuadraticCost(torch.eye(2, dtype=D), torch.eye(1, dtype=D))
    with pytest.raises(ValueError, match="n=2"):
        LQProblem(LinearDynamics(A, B), cost2, torch.zeros(3, dtype=D), horizon=3)


def test_input_status_per_element():
    g = torch.Generator().manual_seed(4)
    b, n, m, T = 4, 3, 2, 5
    Q = _spd(b, 1, k=n, g=g)
    Q[2, 0] = -Q[2, 0]  # element 2: Q negative definite
    x0 = torch.randn(b, n, dtype=D, generator=g)
    x0[1, 0] = float("nan")  # element 1: NaN initial state
    p = LQProblem(LinearDynamics(torch.eye(n, dtype=D), torch.ones(n, m, dtype=D)),
                  QuadraticCost(Q, torch.eye(m, dtype=D)), x0, horizon=T)
    st = SolverStatus.from_reason(p.input_status())
    assert st.reason_names() == ["CONVERGED", "NONFINITE_INPUT", "NOT_POSITIVE_DEFINITE", "CONVERGED"]
    assert st.converged.tolist() == [True, False, False, True]
    assert st.reason[1] == Reason.NONFINITE_INPUT


def test_via_points():
    g = torch.Generator().manual_seed(5)
    targets = torch.randn(2, 3, 2, dtype=D, generator=g)
    c = QuadraticCost.via_points(10, [3, 7, 10], targets, 4.0 * torch.eye(2, dtype=D), torch.eye(2, dtype=D))
    assert c.Q.shape == (2, 11, 2, 2) and c.horizon == 10
    nz = (c.Q.abs().sum((-1, -2)) > 0).nonzero()[:, 1].unique().tolist()
    assert nz == [3, 7, 10]
    torch.testing.assert_close(c.x_ref[:, [3, 7, 10]], targets)
    with pytest.raises(ValueError, match="times"):
        QuadraticCost.via_points(5, [3, 7, 10], targets, torch.eye(2, dtype=D), torch.eye(2, dtype=D))


# ---- linearize (controllers.linearize) --------------------------------------------------------------


def _pendulum():
    dt = 0.05

    def f(x, u, t):
        th, om = x[..., 0], x[..., 1]
        om2 = om + dt * (-9.81 * torch.sin(th) + u[..., 0] * (1 + 0.1 * t))
        return torch.stack([th + dt * om2, om2], -1)

    def jac(x, u, t):
        th = x[..., 0]
        z, o = torch.zeros_like(th), torch.ones_like(th)
        dom = torch.stack([-9.81 * dt * torch.cos(th), o], -1)  # d om2 / d(th, om)
        A = torch.stack([torch.stack([o, z], -1) + dt * dom, dom], -2)
        b = dt * (1 + 0.1 * t) * o
        B = torch.stack([dt * b, b], -1).unsqueeze(-1)
        return A, B

    return f, jac


@pytest.mark.parametrize("method", ["vmap", "batch-sum", "analytic"])
def test_linearize_matches_analytic_and_finite_differences(method):
    from controllers.linearize import linearize

    f, jac = _pendulum()
    dyn = NonlinearDynamics(f, 2, 1, jacobian=jac)
    g = torch.Generator().manual_seed(6)
    x = torch.randn(3, 5, 2, dtype=D, generator=g)
    u = torch.randn(3, 5, 1, dtype=D, generator=g)
    lin = linearize(dyn, x, u, method=method)
    for t in range(5):
        A, B = jac(x[:, t], u[:, t], t)
        torch.testing.assert_close(lin.A[:, t], A)
        torch.testing.assert_close(lin.B[:, t], B)
    # the affine model is exact at the expansion point and first-order accurate around it
    y = torch.stack([f(x[:, t], u[:, t], t) for t in range(5)], 1)
    torch.testing.assert_close(lin.step(x[:, 2], u[:, 2], 2), y[:, 2])
    dx = 1e-5 * torch.randn(3, 2, dtype=D, generator=g)
    err = lin.step(x[:, 2] + dx, u[:, 2], 2) - f(x[:, 2] + dx, u[:, 2], 2)
    assert err.abs().max() < 1e-8


def test_linearize_linear_dynamics_is_exact_and_errors():
    from controllers.linearize import jacobians, linearize

    g = torch.Generator().manual_seed(7)
    A = torch.randn(3, 3, dtype=D, generator=g)
    B = torch.randn(3, 2, dtype=D, generator=g)
    c = torch.randn(3, dtype=D, generator=g)
    f = lambda x, u, t: x @ A.T + u @ B.T + c
    x = torch.randn(4, 6, 3, dtype=D, generator=g)
    u = torch.randn(4, 5, 2, dtype=D, generator=g)
    lin = linearize(f, x, u, time_invariant=True)  # x has T+1 steps: the last one is ignored
    torch.testing.assert_close(lin.A, A.expand(4, 5, 3, 3))
    torch.testing.assert_close(lin.B, B.expand(4, 5, 3, 2))
    torch.testing.assert_close(lin.c, c.expand(4, 5, 3))
    with pytest.raises(ValueError, match="T = 5"):
        linearize(f, x[:, :3], u)
    with pytest.raises(ValueError, match="analytic"):
        jacobians(f, x[:, 0], u[:, 0], method="analytic")
