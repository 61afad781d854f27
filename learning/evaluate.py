"""Batched rollout evaluation of any policy on a task: :func:`evaluate` → :class:`EvalResult`.

The policy (anything :func:`learning.policies.as_policy` accepts: a :class:`~learning.policies.MPCExpert`,
an :class:`~controllers.mpc.MPCPolicy`, an SB3 model, a torch module, a callable) runs on a
:class:`~learning.vector.TaskVectorEnv` of ``num_envs`` environments in lockstep, one batched policy call
and one batched env step per control step, in rounds of ``num_envs`` episodes until every seed has had its
episode.  Every per-episode quantity is accumulated in ``(N,)`` tensors; the only Python loop is over time.

Definitions (per episode; ``a`` the raw normalized action the policy returned, ``u`` the physical control
the env applied: ``clip(a, -1, 1) · u_max``, zero where ``a`` is not finite):

* ``returns``: sum of the env's rewards, the episode's last step included.
* ``success``: ``task.success`` at the final state, and the episode not invalid.
* ``final_error``: ``task.error`` at the final state; ``tracking_error``: the mean of ``task.error`` over
  the states of the episode, initial and final included; ``error_curve (E, T+1)`` the error at each
  time, NaN after the episode ended.
* ``effort``: ``Σ_t ‖u_t‖²`` in physical units.
* ``violations``: the number of steps whose raw action had a finite component outside ``[-1, 1]`` (the
  env clipped it) — a policy that respects the action box has none.  The action reaches the env's dtype
  as it would reach the env itself (:func:`learning.envs.single.as_action`): clipped before the cast, so a
  float64 ``1e39`` for a float32 env is a violation clipped to the bound, not an ``inf``; a complex action
  is an error of the policy (below), never cast to its real part.
* ``invalid``: the episode was ended by a bad policy output or a bad state rather than by the task: the
  action had a NaN/inf (the env ends that episode only, the others go on), the state or reward became
  non-finite, the action had the wrong shape, or the policy raised.  An *exception* in ``act``/``info``
  cannot be blamed on one element: it ends **every episode running at that step** (each flagged invalid,
  with ``errors[i] = "ExceptionType: message"``, the step not taken) and the evaluation goes on with the
  next round; a wrong-shaped action is handled the same way.
* ``terminated``/``truncated``: how the env ended the episode (an invalid step is truncated);
  ``length``: steps taken.
* ``iterations``: mean solver iterations per control step, ``nonconverged``: fraction of the control
  steps whose solve was not certified converged — both from ``policy.info()``, NaN when it gives none.

Timing: the wall time of each batched policy call (the call alone, with a CUDA synchronization after
it), median and p95 at batch N (full rounds only) and, with ``timing_batch1``, at batch 1 from a short
separate run on one environment.

Autoreset mode: ``NEXT_STEP``.  An environment whose episode ended is simply masked out (its later
rewards and flags are not counted, its action is replaced by zero) until the round ends; the env resets
it on its own (``DISABLED`` would refuse to step the whole batch once any environment ended).
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from gymnasium.vector import AutoresetMode
from torch import Tensor

from learning import distributed as _dist
from learning.envs.single import as_action, as_device, as_dtype, int_arg, make_task
from learning.envs.task import Task
from learning.evaluate_env import evaluate_env, is_foreign
from learning.policies import as_policy
from learning.vector import TaskVectorEnv

__all__ = ["evaluate", "EvalResult", "jsonable"]

#: the per-episode arrays of an :class:`EvalResult` (all of shape ``(E,)``)
EPISODE_FIELDS = ("seeds", "returns", "success", "final_error", "tracking_error", "effort", "violations",
                  "invalid", "terminated", "truncated", "length", "iterations", "nonconverged")


def _pct(v: np.ndarray, q: float) -> float:
    v = v[np.isfinite(v)]
    return float(np.percentile(v, q)) if v.size else math.nan


def _stats(v: np.ndarray) -> dict[str, float]:
    """mean, std, median, p05, p95, min, max over the finite values (NaN when there are none)."""
    f = np.asarray(v, dtype=np.float64)
    f = f[np.isfinite(f)]
    if not f.size:
        return {k: math.nan for k in ("mean", "std", "median", "p05", "p95", "min", "max")}
    return {"mean": float(f.mean()), "std": float(f.std()), "median": float(np.median(f)),
            "p05": float(np.percentile(f, 5)), "p95": float(np.percentile(f, 95)),
            "min": float(f.min()), "max": float(f.max())}


def jsonable(v: Any, strict: bool = False) -> Any:
    """JSON-safe: numpy → Python, non-finite floats → None, dict keys → str.  Other values pass through,
    or with ``strict`` anything but numbers, strings, None, lists and dicts is a ``TypeError`` (what must
    be rebuilt without pickle)."""
    if isinstance(v, dict):
        return {str(k): jsonable(x, strict) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [jsonable(x, strict) for x in v]
    if isinstance(v, np.ndarray):
        return jsonable(v.tolist(), strict)
    if isinstance(v, (np.bool_, bool)):
        return bool(v)
    if isinstance(v, (np.integer, int)):
        return int(v)
    if isinstance(v, (np.floating, float)):
        return float(v) if math.isfinite(v) else None
    if strict and not (v is None or isinstance(v, str)):
        raise TypeError(f"value {v!r} is not JSON-serializable (only numbers, strings, lists and dicts "
                        "can be rebuilt without pickle)")
    return v


@dataclass(eq=False)
class EvalResult:
    """What :func:`evaluate` measured (module docstring for the definitions).

    Per-episode numpy arrays ``(E,)`` (episode ``i`` is the one of ``seeds[i]``): ``returns``, ``success``,
    ``final_error``, ``tracking_error``, ``effort``, ``violations``, ``invalid``, ``terminated``,
    ``truncated``, ``length``, ``iterations``, ``nonconverged``; ``errors`` the exception text per episode
    (``""`` when none); ``error_curve (E, T+1)``; ``step_ms`` / ``step_ms_batch1`` the timed policy calls
    (milliseconds); ``meta`` the settings.
    """

    seeds: np.ndarray
    returns: np.ndarray
    success: np.ndarray
    final_error: np.ndarray
    tracking_error: np.ndarray
    effort: np.ndarray
    violations: np.ndarray
    invalid: np.ndarray
    terminated: np.ndarray
    truncated: np.ndarray
    length: np.ndarray
    iterations: np.ndarray
    nonconverged: np.ndarray
    error_curve: np.ndarray
    errors: list[str]
    step_ms: np.ndarray
    step_ms_batch1: np.ndarray
    solver_steps: np.ndarray = field(repr=False)  #: control steps with solver info, per episode
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def episodes(self) -> int:
        return int(self.seeds.shape[0])

    def summary(self) -> dict[str, Any]:
        """Aggregate figures (plain Python numbers; NaN where undefined, e.g. no solver info)."""
        E = self.episodes
        steps = int(self.length.sum())
        solves = self.solver_steps.sum()
        rate = (lambda v: float(v.mean()) if E else math.nan)
        per_solve = (lambda v: float((v * self.solver_steps).sum() / solves) if solves else math.nan)
        s: dict[str, Any] = {
            "task": self.meta.get("task"), "policy": self.meta.get("policy"), "episodes": E,
            "num_envs": self.meta.get("num_envs"),
            "success_rate": rate(self.success) if self.meta.get("success_defined", True) else math.nan,
            "invalid_count": int(self.invalid.sum()), "invalid_rate": rate(self.invalid),
            "terminated_rate": rate(self.terminated), "exceptions": int(sum(1 for e in self.errors if e)),
            "return": _stats(self.returns), "final_error": _stats(self.final_error),
            "tracking_error": _stats(self.tracking_error), "effort": _stats(self.effort),
            "length": _stats(self.length),
            "violations_total": int(self.violations.sum()),
            "violation_rate": float(self.violations.sum() / steps) if steps else math.nan,
            "iterations_mean": per_solve(self.iterations), "nonconverged_rate": per_solve(self.nonconverged),
            "step_ms": {"batch": self.meta.get("num_envs"), "median": _pct(self.step_ms, 50),
                        "p95": _pct(self.step_ms, 95), "calls": int(self.step_ms.size)},
            "step_ms_batch1": {"median": _pct(self.step_ms_batch1, 50), "p95": _pct(self.step_ms_batch1, 95),
                               "calls": int(self.step_ms_batch1.size)},
            "wall_time_s": self.meta.get("wall_time_s"),
        }
        return s

    def to_dict(self) -> dict[str, Any]:
        """Everything as plain JSON-safe Python (non-finite numbers as ``None``)."""
        eps = {k: getattr(self, k) for k in EPISODE_FIELDS}
        eps["errors"] = list(self.errors)
        eps["solver_steps"] = self.solver_steps
        return jsonable({"summary": self.summary(), "meta": self.meta, "episodes": eps,
                       "error_curve": self.error_curve, "step_ms": self.step_ms,
                       "step_ms_batch1": self.step_ms_batch1})

    def to_json(self, path) -> None:
        """Write :meth:`to_dict` as strict JSON (no NaN literals, no pickle)."""
        with open(path, "w") as f:
            json.dump(self.to_dict(), f, allow_nan=False, indent=1)

    def table(self, per_episode: bool = False) -> str:
        """The summary as a text table (and one row per episode with ``per_episode=True``)."""
        s = self.summary()

        def ms(v):
            return "  ".join(f"{k} {_fmt(v[k])}" for k in ("mean", "std", "median", "p95", "min", "max"))

        rows = [("task / policy", f"{s['task']} / {s['policy']}"),
                ("episodes (batch)", f"{s['episodes']} ({s['num_envs']})"),
                ("success rate", _fmt(s["success_rate"])),
                ("return", ms(s["return"])), ("final error", ms(s["final_error"])),
                ("tracking error", ms(s["tracking_error"])), ("effort Σ|u|²", ms(s["effort"])),
                ("episode length", ms(s["length"])),
                ("clipped-action steps", f"{s['violations_total']} (rate {_fmt(s['violation_rate'])})"),
                ("invalid episodes", f"{s['invalid_count']} (of which {s['exceptions']} by exceptions)"),
                ("terminated rate", _fmt(s["terminated_rate"])),
                ("solver iterations/step", _fmt(s["iterations_mean"])),
                ("non-converged solves", _fmt(s["nonconverged_rate"])),
                (f"policy ms/step, batch {s['num_envs']}",
                 f"median {_fmt(s['step_ms']['median'])}  p95 {_fmt(s['step_ms']['p95'])}"),
                ("policy ms/step, batch 1",
                 f"median {_fmt(s['step_ms_batch1']['median'])}  p95 {_fmt(s['step_ms_batch1']['p95'])}"),
                ("wall time s", _fmt(s["wall_time_s"]))]
        w = max(len(r[0]) for r in rows)
        out = [f"{k:<{w}}  {v}" for k, v in rows]
        if per_episode:
            cols = ("seeds", "returns", "success", "final_error", "tracking_error", "effort", "violations",
                    "invalid", "length", "iterations", "nonconverged")
            out.append("")
            out.append("  ".join(f"{c:>14}" for c in cols))
            for i in range(self.episodes):
                out.append("  ".join(f"{_fmt(getattr(self, c)[i]):>14}" for c in cols))
        return "\n".join(out)

    def plot(self, path) -> None:
        """A PNG: histogram of the returns and the task error against time (median and the 10-90 %
        band over the episodes still running: quantiles stay inside the data, so the band of an error
        never dips below 0).  Uses matplotlib's Agg canvas (no global backend change)."""
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        fig = Figure(figsize=(10, 4))
        FigureCanvasAgg(fig)
        ax1, ax2 = fig.subplots(1, 2)
        r = self.returns[np.isfinite(self.returns)]
        ax1.hist(r, bins=max(5, min(40, r.size // 2 or 1)), color="tab:blue")
        ax1.set_xlabel("return")
        ax1.set_ylabel("episodes")
        ax1.set_title(f"{self.meta.get('task')} / {self.meta.get('policy')}: success "
                      f"{100 * float(self.success.mean()):.0f} % of {self.episodes} episodes")
        median, lo, hi = error_band(self.error_curve)
        t = np.arange(self.error_curve.shape[1]) * float(self.meta.get("dt", 1.0))
        ax2.plot(t, median, color="tab:red", label="median")
        ax2.fill_between(t, lo, hi, color="tab:red", alpha=0.25, label="10-90 % of episodes")
        ax2.set_ylim(bottom=0)
        ax2.set_xlabel("time [s]" if "dt" in self.meta else "step")
        unit = self.meta.get("error_unit")
        ax2.set_ylabel(f"task error [{unit}]" if unit else "task error (the task's unit)")
        ax2.legend()
        fig.tight_layout()
        fig.savefig(path, format="png", dpi=100)


def error_band(curves: np.ndarray, lo: float = 10, hi: float = 90):
    """``(median, low, high)`` over the episodes (rows) of ``curves (E, T)``, ignoring NaN (ended
    episodes); a column with no finite value gives NaN, without a warning."""
    c = np.asarray(curves, dtype=float)
    ok = np.isfinite(c).any(0)
    q = np.full((3, c.shape[1]), np.nan)
    if ok.any():
        q[:, ok] = np.nanpercentile(c[:, ok], [50, lo, hi], axis=0)
    return q[0], q[1], q[2]


def _fmt(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, (bool, np.bool_)):
        return str(bool(v))
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    v = float(v)
    if not math.isfinite(v):
        return "nan" if math.isnan(v) else str(v)
    return f"{v:.4g}"


def _progress_bar(total: int, desc: str):
    from tqdm.auto import tqdm  # a dependency

    return tqdm(total=total, desc=desc, unit="step")


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _policy_name(policy, wrapped) -> str:
    name = type(wrapped).__name__
    inner = type(policy).__name__
    return name if name == inner else f"{name}({inner})"


class _PolicyError(Exception):
    pass


def _call(policy, obs: Tensor, m: int):
    """``(action (N, m), info or None)``; raises :class:`_PolicyError` with the message of whatever went
    wrong in the policy (an exception, a wrong shape)."""
    try:
        a = as_action(policy.act(obs), obs.dtype, "the policy's action", obs.device)  # clipped, then cast
        if a.shape != (obs.shape[0], m):
            raise ValueError(f"the policy returned actions of shape {tuple(a.shape)}, "
                             f"expected ({obs.shape[0]}, {m})")
        get = getattr(policy, "info", None)
        info = get() if callable(get) else None
    except Exception as e:  # a broken policy is a result, not a crash
        raise _PolicyError(f"{type(e).__name__}: {e}") from e
    return a, info


def _reset(policy, done: Tensor | None) -> str:
    try:
        policy.reset(done)
    except Exception as e:
        return f"{type(e).__name__}: {e}"
    return ""


def _seeds(seeds, episodes, seed, num_envs: int) -> list[int]:
    """The episodes' seeds: ``seeds`` checked, or ``seed, seed+1, ...`` (``episodes`` of them, by default
    ``num_envs``)."""
    if seeds is None:
        E = int_arg(num_envs if episodes is None else episodes, "episodes", "evaluate")
        return [int_arg(seed, "seed", "evaluate", 0) + i for i in range(E)]
    seeds = [int_arg(s, "seeds", "evaluate", 0) for s in seeds]
    if episodes is not None and episodes != len(seeds):
        raise ValueError("evaluate: give 'seeds' or 'episodes', not both with different counts")
    if not seeds:
        raise ValueError("evaluate: argument 'seeds' is empty")
    return seeds


def evaluate(policy: Any, task: Task | str | type = "PendulumSwingUp", *, num_envs: int = 16,
             episodes: int | None = None, seeds: list[int] | None = None, seed: int = 0,
             max_episode_steps: int | None = None, task_kwargs: dict | None = None,
             device: torch.device | str = "cpu", dtype=torch.float64, progress: bool = True,
             timing_batch1: bool = True, timing_steps: int | None = None,
             compile: bool = False, distributed: bool = True) -> EvalResult:
    """Run ``policy`` on one episode per seed, ``num_envs`` episodes at a time, and measure it.

    Args:
        policy: anything :func:`learning.policies.as_policy` accepts (``"mpc"`` for the task's expert).
        task: a :class:`Task`, Task class or task name (``task_kwargs`` its arguments), or a gymnasium id
            ``"liecontrol/<Name>-v0"`` — or any other gymnasium environment: a registered id
            (``"Pendulum-v1"``, ``task_kwargs`` then go to ``gym.make``), an ``Env`` or a ``VectorEnv``,
            run by :func:`learning.evaluate_env.evaluate_env` (the policy then acts in the env's own
            units; ``"mpc"`` is the env's model MPC, :mod:`learning.env_models`).
        num_envs: batch size N (at most the number of episodes).
        episodes, seeds, seed: the episodes are those of ``seeds`` (one each; env seeding as
            :class:`TaskVectorEnv`, so episode ``s`` equals ``TaskEnv`` reset with ``seed=s``), by default
            ``seed, seed+1, ..., seed+episodes-1`` with ``episodes = num_envs``.
        max_episode_steps: episode length (default: the task's).
        device, dtype, compile: of the environments (the observation the policy sees has this dtype).
        progress: show a progress bar over the control steps (tqdm, on stderr).
        timing_batch1: also time the policy at batch 1 on ``timing_steps`` steps (default: a whole
            episode, so that the two timings see the same mix of swing-up and balancing steps) of one
            environment, the first seed's; run after the evaluation, the policy reset before and after.
        distributed: under torchrun (an initialized process group with ``W > 1`` ranks, every rank calling
            ``evaluate`` with the same arguments) each rank runs one contiguous block of the seeds
            (:func:`learning.distributed.shard`, ``num_envs`` episodes at a time) and every rank returns the
            same merged result, per-episode arrays in seed order (``meta["world_size"] = W``; ``step_ms`` is
            every rank's calls, ``step_ms_batch1`` rank 0's, ``wall_time_s`` the slowest rank's, progress is
            shown on rank 0).  ``False`` (or a single process) evaluates every seed here.

    Returns:
        an :class:`EvalResult` (module docstring for what is measured and how failures are handled).
    """
    dtype = as_dtype(dtype)
    device = as_device(device, "evaluate")
    num_envs = int_arg(num_envs, "num_envs", "evaluate")
    seeds = _seeds(seeds, episodes, seed, num_envs)
    if is_foreign(task):
        if max_episode_steps is not None:
            int_arg(max_episode_steps, "max_episode_steps", "evaluate")
        return evaluate_env(policy, task, num_envs=num_envs, seeds=seeds, max_episode_steps=max_episode_steps,
                            env_kwargs=task_kwargs, device=device, dtype=dtype, progress=progress,
                            timing_batch1=timing_batch1, timing_steps=timing_steps)
    if isinstance(task, str) and "/" in task:  # a gymnasium id
        task = task.split("/", 1)[1].rsplit("-v", 1)[0]
    task = make_task(task, task_kwargs)
    E = len(seeds)
    T = task.max_episode_steps if max_episode_steps is None else int_arg(max_episode_steps,
                                                                         "max_episode_steps", "evaluate")
    if timing_steps is not None:
        int_arg(timing_steps, "timing_steps", "evaluate")
    if not isinstance(distributed, bool):
        raise TypeError(f"evaluate: argument 'distributed' must be a bool, got {distributed!r}")
    if distributed and _dist.world_size() > 1:
        return _evaluate_sharded(policy, task, seeds, num_envs=num_envs, max_episode_steps=max_episode_steps,
                                 device=device, dtype=dtype, progress=progress, timing_batch1=timing_batch1,
                                 timing_steps=timing_steps, compile=compile)
    N = min(num_envs, E)
    pol = as_policy(policy, task)
    m = task.m
    scale = task.u_scale(dtype, device)
    fkw = dict(dtype=dtype, device=device)

    out = {k: torch.zeros(E, **fkw) for k in ("returns", "final_error", "tracking_error", "effort",
                                              "iterations", "nonconverged")}
    out.update({k: torch.zeros(E, dtype=torch.bool, device=device) for k in
                ("success", "invalid", "terminated", "truncated")})
    out.update({k: torch.zeros(E, dtype=torch.int64, device=device) for k in
                ("violations", "length", "solver_steps")})
    curve = torch.full((E, T + 1), math.nan, **fkw)
    errors = [""] * E
    step_ms: list[float] = []

    rounds = [list(range(i, min(i + N, E))) for i in range(0, E, N)]
    envs: dict[int, TaskVectorEnv] = {}

    def env_of(n: int) -> TaskVectorEnv:
        if n not in envs:
            envs[n] = TaskVectorEnv(task, n, max_episode_steps=T, autoreset_mode=AutoresetMode.NEXT_STEP,
                                    device=device, dtype=dtype, output="torch", compile=compile)
        return envs[n]

    bar = _progress_bar(len(rounds) * T, f"evaluate {task.name}") if progress else None
    t_start = time.perf_counter()
    try:
        for idx in rounds:
            n = len(idx)
            sel = torch.tensor(idx, device=device)
            env = env_of(n)
            obs, _ = env.reset(seed=[seeds[i] for i in idx])
            msg = _reset(pol, None)
            x = env.state
            err = task.error(x)
            # per-environment accumulators of this round
            ret = torch.zeros(n, **fkw)
            eff = torch.zeros(n, **fkw)
            err_sum = err.clone()
            its = torch.zeros(n, **fkw)
            nonconv = torch.zeros(n, **fkw)
            solves = torch.zeros(n, dtype=torch.int64, device=device)
            viol = torch.zeros(n, dtype=torch.int64, device=device)
            length = torch.zeros(n, dtype=torch.int64, device=device)
            active = torch.ones(n, dtype=torch.bool, device=device)
            x_final = x.clone()
            term_all = torch.zeros(n, dtype=torch.bool, device=device)
            trunc_all = torch.zeros(n, dtype=torch.bool, device=device)
            bad_all = torch.zeros(n, dtype=torch.bool, device=device)
            rows = [err]
            round_err = [""] * n
            if msg:  # the policy cannot even be reset: every episode of the round is invalid
                bad_all[:] = True
                active[:] = False
                round_err = [msg] * n
            t = 0
            while t < T and bool(active.any()):
                try:
                    _sync(device)
                    t0 = time.perf_counter()
                    a, info = _call(pol, obs, m)
                    _sync(device)
                    if n == N:
                        step_ms.append((time.perf_counter() - t0) * 1e3)
                except _PolicyError as e:
                    bad_all |= active
                    for j in torch.nonzero(active).flatten().tolist():
                        round_err[j] = str(e)
                    trunc_all |= active
                    active = torch.zeros_like(active)
                    _reset(pol, None)
                    break
                finite = torch.isfinite(a).all(-1)
                viol += (active & finite & (a.abs() > 1.0).any(-1)).long()
                a = torch.where(active[:, None], a, torch.zeros((), **fkw))
                obs, r, term, trunc, infos = env.step(a)
                x = env.state
                u = a.nan_to_num(0.0, 0.0, 0.0).clamp(-1.0, 1.0) * scale
                actf = active.to(dtype)
                ret += torch.where(active, r, torch.zeros((), **fkw))
                eff += actf * (u * u).sum(-1)
                err = task.error(x)
                err_sum += torch.where(active, err, torch.zeros((), **fkw))
                rows.append(torch.where(active, err, torch.full((), math.nan, **fkw)))
                length += active.long()
                if info is not None:
                    it = info.get("iterations")
                    cv = info.get("converged")
                    if it is not None:
                        its += actf * it.to(device=device, dtype=dtype)
                        solves += active.long()
                    if cv is not None:
                        nonconv += actf * (~cv.to(device=device, dtype=torch.bool)).to(dtype)
                inv = infos.get("invalid")
                inv = torch.zeros_like(active) if inv is None else inv.to(device=device, dtype=torch.bool)
                ended = active & (term | trunc)
                x_final = torch.where(active[:, None], x, x_final)
                term_all |= active & term
                trunc_all |= active & trunc
                bad_all |= active & inv
                active = active & ~ended
                t += 1
                if bar is not None:
                    bar.update(1)
                msg = _reset(pol, ended)
                if msg:
                    for j in torch.nonzero(active).flatten().tolist():
                        round_err[j] = msg
                    bad_all |= active
                    trunc_all |= active
                    active = torch.zeros_like(active)
            if bar is not None:
                bar.update(T - t)
                bar.set_postfix(episodes=f"{idx[-1] + 1}/{E}")
            L = length
            out["returns"][sel] = ret
            out["effort"][sel] = eff
            out["violations"][sel] = viol
            out["length"][sel] = L
            out["final_error"][sel] = task.error(x_final)
            out["tracking_error"][sel] = err_sum / (L + 1).to(dtype)
            out["success"][sel] = task.success(x_final) & ~bad_all
            out["invalid"][sel] = bad_all
            out["terminated"][sel] = term_all
            out["truncated"][sel] = trunc_all
            sf = solves.to(dtype)
            nan = torch.full((), math.nan, **fkw)
            out["iterations"][sel] = torch.where(solves > 0, its / sf.clamp(min=1), nan)
            out["nonconverged"][sel] = torch.where(solves > 0, nonconv / sf.clamp(min=1), nan)
            out["solver_steps"][sel] = solves
            c = torch.stack(rows, -1)
            curve[sel, : c.shape[1]] = c
            for j, i in enumerate(idx):
                errors[i] = round_err[j]
    finally:
        if bar is not None:
            bar.close()
    wall = time.perf_counter() - t_start

    ms1: list[float] = []
    if timing_batch1:
        steps1 = T if timing_steps is None else min(int(timing_steps), T)
        ms1 = _time_batch1(pol, task, seeds[0], steps1, T, device, dtype, m)

    res = {k: v.cpu().numpy() for k, v in out.items()}
    return EvalResult(
        seeds=np.asarray(seeds, dtype=np.int64), error_curve=curve.cpu().numpy(), errors=errors,
        step_ms=np.asarray(step_ms), step_ms_batch1=np.asarray(ms1),
        meta={"task": task.name, "policy": _policy_name(policy, pol), "num_envs": N, "episodes": E,
              "max_episode_steps": T, "dtype": str(dtype).replace("torch.", ""), "device": str(device),
              "dt": float(torch.as_tensor(task.system.dt).max()), "wall_time_s": wall},
        **res)


def _evaluate_sharded(policy: Any, task: Task, seeds: list[int], **kw: Any) -> EvalResult:
    """:func:`evaluate` of this rank's block of ``seeds``, merged with the other ranks' (all ranks return the
    same result)."""
    lo, hi = _dist.shard_bounds(len(seeds))
    main = _dist.is_main()
    kw.update(progress=kw["progress"] and main, timing_batch1=kw["timing_batch1"] and main)
    mine, error = None, None
    try:  # an exception on one rank is raised on every rank (never a rank left waiting in the gather)
        mine = evaluate(policy, task, seeds=seeds[lo:hi], distributed=False, **kw) if hi > lo else None
    except Exception as e:
        error = e
    parts = _dist.gather_objects((mine, _dist.error_info(error)))
    _dist.raise_gathered(error, [i for _, i in parts], "evaluate")
    return _merge([r for r, _ in parts if r is not None])


def _merge(parts: list[EvalResult]) -> EvalResult:
    """One :class:`EvalResult` from the ranks' results (in rank order, i.e. seed order)."""
    cat = {k: np.concatenate([getattr(p, k) for p in parts]) for k in EPISODE_FIELDS}
    meta = dict(parts[0].meta)
    meta.update(episodes=int(cat["seeds"].shape[0]), world_size=_dist.world_size(),
                wall_time_s=max(float(p.meta["wall_time_s"]) for p in parts))
    return EvalResult(**cat, error_curve=np.concatenate([p.error_curve for p in parts]),
                      errors=[e for p in parts for e in p.errors],
                      step_ms=np.concatenate([p.step_ms for p in parts]),
                      step_ms_batch1=parts[0].step_ms_batch1,
                      solver_steps=np.concatenate([p.solver_steps for p in parts]), meta=meta)


def _time_batch1(pol, task: Task, seed: int, steps: int, T: int, device, dtype, m: int) -> list[float]:
    """Milliseconds of each policy call on one environment (a fresh episode of ``seed``)."""
    env = TaskVectorEnv(task, 1, max_episode_steps=T, autoreset_mode=AutoresetMode.NEXT_STEP, device=device,
                        dtype=dtype, output="torch")
    obs, _ = env.reset(seed=[seed])
    if _reset(pol, None):
        return []
    ms = []
    for _ in range(steps):
        try:
            _sync(device)
            t0 = time.perf_counter()
            a, _ = _call(pol, obs, m)
            _sync(device)
        except _PolicyError:
            break
        ms.append((time.perf_counter() - t0) * 1e3)
        obs, _, term, trunc, _ = env.step(a)
        done = term | trunc
        if bool(done.any()):
            _reset(pol, done)
    _reset(pol, None)
    return ms
