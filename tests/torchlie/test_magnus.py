"""torchlie.magnus: dexp⁻¹ series and closed form, ME2 horizon predictors (seed 000 Eq. 11-17)."""

from fractions import Fraction

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torchlie import magnus, se3, so3

F64 = torch.float64
GROUPS = [pytest.param(so3, 3, id="so3"), pytest.param(se3, 6, id="se3")]


def _gen(seed=0):
    return torch.Generator().manual_seed(seed)


def _tangent(d, *batch, angle=None, seed=0, dtype=F64):
    """Random tangent vectors; the rotation part has norm ``angle`` if given."""
    g = _gen(seed)
    x = torch.randn(*batch, d, generator=g, dtype=dtype)
    if angle is not None:
        w = x[..., -3:]
        x = torch.cat([x[..., :-3], angle * w / torch.linalg.vector_norm(w, dim=-1, keepdim=True)], dim=-1)
    return x


def _G(d):
    return so3 if d == 3 else se3


# ------------------------------------------------------------------------------------------------------
# Bernoulli numbers and the series
# ------------------------------------------------------------------------------------------------------


def test_bernoulli_numbers_known_values_and_generating_function():
    B = magnus.bernoulli_numbers(12)
    assert B[:5] == (Fraction(1), Fraction(-1, 2), Fraction(1, 6), Fraction(0), Fraction(-1, 30))
    assert B[12] == Fraction(-691, 2730)
    assert all(b == 0 for b in B[3::2])
    # Σ B_n z^n / n! = z / (e^z - 1) (left) and z / (1 - e^{-z}) (right), at z = 0.7.
    z = 0.7
    cl = magnus.dexp_inv_coefficients(12, "left")
    cr = magnus.dexp_inv_coefficients(12, "right")
    assert sum(c * z**n for n, c in enumerate(cl)) == pytest.approx(z / (torch.e**z - 1), rel=1e-9)
    assert sum(c * z**n for n, c in enumerate(cr)) == pytest.approx(z / (1 - torch.e ** (-z)), rel=1e-9)
    assert cr[:3] == (1.0, 0.5, pytest.approx(1 / 12))


@pytest.mark.parametrize("G,d", GROUPS)
def test_bracket_is_matrix_commutator_and_ad(G, d):
    x, y = _tangent(d, 5, seed=1), _tangent(d, 5, seed=2)
    b = magnus.bracket(x, y)
    Xh, Yh = G.hat(x), G.hat(y)
    torch.testing.assert_close(G.hat(b), Xh @ Yh - Yh @ Xh)
    torch.testing.assert_close(b, (G.ad(x) @ y[..., None])[..., 0])


@pytest.mark.parametrize("G,d", GROUPS)
def test_dexp_inv_right_is_derivative_of_log_under_right_update(G, d):
    """Ω' = dexp⁻¹_Ω U for X = exp(Ω), X' = X U: central differences of log(exp(x) exp(h u))."""
    x, u = _tangent(d, 4, angle=2.0, seed=3), _tangent(d, 4, seed=4)
    h = 1e-6
    num = (G.log(G.exp(x) @ G.exp(h * u)) - G.log(G.exp(x) @ G.exp(-h * u))) / (2 * h)
    torch.testing.assert_close((magnus.dexp_inv(x) @ u[..., None])[..., 0], num, atol=1e-7, rtol=1e-6)
    num_l = (G.log(G.exp(h * u) @ G.exp(x)) - G.log(G.exp(-h * u) @ G.exp(x))) / (2 * h)
    torch.testing.assert_close((magnus.dexp_inv(x, side="left") @ u[..., None])[..., 0], num_l,
                               atol=1e-7, rtol=1e-6)
    # The two sides differ (they are J_r⁻¹ and J_l⁻¹), so the test above can tell them apart.
    assert (magnus.dexp_inv(x) - magnus.dexp_inv(x, side="left")).abs().max() > 0.1


@pytest.mark.parametrize("side", ["right", "left"])
@pytest.mark.parametrize("G,d", GROUPS)
def test_series_converges_to_closed_form(G, d, side):
    x = _tangent(d, 6, angle=2.5, seed=5)  # |φ| < π
    ref = magnus.dexp_inv(x, side=side)
    errs = [float((magnus.dexp_inv_series(x, n, side=side) - ref).abs().max()) for n in (0, 2, 4, 8, 16, 32)]
    assert all(b < a for a, b in zip(errs, errs[1:])), errs
    assert errs[-1] < 1e-10
    assert errs[1] > 1e-3  # ME2 alone is visibly truncated at 2.5 rad


