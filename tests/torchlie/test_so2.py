"""torchlie.so2 against independent references: complex numbers, matrix_exp, finite differences."""

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from torch.autograd import gradcheck

from torchlie import so2
from torchlie.testing import angles_near_edges, check_batching, fd_jacobian, sample_angles

F64 = torch.float64
SETTINGS = settings(max_examples=25, deadline=None)
angle_st = st.floats(-math.pi, math.pi, allow_nan=False)


def _signed_edges(dtype=F64):
    th = angles_near_edges(dtype)
    return torch.cat((th, -th[1:-1]))  # −π is not principal


def _random(n, seed, dtype=F64):
    g = torch.Generator().manual_seed(seed)
    th = sample_angles(n, g, F64)
    sign = torch.where(torch.rand(n, generator=g, dtype=F64) < 0.5, -1.0, 1.0)
    return torch.cat((_signed_edges(F64), sign * th)).to(dtype).unsqueeze(-1)


# ---------------------------------------------------------------------------------------------- values
@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 2e-5)])
def test_exp_log_round_trip_and_principal(dtype, tol):
    x = _random(300, 0, dtype)
    X = so2.exp(x)
    assert X.dtype == dtype and X.shape == (x.shape[0], 2, 2)
    assert (so2.exp(so2.log(X)) - X).abs().max() <= tol
    # log(exp(θ)) = θ up to 2π (float32(π) > π and −π + 1e-9 rounds to −π in float32, so they wrap) ...
    lx = so2.log(X)
    assert (torch.remainder(lx - x + math.pi, 2 * math.pi) - math.pi).abs().max() <= tol
    # ... and exactly θ where θ is principal
    principal = x.abs() < math.pi - 1e-5
    assert (lx - x)[principal].abs().max() <= tol
    assert ((lx > -math.pi) & (lx <= math.pi)).all()
    # exp vs the complex exponential e^{iθ}
    z = torch.polar(torch.ones_like(x[..., 0]), x[..., 0])
    torch.testing.assert_close(X[..., 0, 0], z.real, atol=tol, rtol=0)
    torch.testing.assert_close(X[..., 1, 0], z.imag, atol=tol, rtol=0)


def test_log_principal_cut():
    # −π and π are the same rotation; log returns +π for both, and angles beyond π wrap
    pi = math.pi
    th = torch.tensor([[-pi], [pi], [3 * pi / 2], [-3 * pi / 2], [2 * pi]], dtype=F64)
    out = so2.log(so2.exp(th))[..., 0]
    torch.testing.assert_close(out, torch.tensor([math.pi, math.pi, -math.pi / 2, math.pi / 2, 0.0],
                                                 dtype=F64), atol=1e-15, rtol=0)
    R = torch.tensor([[-1.0, -0.0], [-0.0, -1.0]], dtype=F64)  # atan2(−0, −1) = −π
    assert so2.log(R).item() == math.pi
    x = _random(200, 1)
    lx = so2.log(so2.exp(x))
    assert ((lx > -math.pi) & (lx <= math.pi)).all()


def test_exp_is_matrix_exponential_of_hat_and_vee_inverts_hat():
    x = _random(50, 2)
    torch.testing.assert_close(so2.exp(x), torch.linalg.matrix_exp(so2.hat(x)), atol=1e-13, rtol=0)
    torch.testing.assert_close(so2.vee(so2.hat(x)), x, atol=0, rtol=0)
    M = so2.hat(x)
    torch.testing.assert_close(so2.hat(so2.vee(M)), M, atol=0, rtol=0)


def test_act_against_complex_multiplication():
    g = torch.Generator().manual_seed(3)
    x = _random(40, 3)
    p = torch.randn(x.shape[0], 2, generator=g, dtype=F64)
    z = torch.polar(torch.ones_like(x[..., 0]), x[..., 0]) * torch.complex(p[..., 0], p[..., 1])
    out = so2.act(so2.exp(x), p)
    torch.testing.assert_close(out, torch.stack((z.real, z.imag), -1), atol=1e-13, rtol=0)


