"""A model of gymnasium's ``MountainCarContinuous-v0`` for a model-based MPC: :func:`mountain_car_model`.

**Dynamics** (:class:`MountainCar`, the env's ``step`` exactly, state ``x = [p, v]`` = the observation)::

    f  = clip(a, -1, 1)
    v' = clip(v + 0.0015 f - 0.0025 cos 3p, -0.07, 0.07)
    p' = clip(p + v', -1.2, 0.6);   v' = 0  where p' = -1.2 and v' < 0      (the inelastic left wall)

In float32 the arithmetic is the env's, operation for operation (it keeps its state in float32 and evaluates
``math.cos`` in double), so a float32 rollout equals the env's to the last bit; in float64 it equals it to
float32 rounding.  The env terminates with reward 100 at ``p ≥ 0.45, v ≥ 0`` and pays ``-0.1 a²`` a step.

**Planning cost** (:class:`EnergyGoalCost`): the reward's ``0.1 Σ u_t²`` plus a terminal energy deficit,
smoothed by a softplus of width ``s``::

    E(p, v) = v²/2 + (0.0025/3) sin 3p                 (the mechanical energy of the valley, per unit mass)
    J = 0.1 Σ_t u_t² + w s softplus((E* - E(x_T)) / s) + w_k s_k softplus((E_k - E(x_T)) / s_k),
    E* = E(0.45, 0) + margin,   E_k = E_min + kick_energy   (E_min = -0.0025/3, the valley floor at rest).

Why energy, and why linear in the deficit: the +100 is a sparse event far beyond any affordable horizon
(a car starting near the valley floor needs several swings), while the energy is what the control changes
— ``ΔE ≈ 0.0015 u v`` a step, gravity conserves it.  With a cost linear in ``E_T`` the optimal control is
``u_t = (w/0.2) ∂E_T/∂u_t ≈ 0.0075 w v_t``: push along the velocity, in proportion to it — by
Cauchy-Schwarz the least ``Σu²`` that injects a given ``Σ u v``, so the car pumps energy at the lowest
price per joule, and ``w`` only sets how fast (hence how much it pays: ``Σu² ≈ k ΔE / 0.0015`` with
``k = 0.0075 w``, against the 999-step limit).  Once ``E_T ≥ E*`` the softplus vanishes and the car coasts
to the goal; the energy lost to the left wall (where ``v`` is zeroed) is seen by the model, so the plan
stops pumping before a swing that would hit it.  A quadratic deficit instead makes the push fade as the
target nears (the car then creeps towards ``E*``), and the goal distance alone has no gradient from the
valley.  ``margin`` covers the gap between this continuous-time energy and the discrete map's.

The second, "kick" term prices the first ``kick_energy`` above the valley floor ~8x higher (``w_k =
10000``): pumping at ``u ∝ v`` grows the energy only exponentially, so a car started within ~0.004 of the
floor would need more than the 999 steps (measured: from ``p = -π/6``, ``v = 0`` in float32, return ≈ 0 in 999
steps without the kick, 98.66 in 442 steps with it).  The exact equilibrium in exact arithmetic stays a
stationary point of both terms (zero gradient): the kick acts on the smallest offset.  The kick costs at
most ``Σu² ≈ 0.0075 w_k E_k / 0.0015 = 1`` and is inactive for every start with more energy than ``E_k``.

The Hessian given to iLQR (:meth:`EnergyGoalCost.derivatives`) is the Gauss-Newton part
``w σ'(·)/s ∇E ∇Eᵀ`` (positive semidefinite); the gradient is exact, so the KKT certificate is unaffected.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

__all__ = ["MountainCar", "EnergyGoalCost", "mountain_car_energy", "mountain_car_state",
           "mountain_car_cost", "mountain_car_model", "GOAL_POSITION", "POWER", "GRAVITY"]

POWER = 0.0015  #: force per unit action
GRAVITY = 0.0025  #: the slope term ``-0.0025 cos 3p``
MAX_SPEED = 0.07
MIN_POSITION, MAX_POSITION = -1.2, 0.6
GOAL_POSITION = 0.45


def _check_xu(x: Tensor, u: Tensor, who: str) -> None:
    if not isinstance(x, Tensor) or not isinstance(u, Tensor):
        raise TypeError(f"{who}: arguments 'x' and 'u' must be tensors")
    if x.shape[-1:] != (2,) or u.shape[-1:] != (1,):
        raise ValueError(f"{who}: expected x (*B, 2) and u (*B, 1), got {tuple(x.shape)} and "
                         f"{tuple(u.shape)}")
    if not x.is_floating_point() or x.dtype != u.dtype:
        raise TypeError(f"{who}: 'x' and 'u' must share one floating dtype, got {x.dtype} and {u.dtype}")


def _slope(p: Tensor) -> Tensor:
    """``0.0025 cos 3p``; in float32 evaluated in double and rounded, as the env's ``math.cos`` does."""
    if p.dtype == torch.float32:
        return (GRAVITY * torch.cos((3 * p).double())).to(p.dtype)
    return GRAVITY * torch.cos(3 * p)


