"""Tests of the Exp/Log vocabulary of torchlie.manifolds (seed 004 §12): the sphere and SPD functional
cores (sphere.py, spd.py), exp_at/log_at/transport of the classes, and SO(3)/SE(3)/S³/SPD statistics
(statistics.py).  (Formerly tests of the module torchlie.riemannian, merged into torchlie.manifolds.)

References are independent of the implementation: arccos / scipy.linalg (sqrtm, logm, expm) for maps
and distances, closed-form geodesic means (slerp, the matrix geometric mean X #_t Y), the seed's
Σ1(Σ1+Σ2)⁻¹Σ2 form of the Euclidean product, torch.distributions for densities, and the quaternion
(S³) picture of SO(3) for the Lie-group transport.
"""

from __future__ import annotations

import math

import mpmath
import numpy as np
import pytest
import scipy.linalg as sla
import torch

from torchlie import manifolds as mf
from torchlie import se3, so3

F64 = torch.float64


def _gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _unit(shape, g, dtype=F64):
    return torch.nn.functional.normalize(torch.randn(*shape, generator=g, dtype=dtype), dim=-1)


def _tangent(x, g, scale=1.0):
    v = scale * torch.randn(x.shape, generator=g, dtype=x.dtype)
    return v - (x * v).sum(-1, keepdim=True) * x


def _spd(shape, n, g, dtype=F64, spread=0.5):
    A = spread * torch.randn(*shape, n, n, generator=g, dtype=dtype)
    return A @ A.mT + 0.5 * torch.eye(n, dtype=dtype)


def _sym(A):
    return 0.5 * (A + A.mT)


def _ai_inner(X, U, V):
    """Affine-invariant inner product tr(X⁻¹ U X⁻¹ V), computed with a solve (independent of eigh)."""
    XiU = torch.linalg.solve(X, U)
    XiV = torch.linalg.solve(X, V)
    return (XiU * XiV.mT).sum((-1, -2))


# ==================================================================================================
# sphere
# ==================================================================================================

@pytest.mark.parametrize("d", [1, 2, 3, 6])
@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 2e-5)])
def test_sphere_round_trips(d, dtype, tol):
    g = _gen(d)
    x, y = _unit((64, d + 1), g, dtype), _unit((64, d + 1), g, dtype)
    assert torch.allclose(mf.sphere_exp(x, mf.sphere_log(x, y)), y, atol=tol * 10)
    u = _tangent(x, g)
    u = u * (torch.rand(64, 1, generator=g, dtype=dtype) * 3.0 / torch.linalg.norm(u, dim=-1, keepdim=True))
    assert torch.allclose(mf.sphere_log(x, mf.sphere_exp(x, u)), u, atol=tol * 100)


def test_sphere_log_matches_seed_formula_and_dist_matches_arccos():
    g = _gen(1)
    x, y = _unit((200, 4), g), _unit((200, 4), g)
    c = (x * y).sum(-1, keepdim=True)
    ref_d = torch.arccos(c)
    w = y - c * x
    ref_u = ref_d * w / torch.linalg.norm(w, dim=-1, keepdim=True)          # Eq. 181 literally
    assert torch.allclose(mf.sphere_log(x, y), ref_u, atol=1e-12)
    assert torch.allclose(mf.sphere_dist(x, y), ref_d.squeeze(-1), atol=1e-12)
    assert torch.allclose(mf.Sphere(3).dist(x, y), ref_d.squeeze(-1), atol=1e-12)


def test_sphere_edges_identical_and_antipodal_points():
    g = _gen(2)
    x = _unit((8, 3), g).requires_grad_()
    u = mf.sphere_log(x, x.detach())
    assert torch.equal(u, torch.zeros_like(u)) or u.abs().max() < 1e-15
    # antipode: Log has length π along a deterministic tangent direction, Exp lands on −x
    ua = mf.sphere_log(x, -x.detach())
    assert torch.allclose(torch.linalg.norm(ua, dim=-1), torch.full((8,), math.pi, dtype=F64))
    assert (ua * x).sum(-1).abs().max() < 1e-12
    assert torch.allclose(mf.sphere_exp(x, ua), -x, atol=1e-12)
    assert torch.allclose(mf.sphere_dist(x, -x), torch.full((8,), math.pi, dtype=F64))
    # e(x) = e(−x): Log_{−x}(x) is the same vector
    assert torch.allclose(mf.sphere_log(-x, x), ua, atol=1e-12)
    # finite gradients at x == y, at the antipode and 1e-9 away from both
    for y in (x, -x, mf.sphere_exp(x, 1e-9 * _tangent(x.detach(), g)),
              mf.sphere_exp(-x, 1e-9 * _tangent(-x.detach(), g))):
        for f in (mf.sphere_log, mf.sphere_dist):
            xx = x.detach().clone().requires_grad_()
            yy = y.detach().clone().requires_grad_()
            out = f(xx, yy)
            gx, gy = torch.autograd.grad(out.sum(), (xx, yy))
            assert torch.isfinite(gx).all() and torch.isfinite(gy).all()
        v = mf.sphere_exp(x, 1e-9 * _tangent(x.detach(), g))
        assert torch.isfinite(v).all()
    # Exp at u = 0 has finite gradient equal to the identity on the tangent space
    uu = torch.zeros(8, 3, dtype=F64, requires_grad=True)
    J = torch.autograd.functional.jacobian(lambda t: mf.sphere_exp(x.detach(), t, project=True).sum(0), uu)
    assert torch.isfinite(J).all()



def _mp_angle(x, y):
    """Angle between float64 vectors, atan2(sqrt(‖x‖²‖y‖² − (x·y)²), x·y) in 50-digit mpmath."""
    mpmath.mp.dps = 50
    out = []
    for a, b in zip(x.tolist(), y.tolist()):
        a, b = [mpmath.mpf(v) for v in a], [mpmath.mpf(v) for v in b]
        xy = sum(p * q for p, q in zip(a, b))
        s2 = sum(p * p for p in a) * sum(q * q for q in b) - xy * xy
        out.append(float(mpmath.atan2(mpmath.sqrt(max(s2, 0)), xy)))
    return torch.tensor(out, dtype=F64)