@SETTINGS
@given(a=angle_st, b=angle_st, c=angle_st)
def test_group_axioms(a, b, c):
    A, B, C = (so2.exp(torch.tensor([v], dtype=F64)) for v in (a, b, c))
    I2 = so2.identity(dtype=F64)
    torch.testing.assert_close(so2.compose(so2.compose(A, B), C), so2.compose(A, so2.compose(B, C)),
                               atol=1e-14, rtol=0)
    torch.testing.assert_close(so2.compose(A, I2), A, atol=0, rtol=0)
    torch.testing.assert_close(so2.compose(A, so2.inverse(A)), I2, atol=1e-15, rtol=0)
    # SO(2) is abelian and exp is a homomorphism from (R, +)
    AB = so2.exp(torch.tensor([a + b], dtype=F64))
    torch.testing.assert_close(so2.compose(A, B), AB, atol=1e-14, rtol=0)
    torch.testing.assert_close(so2.compose(A, B), so2.compose(B, A), atol=1e-15, rtol=0)
    # round trips: exp(log(A)) = A, log(exp(a)) = a up to 2π (−π maps to +π)
    torch.testing.assert_close(so2.exp(so2.log(A)), A, atol=1e-15, rtol=0)
    d = so2.log(A).item() - a
    assert abs(d) <= 1e-15 or abs(abs(d) - 2 * math.pi) <= 1e-15


@SETTINGS
@given(a=angle_st, b=angle_st)
def test_adjoint_and_ad_identities(a, b):
    X = so2.exp(torch.tensor([a], dtype=F64))
    x, y = torch.tensor([b], dtype=F64), torch.tensor([a], dtype=F64)
    # X exp(x) X⁻¹ = exp(Ad_X x)
    lhs = so2.compose(so2.compose(X, so2.exp(x)), so2.inverse(X))
    rhs = so2.exp((so2.adjoint(X) @ x.unsqueeze(-1)).squeeze(-1))
    torch.testing.assert_close(lhs, rhs, atol=1e-14, rtol=0)
    # ad_x y = vee([hat x, hat y]) and Ad_X ad_x Ad_X⁻¹ = ad_{Ad_X x}
    hx, hy = so2.hat(x), so2.hat(y)
    torch.testing.assert_close((so2.ad(x) @ y.unsqueeze(-1)).squeeze(-1), so2.vee(hx @ hy - hy @ hx),
                               atol=1e-15, rtol=0)
    Ad = so2.adjoint(X)
    torch.testing.assert_close(Ad @ so2.ad(x) @ torch.linalg.inv(Ad),
                               so2.ad((Ad @ x.unsqueeze(-1)).squeeze(-1)), atol=0, rtol=0)


def test_jacobians_against_finite_differences():
    x = _random(12, 4)
    for xi in x:
        X = so2.exp(xi)
        z = torch.zeros(1, dtype=F64)
        Jr = fd_jacobian(lambda d, xi=xi, X=X: so2.log(so2.compose(so2.inverse(X), so2.exp(xi + d))), z)
        Jl = fd_jacobian(lambda d, xi=xi, X=X: so2.log(so2.compose(so2.exp(xi + d), so2.inverse(X))), z)
        torch.testing.assert_close(so2.right_jacobian(xi), Jr, atol=1e-8, rtol=0)
        torch.testing.assert_close(so2.left_jacobian(xi), Jl, atol=1e-8, rtol=0)
    I1 = torch.ones(x.shape[0], 1, 1, dtype=F64)
    torch.testing.assert_close(so2.left_jacobian(x) @ so2.left_jacobian_inv(x), I1, atol=1e-10, rtol=0)
    torch.testing.assert_close(so2.right_jacobian(x) @ so2.right_jacobian_inv(x), I1, atol=1e-10, rtol=0)
    torch.testing.assert_close(so2.ad(x), torch.zeros_like(I1), atol=0, rtol=0)


def test_interpolate():
    g = torch.Generator().manual_seed(5)
    X, Y = so2.random(4, generator=g, dtype=F64), so2.random(4, generator=g, dtype=F64)
    torch.testing.assert_close(so2.interpolate(X, Y, 0.0), X, atol=1e-15, rtol=0)
    torch.testing.assert_close(so2.interpolate(X, Y, 1.0), Y, atol=1e-14, rtol=0)
    t = torch.linspace(0, 1, 5, dtype=F64).unsqueeze(-1)  # (T, 1) against batch (4,) -> (T, 4)
    path = so2.interpolate(X, Y, t)
    assert path.shape == (5, 4, 2, 2)
    # constant angular speed along the shortest arc, independent reference: wrapped angle differences
    ax, ay = so2.log(X)[..., 0], so2.log(Y)[..., 0]
    d = torch.remainder(ay - ax + math.pi, 2 * math.pi) - math.pi
    torch.testing.assert_close(path, so2.exp((ax + t * d).unsqueeze(-1)), atol=1e-14, rtol=0)


