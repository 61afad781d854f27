"""controllers.ilqr_lifted.lifted_feedback_gains: the least-squares gains of §8.3 (Eq. 95-99) against the
Riccati gains of ilqr(method="recursive") at the same point (cookbook manipulator, a random LQ problem with
a cross term, a pendulum), against a re-solve from perturbed starts (LQ: the affine policy is exact),
batched == loop, a NaN element isolated, float32, bad input."""

import dataclasses

import pytest
import torch

from controllers.basis import rbf
from controllers.costs import QuadraticCost
from controllers.dynamics import LinearDynamics
from controllers.ilqr import ILQRProblem, ilqr
from controllers.ilqr_lifted import LiftedGains, ilqr_lifted, lifted_feedback_gains
from controllers.lifted import control_primitives
from controllers.systems import Pendulum
from liecontrol.bench.solver import cookbook_problem

D = torch.float64


def _lq_problem(B=3, T=10, n=4, m=2, seed=0, dtype=D, cross=True, dt=0.1):
    """A random discretized LQ tracking problem ``A = I + dt·randn``, ``B = dt·randn`` (with ``seed=0`` a
    mild closed loop: Eq. 99 amplifies rounding only ~1e4 times; other seeds reach 1e9, see below)."""
    g = torch.Generator().manual_seed(seed)
    A = torch.eye(n, dtype=D) + dt * torch.randn(n, n, generator=g, dtype=D)
    Bm = dt * torch.randn(n, m, generator=g, dtype=D)
    M = torch.randn(n, n, generator=g, dtype=D)
    Q = (M @ M.mT / n + 0.1 * torch.eye(n, dtype=D)).expand(T + 1, n, n)
    R = 0.1 * torch.eye(m, dtype=D)
    N = 0.02 * torch.randn(n, m, generator=g, dtype=D) if cross else None
    target = torch.randn(B, T + 1, n, generator=g, dtype=D)
    x0 = torch.randn(B, n, generator=g, dtype=D)
    cost = QuadraticCost(Q=Q.to(dtype), R=R.to(dtype), x_ref=target.to(dtype),
                         N=None if N is None else N.to(dtype))
    return ILQRProblem(LinearDynamics(A.to(dtype), Bm.to(dtype)), cost, x0.to(dtype), T)


def _at(sol, x, u):
    """The lifted solution moved to the point ``(x, u)`` (Ψ = I: ``w = u``; x0 unchanged)."""
    return dataclasses.replace(sol, x=x.detach(), u=u.detach(), w=u.detach().flatten(-2))


def _rel(a, b):
    return float((a - b).abs().max() / b.abs().max())


@pytest.fixture(scope="module")
def cookbook():
    p = cookbook_problem()
    sol = ilqr_lifted(p)
    assert bool(sol.status.converged.all())
    ref = ilqr(p, sol.u, method="recursive", grad="none")
    assert bool(ref.status.converged.all())
    return p, sol, ref


def test_cookbook_gains_equal_riccati_at_the_same_point(cookbook):
    p, sol, ref = cookbook
    G = lifted_feedback_gains(p, _at(sol, ref.x, ref.u))
    assert isinstance(G, LiftedGains)
    assert G.K.shape == (p.T, p.m, p.n) and G.k.shape == (p.T, p.m)
    # rounding of Eq. 99 is amplified where the closed loop contracts hard (t = 23 -> 24, the first via
    # point with r = 1e-6): ~1e-11 before it, a few 1e-8 after it (relative to max |K|)
    assert _rel(G.K, ref.K) < 1e-7
    assert _rel(G.K[:23], ref.K[:23]) < 1e-9
    assert _rel(G.k, ref.k) < 1e-7
    assert 1e2 < float(G.amplification) < 1e8
    # at the solver's own returned point (converged: the two points differ by ~1e-7 in u)
    G2 = lifted_feedback_gains(p, sol)
    assert _rel(G2.K, ref.K) < 1e-5


def test_lq_gains_equal_riccati_and_the_policy_is_the_optimum_from_other_starts():
    p = _lq_problem()
    sol = ilqr_lifted(p)
    assert bool(sol.status.converged.all())
    ref = ilqr(p, sol.u, method="recursive", grad="none")
    G = lifted_feedback_gains(p, _at(sol, ref.x, ref.u))
    assert _rel(G.K, ref.K) < 1e-8
    assert _rel(G.k, ref.k) < 1e-8
    # LQ: u_t = K_t x_t + k_t from any start is the optimum of the problem from that start
    g = torch.Generator().manual_seed(5)
    x0 = p.x0 + torch.randn(p.x0.shape, generator=g, dtype=D)
    p2 = ILQRProblem(p.dynamics, p.cost, x0, p.T)
    opt = ilqr_lifted(p2)
    x, us = x0, []
    for t in range(p.T):
        u = (G.K[..., t, :, :] @ x.unsqueeze(-1)).squeeze(-1) + G.k[..., t, :]
        us.append(u)
        x = p.dynamics.step(x, u, t)
    assert _rel(torch.stack(us, -2), opt.u) < 1e-8