@pytest.mark.parametrize("d", [2, 3, 5])
def test_sphere_log_next_to_the_antipode(d):
    # issue 9 §5: Log switched to π e(x) for ‖y − (xᵀy)x‖ ≤ √eps = 1.5e-8, so Exp_x(Log_x y) missed y
    # by up to 1.5e-8.  Points: Exp_x((π − k·ulp(π)) t) (k = 0..1000, the half-turn included), −x
    # perturbed by k·eps (k = 1..1000) and renormalised, gaps π − θ log-spaced over 1e-16..1e-6 (the
    # old switch band included), and exactly −x.
    g = _gen(60 + d)
    n = 200
    x = _unit((n, d + 1), g)
    t = torch.nn.functional.normalize(_tangent(x, g), dim=-1)
    k = torch.randint(0, 1001, (n, 1), generator=g).to(F64)
    gap = torch.logspace(-16, -6, n, dtype=F64).unsqueeze(-1)
    bump = (k + 1) * torch.finfo(F64).eps * _unit((n, d + 1), g)
    y = torch.cat((mf.sphere_exp(x, (math.pi - k * math.ulp(math.pi)) * t),
                   torch.nn.functional.normalize(-x + bump, dim=-1),
                   mf.sphere_exp(x, (math.pi - gap) * t),
                   -x))
    x = x.repeat(4, 1)
    u = mf.sphere_log(x, y)
    miss = torch.linalg.vector_norm(mf.sphere_exp(x, u) - y, dim=-1)
    assert miss.max() <= 1e-13, f"round trip misses y by {miss.max():.3g}"     # requirement 1e-8
    ref = _mp_angle(x, y)
    assert (torch.linalg.vector_norm(u, dim=-1) - ref).abs().max() <= 1e-14
    assert (mf.sphere_dist(x, y) - ref).abs().max() <= 1e-14
    assert (u * x).sum(-1).abs().max() <= 1e-14                                   # u ∈ T_x
    # float32: the same at float32 roundoff
    x32, y32 = x.float(), torch.nn.functional.normalize(y.float(), dim=-1)
    u32 = mf.sphere_log(x32, y32)
    assert u32.dtype == torch.float32
    assert torch.linalg.vector_norm(mf.sphere_exp(x32, u32) - y32, dim=-1).max() <= 2e-6
    # gradcheck near (not at) the antipode, through project=True (the checker leaves the sphere)
    for gap in (1e-1, 1e-2, 1e-3):
        xr = x[:3].clone().requires_grad_()
        yr = mf.sphere_exp(x[:3], (math.pi - gap) * t[:3]).requires_grad_()
        assert torch.autograd.gradcheck(lambda a, b: mf.sphere_log(a, b, project=True), (xr, yr))

def _seed_eq183_matrix(x, y):
    """A_{x→y} of Eq. 183 built literally from ū and ‖u‖ (reference; generic points only)."""
    c = (x * y).sum(-1, keepdim=True)
    w = y - c * x
    ubar = w / torch.linalg.norm(w, dim=-1, keepdim=True)
    th = torch.arccos(c).unsqueeze(-1)
    eye = torch.eye(x.shape[-1], dtype=x.dtype)
    outer = ubar.unsqueeze(-1) * ubar.unsqueeze(-2)
    return (-x.unsqueeze(-1) * torch.sin(th) * ubar.unsqueeze(-2) + torch.cos(th) * outer + eye - outer)


@pytest.mark.parametrize("d", [2, 3, 5])
def test_sphere_transport_forms_agree_preserve_inner_products_and_land_in_tangent(d):
    g = _gen(10 + d)
    x, y = _unit((100, d + 1), g), _unit((100, d + 1), g)
    v, w = _tangent(x, g), _tangent(x, g)
    t182 = mf.sphere_transport(x, y, v, form=182)
    t183 = mf.sphere_transport(x, y, v, form=183)
    assert torch.allclose(t182, t183, atol=1e-12)
    assert torch.allclose(mf.sphere_transport_matrix(x, y), _seed_eq183_matrix(x, y), atol=1e-12)
    s183 = mf.sphere_transport(x, y, w, form=183)
    assert torch.allclose((t183 * s183).sum(-1), (v * w).sum(-1), atol=1e-12)          # inner products
    assert (t182 * y).sum(-1).abs().max() < 1e-12                                        # in T_y
    # the geodesic direction is carried onto itself: Γ(Log_x y) = −Log_y x
    assert torch.allclose(mf.sphere_transport(x, y, mf.sphere_log(x, y)), -mf.sphere_log(y, x), atol=1e-12)
    # edges: identity at x = y, both forms still agree at the antipode and 1e-7 from x
    assert torch.allclose(mf.sphere_transport(x, x, v, form=182), v, atol=1e-14)
    assert torch.allclose(mf.sphere_transport(x, x, v, form=183), v, atol=1e-14)
    near = mf.sphere_exp(x, 1e-7 * _tangent(x, g))
    assert torch.allclose(mf.sphere_transport(x, near, v, form=182),
                          mf.sphere_transport(x, near, v, form=183), atol=1e-12)
    a182 = mf.sphere_transport(x, -x, v, form=182)
    assert torch.allclose(a182, mf.sphere_transport(x, -x, v, form=183), atol=1e-12)
    assert torch.allclose(torch.linalg.norm(a182, dim=-1), torch.linalg.norm(v, dim=-1), atol=1e-12)
    # covariance transport A Σ Aᵀ equals the seed's eigen-sum form Σ_i Γ(v_i) Γ(v_i)ᵀ
    V = torch.stack([_tangent(x, g) for _ in range(d)], -1)           # Σ = V Vᵀ = Σ_i v_i v_iᵀ
    A = mf.sphere_transport_matrix(x, y)
    eig_sum = sum(mf.sphere_transport(x, y, V[..., i]).unsqueeze(-1) * mf.sphere_transport(x, y, V[..., i])
                  .unsqueeze(-2) for i in range(d))
    assert torch.allclose(A @ V @ V.mT @ A.mT, eig_sum, atol=1e-12)


def test_sphere_distance_symmetry_and_triangle_inequality():
    g = _gen(3)
    x, y, z = _unit((500, 3), g), _unit((500, 3), g), _unit((500, 3), g)
    assert torch.allclose(mf.sphere_dist(x, y), mf.sphere_dist(y, x), atol=1e-14)
    assert (mf.sphere_dist(x, z) <= mf.sphere_dist(x, y) + mf.sphere_dist(y, z) + 1e-12).all()
    assert (mf.sphere_dist(x, y) <= math.pi).all() and (mf.sphere_dist(x, y) >= 0).all()


