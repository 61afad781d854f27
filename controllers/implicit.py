"""Implicit gradients of the LQR/LQT solution from its optimality (KKT) conditions.

The idea is that of Amos et al. 2018, *Differentiable MPC for End-to-end Planning and Control*: the
optimal trajectory ``z = (τ, λ)`` of an LQ problem solves a symmetric linear system ``M z = b``
(stationarity of the Lagrangian and the dynamics), so for a loss ``ℓ(τ)`` with ``ḡ = ∂ℓ/∂τ``::

    ∂ℓ/∂θ = dᵀ ∂b/∂θ - dᵀ (∂M/∂θ) z,       M d = [ḡ; 0].

Solving ``M d = [ḡ; 0]`` is itself an LQ problem with the *same* Hessians and dynamics, linear cost
terms ``-ḡ``, no drift and ``x_0 = 0``, so it reuses the factors of the forward Riccati pass: one extra
backward sweep on vectors.  With this package's conventions (:mod:`controllers.costs`: stage cost
``τᵀCτ + 2gᵀτ``, multipliers ``λ_t = P_t x_t + p_t``; KKT rows ``C_t τ_t + g_t + F_tᵀ λ_{t+1} = [λ_t; 0]``,
``F_t τ_t + c_t = x_{t+1}``, ``x_0 = x_init``) the gradients are, with ``e = -d + ḡ_J τ`` (``ḡ_J`` the
cotangent of the optimal cost, handled by the envelope theorem)::

    ∂Q_t = sym(e_x x_tᵀ)   ∂R_t = sym(e_u u_tᵀ)   ∂N_t = e_x u_tᵀ + x_t e_uᵀ
    ∂q_t = e_x + ḡ_J x_t   ∂r_t = e_u + ḡ_J u_t
    ∂A_t = λ_{t+1} e_xᵀ + e_λ x_tᵀ   ∂B_t = λ_{t+1} e_uᵀ + e_λ u_tᵀ   (e_λ = -d_λ,t+1 + ḡ_J λ_{t+1})
    ∂c_t = e_λ + ḡ_J λ_{t+1}          ∂x_init = -d_λ,0 + 2 ḡ_J λ_0

Memory is O(T) (gains, Cholesky factors, value matrices, the trajectory) and the cost of the backward
pass does not depend on how the forward solution was obtained.  The gains ``K``, ``k`` are outputs
without a gradient in this mode (differentiate them with ``grad="unrolled"`` in
:func:`controllers.riccati.lqr`).
"""

from __future__ import annotations

import dataclasses

import torch

from controllers import _lq_kernels as _k
from controllers.boxqp import at_lower, masked_hessian
from controllers.costs import (
    PeriodicQuadraticCost,
    QuadraticCost,
    cost_derivatives,
    hessian_rows,
    lq_coefficients,
)
from controllers.dynamics import has_analytic_jacobian, step_all, trajectory_jacobians

__all__ = ["LQRFunction", "lqr_implicit", "adjoint_solve", "ilqr_implicit", "reduced_hessian_pd"]

#: iterative-refinement steps of the primal and adjoint solutions in the backward pass (:func:`_refine`)
_REFINE_STEPS = 3