def test_nonlinear_dynamics_pendulum():
    T = 15
    x0 = torch.tensor([[0.3, 0.0], [-0.5, 0.4]], dtype=D)
    Q = torch.zeros(T + 1, 2, 2, dtype=D)
    Q[-1] = 100 * torch.eye(2, dtype=D)
    Q[:-1] = 0.1 * torch.eye(2, dtype=D)
    target = torch.tensor([2.0, 0.0], dtype=D)
    cost = QuadraticCost(Q=Q, R=0.1 * torch.eye(1, dtype=D), x_ref=target)
    p = ILQRProblem(Pendulum(dt=0.1, damping=0.1), cost, x0, T)
    sol = ilqr_lifted(p)
    assert bool(sol.status.converged.all())
    ref = ilqr(p, sol.u, method="recursive", grad="none")
    G = lifted_feedback_gains(p, _at(sol, ref.x, ref.u))
    assert _rel(G.K, ref.K) < 1e-8
    assert _rel(G.k, ref.k) < 1e-8


def test_batched_equals_loop_and_nan_element_is_isolated():
    p = _lq_problem(B=3)
    x0 = p.x0.clone()
    x0[1, 2] = float("nan")
    pb = ILQRProblem(p.dynamics, p.cost, x0, p.T)
    sol = ilqr_lifted(pb)
    G = lifted_feedback_gains(pb, sol)
    assert G.K.shape == (3, p.T, p.m, p.n) and G.amplification.shape == (3,)
    assert bool(torch.isnan(G.K[1]).all()) and bool(torch.isnan(G.k[1]).all())
    for b in (0, 2):
        assert bool(torch.isfinite(G.K[b]).all())
        pe = ILQRProblem(p.dynamics, dataclasses.replace(p.cost, x_ref=p.cost.x_ref[b]), x0[b], p.T)
        se = dataclasses.replace(sol, x=sol.x[b], u=sol.u[b], w=sol.w[b], x0=sol.x0[b])
        Ge = lifted_feedback_gains(pe, se)
        torch.testing.assert_close(G.K[b], Ge.K, rtol=1e-10, atol=1e-10)
        torch.testing.assert_close(G.k[b], Ge.k, rtol=1e-10, atol=1e-10)


def test_cookbook_batch_with_a_failed_start(cookbook):
    """The residual-cost path batched (perturbed starts), a NaN start isolated; batch == loop up to the
    rounding Eq. 99 amplifies (amplification ~1e4 at the via point)."""
    p, _, _ = cookbook
    d = torch.tensor([[0.1, -0.05, 0.02], [float("nan"), 0.0, 0.0]], dtype=D)
    pb = ILQRProblem(p.dynamics, p.cost, p.x0 + d, p.T)
    sol = ilqr_lifted(pb, max_iter=30)
    G = lifted_feedback_gains(pb, sol)
    assert bool(torch.isnan(G.K[1]).all()) and bool(torch.isfinite(G.K[0]).all())
    se = dataclasses.replace(sol, x=sol.x[0], u=sol.u[0], w=sol.w[0], x0=sol.x0[0])
    Ge = lifted_feedback_gains(ILQRProblem(p.dynamics, p.cost, pb.x0[0], p.T), se)
    assert _rel(G.K[0], Ge.K) < 1e-6 and _rel(G.k[0], Ge.k) < 1e-6


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_error_follows_the_amplification_of_eq99(dtype):
    """The error against Riccati stays within 100·eps·amplification (seeds 0-3: amplification 2e2 to 2e9)."""
    eps = torch.finfo(dtype).eps
    amps = []
    for seed in range(4):
        p = _lq_problem(seed=seed, dtype=dtype)
        sol = ilqr_lifted(p)
        ref = ilqr(p, sol.u, method="recursive", grad="none")
        G = lifted_feedback_gains(p, _at(sol, ref.x, ref.u))
        assert G.K.dtype == dtype
        amps.append(float(G.amplification.max()))
        assert _rel(G.K, ref.K) <= 100 * eps * amps[-1]
    assert max(amps) > 1e8 and min(amps) < 1e3  # both regimes are exercised


def test_float32():
    p32 = _lq_problem(dtype=torch.float32)
    sol = ilqr_lifted(p32)
    G = lifted_feedback_gains(p32, sol)
    assert G.K.dtype == torch.float32 and G.k.dtype == torch.float32
    p64 = _lq_problem()
    s64 = dataclasses.replace(ilqr_lifted(p64), x=sol.x.double(), u=sol.u.double(), w=sol.w.double())
    G64 = lifted_feedback_gains(p64, s64)
    assert _rel(G.K.double(), G64.K) < 1e-2
    assert _rel(G.k.double(), G64.k) < 1e-2


def test_bad_input(cookbook):
    p, sol, ref = cookbook
    with pytest.raises(TypeError, match="'problem'"):
        lifted_feedback_gains(object(), sol)
    with pytest.raises(TypeError, match="'solution'"):
        lifted_feedback_gains(p, ref)
    with pytest.raises(ValueError, match="control limits"):
        lifted_feedback_gains(ILQRProblem(p.dynamics, p.cost, p.x0, p.T, u_lower=-1.0, u_upper=1.0), sol)
    with pytest.raises(ValueError, match="'solution' must have u"):
        lifted_feedback_gains(ILQRProblem(p.dynamics, p.cost, p.x0, p.T - 1), sol)
    with pytest.raises(TypeError, match="dtype"):
        lifted_feedback_gains(cookbook_problem(torch.float32), sol)
    # control primitives (Ψ ≠ I) and a free initial state are refused with what to do
    lq = _lq_problem(B=1, T=8)
    Psi = control_primitives(rbf(8, 4, dtype=D), lq.m)
    with pytest.raises(ValueError, match="Ψ ≠ I"):
        lifted_feedback_gains(lq, ilqr_lifted(lq, Psi))
    with pytest.raises(ValueError, match="initial state"):
        lifted_feedback_gains(lq, ilqr_lifted(lq, x0_weight=torch.ones(lq.n, dtype=D)))
