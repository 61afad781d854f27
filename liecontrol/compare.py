"""``liecontrol compare ENV``: the MPC expert (zero training) next to PPO, SAC and TD3 (stable-baselines3)
trained within a step budget, all evaluated on the same held-out episodes.

``ENV`` is one of the project's tasks, or a foreign gymnasium id with a registered model
(:mod:`learning.env_models`: ``Pendulum-v1``, ``MountainCarContinuous-v0``, ``InvertedPendulum-v5``,
``InvertedDoublePendulum-v5``, ``Reacher-v5``, ``HalfCheetah-v5``).  On a foreign id the MPC is the model's
(:func:`learning.model_mpc.model_policy`), the agents train on SB3's vectorized ``gymnasium.make(ENV)`` with
the rl-baselines3-zoo's tuned hyperparameters (:mod:`learning.zoo_hyperparams`, with the zoo's
``VecNormalize`` where it has one), everything is evaluated on the id itself (returns are the env's own),
and the report's one table gives per policy the mean ± std return, the RL steps to match the MPC's mean
return, the milliseconds per action at batch 1 and the zoo's published score (:mod:`learning.zoo`, "not
published" where it has none); a success rate only where the env gives ``info["is_success"]``.  A foreign
id without a registered model is refused unless ``mpc=False``
(``--no-mpc``): then only the agents are trained and compared.  From Python, :func:`compare` also takes an
``Env``, a ``VectorEnv`` or a factory of envs (:mod:`learning.env_source`): it is the recipe — every agent
trains on its own copies, everything is evaluated on fresh ones, the MPC's model is checked against the env
given, and the report names how the copies were made.

For each training seed and algorithm the agent is trained by :func:`learning.baselines.train` (or, with
``--load DIR``, rebuilt from the ``policy.pt`` weights a previous run saved, without training), its learning
curve recorded on the evaluation episodes; then the MPC and every agent are evaluated by
:func:`learning.evaluate` on the same seeds (``10⁶ + j``, disjoint from every training episode).  Writes
into ``--out`` (default ``out/compare/TASK``): ``report.md`` (setup, table, per-seed results, RL steps to
match the MPC, goals),
``curves.png`` (mean evaluation return and success rate against environment steps, the mean over the
training seeds with a min–max band, the MPC as a horizontal line), ``compare.json`` (also written to
``--json PATH``) and ``agents/ALGO/seedS/{model.zip, policy.pt, agent.json}`` (and ``tb/``, the TensorBoard
logs, with ``--tensorboard``).  ``--load DIR`` reads the ``agents/`` folder of such a ``DIR``.

Progress: one bar per agent on stderr, also for agents trained in worker processes (their log lines come
to the command through a queue); Ctrl-C stops the workers at once.

JSON schema: ``{"env", "mpc": {metrics} | null, "ppo": {metrics}, "sac": {metrics}, "budget_steps":
{algo: steps}, "seeds": [training seeds]}``; the metrics are the subset :data:`METRIC_KEYS` of
:meth:`learning.evaluate.EvalResult.summary` (for an algorithm: over the episodes of all its training
seeds pooled), and an algorithm's entry adds ``per_seed``, ``curve``, ``steps_to_match``,
``train_time_s``, ``num_timesteps``, ``loaded`` and ``params``; on a foreign gymnasium id the record also
has ``"foreign": true`` (and a success rate of ``null`` where the env defines none).

"RL steps to match the MPC": the first evaluated step count at which the agent's evaluation success
rate, averaged over the training seeds, reaches the MPC's (and, separately, the mean return reaches the
MPC's mean return), else "not reached within budget".  The learning curve is evaluated before training,
at the first rollout boundary at or past each multiple of ``--eval-every`` (the policy then is the one
updated on exactly that many steps) and after the last step.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import multiprocessing
import os
import signal
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from liecontrol import _options
from liecontrol._args import OptionError
from liecontrol._args import env_name as resolve_env
from liecontrol._progress import TrainingProgress, write
from liecontrol.report import fmt, print_table, restores_threads

__all__ = ["add_arguments", "run", "compare", "METRIC_KEYS", "parse_budgets", "resolve_env", "zoo_text"]

#: the keys of EvalResult.summary() kept in the JSON metrics
METRIC_KEYS = ("episodes", "num_envs", "success_rate", "return", "final_error", "tracking_error", "effort",
               "invalid_rate", "violation_rate", "step_ms", "step_ms_batch1", "wall_time_s")

#: default evaluation episodes by task (the MPC's evaluation dominates where it is slow)
DEFAULT_EVAL_EPISODES = {"PendulumSwingUp": 32, "CartPoleSwingUp": 32}


def parse_budgets(items: list | None, algos: list[str], task) -> dict[str, int]:
    """``--budget-steps`` items (``N`` for every algorithm, or ``ALGO=N``; strings or the ``(algo | None, N)``
    pairs the command line gives) over the per-task defaults."""
    from learning.baselines import default_budget

    out = {a: default_budget(a, task) for a in algos}
    for it in items or []:
        try:
            algo, steps = _options.budget_item(it) if isinstance(it, str) else it
        except argparse.ArgumentTypeError as e:
            raise ValueError(f"argument --budget-steps: {e}") from None
        if algo and algo not in algos:
            raise ValueError(f"argument --budget-steps: {algo}={steps} names an algorithm not in {algos}")
        for a in ([algo] if algo else algos):
            out[a] = steps
    return out


add_arguments = _options.compare


def _metrics(summary: dict) -> dict:
    return {k: summary.get(k) for k in METRIC_KEYS}


def _pooled(results):
    """One EvalResult holding the episodes of several (same task, same evaluation seeds per result)."""
    from learning.evaluate import EPISODE_FIELDS, EvalResult

    if len(results) == 1:
        return results[0]
    cat = {k: np.concatenate([getattr(r, k) for r in results]) for k in EPISODE_FIELDS}
    T = max(r.error_curve.shape[1] for r in results)
    curves = [np.pad(r.error_curve, ((0, 0), (0, T - r.error_curve.shape[1])), constant_values=np.nan)
              for r in results]
    meta = dict(results[0].meta)
    meta["wall_time_s"] = float(sum(r.meta.get("wall_time_s") or 0.0 for r in results))
    return EvalResult(**cat, error_curve=np.concatenate(curves), errors=sum((r.errors for r in results), []),
                      step_ms=np.concatenate([r.step_ms for r in results]),
                      step_ms_batch1=np.concatenate([r.step_ms_batch1 for r in results]),
                      solver_steps=np.concatenate([r.solver_steps for r in results]), meta=meta)


def _find_saved(load: Path, task: str, algo: str, seed: int) -> Path:
    for base in (load / "agents", load, load / task / "agents"):
        p = base / algo / f"seed{seed}" / "policy.pt"
        if p.is_file():
            return p
    raise FileNotFoundError(f"argument --load: no saved weights for {algo} seed {seed} under {load} "
                            f"(expected {load}/agents/{algo}/seed{seed}/policy.pt)")


def _train_and_evaluate(algo: str, task, budget: int, seed: int, every: int, E: int, out_dir: str,
                        train_envs: int | None, ev_seeds: list[int], N: int, threads: int, tensorboard: bool,
                        log=None):
    """Train one agent and evaluate it on the held-out episodes (the unit of work of a ``--jobs`` worker
    process, or of the command itself with one job).  Returns ``(eval result, curve, train_time_s,
    num_timesteps, params, notes)``."""
    from learning import baselines as bl
    from learning.evaluate import evaluate

    torch.set_num_threads(threads)
    res = bl.train(algo, task, budget, seed, eval_every=every, eval_episodes=E, out_dir=out_dir,
                   num_envs=train_envs, log=log, tensorboard=tensorboard)
    r = evaluate(res.model, task, seeds=ev_seeds, num_envs=N, dtype=torch.float32, progress=False)
    return r, res.curve(), res.train_time_s, res.num_timesteps, res.params, list(res.notes)


_QUEUE = None  # a worker process's queue to the command (set by _worker_init)


def _worker_init(queue) -> None:
    """A worker process ignores Ctrl-C (the command stops its workers) and sends its log lines to
    ``queue``."""
    global _QUEUE
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _QUEUE = queue


def _in_worker(key, *args):
    return _train_and_evaluate(*args, log=lambda line: _QUEUE.put((key, line)))


class _Workers:
    """``jobs`` spawned worker processes training agents, their log lines feeding ``progress``.  Leaving the
    ``with`` block by an exception (Ctrl-C included) terminates the workers at once; normally they finish."""

    def __init__(self, jobs: int, progress: TrainingProgress):
        ctx = multiprocessing.get_context("spawn")  # a fresh interpreter per worker (no forked thread pools)
        self.queue = ctx.Queue()
        self.pool = ctx.Pool(jobs, initializer=_worker_init, initargs=(self.queue,))
        progress.drain(self.queue)
        self.progress = progress

    def submit(self, key, *args):
        return self.pool.apply_async(_in_worker, (key, *args))

    def __enter__(self):
        return self

    def __exit__(self, exc_type, *_):
        if exc_type is None:
            self.pool.close()
            self.pool.join()
            self.progress.close()
            self.queue.close()
            self.queue.join_thread()
            return
        self.pool.terminate()
        self.pool.join()
        # a worker killed in the middle of a log line may hold the queue's write lock: nothing more goes
        # through the queue (a put, or waiting for one to flush, could block forever)
        self.progress.close(wait=False)
        self.queue.cancel_join_thread()
        self.queue.close()


@restores_threads
def compare(env: Any, *, algos=("ppo", "sac"), budget_steps: dict[str, int] | None = None,
            seeds=(0, 1, 2), eval_episodes: int | None = None, eval_every: int | None = None,
            num_envs: int | None = None, train_envs: int | None = None, out: str | Path | None = None,
            load: str | Path | None = None, mpc: bool = True, mpc_horizon: int | None = None,
            threads: int = 1, jobs: int | None = None, tensorboard: bool = False, log=None,
            quiet: bool = True) -> dict:
    """Run the comparison (module docstring) and write its files into ``out`` (default
    ``out/compare/TASK``); returns the JSON record, with the extra keys ``"_files"`` (the paths written)
    and ``"_wall_time_s"``.

    ``jobs``: agents trained (and evaluated) at once in worker processes (default: one per CPU core, at
    most one per agent; 1 trains in this process).  The MPC is evaluated here meanwhile.  Every agent
    is trained from its own seed with ``threads`` intra-op threads, so the results do not depend on
    ``jobs``.  ``log(line)`` receives the progress lines; progress bars on stderr unless ``quiet``.
    ``eval_every``: environment steps between two learning-curve points (default: a twentieth of the
    budget); every curve also has a point before training and one after its last step."""
    from learning import baselines as bl
    from learning.env_source import env_source, is_env_like
    from learning.envs.single import int_arg, make_task
    from learning.evaluate import evaluate, jsonable

    t_start = time.perf_counter()
    threads = int_arg(threads, "threads", "compare")
    torch.set_num_threads(threads)
    try:
        resolved = resolve_env(env) if isinstance(env, str) else env
    except argparse.ArgumentTypeError as e:
        raise OptionError("TASK", str(e)) from None
    foreign = bl.is_foreign_id(resolved) or is_env_like(resolved)
    # a foreign env: every agent trains on its own copies, everything is evaluated on fresh ones
    source = env_source(resolved, "compare") if foreign else None
    task = source.detached() if foreign else make_task(resolved)
    name = task.name
    if foreign:
        try:
            bl.check_episode_limit(source, "compare")
        except ValueError as e:
            raise OptionError("TASK", str(e)) from None
    if foreign and mpc:
        _check_model(source)
    algos = list(algos)
    seeds = [int_arg(s, "seeds", "compare", 0) for s in seeds]
    if not seeds:
        raise ValueError("argument --seeds: give at least one training seed")
    budgets = parse_budgets(None, algos, task) if budget_steps is None else {a: int(budget_steps[a])
                                                                             for a in algos}
    E = DEFAULT_EVAL_EPISODES.get(name, 16) if eval_episodes is None else eval_episodes
    E = int_arg(E, "eval_episodes", "compare")
    N = min(E, int_arg(num_envs, "num_envs", "compare") if num_envs is not None else E)
    if eval_every is not None:
        int_arg(eval_every, "eval_every", "compare")
    if jobs is not None:
        int_arg(jobs, "jobs", "compare")
    ev_seeds = bl.eval_seeds(E)
    root = Path(out) if out is not None else Path("out/compare") / name
    root.mkdir(parents=True, exist_ok=True)
    say = log or (lambda s: None)
    record: dict = {"env": name, "mpc": None} | ({"foreign": True} if foreign else {})
    notes: list[str] = []

    work = [(a, s) for a in algos for s in seeds] if load is None else []
    jobs = min(jobs or os.cpu_count() or 1, max(len(work), 1))
    if foreign:
        record["env_copies"] = task.how
        if jobs > 1 and not task.picklable():
            jobs = 1
            notes.append(f"the agents trained one after another in this process: copies of {name} "
                         f"({task.how}) cannot go to worker processes (not picklable)")
    progress = TrainingProgress({k: budgets[k[0]] for k in work}, quiet=quiet,
                                label=lambda k: f"{name} {k[0]} seed {k[1]}", log=log)

    def job(a, s):
        every = eval_every or max(1, budgets[a] // 20)
        return (a, task, budgets[a], s, every, E, str(root / "agents" / a / f"seed{s}"), train_envs, ev_seeds,
                N, threads, tensorboard)

    with contextlib.ExitStack() as stack:
        futures = {}
        if jobs > 1:
            workers = stack.enter_context(_Workers(jobs, progress))
            futures = {(a, s): workers.submit((a, s), *job(a, s)) for a, s in work}
            say(f"{name}: training {len(work)} agents in {jobs} worker processes")
        else:
            stack.callback(progress.close)

        mpc_res = None
        if mpc:
            expert = _expert(source if foreign else task, foreign, mpc_horizon)
            say(f"{name}: evaluating the MPC expert (horizon {expert.horizon}) on {E} episodes")
            mpc_res = evaluate(expert, task, seeds=ev_seeds, num_envs=N, progress=not quiet)
            record["mpc"] = _metrics(mpc_res.summary()) | {"horizon": expert.horizon, "eval_seeds": ev_seeds}
            say(f"{name}: MPC success {_success(mpc_res):.3f}, return {mpc_res.returns.mean():.1f}")
        mpc_success = _success(mpc_res) if mpc_res is not None else math.nan
        mpc_return = float(mpc_res.returns.mean()) if mpc_res is not None else math.nan

        for algo in algos:
            per_seed, results, curves = [], [], []
            for s in seeds:
                if load is not None:
                    pt = _find_saved(Path(load), name, algo, s)
                    meta = bl.read_agent_meta(pt)
                    try:
                        model = bl.load_agent(pt, algo, task)
                    except ValueError as e:  # weights of another task or algorithm
                        raise OptionError("--load", str(e)) from None
                    curve, train_time, steps, params = (meta["curve"], meta.get("train_time_s"),
                                                        meta.get("num_timesteps"), meta["params"])
                    if meta.get("eval_episodes") not in (None, E):
                        notes.append(f"{algo} seed {s}: its saved curve was evaluated on "
                                     f"{meta['eval_episodes']} episodes, the final evaluation on {E}")
                    say(f"{name} {algo} seed {s}: loaded {pt} (no training)")
                    loaded = True
                    r = evaluate(model, task, seeds=ev_seeds, num_envs=N, dtype=torch.float32, progress=False)
                else:
                    if futures:
                        r, curve, train_time, steps, params, new_notes = futures[(algo, s)].get()
                    else:
                        r, curve, train_time, steps, params, new_notes = _train_and_evaluate(
                            *job(algo, s), log=lambda line, k=(algo, s): progress.line(k, line))
                    notes.extend(n for n in new_notes if n not in notes)
                    loaded = False
                results.append(r)
                curves.append(curve)
                per_seed.append(_seed_record(s, r, curve, train_time, steps, loaded, mpc_success, mpc_return))
                say(f"{name} {algo} seed {s}: success {per_seed[-1]['success_rate']:.3f}, "
                    f"return {per_seed[-1]['return_mean']:.1f}")
            record[algo] = _algo_record(results, curves, per_seed, params, ev_seeds, mpc_success, mpc_return)
    record["budget_steps"] = budgets
    record["seeds"] = seeds
    record = jsonable(record)
    wall = time.perf_counter() - t_start
    files = {"json": str(root / "compare.json"), "report": str(root / "report.md"),
             "curves": str(root / "curves.png")}
    _plot(record, algos, files["curves"])
    Path(files["json"]).write_text(json.dumps(record, indent=1, allow_nan=False) + "\n")
    if foreign:
        text = _report_foreign(record, algos, name, E, N, notes, wall, threads, jobs)
    else:
        text = _report(record, algos, task, E, N, notes, wall, threads, jobs)
    Path(files["report"]).write_text(text)
    return record | {"_files": files, "_wall_time_s": wall}


def _check_model(source) -> None:
    """An :class:`OptionError` unless a model is registered for the foreign env and fits it (checked on the
    env given, else on a fresh copy)."""
    from learning.env_models import env_model

    env = source.instance if source.instance is not None else source.make()
    try:
        env_model(env)
    except (TypeError, ValueError) as e:
        raise OptionError("TASK", f"{e}; or pass --no-mpc (mpc=False) to compare the agents only") from None
    finally:
        if env is not source.instance:
            env.close()


def _expert(task, foreign: bool, horizon: int | None):
    """The MPC expert: the task's (:func:`learning.policies.task_expert`), or on a foreign env the model MPC
    of its registered :class:`~learning.env_models.EnvModel` (built on the env given, else on its id)."""
    if foreign:
        from learning.model_mpc import model_policy

        return model_policy(task.instance if task.instance is not None else task.name, horizon=horizon)
    from learning.policies import task_expert

    return task_expert(task, horizon=horizon)


def _success(r) -> float:
    """The success rate of an evaluation (NaN where the env defines no success)."""
    return float(r.success.mean()) if r.meta.get("success_defined", True) else math.nan


def _seed_record(s, r, curve, train_time, steps, loaded, mpc_success, mpc_return) -> dict:
    from learning import baselines as bl

    fe = r.final_error
    return {"seed": s, "success_rate": _success(r),
            "return_mean": float(r.returns.mean()), "return_std": float(r.returns.std()),
            "final_error_mean": float(np.nanmean(fe)) if np.isfinite(fe).any() else math.nan,
            "train_time_s": train_time, "num_timesteps": steps, "loaded": loaded,
            "steps_to_match": {"success": bl.steps_to_match(curve["steps"], curve["success"], mpc_success),
                               "return": bl.steps_to_match(curve["steps"], curve["returns"], mpc_return)}}


def _algo_record(results, curves, per_seed, params, ev_seeds, mpc_success, mpc_return) -> dict:
    from learning import baselines as bl
    from learning._policy_io import encode

    pooled = _pooled(results)
    st, rmean, rmin, rmax = bl.mean_curve(curves, "returns")
    _, smean, smin, smax = bl.mean_curve(curves, "success")
    times = [p["train_time_s"] for p in per_seed if p["train_time_s"] is not None]
    return _metrics(pooled.summary()) | {
        "eval_seeds": ev_seeds, "per_seed": per_seed,
        "steps_to_match": {"success": bl.steps_to_match(st, smean, mpc_success),
                           "return": bl.steps_to_match(st, rmean, mpc_return)},
        "curve": {"steps": st, "return_mean": rmean, "return_min": rmin, "return_max": rmax,
                  "success_mean": smean, "success_min": smin, "success_max": smax},
        "train_time_s": {"mean": float(np.mean(times)) if times else None, "total": float(sum(times))},
        "num_timesteps": max(int(p["num_timesteps"] or 0) for p in per_seed),
        "loaded": all(p["loaded"] for p in per_seed), "params": encode(params, "params")}


def budget_text(budgets: dict[str, int]) -> str:
    """``{"ppo": 100000, "sac": 20000}`` as report text: ``PPO 100000 steps, SAC 20000 steps``."""
    return ", ".join(f"{a.upper()} {int(b)} steps" for a, b in budgets.items())


def _match_text(s: int | None, budget: int) -> str:
    return "not reached within budget" + f" ({budget} steps)" if s is None else f"{s} steps"


def _report(rec: dict, algos: list[str], task, E: int, N: int, notes: list[str], wall: float,
            threads: int, jobs: int = 1) -> str:
    from learning.baselines import EVAL_SEED0

    mpc = rec.get("mpc")
    L = [f"# liecontrol compare — {rec['env']}", "",
         "## Setup", "",
         f"- task `{rec['env']}` (`liecontrol/{rec['env']}-v0`), episodes of {task.max_episode_steps} steps",
         f"- evaluation: {E} held-out episodes, env seeds {EVAL_SEED0}…{EVAL_SEED0 + E - 1}, the same for "
         f"every policy, batch N = {N} (and batch 1 for the timing); RL agents deterministic, float32 "
         "envs (as trained); the MPC in float64",
         f"- MPC expert: iLQR MPC on the task's own model and cost, horizon "
         f"{mpc['horizon'] if mpc else '-'}, zero training" if mpc else "- MPC expert: skipped (--no-mpc)",
         f"- RL: stable-baselines3 {_sb3_version()} ({', '.join(a.upper() for a in algos)}), training seeds "
         f"{rec['seeds']}, budget per seed: {budget_text(rec['budget_steps'])}",
         f"- torch {torch.__version__}, "
         f"{threads} intra-op thread(s) per process, {jobs} training process(es); command wall time "
         f"{wall:.0f} s", ""]
    for a in algos:
        L.append(f"- {a.upper()} hyperparameters: `{json.dumps(rec[a]['params'])}`")
    L += ["", "Model files: `agents/ALGO/seedS/model.zip` is SB3's format — **SB3 unpickles parts of a "
          ".zip when loading it, so a model file from elsewhere can execute code**; `policy.pt` holds the "
          "plain policy weights (`torch.load(path, weights_only=True)`), rebuilt safely by "
          "`learning.baselines.load_agent` (which loads a .zip only with `trust_zip=True`).", ""]
    L += ["## Results", "",
          "| policy | training steps / seed | return mean ± std | success rate | final error mean (median) "
          f"| ms/step batch {N} median (p95) | ms/step batch 1 median (p95) | training wall time / seed |",
          "|---|---|---|---|---|---|---|---|"]

    def row(name, m, steps, ttime):
        r, fe = m["return"], m["final_error"]
        return (f"| {name} | {steps} | {fmt(r['mean'], '.1f')} ± {fmt(r['std'], '.1f')} | "
                f"{fmt(m['success_rate'], '.3f')} | {fmt(fe['mean'])} ({fmt(fe['median'])}) | "
                f"{fmt(m['step_ms']['median'])} ({fmt(m['step_ms']['p95'])}) | "
                f"{fmt(m['step_ms_batch1']['median'])} ({fmt(m['step_ms_batch1']['p95'])}) | {ttime} |")

    if mpc:
        L.append(row("MPC", mpc, 0, "0 s"))
    for a in algos:
        m = rec[a]
        t = m["train_time_s"]["mean"]
        tt = "loaded" if m["loaded"] and t is None else f"{fmt(t, '.0f')} s" + (" (loaded)" if m["loaded"]
                                                                                else "")
        L.append(row(f"{a.upper()} ({len(rec['seeds'])} seeds pooled)", m, m["num_timesteps"], tt))
    L += ["", "### Per training seed", "",
          "| algo | seed | return mean ± std | success rate | final error mean | steps to match MPC success "
          "| steps to match MPC return | training wall time |", "|---|---|---|---|---|---|---|---|"]
    for a in algos:
        for p in rec[a]["per_seed"]:
            sm = p["steps_to_match"]
            L.append(f"| {a.upper()} | {p['seed']} | {fmt(p['return_mean'], '.1f')} ± "
                     f"{fmt(p['return_std'], '.1f')} | {fmt(p['success_rate'], '.3f')} | "
                     f"{fmt(p['final_error_mean'])} | {fmt(sm['success'], 'd')} | "
                     f"{fmt(sm['return'], 'd')} | {fmt(p['train_time_s'], '.0f')} s |")
    L += ["", "## RL steps to match the MPC", ""]
    if not mpc:
        L.append("No MPC reference (--no-mpc).")
    else:
        L.append(f"MPC: success rate {fmt(mpc['success_rate'], '.3f')}, mean return "
                 f"{fmt(mpc['return']['mean'], '.1f')}. First evaluated step count at which the agent's "
                 "curve, averaged over the training seeds, reaches it:")
        L.append("")
        for a in algos:
            sm, b = rec[a]["steps_to_match"], rec["budget_steps"][a]
            L.append(f"- {a.upper()}: success rate — {_match_text(sm['success'], b)}; mean return — "
                     f"{_match_text(sm['return'], b)}")
        L += ["", "## Goals", "",
              f"- MPC success ≥ 95 % with zero training: "
              f"{'reached' if (mpc['success_rate'] or 0) >= 0.95 else 'not reached'} "
              f"({fmt(100 * (mpc['success_rate'] or 0), '.1f')} %)"]
        for a in algos:
            sm = rec[a]["steps_to_match"]["success"]
            L.append(f"- {a.upper()} steps to match the MPC's success rate: "
                     f"{_match_text(sm, rec['budget_steps'][a])}")
    return _ending(L, notes, "the evaluation return and success rate")


def zoo_text(env_id: str, algo: str) -> str:
    """The rl-baselines3-zoo's published score of ``algo`` on ``env_id`` as report text (``"mpc"``: the best
    published agent), or ``"not published"``."""
    from learning.zoo import zoo_best, zoo_scores

    if algo == "mpc":
        best = zoo_best(env_id)
        if best is None:
            return "not published"
        a, _ = best
        return f"best published: {a.upper()} {zoo_text(env_id, a)}"
    row = zoo_scores(env_id).get(algo)
    if row is None:
        return "not published"
    mean, std, steps = row
    return f"{mean:.1f} ± {std:.1f} after {steps} steps"


def _success_defined(rec: dict, algos: list[str]) -> bool:
    return any(m is not None and m.get("success_rate") is not None
               for m in [rec.get("mpc")] + [rec[a] for a in algos])


def _foreign_rows(rec: dict, algos: list[str]) -> tuple[list[dict], list[str]]:
    """The printed table of a foreign id: ``(rows, columns)``."""
    env, mpc = rec["env"], rec.get("mpc")
    rows = []
    if mpc:
        rows.append({"policy": "mpc", "train_steps": 0, "return_mean": mpc["return"]["mean"],
                     "return_std": mpc["return"]["std"], "success_rate": mpc["success_rate"],
                     "steps_to_match_return": "-", "ms_action_batch1": mpc["step_ms_batch1"]["median"],
                     "zoo_published": zoo_text(env, "mpc")})
    for a in algos:
        m, match = rec[a], rec[a]["steps_to_match"]["return"]
        rows.append({"policy": a, "train_steps": m["num_timesteps"], "return_mean": m["return"]["mean"],
                     "return_std": m["return"]["std"], "success_rate": m["success_rate"],
                     "steps_to_match_return": ("-" if not mpc else "not reached" if match is None else match),
                     "ms_action_batch1": m["step_ms_batch1"]["median"], "zoo_published": zoo_text(env, a)})
    cols = ["policy", "train_steps", "return_mean", "return_std"]
    cols += ["success_rate"] if _success_defined(rec, algos) else []
    return rows, cols + ["steps_to_match_return", "ms_action_batch1", "zoo_published"]


def _report_foreign(rec: dict, algos: list[str], env_id: str, E: int, N: int, notes: list[str], wall: float,
                    threads: int, jobs: int = 1) -> str:
    """``report.md`` of a foreign gymnasium id: one table of returns, steps to match, compute and the zoo."""
    from learning.baselines import EVAL_SEED0
    from learning.zoo import ZOO_SOURCE
    from learning.zoo_hyperparams import ZOO_HP_SOURCE, ZOO_TIMESTEPS

    mpc = rec.get("mpc")
    succ = _success_defined(rec, algos)
    zoo_steps = ZOO_TIMESTEPS.get(env_id, {})
    L = [f"# liecontrol compare — {env_id}", "", "## Setup", "",
         f"- gymnasium env `{env_id}` (not one of the project's tasks): returns are the env's own rewards "
         "summed over an episode" + ("" if succ else "; the env defines no success, so no success rate"),
         f"- evaluation: {E} held-out episodes, env seeds {EVAL_SEED0}…{EVAL_SEED0 + E - 1} "
         "(`reset(seed=s)`), the same for every policy, batch N = {N}; compute: milliseconds per action at "
         "batch 1 (one env, a whole episode); RL agents deterministic".replace("{N}", str(N)),
         (f"- MPC: `learning.model_mpc.ModelMPC` on the env's registered model (`learning.env_models`), "
          f"horizon {mpc['horizon']}, zero training — it is given the model and a cost, an RL agent only "
          "the rewards") if mpc else "- MPC: skipped (--no-mpc)",
         f"- RL: stable-baselines3 {_sb3_version()} ({', '.join(a.upper() for a in algos)}) on a "
         "`DummyVecEnv` of `Monitor`-wrapped copies of the env "
         f"({rec.get('env_copies', 'gymnasium.make(id)')}), training seeds {rec['seeds']} "
         "(training env seeds 1000·s + i), "
         f"budget per seed: {budget_text(rec['budget_steps'])}; the zoo trained with "
         + (", ".join(f"{a.upper()} {zoo_steps[a]}" for a in algos if a in zoo_steps) or "no tuned entry")
         + " steps",
         f"- hyperparameters: {ZOO_HP_SOURCE}; published scores: {ZOO_SOURCE}",
         f"- torch {torch.__version__}, {threads} intra-op thread(s) per process, {jobs} training "
         f"process(es); command wall time {wall:.0f} s", ""]
    for a in algos:
        L.append(f"- {a.upper()} hyperparameters: `{json.dumps(rec[a]['params'])}`")
    L += ["", "## Results", ""]
    head = ["policy", "training steps / seed", "return mean ± std"] + (["success rate"] if succ else []) + [
        "steps to match MPC return", "ms/action batch 1 median (p95)", f"ms/step batch {N} median",
        "training wall time / seed", "rl-baselines3-zoo published (mean ± std)"]
    L += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]

    def row(label, m, steps, match, ttime, zoo):
        cells = [label, str(steps), f"{fmt(m['return']['mean'], '.1f')} ± {fmt(m['return']['std'], '.1f')}"]
        cells += [fmt(m["success_rate"], ".3f")] if succ else []
        cells += [match, f"{fmt(m['step_ms_batch1']['median'])} ({fmt(m['step_ms_batch1']['p95'])})",
                  fmt(m["step_ms"]["median"]), ttime, zoo]
        return "| " + " | ".join(cells) + " |"

    if mpc:
        L.append(row("MPC", mpc, 0, "—", "0 s", zoo_text(env_id, "mpc")))
    for a in algos:
        m = rec[a]
        t = m["train_time_s"]["mean"]
        tt = "loaded" if m["loaded"] and t is None else f"{fmt(t, '.0f')} s" + (" (loaded)" if m["loaded"]
                                                                                else "")
        match = "—" if not mpc else _match_text(m["steps_to_match"]["return"], rec["budget_steps"][a])
        L.append(row(f"{a.upper()} ({len(rec['seeds'])} seeds pooled)", m, m["num_timesteps"], match, tt,
                     zoo_text(env_id, a)))
    L += ["", "Steps to match: the first evaluated step count at which the agent's mean evaluation return, "
          "averaged over the training seeds, reaches the MPC's mean return. The zoo's figures are one "
          "training run each, evaluated on other episodes and after the zoo's own budget (in the column): "
          "a reference, not a like-for-like comparison.", "", "### Per training seed", "",
          "| algo | seed | return mean ± std | steps to match MPC return | training wall time |",
          "|---|---|---|---|---|"]
    for a in algos:
        for p in rec[a]["per_seed"]:
            L.append(f"| {a.upper()} | {p['seed']} | {fmt(p['return_mean'], '.1f')} ± "
                     f"{fmt(p['return_std'], '.1f')} | {fmt(p['steps_to_match']['return'], 'd')} | "
                     f"{fmt(p['train_time_s'], '.0f')} s |")
    return _ending(L, notes, "the evaluation return")


def _ending(L: list[str], notes: list[str], what: str) -> str:
    """The report's last sections (the curves' figure, the notes) appended to ``L``, as one text."""
    L += ["", "## Learning curves", "", "![learning curves](curves.png)", "",
          f"Mean over the training seeds (band: min–max) of {what} on the held-out episodes; dashed: the MPC "
          "(zero training)."]
    if notes:
        L += ["", "## Notes", ""] + [f"- {n}" for n in notes]
    return "\n".join(L) + "\n"


def _sb3_version() -> str:
    try:
        import stable_baselines3
    except ImportError:  # pragma: no cover
        return "?"
    return stable_baselines3.__version__


def step_ticks(linthresh: float, xmax: float) -> list[float]:
    """Ticks of the symlog step axis: 0, then the powers of ten from ``linthresh`` up to ``xmax``; none
    inside the linear part near 0, where their labels would overlap the 0."""
    if not (xmax > 0 and linthresh > 0):
        return [0.0]
    k0, k1 = math.ceil(math.log10(linthresh) - 1e-9), math.floor(math.log10(xmax) + 1e-9)
    return [0.0] + [10.0 ** k for k in range(k0, k1 + 1)]


def _steps_label(x: float, _pos=None) -> str:
    if x == 0:
        return "0"
    for div, unit in ((1e6, "M"), (1e3, "k")):
        if x >= div:
            return f"{x / div:g}{unit}"
    return f"{x:g}"


def _plot(rec: dict, algos: list[str], path: str) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.ticker import FixedLocator, FuncFormatter, NullLocator

    fig = Figure(figsize=(11, 4.2))
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, 2)
    colors = {"ppo": "tab:blue", "sac": "tab:orange", "td3": "tab:green"}
    smallest, largest = [], [1.0]
    scale = {"return": 1.0, "success": 100.0}  # success rate drawn in percent
    for a in algos:
        c = rec[a]["curve"]
        st = np.asarray(c["steps"], dtype=float)
        if st.size > 1:
            smallest.append(float(st[1]))
        largest.append(float(st.max(initial=1.0)))
        for ax, key in zip(axes, ("return", "success")):
            mean = scale[key] * np.asarray(c[f"{key}_mean"], dtype=float)
            lo, hi = (scale[key] * np.asarray(c[f"{key}_{k}"], dtype=float) for k in ("min", "max"))
            ax.plot(st, mean, color=colors.get(a), label=f"{a.upper()} (mean of {len(rec['seeds'])} seeds)")
            ax.fill_between(st, lo, hi, color=colors.get(a), alpha=0.2, label=f"{a.upper()} min-max of seeds")
    mpc = rec.get("mpc")
    for ax, key, label in zip(axes, ("return", "success"), ("mean evaluation return", "success rate [%]")):
        if mpc:
            y = mpc["return"]["mean"] if key == "return" else mpc["success_rate"]
            if y is not None:
                ax.axhline(scale[key] * y, color="k", linestyle="--", label="MPC (no training)")
        linthresh = max(min(smallest), 1.0) if smallest else 1.0
        if smallest:
            ax.set_xscale("symlog", linthresh=linthresh)
            ax.xaxis.set_major_locator(FixedLocator(step_ticks(linthresh, max(largest))))
            ax.xaxis.set_minor_locator(NullLocator())
        ax.xaxis.set_major_formatter(FuncFormatter(_steps_label))
        ax.set_xlim(0, max(largest))
        ax.set_xlabel("environment steps (linear to the first evaluation, then log)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[1].set_ylim(0, 100)
    vals = [v for a in algos for v in rec[a]["curve"]["return_min"] + rec[a]["curve"]["return_max"]
            if v is not None]
    ref = abs(mpc["return"]["mean"]) if mpc and mpc["return"]["mean"] is not None else 0.0
    if vals and max(vals) - min(vals) > 20 * max(ref, 1.0):  # a diverged run would flatten the rest
        axes[0].set_yscale("symlog", linthresh=max(ref, 1.0))
    axes[0].legend(fontsize=8)
    fig.suptitle(f"{rec['env']}: RL learning curves vs MPC (evaluation on the same held-out episodes)")
    fig.tight_layout()
    fig.savefig(path, format="png", dpi=100)


def run(args: argparse.Namespace) -> int:
    budgets = parse_budgets(args.budget_steps, list(args.algos), args.task)
    log = None if args.quiet else write
    try:
        rec = compare(args.task, algos=args.algos, budget_steps=budgets, seeds=args.seeds,
                      eval_episodes=args.eval_episodes, eval_every=args.eval_every, num_envs=args.eval_envs,
                      train_envs=args.train_envs, out=args.out, load=args.load, mpc=not args.no_mpc,
                      mpc_horizon=args.mpc_horizon, threads=args.threads, jobs=args.jobs,
                      tensorboard=args.tensorboard, log=log, quiet=args.quiet)
    except FileNotFoundError as e:  # --load: a weights file missing in the folder
        print(f"liecontrol compare: error: {e}", file=sys.stderr)
        return 2
    files, wall = rec.pop("_files"), rec.pop("_wall_time_s")
    episodes = len((rec["mpc"] or rec[args.algos[0]])["eval_seeds"])
    print(f"{rec['env']}: evaluation on {episodes} held-out episodes per policy "
          f"(RL: {len(rec['seeds'])} training seeds pooled)")
    if rec.get("foreign"):
        rows, cols = _foreign_rows(rec, list(args.algos))
        print_table(rows, cols)
    else:
        rows = []
        if rec["mpc"]:
            rows.append(_row("mpc", rec["mpc"], 0))
        for a in args.algos:
            rows.append(_row(a, rec[a], rec[a]["num_timesteps"], rec[a]["steps_to_match"]["success"]))
        print_table(rows, ["policy", "train_steps", "return_mean", "return_std", "success_rate",
                           "final_error", "ms_step_batchN", "ms_step_batch1", "steps_to_match_success"])
    if args.json:
        p = Path(args.json)
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(json.dumps(rec, indent=1, allow_nan=False) + "\n")
    print(f"wrote {files['report']}, {files['curves']}, {files['json']}"
          + (f", {args.json}" if args.json else "") + f" in {wall:.0f} s")
    if args.tensorboard:
        print(f"TensorBoard logs: tensorboard --logdir {Path(files['json']).parent / 'agents'}")
    return 0


def _row(name: str, m: dict, steps: int, match: int | None = None) -> dict:
    return {"policy": name, "train_steps": steps, "return_mean": m["return"]["mean"],
            "return_std": m["return"]["std"], "success_rate": m["success_rate"],
            "final_error": m["final_error"]["mean"], "ms_step_batchN": m["step_ms"]["median"],
            "ms_step_batch1": m["step_ms_batch1"]["median"],
            "steps_to_match_success": "-" if name == "mpc" else ("not reached" if match is None else match)}
