"""Sampling-based planning (MPPI, predictive sampling) and the receding-horizon SamplingMPC."""

from __future__ import annotations

import math

import pytest
import torch

from controllers import riccati
from controllers.costs import QuadraticCost
from controllers.dynamics import LinearDynamics, rollout
from controllers.mpc import shift
from controllers.problem import LQProblem
from controllers.sampling import (
    SamplingMPC,
    SamplingOptions,
    SamplingState,
    plan,
    smoothing_matrix,
)
from controllers.systems import Pendulum

D64 = torch.float64
T = 20
PEND = Pendulum(dt=0.05, damping=0.1)


def _cost(dtype=D64):
    return QuadraticCost(Q=torch.diag(torch.tensor([1.0, 0.1], dtype=dtype)),
                         R=torch.tensor([[0.01]], dtype=dtype),
                         x_ref=torch.tensor([math.pi, 0.0], dtype=dtype))


def _x0(B=4, dtype=D64):
    x = torch.zeros(B, 2, dtype=dtype)
    x[:, 0] = torch.linspace(-0.5, 0.5, B, dtype=dtype)
    x[:, 1] = torch.linspace(0.3, -0.3, B, dtype=dtype)
    return x


def _true_cost(u, x0, dtype=D64):
    """Independent evaluation: our rollout and the cost, per element."""
    return _cost(dtype).evaluate(rollout(PEND, x0, u), u)


def _opts(**kw):
    base = dict(samples=64, iterations=3, noise_sigma=2.0, temperature=0.5)
    base.update(kw)
    return SamplingOptions(**base)


@pytest.mark.parametrize("method", ["mppi", "predictive"])
def test_batched_equals_loop_with_common_noise_and_same_seed(method):
    x0, u0 = _x0(), torch.zeros(4, T, 1, dtype=D64)
    opts = _opts(method=method, common_noise=True, smoothing="knots", knots=5)
    r = plan(PEND, _cost(), x0, u0, u_lower=-5.0, u_upper=5.0, options=opts,
             generator=torch.Generator().manual_seed(3))
    for b in range(4):
        rb = plan(PEND, _cost(), x0[b], u0[b], u_lower=-5.0, u_upper=5.0, options=opts,
                  generator=torch.Generator().manual_seed(3))
        torch.testing.assert_close(r.u[b], rb.u)
        torch.testing.assert_close(r.x[b], rb.x)
        torch.testing.assert_close(r.cost[b], rb.cost)
        torch.testing.assert_close(r.costs_history[b], rb.costs_history)


def test_batched_equals_loop_with_independent_draws():
    B, opts = 3, _opts(smoothing="lowpass", lowpass=0.7)
    x0, u0 = _x0(B), 0.1 * torch.ones(B, T, 1, dtype=D64)
    g = torch.Generator().manual_seed(5)
    # the documented draw order: one (*B, K, T_z, m) draw per iteration
    noise = torch.stack([torch.randn(B, 64, T, 1, generator=g, dtype=D64) for _ in range(3)])
    r_gen = plan(PEND, _cost(), x0, u0, options=opts, generator=torch.Generator().manual_seed(5))
    r = plan(PEND, _cost(), x0, u0, options=opts, noise=noise)
    torch.testing.assert_close(r_gen.u, r.u, rtol=0, atol=0)
    for b in range(B):
        rb = plan(PEND, _cost(), x0[b], u0[b], options=opts, noise=noise[:, b])
        torch.testing.assert_close(r.u[b], rb.u)
        torch.testing.assert_close(r.cost[b], rb.cost)
    assert not torch.equal(r.u[0], r.u[1])  # independent draws: the elements differ


@pytest.mark.parametrize("method", ["mppi", "predictive"])
def test_never_worse_than_nominal(method):
    """A good nominal (a previous plan) and wide noise: most samples are worse, the plan must not be."""
    x0 = _x0(6)
    g = torch.Generator().manual_seed(0)
    zero = torch.zeros(6, T, 1, dtype=D64)
    good = plan(PEND, _cost(), x0, zero, options=_opts(iterations=10), generator=g).u
    nominal = good + 0.05 * torch.randn(good.shape, generator=g, dtype=D64)
    r = plan(PEND, _cost(), x0, nominal, options=_opts(method=method, samples=4, noise_sigma=3.0,
                                                       temperature=50.0, iterations=2), generator=g)
    c_nom, c_new = _true_cost(nominal, x0), _true_cost(r.u, x0)
    assert (c_new <= c_nom + 1e-12).all()
    torch.testing.assert_close(r.cost, c_new)
    torch.testing.assert_close(r.nominal_cost, c_nom)
    if method == "predictive":  # the iterates never get worse (MPPI's may; its result does not)
        assert (r.costs_history.diff(dim=-1) <= 1e-12).all()


