"""The error-state MPC step as one compiled program (``ErrorStateMPC(..., compile=True)``) against the eager
reference.

The eager ``solve`` is the reference: the program must give the same plans, predicted errors, costs, KKT
residuals, clamped sets and statuses (values to round-off), at any batch size (one program serves them
all), with a NaN element, an element with crossed limits and elements whose closed form breaks a limit (the
fixed-budget box QP and its certificate), through the Riccati form of large batches, and raise the eager
path's errors.  The pure core (:func:`controllers._esmpc_core.step`) run eagerly equals the built program.
Each program takes a minute or so to build on a loaded machine, so the tests share one cache directory
and few programs.
"""

import pytest
import torch

from controllers import _compiled
from controllers._esmpc_core import step
from controllers.manifold_mpc import ErrorStateMPC, riccati_terminal_weight
from controllers.problem import Reason
from controllers.systems import quadrotor_flatness as qf
from controllers.systems.quadrotor import Quadrotor
from torchlie import so3
from torchlie.manifolds import ProductState

D = torch.float64


@pytest.fixture(scope="module")
def quad():
    q = Quadrotor()
    Q = torch.tensor([100.0] * 3 + [10.0] * 6, dtype=D)
    R = torch.tensor([0.1] * 4, dtype=D)
    xh, uh = q.hover(torch.zeros(3, dtype=D))
    P, _ = riccati_terminal_weight(q, xh, uh, Q, R)
    return q, Q, R, P


def _problem(q, B: int, N: int = 8, spread: float = 0.05, seed: int = 0):
    ref = qf.circle_ramp(pad=N + 2)
    g = torch.Generator().manual_seed(seed)
    k = torch.randint(0, ref.t.shape[0] - N - 1, (B,), generator=g)
    idx = k[:, None] + torch.arange(N + 1)
    p0 = ref.p[k] + spread * torch.randn(B, 3, generator=g, dtype=D)
    R0 = ref.R[k] @ so3.exp(spread * torch.randn(B, 3, generator=g, dtype=D))
    xr = q.state(ref.p[idx], ref.v[idx], ref.R[idx])
    x0 = q.state(p0, ref.v[k], R0)
    return x0, xr, ref.u[idx[:, :-1]].clone()


def _pair(quad, **kw):
    q, Q, R, P = quad
    return (ErrorStateMPC(q, 8, Q, R, P, grad="none", **kw),
            ErrorStateMPC(q, 8, Q, R, P, grad="none", compile=True, **kw))


def _assert_same(a, b, tol=1e-9):
    for f in ("U", "dx", "cost", "kkt_residual"):
        torch.testing.assert_close(getattr(b, f), getattr(a, f), atol=tol, rtol=1e-9, equal_nan=True, msg=f)
    assert torch.equal(b.status.reason, a.status.reason)
    assert torch.equal(b.clamped, a.clamped)


@pytest.mark.parametrize("B", [1, 6])
def test_step_equals_the_eager_path_at_any_batch_size(quad, B):
    eager, comp = _pair(quad)
    x0, xr, ur = _problem(quad[0], B)
    _assert_same(eager.solve(x0, xr, ur), comp.solve(x0, xr, ur))
    # the pure core run eagerly (Python loops) equals the built program on the same arguments
    spec, args, dims, _ = comp._program_inputs(x0, xr, ur, None)
    ref, out = step(spec, *args), comp._program(spec, args, dims)(*args)
    for r, o in zip(ref, out):
        torch.testing.assert_close(o, r, atol=1e-9, rtol=1e-9, equal_nan=True)


def test_one_program_serves_every_batch_size_and_an_unbatched_state(quad, monkeypatch):
    eager, comp = _pair(quad)
    x0, xr, ur = _problem(quad[0], 3, seed=1)
    comp.solve(x0, xr, ur)
    built = []
    monkeypatch.setattr(_compiled, "_compile", lambda *a, **k: built.append(a))
    x1, xr1, ur1 = x0[0], xr[0], ur[0]  # batch shape ()
    a, b = eager.solve(x1, xr1, ur1), comp.solve(x1, xr1, ur1)
    assert b.U.shape == (8, 4) and not built
    _assert_same(a, b)