def test_sphere_gradcheck():
    g = _gen(4)
    x, y = _unit((3, 4), g), _unit((3, 4), g)
    u = _tangent(x, g, 0.7)
    n = lambda a: a / torch.linalg.norm(a, dim=-1, keepdim=True)
    xr, yr, ur = (t.clone().requires_grad_() for t in (x, y, u))
    assert torch.autograd.gradcheck(lambda a, b: mf.sphere_log(n(a), n(b)), (xr, yr))
    assert torch.autograd.gradcheck(lambda a, b: mf.sphere_dist(n(a), n(b)), (xr, yr))
    assert torch.autograd.gradcheck(lambda a, t: mf.sphere_exp(n(a), t, project=True), (xr, ur))
    assert torch.autograd.gradcheck(lambda a, b, t: mf.sphere_transport(n(a), n(b), t, project=True),
                                    (xr, yr, ur))
    # small-angle branches: u tiny, y within 1e-5 of x
    assert torch.autograd.gradcheck(lambda a, t: mf.sphere_exp(n(a), 1e-5 * t, project=True), (xr, ur))
    yc = mf.sphere_exp(x, 1e-5 * u).clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda a, b: mf.sphere_log(n(a), n(b)), (xr, yc))


def test_sphere_batched_equals_loop_and_broadcasting():
    g = _gen(5)
    x, y = _unit((4, 5, 3), g), _unit((4, 5, 3), g)
    out = mf.sphere_log(x, y)
    loop = torch.stack([torch.stack([mf.sphere_log(x[i, j], y[i, j]) for j in range(5)]) for i in range(4)])
    assert torch.allclose(out, loop, atol=1e-15)
    x0 = x[:, :1]
    assert torch.allclose(mf.sphere_transport_matrix(x0, y), mf.sphere_transport_matrix(x0.expand_as(y), y))


# ==================================================================================================
# SPD
# ==================================================================================================

def _ref_log_map(X, Y):
    Xh = sla.sqrtm(X).real
    Xih = np.linalg.inv(Xh)
    return Xh @ sla.logm(Xih @ Y @ Xih).real @ Xh


@pytest.mark.parametrize("n", [2, 3, 5])
def test_spd_maps_against_scipy_and_round_trips(n):
    g = _gen(20 + n)
    X, Y = _spd((6,), n, g), _spd((6,), n, g)
    U = mf.spd_log(X, Y)
    for i in range(6):
        Xn, Yn = X[i].numpy(), Y[i].numpy()
        assert np.allclose(U[i].numpy(), _ref_log_map(Xn, Yn), atol=1e-9)
        Xh = sla.sqrtm(Xn).real
        Xih = np.linalg.inv(Xh)
        ref_exp = Xh @ sla.expm(Xih @ U[i].numpy() @ Xih) @ Xh
        assert np.allclose(mf.spd_exp(X[i], U[i]).numpy(), ref_exp, atol=1e-9)
        ref_d = np.linalg.norm(sla.logm(Xih @ Yn @ Xih).real)
        assert abs(float(mf.spd_dist(X[i], Y[i])) - ref_d) < 1e-10
    assert torch.allclose(mf.spd_exp(X, U), Y, atol=1e-10)
    V = _sym(torch.randn(6, n, n, generator=g, dtype=F64))
    assert torch.allclose(mf.spd_log(X, mf.spd_exp(X, V)), V, atol=1e-9)
    # float32 round trip
    X32, Y32 = X.float(), Y.float()
    assert torch.allclose(mf.spd_exp(X32, mf.spd_log(X32, Y32)), Y32, rtol=2e-4, atol=2e-4)


def test_spd_distance_properties_and_affine_invariance():
    g = _gen(30)
    X, Y, Z = _spd((100,), 3, g), _spd((100,), 3, g), _spd((100,), 3, g)
    dxy = mf.spd_dist(X, Y)
    assert torch.allclose(dxy, mf.spd_dist(Y, X), atol=1e-10)
    assert (mf.spd_dist(X, Z) <= dxy + mf.spd_dist(Y, Z) + 1e-10).all()
    G = torch.randn(100, 3, 3, generator=g, dtype=F64) + 3 * torch.eye(3, dtype=F64)     # invertible
    assert torch.allclose(mf.spd_dist(_sym(G @ X @ G.mT), _sym(G @ Y @ G.mT)), dxy, atol=1e-8)
    assert torch.allclose(mf.SPD(3).dist(X, Y), dxy, atol=1e-10)
    # a finite gradient (zero) at X == Y
    Xr = X[:2].clone().requires_grad_()
    (gX,) = torch.autograd.grad(mf.spd_dist(Xr, X[:2]).sum(), Xr)
    assert torch.isfinite(gX).all()


def test_spd_transport_isometry_tangent_and_relation_to_geodesic_transport():
    g = _gen(31)
    X, Y = _spd((50,), 3, g), _spd((50,), 3, g)
    U = _sym(torch.randn(50, 3, 3, generator=g, dtype=F64))
    V = _sym(torch.randn(50, 3, 3, generator=g, dtype=F64))
    TU, TV = mf.spd_transport(X, Y, U), mf.spd_transport(X, Y, V)
    assert torch.allclose(TU, TU.mT)                                                   # in T_Y = Sym
    assert torch.allclose(_ai_inner(Y, TU, TV), _ai_inner(X, U, V), atol=1e-9)
    GU, GV = mf.spd_transport_geodesic(X, Y, U), mf.spd_transport_geodesic(X, Y, V)
    assert torch.allclose(_ai_inner(Y, GU, GV), _ai_inner(X, U, V), atol=1e-9)
    # geodesic transport carries the geodesic direction: Γ(Log_X Y) = −Log_Y X
    assert torch.allclose(mf.spd_transport_geodesic(X, Y, mf.spd_log(X, Y)), -mf.spd_log(Y, X), atol=1e-9)
    # Eq. 187 is the geodesic transport along the broken path X → I → Y
    eye = torch.eye(3, dtype=F64).expand(50, 3, 3)
    two_leg = mf.spd_transport_geodesic(eye, Y, mf.spd_transport_geodesic(X, eye, U))
    assert torch.allclose(TU, two_leg, atol=1e-9)
    # and it is not the geodesic transport in general (they differ when X, Y do not commute)
    assert (TU - GU).abs().amax() > 1e-3
    # in the whitened coordinates of SPD(n), Eq. 187 is the identity map
    M = mf.SPD(3)
    c = mf.spd_to_coords(X, U)
    assert torch.allclose(mf.spd_to_coords(Y, TU), c, atol=1e-9)
    assert torch.allclose(M.transport(X, Y, c), c)
    assert torch.allclose(mf.spd_from_coords(X, c), U, atol=1e-10)
    assert torch.allclose(torch.linalg.norm(c, dim=-1) ** 2, _ai_inner(X, U, U), atol=1e-9)


