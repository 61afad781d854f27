"""Batched evaluation on *any* gymnasium environment: :func:`evaluate_env` (what :func:`learning.evaluate`
runs when its ``task`` is a gymnasium id, an ``Env`` or a ``VectorEnv`` rather than one of the project's
tasks).

The policy sees the env's observations as a torch tensor ``(N, obs_dim)`` (``dtype``) and returns actions in
the **env's own units** ``(N, m)`` — what an SB3 agent's ``predict`` returns, and what
:class:`learning.model_mpc.ModelMPC` returns — not the project's normalized ``[-1, 1]`` actions.  An action
outside the env's ``Box`` is clipped to it (as :class:`gymnasium.wrappers.ClipAction` would) and the step
counted in ``violations``; a non-finite action ends that episode as ``invalid`` (a zero action, clipped into
the box, is sent in its place so that the other environments go on); an exception in the policy ends every
episode of the round (``errors`` says why).

Returns and lengths are what SB3's ``evaluate_policy`` and gymnasium's ``RecordEpisodeStatistics`` report:
the sum of the env's rewards from reset to the step that terminated or truncated it, and the number of
steps.  Episode ``s`` is the env reset with ``seed=s`` (a vector env is reset with ``seed=[s_1, ..., s_N]``,
which seeds each sub-env as ``reset(seed=s_i)`` would), so a number here equals the same policy run in a
hand-written loop on ``gym.make(id)``.  ``success`` is the env's ``info["is_success"]`` at the last step
where it gives one (``meta["success_defined"]`` says whether it did; the summary's success rate is NaN when
not); ``final_error``, ``tracking_error`` and ``error_curve`` are NaN (a foreign env has no task error);
``effort`` is ``Σ‖a‖²`` of the applied (clipped) actions in env units.
"""

from __future__ import annotations

import math
import time
from functools import partial
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium.vector import AutoresetMode
from torch import Tensor

__all__ = ["evaluate_env", "is_foreign", "env_id_of", "check_box_env"]


def is_foreign(task: Any) -> bool:
    """Whether ``task`` names a gymnasium environment that is not one of the project's tasks: an ``Env``, a
    ``VectorEnv``, an :class:`~learning.env_source.EnvSource`, an ``Env`` subclass or a factory of envs (a
    callable that is not a class), or a registered id outside the ``liecontrol/`` namespace."""
    from learning.env_source import is_env_like

    if not isinstance(task, str) and is_env_like(task):
        return True
    if isinstance(task, str) and not task.startswith("liecontrol/"):
        from learning.envs import TASKS

        return task not in TASKS and task in gym.registry
    return False


def env_id_of(env: Any) -> str | None:
    """The registered id of an env, a vector env or an id (``None`` when it has none)."""
    if isinstance(env, str):
        return env
    spec = getattr(env, "spec", None)
    if spec is None and isinstance(env, gym.vector.VectorEnv):
        spec = getattr(getattr(env, "envs", [None])[0], "spec", None)
    return None if spec is None else spec.id


def check_box_env(action_space, observation_space, what: str) -> int:
    """The action dimension ``m`` of an env whose action and observation spaces (of one env: a vector env's
    ``single_*_space``) are 1-d ``Box`` es; else a ``TypeError`` naming the space."""
    for name, sp in (("action", action_space), ("observation", observation_space)):
        if not isinstance(sp, gym.spaces.Box):
            raise TypeError(f"{what}: the {name} space must be a gymnasium.spaces.Box (continuous), got "
                            f"{type(sp).__name__}: {sp}")
        if len(sp.shape) != 1:
            raise TypeError(f"{what}: the {name} space must be 1-d (a flat vector), got shape {sp.shape} "
                            "(flatten it, e.g. with gymnasium.wrappers.FlattenObservation)")
    return int(action_space.shape[0])


def _make_vector(env: Any, N: int, T: int | None, env_kwargs: dict | None):
    """``(vector env, factory of one more single env or None, id)`` for an id, an Env or a VectorEnv."""
    kw = dict(env_kwargs or {})
    if T is not None:
        kw["max_episode_steps"] = T
    if isinstance(env, str):
        if env not in gym.registry:
            raise ValueError(f"evaluate: unknown gymnasium id {env!r} (not registered; import the package "
                             "that registers it first)")
        make = partial(gym.make, env, **kw)
        return gym.vector.SyncVectorEnv([make] * N, autoreset_mode=AutoresetMode.NEXT_STEP), make, env
    if env_kwargs:
        raise ValueError("evaluate: 'task_kwargs' apply to a gymnasium id only (they go to gym.make); an env "
                         "instance is run as it was built")
    from learning.env_source import EnvSource

    if isinstance(env, EnvSource):  # fresh copies, as for an id
        return env.copies(N), env.make, env.name
    if isinstance(env, gym.vector.VectorEnv):
        mode = env.metadata.get("autoreset_mode", AutoresetMode.NEXT_STEP)
        if mode == AutoresetMode.DISABLED or mode == "Disabled":
            raise ValueError("evaluate: a VectorEnv with autoreset_mode=DISABLED cannot run episodes of "
                             "different lengths in lockstep; use NEXT_STEP or SAME_STEP")
        return env, None, env_id_of(env)
    return gym.vector.SyncVectorEnv([lambda: env], copy=True), None, env_id_of(env)


