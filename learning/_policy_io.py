"""What :mod:`learning.baselines` writes into ``agent.json`` to rebuild an agent without pickle (private).

* Policies are recorded by a **registered name** (:data:`POLICIES`, :func:`register_policy`, plus the
  algorithm's own SB3 aliases such as ``"MlpPolicy"``); loading looks the name up in that registry and
  never imports a path read from the file.
* Hyperparameters and policy keyword arguments are recorded as JSON by :func:`encode`: numbers, strings,
  bools, None, lists and string-keyed dicts as themselves; non-finite floats, a
  :class:`~controllers.ilqr.ILQROptions`, a task (by its registered name) and a few torch classes
  (activation functions, optimizers: :data:`SAFE_CLASSES`) as tagged objects.  Anything else is a
  ``TypeError`` naming the entry, raised before training starts.  :func:`decode` inverts it.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
import torch
from torch import nn

__all__ = ["POLICIES", "SAFE_CLASSES", "register_policy", "policy_name", "policy_class", "encode", "decode"]

#: policy classes by the name ``agent.json`` records (besides the algorithm's SB3 aliases); a value may
#: be ``"module:attribute"`` (this module's own table, imported lazily: SB3-dependent modules)
POLICIES: dict[str, Any] = {"MPCActorCriticPolicy": "learning.mpc_policy:MPCActorCriticPolicy"}

#: classes that may appear in policy keyword arguments, by their recorded name
SAFE_CLASSES: dict[str, type] = {f"torch.nn.{c.__name__}": c for c in (
    nn.Tanh, nn.ReLU, nn.ELU, nn.LeakyReLU, nn.GELU, nn.SiLU, nn.Sigmoid, nn.Softplus, nn.Identity)}
SAFE_CLASSES.update({f"torch.optim.{c.__name__}": c for c in (
    torch.optim.Adam, torch.optim.AdamW, torch.optim.SGD, torch.optim.RMSprop)})


def register_policy(name: str, cls: type) -> None:
    """Make ``cls`` savable and loadable by :func:`learning.baselines.train`/``load_agent`` as ``name``."""
    if not isinstance(name, str) or not name or not isinstance(cls, type):
        raise TypeError(f"register_policy: expected a non-empty name and a class, got {name!r}, {cls!r}")
    known = POLICIES.get(name)
    if known is not None and _resolve(known) is not cls:
        raise ValueError(f"register_policy: the name {name!r} is already taken by {known!r}")
    POLICIES[name] = cls


def _resolve(entry: Any) -> type:
    if isinstance(entry, str):
        import importlib

        module, attr = entry.split(":")
        return getattr(importlib.import_module(module), attr)
    return entry


def _aliases(algo_cls) -> dict[str, type]:
    return dict(getattr(algo_cls, "policy_aliases", {}))


def policy_name(algo_cls, policy: Any) -> str:
    """The registered name of ``policy`` (an SB3 alias string, a registered name or class)."""
    aliases = _aliases(algo_cls)
    if isinstance(policy, str):
        if policy in aliases or policy in POLICIES:
            return policy
    elif isinstance(policy, type):
        for name, cls in aliases.items():
            if cls is policy:
                return name
        for name, entry in POLICIES.items():
            if _resolve(entry) is policy:
                return name
    raise TypeError(f"argument 'policy' {policy!r} cannot be saved for safe loading: use one of "
                    f"{sorted(set(aliases) | set(POLICIES))} or register it with "
                    "learning.baselines.register_policy(name, cls)")


def policy_class(algo_cls, name: Any) -> Any:
    """The policy of a recorded ``name`` (an SB3 alias is returned as the string SB3 resolves)."""
    if isinstance(name, str):
        if name in _aliases(algo_cls):
            return name
        if name in POLICIES:
            return _resolve(POLICIES[name])
    raise ValueError(f"load_agent: agent.json names the policy {name!r}, which is not registered here "
                     f"(known: {sorted(set(_aliases(algo_cls)) | set(POLICIES))}; "
                     "learning.baselines.register_policy adds one)")


def encode(v: Any, where: str) -> Any:
    """JSON-safe form of ``v`` (module docstring); ``where`` names the entry in the error."""
    from controllers.ilqr import ILQROptions
    from learning.envs.task import Task

    if v is None or isinstance(v, (bool, str, np.bool_)):
        return bool(v) if isinstance(v, np.bool_) else v
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        return float(v) if math.isfinite(v) else {"__float__": repr(float(v))}
    if isinstance(v, (list, tuple)):
        return [encode(x, f"{where}[{i}]") for i, x in enumerate(v)]
    if isinstance(v, dict):
        bad = [k for k in v if not isinstance(k, str) or k.startswith("__")]
        if bad:
            raise TypeError(f"{where}: dict keys must be strings not starting with '__', got {bad[0]!r}")
        return {k: encode(x, f"{where}[{k!r}]") for k, x in v.items()}
    if isinstance(v, Task):
        return {"__task__": v.name}
    if isinstance(v, ILQROptions):
        return {"__ILQROptions__": encode(dataclasses.asdict(v), where)}
    if isinstance(v, type):
        for name, cls in SAFE_CLASSES.items():
            if cls is v:
                return {"__class__": name}
    raise TypeError(f"{where} = {v!r} cannot be saved for safe loading (JSON numbers, strings, lists, dicts, "
                    f"ILQROptions, a Task and the classes {sorted(SAFE_CLASSES)} can)")


def decode(v: Any) -> Any:
    """The value :func:`encode` recorded (a task by its name)."""
    if isinstance(v, list):
        return [decode(x) for x in v]
    if not isinstance(v, dict):
        return v
    if len(v) == 1:
        (tag, x), = v.items()
        if tag == "__float__":
            return float(x)
        if tag == "__task__":
            return str(x)
        if tag == "__ILQROptions__":
            from controllers.ilqr import ILQROptions

            return ILQROptions(**decode(x))
        if tag == "__class__":
            if x not in SAFE_CLASSES:
                raise ValueError(f"load_agent: agent.json names the class {x!r}, not one of "
                                 f"{sorted(SAFE_CLASSES)}")
            return SAFE_CLASSES[x]
    return {k: decode(x) for k, x in v.items()}
