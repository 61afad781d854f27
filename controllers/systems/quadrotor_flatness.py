"""Quadrotor reference trajectories from differential flatness (seed "on-manifold MPC", Eq. 32, §VII-A).

Model and conventions.  World frame north-east-DOWN (NED), body frame forward-right-down (FRD); SI units
(m, s, rad).  State ``p (3,)`` [m], ``v (3,)`` [m/s], ``R ∈ SO(3)`` (body → world); controls
``u = [a_T, ω_x, ω_y, ω_z]``: the mass-normalized collective thrust [m/s²] and the body rates [rad/s]::

    ṗ = v,    v̇ = g e₃ − a_T R e₃,    Ṙ = R [ω]×,        e₃ = [0, 0, 1],  g = 9.81 m/s².

``z`` points down, so gravity is ``+g e₃`` and the thrust acts along the body's ``−z`` (its "up").  The
position is a flat output: for a trajectory ``p(t)`` with ``a = p̈``,

    a_T = ‖g e₃ − a‖,    z_b = R e₃ = (g e₃ − a) / a_T,

and the rotation about ``z_b`` is fixed by one extra constraint (:func:`flat_reference`):

* yaw ``ψ(t)`` (default ``ψ ≡ 0``): ``x_c = [cos ψ, sin ψ, 0]``, ``y_b = (z_b × x_c)/‖·‖``,
  ``x_b = y_b × z_b`` (``ψ`` is the first angle of a Z-X-Y Euler sequence; singular where ``z_b ∥ x_c``);
* a body pitch axis ``c``: ``y_b = (c − (c·z_b) z_b)/‖·‖``, ``x_b = y_b × z_b`` (singular only where
  ``z_b ∥ c``): with ``c = e₂`` and motion in the x–z plane, ``z_b ⟂ c`` always, so vertical loops and
  flips have no singularity.

``R = [x_b y_b z_b]`` (columns).  All derivatives are exact: velocity, acceleration and ``Ṙ`` come from
forward-mode automatic differentiation (:func:`torch.func.jacfwd`) of the position with respect to time,
vectorized over the samples with :func:`torch.func.vmap`; the body rates are ``ω = vee(Rᵀ Ṙ)``.

Scenarios (seed §VII-A): :func:`circle_ramp` (circle with a linear speed ramp to 5 m/s),
:func:`triple_flip` (three vertical flips) and :func:`loop` (a fast horizontal loop at 8 m/s).  Each
samples its trajectory every ``dt`` from ``t = 0`` to its nominal end, then ``pad`` more samples for an
MPC horizon (what the trajectory does there is stated per scenario).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import NamedTuple

import torch
from torch import Tensor
from torch.func import jacfwd, vmap

__all__ = ["FlatReference", "flat_reference", "circle_ramp", "triple_flip", "loop", "GRAVITY"]

#: standard gravity [m/s²] used by default
GRAVITY = 9.81
#: the construction is reported singular where ‖g e₃ − a‖ / g, or the sine of the angle between ``z_b`` and
#: the heading direction, falls below this
_SINGULAR_TOL = 1e-6

PositionFn = Callable[[Tensor], Tensor]
YawFn = Callable[[Tensor], Tensor]


class FlatReference(NamedTuple):
    """A sampled quadrotor reference (NED, SI units; module docstring); ``K`` samples.

    Attributes:
        t: ``(K,)`` sample times [s].
        p, v, a: ``(K, 3)`` position [m], velocity [m/s], acceleration [m/s²] in the world frame.
        R: ``(K, 3, 3)`` attitude, body (FRD) → world (NED).
        thrust: ``(K,)`` mass-normalized collective thrust ``a_T`` [m/s²] (always > 0).
        omega: ``(K, 3)`` body rates [rad/s].
    """

    t: Tensor
    p: Tensor
    v: Tensor
    a: Tensor
    R: Tensor
    thrust: Tensor
    omega: Tensor

    @property
    def u(self) -> Tensor:
        """Controls ``(K, 4) = [a_T, ω_x, ω_y, ω_z]``."""
        return torch.cat([self.thrust.unsqueeze(-1), self.omega], dim=-1)

    def peaks(self) -> dict[str, float]:
        """Peak figures over all samples: ``speed`` [m/s], ``thrust`` (max ``a_T``) and ``thrust_min``
        [m/s²], ``rate`` (max ‖ω‖) [rad/s], ``accel`` (max ‖a‖) [m/s²]."""
        return {"speed": self.v.norm(dim=-1).max().item(),
                "thrust": self.thrust.max().item(),
                "thrust_min": self.thrust.min().item(),
                "rate": self.omega.norm(dim=-1).max().item(),
                "accel": self.a.norm(dim=-1).max().item()}


# --------------------------------------------------------------------------------------------------
# flatness map
# --------------------------------------------------------------------------------------------------

def _normalize(x: Tensor) -> Tensor:
    return x / x.norm(dim=-1, keepdim=True)


def _vee(M: Tensor) -> Tensor:
    return 0.5 * torch.stack((M[..., 2, 1] - M[..., 1, 2], M[..., 0, 2] - M[..., 2, 0],
                              M[..., 1, 0] - M[..., 0, 1]), dim=-1)


def _heading_dir(heading, tk: Tensor) -> Tensor:
    """``x_c = [cos ψ, sin ψ, 0]`` at the scalar time ``tk``."""
    psi = heading(tk) if callable(heading) else torch.as_tensor(heading, dtype=tk.dtype, device=tk.device)
    if psi.shape != ():
        raise ValueError(f"flat_reference: argument 'heading' must give a scalar yaw, got shape "
                         f"{tuple(psi.shape)}")
    return torch.stack((torch.cos(psi), torch.sin(psi), torch.zeros_like(psi)))


def _first_bad(mask: Tensor) -> int | None:
    idx = torch.nonzero(mask)
    return None if idx.numel() == 0 else int(idx[0, 0])


def flat_reference(position: PositionFn, t, *, heading: YawFn | float | None = None,
                   pitch_axis: Sequence[float] | Tensor | None = None, g: float = GRAVITY,
                   dtype: torch.dtype | None = None, device=None) -> FlatReference:
    """Sample the quadrotor reference of a flat output ``position`` at the times ``t``.

    Args:
        position: ``p(t)``: maps a 0-dim time tensor [s] to the position ``(3,)`` [m] (NED).  It is
            differentiated three times by :func:`torch.func.jacfwd` and vectorized by :func:`torch.func.vmap`,
            so it must be a smooth (at least C³ for continuous body rates) torch function without
            data-dependent Python control flow (use ``torch.where``/``clamp`` for pieces).
        t: ``(K,)`` sample times [s] (tensor, sequence or number).
        heading: yaw ``ψ`` [rad]: a function of the 0-dim time tensor returning a 0-dim tensor, or a
            constant; ``None`` is ``ψ ≡ 0``.  ``x_c = [cos ψ, sin ψ, 0]``, ``y_b ∝ z_b × x_c``.
        pitch_axis: instead of ``heading``, a fixed direction ``c`` ``(3,)`` for the body ``y`` axis:
            ``y_b ∝ c − (c·z_b) z_b`` (e.g. ``(0, 1, 0)`` for loops and flips in the x–z plane).
        g: gravity [m/s²].
        dtype, device: of the result; by default those of ``t`` when it is a floating tensor, else
            ``float64`` on the CPU.  Lower precisions than float64 are computed in float64 and cast.

    Returns:
        :class:`FlatReference` with ``ω = vee(Rᵀ Ṙ)``, ``Ṙ`` differentiated exactly through the construction.

    Raises:
        ValueError: where the construction is singular, naming the argument and the first time index:
            ``position`` where ``‖g e₃ − a‖ ≈ 0`` (free fall: no thrust direction), ``heading`` where
            ``z_b ∥ x_c``, ``pitch_axis`` where ``z_b ∥ c``; or for both ``heading`` and ``pitch_axis``.
    """
    if heading is not None and pitch_axis is not None:
        raise ValueError("flat_reference: give either argument 'heading' (a yaw) or 'pitch_axis', not both")
    if not callable(position):
        raise TypeError("flat_reference: argument 'position' must be a function of time")
    if dtype is None:
        dtype = t.dtype if isinstance(t, Tensor) and t.is_floating_point() else torch.float64
    if device is None and isinstance(t, Tensor):
        device = t.device
    t_out = torch.as_tensor(t, dtype=dtype, device=device).reshape(-1)
    # lower precisions are computed in float64 and cast at the end: forward-mode AD under vmap promotes
    # products with Python scalars to float64 in the tangents, which would mix dtypes otherwise
    work = torch.float64 if dtype.itemsize < 8 else dtype
    t = t_out.to(work)
    e3 = torch.tensor([0.0, 0.0, 1.0], dtype=work, device=t.device)
    c = None
    if pitch_axis is not None:
        c = torch.as_tensor(pitch_axis, dtype=work, device=t.device)
        if c.shape != (3,) or not bool(c.norm() > 0):
            raise ValueError(f"flat_reference: argument 'pitch_axis' must be a nonzero 3-vector, got {c}")
        c = c / c.norm()
    elif heading is None:
        heading = 0.0

    def zb_of(a: Tensor) -> tuple[Tensor, Tensor]:
        f = g * e3 - a
        return f, f.norm(dim=-1)

    # one nested forward-mode pass: each level differentiates the previous one and carries its values
    def p_once(s: Tensor):
        q = position(s)
        if q.shape != (3,):
            raise ValueError("flat_reference: argument 'position' must map a scalar time to a (3,) "
                             f"position, got shape {tuple(q.shape)}")
        return q, q

    vel = jacfwd(p_once, has_aux=True)  # s -> (v, p)
    acc = jacfwd(lambda s: (lambda v, p: (v, (v, p)))(*vel(s)), has_aux=True)  # s -> (a, (v, p))

    def frame(s: Tensor):
        a, (v, p) = acc(s)
        a, v, p = a.to(work), v.to(work), p.to(work)
        f, aT = zb_of(a)
        zb = f / aT
        if c is None:
            yb = _normalize(torch.linalg.cross(zb, _heading_dir(heading, s)))
        else:
            yb = _normalize(c - (c @ zb) * zb)
        R = torch.stack((torch.linalg.cross(yb, zb), yb, zb), dim=-1)
        return R, (R, p, v, a)

    # NaNs where singular are caught below, before anything is returned
    Rdot, (R, p, v, a) = vmap(jacfwd(frame, has_aux=True))(t)
    f, thrust = zb_of(a)

    def fail(arg: str, k: int, what: str):
        raise ValueError(f"flat_reference: argument '{arg}' makes the attitude singular at time index {k} "
                         f"(t = {t[k].item():.6g} s): {what}")

    k = _first_bad(~(thrust > _SINGULAR_TOL * g))  # also catches NaN
    if k is not None:
        fail("position", k, f"‖g e3 − a‖ = {thrust[k].item():.3g} m/s² (free fall, no thrust direction)")
    zb = f / thrust.unsqueeze(-1)
    if c is None:
        xc = vmap(lambda s: _heading_dir(heading, s))(t)
        sin = torch.linalg.cross(zb, xc).norm(dim=-1)
        k = _first_bad(~(sin > _SINGULAR_TOL))
        if k is not None:
            fail("heading", k, "the thrust axis z_b is parallel to the heading x_c = [cos ψ, sin ψ, 0]")
    else:
        sin = (c - (zb @ c).unsqueeze(-1) * zb).norm(dim=-1)
        k = _first_bad(~(sin > _SINGULAR_TOL))
        if k is not None:
            fail("pitch_axis", k, "the thrust axis z_b is parallel to the pitch axis c")

    omega = _vee(R.transpose(-1, -2) @ Rdot.to(work))
    return FlatReference(t_out, *(x.to(dtype) for x in (p, v, a, R, thrust, omega)))


# --------------------------------------------------------------------------------------------------
# smooth profiles
# --------------------------------------------------------------------------------------------------
# σ(x) = 35x⁴ − 84x⁵ + 70x⁶ − 20x⁷ is the septic smooth step: 0 for x ≤ 0, 1 for x ≥ 1, with its first
# three derivatives zero at both ends (C³).  S = ∫σ and S₂ = ∫S are continued exactly beyond [0, 1]
# (S(x) = x − ½ and S₂(x) = 5/36 + (x − 1)/2 + (x − 1)²/2 for x ≥ 1).  A speed profile shaped by σ (the
# flips) gives C⁴ positions, a tangential acceleration shaped by σ (circle, loop) C⁵ positions: either way
# acceleration, jerk (hence the body rates) and snap are continuous.

def _beyond(x: Tensor) -> Tensor:
    """``max(x − 1, 0)`` with derivative 0 at ``x = 1`` (``clamp(0, 1)`` already passes the derivative there;
    ``clamp(min=0)`` would pass it a second time)."""
    return torch.where(x > 1.0, x - 1.0, torch.zeros_like(x))


def _ramp1(x: Tensor) -> Tensor:
    """``S(x) = ∫₀ˣ σ``."""
    xc = x.clamp(0.0, 1.0)
    return xc ** 5 * (7.0 - 14.0 * xc + 10.0 * xc ** 2 - 2.5 * xc ** 3) + _beyond(x)


def _ramp2(x: Tensor) -> Tensor:
    """``S₂(x) = ∫₀ˣ S``."""
    xc = x.clamp(0.0, 1.0)
    d = _beyond(x)
    return (xc ** 6 * (7.0 / 6.0 - 2.0 * xc + 1.25 * xc ** 2 - (5.0 / 18.0) * xc ** 3)
            + 0.5 * d + 0.5 * d * d)


def _ramp_arc(t: Tensor, v_end: float, ramp_time: float, blend: float) -> Tensor:
    """Arc length of a speed profile rising from 0 to ``v_end`` over ``[0, ramp_time]``: linear with
    its acceleration ``v_end / (ramp_time − blend)`` switched on over ``[0, blend]`` and off over
    ``[ramp_time − blend, ramp_time]`` by σ, constant ``v_end`` afterwards."""
    acc = v_end / (ramp_time - blend)
    return acc * blend ** 2 * (_ramp2(t / blend) - _ramp2((t - ramp_time + blend) / blend))


def _grid(end: float, dt: float, pad: int, t, dtype, device) -> Tensor:
    dtype = torch.float64 if dtype is None else dtype
    if t is not None:
        return torch.as_tensor(t, dtype=dtype, device=device).reshape(-1)
    if not dt > 0:
        raise ValueError(f"argument 'dt' must be positive, got {dt}")
    if pad < 0:
        raise ValueError(f"argument 'pad' must be >= 0, got {pad}")
    n = math.ceil(end / dt - 1e-9)
    return torch.arange(n + 1 + pad, dtype=dtype, device=device) * dt


def _positive(fn: str, **values) -> None:
    for k, x in values.items():
        if not x > 0:
            raise ValueError(f"{fn}: argument '{k}' must be positive, got {x}")


def _horizontal_circle(radius: float, altitude: float, arc: Callable[[Tensor], Tensor]) -> PositionFn:
    def position(tk: Tensor) -> Tensor:
        th = arc(tk) / radius
        return torch.stack((radius * torch.cos(th), radius * torch.sin(th),
                            torch.full_like(th, -altitude)))
    return position


# --------------------------------------------------------------------------------------------------
# scenarios
# --------------------------------------------------------------------------------------------------

def circle_ramp(radius: float = 1.3, v_max: float = 5.0, duration: float = 12.0, altitude: float = 1.0, *,
                blend: float = 1.0, heading: YawFn | float | None = None, dt: float = 0.01, pad: int = 50,
                t=None, g: float = GRAVITY, dtype: torch.dtype | None = None, device=None) -> FlatReference:
    """Horizontal circle with a linear speed ramp (seed §VII-A): from hover at rest to ``v_max``.

    The circle has centre ``(0, 0, −altitude)`` (NED: ``altitude`` [m] above the origin) and starts at
    ``(radius, 0, −altitude)``, counter-clockwise seen from below (``+x`` towards ``+y``).  The speed rises
    linearly, with tangential acceleration ``v_max / (duration − blend)``, switched on over the first
    ``blend`` seconds and off over the last by a C³ smooth step, so the reference starts in exact hover
    (``v = a = 0``, ``R = I``, ``ω = 0``) and reaches ``v_max`` exactly at ``t = duration``.  The angle
    ``θ(t) = ∫ speed / radius`` is in closed form.  The ``pad`` samples after ``duration`` continue the
    circle at the constant speed ``v_max`` (smoothly).

    Defaults (r = 1.3 m, 5 m/s, 12 s, blend 1 s, ψ ≡ 0): tangential acceleration 5/11 = 0.45 m/s²,
    3.7 laps by ``t = 12 s``; peak speed 5.0 m/s, peak centripetal acceleration v²/r = 19.23 m/s² (1.96 g),
    thrust a_T ∈ [9.81, 21.59] m/s² (peak √(g² + (v²/r)²) = 2.2 g), peak body rate ‖ω‖ = 7.58 rad/s
    (the thrust axis, tilted 63°, turns at v/r = 3.85 rad/s about the vertical while the yaw stays 0).

    Args:
        radius [m], v_max [m/s], duration [s] (of the ramp; > blend), altitude [m].
        blend: duration [s] of the smooth switch-on/off of the tangential acceleration.
        heading: yaw (:func:`flat_reference`); default ψ ≡ 0.
        dt: sample period [s] (100 Hz by default); pad: extra samples after ``duration``.
        t: explicit sample times [s] instead of the ``dt``/``pad`` grid.
        g, dtype (default float64), device.
    """
    _positive("circle_ramp", radius=radius, v_max=v_max, blend=blend)
    if not duration > blend:
        raise ValueError(f"circle_ramp: argument 'duration' must exceed blend = {blend}, got {duration}")
    pos = _horizontal_circle(radius, altitude, lambda tk: _ramp_arc(tk, v_max, duration, blend))
    return flat_reference(pos, _grid(duration, dt, pad, t, dtype, device), heading=heading, g=g)


def loop(speed: float = 8.0, radius: float = 5.0, laps: int = 3, altitude: float = 1.0, *,
         ramp_time: float = 4.0, blend: float = 1.0, heading: YawFn | float | None = None, dt: float = 0.01,
         pad: int = 50, t=None, g: float = GRAVITY, dtype: torch.dtype | None = None,
         device=None) -> FlatReference:
    """Fast horizontal circular loop (drag-mismatch experiment): a smooth ramp to ``speed``, then
    ``laps`` full laps held at ``speed``.

    Same geometry and speed profile as :func:`circle_ramp` (centre ``(0, 0, −altitude)``, start in exact
    hover at ``(radius, 0, −altitude)``; speed ramp over ``ramp_time`` with ``blend``-second C³
    switch-on/off of the tangential acceleration ``speed / (ramp_time − blend)``); the nominal end is
    ``ramp_time + laps · 2π radius / speed`` and the ``pad`` samples after it continue the loop at
    ``speed``.

    Defaults (8 m/s, r = 5 m, 3 laps, ramp 4 s, blend 1 s, ψ ≡ 0): nominal end 15.78 s; peak speed
    8.0 m/s, lateral acceleration v²/r = 12.8 m/s² (1.30 g), thrust a_T ∈ [9.81, 16.13] m/s² (1.64 g),
    peak body rate ‖ω‖ = 2.09 rad/s.

    Args:
        speed [m/s], radius [m], laps (≥ 0, held at ``speed``), altitude [m], ramp_time [s] (> blend),
        blend [s], heading, dt [s], pad, t, g, dtype, device: as in :func:`circle_ramp`.
    """
    _positive("loop", speed=speed, radius=radius, blend=blend)
    if not ramp_time > blend:
        raise ValueError(f"loop: argument 'ramp_time' must exceed blend = {blend}, got {ramp_time}")
    if laps < 0:
        raise ValueError(f"loop: argument 'laps' must be >= 0, got {laps}")
    end = ramp_time + laps * 2.0 * math.pi * radius / speed
    pos = _horizontal_circle(radius, altitude, lambda tk: _ramp_arc(tk, speed, ramp_time, blend))
    return flat_reference(pos, _grid(end, dt, pad, t, dtype, device), heading=heading, g=g)


def triple_flip(radius: float = 1.0, speed: float = 4.5, flips: int = 3, altitude: float = 2.0, *,
                ramp_time: float = 0.6, dt: float = 0.01, pad: int = 50, t=None, g: float = GRAVITY,
                dtype: torch.dtype | None = None, device=None) -> FlatReference:
    """Consecutive vertical flips: ``flips`` vertical loops in the x–z plane, from hover to hover.

    Path ``p = (r sin φ, 0, −altitude − r (1 − cos φ))`` (NED; the loops start and end at the bottom
    point ``(0, 0, −altitude)`` and rise to ``2 r`` above it, moving forward (+x) at the bottom).  The
    angular speed is ``φ̇ = (speed / r) (σ(t/T) − σ((t − t₂)/T))`` with ``T = ramp_time``, σ the C³ smooth
    step and ``t₂ = 2π flips r / speed``, so ``φ`` goes from 0 to ``2π flips`` exactly: the speed rises
    smoothly from rest to ``speed`` over the angle ``speed T / (2 r)`` (1.35 rad, under a quarter loop,
    by default) and falls back to rest over the same angle at the end, and acceleration, jerk and snap are
    continuous.  The body ``y`` axis stays ``e₂`` (``pitch_axis``), so ``ω = (0, ω_y, 0)``: the body
    pitches nose-down to speed up, then nose-up (``ω_y > 0``) through one full turn per loop, nose-up to
    slow down, and back to level (``∫ω_y dt = 2π flips``).  It is upside down at each top
    (``R e₃ = −e₃``: body z up, thrust pointing down towards the centre), where ``a_T = v²/r − g``: the
    construction needs ``speed² / r > g``.  Nominal end ``t₂ + T``; the ``pad`` samples after it hold
    hover at the start point.

    Defaults (r = 1 m, 4.5 m/s, 3 flips, T = 0.6 s; v²/r = 2.06 g): nominal end 4.79 s; peak speed
    4.5 m/s, thrust a_T ∈ [9.81, 30.06] m/s² (g at rest, 10.44 m/s² at the tops, peak 3.06 g at the
    bottoms), peak body rate 8.73 rad/s (ω_y at the tops, ``(v/r) κ/(κ − 1)`` with ``κ = v²/(g r)``).

    Args:
        radius [m], speed [m/s] at the loops (``speed² / radius > g``), flips (≥ 1), altitude [m] of
        the bottom point, ramp_time [s] of the speed-up and slow-down (≤ ``t₂``), dt [s], pad, t, g,
        dtype (default float64), device: as in :func:`circle_ramp`.
    """
    _positive("triple_flip", radius=radius, speed=speed, ramp_time=ramp_time)
    if not speed ** 2 / radius > g:
        raise ValueError(f"triple_flip: argument 'speed' must satisfy speed²/radius > g for positive thrust "
                         f"at the tops of the loops, got {speed}²/{radius} = {speed ** 2 / radius:.3g} m/s²")
    if int(flips) != flips or flips < 1:
        raise ValueError(f"triple_flip: argument 'flips' must be a positive integer, got {flips}")
    rate = speed / radius
    t2 = 2.0 * math.pi * flips / rate
    if not ramp_time <= t2:
        raise ValueError(f"triple_flip: argument 'ramp_time' must be <= {t2:.4g} s (the flips' duration at "
                         f"full speed), got {ramp_time}")

    def position(tk: Tensor) -> Tensor:
        phi = rate * ramp_time * (_ramp1(tk / ramp_time) - _ramp1((tk - t2) / ramp_time))
        return torch.stack((radius * torch.sin(phi), torch.zeros_like(phi),
                            -altitude - radius * (1.0 - torch.cos(phi))))

    grid = _grid(t2 + ramp_time, dt, pad, t, dtype, device)
    return flat_reference(position, grid, pitch_axis=(0.0, 1.0, 0.0), g=g)