def _box(space, dtype, device) -> tuple[Tensor, Tensor]:
    lo = np.asarray(space.low, dtype=np.float64)
    hi = np.asarray(space.high, dtype=np.float64)
    return (torch.as_tensor(lo, dtype=dtype, device=device), torch.as_tensor(hi, dtype=dtype, device=device))


def _policy_action(pol, obs: Tensor, m: int):
    """``(action (n, m) float, info)``; a broken policy raises :class:`RuntimeError` with its message."""
    try:
        a = pol.act(obs)
        a = torch.as_tensor(np.asarray(a) if not isinstance(a, Tensor) else a.detach())
        if a.is_complex() or not (a.is_floating_point() or a.dtype in (torch.int32, torch.int64)):
            raise TypeError(f"the policy's action must be real numbers, got {a.dtype}")
        a = a.to(device=obs.device, dtype=obs.dtype)
        if m == 1 and a.shape == (obs.shape[0],):
            a = a[:, None]
        if a.shape != (obs.shape[0], m):
            raise ValueError(f"the policy returned actions of shape {tuple(a.shape)}, expected "
                             f"({obs.shape[0]}, {m})")
        get = getattr(pol, "info", None)
        return a, (get() if callable(get) else None)
    except Exception as e:
        raise RuntimeError(f"{type(e).__name__}: {e}") from e


def _reset_policy(pol, done) -> str:
    try:
        pol.reset(done)
    except Exception as e:
        return f"{type(e).__name__}: {e}"
    return ""


def _acc(n: int, dtype, device) -> dict[str, Tensor]:
    f = {k: torch.zeros(n, dtype=torch.float64, device=device) for k in ("returns", "effort", "iterations",
                                                                         "nonconverged")}
    f.update({k: torch.zeros(n, dtype=torch.bool, device=device) for k in
              ("success", "invalid", "terminated", "truncated")})
    f.update({k: torch.zeros(n, dtype=torch.int64, device=device) for k in ("violations", "length",
                                                                          "solver_steps")})
    return f


def _record_info(acc: dict, info, active: Tensor, dtype, device) -> None:
    if info is None:
        return
    dtype = torch.float64
    af = active.to(dtype)
    it, cv = info.get("iterations"), info.get("converged")
    if it is not None:
        acc["iterations"] += af * it.to(device=device, dtype=dtype)
        acc["solver_steps"] += active.long()
    if cv is not None:
        acc["nonconverged"] += af * (~cv.to(device=device, dtype=torch.bool)).to(dtype)


def _success_of(infos: dict, n: int, device) -> tuple[Tensor, Tensor] | None:
    """``(is_success, given)`` of a vector env's infos, or ``None`` when it has no ``is_success``."""
    if "is_success" not in infos:
        return None
    s = torch.as_tensor(np.asarray(infos["is_success"], dtype=bool), device=device).reshape(n)
    given = np.asarray(infos.get("_is_success", np.ones(n, dtype=bool)), dtype=bool)
    return s, torch.as_tensor(given, device=device).reshape(n)


def _record_success(acc: dict, infos: dict, active: Tensor, device, seen: Tensor) -> None:
    """``info["is_success"]`` where given — and, in SAME_STEP mode, the ending step's ``final_info`` (the
    ``infos`` of that step belong to the reset)."""
    n = active.shape[0]
    for src in (infos, infos.get("final_info")):
        got = _success_of(src, n, device) if isinstance(src, dict) else None
        if got is None:
            continue
        s, given = got
        if src is not infos:
            given = given & torch.as_tensor(np.asarray(infos.get("_final_info", np.ones(n, dtype=bool)),
                                                       dtype=bool), device=device).reshape(n)
        mask = given & active
        acc["success"] = torch.where(mask, s, acc["success"])
        seen |= mask


