"""LQT recipes of the cookbook (seed 004 §7): nullspace LQT, DMP as LQT with control primitives, agents that
meet, and the bimanual tennis serve of Appendix C — each built on :mod:`controllers.lifted` (Eq. 59-66) and
:mod:`controllers.riccati` (§7.4-7.5), batched over any leading dims.

* :func:`nullspace_lqt` — the batch LQT solution ``û`` (Eq. 62) plus a motion ``N v`` in the null space of
  the tracking objective (``N = I - (S_uᵀQS_u)⁺ S_uᵀQS_u``, the projector of §5.2 applied to Eq. 62):
  every ``u = û + N v`` tracks the targets exactly as well as ``û``; ``v`` is given or chosen by a secondary
  quadratic objective (the seed's ``LQT_nullspace``).
* :func:`dmp_lqt` / :func:`dmp_rollout` — §7.7: from one demonstration, a double integrator that tracks
  the demonstrated accelerations and reaches the demonstrated end point, with controls ``u = Ψ w`` on radial
  basis functions (Eq. 66); the feedback gains of the same cost (§7.5, Eq. 78) correct a different start
  or a perturbation.
* :func:`meeting_lqt` — §7.6 (Fig. 19): point-mass agents stacked in one state, each reaching its target
  at ``T`` and meeting the others at a given time (a precision with off-diagonal agent blocks), or at
  different times per agent (a full precision coupling time steps, solved with ``Qbig``).
* :func:`tennis_serve_lqt` — Appendix C (Eq. 189-192): left hand, right hand and ball with gravity as
  states; the ball is carried, released at ``T/4``, hit at ``T/2`` and sent to a target at ``T``.

Time indices follow :mod:`controllers.problem` (``x_0 .. x_T``; the seed's ``x_1`` is ``x_0`` here) and
costs follow :mod:`controllers.costs` (Eq. 59, no factor ½).
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from controllers import basis
from controllers.costs import QuadraticCost
from controllers.dynamics import LinearDynamics
from controllers.lifted import LiftedSolution, control_primitives, lifted_quadratic, solve_lifted
from controllers.problem import LQProblem, Reason, SolverStatus
from controllers.riccati import solve as riccati_solve

__all__ = [
    "NullspaceLQT",
    "nullspace_lqt",
    "double_integrator",
    "DMPLQT",
    "dmp_lqt",
    "dmp_rollout",
    "MeetingLQT",
    "meeting_lqt",
    "TennisServe",
    "tennis_serve_lqt",
]


def _check_float(x, name: str, fn: str, min_dim: int, shape: str) -> torch.Tensor:
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{fn}: argument '{name}' must be a torch.Tensor {shape}, got {type(x).__name__}")
    if not x.dtype.is_floating_point:
        raise TypeError(f"{fn}: argument '{name}' must have a floating dtype, got {x.dtype}")
    if x.dim() < min_dim:
        raise ValueError(f"{fn}: argument '{name}' must have shape {shape}, got {tuple(x.shape)}")
    return x


def _check_pos(v, name: str, fn: str, integer: bool = False):
    ok = isinstance(v, int) and not isinstance(v, bool) if integer else isinstance(v, (int, float))
    if not ok or v <= 0:
        raise ValueError(f"{fn}: argument '{name}' must be a positive {'int' if integer else 'number'}, "
                         f"got {v!r}")
    return v


# --------------------------------------------------------------------------------------------------
# nullspace LQT
# --------------------------------------------------------------------------------------------------


class NullspaceLQT(NamedTuple):
    """Result of :func:`nullspace_lqt`.

    Attributes:
        x: ``(*B, T+1, n)``, u: ``(*B, T, m)`` — the trajectory with ``u = û + N v``.
        u_primary: ``(*B, T, m)`` — ``û`` (Eq. 62).
        N: ``(*B, T m, T m)`` — null-space projector of the tracking objective.
        v: ``(*B, T m)`` — the null-space command used (projected: ``N v``).
        rank: ``(*B,)`` int64 — rank of ``S_uᵀ Q S_u`` (number of constrained directions).
        status: per-element :class:`SolverStatus` (``NONFINITE_INPUT`` elements are NaN).
    """

    x: torch.Tensor
    u: torch.Tensor
    u_primary: torch.Tensor
    N: torch.Tensor
    v: torch.Tensor
    rank: torch.Tensor
    status: SolverStatus


def nullspace_lqt(problem: LQProblem, *, v: torch.Tensor | None = None,
                  secondary: QuadraticCost | None = None, rtol: float | None = None) -> NullspaceLQT:
    """LQT with a secondary objective in the null space of the tracking one (seed §7, ``LQT_nullspace``).

    The primary solution is the batch LQT ``û = -(S_uᵀQS_u + R)⁺ g`` (Eq. 62; a pseudo-inverse so that
    ``R = 0`` gives the least-norm solution).  The tracking residual ``Q^{½}(x - μ)`` depends on ``u`` only
    through ``S_uᵀ Q S_u``, so every ``u = û + N v`` with ``N = I - (S_uᵀQS_u)⁺ S_uᵀQS_u`` (the projector
    of Eq. 22 for the "Jacobian" ``Q^{½} S_u``) leaves it unchanged.  ``v`` is either given, or chosen to
    minimize a secondary quadratic cost ``c₂(u)`` (same dynamics and ``x_0``):
    ``v = -(N H₂ N)⁺ N (H₂ û + g₂)``, the minimizer of ``c₂`` subject to ``Q^{½}S_u u = Q^{½}S_u û``.

    Args:
        problem: the primary tracking problem (``Q_t`` zero except at the via points: a sparse objective
            leaves a large null space).  Its linear terms ``q`` must be zero for the residual statement.
        v: ``(*B, T, m)`` null-space command (projected by ``N``); exclusive with ``secondary``.
        secondary: a :class:`QuadraticCost` with the problem's ``n``, ``m`` (and horizon).
        rtol: relative threshold on the eigenvalues of ``S_uᵀQS_u`` for its rank (default
            ``T m · eps^{½}`` of the dtype: the matrix squares the singular values of ``Q^{½}S_u``).

    Returns:
        :class:`NullspaceLQT`.  Differentiable in ``x_0``, references and ``v`` (the projector at a fixed
        rank).
    """
    fn = "nullspace_lqt"
    if not isinstance(problem, LQProblem):
        raise TypeError(f"{fn}: argument 'problem' must be an LQProblem, got {type(problem).__name__}")
    if v is not None and secondary is not None:
        raise ValueError(f"{fn}: give either 'v' or 'secondary', not both")
    T, n, m = problem.T, problem.n, problem.m
    dt = problem.dtype
    if v is not None:
        _check_float(v, "v", fn, 2, f"(*B, {T}, {m})")
        if tuple(v.shape[-2:]) != (T, m):
            raise ValueError(f"{fn}: argument 'v' must have shape (*B, {T}, {m}), got {tuple(v.shape)}")
        if v.dtype != dt:
            raise TypeError(f"{fn}: argument 'v' has dtype {v.dtype}, the problem {dt}")
    if secondary is not None:
        if not isinstance(secondary, QuadraticCost):
            raise TypeError(f"{fn}: argument 'secondary' must be a QuadraticCost, "
                            f"got {type(secondary).__name__}")
        if secondary.n != n or secondary.m != m or secondary.horizon not in (None, T):
            raise ValueError(f"{fn}: argument 'secondary' must be a cost with n={n}, m={m}, horizon {T}; got "
                             f"n={secondary.n}, m={secondary.m}, horizon {secondary.horizon}")
    lq = lifted_quadratic(problem, state_part=True)
    H, G, g = lq.H, lq.Hx, lq.g
    lq2 = None
    bs = torch.broadcast_shapes(problem.batch_shape, H.shape[:-2], g.shape[:-1], lq.S.shape[:-2])
    if secondary is not None:
        lq2 = lifted_quadratic(LQProblem(problem.dynamics, secondary, problem.x0, horizon=T))
        H2, g2 = lq2.H, lq2.g
        bs = torch.broadcast_shapes(bs, H2.shape[:-2], g2.shape[:-1])
    if v is not None:
        bs = torch.broadcast_shapes(bs, v.shape[:-2])
    k = T * m
    H, G, g = H.expand(*bs, k, k), G.expand(*bs, k, k), g.expand(*bs, k)
    # one non-finite element must not stop the batch's eigen-solvers: solve it on stand-in data
    bad = ~(torch.isfinite(H).flatten(-2).all(-1) & torch.isfinite(g).all(-1))
    if lq2 is not None:
        H2, g2 = H2.expand(*bs, k, k), g2.expand(*bs, k)
        bad = bad | ~(torch.isfinite(H2).flatten(-2).all(-1) & torch.isfinite(g2).all(-1))
    if v is not None:
        bad = bad | ~torch.isfinite(v).flatten(-2).all(-1).expand(bs)
    eye = torch.eye(k, dtype=dt, device=H.device)
    sel = bad[..., None, None]
    H, G = torch.where(sel, eye, H), torch.where(sel, eye, G)
    g = torch.where(bad[..., None], 0.0, g)
    tol = (k * torch.finfo(dt).eps ** 0.5) if rtol is None else float(rtol)
    u0 = -(torch.linalg.pinv(H, hermitian=True) @ g.unsqueeze(-1)).squeeze(-1)
    Gp = torch.linalg.pinv(G, rtol=tol, hermitian=True)
    Np = eye - Gp @ G
    Np = 0.5 * (Np + Np.mT)
    rank = torch.linalg.matrix_rank(G, rtol=tol, hermitian=True)
    if v is not None:
        vv = torch.where(bad[..., None], 0.0, v.flatten(-2).expand(*bs, k))
    elif lq2 is not None:
        H2 = torch.where(sel, eye, H2)
        g2 = torch.where(bad[..., None], 0.0, g2)
        NHN = Np @ H2 @ Np
        rhs = (Np @ ((H2 @ u0.unsqueeze(-1)).squeeze(-1) + g2).unsqueeze(-1))
        vv = -(torch.linalg.pinv(0.5 * (NHN + NHN.mT), rtol=tol, hermitian=True) @ rhs).squeeze(-1)
    else:
        vv = torch.zeros(*bs, k, dtype=dt, device=H.device)
    uvec = u0 + (Np @ vv.unsqueeze(-1)).squeeze(-1)
    xs = (lq.S @ uvec.unsqueeze(-1)).squeeze(-1) + lq.s0
    nan = torch.full((), torch.nan, dtype=dt, device=H.device)
    reason = torch.where(bad, int(Reason.NONFINITE_INPUT), problem.input_status().expand(bs))
    fail = reason != 0

    def mask(t: torch.Tensor) -> torch.Tensor:
        return torch.where(fail.reshape(*bs, *([1] * (t.dim() - len(bs)))), nan, t)

    return NullspaceLQT(x=mask(xs.reshape(*bs, T + 1, n)), u=mask(uvec.reshape(*bs, T, m)),
                        u_primary=mask(u0.reshape(*bs, T, m)), N=mask(Np), v=mask(vv), rank=rank,
                        status=SolverStatus.from_reason(reason))


# --------------------------------------------------------------------------------------------------
# DMP as LQT with control primitives (§7.7)
# --------------------------------------------------------------------------------------------------


def double_integrator(D: int, dt: float, dtype: torch.dtype = torch.float64,
                      device: torch.device | str | None = None) -> LinearDynamics:
    """``x = [p; ṗ]`` ``(2D)``, ``u = p̈`` ``(D)``: ``A = I + A^c Δt``, ``B = B^c Δt`` (Eq. 192) with
    ``A^c = [[0, I], [0, 0]]``, ``B^c = [0; I]`` (time-invariant, shared)."""
    _check_pos(D, "D", "double_integrator", integer=True)
    _check_pos(dt, "dt", "double_integrator")
    eye = torch.eye(D, dtype=dtype, device=device)
    z = torch.zeros(D, D, dtype=dtype, device=device)
    A = torch.cat([torch.cat([eye, dt * eye], -1), torch.cat([z, eye], -1)], -2)
    B = torch.cat([z, dt * eye], -2)
    return LinearDynamics(A, B)


class DMPLQT(NamedTuple):
    """Result of :func:`dmp_lqt`.

    Attributes:
        problem: the LQT problem (double integrator, goal ``[p_T; 0]`` at ``T``, accelerations tracked).
        Psi: ``(T D, K D)`` control primitives (Eq. 66).
        plan: the open-loop solution with ``u = Ψ w`` (§7.3; ``plan.x``, ``plan.u``, ``plan.w``).
        K: ``(*B, T, D, 2D)`` feedback gains of the same cost (§7.5, Eq. 78; ``u_t = K_t x_t + k_t``).
        demo_x: ``(*B, T+1, 2D)`` the demonstration as states ``[p_t; ṗ_t]``; demo_u ``(*B, T, D)`` its
            accelerations.
    """

    problem: LQProblem
    Psi: torch.Tensor
    plan: LiftedSolution
    K: torch.Tensor
    demo_x: torch.Tensor
    demo_u: torch.Tensor


def dmp_lqt(demo: torch.Tensor, dt: float, *, n_basis: int = 10, goal_weight: float = 1e4,
            accel_weight: float = 1.0, x0: torch.Tensor | None = None) -> DMPLQT:
    """Dynamical movement primitives reformulated as LQT with control primitives (seed §7.7, Fig. 20).

    The demonstration ``p_0 .. p_T`` gives velocities ``ṗ_t = (p_{t+1} - p_t)/Δt`` (``ṗ_T = 0``: the
    movement ends at rest) and accelerations ``a_t = (ṗ_{t+1} - ṗ_t)/Δt``, so that the double integrator
    (:func:`double_integrator`) driven by ``a_t`` from ``[p_0; ṗ_0]`` reproduces it exactly.  The LQT cost
    requests the end point and the acceleration profile (Eq. 59 with a reference on ``u``)::

        c = (x_T - [p_T; 0])ᵀ goal_weight (x_T - [p_T; 0]) + Σ_t (u_t - a_t)ᵀ accel_weight (u_t - a_t)

    with ``u = Ψ w`` on ``n_basis`` normalized radial basis functions per dimension (Eq. 66).  The open-loop
    plan is Eq. 62 with primitives; the feedback gains ``K_t`` of the same cost (Riccati on the augmented
    state, §7.5) give the optimal correction ``K_t (x_t - x̂_t)`` of a perturbed state
    (:func:`dmp_rollout`).

    Args:
        demo: ``(*B, T+1, D)`` demonstrated positions (one demonstration per batch element).
        dt: time step ``Δt``.
        n_basis: number of basis functions ``K`` per dimension.
        goal_weight, accel_weight: precisions of the goal and of the acceleration tracking.
        x0: start ``(*B, 2D)``; default the demonstration's ``[p_0; ṗ_0]``.
    """
    fn = "dmp_lqt"
    _check_float(demo, "demo", fn, 2, "(*B, T+1, D)")
    if demo.shape[-2] < 3:
        raise ValueError(f"{fn}: argument 'demo' needs at least 3 samples (*B, T+1, D), "
                         f"got {tuple(demo.shape)}")
    _check_pos(dt, "dt", fn)
    _check_pos(n_basis, "n_basis", fn, integer=True)
    _check_pos(goal_weight, "goal_weight", fn)
    _check_pos(accel_weight, "accel_weight", fn)
    T, D = demo.shape[-2] - 1, demo.shape[-1]
    dtp, dev = demo.dtype, demo.device
    vel = (demo[..., 1:, :] - demo[..., :-1, :]) / dt
    vel = torch.cat([vel, torch.zeros_like(vel[..., :1, :])], -2)  # ṗ_T = 0
    acc = (vel[..., 1:, :] - vel[..., :-1, :]) / dt
    demo_x = torch.cat([demo, vel], -1)
    if x0 is None:
        x0 = demo_x[..., 0, :]
    else:
        _check_float(x0, "x0", fn, 1, f"(*B, {2 * D})")
        if x0.shape[-1] != 2 * D or x0.dtype != dtp:
            raise ValueError(f"{fn}: argument 'x0' must have shape (*B, {2 * D}) and dtype {dtp}, "
                             f"got {tuple(x0.shape)} {x0.dtype}")
    n = 2 * D
    Q = torch.zeros(T + 1, n, n, dtype=dtp, device=dev)
    Q[T] = goal_weight * torch.eye(n, dtype=dtp, device=dev)
    R = accel_weight * torch.eye(D, dtype=dtp, device=dev)
    goal = demo_x[..., T:, :].expand(*demo_x.shape[:-2], T + 1, n)  # only x_T is weighted
    problem = LQProblem(double_integrator(D, dt, dtp, dev), QuadraticCost(Q, R, x_ref=goal, u_ref=acc), x0)
    Psi = control_primitives(basis.rbf(T, n_basis, normalized=True, dtype=dtp, device=dev), D)
    plan = solve_lifted(problem, Psi=Psi)
    K = riccati_solve(problem, grad="unrolled").K
    return DMPLQT(problem=problem, Psi=Psi, plan=plan, K=K, demo_x=demo_x, demo_u=acc)


def dmp_rollout(dmp: DMPLQT, x0: torch.Tensor | None = None, perturbation: torch.Tensor | None = None,
                at: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Closed-loop reproduction ``u_t = û_t + K_t (x_t - x̂_t)`` around the plan ``(x̂, û)`` of
    :func:`dmp_lqt` (the optimal LQ correction of a deviation, Eq. 78), from ``x0`` (default the plan's
    start), with ``perturbation`` ``(*B, 2D)`` added to the state at step ``at`` (Fig. 20's perturbation
    at a quarter of the movement).  Returns ``x (*B, T+1, 2D)``, ``u (*B, T, D)``.
    """
    fn = "dmp_rollout"
    if not isinstance(dmp, DMPLQT):
        raise TypeError(f"{fn}: argument 'dmp' must come from dmp_lqt, got {type(dmp).__name__}")
    T, n = dmp.problem.T, dmp.problem.n
    if (perturbation is None) != (at is None):
        raise ValueError(f"{fn}: give 'perturbation' and 'at' together")
    if at is not None and (not isinstance(at, int) or isinstance(at, bool) or not 0 <= at <= T):
        raise ValueError(f"{fn}: argument 'at' must be an int in [0, {T}], got {at!r}")
    if perturbation is not None:
        _check_float(perturbation, "perturbation", fn, 1, f"(*B, {n})")
        if perturbation.shape[-1] != n:
            raise ValueError(f"{fn}: argument 'perturbation' must have shape (*B, {n}), "
                             f"got {tuple(perturbation.shape)}")
    xp, up = dmp.plan.x, dmp.plan.u
    x = xp[..., 0, :] if x0 is None else x0
    if x0 is not None:
        _check_float(x0, "x0", fn, 1, f"(*B, {n})")
        if x0.shape[-1] != n:
            raise ValueError(f"{fn}: argument 'x0' must have shape (*B, {n}), got {tuple(x0.shape)}")
    d = dmp.problem.dynamics
    xs, us = [], []
    for t in range(T + 1):
        if at == t:
            x = x + perturbation
        xs.append(x)
        if t == T:
            break
        u = up[..., t, :] + (dmp.K[..., t, :, :] @ (x - xp[..., t, :]).unsqueeze(-1)).squeeze(-1)
        us.append(u)
        x = d.step(x, u, t)
    bs = torch.broadcast_shapes(*(v.shape[:-1] for v in xs))
    return (torch.stack([v.expand(*bs, n) for v in xs], -2),
            torch.stack([v.expand(*bs, up.shape[-1]) for v in us], -2))


