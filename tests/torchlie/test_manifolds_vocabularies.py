"""The merge of issue 10 §4: one class per space carries both vocabularies, and one tolerance rule.

* Where ⊞/⊟/⊕ (seed 003) and Exp/Log (seed 004) are the same map — Rⁿ, SO(2), SO(3), SE(3) — the
  two give bitwise-identical results.
* On S² they are different coordinates of the same geodesics: ``x ⊞ δ = exp_at(x, (B(x)δ) × x)``,
  ``log_at(x, y) = (B(x)(y ⊟ x)) × x``, ``dist = r‖y ⊟ x‖`` — checked for several radii, with the
  unit-sphere functional core as the r = 1 reference.
* Every membership check of both vocabularies (and of the functional cores and the statistics)
  accepts a point 0.3·tol off and rejects one 3·tol off, tol = ``manifold_tolerance(dtype)``.
"""

from __future__ import annotations

import math

import pytest
import torch

from torchlie import se3, so2, so3
from torchlie.manifolds import (
    S2,
    SE3,
    SO2,
    SO3,
    SPD,
    Euclidean,
    Manifold,
    ProductManifold,
    RiemannianManifold,
    Rn,
    Sphere,
    Surface,
    karcher_mean,
    manifold_tolerance,
    quadratic_surface,
    spd_log,
    sphere_exp,
    sphere_log,
)

F64 = torch.float64
DTYPES = [torch.float32, F64]


def _gen(seed):
    return torch.Generator().manual_seed(seed)


# ------------------------------------------------------------------------------------------------
# the same map under two names
# ------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("M", [Rn(4), SO2(), SO3(), SE3()], ids=lambda M: type(M).__name__)
def test_groups_exp_log_are_boxplus_boxminus(M, dtype):
    g = _gen(0)
    x, y = M.random(20, generator=g, dtype=dtype), M.random(20, generator=g, dtype=dtype)
    d = torch.randn(20, M.dim, generator=g, dtype=dtype)
    assert M.has_boxplus and M.has_exp_log and M.tangent_size == M.dim
    assert M.point_shape == M.event_shape
    assert torch.equal(M.exp_at(x, d), M.boxplus(x, d))
    assert torch.equal(M.exp_at(x, d), M.oplus(x, d))
    assert torch.equal(M.log_at(x, y), M.boxminus(y, x))
    torch.testing.assert_close(M.dist(x, y), torch.linalg.vector_norm(M.boxminus(y, x), dim=-1))
    # and both are the group modules' X·Exp(δ), Log(X⁻¹Y)
    grp = {SO2: so2, SO3: so3, SE3: se3}.get(type(M))
    if grp is not None:
        torch.testing.assert_close(M.exp_at(x, d), x @ grp.exp(d))
        torch.testing.assert_close(M.log_at(x, y), grp.log(grp.inverse(x) @ y))


def test_euclidean_is_rn():
    assert Euclidean is Rn and Euclidean(3) == Rn(3)
    x, y = torch.randn(2, 5, 3, dtype=F64).unbind(0)
    assert torch.equal(Euclidean(3).log_at(x, y), Rn(3).boxminus(y, x))


def test_so2_transport_is_identity_and_karcher_mean_is_the_mean_angle():
    g = _gen(1)
    th0 = 2.5
    noise = 0.3 * torch.randn(3, 40, generator=g, dtype=F64)
    R = so2.exp((th0 + noise).unsqueeze(-1))
    res = karcher_mean(SO2(), R)
    assert res.converged.all()
    # no sample is farther than π from the mean, so the Karcher mean is the plain mean angle
    ref = so2.exp((th0 + noise.mean(-1)).unsqueeze(-1))
    torch.testing.assert_close(res.mean, ref, rtol=0, atol=1e-12)
    torch.testing.assert_close(SO2().transport_matrix(R[:, 0], R[:, 1]), torch.ones(3, 1, 1, dtype=F64))


