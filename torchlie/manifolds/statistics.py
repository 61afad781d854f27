"""Statistics on any manifold with the Exp/Log vocabulary: Karcher mean, tangent covariance, Gaussians
and their product (seed 004 §12.3, §2).

Seed 004 §12 (Calinon, *Robotics Cookbook*) carries the Gaussian to a manifold: a mean on the
manifold (weighted Karcher/Fréchet mean by Gauss–Newton), a covariance in the tangent space of the
mean, the log-density, and the product of Gaussians (§2 carried to the manifold by iterating in the
tangent space of the current estimate and transporting the covariances there, as §12.1 describes).

Every function takes the manifold as its first argument and uses only the
:class:`~torchlie.manifolds.RiemannianManifold` protocol (``exp_at``, ``log_at``,
``transport_matrix``, ``normal_basis``, ``check_point``, ``point_shape``, ``tangent_size``, ``dim``),
so one implementation serves Rⁿ, SO(2), SO(3), SE(3), Sᵈ and SPD(n).  Tangent vectors are flat
``(*, m)`` vectors in an orthonormal frame of the metric, so covariances are plain ``(*, m, m)``
matrices and the Gaussian is the usual one in those coordinates.  On the sphere the tangent space
is a d-dimensional subspace of R^{d+1}; covariances are kept in ambient coordinates (Σ x = 0) and
inverted/log-determined on the tangent space only, through ``normal_basis``.

Inputs are checked once at entry (they synchronize with the device); the Gauss–Newton loops pass
``check=False`` and run until every batch element has converged, with one host synchronization per
iteration.  Per-element status (iterations, converged) is returned, never raised.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

from torchlie._batch import broadcast_shapes, check_same_device, check_tensor
from torchlie.manifolds.base import (
    Manifold,
    RiemannianManifold,
    _check_symmetric,
    _first_index,
    _safe_norm,
    _sym,
)

__all__ = [
    "KarcherMean",
    "ManifoldGaussian",
    "karcher_mean",
    "tangent_covariance",
    "fit_gaussian",
    "gaussian_log_density",
    "gaussian_product",
]


class KarcherMean(NamedTuple):
    """Result of :func:`karcher_mean`; batch shape ``(*B,)``.

    mean ``(*B, *point_shape)``; iterations ``(*B,)`` int64, Gauss–Newton steps taken per element;
    converged ``(*B,)`` bool, last step norm ≤ tol; step_norm ``(*B,)`` norm of the last step taken.
    """

    mean: torch.Tensor
    iterations: torch.Tensor
    converged: torch.Tensor
    step_norm: torch.Tensor


class ManifoldGaussian(NamedTuple):
    """A Gaussian N_M(μ, Σ) on a manifold, with the status of the iteration that produced it.

    mean ``(*B, *point_shape)``; covariance ``(*B, m, m)`` in the tangent representation at the mean;
    iterations ``(*B,)`` int64; converged ``(*B,)`` bool.
    """

    mean: torch.Tensor
    covariance: torch.Tensor
    iterations: torch.Tensor
    converged: torch.Tensor


def _check_manifold(manifold, fn: str) -> None:
    if not isinstance(manifold, RiemannianManifold) or (
            isinstance(manifold, Manifold) and not manifold.has_exp_log):
        raise TypeError(f"{fn}: argument 'manifold' must implement RiemannianManifold (exp_at, log_at, "
                        "transport; e.g. Sphere(3), SPD(3), SO3(), SE3(), Rn(n)), got "
                        f"{manifold!r}")


def _point_batch(manifold, points: torch.Tensor, name: str, fn: str) -> tuple[int, ...]:
    k = len(manifold.point_shape)
    check_tensor(points, tuple(manifold.point_shape), name, fn)
    if points.dim() < k + 1:
        shape = ", ".join(map(str, manifold.point_shape))
        raise ValueError(f"{fn}: argument '{name}' must have shape (*B, N, {shape}) with a sample "
                         f"dimension N, got {tuple(points.shape)}")
    return tuple(points.shape[: points.dim() - k])


def _normalized_weights(weights, bn: tuple[int, ...], like: torch.Tensor, fn: str) -> torch.Tensor:
    if weights is None:
        return torch.full(bn, 1.0 / bn[-1], dtype=like.dtype, device=like.device)
    if not isinstance(weights, torch.Tensor):
        raise TypeError(f"{fn}: argument 'weights' must be a torch.Tensor of shape (*B, N), got "
                        f"{type(weights).__name__}")
    check_same_device(fn, points=like, weights=weights)
    try:
        w = weights.expand(bn)
    except RuntimeError as e:
        raise ValueError(f"{fn}: argument 'weights' must broadcast to (*B, N) = {bn}, got "
                         f"{tuple(weights.shape)}") from e
    if bool((w < 0).any()) or not bool(torch.isfinite(w).all()):
        raise ValueError(f"{fn}: argument 'weights' must be finite and non-negative")
    tot = w.sum(-1, keepdim=True)
    if bool((tot <= 0).any()):
        raise ValueError(f"{fn}: argument 'weights' sums to zero at batch index "
                         f"{_first_index(tot.squeeze(-1) <= 0)}")
    return w / tot


def _default_tol(dtype: torch.dtype) -> float:
    return torch.finfo(dtype).eps ** 0.75


def _unsqueeze_points(manifold, x: torch.Tensor) -> torch.Tensor:
    return x.unsqueeze(x.dim() - len(manifold.point_shape))


def karcher_mean(manifold: RiemannianManifold, points: torch.Tensor, weights: torch.Tensor | None = None, *,
                 init: torch.Tensor | None = None, max_iter: int = 30, tol: float | None = None,
                 project: bool = False) -> KarcherMean:
    """Weighted Karcher (Fréchet) mean by Gauss–Newton (seed 004 §12.3).

    Iterates ``u = Σ_n w_n Log_μ(x_n)``, ``μ ← Exp_μ(u)`` until ‖u‖ ≤ tol, per batch element (elements
    that converged stop moving; a non-finite step marks only its element as not converged and freezes it).

    points ``(*B, N, *point_shape)``; weights ``(*B, N)`` non-negative (normalized here; uniform if None);
    init ``(*B, *point_shape)`` (default: the sample with the largest weight); tol default eps^0.75
    of the dtype (≈1.8e-12 float64, 6.4e-6 float32). ``project`` applies to points and init.

    Typical data (spread ≲ 0.3 rad) converge in 2–6 iterations. The unit Gauss–Newton step assumes the
    data are concentrated: on the sphere, samples spread over more than about π/2 from the mean can
    make it oscillate; such elements end with ``converged=False`` (the batch is unaffected).
    Checks run once at entry (they synchronize with the device); the loop runs until every element
    has converged, with one host synchronization per iteration.
    """
    fn = "karcher_mean"
    _check_manifold(manifold, fn)
    bn = _point_batch(manifold, points, "points", fn)
    points = manifold.check_point(points, "points", fn, project)
    w = _normalized_weights(weights, bn, points, fn)
    k = len(manifold.point_shape)
    if init is None:
        idx = w.argmax(-1)
        flat = points.reshape(-1, bn[-1], *manifold.point_shape)
        mu = flat[torch.arange(flat.shape[0], device=points.device), idx.reshape(-1)].reshape(
            *bn[:-1], *manifold.point_shape)
    else:
        check_tensor(init, tuple(manifold.point_shape), "init", fn)
        check_same_device(fn, points=points, init=init)
        mu = manifold.check_point(init, "init", fn, project).expand(*bn[:-1], *manifold.point_shape)
    if max_iter < 1:
        raise ValueError(f"{fn}: argument 'max_iter' must be >= 1, got {max_iter}")
    tol = _default_tol(points.dtype) if tol is None else float(tol)
    batch = bn[:-1]
    iterations = torch.zeros(batch, dtype=torch.int64, device=points.device)
    converged = torch.zeros(batch, dtype=torch.bool, device=points.device)
    failed = torch.zeros(batch, dtype=torch.bool, device=points.device)
    step_norm = torch.full(batch, float("nan"), dtype=points.dtype, device=points.device)
    for _ in range(max_iter):
        active = ~(converged | failed)
        if not bool(active.any()):
            break
        logs = manifold.log_at(_unsqueeze_points(manifold, mu), points, check=False)    # (*B, N, m)
        u = (w.unsqueeze(-1) * logs).sum(-2)
        nrm = _safe_norm(u).squeeze(-1)
        finite = torch.isfinite(u).all(-1)
        failed = failed | (active & ~finite)
        step = active & finite
        u = torch.where(step.unsqueeze(-1), u, torch.zeros_like(u))
        new_mu = manifold.exp_at(mu, u, check=False)
        mask = step.reshape(*batch, *([1] * k))
        mu = torch.where(mask, new_mu, mu)
        iterations = iterations + step.to(torch.int64)
        step_norm = torch.where(step, nrm, step_norm)
        converged = converged | (step & (nrm <= tol))
    return KarcherMean(mu, iterations, converged, step_norm)


def tangent_covariance(manifold: RiemannianManifold, points: torch.Tensor, mean: torch.Tensor,
                       weights: torch.Tensor | None = None, *, unbiased: bool = True,
                       project: bool = False) -> torch.Tensor:
    """Covariance of the data in the tangent space of ``mean`` ``(*B, m, m)`` (seed 004 §12.3).

    Σ = Σ_n w_n L_n L_nᵀ / (1 − Σ_n w_n²) with L_n = Log_μ(x_n) and normalized weights; for uniform
    weights this is the seed's 1/(N−1) Σ L_n L_nᵀ (``unbiased=False`` drops the correction).
    """
    fn = "tangent_covariance"
    _check_manifold(manifold, fn)
    bn = _point_batch(manifold, points, "points", fn)
    points = manifold.check_point(points, "points", fn, project)
    check_tensor(mean, tuple(manifold.point_shape), "mean", fn)
    check_same_device(fn, points=points, mean=mean)
    mean = manifold.check_point(mean, "mean", fn, project)
    w = _normalized_weights(weights, bn, points, fn)
    return _covariance(manifold, points, mean, w, unbiased)


def _covariance(manifold, points, mean, w, unbiased: bool) -> torch.Tensor:
    L = manifold.log_at(_unsqueeze_points(manifold, mean), points, check=False)      # (*B, N, m)
    S = (w.unsqueeze(-1) * L).transpose(-1, -2) @ L
    if unbiased:
        denom = 1 - (w * w).sum(-1)
        if bool((denom <= 0).any()):
            raise ValueError("tangent_covariance: the unbiased covariance needs at least two samples with "
                             "non-zero weight; pass unbiased=False")
        S = S / denom[..., None, None]
    return 0.5 * (S + S.transpose(-1, -2))


def fit_gaussian(manifold: RiemannianManifold, points: torch.Tensor, weights: torch.Tensor | None = None, *,
                 init: torch.Tensor | None = None, max_iter: int = 30, tol: float | None = None,
                 unbiased: bool = True, project: bool = False) -> ManifoldGaussian:
    """Gaussian on a manifold from samples: Karcher mean + tangent covariance at the mean (§12.3)."""
    fn = "fit_gaussian"
    _check_manifold(manifold, fn)
    bn = _point_batch(manifold, points, "points", fn)
    points = manifold.check_point(points, "points", fn, project)
    res = karcher_mean(manifold, points, weights, init=init, max_iter=max_iter, tol=tol, project=project)
    w = _normalized_weights(weights, bn, points, fn)
    cov = _covariance(manifold, points, res.mean, w, unbiased)
    return ManifoldGaussian(res.mean, cov, res.iterations, res.converged)


def _tangent_projector_terms(manifold, mu: torch.Tensor, m: int) -> torch.Tensor:
    N = manifold.normal_basis(mu)
    if N is None:
        return torch.zeros(*mu.shape[: mu.dim() - len(manifold.point_shape)], m, m, dtype=mu.dtype,
                           device=mu.device)
    return N @ N.transpose(-1, -2)


def _check_covariance(manifold, cov: torch.Tensor, name: str, fn: str) -> torch.Tensor:
    m = manifold.tangent_size
    check_tensor(cov, (m, m), name, fn)
    _check_symmetric(cov, name, fn, "a covariance must be symmetric")
    return _sym(cov)


def gaussian_log_density(manifold: RiemannianManifold, x: torch.Tensor, mean: torch.Tensor,
                         covariance: torch.Tensor, *, project: bool = False) -> torch.Tensor:
    """log N_M(x | μ, Σ) = −½ Log_μ(x)ᵀ Σ⁻¹ Log_μ(x) − ½ log((2π)^d |Σ|) (seed 004 §12.3), ``(*B,)``.

    x, mean ``(*, *point_shape)`` and covariance ``(*, m, m)`` broadcast over leading dims. d is the
    manifold dimension; on the sphere Σ⁻¹ and |Σ| are taken on the tangent space (Σ x = 0 expected:
    the normal component of Σ is ignored). A covariance that is not positive definite on the tangent
    space raises ``ValueError``.
    """
    fn = "gaussian_log_density"
    _check_manifold(manifold, fn)
    check_tensor(x, tuple(manifold.point_shape), "x", fn)
    check_tensor(mean, tuple(manifold.point_shape), "mean", fn)
    check_same_device(fn, x=x, mean=mean, covariance=covariance)
    x = manifold.check_point(x, "x", fn, project)
    mean = manifold.check_point(mean, "mean", fn, project)
    cov = _check_covariance(manifold, covariance, "covariance", fn)
    L = manifold.log_at(mean, x, check=False)
    NN = _tangent_projector_terms(manifold, mean, manifold.tangent_size)
    P = torch.eye(manifold.tangent_size, dtype=cov.dtype, device=cov.device) - NN
    cov_t = P @ cov @ P + NN            # full rank: tangent block of Σ plus identity on the normal space
    chol, info = torch.linalg.cholesky_ex(cov_t)
    if bool((info != 0).any()):
        raise ValueError(f"{fn}: argument 'covariance' is not positive definite on the tangent space at "
                         f"batch index {_first_index(info != 0)}")
    batch = broadcast_shapes(L.shape[:-1], chol.shape[:-2])
    chol = chol.expand(*batch, *chol.shape[-2:])
    L = L.expand(*batch, L.shape[-1])
    z = torch.linalg.solve_triangular(chol, L.unsqueeze(-1), upper=False).squeeze(-1)
    logdet = 2 * torch.log(torch.diagonal(chol, dim1=-2, dim2=-1)).sum(-1)
    d = manifold.dim
    return -0.5 * (z * z).sum(-1) - 0.5 * logdet - 0.5 * d * math.log(2 * math.pi)


def gaussian_product(manifold: RiemannianManifold, means: torch.Tensor, covariances: torch.Tensor, *,
                     init: torch.Tensor | None = None, max_iter: int = 30, tol: float | None = None,
                     project: bool = False) -> ManifoldGaussian:
    """Product of K Gaussians on a manifold, ∏_k N_M(μ_k, Σ_k) ≈ N_M(μ̂, Σ̂), by Gauss–Newton.

    At the current estimate μ: u_k = Log_μ(μ_k), Σ_k∥ = A_k Σ_k A_kᵀ with A_k the transport μ_k → μ
    (§12.1), precisions Λ_k = Σ_k∥⁻¹ (on the tangent space), Σ̂ = (Σ_k Λ_k)⁻¹, u = Σ̂ Σ_k Λ_k u_k,
    μ ← Exp_μ(u); repeat until ‖u‖ ≤ tol. On R^n this is the closed form of seed 004 §2 after one step.
    The returned covariance is the one at the last linearization point (within tol of the mean).

    means ``(*B, K, *point_shape)``, covariances ``(*B, K, m, m)`` (each in the tangent representation
    at its own mean); init ``(*B, *point_shape)`` (default: the first mean).
    """
    fn = "gaussian_product"
    _check_manifold(manifold, fn)
    bk = _point_batch(manifold, means, "means", fn)
    m = manifold.tangent_size
    check_tensor(covariances, (m, m), "covariances", fn)
    check_same_device(fn, means=means, covariances=covariances)
    if tuple(covariances.shape[:-2]) != bk:
        raise ValueError(f"{fn}: argument 'covariances' must have shape (*B, K, {m}, {m}) = {(*bk, m, m)} "
                         f"to match 'means', got {tuple(covariances.shape)}")
    means = manifold.check_point(means, "means", fn, project)
    covs = _check_covariance(manifold, covariances, "covariances", fn)
    k = len(manifold.point_shape)
    batch = bk[:-1]
    if init is None:
        mu = means.select(len(batch), 0)
    else:
        check_tensor(init, tuple(manifold.point_shape), "init", fn)
        check_same_device(fn, means=means, init=init)
        mu = manifold.check_point(init, "init", fn, project).expand(*batch, *manifold.point_shape)
    if max_iter < 1:
        raise ValueError(f"{fn}: argument 'max_iter' must be >= 1, got {max_iter}")
    tol = _default_tol(means.dtype) if tol is None else float(tol)
    eye = torch.eye(m, dtype=means.dtype, device=means.device)
    # normal-space terms of each input at its own mean (for the tangent-space inverse)
    NN_k = _tangent_projector_terms(manifold, means, m)
    iterations = torch.zeros(batch, dtype=torch.int64, device=means.device)
    converged = torch.zeros(batch, dtype=torch.bool, device=means.device)
    failed = torch.zeros(batch, dtype=torch.bool, device=means.device)
    cov_hat = torch.zeros(*batch, m, m, dtype=means.dtype, device=means.device)
    for _ in range(max_iter):
        active = ~(converged | failed)
        if not bool(active.any()):
            break
        mu_k = _unsqueeze_points(manifold, mu)
        u_k = manifold.log_at(mu_k, means, check=False)                      # (*B, K, m)
        A = manifold.transport_matrix(means, mu_k, check=False)               # (*B, K, m, m)
        P_k = eye - NN_k
        S = A @ (P_k @ covs @ P_k) @ A.transpose(-1, -2)                      # transported, tangent at μ
        NN = _tangent_projector_terms(manifold, mu, m)                        # (*B, m, m)
        NN1 = NN.unsqueeze(-3)
        # tangent-space inverses; a singular one (a degenerate covariance) fails its element only
        Lam_k, info_k = torch.linalg.inv_ex(S + NN1)
        Lam_k = Lam_k - NN1
        Lam = Lam_k.sum(-3)
        cov_new, info = torch.linalg.inv_ex(Lam + NN)
        cov_new = cov_new - NN
        u = (cov_new @ (Lam_k @ u_k.unsqueeze(-1)).sum(-3)).squeeze(-1)
        finite = torch.isfinite(u).all(-1) & torch.isfinite(cov_new).flatten(-2).all(-1) \
            & (info_k == 0).all(-1) & (info == 0)
        failed = failed | (active & ~finite)
        step = active & finite
        u = torch.where(step.unsqueeze(-1), u, torch.zeros_like(u))
        cov_hat = torch.where(step[..., None, None], 0.5 * (cov_new + cov_new.transpose(-1, -2)), cov_hat)
        nrm = _safe_norm(u).squeeze(-1)
        new_mu = manifold.exp_at(mu, u, check=False)
        mu = torch.where(step.reshape(*batch, *([1] * k)), new_mu, mu)
        iterations = iterations + step.to(torch.int64)
        converged = converged | (step & (nrm <= tol))
    return ManifoldGaussian(mu, cov_hat, iterations, converged)
