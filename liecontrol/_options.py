"""The options of every ``liecontrol`` command, in one light module (no torch): ``liecontrol CMD --help`` and
every check of the command line run before the command's own module is imported.

Conventions, the same in every command:

* ``--out DIR`` is the folder the command writes its files into (created if missing), never a root below
  which a subfolder is made; ``--json PATH`` also writes the JSON record to PATH.
* A task is named by its registered name (``PendulumSwingUp``), its gymnasium id
  (``liecontrol/PendulumSwingUp-v0``) or a unique prefix in any case (``pendulum``, ``cartpole``).
* ``--num-envs`` is a number of batched environments; ``--batch`` a batch size; ``--horizon`` a horizon in
  steps; ``--threads`` torch's intra-op threads; ``--seed`` one seed, ``--seeds`` several.  An option that
  takes a list has a plural name (``--tasks``, ``--batches``, ``--dtypes``, ``--devices``).
* ``--no-plots`` skips the figures; ``--quiet`` turns progress bars and progress lines off.

Each command's builder adds its options to an argparse parser; a check of several options together is set
as the parser's ``_check`` default (a function ``args -> error message | None``).
"""

from __future__ import annotations

import argparse
import importlib.util
import re
from pathlib import Path

from liecontrol._args import (
    env_name,
    existing_dir,
    existing_file,
    float_at_most,
    int_at_most,
    nonnegative_float,
    nonnegative_int,
    out_dir,
    out_file,
    positive_float,
    positive_int,
    seed,
    task_name,
    thread_count,
)

__all__ = ["COMMANDS", "GROUPS", "LIE_OPS", "QUADROTOR_SCENARIOS", "UGV_PAPER_HORIZON", "UGV_QUICK_STEPS",
           "UGV_WEIGHTS", "ILQR_PROBLEMS", "ENV_BENCH_TASKS", "ENV_BENCH_IMPLS", "SOLVER_WORKLOADS", "DTYPES",
           "LEARN_TASKS", "MPC_PPO_TASKS", "budget_item"]

ME2_PAPER = ("Torres Alberto et al., \"A linearization method based on Lie algebra for pose estimation in a "
             "time horizon\" (ARK 2022)")
MANIFOLD_PAPER = ("Lu, Xu and Zhang, \"Model Predictive Control for Trajectory Tracking on Differentiable "
                  "Manifolds\"")

DTYPES = ("float32", "float64")
LIE_OPS = ("exp", "exp_quat", "exp_mat", "log", "log_quat", "log_mat", "compose", "act", "inverse",
           "Jr", "Jl", "Jr_inv", "Jl_inv")
#: the swing-up problems of ``bench ilqr`` (keys of :data:`liecontrol.bench.ilqr.PROBLEMS`)
ILQR_PROBLEMS = ("pendulum", "cartpole")
#: the tasks ``bench envs`` steps (with an anchor each, :data:`liecontrol.bench.envs.ENVS`)
ENV_BENCH_TASKS = ("PendulumSwingUp", "CartPoleSwingUp")
ENV_BENCH_IMPLS = ("ours", "gymnasium-sync", "envpool")
#: the workloads ``bench solver`` times (:mod:`liecontrol.bench.solver` describes each)
SOLVER_WORKLOADS = ("quadrotor_step", "pendulum_mpc_step", "pendulum_ilqr_iteration",
                    "cartpole_swingup_batch64", "pendulum_swingup_batch64", "car_parking_step",
                    "mpc_head_fwd_bwd", "cookbook_manipulator", "cookbook_car", "cookbook_bicopter")
QUADROTOR_SCENARIOS = ("circle", "circle_mass", "flip", "loop8")
UGV_PAPER_HORIZON = 45
UGV_QUICK_STEPS = 150
UGV_WEIGHTS = {"q_pos": 100.0, "q_yaw": 10.0, "r_v": 1.0, "r_omega": 1.0}


def _common(p: argparse.ArgumentParser, *, out: str | None = None, json: bool = True, threads: int | None = 1,
            quiet: bool = False, plots: bool = False) -> None:
    if out is not None:  # a default naming TASK is filled in once the task is known
        p.add_argument("--out", type=out_dir, default=None if "TASK" in out else out, metavar="DIR",
                       help="folder the files are written into (created if missing)"
                       + (f"; default: {out}" if "TASK" in out else ""))
    if json:
        p.add_argument("--json", type=out_file, default=None, metavar="PATH",
                       help="also write the JSON record here")
    if threads is not None:
        p.add_argument("--threads", type=thread_count, default=threads, metavar="N",
                       help="torch intra-op threads (1: robust timings on a shared machine)")
    if plots:
        p.add_argument("--no-plots", action="store_true", help="skip the PNG figures")
    if quiet:
        p.add_argument("--quiet", action="store_true", help="no progress bars or progress lines on stderr")


def _check_devices(args: argparse.Namespace) -> str | None:
    """``--devices``: torch devices this torch can use (torch is imported here, after ``--help``)."""
    if not args.devices:
        return None
    import torch

    for d in args.devices:
        try:
            dev = torch.device(d)
        except RuntimeError:
            return f"argument --devices: {d!r} is not a torch device (cpu, cuda, cuda:1, ...)"
        if dev.type == "cuda" and not torch.cuda.is_available():
            return f"argument --devices: {d} requested, but this torch has no CUDA device"
        if dev.type not in ("cpu", "cuda"):
            return f"argument --devices: expected cpu or cuda devices, got {d}"
    return None


# ----------------------------------------------------------------------------------------------- demo


def demo(p: argparse.ArgumentParser) -> None:
    p.add_argument("--pairs", type=positive_int, default=4096, metavar="N",
                   help="SE(3) pose pairs interpolated in one call")
    p.add_argument("--clouds", type=positive_int, default=256, metavar="N",
                   help="clouds of 200 noisy poses, each averaged on the group")
    p.add_argument("--pendulums", type=positive_int, default=64, metavar="N",
                   help="pendulums swung up at once by the control-limited iLQR")
    p.add_argument("--num-envs", type=positive_int, default=256, metavar="N",
                   help="batched pendulum environments (and evaluation episodes) of the MPC-vs-PPO step")
    p.add_argument("--budget-steps", type=positive_int, default=32768, metavar="N",
                   help="PPO's training budget in environment steps (rounded up to whole PPO rollouts)")
    p.add_argument("--seed", type=seed, default=0, metavar="S", help="random seed")
    _common(p, out="out/demo", json=False, threads=None, plots=True, quiet=True)


