"""Issue 22 for ErrorStateMPC and PoseMPC: limits (one-sided, crossed, NaN), weights, float32, NaN isolation
and argument checks, each against an independent reference (scipy's bounded least squares, central
differences, a per-sample loop)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.optimize import lsq_linear

from controllers.manifold_mpc import ErrorStateMPC
from controllers.pose_mpc import FRAMES, PoseMPC, twist_box
from controllers.problem import Reason
from torchlie import magnus, se3
from torchlie.manifolds import Rn

D = torch.float64
DT = 0.5
QD = np.diag([1.0, 0.1])
RD = 0.1
X0S = [[-1.0, 0.0], [1.0, 0.5], [0.5, -1.0]]


class DoubleIntegrator:
    """``x = [p, v]``, ``x ⊕ Δt f = x + Δt [v, u]``: the error system is the system itself."""

    m = 1

    def __init__(self, dt: float = DT):
        self.manifold, self.n, self.dt = Rn(2), 2, dt

    def f(self, x, u):
        return torch.cat([x[..., 1:2], u], -1)


def _dense(x0, N, dt=DT, Q=QD, R=RD):
    """``(M, b)`` with ``Σ_k x_kᵀQx_k + Σ_k R u_k² = ‖M U + b‖²`` (P = Q), written out from the model."""
    A = np.array([[1.0, dt], [0.0, 1.0]])
    Bm = np.array([[0.0], [dt]])
    Sx, Su = [np.eye(2)], [np.zeros((2, N))]
    for k in range(N):
        Sx.append(A @ Sx[-1])
        row = A @ Su[-1]
        row[:, k:k + 1] += Bm
        Su.append(row)
    L = np.linalg.cholesky(Q).T
    M = np.vstack([L @ s for s in Su] + [math.sqrt(R) * np.eye(N)])
    b = np.concatenate([L @ s @ np.asarray(x0) for s in Sx] + [np.zeros(N)])
    return M, b


def _bvls(x0, N, lo, hi, **kw):
    M, b = _dense(x0, N, **kw)
    lo = np.broadcast_to(np.asarray(lo, dtype=float), (N,))
    hi = np.broadcast_to(np.asarray(hi, dtype=float), (N,))
    return lsq_linear(M, -b, bounds=(lo, hi), method="bvls", tol=1e-14).x


def _di_problem(B=3, N=5, dtype=D):
    x0 = torch.tensor(X0S[:B], dtype=dtype)
    return x0, torch.zeros(B, N + 1, 2, dtype=dtype), torch.zeros(B, N, 1, dtype=dtype)


def _di_mpc(N=5, dtype=D, **kw):
    return ErrorStateMPC(DoubleIntegrator(), N, torch.tensor([1.0, 0.1], dtype=dtype),
                         torch.tensor([RD], dtype=dtype), **kw)


# ------------------------------------------------------------------------------------------------------
# item 1: one-sided limits with gradients
# ------------------------------------------------------------------------------------------------------

N5 = 5
INF = math.inf
LIMITS = {
    "upper float only": (None, 1.0),
    "lower tensor only": (torch.tensor([-0.5], dtype=D), None),
    "per-step, some steps open": (torch.tensor([[-INF], [-0.6], [-INF], [-0.6], [-INF]], dtype=D),
                                  torch.tensor([[1.0], [INF], [0.8], [INF], [INF]], dtype=D)),
    "per-element, one side each": (torch.tensor([[[-INF]], [[-0.7]], [[-INF]]], dtype=D),
                                   torch.tensor([[[0.9]], [[INF]], [[0.4]]], dtype=D)),
    "per-element and per-step": (torch.tensor([[-INF, -0.5, -INF, -INF, -0.3],
                                               [-0.2, -INF, -INF, -0.4, -INF],
                                               [-INF, -INF, -0.1, -INF, -INF]], dtype=D)[..., None],
                                 torch.tensor([[1.0, INF, 0.5, INF, INF],
                                               [INF, 0.3, INF, INF, 0.2],
                                               [0.6, 0.6, INF, INF, 0.05]], dtype=D)[..., None]),
}


def _element_limits(lo, hi, i):
    def one(b, inf):
        if b is None:
            return np.full(N5, inf)
        t = torch.as_tensor(b, dtype=D)
        t = t.expand(3, N5, 1) if t.dim() == 3 else t.expand(N5, 1) if t.dim() >= 1 else t.expand(N5, 1)
        return (t[i] if t.dim() == 3 else t)[:, 0].numpy()
    return one(lo, -INF), one(hi, INF)


@pytest.mark.parametrize("case", list(LIMITS))
def test_one_sided_and_mixed_limits_give_the_bvls_plan_with_finite_gradients(case):
    lo, hi = LIMITS[case]
    mpc = _di_mpc(u_lower=lo, u_upper=hi)
    x0, xr, ur = _di_problem()
    with torch.no_grad():
        plain = mpc.solve(x0, xr, ur)
    refs = []
    for i in range(3):
        lo_i, hi_i = _element_limits(lo, hi, i)
        refs.append(_bvls(X0S[i], N5, lo_i, hi_i))
    ref = torch.tensor(np.stack(refs), dtype=D)
    torch.testing.assert_close(plain.U[..., 0], ref, rtol=0, atol=1e-8)
    assert bool(plain.clamped.any())
    # with gradients: the same plan, certified, and d(plan)/d(x0) equal to central differences
    x0g = x0.clone().requires_grad_(True)
    sol = mpc.solve(x0g, xr, ur)
    assert bool(sol.status.converged.all()), sol.status.reason_names()
    torch.testing.assert_close(sol.U.detach(), plain.U, rtol=0, atol=1e-10)
    w = torch.linspace(1.0, 2.0, N5, dtype=D)
    (gx,) = torch.autograd.grad((sol.U[..., 0] * w).sum(), x0g)
    assert bool(torch.isfinite(gx).all())
    h = 1e-6
    for i in range(3):
        for j in range(2):
            e = torch.zeros_like(x0)
            e[i, j] = h
            with torch.no_grad():
                d = mpc.solve(x0 + e, xr, ur).U[..., 0] - mpc.solve(x0 - e, xr, ur).U[..., 0]
            fd = (d * w).sum() / (2 * h)
            assert abs(float(gx[i, j] - fd)) < 1e-6 * (1 + abs(float(fd))), (case, i, j, float(gx[i, j]))


def test_gradient_with_respect_to_a_one_sided_limit_matches_central_differences():
    hi = torch.tensor([[1.0], [INF], [INF], [INF], [INF]], dtype=D, requires_grad=True)
    x0, xr, ur = _di_problem(1)
    sol = _di_mpc(u_upper=hi).solve(x0, xr, ur)
    assert bool(sol.clamped[0, 0, 0]) and bool(sol.status.converged.all())
    (g,) = torch.autograd.grad(sol.U[..., 0].sum(), hi)
    h = 1e-6
    with torch.no_grad():
        e = torch.zeros_like(hi)
        e[0, 0] = h
        plus = _di_mpc(u_upper=hi + e).solve(x0, xr, ur).U.sum()
        fd = (plus - _di_mpc(u_upper=hi - e).solve(x0, xr, ur).U.sum()) / (2 * h)
    assert abs(float(g[0, 0] - fd)) < 1e-6 * (1 + abs(float(fd)))
    assert float(g[1:].abs().max()) == 0.0


N8, DT8 = 8, 0.02
QW = torch.tensor([100.0] * 3 + [30.0] * 3, dtype=D)
RW = torch.tensor([0.01, 0.02, 0.03, 0.01, 0.02, 0.05], dtype=D)


def _pose_problem(B, seed, twist_scale=0.3, off_scale=0.3):
    g = torch.Generator().manual_seed(seed)
    X0 = se3.random(B, generator=g, dtype=D)
    T = twist_scale * torch.randn(B, N8, 6, generator=g, dtype=D)
    X = torch.cat([X0[:, None], magnus.integrate_exact(X0, T, DT8)], 1)
    Xc = X[:, 0] @ se3.exp(off_scale * torch.randn(B, 6, generator=g, dtype=D))
    return Xc, X, T


def _world_bvls(Xc, X, T, lo, hi):
    """The world-frame MPC (seed 000 Eq. 16) as a bounded least squares, written out: ξ_{k+1} = ξ_k + Δt D T_k
    with D = dexp⁻¹ (order-2 series) at ξ_0 = log Xc, errors ξ_k − log X*_k, weights QW (P = Q), RW on
    T − T*."""
    xi0 = se3.log(Xc).numpy()
    Dm = magnus.dexp_inv_series(se3.log(Xc), 2).numpy()
    xr = se3.log(X).numpy()
    n = 6 * N8
    rows, rhs = [], []
    Lq, Lr = np.sqrt(QW.numpy()), np.sqrt(RW.numpy())
    S = np.zeros((6, n))
    for k in range(N8 + 1):
        rows.append(Lq[:, None] * S)
        rhs.append(Lq * (xr[k] - xi0))
        if k < N8:
            S = S.copy()
            S[:, 6 * k:6 * k + 6] += DT8 * Dm
    for k in range(N8):
        E = np.zeros((6, n))
        E[:, 6 * k:6 * k + 6] = np.diag(Lr)
        rows.append(E)
        rhs.append(Lr * T[k].numpy())
    lo_ = np.tile(np.broadcast_to(lo, (6,)), N8)
    hi_ = np.tile(np.broadcast_to(hi, (6,)), N8)
    return lsq_linear(np.vstack(rows), np.concatenate(rhs), bounds=(lo_, hi_), method="bvls", tol=1e-14).x


@pytest.mark.parametrize("frame", FRAMES)
def test_pose_mpc_with_only_an_upper_limit_is_finite_and_differentiable(frame):
    Xc, X, T = _pose_problem(2, 7)
    _, hi = twist_box(0.5, 1.0)
    mpc = PoseMPC(frame, N8, DT8, QW, RW, u_upper=hi)
    with torch.no_grad():
        plain = mpc.solve(Xc, X, T)
    if frame == "world":
        for b in range(2):
            ref = _world_bvls(Xc[b], X[b], T[b], -np.inf, hi.numpy())
            torch.testing.assert_close(plain.U[b].reshape(-1), torch.tensor(ref, dtype=D), rtol=0, atol=1e-7)
    Tg = T.clone().requires_grad_(True)
    sol = mpc.solve(Xc, X, Tg)
    assert bool(sol.clamped.any()) and bool(sol.status.converged.all())
    torch.testing.assert_close(sol.U.detach(), plain.U, rtol=0, atol=1e-10)
    w = torch.randn(2, 6, generator=torch.Generator().manual_seed(3), dtype=D)
    (g,) = torch.autograd.grad((sol.u * w).sum(), Tg)
    assert bool(torch.isfinite(g).all())
    h = 1e-6
    for (b, i, j) in ((0, 0, 0), (1, 0, 3), (1, 4, 2)):
        E = torch.zeros_like(T)
        E[b, i, j] = h
        with torch.no_grad():
            fd = ((mpc.solve(Xc, X, T + E).u - mpc.solve(Xc, X, T - E).u) * w).sum() / (2 * h)
        assert abs(float(g[b, i, j] - fd)) < 1e-5 * (1 + abs(float(fd))), (frame, b, i, j)


# ------------------------------------------------------------------------------------------------------
# item 2 and 13: crossed and NaN limits are per-element statuses; float ones are ValueErrors
# ------------------------------------------------------------------------------------------------------


def test_crossed_limits_are_infeasible_bounds_per_element_and_the_others_are_untouched():
    x0, xr, ur = _di_problem()
    lo = torch.tensor([-1.0, -1.0, -1.0], dtype=D).reshape(3, 1, 1).repeat(1, N5, 1)
    hi = torch.tensor([1.0, 1.0, 1.0], dtype=D).reshape(3, 1, 1).repeat(1, N5, 1)
    lo[1, 3, 0] = 1.5  # one entry of element 1 crossed
    sol = _di_mpc(u_lower=lo, u_upper=hi).solve(x0, xr, ur)
    assert sol.status.reason.tolist() == [0, int(Reason.INFEASIBLE_BOUNDS), 0]
    assert bool(torch.isnan(sol.U[1]).all())
    for i in (0, 2):
        torch.testing.assert_close(sol.U[i, :, 0], torch.tensor(_bvls(X0S[i], N5, -1.0, 1.0), dtype=D),
                                   rtol=0, atol=1e-8)
    # shared crossed tensor limits: every element
    shared = _di_mpc(u_lower=torch.tensor([0.5], dtype=D), u_upper=torch.tensor([0.2], dtype=D))
    sol = shared.solve(x0, xr, ur)
    assert sol.status.reason.tolist() == [int(Reason.INFEASIBLE_BOUNDS)] * 3
    with pytest.raises(ValueError, match="u_lower"):
        _di_mpc(u_lower=0.5, u_upper=0.2)


@pytest.mark.parametrize("frame", FRAMES)
def test_pose_mpc_crossed_limits_for_one_element(frame):
    Xc, X, T = _pose_problem(3, 5)
    lo, hi = twist_box(0.5, 1.0)
    lo3, hi3 = lo.expand(3, 1, 6).clone(), hi.expand(3, 1, 6).clone()
    lo3[2, 0, 4] = hi3[2, 0, 4] + 0.1
    mpc = PoseMPC(frame, N8, DT8, QW, RW, u_lower=lo3, u_upper=hi3)
    sol = mpc.solve(Xc, X, T)
    assert sol.status.reason.tolist()[2] == int(Reason.INFEASIBLE_BOUNDS)
    assert bool(torch.isnan(sol.u[2]).all())
    one = PoseMPC(frame, N8, DT8, QW, RW, u_lower=lo, u_upper=hi)
    for b in (0, 1):
        ref = one.solve(Xc[b], X[b], T[b])
        assert int(sol.status.reason[b]) == int(ref.status.reason) == 0
        torch.testing.assert_close(sol.U[b], ref.U, rtol=0, atol=1e-9)


def test_nan_limits_follow_one_rule():
    """A NaN in a tensor limit makes its element NONFINITE_INPUT (never silently ignored); a NaN float is a
    ValueError at construction."""
    x0, xr, ur = _di_problem()
    hi = torch.ones(3, 1, 1, dtype=D)
    hi[0, 0, 0] = math.nan
    sol = _di_mpc(u_lower=-torch.ones(3, 1, 1, dtype=D), u_upper=hi).solve(x0, xr, ur)
    assert sol.status.reason.tolist() == [int(Reason.NONFINITE_INPUT), 0, 0]
    assert bool(torch.isnan(sol.U[0]).all())
    for i in (1, 2):
        torch.testing.assert_close(sol.U[i, :, 0], torch.tensor(_bvls(X0S[i], N5, -1.0, 1.0), dtype=D),
                                   rtol=0, atol=1e-8)
    # a NaN in a shared tensor limit: every element, also where no other limit is finite
    for lo, hi in ((torch.tensor([math.nan], dtype=D), None), (-1.0, torch.tensor([math.nan], dtype=D))):
        sol = _di_mpc(u_lower=lo, u_upper=hi).solve(x0, xr, ur)
        assert sol.status.reason.tolist() == [int(Reason.NONFINITE_INPUT)] * 3
    with pytest.raises(ValueError, match="u_upper"):
        _di_mpc(u_upper=math.nan)


# ------------------------------------------------------------------------------------------------------
# item 3: weights
# ------------------------------------------------------------------------------------------------------


def test_shared_weights_that_are_not_symmetric_psd_are_value_errors():
    s = DoubleIntegrator()
    R = torch.tensor([RD], dtype=D)
    Q = torch.tensor([1.0, 0.1], dtype=D)
    bad_Q = {
        "asymmetric": torch.tensor([[1.0, 2.0], [0.0, 1.0]], dtype=D),  # sym part PD: still rejected
        "indefinite": torch.tensor([[1.0, 2.0], [2.0, 1.0]], dtype=D),
        "negative diagonal": torch.tensor([1.0, -0.1], dtype=D),
        "NaN": torch.tensor([1.0, math.nan], dtype=D),
    }
    for Qb in bad_Q.values():
        with pytest.raises(ValueError, match="'Q'"):
            ErrorStateMPC(s, N5, Qb, R, u_upper=1.0)
        with pytest.raises(ValueError, match="'P'"):
            ErrorStateMPC(s, N5, Q, R, Qb, u_upper=1.0)
    for r in (-0.1, 0.0, math.nan):
        Rb = torch.tensor([r], dtype=D)
        with pytest.raises(ValueError, match="'R'"):
            ErrorStateMPC(s, N5, Q, Rb, u_upper=1.0)
    with pytest.raises(ValueError, match="'Q'"):
        PoseMPC("se3", N8, DT8, -QW, RW)


@pytest.mark.parametrize("bounded", [False, True])
def test_batched_weight_defects_are_per_element_statuses_and_isolated(bounded):
    x0, xr, ur = _di_problem()
    Q = torch.tensor([[1.0, 0.1], [1.0, 0.1], [1.0, 0.1]], dtype=D)  # (3, 2): batched diagonals
    Q[1, 1] = -0.5
    R = torch.tensor([[RD], [-RD], [RD]], dtype=D, requires_grad=True)
    lim = dict(u_lower=-1.0, u_upper=1.0) if bounded else {}
    mpc = ErrorStateMPC(DoubleIntegrator(), N5, Q, R, **lim)
    sol = mpc.solve(x0, xr, ur)
    # element 1 has both defects: the first check (Q) is reported; nothing later overwrites it
    assert sol.status.reason.tolist() == [0, int(Reason.NOT_POSITIVE_DEFINITE), 0]
    assert bool(torch.isnan(sol.U[1]).all())
    for i in (0, 2):
        ref = _bvls(X0S[i], N5, -1.0 if bounded else -INF, 1.0 if bounded else INF)
        torch.testing.assert_close(sol.U[i, :, 0], torch.tensor(ref, dtype=D), rtol=0, atol=1e-8)
    (g,) = torch.autograd.grad(torch.nan_to_num(sol.U).sum(), R)
    assert bool(torch.isfinite(g).all()) and float(g[1].abs()) == 0.0
    # only R bad: NOT_POSITIVE_DEFINITE too (with limits, on main the box QP's CONVERGED overwrote it)
    Q2 = torch.tensor([1.0, 0.1], dtype=D)
    sol = ErrorStateMPC(DoubleIntegrator(), N5, Q2, R.detach(), **lim).solve(x0, xr, ur)
    assert sol.status.reason.tolist() == [0, int(Reason.NOT_POSITIVE_DEFINITE), 0]
    # a batched asymmetric Q is that element's defect too (the one rule, controllers._validate.check_weight)
    Qa = torch.diag_embed(Q2.expand(3, 2)).clone()
    Qa[2, 0, 1] = 0.5
    sol = ErrorStateMPC(DoubleIntegrator(), N5, Qa, R.detach().abs(), **lim).solve(x0, xr, ur)
    assert sol.status.reason.tolist() == [0, 0, int(Reason.NOT_POSITIVE_DEFINITE)]


# ------------------------------------------------------------------------------------------------------
# item 4 (ErrorStateMPC / PoseMPC part): float32
# ------------------------------------------------------------------------------------------------------


def test_float32_long_horizon_plan_is_the_bounded_least_squares_minimizer():
    N, dt, B = 40, 0.125, 16  # dt exact in binary: the float32 model is the float64 one
    Qd, Rd = np.diag([1.0, 0.1]), 0.01
    x0 = torch.randn(B, 2, generator=torch.Generator().manual_seed(0), dtype=D)
    x0 = x0 * torch.tensor([3.0, 1.0], dtype=D)
    f = torch.float32
    mpc = ErrorStateMPC(DoubleIntegrator(dt), N, torch.tensor([1.0, 0.1], dtype=f),
                        torch.tensor([Rd], dtype=f), u_lower=-1.0, u_upper=1.0)
    sol = mpc.solve(x0.to(f), torch.zeros(B, N + 1, 2, dtype=f), torch.zeros(B, N, 1, dtype=f))
    assert sol.U.dtype == f
    x0_32 = x0.to(f).double()
    for i in range(B):
        M, b = _dense(x0_32[i].numpy(), N, dt, Qd, Rd)
        ref = lsq_linear(M, -b, bounds=(-1.0, 1.0), method="bvls", tol=1e-14).x
        u = sol.U[i, :, 0].double().numpy()
        J, Jr = np.sum((M @ u + b) ** 2), np.sum((M @ ref + b) ** 2)
        if bool(sol.status.converged[i]):  # a certificate: the objective within reach of the optimum
            assert (J - Jr) / Jr < 1e-6, (i, (J - Jr) / Jr)
            assert np.abs(u - ref).max() < 1e-4, (i, np.abs(u - ref).max())
    assert bool(sol.status.converged.all())


def test_float32_gradients_flow_and_match_float64():
    f = torch.float32
    x0, xr, ur = _di_problem()
    x32 = x0.to(f).requires_grad_(True)
    sol32 = _di_mpc(dtype=f, u_upper=1.0).solve(x32, xr.to(f), ur.to(f))
    (g32,) = torch.autograd.grad(sol32.U.sum(), x32)
    x64 = x0.clone().requires_grad_(True)
    sol64 = _di_mpc(u_upper=1.0).solve(x64, xr, ur)
    (g64,) = torch.autograd.grad(sol64.U.sum(), x64)
    assert g32.dtype == f
    torch.testing.assert_close(g32.double(), g64, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(sol32.U.double(), sol64.U.detach(), rtol=1e-5, atol=1e-5)


def test_pose_mpc_local_float32_plan_matches_float64():
    Xc, X, T = _pose_problem(4, 13, off_scale=0.5)
    lo, hi = twist_box(0.5, 1.0)
    sols = {}
    for dt_ in (torch.float32, D):
        mpc = PoseMPC("local", N8, DT8, QW.to(dt_), RW.to(dt_), u_lower=lo.to(dt_), u_upper=hi.to(dt_))
        sols[dt_] = mpc.solve(Xc.to(dt_), X.to(dt_), T.to(dt_))
    assert bool(sols[D].clamped.any())
    assert bool(sols[torch.float32].status.converged.all())
    assert float((sols[torch.float32].U.double() - sols[D].U).abs().max()) < 1e-4  # main: 0.13


# ------------------------------------------------------------------------------------------------------
# item 6: NaN isolation in the world frame
# ------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("frame", FRAMES)
def test_a_nan_pose_does_not_poison_the_gradient_of_a_shared_weight(frame):
    Xc, X, T = _pose_problem(3, 21, off_scale=0.1)
    bad = Xc.clone()
    bad[1, 0, 3] = math.nan

    def loss(Xs, Xr, Tr, q):
        sol = PoseMPC(frame, N8, DT8, q, RW).solve(Xs, Xr, Tr)
        return torch.nan_to_num(sol.u).sum(), sol

    q = QW.clone().requires_grad_(True)
    val, sol = loss(bad, X, T, q)
    assert sol.status.reason.tolist() == [0, int(Reason.NONFINITE_INPUT), 0]
    (g,) = torch.autograd.grad(val, q)
    ref = torch.zeros_like(QW)
    for b in (0, 2):  # the per-sample loop over the good elements
        qb = QW.clone().requires_grad_(True)
        ref += torch.autograd.grad(loss(Xc[b], X[b], T[b], qb)[0], qb)[0]
    assert bool(torch.isfinite(g).all())
    torch.testing.assert_close(g, ref, rtol=1e-9, atol=1e-9)


# ------------------------------------------------------------------------------------------------------
# item 8: SE(3) membership in every frame
# ------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("frame", FRAMES)
def test_non_rigid_poses_are_rejected_in_every_frame(frame):
    Xc, X, T = _pose_problem(2, 3)
    mpc = PoseMPC(frame, N8, DT8, QW, RW)
    scaled = Xc.clone()
    scaled[1, :3, :3] *= 1.5
    with pytest.raises(ValueError, match="'X'.*not on"):
        mpc.solve(scaled, X, T)
    Xs = X.clone()
    Xs[0, 3, :3, :3] *= 1.5
    with pytest.raises(ValueError, match="'X_ref'.*not on"):
        mpc.solve(Xc, Xs, T)


# ------------------------------------------------------------------------------------------------------
# items 12 and 13: errors that name the argument, nothing accepted and ignored
# ------------------------------------------------------------------------------------------------------


def test_limits_of_the_wrong_shape_are_rejected_at_construction():
    for name in ("u_lower", "u_upper"):
        for shape in ((3,), (N5 + 1, 1), (2, N5, 2)):
            with pytest.raises(ValueError, match=f"'{name}'.*\\(\\*B, {N5}, 1\\)"):
                _di_mpc(**{name: torch.zeros(shape, dtype=D)})
        with pytest.raises(TypeError, match=name):
            _di_mpc(**{name: np.zeros(1)})
    with pytest.raises(ValueError, match="'u_upper'"):
        PoseMPC("local", N8, DT8, QW, RW, u_upper=torch.ones(5, dtype=D))


def test_bad_solve_arguments_are_named():
    mpc = _di_mpc(u_upper=1.0)
    x0, xr, ur = _di_problem()
    with pytest.raises(ValueError, match="'warm'"):
        mpc.solve(x0, xr, ur, warm=torch.zeros(3, N5 + 1, 1, dtype=D))
    with pytest.raises(ValueError, match="'warm'"):
        mpc.solve(x0, xr, ur, warm=torch.zeros(2, N5, 1, dtype=D))
    with pytest.raises(TypeError, match="'x0'"):
        mpc.solve(x0.numpy(), xr, ur)
    with pytest.raises(TypeError, match="'u_ref'"):
        mpc.solve(x0, xr, ur.numpy())
    with pytest.raises(ValueError, match="'u_init'"):
        mpc.iterate(x0, xr, ur, u_init=torch.zeros(N5, 2, dtype=D))
    Xc, X, T = _pose_problem(1, 2)
    with pytest.raises(TypeError, match="'X_ref'"):
        PoseMPC("local", N8, DT8, QW.float(), RW.float()).solve(Xc.float(), X, T.float())
    with pytest.raises(TypeError, match="'T_ref'"):
        PoseMPC("se3", N8, DT8, QW, RW).solve(Xc, X, T.float())


def test_options_are_validated_at_construction():
    with pytest.raises(ValueError, match="bogus.*max_iter"):
        _di_mpc(u_upper=1.0, qp_options={"bogus": 1})
    with pytest.raises(ValueError, match="bogus"):
        PoseMPC("se3", N8, DT8, QW, RW, qp_options={"bogus": 1})
    for order in (2.5, -1, True):
        with pytest.raises(ValueError, match="'order'"):
            PoseMPC("local", N8, DT8, QW, RW, order=order)


def test_iterate_reports_input_failures_first():
    x0, xr, ur = _di_problem()
    lo = -torch.ones(3, 1, 1, dtype=D)
    lo[2] = 2.0
    sol = _di_mpc(u_lower=lo, u_upper=1.0).iterate(x0, xr, ur)
    assert sol.status.reason.tolist() == [0, 0, int(Reason.INFEASIBLE_BOUNDS)]
    for i in (0, 1):
        torch.testing.assert_close(sol.U[i, :, 0], torch.tensor(_bvls(X0S[i], N5, -1.0, 1.0), dtype=D),
                                   rtol=0, atol=1e-6)


# ------------------------------------------------------------------------------------------------------
# adversarial round 2: infinite limits that admit no control, argument errors that name the argument
# ------------------------------------------------------------------------------------------------------


def test_a_lower_limit_of_plus_inf_or_an_upper_of_minus_inf_is_infeasible():
    """ilqr's rule: ``u ≥ +inf`` (or ``u ≤ -inf``) has no solution.  A float limit is a ValueError; a tensor
    limit that says so at one step makes that element INFEASIBLE_BOUNDS (the other elements solved as if
    alone: the bounded least-squares minimizer).  Before, such a limit was dropped (an unconstrained plan,
    CONVERGED) or gave STALLED with inf in the plan."""
    for kw in ({"u_lower": math.inf}, {"u_upper": -math.inf}):
        with pytest.raises(ValueError, match=f"'{next(iter(kw))}'"):
            _di_mpc(**kw)
    x0, xr, ur = _di_problem()
    lo = torch.full((3, N5, 1), -0.5, dtype=D)
    hi = torch.full((3, N5, 1), INF, dtype=D)
    lo[0, 1, 0] = INF  # element 0: no feasible control at step 1
    hi[1, 3, 0] = -INF  # element 1: likewise, by its upper limit
    for method in ("solve", "iterate"):
        sol = getattr(_di_mpc(u_lower=lo, u_upper=hi), method)(x0, xr, ur)
        assert sol.status.reason.tolist() == [int(Reason.INFEASIBLE_BOUNDS)] * 2 + [0], method
        assert bool(sol.U[:2].isnan().all())
        ref = torch.tensor(_bvls(X0S[2], N5, -0.5, INF), dtype=D)
        torch.testing.assert_close(sol.U[2, :, 0], ref, rtol=0, atol=1e-6)


def test_bad_state_and_iteration_arguments_are_named():
    mpc = _di_mpc()
    x0, xr, ur = _di_problem(1)
    with pytest.raises(ValueError, match="'x0'.*\\(\\*, 2\\)"):
        mpc.solve(torch.tensor(1.0, dtype=D), xr, ur)  # a 0-d state (was expand's TypeError)
    with pytest.raises(TypeError, match="'x0'.*floating"):
        mpc.solve(x0.long(), xr, ur)  # (was blamed on 'x_ref')
    with pytest.raises(TypeError, match="'x_ref'.*floating"):
        mpc.solve(x0, xr.long(), ur)
    for kw, err in (({"max_iter": "a"}, TypeError), ({"max_iter": 0}, ValueError),
                    ({"line_search_steps": 2.5}, TypeError), ({"tol": -1.0}, ValueError),
                    ({"tol": math.nan}, ValueError), ({"tol": "1e-8"}, TypeError)):
        with pytest.raises(err, match=f"'{next(iter(kw))}'"):
            mpc.iterate(x0, xr, ur, **kw)


@pytest.mark.parametrize("frame", FRAMES)
def test_pose_mpc_names_its_own_arguments(frame):
    """PoseMPC's errors name X / X_ref / T_ref and PoseMPC (the local frame raised a raw matmul error for
    batches that do not broadcast; a wrong T_ref was reported as ErrorStateMPC's 'u_ref')."""
    mpc = PoseMPC(frame, N8, DT8, QW, RW)
    X0, X, T = _pose_problem(3, 5)
    with pytest.raises(ValueError, match="PoseMPC.solve.*X \\(2,\\), X_ref \\(3,\\)"):
        mpc.solve(X0[:2], X, T)
    with pytest.raises(ValueError, match="PoseMPC.solve: argument 'T_ref'.*\\(\\*B, 8, 6\\)"):
        mpc.solve(X0, X, T[..., :3])


