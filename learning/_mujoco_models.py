"""Models of three gymnasium MuJoCo envs for a model-based MPC: :func:`inverted_pendulum_model`,
:func:`inverted_double_pendulum_model`, :func:`reacher_model`.

Each :class:`~learning.env_models.EnvModel` plans on the env's own ``MjModel`` (a
:class:`~controllers.systems.mujoco_system.MujocoSystem` built from the env, or from ``gym.make(id)``:
``step`` is ``env.step`` to round-off, the Jacobians are central finite differences), with the solver's
tolerances from :meth:`MujocoSystem.ilqr_options` (no tighter than the FD Jacobians allow) and an exact map
from the env's observation to the state ``x = [qpos, qvel]``.  One setting is tightened: the negligible-step
test ``tol`` (absolute, ``tol (1 + ‖u‖∞)``) is ``1e-11``: at a balanced or reached state the controls are
~1e-3 and the default ``1e-8`` stopped iLQR before the (relative) KKT certificate held — measured on
InvertedPendulum, 94 % of the solves ``STALLED`` at a residual ratio 1.3e-6 (tolerance 1e-6), none with
``1e-11``.  The certificate's own tolerance ``tol_kkt`` stays what the FD Jacobians allow.

**InvertedPendulum-v5** (``x = [cart, angle, cart vel, angle vel]`` = the observation; ``a ∈ [-3, 3]``).
The reward is ``+1`` a step while ``|angle| ≤ 0.2`` (else the episode terminates): an indicator, no
gradient.  Planning cost: ``Σ_t x_tᵀ Q x_t + r u_t²`` about the upright, centred rest state,
``Q = diag(1, 10, 0.1, 0.1)`` (the angle first: it terminates; the cart: the rail ends at ``±1``),
``r = 0.01``, the last state's term ``terminal`` times (a value-to-go stand-in).

**InvertedDoublePendulum-v5** (``x = [cart, θ₁, θ₂, v₀, v₁, v₂]``; ``a ∈ [-1, 1]``).  The observation is
``[cart, sin θ₁, sin θ₂, cos θ₁, cos θ₂, clip(qvel, ±10), clip(qfrc_constraint[0], ±10)]``; the state is
``θ_i = atan2(sin θ_i, cos θ_i)`` and the velocities — exact (to round-off) while ``|θ_i| < π`` and
``|v_i| < 10`` (the env terminates long before either: the tip falls below 1 m at ``|θ| ≈ 0.6``); the
constraint force is an output of the state, not part of it.  The reward after a step is
``10·alive − (0.01 x_tip² + (y_tip − 2)²) − (1e-3 v₁² + 5e-3 v₂²)``, the episode terminating when
``y_tip ≤ 1``, with the tip (site ``tip``) at ``x_tip = cart + l₁ sin θ₁ + l₂ sin(θ₁+θ₂)``,
``y_tip = z₀ + l₁ cos θ₁ + l₂ cos(θ₁+θ₂)`` (lengths and offset read from the ``MjModel``).  Planning cost
(:class:`IDPCost`; exact gradient and Hessian by autograd)::

    J = Σ_{t=1}^{T} w_t [0.01 x_tip² + (y_tip − 2)² + 1e-3 v₁² + 5e-3 v₂²         (the reward's penalties)
                         + w_b (s softplus((y_min − y_tip) / s))² + c_x cart² + c_v v₀²]
        + r Σ_{t<T} u_t² + x_Tᵀ P x_T,          w_t = 1 (t < T), terminal (t = T)

— the reward's penalties exactly, on the states it pays them on (after each step, ``x_1 .. x_T``).  What
differs, and why: the alive bonus and the termination become the barrier on the tip height (``y_min =
1.05``, ``s = 0.02``, ``w_b = 1000``: quadratic in the shortfall below ``y_min``, nothing above it); a small
control cost ``r = 1e-3`` (the reward has none; it keeps ``Q_uu`` definite); cart terms ``c_x = c_v = 0.1``
(the rail ends at ``±1``: measured, the reward's ``0.01 x_tip²`` let seed 0 drift at 0.5 m/s into the rail's
end and fall); and ``P``, the infinite-horizon LQR cost-to-go of the cost's quadratic expansion at the upright
rest state on the system linearized there (a discrete Riccati equation, solved once per model): a short
horizon then plans as if it went on (measured: horizon 10 without ``P``, the cart terms made the pendulum
lean and fall on seeds 0 and 5; with it both earn 935.6 and 935.8 of 936.0 in 100 steps).  A Gauss-Newton
Hessian would miss the curvature of ``(y_tip − 2)²`` at the upright state, where ``∇y_tip = 0`` and all of it
is ``2 (y_tip − 2) ∇²y_tip``: iLQR then crawls (50 iterations not converged, against 14 exact).

**Reacher-v5** (``x = [θ₀, θ₁, g_x, g_y, ω₀, ω₁, 0, 0]``: the arm's hinges, the target's two slide joints
(which never move) and their velocities; ``a ∈ [-1, 1]²``).  The observation is ``[cos θ, sin θ,
qpos[2:4], qvel[:2], (fingertip − target)_{xy}]``; the map takes ``θ_i = atan2`` (``θ₀`` is unlimited, so it
is recovered modulo ``2π`` — the dynamics and the reward are ``2π``-periodic in it; ``θ₁`` is limited to
``±3``), the target from ``qpos[2:4]`` and zero target velocities.  The reward after a step is
``−w_d ‖p_tip − p_target‖ − w_c ‖a‖²`` with v5's weights ``w_d = w_c = 1``; the fingertip is
``p_tip = l₁ (cos θ₀, sin θ₀) + l₂ (cos(θ₀+θ₁), sin(θ₀+θ₁))`` about the base, the target
``p_target = p_body + (qpos[2:4] − qpos0[2:4])`` (lengths, offsets and ``qpos0`` read from the ``MjModel``;
both bodies at the same height).  Planning cost (:class:`ReacherCost`)::

    J = Σ_{t<T} w_c ‖u_t‖² + Σ_{t=1}^{T} w_t w_d (√(‖p_tip(x_t) − p_target(x_t)‖² + δ²) − δ)

— the reward exactly but for the distance, smoothed over ``δ = 0.005`` (at most ``δ`` a step below the true
distance: the norm has no derivative at zero, where a reaching plan ends); the last state's term can be
weighted (``terminal``, default 1: measured, 5 and 20 changed a return by at most 0.25).

The MPC knows the model (the env's own ``MjModel``) and the reward's terms; an RL agent knows neither.

**Planner defaults and measurements** (``learning.evaluate(ModelMPC(model), id, seeds=range(10),
num_envs=10, timing_steps=50)``, 2-core CPU shared with other jobs, ``OMP_NUM_THREADS=1``; float64; ms =
median per MPC step at batch 10 / batch 1, eager sweeps)::

    env                        horizon iterations      multistart return (mean ± std) ms b10 / b1 uncertified
    InvertedPendulum-v5        15      2               False      1000 ± 0 (all 1000)  221 / 56    0 %
    InvertedDoublePendulum-v5   6      4               False      9359.91 ± 0.09       304 / 145   0.08 %
    Reacher-v5                 20      4 first, then 1 "start"    -3.42 ± 1.42         197 / 69    61 %

The time is MuJoCo's: an RK4 step costs ~15 µs here, and one iLQR iteration takes ``2 (n + m) T`` rollout
steps for central-difference Jacobians (``n + m + 1`` forward) plus ``line_search_steps · T`` for the line
search, each ``frame_skip`` MuJoCo steps, per element and guess (InvertedPendulum at batch 10: 3.3 s of
4.5 s in ``mujoco.rollout``).  On Reacher the multi-start's extra guesses help where the target is behind
the arm (seed 1: −4.72 against −6.19 from the previous plan alone), but only at an episode's first step:
Reacher plans in real time — the multi-start with 4 iterations at the first step, then one iteration a
step from the shifted plan (``multistart="start"``, ``start_iter=4``, ``max_iter=1``) on forward-difference
Jacobians (``fd_scheme="forward"``) — and scores what the full multi-start with 4 iterations every step did
(−3.42 ± 1.42, the same to 0.01 on every seed) at 69 ms a step instead of 879 (5713 at batch 10).  A plan
after one iteration is rarely certified (61 % not; the certificate's tolerance, 3e-5, follows the forward
differences' accuracy): its first control is what the real-time scheme acts on.  With
``ModelMPC(..., compile=True)`` the backward passes are compiled programs (built once, minutes, cached on
disk): 20.6 ms a step at batch 1 (``liecontrol bench gym --envs Reacher-v5 --policies ilqr --batch 1
--compile``; docs/gym_envs.md).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

__all__ = ["inverted_pendulum_model", "inverted_double_pendulum_model", "reacher_model", "ReacherCost",
           "IDPCost", "ip_state", "idp_state", "reacher_state", "idp_tip", "reacher_fingertip",
           "INVERTED_PENDULUM", "INVERTED_DOUBLE_PENDULUM", "REACHER"]

INVERTED_PENDULUM = "InvertedPendulum-v5"
INVERTED_DOUBLE_PENDULUM = "InvertedDoublePendulum-v5"
REACHER = "Reacher-v5"


# ------------------------------------------------------------------------------------------------ helpers


def _system(env: Any, env_id: str, **kw: Any):
    """``(MujocoSystem, single env)`` of ``env`` (an ``Env``, a ``VectorEnv`` of copies, or ``None``: a new
    ``gym.make(env_id)``); ``kw``: of :meth:`MujocoSystem.from_env`."""
    import gymnasium as gym

    from controllers.systems.mujoco_system import MujocoSystem

    single = env
    if isinstance(env, gym.vector.VectorEnv):
        envs = getattr(env, "envs", None)  # a SyncVectorEnv holds its sub-envs; an async one does not
        single = envs[0] if envs else None
    if single is None:
        single = gym.make(env_id)
    return MujocoSystem.from_env(single, **kw), single


def _options(system, options: dict[str, Any] | None, **defaults) -> dict[str, Any]:
    """``ILQROptions`` overrides (a dict for :class:`EnvModel`): the system's FD-aware settings, ``defaults``,
    then the caller's ``options``."""
    opts = dataclasses.asdict(system.ilqr_options(**{**defaults, **(options or {})}))
    opts.pop("max_iter")
    return opts


