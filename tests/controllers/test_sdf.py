"""SDFs on basis functions (seed 004 §6.4, §6.8): the eikonal Gauss–Newton fit and the closest points between
two shapes, against exact circle distances, autograd stationarity, scipy and per-sample loops."""

import functools
import math

import numpy as np
import pytest
import torch
from scipy.optimize import minimize

from controllers import basis, sdf
from controllers.problem import Reason

D = torch.float64
LO, HI = [-1.0, -1.0], [1.0, 1.0]


def _circle(c, r, M=48):
    th = torch.linspace(0, 2 * math.pi, M + 1, dtype=D)[:-1]
    return torch.tensor(c, dtype=D) + r * torch.stack([th.cos(), th.sin()], -1)


def _ellipse(a, b, M=48):
    th = torch.linspace(0, 2 * math.pi, M + 1, dtype=D)[:-1]
    return torch.stack([a * th.cos(), b * th.sin()], -1)


@pytest.fixture(scope="module")
def fitted():
    shapes = torch.stack([_circle([0.1, -0.05], 0.5), _ellipse(0.6, 0.35)])
    res = sdf.fit_sdf(shapes, LO, HI, eikonal_weight=0.01, eikonal_grid=14, max_iter=60, tol=1e-7)
    plain = sdf.fit_sdf(shapes, LO, HI, eikonal_weight=0.0, eikonal_grid=14, max_iter=60, tol=1e-7)
    return shapes, res, plain


def _grid_points(n=31, lim=0.9):
    g = torch.linspace(-lim, lim, n, dtype=D)
    return torch.stack(torch.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)


def test_eikonal_fit_matches_the_exact_circle_distance(fitted):
    shapes, res, plain = fitted
    assert res.converged.all(), res.reason
    assert bool((res.reason == int(Reason.CONVERGED)).all())
    # contour points on the zero level set
    f_b = sdf.sdf_value(res.sdf, shapes.transpose(0, 1))  # (M, 2)
    assert f_b.abs().max() < 0.02
    # the circle's exact signed distance, in a band around the contour
    p = _grid_points()
    d_true = torch.linalg.vector_norm(p - torch.tensor([0.1, -0.05], dtype=D), dim=-1) - 0.5
    f, g = sdf.sdf_value_and_grad(res.sdf, p[:, None, :])
    band = d_true.abs() < 0.3
    assert (f[band, 0] - d_true[band]).abs().max() < 0.05
    # signs: negative inside, positive outside (away from the contour), for both shapes
    inside_e = (p[:, 0] / 0.6) ** 2 + (p[:, 1] / 0.35) ** 2 < 1
    far_c = d_true.abs() > 0.08
    assert ((f[:, 0] < 0) == (d_true < 0))[far_c].all()
    e_level = (p[:, 0] / 0.6) ** 2 + (p[:, 1] / 0.35) ** 2
    far_e = (e_level - 1).abs() > 0.4
    assert ((f[:, 1] < 0) == inside_e)[far_e].all()
    # the eikonal term (Fig. 16): gradient norms closer to one than the fit without it
    eik = (torch.linalg.vector_norm(g, dim=-1) - 1).pow(2).mean(0).sqrt()
    _, g0 = sdf.sdf_value_and_grad(plain.sdf, p[:, None, :])
    eik0 = (torch.linalg.vector_norm(g0, dim=-1) - 1).pow(2).mean(0).sqrt()
    assert (eik < 0.13).all() and (eik < eik0).all(), (eik, eik0)


