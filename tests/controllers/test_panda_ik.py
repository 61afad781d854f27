"""Panda kinematics (pytorch-kinematics on the shipped URDF vs an independent DH product) and batched IK."""

import math

import pytest
import torch

from controllers.ik import dls_joint_velocity, joint_limit_gradient, solve_ik
from controllers.problem import Reason
from controllers.systems.panda import Panda
from torchlie import se3

pytest.importorskip("pytorch_kinematics")

D64 = torch.float64


@pytest.fixture(scope="module")
def panda():
    return Panda()


def _q(n, seed, dtype=D64):
    return Panda.random_q(n, torch.Generator().manual_seed(seed), dtype=dtype)


# -------------------------------------------------------------------------------------------------- FK
def test_fk_published_poses(panda):
    # Franka's modified-DH table (https://frankaemika.github.io/docs/control_parameters.html).  At q = 0 the
    # arm is stretched up: x = a4 + a5 + a7 = 0.0825 − 0.0825 + 0.088, z = d1 + d3 + d5 − d_F =
    # 0.333 + 0.316 + 0.384 − 0.107 (the flange points down), R = diag(1, −1, −1).
    T0 = panda.fk(torch.zeros(7, dtype=D64))
    expect = torch.tensor([[1.0, 0, 0, 0.088], [0, -1, 0, 0], [0, 0, -1, 0.926], [0, 0, 0, 1]], dtype=D64)
    torch.testing.assert_close(T0, expect, atol=1e-12, rtol=0)
    # q4 = −π/2 (others 0), by hand from the same table: the upper arm is vertical (z = d1 + d3 at the elbow,
    # x = a4), the forearm then runs along +x (d5) rising by −a5 = 0.0825, a7 = 0.088 drops the wrist and the
    # flange axis points along −x: p = (a4 + d5 − d_F, 0, d1 + d3 − a5 − a7), z_F = −x.
    q = torch.zeros(7, dtype=D64)
    q[3] = -math.pi / 2
    T = panda.fk(q)
    expect = torch.tensor([0.0825 + 0.384 - 0.107, 0.0, 0.333 + 0.316 + 0.0825 - 0.088], dtype=D64)
    torch.testing.assert_close(T[:3, 3], expect, atol=1e-12, rtol=0)
    torch.testing.assert_close(T[:3, 2], torch.tensor([-1.0, 0, 0], dtype=D64), atol=1e-12, rtol=0)
    # The "ready" pose of libfranka/franka_ros (q = (0, −π/4, 0, −3π/4, 0, π/2, π/4)): with the Franka Hand
    # the published end-effector pose O_T_EE is x ≈ 0.307, z ≈ 0.487, R = diag(1, −1, −1).
    T = Panda("panda_hand_tcp").fk(Panda.home(D64))
    flip = torch.diag(torch.tensor([1.0, -1, -1], dtype=D64))
    torch.testing.assert_close(T[:3, :3], flip, atol=1e-12, rtol=0)
    torch.testing.assert_close(T[:3, 3], torch.tensor([0.307, 0.0, 0.487], dtype=D64), atol=1e-3, rtol=0)


@pytest.mark.parametrize("end", ["panda_link8", "panda_hand", "panda_hand_tcp"])
def test_fk_pk_equals_dh(end):
    P = Panda(end)
    q = _q((4, 25), 0)
    T = P.fk(q)
    assert T.shape == (4, 25, 4, 4) and T.dtype == D64
    assert (T - P.fk_dh(q)).abs().max() < 1e-12
    T32 = P.fk(q.float())
    assert T32.dtype == torch.float32 and (T32.double() - T).abs().max() < 1e-5


def test_urdf_limits_match_published(panda):
    chain = panda.chain()
    lo, hi = chain.get_joint_limits()
    q_min, q_max = Panda.joint_limits(D64)
    assert lo == q_min.tolist() and hi == q_max.tolist()
    assert [v[1] for v in zip(*chain.get_joint_velocity_limits())] == Panda.velocity_limits(D64).tolist()


