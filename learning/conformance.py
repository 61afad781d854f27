"""A conformance suite for gymnasium vector environments (neither gymnasium nor SB3 ships one).

:func:`check_vector_env` runs every check on a vector env factory and raises ``AssertionError`` with a
message naming the failed property.  It is written against the public ``VectorEnv`` API only, so it can
check any vector env with ``Box`` spaces, not only :class:`learning.vector.TaskVectorEnv`:

* **spaces and dtypes** — ``single_*_space`` present, the batched spaces are ``batch_space`` of them,
  every output has the space's dtype and shape, rewards ``(N,)`` floating, flags ``(N,)`` bool,
  ``metadata["autoreset_mode"]`` an :class:`AutoresetMode`;
* **fresh buffers** — arrays returned by one call are not modified by later calls, and modifying them
  does not change what the env returns next;
* **seed determinism** — equal seeds and actions give equal outputs; different seeds differ;
* **autoreset semantics** of the env's mode, compared output by output with gymnasium's own
  ``SyncVectorEnv`` over the single env (when ``make_single`` is given: this is also the
  **equivalence to the single env**, environment ``i`` seeded with ``seed + i``), through several
  episode ends, a mid-run reset with a list of per-environment seeds (some None), non-finite actions in
  single environments, and every info key the reference returns (masks and nested ``final_info``);
  for ``DISABLED``, that stepping an ended environment is refused and
  ``reset(options={"reset_mask": …})`` resets exactly the masked ones.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode, SyncVectorEnv
from gymnasium.vector.utils import batch_space

__all__ = ["check_vector_env", "check_spaces", "check_fresh_buffers", "check_determinism",
           "check_against_sync", "check_disabled_mode"]


def _np(v) -> np.ndarray:
    return v.detach().cpu().numpy() if hasattr(v, "detach") else np.asarray(v)


def _actions(env, steps: int, seed: int) -> list[np.ndarray]:
    sp = env.single_action_space
    rng = np.random.default_rng(seed)
    # a little outside the box too: clipping is part of the contract being compared
    mid, half = (sp.high + sp.low) / 2, (sp.high - sp.low) / 2
    return [(rng.uniform(-1.2, 1.2, (env.num_envs, *sp.shape)) * half + mid).astype(sp.dtype)
            for _ in range(steps)]


def _step(env, a):
    """``env.step(a)``; in DISABLED mode the environments that ended are first reset by mask."""
    if env.metadata.get("autoreset_mode") == AutoresetMode.DISABLED:
        ended = getattr(env, "_conformance_ended", None)
        if ended is not None and ended.any():
            env.reset(options={"reset_mask": ended.copy()})
    out = env.step(a)
    env._conformance_ended = _np(out[2]) | _np(out[3])
    return out


def check_spaces(env: gym.vector.VectorEnv, seed: int = 0, steps: int = 5) -> None:
    N = env.num_envs
    so, sa = env.single_observation_space, env.single_action_space
    assert isinstance(so, gym.spaces.Box) and isinstance(sa, gym.spaces.Box), "spaces must be Box"
    assert env.observation_space == batch_space(so, N), "observation_space != batch_space(single, N)"
    assert env.action_space == batch_space(sa, N), "action_space != batch_space(single, N)"
    assert isinstance(env.metadata.get("autoreset_mode"), AutoresetMode), "metadata['autoreset_mode'] missing"
    obs, info = env.reset(seed=seed)
    obs = _np(obs)
    assert isinstance(info, dict), "reset infos must be a dict"
    assert obs.shape == (N, *so.shape) and obs.dtype == so.dtype, f"reset obs {obs.shape} {obs.dtype}"
    assert env.observation_space.contains(obs), "reset observation outside the observation space"
    for a in _actions(env, steps, seed):
        o, r, te, tr, info = (_np(v) if i < 4 else v for i, v in enumerate(_step(env, a)))
        assert o.shape == (N, *so.shape) and o.dtype == so.dtype, f"step obs {o.shape} {o.dtype}"
        assert env.observation_space.contains(o), "step observation outside the observation space"
        assert r.shape == (N,) and np.issubdtype(r.dtype, np.floating), f"rewards {r.shape} {r.dtype}"
        assert te.shape == (N,) and te.dtype == np.bool_, f"terminations {te.shape} {te.dtype}"
        assert tr.shape == (N,) and tr.dtype == np.bool_, f"truncations {tr.shape} {tr.dtype}"
        assert isinstance(info, dict), "step infos must be a dict"


def _scribble(arr) -> None:
    """Overwrite a returned array (numpy or torch) in place."""
    if hasattr(arr, "detach"):
        arr.logical_not_() if arr.dtype == __import__("torch").bool else arr.zero_()
    else:
        arr[...] = ~arr if arr.dtype == np.bool_ else 0


def check_fresh_buffers(make: Callable[[], gym.vector.VectorEnv], seed: int = 0, steps: int = 6) -> None:
    e1, e2 = make(), make()
    acts = _actions(e1, steps, seed)
    o1, _ = e1.reset(seed=seed)
    o2, _ = e2.reset(seed=seed)
    kept = [(o2, _np(o2).copy())]  # env 2's outputs, untouched: later calls must not overwrite them
    _scribble(o1)
    for a in acts:
        out1, out2 = _step(e1, a), _step(e2, a)
        for k in range(4):
            assert np.array_equal(_np(out1[k]), _np(out2[k])), \
                f"output {k} changed after the arrays an env returned earlier were modified"
            _scribble(out1[k])  # env 1 must not notice
            kept.append((out2[k], _np(out2[k]).copy()))
    for arr, snap in kept:
        assert np.array_equal(_np(arr), snap), "a later call overwrote an array returned earlier"


def check_determinism(make: Callable[[], gym.vector.VectorEnv], seed: int = 0, steps: int = 20) -> None:
    e1, e2 = make(), make()
    acts = _actions(e1, steps, seed)
    for e in (e1, e2):
        e.reset(seed=seed)
        e._conformance_ended = None
    for a in acts:
        for x, y in zip(_step(e1, a)[:4], _step(e2, a)[:4]):
            assert np.array_equal(_np(x), _np(y)), "same seed and actions gave different outputs"
    oa, _ = e1.reset(seed=seed)
    ob, _ = e1.reset(seed=seed)
    assert np.array_equal(_np(oa), _np(ob)), "reset(seed=s) twice gave different observations"
    oc, _ = e1.reset(seed=seed + 12345)
    assert not np.array_equal(_np(oa), _np(oc)), "different seeds gave the same observations"


def _info_equal(a: dict, b: dict, tol: float, where: str) -> None:
    """Every key of the reference's infos (gymnasium's layout: ``key`` and its mask ``_key``, nested
    dicts such as ``final_info`` compared recursively) has the same masked values in ours."""
    for key, ref_val in b.items():
        if key.startswith("_"):
            continue
        assert key in a, f"{where}: infos lack {key!r} where the reference has it"
        mask = np.asarray(b.get("_" + key, True))
        if "_" + key in b:
            assert "_" + key in a and np.array_equal(_np(a["_" + key]), mask), \
                f"{where}: infos['_{key}'] differs"
        if isinstance(ref_val, dict):
            assert isinstance(a[key], dict), f"{where}: infos[{key!r}] is not a dict"
            _info_equal(a[key], ref_val, tol, f"{where}: {key}")
            continue
        idx = np.flatnonzero(np.broadcast_to(mask, (len(ref_val),)))
        if not len(idx):
            continue
        ref = np.stack([np.asarray(ref_val[i]) for i in idx])
        got = np.stack([np.asarray(_np(a[key])[i]) for i in idx])
        ok = (np.array_equal(got, ref) if ref.dtype.kind in "bOiuU"
              else np.allclose(got.astype(float), ref.astype(float), rtol=0, atol=tol, equal_nan=True))
        assert ok, f"{where}: infos[{key!r}] differs"
    for key in a:
        if not key.startswith("_") and key not in b and "_" + key in a:
            assert not np.any(_np(a["_" + key])), f"{where}: unexpected infos[{key!r}]"


def check_against_sync(make: Callable[[AutoresetMode], gym.vector.VectorEnv],
                       make_single: Callable[[], gym.Env], mode: AutoresetMode, seed: int = 0,
                       steps: int = 40, tol: float = 1e-12) -> None:
    """Ours vs ``SyncVectorEnv([make_single] * N, autoreset_mode=mode)``, all outputs, ``steps`` steps."""
    ours = make(mode)
    ref = SyncVectorEnv([make_single for _ in range(ours.num_envs)], autoreset_mode=mode)
    o1, _ = ours.reset(seed=seed)
    o2, _ = ref.reset(seed=seed)
    assert np.allclose(_np(o1), o2, rtol=0, atol=tol), "reset observations differ from the reference"
    ended = np.zeros(ours.num_envs, bool)
    n_end = 0
    N = ours.num_envs
    for k, a in enumerate(_actions(ours, steps, seed)):
        if k == steps // 2:  # a reset with per-environment seeds (a list, None for some) mid-run
            seeds = [None if i % 3 == 1 else seed + 100 + 7 * i for i in range(N)]
            o1, _ = ours.reset(seed=seeds)
            o2, _ = ref.reset(seed=seeds)
            assert np.allclose(_np(o1), o2, rtol=0, atol=tol), "list-seeded reset observations differ"
            ended[:] = False
        if mode == AutoresetMode.DISABLED and ended.any():
            ours.reset(options={"reset_mask": ended.copy()})
            ref.reset(options={"reset_mask": ended.copy()})
        if k % 7 == 3 and np.issubdtype(a.dtype, np.floating):  # a non-finite action in one env
            a = a.copy()
            a[k % N].flat[0] = np.nan
        out1 = ours.step(a)
        out2 = ref.step(a)
        where = f"{mode.name} step {k}"
        for i, nm in enumerate(("obs", "rewards", "terminations", "truncations")):
            x, y = _np(out1[i]), np.asarray(out2[i])
            assert x.shape == y.shape, f"{where}: {nm} shape {x.shape} vs {y.shape}"
            ok = np.array_equal(x, y) if x.dtype == np.bool_ else np.allclose(x, y, rtol=0, atol=tol)
            dev = np.max(np.abs(x.astype(float) - y))
            assert ok, f"{where}: {nm} differ from the reference (max {dev:.3g})"
        _info_equal(out1[4], out2[4], tol, where)
        ended = _np(out1[2]) | _np(out1[3])
        n_end += int(ended.sum())
    assert n_end > 0, "no episode ended during the check: use a shorter max_episode_steps"


def check_disabled_mode(make: Callable[[AutoresetMode], gym.vector.VectorEnv], seed: int = 0,
                        max_steps: int = 10_000) -> None:
    env = make(AutoresetMode.DISABLED)
    env.reset(seed=seed)
    zero = np.zeros((env.num_envs, *env.single_action_space.shape), env.single_action_space.dtype)
    for _ in range(max_steps):
        _, _, te, tr, _ = env.step(zero)
        ended = _np(te) | _np(tr)
        if ended.any():
            break
    else:
        raise AssertionError("no episode ended in DISABLED mode")
    try:
        env.step(zero)
    except Exception:
        pass
    else:
        raise AssertionError("DISABLED mode: stepping an ended environment was accepted")
    state = getattr(env.unwrapped, "state", None)  # optional: full states, to see who was reset
    before = None if state is None else _np(state).copy()
    env.reset(options={"reset_mask": ended.copy()})
    if before is not None:
        after = _np(env.unwrapped.state)
        assert np.array_equal(after[~ended], before[~ended]), "reset_mask reset environments outside the mask"
        assert not np.array_equal(after[ended], before[ended]), "reset_mask did not reset the masked ones"
    env.step(zero)  # accepted again


def check_vector_env(make: Callable[..., gym.vector.VectorEnv],
                     make_single: Callable[[], gym.Env] | None = None, *, seed: int = 0, tol: float = 1e-12,
                     modes: tuple[AutoresetMode, ...] = tuple(AutoresetMode),
                     steps: int = 40) -> dict[str, Any]:
    """Run the whole suite.

    Args:
        make: ``make(autoreset_mode) -> VectorEnv`` (a fresh env per call).
        make_single: ``() -> Env`` of one environment with the same time limit (e.g. ``gym.make(id,
            max_episode_steps=…)``); enables the comparison with ``SyncVectorEnv`` and the equivalence.
        tol: absolute tolerance of that comparison.
    Returns a small report ``{"checks": [...]}`` of what ran.
    """
    done = []
    for mode in modes:
        check_spaces(make(mode), seed)
        check_fresh_buffers(lambda mode=mode: make(mode), seed)
        check_determinism(lambda mode=mode: make(mode), seed)
        done += [f"spaces[{mode.name}]", f"fresh_buffers[{mode.name}]", f"determinism[{mode.name}]"]
        if make_single is not None:
            check_against_sync(make, make_single, mode, seed, steps, tol)
            done.append(f"sync_equivalence[{mode.name}]")
    if AutoresetMode.DISABLED in modes:
        check_disabled_mode(make, seed)
        done.append("disabled_mode")
    return {"checks": done}
