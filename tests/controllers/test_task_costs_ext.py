"""controllers.task_costs_ext: the decoupling cost (§9.10) — residuals, Gauss-Newton derivatives against
torch.func and finite differences, batching, weights, float32, errors, and a CostSum inside iLQR; the
curvature map (§9.11) — values against Eq. 112 written out, the Jacobian of Eq. 116 against torch.func and
finite differences, gradcheck, the safe value at rest, a circle's curvature, other index layouts, float32,
errors; the object-affordance pieces (§9.14) — the object frame against homogeneous transforms, the coupling
precision against its sum form, and its equivalence with the separable auxiliary-state form; the spacetime
pieces (§9.13) — the phase-augmented dynamics against the seed's linearization, torch.func and finite
differences, and the scaled-time effort's exact gradient and Gauss-Newton Hessian."""

from __future__ import annotations

import math

import pytest
import torch
from torch.func import jacrev, vmap

from controllers.dynamics import LinearDynamics
from controllers.ilqr import ILQROptions, ILQRProblem, ilqr
from controllers.task_costs import on_joints, planar_ee, residual_cost, state, track
from controllers.task_costs_ext import (
    ControlProductCost,
    CostSum,
    PhaseEffortCost,
    SpacetimeDynamics,
    coupled_cost,
    coupling_precision,
    curvature,
    minus_state,
    object_frame,
)

D = torch.float64


def _xu(bs=(3,), T=5, n=2, m=3, seed=0, dtype=D):
    g = torch.Generator().manual_seed(seed)
    return (torch.randn(*bs, T + 1, n, generator=g, dtype=dtype),
            torch.randn(*bs, T, m, generator=g, dtype=dtype))


# ------------------------------------------------------------------------------------------------ §9.10


def test_control_product_residual_jacobian_and_value():
    x, u = _xu()
    c = ControlProductCost([(0, 1), (2, 0)], weight=2.5)
    f = c.residual(u)
    torch.testing.assert_close(f, torch.stack([u[..., 0] * u[..., 1], u[..., 2] * u[..., 0]], -1))
    J = c.jacobian(u)
    Jf = vmap(jacrev(c.residual))(u.reshape(-1, 3)).reshape(3, 5, 2, 3)
    torch.testing.assert_close(J, Jf, atol=1e-14, rtol=0)
    # the seed's J_t = [u_2, u_1] for the pair (1, 2)
    torch.testing.assert_close(J[..., 0, :2], torch.stack([u[..., 1], u[..., 0]], -1))
    ref = 2.5 * ((u[..., 0] * u[..., 1]) ** 2 + (u[..., 2] * u[..., 0]) ** 2).sum(-1)
    torch.testing.assert_close(c.evaluate(x, u), ref, atol=1e-13, rtol=1e-13)


def test_control_product_gauss_newton_derivatives():
    x, u = _xu(seed=1)
    w = torch.tensor([1.0, 3.0], dtype=D)  # per pair
    c = ControlProductCost([(0, 1), (1, 2)], weight=w)
    gx, gu, Hxx, Hux, Huu = c.derivatives(x, u)
    assert Hux is None and gx.shape == x.shape and Hxx.shape == (*x.shape, 2)
    assert not gx.any() and not Hxx.any()
    # the gradient is exact: against autograd and finite differences of evaluate
    ug = u.clone().requires_grad_(True)
    (gu_a,) = torch.autograd.grad(c.evaluate(x, ug).sum(), ug)
    torch.testing.assert_close(gu, gu_a, atol=1e-12, rtol=1e-12)
    h, k = 1e-6, (1, 2, 1)
    e = torch.zeros_like(u)
    e[k] = h
    fd = (c.evaluate(x, u + e) - c.evaluate(x, u - e))[k[0]] / (2 * h)
    assert abs(float(fd) - float(gu[k])) < 1e-7
    # H_uu = 2 Σ w Jᵀ J, positive semi-definite
    J = c.jacobian(u)
    torch.testing.assert_close(Huu, 2 * torch.einsum("k,...ki,...kj->...ij", w, J, J), atol=1e-13, rtol=0)
    assert torch.linalg.eigvalsh(Huu).min() > -1e-12