def _env_step(venv, acc, a: Tensor, active: Tensor, box, dtype, device, succ_seen: Tensor):
    """Clip/repair the actions, step the vector env, accumulate; returns ``(obs, ended)``."""
    finite = torch.isfinite(a).all(-1)
    lo, hi = box
    outside = ((a < lo) | (a > hi)).any(-1)
    acc["violations"] += (active & finite & outside).long()
    zero = torch.zeros_like(a).clamp(lo, hi)
    applied = torch.where(finite[:, None], torch.minimum(torch.maximum(a, lo), hi), zero)
    applied = torch.where(active[:, None], applied, zero)
    act_np = applied.cpu().numpy().astype(venv.action_space.dtype, copy=False)
    obs, r, term, trunc, infos = venv.step(act_np)
    term_t = torch.as_tensor(np.asarray(term), device=device)
    trunc_t = torch.as_tensor(np.asarray(trunc), device=device)
    zero64 = torch.zeros((), dtype=torch.float64, device=device)
    r64 = torch.as_tensor(np.asarray(r, dtype=np.float64), device=device)
    acc["returns"] += torch.where(active, r64, zero64)
    acc["effort"] += active.to(torch.float64) * (applied.double() ** 2).sum(-1)
    acc["length"] += active.long()
    bad = active & ~finite
    acc["invalid"] |= bad
    _record_success(acc, infos, active, device, succ_seen)
    acc["terminated"] |= active & term_t
    acc["truncated"] |= active & (trunc_t | bad)
    return obs, active & (term_t | trunc_t | bad)


def _run_round(pol, venv, seeds: list[int], T: int, m: int, box, dtype, device, step_ms: list, full: bool,
               bar) -> tuple[dict, list[str], Tensor]:
    """One episode per seed on the sub-envs of ``venv`` in lockstep (each masked once it ended)."""
    n = len(seeds)
    acc = _acc(n, dtype, device)
    succ_seen = torch.zeros(n, dtype=torch.bool, device=device)
    errs = [""] * n
    obs, _ = venv.reset(seed=list(seeds))
    active = torch.ones(n, dtype=torch.bool, device=device)
    msg = _reset_policy(pol, None)
    if msg:
        errs, active = [msg] * n, torch.zeros_like(active)
        acc["invalid"][:] = True
    t = 0
    while t < T and bool(active.any()):
        o = torch.as_tensor(np.asarray(obs, dtype=np.float64), device=device).to(dtype)
        try:
            t0 = time.perf_counter()
            a, info = _policy_action(pol, o, m)
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            if full:
                step_ms.append((time.perf_counter() - t0) * 1e3)
        except RuntimeError as e:
            for j in torch.nonzero(active).flatten().tolist():
                errs[j] = str(e)
            acc["invalid"] |= active
            acc["truncated"] |= active
            _reset_policy(pol, None)
            break
        _record_info(acc, info, active, dtype, device)
        obs, ended = _env_step(venv, acc, a, active, box, dtype, device, succ_seen)
        active = active & ~ended
        t += 1
        if bar is not None:
            bar.update(1)
        msg = _reset_policy(pol, ended) if bool(ended.any()) else ""
        if msg:
            for j in torch.nonzero(active).flatten().tolist():
                errs[j] = msg
            acc["invalid"] |= active
            acc["truncated"] |= active
            active = torch.zeros_like(active)
    acc["truncated"] |= active  # still running after T steps: truncated here
    if bar is not None:
        bar.update(T - t)
    return acc, errs, succ_seen


def _resolve_policy(policy: Any, env: Any, venv):
    from learning.policies import as_policy

    if isinstance(policy, str):
        if policy.lower() not in ("mpc", "expert", "mpc_expert"):
            raise ValueError(f"evaluate: unknown policy name {policy!r} (known: 'mpc')")
        from learning.model_mpc import model_policy

        return model_policy(venv)  # checked against the env as built (its arguments, its wrappers)
    return as_policy(policy)


