"""Control limits as inputs of iLQR (issue 22 items 7, 12, 13): derivatives w.r.t. the limits (implicit and
unrolled) against central differences and gradcheck, limit shapes (0-d accepted, a shape that does not
broadcast to (*B, T, m) named at construction) and NaN / infinite limits (shared: ValueError, batched:
a per-element status; the other elements solved as if alone)."""

from __future__ import annotations

import math

import pytest
import torch

from controllers.costs import QuadraticCost
from controllers.ilqr import ILQROptions, ILQRProblem, ilqr
from controllers.problem import Reason
from controllers.systems import Pendulum

D = torch.float64
T = 8
OPTS = ILQROptions(tol=1e-13, tol_cost=0.0)
X0 = torch.tensor([[0.3, 0.0], [-0.2, 0.5]], dtype=D)


def _problem(lo, hi, x0=X0):
    Q = torch.diag(torch.tensor([1.0, 0.1], dtype=D)).expand(T + 1, 2, 2)
    cost = QuadraticCost(Q=Q, R=torch.tensor([[0.05]], dtype=D), x_ref=torch.tensor([1.0, 0.0], dtype=D))
    return ILQRProblem(Pendulum(dt=0.1, damping=0.1), cost, x0, T, u_lower=lo, u_upper=hi)


def _loss(sol):
    w = torch.linspace(-1.0, 1.0, T, dtype=D).view(T, 1)
    return (sol.u * w).sum() + sol.cost.sum() + sol.x.sum()


# (lower, upper) limit values and shapes: one-sided (0-d and (m,)), two-sided per step and per element;
# the pendulum pushes towards +1.2 rad, so the upper limit binds (lower: the mirrored problem, x_ref -1)
CASES = {
    "upper 0-d only": (None, ((), 1.2)),
    "upper (m,) with lower -inf": (((1,), -math.inf), ((1,), 1.2)),
    "both per step": (((T, 1), -3.0), ((T, 1), 1.2)),
    "both per element and step": (((2, T, 1), -3.0), ((2, T, 1), 1.1)),
}


def _limits(case):
    out = []
    for spec in CASES[case]:
        out.append(None if spec is None else torch.full(spec[0], spec[1], dtype=D, requires_grad=True))
    return out


@pytest.mark.parametrize("case", list(CASES))
@pytest.mark.parametrize("method", ["recursive", "batch"])
@pytest.mark.parametrize("grad", ["implicit", "unrolled"])
def test_limit_gradients_match_central_differences(case, method, grad):
    lo, hi = _limits(case)
    sol = ilqr(_problem(lo, hi), method=method, grad=grad, options=OPTS)
    assert sol.status.all_converged and 0 < int(sol.clamped.sum()) < sol.clamped.numel()
    given = [v for v in (lo, hi) if v is not None]
    grads = torch.autograd.grad(_loss(sol), given)
    h = 1e-6
    for leaf, g in zip(given, grads):
        if not math.isfinite(float(leaf.detach().reshape(-1)[0])):
            assert not bool(g.any())  # an infinite limit binds nothing: zero, not NaN
            continue
        fd = torch.zeros_like(leaf)
        for i in range(leaf.numel()):
            e = torch.zeros(leaf.numel(), dtype=D)
            e[i] = h
            e = e.view(leaf.shape)
            args = [[v.detach() if v is not None else None for v in (lo, hi)] for _ in range(2)]
            j = 0 if leaf is lo else 1
            args[0][j], args[1][j] = leaf.detach() + e, leaf.detach() - e
            fd.view(-1)[i] = (_loss(ilqr(_problem(*args[0]), grad="none", options=OPTS))
                              - _loss(ilqr(_problem(*args[1]), grad="none", options=OPTS))) / (2 * h)
        torch.testing.assert_close(g, fd, atol=1e-7, rtol=1e-6)
        if leaf is hi:
            assert float(fd.abs().max()) > 0.1  # the binding limit matters


@pytest.mark.parametrize("method", ["recursive", "batch"])
def test_clamped_control_moves_one_for_one_with_its_limit(method):
    """d u_{b,t} / d upper_{b,t} is 1 for a clamped control (central differences: 1.0); before, ``ilqr``
    returned no gradient at all (None) for the limits."""
    hi = torch.full((2, T, 1), 1.1, dtype=D, requires_grad=True)
    sol = ilqr(_problem(-3.0, hi), method=method, options=OPTS)
    idx = torch.nonzero(sol.clamped)[0].tolist()
    (g,) = torch.autograd.grad(sol.u[tuple(idx)], hi)
    assert abs(float(g[tuple(idx)]) - 1.0) < 1e-9
    h = 1e-6
    e = torch.zeros_like(hi)
    e[tuple(idx)] = h
    up = ilqr(_problem(-3.0, hi.detach() + e), grad="none", options=OPTS).u[tuple(idx)]
    dn = ilqr(_problem(-3.0, hi.detach() - e), grad="none", options=OPTS).u[tuple(idx)]
    assert abs(float((up - dn) / (2 * h)) - 1.0) < 1e-6


