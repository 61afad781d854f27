"""The ``liecontrol`` command line: every bad value of every option of every command is one error line
naming the option (exit status 2) before any work starts; ``--help`` never imports torch; a group without
its subcommand shows its help; Ctrl-C stops ``compare``'s worker processes."""

import argparse
import contextlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from liecontrol import _args, cli
from liecontrol._options import COMMANDS, LEARN_TASKS, budget_item, learn_task

ROOT = Path(__file__).resolve().parents[1]
TASK_ARG = "PendulumSwingUp"

#: bad values by argument type (the file-system ones are made per test: see _bad_paths)
BAD = {
    _args.positive_int: ["0", "-3", "x", "1.5", ""],
    _args.nonnegative_int: ["-1", "x", "2.5"],
    _args.positive_float: ["0", "-1e-3", "nan", "inf", "x"],
    _args.nonnegative_float: ["-1", "nan", "x"],
    _args.task_name: ["NoSuchTask", "liecontrol/PendulumSwingUp-v1", "other/PendulumSwingUp-v0", "quadrotor"],
    budget_item: ["0", "dqn=5", "ppo=-1", "ppo=x"],
    _args.seed: ["-1", "x", "2.5", str(2**32), "99999999999999999999999"],
    _args.thread_count: ["0", "-2", "x", "99999999999"],
    learn_task: ["NoSuchTask", "quadrotorc", "ArmReach", "PandaReach"],  # the last three: not learnable
}
BAD_BY_NAME = {"_anchor_list": ["foo", "pypose,bar"], "_ilqr_problem": ["ArmReach", "x"], "int_at_most_1000":
               ["0", "1001", "x"],
               "task": ["ArmReach"], "_workload_list": ["quadrotor_step,nope", "", " , "]}
PATH_TYPES = ("out_dir", "out_file", "existing_dir", "existing_file")


def _actions(options):
    p = argparse.ArgumentParser()
    options(p)
    return [a for a in p._actions if a.nargs != 0 and a.dest != "help"]


def _cases():
    for path, options, _, _ in COMMANDS:
        for a in _actions(options):
            name = a.option_strings[0] if a.option_strings else a.metavar
            bad = BAD.get(a.type) or BAD_BY_NAME.get(getattr(a.type, "__name__", ""), [])
            if a.choices is not None:
                bad = ["bogus"]
            if a.type in (_args.out_dir, _args.out_file, _args.existing_dir, _args.existing_file):
                bad = [a.type.__name__]  # made in the test (tmp_path)
            for v in bad:
                yield pytest.param(path, name, v, id=f"{' '.join(path)} {name} {v!r}")


def _bad_paths(kind: str, tmp_path: Path) -> list[str]:
    f = tmp_path / "a_file"
    f.write_text("x")
    long = str(tmp_path / ("a" * 300))  # a name longer than the file system allows
    return {"out_dir": [str(f), str(f / "sub"), long], "out_file": [str(tmp_path), str(f / "x.json"), long],
            "existing_dir": [str(tmp_path / "missing"), str(f), long],
            "existing_file": [str(tmp_path / "missing"), str(tmp_path), long]}[kind]


def _argv(path, name, value):
    positional = [] if name == "TASK" else [TASK_ARG] if any(
        not a.option_strings for a in _actions(next(o for p, o, _, _ in COMMANDS if p == path))) else []
    return [*path, value, *positional] if name == "TASK" else [*path, *positional, name, value]


@pytest.mark.parametrize("path, name, value", list(_cases()))
def test_bad_value_is_one_line_naming_the_option(path, name, value, tmp_path, capsys, monkeypatch):
    def no_work(module):
        raise AssertionError(f"{module} imported: the command started working")

    monkeypatch.setattr(cli, "_load", no_work)
    values = _bad_paths(value, tmp_path) if value in PATH_TYPES else [value]
    for v in values:
        with pytest.raises(SystemExit) as e:
            cli.main(_argv(path, name, v))
        assert e.value.code == 2
        err = capsys.readouterr().err
        assert "Traceback" not in err
        errors = [line for line in err.splitlines() if "error:" in line]
        assert len(errors) == 1 and f"argument {name}" in errors[0], err
        assert errors[0].startswith(f"liecontrol {' '.join(path)}: error: argument {name}: "), err


