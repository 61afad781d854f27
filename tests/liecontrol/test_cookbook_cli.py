"""``liecontrol cookbook list|run`` on a folder of small fake examples (the real ones are tested one by one
in tests/cookbook/), and the index of the real folder against examples/cookbook/README.md."""

import json
import re
import textwrap
from pathlib import Path

import pytest

from liecontrol._cookbook_index import DEFAULT_DIR, discover, section_key
from liecontrol.cli import main

ROOT = Path(__file__).resolve().parents[2]

GOOD = '''
"""A passing example."""
SECTION = "{section}"
TITLE = "{title}"


def run(out=None):
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        (out / "{name}.png").write_bytes(b"png")
    return {{"checks": {{"reached": True}}, "values": {{"error": 1e-9}}}}
'''

FAILING = '''
SECTION = "3.1"
TITLE = "A failing check"


def run(out=None):
    return {"checks": {"reached": True, "obstacle_avoided": False}, "values": {}}
'''

RAISING = '''
SECTION = "C"
TITLE = "Raises"


def run(out=None):
    raise RuntimeError("boom")
'''

MALFORMED = '''
SECTION = "4"
TITLE = "Returns a float"


def run(out=None):
    return 1.0
'''


def _write(folder: Path, name: str, text: str) -> None:
    (folder / f"{name}.py").write_text(textwrap.dedent(text))


@pytest.fixture
def examples(tmp_path):
    d = tmp_path / "ex"
    d.mkdir()
    _write(d, "b_second", GOOD.format(section="9.10", title="Second", name="b_second"))
    _write(d, "a_first", GOOD.format(section="9.2", title="First", name="a_first"))
    _write(d, "_helper", "x = 1\n")  # not an example
    return d


def test_list_sorts_by_section_and_skips_helpers(examples, capsys):
    assert main(["cookbook", "list", "--examples", str(examples)]) == 0
    out = capsys.readouterr().out
    assert "_helper" not in out
    assert out.index("a_first") < out.index("b_second")  # 9.2 before 9.10


def test_section_key_orders_numbers_then_appendices():
    secs = ["C", "10.1", "9.10", "9.2", "3", "E"]
    assert sorted(secs, key=section_key) == ["3", "9.2", "9.10", "10.1", "C", "E"]


def test_run_writes_figures_and_outcomes(examples, tmp_path, capsys):
    out = tmp_path / "out"
    js = tmp_path / "rec.json"
    assert main(["cookbook", "run", "--all", "--out", str(out), "--json", str(js), "--quiet"]
                + ["--examples", str(examples)]) == 0
    rec = json.loads((out / "outcomes.json").read_text())
    assert rec["ok"] is True and json.loads(js.read_text()) == rec
    assert [r["name"] for r in rec["examples"]] == ["a_first", "b_second"]
    assert rec["examples"][0]["checks"] == {"reached": True}
    assert rec["examples"][0]["values"] == {"error": 1e-9}
    assert (out / "a_first.png").exists() and (out / "b_second.png").exists()


def test_no_plots_passes_no_folder(examples, tmp_path):
    out = tmp_path / "out"
    assert main(["cookbook", "run", "a_first", "--no-plots", "--out", str(out), "--quiet",
                 "--examples", str(examples)]) == 0
    assert not (out / "a_first.png").exists() and (out / "outcomes.json").exists()


def test_a_failed_check_an_exception_and_a_bad_return_fail_the_run_but_not_the_others(examples, tmp_path,
                                                                                     capsys):
    _write(examples, "c_fail", FAILING)
    _write(examples, "d_raise", RAISING)
    _write(examples, "e_bad", MALFORMED)
    out = tmp_path / "out"
    assert main(["cookbook", "run", "--all", "--out", str(out), "--quiet", "--examples", str(examples)]) == 1
    rec = {r["name"]: r for r in json.loads((out / "outcomes.json").read_text())["examples"]}
    assert rec["a_first"]["ok"] and rec["b_second"]["ok"]
    assert not rec["c_fail"]["ok"] and rec["c_fail"]["checks"]["obstacle_avoided"] is False
    assert "RuntimeError: boom" in rec["d_raise"]["error"]
    assert "must return" in rec["e_bad"]["error"]
    io = capsys.readouterr()
    assert "FAILED: obstacle_avoided" in io.out
    assert "3 of 5 failed" in io.err


@pytest.mark.parametrize("argv, message", [
    (["cookbook", "run"], "name the examples to run, or pass --all"),
    (["cookbook", "run", "a_first", "--all"], "not both"),
    (["cookbook", "run", "nope"], "no cookbook example nope"),
])
def test_bad_command_lines_are_one_error(examples, argv, message, capsys):
    with pytest.raises(SystemExit) as e:
        main(argv + ["--examples", str(examples)])
    assert e.value.code == 2
    assert message in capsys.readouterr().err


def test_an_example_without_a_section_is_named(examples, capsys):
    _write(examples, "nosection", 'TITLE = "x"\n')
    with pytest.raises(SystemExit):
        main(["cookbook", "run", "--all", "--examples", str(examples)])
    assert "nosection.py has no SECTION" in capsys.readouterr().err


def test_the_readme_table_lists_every_example_of_the_source_tree():
    """examples/cookbook/README.md has one row per example, with its section and its figure."""
    readme = (DEFAULT_DIR / "README.md").read_text()
    examples = discover()
    assert examples, "no cookbook examples found"
    row = re.compile(r"^\| *§?([0-9A-Z.]+) *\| *\[`(\w+)`\]", re.M)
    rows = {m.group(2): m.group(1) for m in row.finditer(readme)}
    assert rows == {e.name: e.section for e in examples}
    for e in examples:
        assert f"figures/{e.name}.png" in readme


def test_sys_exit_nan_values_duplicates_and_unparsable_files(examples, tmp_path, capsys):
    _write(examples, "c_exit",
           'SECTION = "3"\nTITLE = "exits"\n\n\ndef run(out=None):\n    import sys\n    sys.exit(0)\n')
    _write(examples, "d_nan", 'SECTION = "3"\nTITLE = "nan"\n\n\ndef run(out=None):\n'
           '    return {"checks": {"ok": True}, "values": {"v": float("nan")}}\n')
    out = tmp_path / "out"
    assert main(["cookbook", "run", "--all", "--out", str(out), "--quiet", "--examples", str(examples)]) == 1
    text = (out / "outcomes.json").read_text()
    rec = {r["name"]: r for r in json.loads(text)["examples"]}  # strict JSON readers reject NaN
    assert "NaN" not in text and rec["d_nan"]["values"] == {"v": None}
    assert "SystemExit" in rec["c_exit"]["error"] and rec["b_second"]["ok"]
    assert main(["cookbook", "run", "a_first", "a_first", "--out", str(out), "--quiet",
                 "--examples", str(examples)]) == 0
    assert len(json.loads((out / "outcomes.json").read_text())["examples"]) == 1
    (examples / "e_broken.py").write_text("SECTION = '1'\nTITLE = 'x'\ndef run(:\n")
    for argv in (["cookbook", "list"], ["cookbook", "run", "a_first"]):
        with pytest.raises(SystemExit) as e:
            main(argv + ["--examples", str(examples)])
        assert e.value.code == 2
        assert "e_broken.py cannot be read: SyntaxError" in capsys.readouterr().err


def test_a_folder_without_examples_is_an_error(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["cookbook", "run", "--all", "--examples", str(tmp_path)])
    assert "no cookbook examples" in capsys.readouterr().err