# --------------------------------------------------------------------------------------------------
# agents meeting (§7.6, Fig. 19)
# --------------------------------------------------------------------------------------------------


class MeetingLQT(NamedTuple):
    """Result of :func:`meeting_lqt`.

    Attributes:
        problem: the stacked LQT problem (state ``[p_1; ṗ_1; ...; p_A; ṗ_A]``, controls ``[p̈_1; ...]``).
        Qbig: ``((T+1) n, (T+1) n)`` full precision when the agents meet at different times (then solve
            with ``solve_lifted(problem, Qbig=Qbig)``), else ``None`` (block diagonal in time: Riccati).
        solution: the solved trajectory (:class:`~controllers.problem.LQSolution` from Riccati with gains,
            or :class:`~controllers.lifted.LiftedSolution`).
        positions: ``(*B, T+1, A, D)`` the agents' positions.
        cost: ``(*B,)`` the stated objective (targets + meeting + control terms) at the solution:
            ``solution.cost`` plus the constant ``μᵀ Q_meet μ`` that the problem's linear term leaves out
            when a meeting time is ``T`` (see :func:`meeting_lqt`).
    """

    problem: LQProblem
    Qbig: torch.Tensor | None
    solution: object
    positions: torch.Tensor
    cost: torch.Tensor


