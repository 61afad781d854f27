"""Adversarial checks of the ``normalize`` hyperparameter (SB3's VecNormalize, learning.sb3_normalize):
tampered ``obs_rms.pt`` files refused with the file named, the wrapper copyable and attribute-transparent,
``norm_obs=False`` agents loadable, ``normalize={}`` consistent between training and loading, SB3 zips of
normalize agents acting as trained, off-policy agents evaluated consistently, ``compare(load=...)``."""

from __future__ import annotations

import copy
import pickle
import shutil

import gymnasium as gym
import numpy as np
import pytest
import torch
from stable_baselines3.common.vec_env import unwrap_vec_normalize

import learning  # noqa: F401
from learning import baselines as bl
from learning.sb3_normalize import NormalizedModel

ID = "Pendulum-v1"
SMALL = dict(n_envs=1, n_steps=32, batch_size=32, n_epochs=1, gamma=0.9, policy_kwargs={"net_arch": [8]})
OBS = np.random.default_rng(0).normal(size=(6, 3)).astype(np.float32) * 4.0  # raw, beyond clip_obs=0.5


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    d = tmp_path_factory.mktemp("norm")
    res = bl.train("ppo", ID, 64, eval_every=64, eval_episodes=1, out_dir=d, tensorboard=False,
                   params=dict(SMALL, normalize={"clip_obs": 0.5}))
    return res, d


def _act(agent, obs=OBS):
    return agent.predict(obs, deterministic=True)[0]


_RAN: list = []


def _mark():
    _RAN.append(1)


class _Evil:
    def __reduce__(self):
        return (_mark, ())


_BAD = {
    "nan mean": {"mean": torch.tensor([np.nan, 0.0, 0.0], dtype=torch.float64)},
    "inf var": {"var": torch.tensor([np.inf, 1.0, 1.0], dtype=torch.float64)},
    "negative var": {"var": torch.tensor([-5.0, 1.0, 1.0], dtype=torch.float64)},
    "negative count": {"count": torch.tensor(-3.0, dtype=torch.float64)},
    "count of two": {"count": torch.tensor([1.0, 2.0])},
    "complex mean": {"mean": torch.tensor([1 + 1j, 2, 3])},
    "bool var": {"var": torch.tensor([True, True, False])},
}


@pytest.mark.parametrize("case", [*_BAD, "list", "text", "empty", "pickled object"])
def test_tampered_obs_rms_is_refused_naming_the_file(trained, tmp_path, case):
    _, src = trained
    d = tmp_path / "agent"
    shutil.copytree(src, d)
    f = d / "obs_rms.pt"
    if case in _BAD:
        torch.save(dict(torch.load(f, weights_only=True), **_BAD[case]), f)
    elif case == "list":
        torch.save([1.0, 2.0], f)
    elif case == "text":
        f.write_bytes(b"hello world")
    elif case == "empty":
        f.write_bytes(b"")
    else:
        f.write_bytes(pickle.dumps({"mean": _Evil()}))
    with pytest.raises(ValueError, match="obs_rms.pt"):
        bl.load_agent(d)
    assert not _RAN  # weights_only: the pickled callable never ran


def test_integer_and_half_statistics_load_as_float64(trained, tmp_path):
    res, src = trained
    d = tmp_path / "agent"
    shutil.copytree(src, d)
    st = torch.load(d / "obs_rms.pt", weights_only=True)
    st = {"mean": st["mean"].round().long(), "var": st["var"].half(), "count": st["count"].long()}
    torch.save(st, d / "obs_rms.pt")
    v = bl.load_agent(d).vecnorm
    assert v.obs_rms.mean.dtype == np.float64 and v.obs_rms.var.dtype == np.float64
    np.testing.assert_array_equal(v.obs_rms.mean, st["mean"].double().numpy())


