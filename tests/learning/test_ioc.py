"""Inverse optimal control (learning/ioc.py; issue 26 §2, seed 004 §7, §7.7, §8).

Recovery tests generate noiseless demos with a known cost (an independent solve with ``grad="none"``) and
fit a model started elsewhere; gradients are checked against finite differences, ``gradcheck`` and the
other solver formulation (implicit Riccati vs autograd through the batch Cholesky of Eq. 62).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from controllers.dynamics import LinearDynamics
from controllers.lqt_cookbook import double_integrator
from controllers.problem import LQProblem, Reason
from controllers.riccati import solve
from learning.demos import Demonstrations
from learning.ioc import (
    LQTCostModel,
    SPDWeight,
    ViaPoints,
    fit_cost,
    ioc_loss,
    minimal_intervention,
    normalize_scale,
    time_weights,
)
from learning.primitives import fit_promp

D64 = torch.float64
T = 30
TARGET = torch.tensor([1.0, -0.5, 0.0, 0.0], dtype=D64)
Q_TRUE = torch.tensor([2.0, 0.5, 0.3, 0.1], dtype=D64)
R_TRUE = torch.tensor([1.0, 3.0], dtype=D64)


def _coupled(dt=0.1, dtype=D64):
    """Planar double integrator whose control axes are rotated by 0.5 rad: a diagonal cost does not
    decouple it into independent axes (each of which would have its own unidentifiable scale)."""
    di = double_integrator(2, dt, dtype)
    c, s = math.cos(0.5), math.sin(0.5)
    rot = torch.tensor([[c, -s], [s, c]], dtype=dtype)
    return LinearDynamics(di.A, di.B @ rot)


def _starts(N=8, seed=0, scale=1.0, dtype=D64):
    g = torch.Generator().manual_seed(seed)
    return (scale * torch.randn(N, 4, generator=g, dtype=D64)).to(dtype)


def _model(q, r, kind="diagonal", tf=5.0, learn=True, T=T, target=TARGET, via=None):
    return LQTCostModel(SPDWeight(q, kind, learn=learn), SPDWeight(r, fix_first=True, learn=learn), T,
                        target=target, terminal_factor=tf, learn_terminal=learn, via_points=via)


def _demos(dyn, cost, x0, T=T):
    with torch.no_grad():
        return solve(LQProblem(dyn, cost, x0, horizon=T), grad="none")


def _rel(a, b):
    return float((a - b).norm() / b.norm())


# ------------------------------------------------------------------------------------ parametrizations
def test_spd_weight_values_and_fix_first():
    g = torch.Generator().manual_seed(1)
    A = torch.randn(3, 4, 4, generator=g, dtype=D64)
    M = A @ A.mT + 0.1 * torch.eye(4, dtype=D64)
    w = SPDWeight(M, "full", fix_first=True)
    assert torch.allclose(w(), M, atol=1e-12)  # the initial matrix is reproduced
    assert w.log_diag.shape == (3, 3) and w.lower.shape == (3, 6)  # k-1 free log-diagonal entries
    with torch.no_grad():  # any parameter vector gives an SPD matrix, W_00 stays fixed
        w.log_diag.copy_(torch.randn(3, 3, generator=g, dtype=D64) * 3)
        w.lower.copy_(torch.randn(3, 6, generator=g, dtype=D64) * 3)
    W = w()
    assert torch.allclose(W, W.mT) and bool((torch.linalg.eigvalsh(W) > 0).all())
    assert torch.allclose(W[:, 0, 0], M[:, 0, 0])
    L = np.linalg.cholesky(W.detach().numpy())  # the factor is the Cholesky factor (positive diagonal)
    assert np.allclose(L, w.factor().detach().numpy())
    d = SPDWeight(torch.tensor([0.5, 2.0, 7.0], dtype=D64))
    assert torch.allclose(d(), torch.diag(torch.tensor([0.5, 2.0, 7.0], dtype=D64)))
    assert d.log_diag.dtype == D64 and SPDWeight(torch.ones(2)).log_diag.dtype == torch.float32
    fixed = SPDWeight(torch.ones(2, dtype=D64), learn=False)
    assert list(fixed.parameters()) == []
    one = SPDWeight(torch.tensor([0.1], dtype=D64), fix_first=True)  # m = 1: the normalization fixes R
    assert list(one.parameters()) == [] and torch.allclose(one(), torch.tensor([[0.1]], dtype=D64))


def test_time_weights_against_formula():
    tau = torch.tensor([3.3, 0.0, 10.0], dtype=D64)
    W = time_weights(tau, 10, "gaussian", 1.5)
    t = np.arange(11.0)
    ref = np.exp(-((t[None] - tau.numpy()[:, None]) ** 2) / (2 * 1.5 ** 2))
    assert np.allclose(W.numpy(), ref / ref.sum(-1, keepdims=True), atol=1e-14)
    L = time_weights(tau, 10, "linear")
    assert torch.allclose(L.sum(-1), torch.ones(3, dtype=D64))
    assert abs(float(L[0, 3]) - 0.7) < 1e-14 and abs(float(L[0, 4]) - 0.3) < 1e-14 and float(L[1, 0]) == 1.0
    tt = torch.tensor([4.37], dtype=D64, requires_grad=True)
    for kernel in ("gaussian", "linear"):
        assert torch.autograd.gradcheck(lambda a, k=kernel: time_weights(a, 10, k, 1.2), (tt,))


# ------------------------------------------------------------------------------------ recovery
def test_recover_diagonal_weights_and_terminal_factor():
    dyn = _coupled()
    truth = _model(Q_TRUE, R_TRUE, learn=False)
    xd = _demos(dyn, truth(), _starts()).x
    init = _model(torch.ones(4, dtype=D64), torch.ones(2, dtype=D64), tf=1.0)
    res = fit_cost(xd, dyn, init, steps=60, solver="lifted")
    w = res.model.weights()
    assert _rel(w["Q"].diagonal(), Q_TRUE) < 1e-3
    assert _rel(w["R"].diagonal(), R_TRUE) < 1e-3 and float(w["R"][0, 0]) == 1.0  # the fixed weight
    assert abs(float(w["terminal_factor"]) - 5.0) < 5e-3
    assert res.loss < 1e-12 and res.history["loss"][0] > 1e-3
    assert res.status.all_converged and sum(res.history["not_converged"]) == 0
    # the argument is not modified
    assert torch.allclose(init.weights()["Q"], torch.eye(4, dtype=D64))


def test_recover_full_state_weight_by_cholesky():
    dyn = double_integrator(2, 0.1)  # a full Q couples the axes: one scale, fixed by R_00
    g = torch.Generator().manual_seed(3)
    A = torch.randn(4, 4, generator=g, dtype=D64)
    Qf = A @ A.mT / 4 + 0.2 * torch.eye(4, dtype=D64)
    truth = _model(Qf, R_TRUE, kind="full", learn=False)
    xd = _demos(dyn, truth(), _starts()).x
    init = _model(torch.eye(4, dtype=D64), torch.ones(2, dtype=D64), kind="full", tf=1.0)
    res = fit_cost(xd, dyn, init, steps=120, solver="lifted")
    w = res.model.weights()
    assert _rel(w["Q"], Qf) < 1e-3 and _rel(w["R"].diagonal(), R_TRUE) < 1e-3
    assert res.loss < 1e-12


@pytest.mark.parametrize("kernel,tau", [("gaussian", 12.4), ("linear", 12.3)])
def test_recover_via_point_target_and_time(kernel, tau):
    dyn = double_integrator(2, 0.1)
    P = torch.diag(torch.tensor([100.0, 100.0, 0.0, 0.0], dtype=D64))  # positions only
    m_true = torch.tensor([[0.5, 1.0, 0.0, 0.0]], dtype=D64)
    q = torch.full((4,), 1e-3, dtype=D64)

    def model(m, t, learn):
        vp = ViaPoints(m, torch.tensor([t], dtype=D64), P, kernel=kernel, width=1.5, learn_targets=learn,
                       learn_times=learn)
        return LQTCostModel(SPDWeight(q, learn=False), torch.eye(2, dtype=D64), T, target=TARGET,
                            terminal_factor=1000.0, via_points=vp)

    xd = _demos(dyn, model(m_true, tau, False)(), _starts(scale=0.1)).x
    # default solver: Riccati with implicit gradients (the same gradient as "lifted": test below)
    res = fit_cost(xd, dyn, model(torch.zeros(1, 4, dtype=D64), 10.0, True), steps=40)
    assert res.model.via_points.times.requires_grad
    w = res.model.weights()
    assert abs(float(w["via_times"][0]) - tau) < 0.05  # a small fraction of a step
    assert float((w["via_targets"][0, :2] - m_true[0, :2]).abs().max()) < 1e-3


def test_recover_pendulum_weights_ilqr_implicit():
    from controllers.ilqr import ILQRProblem, ilqr
    from controllers.systems.pendulum import Pendulum

    pend, Tp = Pendulum(dt=0.05), 30
    g = torch.Generator().manual_seed(0)
    x0 = torch.stack([torch.rand(6, generator=g, dtype=D64) * 0.6 - 0.3,
                      torch.randn(6, generator=g, dtype=D64) * 0.5], -1)
    goal, R = torch.tensor([1.2, 0.0], dtype=D64), torch.tensor([[0.1]], dtype=D64)
    q_true = torch.tensor([10.0, 0.5], dtype=D64)
    truth = LQTCostModel(SPDWeight(q_true, learn=False), R, Tp, target=goal, terminal_factor=10.0)
    with torch.no_grad():
        sol = ilqr(ILQRProblem(pend, truth(), x0, Tp), grad="none")
    assert sol.status.all_converged
    init = LQTCostModel(SPDWeight(torch.ones(2, dtype=D64)), R, Tp, target=goal, learn_terminal=True)
    res = fit_cost(sol.x, pend, init, u_demo=sol.u, steps=20, solver="ilqr")
    w = res.model.weights()
    assert _rel(w["Q"].diagonal(), q_true) < 1e-3 and abs(float(w["terminal_factor"]) - 10.0) < 1e-2
    assert res.status.all_converged and len(res.history["not_converged"]) == len(res.history["loss"])


# ------------------------------------------------------------------------------------ gradients
def _small_problem(dtype=D64):
    dyn = _coupled(dtype=dtype)
    P = SPDWeight(torch.tensor([[50.0, 50.0, 1.0, 1.0]], dtype=dtype))
    vp = ViaPoints(torch.tensor([[0.3, 0.2, 0.0, 0.0]], dtype=dtype), torch.tensor([3.4], dtype=dtype), P,
                   width=1.0)
    g = torch.Generator().manual_seed(5)
    Qi = torch.randn(4, 4, generator=g, dtype=D64)
    Qi = (Qi @ Qi.mT / 4 + 0.5 * torch.eye(4, dtype=D64)).to(dtype)
    Rw = SPDWeight(torch.tensor([1.0, 2.0], dtype=dtype), fix_first=True)
    model = LQTCostModel(SPDWeight(Qi, "full"), Rw, 8, target=TARGET.to(dtype), learn_target=True,
                         terminal_factor=3.0, learn_terminal=True, via_points=vp)
    xd = (torch.randn(3, 9, 4, generator=g, dtype=D64) * 0.3).to(dtype)
    return dyn, model, xd


def _loss_fn(model, dyn, xd, solver):
    names = [k for k, p in model.named_parameters()]

    def f(*vals):
        out = torch.func.functional_call(model, dict(zip(names, vals)), ())
        return ioc_loss(out, dyn, xd, solver=solver).loss

    return f, tuple(p.detach().clone().requires_grad_(True) for _, p in model.named_parameters())


def test_gradient_gradcheck_fd_and_two_solvers():
    dyn, model, xd = _small_problem()
    f, params = _loss_fn(model, dyn, xd, "riccati")
    assert len(params) == 8  # Q: log-diag + lower, R: one free, target, terminal, via target/time/precision
    assert torch.autograd.gradcheck(f, params, atol=1e-7)
    g_ric = torch.autograd.grad(f(*params), params)
    f_lift, _ = _loss_fn(model, dyn, xd, "lifted")
    g_lift = torch.autograd.grad(f_lift(*params), params)
    for a, b in zip(g_ric, g_lift):
        assert torch.allclose(a, b, rtol=1e-8, atol=1e-12)
    # central differences on the via-point time alone (the continuous timing)
    i = [k for k, _ in model.named_parameters()].index("via_points.times")
    h = 1e-6
    up = [p.detach().clone() for p in params]
    dn = [p.detach().clone() for p in params]
    up[i] += h
    dn[i] -= h
    fd = (f(*up) - f(*dn)) / (2 * h)
    assert abs(float(fd) - float(g_ric[i])) < 1e-7 * (1 + abs(float(fd)))


def test_scale_invariance_and_normalization():
    dyn = _coupled()
    truth = _model(Q_TRUE, R_TRUE, learn=False)
    x0 = _starts()
    c = 7.3
    scaled = LQTCostModel(c * torch.diag(Q_TRUE), c * torch.diag(R_TRUE), T, target=TARGET,
                          terminal_factor=5.0)
    a, b = _demos(dyn, truth(), x0), _demos(dyn, scaled(), x0)
    assert torch.allclose(a.x, b.x, atol=1e-12) and torch.allclose(a.u, b.u, atol=1e-12)
    # the loss is flat along the common scale: d/ds loss(exp(s) · cost) = 0
    model = _model(torch.tensor([1.0, 2.0, 0.5, 0.2], dtype=D64), torch.tensor([1.0, 0.7], dtype=D64))
    s = torch.zeros((), dtype=D64, requires_grad=True)
    base = model()
    from controllers.costs import QuadraticCost
    cost = QuadraticCost(Q=s.exp() * base.Q, R=s.exp() * base.R, q=s.exp() * base.q, check=False)
    (gs,) = torch.autograd.grad(ioc_loss(cost, dyn, a.x).loss, s)
    assert abs(float(gs)) < 1e-12
    # demos from a scaled cost: the fit recovers the weights normalized to R_00 = 1
    res = fit_cost(b.x, dyn, _model(torch.ones(4, dtype=D64), torch.ones(2, dtype=D64), tf=1.0), steps=60,
                   solver="lifted")
    Rn, Qn = normalize_scale(c * torch.diag(R_TRUE), c * torch.diag(Q_TRUE))
    assert _rel(res.model.weights()["Q"], Qn) < 1e-3 and _rel(res.model.weights()["R"], Rn) < 1e-3
    # decoupled axes (plain double integrator, diagonal cost): one scale per axis, so R_00 alone does not fix
    # the second axis' weights (module docstring) -- scaling only its weights changes nothing
    di = double_integrator(2, 0.1)
    k = torch.tensor([1.0, 1.88, 1.0, 1.88], dtype=D64)
    other = LQTCostModel(torch.diag(k * Q_TRUE), torch.diag(k[:2] * R_TRUE), T, target=TARGET,
                         terminal_factor=5.0)
    assert torch.allclose(_demos(di, truth(), x0).x, _demos(di, other(), x0).x, atol=1e-12)
    assert not torch.allclose(_demos(dyn, truth(), x0).x, _demos(dyn, other(), x0).x, atol=1e-6)
    # normalize_scale with batch dims
    Rb = torch.stack([torch.diag(R_TRUE), 2 * torch.diag(R_TRUE)])
    Rn2, tf = normalize_scale(Rb, torch.tensor([5.0, 10.0], dtype=D64))
    assert torch.allclose(Rn2[1], torch.diag(R_TRUE))
    assert torch.allclose(tf, torch.tensor([5.0, 5.0], dtype=D64))


# ------------------------------------------------------------------------------- batching, status, dtypes
def test_batched_equals_loop_and_demonstrations_input():
    dyn, model, xd = _small_problem()
    out = ioc_loss(model, dyn, xd)
    params = [p for p in model.parameters()]
    g_batch = torch.autograd.grad(out.loss, params)
    per, grads = [], []
    for i in range(xd.shape[0]):
        o = ioc_loss(model, dyn, xd[i])
        per.append(o.loss.detach())
        grads.append(torch.autograd.grad(o.loss, params))
    assert torch.allclose(out.per_demo.detach(), torch.stack(per), rtol=1e-12)
    for j, gb in enumerate(g_batch):
        assert torch.allclose(gb, sum(gr[j] for gr in grads) / len(grads), rtol=1e-10, atol=1e-14)
    # a leading batch of batches is the same as flat
    out2 = ioc_loss(model, dyn, xd.reshape(1, 3, 9, 4))
    assert torch.allclose(out2.per_demo.reshape(3), out.per_demo)
    # Demonstrations input (T+1 samples, T controls)
    dm = Demonstrations(x=xd, dt=0.1, u=torch.zeros(3, 8, 2, dtype=D64))
    assert torch.allclose(ioc_loss(model, dyn, dm).loss, out.loss)
    assert torch.allclose(ioc_loss(model, dyn, dm, control_weight=0.5).loss,
                          out.loss + 0.5 * (out.u ** 2).mean((-1, -2)).mean())


def test_nan_demo_is_reported_and_does_not_poison():
    dyn, model, xd = _small_problem()
    bad = xd.clone()
    bad[1, 0, 0] = math.nan  # its start state
    out = ioc_loss(model, dyn, bad)
    assert out.usable.tolist() == [True, False, True]
    assert int(out.status.reason[1]) == int(Reason.NONFINITE_INPUT)
    assert bool(out.status.converged[[0, 2]].all())
    ref = ioc_loss(model, dyn, xd[[0, 2]])
    assert torch.allclose(out.loss, ref.loss)
    params = list(model.parameters())
    for a, b in zip(torch.autograd.grad(out.loss, params), torch.autograd.grad(ref.loss, params)):
        assert torch.isfinite(a).all() and torch.allclose(a, b)
    # the lifted solver and a NaN later in a demo (solved fine, left out of the loss)
    lifted = ioc_loss(model, dyn, bad, solver="lifted")
    assert lifted.usable.tolist() == [True, False, True] and torch.allclose(lifted.loss, ref.loss)
    assert torch.isfinite(torch.autograd.grad(lifted.loss, params)[0]).all()
    late = xd.clone()
    late[2, 5, 1] = math.inf
    o = ioc_loss(model, dyn, late)
    assert o.usable.tolist() == [True, True, False] and bool(o.status.converged.all())
    assert torch.isnan(o.per_demo[2]) and torch.allclose(o.loss, ioc_loss(model, dyn, xd[:2]).loss)
    assert torch.isfinite(torch.autograd.grad(o.loss, params)[0]).all()
    # fit_cost counts it at every evaluation
    res = fit_cost(bad, dyn, model, steps=3, optimizer="adam", solver="lifted")
    assert all(v == 1 for v in res.history["unusable"]) and not bool(res.status.converged[1])
    with pytest.raises(ValueError, match="no demo gave a finite solution"):
        fit_cost(torch.full_like(xd, math.nan), dyn, model, steps=2)


def test_float32_follows_inputs():
    dyn64, m64, xd64 = _small_problem()
    dyn32, m32, xd32 = _small_problem(torch.float32)
    o32, o64 = ioc_loss(m32, dyn32, xd32), ioc_loss(m64, dyn64, xd64)
    assert o32.loss.dtype == torch.float32 and o32.x.dtype == torch.float32
    assert abs(float(o32.loss.detach()) - float(o64.loss.detach())) < 1e-4 * float(o64.loss.detach())
    g32 = torch.autograd.grad(o32.loss, m32.Q.lower)[0]
    g64 = torch.autograd.grad(o64.loss, m64.Q.lower)[0]
    assert g32.dtype == torch.float32 and torch.allclose(g32.double(), g64, rtol=1e-2, atol=1e-5)


def test_bad_inputs():
    d64 = torch.ones(2, dtype=D64)
    with pytest.raises(ValueError, match="'kind'"):
        SPDWeight(d64, "lower")
    with pytest.raises(ValueError, match="positive"):
        SPDWeight(torch.tensor([1.0, -1.0], dtype=D64))
    with pytest.raises(ValueError, match="SPD matrix"):
        SPDWeight(d64, "full")
    with pytest.raises(ValueError, match="positive definite"):
        SPDWeight(torch.tensor([[1.0, 2.0], [2.0, 1.0]], dtype=D64), "full")
    with pytest.raises(TypeError, match="'init'"):
        SPDWeight([1.0, 2.0])
    with pytest.raises(ValueError, match="'times'"):
        ViaPoints(torch.zeros(2, 4, dtype=D64), torch.zeros(3, dtype=D64), torch.eye(4, dtype=D64))
    with pytest.raises(ValueError, match="semi-definite"):
        ViaPoints(torch.zeros(1, 4, dtype=D64), torch.zeros(1, dtype=D64), -torch.eye(4, dtype=D64))
    with pytest.raises(ValueError, match="'kernel'"):
        time_weights(torch.zeros(1, dtype=D64), 5, "box")
    vp = ViaPoints(torch.zeros(1, 4, dtype=D64), torch.tensor([40.0], dtype=D64), torch.eye(4, dtype=D64))
    with pytest.raises(ValueError, match=r"times must lie in \[0, 30\]"):
        _model(torch.ones(4, dtype=D64), d64, via=vp)
    with pytest.raises(ValueError, match="per-step 'Q'"):
        LQTCostModel(torch.eye(4, dtype=D64).expand(5, 4, 4), torch.eye(2, dtype=D64), T)
    with pytest.raises(ValueError, match="'horizon'"):
        LQTCostModel(torch.eye(4, dtype=D64), torch.eye(2, dtype=D64), 0)
    with pytest.raises(ValueError, match="'target'"):
        LQTCostModel(torch.eye(4, dtype=D64), torch.eye(2, dtype=D64), T, target=torch.zeros(3, dtype=D64))
    dyn, model, xd = _small_problem()
    with pytest.raises(ValueError, match="horizon 8"):
        ioc_loss(model, dyn, xd[:, :5])
    with pytest.raises(ValueError, match="'solver'"):
        ioc_loss(model, dyn, xd, solver="newton")
    with pytest.raises(TypeError, match="LinearDynamics"):
        from controllers.systems.pendulum import Pendulum
        ioc_loss(model, Pendulum(), xd)
    with pytest.raises(ValueError, match="demo controls"):
        ioc_loss(model, dyn, xd, control_weight=1.0)
    with pytest.raises(TypeError, match="float32"):
        ioc_loss(model, dyn, xd.float())
    with pytest.raises(ValueError, match="'optimizer'"):
        fit_cost(xd, dyn, model, optimizer="sgd")
    with pytest.raises(TypeError, match="LQTCostModel"):
        fit_cost(xd, dyn, model())
    fixed = LQTCostModel(torch.eye(4, dtype=D64), torch.eye(2, dtype=D64), 8)
    with pytest.raises(ValueError, match="no learnable parameter"):
        fit_cost(xd, dyn, fixed)
    with pytest.raises(ValueError, match="batch dims"):
        normalize_scale(torch.eye(2, dtype=D64).expand(3, 2, 2), torch.ones(2, dtype=D64))


# ------------------------------------------------------------------------------------ minimal intervention
def test_minimal_intervention_gains_low_where_demos_vary():
    g = torch.Generator().manual_seed(0)
    N, Tm = 8, 50
    s = torch.linspace(0, 1, Tm, dtype=D64)
    base = torch.stack([torch.sin(math.pi * s), s], -1)
    # variations vanish at s = 0, 1/2, 1 (the demos agree there) and peak at s = 1/4, 3/4
    x = base + torch.randn(N, 1, 2, generator=g, dtype=D64) * 0.2 * torch.sin(2 * math.pi * s)[:, None] ** 2
    mi = minimal_intervention(x, dt=0.02, n_basis=12)
    assert mi.K.shape == (Tm - 1, 2, 4) and mi.gain_norm.shape == (Tm - 1,) and mi.variance.shape == (Tm,)
    # the gains are those of ProMP.track on the same fit (reused, not re-implemented)
    tr = fit_promp(x, dt=0.02, n_basis=12).track()
    assert torch.allclose(mi.K, tr.K)
    # reference variance: the demos' own sample variance (the ProMP reproduces the demos closely)
    emp = x.var(0).sum(-1)
    assert torch.allclose(mi.variance, emp, atol=2e-3)
    agree, vary = 24, 12  # s ≈ 1/2 and s ≈ 1/4
    assert float(emp[agree]) < 1e-3 * float(emp[vary])
    assert float(mi.gain_norm[agree]) > 5 * float(mi.gain_norm[vary])
    assert float(mi.gain_norm[agree]) > 5 * float(mi.gain_norm[36])  # s ≈ 3/4
    # batched sets of demos (*B, N, T, D) == one by one
    xb = torch.stack([x, x.flip(-1)])
    mb = minimal_intervention(xb, dt=0.02, n_basis=12)
    assert torch.allclose(mb.gain_norm[0], mi.gain_norm, rtol=1e-8)
    assert torch.allclose(mb.gain_norm[1], minimal_intervention(x.flip(-1), dt=0.02, n_basis=12).gain_norm,
                          rtol=1e-8)


# ------------------------------------------------------------------------------------ example
def test_example_ioc_weights(tmp_path):
    from examples.learning.ioc_weights import run

    out = run(tmp_path)
    assert all(out["checks"].values()), out
    assert (tmp_path / "ioc_weights.png").exists()
    v = out["values"]
    assert v["weight_rel_error"] < 1e-3 and v["via_time_error_steps"] < 0.05 and v["reproduction_rmse"] < 1e-4
