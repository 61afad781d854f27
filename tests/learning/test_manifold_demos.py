"""learning.manifold_demos: orientation/pose/stiffness demos, per-step Gaussians on manifolds (seed 004 §12.3)
and tracking the mean with the error-state MPC (seed 003) — issue 26 §5."""

import math

import numpy as np
import pytest
import scipy.linalg
import torch
from scipy.spatial.transform import Rotation

from controllers.manifold_mpc import ErrorStateMPC
from controllers.pose_mpc import BodyTwistSE3
from learning.demos import Demonstrations
from learning.manifold_demos import (
    GROUPS,
    BodyRateSO3,
    demo_points,
    manifold_statistics,
    orientation_demos,
    points_to_demos,
    reference_controls,
    stiffness_demos,
    track_mean,
)
from torchlie import quaternion, se3, so3
from torchlie.manifolds import SPD

F64 = torch.float64


def _gen(seed=0):
    return torch.Generator().manual_seed(seed)


def _quat_left(mu):
    """M (…, 4, 3): v ↦ μ ⊗ (0, v)."""
    e = torch.eye(3, dtype=mu.dtype)
    pure = torch.cat([torch.zeros(3, 1, dtype=mu.dtype), e], -1)             # (3, 4) the pure quaternions
    return quaternion.multiply(mu.unsqueeze(-2), pure).mT


# ------------------------------------------------------------------------------------------- demos
@pytest.mark.parametrize("group,n", [("SO3", 9), ("SE3", 16), ("S3", 4)])
def test_orientation_demos_layout_membership_and_seed(group, n):
    d = orientation_demos(5, 20, generator=_gen(1), group=group)
    assert d.x.shape == (5, 20, n) and d.meta["group"] == group and d.frames["reference"].shape == (5, 20, n)
    P = demo_points(d)
    if group == "S3":
        assert torch.allclose(P.norm(dim=-1), torch.ones(5, 20, dtype=F64), atol=1e-12)
    else:
        R = P[..., :3, :3]
        assert torch.allclose(R.mT @ R, torch.eye(3, dtype=F64).expand_as(R), atol=1e-12)
    again = orientation_demos(5, 20, generator=_gen(1), group=group)
    assert torch.equal(d.x, again.x)
    other = orientation_demos(5, 20, generator=_gen(2), group=group)
    assert not torch.allclose(d.x, other.x)


def test_demos_round_trip_and_noise_scale():
    # body noise ε = Log(x*⁻¹ x) with warp 0 and a constant envelope has pointwise std `noise` (spatial_noise)
    d = orientation_demos(400, 9, generator=_gen(3), noise=0.05, warp=0.0)
    P = demo_points(d)
    ref = d.frames["reference"].reshape(400, 9, 3, 3)
    eps = so3.log(ref.mT @ P)
    std = eps.std(dim=0)                                                    # (T, 3)
    assert torch.allclose(std, torch.full_like(std, 0.05), rtol=0.2)       # 400 samples: ~±7% (3.5σ bound)
    back = points_to_demos(P, "SO3", d.dt)
    assert torch.equal(back.x, d.x)


# ------------------------------------------------------------------------------------- Karcher mean
def _antithetic(group, centre, eps):
    """Samples Exp_c(±ε_j): their Karcher mean is exactly the centre."""
    e = torch.cat([eps, -eps], 0)                                           # (N, T, m)
    if group == "SO3":
        return centre @ so3.exp(e)
    if group == "SE3":
        return centre @ se3.exp(e)
    if group == "S3":
        return quaternion.multiply(centre, quaternion.exp(0.5 * e))
    return SPD(centre.shape[-1]).exp_at(centre, e)


