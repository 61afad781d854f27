"""The planar n-link arm: physics against an independent Lagrangian (autograd of T - V built from forward
kinematics only), the one-link arm against the pendulum, analytic Jacobians against torch.func, gradients
with respect to parameters, batching and parameter broadcasting."""

from __future__ import annotations

import math

import pytest
import torch
from torch.func import jacrev, vmap

from controllers.dynamics import trajectory_jacobians
from controllers.systems import Pendulum, PlanarArm
from controllers.systems.arm import spd_solve

D64 = torch.float64


def _arm(k: int, **kw) -> PlanarArm:
    base = dict(links=k, lengths=tuple(0.3 + 0.15 * i for i in range(k)),
                masses=tuple(1.0 + 0.4 * i for i in range(k)),
                damping=tuple(0.1 + 0.05 * i for i in range(k)), gravity=9.81, dt=0.02)
    base.update(kw)
    return PlanarArm(**base)


def _rand(gen, nb, k):
    x = torch.cat([math.pi * (2 * torch.rand(nb, k, generator=gen, dtype=D64) - 1),
                   2 * torch.randn(nb, k, generator=gen, dtype=D64)], -1)
    return x, 3 * torch.randn(nb, k, generator=gen, dtype=D64)


def _lagrangian_acceleration(arm: PlanarArm, q, qd, tau, masses, damping, g):
    """q̈ of one state from L = T - V with T = ½ Σ m_i |ṗ_i|², ṗ_i = (∂p_i/∂q) q̇, V = g Σ m_i y_i, where
    the point positions p_i come from ``fk`` alone (Euler-Lagrange by reverse-mode torch.func)."""

    def L(q, qd):
        pts = lambda q_: arm.fk(q_)[1:]  # (k, 2) tip positions
        J = jacrev(pts)(q)  # (k, 2, k)
        v = J @ qd  # (k, 2)
        T = 0.5 * (masses * (v * v).sum(-1)).sum()
        V = g * (masses * pts(q)[:, 1]).sum()
        return T - V

    M = jacrev(jacrev(L, argnums=1), argnums=1)(q, qd)
    dL_dqd_dq = jacrev(jacrev(L, argnums=1), argnums=0)(q, qd)
    dL_dq = jacrev(L, argnums=0)(q, qd)
    rhs = tau - damping * qd - dL_dqd_dq @ qd + dL_dq
    return torch.linalg.solve(M, rhs), M


@pytest.mark.parametrize("k", [1, 2, 3, 4])
def test_acceleration_and_mass_matrix_match_an_independent_lagrangian(k):
    arm = _arm(k)
    gen = torch.Generator().manual_seed(k)
    x, u = _rand(gen, 6, k)
    masses = torch.tensor(arm.masses, dtype=D64)
    damping = torch.tensor(arm.damping, dtype=D64)
    acc = arm.acceleration(x, u)
    Ms = arm.mass_matrix(x[:, :k])
    for i in range(6):
        ref, M = _lagrangian_acceleration(arm, x[i, :k], x[i, k:], u[i], masses, damping, 9.81)
        torch.testing.assert_close(acc[i], ref, atol=1e-10, rtol=1e-10)
        torch.testing.assert_close(Ms[i], M, atol=1e-12, rtol=1e-12)


def test_energy_balance_and_conservation():
    arm = _arm(3)
    gen = torch.Generator().manual_seed(1)
    x, u = _rand(gen, 10, 3)
    x.requires_grad_(True)
    (gE,) = torch.autograd.grad(arm.energy(x).sum(), x)
    dE = (gE * arm.derivative(x, u)).sum(-1)  # dE/dt = τᵀq̇ - Σ b_j q̇_j²
    qd = x[:, 3:].detach()
    b = torch.tensor(arm.damping, dtype=D64)
    torch.testing.assert_close(dE, (u * qd).sum(-1) - (b * qd * qd).sum(-1), atol=1e-10, rtol=1e-10)
    # without damping or torque the continuous dynamics conserve the energy (RK4 on ``derivative``), and
    # the symplectic Euler step's energy error is first order in dt
    free = _arm(3, damping=0.0)
    z = torch.zeros(1, 3, dtype=D64)
    x0 = torch.tensor([[0.8, -0.5, 1.2, 1.0, -2.0, 0.5]], dtype=D64)
    E0 = free.energy(x0)
    dt, y = 0.002, x0
    for _ in range(250):
        k1 = free.derivative(y, z)
        k2 = free.derivative(y + dt / 2 * k1, z)
        k3 = free.derivative(y + dt / 2 * k2, z)
        k4 = free.derivative(y + dt * k3, z)
        y = y + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    assert float((free.energy(y) - E0).abs()) < 1e-7 * float(E0)
    drift = []
    for dt in (0.004, 0.001):
        arm, xs, err = _arm(3, damping=0.0, dt=dt), x0, 0.0
        for _ in range(int(round(0.5 / dt))):
            xs = arm.step(xs, z)
            err = max(err, float((arm.energy(xs) - E0).abs()))
        drift.append(err / float(E0))
    assert drift[0] < 0.2 and 3.0 < drift[0] / drift[1] < 5.0, drift