@pytest.mark.parametrize("r", [0.5, 1.0, 2.5])
def test_sphere_chart_and_ambient_coordinates_describe_the_same_geodesics(r):
    M = S2(r)
    assert M == Sphere(2, r) and isinstance(M, Sphere) and M.has_boxplus and M.has_exp_log
    g = _gen(2)
    x, y = M.random(200, generator=g, dtype=F64), M.random(200, generator=g, dtype=F64)
    d = 2.5 * torch.randn(200, 2, generator=g, dtype=F64).clamp(-1, 1)   # |δ| < π: inside the cut locus
    B = M.basis(x)
    u = torch.linalg.cross((B @ d.unsqueeze(-1)).squeeze(-1), x, dim=-1)      # ambient tangent of x ⊞ δ
    assert (u * x).sum(-1).abs().max() < 1e-13 * r * r
    torch.testing.assert_close(torch.linalg.vector_norm(u, dim=-1), r * torch.linalg.vector_norm(d, dim=-1))
    torch.testing.assert_close(M.boxplus(x, d), M.exp_at(x, u), rtol=0, atol=1e-13 * r)
    # ⊟ and log_at: the 2-vector in the basis B(x) vs the ambient 3-vector
    delta = M.boxminus(y, x)
    ref = torch.linalg.cross((B @ delta.unsqueeze(-1)).squeeze(-1), x, dim=-1)
    torch.testing.assert_close(M.log_at(x, y), ref, rtol=0, atol=1e-12 * r)
    torch.testing.assert_close(M.dist(x, y), r * torch.linalg.vector_norm(delta, dim=-1), rtol=0,
                               atol=1e-12 * r)
    # ⊕ by a rotation vector ω ⟂ x is Exp_x(ω × x)
    w = torch.randn(200, 3, generator=g, dtype=F64)
    w = w - (w * x).sum(-1, keepdim=True) * x / (r * r)
    torch.testing.assert_close(M.oplus(x, w), M.exp_at(x, torch.linalg.cross(w, x, dim=-1)), rtol=0,
                               atol=1e-12 * r)
    # the Exp/Log vocabulary on radius r: round trip, arc length, transport isometry
    torch.testing.assert_close(M.exp_at(x, M.log_at(x, y)), y, rtol=0, atol=1e-12 * r)
    ang = torch.arccos(((x * y).sum(-1) / (r * r)).clamp(-1, 1))
    torch.testing.assert_close(M.dist(x, y), r * ang, rtol=0, atol=1e-7 * r)
    v = M.check_tangent(x, torch.randn(200, 3, generator=g, dtype=F64), project=True)
    Tv = M.transport(x, y, v)
    torch.testing.assert_close(torch.linalg.vector_norm(Tv, dim=-1), torch.linalg.vector_norm(v, dim=-1))
    assert (Tv * y).sum(-1).abs().max() < 1e-12 * r
    torch.testing.assert_close(M.normal_basis(x).squeeze(-1), x / r)


def test_unit_sphere_class_equals_functional_core_bitwise():
    g = _gen(3)
    for d in (1, 2, 3, 6):
        M = Sphere(d)
        x, y = M.random(30, generator=g, dtype=F64), M.random(30, generator=g, dtype=F64)
        u = M.check_tangent(x, torch.randn(30, d + 1, generator=g, dtype=F64), project=True)
        assert torch.equal(M.exp_at(x, u), sphere_exp(x, u))
        assert torch.equal(M.log_at(x, y), sphere_log(x, y))
        assert M.has_boxplus == (d == 2)


# ------------------------------------------------------------------------------------------------
# one tolerance rule
# ------------------------------------------------------------------------------------------------

def _off_sphere(k, dtype):
    x = torch.nn.functional.normalize(torch.tensor([[0.3, -0.5, 0.8]], dtype=F64), dim=-1)
    return (x * (1 + k * manifold_tolerance(dtype))).to(dtype)


def _off_rotation(k, dtype):
    # RᵀR − I ≈ 2k·tol·I, det − 1 ≈ 3k·tol
    R = so3.exp(torch.tensor([[0.3, -0.2, 0.1]], dtype=F64))
    return (R * (1 + k * manifold_tolerance(dtype))).to(dtype)


def _off_transform(k, dtype):
    X = se3.exp(torch.tensor([[0.3, -0.2, 0.1, 0.5, 0.4, -0.3]], dtype=F64))
    X[..., 3, 0] = k * manifold_tolerance(dtype)
    return X.to(dtype)


def _call(entry, M, bad, y, dtype):
    """Call one entry point of either vocabulary with the point ``bad`` (and the good point y)."""
    zeros = torch.zeros(1, M.tangent_size, dtype=dtype)
    calls = {
        "check": lambda: M.check(bad),
        "check_point": lambda: M.check_point(bad),
        "boxplus": lambda: M.boxplus(bad, torch.zeros(1, M.dim, dtype=dtype)),
        "boxminus": lambda: M.boxminus(y, bad),
        "G_x": lambda: M.G_x(bad, torch.zeros(1, M.ext_dim, dtype=dtype)),
        "exp_at": lambda: M.exp_at(bad, zeros),
        "log_at": lambda: M.log_at(bad, y),
        "dist": lambda: M.dist(y, bad),
        "transport_matrix": lambda: M.transport_matrix(bad, y),
        "karcher_mean": lambda: karcher_mean(M, torch.cat((y, bad)).unsqueeze(0)),
    }
    return calls[entry]()


ENTRIES = ["check", "check_point", "boxplus", "boxminus", "G_x", "exp_at", "log_at", "dist",
           "transport_matrix", "karcher_mean"]
