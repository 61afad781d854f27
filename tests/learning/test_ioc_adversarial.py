"""Adversarial regression tests for learning/ioc.py (issue 26 §2): each test fails on a defect found by
probing (report of the adversarial review) and passes once it is fixed."""

from __future__ import annotations

import math

import pytest
import torch

from controllers.dynamics import LinearDynamics
from controllers.lqt_cookbook import double_integrator
from controllers.problem import LQProblem
from controllers.riccati import solve
from learning.ioc import LQTCostModel, SPDWeight, ViaPoints, fit_cost, ioc_loss, normalize_scale, time_weights

D64 = torch.float64
TARGET = torch.tensor([1.0, -0.5, 0.0, 0.0], dtype=D64)


def _coupled(dtype=D64):
    di = double_integrator(2, 0.1, dtype)
    c, s = math.cos(0.5), math.sin(0.5)
    return LinearDynamics(di.A, di.B @ torch.tensor([[c, -s], [s, c]], dtype=dtype))


def _small():
    dyn = _coupled()
    g = torch.Generator().manual_seed(5)
    Qi = torch.randn(4, 4, generator=g, dtype=D64)
    Qi = Qi @ Qi.mT / 4 + 0.5 * torch.eye(4, dtype=D64)
    Rw = SPDWeight(torch.tensor([1.0, 2.0], dtype=D64), fix_first=True)
    model = LQTCostModel(SPDWeight(Qi, "full"), Rw, 8, target=TARGET, learn_target=True,
                         terminal_factor=3.0, learn_terminal=True)
    xd = torch.randn(3, 9, 4, generator=g, dtype=D64) * 0.3
    return dyn, model, xd


def test_fitted_via_time_stays_in_horizon():
    """A via point at the horizon's end: Adam's momentum carries τ past T, where the clamp kills its
    gradient for good; the fitted model then reports a time its own constructor rejects."""
    T = 20
    dyn = double_integrator(2, 0.1)
    P = torch.diag(torch.tensor([100.0, 100.0, 0.0, 0.0], dtype=D64))
    m_true = torch.tensor([[0.5, 1.0, 0.0, 0.0]], dtype=D64)

    def model(t, learn):
        vp = ViaPoints(m_true.clone(), torch.tensor([t], dtype=D64), P, width=1.5, learn_targets=False,
                       learn_times=learn)
        Qw = SPDWeight(torch.full((4,), 1e-3, dtype=D64), learn=False)
        return LQTCostModel(Qw, torch.eye(2, dtype=D64), T, target=TARGET, terminal_factor=1000.0,
                            via_points=vp)

    x0 = 0.1 * torch.randn(4, 4, generator=torch.Generator().manual_seed(0), dtype=D64)
    with torch.no_grad():
        xd = solve(LQProblem(dyn, model(float(T), False)(), x0, horizon=T), grad="none").x
    res = fit_cost(xd, dyn, model(T - 1.0, True), steps=25, optimizer="adam", lr=0.5)
    tau = float(res.model.weights()["via_times"][0])
    assert 0.0 <= tau <= T, tau
    assert 0.0 <= float(res.model.via_points.times.detach()[0]) <= T
    # the fitted model is a valid model (the constructor's own range check)
    LQTCostModel(torch.eye(4, dtype=D64), torch.eye(2, dtype=D64), T, via_points=res.model.via_points)


def _pendulum_problem():
    from controllers.systems.pendulum import Pendulum

    pend, Tp = Pendulum(dt=0.05), 30
    g = torch.Generator().manual_seed(0)
    x0 = torch.stack([torch.rand(3, generator=g, dtype=D64) * 2 - 1,
                      torch.randn(3, generator=g, dtype=D64)], -1)
    goal = torch.tensor([1.2, 0.0], dtype=D64)
    s = torch.linspace(0, 1, Tp + 1, dtype=D64)[None, :, None]
    xd = x0[:, None, :] + s * (goal - x0)[:, None, :]
    model = LQTCostModel(SPDWeight(torch.tensor([10.0, 0.5], dtype=D64)), torch.tensor([[0.1]], dtype=D64),
                         Tp, target=goal, terminal_factor=10.0, learn_terminal=True)
    return pend, model, xd


def test_nonconverged_ilqr_demo_gradient_is_exact_or_excluded():
    """Issue: a non-converged solve's gradient is either exact or excluded.  With max_iter=2 no demo
    converges, all stay usable, and the implicit gradient at the last iterate is off by 10-30 %."""
    from controllers.ilqr import ILQROptions

    pend, model, xd = _pendulum_problem()
    opts = ILQROptions(max_iter=2)
    base = {k: p.detach().clone() for k, p in model.named_parameters()}

    def per(pd):
        return ioc_loss(torch.func.functional_call(model, pd, ()), pend, xd, solver="ilqr", options=opts)

    pr = {k: v.clone().requires_grad_(True) for k, v in base.items()}
    out = per(pr)
    assert bool((~out.status.converged).any())  # the situation under test
    for i in range(3):
        if not bool(out.usable[i]) or bool(out.status.converged[i]):
            continue  # excluded, or converged: fine
        grads = torch.autograd.grad(out.per_demo[i], list(pr.values()), retain_graph=True)
        for (k, v), gk in zip(base.items(), grads):
            for j in range(v.numel()):
                up = {a: b.clone() for a, b in base.items()}
                dn = {a: b.clone() for a, b in base.items()}
                up[k].view(-1)[j] += 1e-6
                dn[k].view(-1)[j] -= 1e-6
                with torch.no_grad():
                    fd = float((per(up).per_demo[i] - per(dn).per_demo[i]) / 2e-6)
                ga = float(gk.view(-1)[j])
                assert abs(ga - fd) <= 1e-4 * (abs(fd) + 1e-8), (i, k, j, ga, fd)