def _check_obs(obs: Any, k: int, who: str) -> None:
    if not isinstance(obs, Tensor) or not obs.is_floating_point():
        raise TypeError(f"{who}: argument 'obs' must be a floating tensor (N, {k}), got "
                        f"{obs.dtype if isinstance(obs, Tensor) else type(obs).__name__}")
    if obs.dim() < 1 or obs.shape[-1] != k:
        raise ValueError(f"{who}: argument 'obs' must have shape (*B, {k}), got {tuple(obs.shape)}")


def _body(mm, name: str) -> int:
    import mujoco

    i = mujoco.mj_name2id(mm, mujoco.mjtObj.mjOBJ_BODY, name)
    if i < 0:
        raise ValueError(f"the MuJoCo model has no body {name!r} (not the gymnasium XML?)")
    return int(i)


# ---------------------------------------------------------------------------------- InvertedPendulum-v5


def ip_state(obs: Tensor) -> Tensor:
    """InvertedPendulum-v5: the observation ``[qpos, qvel]`` is the state, ``(*B, 4) -> (*B, 4)``."""
    _check_obs(obs, 4, "ip_state")
    return obs


def inverted_pendulum_model(env: Any = None, *, horizon: int = 15, max_iter: int = 2,
                            terminal: float = 10.0, line_search_steps: int = 4,
        options: dict[str, Any] | None = None):
    """The :class:`~learning.env_models.EnvModel` of ``InvertedPendulum-v5`` (module docstring)."""
    from controllers.costs import QuadraticCost
    from learning.env_models import EnvModel

    system, _ = _system(env, INVERTED_PENDULUM)

    def cost(h: int, dtype=torch.float64, device=None):
        kw = dict(dtype=dtype, device=device)
        Q = torch.diag(torch.tensor([1.0, 10.0, 0.1, 0.1], **kw)).expand(h + 1, 4, 4).clone()
        Q[-1] *= terminal
        return QuadraticCost(Q=Q, R=torch.tensor([[0.01]], **kw), x_ref=torch.zeros(4, **kw))

    return EnvModel(
        env_id=INVERTED_PENDULUM, system=system, cost=cost, state_from_obs=ip_state,
        action_low=(-3.0,), action_high=(3.0,), obs_dim=4, horizon=horizon,
        max_iter=max_iter, random_starts=0,
        multistart=False,  # one start is enough at a trim point (4.6x faster, the same 1000)
        options=_options(system, options, line_search_steps=line_search_steps, tol=1e-11),
        knows="the env's MjModel (dynamics, FD Jacobians); a quadratic cost about the upright state in place "
              "of the +1-while-|angle|<=0.2 reward")


