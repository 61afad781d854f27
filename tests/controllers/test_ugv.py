"""The UGV on a curved surface (seed 003 §VII-B, Eq. 35-40): analytic system-specific Jacobians against
torch.func and finite differences, the discrete model against the RK4 simulator of Eq. 35 (order dt² per
step, exact cases on planes), the reference generation (constant 3-D speed, consistency with the model),
the quadratic patches (exact recovery, fit error on the synthetic road) and bad inputs."""

from __future__ import annotations

import math

import pytest
import torch
from torch.func import jacrev

from controllers.systems.ugv import (
    UGV,
    FigureEightPath,
    PatchedSurface,
    SyntheticRoad,
    UGVSimulator,
    ugv_reference,
    ugv_scenario,
)
from torchlie.manifolds import ProductState, quadratic_surface

D64 = torch.float64


@pytest.fixture(scope="module")
def scenario():
    return ugv_scenario(seed=0)


@pytest.fixture(scope="module")
def exact_reference(scenario):
    return ugv_reference(scenario.road)


def _states_near_path(model: UGV, ref, n: int, seed: int, offset: float = 0.3):
    """Random states on the model surface within ``offset`` m of reference points, random headings."""
    gen = torch.Generator().manual_seed(seed)
    k = torch.randint(0, ref.states.batch_shape[0], (n,), generator=gen)
    xy = ref.states.p[k, :2] + offset * (2 * torch.rand(n, 2, generator=gen, dtype=D64) - 1)
    theta = math.pi * (2 * torch.rand(n, generator=gen, dtype=D64) - 1)
    c, s = torch.cos(theta), torch.sin(theta)
    R = torch.stack((c, -s, s, c), -1).reshape(n, 2, 2)
    p = torch.cat((xy, torch.zeros(n, 1, dtype=D64)), -1)
    x = model.manifold.state(p=p, R=R, project=True)  # lifts z onto the model surface
    lo, hi = model.u_lower, model.u_upper
    u = lo + (hi - lo) * torch.rand(n, 2, generator=gen, dtype=D64)
    return x, u


def _rot(theta: torch.Tensor) -> torch.Tensor:
    c, s = torch.cos(theta), torch.sin(theta)
    return torch.stack((c, -s, s, c), -1).unflatten(-1, (2, 2))


def _jacrev_parts(model: UGV, x, u):
    n = x.batch_shape[0]

    def fx(d):
        return model.f(model.manifold.boxplus(x, d, check=False), u, check=False).sum(0)

    def fu(d):
        return model.f(x, u + d, check=False).sum(0)

    Jx = jacrev(fx)(torch.zeros(n, 3, dtype=D64)).movedim(0, -2)
    Ju = jacrev(fu)(torch.zeros(n, 2, dtype=D64)).movedim(0, -2)
    return Jx, Ju


# ------------------------------------------------------------------------------------------------
# Jacobians (Eq. 38-39)
# ------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("which", ["exact", "patched"])
def test_f_jacobians_match_jacrev(scenario, which):
    model = scenario.exact_model if which == "exact" else scenario.model
    x, u = _states_near_path(model, scenario.reference, 64, seed=1)
    A, B = model.f_jacobians(x, u)
    assert A.shape == (64, 3, 3) and B.shape == (64, 3, 2) and A.dtype == D64
    Jx, Ju = _jacrev_parts(model, x, u)
    torch.testing.assert_close(A, Jx, atol=1e-10, rtol=1e-10)
    torch.testing.assert_close(B, Ju, atol=1e-10, rtol=1e-10)
    # the curvature terms (∂α/∂δp, ∂β/∂δp) matter on this road: not a trivially zero block
    assert float(A[:, :, :2].abs().amax()) > 0.05


