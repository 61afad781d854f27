"""Quadrotor trajectory tracking on R³ × R³ × SO(3) (seed 003 §VII-A), on
:class:`controllers.systems.Quadrotor`.

The vehicle must follow a horizontal circle or figure-eight (Gerono's lemniscate) flown at constant
phase rate, in the paper's NED frame (``z`` down; altitude ``h`` is ``z = −h``).  The dynamics are the
canonical discrete model of the error-state MPC (:class:`~controllers.systems.Quadrotor`, Eq. 33: explicit
Euler on ``p``, ``v``, the exact exponential on ``R``) — one definition for the MPC and the environment.

**The clock lives in the state.**  The reference is periodic with a period of exactly ``period_steps``
control steps, so its phase is an integer ``k ∈ {0, …, P−1}`` appended to the state and advanced by
:class:`QuadrotorClock` (``k⁺ = (k + 1) mod P``; exact in float32 too).  The whole reference (position,
velocity, attitude and the controls of differential flatness,
:func:`~controllers.systems.quadrotor_flatness.flat_reference`) is tabulated once per period and read by
index, by the task (observation, reward) and by its expert alike.  State
``x = [p (3), v (3), vec R (9, row-major), k]``, ``n = 16``.

* Controls (physical): ``[Δa_T, ω_x, ω_y, ω_z]``, the mass-normalized thrust's deviation from hover
  (``a_T = g + Δa_T``, so ``a_T ∈ [0, 2g]``) and the body rates (``±rate_max``); the normalized action
  ``±1`` maps to ``±(g, rate_max, rate_max, rate_max)``.
* Observation ``[p − p_ref(k), v − v_ref(k), vec R, cos 2πk/P, sin 2πk/P]`` (17): the tracking errors, the
  attitude and the phase (which fixes the whole future reference).
* Reward per step in ``[0, 1]``: ``1/(1 + (‖e_p‖/0.2)²) · (1 − 0.05 ‖a‖²/4)`` on the state after the step
  (``a`` the normalized action), so ending an episode early is never attractive.
* Termination (a crash): a position error beyond ``position_limit`` or a velocity error beyond
  ``velocity_limit`` in any axis, or the vehicle upside down (``R₃₃ < 0``); these make the observation
  bounds finite.
* Success at the end of the episode: ``‖e_p‖ < 0.1`` m and ``‖e_v‖ < 0.3`` m/s; error ``‖e_p‖`` (m).
* Model mismatch (for studies of robustness): ``mass_scale`` ``s`` and ``drag`` ``(d_x, d_y, d_z)`` make the
  vehicle's model :class:`~controllers.systems.Quadrotor` ``(mass_scale=s, drag=D)``: the thrust produces
  ``a_T / s`` and rotor drag ``−R D Rᵀ v`` acts (defaults: 1 and zeros, the nominal vehicle).  The reference
  path is the same; its tabulated controls are the flatness controls of the drag-free model with the thrust
  times ``s`` (exact without drag).
* Initial state: a uniform integer phase, the reference's position and velocity plus uniform offsets
  (``±start_position`` m, ``±start_velocity`` m/s per axis) and a level attitude tilted by a rotation
  vector uniform in ``±start_tilt`` rad per axis.

:class:`QuadrotorTrackingExpert` solves the task with the error-state MPC of seed 003
(:class:`~controllers.manifold_mpc.ErrorStateMPC`) on the same model, tracking the tabulated reference under
the thrust and rate limits, with the DARE terminal weight at hover (an MPC on the manifold, not on a
flattened state).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
import torch
from torch import Tensor

from controllers.systems.quadrotor import Quadrotor
from learning.envs._canvas import Canvas
from learning.envs.task import ErrorStateExpert, Task

__all__ = ["QuadrotorClock", "QuadrotorTrack", "QuadrotorFigureEight", "QuadrotorTrackingExpert"]

_SHAPES = ("circle", "figure8")


def _flat(p: Tensor, v: Tensor, R: Tensor, k: Tensor) -> Tensor:
    return torch.cat([p, v, R.reshape(*R.shape[:-2], 9), k[..., None]], -1)


@dataclass(frozen=True, eq=False)
class QuadrotorClock:
    """The quadrotor with a phase clock, on flat tensors: state ``[p, v, vec R, k]`` ``(*B, 16)``, control
    ``[Δa_T, ω]`` ``(*B, 4)`` with ``a_T = g + Δa_T``.  ``step`` is :meth:`Quadrotor.step` (one dynamics
    definition) and ``k⁺ = (k + 1) mod period``."""

    quad: Quadrotor
    period: int

    n: ClassVar[int] = 16
    m: ClassVar[int] = 4
    time_invariant: ClassVar[bool] = True

    @property
    def dt(self):
        return self.quad.dt

    def point(self, x: Tensor):
        """The :class:`~torchlie.manifolds.ProductState` ``(p, v, R)`` of flat states (unchecked)."""
        from torchlie.manifolds import ProductState

        return ProductState({"p": x[..., 0:3], "v": x[..., 3:6], "R": x[..., 6:15].unflatten(-1, (3, 3))},
                            {"p": 1, "v": 1, "R": 2})

    def physical(self, u: Tensor) -> Tensor:
        """``[a_T, ω]`` from ``[Δa_T, ω]``."""
        g = torch.as_tensor(self.quad.gravity, dtype=u.dtype, device=u.device)
        return torch.cat([u[..., :1] + g, u[..., 1:]], -1)

    def step(self, x: Tensor, u: Tensor, t: int = 0) -> Tensor:
        y = self.quad.step(self.point(x), self.physical(u))
        k = torch.remainder(x[..., 15] + 1, self.period)
        return _flat(y["p"], y["v"], y["R"], k)


@dataclass(frozen=True, eq=False)
class QuadrotorTrack(Task):
    """Track a circle or a figure-eight (module docstring); registered as ``QuadrotorCircle`` (and, with
    ``shape="figure8"``, as :class:`QuadrotorFigureEight`).

    Attributes:
        shape: ``"circle"`` or ``"figure8"``.
        radius: circle radius / half the figure-eight's length (m); altitude ``h`` (m).
        period_steps: control steps per lap (the lap time is ``period_steps · dt``).
        dt: control period (s).
        rate_max: body-rate limit (rad/s).
        mass_scale: true mass / nominal mass of the vehicle (the thrust produces ``a_T / mass_scale``).
        drag: rotor-drag coefficients per unit mass ``(d_x, d_y, d_z)`` (1/s, body axes).
    """

    name: ClassVar[str] = "QuadrotorCircle"
    obs_dim: ClassVar[int] = 17
    n_noise: ClassVar[int] = 10

    shape: str = "circle"
    radius: float = 1.5
    altitude: float = 1.5
    period_steps: int = 250
    dt: float = 0.02
    rate_max: float = 6.0
    start_position: float = 0.3
    start_velocity: float = 0.3
    start_tilt: float = 0.2
    position_limit: float = 2.0
    velocity_limit: float = 4.0
    gravity: float = 9.81
    max_episode_steps: int = 250
    mass_scale: float = 1.0
    drag: tuple = (0.0, 0.0, 0.0)
    _cache: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self):
        if self.shape not in _SHAPES:
            raise ValueError(f"QuadrotorTrack: argument 'shape' must be one of {_SHAPES}, "
                             f"got {self.shape!r}")
        if not (isinstance(self.period_steps, int) and self.period_steps >= 8):
            raise ValueError(f"QuadrotorTrack: argument 'period_steps' must be an int ≥ 8, "
                             f"got {self.period_steps!r}")
        for name in ("radius", "altitude", "dt", "rate_max", "position_limit", "velocity_limit", "gravity"):
            if not float(getattr(self, name)) > 0:
                raise ValueError(f"QuadrotorTrack: argument '{name}' must be positive, "
                                 f"got {getattr(self, name)!r}")
        self._check_mismatch()
        if not (self.start_position < self.position_limit and self.start_velocity < self.velocity_limit):
            raise ValueError("QuadrotorTrack: the start offsets must lie inside the crash limits")
        g = float(self.gravity)
        quad = Quadrotor(dt=self.dt, gravity=g, thrust_min=0.0, thrust_max=2 * g, rate_max=self.rate_max,
                         mass_scale=float(self.mass_scale),
                         drag=tuple(float(d) for d in self.drag) if any(self.drag) else None)
        object.__setattr__(self, "_system", QuadrotorClock(quad, self.period_steps))
        ref = self._reference_f64()
        s = float(self.mass_scale)
        if not (s * ref.thrust.max() < 2 * g and ref.thrust.min() > 0
                and ref.omega.abs().max() < self.rate_max):
            raise ValueError(f"QuadrotorTrack: the reference needs thrust {s * ref.thrust.min():.3g}…"
                             f"{s * ref.thrust.max():.3g} m/s² and rates up to {ref.omega.abs().max():.3g} "
                             f"rad/s, beyond the limits (0…{2 * g:.3g}, {self.rate_max}); slow it down "
                             "(a larger period_steps)")

    def _check_mismatch(self) -> None:
        s = self.mass_scale
        if not (isinstance(s, (int, float)) and 0 < float(s) < math.inf):
            raise ValueError(f"QuadrotorTrack: argument 'mass_scale' must be a positive finite number, "
                             f"got {s!r}")
        d = self.drag
        if not (isinstance(d, (tuple, list)) and len(d) == 3
                and all(isinstance(c, (int, float)) and 0 <= float(c) < math.inf for c in d)):
            raise ValueError("QuadrotorTrack: argument 'drag' must be a tuple of three finite non-negative "
                             f"coefficients (d_x, d_y, d_z) in 1/s, got {d!r}")

    # -- the reference ------------------------------------------------------------------------------------
    @property
    def omega(self) -> float:
        """Phase rate (rad/s)."""
        return 2 * math.pi / (self.period_steps * self.dt)

    def position(self, t: Tensor) -> Tensor:
        """The reference position at time ``t`` (a 0-dim tensor, s) of the lap that starts at phase 0."""
        s = self.omega * t
        r, zero = self.radius, torch.zeros_like(s)
        if self.shape == "circle":
            return torch.stack((r * torch.cos(s), r * torch.sin(s), zero - self.altitude))
        return torch.stack((r * torch.sin(s), 0.5 * r * torch.sin(2 * s), zero - self.altitude))

    def _reference_f64(self):
        if "f64" not in self._cache:
            from controllers.systems.quadrotor_flatness import flat_reference

            t = torch.arange(self.period_steps, dtype=torch.float64) * self.dt
            self._cache["f64"] = flat_reference(self.position, t, g=float(self.gravity))
        return self._cache["f64"]

    def reference(self, dtype=torch.float64, device=None) -> dict[str, Tensor]:
        """The tabulated lap, ``P`` samples: ``p, v (P, 3)``, ``R (P, 3, 3)``, ``u (P, 4)`` (``[a_T, ω]``; the
        thrust times ``mass_scale``, see the module docstring)."""
        key = (dtype, torch.device(device) if device is not None else torch.device("cpu"))
        if key not in self._cache:
            ref = self._reference_f64()
            u = ref.u
            if float(self.mass_scale) != 1.0:
                u = torch.cat([u[..., :1] * float(self.mass_scale), u[..., 1:]], -1)
            self._cache[key] = {k: v.to(dtype=dtype, device=key[1])
                                for k, v in (("p", ref.p), ("v", ref.v), ("R", ref.R), ("u", u))}
        return self._cache[key]

    def phase_index(self, x: Tensor) -> Tensor:
        """``k`` as int64 ``(*B,)``."""
        return x[..., 15].round().long().remainder(self.period_steps)

    def _errors(self, x: Tensor) -> tuple[Tensor, Tensor]:
        ref = self.reference(x.dtype, x.device)
        k = self.phase_index(x)
        return x[..., 0:3] - ref["p"][k], x[..., 3:6] - ref["v"][k]

    # -- Task -----------------------------------------------------------------------------------------------
    @property
    def system(self) -> QuadrotorClock:
        return self._system

    def u_max(self) -> tuple[float, ...]:
        return (float(self.gravity), self.rate_max, self.rate_max, self.rate_max)

    def obs_high(self) -> np.ndarray:
        # A step starts inside the limits (|e_p,i| ≤ L_p, |e_v,i| ≤ L_v; else the episode has ended, and the
        # initial states are inside), so |v_i| ≤ L_v + V with V = max |v_ref,i|.  One Euler step gives
        # e_p⁺ = e_p + dt v − Δp_ref and e_v⁺ = e_v + dt (g e₃ − (a_T/s) R e₃ − R D Rᵀ v) − Δv_ref, with
        # |(a_T/s) R e₃|_i ≤ 2g/s and |R D Rᵀ v|_i ≤ ‖R D Rᵀ v‖ ≤ d_max ‖v‖ ≤ d_max √3 (L_v + V).
        ref = self._reference_f64()
        nxt = torch.roll(torch.arange(self.period_steps), -1)
        dp = float((ref.p[nxt] - ref.p).abs().max())
        dv = float((ref.v[nxt] - ref.v).abs().max())
        V = float(ref.v.abs().max())
        g, dt = float(self.gravity), self.dt
        ep = self.position_limit + dt * (self.velocity_limit + V) + dp
        s, dmax = float(self.mass_scale), max(float(d) for d in self.drag)
        drag = dt * math.sqrt(3.0) * dmax * (self.velocity_limit + V)
        ev = self.velocity_limit + dt * (1 + 2 / s) * g + drag + dv
        return np.array([ep] * 3 + [ev] * 3 + [1.0] * 11) * (1.0 + 1e-6)

    def initial_state(self, noise: Tensor) -> Tensor:
        from torchlie import so3

        P = self.period_steps
        k = torch.clamp(torch.floor(noise[..., 0] * P), max=P - 1)
        ref = self.reference(noise.dtype, noise.device)
        ki = k.long()
        p = ref["p"][ki] + (2 * noise[..., 1:4] - 1) * self.start_position
        v = ref["v"][ki] + (2 * noise[..., 4:7] - 1) * self.start_velocity
        R = so3.exp((2 * noise[..., 7:10] - 1) * self.start_tilt)
        return _flat(p, v, R, k)

    def observe(self, x: Tensor) -> Tensor:
        ep, ev = self._errors(x)
        ang = x[..., 15] * (2 * math.pi / self.period_steps)
        return torch.cat([ep, ev, x[..., 6:15], torch.cos(ang)[..., None], torch.sin(ang)[..., None]], -1)

    def state_from_obs(self, obs: Tensor) -> Tensor:
        P = self.period_steps
        k = torch.remainder(torch.round(torch.atan2(obs[..., 16], obs[..., 15]) * (P / (2 * math.pi))), P)
        ref = self.reference(obs.dtype, obs.device)
        ki = k.long()
        return torch.cat([obs[..., 0:3] + ref["p"][ki], obs[..., 3:6] + ref["v"][ki], obs[..., 6:15],
                          k[..., None]], -1)

    def reward(self, x: Tensor, u: Tensor, x_next: Tensor) -> Tensor:
        ep, _ = self._errors(x_next)
        a = u / self.u_scale(u.dtype, u.device)
        near = 1.0 / (1.0 + ep.square().sum(-1) / 0.04)
        return near * (1.0 - 0.0125 * a.square().sum(-1))

    def terminated(self, x: Tensor) -> Tensor:
        ep, ev = self._errors(x)
        return ((ep.abs() > self.position_limit).any(-1) | (ev.abs() > self.velocity_limit).any(-1)
                | (x[..., 14] < 0))

    def error(self, x: Tensor) -> Tensor:
        return self._errors(x)[0].norm(dim=-1)

    def success(self, x: Tensor) -> Tensor:
        ep, ev = self._errors(x)
        return (ep.norm(dim=-1) < 0.1) & (ev.norm(dim=-1) < 0.3)

    def mpc_cost(self, horizon: int, *, dtype=torch.float64, device=None):
        raise NotImplementedError("QuadrotorTrack: its MPC is the error-state MPC on R³×R³×SO(3) "
                                  "(QuadrotorTrackingExpert), not a quadratic cost on the flat state")

    def expert(self, horizon: int | None = None, **kwargs) -> QuadrotorTrackingExpert:
        return QuadrotorTrackingExpert(self, horizon, **kwargs)

    def frame(self, x: np.ndarray, size: int = 256) -> np.ndarray:
        """Top view (north up, east right) of the lap, the reference point and the vehicle's arms."""
        ext = self.radius + 0.8
        cv = Canvas(size, extent=ext)
        ref = self._reference_f64()
        pts = ref.p[:, :2].numpy()
        for a, b in zip(pts, np.roll(pts, -1, 0)):
            cv.segment((a[1], a[0]), (b[1], b[0]), 0.03, (150, 150, 150))
        k = int(round(float(x[15]))) % self.period_steps
        cv.disc((pts[k, 1], pts[k, 0]), 0.07, (80, 160, 80))
        p = x[0:3]
        R = np.asarray(x[6:15], dtype=np.float64).reshape(3, 3)
        arm = 0.25
        for axis, color in ((R[:, 0], (204, 77, 77)), (R[:, 1], (60, 90, 160))):
            a = (p[1] - arm * axis[1], p[0] - arm * axis[0])
            b = (p[1] + arm * axis[1], p[0] + arm * axis[0])
            cv.segment(a, b, 0.05, color)
        cv.disc((p[1], p[0]), 0.06, (40, 40, 40))
        return cv.img


