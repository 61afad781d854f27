"""A gymnasium environment as the code that trains and evaluates on it needs it: :class:`EnvSource`, the
env the user gave (a registered id, an ``Env``, a ``VectorEnv`` or a factory) plus a way to make fresh
copies of it.

Training and evaluation need separate environments: an agent's held-out evaluation must not step (or
reset) the env it trains on, SB3 trains on several copies at once, and ``liecontrol compare`` trains
several agents.  :func:`env_source` finds how to copy what it is given:

* a registered id: ``gymnasium.make(id)`` (made once here to check its spaces);
* an ``Env``: ``gymnasium.make(env.spec)`` where the env has a spec that rebuilds it (checked once: the
  same env class, the same wrapper chain, equal spaces) — the spec records ``make``'s arguments and every
  wrapper that records its own (gymnasium's do) — else ``copy.deepcopy(env)``.  An env wrapped in a
  wrapper with running statistics (:data:`STATEFUL_WRAPPERS`, e.g. ``NormalizeObservation``) is always
  copied by ``copy.deepcopy`` of the live env, each copy when it is made: a copy then normalizes with the
  statistics training has reached (a spec would rebuild it with fresh ones, and an evaluation would see
  observations unlike training's); the copy goes on updating its own statistics (they are not frozen);
* a ``VectorEnv`` (``SyncVectorEnv`` / ``AsyncVectorEnv``, as ``gymnasium.make_vec`` builds them): the
  factory of its first sub-env (``env_fns[0]``) — for a ``SyncVectorEnv`` whose first sub-env has a
  :data:`STATEFUL_WRAPPERS` wrapper, ``copy.deepcopy`` of that sub-env (as above; an ``AsyncVectorEnv``'s
  sub-envs live in other processes: its copies start with fresh statistics).  A vector-level wrapper other
  than
  :data:`NEUTRAL_VECTOR_WRAPPERS` is refused (copies of the sub-envs would not have it: build it into the
  sub-envs instead), and so is a vector env without ``env_fns`` (give a factory or its id);
* a factory: a zero-argument callable (a function, a ``functools.partial``, an ``Env`` subclass) that
  returns a new ``Env``; it is called twice here to check it (a factory returning the same instance twice
  is a ``TypeError``: training and evaluation would step one env).

Only 1-d ``Box`` action and observation spaces are accepted (what :func:`learning.evaluate` runs), with a
``TypeError`` naming the space otherwise.  ``EnvSource.name`` is the registered id, or the env class's name
for an env that has none.  An env given as an instance is the one training runs on
(:func:`learning.baselines.make_agent`, as SB3 trains on the env it is given); copies serve everything
else.
"""

from __future__ import annotations

import copy
import dataclasses
import pickle
from collections.abc import Callable
from functools import partial
from typing import Any

import gymnasium as gym

from learning.evaluate_env import check_box_env, env_id_of

__all__ = ["EnvSource", "env_source", "is_env_like", "NEUTRAL_VECTOR_WRAPPERS", "STATEFUL_WRAPPERS",
           "episode_limit"]

#: vector-level wrappers that change nothing an agent or a policy sees (they only record)
NEUTRAL_VECTOR_WRAPPERS = ("RecordEpisodeStatistics",)
#: wrappers whose running statistics change what the agent sees: copies of an env with one are made by
#: ``copy.deepcopy`` of the live env (module docstring)
STATEFUL_WRAPPERS = ("NormalizeObservation", "NormalizeReward")


