"""Time-optimal rest-to-rest screw paths for the seed-000 experiment (§4, Fig. 1-2).

The path is ``X*(α) = X_0 exp(α δ)`` with ``α ∈ [0, 1]`` (a constant body twist ``δ``), timed by a
time-optimal trapezoidal velocity profile on ``α`` under Cartesian speed and acceleration limits.
Along this path the body-frame origin moves at ``‖ρ_δ‖ α̇`` and the frame turns at ``‖φ_δ‖ α̇``
(``δ = [ρ_δ, φ_δ]``), so the Cartesian limits become limits on ``α̇`` and ``α̈`` directly.
The paper used Ruckig (jerk-limited); this is the jerk-unlimited trapezoid it converges to.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from torchlie import se3, so3

__all__ = [
    "CartesianLimits",
    "PANDA_LIMITS",
    "TrapezoidProfile",
    "trapezoid_profile",
    "alpha_limits",
    "design_delta",
    "screw_path",
    "ground_truth_twists",
]


@dataclass(frozen=True)
class CartesianLimits:
    """Cartesian limits of an end effector: translation [m/s, m/s²] and rotation [rad/s, rad/s²]."""

    v_lin: float
    a_lin: float
    v_rot: float
    a_rot: float

    def scaled(self, velocity: float = 1.0, acceleration: float = 1.0) -> CartesianLimits:
        """Limits with the speeds scaled by ``velocity`` and the accelerations by ``acceleration``."""
        return CartesianLimits(self.v_lin * velocity, self.a_lin * acceleration,
                               self.v_rot * velocity, self.a_rot * acceleration)


# Franka Emika Panda end-effector limits as published in the Franka Control Interface documentation
# (translation 1.7 m/s, 13 m/s²; rotation 2.5 rad/s, 25 rad/s²; jerk limits are not used here).
PANDA_LIMITS = CartesianLimits(v_lin=1.7, a_lin=13.0, v_rot=2.5, a_rot=25.0)


@dataclass(frozen=True)
class TrapezoidProfile:
    """Samples of a rest-to-rest trapezoidal profile of ``α`` from 0 to 1.

    ``t``, ``alpha``, ``alpha_dot``: ``(K + 1,)`` at ``t_k = k Δt``; ``duration`` is the exact
    (unsampled) end time; ``v_peak``/``a_max`` the reached peak speed and the acceleration used;
    ``triangular`` is True when the speed limit is never reached.
    """

    t: torch.Tensor
    alpha: torch.Tensor
    alpha_dot: torch.Tensor
    duration: float
    v_peak: float
    a_max: float
    triangular: bool


def trapezoid_profile(v_max: float, a_max: float, dt: float, *, dtype: torch.dtype = torch.float64,
                      device=None) -> TrapezoidProfile:
    """Time-optimal rest-to-rest profile of ``α: 0 → 1`` with ``|α̇| ≤ v_max`` and ``|α̈| ≤ a_max``.

    Accelerate at ``a_max``, cruise at ``v_max`` (if reached), decelerate at ``a_max``; the
    samples cover ``t = 0, Δt, …, KΔt`` with ``KΔt ≥ duration`` (the last sample is exactly α = 1).
    """
    for name, v in (("v_max", v_max), ("a_max", a_max), ("dt", dt)):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not (v > 0 and math.isfinite(v)):
            raise ValueError(f"trapezoid_profile: argument '{name}' must be a positive finite float, "
                             f"got {v!r}")
    if v_max * v_max / a_max >= 1.0:  # the speed limit is not reached: triangle
        ta = math.sqrt(1.0 / a_max)
        vp, tc, tri = a_max * ta, 0.0, True
    else:
        ta = v_max / a_max
        vp, tc, tri = v_max, (1.0 - v_max * ta) / v_max, False
    T = 2 * ta + tc
    K = math.ceil(T / dt - 1e-9)
    t = torch.arange(K + 1, dtype=dtype, device=device) * dt
    tt = t.clamp(max=T)
    a1 = 0.5 * a_max * tt**2  # acceleration phase
    a2 = 0.5 * vp * ta + vp * (tt - ta)  # cruise
    td = (T - tt).clamp(min=0.0)
    a3 = 1.0 - 0.5 * a_max * td**2  # deceleration (time to go td)
    alpha = torch.where(tt < ta, a1, torch.where(tt < ta + tc, a2, a3))
    v1, v3 = a_max * tt, a_max * td
    alpha_dot = torch.where(tt < ta, v1, torch.where(tt < ta + tc, torch.full_like(tt, vp), v3))
    alpha[-1] = 1.0
    alpha_dot[-1] = 0.0
    return TrapezoidProfile(t, alpha, alpha_dot, T, vp, a_max, tri)


def alpha_limits(delta: torch.Tensor, limits: CartesianLimits) -> tuple[float, float]:
    """Largest ``(α̇, α̈)`` that keep the screw motion ``exp(α δ)`` within the Cartesian ``limits``."""
    rho = float(torch.linalg.vector_norm(delta[..., :3]))
    phi = float(torch.linalg.vector_norm(delta[..., 3:]))
    v = min(limits.v_lin / rho if rho > 0 else math.inf, limits.v_rot / phi if phi > 0 else math.inf)
    a = min(limits.a_lin / rho if rho > 0 else math.inf, limits.a_rot / phi if phi > 0 else math.inf)
    if not (math.isfinite(v) and math.isfinite(a)):
        raise ValueError("alpha_limits: argument 'delta' is zero; there is no motion to time")
    return v, a


def design_delta(R0: torch.Tensor, displacement: torch.Tensor, rotvec_body: torch.Tensor) -> torch.Tensor:
    """The body twist ``δ = [ρ, φ]`` with ``X_0 exp(δ)`` displaced by ``displacement`` (world, [m])
    and rotated by ``φ = rotvec_body`` (body frame), i.e. ``p_f - p_0 = R_0 J_l(φ) ρ``."""
    rho = so3.left_jacobian_inv(rotvec_body) @ (R0.transpose(-1, -2) @ displacement)
    return torch.cat([rho, rotvec_body], dim=-1)


def screw_path(X0: torch.Tensor, delta: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """``X*(α_k) = X_0 exp(α_k δ)``: X0 ``(4, 4)``, delta ``(6,)``, alpha ``(K+1,)`` -> ``(K+1, 4, 4)``."""
    return X0 @ se3.exp(alpha[:, None] * delta)


def ground_truth_twists(X: torch.Tensor, dt: float) -> torch.Tensor:
    """``T*_k = log(X*_k⁻¹ X*_{k+1}) / Δt`` (seed 000 §4): ``(K+1, 4, 4)`` -> ``(K, 6)``."""
    return se3.log(se3.compose(se3.inverse(X[:-1]), X[1:])) / dt
