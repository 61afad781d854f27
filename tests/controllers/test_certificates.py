"""A status is a certificate: ``CONVERGED`` only where the optimality (KKT) residual is small at the
returned point, checked here independently of the solver.

The independent residual is the projected gradient ``u − clip(u − ∇_u J)`` with ``∇_u J`` by autograd
through a plain rollout of the system, and scipy's L-BFGS-B started at a certified point must not find
a lower cost.  Before the certificate, batch iLQR reported CONVERGED with projected gradients of 3–64
on a torque-limited arm: its inner box QP returned a zero step with NO_DESCENT, which looked like a
negligible step.
"""

import math

import numpy as np
import pytest
import torch
from scipy.optimize import minimize

from controllers.costs import QuadraticCost
from controllers.ilqr import ILQROptions, ILQRProblem, ilqr
from controllers.problem import Reason
from controllers.systems import Pendulum

D = torch.float64
T = 30


def _swingup(B=6, umax=2.0, seed=0):
    g = torch.Generator().manual_seed(seed)
    sys_ = Pendulum(dt=0.1, damping=0.1)
    x0 = torch.stack([0.5 * torch.randn(B, dtype=D, generator=g), torch.zeros(B, dtype=D)], -1)
    Q = torch.zeros(T + 1, 2, 2, dtype=D)
    Q[:] = 0.01 * torch.eye(2, dtype=D)
    Q[T] = 50 * torch.eye(2, dtype=D)
    ref = torch.tensor([math.pi, 0.0], dtype=D).expand(T + 1, 2)
    cost = QuadraticCost(Q, 0.05 * torch.eye(1, dtype=D), x_ref=ref)
    return sys_, cost, x0, umax


def _rollout_cost(sys_, cost, x0, u):
    xs = [x0]
    for t in range(u.shape[-2]):
        xs.append(sys_.step(xs[-1], u[..., t, :], t))
    return cost.evaluate(torch.stack(xs, -2), u)


def _independent_kkt(sys_, cost, x0, u, umax):
    """Relative projected gradient, computed by autograd through a rollout (not by the solver)."""
    u = u.detach().clone().requires_grad_(True)
    (total,) = torch.autograd.grad(_rollout_cost(sys_, cost, x0, u).sum(), u)
    # the cost's own partial w.r.t. u (x held fixed); the rest is the costate term B_tᵀ λ_{t+1}
    xs = [x0]
    with torch.no_grad():
        for t in range(u.shape[-2]):
            xs.append(sys_.step(xs[-1], u[..., t, :], t))
    (partial,) = torch.autograd.grad(cost.evaluate(torch.stack(xs, -2), u).sum(), u)
    pg = u - torch.clamp(u - total, -umax, umax)
    scale = (partial.abs() + (total - partial).abs()).flatten(-2).amax(-1)
    return (pg.abs().flatten(-2).amax(-1) / scale).detach()


@pytest.mark.parametrize("method", ["recursive", "batch"])
def test_converged_means_kkt_residual_below_tolerance(method):
    sys_, cost, x0, umax = _swingup()
    sol = ilqr(ILQRProblem(sys_, cost, x0, T, -umax, umax), method=method, grad="none",
               options=ILQROptions(max_iter=150))
    kkt = _independent_kkt(sys_, cost, x0, sol.u, umax)
    # the solver's reported residual is the independent one
    torch.testing.assert_close(sol.kkt_residual, kkt, atol=1e-12, rtol=1e-6)
    conv = sol.status.converged
    assert bool((kkt[conv] <= 1e-6).all())
    assert bool((sol.status.reason[~conv] != int(Reason.CONVERGED)).all())
    assert int(conv.sum()) >= 3 and bool(sol.clamped.any())  # the regime: limits active at the optimum
    # L-BFGS-B (bounds) started at every certified point finds no lower cost
    for b in torch.nonzero(conv).flatten().tolist():
        def f(v, b=b):
            u = torch.tensor(v, dtype=D).reshape(1, T, 1).requires_grad_(True)
            J = _rollout_cost(sys_, cost, x0[b:b + 1], u).sum()
            (gr,) = torch.autograd.grad(J, u)
            return J.item(), gr.reshape(-1).numpy()
        res = minimize(f, sol.u[b].reshape(-1).numpy(), jac=True, method="L-BFGS-B",
                       bounds=[(-umax, umax)] * T, options=dict(ftol=1e-15, gtol=1e-12))
        assert res.fun >= sol.cost[b].item() - 1e-7 * abs(sol.cost[b].item()), (b, res.fun, sol.cost[b])


@pytest.mark.parametrize("method", ["recursive", "batch"])
def test_a_stall_is_not_reported_as_converged(method):
    """A huge initial regularization makes the first step negligible at a non-stationary point: that used
    to be CONVERGED (a small step); it is STALLED, with the residual to show it."""
    sys_, cost, x0, umax = _swingup(B=3)
    sol = ilqr(ILQRProblem(sys_, cost, x0, T, -umax, umax), method=method, grad="none",
               options=ILQROptions(mu_init=1e12, mu_max=1e14, max_iter=3))
    kkt = _independent_kkt(sys_, cost, x0, sol.u, umax)
    assert sol.status.reason_names() == ["STALLED"] * 3
    assert bool((kkt > 1e-2).all())
    torch.testing.assert_close(sol.kkt_residual, kkt, atol=1e-12, rtol=1e-6)


def test_max_iterations_at_a_certified_point_is_converged_and_vice_versa():
    """The final status is decided at the returned point: an element stopped by the iteration cap is
    CONVERGED exactly when its residual is below tolerance there."""
    sys_, cost, x0, umax = _swingup(B=6, seed=3)
    for cap in (2, 200):
        sol = ilqr(ILQRProblem(sys_, cost, x0, T, -umax, umax), grad="none",
                   options=ILQROptions(max_iter=cap))
        kkt = _independent_kkt(sys_, cost, x0, sol.u, umax)
        np.testing.assert_array_equal(sol.status.converged.numpy(), (kkt <= 1e-6).numpy())
