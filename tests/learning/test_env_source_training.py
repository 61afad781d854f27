"""Env and VectorEnv instances (and factories) in learning.baselines, learning.evaluate and compare:
the copies :func:`learning.env_source.env_source` makes behave as the env given, training runs on the env
given and evaluation never touches it, and SB3's view of a gymnasium VectorEnv (any autoreset mode) gives the
transitions SB3's own DummyVecEnv gives."""

from __future__ import annotations

import threading

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


class Drift(gym.Env):
    """An unregistered 1-d env: x' = x + a + noise; terminates when |x| > 2, reward -x²; counts its steps
    (per instance) so a test can tell which env a trainer stepped."""

    def __init__(self):
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (2,), np.float64)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)
        self.steps = 0
        self.x = np.zeros(2)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.x = self.np_random.uniform(-1, 1, 2)
        return self.x.copy(), {}

    def step(self, a):
        self.steps += 1
        self.x = self.x + float(np.asarray(a).reshape(-1)[0]) * np.array([1.0, 0.5]) \
            + 0.3 * self.np_random.standard_normal(2)
        term = bool(np.abs(self.x).max() > 2.0)
        return self.x.copy(), -float(self.x @ self.x), term, False, {}


def drift(T: int = 12):
    return gym.wrappers.TimeLimit(Drift(), T)


class Halve(gym.Wrapper):
    """A wrapper that records no constructor arguments (gymnasium.make(spec) cannot rebuild it)."""

    def step(self, a):
        obs, r, term, trunc, info = self.env.step(a)
        return obs, 0.5 * r, term, trunc, info


def _rollout(env, seed, actions):
    obs, _ = env.reset(seed=seed)
    out = [obs]
    for a in actions:
        obs, r, term, trunc, _ = env.step(a)
        out += [obs, np.array([r, term, trunc], dtype=np.float64)]
        if term or trunc:
            break
    return np.concatenate([np.asarray(o, dtype=np.float64).ravel() for o in out])


@pytest.mark.parametrize("build, how", [
    (lambda: gym.make(ID), "gymnasium.make(env.spec)"),
    (lambda: gym.wrappers.RescaleAction(gym.make(ID), -1.0, 1.0), "gymnasium.make(env.spec)"),
    (lambda: Halve(gym.make(ID)), "copy.deepcopy(env)"),
    (drift, "copy.deepcopy(env)"),
])
def test_copies_of_an_env_behave_as_the_env_given(build, how):
    env = build()
    src = env_source(env)
    assert src.how == how and src.instance is env
    actions = [np.full(env.action_space.shape, v, dtype=np.float32) for v in (0.7, -0.3, 1.0, -1.0, 0.2)]
    ref = _rollout(env, 3, actions)
    copy = src.make()
    assert copy is not env and copy.action_space == env.action_space
    np.testing.assert_array_equal(_rollout(copy, 3, actions), ref)
    if isinstance(env.unwrapped, Drift):
        assert src.name == "Drift" and src.env_id is None


def test_vector_env_and_factory_sources():
    venv = gym.make_vec(ID, num_envs=3)
    src = env_source(venv)
    assert src.is_vector and src.name == ID and src.how == "the vector env's env_fns[0]"
    a = [np.array([0.5], np.float32)] * 4
    np.testing.assert_array_equal(_rollout(src.make(), 9, a), _rollout(gym.make(ID), 9, a))
    stats = gym.wrappers.vector.RecordEpisodeStatistics(gym.make_vec(ID, num_envs=2))
    assert env_source(stats).name == ID  # a recording vector wrapper is neutral
    f = env_source(drift)
    assert f.instance is None and f.name == "Drift" and f.picklable()
    assert env_source(Drift).name == "Drift"  # an Env subclass is a factory


