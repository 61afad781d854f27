"""Batch iLQR over a parameterization of the controls and of the initial state (seed 004 §8.1, §9.4, §9.12).

Algorithm 4 (Eq. 87 / 108) is a Gauss-Newton iteration on the whole control sequence: with the
linearization ``x = S_x x_0 + S_u u`` (transfer matrices of the ``A_t, B_t`` along the current
trajectory, Appendix A), one step solves

    (S_uᵀ H_xx S_u + H_uu) Δu = -(S_uᵀ g_x + g_u)

(plain derivatives ``g, H`` of the cost, :mod:`controllers.costs`; ``H_xx = 2 JᵀQJ`` for a
:class:`~controllers.costs.ResidualCost`).  This module takes the decision vector to be

    z = [x_0 ; w],    u = Ψ w,

* **control primitives** ``u = Ψ w`` (§9.12, as §7.3 does for LQT): ``Ψ (T m, K)`` from
  :func:`controllers.lifted.control_primitives` and :mod:`controllers.basis`, a coordination matrix
  folded in; ``Ψ = I`` is Algorithm 4 itself;
* **initial-state optimization** (§9.4, Eq. 109-110): with ``x0_weight = w̄ (n,)`` the initial state is a
  decision too, with the cost ``Σ_i w̄_i (x_0,i - x̄_0,i)²`` around the problem's ``x̄_0``; ``w̄_i = 0``
  frees entry ``i`` (the seed's ``R̃`` block of zeros), a large one pins it (Eq. 110).  E.g. a robot's
  base location as two prismatic joints whose later motion is priced out by a large control weight.

The step with ``S = [S_x, S_u Ψ]`` is ``(Sᵀ H_xx S + blockdiag(2 diag(w̄), Ψᵀ H_uu Ψ) + μ I) Δz = -g_z``
(cross terms ``H_ux`` included), then the backtracking line search of Algorithm 1 (``α = 1, ½, ...``, the
first that lowers the cost; if none does, ``μ`` grows and the step is retried next iteration).

Status (per element, :class:`~controllers.problem.Reason`): ``CONVERGED`` where every component of the
gradient ``g_z`` at the returned point is at most ``tol`` times its own scale ``|Sᵀ g_x|_i + |g_w|_i +
(|H| |z|)_i`` (the componentwise backward error of the Newton system; per component, so that a stiff block
such as a pinned ``x_0`` cannot certify the others), else
``MAX_ITERATIONS``, ``LINE_SEARCH_FAILED`` (``μ`` past ``mu_max``), ``NONFINITE_INPUT`` (NaN/inf in
that element's ``x0``, ``Psi`` or ``w_init``) or ``DIVERGED`` (the first rollout's cost is not finite:
NaN/inf in the cost's targets or batched weights); a failed element's outputs are NaN and the other
elements are solved as if alone.  Control
limits are not supported (a box on ``u = Ψ w`` is not a box on ``w``): :func:`controllers.ilqr.ilqr` takes
them.  Differentiation: the returned tensors carry no graph (``torch.no_grad``); for gradients through
the solution use :func:`controllers.ilqr.ilqr`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

from controllers.costs import ResidualCost, cost_derivatives
from controllers.dynamics import LinearDynamics, rollout, trajectory_jacobians
from controllers.ilqr import ILQRProblem
from controllers.lifted import transfer_matrices
from controllers.problem import Reason, SolverStatus

__all__ = ["LiftedGains", "LiftedILQRSolution", "ilqr_lifted", "lifted_feedback_gains"]


@dataclass(frozen=True)
class LiftedILQRSolution:
    """Result of :func:`ilqr_lifted`.

    Attributes:
        x: ``(*B, T+1, n)`` states; ``u``: ``(*B, T, m)`` controls ``Ψ w``; ``w``: ``(*B, K)`` weights;
        x0: ``(*B, n)`` the (optimized) initial state; cost: ``(*B,)`` including the ``x0_weight`` term;
        status: per-element :class:`~controllers.problem.SolverStatus`; cost_history: ``(iters+1, *B)``;
        grad_residual: ``(*B,)`` ``max_i |g_z,i| / scale_i`` at the returned point (``CONVERGED`` where at
        most ``tol``).
    """

    x: Tensor
    u: Tensor
    w: Tensor
    x0: Tensor
    cost: Tensor
    status: SolverStatus
    cost_history: Tensor
    grad_residual: Tensor


def _check(problem, Psi, x0_weight, w_init, max_iter, tol, line_search_steps, mu_init):
    fn = "ilqr_lifted"
    if not isinstance(problem, ILQRProblem):
        raise TypeError(f"{fn}: argument 'problem' must be an ILQRProblem, got {type(problem).__name__}")
    if problem.u_lower is not None or problem.u_upper is not None:
        raise ValueError(f"{fn}: control limits are not supported (a box on u = Ψw is not a box on w); use "
                         "controllers.ilqr.ilqr for limited controls")
    T, m = problem.T, problem.m
    if Psi is not None:
        if not isinstance(Psi, Tensor) or Psi.dim() < 2 or Psi.shape[-2] != T * m:
            raise ValueError(f"{fn}: argument 'Psi' must be a (*B, T·m, K) = (*B, {T * m}, K) tensor, got "
                             f"{tuple(Psi.shape) if isinstance(Psi, Tensor) else type(Psi).__name__}")
        if Psi.dtype != problem.dtype:
            raise TypeError(f"{fn}: argument 'Psi' must have the problem's dtype {problem.dtype}, got "
                            f"{Psi.dtype}")
    if x0_weight is not None:
        if not isinstance(x0_weight, Tensor) or x0_weight.shape[-1:] != (problem.n,):
            raise ValueError(f"{fn}: argument 'x0_weight' must be a (*B, n) = (*B, {problem.n}) tensor")
        if bool((x0_weight < 0).any()) or not bool(torch.isfinite(x0_weight).all()):
            raise ValueError(f"{fn}: argument 'x0_weight' must be finite and non-negative")
    if w_init is not None:
        K = T * m if Psi is None else Psi.shape[-1]
        if not isinstance(w_init, Tensor) or w_init.shape[-1:] != (K,):
            raise ValueError(f"{fn}: argument 'w_init' must be a (*B, K) = (*B, {K}) tensor (K: columns of "
                             "Psi)")
    if not isinstance(mu_init, (int, float)) or isinstance(mu_init, bool) or not mu_init >= 0:
        raise ValueError(f"{fn}: argument 'mu_init' must be a non-negative number, got {mu_init!r}")
    if isinstance(max_iter, bool) or not isinstance(max_iter, int) or max_iter < 1:
        raise ValueError(f"{fn}: argument 'max_iter' must be a positive int, got {max_iter!r}")
    if tol is not None and not tol > 0:
        raise ValueError(f"{fn}: argument 'tol' must be positive, got {tol!r}")
    if not isinstance(line_search_steps, int) or line_search_steps < 1:
        raise ValueError(f"{fn}: argument 'line_search_steps' must be a positive int, got "
                         f"{line_search_steps!r}")


def _rmul(v: Tensor, M: Tensor) -> Tensor:
    """``M v`` for vectors ``v (..., k)`` and ``M (..., r, k)``, as ``v Mᵀ``: with a matrix shared by the
    batch this is one matrix product over the folded batch (``M @ v`` would copy ``M`` once per element)."""
    if M.dim() == 2:
        return v @ M.mT
    return (M @ v.unsqueeze(-1)).squeeze(-1)


class _Model:
    """Cost, gradient and Gauss-Newton Hessian in ``z = [x0; w]`` at one point (all ``(*B, ...)``).

    Matrices shared by the batch (``Ψ``, the transfer matrices of time-invariant linear dynamics) are kept
    without batch dims and applied by folded matrix products."""

    def __init__(self, problem: ILQRProblem, Psi: Tensor, wbar: Tensor | None, xbar: Tensor, bs,
                 identity: bool = False):
        self.p, self.Psi, self.wbar, self.xbar, self.bs = problem, Psi, wbar, xbar, bs
        T, _n, m, K = problem.T, problem.n, problem.m, Psi.shape[-1]
        self.Psi_t = Psi.reshape(*Psi.shape[:-2], T, m, K)
        self.identity = identity  # Ψ = I: Ψᵀ H_uu Ψ is H_uu's block diagonal itself
        # a ResidualCost's state terms vanish where its precision Q_t is zero (between via points): the
        # steps with a nonzero Q_t, read once per solve, are the only ones S_tᵀ H_xx,t S_t is summed over
        self.active = None
        Q = problem.cost.Q if isinstance(problem.cost, ResidualCost) else None
        if Q is not None and Q.dim() >= 3 and Q.shape[-3] == T + 1:
            self.active = Q.movedim(-3, 0).reshape(T + 1, -1).ne(0).any(1).nonzero().squeeze(-1)
        d = problem.dynamics
        # linear dynamics: the transfer matrices are constant, built once; a rollout is then one product
        self.linear = None
        if isinstance(d, LinearDynamics):
            Sx, Su, sc = transfer_matrices(d.A, d.B, d.c, T)
            SuPsi = Su @ Psi
            S = SuPsi
            if wbar is not None:
                S = torch.cat([Sx.expand(*SuPsi.shape[:-2], *Sx.shape[-2:]), SuPsi], -1)
            self.linear = (Sx, SuPsi, sc, S)

    def cost(self, x0: Tensor, w: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        p = self.p
        T, n, m = p.T, p.n, p.m
        u = _rmul(w, self.Psi).reshape(*w.shape[:-1], T, m)
        if self.linear is None:
            x = rollout(p.dynamics, x0, u)
        else:
            Sx, SuPsi, sc, _ = self.linear
            xf = _rmul(x0, Sx) + _rmul(w, SuPsi)
            if sc is not None:
                xf = xf + sc
            x = xf.reshape(*xf.shape[:-1], T + 1, n)
        c = p.cost.evaluate(x, u)
        if self.wbar is not None:
            c = c + (self.wbar * (x0 - self.xbar) ** 2).sum(-1)
        return c, x, u

    def _jacobian(self, x: Tensor, u: Tensor) -> Tensor:
        """``S = [S_x, S_u Ψ]`` (or ``S_u Ψ``) ``(..., (T+1) n, K')`` along the trajectory."""
        if self.linear is not None:
            return self.linear[3]
        p = self.p
        A, B = trajectory_jacobians(p.dynamics, x[..., :-1, :], u)
        Sx, Su = transfer_matrices(A.movedim(0, -3), B.movedim(0, -3), None, p.T)[:2]
        SuPsi = Su @ self.Psi
        if self.wbar is None:
            return SuPsi
        return torch.cat([Sx.expand(*SuPsi.shape[:-2], *Sx.shape[-2:]), SuPsi], -1)

    def derivatives(self, x0: Tensor, w: Tensor, x: Tensor, u: Tensor):
        p, bs = self.p, self.bs
        T, n, m = p.T, p.n, p.m
        S = self._jacobian(x, u)
        Kz = S.shape[-1]
        Sk = S.reshape(*S.shape[:-2], T + 1, n, Kz)
        gx, gu, Hxx, Hux, Huu = cost_derivatives(p.cost, x, u)
        Ska, Hxa, gxa = Sk, Hxx, gx
        if self.active is not None and Hux is None:
            a = self.active
            Ska, gxa = Sk[..., a, :, :], gx[..., a, :]
            Hxa = Hxx[..., a, :, :] if Hxx.shape[-3] == T + 1 else Hxx
        # Sᵀ H_xx S with the block-diagonal H_xx, and Ψᵀ H_uu Ψ with the block-diagonal H_uu
        H = torch.einsum("...tik,...til->...kl", Ska, torch.einsum("...tij,...tjl->...til", Hxa, Ska))
        gx_z = torch.einsum("...tik,...ti->...k", Ska, gxa)
        if self.identity:
            Huu = Huu.expand(*Huu.shape[:-3], T, m, m)
            Hb = Huu.new_zeros(*Huu.shape[:-3], T, m, T, m)
            idx = torch.arange(T, device=Huu.device)
            Hb[..., idx, :, idx, :] = Huu
            Hw = Hb.reshape(*Huu.shape[:-3], T * m, T * m)
            guw = gu.reshape(*gu.shape[:-2], T * m)
        else:
            Hw = torch.einsum("...tak,...tal->...kl", self.Psi_t,
                              torch.einsum("...tab,...tbl->...tal", Huu, self.Psi_t))
            guw = _rmul(gu.reshape(*gu.shape[:-2], T * m), self.Psi.mT)
        H, Hw, guw, gx_z = H.expand(*bs, Kz, Kz), Hw.expand(*bs, *Hw.shape[-2:]), guw.expand(*bs, -1), \
            gx_z.expand(*bs, Kz)
        nx = 0
        if self.wbar is not None:
            nx = n
            Hw = torch.cat([torch.cat([torch.diag_embed(2 * self.wbar.expand(*bs, n)),
                                       Hw.new_zeros(*bs, n, Hw.shape[-1])], -1),
                            torch.cat([Hw.new_zeros(*bs, Hw.shape[-1], n), Hw], -1)], -2)
            guw = torch.cat([2 * self.wbar * (x0 - self.xbar), guw], -1)
        H = H + Hw
        if Hux is not None:  # Σ_t Δu_tᵀ H_ux,t Δx_t with Δu = Ψ_t Δw, Δx_t = S_t Δz
            Psi_t = self.Psi_t
            if nx:
                Psi_t = torch.cat([Psi_t.new_zeros(*Psi_t.shape[:-1], nx), Psi_t], -1)
            C = torch.einsum("...tak,...tai,...til->...kl", Psi_t, Hux, Sk[..., :T, :, :])
            H = H + C + C.mT
        H = 0.5 * (H + H.mT)
        z = torch.cat([x0.expand(*bs, n), w], -1) if nx else w
        # per component, as the backward error of the linear system H z = -(terms): |g_i| against
        # |terms_i| + (|H| |z|)_i — a stiff block (a pinned x0) cannot hide the other components' residual
        scale = gx_z.abs() + guw.abs() + (H.abs() @ z.abs().unsqueeze(-1)).squeeze(-1)
        return gx_z + guw, H, scale


def _residual(g: Tensor, scale: Tensor) -> Tensor:
    """``max_i |g_i| / scale_i`` (a component with zero gradient counts 0, even at zero scale)."""
    r = g.abs() / scale.clamp_min(torch.finfo(g.dtype).tiny)
    return torch.where(g == 0, torch.zeros((), dtype=g.dtype, device=g.device), r).amax(-1)


def _newton_step(g: Tensor, H: Tensor, mu: Tensor, done: Tensor) -> tuple[Tensor, Tensor]:
    """``Δz = -(H + μ I)⁻¹ g`` and where it exists (positive definite, element not done); zero elsewhere."""
    eye = torch.eye(H.shape[-1], dtype=H.dtype, device=H.device)
    L, info = torch.linalg.cholesky_ex(H + mu[..., None, None] * eye)
    ok = (info == 0) & ~done
    L = torch.where(ok[..., None, None], L, eye)
    dz = -torch.cholesky_solve(g.unsqueeze(-1), L).squeeze(-1)
    return torch.where(ok[..., None], dz, torch.zeros((), dtype=H.dtype, device=H.device)), ok


def _line_search(model: _Model, alphas: Tensor, dz: Tensor, ok: Tensor, x0: Tensor, w: Tensor, x: Tensor,
                 u: Tensor, c: Tensor, free_x0: bool):
    """Algorithm 1 with all step sizes ``α`` rolled out at once: per element the largest ``α`` that lowers
    the cost is taken.  Returns ``(take, first, x0, w, x, u, c)``: whether a step was taken, the index of
    its ``α`` (0: the full step), and the state after it."""
    bs, n = model.bs, model.p.n
    a = alphas.reshape(-1, *[1] * (len(bs) + 1))
    z = torch.cat([x0, w], -1) if free_x0 else w
    zc = z + a * dz
    x0c, wc = (zc[..., :n], zc[..., n:]) if free_x0 else (x0.expand(len(alphas), *bs, n), zc)
    cc, xc, uc = model.cost(x0c, wc)
    better = (cc < c) & ok & torch.isfinite(cc)
    take = better.any(0)
    first = torch.where(take, better.to(torch.int64).argmax(0), 0)

    def pick(v: Tensor, old: Tensor) -> Tensor:
        idx = first.reshape(1, *bs, *[1] * (v.dim() - 1 - len(bs))).expand(1, *v.shape[1:])
        chosen = torch.gather(v, 0, idx)[0]
        return torch.where(take.reshape(take.shape + (1,) * (chosen.dim() - take.dim())), chosen, old)

    return take, first, pick(x0c, x0), pick(wc, w), pick(xc, x), pick(uc, u), pick(cc, c)


@torch.no_grad()
def ilqr_lifted(problem: ILQRProblem, Psi: Tensor | None = None, *, x0_weight: Tensor | None = None,
                w_init: Tensor | None = None, max_iter: int = 100, tol: float | None = None,
                line_search_steps: int = 10, mu_init: float = 0.0, mu_max: float = 1e10
                ) -> LiftedILQRSolution:
    """Batch iLQR (Algorithm 4) in ``z = [x_0; w]`` with ``u = Ψ w`` (module docstring).

    Args:
        problem: an :class:`~controllers.ilqr.ILQRProblem` without control limits (any dynamics and cost).
        Psi: ``(T m, K)`` or ``(*B, T m, K)`` control primitives (time-major stacking ``u = [u_0; ...]``);
            ``None``: the identity (every control free, Algorithm 4).
        x0_weight: ``(n,)`` or ``(*B, n)`` non-negative weights ``w̄`` of ``Σ w̄_i (x_0,i - x̄_0,i)²``: the
            initial state is optimized too (Eq. 109-110); ``None``: ``x_0 = problem.x0`` fixed.
        w_init: ``(*B, K)`` initial weights (zeros by default).
        max_iter, tol: iterations at most, and the certificate's relative gradient tolerance (default
            ``1e-8`` in float64, ``1e-4`` in float32).
        line_search_steps: step sizes ``1, ½, ..., 2^-(steps-1)`` tried at once per iteration.
        mu_init, mu_max: Levenberg-Marquardt damping ``μ I`` of the step: it starts at ``mu_init``, grows
            ×10 (from at least 1e-6) after a failed line search and shrinks ×10 after a full step; past
            ``mu_max`` the element stops with ``LINE_SEARCH_FAILED``.
    """
    _check(problem, Psi, x0_weight, w_init, max_iter, tol, line_search_steps, mu_init)
    T, n, m = problem.T, problem.n, problem.m
    dtype, device = problem.dtype, problem.device
    kw = dict(dtype=dtype, device=device)
    identity = Psi is None
    if identity:
        Psi = torch.eye(T * m, **kw)
    try:
        bs = torch.broadcast_shapes(problem.batch_shape, Psi.shape[:-2],
                                    () if x0_weight is None else x0_weight.shape[:-1],
                                    () if w_init is None else w_init.shape[:-1])
    except RuntimeError as e:
        raise ValueError(f"ilqr_lifted: the batch dims of problem {tuple(problem.batch_shape)}, 'Psi', "
                         f"'x0_weight' and 'w_init' do not broadcast ({e})") from None
    K = Psi.shape[-1]
    if tol is None:
        tol = 1e-4 if dtype in (torch.float32, torch.float16, torch.bfloat16) else 1e-8
    xbar = problem.x0.expand(*bs, n)
    bad = ~torch.isfinite(xbar).all(-1)
    if not torch.isfinite(Psi).all():
        bad = bad | ~torch.isfinite(Psi).all(-1).all(-1).expand(bs)
    if w_init is not None:
        bad = bad | ~torch.isfinite(w_init).all(-1).expand(bs)
    xbar = torch.where(bad[..., None], torch.zeros((), **kw), xbar)
    if Psi.dim() > 2:  # a batched Ψ: zero the failed elements' (a shared one stays unbatched)
        Psi = torch.where(bad[..., None, None], torch.zeros((), **kw), Psi)
    model = _Model(problem, Psi, None if x0_weight is None else x0_weight.to(**kw), xbar, bs, identity)
    w = torch.zeros(*bs, K, **kw) if w_init is None else w_init.to(**kw).expand(*bs, K).clone()
    w = torch.where(bad[..., None], torch.zeros((), **kw), w)
    x0 = xbar.clone()
    mu = torch.full(bs, mu_init, **kw)
    c, x, u = model.cost(x0, w)
    history = [c]
    done = bad.clone()
    reason = torch.where(bad, int(Reason.NONFINITE_INPUT), int(Reason.MAX_ITERATIONS)).to(torch.int64)
    # NaN/inf in the cost's data (a target, a batched weight) shows as a non-finite first rollout
    diverged = ~bad & ~torch.isfinite(c)
    reason = torch.where(diverged, int(Reason.DIVERGED), reason)
    bad = bad | diverged
    done = done | diverged
    iters = torch.zeros(bs, dtype=torch.int64, device=device)
    alphas = 0.5 ** torch.arange(line_search_steps, **kw)
    free_x0 = x0_weight is not None
    g, H, scale = model.derivatives(x0, w, x, u)
    for _ in range(max_iter):
        res = _residual(g, scale)
        certified = res <= tol
        reason = torch.where(~done & certified, int(Reason.CONVERGED), reason)
        done = done | certified
        if bool(done.all()):
            break
        dz, ok = _newton_step(g, H, mu, done)
        iters = iters + (~done).to(torch.int64)
        take, first, x0, w, x, u, c = _line_search(model, alphas, dz, ok, x0, w, x, u, c, free_x0)
        full = take & (first == 0)
        grown = torch.where(done, mu, (mu * 10).clamp_min(1e-6))
        mu = torch.where(take, torch.where(full, mu / 10, mu), grown)
        mu = torch.where(mu < 1e-12, torch.zeros((), **kw), mu)
        failed = ~done & (mu > mu_max)
        reason = torch.where(failed, int(Reason.LINE_SEARCH_FAILED), reason)
        done = done | failed
        history.append(c)
        g, H, scale = model.derivatives(x0, w, x, u)
    res = _residual(g, scale)
    certified = (res <= tol) & ~bad
    reason = torch.where(certified, int(Reason.CONVERGED),
                         torch.where(reason == int(Reason.CONVERGED), int(Reason.MAX_ITERATIONS), reason))
    nan = torch.full((), float("nan"), **kw)
    x = torch.where(bad[..., None, None], nan, x)
    u = torch.where(bad[..., None, None], nan, u)
    return LiftedILQRSolution(
        x=x, u=u, w=torch.where(bad[..., None], nan, w), x0=torch.where(bad[..., None], nan, x0),
        cost=torch.where(bad, nan, c), status=SolverStatus(reason == int(Reason.CONVERGED), iters, reason),
        cost_history=torch.stack(history), grad_residual=torch.where(bad, nan, res))


# --------------------------------------------------------------------------------------------------
# feedback gains of a batch solution: least-squares formulation of recursive iLQR (§8.3)
# --------------------------------------------------------------------------------------------------


class LiftedGains(NamedTuple):
    """Result of :func:`lifted_feedback_gains`: the local policy ``u_t = K_t x_t + k_t``.

    Attributes:
        K: ``(*B, T, m, n)`` feedback gains (this package's sign: ``u = K x``; the seed's ``-K_t``).
        k: ``(*B, T, m)`` offsets, ``k_t = û_t - K_t x̂_t + Δû_t`` (``Δû_t``: the Gauss-Newton step at the
            point, Eq. 98, about zero at a converged solution).
        amplification: ``(*B,)`` ``max_t cond₂(P_t)``, the factor by which Eq. 99 amplifies the rounding of
            ``F``: expect a relative error of about ``eps · cond(C) · amplification`` in ``K`` and treat the
            gains as unreliable where ``eps · amplification`` is not small (``eps``: the dtype's epsilon).
    """

    K: Tensor
    k: Tensor
    amplification: Tensor


def _check_gains(problem, solution) -> None:
    fn = "lifted_feedback_gains"
    if not isinstance(problem, ILQRProblem):
        raise TypeError(f"{fn}: argument 'problem' must be an ILQRProblem, got {type(problem).__name__}")
    if not isinstance(solution, LiftedILQRSolution):
        raise TypeError(f"{fn}: argument 'solution' must be a LiftedILQRSolution (from ilqr_lifted), got "
                        f"{type(solution).__name__}")
    if problem.u_lower is not None or problem.u_upper is not None:
        raise ValueError(f"{fn}: problems with control limits are not supported (ilqr_lifted solves none); "
                         "controllers.ilqr.ilqr returns gains of control-limited problems")
    T, n, m = problem.T, problem.n, problem.m
    u, x, w, x0 = solution.u, solution.x, solution.w, solution.x0
    if u.shape[-2:] != (T, m) or x.shape[-2:] != (T + 1, n) or x0.shape[-1:] != (n,):
        raise ValueError(f"{fn}: argument 'solution' must have u (*B, {T}, {m}), x (*B, {T + 1}, {n}) and x0 "
                         f"(*B, {n}) for this problem, got u {tuple(u.shape)}, x {tuple(x.shape)}, x0 "
                         f"{tuple(x0.shape)}")
    if u.dtype != problem.dtype or x.dtype != problem.dtype:
        raise TypeError(f"{fn}: argument 'solution' has dtype {u.dtype}, the problem {problem.dtype}")
    # Ψ = I: w is u itself, bit for bit (a product with the identity is exact); failed (NaN) elements skipped
    uf = u.reshape(*u.shape[:-2], T * m)
    if w.shape[-1] != T * m or not bool(((uf == w) | ~torch.isfinite(uf) | ~torch.isfinite(w)).all()):
        raise ValueError(f"{fn}: argument 'solution' was computed with control primitives Ψ ≠ I (u ≠ w); the "
                         "least-squares gains of §8.3 need every control free: solve with Psi=None")
    same = (x0 == problem.x0) | ~torch.isfinite(x0)
    if not bool(same.all()):
        raise ValueError(f"{fn}: argument 'solution' has an optimized initial state (x0_weight was given: x0 "
                         "differs from problem.x0); the gains are defined for a fixed x0: solve with "
                         "x0_weight=None")


def lifted_feedback_gains(problem: ILQRProblem, solution: LiftedILQRSolution) -> LiftedGains:
    """Feedback gains of a batch iLQR solution by the least-squares formulation of recursive iLQR (§8.3).

    At the point ``(x̂, û)`` of ``solution`` (from :func:`ilqr_lifted` with ``Psi=None`` and ``x0`` fixed),
    the Gauss-Newton model of the cost in the deviations ``(Δx_1, Δu)`` (seed indices: ``x_1`` is our
    ``x_0``) is, with ``Δx = S_x Δx_1 + S_u Δu`` (Appendix A),

        ½ Δuᵀ C Δu + Δuᵀ (c + C_x Δx_1) + ...,   C = S_uᵀ H_xx S_u + 2 S_uᵀ H_ux + H_uu,   c = S_uᵀ g_x + g_u

    (Eq. 85 / 96, ``C_x = S_uᵀ H_xx S_x + H_ux``-terms: the cross block of the same Hessian in
    ``[Δx_1; Δu]``, built by the solver's own model).  Its minimizer is affine in the augmented initial
    deviation ``Δx̃_1 = [Δx_1; 1]``: ``Δu = -F Δx̃_1`` with

        F = C⁻¹ [C_x, c]    (Eq. 97-98 for every ``Δx̃_1``: ``F [0; 1] = C⁻¹ c`` is Eq. 98 itself, and the
                             columns ``C⁻¹ C_x`` answer a basis of initial deviations, as §7.6 does),

    ``F = [F_1; ...; F_{T-1}]`` in ``(m, n+1)`` blocks.  The time-varying augmented gains
    ``K̃_t = [K_t^seed, k_t^seed]`` (Eq. 95) follow by the forward recursion of Eq. 99 on the augmented
    linearization ``Ã_t = [[A_t, 0], [0, 1]]``, ``B̃_t = [B_t; 0]`` (Eq. 76):

        K̃_1 = F_1,  P_1 = I,  P_t = P_{t-1} (Ã_{t-1} - B̃_{t-1} K̃_{t-1})⁻¹,  K̃_t = F_t P_t.

    These are the gains of the Riccati pass of :func:`controllers.ilqr.ilqr` (``method="recursive"``) at the
    same point.

    Accuracy (a property of Eq. 99, not of this implementation): ``F_t = K̃_t Φ_t`` with ``Φ_t = P_t⁻¹`` the
    closed-loop transition from step 1 to ``t``, so recovering ``K̃_t`` divides by ``Φ_t``, whose
    condition number grows along the horizon wherever the closed loop contracts some directions faster
    than others; rounding in ``F`` is amplified by ``cond(P_t)`` (returned as ``amplification``; see also
    :func:`controllers.riccati.ls_recursive_gains`).  Measured against the Riccati gains at the same point
    (float64, relative to ``max |K|``): cookbook manipulator (``r = 10⁻⁶``) ~1e-11 before the first via point
    and ~2e-8 after it; random LQ problems with ``T = 10, n = 4, m = 2`` from 1e-14 to 3e-7, with ``T = 20``
    and a heavy terminal weight O(1) (useless; float32 likewise from ``T ≈ 10``).  For reliable gains use
    the Riccati pass (:func:`controllers.ilqr.ilqr`); this route is the seed's §8.3 construction and a check
    of it.

    Args:
        problem: the :class:`~controllers.ilqr.ILQRProblem` that was solved (no control limits).
        solution: its :class:`LiftedILQRSolution` from :func:`ilqr_lifted` with ``Psi=None`` (``u = w``) and
            ``x0_weight=None`` (``x0 = problem.x0``); a ``ValueError`` otherwise.

    Returns:
        :class:`LiftedGains` ``(K (*B, T, m, n), k (*B, T, m), amplification (*B,))``, in this package's
        convention: the local
        policy is ``u_t = K_t x_t + k_t = û_t + K_t (x_t - x̂_t) + Δû_t`` (Eq. 94 with ``K_t = -K_t^seed``,
        ``Δû_t = -k_t^seed``).  Elements whose solution failed (NaN), whose ``C`` is not positive definite or
        whose closed loop ``Ã - B̃ K̃`` is singular in the working precision get NaN; the others are
        computed as if alone.  Differentiable through the point and the problem's tensors (autograd).
    """
    _check_gains(problem, solution)
    T, n, m = problem.T, problem.n, problem.m
    dtype, device = problem.dtype, problem.device
    kw = dict(dtype=dtype, device=device)
    x, u = solution.x, solution.u
    bs = torch.broadcast_shapes(x.shape[:-2], u.shape[:-2], solution.x0.shape[:-1])
    bad = ~(torch.isfinite(x).flatten(-2).all(-1) & torch.isfinite(u).flatten(-2).all(-1)).expand(bs)
    zero = torch.zeros((), **kw)
    x = torch.where(bad[..., None, None], zero, x)
    u = torch.where(bad[..., None, None], zero, u)
    x0 = x[..., 0, :]
    # the solver's Gauss-Newton model in [Δx_1; Δu]: a zero x0 weight keeps the S_x columns (Eq. 109)
    model = _Model(problem, torch.eye(T * m, **kw), torch.zeros(n, **kw), x0, bs, identity=True)
    g, H, _ = model.derivatives(x0, u.reshape(*bs, T * m), x, u)
    C, Cx, c = H[..., n:, n:], H[..., n:, :n], g[..., n:]
    L, info = torch.linalg.cholesky_ex(C)
    ok = (info == 0) & ~bad & torch.isfinite(C).flatten(-2).all(-1)
    L = torch.where(ok[..., None, None], L, torch.eye(T * m, **kw))
    rhs = torch.where(ok[..., None, None], torch.cat([Cx, c.unsqueeze(-1)], -1), zero)
    F = torch.cholesky_solve(rhs, L).reshape(*bs, T, m, n + 1)  # Eq. 98 for every [Δx_1; 1]
    A, B = trajectory_jacobians(problem.dynamics, x[..., :-1, :], u)
    A = A.movedim(0, -3).expand(*bs, T, n, n)
    B = B.movedim(0, -3).expand(*bs, T, n, m)
    eye = torch.eye(n + 1, **kw)
    last = torch.zeros(n + 1, **kw)
    last[n] = 1
    P = eye.expand(*bs, n + 1, n + 1)
    amp = torch.ones(bs, **kw)
    Kt = [F[..., 0, :, :]]
    for t in range(1, T):  # Eq. 99, augmented: Ã - B̃K̃ = [[A - B K^s, -B k^s], [0, 1]]
        top = torch.cat([A[..., t - 1, :, :], torch.zeros(*bs, n, 1, **kw)], -1)
        top = top - B[..., t - 1, :, :] @ Kt[-1]
        Acl = torch.cat([top, last.expand(*bs, 1, n + 1)], -2)
        sol_t, info = torch.linalg.solve_ex(Acl.mT, P.mT)  # P_t = P_{t-1} Acl⁻¹ ⇔ Aclᵀ P_tᵀ = P_{t-1}ᵀ
        ok = ok & (info == 0) & torch.isfinite(sol_t).flatten(-2).all(-1)
        P = torch.where(ok[..., None, None], sol_t.mT, eye)
        amp = torch.maximum(amp, torch.linalg.cond(P))
        Kt.append(F[..., t, :, :] @ P)
    Ks = torch.stack(Kt, -3)  # (*B, T, m, n+1), the seed's K̃_t
    K = -Ks[..., :n]
    k = u - (K @ x[..., :T, :].unsqueeze(-1)).squeeze(-1) - Ks[..., n]
    nan = torch.full((), float("nan"), **kw)
    return LiftedGains(torch.where(ok[..., None, None, None], K, nan),
                       torch.where(ok[..., None, None], k, nan), torch.where(ok, amp, nan))
