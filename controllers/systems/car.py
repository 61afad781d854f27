"""Car steering with acceleration control (seed 004 §9.15, ``iLQR_car``): a batched kinematic car shared by
the MPC, the simulator and the environments.

State ``x = [x₁, x₂, θ, v, ϕ]`` (rear-axle position, heading, rear-wheel speed, front-wheel steering angle),
control ``u = [u₁, u₂]`` (rear-wheel acceleration, steering velocity), wheelbase ``ℓ`` (distance between
the axles); the seed's equations::

    ẋ₁ = v cos θ,   ẋ₂ = v sin θ,   θ̇ = (v/ℓ) tan ϕ,   v̇ = u₁,   ϕ̇ = u₂.

Discretized as in the seed (Eq. 192, ``A = I + A_c Δt``, ``B = B_c Δt``), i.e. by **explicit Euler**
``x⁺ = x + Δt f(x, u)``, so :meth:`jacobian` is exactly the seed's linearization (Eq. 119) converted by
Eq. 192 — the analytic Jacobian of :meth:`step`, not an approximation of it.  (The seed's
*velocity-control* variant, ``u₁ = v``, is this model with the speed as a control; it is not provided
separately.)  The model is singular at ``|ϕ| = π/2``: the environments keep ``|ϕ|`` well below it.

Parameters (wheelbase, dt) are floats or tensors broadcasting against the batch dims of the state.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from controllers.dynamics import NonlinearDynamics
from controllers.systems._mechanical import check_xu, param, shape_of
from torchlie._batch import broadcast_shapes

__all__ = ["Car"]


@dataclass(frozen=True, eq=False)
class Car:
    """Batched kinematic car ``x = [x₁, x₂, θ, v, ϕ]``, ``u = [u₁, u₂]`` (acceleration, steering rate).

    Attributes:
        length: wheelbase ℓ (m), float or tensor broadcasting against ``x.shape[:-1]``.
        dt: time step of the explicit Euler :meth:`step` (float or tensor).
    """

    length: Tensor | float = 0.5
    dt: Tensor | float = 0.1

    n = 5
    m = 2
    #: ``step``/``jacobian`` ignore ``t`` and take any leading dims (:class:`controllers.dynamics.System`)
    time_invariant = True

    def _params(self, x: Tensor):
        return tuple(param(getattr(self, k), x, k, "Car") for k in ("length", "dt"))

    def derivative(self, x: Tensor, u: Tensor) -> Tensor:
        """Continuous-time ``ẋ = f(x, u) (*B, 5)`` (the seed's equations)."""
        check_xu(x, u, 5, 2, "Car.derivative")
        length, _ = self._params(x)
        th, v, ph = x[..., 2], x[..., 3], x[..., 4]
        f = (v * torch.cos(th), v * torch.sin(th), v * torch.tan(ph) / length, u[..., 0], u[..., 1])
        return torch.stack(torch.broadcast_tensors(*f), dim=-1)

    def step(self, x: Tensor, u: Tensor, t: int = 0) -> Tensor:
        """``x_{t+1} = x_t + Δt f(x_t, u_t)`` ``(*B, 5)`` (explicit Euler, seed Eq. 192); ``t`` is ignored."""
        f = self.derivative(x, u)
        dt = param(self.dt, x, "dt", "Car")
        if isinstance(dt, Tensor):
            return x + dt.unsqueeze(-1) * f
        return torch.add(x, f, alpha=dt)  # a float step: one fused kernel, no scalar tensor

    def jacobian(self, x: Tensor, u: Tensor, t: int = 0) -> tuple[Tensor, Tensor]:
        """Analytic ``(A (*B, 5, 5), B (*B, 5, 2))`` of :meth:`step`: seed Eq. 119 through Eq. 192."""
        check_xu(x, u, 5, 2, "Car.jacobian")
        length, dt = self._params(x)
        th, v, ph = x[..., 2], x[..., 3], x[..., 4]
        bs = broadcast_shapes(x.shape[:-1], u.shape[:-1], shape_of(length, dt))
        c, s, tn = torch.cos(th), torch.sin(th), torch.tan(ph)
        dtv = dt * v
        zero = torch.zeros(bs, dtype=x.dtype, device=x.device)
        one = torch.ones(bs, dtype=x.dtype, device=x.device)
        dtt = zero + dt  # Δt as a (*B,) tensor
        rows = (
            (one, zero, -dtv * s, dt * c, zero),
            (zero, one, dtv * c, dt * s, zero),
            (zero, zero, one, dt * tn / length, dtv * (1 + tn * tn) / length),
            (zero, zero, zero, one, zero),
            (zero, zero, zero, zero, one),
        )
        A = torch.stack([torch.stack([e.expand(bs) for e in r], -1) for r in rows], -2)
        B = torch.stack([torch.stack([zero, zero], -1), torch.stack([zero, zero], -1),
                         torch.stack([zero, zero], -1), torch.stack([dtt, zero], -1),
                         torch.stack([zero, dtt], -1)], -2)
        return A, B

    def dynamics(self):
        """This model as a :class:`controllers.dynamics.NonlinearDynamics` (analytic Jacobians)."""
        return NonlinearDynamics(f=self.step, n=5, m=2, jacobian=self.jacobian, time_invariant=True)
