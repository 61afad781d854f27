"""Basis functions, seed 004 §6.3-6.5: derivatives, concatenated Bézier curves (continuity matrix) and
multidimensional inputs, against autograd, finite differences, scipy B-splines and torch.kron."""

import functools
import math

import numpy as np
import pytest
import torch
from scipy.interpolate import make_lsq_spline

from controllers import basis

D = torch.float64

DICTS = {
    "bernstein": functools.partial(basis.bernstein_deriv, K=6),
    "rbf": functools.partial(basis.rbf_deriv, K=5, bandwidth=7.0),
    "rbf_normalized": functools.partial(basis.rbf_deriv, K=5, normalized=True),
    "fourier": functools.partial(basis.fourier_deriv, K=4),
    "fourier_complex": functools.partial(basis.fourier_deriv, K=3, complex=True),
    "spline_c1": functools.partial(basis.spline, n_segments=3, continuity=1),
    "spline_c2_quartic": functools.partial(basis.spline, n_segments=4, degree=4, continuity=2),
    "powers": functools.partial(basis.powers, K=5),
}


def _autograd_deriv(f, t):
    """d/dt of every column of f(t) (t (T,), elementwise) by autograd, real and imaginary parts apart."""
    y = f(t)
    parts = [y.real, y.imag] if y.is_complex() else [y]
    out = []
    for p in parts:
        cols = [torch.autograd.grad(p[:, k].sum(), t, create_graph=True)[0] for k in range(p.shape[-1])]
        out.append(torch.stack(cols, -1))
    return torch.complex(*out) if y.is_complex() else out[0]


@pytest.mark.parametrize("name", sorted(DICTS))
def test_first_and_second_derivatives_match_autograd_and_finite_differences(name):
    f = DICTS[name]
    # away from the segment joints, where the C^1 spline's second derivative jumps
    t = torch.tensor([0.07, 0.29, 0.41, 0.58, 0.93], dtype=D, requires_grad=True)
    d1 = _autograd_deriv(lambda s: f(s, order=0), t)
    d2 = _autograd_deriv(lambda s: _autograd_deriv(lambda u: f(u, order=0), s), t)
    torch.testing.assert_close(f(t, order=1), d1, atol=1e-9, rtol=1e-10)
    torch.testing.assert_close(f(t, order=2), d2, atol=1e-8, rtol=1e-10)
    # central differences of the analytic first derivative give the analytic second derivative
    h = 1e-5
    tt = t.detach()
    fd = (f(tt + h, order=1) - f(tt - h, order=1)) / (2 * h)
    torch.testing.assert_close(f(tt, order=2), fd, atol=1e-4 * (1 + fd.abs().max().item()), rtol=0)
    assert f(tt, order=0).shape == f(tt, order=2).shape


def test_derivative_order_zero_is_the_dictionary_and_high_orders_vanish():
    t = basis.phases(11)
    torch.testing.assert_close(basis.bernstein_deriv(t, 5, order=0), basis.bernstein(t, 5))
    torch.testing.assert_close(basis.rbf_deriv(t, 5, order=0, normalized=True),
                               basis.rbf(t, 5, normalized=True))
    torch.testing.assert_close(basis.fourier_deriv(t, 5, order=0), basis.fourier(t, 5))
    assert basis.bernstein_deriv(t, 5, order=5).abs().max() == 0  # degree 4
    assert basis.bernstein_deriv(t, 5, order=4).std(0).max() < 1e-12  # constant 4th derivative
    torch.testing.assert_close(basis.piecewise_deriv(12, 3, order=0), basis.piecewise(12, 3))
    assert basis.piecewise_deriv(12, 3).abs().max() == 0
    # the third derivative of the cosines: (2πk)³ sin(2πkt)
    k = torch.arange(4, dtype=D)
    torch.testing.assert_close(basis.fourier_deriv(t, 4, order=3),
                               (2 * math.pi * k) ** 3 * torch.sin(2 * math.pi * t[:, None] * k))
    with pytest.raises(ValueError, match="'order'"):
        basis.bernstein_deriv(t, 5, order=-1)


def test_power_form_of_bernstein_eq31():
    t = torch.linspace(-0.2, 1.3, 17, dtype=D)
    B = basis.bernstein_matrix(5)
    torch.testing.assert_close(basis.powers(t, 5) @ B, basis.bernstein(t, 5), atol=1e-12, rtol=0)
    torch.testing.assert_close(basis.powers(t, 5, order=1) @ B, basis.bernstein_deriv(t, 5), atol=1e-11,
                               rtol=0)
    # dT/dt = [0, 1, 2t, 3t²] (§6.4)
    torch.testing.assert_close(basis.powers(t, 4, order=1),
                               torch.stack([0 * t, 1 + 0 * t, 2 * t, 3 * t ** 2], -1))