def test_the_wrapper_copies_pickles_and_passes_attributes_on(trained):
    res, _ = trained
    agent = res.model
    ref = _act(agent)
    for other in (copy.copy(agent), copy.deepcopy(agent), pickle.loads(pickle.dumps(agent))):
        assert isinstance(other, NormalizedModel)
        np.testing.assert_array_equal(_act(other), ref)
    twin = copy.deepcopy(agent)
    twin.num_timesteps = 7  # set on the model, not on the wrapper only
    assert twin.model.num_timesteps == 7 and twin.num_timesteps == 7
    assert "num_timesteps" not in vars(twin)


def test_a_zip_of_a_normalize_agent_acts_as_trained(trained):
    res, d = trained
    z = bl.load_agent(d / "model.zip", trust_zip=True)
    assert isinstance(z, NormalizedModel) and z.vecnorm.clip_obs == 0.5
    np.testing.assert_allclose(_act(z), _act(res.model), rtol=1e-6)
    assert not np.allclose(_act(z.model), _act(res.model))  # the raw policy on raw observations differs


def test_norm_obs_false_agents_load(tmp_path):
    res = bl.train("ppo", ID, 32, eval_every=32, eval_episodes=1, out_dir=tmp_path, tensorboard=False,
                   params=dict(SMALL, normalize={"norm_obs": False, "norm_reward": True}))
    assert not isinstance(res.model, NormalizedModel) and "obs_rms" not in res.paths
    loaded = bl.load_agent(tmp_path)
    assert not isinstance(loaded, NormalizedModel)
    v = unwrap_vec_normalize(loaded.get_env())
    assert v is not None and v.norm_reward and not v.norm_obs
    np.testing.assert_allclose(_act(loaded), _act(res.model), rtol=1e-6)


def test_an_empty_normalize_dict_is_no_normalize_in_training_and_loading():
    model = bl.make_agent("ppo", ID, params=dict(SMALL, normalize={}))
    assert unwrap_vec_normalize(model.get_env()) is None


def test_sac_with_normalize_keeps_raw_observations_and_evaluates_with_the_statistics(tmp_path):
    res = bl.train("sac", ID, 48, eval_every=48, eval_episodes=1, out_dir=tmp_path, tensorboard=False,
                   params=dict(n_envs=1, learning_starts=16, batch_size=16, buffer_size=500, normalize=True,
                               policy_kwargs={"net_arch": [8]}))
    model = res.model.model
    v = unwrap_vec_normalize(model.get_env())
    o = model.replay_buffer.observations[:48, 0]
    np.testing.assert_allclose(o[:, 0] ** 2 + o[:, 1] ** 2, 1.0, rtol=1e-5)  # raw (cos, sin, ω) stored
    env = gym.make(ID)
    obs, _ = env.reset(seed=bl.eval_seeds(1)[0])
    total, done = 0.0, False
    while not done:
        a, _ = model.predict(v.normalize_obs(obs[None])[0], deterministic=True)
        obs, r, term, trunc, _ = env.step(a)
        total, done = total + float(r), term or trunc
    assert res.returns[-1] == pytest.approx(total, rel=1e-5)
    np.testing.assert_allclose(_act(bl.load_agent(tmp_path)), _act(res.model), rtol=1e-6)


def test_compare_loads_saved_normalize_agents(tmp_path):
    from liecontrol.compare import compare

    kw = dict(algos=("ppo",), budget_steps={"ppo": 64}, seeds=(0,), eval_episodes=1, mpc=False, jobs=1)
    rec = compare("MountainCarContinuous-v0", out=tmp_path / "a", **kw)
    assert (tmp_path / "a" / "agents" / "ppo" / "seed0" / "obs_rms.pt").is_file()
    again = compare("MountainCarContinuous-v0", out=tmp_path / "b", load=tmp_path / "a", **kw)
    assert again["ppo"]["return"]["mean"] == pytest.approx(rec["ppo"]["return"]["mean"], rel=1e-9)