# ---------------------------------------------------------------------------------------------- bench


def _task_in(allowed: tuple[str, ...]):
    def parse(s: str) -> str:
        name = task_name(s)
        if name not in allowed:
            choices = ", ".join(allowed)
            raise argparse.ArgumentTypeError(f"task {name} is not measured here; choose from {choices}")
        return name

    parse.__name__ = "task"
    return parse


def _ilqr_problem(s: str) -> str:
    """A ``bench ilqr`` problem: its short name, or the task of the same swing-up (``PendulumSwingUp``)."""
    low = s.lower()
    if low in ILQR_PROBLEMS:
        return low
    name = _task_in(("PendulumSwingUp", "CartPoleSwingUp"))(s)
    return ILQR_PROBLEMS[("PendulumSwingUp", "CartPoleSwingUp").index(name)]


def bench_lie(p: argparse.ArgumentParser) -> None:
    p.add_argument("--batches", type=positive_int, nargs="+", default=[1, 1000, 100000], metavar="N",
                   help="batch sizes")
    p.add_argument("--dtypes", nargs="+", default=list(DTYPES), choices=DTYPES, help="dtypes measured")
    p.add_argument("--groups", nargs="+", default=["so3", "se3"], choices=["so3", "se3"],
                   help="groups: rotations SO(3), rigid motions SE(3)")
    p.add_argument("--ops", nargs="+", default=list(LIE_OPS), choices=LIE_OPS, metavar="OP",
                   help=f"operations, from: {', '.join(LIE_OPS)}")
    p.add_argument("--devices", nargs="+", default=None, metavar="DEVICE",
                   help="torch devices (default: cpu, plus cuda when available)")
    p.add_argument("--repeats", type=positive_int, default=9, metavar="N",
                   help="timed runs per measurement (the median is reported)")
    p.add_argument("--no-compile", action="store_true", help="skip the torch.compile column")
    _common(p, threads=None)
    p.add_argument("--threads", type=thread_count, default=None, metavar="N",
                   help="torch intra-op threads (default: torch's own)")
    p.set_defaults(_check=_check_devices)


def bench_lqr(p: argparse.ArgumentParser) -> None:
    p.add_argument("--batch", type=positive_int, default=256, metavar="N", help="batch size")
    p.add_argument("--horizon", type=positive_int, default=50, metavar="T",
                   help="horizon (number of controls)")
    p.add_argument("--state-dim", type=positive_int, default=8, metavar="N", help="state dimension")
    p.add_argument("--control-dim", type=positive_int, default=4, metavar="N", help="control dimension")
    p.add_argument("--dtype", default="float32", choices=DTYPES, help="dtype of every solver")
    p.add_argument("--repeats", type=positive_int, default=7, metavar="N",
                   help="timed runs per solver (the median is reported)")
    p.add_argument("--seed", type=seed, default=0, metavar="S", help="seed of the random problem")
    p.add_argument("--anchors", nargs="+", default=("pypose", "mpc", "plain"), type=_anchor_list,
                   action=_Joined, metavar="ANCHOR",
                   help="subset of: pypose, mpc (mpc.pytorch), plain (a textbook Riccati recursion in plain "
                        "torch); space- or comma-separated")
    p.add_argument("--mpc-python", type=existing_file, default=None, metavar="PATH",
                   help="python of the mpc.pytorch environment (default: <repo>/.venv-mpc/bin/python; made "
                        "by "
                        "'make bench-env')")
    p.add_argument("--no-fused", action="store_true",
                   help="skip the rows of the torch.compile'd (fused) Riccati step")
    _common(p)


class _Joined(argparse.Action):
    """A list option whose values may also be comma-separated (``a b`` or ``a,b``): the values of every
    token, in order, without repeats (each token's ``type`` returns a tuple)."""

    def __call__(self, parser, namespace, values, option_string=None):
        out: list[str] = []
        for v in values:
            out += [x for x in v if x not in out]
        setattr(namespace, self.dest, tuple(out))


def _anchor_list(s: str) -> tuple[str, ...]:
    names = tuple(a.strip() for a in s.split(",") if a.strip())
    bad = [a for a in names if a not in ("pypose", "mpc", "plain")]
    if not names or bad:
        raise argparse.ArgumentTypeError(f"unknown anchor(s) {' '.join(bad) or '(empty)'}; choose from "
                                         "pypose, mpc, plain")
    return names


def bench_ilqr(p: argparse.ArgumentParser) -> None:
    p.add_argument("--batch", type=positive_int, default=64, metavar="N", help="batch size")
    p.add_argument("--horizon", type=positive_int, default=100, metavar="T", help="horizon in steps")
    p.add_argument("--problems", nargs="+", type=_ilqr_problem, default=list(ILQR_PROBLEMS),
                   metavar="PROBLEM",
                   help="swing-ups to solve: pendulum, cartpole (or their task names)")
    p.add_argument("--max-iter", type=positive_int, default=100, metavar="N",
                   help="iLQR iterations at most, on every side")
    p.add_argument("--repeats", type=positive_int, default=3, metavar="N",
                   help="timed runs of our solver (the median is reported)")
    p.add_argument("--anchor-repeats", type=positive_int, default=1, metavar="N",
                   help="timed runs of each anchor (the median is reported)")
    p.add_argument("--grad-batch", type=positive_int, default=4, metavar="N",
                   help="batch of the gradient check (float64)")
    p.add_argument("--seed", type=seed, default=0, metavar="S", help="seed of the initial states")
    p.add_argument("--no-anchor", action="store_true", help="skip every anchor")
    p.add_argument("--anchor-python", type=existing_file, default=None, metavar="PATH",
                   help="python of the mpc.pytorch environment (default: <repo>/.venv-mpc/bin/python)")
    p.add_argument("--croc-python", type=existing_file, default=None, metavar="PATH",
                   help="python with crocoddyl (default: this interpreter; the bench extra installs it)")
    p.add_argument("--no-croc", action="store_true", help="skip the crocoddyl anchor")
    _common(p)


