"""Geodesics of a smoothly varying metric ``G(x)`` on Rⁿ (seed 004 §12.6, non-homogeneous manifolds).

A symmetric positive-definite matrix field ``G(x)`` weighs displacements by ``c(Δx) = Δxᵀ G(x) Δx``
(§12.6: a mass-inertia matrix gives kinetic energy, a stiffness or manipulability ellipsoid gives other
metrics) and makes Rⁿ a Riemannian manifold whose curvature varies from point to point, so there is no
closed-form Exp/Log: geodesics are computed iteratively.

A path ``x_0, ..., x_N`` (``N = steps`` segments, endpoints fixed) is discretized with the metric at the
segment midpoints ``x̄_k = (x_k + x_{k+1}) / 2``:

    E(x) = Σ_{k=0}^{N-1} Δx_kᵀ G(x̄_k) Δx_k,        Δx_k = x_{k+1} - x_k          (path_energy)
    L(x) = Σ_{k=0}^{N-1} (Δx_kᵀ G(x̄_k) Δx_k)^{1/2}                               (path_length)

(``N · E ≈ ∫_0^1 ẋᵀ G(x) ẋ dt`` for a path parameterized on ``[0, 1]``; ``L² ≤ N E`` with equality for a
path of constant metric speed).  :func:`geodesic` minimizes ``E`` over the interior points — its minimizers
are the constant-speed geodesics, which also minimize ``L`` — by damped Newton: the exact Hessian of ``E``
is block tridiagonal (each term couples two consecutive points); its ``2n × 2n`` segment blocks are taken by
``2n`` autograd passes over all segments and problems at once, assembled, and the step
``(H + μ d I) Δx = -∇E`` (``d``: the mean of diag ``H``; ``μ`` Levenberg-Marquardt, grown where ``H`` is not
positive definite or no step size lowers ``E``) is followed by a backtracking line search (``α = 1, ½, ...``
all at once; a full step whose predicted decrease is at the rounding level of ``E`` is taken as long as ``E``
does not rise above that level).

Status is a certificate, per element: ``CONVERGED`` where, at the returned path, the exact Hessian ``H`` is
positive definite (a strict local minimum, not a saddle) and the Newton decrement is small relative to the
energy, ``(∇Eᵀ H⁻¹ ∇E / E)^{1/2} ≤ tol`` (invariant to scaling ``G`` and to affine changes of coordinates;
about the relative distance to the optimum in the energy norm; default ``tol`` 1e-9 in float64, 1e-4 in
float32; a path with ``E = 0``, ``x0 = x1``, is certified), else ``MAX_ITERATIONS``,
``STALLED`` (``μ`` past ``mu_max``) or ``NONFINITE`` (NaN/inf in that element's endpoints or initial path,
or in ``G``'s values there: that element's outputs are NaN; the others are solved as if alone).

The metric is any callable ``G(x (*, n)) -> (*, n, n)``, symmetric positive definite, evaluated pointwise
(``G(x)[i]`` depends on ``x[i]`` only: batch dims are independent points) and twice differentiable by
autograd (torch operations only).  Differentiation: the returned path carries the implicit-function-theorem
derivative of the optimum with respect to the endpoints and to tensors ``G`` closes over (one Newton step
on the graph at the converged point, ``dx*/dθ = -H⁻¹ ∂∇E/∂θ``), its value unchanged.
"""

from __future__ import annotations

import enum
from collections.abc import Callable
from typing import NamedTuple

import torch
from torch import Tensor

from torchlie._batch import broadcast_shapes, check_same_device, check_tensor

__all__ = ["Geodesic", "GeodesicReason", "geodesic", "path_energy", "path_length"]


class GeodesicReason(enum.IntEnum):
    """Per-element outcome of :func:`geodesic` (the ``reason`` codes)."""

    CONVERGED = 0  #: gradient certified at the returned path
    MAX_ITERATIONS = 1
    STALLED = 2  #: no damping up to ``mu_max`` gave a descent step
    NONFINITE = 3  #: NaN/inf in the element's endpoints, initial path, or in G there