def test_spd_gradcheck_including_repeated_eigenvalues():
    g = _gen(32)
    X, Y = _spd((2,), 3, g), _spd((2,), 3, g)
    U = _sym(torch.randn(2, 3, 3, generator=g, dtype=F64))
    Xr, Yr, Ur = (t.clone().requires_grad_() for t in (X, Y, U))
    assert torch.autograd.gradcheck(lambda a, b: mf.spd_log(_sym(a), _sym(b)), (Xr, Yr))
    assert torch.autograd.gradcheck(lambda a, u: mf.spd_exp(_sym(a), _sym(u)), (Xr, Ur))
    assert torch.autograd.gradcheck(lambda a, b: mf.spd_dist(_sym(a), _sym(b)), (Xr, Yr))
    assert torch.autograd.gradcheck(lambda a, b, u: mf.spd_transport(_sym(a), _sym(b), _sym(u)), (Xr, Yr, Ur))
    # X = I and X = 2I (all eigenvalues equal; eigh's own backward would divide by zero), a double pair
    eye = torch.eye(3, dtype=F64)
    D = torch.diag(torch.tensor([2.0, 2.0, 0.5], dtype=F64))
    for P in (eye, 2 * eye, D):
        Pr = P.clone().requires_grad_()
        assert torch.autograd.gradcheck(lambda a: mf.spd_log(_sym(a), Y[0]), (Pr,))
        assert torch.autograd.gradcheck(lambda a: mf.sym_logm(_sym(a)), (Pr,))
        assert torch.autograd.gradcheck(lambda a: mf.sym_expm(_sym(a) - eye), (Pr,))
        assert torch.autograd.gradcheck(lambda a: mf.sym_sqrtm(_sym(a)), (Pr,))
        assert torch.autograd.gradcheck(lambda a: mf.spd_exp(_sym(a), U[0]), (Pr,))
    # near-ties (1e-9 apart) stay accurate: compare with a finite difference of the eigen-formula
    Dn = torch.diag(torch.tensor([2.0, 2.0 + 1e-9, 0.5], dtype=F64)).requires_grad_()
    assert torch.autograd.gradcheck(lambda a: mf.sym_logm(_sym(a)), (Dn,))
    # torch.func agrees with autograd
    J = torch.func.jacrev(lambda a: mf.sym_logm(_sym(a)))(X[0])
    Jb = torch.autograd.functional.jacobian(lambda a: mf.sym_logm(_sym(a)), X[0])
    assert torch.allclose(J, Jb)


def test_spd_batched_equals_loop():
    g = _gen(33)
    X, Y = _spd((3, 4), 3, g), _spd((3, 4), 3, g)
    out = mf.spd_log(X, Y)
    loop = torch.stack([torch.stack([mf.spd_log(X[i, j], Y[i, j]) for j in range(4)]) for i in range(3)])
    assert torch.allclose(out, loop, atol=1e-12)
    assert torch.allclose(mf.spd_dist(X[:, :1], Y), mf.spd_dist(X[:, :1].expand_as(Y), Y), atol=1e-12)


# ==================================================================================================
# means
# ==================================================================================================

def test_karcher_mean_two_points_closed_forms():
    g = _gen(40)
    # sphere: weighted mean of two points is the slerp point at t = w_y
    x, y = _unit((5, 3), g), _unit((5, 3), g)
    t = torch.rand(5, generator=g, dtype=F64)
    res = mf.karcher_mean(mf.Sphere(2), torch.stack([x, y], 1), torch.stack([1 - t, t], -1))
    th = torch.arccos((x * y).sum(-1, keepdim=True))
    tt = t.unsqueeze(-1)
    slerp = (torch.sin((1 - tt) * th) * x + torch.sin(tt * th) * y) / torch.sin(th)
    assert torch.allclose(res.mean, slerp, atol=1e-10) and res.converged.all()
    # SPD: weighted mean of two matrices is the weighted geometric mean X #_t Y
    X, Y = _spd((5,), 3, g), _spd((5,), 3, g)
    res = mf.karcher_mean(mf.SPD(3), torch.stack([X, Y], 1), torch.stack([1 - t, t], -1))
    for i in range(5):
        Xh = sla.sqrtm(X[i].numpy()).real
        Xih = np.linalg.inv(Xh)
        W = Xih @ Y[i].numpy() @ Xih
        lam, Q = np.linalg.eigh(_sym(torch.from_numpy(W)).numpy())
        ref = Xh @ (Q * lam ** float(t[i])) @ Q.T @ Xh
        assert np.allclose(res.mean[i].numpy(), ref, atol=1e-9)
    assert res.converged.all()


def _noisy_sphere(mu, n, sigma, g):
    v = _tangent(mu.expand(n, *mu.shape[-1:]).clone(), g, sigma)
    return mf.sphere_exp(mu.expand_as(v), v)


@pytest.mark.parametrize("sigma", [0.02, 0.2])
def test_karcher_mean_converges_to_known_point_sphere_spd_so3(sigma):
    g = _gen(41)
    N = 400
    bound = 5 * sigma / math.sqrt(N)          # ≈ 5 standard errors of the mean
    # S²
    mu = _unit((3,), g)
    pts = _noisy_sphere(mu, N, sigma, g)
    res = mf.karcher_mean(mf.Sphere(2), pts)
    assert res.converged and int(res.iterations) <= 10
    assert float(mf.sphere_dist(res.mean, mu)) < bound * math.sqrt(2)
    # the first-order condition Σ Log_μ(x_n) = 0 holds at the result
    assert mf.sphere_log(res.mean.expand_as(pts), pts).mean(0).norm() < 1e-10
    # SPD(3): X_n = Exp_M(noise) with whitened noise of std sigma per coordinate
    M = _spd((), 3, g)
    c = sigma * torch.randn(N, 6, generator=g, dtype=F64)
    Xs = mf.SPD(3).exp_at(M.expand(N, 3, 3), c)
    res = mf.karcher_mean(mf.SPD(3), Xs)
    assert res.converged and int(res.iterations) <= 10
    assert float(mf.spd_dist(res.mean, M)) < bound * math.sqrt(6)
    # SO(3)
    R0 = so3.exp(torch.tensor([0.3, -1.0, 2.0], dtype=F64))
    Rs = R0 @ so3.exp(sigma * torch.randn(N, 3, generator=g, dtype=F64))
    res = mf.karcher_mean(mf.SO3(), Rs)
    assert res.converged and int(res.iterations) <= 10
    assert float(so3.angle(R0.mT @ res.mean)) < bound * math.sqrt(3)
    # SE(3)
    X0 = se3.exp(torch.tensor([0.5, -0.2, 1.0, 0.3, -1.0, 2.0], dtype=F64))
    Xs = X0 @ se3.exp(sigma * torch.randn(N, 6, generator=g, dtype=F64))
    res = mf.karcher_mean(mf.SE3(), Xs)
    assert res.converged and int(res.iterations) <= 10
    assert float(torch.linalg.norm(se3.log(se3.inverse(X0) @ res.mean))) < bound * math.sqrt(6)