@pytest.mark.parametrize("group", GROUPS)
def test_karcher_mean_of_symmetric_noise_is_the_centre(group):
    g = _gen(4)
    T = 3
    if group == "SO3":
        centre, m = so3.random(T, generator=g, dtype=F64), 3
    elif group == "SE3":
        centre, m = se3.random(T, generator=g, dtype=F64), 6
    elif group == "S3":
        centre, m = quaternion.random(T, generator=g, dtype=F64), 3
    else:
        centre, m = SPD(3).random(T, generator=g, dtype=F64), 6
    eps = 0.3 * torch.randn(6, T, m, generator=g, dtype=F64)
    st = manifold_statistics(_antithetic(group, centre, eps), group)
    assert bool(st.converged.all())
    mean = st.mean
    if group == "S3":
        mean = mean * torch.sign((mean * centre).sum(-1, keepdim=True))
    assert torch.allclose(mean, centre, atol=1e-10)


def _np_midpoint_so3(R1, R2):
    r1, r2 = Rotation.from_matrix(R1), Rotation.from_matrix(R2)
    return (r1 * Rotation.from_rotvec(0.5 * (r1.inv() * r2).as_rotvec())).as_matrix()


def test_two_points_give_the_geodesic_midpoint():
    g = _gen(5)
    T = 4
    # SO(3): scipy's rotation vectors
    R = so3.random(2, T, generator=g, dtype=F64)
    st = manifold_statistics(R, "SO3")
    ref = np.stack([_np_midpoint_so3(R[0, t].numpy(), R[1, t].numpy()) for t in range(T)])
    assert np.allclose(st.mean.numpy(), ref, atol=1e-10)
    # SE(3): the one-parameter subgroup midpoint X1 expm(½ logm(X1⁻¹ X2)) (scipy's matrix functions)
    X = se3.random(2, T, generator=g, dtype=F64)
    X = torch.cat([X[:1], X[:1] @ se3.exp(0.8 * se3.log(se3.inverse(X[:1]) @ X[1:]) / se3.log(
        se3.inverse(X[:1]) @ X[1:]).norm(dim=-1, keepdim=True))], 0)       # keep the pairs within 0.8
    st = manifold_statistics(X, "SE3")
    for t in range(T):
        A, B = X[0, t].numpy(), X[1, t].numpy()
        mid = A @ scipy.linalg.expm(0.5 * np.real(scipy.linalg.logm(np.linalg.solve(A, B))))
        assert np.allclose(st.mean[t].numpy(), mid, atol=1e-9)
    # S³: the normalized sum of two aligned unit quaternions (the slerp midpoint)
    q = quaternion.random(2, T, generator=g, dtype=F64)
    st = manifold_statistics(q, "S3")
    q1 = q[1] * torch.sign((q[0] * q[1]).sum(-1, keepdim=True))
    mid = torch.nn.functional.normalize(q[0] + q1, dim=-1)
    assert torch.allclose(st.mean * torch.sign((st.mean * mid).sum(-1, keepdim=True)), mid, atol=1e-10)
    # SPD: the matrix geometric mean A # B = A^½ (A^-½ B A^-½)^½ A^½ (scipy's sqrtm)
    K = SPD(3).random(2, T, generator=g, dtype=F64)
    st = manifold_statistics(K, "SPD")
    for t in range(T):
        A, B = K[0, t].numpy(), K[1, t].numpy()
        Ah = np.real(scipy.linalg.sqrtm(A))
        Aih = np.linalg.inv(Ah)
        gm = Ah @ np.real(scipy.linalg.sqrtm(Aih @ B @ Aih)) @ Ah
        assert np.allclose(st.mean[t].numpy(), gm, rtol=1e-9, atol=1e-9)


def _np_karcher_so3(Rs, iters=100):
    mu = Rotation.from_matrix(Rs[0])
    rs = Rotation.from_matrix(Rs)
    for _ in range(iters):
        u = (mu.inv() * rs).as_rotvec().mean(0)
        mu = mu * Rotation.from_rotvec(u)
        if np.linalg.norm(u) < 1e-14:
            break
    return mu.as_matrix()