# -------------------------------------------------------------------------------------------------- Jacobian
def test_jacobian_vs_central_differences(panda):
    q = _q(6, 1)
    T, Jb = panda.fk_and_jacobian(q, "body")
    h = 1e-6
    cols = []
    for i in range(7):
        dq = torch.zeros(7, dtype=D64)
        dq[i] = h
        # body twist: T(q + h e_i) ≈ T exp(h J_b e_i)
        xp = se3.log(se3.compose(se3.inverse(T), panda.fk(q + dq)))
        xm = se3.log(se3.compose(se3.inverse(T), panda.fk(q - dq)))
        cols.append((xp - xm) / (2 * h))
    assert (torch.stack(cols, -1) - Jb).abs().max() < 1e-8
    # world (pytorch-kinematics) and spatial frames from the body one
    Jw, Js = panda.jacobian(q, "world"), panda.jacobian(q, "spatial")
    torch.testing.assert_close(Js, se3.adjoint(T) @ Jb, atol=1e-12, rtol=0)
    R, p = T[..., :3, :3], T[..., :3, 3]
    torch.testing.assert_close(Jw[..., 3:, :], R @ Jb[..., 3:, :], atol=1e-12, rtol=0)
    torch.testing.assert_close(Jw[..., :3, :], R @ Jb[..., :3, :], atol=1e-12, rtol=0)
    assert p.shape == (6, 3)


def test_jacobian_vs_jacrev_of_fk_dh(panda):
    q = _q(5, 2)
    dT = torch.func.vmap(torch.func.jacrev(panda.fk_dh))(q)  # (5, 4, 4, 7)
    Jw = panda.jacobian(q, "world")
    torch.testing.assert_close(Jw[:, :3], dT[:, :3, 3], atol=1e-12, rtol=0)
    # ω̂ = Ṙ Rᵀ
    R = panda.fk_dh(q)[:, :3, :3]
    W = torch.einsum("bijk,blj->bilk", dT[:, :3, :3], R)
    omega = torch.stack((W[:, 2, 1], W[:, 0, 2], W[:, 1, 0]), 1)
    torch.testing.assert_close(Jw[:, 3:], omega, atol=1e-12, rtol=0)


# -------------------------------------------------------------------------------------------------- DLS
def test_dls_small_damping_is_pseudo_inverse(panda):
    q = Panda.home(D64).expand(3, 7) + 0.1 * _q(3, 3) / 3
    J = panda.jacobian(q)
    assert torch.linalg.svdvals(J).amin() > 0.05  # well conditioned
    xi = torch.randn(3, 6, generator=torch.Generator().manual_seed(0), dtype=D64)
    qd = dls_joint_velocity(J, xi, damping=1e-9)
    torch.testing.assert_close(qd, (torch.linalg.pinv(J) @ xi.unsqueeze(-1)).squeeze(-1), atol=1e-10, rtol=0)
    torch.testing.assert_close((J @ qd.unsqueeze(-1)).squeeze(-1), xi, atol=1e-10, rtol=0)


def test_dls_nullspace_keeps_twist_and_moves_off_limits(panda):
    lo, hi = Panda.joint_limits(D64)
    q = _q(8, 4)
    q[:, 6] = hi[6] - 0.01  # q7 near its upper limit
    J = panda.jacobian(q)
    xi = torch.randn(8, 6, generator=torch.Generator().manual_seed(1), dtype=D64)
    base = dls_joint_velocity(J, xi, damping=1e-3)
    full = dls_joint_velocity(J, xi, damping=1e-3, q=q, q_limits=(lo, hi), nullspace_gain=5.0)
    null = full - base
    assert (J @ null.unsqueeze(-1)).abs().max() < 1e-12
    z = joint_limit_gradient(q, lo, hi)
    assert ((null * z).sum(-1) > 0).all()  # the null-space motion decreases h (towards the middle)


# -------------------------------------------------------------------------------------------------- IK
def _goals(n, seed, dtype=D64):
    return Panda().fk(_q(n, seed, dtype))