def test_control_product_batched_equals_loop_and_broadcast_weight():
    x, u = _xu(bs=(2, 3), seed=2)
    w = torch.rand(2, 3, 1, 1, generator=torch.Generator().manual_seed(3), dtype=D)  # per element
    c = ControlProductCost([(0, 2)], weight=w)
    v, d = c.evaluate(x, u), c.derivatives(x, u)
    for i in range(2):
        for j in range(3):
            cij = ControlProductCost([(0, 2)], weight=float(w[i, j]))
            torch.testing.assert_close(v[i, j], cij.evaluate(x[i, j], u[i, j]), atol=1e-14, rtol=1e-14)
            for a, b in zip(d, cij.derivatives(x[i, j], u[i, j])):
                if a is not None:
                    torch.testing.assert_close(a[i, j], b, atol=1e-14, rtol=1e-14)
    # a NaN control in one element leaves the others untouched
    u2 = u.clone()
    u2[0, 0, 1, 0] = float("nan")
    v2 = c.evaluate(x, u2)
    assert v2[0, 0].isnan() and torch.equal(v2.flatten()[1:], v.flatten()[1:])


def test_control_product_float32_and_errors():
    x, u = _xu(seed=4, dtype=torch.float32)
    c = ControlProductCost([(0, 1)], weight=1.0)
    assert c.evaluate(x, u).dtype == torch.float32 and c.derivatives(x, u)[4].dtype == torch.float32
    torch.testing.assert_close(c.evaluate(x, u).double(), c.evaluate(x.double(), u.double()), rtol=1e-5,
                               atol=1e-5)
    with pytest.raises(ValueError, match="distinct"):
        ControlProductCost([(1, 1)])
    with pytest.raises(ValueError, match="at least one"):
        ControlProductCost([])
    with pytest.raises(TypeError, match="pairs"):
        ControlProductCost([1, 2])
    with pytest.raises(ValueError, match="non-negative"):
        ControlProductCost([(0, 1)], weight=-1.0)
    with pytest.raises(ValueError, match="out of range"):
        ControlProductCost([(0, 5)]).evaluate(x, u)
    with pytest.raises(TypeError, match="dtype"):
        ControlProductCost([(0, 1)], weight=torch.tensor(1.0, dtype=D)).evaluate(x, u)
    with pytest.raises(TypeError, match="evaluate"):
        CostSum([c, 3])
    with pytest.raises(ValueError, match="at least one"):
        CostSum([])


def test_cost_sum_derivatives_are_the_sums_and_ilqr_decouples():
    """CostSum of a ResidualCost and the product cost: value and derivatives add; iLQR on it (a 2-D reach)
    reaches the target with products far smaller than without the term, and the result is a certified
    stationary point of the summed cost (gradient of the total cost through the dynamics ~ 0)."""
    kw = dict(dtype=D)
    T, dt = 20, 0.1
    eye = torch.eye(2, **kw)
    Q = torch.zeros(T + 1, 2, 2, **kw)
    Q[-1] = 1e3 * eye
    mu = torch.tensor([[1.5, 0.7], [-0.6, 1.2]], **kw)
    base = residual_cost([(track(state(2), mu[:, None]), Q)], 1e-2 * eye)
    prod = ControlProductCost([(0, 1)], 1e3)
    total = CostSum([base, prod])
    x, u = _xu(bs=(2,), T=T, n=2, m=2, seed=5)
    torch.testing.assert_close(total.evaluate(x, u), base.evaluate(x, u) + prod.evaluate(x, u))
    for a, b, c in zip(total.derivatives(x, u), base.derivatives(x, u), prod.derivatives(x, u)):
        if a is not None:
            torch.testing.assert_close(a, b + c)
    sol = ilqr(ILQRProblem(LinearDynamics(eye, dt * eye), total, torch.zeros(2, 2, **kw), T), grad="none",
               options=ILQROptions(max_iter=60))
    assert bool(sol.status.converged.all())
    assert (sol.x[:, -1] - mu).norm(dim=-1).max() < 1e-2
    ratio = (sol.u[..., 0] * sol.u[..., 1]).abs().amax(-1) / (sol.u.abs().amax(-2).prod(-1))
    assert ratio.max() < 1e-2
    # independent check of stationarity: the gradient of the rolled-out total cost in u
    u_ = sol.u.clone().requires_grad_(True)
    xs = [torch.zeros(2, 2, **kw)]
    for t in range(T):
        xs.append(xs[-1] + dt * u_[:, t])
    (g,) = torch.autograd.grad(total.evaluate(torch.stack(xs, 1), u_).sum(), u_)
    assert g.abs().max() < 1e-4 * (1 + float(sol.cost.max()))


