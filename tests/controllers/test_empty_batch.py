"""A zero-size batch is a batch (issue 22 item 9): every solver returns empty results of the right shapes
and an empty status, forward and backward, and a shared parameter gets a zero gradient (the sum over no
elements) — before, the LQ kernels treated an empty batch as one element and raised an expand error
whenever gradients were on (``MPCPolicy(...)(torch.zeros(0, 2))``, ``ilqr`` with implicit gradients) and
always in ``riccati.solve``."""

from __future__ import annotations

import pytest
import torch

from controllers import riccati
from controllers.costs import DiagonalQuadraticCost, QuadraticCost
from controllers.dynamics import LinearDynamics
from controllers.ilqr import ILQRProblem, ilqr
from controllers.mpc import MPCPolicy
from controllers.problem import LQProblem
from controllers.systems import Pendulum

D = torch.float64
T = 5


@pytest.mark.parametrize("bs", [(0,), (0, 3), (3, 0)])
@pytest.mark.parametrize("method", ["recursive", "batch"])
@pytest.mark.parametrize("grad", ["implicit", "unrolled", "none"])
@pytest.mark.parametrize("limited", [True, False])
def test_ilqr_empty_batch(bs, method, grad, limited):
    x0 = torch.zeros(*bs, 2, dtype=D, requires_grad=True)
    length = torch.tensor(1.0, dtype=D, requires_grad=True)
    x_ref = torch.tensor([1.0, 0.0], dtype=D, requires_grad=True)
    cost = QuadraticCost(torch.eye(2, dtype=D), 0.1 * torch.eye(1, dtype=D), x_ref=x_ref)
    lim = dict(u_lower=-1.0, u_upper=torch.tensor([1.0], dtype=D, requires_grad=True)) if limited else {}
    sol = ilqr(ILQRProblem(Pendulum(dt=0.1, length=length), cost, x0, T, **lim), method=method, grad=grad)
    assert sol.x.shape == (*bs, T + 1, 2) and sol.u.shape == (*bs, T, 1)
    assert sol.K.shape == (*bs, T, 1, 2) and sol.k.shape == (*bs, T, 1) and sol.cost.shape == bs
    assert sol.status.reason.shape == sol.status.converged.shape == sol.kkt_residual.shape == bs
    assert sol.clamped.shape == (*bs, T, 1) and sol.mu.shape == bs
    if grad == "none":
        return
    leaves = [x0, length, x_ref] + ([lim["u_upper"]] if limited else [])
    grads = torch.autograd.grad(sol.u.sum() + sol.x.sum() + sol.cost.sum(), leaves, allow_unused=True)
    assert grads[0].shape == x0.shape
    for g in grads[1:]:  # a sum over no elements
        assert g is None or (not bool(g.any()) and bool(torch.isfinite(g).all()))


@pytest.mark.parametrize("grad", ["implicit", "unrolled"])
def test_mpc_policy_empty_batch(grad):
    cost = DiagonalQuadraticCost(torch.tensor([1.0, 0.1], dtype=D), torch.tensor([0.1], dtype=D),
                                 torch.zeros(2, dtype=D), T)
    policy = MPCPolicy(Pendulum(dt=0.1), T, cost, u_lower=-2.0, u_upper=2.0, grad=grad)
    action, state = policy(torch.zeros(0, 2, dtype=D))
    assert action.shape == (0, 1) and state.u.shape == (0, T, 1) and state.converged.shape == (0,)
    # (unrolled: no iteration ran, so the plan is the initial guess, without a graph, as for any element
    # that starts at its optimum; the implicit gradient is defined at any point)
    assert action.requires_grad or grad == "unrolled"
    if action.requires_grad:
        action.sum().backward()
    for p in policy.parameters():
        assert p.grad is None or not bool(p.grad.any())
    action2, _ = policy(torch.zeros(0, 2, dtype=D), state)  # and warm-started
    assert action2.shape == (0, 1)