class Geodesic(NamedTuple):
    """Result of :func:`geodesic`.

    path ``(*B, N+1, n)`` (endpoints exact); energy, length ``(*B,)`` (:func:`path_energy`,
    :func:`path_length` of the path); converged ``(*B,)`` bool; iterations ``(*B,)`` int64; reason ``(*B,)``
    int64 (:class:`GeodesicReason`); residual ``(*B,)`` ``(∇Eᵀ H⁻¹ ∇E / E)^{1/2}`` at the returned path (inf
    where ``H`` is not positive definite).
    """

    path: Tensor
    energy: Tensor
    length: Tensor
    converged: Tensor
    iterations: Tensor
    reason: Tensor
    residual: Tensor


def _check_G(G) -> None:
    if not callable(G):
        raise TypeError(f"argument 'G' must be a callable G(x (*, n)) -> (*, n, n), got {type(G).__name__}")


def _metric(G: Callable[[Tensor], Tensor], x: Tensor, fn: str) -> Tensor:
    M = G(x)
    n = x.shape[-1]
    if not isinstance(M, Tensor) or M.shape != (*x.shape, n):
        got = tuple(M.shape) if isinstance(M, Tensor) else type(M).__name__
        raise ValueError(f"{fn}: argument 'G' must map x {tuple(x.shape)} to matrices {(*x.shape, n)}, "
                         f"got {got}")
    return M


def _segment_terms(G, a: Tensor, b: Tensor, fn: str) -> Tensor:
    """``e_k = Δx_kᵀ G(x̄_k) Δx_k (*, N)`` of segments ``a → b`` (``(*, N, n)`` each)."""
    d = b - a
    M = _metric(G, 0.5 * (a + b), fn)
    return (d.unsqueeze(-2) @ M @ d.unsqueeze(-1))[..., 0, 0]


def _check_path(path, fn: str) -> Tensor:
    x = check_tensor(path, (), "path", fn)
    if x.dim() < 2 or x.shape[-2] < 2:
        raise ValueError(f"{fn}: argument 'path' must have shape (*B, N+1, n) with N >= 1, got "
                         f"{tuple(x.shape)}")
    return x


def path_energy(G: Callable[[Tensor], Tensor], path: Tensor) -> Tensor:
    """Discretized path energy ``Σ_k Δx_kᵀ G(x̄_k) Δx_k`` ``(*B,)`` of ``path (*B, N+1, n)`` (module docstring;
    §12.6's quadratic error ``c(Δx) = Δxᵀ G(x) Δx`` summed along the path, ``G`` at the midpoints).
    Differentiable."""
    fn = "path_energy"
    _check_G(G)
    x = _check_path(path, fn)
    return _segment_terms(G, x[..., :-1, :], x[..., 1:, :], fn).sum(-1)


def path_length(G: Callable[[Tensor], Tensor], path: Tensor) -> Tensor:
    """Discretized Riemannian length ``Σ_k (Δx_kᵀ G(x̄_k) Δx_k)^{1/2}`` ``(*B,)`` of ``path (*B, N+1, n)``.
    Differentiable (a zero-length segment contributes a zero gradient)."""
    fn = "path_length"
    _check_G(G)
    x = _check_path(path, fn)
    e = _segment_terms(G, x[..., :-1, :], x[..., 1:, :], fn)
    pos = e > 0
    safe = torch.where(pos, e, torch.ones((), dtype=e.dtype, device=e.device))
    return torch.where(pos, safe.sqrt(), torch.zeros((), dtype=e.dtype, device=e.device)).sum(-1)


def _local_derivatives(G, X: Tensor, fn: str):
    """Gradient ``(*B, N-1, n)`` of ``E`` in the interior points and the blocks of
    the block-tridiagonal Hessian: ``D (*B, N-1, n, n)`` (diagonal), ``U (*B, N-2, n, n)`` (coupling
    ``x_k`` to ``x_{k+1}``), from the ``2n × 2n`` Hessians of the segment terms ``e_k(a, b)``."""
    n = X.shape[-1]
    with torch.enable_grad():
        a = X[..., :-1, :].detach().requires_grad_(True)
        b = X[..., 1:, :].detach().requires_grad_(True)
        e = _segment_terms(G, a, b, fn)
        ga, gb = torch.autograd.grad(e.sum(), (a, b), create_graph=True)
        gab = torch.cat([ga, gb], -1)  # (*B, N, 2n)
        rows = []
        for j in range(2 * n):  # column j of every segment's local Hessian at once (segments independent)
            ha, hb = torch.autograd.grad(gab[..., j].sum(), (a, b), retain_graph=True, allow_unused=True)
            ha = torch.zeros_like(a) if ha is None else ha
            hb = torch.zeros_like(b) if hb is None else hb
            rows.append(torch.cat([ha, hb], -1))
        Hs = torch.stack(rows, -1)  # (*B, N, 2n, 2n)
    ga, gb, Hs = ga.detach(), gb.detach(), Hs.detach()
    g = gb[..., :-1, :] + ga[..., 1:, :]
    Hs = 0.5 * (Hs + Hs.mT)
    D = Hs[..., :-1, n:, n:] + Hs[..., 1:, :n, :n]
    U = Hs[..., 1:-1, :n, n:]
    return g, D, U


