"""Recursive Riccati solution of batched LQR/LQT problems (seed 004 §7.4-7.6).

The recursion runs on the homogeneous state ``x̃ = [x; 1]`` (seed Eq. 76-78), so one sweep on
``(n+1) × (n+1)`` matrices handles LQR, LQT and affine dynamics; the kernels (assembly, backward and
forward sweeps) live in the private ``controllers._lq_kernels``, shared with :mod:`controllers.implicit`.

Also here: the explicit augmented-state construction of seed Eq. 76-77 (:func:`augmented_lqt`) and the
least-squares recursive form Eq. 79-81 (:func:`ls_recursive_gains`), which accepts a full (non block
diagonal) trajectory precision matrix and control primitives ``u = Ψ w``.

Entry point: :func:`solve` (an :class:`~controllers.problem.LQProblem` in, an
:class:`~controllers.problem.LQSolution` out), with ``grad="implicit"`` (default, the backward pass of
:mod:`controllers.implicit`), ``grad="unrolled"`` (autograd through the recursion) or ``grad="none"``;
:func:`lqr` is the same on plain canonical tensors.  Re-solving with one cost and new ``x0`` or dynamics
(MPC): :func:`prepare` the cost once and pass the :class:`PreparedCost` to :func:`solve` — an explicit
value the caller holds, never a cache hidden on the cost.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import torch

from controllers._lq_kernels import assemble_cost, solve_core
from controllers._validate import enum_arg
from controllers.costs import CanonicalCost, QuadraticCost, stand_in_cost
from controllers.dynamics import LinearDynamics
from controllers.implicit import lqr_implicit
from controllers.problem import GradMode, LQProblem, LQSolution, Reason, SolverStatus, cost_status_of
from torchlie._batch import broadcast_shapes

__all__ = [
    "solve",
    "lqr",
    "prepare",
    "PreparedCost",
    "augmented_lqt",
    "AugmentedLQT",
    "ls_recursive_gains",
    "LSGains",
]


def lqr(A: torch.Tensor, B: torch.Tensor, c: torch.Tensor | None, Q: torch.Tensor, R: torch.Tensor,
        N: torch.Tensor | None, q: torch.Tensor | None, r: torch.Tensor | None, x0: torch.Tensor,
        T: int, grad: GradMode | str = GradMode.IMPLICIT, fused: bool = False, _stage=None):
    """Functional core on canonical tensors (no validation): returns ``x (*B, T+1, n)``,
    ``u (*B, T, m)``, ``K (*B, T, m, n)``, ``k (*B, T, m)``, ``J (*B,)`` and ``ok (*B, T)`` (False
    where ``H_uu`` was not positive definite).

    Shapes as in :mod:`controllers.problem` with explicit time dims; the cost is ``Σ xᵀQx + uᵀRu + 2xᵀNu +
    2qᵀx + 2rᵀu`` (no constant; :mod:`controllers.costs`).  With ``grad='implicit'`` the gradients of ``x``,
    ``u`` and ``J`` come from :class:`controllers.implicit.LQRFunction`; ``K``, ``k`` are then returned
    without a graph (use ``grad='unrolled'`` to differentiate the gains).  ``fused=True`` runs each step's
    pivot updates as one ``torch.compile``'d kernel (not with ``grad='unrolled'``).
    """
    grad = enum_arg(GradMode, grad, "grad", "lqr")
    if fused and grad is GradMode.UNROLLED:
        raise ValueError("lqr: fused=True needs grad='implicit' or 'none' (no graph through the kernel)")
    n, m = A.shape[-1], B.shape[-1]
    tr = [(A, 3), (B, 3), (c, 2), (Q, 3), (R, 3), (N, 3), (q, 2), (r, 2)]
    bs = broadcast_shapes(x0.shape[:-1], *[v.shape[:v.dim() - k] for v, k in tr if v is not None])
    if grad is GradMode.IMPLICIT:
        x, u, J, K, k, info = lqr_implicit(A, B, c, Q, R, N, q, r, x0, T, bs, fused)
    else:
        ctx = torch.enable_grad() if grad is GradMode.UNROLLED else torch.no_grad()
        with ctx:
            x, u, J, fac, _ = solve_core(A, B, c, Q, R, N, q, r, x0, T, bs,
                                          graph=grad is GradMode.UNROLLED, fused=fused,
                                          stage=_stage)
        K, k, info = fac.Kt[..., :n], fac.Kt[..., n], fac.ok
    return (x.reshape(*bs, T + 1, n), u.reshape(*bs, T, m), K.reshape(*bs, T, m, n), k.reshape(*bs, T, m),
            J.reshape(bs), info.reshape(*bs, T))


@dataclass(frozen=True, eq=False)
class PreparedCost:
    """A :class:`~controllers.costs.QuadraticCost` expanded for one horizon and batch shape
    (:func:`prepare`): the canonical form, the stage matrices of the Riccati sweep and the per-element
    input status of the cost.  A snapshot: it holds the values the cost had when it was prepared (write
    into the cost afterwards and prepare it again)."""

    cost: QuadraticCost
    T: int
    batch_shape: torch.Size
    canonical: CanonicalCost
    C: torch.Tensor
    VT: torch.Tensor
    status: torch.Tensor


def prepare(cost: QuadraticCost, T: int, batch_shape: torch.Size | tuple[int, ...] = ()) -> PreparedCost:
    """Expand ``cost`` once for re-use in many ``solve(..., grad="none", prepared=...)`` calls (MPC with a
    fixed cost and new ``x0``/dynamics, repeated evaluations): references, stage matrices (stored
    time-major) and the cost's part of the input check (non-finite data, Q ⪰ 0 / R ≻ 0 per element).

    ``batch_shape`` is the batch shape of the problems it will be used with (the broadcast of ``x0``,
    dynamics and cost).  No graph is kept (use ``grad="implicit"`` or ``"unrolled"`` without a prepared
    cost to differentiate).
    """
    if not isinstance(cost, QuadraticCost):
        raise TypeError(f"prepare: argument 'cost' must be a QuadraticCost, got {type(cost).__name__}")
    if not isinstance(T, int) or isinstance(T, bool) or T < 1 or cost.horizon not in (None, T):
        raise ValueError(f"prepare: argument 'T' must be a positive int equal to the cost's horizon "
                         f"({cost.horizon}), got {T!r}")
    bs = torch.Size(batch_shape)
    try:
        broadcast_shapes(bs, cost.batch_shape)
    except RuntimeError as e:
        raise ValueError(f"prepare: batch_shape {tuple(bs)} does not broadcast with the cost's batch "
                         f"shape {tuple(cost.batch_shape)}") from e
    bs = broadcast_shapes(bs, cost.batch_shape)
    with torch.no_grad():
        cc = cost.canonical(T)
        C, VT = assemble_cost(cc.Q, cc.R, cc.N, cc.q, cc.r, T, bs)
        if C.shape[0] > 1 and C.shape[1] > 1:
            C = C.transpose(0, 1).contiguous().transpose(0, 1)  # C[:, t] is then one contiguous block
        status = cost_status_of(cost).expand(bs)
    return PreparedCost(cost=cost, T=T, batch_shape=bs, canonical=cc, C=C, VT=VT, status=status)


def solve(problem: LQProblem, grad: GradMode | str = GradMode.IMPLICIT, check: bool = True,
          fused: bool = False, prepared: PreparedCost | None = None) -> LQSolution:
    """Solve a batched LQR/LQT problem with the Riccati recursion.

    Args:
        problem: the :class:`LQProblem`.
        grad: :class:`~controllers.problem.GradMode` — ``"implicit"`` (default), ``"unrolled"`` or
            ``"none"``.
        check: compute the per-element input status (non-finite data, Q/R definiteness when batched).
        fused: run each Riccati step's pivot updates as one ``torch.compile``'d kernel (compiled on
            first use per shape/dtype, seconds; then faster).  Needs a working ``torch.compile``.
        prepared: ``prepare(problem.cost, T, batch_shape)``, re-used across solves (``grad="none"``
            only): the cost's expansion, stage matrices and input status are taken from it.

    Returns:
        :class:`LQSolution` with ``x``, ``u``, gains ``K``/``k`` (``u_t = K_t x_t + k_t``), the optimal
        cost (references included) and per-element status: ``SINGULAR_QUU`` where ``H_uu`` was not
        positive definite at some step, input failures from :meth:`LQProblem.input_status`.  A failed
        element's outputs are NaN and it never changes the others' values or gradients (every operation
        is per element; its backward contributes nothing).
    """
    if not isinstance(problem, LQProblem):
        raise TypeError(f"solve: argument 'problem' must be an LQProblem, got {type(problem).__name__}")
    T = problem.T
    grad = enum_arg(GradMode, grad, "grad", "solve")
    d, cost = problem.dynamics, problem.cost
    stage = None
    if prepared is not None:
        if not isinstance(prepared, PreparedCost):
            raise TypeError(f"solve: argument 'prepared' must come from riccati.prepare, "
                            f"got {type(prepared).__name__}")
        if grad is not GradMode.NONE:
            raise ValueError(f"solve: argument 'prepared' needs grad='none' (it holds no graph), "
                             f"got grad={grad.value!r}")
        if prepared.cost is not cost or prepared.T != T or prepared.batch_shape != problem.batch_shape:
            raise ValueError(f"solve: argument 'prepared' was made for another problem: use "
                             f"prepare(problem.cost, {T}, {tuple(problem.batch_shape)}) (got a cost "
                             f"{'of this problem' if prepared.cost is cost else 'of another problem'}, "
                             f"T={prepared.T}, batch_shape={tuple(prepared.batch_shape)})")
    inp = None
    if check:
        # an element whose inputs failed is solved on stand-in data (identity weights and dynamics, zero
        # elsewhere): its NaN/inf would otherwise reach a shared parameter's gradient as 0·inf
        inp = problem.input_status(None if prepared is None else prepared.status)
        if prepared is None:
            cost = stand_in_cost(cost, inp != 0)
    if prepared is not None:
        cc, stage = prepared.canonical, (prepared.C, prepared.VT)
    else:
        cc = cost.canonical(T)
    data = [d.A, d.B, d.c, cc.Q, cc.R, cc.N, cc.q, cc.r, problem.x0]
    if inp is not None:
        data = [_stand_in(inp != 0, v, k, eye) for v, k, eye in zip(data, _EVENT_DIMS, _IDENTITY)]
    x, u, K, k, J, info = lqr(*data, T, grad, fused, _stage=stage)
    J = J + cc.const
    reason = (~info.all(-1)).to(torch.int64) * int(Reason.SINGULAR_QUU)
    if inp is not None:
        inp = inp.expand(reason.shape)
        reason = torch.where(inp != 0, inp, reason)
    bad = reason != 0
    x, u, K, k, J = (_nan_where(bad, v) for v in (x, u, K, k, J))
    return LQSolution(x=x, u=u, K=K, k=k, cost=J, status=SolverStatus.from_reason(reason, 1))


#: event dims (time included) of lqr's arguments A, B, c, Q, R, N, q, r, x0
_EVENT_DIMS = (3, 3, 2, 3, 3, 3, 2, 2, 1)
_IDENTITY = (True, False, False, True, True, False, False, False, False)  # stand-ins: I for A, Q, R


def _stand_in(bad: torch.Tensor, v: torch.Tensor | None, k: int, eye: bool) -> torch.Tensor | None:
    """``v`` (``k`` event dims) with the elements ``bad (*B,)`` replaced by harmless data: the identity
    (``eye``: A, Q, R) or zero.  Tensors without batch dims are shared and kept."""
    if v is None or v.dim() == k:
        return v
    good_val = torch.eye(v.shape[-1], dtype=v.dtype, device=v.device) if eye \
        else torch.zeros((), dtype=v.dtype, device=v.device)
    return torch.where(bad.reshape(tuple(bad.shape) + (1,) * k), good_val, v)


def _nan_where(bad: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """``v`` with NaN for the failed elements ``bad (*B,)`` (no gradient flows to them)."""
    return torch.where(bad.reshape(tuple(bad.shape) + (1,) * (v.dim() - bad.dim())), torch.nan, v)


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
        At = At.expand(*broadcast_shapes(At.shape[:-2], d.c.shape[:-1]), n + 1, n + 1).clone()
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
    bs = broadcast_shapes(Ft.shape[:-3], A.shape[:-3], B.shape[:-3])
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