def test_mppi_update_and_fallback_against_a_manual_computation():
    """One MPPI iteration recomputed by hand: w ∝ exp(-(S - min S)/λ) over [U, clip(U + σz)], the update
    U + Σ w (V - U), and the returned plan the better of the update and the best candidate."""
    torch.manual_seed(0)
    B, K, lam, sig = 5, 32, 30.0, 2.0
    x0, u0 = _x0(B), torch.zeros(B, T, 1, dtype=D64)
    z = torch.randn(1, B, K, T, 1, generator=torch.Generator().manual_seed(1), dtype=D64)
    r = plan(PEND, _cost(), x0, u0, u_lower=-3.0, u_upper=3.0, noise=z,
             options=SamplingOptions(samples=K, iterations=1, noise_sigma=sig, temperature=lam))
    V = torch.cat([u0.unsqueeze(1), (u0.unsqueeze(1) + sig * z[0]).clamp(-3, 3)], 1)  # (B, 1+K, T, 1)
    S = _cost().evaluate(rollout(PEND, x0.unsqueeze(1), V), V)
    w = torch.softmax(-(S - S.amin(1, keepdim=True)) / lam, 1)
    U = u0 + (w[..., None, None] * (V - u0.unsqueeze(1))).sum(1)
    S_U = _true_cost(U, x0)
    torch.testing.assert_close(r.update_cost, S_U)
    torch.testing.assert_close(r.cost, torch.minimum(S_U, S.amin(1)))
    torch.testing.assert_close(r.best_cost, S[:, 1:].amin(1))
    expect = torch.where((S.amin(1) < S_U)[:, None, None], V[torch.arange(B), S.argmin(1)], U)
    torch.testing.assert_close(r.u, expect)
    assert r.fallback.any()  # a hot temperature averages poor samples in: the best sample wins somewhere
    assert torch.equal(r.fallback, S.amin(1) < S_U)


def test_predictive_is_the_argmin_of_the_candidates():
    B, K = 4, 16
    x0, u0 = _x0(B), torch.zeros(B, T, 1, dtype=D64)
    z = torch.randn(1, B, K, T, 1, generator=torch.Generator().manual_seed(2), dtype=D64)
    r = plan(PEND, _cost(), x0, u0, noise=z,
             options=SamplingOptions(samples=K, iterations=1, noise_sigma=1.0, method="predictive"))
    V = torch.cat([u0.unsqueeze(1), u0.unsqueeze(1) + z[0]], 1)
    S = _cost().evaluate(rollout(PEND, x0.unsqueeze(1), V), V)
    torch.testing.assert_close(r.u, V[torch.arange(B), S.argmin(1)])
    assert not r.fallback.any()


def test_mppi_approaches_the_lqr_plan():
    """Linear dynamics, quadratic cost: the fixed point of the (infinite-sample) MPPI update is the LQ
    optimum, so many samples and a small temperature land close to the Riccati solution."""
    dt, Tl = 0.1, 6
    dyn = LinearDynamics(torch.tensor([[1, dt], [0, 1]], dtype=D64),
                         torch.tensor([[0.5 * dt * dt], [dt]], dtype=D64))
    cost = QuadraticCost(Q=torch.eye(2, dtype=D64), R=torch.tensor([[0.1]], dtype=D64))
    x0 = torch.tensor([[1.0, 0.5], [-0.5, 1.0]], dtype=D64)
    sol = riccati.solve(LQProblem(dyn, cost, x0, horizon=Tl), grad="none")
    r = plan(dyn, cost, x0, torch.zeros(2, Tl, 1, dtype=D64), generator=torch.Generator().manual_seed(1),
             options=SamplingOptions(samples=4096, iterations=15, noise_sigma=0.5, temperature=0.05))
    rel = (r.u - sol.u).norm(dim=(-1, -2)) / sol.u.norm(dim=(-1, -2))
    assert (rel < 0.02).all(), rel
    assert ((r.cost - sol.cost) / sol.cost).abs().max() < 1e-4
    assert (r.cost >= sol.cost - 1e-9).all()  # nothing beats the optimum