def test_so3_mean_matches_a_numpy_riemannian_iterate_at_large_spread():
    g = _gen(6)
    T, N = 5, 15
    C = so3.random(T, generator=g, dtype=F64)
    R = C @ so3.exp(0.7 * torch.randn(N, T, 3, generator=g, dtype=F64))
    st = manifold_statistics(R, "SO3")
    for t in range(T):
        ref = _np_karcher_so3(R[:, t].numpy())
        assert np.allclose(st.mean[t].numpy(), ref, atol=1e-10)
    # the chordal mean (scipy's Rotation.mean) is a different mean: close, not equal, at this spread
    chordal = Rotation.from_matrix(R[:, 0].numpy()).mean().as_matrix()
    gap = np.linalg.norm(Rotation.from_matrix(chordal.T @ st.mean[0].numpy()).as_rotvec())
    assert 1e-6 < gap < 0.1


# ------------------------------------------------------------------------------- tangent covariance
@pytest.mark.parametrize("group", ["SO3", "SE3", "SPD"])
def test_tangent_covariance_recovers_sigma(group):
    g = _gen(7)
    N, T = 6000, 2
    m = 3 if group == "SO3" else 6
    A = 0.08 * torch.randn(T, m, m, generator=g, dtype=F64)
    Sigma = A @ A.mT + 0.002 * torch.eye(m, dtype=F64)
    L = torch.linalg.cholesky(Sigma)
    e = (L @ torch.randn(N, T, m, 1, generator=g, dtype=F64)).squeeze(-1)
    if group == "SO3":
        pts = so3.random(T, generator=g, dtype=F64) @ so3.exp(e)
    elif group == "SE3":
        pts = se3.random(T, generator=g, dtype=F64) @ se3.exp(e)
    else:
        pts = SPD(3).exp_at(SPD(3).random(T, generator=g, dtype=F64), e)
    st = manifold_statistics(pts, group)
    # Monte Carlo: entry std ≈ sqrt((Σii Σjj + Σij²)/N) ≤ ‖Σ‖·sqrt(2/N); bound 5x that in Frobenius norm
    err = torch.linalg.matrix_norm(st.covariance - Sigma)
    assert bool((err <= 5 * math.sqrt(2 / N) * torch.linalg.matrix_norm(Sigma)).all())


def test_s3_statistics_equal_the_so3_ones_through_the_double_cover():
    # same mean (d_S³ = θ/2) and Σ_S³ = ¼ M Σ_ω Mᵀ with M: v ↦ μ ⊗ (0, v) — an exact identity
    d = orientation_demos(10, 12, generator=_gen(8), noise=0.3, warp=0.1)
    R = demo_points(d)
    st_r = manifold_statistics(d)
    st_q = manifold_statistics(so3.to_quaternion(R), "S3")
    assert torch.allclose(so3.from_quaternion(st_q.mean), st_r.mean, atol=1e-10)
    M = _quat_left(st_q.mean)
    assert torch.allclose(st_q.covariance, 0.25 * M @ st_r.covariance @ M.mT, atol=1e-12)
    assert torch.allclose(st_q.covariance @ st_q.mean.unsqueeze(-1), torch.zeros(12, 4, 1, dtype=F64),
                          atol=1e-12)


def test_quaternion_double_cover_gives_identical_statistics():
    plain = orientation_demos(9, 15, generator=_gen(9), group="S3")
    flipped = orientation_demos(9, 15, generator=_gen(9), group="S3", random_signs=True)
    assert not torch.equal(plain.x, flipped.x) and torch.allclose(plain.x.abs(), flipped.x.abs())
    a, b = manifold_statistics(plain), manifold_statistics(flipped)
    neg = manifold_statistics(-demo_points(plain), "S3")
    for other in (b, neg):
        assert torch.allclose(a.mean, other.mean, atol=1e-12)
        assert torch.allclose(a.covariance, other.covariance, atol=1e-12)
    # the mean's sign is continuous over time
    assert bool(((a.mean[1:] * a.mean[:-1]).sum(-1) > 0).all())


