"""``liecontrol bench cookbook --quick``: the rows, the anchor's agreement and the goal lines."""

import json

import pytest

from liecontrol.bench.cookbook import goals
from liecontrol.cli import main


def test_quick_run_prints_both_goals_with_verdicts(tmp_path, capsys):
    js = tmp_path / "cb.json"
    assert main(["bench", "cookbook", "--quick", "--batch", "3", "--json", str(js)]) == 0
    out = capsys.readouterr().out
    rows = json.loads(js.read_text())
    assert {(r["method"], r["batch"]) for r in rows} == {("recursive", 1), ("batch", 1), ("lifted", 1),
                                                         ("recursive", 3), ("lifted", 3)}
    for r in rows:
        if r["batch"] == 1:  # the same problem: the script reaches our cost after as many iterations
            assert r["anchor_cost"] == pytest.approx(r["ours_cost"], rel=1e-6)
    assert "one problem: fastest of ours is" in out and out.count("batch of 3 by") == 2


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