def test_bad_env_input_gets_a_clear_error():
    with pytest.raises(TypeError, match="vector wrapper NormalizeObservation"):
        env_source(gym.wrappers.vector.NormalizeObservation(gym.make_vec(ID, num_envs=2)))
    env = Drift()
    env.lock = threading.Lock()  # no spec, and copy.deepcopy fails
    with pytest.raises(TypeError, match="cannot make copies.*give a factory"):
        env_source(env)
    with pytest.raises(TypeError, match="action space must be a gymnasium.spaces.Box"):
        env_source(gym.make("CartPole-v1"))
    with pytest.raises(TypeError, match="action space must be a gymnasium.spaces.Box"):
        env_source("CartPole-v1")
    with pytest.raises(TypeError, match="must return a gymnasium.Env"):
        env_source(lambda: 3)
    with pytest.raises(TypeError, match="failed when called"):
        env_source(lambda: gym.make("NoSuchEnv-v0"))
    with pytest.raises(ValueError, match="unknown gymnasium id"):
        env_source("NoSuchEnv-v0")
    with pytest.raises(TypeError, match="expected a registered gymnasium id"):
        env_source(3.5)


def test_evaluate_on_a_source_equals_evaluate_on_the_id():
    pol = lambda obs: torch.zeros(obs.shape[0], 1, dtype=obs.dtype)  # noqa: E731
    a = evaluate(pol, env_source(gym.make(ID)), seeds=[5, 6, 7], num_envs=2, progress=False)
    b = evaluate(pol, ID, seeds=[5, 6, 7], num_envs=2, progress=False)
    np.testing.assert_array_equal(a.returns, b.returns)
    np.testing.assert_array_equal(a.length, b.length)
    assert a.meta["task"] == ID and a.step_ms_batch1.size > 0


# ------------------------------------------------------------------------- SB3's view of a VectorEnv


def _transitions(venv, steps: int, seed: int = 11):
    """(obs, rewards, dones, terminal observations, TimeLimit.truncated) of an SB3 VecEnv under fixed
    actions."""
    venv.seed(seed)
    obs = venv.reset()
    rng = np.random.default_rng(0)
    rows = [obs.copy()]
    for _ in range(steps):
        acts = rng.uniform(-1, 1, (venv.num_envs, 1)).astype(np.float32)
        venv.step_async(acts)
        obs, rew, done, infos = venv.step_wait()
        term = [np.asarray(i.get("terminal_observation", np.zeros(2))) for i in infos]
        trunc = [float(i.get("TimeLimit.truncated", False)) for i in infos]  # absent: False
        rows += [obs.copy(), rew.astype(np.float64)[:, None], done.astype(np.float64)[:, None],
                 np.stack(term), np.asarray(trunc)[:, None]]
    return np.concatenate([r.reshape(venv.num_envs, -1) for r in rows], 1)


@pytest.mark.parametrize("mode", [AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP, AutoresetMode.DISABLED])
def test_sb3_view_of_a_vector_env_equals_sb3s_dummy_vec_env(mode):
    from stable_baselines3.common.vec_env import DummyVecEnv

    from learning.sb3 import SB3VecEnv

    ref = _transitions(DummyVecEnv([drift] * 3), 40)
    got = _transitions(SB3VecEnv(gym.vector.SyncVectorEnv([drift] * 3, autoreset_mode=mode)), 40)
    np.testing.assert_array_equal(got, ref)
    dones = ref[:, 5::7]  # obs(2) | obs(2), reward, done, terminal(2), trunc per step
    assert dones.sum() >= 6  # both endings happened: terminations and time limits
    truncs = ref[:, 8::7]
    assert (truncs == 1.0).any() and (truncs == 0.0).any()


# ------------------------------------------------------------------------------------- training


