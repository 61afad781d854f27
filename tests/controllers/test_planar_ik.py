"""Planar FK/Jacobians/IK (seed 004 §4-§5): the seed's matrix formulas, PlanarArm, torch.func and finite
differences; pseudo-inverse and null-space projector properties; IK and prioritized IK against scipy."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.optimize
import torch
from torch.func import jacrev

from controllers.planar_ik import (
    damped_pinv,
    nullspace_projector,
    planar_fk,
    planar_fk_links,
    planar_ik,
    planar_jacobian,
    planar_residual,
    task_priority_ik,
    task_priority_ik_step,
)
from controllers.problem import Reason
from controllers.systems import PlanarArm

D64 = torch.float64
ELL = (2.0, 2.0, 1.0)


def _gen(seed=0):
    return torch.Generator().manual_seed(seed)


def _seed_fk_np(x, ell):
    """§4 / Eq. 18 with numpy matrices: L diag(ℓ) cos(L x), L diag(ℓ) sin(L x), L x."""
    D = len(x)
    L = np.tril(np.ones((D, D)))
    return np.stack([L @ np.diag(ell) @ np.cos(L @ x), L @ np.diag(ell) @ np.sin(L @ x), L @ x])


def _seed_jac_np(x, ell):
    D = len(x)
    L = np.tril(np.ones((D, D)))
    return np.stack([-np.sin(L @ x) @ np.diag(ell) @ L, np.cos(L @ x) @ np.diag(ell) @ L, np.ones(D)])


def test_fk_and_jacobian_match_the_seed_formulas_and_planar_arm():
    q = torch.randn(7, 3, generator=_gen(), dtype=D64)
    links = planar_fk_links(q, ELL)
    J = planar_jacobian(q, ELL)
    arm = PlanarArm(links=3, lengths=ELL)
    for i in range(7):
        ref = _seed_fk_np(q[i].numpy(), np.array(ELL))
        np.testing.assert_allclose(links[i].numpy().T, ref, atol=1e-13)
        np.testing.assert_allclose(J[i].numpy(), _seed_jac_np(q[i].numpy(), np.array(ELL)), atol=1e-13)
    torch.testing.assert_close(planar_fk(q, ELL), links[..., -1, :])
    torch.testing.assert_close(links[..., :2], arm.fk(q)[..., 1:, :], atol=1e-14, rtol=0)
    torch.testing.assert_close(J[..., :2, :], arm.ee_jacobian(q), atol=1e-14, rtol=0)


@pytest.mark.parametrize("link", [0, 1, 2, -1])
def test_jacobians_vs_torch_func_and_finite_differences(link):
    q = torch.randn(3, generator=_gen(1), dtype=D64)
    ell = torch.tensor([0.7, 1.1, 0.4], dtype=D64)
    J = planar_jacobian(q, ell, link)
    Jt = jacrev(lambda q_: planar_fk_links(q_, ell)[link])(q)
    torch.testing.assert_close(J, Jt, atol=1e-14, rtol=0)
    h = 1e-6
    fk = planar_fk_links
    fd = torch.stack([(fk(q + h * e, ell)[link] - fk(q - h * e, ell)[link]) / (2 * h)
                      for e in torch.eye(3, dtype=D64)], -1)
    torch.testing.assert_close(J, fd, atol=1e-8, rtol=0)


def test_gradcheck_fk_jacobian_residual():
    q = torch.randn(2, 3, generator=_gen(2), dtype=D64, requires_grad=True)
    ell = torch.tensor([0.7, 1.1, 0.4], dtype=D64, requires_grad=True)
    tgt = torch.randn(2, 2, generator=_gen(3), dtype=D64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda q_, l_: planar_fk_links(q_, l_), (q, ell))
    assert torch.autograd.gradcheck(lambda q_, l_: planar_jacobian(q_, l_, 1), (q, ell))
    assert torch.autograd.gradcheck(lambda q_, t_: planar_residual(q_, ell, t_, 0.3, 0.8)[0], (q, tgt))


def test_residual_object_frame_eq20():
    q = torch.randn(4, 3, generator=_gen(4), dtype=D64)
    tgt = torch.randn(4, 2, generator=_gen(5), dtype=D64)
    a = torch.tensor([0.0, 0.5, -2.0, 3.0], dtype=D64)
    f, J = planar_residual(q, ELL, tgt, object_angle=a)
    f0, J0 = planar_residual(q, ELL, tgt)
    U = torch.stack([torch.stack([a.cos(), -a.sin()], -1), torch.stack([a.sin(), a.cos()], -1)], -2)
    torch.testing.assert_close(f, (U.mT @ f0[..., None])[..., 0])
    torch.testing.assert_close(J, U.mT @ J0)
    # the orientation row: a geodesic residual in (-π, π], Jacobian 1ᵀ
    f3, J3 = planar_residual(q, ELL, tgt, orientation=q.sum(-1) + 2 * math.pi + 0.1)
    torch.testing.assert_close(f3[..., 2], torch.full((4,), -0.1, dtype=D64))
    torch.testing.assert_close(J3[..., 2, :], torch.ones(4, 3, dtype=D64))


def test_damped_pinv_and_nullspace_projector_properties():
    J = torch.randn(5, 2, 4, generator=_gen(6), dtype=D64)
    torch.testing.assert_close(damped_pinv(J), torch.linalg.pinv(J))
    lam = 0.3
    ref = J.mT @ torch.linalg.inv(J @ J.mT + lam ** 2 * torch.eye(2, dtype=D64))
    torch.testing.assert_close(damped_pinv(J, lam), ref)
    for N in (nullspace_projector(J), nullspace_projector(J, method="pinv")):
        torch.testing.assert_close(J @ N, torch.zeros(5, 2, 4, dtype=D64), atol=1e-13, rtol=0)
        torch.testing.assert_close(N @ N, N)
        torch.testing.assert_close(N, N.mT)
        torch.testing.assert_close(torch.linalg.matrix_rank(N, atol=1e-9), torch.full((5,), 2))
    torch.testing.assert_close(nullspace_projector(J), nullspace_projector(J, method="pinv"))
    # full column rank: N = 0; a singular (stretched) arm: finite, rank k - 1 of the position Jacobian
    Jt = torch.randn(3, 4, 2, generator=_gen(7), dtype=D64)
    torch.testing.assert_close(nullspace_projector(Jt), torch.zeros(3, 2, 2, dtype=D64), atol=1e-14, rtol=0)
    Js = planar_jacobian(torch.zeros(3, dtype=D64), ELL)[:2]
    Ns = nullspace_projector(Js)
    assert torch.linalg.matrix_rank(Ns, atol=1e-9) == 2 and torch.isfinite(damped_pinv(Js)).all()
    torch.testing.assert_close(Js @ Ns, torch.zeros(2, 3, dtype=D64), atol=1e-14, rtol=0)
    Jg = torch.randn(2, 3, generator=_gen(8), dtype=D64, requires_grad=True)
    assert torch.autograd.gradcheck(nullspace_projector, (Jg,))
    assert torch.autograd.gradcheck(lambda j: damped_pinv(j, 0.1), (Jg,))


def _targets(n, seed):
    """Reachable poses (from random joint angles) for the 3-link arm."""
    qt = 2 * torch.rand(n, 3, generator=_gen(seed), dtype=D64) - 1
    return qt, planar_fk(qt, ELL)


def test_ik_position_orientation_against_scipy():
    qt, pose = _targets(6, 9)
    q0 = qt + 0.3 * torch.randn(6, 3, generator=_gen(20), dtype=D64)
    res = planar_ik(ELL, pose[:, :2], q0, orientation=pose[:, 2], tol=1e-10)
    assert res.converged.all() and (res.reason == int(Reason.CONVERGED)).all()
    torch.testing.assert_close(planar_fk(res.q, ELL)[:, :2], pose[:, :2], atol=1e-9, rtol=0)
    for i in range(6):  # 3 equations, 3 unknowns: scipy from the same start lands on the same solution
        def fun(x, i=i):
            return planar_residual(torch.tensor(x), ELL, pose[i, :2], pose[i, 2])[0].numpy()
        ref = scipy.optimize.least_squares(fun, q0[i].numpy(), xtol=1e-15, ftol=1e-15, gtol=1e-15).x
        dq = torch.remainder(res.q[i] - torch.tensor(ref) + math.pi, 2 * math.pi) - math.pi
        assert dq.abs().max() < 1e-7


def test_ik_unreachable_matches_scipy_least_squares_and_is_not_converged():
    tgt = torch.tensor([[6.0, 0.0], [0.0, -5.5], [3.0, 4.5]], dtype=D64)  # reach 5
    q0 = torch.tensor([0.3, 0.2, 0.1], dtype=D64)
    res = planar_ik(ELL, tgt, q0, max_iter=300)
    assert not res.converged.any()
    assert (res.reason == int(Reason.STALLED)).all()  # a stationary point, not the target
    for i in range(3):
        ref = scipy.optimize.least_squares(
            lambda x, i=i: planar_residual(torch.tensor(x), ELL, tgt[i])[0].numpy(), q0.numpy())
        best = math.sqrt(2 * ref.cost)
        assert abs(best - (tgt[i].norm().item() - 5.0)) < 1e-4  # the reference is the stretched arm
        assert abs(res.residual[i] - best) < 1e-8


def test_ik_object_frame_weighting():
    """Eq. 20: errors in the object frame U; weight [1, 0] there asks only for the object's x coordinate."""
    _, pose = _targets(4, 10)
    a = torch.tensor([0.3, -1.0, 2.0, 0.0], dtype=D64)
    w = torch.tensor([1.0, 0.0], dtype=D64)
    q0 = torch.full((3,), 0.2, dtype=D64)
    res = planar_ik(ELL, pose[:, :2], q0, object_angle=a, weight=w)
    assert res.converged.all()
    f, _ = planar_residual(res.q, ELL, pose[:, :2], object_angle=a)
    assert f[:, 0].abs().max() < 1e-9
    # an SPD matrix weight: the same solution set as the identity (reachable targets)
    Wm = torch.tensor([[2.0, 0.5], [0.5, 1.0]], dtype=D64)
    res2 = planar_ik(ELL, pose[:, :2], q0, object_angle=a, weight=Wm)
    assert res2.converged.all() and res2.pos_err.max() < 1e-8