OFF = {"S2": (S2(), _off_sphere), "Sphere(2)": (Sphere(2), _off_sphere), "SO3": (SO3(), _off_rotation),
       "SE3": (SE3(), _off_transform)}


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("space", list(OFF))
def test_one_tolerance_for_both_vocabularies(space, dtype):
    M, off = OFF[space]
    tol = manifold_tolerance(dtype)
    assert tol == math.sqrt(torch.finfo(dtype).eps)
    ok, bad, y = off(0.3, dtype), off(3.0, dtype), M.identity(1, dtype=dtype)
    for entry in ENTRIES:
        _call(entry, M, ok, y, dtype)                       # accepted by every entry point ...
        with pytest.raises(ValueError, match=f"tolerance {tol:.2g}"):
            _call(entry, M, bad, y, dtype)                  # ... rejected by every one, same tolerance
    # the functional sphere core: same rule
    if isinstance(M, Sphere):
        sphere_log(ok, y)
        with pytest.raises(ValueError, match=f"'x'.*tolerance {tol:.2g}"):
            sphere_log(bad, y)


def _tangent_and_symmetry_calls(k, dtype):
    tol = manifold_tolerance(dtype)
    x = torch.tensor([[0.0, 0.0, 1.0]], dtype=dtype)
    u = torch.tensor([[2.0, 0.0, 0.0]], dtype=dtype) + 2 * k * tol * x      # relative normal part k·tol
    X = torch.diag(torch.tensor([2.0, 1.0, 0.5], dtype=dtype))
    X[0, 1] += k * tol * 2                                                   # relative asymmetry k·tol
    return [
        ("tangent", lambda: Sphere(2).exp_at(x, u)),
        ("tangent", lambda: sphere_exp(x, u)),
        ("tangent", lambda: Sphere(2).transport(x, x, u)),
        ("tangent", lambda: Sphere(2).check_tangent(x, u)),
        ("symmetric", lambda: SPD(3).check(X)),
        ("symmetric", lambda: SPD(3).log_at(X, X)),
        ("symmetric", lambda: spd_log(X, X)),
    ]


@pytest.mark.parametrize("dtype", DTYPES)
def test_one_tolerance_for_tangent_vectors_and_symmetry(dtype):
    for _, call in _tangent_and_symmetry_calls(0.3, dtype):
        call()
    for what, call in _tangent_and_symmetry_calls(3.0, dtype):
        with pytest.raises(ValueError, match=f"{what}.*tolerance {manifold_tolerance(dtype):.2g}"):
            call()


# ------------------------------------------------------------------------------------------------
# which space has which vocabulary
# ------------------------------------------------------------------------------------------------

def test_missing_vocabularies_are_explicit():
    surf = quadratic_surface(torch.tensor([0.1, 0.0, 0.1, 0.0, 0.0, 1.0], dtype=F64))
    prod = ProductManifold({"p": Rn(3), "R": SO3()})
    assert isinstance(surf, Surface) and surf.has_boxplus and not surf.has_exp_log
    assert prod.has_boxplus and not prod.has_exp_log
    assert SPD(3).has_exp_log and not SPD(3).has_boxplus
    for M in (Rn(2), SO2(), SO3(), SE3(), Sphere(4), SPD(2)):
        assert isinstance(M, Manifold) and isinstance(M, RiemannianManifold)
    p = surf.identity(2, dtype=F64)
    with pytest.raises(NotImplementedError, match="exp_at"):
        surf.exp_at(p, torch.zeros(2, 2, dtype=F64))
    with pytest.raises(NotImplementedError, match="exp_at"):
        prod.log_at(prod.identity(dtype=F64), prod.identity(dtype=F64))
    with pytest.raises(NotImplementedError, match="⊞"):
        Sphere(3).boxplus(Sphere(3).identity(dtype=F64), torch.zeros(3, dtype=F64))
    with pytest.raises(NotImplementedError, match="⊞"):
        SPD(2).boxminus(torch.eye(2, dtype=F64), torch.eye(2, dtype=F64))
    with pytest.raises(NotImplementedError, match="⊞"):
        _ = Sphere(3).ext_dim
    with pytest.raises(TypeError, match="'q'.*⊞"):
        ProductManifold({"q": Sphere(3)})
    with pytest.raises(TypeError, match="'S'.*⊞"):
        ProductManifold({"S": SPD(3)})
    with pytest.raises(TypeError, match="'manifold'"):
        karcher_mean(surf, surf.random(2, 5, dtype=F64))
    with pytest.raises(ValueError, match="'d'"):
        Sphere(0)


def test_spd_points_and_generic_sphere_points():
    X = SPD(3).random(4, generator=_gen(5), dtype=F64)
    assert torch.equal(SPD(3).check(X), 0.5 * (X + X.mT))
    assert torch.equal(SPD(3).identity(dtype=F64), torch.eye(3, dtype=F64))
    assert (torch.linalg.eigvalsh(X) > 0).all()
    S = Sphere(4, 2.0)
    x = S.random(6, generator=_gen(6), dtype=F64)
    S.check(x)
    torch.testing.assert_close(S.identity(dtype=F64), torch.tensor([0, 0, 0, 0, 2.0], dtype=F64))
    with pytest.raises(ValueError, match="sphere of radius 2 in R\\^5"):
        S.check(x * 1.1)
    torch.testing.assert_close(S.project(x * 1.1), x)
