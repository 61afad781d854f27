"""Cart-pole: a batched model shared by the MPC, the simulator and the environments.

State ``x = [p, θ, ṗ, θ̇]`` (cart position, pole angle with ``θ = 0`` hanging down and ``θ = π`` upright),
control ``u = [F]`` (horizontal force on the cart).  Point mass ``m_p`` at distance ``l`` on a massless pole,
cart mass ``m_c``, no friction.  From the Lagrangian, with ``s = sin θ``, ``c = cos θ``,
``D = m_c + m_p s²``::

    p̈ = (F + m_p s (l θ̇² + g c)) / D
    θ̈ = -(F c + m_p l θ̇² s c + (m_c + m_p) g s) / (l D)

discretized by semi-implicit Euler (:mod:`controllers.systems._mechanical`) with exact analytic Jacobians.
Parameters are floats or tensors broadcasting against the batch dims of the state.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from controllers.dynamics import NonlinearDynamics
from controllers.systems._mechanical import check_xu, euler_jacobian, euler_step, param, shape_of
from torchlie._batch import broadcast_shapes

__all__ = ["CartPole"]


@dataclass(frozen=True, eq=False)
class CartPole:
    """Batched cart-pole ``x = [p, θ, ṗ, θ̇]``, ``u = [F]`` (``θ = 0`` down, ``θ = π`` up).

    Attributes:
        cart_mass, pole_mass, length, gravity: floats or tensors broadcasting against ``x.shape[:-1]``.
        dt: time step of :meth:`step`.
    """

    cart_mass: Tensor | float = 1.0
    pole_mass: Tensor | float = 0.3
    length: Tensor | float = 0.5
    gravity: Tensor | float = 9.81
    dt: Tensor | float = 0.05

    n = 4
    m = 1
    #: ``step``/``jacobian`` ignore ``t`` and take any leading dims (:class:`controllers.dynamics.System`)
    time_invariant = True

    def _params(self, x: Tensor):
        own = "CartPole"
        return tuple(param(getattr(self, k), x, k, own)
                     for k in ("cart_mass", "pole_mass", "length", "gravity", "dt"))

    def acceleration(self, x: Tensor, u: Tensor) -> Tensor:
        """``[p̈, θ̈] (*B, 2)`` from ``x (*B, 4)`` and ``u (*B, 1)``."""
        check_xu(x, u, 4, 1, "CartPole.acceleration")
        mc, mp, length, g, _ = self._params(x)
        _, th, _, om = x.unbind(-1)
        F = u[..., 0]
        s, c = torch.sin(th), torch.cos(th)
        if not any(isinstance(v, Tensor) for v in (mc, mp, length, g)):
            # float parameters: the same formulas with the scalar factors fused into the kernels
            D = (s * s).mul_(mp).add_(mc)
            pdd = torch.addcmul(F, s, torch.addcmul(c * g, om, om, value=length), value=mp).div_(D)
            B = (om * om).mul_(mp * length).mul_(c).add_((mc + mp) * g)  # m_p l ω² c + (m_c + m_p) g
            thdd = torch.addcmul(c * F, s, B).div_(D).mul_(-1.0 / length)
            return torch.stack(torch.broadcast_tensors(pdd, thdd), dim=-1)
        D = mc + mp * (s * s)
        w2 = om * om
        pdd = (F + mp * s * (length * w2 + g * c)) / D
        thdd = (c * (F + (mp * length) * w2 * s) + ((mc + mp) * g) * s) / (-length * D)
        return torch.stack(torch.broadcast_tensors(pdd, thdd), dim=-1)

    def derivative(self, x: Tensor, u: Tensor) -> Tensor:
        """Continuous-time ``ẋ = [ṗ, θ̇, p̈, θ̈]``."""
        return torch.cat([x[..., 2:4].expand(*self.acceleration(x, u).shape[:-1], 2),
                          self.acceleration(x, u)], dim=-1)

    def step(self, x: Tensor, u: Tensor, t: int = 0) -> Tensor:
        """``x_{t+1} (*B, 4)`` by semi-implicit Euler; ``t`` is ignored (time-invariant)."""
        acc = self.acceleration(x, u)
        dt = param(self.dt, x, "dt", "CartPole")
        if isinstance(dt, Tensor):
            dt = dt.expand(acc.shape[:-1])
        if x.shape[:-1] != acc.shape[:-1]:
            x = x.expand(*acc.shape[:-1], 4)
        return euler_step(x, acc, dt)

    def jacobian(self, x: Tensor, u: Tensor, t: int = 0) -> tuple[Tensor, Tensor]:
        """Analytic ``(A (*B, 4, 4), B (*B, 4, 1))`` of :meth:`step`."""
        check_xu(x, u, 4, 1, "CartPole.jacobian")
        mc, mp, length, g, dt = self._params(x)
        th, om, F = x[..., 1], x[..., 3], u[..., 0]
        bs = broadcast_shapes(th.shape, F.shape, shape_of(mc, mp, length, g, dt))
        s, c = torch.sin(th), torch.cos(th)
        D = mc + mp * s * s
        dD = 2 * mp * s * c
        N1 = F + mp * s * (length * om * om + g * c)
        dN1 = mp * (c * length * om * om + g * (c * c - s * s))
        N2 = -(F * c + mp * length * om * om * s * c + (mc + mp) * g * s)
        dN2 = -(-F * s + mp * length * om * om * (c * c - s * s) + (mc + mp) * g * c)
        pdd_th = (dN1 * D - N1 * dD) / (D * D)
        thdd_th = (dN2 * D - N2 * dD) / (length * D * D)
        pdd_om = 2 * mp * s * length * om / D
        thdd_om = -2 * mp * om * s * c / D
        zero = torch.zeros(bs, dtype=x.dtype, device=x.device)

        def mat(a, b, c_, d):
            a, b, c_, d = (v.expand(bs) for v in (a, b, c_, d))
            return torch.stack([torch.stack([a, b], -1), torch.stack([c_, d], -1)], -2)

        a_q = mat(zero, pdd_th, zero, thdd_th)
        a_v = mat(zero, pdd_om, zero, thdd_om)
        a_u = torch.stack([(1.0 / D).expand(bs), (-c / (length * D)).expand(bs)], -1).unsqueeze(-1)
        return euler_jacobian(a_q, a_v, a_u, dt.expand(bs) if isinstance(dt, Tensor) else dt)

    def energy(self, x: Tensor) -> Tensor:
        """Mechanical energy ``(*B,)`` (kinetic of cart and pole mass plus the pole's potential)."""
        mc, mp, length, g, _ = self._params(x)
        pd, th, om = x[..., 2], x[..., 1], x[..., 3]
        kin = 0.5 * (mc + mp) * pd**2 + mp * length * pd * om * torch.cos(th) + 0.5 * mp * length**2 * om**2
        return kin - mp * g * length * torch.cos(th)

    def dynamics(self):
        """This model as a :class:`controllers.dynamics.NonlinearDynamics` (analytic Jacobians)."""
        return NonlinearDynamics(f=self.step, n=4, m=1, jacobian=self.jacobian, time_invariant=True)
