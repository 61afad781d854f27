"""A status is a certificate: ``CONVERGED`` only where the optimality (KKT) residual is small at the
returned point, checked here independently of the solver.

The independent residual is the projected gradient ``u − clip(u − ∇_u J)`` with ``∇_u J`` by autograd
through a plain rollout of the system, and scipy's L-BFGS-B started at a certified point must not find
a lower cost.  Before the certificate, batch iLQR reported CONVERGED with projected gradients of 3–64
on a torque-limited arm: its inner box QP returned a zero step with NO_DESCENT, which looked like a
negligible step.
"""

import dataclasses
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


def _schur_curvature(step, cost, x0, u, free):
    """``max_t max_i |(Q_uu,t)_ii|`` by dense linear algebra: the Gauss-Newton Hessian of the shooting cost
    ``H = Sᵀ H_xx S + H_uu`` (``S = ∂x/∂u`` by autograd through a rollout) and, per step, the Schur complement
    of the later free controls in ``H`` (the curvature in ``u_t`` with the later controls re-optimized)."""
    B, T, m = u.shape
    out = []
    for b in range(B):
        def roll(v, b=b):
            xs = [x0[b]]
            for t in range(T):
                xs.append(step(xs[-1], v[t], t))
            return torch.stack(xs)
        S = torch.autograd.functional.jacobian(roll, u[b].detach())  # (T+1, n, T, m)
        n = S.shape[1]
        S = S.reshape((T + 1) * n, T * m)
        with torch.no_grad():
            xs = roll(u[b].detach())
            _, _, Hxx, _, Huu = cost.derivatives(xs[None], u[b:b + 1].detach())
        Hxx = Hxx.expand(1, T + 1, n, n)[0] if Hxx.dim() == 4 else Hxx.expand(T + 1, n, n)
        Huu = Huu.expand(1, T, m, m)[0] if Huu.dim() == 4 else Huu.expand(T, m, m)
        H = S.mT @ torch.block_diag(*Hxx) @ S + torch.block_diag(*Huu)
        f = free[b].reshape(-1)
        best = torch.zeros((), dtype=u.dtype)
        for t in range(T):
            it = torch.arange(t * m, (t + 1) * m)
            later = torch.nonzero(f & (torch.arange(T * m) >= (t + 1) * m)).flatten()
            Q = H[it][:, it]
            if later.numel():
                Q = Q - H[it][:, later] @ torch.linalg.solve(H[later][:, later], H[later][:, it])
            best = torch.maximum(best, Q.diagonal().abs().max())
        out.append(best)
    return torch.stack(out)


def _independent_kkt(sys_, cost, x0, u, umax, free=None):
    """Relative projected gradient, computed by autograd through a rollout (not by the solver): the projected
    gradient over the gradient's terms plus the curvature times the controls (ILQROptions.tol_kkt); with
    ``free=None`` the terms alone (a stricter scale)."""
    u = u.detach().clone().requires_grad_(True)
    (total,) = torch.autograd.grad(_rollout_cost(sys_, cost, x0, u).sum(), u)
    # the cost's own partial w.r.t. u (x held fixed); the rest is the costate term B_tᵀ λ_{t+1}
    xs = [x0]
    with torch.no_grad():
        for t in range(u.shape[-2]):
            xs.append(sys_.step(xs[-1], u[..., t, :], t))
    (partial,) = torch.autograd.grad(cost.evaluate(torch.stack(xs, -2), u).sum(), u)
    pg = total if umax is None else u - torch.clamp(u - total, -umax, umax)
    scale = (partial.abs() + (total - partial).abs()).flatten(-2).amax(-1)
    if free is not None:
        scale = scale + _schur_curvature(sys_.step, cost, x0, u, free) * u.detach().abs().flatten(-2).amax(-1)
    return (pg.abs().flatten(-2).amax(-1) / scale).detach()