@dataclass(frozen=True, eq=False)
class MountainCar:
    """The dynamics of ``MountainCarContinuous-v0`` (module docstring); ``x = [p, v]``, ``u = [a]``.

    Time-invariant and batched (``x (*B, 2)``, ``u (*B, 1)``, broadcasting); differentiable almost
    everywhere (the clips and the wall have zero derivative where active), with an analytic
    :meth:`jacobian`.
    """

    n: int = 2
    m: int = 1
    time_invariant: bool = True

    def _parts(self, x: Tensor, u: Tensor):
        p, v = x[..., 0], x[..., 1]
        f = u[..., 0].clamp(-1.0, 1.0)
        v1 = v + (f * POWER - _slope(p))
        vc = v1.clamp(-MAX_SPEED, MAX_SPEED)
        p1 = p + vc
        pc = p1.clamp(MIN_POSITION, MAX_POSITION)
        wall = (p1 <= MIN_POSITION) & (vc < 0)
        return p, f, v1, vc, p1, pc, wall

    def step(self, x: Tensor, u: Tensor, t: int = 0) -> Tensor:
        """``x' (*B, 2)`` from ``x (*B, 2)``, ``u (*B, 1)`` (``t`` ignored)."""
        _check_xu(x, u, "MountainCar.step")
        _, _, _, vc, _, pc, wall = self._parts(x, u)
        return torch.stack([pc, torch.where(wall, torch.zeros_like(vc), vc)], -1)

    def jacobian(self, x: Tensor, u: Tensor, t: int = 0) -> tuple[Tensor, Tensor]:
        """``A = ∂x'/∂x (*B, 2, 2)``, ``B = ∂x'/∂u (*B, 2, 1)`` (zero rows where a clip or the wall is
        active, zero columns in ``u`` outside ``[-1, 1]``)."""
        _check_xu(x, u, "MountainCar.jacobian")
        p, f, v1, vc, p1, pc, wall = self._parts(x, u)
        one, zero = torch.ones_like(vc), torch.zeros_like(vc)
        free_v = ((v1 > -MAX_SPEED) & (v1 < MAX_SPEED)).to(vc.dtype)  # velocity not clipped
        free_u = ((u[..., 0] > -1.0) & (u[..., 0] < 1.0)).to(vc.dtype)
        free_p = ((p1 > MIN_POSITION) & (p1 < MAX_POSITION)).to(vc.dtype)
        g = 3 * GRAVITY * torch.sin(3 * p)  # ∂v1/∂p
        dv = torch.stack([g * free_v, one * free_v, POWER * free_u * free_v], -1)  # ∂vc/∂(p, v, a)
        dp = (torch.stack([one, zero, zero], -1) + dv) * free_p[..., None]  # ∂pc/∂(p, v, a)
        dv = torch.where(wall[..., None], torch.zeros_like(dv), dv)
        J = torch.stack([dp, dv], -2)  # (*B, 2, 3)
        return J[..., :2], J[..., 2:]


def mountain_car_energy(x: Tensor) -> Tensor:
    """``E = v²/2 + (0.0025/3) sin 3p`` of ``x (*B, 2)`` -> ``(*B,)``."""
    return 0.5 * x[..., 1] ** 2 + (GRAVITY / 3) * torch.sin(3 * x[..., 0])


def _goal_energy(margin: float) -> float:
    return (GRAVITY / 3) * math.sin(3 * GOAL_POSITION) + margin


