"""learning.bc: demonstrations (batched collection against single-env replay, safe save/load), MLP
behaviour cloning, MPC cost learning through the differentiable MPC, and the study's records."""

import json
import math
from dataclasses import dataclass

import pytest
import torch

from learning import PendulumSwingUp, TaskEnv
from learning.bc import (
    Demos,
    LearnableQuadraticCost,
    action_mse,
    bc_study,
    collect_demos,
    expert_cost_weights,
    format_table,
    mpc_action_mse,
    train_mlp_policy,
    train_mpc_cost,
)
from learning.envs.single import make_task
from learning.policies import MPCExpert

D64 = torch.float64



@dataclass(frozen=True, eq=False)
class NearUpright(PendulumSwingUp):
    """The pendulum started within 0.6 rad of upright (balancing: a well-posed, fast MPC problem)."""

    def initial_state(self, noise):
        return torch.stack([math.pi + (2 * noise[..., 0] - 1) * 0.6, 2 * noise[..., 1] - 1], -1)


def linear_expert(obs):
    """A saturated linear feedback on the angle from upright and the speed."""
    phi = torch.atan2(obs[..., 1], obs[..., 0])
    return (-(1.5 * phi + 0.4 * obs[..., 2])).clamp(-1.0, 1.0)[:, None]


def test_demos_save_load_round_trip(tmp_path):
    task = PendulumSwingUp(max_episode_steps=7)
    d = collect_demos(lambda o: 0.3 * torch.sin(o[:, 2:3] * 5.0), task, episodes=3, seed=4, num_envs=2)
    assert len(d) == 21 and d.episodes == 3 and d.task == "PendulumSwingUp"
    assert d.episode.tolist() == sorted(d.episode.tolist()) and d.step[:7].tolist() == list(range(7))
    assert d.seeds.tolist() == [4, 5, 6] and d.length.tolist() == [7, 7, 7]
    assert d.obs.dtype == D64 and d.action.shape == (21, 1) and bool((d.action.abs() <= 1).all())
    path = tmp_path / "demos.pt"
    d.save(path)
    raw = torch.load(path, weights_only=True)  # plain tensors and strings: no pickled objects
    assert isinstance(raw, dict) and all(isinstance(v, (torch.Tensor, str)) for v in raw.values())
    e = Demos.load(path)
    for k in ("obs", "action", "state", "episode", "step", "seeds", "returns", "success", "length"):
        assert torch.equal(getattr(e, k), getattr(d, k)), k
    assert e.task == d.task
    tr, held = e.split(1)
    assert (tr.episodes, held.episodes, len(tr), len(held)) == (2, 1, 14, 7)
    assert torch.equal(held.obs, d.obs[14:]) and held.seeds.tolist() == [6]
    assert held.episode.unique().tolist() == [0]
    torch.save({"format": "something else"}, tmp_path / "bad.pt")
    with pytest.raises(ValueError, match="not a"):
        Demos.load(tmp_path / "bad.pt")


def test_collect_demos_batched_equals_single_env():
    task = PendulumSwingUp(max_episode_steps=15)
    d = collect_demos(MPCExpert(task), task, episodes=2, seed=11, num_envs=2, dtype=D64)
    assert len(d) == 30
    for i in range(2):
        rows = d.episode == i
        obs, act, steps = d.obs[rows], d.action[rows], d.step[rows]
        assert steps.tolist() == list(range(15))
        env = TaskEnv(task, dtype=D64)
        o, _ = env.reset(seed=11 + i)
        ret = 0.0
        for t in range(15):
            assert torch.allclose(torch.as_tensor(o), obs[t], rtol=0, atol=1e-12)
            o, r, *_ = env.step(act[t].numpy())
            ret += r
        assert ret == pytest.approx(float(d.returns[i]), abs=1e-9)
        # and the batched expert's actions are those of the expert run on this episode alone
        solo = MPCExpert(task)
        a = torch.cat([solo.act(obs[t:t + 1]) for t in range(3)])
        assert torch.allclose(a, act[:3], rtol=0, atol=1e-9)


def test_mlp_bc_beats_trivial_predictor():
    task = PendulumSwingUp(max_episode_steps=40)
    d = collect_demos(linear_expert, task, episodes=12, seed=0, num_envs=12)
    tr, held = d.split(3)
    model, hist = train_mlp_policy(tr, hidden=(32, 32), epochs=60, lr=3e-3, batch_size=64, seed=1, val=held)
    mse = action_mse(lambda o: model(o.float()), held)
    trivial = float(((held.action - tr.action.mean(0)) ** 2).mean())
    zero = float((held.action ** 2).mean())
    assert mse < 0.15 * min(trivial, zero), (mse, trivial, zero)
    assert hist["loss"][-1] < 0.3 * hist["loss"][0] and len(hist["val_mse"]) == 60
    out = model(held.obs.float())
    assert bool((out.abs() <= 1).all())
    # deterministic given the seed
    model2, hist2 = train_mlp_policy(tr, hidden=(32, 32), epochs=3, lr=3e-3, batch_size=64, seed=1)
    model3, hist3 = train_mlp_policy(tr, hidden=(32, 32), epochs=3, lr=3e-3, batch_size=64, seed=1)
    assert hist2["loss"] == hist3["loss"]
    assert all(torch.equal(a, b) for a, b in zip(model2.state_dict().values(), model3.state_dict().values()))