def test_ik_batched_equals_loop_broadcast_lengths():
    _, pose = _targets(5, 11)
    ell = torch.tensor([[2.0, 2.0, 1.0], [1.5, 2.5, 1.0], [2.0, 1.0, 2.0], [3.0, 1.0, 1.0], [2.0, 2.0, 1.0]],
                       dtype=D64)
    q0 = torch.randn(5, 3, generator=_gen(12), dtype=D64)
    res = planar_ik(ell, pose[:, :2], q0)
    for i in range(5):
        r = planar_ik(ell[i], pose[i, :2], q0[i])
        torch.testing.assert_close(res.q[i], r.q, atol=1e-12, rtol=0)
        assert bool(res.converged[i]) == bool(r.converged) and res.iterations[i] == r.iterations
    # leading batch dims
    res2 = planar_ik(ELL, pose[:, :2].reshape(5, 1, 2).expand(5, 2, 2), q0[:, None, :])
    assert res2.q.shape == (5, 2, 3) and res2.converged.shape == (5, 2)


def test_ik_float32():
    _, pose = _targets(4, 13)
    res = planar_ik(ELL, pose[:, :2].float(), torch.full((3,), 0.3), orientation=pose[:, 2].float(), tol=1e-4)
    assert res.q.dtype == torch.float32 and res.converged.all()
    assert res.pos_err.max() < 1e-4


