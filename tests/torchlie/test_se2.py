"""torchlie.se2 against independent references: matrix_exp, the ad-series of the Jacobians, finite
differences and torch.linalg."""

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from torch.autograd import gradcheck

from torchlie import se2
from torchlie.testing import angles_near_edges, check_batching, fd_jacobian, sample_angles

F64 = torch.float64
SETTINGS = settings(max_examples=25, deadline=None)
tangent_st = st.tuples(st.floats(-5, 5), st.floats(-5, 5), st.floats(-math.pi, math.pi))


def _tangents(n, seed, dtype=F64, edges=True):
    """Tangents [vx, vy, θ]: every edge angle (both signs, no −π) and n clustered random angles."""
    g = torch.Generator().manual_seed(seed)
    th = sample_angles(n, g, F64)
    th = th * torch.where(torch.rand(n, generator=g, dtype=F64) < 0.5, -1.0, 1.0)
    if edges:
        e = angles_near_edges(F64)
        th = torch.cat((e, -e[1:-1], th))
    v = 3 * torch.randn(th.shape[0], 2, generator=g, dtype=F64)
    return torch.cat((v, th.unsqueeze(-1)), -1).to(dtype)


def _series_jl(x):
    """J_l = Σ ad_x^k/(k+1)!: top-right block of expm([[ad_x, I], [0, 0]]) (independent of se2's formulas)."""
    A = se2.ad(x)
    n = x.shape[0]
    Z, eye = torch.zeros(n, 3, 3, dtype=x.dtype), torch.eye(3, dtype=x.dtype).expand(n, 3, 3)
    big = torch.cat((torch.cat((A, eye), -1), torch.cat((Z, Z), -1)), -2)
    return torch.linalg.matrix_exp(big)[:, :3, 3:]


def _vec(M, x):
    return (M @ x.unsqueeze(-1)).squeeze(-1)


# ---------------------------------------------------------------------------------------------- values
@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 2e-5)])
def test_exp_log_round_trip(dtype, tol):
    x = _tangents(300, 0, dtype)
    X = se2.exp(x)
    assert X.dtype == dtype and X.shape == (x.shape[0], 3, 3)
    assert (se2.exp(se2.log(X)) - X).abs().max() <= tol
    lx = se2.log(X)
    assert ((lx[..., 2] > -math.pi) & (lx[..., 2] <= math.pi)).all()
    inside = x[..., 2].abs() < math.pi - 1e-5  # float32(π) > π wraps; compare there only via exp
    assert ((lx - x)[inside].abs().max(-1).values / (1 + x[inside].abs().max(-1).values)).max() <= tol


def test_exp_is_matrix_exponential_and_log_of_minus_pi():
    x = _tangents(60, 1)
    torch.testing.assert_close(se2.exp(x), torch.linalg.matrix_exp(se2.hat(x)), atol=1e-12, rtol=0)
    torch.testing.assert_close(se2.vee(se2.hat(x)), x, atol=0, rtol=0)
    # θ = −π maps to +π with the same matrix
    y = torch.tensor([1.0, -2.0, -math.pi], dtype=F64)
    ly = se2.log(se2.exp(y))
    assert ly[2] == math.pi
    torch.testing.assert_close(se2.exp(ly), se2.exp(y), atol=1e-15, rtol=0)


def test_inverse_act_against_linalg():
    g = torch.Generator().manual_seed(2)
    X = se2.random(20, generator=g, dtype=F64)
    p = torch.randn(20, 2, generator=g, dtype=F64)
    torch.testing.assert_close(se2.inverse(X), torch.linalg.inv(X), atol=1e-14, rtol=0)
    ph = torch.cat((p, torch.ones(20, 1, dtype=F64)), -1)
    torch.testing.assert_close(se2.act(X, p), _vec(X, ph)[..., :2], atol=1e-14, rtol=0)


@SETTINGS
@given(a=tangent_st, b=tangent_st, c=tangent_st)
def test_group_axioms(a, b, c):
    A, B, C = (se2.exp(torch.tensor(v, dtype=F64)) for v in (a, b, c))
    eye = se2.identity(dtype=F64)
    torch.testing.assert_close(se2.compose(se2.compose(A, B), C), se2.compose(A, se2.compose(B, C)),
                               atol=1e-12, rtol=0)
    torch.testing.assert_close(se2.compose(A, eye), A, atol=0, rtol=0)
    torch.testing.assert_close(se2.compose(A, se2.inverse(A)), eye, atol=1e-13, rtol=0)
    # exp of multiples of one tangent form a one-parameter subgroup
    x = torch.tensor(a, dtype=F64)
    torch.testing.assert_close(se2.compose(se2.exp(0.3 * x), se2.exp(0.7 * x)), A, atol=1e-13, rtol=0)
    # round trips: exp(log(A)) = A and log(exp(x)) = x for principal θ
    torch.testing.assert_close(se2.exp(se2.log(A)), A, atol=1e-13, rtol=0)
    if x[2] > -math.pi:
        torch.testing.assert_close(se2.log(A), x, atol=1e-12, rtol=0)


