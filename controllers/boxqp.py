"""Batched box-constrained quadratic programs: active-set projected Newton with a gradient safeguard.

Solves, independently for every batch element,

    minimize_x   f(x) = ½ xᵀ H x + gᵀ x     subject to   lower ≤ x ≤ upper,

with the projected-Newton method of control-limited DDP (Tassa, Mansard & Todorov, "Control-limited
differential dynamic programming", ICRA 2014, Algorithm 1), made globally convergent and fast on problems
with many active bounds.  The iterate ``x`` stays feasible and its objective never increases; every
iteration (one or two Cholesky factorizations) takes the best of three families of candidates:

* **The projected-gradient arc** ``clip(x − β D⁻¹∇f(x))`` (``D = diag(H)``), ``β`` from the exact minimizer
  along ``D⁻¹∇f`` down.  It always contains a descent step (Calamai & Moré, "Projected gradient methods for
  linearly constrained problems", Math. Prog. 39, 1987), which makes the method globally convergent, and
  its best point, the *Cauchy point* ``x_c``, puts many variables on their bounds at once.
* **Newton points of working sets.**  A variable is *held* on a bound when a diagonal Newton step
  ``zᵢ − ∂ᵢf(z) / Hᵢᵢ`` carries it onto or past that (finite) bound; the Newton point of the working set puts
  the held variables on their bounds and minimizes ``f`` over the free ones (a Cholesky factor of the free
  block of ``H``).  At a feasible ``z`` the held set is Bertsekas' ε-active set ("Projected Newton methods
  for optimization problems with simple constraints", SIAM J. Control Optim. 20(2), 1982) with ε from
  ``diag(H)``: Tassa's clamped set (on the bound, gradient outwards) plus the variables a hair's breadth
  from it.  Two such points are used: that of the Cauchy point ``x_c`` (the subspace step of gradient
  projection methods, Moré & Toraldo, SIAM J. Optim. 1(1), 1991), and that of ``z``, which follows the
  primal-dual active-set sequence ``z ← its Newton point`` and may leave the box (Hintermüller, Ito &
  Kunisch, "The primal-dual active set strategy as a semismooth Newton method", SIAM J. Optim. 13(3),
  2002).  The latter typically settles the working set in a handful of iterations where feasible methods
  change a few bounds per iteration (6 iterations instead of 60-100 on the 100-variable QPs of a batch-iLQR
  pendulum swing-up).  It can cycle: the map from one working set to the next is deterministic, so a
  repeated (hashed) working set restarts it from ``x``, as does every tenth iteration.
* **The projected Newton arcs** ``clip(x + α (y − x))`` towards the Newton point ``y`` of ``z`` and
  ``clip(x_c + α (y_c − x_c))`` towards that of the Cauchy point (``α = 1`` is the clipped Newton point
  itself, held variables exactly on their bounds).  Such an arc alone is not a descent path: a variable a
  hair above its bound with the gradient pushing it out is free for Tassa's test, the ill-conditioned
  Newton step hits that bound at ``α ~ 1e-8``, and the arc ascends for every step size tried; this is what
  stopped the plain method with ``NO_DESCENT`` far from the optimum.
* **Primal active-set steps** (Nocedal & Wright, *Numerical Optimization*, 2nd ed., Algorithm 16.3): the
  first point where the segment from ``x`` to a Newton point meets a bound, that variable exactly on it,
  for the two Newton points above and for that of the face of ``x`` itself (its variables on a bound held,
  except the one whose multiplier is most negative once the free gradient is smaller than it).  Each adds
  a bound and lowers ``f``; when ``cond(H)`` is large (1e8 and more) and the solution lies on a face whose
  weak directions the gradient hardly sees, the other candidates change bounds back and forth, and these
  steps are what reaches that face (before: ``MAX_ITERATIONS`` on 7 of 24 such problems at cond 1e8).

All candidates are evaluated at once through the exact change ``Δ(s) = ∇fᵀs + ½sᵀHs`` of the quadratic
(``s`` = candidate − x, free of the cancellation of comparing two objective values) and, among those
satisfying the Armijo condition ``Δ(s) ≤ armijo·∇fᵀs < 0``, the lowest is taken.

**Statuses are certificates: a stated relative objective gap.**  ``CONVERGED`` and ``ALL_CLAMPED`` mean
that the returned ``x`` was checked to satisfy

    f(x) − min f  ≤  objective_gap  ≤  gap_tolerance = gap_tol · (½|xᵀHx| + |gᵀx|),

the gap relative to the size of the objective's terms, with ``gap_tol`` 1e-12 in float64 and 1e-6 in
float32 (defaults).  The bound is weak duality.  In the Jacobi-scaled variables (``D = diag(H)``, entries
that are not positive replaced by 1, ``H̃ = D^-½ H D^-½``, ``γ̃ = D^-½ ∇f(x)``), let ``F`` be the variables
not exactly on a bound and take the multipliers of the others as those that leave the Lagrangian's
gradient in the span of ``F``'s coordinates, ``ν = γ̃ − H̃ d`` with ``d = H̃_FF⁻¹ γ̃_F`` (zero outside
``F``), projected onto their sign (``≥ 0`` on a lower bound, ``≤ 0`` on an upper one; ``e`` what the
projection removed).  For convex ``f`` the Lagrangian's minimum is then ``f(x) − gap`` with::

    objective_gap = ½ γ̃_Fᵀ H̃_FF⁻¹ γ̃_F + ½ eᵀ H̃⁻¹ e

(the bound terms ``λᵀ(x − lower)`` vanish: those variables are exactly on their bound).  The first term is
the decrease a Newton step on the face of ``x`` would make, so the bound is tight on the right face and
``e = 0`` there; it is the exact ``f(x) − f*`` in that case, free of the Schur-complement factor that the
plain choice ``ν = γ̃`` would put between them (up to ``cond(H)``).  ``H̃`` is factored with ``mε``
(``ε`` the machine epsilon) added to its unit diagonal, which accepts an ``H`` that is positive
semidefinite up to round-off; where that fails ``H`` is not convex, a KKT point is not certified to be the
minimizer, and the status is ``NOT_POSITIVE_DEFINITE``.  Two Cholesky factorizations per element, done
only where the cheap test below already holds.  Everything is invariant under ``f → c·f`` and under a
change of units of each variable, so the status means the same whatever the scaling.  The gap is computed
in floating point: it bounds the exact gap of ``x`` up to the rounding of ``∇f(x)``, ``½ρᵀH̃_FF⁻¹ρ`` for
``ρ ~ ε(|H̃||u| + |g̃|)`` (``u = D^½x``), about ``ε²·cond(H)`` of the terms, far below ``gap_tol`` in
float64 up to ``cond(H) ≈ 1e14``.  Why the gap and not a gradient test: a gradient residual ``r`` leaves
``f(x) − f*`` as large as ``½ rᵀH⁻¹r``, so any gradient tolerance of ``√ε`` of the terms (the test
before issue 22) let points a box width off along a weak direction pass when ``cond(H) ≳ 1e8`` (measured:
CONVERGED 60 % above the minimum at cond 1e12, 2.5e-3 in float32 at cond 1e4).

Inputs of lower precision than float64 (float32, …) are solved in float64 (widened exactly), and the
point rounded to their dtype is certified again, in float64, against their data; the float32 tolerance
covers that rounding (measured: ≤ 2.3e-11 of the terms at cond(H) = 1e8), and a point that loses its
certificate in the rounding is ``NOT_CERTIFIED``.

The iterations stop on the cheap first test, the KKT condition in projected-gradient form for the
Jacobi-scaled problem (``g̃ = D^-½ g``)::

    kkt_residual  = ‖D^½ (x − clip(x − D⁻¹∇f(x), lower, upper))‖₂
    kkt_tolerance = tol · (‖g̃‖₂ + ‖H̃‖_F ‖u‖₂)                  (‖·‖_F: the Frobenius norm)

and the gap is computed where it holds: a point that passes it but not the gap is iterated further (a
Newton step on the right face usually closes the gap), and where that fails the status names the reason
(``SMALL_IMPROVEMENT``, ``NO_DESCENT``, ``MAX_ITERATIONS``).  Successes satisfy both tests.

Shapes: ``H (*B, m, m)`` symmetric, ``g (*B, m)``, ``lower``/``upper`` broadcastable to ``(*B, m)`` (``±inf``
means unbounded).  Everything is batched: no Python loop over batch elements, one loop over iterations.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, replace
from typing import NamedTuple

import torch
from torch import Tensor

from torchlie._batch import broadcast_shapes

# (also used by the solvers, in compiled programs: box_qp_two, box_qp_fixed, small_spd_solve)
__all__ = ["BoxQPStatus", "BoxQPResult", "box_qp", "masked_hessian", "at_lower"]


class BoxQPStatus(enum.IntEnum):
    """Why the solver stopped for one batch element (``BoxQPResult.status`` holds these values).

    Only ``CONVERGED`` and ``ALL_CLAMPED`` are successes (:attr:`success`); both certify, at the returned
    ``x``, ``objective_gap ≤ gap_tolerance`` (``f(x) − min f`` within the stated relative gap, ``H``
    convex) and ``kkt_residual ≤ kkt_tolerance`` (see the module docstring).  The failures return the best
    point found so far (feasible, never worse than the start), except ``NON_FINITE`` (NaN).
    """

    CONVERGED = 0  #: the certificate holds and at least one variable is free
    #: failure: stalled, the last step lowered f by less than ``min_rel_improve``·|f| (round-off level)
    #: while the certificate still fails
    SMALL_IMPROVEMENT = 1
    ALL_CLAMPED = 2  #: the certificate holds and every variable is clamped (a vertex of the box is optimal)
    MAX_ITERATIONS = 3  #: failure: ``max_iter`` reached without the certificate
    #: failure: ``H`` is not convex (its free block or, at a KKT point, ``H`` itself, with ``mε`` added to the
    #: Jacobi-scaled diagonal, has no Cholesky factor): the point cannot be certified as the minimizer
    NOT_POSITIVE_DEFINITE = 4
    NO_DESCENT = 5  #: failure: no candidate step satisfied the Armijo condition (round-off level)
    NON_FINITE = 6  #: failure: NaN or inf in ``H``, ``g`` or ``x0`` (or NaN bounds) of this element
    #: failure: an input of lower precision than float64 was solved (and certified) in float64, but the
    #: point rounded to its dtype fails the certificate
    NOT_CERTIFIED = 7

    @property
    def success(self) -> bool:
        """The returned point is certified (the objective gap and the KKT test were checked at it)."""
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
        kkt_tolerance: ``(*B,)`` ``tol·(‖D^-½ g‖₂ + ‖D^-½ H D^-½‖_F ‖D^½ x‖₂)``.
        objective_gap: ``(*B,)`` an upper bound on ``f(x) − min f`` at the returned ``x`` (module docstring;
            ``inf`` where ``H`` is not convex or the bound was not computed: the KKT test failed at an
            element that stopped for another reason is still bounded, NaN if ``NON_FINITE``).
        gap_tolerance: ``(*B,)`` ``gap_tol·(½|xᵀHx| + |gᵀx|)``.  The status is a success
            (``CONVERGED``/``ALL_CLAMPED``) iff ``objective_gap ≤ gap_tolerance`` and
            ``kkt_residual ≤ kkt_tolerance``.
    """

    x: Tensor
    free: Tensor
    clamped: Tensor
    status: Tensor
    iterations: Tensor
    kkt_residual: Tensor
    kkt_tolerance: Tensor
    objective_gap: Tensor
    gap_tolerance: Tensor

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