@pytest.mark.parametrize("method", ["recursive", "batch"])
def test_converged_means_kkt_residual_below_tolerance(method):
    sys_, cost, x0, umax = _swingup()
    sol = ilqr(ILQRProblem(sys_, cost, x0, T, -umax, umax), method=method, grad="none",
               options=ILQROptions(max_iter=150))
    assert bool((sol.mu == 0).all())  # (the Riccati curvature is then the unregularized Schur complement)
    kkt = _independent_kkt(sys_, cost, x0, sol.u, umax, ~sol.clamped)
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
    kkt = _independent_kkt(sys_, cost, x0, sol.u, umax)  # the terms alone: a stricter scale
    assert sol.status.reason_names() == ["STALLED"] * 3
    assert bool((kkt > 1e-2).all())
    assert bool((sol.kkt_residual > 1e-3).all())


def test_max_iterations_at_a_certified_point_is_converged_and_vice_versa():
    """The final status is decided at the returned point: an element stopped by the iteration cap is
    CONVERGED exactly when its residual is below tolerance there."""
    sys_, cost, x0, umax = _swingup(B=6, seed=3)
    for cap in (2, 200):
        sol = ilqr(ILQRProblem(sys_, cost, x0, T, -umax, umax), grad="none",
                   options=ILQROptions(max_iter=cap))
        kkt = _independent_kkt(sys_, cost, x0, sol.u, umax, ~sol.clamped)
        np.testing.assert_array_equal(sol.status.converged.numpy(), (kkt <= 1e-6).numpy())


def _cookbook_arm(R: float, starts: int):
    """The cookbook's iLQR manipulator (seed 004 §8-9, RCFS iLQR_manipulator_recursive): three links of
    lengths 2, 2, 1 under velocity commands (x_{t+1} = x_t + Δt u_t, Δt = 0.01, T = 49), end-effector pose
    (position and angle) at two via points t = 24 and 49, identity precision, control weight R·I, from
    perturbed starts around x0 = (3π/4, -π/2, -π/4)."""
    from controllers.costs import ResidualCost
    from controllers.dynamics import LinearDynamics

    lengths = torch.tensor([2.0, 2.0, 1.0], dtype=D)
    Tm = 49

    def fk(x):
        c = torch.cumsum(x, -1)
        xy = [(lengths * torch.cos(c)).sum(-1), (lengths * torch.sin(c)).sum(-1)]
        return torch.stack([*xy, c[..., -1]], -1)

    mu = torch.zeros(Tm + 1, 3, dtype=D)
    mu[24] = torch.tensor([2.0, 1.0, -math.pi / 6], dtype=D)
    mu[49] = torch.tensor([3.0, 1.0, -math.pi / 3], dtype=D)
    Q = torch.zeros(Tm + 1, 3, 3, dtype=D)
    Q[24] = Q[49] = torch.eye(3, dtype=D)

    def residual(x):
        e = fk(x) - mu
        return torch.cat([e[..., :2], torch.remainder(e[..., 2:] + math.pi, 2 * math.pi) - math.pi], -1)

    g = torch.Generator().manual_seed(0)
    x0 = torch.tensor([3 * math.pi / 4, -math.pi / 2, -math.pi / 4], dtype=D) + 0.3 * torch.randn(
        starts, 3, generator=g, dtype=D)
    dyn = LinearDynamics(torch.eye(3, dtype=D), 0.01 * torch.eye(3, dtype=D))
    return dyn, ResidualCost(residual, Q, R * torch.eye(3, dtype=D)), x0, Tm


@pytest.mark.parametrize("R", [1e-6, 1e-10])
def test_certificate_does_not_depend_on_how_small_R_is(R):
    """Issue 22 item 5: batch iLQR stopped at |∇J|∞ ≈ 4e-11 on the cookbook manipulator (R = 1e-6) with a
    relative residual of 1.8e-6 over the gradient's terms alone (20 of 64 starts STALLED on main; at
    R = 1e-10, 57 of 64), because those terms shrink with R at the optimum while the gradient a negligible
    step leaves behind does not.  With the curvature in the scale both formulations certify every start,
    and the certified points are optima: the independent residual (autograd through a rollout, dense
    Schur complements) agrees, the two formulations reach the same controls, and the unscaled gradient
    is at the round-off level of the curvature."""
    dyn, cost, x0, Tm = _cookbook_arm(R, 16)
    sols = {m: ilqr(ILQRProblem(dyn, cost, x0, Tm), method=m, grad="none") for m in ("recursive", "batch")}
    for m, sol in sols.items():
        assert sol.status.reason_names() == ["CONVERGED"] * 16, m
        free = torch.ones_like(sol.u, dtype=torch.bool)
        kkt = _independent_kkt(dyn, cost, x0, sol.u, None, free)
        torch.testing.assert_close(sol.kkt_residual, kkt, atol=1e-12, rtol=1e-5)
        assert bool((kkt <= 1e-6).all())
    torch.testing.assert_close(sols["recursive"].u, sols["batch"].u, atol=1e-5, rtol=0)
    torch.testing.assert_close(sols["recursive"].cost, sols["batch"].cost, atol=1e-14, rtol=1e-9)


