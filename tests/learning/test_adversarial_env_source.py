"""Adversarial use of Env / VectorEnv / factory inputs in learning.baselines, learning.evaluate and compare:
AsyncVectorEnv in every autoreset mode, factories that return one env twice, envs without an episode limit,
running-statistics wrappers, agents loaded on an env of the same id with other wrappers, NaN observations,
bad ``num_envs``, gym.make keyword arguments, and a MuJoCo env instance in ``compare`` with its MPC."""

from __future__ import annotations

import copy
import json
from functools import partial

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.vector import AutoresetMode

import learning  # noqa: F401  (registers the envs)
from learning import baselines as bl
from learning.env_source import env_source
from learning.evaluate import evaluate

ID = "Pendulum-v1"
TINY = dict(n_envs=2, n_steps=16, batch_size=32, n_epochs=1, policy_kwargs={"net_arch": [8]})


class Walk(gym.Env):
    """An unregistered 1-d env: x' = x + a·[1, 0.5] + noise, terminates when |x| > 2, reward -x²; its
    observation is NaN at step ``nan_at`` of an episode (when given)."""

    def __init__(self, nan_at: int | None = None):
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (2,), np.float64)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)
        self.nan_at, self.t, self.x = nan_at, 0, np.zeros(2)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.x, self.t = self.np_random.uniform(-1, 1, 2), 0
        return self.x.copy(), {}

    def step(self, a):
        self.t += 1
        self.x = self.x + float(np.asarray(a).reshape(-1)[0]) * np.array([1.0, 0.5]) \
            + 0.3 * self.np_random.standard_normal(2)
        obs = np.full(2, np.nan) if self.t == self.nan_at else self.x.copy()
        return obs, -float(self.x @ self.x), bool(np.abs(self.x).max() > 2.0), False, {}


def walk(T: int = 12, **kw):
    return gym.wrappers.TimeLimit(Walk(**kw), T)


def zero_policy(obs):
    return torch.zeros(obs.shape[0], 1, dtype=obs.dtype)


def _hand_returns(make, seeds, policy=None):
    """Returns of a hand-written loop, one fresh env per seed (the reference for evaluate)."""
    out = []
    for s in seeds:
        env = make()
        obs, _ = env.reset(seed=s)
        total, done = 0.0, False
        while not done:
            a = np.zeros(env.action_space.shape, np.float32) if policy is None else policy(obs)
            obs, r, term, trunc, _ = env.step(a)
            total, done = total + float(r), term or trunc
        out.append(total)
    return np.asarray(out)


# ------------------------------------------------------------------------------------- env_source


def test_a_factory_returning_one_env_twice_is_refused():
    env = walk()
    with pytest.raises(TypeError, match="returned the same env twice.*new env on each call"):
        env_source(lambda: env)
    with pytest.raises(TypeError, match="train: the env factory.*same env twice"):
        bl.train("ppo", lambda: env, 32, params=TINY, tensorboard=False)
    assert env_source(walk).how == "the factory"  # a real factory is fine


def test_gym_make_kwargs_and_time_limits_are_kept_by_copies():
    src = env_source(gym.make(ID, g=5.0, max_episode_steps=17))
    c = src.make()
    assert src.how == "gymnasium.make(env.spec)" and c.unwrapped.g == 5.0
    ref = _hand_returns(lambda: gym.make(ID, g=5.0, max_episode_steps=17), [3])
    np.testing.assert_array_equal(_hand_returns(src.make, [3]), ref)
    outer = env_source(gym.wrappers.TimeLimit(gym.make(ID), 9))  # an extra TimeLimit: deep copies
    np.testing.assert_array_equal(_hand_returns(outer.make, [4]),
                                  _hand_returns(lambda: gym.make(ID, max_episode_steps=9), [4]))


