"""The MountainCarContinuous-v0 model (learning/_mountain_car.py): dynamics == env, Jacobians, cost, MPC."""

from __future__ import annotations

import dataclasses
import math

import gymnasium as gym
import numpy as np
import pytest
import torch

from controllers.dynamics import jacobians
from learning._mountain_car import (
    EnergyGoalCost,
    MountainCar,
    mountain_car_cost,
    mountain_car_energy,
    mountain_car_model,
    mountain_car_state,
)
from learning.env_models import check_model
from learning.model_mpc import ModelMPC

STARTS = [(-0.5, 0.0), (-1.15, -0.06), (-0.52, 0.0699), (0.3, 0.05), (-1.2, 0.0), (-0.9, -0.03)]


def _env_rollout(starts, steps: int, seed: int = 0):
    """Env states ``(steps+1, N, 2)`` float32 and actions ``(steps, N, 1)`` from float32 ``starts``: random
    actions in [-1, 1] mixed with a bang-bang push along the velocity (to reach the speed limit and the
    wall); the env is stepped from a float32 state, as after its first step."""
    rng = np.random.default_rng(seed)
    envs = [gym.make("MountainCarContinuous-v0").unwrapped for _ in starts]
    xs, us = [], []
    for e, s in zip(envs, starts):
        e.reset(seed=seed)
        e.state = np.array(s, dtype=np.float32)
    xs.append(np.stack([e.state.copy() for e in envs]))
    for _ in range(steps):
        a = np.where(rng.random(len(envs)) < 0.3, rng.uniform(-1, 1, len(envs)), np.sign(xs[-1][:, 1] + 1e-9))
        a = a.astype(np.float32)[:, None]
        for e, ai in zip(envs, a):
            if e.state[0] >= 0.45:  # past the goal the env has terminated; keep the car where it is
                e.state = np.array([-0.5, 0.0], dtype=np.float32)
            e.step(ai)
        us.append(a)
        xs.append(np.stack([e.state.copy() for e in envs]))
    return np.stack(xs), np.stack(us)


def test_step_equals_env_float32_bitwise_and_float64():
    X, U = _env_rollout(STARTS, 300)
    x, u = torch.from_numpy(X[:-1]), torch.from_numpy(U)
    sys = MountainCar()
    nxt = torch.from_numpy(X[1:])
    reset = (x[..., 0] >= 0.45)[..., None]  # steps where the helper moved a finished car back
    y32 = sys.step(x, u, 0)
    assert y32.dtype == torch.float32
    ok = ~reset.expand_as(y32)
    assert torch.equal(y32[ok], nxt[ok])
    y64 = sys.step(x.double(), u.double(), 0)
    assert y64.dtype == torch.float64
    torch.testing.assert_close(y64[ok], nxt[ok].double(), atol=2e-7, rtol=0)
    # the rollout covers the speed limit and the inelastic left wall
    v = X[1:, :, 1]
    assert (np.abs(v) == np.float32(0.07)).sum() >= 2
    wall = (X[1:, :, 0] == np.float32(-1.2)) & (X[:-1, :, 1] < 0)
    assert wall.sum() > 2 and np.all(v[wall] == 0)


def test_step_from_reset_state_float64():
    env = gym.make("MountainCarContinuous-v0")
    obs, _ = env.reset(seed=3)
    x = torch.tensor(env.unwrapped.state, dtype=torch.float64)[None]  # float64 right after reset
    obs1, *_ = env.step(np.array([0.7], dtype=np.float32))
    y = MountainCar().step(x, torch.tensor([[0.7]], dtype=torch.float64))
    torch.testing.assert_close(y[0], torch.from_numpy(obs1).double(), atol=1e-7, rtol=0)


def test_action_clipped_and_batched_broadcast():
    sys = MountainCar()
    x = torch.tensor([[-0.5, 0.01], [0.1, -0.02]], dtype=torch.float64)
    big = sys.step(x, torch.full((2, 1), 5.0, dtype=torch.float64))
    torch.testing.assert_close(big, sys.step(x, torch.ones(2, 1, dtype=torch.float64)))
    xb = torch.randn(3, 4, 2, dtype=torch.float64) * 0.02 + torch.tensor([-0.5, 0.0], dtype=torch.float64)
    ub = torch.rand(4, 1, dtype=torch.float64) * 2 - 1
    yb = sys.step(xb, ub)
    loop = torch.stack([torch.stack([sys.step(xb[i, j], ub[j]) for j in range(4)]) for i in range(3)])
    torch.testing.assert_close(yb, loop)


def test_jacobian_matches_torch_func_and_finite_differences():
    sys = MountainCar()
    g = torch.Generator().manual_seed(0)
    x = torch.stack([torch.rand(64, generator=g, dtype=torch.float64) * 1.5 - 1.1,
                     torch.rand(64, generator=g, dtype=torch.float64) * 0.1 - 0.05], -1)
    u = torch.rand(64, 1, generator=g, dtype=torch.float64) * 1.8 - 0.9
    x = torch.cat([x, torch.tensor([[-1.19, -0.05], [-0.5, 0.0699]], dtype=torch.float64)])  # wall, v clip
    u = torch.cat([u, torch.tensor([[0.0], [1.0 - 1e-3]], dtype=torch.float64)])
    A, B = sys.jacobian(x, u)
    _, A2, B2 = jacobians(sys.step, x, u, 0, method="vmap")
    torch.testing.assert_close(A, A2)
    torch.testing.assert_close(B, B2)
    h = 1e-7  # central differences (no clip switches within h at these points)
    for i in range(2):
        e = torch.zeros(2, dtype=torch.float64)
        e[i] = h
        fd = (sys.step(x + e, u) - sys.step(x - e, u)) / (2 * h)
        torch.testing.assert_close(A[..., :, i], fd, atol=1e-7, rtol=1e-6)
    fd = (sys.step(x, u + h) - sys.step(x, u - h)) / (2 * h)
    torch.testing.assert_close(B[..., 0], fd, atol=1e-7, rtol=1e-6)
    assert torch.all(A[-2, 1] == 0) and torch.all(A[-1, 1] == 0)  # wall and speed limit: no v sensitivity


