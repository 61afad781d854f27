"""The quadrotor model's optional mismatch parameters (mass scale, rotor drag): dynamics, closed-form
Jacobians (Eq. 34 parts) against autograd and finite differences, defaults unchanged, bad input."""

from __future__ import annotations

import math

import pytest
import torch

from controllers.manifold_mpc import system_jacobians
from controllers.systems.quadrotor import Quadrotor, QuadrotorSimulator
from torchlie import so3

D = torch.float64
DRAG = (0.3, 0.5, 0.2)


def _states(q, rot: torch.Tensor, seed=0):
    g = torch.Generator().manual_seed(seed)
    B = rot.shape[0]
    return q.state(torch.randn(B, 3, generator=g, dtype=D), 2 * torch.randn(B, 3, generator=g, dtype=D),
                   so3.exp(rot))


def _rotations():
    """Rotation vectors: near identity, of angle exactly π (two axes) and generic."""
    g = torch.Generator().manual_seed(3)
    axis = torch.tensor([[1.0, 2.0, -2.0], [0.0, 0.0, 1.0]], dtype=D)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    return torch.cat([torch.tensor([[1e-9, -2e-9, 0.5e-9]], dtype=D), math.pi * axis,
                      torch.randn(3, 3, generator=g, dtype=D)])


def _controls(B, seed=1):
    g = torch.Generator().manual_seed(seed)
    thrust = 8 + 4 * torch.rand(B, 1, generator=g, dtype=D)
    return torch.cat([thrust, torch.randn(B, 3, generator=g, dtype=D)], -1)


def _fd_jacobians(q, x, u, h=1e-6):
    M = q.manifold
    cols_x, cols_u = [], []
    for i in range(9):
        d = torch.zeros(*u.shape[:-1], 9, dtype=D)
        d[..., i] = h
        cols_x.append((q.f(M.boxplus(x, d), u) - q.f(M.boxplus(x, -d), u)) / (2 * h))
    for i in range(4):
        d = torch.zeros_like(u)
        d[..., i] = h
        cols_u.append((q.f(x, u + d) - q.f(x, u - d)) / (2 * h))
    return torch.stack(cols_x, -1), torch.stack(cols_u, -1)


