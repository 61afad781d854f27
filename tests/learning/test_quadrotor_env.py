"""Quadrotor tracking envs (circle, figure-eight) on R³×R³×SO(3): gymnasium's and SB3's checkers, the vector
env against the single env through crashes (the conformance suite runs in test_vector for every task),
observation bounds, the task's dynamics against the quadrotor model stepped on its manifold, the tabulated
reference against finite differences of the position, and the error-state MPC expert: batched ==
per-sample, float32, and it tracks both laps."""

import math
import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env as gym_check_env
from stable_baselines3.common.env_checker import check_env as sb3_check_env

import learning
from controllers.manifold_mpc import manifold_rollout
from learning import TASKS, TaskEnv, TaskVectorEnv, evaluate
from learning.envs.quadrotor import QuadrotorFigureEight, QuadrotorTrack, QuadrotorTrackingExpert
from learning.policies import as_policy, task_expert
from torchlie import so3

learning.register_envs()

NAMES = ["QuadrotorCircle", "QuadrotorFigureEight"]
D64 = torch.float64


def test_registered():
    assert TASKS["QuadrotorCircle"] is QuadrotorTrack
    assert TASKS["QuadrotorFigureEight"] is QuadrotorFigureEight
    for name in NAMES:
        env = gym.make(learning.env_id(name))
        assert isinstance(env.unwrapped, TaskEnv) and env.spec.max_episode_steps == 250
        assert env.observation_space.shape == (17,) and env.action_space.shape == (4,)


@pytest.mark.parametrize("name", NAMES)
def test_checkers_pass_without_warnings(name):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        gym_check_env(gym.make(learning.env_id(name), render_mode="rgb_array").unwrapped)
        gym_check_env(gym.make(learning.env_id(name), dtype=D64, render_mode="rgb_array").unwrapped)
        sb3_check_env(TaskEnv(name, render_mode="rgb_array"))