def test_ik_nan_element_isolated():
    _, pose = _targets(4, 14)
    tgt = pose[:, :2].clone()
    tgt[1, 0] = math.nan
    q0 = torch.full((3,), 0.3, dtype=D64)
    res = planar_ik(ELL, tgt, q0)
    ref = planar_ik(ELL, pose[[0, 2, 3], :2], q0)
    assert res.reason[1] == int(Reason.NONFINITE_INPUT) and not res.converged[1]
    assert torch.isnan(res.q[1]).all()
    torch.testing.assert_close(res.q[[0, 2, 3]], ref.q)
    assert res.converged[[0, 2, 3]].all()


def test_ik_gradient_wrt_target_is_the_implicit_derivative():
    """Non-redundant (2 links, position): dq/dμ = J⁻¹, and gradcheck (finite differences of the solver)."""
    ell = (1.0, 0.8)
    q0 = torch.tensor([0.4, 0.9], dtype=D64)
    tgt = planar_fk(torch.tensor([0.5, 1.0], dtype=D64), ell)[:2].clone().requires_grad_(True)

    def solve(t):
        return planar_ik(ell, t, q0, tol=1e-13, max_iter=60).q

    assert torch.autograd.gradcheck(solve, (tgt,), atol=1e-6)
    q = solve(tgt)
    Jinv = torch.linalg.inv(planar_jacobian(q.detach(), ell)[:2])
    (g,) = torch.autograd.grad(q[0], tgt)
    torch.testing.assert_close(g, Jinv[0], atol=1e-9, rtol=0)


