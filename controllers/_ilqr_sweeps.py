"""The time sweeps of iLQR (private): backward Riccati pass, costates of the certificate, candidate rollouts.

Each sweep is one pure function over time-major tensors whose recursion is a
:func:`controllers._compiled.scan`: run eagerly it is the reference; with ``compiled=True`` the same
function is built once per structure by :func:`controllers._compiled.build` (a ``while_loop`` program,
dynamic batch) and called with the batch flattened — one call instead of ``T`` Python steps of 10-30 small
kernels each.  A sweep the compiler cannot take (three or more limited controls: the inner box QP has
data-dependent exits; a time-varying system; a system whose parameters are batched or require grad) runs
eagerly; the numbers are the same up to round-off.  Two limited controls run in a program where the
outcome can be checked and the pass repeated eagerly (:func:`can_compile_iteration`, ``try_two``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from controllers import _compiled
from controllers.boxqp import box_qp, box_qp_two, masked_hessian, small_spd_solve
from torchlie._batch import broadcast_shapes

__all__ = ["Backward", "backward_pass", "kkt_parts", "forward_candidates", "can_compile_backward",
           "can_compile_iteration", "run_flat"]


@dataclass
class Backward:
    K: Tensor  # (T, *B, m, n)
    k: Tensor  # (T, *B, m)
    free: Tensor  # (T, *B, m)
    ok: Tensor  # (*B,)
    dV1: Tensor  # (*B,)  Σ kᵀ Q_u
    dV2: Tensor  # (*B,)  Σ ½ kᵀ Q_uu k
    curv: Tensor  # (*B,)  max_t max_i |(Q_uu,t)_ii| (unregularized): the curvature of the certificate


def _factor(H: Tensor) -> tuple[Tensor, Tensor]:
    """Cholesky factor of SPD ``H (*B, m, m)`` and an ``ok (*B,)`` mask; failed factors are identity."""
    m = H.shape[-1]
    L, info = torch.linalg.cholesky_ex(H)
    ok = info == 0
    return torch.where(ok[..., None, None], L, torch.eye(m, dtype=H.dtype, device=H.device)), ok


# --------------------------------------------------------------------------------------------------
# backward pass
# --------------------------------------------------------------------------------------------------


def _stage_matrices(A, B, gx, gu, Hxx, Hux, Huu, bs):
    """``(F̃ (T, *B, n+1, n+m+1), H̃ (T, *B, n+m+1, n+m+1), Ṽ_T (*B, n+1, n+1))`` for all steps at once."""
    T, n, m = A.shape[0], A.shape[-1], B.shape[-1]
    kw = dict(dtype=A.dtype, device=A.device)
    lead = broadcast_shapes(A.shape[:-2], B.shape[:-2])
    Ft = torch.cat([A.expand(*lead, n, n), B.expand(*lead, n, m), torch.zeros(*lead, n, 1, **kw)], -1)
    last = torch.cat([torch.zeros(n + m, **kw), torch.ones(1, **kw)])
    F = torch.cat([Ft, last.expand(*lead, 1, n + m + 1)], -2)
    full = (T, *bs)
    Hxx_t = Hxx[:T].expand(*full, n, n)
    Hxu = torch.zeros(*full, n, m, **kw) if Hux is None else Hux.mT.expand(*full, n, m)
    gxt, gut = gx[:T].expand(*full, n), gu.expand(*full, m)
    H = torch.cat([
        torch.cat([Hxx_t, Hxu, gxt.unsqueeze(-1)], -1),
        torch.cat([Hxu.mT, Huu.expand(*full, m, m), gut.unsqueeze(-1)], -1),
        torch.cat([gxt.unsqueeze(-2), gut.unsqueeze(-2), torch.zeros(*full, 1, 1, **kw)], -1),
    ], -2)
    gT = gx[T].expand(*bs, n)
    V = torch.cat([torch.cat([Hxx[T].expand(*bs, n, n), gT.unsqueeze(-1)], -1),
                   torch.cat([gT.unsqueeze(-2), torch.zeros(*bs, 1, 1, **kw)], -1)], -2)
    return F, H, V


def _riccati_step(n: int, m: int, bounded: bool):
    """One step of the backward pass (Eq. 91-93): ``Q̃ = H̃ + F̃ᵀṼF̃``; the feedforward solves the box QP on
    ``Q_uu + μI`` (a clip for one control), rows of ``K`` of clamped controls are zero, and with
    ``M̃ = [[I, 0], [K, k], [0, 1]]`` the value is ``Ṽ = M̃ᵀQ̃M̃`` (re-symmetrized)."""

    def step(t, carry, xs):
        (V,) = carry
        Fk, Hk, mu = xs[0], xs[1], xs[2]
        Q = Hk + Fk.mT @ (V @ Fk)
        Quu, Qu, Qux = Q[..., n:n + m, n:n + m], Q[..., n:n + m, -1], Q[..., n:n + m, :n]
        kw = dict(dtype=Q.dtype, device=Q.device)
        if m == 1:  # one control: the box QP is a clip and the factorization a division
            h = Quu[..., 0] + mu.unsqueeze(-1)  # (*B, 1)
            kraw = -Qu / h
            if bounded:
                lo, hi = xs[3], xs[4]
                k = torch.clamp(kraw, lo, hi)
                free = (kraw >= lo) & (kraw <= hi)
            else:
                k, free = kraw, torch.ones_like(kraw, dtype=torch.bool)
            K = Qux * (-free.to(Q.dtype) / h).unsqueeze(-1)
            good = (h[..., 0] > 0) & torch.isfinite(k[..., 0])
        else:
            Qreg = Quu + mu[..., None, None] * torch.eye(m, **kw)
            if not bounded:
                L, good = _factor(Qreg)
                k = -torch.cholesky_solve(Qu.unsqueeze(-1), L).squeeze(-1)
                K = -torch.cholesky_solve(Qux, L)
                free = torch.ones_like(k, dtype=torch.bool)
            else:
                if m == 2 and _compiled.tracing():
                    # in a program: box_qp's own first step (the enumerated minimizer, certified) without
                    # host reads or LAPACK calls; an element it leaves uncertified fails the step, and the
                    # iteration program hands the whole iteration to the eager path (controllers._ilqr_step)
                    kb, conv, clamped = box_qp_two(Qreg, Qu, xs[3], xs[4])
                    free = ~clamped
                    rows = free.to(Q.dtype).unsqueeze(-1) * Qux  # (*B, m, n): one right-hand side a column
                    Kt, okL = small_spd_solve(masked_hessian(Qreg, free).unsqueeze(-3), rows.mT)
                    K, okL = -Kt.mT, okL.squeeze(-1)
                else:
                    res = box_qp(Qreg, Qu, xs[3], xs[4], x0=xs[5] if len(xs) > 5 else None, check=False)
                    kb, conv, free = res.x, res.converged, res.free
                    L, okL = _factor(masked_hessian(Qreg, free))
                    K = -torch.cholesky_solve(free.to(Q.dtype).unsqueeze(-1) * Qux, L)
                # an uncertified inner QP (no descent, iteration cap) is a failed step: μ grows
                good = conv & okL
                k = torch.where(good.unsqueeze(-1), kb, torch.zeros((), **kw))
        bs = Q.shape[:-2]
        top = torch.eye(n, n + 1, **kw).expand(*bs, n, n + 1)
        bot = torch.eye(n + 1, **kw)[n:].expand(*bs, 1, n + 1)
        M = torch.cat([top, torch.cat([K, k.unsqueeze(-1)], -1), bot], -2)  # (*B, n+m+1, n+1)
        V = M.mT @ Q @ M
        V = 0.5 * (V + V.mT)
        return (V,), (K, k, free, good, Qu, Quu)

    return step


def _backward_sweep(n: int, m: int, bounded: bool, F, H, VT, mu, *limits):
    """The backward pass over ``T`` steps (pure; ``limits`` = ``(lo, hi[, k_warm])`` time-major when
    ``bounded``): ``(K, k, free, ok, dV1, dV2, curv)``."""
    T = H.shape[0]
    # μ is shared by every step: a time dim of 1 (no closure over a tensor: the traced loop takes its inputs)
    # two limited controls: each step's box QP (9 faces and their certificate) makes a large loop body,
    # whose copies multiply the build time: one step per loop iteration (CarParking expert, B = 16: its
    # programs built in 321 s against 400-700 s with 4 steps, at 213-223 ms per closed-loop step against 162)
    unroll = 1 if (bounded and m == 2) else None
    _, (K, k, free, good, Qu, Quu) = _compiled.scan(_riccati_step(n, m, bounded), (VT,),
                                                    (F, H, mu.unsqueeze(0), *limits), T, reverse=True,
                                                    unroll=unroll)
    dV1 = (k * Qu).sum((0, -1))
    dV2 = 0.5 * (k * (Quu @ k.unsqueeze(-1)).squeeze(-1)).sum((0, -1))
    curv = Quu.diagonal(dim1=-2, dim2=-1).abs().amax((0, -1))
    return K, k, free, good.all(0), dV1, dV2, curv


def can_compile_backward(m: int, bounded: bool) -> bool:
    """Whether :func:`backward_pass` can run as a program (several limited controls need the box QP)."""
    return m == 1 or not bounded


def can_compile_iteration(m: int, bounded: bool) -> bool:
    """Whether the backward pass can be part of the iteration program: also two limited controls, whose box
    QP it solves as :func:`~controllers.boxqp.box_qp` does in one step where that step certifies (an
    uncertified element fails the pass, and the iteration program's caller reruns it eagerly)."""
    return m <= 2 or not bounded


def backward_pass(A, B, gx, gu, Hxx, Hux, Huu, mu: Tensor, lo, hi, k_warm, bs, compiled: bool = False,
                  try_two: bool = False) -> Backward:
    """Riccati recursion on the local model (time-major inputs, ``lo/hi`` bounds on ``Δu`` or None).

    Homogeneous form (the affine terms ride in an extra coordinate, as in seed Eq. 76-78): with
    ``z̃ = [δx; δu; 1]``, the stage matrix ``H̃_t = [[H_xx, H_xu, g_x], [H_ux, H_uu, g_u], [g_xᵀ, g_uᵀ, 0]]``,
    ``F̃_t = [[A_t, B_t, 0], [0, 0, 1]]`` and the value ``½ x̃ᵀ Ṽ x̃`` (:func:`_riccati_step`).

    ``try_two`` (with ``compiled``): two limited controls run as a program too, whose box QPs are
    :func:`~controllers.boxqp.box_qp`'s first step; where that step leaves an element uncertified (``ok``
    false somewhere: one host read) the pass is run again eagerly.  For a pass that is expected to succeed
    (the gains at the returned point), not for μ's retries.
    """
    n, m = A.shape[-1], B.shape[-1]
    F, H, VT = _stage_matrices(A, B, gx, gu, Hxx, Hux, Huu, bs)
    bounded = lo is not None
    limits = () if not bounded else (lo, hi) if (k_warm is None or m == 1) else (lo, hi, k_warm)
    plain = can_compile_backward(m, bounded)
    if compiled and bs.numel() > 0 and (plain or (try_two and m == 2)):
        lims = limits[:2]  # a warm start only matters to the eager box QP's iterations
        out = run_flat("ilqr_backward", f"n={n};m={m};bounded={bounded}",
                       lambda *a: _backward_sweep(n, m, bounded, *a), (F, H, VT, mu, *lims),
                       ((1, 2), (1, 2), (0, 2), (0, 0)) + ((1, 1),) * len(lims), bs, (1, 1, 1, 0, 0, 0, 0))
        if plain or bool(out[3].all()):
            return Backward(*out)
    return Backward(*_backward_sweep(n, m, bounded, F, H, VT, mu, *limits))


# --------------------------------------------------------------------------------------------------
# certificate: costates and the projected gradient
# --------------------------------------------------------------------------------------------------


def _kkt_sweep(bounded: bool, A, B, gx, gu, u, *limits):
    T = u.shape[0]

    def step(t, carry, xs):
        (lam,) = carry
        At, Bt, gxt, gut = xs
        Btl = (Bt.mT @ lam.unsqueeze(-1)).squeeze(-1)
        lam = gxt + (At.mT @ lam.unsqueeze(-1)).squeeze(-1)
        return (lam,), (gut + Btl, gut.abs() + Btl.abs())

    _, (g, scale) = _compiled.scan(step, (gx[T],), (A, B, gx[:T], gu), T, reverse=True)
    pg = u - torch.minimum(torch.maximum(u - g, limits[0]), limits[1]) if bounded else g
    return pg.abs().amax(dim=(0, -1)), scale.amax(dim=(0, -1))


def kkt_parts(A: Tensor, B: Tensor, gx: Tensor, gu: Tensor, u: Tensor, lo: Tensor | None, hi: Tensor | None,
              bs: torch.Size, compiled: bool = False) -> tuple[Tensor, Tensor]:
    """``(max |pg|, max of the gradient's terms)`` per element ``(*B,)``, time-major inputs.

    ``∇_{u_t} J = ∂l/∂u_t + B_tᵀ λ_{t+1}`` with the costates ``λ_T = ∂l/∂x_T``,
    ``λ_t = ∂l/∂x_t + A_tᵀ λ_{t+1}``; ``pg = u − clip(u − ∇_u J, lo, hi)`` (zero exactly at a KKT point of
    the box-constrained problem) and the terms ``|∂l/∂u_t| + |B_tᵀ λ_{t+1}|`` that cancel in it at a free
    optimum.  A non-finite element gives NaN (never certified).
    """
    bounded = lo is not None
    limits = (lo, hi) if bounded else ()
    if compiled and bs.numel() > 0:
        return run_flat("ilqr_kkt", f"bounded={bounded}", lambda *a: _kkt_sweep(bounded, *a),
                         (A, B, gx, gu, u, *limits), ((1, 2), (1, 2)) + ((1, 1),) * (3 + len(limits)), bs,
                         (0, 0))
    return _kkt_sweep(bounded, A, B, gx, gu, u, *limits)


# --------------------------------------------------------------------------------------------------
# forward pass: every step size at once
# --------------------------------------------------------------------------------------------------


def _forward_sweep(step_fn, S: int, bounded: bool, feedback: bool, x0, base, *rest):
    """Rollouts ``u_t = clip(base_t + K_t x_t)``, ``x_{t+1} = step(x_t, u_t, t)`` for ``S`` step sizes:
    ``base (T, S, *B, m)``, ``x0 (*B, n)``; returns ``(x (S, *B, T+1, n), u (S, *B, T, m))``."""
    T = base.shape[0]
    K = rest[0] if feedback else None
    lims = rest[1:] if feedback else rest

    def step(t, carry, xs):
        (xt,) = carry
        ut = xs[0]
        if feedback:
            ut = ut + (xs[1] @ xt.unsqueeze(-1)).squeeze(-1)
        if bounded:
            ut = torch.minimum(torch.maximum(ut, xs[-2]), xs[-1])
        return (step_fn(xt, ut, t),), (xt, ut)

    xs_in = (base,) + (() if K is None else (K.unsqueeze(1),)) + tuple(v.unsqueeze(1) for v in lims)
    (xT,), (xs, us) = _compiled.scan(step, (x0.expand(S, *x0.shape),), xs_in, T)
    return torch.cat([xs, xT.unsqueeze(0)]).movedim(0, -2), us.movedim(0, -2)


def forward_candidates(dyn, x0, x, u, K, k, alphas, lo, hi, bs, compiled_key: str | None = None):
    """Roll out every step size at once: ``u_t = clip(û_t + α k_t + K_t (x_t - x̂_t))`` (Eq. 101).

    ``alphas (S,)``; returns ``x (S, *B, T+1, n)``, ``u (S, *B, T, m)``.  ``K=None``: open loop (Eq. 100).
    ``compiled_key``: the dynamics' fingerprint (:func:`controllers._compiled.fingerprint`) to run as a
    program (time-invariant dynamics only), or None.
    """
    S, T = alphas.shape[0], u.shape[-2]
    a = alphas.view(S, *([1] * u.dim()))
    ff = u if K is None else u - (K.movedim(0, -3) @ x[..., :T, :].unsqueeze(-1)).squeeze(-1)
    base = (ff.unsqueeze(0) + a * k.movedim(0, -2)).movedim(-2, 0)  # (T, S, *B, m): û - K x̂ + α k
    bounded = lo is not None
    lims = () if not bounded else (lo.expand(*bs, T, lo.shape[-1]).movedim(-2, 0),
                                   hi.expand(*bs, T, hi.shape[-1]).movedim(-2, 0))
    rest = (() if K is None else (K,)) + lims
    x0 = x0.expand(*bs, x0.shape[-1])
    feedback = K is not None
    if compiled_key is not None and bs.numel() > 0:
        def fn(*a):
            return _forward_sweep(dyn.step, S, bounded, feedback, *a)
        return run_flat("ilqr_forward", f"{compiled_key};S={S};bounded={bounded};feedback={feedback}", fn,
                         (x0, base, *rest),
                         ((0, 1), (2, 1)) + (((1, 2),) if feedback else ()) + ((1, 1),) * len(lims), bs,
                         (1, 1))
    return _forward_sweep(dyn.step, S, bounded, feedback, x0, base, *rest)


# --------------------------------------------------------------------------------------------------
# calling a program with the batch flattened
# --------------------------------------------------------------------------------------------------


def run_flat(name: str, key: str, fn, args: tuple, layout: tuple, bs: torch.Size, out_lead: tuple):
    """Call the program of ``fn`` on ``args`` laid out as ``(lead dims, *B or fewer, trailing dims)``
    (``layout[i] = (lead, trail)``; ``None``: shared by the batch, passed as it is): the batch is expanded and
    flattened to one dim for the call, and restored in the outputs (whose batch dim is at ``out_lead[j]``;
    ``None``: an output without one).  Where no program can be built, ``fn(*args)``."""
    nb, Bf = len(bs), math.prod(bs)
    flat, dims = [], []
    for x, lay in zip(args, layout):
        if lay is None:
            flat.append(x.contiguous())
            dims.append(None)
            continue
        lead, trail = lay
        have = x.dim() - lead - trail
        if have == 1 and nb == 1:  # already one batch dim: no reshaping
            flat.append(x.expand(*x.shape[:lead], Bf, *x.shape[lead + 1:]).contiguous())
            dims.append(lead)
            continue
        x = x.reshape((*x.shape[:lead], *([1] * (nb - have)), *x.shape[lead:]))
        x = x.expand((*x.shape[:lead], *bs, *x.shape[lead + nb:]))
        flat.append(x.reshape((*x.shape[:lead], Bf, *x.shape[lead + nb:])).contiguous())
        dims.append(lead)
    prog = _compiled.build(name, key, fn, tuple(flat), dims)
    if prog is None:  # not buildable here (warned once): the same function, eagerly
        return fn(*args)
    outs = prog(*flat)
    return tuple(o if d is None else o.reshape((*o.shape[:d], *bs, *o.shape[d + 1:]))
                 for o, d in zip(outs, out_lead))
