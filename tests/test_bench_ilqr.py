"""Smoke run of ``liecontrol bench ilqr`` at a tiny size (the anchors only when their environments exist)."""

from __future__ import annotations

import argparse
import importlib.util
import json
import math

import pytest
import torch

from liecontrol.bench import ilqr as bench


def test_bench_ilqr_smoke(tmp_path, capsys):
    out = tmp_path / "ilqr.json"
    parser = __import__("argparse").ArgumentParser()
    bench.add_arguments(parser)
    args = parser.parse_args(["--batch", "2", "--horizon", "8", "--repeats", "1", "--max-iter", "10",
                              "--grad-batch", "2", "--problems", "pendulum", "--json", str(out),
                              "--threads", str(torch.get_num_threads() + 1)])
    threads = torch.get_num_threads()
    assert bench.run(args) == 0
    assert torch.get_num_threads() == threads  # the bench sets its own thread count and restores ours
    printed = capsys.readouterr().out
    assert "pendulum swing-up" in printed and "d(loss)/d(length)" in printed
    records = json.loads(out.read_text())
    keys = {"problem", "B", "T", "n", "m", "dtype", "pass", "ours_ms", "anchor", "anchor_ms", "speedup",
            "max_abs_diff_u", "ours_cost", "anchor_cost"}
    fwd = [r for r in records if r.get("pass") == "fwd"]
    assert fwd and all(keys <= set(r) for r in fwd)
    main = [r for r in fwd if r["B"] == 2 and not r["anchor"].startswith("crocoddyl")]
    assert main and all(r["T"] == 8 and r["ours_ms"] > 0 for r in main)
    anchors = {r["anchor"] for r in main}
    if bench._anchor_python(args) is None:
        assert anchors == {"missing (.venv-mpc)"}
    else:
        # mpc.pytorch ran and its controls were scored with our cost; pypose's batch>1 failure is reported
        mp = [r for r in main if r["anchor"] == "mpc.pytorch box-DDP"]
        assert mp and mp[0]["anchor_ms"] > 0 and mp[0]["anchor_cost"] > 0
        assert any(r["anchor"].startswith("pypose") for r in main)
        # pypose on the first element alone, with its limit violation (if any) in the label
        assert any(r["B"] == 1 and r["anchor"].startswith("pypose MPC (B=1") for r in fwd)
    grad = [r for r in records if "grad_implicit" in r]
    assert grad and grad[0]["rel_err"] < 1e-5


needs_crocoddyl = pytest.mark.skipif(
    importlib.util.find_spec("crocoddyl") is None,
    reason="crocoddyl is not installed (the bench extra installs it: pip install -e '.[bench]')")


def _args(*extra):
    parser = argparse.ArgumentParser()
    bench.add_arguments(parser)
    return parser.parse_args(["--batch", "2", "--horizon", "8", "--repeats", "1", "--max-iter", "10",
                              "--grad-batch", "2", *extra])


@needs_crocoddyl
def test_bench_ilqr_crocoddyl_smoke(tmp_path, capsys):
    out = tmp_path / "ilqr.json"
    # the mpc.pytorch environment is pointed at nothing: only crocoddyl runs
    args = _args("--problems", "pendulum", "cartpole", "--json", str(out))
    args.anchor_python = str(tmp_path / "no-python")  # (the command line refuses a missing file)
    assert bench.run(args) == 0
    printed = capsys.readouterr().out
    assert "crocoddyl model check" in printed
    records = json.loads(out.read_text())
    croc = {r["problem"]: r for r in records if r.get("anchor", "").startswith("crocoddyl")}
    assert set(croc) == {"pendulum swing-up", "pendulum swing-up (b=0)", "cartpole swing-up"}
    for r in croc.values():
        assert r["anchor"] == bench.CROC_LABEL, (r["anchor"], r.get("anchor_error"))
        # crocoddyl's model is ours, step for step, in float64
        assert r["dtype"] == "float64" and r["match"] == "yes"
        assert r["model_dx"] < 1e-12 and r["rollout_dx"] < 1e-9 and r["jac_err"] < 1e-9
        assert r["cost_rel_err"] < 1e-12
        assert r["anchor_ms"] > 0 and r["ours_ms"] > 0
        assert math.isclose(r["speedup"], r["anchor_ms"] / r["ours_ms"])
        # per problem: iterations within the shared cap, costs on each side's own trajectory
        assert len(r["anchor_iters_per_problem"]) == 2 and max(r["anchor_iters_per_problem"]) <= 10
        assert max(r["ours_iters_per_problem"]) <= 10
        assert all(c > 0 for c in r["anchor_cost_per_problem"] + r["ours_cost_per_problem"])
        assert math.isclose(r["cost_ratio"], r["ours_cost"] / r["anchor_cost"], rel_tol=1e-9)
        # crocoddyl's own cost of its trajectory is ours (same weights, same discretization)
        assert math.isclose(r["anchor_cost_own"], r["anchor_cost"], rel_tol=1e-9)
        assert r["anchor_unactuated_max"] == 0.0  # the cart-pole's boxed pole torque stays at 0
    assert "Python actuation" in croc["pendulum swing-up"]["anchor_note"]
    assert "all C++" in croc["pendulum swing-up (b=0)"]["anchor_note"]


@needs_crocoddyl
def test_bench_ilqr_crocoddyl_refuses_another_model():
    """Gravity 9.7 on crocoddyl's side: the model check fails and no comparison is reported."""
    args = _args()
    p = bench.PROBLEMS["pendulum"]["params"]
    from controllers.ilqr import ILQROptions

    rec = bench._croc_compare("pendulum", "pendulum swing-up", bench._x0("pendulum", 2, 0), 8, args,
                              ILQROptions(max_iter=10), anchor_params=[p[0], p[1], p[2], 9.7])
    assert rec["match"] == "NO" and "MODEL MISMATCH" in rec["anchor"]
    assert rec["model_dx"] > 1e-6
    assert rec["anchor_ms"] is None and rec["anchor_cost"] is None and rec["cost_ratio"] is None


def test_bench_ilqr_crocoddyl_missing(tmp_path):
    """A missing crocoddyl interpreter is a reported row, not a crash."""
    args = _args()
    args.croc_python = str(tmp_path / "no-python")  # (the command line refuses a missing file)
    from controllers.ilqr import ILQROptions

    rec = bench._croc_compare("pendulum", "pendulum swing-up", bench._x0("pendulum", 2, 0), 8, args,
                              ILQROptions(max_iter=10))
    assert rec["anchor"].startswith("crocoddyl: missing") and rec["anchor_ms"] is None