def test_ik_success_rate_from_home(panda):
    # Goals: FK of 1,000 uniform random configurations inside the limits; starts: the "ready" pose plus
    # PANDA_IK_SEEDS[0] as a second lane, at most 30 iterations deep (60 evaluations over both lanes).
    target = _goals(1000, 11)
    r = solve_ik(panda, target, seeds=Panda.ik_seeds(D64)[:1])
    assert r.success.double().mean() >= 0.95
    assert int(r.iterations.max()) <= 30 and int(r.evaluations.max()) <= 60
    s = r.success
    T = panda.fk(r.q[s])
    assert ((T[:, :3, 3] - target[s, :3, 3]).norm(dim=-1) < 1e-3).all()
    lo, hi = Panda.joint_limits(D64)
    assert ((r.q >= lo) & (r.q <= hi)).all()
    assert (r.reason[s] == Reason.CONVERGED).all() and (r.reason[~s] == Reason.MAX_ITERATIONS).all()
    # single start (no seeds): the honest baseline, a lower rate
    r1 = solve_ik(panda, target)
    assert 0.8 <= r1.success.double().mean() <= r.success.double().mean()
    assert (r1.evaluations == r1.iterations).all()


def test_ik_nan_element_fails_alone(panda):
    target = _goals(6, 12)
    bad = target.clone()
    bad[2, 0, 3] = float("nan")
    r, rb = solve_ik(panda, target), solve_ik(panda, bad)
    assert not rb.success[2] and rb.reason[2] == Reason.NONFINITE_INPUT and torch.isnan(rb.pos_err[2])
    keep = torch.tensor([0, 1, 3, 4, 5])
    torch.testing.assert_close(rb.q[keep], r.q[keep], atol=1e-12, rtol=0)
    assert torch.equal(rb.success[keep], r.success[keep])


def test_ik_batched_equals_loop(panda):
    target = _goals(12, 13).reshape(3, 4, 4, 4)
    seeds = Panda.ik_seeds(D64)[:1]
    r = solve_ik(panda, target, seeds=seeds)
    assert r.q.shape == (3, 4, 7) and r.success.shape == (3, 4)
    for i in range(3):
        for j in range(4):
            ri = solve_ik(panda, target[i, j], seeds=seeds)
            assert ri.q.shape == (7,)
            torch.testing.assert_close(ri.q, r.q[i, j], atol=1e-9, rtol=0)
            assert bool(ri.success) == bool(r.success[i, j]) and int(ri.iterations) == int(r.iterations[i, j])


def test_ik_float32(panda):
    target = _goals(100, 14, torch.float32)
    r = solve_ik(panda, target, seeds=Panda.ik_seeds(torch.float32)[:1])
    assert r.q.dtype == torch.float32 and r.success.double().mean() >= 0.9
    Tq = panda.fk(r.q[r.success].double())
    assert ((Tq[:, :3, 3] - target[r.success, :3, 3].double()).norm(dim=-1) < 1.01e-3).all()


def test_ik_already_solved_and_bad_inputs(panda):
    target = panda.fk(Panda.home(D64))
    r = solve_ik(panda, target)
    assert bool(r.success) and int(r.iterations) == 0
    with pytest.raises(ValueError):
        solve_ik(panda, torch.zeros(3, 3, dtype=D64))
    with pytest.raises(TypeError):
        solve_ik(panda, target, q0=Panda.home(torch.float32))


def test_dls_a_nan_element_does_not_fail_the_batch():
    """The null-space projector's SVD raised for the whole batch when one Jacobian had a NaN."""
    robot = Panda()
    gen = torch.Generator().manual_seed(7)
    q = Panda.random_q(4, generator=gen, dtype=torch.float64)
    J = robot.jacobian(q)
    xi = torch.randn(4, 6, generator=gen, dtype=torch.float64)
    lo, hi = Panda.joint_limits(torch.float64)
    clean = dls_joint_velocity(J, xi, 1e-2, q, (lo, hi))
    J[2, 0, 3] = math.nan
    qd = dls_joint_velocity(J, xi, 1e-2, q, (lo, hi))
    assert torch.isnan(qd[2]).all()
    torch.testing.assert_close(qd[[0, 1, 3]], clean[[0, 1, 3]], rtol=0, atol=0)