#: default relative objective-gap tolerance of the certificate, by dtype (module docstring); float64 is used
#: for every dtype it does not list
_GAP_TOL = {torch.float64: 1e-12, torch.float32: 1e-6}


class _Sol(NamedTuple):
    """The flattened solution of :func:`_solve` (fields as in :class:`BoxQPResult`, ``(nb, …)``)."""

    x: Tensor
    status: Tensor
    iters: Tensor
    clamped: Tensor
    res: Tensor
    kkt_tol: Tensor
    gap: Tensor
    gap_tol: Tensor


def box_qp(
    H: Tensor,
    g: Tensor,
    lower: Tensor | float,
    upper: Tensor | float,
    x0: Tensor | None = None,
    *,
    max_iter: int = 100,
    tol: float | None = None,
    gap_tol: float | None = None,
    min_rel_improve: float | None = None,
    armijo: float = 0.1,
    step_dec: float = 0.5,
    n_steps: int = 24,
    check: bool = True,
) -> BoxQPResult:
    """Solve ``min ½xᵀHx + gᵀx  s.t.  lower ≤ x ≤ upper`` for a batch (projected Newton, see the module doc).

    Args:
        H: ``(*B, m, m)`` symmetric Hessians (positive definite for a certified minimizer).
        g: ``(*B, m)`` linear terms.
        lower, upper: bounds broadcastable to ``(*B, m)``; ``-inf``/``inf`` for unbounded components.
        x0: optional tensor broadcastable to ``(*B, m)``, a warm start (projected onto the box); zero
            (projected) by default.
        max_iter: iterations at most (one or two Cholesky factorizations each).
        tol: the cheap first test of the certificate (and the iterations' stopping test):
            ``‖D^½ (x − clip(x − D⁻¹(Hx + g), lower, upper))‖₂ ≤ tol·(‖D^-½ g‖₂ + ‖D^-½ H D^-½‖_F ‖D^½ x‖₂)``
            with ``D = diag(H)`` (the projected gradient of the Jacobi-scaled problem against the size of
            its terms); default ``sqrt(eps)`` of the dtype (1.5e-8 in float64, 3.5e-4 in float32).
        gap_tol: the certificate proper: an element succeeds iff, besides ``tol``, the bound on
            ``f(x) − min f`` of the module docstring is at most ``gap_tol·(½|xᵀHx| + |gᵀx|)``; default
            ``1e-12`` in float64 and ``1e-6`` in float32 (and lower precisions), see the module docstring.
        min_rel_improve: declare a stall (``SMALL_IMPROVEMENT``, a failure) when an accepted step lowers the
            objective by less than this fraction of ``|f|`` and the certificate still fails; default ``eps``
            of the working precision.
        armijo: an accepted step ``s`` must achieve this fraction of its linearly predicted decrease
            ``−∇fᵀs``.
        step_dec, n_steps: candidate step sizes along each arc are ``step_dec**j`` times its initial step
            (1 for Newton, the exact minimizer along the direction for the projected gradient),
            ``j < n_steps``, all evaluated at once.  The projected-gradient arc then contains an Armijo step
            whenever ``cond(D^-½ H D^-½)`` is below about ``step_dec**-(n_steps - 1)`` (8e6 by default).
        check: validate ``lower <= upper`` (a host sync); solvers that already did may pass ``False``.

    Gradients: with autograd on and ``H``, ``g`` or a bound requiring grad, ``x`` carries the derivative of
    the minimizer on the face it lies on (the active set held fixed, clamped variables moving with their
    bound), which is the derivative of the solution wherever the active set is locally constant; the
    iterations themselves run without a graph.

    Returns:
        :class:`BoxQPResult` with per-element status, ``kkt_residual``/``kkt_tolerance`` and
        ``objective_gap``/``gap_tolerance``; one bad element never affects the others.  Inputs of lower
        precision than float64 are solved in float64 and the rounded point is certified against their
        data.  ``m == 1`` is solved in closed form and ``m ≤ 3`` by enumerating faces, certified the same
        way.
    """
    graph = any(isinstance(v, Tensor) and v.requires_grad for v in (H, g, lower, upper))
    if graph and torch.is_grad_enabled():
        # solve without a graph, then attach the derivative of the minimizer on the face it lies on
        with torch.no_grad():
            res = box_qp(H.detach(), g.detach(), _detached(lower), _detached(upper),
                         None if x0 is None else x0.detach(), max_iter=max_iter, tol=tol, gap_tol=gap_tol,
                         min_rel_improve=min_rel_improve, armijo=armijo, step_dec=step_dec, n_steps=n_steps,
                         check=check)
        return replace(res, x=_with_face_derivative(H, g, lower, upper, res))
    H, g, lo, hi, x0, batch = _inputs(H, g, lower, upper, x0, check)
    dtype, m = H.dtype, H.shape[-1]
    gap_tol = _GAP_TOL.get(dtype, _GAP_TOL[torch.float32]) if gap_tol is None else gap_tol
    nb = int(torch.Size(batch).numel())
    H, g, lo, hi = H.reshape(nb, m, m), g.reshape(nb, m), lo.reshape(nb, m), hi.reshape(nb, m)
    x0 = None if x0 is None else x0.reshape(nb, m)
    H, g, lo, hi, x0, finite = _sanitize(H, g, lo, hi, x0)
    eps = torch.finfo(torch.float64).eps
    opts = dict(gap_tol=gap_tol, max_iter=max_iter, armijo=armijo, step_dec=step_dec, n_steps=n_steps,
                tol=eps ** 0.5 if tol is None else tol,
                min_rel_improve=eps if min_rel_improve is None else min_rel_improve)
    if dtype == torch.float64:
        sol = _solve(H, g, lo, hi, x0, finite, **opts)
    else:  # solved in float64, rounded, and certified against the (exactly widened) data
        wide = [t.double() for t in (H, g, lo, hi)]
        sol = _solve(*wide, None if x0 is None else x0.double(), finite, **opts)
        tol_in = torch.finfo(dtype).eps ** 0.5 if tol is None else tol
        sol = _rounded(sol, *wide, finite, dtype, tol_in, gap_tol)
    fin1 = finite.unsqueeze(-1)
    out, nan = (*batch, m), torch.nan
    return BoxQPResult(
        x=torch.where(fin1, sol.x, nan).reshape(out),
        free=(~sol.clamped).reshape(out),
        clamped=sol.clamped.reshape(out),
        status=sol.status.reshape(batch),
        iterations=sol.iters.reshape(batch),
        kkt_residual=torch.where(finite, sol.res, nan).reshape(batch),
        kkt_tolerance=torch.where(finite, sol.kkt_tol, nan).reshape(batch),
        objective_gap=torch.where(finite, sol.gap, nan).reshape(batch),
        gap_tolerance=torch.where(finite, sol.gap_tol, nan).reshape(batch),
    )


