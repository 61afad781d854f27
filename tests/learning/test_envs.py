"""The single environments: gymnasium's and SB3's checkers, the physics against gymnasium's Pendulum-v1,
bounds, clipping, invalid actions, rendering."""

import math
import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env as gym_check_env
from stable_baselines3.common.env_checker import check_env as sb3_check_env

import learning
from learning import TASKS, TaskEnv

learning.register_envs()


@pytest.mark.parametrize("name", sorted(TASKS))
def test_checkers_pass_without_warnings(name):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        gym_check_env(gym.make(learning.env_id(name), render_mode="rgb_array").unwrapped)
        sb3_check_env(TaskEnv(name, render_mode="rgb_array"))


def test_pendulum_reproduces_gymnasium_pendulum_v1():
    ref = gym.make("Pendulum-v1").unwrapped
    ours = TaskEnv("PendulumSwingUp", dtype=torch.float64)
    rng = np.random.default_rng(0)
    checked = 0
    for _ in range(200):
        phi, om = rng.uniform(-math.pi, math.pi), rng.uniform(-6, 6)
        a = rng.uniform(-1, 1)
        ref.reset(seed=0)
        ref.state = np.array([phi, om])
        o_ref, r_ref, *_ = ref.step(np.array([2.0 * a], np.float32))
        ours.reset(seed=0)
        ours._x = torch.tensor([[phi + math.pi, om]], dtype=torch.float64)
        o, r, term, trunc, _ = ours.step(np.array([a]))
        if abs(o_ref[2]) < 8 - 1e-9:  # Pendulum-v1 clips the speed; ours does not (documented)
            np.testing.assert_allclose(o, o_ref, atol=2e-6)  # Pendulum-v1 computes in float32 actions
            assert r == pytest.approx(r_ref, abs=2e-6)
            checked += 1
        assert not term and not trunc
    assert checked > 150


@pytest.mark.parametrize("name", sorted(TASKS))
def test_observations_stay_in_the_space_under_extreme_actions(name):
    env = gym.make(learning.env_id(name))
    env.reset(seed=1)
    for k in range(600):  # three episodes of bang-bang actions pumping energy
        o, r, term, trunc, _ = env.step(np.full(env.action_space.shape, 1.0 if (k // 7) % 2 else -1.0,
                                                np.float32))
        assert env.observation_space.contains(o), (k, o)
        if term or trunc:
            env.reset()


@pytest.mark.parametrize("name", sorted(TASKS))
def test_state_from_observation_round_trip(name):
    env = TaskEnv(name, dtype=torch.float64)
    env.reset(seed=3)
    for _ in range(30):
        o, *_ = env.step(env.action_space.sample())
        x = env.task.state_from_obs(torch.from_numpy(o)[None])
        # the state up to whole turns of its angles (observed as cos/sin), and the same observation
        np.testing.assert_allclose(env.task.observe(x)[0].numpy(), o, atol=1e-12, rtol=0)
        d = x[0].numpy() - env.state
        np.testing.assert_allclose(np.minimum(np.abs(d), np.abs((d + math.pi) % (2 * math.pi) - math.pi)), 0,
                                   atol=1e-12)


def test_actions_are_clipped_and_non_finite_actions_end_the_episode():
    env = TaskEnv("PendulumSwingUp", dtype=torch.float64)
    env.reset(seed=0)
    x0 = env.state
    o_big, r_big, *_ = env.step(np.array([7.0]))
    env.reset(seed=0)
    o_one, r_one, *_ = env.step(np.array([1.0]))
    np.testing.assert_array_equal(o_big, o_one)
    assert r_big == r_one
    for bad in (np.nan, np.inf, -np.inf):
        env.reset(seed=0)
        o, r, term, trunc, info = env.step(np.array([bad]))
        assert trunc and not term and info == {"invalid": True}
        assert np.isfinite(o).all() and math.isfinite(r)
        env.reset(seed=0)
        o0, r0, *_ = env.step(np.array([0.0]))  # a non-finite action is applied as zero
        np.testing.assert_array_equal(o, o0)
    assert np.array_equal(env.reset(seed=0)[0], env.reset(seed=0)[0]) and x0 is not None


def test_step_rejects_wrong_action_shape_and_requires_reset():
    env = TaskEnv("CartPoleSwingUp")
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros(1))
    env.reset(seed=0)
    with pytest.raises(ValueError, match="action must have shape"):
        env.step(np.zeros(2))
    with pytest.raises(ValueError, match="dtype"):
        TaskEnv("CartPoleSwingUp", dtype=torch.int32)
    with pytest.raises(ValueError, match="unknown task"):
        TaskEnv("NoSuchTask")


def test_cartpole_terminates_off_the_track():
    env = TaskEnv("CartPoleSwingUp", dtype=torch.float64)
    env.reset(seed=0)
    for _ in range(200):
        o, r, term, trunc, _ = env.step(np.array([1.0]))
        assert 0.0 <= r <= 1.0
        if term:
            break
    assert term and (abs(env.state[0]) > 2.4 or abs(env.state[2]) > 10.0 or abs(env.state[3]) > 25.0)


@pytest.mark.parametrize("name", sorted(TASKS))
def test_render_draws_the_state(name):
    env = TaskEnv(name, render_mode="rgb_array")
    env.reset(seed=0)
    f0 = env.render()
    assert f0.shape == (256, 256, 3) and f0.dtype == np.uint8
    for _ in range(10):
        env.step(np.ones(env.action_space.shape, np.float32))
    f1 = env.render()
    assert (f0 != 255).any() and not np.array_equal(f0, f1)
    assert TaskEnv(name).render() is None


def test_seeded_resets_replay_and_unseeded_resets_continue():
    env = TaskEnv("CartPoleSwingUp")
    a = [env.reset(seed=11)[0] for _ in range(1)] + [env.reset()[0] for _ in range(3)]
    b = [env.reset(seed=11)[0] for _ in range(1)] + [env.reset()[0] for _ in range(3)]
    np.testing.assert_array_equal(np.stack(a), np.stack(b))
    assert len({tuple(v) for v in a}) == 4


def test_complex_action_is_refused_naming_the_action():
    """Issue 22 item 13: TaskEnv cast a complex action to float64 with only numpy's ComplexWarning."""
    env = TaskEnv("PendulumSwingUp")
    env.reset(seed=0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no ComplexWarning on the way to the TypeError
        with pytest.raises(TypeError, match="TaskEnv.step: action must be real numbers.*imaginary"):
            env.step(np.array([0.5 + 1j]))
    # a float64 beyond float32's range is clipped like any out-of-box action (as before)
    _, _, _, trunc, info = env.step(np.array([1e39]))
    assert not trunc and info == {}
