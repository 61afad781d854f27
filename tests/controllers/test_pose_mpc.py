"""Pose MPC over body twists (world/local ME2 and SE(3) error state) and the resolved-rate arm step."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from controllers.ik import resolved_rate_step
from controllers.manifold_mpc import manifold_rollout, system_jacobians
from controllers.pose_mpc import FRAMES, ME2LocalModel, ME2WorldModel, PoseMPC, twist_box
from controllers.problem import Reason
from controllers.systems.panda import Panda
from torchlie import magnus, se3, so3

D = torch.float64
N, DT = 8, 0.02
QW = torch.tensor([100.0] * 3 + [30.0] * 3, dtype=D)
RW = torch.tensor([0.01, 0.02, 0.03, 0.01, 0.02, 0.05], dtype=D)


def _gen(seed):
    return torch.Generator().manual_seed(seed)


def _problem(B, seed, twist_scale=0.5):
    g = _gen(seed)
    X0 = se3.random(B, generator=g, dtype=D)
    T = twist_scale * torch.randn(B, N, 6, generator=g, dtype=D)
    X = torch.cat([X0[:, None], magnus.integrate_exact(X0, T, DT)], 1)  # a feasible reference
    return X, T


# ------------------------------------------------------------------------------------------------------
# the models
# ------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("order", [2, None])
def test_world_model_rollout_is_eq16(order):
    X, T = _problem(3, 0)
    xi0 = se3.log(X[:, 0])
    r = manifold_rollout(ME2WorldModel(xi0, DT, order), xi0, T)
    torch.testing.assert_close(r[:, 1:], magnus.predict_world(xi0, T, DT, order=order), rtol=0, atol=1e-14)


def test_local_model_rollout_and_jacobians():
    X, T = _problem(3, 1)
    m = ME2LocalModel(DT)
    r = manifold_rollout(m, torch.zeros(3, 6, dtype=D), T)
    torch.testing.assert_close(r[:, 1:], magnus.predict_local(T, DT), rtol=0, atol=1e-14)
    omega = 0.3 * torch.randn(3, N, 6, generator=_gen(2), dtype=D)
    _, Jx, Ju = system_jacobians(m, omega, T, "analytic")
    _, Ax, Au = system_jacobians(m, omega, T, "autograd")
    torch.testing.assert_close(Jx, Ax, rtol=0, atol=1e-12)
    torch.testing.assert_close(Ju, Au, rtol=0, atol=1e-12)


# ------------------------------------------------------------------------------------------------------
# the MPCs
# ------------------------------------------------------------------------------------------------------


def test_on_a_feasible_reference_se3_returns_the_reference_twists():
    X, T = _problem(4, 3)
    sol = PoseMPC("se3", N, DT, QW, RW).solve(X[:, 0], X, T)
    torch.testing.assert_close(sol.U, T, rtol=0, atol=1e-10)
    # commuting twists (a screw path): the local ME2 model is exact as well
    delta = torch.randn(6, generator=_gen(4), dtype=D)
    Ts = (0.5 + torch.rand(N, 1, generator=_gen(5), dtype=D)) * delta
    Xs = torch.cat([X[:1, 0], magnus.integrate_exact(X[0, 0], Ts, DT)])
    sol = PoseMPC("local", N, DT, QW, RW).solve(Xs[0], Xs, Ts)
    torch.testing.assert_close(sol.U, Ts, rtol=0, atol=1e-9)


def _dense_world(xi0, xi_ref, T_ref, Q, R, order):
    """The world-frame linear MPC as one least-squares problem in numpy (independent of the QP code)."""
    Dm = (magnus.dexp_inv_series(xi0, order) if order is not None else magnus.dexp_inv(xi0)).numpy()
    n = N * 6
    rows, rhs = [], []
    sq = np.sqrt
    for k in range(1, N + 1):  # ξ_k = ξ_0 + Δt D Σ_{j<k} T_j
        S = np.zeros((6, n))
        for j in range(k):
            S[:, 6 * j:6 * j + 6] = DT * Dm
        W = np.diag(sq(Q.numpy()))
        rows.append(W @ S)
        rhs.append(W @ (xi_ref[k].numpy() - xi0.numpy()))
    Wr = np.diag(sq(R.numpy()))
    for k in range(N):
        S = np.zeros((6, n))
        S[:, 6 * k:6 * k + 6] = Wr
        rows.append(S)
        rhs.append(Wr @ T_ref[k].numpy())
    u, *_ = np.linalg.lstsq(np.vstack(rows), np.concatenate(rhs), rcond=None)
    return u.reshape(N, 6)


@pytest.mark.parametrize("order", [2, None])
def test_world_frame_equals_a_dense_least_squares_solve(order):
    X, T = _problem(1, 6)
    Xc = X[0, 0] @ se3.exp(torch.tensor([0.01, -0.02, 0.015, 0.05, -0.03, 0.02], dtype=D))
    sol = PoseMPC("world", N, DT, QW, RW, order=order).solve(Xc, X[0], T[0])
    ref = _dense_world(se3.log(Xc), se3.log(X[0]), T[0], QW, RW, order)
    np.testing.assert_allclose(sol.U.numpy(), ref, rtol=0, atol=1e-8)


@pytest.mark.parametrize("frame", FRAMES)
def test_batched_equals_loop_bounds_hold_and_nan_does_not_poison(frame):
    X, T = _problem(4, 7, twist_scale=0.3)
    off = 0.3 * torch.randn(4, 6, generator=_gen(8), dtype=D)
    Xc = X[:, 0] @ se3.exp(off)  # far enough that the bounds bind
    lo, hi = twist_box(0.5, 1.0)
    mpc = PoseMPC(frame, N, DT, QW, RW, u_lower=lo, u_upper=hi)
    full = mpc.solve(Xc, X, T)
    assert bool(full.status.converged.all()) and bool(full.clamped.any())
    assert float(full.U[..., :3].norm(dim=-1).max()) <= 0.5 + 1e-12
    assert float(full.U[..., 3:].norm(dim=-1).max()) <= 1.0 + 1e-12
    for b in range(4):
        one = mpc.solve(Xc[b], X[b], T[b])
        torch.testing.assert_close(full.U[b], one.U, rtol=0, atol=1e-9)
    bad = Xc.clone()
    bad[1, 0, 3] = float("nan")
    sol = mpc.solve(bad, X, T)
    assert int(sol.status.reason[1]) == Reason.NONFINITE_INPUT and bool(torch.isnan(sol.u[1]).all())
    keep = [0, 2, 3]
    torch.testing.assert_close(sol.U[keep], full.U[keep], rtol=0, atol=1e-9)


def test_cut_locus_world_frame_turns_the_long_way_the_others_do_not():
    """A tool-down reference (rotation angle exactly π) and the arm 0.1 rad past it about the same axis: the
    real error is 0.1 rad, but log puts the two 2π − 0.1 apart, and the world-frame MPC turns that way."""
    Xr = torch.eye(4, dtype=D)
    Xr[:3, :3] = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=D))
    Xr[:3, 3] = torch.tensor([0.3, 0.0, 0.5], dtype=D)
    X = Xr.expand(N + 1, 4, 4)
    T = torch.zeros(N, 6, dtype=D)
    Xc = Xr @ se3.exp(torch.tensor([0.0, 0.0, 0.0, 0.1, 0.0, 0.0], dtype=D))  # angle π + 0.1 → wraps
    assert abs(float(so3.log(Xc[:3, :3]).norm()) - (math.pi - 0.1)) < 1e-12
    short = {}
    for frame in FRAMES:
        u = PoseMPC(frame, N, DT, QW, RW).solve(Xc, X, T).u
        short[frame] = float(u[3])  # body x rate; the short way back is negative
    assert short["se3"] < 0 and short["local"] < 0
    assert short["world"] > 0 and abs(short["world"]) > 10 * abs(short["se3"])


def test_gradients_match_finite_differences_and_gradcheck():
    X, T = _problem(1, 9, twist_scale=0.3)
    Xc = X[0, 0] @ se3.exp(torch.tensor([0.02, 0.01, -0.01, 0.05, 0.02, -0.04], dtype=D))
    w = torch.randn(6, generator=_gen(10), dtype=D)
    for frame in FRAMES:
        mpc = PoseMPC(frame, N, DT, QW, RW)

        def first(Tr, xi, mpc=mpc):
            return (mpc.solve(Xc @ se3.exp(xi), X[0], Tr).u * w).sum()

        Tr = T[0].clone().requires_grad_(True)
        xi = torch.zeros(6, dtype=D, requires_grad=True)
        gT, gx = torch.autograd.grad(first(Tr, xi), (Tr, xi))
        h = 1e-6
        for (i, j) in ((0, 0), (3, 4), (N - 1, 2)):
            E = torch.zeros_like(Tr)
            E[i, j] = h
            fd = (first(T[0] + E, xi.detach()) - first(T[0] - E, xi.detach())) / (2 * h)
            assert abs(float(gT[i, j] - fd)) < 1e-6 * (1 + abs(float(fd))), (frame, i, j)
        for j in (0, 4):
            e = torch.zeros(6, dtype=D)
            e[j] = h
            fd = (first(T[0], e) - first(T[0], -e)) / (2 * h)
            assert abs(float(gx[j] - fd)) < 1e-6 * (1 + abs(float(fd))), (frame, j)
        assert torch.autograd.gradcheck(lambda t, mpc=mpc: mpc.solve(Xc, X[0], t).u,
                                        (T[0].clone().requires_grad_(True),))


def test_bad_inputs_are_named():
    X, T = _problem(1, 11)
    with pytest.raises(ValueError, match="frame"):
        PoseMPC("body", N, DT, QW, RW)
    with pytest.raises(ValueError, match="order"):
        PoseMPC("local", N, DT, QW, RW, order=None)
    with pytest.raises(ValueError, match="'dt'"):
        PoseMPC("se3", N, 0.0, QW, RW)
    mpc = PoseMPC("se3", N, DT, QW, RW)
    with pytest.raises(ValueError, match="'X'"):
        mpc.solve(X[0, 0, :3], X[0], T[0])
    with pytest.raises(ValueError, match="'X_ref'"):
        mpc.solve(X[0, 0], X[0, :-1], T[0])
    with pytest.raises(ValueError, match="v_max"):
        twist_box(0.0, 1.0)


# ------------------------------------------------------------------------------------------------------
# the arm
# ------------------------------------------------------------------------------------------------------


def test_resolved_rate_step_realizes_the_twist_to_first_order_and_respects_limits():
    pytest.importorskip("pytorch_kinematics")
    robot = Panda()
    q = robot.random_q(16, _gen(12), D)
    lo, hi = robot.joint_limits(D)
    q = lo + 0.2 * (hi - lo) + 0.6 * (q - lo)  # away from the limits
    twist = 0.05 * torch.randn(16, 6, generator=_gen(13), dtype=D)
    X0 = robot.fk(q)
    errs = []
    for dt in (1e-3, 5e-4):
        q1, qd = resolved_rate_step(robot, q, twist, dt, damping=1e-6, nullspace_gain=0.0)
        free = (qd.abs() < 0.999 * robot.velocity_limits(D)).all(-1)  # not slowed down by a speed limit
        assert int(free.sum()) >= 12
        pred = X0 @ se3.exp(dt * twist)
        errs.append(float(se3.log(se3.inverse(pred) @ robot.fk(q1))[free].norm(dim=-1).max()))
    assert errs[0] < 1e-6 and errs[1] < 0.3 * errs[0]  # second order in dt
    # a huge twist: joint speeds scaled to the limits, positions clipped to the range
    q1, qd = resolved_rate_step(robot, q, 100 * twist, 0.5)
    assert bool((qd.abs() <= robot.velocity_limits(D) + 1e-12).all())
    assert bool(((q1 >= lo) & (q1 <= hi)).all())


def test_large_batch_goes_riccati_first_and_equals_per_sample_with_gradients():
    """A batch big enough that the condensed QPs would cost O(B N³): solved by Riccati, then the box QP only
    for the elements that break a bound; values and gradients equal the per-element (condensed) solves."""
    from controllers import manifold_mpc

    B, Nl = 12, 30
    g = _gen(20)
    X0 = se3.random(B, generator=g, dtype=D)
    T = 0.1 * torch.randn(B, Nl, 6, generator=g, dtype=D)
    X = torch.cat([X0[:, None], magnus.integrate_exact(X0, T, DT)], 1)
    scale = torch.where(torch.arange(B) % 3 == 0, 0.3, 0.002).to(D)[:, None]  # every third far off
    Xc = X[:, 0] @ se3.exp(scale * torch.randn(B, 6, generator=g, dtype=D))
    lo, hi = twist_box(0.5, 1.0)
    assert B * (Nl * 6) ** 2 * (Nl + 1) * 6 > manifold_mpc._RICCATI_FIRST_FLOPS
    assert (Nl * 6) ** 2 * (Nl + 1) * 6 < manifold_mpc._RICCATI_FIRST_FLOPS
    for frame in FRAMES:
        Tr = T.clone().requires_grad_(True)
        mpc = PoseMPC(frame, Nl, DT, QW, RW, u_lower=lo, u_upper=hi)
        full = mpc.solve(Xc, X, Tr)
        on_bound = full.clamped.flatten(1).any(1)
        assert 0 < int(on_bound.sum()) < B and bool(full.status.converged.all())
        w = torch.randn(B, 6, generator=_gen(21), dtype=D)
        gfull = torch.autograd.grad((full.u * w).sum(), Tr)[0]
        for b in range(B):
            Tb = T[b].clone().requires_grad_(True)
            one = mpc.solve(Xc[b], X[b], Tb)
            torch.testing.assert_close(full.U[b], one.U, rtol=0, atol=1e-8)
            assert bool(one.clamped.any()) == bool(on_bound[b])
            gb = torch.autograd.grad((one.u * w[b]).sum(), Tb)[0]
            torch.testing.assert_close(gfull[b], gb, rtol=1e-7, atol=1e-8)