def at_lower(x: Tensor, lo: Tensor, hi: Tensor, grad: Tensor) -> Tensor:
    """Which bound a clamped variable sits on (True: the lower one), for the derivative of a solution with
    respect to its bounds: the nearer bound, compared as distances (exact with an infinite other bound,
    where a midpoint would be infinite), and where ``lower == upper`` the one the gradient ``grad`` of the
    objective pushes against (``grad ≥ 0``: the minimizer would go lower)."""
    dlo, dhi = x - lo, hi - x
    return (dlo < dhi) | ((dlo == dhi) & (grad >= 0))


def _detached(v):
    return v.detach() if isinstance(v, Tensor) else v


def _with_face_derivative(H: Tensor, g: Tensor, lower, upper, res: BoxQPResult) -> Tensor:
    """``res.x`` carrying the derivative of the minimizer with respect to ``H``, ``g`` and the bounds on the
    face it lies on: clamped variables at their (nearer) bound, the free ones from
    ``H_FF x_F = −(g_F + H_FC x_C)`` (the implicit function theorem on the KKT system with the active set
    held).  The value is ``res.x`` unchanged; elements that are not finite or whose free block is not
    positive definite get no derivative (their status already says they failed)."""
    x, clamped = res.x, res.clamped
    lo = torch.as_tensor(lower, dtype=H.dtype, device=H.device).expand_as(x)
    hi = torch.as_tensor(upper, dtype=H.dtype, device=H.device).expand_as(x)
    free = ~clamped
    xd = x.detach()
    grad = g.detach() + (H.detach() @ xd.unsqueeze(-1)).squeeze(-1)
    on_lo = clamped & at_lower(xd, lo.detach(), hi.detach(), grad)
    usable = torch.isfinite(xd).all(-1) & res.status.ne(int(BoxQPStatus.NON_FINITE))
    good = usable.unsqueeze(-1)
    eye = torch.eye(H.shape[-1], dtype=H.dtype, device=H.device)
    Hs = torch.where(good.unsqueeze(-1), H, eye)
    gs = torch.where(good, g, 0.0)
    xc = torch.where(clamped & good, torch.where(on_lo, lo, hi), 0.0)
    rhs = torch.where(free, -(gs + (Hs @ xc.unsqueeze(-1)).squeeze(-1)), 0.0)
    L, info = torch.linalg.cholesky_ex(masked_hessian(Hs, free))
    ok = (info == 0) & usable
    L = torch.where(ok[..., None, None], L, eye)
    xf = torch.cholesky_solve(rhs.unsqueeze(-1), L).squeeze(-1)
    face = torch.where(free, xf, xc)
    return x + torch.where(ok.unsqueeze(-1), face - face.detach(), 0.0)