def adjoint_solve(Phi: torch.Tensor, B: torch.Tensor, K: torch.Tensor, L: torch.Tensor, P: torch.Tensor,
                  qa: torch.Tensor, ra: torch.Tensor, compiled: bool = False):
    """Solve the LQ problem with the stored factors, linear terms ``qa (Bt, T+1, n)``, ``ra (Bt, T, m)``,
    no drift and ``x_0 = 0``.  ``compiled``: its two sweeps as compiled programs
    (:func:`controllers._lq_kernels.lin_sweep`).

    Args:
        Phi: closed-loop ``A_t + B_t K_t`` ``(Bt, T, n, n)``; B: ``(bB, TB, n, m)``; K: ``(Bt, T, m, n)``;
            L: Cholesky factors of ``H_uu`` ``(Bt, T, m, m)``; P: value matrices ``(Bt, T+1, n, n)``.

    Returns:
        ``(dx (Bt, T+1, n), du (Bt, T, m), dlam (Bt, T+1, n))``.
    """
    Bt, T, n = Phi.shape[0], Phi.shape[1], Phi.shape[-1]
    # p_t = (q_t + K_tᵀ r_t) + Φ_tᵀ p_{t+1},   p_T = q_T
    qhat = qa[:, :T] + torch.matmul(K.mT, ra.unsqueeze(-1)).squeeze(-1)
    p = _k.lin_sweep(Phi.mT, qhat, qa[:, T], True, compiled)
    # k_t = -H_uu⁻¹ (r_t + B_tᵀ p_{t+1})
    Bb = B if B.shape[1] > 1 else B.expand(B.shape[0], T, *B.shape[2:])
    qu = ra + torch.matmul(Bb.mT, p[:, 1:].unsqueeze(-1)).squeeze(-1)
    kk = -torch.cholesky_solve(qu.unsqueeze(-1), L)  # (Bt, T, m, 1)
    Bk = torch.matmul(Bb, kk).squeeze(-1).expand(Bt, T, n)
    dx = _k.lin_sweep(Phi, Bk, torch.zeros((), dtype=Phi.dtype, device=Phi.device).expand(Bt, n), False,
                      compiled)
    du = (torch.matmul(K, dx[:, :T].unsqueeze(-1)) + kk).squeeze(-1)
    dlam = _mv(P, dx) + p
    return dx, du, dlam


def _tv(v: torch.Tensor, T: int) -> torch.Tensor:
    """``(b, Tv, ...)`` with ``Tv`` 1 or ``T`` -> a view with ``T`` time steps."""
    return v if v.shape[1] == T else v.expand(v.shape[0], T, *v.shape[2:])


