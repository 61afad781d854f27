"""The ``liecontrol`` command.

The whole command line is parsed and checked by :mod:`liecontrol._options` (no torch import), so ``--help``
is instant and a bad value is one error line (exit status 2) before any work starts.  Only then is the
command's module imported and its ``run(args) -> int`` called.  A group (``bench``, ``learn``,
``reproduce``) without a subcommand prints the group's help and an error line.  Ctrl-C ends a command with
exit status 130 and one line, after the command has stopped its worker processes.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from liecontrol._args import HelpFormatter, OptionError
from liecontrol._options import COMMANDS, GROUPS

__all__ = ["main", "build_parser"]


def _parser(parent, name: str, help_: str) -> argparse.ArgumentParser:
    # no abbreviations: `--q` must not silently mean `--quick` and start the work
    return parent.add_parser(name, help=help_, description=help_, formatter_class=HelpFormatter,
                             allow_abbrev=False)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of every command (no command module is imported)."""
    parser = argparse.ArgumentParser(
        prog="liecontrol", formatter_class=HelpFormatter, allow_abbrev=False,
        description="Lie groups, differentiable controllers and robot learning in PyTorch.",
    )
    parser.add_argument("--version", action="version", version=sys.modules["liecontrol"].__version__)
    top = parser.add_subparsers(dest="command", metavar="COMMAND")
    groups: dict[str, argparse._SubParsersAction] = {}
    for path, options, module, help_ in COMMANDS:
        if len(path) == 1:
            sub = _parser(top, path[0], help_)
        else:
            if path[0] not in groups:
                gp = _parser(top, path[0], GROUPS[path[0]])
                gp.set_defaults(_group=gp)
                groups[path[0]] = gp.add_subparsers(dest="subcommand", metavar="SUBCOMMAND")
            sub = _parser(groups[path[0]], path[1], help_)
        options(sub)
        sub.set_defaults(_module=module, _parser=sub)
    return parser


def _load(module: str):
    """The command's module (imported only once the command line is known to be good)."""
    return importlib.import_module(module)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    if not argv:
        parser.print_help()
        return 0
    args = parser.parse_args(argv)
    if getattr(args, "_module", None) is None:  # a group without its subcommand
        group = args._group
        group.print_help(sys.stderr)
        names = [p[1] for p, *_ in COMMANDS if p[0] == group.prog.split()[-1]]
        group.error(f"choose a subcommand: {', '.join(names)}")
    check = getattr(args, "_check", None)
    msg = check(args) if check is not None else None
    if msg:
        args._parser.error(msg)
    command, module = args._parser.prog, args._module
    for k in ("_module", "_parser", "_group", "_check"):
        args.__dict__.pop(k, None)
    mod = _load(module)
    try:
        return int(mod.run(args) or 0)
    except KeyboardInterrupt:
        print(f"{command}: interrupted", file=sys.stderr)
        return 130
    except OptionError as e:  # a bad value only the command's data could reveal: argparse's form and code
        print(f"{command}: error: argument {e.option}: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
