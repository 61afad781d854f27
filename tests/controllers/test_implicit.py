"""Implicit (KKT / backward Riccati) gradients of the LQ solution and of its optimal cost."""

import pytest
import torch
from lq_oracle import D, random_problem

from controllers import lifted, riccati
from controllers.costs import QuadraticCost
from controllers.dynamics import LinearDynamics
from controllers.problem import LQProblem

NAMES = ("A", "B", "c", "Q", "R", "N", "x_ref", "u_ref", "q", "r", "x0")


def _inputs(seed, b=(2,), T=4, n=3, m=2):
    g = torch.Generator().manual_seed(seed)
    p = random_problem(g, b=b, T=T, n=n, m=m)
    d, c = p.dynamics, p.cost
    vals = dict(A=d.A, B=d.B, c=d.c, Q=c.Q, R=c.R, N=c.N, x_ref=c.x_ref, u_ref=c.u_ref, q=c.q, r=c.r, x0=p.x0)
    return {k: v.detach().clone() for k, v in vals.items()}, g


def _solve(vals, solver="implicit"):
    p = LQProblem(LinearDynamics(vals["A"], vals["B"], vals["c"]),
                  QuadraticCost(vals["Q"], vals["R"], x_ref=vals["x_ref"], u_ref=vals["u_ref"], N=vals["N"],
                                q=vals["q"], r=vals["r"], check=False), vals["x0"])
    if solver == "lifted":
        s = lifted.solve_lifted(p)
    else:
        s = riccati.solve(p, grad=solver, check=False)
    return s.x, s.u, s.cost


@pytest.mark.parametrize("name", NAMES)
def test_gradcheck_every_input(name):
    vals, _ = _inputs(0)
    x = vals[name].requires_grad_()
    # Q and R are symmetric matrices: perturb them through a symmetric parametrization
    sym = (lambda v: 0.5 * (v + v.mT)) if name in ("Q", "R") else (lambda v: v)

    def f(v):
        return _solve({**vals, name: sym(v)})

    assert torch.autograd.gradcheck(f, (x,), atol=1e-6, rtol=1e-5)


def test_implicit_equals_unrolled_and_lifted_autograd():
    vals, g = _inputs(1, b=(3,), T=6, n=4, m=2)
    for v in vals.values():
        v.requires_grad_()
    x, u, J = _solve(vals)
    wx = torch.randn(x.shape, dtype=D, generator=g)
    wu = torch.randn(u.shape, dtype=D, generator=g)
    wJ = torch.randn(J.shape, dtype=D, generator=g)
    loss = lambda out: (out[0] * wx).sum() + (out[1] * wu).sum() + (out[2] * wJ).sum()
    ins = [vals[k] for k in NAMES]
    g_imp = torch.autograd.grad(loss((x, u, J)), ins)
    g_unr = torch.autograd.grad(loss(_solve(vals, "unrolled")), ins)
    g_lift = torch.autograd.grad(loss(_solve(vals, "lifted")), ins)
    for k, a, b_, c_ in zip(NAMES, g_imp, g_unr, g_lift):
        # only symmetric perturbations of Q, R are meaningful: compare the symmetric parts
        if k in ("Q", "R"):
            a, b_, c_ = (0.5 * (v + v.mT) for v in (a, b_, c_))
        torch.testing.assert_close(a, b_, atol=1e-9, rtol=1e-7, msg=f"implicit vs unrolled: {k}")
        torch.testing.assert_close(a, c_, atol=1e-9, rtol=1e-7, msg=f"implicit vs lifted autograd: {k}")


def test_finite_differences_of_cost_and_first_control():
    vals, g = _inputs(2, b=(), T=5)
    for name in ("x0", "A", "x_ref", "R"):
        v = vals[name].clone().requires_grad_()
        x, u, J = _solve({**vals, name: v})
        out = J + 3.0 * u[0].sum()
        (gr,) = torch.autograd.grad(out, v)
        dirn = torch.randn(v.shape, dtype=D, generator=g)
        if name == "R":
            dirn = dirn + dirn.mT
        eps = 1e-6
        fp = _solve({**vals, name: vals[name] + eps * dirn})
        fm = _solve({**vals, name: vals[name] - eps * dirn})
        fd = ((fp[2] + 3.0 * fp[1][0].sum()) - (fm[2] + 3.0 * fm[1][0].sum())) / (2 * eps)
        assert abs(fd.item() - (gr * dirn).sum().item()) < 1e-6 * max(1.0, abs(fd.item())), name


def test_broadcast_inputs_get_reduced_gradients():
    """Shared (un-batched, time-invariant) A, Q get gradients of their own shape, equal to the sum over
    the batch and time of the expanded problem's gradients."""
    vals, g = _inputs(3, b=(3,), T=4)
    A = vals["A"][0, 0].clone().requires_grad_()
    Q = vals["Q"][0, 0].clone().requires_grad_()
    x, u, J = _solve({**vals, "A": A, "Q": Q})
    (gA, gQ) = torch.autograd.grad(J.sum() + u.sum(), (A, Q))
    Ae = A.detach().expand(3, 4, 3, 3).clone().requires_grad_()
    Qe = Q.detach().expand(3, 5, 3, 3).clone().requires_grad_()
    x, u, J = _solve({**vals, "A": Ae, "Q": Qe})
    (gAe, gQe) = torch.autograd.grad(J.sum() + u.sum(), (Ae, Qe))
    assert gA.shape == (3, 3) and gQ.shape == (3, 3)
    torch.testing.assert_close(gA, gAe.sum((0, 1)))
    torch.testing.assert_close(gQ, gQe.sum((0, 1)))


def test_gains_have_no_graph_in_implicit_mode_but_do_when_unrolled():
    vals, _ = _inputs(4)
    vals["x0"].requires_grad_()
    vals["A"].requires_grad_()
    p = LQProblem(LinearDynamics(vals["A"], vals["B"], vals["c"]),
                  QuadraticCost(vals["Q"], vals["R"], x_ref=vals["x_ref"]), vals["x0"])
    s = riccati.solve(p)
    assert s.u.requires_grad and not s.K.requires_grad
    s2 = riccati.solve(p, grad="unrolled")
    assert s2.K.requires_grad
    s3 = riccati.solve(p, grad="none")
    assert not s3.u.requires_grad
