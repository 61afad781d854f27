"""``liecontrol bench sampling``: every implementation's row, ratios against pytorch_mppi in the same run,
the anchor's absence as a status, and the option checks."""

import json
import math
import sys

import pytest

from liecontrol.bench.sampling import ANCHOR, OURS
from liecontrol.cli import main

ARGS = ["bench", "sampling", "--batch", "1", "2", "--steps", "4", "--repeats", "1", "--seeds", "1",
        "--samples", "16", "--horizon", "8"]


def _run(tmp_path, name="s.json"):
    js = tmp_path / name
    assert main([*ARGS, "--json", str(js)]) == 0
    return json.loads(js.read_text())


def test_rows_and_ratios(tmp_path):
    pytest.importorskip("pytorch_mppi")  # a bench extra (`make bench-env`); CI installs it
    rows = _run(tmp_path)
    assert {(r["impl"], r["batch"]) for r in rows} == {(i, b) for i in (*OURS, ANCHOR) for b in (1, 2)}
    for r in rows:
        assert r["status"] == "ok", r
        assert math.isfinite(r["plan_cost"]) and r["plan_cost"] > 0 and r["step_ms"] > 0
        assert r["episode_return"] < 0  # a cost is paid at every step
    anchor = {r["batch"]: r for r in rows if r["impl"] == ANCHOR}
    for r in rows:
        if r["impl"] in OURS:
            a = anchor[r["batch"]]
            assert r["cost_ratio"] == pytest.approx(r["plan_cost"] / a["plan_cost"], rel=1e-9)
            assert r["time_ratio"] == pytest.approx(r["step_ms"] / a["step_ms"], rel=1e-9)


def test_missing_anchor_is_a_status_not_a_crash(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "pytorch_mppi", None)  # import fails as if not installed
    rows = _run(tmp_path, "missing.json")
    anchor = [r for r in rows if r["impl"] == ANCHOR]
    assert anchor and all("not installed" in r["status"] for r in anchor)
    assert all(r["status"] == "ok" and r["cost_ratio"] is None for r in rows if r["impl"] in OURS)


@pytest.mark.parametrize("bad", [["--samples", "0"], ["--batch", "-1"], ["--dtype", "float16"]])
def test_bad_options_exit_2(bad, capsys):
    with pytest.raises(SystemExit) as e:
        main(["bench", "sampling", *bad])
    assert e.value.code == 2 and "argument" in capsys.readouterr().err
