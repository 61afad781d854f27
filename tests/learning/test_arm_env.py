"""The arm-reaching task: env checkers, the vector env against SyncVectorEnv over the single env (float64,
1e-12, all autoreset modes), observation bounds under extreme actions, the target carried in the state,
obstacles, and an iLQR MPC with the task's own cost reaching the targets."""

import math
import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env as gym_check_env
from stable_baselines3.common.env_checker import check_env as sb3_check_env
from torch.func import jacrev, vmap

import learning
from controllers.ilqr import ILQROptions
from controllers.mpc import run_mpc
from controllers.systems import PlanarArm
from learning import TaskEnv, TaskVectorEnv
from learning._counter_rng import keys_of_seeds, uniforms
from learning.conformance import check_vector_env
from learning.envs import TASKS, ArmReach

learning.register_envs()

D64 = torch.float64
NAME = "ArmReach"
THREE = dict(model=PlanarArm(links=3, lengths=(0.4, 0.35, 0.25), masses=(1.0, 0.8, 0.5), damping=0.05,
                             gravity=9.81, dt=0.05),
             obstacles=((0.0, 0.6, 0.1), (-0.5, -0.3, 0.15)), terminate_on_collision=True)
VARIANTS = {"default": {}, "three_links_obstacles": THREE, "slow": dict(speed_limit=2.0)}


def test_registered():
    assert TASKS[NAME] is ArmReach and learning.env_id(NAME) in gym.registry


@pytest.mark.parametrize("variant", ["default", "three_links_obstacles"])
def test_checkers_pass_without_warnings(variant):
    kw = VARIANTS[variant]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        gym_check_env(gym.make(learning.env_id(NAME), render_mode="rgb_array", task_kwargs=kw).unwrapped)
        sb3_check_env(TaskEnv(NAME, kw, render_mode="rgb_array"))


@pytest.mark.parametrize("variant", sorted(VARIANTS))
def test_conformance_and_equivalence_to_the_single_env(variant):
    kw = VARIANTS[variant]
    make = lambda mode: TaskVectorEnv(NAME, 5, task_kwargs=kw, max_episode_steps=13, autoreset_mode=mode,
                                      dtype=D64)
    single = lambda: gym.make(learning.env_id(NAME), max_episode_steps=13, dtype=D64, task_kwargs=kw)
    report = check_vector_env(make, single, tol=1e-12)
    assert len(report["checks"]) == 13


