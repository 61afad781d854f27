"""The SB3 adapter: output by output against SB3's own DummyVecEnv over the single env, and in use with
PPO, SAC, VecMonitor, VecNormalize and evaluate_policy."""

import gymnasium as gym
import numpy as np
import pytest
import torch
from stable_baselines3 import PPO, SAC
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.vec_env import DummyVecEnv, VecMonitor, VecNormalize

import learning
from learning.sb3 import SB3VecEnv

learning.register_envs()


@pytest.mark.parametrize("name", ["PendulumSwingUp", "CartPoleSwingUp"])
def test_adapter_equals_dummy_vec_env_including_terminal_observations(name):
    N, steps = 4, 9
    ours = SB3VecEnv(name, N, max_episode_steps=steps, dtype=torch.float64)
    ref = DummyVecEnv([lambda: gym.make(learning.env_id(name), max_episode_steps=steps, dtype=torch.float64)
                       for _ in range(N)])
    ours.seed(5)
    ref.seed(5)
    np.testing.assert_allclose(ours.reset(), ref.reset(), rtol=0, atol=1e-12)
    rng = np.random.default_rng(0)
    ends = 0
    for _ in range(3 * steps + 2):
        a = rng.uniform(-1, 1, (N, 1))
        o, r, d, infos = ours.step(a)
        o2, r2, d2, infos2 = ref.step(a)
        np.testing.assert_allclose(o, o2, rtol=0, atol=1e-12)
        np.testing.assert_allclose(r, r2, rtol=0, atol=1e-6)  # SB3's buffer is float32
        np.testing.assert_array_equal(d, d2)
        for i in np.flatnonzero(d):
            np.testing.assert_allclose(infos[i]["terminal_observation"], infos2[i]["terminal_observation"],
                                       rtol=0, atol=1e-12)
            assert infos[i]["TimeLimit.truncated"] == infos2[i]["TimeLimit.truncated"]
            ends += 1
    assert ends >= 3 * N


def test_ppo_sac_monitor_normalize_and_evaluate_policy():
    venv = VecNormalize(VecMonitor(SB3VecEnv("PendulumSwingUp", 8, max_episode_steps=25)))
    venv.seed(0)
    model = PPO("MlpPolicy", venv, n_steps=32, batch_size=64, n_epochs=1, seed=0, device="cpu")
    model.learn(512)
    episodes = [e for e in model.ep_info_buffer]
    assert len(episodes) >= 8 and all(e["l"] == 25 for e in episodes)
    mean, std = evaluate_policy(model, venv, n_eval_episodes=8)
    assert np.isfinite(mean) and -25 * 12 <= mean <= 0  # Pendulum rewards are in [-16.3, 0] per step
    sac = SAC("MlpPolicy", SB3VecEnv("CartPoleSwingUp", 2, max_episode_steps=20), learning_starts=8,
              batch_size=16, seed=0, device="cpu")
    sac.learn(60)
    assert sac.num_timesteps >= 60


def test_adapter_refuses_an_env_with_the_wrong_mode():
    with pytest.raises(ValueError, match="SAME_STEP"):
        SB3VecEnv(learning.TaskVectorEnv("PendulumSwingUp", 2))


def test_wrong_sized_actions_get_the_envs_error_naming_them():
    """Issue 22 sweep: a wrong-sized action array failed in numpy's reshape, not naming the actions."""
    env = SB3VecEnv("PendulumSwingUp", 2)
    env.reset()
    with pytest.raises(ValueError, match=r"actions must have shape \(2, 1\)"):
        env.step(np.zeros(3, np.float32))
    with pytest.raises(TypeError, match="actions must be real numbers"):
        env.step(np.array([0.5j, 0.0]))
    obs, *_ = env.step(np.zeros(2, np.float32))  # a flat (N,) action of a one-control task is fine
    assert obs.shape == (2, 3)
