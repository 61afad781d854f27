"""Basis functions for trajectories and control primitives (seed 004 §6).

Every constructor returns the dictionary ``φ`` as a ``(T, K)`` matrix (``T`` time samples, ``K``
functions), evaluated on ``t`` = ``T`` points linearly spaced in ``[0, 1]`` or on a given tensor of
phases ``t`` (any shape ``(*S,)``, then the result is ``(*S, K)``).  A signal is ``x = φ w`` (Eq. 23);
multidimensional signals use ``Ψ = φ ⊗ I_D`` (Eq. 29, :func:`multidim`).  Weights are fitted in batch
(Eq. 47-48, :func:`fit`) or recursively, one point at a time (Algorithm 2, :func:`recursive_fit`).
"""

from __future__ import annotations

import math

import torch

__all__ = ["phases", "piecewise", "rbf", "bernstein", "fourier", "multidim", "fit", "recursive_fit"]


def phases(T: int, dtype: torch.dtype = torch.float64,
           device: torch.device | str | None = None) -> torch.Tensor:
    """``T`` points linearly spaced in ``[0, 1]`` (a single point is ``0``)."""
    if not isinstance(T, int) or T < 1:
        raise ValueError(f"phases: 'T' must be a positive int, got {T!r}")
    return torch.linspace(0.0, 1.0, T, dtype=dtype, device=device)


def _t(t, dtype, device) -> torch.Tensor:
    if isinstance(t, torch.Tensor):
        if not t.dtype.is_floating_point:
            raise TypeError(f"basis: phases 't' must be a floating tensor, got {t.dtype}")
        return t
    return phases(t, dtype, device)


def _check_K(K: int, fn: str) -> None:
    if not isinstance(K, int) or isinstance(K, bool) or K < 1:
        raise ValueError(f"{fn}: 'K' (number of basis functions) must be a positive int, got {K!r}")