def _inputs(H, g, lower, upper, x0, check: bool):
    """Validate and broadcast the arguments of :func:`box_qp`: ``(H, g, lo, hi, x0, batch)``, expanded to
    ``(*batch, m, m)`` and ``(*batch, m)``."""
    if not isinstance(H, Tensor) or not isinstance(g, Tensor):
        raise TypeError("box_qp: H and g must be tensors")
    if H.dim() < 2 or H.shape[-1] != H.shape[-2]:
        raise ValueError(f"box_qp: H must have shape (*B, m, m), got {tuple(H.shape)}")
    m = H.shape[-1]
    if g.dim() < 1 or g.shape[-1] != m:
        raise ValueError(f"box_qp: g must have shape (*B, {m}) to match H, got {tuple(g.shape)}")
    if not H.dtype.is_floating_point or g.dtype != H.dtype:
        raise TypeError(f"box_qp: H and g must share one floating dtype, got {H.dtype} and {g.dtype}")
    if x0 is not None and not isinstance(x0, Tensor):
        raise TypeError(f"box_qp: argument 'x0' must be a torch.Tensor or None, got {type(x0).__name__}")
    dtype, device = H.dtype, H.device
    batch = broadcast_shapes(H.shape[:-2], g.shape[:-1])
    for name, v in (("lower", lower), ("upper", upper), ("x0", x0)):
        if isinstance(v, Tensor) and (v.dtype != dtype or v.device != device):
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
    if x0 is not None:
        try:
            x0 = x0.expand(*batch, m)
        except RuntimeError:
            raise ValueError(f"box_qp: argument 'x0' must broadcast to (*B, m) = {(*batch, m)} (the batch of "
                             f"H and g), got {tuple(x0.shape)}") from None
    if check and bool((lo > hi).any()):
        raise ValueError("box_qp: lower must be <= upper everywhere")
    return H.expand(*batch, m, m), g.expand(*batch, m), lo, hi, x0, batch


def _sanitize(H, g, lo, hi, x0):
    """Mark the elements with NaN or inf in ``H``, ``g`` or ``x0`` or NaN bounds, and replace their data by
    a harmless problem (identity, zero, unbounded) so that they cannot leak into batched factorizations."""
    finite = torch.isfinite(H).flatten(1).all(-1) & torch.isfinite(g).all(-1) & ~torch.isnan(lo).any(-1) \
        & ~torch.isnan(hi).any(-1)
    if x0 is not None:
        finite = finite & torch.isfinite(x0).all(-1)
    fin1 = finite.unsqueeze(-1)
    eye = torch.eye(H.shape[-1], dtype=H.dtype, device=H.device)
    H = torch.where(fin1.unsqueeze(-1), H, eye)
    g = torch.where(fin1, g, 0.0)
    lo = torch.where(fin1, lo, -torch.inf)
    hi = torch.where(fin1, hi, torch.inf)
    x0 = None if x0 is None else torch.where(fin1, x0, 0.0)
    return H, g, lo, hi, x0, finite


def _solve(H, g, lo, hi, x0, finite, *, tol, gap_tol, max_iter, **kw) -> _Sol:
    """:func:`box_qp` on the flattened, sanitized batch ``H (nb, m, m)``, …, in the dtype of ``H``."""
    nb, m = g.shape
    device = g.device
    dsq, hsc = _jacobi(H)  # the scaling of the certificate
    if m == 1:
        x = _box_qp_scalar_x(H, g, lo, hi)
    elif _enumerate_faces(m, nb, device):
        # small problems: the exact minimizer by enumerating the faces of the box (below), so a warm start
        # has nothing to add; the iterations then only certify it (and take over where no face qualifies:
        # H not positive definite on any face, from the warm start)
        x = _box_qp_enum_x(H, g, lo, hi, None if x0 is None else _clip(x0, lo, hi))
    else:
        x = torch.zeros_like(g) if x0 is None else x0
        x = _clip(x, lo, hi)
    nan = torch.full((nb,), torch.nan, dtype=g.dtype, device=device)
    sol = _Sol(x, torch.full((nb,), int(BoxQPStatus.NON_FINITE), dtype=torch.long, device=device),
               torch.zeros(nb, dtype=torch.long, device=device), torch.zeros_like(x, dtype=torch.bool),
               nan, nan.clone(), nan.clone(), nan.clone())
    if m == 1 or _enumerate_faces(m, nb, device):
        c = _certify(H, g, lo, hi, x, dsq, hsc, tol, gap_tol)
        sol = sol._replace(clamped=c.clamped, res=c.res, kkt_tol=c.kkt_tol, gap=c.gap, gap_tol=c.gap_tol)
        if m == 1:  # closed form: certified like the rest (a failure here would mean round-off trouble)
            st = _certified_status(c.cert, c.clamped, int(BoxQPStatus.NO_DESCENT))
            st = torch.where((H[:, 0, 0] <= 0) | ~c.convex, int(BoxQPStatus.NOT_POSITIVE_DEFINITE), st)
            return sol._replace(status=torch.where(finite, st, sol.status), iters=sol.iters + 1)
        if bool((c.cert | ~finite).all()):  # every enumerated point certified (the usual case): no iteration
            st = _certified_status(c.cert, c.clamped, 0)
            return sol._replace(status=torch.where(finite, st, sol.status))
    _iterate(H, g, lo, hi, dsq, hsc, finite, sol, tol=tol, gap_tol=gap_tol, max_iter=max_iter, **kw)
    return sol


def _rounded(sol: _Sol, H, g, lo, hi, finite, dtype, tol: float, gap_tol: float) -> _Sol:
    """The float64 solution ``sol`` of the widened data ``H, g, lo, hi`` rounded to ``dtype`` and certified
    again (in float64) at the rounded point; a certified solution whose rounding fails the certificate is
    ``NOT_CERTIFIED``."""
    x = sol.x.to(dtype)
    dsq, hsc = _jacobi(H)
    c = _certify(H, g, lo, hi, x.double(), dsq, hsc, tol, gap_tol)
    ok = torch.zeros_like(finite)
    for s in _SUCCESS:
        ok = ok | (sol.status == s)
    st = torch.where(ok, _certified_status(c.cert, c.clamped, int(BoxQPStatus.NOT_CERTIFIED)), sol.status)
    return _Sol(x, st, sol.iters, c.clamped, *(v.to(dtype) for v in (c.res, c.kkt_tol, c.gap, c.gap_tol)))


class _Cert(NamedTuple):
    """The certificate at a point (flattened batch): see :func:`_certify`."""

    grad: Tensor
    clamped: Tensor
    res: Tensor
    kkt_tol: Tensor
    gap: Tensor
    gap_tol: Tensor
    cert: Tensor
    convex: Tensor


def _certify(H, g, lo, hi, x, dsq, hsc, tol: float, gap_tol: float, need: Tensor | None = None) -> _Cert:
    """The certificate of the module docstring at ``x``: the clamped set, the KKT residual and its
    tolerance, the objective-gap bound and its tolerance, whether both hold and whether ``H`` is convex.

    The gap (two Cholesky factorizations) is computed only where the cheap KKT test holds or ``need`` is
    set (one host sync); elsewhere it is ``inf`` (``nan`` tolerance) and ``H`` counts as convex.  (Where
    ``H`` is not positive definite up to ``mε`` the gap is ``inf`` and ``convex`` is false.)
    """
    grad, clamped, res, kkt_tol = _kkt(H, g, lo, hi, x, dsq, hsc, tol)
    kok = (res <= kkt_tol) & torch.isfinite(kkt_tol)  # an overflowed scale certifies nothing
    need = kok if need is None else need | kok
    gap = torch.full_like(res, torch.inf)
    gtol = torch.full_like(res, torch.nan)
    convex = torch.ones_like(kok)
    n_need = int(need.sum())
    if n_need == need.numel():
        gap, scale, convex = _objective_gap(H, g, lo, hi, x, dsq)
        gtol = gap_tol * scale
    elif n_need:
        j = need.nonzero().squeeze(-1)
        gj, sj, cj = _objective_gap(H[j], g[j], lo[j], hi[j], x[j], dsq[j])
        gap, convex = gap.index_copy(0, j, gj), convex.index_copy(0, j, cj)
        gtol = gtol.index_copy(0, j, gap_tol * sj)
    return _Cert(grad, clamped, res, kkt_tol, gap, gtol, kok & (gap <= gtol) & torch.isfinite(gtol), convex)