@SETTINGS
@given(a=tangent_st, b=tangent_st)
def test_adjoint_and_ad_identities(a, b):
    X = se2.exp(torch.tensor(a, dtype=F64))
    x, y = torch.tensor(b, dtype=F64), torch.tensor(a, dtype=F64) * 0.5
    Ad = se2.adjoint(X)
    # X exp(x) X⁻¹ = exp(Ad_X x)
    lhs = se2.compose(se2.compose(X, se2.exp(x)), se2.inverse(X))
    torch.testing.assert_close(lhs, se2.exp(_vec(Ad, x)), atol=1e-11, rtol=0)
    # ad_x y = vee([hat x, hat y])
    hx, hy = se2.hat(x), se2.hat(y)
    torch.testing.assert_close(_vec(se2.ad(x), y), se2.vee(hx @ hy - hy @ hx), atol=1e-13, rtol=0)
    # Ad_X ad_x Ad_X⁻¹ = ad_{Ad_X x}, and Ad is a homomorphism: Ad_{X⁻¹} = Ad_X⁻¹
    torch.testing.assert_close(Ad @ se2.ad(x) @ se2.adjoint(se2.inverse(X)), se2.ad(_vec(Ad, x)),
                               atol=1e-12, rtol=0)
    torch.testing.assert_close(se2.adjoint(se2.inverse(X)), torch.linalg.inv(Ad), atol=1e-12, rtol=0)


def test_jacobians_against_finite_differences_and_ad_series():
    x = _tangents(6, 3)
    z = torch.zeros(3, dtype=F64)
    for xi in x[::3]:
        X = se2.exp(xi)
        Jr = fd_jacobian(lambda d, xi=xi, X=X: se2.log(se2.compose(se2.inverse(X), se2.exp(xi + d))), z)
        Jl = fd_jacobian(lambda d, xi=xi, X=X: se2.log(se2.compose(se2.exp(xi + d), se2.inverse(X))), z)
        torch.testing.assert_close(se2.right_jacobian(xi), Jr, atol=1e-7, rtol=0)
        torch.testing.assert_close(se2.left_jacobian(xi), Jl, atol=1e-7, rtol=0)
    Jl = se2.left_jacobian(x)
    torch.testing.assert_close(Jl, _series_jl(x), atol=1e-12, rtol=0)
    torch.testing.assert_close(se2.right_jacobian(x), _series_jl(-x), atol=1e-12, rtol=0)
    # J_l = Ad_{exp x} J_r
    torch.testing.assert_close(Jl, se2.adjoint(se2.exp(x)) @ se2.right_jacobian(x), atol=1e-12, rtol=0)
    eye = torch.eye(3, dtype=F64).expand_as(Jl)
    torch.testing.assert_close(Jl @ se2.left_jacobian_inv(x), eye, atol=1e-10, rtol=0)
    torch.testing.assert_close(se2.left_jacobian_inv(x) @ Jl, eye, atol=1e-10, rtol=0)
    torch.testing.assert_close(se2.right_jacobian(x) @ se2.right_jacobian_inv(x), eye, atol=1e-10, rtol=0)


def test_float32_jacobians_keep_accuracy_at_small_angles():
    th = torch.tensor([0.0, 1e-9, 1e-6, 1e-4, 1e-3, 1e-2, 0.29, 0.31, 0.99, 1.01, 2.0, 3.1], dtype=F64)
    x = torch.stack((torch.full_like(th, 0.7), torch.full_like(th, -1.3), th), -1)
    for f in (se2.exp, se2.left_jacobian, se2.right_jacobian, se2.left_jacobian_inv, se2.right_jacobian_inv):
        ref = f(x)
        err = (f(x.float()).double() - ref).abs().max()
        assert err <= 4 * torch.finfo(torch.float32).eps * ref.abs().max(), f.__name__