@dataclasses.dataclass(frozen=True, eq=False)
class EnvSource:
    """An environment and a factory of fresh copies of it (module docstring).

    Attributes:
        name: the registered id, or the env class's name.
        env_id: the registered id (``None`` when the env has none).
        make: a zero-argument callable returning a fresh single ``Env``.
        instance: the ``Env`` / ``VectorEnv`` given (``None`` for an id or a factory).
        how: how copies are made (``"gymnasium.make(id)"``, ``"gymnasium.make(env.spec)"``, ...), for
            reports.
    """

    name: str
    env_id: str | None
    make: Callable[[], gym.Env]
    instance: Any = None
    how: str = ""

    @property
    def is_vector(self) -> bool:
        return isinstance(self.instance, gym.vector.VectorEnv)

    def detached(self) -> EnvSource:
        """The same source without the instance (copies only): what worker processes get."""
        return dataclasses.replace(self, instance=None)

    def picklable(self) -> bool:
        """Whether :meth:`detached` can go to another process."""
        try:
            pickle.dumps(self.detached())
        except Exception:
            return False
        return True

    def copies(self, n: int) -> gym.vector.SyncVectorEnv:
        """``n`` fresh copies in a ``SyncVectorEnv`` (``NEXT_STEP`` autoreset), e.g. for an evaluation."""
        return gym.vector.SyncVectorEnv([self.make] * int(n),
                                        autoreset_mode=gym.vector.AutoresetMode.NEXT_STEP)

    def training_factories(self, n: int) -> list[Callable[[], gym.Env]]:
        """``n`` factories of single training envs: the ``Env`` given first (when one was), then copies."""
        fns = [self.make] * int(n)
        if isinstance(self.instance, gym.Env) and n >= 1:
            env = self.instance
            fns[0] = lambda: env
        return fns


def is_env_like(x: Any) -> bool:
    """Whether ``x`` is something :func:`env_source` takes other than an id: an ``Env``, a ``VectorEnv``,
    an :class:`EnvSource`, an ``Env`` subclass or a factory (a callable that is not a class)."""
    if isinstance(x, (gym.Env, gym.vector.VectorEnv, EnvSource)):
        return True
    if isinstance(x, type):
        return issubclass(x, gym.Env)
    return callable(x)


def env_source(env: Any, where: str = "env_source") -> EnvSource:
    """An :class:`EnvSource` of a registered id, an ``Env``, a ``VectorEnv`` or a factory (module
    docstring); ``where`` names the caller in errors."""
    if isinstance(env, EnvSource):
        return env
    if isinstance(env, str):
        if env not in gym.registry:
            raise ValueError(f"{where}: unknown gymnasium id {env!r} (not registered; import the package "
                             "that registers it first)")
        src = EnvSource(env, env, partial(gym.make, env), how="gymnasium.make(id)")
        probe = src.make()
        try:
            _checked(probe, where)
        finally:
            probe.close()
    elif isinstance(env, gym.vector.VectorEnv):
        src = _vector_source(env, where)
    elif isinstance(env, gym.Env):
        src = _env_source(env, where)
    elif callable(env) and (not isinstance(env, type) or issubclass(env, gym.Env)):
        src = _factory_source(env, where)
    else:
        raise TypeError(f"{where}: expected a registered gymnasium id, an Env, a VectorEnv or a factory of "
                        f"envs, got {type(env).__name__} {env!r}")
    return src


def _spaces(env) -> tuple:
    if isinstance(env, gym.vector.VectorEnv):
        return env.single_action_space, env.single_observation_space
    return env.action_space, env.observation_space


def _checked(env, where: str) -> None:
    check_box_env(*_spaces(env), where)


def _chain(env) -> list[str]:
    """The class names from the outermost wrapper down to the bare env."""
    names = []
    while env is not None:
        names.append(type(env).__name__)
        env = getattr(env, "env", None) if isinstance(env, gym.Wrapper) else None
    return names


def _stateful(env) -> bool:
    return any(n in STATEFUL_WRAPPERS for n in _chain(env))


def _same(a, b) -> bool:
    return _chain(a) == _chain(b) and _spaces(a) == _spaces(b)


def _name_of(env) -> tuple[str, str | None]:
    eid = env_id_of(env)
    base = env.unwrapped if hasattr(env, "unwrapped") else env
    return (eid or type(base).__name__), eid