def _assemble(D: Tensor, U: Tensor) -> Tensor:
    """Dense ``((N-1) n, (N-1) n)`` Hessian from its diagonal and upper blocks."""
    *bs, K, n, _ = D.shape
    H = D.new_zeros(*bs, K, n, K, n)
    idx = torch.arange(K, device=D.device)
    # separated advanced indices put the block index first: values (K, *B, n, n)
    H[..., idx, :, idx, :] = D.movedim(-3, 0)
    if K > 1:
        H[..., idx[:-1], :, idx[1:], :] = U.movedim(-3, 0)
        H[..., idx[1:], :, idx[:-1], :] = U.mT.movedim(-3, 0)
    return H.reshape(*bs, K * n, K * n)


def _residual(g: Tensor, H: Tensor, E: Tensor) -> Tensor:
    """``(gᵀ H⁻¹ g / E)^{1/2}`` ``(*B,)``; ``inf`` where ``H`` is not positive definite, 0 where ``g = 0``."""
    K = H.shape[-1]
    L, info = torch.linalg.cholesky_ex(H)
    pd = (info == 0) & torch.isfinite(H).flatten(-2).all(-1)
    L = torch.where(pd[..., None, None], L, torch.eye(K, dtype=H.dtype, device=H.device))
    gf = g.flatten(-2)
    w = torch.linalg.solve_triangular(L, gf.unsqueeze(-1), upper=False).squeeze(-1)
    lam2 = (w * w).sum(-1)
    zero = (gf == 0).all(-1)
    r = (lam2 / E.clamp_min(torch.finfo(E.dtype).tiny)).sqrt()
    r = torch.where(zero, torch.zeros((), dtype=g.dtype, device=g.device), r)
    return torch.where(pd, r, torch.full((), float("inf"), dtype=g.dtype, device=g.device))


