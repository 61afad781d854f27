"""The seed-004 car and bicopter models: analytic Jacobians against torch.func, the seed's linearizations
(Eq. 119, 120) literally, gradcheck, batching and parameter broadcasting, convergence to scipy's
integration of the continuous model at the discretizations' orders, the bicopter's power balance."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.integrate import solve_ivp
from torch.func import jacrev, vmap

from controllers.systems import Bicopter, Car

D64 = torch.float64

SYSTEMS = [Car(), Car(length=0.7, dt=0.05), Bicopter(),
           Bicopter(mass=1.3, inertia=0.2, arm=0.3, hover_relative=True)]
IDS = ["car", "car-params", "bicopter", "bicopter-hover"]


def _rand(sys_, nb, seed=0):
    gen = torch.Generator().manual_seed(seed)
    x = 2 * torch.randn(nb, sys_.n, generator=gen, dtype=D64)
    u = 2 * torch.randn(nb, sys_.m, generator=gen, dtype=D64)
    if isinstance(sys_, Car):
        x[..., 4] = 1.2 * torch.tanh(x[..., 4])  # the steering angle away from the singularity at ±π/2
    return x, u


@pytest.mark.parametrize("sys_", SYSTEMS, ids=IDS)
def test_jacobian_matches_torch_func(sys_):
    x, u = _rand(sys_, 32)
    A, B = sys_.jacobian(x, u)
    assert A.shape == (32, sys_.n, sys_.n) and B.shape == (32, sys_.n, sys_.m)
    Af = vmap(jacrev(lambda a, b: sys_.step(a, b), argnums=0))(x, u)
    Bf = vmap(jacrev(lambda a, b: sys_.step(a, b), argnums=1))(x, u)
    torch.testing.assert_close(A, Af, atol=1e-10, rtol=1e-10)
    torch.testing.assert_close(B, Bf, atol=1e-10, rtol=1e-10)
    Ad, Bd = sys_.dynamics().jacobian(x, u, 0)
    assert torch.equal(Ad, A) and torch.equal(Bd, B)


def test_car_jacobian_is_the_seeds_eq_119_through_eq_192():
    car = Car(length=0.6, dt=0.1)
    x, u = _rand(car, 16, 1)
    th, v, ph = x[:, 2], x[:, 3], x[:, 4]
    l, dt = 0.6, 0.1
    Ac = torch.zeros(16, 5, 5, dtype=D64)
    Ac[:, 0, 2], Ac[:, 0, 3] = -v * torch.sin(th), torch.cos(th)
    Ac[:, 1, 2], Ac[:, 1, 3] = v * torch.cos(th), torch.sin(th)
    Ac[:, 2, 3], Ac[:, 2, 4] = torch.tan(ph) / l, v / l * (torch.tan(ph) ** 2 + 1)
    Bc = torch.zeros(5, 2, dtype=D64)
    Bc[3, 0] = Bc[4, 1] = 1.0
    A, B = car.jacobian(x, u)
    torch.testing.assert_close(A, torch.eye(5, dtype=D64) + Ac * dt, atol=1e-15, rtol=0)
    torch.testing.assert_close(B, (Bc * dt).expand(16, 5, 2), atol=1e-15, rtol=0)
    # and the step is explicit Euler of the seed's equations
    f = torch.stack([v * torch.cos(th), v * torch.sin(th), v / l * torch.tan(ph), u[:, 0], u[:, 1]], -1)
    torch.testing.assert_close(car.step(x, u), x + dt * f, atol=1e-15, rtol=0)


def test_bicopter_continuous_linearization_is_the_seeds_eq_120():
    bc = Bicopter(mass=1.7, inertia=0.4, arm=0.35)
    x, u = _rand(bc, 16, 2)
    m, I, l = 1.7, 0.4, 0.35
    th, S = x[:, 2], u[:, 0] + u[:, 1]
    Ac = torch.zeros(16, 6, 6, dtype=D64)
    Ac[:, :3, 3:] = torch.eye(3, dtype=D64)
    Ac[:, 3, 2], Ac[:, 4, 2] = -S * torch.cos(th) / m, -S * torch.sin(th) / m
    Bc = torch.zeros(16, 6, 2, dtype=D64)
    Bc[:, 3, :] = (-torch.sin(th) / m)[:, None]
    Bc[:, 4, :] = (torch.cos(th) / m)[:, None]
    Bc[:, 5, 0], Bc[:, 5, 1] = l / I, -l / I
    torch.testing.assert_close(vmap(jacrev(bc.derivative, argnums=0))(x, u), Ac, atol=1e-13, rtol=0)
    torch.testing.assert_close(vmap(jacrev(bc.derivative, argnums=1))(x, u), Bc, atol=1e-13, rtol=0)
    acc = bc.acceleration(x, u)
    ref = torch.stack([-S * torch.sin(th) / m, S * torch.cos(th) / m - 9.81, l / I * (u[:, 0] - u[:, 1])], -1)
    torch.testing.assert_close(acc, ref, atol=1e-13, rtol=0)


def test_hover_relative_is_the_absolute_model_shifted_by_the_hover_thrust():
    kw = dict(mass=1.9, inertia=0.3, arm=0.4, gravity=9.81)
    rel, ab = Bicopter(hover_relative=True, **kw), Bicopter(**kw)
    x, u = _rand(rel, 20, 3)
    h = 1.9 * 9.81 / 2
    assert rel.hover_thrust() == pytest.approx(h)
    torch.testing.assert_close(rel.step(x, u), ab.step(x, u + h), atol=1e-12, rtol=0)
    for a, b in zip(rel.jacobian(x, u), ab.jacobian(x, u + h)):
        torch.testing.assert_close(a, b, atol=1e-12, rtol=0)
    z = torch.zeros(1, 6, dtype=D64)
    assert torch.equal(rel.step(z, torch.zeros(1, 2, dtype=D64)), z)  # u = 0 hovers exactly


def test_gradcheck_states_controls_and_parameters():
    car, bc = Car(), Bicopter(hover_relative=True)
    for sys_ in (car, bc):
        x, u = _rand(sys_, 3, 4)
        x.requires_grad_(True)
        u.requires_grad_(True)
        assert torch.autograd.gradcheck(lambda a, b, s=sys_: (s.step(a, b), *s.jacobian(a, b)), (x, u))
    x, u = _rand(car, 4, 5)
    L = torch.tensor([0.4, 0.5, 0.6, 0.8], dtype=D64, requires_grad=True)
    dt = torch.tensor(0.1, dtype=D64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda L, dt: (Car(length=L, dt=dt).step(x, u),
                                                   *Car(length=L, dt=dt).jacobian(x, u)), (L, dt))
    x, u = _rand(bc, 4, 6)
    m = torch.tensor([1.0, 2.0, 2.5, 3.0], dtype=D64, requires_grad=True)
    I_ = torch.tensor(0.7, dtype=D64, requires_grad=True)
    arm = torch.tensor([0.2, 0.3, 0.4, 0.5], dtype=D64, requires_grad=True)

    def f(m, I_, arm):
        b = Bicopter(mass=m, inertia=I_, arm=arm, hover_relative=True)
        return (b.step(x, u), *b.jacobian(x, u))

    assert torch.autograd.gradcheck(f, (m, I_, arm))


@pytest.mark.parametrize("sys_", SYSTEMS, ids=IDS)
def test_batched_equals_loop_and_unbatched(sys_):
    x, u = _rand(sys_, 7, 7)
    xb, (A, B) = sys_.step(x, u), sys_.jacobian(x, u)
    for i in range(7):
        assert torch.equal(sys_.step(x[i], u[i]), xb[i])
        Ai, Bi = sys_.jacobian(x[i], u[i])
        assert torch.equal(Ai, A[i]) and torch.equal(Bi, B[i])
    # time-major (T, B, n) batches, as the solvers evaluate whole trajectories at once
    x3, u3 = x[:6].view(3, 2, -1), u[:6].view(3, 2, -1)
    torch.testing.assert_close(sys_.step(x3, u3), xb[:6].view(3, 2, -1), atol=0, rtol=0)
    assert sys_.step(x.float(), u.float()).dtype == torch.float32


def test_tensor_parameters_broadcast_like_a_batch_of_models():
    L = torch.tensor([0.4, 0.5, 0.7], dtype=D64)
    m = torch.tensor([1.0, 2.5, 4.0], dtype=D64)
    cases = [(Car(length=L, dt=0.1), lambda j: Car(length=float(L[j]), dt=0.1)),
             (Bicopter(mass=m, hover_relative=True),
              lambda j: Bicopter(mass=float(m[j]), hover_relative=True))]
    for batched, single in cases:
        x, u = _rand(batched, 15, 8)
        x, u = x.view(5, 3, -1), u.view(5, 3, -1)  # parameters (3,) against (T=5, B=3, n)
        xb, (A, B) = batched.step(x, u), batched.jacobian(x, u)
        for j in range(3):
            s = single(j)
            torch.testing.assert_close(xb[:, j], s.step(x[:, j], u[:, j]), atol=1e-15, rtol=0)
            Aj, Bj = s.jacobian(x[:, j], u[:, j])
            torch.testing.assert_close(A[:, j], Aj, atol=1e-15, rtol=0)
            torch.testing.assert_close(B[:, j], Bj, atol=1e-15, rtol=0)
    # one state, a batch of models
    xs, us = _rand(cases[0][0], 1, 9)
    assert Car(length=L).step(xs[0], us[0]).shape == (3, 5)


@pytest.mark.parametrize("sys_", [Car(length=0.6), Bicopter(mass=1.5, inertia=0.3, arm=0.3)],
                         ids=["car", "bicopter"])
def test_steps_converge_to_scipys_integration_at_first_order(sys_):
    """N steps of size τ/N against solve_ivp (rtol 1e-12) of ``derivative``: both discretizations are
    first order, so halving the step halves the error; and the local error of one step is O(dt²)."""
    gen = torch.Generator().manual_seed(10)
    x0 = 0.5 * torch.randn(sys_.n, generator=gen, dtype=D64)
    u = torch.randn(sys_.m, generator=gen, dtype=D64)
    if isinstance(sys_, Car):
        x0[3], x0[4] = 1.0, 0.4
    tau = 0.5

    def rhs(_, y):
        return sys_.derivative(torch.from_numpy(y), u).numpy()

    ref = solve_ivp(rhs, (0.0, tau), x0.numpy(), method="DOP853", rtol=1e-12, atol=1e-12).y[:, -1]
    errs = []
    for N in (50, 100, 200, 400):
        s = type(sys_)(**{**sys_.__dict__, "dt": tau / N})
        x = x0
        for _ in range(N):
            x = s.step(x, u)
        errs.append(np.abs(x.numpy() - ref).max())
    ratios = [errs[i] / errs[i + 1] for i in range(3)]
    assert all(1.9 < r < 2.1 for r in ratios), (errs, ratios)
    one = []
    for h in (0.02, 0.01):
        r1 = solve_ivp(rhs, (0.0, h), x0.numpy(), method="DOP853", rtol=1e-13, atol=1e-13).y[:, -1]
        one.append(np.abs(type(sys_)(**{**sys_.__dict__, "dt": h}).step(x0, u).numpy() - r1).max())
    assert 3.8 < one[0] / one[1] < 4.2


def test_car_drives_a_circle_of_the_turning_radius():
    """At constant speed and steering the rear axle follows a circle of radius ℓ/tan ϕ (the seed's
    kinematics); explicit Euler spirals outwards by about π v dt/2 per half turn, so a small step stays
    on it."""
    car = Car(length=0.5, dt=1e-3)
    phi = 0.3
    x = torch.tensor([0.0, 0.0, 0.0, 1.0, phi], dtype=D64)
    R = 0.5 / math.tan(phi)
    center = torch.tensor([0.0, R], dtype=D64)
    for _ in range(int(math.pi * R / 1e-3)):  # half a turn
        x = car.step(x, torch.zeros(2, dtype=D64))
    assert abs(float(torch.linalg.norm(x[:2] - center)) - R) < 3e-3
    assert abs(float(x[1]) - 2 * R) < 5e-3 and abs(float(x[2]) - math.pi) < 2e-3


def test_bicopter_power_balance():
    """d/dt (kinetic + potential energy) along ``derivative`` = power of the thrusts."""
    bc = Bicopter(mass=1.4, inertia=0.25, arm=0.3)
    x, u = _rand(bc, 10, 11)
    x.requires_grad_(True)
    (gE,) = torch.autograd.grad(bc.energy(x).sum(), x)
    dE = (gE * bc.derivative(x, u)).sum(-1)
    th = x[:, 2].detach()
    S = u[:, 0] + u[:, 1]
    power = S * (-torch.sin(th) * x[:, 3].detach() + torch.cos(th) * x[:, 4].detach()) \
        + 0.3 * (u[:, 0] - u[:, 1]) * x[:, 5].detach()
    torch.testing.assert_close(dE, power)


def test_bad_input():
    with pytest.raises(ValueError, match=r"x must have shape \(\*B, 5\)"):
        Car().step(torch.zeros(4), torch.zeros(2))
    with pytest.raises(ValueError, match=r"u must have shape"):
        Bicopter().step(torch.zeros(6), torch.zeros(1))
    with pytest.raises(TypeError, match="parameter 'length'"):
        Car(length=torch.tensor(0.5, dtype=D64)).step(torch.zeros(5), torch.zeros(2))
    with pytest.raises(TypeError, match="share a dtype"):
        Bicopter().jacobian(torch.zeros(6, dtype=D64), torch.zeros(2))
