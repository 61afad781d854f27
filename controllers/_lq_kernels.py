"""The LQ kernels (private): assembly of the augmented matrices, the Riccati backward sweep, the
closed-loop forward sweep, and the two together (:func:`solve_core`).

Shared by :mod:`controllers.riccati` (the public LQR/LQT solver) and :mod:`controllers.implicit` (the
forward pass of :class:`~controllers.implicit.LQRFunction` and the closed-loop matrices its backward
pass re-uses); neither imports the other's internals.  Inputs are canonical tensors in the cost
convention of :mod:`controllers.costs` (``xᵀQx + uᵀRu + 2xᵀNu + 2qᵀx + 2rᵀu``) with explicit time dims;
no validation happens here.

The recursion (seed 004 §7.4-7.6). The backward pass works on the *homogeneous* (augmented) state ``x̃ =
[x; 1]`` of seed Eq. 76-78: affine dynamics ``c_t`` and linear cost terms (tracking references, Eq. 77)
ride along in the extra coordinate, so one Riccati recursion on ``(n+1) × (n+1)`` matrices handles LQR,
LQT and affine dynamics at once. With ``z_t = [u_t; x_t; 1]``, ``F̃_t = [[B_t, A_t, c_t], [0, 0, 1]]``
and the stage matrix ``C̃_t = [[R, Nᵀ, r], [N, Q, q], [rᵀ, qᵀ, 0]]`` (cost ``z_tᵀ C̃_t z_t``, the
convention of :mod:`controllers.costs`) each step is::

    H    = C̃_t + F̃_tᵀ Ṽ_{t+1} F̃_t                       (Eq. 73 with the augmented state)
    K̃_t  = -H_uu⁻¹ H_ux̃ = [K_t, k_t]                     (Eq. 74 / 78, here u_t = K_t x_t + k_t)
    Ṽ_t  = H_x̃x̃ + H_x̃u K̃_t                                (Eq. 75, the Schur complement of H_uu)

and ``Ṽ_t = [[P_t, p_t], [p_tᵀ, s_t]]`` is the value function ``x̃ᵀ Ṽ_t x̃``; the optimal cost is
``x̃_0ᵀ Ṽ_0 x̃_0``.  No inverse is formed: ``H_uu⁻¹ H_ux̃`` and the Schur complement come together from
``m`` Gauss-Jordan pivots on ``H`` applied as batched elementwise updates (cheaper than per-matrix
LAPACK calls for small ``m``; positive pivots certify ``H_uu ≻ 0`` per element), and the unrolled path
uses a batched Cholesky factorization.  The forward pass runs the closed loop
``u_t = K̃_t x̃_t``, ``x̃_{t+1} = F̃_t [u_t; x̃_t]`` in place.

Compiled path (``compiled=True`` of :func:`solve_core` and :func:`lin_sweep`): the same recursions written
once as pure functions of time-major tensors whose time loop is a :func:`controllers._compiled.scan`, built
by :func:`controllers._compiled.build` into one program per structure (dynamic batch, cached on disk) —
the Riccati sweep, the closed-loop rollout and the cost in one call (:func:`_solve_program`), and the
linear recursions of the implicit gradient (costates, adjoint sweeps) in another (:func:`lin_sweep`).
Small matrix products there are elementwise products and sums (``_mm``, ``_mv``), which the compiler
fuses into the loop body.  The eager kernels stay the reference; the two agree to round-off.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import torch

from controllers import _compiled

__all__ = ["flat", "assemble", "assemble_dynamics", "assemble_cost", "RiccatiFactors", "backward_pass",
           "backward_pass_graph", "closed_loop", "closed_loop_rollout", "closed_loop_rollout_graph",
           "solve_core", "lin_sweep"]


def flat(x: torch.Tensor | None, bs: torch.Size, k: int) -> torch.Tensor | None:
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


def _bsize(*sizes: int) -> int:
    """The common leading (batch) size of parts that are shared (1) or batched: 0 when any part is an empty
    batch (a shared part then expands to no elements), else the largest."""
    return 0 if 0 in sizes else max(sizes)


def _expand_bt(x: torch.Tensor, b: int, T: int) -> torch.Tensor:
    return x.expand(b, T, *x.shape[2:])


def assemble(A, B, c, Q, R, N, q, r, T: int, bs: torch.Size):
    """Augmented dynamics ``F̃ (bF, TF, n+1, m+n+1)``, stage costs ``C̃ (bC, TC, k, k)`` and the terminal
    value ``Ṽ_T (bV, n+1, n+1)`` from canonical tensors (problem-module shapes, explicit time dims).

    Leading dims are 1 when a quantity is shared by the batch, time dims are 1 when time-invariant.
    Q and R must be symmetric (:class:`~controllers.costs.QuadraticCost` checks it); they are used
    as given, and the implicit gradients are the symmetric ones.
    """
    return (assemble_dynamics(A, B, c, bs),) + assemble_cost(Q, R, N, q, r, T, bs)


def assemble_dynamics(A, B, c, bs: torch.Size) -> torch.Tensor:
    """The dynamics part of :func:`assemble`: ``F̃ = [[B, A, c], [0, 0, 1]]``."""
    n, m = A.shape[-1], B.shape[-1]
    A, B, c = flat(A, bs, 2), flat(B, bs, 2), flat(c, bs, 1)
    bF = _bsize(A.shape[0], B.shape[0], 1 if c is None else c.shape[0])
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
    Q, R, N, q, r = flat(Q, bs, 2), flat(R, bs, 2), flat(N, bs, 2), flat(q, bs, 1), flat(r, bs, 1)
    Qs = _tsel(Q, 0, T)
    qs = None if q is None else _tsel(q, 0, T)
    parts = [Qs, R] + [v for v in (N, qs, r) if v is not None]
    bC = _bsize(*(v.shape[0] for v in parts))
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
    bV = _bsize(QT.shape[0], 1 if qT is None else qT.shape[0])
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
        r = H[:, i:i + 1, :] * inv  # the pivot row, scaled (set directly: no h_ii − 1 cancellation)
        H = torch.where(E[i].bool(), r, H - H[:, :, i:i + 1] * r)
    return H[:, :m, m:], H[:, m:, m:], torch.cat(invs, -1).reshape(H.shape[0], m)


@functools.lru_cache(maxsize=1)
def _fused_eliminate():
    """``torch.compile``'d :func:`_eliminate` (built once; compiled per shape/dtype on first use)."""
    return torch.compile(_eliminate, dynamic=False, fullgraph=True)