# ---------------------------------------------------------------------------- InvertedDoublePendulum-v5


def idp_state(obs: Tensor) -> Tensor:
    """InvertedDoublePendulum-v5: ``[cart, sin θ₁, sin θ₂, cos θ₁, cos θ₂, v (3), f_c] (*B, 9)`` to
    ``[cart, θ₁, θ₂, v] (*B, 6)`` (exact while ``|θ| < π``, ``|v| < 10``: module docstring)."""
    _check_obs(obs, 9, "idp_state")
    th = torch.atan2(obs[..., 1:3], obs[..., 3:5])
    return torch.cat([obs[..., :1], th, obs[..., 5:8]], -1)


def _idp_geometry(mm) -> tuple[float, float, float]:
    """``(l₁, l₂, z₀)``: the poles' lengths and the cart's height, from the ``MjModel`` (body and site
    offsets along the poles' z axes)."""
    import mujoco

    b2 = _body(mm, "pole2")
    s = mujoco.mj_name2id(mm, mujoco.mjtObj.mjOBJ_SITE, "tip")
    if s < 0:
        raise ValueError("inverted_double_pendulum_model: the MuJoCo model has no site 'tip'")
    z0 = float(mm.body_pos[_body(mm, "cart")][2] + mm.body_pos[_body(mm, "pole")][2])
    return float(mm.body_pos[b2][2]), float(mm.site_pos[s][2]), z0