def test_eikonal_fit_is_a_stationary_point_of_eq58_by_autograd(fitted):
    """The solver checks ‖2Jᵀf‖ with its analytic Jacobian; autograd of the cost written from Eq. (58)
    agrees."""
    shapes, res, _ = fitted
    lam = 0.01
    u_e = (torch.arange(14, dtype=D) + 0.5) / 14
    e_pts = -1 + 2 * torch.stack(torch.meshgrid(u_e, u_e, indexing="ij"), -1).reshape(-1, 2)
    w = res.sdf.w.clone().requires_grad_(True)
    s = sdf.SDF(w[:, None, :], res.sdf.lower, res.sdf.upper, res.sdf.basis)
    fb = sdf.sdf_value(s, shapes)
    _, ge = sdf.sdf_value_and_grad(s, e_pts.expand(2, -1, -1))
    cost = (fb ** 2).sum(-1) + lam * (((ge ** 2).sum(-1) - 1) ** 2).sum(-1)
    grad = torch.autograd.grad(cost.sum(), w)[0]
    assert torch.linalg.vector_norm(grad, dim=-1).max() < 1e-6
    torch.testing.assert_close(cost.detach(), res.cost, rtol=1e-10, atol=1e-14)


def test_fit_batched_equals_per_shape_and_nan_shape_is_isolated(fitted):
    shapes, res, _ = fitted
    one = sdf.fit_sdf(shapes[1], LO, HI, eikonal_weight=0.01, eikonal_grid=14, max_iter=60, tol=1e-7)
    torch.testing.assert_close(one.sdf.w, res.sdf.w[1], atol=1e-9, rtol=0)
    bad = shapes.clone()
    bad[0, 3, 0] = math.nan
    rb = sdf.fit_sdf(bad, LO, HI, eikonal_weight=0.01, eikonal_grid=14, max_iter=60, tol=1e-7)
    assert not bool(rb.converged[0]) and bool(rb.converged[1])
    torch.testing.assert_close(rb.sdf.w[1], res.sdf.w[1], atol=1e-9, rtol=0)


def test_fit_with_observed_distances_and_float32():
    # distances observed off the contour (Eq. 58's x_m) pin down the circle's SDF everywhere in the band
    c = torch.tensor([0.0, 0.1], dtype=D)
    pts = torch.cat([_circle([0.0, 0.1], r, 24) for r in (0.3, 0.6, 0.8)])
    dist = torch.linalg.vector_norm(pts - c, dim=-1) - 0.5
    b4 = sdf.default_sdf_basis(4)
    r = sdf.fit_sdf(pts, LO, HI, basis=b4, distances=dist, eikonal_weight=0.01, eikonal_grid=16, tol=1e-8)
    assert bool(r.converged)
    q = _circle([0.0, 0.1], 0.45, 17)
    torch.testing.assert_close(sdf.sdf_value(r.sdf, q), torch.full((17,), -0.05, dtype=D), atol=0.02, rtol=0)
    r32 = sdf.fit_sdf(pts.float(), LO, HI, basis=b4, distances=dist.float(), eikonal_weight=0.01,
                      eikonal_grid=16, tol=1e-3)
    assert r32.sdf.w.dtype == torch.float32
    assert (sdf.sdf_value(r32.sdf, q.float()).double() - sdf.sdf_value(r.sdf, q)).abs().max() < 1e-3


def test_sdf_gradient_matches_autograd(fitted):
    _, res, _ = fitted
    g0 = torch.Generator().manual_seed(0)
    p = 0.8 * (torch.rand(6, 2, 2, dtype=D, generator=g0) * 2 - 1)  # (6, S=2, 2)
    f, g = sdf.sdf_value_and_grad(res.sdf, p)
    pa = p.clone().requires_grad_(True)
    ga = torch.autograd.grad(sdf.sdf_value(res.sdf, pa).sum(), pa)[0]
    torch.testing.assert_close(g, ga, atol=1e-12, rtol=1e-10)
    h = 1e-6
    fd = torch.stack([(sdf.sdf_value(res.sdf, p + h * e) - sdf.sdf_value(res.sdf, p - h * e)) / (2 * h)
                      for e in torch.eye(2, dtype=D)], -1)
    torch.testing.assert_close(g, fd, atol=1e-7, rtol=0)


def test_fit_bad_input():
    b = _circle([0, 0], 0.5)
    with pytest.raises(ValueError, match="'boundary'"):
        sdf.fit_sdf(b[:, 0], LO, HI)
    with pytest.raises(ValueError, match="'upper'"):
        sdf.fit_sdf(b, HI, LO)
    with pytest.raises(ValueError, match="'eikonal_weight'"):
        sdf.fit_sdf(b, LO, HI, eikonal_weight=-1.0)
    with pytest.raises(ValueError, match="'distances'"):
        sdf.fit_sdf(b, LO, HI, distances=torch.zeros(3, dtype=D))


