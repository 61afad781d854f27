"""The LQ kernels as compiled programs (``_lq_kernels.solve_core(compiled=True)``, ``lin_sweep``) and the
implicit iLQR gradient through them (``ilqr_implicit(compile=True)``) against the eager reference, and the
Newton-step data without double autograd (quadratic cost, analytic Jacobians) against the autograd path.

Each program takes seconds to build, so the tests share one cache directory and few shapes.
"""

import dataclasses
import math

import pytest
import torch

import controllers.implicit as imp
from controllers import _lq_kernels as K
from controllers.costs import PeriodicQuadraticCost, QuadraticCost
from controllers.ilqr import ILQROptions, ILQRProblem, ilqr
from controllers.systems import Pendulum

D = torch.float64


def _lq(B: int, T: int = 6, n: int = 3, m: int = 2, dtype=D, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.randn(*s, generator=g, dtype=dtype)
    L = r(B, T + 1, n, n)
    Lr = r(B, T, m, m)
    return dict(A=0.5 * r(B, T, n, n), B=r(B, T, n, m), c=r(B, T, n), Q=L @ L.mT / n,
                R=Lr @ Lr.mT + torch.eye(m, dtype=dtype), N=None, q=r(B, T + 1, n), r=r(B, T, m), x0=r(B, n))


def _solve(p, T, bs, compiled):
    return K.solve_core(p["A"], p["B"], p["c"], p["Q"], p["R"], p["N"], p["q"], p["r"], p["x0"], T, bs,
                        keep_huu=True, compiled=compiled)


@pytest.mark.parametrize("B", [1, 4])
def test_compiled_lq_solve_equals_the_eager_kernels(B):
    p = _lq(B)
    e, c = _solve(p, 6, torch.Size([B]), False), _solve(p, 6, torch.Size([B]), True)
    for a, b in zip(e[:3], c[:3]):
        torch.testing.assert_close(b, a, atol=1e-11, rtol=1e-11)
    for f in ("Kt", "Huu", "V"):
        torch.testing.assert_close(getattr(c[3], f), getattr(e[3], f), atol=1e-11, rtol=1e-11)
    assert torch.equal(c[3].ok, e[3].ok) and bool(e[3].ok.all())


def test_compiled_lq_solve_marks_a_bad_element_like_the_eager_one():
    p = _lq(4)
    p["R"][2] = -p["R"][2]  # H_uu indefinite in element 2
    p["x0"][1, 0] = math.nan  # a NaN start in element 1
    e, c = _solve(p, 6, torch.Size([4]), False), _solve(p, 6, torch.Size([4]), True)
    assert torch.equal(c[3].ok, e[3].ok)
    assert not bool(e[3].ok[2].all()) and bool(e[3].ok[[0, 1, 3]].all())
    torch.testing.assert_close(c[0], e[0], atol=1e-11, rtol=1e-11, equal_nan=True)
    assert bool(torch.isnan(c[0][1, 1:]).all()) and bool(torch.isfinite(c[0][[0, 3]]).all())


@pytest.mark.parametrize("reverse", [False, True])
def test_lin_sweep_compiled_equals_eager_and_the_recursion(reverse):
    g = torch.Generator().manual_seed(1)
    B, T, n = 3, 5, 3
    M, a, y0 = (torch.randn(B, T, n, n, generator=g, dtype=D), torch.randn(B, T, n, generator=g, dtype=D),
                torch.randn(B, n, generator=g, dtype=D))
    ys = [y0]
    for t in (range(T - 1, -1, -1) if reverse else range(T)):
        ys.append(a[:, t] + (M[:, t] @ ys[-1].unsqueeze(-1)).squeeze(-1))
    ref = torch.stack(ys[::-1] if reverse else ys, 1)
    torch.testing.assert_close(K.lin_sweep(M, a, y0, reverse), ref)
    torch.testing.assert_close(K.lin_sweep(M, a, y0, reverse, compiled=True), ref)


def _lqr_args(p, req):
    return tuple(v.clone().requires_grad_(k in req) if v is not None else None
                 for k, v in ((k, p[k]) for k in ("A", "B", "c", "Q", "R", "N", "q", "r", "x0")))


def test_compiled_lqr_function_gradients_equal_the_eager_ones():
    p = _lq(3)
    grads = []
    for comp in (False, True):
        args = _lqr_args(p, {"A", "B", "c", "Q", "R", "q", "r", "x0"})
        x, u, J, *_ = imp.lqr_implicit(*args, 6, torch.Size([3]), compiled=comp)
        (x.sin().sum() + u.cos().sum() + J.sum()).backward()
        grads.append([v.grad for v in args if v is not None])
    for a, b in zip(*grads):
        torch.testing.assert_close(b, a, atol=1e-10, rtol=1e-9)


def test_compiled_lqr_function_passes_gradcheck():
    p = _lq(2, T=3, n=2, m=1, seed=3)
    A, Bm, _, Q0, R, _, _, _, _ = _lqr_args(p, set())
    args = _lqr_args(p, {"A", "c", "Q", "q", "r", "x0"})
    args = (args[0], args[2], args[3], args[6], args[7], args[8])

    def f(A, c, W, q, r, x0):  # a symmetric weight (the implicit gradient of Q is the symmetric one)
        x, u, J, *_ = imp.lqr_implicit(A, Bm, c, 0.5 * (W + W.mT), R, None, q, r, x0, 3, torch.Size([2]),
                                       compiled=True)
        return x, u, J

    assert torch.autograd.gradcheck(f, args, atol=1e-6, rtol=1e-5)


def _pendulum_problem(B: int, w: torch.Tensor, periodic: bool):
    g = torch.Generator().manual_seed(B)
    x0 = torch.stack([torch.rand(B, generator=g, dtype=D) * 6 - 3, torch.zeros(B, dtype=D)], -1)
    T = 15
    Q = torch.diag(torch.cat([w, torch.ones(1, dtype=D)])).expand(B, T + 1, 2, 2)
    cost = QuadraticCost(Q=Q, R=torch.tensor([[0.05]], dtype=D), x_ref=torch.tensor([math.pi, 0.0], dtype=D),
                         check=False)
    if periodic:
        cost = PeriodicQuadraticCost(cost, torch.tensor([True, False]))
    return ILQRProblem(Pendulum(damping=0.1), cost, x0, T, u_lower=-2.0, u_upper=2.0)


def _implicit_grad(B, periodic, compile, analytic):
    w = torch.tensor([3.0], dtype=D, requires_grad=True)
    prob = _pendulum_problem(B, w, periodic)
    sol = ilqr(prob, grad="none", options=ILQROptions(max_iter=4))  # not converged: r ≠ 0 matters too
    bs = prob.batch_shape
    lo, hi = (v.expand(*bs, prob.T, 1) for v in prob.bounds())
    mp = pytest.MonkeyPatch()
    if not analytic:
        mp.setattr(imp, "_analytic_ok", lambda p: False)
    try:
        x, u = imp.ilqr_implicit(prob, prob.x0, sol.x, sol.u, ~sol.clamped, bs, lo, hi, compile=compile)
    finally:
        mp.undo()
    (x.sin().sum() + u.sum()).backward()
    return x.detach(), u.detach(), w.grad


@pytest.mark.parametrize("periodic", [False, True])
def test_analytic_newton_data_equals_the_autograd_path(periodic):
    assert imp._analytic_ok(_pendulum_problem(2, torch.ones(1, dtype=D), periodic))
    ref = _implicit_grad(5, periodic, compile=False, analytic=False)
    got = _implicit_grad(5, periodic, compile=False, analytic=True)
    assert bool(ref[2].abs().max() > 0)
    for a, b in zip(ref, got):
        torch.testing.assert_close(b, a, atol=1e-10, rtol=1e-9)


@pytest.mark.parametrize("B", [1, 5])
def test_compiled_implicit_gradient_equals_the_eager_one(B):
    ref = _implicit_grad(B, True, compile=False, analytic=True)
    got = _implicit_grad(B, True, compile=True, analytic=True)
    for a, b in zip(ref, got):
        torch.testing.assert_close(b, a, atol=1e-10, rtol=1e-9)


def test_a_system_with_a_learnable_parameter_keeps_the_autograd_path():
    length = torch.nn.Parameter(torch.tensor(1.0, dtype=D))
    prob = _pendulum_problem(2, torch.ones(1, dtype=D), False)
    assert not imp._analytic_ok(dataclasses.replace(prob, dynamics=Pendulum(length=length)))
    assert imp._analytic_ok(dataclasses.replace(prob, dynamics=Pendulum(length=1.5)))
