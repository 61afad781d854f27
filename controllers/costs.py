"""Costs: the :class:`Cost` protocol, the quadratic and residual costs, and their derivatives.

**One cost convention for the whole package** (seed 004 Eq. 59): a cost is a plain sum of per-step terms,
*without* a factor ½, and a quadratic one has its linear terms with a factor 2::

    l_t = dx_tᵀ Q_t dx_t + du_tᵀ R_t du_t + 2 dx_tᵀ N_t du_t + 2 q_tᵀ dx_t + 2 r_tᵀ du_t
    l_T = dx_Tᵀ Q_T dx_T + 2 q_Tᵀ dx_T,        dx_t = x_t - μ_t,  du_t = u_t - ν_t

(shapes in :mod:`controllers.problem`).  Every solver reports this value (``solution.cost``), and every
LQ kernel takes the *coefficients* ``Q, R, N, q, r`` of this form.  Derivatives are plain derivatives:
``g = ∇l``, ``H = ∇²l`` (so ``H_xx = 2Q`` for a :class:`QuadraticCost`), and iLQR's local model is the
Taylor expansion ``l(z + δ) ≈ l + gᵀδ + ½ δᵀHδ``.  The one place where derivatives become the
coefficients of an LQ problem is :func:`lq_coefficients` (``Q = ½H``, ``q = ½g``).

A **cost** is anything with ``evaluate(x (*B, T+1, n), u (*B, T, m)) -> (*B,)`` that is a sum of per-step
terms (no mixing across time or batch), optionally with ``derivatives(x, u) -> (gx, gu, Hxx, Hux,
Huu)``; without it :func:`cost_derivatives` differentiates ``evaluate`` by autograd (exact Hessian blocks,
one double-backward per coordinate).  :class:`QuadraticCost` has exact analytic derivatives;
:class:`ResidualCost` ``Σ f(x)ᵀQf(x) + uᵀRu`` has the Gauss–Newton ones (Eq. 104-105).

Checks: shapes, dtypes and devices are validated at construction; an error names the field and the
expected shape.  Weights follow one rule for every solver (:func:`controllers._validate.check_weight`):
a Q or R shared by the whole batch (no batch dims) that has NaN/inf entries, is not symmetric, or is not
PSD (Q) / PD (R) is a ``ValueError`` at construction; when Q or R carries batch dims,
:meth:`QuadraticCost.finite_mask` and :meth:`QuadraticCost.definite_mask` give the per-element verdict
and the solvers report the failing elements (``Reason.NONFINITE_INPUT``, else
``Reason.NOT_POSITIVE_DEFINITE``) instead of raising.
Nothing is memoized on a cost object: what a solver may reuse across solves is an explicit value the
caller holds (:func:`controllers.riccati.prepare`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import torch
from torch import Tensor, nn

from controllers._validate import (
    all_finite,
    batch_dims,
    check_tensor,
    check_time,
    check_weight,
    expand_time_dim,
    same_dtype_device,
    time_sum,
    timed,
)
from torchlie._batch import broadcast_shapes

__all__ = [
    "Cost",
    "QuadraticCost",
    "CanonicalCost",
    "ResidualCost",
    "PeriodicQuadraticCost",
    "stand_in_cost",
    "cost_derivatives",
    "autograd_derivatives",
    "hessian_rows",
    "lq_coefficients",
    "DiagonalQuadraticCost",
]


@runtime_checkable
class Cost(Protocol):
    """A trajectory cost (module docstring): ``evaluate(x, u) -> (*B,)``, optionally ``derivatives``."""

    def evaluate(self, x: Tensor, u: Tensor) -> Tensor: ...


@dataclass(frozen=True, eq=False)
class CanonicalCost:
    """``Σ_t xᵀQx + uᵀRu + 2xᵀNu + 2qᵀx + 2rᵀu + const`` (references expanded); ``N``/``r`` may be None.

    Shapes as in :class:`QuadraticCost` (explicit time dims); ``const (*B,)`` or a 0-dim tensor.
    """

    Q: torch.Tensor
    R: torch.Tensor
    q: torch.Tensor | None
    r: torch.Tensor | None
    N: torch.Tensor | None
    const: torch.Tensor


@dataclass(frozen=True, eq=False)
class QuadraticCost:
    """Quadratic tracking cost (module docstring; seed 004 Eq. 59 with full precision matrices).

    Args:
        Q: ``(*B, T+1, n, n)``, ``(*B, 1, n, n)`` or ``(n, n)``; symmetric PSD.
        R: ``(*B, T, m, m)``, ``(*B, 1, m, m)`` or ``(m, m)``; symmetric PD.
        x_ref: μ, ``(*B, T+1, n)`` / ``(*B, 1, n)`` / ``(n,)``.
        u_ref: ν, ``(*B, T, m)`` / ``(*B, 1, m)`` / ``(m,)``.
        N: cross term ``(*B, T, n, m)`` / ``(n, m)``.
        q, r: linear terms on the deviations, ``(*B, T+1, n)`` and ``(*B, T, m)``.
        check: verify symmetry and (for matrices shared by the batch) definiteness at construction.
    """

    Q: torch.Tensor
    R: torch.Tensor
    x_ref: torch.Tensor | None = None
    u_ref: torch.Tensor | None = None
    N: torch.Tensor | None = None
    q: torch.Tensor | None = None
    r: torch.Tensor | None = None
    check: bool = field(default=True, repr=False)

    def __post_init__(self) -> None:
        own = "QuadraticCost"
        Q = timed(self.Q, (None, None), "Q", own, "(*B, T+1, n, n) or (n, n)")
        n = Q.shape[-1]
        if Q.shape[-2] != n:
            raise ValueError(f"{own}: field 'Q' must be square (*B, T+1, n, n), got {tuple(self.Q.shape)}")
        R = timed(self.R, (None, None), "R", own, "(*B, T, m, m) or (m, m)")
        m = R.shape[-1]
        if R.shape[-2] != m:
            raise ValueError(f"{own}: field 'R' must be square (*B, T, m, m), got {tuple(self.R.shape)}")
        opt = {}
        if self.x_ref is not None:
            opt["x_ref"] = timed(self.x_ref, (n,), "x_ref", own, f"(*B, T+1, {n}) or ({n},)")
        if self.u_ref is not None:
            opt["u_ref"] = timed(self.u_ref, (m,), "u_ref", own, f"(*B, T, {m}) or ({m},)")
        if self.N is not None:
            opt["N"] = timed(self.N, (n, m), "N", own, f"(*B, T, {n}, {m}) or ({n}, {m})")
        if self.q is not None:
            opt["q"] = timed(self.q, (n,), "q", own, f"(*B, T+1, {n}) or ({n},)")
        if self.r is not None:
            opt["r"] = timed(self.r, (m,), "r", own, f"(*B, T, {m}) or ({m},)")
        same_dtype_device(own, Q=Q, R=R, **opt)
        # horizons: state-indexed fields have T+1 entries, control-indexed ones T
        Ts = {"R": R.shape[-3]}
        for k in ("u_ref", "N", "r"):
            if k in opt:
                Ts[k] = opt[k].shape[-2 if k != "N" else -3]
        Tx = {"Q": Q.shape[-3]}
        for k in ("x_ref", "q"):
            if k in opt:
                Tx[k] = opt[k].shape[-2]
        T_from_u = max(Ts.values())
        T_from_x = max(Tx.values()) - 1
        T = max(T_from_u, T_from_x)
        if T >= 1:
            check_time(Ts, T, own, "control-indexed fields R, u_ref, N, r have T entries")
            check_time(Tx, T + 1, own, "state-indexed fields Q, x_ref, q have T+1 entries")
        trailing = {"Q": 2, "R": 2, "x_ref": 1, "u_ref": 1, "N": 2, "q": 1, "r": 1}
        allf = {"Q": Q, "R": R, **opt}
        try:
            broadcast_shapes(*[batch_dims(v, trailing[k]) for k, v in allf.items()])
        except RuntimeError as e:
            shapes = ", ".join(f"{k} {tuple(v.shape)}" for k, v in allf.items())
            raise ValueError(f"{own}: batch dims do not broadcast: {shapes}") from e
        object.__setattr__(self, "Q", Q)
        object.__setattr__(self, "R", R)
        for k, v in opt.items():
            object.__setattr__(self, k, v)
        if self.check:
            # shared weights (no batch dims): a defect is a ValueError; batched ones: per element
            # (definite_mask / finite_mask, reported by the solvers)
            if Q.dim() == 3:
                check_weight(Q, "Q", own, strict=False, shared=True)
            if R.dim() == 3:
                check_weight(R, "R", own, strict=True, shared=True)

    # ---- properties
    @property
    def n(self) -> int:
        return self.Q.shape[-1]

    @property
    def m(self) -> int:
        return self.R.shape[-1]

    @property
    def horizon(self) -> int | None:
        """``T`` if any field is time-varying (a time dim > 1), else ``None``."""
        T = 0
        for k, d in (("R", -3), ("u_ref", -2), ("N", -3), ("r", -2)):
            v = getattr(self, k)
            if v is not None and v.shape[d] > 1:
                T = max(T, v.shape[d])
        for k, d in (("Q", -3), ("x_ref", -2), ("q", -2)):
            v = getattr(self, k)
            if v is not None and v.shape[d] > 1:
                T = max(T, v.shape[d] - 1)
        return T if T >= 1 else None

    @property
    def batch_shape(self) -> torch.Size:
        tr = {"Q": 2, "R": 2, "x_ref": 1, "u_ref": 1, "N": 2, "q": 1, "r": 1}
        return broadcast_shapes(*[batch_dims(getattr(self, k), d) for k, d in tr.items()
                                        if getattr(self, k) is not None])

    @property
    def dtype(self) -> torch.dtype:
        return self.Q.dtype

    @property
    def device(self) -> torch.device:
        return self.Q.device

    # ---- constructors
    @staticmethod
    def via_points(T: int, times: list[int] | torch.Tensor, targets: torch.Tensor, precision: torch.Tensor,
                   R: torch.Tensor) -> QuadraticCost:
        """Sparse via-point cost: precision zero except at ``times`` (ints in ``[0, T]``).

        Args:
            targets: ``(*B, K, n)`` via points (one per time in ``times``).
            precision: ``(n, n)``, ``(K, n, n)`` or ``(*B, K, n, n)``: the precision at each via point.
            R: control weight as in :class:`QuadraticCost`.
        """
        own = "QuadraticCost.via_points"
        times_t = torch.as_tensor(times, dtype=torch.int64).reshape(-1)
        K = times_t.numel()
        check_tensor(targets, "targets", own)
        if targets.dim() < 2 or targets.shape[-2] != K:
            raise ValueError(f"{own}: argument 'targets' must have shape (*B, {K}, n) "
                             f"for {K} via-point times, "
                             f"got {tuple(targets.shape)}")
        if bool(((times_t < 0) | (times_t > T)).any()):
            raise ValueError(f"{own}: argument 'times' must lie in [0, {T}], got {times_t.tolist()}")
        if times_t.unique().numel() != K:
            raise ValueError(f"{own}: argument 'times' must not repeat, got {times_t.tolist()}")
        n = targets.shape[-1]
        check_tensor(precision, "precision", own)
        if precision.shape[-2:] != (n, n):
            raise ValueError(f"{own}: argument 'precision' must have shape (*B, {K}, {n}, {n}) "
                             f"or ({n}, {n}), "
                             f"got {tuple(precision.shape)}")
        if precision.dim() == 2:
            precision = precision.expand(K, n, n)
        dev, dt = targets.device, targets.dtype
        batch = broadcast_shapes(targets.shape[:-2], precision.shape[:-3])
        Q = torch.zeros(*batch, T + 1, n, n, dtype=dt, device=dev)
        mu = torch.zeros(*batch, T + 1, n, dtype=dt, device=dev)
        idx = times_t.to(dev)
        Q = Q.index_copy(-3, idx, precision.expand(*batch, K, n, n).to(dt))
        mu = mu.index_copy(-2, idx, targets.expand(*batch, K, n))
        return QuadraticCost(Q=Q, R=R, x_ref=mu)

    # ---- evaluation
    def canonical(self, T: int) -> CanonicalCost:
        """Expand the references for horizon ``T``:
        ``Σ dxᵀQdx + ... = Σ xᵀQx + uᵀRu + 2xᵀNu + 2q'ᵀx + 2r'ᵀu + const``.

        ``Q``, ``R``, ``N`` keep their (possibly broadcast) time dims; ``q'``/``r'`` get full time dims
        ``T+1``/``T`` when a reference or linear term is present (else ``None``); ``const (*B,)``.
        """
        Q, R, N = self.Q, self.R, self.N
        mu, nu = expand_time_dim(self.x_ref, T + 1, 1), expand_time_dim(self.u_ref, T, 1)
        q, r = expand_time_dim(self.q, T + 1, 1), expand_time_dim(self.r, T, 1)
        const = torch.zeros((), dtype=Q.dtype, device=Q.device)
        qc, rc = q, r
        if mu is not None:
            Qmu = (Q @ mu.unsqueeze(-1)).squeeze(-1)
            qc = -Qmu if qc is None else qc - Qmu
            const = const + (mu * Qmu).sum((-1, -2))
            if q is not None:
                const = const - 2 * (q * mu).sum((-1, -2))
        if nu is not None:
            Rnu = (R @ nu.unsqueeze(-1)).squeeze(-1)
            rc = -Rnu if rc is None else rc - Rnu
            const = const + (nu * Rnu).sum((-1, -2))
            if r is not None:
                const = const - 2 * (r * nu).sum((-1, -2))
        if N is not None:
            # 2(x-μ)ᵀN(u-ν) = 2xᵀNu - 2(Nν)ᵀx - 2(Nᵀμ)ᵀu + 2μᵀNν   (μ on steps 0..T-1)
            if nu is not None:
                Nnu = (N @ nu.unsqueeze(-1)).squeeze(-1)
                Nnu = torch.cat([Nnu, torch.zeros_like(Nnu[..., :1, :])], dim=-2)
                qc = -Nnu if qc is None else qc - Nnu
            if mu is not None:
                NTmu = (N.mT @ mu[..., :-1, :].unsqueeze(-1)).squeeze(-1)
                rc = -NTmu if rc is None else rc - NTmu
                if nu is not None:
                    const = const + 2 * (NTmu * nu).sum((-1, -2))
        return CanonicalCost(Q=Q, R=R, q=qc, r=rc, N=N, const=const)

    def evaluate(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """Total cost ``(*B,)`` of a trajectory ``x (*B, T+1, n)``, ``u (*B, T, m)``."""
        T = u.shape[-2]
        if x.shape[-2] != T + 1:
            raise ValueError(f"QuadraticCost.evaluate: x must have T+1 = {T + 1} steps, got {tuple(x.shape)}")
        dx = x if self.x_ref is None else x - self.x_ref
        du = u if self.u_ref is None else u - self.u_ref
        c = (dx.unsqueeze(-2) @ self.Q @ dx.unsqueeze(-1)).squeeze(-1).squeeze(-1)
        c = time_sum(c, T + 1)
        cu = (du.unsqueeze(-2) @ self.R @ du.unsqueeze(-1)).squeeze(-1).squeeze(-1)
        c = c + time_sum(cu, T)
        if self.N is not None:
            cn = (dx[..., :-1, :].unsqueeze(-2) @ self.N @ du.unsqueeze(-1)).squeeze(-1).squeeze(-1)
            c = c + 2 * time_sum(cn, T)
        if self.q is not None:
            c = c + 2 * time_sum((self.q * dx).sum(-1), T + 1)
        if self.r is not None:
            c = c + 2 * time_sum((self.r * du).sum(-1), T)
        return c

    def derivatives(self, x: torch.Tensor, u: torch.Tensor):
        """Exact derivatives ``(gx, gu, Hxx, Hux, Huu)`` along ``x (*B, T+1, n)``, ``u (*B, T, m)`` (module
        docstring: ``H = 2Q`` with this package's convention), batch first; ``Hux`` is None without N."""
        T = u.shape[-2]
        dx = x if self.x_ref is None else x - self.x_ref
        du = u if self.u_ref is None else u - self.u_ref
        gx = 2 * (self.Q @ dx.unsqueeze(-1)).squeeze(-1)
        gu = 2 * (self.R @ du.unsqueeze(-1)).squeeze(-1)
        if self.q is not None:
            gx = gx + 2 * self.q
        if self.r is not None:
            gu = gu + 2 * self.r
        Hux = None
        if self.N is not None:
            Nd = 2 * (self.N @ du.unsqueeze(-1)).squeeze(-1)
            gx = gx + torch.cat([Nd, torch.zeros_like(Nd[..., :1, :])], -2)
            gu = gu + 2 * (self.N.mT @ dx[..., :T, :].unsqueeze(-1)).squeeze(-1)
            Hux = 2 * self.N.mT
        return gx, gu, 2 * self.Q, Hux, 2 * self.R

    def definite_mask(self) -> torch.Tensor:
        """``(*B,)`` bool: Q_t symmetric ⪰ 0 and R_t symmetric ≻ 0 at every time step of each batch element
        (:func:`controllers._validate.check_weight`; computed on every call; to reuse it across solves, hold
        the :func:`controllers.riccati.prepare` value)."""
        q = check_weight(self.Q, "Q", "QuadraticCost", strict=False, shared=False)[1]
        r = check_weight(self.R, "R", "QuadraticCost", strict=True, shared=False)[1]
        return q.all(-1) & r.all(-1)

    def finite_mask(self) -> torch.Tensor:
        """``(*B,)`` bool: every field of the element is finite."""
        trc = {"Q": 3, "R": 3, "x_ref": 2, "u_ref": 2, "N": 3, "q": 2, "r": 2}
        fin = torch.ones((), dtype=torch.bool, device=self.device)
        for k, d in trc.items():
            v = getattr(self, k)
            if v is not None:
                fin = fin & all_finite(v, d)
        return fin


@dataclass(frozen=True, eq=False)
class ResidualCost:
    """Quadratic cost on a residual of the state (seed 004 §9, Eq. 102 and 106)::

        c(x, u) = Σ_{t=0}^{T} f(x_t)ᵀ Q_t f(x_t) + Σ_{t=0}^{T-1} u_tᵀ R_t u_t

    with Gauss-Newton derivatives (Eq. 104-105): ``g_x = 2 Jᵀ Q f``, ``H_xx ≈ 2 Jᵀ Q J``, ``g_u = 2 R u``,
    ``H_uu = 2 R``; with them the batch iLQR step is Eq. 108.  (Implicit gradients use exact Hessians.)

    Args:
        residual: ``f(x (*B, T+1, n)) -> (*B, T+1, p)``, applied per time step (no mixing across time or
            batch), e.g. ``f(x) = f_ee(x) - μ`` for a reaching task.
        Q: ``(p, p)``, ``(T+1, p, p)`` or ``(*B, T+1, p, p)`` precision (zero at non-via-point times).
        R: ``(m, m)``, ``(T, m, m)`` or ``(*B, T, m, m)``.
        jacobian: optional ``J(x (*B, T+1, n)) -> (*B, T+1, p, n)``; autograd otherwise.
    """

    residual: Callable[[Tensor], Tensor]
    Q: Tensor
    R: Tensor
    jacobian: Callable[[Tensor], Tensor] | None = None

    def __post_init__(self) -> None:
        if not callable(self.residual):
            raise TypeError("ResidualCost: field 'residual' must be callable f(x) -> (*B, T+1, p)")
        for name in ("Q", "R"):
            v = getattr(self, name)
            if not isinstance(v, Tensor) or v.dim() < 2 or v.shape[-1] != v.shape[-2]:
                raise ValueError(f"ResidualCost: field '{name}' must be a square (*B, T, k, k) or (k, k) "
                                 "tensor")

    def _jac(self, x: Tensor) -> tuple[Tensor, Tensor]:
        if self.jacobian is not None:
            return self.residual(x), self.jacobian(x)
        keep = torch.is_grad_enabled()  # iLQR with grad="unrolled": keep the graph (as autograd_derivatives)
        with torch.enable_grad():
            xg = _inputs(x, keep)
            f = self.residual(xg)
            rows = [torch.autograd.grad(f[..., i].sum(), xg, retain_graph=True, create_graph=keep)[0]
                    for i in range(f.shape[-1])]
        J = torch.stack(rows, -2)
        return (f, J) if keep else (f.detach(), J.detach())

    def evaluate(self, x: Tensor, u: Tensor) -> Tensor:
        f = self.residual(x)
        cx = (f.unsqueeze(-2) @ self.Q @ f.unsqueeze(-1))[..., 0, 0].sum(-1)
        cu = (u.unsqueeze(-2) @ self.R @ u.unsqueeze(-1))[..., 0, 0].sum(-1)
        return cx + cu

    def derivatives(self, x: Tensor, u: Tensor):
        f, J = self._jac(x)
        JtQ = J.mT @ self.Q
        gx = 2 * (JtQ @ f.unsqueeze(-1)).squeeze(-1)
        gu = 2 * (self.R @ u.unsqueeze(-1)).squeeze(-1)
        R = self.R if self.R.dim() > 2 else self.R.unsqueeze(0)  # explicit time dim
        return gx, gu, 2 * JtQ @ J, None, 2 * R


@dataclass(frozen=True, eq=False)
class PeriodicQuadraticCost:
    """A :class:`QuadraticCost` whose angle components are compared modulo ``2π``::

        c(x, u) = base(μ + wrap(x − μ), u),   wrap(d) = ((d + π) mod 2π) − π  on the ``periodic`` components

    so ``dx`` on an angle is the signed shortest angle to its reference and the cost is ``2π``-periodic in
    it: a pendulum one turn away costs nothing more, and a plan that swings past the bottom is charged what
    a wrapped reward charges it.  Off the cut (``|dx| < π``) it equals ``base``; its derivatives are
    ``base``'s at the wrapped point (``d wrap/dd = 1`` away from the cut, where the cost is continuous but
    its gradient flips sign — iLQR's line search handles the kink like any other non-convexity).

    Args:
        base: the quadratic cost (``x_ref`` μ; zero when it has none).
        periodic: ``(n,)`` bool, the angle components.
    """

    base: QuadraticCost
    periodic: Tensor

    def __post_init__(self) -> None:
        if not isinstance(self.base, QuadraticCost):
            raise TypeError("PeriodicQuadraticCost: field 'base' must be a QuadraticCost, got "
                            f"{type(self.base).__name__}")
        p = self.periodic
        if not isinstance(p, Tensor) or p.dtype != torch.bool or p.shape != (self.base.n,):
            got = f"{p.dtype} {tuple(p.shape)}" if isinstance(p, Tensor) else type(p).__name__
            raise ValueError(f"PeriodicQuadraticCost: field 'periodic' must be a bool tensor of shape "
                             f"({self.base.n},), got {got}")

    def wrapped(self, x: Tensor) -> Tensor:
        """``μ + wrap(x − μ)`` on the periodic components, ``x`` elsewhere (same shape as ``x``)."""
        mu = self.base.x_ref
        mu = torch.zeros((), dtype=x.dtype, device=x.device) if mu is None else mu
        d = x - mu
        w = mu + torch.remainder(d + math.pi, 2 * math.pi) - math.pi
        return torch.where(self.periodic.to(x.device), w, x)

    def evaluate(self, x: Tensor, u: Tensor) -> Tensor:
        return self.base.evaluate(self.wrapped(x), u)

    def derivatives(self, x: Tensor, u: Tensor):
        return self.base.derivatives(self.wrapped(x), u)


def stand_in_cost(cost, bad: Tensor):
    """``cost`` with the batched fields of a :class:`QuadraticCost` (or a periodic one's base) replaced by
    identity weights and zero terms in the elements that failed their input check, so that no NaN or
    indefinite weight of one element reaches another's gradient (through a shared reference, say); such
    an element is returned as NaN anyway.  Fields shared by the batch were validated at construction."""
    base = cost.base if isinstance(cost, PeriodicQuadraticCost) else cost
    if not isinstance(base, QuadraticCost):
        return cost
    fields = {}
    for name, k in (("Q", 3), ("R", 3), ("N", 3), ("x_ref", 2), ("u_ref", 2), ("q", 2), ("r", 2)):
        v = getattr(base, name)
        if v is None or v.dim() == k:
            continue
        safe = torch.eye(v.shape[-1], dtype=v.dtype, device=v.device) if name in ("Q", "R") else 0.0
        fields[name] = torch.where(bad.view(*bad.shape, *([1] * k)), safe, v)
    if not fields:
        return cost
    base = dataclasses.replace(base, check=False, **fields)
    return dataclasses.replace(cost, base=base) if isinstance(cost, PeriodicQuadraticCost) else base


# --------------------------------------------------------------------------------------------------
# derivatives
# --------------------------------------------------------------------------------------------------


def _inputs(x: Tensor, keep: bool) -> Tensor:
    """``x`` as an input to differentiate at: itself when its graph is kept and it has one."""
    return x if keep and x.requires_grad else x.detach().requires_grad_(True)


def autograd_derivatives(cost, x: Tensor, u: Tensor):
    """Exact gradient and per-step Hessian blocks of a time-separable cost by double backward.

    Called with gradients enabled (iLQR with ``grad="unrolled"``), the derivatives keep their graph
    to ``x``, ``u`` and the cost's parameters; otherwise they are constants (no graph)."""
    n, m = x.shape[-1], u.shape[-1]
    keep = torch.is_grad_enabled()
    with torch.enable_grad():
        xg, ug = _inputs(x, keep), _inputs(u, keep)
        J = cost.evaluate(xg, ug).sum()
        gx, gu = torch.autograd.grad(J, (xg, ug), create_graph=True)
        Hxx, Hxu, Huu = hessian_rows(gx, gu, xg, ug, n, m, keep_graph=keep)
    if not keep:
        gx, gu = gx.detach(), gu.detach()
    return gx, gu, Hxx, Hxu[..., :-1, :, :].mT, Huu


def hessian_rows(gx: Tensor, gu: Tensor, xg: Tensor, ug: Tensor, n: int, m: int, keep_graph: bool = False):
    """Per-time-step Hessian blocks of a sum of per-step terms from its gradient (built with a graph);
    constants unless ``keep_graph``."""
    rx, rxu, ru = [], [], []
    kw = dict(retain_graph=True, allow_unused=True, create_graph=keep_graph)
    for i in range(n):
        if gx.requires_grad:
            a, b = torch.autograd.grad(gx[..., i].sum(), (xg, ug), **kw)
        else:
            a = b = None
        rx.append(torch.zeros_like(xg) if a is None else a)
        # u has T steps, x has T+1: pad the last (terminal) step with zeros
        rxu.append(torch.zeros_like(xg[..., :1]).expand(*xg.shape[:-1], m) if b is None
                   else torch.cat([b, torch.zeros_like(b[..., :1, :])], -2))
    for i in range(m):
        if gu.requires_grad:
            (c,) = torch.autograd.grad(gu[..., i].sum(), (ug,), **kw)
        else:
            c = None
        ru.append(torch.zeros_like(ug) if c is None else c)
    out = torch.stack(rx, -2), torch.stack(rxu, -2), torch.stack(ru, -2)
    return out if keep_graph else tuple(v.detach() for v in out)


def cost_derivatives(cost, x: Tensor, u: Tensor):
    """``gx (*B,T+1,n)``, ``gu (*B,T,m)``, ``Hxx (…,T+1,n,n)``, ``Hux (…,T,m,n)`` or None, ``Huu``."""
    if callable(getattr(cost, "derivatives", None)):
        return cost.derivatives(x, u)
    return autograd_derivatives(cost, x, u)


def lq_coefficients(gx: Tensor, gu: Tensor, Hxx: Tensor, Hux: Tensor | None, Huu: Tensor):
    """Derivatives of a cost -> the coefficients ``(Q, R, N, q, r)`` of the LQ cost with the same first
    and second derivatives, in this package's convention (module docstring): ``Q = ½ sym(H_xx)``,
    ``R = ½ sym(H_uu)``, ``N = ½ H_uxᵀ``, ``q = ½ g_x``, ``r = ½ g_u``.  The only place where the two
    scales meet."""
    Q = 0.25 * (Hxx + Hxx.mT)
    R = 0.25 * (Huu + Huu.mT)
    N = None if Hux is None else 0.5 * Hux.mT
    return Q, R, N, 0.5 * gx, 0.5 * gu


# --------------------------------------------------------------------------------------------------
# cost modules (observation -> cost, for controllers.mpc.MPCPolicy)
# --------------------------------------------------------------------------------------------------


def _inv_softplus(v: Tensor) -> Tensor:
    return v + torch.log(-torch.expm1(-v))


class DiagonalQuadraticCost(nn.Module):
    """Learnable tracking cost ``Σ_t (x_t - x*)ᵀ diag(q) (x_t - x*) + u_tᵀ diag(r) u_t`` with terminal weight
    ``terminal_factor · diag(q)``, as a module ``forward(obs) -> QuadraticCost`` (the observation is not
    used: the same cost for every element).  ``q``, ``r`` stay positive through a softplus; ``q``, ``r``
    and the target ``x*`` are ``nn.Parameter``s.

    Args:
        q: ``(n,)`` initial state weights; r: ``(m,)`` initial control weights (positive).
        target: ``(n,)`` initial target state.
        horizon: ``T`` (the cost has ``T+1`` state weights).
        terminal_factor: scale of the terminal weight.
    """

    def __init__(self, q: Tensor, r: Tensor, target: Tensor, horizon: int, terminal_factor: float = 10.0):
        super().__init__()
        q, r, target = (torch.as_tensor(v) for v in (q, r, target))
        for name, v in (("r", r), ("target", target)):
            if v.dtype != q.dtype:
                raise TypeError(f"DiagonalQuadraticCost: argument '{name}' has dtype {v.dtype} but 'q' has "
                                f"{q.dtype}; give q, r and target one dtype")
        if q.dim() != 1 or target.shape != q.shape or r.dim() != 1:
            raise ValueError(f"DiagonalQuadraticCost: q and target must have shape (n,) and r (m,), got "
                             f"{tuple(q.shape)}, {tuple(target.shape)} and {tuple(r.shape)}")
        if bool((q <= 0).any()) or bool((r <= 0).any()):
            raise ValueError("DiagonalQuadraticCost: initial weights q and r must be positive")
        if not isinstance(horizon, int) or isinstance(horizon, bool) or horizon < 1:
            raise ValueError(f"DiagonalQuadraticCost: argument 'horizon' must be a positive int, "
                             f"got {horizon!r}")
        self.horizon = horizon
        self.terminal_factor = float(terminal_factor)
        self.q_raw = nn.Parameter(_inv_softplus(q.detach().clone()))
        self.r_raw = nn.Parameter(_inv_softplus(r.detach().clone()))
        self.target = nn.Parameter(target.detach().clone())

    @property
    def q(self) -> Tensor:
        return nn.functional.softplus(self.q_raw)

    @property
    def r(self) -> Tensor:
        return nn.functional.softplus(self.r_raw)

    def forward(self, obs: Tensor | None = None) -> QuadraticCost:
        """The current :class:`QuadraticCost` (differentiable in the parameters)."""
        T = self.horizon
        Q = torch.diag_embed(self.q)
        Qs = torch.cat([Q.expand(T, *Q.shape), (self.terminal_factor * Q)[None]])
        return QuadraticCost(Q=Qs, R=torch.diag_embed(self.r), x_ref=self.target, check=False)

    def extra_repr(self) -> str:
        return f"n={self.q_raw.shape[0]}, m={self.r_raw.shape[0]}, horizon={self.horizon}"
