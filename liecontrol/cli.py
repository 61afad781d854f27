"""The ``liecontrol`` command.

Every subcommand lives in its own module exposing ``add_arguments(parser)`` and ``run(args) -> int``;
the module is imported only when its subcommand runs, so ``liecontrol --help`` stays fast and a
heavy dependency of one subcommand never slows another.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from types import MappingProxyType

__all__ = ["main", "build_parser"]

# (command path, module, one-line help).  A command path of two words is a sub-subcommand.
_COMMANDS: tuple[tuple[tuple[str, ...], str, str], ...] = (
    (("demo",), "liecontrol.demo", "showcase: batched SE(3) accuracy and a differentiable iLQR swing-up"),
    (("bench", "lie"), "liecontrol.bench.lie", "Lie-group ops vs pypose/roma: speed and round-trip error"),
    (("bench", "lqr"), "liecontrol.bench.lqr", "LQR vs pypose and mpc.pytorch"),
    (("bench", "ilqr"), "liecontrol.bench.ilqr", "iLQR swing-up vs mpc.pytorch box-DDP"),
    (("bench", "envs"), "liecontrol.bench.envs", "vector-env steps/s vs gymnasium SyncVectorEnv and EnvPool"),
    (("bench", "solver"), "liecontrol.bench.solver",
     "the solver workloads of issue 23 (MPC steps, iLQR, MPC head) vs crocoddyl, CasADi, numpy, SB3's MLP"),
    (("compare",), "liecontrol.compare", "MPC expert vs PPO/SAC trained within a step budget, same seeds"),
    (("learn",), "liecontrol.learn",
     "learning with the MPC: MPC-headed PPO vs PPO (equal steps, equal time); behaviour cloning"),
    (("reproduce", "me2"), "liecontrol.reproduce.me2",
     "seed 000 Sec. 4: ME2 horizon prediction, Table 1, Fig. 3-4"),
    (("reproduce", "quadrotor"), "liecontrol.reproduce.quadrotor",
     "seed 003 Sec. VII-A: error-state MPC of a quadrotor (circle, flip, 8 m/s loop) vs CasADi+IPOPT"),
    (("reproduce", "ugv"), "liecontrol.reproduce.ugv",
     "seed 003 Sec. VII-B: error-state MPC of a ground vehicle on a curved road"),
    (("reproduce", "pose-mpc"), "liecontrol.reproduce.pose_mpc",
     "seed 000 Eq. 16: ME2 linear pose MPC (world/local frame) vs SE(3) error-state MPC on a Panda"),
)

_GROUP_HELP = MappingProxyType({
    "bench": "benchmarks against the anchors, measured in the same run",
    "reproduce": "reproductions of the experiments in the seed papers",
})


def build_parser(load: bool = False) -> argparse.ArgumentParser:
    """The argument parser; with ``load=True`` every subcommand adds its own options."""
    parser = argparse.ArgumentParser(
        prog="liecontrol",
        description="Lie groups, differentiable controllers and robot learning in PyTorch.",
    )
    parser.add_argument("--version", action="version", version=sys.modules["liecontrol"].__version__)
    top = parser.add_subparsers(dest="command", metavar="COMMAND")
    groups: dict[str, argparse._SubParsersAction] = {}
    for path, module, help_ in _COMMANDS:
        if len(path) == 1:
            sub = top.add_parser(path[0], help=help_, description=help_)
        else:
            if path[0] not in groups:
                gp = top.add_parser(path[0], help=_GROUP_HELP.get(path[0], ""))
                groups[path[0]] = gp.add_subparsers(dest="subcommand", metavar="SUBCOMMAND")
            sub = groups[path[0]].add_parser(path[1], help=help_, description=help_)
        if load:
            importlib.import_module(module).add_arguments(sub)
    return parser


def _selected_path(argv: list[str]) -> tuple[str, ...] | None:
    words = [a for a in argv if not a.startswith("-")]
    for path, _, _ in _COMMANDS:
        if tuple(words[: len(path)]) == path:
            return path
    return None


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    path = _selected_path(argv)
    if path is None:
        # No complete command: argparse prints help (or a usage error) for what was typed.
        parser = build_parser(load=False)
        parser.parse_args(argv)
        parser.print_help()
        return 0 if not argv else 2
    module, help_ = next((m, h) for p, m, h in _COMMANDS if p == path)
    mod = importlib.import_module(module)
    sub = argparse.ArgumentParser(prog="liecontrol " + " ".join(path), description=help_)
    mod.add_arguments(sub)
    args = sub.parse_args(_strip(argv, path))
    return int(mod.run(args) or 0)


def _strip(argv: list[str], path: tuple[str, ...]) -> list[str]:
    out, todo = [], list(path)
    for a in argv:
        if todo and a == todo[0]:
            todo.pop(0)
        else:
            out.append(a)
    return out


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
