"""controllers.ilqr_lifted: Algorithm 4 in z = [x0; w], u = Ψw — against ilqr's batch method (Ψ = I), an
exact Newton solve of the reduced problem by autograd Hessians (LQ problems: one step is the optimum),
and a generic optimizer (scipy) on a nonlinear one; batching, NaN isolation, float32, bad input."""

import pytest
import scipy.optimize
import torch

from controllers.basis import rbf
from controllers.costs import QuadraticCost
from controllers.dynamics import LinearDynamics, rollout
from controllers.ilqr import ILQRProblem, ilqr
from controllers.ilqr_lifted import ilqr_lifted
from controllers.lifted import control_primitives
from controllers.problem import Reason
from liecontrol.bench.solver import cookbook_problem

D = torch.float64


def _lq_problem(B=3, T=12, n=4, m=2, seed=0, dtype=D):
    g = torch.Generator().manual_seed(seed)
    A = torch.eye(n, dtype=dtype) + 0.1 * torch.randn(n, n, generator=g, dtype=dtype)
    Bm = torch.randn(n, m, generator=g, dtype=dtype)
    M = torch.randn(n, n, generator=g, dtype=dtype)
    Q = (M @ M.mT + 0.1 * torch.eye(n, dtype=dtype)).expand(T + 1, n, n)
    R = 0.3 * torch.eye(m, dtype=dtype)
    target = torch.randn(B, T + 1, n, generator=g, dtype=dtype)
    cost = QuadraticCost(Q=Q, R=R, x_ref=target)
    x0 = torch.randn(B, n, generator=g, dtype=dtype)
    return ILQRProblem(LinearDynamics(A, Bm), cost, x0, T)


def _primitives(T, m, K, dtype=D):
    return control_primitives(rbf(T, K, dtype=dtype), m)


def _newton_reference(prob, Psi, x0_weight=None):
    """The exact optimum of an LQ problem in z by one Newton step with autograd's Hessian, per element."""
    T, n, m = prob.T, prob.n, prob.m
    out = []
    for b in range(prob.x0.shape[0]):
        xbar = prob.x0[b]

        def f(z, b=b, xbar=xbar):
            x0, w = (z[:n], z[n:]) if x0_weight is not None else (xbar, z)
            u = (Psi @ w).reshape(T, m)
            x = rollout(prob.dynamics, x0, u)
            e = (x - prob.cost.x_ref[b]).unsqueeze(-1)
            c = (e.mT @ prob.cost.Q @ e).sum()
            c = c + (u.unsqueeze(-2) @ prob.cost.R @ u.unsqueeze(-1)).sum()
            if x0_weight is not None:
                c = c + (x0_weight * (x0 - xbar) ** 2).sum()
            return c

        z0 = torch.zeros((n if x0_weight is not None else 0) + Psi.shape[-1], dtype=D)
        if x0_weight is not None:
            z0[:n] = xbar
        gr = torch.func.grad(f)(z0)
        H = torch.func.hessian(f)(z0)
        out.append(z0 - torch.linalg.solve(H, gr))
    return torch.stack(out)


def test_identity_primitives_are_ilqr_batch_method():
    prob = cookbook_problem()
    a = ilqr(prob, method="batch", grad="none")
    b = ilqr_lifted(prob)
    # the same Gauss-Newton steps; the certificates differ (componentwise here), so one may stop a step
    # earlier: R = 1e-6 makes u ill-conditioned (1e-6 in u is 1e-11 relative in the cost)
    assert bool(a.status.converged) and bool(b.status.converged)
    assert abs(int(b.status.iterations) - int(a.status.iterations)) <= 1
    torch.testing.assert_close(b.cost, a.cost, rtol=1e-10, atol=0)
    torch.testing.assert_close(b.u, a.u, rtol=0, atol=1e-5)


