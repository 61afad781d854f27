"""SE(3) end-effector reaching with a velocity-controlled Franka Panda (:class:`controllers.systems.Panda`).

The arm must bring its flange to a goal *pose* (position and orientation) and hold it.  The controls are
joint velocities held for one step, ``q⁺ = clip(q + Δt q̇, q_min, q_max)`` (:class:`PandaVelocity`, the
integrator of :func:`controllers.ik.resolved_rate_step`); the pose is the forward kinematics of ``q``
(pytorch-kinematics on the shipped URDF).  The goal pose rides in the state as constants
(:class:`~learning.envs.arm.WithConstants`), so one observation, reward and expert serve every
environment: ``x = [q (7), p* (3), vec R* (9, row-major)]``, ``n = 19``.

* Action: normalized joint velocities, ``q̇ = a · q̇_max`` (Franka's published limits).
* Observation ``[q, p* − p, log(Rᵀ R*), p*, vec R*]`` (25): the joint angles, the position error in the
  base frame, the rotation error in the flange frame (a rotation vector, ``‖·‖ ≤ π``) and the goal.
* Reward ``−(‖p* − p‖ + 0.1 θ) − 0.01 ‖a‖²/7`` on the state after the step (``θ`` the rotation error
  angle, rad); no termination (joint limits clip the motion, nothing can crash).
* Success at the end of the episode: ``‖p* − p‖ < 1 cm`` and ``θ < 0.05`` rad; error ``‖p* − p‖`` (m).
* Initial state: the start and the goal configuration each uniform in ``±spread`` rad per joint around
  Franka's "ready" pose (clipped to the limits); the goal pose is the flange pose of the goal
  configuration, so every goal is reachable (IK is not needed, and not given).

:class:`PandaReachExpert` solves it with the SE(3) error-state MPC over body twists
(:class:`controllers.pose_mpc.PoseMPC`, ``frame="se3"``: seed 003 Algorithm 1 on SE(3)) towards the goal
pose, under Panda-sized twist bounds (:func:`~controllers.pose_mpc.twist_box`), and turns the first twist
into joint velocities by damped least squares with joint-limit avoidance in the null space
(:func:`controllers.ik.resolved_rate_step`).  The MPC's model (a free pose) is not the arm: DLS damping,
velocity saturation and the Jacobian changing within a step are model error the feedback absorbs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
import torch
from torch import Tensor

from controllers.systems.panda import PANDA_DH, Panda
from learning.envs._canvas import Canvas
from learning.envs.arm import WithConstants
from learning.envs.task import ErrorStateExpert, Task

__all__ = ["PandaVelocity", "PandaReach", "PandaReachExpert"]


@dataclass(frozen=True, eq=False)
class PandaVelocity:
    """The Panda as a joint-velocity integrator: ``q⁺ = clip(q + Δt q̇, q_min, q_max)`` (``n = m = 7``)."""

    dt: float = 0.05
    robot: Panda = field(default_factory=Panda)

    n: ClassVar[int] = 7
    m: ClassVar[int] = 7
    time_invariant: ClassVar[bool] = True

    def step(self, q: Tensor, qd: Tensor, t: int = 0) -> Tensor:
        lo, hi = self.robot.joint_limits(q.dtype, q.device)
        return torch.minimum(torch.maximum(q + self.dt * qd, lo), hi)


def _reach_bound() -> float:
    """An upper bound of ‖p‖ for the flange: the sum of the DH links' offset lengths (triangle inequality)."""
    return sum(math.hypot(a, d) for a, d, _ in PANDA_DH)