@pytest.mark.parametrize("mass_scale, drag", [(1.3, DRAG), (0.7, (0.0, 0.0, 0.4)), (1.0, (0.0, 0.0, 0.0))])
def test_jacobians_match_autograd_and_finite_differences(mass_scale, drag):
    q = Quadrotor(mass_scale=mass_scale, drag=drag)
    rot = _rotations()
    x, u = _states(q, rot), _controls(rot.shape[0])
    _, Jx, Ju = system_jacobians(q, x, u, "analytic")
    _, Ax, Au = system_jacobians(q, x, u, "autograd")
    torch.testing.assert_close(Jx, Ax, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(Ju, Au, rtol=1e-12, atol=1e-12)
    Fx, Fu = _fd_jacobians(q, x, u)
    torch.testing.assert_close(Jx, Fx, rtol=0, atol=1e-7)
    torch.testing.assert_close(Ju, Fu, rtol=0, atol=1e-7)
    if drag != (0.0, 0.0, 0.0):  # the drag terms are really there
        assert float(Jx[..., 3:6, 3:6].abs().max()) > 0.1


def test_mismatch_closed_forms():
    """Level and moving along x: v̇ = g e₃ − (a_T/s) e₃ − d_x v_x e₁; hover needs a_T = s g."""
    q = Quadrotor(mass_scale=1.3, drag=DRAG)
    x, uh = q.hover(torch.zeros(2, 3, dtype=D))
    torch.testing.assert_close(uh[:, 0], torch.full((2,), 1.3 * 9.81, dtype=D), rtol=1e-15, atol=0)
    torch.testing.assert_close(q.f(x, uh)[:, 3:6], torch.zeros(2, 3, dtype=D), rtol=0, atol=1e-14)
    moving = x.replace(v=torch.tensor([[2.0, 0.0, 0.0], [0.0, -1.0, 3.0]], dtype=D))
    u = torch.tensor([[9.0, 0.0, 0.0, 0.0]], dtype=D).expand(2, 4)
    acc = q.f(moving, u)[:, 3:6]
    want = torch.tensor([[-0.3 * 2.0, 0.0, 9.81 - 9.0 / 1.3],
                         [0.0, 0.5 * 1.0, 9.81 - 9.0 / 1.3 - 0.2 * 3.0]], dtype=D)
    torch.testing.assert_close(acc, want, rtol=1e-14, atol=1e-14)
    # rotated 90° about z: the body x axis points along world y, so world-y velocity sees d_x
    Rz = so3.exp(torch.tensor([0.0, 0.0, math.pi / 2], dtype=D)).expand(2, 3, 3)
    turned = q.state(moving.p, moving.v, Rz)
    torch.testing.assert_close(q.f(turned, u)[1, 4], torch.tensor(0.3, dtype=D), rtol=1e-14, atol=1e-14)


def test_defaults_are_bit_identical_to_the_nominal_formulas():
    q = Quadrotor()
    rot = _rotations()
    x, u = _states(q, rot, seed=5), _controls(rot.shape[0], seed=6)
    R = x.R
    g = torch.tensor([0.0, 0.0, 9.81], dtype=D)
    f_ref = torch.cat([x.v, g - u[:, :1] * R[..., :, 2], u[:, 1:]], -1)
    assert torch.equal(q.f(x, u), f_ref)
    Jx, Ju = q.f_jacobians(x, u)
    B = rot.shape[0]
    Jx_ref = torch.zeros(B, 9, 9, dtype=D)
    Jx_ref[:, 0:3, 3:6] = torch.eye(3, dtype=D)
    Jx_ref[:, 3:6, 6:9] = u[:, 0, None, None] * (R @ so3.hat(torch.tensor([0.0, 0.0, 1.0], dtype=D)))
    Ju_ref = torch.zeros(B, 9, 4, dtype=D)
    Ju_ref[:, 3:6, 0] = -R[..., :, 2]
    Ju_ref[:, 6:9, 1:4] = torch.eye(3, dtype=D)
    assert torch.equal(Jx, Jx_ref) and torch.equal(Ju, Ju_ref)
    xh, uh = q.hover(torch.zeros(4, 3, dtype=D))
    assert torch.equal(uh, torch.tensor([[9.81, 0.0, 0.0, 0.0]], dtype=D).expand(4, 4))


def test_tensor_parameters_broadcast_like_a_per_sample_loop_and_are_differentiable():
    rot = _rotations()
    B = rot.shape[0]
    g = torch.Generator().manual_seed(7)
    s = 0.7 + 0.6 * torch.rand(B, generator=g, dtype=D)
    d = 0.5 * torch.rand(B, 3, generator=g, dtype=D)
    q = Quadrotor(mass_scale=s, drag=d)
    x, u = _states(q, rot, seed=8), _controls(B, seed=9)
    f, (Jx, Ju) = q.f(x, u), q.f_jacobians(x, u)
    for i in range(B):
        qi = Quadrotor(mass_scale=float(s[i]), drag=tuple(float(v) for v in d[i]))
        xi = qi.state(x.p[i], x.v[i], x.R[i])
        torch.testing.assert_close(f[i], qi.f(xi, u[i]), rtol=1e-14, atol=1e-14)
        Ji = qi.f_jacobians(xi, u[i])
        torch.testing.assert_close(Jx[i], Ji[0], rtol=1e-14, atol=1e-14)
        torch.testing.assert_close(Ju[i], Ji[1], rtol=1e-14, atol=1e-14)
    # one parameter set broadcast over a batch (a (3,) drag, a 0-dim mass scale) in float32
    q32 = Quadrotor(mass_scale=torch.tensor(1.3), drag=torch.tensor(DRAG))
    x32 = q32.state(x.p.float(), x.v.float(), x.R.float())
    f32 = q32.f(x32, u.float())
    assert f32.dtype == torch.float32 and f32.shape == (B, 9)
    f64 = Quadrotor(mass_scale=1.3, drag=DRAG).f(x, u)
    torch.testing.assert_close(f32, f64.float(), rtol=1e-5, atol=1e-5)

    def fn(s_, d_):
        return Quadrotor(mass_scale=s_, drag=d_).f(x, u)

    assert torch.autograd.gradcheck(fn, (s.clone().requires_grad_(), d.clone().requires_grad_()))


def test_simulator_applies_the_models_mismatch_on_top_of_its_own():
    q = Quadrotor(dt=0.02)
    rot = _rotations()
    x, u = _states(q, rot, seed=10), _controls(rot.shape[0], seed=11)
    a = QuadrotorSimulator(Quadrotor(dt=0.02, mass_scale=1.2, drag=DRAG)).step(x, u)
    b = QuadrotorSimulator(q, mass_scale=1.2, drag=DRAG).step(x, u)
    torch.testing.assert_close(a.v, b.v, rtol=1e-13, atol=1e-13)
    torch.testing.assert_close(a.p, b.p, rtol=1e-13, atol=1e-13)
    # the fine simulator of the mismatched model agrees with the mismatched Euler model to O(dt²)
    gap = float((a.v - Quadrotor(dt=0.02, mass_scale=1.2, drag=DRAG).step(x, u).v).abs().max())
    nominal_gap = float((a.v - q.step(x, u).v).abs().max())
    assert gap < 0.02 ** 2 * 30 and gap < nominal_gap / 5


@pytest.mark.parametrize("kwargs, name", [
    (dict(mass_scale=0.0), "mass_scale"), (dict(mass_scale=-1.0), "mass_scale"),
    (dict(mass_scale=float("nan")), "mass_scale"), (dict(mass_scale=torch.tensor([1.0, -0.5])), "mass_scale"),
    (dict(drag=(0.1, 0.2)), "drag"), (dict(drag=(0.1, -0.2, 0.0)), "drag"),
    (dict(drag=torch.zeros(2, 2)), "drag"), (dict(drag=(0.1, float("inf"), 0.0)), "drag")])
def test_bad_mismatch_parameters_are_refused(kwargs, name):
    with pytest.raises(ValueError, match=name):
        Quadrotor(**kwargs)
