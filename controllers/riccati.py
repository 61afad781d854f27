"""Recursive Riccati solution of batched LQR/LQT problems (seed 004 §7.4-7.6).

The backward pass works on the *homogeneous* (augmented) state ``x̃ = [x; 1]`` of seed Eq. 76-78:
affine dynamics ``c_t`` and linear cost terms (tracking references, Eq. 77) ride along in the extra
coordinate, so one Riccati recursion on ``(n+1) × (n+1)`` matrices handles LQR, LQT and affine
dynamics at once.  With ``z_t = [u_t; x_t; 1]``, ``F̃_t = [[B_t, A_t, c_t], [0, 0, 1]]`` and the stage
matrix ``C̃_t = [[R, Nᵀ, r], [N, Q, q], [rᵀ, qᵀ, 0]]`` (cost ``z_tᵀ C̃_t z_t``, :mod:`controllers.problem`
conventions) each step is::

    H    = C̃_t + F̃_tᵀ Ṽ_{t+1} F̃_t                       (Eq. 73 with the augmented state)
    K̃_t  = -H_uu⁻¹ H_ux̃ = [K_t, k_t]                     (Eq. 74 / 78, here u_t = K_t x_t + k_t)
    Ṽ_t  = H_x̃x̃ + H_x̃u K̃_t                                (Eq. 75, the Schur complement of H_uu)

and ``Ṽ_t = [[P_t, p_t], [p_tᵀ, s_t]]`` is the value function ``x̃ᵀ Ṽ_t x̃``; the optimal cost is
``x̃_0ᵀ Ṽ_0 x̃_0``.  No inverse is formed: ``H_uu⁻¹ H_ux̃`` and the Schur complement come together from
``m`` Gauss-Jordan pivots on ``H`` applied as batched elementwise updates (cheaper than per-matrix
LAPACK calls for small ``m``; positive pivots certify ``H_uu ≻ 0`` per element), and the unrolled path
uses a batched Cholesky factorization.  The forward pass runs the closed loop
``u_t = K̃_t x̃_t``, ``x̃_{t+1} = F̃_t [u_t; x̃_t]`` in place.

Also here: the explicit augmented-state construction of seed Eq. 76-77 (:func:`augmented_lqt`) and the
least-squares recursive form Eq. 79-81 (:func:`ls_recursive_gains`), which accepts a full (non block
diagonal) trajectory precision matrix and control primitives ``u = Ψ w``.

Entry point: :func:`solve` (an :class:`~controllers.problem.LQProblem` in, an
:class:`~controllers.problem.LQSolution` out), with ``grad="implicit"`` (default, the backward pass of
:mod:`controllers.implicit`), ``grad="unrolled"`` (autograd through the recursion) or ``grad="none"``;
:func:`lqr` is the same on plain canonical tensors (used by iLQR).
"""

from __future__ import annotations

import enum
import functools
from dataclasses import dataclass
from typing import NamedTuple

import torch

from controllers.problem import (
    LinearDynamics,
    LQProblem,
    LQSolution,
    QuadraticCost,
    Reason,
    SolverStatus,
    enum_arg,
)

__all__ = [
    "GradMode",
    "solve",
    "lqr",
    "augmented_lqt",
    "AugmentedLQT",
    "ls_recursive_gains",
    "LSGains",
    "RiccatiFactors",
    "assemble",
    "assemble_cost",
    "assemble_dynamics",
    "backward_pass",
    "closed_loop",
]


class GradMode(str, enum.Enum):
    """How gradients flow through :func:`solve`."""

    IMPLICIT = "implicit"  #: one extra backward Riccati pass on the KKT conditions (O(T) memory)
    UNROLLED = "unrolled"  #: autograd through every step of the recursion
    NONE = "none"  #: no graph at all (inference)


# --------------------------------------------------------------------------------------------------
# assembly of the augmented matrices
# --------------------------------------------------------------------------------------------------


def _flat(x: torch.Tensor | None, bs: torch.Size, k: int) -> torch.Tensor | None:
    """Timed tensor ``(*b, Tx, *trail)`` (``k`` trailing dims) -> ``(Bt or 1, Tx, *trail)``."""
    if x is None:
        return None
    d = x.dim() - k - 1
    b = x.shape[:d]
    if b.numel() == 1:
        return x.reshape(1, *x.shape[d:])
    return x.expand(*bs, *x.shape[d:]).reshape(-1, *x.shape[d:])


def _tsel(x: torch.Tensor, lo: int, hi: int) -> torch.Tensor:
    """Time slice ``[lo:hi]`` of ``(b, Tx, ...)`` (a time dim of 1 broadcasts)."""
    return x if x.shape[1] == 1 else x[:, lo:hi]


