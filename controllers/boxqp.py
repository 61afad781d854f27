"""Batched box-constrained quadratic programs by projected Newton with a projected-gradient safeguard.

Solves, independently for every batch element,

    minimize_x   f(x) = ½ xᵀ H x + gᵀ x     subject to   lower ≤ x ≤ upper,

with the projected-Newton method of control-limited DDP (Tassa, Mansard & Todorov, "Control-limited
differential dynamic programming", ICRA 2014, Algorithm 1), made globally convergent:

* **Working set** (Bertsekas, "Projected Newton methods for optimization problems with simple
  constraints", SIAM J. Control Optim. 20(2), 1982, the ε-active set): a variable is *held* on a bound when
  its gradient points out of the box and a diagonal Newton step ``−∂ᵢf / Hᵢᵢ`` would carry it onto or
  across that (finite) bound.  This contains Tassa's clamped set (on the bound, gradient outwards) and
  also the variables a hair's breadth from it, which otherwise block every step.
* **Newton step on the face**: held variables go to their bound, the others minimize ``f`` with those
  fixed (one Cholesky factor of the free block of ``H``), so once the working set is right one full step
  lands on the minimizer.
* **Safeguard**: the projected Newton arc ``clip(x + α d)`` is not a descent path in general.  A variable a
  hair above its bound with the gradient pushing it out is *free* for Tassa's test (it is not exactly on
  the bound), the ill-conditioned Newton step hits that bound at ``α ~ 1e-8`` and the projected arc ascends
  for every step size tried: this is what stopped the plain method with ``NO_DESCENT`` far from the optimum.
  Every iteration therefore also tries the projected-gradient arc ``clip(x − β D⁻¹∇f)`` (``D = diag(H)``)
  from the exact Cauchy step length ``β₀`` down, which always contains a descent step (Calamai & Moré,
  "Projected gradient methods for linearly constrained problems", Math. Prog. 39, 1987).  All candidates of
  both arcs are evaluated at once through the exact change ``Δ(s) = ∇fᵀs + ½sᵀHs`` of the quadratic
  (``s`` = candidate − x, free of the cancellation of comparing two objective values) and, among those
  satisfying the Armijo condition ``Δ(s) ≤ armijo·∇fᵀs < 0``, the lowest is taken.

**Statuses are certificates.**  With the Jacobi scaling ``D = diag(H)`` (entries that are not positive
replaced by 1), ``y = D^½ x``, ``H̃ = D^-½ H D^-½``, ``g̃ = D^-½ g``, the stopping test, evaluated at the point
that is returned, is the KKT condition of the box QP in projected-gradient form for the scaled problem::

    kkt_residual  = ‖y − clip(y − (H̃y + g̃), D^½ lower, D^½ upper)‖₂
                  = ‖D^½ (x − clip(x − D⁻¹∇f(x), lower, upper))‖₂
    kkt_tolerance = tol · (‖g̃‖₂ + ‖H̃‖_F ‖y‖₂)                  (‖·‖_F: the Frobenius norm)

The residual is zero exactly at the minimizer.  Both sides are unchanged when ``f`` is multiplied by a
constant or a variable is measured in other units, so the test means the same whatever the scaling, and
the tolerance is the size of the terms of the scaled gradient, which floating point attains whatever
``cond(H)``.  ``CONVERGED`` and ``ALL_CLAMPED`` are returned only when it holds; every other status is a
failure and names the reason.  (In practice the last iteration is a full Newton step on the right face and
leaves a residual near round-off, far below ``kkt_tolerance``.)

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
    """Why the solver stopped for one batch element (``BoxQPResult.status`` holds these values).

    Only ``CONVERGED`` and ``ALL_CLAMPED`` are successes (:attr:`success`); both certify
    ``kkt_residual ≤ kkt_tolerance`` at the returned ``x`` (see the module docstring): a KKT point, hence the
    minimizer when ``H`` is positive definite.  The failures return the best point found so far (feasible,
    never worse than the start), except ``NON_FINITE`` (NaN).
    """

    CONVERGED = 0  #: KKT certificate holds and at least one variable is free
    #: failure: stalled, the last step lowered f by less than ``min_rel_improve``·|f| (round-off level)
    #: while the certificate still fails
    SMALL_IMPROVEMENT = 1
    ALL_CLAMPED = 2  #: KKT certificate holds and every variable is clamped (a vertex of the box is optimal)
    MAX_ITERATIONS = 3  #: failure: ``max_iter`` reached without the certificate
    NOT_POSITIVE_DEFINITE = 4  #: failure: the free block of ``H`` is not positive definite
    NO_DESCENT = 5  #: failure: no candidate step satisfied the Armijo condition (round-off level)
    NON_FINITE = 6  #: failure: NaN or inf in ``H``, ``g`` or ``x0`` (or NaN bounds) of this element

    @property
    def success(self) -> bool:
        """The returned point is certified (``kkt_residual ≤ kkt_tolerance`` was checked at it)."""
        return self in _SUCCESS


_SUCCESS = (BoxQPStatus.CONVERGED, BoxQPStatus.ALL_CLAMPED)


@dataclass(frozen=True)
class BoxQPResult:
    """Solution of a batch of box QPs.

    Attributes:
        x: ``(*B, m)`` minimizer (NaN for elements whose status is ``NON_FINITE``).
        free: ``(*B, m)`` bool, variables not clamped at ``x``.
        clamped: ``(*B, m)`` bool, ``~free``: on a bound with the gradient pointing out of the box.
        status: ``(*B,)`` int64, values of :class:`BoxQPStatus`.
        iterations: ``(*B,)`` int64, iterations (accepted steps) used by each element.
        kkt_residual: ``(*B,)`` the projected gradient of the Jacobi-scaled problem at the returned ``x``,
            ``‖D^½ (x − clip(x − D⁻¹(Hx + g), lower, upper))‖₂`` with ``D = diag(H)`` (NaN if ``NON_FINITE``).
        kkt_tolerance: ``(*B,)`` ``tol·(‖D^-½ g‖₂ + ‖D^-½ H D^-½‖_F ‖D^½ x‖₂)``; the status is a success
            (``CONVERGED``/``ALL_CLAMPED``) iff ``kkt_residual ≤ kkt_tolerance`` (see the module docstring).
    """

    x: Tensor
    free: Tensor
    clamped: Tensor
    status: Tensor
    iterations: Tensor
    kkt_residual: Tensor
    kkt_tolerance: Tensor

    @property
    def converged(self) -> Tensor:
        """``(*B,)`` bool: the element stopped certified (``CONVERGED`` or ``ALL_CLAMPED``)."""
        s = self.status
        return (s == BoxQPStatus.CONVERGED) | (s == BoxQPStatus.ALL_CLAMPED)


def masked_hessian(H: Tensor, free: Tensor) -> Tensor:
    """``M H M + (I - M)`` with ``M = diag(free)``: the free block of ``H`` and identity on clamped rows.

    Solving with it gives zero in the clamped components when the right-hand side is masked too, which is how
    the clamped rows of the DDP gains are zeroed.
    """
    eye = torch.eye(H.shape[-1], dtype=H.dtype, device=H.device)
    return torch.where(free.unsqueeze(-1) & free.unsqueeze(-2), H, eye)


def _matvec(H: Tensor, x: Tensor) -> Tensor:
    """``H x`` for ``H (nb, m, m)`` and ``x (nb, m)`` (a bmm: ``H`` is never expanded)."""
    return torch.bmm(H, x.unsqueeze(-1)).squeeze(-1)


def _clip(x: Tensor, lo: Tensor, hi: Tensor) -> Tensor:
    return torch.minimum(torch.maximum(x, lo), hi)


def _jacobi(H: Tensor) -> tuple[Tensor, Tensor]:
    """``D^½`` of the Jacobi scaling ``D = diag(H)`` (1 where not positive) and ``‖D^-½ H D^-½‖_F``."""
    hd = H.diagonal(dim1=-2, dim2=-1)
    dsq = torch.where(hd > 0, hd, 1.0).sqrt()
    return dsq, torch.linalg.matrix_norm(H / (dsq.unsqueeze(-1) * dsq.unsqueeze(-2)))


def _kkt(H: Tensor, g: Tensor, lo: Tensor, hi: Tensor, x: Tensor, dsq: Tensor, hsc: Tensor, tol: float):
    """Gradient, clamped set, KKT residual and its tolerance at ``x`` (flattened batch; module doc)."""
    grad = g + _matvec(H, x)
    clamped = ((x <= lo) & (grad > 0)) | ((x >= hi) & (grad < 0))
    hd = H.diagonal(dim1=-2, dim2=-1)
    D = torch.where(hd > 0, hd, 1.0)
    res = (dsq * (x - _clip(x - grad / D, lo, hi))).norm(dim=-1)
    kkt_tol = tol * ((g / dsq).norm(dim=-1) + hsc * (dsq * x).norm(dim=-1))
    return grad, clamped, res, kkt_tol


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
    """Solve ``min ½xᵀHx + gᵀx  s.t.  lower ≤ x ≤ upper`` for a batch (projected Newton, see the module doc).

    Args:
        H: ``(*B, m, m)`` symmetric Hessians (positive definite on the free subspace for a unique solution).
        g: ``(*B, m)`` linear terms.
        lower, upper: bounds broadcastable to ``(*B, m)``; ``-inf``/``inf`` for unbounded components.
        x0: optional ``(*B, m)`` warm start (projected onto the box); zero (projected) by default.
        max_iter: iterations at most (one Cholesky factorization each).
        tol: the certificate: an element succeeds iff, at the returned ``x`` and with ``D = diag(H)``,
            ``‖D^½ (x − clip(x − D⁻¹(Hx + g), lower, upper))‖₂ ≤ tol·(‖D^-½ g‖₂ + ‖D^-½ H D^-½‖_F ‖D^½ x‖₂)``
            (the projected gradient of the Jacobi-scaled problem against the size of its terms; see the
            module docstring); default ``sqrt(eps)`` of the dtype (1.5e-8 in float64, 3.5e-4 in float32).
        min_rel_improve: declare a stall (``SMALL_IMPROVEMENT``, a failure) when an accepted step lowers the
            objective by less than this fraction of ``|f|`` and the certificate still fails; default ``eps``.
        armijo: an accepted step ``s`` must achieve this fraction of its linearly predicted decrease
            ``−∇fᵀs``.
        step_dec, n_steps: candidate step sizes along each arc are ``step_dec**j`` times its initial step
            (1 for Newton, the Cauchy step for the projected gradient), ``j < n_steps``, all evaluated at
            once;
            the projected-gradient arc then reaches an Armijo step whenever ``cond(D^-½ H D^-½)`` is below
            about ``step_dec**-(n_steps - 1)`` (8e6 by default; the Newton arc has no such limit).
        check: validate ``lower <= upper`` (a host sync); solvers that already did may pass ``False``.

    Returns:
        :class:`BoxQPResult` with per-element status, ``kkt_residual`` and ``kkt_tolerance``; one bad element
        never affects the others.  ``m == 1`` is solved in closed form and certified the same way.
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
    min_rel_improve = eps if min_rel_improve is None else min_rel_improve

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
    dsq, hsc = _jacobi(H)  # the scaling of the certificate
    zero = torch.zeros((), dtype=dtype, device=device)

    if m == 1:
        x = _box_qp_scalar_x(H, g, lo, hi)
    else:
        x = torch.zeros(nb, m, dtype=dtype, device=device) if x0 is None else torch.where(fin1, x0, zero)
        x = _clip(x, lo, hi)
    # the certificate (and the free set) at the returned point; the loop overwrites what it decides
    _, clamped, res, kkt_tol = _kkt(H, g, lo, hi, x, dsq, hsc, tol)
    status = torch.full((nb,), int(BoxQPStatus.NON_FINITE), dtype=torch.long, device=device)
    iters = torch.zeros(nb, dtype=torch.long, device=device)
    if m == 1:  # closed form: certified like the rest (a failure here would mean round-off trouble)
        cert = _certified_status(res <= kkt_tol, clamped, int(BoxQPStatus.NO_DESCENT))
        status = torch.where(finite, cert, status)
        status = torch.where(finite & (H[:, 0, 0] <= 0), int(BoxQPStatus.NOT_POSITIVE_DEFINITE), status)
        iters = iters + 1
    else:
        _iterate(H, g, lo, hi, x, dsq, hsc, finite, status, iters, res, kkt_tol, clamped, max_iter=max_iter,
                 tol=tol, min_rel_improve=min_rel_improve, armijo=armijo, step_dec=step_dec, n_steps=n_steps)
    x = torch.where(fin1, x, torch.nan)
    res = torch.where(finite, res, torch.nan)
    out = (*batch, m)
    return BoxQPResult(
        x=x.reshape(out),
        free=(~clamped).reshape(out),
        clamped=clamped.reshape(out),
        status=status.reshape(batch),
        iterations=iters.reshape(batch),
        kkt_residual=res.reshape(batch),
        kkt_tolerance=kkt_tol.reshape(batch),
    )


