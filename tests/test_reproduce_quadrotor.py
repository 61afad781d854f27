"""`liecontrol reproduce quadrotor` in quick mode: the outcome, the files, the JSON, bad arguments."""

from __future__ import annotations

import json
import math
from argparse import Namespace

import pytest

from liecontrol.reproduce import quadrotor as rq


def test_quick_circle_is_tracked_and_reported(tmp_path):
    res = rq.run_experiment(scenarios=("circle", "flip"), horizons=(8,), anchor=False, quick=True, batch=4,
                            repeats=1)
    assert res["circle"]["pos_err_max_m"] < 0.05  # the issue's target, on the quick (2.5 m/s) circle
    assert res["flip"]["pos_err_max_m"] < 0.05 and res["flip"]["att_err_max_rad"] < 0.1
    assert all(r["not_converged"] == 0 for r in res["rows"])
    figs = rq.save_figures(res, tmp_path)
    report = rq.write_report(res, tmp_path, figs).read_text()
    assert "target < 0.05 m" in report and "QUICK" in report
    batch_line = next(line for line in report.splitlines() if "4 quadrotors in one batched step" in line)
    assert "MISSED" not in batch_line and "met" not in batch_line and "is for 1024" in batch_line
    assert all(p.stat().st_size > 0 for p in figs)


def test_the_batched_target_is_judged_at_1024_only():
    res = {"batch": 1024, "step_ms_batch1024": 60.0, "step_ms_single": 1.0}
    (line,) = [v for v in rq._verdicts(res) if "batched" in v]
    assert "1024 quadrotors" in line and "MISSED" in line
    res["step_ms_batch1024"] = 20.0
    assert any("1024 quadrotors" in v and "met" in v for v in rq._verdicts(res))


def test_cli_writes_json_with_the_issue_keys(tmp_path):
    args = Namespace(out=str(tmp_path / "out"), json=str(tmp_path / "q.json"), horizons=[8],
                     scenarios=["loop8"], no_anchor=True, batch=4, threads=1, quick=True, no_plots=True)
    assert rq.run(args) == 0
    data = json.loads((tmp_path / "q.json").read_text())
    for key in ("loop8", "step_ms_single", "step_ms_batch1024", "horizon"):
        assert key in data
    assert set(data["loop8"]) >= {"pos_err_max_m", "pos_err_rms_m"}
    assert all(math.isfinite(v) for v in data["loop8"].values())
    assert (tmp_path / "out" / "report.md").exists()


def test_bad_arguments_are_named():
    with pytest.raises(ValueError, match="scenarios"):
        rq.run_experiment(scenarios=("nope",), anchor=False, quick=True)
    with pytest.raises(ValueError, match="horizons"):
        rq.run_experiment(horizons=(0,), anchor=False, quick=True)