def piecewise(t: int | torch.Tensor, K: int, dtype: torch.dtype = torch.float64,
              device: torch.device | str | None = None) -> torch.Tensor:
    """Piecewise-constant basis (Eq. 24): ``φ = I_K ⊗ 1_{T/K}`` when ``K`` divides ``T``; in general
    sample ``t`` belongs to segment ``min(⌊t K⌋, K-1)``."""
    _check_K(K, "piecewise")
    if isinstance(t, int) and t % K == 0:
        return torch.kron(torch.eye(K, dtype=dtype, device=device),
                          torch.ones(t // K, 1, dtype=dtype, device=device))
    tt = _t(t, dtype, device)
    if isinstance(t, int):
        # equal-length segments over sample indices
        idx = torch.div(torch.arange(t, device=device) * K, t, rounding_mode="floor")
    else:
        idx = (tt * K).floor().clamp(0, K - 1).long()
    return torch.nn.functional.one_hot(idx, K).to(tt.dtype)


def rbf(t: int | torch.Tensor, K: int, bandwidth: float | None = None, normalized: bool = False,
        dtype: torch.dtype = torch.float64, device: torch.device | str | None = None) -> torch.Tensor:
    """Gaussian radial basis functions (Eq. 25): ``φ = exp(-λ E ⊙ E)``, ``E = t 1ᵀ - 1 μˢᵀ`` with centers
    ``μˢ`` linearly spaced in ``[0, 1]``.

    Args:
        bandwidth: ``λ``; default ``(K-1)² `` (neighbouring functions cross at ``exp(-1/4)``), ``1`` if K=1.
        normalized: rescale each row to sum to one (the rescaled form after Eq. 25).
    """
    _check_K(K, "rbf")
    tt = _t(t, dtype, device)
    lam = float((K - 1) ** 2 if K > 1 else 1.0) if bandwidth is None else float(bandwidth)
    if lam <= 0:
        raise ValueError(f"rbf: 'bandwidth' must be positive, got {bandwidth!r}")
    mu = torch.linspace(0.0, 1.0, K, dtype=tt.dtype, device=tt.device) if K > 1 else \
        torch.full((1,), 0.5, dtype=tt.dtype, device=tt.device)
    E = tt.unsqueeze(-1) - mu
    phi = torch.exp(-lam * E * E)
    return phi / phi.sum(-1, keepdim=True) if normalized else phi


def bernstein(t: int | torch.Tensor, K: int, dtype: torch.dtype = torch.float64,
              device: torch.device | str | None = None) -> torch.Tensor:
    """Bernstein polynomials of degree ``K-1`` (Eq. 26): ``φ_k = C(K-1, k-1) (1-t)^{K-k} t^{k-1}``."""
    _check_K(K, "bernstein")
    tt = _t(t, dtype, device).unsqueeze(-1)
    k = torch.arange(K, dtype=tt.dtype, device=tt.device)
    binom = torch.tensor([math.comb(K - 1, i) for i in range(K)], dtype=tt.dtype, device=tt.device)
    return binom * (1 - tt) ** (K - 1 - k) * tt ** k


def fourier(t: int | torch.Tensor, K: int, complex: bool = False, dtype: torch.dtype = torch.float64,
            device: torch.device | str | None = None) -> torch.Tensor:
    """Fourier basis.

    ``complex=False`` (default): the cosine basis for real, even signals (Eq. 28),
    ``φ = cos(2π t kᵀ)`` with ``k = 0 .. K-1``, shape ``(T, K)``.
    ``complex=True``: Eq. 27, ``φ = exp(2π i t k̃ᵀ)`` with ``k̃ = -K+1 .. K-1``, shape ``(T, 2K-1)``
    (a complex tensor).
    """
    _check_K(K, "fourier")
    tt = _t(t, dtype, device).unsqueeze(-1)
    if complex:
        k = torch.arange(-K + 1, K, dtype=tt.dtype, device=tt.device)
        return torch.exp(2j * math.pi * tt * k)
    k = torch.arange(K, dtype=tt.dtype, device=tt.device)
    return torch.cos(2 * math.pi * tt * k)


def multidim(phi: torch.Tensor, D: int, coordination: torch.Tensor | None = None) -> torch.Tensor:
    """``Ψ = φ ⊗ I_D`` (Eq. 29), or ``φ ⊗ C`` with a coordination matrix ``C (D, d)``: ``(T D, K d)``,
    for time-major stacked signals ``x = [x_0; x_1; ...]``."""
    C = torch.eye(D, dtype=phi.dtype, device=phi.device) if coordination is None else coordination
    if C.shape[0] != D:
        raise ValueError(f"multidim: 'coordination' must have shape ({D}, d), got {tuple(C.shape)}")
    return torch.kron(phi, C)


def fit(Psi: torch.Tensor, x: torch.Tensor, ridge: float = 0.0) -> torch.Tensor:
    """Least-squares weights ``ŵ = (ΨᵀΨ + λI)⁻¹ Ψᵀ x`` (Eq. 47-48), batched over ``x (*B, T)``."""
    if Psi.shape[-2] != x.shape[-1]:
        raise ValueError(f"fit: 'x' must have shape (*B, {Psi.shape[-2]}) to match Psi {tuple(Psi.shape)}, "
                         f"got {tuple(x.shape)}")
    G = Psi.mT @ Psi
    if ridge:
        G = G + ridge * torch.eye(G.shape[-1], dtype=G.dtype, device=G.device)
    rhs = (Psi.mT @ x.unsqueeze(-1))
    return torch.linalg.solve(G, rhs).squeeze(-1)


def recursive_fit(Psi: torch.Tensor, x: torch.Tensor, ridge: float, w0: torch.Tensor | None = None
                  ) -> torch.Tensor:
    """Recursive least squares (Algorithm 2, Eq. 51-57): the rows of ``Psi`` arrive one at a time.

    Starts from ``B̃ = I / λ`` (``ridge = λ > 0``) and ``w = w0`` (zeros), and returns the same weights as
    :func:`fit` with the same ridge (for ``w0 = 0``).  Batched over ``x (*B, T)``.
    """
    if ridge <= 0:
        raise ValueError(f"recursive_fit: 'ridge' must be positive (B̃ starts at I/ridge), got {ridge!r}")
    K = Psi.shape[-1]
    dt, dev = Psi.dtype, Psi.device
    Binv = torch.eye(K, dtype=dt, device=dev) / ridge
    w = torch.zeros(*x.shape[:-1], K, dtype=dt, device=dev) if w0 is None else w0.clone()
    for i in range(Psi.shape[-2]):
        v = Psi[..., i:i + 1, :]  # (1, K)
        Bv = Binv @ v.mT
        Kg = Bv / (1.0 + (v @ Bv))  # Kalman gain, Eq. 57 (scalar innovation)
        Binv = Binv - Kg @ v @ Binv
        w = w + Kg.squeeze(-1) * (x[..., i:i + 1] - (w * v.squeeze(-2)).sum(-1, keepdim=True))
    return w
