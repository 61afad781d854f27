"""Shared pieces of the second-order (position, velocity) system models.

State ``x = [q, v]`` with ``q, v ∈ R^k``; continuous acceleration ``a(q, v, u)``.  The discrete step is
semi-implicit (symplectic) Euler::

    v⁺ = v + dt · a(q, v, u),     q⁺ = q + dt · v⁺,

whose exact Jacobians follow from those of ``a``::

    A = [[I + dt² a_q,  dt I + dt² a_v],     B = [[dt² a_u],
         [dt a_q,       I + dt a_v    ]],         [dt a_u ]].
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchlie._batch import broadcast_shapes

__all__ = ["param", "shape_of", "euler_step", "euler_jacobian", "check_xu"]


def param(value: Tensor | float, like: Tensor, name: str, owner: str) -> Tensor | float:
    """A model parameter for computations with ``like``: Python numbers stay floats (they broadcast for
    free), tensors must have the dtype of ``like`` and broadcast against ``like.shape[:-1]`` from the
    right (``(B,)`` for a batch of models).  Nothing is cast silently: another dtype is an error.
    """
    if isinstance(value, Tensor):
        if value.dtype != like.dtype:
            raise TypeError(f"{owner}: parameter '{name}' has dtype {value.dtype} but the state has "
                            f"{like.dtype}; cast one of them explicitly")
        return value if value.device == like.device else value.to(like.device)
    return float(value)


def shape_of(*values) -> torch.Size:
    """Broadcast shape of the tensor values among ``values`` (floats count as scalars)."""
    return broadcast_shapes(*[v.shape for v in values if isinstance(v, Tensor)])


def check_xu(x: Tensor, u: Tensor, n: int, m: int, owner: str) -> None:
    if not isinstance(x, Tensor) or not isinstance(u, Tensor):
        raise TypeError(f"{owner}: x and u must be tensors")
    if x.shape[-1:] != (n,):
        raise ValueError(f"{owner}: x must have shape (*B, {n}), got {tuple(x.shape)}")
    if u.shape[-1:] != (m,):
        raise ValueError(f"{owner}: u must have shape (*B, {m}), got {tuple(u.shape)}")
    if x.dtype != u.dtype:
        raise TypeError(f"{owner}: x and u must share a dtype, got {x.dtype} and {u.dtype}")


def euler_step(x: Tensor, acc: Tensor, dt: Tensor | float) -> Tensor:
    """Semi-implicit Euler step of ``x = [q, v]`` given the acceleration ``acc`` (same shape as ``v``)."""
    k = acc.shape[-1]
    q, v = x[..., :k], x[..., k:]
    if isinstance(dt, Tensor):
        dt = dt.unsqueeze(-1)
        v1 = v + dt * acc
        return torch.cat([q + dt * v1, v1], dim=-1)
    v1 = torch.add(v, acc, alpha=dt)  # a float step: one fused kernel per line, no scalar tensor
    return torch.cat([torch.add(q, v1, alpha=dt), v1], dim=-1)


def euler_jacobian(a_q: Tensor, a_v: Tensor, a_u: Tensor, dt: Tensor | float) -> tuple[Tensor, Tensor]:
    """``(A, B)`` of the semi-implicit Euler step from ``a_q, a_v (*B, k, k)`` and ``a_u (*B, k, m)``."""
    k = a_q.shape[-1]
    eye = torch.eye(k, dtype=a_q.dtype, device=a_q.device)
    if isinstance(dt, Tensor):
        dt = dt[..., None, None]
    bs = broadcast_shapes(a_q.shape, a_v.shape)
    a_q, a_v = a_q.expand(bs), a_v.expand(bs)
    Av = torch.cat([dt * a_q, eye + dt * a_v], dim=-1)
    Aq = torch.cat([eye.expand(bs), torch.zeros_like(eye).expand(bs)], dim=-1) + dt * Av
    Bv = dt * a_u
    Bq = dt * Bv
    return torch.cat([Aq, Av], dim=-2), torch.cat([Bq, Bv], dim=-2)