# ----------------------------------------------------------------------------------------------------------
# closest points: two ellipses, whose implicit fields x²/a² + y²/b² - 1 are biquadratic Bézier surfaces
# ----------------------------------------------------------------------------------------------------------

AXES = [(0.6, 0.3), (0.4, 0.25)]
BERN3 = functools.partial(basis.bernstein_deriv, K=3)


def _ellipse_field(a, b):
    p = _grid_points(9, 1.0)
    vals = (p[:, 0] / a) ** 2 + (p[:, 1] / b) ** 2 - 1
    w = basis.fit(basis.tensor_basis((p + 1) / 2, BERN3), vals)
    return sdf.SDF(w, torch.tensor(LO, dtype=D), torch.tensor(HI, dtype=D), BERN3)


def _rot(th):
    th = torch.as_tensor(th, dtype=D)
    return torch.stack([torch.stack([th.cos(), -th.sin()], -1), torch.stack([th.sin(), th.cos()], -1)], -2)


POSES = (torch.tensor([0.4, -1.1, 2.5], dtype=D),
         torch.tensor([[1.5, 0.4], [-0.3, 1.2], [-1.3, -0.8]], dtype=D))


def _reference_distance(A, b):
    """Parametric ellipses: a dense search refined by scipy over the two angles."""
    (a1, b1), (a2, b2) = AXES
    A, b = A.numpy(), b.numpy()

    def pts(th1, th2):
        p1 = np.stack([a1 * np.cos(th1), b1 * np.sin(th1)], -1)
        p2 = np.stack([a2 * np.cos(th2), b2 * np.sin(th2)], -1) @ A.T + b
        return p1, p2

    th = np.linspace(0, 2 * np.pi, 600, endpoint=False)
    p1, p2 = pts(th, th)
    dist = np.linalg.norm(p1[:, None] - p2[None], axis=-1)
    i, j = np.unravel_index(dist.argmin(), dist.shape)
    res = minimize(lambda z: np.sum(np.subtract(*pts(z[0], z[1])) ** 2), [th[i], th[j]], method="BFGS",
                   options={"gtol": 1e-14})
    return math.sqrt(res.fun)


def test_prioritized_closest_points_match_the_parametric_reference():
    s1, s2 = (_ellipse_field(*ab) for ab in AXES)
    A, b = _rot(POSES[0]), POSES[1]
    r = sdf.closest_points_prioritized(s1, s2, A, b, tol=1e-11)
    assert r.converged.all(), (r.reason, r.residual)
    assert r.f1.abs().max() < 1e-11 and r.f2.abs().max() < 1e-11
    for i in range(3):
        assert abs(r.distance[i].item() - _reference_distance(A[i], b[i])) < 1e-8
    # the segment is normal to both contours
    _, g1 = sdf.sdf_value_and_grad(s1, r.p1)
    _, g2 = sdf.sdf_value_and_grad(s2, r.p2)
    seg = r.p2_in_1 - r.p1
    n2 = (A @ g2.unsqueeze(-1)).squeeze(-1)
    cross = lambda u, v: u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]  # noqa: E731
    assert cross(seg, g1).abs().max() < 1e-8 and cross(seg, n2).abs().max() < 1e-8
    torch.testing.assert_close(r.p2_in_1, (A @ r.p2.unsqueeze(-1)).squeeze(-1) + b)
    # batched == per-sample, and a NaN pose does not touch the others
    for i in range(3):
        ri = sdf.closest_points_prioritized(s1, s2, A[i], b[i], tol=1e-11)
        torch.testing.assert_close(ri.p1, r.p1[i], atol=1e-12, rtol=0)
    bn = b.clone()
    bn[1, 0] = math.nan
    rn = sdf.closest_points_prioritized(s1, s2, A, bn, tol=1e-11)
    assert rn.reason.tolist()[1] == int(Reason.NONFINITE_INPUT) and rn.converged[[0, 2]].all()
    torch.testing.assert_close(rn.distance[[0, 2]], r.distance[[0, 2]], atol=1e-12, rtol=0)