def test_vector_equals_single_through_crashes():
    """Bang-bang body rates flip vehicles over and full thrust flies them off the track: terminations are
    compared step for step (NEXT_STEP autoreset) to 1e-12, the clock wrapping included."""
    N, name = 5, "QuadrotorFigureEight"
    ours = TaskVectorEnv(name, N, max_episode_steps=600, dtype=D64)
    singles = [gym.make(learning.env_id(name), max_episode_steps=600, dtype=D64) for _ in range(N)]
    ours.reset(seed=11)
    for i, e in enumerate(singles):
        e.reset(seed=11 + i)
    rng = np.random.default_rng(0)
    prev = np.zeros(N, bool)
    terms = 0
    for k in range(300):
        bang = np.where(rng.uniform(size=(N, 4)) < 0.5, -1.0, 1.0)
        a = rng.uniform(-1, 1, (N, 4)) if (k // 30) % 2 else bang
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
    assert terms >= 5


@pytest.mark.parametrize("dtype", [torch.float32, D64])
@pytest.mark.parametrize("name", NAMES)
def test_observations_stay_within_obs_high(name, dtype):
    N = 48
    env = TaskVectorEnv(name, N, dtype=dtype, autoreset_mode="same_step", output="torch")
    high = torch.as_tensor(env.single_observation_space.high, dtype=dtype)
    env.reset(seed=0)
    g = torch.Generator().manual_seed(1)
    ends = 0
    for k in range(300):
        if k < 150:
            a = torch.rand(N, 4, generator=g, dtype=dtype) * 2 - 1
        else:
            a = torch.where(torch.rand(N, 4, generator=g, dtype=dtype) < 0.5, -1.0, 1.0).to(dtype)
        o, r, te, tr, info = env.step(a)
        assert (o.abs() <= high).all(), (k, o[(o.abs() > high).any(-1)])
        assert ((r >= 0) & (r <= 1)).all()
        if "final_obs" in info:
            fo = info["final_obs"][info["_final_obs"]]
            assert (fo.abs() <= high).all(), (k, fo)
            ends += int(info["_final_obs"].sum())
    assert ends > N


@pytest.mark.parametrize("name", NAMES)
def test_state_from_obs_round_trip_and_render(name):
    env = TaskEnv(name, dtype=D64, render_mode="rgb_array")
    env.reset(seed=3)
    f0 = env.render()
    for _ in range(10):
        o, *_ = env.step(env.action_space.sample())
        x = env.task.state_from_obs(torch.from_numpy(o)[None])
        np.testing.assert_allclose(x[0].numpy(), env.state, rtol=0, atol=1e-12)
    f1 = env.render()
    assert f0.shape == (256, 256, 3) and f0.dtype == np.uint8 and not np.array_equal(f0, f1)


def test_dynamics_are_the_quadrotor_model_on_its_manifold():
    """The flat env step equals the Quadrotor stepped on R³×R³×SO(3) (manifold_rollout), with the thrust
    offset by g; R stays a rotation; the clock wraps at the period."""
    task = QuadrotorTrack(period_steps=100, max_episode_steps=100)
    gen = torch.Generator().manual_seed(0)
    x0 = task.initial_state(torch.rand(6, 10, dtype=D64, generator=gen))
    a = torch.rand(6, 30, 4, dtype=D64, generator=gen) * 2 - 1
    u = a * task.u_scale(D64, "cpu")
    x = x0
    for k in range(30):
        x = task.step(x, u[:, k])
    quad = task.system.quad
    u_phys = u + torch.tensor([quad.gravity, 0, 0, 0], dtype=D64)
    traj = manifold_rollout(quad, task.system.point(x0), u_phys)
    end = traj[:, -1]
    torch.testing.assert_close(x[:, 0:3], end["p"], rtol=0, atol=1e-12)
    torch.testing.assert_close(x[:, 3:6], end["v"], rtol=0, atol=1e-12)
    R = x[:, 6:15].reshape(-1, 3, 3)
    torch.testing.assert_close(R, end["R"], rtol=0, atol=1e-12)
    torch.testing.assert_close(R @ R.transpose(-1, -2), torch.eye(3, dtype=D64).expand(6, 3, 3), atol=1e-12,
                               rtol=0)
    assert (x0[:, 15] + 30 >= 100).any() and (x0[:, 15] + 30 < 100).any()  # some clocks wrapped
    torch.testing.assert_close(x[:, 15], torch.remainder(x0[:, 15] + 30, 100))


@pytest.mark.parametrize("shape", ["circle", "figure8"])
def test_reference_table_against_finite_differences(shape):
    """The tabulated velocity is the derivative of the position (central differences of the task's own
    position function), the attitude's third column is the thrust direction, and the lap closes."""
    task = QuadrotorTrack(shape=shape)
    ref = task.reference(D64)
    t = torch.arange(task.period_steps, dtype=D64) * task.dt
    h = 1e-5
    fd = torch.stack([(task.position(s + h) - task.position(s - h)) / (2 * h) for s in t])
    torch.testing.assert_close(ref["v"], fd, rtol=0, atol=1e-8)
    p_lap = torch.stack([task.position(s) for s in t + task.period_steps * task.dt])
    torch.testing.assert_close(p_lap, ref["p"], rtol=0, atol=1e-12)
    a = torch.stack([(task.position(s + h) - 2 * task.position(s) + task.position(s - h)) / h**2 for s in t])
    f = torch.tensor([0, 0, task.gravity], dtype=D64) - a
    torch.testing.assert_close(ref["R"][:, :, 2], f / f.norm(dim=-1, keepdim=True), rtol=0, atol=1e-4)
    torch.testing.assert_close(ref["u"][:, 0], f.norm(dim=-1), rtol=0, atol=1e-4)


def test_task_definition():
    task = QuadrotorTrack()
    ref = task.reference(D64)
    k = torch.tensor([0.0, 17.0, 249.0], dtype=D64)
    x = torch.cat([ref["p"][k.long()], ref["v"][k.long()], ref["R"][k.long()].reshape(3, 9), k[:, None]], -1)
    assert (task.error(x) == 0).all() and task.success(x).all() and not task.terminated(x).any()
    z = torch.zeros(3, 4, dtype=D64)
    torch.testing.assert_close(task.reward(x, z, x), torch.ones(3, dtype=D64))
    full = task.u_scale(D64, "cpu").expand(3, 4)
    torch.testing.assert_close(task.reward(x, full, x), torch.full((3,), 0.95, dtype=D64))
    off = x.clone()
    off[:, 1] += 0.2
    torch.testing.assert_close(task.reward(off, z, off), torch.full((3,), 0.5, dtype=D64))
    assert not task.success(off).any() and task.error(off) == pytest.approx(0.2)
    for i, d in ((0, 2.01), (4, -4.01)):
        y = x.clone()
        y[:, i] += d
        assert task.terminated(y).all()
    flipped = x.clone()
    flipped[:, 6:15] = (ref["R"][k.long()] @ so3.exp(torch.tensor([math.pi, 0, 0], dtype=D64))).reshape(3, 9)
    assert task.terminated(flipped).all()
    # initial states: inside the crash limits, level within the tilt, integer phase
    x0 = task.initial_state(torch.rand(500, 10, dtype=D64, generator=torch.Generator().manual_seed(0)))
    assert not task.terminated(x0).any() and (x0[:, 15] == x0[:, 15].round()).all()
    assert so3.angle(x0[:, 6:15].reshape(-1, 3, 3)).max() <= math.sqrt(3) * 0.2 + 1e-12


def test_bad_arguments():
    with pytest.raises(ValueError, match="shape"):
        QuadrotorTrack(shape="square")
    with pytest.raises(ValueError, match="period_steps"):
        QuadrotorTrack(period_steps=4)
    with pytest.raises(ValueError, match="beyond the limits"):
        QuadrotorTrack(period_steps=20)  # a 0.4 s lap needs more than 2 g
    with pytest.raises(NotImplementedError, match="error-state MPC"):
        QuadrotorTrack().mpc_cost(10)


def test_expert_batched_equals_per_sample_and_float32():
    task = QuadrotorFigureEight()
    x = task.initial_state(torch.rand(5, 10, dtype=D64, generator=torch.Generator().manual_seed(2)))
    obs = task.observe(x)
    batched = QuadrotorTrackingExpert(task).act(obs)
    single = torch.cat([QuadrotorTrackingExpert(task).act(obs[i:i + 1]) for i in range(5)])
    torch.testing.assert_close(batched, single, rtol=0, atol=1e-10)
    a32 = QuadrotorTrackingExpert(task).act(obs.float())
    assert a32.dtype == torch.float32
    torch.testing.assert_close(a32.double(), batched, rtol=0, atol=2e-3)
    assert isinstance(as_policy("mpc", task), QuadrotorTrackingExpert)
    assert task_expert(task, 12).horizon == 12


@pytest.mark.parametrize("name", NAMES)
def test_expert_tracks_both_laps(name):
    """Full episodes from offset starts (0.3 m, 0.3 m/s, 0.2 rad): every vehicle on the lap within 1 cm at
    the end, no crash, every QP certified."""
    res = evaluate("mpc", name, num_envs=6, episodes=6, progress=False, timing_batch1=False)
    s = res.summary()
    assert s["success_rate"] == 1.0 and s["terminated_rate"] == 0.0 and s["nonconverged_rate"] == 0.0
    assert s["final_error"]["max"] < 0.01


def test_expert_a_nan_observation_poisons_only_its_element():
    task = QuadrotorTrack()
    gen = torch.Generator().manual_seed(4)
    obs = task.observe(task.initial_state(torch.rand(3, 10, dtype=D64, generator=gen)))
    clean = QuadrotorTrackingExpert(task).act(obs)
    obs[1, 6] = math.nan  # an attitude entry
    expert = QuadrotorTrackingExpert(task)
    a = expert.act(obs)
    assert torch.isnan(a[1]).all() and expert.info()["converged"].tolist() == [True, False, True]
    torch.testing.assert_close(a[[0, 2]], clean[[0, 2]], rtol=0, atol=0)