def _qmul(p, q):
    pw, pv = p[..., :1], p[..., 1:]
    qw, qv = q[..., :1], q[..., 1:]
    return torch.cat((pw * qw - (pv * qv).sum(-1, keepdim=True),
                      pw * qv + qw * pv + torch.linalg.cross(pv, qv)), -1)


def test_quaternion_mean_on_s3_matches_so3_mean():
    """S³ is SU(2): the round-sphere Karcher mean of (hemisphere-aligned) quaternions is the SO(3) mean."""
    g = _gen(42)
    N, sigma = 300, 0.3
    R0 = so3.exp(torch.tensor([2.0, 0.5, -1.0], dtype=F64))
    Rs = R0 @ so3.exp(sigma * torch.randn(N, 3, generator=g, dtype=F64))
    q = so3.to_quaternion(Rs)
    q = q * torch.where(torch.rand(N, 1, generator=g) < 0.5, -1.0, 1.0).to(F64)   # random ±q signs
    q = mf.hemisphere_align(q, q[0])
    res_q = mf.karcher_mean(mf.Sphere(3), q)
    res_R = mf.karcher_mean(mf.SO3(), Rs)
    assert res_q.converged and res_R.converged
    assert torch.allclose(so3.from_quaternion(res_q.mean), res_R.mean, atol=1e-9)
    assert float(so3.angle(R0.mT @ so3.from_quaternion(res_q.mean))) < 5 * sigma / math.sqrt(N) * math.sqrt(3)


def test_so3_transport_matches_quaternion_sphere_transport():
    """Ad_{exp(−u/2)} on body coordinates is the round-S³ parallel transport seen through q ↦ R(q)."""
    g = _gen(43)
    q1 = _unit((20, 4), g)
    q2 = mf.hemisphere_align(_unit((20, 4), g), q1)
    omega = torch.randn(20, 3, generator=g, dtype=F64)
    zero = torch.zeros(20, 1, dtype=F64)
    qdot = 0.5 * _qmul(q1, torch.cat((zero, omega), -1))                 # tangent at q1 for body rate ω
    qdot2 = mf.sphere_transport(q1, q2, qdot)
    conj = q2 * torch.tensor([1.0, -1, -1, -1], dtype=F64)
    omega2 = 2 * _qmul(conj, qdot2)[..., 1:]
    R1, R2 = so3.from_quaternion(q1), so3.from_quaternion(q2)
    T = mf.SO3().transport(R1, R2, omega)
    assert torch.allclose(T, omega2, atol=1e-10)
    assert torch.allclose(torch.linalg.norm(T, dim=-1), torch.linalg.norm(omega, dim=-1))


def test_transport_round_trip_and_geodesic_direction_for_every_manifold():
    """Γ_{y→x} Γ_{x→y} = I and Γ_{x→y}(Log_x y) = −Log_y x, through the protocol, for all manifolds."""
    g = _gen(45)
    cases = [
        (mf.Sphere(3), _unit((6, 4), g), _unit((6, 4), g)),
        (mf.SPD(3, mf.SPDTransport.GEODESIC), _spd((6,), 3, g), _spd((6,), 3, g)),
        (mf.SO3(), so3.exp(torch.randn(6, 3, generator=g, dtype=F64)),
         so3.exp(torch.randn(6, 3, generator=g, dtype=F64))),
        (mf.SE3(), se3.exp(torch.randn(6, 6, generator=g, dtype=F64)),
         se3.exp(torch.randn(6, 6, generator=g, dtype=F64))),
        (mf.Euclidean(4), torch.randn(6, 4, generator=g, dtype=F64),
         torch.randn(6, 4, generator=g, dtype=F64)),
    ]
    for M, x, y in cases:
        A, B = M.transport_matrix(x, y), M.transport_matrix(y, x)
        m = M.tangent_size
        P = torch.eye(m, dtype=F64)
        if M.normal_basis(x) is not None:                       # identity on T_x only (sphere)
            P = P - M.normal_basis(x) @ M.normal_basis(x).mT
        assert torch.allclose(B @ A @ P, P.expand_as(A), atol=1e-10), type(M).__name__
        name = type(M).__name__
        assert torch.allclose(M.transport(x, y, M.log_at(x, y)), -M.log_at(y, x), atol=1e-10), name
        assert torch.allclose(M.dist(x, y), M.dist(y, x), atol=1e-10)
        assert torch.allclose(M.exp_at(x, M.log_at(x, y)), y, atol=1e-10)
        if not isinstance(M, mf.SE3):                   # an isometry (SE(3)'s transport is not: docstring)
            v, w = ((P @ torch.randn(6, m, 1, generator=g, dtype=F64)).squeeze(-1) for _ in range(2))
            assert torch.allclose((M.transport(x, y, v) * M.transport(x, y, w)).sum(-1), (v * w).sum(-1),
                                  atol=1e-10), name
    # the seed's SPD transport (Eq. 187) is its own inverse pair too, but it does not carry Log_X Y
    X, Y = cases[1][1], cases[1][2]
    seed = mf.SPD(3)
    assert torch.allclose(seed.transport_matrix(Y, X) @ seed.transport_matrix(X, Y), torch.eye(6, dtype=F64))
    # the geodesic transport in coordinates equals spd_transport_geodesic on matrices
    U = _sym(torch.randn(6, 3, 3, generator=g, dtype=F64))
    geo = mf.SPD(3, mf.SPDTransport.GEODESIC)
    assert torch.allclose(geo.transport(X, Y, mf.spd_to_coords(X, U)),
                          mf.spd_to_coords(Y, mf.spd_transport_geodesic(X, Y, U)), atol=1e-10)
    # Euclidean Karcher mean is the weighted average, reached in one step
    pts = torch.randn(3, 7, 4, generator=g, dtype=F64)
    w = torch.rand(3, 7, generator=g, dtype=F64)
    res = mf.karcher_mean(mf.Euclidean(4), pts, w)
    assert torch.allclose(res.mean, (w.unsqueeze(-1) * pts).sum(1) / w.sum(1, keepdim=True), atol=1e-12)
    assert (res.iterations <= 2).all() and res.converged.all()


