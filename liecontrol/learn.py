"""``liecontrol learn``: learning *with* the differentiable MPC (issue 12 §5-§6), measured and reported.

``liecontrol learn mpc-ppo TASK``
    PPO with the MPC-headed policy (:class:`learning.mpc_policy.MPCActorCriticPolicy`: observation → cost
    network → iLQR MPC → action; untrained it *is* the task's MPC) against plain PPO (``MlpPolicy``, the
    task's tuned settings) at **equal environment steps** and at **equal training wall time** (plain PPO
    trained until its own training clock reaches the MPC-headed run's), per training seed, all evaluated on
    the same held-out episodes (:func:`learning.evaluate`); with the per-step compute of each policy at
    batch 1 and their ratio.  Writes ``report.md``, ``curves.png`` and ``learn.json`` into ``--out`` (default
    ``out/learn/TASK``); with ``--tensorboard`` also each run's agent and TensorBoard logs under ``agents/``.
    ``--warm-start`` carries each solve's plan in the observation (:mod:`learning.mpc_warmstart`),
    ``--per-step`` makes the cost network a per-step cost map, ``--no-equal-time`` skips the equal-time run,
    and ``--robustness`` evaluates each seed's trained head and equal-steps PPO (and once the nominal task's
    MPC expert) unchanged on the task's ±30 % model changes (:func:`learning.robustness.robustness_study`,
    the same held-out episodes).  On a quadrotor task the head is the error-state MPC on the manifold
    (:mod:`learning.mpc_head_quadrotor`).

``liecontrol learn bc TASK``
    Behaviour cloning from the task's MPC expert (:func:`learning.bc.bc_study`): an MLP policy and,
    separately, the MPC layer's cost weights learned from 1, 2, 5, … expert episodes; held-out action
    error and closed-loop success against the number of demonstrations.  Writes ``bc.md``, ``bc.png`` and
    ``bc.json`` into ``--out`` (default ``out/learn/TASK``).

JSON of ``mpc-ppo``: ``{"env", "steps", "seeds", "eval_seeds", "mpc_ppo": [per seed],
"ppo_equal_steps": [...], "ppo_equal_time": [...], "robustness": [records of robustness_study plus "seed"],
"step_ms_batch1": {"mpc_ppo", "ppo", "ratio"}}``,
each per-seed record ``{"seed", "num_timesteps", "train_time_s", "return_mean", "return_std",
"success_rate", "curve"}``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from liecontrol._args import task_name as resolve_env
from liecontrol._progress import TrainingProgress, write
from liecontrol.report import markdown_cell, print_table, restores_threads

__all__ = ["mpc_ppo", "bc", "run"]


def _record(res, ev) -> dict:
    return {"seed": res.seed, "num_timesteps": res.num_timesteps, "train_time_s": res.train_time_s,
            "return_mean": float(np.mean(ev.returns)), "return_std": float(np.std(ev.returns)),
            "success_rate": float(np.mean(ev.success)), "curve": res.curve()}


#: the MPC head's PPO learning rate at most: it refines a cost that is already good (PendulumSwingUp, seed
#: 0, 16 held-out episodes: at 1e-3, PPO's tuned rate, the head went -124 → -175 in 20 k steps; at 3e-4
#: -124 → -123.5)
MPC_HEAD_MAX_LR = 3e-4


def _mpc_ppo_params(task) -> dict:
    """Plain PPO's settings for the task, less what the MPC-headed policy does not support (gSDE: its
    action noise is SB3's state-independent diagonal Gaussian), with the learning rate capped at
    :data:`MPC_HEAD_MAX_LR`."""
    from learning.baselines import hyperparams

    kw = hyperparams("ppo", task)
    kw.pop("use_sde", None)
    kw.pop("sde_sample_freq", None)
    lr = kw.get("learning_rate", MPC_HEAD_MAX_LR)
    if isinstance(lr, (int, float)):
        kw["learning_rate"] = min(float(lr), MPC_HEAD_MAX_LR)
    return kw


def _evaluate(model, task, ev_seeds, quiet: bool, timing: bool):
    from learning.evaluate import evaluate

    return evaluate(model, task, seeds=ev_seeds, num_envs=len(ev_seeds), dtype=torch.float32,
                    progress=not quiet, timing_batch1=timing)


def _robustness(models: dict, task, ev_seeds, expert: bool) -> list[dict]:
    """Records of :func:`learning.robustness.robustness_study` for ``models`` (and the nominal task's MPC
    expert when ``expert``) on the task's default ±30 % grid, the held-out episodes of the curves."""
    from learning.robustness import robustness_study

    pols = dict(models) | ({"mpc_expert": "mpc"} if expert else {})
    return robustness_study(pols, task, seeds=ev_seeds, dtype=torch.float32)