def _objective_gap(H, g, lo, hi, x, dsq, small: bool = False) -> tuple[Tensor, Tensor, Tensor]:
    """The bound ``gap ≥ f(x) − min f`` of the module docstring, the scale ``½|xᵀHx| + |gᵀx|`` of the
    objective's terms, and whether ``H̃ + mεI`` is positive definite (else the gap is ``inf``).

    ``F`` are the variables not exactly on a bound.  In the Jacobi-scaled variables (``H̃ = D^-½HD^-½``,
    ``γ̃ = D^-½∇f(x)``, ``H̃ₛ = H̃ + mεI``): ``d = H̃ₛ,FF⁻¹ γ̃_F`` (zero elsewhere), the multipliers
    ``ν = γ̃ − H̃ₛd`` on the bound variables projected onto their sign (``≥ 0`` on a lower bound, ``≤ 0`` on
    an upper one, free when both coincide), ``e`` what the projection removed, and
    ``gap = ½ γ̃_Fᵀd + ½ eᵀH̃ₛ⁻¹e``.  ``small``: the factorizations written out elementwise
    (:func:`_small_cholesky`; for a few variables in a compiled program, where each LAPACK call is a
    library call per element); equal up to round-off.
    """
    m = H.shape[-1]
    hx = _matvec(H, x)
    grad = g + hx
    on_lo, on_hi = x == lo, x == hi
    bound = on_lo | on_hi
    Hs = H / (dsq.unsqueeze(-1) * dsq.unsqueeze(-2)) \
        + m * torch.finfo(H.dtype).eps * torch.eye(m, dtype=H.dtype, device=H.device)
    gt = grad / dsq
    factor, lower, upper = _SMALL if small else _LAPACK
    LF, okF = factor(masked_hessian(Hs, ~bound))
    w = lower(LF, torch.where(bound, 0.0, gt))
    d = upper(LF, w)
    nu = gt - _matvec(Hs, d)
    lam = torch.where(on_lo & ~on_hi, nu.clamp(min=0), torch.where(on_hi & ~on_lo, nu.clamp(max=0), nu))
    L, convex = factor(Hs)
    v = lower(L, torch.where(bound, nu - lam, 0.0))
    gap = 0.5 * (w.square().sum(-1) + v.square().sum(-1))
    gap = torch.where(convex & okF, gap, torch.inf)
    scale = 0.5 * (x * hx).sum(-1).abs() + (g * x).sum(-1).abs()
    return gap, scale, convex


# (factor, L⁻¹b, L⁻ᵀy) of (nb, m, m) matrices and (nb, m) vectors: by LAPACK, or written out entry by entry
_LAPACK = (
    lambda A: _safe_cholesky(A),
    lambda L, b: torch.linalg.solve_triangular(L, b.unsqueeze(-1), upper=False).squeeze(-1),
    lambda L, y: torch.linalg.solve_triangular(L.mT, y.unsqueeze(-1), upper=True).squeeze(-1),
)
_SMALL = (
    lambda A: _small_cholesky(A),
    lambda L, b: torch.stack(_small_lower_solve(L, b), -1),
    lambda L, y: torch.stack(_small_upper_solve(L, list(y.unbind(-1))), -1),
)


def _safe_cholesky(A: Tensor) -> tuple[Tensor, Tensor]:
    """Cholesky factors of ``A (nb, m, m)`` and where they exist (the identity where not)."""
    L, info = torch.linalg.cholesky_ex(A)
    ok = info == 0
    return torch.where(ok.view(-1, 1, 1), L, torch.eye(A.shape[-1], dtype=A.dtype, device=A.device)), ok


def _certified_status(cert: Tensor, clamped: Tensor, otherwise: Tensor | int) -> Tensor:
    code = torch.where(clamped.all(-1), int(BoxQPStatus.ALL_CLAMPED), int(BoxQPStatus.CONVERGED))
    return torch.where(cert, code, otherwise)


_RESTART = 10  # the active-set sequence restarts from the best feasible point at least this often


def _change(H: Tensor, grad: Tensor, x: Tensor, c: Tensor) -> tuple[Tensor, Tensor]:
    """``∇fᵀs`` and the exact change ``∇fᵀs + ½sᵀHs`` of the quadratic for candidates ``c (nb, m, S)``,
    ``s = c − x``: no cancellation of comparing two objective values."""
    s = c - x.unsqueeze(-1)
    lin = (grad.unsqueeze(-1) * s).sum(-2)
    return lin, lin + 0.5 * (s * torch.bmm(H, s)).sum(-2)


def _arc(x: Tensor, d: Tensor, steps: Tensor, lo: Tensor, hi: Tensor, end: Tensor | None = None) -> Tensor:
    """``(nb, m, S)`` points ``clip(x + t d)`` for the step sizes ``steps`` ``(S,)`` or ``(nb, S)``; the first
    is replaced by ``clip(end)`` when given (the exact target of a unit step, free of ``x + (end − x)``'s
    rounding)."""
    t = steps.unsqueeze(-2) if steps.dim() == 2 else steps
    c = torch.clamp(x.unsqueeze(-1) + d.unsqueeze(-1) * t, min=lo.unsqueeze(-1), max=hi.unsqueeze(-1))
    if end is not None:
        c[..., 0] = _clip(end, lo, hi)
    return c


def _breakpoint(x: Tensor, d: Tensor, lo: Tensor, hi: Tensor) -> Tensor:
    """``(nb, m, 1)``: the first point where the segment ``x + t d``, ``0 ≤ t ≤ 1``, from a feasible ``x``
    meets a bound, that bound's variables exactly on it (the step of a primal active-set method, which
    adds one bound; ``x + d`` if none is met)."""
    t = torch.where(d < 0, (lo - x) / d, torch.where(d > 0, (hi - x) / d, torch.inf)).clamp(min=0)
    tmin = t.amin(-1, keepdim=True).clamp(max=1.0)
    c = x + tmin * d
    hit = t <= tmin
    c = torch.where(hit & (d < 0), lo, torch.where(hit & (d > 0), hi, c))
    return _clip(c, lo, hi).unsqueeze(-1)


def _working_set(z: Tensor, gz: Tensor, lo: Tensor, hi: Tensor, hdiag: Tensor) -> Tensor:
    """``(nb, m)`` int8: 1 (2) where a diagonal Newton step ``zᵢ − ∂ᵢf(z)/Hᵢᵢ`` reaches the lower (upper)
    bound, which then holds the variable, 0 where it is free."""
    hold_lo = ((z - lo) * hdiag <= gz) & torch.isfinite(lo)
    hold_hi = ((hi - z) * hdiag <= -gz) & torch.isfinite(hi) & ~hold_lo
    return hold_lo.to(torch.int8) + 2 * hold_hi.to(torch.int8)


