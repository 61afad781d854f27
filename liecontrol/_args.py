"""Argument types and the help formatter shared by every ``liecontrol`` command.

Every type here is an argparse ``type=`` callable: a bad value becomes one line
``liecontrol CMD: error: argument --NAME: ...`` (exit status 2) while the command line is parsed, before
any work starts.  This module imports nothing heavy (no torch): ``liecontrol CMD --help`` builds its parser
from it alone.  :func:`task_name` imports :mod:`learning.envs` (and :func:`env_name` gymnasium) only when
it is called.
"""

from __future__ import annotations

import argparse
import math
import os
from pathlib import Path

__all__ = ["HelpFormatter", "positive_int", "nonnegative_int", "positive_float", "nonnegative_float", "seed",
           "thread_count", "int_at_most", "float_at_most", "OptionError", "out_dir", "out_file",
           "existing_file", "existing_dir", "task_name", "env_name", "KNOWN_VERSION", "SEED_MAX",
           "THREADS_MAX"]

#: the only registered version of the ``liecontrol/<Name>-vN`` environment ids
KNOWN_VERSION = 0


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Every option's help ends with its default, unless the default is nothing to show (``None``, a flag's
    ``False``) or the help already says it ("default" in the text)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        shown = not any(action.default is v for v in (None, False, argparse.SUPPRESS))
        nothing = not shown or not action.option_strings
        if nothing or "default" in text:
            return text
        d = action.default
        shown = " ".join(map(str, d)) if isinstance(d, (list, tuple)) else str(d)
        return f"{text} (default: {shown})"


def _number(s: str, kind: type):
    try:
        v = kind(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {'an integer' if kind is int else 'a number'}, got {s!r}"
                                         ) from None
    if kind is float and not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {s!r}")
    return v


def positive_int(s: str) -> int:
    """A count ≥ 1."""
    v = _number(s, int)
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {s}")
    return v


def nonnegative_int(s: str) -> int:
    """An integer ≥ 0 (a seed, or a count where 0 means "skip")."""
    v = _number(s, int)
    if v < 0:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {s}")
    return v


SEED_MAX = 2**32 - 1  # numpy's and gymnasium's seeds are 32-bit
THREADS_MAX = 1024


def seed(s: str) -> int:
    """A random seed, ``0 … 2³² − 1``."""
    v = nonnegative_int(s)
    if v > SEED_MAX:
        raise argparse.ArgumentTypeError(f"expected a seed between 0 and 2**32 - 1, got {s}")
    return v


def thread_count(s: str) -> int:
    """A count of torch threads, ``1 … 1024``."""
    v = positive_int(s)
    if v > THREADS_MAX:
        raise argparse.ArgumentTypeError(f"expected at most {THREADS_MAX} threads, got {s}")
    return v


def float_at_most(hi: float):
    """A finite number in ``[0, hi]``."""
    def check(s: str) -> float:
        v = nonnegative_float(s)
        if v > hi:
            raise argparse.ArgumentTypeError(f"expected a number between 0 and {hi:g}, got {s}")
        return v
    check.__name__ = "number"
    return check


def int_at_most(hi: int):
    """A count ``1 … hi``."""
    def check(s: str) -> int:
        v = positive_int(s)
        if v > hi:
            raise argparse.ArgumentTypeError(f"expected a positive integer of at most {hi}, got {s}")
        return v
    check.__name__ = f"int_at_most_{hi}"
    return check


class OptionError(ValueError):
    """A bad option value found after parsing (it needs data the parser does not load): the command prints
    ``<command>: error: argument <option>: <message>`` and exits with 2, as argparse does."""

    def __init__(self, option: str, message: str):
        super().__init__(message)
        self.option = option


def positive_float(s: str) -> float:
    """A finite number > 0."""
    v = _number(s, float)
    if v <= 0:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {s}")
    return v


def nonnegative_float(s: str) -> float:
    """A finite number ≥ 0."""
    v = _number(s, float)
    if v < 0:
        raise argparse.ArgumentTypeError(f"expected a number >= 0, got {s}")
    return v


def _path_check(s: str, check) -> str:
    """``check(Path(s))``, with an operating-system refusal (a name too long, …) as an argument error."""
    try:
        check(Path(s))
    except OSError as e:
        raise argparse.ArgumentTypeError(f"{s[:80]}{'…' if len(s) > 80 else ''}: {e.strerror or e}") from None
    return s