def test_equivalence_through_terminations():
    """Bang-bang torques exceed the speed limit: terminations (not only time limits) are compared."""
    kw = VARIANTS["slow"]
    ours = TaskVectorEnv(NAME, 4, task_kwargs=kw, dtype=D64)
    singles = [TaskEnv(NAME, kw, dtype=D64) for _ in range(4)]
    ours.reset(seed=7)
    for i, e in enumerate(singles):
        e.reset(seed=7 + i)
    terms, prev = 0, np.zeros(4, bool)
    for k in range(120):
        a = np.tile(np.array([1.0, -1.0]) * (1 if (k // 15) % 2 else -1), (4, 1))
        o, r, te, tr, _ = ours.step(a)
        for i, e in enumerate(singles):
            if prev[i]:  # NEXT_STEP: ours resets on this step
                oi, _ = e.reset()
                ri, tei = 0.0, False
            else:
                oi, ri, tei, _, _ = e.step(a[i])
            np.testing.assert_allclose(o[i], oi, rtol=0, atol=1e-12)
            assert r[i] == pytest.approx(ri, abs=1e-9) and te[i] == tei
        prev = te | tr
        terms += int(te.sum())
    assert terms >= 4


@pytest.mark.parametrize("dtype", [torch.float32, D64])
@pytest.mark.parametrize("variant", sorted(VARIANTS))
def test_observations_stay_in_the_space_under_random_and_extreme_actions(variant, dtype):
    env = gym.make(learning.env_id(NAME), task_kwargs=VARIANTS[variant], dtype=dtype)
    m = env.action_space.shape[0]
    rng = np.random.default_rng(0)
    for policy in ("random", "bang"):
        env.reset(seed=1)
        episodes = 0
        for k in range(400):
            a = (rng.uniform(-1, 1, m) if policy == "random"
                 else np.where(np.arange(m) % 2 == (k // 9) % 2, 1.0, -1.0))
            o, r, term, trunc, _ = env.step(a.astype(env.action_space.dtype))
            assert env.observation_space.contains(o), (policy, k, o)
            assert math.isfinite(r)
            if term or trunc:
                episodes += 1
                env.reset()
        assert episodes >= 3


def test_state_from_observation_round_trip_and_the_target_is_constant():
    env = TaskEnv(NAME, VARIANTS["three_links_obstacles"], dtype=D64)
    env.reset(seed=3)
    target = env.state[6:]
    for _ in range(30):
        o, *_ = env.step(env.action_space.sample())
        x = env.task.state_from_obs(torch.from_numpy(o)[None])[0].numpy()
        d = x - env.state
        d[:3] = (d[:3] + math.pi) % (2 * math.pi) - math.pi
        np.testing.assert_allclose(d, 0, atol=1e-12)
        np.testing.assert_array_equal(env.state[6:], target)
        ee = env.task.end_effector(torch.from_numpy(env.state)[None])[0].numpy()
        np.testing.assert_allclose(o[-2:], ee - target, atol=1e-12)


def test_initial_targets_lie_in_the_annulus_and_the_system_jacobian_is_exact():
    task = ArmReach()
    N = 500
    x0 = task.initial_state(uniforms(keys_of_seeds(torch.arange(N)), torch.zeros(N, dtype=torch.int64),
                                     task.n_noise, D64))
    rho = torch.linalg.vector_norm(x0[:, 4:], dim=-1)
    assert float(rho.min()) >= 0.25 * task.reach - 1e-12 and float(rho.max()) <= 0.9 * task.reach + 1e-12
    assert float(x0[:, 2:4].abs().max()) == 0.0
    sys_ = task.system
    assert sys_.n == 6 and sys_.m == 2 and sys_.time_invariant and sys_.dt == task.model.dt
    gen = torch.Generator().manual_seed(0)
    x, u = torch.randn(8, 6, generator=gen, dtype=D64), torch.randn(8, 2, generator=gen, dtype=D64)
    A, B = sys_.jacobian(x, u)
    torch.testing.assert_close(A, vmap(jacrev(sys_.step, argnums=0))(x, u), atol=1e-10, rtol=1e-10)
    torch.testing.assert_close(B, vmap(jacrev(sys_.step, argnums=1))(x, u), atol=1e-10, rtol=1e-10)


def test_obstacles_penalty_collisions_and_termination():
    task = ArmReach(obstacles=((0.5, 0.0, 0.1),))
    # stretched along +x: link 2 (0.5..1.0) passes through the obstacle's center, link 1 touches it
    x_hit = torch.tensor([[0.0, 0.0, 0.0, 0.0, 0.0, 0.5]], dtype=D64)
    x_free = torch.tensor([[math.pi / 2, 0.0, 0.0, 0.0, 0.0, 0.5]], dtype=D64)
    pen = task.penetration(x_hit)
    assert pen.shape == (1, 1, 2)
    torch.testing.assert_close(pen, torch.full((1, 1, 2), 0.1, dtype=D64), atol=1e-5, rtol=0)
    assert task.collisions(x_hit).item() == 2 and task.collisions(x_free).item() == 0
    u = torch.zeros(1, 2, dtype=D64)
    r_hit = task.reward(x_hit, u, x_hit)
    r_ref = -(1.0 + 0.5**2) - 100.0 * pen.pow(2).sum()  # |ee - target|² + w_o Σ pen²
    torch.testing.assert_close(r_hit, r_ref.reshape(1), atol=1e-9, rtol=0)
    assert not task.terminated(x_hit).item()
    stop = ArmReach(obstacles=((0.5, 0.0, 0.1),), terminate_on_collision=True)
    assert stop.terminated(x_hit).item() and not stop.terminated(x_free).item()
    # ending an episode early never pays: the terminating step costs more than any whole episode
    assert float(stop.reward(x_hit, u, x_hit)) < -stop.max_episode_steps * stop.max_step_cost()
    fast = torch.tensor([[math.pi / 2, 0.0, 0.0, 11.0, 0.0, 0.5]], dtype=D64)
    assert task.terminated(fast).item()


def test_render_draws_the_arm_and_the_target():
    env = TaskEnv(NAME, VARIANTS["three_links_obstacles"], render_mode="rgb_array")
    env.reset(seed=0)
    f0 = env.render()
    assert f0.shape == (256, 256, 3) and f0.dtype == np.uint8
    for _ in range(10):
        env.step(np.ones(3, np.float32))
    f1 = env.render()
    assert (f0 != 255).any() and not np.array_equal(f0, f1)
    assert (f1 == np.array([60, 170, 60], np.uint8)).all(-1).any()  # the target


def test_mpc_with_the_task_cost_reaches_the_targets():
    """Receding-horizon iLQR (horizon 12, 3 warm-started iterations per step) from the task's own
    ``mpc_cost`` on the task's system, from the first states of four seeded episodes: every target is
    reached and the arm stopped (the task's success) within 40 steps (2 s), within the torque limits."""
    task = ArmReach()
    N, T = 4, 12
    x0 = task.initial_state(uniforms(keys_of_seeds(torch.arange(N)), torch.zeros(N, dtype=torch.int64),
                                     task.n_noise, D64))
    assert float(task.error(x0).min()) > 0.3
    roll = run_mpc(task.system, task.mpc_cost(T), x0, T, 40, u_lower=-task.max_torque,
                   u_upper=task.max_torque, options=ILQROptions(max_iter=3))
    xf = roll.x[:, -1]
    assert bool(task.success(xf).all()), (task.error(xf), xf[:, 2:4])
    assert float(roll.u.abs().max()) <= task.max_torque + 1e-12
    assert not bool(task.terminated(roll.x).any())
    torch.testing.assert_close(roll.x[..., 4:], x0[:, None, 4:].expand(-1, 41, -1), atol=0, rtol=0)


VIA = dict(via_points=2, max_episode_steps=150)


def test_via_points_checkers_conformance_and_state_round_trip():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        gym_check_env(gym.make(learning.env_id(NAME), render_mode="rgb_array", task_kwargs=VIA).unwrapped)
        sb3_check_env(TaskEnv(NAME, VIA, render_mode="rgb_array"))
    make = lambda mode: TaskVectorEnv(NAME, 5, task_kwargs=VIA, max_episode_steps=13, autoreset_mode=mode,  # noqa: E731
                                      dtype=D64)
    single = lambda: gym.make(learning.env_id(NAME), max_episode_steps=13, dtype=D64, task_kwargs=VIA)  # noqa: E731
    assert len(check_vector_env(make, single, tol=1e-12)["checks"]) == 13
    env = TaskEnv(NAME, VIA, dtype=D64)
    env.reset(seed=2)
    assert env.observation_space.shape == (3 * 2 + 4 + 2 * 2 + 5,)
    for _ in range(20):
        o, *_ = env.step(env.action_space.sample())
        x = env.task.state_from_obs(torch.from_numpy(o)[None])[0].numpy()
        d = x - env.state
        d[:2] = (d[:2] + math.pi) % (2 * math.pi) - math.pi
        np.testing.assert_allclose(d, 0, atol=1e-12)


def test_via_points_are_passed_in_order_and_distance_to_go_never_grows():
    """Hand-placed states of a 2-link arm (reach 1): the counter advances only inside the radius of the
    *next* via-point, the distance to go is |ee − w_j| + the remaining legs, and passing a via-point never
    increases it."""
    task = ArmReach(via_points=2)
    sys_ = task.system
    # target (0, -0.8), via 1 at (1, 0) (the stretched arm's tip), via 2 at (0, 0.8); j = 0, at rest
    x = torch.tensor([[0.0, 0.0, 0.0, 0.0, 0.0, -0.8, 1.0, 0.0, 0.0, 0.8, 0.0]], dtype=D64)
    legs = math.hypot(1.0, 0.8) + 1.6
    assert task.distance_to_go(x).item() == pytest.approx(0.0 + legs)
    assert sys_.step(x, torch.zeros(1, 2, dtype=D64))[0, -1].item() == 0.0  # the system holds j
    y = task.step(x, torch.zeros(1, 2, dtype=D64))
    assert y[0, -1].item() == 1.0  # the tip sits on via 1: the task's event passes it
    assert task.distance_to_go(y).item() == pytest.approx(math.hypot(1.0, 0.8) + 1.6, abs=1e-9)
    assert task.distance_to_go(y).item() <= task.distance_to_go(x).item() + 1e-12
    # a state on via 2 while via 1 is still pending: nothing is passed (order matters)
    x2 = x.clone()
    x2[0, 0], x2[0, 9] = math.pi / 2, 1.0  # the tip on via 2, moved to (0, 1)
    y2 = task.step(x2, torch.zeros(1, 2, dtype=D64))
    assert y2[0, -1].item() == 0.0
    # success needs every via-point: at the target with j < V it is not a success
    at_target = torch.tensor([[-math.pi / 2, 0.0, 0.0, 0.0, 0.0, -1.0, 1.0, 0.0, 0.0, 0.8, 1.0]], dtype=D64)
    assert not task.success(at_target).item()
    at_target[0, -1] = 2.0
    assert task.success(at_target).item() and task.error(at_target).item() < 1e-12
    # j saturates at V
    assert task.step(at_target, torch.zeros(1, 2, dtype=D64))[0, -1].item() == 2.0
    # the reward is minus the squared distance to go (plus the control cost)
    r = task.reward(x, torch.zeros(1, 2, dtype=D64), y)
    assert r.item() == pytest.approx(-task.distance_to_go(y).item() ** 2)


def test_via_points_initial_states_and_observation_bounds():
    task = ArmReach(via_points=3)
    N = 400
    x0 = task.initial_state(uniforms(keys_of_seeds(torch.arange(N)), torch.zeros(N, dtype=torch.int64),
                                     task.n_noise, D64))
    pts, j = task.system.waypoints(x0)
    rho = torch.linalg.vector_norm(pts, dim=-1)
    assert float(rho.min()) >= 0.25 * task.reach - 1e-12 and float(rho.max()) <= 0.9 * task.reach + 1e-12
    assert (j == 0).all() and (x0[:, -1] == 0).all()
    # the via-points are not the target's copy: independent draws
    assert float((pts[:, 0] - pts[:, -1]).norm(dim=-1).min()) > 0
    env = gym.make(learning.env_id(NAME), task_kwargs=dict(via_points=3))
    rng = np.random.default_rng(0)
    env.reset(seed=0)
    for _ in range(300):
        o, r, te, tr, _ = env.step(rng.uniform(-1, 1, 2).astype(np.float32))
        assert env.observation_space.contains(o)
        if te or tr:
            env.reset()


def test_mpc_passes_the_via_points_and_reaches_the_target():
    """The task's expert (iLQR MPC on the task's system towards the next waypoint) on seeded episodes: every
    via-point passed in order and the target reached."""
    task = ArmReach(via_points=2, max_episode_steps=110)
    expert = learning.MPCExpert(task, horizon=15, max_iter=3)
    res = learning.evaluate(expert, task, num_envs=3, episodes=3, progress=False, timing_batch1=False)
    assert res.summary()["success_rate"] == 1.0, res.final_error