def test_interpolate():
    g = torch.Generator().manual_seed(5)
    X, Y = se2.random(4, generator=g, dtype=F64), se2.random(4, generator=g, dtype=F64)
    torch.testing.assert_close(se2.interpolate(X, Y, 0.0), X, atol=1e-14, rtol=0)
    torch.testing.assert_close(se2.interpolate(X, Y, 1.0), Y, atol=1e-13, rtol=0)
    t = torch.linspace(0, 1, 5, dtype=F64).unsqueeze(-1)
    path = se2.interpolate(X, Y, t)
    assert path.shape == (5, 4, 3, 3)
    # constant twist: X⁻¹ path(t) = exp(t ξ), checked with matrix_exp of the algebra element
    xi = se2.log(se2.compose(se2.inverse(X), Y))
    ref = X @ torch.linalg.matrix_exp(t.unsqueeze(-1).unsqueeze(-1) * se2.hat(xi))
    torch.testing.assert_close(path, ref, atol=1e-12, rtol=0)


# ---------------------------------------------------------------------------------------------- gradients
def test_gradcheck_every_function_including_zero():
    g = torch.Generator().manual_seed(6)
    th = torch.tensor([0.0, 1e-9, -0.04, 0.3, -1.0, 2.0, math.pi - 1e-3, -math.pi + 1e-3], dtype=F64)
    x = torch.cat((torch.randn(8, 2, generator=g, dtype=F64), th.unsqueeze(-1)), -1).requires_grad_(True)
    X = se2.exp(x.detach()).requires_grad_(True)
    Y = se2.exp(x.detach().flip(0)).requires_grad_(True)
    p = torch.randn(8, 2, generator=g, dtype=F64).requires_grad_(True)
    t = torch.rand(4, generator=g, dtype=F64).requires_grad_(True)
    for f in (se2.exp, se2.hat, se2.ad, se2.left_jacobian, se2.left_jacobian_inv, se2.right_jacobian,
              se2.right_jacobian_inv):
        assert gradcheck(f, (x,)), f.__name__
    for f in (se2.log, se2.vee, se2.inverse, se2.adjoint):
        assert gradcheck(f, (X,)), f.__name__
    assert gradcheck(se2.compose, (X, Y))
    assert gradcheck(se2.act, (X, p))
    assert gradcheck(lambda a, b, s: se2.interpolate(a, b, s), (X[:4], Y[4:], t))


def test_gradient_exact_and_finite_at_zero_and_pi():
    th = torch.tensor([0.0, 1e-9, math.pi - 1e-9, math.pi], dtype=F64)
    x = torch.stack((torch.full_like(th, 0.5), torch.full_like(th, -2.0), th), -1)
    J = torch.func.vmap(torch.func.jacrev(lambda v: se2.log(se2.exp(v))))(x)
    torch.testing.assert_close(J, torch.eye(3, dtype=F64).expand_as(J), atol=1e-12, rtol=0)
    for f in (se2.left_jacobian, se2.left_jacobian_inv, se2.right_jacobian_inv):
        Jf = torch.func.vmap(torch.func.jacrev(f))(x)
        assert torch.isfinite(Jf).all(), f.__name__
    # at θ = 0 the θ-derivative of J_l's block [[a, −b], [b, a]] is [[0, −½], [½, 0]] (a' = 0, b' = ½)
    d = torch.func.jacrev(se2.left_jacobian)(x[0])[..., 2]
    ref = torch.tensor([[0.0, -0.5], [0.5, 0.0]], dtype=F64)
    torch.testing.assert_close(d[:2, :2], ref, atol=1e-15, rtol=0)


# ---------------------------------------------------------------------------------------------- batching
def test_batched_flattened_loop_and_broadcasting():
    g = torch.Generator().manual_seed(8)
    x = _tangents(12, 8, edges=False).reshape(3, 4, 3)
    X, Y = se2.exp(x), se2.random(3, 4, generator=g, dtype=F64)
    p = torch.randn(3, 4, 2, generator=g, dtype=F64)
    for f in (se2.exp, se2.left_jacobian, se2.right_jacobian_inv, se2.ad):
        check_batching(f, (x,), (1,), atol=1e-14)
    for f in (se2.log, se2.inverse, se2.adjoint):
        check_batching(f, (X,), (2,), atol=1e-14)
    check_batching(se2.compose, (X, Y), (2, 2), atol=1e-14)
    check_batching(se2.act, (X, p), (2, 1), atol=1e-14)
    torch.testing.assert_close(se2.compose(X[:, :1], Y), se2.compose(X[:, :1].expand(3, 4, 3, 3), Y))
    torch.testing.assert_close(se2.act(X[0, 0], p), se2.act(X[0, 0].expand(3, 4, 3, 3), p))


