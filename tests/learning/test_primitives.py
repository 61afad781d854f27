"""Movement primitives as LQT (learning/primitives.py; issue 26 §3, seed 004 §7.3, §7.7).

References are independent: transfer matrices by simulating the integrator chain in numpy, weights by
``numpy.linalg.lstsq``, Gaussian conditioning in state space with numpy, Monte Carlo for the covariance.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from controllers import basis
from controllers.lqt_cookbook import dmp_lqt, double_integrator
from learning.demos import handwriting
from learning.primitives import (
    DMP,
    ProMP,
    fit_dmp,
    fit_promp,
    integrator_chain,
    perturbation_recovery,
    reproduction_error,
    via_point_error,
)
from tests.learning.demo_data import smooth_demos

D64 = torch.float64


def _np_transfer(order, D, dt, T):
    """``S_x ((T n) × n)`` and ``S_u ((T n) × (T-1) D)`` by simulating unit inputs (numpy)."""
    n = order * D
    A = np.eye(n) + dt * np.eye(n, k=D)
    B = np.zeros((n, D))
    B[n - D:] = dt * np.eye(D)
    Sx = np.zeros((T * n, n))
    Su = np.zeros((T * n, (T - 1) * D))
    for j in range(n):  # free response of e_j
        x = np.eye(n)[j]
        for t in range(T):
            Sx[t * n:(t + 1) * n, j] = x
            x = A @ x
    for s in range(T - 1):
        for j in range(D):
            x = B[:, j].copy()
            for t in range(s + 1, T):
                Su[t * n:(t + 1) * n, s * D + j] = x
                x = A @ x
    return Sx, Su


def _np_model(x, dt, K, order, reg):
    """Dense numpy reference of fit_promp for one set of demos ``x (N, T, D)``: (Z, mean, cov, S)."""
    N, T, D = x.shape
    n = order * D
    Sx, Su = _np_transfer(order, D, dt, T)
    phi = basis.rbf(T - 1, K, normalized=True).numpy()
    Psi = np.kron(phi, np.eye(D))
    S = np.hstack([Sx, Su @ Psi])
    pos = np.concatenate([np.arange(t * n, t * n + D) for t in range(T)])
    M = S[pos, n:]
    lam = reg * np.trace(M.T @ M) / M.shape[1]
    Z = []
    for i in range(N):
        p = x[i]
        x1, d = [], p
        for _ in range(order):
            x1.append(d[0])
            d = np.diff(d, axis=0) / dt
        x1 = np.concatenate(x1)
        r = p.reshape(-1) - S[pos, :n] @ x1
        w = np.linalg.lstsq(np.vstack([M, math.sqrt(lam) * np.eye(M.shape[1])]),
                            np.concatenate([r, np.zeros(M.shape[1])]), rcond=None)[0]
        Z.append(np.concatenate([x1, w]))
    Z = np.array(Z)
    C = np.cov(Z.T)
    C = C + reg * np.trace(C) / C.shape[0] * np.eye(C.shape[0])
    return Z, Z.mean(0), C, S


# ------------------------------------------------------------------------------------------- ProMP fit


@pytest.mark.parametrize("order", [1, 2, 3])
def test_fit_matches_dense_lstsq_and_covariance(order):
    x = smooth_demos(N=5, T=25)
    dt, K, reg = 0.04, 6, 1e-6
    pm = fit_promp(x, dt=dt, n_basis=K, order=order, reg=reg)
    Z, mu, C, S = _np_model(x.numpy(), dt, K, order, reg)
    np.testing.assert_allclose(pm.S.numpy(), S, atol=1e-12)
    np.testing.assert_allclose(pm.params.numpy(), Z, rtol=1e-7, atol=1e-8)
    np.testing.assert_allclose(pm.mean.numpy(), mu, rtol=1e-7, atol=1e-8)
    np.testing.assert_allclose(pm.cov.numpy(), C, rtol=1e-6, atol=1e-8)
    # the first `order` samples are matched exactly (inputs reach positions only after `order` steps)
    rep = pm.reproductions()[..., :2]
    torch.testing.assert_close(rep[:, :order], x[:, :order], atol=1e-10, rtol=0)
    assert reproduction_error(x, pm.reproductions()).max() < 5e-3


def test_integrator_chain_order2_is_double_integrator():
    a, b = integrator_chain(2, 2, 0.1), double_integrator(2, 0.1)
    torch.testing.assert_close(a.A, b.A)
    torch.testing.assert_close(a.B, b.B)


def test_state_and_control_covariance_dense_and_monte_carlo():
    x = smooth_demos(N=6, T=20)
    pm = fit_promp(x, dt=0.05, n_basis=5)
    Z, mu, C, S = _np_model(x.numpy(), 0.05, 5, 2, 1e-8)
    np.testing.assert_allclose(pm.state_cov().numpy(), S @ C @ S.T, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(pm.state_mean().reshape(-1).numpy(), S @ mu, rtol=1e-9, atol=1e-10)
    n = 4
    blocks = np.stack([(S @ C @ S.T)[t * n:(t + 1) * n, t * n:(t + 1) * n] for t in range(20)])
    np.testing.assert_allclose(pm.state_marginal_cov().numpy(), blocks, rtol=1e-6, atol=1e-9)
    Psi = pm.Psi.numpy()
    np.testing.assert_allclose(pm.control_cov().numpy(), Psi @ C[n:, n:] @ Psi.T, rtol=1e-6, atol=1e-9)
    # Monte Carlo: 40000 draws; the relative Frobenius error of a sample covariance of a rank-r Gaussian
    # is about sqrt(2 r / n) ≈ 0.02 here (r ≈ 5 demos' spread); tolerance 0.06 (≈ 3 standard errors)
    g = torch.Generator().manual_seed(3)
    xs = pm.sample(40000, g).reshape(40000, -1)
    emp = torch.cov(xs.T)
    ref = pm.state_cov()
    assert ((emp - ref).norm() / ref.norm()) < 0.06
    assert ((xs.mean(0) - pm.state_mean().reshape(-1)).abs().max()) < 0.05 * ref.diagonal().sqrt().max()


# ---------------------------------------------------------------------------------------- conditioning


def _np_condition(mu_x, Sig_x, rows, y, R):
    Sxy = Sig_x[:, rows]
    Syy = Sig_x[np.ix_(rows, rows)] + R
    G = np.linalg.solve(Syy, Sxy.T).T
    return mu_x + G @ (y - mu_x[rows]), Sig_x - G @ Sxy.T


@pytest.mark.parametrize("noise", [1e-3, 0.0])
def test_condition_matches_dense_gaussian_conditioning(noise):
    x = smooth_demos(N=7, T=20)
    pm = fit_promp(x, dt=0.05, n_basis=6)
    t_idx = [5, 14]
    y = torch.tensor([[0.7, 0.1], [0.9, 0.5]], dtype=D64)
    c = pm.condition(t_idx, y, noise=noise)
    n = 4
    rows = [t * n + j for t in t_idx for j in range(2)]
    mu, Sig = _np_condition(pm.state_mean().reshape(-1).numpy(), pm.state_cov().numpy(), rows,
                            y.reshape(-1).numpy(), noise * np.eye(4))
    scale = np.abs(pm.state_cov().numpy()).max()
    np.testing.assert_allclose(c.state_mean().reshape(-1).numpy(), mu, atol=1e-8)
    np.testing.assert_allclose(c.state_cov().numpy(), Sig, atol=1e-7 * scale)
    assert c.params is None


def test_condition_passes_through_via_points_and_custom_observation():
    x = smooth_demos(N=6, T=30)
    pm = fit_promp(x, dt=0.04, n_basis=8)
    y = pm.state_mean()[[10, 22], :2] + torch.tensor([[0.05, -0.04], [-0.03, 0.06]], dtype=D64)
    c = pm.condition([10, 22], y, noise=1e-14)
    assert via_point_error(c.state_mean(), [10, 22], y).max() < 1e-8
    g = torch.Generator().manual_seed(0)
    assert via_point_error(c.sample(50, g), [10, 22], y).max() < 1e-5
    # observe the velocity at the end (C = [0, I]): a stop at T-1
    C = torch.cat([torch.zeros(2, 2, dtype=D64), torch.eye(2, dtype=D64)], 1)
    c2 = pm.condition([29], torch.zeros(1, 2, dtype=D64), noise=0.0, C=C)
    assert c2.state_mean()[-1, 2:].abs().max() < 1e-8
    # full-covariance noise tensor == float noise
    c3 = pm.condition([10, 22], y, noise=1e-3 * torch.eye(2, dtype=D64).expand(2, 2, 2))
    c4 = pm.condition([10, 22], y, noise=1e-3)
    torch.testing.assert_close(c3.mean, c4.mean)
    torch.testing.assert_close(c3.cov, c4.cov)
    # mean_trajectory given a start: passes through it; default: the unconditioned mean
    x1 = torch.tensor([0.05, 0.02], dtype=D64)
    torch.testing.assert_close(pm.mean_trajectory(x1)[0, :2], x1, atol=1e-9, rtol=0)
    torch.testing.assert_close(pm.mean_trajectory(), pm.state_mean())
    assert pm.sample(3, g, x1=x1).shape == (3, 30, 4)


def test_batched_equals_per_sample_loop():
    x = smooth_demos(N=5, T=20, b=(3,))
    pm = fit_promp(x, dt=0.05, n_basis=5)
    assert pm.batch_shape == (3,)
    t_idx = torch.tensor([[4, 12], [6, 15], [3, 18]])
    y = 0.1 * torch.arange(2 * 3 * 2 * 2, dtype=D64).reshape(2, 3, 2, 2)  # two via-point sets per letter
    c = pm.condition(t_idx, y, noise=1e-4)
    assert c.batch_shape == (2, 3)
    for i in range(3):
        pi = fit_promp(x[i], dt=0.05, n_basis=5)
        torch.testing.assert_close(pm.mean[i], pi.mean, atol=1e-10, rtol=1e-9)
        torch.testing.assert_close(pm.cov[i], pi.cov, atol=1e-10, rtol=1e-9)
        for j in range(2):
            cij = pi.condition(t_idx[i].tolist(), y[j, i], noise=1e-4)
            torch.testing.assert_close(c.mean[j, i], cij.mean, atol=1e-9, rtol=1e-9)
            torch.testing.assert_close(c.cov[j, i], cij.cov, atol=1e-9, rtol=1e-9)
    tr = pm.track()
    t1 = fit_promp(x[1], dt=0.05, n_basis=5).track()
    torch.testing.assert_close(tr.x[1], t1.x, atol=1e-8, rtol=1e-8)


def test_nan_element_does_not_poison_the_batch():
    x = smooth_demos(N=5, T=20, b=(2,)).clone()
    x[0, 2, 7, 1] = float("nan")
    pm = fit_promp(x, dt=0.05, n_basis=5)
    ref = fit_promp(x[1], dt=0.05, n_basis=5)
    assert not torch.isfinite(pm.mean[0]).all()
    torch.testing.assert_close(pm.mean[1], ref.mean)
    c = pm.condition([10], torch.zeros(1, 2, dtype=D64), noise=1e-3)
    torch.testing.assert_close(c.mean[1], ref.condition([10], torch.zeros(1, 2, dtype=D64), noise=1e-3).mean)


def test_float32_and_dtype_follow():
    x = smooth_demos(N=6, T=30)
    p64 = fit_promp(x, dt=0.04, n_basis=8)
    p32 = fit_promp(x.float(), dt=0.04, n_basis=8)
    assert p32.mean.dtype == p32.cov.dtype == p32.S.dtype == torch.float32
    assert (p32.state_mean().double() - p64.state_mean()).abs()[..., :2].max() < 5e-3
    y = p32.state_mean()[[15], :2] + 0.02
    c = p32.condition([15], y, noise=1e-8)
    assert c.mean.dtype == torch.float32
    assert via_point_error(c.state_mean(), [15], y).max() < 1e-3
    s = c.sample(4, torch.Generator().manual_seed(0))
    assert s.dtype == torch.float32 and torch.isfinite(s).all()
    with pytest.raises(TypeError, match="targets"):
        p32.condition([15], y.double())


def test_gradcheck_conditioning():
    x0 = smooth_demos(N=4, T=10)
    y0 = torch.tensor([[0.6, 0.3]], dtype=D64)

    def f(x, y):
        c = fit_promp(x, dt=0.1, n_basis=3).condition([6], y, noise=1e-2)
        return c.state_mean()[..., :2], c.state_cov()[::7, ::7]

    torch.autograd.gradcheck(f, (x0.clone().requires_grad_(), y0.clone().requires_grad_()))


def test_track_is_minimal_intervention():
    g = torch.Generator().manual_seed(1)
    d = handwriting("S", 8, 60, generator=g)["S"]
    pm = fit_promp(d, n_basis=12)
    tr = pm.track()
    assert bool(tr.status.converged.all())
    Sig = pm.state_marginal_cov()
    eye = torch.eye(4, dtype=D64)
    torch.testing.assert_close(tr.precision @ (Sig + 1e-6 * eye), eye.expand(60, 4, 4), atol=1e-6, rtol=0)
    # from the mean start the LQT follows the mean closely
    assert (tr.x[:, :2] - pm.state_mean()[:, :2]).norm(dim=-1).max() < 1e-2
    push = torch.tensor([0.08, -0.08], dtype=D64)
    tp = pm.track(perturbation=push, at=30)
    rec = perturbation_recovery(tr.x, tp.x, 30, d=2)
    assert rec.peak > 0.1 and rec.final < 0.1 * rec.peak


# ------------------------------------------------------------------------------------------------ DMP


def test_dmp_batched_reproduce_goal_and_perturbation():
    g = torch.Generator().manual_seed(2)
    d = handwriting("S", 3, 80, generator=g)["S"]
    dm = fit_dmp(d, n_basis=25)
    assert isinstance(dm, DMP) and dm.T == 80
    one = dmp_lqt(d.x[1], d.dt, n_basis=25, goal_weight=1e6)
    torch.testing.assert_close(dm.plan()[1], one.plan.x, atol=1e-9, rtol=0)
    r = dm.reproduce()
    err = reproduction_error(d, r.x)
    assert err.shape == (3,) and err.max() < 1e-2
    push = torch.tensor([0.1, -0.1], dtype=D64)
    rp = dm.reproduce(perturbation=push)  # at mid-course
    rec = perturbation_recovery(r.x, rp.x, 39, d=2)
    torch.testing.assert_close(rp.x[:, 39, :2], r.x[:, 39, :2] + push)
    assert (rec.peak >= 0.14).all() and (rec.final < 1e-2).all()
    assert ((rp.x[:, -1, :2] - d.x[:, -1]).norm(dim=-1) < 1e-2).all()
    goal = d.x[:, -1] + torch.tensor([0.2, 0.1], dtype=D64)
    x0 = d.x[:, 0] + torch.tensor([-0.1, 0.05], dtype=D64)
    rg = dm.reproduce(x0=x0, goal=goal)
    assert ((rg.x[:, -1, :2] - goal).norm(dim=-1) < 1e-2).all()
    torch.testing.assert_close(rg.x[:, 0, :2], x0)
    r32 = fit_dmp(d.to(torch.float32), n_basis=25).reproduce()
    assert r32.x.dtype == torch.float32 and reproduction_error(d, r32.x).max() < 2e-2


# -------------------------------------------------------------------------------------------- metrics


def test_metrics_against_numpy():
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(3, 10, 2)), rng.normal(size=(3, 10, 4))
    e = reproduction_error(a, b)
    np.testing.assert_allclose(e.numpy(), np.sqrt(((b[..., :2] - a) ** 2).sum(-1).mean(-1)))
    tg = rng.normal(size=(3, 2, 2))
    v = via_point_error(b, [2, 7], tg)
    np.testing.assert_allclose(v.numpy(), np.linalg.norm(b[:, [2, 7], :2] - tg, axis=-1))
    rec = perturbation_recovery(a, b, 4, d=2)
    dist = np.linalg.norm(b[..., :2] - a, axis=-1)
    np.testing.assert_allclose(rec.final.numpy(), dist[:, -1])
    np.testing.assert_allclose(rec.peak.numpy(), dist[:, 4:].max(-1))
    np.testing.assert_allclose(rec.ratio.numpy(), dist[:, -1] / dist[:, 4:].max(-1))


# ----------------------------------------------------------------------------------------- bad inputs


def test_bad_inputs_name_the_argument():
    x = smooth_demos(N=4, T=20)
    pm = fit_promp(x, dt=0.05, n_basis=4)
    with pytest.raises(ValueError, match="N >= 2"):
        fit_promp(x[:1], dt=0.05)
    with pytest.raises(ValueError, match="'dt'"):
        fit_promp(x)
    with pytest.raises(ValueError, match="basis_fn"):
        fit_promp(x, dt=0.05, basis_fn="wavelet")
    with pytest.raises(ValueError, match="n_basis"):
        fit_promp(x, dt=0.05, n_basis=0)
    with pytest.raises(TypeError, match="demos"):
        fit_promp(x.long(), dt=0.05)
    with pytest.raises(ValueError, match="targets"):
        pm.condition([3], torch.zeros(2, 2, dtype=D64))
    with pytest.raises(ValueError, match="t_idx"):
        pm.condition([20], torch.zeros(1, 2, dtype=D64))
    with pytest.raises(TypeError, match="t_idx"):
        pm.condition([1.5], torch.zeros(1, 2, dtype=D64))
    with pytest.raises(ValueError, match="noise"):
        pm.condition([3], torch.zeros(1, 2, dtype=D64), noise=-1.0)
    with pytest.raises(ValueError, match="'C'"):
        pm.condition([3], torch.zeros(1, 2, dtype=D64), C=torch.eye(2, dtype=D64))
    with pytest.raises(ValueError, match="x1"):
        pm.mean_trajectory(torch.zeros(3, dtype=D64))
    with pytest.raises(TypeError, match="generator"):
        pm.sample(3, None)
    with pytest.raises(ValueError, match="'at'"):
        pm.track(at=5)
    dm = fit_dmp(x[:2], dt=0.05, n_basis=5)
    with pytest.raises(ValueError, match="'at'"):
        dm.reproduce(at=3)
    with pytest.raises(ValueError, match="goal"):
        dm.reproduce(goal=torch.zeros(3, dtype=D64))
    with pytest.raises(ValueError, match="generated"):
        reproduction_error(x, x[:, :10])
    with pytest.raises(ValueError, match="'at'"):
        perturbation_recovery(x, x, 25)
    assert isinstance(pm, ProMP)


# -------------------------------------------------------------------------------------------- example


def test_example_promp_lqt(tmp_path):
    from examples.learning.promp_lqt import run

    res = run(tmp_path)
    assert all(res["checks"].values()), res
    assert (tmp_path / "promp_lqt.png").exists()
    v = res["values"]
    assert v["via_point_error_mean"] < 1e-6
    assert v["mean_vs_demo_mean_max"] < 1e-2
    assert v["via_point_offset"] > 0.05
