"""learning.baselines and ``liecontrol compare`` on foreign gymnasium ids (``Pendulum-v1``): SB3's own env of
``gymnasium.make(id)`` seeded as the task path, the rl-baselines3-zoo's hyperparameters, learning curves
evaluated on the id, the compare report with the zoo's published figures, the CLI."""

from __future__ import annotations

import json

import gymnasium as gym
import numpy as np
import pytest
import torch

from learning import baselines as bl
from learning._policy_io import decode, encode
from learning.zoo_hyperparams import ZOO_DEFAULT, ZOO_HYPERPARAMS

ID = "Pendulum-v1"


def _returns_by_hand(model, seeds):
    """Deterministic episodes of an SB3 model in a hand-written loop on gym.make(ID)."""
    out = []
    for s in seeds:
        env = gym.make(ID)
        obs, _ = env.reset(seed=s)
        total, done = 0.0, False
        while not done:
            a, _ = model.predict(obs, deterministic=True)
            obs, r, term, trunc, _ = env.step(a)
            total += float(r)
            done = term or trunc
        out.append(total)
        env.close()
    return np.asarray(out)


def _without_model() -> str:
    """A continuous gymnasium id without a registered EnvModel (models are added over time)."""
    from learning.env_models import ENV_MODELS

    ids = [i for i in ("Swimmer-v5", "Walker2d-v5", "Ant-v5", "Pusher-v5", "Hopper-v5")
           if i not in ENV_MODELS]
    assert ids, "every candidate id has a model now: add one without"
    return ids[0]


def test_hyperparams_are_the_zoo_entries_and_the_task_path_is_unchanged():
    assert bl.hyperparams("td3", ID) == ZOO_HYPERPARAMS[ID]["td3"]
    assert bl.hyperparams("ppo", "MountainCarContinuous-v0")["policy_kwargs"] == {"log_std_init": -3.29,
                                                                                  "ortho_init": False}
    assert bl.hyperparams("sac", "InvertedPendulum-v5") == ZOO_DEFAULT["sac"]  # no tuned zoo entry
    hc = bl.hyperparams("ppo", "HalfCheetah-v5")  # the zoo's activation_fn=nn.ReLU, recordable as JSON
    assert decode(json.loads(json.dumps(encode(hc, "params")))) == hc
    assert bl.make_agent("ppo", "HalfCheetah-v5", params=hc).policy.activation_fn is torch.nn.ReLU
    hp = bl.hyperparams("td3", ID)
    hp["policy_kwargs"]["net_arch"].append(1)  # a copy: the table is untouched
    assert ZOO_HYPERPARAMS[ID]["td3"]["policy_kwargs"]["net_arch"] == [400, 300]
    assert bl.hyperparams("ppo", "PendulumSwingUp") == bl.PPO_DEFAULTS["PendulumSwingUp"]
    assert bl.default_budget("sac", "PendulumSwingUp") == bl.DEFAULT_BUDGETS["PendulumSwingUp"]["sac"]
    assert bl.default_budget("td3", "PendulumSwingUp") == bl.DEFAULT_BUDGETS["PendulumSwingUp"]["sac"]
    assert bl.default_budget("td3", ID) == bl.FOREIGN_BUDGETS[ID]["td3"]
    assert bl.default_budget("ppo", "Reacher-v5") == bl.FOREIGN_BUDGETS["*"]["ppo"]


def test_make_agent_on_a_gym_id_seeds_its_envs_like_the_task_path():
    from stable_baselines3 import TD3
    from stable_baselines3.common.noise import NormalActionNoise, OrnsteinUhlenbeckActionNoise

    model = bl.make_agent("td3", ID, seed=3, num_envs=2)
    assert isinstance(model, TD3) and model.env.num_envs == 2
    assert isinstance(model.action_noise, NormalActionNoise)
    assert np.allclose(model.action_noise._sigma, 0.1) and model.learning_starts == 10_000
    sizes = [m.out_features for m in model.actor.mu if isinstance(m, torch.nn.Linear)]
    assert sizes == [400, 300, 1]  # the zoo's net_arch, one action
    obs = model.env.reset()
    for i in range(2):  # env i of training seed s has the env seed 1000 s + i
        ref, _ = gym.make(ID).reset(seed=bl.train_env_seed(3) + i)
        np.testing.assert_allclose(obs[i], ref)
    mc = bl.make_agent("td3", "MountainCarContinuous-v0")
    assert isinstance(mc.action_noise, OrnsteinUhlenbeckActionNoise)
    assert np.allclose(mc.action_noise._sigma, 0.5)
    ppo = bl.make_agent("ppo", ID, params=dict(bl.hyperparams("ppo", ID), clip_range="lin_0.4"))
    assert ppo.clip_range(1.0) == pytest.approx(0.4) and ppo.clip_range(0.5) == pytest.approx(0.2)