@pytest.mark.parametrize("solver", ["riccati", "lifted"])
def test_overflowing_demo_does_not_poison_loss_or_gradient(solver):
    """A finite but huge start: the solve is 'CONVERGED' and the demo 'usable', yet its squared error
    overflows, making the shared loss inf and every parameter gradient NaN."""
    dyn, model, xd = _small()
    params = list(model.parameters())
    bad = xd.clone()
    bad[1, 0, 0] = 1e160
    out = ioc_loss(model, dyn, bad, solver=solver)
    grads = torch.autograd.grad(out.loss, params)
    assert bool(torch.isfinite(out.loss)), out.loss
    assert all(bool(torch.isfinite(gr).all()) for gr in grads)
    assert not bool(out.usable[1])  # reported per demo, left out
    ref = ioc_loss(model, dyn, xd[[0, 2]], solver=solver)
    assert torch.allclose(out.loss, ref.loss)
    for a, b in zip(grads, torch.autograd.grad(ref.loss, params)):
        assert torch.allclose(a, b)


def test_spd_weight_full_accepts_rounding_asymmetry():
    """rtol=1e-10, atol=0: a float32 Gram matrix A Aᵀ (asymmetric at round-off) and a float64 matrix with
    1e-17 off-diagonal noise are rejected as 'not symmetric'."""
    A = torch.randn(6, 6, generator=torch.Generator().manual_seed(0))
    M = A @ A.mT + 0.1 * torch.eye(6)
    assert not bool((M == M.mT).all())  # the situation under test: round-off asymmetry
    w = SPDWeight(M, "full")
    assert w().dtype == torch.float32
    assert torch.allclose(w(), 0.5 * (M + M.mT), rtol=1e-5, atol=1e-5)
    M64 = torch.tensor([[1.0, 1e-17, 0.0], [-1e-17, 1.0, 0.0], [0.0, 0.0, 1.0]], dtype=D64)
    assert torch.allclose(SPDWeight(M64, "full")(), torch.eye(3, dtype=D64), atol=1e-15)


@pytest.mark.parametrize("dtype,width", [(torch.float32, 1e-20), (torch.float64, 1e-200)])
def test_time_weights_tiny_width_is_finite(dtype, width):
    """width -> 0: (d / width)² overflows to inf for every step, softmax of all -inf gives NaN weights
    (accepted silently: width passes the positive-finite check).  The limit is the linear split's nearest
    step / the two equidistant steps."""
    W = time_weights(torch.tensor([3.5, 2.0], dtype=dtype), 10, "gaussian", width)
    assert bool(torch.isfinite(W).all())
    assert torch.allclose(W.sum(-1), torch.ones(2, dtype=dtype))
    assert float(W[1, 2]) == 1.0 and abs(float(W[0, 3]) - 0.5) < 1e-6 and abs(float(W[0, 4]) - 0.5) < 1e-6


def test_normalize_scale_rejects_nan_scale():
    """R_00 = NaN passes the `R_00 <= 0` check and returns all-NaN weights silently."""
    with pytest.raises(ValueError, match="R"):
        normalize_scale(torch.tensor([[math.nan]], dtype=D64), torch.eye(2, dtype=D64))


def test_unconverged_choice_is_explicit_and_reported():
    """'exclude' (default) leaves a non-converged demo out (reported, error still shown); 'include' keeps
    it; fit_cost says why nothing is usable and counts the non-converged demos per evaluation."""
    from controllers.ilqr import ILQROptions

    pend, model, xd = _pendulum_problem()
    opts = ILQROptions(max_iter=2)
    ex = ioc_loss(model, pend, xd, solver="ilqr", options=opts)
    assert not bool(ex.status.converged.any()) and not bool(ex.usable.any())
    assert bool(torch.isnan(ex.loss)) and bool(torch.isfinite(ex.per_demo).all())
    inc = ioc_loss(model, pend, xd, solver="ilqr", options=opts, unconverged="include")
    assert bool(inc.usable.all()) and torch.allclose(inc.loss, inc.per_demo.mean())
    assert torch.allclose(inc.per_demo, ex.per_demo)
    with pytest.raises(ValueError, match="unconverged='include'"):
        fit_cost(xd, pend, model, steps=1, optimizer="adam", solver="ilqr", options=opts)
    res = fit_cost(xd, pend, model, steps=1, optimizer="adam", solver="ilqr", options=opts,
                   unconverged="include")
    assert res.history["not_converged"] == [3, 3] and res.history["unusable"] == [0, 0]
    assert bool(res.usable.all()) and not bool(res.status.converged.any())
    with pytest.raises(ValueError, match="'unconverged'"):
        ioc_loss(model, pend, xd, solver="ilqr", unconverged="drop")


def test_fit_cost_rejects_nan_tol():
    dyn, model, xd = _small()
    for bad in (math.nan, -1.0):
        with pytest.raises(ValueError, match="'tol'"):
            fit_cost(xd, dyn, model, steps=1, tol=bad)


def test_time_outside_horizon_is_reflected_with_gradient():
    """Past an end the kernel is that of the reflected time, and the gradient does not vanish."""
    T = 10
    tau = torch.tensor([-1.3, 12.5, 10.0], dtype=D64, requires_grad=True)
    for kernel in ("gaussian", "linear"):
        W = time_weights(tau, T, kernel, 1.2)
        assert torch.allclose(W, time_weights(torch.tensor([1.3, 7.5, 10.0], dtype=D64), T, kernel, 1.2))
        gr = torch.autograd.grad((W * torch.arange(T + 1, dtype=D64)).sum(), tau)[0]
        assert bool((gr[:2].abs() > 0.1).all()), gr