def test_gradcheck_per_step_limits():
    def f(lo, hi):
        sol = ilqr(_problem(lo, hi), options=OPTS)
        return sol.u, sol.x, sol.cost

    lo = torch.full((T, 1), -3.0, dtype=D, requires_grad=True)
    hi = torch.full((T, 1), 1.2, dtype=D, requires_grad=True)
    assert torch.autograd.gradcheck(f, (lo, hi), eps=1e-6, atol=1e-6, rtol=1e-5)


def test_limit_shapes_are_checked_at_construction():
    # a 0-d tensor broadcasts to (*B, T, m): accepted (was a ValueError)
    p = _problem(torch.tensor(-2.0, dtype=D), torch.tensor(2.0, dtype=D))
    assert ilqr(p, grad="none").u.shape == (2, T, 1)
    # (2, 1) for batch (2,): a time dim of 2 for T = 8 (was accepted, then crashed inside ilqr)
    with pytest.raises(ValueError, match=r"'u_lower' must broadcast to \(\*B, T, m\) = \(2, 8, 1\)"):
        _problem(torch.full((2, 1), -2.0, dtype=D), 2.0)
    with pytest.raises(ValueError, match=r"'u_upper' must broadcast"):
        _problem(-2.0, torch.full((2,), 2.0, dtype=D))
    with pytest.raises(TypeError, match="u_upper"):
        _problem(-2.0, "2")


def test_nan_limits_shared_raise_batched_are_per_element():
    with pytest.raises(ValueError, match="u_upper"):
        _problem(-2.0, float("nan"))
    shared = torch.full((T, 1), 2.0, dtype=D)
    shared[3] = math.nan
    with pytest.raises(ValueError, match="'u_upper' \\(shared by the batch\\) has NaN"):
        _problem(-2.0, shared)
    x0 = torch.tensor([[0.3, 0.0], [-0.2, 0.5], [0.1, 0.1], [0.0, 0.2]], dtype=D)
    hi = torch.full((4, T, 1), 1.1, dtype=D)
    lo = torch.full((4, T, 1), -3.0, dtype=D)
    hi[1, 2] = math.nan  # NaN: the element's NONFINITE_INPUT (was solved with the limit ignored)
    lo[2, 5] = math.inf  # no finite control satisfies it: INFEASIBLE_BOUNDS (was DIVERGED)
    hi[3, 0] = -math.inf
    sol = ilqr(_problem(lo, hi, x0), grad="none", options=OPTS)
    assert sol.status.reason_names() == ["CONVERGED", "NONFINITE_INPUT", "INFEASIBLE_BOUNDS",
                                         "INFEASIBLE_BOUNDS"]
    assert bool(torch.isnan(sol.u[1:]).all()) and bool(torch.isnan(sol.cost[1:]).all())
    alone = ilqr(_problem(lo[0], hi[0], x0[0]), grad="none", options=OPTS)
    torch.testing.assert_close(sol.u[0], alone.u, atol=1e-12, rtol=0)


@pytest.mark.parametrize("grad", ["implicit", "unrolled"])
@pytest.mark.parametrize("method", ["recursive", "batch"])
def test_a_diverged_element_adds_nothing_to_a_shared_parameter_gradient(grad, method):
    """x0 = 1e200 makes one element DIVERGED (its first rollout costs inf): its outputs are NaN and the
    gradient of a shared pendulum length equals that of the good element alone (unrolled: NaN before)."""
    D = torch.float64
    cost = QuadraticCost(Q=torch.diag(torch.tensor([1.0, 0.1], dtype=D)), R=torch.tensor([[0.05]], dtype=D),
                         x_ref=torch.tensor([1.0, 0.0], dtype=D))

    def solve(x0):
        length = torch.tensor(1.2, dtype=D, requires_grad=True)
        sol = ilqr(ILQRProblem(Pendulum(dt=0.1, damping=0.1, length=length), cost, x0, 8), grad=grad,
                   method=method)
        (g,) = torch.autograd.grad(torch.nan_to_num(sol.u).sum() + torch.nan_to_num(sol.cost).sum(), length)
        return sol, g

    sol, g = solve(torch.tensor([[0.3, 0.0], [1e200, 0.0]], dtype=D))
    assert sol.status.reason.tolist() == [int(Reason.CONVERGED), int(Reason.DIVERGED)]
    assert bool(torch.isnan(sol.u[1]).all()) and bool(torch.isnan(sol.cost[1]))
    alone, g_alone = solve(torch.tensor([[0.3, 0.0]], dtype=D))
    torch.testing.assert_close(sol.u[0], alone.u[0], rtol=0, atol=1e-12)
    torch.testing.assert_close(g, g_alone, rtol=1e-10, atol=1e-12)