def _unicycle_problem(R: float, x0):
    from controllers.dynamics import NonlinearDynamics

    D, T, dt = torch.float64, 10, 0.1

    def f(x, u, t):
        px, py, th = x.unbind(-1)
        v, w = u.unbind(-1)
        return torch.stack([px + dt * v * torch.cos(th), py + dt * v * torch.sin(th), th + dt * w], -1)

    cost = QuadraticCost(Q=torch.diag(torch.tensor([1.0, 1.0, 0.1], dtype=D)), R=torch.eye(2, dtype=D) * R,
                         x_ref=torch.tensor([1.0, 0.5, 0.0], dtype=D))
    return ILQRProblem(NonlinearDynamics(f, 3, 2, time_invariant=True), cost, x0, T), f, cost


def _min_hessian_eigenvalue(f, cost, x0, u):
    """The smallest eigenvalue of the exact Hessian of J(u) by autograd through a rollout (independent of
    the solver's Riccati sweep)."""
    T = u.shape[0]

    def J(z):
        us = z.view(T, 2)
        xs = [x0]
        for t in range(T):
            xs.append(f(xs[-1], us[t], t))
        return cost.evaluate(torch.stack(xs), us)

    H = torch.autograd.functional.hessian(J, u.reshape(-1))
    return float(torch.linalg.eigvalsh(H).min())


def test_second_order_check_tells_a_saddle_from_a_minimum():
    """A unicycle from rest with R = 1e-12: Gauss-Newton iLQR stops on a KKT point whose exact Hessian
    has a negative eigenvalue (J = 3.75; the minimum is 1.65). With second_order=True that element is
    NOT_A_MINIMUM; a true minimum (a start with a heading) stays CONVERGED, in the same batch."""
    D = torch.float64
    x0 = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 0.4]], dtype=D)
    prob, f, cost = _unicycle_problem(1e-12, x0)
    plain = ilqr(prob, grad="none")
    checked = ilqr(prob, grad="none", options=ILQROptions(second_order=True))
    assert plain.status.reason.tolist() == [0, 0]
    eig = [_min_hessian_eigenvalue(f, cost, x0[i], plain.u[i]) for i in range(2)]
    assert eig[0] < -1e-3 and eig[1] > 0  # the reference: a saddle, then a minimum
    assert checked.status.reason.tolist() == [int(Reason.NOT_A_MINIMUM), int(Reason.CONVERGED)]
    torch.testing.assert_close(checked.u, plain.u, rtol=0, atol=0)  # the check changes no value


def test_second_order_check_holds_at_a_constrained_minimum():
    """Pendulum swing-ups with active limits: the reduced Hessian on the free controls is PD at the
    certified points, so second_order=True changes no status."""
    D = torch.float64
    x0 = torch.tensor([[0.1, 0.0], [-0.2, 0.3], [0.0, 1.0]], dtype=D)
    cost = QuadraticCost(Q=torch.diag(torch.tensor([1.0, 0.1], dtype=D)), R=torch.tensor([[0.01]], dtype=D),
                         x_ref=torch.tensor([math.pi, 0.0], dtype=D))
    prob = ILQRProblem(Pendulum(dt=0.05), cost, x0, 40, u_lower=-2.0, u_upper=2.0)
    plain = ilqr(prob, grad="none")
    checked = ilqr(prob, grad="none", options=ILQROptions(second_order=True))
    assert bool(plain.clamped.any())  # the regime: some controls on their limits
    assert checked.status.reason.tolist() == plain.status.reason.tolist()
    assert bool(plain.status.converged.all())