# ------------------------------------------------------------------------------------------------ §9.11


def _kappa_ref(x):
    v1, v2, a1, a2 = x[..., 2], x[..., 3], x[..., 4], x[..., 5]
    return (v1 * a2 - v2 * a1) / (v1**2 + v2**2) ** 1.5


def test_curvature_values_jacobian_and_gradcheck():
    g = torch.Generator().manual_seed(6)
    x = torch.randn(2, 7, 6, generator=g, dtype=D)
    k = curvature()
    f, J = k(x)
    assert f.shape == (2, 7, 1) and J.shape == (2, 7, 1, 6)
    torch.testing.assert_close(f[..., 0], _kappa_ref(x), atol=1e-12, rtol=1e-12)
    Jf = vmap(jacrev(lambda v: k.f(v[None])[0]))(x.reshape(-1, 6)).reshape(2, 7, 1, 6)
    torch.testing.assert_close(J, Jf, atol=1e-10, rtol=1e-10)
    h = 1e-6
    for j in range(6):
        e = torch.zeros(6, dtype=D)
        e[j] = h
        torch.testing.assert_close(J[..., 0, j], (_kappa_ref(x + e) - _kappa_ref(x - e)) / (2 * h),
                                   atol=1e-6, rtol=1e-6)
    xg = x[:, :2].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda v: k(v), (xg,))
    # batched == loop
    for b in range(2):
        fb, Jb = k(x[b])
        torch.testing.assert_close(fb, f[b], atol=1e-15, rtol=1e-14)
        torch.testing.assert_close(Jb, J[b], atol=1e-15, rtol=1e-14)


def test_curvature_of_a_circle_sign_and_layout():
    """On a circle of radius r traversed at speed s, κ = ±1/r whatever s (left turns positive); another
    state layout through the index arguments gives the same numbers."""
    r, s, th = 2.0, 3.0, torch.linspace(0, 2 * math.pi, 9, dtype=D)
    vel = s * torch.stack([-th.sin(), th.cos()], -1)
    acc = -(s * s / r) * torch.stack([th.cos(), th.sin()], -1)
    x = torch.cat([r * torch.stack([th.cos(), th.sin()], -1), vel, acc], -1)
    torch.testing.assert_close(curvature().f(x)[..., 0], torch.full_like(th, 1 / r), atol=1e-13, rtol=0)
    xr = torch.cat([x[..., :2], -vel, acc], -1)  # reversed direction: a right turn
    torch.testing.assert_close(curvature().f(xr)[..., 0], torch.full_like(th, -1 / r), atol=1e-13, rtol=0)
    # layout [ẍ, x, ẋ] with a padding entry: n = 7
    y = torch.cat([acc, x[..., :2], vel, torch.zeros_like(th)[:, None]], -1)
    k2 = curvature(7, velocity=(4, 5), acceleration=(0, 1))
    torch.testing.assert_close(k2.f(y), curvature().f(x), atol=1e-14, rtol=0)
    torch.testing.assert_close(k2.J(y)[..., [2, 3, 4, 5, 0, 1]], curvature().J(x), atol=1e-14, rtol=0)


def test_curvature_at_rest_is_zero_with_finite_gradients_and_float32():
    x = torch.zeros(3, 6, dtype=D)
    x[1, 2:] = torch.tensor([1.0, 0.0, 0.0, 2.0], dtype=D)  # moving: κ = 2
    x[2, 4:] = torch.tensor([1.0, 1.0], dtype=D)  # at rest but accelerating: undefined -> 0
    xg = x.clone().requires_grad_(True)
    f = curvature().f(xg)
    assert torch.equal(f[:, 0].detach(), torch.tensor([0.0, 2.0, 0.0], dtype=D))
    (g,) = torch.autograd.grad(f.sum(), xg)
    assert torch.isfinite(g).all()
    assert not curvature().J(x)[[0, 2]].any()
    f32 = curvature().f(x.float())
    assert f32.dtype == torch.float32 and torch.equal(f32.double(), f.detach())
    # a NaN element stays in its element
    xn = x.clone()
    xn[0, 3] = float("nan")
    fn = curvature().f(xn)
    assert fn[0].isnan().all() and torch.equal(fn[1:], f[1:].detach())


