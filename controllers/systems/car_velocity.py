"""Car steering with velocity control (seed 004 §9.15, ``iLQR_car``, "Velocity Control Input"): a batched
kinematic car whose rear-wheel speed is a control, next to :class:`controllers.systems.car.Car` (the
acceleration-input variant, where the speed is a state).

State ``x = [x₁, x₂, θ, ϕ]`` (rear-axle position, heading, front-wheel steering angle), control
``u = [u₁, u₂]`` (rear-wheel velocity, steering velocity), wheelbase ``ℓ``; the seed's equations::

    ẋ₁ = u₁ cos θ,   ẋ₂ = u₁ sin θ,   θ̇ = (u₁/ℓ) tan ϕ,   ϕ̇ = u₂.

Discretized as in the seed (Eq. 192, ``A = I + A_c Δt``, ``B = B_c Δt``), i.e. by **explicit Euler**
``x⁺ = x + Δt f(x, u)``, so :meth:`CarVelocity.jacobian` is exactly the seed's linearization (Eq. 118)
converted by Eq. 192 — the analytic Jacobian of :meth:`CarVelocity.step`.  The model is singular at
``|ϕ| = π/2``.

Parameters (wheelbase, dt) are floats or tensors broadcasting against the batch dims of the state.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from controllers.dynamics import NonlinearDynamics
from controllers.systems._mechanical import check_xu, param, shape_of
from torchlie._batch import broadcast_shapes

__all__ = ["CarVelocity"]


@dataclass(frozen=True, eq=False)
class CarVelocity:
    """Batched kinematic car ``x = [x₁, x₂, θ, ϕ]``, ``u = [u₁, u₂]`` (rear-wheel speed, steering rate).

    Attributes:
        length: wheelbase ℓ (m), float or tensor broadcasting against ``x.shape[:-1]``.
        dt: time step of the explicit Euler :meth:`step` (float or tensor).
    """

    length: Tensor | float = 0.5
    dt: Tensor | float = 0.1

    n = 4
    m = 2
    #: ``step``/``jacobian`` ignore ``t`` and take any leading dims (:class:`controllers.dynamics.System`)
    time_invariant = True

    def __post_init__(self) -> None:
        for k in ("length", "dt"):
            v = getattr(self, k)
            if isinstance(v, bool) or not isinstance(v, (int, float, Tensor)):
                raise TypeError(f"CarVelocity: field '{k}' must be a float or a tensor, got "
                                f"{type(v).__name__}")
            if not isinstance(v, Tensor) and not float(v) > 0:
                raise ValueError(f"CarVelocity: field '{k}' must be positive, got {v!r}")

    def _params(self, x: Tensor):
        return tuple(param(getattr(self, k), x, k, "CarVelocity") for k in ("length", "dt"))

    def derivative(self, x: Tensor, u: Tensor) -> Tensor:
        """Continuous-time ``ẋ = f(x, u) (*B, 4)`` (the seed's equations)."""
        check_xu(x, u, 4, 2, "CarVelocity.derivative")
        length, _ = self._params(x)
        th, ph, v = x[..., 2], x[..., 3], u[..., 0]
        f = (v * torch.cos(th), v * torch.sin(th), v * torch.tan(ph) / length, u[..., 1])
        return torch.stack(torch.broadcast_tensors(*f), dim=-1)

    def step(self, x: Tensor, u: Tensor, t: int = 0) -> Tensor:
        """``x_{t+1} = x_t + Δt f(x_t, u_t)`` ``(*B, 4)`` (explicit Euler, seed Eq. 192); ``t`` is ignored."""
        f = self.derivative(x, u)
        dt = param(self.dt, x, "dt", "CarVelocity")
        if isinstance(dt, Tensor):
            return x + dt.unsqueeze(-1) * f
        return x + dt * f

    def jacobian(self, x: Tensor, u: Tensor, t: int = 0) -> tuple[Tensor, Tensor]:
        """Analytic ``(A (*B, 4, 4), B (*B, 4, 2))`` of :meth:`step`: seed Eq. 118 through Eq. 192::

            A = I + Δt [[0, 0, -u₁ sin θ, 0], [0, 0, u₁ cos θ, 0], [0, 0, 0, (u₁/ℓ)(tan²ϕ + 1)], [0, 0, 0, 0]]
            B = Δt [[cos θ, 0], [sin θ, 0], [tan(ϕ)/ℓ, 0], [0, 1]]
        """
        check_xu(x, u, 4, 2, "CarVelocity.jacobian")
        length, dt = self._params(x)
        th, ph, v = x[..., 2], x[..., 3], u[..., 0]
        bs = broadcast_shapes(x.shape[:-1], u.shape[:-1], shape_of(length, dt))
        c, s, tn = torch.cos(th), torch.sin(th), torch.tan(ph)
        dtv = dt * v
        zero = torch.zeros(bs, dtype=x.dtype, device=x.device)
        one = torch.ones(bs, dtype=x.dtype, device=x.device)
        rows = (
            (one, zero, -dtv * s, zero),
            (zero, one, dtv * c, zero),
            (zero, zero, one, dtv * (1 + tn * tn) / length),
            (zero, zero, zero, one),
        )
        A = torch.stack([torch.stack([(e + zero).expand(bs) for e in r], -1) for r in rows], -2)
        brows = ((dt * c, zero), (dt * s, zero), (dt * tn / length, zero), (zero, zero + dt))
        B = torch.stack([torch.stack([(e + zero).expand(bs) for e in r], -1) for r in brows], -2)
        return A, B

    def dynamics(self) -> NonlinearDynamics:
        """This model as a :class:`controllers.dynamics.NonlinearDynamics` (analytic Jacobians)."""
        return NonlinearDynamics(f=self.step, n=4, m=2, jacobian=self.jacobian, time_invariant=True)