def test_f_jacobians_match_central_differences(scenario):
    model = scenario.exact_model
    x, u = _states_near_path(model, scenario.reference, 16, seed=2)
    A, B = model.f_jacobians(x, u)
    eps = 1e-6
    cols_x, cols_u = [], []
    for j in range(3):
        d = torch.zeros(16, 3, dtype=D64)
        d[:, j] = eps
        fp = model.f(model.manifold.boxplus(x, d), u)
        fm = model.f(model.manifold.boxplus(x, -d), u)
        cols_x.append((fp - fm) / (2 * eps))
    for j in range(2):
        d = torch.zeros(16, 2, dtype=D64)
        d[:, j] = eps
        cols_u.append((model.f(x, u + d) - model.f(x, u - d)) / (2 * eps))
    torch.testing.assert_close(A, torch.stack(cols_x, -1), atol=1e-8, rtol=0)
    torch.testing.assert_close(B, torch.stack(cols_u, -1), atol=1e-8, rtol=0)


def test_linearize_matches_jacobian_of_the_step(scenario):
    """What the error-state MPC builds, F_x = G_x + Δt G_f ∂f/∂δx and F_u = Δt G_f ∂f/∂δu (Eq. 21-22),
    is the Jacobian of (step(x ⊞ δx, u + δu) ⊟ step(x, u)) at 0."""
    model = scenario.model
    x, u = _states_near_path(model, scenario.reference, 32, seed=3)
    M = model.manifold
    A, B = model.f_jacobians(x, u)
    Fx, Fu = M.linearize(x, model.dt * model.f(x, u), model.dt, A, B)
    y = model.step(x, u)

    def ex(d):
        return M.boxminus(model.step(M.boxplus(x, d, check=False), u, check=False), y, check=False).sum(0)

    def eu(d):
        return M.boxminus(model.step(x, u + d, check=False), y, check=False).sum(0)

    torch.testing.assert_close(Fx, jacrev(ex)(torch.zeros(32, 3, dtype=D64)).movedim(0, -2),
                               atol=1e-10, rtol=1e-10)
    torch.testing.assert_close(Fu, jacrev(eu)(torch.zeros(32, 2, dtype=D64)).movedim(0, -2),
                               atol=1e-10, rtol=1e-10)


def test_f_values_and_body_axes(scenario):
    """f = [α R e₁ v; β ω] with x_b the unit tangent over R e₁ and z_b the normal: E₁₂ᵀx_b v = f[:2]."""
    model = scenario.exact_model
    x, u = _states_near_path(model, scenario.reference, 32, seed=4)
    f = model.f(x, u)
    xb, zb = model.body_axes(x)
    torch.testing.assert_close(f[:, :2], xb[:, :2] * u[:, :1], atol=1e-14, rtol=0)
    torch.testing.assert_close(f[:, 2], zb[:, 2] * u[:, 1], atol=1e-14, rtol=0)
    torch.testing.assert_close(xb.norm(dim=-1), torch.ones(32, dtype=D64))
    torch.testing.assert_close((xb * zb).sum(-1), torch.zeros(32, dtype=D64), atol=1e-14, rtol=0)
    # x_b's horizontal part is along R e₁ (no lateral slip)
    c = x.R[..., :, 0]
    torch.testing.assert_close(xb[:, 0] * c[:, 1] - xb[:, 1] * c[:, 0], torch.zeros(32, dtype=D64),
                               atol=1e-14, rtol=0)


def test_road_derivatives_are_exact():
    road = SyntheticRoad()
    gen = torch.Generator().manual_seed(5)
    xy = 30 * torch.rand(64, 2, generator=gen, dtype=D64) - 15
    g = torch.func.vmap(torch.func.grad(road.height))(xy)
    H = torch.func.vmap(torch.func.hessian(road.height))(xy)
    torch.testing.assert_close(road.gradient(xy), g, atol=1e-12, rtol=1e-12)
    torch.testing.assert_close(road.hessian(xy), H, atol=1e-12, rtol=1e-12)


def test_road_figures():
    """The synthetic road has the 'significant height variation' of the experiment."""
    road = SyntheticRoad()
    s = torch.linspace(-16, 16, 321, dtype=D64)
    xy = torch.stack(torch.meshgrid(s, s, indexing="ij"), -1).reshape(-1, 2)
    z = road.height(xy)
    slope = torch.rad2deg(torch.atan(road.gradient(xy).norm(dim=-1)))
    assert 1.5 < float(z.max() - z.min()) < 2.5
    assert 15 < float(slope.max()) < 22


