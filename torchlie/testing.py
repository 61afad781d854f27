"""Public helpers for testing code built on torchlie: edge-case samplers and derivative checkers.

Nothing here is used by the library itself; it only depends on torch. Typical use::

    th = angles_near_edges(torch.float64)                   # 0, 1e-9, ..., π − 1e-9, π
    J = fd_jacobian(lambda d: so2.log(so2.exp(x + d)), torch.zeros(1, dtype=torch.float64))
    check_batching(se2.exp, (x,), (1,))                       # batched == flattened == per-sample loop
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import torch

__all__ = [
    "angles_near_edges",
    "sample_angles",
    "random_unit_vectors",
    "rotation_vectors",
    "fd_jacobian",
    "check_batching",
]


def angles_near_edges(dtype: torch.dtype = torch.float64, device=None) -> torch.Tensor:
    """Rotation angles in ``[0, π]`` at and around the places closed forms break, shape ``(N,)``.

    Exactly 0 and π, within 1e-12 … 1e-3 of both, and values straddling the usual small-angle switches
    (1e-3, 1e-2, 0.05, 0.1, 0.3, 0.5, 1). Values that round to π or 0 in ``dtype`` are kept (they are edges
    too). Negate them for signed angles.
    """
    near = [1e-12, 1e-9, 1e-6, 1e-4, 1e-3]
    mid = [1e-2, 3e-2, 0.05, 0.1, 0.2999, 0.3, 0.3001, 0.5, 0.9999, 1.0, 1.0001, 2.0, 3.0]
    vals = [0.0] + near + mid + [math.pi - e for e in reversed(near)] + [math.pi]
    return torch.tensor(vals, dtype=dtype, device=device)


def sample_angles(n: int, generator: torch.Generator | None = None, dtype: torch.dtype = torch.float64,
                  device=None) -> torch.Tensor:
    """``n`` random angles in ``[0, π]``: a third uniform in ``[0, π)``, a third at ``10^U(−12, −1)`` from 0,
    the rest at ``10^U(−12, −1)`` below π (clusters near both singular points). Shape ``(n,)``."""
    if device is None and generator is not None:
        device = generator.device
    k = n // 3
    u = torch.rand(n, generator=generator, dtype=torch.float64, device=device)
    e = 10.0 ** (-12 + 11 * torch.rand(n, generator=generator, dtype=torch.float64, device=device))
    idx = torch.arange(n, device=device)
    th = torch.where(idx < k, u * math.pi, torch.where(idx < 2 * k, e, math.pi - e))
    return th.to(dtype)


def random_unit_vectors(n: int, dim: int = 3, generator: torch.Generator | None = None,
                        dtype: torch.dtype = torch.float64, device=None) -> torch.Tensor:
    """``n`` unit vectors ``(n, dim)`` uniform on the sphere S^{dim−1}."""
    if device is None and generator is not None:
        device = generator.device
    v = torch.randn(n, dim, generator=generator, dtype=torch.float64, device=device)
    v = v / torch.linalg.vector_norm(v, dim=-1, keepdim=True).clamp_min(1e-300)
    return v.to(dtype)


def rotation_vectors(n: int, generator: torch.Generator | None = None, dtype: torch.dtype = torch.float64,
                     device=None) -> torch.Tensor:
    """Rotation vectors ``(m, 3)``: every :func:`angles_near_edges` angle and ``n`` :func:`sample_angles`,
    each times a random unit axis (``m = n + len(angles_near_edges())``)."""
    th = torch.cat((angles_near_edges(torch.float64, device),
                    sample_angles(n, generator, torch.float64, device)))
    axis = random_unit_vectors(th.shape[0], 3, generator, torch.float64, device)
    return (th.unsqueeze(-1) * axis).to(dtype)


def fd_jacobian(f: Callable[[torch.Tensor], torch.Tensor], x: torch.Tensor,
                eps: float = 1e-6) -> torch.Tensor:
    """Central finite-difference Jacobian of ``f`` at ``x``, shape ``(*f(x).shape, *x.shape)``.

    One pair of evaluations per entry of ``x`` (a Python loop: meant for small test inputs). Use float64.
    """
    x = x.detach()
    y0 = f(x)
    cols = []
    flat = x.reshape(-1)
    for i in range(flat.numel()):
        d = torch.zeros_like(flat)
        d[i] = eps
        d = d.reshape(x.shape)
        cols.append((f(x + d) - f(x - d)) / (2 * eps))
    J = torch.stack(cols, dim=-1) if cols else y0.new_zeros(*y0.shape, 0)
    return J.reshape(*y0.shape, *x.shape)


def check_batching(fn: Callable[..., torch.Tensor], args: Sequence[torch.Tensor], event_dims: Sequence[int],
                   atol: float = 1e-12, rtol: float = 0.0) -> None:
    """Assert ``fn`` on a batch == ``fn`` on the flattened batch == ``fn`` per sample in a loop.

    ``args`` share the leading batch shape ``B`` (at least one dim); ``event_dims[i]`` is the number of
    trailing (non-batch) dims of ``args[i]``. ``fn`` must return one tensor of shape ``(*B, ...)``.
    Raises ``AssertionError`` naming the failing comparison.
    """
    if len(args) != len(event_dims):
        raise ValueError("check_batching: 'args' and 'event_dims' must have the same length")
    batch = args[0].shape[: args[0].dim() - event_dims[0]]
    for a, k in zip(args, event_dims):
        if a.shape[: a.dim() - k] != batch:
            raise ValueError(f"check_batching: every arg needs batch shape {tuple(batch)}, "
                             f"got {tuple(a.shape)}")
    out = fn(*args)
    n = math.prod(batch)
    flat_args = [a.reshape(n, *a.shape[a.dim() - k:]) for a, k in zip(args, event_dims)]
    flat = fn(*flat_args)
    event = out.shape[len(batch):]
    torch.testing.assert_close(flat.reshape(*batch, *event), out, atol=atol, rtol=rtol,
                               msg=lambda m: f"batched != flattened: {m}")
    loop = torch.stack([fn(*[a[i] for a in flat_args]) for i in range(n)])
    torch.testing.assert_close(loop.reshape(*batch, *event), out, atol=atol, rtol=rtol,
                               msg=lambda m: f"batched != per-sample loop: {m}")
