"""Ergodic control (seed 004 §10): SMC basis/coefficients/metric/controller and HEDAC heat diffusion.

References are independent: scipy quadrature and scipy's multivariate normal for the Fourier coefficients,
autograd and finite differences for the basis gradient, a dense Kronecker-built Neumann Laplacian for the
heat step, per-sample loops for batching.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import integrate, stats

from controllers import ergodic as E

F64 = torch.float64


def _gmm2d(dtype=F64):
    al = torch.tensor([0.35, 0.65], dtype=dtype)
    mu = torch.tensor([[0.6, 1.3], [1.4, 0.7]], dtype=dtype)
    S = torch.tensor([[[0.04, 0.01], [0.01, 0.03]], [[0.02, -0.008], [-0.008, 0.05]]], dtype=dtype)
    return al, mu, S


# ---------------------------------------------------------------------------------------------- basis

def test_indices_order_matches_seed_example():
    k = E.fourier_indices(2, 2)
    assert k.tolist() == [[0, 0], [0, 1], [1, 0], [1, 1]]           # §10.1.2 example
    assert E.fourier_indices(3, 4).shape == (64, 3)


def test_basis_matches_seed_formulas_1d_and_2d():
    ell, K = 1.7, 5
    L = 2 * ell
    x = torch.linspace(0, ell, 11, dtype=F64)[:, None]
    k = torch.arange(K, dtype=F64)
    ref1 = torch.cos(2 * math.pi * k * x / L) / L                      # Eq. 123
    torch.testing.assert_close(E.fourier_basis(x, n_basis=K, length=ell), ref1)
    gref1 = -2 * math.pi * k / L ** 2 * torch.sin(2 * math.pi * k * x / L)   # Eq. 124
    torch.testing.assert_close(E.fourier_basis_grad(x, n_basis=K, length=ell)[..., 0], gref1)
    # Eq. 155: outer product of the two 1-D cosine vectors, row-major
    x2 = torch.tensor([[0.3, 1.1], [1.6, 0.05]], dtype=F64)
    V = 2 * math.pi * k / L
    c1, c2 = torch.cos(V * x2[:, :1]), torch.cos(V * x2[:, 1:])
    ref2 = (c1[:, :, None] * c2[:, None, :]).reshape(2, K * K) / L ** 2
    torch.testing.assert_close(E.fourier_basis(x2, n_basis=K, length=ell), ref2)


@pytest.mark.parametrize("D", [1, 2, 3])
def test_basis_grad_vs_autograd_and_finite_differences(D):
    g = torch.Generator().manual_seed(D)
    x = torch.rand(4, D, dtype=F64, generator=g) * 1.3
    K, ell = 4, 1.3
    G = E.fourier_basis_grad(x, n_basis=K, length=ell)                # (4, K^D, D)
    for i in range(x.shape[0]):
        J = torch.autograd.functional.jacobian(lambda y: E.fourier_basis(y, n_basis=K, length=ell), x[i])
        torch.testing.assert_close(G[i], J)
        h = 1e-6
        fd = torch.stack([(E.fourier_basis(x[i] + h * e, n_basis=K, length=ell)
                           - E.fourier_basis(x[i] - h * e, n_basis=K, length=ell)) / (2 * h)
                          for e in torch.eye(D, dtype=F64)], -1)
        torch.testing.assert_close(G[i], fd, atol=1e-8, rtol=1e-6)
    xg = x.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda y: E.fourier_basis_grad(y, n_basis=3, length=ell), (xg,))


def test_sobolev_weights_closed_form():
    torch.testing.assert_close(E.sobolev_weights(1, 4), 1 / (1 + torch.arange(4, dtype=F64) ** 2))   # Eq. 130
    k = E.fourier_indices(2, 3).to(F64)
    torch.testing.assert_close(E.sobolev_weights(2, 3), (1 + (k ** 2).sum(-1)) ** -1.5)            # Eq. 149


# --------------------------------------------------------------------------------------- coefficients

def test_gmm_coefficients_1d_vs_scipy_quad():
    ell, K = 2.0, 8
    al = torch.tensor([0.3, 0.7], dtype=F64)
    mu = torch.tensor([[0.8], [1.2]], dtype=F64)                       # ≥ 6.5 σ inside [0, ℓ]
    S = torch.tensor([[[0.01]], [[0.0144]]], dtype=F64)
    w = E.gmm_fourier_coefficients(al, mu, S, n_basis=K, length=ell)
    pdf = lambda x: 0.3 * stats.norm.pdf(x, 0.8, 0.1) + 0.7 * stats.norm.pdf(x, 1.2, 0.12)   # noqa: E731
    ref = [integrate.quad(lambda x, k=k: pdf(x) * np.cos(math.pi * k * x / ell) / (2 * ell), 0, ell,
                          epsabs=1e-14, limit=200)[0] for k in range(K)]
    torch.testing.assert_close(w, torch.tensor(ref, dtype=F64), atol=1e-10, rtol=0)


def test_gmm_coefficients_near_wall_equal_reflected_density():
    # exact claim of the docstring: the formula integrates the mixture folded into [0, ℓ] by reflection
    ell, K = 1.0, 6
    m, s = 0.05, 0.12
    w = E.gmm_fourier_coefficients(torch.ones(1, dtype=F64), torch.tensor([[m]], dtype=F64),
                                   torch.tensor([[[s * s]]], dtype=F64), n_basis=K, length=ell)

    def folded(x):
        return sum(stats.norm.pdf(2 * j * ell + x, m, s) + stats.norm.pdf(2 * j * ell - x, m, s)
                   for j in range(-3, 4))
    ref = [integrate.quad(lambda x, k=k: folded(x) * np.cos(math.pi * k * x / ell) / (2 * ell), 0, ell,
                          epsabs=1e-14)[0] for k in range(K)]
    torch.testing.assert_close(w, torch.tensor(ref, dtype=F64), atol=1e-11, rtol=0)


def test_gmm_coefficients_2d_vs_dense_quadrature_and_density_vs_scipy():
    ell, K, n = 2.0, 6, 400
    al, mu, S = _gmm2d()
    S = S / 4                                                          # mass outside [0, ℓ]² < 1e-10
    w = E.gmm_fourier_coefficients(al, mu, S, n_basis=K, length=ell)
    c = (np.arange(n) + 0.5) * ell / n
    X = np.stack(np.meshgrid(c, c, indexing="ij"), -1).reshape(-1, 2)
    pdf = sum(float(al[j]) * stats.multivariate_normal(mu[j].numpy(), S[j].numpy()).pdf(X) for j in range(2))
    torch.testing.assert_close(E.gmm_density(torch.from_numpy(X), al, mu, S), torch.from_numpy(pdf))
    phi = E.fourier_basis(torch.from_numpy(X), n_basis=K, length=ell).numpy()
    ref = (pdf[:, None] * phi).sum(0) * (ell / n) ** 2                                # Eq. 146
    torch.testing.assert_close(w, torch.from_numpy(ref), atol=1e-9, rtol=0)


def test_gmm_coefficients_batched_equals_loop_and_gradcheck():
    g = torch.Generator().manual_seed(1)
    al = torch.softmax(torch.randn(2, 3, 2, dtype=F64, generator=g), -1)
    mu = 0.2 + 0.6 * torch.rand(2, 3, 2, 2, dtype=F64, generator=g)
    A = 0.1 * torch.randn(2, 3, 2, 2, 2, dtype=F64, generator=g)
    S = A @ A.mT + 0.01 * torch.eye(2, dtype=F64)
    w = E.gmm_fourier_coefficients(al, mu, S, n_basis=4, length=1.0)
    assert w.shape == (2, 3, 16)
    for i in range(2):
        for j in range(3):
            torch.testing.assert_close(w[i, j], E.gmm_fourier_coefficients(al[i, j], mu[i, j], S[i, j],
                                                                            n_basis=4, length=1.0))
    args = (al[0, 0].clone().requires_grad_(), mu[0, 0].clone().requires_grad_(),
            S[0, 0].clone().requires_grad_())
    fn = lambda a, m, s: E.gmm_fourier_coefficients(a, m, s, n_basis=3, length=1.0)   # noqa: E731
    assert torch.autograd.gradcheck(fn, args)


# ------------------------------------------------------------------------------------------- metric

def test_metric_and_running_coefficients_definitions():
    g = torch.Generator().manual_seed(2)
    traj = torch.rand(3, 7, 2, 2, dtype=F64, generator=g)              # (B, T, N, D)
    K = 3
    run = E.running_coefficients(traj, n_basis=K, length=1.0)
    for t in range(7):
        ref = E.fourier_basis(traj[:, : t + 1].reshape(3, -1, 2), n_basis=K, length=1.0).mean(-2)  # Eq. 145
        torch.testing.assert_close(run[:, t], ref)
    w_hat = torch.rand(9, dtype=F64, generator=g)
    lam = E.sobolev_weights(2, K)
    e = run[:, -1] - w_hat
    torch.testing.assert_close(E.ergodic_metric(run[:, -1], w_hat, lam),
                               0.5 * torch.einsum("bk,kl,bl->b", e, torch.diag(lam), e))     # Eq. 148


def test_metric_of_samples_from_distribution_is_small():
    ell, K, n = 2.0, 8, 20000
    al, mu, S = _gmm2d()
    g = torch.Generator().manual_seed(3)
    comp = torch.multinomial(al, n, replacement=True, generator=g)
    z = torch.randn(n, 2, dtype=F64, generator=g)
    samples = mu[comp] + (torch.linalg.cholesky(S)[comp] @ z[..., None])[..., 0]
    lam = E.sobolev_weights(2, K)
    w_hat = E.gmm_fourier_coefficients(al, mu, S, n_basis=K, length=ell)
    w = E.fourier_basis(samples, n_basis=K, length=ell).mean(0)
    eps = E.ergodic_metric(w, w_hat, lam)
    # Monte Carlo: E[ε] = ½ Σ Λ_k Var φ_k / n <= ½ Σ Λ_k / (L^{2D} n)
    mc_bound = 0.5 * lam.sum() / ((2 * ell) ** 4 * n)
    assert eps < 5 * mc_bound
    point = E.fourier_basis(mu[:1], n_basis=K, length=ell)[0]
    assert eps < 1e-3 * E.ergodic_metric(point, w_hat, lam)


# --------------------------------------------------------------------------------------- controller

def test_controller_speed_limit_direction_and_zero():
    g = torch.Generator().manual_seed(4)
    K, ell = 5, 1.0
    x = torch.rand(6, 3, 2, dtype=F64, generator=g)
    w, w_hat = torch.rand(6, 25, dtype=F64, generator=g), torch.rand(6, 25, dtype=F64, generator=g)
    lam = E.sobolev_weights(2, K)
    u = E.smc_control(x, w, w_hat, lam, n_basis=K, length=ell, u_max=0.7)
    torch.testing.assert_close(u.norm(dim=-1), torch.full((6, 3), 0.7, dtype=F64))
    ut = -torch.einsum("bnkd,bk->bnd", E.fourier_basis_grad(x, n_basis=K, length=ell), lam * (w - w_hat))
    torch.testing.assert_close(u, 0.7 * ut / ut.norm(dim=-1, keepdim=True))          # Eq. 159
    assert (E.smc_control(x, w, w, lam, n_basis=K, length=ell, u_max=0.7) == 0).all()
    # 1-D: u = sign(ũ) u_max (Eq. 138 with the normalization of §10.1.1)
    x1, w1, wh1 = torch.rand(5, 1, 1, dtype=F64, generator=g), torch.rand(5, K, dtype=F64, generator=g), \
        torch.rand(5, K, dtype=F64, generator=g)
    lam1 = E.sobolev_weights(1, K)
    u1 = E.smc_control(x1, w1, wh1, lam1, n_basis=K, length=ell, u_max=2.0)
    ut1 = -(E.fourier_basis_grad(x1, n_basis=K, length=ell)[..., 0] * (lam1 * (w1 - wh1))[:, None]).sum(-1)
    torch.testing.assert_close(u1[..., 0], 2.0 * torch.sign(ut1))


def test_rollout_speed_limit_shared_coefficients_and_decrease():
    al, mu, S = _gmm2d()
    K, ell = 6, 2.0
    w_hat = E.gmm_fourier_coefficients(al, mu, S, n_basis=K, length=ell)
    x0 = torch.tensor([[0.2, 0.2], [1.8, 1.8], [1.0, 0.1]], dtype=F64)
    r = E.smc_rollout(x0, w_hat, n_steps=150, dt=0.02, u_max=1.5, n_basis=K, length=ell)
    assert r.x.shape == (150, 3, 2) and r.u.shape == (150, 3, 2) and r.metric.shape == (150,)
    steps = torch.cat([r.x, r.x_final[None]])
    assert ((steps[1:] - steps[:-1]).norm(dim=-1) <= 1.5 * 0.02 * (1 + 1e-12)).all()
    # the agents share one set of coefficients: w is the average over all agents and steps (Eq. 145)
    torch.testing.assert_close(r.w, E.running_coefficients(r.x, n_basis=K, length=ell)[-1])
    lam = E.sobolev_weights(2, K)
    torch.testing.assert_close(r.metric, E.ergodic_metric(E.running_coefficients(r.x, n_basis=K, length=ell),
                                                          w_hat, lam))
    assert r.metric[-1] < 0.05 * r.metric[0]
    # sharing matters: three separate single-agent problems behave differently
    solo = E.smc_rollout(x0[:, None], w_hat, n_steps=150, dt=0.02, u_max=1.5, n_basis=K, length=ell)
    assert not torch.allclose(solo.x[:, :, 0], r.x.transpose(0, 1))
    # continuing from the state == one long rollout
    a = E.smc_rollout(x0, w_hat, n_steps=60, dt=0.02, u_max=1.5, n_basis=K, length=ell)
    b = E.smc_rollout(None, w_hat, n_steps=90, dt=0.02, u_max=1.5, n_basis=K, length=ell, state=a.state)
    torch.testing.assert_close(torch.cat([a.x, b.x]), r.x)


def test_rollout_batched_equals_loop_and_nan_isolated():
    g = torch.Generator().manual_seed(5)
    K, ell = 5, 1.0
    al = torch.softmax(torch.randn(3, 2, dtype=F64, generator=g), -1)
    mu = 0.2 + 0.6 * torch.rand(3, 2, 2, dtype=F64, generator=g)
    S = torch.diag_embed(0.005 + 0.01 * torch.rand(3, 2, 2, dtype=F64, generator=g))
    w_hat = E.gmm_fourier_coefficients(al, mu, S, n_basis=K, length=ell)      # (3, K^2)
    x0 = torch.rand(2, 3, 2, 2, dtype=F64, generator=g)                        # (2, 3, N=2, D=2)
    x0[1, 2, 0, 0] = float("nan")
    r = E.smc_rollout(x0, w_hat, n_steps=40, dt=0.01, u_max=1.0, n_basis=K, length=ell)
    for i in range(2):
        for j in range(3):
            rij = E.smc_rollout(x0[i, j], w_hat[j], n_steps=40, dt=0.01, u_max=1.0, n_basis=K, length=ell)
            if (i, j) == (1, 2):
                assert r.metric[i, j].isnan().all()
                continue
            torch.testing.assert_close(r.x[i, j], rij.x, atol=1e-12, rtol=0)
            torch.testing.assert_close(r.metric[i, j], rij.metric, atol=1e-14, rtol=1e-10)
    assert torch.isfinite(r.metric[0]).all() and torch.isfinite(r.metric[1, :2]).all()


def test_float32_follows_dtype():
    al, mu, S = _gmm2d()
    w32 = E.gmm_fourier_coefficients(al.float(), mu.float(), S.float(), n_basis=6, length=2.0)
    w64 = E.gmm_fourier_coefficients(al, mu, S, n_basis=6, length=2.0)
    assert w32.dtype == torch.float32
    torch.testing.assert_close(w32.double(), w64, atol=1e-6, rtol=1e-4)
    x0 = torch.tensor([[0.2, 0.3]])
    r = E.smc_rollout(x0, w32, n_steps=10, dt=0.02, u_max=1.0, n_basis=6, length=2.0)
    r64 = E.smc_rollout(x0.double(), w64, n_steps=10, dt=0.02, u_max=1.0, n_basis=6, length=2.0)
    assert r.x.dtype == r.metric.dtype == torch.float32
    torch.testing.assert_close(r.metric.double(), r64.metric, rtol=1e-4, atol=1e-7)
    grid = E.HeatGrid(2, 8, 1.0)
    h = E.hedac_rollout(torch.tensor([[0.5, 0.5]]), torch.ones(8, 8), grid, n_steps=3, alpha=0.01, dt=0.01,
                        u_max=1.0, shape=10.0)
    assert h.residual_norm.dtype == torch.float32


def test_bad_inputs_raise():
    al, mu, S = _gmm2d()
    x = torch.rand(3, 2, dtype=F64)
    with pytest.raises(ValueError, match="n_basis"):
        E.fourier_basis(x, n_basis=0, length=1.0)
    with pytest.raises(ValueError, match="length"):
        E.fourier_basis(x, n_basis=3, length=-1.0)
    with pytest.raises(TypeError, match="'x'"):
        E.fourier_basis(torch.ones(3, 2, dtype=torch.long), n_basis=3, length=1.0)
    with pytest.raises(ValueError, match="covariances"):
        E.gmm_fourier_coefficients(al, mu, S[:, :1], n_basis=3, length=1.0)
    with pytest.raises(ValueError, match="weights"):
        E.gmm_fourier_coefficients(al[:1], mu, S, n_basis=3, length=1.0)
    with pytest.raises(TypeError, match="dtypes"):
        E.gmm_fourier_coefficients(al.float(), mu, S, n_basis=3, length=1.0)
    w = torch.zeros(9, dtype=F64)
    with pytest.raises(ValueError, match="w_hat"):
        E.smc_control(x[None], w, torch.zeros(8, dtype=F64), E.sobolev_weights(2, 3), n_basis=3, length=1.0,
                      u_max=1.0)
    with pytest.raises(ValueError, match="u_max"):
        E.smc_control(x[None], w, w, E.sobolev_weights(2, 3), n_basis=3, length=1.0, u_max=0.0)
    with pytest.raises(ValueError, match="n_steps"):
        E.smc_rollout(x[None], w, n_steps=0, dt=0.1, u_max=1.0, n_basis=3, length=1.0)
    with pytest.raises(TypeError, match="state"):
        E.smc_step((x, w, 0), w, E.sobolev_weights(2, 3), n_basis=3, length=1.0, u_max=1.0, dt=0.1)
    with pytest.raises(ValueError, match="n_cells"):
        E.HeatGrid(2, 2, 1.0)
    grid = E.HeatGrid(2, 8, 1.0)
    with pytest.raises(ValueError, match="unstable"):
        E.heat_step(torch.zeros(8, 8), torch.zeros(8, 8), grid, alpha=1.0, dt=0.1)
    with pytest.raises(ValueError, match="unstable"):
        E.heat_step(torch.zeros(8, 8), torch.zeros(8, 8), grid, alpha=0.0, dt=0.1, cooling=20.0)
    with pytest.raises(ValueError, match="cooling"):
        E.heat_step(torch.zeros(8, 8), torch.zeros(8, 8), grid, alpha=0.0, dt=0.1, cooling=-1.0)
    with pytest.raises(ValueError, match="'source'"):
        E.heat_step(torch.zeros(8, 8), torch.zeros(8, 7), grid, alpha=0.0, dt=0.1)
    with pytest.raises(ValueError, match="'x0'"):
        E.hedac_init(torch.zeros(2, 3), grid)


# ------------------------------------------------------------------------------------ SMC planning

def _plan_cost(x0, u, w_hat, dt, K, ell, r):
    x = x0[..., None, :, :] + dt * u.cumsum(-3)
    f = E.fourier_basis(x, n_basis=K, length=ell).mean((-3, -2)) - w_hat
    lam = E.sobolev_weights(x0.shape[-1], K, dtype=u.dtype)
    return (lam * f * f).sum(-1) + r * (u * u).flatten(-3).sum(-1)          # Eq. 139


def test_plan_gradient_is_that_of_eq139_and_improves_on_myopic():
    K, ell, T, dt, r = 8, 1.0, 80, 0.01, 1e-6
    al = torch.tensor([0.3, 0.7], dtype=F64)
    w_hat = E.gmm_fourier_coefficients(al, torch.tensor([[0.3], [0.7]], dtype=F64),
                                       torch.tensor([[[0.003]], [[0.005]]], dtype=F64), n_basis=K, length=ell)
    x0 = torch.tensor([[[0.1]], [[0.5]], [[0.9]]], dtype=F64)
    m = E.smc_rollout(x0, w_hat, n_steps=T, dt=dt, u_max=1.0, n_basis=K, length=ell)
    for it in (0, 50):
        p = E.smc_plan(x0, m.u, w_hat, dt=dt, n_basis=K, length=ell, control_weight=r, max_iter=it)
        u = p.u.clone().requires_grad_(True)
        c = _plan_cost(x0, u, w_hat, dt, K, ell, r)
        (g,) = torch.autograd.grad(c.sum(), u)
        torch.testing.assert_close(p.gradient_norm, g.flatten(1).abs().amax(-1))
        torch.testing.assert_close(p.cost, c.detach())
    torch.testing.assert_close(p.x, x0[:, None] + dt * p.u.cumsum(-3))
    assert p.converged.all()                                          # ‖∇c‖∞ ≤ 1e-4 ‖∇c(u_init)‖∞, checked
    assert (p.cost_history[:, 1:] <= p.cost_history[:, :-1]).all()
    assert (p.metric < 0.01 * m.metric[:, -1]).all()                  # planning beats the myopic guess
    assert (p.iterations > 0).all()


def test_plan_batched_equals_loop_2d_and_nan_isolated():
    al, mu, S = _gmm2d()
    K, ell, T = 5, 2.0, 30
    w_hat = E.gmm_fourier_coefficients(al, mu, S, n_basis=K, length=ell)
    g = torch.Generator().manual_seed(8)
    x0 = 2.0 * torch.rand(3, 2, 2, dtype=F64, generator=g)                   # 3 problems, N=2 agents
    u0 = torch.randn(3, T, 2, 2, dtype=F64, generator=g)
    x0[2, 0, 0] = float("nan")
    p = E.smc_plan(x0, u0, w_hat, dt=0.02, n_basis=K, length=ell, max_iter=8)
    for b in range(2):
        pb = E.smc_plan(x0[b], u0[b], w_hat, dt=0.02, n_basis=K, length=ell, max_iter=8)
        torch.testing.assert_close(p.u[b], pb.u)
        torch.testing.assert_close(p.cost_history[b], pb.cost_history)
        assert p.iterations[b] == pb.iterations and p.converged[b] == pb.converged
    assert torch.isfinite(p.u[:2]).all() and not p.converged[2] and p.iterations[2] == 0
    assert (p.cost_history[:2, -1] < p.cost_history[:2, 0]).all()
    with pytest.raises(ValueError, match="u_init"):
        E.smc_plan(x0, u0[..., :1, :], w_hat, dt=0.02, n_basis=K, length=ell)
    with pytest.raises(ValueError, match="control_weight"):
        E.smc_plan(x0, u0, w_hat, dt=0.02, n_basis=K, length=ell, control_weight=0.0)


# --------------------------------------------------------------------------------------------- HEDAC

def _neumann_1d(G: int) -> np.ndarray:
    A = -2 * np.eye(G) + np.eye(G, k=1) + np.eye(G, k=-1)
    A[0, 0] = A[-1, -1] = -1                                            # insulated walls (Eq. 165)
    return A


@pytest.mark.parametrize("D", [1, 2])
def test_heat_step_matches_dense_reference_and_conserves(D):
    G, ell, alpha, dt = 5, 1.0, 0.02, 0.05
    grid = E.HeatGrid(D, G, ell)
    h = ell / G
    A1 = _neumann_1d(G)
    A = A1 if D == 1 else np.kron(A1, np.eye(G)) + np.kron(np.eye(G), A1)
    g = torch.Generator().manual_seed(6)
    u = torch.rand(3, *grid.field_shape, dtype=F64, generator=g)
    s = torch.rand(3, *grid.field_shape, dtype=F64, generator=g)
    out = E.heat_step(u, s, grid, alpha=alpha, dt=dt)
    un, sn = u.reshape(3, -1).numpy(), s.reshape(3, -1).numpy()
    ref = un + dt * (alpha * un @ A.T / h ** 2 + sn)                    # Eq. 163, explicit Euler
    torch.testing.assert_close(out.reshape(3, -1), torch.from_numpy(ref))
    cooled = E.heat_step(u, s, grid, alpha=alpha, dt=dt, cooling=2.0)             # the −β u term of [6]
    torch.testing.assert_close(cooled.reshape(3, -1), torch.from_numpy(ref - dt * 2.0 * un))
    # the insulated walls conserve the heat; the source adds Δt ∫ s
    torch.testing.assert_close(grid.integrate(out), grid.integrate(u) + dt * grid.integrate(s))
    v = u
    for _ in range(2000):
        v = E.heat_step(v, torch.zeros_like(v), grid, alpha=alpha, dt=dt)
    torch.testing.assert_close(v, u.mean(dim=tuple(range(1, D + 1)), keepdim=True).expand_as(v))


def test_source_footprint_and_gradient():
    grid = E.HeatGrid(2, 10, 2.0)
    pts = grid.points(dtype=F64)
    g = torch.Generator().manual_seed(7)
    p = grid.normalize(torch.rand(2, 10, 10, dtype=F64, generator=g))
    c = grid.normalize(torch.rand(2, 10, 10, dtype=F64, generator=g))
    s = E.hedac_source(p, c, grid)
    e = p - c
    ref = torch.where(e > 0, e * e, 0)
    torch.testing.assert_close(s, ref / (ref.sum((-2, -1), keepdim=True) * grid.cell_volume))   # Eq. 160-162
    torch.testing.assert_close(grid.integrate(s), torch.ones(2, dtype=F64))
    x = torch.rand(2, 3, 2, dtype=F64, generator=g) * 2.0
    fp = E.agent_footprint(x, grid, shape=3.0)
    ref = sum(torch.exp(-9.0 * ((pts - x[:, i, None, None, :]) ** 2).sum(-1)) for i in range(3))  # Eq. 167
    torch.testing.assert_close(fp, ref)
    # a linear field: the interpolated gradient is exact inside the hull of the cell centres
    a = torch.tensor([[0.7, -1.3], [2.0, 0.5]], dtype=F64)
    u = (pts * a[:, None, None, :]).sum(-1) + 3.0
    xin = 0.1 + 1.8 * torch.rand(2, 4, 2, dtype=F64, generator=g)
    torch.testing.assert_close(E.field_gradient_at(u, xin, grid), a[:, None, :].expand(2, 4, 2))
    # a smooth field: close to the analytic gradient; and batching == loop
    uq = torch.cos(pts[..., 0]) * torch.sin(pts[..., 1])
    gq = E.field_gradient_at(uq, xin, grid)
    ana = torch.stack([-torch.sin(xin[..., 0]) * torch.sin(xin[..., 1]),
                       torch.cos(xin[..., 0]) * torch.cos(xin[..., 1])], -1)
    assert (gq - ana).abs().max() < 0.05
    torch.testing.assert_close(gq[1], E.field_gradient_at(uq, xin[1], grid))


def test_hedac_rollout_covers_batched_equals_loop_and_nan_isolated():
    grid = E.HeatGrid(2, 16, 1.0)
    al, mu, S = _gmm2d()
    p = E.gmm_density(grid.points(dtype=F64).reshape(-1, 2), al, mu / 2, S / 4).reshape(16, 16)
    x0 = torch.tensor([[[0.1, 0.1], [0.9, 0.9]], [[0.5, 0.5], [0.2, 0.8]], [[0.3, 0.3], [0.6, 0.6]]],
                      dtype=F64)
    x0[2, 1, 0] = float("nan")
    kw = dict(n_steps=60, alpha=0.02, dt=0.01, u_max=1.0, shape=15.0)
    r = E.hedac_rollout(x0, p, grid, **kw)
    assert r.x.shape == (3, 60, 2, 2) and r.residual_norm.shape == (3, 60)
    for b in range(2):
        rb = E.hedac_rollout(x0[b], p, grid, **kw)
        torch.testing.assert_close(r.x[b], rb.x)
        torch.testing.assert_close(r.residual_norm[b], rb.residual_norm)
        assert r.residual_norm[b, -1] < 0.6 * r.residual_norm[b, 0]
    assert ((r.x[:2] >= 0) & (r.x[:2] <= 1)).all()
    assert torch.isfinite(r.x[:2]).all() and torch.isnan(r.residual_norm[2, -1])


def test_hedac_1d_covers_target():
    grid = E.HeatGrid(1, 40, 1.0)
    pts = grid.points(dtype=F64)
    p = E.gmm_density(pts, torch.tensor([0.5, 0.5], dtype=F64), torch.tensor([[0.25], [0.7]], dtype=F64),
                      torch.tensor([[[0.004]], [[0.004]]], dtype=F64))
    r = E.hedac_rollout(torch.tensor([[0.05], [0.95]], dtype=F64), p, grid, n_steps=150, alpha=0.01, dt=0.01,
                        u_max=0.5, shape=20.0, cooling=10.0)
    assert r.residual_norm[-1] < 0.5 * r.residual_norm[0]
    near = ((r.x[..., 0, None] - torch.tensor([0.25, 0.7], dtype=F64)).abs() < 0.13).to(F64).mean((0, 1))
    assert (near > 0.3).all()                                            # both components visited


def test_zero_agents_and_too_few_substeps_raise():
    """No agents would make every average a silent NaN; too few heat sub-steps name ``n_substeps``."""
    F = torch.float64
    none = torch.zeros(1, 0, 2, dtype=F)
    w_hat = torch.zeros(25, dtype=F)
    with pytest.raises(ValueError, match="'x0'.*N >= 1"):
        E.smc_rollout(none, w_hat, n_steps=3, dt=0.01, u_max=1.0, n_basis=5, length=1.0)
    with pytest.raises(ValueError, match="'x0'.*N >= 1"):
        E.smc_plan(none, torch.zeros(1, 3, 0, 2, dtype=F), w_hat, dt=0.01, n_basis=5, length=1.0)
    with pytest.raises(ValueError, match="'traj'.*N >= 1"):
        E.running_coefficients(torch.zeros(3, 0, 2, dtype=F), n_basis=5, length=1.0)
    grid = E.HeatGrid(2, 20, 1.0)
    target = torch.ones(20, 20, dtype=F)
    with pytest.raises(ValueError, match="'x0'.*N >= 1"):
        E.hedac_rollout(none, target, grid, n_steps=2, alpha=0.01, dt=0.05, u_max=1.0, shape=10.0)
    state = E.hedac_init(torch.full((1, 1, 2), 0.5, dtype=F), grid)
    with pytest.raises(ValueError, match="'n_substeps'"):
        E.hedac_step(state, target, grid, alpha=1.0, dt=1.0, u_max=1.0, shape=10.0, n_substeps=1)
    # the smallest stable count passes: dt (2 D α / h² + β) = 1 · 4 · 400 = 1600 sub-steps of 1/1600
    step = E.hedac_step(state, target, grid, alpha=1.0, dt=1.0, u_max=1.0, shape=10.0, n_substeps=1600)
    assert torch.isfinite(step.state.heat).all()