def test_a_float_limit_no_control_satisfies_is_a_value_error():
    """u_lower = +inf / u_upper = -inf as numbers are the caller's error (as a NaN or crossed float pair
    is); in a tensor they are the element's INFEASIBLE_BOUNDS (checked without a host sync)."""
    D = torch.float64
    cost = QuadraticCost(Q=torch.eye(2, dtype=D), R=torch.eye(1, dtype=D))
    x0 = torch.zeros(2, 2, dtype=D)
    for kw, name in ((dict(u_lower=math.inf), "u_lower"), (dict(u_upper=-math.inf), "u_upper")):
        with pytest.raises(ValueError, match=name):
            ILQRProblem(Pendulum(), cost, x0, 5, **kw)
    lo = torch.tensor([[[-1.0]], [[math.inf]]], dtype=D)
    sol = ilqr(ILQRProblem(Pendulum(), cost, x0, 5, u_lower=lo, u_upper=2.0), grad="none")
    assert sol.status.reason.tolist() == [int(Reason.CONVERGED), int(Reason.INFEASIBLE_BOUNDS)]


def _one_sided_limit_fd(solve, lo, hi, h=1e-6):
    """Per-entry one-sided differences of ``solve(lo, hi).sum()``: raise ``hi`` / lower ``lo`` (the only
    feasible moves when ``lo == hi``)."""
    with torch.no_grad():
        base = float(solve(lo, hi).sum())
        dlo, dhi = torch.zeros_like(lo), torch.zeros_like(hi)
        for i in range(lo.numel()):
            e = torch.zeros_like(lo).reshape(-1)
            e[i] = h
            e = e.reshape(lo.shape)
            dhi.view(-1)[i] = (float(solve(lo, hi + e).sum()) - base) / h
            dlo.view(-1)[i] = (base - float(solve(lo - e, hi).sum())) / h
    return dlo, dhi


@pytest.mark.parametrize("which", ["ilqr", "error_state_mpc"])
def test_at_equal_limits_the_derivative_goes_to_the_limit_that_binds(which):
    """u_lower == u_upper pins every control; its derivative belongs to the limit the cost pushes against
    (one-sided differences), not always to the lower one (the nearer-bound rule's tie)."""
    from controllers.manifold_mpc import ErrorStateMPC
    from torchlie.manifolds import Euclidean

    D, T = torch.float64, 5
    lim = torch.tensor([[0.2], [0.2], [-0.1], [0.2], [0.2]], dtype=D)
    if which == "ilqr":
        Q = torch.diag(torch.tensor([1.0, 0.1], dtype=D))
        ref = torch.tensor([math.pi, 0.0], dtype=D)
        cost = QuadraticCost(Q=Q, R=torch.tensor([[0.01]], dtype=D), x_ref=ref)
        x0 = torch.tensor([[0.1, 0.0]], dtype=D)

        def solve(lo, hi):
            return ilqr(ILQRProblem(Pendulum(dt=0.05), cost, x0, T, u_lower=lo, u_upper=hi)).u
    else:
        class DoubleIntegrator:
            manifold, m, dt = Euclidean(2), 1, 0.5

            def f(self, x, u):
                return torch.stack([x[..., 1], u[..., 0]], -1)

        x0 = torch.tensor([-2.0, 0.0], dtype=D)
        xr, ur = torch.zeros(T + 1, 2, dtype=D), torch.zeros(T, 1, dtype=D)

        def solve(lo, hi):
            return ErrorStateMPC(DoubleIntegrator(), T, torch.tensor([1.0, 0.1], dtype=D),
                                 torch.tensor([0.01], dtype=D), u_lower=lo, u_upper=hi).solve(x0, xr, ur).U
    lo, hi = lim.clone().requires_grad_(True), lim.clone().requires_grad_(True)
    glo, ghi = torch.autograd.grad(solve(lo, hi).sum(), (lo, hi))
    flo, fhi = _one_sided_limit_fd(solve, lim, lim)
    torch.testing.assert_close(glo, flo, rtol=0, atol=1e-5)
    torch.testing.assert_close(ghi, fhi, rtol=0, atol=1e-5)
    torch.testing.assert_close(glo + ghi, torch.ones_like(lim), rtol=0, atol=1e-9)  # each pinned control
    assert float(ghi.sum()) >= 1  # the regime: some controls pushed against the upper limit
