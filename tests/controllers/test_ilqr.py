"""iLQR: against the Riccati LQR, a generic optimizer, each formulation against the other, implicit gradients
by gradcheck / finite differences / unrolled autograd, batching and bad elements."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from controllers import riccati
from controllers.costs import QuadraticCost
from controllers.dynamics import LinearDynamics, NonlinearDynamics
from controllers.ilqr import ILQROptions, ILQRProblem, ILQRSolution, ilqr
from controllers.problem import GradMode, LQProblem, Reason
from controllers.systems import CartPole, Pendulum

D64 = torch.float64
TIGHT = ILQROptions(max_iter=100, tol=1e-12, tol_cost=0.0)



def _linear_problem(seed=0, B=3, T=6, n=3, m=2, limits=None):
    g = torch.Generator().manual_seed(seed)
    A = torch.eye(n, dtype=D64) + 0.2 * torch.randn(B, T, n, n, generator=g, dtype=D64)
    Bm = torch.randn(B, T, n, m, generator=g, dtype=D64)
    c = 0.1 * torch.randn(B, T, n, generator=g, dtype=D64)
    Q = torch.eye(n, dtype=D64).expand(T + 1, n, n).clone()
    Q[-1] *= 10
    R = torch.tensor([[0.2, 0.05], [0.05, 0.1]], dtype=D64)
    N = 0.05 * torch.ones(n, m, dtype=D64)
    cost = QuadraticCost(Q=Q, R=R, N=N, x_ref=torch.randn(B, T + 1, n, generator=g, dtype=D64),
                         u_ref=0.1 * torch.ones(m, dtype=D64))
    x0 = 2 * torch.randn(B, n, generator=g, dtype=D64)
    lo, hi = (None, None) if limits is None else (-limits, limits)
    return LinearDynamics(A, Bm, c), cost, x0, T, lo, hi


def _pendulum_problem(x0, length=1.0, T=12, umax=2.0, target=1.0, dt=0.1):
    p = Pendulum(length=length, dt=dt, damping=0.1)
    Q = torch.diag(torch.tensor([1.0, 0.1], dtype=x0.dtype)).expand(T + 1, 2, 2)
    x_ref = target if isinstance(target, torch.Tensor) else torch.tensor([target, 0.0], dtype=x0.dtype)
    cost = QuadraticCost(Q=Q, R=torch.tensor([[0.05]], dtype=x0.dtype), x_ref=x_ref)
    return ILQRProblem(p, cost, x0, T, u_lower=-umax, u_upper=umax)


@pytest.mark.parametrize("method", ["recursive", "batch"])
def test_linear_quadratic_equals_riccati(method):
    dyn, cost, x0, T, _, _ = _linear_problem()
    ref = riccati.solve(LQProblem(dyn, cost, x0))
    sol = ilqr(ILQRProblem(dyn, cost, x0, T), method=method, grad="none")
    assert isinstance(sol, ILQRSolution)
    assert bool(sol.status.converged.all())
    assert int(sol.status.iterations.max()) <= 2  # Gauss-Newton is exact on an LQ problem
    torch.testing.assert_close(sol.u, ref.u, atol=1e-9, rtol=0)
    torch.testing.assert_close(sol.x, ref.x, atol=1e-9, rtol=0)
    torch.testing.assert_close(sol.cost, ref.cost, atol=1e-8, rtol=1e-10)
    torch.testing.assert_close(sol.K, ref.K, atol=1e-9, rtol=0)
    torch.testing.assert_close(sol.k, ref.k, atol=1e-9, rtol=0)


@pytest.mark.parametrize("method", ["recursive", "batch"])
def test_linear_with_limits_against_lbfgsb(method):
    scipy_opt = pytest.importorskip("scipy.optimize")
    from controllers.lifted import transfer_matrices

    dyn, cost, x0, T, lo, hi = _linear_problem(seed=1, B=2, limits=0.6)
    sol = ilqr(ILQRProblem(dyn, cost, x0, T, u_lower=lo, u_upper=hi), method=method, grad="none",
               options=TIGHT)
    assert bool(sol.status.converged.all())
    n_cl = int(sol.clamped.sum())
    assert 0 < n_cl < sol.clamped.numel()  # the regime: some controls on their limits, some not
    # reference: the same QP over the stacked controls, x = S_x x0 + S_u u + s_c, by L-BFGS-B
    Sx, Su, sc = transfer_matrices(dyn.A, dyn.B, dyn.c, T)
    for b in range(2):
        cb = QuadraticCost(Q=cost.Q, R=cost.R, N=cost.N, x_ref=cost.x_ref[b], u_ref=cost.u_ref)

        def f(uv, b=b, cb=cb):
            u = torch.as_tensor(uv, dtype=D64).reshape(1, T, 2).requires_grad_(True)
            x = (Sx[b] @ x0[b] + Su[b] @ u.reshape(-1) + sc[b]).reshape(1, T + 1, 3)
            J = cb.evaluate(x, u)
            (gu,) = torch.autograd.grad(J.sum(), u)
            return float(J.detach().sum()), gu.reshape(-1).numpy()
        r = scipy_opt.minimize(f, np.zeros(T * 2), jac=True, method="L-BFGS-B",
                               bounds=[(-0.6, 0.6)] * (T * 2),
                               options={"ftol": 1e-15, "gtol": 1e-11, "maxiter": 2000})
        np.testing.assert_allclose(sol.u[b].reshape(-1).numpy(), r.x, atol=2e-5)
        assert float(sol.cost[b]) <= r.fun + 1e-8


def test_nonlinear_against_generic_optimizer_and_formulations():
    scipy_opt = pytest.importorskip("scipy.optimize")
    x0 = torch.tensor([[0.3, 0.0], [-0.2, 0.5]], dtype=D64)
    prob = _pendulum_problem(x0, T=10)
    rec = ilqr(prob, method="recursive", grad="none", options=TIGHT)
    bat = ilqr(prob, method="batch", grad="none", options=TIGHT)
    assert bool(rec.status.converged.all()) and bool(bat.status.converged.all())
    assert int(rec.clamped.sum()) > 0 and int((~rec.clamped).sum()) > 0
    torch.testing.assert_close(rec.cost, bat.cost, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(rec.u, bat.u, atol=1e-7, rtol=0)
    # shooting cost J(u) minimized by L-BFGS-B with autograd gradients
    for b in range(2):
        def f(uv, b=b):
            u = torch.as_tensor(uv, dtype=D64).reshape(1, 10, 1).requires_grad_(True)
            xs = [x0[b:b + 1]]
            for t in range(10):
                xs.append(prob.dynamics.step(xs[-1], u[:, t], t))
            J = prob.cost.evaluate(torch.stack(xs, -2), u).sum()
            (gu,) = torch.autograd.grad(J, u)
            return float(J.detach()), gu.reshape(-1).numpy()
        r = scipy_opt.minimize(f, np.zeros(10), jac=True, method="L-BFGS-B", bounds=[(-2.0, 2.0)] * 10,
                               options={"ftol": 1e-15, "gtol": 1e-10, "maxiter": 1000})
        assert float(rec.cost[b]) <= r.fun + 1e-9
        np.testing.assert_allclose(rec.u[b].reshape(-1).numpy(), r.x, atol=1e-4)


def test_swing_up_batch_and_recursive_reach_same_cost():
    # a genuine swing-up (limits active, several iterations) with both formulations
    x0 = torch.tensor([[0.0, 0.0], [0.2, -0.3]], dtype=D64)
    T = 30
    Q = torch.diag(torch.tensor([1.0, 0.1], dtype=D64))
    cost = QuadraticCost(Q=torch.cat([Q.expand(T, 2, 2), 100 * Q[None]]), R=torch.tensor([[0.01]], dtype=D64),
                         x_ref=torch.tensor([math.pi, 0.0], dtype=D64))
    prob = ILQRProblem(Pendulum(dt=0.1, damping=0.1), cost, x0, T, u_lower=-4.0, u_upper=4.0)
    opts = ILQROptions(max_iter=300)
    rec = ilqr(prob, method="recursive", grad="none", options=opts)
    bat = ilqr(prob, method="batch", grad="none", options=opts)
    assert bool(rec.status.converged.all()) and bool(bat.status.converged.all())
    assert float(rec.x[:, -1, 0].min()) > 2.5  # swung up from hanging (0) towards upright (π)
    assert int(rec.clamped.sum()) > 0
    torch.testing.assert_close(rec.cost, bat.cost, rtol=1e-6, atol=0)
    assert int(rec.status.iterations.min()) > 3
    h = rec.cost_history
    assert bool((h[1:] <= h[:-1] + 1e-9 * h[:-1].abs()).all())  # monotone (Algorithm 1)


def _grad_problem(x0, length, target):
    return _pendulum_problem(x0, length=length, T=8, umax=1.5, target=target)


def test_implicit_gradients_gradcheck_with_active_and_inactive_limits():
    x0 = torch.tensor([[0.3, 0.0], [-0.2, 0.5]], dtype=D64, requires_grad=True)
    length = torch.tensor([1.0, 1.3], dtype=D64, requires_grad=True)
    target = torch.tensor([1.0, 0.0], dtype=D64, requires_grad=True)
    sol = ilqr(_grad_problem(x0, length, target), options=TIGHT)
    assert bool(sol.status.converged.all())
    n_cl = int(sol.clamped.sum())
    assert 0 < n_cl < sol.clamped.numel()
    # no control is within 1e-3 of a limit without being clamped (finite differences stay in one regime)
    near = (sol.u.detach().abs() - 1.5).abs() < 1e-3
    assert bool((near == sol.clamped).all())

    def f(x0, length, target):
        s = ilqr(_grad_problem(x0, length, target), options=TIGHT)
        return s.u, s.x, s.cost

    assert torch.autograd.gradcheck(f, (x0, length, target), eps=1e-6, atol=1e-6, rtol=1e-4)


def test_implicit_matches_unrolled_and_finite_differences():
    x0 = torch.tensor([[0.3, 0.1]], dtype=D64)
    length = torch.tensor(1.1, dtype=D64, requires_grad=True)
    w = torch.linspace(-1, 1, 8, dtype=D64).view(1, 8, 1)
    grads = {}
    for mode in (GradMode.IMPLICIT, GradMode.UNROLLED):
        s = ilqr(_grad_problem(x0, length, 1.0), grad=mode, options=TIGHT)
        (grads[mode],) = torch.autograd.grad((s.u * w).sum() + s.cost.sum(), length)
    h = 1e-4
    vals = []
    for L in (1.1 + h, 1.1 - h):
        s = ilqr(_grad_problem(x0, torch.tensor(L, dtype=D64), 1.0), grad="none", options=TIGHT)
        vals.append(float((s.u * w).sum() + s.cost.sum()))
    fd = (vals[0] - vals[1]) / (2 * h)
    assert abs(float(grads[GradMode.IMPLICIT]) - fd) < 1e-6 * max(1.0, abs(fd))
    assert abs(float(grads[GradMode.UNROLLED]) - float(grads[GradMode.IMPLICIT])) < 1e-6


def test_cartpole_parameter_gradient_by_finite_differences():
    x0 = torch.tensor([[0.0, 0.3, 0.0, 0.0]], dtype=D64)
    T = 10
    Q = torch.diag(torch.tensor([1.0, 5.0, 0.1, 0.1], dtype=D64)).expand(T + 1, 4, 4)
    cost = QuadraticCost(Q=Q, R=torch.tensor([[0.01]], dtype=D64))

    def solve(L, grad="implicit"):
        return ilqr(ILQRProblem(CartPole(length=L, dt=0.05), cost, x0, T, u_lower=-5.0, u_upper=5.0),
                    grad=grad, options=TIGHT)

    L = torch.tensor(0.5, dtype=D64, requires_grad=True)
    s = solve(L)
    assert bool(s.status.converged.all())
    (g,) = torch.autograd.grad(s.u.sum(), L)
    h = 1e-5
    fd = (float(solve(torch.tensor(0.5 + h, dtype=D64), "none").u.sum())
          - float(solve(torch.tensor(0.5 - h, dtype=D64), "none").u.sum())) / (2 * h)
    assert abs(float(g) - fd) < 1e-5 * max(1.0, abs(fd))


def test_batched_equals_per_sample_loop():
    x0 = torch.tensor([[0.0, 0.0], [0.4, 0.1], [-0.3, 0.2]], dtype=D64)
    length = torch.tensor([0.8, 1.0, 1.2], dtype=D64)
    prob = _pendulum_problem(x0, length=length, T=15, target=2.0)
    sol = ilqr(prob, grad="none")
    for b in range(3):
        one = ilqr(_pendulum_problem(x0[b], length=float(length[b]), T=15, target=2.0), grad="none")
        torch.testing.assert_close(one.u, sol.u[b], atol=1e-9, rtol=0)
        torch.testing.assert_close(one.cost, sol.cost[b], atol=1e-9, rtol=1e-12)
        assert int(one.status.iterations) == int(sol.status.iterations[b])


def test_nan_element_does_not_poison_the_batch():
    x0 = torch.tensor([[0.3, 0.0], [math.nan, 0.0], [-0.2, 0.5]], dtype=D64, requires_grad=True)
    target = torch.tensor([1.0, 0.0], dtype=D64, requires_grad=True)
    sol = ilqr(_grad_problem(x0, 1.0, target), options=TIGHT)
    assert sol.status.reason_names() == ["CONVERGED", "NONFINITE_INPUT", "CONVERGED"]
    assert bool(torch.isnan(sol.u[1]).all()) and bool(torch.isnan(sol.cost[1]))
    clean = ilqr(_grad_problem(x0.detach()[[0, 2]], 1.0, target.detach()), grad="none", options=TIGHT)
    torch.testing.assert_close(sol.u[[0, 2]].detach(), clean.u, atol=1e-10, rtol=0)
    (g,) = torch.autograd.grad(sol.cost[[0, 2]].sum() + sol.u[[0, 2]].sum(), target)
    assert bool(torch.isfinite(g).all())


def test_unconverged_elements_are_flagged_not_detached():
    x0 = torch.tensor([[0.0, 0.0]], dtype=D64, requires_grad=True)
    prob = _pendulum_problem(x0, T=30, umax=3.0, target=math.pi)
    sol = ilqr(prob, options=ILQROptions(max_iter=2))
    assert sol.status.reason_names() == ["MAX_ITERATIONS"]
    assert not bool(sol.status.converged.any())
    assert int(sol.status.iterations) == 2 and sol.cost_history.shape[0] == 3
    assert sol.u.requires_grad
    (g,) = torch.autograd.grad(sol.cost.sum(), x0)
    assert bool(torch.isfinite(g).all())


def test_generic_cost_and_torch_func_dynamics_paths():
    # the same pendulum problem through NonlinearDynamics without a Jacobian (torch.func) and a cost that
    # only has evaluate() (autograd derivatives) gives the same solution as the analytic path
    x0 = torch.tensor([[0.3, 0.0], [-0.2, 0.5]], dtype=D64)
    prob = _pendulum_problem(x0, T=10)

    class OnlyEvaluate:
        def __init__(self, c):
            self.c = c

        def evaluate(self, x, u):
            return self.c.evaluate(x, u)

    p = prob.dynamics
    dyn = NonlinearDynamics(f=lambda x, u, t: p.step(x, u), n=2, m=1)
    prob2 = ILQRProblem(dyn, OnlyEvaluate(prob.cost), x0, 10, u_lower=-2.0, u_upper=2.0)
    a = ilqr(prob, grad="none", options=TIGHT)
    b = ilqr(prob2, grad="none", options=TIGHT)
    torch.testing.assert_close(a.u, b.u, atol=1e-9, rtol=0)
    torch.testing.assert_close(a.K, b.K, atol=1e-9, rtol=0)


def test_float32_default_and_policy_gains():
    x0 = torch.tensor([[0.3, 0.0]], dtype=torch.float32)
    sol = ilqr(_pendulum_problem(x0, T=10), grad="none")
    assert sol.u.dtype == torch.float32 and bool(sol.status.converged.all())
    # the local policy u = clip(K x + k) reproduces the solution along the solution
    u = (sol.K @ sol.x[..., :-1, :].unsqueeze(-1)).squeeze(-1) + sol.k
    torch.testing.assert_close(u.clamp(-2, 2), sol.u, atol=1e-5, rtol=0)
    assert bool((sol.K[sol.clamped] == 0).all())


def test_bad_input():
    x0 = torch.zeros(2, 2, dtype=D64)
    prob = _pendulum_problem(x0)
    with pytest.raises(ValueError, match="x0"):
        ILQRProblem(prob.dynamics, prob.cost, torch.zeros(2, 3, dtype=D64), 12)
    with pytest.raises(ValueError, match=r"u_lower \(1.0\) must be <= u_upper \(-1.0\)"):
        ILQRProblem(prob.dynamics, prob.cost, x0, 12, u_lower=1.0, u_upper=-1.0)
    with pytest.raises(TypeError, match="dynamics"):
        ILQRProblem(object(), prob.cost, x0, 12)
    with pytest.raises(ValueError, match="horizon"):
        ILQRProblem(prob.dynamics, prob.cost, x0, 0)
    with pytest.raises(ValueError, match="u_init"):
        ilqr(prob, torch.zeros(2, 5, 1, dtype=D64))
    with pytest.raises(TypeError, match="dtype"):
        ILQRProblem(prob.dynamics, prob.cost, x0.float(), 12)
    assert int(Reason.CONVERGED) == 0


def test_crossed_tensor_limits_are_a_per_element_status():
    """Tensor limits with u_lower > u_upper in one element: that element is INFEASIBLE_BOUNDS with NaN
    outputs, the others are solved exactly as alone; building the problem never reads device values."""
    x0 = torch.tensor([[0.3, 0.0], [2.8, 0.0], [-0.5, 0.1]], dtype=D64)
    prob = _pendulum_problem(x0)
    lo = torch.full((3, 1, 1), -2.0, dtype=D64)
    hi = torch.full((3, 1, 1), 2.0, dtype=D64)
    lo[1] = 3.0  # crossed for element 1 only
    crossed = ILQRProblem(prob.dynamics, prob.cost, x0, 12, u_lower=lo, u_upper=hi)
    sol = ilqr(crossed, grad="none")
    assert sol.status.reason_names()[1] == "INFEASIBLE_BOUNDS"
    assert bool(torch.isnan(sol.u[1]).all()) and bool(torch.isnan(sol.cost[1]))
    assert bool(torch.isnan(sol.K[1]).all()) and bool(torch.isnan(sol.k[1]).all())
    assert bool(torch.isnan(sol.kkt_residual[1]))
    for i in (0, 2):
        alone = ilqr(ILQRProblem(prob.dynamics, prob.cost, x0[i], 12, u_lower=-2.0, u_upper=2.0), grad="none")
        torch.testing.assert_close(sol.u[i], alone.u, atol=1e-10, rtol=0)
        assert sol.status.reason_names()[i] == alone.status.reason_names()[0]


def test_residual_cost_reaching_task_eq_102_108():
    # planar 2-link arm with velocity commands (seed §9.1): residual f(x) = f_ee(x) - μ at two via points
    from controllers.costs import ResidualCost

    T, dt = 16, 0.1
    lengths = torch.tensor([1.0, 0.8], dtype=D64)

    def fk(q):
        a, b = q[..., 0], q[..., 0] + q[..., 1]
        return torch.stack([lengths[0] * torch.cos(a) + lengths[1] * torch.cos(b),
                            lengths[0] * torch.sin(a) + lengths[1] * torch.sin(b)], -1)

    dyn = LinearDynamics(torch.eye(2, dtype=D64), dt * torch.eye(2, dtype=D64))
    Q = torch.zeros(T + 1, 2, 2, dtype=D64)
    Q[T] = 100 * torch.eye(2)
    Q[T // 2] = 10 * torch.eye(2)
    x0 = torch.tensor([[0.3, 0.5], [0.1, 1.0]], dtype=D64)

    def problem(mu):
        cost = ResidualCost(lambda x: fk(x) - mu.unsqueeze(-2), Q, 0.01 * torch.eye(2, dtype=D64))
        return ILQRProblem(dyn, cost, x0, T, u_lower=-1.5, u_upper=1.5)

    mu = torch.tensor([[0.5, 1.2], [0.2, 1.4]], dtype=D64, requires_grad=True)
    rec = ilqr(problem(mu), options=TIGHT)
    bat = ilqr(problem(mu), method="batch", grad="none", options=TIGHT)  # Eq. 108
    assert bool(rec.status.converged.all()) and bool(bat.status.converged.all())
    torch.testing.assert_close(rec.cost.detach(), bat.cost, rtol=1e-9, atol=1e-12)
    assert float((fk(rec.x[:, -1]) - mu).detach().abs().max()) < 0.01  # reached
    (g,) = torch.autograd.grad(rec.cost.sum() + rec.u.sum(), mu)
    h = 1e-5
    for i in range(4):
        e = torch.zeros(4, dtype=D64)
        e[i] = h
        e = e.view(2, 2)
        sp = ilqr(problem(mu.detach() + e), grad="none", options=TIGHT)
        sm = ilqr(problem(mu.detach() - e), grad="none", options=TIGHT)
        fd = float((sp.cost.sum() + sp.u.sum()) - (sm.cost.sum() + sm.u.sum())) / (2 * h)
        assert abs(float(g.view(-1)[i]) - fd) < 1e-5 * max(1.0, abs(fd))


def test_implicit_gradients_on_lq_problem_equal_riccati_gradients():
    # on an LQ problem the iLQR solution is the LQR solution, and so must be its derivatives w.r.t. every
    # problem tensor (compared with the Riccati solver's own implicit backward)
    dyn, cost, x0, T, _, _ = _linear_problem(seed=3, B=2, T=5)
    leaves = [t.detach().clone().requires_grad_(True) for t in (dyn.A, dyn.B, dyn.c, cost.Q, cost.x_ref, x0)]

    def build(A, B, c, Q, x_ref, x0):
        qc = QuadraticCost(Q=Q, R=cost.R, N=cost.N, x_ref=x_ref, u_ref=cost.u_ref)
        return LinearDynamics(A, B, c), qc, x0

    w = torch.linspace(-1, 1, T * 2, dtype=D64).view(1, T, 2)
    d1, c1, z1 = build(*leaves)
    s1 = ilqr(ILQRProblem(d1, c1, z1, T), options=TIGHT)
    g1 = torch.autograd.grad((s1.u * w).sum() + s1.x.sum() + s1.cost.sum(), leaves)
    d2, c2, z2 = build(*leaves)
    s2 = riccati.solve(LQProblem(d2, c2, z2))
    g2 = torch.autograd.grad((s2.u * w).sum() + s2.x.sum() + s2.cost.sum(), leaves)
    for i, (a, b) in enumerate(zip(g1, g2)):
        if i == 3:  # Q: the cost sees only its symmetric part, compare the symmetric parts of the gradients
            a, b = 0.5 * (a + a.mT), 0.5 * (b + b.mT)
            assert float((g1[3] - g1[3].mT).abs().max()) < 1e-12  # ours is symmetric already
        torch.testing.assert_close(a, b, atol=1e-8, rtol=1e-8)


@pytest.mark.parametrize("method", ["recursive", "batch"])
def test_multi_dim_batch_equals_flattened(method):
    g = torch.Generator().manual_seed(5)
    x0 = 0.3 * torch.randn(2, 3, 2, generator=g, dtype=D64)
    length = torch.tensor([[0.8, 1.0, 1.2], [0.9, 1.1, 1.3]], dtype=D64, requires_grad=True)
    a = ilqr(_pendulum_problem(x0, length=length, T=8, umax=1.5), method=method)
    b = ilqr(_pendulum_problem(x0.reshape(6, 2), length=length.reshape(6), T=8, umax=1.5), method=method)
    assert a.u.shape == (2, 3, 8, 1) and a.status.converged.shape == (2, 3)
    torch.testing.assert_close(a.u.reshape(6, 8, 1), b.u, atol=1e-12, rtol=0)
    ga = torch.autograd.grad(a.cost.sum(), length)[0]
    gb = torch.autograd.grad(b.cost.sum(), length)[0]
    torch.testing.assert_close(ga, gb, atol=1e-10, rtol=1e-10)


class _AutogradCost:
    """A cost with no derivatives of its own (iLQR differentiates ``evaluate`` by autograd)."""

    def __init__(self, xr):
        self.xr = xr

    def evaluate(self, x, u):
        return ((x - self.xr.unsqueeze(-2)) ** 2).sum((-1, -2)) + 0.1 * (u**2).sum((-1, -2))


@pytest.mark.parametrize("kind", ["autograd", "residual"])
def test_unrolled_gradients_through_autograd_and_residual_costs(kind):
    """grad="unrolled" differentiates through derivatives that iLQR gets by autograd (a cost without
    ``derivatives``, a ResidualCost without a Jacobian): it must equal the implicit gradient and central
    differences (a detached derivative lost the cost's dependence on its parameters)."""
    from controllers.costs import ResidualCost

    T = 6
    x0 = torch.tensor([[1.0, 0.0], [0.5, 0.2]], dtype=D64)

    def solve(length, xr, grad):
        if kind == "autograd":
            cost = _AutogradCost(xr)
        else:
            eye = torch.eye(2, dtype=D64)
            cost = ResidualCost(lambda x: x - xr.unsqueeze(-2), eye, 0.1 * eye[:1, :1])
        s = ilqr(ILQRProblem(Pendulum(length=length), cost, x0, T, u_lower=-2.0, u_upper=2.0), grad=grad,
                 options=ILQROptions(max_iter=200, tol=1e-13, tol_cost=0.0))
        return s, s.u.sum() + s.x.sum()

    grads = {}
    for grad in ("implicit", "unrolled"):
        L = torch.tensor(1.3, dtype=D64, requires_grad=True)
        xr = torch.zeros(2, 2, dtype=D64, requires_grad=True)
        s, loss = solve(L, xr, grad)
        assert s.status.all_converged
        grads[grad] = torch.autograd.grad(loss, (L, xr))
    h = 1e-6
    fd = (float(solve(torch.tensor(1.3 + h, dtype=D64), torch.zeros(2, 2, dtype=D64), "none")[1])
          - float(solve(torch.tensor(1.3 - h, dtype=D64), torch.zeros(2, 2, dtype=D64), "none")[1])) / (2 * h)
    assert abs(float(grads["implicit"][0]) - fd) < 1e-5 * max(1.0, abs(fd))
    for a, b in zip(grads["unrolled"], grads["implicit"]):
        torch.testing.assert_close(a, b, atol=1e-6, rtol=1e-6)
