"""``liecontrol learn costs|primitives|dynamics|manifold`` under a demanding user (issue 26 §8): option values
out of range, output places the system refuses, two pipelines into one ``--out``, and reports whose numbers
are the JSON's."""

import json
import re

import pytest

from liecontrol import cli
from liecontrol.report import markdown_cell


def _strict(text: str):
    def bad(token):
        raise AssertionError(f"non-strict JSON token {token}")
    return json.loads(text, parse_constant=bad)


@pytest.mark.parametrize("argv,option", [
    (["costs", "--warp", "1e308"], "--warp"),    # overflowed the time warp: a ValueError traceback
    (["costs", "--noise", "1e200"], "--noise"),
    (["costs", "--warp", "-0.5"], "--warp"),
    (["primitives", "--T", "9"], "--T"),
    (["manifold", "--horizon", "0"], "--horizon"),
    (["dynamics", "--seeds", "0"], "--seeds")])
def test_bad_values_exit_2_naming_the_option(capsys, argv, option):
    with pytest.raises(SystemExit) as e:
        cli.main(["learn", *argv])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert f"argument {option}:" in err and "Traceback" not in err


PRIMITIVES = ["learn", "primitives", "--letters", "S", "--n-demos", "4", "--T", "60", "--quiet", "--no-plots"]


def test_unwritable_out_or_json_is_exit_2_not_a_traceback(tmp_path, capsys):
    # /proc refuses new files even to root; was a FileNotFoundError traceback after the whole run
    assert cli.main(["learn", "manifold", "--out", "/proc/liecontrol_x/y", "--quiet"]) == 2
    assert "argument --out:" in capsys.readouterr().err
    assert cli.main([*PRIMITIVES, "--out", str(tmp_path), "--json", "/proc/liecontrol_x.json"]) == 2
    assert "argument --json: cannot write /proc/liecontrol_x.json" in capsys.readouterr().err


def test_two_pipelines_in_one_out_keep_both_reports(tmp_path, capsys):
    out = str(tmp_path)
    assert cli.main([*PRIMITIVES, "--out", out]) == 0
    rc = cli.main(["learn", "manifold", "--n-demos", "4", "--T", "12", "--out", out, "--quiet", "--no-plots"])
    assert rc == (0 if all(_strict((tmp_path / "manifold.json").read_text())["checks"].values()) else 1)
    assert cli.main([*PRIMITIVES, "--out", out]) == 0  # its own section replaced, not repeated
    text = (tmp_path / "report.md").read_text()
    heads = re.findall(r"(?m)^# liecontrol learn (\w+)$", text)
    assert heads == ["primitives", "manifold"], heads
    assert (tmp_path / "primitives.json").exists() and (tmp_path / "manifold.json").exists()
    assert capsys.readouterr().err == ""  # --quiet: nothing on stderr
    rec = _strict((tmp_path / "manifold.json").read_text())
    # the report's start distance is the JSON's initial tracking error (it said 0.45 for 0.4387)
    assert f"from a start {markdown_cell(rec['values']['tracking_error_initial_rad'])} rad away" in text
    assert rec["values"]["tracking_error_initial_rad"] == pytest.approx((0.3**2 + 0.2**2 + 0.25**2) ** 0.5)


def test_dynamics_tiny_run_json_in_new_nested_folder(tmp_path):
    path = tmp_path / "a" / "b" / "runs.json"
    argv = ["learn", "dynamics", "--n-train", "1", "--seeds", "1", "--steps", "1", "--n-test", "1",
            "--baselines", "--quiet", "--out", str(tmp_path / "o"), "--json", str(path), "--no-plots"]
    assert cli.main(argv) == 1  # one evaluation cannot learn the parameters: a failed check
    runs = _strict(path.read_text())
    assert runs == _strict((tmp_path / "o" / "dynamics.json").read_text()) and len(runs) == 1
    report = (tmp_path / "o" / "report.md").read_text()
    assert "| identifiable_within_1_percent | **NO** |" in report
    # the step budget is not a bound on the evaluations taken (L-BFGS ends its line search)
    assert "a budget of 1 loss evaluations" in report and "up to 1 loss" not in report
    assert f"| {runs[0]['evaluations']} |" in report


@pytest.mark.parametrize("name,shown", [("costs", "default: 80"), ("primitives", "default: 100"),
                                        ("dynamics", "default: pendulum"), ("manifold", "default: 12")])
def test_help_of_each_command_shows_its_defaults(capsys, name, shown):
    with pytest.raises(SystemExit) as e:
        cli.main(["learn", name, "--help"])
    assert e.value.code == 0
    assert shown in capsys.readouterr().out.replace("\n", " ")
