"""torchrun / DistributedDataParallel helpers for the learning loops (issue 26 §6).

Every helper is a no-op when :mod:`torch.distributed` is not initialized (or the world has one rank): a
script written with them runs unchanged as ``python script.py`` and as
``torchrun --nproc_per_node=N script.py``.  What the learning loops do with them:

* :func:`learning.ioc.fit_cost` gives each rank one contiguous block of the demos (:func:`shard`), wraps the
  cost model in :class:`~torch.nn.parallel.DistributedDataParallel` (:func:`wrap_ddp`), all-reduces the loss
  and the per-evaluation counters and gathers the per-demo results back in demo order (:func:`gather_along`);
* :func:`learning.evaluate.evaluate` gives each rank one contiguous block of the episode seeds and gathers
  the per-episode results in seed order (:func:`gather_objects`).

Sharding (:func:`shard_bounds`): ``n`` items over ``W`` ranks in contiguous blocks, the first ``n mod W``
ranks one item more (the split of ``numpy.array_split``): deterministic, every item on exactly one rank,
the blocks in rank order are ``range(n)`` (so concatenating the ranks' results restores the order), and
``n < W`` leaves the last ranks empty.

Backends: ``"gloo"`` for CPU tensors, ``"nccl"`` for CUDA tensors (one GPU per rank: :func:`init_from_env`
sets the current CUDA device to ``LOCAL_RANK``).  Collectives run on the tensors' own device.  See
``docs/distributed.md`` for commands (one machine, several machines with torchrun's rendezvous).
"""

from __future__ import annotations

import inspect
import os
from typing import Any

import torch
import torch.distributed as dist
from torch import Tensor, nn

__all__ = ["init_from_env", "is_distributed", "rank", "world_size", "local_rank", "is_main", "shard_bounds",
           "shard", "all_reduce_sum", "gather_along", "gather_objects", "wrap_ddp", "shutdown", "RankError",
           "error_info", "raise_together", "raise_gathered"]

_BACKENDS = ("gloo", "nccl")


def is_distributed() -> bool:
    """``True`` when :mod:`torch.distributed` is available and initialized."""
    return dist.is_available() and dist.is_initialized()


def rank() -> int:
    """This process' rank (0 without an initialized process group)."""
    return dist.get_rank() if is_distributed() else 0


def world_size() -> int:
    """The number of ranks (1 without an initialized process group)."""
    return dist.get_world_size() if is_distributed() else 1


def local_rank() -> int:
    """The rank on this machine (torchrun's ``LOCAL_RANK``; 0 when unset)."""
    return int(os.environ.get("LOCAL_RANK", "0"))


def is_main() -> bool:
    """``True`` on rank 0 (and in a single process): the rank that writes files and shows progress."""
    return rank() == 0


def init_from_env(backend: str | None = None, device: torch.device | str = "cpu") -> torch.device:
    """Join the process group that torchrun describes in the environment; return this rank's device.

    Reads torchrun's ``RANK``, ``WORLD_SIZE``, ``LOCAL_RANK``, ``MASTER_ADDR``/``MASTER_PORT`` (the
    ``env://`` method).  Without ``WORLD_SIZE`` (a plain ``python script.py``) nothing is initialized and
    ``device`` comes back unchanged; when a group is already initialized it is kept.

    Args:
        backend: ``"gloo"`` or ``"nccl"``; default ``"nccl"`` when ``device`` is CUDA (and CUDA is
            available), else ``"gloo"``.
        device: where this rank's tensors live: ``"cpu"`` or ``"cuda"``.  For CUDA the device becomes
            ``cuda:LOCAL_RANK`` (one GPU per rank; set as the current CUDA device, which NCCL needs).

    Raises:
        ValueError: an unknown backend or device, ``"cuda"`` without CUDA, or ``"nccl"`` for CPU tensors.
    """
    try:
        dev = torch.device(device) if isinstance(device, (str, torch.device)) else None
    except RuntimeError:
        dev = None
    if dev is None or dev.type not in ("cpu", "cuda"):
        raise ValueError(f"init_from_env: argument 'device' must be 'cpu' or 'cuda', got {device!r}")
    cuda = dev.type == "cuda"
    if cuda and not torch.cuda.is_available():
        raise ValueError("init_from_env: device 'cuda' was asked for but CUDA is not available")
    if backend is None:
        backend = "nccl" if cuda else "gloo"
    if backend not in _BACKENDS:
        raise ValueError(f"init_from_env: argument 'backend' must be one of {_BACKENDS}, got {backend!r}")
    if backend == "nccl" and not cuda:
        raise ValueError(f"init_from_env: backend 'nccl' needs CUDA tensors (device 'cuda'), got device "
                         f"{dev}; use 'gloo' for CPU tensors")
    if dev.type == "cuda":
        dev = torch.device("cuda", local_rank() if "WORLD_SIZE" in os.environ else (dev.index or 0))
        torch.cuda.set_device(dev)
    if "WORLD_SIZE" in os.environ and not is_distributed():
        _check_env()
        dist.init_process_group(backend=backend, init_method="env://")
    return dev