def _newton_point(H: Tensor, g: Tensor, lo: Tensor, hi: Tensor, w: Tensor) -> tuple[Tensor, Tensor]:
    """The minimizer of f on the face of working set ``w`` (held variables on their bound, the free ones
    minimizing with those fixed; one Cholesky factor of the free block), and where that block is not PD.

    It is solved for directly (not as a correction to an iterate), so its residual is relative to its own
    size.
    """
    free = w == 0
    b = torch.where(w == 1, lo, torch.where(w == 2, hi, torch.zeros((), dtype=H.dtype, device=H.device)))
    L, info = torch.linalg.cholesky_ex(masked_hessian(H, free))
    notpd = info != 0
    if bool(notpd.any()):  # keep the solve finite for those (their step is discarded anyway)
        L = torch.where(notpd.view(-1, 1, 1), torch.eye(H.shape[-1], dtype=H.dtype, device=H.device), L)
    rhs = torch.where(free, g + _matvec(H, b), 0.0)
    return b - torch.cholesky_solve(rhs.unsqueeze(-1), L).squeeze(-1), notpd


def _face_of(x: Tensor, grad: Tensor, lo: Tensor, hi: Tensor, dsq: Tensor) -> Tensor:
    """The working set of a primal active-set step at a feasible ``x`` (as :func:`_working_set`): every
    variable on a bound held, except, where the largest Jacobi-scaled gradient pointing into the box from a
    bound exceeds that of the free variables (``x`` near the minimizer of its face), that one variable."""
    on_lo, on_hi = x <= lo, (x >= hi) & (x > lo)
    gs = grad / dsq
    inward = torch.where(on_lo, -gs, torch.where(on_hi, gs, 0.0)).clamp(min=0)  # multiplier violations
    free_g = torch.where(on_lo | on_hi, 0.0, gs.abs()).amax(-1, keepdim=True)
    worst = inward.amax(-1, keepdim=True)
    release = (inward == worst) & (worst > free_g)
    release = release & (release.cumsum(-1) == 1)  # one variable
    w = torch.where(on_lo, 1, torch.where(on_hi, 2, 0))
    return torch.where(release, 0, w).to(torch.int8)


def _other_newton_point(H, g, lo, hi, w, w0, y0) -> tuple[Tensor, Tensor]:
    """:func:`_newton_point` of working sets ``w``, reusing ``y0`` (that of ``w0``) where they agree."""
    differ = (w != w0).any(-1)
    notpd = torch.zeros_like(differ)
    if not bool(differ.any()):
        return y0, notpd
    j = differ.nonzero().squeeze(-1)
    yj, notpd_j = _newton_point(H[j], g[j], lo[j], hi[j], w[j])
    return y0.index_copy(0, j, yj), notpd.index_copy(0, j, notpd_j)


def _hash_weights(m: int, device) -> Tensor:
    """Fixed pseudo-random weights < 2⁴⁸ hashing a working set (0 free, 1 lower, 2 upper per variable) into
    one int64 without overflow (m < 16384); a collision only costs an early restart."""
    gen = torch.Generator().manual_seed(0x5EED)
    return torch.randint(0, 1 << 48, (m,), generator=gen, dtype=torch.long).to(device)


def _iterate(H, g, lo, hi, dsq, hsc, finite, sol: _Sol, *, max_iter, tol, gap_tol, min_rel_improve, armijo,
             step_dec, n_steps) -> None:
    """The iterations of :func:`box_qp` on the flattened batch from ``sol.x``, writing the point, status,
    iterations and certificate of every finite element into ``sol``'s tensors in place.

    Only the undecided elements are carried: the working tensors are compacted (one boolean index, a host
    sync) whenever some element stops, so a batch of easy problems with a few hard ones costs little more
    than the hard ones alone.
    """
    dtype, device = H.dtype, H.device
    m = H.shape[-1]
    zero = torch.zeros((), dtype=dtype, device=device)
    alphas = step_dec ** torch.arange(n_steps, dtype=dtype, device=device)  # (S,)
    pending_code = int(BoxQPStatus.MAX_ITERATIONS)
    sel = finite.nonzero().squeeze(-1)
    Hc, gc, loc, hic, dc, hc, xc = H[sel], g[sel], lo[sel], hi[sel], dsq[sel], hsc[sel], sol.x[sel]
    fval = 0.5 * (xc * _matvec(Hc, xc)).sum(-1) + (gc * xc).sum(-1)
    pending = torch.full_like(sel, pending_code)  # a failure decided at the current point, if any
    # The active-set iterate z (may leave the box) and the working sets it visited since its last restart.
    zc = xc
    seen = torch.full((xc.shape[0], _RESTART), -1, dtype=torch.long, device=device)  # keys are ≥ 0
    weights = _hash_weights(m, device)

    for it in range(max_iter + 1):
        # the certificate, its gap part where the KKT test holds or the element stops anyway; a KKT point
        # of a non-convex QP is not certified and iterating cannot change that
        c = _certify(Hc, gc, loc, hic, xc, dc, hc, tol, gap_tol,
                     need=(pending != pending_code) | (it == max_iter))
        pending = torch.where(~c.cert & (c.res <= c.kkt_tol) & ~c.convex,
                              int(BoxQPStatus.NOT_POSITIVE_DEFINITE), pending)
        stop = c.cert | (pending != pending_code) | (it == max_iter)
        grad, clc = c.grad, c.clamped
        if bool(stop.any()):
            idx = sel[stop]
            sol.x[idx] = xc[stop]
            sol.status[idx] = _certified_status(c.cert, clc, pending)[stop]
            for name in ("clamped", "res", "kkt_tol", "gap", "gap_tol"):
                getattr(sol, name)[idx] = getattr(c, name)[stop]
            go = ~stop
            sel, Hc, gc, loc, hic, xc = sel[go], Hc[go], gc[go], loc[go], hic[go], xc[go]
            dc, hc = dc[go], hc[go]
            fval, grad, clc, zc, seen = fval[go], grad[go], clc[go], zc[go], seen[go]
            if sel.numel() == 0:
                break
        nc = sel.shape[0]

        hdiag = Hc.diagonal(dim1=-2, dim2=-1)
        # 1. Cauchy point: the best Armijo step on the projected-gradient arc (scaled by diag(H)) from the
        #    exact minimizer along it down.
        p = torch.where(clc, zero, -grad / torch.where(hdiag > 0, hdiag, 1.0))
        pHp = (p * _matvec(Hc, p)).sum(-1)
        beta0 = torch.where(pHp > 0, -(grad * p).sum(-1) / torch.where(pHp > 0, pHp, 1.0), 1.0)
        c_pg = _arc(xc, p, beta0.unsqueeze(-1) * alphas, loc, hic)
        lin_pg, delta_pg = _change(Hc, grad, xc, c_pg)
        ok_pg = (lin_pg < 0) & (delta_pg <= armijo * lin_pg)
        k = torch.argmin(torch.where(ok_pg, delta_pg, torch.inf), dim=-1, keepdim=True)
        xcp = c_pg.gather(-1, k.unsqueeze(1).expand(nc, m, 1)).squeeze(-1)
        xcp = torch.where(ok_pg.any(-1, keepdim=True), xcp, xc)
        # 2. Newton points of the working sets at z (the active-set sequence) and at the Cauchy point.
        gz = grad if zc is xc else gc + _matvec(Hc, zc)
        wz = _working_set(zc, gz, loc, hic, hdiag)
        y, notpd = _newton_point(Hc, gc, loc, hic, wz)
        wcp = _working_set(xcp, grad + _matvec(Hc, xcp - xc), loc, hic, hdiag)
        ycp, notpd_cp = _other_newton_point(Hc, gc, loc, hic, wcp, wz, y)
        notpd = notpd | notpd_cp
        #    and of the face of x (its clamped variables held): a primal active-set step towards it
        wx = _face_of(xc, grad, loc, hic, dc)
        yx, notpd_x = _other_newton_point(Hc, gc, loc, hic, wx, wz, y)
        yx = torch.where(notpd_x.unsqueeze(-1), xc, yx)  # no step where that face is not convex
        # 3. The projected arcs x → y and Cauchy point → its Newton point (α = 1: the target itself, held
        #    variables exactly on their bounds), the first breakpoints of the segments towards the three
        #    Newton points (a bound added exactly), with the gradient arc: (nc, m, 3S + 3) candidates.
        c_n = torch.cat([_arc(xc, y - xc, alphas, loc, hic, y),
                         _arc(xcp, ycp - xcp, alphas, loc, hic, ycp),
                         _breakpoint(xc, y - xc, loc, hic), _breakpoint(xcp, ycp - xcp, loc, hic),
                         _breakpoint(xc, yx - xc, loc, hic)], -1)
        lin_n, delta_n = _change(Hc, grad, xc, c_n)
        cand = torch.cat([c_n, c_pg], -1)
        lin = torch.cat([lin_n, lin_pg], -1)
        delta = torch.cat([delta_n, delta_pg], -1)
        ok = (lin < 0) & (delta <= armijo * lin)
        best = torch.argmin(torch.where(ok, delta, torch.inf), dim=-1, keepdim=True)
        nodesc = ~ok.any(-1)
        stepped = ~notpd & ~nodesc
        dbest = delta.gather(-1, best).squeeze(-1)
        xn = cand.gather(-1, best.unsqueeze(1).expand(nc, m, 1)).squeeze(-1)  # exactly on a bound if clipped
        xc = torch.where(stepped.unsqueeze(-1), xn, xc)
        sol.iters[sel] += stepped.long()
        stall = stepped & (-dbest < min_rel_improve * fval.abs())
        fval = torch.where(stepped, fval + dbest, fval)
        # The map from one working set to the next is deterministic: a repeated set is a cycle, and the
        # sequence restarts from the best feasible point (so does every sequence every _RESTART iterations).
        key = (wz.long() * weights).sum(-1)
        cycle = (seen == key.unsqueeze(-1)).any(-1)
        seen[:, it % _RESTART] = key
        restart = cycle | ((it + 1) % _RESTART == 0)
        seen = torch.where(restart.unsqueeze(-1), -1, seen)
        zc = torch.where(restart.unsqueeze(-1), xc, y)
        pending = torch.where(stall, int(BoxQPStatus.SMALL_IMPROVEMENT), pending_code)
        pending = torch.where(nodesc, int(BoxQPStatus.NO_DESCENT), pending)
        pending = torch.where(notpd, int(BoxQPStatus.NOT_POSITIVE_DEFINITE), pending)