def test_curvature_errors():
    with pytest.raises(ValueError, match="'n'"):
        curvature(3)
    with pytest.raises(ValueError, match="'velocity'"):
        curvature(6, velocity=(2, 9))
    with pytest.raises(ValueError, match="distinct"):
        curvature(6, velocity=(2, 3), acceleration=(3, 4))
    with pytest.raises(ValueError, match="end in 6"):
        curvature().f(torch.zeros(2, 5, dtype=D))
    with pytest.raises(TypeError, match="floating"):
        curvature().f(torch.zeros(2, 6, dtype=torch.int64))


# ------------------------------------------------------------------------------------------------ §9.14


def test_object_frame_values_jacobian_and_batching():
    g = torch.Generator().manual_seed(7)
    ee = planar_ee((2.0, 2.0, 1.0))
    q = torch.randn(2, 4, 3, generator=g, dtype=D)
    mu = torch.randn(2, 4, 2, generator=g, dtype=D)
    th = torch.randn(2, 4, generator=g, dtype=D)
    m = object_frame(ee, mu, th)
    f, J = m(q)
    # the pose in the object frame by homogeneous transforms (an independent formula)
    p = ee.f(q)
    c, s = th.cos(), th.sin()
    H = torch.zeros(2, 4, 3, 3, dtype=D)
    H[..., 0, 0], H[..., 0, 1], H[..., 1, 0], H[..., 1, 1] = c, -s, s, c
    H[..., :2, 2], H[..., 2, 2] = mu, 1.0
    local = torch.linalg.solve(H, torch.cat([p[..., :2], torch.ones(2, 4, 1, dtype=D)], -1).unsqueeze(-1))
    torch.testing.assert_close(f[..., :2], local[..., :2, 0], atol=1e-12, rtol=1e-12)
    torch.testing.assert_close(f[..., 2], p[..., 2] - th, atol=1e-14, rtol=0)
    Jf = vmap(jacrev(lambda v, a, b: object_frame(ee, a, b).f(v)))(q.reshape(-1, 3), mu.reshape(-1, 2),
                                                                   th.reshape(-1))
    torch.testing.assert_close(J, Jf.reshape(2, 4, 3, 3), atol=1e-12, rtol=1e-12)
    for b in range(2):
        fb, Jb = object_frame(ee, mu[b], th[b])(q[b])
        torch.testing.assert_close(fb, f[b], atol=1e-15, rtol=1e-14)
        torch.testing.assert_close(Jb, J[b], atol=1e-15, rtol=1e-14)
    # a fixed object pose (2,) and () broadcasts over the trajectory; float32 follows
    f1 = object_frame(ee, mu[0, 0], th[0, 0]).f(q.float())
    assert f1.dtype == torch.float32 and f1.shape == (2, 4, 3)
    mg, tg = mu[:1, :2].clone().requires_grad_(True), th[:1, :2].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a, b: object_frame(ee, a, b)(q[:1, :2]), (mg, tg))
    with pytest.raises(TypeError, match="p = 3"):
        object_frame(planar_ee((1.0, 1.0), orientation=False), mu, th)
    with pytest.raises(ValueError, match="'position'"):
        m2 = object_frame(ee, torch.zeros(3, dtype=D), 0.0)
        m2.f(q)