def test_bad_elements_limits_and_box_qp_equal_the_eager_path(quad):
    """Per-element limits: a NaN state, crossed limits, tight limits (the box QP, certified), normal ones."""
    q = quad[0]
    B = 6
    x0, xr, ur = _problem(q, B, spread=0.3, seed=2)
    lo = torch.tensor(q.u_lower, dtype=D).expand(B, 8, 4).clone()
    hi = torch.tensor(q.u_upper, dtype=D).expand(B, 8, 4).clone()
    lo[1:3, :, 1:] = -0.2  # tight body rates: the closed form breaks them
    hi[1:3, :, 1:] = 0.2
    lo[3, 2, 0] = hi[3, 2, 0] + 1.0  # crossed
    x0["p"][4, 0] = torch.nan
    eager, comp = _pair(quad, u_lower=lo, u_upper=hi)
    a, b = eager.solve(x0, xr, ur), comp.solve(x0, xr, ur)
    _assert_same(a, b)
    reason = b.status.reason
    assert reason[3] == int(Reason.INFEASIBLE_BOUNDS) and reason[4] == int(Reason.NONFINITE_INPUT)
    assert (reason[[0, 1, 2, 5]] == int(Reason.CONVERGED)).all()
    assert b.clamped[1:3].any() and torch.isnan(b.U[3:5]).all()
    # the program certified the clamped elements itself (no eager re-solve was needed)
    spec, args, dims, _ = comp._program_inputs(x0, xr, ur, None)
    out = comp._program(spec, args, dims)(*args)
    assert out[-1].tolist() == [0, 0, 0]
    assert torch.equal(out[3], a.status.reason)


def test_uncertified_box_qp_elements_are_solved_again_eagerly(quad, monkeypatch):
    q = quad[0]
    B = 3
    x0, xr, ur = _problem(q, B, spread=0.3, seed=2)
    lo = torch.tensor(q.u_lower, dtype=D).expand(B, 8, 4).clone()
    hi = torch.tensor(q.u_upper, dtype=D).expand(B, 8, 4).clone()
    lo[:2, :, 1:], hi[:2, :, 1:] = -0.2, 0.2
    # a zero gap tolerance: no point passes the certificate, the box QP elements fail in both paths
    eager, comp = _pair(quad, u_lower=lo, u_upper=hi, qp_options={"gap_tol": 0.0})
    calls = []
    orig = ErrorStateMPC._eager_subset
    monkeypatch.setattr(ErrorStateMPC, "_eager_subset", lambda self, *a: calls.append(a[4]) or orig(self, *a))
    a = eager.solve(x0, xr, ur)
    _assert_same(a, comp.solve(x0, xr, ur))
    assert calls and set(calls[0].tolist()) == {0, 1}
    assert (a.status.reason[:2] != int(Reason.CONVERGED)).all()
    assert a.status.reason[2] == int(Reason.CONVERGED)


def test_large_batches_take_the_riccati_program_like_the_eager_path(quad):
    q = quad[0]
    B = 400  # above the eager path's Riccati-first size for H = 8
    x0, xr, ur = _problem(q, B, spread=0.2, seed=3)
    eager, comp = _pair(quad)
    assert comp._riccati_first(B)
    a, b = eager.solve(x0, xr, ur), comp.solve(x0, xr, ur)
    _assert_same(a, b)
    assert b.clamped.any()  # some elements broke a limit and were condensed (the qp program on them)


def test_errors_of_the_eager_path(quad):
    eager, comp = _pair(quad)
    x0, xr, ur = _problem(quad[0], 2, seed=4)
    R = x0["R"].clone()
    R[1] = 2 * R[1]  # off SO(3)
    q_off = ProductState({"p": x0["p"], "v": x0["v"], "R": R}, {"p": 1, "v": 1, "R": 2})
    with pytest.raises(ValueError, match="not on") as e_eager:
        eager.solve(q_off, xr, ur)
    with pytest.raises(ValueError, match="not on") as e_comp:
        comp.solve(q_off, xr, ur)
    assert str(e_comp.value) == str(e_eager.value)
    nan = ur.clone()
    nan[:] = torch.nan
    with pytest.raises(ValueError, match="every element"):
        comp.solve(x0, xr, nan)
    with pytest.raises(ValueError, match="u_ref"):
        comp.solve(x0, xr, ur[..., :3])
    with pytest.raises(TypeError, match="compile"):
        ErrorStateMPC(quad[0], 8, quad[1], quad[2], compile=1)


def test_gradients_fall_back_to_the_eager_path(quad, monkeypatch):
    q, Q, R, P = quad
    mpc = ErrorStateMPC(q, 8, Q, R, P, grad="implicit", compile=True)
    monkeypatch.setattr(ErrorStateMPC, "_solve_compiled", lambda *a: pytest.fail("compiled with a graph"))
    x0, xr, ur = _problem(q, 2, seed=5)
    ur = ur.requires_grad_()
    sol = mpc.solve(x0, xr, ur)
    sol.u.sum().backward()
    assert ur.grad is not None and torch.isfinite(ur.grad).all()
