"""``liecontrol bench solver`` at its ``--quick`` sizes: the record schema, every workload present, the
anchors on the same problems (no timing asserts), and bad options refused before any work."""

from __future__ import annotations

import contextlib
import importlib.util
import io
import json
import math

import pytest
import torch

from liecontrol import cli
from liecontrol.bench import solver

KEYS = {"workload", "batch", "dtype", "device", "ours_ms", "anchor", "anchor_ms", "ratio"}


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    """``--eager``: the compiled programs at these sizes would take minutes to build, and their numbers are
    compared with the eager path's in tests/controllers/test_compiled_sweeps.py and test_esmpc_compiled.py;
    here the command's plumbing is under test (``compiled`` records what ran)."""
    path = tmp_path_factory.mktemp("bench") / "solver.json"
    threads = torch.get_num_threads()
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        rc = cli.main(["bench", "solver", "--quick", "--eager", "--threads", str(threads + 1), "--json",
                       str(path)])
    return {"rc": rc, "records": json.loads(path.read_text()), "printed": printed.getvalue(),
            "threads_after": torch.get_num_threads(), "threads": threads}


def test_quick_run_writes_every_workload_with_the_schema(quick_run):
    assert quick_run["rc"] == 0
    assert quick_run["threads_after"] == quick_run["threads"]  # --threads is restored afterwards
    records = quick_run["records"]
    assert {r["workload"] for r in records} == set(solver.WORKLOADS)
    for r in records:
        assert KEYS <= set(r), r
        assert r["compiled"] is False  # --eager reached every workload
        assert r["device"] == "cpu" and r["dtype"] in ("float32", "float64")
        assert isinstance(r["batch"], int) and r["batch"] >= 1
        assert r["ours_ms"] is not None and math.isfinite(r["ours_ms"]) and r["ours_ms"] > 0, r
        if r["anchor"] is None:
            assert r["anchor_ms"] is None and r["ratio"] is None
        else:
            assert r["anchor_ms"] > 0
            assert r["ratio"] == pytest.approx(r["anchor_ms"] / r["ours_ms"], rel=1e-12)
    for w in solver.WORKLOADS:  # the printed table names every workload
        assert w in quick_run["printed"]
    head = [r for r in records if r["workload"] == "mpc_head_fwd_bwd"]
    assert {r["task"] for r in head} == {"PendulumSwingUp", "CartPoleSwingUp"}
    assert all(r["anchor"].startswith("SB3 MlpPolicy") and r["dtype"] == "float32" for r in head)
    quad = {r["batch"] for r in records if r["workload"] == "quadrotor_step"}
    assert quad == set(solver.QUICK_SIZES.quad_batches)


def test_cookbook_anchor_solves_the_same_problem(quick_run):
    """Ours and the numpy batch iLQR, after as many iterations, reach the same cost and controls."""
    rows = [r for r in quick_run["records"] if r["workload"] == "cookbook_manipulator"]
    one = [r for r in rows if r["batch"] == 1]
    assert {r["method"] for r in one} == {"recursive", "batch", "lifted"}
    # the batch rows: every start certified, timed against the same solver on one problem
    many = [r for r in rows if r["batch"] > 1]
    assert {r["method"] for r in many} == {"recursive", "lifted"}
    assert all(r["converged"] == r["batch"] and r["per_one"] > 0 for r in many)
    for r in one:
        assert r["status"] == "CONVERGED" and r["anchor"] is not None
        assert r["anchor_cost"] == pytest.approx(r["ours_cost"], rel=1e-6)
        assert r["max_abs_diff_u"] < 1e-3


def test_crocoddyl_rows_ran_or_say_why(quick_run):
    croc = ("pendulum_mpc_step", "pendulum_ilqr_iteration", "cartpole_swingup_batch64",
            "pendulum_swingup_batch64")
    rows = [r for r in quick_run["records"] if r["workload"] in croc]
    assert len(rows) == 5
    if importlib.util.find_spec("crocoddyl") is None:
        assert all(r["anchor"] is None and "crocoddyl" in r["anchor_note"] for r in rows)
    else:  # the model checks passed: the anchor ran on the same problem
        assert all(r["anchor"] is not None for r in rows), [r.get("anchor_note") for r in rows]
        step = next(r for r in rows if r["workload"] == "pendulum_mpc_step")
        # the same closed loop: a swing-up episode of similar return on both sides
        assert step["anchor_return"] == pytest.approx(step["ours_return"], rel=0.2)


def test_record_without_an_anchor_time_has_null_anchor_columns():
    ctx = solver._Ctx(solver.QUICK_SIZES, torch.float64, torch.device("cpu"), 1, None)
    r = solver._record(ctx, "car_parking_step", "c", 2, 5.0, "something", None, "why")
    assert (r["anchor"], r["anchor_ms"], r["ratio"], r["anchor_note"]) == (None, None, None, "why")
    r = solver._record(ctx, "car_parking_step", "c", 2, 5.0, "something", 10.0)
    assert (r["anchor"], r["ratio"], r["dtype"]) == ("something", 2.0, "float64")


@pytest.mark.parametrize("argv, option", [
    (["--workloads", "quadrotor_step,nope"], "--workloads"),
    (["--workloads", ""], "--workloads"),
    (["--threads", "0"], "--threads"),
    (["--repeats", "-1"], "--repeats"),
    (["--dtype", "float16"], "--dtype"),
])
def test_bad_options_are_refused_naming_the_option(argv, option, capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(["bench", "solver", *argv])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert option in err and "measuring" not in err


def test_cuda_refused_without_a_device(monkeypatch, capsys):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(SystemExit):
        cli.main(["bench", "solver", "--device", "cuda"])
    assert "--device" in capsys.readouterr().err