def test_karcher_mean_batched_equals_loop_and_per_element_status():
    g = _gen(44)
    mu = _unit((3, 3), g)
    pts = torch.stack([_noisy_sphere(mu[i], 30, 0.3, g) for i in range(3)])
    w = torch.rand(3, 30, generator=g, dtype=F64)
    res = mf.karcher_mean(mf.Sphere(2), pts, w)
    for i in range(3):
        ri = mf.karcher_mean(mf.Sphere(2), pts[i], w[i])
        assert torch.allclose(res.mean[i], ri.mean, atol=1e-12)
        assert int(res.iterations[i]) == int(ri.iterations)
    # one element with too few iterations reports not converged; the others are unaffected
    tight = _noisy_sphere(mu[0], 30, 0.05, g)            # converges in ~5 steps
    wide = _noisy_sphere(mu[1], 30, 0.8, g)              # slow linear rate: ~20+ steps
    res2 = mf.karcher_mean(mf.Sphere(2), torch.stack([tight, wide]), max_iter=10)
    assert res2.converged[0] and not res2.converged[1]
    assert int(res2.iterations[1]) == 10 and int(res2.iterations[0]) < 10
    assert torch.allclose(res2.mean[0], mf.karcher_mean(mf.Sphere(2), tight).mean, atol=1e-12)
    # SO(3) batch == loop
    Rs = so3.exp(0.4 * torch.randn(2, 20, 3, generator=g, dtype=F64))
    r = mf.karcher_mean(mf.SO3(), Rs)
    for i in range(2):
        assert torch.allclose(r.mean[i], mf.karcher_mean(mf.SO3(), Rs[i]).mean, atol=1e-12)


# ==================================================================================================
# covariance, density, product
# ==================================================================================================

def test_covariance_recovery_of_known_tangent_noise():
    g = _gen(50)
    N = 6000
    # SO(3): body-frame noise with a known covariance
    L = torch.tensor([[0.05, 0, 0], [0.02, 0.03, 0], [-0.01, 0.01, 0.02]], dtype=F64)
    S_true = L @ L.T
    R0 = so3.exp(torch.tensor([1.0, 0.2, -0.4], dtype=F64))
    Rs = R0 @ so3.exp(torch.randn(N, 3, generator=g, dtype=F64) @ L.T)
    fit = mf.fit_gaussian(mf.SO3(), Rs)
    rel = torch.linalg.norm(fit.covariance - S_true) / torch.linalg.norm(S_true)
    assert fit.converged and rel < 0.08
    # S²: noise in an explicit orthonormal frame of T_μ, covariance compared in ambient coordinates
    mu = torch.nn.functional.normalize(torch.tensor([0.3, -0.5, 0.8], dtype=F64), dim=0)
    E = torch.linalg.qr(torch.eye(3, dtype=F64) - mu[:, None] * mu[None, :])[0][:, :2]
    E = E - mu[:, None] * (mu @ E)[None]
    E = torch.linalg.qr(E)[0]
    C = torch.tensor([[0.04 ** 2, 0.0003], [0.0003, 0.02 ** 2]], dtype=F64)
    z = torch.randn(N, 2, generator=g, dtype=F64) @ torch.linalg.cholesky(C).T
    pts = mf.sphere_exp(mu.expand(N, 3), z @ E.T)
    fit = mf.fit_gaussian(mf.Sphere(2), pts)
    S_amb = E @ C @ E.T
    assert torch.linalg.norm(fit.covariance - S_amb) / torch.linalg.norm(S_amb) < 0.08
    assert (fit.covariance @ fit.mean).abs().max() < 1e-12                 # tangent at the mean
    # SPD(2) in whitened coordinates
    M = _spd((), 2, g)
    C3 = torch.diag(torch.tensor([0.05, 0.03, 0.02], dtype=F64)) ** 2
    c = torch.randn(N, 3, generator=g, dtype=F64) @ C3.sqrt()
    fit = mf.fit_gaussian(mf.SPD(2), mf.SPD(2).exp_at(M.expand(N, 2, 2), c))
    assert torch.linalg.norm(fit.covariance - C3) / torch.linalg.norm(C3) < 0.08


def test_log_density_matches_references():
    g = _gen(51)
    # Euclidean: torch.distributions
    mu = torch.randn(4, 3, generator=g, dtype=F64)
    A = torch.randn(4, 3, 3, generator=g, dtype=F64)
    S = A @ A.mT + 0.1 * torch.eye(3, dtype=F64)
    x = torch.randn(4, 3, generator=g, dtype=F64)
    ref = torch.distributions.MultivariateNormal(mu, S).log_prob(x)
    assert torch.allclose(mf.gaussian_log_density(mf.Euclidean(3), x, mu, S), ref, atol=1e-10)
    # sphere S²: explicit 2-D frame of T_μ + torch.distributions on the coordinates
    m = _unit((3,), g)
    E = torch.linalg.qr(torch.stack([m, torch.randn(3, generator=g, dtype=F64),
                                     torch.randn(3, generator=g, dtype=F64)], 1))[0][:, 1:]
    C = torch.tensor([[0.05, 0.01], [0.01, 0.02]], dtype=F64)
    pts = _noisy_sphere(m, 10, 0.3, g)
    coords = mf.sphere_log(m.expand_as(pts), pts) @ E
    ref = torch.distributions.MultivariateNormal(torch.zeros(2, dtype=F64), C).log_prob(coords)
    out = mf.gaussian_log_density(mf.Sphere(2), pts, m, E @ C @ E.T)
    assert torch.allclose(out, ref, atol=1e-10)
    # SO(3): body coordinates
    R0 = so3.exp(torch.tensor([0.1, 0.2, 0.3], dtype=F64))
    Rs = so3.exp(0.2 * torch.randn(5, 3, generator=g, dtype=F64))
    S3 = torch.diag(torch.tensor([0.1, 0.2, 0.3], dtype=F64))
    ref = torch.distributions.MultivariateNormal(torch.zeros(3, dtype=F64), S3).log_prob(so3.log(R0.mT @ Rs))
    assert torch.allclose(mf.gaussian_log_density(mf.SO3(), Rs, R0, S3), ref, atol=1e-10)


def test_product_of_gaussians_euclidean_matches_closed_form():
    g = _gen(52)
    mu = torch.randn(6, 2, 4, generator=g, dtype=F64)
    A = torch.randn(6, 2, 4, 4, generator=g, dtype=F64)
    S = A @ A.mT + 0.05 * torch.eye(4, dtype=F64)
    res = mf.gaussian_product(mf.Euclidean(4), mu, S)
    S1, S2, m1, m2 = S[:, 0], S[:, 1], mu[:, 0:1].mT, mu[:, 1:2].mT
    inv = torch.linalg.inv(S1 + S2)
    S_ref = S1 @ inv @ S2                                                # seed 004 §2, robust form
    m_ref = (S2 @ inv @ m1 + S1 @ inv @ m2).squeeze(-1)
    assert torch.allclose(res.covariance, S_ref, atol=1e-10)
    assert torch.allclose(res.mean, m_ref, atol=1e-10)
    assert res.converged.all() and (res.iterations <= 2).all()