def test_minus_state_and_coupling_precision_equivalence():
    """``coupling_precision`` is the seed's off-diagonal precision: ``fᵀQf = Σ (f_a - f_b)ᵀ W (f_a - f_b)``;
    the separable form with an auxiliary ``z`` and precision ``2W`` has the same minimum over ``z``, at
    ``z = (f_a + f_b)/2`` (checked against a dense least-squares solve over ``z``)."""
    g = torch.Generator().manual_seed(8)
    T, p = 6, 3
    Wf = torch.randn(p, p, generator=g, dtype=D)
    W = Wf @ Wf.mT + 0.1 * torch.eye(p, dtype=D)
    Q = coupling_precision(T, p, [(2, 6), (0, 1)], W)
    assert Q.shape == (21, 21) and torch.equal(Q, Q.mT) and torch.linalg.eigvalsh(Q).min() > -1e-12
    f = torch.randn(4, T + 1, p, generator=g, dtype=D)
    ref = sum(((f[:, a] - f[:, b]) @ W * (f[:, a] - f[:, b])).sum(-1) for a, b in [(2, 6), (0, 1)])
    torch.testing.assert_close(coupled_cost(f, Q), ref, atol=1e-12, rtol=1e-12)
    assert coupled_cost(f[:, :1].expand(4, T + 1, p), Q).abs().max() < 1e-12  # equal residuals cost nothing
    # the separable form: min_z (a - z)ᵀ2W(a - z) + (b - z)ᵀ2W(b - z), by a dense weighted least squares
    a, b = f[:, 2], f[:, 6]
    L = torch.linalg.cholesky(2 * W)
    Aw = torch.cat([L.mT, L.mT], 0)  # rows: L ᵀ z  ≈ L ᵀ a,  L ᵀ z ≈ L ᵀ b
    rhs = torch.cat([a @ L, b @ L], -1)
    z = torch.linalg.lstsq(Aw.expand(4, 6, 3), rhs.unsqueeze(-1)).solution[..., 0]
    torch.testing.assert_close(z, (a + b) / 2, atol=1e-12, rtol=1e-12)
    sep = (((a - z) @ (2 * W)) * (a - z)).sum(-1) + (((b - z) @ (2 * W)) * (b - z)).sum(-1)
    torch.testing.assert_close(sep, coupled_cost(f, coupling_precision(T, p, [(2, 6)], W)), atol=1e-11,
                               rtol=1e-11)
    # minus_state: g(x) - x[idx] with J = J_g - E
    x = torch.randn(2, 5, 6, generator=g, dtype=D)
    ms = minus_state(on_joints(planar_ee((1.0, 1.0, 0.5)), [0, 1, 2], 6), [3, 4, 5], 6)
    torch.testing.assert_close(ms.f(x), planar_ee((1.0, 1.0, 0.5)).f(x[..., :3]) - x[..., 3:])
    Jf = vmap(jacrev(lambda v: ms.f(v)))(x.reshape(-1, 6)).reshape(2, 5, 3, 6)
    torch.testing.assert_close(ms.J(x), Jf, atol=1e-13, rtol=0)
    with pytest.raises(ValueError, match="'index'"):
        minus_state(ms, [3, 4], 6)
    with pytest.raises(ValueError, match="in \\[0, 6\\]"):
        coupling_precision(6, 3, [(2, 7)], 1.0)
    with pytest.raises(ValueError, match="'weight'"):
        coupling_precision(6, 3, [(2, 5)], torch.eye(2, dtype=D))
    with pytest.raises(ValueError, match="distinct non-negative time steps"):
        coupling_precision(6, 3, [(2, 2)], 1.0)
    with pytest.raises(ValueError, match="positive ints"):
        coupling_precision(0, 3, [(0, 1)], 1.0)
    with pytest.raises(ValueError, match="'Q'"):
        coupled_cost(f, torch.eye(5, dtype=D))


# ------------------------------------------------------------------------------------------------ §9.13


def _double_integrator(dt=0.1, dtype=D):
    I, Z = torch.eye(2, dtype=dtype), torch.zeros(2, 2, dtype=dtype)
    A = torch.cat([torch.cat([I, dt * I], 1), torch.cat([Z, I], 1)], 0)
    return A, torch.cat([dt**2 / 2 * I, dt * I], 0)


def test_spacetime_dynamics_step_and_the_seeds_linearization():
    A, B = _double_integrator()
    sys_ = SpacetimeDynamics(A, B)
    assert (sys_.n, sys_.m) == (5, 3)
    g = torch.Generator().manual_seed(9)
    x, u = torch.randn(6, 5, generator=g, dtype=D), torch.randn(6, 3, generator=g, dtype=D)
    nxt = sys_.step(x, u)
    torch.testing.assert_close(nxt[:, :4], x[:, :4] @ A.mT + (u[:, :2] * u[:, 2:]) @ B.mT, atol=1e-15, rtol=0)
    torch.testing.assert_close(nxt[:, 4], x[:, 4] + u[:, 2], atol=1e-15, rtol=0)
    Aa, Ba = sys_.jacobian(x, u)
    # the seed's block form
    for i in range(6):
        torch.testing.assert_close(Aa[i], torch.block_diag(A, torch.ones(1, 1, dtype=D)), atol=0, rtol=0)
        ref = torch.zeros(5, 3, dtype=D)
        ref[:4, :2], ref[:4, 2], ref[4, 2] = B * u[i, 2], B @ u[i, :2], 1.0
        torch.testing.assert_close(Ba[i], ref, atol=1e-15, rtol=0)
    Af = vmap(jacrev(sys_.step, argnums=0))(x, u)
    Bf = vmap(jacrev(sys_.step, argnums=1))(x, u)
    torch.testing.assert_close(Aa, Af, atol=1e-14, rtol=0)
    torch.testing.assert_close(Ba, Bf, atol=1e-14, rtol=0)
    h = 1e-6
    for j in range(3):
        e = torch.zeros(3, dtype=D)
        e[j] = h
        fd = (sys_.step(x, u + e) - sys_.step(x, u - e)) / (2 * h)
        torch.testing.assert_close(Ba[..., j], fd, atol=1e-8, rtol=1e-8)
    # batched == loop, time-major batches, the NonlinearDynamics wrapper, float32
    x3, u3 = x.view(3, 2, 5), u.view(3, 2, 3)
    torch.testing.assert_close(sys_.step(x3, u3), nxt.view(3, 2, 5), atol=0, rtol=0)
    for i in range(6):
        torch.testing.assert_close(sys_.step(x[i], u[i]), nxt[i], atol=1e-15, rtol=0)
    Ad, Bd = sys_.dynamics().jacobian(x, u, 0)
    assert torch.equal(Ad, Aa) and torch.equal(Bd, Ba)
    s32 = SpacetimeDynamics(A.float(), B.float())
    assert s32.step(x.float(), u.float()).dtype == torch.float32
    torch.testing.assert_close(s32.step(x.float(), u.float()).double(), nxt, atol=1e-5, rtol=1e-5)


