"""Gravity torque of PlanarArm and impedance control (seed 004 §11.1-§11.2): the gravity torque against
autograd of the potential energy and the forward dynamics; closed-loop equilibria; batching; bad input."""

from __future__ import annotations

import math

import pytest
import torch
from torch.func import jacrev

from controllers.impedance import joint_impedance_torque, simulate, task_impedance_torque
from controllers.systems import Pendulum, PlanarArm

D64 = torch.float64


def _gen(seed=0):
    return torch.Generator().manual_seed(seed)


def _arm(**kw) -> PlanarArm:
    base = dict(links=3, lengths=(0.5, 0.4, 0.3), masses=(1.0, 0.8, 0.5), damping=0.1, gravity=9.81, dt=0.02)
    base.update(kw)
    return PlanarArm(**base)


def test_gravity_torque_is_the_gradient_of_the_potential():
    arm = _arm()
    q = math.pi * (2 * torch.rand(6, 3, generator=_gen(), dtype=D64) - 1)

    def potential(q_):
        return arm.energy(torch.cat([q_, torch.zeros_like(q_)], -1))  # zero velocity: V(q)

    ref = torch.stack([jacrev(potential)(q[i]) for i in range(6)])
    torch.testing.assert_close(arm.gravity_torque(q), ref, atol=1e-13, rtol=0)
    # and by central finite differences
    h = 1e-6
    fd = torch.stack([(potential(q + h * e) - potential(q - h * e)) / (2 * h)
                      for e in torch.eye(3, dtype=D64)], -1)
    torch.testing.assert_close(arm.gravity_torque(q), fd, atol=1e-8, rtol=0)


def test_gravity_torque_holds_the_arm_still_in_its_forward_dynamics():
    g = torch.tensor([9.81, 3.0, 0.0, 1.6], dtype=D64)  # a batch of gravities (broadcast)
    arm = _arm(gravity=g)
    q = torch.randn(4, 3, generator=_gen(1), dtype=D64)
    x = torch.cat([q, torch.zeros_like(q)], -1)
    tau = arm.gravity_torque(q)
    torch.testing.assert_close(arm.acceleration(x, tau), torch.zeros(4, 3, dtype=D64), atol=1e-12, rtol=0)
    torch.testing.assert_close(arm.step(x, tau), x, atol=1e-12, rtol=0)
    assert (arm.acceleration(x, torch.zeros_like(tau))[[0, 1, 3]].abs().amax(-1) > 1e-3).all()  # it falls
    torch.testing.assert_close(tau[3], _arm(gravity=1.6).gravity_torque(q[3]))
    torch.testing.assert_close(_arm(gravity=0.0).gravity_torque(q), torch.zeros(4, 3, dtype=D64))
    # one link: m g l cos q (the pendulum's gravity torque; its q = 0 hangs down, ours is horizontal)
    one = PlanarArm(links=1, lengths=0.7, masses=1.3, gravity=9.81)
    qq = torch.tensor([[0.3], [-1.0]], dtype=D64)
    torch.testing.assert_close(one.gravity_torque(qq), 1.3 * 9.81 * 0.7 * torch.cos(qq))
    assert Pendulum  # the one-link model is the pendulum (tests/controllers/test_arm.py)


def test_gravity_torque_gradcheck_and_bad_input():
    arm = _arm(masses=torch.tensor([1.0, 0.8, 0.5], dtype=D64, requires_grad=True))
    q = torch.randn(2, 3, generator=_gen(2), dtype=D64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda q_: arm.gravity_torque(q_), (q,))
    with pytest.raises(ValueError, match="q must have shape"):
        arm.gravity_torque(torch.zeros(2, 2, dtype=D64))


def test_joint_impedance_equilibrium_and_convergence():
    arm = _arm(lengths=0.5, masses=1.0)
    q_ref = torch.tensor([[0.5, -0.3, 0.4], [1.2, 0.6, -0.9]], dtype=D64)
    M = arm.mass_matrix(q_ref)
    K, Dm = 100 * M, 20 * M  # q̈ ≈ 100 e - 20 ė: critically damped, ω = 10 rad/s
    x_ref = torch.cat([q_ref, torch.zeros_like(q_ref)], -1)
    # the set point is an equilibrium of the closed loop (Eq. 171 with e = 0): τ = g(q^d), q̈ = 0
    tau = joint_impedance_torque(arm, x_ref, q_ref, K, Dm)
    torch.testing.assert_close(tau, arm.gravity_torque(q_ref))
    torch.testing.assert_close(arm.acceleration(x_ref, tau), torch.zeros(2, 3, dtype=D64), atol=1e-12, rtol=0)
    x0 = torch.zeros(2, 6, dtype=D64)
    r = simulate(arm, x0, lambda x, t: joint_impedance_torque(arm, x, q_ref, K, Dm), 200)
    assert (r.x[:, -1, :3] - q_ref).abs().max() < 1e-9
    # without gravity compensation: the rest point balances the spring against gravity, K (q^d - q) = g(q)
    r2 = simulate(arm, x0, lambda x, t: joint_impedance_torque(arm, x, q_ref, K, Dm,
                                                               gravity_compensation=False), 300)
    qs = r2.x[:, -1, :3]
    assert (r2.x[:, -1, 3:].abs().max() < 1e-6) and ((qs - q_ref).norm(dim=-1) > 0.2).all()
    bal = (K @ (q_ref - qs)[..., None])[..., 0] - arm.gravity_torque(qs)
    assert bal.abs().max() < 1e-6