def test_product_of_gaussians_a_singular_covariance_fails_only_its_element():
    """A degenerate (singular) covariance has no precision: that element ends not converged, the others
    equal the product computed without it (before: one LinAlgError for the whole batch)."""
    g = _gen(53)
    mu = torch.randn(3, 2, 4, generator=g, dtype=F64)
    A = torch.randn(3, 2, 4, 4, generator=g, dtype=F64)
    S = A @ A.mT + 0.05 * torch.eye(4, dtype=F64)
    S[1, 0] = torch.diag(torch.tensor([1.0, 1.0, 0.0, 1.0], dtype=F64))
    res = mf.gaussian_product(mf.Euclidean(4), mu, S)
    assert res.converged.tolist() == [True, False, True]
    ref = mf.gaussian_product(mf.Euclidean(4), mu[[0, 2]], S[[0, 2]])
    torch.testing.assert_close(res.mean[[0, 2]], ref.mean, rtol=0, atol=0)
    torch.testing.assert_close(res.covariance[[0, 2]], ref.covariance, rtol=0, atol=0)


def test_product_of_gaussians_on_sphere_approaches_euclidean_for_tiny_covariances():
    g = _gen(53)
    p = _unit((3,), g)
    E = torch.linalg.qr(torch.stack([p, torch.randn(3, generator=g, dtype=F64),
                                     torch.randn(3, generator=g, dtype=F64)], 1))[0][:, 1:]
    errs = []
    for eps in (1e-2, 1e-3):
        c1, c2 = torch.tensor([1.0, -0.5], dtype=F64) * eps, torch.tensor([-0.3, 0.8], dtype=F64) * eps
        m1, m2 = mf.sphere_exp(p, E @ c1), mf.sphere_exp(p, E @ c2)
        C1 = torch.tensor([[2.0, 0.3], [0.3, 0.5]], dtype=F64) * eps ** 2
        C2 = torch.tensor([[0.4, -0.1], [-0.1, 1.5]], dtype=F64) * eps ** 2
        # each covariance given in T_{m_k}: carry the frame E from p by transport
        Ek = [mf.sphere_transport_matrix(p, mk) @ E for mk in (m1, m2)]
        S = torch.stack([Ek[0] @ C1 @ Ek[0].T, Ek[1] @ C2 @ Ek[1].T])
        res = mf.gaussian_product(mf.Sphere(2), torch.stack([m1, m2]), S)
        assert res.converged
        inv = torch.linalg.inv(C1 + C2)
        c_ref = C2 @ inv @ c1 + C1 @ inv @ c2
        c_got = mf.sphere_log(p, res.mean) @ E
        errs.append(float(torch.linalg.norm(c_got - c_ref)) / eps)
        cov_got = E.T @ mf.sphere_transport_matrix(res.mean, p) @ res.covariance @ \
            mf.sphere_transport_matrix(res.mean, p).T @ E
        C_ref = C1 @ inv @ C2
        assert torch.linalg.norm(cov_got - C_ref) / torch.linalg.norm(C_ref) < 10 * eps
    assert errs[0] < 0.05 and errs[1] < errs[0] / 5             # relative error shrinks with the scale


def test_product_of_gaussians_on_so3_is_the_minimizer_of_the_summed_cost():
    """A different formulation: the product mean is (nearly) stationary for Σ_k ‖Log_{μ_k}(μ)‖²_{Σ_k⁻¹}.

    The Gauss–Newton fixed point differs from the exact minimizer at second order (it neglects the
    derivative of the Log); with the transport Ad_{exp(−u/2)} the residual gradient is ~3e-4 of the
    gradient scale on this problem, with the identity instead of a transport it is ~1.4e-2 and with the
    opposite sign ~2.9e-2, so the bound below checks the transport too.
    """
    R1 = so3.exp(torch.tensor([0.2, 0.1, -0.1], dtype=F64))
    R2 = so3.exp(torch.tensor([0.1, -0.15, 0.05], dtype=F64))
    S1 = torch.diag(torch.tensor([1.0, 2.0, 0.5], dtype=F64)) * 0.01
    S2 = torch.diag(torch.tensor([0.5, 1.0, 3.0], dtype=F64)) * 0.01
    res = mf.gaussian_product(mf.SO3(), torch.stack([R1, R2]), torch.stack([S1, S2]))
    assert res.converged and int(res.iterations) <= 10

    def cost(delta):
        R = res.mean @ so3.exp(delta)
        e1, e2 = so3.log(R1.mT @ R), so3.log(R2.mT @ R)
        return e1 @ torch.linalg.solve(S1, e1) + e2 @ torch.linalg.solve(S2, e2)

    grad = torch.func.grad(cost)(torch.zeros(3, dtype=F64))
    scale = torch.func.grad(cost)(so3.log(res.mean.mT @ R1))          # the gradient at μ = R1
    assert float(torch.linalg.norm(grad)) < 2e-3 * float(torch.linalg.norm(scale))


def test_product_of_gaussians_on_spd_near_stationary_with_both_transports():
    """Same check as for SO(3) on SPD(3); the geodesic transport lands ~25× closer to stationarity."""
    g = _gen(55)
    base = mf.SPD(3)
    M0 = torch.tensor([[2.0, 0.3, 0.1], [0.3, 1.0, 0.2], [0.1, 0.2, 1.5]], dtype=F64)
    Xk = base.exp_at(M0, 0.1 * torch.randn(2, 6, generator=g, dtype=F64))
    A = torch.randn(2, 6, 6, generator=g, dtype=F64)
    Sk = 0.01 * (A @ A.mT / 6 + 0.1 * torch.eye(6, dtype=F64))
    rel = {}
    for kind in mf.SPDTransport:
        res = mf.gaussian_product(mf.SPD(3, kind), Xk, Sk)
        assert res.converged and int(res.iterations) <= 20

        def cost(d, res=res):
            mu = base.exp_at(res.mean, d, check=False)
            e = base.log_at(Xk, mu, check=False)
            return (e * torch.linalg.solve(Sk, e.unsqueeze(-1)).squeeze(-1)).sum()

        grad = torch.autograd.functional.jacobian(cost, torch.zeros(6, dtype=F64))
        scale = torch.autograd.functional.jacobian(cost, base.log_at(res.mean, Xk[0]))
        rel[kind] = float(torch.linalg.norm(grad) / torch.linalg.norm(scale))
        # the covariance is the inverse of the summed transported precisions: SPD and smaller than each
        assert (torch.linalg.eigvalsh(res.covariance) > 0).all()
        assert torch.linalg.eigvalsh(Sk.sum(0) - res.covariance).min() > 0
    # measured: seed 2.7e-2, geodesic 1.0e-3 (halving the spread divides the geodesic one by ~4 and the
    # seed one by ~2.6: Eq. 187 transports through I, which is a first-order error away from I)
    assert rel[mf.SPDTransport.SEED] < 5e-2 and rel[mf.SPDTransport.GEODESIC] < 2e-3
    assert rel[mf.SPDTransport.GEODESIC] < rel[mf.SPDTransport.SEED] / 10