# ------------------------------------------------------------------------------------------------------
# the iterated variant: a scale-invariant certificate, the same values with gradients, gradients in x0
# ------------------------------------------------------------------------------------------------------

X0_LONG = [1.97, 1.03]


def _lsq_oracle(x0, N, lo, hi):
    """The bounded least-squares plan: the better of scipy's trf (tight tolerances) and bvls (bvls alone is
    wrong on the double integrator at N ≥ 40)."""
    M, b = _dense(x0, N)
    lo, hi = np.full(N, lo), np.full(N, hi)
    plans = [lsq_linear(M, -b, bounds=(lo, hi), method="trf", lsq_solver="exact", tol=1e-15,
                        max_iter=10000).x,
             lsq_linear(M, -b, bounds=(lo, hi), method="bvls", tol=1e-15).x]
    costs = [float(np.sum((M @ p + b) ** 2)) for p in plans]
    return plans[int(np.argmin(costs))], min(costs)


@pytest.mark.parametrize(("scale", "dtype"), [(1.0, D), (1e5, D), (1e-4, D), (1.0, torch.float32),
                                              (1e5, torch.float32)])
def test_iterate_certificate_is_scale_invariant(scale, dtype):
    """Scaling Q and R together leaves the minimizer unchanged: iterate returns it, CONVERGED, at every
    scale and in float32.  Before, the stopping test (projected gradient, bounded by the width of the box,
    against the size of the gradient's terms, which grows with the weights) passed at the starting point:
    U = u_ref, 0 iterations, a cost 31 times the optimum, at scale 1e5 (and at scale 1 in float32)."""
    N = 30
    ref, ref_cost = _lsq_oracle(X0_LONG, N, -0.4, 0.6)
    mpc = ErrorStateMPC(DoubleIntegrator(), N, scale * torch.tensor([1.0, 0.1], dtype=dtype),
                        scale * torch.tensor([RD], dtype=dtype), u_lower=-0.4, u_upper=0.6)
    with torch.no_grad():
        sol = mpc.iterate(torch.tensor(X0_LONG, dtype=dtype), torch.zeros(N + 1, 2, dtype=dtype),
                          torch.zeros(N, 1, dtype=dtype))
    assert sol.status.reason.item() == int(Reason.CONVERGED)
    atol, rtol = (1e-6, 1e-10) if dtype == D else (2e-3, 1e-5)
    np.testing.assert_allclose(sol.U[:, 0].double().numpy(), ref, rtol=0, atol=atol)
    assert float(sol.cost) / scale <= ref_cost * (1 + rtol)
    assert float(sol.kkt_residual) <= 1e3 * torch.finfo(dtype).eps


