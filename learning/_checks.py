"""Argument checks shared by the learning-from-demonstration modules (one wording for one mistake)."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor

__all__ = ["FLOAT_DTYPES", "float_tensor"]

FLOAT_DTYPES = (torch.float32, torch.float64)


def float_tensor(v: Any, name: str, own: str, like: Tensor | None = None, *, finite: bool = False,
                 min_dim: int = 0, numpy: bool = False, whose: str = "") -> Tensor:
    """``v`` checked as a float32/float64 tensor, else ``TypeError``/``ValueError`` naming ``own`` and
    ``name``.

    ``like``: the dtype and device ``v`` must have (``whose`` names their owner in the message); with
    ``numpy=True`` a numpy array is accepted and converted (to ``like``'s dtype and device when given,
    else float64 unless it is already floating); ``min_dim``: at least that many dims; ``finite``: no
    NaN or inf."""
    if numpy and isinstance(v, np.ndarray):
        v = torch.from_numpy(np.array(v, dtype=np.float64 if v.dtype.kind != "f" else v.dtype))
        if like is not None:
            v = v.to(dtype=like.dtype, device=like.device)
    if not isinstance(v, Tensor):
        raise TypeError(f"{own}: argument '{name}' must be a floating tensor, got {type(v).__name__}")
    if v.dtype not in FLOAT_DTYPES:
        raise TypeError(f"{own}: argument '{name}' must be float32 or float64, got {v.dtype}")
    if like is not None and (v.dtype != like.dtype or v.device != like.device):
        raise TypeError(f"{own}: argument '{name}' has dtype {v.dtype} on {v.device}, expected {like.dtype} "
                        f"on {like.device}" + (f" ({whose})" if whose else ""))
    if v.dim() < min_dim:
        raise ValueError(f"{own}: argument '{name}' must have at least {min_dim} dim(s), got "
                         f"{tuple(v.shape)}")
    if finite and not bool(torch.isfinite(v).all()):
        raise ValueError(f"{own}: argument '{name}' has non-finite entries")
    return v