# ------------------------------------------------------------------------------------------------
# the step and the simulator
# ------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("which", ["exact", "patched"])
def test_step_stays_on_surface(scenario, which):
    model = scenario.exact_model if which == "exact" else scenario.model
    x, u = _states_near_path(model, scenario.reference, 64, seed=6)
    y = x
    for _ in range(20):
        y = model.step(y, u)
    model.manifold.check(y)  # raises if off the surface / not a rotation
    torch.testing.assert_close(y.p[:, 2], model.surface.height(y.p[:, :2]), atol=1e-12, rtol=0)
    assert float((y.p[:, :2] - x.p[:, :2]).norm(dim=-1).max()) > 0.1  # it did move


def test_step_matches_simulator_to_second_order(scenario):
    """One model step (⊕ of Eq. 36) against Eq. 35 integrated exactly: the error is O(dt²)."""
    road = scenario.road
    base = scenario.exact_model
    x, u = _states_near_path(base, scenario.reference, 64, seed=7)
    errs = []
    for dt in (0.04, 0.02, 0.01):
        model = UGV(road.surface(), dt)
        sim = UGVSimulator(road, dt, substeps=20)
        e = model.manifold.boxminus(sim.step(x, u), model.step(x, u))
        errs.append(float(e.norm(dim=-1).max()))
    r1, r2 = errs[0] / errs[1], errs[1] / errs[2]
    assert 3.5 < r1 < 4.5 and 3.5 < r2 < 4.5, errs
    # 50 Hz, |v| ≤ 3.5 m/s, |ω| ≤ 3 rad/s: the heading held over the step costs ≤ v ω dt²/2 = 2.1 mm
    # laterally (measured 1.85 mm)
    assert errs[1] < 2.5e-3, errs


def test_simulator_exact_cases():
    """On a plane the model is exact for ω = 0; on level ground the simulator follows the exact circle;
    inputs are clamped; the speed scale scales the distance."""
    plane = quadratic_surface(torch.tensor([0.0, 0.0, 0.0, 0.2, -0.1, 0.5], dtype=D64), name="plane")
    model = UGV(plane, 0.02)
    gen = torch.Generator().manual_seed(8)
    n = 16
    xy = torch.randn(n, 2, generator=gen, dtype=D64)
    th = math.pi * (2 * torch.rand(n, generator=gen, dtype=D64) - 1)
    R = torch.stack((th.cos(), -th.sin(), th.sin(), th.cos()), -1).reshape(n, 2, 2)
    x = model.manifold.state(p=torch.cat((xy, torch.zeros(n, 1, dtype=D64)), -1), R=R, project=True)
    v = 3 * torch.rand(n, generator=gen, dtype=D64)
    u0 = torch.stack((v, torch.zeros_like(v)), -1)
    sim = UGVSimulator(plane, 0.02, substeps=4)
    e = model.manifold.boxminus(sim.step(x, u0), model.step(x, u0))
    assert float(e.abs().max()) < 1e-13

    level = quadratic_surface(torch.tensor([0.0, 0.0, 0.0, 0.0, 0.0, 0.3], dtype=D64), name="level")
    sim = UGVSimulator(level, 0.1, substeps=50)
    w = 2.5
    u = torch.stack((v, torch.full_like(v, w)), -1)
    y = sim.step(x, u)
    phi = w * 0.1
    local = torch.stack((torch.sin(torch.tensor(phi, dtype=D64)).expand(n),
                         (1 - torch.cos(torch.tensor(phi, dtype=D64))).expand(n)), -1) * (v / w).unsqueeze(-1)
    xy_exact = xy + (R @ local.unsqueeze(-1)).squeeze(-1)
    torch.testing.assert_close(y.p[:, :2], xy_exact, atol=1e-10, rtol=0)
    torch.testing.assert_close(y.p[:, 2], torch.full((n,), 0.3, dtype=D64), atol=0, rtol=0)
    torch.testing.assert_close(y.R, R @ _rot(torch.tensor(phi, dtype=D64)), atol=1e-14, rtol=0)

    # clamping: (10 m/s, −10 rad/s) acts as (3.5, −3)
    big = torch.tensor([10.0, -10.0], dtype=D64).expand(n, 2)
    lim = torch.tensor([3.5, -3.0], dtype=D64).expand(n, 2)
    ya, yb = sim.step(x, big), sim.step(x, lim)
    torch.testing.assert_close(ya.p, yb.p, atol=0, rtol=0)
    # speed scale: 0.9 of the commanded distance on level ground with ω = 0
    slow = UGVSimulator(level, 0.1, substeps=2, speed_scale=0.9)
    d = (slow.step(x, u0).p[:, :2] - xy).norm(dim=-1)
    torch.testing.assert_close(d, 0.9 * 0.1 * v, atol=1e-14, rtol=0)


