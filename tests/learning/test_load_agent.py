"""learning.baselines.load_agent rebuilds every policy the project trains from policy.pt + agent.json
(issue 22 item 10: an MPC-headed PPO agent was rebuilt as an MlpPolicy and failed on missing keys)."""

import json

import numpy as np
import pytest
import torch
from stable_baselines3.common.policies import ActorCriticPolicy
from torch import nn

from controllers.ilqr import ILQROptions
from learning import baselines as bl
from learning._policy_io import POLICIES
from learning.envs.single import make_task
from learning.mpc_policy import MPCActorCriticPolicy

TASK = "PendulumSwingUp"
TINY = dict(n_envs=2, n_steps=32, batch_size=64, n_epochs=1)



def _obs(n=7, seed=0):
    """Observations of states near the goal (unsaturated MPC actions, so the weights show) and at random."""
    task = make_task(TASK)
    g = torch.Generator().manual_seed(seed)
    ref = task.mpc_cost(5).x_ref.reshape(-1, task.n)[-1]
    near = ref + 0.3 * torch.randn(n, task.n, generator=g, dtype=torch.float64)
    far = task.initial_state(torch.rand(n, task.n_noise, generator=g, dtype=torch.float64))
    return task.observe(torch.cat([near, far])).float().numpy()


def _train(out, policy="MlpPolicy", policy_kwargs=None, budget=64):
    return bl.train("ppo", TASK, budget, seed=0, eval_every=budget, eval_episodes=1, out_dir=out,
                    params=dict(TINY), policy=policy, policy_kwargs=policy_kwargs, tensorboard=False)


@pytest.fixture(scope="module")
def mpc_agent(tmp_path_factory):
    out = tmp_path_factory.mktemp("mpc_agent")
    pk = {"task": TASK, "horizon": 5, "ilqr_options": ILQROptions(max_iter=2), "activation_fn": nn.ReLU,
          "cost_net_arch": (16,), "net_arch": {"vf": [16]}}
    res = _train(out, MPCActorCriticPolicy, pk)
    # move the cost network well off its zero output layer, so that the weights decide the actions
    g = torch.Generator().manual_seed(1)
    last = res.model.policy.mlp_extractor.mpc.cost.net[-1]
    with torch.no_grad():
        last.weight.copy_(0.5 * torch.randn(last.weight.shape, generator=g))
        last.bias.copy_(0.5 * torch.randn(last.bias.shape, generator=g))
    bl.save_agent(res, out)
    return res, out


def test_mpc_headed_agent_reloads_safely_with_the_same_actions(mpc_agent):
    res, out = mpc_agent
    meta = json.loads((out / "agent.json").read_text())
    assert meta["policy"] == "MPCActorCriticPolicy"
    assert meta["policy_kwargs"]["horizon"] == 5
    loaded = bl.load_agent(out)
    pol = loaded.policy
    assert isinstance(pol, MPCActorCriticPolicy)
    assert pol.horizon == 5 and pol.ilqr_options == ILQROptions(max_iter=2) and pol.activation_fn is nn.ReLU
    obs = _obs()
    want, _ = res.model.predict(obs, deterministic=True)  # the trained agent in memory is the reference
    got, _ = loaded.predict(obs, deterministic=True)
    np.testing.assert_array_equal(got, want)
    # the loaded weights matter: the same policy built afresh (zero cost-net output) acts differently
    fresh = bl.make_agent("ppo", TASK, params=dict(TINY), policy=MPCActorCriticPolicy,
                          policy_kwargs=bl.read_agent_meta(out)["policy_kwargs"]
                          | {"ilqr_options": ILQROptions(max_iter=2), "activation_fn": nn.ReLU})
    assert np.abs(fresh.predict(obs, deterministic=True)[0] - want).max() > 1e-3