def test_mpc_cost_learning_moves_towards_the_expert():
    task = NearUpright(max_episode_steps=20)
    H = 10
    d = collect_demos(MPCExpert(task, horizon=H), task, episodes=6, seed=3, num_envs=6)
    tr, held = d.split(2)
    mpc, hist = train_mpc_cost(tr, task, horizon=H, steps=8, window=10, batch_size=4, lr=0.3, val=held)
    assert hist["val_mse_expert_cost"] < 1e-12  # the expert's own cost, teacher-forced, is the expert
    assert hist["val_mse"] < 0.5 * hist["val_mse_init"], (hist["val_mse"], hist["val_mse_init"])
    first_window = hist["loss"][0::2]  # every pass replays all 4 episodes: the same first 10 steps
    assert first_window[-1] < 0.5 * first_window[0], first_window
    w, we = hist["weights"], hist["weights_expert"]
    assert we["q"] == pytest.approx([1.0, 0.1]) and we["r"] == pytest.approx([0.001])
    assert we["terminal_factor"] == pytest.approx(10.0)
    # the control weight relative to the angle weight moved from 1 towards the expert's 0.001
    assert w["r_rel"][0] < 0.5 * hist["weights_init"]["r_rel"][0]
    assert mpc_action_mse(mpc, held, task) == pytest.approx(hist["val_mse"], rel=1e-9)
    # the minibatch modes run too
    for mode in ("demo", "cold"):
        _, h = train_mpc_cost(tr, task, horizon=H, steps=1, batch_size=8, warm_start=mode)
        assert len(h["loss"]) == 1 and math.isfinite(h["loss"][0])


def test_learnable_cost_and_expert_weights():
    c = LearnableQuadraticCost(torch.tensor([2.0, 0.5]), torch.tensor([0.1]), torch.zeros(2), 4, 10.0)
    qc = c()
    assert qc.Q.shape == (5, 2, 2) and torch.allclose(qc.Q[-1], 10 * qc.Q[0])
    assert c.weights()["q_rel"] == pytest.approx([1.0, 0.25])
    assert [n for n, _ in c.named_parameters()] == ["log_q", "log_r"]
    assert "target" in dict(LearnableQuadraticCost(torch.ones(2), torch.ones(1), torch.zeros(2), 4,
                                                   learn_target=True).named_parameters())
    with pytest.raises(ValueError, match="positive"):
        LearnableQuadraticCost(torch.tensor([1.0, 0.0]), torch.ones(1), torch.zeros(2), 4)
    assert expert_cost_weights(make_task("CartPoleSwingUp"), 5)["terminal_factor"] == pytest.approx(100.0)
    with pytest.raises(ValueError, match="not a diagonal QuadraticCost"):
        expert_cost_weights(make_task("ArmReach"), 5)


def test_bc_study_records():
    task = NearUpright(max_episode_steps=12)
    recs = bc_study(task, (1, 2), heldout_episodes=1, eval_episodes=2, num_envs=2,
                    expert=MPCExpert(task, horizon=6), mlp_kwargs={"epochs": 3, "hidden": (8,)},
                    mpc_kwargs={"steps": 1, "horizon": 6, "window": 6})
    json.dumps(recs, allow_nan=False)
    assert [(r["learner"], r["demos"]) for r in recs] == [("expert", None), ("mlp", 1), ("mpc", 1),
                                                          ("mlp", 2), ("mpc", 2)]
    keys = {"task", "learner", "demos", "train_samples", "heldout_mse", "train_mse", "success_rate",
            "return_mean", "return_std", "final_error_mean", "eval_episodes", "eval_time_s", "train_time_s"}
    for r in recs:
        assert keys <= set(r), keys - set(r)
        assert r["eval_episodes"] == 2 and r["task"] == "PendulumSwingUp"
    mpc = [r for r in recs if r["learner"] == "mpc"]
    assert {"weights", "weights_expert", "heldout_mse_init", "heldout_mse_expert_cost"} <= set(mpc[0])
    assert mpc[1]["train_samples"] == 24 and recs[1]["train_samples"] == 12
    assert "heldout_mse" in format_table(recs)


def test_collect_demos_clips_a_huge_float64_action_and_refuses_float_counts():
    """Issue 22 item 13 / sweep: in float32 a float64 1e39 expert action became inf (the episode ended at
    step 0, nothing recorded), where the env clips it; a float num_envs was truncated."""
    expert = lambda o: torch.full((o.shape[0], 1), 1e39, dtype=torch.float64)  # noqa: E731
    d = collect_demos(expert, "PendulumSwingUp", episodes=2, num_envs=2, dtype=torch.float32,
                      max_episode_steps=5)
    assert d.length.tolist() == [5, 5] and len(d) == 10
    assert bool((d.action == 1.0).all())
    with pytest.raises(ValueError, match="'num_envs'"):
        collect_demos(expert, "PendulumSwingUp", episodes=2, num_envs=1.5)