def _expand_bt(x: torch.Tensor, b: int, T: int) -> torch.Tensor:
    return x.expand(b, T, *x.shape[2:])


def assemble(A, B, c, Q, R, N, q, r, T: int, bs: torch.Size):
    """Augmented dynamics ``F̃ (bF, TF, n+1, m+n+1)``, stage costs ``C̃ (bC, TC, k, k)`` and the terminal
    value ``Ṽ_T (bV, n+1, n+1)`` from canonical tensors (problem-module shapes, explicit time dims).

    Leading dims are 1 when a quantity is shared by the batch, time dims are 1 when time-invariant.
    Q and R must be symmetric (:class:`~controllers.problem.QuadraticCost` checks it); they are used
    as given, and the implicit gradients are the symmetric ones.
    """
    return (assemble_dynamics(A, B, c, bs),) + assemble_cost(Q, R, N, q, r, T, bs)


def assemble_dynamics(A, B, c, bs: torch.Size) -> torch.Tensor:
    """The dynamics part of :func:`assemble`: ``F̃ = [[B, A, c], [0, 0, 1]]``."""
    n, m = A.shape[-1], B.shape[-1]
    A, B, c = _flat(A, bs, 2), _flat(B, bs, 2), _flat(c, bs, 1)
    bF = max(A.shape[0], B.shape[0], 1 if c is None else c.shape[0])
    TF = max(A.shape[1], B.shape[1], 1 if c is None else c.shape[1])
    dt, dev = A.dtype, A.device
    top = [_expand_bt(B, bF, TF), _expand_bt(A, bF, TF)]
    top.append(torch.zeros(bF, TF, n, 1, dtype=dt, device=dev) if c is None
               else _expand_bt(c, bF, TF).unsqueeze(-1))
    bottom = torch.zeros(bF, TF, 1, m + n + 1, dtype=dt, device=dev)
    bottom[..., 0, -1] = 1.0
    F = torch.cat([torch.cat(top, -1), bottom], -2)
    return F


def assemble_cost(Q, R, N, q, r, T: int, bs: torch.Size) -> tuple[torch.Tensor, torch.Tensor]:
    """The cost part of :func:`assemble`: ``(C̃, Ṽ_T)``."""
    n, m = Q.shape[-1], R.shape[-1]
    dt, dev = Q.dtype, Q.device
    Q, R, N, q, r = _flat(Q, bs, 2), _flat(R, bs, 2), _flat(N, bs, 2), _flat(q, bs, 1), _flat(r, bs, 1)
    Qs = _tsel(Q, 0, T)
    qs = None if q is None else _tsel(q, 0, T)
    parts = [Qs, R] + [v for v in (N, qs, r) if v is not None]
    bC = max(v.shape[0] for v in parts)
    TC = max(v.shape[1] for v in parts)
    z = lambda *sh: torch.zeros(bC, TC, *sh, dtype=dt, device=dev)
    Rr, Qq = _expand_bt(R, bC, TC), _expand_bt(Qs, bC, TC)
    Nn = z(n, m) if N is None else _expand_bt(N, bC, TC)
    qq = z(n) if qs is None else _expand_bt(qs, bC, TC)
    rr = z(m) if r is None else _expand_bt(r, bC, TC)
    C = torch.cat([
        torch.cat([Rr, Nn.mT, rr.unsqueeze(-1)], -1),
        torch.cat([Nn, Qq, qq.unsqueeze(-1)], -1),
        torch.cat([rr.unsqueeze(-2), qq.unsqueeze(-2), z(1, 1)], -1),
    ], -2)

    QT = Q[:, -1]
    qT = None if q is None else q[:, -1]
    bV = max(QT.shape[0], 1 if qT is None else qT.shape[0])
    VT = torch.zeros(bV, n + 1, n + 1, dtype=dt, device=dev)
    VT[:, :n, :n] = QT
    if qT is not None:
        VT[:, :n, n] = qT
        VT[:, n, :n] = qT
    return C, VT


# --------------------------------------------------------------------------------------------------
# backward and forward passes
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class RiccatiFactors:
    """What the backward pass leaves behind (all ``(Bt, T, ...)``): gains ``Kt = [K, k] (m, n+1)``,
    ``Huu (m, m)``, value matrices ``V (Bt, T+1, n+1, n+1)`` and ``ok (Bt, T)`` (False where ``H_uu``
    is not positive definite).  Without ``keep_huu`` (no gradient wanted) ``Huu`` is None and ``V``
    holds only ``[Ṽ_0, Ṽ_T]``."""

    Kt: torch.Tensor
    Huu: torch.Tensor | None
    V: torch.Tensor
    ok: torch.Tensor


