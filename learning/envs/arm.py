"""Reaching with a planar n-link arm on :class:`controllers.systems.PlanarArm`, optionally through via-points
and around circular obstacles.

**Where the target lives.**  A :class:`~learning.envs.task.Task` sees only the system state ``x`` (its
``observe``/``reward``/``mpc_cost`` are functions of ``x``), so the task's system is the arm with the
target appended as two *constant* state components: :class:`WithConstants` steps the arm with the arm's own
``step`` (one dynamics definition) and carries the extra components unchanged (its Jacobian is the arm's,
block-diagonal with an identity).  State ``x = [q (k), q̇ (k), target (2)]``; the initial-state
distribution draws the target, the vector env resets it with the rest of the state, ``state_from_obs``
recovers it from the observation, and the MPC cost reads it from the state — so one
:class:`~controllers.costs.ResidualCost` serves every environment and every target (no per-env cost).

* Observation ``[cos q, sin q, q̇, target, ee - target]`` (``3k + 4``), ee the end-effector position.
* Reward ``-(|ee' - target|² + c_u |a|² + w_o Σ pen²)`` on the state *after* the step (``a = τ/τ_max`` the
  normalized action, ``pen`` the depth of each link segment inside each obstacle), minus a one-off
  :meth:`ArmReach.termination_cost` when the step ends the episode (see below).
* Termination: a joint faster than ``speed_limit`` (the dynamics are not clipped; this is what keeps the
  observation bounded, as for the cart-pole), or, with ``terminate_on_collision=True``, a link inside an
  obstacle.  Since every per-step reward is ``≤ 0``, ending an episode early would otherwise be attractive;
  the penalty is by default 1000 times the largest per-step cost, so it never is in an episode of up to
  1000 steps (it does not depend on ``max_episode_steps``, so that an env whose time limit is set from
  outside the task, e.g. by ``gym.make(..., max_episode_steps=K)``, gives the same rewards).  Without
  termination on collision, :meth:`ArmReach.collisions` counts the violations of a state (for evaluation).
* Success: ``|ee - target| < 0.05 · reach`` and every ``|q̇_j| < success_speed`` at the end; error
  ``|ee - target|``.
* Initial state: joint angles uniform in ``[-π, π)``, at rest; the target uniform (in area) in the annulus
  ``target_radius · reach`` around the base, uniform in angle.  Obstacles are fixed by the constructor;
  a drawn target or initial configuration may lie inside one (choose obstacles off the sampled region).

**Via-points** (``via_points = V > 0``): the end effector must pass ``V`` points, in order, before the
target.  They are drawn like the target and carried in the state after it, followed by a counter ``j``
of the via-points passed (:class:`ArmWaypoints`).  Passing a via-point is a task event, not dynamics: the
system carries ``j`` unchanged like the other constants (so the MPC plans towards the next waypoint
``w_j``, a smooth problem), and :meth:`ArmReach.step` advances ``j`` after the arm's step when the new
end-effector position lies within ``via_radius · reach`` of ``w_j`` (:meth:`ArmWaypoints.advance`).  State
``[q, q̇, target, via_1 … via_V, j]``; the observation appends ``[via_1 … via_V, w_j, ee − w_j, j]`` to
the one above (``w_j`` the next waypoint: via-point ``j + 1``, or the target once all are passed).  The
tracking term of the reward and of the MPC cost is the squared *distance to go*
``d = |ee − w_j| + Σ`` (lengths of the remaining legs ``w_j → … → target``), which never grows when a
via-point is passed (the triangle inequality), so passing one never costs reward; :meth:`ArmReach.error`
is ``d`` and success requires every via-point passed.  The MPC cost tracks ``ee − w_j`` (the constant
remaining legs change nothing in a plan with ``j`` held).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
import torch
from torch import Tensor

from controllers.systems import PlanarArm
from learning.envs._canvas import Canvas
from learning.envs.task import Task, hi, lo

__all__ = ["ArmReach", "WithConstants", "ArmWaypoints"]


@dataclass(frozen=True, eq=False)
class WithConstants:
    """A system whose state carries ``extra`` components that every step keeps unchanged (a goal, a
    task parameter), appended after the state of ``base``: ``step([x, c], u) = [base.step(x, u), c]``.

    A :class:`controllers.dynamics.System` with the analytic Jacobian ``A = diag(A_base, I)``,
    ``B = [B_base; 0]`` (requires ``base.jacobian``); ``dt`` and ``time_invariant`` are the base's.
    """

    base: Any
    extra: int

    @property
    def n(self) -> int:
        return self.base.n + self.extra

    @property
    def m(self) -> int:
        return self.base.m

    @property
    def time_invariant(self) -> bool:
        return bool(getattr(self.base, "time_invariant", False))

    @property
    def dt(self):
        return self.base.dt

    def step(self, x: Tensor, u: Tensor, t: int = 0) -> Tensor:
        nb = self.base.n
        y = self.base.step(x[..., :nb], u, t)
        c = x[..., nb:]
        if c.shape[:-1] != y.shape[:-1]:
            c = c.expand(*y.shape[:-1], self.extra)
        return torch.cat([y, c], -1)

    def jacobian(self, x: Tensor, u: Tensor, t: int = 0) -> tuple[Tensor, Tensor]:
        nb, p = self.base.n, self.extra
        A, B = self.base.jacobian(x[..., :nb], u, t)
        bs = A.shape[:-2]
        zr = A.new_zeros(*bs, nb, p)
        eye = torch.eye(p, dtype=A.dtype, device=A.device).expand(*bs, p, p)
        A = torch.cat([torch.cat([A, zr], -1), torch.cat([zr.mT, eye], -1)], -2)
        return A, torch.cat([B, B.new_zeros(*bs, p, B.shape[-1])], -2)


@dataclass(frozen=True, eq=False)
class ArmWaypoints(WithConstants):
    """:class:`WithConstants` over a planar arm whose constants are ``[target, via_1 … via_V]`` followed by
    a counter ``j`` of the via-points passed (``extra = 2V + 3``), which its step carries unchanged;
    :meth:`advance` is the task's event ``j⁺ = j + 1`` where ``j < V`` and the end effector lies within
    ``radius`` of via-point ``j + 1``."""

    vias: int = 0
    radius: float = 0.0

    def waypoints(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """``(points (*B, V+1, 2) = [via_1 … via_V, target], j (*B,) int64)``."""
        nb, V = self.base.n, self.vias
        tgt = x[..., nb:nb + 2]
        vias = x[..., nb + 2:nb + 2 + 2 * V].unflatten(-1, (V, 2))
        j = x[..., nb + 2 + 2 * V].round().long().clamp(0, V)
        return torch.cat([vias, tgt[..., None, :]], -2), j

    def current(self, x: Tensor) -> Tensor:
        """The next waypoint ``w_j`` ``(*B, 2)``."""
        pts, j = self.waypoints(x)
        return torch.gather(pts, -2, j[..., None, None].expand(*j.shape, 1, 2)).squeeze(-2)

    def advance(self, x: Tensor) -> Tensor:
        """``x`` with ``j`` advanced where the end effector is within ``radius`` of the next via-point."""
        ee = self.base.end_effector(x[..., :self.base.links])
        e = ee - self.current(x)
        j = x[..., -1]
        passed = (j < self.vias) & ((e * e).sum(-1) < self.radius * self.radius)
        return torch.cat([x[..., :-1], (j + passed.to(j.dtype))[..., None]], -1)


def _default_arm() -> PlanarArm:
    return PlanarArm(links=2, lengths=0.5, masses=1.0, damping=0.1, gravity=0.0, dt=0.05)


@dataclass(frozen=True, eq=False)
class ArmReach(Task):
    """Reach a random target with the end effector and stop there (module docstring).

    Args:
        model: the arm (default: 2 links of 0.5 m with 1 kg tip masses, damping 0.1, horizontal).
        max_torque: torque limit per joint (float, or one per joint).
        speed_limit: joint speed [rad/s] above which the episode terminates.
        target_radius: ``(r_min, r_max)`` of the target annulus, as fractions of the reach.
        control_cost: weight ``c_u`` of ``|a|²`` (normalized action) in the reward.
        obstacles: circles ``((cx, cy, r), ...)`` the links must stay out of.
        obstacle_weight: weight ``w_o`` of the squared penetration depths in the reward and the MPC cost.
        obstacle_margin: the MPC cost keeps the links this far outside the obstacles (fraction of the reach).
        terminate_on_collision: end the episode when a link is inside an obstacle.
        success_speed: joint speed below which a reached target counts as a success.
        via_points: number ``V`` of via-points to pass, in order, before the target (module docstring).
        via_radius: a via-point is passed within this distance (fraction of the reach).
        termination_penalty: subtracted from the reward of a step that terminates the episode (default
            ``None``: :meth:`termination_cost`).
    """

    name: ClassVar[str] = "ArmReach"

    model: PlanarArm = field(default_factory=_default_arm)
    max_torque: float | tuple[float, ...] = 1.0
    speed_limit: float = 10.0
    target_radius: tuple[float, float] = (0.25, 0.9)
    control_cost: float = 0.01
    obstacles: tuple[tuple[float, float, float], ...] = ()
    obstacle_weight: float = 100.0
    obstacle_margin: float = 0.05
    terminate_on_collision: bool = False
    success_speed: float = 0.5
    termination_penalty: float | None = None
    via_points: int = 0
    via_radius: float = 0.05
    max_episode_steps: int = 100

    def __post_init__(self) -> None:
        k = self.model.links
        if isinstance(self.max_torque, (tuple, list)) and len(self.max_torque) != k:
            raise ValueError(f"ArmReach: 'max_torque' has {len(self.max_torque)} values for {k} links")
        r0, r1 = self.target_radius
        if not 0.0 <= r0 <= r1 <= 1.0:
            raise ValueError(f"ArmReach: 'target_radius' must be 0 <= r_min <= r_max <= 1, got {(r0, r1)}")
        obs = tuple(tuple(float(v) for v in o) for o in self.obstacles)
        if any(len(o) != 3 or o[2] <= 0 for o in obs):
            raise ValueError("ArmReach: 'obstacles' must be circles (cx, cy, r) with r > 0")
        object.__setattr__(self, "obstacles", obs)
        V = self.via_points
        if isinstance(V, bool) or not isinstance(V, int) or V < 0:
            raise ValueError(f"ArmReach: 'via_points' must be a non-negative int, got {V!r}")
        if not 0.0 < self.via_radius < 1.0:
            raise ValueError(f"ArmReach: 'via_radius' must be in (0, 1) (a fraction of the reach), "
                             f"got {self.via_radius!r}")
        system = (ArmWaypoints(self.model, 2 * V + 3, V, self.via_radius * self.model.reach) if V
                  else WithConstants(self.model, 2))
        object.__setattr__(self, "_system", system)

    # --- sizes ------------------------------------------------------------------------------------------
    @property
    def links(self) -> int:
        return self.model.links

    @property
    def obs_dim(self) -> int:  # type: ignore[override]
        return 3 * self.links + 4 + (2 * self.via_points + 5 if self.via_points else 0)

    @property
    def n_noise(self) -> int:  # type: ignore[override]
        return self.links + 2 + 2 * self.via_points

    @property
    def system(self) -> WithConstants:
        return self._system

    @property
    def reach(self) -> float:
        return self.model.reach

    def u_max(self) -> tuple[float, ...]:
        t = self.max_torque
        return tuple(float(v) for v in t) if isinstance(t, (tuple, list)) else (float(t),) * self.links

    # --- bounds -----------------------------------------------------------------------------------------
    def _acc_bound(self) -> float:
        """A bound on ``|q̈|₂`` over every state with ``|q̇_j| ≤ speed_limit`` and every allowed torque.

        ``q̇ᵀ M q̇ = Σ_i m_i |ṗ_i|²`` and ``l_i |φ̇_i| = |ṗ_i - ṗ_{i-1}|`` give ``Σ l_i² φ̇_i² ≤ 4 Σ |ṗ_i|²``;
        with ``|φ̇| = |Sᵀ q̇| ≥ |q̇|/2`` (``‖S⁻ᵀ‖ ≤ 2``), ``λ_min(M) ≥ m_min l_min² / 16``.  The right-hand
        side ``τ - b q̇ - S (P φ̇² + G)`` is bounded term by term (``|φ̇_j| ≤ k v``, ``|P_jk| ≤ l_max² Σm``,
        ``‖S‖₂ ≤ ‖S‖_F``)."""
        md, k, v = self.model, self.links, self.speed_limit
        m_min, l_min = lo(md.masses), lo(md.lengths)
        l_max, b_max, g = hi(md.lengths), hi(md.damping), abs(hi(md.gravity))
        m_tot = k * hi(md.masses)
        rk = math.sqrt(k)
        tau = rk * max(self.u_max())
        coriolis = rk * k * (l_max * l_max * m_tot) * (k * v) ** 2
        grav = rk * g * m_tot * l_max
        rhs = tau + rk * b_max * v + math.sqrt(k * (k + 1) / 2) * (coriolis + grav)
        return 16.0 * rhs / (m_min * l_min * l_min)

    def obs_high(self) -> np.ndarray:
        # Every step starts with |q̇_j| ≤ speed_limit (else the episode has ended; the initial state is at
        # rest), so one semi-implicit Euler step ends with |q̇_j| ≤ speed_limit + dt · max|q̈|.  |target|
        # ≤ r_max · reach and |ee| ≤ reach.
        k, R = self.links, self.reach
        qd = self.speed_limit + hi(self.model.dt) * self._acc_bound()
        high = [1.0] * (2 * k) + [qd] * k + [R, R, 2 * R, 2 * R]
        if self.via_points:  # via-points and w_j lie in the target annulus; j ≤ V
            high += [R] * (2 * self.via_points) + [R, R, 2 * R, 2 * R, float(self.via_points)]
        return np.array(high)

    def max_step_cost(self) -> float:
        """An upper bound of the per-step cost ``-r`` (``|ee - target| ≤ 2 reach``, ``|a_j| ≤ 1``, a
        penetration depth at most the obstacle's radius)."""
        k, R = self.links, self.reach
        pen = self.obstacle_weight * k * sum(o[2] ** 2 for o in self.obstacles)
        # the distance to go: at most 2R to the next waypoint plus 2R per remaining leg
        return (2 * R * (self.via_points + 1)) ** 2 + self.control_cost * k + pen

    def termination_cost(self) -> float:
        """The reward penalty of a terminating step: ``termination_penalty``, or by default
        ``1000 · max_step_cost()`` (ending early never pays in an episode of up to 1000 steps)."""
        if self.termination_penalty is not None:
            return float(self.termination_penalty)
        return 1000.0 * self.max_step_cost()

    # --- state ------------------------------------------------------------------------------------------
    def initial_state(self, noise: Tensor) -> Tensor:
        k = self.links
        q = (2 * noise[..., :k] - 1) * math.pi
        r0, r1 = (f * self.reach for f in self.target_radius)

        def annulus(i: int) -> Tensor:  # a point from the uniforms k+i, k+i+1
            rho = torch.sqrt(r0 * r0 + (r1 * r1 - r0 * r0) * noise[..., k + i])
            ang = (2 * noise[..., k + i + 1] - 1) * math.pi
            return torch.stack([rho * torch.cos(ang), rho * torch.sin(ang)], -1)

        parts = [q, torch.zeros_like(q), annulus(0)]
        if self.via_points:
            vias = [annulus(2 + 2 * i) for i in range(self.via_points)]
            parts += vias + [noise.new_zeros(*q.shape[:-1], 1)]
        return torch.cat(parts, -1)

    def _split(self, x: Tensor):
        k = self.links
        return x[..., :k], x[..., k:2 * k], x[..., 2 * k:2 * k + 2]

    def end_effector(self, x: Tensor) -> Tensor:
        return self.model.end_effector(x[..., :self.links])

    def step(self, x: Tensor, u: Tensor) -> Tensor:
        """The system's step, then (with via-points) the via-point event (module docstring)."""
        y = self.system.step(x, u, 0)
        return self.system.advance(y) if self.via_points else y

    def observe(self, x: Tensor) -> Tensor:
        q, v, tgt = self._split(x)
        ee = self.model.end_effector(q)
        parts = [torch.cos(q), torch.sin(q), v, tgt, ee - tgt]
        if self.via_points:
            w = self.system.current(x)
            parts += [x[..., 2 * self.links + 2:-1], w, ee - w, x[..., -1:]]
        return torch.cat(parts, -1)

    def state_from_obs(self, obs: Tensor) -> Tensor:
        k, V = self.links, self.via_points
        q = torch.atan2(obs[..., k:2 * k], obs[..., :k])
        parts = [q, obs[..., 2 * k:3 * k + 2]]
        if V:
            parts += [obs[..., 3 * k + 4:3 * k + 4 + 2 * V], obs[..., -1:]]
        return torch.cat(parts, -1)

    def distance_to_go(self, x: Tensor) -> Tensor:
        """``|ee − w_j| + Σ`` remaining leg lengths ``(*B,)`` (module docstring); with ``via_points = 0`` the
        distance to the target."""
        q, _, tgt = self._split(x)
        ee = self.model.end_effector(q)
        if not self.via_points:
            return torch.linalg.vector_norm(ee - tgt, dim=-1)
        pts, j = self.system.waypoints(x)
        e = ee - self.system.current(x)
        legs = torch.linalg.vector_norm(pts[..., 1:, :] - pts[..., :-1, :], dim=-1)  # (*B, V)
        remaining = (legs * (torch.arange(self.via_points, device=x.device) >= j[..., None])).sum(-1)
        return torch.linalg.vector_norm(e, dim=-1) + remaining

    # --- obstacles --------------------------------------------------------------------------------------
    def penetration(self, x: Tensor, margin: float = 0.0) -> Tensor:
        """Depth ``(*B, n_obstacles, k)`` of each link segment inside each obstacle grown by ``margin``
        (0 outside)."""
        pts = self.model.fk(x[..., :self.links])
        if not self.obstacles:
            return pts.new_zeros(*pts.shape[:-2], 0, self.links)
        ob = torch.tensor(self.obstacles, dtype=x.dtype, device=x.device)
        c, r = ob[:, None, :2], ob[:, 2:3]  # (O, 1, 2), (O, 1)
        a, d = pts[..., None, :-1, :], (pts[..., 1:, :] - pts[..., :-1, :])[..., None, :, :]
        t = (((c - a) * d).sum(-1) / (d * d).sum(-1)).clamp(0.0, 1.0)
        gap = a + t[..., None] * d - c
        dist = torch.sqrt((gap * gap).sum(-1) + 1e-12)  # smooth at 0 (for the MPC cost's derivatives)
        return torch.relu(r + margin - dist)

    def collisions(self, x: Tensor) -> Tensor:
        """Number ``(*B,)`` of (link, obstacle) pairs in contact: the constraint violations of a state."""
        return (self.penetration(x) > 0).sum((-1, -2))

    # --- reward and flags -------------------------------------------------------------------------------
    def _step_cost(self, x_next: Tensor, u: Tensor) -> Tensor:
        q, _, tgt = self._split(x_next)
        a = u / self.u_scale(u.dtype, u.device)
        if self.via_points:
            track = self.distance_to_go(x_next).square()
        else:
            e = self.model.end_effector(q) - tgt
            track = (e * e).sum(-1)
        cost = track + self.control_cost * (a * a).sum(-1)
        if self.obstacles:
            pen = self.penetration(x_next)
            cost = cost + self.obstacle_weight * (pen * pen).sum((-1, -2))
        return cost

    def reward(self, x: Tensor, u: Tensor, x_next: Tensor) -> Tensor:
        r = -self._step_cost(x_next, u)
        return r - self.termination_cost() * self.terminated(x_next).to(r.dtype)

    def terminated(self, x: Tensor) -> Tensor:
        """A joint faster than ``speed_limit``, or (``terminate_on_collision``) a link in an obstacle."""
        _, v, _ = self._split(x)
        term = (v.abs() > self.speed_limit).any(-1)
        if self.terminate_on_collision and self.obstacles:
            term = term | (self.collisions(x) > 0)
        return term

    def error(self, x: Tensor) -> Tensor:
        """The distance to the target (with via-points: the distance to go, module docstring)."""
        if self.via_points:
            return self.distance_to_go(x)
        q, _, tgt = self._split(x)
        return torch.linalg.vector_norm(self.model.end_effector(q) - tgt, dim=-1)

    def success(self, x: Tensor) -> Tensor:
        _, v, _ = self._split(x)
        ok = (self.error(x) < 0.05 * self.reach) & (v.abs() < self.success_speed).all(-1)
        if self.via_points:
            ok = ok & (x[..., -1] >= self.via_points - 0.5)
        return ok

    # --- MPC --------------------------------------------------------------------------------------------
    def mpc_cost(self, horizon: int, *, dtype=torch.float64, device=None):
        """A :class:`controllers.costs.ResidualCost` on ``[ee - target, q̇, pen]`` (the target read from
        the state, so one cost serves every environment; ``pen`` the penetrations into the obstacles grown by
        ``obstacle_margin · reach``), weights ``diag(1, 1, 0.01…, w_o…)`` per step and
        ``diag(10, 10, 1…, w_o…)`` at the end, control weight ``c_u / τ_max²`` (physical torques).  With
        via-points the first residual is ``ee − w_j`` (the next waypoint) instead of ``ee − target``."""
        from controllers.costs import ResidualCost

        kw = dict(dtype=dtype, device=device)
        k, n_obs = self.links, len(self.obstacles) * self.links

        V = self.via_points

        def residual(x: Tensor) -> Tensor:
            q, v, tgt = self._split(x)
            parts = [self.model.end_effector(q) - (self.system.current(x) if V else tgt), v]
            if n_obs:
                parts.append(self.penetration(x, self.obstacle_margin * self.reach).flatten(-2))
            return torch.cat(parts, -1)

        run = torch.tensor([1.0, 1.0] + [0.01] * k + [self.obstacle_weight] * n_obs, **kw)
        end = torch.tensor([10.0, 10.0] + [1.0] * k + [self.obstacle_weight] * n_obs, **kw)
        Q = torch.diag_embed(torch.cat([run.expand(horizon, -1), end[None]], 0))
        R = torch.diag(self.control_cost / torch.tensor(self.u_max(), **kw) ** 2)
        return ResidualCost(residual=residual, Q=Q, R=R)

    # --- rendering --------------------------------------------------------------------------------------
    def frame(self, x: np.ndarray, size: int = 256) -> np.ndarray:
        R = self.reach
        cv = Canvas(size, extent=1.1 * R + 0.05)
        for cx, cy, r in self.obstacles:
            cv.disc((cx, cy), r, (170, 170, 170))
        xt = torch.as_tensor(np.asarray(x, dtype=np.float64))
        tgt = (float(xt[2 * self.links]), float(xt[2 * self.links + 1]))
        cv.disc(tgt, 0.05 * R, (60, 170, 60))
        if self.via_points:  # passed ones grey, the next orange, the later ones light orange
            pts, j = self.system.waypoints(xt[None])
            for i in range(self.via_points):
                color = (150, 150, 150) if i < int(j[0]) else ((230, 140, 30) if i == int(j[0])
                                                                else (245, 200, 150))
                cv.disc(pts[0, i].tolist(), self.via_radius * R, color)
        lv = torch.as_tensor(self.model.lengths).detach().to(torch.float64).reshape(-1)
        lv = lv.expand(self.links) if lv.numel() == 1 else lv.reshape(-1, self.links)[0]  # a batch: the first
        pts = PlanarArm(links=self.links, lengths=tuple(lv.tolist())).fk(xt[None, :self.links])[0].numpy()
        w = 0.04 * R
        for i in range(self.links):
            cv.segment(pts[i], pts[i + 1], w, (204, 77, 77))
            cv.disc(pts[i], 0.8 * w, (0, 0, 0))
        cv.disc(pts[-1], w, (150, 40, 40))
        return cv.img