@restores_threads
def mpc_ppo(env: str, *, steps: int = 20_000, seeds=(0,), eval_episodes: int = 16, horizon: int | None = None,
            max_iter: int = 5, out: str | Path | None = None, threads: int = 1, log=None,
            tensorboard: bool = False, quiet: bool = True, warm_start: bool = False, per_step: bool = False,
            equal_time: bool = True, robustness: bool = False) -> dict:
    """Run the comparison of the module docstring and write its files into ``out`` (default
    ``out/learn/TASK``); returns the JSON record (plus ``"_files"``).  With ``tensorboard`` every run is
    saved and logs to TensorBoard in ``out/agents/RUN/seedS/`` (RUN: ``mpc_ppo``, ``ppo_equal_steps``,
    ``ppo_equal_time``).  Progress bars on stderr unless ``quiet``; ``log(line)`` gets the progress lines.
    ``warm_start``/``per_step``: of the MPC head (:class:`~learning.mpc_policy.MPCActorCriticPolicy`);
    ``equal_time``: also train plain PPO for the head's training time; ``robustness``: evaluate each seed's
    trained head and equal-steps PPO (and once the nominal MPC expert) unchanged on the task's ±30 %
    perturbations (:func:`learning.robustness.robustness_study`), into ``rec["robustness"]``."""
    from learning import baselines as bl
    from learning.envs.single import make_task
    from learning.mpc_policy import MPCActorCriticPolicy

    torch.set_num_threads(threads)
    task = make_task(resolve_env(env))
    ev_seeds = bl.eval_seeds(eval_episodes)
    say = log or (lambda s: None)
    pk = {"task": task.name, "max_iter": int(max_iter)}
    if horizon is not None:
        pk["horizon"] = int(horizon)
    pk |= {k: True for k, v in (("warm_start", warm_start), ("per_step", per_step)) if v}
    every = max(1, steps // 10)
    rec: dict = {"env": task.name, "steps": int(steps), "seeds": [int(s) for s in seeds],
                 "eval_seeds": ev_seeds, "mpc_policy_kwargs": dict(pk),
                 "mpc_ppo_params": _mpc_ppo_params(task), "mpc_ppo": [], "ppo_equal_steps": [],
                 "ppo_equal_time": [], "robustness": []}
    root = Path(out) if out is not None else Path("out/learn") / task.name
    last = {}
    for i, s in enumerate(seeds):
        runs = {"mpc_ppo": steps, "ppo_equal_steps": steps} | ({"ppo_equal_time": None} if equal_time else {})
        progress = TrainingProgress(runs, quiet=quiet, label=lambda k, s=s: f"{task.name} {k} seed {s}",
                                    log=log)

        def kw(run: str, progress=progress, s=s) -> dict:  # logging; TensorBoard beside the saved agent
            d = dict(log=lambda line: progress.line(run, line), tensorboard=tensorboard)
            return d | ({"out_dir": root / "agents" / run / f"seed{s}"} if tensorboard else {})

        say(f"{task.name} seed {s}: PPO with the MPC-headed policy, {steps} steps")
        r = bl.train("ppo", task, steps, seed=s, eval_every=every, eval_episodes=eval_episodes,
                     params=dict(rec["mpc_ppo_params"]), policy=MPCActorCriticPolicy, policy_kwargs=pk,
                     **kw("mpc_ppo"))
        last["mpc_ppo"] = ev = _evaluate(r.model, task, ev_seeds, quiet, True)
        rec["mpc_ppo"].append(_record(r, ev))
        say(f"{task.name} seed {s}: plain PPO, {steps} steps")
        p = bl.train("ppo", task, steps, seed=s, eval_every=every, eval_episodes=eval_episodes,
                     **kw("ppo_equal_steps"))
        last["ppo"] = ev = _evaluate(p.model, task, ev_seeds, quiet, True)
        rec["ppo_equal_steps"].append(_record(p, ev))
        if equal_time:
            budget_s = r.train_time_s
            say(f"{task.name} seed {s}: plain PPO for the MPC-headed run's training time, {budget_s:.0f} s")
            q = bl.train("ppo", task, 10**9, seed=s, eval_every=max(every, 4096), eval_episodes=eval_episodes,
                         max_train_s=budget_s, **kw("ppo_equal_time"))
            rec["ppo_equal_time"].append(_record(q, _evaluate(q.model, task, ev_seeds, quiet, False)))
        progress.close()
        if robustness:
            say(f"{task.name} seed {s}: robustness to ±30 % model changes")
            for x in _robustness({"mpc_ppo": r.model, "ppo_equal_steps": p.model}, task, ev_seeds,
                                 expert=i == 0):
                rec["robustness"].append(x | {"seed": int(s)})
    a = float(np.median(last["mpc_ppo"].step_ms_batch1))
    b = float(np.median(last["ppo"].step_ms_batch1))
    rec["step_ms_batch1"] = {"mpc_ppo": a, "ppo": b, "ratio": a / b}
    root.mkdir(parents=True, exist_ok=True)
    files = {"json": str(root / "learn.json"), "report": str(root / "report.md"),
             "curves": str(root / "curves.png")}
    Path(files["json"]).write_text(json.dumps(rec, indent=1, allow_nan=False) + "\n")
    _plot(rec, files["curves"])
    Path(files["report"]).write_text(_report(rec))
    rec["_files"] = files
    return rec


def robustness_rows(rec: dict) -> list[dict]:
    """One row per (policy, perturbation): return and success over the seeds (mean, min, max of the
    per-seed means)."""
    groups: dict[tuple, list[dict]] = {}
    for x in rec.get("robustness", []):
        groups.setdefault((x["policy"], x["perturbation"]), []).append(x)
    rows = []
    for (pol, label), xs in groups.items():
        ret = [x["return_mean"] for x in xs]
        succ = [x["success_rate"] for x in xs]
        rows.append({"policy": pol, "perturbation": label, "seeds": len(xs),
                     "return_mean": float(np.mean(ret)),
                     "return_min": float(np.min(ret)), "return_max": float(np.max(ret)),
                     "success": float(np.mean(succ))})
    return rows


def _rows(rec: dict) -> list[dict]:
    rows = []
    for key, name in (("mpc_ppo", "PPO + MPC head"), ("ppo_equal_steps", "PPO, equal steps"),
                      ("ppo_equal_time", "PPO, equal time")):
        for r in rec[key]:
            rows.append({"policy": name, "seed": r["seed"], "steps": r["num_timesteps"],
                         "train_s": r["train_time_s"], "return_mean": r["return_mean"],
                         "return_std": r["return_std"], "success": r["success_rate"]})
    return rows


def _report(rec: dict) -> str:
    cols = ["policy", "seed", "steps", "train_s", "return_mean", "return_std", "success"]
    lines = [f"# liecontrol learn mpc-ppo — {rec['env']}", "",
             f"PPO with the MPC-headed policy (`MPCActorCriticPolicy`, {rec['mpc_policy_kwargs']}; PPO "
             f"{rec['mpc_ppo_params']}) against plain PPO (`MlpPolicy`, the task's tuned settings) at equal "
             "environment steps "
             f"({rec['steps']}) and at equal training wall time; {len(rec['eval_seeds'])} held-out "
             "episodes, the same for every policy.",
             "", "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in _rows(rec):
        lines.append("| " + " | ".join(markdown_cell(r[c]) for c in cols) + " |")
    t = rec["step_ms_batch1"]
    lines += ["", f"Per-step compute at batch 1 (median): MPC-headed policy {t['mpc_ppo']:.3g} ms, "
              f"MLP policy {t['ppo']:.3g} ms — **{t['ratio']:.0f}×**.", "", "![curves](curves.png)", ""]
    rows = robustness_rows(rec)
    if rows:
        rcols = ["policy", "perturbation", "seeds", "return_mean", "return_min", "return_max", "success"]
        lines += ["## Robustness: the trained policies, unchanged, on the task with ±30 % model changes", "",
                  "Return on the same held-out episodes; mean, min and max over the training seeds "
                  "(`mpc_expert`: the MPC expert planning with the nominal model).", "",
                  "| " + " | ".join(rcols) + " |", "|" + "---|" * len(rcols)]
        lines += ["| " + " | ".join(markdown_cell(r[c]) for c in rcols) + " |" for r in rows] + [""]
    return "\n".join(lines)


def _plot(rec: dict, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for key, name, c in (("mpc_ppo", "PPO + MPC head", "C0"), ("ppo_equal_steps", "PPO", "C1")):
        for i, r in enumerate(rec[key]):
            ax.plot(r["curve"]["steps"], r["curve"]["returns"], color=c, label=name if i == 0 else None)
    ax.set_xlabel("environment steps")
    ax.set_ylabel("mean evaluation return")
    ax.set_title(f"{rec['env']}: MPC-headed PPO vs PPO")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


@restores_threads
def bc(env, *, counts=(1, 2, 5, 10), heldout: int = 5, eval_episodes: int = 16, mlp_epochs: int = 200,
       mpc_steps: int = 60, out: str | Path | None = None, threads: int = 1, log=None,
       mlp_kwargs: dict | None = None, mpc_kwargs: dict | None = None, **study_kwargs) -> dict:
    """The behaviour-cloning study of the module docstring, written into ``out`` (default
    ``out/learn/TASK``); returns ``{"env", "records", "_files"}``.
    ``env`` is a task name or a :class:`~learning.envs.task.Task`; ``mlp_kwargs``/``mpc_kwargs`` add to the
    learners' settings and ``study_kwargs`` go to :func:`learning.bc.bc_study` (``expert``, ``num_envs``)."""
    from learning.bc import bc_study
    from learning.envs.task import Task

    torch.set_num_threads(threads)
    task = env if isinstance(env, Task) else resolve_env(env)
    name = task.name if isinstance(task, Task) else task
    recs = bc_study(task, list(counts), heldout_episodes=heldout, eval_episodes=eval_episodes,
                    mlp_kwargs={"epochs": mlp_epochs, **(mlp_kwargs or {})},
                    mpc_kwargs={"steps": mpc_steps, **(mpc_kwargs or {})}, log=log, **study_kwargs)
    root = Path(out) if out is not None else Path("out/learn") / name
    root.mkdir(parents=True, exist_ok=True)
    files = {"json": str(root / "bc.json"), "report": str(root / "bc.md"), "plot": str(root / "bc.png")}
    rec = {"env": name, "records": recs}
    Path(files["json"]).write_text(json.dumps(rec, indent=1, allow_nan=False) + "\n")
    cols = ["learner", "demos", "train_samples", "heldout_mse", "success_rate", "return_mean", "train_time_s"]
    lines = [f"# liecontrol learn bc — {name}", "",
             "Behaviour cloning from the task's MPC expert: an MLP policy, and the MPC layer's cost weights, "
             f"learned from k expert episodes; held-out action error ({heldout} episodes) and closed-loop "
             f"success ({eval_episodes} held-out episodes).", "",
             "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in recs:
        lines.append("| " + " | ".join(markdown_cell(r.get(c)) for c in cols) + " |")
    Path(files["report"]).write_text("\n".join(lines + ["", "![bc](bc.png)", ""]))
    _plot_bc(recs, name, files["plot"])
    rec["_files"] = files
    return rec


def _plot_bc(recs: list[dict], name: str, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for learner, c in (("mlp", "C1"), ("mpc", "C0")):
        pts = sorted((r["demos"], r["success_rate"]) for r in recs if r.get("learner") == learner)
        if pts:
            ax.plot(*zip(*pts), "o-", color=c, label=f"{learner} (cloned)")
    exp = [r["success_rate"] for r in recs if r.get("learner") == "expert"]
    if exp:
        ax.axhline(exp[0], color="k", ls="--", label="MPC expert")
    ax.set_xscale("log")
    ax.set_xlabel("expert episodes")
    ax.set_ylabel("closed-loop success rate")
    ax.set_title(f"{name}: behaviour cloning")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def run(args: argparse.Namespace) -> int:
    log = None if args.quiet else write
    t0 = time.perf_counter()
    if args.subcommand == "mpc-ppo":
        rec = mpc_ppo(args.task, steps=args.budget_steps, seeds=args.seeds, eval_episodes=args.eval_episodes,
                      horizon=args.mpc_horizon, max_iter=args.max_iter, out=args.out, threads=args.threads,
                      log=log, tensorboard=args.tensorboard, quiet=args.quiet, warm_start=args.warm_start,
                      per_step=args.per_step, equal_time=args.equal_time, robustness=args.robustness)
        print_table(_rows(rec), ["policy", "seed", "steps", "train_s", "return_mean", "return_std",
                                 "success"])
        t = rec["step_ms_batch1"]
        print(f"per-step compute at batch 1: MPC head {t['mpc_ppo']:.3g} ms, MLP {t['ppo']:.3g} ms "
              f"({t['ratio']:.0f}x)")
        if rec["robustness"]:
            print_table(robustness_rows(rec), ["policy", "perturbation", "seeds", "return_mean", "return_min",
                                               "return_max", "success"])
    else:
        rec = bc(args.task, counts=args.demos, heldout=args.heldout_episodes,
                 eval_episodes=args.eval_episodes,
                 mlp_epochs=args.mlp_epochs, mpc_steps=args.mpc_steps, out=args.out, threads=args.threads,
                 log=log)
        print_table(rec["records"], ["learner", "demos", "heldout_mse", "success_rate", "return_mean"])
    files = rec.pop("_files")
    if args.json:
        p = Path(args.json)
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(json.dumps(rec, indent=1, allow_nan=False) + "\n")
    print(f"wrote {', '.join(files.values())} in {time.perf_counter() - t0:.0f} s")
    if getattr(args, "tensorboard", False):
        print(f"TensorBoard logs: tensorboard --logdir {Path(files['json']).parent / 'agents'}")
    return 0