# ==================================================================================================
# bad input
# ==================================================================================================

def test_bad_inputs_raise_naming_the_argument():
    g = _gen(60)
    x = _unit((4, 3), g)
    with pytest.raises(ValueError, match="'y'.*unit sphere"):
        mf.sphere_log(x, 1.1 * x)
    assert torch.allclose(mf.sphere_log(x, 1.1 * x, project=True), torch.zeros_like(x), atol=1e-15)
    with pytest.raises(ValueError, match="'u'.*tangent"):
        mf.sphere_exp(x, x)
    with pytest.raises(ValueError, match="'x'"):
        mf.sphere_exp(torch.zeros(4, 3, dtype=F64), x, project=True)
    with pytest.raises(TypeError, match="'x'"):
        mf.sphere_log([1.0, 0.0], x)
    with pytest.raises(ValueError, match="form"):
        mf.sphere_transport(x, x, x, form=181)
    with pytest.raises(ValueError, match="'y'"):
        mf.sphere_log(x, torch.ones(4, 5, dtype=F64) / 5 ** 0.5)
    with pytest.raises(TypeError, match="dtype"):
        mf.sphere_log(x, x.float())
    # tolerance follows the dtype: 1e-6 off is fine in float32, not in float64
    off = x * (1 + 1e-6)
    mf.sphere_log(off.float(), x.float())
    with pytest.raises(ValueError, match="'x'"):
        mf.sphere_log(off, x)
    # SPD
    X = _spd((2,), 3, g)
    bad = X.clone()
    bad[1] = -bad[1]
    with pytest.raises(ValueError, match="'Y'.*positive definite.*batch index \\(1,\\)"):
        mf.spd_log(X, bad)
    asym = X.clone()
    asym[0, 0, 1] += 0.1
    with pytest.raises(ValueError, match="'X'.*symmetric"):
        mf.spd_dist(asym, X)
    proj = mf.sym_logm(bad, project=True)
    assert torch.isfinite(proj).all()
    assert torch.allclose(mf.spd_dist(asym, X, project=True)[1], torch.zeros((), dtype=F64), atol=1e-7)
    with pytest.raises(ValueError, match="'U'.*symmetric"):
        mf.spd_exp(X, torch.randn(2, 3, 3, generator=g, dtype=F64))
    with pytest.raises(ValueError, match="'X'.*\\(\\*, n, n\\)"):
        mf.spd_log(torch.ones(3, 4, dtype=F64), X)
    # rotations
    R = so3.exp(torch.randn(3, 3, generator=g, dtype=F64))
    Rb = R.clone()
    Rb[2] = Rb[2] * 1.01
    with pytest.raises(ValueError, match="'y'.*rotation.*batch index \\(2,\\)"):
        mf.SO3().log_at(R, Rb)
    with pytest.raises(ValueError, match="rotation"):
        mf.SO3().log_at(R, -R)                                              # det = −1
    v = mf.SO3().log_at(R, Rb, project=True)
    assert torch.isfinite(v).all() and v[:2].abs().max() < 1e-12
    Xb = se3.exp(torch.randn(2, 6, generator=g, dtype=F64))
    Xb[0, 3, 0] = 0.5
    with pytest.raises(ValueError, match="homogeneous"):
        mf.SE3().check_point(Xb)
    # statistics
    pts = _noisy_sphere(x[0], 10, 0.2, g)
    with pytest.raises(ValueError, match="'weights'"):
        mf.karcher_mean(mf.Sphere(2), pts, -torch.ones(10, dtype=F64))
    with pytest.raises(ValueError, match="'points'"):
        mf.karcher_mean(mf.Sphere(2), pts[0])
    with pytest.raises(ValueError, match="'points'"):
        mf.karcher_mean(mf.Sphere(2), 2 * pts)
    assert mf.karcher_mean(mf.Sphere(2), 2 * pts, project=True).converged
    with pytest.raises(TypeError, match="'manifold'"):
        mf.karcher_mean("sphere", pts)
    with pytest.raises(ValueError, match="'covariances'"):
        mf.gaussian_product(mf.Sphere(2), pts[:2], torch.eye(3, dtype=F64).expand(3, 3, 3))
    with pytest.raises(ValueError, match="'covariance'"):
        mf.gaussian_log_density(mf.Euclidean(3), pts[0], pts[1], -torch.eye(3, dtype=F64))
    with pytest.raises(ValueError, match="'d'"):
        mf.Sphere(0)


def test_project_gradients_are_finite_at_exact_points():
    R = so3.exp(torch.tensor([0.3, 0.2, 0.1], dtype=F64)).requires_grad_()
    v = mf.SO3().log_at(R, R.detach(), project=True)
    (gR,) = torch.autograd.grad(v.sum(), R)
    assert torch.isfinite(gR).all()
    X = torch.eye(3, dtype=F64).requires_grad_()
    (gX,) = torch.autograd.grad(mf.sym_logm(X, project=True).sum(), X)
    assert torch.isfinite(gX).all()


# ==================================================================================================
# example
# ==================================================================================================

def test_example_riemannian_mean(tmp_path):
    from examples.riemannian_mean import main

    out = main(n_samples=200, seed=0, plot=True, out_dir=tmp_path)
    assert (tmp_path / "convergence.png").stat().st_size > 0
    assert out["spd"]["converged"] and out["quaternion"]["converged"]
    assert out["spd"]["error"] < out["spd"]["bound"]
    assert out["quaternion"]["error_rad"] < out["quaternion"]["bound_rad"]
    # the affine-invariant mean beats the (swollen) arithmetic mean of the SPD samples
    assert out["spd"]["error"] < out["spd"]["euclidean_error"]
    assert out["spd"]["iterations"] <= 10 and out["quaternion"]["iterations"] <= 10