def test_task_priority_step_keeps_the_primary_and_eq22():
    q = torch.randn(6, 3, generator=_gen(15), dtype=D64)
    f1, J1 = planar_residual(q, ELL, torch.randn(6, 2, generator=_gen(16), dtype=D64))
    J2 = torch.eye(3, dtype=D64).expand(6, 3, 3)
    f2 = torch.randn(6, 3, generator=_gen(17), dtype=D64)
    dq = task_priority_ik_step(J1, f1, J2, f2)
    dq0 = task_priority_ik_step(J1, f1)
    torch.testing.assert_close(J1 @ dq[..., None], J1 @ dq0[..., None], atol=1e-12, rtol=0)
    torch.testing.assert_close(dq0, -(torch.linalg.pinv(J1) @ f1[..., None])[..., 0])
    g = torch.tensor([1.0, 0.0, 0.0], dtype=D64)  # §5.2: keep the end effector still, move joint 1
    dqg = task_priority_ik_step(J1, torch.zeros_like(f1), g=g)
    N = torch.eye(3, dtype=D64) - torch.linalg.pinv(J1) @ J1
    torch.testing.assert_close(dqg, N @ g)
    assert (J1 @ dqg[..., None]).abs().max() < 1e-12
    # the secondary term is the minimum-norm least-squares step of the secondary task in the null space
    ref = torch.linalg.pinv(J2 @ N, rtol=1e-10) @ -(f2 + (J2 @ dq0[..., None])[..., 0])[..., None]
    Nref = (N @ ref)[..., 0]
    torch.testing.assert_close(dq - dq0, Nref, atol=1e-5, rtol=0)
    J1g = J1.clone().requires_grad_(True)
    f2g = f2.clone().requires_grad_(True)
    out = task_priority_ik_step(J1g, f1, J2, f2g, secondary_damping=0.0)
    gJ, gf = torch.autograd.grad(out.sum(), (J1g, f2g))
    assert torch.isfinite(gJ).all() and torch.isfinite(gf).all()