def test_plain_closest_points_is_the_minimum_of_eq40():
    s1, s2 = (_ellipse_field(*ab) for ab in AXES)
    A, b = _rot(POSES[0]), POSES[1]
    beta = 0.1
    r = sdf.closest_points(s1, s2, A, b, weight=beta, tol=1e-8, max_iter=300)
    assert r.converged.all(), r.reason
    t = torch.cat([r.p1, r.p2], -1).requires_grad_(True)

    def cost(tt):
        f1 = sdf.sdf_value(s1, tt[..., :2])
        f2 = sdf.sdf_value(s2, tt[..., 2:])
        res = (A @ tt[..., 2:].unsqueeze(-1)).squeeze(-1) + b - tt[..., :2]
        return f1 ** 2 + f2 ** 2 + beta * (res ** 2).sum(-1)

    g = torch.autograd.grad(cost(t).sum(), t)[0]
    assert torch.linalg.vector_norm(g, dim=-1).max() < 1e-7
    # the same local minimum as scipy's BFGS on the cost of Eq. (40), started from the same point
    for i in range(3):
        def c_np(z, i=i):
            return float(cost(torch.as_tensor(z, dtype=D).expand(3, 4))[i])
        p1_0 = 0.5 * (b[i]) * 1.0
        p2_0 = (A[i].T @ (p1_0 - b[i]))
        z = minimize(c_np, torch.cat([p1_0, p2_0]).numpy(), method="BFGS", options={"gtol": 1e-11}).x
        np.testing.assert_allclose(t[i].detach().numpy(), z, atol=1e-5)
    # penalty formulation: the points stop off the contours, prioritized ones do not
    rp = sdf.closest_points_prioritized(s1, s2, A, b)
    assert (r.f1.abs() > 1e-3).all() and (r.distance < rp.distance).all()


def test_closest_points_bad_input():
    s1 = _ellipse_field(*AXES[0])
    with pytest.raises(ValueError, match="'A'"):
        sdf.closest_points_prioritized(s1, s1, torch.eye(3, dtype=D), torch.zeros(2, dtype=D))
    with pytest.raises(TypeError, match="'sdf2'"):
        sdf.closest_points(s1, "circle", torch.eye(2, dtype=D), torch.zeros(2, dtype=D))
    with pytest.raises(ValueError, match="'alpha2'"):
        sdf.closest_points_prioritized(s1, s1, torch.eye(2, dtype=D), torch.ones(2, dtype=D), alpha2=0.0)
    with pytest.raises(ValueError, match="'weight'"):
        sdf.closest_points(s1, s1, torch.eye(2, dtype=D), torch.ones(2, dtype=D), weight=0.0)


def test_fit_sdf_in_3d_sphere():
    """A 3-D input (Ψ = φ ⊗ φ ⊗ φ, Eq. 33): the sphere's signed distance from surface points only."""
    g = torch.Generator().manual_seed(0)
    v = torch.randn(150, 3, dtype=D, generator=g)
    v = 0.5 * v / torch.linalg.vector_norm(v, dim=-1, keepdim=True)
    r = sdf.fit_sdf(v, [-1.0] * 3, [1.0] * 3, basis=sdf.default_sdf_basis(3), eikonal_grid=9, tol=1e-7)
    assert bool(r.converged) and r.sdf.w.shape == (8 ** 3,)  # 3 C¹ cubic segments: 4 + 2·2 per input
    q = 0.4 * torch.randn(40, 3, dtype=D, generator=g)
    d = torch.linalg.vector_norm(q, dim=-1) - 0.5
    assert (sdf.sdf_value(r.sdf, q) - d).abs().max() < 0.06


