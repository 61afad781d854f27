"""``liecontrol bench cookbook --quick``: the rows of the manipulator, the car and the bicopter, the
anchor's agreement and the goal lines."""

import json

import pytest

from liecontrol.bench.cookbook import WORKLOADS, goals
from liecontrol.cli import main

SYSTEMS = {"cookbook_manipulator": "manipulator", "cookbook_car": "car", "cookbook_bicopter": "bicopter"}


def test_quick_run_prints_both_goals_with_verdicts(tmp_path, capsys):
    js = tmp_path / "cb.json"
    assert main(["bench", "cookbook", "--quick", "--batch", "3", "--json", str(js)]) == 0
    out = capsys.readouterr().out
    rows = json.loads(js.read_text())
    assert {r["workload"] for r in rows} == set(WORKLOADS) == set(SYSTEMS)
    for workload, system in SYSTEMS.items():
        mine = [r for r in rows if r["workload"] == workload]
        # the vehicles' batch rows are the recursive solver's alone (lifted's batch on nonlinear dynamics
        # runs every element to the slowest's count with dense transfer matrices: a minute a call at 64)
        batch_methods = {"recursive", "lifted"} if system == "manipulator" else {"recursive"}
        one = {("recursive", 1), ("batch", 1), ("lifted", 1)}
        assert {(r["method"], r["batch"]) for r in mine} == one | {(m, 3) for m in batch_methods}
        assert all(r["system"] == system for r in mine)
        for r in mine:
            if r["batch"] == 1:  # the same problem: the script reaches our cost after as many iterations
                assert r["status"] == "CONVERGED", r
                assert r["anchor"] is not None and r["anchor_ms"] > 0, r.get("anchor_note")
                assert r["anchor_cost"] == pytest.approx(r["ours_cost"], rel=1e-6), r
            else:
                assert r["per_one"] > 0 and 0 <= r["converged"] <= 3
                assert 0 <= r["iterations_median"] <= r["iterations"]
        assert f"{system}: one problem: fastest of ours is" in out
        assert out.count(f"{system}: batch of 3 by") == len(batch_methods)
        assert f"cookbook {system} (lifted): cost ours" in out
    # the car and the bicopter at --quick sizes: 20 and 30 control steps
    assert {r["horizon"] for r in rows if r["workload"] == "cookbook_car"} == {20}
    assert {r["horizon"] for r in rows if r["workload"] == "cookbook_bicopter"} == {30}


def test_goal_verdicts():
    rows = [{"batch": 1, "ratio": 0.6, "method": "batch", "ours_ms": 10.0, "anchor_ms": 6.0, "iterations": 6},
            {"batch": 1, "ratio": 8.5 / 11.6, "method": "lifted", "ours_ms": 11.6, "anchor_ms": 8.5,
             "iterations": 5},
            {"batch": 64, "method": "recursive", "ours_ms": 80.0, "per_one": 6.0, "converged": 64},
            {"batch": 4, "method": "lifted", "ours_ms": 20.0, "per_one": 2.0, "converged": 4}]
    lines = goals(rows)
    # the fastest is the smallest time, not the best ratio (the anchor's time varies between rows)
    assert "fastest of ours is batch at 10" in lines[0] and "(goal >= 1: MISSED)" in lines[0]
    assert "(goal <= 5: MISSED)" in lines[1]
    assert "no verdict" in lines[2] and "met" not in lines[2]


def test_goal_verdicts_per_workload():
    """Each workload gets its own fastest-of-ours line and batch lines, named by its system."""
    rows = [{"workload": "cookbook_car", "system": "car", "batch": 1, "ratio": 2.0, "method": "lifted",
             "ours_ms": 5.0, "anchor_ms": 10.0, "iterations": 9},
            {"workload": "cookbook_bicopter", "system": "bicopter", "batch": 1, "ratio": 0.5,
             "method": "recursive", "ours_ms": 4.0, "anchor_ms": 2.0, "iterations": 3},
            {"workload": "cookbook_car", "system": "car", "batch": 1, "ratio": 0.1, "method": "recursive",
             "ours_ms": 50.0, "anchor_ms": 5.0, "iterations": 20},
            {"workload": "cookbook_car", "system": "car", "batch": 64, "method": "lifted", "ours_ms": 20.0,
             "per_one": 4.0, "converged": 63},
            {"workload": "cookbook_bicopter", "system": "bicopter", "batch": 64, "method": "lifted",
             "ours_ms": 80.0, "per_one": 20.0, "converged": 64}]
    lines = goals(rows)
    assert len(lines) == 4
    # grouped in order of appearance: the car's rows first, with the fastest of the car's rows only
    assert lines[0].startswith("car: one problem: fastest of ours is lifted at 5")
    assert "(goal >= 1: met)" in lines[0]
    assert lines[1].startswith("car: batch of 64 by lifted") and "(goal <= 5: met)" in lines[1]
    assert "63 of 64 certified" in lines[1]
    assert lines[2].startswith("bicopter: one problem: fastest of ours is recursive at 4")
    assert "(goal >= 1: MISSED)" in lines[2]
    assert lines[3].startswith("bicopter: batch of 64") and "(goal <= 5: MISSED)" in lines[3]