def bench_envs(p: argparse.ArgumentParser) -> None:
    p.add_argument("--tasks", nargs="+", type=_task_in(ENV_BENCH_TASKS), default=list(ENV_BENCH_TASKS),
                   metavar="TASK", help=f"tasks to step, from: {', '.join(ENV_BENCH_TASKS)}")
    p.add_argument("--num-envs", nargs="+", type=positive_int, default=[1, 16, 64, 256, 1024, 4096],
                   metavar="N", help="numbers of batched environments")
    p.add_argument("--impls", nargs="+", default=list(ENV_BENCH_IMPLS), choices=ENV_BENCH_IMPLS,
                   help="implementations: ours, gymnasium's SyncVectorEnv, EnvPool (C++)")
    p.add_argument("--modes", nargs="+", default=["torch", "numpy"], choices=["torch", "numpy"],
                   help="output modes of our env (torch tensors or numpy arrays)")
    p.add_argument("--devices", nargs="+", default=None, metavar="DEVICE",
                   help="torch devices of our env (default: cpu, plus cuda when available)")
    p.add_argument("--seconds", type=positive_float, default=0.25, help="stepping time per sample")
    p.add_argument("--repeats", type=positive_int, default=5, metavar="N",
                   help="samples per measurement (the median is reported)")
    p.add_argument("--max-sync-envs", type=positive_int, default=1024, metavar="N",
                   help="largest gymnasium SyncVectorEnv measured (a Python loop: 4096 takes long to build)")
    p.add_argument("--no-compile", action="store_true",
                   help="skip the rows of our env with torch.compile and AOTInductor")
    _common(p)
    p.set_defaults(_check=_check_devices)


GYM_BENCH_ENVS = ("InvertedPendulum-v5", "Reacher-v5")


def bench_gym(p: argparse.ArgumentParser) -> None:
    p.add_argument("--envs", nargs="+", choices=GYM_BENCH_ENVS, default=list(GYM_BENCH_ENVS),
                   help="gymnasium MuJoCo envs (their registered models)")
    p.add_argument("--policies", nargs="+", choices=("linear", "ilqr"), default=["linear", "ilqr"],
                   help="linear: one linearization a step (LinearModelMPC); ilqr: ModelMPC")
    p.add_argument("--batch", type=positive_int, nargs="+", default=[1, 64], metavar="N",
                   help="environments stepped in lockstep (one batched policy call each step)")
    p.add_argument("--steps", type=positive_int, default=50, metavar="N", help="steps of each episode timed")
    p.add_argument("--horizon", type=positive_int, default=None, metavar="T",
                   help="planning horizon (default: the model's)")
    p.add_argument("--compile", action="store_true",
                   help="ilqr: compiled solver sweeps (built once: minutes; cached on disk)")
    _common(p)


def bench_sampling(p: argparse.ArgumentParser) -> None:
    p.add_argument("--samples", type=positive_int, default=256, metavar="K", help="samples per iteration")
    p.add_argument("--horizon", type=positive_int, default=40, metavar="T", help="planning horizon")
    p.add_argument("--iterations", type=positive_int, default=1, metavar="N",
                   help="sample-update iterations per MPC step")
    p.add_argument("--batch", type=positive_int, nargs="+", default=[1, 64], metavar="B",
                   help="batch sizes (environments planned at once)")
    p.add_argument("--steps", type=positive_int, default=200, metavar="N", help="closed-loop episode length")
    p.add_argument("--seeds", type=positive_int, default=5, metavar="N",
                   help="repeats of the one-step plan cost")
    p.add_argument("--repeats", type=positive_int, default=7, metavar="N",
                   help="timing samples (the median is reported)")
    p.add_argument("--dtype", choices=DTYPES, default="float32", help="dtype of both planners")
    _common(p)


def _workload_list(s: str) -> tuple[str, ...]:
    names = tuple(w.strip() for w in s.split(",") if w.strip())
    bad = [w for w in names if w not in SOLVER_WORKLOADS]
    if not names or bad:
        raise argparse.ArgumentTypeError(f"expected workloads among {', '.join(SOLVER_WORKLOADS)}; "
                                         f"unknown: {', '.join(bad) or '(empty)'}")
    return names


def _check_device(args: argparse.Namespace) -> str | None:
    """``--device cuda``: this torch must see a CUDA device (torch is imported here, after ``--help``)."""
    if args.device != "cuda":
        return None
    import torch

    if not torch.cuda.is_available():
        return "argument --device: cuda requested, but this torch has no CUDA device"
    return None


def bench_solver(p: argparse.ArgumentParser) -> None:
    p.add_argument("--workloads", nargs="+", type=_workload_list, action=_Joined, default=SOLVER_WORKLOADS,
                   metavar="WORKLOAD",
                   help=f"subset of: {', '.join(SOLVER_WORKLOADS)}; space- or comma-separated (default: all)")
    p.add_argument("--device", choices=("cpu", "cuda"), default="cpu",
                   help="device of our solvers (the anchors run on the CPU)")
    p.add_argument("--dtype", choices=DTYPES, default="float64",
                   help="dtype of our solvers (float64 is the anchors' precision; the MPC head is float32 "
                        "like SB3, the swing-ups' anchor rows float64)")
    p.add_argument("--repeats", type=positive_int, default=None, metavar="N",
                   help="timed calls per figure, the median is reported (default: 5, 1 for the 64 swing-ups)")
    p.add_argument("--quick", action="store_true", help="tiny sizes (a smoke run of seconds)")
    p.add_argument("--eager", action="store_true",
                   help="run iLQR's time sweeps eagerly (default: compiled programs, "
                        "ILQROptions(compile=True); the first run builds them, 1-6 minutes each on a 2-core "
                        "machine, cached on disk)")
    _common(p, threads=None)
    p.add_argument("--threads", type=thread_count, default=1, metavar="N",
                   help="torch intra-op threads, and the anchors' (1: per-core timings)")
    p.set_defaults(_check=_check_device)