def test_one_link_is_the_pendulum():
    gen = torch.Generator().manual_seed(2)
    arm = PlanarArm(links=1, lengths=0.7, masses=1.3, damping=0.2, gravity=9.81, dt=0.05)
    pend = Pendulum(mass=1.3, length=0.7, damping=0.2, gravity=9.81, dt=0.05)
    x, u = _rand(gen, 20, 1)
    shift = torch.tensor([math.pi / 2, 0.0], dtype=D64)  # q = 0 along +x is θ = π/2 from hanging
    torch.testing.assert_close(arm.step(x, u), pend.step(x + shift, u) - shift, atol=1e-13, rtol=0)
    A, B = arm.jacobian(x, u)
    Ap, Bp = pend.jacobian(x + shift, u)
    torch.testing.assert_close(A, Ap, atol=1e-13, rtol=0)
    torch.testing.assert_close(B, Bp, atol=1e-13, rtol=0)
    torch.testing.assert_close(arm.energy(x) - arm.energy(x[:1] * 0), pend.energy(x + shift)
                               - pend.energy(shift[None]), atol=1e-12, rtol=0)


@pytest.mark.parametrize("k", [1, 2, 3, 5])
def test_analytic_jacobian_equals_torch_func(k):
    arm = _arm(k)
    gen = torch.Generator().manual_seed(10 + k)
    x, u = _rand(gen, 16, k)
    A, B = arm.jacobian(x, u)
    assert A.shape == (16, 2 * k, 2 * k) and B.shape == (16, 2 * k, k)
    Af = vmap(jacrev(arm.step, argnums=0))(x, u)
    Bf = vmap(jacrev(arm.step, argnums=1))(x, u)
    torch.testing.assert_close(A, Af, atol=1e-10, rtol=1e-10)
    torch.testing.assert_close(B, Bf, atol=1e-10, rtol=1e-10)
    h = 1e-6
    for i in range(2 * k):
        e = torch.zeros(2 * k, dtype=D64)
        e[i] = h
        fd = (arm.step(x + e, u) - arm.step(x - e, u)) / (2 * h)
        torch.testing.assert_close(A[..., i], fd, atol=1e-7, rtol=1e-6)


def test_parameter_gradients_gradcheck():
    gen = torch.Generator().manual_seed(3)
    x, u = _rand(gen, 3, 2)
    lengths = torch.tensor([[0.5, 0.4], [0.6, 0.3], [0.45, 0.45]], dtype=D64, requires_grad=True)
    masses = torch.tensor([1.0, 0.7], dtype=D64, requires_grad=True)
    damping = torch.tensor(0.1, dtype=D64, requires_grad=True)
    gravity = torch.tensor(9.81, dtype=D64, requires_grad=True)

    def f(lengths, masses, damping, gravity):
        arm = PlanarArm(links=2, lengths=lengths, masses=masses, damping=damping, gravity=gravity)
        A, B = arm.jacobian(x, u)
        return arm.step(x, u), A, B

    assert torch.autograd.gradcheck(f, (lengths, masses, damping, gravity))
    xs, us = x.clone().requires_grad_(True), u.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a, b: _arm(2).jacobian(a, b), (xs, us))


