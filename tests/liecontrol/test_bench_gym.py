"""``liecontrol bench gym``: rows per env, policy and batch, the targets and their ratio, a failing policy
as a status, and the option checks."""

import json
import math

import pytest

from liecontrol.bench.gym_mpc import TARGETS
from liecontrol.cli import main

pytest.importorskip("mujoco")  # the dev extra installs it; without it there is no MuJoCo env to time


def test_rows_targets_and_ratios(tmp_path):
    js = tmp_path / "gym.json"
    assert main(["bench", "gym", "--envs", "InvertedPendulum-v5", "--policies", "linear", "ilqr",
                 "--batch", "1", "2", "--steps", "3", "--json", str(js)]) == 0
    rows = json.loads(js.read_text())
    assert {(r["policy"], r["batch"]) for r in rows} == {(p, b) for p in ("linear", "ilqr") for b in (1, 2)}
    for r in rows:
        assert r["status"] == "ok", r
        assert r["step_ms"] > 0 and r["first_ms"] > 0 and r["return_mean"] == 3.0  # the pole stays up
        assert r["target_ms"] == TARGETS.get((r["env"], r["batch"]))
        if r["target_ms"] is not None:
            assert math.isclose(r["vs_target"], r["step_ms"] / r["target_ms"])
        else:
            assert r["vs_target"] is None


def test_a_model_that_cannot_run_is_a_status(tmp_path):
    js = tmp_path / "gym.json"
    assert main(["bench", "gym", "--envs", "Reacher-v5", "--policies", "linear", "--batch", "1", "--steps",
                 "2", "--json", str(js)]) == 0
    (row,) = json.loads(js.read_text())
    assert "not quadratic" in row["status"] and row.get("step_ms") is None and row["vs_target"] is None


@pytest.mark.parametrize("bad", [["--envs", "Hopper-v5"], ["--policies", "mppi"], ["--steps", "0"]])
def test_bad_options_exit_2(bad, capsys):
    with pytest.raises(SystemExit) as e:
        main(["bench", "gym", *bad])
    assert e.value.code == 2 and "argument" in capsys.readouterr().err