# ------------------------------------------------------------------------------------- issue 22 (8, 11, 12)
def test_dls_rank_deficient_element_does_not_fail_the_batch():
    """Issue 22 item 11: with damping=0 one rank-deficient J made the whole batch's solve raise (singular
    J Jᵀ).  Every element is J⁺ ξ (the λ → 0 limit of DLS), checked against numpy's pinv per sample."""
    np = pytest.importorskip("numpy")
    robot = Panda()
    gen = torch.Generator().manual_seed(3)
    q = Panda.random_q(5, generator=gen, dtype=D64)
    J = robot.jacobian(q)
    J[1, 2] = 0.0  # a zero row: rank 5
    J[3, :, 4:] = 0.0  # three joints without effect: rank 4 (J Jᵀ singular)
    xi = torch.randn(5, 6, generator=gen, dtype=D64)
    lo, hi = Panda.joint_limits(D64)
    qd = dls_joint_velocity(J, xi, damping=0.0)
    full = dls_joint_velocity(J, xi, 0.0, q, (lo, hi), nullspace_gain=3.0)
    for i in range(5):
        Ji, xii = J[i].numpy(), xi[i].numpy()
        Jp = np.linalg.pinv(Ji, rcond=7 * np.finfo(np.float64).eps)
        np.testing.assert_allclose(qd[i].numpy(), Jp @ xii, atol=1e-9, rtol=1e-9)
        z = joint_limit_gradient(q[i], lo, hi).numpy() * 3.0
        np.testing.assert_allclose(full[i].numpy(), Jp @ xii + z - Jp @ (Ji @ z), atol=1e-9, rtol=1e-9)
    assert torch.isfinite(qd).all()


def test_dls_damped_equals_formula_per_sample_and_nan_stays_alone():
    """The SVD form equals ``Jᵀ (J Jᵀ + λ² I)⁻¹ ξ`` (numpy, per sample, per-element λ); a NaN twist or J gives
    NaN for that element only."""
    np = pytest.importorskip("numpy")
    robot = Panda()
    gen = torch.Generator().manual_seed(4)
    J = robot.jacobian(Panda.random_q(4, generator=gen, dtype=D64))
    xi = torch.randn(4, 6, generator=gen, dtype=D64)
    lam = torch.tensor([1e-3, 0.0, 0.1, 1.0], dtype=D64)
    qd = dls_joint_velocity(J, xi, lam)
    for i in range(4):
        Ji = J[i].numpy()
        ref = Ji.T @ np.linalg.solve(Ji @ Ji.T + float(lam[i]) ** 2 * np.eye(6), xi[i].numpy())
        np.testing.assert_allclose(qd[i].numpy(), ref, atol=1e-9, rtol=1e-9)
    xi[1, 0] = math.nan
    J[2, 0, 0] = math.inf
    bad = dls_joint_velocity(J, xi, lam)
    assert torch.isnan(bad[1]).all() and torch.isnan(bad[2]).all()
    torch.testing.assert_close(bad[[0, 3]], qd[[0, 3]], rtol=0, atol=0)


def test_ik_rejects_a_target_that_is_not_a_rigid_motion(panda):
    """Issue 22 item 8: a target rotation scaled by 1.02 was 'solved' (success, FK 1.9e-2 off it)."""
    target = _goals(3, 21)
    scaled = target.clone()
    scaled[1, :3, :3] *= 1.02
    # the reference: that block is off SO(3) (RᵀR − I = 0.0404 I), far above torchlie's tolerance
    R = scaled[1, :3, :3]
    assert float((R.T @ R - torch.eye(3, dtype=D64)).abs().max()) > 0.04
    with pytest.raises(ValueError, match="'target'.*SE\\(3\\)"):
        solve_ik(panda, scaled)
    sheared = target.clone()
    sheared[0, 3, 0] = 0.1  # a wrong last row
    with pytest.raises(ValueError, match="'target'"):
        solve_ik(panda, sheared)
    # a NaN element keeps its per-element status (not a ValueError), the rigid ones are solved
    nan = target.clone()
    nan[2, 0, 0] = math.nan
    r = solve_ik(panda, nan)
    assert r.reason[2] == Reason.NONFINITE_INPUT and bool(r.success[:2].all())
    # float32 FK output is rigid to its own rounding: accepted
    assert bool(solve_ik(panda, _goals(4, 22, torch.float32)).success.any())