def test_primitives_reach_the_exact_optimum_of_the_reduced_lq_problem():
    prob = _lq_problem()
    Psi = _primitives(prob.T, prob.m, 4)
    sol = ilqr_lifted(prob, Psi)
    assert bool(sol.status.converged.all())
    torch.testing.assert_close(sol.w, _newton_reference(prob, Psi), rtol=1e-8, atol=1e-10)
    torch.testing.assert_close(sol.u, (Psi @ sol.w.unsqueeze(-1)).squeeze(-1).reshape(sol.u.shape))


def test_initial_state_optimization_matches_the_exact_optimum():
    prob = _lq_problem(seed=1)
    Psi = _primitives(prob.T, prob.m, 5)
    wbar = torch.tensor([0.0, 0.0, 10.0, 1e6], dtype=D)  # two entries free, one soft, one pinned
    sol = ilqr_lifted(prob, Psi, x0_weight=wbar)
    assert bool(sol.status.converged.all())
    z = _newton_reference(prob, Psi, wbar)
    torch.testing.assert_close(sol.x0, z[:, :4], rtol=1e-8, atol=1e-9)
    torch.testing.assert_close(sol.w, z[:, 4:], rtol=1e-7, atol=1e-9)
    assert (sol.x0[:, 3] - prob.x0[:, 3]).abs().max() < 1e-4  # the pinned entry stays
    assert (sol.x0[:, :2] - prob.x0[:, :2]).abs().min() > 1e-3  # the free ones moved
    fixed = ilqr_lifted(prob, Psi)
    assert bool((sol.cost <= fixed.cost).all())


def test_nonlinear_problem_against_scipy():
    prob = cookbook_problem()
    T, m = prob.T, prob.m
    Psi = _primitives(T, m, 6)
    sol = ilqr_lifted(prob, Psi)
    assert bool(sol.status.converged.all())

    def f(w):
        wt = torch.tensor(w, dtype=D, requires_grad=True)
        u = (Psi @ wt).reshape(T, m)
        c = prob.cost.evaluate(rollout(prob.dynamics, prob.x0, u), u)
        (gw,) = torch.autograd.grad(c, wt)
        return float(c.detach()), gw.numpy()

    ref = scipy.optimize.minimize(f, torch.zeros(Psi.shape[-1], dtype=D).numpy(), jac=True, method="BFGS",
                                  options={"gtol": 1e-12, "maxiter": 2000})
    assert float(sol.cost) <= ref.fun * (1 + 1e-7)
    assert abs(float(sol.cost) - ref.fun) <= 1e-6 * ref.fun


def test_batched_equals_loop_and_a_nan_element_is_isolated():
    prob = _lq_problem(B=4, seed=2)
    Psi = _primitives(prob.T, prob.m, 4)
    x0 = prob.x0.clone()
    x0[1, 0] = float("nan")
    bad = ILQRProblem(prob.dynamics, prob.cost, x0, prob.T)
    sol = ilqr_lifted(bad, Psi, x0_weight=torch.tensor([0.0, 1.0, 1.0, 1.0], dtype=D))
    assert sol.status.reason.tolist()[1] == int(Reason.NONFINITE_INPUT)
    assert torch.isnan(sol.u[1]).all() and torch.isnan(sol.cost[1])
    for b in (0, 2, 3):
        cost_b = QuadraticCost(Q=prob.cost.Q, R=prob.cost.R, x_ref=prob.cost.x_ref[b])
        one = ilqr_lifted(ILQRProblem(prob.dynamics, cost_b, x0[b], prob.T), Psi,
                          x0_weight=torch.tensor([0.0, 1.0, 1.0, 1.0], dtype=D))
        assert bool(one.status.converged)
        torch.testing.assert_close(sol.u[b], one.u, rtol=1e-10, atol=1e-12)


