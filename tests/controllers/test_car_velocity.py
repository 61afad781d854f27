"""controllers.systems.car_velocity.CarVelocity (seed 004 §9.15, velocity input): the analytic Jacobians
against torch.func, finite differences and the seed's Eq. 118 through Eq. 192, gradcheck, batching and
parameter broadcasting, agreement with the acceleration-input Car when its speed is the velocity command,
float32, the turning circle, and bad input."""

from __future__ import annotations

import math

import pytest
import torch
from torch.func import jacrev, vmap

from controllers.dynamics import NonlinearDynamics
from controllers.systems.car import Car
from controllers.systems.car_velocity import CarVelocity

D64 = torch.float64


def _rand(nb, seed=0, dtype=D64):
    gen = torch.Generator().manual_seed(seed)
    x = 2 * torch.randn(nb, 4, generator=gen, dtype=dtype)
    u = 2 * torch.randn(nb, 2, generator=gen, dtype=dtype)
    x[..., 3] = 1.2 * torch.tanh(x[..., 3])  # the steering angle away from the singularity at ±π/2
    return x, u


@pytest.mark.parametrize("car", [CarVelocity(), CarVelocity(length=0.7, dt=0.05)], ids=["default", "params"])
def test_jacobian_matches_torch_func_and_finite_differences(car):
    x, u = _rand(32)
    A, B = car.jacobian(x, u)
    assert A.shape == (32, 4, 4) and B.shape == (32, 4, 2)
    Af = vmap(jacrev(lambda a, b: car.step(a, b), argnums=0))(x, u)
    Bf = vmap(jacrev(lambda a, b: car.step(a, b), argnums=1))(x, u)
    torch.testing.assert_close(A, Af, atol=1e-12, rtol=1e-12)
    torch.testing.assert_close(B, Bf, atol=1e-12, rtol=1e-12)
    h = 1e-6
    for j in range(4):
        e = torch.zeros(4, dtype=D64)
        e[j] = h
        fd = (car.step(x + e, u) - car.step(x - e, u)) / (2 * h)
        torch.testing.assert_close(A[..., j], fd, atol=1e-8, rtol=1e-8)
    for j in range(2):
        e = torch.zeros(2, dtype=D64)
        e[j] = h
        fd = (car.step(x, u + e) - car.step(x, u - e)) / (2 * h)
        torch.testing.assert_close(B[..., j], fd, atol=1e-8, rtol=1e-8)
    Ad, Bd = car.dynamics().jacobian(x, u, 0)
    assert isinstance(car.dynamics(), NonlinearDynamics)
    assert torch.equal(Ad, A) and torch.equal(Bd, B)


def test_jacobian_is_the_seeds_eq_118_through_eq_192_and_step_is_euler():
    car = CarVelocity(length=0.6, dt=0.1)
    x, u = _rand(16, 1)
    th, ph, v = x[:, 2], x[:, 3], u[:, 0]
    l, dt = 0.6, 0.1
    Ac = torch.zeros(16, 4, 4, dtype=D64)
    Ac[:, 0, 2], Ac[:, 1, 2] = -v * torch.sin(th), v * torch.cos(th)
    Ac[:, 2, 3] = v / l * (torch.tan(ph) ** 2 + 1)
    Bc = torch.zeros(16, 4, 2, dtype=D64)
    Bc[:, 0, 0], Bc[:, 1, 0], Bc[:, 2, 0], Bc[:, 3, 1] = torch.cos(th), torch.sin(th), torch.tan(ph) / l, 1.0
    A, B = car.jacobian(x, u)
    torch.testing.assert_close(A, torch.eye(4, dtype=D64) + Ac * dt, atol=1e-15, rtol=0)
    torch.testing.assert_close(B, Bc * dt, atol=1e-15, rtol=0)
    f = torch.stack([v * torch.cos(th), v * torch.sin(th), v / l * torch.tan(ph), u[:, 1]], -1)
    torch.testing.assert_close(car.step(x, u), x + dt * f, atol=1e-15, rtol=0)


def test_agrees_with_the_acceleration_car_whose_speed_is_the_command():
    """The acceleration car with ``v = u₁`` moves its pose ``[x₁, x₂, θ, ϕ]`` exactly like this one."""
    x, u = _rand(10, 2)
    acc = torch.randn(10, generator=torch.Generator().manual_seed(3), dtype=D64)
    x5 = torch.stack([x[:, 0], x[:, 1], x[:, 2], u[:, 0], x[:, 3]], -1)
    u5 = torch.stack([acc, u[:, 1]], -1)
    ref = Car(length=0.45, dt=0.07).step(x5, u5)[:, [0, 1, 2, 4]]
    torch.testing.assert_close(CarVelocity(length=0.45, dt=0.07).step(x, u), ref, atol=1e-15, rtol=0)


