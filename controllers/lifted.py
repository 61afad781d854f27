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

import torch

from controllers.problem import LQProblem, Reason, SolverStatus
from torchlie._batch import broadcast_shapes

__all__ = [
    "transfer_matrices",
    "block_diag_time",
    "smoothness_precision",
    "control_primitives",
    "LiftedSolution",
    "solve_lifted",
]


def transfer_matrices(A: torch.Tensor, B: torch.Tensor, c: torch.Tensor | None = None, T: int | None = None
                      ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """Transfer matrices ``S_x (*B, (T+1) n, n)``, ``S_u (*B, (T+1) n, T m)`` and drift response
    ``s_c (*B, (T+1) n)``.

    Appendix A (Eq. 188): block row ``t`` of ``S_x`` is ``A_{t-1} ... A_0``; block ``(t, s)`` of ``S_u``
    is ``A_{t-1} ... A_{s+1} B_s`` for ``s < t``.  ``A (*B, T|1, n, n)``, ``B (*B, T|1, n, m)``,
    ``c (*B, T|1, n)`` (time dims of 1 broadcast; then ``T`` must be given).
    """
    if T is None:
        T = max(A.shape[-3], B.shape[-3], 1 if c is None else c.shape[-2])
    n, m = A.shape[-1], B.shape[-1]
    bs = broadcast_shapes(A.shape[:-3], B.shape[:-3], *([] if c is None else [c.shape[:-2]]))
    dt, dev = A.dtype, A.device
    At = lambda t: A[..., t if A.shape[-3] > 1 else 0, :, :]
    Bt = lambda t: B[..., t if B.shape[-3] > 1 else 0, :, :]
    rows_x = [torch.eye(n, dtype=dt, device=dev).expand(*bs, n, n)]
    rows_u = [torch.zeros(*bs, n, T * m, dtype=dt, device=dev)]
    rows_c = None if c is None else [torch.zeros(*bs, n, dtype=dt, device=dev)]
    for t in range(T):
        a = At(t)
        rows_x.append(a @ rows_x[-1])
        ru = a @ rows_u[-1]
        ru = torch.cat([ru[..., : t * m], ru[..., t * m:(t + 1) * m] + Bt(t).expand(*bs, n, m),
                        ru[..., (t + 1) * m:]], -1)
        rows_u.append(ru)
        if rows_c is not None:
            ct = c[..., t if c.shape[-2] > 1 else 0, :]
            rows_c.append((a @ rows_c[-1].unsqueeze(-1)).squeeze(-1) + ct)
    Sx = torch.cat(rows_x, -2)
    Su = torch.cat(rows_u, -2)
    sc = None if rows_c is None else torch.cat(rows_c, -1)
    return Sx, Su, sc


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

    Args:
        problem: the :class:`LQProblem` (dynamics, references, linear and cross terms, ``x0``).
        Qbig: optional full state precision ``(*B, (T+1) n, (T+1) n)`` replacing the block-diagonal
            ``blockdiag(Q_t)`` (may couple time steps / agents).
        Rbig: optional full control weight ``(*B, T m, T m)`` (e.g. :func:`smoothness_precision`).
        Psi: optional control primitives ``(T m, K)`` or ``(*B, T m, K)``: ``u = Ψ w``.
        optimize_x0: also optimize the initial state (``R̃ = blockdiag(0, R)``, Eq. 65); the cost on
            ``x_0`` (``Q_0``, references) then matters and must make the problem well posed.
        covariance: return ``cov`` (Eq. 63).
    """
    if not isinstance(problem, LQProblem):
        raise TypeError("solve_lifted: argument 'problem' must be an LQProblem, "
                        f"got {type(problem).__name__}")
    T, n, m = problem.T, problem.n, problem.m
    bs = problem.batch_shape
    d = problem.dynamics
    dt, dev = problem.dtype, problem.device
    for name, M, sz in (("Qbig", Qbig, (T + 1) * n), ("Rbig", Rbig, T * m)):
        if M is not None and tuple(M.shape[-2:]) != (sz, sz):
            raise ValueError(f"solve_lifted: argument '{name}' must have shape (*B, {sz}, {sz}), "
                             f"got {tuple(M.shape)}")
    cost = problem.cost
    # a full precision replaces the block-diagonal one: expand its references separately
    if Qbig is not None:
        cost = dataclasses.replace(cost, Q=torch.zeros_like(cost.Q), check=False)
    if Rbig is not None:
        cost = dataclasses.replace(cost, R=torch.zeros_like(cost.R), check=False)
    cc = cost.canonical(T)
    Sx, Su, sc = transfer_matrices(d.A, d.B, d.c, T)
    Qb = block_diag_time(cc.Q, T + 1) if Qbig is None else Qbig
    Rb = block_diag_time(cc.R, T) if Rbig is None else Rbig
    extra_q = extra_r = None
    const = cc.const
    if Qbig is not None and problem.cost.x_ref is not None:
        mu = problem.cost.x_ref.expand(*problem.cost.x_ref.shape[:-2], T + 1, n).flatten(-2)
        extra_q = -(Qbig @ mu.unsqueeze(-1)).squeeze(-1)
        const = const - (mu * extra_q).sum(-1)
    if Rbig is not None and problem.cost.u_ref is not None:
        nu = problem.cost.u_ref.expand(*problem.cost.u_ref.shape[:-2], T, m).flatten(-2)
        extra_r = -(Rbig @ nu.unsqueeze(-1)).squeeze(-1)
        const = const - (nu * extra_r).sum(-1)
    Nb = None
    if cc.N is not None:
        Nb = torch.cat([block_diag_time(cc.N, T),
                        torch.zeros(*cc.N.shape[:-3], n, T * m, dtype=dt, device=dev)], -2)
    qv = None if cc.q is None else cc.q.reshape(*cc.q.shape[:-2], (T + 1) * n)
    rv = None if cc.r is None else cc.r.reshape(*cc.r.shape[:-2], T * m)
    if extra_q is not None:
        qv = extra_q if qv is None else qv + extra_q
    if extra_r is not None:
        rv = extra_r if rv is None else rv + extra_r
    x0 = problem.x0.expand(*bs, n)
    # decision variable z: u (or w), or [x0; u]; state x = S z + s0
    if optimize_x0:
        S = torch.cat([Sx.expand(*bs, *Sx.shape[-2:]), Su.expand(*bs, *Su.shape[-2:])], -1)
        s0 = (torch.zeros(*bs, (T + 1) * n, dtype=dt, device=dev) if sc is None
              else sc.expand(*bs, (T + 1) * n))
        Rz = torch.zeros(*bs, n + T * m, n + T * m, dtype=dt, device=dev)
        Rz[..., n:, n:] = Rb
        Nz = None
        if Nb is not None:
            Nz = torch.cat([torch.zeros(*Nb.shape[:-1], n, dtype=dt, device=dev), Nb], -1)
        rz = None if rv is None else torch.cat([torch.zeros(*rv.shape[:-1], n, dtype=dt, device=dev), rv], -1)
        Pz = None
        if Psi is not None:
            raise ValueError("solve_lifted: 'Psi' and 'optimize_x0' cannot be combined")
    else:
        s0 = (Sx @ x0.unsqueeze(-1)).squeeze(-1)
        if sc is not None:
            s0 = s0 + sc
        S, Rz, Nz, rz = Su, Rb, Nb, rv
        Pz = Psi
    if Pz is not None:
        if Pz.shape[-2] != T * m:
            raise ValueError(f"solve_lifted: argument 'Psi' must have shape (*B, {T * m}, K), "
                             f"got {tuple(Pz.shape)}")
        S = S @ Pz
        Rz = Pz.mT @ Rz @ Pz
        Nz = None if Nz is None else Nz @ Pz
        rz = None if rz is None else (Pz.mT @ rz.unsqueeze(-1)).squeeze(-1)
    # J(z) = zᵀ H z + 2 zᵀ g + const
    QS = Qb @ S
    H = S.mT @ QS + Rz
    g = (QS.mT @ s0.unsqueeze(-1)).squeeze(-1)
    if Nz is not None:
        SN = S.mT @ Nz
        H = H + SN + SN.mT
        g = g + (Nz.mT @ s0.unsqueeze(-1)).squeeze(-1)
    if qv is not None:
        g = g + (S.mT @ qv.unsqueeze(-1)).squeeze(-1)
    if rz is not None:
        g = g + rz
    H = 0.5 * (H + H.mT)
    L, info = torch.linalg.cholesky_ex(H)
    z = -torch.cholesky_solve(g.unsqueeze(-1), L).squeeze(-1)
    xs = (S @ z.unsqueeze(-1)).squeeze(-1) + s0
    x = xs.reshape(*xs.shape[:-1], T + 1, n)
    w = None
    if optimize_x0:
        x0o, uv = z[..., :n], z[..., n:]
    else:
        x0o = x0
        if Pz is not None:
            w = z
            uv = (Pz @ z.unsqueeze(-1)).squeeze(-1)
        else:
            uv = z
    u = uv.reshape(*uv.shape[:-1], T, m)
    # cost straight from the definition (full matrices when given)
    xd = xs
    J = (xd.unsqueeze(-2) @ Qb @ xd.unsqueeze(-1)).squeeze(-1).squeeze(-1)
    J = J + (uv.unsqueeze(-2) @ Rb @ uv.unsqueeze(-1)).squeeze(-1).squeeze(-1)
    if Nb is not None:
        J = J + 2 * (xd.unsqueeze(-2) @ Nb @ uv.unsqueeze(-1)).squeeze(-1).squeeze(-1)
    if qv is not None:
        J = J + 2 * (qv * xd).sum(-1)
    if rv is not None:
        J = J + 2 * (rv * uv).sum(-1)
    J = J + const
    cov = torch.cholesky_inverse(L) if covariance else None
    reason = torch.where(info.expand(bs) != 0, int(Reason.SINGULAR_QUU), 0).to(torch.int64)
    inp = problem.input_status()
    reason = torch.where(inp != 0, inp, reason)
    return LiftedSolution(x=x, u=u, cost=J, x0=x0o, w=w, cov=cov, Sx=Sx, Su=Su,
                          status=SolverStatus.from_reason(reason, 1))
