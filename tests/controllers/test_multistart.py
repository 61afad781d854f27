"""Multi-start iLQR (controllers.multistart): the choice rule, never worse than a certified guess, the
closed-loop hold guess that finds the braking plan, batched == one solve per guess, gradients through the
chosen guess, and bad input."""

import math

import pytest
import torch

from controllers.costs import PeriodicQuadraticCost, QuadraticCost
from controllers.ilqr import ILQROptions, ILQRProblem, ilqr
from controllers.multistart import guesses, ilqr_multistart, lqr_guess, select_best
from controllers.systems import Pendulum

D = torch.float64
H = 30
OPTS = ILQROptions(max_iter=60)


def _pendulum():
    return Pendulum(mass=0.75, length=2.0 / 3.0, damping=0.0, gravity=10.0, dt=0.05)


def _cost(dtype=D, terminal=10.0):
    Q = torch.diag(torch.tensor([1.0, 0.1], dtype=dtype)).expand(H + 1, 2, 2).clone()
    Q[-1] *= terminal
    base = QuadraticCost(Q=Q, R=torch.tensor([[0.001]], dtype=dtype), x_ref=torch.tensor([math.pi, 0.0],
                                                                                          dtype=dtype))
    return PeriodicQuadraticCost(base, torch.tensor([True, False]))


def _limits(dtype=D):
    return torch.tensor([-2.0], dtype=dtype), torch.tensor([2.0], dtype=dtype)


def _problem(x0, dtype=D):
    lo, hi = _limits(dtype)
    return ILQRProblem(_pendulum(), _cost(dtype), x0, H, u_lower=lo, u_upper=hi)


def test_select_best_prefers_certified_then_lowest_finite():
    c = torch.tensor([[3.0, 1.0, 2.0], [3.0, 1.0, 2.0], [math.nan, 5.0, 4.0], [math.nan, math.nan, math.nan]])
    conv = torch.tensor([[True, False, True], [False, False, False], [False, False, False],
                         [True, True, True]])
    assert select_best(c, conv).tolist() == [2, 1, 2, 0]


def test_braking_plan_found_where_the_zero_start_swings():
    """4 degrees from upright at rest: zero controls lead iLQR (certified) to a full swing; the hold
    guess leads it to braking, and the multi-start keeps that."""
    x0 = torch.tensor([[math.pi - math.radians(4.0), 0.0]], dtype=D)
    p = _problem(x0)
    zero = ilqr(p, options=OPTS)
    lo, hi = _limits()
    U = torch.cat([guesses((1,), H, lo, hi), lqr_guess(p.dynamics, p.cost, x0, H, lo, hi)[:, None]], 1)
    ms = ilqr_multistart(p, U, options=OPTS)
    assert bool(zero.status.converged) and bool(ms.best.status.converged)
    assert float(zero.cost) > 50.0  # the swing
    assert float(ms.best.cost) < 1.0 and int(ms.choice) == U.shape[1] - 1
    # the plan keeps the pendulum near upright
    assert float((ms.best.x[0, :, 0] - math.pi).abs().max()) < math.radians(5.0)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_batched_equals_one_solve_per_guess_and_never_worse_than_a_certified_guess(dtype):
    x0 = torch.tensor([[0.3, 0.0], [math.pi - 0.2, 0.5], [2.0, -1.0]], dtype=dtype)
    lo, hi = _limits(dtype)
    U = guesses((3,), H, lo, hi, random=2, generator=torch.Generator().manual_seed(3))
    p = _problem(x0, dtype)
    ms = ilqr_multistart(p, U, options=OPTS)
    K = U.shape[1]
    for k in range(K):
        s = ilqr(p, U[:, k], options=OPTS)
        tol = 1e-6 if dtype == D else 2e-3
        torch.testing.assert_close(ms.costs[:, k], s.cost, rtol=tol, atol=tol)
        assert torch.equal(ms.converged[:, k], s.status.converged)
        better = ms.best.cost <= s.cost * (1 + tol) + tol
        assert bool((better | ~s.status.converged).all())
    # the chosen solution is the chosen guess's own
    for b in range(3):
        s = ilqr(_problem(x0[b:b + 1], dtype), U[b:b + 1, int(ms.choice[b])], options=OPTS)
        torch.testing.assert_close(ms.best.u[b:b + 1], s.u, rtol=1e-4, atol=1e-4)
        assert int(ms.best.status.iterations[b]) == int(s.status.iterations)