def test_second_order_check_refuses_what_it_cannot_decide():
    """A step autograd cannot follow (numpy inside, analytic Jacobian given) would drop the dynamics'
    second derivatives and pass a maximum (x' = x + 0.1u², u = 0); inference mode has no autograd: both
    are ValueErrors instead of a silent CONVERGED or a deep RuntimeError."""
    from controllers.dynamics import NonlinearDynamics

    D = torch.float64

    def opaque(x, u, t):
        return torch.from_numpy((x + 0.1 * u**2).detach().numpy())

    def jac(x, u, t):
        return torch.ones(*x.shape, 1, dtype=D), (0.2 * u).unsqueeze(-1)

    cost = QuadraticCost(Q=torch.eye(1, dtype=D), R=torch.eye(1, dtype=D) * 0.01,
                         x_ref=torch.tensor([5.0], dtype=D))
    prob = ILQRProblem(NonlinearDynamics(opaque, 1, 1, jacobian=jac, time_invariant=True), cost,
                       torch.zeros(1, 1, dtype=D), 4)
    with pytest.raises(ValueError, match="second_order.*step"):
        ilqr(prob, grad="none", options=ILQROptions(second_order=True))
    pend_cost = QuadraticCost(Q=torch.eye(2, dtype=D), R=torch.eye(1, dtype=D))
    pend = ILQRProblem(Pendulum(dt=0.05), pend_cost, torch.zeros(1, 2, dtype=D), 5)
    with torch.inference_mode(), pytest.raises(ValueError, match="inference_mode"):
        ilqr(pend, grad="none", options=ILQROptions(second_order=True))


def test_an_optimum_where_everything_is_zero_is_certified():
    """A pendulum held exactly upright (and 1e-9 off): the plan is zero controls, the gradient and its
    terms are rounding, the controls 0 — the relative residual alone was 0/0-like and reported STALLED
    (and a multi-start then preferred a certified full swing).  The scale's floor ``c · tol / tol_kkt``
    certifies it: the Newton step the residual implies is below ``tol``."""
    from controllers.multistart import guesses, ilqr_multistart

    Q = torch.diag(torch.tensor([1.0, 0.1], dtype=D))
    cost = QuadraticCost(Q=Q, R=torch.tensor([[0.01]], dtype=D), x_ref=torch.tensor([math.pi, 0.0], dtype=D))
    x0 = torch.tensor([[math.pi, 0.0], [math.pi + 1e-9, 0.0]], dtype=D)
    p = ILQRProblem(Pendulum(), cost, x0, 20, u_lower=-2.0, u_upper=2.0)
    for method in ("recursive", "batch"):
        sol = ilqr(p, method=method, grad="none", options=ILQROptions(max_iter=10))
        assert sol.status.reason_names() == ["CONVERGED"] * 2
        assert sol.u.abs().max() < 1e-6 and sol.cost.max() < 1e-15
    lo, hi = torch.tensor([-2.0], dtype=D), torch.tensor([2.0], dtype=D)
    best = ilqr_multistart(p, guesses((2,), 20, lo, hi), options=ILQROptions(max_iter=30)).best
    assert best.cost.max() < 1e-15  # the hold, not a certified swing
    # a genuinely non-stationary point is still not certified (the floor is a Newton step below tol)
    far = ilqr(dataclasses.replace(p, x0=torch.tensor([[2.0, 0.0]], dtype=D)), grad="none",
               options=ILQROptions(mu_init=1e12, mu_max=1e14, max_iter=2))
    assert far.status.reason_names() != ["CONVERGED"]


def test_tol_kkt_zero_certifies_nothing_but_an_exact_zero():
    """``tol_kkt = 0`` (certify nothing): the scale's floor ``tol / tol_kkt`` is 0 then, not a division by
    zero, and a point with any residual is not CONVERGED."""
    sys_, cost, x0, umax = _swingup(B=2)
    sol = ilqr(ILQRProblem(sys_, cost, x0, T, -umax, umax), grad="none",
               options=ILQROptions(max_iter=3, tol_kkt=0.0))
    assert (sol.status.reason != int(Reason.CONVERGED)).all()
    assert bool(torch.isfinite(sol.kkt_residual).all())