def test_task_priority_ik_against_scipy_slsqp():
    """min ‖q - q_ref‖² s.t. f^ee(q) = μ: the certified fixed point is the constrained optimum (SLSQP)."""
    qt, pose = _targets(4, 18)
    q_ref = torch.zeros(3, dtype=D64)
    res = task_priority_ik(ELL, pose[:, :2], qt + 0.05, q_ref)
    assert res.converged.all() and res.primary_residual.max() < 1e-9
    plain = planar_ik(ELL, pose[:, :2], qt + 0.05)
    assert ((res.q - q_ref).norm(dim=-1) < (plain.q - q_ref).norm(dim=-1)).all()
    for i in range(4):
        cons = {"type": "eq",
                "fun": lambda x, i=i: planar_residual(torch.tensor(x), ELL, pose[i, :2])[0].numpy()}
        ref = scipy.optimize.minimize(lambda x: float(np.sum((x - q_ref.numpy()) ** 2)),
                                      res.q[i].numpy() + 0.01, constraints=[cons], method="SLSQP",
                                      options={"ftol": 1e-14, "maxiter": 500})
        np.testing.assert_allclose(res.q[i].numpy(), ref.x, atol=1e-5)


def test_task_priority_ik_callable_secondary_and_nan():
    qt, _ = _targets(3, 19)
    qt[:, 0] = math.pi / 2  # targets reachable with the first link's tip on (0, 2): both tasks feasible
    tgt = planar_fk(qt, ELL)[:, :2].clone()
    tgt[2] = math.nan
    elbow = torch.tensor([0.0, 2.0], dtype=D64)  # secondary: the tip of link 1 towards (0, 2)

    def sec(q):
        return planar_fk_links(q, ELL)[..., 0, :2] - elbow, planar_jacobian(q, ELL, 0)[..., :2, :]

    res = task_priority_ik(ELL, tgt, torch.full((3,), 0.4, dtype=D64), sec)
    assert res.converged[:2].all() and res.reason[2] == int(Reason.NONFINITE_INPUT)
    assert res.secondary_residual[:2].max() < 1e-8 and res.primary_residual[:2].max() < 1e-9
    assert torch.isnan(res.q[2]).all() and torch.isfinite(res.q[:2]).all()


def test_bad_input():
    q = torch.zeros(2, 3, dtype=D64)
    with pytest.raises(TypeError, match="'q'"):
        planar_fk([0.0, 1.0], ELL)
    with pytest.raises(ValueError, match="'lengths'"):
        planar_fk(q, (1.0, 2.0))
    with pytest.raises(TypeError, match="'lengths'"):
        planar_fk(q, torch.ones(3))
    with pytest.raises(ValueError, match="'link'"):
        planar_jacobian(q, ELL, 3)
    with pytest.raises(ValueError, match="'target'"):
        planar_ik(ELL, torch.zeros(2, 3, dtype=D64), q)
    with pytest.raises(TypeError, match="'target'"):
        planar_ik(ELL, torch.zeros(2, 2), q)
    with pytest.raises(ValueError, match="'weight'"):
        planar_ik(ELL, torch.zeros(2, 2, dtype=D64), q, weight=torch.tensor([1.0, -1.0], dtype=D64))
    with pytest.raises(ValueError, match="'tol'"):
        planar_ik(ELL, torch.zeros(2, 2, dtype=D64), q, tol=0.0)
    with pytest.raises(ValueError, match="broadcast"):
        planar_ik(ELL, torch.zeros(4, 2, dtype=D64), q)
    with pytest.raises(ValueError, match="'method'"):
        nullspace_projector(torch.zeros(2, 3), method="qr")
    with pytest.raises(ValueError, match="'secondary'"):
        task_priority_ik(ELL, torch.zeros(2, 2, dtype=D64), q, torch.zeros(2, 2, dtype=D64))
    with pytest.raises(ValueError, match="not both"):
        task_priority_ik_step(torch.zeros(2, 3), torch.zeros(2), torch.eye(3), torch.zeros(3),
                              g=torch.zeros(3))


def test_task_priority_ik_batched_equals_loop_and_float32():
    qt, pose = _targets(3, 21)
    q_ref = torch.tensor([[0.0, 0.5, -0.5], [0.3, 0.0, 0.0], [-0.2, 0.2, 0.4]], dtype=D64)
    res = task_priority_ik(ELL, pose[:, :2], qt + 0.05, q_ref)
    for i in range(3):
        r = task_priority_ik(ELL, pose[i, :2], qt[i] + 0.05, q_ref[i])
        torch.testing.assert_close(res.q[i], r.q, atol=1e-12, rtol=0)
        assert res.iterations[i] == r.iterations
    r32 = task_priority_ik(ELL, pose[:, :2].float(), (qt + 0.05).float(), q_ref.float(), tol=1e-4,
                           tol_secondary=1e-4)
    assert r32.q.dtype == torch.float32 and r32.converged.all()
    torch.testing.assert_close(r32.q, res.q.float(), atol=1e-3, rtol=0)