def bench_cookbook(p: argparse.ArgumentParser) -> None:
    p.add_argument("--batch", type=positive_int, default=None, metavar="N",
                   help="starts solved in one call after the single problem (default: 64; --quick: 4)")
    p.add_argument("--repeats", type=positive_int, default=None, metavar="N",
                   help="timed calls per figure, the median is reported (default: 5; 1 for the car's and "
                        "the bicopter's batch rows)")
    p.add_argument("--quick", action="store_true",
                   help="one repeat, a batch of 4, the car over 20 steps and the bicopter over 30 "
                        "(a smoke run)")
    _common(p, threads=None)
    p.add_argument("--threads", type=thread_count, default=1, metavar="N",
                   help="torch intra-op threads, and numpy's in the anchor (1: per-core timings)")


def _letter_list(s: str) -> tuple[str, ...]:
    names = tuple(c.strip().upper() for c in s.split(",") if c.strip())
    bad = [c for c in names if len(c) != 1 or not c.isalpha()]
    if not names or bad:
        raise argparse.ArgumentTypeError(f"expected single letters; got {', '.join(bad) or '(empty)'}")
    return names


def _check_bench_primitives(args: argparse.Namespace) -> str | None:
    """``--n-demos`` ≥ 2 (a covariance), ``--T`` ≥ 10; ``--letters``: letters that
    :func:`learning.demos.handwriting` knows (imported here, after ``--help``)."""
    if args.n_demos is not None and args.n_demos < 2:
        return f"argument --n-demos: expected at least 2 (a ProMP needs a covariance), got {args.n_demos}"
    if args.T is not None and args.T < 10:
        return f"argument --T: expected at least 10 samples, got {args.T}"
    if args.letters is None:
        return None
    from learning.demos import LETTERS

    bad = [c for c in args.letters if c not in LETTERS]
    if bad:
        return f"argument --letters: {', '.join(bad)} not among the handwriting letters {' '.join(LETTERS)}"
    return None


def bench_primitives(p: argparse.ArgumentParser) -> None:
    p.add_argument("--letters", nargs="+", type=_letter_list, action=_Joined, default=None, metavar="L",
                   help="handwriting letters, one demo set each; space- or comma-separated (default: "
                        "S C U N; --quick: S C)")
    p.add_argument("--n-demos", type=positive_int, default=None, metavar="N",
                   help="demonstrations per letter (default: 8; --quick: 4)")
    p.add_argument("--T", type=positive_int, default=None, metavar="T",
                   help="samples per demonstration, over 1 s (default: 100; --quick: 40)")
    p.add_argument("--n-generate", type=positive_int, default=None, metavar="N",
                   help="trajectories generated in the timed generation (default: 1000; --quick: 20)")
    p.add_argument("--repeats", type=positive_int, default=None, metavar="N",
                   help="timed calls per figure after a warm-up, the median is reported (default: 3; "
                        "--quick: 1)")
    p.add_argument("--quick", action="store_true", help="small sizes (a smoke run of seconds)")
    _common(p, threads=None)
    p.add_argument("--threads", type=thread_count, default=1, metavar="N",
                   help="torch intra-op threads and numpy's BLAS threads (1: per-core timings)")
    p.set_defaults(_check=_check_bench_primitives)


# --------------------------------------------------------------------------------------- compare, learn


_BUDGET = re.compile(r"^(?:(ppo|sac|td3)=)?(\d+)$")


def budget_item(s: str) -> tuple[str | None, int]:
    """A ``--budget-steps`` item: ``N`` (every algorithm) or ``ALGO=N`` -> ``(ALGO or None, N)``."""
    m = _BUDGET.match(s.strip().lower())
    if not m or int(m.group(2)) < 1:
        raise argparse.ArgumentTypeError("expected N or ALGO=N with ALGO in ppo, sac, td3 and N a positive "
                                         "integer, "
                                         f"got {s!r}")
    return m.group(1), int(m.group(2))


def _check_tensorboard(args: argparse.Namespace) -> str | None:
    if args.tensorboard and importlib.util.find_spec("tensorboard") is None:
        return ("argument --tensorboard: the 'tensorboard' package is not installed (pip install "
                "tensorboard, "
                "or leave --tensorboard out)")
    return None


def _check_compare(args: argparse.Namespace) -> str | None:
    for algo, n in args.budget_steps or []:
        if algo is not None and algo not in args.algos:
            algos = " ".join(args.algos)
            return f"argument --budget-steps: {algo}={n} names an algorithm not in --algos ({algos})"
    if args.load is not None and args.tensorboard:
        return "argument --tensorboard: nothing is trained with --load"
    algos = [a for a, _ in args.budget_steps or []]
    if len(algos) != len(set(algos)):
        return "argument --budget-steps: one budget per algorithm (an algorithm, or N for all, given twice)"
    if len(args.seeds) != len(set(args.seeds)):
        return f"argument --seeds: a seed given twice ({' '.join(map(str, args.seeds))})"
    if args.json and args.out and Path(args.json).absolute() == Path(args.out).absolute():
        return "argument --json: the JSON file cannot be the --out folder"
    return _check_tensorboard(args)


