"""Quadrotor on R³ × R³ × SO(3) (seed 003 §VII-A, Eq. 32–34): one model for the error-state MPC, the
simulator and the environments.

Frame and units follow the paper: world axes forward-right-**down** (NED, gravity ``+g e₃``), body
axes forward-right-down, thrust along ``−z_b``.  State ``x = (p, v, R)`` (a
:class:`~torchlie.manifolds.ProductState`: position and velocity in the world frame, ``R`` body → world);
control ``u = [a_T, ω_x, ω_y, ω_z]``: the mass-normalized collective thrust (m/s², ``a_T = g`` hovers) and
the body rates (rad/s)::

    ṗ = v,    v̇ = g e₃ − a_T R e₃,    Ṙ = R ⌊ω⌋                                     (Eq. 32)

:class:`Quadrotor` is the canonical discrete model of Eq. 33, ``x_{k+1} = x_k ⊕ Δt f(x_k, u_k)`` with
``f = [v; g e₃ − a_T R e₃; ω]`` (explicit Euler on ``p``, ``v``; the exact exponential on ``R``), with the
system-specific Jacobians of Eq. 34 in closed form (:meth:`Quadrotor.f_jacobians`).  It is a
:class:`controllers.manifold_mpc.ManifoldSystem`.

**Model mismatch (optional).**  :class:`Quadrotor` takes the two physical parameters the simulator below
perturbs, with defaults that change nothing: ``mass_scale`` ``s`` (true mass / nominal mass; the commanded
thrust produces ``a_T / s``) and the rotor drag per unit mass ``D = diag(d_x, d_y, d_z)`` (1/s, body axes;
default 0)::

    v̇ = g e₃ − (a_T / s) R e₃ − R D Rᵀ v

so that an environment, an MPC or a study of robustness can be built on a perturbed vehicle from the same
model definition.  A body-rate-controlled model has no arm length or inertia: the rates are inputs.

:class:`QuadrotorSimulator` is the "real" vehicle, deliberately *not* the MPC's model: the continuous
dynamics integrated with RK4 at ``substeps`` finer steps per control period, the attitude by the exact
SO(3) exponential (the body rate is held over the period, so ``R(s) = R_k Exp(ω s)`` is exact), thrust and
body-rate saturation, optional rotor drag ``−R D Rᵀ v`` (``D = diag(d_x, d_y, d_z)``, per unit mass) and a
mass error (the thrust produces ``a_T / mass_scale``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor

from torchlie import so3
from torchlie._batch import broadcast_shapes
from torchlie.manifolds import SO3, ProductManifold, ProductState, Rn

__all__ = ["Quadrotor", "QuadrotorSimulator", "quadrotor_manifold"]

_E3 = (0.0, 0.0, 1.0)


def quadrotor_manifold() -> ProductManifold:
    """``R³ × R³ × SO(3)`` with components ``p``, ``v``, ``R`` (n = 9, l = 9; Eq. 33a)."""
    return ProductManifold({"p": Rn(3), "v": Rn(3), "R": SO3()})


def _e3(like: Tensor) -> Tensor:
    return torch.tensor(_E3, dtype=like.dtype, device=like.device)


def _no_drag(drag) -> bool:
    """``drag`` is ``None`` or a tuple/list of Python zeros (nothing to compute)."""
    return drag is None or (not isinstance(drag, Tensor) and all(float(d) == 0.0 for d in drag))


def _unit_mass(mass_scale) -> bool:
    return not isinstance(mass_scale, Tensor) and float(mass_scale) == 1.0


def _drag_diag(drag, like: Tensor) -> Tensor:
    """``(d_x, d_y, d_z)`` as a tensor ``(*B, 3)`` in the dtype and on the device of ``like``."""
    return torch.as_tensor(drag, dtype=like.dtype, device=like.device)


def _drag_acc(R: Tensor, v: Tensor, d: Tensor) -> Tensor:
    """Rotor drag per unit mass ``−R D Rᵀ v`` ``(*B, 3)``, ``D = diag(d)``, ``d (*B, 3)`` in body axes."""
    vb = (R.transpose(-1, -2) @ v.unsqueeze(-1)).squeeze(-1)
    return -(R @ (d * vb).unsqueeze(-1)).squeeze(-1)


def _drag_jacobians(R: Tensor, v: Tensor, d: Tensor) -> tuple[Tensor, Tensor]:
    """``∂(−R D Rᵀ v)/∂δv = −R D Rᵀ`` and ``∂/∂δθ = R (⌊D Rᵀ v⌋ − D ⌊Rᵀ v⌋)`` (``R ⊞ δθ = R Exp(δθ)``),
    both ``(*B, 3, 3)``: from ``R Exp(δθ) D Exp(−δθ) Rᵀ v ≈ R D vb + R (⌊δθ⌋ D − D ⌊δθ⌋) vb``, ``vb = Rᵀ v``,
    and ``⌊δθ⌋ a = −⌊a⌋ δθ``."""
    vb = (R.transpose(-1, -2) @ v.unsqueeze(-1)).squeeze(-1)
    Jv = -(R * d.unsqueeze(-2)) @ R.transpose(-1, -2)
    Jth = R @ (so3.hat(d * vb) - d.unsqueeze(-1) * so3.hat(vb))
    return Jv, Jth


def _check_mismatch(mass_scale, drag, owner: str) -> None:
    if isinstance(mass_scale, Tensor):
        if not bool(torch.all(mass_scale.detach() > 0)):
            raise ValueError(f"{owner}: argument 'mass_scale' must be positive")
    elif not (isinstance(mass_scale, (int, float)) and 0 < float(mass_scale) < float("inf")):
        raise ValueError(f"{owner}: argument 'mass_scale' must be a positive finite number or a tensor, "
                         f"got {mass_scale!r}")
    if drag is None:
        return
    if isinstance(drag, Tensor):
        if drag.dim() < 1 or drag.shape[-1] != 3:
            raise ValueError(f"{owner}: argument 'drag' must be a tensor (*B, 3), got shape "
                             f"{tuple(drag.shape)}")
        ok = bool(torch.all(torch.isfinite(drag.detach()) & (drag.detach() >= 0)))
    else:
        vals = tuple(drag)
        ok = len(vals) == 3 and all(isinstance(d, (int, float)) and 0 <= float(d) < float("inf")
                                    for d in vals)
    if not ok:
        raise ValueError(f"{owner}: argument 'drag' must hold three finite non-negative coefficients "
                         f"(d_x, d_y, d_z) in 1/s, got {drag!r}")


@dataclass(frozen=True, eq=False)
class Quadrotor:
    """The canonical discrete quadrotor (module docstring), batched over any leading dims.

    Attributes:
        dt: control period (s); the paper runs its MPC at 100 Hz.
        gravity: g (m/s²), a float or a tensor broadcasting against the batch.
        thrust_min, thrust_max: limits of ``a_T`` (m/s²); the defaults allow 0 … 4 g.
        rate_max: limit of each body rate (rad/s).
        mass_scale: true mass / nominal mass ``s`` (the thrust acceleration is ``a_T / s``), a float or a
            tensor ``(*B,)`` broadcasting against the batch; default 1 (no mismatch).
        drag: rotor-drag coefficients per unit mass ``(d_x, d_y, d_z)`` (1/s, body axes; acceleration
            ``−R D Rᵀ v``), a tuple or a tensor ``(*B, 3)``; default ``None`` (no drag: every field of the
            nominal model is then a plain number, which is what lets a compiled error-state MPC bake it
            into a program, :func:`controllers._esmpc_core.system_key`).
    """

    dt: float = 0.01
    gravity: Tensor | float = 9.81
    thrust_min: float = 0.0
    thrust_max: float = 4 * 9.81
    rate_max: float = 15.0
    manifold: ProductManifold = field(default_factory=quadrotor_manifold)
    mass_scale: Tensor | float = 1.0
    drag: Tensor | tuple[float, float, float] | None = None

    n = 9
    m = 4

    def __post_init__(self):
        _check_mismatch(self.mass_scale, self.drag, "Quadrotor")

    @property
    def u_lower(self) -> tuple[float, ...]:
        return (self.thrust_min, -self.rate_max, -self.rate_max, -self.rate_max)

    @property
    def u_upper(self) -> tuple[float, ...]:
        return (self.thrust_max, self.rate_max, self.rate_max, self.rate_max)

    def state(self, p: Tensor, v: Tensor, R: Tensor, *, project: bool = False) -> ProductState:
        """A checked state from its components (``project=True`` re-orthonormalizes ``R``)."""
        return self.manifold.state(p=p, v=v, R=R, project=project)

    def hover(self, p: Tensor) -> tuple[ProductState, Tensor]:
        """The hover state at positions ``p (*B, 3)`` (at rest, ``R = I``) and its control ``[s g, 0, 0, 0]``
        (``s`` = ``mass_scale``; at rest the drag vanishes)."""
        g = torch.as_tensor(self.gravity, dtype=p.dtype, device=p.device)
        if not _unit_mass(self.mass_scale):
            g = g * torch.as_tensor(self.mass_scale, dtype=p.dtype, device=p.device)
        batch = broadcast_shapes(p.shape[:-1], g.shape)
        p = p.expand(*batch, 3)
        R = torch.eye(3, dtype=p.dtype, device=p.device).expand(*batch, 3, 3)
        x = self.state(p, torch.zeros_like(p), R)
        u = torch.cat([g.expand(batch)[..., None], p.new_zeros(*batch, 3)], -1)
        return x, u

    def _thrust(self, u: Tensor) -> Tensor:
        """``a_T / s`` ``(*B, 1)``."""
        if _unit_mass(self.mass_scale):
            return u[..., :1]
        return u[..., :1] / torch.as_tensor(self.mass_scale, dtype=u.dtype, device=u.device)[..., None]

    def f(self, x: ProductState, u: Tensor) -> Tensor:
        """``[v; g e₃ − a_T R e₃; ω]`` ``(*B, 9)`` (Eq. 33c), with ``a_T / s`` and ``− R D Rᵀ v`` under a
        model mismatch (module docstring)."""
        R = x["R"]
        g = torch.as_tensor(self.gravity, dtype=u.dtype, device=u.device)
        acc = g[..., None] * _e3(u) - self._thrust(u) * R[..., :, 2]
        if not _no_drag(self.drag):
            acc = acc + _drag_acc(R, x["v"], _drag_diag(self.drag, u))
        batch = broadcast_shapes(x["v"].shape[:-1], acc.shape[:-1], u.shape[:-1])
        return torch.cat([x["v"].expand(*batch, 3), acc.expand(*batch, 3), u[..., 1:].expand(*batch, 3)], -1)

    def f_jacobians(self, x: ProductState, u: Tensor) -> tuple[Tensor, Tensor]:
        """The system-specific parts of Eq. 34: ``∂f(x ⊞ δx, u)/∂δx`` ``(*B, 9, 9)`` and
        ``∂f(x, u ⊞ δu)/∂δu`` ``(*B, 9, 4)`` (``R ⊞ δθ = R Exp(δθ)``).  Under a mismatch the thrust terms
        are divided by ``s`` and the drag adds ``−R D Rᵀ`` (w.r.t. ``δv``) and ``R (⌊D Rᵀv⌋ − D ⌊Rᵀv⌋)``
        (w.r.t. ``δθ``)."""
        R, v = x["R"], x["v"]
        drag = None if _no_drag(self.drag) else _drag_diag(self.drag, u)
        aT = self._thrust(u)[..., 0]
        dshape = () if drag is None else drag.shape[:-1]
        batch = broadcast_shapes(R.shape[:-2], aT.shape, v.shape[:-1], dshape)
        R = R.expand(*batch, 3, 3)
        aT = aT.expand(batch)
        eye = torch.eye(3, dtype=u.dtype, device=u.device).expand(*batch, 3, 3)
        zero = u.new_zeros(*batch, 3, 3)
        # a_T R ⌊e₃⌋: ⌊e₃⌋ has columns (e₂, −e₁, 0), so its product with R has columns (r₂, −r₁, 0)
        Re3x = torch.stack([R[..., :, 1], -R[..., :, 0], R.new_zeros(*batch, 3)], -1)
        Jvv, Jvth = zero, aT[..., None, None] * Re3x
        if drag is not None:
            Dv, Dth = _drag_jacobians(R, v.expand(*batch, 3), drag.expand(*batch, 3))
            Jvv, Jvth = Dv, Jvth + Dth
        Jx = torch.cat([
            torch.cat([zero, eye, zero], -1),
            torch.cat([zero, Jvv, Jvth], -1),
            torch.cat([zero, zero, zero], -1),
        ], -2)
        col = u.new_zeros(*batch, 3, 1)
        dT = -R[..., :, 2:3]
        if not _unit_mass(self.mass_scale):
            dT = dT / torch.as_tensor(self.mass_scale, dtype=u.dtype, device=u.device)[..., None, None]
        Ju = torch.cat([
            torch.cat([col, zero], -1),
            torch.cat([dT.expand(*batch, 3, 1), zero], -1),
            torch.cat([col, eye], -1),
        ], -2)
        return Jx, Ju

    def step(self, x: ProductState, u: Tensor, t: int = 0) -> ProductState:
        """``x ⊕ Δt f(x, u)`` (Eq. 33), unchecked."""
        return self.manifold.oplus(x, self.dt * self.f(x, u), check=False)


@dataclass(frozen=True, eq=False)
class QuadrotorSimulator:
    """The "real" quadrotor (module docstring): RK4 on ``p``, ``v`` at ``substeps`` steps per control
    period, exact attitude, saturation, optional rotor drag and mass error.

    Attributes:
        model: the :class:`Quadrotor` whose ``dt``, ``gravity``, limits and own ``mass_scale``/``drag`` are
            used (the simulator's mismatch comes on top: mass scales multiply, drag coefficients add).
        substeps: integration steps per control period.
        drag: ``None`` or ``(d_x, d_y, d_z)`` rotor-drag coefficients (1/s): ``a_drag = −R D Rᵀ v``.
        mass_scale: true mass / modelled mass (the thrust acceleration is ``a_T / mass_scale``).
    """

    model: Quadrotor = field(default_factory=Quadrotor)
    substeps: int = 10
    drag: tuple[float, float, float] | None = None
    mass_scale: float = 1.0

    def saturate(self, u: Tensor) -> Tensor:
        """The command the motors can deliver: thrust and rates clipped to the model's limits."""
        lo = torch.tensor(self.model.u_lower, dtype=u.dtype, device=u.device)
        hi = torch.tensor(self.model.u_upper, dtype=u.dtype, device=u.device)
        return torch.minimum(torch.maximum(u, lo), hi)

    def _acc(self, R: Tensor, v: Tensor, aT: Tensor) -> Tensor:
        g = torch.as_tensor(self.model.gravity, dtype=v.dtype, device=v.device)
        a = g[..., None] * _e3(v) - self.model._thrust((aT / self.mass_scale)[..., None]) * R[..., :, 2]
        if self.drag is not None:
            a = a + _drag_acc(R, v, _drag_diag(self.drag, v))
        if not _no_drag(self.model.drag):
            a = a + _drag_acc(R, v, _drag_diag(self.model.drag, v))
        return a

    def step(self, x: ProductState, u: Tensor) -> ProductState:
        """One control period from ``x`` under the (saturated) command ``u``."""
        u = self.saturate(u)
        aT, w = u[..., 0], u[..., 1:]
        p, v, R0 = x["p"], x["v"], x["R"]
        batch = broadcast_shapes(p.shape[:-1], u.shape[:-1])
        p, v, R0 = p.expand(*batch, 3), v.expand(*batch, 3), R0.expand(*batch, 3, 3)
        aT, w = aT.expand(batch), w.expand(*batch, 3)
        h = self.model.dt / self.substeps
        half = so3.exp(w * (h / 2))
        R = R0
        for _ in range(self.substeps):
            Rm = R @ half
            R1 = Rm @ half
            k1v, k1p = self._acc(R, v, aT), v
            k2v, k2p = self._acc(Rm, v + h / 2 * k1v, aT), v + h / 2 * k1v
            k3v, k3p = self._acc(Rm, v + h / 2 * k2v, aT), v + h / 2 * k2v
            k4v, k4p = self._acc(R1, v + h * k3v, aT), v + h * k3v
            p = p + h / 6 * (k1p + 2 * k2p + 2 * k3p + k4p)
            v = v + h / 6 * (k1v + 2 * k2v + 2 * k3v + k4v)
            R = R1
        R = R0 @ so3.exp(w * self.model.dt)  # exact over the whole period (no drift from the products)
        return ProductState({"p": p, "v": v, "R": R}, {"p": 1, "v": 1, "R": 2})