@pytest.mark.parametrize("argv, where", [
    (["compare", TASK_ARG, "--algos", "ppo", "--budget-steps", "sac=5"], "--budget-steps"),
    (["bench", "lie", "--devices", "tpu"], "--devices"),
    (["bench", "envs", "--devices", "cuda:0" if not __import__("torch").cuda.is_available() else "xla"],
     "--devices"),
])
def test_bad_combinations_name_the_option(argv, where, capsys, monkeypatch):
    monkeypatch.setattr(cli, "_load", lambda m: pytest.fail(f"{m} imported"))
    with pytest.raises(SystemExit) as e:
        cli.main(argv)
    err = capsys.readouterr().err
    assert e.value.code == 2 and f"error: argument {where}: " in err and "Traceback" not in err


def test_tensorboard_missing_is_an_error_before_any_work(capsys, monkeypatch):
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda n, *a: None if n == "tensorboard" else real(n, *a))
    monkeypatch.setattr(cli, "_load", lambda m: pytest.fail(f"{m} imported"))
    for argv in (["compare", TASK_ARG, "--tensorboard"], ["learn", "mpc-ppo", TASK_ARG, "--tensorboard"]):
        with pytest.raises(SystemExit) as e:
            cli.main(argv)
        err = capsys.readouterr().err
        assert e.value.code == 2
        assert "argument --tensorboard: the 'tensorboard' package is not installed" in err


def test_task_names_ids_and_prefixes():
    assert _args.task_name("PendulumSwingUp") == "PendulumSwingUp"
    assert _args.task_name("liecontrol/CartPoleSwingUp-v0") == "CartPoleSwingUp"
    assert _args.task_name("pendulum") == "PendulumSwingUp"
    assert _args.task_name("CARTPOLE") == "CartPoleSwingUp"
    with pytest.raises(argparse.ArgumentTypeError, match="ambiguous"):
        _args.task_name("quadrotor")  # QuadrotorTrack and QuadrotorFigureEight
    with pytest.raises(argparse.ArgumentTypeError, match="-v0"):
        _args.task_name("liecontrol/PendulumSwingUp-v1")


def test_option_lists_match_the_commands_tables():
    from liecontrol._options import ENV_BENCH_TASKS, ILQR_PROBLEMS
    from liecontrol.bench.envs import ENVS
    from liecontrol.bench.ilqr import PROBLEMS

    assert tuple(PROBLEMS) == ILQR_PROBLEMS
    assert tuple(task for task, _ in ENVS.values()) == ENV_BENCH_TASKS


def test_every_option_shows_its_default_and_a_help():
    for path, options, _, _ in COMMANDS:
        p = argparse.ArgumentParser(formatter_class=_args.HelpFormatter)
        options(p)
        for a in p._actions:
            assert a.help, f"{path} {a.dest}: no help"
            shown = p._get_formatter()._get_help_string(a)
            if a.option_strings and a.default not in (None, False) and a.dest != "help":
                assert "default" in shown, f"{path} {a.dest}: {shown}"