def idp_tip(x: Tensor, l1: float = 0.6, l2: float = 0.6, z0: float = 0.0) -> Tensor:
    """The tip's ``(x_tip, y_tip) (*B, 2)`` of states ``x (*B, 6)`` (module docstring)."""
    t1, t12 = x[..., 1], x[..., 1] + x[..., 2]
    return torch.stack([x[..., 0] + l1 * torch.sin(t1) + l2 * torch.sin(t12),
                        z0 + l1 * torch.cos(t1) + l2 * torch.cos(t12)], -1)


@dataclass(frozen=True, eq=False)
class IDPCost:
    """``J = Σ_{t=1}^{T} w_t stage(x_t) + r Σ_{t<T} u_t² + x_Tᵀ P x_T`` (module docstring), ``w_t = 1`` for
    ``0 < t < T``, ``terminal`` at ``T``, 0 at ``t = 0``; ``stage`` = the reward's penalties (:meth:`penalty`)
    ``+ barrier (width softplus((y_min − y_tip) / width))² + cart · cart² + cart_vel · v₀²``; ``P (6, 6)`` the
    terminal cost-to-go (``None``: none); geometry ``l1``, ``l2``, ``z0`` (:func:`idp_tip`).

    ``evaluate(x (*B, T+1, 6), u (*B, T, 1)) -> (*B,)``; no ``derivatives``: iLQR takes the exact gradient
    and Hessian by autograd (:func:`controllers.costs.cost_derivatives`).  (A Gauss-Newton Hessian would
    miss the curvature of ``(y_tip − 2)²`` at the upright state, where ``∇y_tip = 0`` and all of it is
    ``2 (y_tip − 2) ∇²y_tip``: iLQR then crawls.)
    """

    l1: float = 0.6
    l2: float = 0.6
    z0: float = 0.0
    terminal: float = 10.0
    r: float = 1e-3
    y_min: float = 1.05
    barrier: float = 1000.0
    width: float = 0.02
    cart: float = 0.1
    cart_vel: float = 0.1
    P: Tensor | None = None

    def __post_init__(self) -> None:
        if self.P is not None and (not isinstance(self.P, Tensor) or self.P.shape != (6, 6)):
            raise ValueError("IDPCost: field 'P' must be None or a (6, 6) tensor (the terminal cost-to-go)")
        for name in ("l1", "l2", "terminal", "r", "width"):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not v > 0:
                raise ValueError(f"IDPCost: field '{name}' must be a positive number, got {v!r}")
        for name in ("barrier", "cart", "cart_vel"):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not v >= 0:
                raise ValueError(f"IDPCost: field '{name}' must be a number >= 0, got {v!r}")

    def penalty(self, x: Tensor) -> Tensor:
        """The reward's penalties ``0.01 x_tip² + (y_tip − 2)² + 1e-3 v₁² + 5e-3 v₂²`` of ``x (*B, 6)``."""
        tip = idp_tip(x, self.l1, self.l2, self.z0)
        return (0.01 * tip[..., 0] ** 2 + (tip[..., 1] - 2.0) ** 2 + 1e-3 * x[..., 4] ** 2
                + 5e-3 * x[..., 5] ** 2)

    def stage(self, x: Tensor) -> Tensor:
        """The planning cost of states ``x (*B, 6)``: :meth:`penalty`, the barrier and the cart terms."""
        y = idp_tip(x, self.l1, self.l2, self.z0)[..., 1]
        b = self.width * torch.nn.functional.softplus((self.y_min - y) / self.width)
        return (self.penalty(x) + self.barrier * b * b + self.cart * x[..., 0] ** 2
                + self.cart_vel * x[..., 3] ** 2)

    def evaluate(self, x: Tensor, u: Tensor) -> Tensor:
        if x.shape[-1] != 6 or u.shape[-1] != 1 or x.shape[-2] != u.shape[-2] + 1:
            raise ValueError(f"IDPCost.evaluate: expected x (*B, T+1, 6), u (*B, T, 1), got "
                             f"{tuple(x.shape)} and {tuple(u.shape)}")
        w = torch.ones(x.shape[-2], dtype=x.dtype, device=x.device)
        w[0], w[-1] = 0.0, self.terminal
        J = (w * self.stage(x)).sum(-1) + self.r * (u * u).sum((-1, -2))
        if self.P is not None:
            xT = x[..., -1, :]
            J = J + (xT.unsqueeze(-2) @ self.P.to(xT) @ xT.unsqueeze(-1))[..., 0, 0]
        return J