def _mv(M: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    return torch.matmul(M, v.unsqueeze(-1)).squeeze(-1)


def _refine(Phi, A, B, K, L, P, Q, R, N, qlin, rlin, x, u, steps: int, compiled: bool = False):
    """Iterative refinement of an LQ solution ``(x, u)`` with linear terms ``qlin, rlin`` (either None).

    The Riccati gains are computed from value matrices that grow with the cost weights, so the closed-loop
    trajectory carries an absolute error of about ``‖P‖ ε``; a costate ``λ_T = Q_T x_T + q_T`` multiplies
    that error by ``‖Q_T‖`` again (an error ``~w² ε`` for a terminal weight ``w``).  Each step takes the
    costates from the stationarity in ``x`` (backward recursion
    ``λ_t = Q_t x_t + q_t + N_t u_t + A_tᵀ λ_{t+1}``, ``λ_T = Q_T x_T + q_T``), measures the residual of
    the stationarity in ``u``, ``ρ_t = R_t u_t + r_t + N_tᵀ x_t + B_tᵀ λ_{t+1}``, and removes it with
    the stored factors (the dynamics hold to round-off by construction of the forward pass).  Stops when
    ``max|ρ|`` is below ``64 ε`` relative to the terms that cancel in it (well-conditioned problems: no
    correction at all) or after ``steps`` corrections (three reach the round-off floor at a weight of
    1e8 in float64; the residual itself cannot certify that floor, its terms cancel too).
    Returns ``(x, u, λ)`` with ``λ`` consistent with the returned trajectory.  ``compiled``: the sweeps as
    compiled programs.
    """
    T = u.shape[1]
    QT = _tv(Q, T + 1)
    Rt, Bt_ = _tv(R, T), _tv(B, T)
    Nt = None if N is None else _tv(N, T)
    At = A.mT
    fi = torch.finfo(x.dtype)
    tol, tiny = 64 * fi.eps, fi.tiny
    for it in range(steps + 1):
        g = _mv(QT, x)
        if qlin is not None:
            g = g + qlin
        if Nt is not None:
            g = torch.cat([g[:, :T] + _mv(Nt, u), g[:, T:]], 1)
        lam = _k.lin_sweep(At, g[:, :T], g[:, T], True, compiled)
        terms = [_mv(Rt, u), _mv(Bt_.mT, lam[:, 1:])]
        if rlin is not None:
            terms.append(rlin)
        if Nt is not None:
            terms.append(_mv(Nt.mT, x[:, :T]))
        rho = sum(terms)
        # residual relative to the terms that cancel in it, per element (non-finite elements ignored)
        rel = rho.abs().flatten(1).amax(1) / sum(v.abs() for v in terms).flatten(1).amax(1).clamp_min(tiny)
        if it == steps or not bool((torch.nan_to_num(rel, nan=0.0, posinf=0.0) > tol).any()):
            return x, u, lam
        dx, du, _ = adjoint_solve(Phi, B, K, L, P, torch.zeros_like(x), rho, compiled)
        x, u = x + dx, u + du


def _sym(M: torch.Tensor) -> torch.Tensor:
    return 0.5 * (M + M.mT)


def _outer(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return a.unsqueeze(-1) * b.unsqueeze(-2)


class LQRFunction(torch.autograd.Function):
    """``(A, B, c, Q, R, N, q, r, x0) -> (x, u, J, K, k, ok)`` flattened over the batch ``(Bt, ...)``.

    Forward: the Riccati solve of :mod:`controllers.riccati`.  Backward: the implicit gradient of the
    module docstring.  ``K``, ``k``, ``info`` are non-differentiable outputs.  ``compiled``: the forward
    solve and the sweeps of the backward pass as compiled programs (:mod:`controllers._lq_kernels`).
    """

    @staticmethod
    def forward(ctx, A, B, c, Q, R, N, q, r, x0, T, bs, fused=False, compiled=False):
        n, m = A.shape[-1], B.shape[-1]
        x, u, J, fac, F = _k.solve_core(A, B, c, Q, R, N, q, r, x0, T, bs, keep_huu=True, fused=fused,
                                        compiled=compiled)
        Bt = x.shape[0]
        K = fac.Kt[..., :n]
        k = fac.Kt[..., n]
        ctx.T, ctx.bs, ctx.n, ctx.m, ctx.compiled = T, bs, n, m, compiled
        ctx.shapes = [None if v is None else v.shape for v in (A, B, c, Q, R, N, q, r, x0)]
        ctx.has = [v is not None for v in (A, B, c, Q, R, N, q, r, x0)]
        Bflat = F[..., :n, :m]
        cost = ((Q, 2), (R, 2), (N, 2), (q, 1), (r, 1))
        fl = [None if v is None else _k.flat(v, bs, k) for v, k in cost]
        ctx.save_for_backward(x, u, fac.Kt, fac.Huu, fac.V, F, Bflat, fac.ok, *fl)
        ctx.mark_non_differentiable(K, k, fac.ok)
        ctx.Bt = Bt
        return x, u, J, K, k, fac.ok

    @staticmethod
    def backward(ctx, gx, gu, gJ, _gK, _gk, _ginfo):
        x, u, Kt, Huu, V, F, Bm, ok, Q, R, N, q, r = ctx.saved_tensors
        T, n, m, Bt, bs = ctx.T, ctx.n, ctx.m, ctx.Bt, ctx.bs
        dt, dev = x.dtype, x.device
        gx = torch.zeros(Bt, T + 1, n, dtype=dt, device=dev) if gx is None else gx
        gu = torch.zeros(Bt, T, m, dtype=dt, device=dev) if gu is None else gu
        gJ = torch.zeros(Bt, dtype=dt, device=dev) if gJ is None else gJ
        K = Kt[..., :n]
        Phi = _k.closed_loop(F, Kt, m)[..., :n, :n]
        P = V[..., :n, :n]
        L, _ = torch.linalg.cholesky_ex(Huu)
        A = F[..., :n, m:m + n]
        # costates and adjoint trajectory refined against the stationarity conditions (see _refine): the
        # plain λ = P x + p and the adjoint sweep lose accuracy like ‖Q‖²ε for large weights
        steps = _REFINE_STEPS
        cc = ctx.compiled
        x, u, lam = _refine(Phi, A, Bm, K, L, P, Q, R, N, q, r, x, u, steps, cc)
        dx, du, _ = adjoint_solve(Phi, Bm, K, L, P, -gx, -gu, cc)
        dx, du, dlam = _refine(Phi, A, Bm, K, L, P, Q, R, N, -gx, -gu, dx, du, steps, cc)
        # an element whose H_uu was not positive definite (SINGULAR_QUU) has no gradient: its factors are
        # garbage, and 0·NaN would reach the summed gradient of a shared parameter; it contributes zero
        good = ok.all(-1)[:, None, None]
        x, u, lam, dlam = (torch.where(good, v, 0.0) for v in (x, u, lam, dlam))
        gJ1 = torch.where(good, gJ[:, None, None], 0.0)
        ex = torch.where(good, -dx + gJ1 * x, 0.0)
        eu = torch.where(good, -du + gJ1 * u, 0.0)
        el = -dlam[:, 1:] + gJ1 * lam[:, 1:]
        needs = ctx.needs_input_grad
        out = [None] * 13

        def fit(g: torch.Tensor, idx: int, k: int) -> torch.Tensor:
            shp = ctx.shapes[idx]
            g = g.reshape(*bs, *g.shape[1:])
            Tin = shp[len(shp) - k - 1] if idx != 8 else None
            if Tin == 1 and g.shape[len(bs)] != 1:
                g = g.sum(len(bs), keepdim=True)
            return g.sum_to_size(shp)

        if needs[0]:
            out[0] = fit(_outer(lam[:, 1:], ex[:, :T]) + _outer(el, x[:, :T]), 0, 2)
        if needs[1]:
            out[1] = fit(_outer(lam[:, 1:], eu) + _outer(el, u), 1, 2)
        if needs[2]:
            out[2] = fit(el + gJ1 * lam[:, 1:], 2, 1)
        if needs[3]:
            out[3] = fit(_sym(_outer(ex, x)), 3, 2)
        if needs[4]:
            out[4] = fit(_sym(_outer(eu, u)), 4, 2)
        if needs[5]:
            out[5] = fit(_outer(ex[:, :T], u) + _outer(x[:, :T], eu), 5, 2)
        if needs[6]:
            out[6] = fit(ex + gJ1 * x, 6, 1)
        if needs[7]:
            out[7] = fit(eu + gJ1 * u, 7, 1)
        if needs[8]:
            g0 = -dlam[:, 0] + 2 * gJ1[:, 0] * lam[:, 0]
            out[8] = g0.reshape(*bs, n).sum_to_size(ctx.shapes[8])
        return tuple(out)


def lqr_implicit(A, B, c, Q, R, N, q, r, x0, T: int, bs: torch.Size, fused: bool = False,
                 compiled: bool = False):
    """Run :class:`LQRFunction`; returns flattened ``(x, u, J, K, k, ok)``."""
    return LQRFunction.apply(A, B, c, Q, R, N, q, r, x0, T, bs, fused, compiled)


# --------------------------------------------------------------------------------------------------
# iLQR: the implicit gradient at a (control-limited) local optimum
# --------------------------------------------------------------------------------------------------


def _bound_motion(u: torch.Tensor, free: torch.Tensor, lo: torch.Tensor | None,
                  hi: torch.Tensor | None, grad: torch.Tensor) -> torch.Tensor | None:
    """``(*B, T, m)``, zero in value: ``b - sg(b)`` on the clamped controls, ``b`` the limit each sits on
    (:func:`controllers.boxqp.at_lower`: the nearer one, never a midpoint of possibly infinite limits; at
    equal limits the one ``grad = ∇_u J`` pushes against), zero on the free ones; None when no limit has a
    graph.  Its derivative is the identity from a clamped control's limit to that control."""
    if lo is None or not (lo.requires_grad or hi.requires_grad):
        return None
    clamped = ~free
    on_lo = at_lower(u, lo.detach(), hi.detach(), grad.detach())
    b = torch.where(clamped, torch.where(on_lo, lo, hi), u)
    return b - b.detach()


def ilqr_implicit(problem, x0s: torch.Tensor, x: torch.Tensor, u: torch.Tensor, free: torch.Tensor,
                  bs: torch.Size, lo: torch.Tensor | None = None, hi: torch.Tensor | None = None, *,
                  compile: bool = False):
    """Give iLQR's solution ``x, u`` of ``problem`` (an :class:`~controllers.ilqr.ILQRProblem`) the implicit
    derivatives of its KKT conditions (:mod:`controllers.ilqr` docstring).

    ``x + (δx - sg(δx))`` where ``δx`` is the Newton step on the KKT system (≈ 0 at a stationary point):
    the value is unchanged and the derivative is ``-K⁻¹ ∂F/∂θ``.  Clamped controls are fixed on their
    bounds: their stationarity rows are replaced by ``δu = δb`` with ``b`` the limit they sit on
    (``lo``/``hi``, ``(*B, T, m)``, differentiable), so ``∂u_c/∂b = 1`` and the free controls and states
    respond through the same Newton step (``δb`` drives the linearized dynamics through ``B`` and the
    stationarity of the free controls through the Hessian's cross terms).

    ``compile`` (:attr:`~controllers.ilqr.ILQROptions.compile`): the costates, the LQ solve of the Newton
    step and the sweeps of its backward pass run as compiled programs (:mod:`controllers._lq_kernels`);
    the same values and gradients as the eager path up to round-off.
    """
    T, n, m = problem.T, problem.n, problem.m
    x0 = problem.x0.expand(*bs, n)
    x0 = torch.where(torch.isfinite(x0), x0, torch.zeros((), dtype=x0.dtype, device=x0.device))
    x, u = x.detach(), u.detach()
    newton = _newton_data_analytic if _analytic_ok(problem) else _newton_data_autograd
    with torch.enable_grad():
        rx, ru, cdyn, c0, Hxx, Hxu, Huu, A, B = newton(problem, x0, x, u, bs, compile)
        db = _bound_motion(u, free, lo, hi, ru)
        if db is None and not any(v.requires_grad for v in (rx, ru, cdyn, c0)):
            return x, u  # nothing upstream has a graph: no derivative to give
        fm = free.to(x.dtype)
        Bf = B.movedim(0, -3)
        if db is not None:
            # the clamped controls move with their limits: a drift of the linearized dynamics and linear
            # terms in the stationarity of the states and of the free controls
            cdyn = cdyn + (Bf @ db.unsqueeze(-1)).squeeze(-1)
            hxu = (Hxu[..., :T, :, :] @ db.unsqueeze(-1)).squeeze(-1)
            rx = rx + torch.cat([hxu, torch.zeros_like(hxu[..., :1, :])], -2)
            ru = ru + (Huu @ db.unsqueeze(-1)).squeeze(-1)
        Bm = Bf * fm.unsqueeze(-2)
        # the Newton step's LQ problem: coefficients of the Lagrangian's second-order model (clamped
        # controls fixed on their bounds: their rows and columns masked out)
        Q, R, N, q, r = lq_coefficients(rx, ru * fm, Hxx, (Hxu[..., :T, :, :] * fm.unsqueeze(-2)).mT,
                                        masked_hessian(Huu, free))
        A = A.movedim(0, -3).expand(*bs, T, n, n)
        dx, du, *_ = lqr_implicit(A, Bm, cdyn, Q, R, N, q, r, c0, T, bs, compiled=compile)
        dx, du = dx.reshape(*bs, T + 1, n), du.reshape(*bs, T, m)
    u = u + (du - du.detach())
    return x + (dx - dx.detach()), u if db is None else u + db


def _newton_data_autograd(problem, x0, x, u, bs, compile):
    """The data of the Newton step by autograd: the Lagrangian's gradient ``(rx, ru)`` with its graph
    to the parameters, its Hessian blocks (constants), the dynamics' residual ``cdyn`` and ``c0`` with
    theirs, and ``A, B`` (time-major, constants).  Any cost and system."""
    dyn, cost = problem.dynamics, problem.cost
    T, n, m = problem.T, problem.n, problem.m
    A, B = trajectory_jacobians(dyn, x, u)  # time-major
    A, B = A.detach(), B.detach()
    lam = _costates(cost, x, u, A, bs, compile)
    xs = x.clone().requires_grad_(True)
    us = u.clone().requires_grad_(True)
    cdyn = step_all(dyn, xs[..., :T, :], us) - xs[..., 1:, :]
    c0 = x0 - xs[..., 0, :]
    L = cost.evaluate(xs, us).sum() + (lam[..., 1:, :] * cdyn).sum() + (lam[..., 0, :] * c0).sum()
    rx, ru = torch.autograd.grad(L, (xs, us), create_graph=True)
    Hxx, Hxu, Huu = hessian_rows(rx, ru, xs, us, n, m)
    return rx, ru, cdyn, c0, Hxx, Hxu, Huu, A, B


def _analytic_ok(problem) -> bool:
    """Whether :func:`_newton_data_analytic` applies: a quadratic cost (analytic derivatives, differentiable
    in its weights) and a system with an analytic Jacobian whose fields carry no graph (plain numbers or
    tensors that do not require grad), so that the dynamics add a constant curvature and residual."""
    dyn, cost = problem.dynamics, problem.cost
    if not isinstance(cost, (QuadraticCost, PeriodicQuadraticCost)) or not has_analytic_jacobian(dyn):
        return False
    if not dataclasses.is_dataclass(dyn):
        return False
    for f in dataclasses.fields(dyn):
        v = getattr(dyn, f.name)
        if isinstance(v, torch.Tensor):
            if v.requires_grad:
                return False
        elif not (v is None or isinstance(v, (bool, int, float, str))):
            return False  # a callable (NonlinearDynamics) may close over parameters
    return True


def _newton_data_analytic(problem, x0, x, u, bs, compile):
    """:func:`_newton_data_autograd` without differentiating the Lagrangian twice: the cost's exact
    derivatives (:meth:`QuadraticCost.derivatives`, with their graph to the weights), the analytic
    Jacobians ``A, B`` (one call) and the dynamics' curvature ``Σ λ_{t+1}ᵀ f(x_t, u_t)`` as the derivative
    of ``A_tᵀλ_{t+1}``, ``B_tᵀλ_{t+1}`` (one level of autograd on the Jacobian, constants).  With
    ``∂L/∂x_t = ∂l/∂x_t + A_tᵀλ_{t+1} − λ_t`` (``t < T``), ``∂L/∂x_T = ∂l/∂x_T − λ_T``,
    ``∂L/∂u_t = ∂l/∂u_t + B_tᵀλ_{t+1}``: the same data to round-off (the weights are symmetric)."""
    dyn, cost = problem.dynamics, problem.cost
    T, n, m = problem.T, problem.n, problem.m
    xs = x.clone().requires_grad_(True)
    us = u.clone().requires_grad_(True)
    Ag, Bg = trajectory_jacobians(dyn, xs, us)  # time-major, with a graph to xs, us where they depend
    A, B = Ag.detach(), Bg.detach()
    lam = _costates(cost, x, u, A, bs, compile)
    lam1 = lam[..., 1:, :].movedim(-2, 0)  # (T, *B, n)
    gxd = (Ag.mT @ lam1.unsqueeze(-1)).squeeze(-1).movedim(0, -2)  # (*B, T, n)
    gud = (Bg.mT @ lam1.unsqueeze(-1)).squeeze(-1).movedim(0, -2)
    gxd = torch.cat([gxd, torch.zeros_like(gxd[..., :1, :])], -2)
    Hxx, Hxu, Huu = hessian_rows(gxd, gud, xs, us, n, m)
    gx, gu, cHxx, cHux, cHuu = cost.derivatives(x, u)
    Hxx = Hxx + cHxx.detach()
    Huu = Huu + cHuu.detach()
    if cHux is not None:
        cHxu = cHux.detach().mT
        Hxu = Hxu + torch.cat([cHxu, torch.zeros_like(cHxu[..., :1, :, :])], -3)
    rx = gx + gxd.detach() - lam
    ru = gu + gud.detach()
    with torch.no_grad():
        cdyn = step_all(dyn, x[..., :T, :], u) - x[..., 1:, :]
    return rx, ru, cdyn, x0 - x[..., 0, :], Hxx, Hxu, Huu, A, B


def _costates(cost, x: torch.Tensor, u: torch.Tensor, A: torch.Tensor, bs: torch.Size,
              compiled: bool = False) -> torch.Tensor:
    """``λ (*B, T+1, n)``: ``λ_T = ∂l/∂x_T``, ``λ_t = ∂l/∂x_t + A_tᵀ λ_{t+1}`` (``A`` time-major).

    An element whose costates overflow (unstable ``A`` at absurd parameters: never a certified solution)
    gets ``λ = 0``: an infinite ``λ`` would make the Newton data's derivatives w.r.t. shared parameters NaN
    even under a zero cotangent, and through their sum every element's gradient."""
    T, n = u.shape[-2], x.shape[-1]
    with torch.no_grad():
        gx, *_ = cost_derivatives(cost, x, u)
        gx = gx.expand(*bs, T + 1, n).reshape(-1, T + 1, n)
        M = A.mT.expand(T, *bs, n, n).reshape(T, -1, n, n).movedim(0, 1)
        lam = _k.lin_sweep(M, gx[:, :T], gx[:, T], True, compiled)
        lam = torch.where(torch.isfinite(lam).flatten(1).all(-1)[:, None, None], lam, 0.0)
        return lam.reshape(*bs, T + 1, n)


def reduced_hessian_pd(problem, x: torch.Tensor, u: torch.Tensor, free: torch.Tensor,
                       bs: torch.Size) -> torch.Tensor:
    """``(*B,)`` bool: at the KKT point ``x, u`` of ``problem`` the exact Hessian of the cost in the free
    controls, with the dynamics eliminated (the Lagrangian's Hessian, dynamics' second derivatives
    included), is positive definite — the second-order sufficient condition of a strict local minimum
    with the clamped controls held.  Decided by the pivots of one Riccati sweep on that Hessian (all
    ``Q_uu,t`` positive definite iff the reduced Hessian is; a Gauss-Newton iLQR never sees negative
    curvature, so it can certify a saddle)."""
    dyn, cost = problem.dynamics, problem.cost
    T, n, m = problem.T, problem.n, problem.m
    x, u = x.detach(), u.detach()
    A, B = (v.detach() for v in trajectory_jacobians(dyn, x, u))
    lam = _costates(cost, x, u, A, bs)
    with torch.enable_grad():
        xs = x.clone().requires_grad_(True)
        us = u.clone().requires_grad_(True)
        y = step_all(dyn, xs[..., :T, :], us)
        if not y.requires_grad:  # the dynamics' second derivatives would be dropped without a word
            raise ValueError("ILQROptions(second_order=True) needs a system whose step autograd can "
                             f"differentiate (twice); {type(dyn).__name__}.step returned no graph")
        L = cost.evaluate(xs, us).sum() + (lam[..., 1:, :] * y).sum()
        rx, ru = torch.autograd.grad(L, (xs, us), create_graph=True)
        Hxx, Hxu, Huu = hessian_rows(rx, ru, xs, us, n, m)
    fm = free.to(x.dtype)
    Q, R, N, _, _ = lq_coefficients(rx.detach(), ru.detach(), Hxx,
                                    (Hxu[..., :T, :, :] * fm.unsqueeze(-2)).mT, masked_hessian(Huu, free))
    Bm = B.movedim(0, -3) * fm.unsqueeze(-2)
    A = A.movedim(0, -3).expand(*bs, T, n, n)
    with torch.no_grad():
        fac = _k.solve_core(A, Bm, None, Q, R, N, None, None, x[..., 0, :], T, bs)[3]
    return fac.ok.all(-1).reshape(bs)
