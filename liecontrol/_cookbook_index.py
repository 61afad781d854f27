"""The index of the seed-004 cookbook examples (``examples/cookbook/*.py``), read without importing them.

Every example is one file with two module-level string constants, ``SECTION`` (the seed section,
``"10.1.2"``) and ``TITLE``, and a function ``run(out: Path | None) -> {"checks": {name: bool},
"values": {name: number}}`` (see ``examples/cookbook/README.md``).  The index reads the two constants
with :mod:`ast`, so ``liecontrol cookbook list`` and the checks of ``liecontrol cookbook run NAME`` need
neither torch nor the examples' imports.

The examples live in the source tree, next to the packages (an editable install, as ``make`` does);
``--examples DIR`` points elsewhere.
"""

from __future__ import annotations

import ast
from dataclasses import dataclass
from pathlib import Path

__all__ = ["Example", "DEFAULT_DIR", "discover", "section_key"]

#: ``examples/cookbook`` of the source tree this package was installed from (editable install)
DEFAULT_DIR = Path(__file__).resolve().parent.parent / "examples" / "cookbook"


@dataclass(frozen=True)
class Example:
    """One example file: its name (the file stem), seed section, title and path."""

    name: str
    section: str
    title: str
    path: Path


def section_key(section: str) -> tuple:
    """Sort key of a section number: ``"9.10"`` after ``"9.2"``; appendices (``"C"``) after the numbers."""
    parts = section.split(".")
    return tuple((0, int(p), "") if p.isdigit() else (1, 0, p) for p in parts)


def _constants(path: Path) -> dict[str, str]:
    try:
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    except (SyntaxError, UnicodeDecodeError) as e:
        raise ValueError(f"cookbook example {path} cannot be read: {type(e).__name__}: {e}") from None
    found: dict[str, str] = {}
    for node in tree.body:
        if isinstance(node, ast.Assign) and len(node.targets) == 1 and isinstance(node.targets[0], ast.Name):
            if isinstance(node.value, ast.Constant) and isinstance(node.value.value, str):
                found[node.targets[0].id] = node.value.value
    return found


def discover(folder: str | Path | None = None) -> list[Example]:
    """The examples in ``folder`` (default :data:`DEFAULT_DIR`), sorted by seed section then name.

    Files starting with ``_`` are helpers, not examples.  A file without ``SECTION`` and ``TITLE`` string
    constants, or that does not parse, raises ``ValueError`` naming it (an example the index cannot
    describe is a bug); a folder without examples raises ``FileNotFoundError``."""
    folder = DEFAULT_DIR if folder is None else Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(
            f"no cookbook examples at {folder}: they live in the source tree's examples/cookbook/ (an "
            "editable install from a clone, as `make demo` does); pass --examples DIR to point elsewhere")
    out = []
    for path in sorted(folder.glob("*.py")):
        if path.name.startswith("_"):
            continue
        c = _constants(path)
        missing = [k for k in ("SECTION", "TITLE") if k not in c]
        if missing:
            raise ValueError(f"cookbook example {path} has no {' and '.join(missing)} string constant")
        out.append(Example(path.stem, c["SECTION"], c["TITLE"], path))
    if not out:
        raise FileNotFoundError(f"no cookbook examples (*.py files with SECTION and TITLE) in {folder}")
    return sorted(out, key=lambda e: (section_key(e.section), e.name))
