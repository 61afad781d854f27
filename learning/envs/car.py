"""Car parking on :class:`controllers.systems.Car` (seed 004 §9.15, the acceleration-controlled car).

The car starts at rest with straight wheels at a random pose — rear-axle position uniform in the square
``±start_range`` around the parking spot, heading uniform in ``[-π, π)`` — and must park at the origin
facing ``+x₁`` (``x₁ = x₂ = 0``, ``θ = 0``) and stop there.  Controls: rear-wheel acceleration
``|u₁| ≤ max_accel`` and steering velocity ``|u₂| ≤ max_steer_rate``.  The episode terminates when the car
leaves the lot (``|x₁|`` or ``|x₂| > area_limit``), drives faster than ``speed_limit`` or steers beyond
``steer_limit`` (the steering lock, 1.3 rad, below the singularity at ``|ϕ| = π/2``), as the cart-pole
terminates off its track; these limits make the observation bounds finite.  Reward in ``[0, 1]`` per step
(a product of smooth factors, so ending the episode early is never attractive)::

    r = 1/(1 + ‖p‖²) · (3 + cos θ)/4 · (1 + exp(-v²))/2 · (1 - ‖a‖²/10),

``p = (x₁, x₂)``, ``a = (u₁/max_accel, u₂/max_steer_rate)`` the normalized action.  The seed gives the model
but no numbers; the wheelbase (0.5 m), the step (0.1 s, explicit Euler as the seed's Eq. 192) and the
limits here are this task's choices.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
import torch
from torch import Tensor

from controllers.systems import Car
from learning.envs._canvas import Canvas
from learning.envs.task import Task, angle_wrap, terminal_weighted

__all__ = ["CarParking"]


def _hi(v) -> float:
    """Largest value of a float or tensor model parameter, exactly (``task.hi`` rounds through float32)."""
    return float(v.detach().max()) if isinstance(v, Tensor) else float(v)


@dataclass(frozen=True, eq=False)
class CarParking(Task):
    """Park at the origin facing ``+x₁`` (observation ``[x₁, x₂, cos θ, sin θ, v, ϕ]``).

    Success: ``‖p‖ < 0.1`` m, ``|θ| < 0.1`` rad and ``|v| < 0.1`` m/s at the end of the episode; error
    ``‖p‖`` (m).  Initial state: ``x₁, x₂`` uniform in ``±start_range``, ``θ`` uniform in ``[-π, π)``,
    ``v = ϕ = 0``.
    """

    name: ClassVar[str] = "CarParking"
    obs_dim: ClassVar[int] = 6
    n_noise: ClassVar[int] = 3

    model: Car = field(default_factory=lambda: Car(length=0.5, dt=0.1))
    max_accel: float = 1.0
    max_steer_rate: float = 1.0
    start_range: float = 2.0
    area_limit: float = 5.0
    speed_limit: float = 2.0
    steer_limit: float = 1.3
    max_episode_steps: int = 200

    @property
    def system(self) -> Car:
        return self.model

    def u_max(self) -> tuple[float, ...]:
        return (self.max_accel, self.max_steer_rate)

    def obs_high(self) -> np.ndarray:
        # Every step starts inside the limits (|x₁|, |x₂| ≤ X, |v| ≤ V, |ϕ| ≤ Φ, else the episode has
        # ended; the initial states are inside), and one explicit Euler step moves the position by at most
        # dt·|v| ≤ dt·V, the speed by dt·max_accel and the steering angle by dt·max_steer_rate.
        dt, X, V, P = _hi(self.model.dt), self.area_limit, self.speed_limit, self.steer_limit
        # (A relative 1e-6 on top covers the rounding of a float32 simulation.)
        pos, slack = X + dt * V, 1.0 + 1e-6
        return np.array([pos * slack, pos * slack, 1.0, 1.0, (V + dt * self.max_accel) * slack,
                         (P + dt * self.max_steer_rate) * slack])

    def initial_state(self, noise: Tensor) -> Tensor:
        pos = (2 * noise[..., :2] - 1) * self.start_range
        th = (2 * noise[..., 2:3] - 1) * math.pi
        return torch.cat([pos, th, torch.zeros_like(pos)], -1)

    def observe(self, x: Tensor) -> Tensor:
        th = x[..., 2]
        return torch.stack([x[..., 0], x[..., 1], torch.cos(th), torch.sin(th), x[..., 3], x[..., 4]], -1)

    def reward(self, x: Tensor, u: Tensor, x_next: Tensor) -> Tensor:
        p1, p2, th, v = x_next[..., 0], x_next[..., 1], x_next[..., 2], x_next[..., 3]
        a1, a2 = u[..., 0] / self.max_accel, u[..., 1] / self.max_steer_rate
        near = 1.0 / (1.0 + p1 * p1 + p2 * p2)
        aligned = 0.75 + 0.25 * torch.cos(th)
        slow = 0.5 + 0.5 * torch.exp(-v * v)
        small_u = 1.0 - 0.1 * (a1 * a1 + a2 * a2)
        return near * aligned * slow * small_u

    def terminated(self, x: Tensor) -> Tensor:
        """Out of the lot, faster than the speed limit or steering beyond the lock."""
        X = self.area_limit
        return ((x[..., 0].abs() > X) | (x[..., 1].abs() > X) | (x[..., 3].abs() > self.speed_limit)
                | (x[..., 4].abs() > self.steer_limit))

    #: distance to the speed and steering limits that :meth:`safe_action_box` keeps
    safety_margin: ClassVar[float] = 0.05

    def safe_action_box(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """Actions whose next speed and steering angle stay ``safety_margin`` inside ``speed_limit`` and
        ``steer_limit`` (one explicit Euler step: ``v⁺ = v + dt u₁``, ``ϕ⁺ = ϕ + dt u₂``).  The iLQR MPC has
        no state constraints; without this filter it steered past the lock in 2 of 16 held-out episodes."""
        dt = float(torch.as_tensor(self.model.dt).max())
        kw = dict(dtype=x.dtype, device=x.device)
        lim = torch.tensor([self.speed_limit, self.steer_limit], **kw) - self.safety_margin
        rate = dt * torch.tensor([self.max_accel, self.max_steer_rate], **kw)
        s = x[..., 3:5]
        one = torch.ones((), dtype=x.dtype, device=x.device)
        hi = ((lim - s) / rate).clamp(-one, one)
        lo = ((-lim - s) / rate).clamp(-one, one)
        return torch.minimum(lo, hi), hi

    def error(self, x: Tensor) -> Tensor:
        return torch.hypot(x[..., 0], x[..., 1])

    def success(self, x: Tensor) -> Tensor:
        return (self.error(x) < 0.1) & (angle_wrap(x[..., 2]).abs() < 0.1) & (x[..., 3].abs() < 0.1)

    def state_from_obs(self, obs: Tensor) -> Tensor:
        """The state with the heading wrapped to ``(-π, π]`` (what an MPC on :meth:`mpc_cost` must be given:
        its quadratic heading term then turns the short way)."""
        th = torch.atan2(obs[..., 3], obs[..., 2])
        return torch.stack([obs[..., 0], obs[..., 1], th, obs[..., 4], obs[..., 5]], -1)

    def mpc_cost(self, horizon: int, *, dtype=torch.float64, device=None):
        """Quadratic cost to the parked state ``0`` (controls in physical units).  The heading term is
        quadratic in ``θ``: plan from :meth:`state_from_obs` (heading in ``(-π, π]``)."""
        from controllers.costs import QuadraticCost

        kw = dict(dtype=dtype, device=device)
        Q = terminal_weighted(torch.tensor([1.0, 3.0, 0.3, 0.1, 1.0], **kw), horizon, 100.0)
        return QuadraticCost(Q=Q, R=torch.diag(torch.tensor([0.01, 0.01], **kw)),
                             x_ref=torch.zeros(5, **kw))

    def frame(self, x: np.ndarray, size: int = 256) -> np.ndarray:
        cv = Canvas(size, extent=self.area_limit + 0.3)
        L = float(torch.as_tensor(self.model.length).mean())
        X = self.area_limit
        for a, b in (((-X, -X), (X, -X)), ((X, -X), (X, X)), ((X, X), (-X, X)), ((-X, X), (-X, -X))):
            cv.segment(a, b, 0.06, (0, 0, 0))
        # the parking spot (car outline at the target pose) and its axis
        cv.rectangle((L / 2, 0.0), L / 2 + 0.25, 0.3, 0.0, (200, 230, 200))
        cv.segment((0.0, 0.0), (L, 0.0), 0.04, (80, 160, 80))
        p1, p2, th, phi = float(x[0]), float(x[1]), float(x[2]), float(x[4])
        c, s = math.cos(th), math.sin(th)
        mid = (p1 + c * L / 2, p2 + s * L / 2)
        cv.rectangle(mid, L / 2 + 0.2, 0.22, th, (60, 90, 160))
        front = (p1 + c * L, p2 + s * L)
        d = 0.15  # front wheel, drawn along the steering direction
        cv.segment((front[0] - d * math.cos(th + phi), front[1] - d * math.sin(th + phi)),
                   (front[0] + d * math.cos(th + phi), front[1] + d * math.sin(th + phi)), 0.08, (20, 20, 20))
        cv.segment((p1 - d * c, p2 - d * s), (p1 + d * c, p2 + d * s), 0.08, (20, 20, 20))
        return cv.img
