"""Error-state (tangent-space) iterated LQ planning and MPC on a :class:`~controllers.systems.MujocoSystem`,
whose ``qpos`` may hold quaternions (free and ball joints, ``nq > nv``).

The state ``x = [qpos, qvel, act]`` is a point of size ``nx``; its tangent space has size ``n = 2 nv + na``
and the system's ``oplus``/``ominus`` (``mj_integratePos``/``mj_differentiatePos``) move between them.
Nothing here adds or subtracts points: every deviation is ``x ⊖ x̄``, every update ``x̄ ⊕ δx``, and the
Jacobians ``A_t = ∂x_{t+1}/∂δx_t``, ``B_t`` are the system's tangent Jacobians
(:meth:`~controllers.systems.MujocoSystem.trajectory_jacobians`).

**Problem** (this package's cost convention, no ½)::

    min_u  Σ_{t<T} ‖r(x_t)‖²_Q + ‖u_t − u_ref,t‖²_R + ‖r(x_T)‖²_{Q_T}     u_lower ≤ u_t ≤ u_upper,
    x_{t+1} = step(x_t, u_t),  x_0 given,

with the residual ``r(x) = x ⊖ x_ref`` (``residual='manifold'``, size ``n``: the principal rotation vector
of each quaternion error, angle ≤ π, so ``q`` and ``−q`` are one attitude) or, for comparison only,
``r(x) = x − x_ref`` on the raw point coordinates (``residual='euclidean'``, size ``nx``: the quaternion's
four numbers treated as a vector, which is what planning on ``qpos`` as if it were Euclidean amounts to).

**Iteration** (Gauss–Newton on the controls, the iterated error-state MPC of seed 003 §V-D with the
MuJoCo model's FD Jacobians):

1. roll the current controls ``ū`` out: ``x̄ = rollout(x_0, ū)`` (one batched call; so the error system
   has no drift term and ``δx_0 = 0``);
2. ``A_t, B_t`` along ``(x̄, ū)`` (one batched Jacobian call) and the residual model
   ``r(x̄_t ⊕ δx_t) ≈ r̄_t + J_t δx_t`` (``J_t`` by autograd through ``⊕``/``⊖``: for a quaternion the
   inverse right Jacobian of ``log``, not the identity, which matters at large attitude errors);
3. condense ``δX = S_u δU`` (:func:`controllers.lifted.transfer_matrices`) and solve the box QP in the
   ``T m`` control changes with limits ``u_lower − ū ≤ δU ≤ u_upper − ū``
   (:func:`controllers.boxqp.box_qp`, batched);
4. a backtracking line search on the *true* cost: all step sizes ``α ∈ {1, ½, …, 2⁻⁹}`` rolled out in one
   call, the best one that lowers the cost is taken, per element;
5. an element stops ``converged`` when the model about its current point predicts a decrease of at most
   ``tol`` times its cost (the Gauss–Newton gap, zero at a KKT point of the constrained problem) or the
   accepted step lowered the cost by less than that; ``stalled`` when no step size lowers the cost or
   the box QP failed (a NaN step: a non-finite state, Jacobian or cost of that element; the others go
   on).

Everything is batched over the leading dims of ``x0`` (and of ``x_ref``, ``u_ref``, ``u_init``), with no
Python loop over elements; an element's result does not depend on the others except through round-off
of the batched products, which the iteration can amplify along directions where the cost is flat
(measured on the free body of ``examples/mujoco_free_body_mpc.py``: batched vs one-at-a-time, the same
iteration counts and costs to 1e-12 relative, controls within 2.4e-6 of limits ±20/±0.1).

**Not done:** gradients (the planner runs under ``no_grad``; use
:func:`controllers.ilqr.ilqr` on a Euclidean model for implicit gradients), per-element weights (``Q``,
``R`` are shared), state constraints, and a second-order (DDP) dynamics term.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from controllers.boxqp import box_qp
from controllers.lifted import transfer_matrices
from torchlie._batch import broadcast_shapes

__all__ = ["TangentPlan", "TangentILQR"]

_ALPHAS = tuple(0.5 ** k for k in range(10))


@dataclass
class TangentPlan:
    """Result of :meth:`TangentILQR.solve` (batch dims ``*B`` of the broadcast inputs).

    Attributes:
        u: ``(*B, T, m)`` the planned controls (within the limits).
        x: ``(*B, T+1, nx)`` their rollout from ``x0`` (points: unit quaternions, as MuJoCo keeps them).
        cost: ``(*B,)`` the true cost of ``(x, u)``.
        iterations: ``(*B,)`` accepted Gauss–Newton steps.
        converged: ``(*B,)`` the element stopped on the ``tol`` test (module docstring).
        stalled: ``(*B,)`` the element stopped because no step size lowered its cost.
    """

    u: Tensor
    x: Tensor
    cost: Tensor
    iterations: Tensor
    converged: Tensor
    stalled: Tensor


def _weight(W, size: int, name: str) -> Tensor:
    W = torch.as_tensor(W, dtype=torch.float64)
    if W.dim() == 1:
        W = torch.diag(W)
    if W.shape != (size, size) or not torch.isfinite(W).all():
        raise ValueError(f"TangentILQR: argument '{name}' must be finite of shape ({size}, {size}) or its "
                         f"diagonal ({size},), got {tuple(W.shape)}")
    if not torch.allclose(W, W.mT) or torch.linalg.eigvalsh(W).min() < 0:
        raise ValueError(f"TangentILQR: argument '{name}' must be symmetric positive semidefinite")
    return W


class TangentILQR:
    """Batched tangent-space iterated LQ planner / MPC for a :class:`~controllers.systems.MujocoSystem`
    (module docstring).

    Args:
        system: the model (needs ``nx``, ``n``, ``m``, ``oplus``, ``ominus``, ``rollout_states``,
            ``trajectory_jacobians``, ``ctrl_lower``/``ctrl_upper``).
        Q, R: stage weights ``(r, r)`` and ``(m, m)`` (or their diagonals), ``r = n`` for
            ``residual='manifold'``, ``nx`` for ``'euclidean'``; ``Q`` PSD, ``R`` positive definite.
        horizon: ``T >= 1`` steps of ``system.dt``.
        Q_terminal: the weight of ``r(x_T)`` (default ``Q``).
        u_lower, u_upper: ``(m,)`` limits (default: the model's ``ctrlrange`` where limited, else ±inf).
        max_iter: Gauss–Newton iterations at most per :meth:`solve`.
        tol: relative stopping test (module docstring).
        residual: ``'manifold'`` (default) or ``'euclidean'`` (the naive comparison).
    """

    def __init__(self, system, Q, R, horizon: int, *, Q_terminal=None, u_lower=None, u_upper=None,
                 max_iter: int = 20, tol: float = 1e-6, residual: str = "manifold") -> None:
        for attr in ("oplus", "ominus", "rollout_states", "trajectory_jacobians", "nx", "n", "m"):
            if not hasattr(system, attr):
                raise TypeError(f"TangentILQR: argument 'system' must be a MujocoSystem-like model with "
                                f"'{attr}', got {type(system).__name__}")
        if residual not in ("manifold", "euclidean"):
            raise ValueError(f"TangentILQR: argument 'residual' must be 'manifold' or 'euclidean', "
                             f"got {residual!r}")
        if isinstance(horizon, bool) or not isinstance(horizon, int) or horizon < 1:
            raise ValueError(f"TangentILQR: argument 'horizon' must be an int >= 1, got {horizon!r}")
        if isinstance(max_iter, bool) or not isinstance(max_iter, int) or max_iter < 1:
            raise ValueError(f"TangentILQR: argument 'max_iter' must be an int >= 1, got {max_iter!r}")
        if not isinstance(tol, (int, float)) or not tol > 0:
            raise ValueError(f"TangentILQR: argument 'tol' must be a positive float, got {tol!r}")
        self.system, self.horizon, self.max_iter, self.tol, self.residual = (
            system, horizon, max_iter, float(tol), residual)
        r = system.n if residual == "manifold" else system.nx
        self.Q = _weight(Q, r, "Q")
        self.Q_terminal = self.Q if Q_terminal is None else _weight(Q_terminal, r, "Q_terminal")
        self.R = _weight(R, system.m, "R")
        if torch.linalg.eigvalsh(self.R).min() <= 0:
            raise ValueError("TangentILQR: argument 'R' must be positive definite")
        lo = getattr(system, "ctrl_lower", None) if u_lower is None else u_lower
        hi = getattr(system, "ctrl_upper", None) if u_upper is None else u_upper
        inf = torch.full((system.m,), float("inf"), dtype=torch.float64)
        lims = []
        for name, v, default in (("u_lower", lo, -inf), ("u_upper", hi, inf)):
            v = default if v is None else torch.as_tensor(v, dtype=torch.float64).cpu()
            if v.dim() > 1 or v.numel() not in (1, system.m) or v.isnan().any():
                raise ValueError(f"TangentILQR: argument '{name}' must be a number or ({system.m},) without "
                                 f"NaN, got shape {tuple(v.shape)}")
            lims.append(v.expand(system.m))
        self.u_lower, self.u_upper = lims
        if not (self.u_lower <= self.u_upper).all():
            raise ValueError("TangentILQR: arguments 'u_lower' <= 'u_upper' must hold componentwise")

    # ------------------------------------------------------------------------------------------------

    def residuals(self, x: Tensor, x_ref: Tensor) -> Tensor:
        """``r(x) (*, r)``: ``x ⊖ x_ref`` or ``x − x_ref`` (``residual``)."""
        return self.system.ominus(x, x_ref) if self.residual == "manifold" else x - x_ref

    def cost(self, x: Tensor, u: Tensor, x_ref: Tensor, u_ref: Tensor) -> Tensor:
        """The true cost ``(*B,)`` of ``x (*B, T+1, nx)``, ``u (*B, T, m)`` (module docstring)."""
        r = self.residuals(x, x_ref)
        Q, QT, R = (W.to(x.dtype) for W in (self.Q, self.Q_terminal, self.R))
        stage = ((r[..., :-1, :] @ Q) * r[..., :-1, :]).sum((-1, -2))
        term = ((r[..., -1, :] @ QT) * r[..., -1, :]).sum(-1)
        du = u - u_ref
        return stage + term + ((du @ R) * du).sum((-1, -2))

    def _residual_model(self, x: Tensor, x_ref: Tensor) -> tuple[Tensor, Tensor]:
        """``r̄ (*B, T+1, r)`` and ``J = ∂r(x̄ ⊕ δ)/∂δ|₀ (*B, T+1, r, n)`` (autograd, one pass per row)."""
        sysm = self.system
        with torch.enable_grad():
            d = torch.zeros(*x.shape[:-1], sysm.n, dtype=x.dtype, device=x.device, requires_grad=True)
            out = self.residuals(sysm.oplus(x, d), x_ref)
            rows = [torch.autograd.grad(out[..., i].sum(), d, retain_graph=i + 1 < out.shape[-1])[0]
                    for i in range(out.shape[-1])]
        return out.detach(), torch.stack(rows, -2)

    def solve(self, x0: Tensor, x_ref: Tensor, u_ref: Tensor | None = None,
              u_init: Tensor | None = None, *, trajectory: bool = False) -> TangentPlan:
        """Plan from ``x0 (*B, nx)`` to ``x_ref`` (``(*B, nx)``: a goal held over the horizon, or with
        ``trajectory=True`` ``(*B, T+1, nx)``: a reference trajectory), ``u_ref`` (``(m,)`` or
        ``(*B, T, m)``; default 0), starting from ``u_init`` (``(*B, T, m)``; default ``u_ref`` clipped to
        the limits).  Tensors on one device (MuJoCo runs on the CPU); results follow ``x0``'s dtype."""
        T, m, nx = self.horizon, self.system.m, self.system.nx
        if not isinstance(x0, Tensor) or x0.shape[-1:] != (nx,):
            raise ValueError(f"TangentILQR.solve: argument 'x0' must be a tensor (*B, {nx}), got "
                             f"{tuple(x0.shape) if isinstance(x0, Tensor) else type(x0).__name__}")
        dt = x0.dtype
        x_ref = torch.as_tensor(x_ref, dtype=dt)
        dev = x0.device
        x_ref = torch.as_tensor(x_ref, dtype=dt, device=dev)
        if trajectory and (x_ref.dim() < 2 or x_ref.shape[-2:] != (T + 1, nx)):
            raise ValueError(f"TangentILQR.solve: argument 'x_ref' must have shape (*B, {T + 1}, {nx}) with "
                             f"trajectory=True, got {tuple(x_ref.shape)}")
        if x_ref.shape[-1:] != (nx,):
            raise ValueError(f"TangentILQR.solve: argument 'x_ref' must have shape (*B, {nx}), "
                             f"got {tuple(x_ref.shape)}")
        if not trajectory:
            x_ref = x_ref.unsqueeze(-2)
        u_ref = (torch.zeros(m, dtype=dt, device=dev) if u_ref is None
                 else torch.as_tensor(u_ref, dtype=dt, device=dev))
        if u_ref.shape[-1:] != (m,) or (u_ref.dim() >= 2 and u_ref.shape[-2] != T):
            raise ValueError(f"TangentILQR.solve: argument 'u_ref' must have shape ({m},) or (*B, {T}, {m}), "
                             f"got {tuple(u_ref.shape)}")
        # the limits in x0's dtype, rounded inwards: float32's 0.1 is above float64's, and a control on such a
        # limit would lie outside the model's ctrlrange, where MuJoCo clamps it and its Jacobian column is 0
        lo, hi = self.u_lower.to(dt), self.u_upper.to(dt)
        lo, hi = (torch.where(lo.double() < self.u_lower, torch.nextafter(lo, hi), lo).to(dev),
                  torch.where(hi.double() > self.u_upper, torch.nextafter(hi, lo), hi).to(dev))
        if u_init is not None:
            if not isinstance(u_init, Tensor) or u_init.shape[-2:] != (T, m):
                got = tuple(u_init.shape) if isinstance(u_init, Tensor) else type(u_init).__name__
                raise ValueError(f"TangentILQR.solve: argument 'u_init' must be a tensor (*B, {T}, {m}), "
                                 f"got {got}")
            u_init = u_init.to(dtype=dt, device=dev)
        bs = broadcast_shapes(x0.shape[:-1], x_ref.shape[:-2],
                              u_ref.shape[:-2] if u_ref.dim() >= 2 else torch.Size(),
                              u_init.shape[:-2] if u_init is not None else torch.Size())
        if u_init is None:
            u_init = u_ref.expand(*bs, T, m)
        with torch.no_grad():
            return self._solve(x0.expand(*bs, nx), x_ref, u_ref, torch.clamp(u_init, lo, hi).expand(*bs, T, m)
                               .clone(), lo, hi, bs)

    def _solve(self, x0, x_ref, u_ref, U, lo, hi, bs) -> TangentPlan:
        sysm, T, m, n = self.system, self.horizon, self.system.m, self.system.n
        kw = dict(dtype=x0.dtype, device=x0.device)
        Q, QT, R = (W.to(**kw) for W in (self.Q, self.Q_terminal, self.R))
        Qs = torch.cat([Q.expand(T, *Q.shape), QT[None]], 0)  # (T+1, r, r)
        X = sysm.rollout_states(x0, U)
        J0 = self.cost(X, U, x_ref, u_ref)
        active = torch.ones(bs, dtype=torch.bool, device=x0.device)
        converged, stalled = torch.zeros_like(active), torch.zeros_like(active)
        iters = torch.zeros(bs, dtype=torch.long, device=x0.device)
        alphas = torch.tensor(_ALPHAS, **kw)
        for _ in range(self.max_iter):
            if not active.any():
                break
            A, B = sysm.trajectory_jacobians(X, U)  # (*B, T, n, n), (*B, T, n, m)
            rbar, Jr = self._residual_model(X, x_ref)
            _, Su, _ = transfer_matrices(A, B)  # (*B, (T+1) n, T m)
            Su = Su.reshape(*bs, T + 1, n, T * m)
            W = Jr.mT @ Qs @ Jr  # (*B, T+1, n, n)
            w = (Jr.mT @ (Qs @ rbar.unsqueeze(-1))).squeeze(-1)  # (*B, T+1, n)
            Rb = torch.block_diag(*([R] * T))
            H = 2 * (torch.einsum("...tia,...tij,...tjb->...ab", Su, W, Su) + Rb)
            g = 2 * (torch.einsum("...tia,...ti->...a", Su, w)
                     + ((U - u_ref) @ R).reshape(*bs, T * m))
            H = 0.5 * (H + H.mT)
            res = box_qp(H, g, (lo - U).reshape(*bs, T * m), (hi - U).reshape(*bs, T * m), check=False)
            qp_ok = torch.isfinite(res.x).all(-1)  # a failed QP (NaN step) stops the element, stalled
            s = torch.nan_to_num(res.x)
            dU = s.reshape(*bs, T, m)
            pred = -(g * s).sum(-1) - 0.5 * (s.unsqueeze(-2) @ H @ s.unsqueeze(-1))[..., 0, 0]
            small = qp_ok & (pred <= self.tol * J0)
            # line search: all step sizes in one rollout call
            Uc = torch.clamp(U.unsqueeze(-3) + alphas[:, None, None] * dU.unsqueeze(-3), lo, hi)
            Xc = sysm.rollout_states(x0.unsqueeze(-2), Uc)  # (*B, K, T+1, nx)
            Jc = self.cost(Xc, Uc, x_ref.unsqueeze(-3), u_ref.unsqueeze(-3) if u_ref.dim() >= 2 else u_ref)
            Jc = torch.nan_to_num(Jc, nan=float("inf"))
            Jbest, k = Jc.min(-1)
            better = Jbest < J0
            take = active & better & ~small & qp_ok
            idx = k[..., None, None, None]
            U = torch.where(take[..., None, None], Uc.gather(-3, idx.expand(*bs, 1, T, m)).squeeze(-3), U)
            X = torch.where(take[..., None, None],
                            Xc.gather(-3, idx.expand(*bs, 1, T + 1, sysm.nx)).squeeze(-3), X)
            tiny = take & (J0 - Jbest <= self.tol * J0)
            J0 = torch.where(take, Jbest, J0)
            iters += take.long()
            converged |= active & (small | tiny)
            stalled |= active & ~small & (~better | ~qp_ok)
            active &= take & ~tiny
        return TangentPlan(u=U, x=X, cost=J0, iterations=iters, converged=converged, stalled=stalled)

    def control(self, x: Tensor, x_ref: Tensor, u_ref: Tensor | None = None, warm: Tensor | None = None
                ) -> tuple[Tensor, TangentPlan]:
        """One MPC step: :meth:`solve` from ``x`` warm-started with the last plan ``warm (*B, T, m)`` shifted
        by one step (its last control repeated); returns the first control ``(*B, m)`` and the plan."""
        u_init = None if warm is None else torch.cat([warm[..., 1:, :], warm[..., -1:, :]], -2)
        plan = self.solve(x, x_ref, u_ref, u_init)
        return plan.u[..., 0, :], plan