_ENV = ("WORLD_SIZE", "RANK", "MASTER_ADDR", "MASTER_PORT")


def _check_env() -> None:
    """torchrun's variables all set, the counts integers (else a ValueError saying how to launch)."""
    missing = [k for k in _ENV if not os.environ.get(k)]
    if missing:
        raise ValueError(f"init_from_env: WORLD_SIZE is set but {', '.join(missing)} not: launch with "
                         "torchrun (or python -m torch.distributed.run), which sets them, or unset "
                         "WORLD_SIZE for one process")
    for k in ("WORLD_SIZE", "RANK", "LOCAL_RANK", "MASTER_PORT"):
        v = os.environ.get(k, "0")
        if not v.isdigit():
            raise ValueError(f"init_from_env: environment variable {k} must be an integer >= 0, got {v!r}")
    if not int(os.environ["RANK"]) < int(os.environ["WORLD_SIZE"]):
        raise ValueError(f"init_from_env: RANK {os.environ['RANK']} is not below WORLD_SIZE "
                         f"{os.environ['WORLD_SIZE']}")


def shutdown() -> None:
    """Leave the process group (no-op without one)."""
    if is_distributed():
        dist.destroy_process_group()


def shard_bounds(n: int, r: int | None = None, w: int | None = None) -> tuple[int, int]:
    """``(start, stop)`` of rank ``r``'s block of ``n`` items over ``w`` ranks (module docstring); ``r``
    and ``w`` default to this process' rank and world size."""
    if isinstance(n, bool) or not isinstance(n, int) or n < 0:
        raise ValueError(f"shard_bounds: argument 'n' must be an int >= 0, got {n!r}")
    r = rank() if r is None else r
    w = world_size() if w is None else w
    for name, v in (("r", r), ("w", w)):
        if isinstance(v, bool) or not isinstance(v, int):
            raise ValueError(f"shard_bounds: argument {name!r} must be an int, got {v!r}")
    if not 0 <= r < w:
        raise ValueError(f"shard_bounds: rank {r} is not in [0, {w})")
    q, extra = divmod(n, w)
    start = r * q + min(r, extra)
    return start, start + q + (1 if r < extra else 0)


def shard(n: int) -> slice:
    """This rank's block of ``range(n)`` as a ``slice`` (``slice(0, n)`` in a single process)."""
    return slice(*shard_bounds(n))


def all_reduce_sum(t: Tensor) -> Tensor:
    """The sum of ``t`` over the ranks, as a new tensor (``t`` itself without a process group).  Not
    differentiable: for values and counters, not for gradients (:func:`wrap_ddp` reduces those)."""
    if world_size() == 1:
        return t
    out = t.detach().clone()
    dist.all_reduce(out, op=dist.ReduceOp.SUM)
    return out


def _all_gather(t: Tensor) -> list[Tensor]:
    parts = [torch.empty_like(t) for _ in range(world_size())]
    dist.all_gather(parts, t.contiguous())
    return parts


