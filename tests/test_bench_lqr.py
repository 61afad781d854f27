"""Smoke test of ``liecontrol bench lqr`` at a tiny size: record keys and agreement of the controls."""

import json
from pathlib import Path

import pytest

from liecontrol.bench import lqr as bench

KEYS = {"problem", "B", "T", "n", "m", "dtype", "pass", "ours_ms", "anchor", "anchor_ms", "speedup",
        "max_abs_diff_u"}
MPC_PY = Path(__file__).resolve().parents[1] / ".venv-mpc" / "bin" / "python"


def _check(records, anchors):
    assert {r["anchor"] for r in records} == set(anchors) | {"ours-float64"}
    assert {"lqr", "lqr-cold"} <= {r["problem"] for r in records}
    for r in records:
        assert set(r) == KEYS
        assert r["problem"] in ("lqr", "lqr-cold", "lqr-fused")
        assert (r["B"], r["T"], r["n"], r["m"]) == (4, 6, 3, 2)
        assert r["ours_ms"] > 0
        if r["anchor"] == "ours-float64" or r["pass"] == "fwd":
            # the anchor's forward ran: same optimal controls (float32 round-off only)
            assert r["max_abs_diff_u"] is not None and r["max_abs_diff_u"] < 1e-4, r
        if isinstance(r["anchor_ms"], float):
            assert r["speedup"] == pytest.approx(r["anchor_ms"] / r["ours_ms"])
        elif r["anchor"] != "ours-float64":
            assert isinstance(r["anchor_ms"], str) and r["speedup"] is None  # a failure is reported


def test_bench_lqr_pypose_smoke(tmp_path):
    pytest.importorskip("pypose")
    out = tmp_path / "lqr.json"
    parser = __import__("argparse").ArgumentParser()
    bench.add_arguments(parser)
    args = parser.parse_args(["--batch", "4", "--horizon", "6", "--state-dim", "3", "--control-dim", "2",
                              "--repeats", "1", "--anchors", "pypose,plain", "--no-fused", "--json",
                              str(out)])
    assert bench.run(args) == 0
    _check(json.loads(out.read_text()), ["pypose", "plain-riccati"])


@pytest.mark.skipif(not MPC_PY.exists(),
                    reason="no mpc.pytorch anchor environment .venv-mpc (`make bench-env` creates it)")
def test_bench_lqr_mpc_anchor_smoke():
    records = bench.run_bench(B=4, T=6, n=3, m=2, repeats=1, anchors=("mpc",))
    _check(records, ["mpc.pytorch"])


def test_missing_mpc_environment_is_reported_not_raised(tmp_path):
    records = bench.run_bench(B=4, T=6, n=3, m=2, repeats=1, anchors=("mpc",),
                              mpc_python=str(tmp_path / "nope" / "python"))
    bad = [r for r in records if r["anchor"] == "mpc.pytorch"]
    assert len(bad) == 4 and all(r["anchor_ms"].startswith("missing") for r in bad)  # 2 passes x 2 variants