def test_task_impedance_equilibrium_convergence_and_gain_forms():
    arm = PlanarArm(links=2, lengths=(0.5, 0.4), masses=(1.0, 0.8), damping=0.1, gravity=9.81, dt=0.02)
    f_ref = torch.tensor([[0.5, 0.3], [0.2, 0.6], [-0.3, 0.4]], dtype=D64)
    x0 = torch.tensor([0.3, 0.8, 0.0, 0.0], dtype=D64)
    Kf, Kv, Km = 200.0, torch.full((3, 2), 30.0, dtype=D64), 200.0 * torch.eye(2, dtype=D64)
    x = torch.randn(3, 4, generator=_gen(3), dtype=D64)
    t1 = task_impedance_torque(arm, x, f_ref, Kf, Kv)
    torch.testing.assert_close(t1, task_impedance_torque(arm, x, f_ref, Km, 30.0 * torch.eye(2, dtype=D64)))
    # Eq. 172 by hand: Jᵀ (K (f^d - f) - D J q̇) + g
    J = arm.ee_jacobian(x[:, :2])
    w = 200.0 * (f_ref - arm.end_effector(x[:, :2])) - 30.0 * (J @ x[:, 2:, None])[..., 0]
    torch.testing.assert_close(t1, (J.mT @ w[..., None])[..., 0] + arm.gravity_torque(x[:, :2]))
    r = simulate(arm, x0, lambda x, t: task_impedance_torque(arm, x, f_ref, Kf, Kv), 300)
    err = (arm.end_effector(r.x[:, -1, :2]) - f_ref).norm(dim=-1)
    assert err.max() < 1e-6
    r2 = simulate(arm, x0, lambda x, t: task_impedance_torque(arm, x, f_ref, Kf, Kv,
                                                              gravity_compensation=False), 300)
    assert ((arm.end_effector(r2.x[:, -1, :2]) - f_ref).norm(dim=-1) > 1e-2).all()
    for i in range(3):  # batched == loop
        ri = simulate(arm, x0, lambda x, t, i=i: task_impedance_torque(arm, x, f_ref[i], Kf, Kv[i]), 300)
        torch.testing.assert_close(ri.x, r.x[i], atol=1e-12, rtol=0)


def test_simulate_is_the_arm_step_and_external_torque():
    arm = _arm()
    x0 = torch.randn(2, 6, generator=_gen(4), dtype=D64)
    u = torch.randn(2, 5, 3, generator=_gen(5), dtype=D64)
    ext = torch.tensor([0.3, -0.2, 0.1], dtype=D64)
    r = simulate(arm, x0, lambda x, t: u[:, t], 5, tau_ext=ext)
    x = x0
    for t in range(5):
        x = arm.step(x, u[:, t] - ext)
        torch.testing.assert_close(r.x[:, t + 1], x, atol=0, rtol=0)
    torch.testing.assert_close(r.u, u)
    assert simulate(arm, x0, lambda x, t: u[:, t], 0).x.shape == (2, 1, 6)


def test_impedance_float32_and_gradients():
    arm = _arm(lengths=0.5, masses=1.0, dt=0.02)
    q_ref = torch.tensor([0.5, -0.3, 0.4], requires_grad=True)
    x0 = torch.zeros(6)
    r = simulate(arm, x0, lambda x, t: joint_impedance_torque(arm, x, q_ref, 20.0, 3.0), 20)
    assert r.x.dtype == torch.float32 and torch.isfinite(r.x).all()
    (g,) = torch.autograd.grad(r.x[-1, :3].sum(), q_ref)
    assert torch.isfinite(g).all() and (g.abs() > 0).all()
    qd = torch.tensor([0.5, -0.3, 0.4], dtype=D64, requires_grad=True)
    x = torch.randn(6, generator=_gen(6), dtype=D64)
    arm64 = _arm()
    assert torch.autograd.gradcheck(lambda q_: joint_impedance_torque(arm64, x, q_, 10.0, 2.0), (qd,))
    fr = torch.tensor([0.4, 0.5], dtype=D64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda f_: task_impedance_torque(arm64, x, f_, 50.0, 5.0), (fr,))


def test_bad_input():
    arm = _arm()
    x = torch.zeros(6, dtype=D64)
    q = torch.zeros(3, dtype=D64)
    with pytest.raises(TypeError, match="'arm'"):
        joint_impedance_torque(object(), x, q, 1.0, 1.0)
    with pytest.raises(ValueError, match="'x'"):
        joint_impedance_torque(arm, torch.zeros(4, dtype=D64), q, 1.0, 1.0)
    with pytest.raises(ValueError, match="'q_ref'"):
        joint_impedance_torque(arm, x, torch.zeros(2, dtype=D64), 1.0, 1.0)
    with pytest.raises(TypeError, match="'q_ref'"):
        joint_impedance_torque(arm, x, torch.zeros(3), 1.0, 1.0)
    with pytest.raises(ValueError, match="'stiffness'"):
        joint_impedance_torque(arm, x, q, torch.ones(2, 2, dtype=D64), 1.0)
    with pytest.raises(ValueError, match="'f_ref'"):
        task_impedance_torque(arm, x, q, 1.0, 1.0)
    with pytest.raises(ValueError, match="'steps'"):
        simulate(arm, x, lambda x, t: q, -1)
    with pytest.raises(TypeError, match="'controller'"):
        simulate(arm, x, None, 3)