def gather_along(t: Tensor, n: int) -> Tensor:
    """Reassemble per-item results sharded with :func:`shard`: ``t (n_r, ...)`` is this rank's block of an
    ``(n, ...)`` result; returns the whole ``(n, ...)`` on every rank, in the original item order (``t``
    itself in a single process).  The blocks are padded to a common length for ``all_gather`` and trimmed;
    bool tensors travel as ``uint8``.  Not differentiable."""
    w = world_size()
    if w == 1:
        return t
    lo, hi = shard_bounds(n)
    if t.shape[0] != hi - lo:
        raise ValueError(f"gather_along: rank {rank()} holds items [{lo}, {hi}) of {n}, got a tensor with "
                         f"{t.shape[0]} rows")
    sizes = [b - a for a, b in (shard_bounds(n, r, w) for r in range(w))]
    is_bool = t.dtype == torch.bool
    x = t.detach().to(torch.uint8) if is_bool else t.detach()
    pad = x.new_zeros((max(sizes), *x.shape[1:]))
    pad[:x.shape[0]] = x
    out = torch.cat([p[:s] for p, s in zip(_all_gather(pad), sizes)])
    return out.bool() if is_bool else out


def gather_objects(obj: Any) -> list[Any]:
    """``[obj of rank 0, obj of rank 1, ...]`` on every rank (pickled; ``[obj]`` in a single process)."""
    if world_size() == 1:
        return [obj]
    out: list[Any] = [None] * world_size()
    dist.all_gather_object(out, obj)
    return out


class RankError(RuntimeError):
    """Raised on the ranks that did not fail when another rank raised (:func:`raise_together`): every rank
    stops together instead of waiting in a collective that the failed rank never reaches."""


def error_info(error: BaseException | None) -> tuple[str, str] | None:
    """``(type name, message)`` of ``error`` (plain strings travel to the other ranks), ``None`` for none."""
    return None if error is None else (type(error).__name__, str(error))


def raise_gathered(error: BaseException | None, infos: list[tuple[str, str] | None], what: str) -> None:
    """Given every rank's :func:`error_info` (already gathered, in rank order): a rank that failed re-raises
    its own ``error``; the others raise :class:`RankError` naming the first rank that failed and its error.
    Nothing when no rank failed."""
    if error is not None:
        raise error
    failed = [(r, i) for r, i in enumerate(infos) if i is not None]
    if failed:
        r, (name, msg) = failed[0]
        raise RankError(f"{what}: rank {r} raised {name}: {msg}")


def raise_together(error: BaseException | None, what: str) -> None:
    """Collective (every rank calls it, with its exception or ``None``): when any rank failed, every rank
    raises (:func:`raise_gathered`; one ``all_gather_object``).  In a single process ``error`` is raised
    when given."""
    if world_size() == 1:
        if error is not None:
            raise error
        return
    raise_gathered(error, gather_objects(error_info(error)), what)


def wrap_ddp(module: nn.Module) -> nn.Module:
    """``module`` in :class:`~torch.nn.parallel.DistributedDataParallel` when distributed (``module`` itself
    otherwise).

    The wrapper starts every rank from rank 0's parameters and buffers (one broadcast), and after each
    backward **averages** the gradients over the ranks (a loss whose global value is the sum of the ranks'
    values must therefore be multiplied by the world size before ``backward``, as
    :func:`learning.ioc.fit_cost` does).  Buffers are not re-broadcast at every forward (the cost models
    never change theirs).  No ``device_ids`` (CPU or CUDA): DDP then leaves the forward's inputs where they
    are — with ``device_ids`` it moves them and fails on a forward without arguments, as the cost models'
    (measured on an H200, torch 2.11: ``IndexError`` in ``_pre_forward``).
    """
    if world_size() == 1:
        return module
    ddp = nn.parallel.DistributedDataParallel
    # torch >= 2.13 spells "no buffer broadcast at forward" forward_sync_buffers (broadcast_buffers warns)
    key = "forward_sync_buffers" if "forward_sync_buffers" in inspect.signature(ddp).parameters else \
        "broadcast_buffers"
    return ddp(module, **{key: False})