def test_copies_of_a_normalizing_env_carry_its_statistics():
    env = gym.wrappers.NormalizeObservation(gym.make(ID))
    env.reset(seed=0)
    for _ in range(60):
        env.step(np.array([1.0], np.float32))
    src = env_source(env)
    assert src.how == "copy.deepcopy(env)"
    ref = copy.deepcopy(env).reset(seed=7)[0]
    np.testing.assert_allclose(src.make().reset(seed=7)[0], ref)
    fresh = gym.make(env.spec).reset(seed=7)[0]  # what a rebuild from the spec saw: other statistics
    assert not np.allclose(fresh, ref)
    venv = gym.make_vec(ID, 2, vectorization_mode="sync", wrappers=[gym.wrappers.NormalizeObservation])
    venv.reset(seed=0)
    for _ in range(30):
        venv.step(np.ones((2, 1), np.float32))
    vs = env_source(venv)
    np.testing.assert_allclose(vs.make().reset(seed=2)[0], copy.deepcopy(venv.envs[0]).reset(seed=2)[0])


# ------------------------------------------------------------------------------------- evaluate


def test_evaluate_takes_a_factory_or_an_env_class():
    seeds = [1, 2, 3]
    r = evaluate(zero_policy, walk, seeds=seeds, num_envs=2, progress=False)
    np.testing.assert_allclose(r.returns, _hand_returns(walk, seeds), rtol=1e-12)
    assert r.meta["task"] == "Walk"
    r = evaluate(zero_policy, Walk, seeds=seeds, num_envs=2, max_episode_steps=5, progress=False)
    np.testing.assert_allclose(r.returns, _hand_returns(lambda: walk(5), seeds), rtol=1e-12)
    with pytest.raises(ValueError, match="evaluate: the env has no episode limit.*max_episode_steps"):
        evaluate(zero_policy, Walk, seeds=seeds, progress=False)


@pytest.mark.parametrize("mode", [AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP, AutoresetMode.DISABLED])
def test_async_vector_env_in_each_autoreset_mode(mode):
    from stable_baselines3.common.vec_env import DummyVecEnv

    from learning.sb3 import SB3VecEnv

    def transitions(venv):
        venv.seed(11)
        rows, rng = [venv.reset()], np.random.default_rng(0)
        for _ in range(30):
            venv.step_async(rng.uniform(-1, 1, (3, 1)).astype(np.float32))
            obs, rew, done, infos = venv.step_wait()
            rows += [obs, rew[:, None], done[:, None],
                     np.stack([i.get("terminal_observation", np.zeros(2)) for i in infos]),
                     np.array([[i.get("TimeLimit.truncated", False)] for i in infos], np.float64)]
        return np.concatenate([np.asarray(r, np.float64).reshape(3, -1) for r in rows], 1)

    venv = gym.vector.AsyncVectorEnv([walk] * 3, autoreset_mode=mode)
    try:
        np.testing.assert_array_equal(transitions(SB3VecEnv(venv)), transitions(DummyVecEnv([walk] * 3)))
        seeds = [5, 6, 7]
        r = evaluate(zero_policy, env_source(venv), seeds=seeds, progress=False)  # fresh copies
        np.testing.assert_allclose(r.returns, _hand_returns(walk, seeds), rtol=1e-12)
        if mode != AutoresetMode.DISABLED:  # the VectorEnv itself (DISABLED cannot run in lockstep)
            r = evaluate(zero_policy, venv, seeds=seeds, progress=False)
            np.testing.assert_allclose(r.returns, _hand_returns(walk, seeds), rtol=1e-12)
    finally:
        venv.close()


# ------------------------------------------------------------------------------------- train / load


def test_train_on_an_async_vector_env_evaluates_on_copies():
    venv = gym.vector.AsyncVectorEnv([walk] * 2)
    try:
        res = bl.train("sac", venv, 40, eval_episodes=2, eval_every=20, tensorboard=False,
                       params=dict(n_envs=1, learning_starts=10, policy_kwargs={"net_arch": [8]}))
    finally:
        venv.close()
    assert res.num_timesteps == 40 and res.params["n_envs"] == 2
    hand = _hand_returns(walk, bl.eval_seeds(2), lambda o: res.model.predict(o, deterministic=True)[0])
    assert res.returns[-1] == pytest.approx(hand.mean(), rel=1e-5)