def test_rotations_at_angle_exactly_pi():
    g = _gen(10)
    Rpi = torch.diag(torch.tensor([-1.0, -1.0, 1.0], dtype=F64))           # angle π about z
    eps = 0.4 * torch.randn(5, 1, 3, generator=g, dtype=F64)
    R = torch.cat([_antithetic("SO3", Rpi, eps), Rpi.expand(1, 1, 3, 3)], 0)  # includes Rpi itself
    st = manifold_statistics(R, "SO3")
    assert torch.allclose(st.mean[0], Rpi, atol=1e-10)
    e = torch.cat([eps, -eps, torch.zeros(1, 1, 3, dtype=F64)], 0)
    assert torch.allclose(st.covariance[0], e[:, 0].mT @ e[:, 0] / 10, atol=1e-10)
    # the same on S³: the centre quaternion (0, 0, 0, 1) has w = 0
    qpi = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=F64)
    q = torch.cat([_antithetic("S3", qpi, eps), qpi.expand(1, 1, 4)], 0)
    st = manifold_statistics(q, "S3")
    assert torch.allclose(st.mean[0].abs(), qpi, atol=1e-10)


# ----------------------------------------------------------------------------- batching and dtypes
@pytest.mark.parametrize("group", GROUPS)
def test_batched_equals_per_step_loop(group):
    g = _gen(11)
    if group == "SPD":
        d = stiffness_demos(6, 7, generator=g)
    else:
        d = orientation_demos(6, 7, generator=g, group=group, random_signs=True)
    P = demo_points(d)
    P2 = torch.stack([P, P.flip(0)], 0)                                      # (B=2, N, T, ...)
    st = manifold_statistics(P2, group)
    for t in range(d.T):
        one = manifold_statistics(P[:, t:t + 1], group)
        mean_t, cov_t = st.mean[0, t], st.covariance[0, t]
        if group == "S3":
            mean_t = mean_t * torch.sign((mean_t * one.mean[0]).sum())
        assert torch.allclose(mean_t, one.mean[0], atol=1e-10)
        assert torch.allclose(cov_t, one.covariance[0], atol=1e-10)
    assert torch.allclose(st.covariance[0], st.covariance[1], atol=1e-10)


@pytest.mark.parametrize("group", GROUPS)
def test_float32_agrees_with_float64(group):
    g = _gen(12)
    d = stiffness_demos(6, 5, generator=g) if group == "SPD" else orientation_demos(6, 5, generator=g,
                                                                                    group=group)
    s64 = manifold_statistics(d)
    s32 = manifold_statistics(d.to(torch.float32))
    assert s32.mean.dtype == torch.float32 and s32.covariance.dtype == torch.float32
    scale = 1.0 if group != "SPD" else float(s64.mean.abs().max())
    assert torch.allclose(s32.mean.double(), s64.mean, atol=2e-4 * scale)
    assert torch.allclose(s32.covariance.double(), s64.covariance, atol=2e-5)


def test_statistics_are_differentiable():
    d = orientation_demos(5, 3, generator=_gen(13))
    P = demo_points(d).clone().requires_grad_(True)
    st = manifold_statistics(P, "SO3")
    (st.covariance.sum() + st.mean.sum()).backward()
    assert P.grad is not None and bool(torch.isfinite(P.grad).all()) and float(P.grad.abs().sum()) > 0


