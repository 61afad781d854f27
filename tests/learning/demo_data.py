"""Synthetic demonstration data shared by the learning tests (no test here)."""

import math

import torch

__all__ = ["smooth_demos"]


def smooth_demos(N=6, T=30, D=2, b=(), seed=0, dtype=torch.float64):
    """Smooth random demos ``(*b, N, T, D)``: a common curve plus per-demo low-frequency variations."""
    g = torch.Generator().manual_seed(seed)
    s = torch.linspace(0, 1, T, dtype=torch.float64)
    base = torch.stack([torch.sin(math.pi * s), s ** 2], -1)[:, :D]
    c = torch.randn(*b, N, 3, D, generator=g, dtype=torch.float64) * 0.1
    var = sum(c[..., k:k + 1, :] * torch.sin((k + 1) * math.pi * s)[:, None] for k in range(3))
    return (base + var).to(dtype)