def _dare(A: Tensor, B: Tensor, Q: Tensor, R: Tensor, max_iter: int = 5000, rtol: float = 1e-13) -> Tensor:
    """The stabilizing solution ``P`` of ``P = Q + AᵀPA − AᵀPB (R + BᵀPB)⁻¹ BᵀPA`` (the infinite-horizon LQR
    cost-to-go ``xᵀPx`` of ``Σ xᵀQx + uᵀRu``), by the Riccati recursion from ``P = Q`` until it settles."""
    P = Q
    for _ in range(max_iter):
        BtP = B.mT @ P
        Pn = Q + A.mT @ P @ A - (BtP @ A).mT @ torch.linalg.solve(R + BtP @ B, BtP @ A)
        Pn = 0.5 * (Pn + Pn.mT)
        done = bool((Pn - P).abs().max() <= rtol * Pn.abs().max())
        P = Pn
        if done:
            break
    return P


def _upright_value(system, cost: IDPCost) -> Tensor:
    """``P (6, 6)``: the LQR cost-to-go at the upright rest state of the cost's quadratic expansion there
    (``Q = ½ ∇²stage``, ``R = r``) on the system linearized there (FD Jacobians)."""
    x0 = torch.zeros(1, 6, dtype=torch.float64)
    A, B = system.jacobian(x0, torch.zeros(1, 1, dtype=torch.float64))
    H = torch.autograd.functional.hessian(lambda z: cost.stage(z), x0[0])
    return _dare(A[0], B[0], 0.25 * (H + H.mT), torch.tensor([[cost.r]], dtype=torch.float64))


def inverted_double_pendulum_model(env: Any = None, *, horizon: int = 6, max_iter: int = 4,
                                   terminal: float = 10.0, r: float = 1e-3, y_min: float = 1.05,
                                   barrier: float = 1000.0, width: float = 0.02, cart: float = 0.1,
                                   cart_vel: float = 0.1, value_to_go: bool = True,
                                   line_search_steps: int = 4,
        options: dict[str, Any] | None = None):
    """The :class:`~learning.env_models.EnvModel` of ``InvertedDoublePendulum-v5`` (module docstring)."""
    from learning.env_models import EnvModel

    system, _ = _system(env, INVERTED_DOUBLE_PENDULUM)
    l1, l2, z0 = _idp_geometry(system.model)
    ic = IDPCost(l1=l1, l2=l2, z0=z0, terminal=terminal, r=r, y_min=y_min, barrier=barrier, width=width,
                 cart=cart, cart_vel=cart_vel)
    if value_to_go:
        ic = dataclasses.replace(ic, P=_upright_value(system, ic))

    def cost(h: int, dtype=torch.float64, device=None):
        return ic

    return EnvModel(
        env_id=INVERTED_DOUBLE_PENDULUM, system=system, cost=cost, state_from_obs=idp_state,
        action_low=(-1.0,), action_high=(1.0,), obs_dim=9, horizon=horizon,
        max_iter=max_iter, random_starts=0,
        multistart=False,
        options=_options(system, options, line_search_steps=line_search_steps, tol=1e-11),
        knows="the env's MjModel (dynamics, FD Jacobians) and the reward's penalties; the alive bonus and "
              "the termination become a barrier on the tip height")