def test_train_steps_the_env_given_and_evaluates_on_copies(tmp_path):
    env = drift()
    params = dict(n_envs=1, n_steps=32, batch_size=32, n_epochs=1, policy_kwargs={"net_arch": [8]})
    res = bl.train("ppo", env, 64, eval_every=32, eval_episodes=3, params=params, out_dir=tmp_path,
                   tensorboard=False)
    assert res.task == "Drift" and res.num_timesteps == 64
    assert env.unwrapped.steps == 64  # every training step on the env given, no evaluation step
    assert any("trains on the env given" in n for n in res.notes)
    # the last curve point is the deterministic policy on fresh copies, as a hand loop gives
    hand = []
    for s in bl.eval_seeds(3):
        e = drift()
        obs, _ = e.reset(seed=s)
        total, done = 0.0, False
        while not done:
            a, _ = res.model.predict(obs, deterministic=True)
            obs, r, term, trunc, _ = e.step(a)
            total, done = total + r, term or trunc
        hand.append(total)
    assert res.returns[-1] == pytest.approx(np.mean(hand), rel=1e-5)
    # rebuilt from policy.pt + agent.json: the unregistered env must be given
    with pytest.raises(ValueError, match="pass task="):
        bl.load_agent(tmp_path)
    loaded = bl.load_agent(tmp_path, task=drift)
    obs = np.stack([drift().reset(seed=s)[0] for s in range(4)])
    np.testing.assert_allclose(loaded.predict(obs, deterministic=True)[0],
                               res.model.predict(obs, deterministic=True)[0], rtol=1e-6)
    assert env.unwrapped.steps == 64


def test_train_on_a_vector_env_steps_its_sub_envs():
    venv = gym.vector.SyncVectorEnv([drift] * 2)
    params = dict(n_envs=4, n_steps=16, batch_size=32, n_epochs=1, policy_kwargs={"net_arch": [8]})
    res = bl.train("ppo", venv, 32, eval_episodes=2, params=params, tensorboard=False)
    assert res.num_timesteps == 32 and res.params["n_envs"] == 2
    assert [e.unwrapped.steps for e in venv.envs] == [16, 16]
    assert any("2 sub-envs of the VectorEnv given" in n for n in res.notes)
    with pytest.raises(ValueError, match="argument 'num_envs' is 3.*2 sub-envs"):
        bl.train("ppo", venv, 32, num_envs=3, params=params, tensorboard=False)
    with pytest.raises(ValueError, match="argument 'num_envs' is 3.*2 sub-envs"):
        bl.make_agent("ppo", venv, num_envs=3, params=params)


def test_compare_on_an_unregistered_env_instance(tmp_path):
    from liecontrol._args import OptionError
    from liecontrol.compare import compare

    env = drift()
    env.unwrapped.hook = lambda x: x  # copies by deepcopy work; they cannot go to worker processes
    rec = compare(env, algos=("ppo",), budget_steps={"ppo": 64}, seeds=(0, 1), eval_episodes=2,
                  eval_every=32, out=tmp_path, jobs=2, mpc=False)
    assert rec["foreign"] and rec["env"] == "Drift" and rec["env_copies"] == "copy.deepcopy(env)"
    assert rec["ppo"]["num_timesteps"] >= 64 and env.unwrapped.steps == 0  # agents train on copies
    report = (tmp_path / "report.md").read_text()
    assert "copies of the env (copy.deepcopy(env))" in report and "one after another" in report
    with pytest.raises(OptionError, match="no model is registered for 'Drift'.*--no-mpc"):
        compare(env, algos=("ppo",), seeds=(0,), out=tmp_path)
    with pytest.raises(OptionError, match="action box"):  # a model that does not fit the env given
        compare(gym.wrappers.RescaleAction(gym.make(ID), -1.0, 1.0), algos=("ppo",), seeds=(0,),
                out=tmp_path)


def test_a_clip_action_wrapper_keeps_the_model_usable():
    """gymnasium 1.x's ClipAction widens the action space to ±inf and clips to the inner box: the model is
    checked against that inner box (a RescaleAction is still refused)."""
    from learning.env_models import env_model

    assert env_model(gym.wrappers.ClipAction(gym.make(ID))).env_id == ID
    with pytest.raises(ValueError, match="action box"):
        env_model(gym.wrappers.RescaleAction(gym.make(ID), -1.0, 1.0))