def backward_pass(F: torch.Tensor, C: torch.Tensor, VT: torch.Tensor, T: int, Bt: int, m: int,
                  keep_huu: bool = True, fused: bool = False) -> RiccatiFactors:
    """Riccati recursion on the augmented state (module docstring); batch ``Bt``, horizon ``T``.

    No autograd graph (use :func:`backward_pass_graph` for that).  ``H_uu⁻¹ H_ux̃`` and the Schur complement
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
                # rows j ≠ i: H_j − H_ji r; row i: r itself.  (Subtracting (H_ii − 1) r from row i instead
                # loses the 1 once H_ii ≳ 1/ε: a cost scaled by 1e16 gave gains 17 % off.)
                H.addcmul_(H[:, :, i:i + 1].clone(), r, value=-1.0)
                H[:, i:i + 1, :] = r
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


def closed_loop_rollout(F: torch.Tensor, Kt: torch.Tensor, x0t: torch.Tensor, T: int
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


def closed_loop_rollout_graph(F: torch.Tensor, Kt: torch.Tensor, x0t: torch.Tensor, T: int
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """Same as :func:`closed_loop_rollout` without in-place writes (for autograd through the recursion)."""
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


def backward_pass_graph(F, C, VT, T: int, Bt: int, m: int) -> RiccatiFactors:
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


def solve_core(A, B, c, Q, R, N, q, r, x0, T: int, bs: torch.Size, graph: bool = False,
                keep_huu: bool = False, fused: bool = False, stage=None, compiled: bool = False):
    """Solve the canonical LQ problem; returns ``(x, u, J, factors, F)`` flattened to ``(Bt, ...)``.

    ``J`` is the optimal cost without the constant of :meth:`QuadraticCost.canonical`.  ``compiled``: the
    Riccati sweep and the rollout as one compiled program (:func:`_solve_program`; not with ``graph``).
    """
    n, m = A.shape[-1], B.shape[-1]
    Bt = bs.numel()  # 1 for an unbatched problem, 0 for an empty batch
    if stage is None:
        F, C, VT = assemble(A, B, c, Q, R, N, q, r, T, bs)
    else:  # cost part precomputed by the caller (controllers.riccati.prepare)
        F = assemble_dynamics(A, B, c, bs)
        C, VT = stage
    x0f = x0.expand(*bs, n).reshape(Bt, n)
    x0t = torch.cat([x0f, torch.ones(Bt, 1, dtype=x0.dtype, device=x0.device)], -1)
    if compiled and not graph and Bt > 0:
        xt, u, J, fac = _solve_program(F, C, VT, x0t, T, Bt, m, keep_huu)
        return xt[..., :n], u, J, fac, F
    if graph:
        fac = backward_pass_graph(F, C, VT, T, Bt, m)
    else:
        fac = backward_pass(F, C, VT, T, Bt, m, keep_huu, fused)
    xt, u = (closed_loop_rollout_graph if graph else closed_loop_rollout)(F, fac.Kt, x0t, T)
    J = (x0t.unsqueeze(-2) @ fac.V[:, 0] @ x0t.unsqueeze(-1)).reshape(Bt)
    return xt[..., :n], u, J, fac, F


# --------------------------------------------------------------------------------------------------
# compiled path: the same recursions as programs (module docstring)
# --------------------------------------------------------------------------------------------------


def _mv(M: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """``M v`` for tiny ``M (..., a, b)``, ``v (..., b)`` as a product and a sum (fused when compiled)."""
    return (M * v.unsqueeze(-2)).sum(-1)


def _mm(X: torch.Tensor, Y: torch.Tensor) -> torch.Tensor:
    """``X Y`` for tiny ``X (..., a, b)``, ``Y (..., b, c)`` as a product and a sum (fused when compiled)."""
    return (X.unsqueeze(-1) * Y.unsqueeze(-3)).sum(-2)


def _riccati_step(m: int):
    """One step of :func:`backward_pass`, out of place: ``H = C̃ + F̃ᵀṼF̃`` and ``m`` Gauss-Jordan pivots;
    outputs ``(K̃ = -H_uu⁻¹H_ux̃, H_uu, Ṽ, reciprocal pivots)``."""

    def step(t, carry, xs):
        (V,) = carry
        Ft, Ct = xs
        H = Ct + _mm(Ft.mT, _mm(V, Ft))
        Huu = H[..., :m, :m]
        k = H.shape[-1]
        rows = torch.arange(k, device=H.device).unsqueeze(-1)  # (k, 1): a constant of the program
        invs = []
        for i in range(m):
            inv = torch.reciprocal(H[..., i:i + 1, i:i + 1])
            invs.append(inv[..., 0, 0])
            r = H[..., i:i + 1, :] * inv  # the pivot row, scaled (as backward_pass: no h_ii − 1 cancellation)
            H = torch.where(rows == i, r, H - H[..., :, i:i + 1] * r)
        V = H[..., m:, m:].contiguous()  # a loop carry keeps its layout from step to step
        return (V,), (-H[..., :m, m:], Huu, V, torch.stack(invs, -1))

    return step


def _solve_sweeps(T: int, m: int, F, C, VT, x0t):
    """The pure LQ solve (batch first, ``F (Bt, TF, n+1, k)``, ``C (Bt, TC, k, k)``, ``VT (Bt, n+1, n+1)``,
    ``x0t (Bt, n+1)``): ``(K̃ (Bt, T, m, n+1), H_uu (Bt, T, m, m), Ṽ (Bt, T+1, n+1, n+1), pivots (Bt, T, m),
    x̃ (Bt, T+1, n+1), u (Bt, T, m), J (Bt,))``."""
    # time-major copies: a loop input that is a view of another input specializes the batch in the trace
    Ftm, Ctm = F.movedim(1, 0).contiguous(), C.movedim(1, 0).contiguous()
    (V0,), (Kt, Huu, V, inv) = _compiled.scan(_riccati_step(m), (VT,), (Ftm, Ctm), T, reverse=True)

    def roll(t, carry, xs):
        (x,) = carry
        Kk, Ft = xs
        u = _mv(Kk, x)
        return (_mv(Ft[..., :, m:], x) + _mv(Ft[..., :, :m], u),), (x, u)

    (xT,), (xs, us) = _compiled.scan(roll, (x0t,), (Kt, Ftm), T)
    J = (x0t * _mv(V0, x0t)).sum(-1)
    V = torch.cat([V, VT.unsqueeze(0)], 0)
    x = torch.cat([xs, xT.unsqueeze(0)], 0)
    return (Kt.movedim(0, 1), Huu.movedim(0, 1), V.movedim(0, 1), inv.movedim(0, 1), x.movedim(0, 1),
            us.movedim(0, 1), J)


def _solve_program(F, C, VT, x0t, T: int, Bt: int, m: int, keep_huu: bool):
    """:func:`_solve_sweeps` as a compiled program (shared parts expanded to the batch); returns
    ``(x̃, u, J, RiccatiFactors)`` as :func:`solve_core`'s eager path does."""
    args = tuple(v.expand(Bt, *v.shape[1:]).contiguous() for v in (F, C, VT, x0t))
    prog = _compiled.build("lq_solve", f"T={T};m={m}", lambda *a: _solve_sweeps(T, m, *a), args, (0, 0, 0, 0))
    Kt, Huu, V, inv, xt, u, J = prog(*args)
    ok = (inv > 0).all(-1) & torch.isfinite(inv).all(-1)
    if not keep_huu:
        Huu, V = None, V[:, [0, T]]
    return xt, u, J, RiccatiFactors(Kt=Kt, Huu=Huu, V=V, ok=ok)


