"""The README runs: every ```python block executes as written, in a fresh namespace and a scratch folder,
and every command line of its command table is a command that exists."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from liecontrol import cli

README = Path(__file__).resolve().parents[1] / "README.md"


def blocks(language: str) -> list[str]:
    """The fenced code blocks of the README written in ``language`` ('' for a bare fence)."""
    found, current, lang = [], None, ""
    for line in README.read_text().splitlines(keepends=True):
        if current is None and line.startswith("```"):
            current, lang = [], line[3:].strip()
        elif current is not None and line.rstrip() == "```":
            if lang == language:
                found.append("".join(current))
            current = None
        elif current is not None:
            current.append(line)
    return found


def test_the_readme_has_python_blocks():
    assert len(blocks("python")) >= 3


@pytest.mark.parametrize("index", range(len(blocks("python"))))
def test_python_block_runs(index, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # a block may write files (eval.json, eval.png)
    code = blocks("python")[index]
    exec(compile(code, f"README.md python block {index}", "exec"), {"__name__": f"readme_{index}"})


def _command_lines() -> list[list[str]]:
    table = next(b for b in blocks("") if b.startswith("liecontrol "))
    # each line: the command (words, then placeholders and options), two spaces, what it does
    commands = [re.split(r"\s{2,}", line)[0].split()[1:] for line in table.splitlines() if line.strip()]
    return [[w for w in c if re.fullmatch(r"[a-z][a-z0-9-]*", w)] for c in commands]


@pytest.mark.parametrize("path", _command_lines(), ids=" ".join)
def test_command_in_the_table_exists(path, capsys):
    with pytest.raises(SystemExit) as e:
        cli.main([*path, "--help"])
    assert e.value.code == 0
    assert f"liecontrol {path[0]}" in capsys.readouterr().out  # (an unknown subcommand or mode exits 2)