def test_vmap_jacrev_and_compile():
    x = _tangents(5, 9)
    torch.testing.assert_close(torch.func.vmap(se2.exp)(x), se2.exp(x), atol=0, rtol=0)
    torch.testing.assert_close(torch.func.vmap(se2.right_jacobian)(x), se2.right_jacobian(x), atol=0, rtol=0)
    # jacrev of exp at 0 is the algebra basis: ∂exp/∂x_i (0) = hat(e_i)
    J0 = torch.func.jacrev(se2.exp)(torch.zeros(3, dtype=F64))
    torch.testing.assert_close(J0.permute(2, 0, 1), se2.hat(torch.eye(3, dtype=F64)), atol=0, rtol=0)
    f = torch.compile(se2.exp, fullgraph=True, dynamic=False)
    torch.testing.assert_close(f(x), se2.exp(x), atol=1e-14, rtol=0)


# ---------------------------------------------------------------------------------------------- constructors
def test_identity_and_random():
    from scipy.stats import kstest

    assert se2.identity(2, 3).shape == (2, 3, 3, 3) and se2.identity((5,), dtype=F64).dtype == F64
    torch.testing.assert_close(se2.identity(4, dtype=F64), torch.eye(3, dtype=F64).expand(4, 3, 3))
    a = se2.random(2000, generator=torch.Generator().manual_seed(0), dtype=F64)
    assert torch.equal(a, se2.random(2000, generator=torch.Generator().manual_seed(0), dtype=F64))
    R = a[:, :2, :2]
    torch.testing.assert_close(R.transpose(-1, -2) @ R, torch.eye(2, dtype=F64).expand(2000, 2, 2),
                               atol=1e-15, rtol=0)
    torch.testing.assert_close(a[:, 2], torch.tensor([0.0, 0.0, 1.0], dtype=F64).expand(2000, 3))
    assert kstest(se2.log(a)[:, 2].numpy(), "uniform", args=(-math.pi, 2 * math.pi)).pvalue > 1e-3
    assert kstest(a[:, 0, 2].numpy(), "norm").pvalue > 1e-3
    assert kstest(a[:, 1, 2].numpy(), "norm").pvalue > 1e-3


# ---------------------------------------------------------------------------------------------- bad input
def test_bad_input_names_argument_and_shape():
    with pytest.raises(ValueError, match=r"se2.exp.*'x'.*\(\*, 3\)"):
        se2.exp(torch.zeros(4, 2))
    with pytest.raises(ValueError, match=r"'X'.*\(\*, 3, 3\)"):
        se2.log(torch.zeros(4, 2, 2))
    with pytest.raises(TypeError, match="'x'.*floating"):
        se2.left_jacobian(torch.zeros(3, dtype=torch.int32))
    with pytest.raises(ValueError, match=r"'p'.*\(\*, 2\)"):
        se2.act(se2.identity(), torch.zeros(3))
    with pytest.raises(TypeError, match="dtype"):
        se2.compose(se2.identity(dtype=F64), se2.identity(dtype=torch.float32))
    with pytest.raises(TypeError, match="not a|must be"):
        se2.exp([0.0, 0.0, 0.0])


def test_nan_stays_in_its_element():
    x = _tangents(6, 10, edges=False)
    x[2, 0] = float("nan")
    x[4, 2] = float("nan")
    bad = torch.tensor([False, False, True, False, True, False])
    for out in (se2.exp(x), se2.left_jacobian(x), se2.left_jacobian_inv(x), se2.log(se2.exp(x))):
        assert torch.isfinite(out[~bad]).all() and torch.isnan(out[bad]).any()


def test_device_follows_input_and_mismatch_is_rejected():
    m = torch.device("meta")
    cases = ((se2.exp, (4, 3)), (se2.log, (4, 3, 3)), (se2.left_jacobian_inv, (4, 3)), (se2.adjoint, (3, 3)))
    for f, shape in cases:
        assert f(torch.zeros(*shape, device=m)).device == m, f.__name__
    assert se2.random(2, device=m).device == m and se2.identity(2, device=m).device == m
    with pytest.raises(ValueError, match="'X' and 'Y' are on different devices"):
        se2.compose(torch.zeros(3, 3), torch.zeros(3, 3, device=m))
    with pytest.raises(ValueError, match="'X' and 't' are on different devices"):
        se2.interpolate(torch.zeros(3, 3), torch.zeros(3, 3), torch.zeros(1, device=m))