def _lin_sweep_pure(reverse: bool, M, a, y0):
    """``y`` of the linear recursion over ``T`` steps (batch first: ``M (Bt, TM, n, n)``, ``a (Bt, T, n)``,
    ``y0 (Bt, n)``): reverse ``y_T = y0``, ``y_t = a_t + M_t y_{t+1}``; forward ``y_0 = y0``,
    ``y_{t+1} = a_t + M_t y_t``.  Returns ``(Bt, T+1, n)``."""
    T = a.shape[1]

    def step(t, carry, xs):
        (y,) = carry
        Mt, at = xs
        return (at + _mv(Mt, y),), (y,)

    xs = (M.movedim(1, 0).contiguous(), a.movedim(1, 0).contiguous())  # as in _solve_sweeps
    (yl,), (ys,) = _compiled.scan(step, (y0,), xs, T, reverse=reverse)
    # ys[t] is the carry a step received: y_{t+1} in reverse, y_t forward; yl the last one made
    ys, yl = ys.movedim(0, 1), yl.unsqueeze(1)
    return torch.cat([yl, ys], 1) if reverse else torch.cat([ys, yl], 1)


def lin_sweep(M: torch.Tensor, a: torch.Tensor, y0: torch.Tensor, reverse: bool, compiled: bool = False
              ) -> torch.Tensor:
    """The linear recursion of :func:`_lin_sweep_pure` (``M`` with a time dim of 1 or ``T``, batch ``Bt`` or
    1): eagerly a loop of batched products, or (``compiled``) one program call.  Reverse: ``y (Bt, T+1, n)``
    with ``y_T = y0`` last (costates); forward: ``y_0 = y0`` first (a closed-loop trajectory)."""
    Bt, T = a.shape[0], a.shape[1]
    if compiled and Bt > 0:
        args = tuple(v.expand(Bt, *v.shape[1:]).contiguous() for v in (M, a, y0))
        prog = _compiled.build("lq_lin_sweep", f"reverse={reverse}",
                               lambda *x: (_lin_sweep_pure(reverse, *x),), args, (0, 0, 0))
        return prog(*args)[0]
    Mc = M.expand(Bt, *M.shape[1:]) if M.shape[1] > 1 else M.expand(Bt, T, *M.shape[2:])
    out = torch.empty(Bt, T + 1, y0.shape[-1], 1, dtype=a.dtype, device=a.device)
    cur = y0.expand(Bt, y0.shape[-1]).unsqueeze(-1)
    ac = a.unsqueeze(-1)
    first = T if reverse else 0
    out[:, first] = cur
    for t in (range(T - 1, -1, -1) if reverse else range(T)):
        cur = torch.baddbmm(ac[:, t], Mc[:, t], cur)
        out[:, t if reverse else t + 1] = cur
    return out.squeeze(-1)
