"""Car parking and bicopter hover: gymnasium's and SB3's checkers, the vector env against the single env
(conformance suite, float64, every autoreset mode, through terminations), observation bounds under random
and bang-bang actions, the task definitions, and an iLQR MPC on the task's own model and cost solving both."""

import math
import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env as gym_check_env
from stable_baselines3.common.env_checker import check_env as sb3_check_env

import learning
from controllers.ilqr import ILQROptions, ILQRProblem, ilqr
from controllers.systems import Bicopter, Car
from learning import TASKS, TaskEnv, TaskVectorEnv
from learning.conformance import check_vector_env
from learning.envs.bicopter import BicopterHover
from learning.envs.car import CarParking

learning.register_envs()

NAMES = ["BicopterHover", "CarParking"]
D64 = torch.float64


@pytest.fixture
def one_thread():
    """Small batched solves on a shared 2-core machine: one intra-op thread avoids OpenMP contention."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def test_registered():
    assert TASKS["CarParking"] is CarParking and TASKS["BicopterHover"] is BicopterHover
    for name in NAMES:
        env = gym.make(learning.env_id(name))
        assert isinstance(env.unwrapped, TaskEnv) and env.spec.max_episode_steps == 200


@pytest.mark.parametrize("name", NAMES)
def test_checkers_pass_without_warnings(name):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        gym_check_env(gym.make(learning.env_id(name), render_mode="rgb_array").unwrapped)
        gym_check_env(gym.make(learning.env_id(name), dtype=D64, render_mode="rgb_array").unwrapped)
        sb3_check_env(TaskEnv(name, render_mode="rgb_array"))


@pytest.mark.parametrize("name", NAMES)
def test_vector_env_conformance_and_equivalence_float64(name):
    make = lambda mode: TaskVectorEnv(name, 5, max_episode_steps=13, autoreset_mode=mode,  # noqa: E731
                                      dtype=D64)
    single = lambda: gym.make(learning.env_id(name), max_episode_steps=13, dtype=D64)  # noqa: E731
    report = check_vector_env(make, single, tol=1e-12)
    assert len(report["checks"]) == 13


@pytest.mark.parametrize("name", NAMES)
def test_vector_equals_single_through_terminations(name):
    """Bang-bang actions crash bicopters and drive cars out of the lot or into the steering lock:
    terminations (not only time limits) are compared, NEXT_STEP autoreset, to 1e-12."""
    N = 6
    ours = TaskVectorEnv(name, N, max_episode_steps=500, dtype=D64)
    singles = [gym.make(learning.env_id(name), max_episode_steps=500, dtype=D64) for _ in range(N)]
    ours.reset(seed=4)
    for i, e in enumerate(singles):
        e.reset(seed=4 + i)
    rng = np.random.default_rng(0)
    prev = np.zeros(N, bool)
    terms = 0
    for k in range(250):
        bang = np.where(rng.uniform(size=(N, 2)) < 0.5, -1.0, 1.0)
        a = bang if (k // 20) % 2 else rng.uniform(-1, 1, (N, 2))
        o, r, te, tr, _ = ours.step(a)
        for i, e in enumerate(singles):
            if prev[i]:
                oi, _ = e.reset()
                ri, tei, tri = 0.0, False, False
            else:
                oi, ri, tei, tri, _ = e.step(a[i])
            np.testing.assert_allclose(o[i], oi, rtol=0, atol=1e-12)
            assert (r[i], te[i], tr[i]) == (pytest.approx(ri, abs=1e-12), tei, tri)
        prev = te | tr
        terms += int(te.sum())
    assert terms >= 3


@pytest.mark.parametrize("dtype", [torch.float32, D64])
@pytest.mark.parametrize("name", NAMES)
def test_observations_stay_within_obs_high_for_full_episodes(name, dtype):
    """Random and bang-bang (constant, alternating, differential) actions for full 200-step episodes,
    SAME_STEP autoreset so the last observation of every episode is checked too."""
    N = 64
    env = TaskVectorEnv(name, N, dtype=dtype, autoreset_mode="same_step", output="torch")
    space = env.single_observation_space
    high = torch.as_tensor(space.high, dtype=dtype)
    env.reset(seed=0)
    g = torch.Generator().manual_seed(1)
    patterns = torch.tensor([[1, 1], [-1, -1], [1, -1], [-1, 1]], dtype=dtype)
    ends = 0
    for k in range(400):
        if k < 200:
            a = torch.rand(N, 2, generator=g, dtype=dtype) * 2 - 1
        else:
            a = patterns[(torch.arange(N) + (k // 9)) % 4] * (1 if (k // 23) % 2 else -1)
        o, r, te, tr, info = env.step(a)
        assert (o.abs() <= high).all(), (k, o[(o.abs() > high).any(-1)])
        assert ((r >= 0) & (r <= 1)).all()
        if "final_obs" in info:
            fo = info["final_obs"][info["_final_obs"]]
            assert (fo.abs() <= high).all(), (k, fo)
            ends += int(info["_final_obs"].sum())
    assert ends > N  # episodes ended by termination as well as by the time limit


@pytest.mark.parametrize("name", NAMES)
def test_state_from_obs_round_trip_and_render(name):
    env = TaskEnv(name, dtype=D64, render_mode="rgb_array")
    env.reset(seed=3)
    f0 = env.render()
    for _ in range(10):
        o, *_ = env.step(env.action_space.sample())
        x = env.task.state_from_obs(torch.from_numpy(o)[None])
        np.testing.assert_allclose(env.task.observe(x)[0].numpy(), o, rtol=0, atol=1e-12)
        d = x[0].numpy() - env.state
        if name == "CarParking":
            d[2] = (d[2] + math.pi) % (2 * math.pi) - math.pi  # the heading, observed as cos/sin
            assert -math.pi < x[0, 2] <= math.pi
        np.testing.assert_allclose(d, 0, atol=1e-12)
    f1 = env.render()
    assert f0.shape == (256, 256, 3) and f0.dtype == np.uint8 and not np.array_equal(f0, f1)


def test_car_parking_definition():
    task = CarParking()
    assert isinstance(task.system, Car) and task.n == 5 and task.m == 2
    gen = torch.Generator().manual_seed(0)
    x0 = task.initial_state(torch.rand(1000, 3, dtype=D64, generator=gen))
    assert (x0[:, :2].abs() <= 2.0).all() and (x0[:, 2].abs() <= math.pi).all() and (x0[:, 3:] == 0).all()
    # a start may happen to be parked already (about 6e-5 of them: within 0.1 m and 0.1 rad): rare, not never
    assert not task.terminated(x0).any() and task.success(x0).double().mean() < 0.01
    parked = torch.tensor([[0.05, -0.05, 2 * math.pi + 0.05, 0.05, 0.3]], dtype=D64)
    assert task.success(parked).all() and task.error(parked).item() == pytest.approx(math.hypot(0.05, 0.05))
    for bad in ([0.2, 0, 0, 0, 0], [0, 0, 0.2, 0, 0], [0, 0, 0, 0.2, 0], [0, 0, math.pi, 0, 0]):
        assert not task.success(torch.tensor([bad], dtype=D64)).any()
    for out in ([5.1, 0, 0, 0, 0], [0, -5.1, 0, 0, 0], [0, 0, 0, 2.1, 0], [0, 0, 0, 0, -1.31]):
        assert task.terminated(torch.tensor([out], dtype=D64)).all()
    # the reward is largest parked, and a full action costs at most 20 %
    z = torch.zeros(1, 5, dtype=D64)
    assert task.reward(z, torch.zeros(1, 2, dtype=D64), z).item() == 1.0
    assert task.reward(z, torch.tensor([[1.0, 1.0]], dtype=D64), z).item() == pytest.approx(0.8)


def test_bicopter_hover_definition_and_thrust_mapping():
    task = BicopterHover()
    md = task.system
    assert isinstance(md, Bicopter) and md.hover_relative and task.n == 6 and task.m == 2
    assert task.u_max() == pytest.approx((2.5 * 9.81 / 2,) * 2)
    scale = task.u_scale(D64, "cpu")
    level = torch.zeros(1, 6, dtype=D64)
    # action -1: both rotors off (free fall); 0: hover; +1: thrust m g per rotor (climb at +g)
    for a, acc in ((-1.0, -9.81), (0.0, 0.0), (1.0, 9.81)):
        x1, u, *_ = task.transition(level, torch.full((1, 2), a, dtype=D64), scale)
        thrust = u + md.hover_thrust()
        assert ((thrust >= 0) & (thrust <= 2.5 * 9.81 + 1e-12)).all()
        assert md.acceleration(level, u)[0, 1].item() == pytest.approx(acc, abs=1e-12)
    assert torch.equal(task.step(level, torch.zeros(1, 2, dtype=D64)), level)
    with pytest.raises(ValueError, match="hover_relative"):
        BicopterHover(model=Bicopter())
    x0 = task.initial_state(torch.rand(1000, 6, dtype=D64, generator=torch.Generator().manual_seed(0)))
    assert not task.terminated(x0).any() and (x0[:, :2].abs() <= 1.5).all()
    for out in ([3.1, 0, 0, 0, 0, 0], [0, -3.1, 0, 0, 0, 0], [0, 0, 1.21, 0, 0, 0], [0, 0, 0, 0, 6.1, 0],
                [0, 0, 0, 0, 0, -10.1]):
        assert task.terminated(torch.tensor([out], dtype=D64)).all()
    assert task.success(torch.tensor([[0.05, 0.05, 0.05, 0.1, -0.1, 3.0]], dtype=D64)).all()
    assert not task.success(torch.tensor([[0.0, 0.0, 0.0, 0.2, 0.1, 0.0]], dtype=D64)).any()
    env = TaskEnv("BicopterHover", dtype=D64)
    env.reset(seed=0)
    for _ in range(200):  # full differential thrust: a tilt crash
        _, _, term, _, _ = env.step(np.array([1.0, -1.0]))
        if term:
            break
    assert term and abs(env.state[2]) > 1.2


def _mpc_episode(name: str, seeds, steps: int, horizon: int, period: int, iters: int = 5):
    """Receding-horizon iLQR on the task's system and ``mpc_cost`` in the vector env: every ``period``
    steps the plan is re-solved (warm-started by the previous one, shifted) from ``state_from_obs`` of the
    observation, and its controls are applied as normalized actions ``u / u_max``."""
    N = len(seeds)
    env = TaskVectorEnv(name, N, max_episode_steps=steps, dtype=D64, output="torch",
                        autoreset_mode="disabled")
    task = env.task
    obs, _ = env.reset(seed=list(seeds))
    cost = task.mpc_cost(horizon, dtype=D64)
    um = task.u_scale(D64, "cpu")
    u_warm, plan = None, None
    ended = torch.zeros(N, dtype=torch.bool)
    for k in range(steps):
        if k % period == 0:
            prob = ILQRProblem(task.system, cost, task.state_from_obs(obs), horizon, u_lower=-um, u_upper=um)
            sol = ilqr(prob, u_warm, method="batch", grad="none",
                       options=ILQROptions(max_iter=50 if k == 0 else iters))
            plan = sol.u
            u_warm = torch.cat([plan[:, period:], plan[:, -1:].expand(-1, period, -1)], 1)
        obs, r, te, tr, _ = env.step(plan[:, k % period] / um)
        assert not te.any(), f"{name}: an MPC episode terminated at step {k}"
        ended |= te | tr
    assert ended.all()
    x = env.state
    return task.success(x), task.error(x)


def test_mpc_solves_bicopter_hover(one_thread):
    ok, err = _mpc_episode("BicopterHover", range(4), steps=60, horizon=20, period=10)
    assert ok.all() and (err < 0.01).all(), err


def test_mpc_parks_the_car(one_thread):
    ok, err = _mpc_episode("CarParking", range(4), steps=120, horizon=40, period=10)
    assert ok.all() and (err < 0.05).all(), err


def test_car_safe_action_box_keeps_speed_and_steering_inside_the_limits():
    task = CarParking()
    g = torch.Generator().manual_seed(5)
    N = 4000
    # states anywhere up to the limits (and a little past them: the box must stay non-empty)
    x = torch.rand(N, 5, generator=g, dtype=D64) * 2 - 1
    x[:, 3] *= task.speed_limit * 1.02
    x[:, 4] *= task.steer_limit * 1.02
    lo, hi = task.safe_action_box(x)
    assert lo.shape == hi.shape == (N, 2) and bool((lo <= hi).all())
    assert bool((lo >= -1).all()) and bool((hi <= 1).all())
    inside = (x[:, 3].abs() <= task.speed_limit - task.safety_margin) & \
        (x[:, 4].abs() <= task.steer_limit - task.safety_margin)
    # from inside, every action of the box keeps the next state inside (corners and random points)
    um = task.u_scale(D64, "cpu")
    for w in (torch.zeros(N, 2, dtype=D64), torch.ones(N, 2, dtype=D64),
              torch.rand(N, 2, generator=g, dtype=D64), torch.tensor([[0.0, 1.0]], dtype=D64).expand(N, 2)):
        a = lo + w * (hi - lo)
        nxt = task.step(x, a * um)
        assert not task.terminated(nxt)[inside].any()
        assert bool((nxt[inside, 3].abs() <= task.speed_limit - task.safety_margin + 1e-12).all())
    # the box only cuts where it must: far from the limits it is the whole action space
    calm = (x[:, 3].abs() < 1.0) & (x[:, 4].abs() < 1.0)
    assert bool((lo[calm] == -1).all()) and bool((hi[calm] == 1).all())


def test_car_expert_respects_the_steering_lock_where_the_unfiltered_mpc_crossed_it(one_thread):
    """Held-out episode 1000005 of `liecontrol compare CarParking`: the unfiltered MPC expert steered past
    the lock at step 17 (the episode terminated); filtered, it goes on and never leaves the box."""
    from learning.policies import task_expert

    task = CarParking()
    env = TaskVectorEnv(task, num_envs=1, dtype=D64)
    obs, _ = env.reset(seed=[1000005])
    pol = task_expert(task)
    for _ in range(40):
        o = torch.as_tensor(obs)
        a = pol.act(o)
        lo, hi = task.safe_action_box(task.state_from_obs(o))
        assert bool(((a >= lo) & (a <= hi)).all())
        obs, _, te, tr, _ = env.step(a.numpy())
        assert not te.any()
    assert abs(float(env.state[0, 4])) <= task.steer_limit - task.safety_margin + 1e-12