def compare(p: argparse.ArgumentParser) -> None:
    p.add_argument("task", metavar="TASK", type=env_name,
                   help="task: PendulumSwingUp, CartPoleSwingUp, ... (a unique prefix in any case, or "
                        "liecontrol/<task>-v0), or a registered gymnasium id with a model for its MPC "
                        "(Pendulum-v1, MountainCarContinuous-v0, InvertedPendulum-v5, "
                        "InvertedDoublePendulum-v5, Reacher-v5; learning.env_models): the agents then train "
                        "on gymnasium.make(ENV) with the rl-baselines3-zoo's hyperparameters")
    p.add_argument("--algos", nargs="+", default=["ppo", "sac"], choices=["ppo", "sac", "td3"],
                   help="RL algorithms (stable-baselines3)")
    p.add_argument("--budget-steps", nargs="+", type=budget_item, default=None, metavar="[ALGO=]N",
                   help="training environment steps per seed: N for every algorithm, or ALGO=N (default: per "
                        "task and algorithm, learning.baselines.DEFAULT_BUDGETS; gymnasium ids: "
                        "FOREIGN_BUDGETS)")
    p.add_argument("--seeds", nargs="+", type=seed, default=[0, 1, 2], metavar="S",
                   help="training seeds (one agent per algorithm and seed)")
    p.add_argument("--eval-episodes", type=positive_int, default=None, metavar="N",
                   help="held-out evaluation episodes (env seeds 10^6 + j), also those of the learning "
                        "curves "
                        "(default: 32 for PendulumSwingUp and CartPoleSwingUp, else 16)")
    p.add_argument("--eval-every", type=positive_int, default=None, metavar="N",
                   help="environment steps between two learning-curve evaluations; the curve is also "
                        "evaluated "
                        "before training and after its last step (default: a twentieth of the budget)")
    p.add_argument("--eval-envs", type=positive_int, default=None, metavar="N",
                   help="batched environments of the evaluation (default: all evaluation episodes at once)")
    p.add_argument("--train-envs", type=positive_int, default=None, metavar="N",
                   help="batched training environments (default: per task and algorithm)")
    p.add_argument("--mpc-horizon", type=positive_int, default=None, metavar="T",
                   help="horizon of the MPC expert (default: per task)")
    p.add_argument("--no-mpc", action="store_true", help="skip the MPC expert")
    p.add_argument("--load", type=existing_dir, default=None, metavar="DIR",
                   help="instead of training, rebuild each agent from the policy.pt weights a previous run "
                        "wrote "
                        "(DIR is that run's --out folder, holding agents/ALGO/seedS/policy.pt); only the "
                        "weights-only .pt files are read, never SB3's .zip; the training options "
                        "(--budget-steps, --train-envs, --eval-every, --jobs) then have no effect")
    p.add_argument("--jobs", type=positive_int, default=None, metavar="N",
                   help="agents trained at once in worker processes (default: one per CPU core; 1: in this "
                        "process); the results do not depend on it")
    p.add_argument("--tensorboard", action="store_true",
                   help="log training to TensorBoard in OUT/agents/ALGO/seedS/tb (needs 'pip install "
                        "tensorboard')")
    _common(p, out="out/compare/TASK", quiet=True)
    p.set_defaults(_check=_check_compare)


#: the tasks whose MPC cost is a quadratic one on the flat state, which the learning commands learn
#: (tests/test_cli_options.py checks this list against each task's ``mpc_cost``)
LEARN_TASKS = ("PendulumSwingUp", "CartPoleSwingUp", "CarParking", "BicopterHover")


#: the tasks of ``learn mpc-ppo``: those, and the quadrotors (their head is the error-state MPC on the
#: manifold, :mod:`learning.mpc_head_quadrotor`)
MPC_PPO_TASKS = (*LEARN_TASKS, "QuadrotorCircle", "QuadrotorFigureEight")


def learn_task(value: str, allowed: tuple[str, ...] = LEARN_TASKS) -> str:
    """:func:`task_name`, restricted to ``allowed`` (default :data:`LEARN_TASKS`)."""
    name = task_name(value)
    if name not in allowed:
        raise argparse.ArgumentTypeError(
            f"{name} cannot be learnt by this command (its MPC is not a quadratic cost on the flat state); "
            f"choose from {', '.join(allowed)}")
    return name


def mpc_ppo_task(value: str) -> str:
    """:func:`learn_task` for ``learn mpc-ppo`` (:data:`MPC_PPO_TASKS`)."""
    return learn_task(value, MPC_PPO_TASKS)


_LEARN_TASK_HELP = f"task: {', '.join(LEARN_TASKS)} (a unique prefix in any case, or liecontrol/<task>-v0)"


def learn_mpc_ppo(p: argparse.ArgumentParser) -> None:
    p.add_argument("task", metavar="TASK", type=mpc_ppo_task,
                   help=_LEARN_TASK_HELP.replace(", ".join(LEARN_TASKS), ", ".join(MPC_PPO_TASKS)))
    p.add_argument("--budget-steps", type=positive_int, default=20_000, metavar="N",
                   help="training environment steps per seed, of each policy")
    p.add_argument("--seeds", nargs="+", type=seed, default=[0], metavar="S",
                   help="training seeds")
    p.add_argument("--mpc-horizon", type=positive_int, default=None, metavar="T",
                   help="horizon of the MPC head (default: the task's expert's)")
    p.add_argument("--max-iter", type=positive_int, default=5, metavar="N",
                   help="iLQR iterations per call of the MPC head")
    p.add_argument("--eval-episodes", type=positive_int, default=16, metavar="N",
                   help="held-out evaluation episodes")
    p.add_argument("--warm-start", action="store_true",
                   help="warm-start each MPC solve from the previous plan, carried in the observation")
    p.add_argument("--per-step", action="store_true",
                   help="a per-step cost map: the cost network outputs weights and targets for every step")
    p.add_argument("--no-equal-time", dest="equal_time", action="store_false",
                   help="skip plain PPO trained for the MPC head's training time")
    p.add_argument("--robustness", action="store_true",
                   help="evaluate the trained policies unchanged on the task with +-30%% model changes")
    p.add_argument("--tensorboard", action="store_true",
                   help="log training to TensorBoard in OUT/agents/RUN/seedS/tb (needs 'pip install "
                        "tensorboard')")
    _common(p, out="out/learn/TASK", quiet=True)
    p.set_defaults(_check=_check_tensorboard)


def learn_bc(p: argparse.ArgumentParser) -> None:
    p.add_argument("task", metavar="TASK", type=learn_task, help=_LEARN_TASK_HELP)
    p.add_argument("--demos", nargs="+", type=positive_int, default=[1, 2, 5, 10], metavar="N",
                   help="numbers of expert episodes to learn from (one learning run each)")
    p.add_argument("--heldout-episodes", type=positive_int, default=5, metavar="N",
                   help="expert episodes held out to measure the action error")
    p.add_argument("--eval-episodes", type=positive_int, default=16, metavar="N",
                   help="held-out closed-loop evaluation episodes")
    p.add_argument("--mlp-epochs", type=positive_int, default=200, metavar="N",
                   help="training epochs of the MLP")
    p.add_argument("--mpc-steps", type=positive_int, default=60, metavar="N",
                   help="gradient steps on the MPC layer's cost weights")
    _common(p, out="out/learn/TASK", quiet=True)