def test_continuity_matrix_is_eq45_for_cubic_c1():
    C = basis.continuity_matrix(3, 3, 1)
    assert C.shape == (12, 8)
    block = torch.tensor([[1.0, 0], [0, 1], [0, 1], [-1, 2]], dtype=D)  # Eq. (46)
    torch.testing.assert_close(C[2:6, 2:4], block)
    torch.testing.assert_close(C[6:10, 4:6], block)
    torch.testing.assert_close(C[:4, :4], torch.eye(4, dtype=D))
    assert basis.continuity_matrix(3, 3, None).equal(torch.eye(12, dtype=D))
    with pytest.raises(ValueError, match="'continuity'"):
        basis.continuity_matrix(3, 3, 4)


@pytest.mark.parametrize("degree,k", [(3, 0), (3, 1), (3, 2), (4, 2), (5, 3)])
def test_spline_is_ck_at_the_joints_and_not_more(degree, k):
    S = 4
    g = torch.Generator().manual_seed(degree * 10 + k)
    C = basis.continuity_matrix(S, degree, k)
    assert C.shape == (S * (degree + 1), degree + 1 + (S - 1) * (degree - k))
    v = torch.randn(6, C.shape[1], dtype=D, generator=g)  # a batch of random free weights
    w = (v @ C.T).reshape(6, S, degree + 1)  # control points per segment
    one, zero = torch.ones((), dtype=D), torch.zeros((), dtype=D)
    for j in range(k + 2):
        left = w[:, :-1] @ basis.bernstein_deriv(one, degree + 1, order=j)  # end of segment s
        right = w[:, 1:] @ basis.bernstein_deriv(zero, degree + 1, order=j)  # start of segment s+1
        gap = (left - right).abs().max().item()
        if j <= k:
            assert gap < 1e-10 * (1 + left.abs().max().item())
        else:
            assert gap > 1e-3  # generic weights: the next derivative jumps
    # the global basis agrees: evaluating spline() just left/right of a joint
    t = torch.tensor([0.5 - 1e-9, 0.5 + 1e-9], dtype=D)
    x = basis.spline(t, S, degree, k, order=k) @ v.T
    assert ((x[0] - x[1]).abs() <= 1e-6 * (1 + x[0].abs())).all()


@pytest.mark.parametrize("k,mult", [(2, 1), (1, 2)])
def test_cubic_spline_least_squares_equals_scipy_bspline(k, mult):
    """C² cubic concatenated Bézier curves span the cubic B-splines with simple interior knots, C¹ ones those
    with double knots: the least-squares fits (Eq. 47) coincide with scipy's ``make_lsq_spline``."""
    S = 5
    g = torch.Generator().manual_seed(3)
    t = torch.sort(torch.rand(120, dtype=D, generator=g)).values
    y = torch.sin(7 * t) + 0.3 * t ** 2 + 0.05 * torch.randn(120, dtype=D, generator=g)
    phi = basis.spline(t, S, 3, k)
    v = basis.fit(phi, y)
    tq = torch.linspace(0, 1, 301, dtype=D)
    ours = basis.spline(tq, S, 3, k) @ v
    interior = np.repeat(np.arange(1, S) / S, mult)
    knots = np.concatenate([np.zeros(4), interior, np.ones(4)])
    ref = make_lsq_spline(t.numpy(), y.numpy(), knots, k=3)(tq.numpy())
    np.testing.assert_allclose(ours.numpy(), ref, atol=1e-9)


def test_kron_rows_and_tensor_basis_match_torch_kron_eq30_33():
    g = torch.Generator().manual_seed(0)
    x = torch.rand(7, 3, dtype=D, generator=g)
    bern = functools.partial(basis.bernstein_deriv, K=4)
    Psi = basis.tensor_basis(x, bern)
    assert Psi.shape == (7, 64)
    for i in range(7):
        rows = [basis.bernstein(x[i, j:j + 1], 4) for j in range(3)]
        torch.testing.assert_close(Psi[i:i + 1], torch.kron(torch.kron(rows[0], rows[1]), rows[2]))
    # Eq. (30): on the grid t1 × t2 (t1 slowest), Ψ = φ ⊗ φ as matrices
    t = basis.phases(6)
    grid = torch.stack(torch.meshgrid(t, t, indexing="ij"), -1).reshape(-1, 2)
    phi = basis.bernstein(t, 4)
    torch.testing.assert_close(basis.tensor_basis(grid, bern), torch.kron(phi, phi))
    # mixed dictionaries, one per input, and a partition of unity for Bernstein ⊗ Bernstein
    mixed = basis.tensor_basis(x[:, :2], [bern, functools.partial(basis.fourier_deriv, K=3)])
    assert mixed.shape == (7, 12)
    torch.testing.assert_close(Psi.sum(-1), torch.ones(7, dtype=D))