def test_simulator_converges_in_substeps(scenario):
    x, u = _states_near_path(scenario.exact_model, scenario.reference, 32, seed=9)
    sims = [UGVSimulator(scenario.road, 0.02, substeps=k) for k in (1, 2, 64)]
    ys = [s.step(x, u) for s in sims]
    M = scenario.exact_model.manifold
    e1 = float(M.boxminus(ys[0], ys[2]).norm(dim=-1).max())
    e2 = float(M.boxminus(ys[1], ys[2]).norm(dim=-1).max())
    assert e2 < e1 / 10 and e1 < 1e-8  # RK4: ~2⁴ per halving; already tiny at one substep


# ------------------------------------------------------------------------------------------------
# reference (§VII-B-4)
# ------------------------------------------------------------------------------------------------

def test_reference_exact_road(scenario, exact_reference):
    ref, model = exact_reference, scenario.exact_model
    ds = 2.4 * 0.02
    T = ref.steps + ref.horizon + 1
    assert ref.horizon == 45 and ref.states.batch_shape == (T,) and ref.inputs.shape == (T - 1, 2)
    assert 50 < ref.length < 60 and abs(ref.length - ref.steps * ds) < 1e-9
    model.manifold.check(ref.states)
    dist = (ref.states.p[1:] - ref.states.p[:-1]).norm(dim=-1)
    assert float(((dist - ds) / ds).abs().max()) < 1e-6
    assert ref.spacing_error < 1e-6
    # R^d tangent to the 2-D path
    path = FigureEightPath()
    vel = path.velocity(ref.params)
    heading = ref.states.R[:, :, 0]
    torch.testing.assert_close(heading, vel / vel.norm(dim=-1, keepdim=True), atol=1e-12, rtol=0)
    assert bool((ref.inputs[:, 0] == 2.4).all())
    assert float(ref.inputs[:, 1].abs().max()) < 1.0  # the sharpest turn needs ≈0.9 rad/s
    assert bool((ref.params[1:] > ref.params[:-1]).all())
    # the model rolled one step from x^d_k under u^d_k lands on x^d_{k+1}: the heading exactly (the
    # yaw rate was divided by β), the position to O(κ (v dt)²)
    e = model.manifold.boxminus(model.step(ref.states[:-1], ref.inputs), ref.states[1:])
    assert float(e[:, 2].abs().max()) < 1e-12
    assert float(e[:, :2].norm(dim=-1).max()) < 1e-3


def test_reference_patched_surface(scenario):
    ref, model = scenario.reference, scenario.model
    ds = 2.4 * 0.02
    model.manifold.check(ref.states)  # the reference lies on the MPC's manifold
    assert ref.spacing_error < 1e-3  # patch boundaries can cost up to the height jump
    dist = (ref.states.p[1:] - ref.states.p[:-1]).norm(dim=-1)
    assert float(((dist - ds) / ds).abs().max()) < 1e-3
    e = model.manifold.boxminus(model.step(ref.states[:-1], ref.inputs), ref.states[1:])
    assert float(e[:, 2].abs().max()) < 1e-12
    assert float(e[:, :2].norm(dim=-1).max()) < 6e-3  # measured 3.0 mm (patch jumps shift the spacing)


