"""Every ``liecontrol`` command line the documents show (README.md, BENCHMARKS.md, ARCHITECTURE.md, the
Makefile) parses with today's options: a renamed or removed option in the code fails here until the
documents follow.  Placeholders (``TASK``, ``ENV``, ``F``, ``PATH``) stand for a task and a file; lines are
only parsed, never run."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from liecontrol import cli
from liecontrol._options import GROUPS

ROOT = Path(__file__).resolve().parents[1]
PLACEHOLDERS = {"TASK": "PendulumSwingUp", "ENV": "PendulumSwingUp"}
FILES = {"F", "PATH"}


def _table_lines() -> list[str]:
    """The README's command table: the command part of each line (before two spaces)."""
    lines, inside = [], False
    for line in (ROOT / "README.md").read_text().splitlines():
        if line.startswith("```"):
            inside = not inside
        elif inside and line.startswith("liecontrol "):
            lines.append(re.split(r"\s{2,}", line)[0])
    return lines


def _quoted_lines() -> list[tuple[str, str]]:
    found = [("README.md table", line) for line in _table_lines()]
    for name in ("README.md", "BENCHMARKS.md", "ARCHITECTURE.md"):
        for span in re.findall(r"`(?:\.venv/bin/)?(liecontrol\s[^`]+)`", (ROOT / name).read_text()):
            found.append((name, " ".join(span.split())))
    for line in re.findall(r"\$\(BIN\)/(liecontrol [^\n]+)", (ROOT / "Makefile").read_text()):
        found.append(("Makefile", line.strip()))
    # alternatives written a|b are one line each
    out = []
    for where, line in found:
        m = re.search(r"(\S+)\|(\S+)", line)
        out += [(where, line.replace(m.group(0), alt)) for alt in m.groups()] if m else [(where, line)]
    return out


def _argv(line: str, tmp_path: Path) -> list[str]:
    words = line.replace("[", " ").replace("]", " ").split()[1:]
    return [PLACEHOLDERS.get(w, str(tmp_path / "out.json") if w in FILES else w) for w in words]


LINES = [pytest.param(line, id=f"{where}: {line}") for where, line in _quoted_lines()
         if "COMMAND" not in line]


def test_the_documents_show_command_lines():
    assert len(LINES) >= 20


@pytest.mark.parametrize("line", LINES)
def test_documented_command_line_parses(line, tmp_path, capsys):
    argv = _argv(line, tmp_path)
    parser = cli.build_parser()
    if argv in (["--help"], ["--version"]):
        with pytest.raises(SystemExit) as e:
            parser.parse_args(argv)
        assert e.value.code == 0
        return
    args = parser.parse_args(argv)  # a bad option or value exits 2 with argparse's error line
    if argv == [argv[0]] and argv[0] in GROUPS:  # a group named in the text
        return
    options = args._parser._option_string_actions
    # whole option names (argparse would also take a prefix: the old --batch for --batches)
    assert [w for w in argv if w.startswith("--") and w not in options] == [], line
