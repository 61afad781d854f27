"""controllers.optim (seed 004 §3): gradient descent, Newton, Gauss–Newton, (constrained) least squares.

References are independent formulations: scipy.optimize.minimize / least_squares on numpy re-implementations
of the costs, numpy lstsq (with the ridge written as stacked rows), the null-space method for equality
constraints, and gradcheck in float64 for the differentiable closed forms.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.linalg
import scipy.optimize
import torch

from controllers.optim import (
    ConstrainedLSResult,
    OptimResult,
    constrained_least_squares,
    gauss_newton,
    gradient_descent,
    least_squares,
    newton,
)
from controllers.problem import Reason

F64 = torch.float64


def _gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


# --------------------------------------------------------------------------------------------------
# a smooth strictly convex test family with per-element data:
#   c_b(x) = ½ xᵀ Q_b x − q_bᵀ x + logsumexp(M_b x)
# --------------------------------------------------------------------------------------------------


def _convex_problem(B: int, n: int, k: int = 3, seed: int = 0, dtype=F64):
    g = _gen(seed)
    R = torch.randn(B, n, n, generator=g, dtype=F64)
    Q = torch.eye(n, dtype=F64) + 0.3 * R @ R.mT / n
    q = torch.randn(B, n, generator=g, dtype=F64)
    M = torch.randn(B, k, n, generator=g, dtype=F64)
    Q, q, M = Q.to(dtype), q.to(dtype), M.to(dtype)

    def f(x):
        return 0.5 * (x * (Q @ x.unsqueeze(-1)).squeeze(-1)).sum(-1) - (q * x).sum(-1) \
            + torch.logsumexp((M @ x.unsqueeze(-1)).squeeze(-1), -1)

    return f, Q, q, M


def _scipy_convex(Q, q, M, x0):
    Q, q, M = Q.double().numpy(), q.double().numpy(), M.double().numpy()

    def fun(x):
        z = M @ x
        zmax = z.max()
        lse = zmax + np.log(np.exp(z - zmax).sum())
        p = np.exp(z - lse)
        return 0.5 * x @ Q @ x - q @ x + lse, Q @ x - q + M.T @ p

    res = scipy.optimize.minimize(fun, x0, jac=True, method="BFGS", options={"gtol": 1e-12, "maxiter": 2000})
    return res.x


@pytest.mark.parametrize("solver", ["newton", "gd"])
def test_convex_batch_matches_scipy(solver):
    B, n = 5, 3
    f, Q, q, M = _convex_problem(B, n)
    x0 = torch.randn(B, n, generator=_gen(1), dtype=F64)
    if solver == "newton":
        r = newton(f, x0, tol=1e-10)
    else:
        r = gradient_descent(f, x0, tol=1e-9, max_iter=2000, step_size=0.5)
    assert isinstance(r, OptimResult)
    assert r.converged.all() and (r.reason == int(Reason.CONVERGED)).all()
    assert r.x.shape == (B, n) and r.cost.shape == (B,) and r.iterations.dtype == torch.int64
    ref = np.stack([_scipy_convex(Q[b], q[b], M[b], x0[b].numpy()) for b in range(B)])
    np.testing.assert_allclose(r.x.numpy(), ref, atol=1e-7)
    np.testing.assert_allclose(r.cost.numpy(), f(torch.from_numpy(ref)).numpy(), rtol=1e-12, atol=1e-12)
    if solver == "newton":
        assert (r.iterations <= 10).all()


def test_converged_is_checked_at_returned_x():
    f, *_ = _convex_problem(6, 4, seed=3)
    x0 = torch.randn(6, 4, generator=_gen(4), dtype=F64)
    for r, tol in ((newton(f, x0, tol=1e-6), 1e-6), (gradient_descent(f, x0, tol=1e-4, max_iter=400), 1e-4),
                   (gradient_descent(f, x0, tol=1e-8, max_iter=5), 1e-8)):
        x = r.x.clone().requires_grad_()
        (g,) = torch.autograd.grad(f(x).sum(), x)
        gn = g.norm(dim=-1)
        torch.testing.assert_close(r.grad_norm, gn, rtol=1e-10, atol=1e-14)
        assert torch.equal(r.converged, gn <= tol)
        torch.testing.assert_close(r.cost, f(r.x))


def test_newton_quadratic_one_step():
    """A quadratic with a positive-definite Hessian is solved by one Newton step (seed §3.2)."""
    f, Q, q, _ = _convex_problem(4, 3, seed=5)
    fq = lambda x: 0.5 * (x * (Q @ x.unsqueeze(-1)).squeeze(-1)).sum(-1) - (q * x).sum(-1)  # noqa: E731
    r = newton(fq, torch.zeros(4, 3, dtype=F64), tol=1e-9)
    assert r.converged.all() and (r.iterations == 1).all()
    torch.testing.assert_close(r.x, torch.linalg.solve(Q, q))


# --------------------------------------------------------------------------------------------------
# Rosenbrock
# --------------------------------------------------------------------------------------------------


def _rosenbrock(b: float = 100.0):
    return lambda x: (1 - x[..., 0]) ** 2 + b * (x[..., 1] - x[..., 0] ** 2) ** 2


STARTS = [[-1.2, 1.0], [0.0, 0.0], [2.0, 2.0], [-0.5, 1.5]]


def test_rosenbrock_newton_float64():
    r = newton(_rosenbrock(), torch.tensor(STARTS, dtype=F64), tol=1e-9)
    assert r.converged.all()
    torch.testing.assert_close(r.x, torch.ones(4, 2, dtype=F64), atol=1e-8, rtol=0)
    assert (r.iterations < 40).all()
    # scipy's Newton-CG with exact derivatives reaches the same point
    ref = scipy.optimize.minimize(scipy.optimize.rosen, np.array(STARTS[0]), jac=scipy.optimize.rosen_der,
                                  hess=scipy.optimize.rosen_hess, method="Newton-CG", options={"xtol": 1e-12})
    np.testing.assert_allclose(r.x[0].numpy(), ref.x, atol=1e-6)


def test_newton_with_supplied_derivatives_matches_autodiff():
    """Analytic Rosenbrock gradient and Hessian (Eqs. 7-8) give the same iterates as torch.func."""
    def grad(x):
        x1, x2 = x[..., 0], x[..., 1]
        return torch.stack([-2 * (1 - x1) - 400 * x1 * (x2 - x1 ** 2), 200 * (x2 - x1 ** 2)], -1)

    def hess(x):
        x1, x2 = x[..., 0], x[..., 1]
        h11 = 2 - 400 * (x2 - 3 * x1 ** 2)
        h12 = -400 * x1
        h22 = torch.full_like(x1, 200.0)
        return torch.stack([torch.stack([h11, h12], -1), torch.stack([h12, h22], -1)], -2)

    x0 = torch.tensor(STARTS, dtype=F64)
    auto = newton(_rosenbrock(), x0, tol=1e-9)
    given = newton(_rosenbrock(), x0, tol=1e-9, gradient=grad, hessian=hess)
    half = newton(_rosenbrock(), x0, tol=1e-9, gradient=grad)  # Hessian by torch.func through `grad`
    for r in (given, half):
        assert r.converged.all() and torch.equal(r.iterations, auto.iterations)
        torch.testing.assert_close(r.x, auto.x, atol=1e-12, rtol=0)


def test_rosenbrock_gradient_descent_is_slower_than_newton():
    f = _rosenbrock(5.0)  # a milder valley (b = 5) keeps the first-order run short (~700 steps)
    x0 = torch.tensor(STARTS, dtype=F64)
    gd = gradient_descent(f, x0, tol=1e-6, max_iter=5000)
    nt = newton(f, x0, tol=1e-6)
    assert gd.converged.all() and nt.converged.all()
    torch.testing.assert_close(gd.x, torch.ones(4, 2, dtype=F64), atol=1e-5, rtol=0)
    torch.testing.assert_close(nt.x, torch.ones(4, 2, dtype=F64), atol=1e-6, rtol=0)
    assert (nt.iterations * 10 < gd.iterations).all()


def test_rosenbrock_float32():
    x0 = torch.tensor(STARTS, dtype=torch.float32)
    r = newton(_rosenbrock(), x0, tol=1e-3)
    assert r.x.dtype == torch.float32 and r.cost.dtype == torch.float32
    assert r.converged.all()
    torch.testing.assert_close(r.x, torch.ones(4, 2), atol=2e-3, rtol=0)
    g = gradient_descent(_rosenbrock(5.0), x0[:2], tol=1e-3, max_iter=3000)
    assert g.x.dtype == torch.float32 and g.converged.all()
    torch.testing.assert_close(g.x, torch.ones(2, 2), atol=5e-3, rtol=0)


# --------------------------------------------------------------------------------------------------
# per-element status
# --------------------------------------------------------------------------------------------------


def test_nan_element_does_not_poison_batch():
    f, *_ = _convex_problem(4, 3, seed=7)
    x0 = torch.randn(4, 3, generator=_gen(8), dtype=F64)
    clean_n, clean_g = newton(f, x0), gradient_descent(f, x0, tol=1e-6, step_size=0.5)
    bad = x0.clone()
    bad[2, 1] = float("nan")
    for clean, r in ((clean_n, newton(f, bad)), (clean_g, gradient_descent(f, bad, tol=1e-6, step_size=0.5))):
        keep = torch.tensor([0, 1, 3])
        assert r.reason[2] == int(Reason.NONFINITE_INPUT) and not r.converged[2] and r.iterations[2] == 0
        assert torch.isnan(r.x[2, 1])
        torch.testing.assert_close(r.x[keep], clean.x[keep])
        assert torch.equal(r.iterations[keep], clean.iterations[keep]) and r.converged[keep].all()


def test_nan_in_element_data_is_diverged_and_isolated():
    """NaN data of one element (closure) makes its cost NaN: DIVERGED there, the others unchanged."""
    t = torch.linspace(0, 1, 6, dtype=F64).expand(3, 6).clone()
    y = torch.randn(3, 6, generator=_gen(9), dtype=F64)
    y_bad = y.clone()
    y_bad[1, 2] = float("nan")

    def res(y_):
        return lambda p: p[..., :1] + p[..., 1:2] * t - y_

    x0 = torch.zeros(3, 2, dtype=F64)
    ok, r = gauss_newton(res(y), x0), gauss_newton(res(y_bad), x0)
    assert r.reason.tolist() == [0, int(Reason.DIVERGED), 0]
    torch.testing.assert_close(r.x[[0, 2]], ok.x[[0, 2]])


def test_saddle_is_not_a_minimum():
    f = lambda x: x[..., 0] ** 2 - x[..., 1] ** 2 + x[..., 1] ** 4  # noqa: E731
    x0 = torch.tensor([[0.5, 0.0], [0.5, 0.3]], dtype=F64)
    r = newton(f, x0, tol=1e-10)
    assert r.reason.tolist() == [int(Reason.NOT_A_MINIMUM), int(Reason.CONVERGED)]
    assert r.converged.tolist() == [False, True]
    torch.testing.assert_close(r.x[1], torch.tensor([0.0, 0.5 ** 0.5], dtype=F64))


def test_line_search_failure_and_max_iterations():
    f = _rosenbrock()
    x0 = torch.tensor(STARTS, dtype=F64)
    r = newton(f, x0, max_iter=2)
    assert (r.reason == int(Reason.MAX_ITERATIONS)).all() and not r.converged.any()
    assert (r.iterations == 2).all()
    # a wrong (ascent) gradient: no step length decreases the cost
    up = gradient_descent(lambda x: (x ** 2).sum(-1), x0 + 1, gradient=lambda x: -2 * x)
    assert (up.reason == int(Reason.LINE_SEARCH_FAILED)).all() and not up.converged.any()
    torch.testing.assert_close(up.x, x0 + 1)
    # fixed step too long: the iterates blow up
    div = gradient_descent(lambda x: (x ** 2).sum(-1), x0 + 1, step_size=10.0, line_search=False,
                           max_iter=2000)
    assert (div.reason == int(Reason.DIVERGED)).all() and not div.converged.any()
    assert (~torch.isfinite(div.cost) | ~torch.isfinite(div.grad_norm)).all()
    ok = gradient_descent(lambda x: (x ** 2).sum(-1), x0, step_size=0.25, line_search=False, tol=1e-10)
    assert ok.converged.all()


def test_line_search_does_not_bounce_between_equal_costs():
    """From 0, the full gradient step on (x − 1)² lands at 2, the same cost: a strict decrease is required
    there (the halved step reaches the minimum), else the iterates would bounce between 0 and 2."""
    x0 = torch.zeros(2, 3, dtype=F64)
    r = gradient_descent(lambda x: ((x - 1) ** 2).sum(-1), x0, max_iter=20)
    assert r.converged.all() and (r.iterations == 1).all()
    torch.testing.assert_close(r.x, torch.ones(2, 3, dtype=F64))


def test_converged_elements_stop_moving():
    """An element converged at x0 is returned untouched with 0 iterations while the others iterate."""
    f, Q, q, _ = _convex_problem(3, 3, seed=11)
    x0 = torch.randn(3, 3, generator=_gen(12), dtype=F64)
    sol = newton(f, x0, tol=1e-12).x
    x0[1] = sol[1]
    r = newton(f, x0, tol=1e-6)
    assert r.iterations[1] == 0 and r.iterations[0] > 0
    assert torch.equal(r.x[1], x0[1])


# --------------------------------------------------------------------------------------------------
# batching
# --------------------------------------------------------------------------------------------------


def test_batched_equals_per_sample_loop_and_multi_dims():
    B, n = 6, 3
    f, Q, q, M = _convex_problem(B, n, seed=13)
    x0 = torch.randn(B, n, generator=_gen(14), dtype=F64)
    r = newton(f, x0)
    for b in range(B):
        fb = lambda x, b=b: 0.5 * x @ Q[b] @ x - q[b] @ x + torch.logsumexp(M[b] @ x, -1)  # noqa: E731
        rb = newton(fb, x0[b])  # unbatched x0 (n,)
        assert rb.x.shape == (n,) and rb.converged.shape == ()
        torch.testing.assert_close(rb.x, r.x[b], rtol=0, atol=1e-12)
        assert int(rb.iterations) == int(r.iterations[b])
    # two batch dims: the same problems as (2, 3)
    f2, *_ = _convex_problem(B, n, seed=13)
    r2 = newton(lambda x: f2(x.reshape(B, n)).reshape(2, 3), x0.reshape(2, 3, n))
    assert r2.x.shape == (2, 3, n) and r2.reason.shape == (2, 3)
    torch.testing.assert_close(r2.x.reshape(B, n), r.x)


# --------------------------------------------------------------------------------------------------
# Gauss–Newton: curve fitting against scipy.optimize.least_squares
# --------------------------------------------------------------------------------------------------


def _curve_data(B: int, m: int = 25, seed: int = 20):
    g = _gen(seed)
    t = torch.linspace(0.0, 3.0, m, dtype=F64)
    p_true = torch.stack([1.0 + torch.rand(B, generator=g, dtype=F64),
                          0.5 + torch.rand(B, generator=g, dtype=F64),
                          torch.rand(B, generator=g, dtype=F64) - 0.5], -1)
    y = p_true[:, :1] * torch.exp(-p_true[:, 1:2] * t) + p_true[:, 2:] \
        + 0.02 * torch.randn(B, m, generator=g, dtype=F64)
    return t, y, p_true


def _model(t, p):
    return p[..., :1] * torch.exp(-p[..., 1:2] * t) + p[..., 2:]


@pytest.mark.parametrize("weighted", [False, True])
def test_gauss_newton_curve_fit_matches_scipy(weighted):
    B = 4
    t, y, p_true = _curve_data(B)
    w = 0.5 + torch.rand(B, t.shape[0], generator=_gen(21), dtype=F64)
    W = torch.diag_embed(w) if weighted else None
    p0 = torch.tensor([1.0, 1.0, 0.0], dtype=F64).expand(B, 3)
    r = gauss_newton(lambda p: _model(t, p) - y, p0, weights=W, tol=1e-10)
    assert r.converged.all()
    tn, yn = t.numpy(), y.numpy()
    for b in range(B):
        sw = np.sqrt(w[b].numpy()) if weighted else np.ones_like(tn)

        def fun(p, sw=sw, yb=yn[b]):
            return sw * (p[0] * np.exp(-p[1] * tn) + p[2] - yb)

        ref = scipy.optimize.least_squares(fun, p0[b].numpy(), method="lm", xtol=1e-15, ftol=1e-15,
                                           gtol=1e-15)
        np.testing.assert_allclose(r.x[b].numpy(), ref.x, atol=1e-8)
        np.testing.assert_allclose(float(r.cost[b]), 2 * ref.cost, rtol=1e-10)  # scipy: ½‖f‖²
    assert (r.x - p_true).abs().max() < 0.2


def test_gauss_newton_options_and_jacobian():
    B = 3
    t, y, _ = _curve_data(B, seed=22)
    p0 = torch.tensor([1.0, 1.0, 0.0], dtype=F64).expand(B, 3)
    res = lambda p: _model(t, p) - y  # noqa: E731

    def jac(p):
        e = torch.exp(-p[..., 1:2] * t)
        return torch.stack([e, -p[..., :1] * t * e, torch.ones_like(e)], -1)

    base = gauss_newton(res, p0, tol=1e-10)
    for r in (gauss_newton(res, p0, tol=1e-10, jacobian=jac),
              gauss_newton(res, p0, tol=1e-10, damping=1e-2),
              gauss_newton(res, p0, tol=1e-10, weights=torch.eye(t.shape[0], dtype=F64)),  # shared W
              gauss_newton(res, p0, tol=1e-10, line_search=False)):
        assert r.converged.all()
        torch.testing.assert_close(r.x, base.x, atol=1e-9, rtol=0)
    # a residual with fewer outputs than unknowns (forward-mode Jacobian branch taken for r > n above)
    under = gauss_newton(lambda x: (x ** 2).sum(-1, keepdim=True) - 1.0,
                         torch.tensor([[2.0, 1.0, 0.5]], dtype=F64))
    assert under.converged.all()
    torch.testing.assert_close((under.x ** 2).sum(-1), torch.ones(1, dtype=F64))


def test_gauss_newton_linear_residual_is_least_squares_in_one_step():
    """§3.4: with f = Ax − b, one Gauss–Newton step from any x0 is A†b."""
    g = _gen(23)
    A = torch.randn(3, 6, 4, generator=g, dtype=F64)
    b = torch.randn(3, 6, generator=g, dtype=F64)
    x0 = torch.randn(3, 4, generator=g, dtype=F64)
    r = gauss_newton(lambda x: (A @ x.unsqueeze(-1)).squeeze(-1) - b, x0, tol=1e-9)
    assert r.converged.all() and (r.iterations == 1).all()
    torch.testing.assert_close(r.x, least_squares(A, b))


def test_gauss_newton_float32():
    t, y, _ = _curve_data(3, seed=24)
    t32, y32 = t.float(), y.float()
    r = gauss_newton(lambda p: _model(t32, p) - y32, torch.tensor([1.0, 1.0, 0.0]).expand(3, 3), tol=1e-4)
    r64 = gauss_newton(lambda p: _model(t, p) - y, torch.tensor([1.0, 1.0, 0.0], dtype=F64).expand(3, 3))
    assert r.x.dtype == torch.float32 and r.converged.all()
    torch.testing.assert_close(r.x.double(), r64.x, atol=1e-4, rtol=0)


# --------------------------------------------------------------------------------------------------
# least squares (§3.4)
# --------------------------------------------------------------------------------------------------


def _ls_data(B=4, m=7, n=4, seed=30):
    g = _gen(seed)
    return torch.randn(B, m, n, generator=g, dtype=F64), torch.randn(B, m, generator=g, dtype=F64)


def test_least_squares_matches_numpy():
    A, b = _ls_data()
    x = least_squares(A, b)
    for k in range(A.shape[0]):
        ref = np.linalg.lstsq(A[k].numpy(), b[k].numpy(), rcond=None)[0]
        np.testing.assert_allclose(x[k].numpy(), ref, atol=1e-12)
    # under-determined: the minimum-norm solution, as numpy
    Aw, bw = _ls_data(m=3, n=5, seed=31)
    xw = least_squares(Aw, bw)
    ref = np.stack([np.linalg.lstsq(Aw[k].numpy(), bw[k].numpy(), rcond=None)[0] for k in range(4)])
    np.testing.assert_allclose(xw.numpy(), ref, atol=1e-12)


def test_ridge_and_weighted_match_stacked_lstsq():
    A, b = _ls_data(seed=32)
    B, m, n = A.shape
    w = 0.1 + torch.rand(B, m, generator=_gen(33), dtype=F64)
    alpha = torch.tensor([0.0, 0.1, 1.0, 5.0], dtype=F64)
    x_r = least_squares(A, b, ridge=alpha)
    x_w = least_squares(A, b, weights=torch.diag_embed(w))
    x_wr = least_squares(A, b, ridge=0.7, weights=torch.diag_embed(w))
    for k in range(B):
        An, bn, wn = A[k].numpy(), b[k].numpy(), np.sqrt(w[k].numpy())
        # Eq. 13: ‖Ax − b‖² + α‖x‖² = ‖[A; √α I] x − [b; 0]‖²
        ref_r = np.linalg.lstsq(np.vstack([An, np.sqrt(float(alpha[k])) * np.eye(n)]),
                                np.concatenate([bn, np.zeros(n)]), rcond=None)[0]
        ref_w = np.linalg.lstsq(wn[:, None] * An, wn * bn, rcond=None)[0]  # Eq. 14
        ref_wr = np.linalg.lstsq(np.vstack([wn[:, None] * An, np.sqrt(0.7) * np.eye(n)]),
                                 np.concatenate([wn * bn, np.zeros(n)]), rcond=None)[0]  # Eq. 15
        np.testing.assert_allclose(x_r[k].numpy(), ref_r, atol=1e-12)
        np.testing.assert_allclose(x_w[k].numpy(), ref_w, atol=1e-12)
        np.testing.assert_allclose(x_wr[k].numpy(), ref_wr, atol=1e-12)
    # a full (non-diagonal) SPD weight: ‖L^T (Ax − b)‖² with W = L Lᵀ
    R = torch.randn(m, m, generator=_gen(34), dtype=F64)
    W = R @ R.T + 0.1 * torch.eye(m, dtype=F64)
    L = torch.linalg.cholesky(W)
    torch.testing.assert_close(least_squares(A, b, weights=W),
                               least_squares(L.mT @ A, (L.mT @ b.unsqueeze(-1))[..., 0]))


def test_zero_weight_block_is_eq16():
    """Eq. (16): W = blockdiag(W1, 0) gives the estimate of the first block alone."""
    A, b = _ls_data(m=9, n=3, seed=35)
    w = torch.cat([torch.ones(4, dtype=F64) * 2.0, torch.zeros(5, dtype=F64)])
    for ridge in (0.0, 0.3):
        x = least_squares(A, b, ridge=ridge, weights=torch.diag(w))
        torch.testing.assert_close(x, least_squares(A[:, :4], b[:, :4], ridge=ridge / 2.0))


def test_least_squares_broadcast_nan_and_float32():
    A, b = _ls_data(seed=36)
    x = least_squares(A[0], b)  # a shared A against a batch of b
    torch.testing.assert_close(x, least_squares(A[0].expand_as(A), b))
    Ab = A.clone()
    Ab[1, 0, 0] = float("nan")
    for kw in ({}, {"ridge": 0.1}, {"weights": torch.eye(7, dtype=F64)}):
        xb, xc = least_squares(Ab, b, **kw), least_squares(A, b, **kw)
        assert torch.isnan(xb[1]).all()
        torch.testing.assert_close(xb[[0, 2, 3]], xc[[0, 2, 3]])
    x32 = least_squares(A.float(), b.float(), ridge=0.1)
    assert x32.dtype == torch.float32
    torch.testing.assert_close(x32.double(), least_squares(A, b, ridge=0.1), atol=1e-5, rtol=1e-5)


def test_least_squares_gradcheck():
    A, b = _ls_data(B=2, m=5, n=3, seed=37)
    w = (0.5 + torch.rand(2, 5, generator=_gen(38), dtype=F64))
    A.requires_grad_()
    b.requires_grad_()
    W = torch.diag_embed(w).requires_grad_()
    alpha = torch.tensor([0.2, 0.5], dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda A_, b_: least_squares(A_, b_), (A, b))
    assert torch.autograd.gradcheck(lambda A_, b_, a_: least_squares(A_, b_, ridge=a_), (A, b, alpha))
    assert torch.autograd.gradcheck(lambda A_, b_, W_: least_squares(A_, b_, weights=W_), (A, b, W))
    assert torch.autograd.gradcheck(lambda A_, b_, W_: least_squares(A_, b_, ridge=0.3, weights=W_),
                                    (A, b, W))


# --------------------------------------------------------------------------------------------------
# constrained least squares (§3.5)
# --------------------------------------------------------------------------------------------------


def _cls_data(B=4, m=6, n=5, p=2, seed=40):
    g = _gen(seed)
    A, b = _ls_data(B, m, n, seed)
    C = torch.randn(B, p, n, generator=g, dtype=F64)
    d = torch.randn(B, p, generator=g, dtype=F64)
    return A, b, C, d


def _nullspace_reference(A, b, C, d, w=None):
    """x = x_p + N z with C x_p = d, N spanning null(C), z the (weighted) LS fit: a different formulation."""
    sw = np.ones(A.shape[0]) if w is None else np.sqrt(w)
    xp = np.linalg.lstsq(C, d, rcond=None)[0]
    N = scipy.linalg.null_space(C)
    z = np.linalg.lstsq(sw[:, None] * (A @ N), sw * (b - A @ xp), rcond=None)[0]
    return xp + N @ z


@pytest.mark.parametrize("weighted", [False, True])
def test_constrained_matches_nullspace_method(weighted):
    A, b, C, d = _cls_data()
    w = 0.2 + torch.rand(4, 6, generator=_gen(41), dtype=F64)
    res = constrained_least_squares(A, b, C, d, weights=torch.diag_embed(w) if weighted else None)
    assert isinstance(res, ConstrainedLSResult) and res.x.shape == (4, 5) and res.multiplier.shape == (4, 2)
    torch.testing.assert_close((C @ res.x.unsqueeze(-1)).squeeze(-1), d, atol=1e-12, rtol=0)
    for k in range(4):
        ref = _nullspace_reference(A[k].numpy(), b[k].numpy(), C[k].numpy(), d[k].numpy(),
                                   w[k].numpy() if weighted else None)
        np.testing.assert_allclose(res.x[k].numpy(), ref, atol=1e-11)
    # stationarity of the seed's Lagrangian: AᵀW(Ax − b) + Cᵀλ = 0
    Wm = torch.diag_embed(w) if weighted else torch.eye(6, dtype=F64)
    r = (A.mT @ Wm @ ((A @ res.x.unsqueeze(-1)).squeeze(-1) - b).unsqueeze(-1)).squeeze(-1)
    torch.testing.assert_close(r + (C.mT @ res.multiplier.unsqueeze(-1)).squeeze(-1),
                               torch.zeros(4, 5, dtype=F64), atol=1e-11, rtol=0)


def test_constrained_batched_loop_nan_singular_float32():
    A, b, C, d = _cls_data(seed=42)
    res = constrained_least_squares(A, b, C, d)
    for k in range(4):
        rk = constrained_least_squares(A[k], b[k], C[k], d[k])
        torch.testing.assert_close(rk.x, res.x[k], atol=1e-13, rtol=0)
    # a shared constraint broadcast against batched A, b
    rs = constrained_least_squares(A, b, C[0], d[0])
    torch.testing.assert_close(rs.x, constrained_least_squares(A, b, C[0].expand_as(C), d[0].expand_as(d)).x)
    Cb, Ab = C.clone(), A.clone()
    Cb[1] = 0.0  # rank-deficient constraint: singular KKT
    Ab[2, 0, 0] = float("nan")
    bad = constrained_least_squares(Ab, b, Cb, d)
    assert torch.isnan(bad.x[1]).all() and torch.isnan(bad.x[2]).all()
    torch.testing.assert_close(bad.x[[0, 3]], res.x[[0, 3]])
    r32 = constrained_least_squares(A.float(), b.float(), C.float(), d.float())
    assert r32.x.dtype == torch.float32
    torch.testing.assert_close(r32.x.double(), res.x, atol=1e-4, rtol=1e-4)


def test_constrained_gradcheck():
    A, b, C, d = _cls_data(B=2, m=5, n=4, p=2, seed=43)
    W = torch.diag_embed(0.5 + torch.rand(2, 5, generator=_gen(44), dtype=F64))
    args = tuple(t.requires_grad_() for t in (A, b, C, d, W))
    assert torch.autograd.gradcheck(lambda *a: constrained_least_squares(*a[:4], weights=a[4]), args)
    assert torch.autograd.gradcheck(lambda *a: constrained_least_squares(*a[:4]).multiplier, args[:4])


# --------------------------------------------------------------------------------------------------
# bad input
# --------------------------------------------------------------------------------------------------


def _sq(x):
    return (x ** 2).sum(-1)


X0 = torch.zeros(2, 3, dtype=F64)
I3, Z3 = torch.eye(3, dtype=F64), torch.zeros(3, dtype=F64)


def _z(*shape):
    return torch.zeros(*shape, dtype=F64)


@pytest.mark.parametrize("call, exc, word", [
    (lambda: newton("f", X0), TypeError, "'f'"),
    (lambda: newton(_sq, [0.0, 1.0]), TypeError, "'x0'"),
    (lambda: newton(_sq, torch.zeros(2, 3, dtype=torch.int64)), TypeError, "'x0'"),
    (lambda: newton(_sq, torch.zeros((), dtype=F64)), ValueError, "'x0'"),
    (lambda: newton(_sq, X0, tol=0.0), ValueError, "'tol'"),
    (lambda: newton(_sq, X0, tol=float("nan")), ValueError, "'tol'"),
    (lambda: newton(_sq, X0, max_iter=0), ValueError, "'max_iter'"),
    (lambda: newton(_sq, X0, max_iter=2.5), TypeError, "'max_iter'"),
    (lambda: newton(_sq, X0, max_iter=True), TypeError, "'max_iter'"),
    (lambda: newton(_sq, X0, hessian=3), TypeError, "'hessian'"),
    (lambda: newton(_sq, X0, hessian=lambda x: x), ValueError, "'hessian'"),
    (lambda: newton(_sq, X0, min_curvature=-1.0), ValueError, "'min_curvature'"),
    (lambda: newton(lambda x: x, X0), ValueError, "'f'"),
    (lambda: newton(lambda x: _sq(x).float(), X0), TypeError, "'f'"),
    (lambda: gradient_descent(_sq, X0, step_size=0.0), ValueError, "'step_size'"),
    (lambda: gradient_descent(_sq, X0, alpha_min=2.0), ValueError, "'alpha_min'"),
    (lambda: gradient_descent(_sq, X0, line_search=1), TypeError, "'line_search'"),
    (lambda: gradient_descent(_sq, X0, gradient=lambda x: x[..., :2]), ValueError, "'gradient'"),
    (lambda: gauss_newton(None, X0), TypeError, "'residual'"),
    (lambda: gauss_newton(lambda x: x.sum(-1), X0), ValueError, "'residual'"),
    (lambda: gauss_newton(lambda x: x, X0, weights=torch.eye(2, dtype=F64)), ValueError, "'weights'"),
    (lambda: gauss_newton(lambda x: x, X0, weights=torch.eye(3)), TypeError, "'weights'"),
    (lambda: gauss_newton(lambda x: x, X0, weights=torch.eye(3, dtype=F64).expand(4, 3, 3)), ValueError,
     "'weights'"),
    (lambda: gauss_newton(lambda x: x, X0, damping=-1.0), ValueError, "'damping'"),
    (lambda: gauss_newton(lambda x: x, X0, jacobian=lambda x: x), ValueError, "'jacobian'"),
    (lambda: least_squares(np.eye(3), torch.zeros(3)), TypeError, "'A'"),
    (lambda: least_squares(torch.eye(3, dtype=F64), torch.zeros(4, dtype=F64)), ValueError, "'b'"),
    (lambda: least_squares(torch.eye(3, dtype=F64), torch.zeros(3)), TypeError, "'b'"),
    (lambda: least_squares(I3, Z3, ridge=-0.1), ValueError, "'ridge'"),
    (lambda: least_squares(I3, Z3, ridge="a"), TypeError, "'ridge'"),
    (lambda: least_squares(I3, Z3, weights=torch.eye(2, dtype=F64)),
     ValueError, "'weights'"),
    (lambda: least_squares(torch.zeros(2, 3, 3, dtype=F64), torch.zeros(4, 3, dtype=F64)), ValueError, "'b'"),
    (lambda: constrained_least_squares(I3, Z3, _z(1, 2), _z(1)), ValueError, "'C'"),
    (lambda: constrained_least_squares(I3, Z3, _z(1, 3), _z(2)), ValueError, "'d'"),
    (lambda: constrained_least_squares(I3, Z3, _z(4, 3), _z(4)), ValueError, "'C'"),
    (lambda: constrained_least_squares(I3, Z3, "C", _z(1)), TypeError, "'C'"),
])
def test_bad_input(call, exc, word):
    with pytest.raises(exc, match=word):
        call()


# --------------------------------------------------------------------------------------------------
# regressions: conditioning, ridge zeros, rank-deficient constraints, float32 tolerances
# --------------------------------------------------------------------------------------------------


def _mp_lstsq(A: torch.Tensor, b: torch.Tensor) -> np.ndarray:
    """The exact least-squares solution of the stored float64 data (full column rank), in 60 digits."""
    import mpmath

    with mpmath.workdps(60):
        Am, bm = mpmath.matrix(A.tolist()), mpmath.matrix(b.tolist())
        x = mpmath.lu_solve(Am.T * Am, Am.T * bm)
        return np.array([float(v) for v in x])


def test_weighted_least_squares_does_not_square_the_condition_number():
    A = torch.tensor([[1.0, 0.0], [0.0, 1e-8], [0.0, 0.0]], dtype=F64)
    b = torch.tensor([1.0, 1e-8, 0.0], dtype=F64)
    one = torch.ones(2, dtype=F64)
    torch.testing.assert_close(least_squares(A, b), one, atol=1e-12, rtol=0)
    torch.testing.assert_close(least_squares(A, b, weights=torch.eye(3, dtype=F64)), one, atol=1e-12, rtol=0)
    torch.testing.assert_close(least_squares(A, b, ridge=torch.zeros((), dtype=F64)), one, atol=1e-12, rtol=0)
    # cond(A) = 1e6 .. 1e10 with a diagonal W: as accurate as numpy's lstsq of √W A (vs a 60-digit reference)
    g = _gen(90)
    U, _ = torch.linalg.qr(torch.randn(8, 8, generator=g, dtype=F64))
    V, _ = torch.linalg.qr(torch.randn(4, 4, generator=g, dtype=F64))
    for cond in (1e6, 1e8, 1e10):
        s = torch.logspace(0, -math.log10(cond), 4, dtype=F64)
        A = U[:, :4] @ torch.diag(s) @ V.T
        b = A @ torch.randn(4, generator=g, dtype=F64) + 1e-3 * torch.randn(8, generator=g, dtype=F64)
        w = 0.5 + torch.rand(8, generator=g, dtype=F64)
        Aw, bw = w.sqrt()[:, None] * A, w.sqrt() * b
        ref = _mp_lstsq(Aw, bw)
        err_np = np.abs(np.linalg.lstsq(Aw.numpy(), bw.numpy(), rcond=None)[0] - ref).max()
        for x in (least_squares(A, b, weights=torch.diag(w)),
                  least_squares(Aw, bw, weights=torch.eye(8, dtype=F64))):
            err = np.abs(x.numpy() - ref).max()
            assert err <= max(1e-8, 10 * err_np) * np.abs(ref).max(), (cond, err, err_np)


def test_tensor_ridge_with_zeros_is_the_pseudoinverse():
    A = torch.tensor([[1.0, 1.0], [2.0, 2.0], [3.0, 3.0]], dtype=F64)  # rank 1
    b = torch.tensor([1.0, 2.0, 3.5], dtype=F64)
    alpha = torch.tensor([0.0, 1e-300, 0.5, float("nan")], dtype=F64)
    x = least_squares(A, b, ridge=alpha)
    ref0 = np.linalg.lstsq(A.numpy(), b.numpy(), rcond=None)[0]
    ref_r = np.linalg.lstsq(np.vstack([A.numpy(), np.sqrt(0.5) * np.eye(2)]), np.r_[b.numpy(), 0, 0],
                            rcond=None)[0]
    np.testing.assert_allclose(x[0].numpy(), ref0, atol=1e-12)
    np.testing.assert_allclose(x[1].numpy(), ref0, atol=1e-12)
    np.testing.assert_allclose(x[2].numpy(), ref_r, atol=1e-12)
    assert torch.isnan(x[3]).all()
    torch.testing.assert_close(least_squares(A, b, ridge=0.0), x[0])
    # the same with a singular PSD weight (Eq. 16) and a zero ridge entry
    W = torch.diag(torch.tensor([1.0, 1.0, 0.0], dtype=F64))
    xw = least_squares(A, b, ridge=alpha[:3], weights=W)
    np.testing.assert_allclose(xw[0].numpy(), np.linalg.lstsq(A[:2].numpy(), b[:2].numpy(), rcond=None)[0],
                               atol=1e-12)
    # a weight that is not PSD gives NaN for its element only
    Wb = torch.stack([torch.eye(3, dtype=F64), -torch.eye(3, dtype=F64)])
    xb = least_squares(A, b, ridge=0.1, weights=Wb)
    assert torch.isfinite(xb[0]).all() and torch.isnan(xb[1]).all()


def test_constrained_nearly_rank_deficient_constraint_is_nan():
    A, b, C, d = _cls_data(B=3, m=6, n=4, p=2, seed=98)
    good = constrained_least_squares(A, b, C, d)
    Cb, db = C.clone(), d.clone()
    Cb[1] = torch.tensor([[0.1, 0.2, 0.3, 0.4], [0.3, 0.6, 0.9, 1.2]], dtype=F64)  # rank 1 up to rounding
    db[1] = torch.tensor([1.0, 2.9], dtype=F64)  # inconsistent: no x satisfies Cx = d
    res = constrained_least_squares(A, b, Cb, db)
    assert torch.isnan(res.x[1]).all() and torch.isnan(res.multiplier[1]).all()
    torch.testing.assert_close(res.x[[0, 2]], good.x[[0, 2]])
    torch.testing.assert_close(res.multiplier[[0, 2]], good.multiplier[[0, 2]])
    # A singular on the null space of C (up to rounding): the minimizer is not unique
    A0 = (0.1 * torch.arange(1.0, 7.0, dtype=F64))[:, None] * torch.tensor([0.1, 0.3, 0.7, 0.2], dtype=F64)
    r0 = constrained_least_squares(A0, b[0], C[0, :1], d[0, :1])
    assert torch.isnan(r0.x).all()


def test_gauss_newton_float32_unbatched_tall_residual():
    def res(x):
        return torch.stack([x[..., 0] - 2.0, x[..., 1] - 1.0, x[..., 0] * x[..., 1] - 2.0], -1)

    r32 = gauss_newton(res, torch.ones(2))
    r64 = gauss_newton(res, torch.ones(2, dtype=F64))
    assert r32.x.dtype == torch.float32 and bool(r32.converged) and bool(r64.converged)
    torch.testing.assert_close(r32.x.double(), r64.x, atol=1e-5, rtol=0)
    ref = scipy.optimize.least_squares(lambda v: res(torch.tensor(v)).numpy(), np.ones(2), xtol=1e-15,
                                       ftol=1e-15, gtol=1e-15).x
    np.testing.assert_allclose(r64.x.numpy(), ref, atol=1e-8)


def test_default_tolerance_follows_dtype():
    q = torch.tensor([3.0, -2.0])
    h = torch.tensor([1.0, 10.0])

    def quad(x):  # scaled so that float32 cannot resolve ‖g‖ ≤ 1e-8 near the minimizer
        return 1e3 * (((x - q.to(x.dtype)) ** 2) * h.to(x.dtype)).sum(-1) + torch.exp(x.sum(-1) / 8)

    def res(x):
        return torch.stack([x[..., 0] - 3.0, 10 * (x[..., 1] - x[..., 0] ** 2 / 9), 0.1 * x[..., 0]], -1)

    def res_cost(x):
        return (res(x) ** 2).sum(-1)

    x0 = torch.tensor([[0.0, 0.0], [1.0, 2.0]])
    for dtype in (torch.float32, F64):
        for name, r, c, tau in (
                ("newton", newton(quad, x0.to(dtype)), quad, 1e-8),
                ("gradient_descent",
                 gradient_descent(quad, x0.to(dtype), step_size=1e-3, max_iter=5000), quad, 1e-6),
                ("gauss_newton", gauss_newton(res, x0.to(dtype)), res_cost, 1e-8)):
            tau = 1e-4 if dtype == torch.float32 else tau
            assert r.converged.all(), (name, dtype, r.reason_names(), r.grad_norm)
            # the documented rule: ‖g(x)‖ ≤ τ max(1, ‖g(x0)‖), g by autograd in float64
            x0d = x0.clone().requires_grad_()
            g0 = torch.autograd.grad(c(x0d).sum(), x0d)[0].norm(dim=-1)
            bound = tau * g0.clamp_min(1.0)
            assert (r.grad_norm.double() <= bound).all(), (name, dtype, r.grad_norm, bound)
            ref = newton(c, x0.double(), tol=1e-12)
            assert ref.converged.all()
            # ‖x − x*‖ ≤ ‖g(x)‖ / λ_min(H) (λ_min ≥ 2e3 for quad, ≥ 0.5 for the residual near x*), with slack
            lam_min = 2e3 if c is quad else 0.5
            err = (r.x.double() - ref.x).norm(dim=-1)
            slack = 1e-5 if dtype == torch.float32 else 1e-12
            assert (err <= 2 * bound / lam_min + slack).all(), (name, err)
