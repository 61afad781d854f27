"""Pendulum swing-up on :class:`controllers.systems.Pendulum`.

The parameters reproduce gymnasium's ``Pendulum-v1`` exactly — its rod pendulum
``ω̇ = 3g/(2l) sin φ + 3u/(ml²)`` (g = 10, m = l = 1, φ from upright) is the point-mass model
``ω̇ = -(g'/l') sin θ + u/(m'l'²)`` with ``l' = 2/3``, ``m' = 3/4``, ``g' = 10`` — with the same
semi-implicit Euler step (dt = 0.05), torque limit 2, reward ``-(φ² + 0.1 ω² + 0.001 u²)``, initial
``φ ∈ U[-π, π]``, ``ω ∈ U[-1, 1]`` and 200 steps, so returns compare with published Pendulum-v1 figures.
One difference: Pendulum-v1 clips ``|ω|`` to 8 after each step; here the dynamics are the system's
(one model for MPC, simulator and env) and are not clipped — with a torque limit of 2 the pendulum
reaches ``|ω| ≈ 8`` only when pumped on purpose.  The observation bound on ``|ω|`` is the largest speed
reachable within an episode (about 211 rad/s), as the speed is not clipped.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
import torch
from torch import Tensor

from controllers.systems import Pendulum
from learning.envs._canvas import Canvas
from learning.envs.task import Task, angle_wrap, hi, lo, terminal_weighted

__all__ = ["PendulumSwingUp"]


def _gym_pendulum() -> Pendulum:
    return Pendulum(mass=0.75, length=2.0 / 3.0, damping=0.0, gravity=10.0, dt=0.05)


@dataclass(frozen=True, eq=False)
class PendulumSwingUp(Task):
    """Swing the pendulum up and hold it (observation ``[cos φ, sin φ, ω]``, φ = 0 upright).

    Success: ``|φ| < 0.1`` rad and ``|ω| < 0.5`` rad/s at the end of the episode; error ``|φ|``.
    """

    name: ClassVar[str] = "PendulumSwingUp"
    obs_dim: ClassVar[int] = 3
    n_noise: ClassVar[int] = 2

    model: Pendulum = field(default_factory=_gym_pendulum)
    max_torque: float = 2.0
    max_episode_steps: int = 200

    @property
    def system(self) -> Pendulum:
        return self.model

    def u_max(self) -> tuple[float, ...]:
        return (self.max_torque,)

    def obs_high(self) -> np.ndarray:
        # |ω̇| ≤ g/l + u_max/(m l²) and |ω_0| ≤ 1, so |ω| ≤ 1 + steps·dt·max|ω̇| within an episode
        md = self.model
        acc = hi(md.gravity) / lo(md.length) + self.max_torque / (lo(md.mass) * lo(md.length) ** 2)
        return np.array([1.0, 1.0, 1.0 + self.max_episode_steps * hi(md.dt) * acc])

    def initial_state(self, noise: Tensor) -> Tensor:
        phi = (2 * noise[..., 0] - 1) * math.pi
        return torch.stack([phi + math.pi, 2 * noise[..., 1] - 1], -1)

    def observe(self, x: Tensor) -> Tensor:
        th = x[..., 0]
        # φ = θ − π: cos φ = −cos θ, sin φ = −sin θ
        return torch.stack([-torch.cos(th), -torch.sin(th), x[..., 1]], -1)

    def reward(self, x: Tensor, u: Tensor, x_next: Tensor) -> Tensor:
        phi = torch.remainder(x[..., 0], 2 * math.pi) - math.pi  # = angle_wrap(θ − π)
        om, tau = x[..., 1], u[..., 0]
        return torch.addcmul(phi * phi, om, om, value=0.1).addcmul_(tau, tau, value=0.001).neg_()

    def error(self, x: Tensor) -> Tensor:
        return angle_wrap(x[..., 0] - math.pi).abs()

    def success(self, x: Tensor) -> Tensor:
        return (self.error(x) < 0.1) & (x[..., 1].abs() < 0.5)

    def state_from_obs(self, obs: Tensor) -> Tensor:
        return torch.stack([torch.atan2(-obs[..., 1], -obs[..., 0]), obs[..., 2]], -1)

    def mpc_cost(self, horizon: int, *, dtype=torch.float64, device=None):
        from controllers.costs import QuadraticCost

        kw = dict(dtype=dtype, device=device)
        return QuadraticCost(Q=terminal_weighted(torch.tensor([1.0, 0.1], **kw), horizon),
                             R=torch.tensor([[0.001]], **kw), x_ref=torch.tensor([math.pi, 0.0], **kw))

    def frame(self, x: np.ndarray, size: int = 256) -> np.ndarray:
        cv = Canvas(size, extent=1.2 * float(self.model.length) + 0.2)
        L = float(self.model.length)
        tip = (L * math.sin(x[0]), -L * math.cos(x[0]))
        cv.segment((0.0, 0.0), tip, 0.08, (204, 77, 77))
        cv.disc(tip, 0.08, (150, 40, 40))
        cv.disc((0.0, 0.0), 0.04, (0, 0, 0))
        return cv.img