def test_cost_against_hand_formula_and_autograd():
    cost = EnergyGoalCost(weight=1300.0, margin=2e-5, width=2e-5)
    g = torch.Generator().manual_seed(1)
    T = 7
    x = torch.stack([torch.rand(5, T + 1, generator=g, dtype=torch.float64) * 0.05 - math.pi / 6 - 0.025,
                     torch.rand(5, T + 1, generator=g, dtype=torch.float64) * 0.01 - 0.005], -1)
    x[:2, -1] = torch.tensor([[-0.9, 0.03], [0.3, -0.04]], dtype=torch.float64)  # far from the floor
    u = torch.rand(5, T, 1, generator=g, dtype=torch.float64) * 2 - 1
    Estar = 0.0025 / 3 * math.sin(3 * 0.45) + 2e-5
    Ek = -0.0025 / 3 + 2e-5
    for b in range(5):
        p, v = float(x[b, -1, 0]), float(x[b, -1, 1])
        E = v * v / 2 + 0.0025 / 3 * math.sin(3 * p)
        hand = (0.1 * float((u[b] ** 2).sum()) + 1300 * 2e-5 * math.log1p(math.exp((Estar - E) / 2e-5))
                + 1e4 * 2e-6 * math.log1p(math.exp((Ek - E) / 2e-6)))
        assert float(cost.evaluate(x[b], u[b])) == pytest.approx(hand, rel=1e-12, abs=1e-12)
    torch.testing.assert_close(mountain_car_energy(x[:, -1]), 0.5 * x[:, -1, 1] ** 2
                               + 0.0025 / 3 * torch.sin(3 * x[:, -1, 0]))
    gx, gu, Hxx, Hux, Huu = cost.derivatives(x, u)
    xg, ug = x.clone().requires_grad_(), u.clone().requires_grad_()
    ax, au = torch.autograd.grad(cost.evaluate(xg, ug).sum(), (xg, ug))
    torch.testing.assert_close(gx, ax)
    torch.testing.assert_close(gu, au)
    assert Hux is None and torch.all(Huu == 0.2)
    ev = torch.linalg.eigvalsh(Hxx)
    assert torch.all(ev >= -1e-12)  # Gauss-Newton: positive semidefinite
    assert mountain_car_cost(10).weight == 1300.0
    with pytest.raises(ValueError, match="weight"):
        EnergyGoalCost(weight=-1.0)
    with pytest.raises(ValueError, match="T\\+1"):
        cost.evaluate(x[:, :-1], u)


def test_model_fits_env_and_bad_input():
    env = gym.make("MountainCarContinuous-v0")
    md = mountain_car_model(env)
    check_model(md, env)
    obs = torch.tensor([[-0.5, 0.01]], dtype=torch.float32)
    assert mountain_car_state(obs) is obs
    with pytest.raises(ValueError, match=r"\(\*B, 2\)"):
        MountainCar().step(torch.zeros(3), torch.zeros(1))
    with pytest.raises(TypeError, match="dtype"):
        MountainCar().step(torch.zeros(2), torch.zeros(1, dtype=torch.float64))


def test_kick_pushes_a_car_near_the_floor():
    """Near the valley floor at rest the linear energy price barely pushes (u ∝ v ≈ 0); the kick term
    makes the MPC's first action a real push (the floor is at p = -π/6)."""
    torch.set_num_threads(1)
    x = torch.tensor([[-math.pi / 6 + 0.002, 0.0]], dtype=torch.float64)
    a = ModelMPC(mountain_car_model()).act(x)
    md = mountain_car_model()
    flat = dataclasses.replace(md, cost=lambda h, dtype=torch.float64, device=None: EnergyGoalCost(
        weight=1300.0, kick_weight=0.0))
    a0 = ModelMPC(flat).act(x)
    assert abs(float(a)) > 0.01 and abs(float(a)) > 20 * abs(float(a0))


def test_mpc_reaches_goal_from_one_start():
    torch.set_num_threads(1)
    env = gym.make("MountainCarContinuous-v0")
    env.reset(seed=0)
    env.unwrapped.state = np.array([-1.0, 0.03], dtype=np.float32)  # needs some pumping to get over
    obs = env.unwrapped.state.copy()
    pol = ModelMPC(mountain_car_model())
    pol.reset()
    ret, effort, terminated = 0.0, 0.0, False
    for _ in range(80):
        a = pol.act(torch.tensor(obs, dtype=torch.float64)[None])
        assert a.shape == (1, 1) and -1 <= float(a) <= 1
        obs, r, terminated, truncated, _ = env.step(a.numpy()[0].astype(np.float32))
        ret += r
        effort += float(a) ** 2
        if terminated:
            break
    assert terminated
    assert 0 < effort < 5 and ret == pytest.approx(100 - 0.1 * effort, abs=1e-4)