def test_bad_foreign_input_raises_clear_errors():
    with pytest.raises(ValueError, match="only SB3's own policies"):
        bl.make_agent("ppo", ID, policy="MPCActorCriticPolicy")
    with pytest.raises(TypeError, match="the action space must be a gymnasium.spaces.Box"):
        bl.make_agent("sac", gym.make("CartPole-v1"))
    with pytest.raises(ValueError, match="noise_type"):
        bl.make_agent("td3", ID, params={"noise_type": "pink"})
    with pytest.raises(ValueError, match="argument 'algo'"):
        bl.hyperparams("ddpg", ID)


def test_train_on_a_gym_id_records_a_curve_evaluated_on_the_id(tmp_path):
    params = dict(bl.hyperparams("sac", ID), learning_starts=100)
    res = bl.train("sac", ID, 300, seed=0, eval_every=150, eval_episodes=2, params=params,
                   out_dir=tmp_path, tensorboard=False)
    assert res.task == ID and res.steps == [0, 150, 300] and res.num_timesteps == 300
    assert np.isnan(res.success).all()  # Pendulum-v1 defines no success
    # the last curve point is the trained policy's mean return on the held-out seeds, as a hand loop gives
    ref = _returns_by_hand(res.model, bl.eval_seeds(2))
    assert res.returns[-1] == pytest.approx(ref.mean(), rel=1e-4)
    meta = json.loads((tmp_path / "agent.json").read_text())
    assert meta["task"] == ID and meta["curve"]["success"] == [None] * 3
    loaded = bl.load_agent(tmp_path)  # rebuilt from policy.pt + agent.json on the id
    obs = np.stack([gym.make(ID).reset(seed=s)[0] for s in range(5)])
    np.testing.assert_allclose(loaded.predict(obs, deterministic=True)[0],
                               res.model.predict(obs, deterministic=True)[0], rtol=1e-6)
    # TD3 with the zoo's learning_starts above the budget: noted, never updated
    td3 = bl.train("td3", ID, 200, eval_every=200, eval_episodes=1)
    assert any("never updated" in n for n in td3.notes) and td3.returns[0] == td3.returns[-1]


def test_compare_on_a_gym_id_reports_returns_zoo_and_steps_to_match(tmp_path):
    from liecontrol.compare import compare

    rec = compare(ID, algos=("sac",), budget_steps={"sac": 200}, seeds=(0,), eval_episodes=2, eval_every=100,
                  out=tmp_path, jobs=1, mpc_horizon=8)
    assert rec["foreign"] and rec["env"] == ID
    mpc, sac = rec["mpc"], rec["sac"]
    assert mpc["success_rate"] is None and sac["success_rate"] is None
    assert mpc["step_ms_batch1"]["median"] > 0 and sac["step_ms_batch1"]["median"] > 0
    curve = sac["curve"]
    assert curve["steps"] == [0, 100, 200]
    want = bl.steps_to_match(curve["steps"], curve["return_mean"], mpc["return"]["mean"])
    assert sac["steps_to_match"]["return"] == want
    report = (tmp_path / "report.md").read_text()
    assert "rl-baselines3-zoo published" in report and "-157.0 ± 88.7 after 20k steps" in report
    assert "best published: TD3 -151.9" in report and "steps to match MPC return" in report
    assert f"{mpc['return']['mean']:.1f} ± {mpc['return']['std']:.1f}" in report
    assert "success rate" not in report.split("## Results")[1].split("\n")[2]  # no success column
    # agents only (no MPC): runs, and there is nothing to match
    rec2 = compare(ID, algos=("ppo",), budget_steps={"ppo": 256}, seeds=(0,), eval_episodes=1,
                   out=tmp_path / "nompc", jobs=1, mpc=False)
    assert rec2["mpc"] is None and rec2["ppo"]["steps_to_match"]["return"] is None


def test_compare_refuses_a_gym_id_without_a_model():
    from liecontrol._args import OptionError
    from liecontrol.compare import compare

    with pytest.raises(OptionError, match="no model is registered.*--no-mpc"):
        compare(_without_model(), algos=("sac",), budget_steps={"sac": 10}, seeds=(0,))


def test_cli_compare_on_a_gym_id(tmp_path, capsys):
    from liecontrol import _args, cli

    assert _args.env_name(ID) == ID and _args.env_name("pendulum") == "PendulumSwingUp"
    with pytest.raises(Exception, match="gymnasium id"):
        _args.env_name("NoSuchEnv-v7")
    d = str(tmp_path)
    rc = cli.main(["compare", ID, "--algos", "td3", "--budget-steps", "150", "--seeds", "0",
                   "--eval-episodes", "1", "--mpc-horizon", "5", "--jobs", "1", "--quiet", "--out", d])
    out = capsys.readouterr().out
    assert rc == 0
    assert "zoo_published" in out and "steps_to_match_return" in out and "-151.9 ± 90.2" in out
    assert json.loads((tmp_path / "compare.json").read_text())["td3"]["num_timesteps"] == 150
    rc = cli.main(["compare", _without_model(), "--algos", "sac", "--quiet", "--out", d])
    assert rc == 2 and "--no-mpc" in capsys.readouterr().err