def meeting_lqt(x0: torch.Tensor, targets: torch.Tensor, T: int, dt: float, *,
                meet_times: int | list[int] | None = None, target_weight: float = 1e3,
                meet_weight: float = 1e3, control_weight: float = 1e-2) -> MeetingLQT:
    """Point-mass agents that reach their targets at ``T`` and meet each other (seed §7.6, Fig. 19).

    Each agent ``i`` is a double integrator (:func:`double_integrator`) and the states are stacked.  The
    cost is Eq. 59 with ``target_weight (‖p_{i,T} - target_i‖² + ‖ṗ_{i,T}‖²)`` and, for every pair
    ``i < j``, ``meet_weight ‖p_{i,t_i} - p_{j,t_j}‖²``: the precision ``[[I, -I], [-I, I]]`` of the
    seed's footnote 3, so the meeting point is not given but optimized.  With one meeting time
    (``t_i = t_j``) this is a per-step precision with off-diagonal agent blocks, solved by Riccati (with
    feedback gains); with different times (``meet_times`` a list, the "drop and pick up" variant) it couples
    time steps and goes into a full ``Qbig`` solved by :func:`~controllers.lifted.solve_lifted`.

    Args:
        x0: ``(*B, A, 2D)`` initial ``[p_i; ṗ_i]`` of the ``A ≥ 2`` agents.
        targets: ``(*B, A, D)`` final positions.
        T, dt: horizon and time step.
        meet_times: one int in ``[1, T]`` (default ``T // 2``) or one time per agent in ``[0, T]``, at most
            one of them ``0`` (``x_0`` is fixed: a meeting of two agents at ``t = 0`` would be a no-op).

    The meeting term penalizes ``p_i - p_j`` itself at every meeting time, also at ``T`` where the target
    reference ``μ_T`` is non-zero: the problem stores ``Q = Q_target + Q_meet`` with reference ``μ`` and the
    linear term ``q = Q_meet μ`` (Eq. 59's ``2 qᵀ(x - μ)``), so that
    ``(x - μ)ᵀ Q (x - μ) + 2 qᵀ(x - μ) = (x - μ)ᵀ Q_target (x - μ) + xᵀ Q_meet x - μᵀ Q_meet μ``; the
    constant ``μᵀ Q_meet μ`` is added back in :attr:`MeetingLQT.cost`.
    """
    fn = "meeting_lqt"
    _check_float(x0, "x0", fn, 2, "(*B, A, 2D)")
    _check_float(targets, "targets", fn, 2, "(*B, A, D)")
    A, D = targets.shape[-2], targets.shape[-1]
    if A < 2 or x0.shape[-2] != A or x0.shape[-1] != 2 * D:
        raise ValueError(f"{fn}: arguments 'x0' (*B, A, 2D) and 'targets' (*B, A, D) must agree with A >= 2; "
                         f"got {tuple(x0.shape)} and {tuple(targets.shape)}")
    if x0.dtype != targets.dtype:
        raise TypeError(f"{fn}: 'x0' and 'targets' have dtypes {x0.dtype} and {targets.dtype}")
    _check_pos(T, "T", fn, integer=True)
    _check_pos(dt, "dt", fn)
    if meet_times is None:
        meet_times = T // 2
    times = [meet_times] * A if isinstance(meet_times, int) else list(meet_times)
    if len(times) != A or any(not isinstance(t, int) or isinstance(t, bool) or not 0 <= t <= T
                              for t in times):
        raise ValueError(f"{fn}: argument 'meet_times' must be an int or {A} ints in [0, {T}], "
                         f"got {meet_times!r}")
    if times.count(0) > 1:
        raise ValueError(f"{fn}: argument 'meet_times' must not have two agents meet at t = 0 (x0 is fixed, "
                         f"the meeting would be ignored); use times in [1, {T}], got {meet_times!r}")
    dtp, dev = x0.dtype, x0.device
    d1 = double_integrator(D, dt, dtp, dev)
    n1, n = 2 * D, 2 * D * A
    eyeA = torch.eye(A, dtype=dtp, device=dev)
    Ad, Bd = torch.kron(eyeA, d1.A[0]), torch.kron(eyeA, d1.B[0])
    Q = torch.zeros(T + 1, n, n, dtype=dtp, device=dev)
    Q[T] = target_weight * torch.eye(n, dtype=dtp, device=dev)
    # references only where a target is weighted (x_T); zero elsewhere, so that the meeting precision
    # penalizes p_i - p_j itself
    ref = torch.cat([targets, torch.zeros_like(targets)], -1).flatten(-2)  # (*B, n)
    x_ref = torch.cat([torch.zeros(*ref.shape[:-1], T, n, dtype=dtp, device=dev), ref.unsqueeze(-2)], -2)
    eD = torch.eye(D, dtype=dtp, device=dev)
    pos = lambda i, t: slice(t * n + i * n1, t * n + i * n1 + D)  # noqa: E731  (rows of p_i at t in x)
    # the meeting precision over the whole trajectory (pairs of time-indexed positions)
    Qm = torch.zeros((T + 1) * n, (T + 1) * n, dtype=dtp, device=dev)
    for i in range(A):
        for j in range(i + 1, A):
            a, b = pos(i, times[i]), pos(j, times[j])
            Qm[a, a] += meet_weight * eD
            Qm[b, b] += meet_weight * eD
            Qm[a, b] -= meet_weight * eD
            Qm[b, a] -= meet_weight * eD
    # penalize p_i - p_j, not its deviation from the (target) reference: linear term q = Q_meet μ
    mu = x_ref.flatten(-2)
    q = (Qm @ mu.unsqueeze(-1)).squeeze(-1).unflatten(-1, (T + 1, n))
    const = (mu * q.flatten(-2)).sum(-1)  # μᵀ Q_meet μ, left out of the problem's cost
    Qbig = None
    if len(set(times)) == 1:
        t = times[0]
        Q[t] = Q[t] + Qm[t * n:(t + 1) * n, t * n:(t + 1) * n]
    else:
        Qbig = Qm.clone()
        for t in range(T + 1):
            Qbig[t * n:(t + 1) * n, t * n:(t + 1) * n] += Q[t]
    R = control_weight * torch.eye(D * A, dtype=dtp, device=dev)
    problem = LQProblem(LinearDynamics(Ad, Bd), QuadraticCost(Q, R, x_ref=x_ref, q=q), x0.flatten(-2),
                        horizon=T)
    if Qbig is None:
        sol = riccati_solve(problem)
    else:
        sol = solve_lifted(problem, Qbig=Qbig)
    positions = sol.x.unflatten(-1, (A, n1))[..., :D]
    return MeetingLQT(problem=problem, Qbig=Qbig, solution=sol, positions=positions, cost=sol.cost + const)


