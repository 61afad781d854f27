"""The zoo's ``normalize: true`` (SB3's VecNormalize) in learning.baselines: applied where the zoo applies it,
evaluated with the training statistics (checked against SB3's own ``VecNormalize.normalize_obs``), saved as
plain tensors and loaded back without pickle."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch
from stable_baselines3.common.vec_env import VecNormalize, unwrap_vec_normalize

import learning  # noqa: F401
from learning import baselines as bl
from learning.sb3_normalize import NormalizedModel, agent_of, wrap_normalize

ID = "Pendulum-v1"
SMALL = dict(n_envs=1, n_steps=32, batch_size=32, n_epochs=1, gamma=0.9, policy_kwargs={"net_arch": [8]})


def _hand_returns(model, vecnorm, seeds):
    """Deterministic episodes on gym.make(ID), observations normalized by SB3's VecNormalize itself."""
    out = []
    for s in seeds:
        env = gym.make(ID)
        obs, _ = env.reset(seed=s)
        total, done = 0.0, False
        while not done:
            a, _ = model.predict(vecnorm.normalize_obs(obs[None])[0], deterministic=True)
            obs, r, term, trunc, _ = env.step(a)
            total, done = total + float(r), term or trunc
        out.append(total)
    return np.asarray(out)


def test_the_zoo_entries_with_normalize_carry_it():
    assert bl.hyperparams("ppo", "Reacher-v5")["normalize"] is True
    assert bl.hyperparams("ppo", "MountainCarContinuous-v0")["normalize"] is True
    assert "normalize" not in bl.hyperparams("sac", ID) and "normalize" not in bl.hyperparams("ppo", ID)
    assert "normalize" not in bl.hyperparams("ppo", "PendulumSwingUp")


def test_train_with_normalize_evaluates_with_the_training_statistics(tmp_path):
    res = bl.train("ppo", ID, 64, eval_every=32, eval_episodes=2, params=dict(SMALL, normalize=True),
                   out_dir=tmp_path, tensorboard=False)
    assert isinstance(res.model, NormalizedModel)
    v = unwrap_vec_normalize(res.model.model.get_env())
    assert isinstance(v, VecNormalize) and v.gamma == 0.9 and v.obs_rms.count > 64
    assert any("trains on VecNormalize" in n for n in res.notes)
    ref = _hand_returns(res.model.model, v, bl.eval_seeds(2))
    assert res.returns[-1] == pytest.approx(ref.mean(), rel=1e-5)
    # saved as plain tensors, loaded back: the same actions on raw observations
    assert (tmp_path / "obs_rms.pt").is_file() and res.paths["obs_rms"].endswith("obs_rms.pt")
    loaded = bl.load_agent(tmp_path)
    assert isinstance(loaded, NormalizedModel) and loaded.vecnorm.training is False
    np.testing.assert_array_equal(loaded.vecnorm.obs_rms.mean, v.obs_rms.mean)
    obs = np.stack([gym.make(ID).reset(seed=s)[0] for s in range(6)]) * 3.0
    np.testing.assert_allclose(loaded.predict(obs, deterministic=True)[0],
                               res.model.predict(obs, deterministic=True)[0], rtol=1e-6)
    assert loaded.num_timesteps == res.num_timesteps
    # the statistics are needed, and checked
    bad = {"mean": torch.zeros(5), "var": torch.ones(5), "count": torch.tensor(1.0)}
    torch.save(bad, tmp_path / "obs_rms.pt")
    with pytest.raises(ValueError, match="obs_rms.pt must hold tensors 'mean' and 'var' of shape \\(3,\\)"):
        bl.load_agent(tmp_path)
    (tmp_path / "obs_rms.pt").unlink()
    with pytest.raises(ValueError, match="obs_rms.pt is missing"):
        bl.load_agent(tmp_path)


def test_normalize_on_a_task_and_its_options():
    model = bl.make_agent("ppo", "PendulumSwingUp", params=dict(SMALL, normalize={"norm_reward": False}))
    v = unwrap_vec_normalize(model.get_env())
    assert v is not None and v.norm_reward is False and v.gamma == 0.9
    agent = agent_of(model)
    r = learning.evaluate(agent, "PendulumSwingUp", num_envs=2, progress=False, timing_batch1=False)
    assert np.isfinite(r.returns).all()
    plain = bl.make_agent("ppo", "PendulumSwingUp", params=SMALL)
    assert agent_of(plain) is plain
    off = bl.make_agent("ppo", ID, params=dict(SMALL, normalize={"norm_obs": False}))
    assert agent_of(off) is off  # nothing to normalize at evaluation
    with pytest.raises(ValueError, match="hyperparameter 'normalize' must be"):
        bl.make_agent("ppo", ID, params=dict(SMALL, normalize="yes"))
    with pytest.raises(ValueError, match="hyperparameter 'normalize'"):
        wrap_normalize(plain.get_env(), {"no_such_option": 1}, 0.99)