# ------------------------------------------------------------------------------------------- errors
def test_bad_inputs_raise_clear_errors():
    d = orientation_demos(4, 5, generator=_gen(14))
    with pytest.raises(ValueError, match="'group'"):
        manifold_statistics(d, "SO4")
    with pytest.raises(ValueError, match="needs x"):
        manifold_statistics(d, "SE3")
    with pytest.raises(ValueError, match="meta"):
        manifold_statistics(Demonstrations(x=d.x, dt=d.dt))
    with pytest.raises(ValueError, match="'group' is needed"):
        manifold_statistics(demo_points(d))
    with pytest.raises(ValueError, match="N >= 2"):
        manifold_statistics(demo_points(d)[:1], "SO3")
    with pytest.raises(ValueError, match="points"):
        manifold_statistics(torch.zeros(4, 5, 3, 4, dtype=F64), "SO3")
    with pytest.raises(ValueError, match="demos"):                          # not rotations
        manifold_statistics(torch.ones(4, 5, 3, 3, dtype=F64), "SO3")
    with pytest.raises(TypeError, match="'demos'"):
        manifold_statistics([1, 2], "SO3")
    with pytest.raises(TypeError, match="generator"):
        orientation_demos(3, 5, generator=None)
    with pytest.raises(ValueError, match="stiffness_demos"):
        orientation_demos(3, 5, generator=_gen(), group="SPD")
    with pytest.raises(ValueError, match="envelope"):
        orientation_demos(3, 5, generator=_gen(), envelope=-torch.ones(5))
    with pytest.raises(ValueError, match="start"):
        stiffness_demos(3, 5, generator=_gen(), start=-torch.eye(3, dtype=F64))
    st = manifold_statistics(d)
    sys = BodyRateSO3(d.dt)
    with pytest.raises(ValueError, match="'covariance'"):
        track_mean(sys, st.mean, st.covariance[:-1], st.mean[0])
    with pytest.raises(ValueError, match="'R'"):
        track_mean(sys, st.mean, st.covariance, st.mean[0], R=-1.0)
    with pytest.raises(ValueError, match="'steps'"):
        track_mean(sys, st.mean, st.covariance, st.mean[0], steps=10)
    with pytest.raises(TypeError, match="'system'"):
        track_mean(object(), st.mean, st.covariance, st.mean[0])


# ------------------------------------------------------------------------------------------ tracking
def _via_point_demos(T=40):
    s = torch.linspace(0, 1, T, dtype=F64)
    env = 1 - 0.9 * torch.exp(-((s - 0.6) / 0.08) ** 2)                       # the demos agree near s = 0.6
    return orientation_demos(12, T, generator=_gen(15), envelope=env, warp=0.05)


def test_tracking_the_mean_reduces_the_error_and_is_stiffer_where_demos_agree():
    d = _via_point_demos()
    st = manifold_statistics(d)
    x0 = st.mean[0] @ so3.exp(torch.tensor([0.3, -0.2, 0.25], dtype=F64))
    run = track_mean(BodyRateSO3(d.dt), st.mean, st.covariance, x0, horizon=8, R=1.0)
    assert bool((run.reason == 0).all())
    err = run.error.norm(dim=-1)
    assert float(err[-1]) < 0.01 * float(err[0])
    assert bool((err[1:] <= err[:-1] + 1e-12).all())                          # monotone here
    # the closed loop really is on the mean: rerun the error with torchlie directly
    assert torch.allclose(run.error, so3.log(st.mean.mT @ run.x), atol=1e-12)
    # tightest step (smallest λ_max Σ) against loosest (largest λ_min Σ): every direction looser there
    ev = torch.linalg.eigvalsh(st.covariance[:-1])
    gain = torch.linalg.matrix_norm(run.gain, ord=2)
    lo, hi = int(ev[:, -1].argmin()), int(ev[:, 0].argmax())
    assert float(ev[hi, 0]) > 5 * float(ev[lo, -1])
    assert float(gain[lo]) > 2 * float(gain[hi])
    # same system and start, constant precision: no peak of the gain where the demos agree
    flat = track_mean(BodyRateSO3(d.dt), st.mean, st.covariance.mean(0).expand_as(st.covariance), x0,
                      horizon=8, R=1.0)
    gflat = torch.linalg.matrix_norm(flat.gain, ord=2)
    assert float(gflat[lo]) < 1.2 * float(gflat[hi])