# --------------------------------------------------------------------------------------------------
# bimanual tennis serve (Appendix C)
# --------------------------------------------------------------------------------------------------


class TennisServe(NamedTuple):
    """Result of :func:`tennis_serve_lqt`.

    Attributes:
        problem: the LQT problem (time-varying ``A_t``, Eq. 189-192; state ``[p_i; ṗ_i; f_i]`` for the left
            hand, the right hand and the ball, controls ``[u_1; u_2]`` the hands' accelerations).
        solution: its batch solution (Eq. 64 solved by Eq. 62, :func:`~controllers.lifted.solve_lifted`).
        positions: ``(*B, T+1, 3, 2)`` positions of left hand, right hand, ball.
        t_release, t_hit: the phase changes (``T/4``, ``T/2``).
    """

    problem: LQProblem
    solution: LiftedSolution
    positions: torch.Tensor
    t_release: int
    t_hit: int


def tennis_serve_lqt(hands0: torch.Tensor, ball_target: torch.Tensor, T: int = 100, dt: float = 0.02, *,
                     gravity: float = 9.81, target_weight: float = 1e4, hit_weight: float = 1e4,
                     control_weight: float = 1e-4) -> TennisServe:
    """The bimanual tennis serve of seed §7 / Appendix C (Fig. 17), batched.

    Three agents — left hand (1), right hand (2), ball (3) — each with state ``[p_i; ṗ_i; f_i]`` (2-D
    position, velocity and the gravity acceleration ``f_i = g`` carried as a constant state, ``ḟ_i = 0``);
    only the hands are driven (``p̈_i = u_i + f_i``).  The continuous matrices of the three phases are
    discretized with Eq. 192 (``A_t = I + A^c_t Δt``, ``B_t = B^c_t Δt``):

    * ``t < T/4`` (Eq. 189): the ball is carried by the left hand — it moves as the left hand does
      (``p̈_3 = u_1 + f_3``; it starts at the left hand's position and velocity);
    * ``t = T/2`` (Eq. 190): the right hand hits the ball — over this step the ball takes the right hand's
      velocity (``ṗ_{3,t+1} = ṗ_{2,t} + f_3 Δt``);
    * otherwise (Eq. 191): the ball flies freely under gravity (``p̈_3 = f_3``).

    The cost (Eq. 64, Appendix C): the ball at ``ball_target`` at ``T``; the hands back at their initial
    positions from ``3T/4`` to ``T``; and at ``T/2`` the precision ``hit_weight [[I, -I], [-I, I]]`` on the
    positions of the right hand and the ball, so that they coincide at a place that is not given.

    Args:
        hands0: ``(*B, 2, 2)`` initial positions of the left and right hand (at rest).
        ball_target: ``(*B, 2)``.
        T: horizon (a multiple of 4).  dt: time step.
    """
    fn = "tennis_serve_lqt"
    _check_float(hands0, "hands0", fn, 2, "(*B, 2, 2)")
    _check_float(ball_target, "ball_target", fn, 1, "(*B, 2)")
    if tuple(hands0.shape[-2:]) != (2, 2):
        raise ValueError(f"{fn}: argument 'hands0' must have shape (*B, 2, 2), got {tuple(hands0.shape)}")
    if ball_target.shape[-1] != 2:
        raise ValueError(f"{fn}: argument 'ball_target' must have shape (*B, 2), "
                         f"got {tuple(ball_target.shape)}")
    if hands0.dtype != ball_target.dtype:
        raise TypeError(f"{fn}: 'hands0' and 'ball_target' have dtypes {hands0.dtype} and "
                        f"{ball_target.dtype}")
    _check_pos(T, "T", fn, integer=True)
    if T % 4:
        raise ValueError(f"{fn}: argument 'T' must be a multiple of 4, got {T}")
    _check_pos(dt, "dt", fn)
    dtp, dev = hands0.dtype, hands0.device
    n, m = 18, 4
    I2 = torch.eye(2, dtype=dtp, device=dev)
    p, v, f = (lambda i: slice(6 * i, 6 * i + 2)), (lambda i: slice(6 * i + 2, 6 * i + 4)), \
        (lambda i: slice(6 * i + 4, 6 * i + 6))
    t_rel, t_hit = T // 4, T // 2

    def phase(kind: str) -> tuple[torch.Tensor, torch.Tensor]:
        Ac = torch.zeros(n, n, dtype=dtp, device=dev)
        Bc = torch.zeros(n, m, dtype=dtp, device=dev)
        for i in range(3):
            Ac[p(i), v(i)] = I2
            Ac[v(i), f(i)] = I2
        Bc[v(0), 0:2] = I2
        Bc[v(1), 2:4] = I2
        if kind == "carry":
            Bc[v(2), 0:2] = I2  # the ball accelerates with the left hand
        Ad, Bd = torch.eye(n, dtype=dtp, device=dev) + Ac * dt, Bc * dt
        if kind == "hit":
            Ad[v(2), v(2)] = 0.0
            Ad[v(2), v(1)] = I2  # the ball takes the right hand's velocity
        return Ad, Bd

    (Ac_, Bc_), (Af, Bf), (Ah, Bh) = phase("carry"), phase("free"), phase("hit")
    kinds = ["carry" if t < t_rel else ("hit" if t == t_hit else "free") for t in range(T)]
    A = torch.stack([{"carry": Ac_, "free": Af, "hit": Ah}[k] for k in kinds])
    B = torch.stack([{"carry": Bc_, "free": Bf, "hit": Bh}[k] for k in kinds])
    Q = torch.zeros(T + 1, n, n, dtype=dtp, device=dev)
    for t in range(3 * T // 4, T + 1):
        Q[t, p(0), p(0)] = target_weight * I2
        Q[t, p(1), p(1)] = target_weight * I2
    Q[T, p(2), p(2)] = target_weight * I2
    Q[t_hit, p(1), p(1)] += hit_weight * I2
    Q[t_hit, p(2), p(2)] += hit_weight * I2
    Q[t_hit, p(1), p(2)] = -hit_weight * I2
    Q[t_hit, p(2), p(1)] = -hit_weight * I2
    bs = torch.broadcast_shapes(hands0.shape[:-2], ball_target.shape[:-1])
    hands0, ball_target = hands0.expand(*bs, 2, 2), ball_target.expand(*bs, 2)
    g = torch.tensor([0.0, -gravity], dtype=dtp, device=dev).expand(*bs, 2)
    zero = torch.zeros(*bs, 2, dtype=dtp, device=dev)
    x0 = torch.cat([hands0[..., 0, :], zero, g, hands0[..., 1, :], zero, g, hands0[..., 0, :], zero, g], -1)
    # references where they are weighted (hands from 3T/4, the ball at T), zero at the hit, where the
    # precision penalizes p_2 - p_3 itself
    hands = torch.cat([hands0[..., 0, :], zero, zero, hands0[..., 1, :], zero, zero, zero, zero, zero], -1)
    ball = torch.cat([zero, zero, zero, zero, zero, zero, ball_target, zero, zero], -1)
    tt = torch.arange(T + 1, device=dev)
    x_ref = (torch.where((tt >= 3 * T // 4)[:, None], hands.unsqueeze(-2), 0.0)
             + torch.where((tt == T)[:, None], ball.unsqueeze(-2), 0.0))
    R = control_weight * torch.eye(m, dtype=dtp, device=dev)
    problem = LQProblem(LinearDynamics(A, B), QuadraticCost(Q, R, x_ref=x_ref), x0)
    sol = solve_lifted(problem)
    positions = sol.x.unflatten(-1, (3, 6))[..., :2]
    return TennisServe(problem=problem, solution=sol, positions=positions, t_release=t_rel, t_hit=t_hit)