def _check_at_least(**least: int):
    """A ``_check``: each named option (``n_demos=2``: ``--n-demos``) at least its bound."""
    def check(args: argparse.Namespace) -> str | None:
        for dest, lo in least.items():
            v = getattr(args, dest)
            if v is not None and v < lo:
                return f"argument --{dest.replace('_', '-')}: expected at least {lo}, got {v}"
        return None
    return check


#: ``learn costs``: beyond these the demos' time warp loses its resolution (rate ratios e^±50 round steps to
#: zero, :func:`learning.demos.time_warp`) and the noise's squares leave float64 (std 1e160: variance inf)
LEARN_WARP_MAX = 50.0
LEARN_NOISE_MAX = 1e3


def learn_costs(p: argparse.ArgumentParser) -> None:
    p.add_argument("--n-demos", type=positive_int, default=8, metavar="N",
                   help="expert demonstrations (random starts), at least 2")
    p.add_argument("--steps", type=positive_int, default=80, metavar="N",
                   help="L-BFGS iterations of fit_cost")
    p.add_argument("--warp", type=float_at_most(LEARN_WARP_MAX), default=0.1,
                   help="time-warp strength of the minimal-intervention demos (local speed factors about "
                        f"e^±warp), 0 ... {LEARN_WARP_MAX}")
    p.add_argument("--noise", type=float_at_most(LEARN_NOISE_MAX), default=0.02,
                   help="spatial noise (std of the position offsets) of the "
                        f"minimal-intervention demos, 0 ... {LEARN_NOISE_MAX:g}")
    p.add_argument("--seed", type=seed, default=0, metavar="S", help="seed of the starts and the variability")
    _common(p, out="out/learn/costs", quiet=True, plots=True)
    p.set_defaults(_check=_check_at_least(n_demos=2))


def _check_learn_primitives(args: argparse.Namespace) -> str | None:
    if args.n_demos < 2:
        return f"argument --n-demos: expected at least 2 (a ProMP needs a covariance), got {args.n_demos}"
    if args.T < 10:
        return f"argument --T: expected at least 10 samples, got {args.T}"
    from learning.demos import LETTERS

    bad = [c for c in args.letters if c not in LETTERS]
    if bad:
        return f"argument --letters: {', '.join(bad)} not among the handwriting letters {' '.join(LETTERS)}"
    return None


def learn_primitives(p: argparse.ArgumentParser) -> None:
    p.add_argument("--letters", nargs="+", type=_letter_list, action=_Joined, default=("S", "C", "U", "N"),
                   metavar="L", help="handwriting letters, one demo set each; space- or comma-separated")
    p.add_argument("--n-demos", type=positive_int, default=8, metavar="N", help="demonstrations per letter")
    p.add_argument("--T", type=positive_int, default=100, metavar="T", help="samples per demonstration (1 s)")
    p.add_argument("--seed", type=seed, default=11, metavar="S", help="seed of the demos and the samples")
    _common(p, out="out/learn/primitives", quiet=True, plots=True)
    p.set_defaults(_check=_check_learn_primitives)


#: what ``learn dynamics`` compares the learned model with (:func:`learning.imitation.learn_dynamics`)
DYNAMICS_BASELINES = ("sysid", "mlp", "lstm")


def learn_dynamics(p: argparse.ArgumentParser) -> None:
    p.add_argument("--system", choices=("pendulum", "cartpole"), default="pendulum",
                   help="the system whose parameters are learned (Amos et al. 2018's two); with the other "
                        "options left as they are a run took about 1 min (pendulum) and 3 min (cart-pole) on "
                        "a 2-core CPU, 1 thread")
    p.add_argument("--n-train", type=positive_int, default=10, metavar="N", help="training demonstrations")
    p.add_argument("--seeds", type=positive_int, default=4, metavar="K",
                   help="number of seeds: runs with seeds 0 ... K-1 (a count here, not a list)")
    p.add_argument("--baselines", nargs="*", choices=DYNAMICS_BASELINES, default=list(DYNAMICS_BASELINES),
                   help="sysid: system identification on the transitions; mlp, lstm: behaviour cloning (the "
                        "option alone: none)")
    p.add_argument("--steps", type=positive_int, default=100, metavar="N",
                   help="budget of loss evaluations (one learner solve each; L-BFGS may finish its last line "
                        "search past it: the JSON's 'evaluations' is the count)")
    p.add_argument("--n-test", type=positive_int, default=50, metavar="N",
                   help="held-out starts of the imitation MSE")
    p.add_argument("--unconverged", choices=("include", "exclude"), default="include",
                   help="a non-converged training solve: kept with the implicit gradient at its last "
                        "iterate, or left out of that evaluation's loss (counted either way; "
                        "learning.imitation says why 'include' is the default)")
    _common(p, out="out/learn/dynamics", quiet=True, plots=True)


def learn_manifold(p: argparse.ArgumentParser) -> None:
    p.add_argument("--n-demos", type=positive_int, default=12, metavar="N",
                   help="orientation demos and stiffness demos, at least 2")
    p.add_argument("--T", type=positive_int, default=40, metavar="T",
                   help="steps per demonstration, at least 2")
    p.add_argument("--horizon", type=positive_int, default=8, metavar="N", help="horizon of the tracking MPC")
    p.add_argument("--seed", type=seed, default=3, metavar="S", help="seed of the demos")
    _common(p, out="out/learn/manifold", quiet=True, plots=True)
    p.set_defaults(_check=_check_at_least(n_demos=2, T=2))


# ------------------------------------------------------------------------------------------ reproduce


