"""controllers.costs: QuadraticCost validation, canonical expansion against direct evaluation, via points,
analytic derivatives against autograd, and the one scale convention (lq_coefficients)."""

import math

import pytest
import torch
from lq_oracle import spd

from controllers.costs import QuadraticCost

D = torch.float64


@pytest.mark.parametrize("with_N", [False, True])
def test_canonical_expansion_equals_direct_evaluation(with_N):
    g = torch.Generator().manual_seed(2)
    n, m, T, b = 3, 2, 4, 5
    Q = spd(b, T + 1, k=n, g=g)
    R = spd(T, k=m, g=g)
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


@pytest.mark.parametrize("with_N", [False, True])
def test_quadratic_cost_derivatives_equal_autograd_and_lq_coefficients_round_trip(with_N):
    """QuadraticCost.derivatives (H = 2Q: no ½ in the cost) equals double-backward autograd, and
    lq_coefficients — the one place where derivatives become LQ coefficients — gives back Q, R, N and the
    canonical linear terms exactly."""
    from controllers.costs import autograd_derivatives, lq_coefficients

    g = torch.Generator().manual_seed(6)
    T, n, m = 4, 3, 2
    rnd = lambda *s: torch.randn(*s, dtype=D, generator=g)
    kw = dict(x_ref=rnd(2, T + 1, n), u_ref=rnd(2, T, m), q=rnd(2, T + 1, n), r=rnd(2, T, m))
    if with_N:
        kw["N"] = 0.1 * torch.randn(2, T, n, m, dtype=D, generator=g)
    cost = QuadraticCost(spd(2, T + 1, k=n, g=g), spd(2, T, k=m, g=g), **kw)
    x = torch.randn(2, T + 1, n, dtype=D, generator=g)
    u = torch.randn(2, T, m, dtype=D, generator=g)
    ana = cost.derivatives(x, u)
    auto = autograd_derivatives(cost, x, u)
    for a, b in zip(ana, auto):
        if a is None:
            assert b is None or float(b.abs().max()) == 0.0
            continue
        torch.testing.assert_close(a.expand_as(b), b, atol=1e-12, rtol=0)
    # at x = u = 0 the gradient is twice the canonical linear terms
    z = lq_coefficients(*cost.derivatives(torch.zeros_like(x), torch.zeros_like(u)))
    cc = cost.canonical(T)
    torch.testing.assert_close(z[0], cost.Q)
    torch.testing.assert_close(z[1], cost.R)
    if with_N:
        torch.testing.assert_close(z[2], cost.N)
    torch.testing.assert_close(z[3], cc.q)
    torch.testing.assert_close(z[4], cc.r)


# ---------------------------------------------------------------------------------------------------
# PeriodicQuadraticCost: angles compared modulo 2π
# ---------------------------------------------------------------------------------------------------


def _periodic_cost(B=3, T=4, seed=0):
    from controllers.costs import PeriodicQuadraticCost

    g = torch.Generator().manual_seed(seed)
    n, m = 3, 2
    Q = spd(B, T + 1, k=n, g=g)
    R = spd(B, T, k=m, g=g)
    mu = torch.randn(B, T + 1, n, generator=g, dtype=torch.float64)
    nu = torch.randn(B, T, m, generator=g, dtype=torch.float64)
    base = QuadraticCost(Q=Q, R=R, x_ref=mu, u_ref=nu)
    periodic = torch.tensor([True, False, True])
    return PeriodicQuadraticCost(base, periodic), base, g


def test_periodic_cost_is_the_base_off_the_cut_and_2pi_periodic_in_the_angles():
    cost, base, g = _periodic_cost()
    B, T1, n = base.x_ref.shape
    u = torch.randn(B, T1 - 1, 2, generator=g, dtype=torch.float64)
    # within π of the reference on every component: the plain quadratic cost
    x = base.x_ref + (torch.rand(B, T1, n, generator=g, dtype=torch.float64) * 2 - 1) * 3.0
    torch.testing.assert_close(cost.evaluate(x, u), base.evaluate(x, u), rtol=1e-14, atol=0)
    # whole turns on the angles change nothing; on the other component they do
    k = torch.randint(-3, 4, (B, T1, n), generator=g).double()
    turns = 2 * math.pi * k * torch.tensor([1.0, 0.0, 1.0], dtype=torch.float64)
    torch.testing.assert_close(cost.evaluate(x + turns, u), cost.evaluate(x, u), rtol=1e-12, atol=1e-12)
    other = torch.tensor([0.0, 2 * math.pi, 0.0], dtype=torch.float64)
    assert bool((cost.evaluate(x + other, u) - cost.evaluate(x, u)).abs().min() > 1e-3)
    # the charged angle is the shortest one: |dx| = 3π/2 is charged as π/2
    d = torch.zeros(B, T1, n, dtype=torch.float64)
    d[..., 0] = 1.5 * math.pi
    e = torch.zeros_like(d)
    e[..., 0] = -0.5 * math.pi
    torch.testing.assert_close(cost.evaluate(base.x_ref + d, u), base.evaluate(base.x_ref + e, u))


def test_periodic_cost_derivatives_equal_autograd_and_gradcheck():
    from controllers.costs import autograd_derivatives

    cost, base, g = _periodic_cost(seed=1)
    B, T1, n = base.x_ref.shape
    x = base.x_ref + (torch.rand(B, T1, n, generator=g, dtype=torch.float64) * 2 - 1) * 9.0  # across cuts
    u = torch.randn(B, T1 - 1, 2, generator=g, dtype=torch.float64)
    mine = cost.derivatives(x, u)
    ref = autograd_derivatives(cost, x, u)
    for a, b in zip(mine, ref):
        if a is None or b is None:
            continue
        torch.testing.assert_close(a.expand_as(b), b, rtol=1e-10, atol=1e-10)
    # away from the cut the cost is smooth in the state and the reference: float64 gradcheck
    xs = (base.x_ref + 0.5).clone().requires_grad_(True)
    mu = base.x_ref.clone().requires_grad_(True)
    from controllers.costs import PeriodicQuadraticCost

    def f(xs, mu):
        q = QuadraticCost(Q=base.Q, R=base.R, x_ref=mu, u_ref=base.u_ref)
        c = PeriodicQuadraticCost(q, cost.periodic)
        return c.evaluate(xs + 4 * math.pi, u)  # two turns off: the wrapped branch
    assert torch.autograd.gradcheck(f, (xs, mu))


def test_periodic_cost_rejects_a_bad_mask():
    from controllers.costs import PeriodicQuadraticCost

    _, base, _ = _periodic_cost()
    with pytest.raises(ValueError, match="periodic"):
        PeriodicQuadraticCost(base, torch.tensor([True, False]))
    with pytest.raises(ValueError, match="periodic"):
        PeriodicQuadraticCost(base, torch.tensor([1, 0, 1]))
    with pytest.raises(TypeError, match="base"):
        PeriodicQuadraticCost("not a cost", torch.tensor([True]))