def _fresh_copy(env: gym.Env) -> gym.Env:
    return copy.deepcopy(env)


def _env_source(env: gym.Env, where: str) -> EnvSource:
    _checked(env, where)
    name, eid = _name_of(env)
    spec = None if _stateful(env) else getattr(env, "spec", None)
    if spec is not None:
        try:
            probe = gym.make(spec)
        except Exception:  # a wrapper that records no arguments, an entry point that is gone, ...
            probe = None
        if probe is not None:
            ok = _same(probe, env)
            probe.close()
            if ok:
                return EnvSource(name, eid, partial(gym.make, spec), env, "gymnasium.make(env.spec)")
    try:
        _fresh_copy(env).close()
    except Exception as e:
        raise TypeError(f"{where}: cannot make copies of the env {env!r} (training and evaluation need "
                        f"separate ones): its spec does not rebuild it and copy.deepcopy fails "
                        f"({type(e).__name__}: {e}); give a factory (a zero-argument callable returning a "
                        "new env) or register it and give its id") from e
    return EnvSource(name, eid, partial(_fresh_copy, env), env, "copy.deepcopy(env)")


def _vector_source(venv: gym.vector.VectorEnv, where: str) -> EnvSource:
    _checked(venv, where)
    v = venv
    while isinstance(v, gym.vector.VectorWrapper):
        if type(v).__name__ not in NEUTRAL_VECTOR_WRAPPERS:
            raise TypeError(f"{where}: the VectorEnv is wrapped in the vector wrapper {type(v).__name__}, "
                            "which copies of its sub-envs would not have (training and evaluation need "
                            "separate envs): apply it to each sub-env instead (gymnasium.make_vec(..., "
                            f"wrappers=[...])); vector wrappers allowed: {list(NEUTRAL_VECTOR_WRAPPERS)}")
        v = v.env
    fns = getattr(v, "env_fns", None)
    if not fns:
        raise TypeError(f"{where}: cannot make copies of the VectorEnv {type(v).__name__} (it has no "
                        "env_fns; training and evaluation need separate envs): give its id or a factory "
                        "of one sub-env")
    name, eid = _name_of(venv)
    first = (getattr(v, "envs", None) or [None])[0]
    if isinstance(first, gym.Env) and _stateful(first):  # copies carry its running statistics
        _fresh_copy(first).close()
        return EnvSource(name, eid, partial(_fresh_copy, first), venv, "copy.deepcopy(the first sub-env)")
    return EnvSource(name, eid, fns[0], venv, "the vector env's env_fns[0]")


def _call(fn: Callable, where: str) -> gym.Env:
    try:
        env = fn()
    except Exception as e:
        raise TypeError(f"{where}: the env factory {fn!r} failed when called with no arguments: "
                        f"{type(e).__name__}: {e}") from e
    if not isinstance(env, gym.Env):
        raise TypeError(f"{where}: the env factory {fn!r} must return a gymnasium.Env, got "
                        f"{type(env).__name__}")
    return env


def _factory_source(fn: Callable, where: str) -> EnvSource:
    env = _call(fn, where)
    try:
        _checked(env, where)
        name, eid = _name_of(env)
        other = _call(fn, where)
    except BaseException:
        env.close()
        raise
    if other is env or other.unwrapped is env.unwrapped:  # left open: it is the factory's one env
        raise TypeError(f"{where}: the env factory {fn!r} returned the same env twice; it must return a "
                        "new env on each call (training and evaluation need separate ones): give the env "
                        "itself instead, and copies of it are made")
    other.close()
    env.close()
    return EnvSource(name, eid, fn, None, "the factory")


def episode_limit(src: EnvSource) -> int | None:
    """The ``max_episode_steps`` of the copies of ``src`` (their spec's, else a ``TimeLimit`` in their
    wrapper chain), ``None`` when they have none."""
    from learning.evaluate_env import _time_limit

    env = src.make()
    try:
        return _time_limit(env)
    finally:
        env.close()
