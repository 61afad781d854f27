"""The quadrotor model (seed 003 Eq. 32-34) and its simulator."""

from __future__ import annotations

import math

import torch

from controllers.manifold_mpc import ManifoldSystem
from controllers.systems.quadrotor import Quadrotor, QuadrotorSimulator
from torchlie import so3

D = torch.float64


def _x(q, B=4, seed=0):
    g = torch.Generator().manual_seed(seed)
    return q.state(torch.randn(B, 3, generator=g, dtype=D), torch.randn(B, 3, generator=g, dtype=D),
                   so3.exp(torch.randn(B, 3, generator=g, dtype=D)))


def test_model_is_a_manifold_system_and_steps_on_the_manifold():
    q = Quadrotor()
    assert isinstance(q, ManifoldSystem)
    x = _x(q)
    u = torch.tensor([[12.0, 1.0, -2.0, 0.5]], dtype=D).expand(4, 4)
    y = q.step(x, u)
    q.manifold.check(y)
    torch.testing.assert_close(y.p, x.p + q.dt * x.v)
    acc = torch.tensor([0, 0, 9.81], dtype=D) - 12.0 * x.R[..., :, 2]
    torch.testing.assert_close(y.v, x.v + q.dt * acc)
    torch.testing.assert_close(y.R, x.R @ so3.exp(q.dt * u[..., 1:]))


def test_hover_is_an_equilibrium():
    q = Quadrotor()
    x, u = q.hover(torch.tensor([[1.0, 2.0, -3.0]], dtype=D))
    y = q.step(x, u)
    torch.testing.assert_close(y.p, x.p, rtol=0, atol=0)
    torch.testing.assert_close(y.v, x.v, rtol=0, atol=0)
    sim = QuadrotorSimulator(q)
    z = sim.step(x, u)
    torch.testing.assert_close(z.p, x.p, rtol=0, atol=1e-15)


def test_simulator_is_exact_for_constant_acceleration_and_rotation():
    """ω = 0 and constant thrust: the acceleration is constant, so RK4 is exact; R moves exactly by Exp."""
    q = Quadrotor()
    sim = QuadrotorSimulator(q, substeps=3)
    x = _x(q, seed=1)
    u = torch.tensor([[7.0, 0.0, 0.0, 0.0]], dtype=D).expand(4, 4)
    y = sim.step(x, u)
    a = torch.tensor([0, 0, 9.81], dtype=D) - 7.0 * x.R[..., :, 2]
    torch.testing.assert_close(y.v, x.v + q.dt * a, rtol=0, atol=1e-14)
    torch.testing.assert_close(y.p, x.p + q.dt * x.v + 0.5 * q.dt ** 2 * a, rtol=0, atol=1e-14)
    w = torch.tensor([[0.3, -4.0, 2.0]], dtype=D)
    y = sim.step(x, torch.cat([u[..., :1], w.expand(4, 3)], -1))
    torch.testing.assert_close(y.R, x.R @ so3.exp(q.dt * w), rtol=0, atol=1e-14)


def test_simulator_converges_at_fourth_order_and_differs_from_the_model_at_second():
    q = Quadrotor(dt=0.02)
    x = _x(q, seed=2)
    u = torch.tensor([[11.0, 3.0, -6.0, 2.0]], dtype=D).expand(4, 4)
    fine = QuadrotorSimulator(q, substeps=64).step(x, u)
    e = [float((QuadrotorSimulator(q, substeps=s).step(x, u).p - fine.p).abs().max()) for s in (2, 4)]
    assert e[1] < e[0] / 12  # 4th order: about 16× per halving
    gap = float((q.step(x, u).v - fine.v).abs().max())
    assert 1e-5 < gap < 0.02 ** 2 * 200  # explicit Euler vs the exact flow: O(dt²) per step


def test_simulator_mismatch_saturation_and_drag():
    q = Quadrotor(thrust_max=20.0, rate_max=2.0)
    x, uh = q.hover(torch.zeros(1, 3, dtype=D))
    sat = QuadrotorSimulator(q).saturate(torch.tensor([[50.0, 5.0, -5.0, 1.0]], dtype=D))
    torch.testing.assert_close(sat, torch.tensor([[20.0, 2.0, -2.0, 1.0]], dtype=D))
    heavy = QuadrotorSimulator(q, mass_scale=1.2).step(x, uh)
    assert float(heavy.v[0, 2]) > 0  # heavier than modelled: sinks (z down)
    moving = x.replace(v=torch.tensor([[8.0, 0.0, 0.0]], dtype=D))
    dragged = QuadrotorSimulator(q, drag=(0.4, 0.4, 0.1)).step(moving, uh)
    exact = torch.tensor(8.0 * math.exp(-0.4 * q.dt), dtype=D)  # v̇ = −0.4 v along x (RK4: error ~1e-13)
    torch.testing.assert_close(dragged.v[0, 0], exact, rtol=1e-11, atol=0)