def test_help_of_every_command_imports_no_torch():
    code = ("import sys\nfrom liecontrol import cli\nfrom liecontrol._options import COMMANDS\n"
            "for path, *_ in COMMANDS:\n"
            "    try:\n        cli.main([*path, '--help'])\n    except SystemExit as e:\n"
            "        assert e.code == 0, path\n"
            "heavy = [m for m in ('torch', 'numpy', 'learning', 'controllers', 'stable_baselines3') "
            "if m in sys.modules]\nassert not heavy, heavy\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "usage: liecontrol reproduce pose-mpc" in r.stdout


@pytest.mark.parametrize("group", ["bench", "learn", "reproduce"])
def test_group_without_subcommand_prints_its_help_and_an_error(group, capsys):
    with pytest.raises(SystemExit) as e:
        cli.main([group])
    err = capsys.readouterr().err
    assert e.value.code == 2
    subs = [p[1] for p, *_ in COMMANDS if p[0] == group]
    assert all(s in err.split("error:")[0] for s in subs)  # the group's help, listing its subcommands
    assert f"liecontrol {group}: error: choose a subcommand: {', '.join(subs)}" in err


def _children(pid: int) -> list[int]:
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                stat = (d / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                out.append(int(d.name))
    return out


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="reads the process table from /proc (Linux)")
def test_ctrl_c_stops_compare_and_its_workers(tmp_path):
    cmd = [sys.executable, "-m", "liecontrol", "compare", TASK_ARG, "--algos", "ppo", "--seeds", "0", "1",
           "--budget-steps", "1000000", "--eval-episodes", "1", "--no-mpc", "--jobs", "2", "--quiet",
           "--out", str(tmp_path)]
    # Ctrl-C as in a terminal: a run started in the background of a non-interactive shell (as CI may start
    # the suite) inherits SIGINT ignored, and Python then never raises KeyboardInterrupt
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    workers: list[int] = []
    try:
        deadline = time.monotonic() + 120
        while len(workers) < 3 and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.5)  # two workers and the resource tracker
            workers = _children(proc.pid)
        assert len(workers) >= 3, "the worker processes never started"
        time.sleep(2)
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=60)
    finally:  # a failed test leaves no training processes behind
        if proc.poll() is None:
            for pid in [*_children(proc.pid), proc.pid]:
                with contextlib.suppress(OSError):
                    os.kill(pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 130, err
    assert "liecontrol compare: interrupted" in err and "Traceback" not in err
    assert "leaked" not in err  # the resource tracker's warning about semaphores
    deadline = time.monotonic() + 10
    while any(_alive(w) for w in workers) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not any(_alive(w) for w in workers)
    assert not (tmp_path / "compare.json").exists()


def test_old_invocation_of_make_demo_still_parses():
    args = cli.build_parser().parse_args(["demo", "--out", "out"])
    assert args.out == "out" and args.num_envs == 256



def test_the_learnable_tasks_are_those_with_a_quadratic_mpc_cost():
    """``LEARN_TASKS`` (checked at parse time, without torch) against each task's own MPC cost."""
    from controllers.costs import PeriodicQuadraticCost, QuadraticCost
    from learning.envs import TASKS
    from learning.envs.single import make_task

    learnable = []
    for name in TASKS:
        try:
            cost = make_task(name).mpc_cost(5)
        except NotImplementedError:
            continue
        base = cost.base if isinstance(cost, PeriodicQuadraticCost) else cost
        if isinstance(base, QuadraticCost):
            learnable.append(name)
    assert sorted(learnable) == sorted(LEARN_TASKS)


@pytest.mark.skipif(not hasattr(__import__("os"), "geteuid") or __import__("os").geteuid() == 0,
                    reason="root writes into any folder: the check cannot be seen failing")
def test_an_existing_out_folder_that_cannot_be_written_is_refused(tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    with pytest.raises(argparse.ArgumentTypeError, match="cannot write into this folder"):
        _args.out_dir(str(ro))


def test_json_at_the_out_folder_is_refused(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(cli, "_load", lambda m: pytest.fail(f"{m} imported"))
    d = str(tmp_path / "c9")
    with pytest.raises(SystemExit) as e:
        cli.main(["compare", TASK_ARG, "--out", d, "--json", d])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "error: argument --json: " in err


def test_an_option_error_found_by_the_command_is_argparse_shaped(capsys, monkeypatch):
    """A value only the command's data can judge (here: more steps than the path has) ends like a parse
    error: one line naming the option, exit status 2, no traceback."""
    import types

    def fake_load(module):
        def run(args):
            raise _args.OptionError("--steps", "must be at most 1127 (one lap of the path), got 5000")
        return types.SimpleNamespace(run=run)

    monkeypatch.setattr(cli, "_load", fake_load)
    assert cli.main(["reproduce", "ugv", "--steps", "5000"]) == 2
    err = capsys.readouterr().err
    assert err.strip() == ("liecontrol reproduce ugv: error: argument --steps: must be at most 1127 (one lap "
                           "of the path), got 5000")


def test_list_options_take_spaces_or_commas_without_repeats():
    p = cli.build_parser()
    a = p.parse_args(["bench", "solver", "--workloads", "quadrotor_step", "pendulum_mpc_step,quadrotor_step"])
    b = p.parse_args(["bench", "solver", "--workloads", "quadrotor_step,pendulum_mpc_step"])
    assert a.workloads == b.workloads == ("quadrotor_step", "pendulum_mpc_step")
    assert p.parse_args(["bench", "lqr", "--anchors", "pypose", "plain"]).anchors == ("pypose", "plain")
    assert p.parse_args(["bench", "lqr"]).anchors == ("pypose", "mpc", "plain")


@pytest.mark.parametrize("argv, where", [
    (["bench", "solver", "--q"], "unrecognized arguments: --q"),  # no abbreviation of --quick
    (["compare", TASK_ARG, "--seeds", "0", "0"], "argument --seeds: a seed given twice"),
    (["compare", TASK_ARG, "--budget-steps", "ppo=1", "ppo=16"], "argument --budget-steps: one budget per"),
    (["compare", ""], "argument TASK: expected a task name, got an empty string"),
])
def test_conflicting_or_ambiguous_values_are_refused(argv, where, capsys, monkeypatch):
    monkeypatch.setattr(cli, "_load", lambda m: pytest.fail(f"{m} imported"))
    with pytest.raises(SystemExit) as e:
        cli.main(argv)
    err = capsys.readouterr().err
    assert e.value.code == 2 and where in err and "Traceback" not in err