@dataclass(frozen=True, eq=False)
class QuadrotorFigureEight(QuadrotorTrack):
    """:class:`QuadrotorTrack` on the figure-eight (Gerono's lemniscate ``(r sin s, (r/2) sin 2s, −h)``)."""

    name: ClassVar[str] = "QuadrotorFigureEight"
    shape: str = "figure8"


class QuadrotorTrackingExpert(ErrorStateExpert):
    """The error-state MPC of seed 003 (:class:`~controllers.manifold_mpc.ErrorStateMPC`) on a
    :class:`QuadrotorTrack`: from each observation, the state ``(p, v, R)`` and phase ``k``; the reference of
    the next ``horizon`` steps from the task's table; one QP under the thrust and rate limits, warm-started
    with the previous plan; action ``(u − [g, 0, 0, 0]) / u_max``.  A :class:`learning.policies.Policy`.

    Weights ``Q = diag(q_p I, q_v I, q_R I)``, ``R = diag(r_T, r_ω I)`` and the DARE weight at hover as the
    terminal weight (:func:`~controllers.manifold_mpc.riccati_terminal_weight`).  The solve follows the
    observation's dtype and device.
    """

    def __init__(self, task: QuadrotorTrack, horizon: int | None = None, *, q_p: float = 100.0,
                 q_v: float = 10.0, q_R: float = 10.0, r_T: float = 0.1, r_w: float = 0.1):
        super().__init__()
        self.task = task
        self.horizon = int(horizon or 25)
        self.weights = dict(Q=[q_p] * 3 + [q_v] * 3 + [q_R] * 3, R=[r_T] + [r_w] * 3)
        self._mpcs: dict[Any, Any] = {}

    def _mpc(self, dtype, device):
        from controllers.manifold_mpc import ErrorStateMPC, riccati_terminal_weight

        key = (dtype, device)
        if key not in self._mpcs:
            quad = self.task.system.quad
            Q = torch.tensor(self.weights["Q"], dtype=torch.float64)
            R = torch.tensor(self.weights["R"], dtype=torch.float64)
            x_h, u_h = quad.hover(torch.zeros(3, dtype=torch.float64))
            P, _ = riccati_terminal_weight(quad, x_h, u_h, Q, R)
            kw = dict(dtype=dtype, device=device)
            self._mpcs[key] = ErrorStateMPC(quad, self.horizon, Q.to(**kw), R.to(**kw), P.to(**kw),
                                            grad="none")
        return self._mpcs[key]

    @torch.no_grad()
    def act(self, obs: Tensor) -> Tensor:
        task, H = self.task, self.horizon
        x = task.state_from_obs(obs)
        sysm = task.system
        mpc = self._mpc(obs.dtype, obs.device)
        ref = task.reference(obs.dtype, obs.device)
        idx = (task.phase_index(x)[:, None] + torch.arange(H + 1, device=obs.device)) % task.period_steps
        from torchlie.manifolds import ProductState

        x_ref = ProductState({"p": ref["p"][idx], "v": ref["v"][idx], "R": ref["R"][idx]},
                             {"p": 1, "v": 1, "R": 2})
        u_ref = ref["u"][idx[:, :H]]
        sol = mpc.solve(sysm.point(x), x_ref, u_ref, warm=self._warm_start(u_ref))
        self._remember(sol, obs.device)
        g = torch.as_tensor(sysm.quad.gravity, dtype=obs.dtype, device=obs.device)
        du = torch.cat([sol.u[:, :1] - g, sol.u[:, 1:]], -1)
        return du / task.u_scale(obs.dtype, obs.device)
