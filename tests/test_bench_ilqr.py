"""Smoke run of ``liecontrol bench ilqr`` at a tiny size (the anchor only when its environment exists)."""

from __future__ import annotations

import json

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
    main = [r for r in fwd if r["B"] == 2]
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
