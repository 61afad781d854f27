"""Batch least-squares LQT with transfer matrices (seed 004 §7, Eq. 59-66, Appendix A).

The whole trajectory is written as ``x = S_x x_0 + S_u u + s_c`` (Eq. 61 / Eq. 188, with ``s_c`` the
response to the drift ``c_t``) and the quadratic cost becomes a least-squares problem in the stacked
controls, solved in one batched Cholesky solve (Eq. 62).  This is the simplest formulation to trust, so
it doubles as the test oracle of the recursive solvers.  Variants from the seed:

* the control-space covariance ``Σ_u = (S_uᵀ Q S_u + R)⁻¹`` (Eq. 63),
* optimization of the initial state together with the controls (Eq. 65),
* full (non block-diagonal) precision matrices over the whole trajectory, e.g. the smoothness cost of
  §7.2 (:func:`smoothness_precision`) or precisions coupling several time steps,
* control primitives ``u = Ψ w`` (§7.3, Eq. 66; :func:`control_primitives` with :mod:`controllers.basis`).

Cost conventions are those of :mod:`controllers.costs` (no factor 1/2, as in Eq. 59).  Stacked vectors
are time-major: ``x = [x_0; x_1; ...; x_T]`` ``((T+1) n)``, ``u = [u_0; ...; u_{T-1}]`` ``(T m)``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import NamedTuple

import torch

from controllers.problem import LQProblem, Reason, SolverStatus
from torchlie._batch import broadcast_shapes

__all__ = [
    "transfer_matrices",
    "block_diag_time",
    "smoothness_precision",
    "control_primitives",
    "LiftedQuadratic",
    "lifted_quadratic",
    "LiftedSolution",
    "solve_lifted",
]


def transfer_matrices(A: torch.Tensor, B: torch.Tensor, c: torch.Tensor | None = None, T: int | None = None
                      ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """Transfer matrices ``S_x (*B, (T+1) n, n)``, ``S_u (*B, (T+1) n, T m)`` and drift response
    ``s_c (*B, (T+1) n)``.

    Appendix A (Eq. 188): block row ``t`` of ``S_x`` is ``A_{t-1} ... A_0``; block ``(t, s)`` of ``S_u``
    is ``A_{t-1} ... A_{s+1} B_s`` for ``s < t``.  ``A (*B, T|1, n, n)``, ``B (*B, T|1, n, m)``,
    ``c (*B, T|1, n)`` (time dims of 1 broadcast; then ``T`` must be given).  ``T = 0`` (no step) gives
    ``S_x = I``, an empty ``S_u (*B, n, 0)`` and ``s_c = 0``.
    """
    if T is None:
        T = max(A.shape[-3], B.shape[-3], 1 if c is None else c.shape[-2])
    if isinstance(T, bool) or not isinstance(T, int) or T < 0:
        raise ValueError(f"transfer_matrices: argument 'T' must be an int >= 0, got {T!r}")
    n, m = A.shape[-1], B.shape[-1]
    bs = broadcast_shapes(A.shape[:-3], B.shape[:-3], *([] if c is None else [c.shape[:-2]]))
    dt, dev = A.dtype, A.device
    if A.shape[-3] == 1 and B.shape[-3] == 1 and (c is None or c.shape[-2] == 1):
        return _transfer_time_invariant(A[..., 0, :, :], B[..., 0, :, :], None if c is None else c[..., 0, :],
                                        T, bs)
    At = lambda t: A[..., t if A.shape[-3] > 1 else 0, :, :]
    Bt = lambda t: B[..., t if B.shape[-3] > 1 else 0, :, :]
    rows_x = [torch.eye(n, dtype=dt, device=dev).expand(*bs, n, n)]
    rows_c = None if c is None else [torch.zeros(*bs, n, dtype=dt, device=dev)]
    Su = torch.zeros(*bs, (T + 1) * n, T * m, dtype=dt, device=dev)
    nz = None  # the non-zero part [A_{t-1} S_{t-1,0..t-2}, B_{t-1}] (n × t m) of block row t of S_u
    for t in range(T):
        a = At(t)
        rows_x.append(a @ rows_x[-1])
        b = Bt(t).expand(*bs, n, m)
        nz = b if nz is None else torch.cat([(a @ nz).expand(*bs, n, t * m), b], -1)
        Su[..., (t + 1) * n:(t + 2) * n, :(t + 1) * m] = nz
        if rows_c is not None:
            ct = c[..., t if c.shape[-2] > 1 else 0, :]
            rows_c.append((a @ rows_c[-1].unsqueeze(-1)).squeeze(-1) + ct)
    Sx = torch.cat(rows_x, -2)
    sc = None if rows_c is None else torch.cat(rows_c, -1)
    return Sx, Su, sc


def _transfer_time_invariant(A: torch.Tensor, B: torch.Tensor, c: torch.Tensor | None, T: int, bs
                              ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """:func:`transfer_matrices` of constant ``A (*B, n, n)``, ``B (*B, n, m)``, ``c (*B, n)``: the powers
    ``A^k`` (``k = 0..T``) by doubling (``log₂ T`` products), then block ``(t, s)`` of ``S_u`` is
    ``A^{t-1-s} B`` (a block-Toeplitz gather) and ``s_c,t = Σ_{k<t} A^k c``."""
    n, m = A.shape[-1], B.shape[-1]
    P = torch.eye(n, dtype=A.dtype, device=A.device).expand(*A.shape[:-2], 1, n, n)
    Ak = A.unsqueeze(-3)  # A^(2^j)
    while P.shape[-3] < T + 1:
        P = torch.cat([P, Ak @ P], -3)
        Ak = Ak @ Ak
    P = P[..., :T + 1, :, :].expand(*bs, T + 1, n, n)
    Sx = P.reshape(*bs, (T + 1) * n, n)
    G = P[..., :T, :, :] @ B.unsqueeze(-3)  # A^k B, k = 0..T-1
    t = torch.arange(T + 1, device=A.device)[:, None]
    s = torch.arange(T, device=A.device)[None, :]
    blocks = G[..., (t - 1 - s).clamp_min(0), :, :] * (s < t).to(A.dtype)[:, :, None, None]
    Su = blocks.movedim(-3, -2).reshape(*bs, (T + 1) * n, T * m)
    sc = None
    if c is not None:
        Pc = (P[..., :T, :, :] @ c.unsqueeze(-1).unsqueeze(-3)).squeeze(-1)  # A^k c
        Pc = Pc.expand(*bs, T, n)
        sc = torch.cat([Pc.new_zeros(*bs, 1, n), Pc.cumsum(-2)], -2).reshape(*bs, (T + 1) * n)
    return Sx, Su, sc


def _gram_blocks(A: torch.Tensor, B: torch.Tensor, Q: torch.Tensor, Sx: torch.Tensor, Su: torch.Tensor,
                 T: int, with_x: bool, R: torch.Tensor | None = None, N: torch.Tensor | None = None
                 ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
    """``S_uᵀ Q S_u`` (and ``S_uᵀ Q S_x``, ``S_xᵀ Q S_x`` when ``with_x``) for ``Q = blockdiag(Q_t)``, from
    the backward recursion ``P_T = Q_T``, ``P_t = Q_t + A_tᵀ P_{t+1} A_t`` (the sum over ``t' ≥ t`` of the
    state-transition-weighted ``Q_{t'}``).

    Block ``(s, s')`` of ``S_uᵀ Q S_u`` is ``Σ_{t>s'} S_{t,s}ᵀ Q_t S_{t,s'} = S_{s'+1,s}ᵀ P_{s'+1} B_{s'}``
    for ``s ≤ s'``: ``B_{s'}ᵀ P_{s'+1} B_{s'}`` on the diagonal and ``S_{s',s}ᵀ A_{s'}ᵀ P_{s'+1} B_{s'}``
    above it (block row ``s'`` of ``S_u``), so block column ``s'`` costs one ``(T m × n)·(n × m)`` product
    instead of a sum over ``T`` time steps.  Block ``s`` of ``S_uᵀ Q S_x`` is ``B_sᵀ P_{s+1} S_{x,s+1}`` and
    ``S_xᵀ Q S_x = P_0``.  ``R (*B, T|1, m, m)`` and ``N (*B, T|1, n, m)``, when given, are folded in: the
    normal matrix of Eq. 62 ``S_uᵀQS_u + blockdiag(R) + S_uᵀN + NᵀS_u`` with ``N`` stacked as in
    :func:`solve_lifted` (block ``(s, s')``, ``s < s'``, of ``S_uᵀ N`` is ``S_{s',s}ᵀ N_{s'}``), without
    forming ``blockdiag(R)`` or the stacked ``N``.
    """
    n, m = A.shape[-1], B.shape[-1]
    At = lambda t: A[..., t if A.shape[-3] > 1 else 0, :, :]  # noqa: E731
    Bt = lambda t: B[..., t if B.shape[-3] > 1 else 0, :, :]  # noqa: E731
    Qt = lambda t: Q[..., t if Q.shape[-3] > 1 else 0, :, :]  # noqa: E731
    P = Qt(T)
    PBs, Ys, Ds = [None] * T, [None] * T, [None] * T
    for t in range(T - 1, -1, -1):
        b, a = Bt(t), At(t)
        PBs[t] = P @ b  # P_{t+1} B_t
        Ys[t] = a.mT @ PBs[t]
        Ds[t] = b.mT @ PBs[t]
        P = Qt(t) + a.mT @ P @ a
    PB = torch.stack(torch.broadcast_tensors(*PBs), -3)  # (*B, T, n, m)
    Y = torch.stack(torch.broadcast_tensors(*Ys), -3)
    Dg = torch.stack(torch.broadcast_tensors(*Ds), -3)  # (*B, T, m, m)
    if N is not None:
        Y = Y + N
    if R is not None:
        Dg = Dg + R
    rows = Su[..., :T * n, :].unflatten(-2, (T, n))  # block rows 0..T-1 of S_u: (*B, T, n, T m)
    # block column s' above the diagonal: S_{s'}ᵀ Y_{s'} (zero on and below the diagonal)
    M = torch.einsum("...tnr,...tnj->...rtj", rows, Y).contiguous()  # (*B, T m [r], T [s'], m [j])
    bs = torch.broadcast_shapes(M.shape[:-3], Dg.shape[:-3])
    if M.shape[:-3] != bs:
        M = M.expand(*bs, *M.shape[-3:]).clone()
    diag = torch.diagonal(M.unflatten(-3, (T, m)), dim1=-4, dim2=-2)  # (*B, m [i], m [j], T) view
    diag.add_(Dg.permute(*range(Dg.dim() - 3), -2, -1, -3))  # in place on the zero diagonal blocks
    M = M.flatten(-2)  # (*B, T m, T m), block upper triangular
    blk = torch.arange(T, device=M.device).repeat_interleave(m)
    H = torch.where(blk.unsqueeze(-1) > blk, M.mT, M)  # mirror the upper blocks into the lower ones
    if not with_x:
        return H, None, None
    ux = PB.mT @ Sx[..., n:, :].unflatten(-2, (T, n))  # B_sᵀ P_{s+1} S_{x,s+1}: (*B, T, m, n)
    return H, ux.flatten(-3, -2), P


def block_diag_time(M: torch.Tensor, T: int) -> torch.Tensor:
    """``blockdiag(M_0, ..., M_{T-1})`` ``(*B, T r, T s)`` from ``M (*B, T|1, r, s)``."""
    r, s = M.shape[-2:]
    M = M.expand(*M.shape[:-3], T, r, s)
    out = torch.zeros(*M.shape[:-3], T * r, T * s, dtype=M.dtype, device=M.device)
    for t in range(T):
        out[..., t * r:(t + 1) * r, t * s:(t + 1) * s] = M[..., t, :, :]
    return out


def smoothness_precision(T: int, m: int, dtype: torch.dtype = torch.float64,
                         device: torch.device | str | None = None) -> torch.Tensor:
    """Control weight of seed §7.2: ``tridiag(-1, 2, -1) ⊗ I_m`` ``(T m, T m)`` (penalizes differences of
    consecutive controls), to be passed as ``Rbig`` to :func:`solve_lifted`."""
    D = 2.0 * torch.eye(T, dtype=dtype, device=device)
    if T > 1:
        off = -torch.ones(T - 1, dtype=dtype, device=device)
        D = D + torch.diag(off, 1) + torch.diag(off, -1)
    return torch.kron(D, torch.eye(m, dtype=dtype, device=device))


def control_primitives(phi: torch.Tensor, m: int, coordination: torch.Tensor | None = None) -> torch.Tensor:
    """Dictionary ``Ψ = φ ⊗ C`` (seed Eq. 66) for time-major stacked controls.

    Args:
        phi: ``(T, K)`` basis functions (:mod:`controllers.basis`).
        m: control dimension.
        coordination: ``C (m, d)`` coordination matrix (identity when omitted).
    Returns:
        ``Ψ (T m, K d)``.
    """
    Cm = torch.eye(m, dtype=phi.dtype, device=phi.device) if coordination is None else coordination
    if Cm.shape[0] != m:
        raise ValueError(f"control_primitives: 'coordination' must have shape ({m}, d), "
                         f"got {tuple(Cm.shape)}")
    return torch.kron(phi, Cm)


class LiftedQuadratic(NamedTuple):
    """The LQ cost as a quadratic in the decision variable ``z`` (:func:`lifted_quadratic`):
    ``J(z) = zᵀ H z + 2 zᵀ g + const`` with the state trajectory ``x = S z + s0``.

    Attributes:
        H: ``(*B, k, k)`` normal matrix ``Sᵀ Q S + Uᵀ R U + Sᵀ N U + Uᵀ Nᵀ S`` (Eq. 62; ``U`` maps ``z`` to
            the stacked controls ``u = U z``: ``I``, ``Ψ`` (§7.3) or ``[0, I]`` (Eq. 65)).
        Hx: ``(*B, k, k)`` (with ``state_part=True``, else ``None``) its state part ``Sᵀ Q S`` alone (the
            precision of the tracking objective seen in the decision space; its null space is the null
            space of the tracking task).
        g: ``(*B, k)``; const: ``(*B,)`` or 0-dim.
        S: ``(*B, (T+1) n, k)``; s0: ``(*B, (T+1) n)`` free response (``S_x x_0 + s_c``, zero with Eq. 65).
        Sx, Su: the transfer matrices (:func:`transfer_matrices`).
    """

    H: torch.Tensor
    Hx: torch.Tensor | None
    g: torch.Tensor
    const: torch.Tensor
    S: torch.Tensor
    s0: torch.Tensor
    Sx: torch.Tensor
    Su: torch.Tensor


class _ControlMap:
    """``u = U z`` for the three decision variables of :func:`solve_lifted`: ``U = I`` (``z = u``),
    ``U = [0_{Tm×n}, I]`` (``z = [x_0; u]``, Eq. 65) or a dense dictionary ``U = Ψ`` (§7.3).  The identity
    and padded maps are never formed: the products below exploit their structure."""

    def __init__(self, T: int, m: int, pad: int = 0, Psi: torch.Tensor | None = None):
        self.T, self.m, self.pad, self.Psi = T, m, pad, Psi
        self.k = Psi.shape[-1] if Psi is not None else pad + T * m

    def apply(self, z: torch.Tensor) -> torch.Tensor:
        """``U z``: ``(*B, k)`` -> ``(*B, T m)``."""
        if self.Psi is not None:
            return (self.Psi @ z.unsqueeze(-1)).squeeze(-1)
        return z[..., self.pad:]

    def t_vec(self, v: torch.Tensor) -> torch.Tensor:
        """``Uᵀ v`` for ``v (*B, T m)`` -> ``(*B, k)``."""
        if self.Psi is not None:
            return (self.Psi.mT @ v.unsqueeze(-1)).squeeze(-1)
        if self.pad:
            v = torch.cat([v.new_zeros(*v.shape[:-1], self.pad), v], -1)
        return v

    def right(self, W: torch.Tensor) -> torch.Tensor:
        """``W U`` for ``W (*B, r, T m)`` -> ``(*B, r, k)``."""
        if self.Psi is not None:
            return W @ self.Psi
        if self.pad:
            W = torch.cat([W.new_zeros(*W.shape[:-1], self.pad), W], -1)
        return W

    def quad_blocks(self, R: torch.Tensor) -> torch.Tensor:
        """``Uᵀ blockdiag(R_t) U`` for ``R (*B, T|1, m, m)`` -> ``(*B, k, k)``, without forming blockdiag."""
        T, m = self.T, self.m
        R = R.expand(*R.shape[:-3], T, m, m)
        if self.Psi is not None:
            P = self.Psi.reshape(*self.Psi.shape[:-2], T, m, self.k)
            RP = (R @ P).flatten(-3, -2)  # (*B, T m, k)
            return self.Psi.mT @ RP
        eye = torch.eye(T, dtype=R.dtype, device=R.device)
        Rb = (eye[:, None, :, None] * R.unsqueeze(-2)).flatten(-4, -3).flatten(-2)  # (*B, T m, T m)
        if self.pad:
            Rb = torch.nn.functional.pad(Rb, (self.pad, 0, self.pad, 0))
        return Rb

    def quad_dense(self, Rbig: torch.Tensor) -> torch.Tensor:
        """``Uᵀ Rbig U`` for a full ``Rbig (*B, T m, T m)``."""
        if self.Psi is not None:
            return self.Psi.mT @ Rbig @ self.Psi
        if self.pad:
            Rbig = torch.nn.functional.pad(Rbig, (self.pad, 0, self.pad, 0))
        return Rbig


def lifted_quadratic(problem: LQProblem, *, Qbig: torch.Tensor | None = None,
                     Rbig: torch.Tensor | None = None, Psi: torch.Tensor | None = None,
                     optimize_x0: bool = False, state_part: bool = False) -> LiftedQuadratic:
    """The cost of ``problem`` as a quadratic in the decision variable (seed Eq. 62, 65, §7.3).

    Arguments as in :func:`solve_lifted`; ``state_part`` also returns ``Hx = Sᵀ Q S``.  With the
    block-diagonal precisions of the problem (no ``Qbig`` / ``Rbig``) nothing of size
    ``(T+1) n × (T+1) n`` is formed: ``S_uᵀ Q S_u = Σ_t S_tᵀ Q_t S_t`` comes from a backward recursion
    over the ``n``-row blocks ``S_t`` (``_gram_blocks``), and the control terms are ``U_tᵀ R_t U_t``
    over the blocks of ``U`` (``blockdiag(R_t)`` is never formed for ``U = I``).
    """
    if not isinstance(problem, LQProblem):
        raise TypeError("lifted_quadratic: argument 'problem' must be an LQProblem, "
                        f"got {type(problem).__name__}")
    T, n, m = problem.T, problem.n, problem.m
    bs = problem.batch_shape
    d = problem.dynamics
    dt, dev = problem.dtype, problem.device
    for name, M, sz in (("Qbig", Qbig, (T + 1) * n), ("Rbig", Rbig, T * m)):
        if M is not None and tuple(M.shape[-2:]) != (sz, sz):
            raise ValueError(f"solve_lifted: argument '{name}' must have shape (*B, {sz}, {sz}), "
                             f"got {tuple(M.shape)}")
    if Psi is not None:
        if optimize_x0:
            raise ValueError("solve_lifted: 'Psi' and 'optimize_x0' cannot be combined")
        if Psi.dim() < 2 or Psi.shape[-2] != T * m:
            raise ValueError(f"solve_lifted: argument 'Psi' must have shape (*B, {T * m}, K), "
                             f"got {tuple(Psi.shape)}")
    for name, M in (("Qbig", Qbig), ("Rbig", Rbig), ("Psi", Psi)):
        if M is not None:
            try:
                torch.broadcast_shapes(bs, M.shape[:-2])
            except RuntimeError:
                raise ValueError(f"solve_lifted: the batch dims {tuple(M.shape[:-2])} of argument '{name}' "
                                 f"do not broadcast with the problem's {tuple(bs)}") from None
    cost = problem.cost
    # a full precision replaces the block-diagonal one: expand its references separately
    if Qbig is not None:
        cost = dataclasses.replace(cost, Q=torch.zeros_like(cost.Q), check=False)
    if Rbig is not None:
        cost = dataclasses.replace(cost, R=torch.zeros_like(cost.R), check=False)
    cc = cost.canonical(T)
    Sx, Su, sc = transfer_matrices(d.A, d.B, d.c, T)
    const = cc.const
    qv = None if cc.q is None else cc.q.reshape(*cc.q.shape[:-2], (T + 1) * n)
    rv = None if cc.r is None else cc.r.reshape(*cc.r.shape[:-2], T * m)
    if Qbig is not None and problem.cost.x_ref is not None:
        mu = problem.cost.x_ref.expand(*problem.cost.x_ref.shape[:-2], T + 1, n).flatten(-2)
        extra = -(Qbig @ mu.unsqueeze(-1)).squeeze(-1)
        const = const - (mu * extra).sum(-1)
        qv = extra if qv is None else qv + extra
    if Rbig is not None and problem.cost.u_ref is not None:
        nu = problem.cost.u_ref.expand(*problem.cost.u_ref.shape[:-2], T, m).flatten(-2)
        extra = -(Rbig @ nu.unsqueeze(-1)).squeeze(-1)
        const = const - (nu * extra).sum(-1)
        rv = extra if rv is None else rv + extra
    x0 = problem.x0.expand(*bs, n)
    # decision variable z: u (or w), or [x0; u]; state x = S z + s0, controls u = U z
    if optimize_x0:
        S = torch.cat([Sx.expand(*bs, *Sx.shape[-2:]), Su.expand(*bs, *Su.shape[-2:])], -1)
        s0 = (torch.zeros(*bs, (T + 1) * n, dtype=dt, device=dev) if sc is None
              else sc.expand(*bs, (T + 1) * n))
        U = _ControlMap(T, m, pad=n)
    else:
        s0 = (Sx @ x0.unsqueeze(-1)).squeeze(-1)
        if sc is not None:
            s0 = s0 + sc
        S = Su if Psi is None else Su @ Psi
        U = _ControlMap(T, m, Psi=Psi)
    k = S.shape[-1]
    # state part Sᵀ Q S and Sᵀ Q s0: per-time blocks unless a full precision is given
    R_in = Rbig is None and Psi is None and not optimize_x0 and not state_part  # R added by _gram_blocks
    if Qbig is None:
        Qs0 = (cc.Q @ s0.reshape(*s0.shape[:-1], T + 1, n, 1)).flatten(-3)
        N_in = cc.N if R_in else None  # the cross term folded in as well
        SuQSu, SuQSx, P0 = _gram_blocks(d.A, d.B, cc.Q, Sx, Su, T, optimize_x0, cc.R if R_in else None,
                                        None if N_in is None else N_in.expand(*N_in.shape[:-3], T, n, m))
        if optimize_x0:
            SuQSx = SuQSx.expand(*bs, T * m, n)
            Hx = torch.cat([torch.cat([P0.expand(*bs, n, n), SuQSx.mT], -1),
                            torch.cat([SuQSx, SuQSu.expand(*bs, T * m, T * m)], -1)], -2)
        elif Psi is not None:
            Hx = Psi.mT @ SuQSu @ Psi
        else:
            Hx = SuQSu
    else:
        Qs0 = (Qbig @ s0.unsqueeze(-1)).squeeze(-1)
        Hx = S.mT @ (Qbig @ S)
    if R_in and Qbig is None:
        H = Hx
    else:
        H = Hx + (U.quad_blocks(cc.R) if Rbig is None else U.quad_dense(Rbig))
    gx = Qs0 if qv is None else Qs0 + qv
    const = const + (s0 * (Qs0 if qv is None else Qs0 + 2 * qv)).sum(-1)  # s0ᵀ Q s0 + 2 qᵀ s0
    g = (S.mT @ gx.unsqueeze(-1)).squeeze(-1)
    ru = rv
    if cc.N is not None:
        # 2 xᵀ N u over t < T: H += Sᵀ N U + Uᵀ Nᵀ S (unless folded in above),  g += Uᵀ Nᵀ s0
        N = cc.N.expand(*cc.N.shape[:-3], T, n, m)
        if not (R_in and Qbig is None):
            Sb = S.reshape(*S.shape[:-2], T + 1, n, k)[..., :T, :, :]
            SN = torch.einsum("...tnk,...tnj->...ktj", Sb, N).flatten(-2)  # (*B, k, T m): block t: S_tᵀ N_t
            SNU = U.right(SN)
            H = H + SNU + SNU.mT
        Nts0 = (N.mT @ s0.reshape(*s0.shape[:-1], T + 1, n, 1)[..., :T, :, :]).flatten(-3)
        ru = Nts0 if ru is None else ru + Nts0
    if ru is not None:
        g = g + U.t_vec(ru)
    if Qbig is not None or Rbig is not None or Psi is not None or optimize_x0:
        H = 0.5 * (H + H.mT)  # dense products: symmetric up to rounding (the block path is symmetric)
    return LiftedQuadratic(H=H, Hx=0.5 * (Hx + Hx.mT) if state_part else None, g=g, const=const, S=S, s0=s0,
                           Sx=Sx, Su=Su)


@dataclass(frozen=True, eq=False)
class LiftedSolution:
    """Result of :func:`solve_lifted`.

    Attributes:
        x: ``(*B, T+1, n)``; u: ``(*B, T, m)``; cost: ``(*B,)``.
        x0: the (optimized, Eq. 65, or given) initial state ``(*B, n)``.
        w: primitive weights ``(*B, K)`` when ``Psi`` was given, else ``None``.
        cov: covariance of the decision variable (Eq. 63): ``(*B, T m, T m)`` for ``u``, ``(*B, K, K)``
            for ``w``, ``(*B, n + T m, n + T m)`` for ``[x_0; u]`` when the initial state is optimized.
        Sx, Su: the transfer matrices.
        status: per-element :class:`SolverStatus` (``SINGULAR_QUU`` when the normal matrix is not PD).
    """

    x: torch.Tensor
    u: torch.Tensor
    cost: torch.Tensor
    x0: torch.Tensor
    w: torch.Tensor | None
    cov: torch.Tensor | None
    Sx: torch.Tensor
    Su: torch.Tensor
    status: SolverStatus


def solve_lifted(problem: LQProblem, *, Qbig: torch.Tensor | None = None, Rbig: torch.Tensor | None = None,
                 Psi: torch.Tensor | None = None, optimize_x0: bool = False, covariance: bool = False
                 ) -> LiftedSolution:
    """Solve an LQ problem in batch form (seed Eq. 62; Eq. 65 with ``optimize_x0``; §7.3 with ``Psi``).

    The normal equations are assembled by :func:`lifted_quadratic`, which uses the block structure of
    the problem's per-step ``Q_t``, ``R_t``, ``N_t``: ``S_uᵀ Q S_u + R + S_uᵀN + NᵀS_u`` comes from a
    backward recursion in ``O(T n³ + T² n m²)`` per element instead of products with the
    ``(T+1) n × (T+1) n`` matrix ``blockdiag(Q_t)`` (which is never formed); a ``Qbig``/``Rbig`` is used as
    the full matrix it is.  Then one Cholesky factorization of the ``T m × T m`` normal matrix.

    Args:
        problem: the :class:`LQProblem` (dynamics, references, linear and cross terms, ``x0``).
        Qbig: optional full state precision ``(*B, (T+1) n, (T+1) n)`` replacing the block-diagonal
            ``blockdiag(Q_t)`` (may couple time steps / agents).
        Rbig: optional full control weight ``(*B, T m, T m)`` (e.g. :func:`smoothness_precision`).
        Psi: optional control primitives ``(T m, K)`` or ``(*B, T m, K)``: ``u = Ψ w``.
            The batch dims of ``Qbig``, ``Rbig`` and ``Psi`` broadcast with the problem's into the result's.
        optimize_x0: also optimize the initial state (``R̃ = blockdiag(0, R)``, Eq. 65); the cost on
            ``x_0`` (``Q_0``, references) then matters and must make the problem well posed.
        covariance: return ``cov`` (Eq. 63).
    """
    if not isinstance(problem, LQProblem):
        raise TypeError("solve_lifted: argument 'problem' must be an LQProblem, "
                        f"got {type(problem).__name__}")
    T, n, m = problem.T, problem.n, problem.m
    lq = lifted_quadratic(problem, Qbig=Qbig, Rbig=Rbig, Psi=Psi, optimize_x0=optimize_x0)
    # batched Qbig / Rbig / Psi broadcast with the problem's batch dims (all carried by H and g)
    bs = torch.broadcast_shapes(problem.batch_shape, lq.H.shape[:-2], lq.g.shape[:-1])
    L, info = torch.linalg.cholesky_ex(lq.H)
    z = -torch.cholesky_solve(lq.g.unsqueeze(-1), L).squeeze(-1)
    xs = (lq.S @ z.unsqueeze(-1)).squeeze(-1) + lq.s0
    x = xs.reshape(*xs.shape[:-1], T + 1, n)
    w = None
    if optimize_x0:
        x0o, uv = z[..., :n], z[..., n:]
    else:
        x0o = problem.x0.expand(*bs, n)
        if Psi is not None:
            w = z
            uv = (Psi @ z.unsqueeze(-1)).squeeze(-1)
        else:
            uv = z
    u = uv.reshape(*uv.shape[:-1], T, m)
    # cost at the solution: J = zᵀHz + 2zᵀg + const (the definition, by construction of H and g)
    J = (z * (lq.H @ z.unsqueeze(-1)).squeeze(-1)).sum(-1) + 2 * (z * lq.g).sum(-1) + lq.const
    cov = torch.cholesky_inverse(L) if covariance else None
    reason = torch.where(info.expand(bs) != 0, int(Reason.SINGULAR_QUU), 0).to(torch.int64)
    inp = problem.input_status().expand(bs)
    reason = torch.where(inp != 0, inp, reason)
    return LiftedSolution(x=x, u=u, cost=J, x0=x0o, w=w, cov=cov, Sx=lq.Sx, Su=lq.Su,
                          status=SolverStatus.from_reason(reason, 1))