def test_tensor_gradient_matches_autograd_finite_differences_and_gradcheck():
    g = torch.Generator().manual_seed(1)
    spl = functools.partial(basis.spline, n_segments=3, continuity=2)
    P = basis.tensor_basis(torch.zeros(1, 2, dtype=D), spl).shape[-1]
    w = torch.randn(P, dtype=D, generator=g)
    x = 0.05 + 0.9 * torch.rand(9, 2, dtype=D, generator=g)
    f, grad = basis.tensor_grad(x, w, spl)
    torch.testing.assert_close(f, basis.tensor_eval(x, w, spl))
    torch.testing.assert_close(grad, (basis.tensor_basis_grad(x, spl) @ w))  # Eq. (37)
    xa = x.clone().requires_grad_(True)
    auto = torch.autograd.grad(basis.tensor_eval(xa, w, spl).sum(), xa)[0]
    torch.testing.assert_close(grad, auto, atol=1e-11, rtol=1e-11)
    h = 1e-6
    fd = torch.stack([(basis.tensor_eval(x + h * e, w, spl) - basis.tensor_eval(x - h * e, w, spl)) / (2 * h)
                      for e in torch.eye(2, dtype=D)], -1)
    torch.testing.assert_close(grad, fd, atol=1e-6, rtol=0)
    # differentiable in x and w
    bern = functools.partial(basis.bernstein_deriv, K=4)
    w2 = torch.randn(16, dtype=D, generator=g, requires_grad=True)
    x3 = xa[:3].detach().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda xx, ww: basis.tensor_grad(xx, ww, bern), (x3, w2))


def test_tensor_eval_batching_broadcasting_dtypes_and_nan():
    g = torch.Generator().manual_seed(2)
    bern = functools.partial(basis.bernstein_deriv, K=3)
    w = torch.randn(4, 1, 9, dtype=D, generator=g)  # 4 fields
    x = torch.rand(5, 2, dtype=D, generator=g)  # 5 points
    f, grad = basis.tensor_grad(x, w, bern)
    assert f.shape == (4, 5) and grad.shape == (4, 5, 2)
    for i in range(4):
        for j in range(5):
            fi, gi = basis.tensor_grad(x[j], w[i, 0], bern)
            torch.testing.assert_close(f[i, j], fi)
            torch.testing.assert_close(grad[i, j], gi)
    f32, g32 = basis.tensor_grad(x.float(), w.float(), bern)
    assert f32.dtype == torch.float32 and g32.dtype == torch.float32
    torch.testing.assert_close(f32.double(), f, atol=1e-5, rtol=1e-5)
    xn = x.clone()
    xn[2, 0] = math.nan
    fn_, gn = basis.tensor_grad(xn, w, bern)
    assert torch.isnan(fn_[:, 2]).all() and torch.isfinite(fn_[:, [0, 1, 3, 4]]).all()
    torch.testing.assert_close(gn[:, [0, 1, 3, 4]], grad[:, [0, 1, 3, 4]])
    with pytest.raises(ValueError, match="'w'"):
        basis.tensor_eval(x, torch.zeros(8, dtype=D), bern)
    with pytest.raises(TypeError, match="'basis'"):
        basis.tensor_eval(x, w, [bern])
    with pytest.raises(TypeError, match="dtype"):
        basis.tensor_eval(x, w.float(), bern)
    with pytest.raises(ValueError, match="'x'"):
        basis.tensor_basis(torch.zeros(3, 2, dtype=torch.int64), bern)


def test_bezier_surface_fit_recovers_a_polynomial_surface():
    """A degree-(3,3) polynomial height field is exactly a bicubic Bézier surface: least squares (Eq. 47) on
    Ψ = φ ⊗ φ recovers it, and its gradient (Eq. 35-37) is the polynomial's."""
    g = torch.Generator().manual_seed(4)
    x = torch.rand(80, 2, dtype=D, generator=g)
    u, v = x[:, 0], x[:, 1]
    z = 1 + u - 2 * v ** 2 + 3 * u ** 3 * v - u * v ** 3
    bern = functools.partial(basis.bernstein_deriv, K=4)
    w = basis.fit(basis.tensor_basis(x, bern), z)
    xq = torch.rand(20, 2, dtype=D, generator=g)
    uq, vq = xq[:, 0], xq[:, 1]
    f, grad = basis.tensor_grad(xq, w, bern)
    torch.testing.assert_close(f, 1 + uq - 2 * vq ** 2 + 3 * uq ** 3 * vq - uq * vq ** 3, atol=1e-10, rtol=0)
    torch.testing.assert_close(grad[:, 0], 1 + 9 * uq ** 2 * vq - vq ** 3, atol=1e-9, rtol=0)
    torch.testing.assert_close(grad[:, 1], -4 * vq + 3 * uq ** 3 - 3 * uq * vq ** 2, atol=1e-9, rtol=0)