def _enumerate_faces(m: int, nb: int, device: torch.device) -> bool:
    """Whether :func:`_box_qp_enum_x` solves the batch: 3^m faces of small solves at once beat the
    iterations' per-call overhead for m = 2 at every batch size, and for m = 3 up to a few hundred problems
    on CPU (measured: 8 problems 1.6 vs 9.5 ms, 256 8.5 vs 18 ms, 4096 127 vs 109 ms) and on GPUs, where
    the iterations' host syncs dominate."""
    return m == 2 or (m == 3 and (device.type != "cpu" or nb <= 1024))


def _box_qp_enum_x(H: Tensor, g: Tensor, lo: Tensor, hi: Tensor, start: Tensor | None = None) -> Tensor:
    """The minimizer of a strictly convex box QP with few variables, by enumerating the faces of the box.

    Every face (each variable free, on its lower or on its upper bound: ``3^m`` of them) has one minimizer
    of ``f`` on its affine hull (the bound variables fixed, the free ones from the free block of ``H``);
    the box QP's minimizer is the minimizer of the face it lies on, and it is feasible, so it is the
    feasible face minimizer of lowest ``f``.  All faces are solved at once (a batched solve of the free
    block padded with the identity).  Faces with an infinite bound, a free block that is not positive
    definite, or a non-finite solution are skipped; where no face qualifies, ``start`` (default: the
    projected zero) is returned and :func:`_iterate` decides.
    """
    nb, m = g.shape
    dtype, device = g.dtype, g.device
    codes = torch.cartesian_prod(*[torch.arange(3, device=device)] * m).reshape(-1, m)  # (F, m): 0 free
    free = codes == 0  # (F, m)
    at_lo, at_hi = codes == 1, codes == 2
    fixed = torch.where(at_lo, lo.unsqueeze(1), torch.where(at_hi, hi.unsqueeze(1), 0.0))  # (nb, F, m)
    ok = torch.isfinite(fixed).all(-1)  # a face on an infinite bound does not exist
    fixed = torch.where(ok.unsqueeze(-1), fixed, 0.0)
    ff = (free.unsqueeze(-1) & free.unsqueeze(-2)).to(dtype)  # (F, m, m)
    eye = torch.eye(m, dtype=dtype, device=device)
    Hf = H.unsqueeze(1) * ff + eye * (~free).to(dtype).unsqueeze(-1)  # free block, identity elsewhere
    H1 = H.unsqueeze(1)
    rhs = torch.where(free, -(g.unsqueeze(1) + torch.matmul(H1, fixed.unsqueeze(-1)).squeeze(-1)), 0.0)
    xf, pd = small_spd_solve(Hf, rhs)
    x = torch.where(free, xf, fixed)
    rtol = 8 * torch.finfo(dtype).eps
    span = torch.where(torch.isfinite(hi - lo), hi - lo, 1.0).unsqueeze(1) + x.abs()
    feas = ((x >= lo.unsqueeze(1) - rtol * span) & (x <= hi.unsqueeze(1) + rtol * span)).all(-1)
    ok = ok & pd & feas & torch.isfinite(x).all(-1)
    x = _clip(x, lo.unsqueeze(1), hi.unsqueeze(1))
    fval = 0.5 * (x * torch.matmul(H1, x.unsqueeze(-1)).squeeze(-1)).sum(-1) + (g.unsqueeze(1) * x).sum(-1)
    k = torch.argmin(torch.where(ok, fval, torch.inf), dim=-1)  # (nb,)
    best = x.gather(1, k.view(nb, 1, 1).expand(nb, 1, m)).squeeze(1)
    fallback = _clip(torch.zeros_like(g), lo, hi) if start is None else start
    return torch.where(ok.any(-1, keepdim=True), best, fallback)


