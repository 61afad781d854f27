"""Implicit gradients at cost weights from 1e-8 to 1e8, against a 50-digit reference.

A via-point / terminal precision ``w`` makes the forward trajectory accurate only to ``~w ε`` in
absolute terms while the costate ``λ = Q (x - μ)`` multiplies that error by ``w`` again; before the
refinement of :func:`controllers.implicit._refine` the implicit gradient w.r.t. ``A`` was wrong by
0.56 at ``w = 1e8``.  The reference (``mp_oracle``) solves the condensed problem in 50-digit
arithmetic and differentiates by central differences with a step of 1e-20.
"""

import pytest
import torch
from mp_oracle import fd_gradient

from controllers import ilqr as il
from controllers import riccati
from controllers.costs import QuadraticCost
from controllers.dynamics import LinearDynamics
from controllers.problem import LQProblem

D = torch.float64
T, n, m = 6, 3, 2
INPUTS = ("A", "B", "c", "Q", "R", "N", "x_ref", "u_ref", "q", "r", "x0")


def _fields(seed: int, w: float, where: str) -> dict:
    """Random time-varying A, B, c, R = I-ish, a cost that is zero but for precision ``w``: at the end
    (``terminal``) or at a via point in the middle plus a small terminal one (``via``)."""
    g = torch.Generator().manual_seed(seed)
    r = lambda *s, sc=1.0: sc * torch.randn(*s, dtype=D, generator=g)  # noqa: E731
    Q = torch.zeros(T + 1, n, n, dtype=D)
    M = r(T, m, m, sc=0.3)
    R = torch.eye(m, dtype=D) + M @ M.mT
    if where == "terminal":
        Q[T] = w * torch.eye(n, dtype=D)
    elif where == "via":
        Q[T // 2] = w * torch.eye(n, dtype=D)
        Q[T] = 1e-2 * torch.eye(n, dtype=D)
    else:  # "cond(R)": unit state precision, control weights with eigenvalues 1 and 1/w
        Q[:] = torch.eye(n, dtype=D)
        U = torch.linalg.qr(r(T, m, m))[0]
        R = U @ torch.diag(torch.tensor([1.0, 1.0 / w], dtype=D)) @ U.mT
        R = 0.5 * (R + R.mT)
    return dict(A=torch.eye(n, dtype=D) + r(T, n, n, sc=0.4), B=r(T, n, m), c=r(T, n, sc=0.3), Q=Q,
                R=R, N=r(T, n, m, sc=0.05) if where != "cond(R)" else torch.zeros(T, n, m, dtype=D),
                x_ref=r(T + 1, n), u_ref=r(T, m, sc=0.5), q=r(T + 1, n, sc=0.5), r=r(T, m, sc=0.5),
                x0=r(n)), g


def _loss_weights(g):
    return r_(g, T + 1, n), r_(g, T, m)


def r_(g, *s):
    return torch.randn(*s, dtype=D, generator=g)


def _ours(f: dict, solver: str, wx, wu):
    vals = {k: v.clone().requires_grad_(True) for k, v in f.items()}
    cost = QuadraticCost(vals["Q"], vals["R"], x_ref=vals["x_ref"], u_ref=vals["u_ref"], N=vals["N"],
                         q=vals["q"], r=vals["r"], check=False)
    dyn = LinearDynamics(vals["A"], vals["B"], vals["c"])
    if solver == "riccati":
        s = riccati.solve(LQProblem(dyn, cost, vals["x0"]), grad="implicit", check=False)
        x, u, J = s.x, s.u, s.cost
    else:
        s = il.ilqr(il.ILQRProblem(dyn, cost, vals["x0"], T), grad="implicit")
        assert bool(s.status.converged.all())
        x, u, J = s.x, s.u, s.cost
    loss = J + (wx * x).sum() + (wu * u).sum()
    grads = torch.autograd.grad(loss, [vals[k] for k in INPUTS])
    return dict(zip(INPUTS, grads))


def _entries(name: str, shape, g, where: str, k=2):
    """``k`` random entries; for the symmetric Q, R a symmetric pair is perturbed (see _ref)."""
    out = []
    for _ in range(k):
        idx = tuple(int(torch.randint(s, (), generator=g)) for s in shape)
        if name == "Q" and where != "cond(R)":  # the precision's non-zero steps
            idx = (T if idx[0] % 2 else T // 2, *idx[1:])
        out.append(idx)
    return out


def _ref(f, name, idx, wx, wu):
    import mpmath

    def loss(J, x, u):
        s = J
        for t in range(T + 1):
            for i in range(n):
                s += mpmath.mpf(float(wx[t, i])) * x[t][i]
        for t in range(T):
            for i in range(m):
                s += mpmath.mpf(float(wu[t, i])) * u[t][i]
        return s

    if name in ("Q", "R") and idx[-1] != idx[-2]:
        # a symmetric matrix: perturb (i, j) and (j, i) together; ours' symmetric-part gradient is
        # then g_ij + g_ji
        a = fd_gradient(f, name, idx, loss, sym=True)
        return a
    return fd_gradient(f, name, idx, loss)


# iLQR's implicit gradient is a Newton step solved by the same LQ machinery: its cases are the hard ones
CASES = [("riccati", w, where) for w in (1e-8, 1.0, 1e4, 1e8) for where in ("terminal", "via")]
CASES += [("ilqr", w, where) for w in (1e4, 1e8) for where in ("terminal", "via")]
CASES += [("ilqr", 1.0, "terminal")]
CASES += [("riccati", w, "cond(R)") for w in (1e4, 1e8)]


@pytest.mark.parametrize(("solver", "w", "where"), CASES)
def test_implicit_gradients_match_a_50_digit_reference(solver, w, where):
    f, g = _fields(7, w, where)
    wx, wu = _loss_weights(g)
    ours = _ours(f, solver, wx, wu)
    for name in INPUTS:
        gr = ours[name]
        for idx in _entries(name, f[name].shape, g, where):
            ref = _ref(f, name, idx, wx, wu)
            val = float(gr[idx])
            if name in ("Q", "R") and idx[-1] != idx[-2]:
                j = (*idx[:-2], idx[-1], idx[-2])
                val = float(gr[idx] + gr[j])
            # relative to the size of this input's gradient (entries may be tiny)
            scale = max(float(gr.abs().max()), abs(ref), 1e-300)
            assert abs(val - ref) <= 1e-6 * scale, (name, idx, val, ref)