def geodesic(G: Callable[[Tensor], Tensor], x0: Tensor, x1: Tensor, steps: int = 32, *,
             init: Tensor | None = None, max_iter: int = 50, tol: float | None = None,
             line_search_steps: int = 12, mu_init: float = 0.0, mu_max: float = 1e8) -> Geodesic:
    """Geodesic of the metric ``G`` from ``x0`` to ``x1`` by minimizing the discretized energy (module
    docstring; seed 004 §12.6), batched over problems.

    Args:
        G: metric field, ``G(x (*, n)) -> (*, n, n)`` symmetric positive definite, pointwise over the batch
            dims, twice differentiable by autograd.
        x0, x1: ``(*B, n)`` endpoints (broadcast against each other; same dtype and device).
        steps: ``N >= 2`` segments (``N - 1`` interior points are optimized).
        init: ``(*B, N+1, n)`` initial path (its endpoints are replaced by ``x0, x1``); default: the straight
            line ``x0 + (x1 - x0) k / N``.
        max_iter: Newton iterations at most; tol: the certificate's relative gradient tolerance (default
            ``1e-9`` float64, ``1e-4`` float32); line_search_steps: step sizes ``1, ½, ...`` tried at once.
        mu_init, mu_max: Levenberg-Marquardt damping ``μ`` (relative to the mean of diag ``H``): it grows ×10
            (from at least 1e-6) where the damped Hessian is not positive definite or no step size lowers
            ``E``, shrinks ×10 after a full step; past ``mu_max`` the element stops (``STALLED``).

    Returns:
        :class:`Geodesic` ``(path (*B, N+1, n), energy, length, converged, iterations, reason, residual)``.
    """
    fn = "geodesic"
    _check_G(G)
    x0 = check_tensor(x0, (), "x0", fn)
    if x0.dim() < 1 or x0.shape[-1] < 1:
        raise ValueError(f"{fn}: argument 'x0' must have shape (*B, n) with n >= 1, got {tuple(x0.shape)}")
    n = x0.shape[-1]
    x1 = check_tensor(x1, (n,), "x1", fn)
    check_same_device(fn, x0=x0, x1=x1)
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 2:
        raise ValueError(f"{fn}: argument 'steps' must be an int >= 2, got {steps!r}")
    if isinstance(max_iter, bool) or not isinstance(max_iter, int) or max_iter < 0:
        raise ValueError(f"{fn}: argument 'max_iter' must be a non-negative int, got {max_iter!r}")
    if tol is not None and not tol > 0:
        raise ValueError(f"{fn}: argument 'tol' must be positive, got {tol!r}")
    if isinstance(line_search_steps, bool) or not isinstance(line_search_steps, int) or line_search_steps < 1:
        raise ValueError(f"{fn}: argument 'line_search_steps' must be a positive int, got "
                         f"{line_search_steps!r}")
    if not mu_init >= 0 or not mu_max > 0:
        raise ValueError(f"{fn}: arguments 'mu_init' >= 0 and 'mu_max' > 0 expected, got {mu_init!r}, "
                         f"{mu_max!r}")
    try:
        bs = broadcast_shapes(x0.shape[:-1], x1.shape[:-1],
                              () if init is None or not isinstance(init, Tensor) else init.shape[:-2])
    except RuntimeError as e:
        raise ValueError(f"{fn}: the batch dims of 'x0' {tuple(x0.shape[:-1])}, 'x1' {tuple(x1.shape[:-1])} "
                         f"and 'init' do not broadcast ({e})") from None
    N = steps
    kw = dict(dtype=x0.dtype, device=x0.device)
    if tol is None:
        tol = 1e-4 if x0.dtype in (torch.float32, torch.float16, torch.bfloat16) else 1e-9
    a0, a1 = x0.expand(*bs, n), x1.expand(*bs, n)
    if init is None:
        s = torch.linspace(0, 1, N + 1, **kw)[:, None]
        X = a0.detach().unsqueeze(-2) + s * (a1 - a0).detach().unsqueeze(-2)
    else:
        init = check_tensor(init, (N + 1, n), "init", fn)
        check_same_device(fn, x0=x0, init=init)
        X = init.detach().expand(*bs, N + 1, n).clone()
        X[..., 0, :], X[..., -1, :] = a0.detach(), a1.detach()
    bad = ~torch.isfinite(X).flatten(-2).all(-1)
    zero = torch.zeros((), **kw)
    X = torch.where(bad[..., None, None], zero, X)  # a harmless stand-in (0 → 0, the empty path)
    K = (N - 1) * n

    def energy(P: Tensor) -> Tensor:
        with torch.no_grad():
            return _segment_terms(G, P[..., :-1, :], P[..., 1:, :], fn).sum(-1)

    E = energy(X)
    bad = bad | ~torch.isfinite(E)
    reason = torch.where(bad, int(GeodesicReason.NONFINITE), int(GeodesicReason.MAX_ITERATIONS))
    done = bad.clone()
    mu = torch.full(bs, float(mu_init), **kw)
    iters = torch.zeros(bs, dtype=torch.int64, device=x0.device)
    alphas = 0.5 ** torch.arange(line_search_steps, **kw)
    eye = torch.eye(K, **kw)
    g, D, U = _local_derivatives(G, X, fn)
    H = _assemble(D, U)
    for _ in range(max_iter):
        certified = (_residual(g, H, E) <= tol) & ~done
        reason = torch.where(certified, int(GeodesicReason.CONVERGED), reason)
        done = done | certified
        if bool(done.all()):
            break
        d = H.diagonal(dim1=-2, dim2=-1).abs().mean(-1).clamp_min(torch.finfo(X.dtype).tiny)
        L, info = torch.linalg.cholesky_ex(H + (mu * d)[..., None, None] * eye)
        ok = (info == 0) & ~done & torch.isfinite(H).flatten(-2).all(-1)
        L = torch.where(ok[..., None, None], L, eye)
        step = -torch.cholesky_solve(g.reshape(*bs, K, 1), L).reshape(*bs, N - 1, n)
        step = torch.where(ok[..., None, None], step, zero)
        a = alphas.reshape(-1, *[1] * (len(bs) + 2))
        cand = X.unsqueeze(0).expand(len(alphas), *X.shape).clone()
        cand[..., 1:-1, :] = cand[..., 1:-1, :] + a * step
        Ec = energy(cand)
        # a step whose predicted decrease -gᵀΔx is at the rounding level of E is taken in full when E does
        # not rise above that level (a strict decrease cannot be seen there; Newton converges on)
        slack = 100 * torch.finfo(X.dtype).eps * E.abs()
        near = -(g * step).flatten(-2).sum(-1) <= slack
        full_ok = torch.zeros_like(Ec, dtype=torch.bool)
        full_ok[0] = near & (Ec[0] <= E + slack)
        better = ((Ec < E) | full_ok) & ok & torch.isfinite(Ec)
        take = better.any(0)
        first = torch.where(take, better.to(torch.int64).argmax(0), 0)
        idx = first.reshape(1, *bs, 1, 1).expand(1, *X.shape)
        X = torch.where(take[..., None, None], torch.gather(cand, 0, idx)[0], X)
        E = torch.where(take, torch.gather(Ec, 0, first.reshape(1, *bs))[0], E)
        iters = iters + (~done).to(torch.int64)
        full = take & (first == 0)
        grown = torch.where(done, mu, (mu * 10).clamp_min(1e-6))
        mu = torch.where(take, torch.where(full, mu / 10, mu), grown)
        mu = torch.where(mu < 1e-12, zero, mu)
        stalled = ~done & (mu > mu_max)
        reason = torch.where(stalled, int(GeodesicReason.STALLED), reason)
        done = done | stalled
        g, D, U = _local_derivatives(G, X, fn)
        H = _assemble(D, U)
    res = _residual(g, H, E)
    certified = (res <= tol) & ~bad
    was = reason == int(GeodesicReason.CONVERGED)
    reason = torch.where(certified, int(GeodesicReason.CONVERGED),
                         torch.where(was, int(GeodesicReason.MAX_ITERATIONS), reason))
    X = _attach(G, X, a0, a1, H, bad, fn)
    nan = torch.full((), float("nan"), **kw)
    X = torch.where(bad[..., None, None], nan, X)
    e = path_energy(G, X)
    return Geodesic(X, e, path_length(G, X), reason == int(GeodesicReason.CONVERGED), iters, reason,
                    torch.where(bad, nan, res))