def _certified_status(cert: Tensor, clamped: Tensor, otherwise: Tensor | int) -> Tensor:
    code = torch.where(clamped.all(-1), int(BoxQPStatus.ALL_CLAMPED), int(BoxQPStatus.CONVERGED))
    return torch.where(cert, code, otherwise)


def _iterate(H, g, lo, hi, x, dsq, hsc, finite, status, iters, res, kkt_tol, clamped, *, max_iter, tol,
             min_rel_improve, armijo, step_dec, n_steps) -> None:
    """The iterations of :func:`box_qp` on the flattened batch, writing ``x``, ``status``, ``iters`` and the
    certificate (``res``, ``kkt_tol``, ``clamped``) of every finite element in place.

    Only the undecided elements are carried: the working tensors are compacted (one boolean index, a host
    sync) whenever some element stops, so a batch of easy problems with a few hard ones costs little more
    than the hard ones alone.
    """
    dtype, device = H.dtype, H.device
    m = H.shape[-1]
    zero = torch.zeros((), dtype=dtype, device=device)
    eye = torch.eye(m, dtype=dtype, device=device)
    alphas = step_dec ** torch.arange(n_steps, dtype=dtype, device=device)  # (S,)
    pending_code = int(BoxQPStatus.MAX_ITERATIONS)
    sel = finite.nonzero().squeeze(-1)
    Hc, gc, loc, hic, dc, hc, xc = H[sel], g[sel], lo[sel], hi[sel], dsq[sel], hsc[sel], x[sel]
    fval = 0.5 * (xc * _matvec(Hc, xc)).sum(-1) + (gc * xc).sum(-1)
    pending = torch.full_like(sel, pending_code)  # a failure decided at the current point, if any

    for it in range(max_iter + 1):
        grad, clc, rc, tc = _kkt(Hc, gc, loc, hic, xc, dc, hc, tol)
        cert = rc <= tc
        stop = cert | (pending != pending_code) | (it == max_iter)
        if bool(stop.any()):
            idx = sel[stop]
            x[idx] = xc[stop]
            status[idx] = _certified_status(cert, clc, pending)[stop]
            res[idx], kkt_tol[idx], clamped[idx] = rc[stop], tc[stop], clc[stop]
            go = ~stop
            sel, Hc, gc, loc, hic, xc = sel[go], Hc[go], gc[go], loc[go], hic[go], xc[go]
            dc, hc = dc[go], hc[go]
            fval, grad, clc = fval[go], grad[go], clc[go]
            if sel.numel() == 0:
                break
        nc = sel.shape[0]

        # Working set: gradient outwards and a diagonal Newton step reaches the (finite) bound.
        hdiag = Hc.diagonal(dim1=-2, dim2=-1)
        hold_lo = (grad > 0) & ((xc - loc) * hdiag <= grad) & torch.isfinite(loc)
        hold_hi = (grad < 0) & ((hic - xc) * hdiag <= -grad) & torch.isfinite(hic) & ~hold_lo
        free = ~(hold_lo | hold_hi)
        # Newton point of that face: held variables on their bound, the free ones minimize f with those fixed.
        # It is solved for directly (not as x + correction), so its residual is relative to its own size.
        b_held = torch.where(hold_lo, loc, torch.where(hold_hi, hic, zero))
        L, info = torch.linalg.cholesky_ex(masked_hessian(Hc, free))
        notpd = info != 0
        if bool(notpd.any()):  # keep the solve finite for those (their step is discarded anyway)
            L = torch.where(notpd.view(nc, 1, 1), eye, L)
        rhs = torch.where(free, gc + _matvec(Hc, b_held), zero)
        y = b_held - torch.cholesky_solve(rhs.unsqueeze(-1), L).squeeze(-1)
        d = y - xc
        # Projected-gradient (Cauchy) arc, scaled by diag(H), from the exact step length along it.
        p = torch.where(clc, zero, -grad / torch.where(hdiag > 0, hdiag, 1.0))
        pHp = (p * _matvec(Hc, p)).sum(-1)
        beta0 = torch.where(pHp > 0, -(grad * p).sum(-1) / torch.where(pHp > 0, pHp, 1.0), 1.0)  # min on p

        # Both arcs, every step size at once, (nc, m, 2S), and the exact change of f for each.
        betas = beta0.unsqueeze(-1) * alphas
        steps = torch.cat([d.unsqueeze(-1) * alphas, p.unsqueeze(-1) * betas.unsqueeze(1)], -1)
        cand = torch.clamp(xc.unsqueeze(-1) + steps, min=loc.unsqueeze(-1), max=hic.unsqueeze(-1))
        cand[..., 0] = _clip(y, loc, hic)  # the full Newton step is y itself (held ones exactly on bounds)
        s = cand - xc.unsqueeze(-1)
        lin = (grad.unsqueeze(-1) * s).sum(-2)  # (nc, 2S), < 0 for a descent step
        delta = lin + 0.5 * (s * torch.bmm(Hc, s)).sum(-2)
        ok = (lin < 0) & (delta <= armijo * lin)
        best = torch.argmin(torch.where(ok, delta, torch.inf), dim=-1, keepdim=True)
        nodesc = ~ok.any(-1)
        stepped = ~notpd & ~nodesc
        dbest = delta.gather(-1, best).squeeze(-1)
        xn = cand.gather(-1, best.unsqueeze(1).expand(nc, m, 1)).squeeze(-1)  # exactly on a bound if clipped
        xc = torch.where(stepped.unsqueeze(-1), xn, xc)
        iters[sel] += stepped.long()
        stall = stepped & (-dbest < min_rel_improve * fval.abs())
        fval = torch.where(stepped, fval + dbest, fval)
        pending = torch.where(stall, int(BoxQPStatus.SMALL_IMPROVEMENT), pending_code)
        pending = torch.where(nodesc, int(BoxQPStatus.NO_DESCENT), pending)
        pending = torch.where(notpd, int(BoxQPStatus.NOT_POSITIVE_DEFINITE), pending)


def _box_qp_scalar_x(H: Tensor, g: Tensor, lo: Tensor, hi: Tensor) -> Tensor:
    """Closed form for one variable: ``x = clip(-g/h, lower, upper)`` when ``h > 0``, else ``clip(0)``."""
    h = H[..., 0]  # (nb, 1)
    x = _clip(-g / torch.where(h > 0, h, 1.0), lo, hi)
    return torch.where(h > 0, x, _clip(torch.zeros_like(x), lo, hi))
