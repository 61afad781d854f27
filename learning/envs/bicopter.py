"""Bicopter hover-to-target on :class:`controllers.systems.Bicopter` (seed 004 §9.16).

The state is relative to the target: the bicopter starts at a random offset from it — position uniform in
``±start_range``, roll and velocities small — and must fly there and hover (``x = 0``).  A random target
and a fixed start are the same problem in these coordinates, so the target needs no extra state.

Controls: the two rotor thrusts, each in ``[0, m g]`` (thrust-to-weight ratio 2).  :class:`Task` maps the
normalized action ``[-1, 1]`` to a symmetric box ``±u_max``, so the model is used with
``hover_relative=True``: its controls are the thrusts' deviations from the hover thrust ``m g/2`` of each
rotor, ``u_max = m g/2``, and the action ``-1`` / ``0`` / ``+1`` is thrust ``0`` / hover / ``m g``.
(A thrust range ``[0, T_max]`` with ``T_max ≠ m g`` is not symmetric about hover and would need an offset
in the action map; this task fixes the ratio at 2 instead.)

The episode terminates on a crash: leaving the box ``|x₁|, |x₂| ≤ position_limit`` around the target (the
floor included), tilting beyond ``tilt_limit``, or exceeding the speed limits — as the cart-pole terminates
off its track; these limits make the observation bounds finite.  Reward in ``[0, 1]`` per step (a product
of smooth factors, so ending the episode early is never attractive)::

    r = 1/(1 + ‖p‖²) · (1 + cos θ)/2 · (1 + exp(-‖ṗ‖²))/2 · (1 - ‖a‖²/10),

``p = (x₁, x₂)``, ``a = u/u_max`` the normalized action.  The seed gives the equations and ``g = 9.81``;
mass, inertia, arm, step and limits are this task's choices.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
import torch
from torch import Tensor

from controllers.systems import Bicopter
from learning.envs._canvas import Canvas
from learning.envs.task import Task, terminal_weighted

__all__ = ["BicopterHover"]


def _hi(v) -> float:
    """Largest value of a float or tensor model parameter, exactly (``task.hi`` rounds through float32)."""
    return float(v.detach().max()) if isinstance(v, Tensor) else float(v)


def _lo(v) -> float:
    """Smallest value of a float or tensor model parameter, exactly."""
    return float(v.detach().min()) if isinstance(v, Tensor) else float(v)


def _hover_bicopter() -> Bicopter:
    return Bicopter(mass=2.5, inertia=1.2, arm=0.5, gravity=9.81, dt=0.05, hover_relative=True)


@dataclass(frozen=True, eq=False)
class BicopterHover(Task):
    """Reach the target (the origin of the relative state) and hover (observation: the state
    ``[x₁, x₂, θ, ẋ₁, ẋ₂, θ̇]``, bounded by the crash limits).

    Success: ``‖p‖ < 0.1`` m, ``|θ| < 0.1`` rad and ``‖ṗ‖ < 0.2`` m/s at the end of the episode; error ``‖p‖``
    (m).  Initial state: ``x₁, x₂`` uniform in ``±start_range``, ``θ`` in ``±0.2`` rad, ``ẋ₁, ẋ₂`` in
    ``±0.5`` m/s, ``θ̇`` in ``±0.5`` rad/s.
    """

    name: ClassVar[str] = "BicopterHover"
    obs_dim: ClassVar[int] = 6
    n_noise: ClassVar[int] = 6

    model: Bicopter = field(default_factory=_hover_bicopter)
    start_range: float = 1.5
    position_limit: float = 3.0
    tilt_limit: float = 1.2
    speed_limit: float = 6.0
    rate_limit: float = 10.0
    max_episode_steps: int = 200

    def __post_init__(self):
        if not self.model.hover_relative:
            raise ValueError("BicopterHover: the model must have hover_relative=True (controls are thrust "
                             "deviations from hover, see the module docstring)")
        # m g/2 of the lightest model: every rotor's thrust u + m g/2 stays in [0, m g] (≥ 0 for all models)
        object.__setattr__(self, "_u_max", 0.5 * _lo(self.model.mass) * _lo(self.model.gravity))

    @property
    def system(self) -> Bicopter:
        return self.model

    def u_max(self) -> tuple[float, ...]:
        return (self._u_max, self._u_max)

    def obs_high(self) -> np.ndarray:
        # Every step starts inside the limits (|x₁|, |x₂| ≤ X, |θ| ≤ Θ, |ẋ₁|, |ẋ₂| ≤ V, |θ̇| ≤ W, else the
        # episode has ended; the initial states are inside).  The total thrust is at most 2 u_max + m g, so
        # |ẍ₁|, |ẍ₂| ≤ 2 u_max/m + 2 g and |θ̈| ≤ 2 u_max ℓ/I, and one semi-implicit Euler step
        # (v⁺ = v + dt a, q⁺ = q + dt v⁺) ends within these bounds.
        md, dt = self.model, _hi(self.model.dt)
        um = self.u_max()[0]
        acc = 2 * um / _lo(md.mass) + 2 * _hi(md.gravity)
        alpha = 2 * um * _hi(md.arm) / _lo(md.inertia)
        v = self.speed_limit + dt * acc
        w = self.rate_limit + dt * alpha
        p = self.position_limit + dt * v
        # (A relative 1e-6 on top covers the rounding of a float32 simulation.)
        return np.array([p, p, self.tilt_limit + dt * w, v, v, w]) * (1.0 + 1e-6)

    def initial_state(self, noise: Tensor) -> Tensor:
        half = torch.tensor([self.start_range, self.start_range, 0.2, 0.5, 0.5, 0.5], dtype=noise.dtype,
                            device=noise.device)
        return (2 * noise - 1) * half

    def observe(self, x: Tensor) -> Tensor:
        return x.clone()

    def reward(self, x: Tensor, u: Tensor, x_next: Tensor) -> Tensor:
        p1, p2, th, v1, v2 = x_next[..., 0], x_next[..., 1], x_next[..., 2], x_next[..., 3], x_next[..., 4]
        um = self._u_max
        a1, a2 = u[..., 0] / um, u[..., 1] / um
        near = 1.0 / (1.0 + p1 * p1 + p2 * p2)
        upright = 0.5 + 0.5 * torch.cos(th)
        slow = 0.5 + 0.5 * torch.exp(-(v1 * v1 + v2 * v2))
        small_u = 1.0 - 0.1 * (a1 * a1 + a2 * a2)
        return near * upright * slow * small_u

    def terminated(self, x: Tensor) -> Tensor:
        """A crash: out of the box around the target, tilted beyond the limit, or too fast."""
        X, V = self.position_limit, self.speed_limit
        return ((x[..., 0].abs() > X) | (x[..., 1].abs() > X) | (x[..., 2].abs() > self.tilt_limit)
                | (x[..., 3].abs() > V) | (x[..., 4].abs() > V) | (x[..., 5].abs() > self.rate_limit))

    def error(self, x: Tensor) -> Tensor:
        return torch.hypot(x[..., 0], x[..., 1])

    def success(self, x: Tensor) -> Tensor:
        return (self.error(x) < 0.1) & (x[..., 2].abs() < 0.1) & (torch.hypot(x[..., 3], x[..., 4]) < 0.2)

    def state_from_obs(self, obs: Tensor) -> Tensor:
        return obs.clone()

    def mpc_cost(self, horizon: int, *, dtype=torch.float64, device=None):
        """Quadratic cost to hover at the target (controls: thrust deviations from hover, in N)."""
        from controllers.costs import QuadraticCost

        kw = dict(dtype=dtype, device=device)
        Q = terminal_weighted(torch.tensor([1.0, 1.0, 0.1, 0.1, 0.1, 0.01], **kw), horizon, 10.0)
        return QuadraticCost(Q=Q, R=torch.diag(torch.tensor([1e-3, 1e-3], **kw)), x_ref=torch.zeros(6, **kw))

    def frame(self, x: np.ndarray, size: int = 256) -> np.ndarray:
        X = self.position_limit
        cv = Canvas(size, extent=X + 0.3)
        for a, b in (((-X, -X), (X, -X)), ((X, -X), (X, X)), ((X, X), (-X, X)), ((-X, X), (-X, -X))):
            cv.segment(a, b, 0.05, (0, 0, 0))
        cv.segment((-0.2, 0.0), (0.2, 0.0), 0.04, (80, 160, 80))  # the target
        cv.segment((0.0, -0.2), (0.0, 0.2), 0.04, (80, 160, 80))
        arm = float(torch.as_tensor(self.model.arm).mean())
        p1, p2, th = float(x[0]), float(x[1]), float(x[2])
        c, s = math.cos(th), math.sin(th)
        r1, r2 = (p1 + arm * c, p2 + arm * s), (p1 - arm * c, p2 - arm * s)
        cv.segment(r2, r1, 0.08, (60, 90, 160))
        for r in (r1, r2):  # rotors, slightly above the arm
            cv.segment((r[0] - 0.15 * c - 0.06 * s, r[1] - 0.15 * s + 0.06 * c),
                       (r[0] + 0.15 * c - 0.06 * s, r[1] + 0.15 * s + 0.06 * c), 0.05, (204, 77, 77))
        cv.disc((p1, p2), 0.08, (40, 40, 40))
        return cv.img