# ---------------------------------------------------------------------------------------------- gradients
def test_gradcheck_every_function_including_zero():
    # log jumps by 2π across ±π, so its finite differences stay 1e-3 away from the cut
    u = torch.rand(6, 1, dtype=F64, generator=torch.Generator().manual_seed(5))
    edges = [[0.0], [1e-9], [-0.04], [0.7], [math.pi - 1e-3], [-math.pi + 1e-3]]
    x = torch.cat((torch.tensor(edges, dtype=F64), (2 * u - 1) * 3.0))
    x.requires_grad_(True)
    R = so2.exp(x.detach()).requires_grad_(True)
    S = so2.exp(x.detach().flip(0)).requires_grad_(True)
    p = torch.randn(x.shape[0], 2, dtype=F64, generator=torch.Generator().manual_seed(6)).requires_grad_(True)
    t = torch.rand(x.shape[0], dtype=F64, generator=torch.Generator().manual_seed(7)).requires_grad_(True)
    assert gradcheck(so2.exp, (x,))
    assert gradcheck(so2.log, (R,))
    assert gradcheck(so2.hat, (x,))
    assert gradcheck(so2.vee, (R,))
    assert gradcheck(so2.compose, (R, S))
    assert gradcheck(so2.inverse, (R,))
    assert gradcheck(so2.act, (R, p))
    assert gradcheck(lambda a, b, s: so2.interpolate(a, b, s), (R[:4], S[:4], t[:4]))
    for f in (so2.adjoint, so2.ad, so2.left_jacobian, so2.left_jacobian_inv, so2.right_jacobian,
              so2.right_jacobian_inv):
        arg = R if f is so2.adjoint else x
        assert gradcheck(f, (arg,))


def test_gradient_exact_and_finite_at_zero_and_pi():
    # d log(exp(θ))/dθ = 1 on (−π, π], also exactly at 0 and at π (one-sided there)
    th = torch.tensor([[0.0], [1e-9], [math.pi - 1e-9], [math.pi]], dtype=F64)
    J = torch.func.vmap(torch.func.jacrev(lambda v: so2.log(so2.exp(v))))(th)
    torch.testing.assert_close(J, torch.ones_like(J), atol=1e-15, rtol=0)
    R = so2.exp(th).requires_grad_(True)
    so2.log(R).sum().backward()
    assert torch.isfinite(R.grad).all()


# ---------------------------------------------------------------------------------------------- batching
def test_batched_flattened_loop_and_broadcasting():
    g = torch.Generator().manual_seed(8)
    x = torch.randn(3, 4, 1, generator=g, dtype=F64)
    X, Y = so2.exp(x), so2.random(3, 4, generator=g, dtype=F64)
    p = torch.randn(3, 4, 2, generator=g, dtype=F64)
    check_batching(so2.exp, (x,), (1,))
    check_batching(so2.log, (X,), (2,))
    check_batching(so2.compose, (X, Y), (2, 2))
    check_batching(so2.act, (X, p), (2, 1))
    check_batching(lambda a, b: so2.interpolate(a, b, 0.3), (X, Y), (2, 2))
    # broadcasting == manual expansion
    torch.testing.assert_close(so2.compose(X[:, :1], Y), so2.compose(X[:, :1].expand(3, 4, 2, 2), Y))
    torch.testing.assert_close(so2.act(X[0, 0], p), so2.act(X[0, 0].expand(3, 4, 2, 2), p))
    assert so2.exp(torch.zeros(0, 1)).shape == (0, 2, 2)