@dataclass(frozen=True, eq=False)
class PandaReach(Task):
    """Reach a goal pose with the flange and hold it (module docstring).

    Attributes:
        dt: control period (s).
        spread: half-width (rad) of the start and goal configurations around the ready pose.
        control_cost: weight of ``‖a‖²/7`` in the reward.
        position_tolerance, angle_tolerance: the success thresholds (m, rad).
    """

    name: ClassVar[str] = "PandaReach"
    obs_dim: ClassVar[int] = 25
    n_noise: ClassVar[int] = 14

    dt: float = 0.05
    spread: float = 0.6
    control_cost: float = 0.01
    position_tolerance: float = 0.01
    angle_tolerance: float = 0.05
    max_episode_steps: int = 100

    def __post_init__(self):
        for name in ("dt", "spread", "position_tolerance", "angle_tolerance"):
            if not float(getattr(self, name)) > 0:
                raise ValueError(f"PandaReach: argument '{name}' must be positive, "
                                 f"got {getattr(self, name)!r}")
        object.__setattr__(self, "_system", WithConstants(PandaVelocity(self.dt), 12))

    @property
    def system(self) -> WithConstants:
        return self._system

    @property
    def robot(self) -> Panda:
        return self._system.base.robot

    def u_max(self) -> tuple[float, ...]:
        return tuple(float(v) for v in Panda.velocity_limits(torch.float64))

    def goal(self, x: Tensor) -> Tensor:
        """The goal poses ``(*B, 4, 4)`` of states ``x``."""
        R = x[..., 10:19].unflatten(-1, (3, 3))
        top = torch.cat([R, x[..., 7:10, None]], -1)
        bottom = torch.zeros_like(top[..., :1, :])
        bottom[..., 0, 3] = 1.0
        return torch.cat([top, bottom], -2)

    def errors(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """``(p* − p (*B, 3), log(Rᵀ R*) (*B, 3))`` of states ``x``."""
        from torchlie import so3

        T = self.robot.fk(x[..., :7])
        R_goal = x[..., 10:19].unflatten(-1, (3, 3))
        return x[..., 7:10] - T[..., :3, 3], so3.log(T[..., :3, :3].transpose(-1, -2) @ R_goal)

    def obs_high(self) -> np.ndarray:
        # q within the joint limits (the step clips); |p|, |p*| ≤ the reach bound, so |p* − p| ≤ twice it;
        # a rotation vector from log has norm ≤ π; rotation entries ≤ 1.
        qmax = np.maximum(np.abs(Panda.joint_limits(torch.float64)[0].numpy()),
                          np.abs(Panda.joint_limits(torch.float64)[1].numpy()))
        reach = _reach_bound()
        high = np.concatenate([qmax, [2 * reach] * 3, [math.pi] * 3, [reach] * 3, [1.0] * 9])
        return high * (1.0 + 1e-6)

    def _configuration(self, noise: Tensor) -> Tensor:
        lo, hi = Panda.joint_limits(noise.dtype, noise.device)
        q = Panda.home(noise.dtype, noise.device) + (2 * noise - 1) * self.spread
        return torch.minimum(torch.maximum(q, lo), hi)

    def initial_state(self, noise: Tensor) -> Tensor:
        q = self._configuration(noise[..., :7])
        T = self.robot.fk(self._configuration(noise[..., 7:14]))
        return torch.cat([q, T[..., :3, 3], T[..., :3, :3].flatten(-2)], -1)

    def observe(self, x: Tensor) -> Tensor:
        ep, er = self.errors(x)
        return torch.cat([x[..., :7], ep, er, x[..., 7:19]], -1)

    def state_from_obs(self, obs: Tensor) -> Tensor:
        return torch.cat([obs[..., :7], obs[..., 13:25]], -1)

    def reward(self, x: Tensor, u: Tensor, x_next: Tensor) -> Tensor:
        ep, er = self.errors(x_next)
        a = u / self.u_scale(u.dtype, u.device)
        return -(ep.norm(dim=-1) + 0.1 * er.norm(dim=-1)) - self.control_cost * a.square().mean(-1)

    def error(self, x: Tensor) -> Tensor:
        return self.errors(x)[0].norm(dim=-1)

    def success(self, x: Tensor) -> Tensor:
        ep, er = self.errors(x)
        return (ep.norm(dim=-1) < self.position_tolerance) & (er.norm(dim=-1) < self.angle_tolerance)

    def mpc_cost(self, horizon: int, *, dtype=torch.float64, device=None):
        raise NotImplementedError("PandaReach: its MPC is the SE(3) pose MPC over body twists "
                                  "(PandaReachExpert), not a quadratic cost on the joint state")

    def expert(self, horizon: int | None = None, **kwargs) -> PandaReachExpert:
        return PandaReachExpert(self, horizon, **kwargs)

    def frame(self, x: np.ndarray, size: int = 256) -> np.ndarray:
        """Side view (x forward, z up) of the arm's joint frames, the flange and the goal."""
        chain = self.robot.chain(torch.float64)
        q = torch.as_tensor(np.asarray(x[:7], dtype=np.float64))[None]
        Ts = chain.forward_kinematics_tensor(q)  # every frame of the chain
        pts = Ts[:, 0, :3, 3].numpy()
        cv = Canvas(size, extent=1.2)
        cv.hline(-0.0, (0, 0, 0), 0.02)
        for a, b in zip(pts[:-1], pts[1:]):
            cv.segment((a[0], a[2] - 0.4), (b[0], b[2] - 0.4), 0.05, (60, 90, 160))
        goal = np.asarray(x[7:10], dtype=np.float64)
        Rg = np.asarray(x[10:19], dtype=np.float64).reshape(3, 3)
        g0 = (goal[0], goal[2] - 0.4)
        cv.segment(g0, (g0[0] + 0.15 * Rg[0, 2], g0[1] + 0.15 * Rg[2, 2]), 0.03, (80, 160, 80))
        cv.disc(g0, 0.04, (80, 160, 80))
        cv.disc((pts[-1][0], pts[-1][2] - 0.4), 0.035, (204, 77, 77))
        return cv.img


class PandaReachExpert(ErrorStateExpert):
    """SE(3) pose MPC + resolved-rate control on :class:`PandaReach` (module docstring); a
    :class:`learning.policies.Policy`.  The goal is held as the reference over the horizon (zero reference
    twists); the QP is warm-started with the previous plan; the solve follows the observation's dtype.

    Args:
        horizon: MPC steps of the task's ``dt`` (default 10).
        q_p, q_r: position and rotation error weights; ``r``: twist weight; the terminal weight is
            ``terminal`` times the stage weight.
        v_max, w_max: end-effector speed bounds (m/s, rad/s), enforced as :func:`twist_box`.
        damping: of the DLS step (:func:`controllers.ik.resolved_rate_step`).
    """

    def __init__(self, task: PandaReach, horizon: int | None = None, *, q_p: float = 10.0, q_r: float = 3.0,
                 r: float = 0.1, terminal: float = 10.0, v_max: float = 0.8, w_max: float = 2.0,
                 damping: float = 1e-2):
        super().__init__()
        self.task, self.horizon = task, int(horizon or 10)
        self.params = dict(q_p=q_p, q_r=q_r, r=r, terminal=terminal, v_max=v_max, w_max=w_max)
        self.damping = damping
        self._mpcs: dict = {}

    def _mpc(self, dtype, device):
        from controllers.pose_mpc import PoseMPC, twist_box

        key = (dtype, device)
        if key not in self._mpcs:
            p, kw = self.params, dict(dtype=dtype, device=device)
            Q = torch.tensor([p["q_p"]] * 3 + [p["q_r"]] * 3, **kw)
            R = torch.full((6,), p["r"], **kw)
            lo, hi = twist_box(p["v_max"], p["w_max"], **kw)
            self._mpcs[key] = PoseMPC("se3", self.horizon, self.task.dt, Q, R, p["terminal"] * Q, u_lower=lo,
                                      u_upper=hi, grad="none")
        return self._mpcs[key]

    @torch.no_grad()
    def act(self, obs: Tensor) -> Tensor:
        from controllers.ik import resolved_rate_step

        task, H = self.task, self.horizon
        x = task.state_from_obs(obs)
        q = x[..., :7]
        X = task.robot.fk(q)
        goal = task.goal(x)
        X_ref = goal[:, None].expand(-1, H + 1, 4, 4)
        T_ref = obs.new_zeros(obs.shape[0], H, 6)
        sol = self._mpc(obs.dtype, obs.device).solve(X, X_ref, T_ref, warm=self._warm_start(T_ref))
        self._remember(sol, obs.device)
        _, qd = resolved_rate_step(task.robot, q, sol.u, task.dt, frame="body", damping=self.damping)
        return qd / task.u_scale(obs.dtype, obs.device)
