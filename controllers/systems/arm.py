"""Planar n-link serial arm: a batched model shared by the MPC, the simulator and the environments.

State ``x = [q, q̇]`` (``q ∈ R^k`` relative joint angles, ``k ≥ 1`` links), control ``u = τ ∈ R^k`` (joint
torques).  Link ``j`` has length ``l_j`` and a **point mass** ``m_j`` at its tip (massless links: the
choice that makes ``k = 1`` exactly :class:`~controllers.systems.Pendulum`); joint ``j`` has viscous damping
``b_j``; gravity ``g`` acts along ``-y`` in the plane of motion (``g = 0``, the default, is a horizontal
arm).  With ``q = 0`` the arm is stretched along ``+x``.

In the absolute link angles ``φ = Sᵀ q`` (``φ_j = q_1 + … + q_j``; ``S`` the upper-triangular matrix of
ones) the Lagrangian is simple: with ``μ_j = Σ_{i≥j} m_i`` (the mass carried by link ``j``),
``K_jk = l_j l_k μ_max(j,k)``, ``W = K ∘ cos(φ_j - φ_k)`` and ``P = K ∘ sin(φ_j - φ_k)``::

    T = ½ φ̇ᵀ W(φ) φ̇,      V = g Σ_j μ_j l_j sin φ_j,
    W φ̈ + P φ̇² + G = S⁻¹ (τ - b ∘ q̇),      G_j = g μ_j l_j cos φ_j,

which is the manipulator equation ``M(q) q̈ + C(q, q̇) q̇ + g(q) + b q̇ = τ`` with ``M = S W Sᵀ``
(:meth:`PlanarArm.mass_matrix`) multiplied by ``S⁻¹``.  So ``φ̈ = W⁻¹ rhs`` (one ``k × k`` SPD solve,
written out as a Cholesky factorization with a Python loop over the links only — elementwise batched
kernels, no LAPACK call, so a batch of any size gives every element bit for bit what it gets alone) and
``q̈ = S⁻ᵀ φ̈`` (``q̈_j = φ̈_j - φ̈_{j-1}``).

The discrete step is semi-implicit Euler (:mod:`controllers.systems._mechanical`).  :meth:`PlanarArm.jacobian`
is analytic: differentiating ``W φ̈ = rhs``::

    ∂φ̈/∂φ = W⁻¹ (R_φ - D),    R_φ = -diag(W φ̇²) + W diag(φ̇²) + diag(g μ ∘ l ∘ sin φ),
                               D   = -diag(P φ̈) + P diag(φ̈)            (D = (∂W/∂φ) φ̈),
    ∂φ̈/∂φ̇ = -2 W⁻¹ P diag(φ̇),        ∂φ̈/∂τ = W⁻¹ S⁻¹,

and ``a_q = S⁻ᵀ (∂φ̈/∂φ) Sᵀ``, ``a_v = S⁻ᵀ ((∂φ̈/∂φ̇) Sᵀ - W⁻¹ S⁻¹ diag(b))``, ``a_u = S⁻ᵀ W⁻¹ S⁻¹`` (all
three right-hand sides in one solve).  Parameters broadcast against the batch dims of the state.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from controllers.dynamics import NonlinearDynamics
from controllers.systems._mechanical import check_xu, euler_jacobian, euler_step, param, shape_of
from torchlie._batch import broadcast_shapes

__all__ = ["PlanarArm", "spd_solve"]


def spd_solve(W: Tensor, rhs: Tensor) -> Tensor:
    """``W⁻¹ rhs`` for symmetric positive definite ``W (*B, k, k)`` and ``rhs (*B, k, r)`` by a Cholesky
    factorization written with a Python loop over ``k`` (meant for small ``k``): batched elementwise
    kernels only, exact to rounding, differentiable (autograd and ``torch.func``) and deterministic per
    batch element.  A ``W`` that is not positive definite gives NaN."""
    k = W.shape[-1]
    L: list[list[Tensor | None]] = [[None] * k for _ in range(k)]
    for j in range(k):
        s = W[..., j, j]
        for i in range(j):
            s = s - L[j][i] * L[j][i]
        d = torch.sqrt(s)
        L[j][j] = d
        for r in range(j + 1, k):
            t = W[..., r, j]
            for i in range(j):
                t = t - L[r][i] * L[j][i]
            L[r][j] = t / d
    y: list[Tensor] = []
    for r in range(k):  # L y = rhs
        t = rhs[..., r, :]
        for i in range(r):
            t = t - L[r][i][..., None] * y[i]
        y.append(t / L[r][r][..., None])
    z: list[Tensor | None] = [None] * k
    for r in reversed(range(k)):  # Lᵀ z = y
        t = y[r]
        for i in range(r + 1, k):
            t = t - L[i][r][..., None] * z[i]
        z[r] = t / L[r][r][..., None]
    return torch.stack(torch.broadcast_tensors(*z), -2)


def _rcumsum(v: Tensor, dim: int = -1) -> Tensor:
    """Reverse cumulative sum ``out_j = Σ_{i≥j} v_i`` along ``dim``."""
    return v.flip(dim).cumsum(dim).flip(dim)


def _next_diff(v: Tensor) -> Tensor:
    """``S⁻¹ v`` along the last dim: ``v_j - v_{j+1}`` (``v_{k+1} = 0``)."""
    return torch.cat([v[..., :-1] - v[..., 1:], v[..., -1:]], -1)


def _prev_diff_rows(M: Tensor) -> Tensor:
    """``S⁻ᵀ M`` (rows): ``M_j - M_{j-1}`` (``M_0 = 0``)."""
    return torch.cat([M[..., :1, :], M[..., 1:, :] - M[..., :-1, :]], -2)


@dataclass(frozen=True, eq=False)
class PlanarArm:
    """Batched planar ``k``-link arm ``x = [q, q̇] (2k)``, ``u = τ (k)`` (module docstring).

    Attributes:
        links: number of links ``k ≥ 1``.
        lengths, masses, damping: per link/joint: a float (every link), a tuple of ``k`` floats, or a
            tensor of shape ``(*B, k)`` (or ``(*B, 1)``, or 0-dim: every link) whose batch dims broadcast
            against ``x.shape[:-1]``.  Masses are point masses at the link tips (must be positive).
        gravity: along ``-y`` in the plane (0 = horizontal arm); float or tensor broadcasting against the
            batch dims.
        dt: time step of :meth:`step` (float or tensor).
    """

    links: int = 2
    lengths: Tensor | float | tuple[float, ...] = 0.5
    masses: Tensor | float | tuple[float, ...] = 1.0
    damping: Tensor | float | tuple[float, ...] = 0.0
    gravity: Tensor | float = 0.0
    dt: Tensor | float = 0.05

    #: ``step``/``jacobian`` ignore ``t`` and take any leading dims (:class:`controllers.dynamics.System`)
    time_invariant = True

    def __post_init__(self) -> None:
        k = self.links
        if not isinstance(k, int) or isinstance(k, bool) or k < 1:
            raise ValueError(f"PlanarArm: field 'links' must be a positive int, got {k!r}")
        for name in ("lengths", "masses", "damping"):
            v = getattr(self, name)
            if isinstance(v, list):
                v = tuple(v)
                object.__setattr__(self, name, v)
            if isinstance(v, tuple):
                if len(v) != k:
                    raise ValueError(f"PlanarArm: field '{name}' has {len(v)} values for {k} links")
                object.__setattr__(self, name, tuple(float(e) for e in v))
            elif isinstance(v, Tensor):
                if v.dim() > 0 and v.shape[-1] not in (1, k):
                    raise ValueError(f"PlanarArm: field '{name}' must have shape (*B, {k}) or (*B, 1), "
                                     f"got {tuple(v.shape)}")
            elif not isinstance(v, (int, float)):
                raise TypeError(f"PlanarArm: field '{name}' must be a float, a tuple of floats or a tensor")
        for name in ("lengths", "masses"):
            v = getattr(self, name)
            vals = v if isinstance(v, tuple) else (v,) if isinstance(v, (int, float)) else ()
            if any(e <= 0 for e in vals):
                raise ValueError(f"PlanarArm: field '{name}' must be positive, got {v!r}")

    @property
    def n(self) -> int:
        return 2 * self.links

    @property
    def m(self) -> int:
        return self.links

    @property
    def reach(self) -> float:
        """Largest distance of the end effector from the base, ``Σ l_j`` (the max over a parameter batch)."""
        lv = self.lengths
        if isinstance(lv, Tensor):
            return float(lv.detach().expand(*lv.shape[:-1], self.links).sum(-1).max()) if lv.dim() \
                else self.links * float(lv)
        return float(sum(lv)) if isinstance(lv, tuple) else self.links * float(lv)

    # ------------------------------------------------------------------------------------------ params
    def _link(self, name: str, like: Tensor) -> Tensor:
        """A per-link parameter as a tensor ``(*P, k)`` in the dtype/device of ``like``."""
        v, k = getattr(self, name), self.links
        if isinstance(v, Tensor):
            v = param(v, like, name, "PlanarArm")
            return v.expand(k) if v.dim() == 0 else v.expand(*v.shape[:-1], k)
        vals = v if isinstance(v, tuple) else (float(v),) * k
        return torch.tensor(vals, dtype=like.dtype, device=like.device)

    def _inertia(self, x: Tensor):
        """``l, μ, K (*P, k, k)`` for computations with ``x``."""
        k = self.links
        length, mass = self._link("lengths", x), self._link("masses", x)
        mu = _rcumsum(mass)
        ar = torch.arange(k, device=x.device)
        idx = torch.maximum(ar[:, None], ar[None, :])
        K = length[..., :, None] * length[..., None, :] * mu[..., idx]
        return length, mu, K

    def _kinematics(self, x: Tensor):
        k = self.links
        phi, w = x[..., :k].cumsum(-1), x[..., k:].cumsum(-1)
        c, s = torch.cos(phi), torch.sin(phi)
        C = c[..., :, None] * c[..., None, :] + s[..., :, None] * s[..., None, :]  # cos(φ_j - φ_k)
        Sn = s[..., :, None] * c[..., None, :] - c[..., :, None] * s[..., None, :]  # sin(φ_j - φ_k)
        return w, c, s, C, Sn

    def _solve(self, x: Tensor, u: Tensor):
        """Everything the acceleration and its Jacobian need: ``φ̈`` and the intermediate terms."""
        k = self.links
        length, mu, K = self._inertia(x)
        b = self._link("damping", x)
        g = param(self.gravity, x, "gravity", "PlanarArm")
        if isinstance(g, Tensor):
            g = g[..., None]
        w, c, s, C, Sn = self._kinematics(x)
        W, P = K * C, K * Sn
        w2 = w * w
        gml = g * mu * length  # (*P, k) or a float times a tensor
        rhs = _next_diff(u - b * x[..., k:]) - (P * w2[..., None, :]).sum(-1) - gml * c
        phidd = spd_solve(W, rhs[..., None])[..., 0]
        return phidd, dict(W=W, P=P, w=w, w2=w2, s=s, gml=gml, b=b)

    # ------------------------------------------------------------------------------------------ dynamics
    def acceleration(self, x: Tensor, u: Tensor) -> Tensor:
        """``q̈ (*B, k)`` from ``x (*B, 2k)`` and ``u (*B, k)``."""
        check_xu(x, u, self.n, self.m, "PlanarArm.acceleration")
        phidd, _ = self._solve(x, u)
        return torch.cat([phidd[..., :1], phidd[..., 1:] - phidd[..., :-1]], -1)

    def derivative(self, x: Tensor, u: Tensor) -> Tensor:
        """Continuous-time ``ẋ = [q̇, q̈]``."""
        acc = self.acceleration(x, u)
        return torch.cat([x[..., self.links:].expand(*acc.shape[:-1], self.links), acc], dim=-1)

    def step(self, x: Tensor, u: Tensor, t: int = 0) -> Tensor:
        """``x_{t+1} (*B, 2k)`` by semi-implicit Euler; ``t`` is ignored (time-invariant)."""
        acc = self.acceleration(x, u)
        dt = param(self.dt, x, "dt", "PlanarArm")
        if isinstance(dt, Tensor):
            dt = dt.expand(acc.shape[:-1])
        if x.shape[:-1] != acc.shape[:-1]:
            x = x.expand(*acc.shape[:-1], self.n)
        return euler_step(x, acc, dt)

    def jacobian(self, x: Tensor, u: Tensor, t: int = 0) -> tuple[Tensor, Tensor]:
        """Analytic ``(A (*B, 2k, 2k), B (*B, 2k, k))`` of :meth:`step` (module docstring)."""
        check_xu(x, u, self.n, self.m, "PlanarArm.jacobian")
        k = self.links
        phidd, d = self._solve(x, u)
        W, P, w, w2, b = d["W"], d["P"], d["w"], d["w2"], d["b"]
        dt = param(self.dt, x, "dt", "PlanarArm")
        bs = broadcast_shapes(phidd.shape[:-1], b.shape[:-1], shape_of(dt))
        diag = torch.diag_embed
        R_phi = diag(d["gml"] * d["s"] - (W * w2[..., None, :]).sum(-1)) + W * w2[..., None, :]
        D = P * phidd[..., None, :] - diag((P * phidd[..., None, :]).sum(-1))
        R_w = -2.0 * P * w[..., None, :]
        eye = torch.eye(k, dtype=x.dtype, device=x.device)
        s_inv = eye - torch.diag(torch.ones(k - 1, dtype=x.dtype, device=x.device), 1)  # S⁻¹
        R_phi, D, R_w = (v.expand(*bs, k, k) for v in (R_phi, D, R_w))
        X = spd_solve(W.expand(*bs, k, k), torch.cat([R_phi - D, R_w, s_inv.expand(*bs, k, k)], -1))
        a_u = _prev_diff_rows(X[..., 2 * k:])
        a_q = _prev_diff_rows(_rcumsum(X[..., :k]))
        a_v = _prev_diff_rows(_rcumsum(X[..., k:2 * k])) - a_u * b[..., None, :]
        return euler_jacobian(a_q, a_v.expand(*bs, k, k), a_u,
                              dt.expand(bs) if isinstance(dt, Tensor) else dt)

    def dynamics(self):
        """This model as a :class:`controllers.dynamics.NonlinearDynamics` (analytic Jacobians)."""
        return NonlinearDynamics(f=self.step, n=self.n, m=self.m, jacobian=self.jacobian, time_invariant=True)

    # ------------------------------------------------------------------------------------------ physics
    def mass_matrix(self, q: Tensor) -> Tensor:
        """``M(q) = S W(φ) Sᵀ (*B, k, k)`` of the manipulator equation (joint coordinates)."""
        x = torch.cat([q, torch.zeros_like(q)], -1)
        _, _, K = self._inertia(x)
        _, _, _, C, _ = self._kinematics(x)
        return _rcumsum(_rcumsum(K * C, -1), -2)

    def gravity_torque(self, q: Tensor) -> Tensor:
        """Gravitational joint torque ``g(q) = ∂V/∂q (*B, k)`` of the manipulator equation (seed 004 Eq. 169,
        Eq. 198: ``g = Lᵀ g̃``), ``g̃_j = g μ_j l_j cos φ_j`` in the absolute angles: ``g_a = Σ_{j≥a} g̃_j``.
        The torque ``τ = g(q)`` holds the arm still at ``q`` (zero velocity, zero acceleration)."""
        if q.shape[-1] != self.links:
            raise ValueError(f"PlanarArm.gravity_torque: q must have shape (*B, {self.links}), "
                             f"got {tuple(q.shape)}")
        length, mu, _ = self._inertia(q)
        g = param(self.gravity, q, "gravity", "PlanarArm")
        if isinstance(g, Tensor):
            g = g[..., None]
        return _rcumsum(g * mu * length * torch.cos(q.cumsum(-1)))

    def energy(self, x: Tensor) -> Tensor:
        """Mechanical energy ``½ φ̇ᵀ W φ̇ + g Σ μ_j l_j sin φ_j`` ``(*B,)`` (zero potential at ``y = 0``)."""
        length, mu, K = self._inertia(x)
        w, c, s, C, _ = self._kinematics(x)
        kin = 0.5 * (w[..., :, None] * (K * C) * w[..., None, :]).sum((-1, -2))
        g = param(self.gravity, x, "gravity", "PlanarArm")
        return kin + g * (mu * length * s).sum(-1)

    def fk(self, q: Tensor) -> Tensor:
        """Joint positions ``(*B, k+1, 2)`` from ``q (*B, k)``: the base (origin), the joints, the tip."""
        if q.shape[-1] != self.links:
            raise ValueError(f"PlanarArm.fk: q must have shape (*B, {self.links}), got {tuple(q.shape)}")
        length = self._link("lengths", q)
        phi = q.cumsum(-1)
        seg = length[..., None] * torch.stack([torch.cos(phi), torch.sin(phi)], -1)
        pts = seg.cumsum(-2)
        return torch.cat([torch.zeros_like(pts[..., :1, :]), pts], -2)

    def end_effector(self, q: Tensor) -> Tensor:
        """Tip position ``(*B, 2)`` from ``q (*B, k)``."""
        return self.fk(q)[..., -1, :]

    def ee_jacobian(self, q: Tensor) -> Tensor:
        """``∂ end_effector / ∂q (*B, 2, k)``: column ``a`` is ``Σ_{j≥a} l_j (-sin φ_j, cos φ_j)``."""
        if q.shape[-1] != self.links:
            raise ValueError(f"PlanarArm.ee_jacobian: q must have shape (*B, {self.links}), "
                             f"got {tuple(q.shape)}")
        length = self._link("lengths", q)
        phi = q.cumsum(-1)
        return _rcumsum(length[..., None, :] * torch.stack([-torch.sin(phi), torch.cos(phi)], -2))