def test_a_pinned_initial_state_does_not_certify_a_wrong_plan():
    """A stiff x0 block (weight 1e6..1e10) must not hide the controls' gradient (float32 and float64)."""
    from controllers.task_costs import residual_cost, state, track

    for dt, w in ((torch.float32, 1e6), (D, 1e6), (D, 1e10)):
        T, eye = 10, torch.eye(2, dtype=dt)
        Q = torch.zeros(T + 1, 2, 2, dtype=dt)
        Q[-1] = eye
        cost = residual_cost([(track(state(2), torch.tensor([1.0, 1.0], dtype=dt)), Q)], 1e-2 * eye)
        prob = ILQRProblem(LinearDynamics(eye, 0.1 * eye), cost, torch.tensor([1.0, -1.0], dtype=dt), T)
        sol = ilqr_lifted(prob, x0_weight=torch.full((2,), w, dtype=dt))
        free = ilqr_lifted(prob)  # the same problem with x0 fixed exactly
        assert bool(sol.status.converged) and int(sol.status.iterations) >= 1
        # a weight w pins x0 to O(1/w): the cost moves by about that much, not more
        rtol = 1e-5 if dt == torch.float32 else max(1e-8, 10 / w)
        torch.testing.assert_close(sol.cost, free.cost, rtol=rtol, atol=0)


def test_nan_in_a_target_is_that_elements_failure_and_an_empty_batch_is_empty():
    prob = _lq_problem(B=3, seed=4)
    ref = prob.cost.x_ref.clone()
    ref[2, 5, 1] = float("nan")
    bad = ILQRProblem(prob.dynamics, QuadraticCost(Q=prob.cost.Q, R=prob.cost.R, x_ref=ref), prob.x0, prob.T)
    sol = ilqr_lifted(bad)
    assert sol.status.reason.tolist()[2] == int(Reason.DIVERGED) and torch.isnan(sol.u[2]).all()
    torch.testing.assert_close(sol.u[:2], ilqr_lifted(prob).u[:2], rtol=1e-10, atol=1e-12)
    empty = ILQRProblem(prob.dynamics, QuadraticCost(Q=prob.cost.Q, R=prob.cost.R), prob.x0[:0], prob.T)
    sol = ilqr_lifted(empty, _primitives(prob.T, prob.m, 3))
    assert sol.u.shape == (0, prob.T, prob.m) and sol.status.reason.shape == (0,)


def test_float32():
    prob = _lq_problem(dtype=torch.float32)
    sol = ilqr_lifted(prob, _primitives(prob.T, prob.m, 4, dtype=torch.float32))
    assert sol.u.dtype == torch.float32 and bool(sol.status.converged.all())


def test_bad_input_is_named():
    prob = _lq_problem()
    with pytest.raises(ValueError, match="'Psi' must be a"):
        ilqr_lifted(prob, torch.eye(5, dtype=D))
    with pytest.raises(TypeError, match="'Psi' must have the problem's dtype"):
        ilqr_lifted(prob, _primitives(prob.T, prob.m, 4, dtype=torch.float32))
    with pytest.raises(ValueError, match="'x0_weight' must be finite and non-negative"):
        ilqr_lifted(prob, x0_weight=torch.tensor([-1.0, 0, 0, 0], dtype=D))
    with pytest.raises(ValueError, match="'max_iter'"):
        ilqr_lifted(prob, max_iter=0)
    with pytest.raises(ValueError, match="'max_iter'"):
        ilqr_lifted(prob, max_iter=True)
    with pytest.raises(ValueError, match="'mu_init'"):
        ilqr_lifted(prob, mu_init=-1.0)
    with pytest.raises(ValueError, match="'w_init' must be a"):
        ilqr_lifted(prob, _primitives(prob.T, prob.m, 4), w_init=torch.zeros(3, 5, dtype=D))
    with pytest.raises(ValueError, match="do not broadcast"):
        ilqr_lifted(prob, _primitives(prob.T, prob.m, 4), w_init=torch.zeros(7, 8, dtype=D))
    limited = ILQRProblem(prob.dynamics, prob.cost, prob.x0, prob.T, u_lower=-1.0, u_upper=1.0)
    with pytest.raises(ValueError, match="control limits are not supported"):
        ilqr_lifted(limited)
    with pytest.raises(TypeError, match="must be an ILQRProblem"):
        ilqr_lifted("problem")
