"""``liecontrol bench envs``: environment steps per second of our batched vector envs against gymnasium's
``SyncVectorEnv`` and EnvPool (C++), in one run.

Our pendulum swing-up (Pendulum-v1's physics and reward, :mod:`learning.envs.pendulum`) and continuous
cart-pole swing-up are stepped as :class:`learning.vector.TaskVectorEnv` in tensor mode (actions and outputs
stay torch tensors on the device) and numpy mode (numpy in and out, what SB3 and stock wrappers see), on CPU
and, when present, CUDA; ``ours-compiled`` is the same env built with ``compile=True`` (the pure part of the
step through ``torch.compile``) and ``ours-aot`` with ``compile="aot"`` (exported and built by AOTInductor
once per task: ~40 s before the first row, then ~10 µs of call overhead). The anchors step their closest
tasks: gymnasium's ``Pendulum-v1`` and ``CartPole-v1`` (discrete balancing: the same physics family, a
different task) through ``gymnasium.vector.SyncVectorEnv``, and EnvPool's C++ ``Pendulum-v1`` and
``CartPole-v1`` (numpy in and out, its default thread pool). Every measurement steps with random actions for
``--seconds`` after warm-up, the median of ``--repeats`` samples is kept, and records carry the ratio to
each anchor at the same number of environments. Autoreset is on everywhere.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch

from liecontrol import _options
from liecontrol.report import print_table, restores_threads, sync, write_json

__all__ = ["add_arguments", "run", "measure"]

ENVS = {"pendulum": ("PendulumSwingUp", "Pendulum-v1"), "cartpole": ("CartPoleSwingUp", "CartPole-v1")}
IMPLS = _options.ENV_BENCH_IMPLS
COLUMNS = ["env", "impl", "mode", "device", "num_envs", "steps_per_s", "vs_gymnasium_sync", "vs_envpool",
           "status"]


add_arguments = _options.bench_envs


def _rate(step, N: int, seconds: float, repeats: int, device=None, warmup: int = 5) -> float:
    for _ in range(warmup):
        step()
    sync(device)
    rates = []
    for _ in range(max(repeats, 1)):
        k, t0 = 0, time.perf_counter()
        while True:
            step()
            k += 1
            if k % 8 == 0 or N >= 256:
                sync(device)
                dt = time.perf_counter() - t0
                if dt >= seconds:
                    break
        rates.append(N * k / dt)
    return statistics.median(rates)


def _ours(task: str, N: int, mode: str, device: str, seconds: float, repeats: int, compiled) -> float:
    from learning import TaskVectorEnv

    if compiled is True:  # every env compiles the same step code: start from an empty cache (recompile limit)
        torch._dynamo.reset()
    env = TaskVectorEnv(task, N, device=device, output=mode, compile=compiled)
    env.reset(seed=0)
    g = torch.Generator().manual_seed(0)
    acts = [torch.rand(N, env.task.m, generator=g) * 2 - 1 for _ in range(8)]
    acts = [a.to(device) for a in acts] if mode == "torch" else [a.numpy() for a in acts]
    it = iter(range(1 << 62))
    return _rate(lambda: env.step(acts[next(it) % 8]), N, seconds, repeats, device)


def _gym_actions(env, N: int, rng) -> list:
    sp = env.single_action_space
    if hasattr(sp, "n"):
        return [rng.integers(0, sp.n, size=N) for _ in range(8)]
    return [rng.uniform(sp.low, sp.high, size=(N, *sp.shape)).astype(sp.dtype) for _ in range(8)]


def _gymnasium(gid: str, N: int, seconds: float, repeats: int) -> float:
    import gymnasium as gym

    env = gym.make_vec(gid, num_envs=N, vectorization_mode="sync")
    env.reset(seed=0)
    acts = _gym_actions(env, N, np.random.default_rng(0))
    it = iter(range(1 << 62))
    return _rate(lambda: env.step(acts[next(it) % 8]), N, seconds, repeats)


def _envpool(gid: str, N: int, seconds: float, repeats: int) -> float:
    import warnings

    import envpool

    with warnings.catch_warnings():  # its own spaces warn about float64 bounds cast to float32
        warnings.simplefilter("ignore")
        env = envpool.make(gid, env_type="gymnasium", num_envs=N, seed=0)
    env.reset()
    sp = env.action_space
    rng = np.random.default_rng(0)
    if hasattr(sp, "n"):
        acts = [rng.integers(0, sp.n, size=N) for _ in range(8)]
    else:
        acts = [rng.uniform(sp.low, sp.high, size=(N, *sp.shape)).astype(sp.dtype) for _ in range(8)]
    it = iter(range(1 << 62))
    return _rate(lambda: env.step(acts[next(it) % 8]), N, seconds, repeats)


@restores_threads
def measure(envs=tuple(ENVS), num_envs=(1, 16, 64, 256, 1024, 4096), impls=IMPLS, modes=("torch", "numpy"),
            devices=None, seconds: float = 0.25, repeats: int = 5, max_sync_envs: int = 1024,
            threads: int = 1, compiled: bool = True, log=print) -> list[dict]:
    """Run the benchmark and return its records (module docstring)."""
    if threads > 0:
        torch.set_num_threads(threads)
    if devices is None:
        devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    records: list[dict] = []
    for env in envs:
        task, gid = ENVS[env]
        anchors: dict[tuple[str, int], float] = {}
        for impl in [i for i in impls if i != "ours"]:
            for N in num_envs:
                rec = {"env": env, "impl": impl, "mode": "numpy", "device": "cpu", "num_envs": N,
                       "steps_per_s": None, "anchor_task": gid, "status": "ok"}
                if impl == "gymnasium-sync" and N > max_sync_envs:
                    rec["status"] = f"skipped (> --max-sync-envs {max_sync_envs})"
                else:
                    try:
                        fn = _gymnasium if impl == "gymnasium-sync" else _envpool
                        rec["steps_per_s"] = fn(gid, N, seconds, repeats)
                        anchors[(impl, N)] = rec["steps_per_s"]
                    except ImportError as e:
                        rec["status"] = f"missing ({e.name or e})"
                    except Exception as e:  # an anchor's failure is its result
                        rec["status"] = f"failed: {type(e).__name__}: {e}"
                records.append(rec)
                log(f"{env} {impl} N={N}: {rec['steps_per_s'] or rec['status']}")
        if "ours" not in impls:
            continue
        for device in devices:
            for comp in (False, True, "aot") if compiled else (False,):
                impl = {False: "ours", True: "ours-compiled", "aot": "ours-aot"}[comp]
                for mode in modes:
                    for N in num_envs:
                        sps = _ours(task, N, mode, device, seconds, repeats, comp)
                        pairs = (("vs_gymnasium_sync", "gymnasium-sync"), ("vs_envpool", "envpool"))
                        ratio = {k: sps / anchors[(a, N)] if (a, N) in anchors else None for k, a in pairs}
                        records.append({"env": env, "impl": impl, "mode": mode, "device": device,
                                        "num_envs": N, "steps_per_s": sps, "status": "ok", **ratio})
                        log(f"{env} {impl} {mode} {device} N={N}: {sps:.3g}")
    return records


def run(args: argparse.Namespace) -> int:
    short = {task: key for key, (task, _) in ENVS.items()}
    records = measure(envs=[short[t] for t in args.tasks], num_envs=args.num_envs, impls=args.impls,
                      modes=args.modes, devices=args.devices, seconds=args.seconds, repeats=args.repeats,
                      max_sync_envs=args.max_sync_envs, threads=args.threads, compiled=not args.no_compile,
                      log=lambda s: None)
    threads = args.threads
    print(f"env steps per second, torch {torch.__version__}, {threads} thread(s) of ours; "
          "vs_* = ours / anchor at the same number of envs (same run)")
    print_table(records, COLUMNS)
    if args.json:
        write_json(args.json, records)
        print(f"wrote {args.json}")
    return 0
