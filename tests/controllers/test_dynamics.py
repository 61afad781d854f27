"""controllers.dynamics: LinearDynamics validation and broadcasting, rollout, the System protocol,
linearization (analytic, torch.func, batch-sum) and trajectory Jacobians."""

import pytest
import torch

from controllers.costs import QuadraticCost
from controllers.dynamics import LinearDynamics, NonlinearDynamics, rollout

D = torch.float64


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


# ---- linearize (controllers.dynamics) ---------------------------------------------------------------


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
    from controllers.dynamics import linearize

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
    from controllers.dynamics import jacobians, linearize

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


class _UnicycleNoJacobian:
    """A user-written system: only n, m and step (no Jacobian, not time-invariant)."""

    n, m = 3, 2

    def step(self, x, u, t):
        dt = 0.1
        th = x[..., 2]
        return x + dt * torch.stack([u[..., 0] * torch.cos(th), u[..., 0] * torch.sin(th), u[..., 1]], -1)


def test_a_user_system_is_a_system_and_every_path_agrees():
    """The System protocol: a plain class with n, m, step is accepted by the solvers; its trajectory
    Jacobians (torch.func) equal central differences, and the time-invariant fast path (time folded into
    the batch) equals the per-step loop for the library's models."""
    from controllers.dynamics import System, check_system, step_all, trajectory_jacobians
    from controllers.ilqr import ILQRProblem, ilqr
    from controllers.systems import CartPole, Pendulum

    sysu = _UnicycleNoJacobian()
    assert isinstance(sysu, System) and isinstance(Pendulum(), System)
    g = torch.Generator().manual_seed(3)
    x = torch.randn(4, 6, 3, dtype=D, generator=g)
    u = torch.randn(4, 5, 2, dtype=D, generator=g)
    A, B = trajectory_jacobians(sysu, x, u)
    assert A.shape == (5, 4, 3, 3) and B.shape == (5, 4, 3, 2)
    h = 1e-6
    for j in range(3):
        e = torch.zeros(3, dtype=D)
        e[j] = h
        fd = (step_all(sysu, x[..., :5, :] + e, u) - step_all(sysu, x[..., :5, :] - e, u)) / (2 * h)
        torch.testing.assert_close(A[..., j].movedim(0, -2), fd, atol=1e-8, rtol=0)
    for model in (Pendulum(damping=0.2), CartPole()):
        xm = torch.randn(4, 6, model.n, dtype=D, generator=g)
        um = torch.randn(4, 5, model.m, dtype=D, generator=g)
        fast = trajectory_jacobians(model, xm, um)
        loop = trajectory_jacobians(model, xm, um, time_invariant=False)
        for a, b in zip(fast, loop):
            torch.testing.assert_close(a, b, atol=1e-14, rtol=0)
        loop_x = torch.stack([model.step(xm[..., t, :], um[..., t, :]) for t in range(5)], -2)
        torch.testing.assert_close(step_all(model, xm[..., :5, :], um), loop_x)
    # the solver takes the user's system as is (Jacobians by torch.func)
    target = torch.tensor([1.0, 1.0, 0.0], dtype=D)
    cost = QuadraticCost(torch.eye(3, dtype=D), 0.1 * torch.eye(2, dtype=D), x_ref=target)
    sol = ilqr(ILQRProblem(sysu, cost, torch.zeros(2, 3, dtype=D), 20), grad="none")
    assert sol.status.all_converged
    with pytest.raises(TypeError, match="field 'dynamics' must be a system"):
        check_system(object(), "ILQRProblem")


def test_linearize_of_a_system_model_equals_its_analytic_jacobians():
    """linearize() and the solvers use one path: for a model with analytic Jacobians, the affine model's
    A, B are the model's own and c reproduces f along the trajectory."""
    from controllers.dynamics import linearize, trajectory_jacobians
    from controllers.systems import Pendulum

    p = Pendulum(damping=0.1)
    g = torch.Generator().manual_seed(4)
    x = torch.randn(3, 7, 2, dtype=D, generator=g)
    u = torch.randn(3, 6, 1, dtype=D, generator=g)
    lin = linearize(p, x, u)
    A, B = p.jacobian(x[..., :6, :], u)
    torch.testing.assert_close(lin.A, A)
    torch.testing.assert_close(lin.B, B)
    torch.testing.assert_close(lin.A, trajectory_jacobians(p, x, u)[0].movedim(0, -3))
    nxt = (lin.A @ x[..., :6, :].unsqueeze(-1) + lin.B @ u.unsqueeze(-1)).squeeze(-1) + lin.c
    torch.testing.assert_close(nxt, p.step(x[..., :6, :], u), atol=1e-14, rtol=0)


def test_per_element_parameters_or_matrices_with_an_unbatched_trajectory():
    """A system whose parameters (or matrices) carry the batch while x does not: time is folded into the
    batch in front of the parameters' dims, so step t never sees element t's parameter (it did, silently,
    when T equalled the batch size)."""
    from controllers.dynamics import jacobians, linearize, step_all, trajectory_jacobians
    from controllers.systems import Pendulum

    g = torch.Generator().manual_seed(8)
    L = torch.tensor([1.0, 2.0, 3.0], dtype=D)
    T = 3  # = the parameters' batch size, the case that used to mix them up
    x = torch.randn(T + 1, 2, dtype=D, generator=g)
    u = torch.randn(T, 1, dtype=D, generator=g)
    lin = linearize(Pendulum(length=L), x, u)
    A, B = trajectory_jacobians(Pendulum(length=L), x, u)
    nxt = step_all(Pendulum(length=L), x[:T], u)
    assert lin.A.shape == (3, T, 2, 2) and A.shape == (T, 3, 2, 2) and nxt.shape == (3, T, 2)
    for i in range(3):
        one = Pendulum(length=float(L[i]))
        li = linearize(one, x, u)
        torch.testing.assert_close(lin.A[i], li.A, atol=0, rtol=0)
        torch.testing.assert_close(lin.c[i], li.c, atol=0, rtol=0)
        torch.testing.assert_close(A[:, i], li.A, atol=0, rtol=0)
        torch.testing.assert_close(nxt[i], step_all(one, x[:T], u), atol=0, rtol=0)
    rnd = lambda *s: torch.randn(*s, dtype=D, generator=g)
    d = LinearDynamics(rnd(3, 1, 2, 2), rnd(3, 1, 2, 1))
    y, Aj, Bj = jacobians(d, x[0], u[0])
    assert Aj.shape == (3, 2, 2) and Bj.shape == (3, 2, 1) and y.shape == (3, 2)
    ld = linearize(d, x, u)
    torch.testing.assert_close(ld.A, d.A.expand(3, T, 2, 2))
    torch.testing.assert_close(ld.c, torch.zeros(3, T, 2, dtype=D), atol=1e-14, rtol=0)