def _eliminate(H: torch.Tensor, E: torch.Tensor, m: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``m`` Gauss-Jordan pivots on ``H (Bt, k, k)``: returns ``(H_uu⁻¹ H_ux̃, Schur complement Ṽ,
    reciprocal pivots (Bt, m))`` (out of place, so that ``torch.compile`` can fuse it)."""
    invs = []
    for i in range(m):
        inv = torch.reciprocal(H[:, i:i + 1, i:i + 1])
        invs.append(inv)
        H = H - (H[:, :, i:i + 1] - E[i]) * (H[:, i:i + 1, :] * inv)
    return H[:, :m, m:], H[:, m:, m:], torch.cat(invs, -1).reshape(H.shape[0], m)


@functools.lru_cache(maxsize=1)
def _fused_eliminate():
    """``torch.compile``'d :func:`_eliminate` (built once; compiled per shape/dtype on first use)."""
    return torch.compile(_eliminate, dynamic=False, fullgraph=True)


def backward_pass(F: torch.Tensor, C: torch.Tensor, VT: torch.Tensor, T: int, Bt: int, m: int,
                  keep_huu: bool = True, fused: bool = False) -> RiccatiFactors:
    """Riccati recursion on the augmented state (module docstring); batch ``Bt``, horizon ``T``.

    No autograd graph (use :func:`_backward_graph` for that).  ``H_uu⁻¹ H_ux̃`` and the Schur complement
    ``Ṽ_t`` come from ``m`` Gauss-Jordan pivots on ``H`` done as batched elementwise updates: for tiny
    ``m`` this is several times cheaper than per-matrix LAPACK calls, and the pivots of a symmetric
    positive-definite ``H_uu`` are positive, so no pivoting is needed; a non-positive pivot marks the
    element as failed (``ok``).  With ``fused=True`` the ``4 m`` elementwise pivot updates of a step run
    as one ``torch.compile``'d kernel (compiled on first use for each shape and dtype).
    """
    n1 = VT.shape[-1]
    k = C.shape[-1]
    dt, dev = VT.dtype, VT.device
    shared_F = F.shape[0] == 1
    tvF, tvC = F.shape[1] > 1, C.shape[1] > 1
    E = torch.eye(k, dtype=dt, device=dev)[:m].unsqueeze(-1)  # unit columns e_i (k, 1)
    V = VT.expand(Bt, n1, n1).contiguous() if fused else VT.expand(Bt, n1, n1)
    F0 = F[0, 0] if shared_F else F[:, 0]
    if C.shape[0] != Bt:
        C = C.expand(Bt, *C.shape[1:])
    C0 = C[:, 0]
    elim = _fused_eliminate() if fused else None
    # H is a fresh tensor at every step: the value matrices are kept as views of it (gradient mode only)
    Vs, Huus = [V], []
    pivbuf = torch.empty(Bt, T, m, 1, 1, dtype=dt, device=dev)
    Kt = torch.empty(Bt, T, m, n1, dtype=dt, device=dev)
    for t in range(T - 1, -1, -1):
        Ft = (F[0, t] if shared_F else F[:, t]) if tvF else F0
        Ct = C[:, t] if tvC else C0
        if shared_F:
            H = torch.matmul(torch.matmul(V, Ft).mT, Ft).mT.add_(Ct)
        else:
            H = torch.baddbmm(Ct, Ft.mT, torch.bmm(V, Ft))
        if keep_huu:
            Huus.append(H[:, :m, :m].clone())
        if fused:
            S, V, inv = elim(H, E, m)
            pivbuf[:, t] = inv.reshape(Bt, m, 1, 1)
            torch.neg(S, out=Kt[:, t])
        else:
            for i in range(m):
                inv = torch.reciprocal(H[:, i:i + 1, i:i + 1], out=pivbuf[:, t, i])
                r = H[:, i:i + 1, :] * inv
                H.addcmul_(H[:, :, i:i + 1] - E[i], r, value=-1.0)
            V = H[:, m:, m:]
            torch.neg(H[:, :m, m:], out=Kt[:, t])
        if keep_huu:
            Vs.append(V)
    Vs.reverse()
    piv = pivbuf.reshape(Bt, T, m)
    ok = (piv > 0).all(-1) & torch.isfinite(piv).all(-1)
    Vst = torch.stack(Vs, 1) if keep_huu else torch.stack([V, VT.expand(Bt, n1, n1)], 1)
    Huu = torch.stack(Huus[::-1], 1) if keep_huu else None
    return RiccatiFactors(Kt=Kt, Huu=Huu, V=Vst, ok=ok)


def closed_loop(F: torch.Tensor, Kt: torch.Tensor, m: int) -> torch.Tensor:
    """``Φ̃_t = F̃_x̃ + F̃_u K̃_t`` for all steps at once: ``(Bt, T, n+1, n+1)`` (a sum of ``m`` outer
    products, elementwise: cheaper than a batched matmul of many tiny matrices)."""
    Phi = F[..., :, m:]
    for j in range(m):
        Phi = Phi + F[..., :, j:j + 1] * Kt[..., j:j + 1, :]
    return Phi


def _forward(F: torch.Tensor, Kt: torch.Tensor, x0t: torch.Tensor, T: int
             ) -> tuple[torch.Tensor, torch.Tensor]:
    """Closed-loop rollout ``u_t = K̃_t x̃_t``, ``x̃_{t+1} = F̃_x̃ x̃_t + F̃_u u_t``: ``(x̃ (Bt, T+1, n+1),
    u (Bt, T, m))``, written into preallocated buffers (no graph)."""
    Bt, m, n1 = Kt.shape[0], Kt.shape[-2], Kt.shape[-1]
    shared = F.shape[0] == 1
    tv = F.shape[1] > 1
    if not shared:
        # z_t = [u_t; x̃_t] in one buffer: two products per step, written in place
        Z = torch.empty(Bt, T + 1, m + n1, 1, dtype=Kt.dtype, device=Kt.device)
        Z[:, 0, m:] = x0t.unsqueeze(-1)
        for t in range(T):
            torch.bmm(Kt[:, t], Z[:, t, m:], out=Z[:, t, :m])
            torch.bmm(F[:, t if tv else 0], Z[:, t], out=Z[:, t + 1, m:])
        Z = Z.squeeze(-1)
        return Z[:, :, m:], Z[:, :T, :m]
    xs = torch.empty(Bt, T + 1, n1, 1, dtype=Kt.dtype, device=Kt.device)
    us = torch.empty(Bt, T, m, 1, dtype=Kt.dtype, device=Kt.device)
    x = x0t.unsqueeze(-1)
    xs[:, 0] = x
    for t in range(T):
        Ft = F[0, t if tv else 0]
        u = torch.bmm(Kt[:, t], x)
        x = torch.matmul(Ft[:, m:], x) + torch.matmul(Ft[:, :m], u)
        us[:, t] = u
        xs[:, t + 1] = x
    return xs.squeeze(-1), us.squeeze(-1)


def _forward_graph(F: torch.Tensor, Kt: torch.Tensor, x0t: torch.Tensor, T: int
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """Same as :func:`_forward` without in-place writes (for autograd through the recursion)."""
    x = x0t.unsqueeze(-1)
    xs, us = [x], []
    m = Kt.shape[-2]
    for t in range(T):
        Ft = F[:, t if F.shape[1] > 1 else 0]
        u = torch.matmul(Kt[:, t], x)
        x = torch.matmul(Ft[..., :, m:], x) + torch.matmul(Ft[..., :, :m], u)
        xs.append(x)
        us.append(u)
    return torch.stack(xs, 1).squeeze(-1), torch.stack(us, 1).squeeze(-1)


def _backward_graph(F, C, VT, T: int, Bt: int, m: int) -> RiccatiFactors:
    """:func:`backward_pass` without in-place writes (autograd-friendly, for ``grad='unrolled'``)."""
    n1 = VT.shape[-1]
    V = VT.expand(Bt, n1, n1)
    Ks, Hs, Vs, infos = [], [], [V], []
    for t in range(T - 1, -1, -1):
        Ft = F[:, t] if F.shape[1] > 1 else F[:, 0]
        Ct = C[:, t] if C.shape[1] > 1 else C[:, 0]
        H = torch.matmul(Ft.mT, torch.matmul(V, Ft)) + Ct
        L, info = torch.linalg.cholesky_ex(H[:, :m, :m])
        S = torch.cholesky_solve(H[:, :m, m:], L)
        V = H[:, m:, m:] - torch.matmul(H[:, m:, :m], S)
        V = 0.5 * (V + V.mT)
        Ks.append(-S)
        Hs.append(H[:, :m, :m])
        Vs.append(V)
        infos.append(info)
    Ks.reverse()
    Hs.reverse()
    Vs.reverse()
    infos.reverse()
    return RiccatiFactors(Kt=torch.stack(Ks, 1), Huu=torch.stack(Hs, 1), V=torch.stack(Vs, 1),
                          ok=torch.stack(infos, 1) == 0)


def _solve_core(A, B, c, Q, R, N, q, r, x0, T: int, bs: torch.Size, graph: bool = False,
                keep_huu: bool = False, fused: bool = False, stage=None):
    """Solve the canonical LQ problem; returns ``(x, u, J, factors, F)`` flattened to ``(Bt, ...)``.

    ``J`` is the optimal cost without the constant of :meth:`QuadraticCost.canonical`.
    """
    n, m = A.shape[-1], B.shape[-1]
    Bt = max(bs.numel(), 1)
    if stage is None:
        F, C, VT = assemble(A, B, c, Q, R, N, q, r, T, bs)
    else:  # cost part precomputed (and cached on the cost object by solve())
        F = assemble_dynamics(A, B, c, bs)
        C, VT = stage
    if graph:
        fac = _backward_graph(F, C, VT, T, Bt, m)
    else:
        fac = backward_pass(F, C, VT, T, Bt, m, keep_huu, fused)
    x0f = x0.expand(*bs, n).reshape(Bt, n)
    x0t = torch.cat([x0f, torch.ones(Bt, 1, dtype=x0.dtype, device=x0.device)], -1)
    xt, u = (_forward_graph if graph else _forward)(F, fac.Kt, x0t, T)
    J = (x0t.unsqueeze(-2) @ fac.V[:, 0] @ x0t.unsqueeze(-1)).reshape(Bt)
    return xt[..., :n], u, J, fac, F


# --------------------------------------------------------------------------------------------------
# public API
# --------------------------------------------------------------------------------------------------


def lqr(A: torch.Tensor, B: torch.Tensor, c: torch.Tensor | None, Q: torch.Tensor, R: torch.Tensor,
        N: torch.Tensor | None, q: torch.Tensor | None, r: torch.Tensor | None, x0: torch.Tensor,
        T: int, grad: GradMode | str = GradMode.IMPLICIT, fused: bool = False, _stage=None):
    """Functional core on canonical tensors (no validation): returns ``x (*B, T+1, n)``,
    ``u (*B, T, m)``, ``K (*B, T, m, n)``, ``k (*B, T, m)``, ``J (*B,)`` and ``ok (*B, T)`` (False
    where ``H_uu`` was not positive definite).

    Shapes as in :mod:`controllers.problem` with explicit time dims; the cost is
    ``Σ xᵀQx + uᵀRu + 2xᵀNu + 2qᵀx + 2rᵀu`` (no constant).  With ``grad='implicit'`` the gradients of
    ``x``, ``u`` and ``J`` come from :class:`controllers.implicit.LQRFunction`; ``K``, ``k`` are then
    returned without a graph (use ``grad='unrolled'`` to differentiate the gains).  ``fused=True``
    runs each step's pivot updates as one ``torch.compile``'d kernel (not with ``grad='unrolled'``).
    """
    grad = enum_arg(GradMode, grad, "grad", "lqr")
    if fused and grad is GradMode.UNROLLED:
        raise ValueError("lqr: fused=True needs grad='implicit' or 'none' (no graph through the kernel)")
    n, m = A.shape[-1], B.shape[-1]
    tr = [(A, 3), (B, 3), (c, 2), (Q, 3), (R, 3), (N, 3), (q, 2), (r, 2)]
    bs = torch.broadcast_shapes(x0.shape[:-1], *[v.shape[:v.dim() - k] for v, k in tr if v is not None])
    if grad is GradMode.IMPLICIT:
        from controllers.implicit import lqr_implicit

        x, u, J, K, k, info = lqr_implicit(A, B, c, Q, R, N, q, r, x0, T, bs, fused)
    else:
        ctx = torch.enable_grad() if grad is GradMode.UNROLLED else torch.no_grad()
        with ctx:
            x, u, J, fac, _ = _solve_core(A, B, c, Q, R, N, q, r, x0, T, bs,
                                          graph=grad is GradMode.UNROLLED, fused=fused,
                                          stage=_stage if grad is GradMode.NONE else None)
        K, k, info = fac.Kt[..., :n], fac.Kt[..., n], fac.ok
    return (x.reshape(*bs, T + 1, n), u.reshape(*bs, T, m), K.reshape(*bs, T, m, n), k.reshape(*bs, T, m),
            J.reshape(bs), info.reshape(*bs, T))


def solve(problem: LQProblem, grad: GradMode | str = GradMode.IMPLICIT, check: bool = True,
          fused: bool = False) -> LQSolution:
    """Solve a batched LQR/LQT problem with the Riccati recursion.

    Args:
        problem: the :class:`LQProblem`.
        grad: :class:`GradMode` — ``"implicit"`` (default), ``"unrolled"`` or ``"none"``.
        check: compute the per-element input status (non-finite data, Q/R definiteness when batched;
            the cost's part is cached on the cost object).
        fused: run each Riccati step's pivot updates as one ``torch.compile``'d kernel (compiled on
            first use per shape/dtype, seconds; then faster).  Needs a working ``torch.compile``.

    With ``grad="none"`` the expansion of the cost (references, stage matrices) is cached on the cost
    object, so re-solving with the same cost and new ``x0`` or dynamics (MPC) skips it.

    Returns:
        :class:`LQSolution` with ``x``, ``u``, gains ``K``/``k`` (``u_t = K_t x_t + k_t``), the optimal
        cost (references included) and per-element status: ``SINGULAR_QUU`` where ``H_uu`` was not
        positive definite at some step, input failures from :meth:`LQProblem.input_status`.  A failed
        element never changes the others (every operation is per element).
    """
    if not isinstance(problem, LQProblem):
        raise TypeError(f"solve: argument 'problem' must be an LQProblem, got {type(problem).__name__}")
    T = problem.T
    grad = enum_arg(GradMode, grad, "grad", "solve")
    d, cost = problem.dynamics, problem.cost
    stage = None
    if grad is GradMode.NONE:
        # the cost's expansion and stage matrices depend on the cost alone: cache them on the cost
        key = ("stage", T, tuple(problem.batch_shape), cost.versions())
        if key not in cost._cache:
            for old in [k for k in cost._cache if k[0] == "stage" and k[1:3] == key[1:3]]:
                del cost._cache[old]  # stale: the cost's data changed in place
            with torch.no_grad():
                cc = cost.canonical(T)
                cost._cache[key] = (cc, assemble_cost(cc.Q, cc.R, cc.N, cc.q, cc.r, T, problem.batch_shape))
        else:
            cc, (C, VT) = cost._cache[key]
            if C.shape[0] > 1 and C.shape[1] > 1 and C.stride(0) != C.shape[-1] ** 2:
                # re-used: store the stage matrices time-major (C[:, t] then one contiguous block)
                with torch.no_grad():
                    C = C.transpose(0, 1).contiguous().transpose(0, 1)
                cost._cache[key] = (cc, (C, VT))
        cc, stage = cost._cache[key]
    else:
        cc = cost.canonical(T)
    x, u, K, k, J, info = lqr(d.A, d.B, d.c, cc.Q, cc.R, cc.N, cc.q, cc.r, problem.x0, T, grad, fused,
                              _stage=stage)
    J = J + cc.const
    reason = (~info.all(-1)).to(torch.int64) * int(Reason.SINGULAR_QUU)
    if check:
        inp = problem.input_status().expand(reason.shape)
        reason = torch.where(inp != 0, inp, reason)
    return LQSolution(x=x, u=u, K=K, k=k, cost=J, status=SolverStatus.from_reason(reason, 1))


# --------------------------------------------------------------------------------------------------
# seed formulations kept for comparison: explicit augmented state (Eq. 76-78), LS recursive (Eq. 79-81)
# --------------------------------------------------------------------------------------------------


def _least_psd_constant(W: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(vᵀ W⁺ v, v ∈ range(W))`` for PSD ``W (..., k, k)``: ``[[W, v], [vᵀ, s]] ⪰ 0`` iff ``v`` is in the
    range of ``W`` and ``s ≥ vᵀ W⁺ v``."""
    y = (torch.linalg.pinv(W, hermitian=True) @ v.unsqueeze(-1)).squeeze(-1)
    res = ((W @ y.unsqueeze(-1)).squeeze(-1) - v).abs().amax(-1)
    scale = (1 + v.abs().amax(-1)) * (1 + W.abs().flatten(-2).amax(-1))
    return (v * y).sum(-1), res <= 1e3 * torch.finfo(W.dtype).eps * scale


class AugmentedLQT(NamedTuple):
    """An LQT problem recast as regulation on ``x̃ = [x; 1]`` (:func:`augmented_lqt`)."""

    dynamics: LinearDynamics  #: ``Ã = [[A, c], [0, 1]]``, ``B̃ = [B; 0]``
    cost: QuadraticCost  #: PSD ``Q̃_t`` (and cross term ``Ñ_t = [N_t; r_tᵀ]``), no references
    x0: torch.Tensor  #: ``x̃_0 = [x_0; 1]``
    offset: torch.Tensor  #: ``(*B,)``: original cost = augmented cost + offset (≤ 0; 0 for pure tracking)


def augmented_lqt(problem: LQProblem) -> AugmentedLQT:
    """Recast an LQT problem as an LQR problem on ``x̃ = [x; 1]`` (seed Eq. 76-77).

    Returns dynamics ``Ã = [[A, c], [0, 1]]``, ``B̃ = [B; 0]``, a regulation cost with
    ``Q̃_t = [[Q_t, q_t'], [q_t'ᵀ, s_t]]`` where ``q_t' = q_t - Q_t μ_t - N_t ν_t`` folds the references
    and linear terms in (``u_ref`` and ``r`` go into the cross term ``Ñ_t = [N_t; r_t'ᵀ]``), ``x̃_0`` and
    an offset.  Each step keeps its own constant (``μ_tᵀQ_tμ_t`` of Eq. 77 and the like), so that for
    pure tracking ``Q̃_t = [I, -μ_t]ᵀ Q_t [I, -μ_t] ⪰ 0`` (Eq. 77) and the stage matrix of ``[x̃; u]`` is
    positive semi-definite.  Linear terms ``q``, ``r`` make a stage cost negative somewhere (its
    minimum is ``-[q; r]ᵀ W⁺ [q; r]`` with ``W = [[Q, N], [Nᵀ, R]]``); there the constant is raised to
    the least value that keeps the stage matrix PSD and the difference is returned in ``offset``
    (constants change no minimizer).  Solving the result with zero references gives the LQT solution,
    ``K̃_t = [K_t, k_t]`` as in Eq. 78, and cost + offset = the LQT cost.  A stage with a linear term
    outside the range of a singular ``W`` has no PSD form: its constant is left as is.
    """
    T = problem.T
    d = problem.dynamics.expand_time(T)
    n, m = problem.n, problem.m
    c = problem.cost
    cc = c.canonical(T)
    bs = problem.batch_shape
    dt, dev = problem.dtype, problem.device
    kw = dict(dtype=dt, device=dev)
    At = torch.zeros(*d.A.shape[:-2], n + 1, n + 1, **kw)
    At[..., :n, :n] = d.A
    At[..., n, n] = 1.0
    if d.c is not None:
        At = At.expand(*torch.broadcast_shapes(At.shape[:-2], d.c.shape[:-1]), n + 1, n + 1).clone()
        At[..., :n, n] = d.c
    Bt = torch.cat([d.B, torch.zeros(*d.B.shape[:-2], 1, m, **kw)], -2)

    def full(v, steps, *trail):
        return torch.zeros(*bs, steps, *trail, **kw) if v is None else v.expand(*bs, steps, *trail)

    Q, R = full(c.Q, T + 1, n, n), full(c.R, T, m, m)
    N = full(c.N, T, n, m)
    mu, nu = full(c.x_ref, T + 1, n), full(c.u_ref, T, m)
    q, r = full(c.q, T + 1, n), full(c.r, T, m)
    qc, rc = full(cc.q, T + 1, n), full(cc.r, T, m)
    dot = lambda a, b: (a * b).sum(-1)  # noqa: E731
    mv = lambda M, v: (M @ v.unsqueeze(-1)).squeeze(-1)  # noqa: E731
    # per-step constants of the expanded cost (their sum is the canonical constant)
    const = dot(mu, mv(Q, mu)) - 2 * dot(q, mu)
    cu = dot(nu, mv(R, nu)) - 2 * dot(r, nu) + 2 * dot(mu[..., :T, :], mv(N, nu))
    const = torch.cat([const[..., :T] + cu, const[..., T:]], -1)
    # least constant that keeps the stage matrix of [x; 1; u] PSD: vᵀ W⁺ v
    W = torch.cat([torch.cat([Q[..., :T, :, :], N], -1), torch.cat([N.mT, R], -1)], -2)
    smin, inrange = _least_psd_constant(W, torch.cat([qc[..., :T, :], rc], -1))
    sminT, inrangeT = _least_psd_constant(Q[..., T:, :, :], qc[..., T:, :])
    smin, inrange = torch.cat([smin, sminT], -1), torch.cat([inrange, inrangeT], -1)
    s = torch.where(inrange & (smin > const), smin, const)
    Qt = torch.zeros(*bs, T + 1, n + 1, n + 1, **kw)
    Qt[..., :n, :n] = Q
    Qt[..., :n, n] = qc
    Qt[..., n, :n] = qc
    Qt[..., n, n] = s
    Nt = None
    if c.N is not None or cc.r is not None:
        Nt = torch.zeros(*bs, T, n + 1, m, **kw)
        Nt[..., :n, :] = N
        Nt[..., n, :] = rc
    x0t = torch.cat([problem.x0.expand(*bs, n), torch.ones(*bs, 1, **kw)], -1)
    offset = (const - s).sum(-1)
    return AugmentedLQT(LinearDynamics(At, Bt), QuadraticCost(Qt, R, N=Nt, check=False), x0t, offset)


class LSGains(NamedTuple):
    """Result of :func:`ls_recursive_gains`."""

    K: torch.Tensor  #: ``(*B, T, m, n)`` feedback gains, ``u_t = K_t x_t`` (NaN where ``status`` failed)
    F: torch.Tensor  #: ``(*B, T m, n)`` open-loop map, ``u = -F x_0``
    status: SolverStatus  #: per element: ``SINGULAR_QUU`` where the normal matrix or a closed loop failed


def ls_recursive_gains(Sx: torch.Tensor, Su: torch.Tensor, Qbig: torch.Tensor, Rbig: torch.Tensor,
                       A: torch.Tensor, B: torch.Tensor, Psi: torch.Tensor | None = None) -> LSGains:
    """Least-squares formulation of recursive LQR (seed §7.6, Eq. 79-81), batched.

    Computes ``F = (Ψᵀ S_uᵀ Q S_u Ψ + Ψᵀ R Ψ)⁻¹ Ψᵀ S_uᵀ Q S_x`` (Eq. 80, with control primitives §7.7;
    ``Ψ = I`` when omitted) and rebuilds the time-varying feedback gains by ``P_1 = I``,
    ``K_1 = F_1``, ``P_t = P_{t-1} (A_{t-1} - B_{t-1} K_{t-1})⁻¹``, ``K_t = F_t P_t`` (Eq. 81).

    Accuracy: Eq. 81 inverts the closed loop ``A - B K`` at every step, and a well-damped closed loop is
    close to singular in the directions it contracts most, so errors grow along the horizon.  An
    ill-conditioned ``R`` makes that worse (cheap control directions give near-deadbeat gains): on a
    random problem (T = 10, n = 4, m = 2, float64) the closed-loop controls differ from the Riccati
    optimum by 3e-10 at cond(R) = 1, 8e-3 at 1e2, 3e-2 at 1e4 and 0.13 at 1e8 (float32: 1e-2 already at
    cond(R) = 1).  Use :func:`solve` for gains; this form is kept for the full (non block-diagonal)
    precisions and control primitives it accepts.

    Args:
        Sx: ``(*B, (T+1) n, n)``, Su: ``(*B, (T+1) n, T m)`` transfer matrices (:mod:`controllers.lifted`).
        Qbig: full trajectory precision ``(*B, (T+1) n, (T+1) n)`` (may couple time steps), Rbig
            ``(*B, T m, T m)``.
        A, B: ``(*B, T, n, n)``, ``(*B, T, n, m)`` (needed for Eq. 81).
        Psi: optional control primitives ``(*B, T m, K)``.

    Returns:
        :class:`LSGains` ``(K, F, status)``: gains in this package's sign convention (``u_t = K_t x_t``;
        the seed's ``u = -K x``), the open-loop map, and a per-element status: ``SINGULAR_QUU`` (outputs
        NaN) where the normal matrix is not positive definite or a closed loop ``A - B K`` is singular
        in the working precision, instead of an exception for the whole batch.
    """
    T = A.shape[-3]
    n, m = A.shape[-1], B.shape[-1]
    SuP = Su if Psi is None else Su @ Psi
    Ru = Rbig if Psi is None else Psi.mT @ Rbig @ Psi
    Hm = SuP.mT @ Qbig @ SuP + Ru
    Lh, info = torch.linalg.cholesky_ex(0.5 * (Hm + Hm.mT))
    ok = info == 0
    eye_h = torch.eye(Hm.shape[-1], dtype=Hm.dtype, device=Hm.device)
    Lh = torch.where(ok[..., None, None], Lh, eye_h)
    W = torch.cholesky_solve(SuP.mT @ Qbig @ Sx, Lh)
    Fm = W if Psi is None else Psi @ W  # (*B, T m, n)
    Ft = Fm.reshape(*Fm.shape[:-2], T, m, n)
    bs = torch.broadcast_shapes(Ft.shape[:-3], A.shape[:-3], B.shape[:-3])
    ok = ok.expand(bs)
    eye = torch.eye(n, dtype=A.dtype, device=A.device)
    P = eye.expand(*bs, n, n)
    Ks = []
    for t in range(T):
        if t > 0:
            Acl = A[..., t - 1, :, :] - B[..., t - 1, :, :] @ Ks[-1]
            # P_t = P_{t-1} Acl⁻¹  ⇔  Aclᵀ P_tᵀ = P_{t-1}ᵀ  (a singular Acl fails its element only)
            good = torch.linalg.solve_ex(Acl.mT, eye.expand(*Acl.shape))[1] == 0
            ok = ok & good & torch.isfinite(Acl).flatten(-2).all(-1)
            Acl = torch.where(ok[..., None, None], Acl, eye)
            P = torch.linalg.solve(Acl.mT, P.mT).mT
        Ks.append(Ft[..., t, :, :] @ P)
    K = -torch.stack(Ks, -3)
    nan = torch.full((), torch.nan, dtype=K.dtype, device=K.device)
    K = torch.where(ok[..., None, None, None], K, nan)
    Fm = torch.where(ok.reshape(*ok.shape, *([1] * (Fm.dim() - ok.dim()))), Fm, nan)
    reason = torch.where(ok, int(Reason.CONVERGED), int(Reason.SINGULAR_QUU))
    return LSGains(K, Fm, SolverStatus.from_reason(reason))