def test_batched_equals_loop_and_parameters_broadcast():
    gen = torch.Generator().manual_seed(4)
    x, u = _rand(gen, 15, 3)
    arm = _arm(3)
    xb, (Ab, Bb) = arm.step(x, u), arm.jacobian(x, u)
    for i in range(15):
        torch.testing.assert_close(arm.step(x[i], u[i]), xb[i], atol=0, rtol=0)
        Ai, Bi = arm.jacobian(x[i:i + 1], u[i:i + 1])
        torch.testing.assert_close(Ai[0], Ab[i], atol=1e-15, rtol=0)
        torch.testing.assert_close(Bi[0], Bb[i], atol=1e-15, rtol=0)
    # a batch of models (lengths (B, k), gravity (B,)) == one model per element, also time-major (T, B, n)
    L = 0.3 + torch.rand(3, 3, generator=gen, dtype=D64)
    g = torch.tensor([0.0, 9.81, 3.0], dtype=D64)
    xt, ut = x.view(5, 3, 6), u.view(5, 3, 3)
    batch = PlanarArm(links=3, lengths=L, masses=1.5, gravity=g, dt=0.03)
    A, B = batch.jacobian(xt, ut)
    step = batch.step(xt, ut)
    for j in range(3):
        one = PlanarArm(links=3, lengths=tuple(L[j].tolist()), masses=1.5, gravity=float(g[j]), dt=0.03)
        torch.testing.assert_close(step[:, j], one.step(xt[:, j], ut[:, j]))
        Aj, Bj = one.jacobian(xt[:, j], ut[:, j])
        torch.testing.assert_close(A[:, j], Aj)
        torch.testing.assert_close(B[:, j], Bj)
    # broadcasting of a single state against a batch of parameters
    assert batch.step(x[0], u[0]).shape == (3, 6) and batch.jacobian(x[0], u[0])[0].shape == (3, 6, 6)
    # the solvers' time-invariant fast path equals the per-step loop
    xm, um = x.view(3, 5, 6)[:, :5], u.view(3, 5, 3)[:, :4]
    fast = trajectory_jacobians(arm, xm, um)
    loop = trajectory_jacobians(arm, xm, um, time_invariant=False)
    for a, b in zip(fast, loop):
        torch.testing.assert_close(a, b, atol=1e-14, rtol=0)
    assert arm.step(x.float(), u.float()).dtype == torch.float32


def test_kinematics():
    arm = PlanarArm(links=3, lengths=(0.5, 0.3, 0.2))
    q = torch.tensor([[0.0, 0.0, 0.0], [math.pi / 2, -math.pi / 2, math.pi]], dtype=D64)
    pts = arm.fk(q)
    assert pts.shape == (2, 4, 2)
    torch.testing.assert_close(pts[0], torch.tensor([[0, 0], [0.5, 0], [0.8, 0], [1.0, 0]], dtype=D64))
    torch.testing.assert_close(arm.end_effector(q)[1], torch.tensor([0.1, 0.5], dtype=D64))
    gen = torch.Generator().manual_seed(5)
    qr = torch.randn(7, 3, generator=gen, dtype=D64)
    torch.testing.assert_close(arm.ee_jacobian(qr), vmap(jacrev(arm.end_effector))(qr))
    assert arm.reach == pytest.approx(1.0)


def test_spd_solve_and_the_model_as_nonlinear_dynamics():
    gen = torch.Generator().manual_seed(6)
    G = torch.randn(9, 4, 4, generator=gen, dtype=D64)
    W = G @ G.mT + 0.5 * torch.eye(4, dtype=D64)
    r = torch.randn(9, 4, 3, generator=gen, dtype=D64)
    torch.testing.assert_close(spd_solve(W, r), torch.linalg.solve(W, r))
    arm = _arm(2)
    x, u = _rand(gen, 4, 2)
    dyn = arm.dynamics()
    torch.testing.assert_close(dyn.f(x, u, 0), arm.step(x, u))
    assert arm.n == 4 and arm.m == 2 and arm.time_invariant


def test_bad_input():
    with pytest.raises(ValueError, match="links"):
        PlanarArm(links=0)
    with pytest.raises(ValueError, match="3 values for 2 links"):
        PlanarArm(links=2, lengths=(1.0, 1.0, 1.0))
    with pytest.raises(ValueError, match="positive"):
        PlanarArm(masses=(1.0, -1.0))
    with pytest.raises(ValueError, match=r"shape \(\*B, 2\)"):
        PlanarArm(lengths=torch.ones(3))
    with pytest.raises(ValueError, match=r"x must have shape \(\*B, 4\)"):
        PlanarArm().step(torch.zeros(3), torch.zeros(2))
    with pytest.raises(TypeError, match="parameter 'lengths'"):
        PlanarArm(lengths=torch.ones(2, dtype=torch.float32)).step(torch.zeros(4, dtype=D64),
                                                                   torch.zeros(2, dtype=D64))