def test_env_without_episode_limit_is_refused_before_training(tmp_path):
    from liecontrol._args import OptionError
    from liecontrol.compare import compare

    with pytest.raises(ValueError, match="train: the env 'Walk' has no episode limit.*TimeLimit"):
        bl.train("ppo", Walk, 32, params=TINY, tensorboard=False)
    with pytest.raises(OptionError, match="compare: the env 'Walk' has no episode limit"):
        compare(Walk(), algos=("ppo",), seeds=(0,), out=tmp_path, mpc=False)


@pytest.mark.parametrize("n", [0, -1, 2.5, "2", True])
def test_bad_num_envs_names_the_argument(n):
    with pytest.raises(ValueError, match="make_agent: argument 'num_envs' must be an int >= 1"):
        bl.make_agent("ppo", walk(), num_envs=n, params=TINY)
    with pytest.raises(ValueError, match="train: argument 'num_envs' must be an int >= 1"):
        bl.train("ppo", walk(), 32, num_envs=n, params=TINY, tensorboard=False)


def test_bad_n_envs_in_params_names_it():
    with pytest.raises(ValueError, match=r"make_agent: argument 'params\['n_envs'\]' must be an int >= 1"):
        bl.make_agent("ppo", walk(), params=dict(TINY, n_envs=0))


@pytest.mark.parametrize("vector", [False, True])
def test_nan_observations_are_named_in_training(vector):
    env = gym.vector.SyncVectorEnv([partial(walk, nan_at=3)] * 2) if vector else walk(nan_at=3)
    with pytest.raises(ValueError, match="found nan in observations"):
        bl.train("ppo", env, 64, eval_episodes=1, params=TINY, tensorboard=False)


def test_load_agent_checks_the_spaces_of_the_env_given(tmp_path):
    rescaled = partial(gym.wrappers.RescaleAction, gym.make(ID), -1.0, 1.0)
    res = bl.train("ppo", rescaled(), 32, eval_episodes=1, params=TINY, tensorboard=False, out_dir=tmp_path)
    assert json.loads((tmp_path / "agent.json").read_text())["spaces"]["action"]["high"] == [1.0]
    with pytest.raises(ValueError, match="trained on Pendulum-v1 with the action space.*'spaces'"):
        bl.load_agent(tmp_path)  # the id alone: actions in [-2, 2], not the [-1, 1] it learned in
    with pytest.raises(ValueError, match="observation space"):
        bl.load_agent(tmp_path, task=gym.wrappers.DtypeObservation(rescaled(), np.float64))
    loaded = bl.load_agent(tmp_path, task=gym.wrappers.RescaleAction(gym.make(ID), -1.0, 1.0))
    obs = np.stack([gym.make(ID).reset(seed=s)[0] for s in range(4)])
    np.testing.assert_allclose(loaded.predict(obs, deterministic=True)[0],
                               res.model.predict(obs, deterministic=True)[0], rtol=1e-6)


# ------------------------------------------------------------------------------------- compare


def test_compare_on_a_mujoco_env_instance_with_its_mpc(tmp_path):
    pytest.importorskip("mujoco", reason="MuJoCo is not installed")
    from liecontrol.compare import compare

    env = gym.make("InvertedPendulum-v5", max_episode_steps=20)
    rec = compare(env, algos=("ppo",), budget_steps={"ppo": 32}, seeds=(0,), eval_episodes=1,
                  eval_every=32, out=tmp_path, jobs=1, mpc=True, mpc_horizon=5)
    assert rec["env"] == "InvertedPendulum-v5" and rec["env_copies"] == "gymnasium.make(env.spec)"
    assert rec["mpc"]["horizon"] == 5 and rec["mpc"]["episodes"] == 1
    assert rec["ppo"]["num_timesteps"] >= 32 and env.unwrapped.data.time == 0.0  # the instance not stepped