def _writable_parent(p: Path) -> None:
    """Refuse ``p`` when an existing ancestor is a file or cannot be written (the folder is made later)."""
    for a in p.absolute().parents:
        if a.exists():
            if not a.is_dir():
                raise argparse.ArgumentTypeError(f"{p} is under {a}, which is a file, not a folder")
            if not os.access(a, os.W_OK | os.X_OK):
                raise argparse.ArgumentTypeError(f"{p}: cannot write into {a}")
            return


def out_dir(s: str) -> str:
    """An output folder: an existing folder, or a path that can be created (nothing on its way is a file)."""
    if not s:
        raise argparse.ArgumentTypeError("expected a folder, got an empty string")
    def check(p: Path) -> None:
        if p.exists() and not p.is_dir():
            raise argparse.ArgumentTypeError(f"{s} is a file, not a folder")
        if p.is_dir() and not os.access(p, os.W_OK | os.X_OK):
            raise argparse.ArgumentTypeError(f"{s}: cannot write into this folder")
        _writable_parent(p)
    return _path_check(s, check)


def out_file(s: str) -> str:
    """An output file: not an existing folder, and its folder can be created."""
    if not s:
        raise argparse.ArgumentTypeError("expected a file path, got an empty string")
    def check(p: Path) -> None:
        if p.is_dir():
            raise argparse.ArgumentTypeError(f"{s} is a folder, expected a file path")
        _writable_parent(p)
    return _path_check(s, check)


def existing_file(s: str) -> str:
    """An existing file (an interpreter, for example)."""
    def check(p: Path) -> None:
        if not p.is_file():
            raise argparse.ArgumentTypeError(f"{s} is not a file" if p.exists() else f"{s} does not exist")
    return _path_check(s, check)


def existing_dir(s: str) -> str:
    """An existing folder."""
    def check(p: Path) -> None:
        if not p.is_dir():
            raise argparse.ArgumentTypeError(f"{s} is not a folder" if p.exists() else f"{s} does not exist")
    return _path_check(s, check)


def task_name(value: str) -> str:
    """The registered task name of ``value``: the name (``PendulumSwingUp``), its gymnasium id
    (``liecontrol/PendulumSwingUp-v0``), or, ignoring case, the name or a prefix of exactly one name
    (``pendulum``, ``cartpole``)."""
    from learning.envs import TASKS

    if not value.strip():
        raise argparse.ArgumentTypeError("expected a task name, got an empty string")
    name = value
    if "/" in value:
        ns, _, rest = value.partition("/")
        base, sep, version = rest.rpartition("-v")
        if ns != "liecontrol" or not sep or version != str(KNOWN_VERSION):
            raise argparse.ArgumentTypeError(
                f"unknown environment id {value!r}: the registered ids are "
                f"liecontrol/<task>-v{KNOWN_VERSION}")
        name = base
    if name in TASKS:
        return name
    low = name.lower()
    hits = [t for t in TASKS if t.lower() == low] or [t for t in TASKS if t.lower().startswith(low)]
    if len(hits) == 1 and low:
        return hits[0]
    what = f"ambiguous task {value!r} (matches {', '.join(hits)})" if len(hits) > 1 else \
        f"unknown task {value!r}"
    raise argparse.ArgumentTypeError(f"{what}; known: {', '.join(sorted(TASKS))} (or a unique prefix, any "
                                     f"case, or liecontrol/<task>-v{KNOWN_VERSION})")


def env_name(value: str) -> str:
    """:func:`task_name`, or a foreign gymnasium id kept as it is: a registered id outside the
    ``liecontrol/`` namespace (``Pendulum-v1``, ``InvertedPendulum-v5``; exact spelling) that is not a task.
    An unknown value is the task error, which also names this form."""
    if value.strip() and not value.startswith("liecontrol/"):
        import gymnasium as gym

        from learning.envs import TASKS

        if value not in TASKS and value in gym.registry:
            return value
    try:
        return task_name(value)
    except argparse.ArgumentTypeError as e:
        raise argparse.ArgumentTypeError(f"{e}; or a registered gymnasium id such as Pendulum-v1") from None
