"""Continuous cart-pole swing-up on :class:`controllers.systems.CartPole`.

The classic differentiable-MPC task: the pole starts hanging (``θ ≈ 0``) and must be swung up to
``θ = π`` and balanced with a bounded horizontal force, the cart staying on a track of half-length 2.4 m
and under speed limits of 10 m/s (cart) and 25 rad/s (pole); leaving the track or exceeding a limit
terminates the episode.  Reward in ``[0, 1]`` per step (a product of smooth factors in the
manner of the DeepMind control suite's swing-up, so ending the episode early is never attractive)::

    r = (1 + cos φ)/2 · (1 + exp(-p²))/2 · (4 + 1 - a²)/5 · (1 + exp(-ω²/10))/2,

φ = θ − π the angle from upright, ``a = F/F_max`` the normalized action.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
import torch
from torch import Tensor

from controllers.systems import CartPole
from learning.envs._canvas import Canvas
from learning.envs.task import Task, angle_wrap, hi, lo, terminal_weighted

__all__ = ["CartPoleSwingUp"]


@dataclass(frozen=True, eq=False)
class CartPoleSwingUp(Task):
    """Swing up and balance (observation ``[p, cos φ, sin φ, ṗ, ω]``, φ = 0 upright).

    Success: ``|φ| < 0.2`` rad, ``|p| < 0.5`` m and ``|ω| < 1`` rad/s at the end of the episode; error
    ``|φ|``.  Initial state: ``p, θ, ṗ, ω`` uniform in ``±(0.2, 0.2, 0.2, 0.2)`` around hanging at rest.
    """

    name: ClassVar[str] = "CartPoleSwingUp"
    obs_dim: ClassVar[int] = 5
    n_noise: ClassVar[int] = 4

    model: CartPole = field(default_factory=lambda: CartPole(cart_mass=1.0, pole_mass=0.3, length=0.5,
                                                             gravity=9.81, dt=0.05))
    max_force: float = 10.0
    track_limit: float = 2.4
    speed_limit: float = 10.0
    rate_limit: float = 25.0
    max_episode_steps: int = 200

    @property
    def system(self) -> CartPole:
        return self.model

    def u_max(self) -> tuple[float, ...]:
        return (self.max_force,)

    def obs_high(self) -> np.ndarray:
        # Every step starts inside the limits (|ṗ| ≤ v, |ω| ≤ w, else the episode has ended), where
        # |p̈| ≤ (F + m_p(l w² + g))/m_c and |θ̈| ≤ (F + m_p l w² + (m_c + m_p) g)/(l m_c) (D ≥ m_c), so
        # one semi-implicit Euler step ends within these bounds.
        md, F, v, w = self.model, self.max_force, self.speed_limit, self.rate_limit
        mc, mp, g, dt = lo(md.cart_mass), hi(md.pole_mass), hi(md.gravity), hi(md.dt)
        pd = v + dt * (F + mp * (hi(md.length) * w * w + g)) / mc
        om = w + dt * ((F + (hi(md.cart_mass) + mp) * g) / (lo(md.length) * mc) + mp * w * w / mc)
        return np.array([self.track_limit + dt * pd, 1.0, 1.0, pd, om])

    def initial_state(self, noise: Tensor) -> Tensor:
        return (2 * noise - 1) * 0.2

    def observe(self, x: Tensor) -> Tensor:
        th = x[..., 1]
        return torch.stack([x[..., 0], -torch.cos(th), -torch.sin(th), x[..., 2], x[..., 3]], -1)

    def reward(self, x: Tensor, u: Tensor, x_next: Tensor) -> Tensor:
        p, th, om = x_next[..., 0], x_next[..., 1], x_next[..., 3]
        a = u[..., 0] / self.max_force
        upright = 0.5 - 0.5 * torch.cos(th)  # (1 + cos φ)/2
        centered = 0.5 + 0.5 * torch.exp(-p * p)
        small_u = (5 - a * a) / 5
        slow = 0.5 + 0.5 * torch.exp(-0.1 * om * om)
        return upright * centered * small_u * slow

    def terminated(self, x: Tensor) -> Tensor:
        """Off the track, or faster than the cart's or the pole's speed limit."""
        return ((x[..., 0].abs() > self.track_limit) | (x[..., 2].abs() > self.speed_limit)
                | (x[..., 3].abs() > self.rate_limit))

    def error(self, x: Tensor) -> Tensor:
        return angle_wrap(x[..., 1] - math.pi).abs()

    def success(self, x: Tensor) -> Tensor:
        return (self.error(x) < 0.2) & (x[..., 0].abs() < 0.5) & (x[..., 3].abs() < 1.0)

    def state_from_obs(self, obs: Tensor) -> Tensor:
        theta = torch.atan2(-obs[..., 2], -obs[..., 1])
        return torch.stack([obs[..., 0], theta, obs[..., 3], obs[..., 4]], -1)

    def mpc_cost(self, horizon: int, *, dtype=torch.float64, device=None):
        from controllers.costs import QuadraticCost

        kw = dict(dtype=dtype, device=device)
        Q = terminal_weighted(torch.tensor([1.0, 1.0, 0.1, 0.1], **kw), horizon, 100.0)
        x_ref = torch.tensor([0.0, math.pi, 0.0, 0.0], **kw)
        return QuadraticCost(Q=Q, R=torch.tensor([[0.01]], **kw), x_ref=x_ref)

    def frame(self, x: np.ndarray, size: int = 256) -> np.ndarray:
        cv = Canvas(size, extent=self.track_limit + 0.4)
        L = 2 * float(self.model.length)  # drawn at twice the pendulum length for visibility
        p, th = float(x[0]), float(x[1])
        cv.hline(0.0, (120, 120, 120))
        for s in (-1, 1):
            cv.segment((s * self.track_limit, -0.2), (s * self.track_limit, 0.2), 0.03, (0, 0, 0))
        tip = (p + L * math.sin(th), -L * math.cos(th))
        cv.rectangle((p, 0.0), 0.25, 0.12, 0.0, (60, 90, 160))
        cv.segment((p, 0.0), tip, 0.06, (204, 153, 77))
        cv.disc(tip, 0.06, (150, 100, 40))
        return cv.img
