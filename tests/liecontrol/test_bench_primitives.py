"""``liecontrol bench primitives --quick``: both sides' rows, our errors against bounds, the anchor's rows
(when ``movement_primitives`` is installed), a missing anchor as null columns, and the option checks."""

import json
import math
import sys

import pytest

from liecontrol.bench.primitives import ANCHOR, PUSH
from liecontrol.cli import main

METRICS = {"DMP": {"reproduction_rms", "push_final_to_goal", "push_peak_dev", "fit_ms", "generate_ms"},
           "ProMP": {"reproduction_rms", "push_final_to_goal", "push_peak_dev", "via_point_err", "fit_ms",
                     "generate_ms"}}
PUSH_NORM = math.hypot(*PUSH)


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    js = tmp_path_factory.mktemp("prim") / "prim.json"
    assert main(["bench", "primitives", "--quick", "--json", str(js)]) == 0
    rows = json.loads(js.read_text())
    return {(r["method"], r["metric"], r["side"]): r for r in rows}, rows


def test_quick_run_has_both_sides_for_every_metric(quick):
    by_key, rows = quick
    expected = {(m, k, s) for m, ks in METRICS.items() for k in ks for s in ("ours", ANCHOR)}
    assert set(by_key) == expected and len(rows) == len(expected)
    for r in rows:
        assert r["unit"] == ("ms" if r["metric"].endswith("_ms") else "box")
        assert (r["T"], r["n_demos"], r["n_generate"], r["letters"]) == (40, 4, 20, "SC")


def test_our_side_errors_within_bounds(quick):
    by_key, _ = quick
    ours = {(m, k): r for (m, k, s), r in by_key.items() if s == "ours"}
    for r in ours.values():
        assert r["value"] is not None and math.isfinite(r["value"]) and r["value"] >= 0, r
    # noiseless conditioning passes through the via point
    assert ours["ProMP", "via_point_err"]["max"] <= 1e-6
    # each demo's own LQT-DMP reproduces it within 1 % of the letters' box (RMS); the ProMP mean the
    # demos' mean
    assert ours["DMP", "reproduction_rms"]["max"] <= 1e-2
    assert ours["ProMP", "reproduction_rms"]["max"] <= 1e-2
    # the push of |(0.1, -0.1)| is felt (peak deviation at least the push) and recovered to 10 % of it at
    # the end
    for method in METRICS:
        assert ours[method, "push_peak_dev"]["value"] >= PUSH_NORM * (1 - 1e-9)
        assert ours[method, "push_final_to_goal"]["max"] <= 0.1 * PUSH_NORM
    assert ours["DMP", "fit_ms"]["value"] > 0 and ours["ProMP", "generate_ms"]["value"] > 0


def test_anchor_side_rows(quick):
    pytest.importorskip("movement_primitives")
    by_key, _ = quick
    theirs = {(m, k): r for (m, k, s), r in by_key.items() if s == ANCHOR}
    for (method, metric), r in theirs.items():
        if method == "ProMP" and metric.startswith("push_"):  # no feedback controller in the anchor's ProMP
            assert r["value"] is None and "not supported" in r["note"] and r["ratio"] is None
            continue
        assert r["value"] is not None and math.isfinite(r["value"]), r
        ours = by_key[method, metric, "ours"]["value"]
        assert r["ratio"] == pytest.approx(r["value"] / ours)
    assert theirs["ProMP", "via_point_err"]["max"] <= 1e-6  # its Gaussian conditioning is exact too
    assert theirs["DMP", "push_peak_dev"]["value"] >= PUSH_NORM * (1 - 1e-9)  # the push reached its state
    assert theirs["DMP", "reproduction_rms"]["value"] < 0.2  # a DMP of the demo, not noise
    assert math.isfinite(theirs["DMP", "reproduction_rms"]["open_loop_value"])


def test_missing_anchor_gives_null_columns(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "movement_primitives.dmp", None)  # importing it raises ImportError
    js = tmp_path / "p.json"
    assert main(["bench", "primitives", "--letters", "u", "--n-demos", "2", "--T", "16", "--n-generate", "3",
                 "--repeats", "1", "--json", str(js)]) == 0
    rows = json.loads(js.read_text())
    anchor = [r for r in rows if r["side"] == ANCHOR]
    assert len(anchor) == sum(map(len, METRICS.values()))
    assert all(r["value"] is None and r["ratio"] is None and "missing" in r["note"] for r in anchor)
    assert all(r["value"] is not None and r["letters"] == "U" for r in rows if r["side"] == "ours")
    assert f"{ANCHOR} missing" in capsys.readouterr().out


@pytest.mark.parametrize("argv, msg", [(["--letters", "Q"], "--letters"), (["--letters", "S,1"], "--letters"),
                                       (["--n-demos", "1"], "--n-demos"), (["--T", "5"], "--T")])
def test_bad_options(argv, msg, capsys):
    with pytest.raises(SystemExit) as e:
        main(["bench", "primitives", *argv])
    assert e.value.code == 2 and msg in capsys.readouterr().err