def test_ik_bad_starts_and_settings_name_the_argument(panda):
    """Issue 22 item 12: a q0 with the wrong joint count raised torch's expand error from deep inside."""
    target = _goals(3, 23)
    with pytest.raises(ValueError, match=r"'q0'.*\(7,\) or \(\*B, 7\).*got \(6,\)"):
        solve_ik(panda, target, q0=torch.zeros(6, dtype=D64))
    with pytest.raises(ValueError, match="'q0'.*batch"):
        solve_ik(panda, target, q0=torch.zeros(2, 7, dtype=D64))
    with pytest.raises(ValueError, match=r"'seeds'.*\(K, 7\)"):
        solve_ik(panda, target, seeds=torch.zeros(2, 6, dtype=D64))
    with pytest.raises(ValueError, match="'seeds'"):
        solve_ik(panda, target, seeds=torch.zeros(7, dtype=D64))
    with pytest.raises(TypeError, match="'target'"):
        solve_ik(panda, target.numpy())
    with pytest.raises(TypeError, match="'q0'"):
        solve_ik(panda, target, q0=[0.0] * 7)
    for kw, name in ((dict(max_iter=-1), "max_iter"), (dict(max_iter=2.5), "max_iter"),
                     (dict(rot_scale=-0.2), "rot_scale"), (dict(damping=-1.0), "damping"),
                     (dict(rot_scale=float("nan")), "rot_scale")):
        with pytest.raises(ValueError, match=f"'{name}'"):
            solve_ik(panda, target, **kw)
    # broadcasting starts still work: a per-goal q0 and shared seeds
    r = solve_ik(panda, target, q0=Panda.home(D64).expand(3, 7), seeds=Panda.ik_seeds(D64)[:1])
    assert r.q.shape == (3, 7)


# -------------------------------------------------------------- adversarial check after issue 22 (D8, minor)
def test_ik_a_nan_shared_seed_is_an_error_and_a_per_goal_one_fails_its_goal_alone(panda):
    """seeds=[home + 0.1, NaN] reported success=False, pos_err=NaN for every goal, although lane 0 alone meets
    the tolerance.  A shared start is the caller's input: ValueError naming it.  A per-goal start with a NaN
    fails its goal only (NONFINITE_INPUT); the other goals equal a per-goal loop with finite seeds, and their
    success is checked against the forward kinematics."""
    q = Panda.home(D64)
    target = panda.fk(q).clone()
    target[:3, 3] += torch.tensor([0.05, 0.0, -0.05], dtype=D64)
    good = q + 0.1
    with pytest.raises(ValueError, match="'seeds'.*NaN or inf"):
        solve_ik(panda, target, seeds=torch.stack([good, torch.full((7,), math.nan, dtype=D64)]))
    with pytest.raises(ValueError, match="'q0'.*NaN or inf"):
        solve_ik(panda, target, q0=torch.full((7,), math.inf, dtype=D64))
    targets = torch.cat([target[None], _goals(2, 31)])
    seeds = torch.stack([good, good]).expand(3, 2, 7).clone()
    seeds[1, 1, 3] = math.nan
    r = solve_ik(panda, targets, seeds=seeds)
    assert r.reason[1] == Reason.NONFINITE_INPUT and not r.success[1] and torch.isnan(r.pos_err[1])
    for i in (0, 2):
        ri = solve_ik(panda, targets[i], seeds=seeds[i])
        torch.testing.assert_close(r.q[i], ri.q, rtol=0, atol=0)
        assert bool(r.success[i]) == bool(ri.success)
    assert bool(r.success[0])
    T = panda.fk(r.q[0])
    assert float((T[:3, 3] - target[:3, 3]).norm()) < 1e-3