@pytest.mark.parametrize("method", ["mppi", "predictive"])
def test_limits_respected_and_nominal_clipped(method):
    lo = torch.tensor([-1.5], dtype=D64)
    x0, u0 = _x0(), 4.0 * torch.ones(4, T, 1, dtype=D64)  # nominal outside the limits
    r = plan(PEND, _cost(), x0, u0, u_lower=lo, u_upper=2.0, generator=torch.Generator().manual_seed(0),
             options=_opts(method=method, noise_sigma=5.0))
    assert (r.u >= -1.5).all() and (r.u <= 2.0).all()
    assert ((r.u == -1.5) | (r.u == 2.0)).any()  # the limits are active
    torch.testing.assert_close(r.nominal_cost, _true_cost(u0.clamp(-1.5, 2.0), x0))
    torch.testing.assert_close(r.x, rollout(PEND, x0, r.u))


def test_nan_element_is_isolated():
    B = 3
    x0, u0 = _x0(B), torch.zeros(B, T, 1, dtype=D64)
    z = torch.randn(2, B, 32, T, 1, generator=torch.Generator().manual_seed(0), dtype=D64)
    opts = _opts(samples=32, iterations=2)
    bad = x0.clone()
    bad[1, 0] = math.nan
    r = plan(PEND, _cost(), bad, u0, options=opts, noise=z)
    ref = plan(PEND, _cost(), x0, u0, options=opts, noise=z)
    assert r.finite.tolist() == [True, False, True]
    assert torch.isnan(r.u[1]).all() and torch.isnan(r.cost[1])
    for b in (0, 2):
        torch.testing.assert_close(r.u[b], ref.u[b])
        torch.testing.assert_close(r.cost[b], ref.cost[b])


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("smoothing", ["none", "knots", "lowpass"])
def test_dtypes_and_smoothing(dtype, smoothing):
    x0, u0 = _x0(dtype=dtype), torch.zeros(4, T, 1, dtype=dtype)
    r = plan(PEND, _cost(dtype), x0, u0, generator=torch.Generator().manual_seed(0),
             options=_opts(smoothing=smoothing, noise_sigma=torch.tensor([2.0], dtype=dtype)))
    assert r.u.dtype == r.x.dtype == r.cost.dtype == dtype
    assert r.finite.all() and (r.cost < r.nominal_cost).all()
    torch.testing.assert_close(r.cost, _true_cost(r.u, x0, dtype), rtol=1e-5, atol=1e-4)


def test_smoothing_matrices():
    lp = smoothing_matrix(SamplingOptions(smoothing="lowpass", lowpass=0.6), 7)
    cov = lp @ lp.T  # stationary AR(1): unit variance, correlation β^|t-s|
    t = torch.arange(7, dtype=D64)
    torch.testing.assert_close(cov, 0.6 ** (t[:, None] - t[None, :]).abs())
    z = torch.randn(7, generator=torch.Generator().manual_seed(0), dtype=D64)
    e = [z[0]]
    for k in range(1, 7):
        e.append(0.6 * e[-1] + math.sqrt(1 - 0.36) * z[k])
    torch.testing.assert_close(lp @ z, torch.stack(e))
    kn = smoothing_matrix(SamplingOptions(smoothing="knots", knots=4), 10)
    assert kn.shape == (10, 4)
    torch.testing.assert_close(kn[[0, 3, 6, 9]], torch.eye(4, dtype=D64))  # knots at 0, 3, 6, 9
    torch.testing.assert_close(kn.sum(1), torch.ones(10, dtype=D64))  # linear interpolation
    assert smoothing_matrix(SamplingOptions(), 10) is None


def test_bad_arguments():
    x0, u0, g = _x0(), torch.zeros(4, T, 1, dtype=D64), torch.Generator()
    for kw, name in (({"samples": 0}, "samples"), ({"temperature": -1.0}, "temperature"),
                     ({"temperature": 0.0}, "temperature"), ({"iterations": 0}, "iterations"),
                     ({"method": "cem"}, "method"), ({"noise_sigma": -1.0}, "noise_sigma"),
                     ({"lowpass": 1.0}, "lowpass"), ({"knots": 1}, "knots"), ({"elites": 0}, "elites")):
        with pytest.raises(ValueError, match=name):
            SamplingOptions(**kw)
    with pytest.raises(ValueError, match="u_nominal"):
        plan(PEND, _cost(), x0, torch.zeros(4, T, 2, dtype=D64), generator=g)
    with pytest.raises(ValueError, match="u_nominal"):
        plan(PEND, _cost(), x0, torch.zeros(T, dtype=D64), generator=g)
    with pytest.raises(ValueError, match="x0"):
        plan(PEND, _cost(), torch.zeros(4, 3, dtype=D64), u0, generator=g)
    with pytest.raises(ValueError, match="u_nominal"):
        plan(PEND, _cost(), x0, torch.zeros(3, T, 1, dtype=D64), generator=g)
    with pytest.raises(TypeError, match="generator"):
        plan(PEND, _cost(), x0, u0)
    with pytest.raises(ValueError, match="noise"):
        plan(PEND, _cost(), x0, u0, noise=torch.zeros(1, 4, 5, T, 1, dtype=D64))
    with pytest.raises(ValueError, match="noise_sigma"):
        plan(PEND, _cost(), x0, u0, generator=g, options=_opts(noise_sigma=torch.ones(3, dtype=D64)))
    with pytest.raises(ValueError, match="u_upper"):
        plan(PEND, _cost(), x0, u0, generator=g, u_upper=torch.ones(T, 3, dtype=D64))
    with pytest.raises(TypeError, match="u_nominal"):
        plan(PEND, _cost(), x0, u0.float(), generator=g)


