"""SE(3) end-effector reaching with the Panda: gymnasium's and SB3's checkers, observation bounds (joint
limits hit on purpose), the task's errors against an independent DH forward kinematics, the expert (SE(3)
pose MPC + resolved rate) batched == per-sample and reaching every goal (the vector-env conformance suite
runs in test_vector for every task)."""

import math
import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env as gym_check_env
from stable_baselines3.common.env_checker import check_env as sb3_check_env

import learning
from controllers.systems.panda import PANDA_DQ_MAX, Panda
from learning import TASKS, TaskEnv, TaskVectorEnv, evaluate
from learning.envs.panda_reach import PandaReach, PandaReachExpert
from learning.policies import as_policy

learning.register_envs()

NAME = "PandaReach"
D64 = torch.float64


def test_registered_and_checkers_pass_without_warnings():
    assert TASKS[NAME] is PandaReach
    env = gym.make(learning.env_id(NAME))
    assert isinstance(env.unwrapped, TaskEnv) and env.spec.max_episode_steps == 100
    assert env.observation_space.shape == (25,) and env.action_space.shape == (7,)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        gym_check_env(gym.make(learning.env_id(NAME), render_mode="rgb_array").unwrapped)
        gym_check_env(gym.make(learning.env_id(NAME), dtype=D64, render_mode="rgb_array").unwrapped)
        sb3_check_env(TaskEnv(NAME, render_mode="rgb_array"))


@pytest.mark.parametrize("dtype", [torch.float32, D64])
def test_observations_stay_within_obs_high(dtype):
    """Full-speed constant actions drive every joint into its limits (the step clips there)."""
    N = 32
    env = TaskVectorEnv(NAME, N, dtype=dtype, max_episode_steps=60, autoreset_mode="same_step",
                        output="torch")
    high = torch.as_tensor(env.single_observation_space.high, dtype=dtype)
    lo, hi = Panda.joint_limits(dtype)
    env.reset(seed=0)
    g = torch.Generator().manual_seed(1)
    at_limit = torch.zeros(7, dtype=torch.bool)
    for k in range(120):
        a = torch.rand(N, 7, generator=g, dtype=dtype) * 2 - 1 if k % 60 < 20 else \
            torch.where(torch.arange(N)[:, None] % 2 == 0, 1.0, -1.0).to(dtype).expand(N, 7)
        o, r, te, tr, info = env.step(a)
        assert (o.abs() <= high).all(), (k, o[(o.abs() > high).any(-1)])
        assert (r <= 0).all() and not te.any()
        q = o[:, :7]
        assert ((q >= lo) & (q <= hi)).all()
        at_limit |= ((q == lo) | (q == hi)).any(0)
    assert at_limit.all()  # every joint was driven into a limit


def test_state_round_trip_errors_and_render():
    """The observation's errors against an independent forward kinematics (the DH product, not
    pytorch-kinematics), and the state recovered exactly from the observation."""
    env = TaskEnv(NAME, dtype=D64, render_mode="rgb_array")
    env.reset(seed=5)
    f0 = env.render()
    for _ in range(5):
        o, *_ = env.step(env.action_space.sample())
        x = env.task.state_from_obs(torch.from_numpy(o)[None])
        np.testing.assert_array_equal(x[0].numpy(), env.state)
        T = Panda().fk_dh(x[:, :7])[0]
        goal = env.task.goal(x)[0]
        np.testing.assert_allclose(o[7:10], (goal[:3, 3] - T[:3, 3]).numpy(), rtol=0, atol=1e-12)
        # log(Rᵀ R*) by an independent route: the rotation angle from the trace
        Rerr = T[:3, :3].T @ goal[:3, :3]
        angle = math.acos(max(-1.0, min(1.0, (float(torch.trace(Rerr)) - 1) / 2)))
        assert np.linalg.norm(o[10:13]) == pytest.approx(angle, abs=1e-9)
    f1 = env.render()
    assert f0.shape == (256, 256, 3) and f0.dtype == np.uint8 and not np.array_equal(f0, f1)