def _attach(G, X: Tensor, a0: Tensor, a1: Tensor, H: Tensor, bad: Tensor, fn: str) -> Tensor:
    """The path with its endpoints ``a0, a1`` (possibly carrying a graph) and, where anything requires
    grad, the implicit derivative of the interior: ``x* + (-H⁻¹ ∇E(x*; θ)) - (same, detached)``."""
    X = torch.cat([a0.unsqueeze(-2), X[..., 1:-1, :], a1.unsqueeze(-2)], -2)
    # anything with a graph: the endpoints, or tensors G closes over (G at one point tells)
    if not torch.is_grad_enabled():
        return X
    if not (a0.requires_grad or a1.requires_grad or _closes_over_graph(G, X, fn)):
        return X
    n = X.shape[-1]
    bs = X.shape[:-2]
    K = (X.shape[-2] - 2) * n
    with torch.enable_grad():
        # ∇E in the interior at the converged path, with the graph to θ and the endpoints
        inner = X[..., 1:-1, :].detach().requires_grad_(True)
        Xi = torch.cat([a0.unsqueeze(-2), inner, a1.unsqueeze(-2)], -2)
        E = _segment_terms(G, Xi[..., :-1, :], Xi[..., 1:, :], fn).sum()
        (gin,) = torch.autograd.grad(E, inner, create_graph=True)
    L, info = torch.linalg.cholesky_ex(H)
    good = (info == 0) & ~bad
    L = torch.where(good[..., None, None], L, torch.eye(K, dtype=X.dtype, device=X.device))
    dx = -torch.cholesky_solve(gin.reshape(*bs, K, 1), L).reshape(*bs, -1, n)
    dx = torch.where(good[..., None, None], dx, torch.zeros((), dtype=X.dtype, device=X.device))
    interior = X[..., 1:-1, :].detach() + dx - dx.detach()
    return torch.cat([a0.unsqueeze(-2), interior, a1.unsqueeze(-2)], -2)


def _closes_over_graph(G, X: Tensor, fn: str) -> bool:
    with torch.enable_grad():
        return bool(_metric(G, X[..., :1, :].detach(), fn).requires_grad)