def test_elites_restrict_the_weights():
    x0, u0 = _x0(2), torch.zeros(2, T, 1, dtype=D64)
    z = torch.randn(1, 2, 16, T, 1, generator=torch.Generator().manual_seed(0), dtype=D64)
    one = plan(PEND, _cost(), x0, u0, noise=z, options=SamplingOptions(samples=16, elites=1, temperature=1e3))
    pred = plan(PEND, _cost(), x0, u0, noise=z, options=SamplingOptions(samples=16, method="predictive"))
    torch.testing.assert_close(one.u, pred.u)  # one elite: the update is the best candidate


def test_sampling_mpc_stabilizes_and_carries_the_shifted_plan():
    mpc = SamplingMPC(PEND, _cost(), 20, _opts(samples=64, iterations=2, noise_sigma=1.0, temperature=0.1),
                      u_lower=-8.0, u_upper=8.0)
    x = torch.tensor([[math.pi - 0.6, 0.0], [math.pi + 0.4, 0.5], [math.nan, 0.0]], dtype=D64)
    state = mpc.initial_state(3, dtype=D64)
    assert isinstance(state, SamplingState) and state.u.shape == (3, 20, 1)
    g = torch.Generator().manual_seed(0)
    for _ in range(40):
        u, nxt, res = mpc(x, state, g)
        torch.testing.assert_close(nxt.u[:2], shift(res.u[:2]))
        assert (nxt.u[2] == 0).all() and torch.isnan(u[2]).all()  # the NaN element restarts from zeros
        torch.testing.assert_close(u[:2], res.u[:2, 0])
        x, state = PEND.step(x, u), nxt
    assert (x[:2, 0] - math.pi).abs().max() < 0.1 and x[:2, 1].abs().max() < 0.5
    reset = state.reset(torch.tensor([True, False, False]))
    assert (reset.u[0] == 0).all() and torch.equal(reset.u[1], state.u[1])
    with pytest.raises(ValueError, match="horizon"):
        mpc(x, mpc.initial_state(3, dtype=D64).__class__(torch.zeros(3, 5, 1, dtype=D64), torch.zeros(3)), g)


class _CountingSystem:
    """The pendulum behind ``rollout_states`` (as a MuJoCo system provides it), recording each call."""

    n, m = 2, 1

    def __init__(self):
        self.calls = []

    def step(self, x, u, t=0):
        raise AssertionError("plan must prefer rollout_states")

    def rollout_states(self, x0, u):
        self.calls.append((tuple(x0.shape), tuple(u.shape)))
        return rollout(PEND, x0, u)


def test_one_rollout_states_call_per_iteration_and_per_element_cost_fields():
    sysm, B, K = _CountingSystem(), 3, 16
    target = torch.zeros(B, 1, 2, dtype=D64)
    target[:, 0, 0] = torch.tensor([math.pi, 1.0, -1.0], dtype=D64)  # one target per element (*B, 1, n)
    cost = QuadraticCost(Q=torch.eye(2, dtype=D64), R=0.01 * torch.eye(1, dtype=D64), x_ref=target)
    x0, u0 = _x0(B), torch.zeros(B, T, 1, dtype=D64)
    opts = _opts(samples=K, iterations=2, common_noise=True)
    r = plan(sysm, cost, x0, u0, options=opts, generator=torch.Generator().manual_seed(0))
    # two iterations of (1 + K, *B) candidates, then the final MPPI update
    assert sysm.calls == [((1 + K, B, 2), (1 + K, B, T, 1))] * 2 + [((1, B, 2), (1, B, T, 1))]
    for b in range(B):
        cb = QuadraticCost(Q=torch.eye(2, dtype=D64), R=0.01 * torch.eye(1, dtype=D64), x_ref=target[b, 0])
        rb = plan(PEND, cb, x0[b], u0[b], options=opts, generator=torch.Generator().manual_seed(0))
        torch.testing.assert_close(r.u[b], rb.u)
        torch.testing.assert_close(r.cost[b], rb.cost)
