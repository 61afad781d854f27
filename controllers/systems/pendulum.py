"""Torque-driven pendulum: a batched model shared by the MPC, the simulator and the environments.

State ``x = [θ, ω]`` with ``θ = 0`` hanging down and ``θ = π`` upright; control ``u = [τ]`` (torque)::

    m l² ω̇ = τ - b ω - m g l sin θ,

discretized by semi-implicit Euler (:mod:`controllers.systems._mechanical`) with exact analytic Jacobians.
Parameters (mass, length, damping, gravity, dt) are floats or tensors broadcasting against the batch dims
of the state, so gradients with respect to a physical parameter flow through :meth:`step` and
:meth:`jacobian`.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from controllers.dynamics import NonlinearDynamics
from controllers.systems._mechanical import check_xu, euler_jacobian, euler_step, param, shape_of
from torchlie._batch import broadcast_shapes

__all__ = ["Pendulum"]


@dataclass(frozen=True, eq=False)
class Pendulum:
    """Batched pendulum ``x = [θ, ω]``, ``u = [τ]`` (``θ = 0`` down, ``θ = π`` up).

    Attributes:
        mass, length, damping, gravity: floats or tensors broadcasting against ``x.shape[:-1]``.
        dt: time step of :meth:`step` (float or tensor).
    """

    mass: Tensor | float = 1.0
    length: Tensor | float = 1.0
    damping: Tensor | float = 0.0
    gravity: Tensor | float = 9.81
    dt: Tensor | float = 0.05

    n = 2
    m = 1
    #: ``step``/``jacobian`` ignore ``t`` and take any leading dims (:class:`controllers.dynamics.System`)
    time_invariant = True

    def _params(self, x: Tensor):
        own = "Pendulum"
        return tuple(param(getattr(self, k), x, k, own)
                     for k in ("mass", "length", "damping", "gravity", "dt"))

    def acceleration(self, x: Tensor, u: Tensor) -> Tensor:
        """``ω̇ (*B, 1)`` from ``x (*B, 2)`` and ``u (*B, 1)``."""
        check_xu(x, u, 2, 1, "Pendulum.acceleration")
        mass, length, b, g, _ = self._params(x)
        th, om = x[..., 0], x[..., 1]
        ml2 = mass * length * length
        if not any(isinstance(v, Tensor) for v in (mass, length, b, g)):
            # float parameters: scalar factors fused into the kernels (no scalar tensors)
            acc = torch.sub(u[..., 0], om, alpha=b).div_(ml2).sub_(torch.sin(th), alpha=g / length)
            return acc.unsqueeze(-1)
        return ((u[..., 0] - b * om) / ml2 - g / length * torch.sin(th)).unsqueeze(-1)

    def derivative(self, x: Tensor, u: Tensor) -> Tensor:
        """Continuous-time ``ẋ = [ω, ω̇]``."""
        return torch.cat([x[..., 1:2], self.acceleration(x, u)], dim=-1)

    def step(self, x: Tensor, u: Tensor, t: int = 0) -> Tensor:
        """``x_{t+1} (*B, 2)`` by semi-implicit Euler; ``t`` is ignored (time-invariant)."""
        acc = self.acceleration(x, u)
        dt = param(self.dt, x, "dt", "Pendulum")
        if isinstance(dt, Tensor):
            dt = dt.expand(acc.shape[:-1])
        if x.shape[:-1] != acc.shape[:-1]:
            x = x.expand(*acc.shape[:-1], 2)
        return euler_step(x, acc, dt)

    def jacobian(self, x: Tensor, u: Tensor, t: int = 0) -> tuple[Tensor, Tensor]:
        """Analytic ``(A (*B, 2, 2), B (*B, 2, 1))`` of :meth:`step`."""
        check_xu(x, u, 2, 1, "Pendulum.jacobian")
        mass, length, b, g, dt = self._params(x)
        bs = broadcast_shapes(x.shape[:-1], u.shape[:-1], shape_of(mass, length, b, g, dt))
        ml2 = mass * length * length
        full = lambda v: (v if isinstance(v, Tensor) else torch.tensor(v, dtype=x.dtype, device=x.device)
                          ).expand(bs)[..., None, None]
        a_q = full(-g / length * torch.cos(x[..., 0]))
        a_v = full(-b / ml2)
        a_u = full(1.0 / ml2)
        return euler_jacobian(a_q, a_v, a_u, dt.expand(bs) if isinstance(dt, Tensor) else dt)

    def energy(self, x: Tensor) -> Tensor:
        """Mechanical energy ``½ m l² ω² + m g l (1 - cos θ)`` ``(*B,)``."""
        mass, length, _, g, _ = self._params(x)
        return 0.5 * mass * length**2 * x[..., 1] ** 2 + mass * g * length * (1 - torch.cos(x[..., 0]))

    def dynamics(self):
        """This model as a :class:`controllers.dynamics.NonlinearDynamics` (analytic Jacobians)."""
        return NonlinearDynamics(f=self.step, n=2, m=1, jacobian=self.jacobian, time_invariant=True)