def test_reference_padding_continues_the_path(exact_reference):
    """The padding continues along the closed path into its next lap (here: back over the start)."""
    ref = exact_reference
    assert float(ref.params[ref.steps]) <= 2 * math.pi + 1e-9 < float(ref.params[-1])
    k = ref.steps + 20
    p0 = FigureEightPath().position(ref.params[k] - 2 * math.pi)
    torch.testing.assert_close(ref.states.p[k, :2], p0, atol=1e-12, rtol=0)


# ------------------------------------------------------------------------------------------------
# patches (Eq. 40)
# ------------------------------------------------------------------------------------------------

def test_patch_fit_recovers_a_quadratic_exactly():
    gamma = torch.tensor([0.13, -0.07, 0.05, 0.4, -0.3, 1.2], dtype=D64)
    field = quadratic_surface(gamma)
    gen = torch.Generator().manual_seed(10)
    xy = 10 * torch.rand(3000, 2, generator=gen, dtype=D64) - 5
    pts = torch.cat((xy, field.height(xy).unsqueeze(-1)), -1)
    centres = 6 * torch.rand(7, 2, generator=gen, dtype=D64) - 3
    ps = PatchedSurface.fit(pts, centres, neighbours=40)
    g1, g2, g3, g4, g5, g6 = gamma
    cx, cy = centres.unbind(-1)
    expected = torch.stack((g1.expand(7), g2.expand(7), g3.expand(7), 2 * g1 * cx + g2 * cy + g4,
                            g2 * cx + 2 * g3 * cy + g5, field.height(centres)), -1)
    torch.testing.assert_close(ps.coefficients, expected, atol=1e-10, rtol=0)
    assert float(ps.rms.max()) < 1e-10
    q = 6 * torch.rand(200, 2, generator=gen, dtype=D64) - 3
    torch.testing.assert_close(ps.height(q), field.height(q), atol=1e-10, rtol=0)
    torch.testing.assert_close(ps.gradient(q), field.gradient(q), atol=1e-10, rtol=0)
    torch.testing.assert_close(ps.hessian(q), field.hessian(q), atol=1e-10, rtol=0)
    # nearest centre by brute force, and batched over leading dims
    d = (q.unsqueeze(-2) - centres).norm(dim=-1)
    assert torch.equal(ps.nearest(q), d.argmin(-1))
    assert torch.equal(ps.nearest(q.reshape(10, 20, 2)), d.argmin(-1).reshape(10, 20))


def test_patch_fit_on_the_road(scenario):
    """Measured (seed 0, 40 000 points, 2 cm noise, 64 neighbours, 224 patches every 0.25 m):
    height RMS 5.0 mm, max 14.9 mm, slope error max 0.028 along the reference."""
    sc = scenario
    assert sc.patches.num_patches > 200
    assert sc.height_rms < 0.01 and sc.height_max < 0.03 and sc.slope_max_error < 0.05
    assert 0.015 < float(sc.patches.rms.mean()) < 0.025  # residual ≈ the 2 cm noise: a good fit
    # the patched surface is much closer to the road than a flat or tilted-plane guess would be
    xy = sc.reference.states.p[:, :2]
    z = sc.road.height(xy)
    assert float((z - z.mean()).pow(2).mean().sqrt()) > 20 * sc.height_rms


# ------------------------------------------------------------------------------------------------
# batching, dtype, bad inputs
# ------------------------------------------------------------------------------------------------

