"""Counter-based random numbers: the initial state of episode ``k`` of an environment with key ``s`` is a
pure function of ``(s, k)``.

A vector environment then needs no per-environment generator (no Python loop over environments when some
of them reset), environment ``i`` of a vector env seeded with ``s`` draws exactly what a single
environment seeded with ``s + i`` draws episode after episode, and results do not depend on the number
of environments, the device or the order of resets.  The mixing function is SplitMix64 (Steele, Lea,
Flood, *Fast splittable pseudorandom number generators*, OOPSLA 2014), computed in int64 arithmetic,
which wraps modulo 2⁶⁴ on every backend torch supports (checked against a numpy uint64 reference in the
tests).
"""

from __future__ import annotations

import torch

__all__ = ["mix64", "uniforms", "keys_of_seeds"]

def _signed(c: int) -> int:
    return c - (1 << 64) if c >= (1 << 63) else c


_GOLDEN = _signed(0x9E3779B97F4A7C15)
_M1 = _signed(0xBF58476D1CE4E5B9)
_M2 = _signed(0x94D049BB133111EB)


def _srl(z: torch.Tensor, s: int) -> torch.Tensor:
    """Logical right shift of int64 bit patterns (torch's ``>>`` is arithmetic)."""
    return (z >> s) & ((1 << (64 - s)) - 1)


def mix64(z: torch.Tensor) -> torch.Tensor:
    """SplitMix64's output function of ``z + golden`` on int64 bit patterns (a bijection of 2⁶⁴)."""
    z = z + _GOLDEN
    z = (z ^ _srl(z, 30)) * _M1
    z = (z ^ _srl(z, 27)) * _M2
    return z ^ _srl(z, 31)


def uniforms(key: torch.Tensor, episode: torch.Tensor, k: int, dtype: torch.dtype) -> torch.Tensor:
    """``(N, k)`` uniforms in ``[0, 1)`` for environments with int64 ``key (N,)`` at episode ``(N,)``.

    Each value has 53 random bits (rounded to ``dtype`` afterwards, so a float32 value may round up to
    1.0 only if ``dtype`` cannot represent the 53-bit number; callers map [0, 1] affinely).
    """
    base = mix64(key ^ mix64(episode))
    # j·golden (mod 2⁶⁴) for j = 1..k as a table of constants: written as ``arange * golden`` (or as a
    # cumulative sum, which inductor rewrites into it), inductor folds it into its int32 index arithmetic
    # and Triton refuses the 64-bit constant there (measured on an H200, torch 2.11: "Scalar
    # -7046029254386353131 is out of range for type int32")
    steps = torch.tensor([_signed(j * (_GOLDEN % (1 << 64)) % (1 << 64)) for j in range(1, k + 1)],
                         dtype=torch.int64, device=key.device)
    z = mix64(base.unsqueeze(-1) + steps)
    return (_srl(z, 11).to(torch.float64) * 2.0 ** -53).to(dtype)


def keys_of_seeds(seeds: torch.Tensor) -> torch.Tensor:
    """int64 keys of non-negative integer seeds ``(N,)`` (seeds are taken modulo 2⁶²)."""
    return mix64(torch.remainder(seeds.to(torch.int64), 2**62))