def test_task_definition():
    task = PandaReach()
    gen = torch.Generator().manual_seed(0)
    x0 = task.initial_state(torch.rand(200, 14, dtype=D64, generator=gen))
    home = Panda.home(D64)
    assert ((x0[:, :7] - home).abs() <= task.spread + 1e-12).all()
    goal = task.goal(x0)
    torch.testing.assert_close(goal[:, :3, :3] @ goal[:, :3, :3].transpose(-1, -2),
                               torch.eye(3, dtype=D64).expand(200, 3, 3), rtol=0, atol=1e-12)
    assert not task.success(x0).any()  # two independent configurations: never the same pose
    # the goal of the start configuration itself: reached, reward 0 with zero action
    T = task.robot.fk(x0[:, :7])
    at = torch.cat([x0[:, :7], T[:, :3, 3], T[:, :3, :3].flatten(-2)], -1)
    assert task.success(at).all() and (task.error(at) < 1e-12).all()
    z = torch.zeros(200, 7, dtype=D64)
    assert (task.reward(at, z, at).abs() < 1e-9).all()
    full = task.u_scale(D64, "cpu").expand(200, 7)
    torch.testing.assert_close(task.reward(at, full, at), torch.full((200,), -0.01, dtype=D64), atol=1e-9,
                               rtol=0)
    assert task.u_max() == pytest.approx(PANDA_DQ_MAX)
    # the step is the clipped integrator
    y = task.step(x0, full)
    lo, hi = Panda.joint_limits(D64)
    torch.testing.assert_close(y[:, :7], torch.minimum(torch.maximum(x0[:, :7] + task.dt * full, lo), hi))
    torch.testing.assert_close(y[:, 7:], x0[:, 7:], rtol=0, atol=0)
    with pytest.raises(ValueError, match="spread"):
        PandaReach(spread=0.0)
    with pytest.raises(NotImplementedError, match="pose MPC"):
        task.mpc_cost(5)


def test_expert_batched_equals_per_sample():
    task = PandaReach()
    x = task.initial_state(torch.rand(4, 14, dtype=D64, generator=torch.Generator().manual_seed(3)))
    obs = task.observe(x)
    batched = PandaReachExpert(task).act(obs)
    single = torch.cat([PandaReachExpert(task).act(obs[i:i + 1]) for i in range(4)])
    torch.testing.assert_close(batched, single, rtol=0, atol=1e-10)
    assert batched.abs().max() <= 1 + 1e-12  # joint speeds within the limits
    a32 = PandaReachExpert(task).act(obs.float())
    assert a32.dtype == torch.float32 and (a32.double() - batched).abs().max() < 1e-3
    assert isinstance(as_policy("mpc", task), PandaReachExpert)


def test_expert_reaches_every_goal_pose():
    res = evaluate("mpc", NAME, num_envs=8, episodes=8, progress=False, timing_batch1=False)
    s = res.summary()
    assert s["success_rate"] == 1.0 and s["nonconverged_rate"] == 0.0
    assert s["final_error"]["max"] < 1e-3


def test_expert_a_nan_joint_angle_poisons_only_its_element():
    """One NaN joint angle used to fail the SVD of the whole batch (the DLS null-space projector)."""
    task = PandaReach()
    gen = torch.Generator().manual_seed(4)
    obs = task.observe(task.initial_state(torch.rand(3, 14, dtype=D64, generator=gen)))
    clean = PandaReachExpert(task).act(obs)
    obs[1, 2] = math.nan
    expert = PandaReachExpert(task)
    a = expert.act(obs)
    assert torch.isnan(a[1]).all() and expert.info()["converged"].tolist() == [True, False, True]
    torch.testing.assert_close(a[[0, 2]], clean[[0, 2]], rtol=0, atol=0)
