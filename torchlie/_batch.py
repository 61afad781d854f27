"""Argument checks and broadcasting helpers shared by every group module.

Every public function checks its arguments at the entry point with these helpers, so a wrong shape
or dtype fails with an error that names the argument and the expected trailing shape, instead of
broadcasting silently or failing deep inside a matmul.
"""

from __future__ import annotations

import torch

__all__ = [
    "check_tensor",
    "check_same_device",
    "broadcast_leading",
    "small_angle_eps",
    "taylor_eps",
    "interp_param",
]


def _shape_str(trailing: tuple[int, ...]) -> str:
    return "(*, " + ", ".join(str(t) for t in trailing) + ")"


def check_tensor(x, trailing: tuple[int, ...], name: str, fn: str = "") -> torch.Tensor:
    """Check that ``x`` is a floating tensor of shape ``(*B, *trailing)`` and return it.

    Raises ``TypeError`` for a non-tensor or a non-floating dtype and ``ValueError`` for a wrong
    trailing shape; the message names ``fn`` (the function) and ``name`` (the argument).
    """
    where = f"{fn}: " if fn else ""
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{where}argument '{name}' must be a torch.Tensor of shape {_shape_str(trailing)}, "
                        f"got {type(x).__name__}")
    if not x.dtype.is_floating_point:
        raise TypeError(f"{where}argument '{name}' must have a floating dtype (float32 or float64), "
                        f"got {x.dtype}")
    k = len(trailing)
    if x.dim() < k or tuple(x.shape[x.dim() - k:]) != tuple(trailing):
        raise ValueError(f"{where}argument '{name}' must have shape {_shape_str(trailing)}, "
                         f"got {tuple(x.shape)}")
    return x


def check_same_device(fn: str, **tensors: torch.Tensor) -> None:
    """Raise ``ValueError`` when the named tensors are not on one device or share no dtype."""
    items = list(tensors.items())
    n0, t0 = items[0]
    for n, t in items[1:]:
        if t.device != t0.device:
            raise ValueError(f"{fn}: arguments '{n0}' and '{n}' are on different devices "
                             f"({t0.device} and {t.device}); move them to one device first")
        if t.dtype != t0.dtype:
            raise TypeError(f"{fn}: arguments '{n0}' and '{n}' have different dtypes "
                            f"({t0.dtype} and {t.dtype}); cast one explicitly (nothing is cast silently)")


def broadcast_leading(a: torch.Tensor, ka: int, b: torch.Tensor, kb: int, fn: str = "",
                      names: tuple[str, str] = ("a", "b")) -> tuple[torch.Tensor, torch.Tensor]:
    """Broadcast the leading (batch) dims of ``a`` and ``b``; ``ka``/``kb`` trailing dims are kept."""
    ba, bb = a.shape[: a.dim() - ka], b.shape[: b.dim() - kb]
    if ba == bb:
        return a, b
    try:
        batch = torch.broadcast_shapes(ba, bb)
    except RuntimeError as e:
        raise ValueError(f"{fn}: batch shapes of '{names[0]}' {tuple(ba)} and '{names[1]}' {tuple(bb)} "
                         "do not broadcast") from e
    return a.expand(*batch, *a.shape[a.dim() - ka:]), b.expand(*batch, *b.shape[b.dim() - kb:])


def small_angle_eps(dtype: torch.dtype) -> float:
    """Angle below which closed forms switch to their Taylor series.

    Chosen so that the first omitted Taylor term (~θ^4 relative) is below the dtype's resolution while
    the closed form's cancellation error (~eps/θ^2) has not yet grown large.
    """
    return 1e-3 if dtype == torch.float64 else 3e-2 if dtype in (torch.float32,) else 1e-1


def taylor_eps(dtype: torch.dtype) -> float:
    """Machine epsilon of ``dtype``."""
    return torch.finfo(dtype).eps


def interp_param(t, like: torch.Tensor, fn: str) -> torch.Tensor:
    """An interpolation parameter as a tensor of ``like``'s dtype and device.

    A Python number is converted; a tensor must already have the right dtype (nothing is cast
    silently) and is broadcast against the batch.
    """
    if isinstance(t, torch.Tensor):
        if t.dtype != like.dtype:
            raise TypeError(f"{fn}: argument 't' has dtype {t.dtype} but the poses are {like.dtype}; "
                            "cast it explicitly")
        if t.device != like.device:
            raise ValueError(f"{fn}: argument 't' is on {t.device} but the poses are on {like.device}")
        return t
    return torch.as_tensor(float(t), dtype=like.dtype, device=like.device)