@pytest.mark.parametrize("G,d", GROUPS)
def test_me2_series_is_eq13(G, d):
    x, u = _tangent(d, 3, seed=6), _tangent(d, 3, seed=7)
    me2 = (magnus.dexp_inv_series(x, 2) @ u[..., None])[..., 0]
    b1 = magnus.bracket(x, u)
    torch.testing.assert_close(me2, u + b1 / 2 + magnus.bracket(x, b1) / 12)
    # ME3 ≡ ME2 (B_3 = 0).
    torch.testing.assert_close(magnus.dexp_inv_series(x, 3), magnus.dexp_inv_series(x, 2))


@settings(max_examples=25, deadline=None)
@given(angle=st.floats(0.0, 3.0), seed=st.integers(0, 10_000), d=st.sampled_from([3, 6]))
def test_series_order_24_matches_closed_form_property(angle, seed, d):
    x = _tangent(d, angle=angle, seed=seed)
    torch.testing.assert_close(magnus.dexp_inv_series(x, 24), magnus.dexp_inv(x), atol=1e-6, rtol=1e-6)


def test_dexp_inv_edge_angles_finite():
    for a in (0.0, 1e-9, torch.pi - 1e-9):
        x = _tangent(6, 2, angle=a, seed=8)
        assert torch.isfinite(magnus.dexp_inv(x)).all()
        assert torch.isfinite(magnus.dexp_inv_series(x, 2)).all()
    torch.testing.assert_close(magnus.dexp_inv(torch.zeros(6, dtype=F64)), torch.eye(6, dtype=F64))


def test_gradcheck_dexp_inv_and_series():
    x = _tangent(6, 2, angle=1.3, seed=9).requires_grad_()
    assert torch.autograd.gradcheck(lambda v: magnus.dexp_inv_series(v, 4), (x,))
    assert torch.autograd.gradcheck(magnus.dexp_inv, (x,))
    w = _tangent(3, 2, angle=0.7, seed=10).requires_grad_()
    assert torch.autograd.gradcheck(lambda v: magnus.dexp_inv_series(v, 2, side="left"), (w,))


# ------------------------------------------------------------------------------------------------------
# Predictors
# ------------------------------------------------------------------------------------------------------


def _world_error(xi0, T, dt, order=2):
    X0 = se3.exp(xi0)
    X_ex = magnus.integrate_exact(X0, T, dt)
    X_pr = se3.exp(magnus.predict_world(xi0, T, dt, order))
    return (X_pr - X_ex).abs().amax(dim=(-1, -2))


@pytest.mark.parametrize("order", [2, None])
def test_world_predictor_is_first_order_accurate(order):
    """Eq. 16 linearizes at ξ_0: the error over a horizon of duration τ is O(τ²).

    With the wrong sign of the ½ term (the left-trivialized J_l⁻¹) it is only O(τ).
    """
    xi0 = _tangent(6, 8, angle=1.2, seed=11)
    T = _tangent(6, 8, 1, seed=12).expand(8, 10, 6)  # constant twist
    errs = [float(_world_error(xi0, T, tau / 10, order)[..., -1].max()) for tau in (0.2, 0.1, 0.05)]
    assert errs[0] / errs[1] > 3.3 and errs[1] / errs[2] > 3.5, errs
    wrong = []
    for tau in (0.2, 0.1, 0.05):
        M = magnus.dexp_inv_series(xi0, 2, side="left")
        xi = xi0[:, None, :] + (tau / 10) * torch.cumsum(T, dim=-2) @ M.transpose(-1, -2)
        X_ex = magnus.integrate_exact(se3.exp(xi0), T, tau / 10)
        wrong.append(float((se3.exp(xi) - X_ex)[:, -1].abs().max()))
    assert wrong[0] / wrong[1] < 2.5 and wrong[1] > 5 * errs[1], (wrong, errs)


def test_world_predictor_degrades_near_cut_locus():
    """Same twists, start rotation angle 1.0 vs π - 0.01: the world-frame prediction error grows a lot."""
    T = _tangent(6, 16, 50, seed=13) * 0.5
    far = _world_error(_tangent(6, 16, angle=1.0, seed=14), T, 1e-3).mean()
    near = _world_error(_tangent(6, 16, angle=torch.pi - 0.01, seed=14), T, 1e-3).mean()
    assert near > 5 * far


def test_linear_model_rollout_equals_predict_world():
    xi0 = _tangent(6, 3, angle=0.8, seed=15)
    T = _tangent(6, 3, 7, seed=16)
    A, B = magnus.linear_model(xi0, 0.01)
    x, xs = xi0, []
    for k in range(7):
        x = (A @ x[..., None] + B @ T[:, k, :, None])[..., 0]
        xs.append(x)
    torch.testing.assert_close(torch.stack(xs, dim=-2), magnus.predict_world(xi0, T, 0.01))
    torch.testing.assert_close(A, torch.eye(6, dtype=F64).expand(3, 6, 6))