def test_gradcheck_states_controls_and_parameters():
    car = CarVelocity()
    x, u = _rand(3, 4)
    x.requires_grad_(True)
    u.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a, b: (car.step(a, b), *car.jacobian(a, b)), (x, u))
    x, u = _rand(4, 5)
    L = torch.tensor([0.4, 0.5, 0.6, 0.8], dtype=D64, requires_grad=True)
    dt = torch.tensor(0.1, dtype=D64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda L, dt: (CarVelocity(length=L, dt=dt).step(x, u),
                                                   *CarVelocity(length=L, dt=dt).jacobian(x, u)), (L, dt))


def test_batched_equals_loop_time_major_and_float32():
    car = CarVelocity(length=0.55)
    x, u = _rand(7, 7)
    xb, (A, B) = car.step(x, u), car.jacobian(x, u)
    for i in range(7):
        assert torch.equal(car.step(x[i], u[i]), xb[i])
        Ai, Bi = car.jacobian(x[i], u[i])
        assert torch.equal(Ai, A[i]) and torch.equal(Bi, B[i])
    x3, u3 = x[:6].view(3, 2, 4), u[:6].view(3, 2, 2)
    torch.testing.assert_close(car.step(x3, u3), xb[:6].view(3, 2, 4), atol=0, rtol=0)
    x32, u32 = x.float(), u.float()
    s32, (A32, B32) = car.step(x32, u32), car.jacobian(x32, u32)
    assert s32.dtype == A32.dtype == B32.dtype == torch.float32
    torch.testing.assert_close(s32.double(), xb, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(A32.double(), A, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(B32.double(), B, atol=1e-5, rtol=1e-5)


def test_tensor_parameters_broadcast_like_a_batch_of_models():
    L = torch.tensor([0.4, 0.5, 0.7], dtype=D64)
    x, u = _rand(15, 8)
    x, u = x.view(5, 3, 4), u.view(5, 3, 2)  # parameters (3,) against (T=5, B=3, n)
    batched = CarVelocity(length=L, dt=0.1)
    xb, (A, B) = batched.step(x, u), batched.jacobian(x, u)
    for j in range(3):
        s = CarVelocity(length=float(L[j]), dt=0.1)
        torch.testing.assert_close(xb[:, j], s.step(x[:, j], u[:, j]), atol=1e-15, rtol=0)
        Aj, Bj = s.jacobian(x[:, j], u[:, j])
        torch.testing.assert_close(A[:, j], Aj, atol=1e-15, rtol=0)
        torch.testing.assert_close(B[:, j], Bj, atol=1e-15, rtol=0)
    assert CarVelocity(length=L).step(x[0, 0], u[0, 0]).shape == (3, 4)  # one state, a batch of models


def test_drives_a_circle_of_the_turning_radius():
    """Constant speed and steering: the rear axle follows the circle of radius ℓ / tan ϕ."""
    car = CarVelocity(length=0.5, dt=1e-3)
    phi = 0.3
    x = torch.tensor([0.0, 0.0, 0.0, phi], dtype=D64)
    R = 0.5 / math.tan(phi)
    center = torch.tensor([0.0, R], dtype=D64)
    u = torch.tensor([1.0, 0.0], dtype=D64)
    for _ in range(int(math.pi * R / 1e-3)):  # half a turn
        x = car.step(x, u)
    assert abs(float(torch.linalg.norm(x[:2] - center)) - R) < 3e-3
    assert abs(float(x[1]) - 2 * R) < 5e-3 and abs(float(x[2]) - math.pi) < 2e-3
    assert float(x[3]) == phi


def test_bad_input_raises():
    car = CarVelocity()
    x, u = _rand(2)
    with pytest.raises(ValueError, match="x must have shape"):
        car.step(x[:, :3], u)
    with pytest.raises(ValueError, match="u must have shape"):
        car.jacobian(x, u[:, :1])
    with pytest.raises(TypeError, match="share a dtype"):
        car.step(x, u.float())
    with pytest.raises(TypeError, match="dtype"):
        CarVelocity(length=torch.tensor(0.5, dtype=torch.float32)).step(x, u)
    with pytest.raises(ValueError, match="'dt' must be positive"):
        CarVelocity(dt=0.0)
    with pytest.raises(TypeError, match="'length'"):
        CarVelocity(length="long")
