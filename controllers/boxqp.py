"""Batched box-constrained quadratic programs by projected Newton.

Solves, independently for every batch element,

    minimize_x   ½ xᵀ H x + gᵀ x     subject to   lower ≤ x ≤ upper,

with the projected-Newton method used by control-limited DDP (Tassa, Mansard & Todorov, "Control-limited
differential dynamic programming", ICRA 2014, Algorithm 1): at every iteration the variables sitting on a
bound with the gradient pushing outwards are *clamped*, a Newton step is taken in the remaining *free*
subspace, and a projected Armijo line search (all candidate step sizes evaluated at once, one accepted step
size per element) keeps the iterate feasible.  The factor of the free Hessian at the solution is what iLQR
needs for its feedback gains (clamped rows are zero).

Shapes: ``H (*B, m, m)`` symmetric, ``g (*B, m)``, ``lower``/``upper`` broadcastable to ``(*B, m)`` (``±inf``
means unbounded).  Everything is batched: no Python loop over batch elements, one loop over iterations.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["BoxQPStatus", "BoxQPResult", "box_qp", "masked_hessian"]


class BoxQPStatus(enum.IntEnum):
    """Why the solver stopped for one batch element (``BoxQPResult.status`` holds these values)."""

    CONVERGED = 0  #: norm of the projected gradient below tolerance
    SMALL_IMPROVEMENT = 1  #: relative decrease of the objective below ``min_rel_improve``
    ALL_CLAMPED = 2  #: every variable is clamped on a bound (a vertex of the box is optimal)
    MAX_ITERATIONS = 3  #: ``max_iter`` reached before any other criterion
    NOT_POSITIVE_DEFINITE = 4  #: the free block of ``H`` is not positive definite
    NO_DESCENT = 5  #: the line search found no step satisfying the Armijo condition
    NON_FINITE = 6  #: NaN or inf in ``H``, ``g`` or ``x0`` of this element

    @property
    def success(self) -> bool:
        return self in (BoxQPStatus.CONVERGED, BoxQPStatus.SMALL_IMPROVEMENT, BoxQPStatus.ALL_CLAMPED)


_SUCCESS = (BoxQPStatus.CONVERGED, BoxQPStatus.SMALL_IMPROVEMENT, BoxQPStatus.ALL_CLAMPED)


@dataclass(frozen=True)
class BoxQPResult:
    """Solution of a batch of box QPs.

    Attributes:
        x: ``(*B, m)`` minimizer (NaN for elements whose status is ``NON_FINITE``).
        free: ``(*B, m)`` bool, variables not clamped at the solution.
        clamped: ``(*B, m)`` bool, ``~free``: on a bound with the gradient pointing out of the box.
        status: ``(*B,)`` int64, values of :class:`BoxQPStatus`.
        iterations: ``(*B,)`` int64, Newton iterations used by each element.
    """

    x: Tensor
    free: Tensor
    clamped: Tensor
    status: Tensor
    iterations: Tensor

    @property
    def converged(self) -> Tensor:
        """``(*B,)`` bool: the element stopped for a successful reason."""
        s = self.status
        return (s == BoxQPStatus.CONVERGED) | (s == BoxQPStatus.SMALL_IMPROVEMENT) | (
            s == BoxQPStatus.ALL_CLAMPED)


def masked_hessian(H: Tensor, free: Tensor) -> Tensor:
    """``M H M + (I - M)`` with ``M = diag(free)``: the free block of ``H`` and identity on clamped rows.

    Solving with it gives zero in the clamped components when the right-hand side is masked too, which is how
    the clamped rows of the DDP gains are zeroed.
    """
    f = free.to(H.dtype)
    eye = torch.eye(H.shape[-1], dtype=H.dtype, device=H.device)
    return H * f.unsqueeze(-1) * f.unsqueeze(-2) + eye * (1.0 - f).unsqueeze(-1)


def _objective(H: Tensor, g: Tensor, x: Tensor) -> Tensor:
    return 0.5 * (x * (H @ x.unsqueeze(-1)).squeeze(-1)).sum(-1) + (g * x).sum(-1)


def box_qp(
    H: Tensor,
    g: Tensor,
    lower: Tensor | float,
    upper: Tensor | float,
    x0: Tensor | None = None,
    *,
    max_iter: int = 100,
    tol: float | None = None,
    min_rel_improve: float | None = None,
    armijo: float = 0.1,
    step_dec: float = 0.5,
    n_steps: int = 24,
    check: bool = True,
) -> BoxQPResult:
    """Solve ``min ½xᵀHx + gᵀx  s.t.  lower ≤ x ≤ upper`` for a batch, by projected Newton.

    Args:
        H: ``(*B, m, m)`` symmetric Hessians (positive definite on the free subspace for a unique solution).
        g: ``(*B, m)`` linear terms.
        lower, upper: bounds broadcastable to ``(*B, m)``; ``-inf``/``inf`` for unbounded components.
        x0: optional ``(*B, m)`` warm start (projected onto the box); zero (projected) by default.
        max_iter: Newton iterations at most.
        tol: stop when ``‖projected gradient‖ ≤ tol·(1 + ‖g‖)``; default ``sqrt(eps)`` of the dtype.
        min_rel_improve: stop when an accepted step lowers the objective by less than this fraction.
        armijo: accepted step must achieve this fraction of the linearly predicted decrease.
        step_dec, n_steps: candidate steps are ``step_dec**j`` for ``j < n_steps``, all evaluated at once.
        check: validate ``lower <= upper`` (a host sync); solvers that already did may pass ``False``.

    Returns:
        :class:`BoxQPResult` with per-element status; one bad element never affects the others.
    """
    if not isinstance(H, Tensor) or not isinstance(g, Tensor):
        raise TypeError("box_qp: H and g must be tensors")
    if H.dim() < 2 or H.shape[-1] != H.shape[-2]:
        raise ValueError(f"box_qp: H must have shape (*B, m, m), got {tuple(H.shape)}")
    m = H.shape[-1]
    if g.dim() < 1 or g.shape[-1] != m:
        raise ValueError(f"box_qp: g must have shape (*B, {m}) to match H, got {tuple(g.shape)}")
    if not H.dtype.is_floating_point or g.dtype != H.dtype:
        raise TypeError(f"box_qp: H and g must share one floating dtype, got {H.dtype} and {g.dtype}")
    dtype, device = H.dtype, H.device
    batch = torch.broadcast_shapes(H.shape[:-2], g.shape[:-1])
    for name, v in (("lower", lower), ("upper", upper), ("x0", x0)):
        if isinstance(v, torch.Tensor) and (v.dtype != dtype or v.device != device):
            raise TypeError(f"box_qp: argument '{name}' must have H's dtype and device ({dtype}, {device}), "
                            f"got {v.dtype} on {v.device}; convert it explicitly (nothing is cast silently)")
    lo = torch.as_tensor(lower, dtype=dtype, device=device)
    hi = torch.as_tensor(upper, dtype=dtype, device=device)
    try:
        lo = lo.expand(*batch, m)
        hi = hi.expand(*batch, m)
    except RuntimeError as e:
        raise ValueError(f"box_qp: lower/upper must broadcast to {(*batch, m)}, got {tuple(lo.shape)} "
                         f"and {tuple(hi.shape)}") from e
    if check and bool((lo > hi).any()):
        raise ValueError("box_qp: lower must be <= upper everywhere")
    H = H.expand(*batch, m, m)
    g = g.expand(*batch, m)
    if x0 is not None:
        if x0.shape[-1] != m:
            raise ValueError(f"box_qp: x0 must have shape (*B, {m}), got {tuple(x0.shape)}")
        x0 = x0.expand(*batch, m)
    eps = torch.finfo(dtype).eps
    tol = eps ** 0.5 if tol is None else tol
    min_rel_improve = 10 * eps if min_rel_improve is None else min_rel_improve

    # Flatten the batch; sanitize non-finite elements so they cannot leak into batched factorizations.
    nb = int(torch.Size(batch).numel())
    H = H.reshape(nb, m, m)
    g = g.reshape(nb, m)
    lo = lo.reshape(nb, m)
    hi = hi.reshape(nb, m)
    finite = torch.isfinite(H).flatten(1).all(-1) & torch.isfinite(g).all(-1) & ~torch.isnan(lo).any(-1) \
        & ~torch.isnan(hi).any(-1)
    if x0 is not None:
        x0 = x0.reshape(nb, m)
        finite = finite & torch.isfinite(x0).all(-1)
    eye = torch.eye(m, dtype=dtype, device=device)
    fin1 = finite.unsqueeze(-1)
    H = torch.where(fin1.unsqueeze(-1), H, eye)
    g = torch.where(fin1, g, torch.zeros((), dtype=dtype, device=device))
    lo = torch.where(fin1, lo, -torch.inf)
    hi = torch.where(fin1, hi, torch.inf)
    x = torch.zeros(nb, m, dtype=dtype, device=device) if x0 is None else torch.where(fin1, x0, 0.0)
    x = torch.minimum(torch.maximum(x, lo), hi)

    if m == 1:
        return _box_qp_scalar(H, g, lo, hi, finite, batch)

    status = torch.full((nb,), int(BoxQPStatus.MAX_ITERATIONS), dtype=torch.long, device=device)
    status = torch.where(finite, status, int(BoxQPStatus.NON_FINITE))
    iters = torch.zeros(nb, dtype=torch.long, device=device)
    active = finite.clone()
    gscale = tol * (1.0 + g.norm(dim=-1))
    alphas = step_dec ** torch.arange(n_steps, dtype=dtype, device=device)  # (S,)
    fval = _objective(H, g, x)
    free = torch.ones(nb, m, dtype=torch.bool, device=device)

    for _ in range(max_iter):
        if not bool(active.any()):
            break
        grad = g + (H @ x.unsqueeze(-1)).squeeze(-1)
        clamped = ((x <= lo) & (grad > 0)) | ((x >= hi) & (grad < 0))
        free = torch.where(active.unsqueeze(-1), ~clamped, free)
        pg = torch.where(free, grad, torch.zeros((), dtype=dtype, device=device))
        small = pg.norm(dim=-1) <= gscale
        allc = ~free.any(-1)
        done = active & (small | allc)
        status = torch.where(done & allc, int(BoxQPStatus.ALL_CLAMPED), status)
        status = torch.where(done & ~allc, int(BoxQPStatus.CONVERGED), status)
        active = active & ~done

        Hf = masked_hessian(H, free)
        L, info = torch.linalg.cholesky_ex(Hf)
        notpd = active & (info != 0)
        status = torch.where(notpd, int(BoxQPStatus.NOT_POSITIVE_DEFINITE), status)
        active = active & ~notpd
        L = torch.where((info != 0).view(nb, 1, 1), eye, L)
        dx = -torch.cholesky_solve(pg.unsqueeze(-1), L).squeeze(-1)

        # Projected Armijo line search, every candidate step at once: (nb, S, m).
        cand = x.unsqueeze(1) + alphas.view(1, -1, 1) * dx.unsqueeze(1)
        cand = torch.minimum(torch.maximum(cand, lo.unsqueeze(1)), hi.unsqueeze(1))
        fc = _objective(H.unsqueeze(1), g.unsqueeze(1), cand)  # (nb, S)
        expected = (grad.unsqueeze(1) * (cand - x.unsqueeze(1))).sum(-1)  # < 0 for a descent step
        ok = (expected < 0) & (fval.unsqueeze(1) - fc >= -armijo * expected)
        anyok = ok.any(-1)
        first = torch.argmax(ok.to(torch.int8), dim=-1)
        xn = cand[torch.arange(nb, device=device), first]
        fn = fc[torch.arange(nb, device=device), first]
        nodesc = active & ~anyok
        status = torch.where(nodesc, int(BoxQPStatus.NO_DESCENT), status)
        active = active & ~nodesc
        step = active.unsqueeze(-1)
        improve = fval - fn
        x = torch.where(step, xn, x)
        iters = iters + active.long()
        smallimp = active & (improve < min_rel_improve * fval.abs().clamp_min(eps))
        fval = torch.where(active, fn, fval)
        status = torch.where(smallimp, int(BoxQPStatus.SMALL_IMPROVEMENT), status)
        active = active & ~smallimp

    # Final free/clamped sets at the returned point.
    grad = g + (H @ x.unsqueeze(-1)).squeeze(-1)
    clamped = ((x <= lo) & (grad > 0)) | ((x >= hi) & (grad < 0))
    x = torch.where(fin1, x, torch.nan)
    out = (*batch, m)
    return BoxQPResult(
        x=x.reshape(out),
        free=(~clamped).reshape(out),
        clamped=clamped.reshape(out),
        status=status.reshape(batch),
        iterations=iters.reshape(batch),
    )


def _box_qp_scalar(H: Tensor, g: Tensor, lo: Tensor, hi: Tensor, finite: Tensor, batch) -> BoxQPResult:
    """Closed form for one variable: ``x = clip(-g/h, lower, upper)`` when ``h > 0``."""
    h = H[..., 0]  # (nb, 1)
    pd = (h > 0).squeeze(-1)
    x = torch.minimum(torch.maximum(-g / torch.where(h > 0, h, 1.0), lo), hi)
    x = torch.where(pd.unsqueeze(-1), x, torch.minimum(torch.maximum(torch.zeros_like(x), lo), hi))
    grad = g + h * x
    clamped = ((x <= lo) & (grad > 0)) | ((x >= hi) & (grad < 0))
    status = torch.where(clamped.squeeze(-1), int(BoxQPStatus.ALL_CLAMPED), int(BoxQPStatus.CONVERGED))
    status = torch.where(pd, status, int(BoxQPStatus.NOT_POSITIVE_DEFINITE))
    status = torch.where(finite, status, int(BoxQPStatus.NON_FINITE))
    x = torch.where(finite.unsqueeze(-1), x, torch.nan)
    out = (*batch, 1)
    return BoxQPResult(x=x.reshape(out), free=(~clamped).reshape(out), clamped=clamped.reshape(out),
                       status=status.reshape(batch), iterations=torch.ones_like(status).reshape(batch))