def test_nonfinite_element_gives_nan_only_there():
    g = torch.Generator().manual_seed(5)
    J = torch.randn(4, 2, 3, dtype=torch.float64, generator=g)
    Jn = J.clone()
    Jn[2, 1, 0] = math.nan
    f = torch.randn(4, 2, dtype=torch.float64, generator=g)
    for fn in (damped_pinv, nullspace_projector):
        out = fn(Jn)
        assert out[2].isnan().all()
        torch.testing.assert_close(out[[0, 1, 3]], fn(J[[0, 1, 3]]))
    J2 = torch.randn(4, 3, 3, dtype=torch.float64, generator=g)
    f2 = torch.randn(4, 3, dtype=torch.float64, generator=g)
    step = task_priority_ik_step(Jn, f, J2, f2)
    assert step[2].isnan().all()
    keep = [0, 1, 3]
    torch.testing.assert_close(step[keep], task_priority_ik_step(J[keep], f[keep], J2[keep], f2[keep]))


def test_planar_ik_escapes_the_zero_gradient_home_configuration():
    """From q0 = 0 (stretched arm) J^T f = 0 exactly for targets on the x axis: a saddle if reachable."""
    d = torch.float64
    tgt = torch.tensor([[1.0, 0.0], [0.0, 0.0], [0.5, 0.0], [3.0, 0.0]], dtype=d)  # last: out of reach
    r = planar_ik([1.0, 1.0], tgt, torch.zeros(2, dtype=d))
    assert r.converged[:3].all(), (r.reason, r.residual)
    torch.testing.assert_close(planar_fk(r.q[:3], [1.0, 1.0])[:, :2], tgt[:3], atol=1e-8, rtol=0)
    assert r.reason[3].item() == int(Reason.STALLED)
    assert abs(r.residual[3].item() - 1.0) < 1e-8  # the closest point of the workspace, 2 along x
    # batched == per element
    for i in range(4):
        ri = planar_ik([1.0, 1.0], tgt[i], torch.zeros(2, dtype=d))
        assert ri.reason.item() == r.reason[i].item()


def test_default_tolerances_follow_the_dtype():
    L = [1.0, 0.7, 0.4]
    g = torch.Generator().manual_seed(3)
    tgt = planar_fk(torch.randn(16, 3, dtype=torch.float64, generator=g), L)[:, :2]
    r64 = planar_ik(L, tgt, torch.full((3,), 0.3, dtype=torch.float64))
    r32 = planar_ik(L, tgt.float(), torch.full((3,), 0.3))
    assert r64.converged.all() and r32.converged.all(), (r64.reason, r32.reason)
    assert (r64.residual <= 1e-9).all()
    assert (r32.pos_err <= 1e-4).all()
    # the prioritized solver: float32 converges where float64 does
    L4 = [1.0, 0.7, 0.4, 0.3]
    tg4 = planar_fk(torch.randn(8, 4, dtype=torch.float64, generator=g), L4)[:, :2]
    qref = 0.3 * torch.randn(8, 4, dtype=torch.float64, generator=g)
    p64 = task_priority_ik(L4, tg4, torch.full((4,), 0.1, dtype=torch.float64), qref)
    p32 = task_priority_ik(L4, tg4.float(), torch.full((4,), 0.1), qref.float())
    assert p64.converged.any()
    assert (p32.converged | ~p64.converged).all(), (p64.reason, p32.reason)
    ok = p64.converged
    torch.testing.assert_close(p32.q[ok].double(), p64.q[ok], atol=1e-3, rtol=0)