@pytest.mark.parametrize("dtype", [D, torch.float32])
def test_iterate_returns_the_same_values_with_and_without_gradients(dtype):
    """The differentiable step at the certified point changes no value (before, with gradients enabled a
    final uncertified Gauss-Newton step was added: another plan in float32)."""
    N = 30
    mpc = ErrorStateMPC(DoubleIntegrator(), N, torch.tensor([1.0, 0.1], dtype=dtype),
                        torch.tensor([RD], dtype=dtype), u_lower=-0.4, u_upper=0.6)
    x0 = torch.tensor([X0_LONG, [-0.5, 0.2]], dtype=dtype)
    args = (torch.zeros(2, N + 1, 2, dtype=dtype), torch.zeros(2, N, 1, dtype=dtype))
    with torch.no_grad():
        plain = mpc.iterate(x0, *args)
    graph = mpc.iterate(x0.clone().requires_grad_(True), *args)
    assert graph.U.requires_grad
    for name in ("U", "cost", "kkt_residual", "dx", "x", "clamped"):
        assert torch.equal(getattr(plain, name), getattr(graph, name)), name
    assert torch.equal(plain.status.reason, graph.status.reason)


@pytest.mark.parametrize(("x0", "lo", "hi"), [([0.93, 0.47], -INF, 0.5), ([-1.0, 0.3], -0.6, 0.9)])
def test_iterate_gradients_in_x0_match_central_differences(x0, lo, hi):
    """dU/dx0 and dx/dx0 of iterate against central differences of the bounded least-squares plan (and its
    rollout written out).  Before, U did not depend on x0 in the graph (requires_grad False) and x only
    through the final rollout."""
    N = 5
    mpc = _di_mpc(u_lower=lo, u_upper=hi)
    xr, ur = torch.zeros(N + 1, 2, dtype=D), torch.zeros(N, 1, dtype=D)
    A = np.array([[1.0, DT], [0.0, 1.0]])
    Bm = np.array([0.0, DT])

    def oracle(z):
        U = _bvls(z, N, lo, hi)
        xs = [np.asarray(z, dtype=float)]
        for u in U:
            xs.append(A @ xs[-1] + Bm * u)
        return np.concatenate([U, np.stack(xs).ravel()])

    h = 1e-6
    fd = np.stack([(oracle(np.add(x0, h * e)) - oracle(np.subtract(x0, h * e))) / (2 * h)
                   for e in np.eye(2)], -1)
    z = torch.tensor(x0, dtype=D, requires_grad=True)
    sol = mpc.iterate(z, xr, ur)
    assert sol.status.reason.item() == int(Reason.CONVERGED) and sol.U.requires_grad
    out = torch.cat([sol.U.reshape(-1), sol.x.reshape(-1)])
    jac = torch.stack([torch.autograd.grad(o, z, retain_graph=True)[0] for o in out]).numpy()
    np.testing.assert_allclose(jac, fd, rtol=0, atol=1e-6)
