"""Basis functions for trajectories and control primitives (seed 004 §6).

Every constructor returns the dictionary ``φ`` as a ``(T, K)`` matrix (``T`` time samples, ``K``
functions), evaluated on ``t`` = ``T`` points linearly spaced in ``[0, 1]`` or on a given tensor of
phases ``t`` (any shape ``(*S,)``, then the result is ``(*S, K)``).  A signal is ``x = φ w`` (Eq. 23);
multidimensional signals use ``Ψ = φ ⊗ I_D`` (Eq. 29, :func:`multidim`).  Weights are fitted in batch
(Eq. 47-48, :func:`fit`) or recursively, one point at a time (Algorithm 2, :func:`recursive_fit`).

Derivatives (§6.4): ``*_deriv(t, K, order)`` returns ``d^order φ / dt^order`` with the shape of ``φ``
(``order = 0`` is the dictionary itself).  Concatenated Bézier curves (§6.5): ``φ C`` with the continuity
matrix ``C`` of Eq. (45)-(46) generalized to ``C^k`` joints (:func:`continuity_matrix`, :func:`spline`).
Multidimensional inputs (§6.3): ``Ψ(t) = φ(t_1) ⊗ φ(t_2) ⊗ … ⊗ φ(t_d)`` (Eq. 30, 33) for a batch of input
points ``t (*B, d)`` (:func:`tensor_basis`), its gradient (Eq. 35-36, :func:`tensor_basis_grad`) and the
field ``x = Ψ(t) w`` with its gradient ``∇x = ∇Ψ(t) w`` (Eq. 37, :func:`tensor_eval`, :func:`tensor_grad`).
A 1-D dictionary is passed to these as a callable ``basis(t, order=j) -> (*S, K)`` with ``t (*S,)``, e.g.
``functools.partial(bernstein_deriv, K=4)`` or ``functools.partial(spline, n_segments=5)``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import torch

__all__ = ["phases", "piecewise", "rbf", "bernstein", "fourier", "multidim", "fit", "recursive_fit",
           # derivatives of the 1-D dictionaries (§6.4)
           "piecewise_deriv", "rbf_deriv", "bernstein_deriv", "fourier_deriv",
           # polynomial form and concatenated Bézier curves / splines (Eq. 31-32, §6.5)
           "powers", "bernstein_matrix", "continuity_matrix", "concatenated_bernstein", "spline",
           # multidimensional inputs (§6.3-6.4)
           "kron_rows", "tensor_basis", "tensor_basis_grad", "tensor_eval", "tensor_grad"]


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


# --------------------------------------------------------------------------------------------------
# derivatives of the 1-D dictionaries (§6.4)
# --------------------------------------------------------------------------------------------------


def _check_order(order: int, fn: str) -> None:
    if not isinstance(order, int) or isinstance(order, bool) or order < 0:
        raise ValueError(f"{fn}: 'order' (derivative order) must be a non-negative int, got {order!r}")


def piecewise_deriv(t: int | torch.Tensor, K: int, order: int = 1, dtype: torch.dtype = torch.float64,
                    device: torch.device | str | None = None) -> torch.Tensor:
    """``d^order φ / dt^order`` of the piecewise-constant basis (Eq. 24): ``φ`` itself for ``order = 0``,
    else zero (the derivative almost everywhere; the jumps at the segment borders are not represented)."""
    _check_order(order, "piecewise_deriv")
    phi = piecewise(t, K, dtype, device)
    return phi if order == 0 else torch.zeros_like(phi)


def rbf_deriv(t: int | torch.Tensor, K: int, order: int = 1, bandwidth: float | None = None,
              normalized: bool = False, dtype: torch.dtype = torch.float64,
              device: torch.device | str | None = None) -> torch.Tensor:
    """``d^order φ / dt^order`` of the Gaussian RBFs of :func:`rbf` (Eq. 25), same arguments, ``(*S, K)``.

    ``d^n/dt^n exp(-λe²) = h_n(e) exp(-λe²)`` with ``h_0 = 1``, ``h_1 = -2λe``,
    ``h_{n+1} = -2λe h_n - 2nλ h_{n-1}`` (scaled Hermite polynomials), ``e = t - μ_k``.  The rescaled form
    ``ψ = φ / s``, ``s = Σ_k φ_k``, follows from Leibniz' rule on ``ψ s = φ``:
    ``ψ^{(n)} = (φ^{(n)} - Σ_{i=1}^{n} C(n,i) s^{(i)} ψ^{(n-i)}) / s``.
    """
    _check_order(order, "rbf_deriv")
    phi = rbf(t, K, bandwidth, False, dtype, device)
    tt = _t(t, dtype, device)
    lam = float((K - 1) ** 2 if K > 1 else 1.0) if bandwidth is None else float(bandwidth)
    mu = torch.linspace(0.0, 1.0, K, dtype=tt.dtype, device=tt.device) if K > 1 else \
        torch.full((1,), 0.5, dtype=tt.dtype, device=tt.device)
    e = tt.unsqueeze(-1) - mu
    h = [torch.ones_like(e), -2.0 * lam * e]
    for n in range(1, order):
        h.append(-2.0 * lam * e * h[n] - 2.0 * n * lam * h[n - 1])
    ders = [h[n] * phi for n in range(order + 1)]  # φ^{(n)}, n = 0..order
    if not normalized:
        return ders[order]
    sums = [d.sum(-1, keepdim=True) for d in ders]
    psi: list[torch.Tensor] = []
    for n in range(order + 1):
        acc = ders[n]
        for i in range(1, n + 1):
            acc = acc - math.comb(n, i) * sums[i] * psi[n - i]
        psi.append(acc / sums[0])
    return psi[order]


def _difference_matrix(K: int, order: int, dtype, device) -> torch.Tensor:
    """``D (K-order, K)``: ``d^order/dt^order Σ_k w_k b_{k,p}(t) = Σ_i (D w)_i b_{i,p-order}(t)``, ``p = K-1``
    (``D = p!/(p-order)! Δ^order``, the forward differences of the control points)."""
    p = K - 1
    D = torch.zeros(K - order, K, dtype=dtype, device=device)
    scale = math.factorial(p) / math.factorial(p - order)
    for l_ in range(order + 1):
        c = scale * (-1) ** (order - l_) * math.comb(order, l_)
        idx = torch.arange(K - order, device=device)
        D[idx, idx + l_] = c
    return D


def bernstein_deriv(t: int | torch.Tensor, K: int, order: int = 1, dtype: torch.dtype = torch.float64,
                    device: torch.device | str | None = None) -> torch.Tensor:
    """``d^order φ / dt^order`` of the Bernstein basis of degree ``p = K-1`` (Eq. 26), ``(*S, K)``.

    Uses ``d^j/dt^j Σ_k w_k b_{k,p} = p!/(p-j)! Σ_i (Δ^j w)_i b_{i,p-j}`` (forward differences of the control
    points), i.e. ``bernstein(t, K-j) D_j``; zero for ``order ≥ K``.
    """
    _check_K(K, "bernstein_deriv")
    _check_order(order, "bernstein_deriv")
    if order == 0:
        return bernstein(t, K, dtype, device)
    tt = _t(t, dtype, device)
    if order >= K:
        return torch.zeros(*tt.shape, K, dtype=tt.dtype, device=tt.device)
    return bernstein(tt, K - order) @ _difference_matrix(K, order, tt.dtype, tt.device)


def fourier_deriv(t: int | torch.Tensor, K: int, order: int = 1, complex: bool = False,
                  dtype: torch.dtype = torch.float64, device: torch.device | str | None = None
                  ) -> torch.Tensor:
    """``d^order φ / dt^order`` of the Fourier bases of :func:`fourier` (Eq. 27-28), same shapes:
    ``(2πk)^n cos(2πkt + nπ/2)`` for the cosine basis, ``(2πik)^n exp(2πikt)`` for the complex one."""
    _check_K(K, "fourier_deriv")
    _check_order(order, "fourier_deriv")
    tt = _t(t, dtype, device).unsqueeze(-1)
    if complex:
        k = torch.arange(-K + 1, K, dtype=tt.dtype, device=tt.device)
        return (2j * math.pi * k) ** order * torch.exp(2j * math.pi * tt * k)
    k = torch.arange(K, dtype=tt.dtype, device=tt.device)
    return (2 * math.pi * k) ** order * torch.cos(2 * math.pi * tt * k + order * math.pi / 2)


# --------------------------------------------------------------------------------------------------
# polynomial form, concatenated Bézier curves and splines (Eq. 31-32, §6.5)
# --------------------------------------------------------------------------------------------------


def powers(t: int | torch.Tensor, K: int, order: int = 0, dtype: torch.dtype = torch.float64,
           device: torch.device | str | None = None) -> torch.Tensor:
    """``T(t) = [1, t, …, t^{K-1}]`` (Eq. 31-32) or its ``order``-th derivative
    (``order = 1``: ``[0, 1, 2t, 3t², …]``), ``(*S, K)``."""
    _check_K(K, "powers")
    _check_order(order, "powers")
    tt = _t(t, dtype, device).unsqueeze(-1)
    j = torch.arange(K, dtype=tt.dtype, device=tt.device)
    fall = torch.ones(K, dtype=tt.dtype, device=tt.device)  # j (j-1) … (j-order+1)
    for i in range(order):
        fall = fall * (j - i)
    return fall * tt ** (j - order).clamp(min=0)


def bernstein_matrix(K: int, dtype: torch.dtype = torch.float64,
                     device: torch.device | str | None = None) -> torch.Tensor:
    """``B (K, K)`` with ``bernstein(t, K) = powers(t, K) B`` (the ``T(t) B`` form of Eq. 31-32):
    ``B[k+i, k] = C(p, k) C(p-k, i) (-1)^i``, ``p = K-1``."""
    _check_K(K, "bernstein_matrix")
    p = K - 1
    B = torch.zeros(K, K, dtype=dtype, device=device)
    for k in range(K):
        for i in range(K - k):
            B[k + i, k] = math.comb(p, k) * math.comb(p - k, i) * (-1) ** i
    return B


def _check_segments(n_segments: int, degree: int, fn: str) -> None:
    if not isinstance(n_segments, int) or isinstance(n_segments, bool) or n_segments < 1:
        raise ValueError(f"{fn}: 'n_segments' must be a positive int, got {n_segments!r}")
    if not isinstance(degree, int) or isinstance(degree, bool) or degree < 0:
        raise ValueError(f"{fn}: 'degree' must be a non-negative int, got {degree!r}")


def continuity_matrix(n_segments: int, degree: int = 3, continuity: int | None = 1,
                      dtype: torch.dtype = torch.float64, device: torch.device | str | None = None
                      ) -> torch.Tensor:
    """The continuity matrix ``C (S (p+1), K_v)`` of §6.5 (Eq. 45-46): the control points of ``S``
    concatenated Bézier curves of degree ``p`` are ``w = C v``, with ``v`` the free weights.

    At each joint, the derivatives of order ``0..continuity`` of the curve (w.r.t. the global phase, with
    segments of equal length) agree, which fixes the first ``continuity + 1`` control points of the next
    segment from the last ones of the previous segment:
    ``w'_j = Σ_{l≤j} (-1)^{j-l} C(j,l) w_{p-j+l} - Σ_{l<j} (-1)^{j-l} C(j,l) w'_l``.
    For ``p = 3``, ``continuity = 1`` this is the pattern ``[[1, 0], [0, 1], [0, 1], [-1, 2]]`` of
    Eq. (45)-(46) (``w_4 = w_5``, ``w_6 = 2 w_5 - w_3``), and ``K_v = p + 1 + (S-1)(p - continuity)``.
    ``continuity=None``: no constraint (``C = I``).
    """
    fn = "continuity_matrix"
    _check_segments(n_segments, degree, fn)
    p = degree
    if continuity is None:
        return torch.eye(n_segments * (p + 1), dtype=dtype, device=device)
    if not isinstance(continuity, int) or isinstance(continuity, bool) or not 0 <= continuity <= p:
        raise ValueError(f"{fn}: 'continuity' must be None or an int in [0, degree={p}], got {continuity!r}")
    k = continuity
    Kv = p + 1 + (n_segments - 1) * (p - k)
    # rows as Python float lists (small, exact integer arithmetic), one tensor at the end
    rows: list[list[float]] = [[1.0 if j == i else 0.0 for j in range(Kv)] for i in range(p + 1)]
    nxt = p + 1  # next free weight
    for _ in range(1, n_segments):
        prev = rows[-(p + 1):]
        new: list[list[float]] = []
        for j in range(k + 1):
            r = [0.0] * Kv
            for l_ in range(j + 1):
                c = (-1) ** (j - l_) * math.comb(j, l_)
                r = [ri + c * pi for ri, pi in zip(r, prev[p - j + l_])]
                if l_ < j:
                    r = [ri - c * ni for ri, ni in zip(r, new[l_])]
            new.append(r)
        for _j in range(k + 1, p + 1):
            new.append([1.0 if i == nxt else 0.0 for i in range(Kv)])
            nxt += 1
        rows.extend(new)
    return torch.tensor(rows, dtype=dtype, device=device)


def concatenated_bernstein(t: int | torch.Tensor, n_segments: int, degree: int = 3, order: int = 0,
                           dtype: torch.dtype = torch.float64, device: torch.device | str | None = None
                           ) -> torch.Tensor:
    """``S`` Bernstein dictionaries of degree ``p`` side by side (§6.5, before the constraints):
    ``(*T, S (p+1))``.

    Sample ``t`` lies in segment ``s = min(⌊t S⌋, S-1)`` (clamped at ``0``) with local phase ``τ = t S - s``;
    its row holds ``d^order b(τ)/dt^order = S^order d^order b/dτ^order`` in block ``s`` and zeros elsewhere.
    Outside ``[0, 1]`` the end segments are extrapolated.
    """
    fn = "concatenated_bernstein"
    _check_segments(n_segments, degree, fn)
    _check_order(order, fn)
    tt = _t(t, dtype, device)
    S = n_segments
    s = (tt * S).floor().clamp(0, S - 1)
    tau = tt * S - s
    local = bernstein_deriv(tau, degree + 1, order) * float(S) ** order  # (*T, p+1)
    idx = torch.nan_to_num(s, nan=0.0).long()  # a NaN phase gives a NaN row (through τ), not an index error
    mask = torch.nn.functional.one_hot(idx, S).to(tt.dtype)  # (*T, S)
    return (mask.unsqueeze(-1) * local.unsqueeze(-2)).flatten(-2)


def spline(t: int | torch.Tensor, n_segments: int, degree: int = 3, continuity: int | None = 1,
           order: int = 0, dtype: torch.dtype = torch.float64, device: torch.device | str | None = None
           ) -> torch.Tensor:
    """Concatenated Bézier curves with ``C^continuity`` joints: ``φ C`` (§6.5, Eq. 45-46), ``(*T, K_v)``
    (``order``: the ``order``-th derivative w.r.t. ``t``).  A signal is ``x = φ C v``; the control points of
    the segments are ``w = C v`` (:func:`continuity_matrix`).  As a ``basis`` callable:
    ``functools.partial(spline, n_segments=S, continuity=k)``."""
    phi = concatenated_bernstein(t, n_segments, degree, order, dtype, device)
    return phi @ continuity_matrix(n_segments, degree, continuity, phi.dtype, phi.device)


# --------------------------------------------------------------------------------------------------
# multidimensional inputs (§6.3-6.4)
# --------------------------------------------------------------------------------------------------


def kron_rows(*phis: torch.Tensor) -> torch.Tensor:
    """Row-wise Kronecker product ``φ_1 ⊗ φ_2 ⊗ … ⊗ φ_d`` of ``φ_i (*B_i, K_i)`` (Eq. 30, 33), batch dims
    broadcast: ``(*B, K_1 K_2 … K_d)``, index ``(k_1, …, k_d)`` at ``k_1 K_2…K_d + … + k_d`` (the order of
    ``torch.kron``; the first input varies slowest)."""
    if not phis:
        raise ValueError("kron_rows: expected at least one basis matrix")
    out = phis[0]
    for ph in phis[1:]:
        out = (out.unsqueeze(-1) * ph.unsqueeze(-2)).flatten(-2)
    return out


_BasisFn = Callable[..., torch.Tensor]


def _bases(x: torch.Tensor, basis, fn: str) -> list:
    if not isinstance(x, torch.Tensor) or not x.dtype.is_floating_point or x.dim() < 1 or x.shape[-1] < 1:
        got = (f"{x.dtype} tensor of shape {tuple(x.shape)}" if isinstance(x, torch.Tensor)
               else type(x).__name__)
        raise ValueError(f"{fn}: 'x' must be a floating tensor of input points (*B, d), got {got}")
    d = x.shape[-1]
    if callable(basis):
        return [basis] * d
    if isinstance(basis, Sequence) and len(basis) == d and all(callable(b) for b in basis):
        return list(basis)
    raise TypeError(f"{fn}: 'basis' must be a callable basis(t, order=j) or a sequence of {d} such callables "
                    f"(one per input dimension of x (*B, {d}))")


def tensor_basis(x: torch.Tensor, basis: _BasisFn | Sequence[_BasisFn], orders: Sequence[int] | None = None
                 ) -> torch.Tensor:
    """``Ψ(x) = φ(x_1) ⊗ φ(x_2) ⊗ … ⊗ φ(x_d)`` (Eq. 30, 33) at input points ``x (*B, d)`` in ``[0, 1]^d``.

    Args:
        x: ``(*B, d)`` input points.
        basis: a 1-D dictionary ``basis(t, order=j) -> (*S, K)`` used for every input, or one per input.
        orders: optional derivative order per input (``∂^{Σ orders} Ψ / ∂x_1^{o_1} … ∂x_d^{o_d}``, Eq. 35).

    Returns:
        ``(*B, P)``, ``P = K_1 … K_d``.  ``Ψ(x) w`` with ``w (*, P)`` (a flattened coefficient tensor
        ``(K_1, …, K_d)``) is the field; ``⊗ I_{d_out}`` (Eq. 33-34) is a trailing output dim on ``w``.
    """
    bases = _bases(x, basis, "tensor_basis")
    d = x.shape[-1]
    orders = [0] * d if orders is None else list(orders)
    if len(orders) != d:
        raise ValueError(f"tensor_basis: 'orders' must have one entry per input dimension ({d}), "
                         f"got {orders}")
    return kron_rows(*(b(x[..., i], order=o) for i, (b, o) in enumerate(zip(bases, orders))))


def tensor_basis_grad(x: torch.Tensor, basis: _BasisFn | Sequence[_BasisFn]) -> torch.Tensor:
    """``∇Ψ(x) (*B, d, P)``: row ``i`` is ``∂Ψ/∂x_i = φ(x_1) ⊗ … ⊗ φ'(x_i) ⊗ … ⊗ φ(x_d)`` (Eq. 35), the rows
    stacked as in Eq. (36)."""
    bases = _bases(x, basis, "tensor_basis_grad")
    d = x.shape[-1]
    phi0 = [b(x[..., i], order=0) for i, b in enumerate(bases)]
    phi1 = [b(x[..., i], order=1) for i, b in enumerate(bases)]
    return torch.stack([kron_rows(*(phi1[j] if j == i else phi0[j] for j in range(d))) for i in range(d)], -2)


def _check_w(x: torch.Tensor, w: torch.Tensor, P: int, fn: str) -> None:
    if not isinstance(w, torch.Tensor) or w.dim() < 1 or w.shape[-1] != P:
        got = tuple(w.shape) if isinstance(w, torch.Tensor) else type(w).__name__
        raise ValueError(f"{fn}: 'w' must have shape (*B, {P}) (the flattened coefficients of the tensor "
                         f"basis), got {got}")
    if w.dtype != x.dtype:
        raise TypeError(f"{fn}: 'w' has dtype {w.dtype} but 'x' has {x.dtype}")


def tensor_eval(x: torch.Tensor, w: torch.Tensor, basis: _BasisFn | Sequence[_BasisFn]) -> torch.Tensor:
    """The field ``f(x) = Ψ(x) w`` (§6.3) at ``x (*B, d)`` with coefficients ``w (*B_w, P)`` (batch dims
    broadcast): ``(*B',)``."""
    Psi = tensor_basis(x, basis)
    _check_w(x, w, Psi.shape[-1], "tensor_eval")
    return (Psi * w).sum(-1)


def tensor_grad(x: torch.Tensor, w: torch.Tensor, basis: _BasisFn | Sequence[_BasisFn]
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """``f(x) = Ψ(x) w`` and its gradient ``∇f(x) = ∇Ψ(x) w`` (Eq. 37): ``((*B',), (*B', d))``."""
    bases = _bases(x, basis, "tensor_grad")
    d = x.shape[-1]
    phi0 = [b(x[..., i], order=0) for i, b in enumerate(bases)]
    phi1 = [b(x[..., i], order=1) for i, b in enumerate(bases)]
    Psi = kron_rows(*phi0)
    _check_w(x, w, Psi.shape[-1], "tensor_grad")
    grads = [(kron_rows(*(phi1[j] if j == i else phi0[j] for j in range(d))) * w).sum(-1) for i in range(d)]
    return (Psi * w).sum(-1), torch.stack(grads, -1)
