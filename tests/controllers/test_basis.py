"""Basis functions (seed 004 §6) against their defining formulas and properties."""

import math

import pytest
import torch

from controllers import basis

D = torch.float64


def test_piecewise_kron_and_general():
    phi = basis.piecewise(12, 3)
    assert phi.shape == (12, 3)
    torch.testing.assert_close(phi, torch.kron(torch.eye(3, dtype=D), torch.ones(4, 1, dtype=D)))
    phi2 = basis.piecewise(10, 3)
    assert phi2.shape == (10, 3) and bool((phi2.sum(-1) == 1).all())
    assert phi2.argmax(-1).tolist() == [0, 0, 0, 0, 1, 1, 1, 2, 2, 2]
    # continuous phases: segment index floor(t K), last point in the last segment
    tt = torch.tensor([0.0, 0.34, 0.99, 1.0], dtype=D)
    assert basis.piecewise(tt, 3).argmax(-1).tolist() == [0, 1, 2, 2]


def test_rbf_formula_and_normalization():
    t = basis.phases(7)
    phi = basis.rbf(7, 4, bandwidth=5.0)
    mu = torch.linspace(0, 1, 4, dtype=D)
    for i in range(7):
        for k in range(4):
            assert math.isclose(phi[i, k].item(), math.exp(-5.0 * (t[i] - mu[k]).item() ** 2), rel_tol=1e-12)
    nphi = basis.rbf(7, 4, normalized=True)
    torch.testing.assert_close(nphi.sum(-1), torch.ones(7, dtype=D))
    with pytest.raises(ValueError, match="bandwidth"):
        basis.rbf(7, 4, bandwidth=-1.0)
    with pytest.raises(ValueError, match="'K'"):
        basis.rbf(7, 0)


def test_bernstein_partition_of_unity_and_formula():
    phi = basis.bernstein(9, 5)
    torch.testing.assert_close(phi.sum(-1), torch.ones(9, dtype=D))
    t = basis.phases(9)
    for k in range(5):
        ref = math.comb(4, k) * (1 - t) ** (4 - k) * t ** k
        torch.testing.assert_close(phi[:, k], ref)
    # a Bézier curve interpolates its end control points
    w = torch.tensor([2.0, -1.0, 3.0, 0.5, 4.0], dtype=D)
    x = phi @ w
    assert math.isclose(x[0].item(), 2.0) and math.isclose(x[-1].item(), 4.0)


def test_fourier_real_is_real_part_of_symmetric_complex():
    K = 4
    phi = basis.fourier(16, K)
    t = basis.phases(16)
    torch.testing.assert_close(phi[:, 2], torch.cos(2 * math.pi * 2 * t))
    c = basis.fourier(16, K, complex=True)
    assert c.shape == (16, 2 * K - 1) and c.is_complex()
    # exp(i a) + exp(-i a) = 2 cos a (the derivation after Eq. 28)
    for k in range(1, K):
        torch.testing.assert_close((c[:, K - 1 + k] + c[:, K - 1 - k]).real, 2 * phi[:, k])
        assert (c[:, K - 1 + k] + c[:, K - 1 - k]).imag.abs().max() < 1e-12


def test_multidim_and_fits():
    g = torch.Generator().manual_seed(0)
    phi = basis.rbf(20, 5)
    Psi = basis.multidim(phi, 2)
    assert Psi.shape == (40, 10)
    w = torch.randn(3, 10, dtype=D, generator=g)
    x = (Psi @ w.unsqueeze(-1)).squeeze(-1)
    # exact data is recovered by least squares (Eq. 47), batched
    torch.testing.assert_close(basis.fit(Psi, x), w, atol=1e-8, rtol=0)
    # recursive least squares (Algorithm 2) == batch ridge regression (Eq. 48)
    xn = x + 0.1 * torch.randn(x.shape, dtype=D, generator=g)
    torch.testing.assert_close(basis.recursive_fit(Psi, xn, ridge=0.5), basis.fit(Psi, xn, ridge=0.5))
    # ridge solution is the stationary point of the regularized cost
    wr = basis.fit(Psi, xn[0], ridge=0.5)
    grad = Psi.T @ (Psi @ wr - xn[0]) + 0.5 * wr
    assert grad.abs().max() < 1e-10
    with pytest.raises(ValueError, match="'x'"):
        basis.fit(Psi, torch.zeros(39, dtype=D))