# -------------------------------------------------------------------------------------------- Reacher-v5


def reacher_state(obs: Tensor) -> Tensor:
    """Reacher-v5: ``[cos θ (2), sin θ (2), target (2), ω (2), tip − target (2)] (*B, 10)`` to
    ``[θ (2), target (2), ω (2), 0, 0] (*B, 8)`` (module docstring; ``θ₀`` modulo ``2π``)."""
    _check_obs(obs, 10, "reacher_state")
    th = torch.atan2(obs[..., 2:4], obs[..., 0:2])
    return torch.cat([th, obs[..., 4:8], torch.zeros_like(obs[..., :2])], -1)


def reacher_fingertip(x: Tensor, l1: float = 0.1, l2: float = 0.11, base: tuple[float, float] = (0.0, 0.0)
                      ) -> Tensor:
    """The fingertip's ``(x, y) (*B, 2)`` of states ``x (*B, 8)`` (module docstring)."""
    t0, t01 = x[..., 0], x[..., 0] + x[..., 1]
    return torch.stack([base[0] + l1 * torch.cos(t0) + l2 * torch.cos(t01),
                        base[1] + l1 * torch.sin(t0) + l2 * torch.sin(t01)], -1)


@dataclass(frozen=True, eq=False)
class ReacherCost:
    """``J = Σ_{t<T} w_c ‖u_t‖² + Σ_{t=1}^{T} w_t w_d (√(‖d(x_t)‖² + dz² + δ²) − δ)``,
    ``d = p_tip − p_target`` (module docstring), ``w_t = 1`` for ``0 < t < T``, ``terminal`` at ``T``, 0 at
    ``t = 0``.

    ``evaluate(x (*B, T+1, 8), u (*B, T, 2)) -> (*B,)``; :meth:`derivatives` gives the exact gradient and
    the Gauss-Newton Hessian ``Jᵀ ∇²ρ J`` (``J = ∂d/∂x``, ``ρ`` the smoothed norm: positive semidefinite).
    Geometry: ``l1``, ``l2`` (links), ``base`` (the arm's xy), ``target0`` (the target's xy at
    ``qpos[2:4] = qpos0``), ``qpos0`` (the slide joints' reference), ``dz`` (height difference).
    """

    l1: float = 0.1
    l2: float = 0.11
    base: tuple[float, float] = (0.0, 0.0)
    target0: tuple[float, float] = (0.1, -0.1)
    qpos0: tuple[float, float] = (0.1, -0.1)
    dz: float = 0.0
    w_dist: float = 1.0
    w_ctrl: float = 1.0
    smoothing: float = 0.005
    terminal: float = 1.0

    def __post_init__(self) -> None:
        for name in ("l1", "l2", "w_dist", "w_ctrl", "smoothing", "terminal"):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not v > 0:
                raise ValueError(f"ReacherCost: field '{name}' must be a positive number, got {v!r}")

    def _weights(self, x: Tensor) -> Tensor:
        w = torch.ones(x.shape[-2], dtype=x.dtype, device=x.device)
        w[0], w[-1] = 0.0, self.terminal
        return self.w_dist * w

    def offset(self, x: Tensor) -> Tensor:
        """``d = p_tip − p_target (*B, [T,] 2)`` of states ``x (*B, [T,] 8)``."""
        tip = reacher_fingertip(x, self.l1, self.l2, self.base)
        g = torch.stack([self.target0[0] + x[..., 2] - self.qpos0[0],
                         self.target0[1] + x[..., 3] - self.qpos0[1]], -1)
        return tip - g

    def _rho(self, d: Tensor) -> Tensor:
        return torch.sqrt((d * d).sum(-1) + self.dz ** 2 + self.smoothing ** 2)

    def evaluate(self, x: Tensor, u: Tensor) -> Tensor:
        if x.shape[-1] != 8 or u.shape[-1] != 2 or x.shape[-2] != u.shape[-2] + 1:
            raise ValueError(f"ReacherCost.evaluate: expected x (*B, T+1, 8), u (*B, T, 2), got "
                             f"{tuple(x.shape)} and {tuple(u.shape)}")
        dist = (self._rho(self.offset(x)) - self.smoothing) * self._weights(x)
        return dist.sum(-1) + self.w_ctrl * (u * u).sum((-1, -2))

    def derivatives(self, x: Tensor, u: Tensor):
        """``(gx (*B,T+1,8), gu (*B,T,2), Hxx (*B,T+1,8,8), None, Huu (*B,T,2,2))``; Hxx Gauss-Newton."""
        d = self.offset(x)
        rho = self._rho(d)
        w = self._weights(x)
        t0, t01 = x[..., 0], x[..., 0] + x[..., 1]
        s0, c0, s01, c01 = torch.sin(t0), torch.cos(t0), torch.sin(t01), torch.cos(t01)
        J = torch.zeros(*x.shape[:-1], 2, 8, dtype=x.dtype, device=x.device)  # ∂d/∂x
        J[..., 0, 0] = -self.l1 * s0 - self.l2 * s01
        J[..., 1, 0] = self.l1 * c0 + self.l2 * c01
        J[..., 0, 1] = -self.l2 * s01
        J[..., 1, 1] = self.l2 * c01
        J[..., 0, 2] = -1.0
        J[..., 1, 3] = -1.0
        grad_rho = d / rho[..., None]  # ∂ρ/∂d
        gx = w[..., None] * (grad_rho.unsqueeze(-2) @ J).squeeze(-2)
        eye = torch.eye(2, dtype=x.dtype, device=x.device)
        H_rho = (eye - grad_rho[..., :, None] * grad_rho[..., None, :]) / rho[..., None, None]
        Hxx = w[..., None, None] * (J.mT @ H_rho @ J)
        gu = 2 * self.w_ctrl * u
        Huu = (2 * self.w_ctrl * eye).expand(*u.shape[:-1], 2, 2)
        return gx, gu, Hxx, None, Huu