@pytest.mark.parametrize("grad", ["implicit", "unrolled", "none"])
def test_riccati_empty_batch(grad):
    A = (torch.eye(2, dtype=D) + 0.1).requires_grad_(True)
    Q = torch.eye(2, dtype=D).requires_grad_(True)
    x0 = torch.zeros(0, 2, dtype=D, requires_grad=True)
    dyn = LinearDynamics(A, torch.ones(2, 1, dtype=D))
    prob = LQProblem(dyn, QuadraticCost(Q, torch.eye(1, dtype=D)), x0, 4)
    sol = riccati.solve(prob, grad=grad)
    assert sol.x.shape == (0, 5, 2) and sol.u.shape == (0, 4, 1) and sol.K.shape == (0, 4, 1, 2)
    assert sol.cost.shape == sol.status.reason.shape == (0,)
    if grad == "none":
        return
    loss = sol.u.sum() + sol.x.sum() + sol.cost.sum()
    gA, gQ, gx = torch.autograd.grad(loss, (A, Q, x0), allow_unused=True)
    assert gx.shape == (0, 2)
    for g in (gA, gQ):
        assert g is None or not bool(g.any())


class _DoubleIntegrator:
    m = 1

    def __init__(self, dt=0.5):
        from torchlie.manifolds import Rn  # noqa: PLC0415

        self.manifold, self.n, self.dt = Rn(2), 2, dt

    def f(self, x, u):
        return torch.cat([x[..., 1:2], u], -1)


@pytest.mark.parametrize("method", ["solve", "iterate"])
@pytest.mark.parametrize("limited", [False, True])
@pytest.mark.parametrize("requires_grad", [False, True])
def test_error_state_mpc_empty_batch(method, limited, requires_grad):
    """Without limits the Riccati path saw a stage weight batched to 0 elements beside a shared R and
    expanded it to one element (``_lq_kernels``: RuntimeError)."""
    from controllers.manifold_mpc import ErrorStateMPC  # noqa: PLC0415

    Q = torch.tensor([1.0, 0.1], dtype=D, requires_grad=requires_grad)
    x0 = torch.zeros(0, 2, dtype=D, requires_grad=requires_grad)
    lim = dict(u_lower=-1.0, u_upper=1.0) if limited else {}
    mpc = ErrorStateMPC(_DoubleIntegrator(), T, Q, torch.tensor([0.1], dtype=D), **lim)
    sol = getattr(mpc, method)(x0, torch.zeros(0, T + 1, 2, dtype=D), torch.zeros(0, T, 1, dtype=D))
    assert sol.U.shape == (0, T, 1) and sol.u.shape == (0, 1) and sol.dx.shape == (0, T + 1, 2)
    assert sol.cost.shape == sol.status.reason.shape == sol.kkt_residual.shape == (0,)
    if requires_grad:
        gx, gQ = torch.autograd.grad(sol.U.sum() + sol.cost.sum(), (x0, Q), allow_unused=True)
        assert gx is None or gx.shape == (0, 2)
        assert gQ is None or not bool(gQ.any())


@pytest.mark.parametrize("frame", ["world", "local", "se3"])
@pytest.mark.parametrize("limited", [False, True])
def test_pose_mpc_empty_batch(frame, limited):
    from controllers.pose_mpc import PoseMPC  # noqa: PLC0415

    Q = torch.ones(6, dtype=D, requires_grad=True)
    lim = dict(u_upper=1.0) if limited else {}
    eye = torch.eye(4, dtype=D)
    sol = PoseMPC(frame, T, 0.1, Q, torch.ones(6, dtype=D), **lim).solve(
        eye.expand(0, 4, 4), eye.expand(0, T + 1, 4, 4), torch.zeros(0, T, 6, dtype=D))
    assert sol.U.shape == (0, T, 6) and sol.status.reason.shape == (0,)
    (gQ,) = torch.autograd.grad(sol.U.sum(), Q, allow_unused=True)
    assert gQ is None or not bool(gQ.any())


@pytest.mark.parametrize("time_invariant", [True, False])
def test_ilqr_empty_batch_with_autograd_jacobians(time_invariant):
    """A NonlinearDynamics without an analytic Jacobian (vmap'd jacrev) on batch 0: empty results (the
    reshape to (*B, -1, n) was ambiguous)."""
    from controllers.costs import QuadraticCost
    from controllers.dynamics import NonlinearDynamics
    from controllers.ilqr import ILQRProblem, ilqr

    D = torch.float64

    def f(x, u, t):
        return x + 0.1 * torch.sin(u)

    cost = QuadraticCost(Q=torch.eye(2, dtype=D), R=torch.eye(2, dtype=D))
    dyn = NonlinearDynamics(f, 2, 2, time_invariant=time_invariant)
    sol = ilqr(ILQRProblem(dyn, cost, torch.zeros(0, 2, dtype=D), 5), grad="none")
    assert tuple(sol.u.shape) == (0, 5, 2) and tuple(sol.x.shape) == (0, 6, 2)