@dataclass(frozen=True, eq=False)
class EnergyGoalCost:
    """``J = r Σ_t u_t² + w s softplus((E* - E(x_T)) / s) + w_k s_k softplus((E_k - E(x_T)) / s_k)`` (module
    docstring); ``r = 0.1`` is the reward's; ``kick_weight = 0`` drops the kick term.

    ``evaluate(x (*B, T+1, 2), u (*B, T, 1)) -> (*B,)``; :meth:`derivatives` gives the exact gradient and
    the Gauss-Newton Hessian.
    """

    weight: float = 1300.0
    margin: float = 2e-5
    width: float = 2e-5
    r: float = 0.1
    kick_weight: float = 10000.0
    kick_energy: float = 2e-5
    kick_width: float = 2e-6

    def __post_init__(self) -> None:
        if not isinstance(self.kick_weight, (int, float)) or not self.kick_weight >= 0:
            raise ValueError(f"EnergyGoalCost: field 'kick_weight' must be >= 0, got {self.kick_weight!r}")
        for name in ("weight", "width", "r", "kick_energy", "kick_width"):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not v > 0:
                raise ValueError(f"EnergyGoalCost: field '{name}' must be a positive number, got {v!r}")

    @property
    def target(self) -> float:
        """``E*``: the energy of the car at rest at the goal, plus the margin."""
        return _goal_energy(self.margin)

    def _deficit(self, x: Tensor) -> Tensor:
        return (self.target - mountain_car_energy(x[..., -1, :])) / self.width

    def _kick(self, x: Tensor) -> Tensor:
        return (self.kick_energy - GRAVITY / 3 - mountain_car_energy(x[..., -1, :])) / self.kick_width

    def evaluate(self, x: Tensor, u: Tensor) -> Tensor:
        if x.shape[-1] != 2 or u.shape[-1] != 1 or x.shape[-2] != u.shape[-2] + 1:
            raise ValueError(f"EnergyGoalCost.evaluate: expected x (*B, T+1, 2), u (*B, T, 1), got "
                             f"{tuple(x.shape)} and {tuple(u.shape)}")
        sp = torch.nn.functional.softplus
        term = self.weight * self.width * sp(self._deficit(x))
        if self.kick_weight > 0:
            term = term + self.kick_weight * self.kick_width * sp(self._kick(x))
        return self.r * (u * u).sum((-1, -2)) + term

    def derivatives(self, x: Tensor, u: Tensor):
        """``(gx (*B,T+1,2), gu (*B,T,1), Hxx (*B,T+1,2,2), None, Huu (*B,T,1,1))``; Hxx Gauss-Newton."""
        sig = torch.sigmoid(self._deficit(x))
        slope = self.weight * sig  # -∂J/∂E_T
        curv = self.weight / self.width * sig * (1 - sig)
        if self.kick_weight > 0:
            sk = torch.sigmoid(self._kick(x))
            slope = slope + self.kick_weight * sk
            curv = curv + self.kick_weight / self.kick_width * sk * (1 - sk)
        p, v = x[..., -1, 0], x[..., -1, 1]
        gE = torch.stack([GRAVITY * torch.cos(3 * p), v], -1)  # ∇E at x_T
        gx = torch.zeros_like(x)
        gx[..., -1, :] = -slope[..., None] * gE
        Hxx = torch.zeros(*x.shape, 2, dtype=x.dtype, device=x.device)
        Hxx[..., -1, :, :] = curv[..., None, None] * gE[..., :, None] * gE[..., None, :]
        gu = 2 * self.r * u
        Huu = torch.full((*u.shape, 1), 2 * self.r, dtype=u.dtype, device=u.device)
        return gx, gu, Hxx, None, Huu


def mountain_car_state(obs: Tensor) -> Tensor:
    """The observation ``[p, v]`` is the state: ``(N, 2) -> (N, 2)`` (dtype and device kept)."""
    if obs.shape[-1] != 2:
        raise ValueError(f"mountain_car_state: expected observations (N, 2), got {tuple(obs.shape)}")
    return obs


def mountain_car_cost(horizon: int, dtype=torch.float64, device=None, *, weight: float = 1300.0,
                      margin: float = 2e-5, width: float = 2e-5) -> EnergyGoalCost:
    """The planning cost (:class:`EnergyGoalCost`; the same object for every horizon, dtype and device)."""
    return EnergyGoalCost(weight=weight, margin=margin, width=width)


def mountain_car_model(env: Any = None, *, horizon: int = 30, max_iter: int = 5, weight: float = 1300.0,
                       margin: float = 2e-5, width: float = 2e-5):
    """The :class:`~learning.env_models.EnvModel` of ``MountainCarContinuous-v0`` (module docstring)."""
    from learning.env_models import EnvModel

    def cost(h: int, dtype=torch.float64, device=None):
        return mountain_car_cost(h, dtype, device, weight=weight, margin=margin, width=width)

    return EnvModel(
        env_id="MountainCarContinuous-v0", system=MountainCar(), cost=cost, state_from_obs=mountain_car_state,
        action_low=(-1.0,), action_high=(1.0,), obs_dim=2, horizon=horizon, max_iter=max_iter,
        random_starts=0,
        knows="the car's exact dynamics (slope, power, clips, the inelastic left wall); the cost is the "
              "reward's 0.1 u² plus a terminal energy deficit in place of the sparse +100 at the goal")
