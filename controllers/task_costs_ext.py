"""More of the seed-004 §9 iLQR zoo: decoupled commands (§9.10), curvature (§9.11), spacetime optimization
(§9.13) and object affordances (§9.14).

* :class:`ControlProductCost` — the decoupling cost of §9.10, ``Σ_t Σ_k w (u_{i_k,t} u_{j_k,t})²`` over pairs
  ``(i_k, j_k)`` of control indices, with the seed's residuals ``f_t = u_{i,t} u_{j,t}`` and Jacobians
  ``J_t = [u_{j,t}, u_{i,t}]`` (in the columns ``i, j``) giving Gauss-Newton derivatives
  ``g_u = 2 w Jᵀ f``, ``H_uu ≈ 2 w Jᵀ J``.  It depends on ``u`` only, so it is a cost object (``evaluate``,
  ``derivatives``) rather than a state :class:`~controllers.task_costs.Map`; :class:`CostSum` adds it to a
  :class:`~controllers.costs.ResidualCost` built by :func:`controllers.task_costs.residual_cost`.
* :func:`curvature` — the signed curvature of a planar path (Eq. 112) as a
  :class:`~controllers.task_costs.Map` in the seed's quadratic-form notation (Eq. 114-116):
  ``κ(x) = (xᵀ S_B x)^{-3/2} xᵀ S_A x`` with
  ``S_A = s_{1,1} s_{2,2}ᵀ - s_{1,2} s_{2,1}ᵀ`` and ``S_B = s_{1,1} s_{1,1}ᵀ + s_{1,2} s_{1,2}ᵀ`` (so that
  ``xᵀ S_B x = ẋ₁² + ẋ₂²``, the denominator of Eq. 112; the seed's printed ``S_B = s_{1,1} s_{1,2}ᵀ +
  s_{1,2} s_{1,1}ᵀ`` would give ``2 ẋ₁ ẋ₂``), and the Jacobian of Eq. 116.  Compose it with
  :func:`controllers.task_costs.track` (a desired curvature) or :func:`controllers.task_costs.cut` (a bound
  ``|κ| ≤ κ_max``).

* object affordances (§9.14): :func:`object_frame` (a planar pose ``[p, φ]`` expressed in an object's frame:
  the grasp offset), :func:`coupling_precision` (the seed's precision with off-diagonal blocks
  ``[[W, -W], [-W, W]]`` between two time steps, which asks two residuals to be equal wherever they meet) and
  :func:`coupled_cost` (``fᵀ Q f`` of a whole stacked trajectory residual under it).  The iLQR solvers take
  costs that are sums of per-step terms, so the coupling is solved in its equivalent time-separable form: an
  auxiliary constant state ``z`` (``z_{t+1} = z_t``, its initial value optimized, e.g. by
  :func:`controllers.ilqr_lifted.ilqr_lifted` with a zero ``x0_weight`` on it) and the residuals
  ``g(x_{t_1}) - z``, ``g(x_{t_2}) - z`` (:func:`minus_state`) with precision ``2W`` each, since
  ``min_z (a - z)ᵀ 2W (a - z) + (b - z)ᵀ 2W (b - z) = (a - b)ᵀ W (a - b) = [a; b]ᵀ [[W, -W], [-W, W]] [a; b]``
  (the minimum at ``z = (a + b)/2``: a Schur complement).

* spacetime optimization (§9.13): :class:`SpacetimeDynamics`, a linear system with a phase variable ``s``
  and a time-scaling control ``u^s`` appended (``x_{t+1} = A x_t + B u^x_t u^s_t``,
  ``s_{t+1} = s_t + u^s_t``), with the seed's analytic linearization; costs on the phase (the movement's
  duration) are ordinary costs of the augmented state and control, and :class:`PhaseEffortCost` is the effort
  ``Σ_t r ‖u^x_t‖² u^s_t`` integrated over the scaled time.

Shapes follow :mod:`controllers.task_costs` (states ``(*B, T+1, n)``, controls ``(*B, T, m)``, any leading
dims); dtype and device follow the inputs.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from controllers.costs import cost_derivatives
from controllers.dynamics import NonlinearDynamics
from controllers.task_costs import Map

__all__ = ["ControlProductCost", "CostSum", "curvature", "object_frame", "minus_state", "coupling_precision",
           "coupled_cost", "SpacetimeDynamics", "PhaseEffortCost"]


def _pairs(pairs, fn: str, what: str = "control indices") -> tuple[tuple[int, int], ...]:
    try:
        out = tuple((int(i), int(j)) for i, j in pairs)
    except (TypeError, ValueError):
        raise TypeError(f"{fn}: argument 'pairs' must be a sequence of (i, j) {what}, got "
                        f"{pairs!r}") from None
    if not out:
        raise ValueError(f"{fn}: argument 'pairs' must hold at least one (i, j) pair")
    for i, j in out:
        if i < 0 or j < 0 or i == j:
            raise ValueError(f"{fn}: argument 'pairs' must hold pairs of distinct non-negative {what}, got "
                             f"{pairs!r}")
    return out


@dataclass(frozen=True, eq=False)
class ControlProductCost:
    """Decoupling of control commands (seed 004 §9.10)::

        c(u) = Σ_t Σ_k w_k (u_{i_k,t} u_{j_k,t})²,     f_{k,t} = u_{i_k,t} u_{j_k,t},
        J_{k,t} = ∂f_{k,t}/∂u_t = u_{j_k,t} e_{i_k}ᵀ + u_{i_k,t} e_{j_k}ᵀ   (the seed's [u_{2,t}, u_{1,t}])

    which vanishes exactly when, at every step, at most one command of each pair is non-zero (e.g. the arm
    of a mobile manipulator still while its platform moves).  :meth:`derivatives` returns the Gauss-Newton
    ones, ``g_u = 2 Σ_k w_k f_k J_kᵀ``, ``H_uu = 2 Σ_k w_k J_kᵀ J_k`` (positive semi-definite; the exact
    Hessian adds the indefinite ``2 w f ∂²f``), and zero state derivatives.

    Args:
        pairs: ``[(i, j), ...]`` distinct control indices per pair (``K`` pairs).
        weight: ``w``, a float or a tensor broadcasting against ``(*B, T, K)`` (per element, step, pair).
    """

    pairs: Sequence[tuple[int, int]]
    weight: Tensor | float = 1.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "pairs", _pairs(self.pairs, "ControlProductCost"))
        w = self.weight
        if isinstance(w, bool) or not isinstance(w, (int, float, Tensor)):
            raise TypeError(f"ControlProductCost: field 'weight' must be a float or a tensor, got "
                            f"{type(w).__name__}")
        if isinstance(w, Tensor) and not w.dtype.is_floating_point:
            raise TypeError(f"ControlProductCost: field 'weight' must be floating, got {w.dtype}")
        if not isinstance(w, Tensor) and not float(w) >= 0:
            raise ValueError(f"ControlProductCost: field 'weight' must be non-negative, got {w!r}")

    def _check(self, x: Tensor, u: Tensor) -> None:
        if not isinstance(u, Tensor) or not u.dtype.is_floating_point or u.dim() < 2:
            raise TypeError("ControlProductCost: u must be a floating tensor (*B, T, m)")
        hi = max(max(p) for p in self.pairs)
        if u.shape[-1] <= hi:
            raise ValueError(f"ControlProductCost: pair index {hi} out of range for u of shape "
                             f"{tuple(u.shape)}")
        if isinstance(self.weight, Tensor) and self.weight.dtype != u.dtype:
            raise TypeError(f"ControlProductCost: field 'weight' has dtype {self.weight.dtype} but u has "
                            f"{u.dtype}; cast one of them explicitly")

    def _w(self, u: Tensor) -> Tensor | float:
        w = self.weight
        return w.to(u.device) if isinstance(w, Tensor) else float(w)

    def residual(self, u: Tensor) -> Tensor:
        """``f (*B, T, K)``: the products ``u_{i_k,t} u_{j_k,t}``."""
        i, j = [p[0] for p in self.pairs], [p[1] for p in self.pairs]
        return u[..., i] * u[..., j]

    def jacobian(self, u: Tensor) -> Tensor:
        """``J (*B, T, K, m)``: row ``k`` holds ``u_j`` in column ``i`` and ``u_i`` in column ``j``."""
        m = u.shape[-1]
        i = torch.tensor([p[0] for p in self.pairs], device=u.device)
        j = torch.tensor([p[1] for p in self.pairs], device=u.device)
        Ei = torch.nn.functional.one_hot(i, m).to(u.dtype)  # (K, m)
        Ej = torch.nn.functional.one_hot(j, m).to(u.dtype)
        return u[..., j].unsqueeze(-1) * Ei + u[..., i].unsqueeze(-1) * Ej

    def evaluate(self, x: Tensor, u: Tensor) -> Tensor:
        """``(*B,)`` the cost (``x`` only fixes the batch shape)."""
        self._check(x, u)
        f = self.residual(u)
        c = (self._w(u) * f * f).sum((-1, -2))
        return c.expand(torch.broadcast_shapes(c.shape, x.shape[:-2]))

    def derivatives(self, x: Tensor, u: Tensor):
        """Gauss-Newton ``(gx (*B,T+1,n), gu (*B,T,m), Hxx (*B,T+1,n,n), None, Huu (*B,T,m,m))``."""
        self._check(x, u)
        f, J = self.residual(u), self.jacobian(u)
        w = self._w(u)
        wf = w * f
        wJ = (w.unsqueeze(-1) if isinstance(w, Tensor) else w) * J  # (*B, T, K, m)
        gu = 2 * (wf.unsqueeze(-1) * J).sum(-2)
        Huu = 2 * wJ.mT @ J
        bs = torch.broadcast_shapes(x.shape[:-2], gu.shape[:-2])
        T, m, n = u.shape[-2], u.shape[-1], x.shape[-1]
        gu, Huu = gu.expand(*bs, T, m), Huu.expand(*bs, T, m, m)
        gx = x.new_zeros(*bs, T + 1, n)
        Hxx = x.new_zeros(*bs, T + 1, n, n)
        return gx, gu, Hxx, None, Huu


def _add(a: Tensor | None, b: Tensor | None) -> Tensor | None:
    if a is None:
        return b
    if b is None:
        return a
    return a + b


@dataclass(frozen=True, eq=False)
class CostSum:
    """The sum of costs ``c = Σ_i c_i(x, u)`` (each a :class:`~controllers.costs.Cost`: a
    :class:`~controllers.costs.ResidualCost`, a :class:`ControlProductCost`, ...); its derivatives are the
    sums of theirs (:func:`controllers.costs.cost_derivatives`: analytic where a term has them, autograd
    otherwise), broadcast against each other."""

    terms: Sequence

    def __post_init__(self) -> None:
        terms = tuple(self.terms)
        if not terms:
            raise ValueError("CostSum: field 'terms' must hold at least one cost")
        for k, c in enumerate(terms):
            if not callable(getattr(c, "evaluate", None)):
                raise TypeError(f"CostSum: terms[{k}] must have evaluate(x, u), got {type(c).__name__}")
        object.__setattr__(self, "terms", terms)

    def evaluate(self, x: Tensor, u: Tensor) -> Tensor:
        return sum(c.evaluate(x, u) for c in self.terms)

    def derivatives(self, x: Tensor, u: Tensor):
        out = [None] * 5
        for c in self.terms:
            d = cost_derivatives(c, x, u)
            out = [_add(a, b) for a, b in zip(out, d)]
        return tuple(out)


def _index(v, n: int, name: str, fn: str) -> tuple[int, int]:
    if not (isinstance(v, Sequence) and len(v) == 2 and all(isinstance(k, int) and 0 <= k < n for k in v)):
        raise ValueError(f"{fn}: argument '{name}' must be two state indices in [0, {n}), got {v!r}")
    return int(v[0]), int(v[1])


def curvature(n: int = 6, velocity: Sequence[int] = (2, 3), acceleration: Sequence[int] = (4, 5)) -> Map:
    """Signed curvature of a planar path (seed 004 §9.11, Eq. 112-116) as a map ``κ(x) (*B, T+1, 1)``::

        κ = (ẋ₁ ẍ₂ - ẋ₂ ẍ₁) / (ẋ₁² + ẋ₂²)^{3/2} = (xᵀ S_B x)^{-3/2} xᵀ S_A x,
        J = (xᵀ S_B x)^{-3/2} (S_A + S_Aᵀ) x - 3 (xᵀ S_A x) (xᵀ S_B x)^{-5/2} S_B x,

    (``S_A``, ``S_B`` in the module docstring) for the state ``x = [x, ẋ, ẍ]`` of Eq. 113 (default: ``n = 6``,
    ``ẋ`` at indices ``(2, 3)``, ``ẍ`` at ``(4, 5)``); ``velocity``/``acceleration`` name the indices of
    ``ẋ₁, ẋ₂`` and ``ẍ₁, ẍ₂`` in another layout.  Positive when the path turns left.  The curvature of a
    point at rest is undefined: where ``ẋ = 0`` exactly, ``κ = 0`` and ``J = 0`` (a safe ``where``: no NaN,
    and finite gradients elsewhere)."""
    if not isinstance(n, int) or isinstance(n, bool) or n < 4:
        raise ValueError(f"curvature: argument 'n' must be an int >= 4, got {n!r}")
    v1, v2 = _index(velocity, n, "velocity", "curvature")
    a1, a2 = _index(acceleration, n, "acceleration", "curvature")
    if len({v1, v2, a1, a2}) != 4:
        raise ValueError("curvature: 'velocity' and 'acceleration' must be four distinct indices")

    def mats(x: Tensor) -> tuple[Tensor, Tensor]:
        if not isinstance(x, Tensor) or not x.dtype.is_floating_point:
            raise TypeError("curvature: the state must be a floating tensor (*B, T+1, n)")
        if x.shape[-1] != n:
            raise ValueError(f"curvature: the state must end in {n}, got shape {tuple(x.shape)}")
        e = torch.eye(n, dtype=x.dtype, device=x.device)
        s11, s12, s21, s22 = e[v1], e[v2], e[a1], e[a2]
        SA = torch.outer(s11, s22) - torch.outer(s12, s21)
        SB = torch.outer(s11, s11) + torch.outer(s12, s12)
        return SA, SB

    def parts(x: Tensor):
        SA, SB = mats(x)
        a = ((x @ SA) * x).sum(-1)
        b = ((x @ SB) * x).sum(-1)
        moving = b != 0  # NaN stays NaN
        bs = torch.where(moving, b, torch.ones_like(b))  # the unsafe branch on a harmless value
        return SA, SB, a, bs, moving

    def f(x: Tensor) -> Tensor:
        _, _, a, b, moving = parts(x)
        return torch.where(moving, a * b.pow(-1.5), torch.zeros_like(a)).unsqueeze(-1)

    def J(x: Tensor) -> Tensor:
        SA, SB, a, b, moving = parts(x)
        row = (b.pow(-1.5).unsqueeze(-1) * (x @ (SA + SA.mT).mT)
               - (3 * a * b.pow(-2.5)).unsqueeze(-1) * (x @ SB))
        return torch.where(moving.unsqueeze(-1), row, torch.zeros_like(row)).unsqueeze(-2)

    return Map(f, J, 1)


def object_frame(g: Map, position, angle) -> Map:
    """A planar pose ``g(x) = [p, φ]`` (``p = 3``, e.g. :func:`controllers.task_costs.planar_ee`) expressed in
    the frame of an object at ``(position, angle)`` (§9.14): the grasp offset::

        o = [R(θ)ᵀ (p - μ), φ - θ],      J_o = [R(θ)ᵀ J_p ; J_φ],

    ``position (..., 2)`` and ``angle (...)`` broadcast against ``(*B, T+1)`` (e.g. ``(T+1, 2)``: the object's
    pose at each step, where it is picked up and where it is put down)."""
    if not isinstance(g, Map) or g.p != 3:
        raise TypeError("object_frame: argument 'g' must be a controllers.task_costs.Map of a planar pose "
                        "[x, y, φ] (p = 3)")

    def pose(x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        mu = torch.as_tensor(position, dtype=x.dtype, device=x.device)
        th = torch.as_tensor(angle, dtype=x.dtype, device=x.device)
        if mu.shape[-1:] != (2,):
            raise ValueError(f"object_frame: argument 'position' must end in 2, got {tuple(mu.shape)}")
        return mu, th, torch.cos(th), torch.sin(th)

    def f(x: Tensor) -> Tensor:
        mu, th, c, s = pose(x)
        y = g.f(x)
        d = y[..., :2] - mu
        rows = (c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1], y[..., 2] - th)
        return torch.stack(torch.broadcast_tensors(*rows), -1)

    def J(x: Tensor) -> Tensor:
        _, _, c, s = pose(x)
        Jg = g.J(x)
        c, s = c.unsqueeze(-1), s.unsqueeze(-1)
        rows = (c * Jg[..., 0, :] + s * Jg[..., 1, :], -s * Jg[..., 0, :] + c * Jg[..., 1, :], Jg[..., 2, :])
        return torch.stack(torch.broadcast_tensors(*rows), -2)

    return Map(f, J, 3)


def minus_state(g: Map, index: Sequence[int], n: int) -> Map:
    """``f(x) = g(x) - x[index]`` (``J = J_g - E_index``): a residual against auxiliary state entries, e.g. a
    constant offset ``z`` shared by two time steps (the time-separable form of :func:`coupling_precision`).
    ``g`` must be a map of the full ``n``-dimensional state (:func:`controllers.task_costs.on_joints`)."""
    if not isinstance(g, Map):
        raise TypeError(f"minus_state: argument 'g' must be a controllers.task_costs.Map, got "
                        f"{type(g).__name__}")
    idx = list(index)
    if (len(idx) != g.p or len(set(idx)) != len(idx)
            or any(not isinstance(i, int) or isinstance(i, bool) or not 0 <= i < n for i in idx)):
        raise ValueError(f"minus_state: argument 'index' must be {g.p} distinct indices in [0, {n}), got "
                         f"{index!r}")

    def J(x: Tensor) -> Tensor:
        E = torch.zeros(g.p, n, dtype=x.dtype, device=x.device)
        E[torch.arange(g.p), idx] = 1.0
        return g.J(x) - E

    return Map(lambda x: g.f(x) - x[..., idx], J, g.p)


def coupling_precision(T: int, p: int, pairs: Sequence[tuple[int, int]], weight) -> Tensor:
    """The precision ``Q ((T+1) p, (T+1) p)`` of a whole trajectory residual ``[f_0; ...; f_T]`` with the
    blocks ``[[W, -W], [-W, W]]`` at the steps ``(t_1, t_2)`` of each pair (§9.14): ``fᵀ Q f = Σ_pairs
    (f_{t_1} - f_{t_2})ᵀ W (f_{t_1} - f_{t_2})``, zero exactly when the two residuals are equal, wherever they
    meet.  ``weight``: ``W (p, p)`` (symmetric PSD) or a float (``W = w I``); dtype and device follow a tensor
    ``weight`` (float64 otherwise)."""
    if any(isinstance(v, bool) or not isinstance(v, int) or v < 1 for v in (T, p)):
        raise ValueError(f"coupling_precision: 'T' and 'p' must be positive ints, got {T!r} and {p!r}")
    W = weight if isinstance(weight, Tensor) else float(weight) * torch.eye(p, dtype=torch.float64)
    if W.shape != (p, p):
        raise ValueError(f"coupling_precision: argument 'weight' must be a float or a ({p}, {p}) matrix, got "
                         f"{tuple(W.shape)}")
    pr = _pairs(pairs, "coupling_precision", "time steps")
    if any(t > T for pair in pr for t in pair):
        raise ValueError(f"coupling_precision: the time steps of 'pairs' must be in [0, {T}], got {pairs!r}")
    Q = W.new_zeros((T + 1) * p, (T + 1) * p)
    for a, b in pr:
        sa, sb = slice(a * p, (a + 1) * p), slice(b * p, (b + 1) * p)
        Q[sa, sa] += W
        Q[sb, sb] += W
        Q[sa, sb] -= W
        Q[sb, sa] -= W
    return Q


def coupled_cost(f: Tensor, Q: Tensor) -> Tensor:
    """``fᵀ Q f`` per element for a trajectory residual ``f (*B, T+1, p)`` stacked time-major and a full
    precision ``Q ((T+1) p, (T+1) p)`` (:func:`coupling_precision`): ``(*B,)``."""
    v = f.reshape(*f.shape[:-2], -1)
    if Q.shape != (v.shape[-1], v.shape[-1]):
        raise ValueError(f"coupled_cost: 'Q' must be ({v.shape[-1]}, {v.shape[-1]}) for f of shape "
                         f"{tuple(f.shape)}, got {tuple(Q.shape)}")
    return ((v @ Q.to(v.dtype)) * v).sum(-1)


@dataclass(frozen=True, eq=False)
class SpacetimeDynamics:
    """A linear system with a phase variable (seed 004 §9.13): augmented state ``[x, s]`` ``(*B, n+1)`` and
    control ``[u^x, u^s]`` ``(*B, m+1)``::

        x_{t+1} = A x_t + B u^x_t u^s_t,      s_{t+1} = s_t + u^s_t,

    so ``u^s_t`` scales the effect of the command at step ``t`` and ``s`` accumulates it (the phase, starting
    from ``s = 0``; with ``A = I``, ``B = I`` and ``u^x`` a velocity, ``u^s_t`` is the duration of step ``t``
    and ``s_T`` the movement's duration).  :meth:`jacobian` is the seed's linearization::

        A_aug = [[A, 0], [0, 1]],      B_aug = [[B u^s, B u^x], [0, 1]].

    Attributes:
        A: ``(n, n)``; B: ``(n, m)`` (one time-invariant system shared by the batch; same dtype).
    """

    A: Tensor
    B: Tensor

    time_invariant = True

    def __post_init__(self) -> None:
        A, B = self.A, self.B
        if not isinstance(A, Tensor) or not isinstance(B, Tensor):
            raise TypeError("SpacetimeDynamics: fields 'A' and 'B' must be tensors")
        if A.dim() != 2 or A.shape[0] != A.shape[1] or B.dim() != 2 or B.shape[0] != A.shape[0]:
            raise ValueError(f"SpacetimeDynamics: 'A' must be (n, n) and 'B' (n, m), got {tuple(A.shape)} "
                             f"and {tuple(B.shape)}")
        if A.dtype != B.dtype or not A.dtype.is_floating_point:
            raise TypeError(f"SpacetimeDynamics: 'A' and 'B' must share a floating dtype, got {A.dtype} and "
                            f"{B.dtype}")

    @property
    def n(self) -> int:
        return self.A.shape[0] + 1

    @property
    def m(self) -> int:
        return self.B.shape[1] + 1

    def _check(self, x: Tensor, u: Tensor, fn: str) -> None:
        if not isinstance(x, Tensor) or not isinstance(u, Tensor):
            raise TypeError(f"SpacetimeDynamics.{fn}: x and u must be tensors")
        if x.shape[-1:] != (self.n,) or u.shape[-1:] != (self.m,):
            raise ValueError(f"SpacetimeDynamics.{fn}: expected x (*B, {self.n}) and u (*B, {self.m}) "
                             f"([x, s] and [u^x, u^s]), got {tuple(x.shape)} and {tuple(u.shape)}")
        if x.dtype != self.A.dtype or u.dtype != self.A.dtype:
            raise TypeError(f"SpacetimeDynamics.{fn}: x and u must have the dtype of A ({self.A.dtype}), got "
                            f"{x.dtype} and {u.dtype}")

    def step(self, x: Tensor, u: Tensor, t: int = 0) -> Tensor:
        """``[A x + B u^x u^s, s + u^s]`` ``(*B, n+1)``; ``t`` is ignored."""
        self._check(x, u, "step")
        A, B = self.A.to(x.device), self.B.to(x.device)
        us = u[..., -1:]
        xs = x[..., :-1] @ A.mT + (u[..., :-1] * us) @ B.mT
        sn = x[..., -1:] + us
        bs = torch.broadcast_shapes(xs.shape[:-1], sn.shape[:-1])
        return torch.cat([xs.expand(*bs, xs.shape[-1]), sn.expand(*bs, 1)], -1)

    def jacobian(self, x: Tensor, u: Tensor, t: int = 0) -> tuple[Tensor, Tensor]:
        """``(A_aug (*B, n+1, n+1), B_aug (*B, n+1, m+1))`` (the seed's linearization, exact)."""
        self._check(x, u, "jacobian")
        A, B = self.A.to(x.device), self.B.to(x.device)
        n, m = A.shape[0], B.shape[1]
        bs = torch.broadcast_shapes(x.shape[:-1], u.shape[:-1])
        Aa = x.new_zeros(*bs, n + 1, n + 1)
        Aa[..., :n, :n] = A
        Aa[..., n, n] = 1.0
        Ba = x.new_zeros(*bs, n + 1, m + 1)
        Ba[..., :n, :m] = B * u[..., -1, None, None]
        Ba[..., :n, m] = u[..., :-1] @ B.mT
        Ba[..., n, m] = 1.0
        return Aa, Ba

    def dynamics(self) -> NonlinearDynamics:
        """This model as a :class:`controllers.dynamics.NonlinearDynamics` (analytic Jacobians)."""
        return NonlinearDynamics(f=self.step, n=self.n, m=self.m, jacobian=self.jacobian, time_invariant=True)


@dataclass(frozen=True, eq=False)
class PhaseEffortCost:
    """Control effort integrated over scaled time for :class:`SpacetimeDynamics` (§9.13)::

        c(u) = Σ_t r ‖u^x_t‖² u^s_t,     f_t = √(r u^s_t) u^x_t,

    (``u = [u^x, u^s]``, the time scale the last control): ``∫ r ‖u^x‖² dt`` when ``u^s_t`` is the duration of
    step ``t``, so that spreading a motion over more time is cheaper (unlike ``Σ_t u_tᵀ R u_t``, which a
    time-scaled problem minimizes by one long step).  :meth:`derivatives` are the Gauss-Newton ones of the
    residual ``f_t``: the exact gradient ``g = [2 r u^s u^x, r ‖u^x‖²]`` and the positive semi-definite
    ``H = 2 J_tᵀ J_t = [[2 r u^s I, r u^x], [r u^xᵀ, r ‖u^x‖² / (2 u^s)]]``; it needs ``u^s > 0`` (give the
    problem a positive lower limit on ``u^s``; at ``u^s ≤ 0`` the last entry uses the smallest positive
    normal number of the dtype).

    Attributes:
        r: a positive float or a tensor broadcasting against ``(*B, T)``.
    """

    r: Tensor | float = 1.0

    def __post_init__(self) -> None:
        r = self.r
        if isinstance(r, bool) or not isinstance(r, (int, float, Tensor)):
            raise TypeError(f"PhaseEffortCost: field 'r' must be a float or a tensor, got {type(r).__name__}")
        if not isinstance(r, Tensor) and not float(r) > 0:
            raise ValueError(f"PhaseEffortCost: field 'r' must be positive, got {r!r}")

    def _check(self, x: Tensor, u: Tensor) -> Tensor | float:
        if not isinstance(u, Tensor) or not u.dtype.is_floating_point or u.dim() < 2 or u.shape[-1] < 2:
            raise ValueError("PhaseEffortCost: u must be a floating (*B, T, m+1) tensor [u^x, u^s]")
        r = self.r
        if isinstance(r, Tensor):
            if r.dtype != u.dtype:
                raise TypeError(f"PhaseEffortCost: field 'r' has dtype {r.dtype} but u has {u.dtype}")
            return r.to(u.device)
        return float(r)

    def evaluate(self, x: Tensor, u: Tensor) -> Tensor:
        r = self._check(x, u)
        c = (r * (u[..., :-1] ** 2).sum(-1) * u[..., -1]).sum(-1)
        return c.expand(torch.broadcast_shapes(c.shape, x.shape[:-2]))

    def derivatives(self, x: Tensor, u: Tensor):
        """Gauss-Newton ``(gx, gu, Hxx, None, Huu)`` (class docstring)."""
        r = self._check(x, u)
        ux, us = u[..., :-1], u[..., -1:]
        rr = r.unsqueeze(-1) if isinstance(r, Tensor) else r
        sq = (ux**2).sum(-1, keepdim=True)
        gu = torch.cat([2 * rr * us * ux, rr * sq], -1)
        m = ux.shape[-1]
        eye = torch.eye(m, dtype=u.dtype, device=u.device)
        pos = us.clamp_min(torch.finfo(u.dtype).tiny)
        top = torch.cat([(2 * rr * us).unsqueeze(-1) * eye, (rr * ux).unsqueeze(-1)], -1)
        bottom = torch.cat([rr * ux, rr * sq / (2 * pos)], -1).unsqueeze(-2)
        Huu = torch.cat([top, bottom], -2)
        bs = torch.broadcast_shapes(x.shape[:-2], gu.shape[:-2])
        T, n = u.shape[-2], x.shape[-1]
        return (x.new_zeros(*bs, T + 1, n), gu.expand(*bs, T, m + 1), x.new_zeros(*bs, T + 1, n, n), None,
                Huu.expand(*bs, T, m + 1, m + 1))