def test_sdf_constructor_checks():
    w = torch.zeros(16, dtype=D)
    lo, hi = torch.tensor(LO, dtype=D), torch.tensor(HI, dtype=D)
    with pytest.raises(TypeError, match="'lower'"):
        sdf.SDF(w, LO, hi, BERN3)
    with pytest.raises(TypeError, match="'lower'"):
        sdf.SDF(w, lo.float(), hi, BERN3)
    with pytest.raises(TypeError, match="'basis'"):
        sdf.SDF(w, lo, hi, [BERN3])
    with pytest.raises(ValueError, match="'p'"):
        s4 = sdf.SDF(w, lo, hi, functools.partial(basis.bernstein_deriv, K=4))
        sdf.sdf_value(s4, torch.zeros(3, dtype=D))


def _unit_circle_field():
    """The circle of radius 0.5 (fitted from contour points with the eikonal term)."""
    return sdf.fit_sdf(_circle([0.0, 0.0], 0.5, M=40), LO, HI).sdf


def test_prioritized_closest_points_reject_a_saddle_and_keep_the_minimum():
    """Two copies of one circle, 2 apart: antipodal far-side points are a stationary pair (the segment is
    normal to both contours) at distance 2, but a saddle of the distance; the minimum is about 1."""
    s = _unit_circle_field()
    A, b = torch.eye(2, dtype=D), torch.tensor([2.0, 0.0], dtype=D)
    x = torch.linspace(-0.9, -0.1, 2001, dtype=D)  # the contour's left crossing of the x axis, by bisection
    v = sdf.sdf_value(s, torch.stack([x, torch.zeros_like(x)], -1))
    xl = x[torch.argmin(v.abs())].item()
    lo, hi = xl - 1e-3, xl + 1e-3
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        fm = sdf.sdf_value(s, torch.tensor([mid, 0.0], dtype=D))
        lo, hi = (mid, hi) if fm > 0 else (lo, mid)
    xl = 0.5 * (lo + hi)
    pl = torch.tensor([xl, 0.0], dtype=D)
    starts1 = torch.stack([pl, pl, pl.neg()])
    starts2 = torch.stack([pl, pl.neg(), pl])  # saddle; maximum (far sides facing away); the minimum side
    r = sdf.closest_points_prioritized(s, s, A, b, p1_0=starts1, p2_0=starts2, tol=1e-9)
    # every element is a stationary pair (first order) ...
    assert (r.residual <= 1e-9).all(), r.residual
    # ... but only the last one is a minimum
    assert r.reason.tolist()[:2] == [int(Reason.NOT_A_MINIMUM)] * 2
    assert not r.converged[:2].any()
    # the minimum: found from the default start and from the near-side start, certified
    r0 = sdf.closest_points_prioritized(s, s, A, b, tol=1e-9)
    assert r0.converged.item() and r.converged[2].item()
    assert abs(r0.distance.item() - (2 + 2 * xl)) < 1e-8 and r0.distance.item() < r.distance[0].item()
    # independent check of the second-order claim: along the contours (angles a1, a2 of the points around
    # their circles, the contour being nearly circular) the distance has a negative curvature at the saddle
    rad = -xl

    def dist(a1, a2):
        p1 = rad * torch.stack([torch.cos(math.pi + a1), torch.sin(math.pi + a1)])
        p2 = b + rad * torch.stack([torch.cos(math.pi + a2), torch.sin(math.pi + a2)])
        return (p2 - p1).norm()

    h = 1e-3
    z = torch.zeros((), dtype=D)
    curv = (dist(z + h, z) - 2 * dist(z, z) + dist(z - h, z)) / h ** 2
    assert curv < 0


def test_fit_sdf_rejects_no_boundary_points_and_float32_converges():
    with pytest.raises(ValueError, match="'boundary'"):
        sdf.fit_sdf(torch.zeros(0, 2, dtype=D), LO, HI)
    c = _circle([0.0, 0.0], 0.5, M=40)
    r64 = sdf.fit_sdf(c, LO, HI)
    r32 = sdf.fit_sdf(c.float(), LO, HI)
    assert r64.converged.item() and r32.converged.item(), (r64.reason, r32.reason)
    assert r32.sdf.w.dtype == torch.float32
    assert abs(r32.cost.item() - r64.cost.item()) < 1e-4 * max(1.0, r64.cost.item())
