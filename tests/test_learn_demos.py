"""``liecontrol learn costs|primitives|dynamics|manifold`` (issue 26 §8): each pipeline end to end on small
settings — its files, its JSON record (the runs of ``dynamics`` with exactly the documented keys), the values
it learns against the values the demos were generated with, exit status 1 when a check fails, and bad
arguments refused by name with status 2."""

import json
import math

import pytest

from liecontrol import cli, learn_demos

PNG = b"\x89PNG\r\n\x1a\n"


def _files(out, name):
    assert (out / f"{name}.png").read_bytes()[:8] == PNG
    report = (out / "report.md").read_text()
    assert report.startswith(f"# liecontrol learn {name}") and "## Checks" in report
    return json.loads((out / f"{name}.json").read_text()), report


def test_help_lists_the_four_pipelines(capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(["learn", "--help"])
    assert e.value.code == 0
    text = capsys.readouterr().out
    for name in learn_demos.PIPELINES:
        assert name in text


def test_costs_recovers_the_weights_and_the_via_point(tmp_path):
    out = tmp_path / "costs"
    assert cli.main(["learn", "costs", "--out", str(out), "--json", str(tmp_path / "c.json"), "--quiet"]) == 0
    rec, report = _files(out, "costs")
    assert rec == json.loads((tmp_path / "c.json").read_text())
    assert all(rec["checks"].values()) and set(rec["tolerances"]) == set(learn_demos.COSTS_TOL)
    le = rec["learned"]  # against the expert's weights the demos were generated with
    assert le["Q"] == pytest.approx([2.0, 0.5, 0.3, 0.1], rel=1e-3)
    assert le["R"] == pytest.approx([1.0, 3.0], rel=1e-3) and le["R"][0] == 1.0  # R_00 fixed: the scale
    assert le["terminal_factor"] == pytest.approx(5.0, rel=1e-3)
    assert le["via_target"] == pytest.approx([0.6, 1.1], abs=1e-3)
    assert le["via_time"] == pytest.approx(12.4, abs=0.05)
    mi = rec["minimal_intervention"]
    assert len(mi["variance"]) == 31 and len(mi["gain_norm"]) == 30
    i = max(range(30), key=lambda t: mi["variance"][t])
    assert mi["gain_norm"][i] < 0.5 * max(mi["gain_norm"])  # low gains where the demos vary most
    assert "| Q_00 | 2 |" in report


def test_a_failed_check_is_exit_status_1(tmp_path):
    # two L-BFGS iterations cannot recover the weights: the pipeline's own check fails
    assert cli.main(["learn", "costs", "--steps", "2", "--out", str(tmp_path), "--quiet", "--no-plots"]) == 1
    rec = json.loads((tmp_path / "costs.json").read_text())
    assert rec["checks"]["weights_recovered"] is False and rec["values"]["weights_rel_err"] > 1e-3
    assert "| weights_recovered | **NO** |" in (tmp_path / "report.md").read_text()
    assert not (tmp_path / "costs.png").exists()


def test_primitives_pipeline(tmp_path, capsys):
    assert cli.main(["learn", "primitives", "--letters", "S,C", "--n-demos", "4", "--T", "60", "--out",
                     str(tmp_path), "--quiet"]) == 0
    rec, report = _files(tmp_path, "primitives")
    s, v = rec["settings"], rec["values"]
    assert s["letters"] == "SC" and s["n_demos"] == 4 and s["T"] == 60
    assert all(rec["checks"].values())
    assert v["via_mean_err_max"] < 1e-6 and v["via_sample_err_max"] < 1e-3 and v["via_offset"] > 0.05
    assert v["dmp_push_to_goal_max"] < 7e-3 and v["dmp_push_peak_dev_mean"] > 0.05  # pushed, then back
    assert len(v["per_letter"]["dmp_reproduction_rms"]) == 2
    assert "| S |" in report and "| C |" in report and "bench primitives" in report
    assert "via_mean_err_max" in capsys.readouterr().out


def test_manifold_pipeline(tmp_path):
    argv = ["learn", "manifold", "--n-demos", "8", "--T", "24", "--out", str(tmp_path), "--quiet"]
    assert cli.main(argv) == 0
    rec, _ = _files(tmp_path, "manifold")
    v, p = rec["values"], rec["per_step"]
    assert all(rec["checks"].values())
    assert len(p["tracking_error"]) == 24 and len(p["stiffness_rel_err_karcher"]) == 24
    assert v["tracking_error_final_rad"] < 0.01 * v["tracking_error_initial_rad"]
    assert v["stiffness_noise_scale"] == pytest.approx(0.3 * math.sqrt(6 / 8))
    assert 0 < v["stiffness_dist_karcher_mean"] <= 2 * v["stiffness_noise_scale"]


def _finite(x):
    return isinstance(x, float) and math.isfinite(x)


def test_dynamics_runs_have_the_documented_keys(tmp_path):
    out, extra = tmp_path / "dyn", tmp_path / "runs.json"
    argv = ["learn", "dynamics", "--system", "pendulum", "--n-train", "3", "--seeds", "1", "--baselines",
            "sysid", "mlp", "--n-test", "10", "--steps", "40", "--out", str(out), "--json", str(extra),
            "--quiet"]
    assert cli.main(argv) == 0
    runs, report = _files(out, "dynamics")
    assert runs == json.loads(extra.read_text())
    assert isinstance(runs, list) and len(runs) == 1
    r = runs[0]
    assert tuple(r)[:6] == learn_demos.DYNAMICS_KEYS
    assert tuple(r) == learn_demos.DYNAMICS_KEYS + learn_demos.DYNAMICS_EXTRA
    assert (r["system"], r["n_train"], r["seed"]) == ("pendulum", 3, 0)
    err = r["param_rel_err"]
    assert set(err) == {"gravity", "mass", "length", "g/l", "1/(m l^2)"}
    assert r["identifiable"] == ["g/l", "1/(m l^2)"]
    assert all(_finite(err[k]) and err[k] < 0.01 for k in r["identifiable"])  # the 1 % goal
    assert _finite(r["imitation_mse"]) and r["imitation_mse"] < 1e-3 * r["imitation_mse_init"]
    assert set(r["baselines"]) == {"sysid", "mlp"}
    assert all(_finite(b["imitation_mse"]) for b in r["baselines"].values())
    assert r["expert_unconverged"] == 0 and r["unconverged"]["policy"] == "include"
    assert r["nonfinite_values"] == []
    assert len(r["history"]["loss"]) == r["evaluations"] <= 40
    assert "err g/l" in report and "identifiable_within_1_percent | yes" in report


def test_dynamics_seeds_is_a_count(tmp_path):
    argv = ["learn", "dynamics", "--n-train", "2", "--seeds", "2", "--baselines", "--n-test", "4", "--steps",
            "3", "--out", str(tmp_path), "--no-plots", "--quiet"]
    assert cli.main(argv) in (0, 1)  # 3 evaluations: the 1 % goal need not be met, the runs must be there
    runs = json.loads((tmp_path / "dynamics.json").read_text())
    assert [(r["seed"], r["n_train"], r["baselines"]) for r in runs] == [(0, 2, {}), (1, 2, {})]


@pytest.mark.parametrize("argv, option", [
    (["dynamics", "--system", "foo"], "--system"),
    (["dynamics", "--n-train", "0"], "--n-train"),
    (["dynamics", "--seeds", "0"], "--seeds"),
    (["dynamics", "--baselines", "gp"], "--baselines"),
    (["costs", "--n-demos", "1"], "--n-demos"),
    (["primitives", "--letters", "S,1"], "--letters"),
    (["primitives", "--T", "5"], "--T"),
    (["manifold", "--T", "1"], "--T"),
])
def test_bad_arguments_exit_2_naming_the_option(argv, option, capsys, monkeypatch):
    monkeypatch.setattr(cli, "_load", lambda m: pytest.fail(f"{m} imported: the work started"))
    with pytest.raises(SystemExit) as e:
        cli.main(["learn", *argv])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert f"error: argument {option}" in err and "Traceback" not in err


def test_non_finite_numbers_are_written_as_null(tmp_path):
    p = learn_demos._write_json(tmp_path / "r.json", [{"imitation_mse": float("nan"), "x": float("inf")}])
    assert json.loads(p.read_text()) == [{"imitation_mse": None, "x": None}]


def _run(seed, err, mse, nonfinite=()):
    return {"system": "cartpole", "n_train": 2, "seed": seed,
            "param_rel_err": {"gravity": err, "cart_mass": err, "pole_mass": err, "length": err},
            "imitation_mse": mse, "baselines": {"mlp": {"imitation_mse": None}},
            "identifiable": ["gravity", "cart_mass", "pole_mass", "length"], "identifiable_rel_err_max": err,
            "params_true": {"gravity": 9.8}, "params_init": {"gravity": 9.8}, "imitation_mse_init": 5.0,
            "unconverged": {"sample_solves": 3}, "expert_unconverged": 0, "evaluations": 2, "time_s": 1.0,
            "n_test": 4, "nonfinite_values": list(nonfinite),
            "history": {"loss": [1.0, None], "identifiable_rel_err_max": [0.5, None]}}


def test_a_diverged_dynamics_run_is_reported_not_a_crash(tmp_path):
    # a run whose learning diverged: its non-finite values are None in the record (learning.imitation)
    runs = [_run(0, 1e-6, 1e-9), _run(1, None, None, ["imitation_mse", "param_rel_err.length"])]
    checks, tol = learn_demos.dynamics_checks(runs)
    assert checks == {"identifiable_within_1_percent": False, "imitation_mse_below_initial": False,
                      "expert_solves_converged": True} and tol == {"identifiable_rel_err": 0.01}
    assert learn_demos.dynamics_checks(runs[:1])[0]["identifiable_within_1_percent"] is True
    settings = {"system": "cartpole", "n_train": 2, "seeds": 2, "steps": 2, "unconverged": "exclude",
                "baselines": ["mlp"]}
    report = "\n".join(learn_demos._dynamics_report(runs, settings))
    assert "seed 1: imitation_mse, param_rel_err.length" in report
    learn_demos._dynamics_plot(runs, tmp_path / "d.png")
    assert (tmp_path / "d.png").read_bytes()[:8] == PNG
