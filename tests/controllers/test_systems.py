"""System models: analytic Jacobians three ways, physics against an independent formulation, parameters."""

from __future__ import annotations

import pytest
import torch
from torch.func import jacrev, vmap

from controllers.systems import CartPole, Pendulum

D64 = torch.float64


def _rand(gen, nb, n, m):
    x = 3 * torch.randn(nb, n, generator=gen, dtype=D64)
    u = 2 * torch.randn(nb, m, generator=gen, dtype=D64)
    return x, u


SYSTEMS = [Pendulum(damping=0.3), CartPole()]


@pytest.mark.parametrize("sys_", SYSTEMS, ids=["pendulum", "cartpole"])
def test_jacobians_analytic_vs_torch_func_vs_fd(sys_):
    gen = torch.Generator().manual_seed(0)
    x, u = _rand(gen, 16, sys_.n, sys_.m)
    A, B = sys_.jacobian(x, u)
    assert A.shape == (16, sys_.n, sys_.n) and B.shape == (16, sys_.n, sys_.m)
    Af = vmap(jacrev(lambda a, b: sys_.step(a, b), argnums=0))(x, u)
    Bf = vmap(jacrev(lambda a, b: sys_.step(a, b), argnums=1))(x, u)
    torch.testing.assert_close(A, Af, atol=1e-12, rtol=1e-10)
    torch.testing.assert_close(B, Bf, atol=1e-12, rtol=1e-10)
    h = 1e-6
    for i in range(sys_.n):
        e = torch.zeros(sys_.n, dtype=D64)
        e[i] = h
        fd = (sys_.step(x + e, u) - sys_.step(x - e, u)) / (2 * h)
        torch.testing.assert_close(A[..., i], fd, atol=1e-7, rtol=1e-6)
    fd = (sys_.step(x, u + h) - sys_.step(x, u - h)) / (2 * h)
    torch.testing.assert_close(B[..., 0], fd, atol=1e-7, rtol=1e-6)


def test_pendulum_energy_balance():
    # dE/dt along the continuous dynamics equals the power τω minus the damping loss bω²
    p = Pendulum(mass=1.3, length=0.7, damping=0.2)
    gen = torch.Generator().manual_seed(1)
    x, u = _rand(gen, 10, 2, 1)
    x.requires_grad_(True)
    (gE,) = torch.autograd.grad(p.energy(x).sum(), x)
    dE = (gE * p.derivative(x, u)).sum(-1)
    torch.testing.assert_close(dE, u[:, 0] * x[:, 1] - 0.2 * x[:, 1] ** 2)


def test_cartpole_against_manipulator_equation_and_energy():
    cp = CartPole(cart_mass=1.1, pole_mass=0.4, length=0.6)
    gen = torch.Generator().manual_seed(2)
    x, u = _rand(gen, 12, 4, 1)
    mc, mp, l, g = 1.1, 0.4, 0.6, 9.81
    th, om = x[:, 1], x[:, 3]
    s, c = torch.sin(th), torch.cos(th)
    M = torch.stack([torch.stack([torch.full_like(c, mc + mp), mp * l * c], -1),
                     torch.stack([mp * l * c, torch.full_like(c, mp * l * l)], -1)], -2)
    rhs = torch.stack([u[:, 0] + mp * l * s * om**2, -mp * g * l * s], -1)
    torch.testing.assert_close(cp.acceleration(x, u), torch.linalg.solve(M, rhs))
    x.requires_grad_(True)
    (gE,) = torch.autograd.grad(cp.energy(x).sum(), x)
    torch.testing.assert_close((gE * cp.derivative(x, u)).sum(-1), u[:, 0] * x[:, 2])


def test_parameter_gradients_gradcheck_and_batched_params():
    gen = torch.Generator().manual_seed(3)
    x, u = _rand(gen, 4, 2, 1)
    length = torch.tensor([0.8, 1.0, 1.2, 1.5], dtype=D64, requires_grad=True)
    mass = torch.tensor(0.9, dtype=D64, requires_grad=True)

    def f(length, mass):
        p = Pendulum(length=length, mass=mass, damping=0.1)
        A, B = p.jacobian(x, u)
        return p.step(x, u), A, B

    assert torch.autograd.gradcheck(f, (length, mass))
    # a batch of parameters == one model per element
    xb = Pendulum(length=length.detach()).step(x, u)
    for i in range(4):
        torch.testing.assert_close(xb[i], Pendulum(length=float(length.detach()[i])).step(x[i], u[i]))
    xc, uc = _rand(gen, 3, 4, 1)
    lc = torch.tensor([0.4, 0.5, 0.7], dtype=D64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda L: CartPole(length=L).jacobian(xc, uc)[0], (lc,))


def test_time_major_broadcast_and_float32():
    # parameters (B,) broadcast against (T, B, n) states: the solvers evaluate Jacobians time-major
    gen = torch.Generator().manual_seed(4)
    x, u = _rand(gen, 15, 4, 1)
    x, u = x.view(5, 3, 4), u.view(5, 3, 1)
    L = torch.tensor([0.4, 0.5, 0.7], dtype=D64)
    A, B = CartPole(length=L).jacobian(x, u)
    for j in range(3):
        Aj, Bj = CartPole(length=float(L[j])).jacobian(x[:, j], u[:, j])
        torch.testing.assert_close(A[:, j], Aj)
        torch.testing.assert_close(B[:, j], Bj)
    x32 = x.float()
    assert CartPole().step(x32, u.float()).dtype == torch.float32


def test_swing_free_motion_conserves_energy_approximately():
    # symplectic Euler keeps the energy of the undamped pendulum bounded close to its initial value
    p = Pendulum(dt=0.01)
    x = torch.tensor([[2.0, 0.0]], dtype=D64)
    E0 = p.energy(x)
    for _ in range(500):
        x = p.step(x, torch.zeros(1, 1, dtype=D64))
    assert abs(float(p.energy(x) - E0)) < 0.05 * float(E0)


def test_bad_input():
    with pytest.raises(ValueError, match=r"x must have shape \(\*B, 2\)"):
        Pendulum().step(torch.zeros(3), torch.zeros(1))
    with pytest.raises(ValueError, match=r"u must have shape"):
        CartPole().step(torch.zeros(4), torch.zeros(2))
    with pytest.raises(TypeError, match="parameter 'length'"):
        Pendulum(length=torch.tensor(1.0, dtype=D64)).step(torch.zeros(2), torch.zeros(1))