def evaluate_env(policy: Any, env: Any, *, num_envs: int = 16, seeds: list[int], max_episode_steps=None,
                 env_kwargs: dict | None = None, device="cpu", dtype=torch.float64,
                 progress: bool = True, timing_batch1: bool = True, timing_steps: int | None = None):
    """Run ``policy`` for one episode per seed on a gymnasium env (module docstring) and measure it.

    Args:
        policy: anything :func:`learning.policies.as_policy` accepts, acting in the env's units, or
            ``"mpc"`` for the env's registered model MPC (:func:`learning.env_models.env_model`).
        env: a registered id (``num_envs`` copies are made, ``max_episode_steps`` and ``env_kwargs`` passed
            to ``gym.make``), an :class:`~learning.env_source.EnvSource` or a factory of envs (an ``Env``
            subclass, a zero-argument callable; ``num_envs`` fresh copies made by its factory;
            ``max_episode_steps`` then truncates the episodes here), an ``Env`` (run as is,
            one episode at a time) or a ``VectorEnv`` (as many
            episodes at a time as it has sub-envs; its autoreset mode must not be ``DISABLED``).
        seeds: one episode per seed.
    Returns:
        an :class:`~learning.evaluate.EvalResult`.
    """
    from learning.env_source import EnvSource
    from learning.evaluate import EvalResult, _policy_name, _progress_bar

    if not isinstance(env, (str, EnvSource, gym.Env, gym.vector.VectorEnv)):  # a factory: its copies
        from learning.env_source import env_source

        env = env_source(env, "evaluate")
    E = len(seeds)
    if isinstance(env, (str, EnvSource)):
        N = min(num_envs, E)
    else:  # an instance runs all its sub-envs (the seeds padded)
        N = env.num_envs if isinstance(env, gym.vector.VectorEnv) else 1
    venv, make, eid = _make_vector(env, N, max_episode_steps, env_kwargs)
    m = check_box_env(venv.single_action_space, venv.single_observation_space, "evaluate")
    T = max_episode_steps or _spec_steps(venv)
    pol = _resolve_policy(policy, env, venv)
    box = _box(venv.single_action_space, dtype, device)
    device = torch.device(device)
    parts, errors, step_ms, seen = [], [], [], []
    bar = _progress_bar(math.ceil(E / N) * T, f"evaluate {eid}") if progress else None
    t_start = time.perf_counter()
    try:
        for i in range(0, E, N):
            idx = seeds[i:i + N]
            k = len(idx)
            sub = venv
            if k < N and make is not None:  # an id: a smaller vector env for the last round
                sub = gym.vector.SyncVectorEnv([make] * k, autoreset_mode=AutoresetMode.NEXT_STEP)
            elif k < N:
                idx = idx + [idx[-1]] * (N - k)  # a given vector env cannot shrink: pad, drop after
            acc, errs, ss = _run_round(pol, sub, idx, T, m, box, dtype, device, step_ms, k == N, bar)
            parts.append({key: v[:k] for key, v in acc.items()})
            errors += errs[:k]
            seen.append(ss[:k])
            if sub is not venv:
                sub.close()
    finally:
        if bar is not None:
            bar.close()
    wall = time.perf_counter() - t_start
    ms1: list[float] = list(step_ms) if N == 1 else []
    if timing_batch1 and make is not None:
        ms1 = _time_batch1(pol, make, seeds[0], T, m, dtype, device, timing_steps)
    if make is not None:
        venv.close()
    out = {k: torch.cat([p[k] for p in parts]).cpu().numpy() for k in parts[0]}
    success_defined = bool(torch.cat(seen).any())
    sf = np.maximum(out["solver_steps"], 1)
    for k in ("iterations", "nonconverged"):
        out[k] = np.where(out["solver_steps"] > 0, out[k] / sf, np.nan)
    nan = np.full(E, np.nan)
    return EvalResult(
        seeds=np.asarray(seeds, dtype=np.int64), final_error=nan, tracking_error=nan.copy(),
        error_curve=np.full((E, T + 1), np.nan), errors=errors, step_ms=np.asarray(step_ms),
        step_ms_batch1=np.asarray(ms1),
        meta={"task": eid or type(env).__name__, "policy": _policy_name(policy, pol), "num_envs": N,
              "episodes": E, "max_episode_steps": T, "dtype": str(dtype).replace("torch.", ""),
              "device": str(device), "wall_time_s": wall, "foreign_env": True,
              "success_defined": success_defined},
        **out)


def _time_limit(env) -> int | None:
    """The ``max_episode_steps`` of an env: its spec's, else a ``TimeLimit`` wrapper's in its chain."""
    T = getattr(getattr(env, "spec", None), "max_episode_steps", None)
    while T is None and env is not None:
        if isinstance(env, gym.wrappers.TimeLimit):
            T = env._max_episode_steps
        env = getattr(env, "env", None)
    return T


def _spec_steps(venv) -> int:
    envs = getattr(venv, "envs", None)
    T = _time_limit(envs[0]) if envs else _time_limit(venv)
    fns = getattr(getattr(venv, "unwrapped", venv), "env_fns", None)
    if T is None and not envs and fns:  # e.g. an AsyncVectorEnv: its sub-envs are elsewhere, build one here
        probe = fns[0]()
        try:
            T = _time_limit(probe)
        finally:
            probe.close()
    if T is None:
        raise ValueError("evaluate: the env has no episode limit (no max_episode_steps in its spec, no "
                         "TimeLimit wrapper): give 'max_episode_steps'")
    return int(T)


def _time_batch1(pol, make, seed: int, T: int, m: int, dtype, device, steps: int | None) -> list[float]:
    """Milliseconds of each policy call on one env (a fresh episode of ``seed``)."""
    env = gym.vector.SyncVectorEnv([make], autoreset_mode=AutoresetMode.NEXT_STEP)
    box = _box(env.single_action_space, dtype, device)
    ms: list[float] = []
    try:
        _run_round(pol, env, [seed], min(T, steps or T), m, box, dtype, device, ms, True, None)
    finally:
        env.close()
        _reset_policy(pol, None)
    return ms
