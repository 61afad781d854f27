"""``liecontrol learn``: MPC-headed PPO against plain PPO at equal steps and equal wall time, and the
behaviour-cloning study, end to end on tiny budgets; the wall-time stop of
:func:`learning.baselines.train`."""

import json

import pytest

from learning import baselines as bl
from liecontrol import cli

TASK = "PendulumSwingUp"


def test_train_stops_at_its_wall_time_budget():
    res = bl.train("ppo", TASK, 10**7, seed=0, eval_every=10**6, eval_episodes=1, max_train_s=1.0,
                   tensorboard=False)
    # stopped by the clock (at the first environment step past it), far short of the step budget
    assert res.num_timesteps < 10**6 and res.train_time_s >= 1.0
    assert res.steps[-1] == res.num_timesteps  # the final evaluation is of the stopped policy


def test_mpc_ppo_command_writes_report_and_json(tmp_path):
    out = tmp_path / "learn"
    args = ["learn", "mpc-ppo", TASK, "--budget-steps", "64", "--eval-episodes", "2", "--mpc-horizon", "5",
            "--max-iter", "1", "--out", str(out), "--json", str(tmp_path / "r.json"), "--quiet"]
    assert cli.main(args) == 0
    rec = json.loads((tmp_path / "r.json").read_text())
    assert rec == json.loads((out / "learn.json").read_text())
    assert rec["env"] == TASK and rec["steps"] == 64 and rec["seeds"] == [0]
    assert rec["eval_seeds"] == bl.eval_seeds(2)
    assert rec["mpc_policy_kwargs"] == {"task": TASK, "max_iter": 1, "horizon": 5}
    mp, same, eq_t = rec["mpc_ppo"][0], rec["ppo_equal_steps"][0], rec["ppo_equal_time"][0]
    assert mp["num_timesteps"] >= 64 and same["num_timesteps"] == mp["num_timesteps"]
    # equal wall time: plain PPO trained at least as long as the MPC-headed run, hence many more steps
    assert eq_t["train_time_s"] >= mp["train_time_s"] and eq_t["num_timesteps"] > mp["num_timesteps"]
    for r in (mp, same, eq_t):
        assert 0 <= r["success_rate"] <= 1 and isinstance(r["return_mean"], float)
        assert r["curve"]["steps"][0] == 0
    t = rec["step_ms_batch1"]
    assert t["mpc_ppo"] > 0 and t["ppo"] > 0 and t["ratio"] == pytest.approx(t["mpc_ppo"] / t["ppo"])
    report = (out / "report.md").read_text()
    assert "equal steps" in report and "equal time" in report and "Per-step compute" in report
    assert (out / "curves.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_bc_command_writes_the_study(tmp_path):
    import liecontrol.learn as learn
    from learning import MPCExpert, PendulumSwingUp

    task = PendulumSwingUp(max_episode_steps=12)
    rec = learn.bc(task, counts=(1,), heldout=1, eval_episodes=2, mlp_epochs=2, mpc_steps=1, out=tmp_path,
                   expert=MPCExpert(task, horizon=6), num_envs=2, mlp_kwargs={"hidden": (8,)},
                   mpc_kwargs={"horizon": 6, "window": 6})
    d = tmp_path
    saved = json.loads((d / "bc.json").read_text())
    assert saved["env"] == TASK
    pairs = [(r["learner"], r["demos"]) for r in saved["records"]]
    assert pairs == [("expert", None), ("mlp", 1), ("mpc", 1)]
    assert "| mlp | 1 |" in (d / "bc.md").read_text()
    assert (d / "bc.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert rec["_files"]["json"] == str(d / "bc.json")


def test_bad_arguments_exit_2(capsys):
    for argv in (["learn", "bc", TASK, "--demos", "a", "b"], ["learn", "bc", TASK, "--demos", "-1", "2"],
                 ["learn", "mpc-ppo", "NoSuchTask"], ["learn", "mpc-ppo", TASK, "--budget-steps", "0"]):
        with pytest.raises(SystemExit) as e:
            cli.main(argv)
        assert e.value.code == 2
        err = capsys.readouterr().err
        assert ("--demos" if "--demos" in argv else "--budget-steps" if "0" in argv else "TASK") in err


def test_mpc_head_ppo_settings_cap_the_learning_rate_and_drop_gsde():
    from learning.envs.single import make_task
    from liecontrol.learn import MPC_HEAD_MAX_LR, _mpc_ppo_params

    task = make_task("PendulumSwingUp")
    plain = bl.hyperparams("ppo", task)
    head = _mpc_ppo_params(task)
    assert plain["learning_rate"] > MPC_HEAD_MAX_LR and head["learning_rate"] == MPC_HEAD_MAX_LR
    assert "use_sde" in plain and "use_sde" not in head and "sde_sample_freq" not in head
    assert {k: v for k, v in head.items() if k != "learning_rate"} == \
        {k: v for k, v in plain.items() if k not in ("learning_rate", "use_sde", "sde_sample_freq")}


def test_tensorboard_flag_reaches_training(tmp_path, monkeypatch):
    """``learn mpc-ppo --tensorboard``: every run is trained with TensorBoard on, beside its saved agent in
    OUT/agents/RUN/seedS (checked on the arguments train receives: tensorboard is not a dependency)."""
    import liecontrol.learn as learn

    seen = []

    def fake_train(*a, **kw):
        seen.append(kw)
        raise RuntimeError("stop")

    monkeypatch.setattr(bl, "train", fake_train)
    with pytest.raises(RuntimeError, match="stop"):
        learn.mpc_ppo(TASK, steps=64, out=tmp_path, tensorboard=True)
    assert seen[0]["tensorboard"] is True and seen[0]["out_dir"] == tmp_path / "agents" / "mpc_ppo" / "seed0"
    seen.clear()
    with pytest.raises(RuntimeError, match="stop"):
        learn.mpc_ppo(TASK, steps=64, out=tmp_path)
    assert seen[0]["tensorboard"] is False and "out_dir" not in seen[0]


def test_mpc_ppo_on_the_quadrotor_with_the_robustness_study(tmp_path):
    """The manifold head (error-state MPC) through the CLI; ``--robustness`` evaluates each trained policy
    (and the nominal expert once) unchanged on the task's perturbations, and the report tabulates them."""
    from learning.robustness import default_perturbations

    out = tmp_path / "learn"
    args = ["learn", "mpc-ppo", "QuadrotorCircle", "--budget-steps", "32", "--eval-episodes", "2",
            "--mpc-horizon", "5", "--per-step", "--robustness", "--no-equal-time", "--out", str(out),
            "--json", str(tmp_path / "r.json"), "--quiet"]
    assert cli.main(args) == 0
    rec = json.loads((tmp_path / "r.json").read_text())
    assert rec["mpc_policy_kwargs"] == {"task": "QuadrotorCircle", "max_iter": 5, "horizon": 5,
                                        "per_step": True}
    assert rec["ppo_equal_time"] == [] and len(rec["mpc_ppo"]) == len(rec["ppo_equal_steps"]) == 1
    labels = list(default_perturbations("QuadrotorCircle"))
    got = [(r["policy"], r["perturbation"]) for r in rec["robustness"]]
    assert got == [(p, lab) for p in ("mpc_ppo", "ppo_equal_steps", "mpc_expert") for lab in labels]
    nominal = {r["policy"]: r for r in rec["robustness"] if r["perturbation"] == "nominal"}
    # the nominal row is the same evaluation as the curve's last point (same seeds, same policy)
    assert nominal["mpc_ppo"]["return_mean"] == pytest.approx(rec["mpc_ppo"][0]["return_mean"], rel=1e-5)
    assert "## Robustness" in (out / "report.md").read_text()


def test_robustness_rows_aggregate_over_seeds():
    from liecontrol.learn import robustness_rows

    recs = [{"policy": "a", "perturbation": "nominal", "return_mean": r, "success_rate": s, "seed": i}
            for i, (r, s) in enumerate([(10.0, 1.0), (20.0, 0.5), (30.0, 0.0)])]
    (row,) = robustness_rows({"robustness": recs})
    assert row == {"policy": "a", "perturbation": "nominal", "seeds": 3, "return_mean": 20.0,
                   "return_min": 10.0, "return_max": 30.0, "success": 0.5}


def test_only_mpc_ppo_takes_the_quadrotors():
    from liecontrol._options import MPC_PPO_TASKS, learn_task, mpc_ppo_task

    assert mpc_ppo_task("quadrotorc") == "QuadrotorCircle" and "QuadrotorFigureEight" in MPC_PPO_TASKS
    import argparse

    with pytest.raises(argparse.ArgumentTypeError, match="QuadrotorCircle cannot be learnt"):
        learn_task("QuadrotorCircle")