def small_spd_solve(A: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:
    """``A⁻¹ b`` for many tiny (m ≤ 3) matrices ``A (..., m, m)`` by a Cholesky factorization written out
    entry by entry (a few elementwise kernels instead of one LAPACK call per matrix), and whether each
    ``A`` is positive definite (pivots > 0; where not, the solution is garbage and must be ignored).
    ``A`` and ``b (..., m)`` broadcast (``A (..., 1, m, m)`` with ``b (..., k, m)``: ``k`` right-hand
    sides)."""
    L, pd = _small_cholesky(A)
    return torch.stack(_small_upper_solve(L, _small_lower_solve(L, b)), -1), pd


def _small_cholesky(A: Tensor) -> tuple[dict, Tensor]:
    """The entries ``L[i, j]`` (``i ≥ j``) of the Cholesky factor of tiny ``A (..., m, m)``, elementwise, and
    whether ``A`` is positive definite (where not, a non-positive pivot is replaced by 1: garbage)."""
    m = A.shape[-1]
    L: dict = {}
    pd = torch.ones(A.shape[:-2], dtype=torch.bool, device=A.device)
    for i in range(m):
        for j in range(i + 1):
            v = A[..., i, j]
            for k in range(j):
                v = v - L[i, k] * L[j, k]
            if i == j:
                pd = pd & (v > 0)
                L[i, i] = torch.sqrt(torch.where(v > 0, v, 1.0))
            else:
                L[i, j] = v / L[j, j]
    return L, pd


def _small_lower_solve(L: dict, b: Tensor) -> list[Tensor]:
    """``y = L⁻¹ b`` (entries of :func:`_small_cholesky`, ``b (..., m)``) as a list of the ``m`` entries."""
    y: list = []
    for i in range(b.shape[-1]):
        v = b[..., i]
        for k in range(i):
            v = v - L[i, k] * y[k]
        y.append(v / L[i, i])
    return y


def _small_upper_solve(L: dict, y: list[Tensor]) -> list[Tensor]:
    """``x = L⁻ᵀ y`` (``y`` a list of entries, as :func:`_small_lower_solve` returns) as a list of entries."""
    m = len(y)
    x: list = [None] * m
    for i in reversed(range(m)):
        v = y[i]
        for k in range(i + 1, m):
            v = v - L[k, i] * x[k]
        x[i] = v / L[i, i]
    return x


def _box_qp_scalar_x(H: Tensor, g: Tensor, lo: Tensor, hi: Tensor) -> Tensor:
    """Closed form for one variable: ``x = clip(-g/h, lower, upper)`` when ``h > 0``, else ``clip(0)``."""
    h = H[..., 0]  # (nb, 1)
    x = _clip(-g / torch.where(h > 0, h, 1.0), lo, hi)
    return torch.where(h > 0, x, _clip(torch.zeros_like(x), lo, hi))


def box_qp_two(H: Tensor, g: Tensor, lo: Tensor, hi: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`box_qp` for two variables as a fixed-shape, sync-free function for compiled programs (private
    to the solvers): ``(x, certified, clamped)`` for ``H (nb, 2, 2)``, ``g``, ``lo``, ``hi`` ``(nb, 2)``.

    The same steps as :func:`box_qp`'s usual case, with every test computed for every element: the exact
    minimizer by enumerating the faces (solved in float64, rounded to the input dtype), certified in float64
    (where the input is narrower: at the float64 point and at the rounded one).  Where ``box_qp`` certifies
    its enumerated point it returns it with the same clamped set, so a certified element equals its result;
    an uncertified one is the caller's to hand to :func:`box_qp` (which iterates from there).  Non-finite
    data give an uncertified element."""
    dtype = H.dtype
    Hw, gw, lw, hw = (v.double() for v in (H, g, lo, hi))
    eps = torch.finfo(torch.float64).eps
    gap_tol = _GAP_TOL.get(dtype, _GAP_TOL[torch.float32])
    dsq, hsc = _jacobi(Hw)
    x = _box_qp_enum_x(Hw, gw, lw, hw)
    cert, clamped, _ = _certified_everywhere(Hw, gw, lw, hw, x, dsq, hsc, eps ** 0.5, gap_tol, True)
    if dtype != torch.float64:
        x = x.to(dtype)
        tol_in = torch.finfo(dtype).eps ** 0.5
        c2, clamped, _ = _certified_everywhere(Hw, gw, lw, hw, x.double(), dsq, hsc, tol_in, gap_tol, True)
        cert = cert & c2
    return x.to(dtype), cert, clamped


def _certified_everywhere(H, g, lo, hi, x, dsq, hsc, tol: float, gap_tol: float, small: bool = False
                          ) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`_certify`'s verdict, clamped set and KKT residual, the gap computed for every element (no host
    read)."""
    _, clamped, res, kkt_tol = _kkt(H, g, lo, hi, x, dsq, hsc, tol)
    gap, scale, _ = _objective_gap(H, g, lo, hi, x, dsq, small)
    gtol = gap_tol * scale
    cert = (res <= kkt_tol) & torch.isfinite(kkt_tol) & (gap <= gtol) & torch.isfinite(gtol)
    return cert, clamped, res


def box_qp_fixed(H: Tensor, g: Tensor, lo: Tensor, hi: Tensor, x0: Tensor, iters: int, *,
                 tol: float | None = None, gap_tol: float | None = None
                 ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """A fixed-shape, sync-free box QP for compiled programs (private to the solvers): ``iters`` steps of the
    primal-dual active-set sequence (:func:`_working_set` of ``z``, ``z ←`` its Newton point) from ``x0``,
    the lowest feasible point ``clip(z)`` met (``clip(x0)`` included) returned with :func:`box_qp`'s
    certificate at it (the same tests, computed for every element).

    ``H (nb, m, m)``, ``g``, ``lo``, ``hi``, ``x0`` ``(nb, m)``, finite data (the caller sanitizes).  Returns
    ``(x, certified, clamped, kkt_residual)``; an uncertified element has no status here: the caller decides
    (the MPC solves it again with :func:`box_qp`).  No data-dependent exit, no host read: every element
    runs every step (the sequence settles on its face in a few steps; a settled element repeats its point).
    """
    from controllers._compiled import scan  # noqa: PLC0415  (a private sibling; keeps this module light)

    dtype = H.dtype
    eps = torch.finfo(torch.float64).eps
    tol = eps ** 0.5 if tol is None else tol
    gap_tol = _GAP_TOL.get(dtype, _GAP_TOL[torch.float32]) if gap_tol is None else gap_tol
    dsq, hsc = _jacobi(H)
    x = _clip(x0, lo, hi)
    fx = 0.5 * (x * _matvec(H, x)).sum(-1) + (g * x).sum(-1)
    eye = torch.eye(H.shape[-1], dtype=dtype, device=H.device)

    def body(t, carry, xs):
        z, best, fbest = carry
        Ht, gt, lot, hit, e = xs
        hd = Ht.diagonal(dim1=-2, dim2=-1)
        w = _working_set(z, gt + _matvec(Ht, z), lot, hit, hd)
        free = w == 0
        b = torch.where(w == 1, lot, torch.where(w == 2, hit, torch.zeros_like(z)))
        L, info = torch.linalg.cholesky_ex(masked_hessian(Ht, free))
        L = torch.where((info != 0).view(-1, 1, 1), e, L)
        rhs = torch.where(free, gt + _matvec(Ht, b), 0.0)
        y = b - torch.cholesky_solve(rhs.unsqueeze(-1), L).squeeze(-1)
        y = torch.where((info == 0).unsqueeze(-1), y, z)
        xc = _clip(y, lot, hit)
        fc = 0.5 * (xc * _matvec(Ht, xc)).sum(-1) + (gt * xc).sum(-1)
        better = fc < fbest
        return (y, torch.where(better.unsqueeze(-1), xc, best), torch.where(better, fc, fbest)), (fc,)

    xs = [v.unsqueeze(0) for v in (H, g, lo, hi, eye)]
    (_, x, _), _ = scan(body, (x, x.clone(), fx), xs, iters)
    cert, clamped, res = _certified_everywhere(H, g, lo, hi, x, dsq, hsc, tol, gap_tol)
    return x, cert, clamped, res
