"""Error-state MPC on manifolds (seed 003 Algorithm 1): linearization, solvers, gradients, batch behaviour."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
import scipy.optimize
import torch

from controllers.manifold_mpc import (
    ErrorStateMPC,
    error_system,
    manifold_rollout,
    riccati_terminal_weight,
    system_jacobians,
    time_index,
)
from controllers.problem import Reason
from controllers.systems.quadrotor import Quadrotor, QuadrotorSimulator
from torchlie import so3
from torchlie.manifolds import SO3, ProductManifold, Rn

D = torch.float64
N = 6
QW = torch.tensor([50.0] * 3 + [5.0] * 3 + [8.0] * 3, dtype=D)
RW = torch.tensor([0.05, 0.2, 0.2, 0.2], dtype=D)


def _gen(seed=0):
    return torch.Generator().manual_seed(seed)


def _ref(q: Quadrotor, B: int, seed: int = 0):
    """A dynamically *infeasible* but smooth reference: random states near hover, random inputs."""
    g = _gen(seed)
    M = q.manifold
    p = 0.3 * torch.randn(B, N + 1, 3, generator=g, dtype=D)
    v = 0.5 * torch.randn(B, N + 1, 3, generator=g, dtype=D)
    R = so3.exp(0.4 * torch.randn(B, N + 1, 3, generator=g, dtype=D))
    u = torch.tensor([9.81, 0, 0, 0], dtype=D) + torch.randn(B, N, 4, generator=g, dtype=D) * torch.tensor(
        [1.0, 0.5, 0.5, 0.5], dtype=D)
    return M.state(p=p, v=v, R=R), u


def _state(q: Quadrotor, B: int, seed: int = 1):
    g = _gen(seed)
    return q.state(0.3 * torch.randn(B, 3, generator=g, dtype=D),
                   0.5 * torch.randn(B, 3, generator=g, dtype=D),
                   so3.exp(0.4 * torch.randn(B, 3, generator=g, dtype=D)))


# ------------------------------------------------------------------------------------------------------
# linearization (Eq. 20-23, 34)
# ------------------------------------------------------------------------------------------------------


def test_quadrotor_jacobians_analytic_autograd_and_finite_differences():
    q = Quadrotor()
    M = q.manifold
    x = M.random(7, generator=_gen(3), dtype=D)
    u = torch.randn(7, 4, generator=_gen(4), dtype=D)
    f, Jx, Ju = system_jacobians(q, x, u, "analytic")
    f2, Jx2, Ju2 = system_jacobians(q, x, u, "autograd")
    torch.testing.assert_close(Jx, Jx2, rtol=0, atol=1e-12)
    torch.testing.assert_close(Ju, Ju2, rtol=0, atol=1e-12)
    h = 1e-6  # central differences through ⊞ (the chart of Eq. 34)
    for i in range(9):
        e = torch.zeros(9, dtype=D)
        e[i] = h
        fd = (q.f(M.boxplus(x, e), u) - q.f(M.boxplus(x, -e), u)) / (2 * h)
        torch.testing.assert_close(Jx[..., i], fd, rtol=0, atol=1e-7)


@pytest.mark.parametrize("feasible", [True, False])
def test_error_system_is_the_derivative_of_the_exact_error_map(feasible):
    """A, B, c against autograd of Eq. 19: δx_{k+1} = ((x̄_k ⊞ δx) ⊕ Δt f(x̄_k ⊞ δx, ū_k + δu)) ⊟ x̄_{k+1}.

    Eq. 21-22 are exact for a trajectory of the model; on an infeasible reference the ⊟ factor at c
    (``exact_reference=True``) makes them exact, and without it they differ by O(‖c‖)."""
    q = Quadrotor()
    M = q.manifold
    xr, ur = _ref(q, 2)
    if feasible:
        xr = manifold_rollout(q, time_index(M, xr, 0), ur)
    es = error_system(q, xr, ur, exact_reference=not feasible)
    paper = error_system(q, xr, ur)
    if feasible:
        assert float(es.c.abs().max()) < 1e-14
    else:
        assert float((paper.A - es.A).abs().max()) > 1e-3  # the factor matters on this reference
    for b in range(2):
        for k in range(N):
            xk, xk1 = time_index(M, xr[b], k), time_index(M, xr[b], k + 1)

            def err(dx, du, xk=xk, xk1=xk1, uk=ur[b, k]):
                x = M.boxplus(xk, dx)
                return M.boxminus(M.oplus(x, q.dt * q.f(x, uk + du)), xk1)

            z9, z4 = torch.zeros(9, dtype=D), torch.zeros(4, dtype=D)
            A, B = torch.func.jacrev(err, argnums=(0, 1))(z9, z4)
            torch.testing.assert_close(es.A[b, k], A, rtol=0, atol=1e-12)
            torch.testing.assert_close(es.B[b, k], B, rtol=0, atol=1e-12)
            torch.testing.assert_close(es.c[b, k], err(z9, z4), rtol=0, atol=1e-13)


# ------------------------------------------------------------------------------------------------------
# the solve against independent references
# ------------------------------------------------------------------------------------------------------


def _objective_numpy(es, dx0, Q, R, P):
    """Cost of the error-state QP as a function of U, by simulating the linear error system in numpy."""
    A, B, c = (t.detach().numpy() for t in (es.A, es.B, es.c))
    Qn, Rn_, Pn = Q.numpy(), R.numpy(), P.numpy()

    def J(U):
        U = U.reshape(N, -1)
        x, tot = dx0.numpy().copy(), 0.0
        for k in range(N):
            tot += x @ Qn @ x + U[k] @ Rn_ @ U[k]
            x = A[k] @ x + B[k] @ U[k] + c[k]
        return tot + x @ Pn @ x
    return J


def test_unconstrained_riccati_condensed_and_dense_agree():
    q = Quadrotor()
    M = q.manifold
    xr, ur = _ref(q, 3)
    x0 = _state(q, 3)
    Q, R = torch.diag(QW), torch.diag(RW)
    P = 3 * Q
    sols = [ErrorStateMPC(q, N, QW, RW, P, u_lower=-np.inf, u_upper=np.inf, solver=s).solve(x0, xr, ur)
            for s in ("riccati", "qp")]
    torch.testing.assert_close(sols[0].U, sols[1].U, rtol=0, atol=1e-9)
    torch.testing.assert_close(sols[0].cost, sols[1].cost, rtol=1e-10, atol=0)
    assert bool(sols[0].status.converged.all()) and bool(sols[1].status.converged.all())
    es = error_system(q, xr, ur)
    for b in range(3):
        dx0 = M.boxminus(x0[b], time_index(M, xr[b], 0))
        J = _objective_numpy(type(es)(es.A[b], es.B[b], es.c[b]), dx0, Q, R, P)
        # the dense normal equations of J (quadratic): Hessian and gradient by exact differences
        z = np.zeros(N * 4)
        E = np.eye(N * 4)
        H = np.array([[J(E[i] + E[j]) - J(E[i]) - J(E[j]) + J(z) for j in range(N * 4)]
                      for i in range(N * 4)])
        grad = np.array([(J(E[i]) - J(-E[i])) / 2 for i in range(N * 4)])
        dU = np.linalg.solve(H, -grad)
        np.testing.assert_allclose((sols[0].U[b] - ur[b]).numpy().ravel(), dU, atol=1e-8)


def test_box_constrained_solve_matches_lbfgsb_with_controls_on_bounds():
    q = Quadrotor(rate_max=0.4, thrust_min=8.0, thrust_max=11.0)
    M = q.manifold
    xr, ur = _ref(q, 2, seed=5)
    ur = torch.minimum(torch.maximum(ur, torch.tensor(q.u_lower, dtype=D)), torch.tensor(q.u_upper, dtype=D))
    x0 = _state(q, 2, seed=6)
    mpc = ErrorStateMPC(q, N, QW, RW)
    sol = mpc.solve(x0, xr, ur)
    assert mpc.solver == "qp" and sol.status.converged.all()
    assert 0 < int(sol.clamped.sum()) < sol.clamped.numel()  # the regime: some controls on a bound, some not
    es = error_system(q, xr, ur)
    lo = (torch.tensor(q.u_lower, dtype=D) - ur).numpy()
    hi = (torch.tensor(q.u_upper, dtype=D) - ur).numpy()
    for b in range(2):
        dx0 = M.boxminus(x0[b], time_index(M, xr[b], 0))
        J = _objective_numpy(type(es)(es.A[b], es.B[b], es.c[b]), dx0, torch.diag(QW), torch.diag(RW),
                             torch.diag(QW))
        res = scipy.optimize.minimize(J, np.zeros(N * 4), method="L-BFGS-B",
                                      bounds=list(zip(lo[b].ravel(), hi[b].ravel())),
                                      options={"ftol": 1e-15, "gtol": 1e-12, "maxiter": 10000})
        ours = (sol.U[b] - ur[b]).numpy().ravel()
        assert J(ours) <= res.fun + 1e-9 * abs(res.fun)
        np.testing.assert_allclose(ours, res.x, atol=1e-4)  # L-BFGS-B stops early; its cost is not lower
        # KKT of the numpy objective at our point (its gradient by exact differences of a quadratic)
        E = np.eye(N * 4)
        grad = np.array([(J(ours + E[i]) - J(ours - E[i])) / 2 for i in range(N * 4)])
        at_lo, at_hi = ours <= lo[b].ravel() + 1e-12, ours >= hi[b].ravel() - 1e-12
        free = ~(at_lo | at_hi)
        scale = np.abs(grad).max() + 1.0
        assert np.abs(grad[free]).max() < 1e-9 * scale
        assert np.all(grad[at_lo] > -1e-9 * scale) and np.all(grad[at_hi] < 1e-9 * scale)
        assert np.all(ours >= lo[b].ravel() - 1e-12) and np.all(ours <= hi[b].ravel() + 1e-12)


def test_batched_equals_per_sample_and_nan_element_does_not_poison():
    q = Quadrotor(rate_max=1.0)
    xr, ur = _ref(q, 4, seed=7)
    x0 = _state(q, 4, seed=8)
    mpc = ErrorStateMPC(q, N, QW, RW)
    full = mpc.solve(x0, xr, ur)
    for b in range(4):
        one = mpc.solve(x0[b:b + 1], xr[b:b + 1], ur[b:b + 1])
        torch.testing.assert_close(full.U[b:b + 1], one.U, rtol=0, atol=1e-10)
    bad = x0.replace(p=x0.p.clone())
    bad.p[2, 0] = float("nan")
    sol = mpc.solve(bad, xr, ur)
    assert sol.status.reason[2] == Reason.NONFINITE_INPUT and torch.isnan(sol.u[2]).all()
    keep = [0, 1, 3]
    torch.testing.assert_close(sol.U[keep], full.U[keep], rtol=0, atol=1e-10)
    assert bool(sol.status.converged[keep].all())


def test_mixed_batch_box_qp_only_where_needed_equals_per_sample_with_gradients():
    """Elements whose closed form respects the limits keep it; the others get the box QP: values and
    gradients equal those of one-element solves."""
    q = Quadrotor(rate_max=0.6, thrust_min=-1e3, thrust_max=1e3)
    M = q.manifold
    _, ur = _ref(q, 4, seed=21)
    ur = ur.clone()
    ur[..., 1:] = ur[..., 1:].clamp(-0.3, 0.3)
    xr = manifold_rollout(q, _state(q, 4, seed=23), ur)  # a feasible reference
    # elements 0 and 2 start on their reference (a small correction), 1 and 3 far from it
    far = _state(q, 4, seed=22)
    x0 = _where_near(M, time_index(M, xr, 0), far, torch.tensor([True, False, True, False]))
    qw = QW.clone().requires_grad_(True)
    mpc = ErrorStateMPC(q, N, qw, RW)
    full = mpc.solve(x0, xr, ur)
    any_clamped = full.clamped.flatten(1).any(1)
    assert any_clamped.tolist() == [False, True, False, True]
    gfull = torch.autograd.grad(full.u.sum(), qw)[0]
    gsum = torch.zeros_like(gfull)
    for b in range(4):
        one = mpc.solve(x0[b:b + 1], xr[b:b + 1], ur[b:b + 1])
        torch.testing.assert_close(full.U[b:b + 1], one.U, rtol=0, atol=1e-10)
        assert one.clamped.any().item() == any_clamped[b].item()
        gsum += torch.autograd.grad(one.u.sum(), qw)[0]
    torch.testing.assert_close(gfull, gsum, rtol=1e-9, atol=1e-10)


def _where_near(M, ref, far, near_mask):
    """``ref`` nudged slightly where ``near_mask``, ``far`` elsewhere."""
    nudged = M.boxplus(ref, 1e-3 * torch.ones(ref.p.shape[0], M.dim, dtype=D))
    return nudged.replace(p=torch.where(near_mask[:, None], nudged.p, far.p),
                          v=torch.where(near_mask[:, None], nudged.v, far.v),
                          R=torch.where(near_mask[:, None, None], nudged.R, far.R))


def test_bad_inputs_are_named():
    q = Quadrotor()
    xr, ur = _ref(q, 1)
    mpc = ErrorStateMPC(q, N, QW, RW)
    off = _state(q, 1).replace(R=2 * torch.eye(3, dtype=D).expand(1, 3, 3))
    with pytest.raises(ValueError, match="x0"):
        mpc.solve(off, xr, ur)
    with pytest.raises(ValueError, match="u_ref"):
        mpc.solve(_state(q, 1), xr, ur[:, :-1])
    with pytest.raises(ValueError, match="x_ref"):
        mpc.solve(_state(q, 1), xr[:, :-1], ur)
    with pytest.raises(ValueError, match="'Q'"):
        ErrorStateMPC(q, N, torch.ones(5, dtype=D), RW)
    with pytest.raises(ValueError, match="riccati"):
        ErrorStateMPC(q, N, QW, RW, solver="riccati")


# ------------------------------------------------------------------------------------------------------
# gradients
# ------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("bounded", [False, True])
def test_gradients_match_finite_differences(bounded):
    """d(first control)/d(reference input, weights, gravity, state) against central differences."""
    g_ = torch.tensor(9.81, dtype=D, requires_grad=True)
    q = Quadrotor(gravity=g_, rate_max=0.6 if bounded else 1e3, thrust_min=-1e3, thrust_max=1e3)
    xr, ur = _ref(q, 1, seed=11)
    x0 = _state(q, 1, seed=12)
    qw = QW.clone().requires_grad_(True)
    ur = ur.clone().requires_grad_(True)
    dp = torch.zeros(3, dtype=D, requires_grad=True)

    def first(qw, ur, dp, g_):
        qq = Quadrotor(gravity=g_, rate_max=q.rate_max, thrust_min=q.thrust_min, thrust_max=q.thrust_max)
        mpc = ErrorStateMPC(qq, N, qw, RW)
        sol = mpc.solve(x0.replace(p=x0.p + dp), xr, ur)
        return sol.u, sol

    u, sol = first(qw, ur, dp, g_)
    if bounded:
        assert bool(sol.clamped.any()) and not bool(sol.clamped[..., 0, :].all())
    w = torch.tensor([[1.0, -2.0, 0.5, 3.0]], dtype=D)
    grads = torch.autograd.grad((u * w).sum(), (qw, ur, dp, g_))
    args = [qw.detach(), ur.detach(), dp.detach(), g_.detach()]
    h = 1e-6
    for i, gr in enumerate(grads):
        flat = args[i].reshape(-1)
        for j in range(0, flat.numel(), max(1, flat.numel() // 6)):
            plus = [a.clone() for a in args]
            minus = [a.clone() for a in args]
            plus[i].view(-1)[j] += h
            minus[i].view(-1)[j] -= h
            fd = ((first(*plus)[0] - first(*minus)[0]) * w).sum() / (2 * h)
            assert abs(float(gr.reshape(-1)[j]) - float(fd)) < 1e-5 * (1 + abs(float(fd))), (i, j)


def test_gradcheck_unconstrained():
    q = Quadrotor()
    xr, ur = _ref(q, 1, seed=2)
    x0 = _state(q, 1, seed=3)

    def fn(ur, qw):
        return ErrorStateMPC(q, N, qw, RW, u_upper=np.inf, u_lower=-np.inf).solve(x0, xr, ur).U

    assert torch.autograd.gradcheck(fn, (ur.clone().requires_grad_(True), QW.clone().requires_grad_(True)))


# ------------------------------------------------------------------------------------------------------
# other manifolds (autograd system parts), the iterated variant, the terminal weight, closed loop
# ------------------------------------------------------------------------------------------------------


class _RigidBody:
    """Attitude and body rate of a rigid body with torque input: SO(3) × R³ (no analytic Jacobians)."""

    def __init__(self, dt=0.05):
        self.manifold = ProductManifold({"R": SO3(), "w": Rn(3)})
        self.n, self.m, self.dt = 6, 3, dt
        self.J = torch.tensor([1.0, 2.0, 3.0], dtype=D)

    def f(self, x, u):
        w = x["w"]
        wdot = (u - torch.linalg.cross(w, self.J * w)) / self.J
        return torch.cat([w.expand_as(wdot), wdot], -1)


def test_iterated_variant_converges_to_the_true_optimum():
    """§V-D on a reference that is not a trajectory (a constant far attitude): the certified point
    matches L-BFGS on the true nonlinear cost (autograd through the rollout)."""
    sys = _RigidBody()
    M = sys.manifold
    T = 10
    target = so3.exp(torch.tensor([1.2, -0.7, 0.4], dtype=D))
    xr = M.state(R=target.expand(1, T + 1, 3, 3), w=torch.zeros(1, T + 1, 3, dtype=D))
    ur = torch.zeros(1, T, 3, dtype=D)
    x0 = M.state(R=torch.eye(3, dtype=D)[None], w=torch.zeros(1, 3, dtype=D))
    Qw = torch.tensor([10.0] * 3 + [0.1] * 3, dtype=D)
    Rw = torch.full((3,), 0.01, dtype=D)
    mpc = ErrorStateMPC(sys, T, Qw, Rw, u_lower=-3.0, u_upper=3.0)
    sol = mpc.iterate(x0, xr, ur, max_iter=100)
    assert sol.status.reason.tolist() == [int(Reason.CONVERGED)], sol.status.reason_names()
    assert float(sol.kkt_residual) < 1.5e-8

    def cost(Uflat):
        U = torch.as_tensor(Uflat, dtype=D).reshape(1, T, 3).requires_grad_(True)
        x = manifold_rollout(sys, x0, U)
        e = M.boxminus(x, xr)
        J = (e * e * Qw).sum() + (U * U * Rw).sum()
        (gr,) = torch.autograd.grad(J, U)
        return float(J.detach()), gr.numpy().ravel()

    ref = scipy.optimize.minimize(cost, np.zeros(T * 3), jac=True, method="L-BFGS-B",
                                  bounds=[(-3.0, 3.0)] * (T * 3), options={"ftol": 1e-15, "gtol": 1e-11})
    assert float(sol.cost) <= ref.fun * (1 + 1e-8)
    np.testing.assert_allclose(sol.U.detach().numpy().ravel(), ref.x, atol=1e-4)
    # Algorithm 1 alone (one linearization about this infeasible reference) is not better
    one = mpc.solve(x0, xr, ur)
    x1 = manifold_rollout(sys, x0, one.U)
    e1 = M.boxminus(x1, xr)
    assert float((e1 * e1 * Qw).sum() + (one.U ** 2 * Rw).sum()) > float(sol.cost)


def test_iterated_variant_reports_max_iterations_honestly():
    sys = _RigidBody()
    M = sys.manifold
    T = 10
    target = so3.exp(torch.tensor([2.5, -0.7, 0.4], dtype=D))
    xr = M.state(R=target.expand(1, T + 1, 3, 3), w=torch.zeros(1, T + 1, 3, dtype=D))
    x0 = M.state(R=torch.eye(3, dtype=D)[None], w=torch.zeros(1, 3, dtype=D))
    mpc = ErrorStateMPC(sys, T, torch.tensor([10.0] * 3 + [0.1] * 3, dtype=D),
                        torch.full((3,), 0.01, dtype=D))
    sol = mpc.iterate(x0, xr, torch.zeros(1, T, 3, dtype=D), max_iter=1)
    assert sol.status.reason.tolist() == [int(Reason.MAX_ITERATIONS)]
    assert float(sol.kkt_residual) > 1e-8


def test_riccati_terminal_weight_solves_the_dare():
    q = Quadrotor()
    xh, uh = q.hover(torch.zeros(3, dtype=D))
    P, done = riccati_terminal_weight(q, xh, uh, QW, RW)
    assert bool(done)
    M = q.manifold
    es = error_system(q, M.state(p=torch.zeros(2, 3, dtype=D), v=torch.zeros(2, 3, dtype=D),
                                 R=torch.eye(3, dtype=D).expand(2, 3, 3)), uh[None])
    A, B = es.A[0].numpy(), es.B[0].numpy()
    ref = scipy.linalg.solve_discrete_are(A, B, np.diag(QW.numpy()), np.diag(RW.numpy()))
    np.testing.assert_allclose(P.numpy(), ref, rtol=1e-6, atol=1e-6 * np.abs(ref).max())


def test_hover_recovery_in_the_simulator():
    """Closed loop against the RK4 simulator (not the MPC's model): 0.5 m and 17° off, 1.5 s."""
    q = Quadrotor()
    xh, uh = q.hover(torch.zeros(2, 3, dtype=D))
    P, _ = riccati_terminal_weight(q, xh[0], uh[0], QW, RW)
    mpc = ErrorStateMPC(q, 8, QW, RW, P)
    xr = xh.unsqueeze(-1).expand(2, 9)
    ur = uh.unsqueeze(-2).expand(2, 8, 4)
    x = q.state(torch.tensor([[0.3, -0.3, 0.2], [-0.2, 0.1, -0.4]], dtype=D), torch.zeros(2, 3, dtype=D),
                so3.exp(torch.tensor([[0.3, 0.0, 0.0], [0.0, -0.2, 0.1]], dtype=D)))
    sim = QuadrotorSimulator(q)
    for _ in range(150):
        sol = mpc.solve(x, xr, ur)
        assert bool(sol.status.converged.all())
        assert bool((sol.u[..., 0] >= q.thrust_min).all())
        assert bool((sol.u[..., 1:].abs() <= q.rate_max).all())
        x = sim.step(x, sol.u)
    assert float(x.p.norm(dim=-1).max()) < 0.01
    assert float(so3.log(x.R).norm(dim=-1).max()) < 0.01