def test_local_commuting_twists_exact():
    """Parallel twists commute: Ω_k = Δt Σ T_i and X_0 exp(Ω_k) equals the exact chain."""
    delta = _tangent(6, seed=17)
    s = torch.rand(40, dtype=F64, generator=_gen(18))
    T = s[:, None] * delta
    om = magnus.predict_local(T, 0.01)
    torch.testing.assert_close(om, 0.01 * torch.cumsum(T, dim=0))
    X0 = se3.exp(_tangent(6, angle=3.1, seed=19))
    torch.testing.assert_close(magnus.local_poses(X0, om), magnus.integrate_exact(X0, T, 0.01))


def _local_loop_reference(T, dt, order):
    """Per-sample, per-step recursion written with 6×6 matrices: Ω ← Ω + Δt dexp_inv_series(Ω) T."""
    outs = []
    for b in range(T.shape[0]):
        om = torch.zeros(T.shape[-1], dtype=T.dtype)
        seq = []
        for k in range(T.shape[1]):
            om = om + dt * magnus.dexp_inv_series(om, order) @ T[b, k]
            seq.append(om)
        outs.append(torch.stack(seq))
    return torch.stack(outs)


@pytest.mark.parametrize("order", [1, 2, 4])
def test_local_batched_equals_loop(order):
    T = _tangent(6, 3, 12, seed=20)
    torch.testing.assert_close(magnus.predict_local(T, 0.02, order), _local_loop_reference(T, 0.02, order))