def _reacher_geometry(mm) -> dict[str, Any]:
    """``l1, l2, base, target0, qpos0, dz`` of :class:`ReacherCost` from the ``MjModel``."""
    b0, b1, ft, tg = (_body(mm, n) for n in ("body0", "body1", "fingertip", "target"))
    return dict(l1=float(mm.body_pos[b1][0]), l2=float(mm.body_pos[ft][0]),
                base=(float(mm.body_pos[b0][0]), float(mm.body_pos[b0][1])),
                target0=(float(mm.body_pos[tg][0]), float(mm.body_pos[tg][1])),
                qpos0=(float(mm.qpos0[2]), float(mm.qpos0[3])),
                dz=float(mm.body_pos[b0][2] + mm.body_pos[b1][2] + mm.body_pos[ft][2] - mm.body_pos[tg][2]))


def reacher_model(env: Any = None, *, horizon: int = 20, max_iter: int = 1, start_iter: int = 4,
                  multistart: bool | str = "start", terminal: float = 1.0, smoothing: float = 0.005,
                  line_search_steps: int = 4, fd_scheme: str = "forward",
                  options: dict[str, Any] | None = None):
    """The :class:`~learning.env_models.EnvModel` of ``Reacher-v5`` (module docstring)."""
    from learning.env_models import EnvModel

    system, single = _system(env, REACHER, fd_scheme=fd_scheme)
    inner = getattr(single, "unwrapped", single)
    wd = float(getattr(inner, "_reward_dist_weight", 1.0))
    wc = float(getattr(inner, "_reward_control_weight", 1.0))
    geo = _reacher_geometry(system.model)
    rc = ReacherCost(**geo, w_dist=wd, w_ctrl=wc, smoothing=smoothing, terminal=terminal)

    def cost(h: int, dtype=torch.float64, device=None):
        return rc

    return EnvModel(
        env_id=REACHER, system=system, cost=cost, state_from_obs=reacher_state,
        action_low=(-1.0, -1.0), action_high=(1.0, 1.0), obs_dim=10, horizon=horizon, max_iter=max_iter,
        start_iter=start_iter, multistart=multistart, random_starts=0,
        options=_options(system, options, line_search_steps=line_search_steps, tol=1e-11),
        knows="the env's MjModel (dynamics, FD Jacobians, link lengths) and the reward, the distance "
              "smoothed over 5 mm")