def reproduce_me2(p: argparse.ArgumentParser) -> None:
    p.add_argument("--dt", type=positive_float, default=1e-3, help="time step [s]")
    p.add_argument("--horizon", type=positive_int, default=300, metavar="H",
                   help="prediction horizon in steps")
    p.add_argument("--fig4-horizons", type=positive_int, nargs="+", default=[10, 25, 50, 100, 200, 300, 500],
                   metavar="H", help="horizon lengths [steps] of the error-vs-horizon figure (the paper's "
                                     "Fig. 4)")
    p.add_argument("--velocity-scale", type=positive_float, default=0.25,
                   help="fraction of the Panda's Cartesian speed limits")
    p.add_argument("--acceleration-scale", type=positive_float, default=0.1,
                   help="fraction of the Panda's Cartesian acceleration limits")
    p.add_argument("--timing-batch", type=positive_int, default=1000, metavar="N",
                   help="at least this many horizons in the timed batch")
    p.add_argument("--timing-horizon", type=positive_int, default=None, metavar="H",
                   help="steps per timed horizon (default: --horizon)")
    p.add_argument("--repeats", type=positive_int, default=7, metavar="N", help="timed repetitions")
    p.add_argument("--timing-dtype", choices=DTYPES, default="float64",
                   help="dtype of the timed batch (the errors are always computed in float64)")
    p.add_argument("--no-cut-locus", action="store_true",
                   help="skip the runs from the tool-down start pose (rotation angle pi)")
    p.add_argument("--no-wobble", action="store_true",
                   help="skip the variants with non-commuting twists (the paper's path plus a sinusoidal "
                        "twist)")
    _common(p, out="out/me2", threads=None, plots=True)


def reproduce_quadrotor(p: argparse.ArgumentParser) -> None:
    p.add_argument("--horizons", type=positive_int, nargs="+", default=[8, 16, 32], metavar="H",
                   help="MPC horizons in steps; the first is the headline and the anchor's (8: the paper's)")
    p.add_argument("--scenarios", nargs="+", choices=QUADROTOR_SCENARIOS, default=list(QUADROTOR_SCENARIOS),
                   help="circle: radius 1.3 m up to 5 m/s; circle_mass: the same 5 %% heavier than modelled; "
                        "flip: three vertical flips; loop8: a loop at 8 m/s with rotor drag")
    p.add_argument("--batch", type=positive_int, default=1024, metavar="N",
                   help="quadrotors in the batched step")
    p.add_argument("--no-anchor", action="store_true", help="skip the CasADi + IPOPT anchor")
    p.add_argument("--quick", action="store_true", help="short references (a smoke run)")
    _common(p, out="out/quadrotor", plots=True)


def reproduce_ugv(p: argparse.ArgumentParser) -> None:
    p.add_argument("--horizon", type=int_at_most(1000), default=UGV_PAPER_HORIZON, metavar="H",
                   help=f"MPC horizon in steps, at most 1000 (default: {UGV_PAPER_HORIZON}, the paper's)")
    p.add_argument("--steps", type=positive_int, default=None, metavar="N",
                   help="closed-loop steps (default: the whole path)")
    p.add_argument("--quick", action="store_true", help=f"a short run ({UGV_QUICK_STEPS} steps, batch <= 16)")
    p.add_argument("--seed", type=seed, default=0, metavar="S", help="seed of the map points")
    p.add_argument("--dtype", choices=DTYPES, default="float64", help="dtype of the MPC")
    p.add_argument("--batch", type=nonnegative_int, default=256, metavar="N",
                   help="vehicles in the batched-step timing (0 skips it)")
    p.add_argument("--q-pos", type=positive_float, default=UGV_WEIGHTS["q_pos"], help="position weight")
    p.add_argument("--q-yaw", type=nonnegative_float, default=UGV_WEIGHTS["q_yaw"], help="yaw weight")
    p.add_argument("--r-v", type=positive_float, default=UGV_WEIGHTS["r_v"], help="speed input weight")
    p.add_argument("--r-omega", type=positive_float, default=UGV_WEIGHTS["r_omega"],
                   help="yaw-rate input weight")
    p.add_argument("--no-offset", action="store_true", help="skip the run from an offset start")
    _common(p, out="out/ugv", plots=True)


def reproduce_pose_mpc(p: argparse.ArgumentParser) -> None:
    p.add_argument("--horizon", type=positive_int, default=30, metavar="H", help="MPC horizon in steps")
    p.add_argument("--dt", type=positive_float, default=0.01, help="control period [s]")
    p.add_argument("--velocity-scale", type=positive_float, default=0.25,
                   help="fraction of the Panda's Cartesian speed limits (of the references)")
    p.add_argument("--batch", type=positive_int, default=256, metavar="N", help="arms in the batched timing")
    p.add_argument("--ik-goals", type=positive_int, default=1000, metavar="N",
                   help="goals of the IK benchmark")
    p.add_argument("--quick", action="store_true", help="one path per start, 100 IK goals (a smoke run)")
    _common(p, out="out/pose_mpc", plots=True)


# ------------------------------------------------------------------------------------------- cookbook


def _examples_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--examples", type=existing_dir, default=None, metavar="DIR",
                   help="folder of the example files (default: examples/cookbook of the source tree)")


def _check_cookbook_list(args: argparse.Namespace) -> str | None:
    from liecontrol._cookbook_index import discover

    try:
        discover(args.examples)
    except (FileNotFoundError, ValueError) as e:
        return str(e)
    return None


def cookbook_list(p: argparse.ArgumentParser) -> None:
    _examples_option(p)
    p.set_defaults(_check=_check_cookbook_list)


def _check_cookbook_run(args: argparse.Namespace) -> str | None:
    from liecontrol._cookbook_index import discover

    if args.all == bool(args.names):
        return "name the examples to run, or pass --all (not both)"
    try:
        known = {e.name for e in discover(args.examples)}
    except (FileNotFoundError, ValueError) as e:
        return str(e)
    unknown = [n for n in args.names if n not in known]
    if unknown:
        return (f"argument NAME: no cookbook example {', '.join(unknown)} (see `liecontrol cookbook list`; "
                f"{len(known)} examples)")
    return None