def test_constant_precision_equals_error_state_mpc():
    d = orientation_demos(6, 12, generator=_gen(16))
    st = manifold_statistics(d)
    sys = BodyRateSO3(d.dt)
    Sigma = torch.diag(torch.tensor([0.01, 0.02, 0.03], dtype=F64))
    x0 = st.mean[0] @ so3.exp(torch.tensor([0.2, 0.1, -0.3], dtype=F64))
    N, lam = 5, 1e-4
    run = track_mean(sys, st.mean, Sigma.expand(12, 3, 3), x0, horizon=N, R=0.5, regularization=lam, steps=1)
    Q = torch.linalg.inv(Sigma + lam * torch.eye(3, dtype=F64))
    mpc = ErrorStateMPC(sys, N, Q, 0.5 * torch.eye(3, dtype=F64), solver="riccati")
    ur = reference_controls(sys.manifold, st.mean, d.dt)
    sol = mpc.solve(x0, st.mean[:N + 1], ur[:N])
    assert torch.allclose(run.u[0], sol.u, atol=1e-10)


def test_tracking_float32_agrees_with_float64():
    d = orientation_demos(6, 10, generator=_gen(19))
    st = manifold_statistics(d)
    x0 = st.mean[0] @ so3.exp(torch.tensor([0.2, 0.1, -0.3], dtype=F64))
    r64 = track_mean(BodyRateSO3(d.dt), st.mean, st.covariance, x0, horizon=4, R=1.0, regularization=1e-3)
    r32 = track_mean(BodyRateSO3(d.dt), st.mean.float(), st.covariance.float(), x0.float(), horizon=4, R=1.0,
                     regularization=1e-3)
    assert r32.x.dtype == torch.float32 and r32.u.dtype == torch.float32
    assert torch.allclose(r32.u.double(), r64.u, atol=2e-3 * float(r64.u.abs().max()))
    assert torch.allclose(r32.error.double(), r64.error, atol=1e-4)


def test_tracking_poses_batched_equals_single():
    d = orientation_demos(8, 16, generator=_gen(17), group="SE3")
    st = manifold_statistics(d)
    sys = BodyTwistSE3(d.dt)
    kick = torch.tensor([[0.05, -0.02, 0.03, 0.2, 0.1, -0.1], [-0.04, 0.0, 0.02, -0.1, 0.25, 0.05]],
                        dtype=F64)
    x0 = st.mean[0] @ se3.exp(kick)                                           # (2, 4, 4)
    run = track_mean(sys, st.mean, st.covariance, x0, horizon=5, R=0.1)
    assert run.x.shape == (2, 16, 4, 4) and run.error.shape == (2, 16, 6)
    err = run.error.norm(dim=-1)
    assert bool((err[:, -1] < 0.05 * err[:, 0]).all())
    one = track_mean(sys, st.mean, st.covariance, x0[1], horizon=5, R=0.1)
    assert torch.allclose(one.x, run.x[1], atol=1e-10)


# ------------------------------------------------------------------------------------------ SPD target
def test_spd_target_karcher_versus_euclidean_mean():
    d = stiffness_demos(10, 20, generator=_gen(18), noise=0.3)
    st = manifold_statistics(d)
    K = demo_points(d)
    logdet = torch.linalg.slogdet(K)[1]                                       # (N, T)
    # affine-invariant Karcher mean: det μ = geometric mean of the determinants (trace of the optimality
    # condition Σ log(μ^-½ K_i μ^-½) = 0), exactly
    assert torch.allclose(torch.linalg.slogdet(st.mean)[1], logdet.mean(0), atol=1e-9)
    # the Euclidean mean swells the determinant (log det is concave): strictly here
    eu = torch.linalg.slogdet(K.mean(0))[1]
    assert bool((eu > torch.linalg.slogdet(st.mean)[1] + 1e-3).all())
    assert st.covariance.shape == (20, 6, 6)


# ------------------------------------------------------------------------------------------ example
def test_example_manifold_demos(tmp_path):
    from examples.learning.manifold_demos import run

    res = run(tmp_path)
    assert all(res["checks"].values()), res["checks"]
    assert (tmp_path / "manifold_demos.png").exists()
    v = res["values"]
    assert v["final_error_rad"] < 0.01 * v["initial_error_rad"]
    assert v["gain_at_low_variance"] > 2 * v["gain_at_high_variance"]
    assert v["max_det_ratio_euclid_over_karcher"] > 1.0
    assert v["fraction_inside_95"] >= 0.85
