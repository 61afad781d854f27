"""One broadcasting rule for every solver entry point (``controllers.problem`` module docstring).

Each field's batch dims broadcast like torch against the others and against ``x0``; a matrix without
batch dims is shared.  Every solver must give, for a problem with mixed batch shapes, exactly what it
gives for the same problem expanded by hand — and the dense KKT oracle agrees.
"""

import pytest
import torch
from lq_oracle import D, dense_kkt

from controllers import ilqr as il
from controllers import lifted, riccati
from controllers.boxqp import box_qp
from controllers.costs import QuadraticCost
from controllers.dynamics import LinearDynamics
from controllers.problem import LQProblem

T, n, m = 4, 3, 2

# (A shape, B shape, x0 shape, Q shape): shared, per-element, time-invariant-per-element, extra dims
SHAPES = {
    "A shared, B per element": ((n, n), (2, T, n, m), (n,), (n, n)),
    "A per element, B shared": ((2, T, n, n), (n, m), (n,), (n, n)),
    "B (2, 1), x0 (3, 2)": ((n, n), (2, 1, n, m), (3, 2, n), (n, n)),
    "Q (3, 1), B (2,), x0 shared": ((n, n), (2, 1, n, m), (n,), (3, 1, T + 1, n, n)),
}


def _fields(case: str, g):
    sa, sb, sx, sq = SHAPES[case]
    A = torch.eye(n, dtype=D) + 0.3 * torch.randn(sa, dtype=D, generator=g)
    B = torch.randn(sb, dtype=D, generator=g)
    x0 = torch.randn(sx, dtype=D, generator=g)
    M = torch.randn(sq, dtype=D, generator=g)
    Q = M @ M.mT + 0.5 * torch.eye(n, dtype=D)
    return A, B, x0, Q


def _expanded(A, B, x0, Q, bs):
    """The same problem with every field expanded by hand to the full batch and time dims."""
    At = A if A.dim() > 2 else A.expand(T, n, n)
    Bt = B if B.dim() > 2 else B.expand(T, n, m)
    Qt = Q if Q.dim() > 2 else Q.expand(T + 1, n, n)
    return (At.expand(*bs, T, n, n).clone(), Bt.expand(*bs, T, n, m).clone(), x0.expand(*bs, n).clone(),
            Qt.expand(*bs, T + 1, n, n).clone())


def _problem(A, B, x0, Q):
    ref = torch.linspace(-1, 1, (T + 1) * n, dtype=D).reshape(T + 1, n)
    cost = QuadraticCost(Q, 0.5 * torch.eye(m, dtype=D), x_ref=ref)
    return LQProblem(LinearDynamics(A, B), cost, x0, horizon=T)


@pytest.mark.parametrize("case", list(SHAPES))
def test_every_solver_accepts_mixed_batch_shapes(case):
    g = torch.Generator().manual_seed(0)
    A, B, x0, Q = _fields(case, g)
    p = _problem(A, B, x0, Q)
    bs = p.batch_shape
    pe = _problem(*_expanded(A, B, x0, Q, bs))
    _, u_kkt = dense_kkt(pe)
    ref = riccati.solve(pe, grad="none")
    torch.testing.assert_close(ref.u, u_kkt, atol=1e-10, rtol=0)
    outs = {
        "riccati": lambda: riccati.solve(p, grad="none").u,
        "riccati implicit": lambda: riccati.solve(p).u,
        "riccati unrolled": lambda: riccati.solve(p, grad="unrolled").u,
        "lifted": lambda: lifted.solve_lifted(p).u,
    }
    for meth in ("recursive", "batch"):
        for gm in ("none", "implicit", "unrolled"):
            outs[f"ilqr {meth} {gm}"] = (lambda meth=meth, gm=gm: il.ilqr(
                il.ILQRProblem(p.dynamics, p.cost, x0, T), method=meth, grad=gm).u)
    for name, fn in outs.items():
        u = fn()
        assert u.shape == (*bs, T, m), name
        torch.testing.assert_close(u, ref.u, atol=1e-9, rtol=0, msg=name)


@pytest.mark.parametrize("case", list(SHAPES))
def test_ilqr_with_limits_and_gradients_under_mixed_shapes(case):
    """Limits with their own batch dims, and implicit gradients reduced to each input's own shape, equal
    to those of the hand-expanded problem summed over the broadcast dims."""
    g = torch.Generator().manual_seed(1)
    A, B, x0, Q = _fields(case, g)
    bs = _problem(A, B, x0, Q).batch_shape
    lo = torch.full((*bs[-1:], 1, m), -0.3, dtype=D)  # limits batched over the last batch dim only
    leaves = [v.clone().requires_grad_() for v in (A, B, x0, Q)]
    pr = _problem(*leaves)
    sol = il.ilqr(il.ILQRProblem(pr.dynamics, pr.cost, leaves[2], T, lo, 0.3))
    assert bool(sol.status.converged.all()) and bool(sol.clamped.any()) and bool((~sol.clamped).any())
    grads = torch.autograd.grad(sol.u.square().sum(), leaves)
    exp = [v.requires_grad_() for v in _expanded(A, B, x0, Q, bs)]
    pe = _problem(*exp)
    sole = il.ilqr(il.ILQRProblem(pe.dynamics, pe.cost, exp[2], T, lo, 0.3))
    torch.testing.assert_close(sol.u, sole.u, atol=1e-10, rtol=0)
    grads_e = torch.autograd.grad(sole.u.square().sum(), exp)
    for gr, ge, v in zip(grads, grads_e, (A, B, x0, Q)):
        assert gr.shape == v.shape
        torch.testing.assert_close(gr, _reduce(ge, v), atol=1e-9, rtol=1e-7)


def _reduce(ge, v):
    """Sum a gradient of the expanded field back to the field's own shape (time dim included)."""
    if v.dim() == 2:  # shared and time-invariant: sum over batch and time
        return ge.sum(dim=tuple(range(ge.dim() - 2)))
    return ge.sum_to_size(v.shape)


def test_ilqr_problem_rejects_non_broadcasting_limits_naming_them():
    A = torch.eye(n, dtype=D)
    p = _problem(A, torch.ones(n, m, dtype=D), torch.zeros(3, 2, n, dtype=D), torch.eye(n, dtype=D))
    with pytest.raises(ValueError, match="u_lower"):
        il.ILQRProblem(p.dynamics, p.cost, p.x0, T, torch.zeros(4, 1, T, m, dtype=D), 1.0)


def test_box_qp_broadcasts_bounds_and_hessians():
    g = torch.Generator().manual_seed(2)
    M = torch.randn(m + 2, m + 2, dtype=D, generator=g)
    H = M @ M.mT + torch.eye(m + 2, dtype=D)  # shared
    q = torch.randn(3, 2, m + 2, dtype=D, generator=g)
    lo = torch.full((2, 1), -0.2, dtype=D)  # broadcasts to (3, 2, m+2)
    r = box_qp(H, q, lo, 0.2)
    hi = torch.full((3, 2, m + 2), 0.2, dtype=D)
    re = box_qp(H.expand(3, 2, m + 2, m + 2), q, lo.expand(3, 2, m + 2), hi)
    torch.testing.assert_close(r.x, re.x, atol=0, rtol=0)
    assert r.x.shape == (3, 2, m + 2)