def test_local_converges_to_exact_with_order_and_dt():
    """Non-commuting twists: the local recursion approaches log(X_0⁻¹ X_H) as Δt → 0 at high order, and
    ME2 is much closer than the plain sum (order 0)."""
    g = _gen(21)
    tau = 0.5
    coarse = torch.randn(4, 5, 6, generator=g, dtype=F64)

    def err(H, order):
        T = coarse.repeat_interleave(H // 5, dim=1)
        om = magnus.predict_local(T, tau / H, order)
        ref = se3.log(magnus.integrate_exact(se3.identity(4, dtype=F64), T, tau / H)[:, -1])
        return float((om[:, -1] - ref).abs().max())

    e = [err(H, 8) for H in (50, 100, 200)]
    assert e[0] / e[1] > 1.7 and e[1] / e[2] > 1.7, e  # explicit Euler: O(Δt)
    assert err(200, 2) < 0.1 * err(200, 0)


def test_local_far_better_than_world_near_cut_locus():
    X0 = se3.exp(_tangent(6, 8, angle=torch.pi - 1e-3, seed=22))
    T = _tangent(6, 8, 100, seed=23) * 0.5
    X_ex = magnus.integrate_exact(X0, T, 1e-3)
    e_w = (magnus.predict_poses(X0, T, 1e-3, "world") - X_ex).abs().max()
    e_l = (magnus.predict_poses(X0, T, 1e-3, magnus.Frame.LOCAL) - X_ex).abs().max()
    assert e_l < 1e-2 * e_w


@pytest.mark.parametrize("G,d", GROUPS)
def test_integrate_exact_matches_loop_and_constant_twist(G, d):
    X0 = G.exp(_tangent(d, 3, seed=24))
    T = _tangent(d, 3, 6, seed=25)
    out = magnus.integrate_exact(X0, T, 0.1)
    for b in range(3):
        X = X0[b]
        for k in range(6):
            X = X @ G.exp(0.1 * T[b, k])
            torch.testing.assert_close(out[b, k], X)
    c = T[:, :1].expand(3, 6, d)
    torch.testing.assert_close(magnus.integrate_exact(X0, c, 0.1)[:, -1], X0 @ G.exp(0.6 * T[:, 0]))


def test_predict_world_batched_equals_loop_and_broadcasts():
    xi0 = _tangent(6, 2, 1, angle=1.0, seed=26)
    T = _tangent(6, 3, 5, seed=27)
    out = magnus.predict_world(xi0, T, 0.01)
    assert out.shape == (2, 3, 5, 6)
    for i in range(2):
        for j in range(3):
            torch.testing.assert_close(out[i, j], magnus.predict_world(xi0[i, 0], T[j], 0.01))
    # per-robot Δt as a tensor
    dts = torch.tensor([0.01, 0.02, 0.03], dtype=F64)
    out = magnus.predict_world(xi0[0, 0].expand(3, 6), T, dts)
    for j in range(3):
        torch.testing.assert_close(out[j], magnus.predict_world(xi0[0, 0], T[j], float(dts[j])))
    om = magnus.predict_local(T, dts)
    for j in range(3):
        torch.testing.assert_close(om[j], magnus.predict_local(T[j], float(dts[j])))


def test_so3_predictors():
    w0 = _tangent(3, 4, angle=0.5, seed=28)
    T = _tangent(3, 4, 20, seed=29)
    R0 = so3.exp(w0)
    R_ex = magnus.integrate_exact(R0, T, 1e-3)
    assert R_ex.shape == (4, 20, 3, 3)
    R_w = magnus.predict_poses(R0, T, 1e-3, "world", order=None)
    R_l = magnus.predict_poses(R0, T, 1e-3, "local")
    assert (R_w - R_ex).abs().max() < 1e-3
    assert (R_l - R_ex).abs().max() < 1e-7


def test_linearize_local_matches_jacrev():
    om = _tangent(6, 2, 3, seed=30) * 0.3
    T = _tangent(6, 2, 3, seed=31)
    dt = 0.05
    A, B = magnus.linearize_local(om, T, dt, order=2)

    def step(o, u):
        return o + dt * (magnus.dexp_inv_series(o, 2) @ u[..., None])[..., 0]

    for b in range(2):
        for k in range(3):
            Ja, Jb = torch.func.jacrev(step, argnums=(0, 1))(om[b, k], T[b, k])
            torch.testing.assert_close(A[b, k], Ja)
            torch.testing.assert_close(B[b, k], Jb)


def test_gradcheck_predictors():
    xi0 = _tangent(6, 2, angle=0.9, seed=32).requires_grad_()
    T = (_tangent(6, 2, 4, seed=33) * 0.5).requires_grad_()
    assert torch.autograd.gradcheck(lambda a, b: magnus.predict_world(a, b, 0.05), (xi0, T))
    assert torch.autograd.gradcheck(lambda a, b: magnus.predict_world(a, b, 0.05, order=None), (xi0, T))
    assert torch.autograd.gradcheck(lambda b: magnus.predict_local(b, 0.05), (T,))
    X0 = se3.exp(xi0.detach()).requires_grad_()
    assert torch.autograd.gradcheck(lambda X, b: magnus.integrate_exact(X, b, 0.05), (X0, T))


def test_float32_dtype_follows_inputs():
    xi0 = _tangent(6, 5, angle=1.0, seed=34, dtype=torch.float32)
    T = _tangent(6, 5, 30, seed=35, dtype=torch.float32)
    for out in (magnus.predict_world(xi0, T, 1e-3), magnus.predict_local(T, 1e-3),
                magnus.integrate_exact(se3.exp(xi0), T, 1e-3), magnus.dexp_inv_series(xi0, 2)):
        assert out.dtype == torch.float32
    ref = magnus.predict_world(xi0.double(), T.double(), 1e-3).float()
    torch.testing.assert_close(magnus.predict_world(xi0, T, 1e-3), ref, atol=1e-5, rtol=1e-5)


def test_bad_input():
    xi0, T = torch.zeros(2, 6), torch.zeros(2, 4, 6)
    with pytest.raises(ValueError, match="'xi0'"):
        magnus.predict_world(torch.zeros(2, 5), T, 0.1)
    with pytest.raises(ValueError, match="'twists'"):
        magnus.predict_world(xi0, torch.zeros(2, 4, 3), 0.1)
    with pytest.raises(ValueError, match="'twists'"):
        magnus.predict_world(xi0, torch.zeros(6), 0.1)
    with pytest.raises(ValueError, match="'twists'"):
        magnus.predict_local(torch.zeros(2, 0, 6), 0.1)
    with pytest.raises(TypeError, match="'x'"):
        magnus.dexp_inv_series([0.0] * 6, 2)
    with pytest.raises(TypeError, match="floating"):
        magnus.dexp_inv(torch.zeros(6, dtype=torch.int64))
    with pytest.raises(ValueError, match="'order'"):
        magnus.dexp_inv_series(xi0, -1)
    with pytest.raises(ValueError, match="'side'"):
        magnus.dexp_inv(xi0, side="middle")
    with pytest.raises(ValueError, match="'dt'"):
        magnus.predict_local(T, -0.1)
    with pytest.raises(TypeError, match="'dt'"):
        magnus.predict_local(T, "0.1")
    with pytest.raises(ValueError, match="'X0'"):
        magnus.integrate_exact(torch.eye(3).expand(2, 3, 3), T, 0.1)
    with pytest.raises(ValueError, match="do not broadcast"):
        magnus.predict_world(torch.zeros(3, 6), T, 0.1)
    with pytest.raises(TypeError, match="dtypes"):
        magnus.predict_world(xi0.double(), T, 0.1)
    with pytest.raises(ValueError, match="'frame'"):
        magnus.predict_poses(torch.eye(4), T, 0.1, "sideways")
    with pytest.raises(ValueError, match="'order'"):
        magnus.predict_poses(torch.eye(4), T, 0.1, "local", order=None)