def test_batching_and_dtype(scenario):
    model = scenario.model
    x, u = _states_near_path(model, scenario.reference, 12, seed=11)
    f = model.f(x, u)
    torch.testing.assert_close(model.f(x.reshape(3, 4), u.reshape(3, 4, 2)), f.reshape(3, 4, 3))
    A, B = model.f_jacobians(x, u)
    A2, B2 = model.f_jacobians(x.reshape(3, 4), u.reshape(3, 4, 2))
    torch.testing.assert_close(A2, A.reshape(3, 4, 3, 3))
    torch.testing.assert_close(B2, B.reshape(3, 4, 3, 2))
    # one input for the whole batch broadcasts
    torch.testing.assert_close(model.f(x, u[0]), model.f(x, u[0].expand(12, 2)))
    # float32 in, float32 out (surface tables follow the input dtype)
    x32, u32 = x.to(torch.float32), u.to(torch.float32)
    A32, B32 = model.f_jacobians(x32, u32)
    assert A32.dtype == torch.float32 and model.step(x32, u32).p.dtype == torch.float32
    torch.testing.assert_close(A32.double(), A, atol=1e-4, rtol=1e-4)


def test_bad_states_raise_or_stay_isolated(scenario):
    model = scenario.model
    x, u = _states_near_path(model, scenario.reference, 8, seed=12)
    p = x.p.clone()
    p[3, 2] += 0.1  # off the surface
    off = ProductState({"p": p, "R": x.R}, {"p": 1, "R": 2})
    with pytest.raises(ValueError, match=r"x\.p.*\(3,\)"):
        model.f(off, u)
    p = x.p.clone()
    p[5, 0] = float("nan")
    bad = ProductState({"p": p, "R": x.R}, {"p": 1, "R": 2})
    with pytest.raises(ValueError, match=r"x\.p.*\(5,\)"):
        model.step(bad, u)
    # unchecked: the NaN element stays in its own row
    ok = torch.arange(8) != 5
    for fun in (lambda s: model.f(s, u, check=False),
                lambda s: model.f_jacobians(s, u, check=False)[0]):
        good, poisoned = fun(x), fun(bad)
        assert not bool(torch.isfinite(poisoned[5]).all())
        torch.testing.assert_close(poisoned[ok], good[ok], atol=0, rtol=0)
    y = model.step(bad, u, check=False)
    torch.testing.assert_close(y.p[ok], model.step(x, u).p[ok], atol=0, rtol=0)

    sim = scenario.simulator
    with pytest.raises(ValueError, match=r"x\.p.*\(5,\)"):
        sim.step(bad, u)
    ys = sim.step(bad, u, check=False)
    torch.testing.assert_close(ys.p[ok], sim.step(x, u).p[ok], atol=0, rtol=0)
    R = x.R.clone()
    R[2] *= 1.1
    with pytest.raises(ValueError, match=r"x\.R"):
        sim.step(ProductState({"p": x.p, "R": R}, {"p": 1, "R": 2}), u)


def test_bad_arguments_are_named(scenario):
    model = scenario.model
    x, u = _states_near_path(model, scenario.reference, 4, seed=13)
    with pytest.raises(ValueError, match="'u'"):
        model.f(x, u[:, :1])
    with pytest.raises(ValueError, match="'x' .* 'u' .* broadcast"):
        model.f(x, u[:3])
    with pytest.raises(TypeError, match="'x' must be a ProductState"):
        model.f(x.p, u)
    with pytest.raises(TypeError, match="'surface'"):
        UGV("road")
    with pytest.raises(ValueError, match="'dt'"):
        UGV(scenario.road.surface(), dt=0.0)
    with pytest.raises(ValueError, match="'xy'"):
        scenario.road.height(torch.zeros(3, 4, dtype=D64))
    with pytest.raises(ValueError, match="'substeps'"):
        UGVSimulator(scenario.road, substeps=0)
    line = torch.linspace(0, 1, 50, dtype=D64)
    collinear = torch.stack((line, 2 * line, line), -1)
    with pytest.raises(ValueError, match="centre 0"):
        PatchedSurface.fit(collinear, torch.zeros(1, 2, dtype=D64), neighbours=10)
    with pytest.raises(ValueError, match="'neighbours'"):
        PatchedSurface.fit(collinear, torch.zeros(1, 2, dtype=D64), neighbours=100)
    with pytest.raises(TypeError, match="'surface'"):
        ugv_reference(object())