def cookbook_run(p: argparse.ArgumentParser) -> None:
    p.add_argument("names", nargs="*", metavar="NAME", help="examples to run (names from `cookbook list`)")
    p.add_argument("--all", action="store_true", help="run every example")
    _examples_option(p)
    _common(p, out="out/cookbook", plots=True, quiet=True)
    p.set_defaults(_check=_check_cookbook_run)


# --------------------------------------------------------------------------------------------- table

#: (command path, options builder, module with ``run(args)``, one-line help).  A path of two words is a
#: subcommand of a group (:data:`GROUPS`); add a row to add a command.
COMMANDS: tuple[tuple[tuple[str, ...], object, str, str], ...] = (
    (("demo",), demo, "liecontrol.demo",
     "a tour in about 3 minutes: batched SE(3) interpolation and averaging, exactness at the edges, a "
     "differentiable control-limited iLQR swing-up, and the MPC expert vs PPO trained on the spot"),
    (("compare",), compare, "liecontrol.compare",
     "the MPC expert (no training) vs PPO and SAC trained within a step budget, on the same held-out "
     "episodes"),
    (("learn", "mpc-ppo"), learn_mpc_ppo, "liecontrol.learn",
     "PPO whose policy is the MPC with a learned cost vs plain PPO, at equal steps and at equal training "
     "time"),
    (("learn", "bc"), learn_bc, "liecontrol.learn",
     "behaviour cloning from the MPC expert: an MLP policy and the MPC's cost weights vs number of demos"),
    (("learn", "costs"), learn_costs, "liecontrol.learn_demos",
     "inverse optimal control: LQT weights and a via point recovered from expert demos; minimal-intervention "
     "gains from their variability"),
    (("learn", "primitives"), learn_primitives, "liecontrol.learn_demos",
     "movement primitives as LQT on handwriting letters: DMP reproduction and push recovery, ProMP "
     "distribution, via-point conditioning and samples"),
    (("learn", "dynamics"), learn_dynamics, "liecontrol.learn_demos",
     "pendulum or cart-pole parameters learned by imitation through the differentiable MPC, vs system "
     "identification and MLP/LSTM behaviour cloning (Amos et al. 2018)"),
    (("learn", "manifold"), learn_manifold, "liecontrol.learn_demos",
     "orientation and stiffness demos on SO(3), S3 and SPD: per-step Gaussians, their mean tracked by the "
     "on-manifold MPC, a stiffness target"),
    (("bench", "lie"), bench_lie, "liecontrol.bench.lie",
     "Lie-group operations vs pypose and roma: speed and round-trip error"),
    (("bench", "lqr"), bench_lqr, "liecontrol.bench.lqr", "batched LQR vs pypose and mpc.pytorch"),
    (("bench", "ilqr"), bench_ilqr, "liecontrol.bench.ilqr",
     "iLQR swing-ups vs mpc.pytorch box-DDP, pypose MPC and crocoddyl"),
    (("bench", "envs"), bench_envs, "liecontrol.bench.envs",
     "batched environment steps per second vs gymnasium SyncVectorEnv and EnvPool"),
    (("bench", "gym"), bench_gym, "liecontrol.bench.gym_mpc",
     "the MPC step on gymnasium's MuJoCo envs (linear MPC, iLQR on the MuJoCo model) against issue 27's "
     "targets"),
    (("bench", "sampling"), bench_sampling, "liecontrol.bench.sampling",
     "MPPI and predictive sampling (batched) vs pytorch_mppi on a pendulum swing-up: plan cost, time and "
     "return"),
    (("bench", "solver"), bench_solver, "liecontrol.bench.solver",
     "the solver workloads (MPC steps, iLQR swing-ups, the MPC policy head, the cookbook manipulator, car "
     "and bicopter) vs crocoddyl, CasADi, a numpy iLQR and SB3's MLP policy"),
    (("cookbook", "list"), cookbook_list, "liecontrol.cookbook",
     "every example of the seed-004 cookbook (robot manipulation) with its seed section"),
    (("cookbook", "run"), cookbook_run, "liecontrol.cookbook",
     "run cookbook examples (NAME... or --all): figures and a JSON of their checked outcomes"),
    (("bench", "cookbook"), bench_cookbook, "liecontrol.bench.cookbook",
     "the cookbook manipulator, car and bicopter (seed 004 §9.1, §9.15, §9.16) vs the cookbook's own numpy "
     "algorithm, one problem and a batch"),
    (("bench", "primitives"), bench_primitives, "liecontrol.bench.primitives",
     "movement primitives as LQT (DMP, ProMP) vs DFKI's movement_primitives on handwriting demos: "
     "reproduction, push recovery, via points, fit and generation time"),
    (("reproduce", "me2"), reproduce_me2, "liecontrol.reproduce.me2",
     f"pose prediction over a 300 ms horizon by the second-order Magnus (ME2) linearization (Table 1, "
     f"Figs. 2-4) of {ME2_PAPER}"),
    (("reproduce", "quadrotor"), reproduce_quadrotor, "liecontrol.reproduce.quadrotor",
     f"quadrotor tracking (circle, flips, 8 m/s loop) by the error-state MPC of {MANIFOLD_PAPER} (Sec. "
     "VII-A), "
     "vs CasADi + IPOPT"),
    (("reproduce", "ugv"), reproduce_ugv, "liecontrol.reproduce.ugv",
     f"a ground vehicle tracking a path on a hilly road by the error-state MPC of {MANIFOLD_PAPER} (Sec. "
     "VII-B)"),
    (("reproduce", "pose-mpc"), reproduce_pose_mpc, "liecontrol.reproduce.pose_mpc",
     "a Franka Panda arm tracking poses: the linear pose MPC of the ME2 paper (Eq. 16) vs the SE(3) "
     "error-state MPC of the manifold-MPC paper"),
)

GROUPS = {
    "cookbook": "the seed-004 cookbook (Calinon, A Math Cookbook for Robot Manipulation) as examples on the "
                "library, each with a checked outcome",
    "bench": "benchmarks against other libraries (the anchors), measured in the same run",
    "learn": "learning with the differentiable MPC",
    "reproduce": f"the experiments of the papers this project implements: {ME2_PAPER}; {MANIFOLD_PAPER}",
}
