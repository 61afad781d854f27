"""``liecontrol compare`` and :mod:`learning.baselines`: end to end on tiny budgets, safe weights, ``--load``,
the "steps to match the MPC" logic and argument errors."""

import json
import os

import numpy as np
import pytest
import torch

from learning import baselines as bl
from liecontrol import cli

TASK = "PendulumSwingUp"
TINY = ["--budget-steps", "256", "--eval-episodes", "2", "--eval-every", "128", "--mpc-horizon", "10",
        "--quiet"]


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    out = tmp_path_factory.mktemp("compare")
    args = ["compare", TASK, "--algos", "ppo", "sac", "--seeds", "0", "1", "2", "--out", str(out / TASK),
            "--json", str(out / "record.json"), *TINY]
    assert cli.main(args) == 0
    return out


def test_cli_writes_report_curves_and_json(trained):
    d = trained / TASK
    rec = json.loads((trained / "record.json").read_text())
    assert rec == json.loads((d / "compare.json").read_text())
    assert set(rec) == {"env", "mpc", "ppo", "sac", "budget_steps", "seeds"}
    assert rec["env"] == TASK and rec["seeds"] == [0, 1, 2]
    assert rec["budget_steps"] == {"ppo": 256, "sac": 256}
    for name in ("mpc", "ppo", "sac"):
        m = rec[name]
        assert isinstance(m["success_rate"], float) and 0 <= m["success_rate"] <= 1
        assert isinstance(m["return"]["mean"], float) and isinstance(m["return"]["std"], float)
        assert m["step_ms"]["median"] > 0 and m["step_ms_batch1"]["median"] > 0
        assert m["eval_seeds"] == bl.eval_seeds(2)
    assert rec["mpc"]["episodes"] == 2 and rec["mpc"]["horizon"] == 10
    for algo in ("ppo", "sac"):
        m = rec[algo]
        assert m["episodes"] == 6  # 3 training seeds x 2 evaluation episodes, pooled
        assert [p["seed"] for p in m["per_seed"]] == [0, 1, 2]
        assert all(not p["loaded"] and p["train_time_s"] > 0 and p["num_timesteps"] >= 256
                   for p in m["per_seed"])
        c = m["curve"]
        assert c["steps"][0] == 0 and c["steps"][-1] >= 256
        assert len(c["return_mean"]) == len(c["steps"]) == len(c["success_max"])
        assert set(m["steps_to_match"]) == {"success", "return"}
        # the last curve point is the final policy on the same episodes as the final evaluation
        assert np.isclose(c["return_mean"][-1], np.mean([p["return_mean"] for p in m["per_seed"]]))
    report = (d / "report.md").read_text()
    for text in ("| MPC |", "PPO", "SAC", "RL steps to match the MPC", "curves.png", "execute code",
                 "weights_only=True"):
        assert text in report
    assert (d / "curves.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_saved_weights_load_safely_and_act_like_the_trained_agent(trained):
    rec = json.loads((trained / "record.json").read_text())
    obs = np.random.default_rng(0).uniform(-1, 1, (7, 3)).astype(np.float32)
    obs[:, 2] *= 8
    for algo in ("ppo", "sac"):
        d = trained / TASK / "agents" / algo / "seed1"
        state = torch.load(d / "policy.pt", weights_only=True)
        assert state and all(isinstance(v, torch.Tensor) for v in state.values())
        safe = bl.load_agent(d / "policy.pt")
        trusted = bl.load_agent(d / "model.zip", trust_zip=True)  # SB3's own save of the trained model
        np.testing.assert_array_equal(safe.predict(obs, deterministic=True)[0],
                                      trusted.predict(obs, deterministic=True)[0])
        # and it reproduces the trained agent's evaluation exactly
        from learning import evaluate
        r = evaluate(safe, TASK, seeds=bl.eval_seeds(2), num_envs=2, dtype=torch.float32, progress=False,
                     timing_batch1=False)
        assert float(r.returns.mean()) == pytest.approx(rec[algo]["per_seed"][1]["return_mean"], rel=1e-6)


def test_train_then_load_agent_gives_the_same_deterministic_actions(tmp_path):
    res = bl.train("sac", TASK, 150, seed=3, eval_every=100, eval_episodes=1, out_dir=tmp_path)
    assert res.steps == [0, 100, 150] and len(res.returns) == 3
    meta = json.loads((tmp_path / "agent.json").read_text())
    assert set(meta) >= {"algo", "task", "seed", "params", "curve"}
    again = bl.load_agent(tmp_path)
    obs = np.random.default_rng(1).uniform(-1, 1, (5, 3)).astype(np.float32)
    np.testing.assert_array_equal(res.model.predict(obs, deterministic=True)[0],
                                  again.predict(obs, deterministic=True)[0])
    with pytest.raises(ValueError, match="trust_zip"):
        bl.load_agent(tmp_path / "model.zip")


def test_load_reuses_the_weights_without_training(trained, tmp_path):
    first = json.loads((trained / "record.json").read_text())
    args = ["compare", TASK, "--algos", "ppo", "sac", "--seeds", "0", "1", "2", "--no-mpc", "--out",
            str(tmp_path), "--load", str(trained / TASK), "--json", str(tmp_path / "r.json"), *TINY]
    assert cli.main(args) == 0
    rec = json.loads((tmp_path / "r.json").read_text())
    assert rec["mpc"] is None
    assert not (tmp_path / "agents").exists()  # nothing trained, nothing saved
    for algo in ("ppo", "sac"):
        assert rec[algo]["loaded"] and all(p["loaded"] for p in rec[algo]["per_seed"])
        assert rec[algo]["curve"] == first[algo]["curve"]  # the saved curves, not recomputed
        for p, q in zip(rec[algo]["per_seed"], first[algo]["per_seed"]):
            assert p["return_mean"] == pytest.approx(q["return_mean"], rel=1e-6)
            assert p["train_time_s"] == q["train_time_s"]
    missing = ["compare", TASK, "--algos", "ppo", "--seeds", "7", "--no-mpc", "--out", str(tmp_path),
               "--load", str(trained / TASK), *TINY]
    assert cli.main(missing) == 2


def test_steps_to_match_on_synthetic_curves():
    steps = [0, 100, 200, 300]
    assert bl.steps_to_match(steps, [0.0, 0.5, 0.96, 1.0], 0.95) == 200
    assert bl.steps_to_match(steps, [0.0, 0.5, 0.9, 0.94], 0.95) is None
    assert bl.steps_to_match(steps, [0.0, 1 / 3 + 1 / 3 + 1 / 3, 1.0, 1.0], 1.0) == 100  # rounding
    assert bl.steps_to_match(steps, [-900, -400, -150, -140], -150.0) == 200  # returns: higher is better
    assert bl.steps_to_match(steps, [0.0, 1.0, 1.0, 1.0], float("nan")) is None
    curves = [{"steps": [0, 100, 200], "returns": [-9, -5, -1], "success": [0, 0.5, 1]},
              {"steps": [0, 100, 200, 300], "returns": [-7, -3, -3, -2], "success": [0, 0, 0.5, 1]}]
    st, mean, lo, hi = bl.mean_curve(curves, "success")
    assert st.tolist() == [0, 100, 200] and mean.tolist() == [0, 0.25, 0.75]
    assert lo.tolist() == [0, 0, 0.5] and hi.tolist() == [0, 0.5, 1]
    assert bl.steps_to_match(st, mean, 0.75) == 200


def test_unknown_env_and_bad_budget_name_the_argument(capsys, tmp_path):
    with pytest.raises(SystemExit) as e:
        cli.main(["compare", "NoSuchTask"])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "TASK" in err and "NoSuchTask" in err and "PendulumSwingUp" in err
    with pytest.raises(SystemExit) as e:
        cli.main(["compare", "liecontrol/PendulumSwingUp-v0", "--budget-steps", "dqn=5", "--out",
                  str(tmp_path)])
    assert e.value.code == 2 and "--budget-steps" in capsys.readouterr().err


def test_defaults_and_budget_parsing():
    from liecontrol.compare import parse_budgets, resolve_env

    assert resolve_env("liecontrol/CartPoleSwingUp-v0") == "CartPoleSwingUp"
    assert bl.hyperparams("ppo", TASK)["gamma"] == 0.9
    assert bl.hyperparams("sac", TASK)["learning_rate"] == 1e-3
    assert bl.hyperparams("ppo", "ArmReach") == bl.PPO_DEFAULTS["*"]
    assert parse_budgets(None, ["ppo", "sac"], TASK) == bl.DEFAULT_BUDGETS[TASK]
    assert parse_budgets(["1000", "sac=50"], ["ppo", "sac"], TASK) == {"ppo": 1000, "sac": 50}
    with pytest.raises(ValueError, match="budget"):
        parse_budgets(["0"], ["ppo"], TASK)


def test_agents_trained_in_worker_processes_equal_those_trained_in_process(trained, tmp_path):
    """The fixture trained its six agents in worker processes (--jobs default: one per core); training
    PPO seeds 0 and 1 again in this process (--jobs 1) gives the same curves and evaluations."""
    if (os.cpu_count() or 1) < 2:
        pytest.skip("one CPU core: the fixture trained in process too, nothing to compare")
    args = ["compare", TASK, "--algos", "ppo", "--seeds", "0", "1", "--out", str(tmp_path), "--no-mpc",
            "--jobs", "1", "--json", str(tmp_path / "r.json"), *TINY]
    assert cli.main(args) == 0
    one = json.loads((tmp_path / "r.json").read_text())["ppo"]["per_seed"]
    many = json.loads((trained / "record.json").read_text())["ppo"]["per_seed"][:2]
    for a, b in zip(one, many):
        assert a["seed"] == b["seed"] and a["num_timesteps"] == b["num_timesteps"]
        assert a["return_mean"] == b["return_mean"] and a["success_rate"] == b["success_rate"]
    assert "1 training process" in (tmp_path / "report.md").read_text()
    jobs = min(os.cpu_count(), 6)  # six agents in the fixture
    assert f"{jobs} training process" in (trained / TASK / "report.md").read_text()


def test_bad_jobs_is_refused(tmp_path):
    with pytest.raises(ValueError, match="'jobs'"):
        from liecontrol.compare import compare
        compare(TASK, jobs=0, out=tmp_path, mpc=False)


def test_learning_curve_points_before_training_after_each_multiple_and_at_the_end(trained):
    """Each saved curve: a point before training (0 steps), at the first rollout boundary at or past each
    multiple of --eval-every (the policy then is the one updated on exactly that many steps), and after
    the last step."""
    every = int(TINY[TINY.index("--eval-every") + 1])
    for algo in ("ppo", "sac"):
        meta = bl.read_agent_meta(trained / TASK / "agents" / algo / "seed0" / "policy.pt")
        steps, last, p = meta["curve"]["steps"], meta["num_timesteps"], meta["params"]
        rollout = p.get("n_envs", 1) * (p["n_steps"] if algo == "ppo" else p.get("train_freq", 1))
        assert steps[0] == 0 and steps[-1] == last and steps == sorted(set(steps))
        for m in range(every, last, every):
            assert any(m <= s < m + rollout for s in steps), (algo, m, steps)


def test_workers_report_their_progress_to_the_command(tmp_path, capsys):
    """With worker processes (--jobs 2), each agent's evaluation lines reach the command (a queue) and
    move its progress bar to the budget."""
    args = ["compare", TASK, "--algos", "sac", "--seeds", "0", "1", "--no-mpc", "--jobs", "2", "--out",
            str(tmp_path), *[a for a in TINY if a != "--quiet"]]
    assert cli.main(args) == 0
    err = capsys.readouterr().err
    for s in (0, 1):
        assert f"{TASK} sac seed {s}: 128 steps, eval return" in err  # a line logged in a worker
        assert f"{TASK} sac seed {s}: 100%" in err and "256/256" in err  # its bar, full