def test_spacetime_dynamics_errors():
    A, B = _double_integrator()
    with pytest.raises(ValueError, match="'A' must be"):
        SpacetimeDynamics(A[:3], B)
    with pytest.raises(TypeError, match="dtype"):
        SpacetimeDynamics(A, B.float())
    with pytest.raises(TypeError, match="tensors"):
        SpacetimeDynamics([[1.0]], B)
    s = SpacetimeDynamics(A, B)
    with pytest.raises(ValueError, match=r"x \(\*B, 5\)"):
        s.step(torch.zeros(2, 4, dtype=D), torch.zeros(2, 3, dtype=D))
    with pytest.raises(TypeError, match="dtype of A"):
        s.jacobian(torch.zeros(2, 5), torch.zeros(2, 3))


def test_phase_effort_cost_value_and_gauss_newton_derivatives():
    g = torch.Generator().manual_seed(10)
    x = torch.randn(3, 5, 3, generator=g, dtype=D)
    u = torch.randn(3, 4, 3, generator=g, dtype=D)
    u[..., 2] = u[..., 2].abs() + 0.1  # positive time scales
    r = torch.tensor([0.5, 1.0, 2.0], dtype=D)[:, None]  # per element
    c = PhaseEffortCost(r)
    ref = (r * (u[..., :2] ** 2).sum(-1) * u[..., 2]).sum(-1)
    torch.testing.assert_close(c.evaluate(x, u), ref, atol=1e-13, rtol=1e-13)
    gx, gu, Hxx, Hux, Huu = c.derivatives(x, u)
    assert Hux is None and not gx.any() and not Hxx.any()
    ug = u.clone().requires_grad_(True)
    (ga,) = torch.autograd.grad(c.evaluate(x, ug).sum(), ug)
    torch.testing.assert_close(gu, ga, atol=1e-13, rtol=1e-13)  # the gradient is exact
    # H = 2 JᵀJ of the residual f = √(r u^s) u^x, J by torch.func
    rr = r.expand(3, 4).reshape(-1)

    def res(v, rv):
        return torch.sqrt(rv * v[2]) * v[:2]

    J = vmap(jacrev(res))(u.reshape(-1, 3), rr).reshape(3, 4, 2, 3)
    torch.testing.assert_close(Huu, 2 * J.mT @ J, atol=1e-12, rtol=1e-12)
    assert torch.linalg.eigvalsh(Huu).min() > -1e-12
    for b in range(3):
        cb = PhaseEffortCost(float(r[b]))
        torch.testing.assert_close(cb.derivatives(x[b], u[b])[4], Huu[b], atol=1e-14, rtol=1e-14)
    assert PhaseEffortCost(1.0).evaluate(x.float(), u.float()).dtype == torch.float32
    with pytest.raises(ValueError, match="positive"):
        PhaseEffortCost(0.0)
    with pytest.raises(ValueError, match="m\\+1"):
        PhaseEffortCost(1.0).evaluate(x, u[..., :1])
    with pytest.raises(TypeError, match="dtype"):
        PhaseEffortCost(torch.tensor(1.0)).evaluate(x, u)
