"""Planar bicopter (seed 004 §9.16, ``iLQR_bicopter``): a batched model shared by the MPC, the simulator and
the environments.

State ``x = [x₁, x₂, θ, ẋ₁, ẋ₂, θ̇]`` (horizontal and vertical position, roll angle and their rates),
control ``u = [u₁, u₂]`` (thrusts of the two propellers, rotor 1 on the ``+x₁`` side at ``θ = 0``); mass
``m``, inertia ``I``, arm ``ℓ`` (distance of each propeller to the centre), gravity ``g``.  The seed's
equations::

    ẍ₁ = -(u₁ + u₂) sin θ / m,    ẍ₂ = (u₁ + u₂) cos θ / m - g,    θ̈ = ℓ (u₁ - u₂) / I.

With ``hover_relative=True`` the controls are the thrusts' deviations from the hover thrust ``m g / 2``
of each rotor (thrust ``u_i + m g/2``), so ``u = 0`` hovers at ``θ = 0`` exactly (the gravity terms become
``-g sin θ`` and ``g (cos θ - 1) = -2 g sin²(θ/2)``): a symmetric control box ``|u_i| ≤ m g/2`` is then the
physical thrust range ``[0, m g]`` per rotor (thrust-to-weight ratio 2), which is what a normalized action
in ``[-1, 1]`` maps to (:class:`learning.envs.bicopter.BicopterHover`).

Discretized by semi-implicit Euler (:mod:`controllers.systems._mechanical`), like the other mechanical
models, with exact analytic Jacobians.  (The seed converts its linearization, Eq. 120, to discrete time by
explicit Euler, Eq. 192; the semi-implicit step has the same first-order accuracy and is the project's
convention for second-order systems.)  Parameters are floats or tensors broadcasting against the batch
dims of the state.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from controllers.dynamics import NonlinearDynamics
from controllers.systems._mechanical import check_xu, euler_jacobian, euler_step, param, shape_of
from torchlie._batch import broadcast_shapes

__all__ = ["Bicopter"]


@dataclass(frozen=True, eq=False)
class Bicopter:
    """Batched planar bicopter ``x = [x₁, x₂, θ, ẋ₁, ẋ₂, θ̇]``, ``u = [u₁, u₂]`` (rotor thrusts).

    Attributes:
        mass, inertia, arm, gravity: floats or tensors broadcasting against ``x.shape[:-1]``.
        dt: time step of :meth:`step`.
        hover_relative: controls are deviations from the hover thrust ``m g/2`` per rotor (module
            docstring); ``False`` (default) is the seed's absolute thrusts.
    """

    mass: Tensor | float = 2.5
    inertia: Tensor | float = 1.2
    arm: Tensor | float = 0.5
    gravity: Tensor | float = 9.81
    dt: Tensor | float = 0.05
    hover_relative: bool = False

    n = 6
    m = 2
    #: ``step``/``jacobian`` ignore ``t`` and take any leading dims (:class:`controllers.dynamics.System`)
    time_invariant = True

    def _params(self, x: Tensor):
        return tuple(param(getattr(self, k), x, k, "Bicopter")
                     for k in ("mass", "inertia", "arm", "gravity", "dt"))

    def hover_thrust(self) -> Tensor | float:
        """Thrust ``m g / 2`` of each rotor at hover."""
        return self.mass * self.gravity / 2

    def acceleration(self, x: Tensor, u: Tensor) -> Tensor:
        """``[ẍ₁, ẍ₂, θ̈] (*B, 3)`` from ``x (*B, 6)`` and ``u (*B, 2)``."""
        check_xu(x, u, 6, 2, "Bicopter.acceleration")
        mass, inertia, arm, g, _ = self._params(x)
        th = x[..., 2]
        u1, u2 = u[..., 0], u[..., 1]
        s, c = torch.sin(th), torch.cos(th)
        T = u1 + u2
        a1 = -T * s / mass
        if self.hover_relative:
            a1 = a1 - g * s
            sh = torch.sin(0.5 * th)
            a2 = T * c / mass - 2 * g * sh * sh
        else:
            a2 = T * c / mass - g
        a3 = (u1 - u2) * (arm / inertia)
        return torch.stack(torch.broadcast_tensors(a1, a2, a3), dim=-1)

    def derivative(self, x: Tensor, u: Tensor) -> Tensor:
        """Continuous-time ``ẋ = [ẋ₁, ẋ₂, θ̇, ẍ₁, ẍ₂, θ̈]``."""
        acc = self.acceleration(x, u)
        return torch.cat([x[..., 3:6].expand(*acc.shape[:-1], 3), acc], dim=-1)

    def step(self, x: Tensor, u: Tensor, t: int = 0) -> Tensor:
        """``x_{t+1} (*B, 6)`` by semi-implicit Euler; ``t`` is ignored (time-invariant)."""
        acc = self.acceleration(x, u)
        dt = param(self.dt, x, "dt", "Bicopter")
        if isinstance(dt, Tensor):
            dt = dt.expand(acc.shape[:-1])
        if x.shape[:-1] != acc.shape[:-1]:
            x = x.expand(*acc.shape[:-1], 6)
        return euler_step(x, acc, dt)

    def jacobian(self, x: Tensor, u: Tensor, t: int = 0) -> tuple[Tensor, Tensor]:
        """Analytic ``(A (*B, 6, 6), B (*B, 6, 2))`` of :meth:`step` (seed Eq. 120 through the step)."""
        check_xu(x, u, 6, 2, "Bicopter.jacobian")
        mass, inertia, arm, g, dt = self._params(x)
        th = x[..., 2]
        bs = broadcast_shapes(x.shape[:-1], u.shape[:-1], shape_of(mass, inertia, arm, g, dt))
        s, c = torch.sin(th), torch.cos(th)
        T = u[..., 0] + u[..., 1]
        if self.hover_relative:
            T = T + mass * g
        zero = torch.zeros(bs, dtype=x.dtype, device=x.device)
        e = lambda v: (zero + v).expand(bs)  # noqa: E731 - a float or tensor as a (*B,) tensor
        col = torch.stack([e(-T * c / mass), e(-T * s / mass), zero], -1)  # ∂a/∂θ
        a_q = torch.stack([zero.unsqueeze(-1).expand(*bs, 3), zero.unsqueeze(-1).expand(*bs, 3), col], -1)
        a_v = torch.zeros(*bs, 3, 3, dtype=x.dtype, device=x.device)
        k = e(arm / inertia)
        a_u = torch.stack([torch.stack([e(-s / mass)] * 2, -1), torch.stack([e(c / mass)] * 2, -1),
                           torch.stack([k, -k], -1)], -2)
        return euler_jacobian(a_q, a_v, a_u, dt.expand(bs) if isinstance(dt, Tensor) else dt)

    def energy(self, x: Tensor) -> Tensor:
        """Mechanical energy ``½ m (ẋ₁² + ẋ₂²) + ½ I θ̇² + m g x₂`` ``(*B,)``."""
        mass, inertia, _, g, _ = self._params(x)
        v1, v2, om = x[..., 3], x[..., 4], x[..., 5]
        return 0.5 * mass * (v1 * v1 + v2 * v2) + 0.5 * inertia * om * om + mass * g * x[..., 1]

    def dynamics(self):
        """This model as a :class:`controllers.dynamics.NonlinearDynamics` (analytic Jacobians)."""
        return NonlinearDynamics(f=self.step, n=6, m=2, jacobian=self.jacobian, time_invariant=True)