def test_vmap_jacrev_and_compile():
    x = _random(6, 9)
    v = torch.func.vmap(so2.exp)(x)
    torch.testing.assert_close(v, so2.exp(x), atol=0, rtol=0)
    J = torch.func.vmap(torch.func.jacrev(so2.exp))(x)  # dR/dθ = R hat(1)
    torch.testing.assert_close(J[..., 0], so2.exp(x) @ so2.hat(torch.ones_like(x)), atol=1e-15, rtol=0)
    f = torch.compile(so2.log, fullgraph=True, dynamic=False)
    X = so2.exp(x)
    torch.testing.assert_close(f(X), so2.log(X), atol=1e-15, rtol=0)


# ---------------------------------------------------------------------------------------------- constructors
def test_identity_and_random():
    assert so2.identity(2, 3).shape == (2, 3, 2, 2) and so2.identity((2, 3)).shape == (2, 3, 2, 2)
    assert so2.identity(dtype=F64).dtype == F64 and so2.identity().dtype == torch.get_default_dtype()
    torch.testing.assert_close(so2.identity(4, dtype=F64), torch.eye(2, dtype=F64).expand(4, 2, 2))
    a = so2.random(1000, generator=torch.Generator().manual_seed(0), dtype=F64)
    b = so2.random(1000, generator=torch.Generator().manual_seed(0), dtype=F64)
    assert torch.equal(a, b) and a.shape == (1000, 2, 2)
    torch.testing.assert_close(a.transpose(-1, -2) @ a, torch.eye(2, dtype=F64).expand(1000, 2, 2),
                               atol=1e-15, rtol=0)
    from scipy.stats import kstest

    th = so2.log(a)[..., 0].numpy()
    assert kstest(th, "uniform", args=(-math.pi, 2 * math.pi)).pvalue > 1e-3
    with pytest.raises(TypeError, match="dtype"):
        so2.random(3, dtype=torch.int64)


# ---------------------------------------------------------------------------------------------- bad input
def test_bad_input_names_argument_and_shape():
    with pytest.raises(ValueError, match=r"'x'.*\(\*, 1\)"):
        so2.exp(torch.zeros(3, 2))
    with pytest.raises(ValueError, match=r"'X'.*\(\*, 2, 2\)"):
        so2.log(torch.zeros(3, 3))
    with pytest.raises(TypeError, match="'x'.*floating"):
        so2.exp(torch.zeros(3, 1, dtype=torch.int64))
    with pytest.raises(TypeError, match="'X'.*'Y'.*dtype"):
        so2.compose(so2.identity(dtype=F64), so2.identity(dtype=torch.float32))
    with pytest.raises(ValueError, match="'p'.*\\(\\*, 2\\)"):
        so2.act(so2.identity(), torch.zeros(3))
    with pytest.raises(ValueError, match="do not broadcast"):
        so2.compose(so2.identity(3), so2.identity(4))
    with pytest.raises(TypeError, match="'t'"):
        I2 = so2.identity(dtype=F64)
        so2.interpolate(I2, I2, torch.tensor(0.5, dtype=torch.float32))


def test_nan_stays_in_its_element():
    x = _random(5, 10)[:5].clone()
    x[2] = float("nan")
    X = so2.exp(x)
    bad = torch.zeros(5, dtype=torch.bool)
    bad[2] = True
    assert torch.isnan(X[bad]).all() and torch.isfinite(X[~bad]).all()
    assert torch.isfinite(so2.log(X)[~bad]).all() and torch.isnan(so2.log(X)[bad]).all()
    assert torch.isfinite(so2.compose(X, so2.exp(x.flip(0)))[~bad & ~bad.flip(0)]).all()


def test_device_follows_input_and_mismatch_is_rejected():
    m = torch.device("meta")  # shape/dtype/device propagation without data
    assert so2.exp(torch.zeros(4, 1, device=m)).device == m
    assert so2.log(torch.zeros(4, 2, 2, device=m)).device == m
    assert so2.identity(3, device=m).device == m
    assert so2.interpolate(so2.identity(2, device=m), so2.identity(2, device=m), 0.5).device == m
    with pytest.raises(ValueError, match="'X' and 'Y' are on different devices"):
        so2.compose(torch.zeros(2, 2), torch.zeros(2, 2, device=m))
    with pytest.raises(ValueError, match="'X' and 'p' are on different devices"):
        so2.act(torch.zeros(2, 2), torch.zeros(2, device=m))