def test_ik_tolerances_that_can_never_be_met_are_refused(panda):
    """A negative or NaN pos_tol/rot_tol was accepted and never met (max_iter iterations, then failure)."""
    target = _goals(2, 32)
    for name in ("pos_tol", "rot_tol"):
        for bad in (-1e-3, 0.0, math.nan):
            with pytest.raises(ValueError, match=f"'{name}'.*> 0"):
                solve_ik(panda, target, **{name: bad})
    # inf means "not tested": the rotation alone decides (checked against the forward kinematics)
    r = solve_ik(panda, target, pos_tol=math.inf)
    R = panda.fk(r.q[r.success])[:, :3, :3]
    Rt = target[r.success, :3, :3]
    cos = ((R.mT @ Rt).diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2
    assert bool(r.success.any()) and bool((torch.arccos(cos.clamp(-1, 1)) < 1e-2).all())


def test_dls_bad_arguments_name_the_argument():
    """A float32 twist with a float64 J, an integer J, a damping of the wrong shape raised torch's own errors;
    zero-width limits made the whole batch NaN; crossed limits were accepted silently."""
    g = torch.Generator().manual_seed(33)
    J, tw = torch.randn(2, 6, 7, dtype=D64, generator=g), torch.randn(2, 6, dtype=D64, generator=g)
    q, z = torch.zeros(2, 7, dtype=D64), torch.zeros(7, dtype=D64)
    with pytest.raises(TypeError, match="'twist'.*float32"):
        dls_joint_velocity(J, tw.float(), 0.01)
    with pytest.raises(TypeError, match="'J'.*int32"):
        dls_joint_velocity(J.int(), tw, 0.01)
    with pytest.raises(ValueError, match="'damping'.*\\(3,\\)"):
        dls_joint_velocity(J, tw, torch.full((3,), 0.01, dtype=D64))
    with pytest.raises(TypeError, match="'damping'"):
        dls_joint_velocity(J, tw, torch.full((2,), 0.01))
    with pytest.raises(ValueError, match="'nullspace_gain'"):
        dls_joint_velocity(J, tw, 0.01, q, (z - 1, z + 1), nullspace_gain=torch.ones(3, dtype=D64))
    with pytest.raises(ValueError, match="'q'.*\\(\\*B, 7\\)"):
        dls_joint_velocity(J, tw, 0.01, q=torch.zeros(3, 7, dtype=D64), q_limits=(z - 1, z + 1))
    nan_hi = torch.where(torch.arange(7) == 2, math.nan, 1.0).double()
    for lo, hi in ((z, z), (z + 1, z - 1), (z - 1, nan_hi)):
        with pytest.raises(ValueError, match="'q_limits'.*q_min < q_max"):
            dls_joint_velocity(J, tw, 0.01, q=q, q_limits=(lo, hi))


def test_dls_an_unbounded_joint_gets_no_limit_avoidance():
    """q_limits with ±inf (a continuous joint) made every element NaN ((−inf + inf)/2 in the mid-range).  The
    Liégeois term of that joint is 0 (its limit as the range grows); numpy per sample is the reference."""
    np = pytest.importorskip("numpy")
    robot = Panda()
    gen = torch.Generator().manual_seed(34)
    q = Panda.random_q(3, generator=gen, dtype=D64)
    J, xi = robot.jacobian(q), torch.randn(3, 6, generator=gen, dtype=D64)
    lo, hi = Panda.joint_limits(D64)
    lo, hi = lo.clone(), hi.clone()
    lo[6], hi[6] = -math.inf, math.inf
    hi[0] = math.inf  # one-sided
    qd = dls_joint_velocity(J, xi, 0.05, q, (lo, hi), nullspace_gain=2.0)
    for i in range(3):
        Ji, qi = J[i].numpy(), q[i].numpy()
        bounded = np.isfinite(lo.numpy()) & np.isfinite(hi.numpy())
        l, h = np.where(bounded, lo.numpy(), 0.0), np.where(bounded, hi.numpy(), 1.0)
        zi = np.where(bounded, -2.0 * (qi - 0.5 * (l + h)) / ((h - l) ** 2 * 7), 0.0)
        Jp = np.linalg.pinv(Ji, rcond=7 * np.finfo(np.float64).eps)
        ref = Ji.T @ np.linalg.solve(Ji @ Ji.T + 0.05 ** 2 * np.eye(6), xi[i].numpy()) + zi - Jp @ (Ji @ zi)
        np.testing.assert_allclose(qd[i].numpy(), ref, rtol=1e-9, atol=1e-12)
