"""``liecontrol reproduce pose-mpc`` (issue 11 §4): a quick run, its findings, report, figures and JSON."""

from __future__ import annotations

import json

import pytest

pytest.importorskip("pytorch_kinematics")

from liecontrol import cli  # noqa: E402
from liecontrol.report import public  # noqa: E402
from liecontrol.reproduce import pose_mpc  # noqa: E402


@pytest.fixture(scope="module")
def quick():
    return pose_mpc.run_experiment(horizon=10, quick=True, batch=4)


def test_quick_run_tracks_and_shows_the_cut_locus(quick):
    rows = quick["rows"]
    assert len(rows) == 2 * 2 * 3  # (tilted, tool_down) × (on_path, offset) × 3 frames, one path each
    assert all(r["not_converged"] == 0 for r in rows)
    for r in rows:
        if r["frame"] in ("local", "se3"):  # settled on the path within one horizon, from either start
            assert r["pos_max_after_mm"] < 1.0 and r["ang_max_after_deg"] < 0.5, r
    world_cut = next(r for r in rows if r["frame"] == "world" and r["start"] == "offset"
                     and r["path"].endswith("tool_down"))
    assert world_cut["ang_max_deg"] > 90  # turned the long way round
    tilted = next(r for r in rows if r["frame"] == "world" and r["start"] == "offset"
                  and r["path"].endswith("tilted"))
    # away from the cut locus the paper's MPC tracks as well
    assert tilted["pos_max_after_mm"] < 5.0 and tilted["ang_max_after_deg"] < 1.0
    offset_rows = [r for r in rows if r["start"] == "offset"]
    assert all(r["bound_active_frac"] > 0 for r in offset_rows)  # the twist bounds bind at the offset start
    assert quick["ik"]["success_rate"] >= 0.95 and quick["ik"]["max_iterations"] <= 30
    assert all(quick["timing"][f]["batch_ms"] > 0 for f in ("world", "local", "se3"))


def test_report_figures_and_json(quick, tmp_path):
    figs = pose_mpc.save_figures(quick, tmp_path)
    assert {p.name for p in figs} == {"errors.png", "cut_locus.png", "paths.png"}
    assert all(p.stat().st_size > 10_000 for p in figs)
    text = pose_mpc.write_report(quick, tmp_path, figs).read_text()
    assert "cut locus" in text and "batched IK" in text and "| path |" in text
    data = json.loads(json.dumps(public(quick)))
    assert set(data["timing"]) == {"world", "local", "se3"} and "_curves" not in data


def test_cli_rejects_bad_arguments(capsys):
    with pytest.raises(SystemExit):
        cli.main(["reproduce", "pose-mpc", "--horizon", "0"])
    assert "positive integer" in capsys.readouterr().err