def test_load_refuses_an_unregistered_policy_name_without_importing_it(mpc_agent, tmp_path):
    _, out = mpc_agent
    for f in ("policy.pt", "agent.json"):
        (tmp_path / f).write_bytes((out / f).read_bytes())
    meta = json.loads((tmp_path / "agent.json").read_text())
    meta["policy"] = "os:system"
    (tmp_path / "agent.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="'os:system'.*not registered"):
        bl.load_agent(tmp_path)
    meta["policy"] = "MPCActorCriticPolicy"
    meta["policy_kwargs"]["activation_fn"] = {"__class__": "builtins.eval"}
    (tmp_path / "agent.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="builtins.eval"):
        bl.load_agent(tmp_path)


def test_what_cannot_be_recorded_is_refused_before_training(tmp_path):
    class Custom(ActorCriticPolicy):
        """An SB3 policy subclass nobody registered: agent.json could not name it."""

    with pytest.raises(TypeError, match="'policy'.*register_policy"):
        _train(tmp_path, Custom)
    with pytest.raises(TypeError, match="policy_kwargs.*'activation_fn'"):
        _train(tmp_path, policy_kwargs={"activation_fn": lambda: nn.Tanh()})
    assert not (tmp_path / "agent.json").exists()


def test_registered_policy_round_trip(tmp_path):
    class Registered(ActorCriticPolicy):
        """An SB3 policy subclass registered under a name for this test."""

    bl.register_policy("RegisteredForTest", Registered)
    try:
        res = _train(tmp_path, Registered, {"net_arch": [8], "activation_fn": nn.ReLU})
        assert json.loads((tmp_path / "agent.json").read_text())["policy"] == "RegisteredForTest"
        loaded = bl.load_agent(tmp_path)
        assert type(loaded.policy) is Registered
        obs = _obs(5, 2)
        np.testing.assert_array_equal(loaded.predict(obs, deterministic=True)[0],
                                      res.model.predict(obs, deterministic=True)[0])
        with pytest.raises(ValueError, match="already taken"):
            bl.register_policy("RegisteredForTest", ActorCriticPolicy)
    finally:
        POLICIES.pop("RegisteredForTest", None)


def test_old_agent_json_without_a_policy_still_loads_as_mlp(tmp_path):
    res = _train(tmp_path)
    meta = json.loads((tmp_path / "agent.json").read_text())
    assert meta["policy"] == "MlpPolicy"
    del meta["policy"], meta["policy_kwargs"]  # the format written before this change
    (tmp_path / "agent.json").write_text(json.dumps(meta))
    obs = _obs(5, 3)
    np.testing.assert_array_equal(bl.load_agent(tmp_path).predict(obs, deterministic=True)[0],
                                  res.model.predict(obs, deterministic=True)[0])


def test_train_refuses_counts_that_are_not_ints(tmp_path):
    """Issue 22 sweep: budget_steps=100.5 trained 100 steps and eval_episodes=1.5 evaluated 1, silently."""
    for kw, name in ((dict(budget_steps=100.5), "budget_steps"), (dict(eval_every=50.5), "eval_every"),
                     (dict(eval_episodes=1.5), "eval_episodes"), (dict(budget_steps=0), "budget_steps")):
        args = dict(budget_steps=64, seed=0, eval_episodes=1) | kw
        with pytest.raises(ValueError, match=f"train: argument '{name}' must be an int"):
            bl.train("ppo", TASK, params=dict(TINY), tensorboard=False, **args)


@pytest.fixture(scope="module")
def mlp_agent(tmp_path_factory):
    out = tmp_path_factory.mktemp("mlp_agent")
    _train(out)
    return out


def _tampered(src, dst, edit):
    for f in ("policy.pt", "agent.json"):
        (dst / f).write_bytes((src / f).read_bytes())
    meta = json.loads((dst / "agent.json").read_text())
    edit(meta)
    (dst / "agent.json").write_text(json.dumps(meta))
    return dst / "agent.json"


@pytest.mark.parametrize("edit, key", [
    (lambda m: m.update(policy_kwargs="abc"), "'policy_kwargs' must be dict"),
    (lambda m: m.update(params=[1, 2]), "'params' must be dict"),
    (lambda m: m.update(seed="0"), "'seed' must be int"),
    (lambda m: m["params"].update(n_steps="32"), "\\['params'\\]: key 'n_steps' must be int"),
    (lambda m: m["params"].update(gamma=True), "'gamma' must be int or float"),
    (lambda m: m["params"].update(use_sde=1), "'use_sde' must be bool"),
    (lambda m: m.update(policy_kwargs={"net_arch": "64"}), "'policy_kwargs'\\]: key 'net_arch' must be list"),
    (lambda m: m.update(policy_kwargs={"activation_fn": "relu"}), "'activation_fn' must be type"),
    (lambda m: m.update(policy_kwargs={"bogus": 1}), "'params' / 'policy_kwargs' do not build a ppo agent"),
    (lambda m: m.update(policy_kwargs={"net_arch": [8]}), "do not fit the policy.*'policy_kwargs'"),
])
def test_a_tampered_agent_json_is_a_value_error_naming_the_file_and_the_key(mlp_agent, tmp_path, edit, key):
    """Wrong types in agent.json's params/policy_kwargs failed deep inside SB3/torch (dict() of a string,
    a str n_steps in a range(), missing keys in load_state_dict) without naming the file or the entry."""
    meta = _tampered(mlp_agent, tmp_path, edit)
    with pytest.raises(ValueError, match=key) as err:
        bl.load_agent(tmp_path)
    assert str(meta) in str(err.value)
