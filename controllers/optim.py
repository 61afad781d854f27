"""A small batched optimization toolbox: gradient descent, Newton, Gauss–Newton, (constrained) least squares.

Seed 004 §3 (Calinon, *A Math Cookbook for Robot Manipulation*):

* :func:`gradient_descent` — ``x_{k+1} = x_k − α g(x_k)`` (§3.1), a fixed step ``α`` or Algorithm 1;
* :func:`newton` — ``x_{k+1} = x_k − α H(x_k)⁻¹ g(x_k)`` (Eq. 9, §3.2), curvature below a floor replaced by
  a small positive value (the seed's remedy for ``c'' ≤ 0``, applied to the eigenvalues of ``H``);
* :func:`gauss_newton` — ``c(x) = f(x)ᵀ W f(x)``, ``g = 2 Jᵀ W f``, ``H ≈ 2 Jᵀ W J`` (§3.3), the step
  ``Δx = −(Jᵀ W J + λ I)⁻¹ Jᵀ W f`` (Eq. 10 with weights and an optional Levenberg damping ``λ``);
* :func:`least_squares` — ridge / weighted / weighted-ridge least squares, Eqs. (12)–(16) (§3.4);
* :func:`constrained_least_squares` — ``min ‖Ax − b‖²_W s.t. Cx = d`` by the KKT system (Eq. 17, §3.5).

Conventions
-----------
* **Batch first.** ``x0 (*B, n)``; the cost ``f: (*B, n) -> (*B,)`` (a residual ``(*B, n) -> (*B, r)``) is
  called on the whole batch at once, so it may close over per-element data of batch shape ``*B``.  Element
  ``i`` of its output must depend on element ``i`` of its input only (no reductions over the batch): the
  derivatives are then taken for the whole batch at once — the gradient of ``Σ_b f_b`` is the stack of the
  per-element gradients — with :mod:`torch.func` (``grad``; ``jacrev`` of its sum for the Hessian;
  ``jacrev`` of ``Σ_b f_b`` or ``n`` ``jvp`` passes for a Jacobian, whichever needs fewer passes).
  Derivatives supplied by the caller (``gradient=``, ``hessian=``, ``jacobian=``) replace them.
* **Cost** as the seed writes it: ``c(x)`` for the first two, ``c(x) = f(x)ᵀ W f(x)`` (no factor ½) for
  Gauss–Newton, so its gradient is ``2 Jᵀ W f``.
* **Line search** (Algorithm 1 of the seed: ``α ← 1``, halved while ``c(x + αΔx) > c(x)`` and ``α > α_min``)
  with ``α ← α₀`` (``1`` but for a gradient step) and two refinements.  A step needs a strict decrease
  ``c(x + αΔx) < c(x)`` (with "no increase", a step to a point of equal cost on the other side of a valley
  could be taken forever) unless its predicted decrease ``−α gᵀΔx`` is below the rounding of the cost
  (``8 ε |c(x)|``): then it passes when ``c`` does not increase beyond that rounding, so that near a minimum,
  where the cost cannot resolve the decrease any more, the full step is still taken.  Where no
  ``α ≥ α_min`` passes, the element stops where it is (``LINE_SEARCH_FAILED``) instead of taking a step that
  increases its cost; an accepted step too small to change ``x`` in its precision stops it too
  (``STALLED``).
* **Tolerance.**  ``tol=None`` (the default) is relative to the gradient's scale and to the precision:
  ``tol_b = τ · max(1, ‖g(x₀)_b‖₂)`` per element, ``τ = 10⁻⁴`` in float32 and ``10⁻⁸`` in float64
  (``10⁻⁶`` for :func:`gradient_descent`, which converges only linearly) — in float32 the gradient at the
  minimizer of an ordinary problem is only resolved to about ``10⁻⁶ … 10⁻⁴`` of its scale.  A number
  given as ``tol`` is used as it is (absolute, the same for every element).
* **Status per element**: ``converged`` is ``‖g(x)‖₂ ≤ tol`` evaluated AT the returned ``x`` (and, for
  :func:`newton`, no clearly negative curvature there: else ``NOT_A_MINIMUM``); ``iterations`` counts the
  steps taken by that element; ``reason`` holds codes of :class:`controllers.problem.Reason`
  (``CONVERGED``, ``NONFINITE_INPUT`` for NaN/inf in ``x0``, ``DIVERGED`` for a non-finite cost or
  derivative at an iterate, ``LINE_SEARCH_FAILED``, ``STALLED``, ``MAX_ITERATIONS``, ``NOT_A_MINIMUM``).
  An element stops moving once it is done (masked updates), and a NaN element never changes the others.
* dtype and device follow ``x0`` (float32 or float64; the cost must return the same dtype).  The iterative
  solvers are meant as solvers, not as differentiable layers: no ``detach`` is applied, but gradients
  through their iterations are not part of the contract.  :func:`least_squares` and
  :func:`constrained_least_squares` are differentiable closed forms (autograd through ``torch.linalg``).
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

from controllers.problem import Reason, SolverStatus
from torchlie._batch import broadcast_shapes

__all__ = [
    "OptimResult",
    "ConstrainedLSResult",
    "gradient_descent",
    "newton",
    "gauss_newton",
    "least_squares",
    "constrained_least_squares",
]


# --------------------------------------------------------------------------------------------------
# result type
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class OptimResult:
    """Outcome of :func:`gradient_descent`, :func:`newton` or :func:`gauss_newton` (batch shape ``*B``).

    Attributes:
        x: ``(*B, n)`` the returned iterate (``x0`` for a ``NONFINITE_INPUT`` element).
        cost: ``(*B,)`` ``c(x)`` at the returned ``x`` (``f(x)ᵀ W f(x)`` for Gauss–Newton).
        grad_norm: ``(*B,)`` ``‖g(x)‖₂`` at the returned ``x`` — the residual that ``converged`` checks.
        converged: ``(*B,)`` bool — ``grad_norm ≤ tol`` at ``x`` (Newton: and not ``NOT_A_MINIMUM``; for the
            default ``tol=None`` the per-element tolerance of the module notes).
        iterations: ``(*B,)`` int64 — steps taken by this element (``0`` if ``x0`` already converged).
        reason: ``(*B,)`` int64 codes of :class:`controllers.problem.Reason`.
    """

    x: Tensor
    cost: Tensor
    grad_norm: Tensor
    converged: Tensor
    iterations: Tensor
    reason: Tensor

    @property
    def status(self) -> SolverStatus:
        return SolverStatus(converged=self.converged, iterations=self.iterations, reason=self.reason)

    def reason_names(self) -> list[str]:
        """The reasons as names, flattened over the batch in row-major order."""
        return self.status.reason_names()


class ConstrainedLSResult(NamedTuple):
    """``x (*B, n)`` the minimizer and ``multiplier (*B, p)`` the ``λ`` of the KKT system of Eq. (17)."""

    x: Tensor
    multiplier: Tensor


# --------------------------------------------------------------------------------------------------
# argument checks
# --------------------------------------------------------------------------------------------------


def _check_x0(x0, fn: str) -> Tensor:
    if not isinstance(x0, Tensor):
        raise TypeError(f"{fn}: argument 'x0' must be a torch.Tensor of shape (*B, n), "
                        f"got {type(x0).__name__}")
    if x0.dtype not in (torch.float32, torch.float64):
        raise TypeError(f"{fn}: argument 'x0' must be float32 or float64, got {x0.dtype}")
    if x0.dim() < 1 or x0.shape[-1] < 1:
        raise ValueError(f"{fn}: argument 'x0' must have shape (*B, n) with n >= 1, got {tuple(x0.shape)}")
    return x0


def _check_callable(v, name: str, fn: str, optional: bool = False) -> None:
    if v is None and optional:
        return
    if not callable(v):
        what = "None or a callable" if optional else "a callable"
        raise TypeError(f"{fn}: argument '{name}' must be {what}, got {type(v).__name__}")


def _positive(v, name: str, fn: str, *, upper: float | None = None, allow_zero: bool = False) -> float:
    if isinstance(v, bool) or not isinstance(v, numbers.Real):
        raise TypeError(f"{fn}: argument '{name}' must be a real number, got {type(v).__name__}")
    v = float(v)
    bad = not math.isfinite(v) or (v < 0 if allow_zero else v <= 0) or (upper is not None and v > upper)
    if bad:
        rng = ">= 0" if allow_zero else "> 0"
        if upper is not None:
            rng += f" and <= {upper}"
        raise ValueError(f"{fn}: argument '{name}' must be finite and {rng}, got {v}")
    return v


def _check_max_iter(v, fn: str) -> int:
    if isinstance(v, bool) or not isinstance(v, numbers.Integral):
        raise TypeError(f"{fn}: argument 'max_iter' must be an int, got {type(v).__name__}")
    if v < 1:
        raise ValueError(f"{fn}: argument 'max_iter' must be >= 1, got {v}")
    return int(v)


def _check_output(y, name: str, fn: str, shape: tuple[int, ...], expected: str, x0: Tensor) -> Tensor:
    if not isinstance(y, Tensor):
        raise TypeError(f"{fn}: '{name}' must return a torch.Tensor, got {type(y).__name__}")
    if tuple(y.shape) != shape:
        raise ValueError(f"{fn}: '{name}' must map x (*B, n) = {tuple(x0.shape)} to {expected} = {shape}, "
                         f"got {tuple(y.shape)}")
    if y.dtype != x0.dtype:
        raise TypeError(f"{fn}: '{name}' returned {y.dtype} for x0 of {x0.dtype} (nothing is cast silently)")
    return y


def _check_weights(W, fn: str, r: int, x0: Tensor) -> Tensor | None:
    if W is None:
        return None
    if not isinstance(W, Tensor):
        raise TypeError(f"{fn}: argument 'weights' must be None or a tensor (*B, {r}, {r}), "
                        f"got {type(W).__name__}")
    if W.dtype != x0.dtype:
        raise TypeError(f"{fn}: argument 'weights' is {W.dtype} but x0 is {x0.dtype} "
                        "(nothing is cast silently)")
    if W.dim() < 2 or W.shape[-2:] != (r, r):
        raise ValueError(f"{fn}: argument 'weights' must have shape (*B, {r}, {r}), got {tuple(W.shape)}")
    try:
        ok = tuple(broadcast_shapes(W.shape[:-2], x0.shape[:-1])) == tuple(x0.shape[:-1])
    except (RuntimeError, ValueError):
        ok = False
    if not ok:
        raise ValueError(f"{fn}: batch dims of 'weights' {tuple(W.shape[:-2])} must broadcast to those of "
                         f"'x0' {tuple(x0.shape[:-1])}")
    return W


# --------------------------------------------------------------------------------------------------
# derivatives by torch.func (one pass for the whole batch)
# --------------------------------------------------------------------------------------------------


def _auto_gradient(f: Callable[[Tensor], Tensor]) -> Callable[[Tensor], Tensor]:
    """``x (*B, n) -> ∇f (*B, n)``: the gradient of ``Σ_b f_b`` (elements independent)."""
    return torch.func.grad(lambda x: f(x).sum())


def _auto_grad_hessian(grad: Callable[[Tensor], Tensor]) -> Callable[[Tensor], tuple[Tensor, Tensor]]:
    """``x (*B, n) -> (g (*B, n), H (*B, n, n))``: ``jacrev`` of ``Σ_b g_b`` (``n`` reverse-over-reverse
    passes, each through every element at once; no element sees another's derivatives), ``g`` as its aux."""

    def summed(z: Tensor) -> tuple[Tensor, Tensor]:
        gz = grad(z)
        return gz.reshape(-1, z.shape[-1]).sum(0), gz

    def grad_hess(x: Tensor) -> tuple[Tensor, Tensor]:
        H, g = torch.func.jacrev(summed, has_aux=True)(x)  # (n, *B, n)[i, b, j] = H_b[i, j]
        return g, H.movedim(0, -2)

    return grad_hess


def _auto_jacobian(residual: Callable[[Tensor], Tensor], r: int, n: int
                   ) -> Callable[[Tensor], tuple[Tensor, Tensor]]:
    """``x (*B, n) -> (f (*B, r), J (*B, r, n))``: ``r`` reverse passes of ``Σ_b f_b`` if ``r ≤ n``, else
    ``n`` forward passes with the tangent ``e_j`` for every element."""
    if r <= n:
        def summed(z: Tensor) -> tuple[Tensor, Tensor]:
            fz = residual(z)
            return fz.reshape(-1, r).sum(0), fz

        def jac(x: Tensor) -> tuple[Tensor, Tensor]:
            J, fx = torch.func.jacrev(summed, has_aux=True)(x)  # (r, *B, n)
            return fx, J.movedim(0, -2)
    else:
        def jac(x: Tensor) -> tuple[Tensor, Tensor]:
            n_ = x.shape[-1]
            eye = torch.eye(n_, dtype=x.dtype, device=x.device)
            tangents = eye.reshape((n_,) + (1,) * (x.dim() - 1) + (n_,)).expand((n_,) + tuple(x.shape))
            cols = torch.func.vmap(lambda v: torch.func.jvp(residual, (x,), (v,))[1])(tangents)
            fx = residual(x)
            # forward AD promotes a 0-dim float32 tangent combined with a Python float to float64 (as for an
            # unbatched x0): the values are those of the float32 computation, so restore the residual's dtype
            return fx, cols.movedim(0, -1).to(fx.dtype)  # (n, *B, r) -> (*B, r, n)
    return jac


# --------------------------------------------------------------------------------------------------
# the shared loop
# --------------------------------------------------------------------------------------------------


def _spd_solve(H: Tensor, g: Tensor) -> Tensor:
    """``H⁻¹ g`` for SPD ``H (*B, n, n)`` by Cholesky, the pseudoinverse where the factorization fails."""
    L, info = torch.linalg.cholesky_ex(H)
    d = torch.cholesky_solve(g.unsqueeze(-1), L).squeeze(-1)
    bad = (info != 0) | ~torch.isfinite(d).all(-1)
    if bool(bad.any()):
        eye = torch.eye(H.shape[-1], dtype=H.dtype, device=H.device)
        Hs = torch.where(bad[..., None, None], H, eye)
        dp = (torch.linalg.pinv(Hs, hermitian=True) @ g.unsqueeze(-1)).squeeze(-1)
        d = torch.where(bad[..., None], dp, d)
    return d


def _default_tau(dtype: torch.dtype, tau64: float) -> float:
    """``τ`` of the default tolerance (module notes): ``10⁻⁴`` in float32, ``tau64`` in float64."""
    return 1e-4 if dtype == torch.float32 else tau64


def _check_tol(tol, fn: str) -> float | None:
    return None if tol is None else _positive(tol, "tol", fn)


def _minimize(cost, derivs, direction, x0: Tensor, *, tol: float | None, tau: float, max_iter: int,
              line_search: bool, step_size: float, alpha_min: float, second_order_check: bool) -> OptimResult:
    """The loop shared by the three iterative solvers.

    ``tol``: an absolute tolerance on ``‖g‖₂``, or ``None``: ``τ · max(1, ‖g(x₀)‖₂)`` per element.

    ``cost(x) -> (*B,)``; ``derivs(x) -> (g (*B, n), aux)``; ``direction(g, aux, active) -> Δx (*B, n)``
    (finite everywhere; only ``active`` rows are used).  ``second_order_check``: ``aux`` is the Hessian.
    """
    batch = x0.shape[:-1]
    dev = x0.device
    slack = 8.0 * torch.finfo(x0.dtype).eps
    x = x0.clone()
    finite_in = torch.isfinite(x0).all(-1)
    reason = torch.full(batch, int(Reason.MAX_ITERATIONS), dtype=torch.int64, device=dev)
    reason = torch.where(finite_in, reason, int(Reason.NONFINITE_INPUT))
    active = finite_in.clone()
    iterations = torch.zeros(batch, dtype=torch.int64, device=dev)
    c = cost(x)
    gnorm = torch.full(batch, math.nan, dtype=x0.dtype, device=dev)
    H = None
    for k in range(max_iter + 1):
        g, aux = derivs(x)
        gnorm = torch.linalg.vector_norm(g, dim=-1)
        ok = torch.isfinite(c) & torch.isfinite(gnorm)
        if second_order_check:
            H = aux
            ok = ok & torch.isfinite(H).flatten(-2).all(-1)
        reason = torch.where(active & ~ok, int(Reason.DIVERGED), reason)
        active = active & ok
        if k == 0:
            tol_b = tau * gnorm.clamp_min(1.0) if tol is None else tol
        done = active & (gnorm <= tol_b)
        reason = torch.where(done, int(Reason.CONVERGED), reason)
        active = active & ~done
        if k == max_iter or not bool(active.any()):
            break
        d = direction(g, aux, active)
        d = torch.where(active[..., None], d, torch.zeros((), dtype=d.dtype, device=dev))
        if not line_search:
            x_new = x + step_size * d
            c_new = cost(x_new)
            accepted = active
        else:
            # Algorithm 1, vectorized: every pending element halves its own α
            alpha = torch.full(batch, step_size, dtype=x.dtype, device=dev)
            pending = active.clone()
            x_new, c_new = x, c
            round_c = slack * c.abs()  # the rounding level of c
            pred = -(torch.where(active[..., None], g, 0.0) * d).sum(-1)  # predicted decrease per unit α
            while True:
                xt = x + alpha[..., None] * d
                ct = cost(xt)
                # a decrease where the model predicts one the cost resolves; else "no increase" up to rounding
                unresolved = alpha * pred <= round_c
                take = pending & (alpha >= alpha_min) & ((ct < c) | (unresolved & (ct <= c + round_c)))
                x_new = torch.where(take[..., None], xt, x_new)
                c_new = torch.where(take, ct, c_new)
                pending = pending & ~take
                alpha = alpha * 0.5
                if not bool((pending & (alpha >= alpha_min)).any()):
                    break
            accepted = active & ~pending
            reason = torch.where(pending, int(Reason.LINE_SEARCH_FAILED), reason)
            active = accepted
        # a step too small to change x in this precision: no further progress is possible
        stalled = accepted & (x_new == x).all(-1)
        reason = torch.where(stalled, int(Reason.STALLED), reason)
        active = active & ~stalled
        accepted = accepted & ~stalled
        x = torch.where(accepted[..., None], x_new, x)
        c = torch.where(accepted, c_new, c)
        iterations = iterations + accepted.to(torch.int64)
    if second_order_check and H is not None:
        # a stationary point with clearly negative curvature is a saddle or a maximum
        eye = torch.eye(x.shape[-1], dtype=x.dtype, device=dev)
        conv = reason == int(Reason.CONVERGED)
        Hs = torch.where(conv[..., None, None], H, eye)
        lam = torch.linalg.eigvalsh(0.5 * (Hs + Hs.mT))
        scale = lam.abs().amax(-1).clamp_min(1.0)
        neg = lam[..., 0] < -math.sqrt(torch.finfo(x.dtype).eps) * scale
        reason = torch.where(conv & neg, int(Reason.NOT_A_MINIMUM), reason)
    converged = reason == int(Reason.CONVERGED)
    return OptimResult(x=x, cost=c, grad_norm=gnorm, converged=converged, iterations=iterations,
                       reason=reason)


def _cost_fn(f, fn: str, x0: Tensor):
    batch = tuple(x0.shape[:-1])
    _check_output(f(x0), "f", fn, batch, "(*B,)", x0)
    return f


# --------------------------------------------------------------------------------------------------
# gradient descent and Newton's method (§3.1-3.2)
# --------------------------------------------------------------------------------------------------



def _check_second_order(x0, line_search, tol, max_iter, alpha_min, fn: str):
    """The arguments Newton and Gauss–Newton share: ``(x0, tol, max_iter, alpha_min)`` checked."""
    x0 = _check_x0(x0, fn)
    if not isinstance(line_search, bool):
        raise TypeError(f"{fn}: argument 'line_search' must be a bool, got {type(line_search).__name__}")
    alpha_min = _positive(alpha_min, "alpha_min", fn, upper=1.0)
    return x0, _check_tol(tol, fn), _check_max_iter(max_iter, fn), alpha_min

def gradient_descent(f: Callable[[Tensor], Tensor], x0: Tensor, *, step_size: float = 1.0,
                     line_search: bool = True, alpha_min: float = 1e-10, tol: float | None = None,
                     max_iter: int = 1000, gradient: Callable[[Tensor], Tensor] | None = None) -> OptimResult:
    """Minimize ``c(x) = f(x)`` by gradient descent, ``x_{k+1} = x_k − α g(x_k)`` (seed 004 §3.1).

    Args:
        f: the cost ``(*B, n) -> (*B,)``, element-wise over the batch (see the module notes).
        x0: ``(*B, n)`` initial estimates ``x_1``.
        step_size: the fixed ``α`` (``line_search=False``) or the first ``α`` tried by Algorithm 1.
        line_search: backtracking (Algorithm 1 as in the module notes: halve ``α`` until the cost
            decreases, down to ``alpha_min``); ``False``: every step is ``−step_size · g`` (a non-finite cost
            or gradient: ``DIVERGED``).
        alpha_min: smallest ``α`` tried by the line search, in ``(0, step_size]``.
        tol: ``converged`` where ``‖g(x)‖₂ ≤ tol`` at the returned ``x``; default ``None``:
            ``τ · max(1, ‖g(x₀)‖₂)`` per element, ``τ = 10⁻⁶`` (float64) or ``10⁻⁴`` (float32).
        max_iter: at most this many steps per element.
        gradient: optional ``(*B, n) -> (*B, n)``, ``∂c/∂x`` (Eq. 7); default: :mod:`torch.func`.

    Returns:
        :class:`OptimResult`.
    """
    fn = "gradient_descent"
    _check_callable(f, "f", fn)
    _check_callable(gradient, "gradient", fn, optional=True)
    x0 = _check_x0(x0, fn)
    if not isinstance(line_search, bool):
        raise TypeError(f"{fn}: argument 'line_search' must be a bool, got {type(line_search).__name__}")
    step_size = _positive(step_size, "step_size", fn)
    alpha_min = _positive(alpha_min, "alpha_min", fn, upper=step_size)
    tol = _check_tol(tol, fn)
    max_iter = _check_max_iter(max_iter, fn)
    _cost_fn(f, fn, x0)
    grad = gradient if gradient is not None else _auto_gradient(f)
    if gradient is not None:
        _check_output(gradient(x0), "gradient", fn, tuple(x0.shape), "(*B, n)", x0)

    def derivs(x):
        return grad(x), None

    def direction(g, aux, active):
        return -torch.where(torch.isfinite(g), g, 0.0)

    return _minimize(f, derivs, direction, x0, tol=tol, tau=_default_tau(x0.dtype, 1e-6), max_iter=max_iter,
                     line_search=line_search, step_size=step_size, alpha_min=alpha_min,
                     second_order_check=False)


def newton(f: Callable[[Tensor], Tensor], x0: Tensor, *, tol: float | None = None, max_iter: int = 100,
           line_search: bool = True, alpha_min: float = 1e-10, min_curvature: float = 1e-8,
           gradient: Callable[[Tensor], Tensor] | None = None,
           hessian: Callable[[Tensor], Tensor] | None = None) -> OptimResult:
    """Minimize ``c(x) = f(x)`` by Newton's method, ``x_{k+1} = x_k − α H(x_k)⁻¹ g(x_k)`` (Eqs. 5, 9; §3.2).

    Where ``H`` is not positive definite, each eigenvalue below ``min_curvature · max(1, max|λ|)`` is
    replaced by that small positive value (the seed's "replaced by a small positive value in (5)"), so the
    step is always a descent direction; Algorithm 1 (``α = 1``, halved until the cost decreases, down to
    ``alpha_min``; module notes) then scales it.  A quadratic with a positive-definite Hessian is solved in
    one step.

    Args:
        f: the cost ``(*B, n) -> (*B,)``, element-wise over the batch.
        x0: ``(*B, n)`` initial estimates.
        tol: ``converged`` where ``‖g(x)‖₂ ≤ tol`` at the returned ``x`` and ``H(x)`` has no eigenvalue below
            ``−√ε · max(1, max|λ|)`` (else ``NOT_A_MINIMUM``: a saddle or a maximum); default ``None``:
            ``τ · max(1, ‖g(x₀)‖₂)`` per element, ``τ = 10⁻⁸`` (float64) or ``10⁻⁴`` (float32).
        max_iter: at most this many steps per element.
        line_search: ``False``: full Newton steps (``α = 1``).
        alpha_min: smallest ``α`` of the line search, in ``(0, 1]``.
        min_curvature: relative eigenvalue floor (> 0).
        gradient: optional ``(*B, n) -> (*B, n)`` (Eq. 7); default: :func:`torch.func.grad`.
        hessian: optional ``(*B, n) -> (*B, n, n)`` (Eq. 8); default: reverse-over-reverse
            (:func:`torch.func.jacrev` of the gradient).

    Returns:
        :class:`OptimResult`.
    """
    fn = "newton"
    _check_callable(f, "f", fn)
    _check_callable(gradient, "gradient", fn, optional=True)
    _check_callable(hessian, "hessian", fn, optional=True)
    x0, tol, max_iter, alpha_min = _check_second_order(x0, line_search, tol, max_iter, alpha_min, fn)
    min_curvature = _positive(min_curvature, "min_curvature", fn)
    _cost_fn(f, fn, x0)
    n = x0.shape[-1]
    grad = gradient if gradient is not None else _auto_gradient(f)
    if gradient is not None:
        _check_output(gradient(x0), "gradient", fn, tuple(x0.shape), "(*B, n)", x0)
    if hessian is not None:
        _check_output(hessian(x0), "hessian", fn, tuple(x0.shape) + (n,), "(*B, n, n)", x0)

    if hessian is not None:
        def derivs(x):
            return grad(x), hessian(x)
    else:
        derivs = _auto_grad_hessian(grad)

    def direction(g, H, active):
        eye = torch.eye(n, dtype=g.dtype, device=g.device)
        Hs = torch.where(active[..., None, None], 0.5 * (H + H.mT), eye)
        gs = torch.where(active[..., None], g, 0.0)
        lam, V = torch.linalg.eigh(Hs)
        floor = min_curvature * lam.abs().amax(-1, keepdim=True).clamp_min(1.0)
        lam = torch.maximum(lam, floor)
        return -(V @ ((V.mT @ gs.unsqueeze(-1)) / lam.unsqueeze(-1))).squeeze(-1)

    return _minimize(f, derivs, direction, x0, tol=tol, tau=_default_tau(x0.dtype, 1e-8), max_iter=max_iter,
                     line_search=line_search, step_size=1.0, alpha_min=alpha_min, second_order_check=True)


# --------------------------------------------------------------------------------------------------
# Gauss–Newton (§3.3)
# --------------------------------------------------------------------------------------------------


def gauss_newton(residual: Callable[[Tensor], Tensor], x0: Tensor, *, tol: float | None = None,
                 max_iter: int = 100,
                 jacobian: Callable[[Tensor], Tensor] | None = None, weights: Tensor | None = None,
                 damping: float = 0.0, line_search: bool = True, alpha_min: float = 1e-10) -> OptimResult:
    """Minimize ``c(x) = f(x)ᵀ W f(x)`` by Gauss–Newton (seed 004 §3.3, Eq. 10).

    With ``J = ∂f/∂x``, ``g = 2 Jᵀ W f`` and ``H ≈ 2 Jᵀ W J``, the step is
    ``Δx = −(Jᵀ W J + λ I)⁻¹ Jᵀ W f`` (``W = I``, ``λ = 0``: ``Δx = −J† f``, Eq. 10; ``λ > 0``: the
    Levenberg-damped step), scaled by Algorithm 1.  Where ``Jᵀ W J + λ I`` is singular the pseudoinverse is
    used (the minimum-norm step, as ``J†``).

    Args:
        residual: ``f: (*B, n) -> (*B, r)``, element-wise over the batch.
        x0: ``(*B, n)`` initial estimates.
        tol: ``converged`` where ``‖2 Jᵀ W f‖₂ ≤ tol`` at the returned ``x``; default ``None``:
            ``τ · max(1, ‖2 Jᵀ W f‖₂ at x₀)`` per element, ``τ = 10⁻⁸`` (float64) or ``10⁻⁴`` (float32).
        max_iter: at most this many steps per element.
        jacobian: optional ``(*B, n) -> (*B, r, n)``; default: :mod:`torch.func` (``jacrev`` if ``r ≤ n``,
            else ``n`` ``jvp`` passes).
        weights: optional ``W (*B, r, r)``, positive semi-definite (only ``(W + Wᵀ)/2`` is used), batch dims
            broadcasting to ``x0``'s; default ``I``.
        damping: Levenberg ``λ ≥ 0``.
        line_search: ``False``: full steps.
        alpha_min: smallest ``α`` of the line search, in ``(0, 1]``.

    Returns:
        :class:`OptimResult` (``cost = fᵀ W f``, ``grad_norm = ‖2 Jᵀ W f‖₂``).
    """
    fn = "gauss_newton"
    _check_callable(residual, "residual", fn)
    _check_callable(jacobian, "jacobian", fn, optional=True)
    x0, tol, max_iter, alpha_min = _check_second_order(x0, line_search, tol, max_iter, alpha_min, fn)
    damping = _positive(damping, "damping", fn, allow_zero=True)
    f0 = residual(x0)
    if not isinstance(f0, Tensor) or f0.dim() != x0.dim() or f0.shape[:-1] != x0.shape[:-1]:
        got = tuple(f0.shape) if isinstance(f0, Tensor) else type(f0).__name__
        raise ValueError(f"{fn}: 'residual' must map x (*B, n) = {tuple(x0.shape)} to (*B, r), got {got}")
    r = f0.shape[-1]
    _check_output(f0, "residual", fn, tuple(f0.shape), "(*B, r)", x0)
    W = _check_weights(weights, fn, r, x0)
    if W is not None:
        W = 0.5 * (W + W.mT)  # fᵀ W f sees only the symmetric part
    n = x0.shape[-1]
    if jacobian is not None:
        def res_jac(x):
            return residual(x), jacobian(x)
    else:
        res_jac = _auto_jacobian(residual, r, n)
    if jacobian is not None:
        _check_output(jacobian(x0), "jacobian", fn, tuple(x0.shape[:-1]) + (r, n), "(*B, r, n)", x0)

    def weighted(v: Tensor) -> Tensor:  # W v, v (*B, r)
        return v if W is None else (W @ v.unsqueeze(-1)).squeeze(-1)

    def cost(x):
        fx = residual(x)
        return (fx * weighted(fx)).sum(-1)

    def derivs(x):
        fx, J = res_jac(x)
        JtW = J.mT if W is None else J.mT @ W
        g = 2.0 * (JtW @ fx.unsqueeze(-1)).squeeze(-1)
        return g, JtW @ J

    def direction(g, JtWJ, active):
        eye = torch.eye(n, dtype=g.dtype, device=g.device)
        use = active & torch.isfinite(JtWJ).flatten(-2).all(-1)  # else a gradient step (never a NaN solve)
        N = torch.where(use[..., None, None], JtWJ + damping * eye, eye)
        return -_spd_solve(N, torch.where(active[..., None], 0.5 * g, 0.0))

    return _minimize(cost, derivs, direction, x0, tol=tol, tau=_default_tau(x0.dtype, 1e-8),
                     max_iter=max_iter, line_search=line_search, step_size=1.0, alpha_min=alpha_min,
                     second_order_check=False)


# --------------------------------------------------------------------------------------------------
# least squares (§3.4-3.5)
# --------------------------------------------------------------------------------------------------


def _ls_inputs(fn: str, A, b, W, extra: dict[str, tuple[object, str]] | None = None) -> None:
    for name, v in (("A", A), ("b", b)):
        if not isinstance(v, Tensor):
            raise TypeError(f"{fn}: argument '{name}' must be a torch.Tensor, got {type(v).__name__}")
        if v.dtype not in (torch.float32, torch.float64):
            raise TypeError(f"{fn}: argument '{name}' must be float32 or float64, got {v.dtype}")
    if A.dim() < 2:
        raise ValueError(f"{fn}: argument 'A' must have shape (*B, m, n), got {tuple(A.shape)}")
    m = A.shape[-2]
    if b.dim() < 1 or b.shape[-1] != m:
        raise ValueError(f"{fn}: argument 'b' must have shape (*B, {m}) (m = rows of A), "
                         f"got {tuple(b.shape)}")
    tensors = {"A": A, "b": b}
    if W is not None:
        if not isinstance(W, Tensor):
            raise TypeError(f"{fn}: argument 'weights' must be None or a tensor (*B, {m}, {m}), "
                            f"got {type(W).__name__}")
        if W.dim() < 2 or W.shape[-2:] != (m, m):
            raise ValueError(f"{fn}: argument 'weights' must have shape (*B, {m}, {m}), got {tuple(W.shape)}")
        tensors["weights"] = W
    for k, v in (extra or {}).items():
        tensors[k] = v
    for k, v in tensors.items():
        if v.dtype != A.dtype:
            raise TypeError(f"{fn}: arguments 'A' and '{k}' have different dtypes ({A.dtype} vs {v.dtype}); "
                            "cast explicitly (nothing is cast silently)")
        if v.device != A.device:
            raise ValueError(f"{fn}: arguments 'A' and '{k}' are on different devices")


def _batch_of(fn: str, **shapes: tuple[int, ...]) -> tuple[int, ...]:
    try:
        return tuple(broadcast_shapes(*shapes.values()))
    except (RuntimeError, ValueError):
        desc = ", ".join(f"'{k}' {v}" for k, v in shapes.items())
        raise ValueError(f"{fn}: batch dims do not broadcast: {desc}") from None


def _sqrt0(v: Tensor) -> Tensor:
    """``√v`` for ``v ≥ 0`` with the gradient ``0`` (not ``inf``) where ``v = 0``; NaN stays NaN."""
    pos = v > 0
    return torch.where(pos, torch.sqrt(torch.where(pos, v, torch.ones_like(v))), 0.0 * v)


def _weight_factor(W: Tensor) -> tuple[Tensor, Tensor]:
    """``(Lᵀ (*B, m, m), psd (*B,))`` with ``W = L Lᵀ`` for a symmetric ``W``: Cholesky where it succeeds,
    else (positive semi-definite, e.g. Eq. 16's zero block) ``Lᵀ = diag(√λ) Vᵀ`` from ``W = V diag(λ) Vᵀ``.
    ``psd`` is ``False`` where ``W`` has an eigenvalue below ``−m ε max|λ|`` (not PSD) or a non-finite
    entry; eigenvalues in ``[−m ε max|λ|, m ε max|λ|]`` count as zero."""
    m = W.shape[-1]
    finite = torch.isfinite(W).flatten(-2).all(-1)
    L, info = torch.linalg.cholesky_ex(torch.where(finite[..., None, None], W, 0.0))
    chol = (info == 0) & finite
    R, psd = L.mT, chol
    if not bool(chol.all()):
        # distinct eigenvalues where unused, so that eigh's backward stays finite there
        filler = torch.diag_embed(torch.arange(1, m + 1, dtype=W.dtype, device=W.device))
        semi = ~chol & finite
        lam, V = torch.linalg.eigh(torch.where(semi[..., None, None], W, filler))
        floor = m * torch.finfo(W.dtype).eps * lam.abs().amax(-1, keepdim=True)
        psd = chol | (semi & (lam >= -floor).all(-1))
        Re = _sqrt0(torch.where(lam > floor, lam, 0.0))[..., :, None] * V.mT
        R = torch.where(chol[..., None, None], R, Re)
    return R, psd


def _min_norm_solve(M: Tensor, y: Tensor) -> Tensor:
    """``M† y`` per element (``M (*B, k, n)``, ``y (*B, k)``): the minimum-norm least-squares solution by the
    SVD (:func:`torch.linalg.pinv`, singular values below ``max(k, n) ε σ_max`` dropped, as
    ``numpy.linalg.lstsq``; the same on CPU and CUDA, where LAPACK's rank-revealing ``lstsq`` drivers are not
    available), differentiable where the rank is constant.  NaN for an element with a non-finite entry."""
    finite = torch.isfinite(M).flatten(-2).all(-1) & torch.isfinite(y).all(-1)
    rtol = max(M.shape[-2], M.shape[-1]) * torch.finfo(M.dtype).eps
    P = torch.linalg.pinv(torch.where(finite[..., None, None], M, 0.0), rtol=rtol)
    x = (P @ torch.where(finite[..., None], y, 0.0).unsqueeze(-1)).squeeze(-1)
    return torch.where(finite[..., None], x, math.nan)


def least_squares(A: Tensor, b: Tensor, ridge: float | Tensor = 0.0, weights: Tensor | None = None) -> Tensor:
    """``x̂ = argmin ‖Ax − b‖²_W + α‖x‖²`` (seed 004 §3.4, Eqs. 12–16), batched and differentiable.

    * ``ridge = 0``, no weights: ``x̂ = A† b`` (Eq. 12; the minimum-norm solution when ``A`` is
      rank-deficient, as ``numpy.linalg.lstsq``);
    * ``ridge = α > 0``: ``(Aᵀ W A + α I)⁻¹ Aᵀ W b`` (Eqs. 13, 15; ``W = I`` without weights);
    * ``weights = W``, ``ridge = 0``: ``(Aᵀ W A)† Aᵀ W b`` (Eq. 14; a PSD ``W`` with a zero block is
      Eq. 16).

    The normal matrix ``Aᵀ W A`` (whose condition number is the square of ``A``'s) is never formed: with
    ``W = L Lᵀ`` (Cholesky; for a singular PSD ``W`` its eigen-decomposition), all three are the
    minimum-norm least-squares solution of the whitened system stacked with the ridge rows,
    ``‖[Lᵀ A; √α I] x − [Lᵀ b; 0]‖²``, solved by the SVD (:func:`torch.linalg.pinv` with
    ``rtol = max(rows, n) ε``, as ``numpy.linalg.lstsq``; also on CUDA).  So a zero ``α`` (a number or an
    entry of a tensor ``ridge``) gives ``(√W A)† √W b`` — ``A† b`` for a rank-deficient ``A`` — and a
    tiny ``α`` its limit.

    Gradients reach ``A``, ``b``, ``weights`` and a tensor ``ridge`` by autograd through
    :func:`torch.linalg.pinv` (where the rank is constant, e.g. full; the gradient w.r.t. a ridge entry
    that is exactly ``0`` is returned as ``0``).  An element with NaN/inf data, or with a ``W`` that is not
    positive semi-definite (an eigenvalue below ``−m ε max|λ|``), gets a NaN ``x̂`` without affecting the
    others.

    Args:
        A: ``(*B, m, n)``.
        b: ``(*B, m)``.
        ridge: ``α ≥ 0``: a number, or a tensor ``(*B,)`` broadcasting with the batch.
        weights: optional ``W (*B, m, m)`` positive semi-definite (only ``(W + Wᵀ)/2`` is used, as the cost
            sees only that; so gradients w.r.t. ``W`` are symmetric).

    Returns:
        ``x̂ (*B, n)`` (batch dims broadcast from ``A``, ``b``, ``weights``, ``ridge``).
    """
    fn = "least_squares"
    extra = {}
    if isinstance(ridge, Tensor):
        extra["ridge"] = ridge
    elif isinstance(ridge, bool) or not isinstance(ridge, numbers.Real):
        raise TypeError(f"{fn}: argument 'ridge' must be a number >= 0 or a tensor (*B,), "
                        f"got {type(ridge).__name__}")
    else:
        ridge = _positive(ridge, "ridge", fn, allow_zero=True)
    _ls_inputs(fn, A, b, weights, extra)
    shapes = {"A": tuple(A.shape[:-2]), "b": tuple(b.shape[:-1])}
    if weights is not None:
        shapes["weights"] = tuple(weights.shape[:-2])
    if isinstance(ridge, Tensor):
        shapes["ridge"] = tuple(ridge.shape)
        if bool((ridge.detach() < 0).any()):
            raise ValueError(f"{fn}: argument 'ridge' must be >= 0 everywhere")
    batch = _batch_of(fn, **shapes)
    m, n = A.shape[-2:]
    M, y = A, b
    psd = None
    if weights is not None:
        R, psd = _weight_factor(0.5 * (weights + weights.mT))  # the cost sees only the symmetric part
        M = R @ A
        y = (R @ b.unsqueeze(-1)).squeeze(-1)
    if isinstance(ridge, Tensor) or ridge > 0.0:
        eye = torch.eye(n, dtype=A.dtype, device=A.device)
        s = _sqrt0(ridge)[..., None, None] if isinstance(ridge, Tensor) else math.sqrt(ridge)
        rows = (s * eye).expand(batch + (n, n))
        M = torch.cat((M.expand(batch + (m, n)), rows), -2)
        y = torch.cat((y.expand(batch + (m,)), y.new_zeros(batch + (n,))), -1)
    x = _min_norm_solve(M, y)
    if psd is not None:
        x = torch.where(psd[..., None], x, math.nan)
    return x.expand(batch + (n,))


def constrained_least_squares(A: Tensor, b: Tensor, C: Tensor, d: Tensor,
                              weights: Tensor | None = None) -> ConstrainedLSResult:
    """``min_x ‖Ax − b‖²_W  s.t.  Cx = d`` by the KKT system of seed 004 §3.5 (Eq. 17; the seed's ``h`` is
    ``d`` here), batched and differentiable::

        [Aᵀ W A   Cᵀ] [x]   [Aᵀ W b]
        [  C      0 ] [λ] = [  d   ]

    (the multiplier scaled as in the seed: the cost's factor 2 is absorbed into ``λ``).  Solved by LU
    (:func:`torch.linalg.solve_ex`).  An element whose KKT matrix is singular — ``C`` without full row rank,
    or ``√W A`` not of full column rank on the null space of ``C``, each tested numerically (a singular
    value below ``max(rows, n) ε σ_max``, so also a ``C`` that is singular only up to rounding) — or whose
    ``W`` is not positive semi-definite, or with NaN/inf data, gets NaN in its ``x`` and ``λ`` without
    affecting the others.  Gradients reach ``A``, ``b``, ``C``, ``d`` and ``weights`` by autograd.

    Args:
        A: ``(*B, m, n)``; b: ``(*B, m)``; C: ``(*B, p, n)`` with ``p ≤ n``; d: ``(*B, p)``.
        weights: optional ``W (*B, m, m)`` positive semi-definite (only ``(W + Wᵀ)/2`` is used, as the cost
            sees only that; so gradients w.r.t. ``W`` are symmetric).

    Returns:
        :class:`ConstrainedLSResult` ``(x (*B, n), multiplier (*B, p))``.
    """
    fn = "constrained_least_squares"
    for name, v in (("C", C), ("d", d)):
        if not isinstance(v, Tensor):
            raise TypeError(f"{fn}: argument '{name}' must be a torch.Tensor, got {type(v).__name__}")
    _ls_inputs(fn, A, b, weights, {"C": C, "d": d})
    n = A.shape[-1]
    if C.dim() < 2 or C.shape[-1] != n:
        raise ValueError(f"{fn}: argument 'C' must have shape (*B, p, {n}) (n = columns of A), "
                         f"got {tuple(C.shape)}")
    p = C.shape[-2]
    if p > n or p < 1:
        raise ValueError(f"{fn}: argument 'C' must have 1 <= p <= n = {n} rows, got {p}")
    if d.dim() < 1 or d.shape[-1] != p:
        raise ValueError(f"{fn}: argument 'd' must have shape (*B, {p}) (p = rows of C), "
                         f"got {tuple(d.shape)}")
    shapes = {"A": tuple(A.shape[:-2]), "b": tuple(b.shape[:-1]), "C": tuple(C.shape[:-2]),
              "d": tuple(d.shape[:-1])}
    if weights is not None:
        shapes["weights"] = tuple(weights.shape[:-2])
    batch = _batch_of(fn, **shapes)
    if weights is not None:
        weights = 0.5 * (weights + weights.mT)  # the cost sees only the symmetric part
    AtW = A.mT if weights is None else A.mT @ weights
    N = (AtW @ A).expand(batch + (n, n))
    Cb = C.expand(batch + (p, n))
    zero = torch.zeros(batch + (p, p), dtype=A.dtype, device=A.device)
    K = torch.cat((torch.cat((N, Cb.mT), -1), torch.cat((Cb, zero), -1)), -2)
    rhs = torch.cat(((AtW @ b.unsqueeze(-1)).squeeze(-1).expand(batch + (n,)), d.expand(batch + (p,))), -1)
    sol, info = torch.linalg.solve_ex(K, rhs)
    # LU is backward stable, so a numerically singular KKT matrix gives a finite, meaningless answer: test
    # its two conditions on the data instead (numerical rank by the SVD, tolerance max(rows, n) ε σ_max)
    well_posed = (info == 0) & _kkt_well_posed(A, C, weights)
    sol = torch.where(well_posed[..., None], sol, math.nan)
    return ConstrainedLSResult(x=sol[..., :n], multiplier=sol[..., n:])


def _kkt_well_posed(A: Tensor, C: Tensor, weights: Tensor | None) -> Tensor:
    """``(*B,)``: ``C (*B, p, n)`` has full row rank and ``√W A`` full column rank on ``null(C)``
    (numerically: no singular value below ``max(rows, n) ε σ_max``); False for non-finite data or a ``W``
    that is not PSD.  A mask only: computed without gradients."""
    with torch.no_grad():
        p, n = C.shape[-2:]
        eps = torch.finfo(C.dtype).eps
        finite_c = torch.isfinite(C).flatten(-2).all(-1)
        _, sC, Vh = torch.linalg.svd(torch.where(finite_c[..., None, None], C, 0.0))
        ok = finite_c & (sC[..., -1] > max(p, n) * eps * sC[..., 0])
        if p == n:
            return ok
        M, psd = A, None
        if weights is not None:
            R, psd = _weight_factor(weights)
            M = R @ A
        finite_m = torch.isfinite(M).flatten(-2).all(-1)
        M = torch.where(finite_m[..., None, None], M, 0.0)
        sM = torch.linalg.svdvals(M)[..., :1]  # σ_max(√W A)
        sZ = torch.linalg.svdvals(M @ Vh[..., p:, :].mT)  # √W A on an orthonormal basis of null(C)
        ok = ok & finite_m & (sZ[..., -1] > max(M.shape[-2], n) * eps * sM[..., 0])
        return ok if psd is None else ok & psd