def test_gradient_flows_through_the_chosen_guess():
    x0 = torch.tensor([[math.pi - 0.1, 0.0], [0.5, 0.2]], dtype=D, requires_grad=True)
    lo, hi = _limits()
    U = guesses((2,), H, lo, hi)
    ms = ilqr_multistart(_problem(x0), U, grad="implicit", options=OPTS)
    (g,) = torch.autograd.grad(ms.best.u[:, 0].sum(), x0)
    for b in range(2):
        xb = x0.detach()[b:b + 1].clone().requires_grad_(True)
        s = ilqr(_problem(xb), U[b:b + 1, int(ms.choice[b])], grad="implicit", options=OPTS)
        (gb,) = torch.autograd.grad(s.u[:, 0].sum(), xb)
        torch.testing.assert_close(g[b:b + 1], gb, rtol=1e-6, atol=1e-8)


def test_nan_element_does_not_poison_the_batch():
    x0 = torch.tensor([[math.nan, 0.0], [math.pi - 0.1, 0.0]], dtype=D)
    lo, hi = _limits()
    ms = ilqr_multistart(_problem(x0), guesses((2,), H, lo, hi), options=OPTS)
    assert not bool(ms.best.status.converged[0]) and bool(ms.best.status.converged[1])
    assert bool(torch.isnan(ms.best.u[0]).all()) and bool(torch.isfinite(ms.best.u[1]).all())


def test_guesses_content_and_determinism():
    lo, hi = torch.tensor([-1.0, -2.0], dtype=D), torch.tensor([1.0, 3.0], dtype=D)
    prev = torch.full((4, H, 2), 0.5, dtype=D)
    U = guesses((4,), H, lo, hi, previous=prev, random=3, generator=torch.Generator().manual_seed(0))
    assert U.shape == (4, 1 + 1 + 4 + 3, H, 2)
    assert torch.equal(U[:, 0], prev) and bool((U[:, 1] == 0).all())
    bang = torch.tensor([[-1.0, 0.0], [0.0, -2.0], [1.0, 0.0], [0.0, 3.0]], dtype=D)
    assert torch.equal(U[0, 2:6, 0], bang)
    r = U[:, 6:]
    assert bool(((r >= lo) & (r <= hi)).all())
    U2 = guesses((4,), H, lo, hi, previous=prev, random=3, generator=torch.Generator().manual_seed(0))
    assert torch.equal(U, U2)
    with pytest.raises(ValueError, match="finite"):
        guesses((1,), H, torch.tensor([-math.inf]), torch.tensor([1.0]))


def test_lqr_guess_needs_a_quadratic_cost_and_respects_limits():
    x0 = torch.tensor([[0.2, 0.0]], dtype=D)
    lo, hi = _limits()
    g = lqr_guess(_pendulum(), _cost(), x0, H, lo, hi)
    assert g.shape == (1, H, 1) and bool(((g >= -2) & (g <= 2)).all())

    class Other:
        def evaluate(self, x, u):
            return (x * x).sum((-1, -2))

    assert lqr_guess(_pendulum(), Other(), x0, H, lo, hi) is None


def test_bad_guesses_are_refused():
    p = _problem(torch.zeros(2, 2, dtype=D))
    with pytest.raises(ValueError, match="u_inits"):
        ilqr_multistart(p, torch.zeros(2, 3, H + 1, 1, dtype=D))
    with pytest.raises(TypeError, match="u_inits"):
        ilqr_multistart(p, torch.zeros(2, 3, H, 1, dtype=torch.float32))
    with pytest.raises(ValueError, match="no guess"):
        ilqr_multistart(p, torch.zeros(2, 0, H, 1, dtype=D))


def test_a_cost_batched_over_the_elements_stays_with_its_element():
    """Per-element targets (a periodic cost batched over (*B,)): every guess of element b is scored with b's
    target — the guesses run as a leading batch dim, so (*B,)-batched data never lines up with them."""
    xr = torch.tensor([[math.pi, 0.0], [0.0, 0.0], [1.0, 0.0]], dtype=D)[:, None, :]
    base = QuadraticCost(Q=torch.eye(2, dtype=D), R=0.1 * torch.eye(1, dtype=D), x_ref=xr)
    cost = PeriodicQuadraticCost(base, torch.tensor([True, False]))
    x0 = torch.full((3, 2), 0.5, dtype=D)
    lo, hi = _limits()
    p = ILQRProblem(_pendulum(), cost, x0, 8, u_lower=lo, u_upper=hi)
    U = guesses((3,), 8, lo, hi)
    ms = ilqr_multistart(p, U, options=OPTS)
    for k in range(U.shape[1]):
        torch.testing.assert_close(ms.costs[:, k], ilqr(p, U[:, k], options=OPTS).cost)
    assert ms.costs[0, 0] != ms.costs[1, 0]  # a different target, a different cost
    with pytest.raises(ValueError, match="broadcast"):
        ilqr_multistart(p, torch.zeros(2, 4, 8, 1, dtype=D))
