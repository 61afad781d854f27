"""An MPC-headed stable-baselines3 policy: observation → cost network → differentiable iLQR MPC → action.

:class:`MPCActorCriticPolicy` is an SB3 ``ActorCriticPolicy`` (PPO, A2C) whose mean action is the first
control of an MPC solve on the task's own model (:class:`controllers.mpc.MPCPolicy`, iLQR with control
limits ``±u_max``).  A small MLP maps the observation to the parameters of the MPC's cost — positive
scales of the task's ``mpc_cost`` state and control weights and an offset of its target — and the output
layer starts at zero, so **the untrained policy is the task's MPC** (cold-started, angles compared modulo
2π, with this policy's horizon and iteration budget).  Gradients of the PPO loss reach the cost network
through the implicit (or unrolled) iLQR gradients.

How it plugs into SB3 (the recipe of issue 12 §5):

* the ``mlp_extractor`` is :class:`MPCExtractor`: its actor latent *is* the MPC action normalized to the
  action space, ``u / u_max ∈ [-1, 1]^m``; its critic is a plain MLP on the observation;
* ``action_net`` is ``nn.Identity`` (the latent is the Gaussian's mean), ``log_std`` a learnable
  state-independent vector (SB3's ``DiagGaussianDistribution``);
* ``ortho_init`` is off for the actor (it would overwrite the zero output layer that makes the initial
  policy the MPC); the critic gets SB3's orthogonal init, as a plain ``MlpPolicy`` does;
* the optimizer is built after the modules are replaced.

**Stateless.**  Every call solves cold (zero initial controls) from the observation alone: no warm start
is kept between calls, since PPO recomputes the log-probabilities of stored observations during its
updates and they must equal those of the rollout.  The state the MPC plans from is
``task.state_from_obs(obs)`` with its angle components (:func:`learning.policies.angle_dims`) taken
within ``±π`` of the cost's target — the stateless counterpart of :class:`~learning.policies.MPCAdapter`'s
hysteresis.  Any batch size works; the solve is float32 (the dtype of SB3's observations).

**Warm start in the observation** (``warm_start=True``, :mod:`learning.mpc_warmstart`).  Cold solves are
what fails on the cart-pole: 16 held-out episodes of CartPoleSwingUp, horizon 25, 5 iterations, float32,
untrained: cold 17.4 ± 2.7 (99.97 % of the solves uncertified, 55 % of the actions on the force limit);
warm-started from the previous plan 179.3 ± 0.3 (6 % saturated; the task's expert, horizon 30 and 20
iterations: 178.4 ± 0.4).  With ``warm_start`` the policy's input is ``[observation, plan]``, the plan
(the previous solve shifted, normalized by ``u_max``) appended by the env wrapper
:class:`~learning.mpc_warmstart.PlanInObservation`: still a deterministic function of what the rollout
buffer stores, so the recomputed log-probabilities equal the rollout's.

**Per-step cost map** (``per_step=True``): the cost network outputs weights and target offsets for every
step of the horizon (the cost map of Actor-Critic MPC, Romero et al., TRO 2025), zero-initialized too.

Off-policy algorithms (SAC, TD3): not provided.  SAC's actor outputs the mean of a *tanh-squashed*
Gaussian, so the MPC action would enter as ``atanh(clip(u/u_max, ±(1-ε)))`` — infinite slope where the
MPC saturates, which a bang-bang swing-up does most of the time, so the gradient reaching the cost
network vanishes there (``d/dθ atanh(clip(·))`` is zero when clipped) or explodes next to it.  And the
cost is prohibitive: SAC/TD3 run one actor forward *and backward* on a batch of 256 (plus a no-grad
forward for the target) per environment step, i.e. ~20 k differentiable MPC solves of batch 256 for 20 k
steps, against ``n_epochs · steps / batch_size`` (1.6 k for 10 epochs of 128) for PPO.

Limitation: a control on its bound is fixed there in the implicit (and, through the clamp, the unrolled)
gradient, so the PPO gradient reaches the cost network only through the elements whose first MPC control
is not saturated; a swing-up that is bang-bang far from the goal learns only near it.

Not exported from :mod:`learning` (SB3 is imported here at module level); import it as
``from learning.mpc_policy import MPCActorCriticPolicy, make_mpc_ppo``.
"""

from __future__ import annotations

import math
from functools import partial
from typing import Any

import numpy as np
import torch
from gymnasium import spaces
from stable_baselines3 import PPO
from stable_baselines3.common.distributions import DiagGaussianDistribution
from stable_baselines3.common.policies import ActorCriticPolicy
from torch import Tensor, nn

from controllers.costs import PeriodicQuadraticCost, QuadraticCost
from controllers.ilqr import ILQROptions
from controllers.mpc import MPCPolicy, MPCState
from learning.envs.single import make_task
from learning.envs.task import Task
from learning.policies import angle_dims

__all__ = ["MPCActorCriticPolicy", "MPCExtractor", "LearnedTaskCost", "make_mpc_ppo", "DEFAULT_MPC_HORIZON",
           "DEFAULT_TERMINAL_FACTOR"]

#: planning horizon of the MPC head by task name (shorter than the expert's: every call is a cold solve)
DEFAULT_MPC_HORIZON = {"PendulumSwingUp": 20, "CartPoleSwingUp": 25, "CarParking": 25, "BicopterHover": 15,
                       "ArmReach": 20, "QuadrotorCircle": 25, "QuadrotorFigureEight": 25}
#: terminal weight of the MPC head's cost as a multiple of the running one, by task name (else the task's
#: own terminal weight); measured in :class:`LearnedTaskCost`'s docstring
DEFAULT_TERMINAL_FACTOR = {"PendulumSwingUp": 1.0}


def _mlp(sizes: list[int], activation_fn: type[nn.Module]) -> list[nn.Module]:
    layers: list[nn.Module] = []
    for a, b in zip(sizes[:-1], sizes[1:]):
        layers += [nn.Linear(a, b), activation_fn()]
    return layers


class LearnedTaskCost(nn.Module):
    """The task's quadratic MPC cost, re-weighted per observation by a network (a cost module for
    :class:`~controllers.mpc.MPCPolicy`: ``forward(x (*B, n)) -> QuadraticCost``).

    With ``s = net(observe(x))`` split into ``(s_q (n), s_r (m), s_t (n))``::

        Q_t = D_q Q_t⁰ D_q,   D_q = diag(exp(½ ρ tanh s_q))        (every t, the terminal one included)
        R   = D_r R⁰ D_r,     D_r = diag(exp(½ ρ tanh s_r))
        x*  = x*⁰ + δ tanh s_t

    ``Q⁰, R⁰, x*⁰`` from ``task.mpc_cost(horizon)`` (``D Q D`` keeps a non-diagonal weight symmetric
    PSD), with the terminal weight ``Q_T⁰ = terminal_factor · Q_{T-1}⁰`` when ``terminal_factor`` is
    given; the weights move by a factor of at most ``exp(±ρ)``, the target by at most ``δ`` per component.
    The net's last layer is zero at construction, so the cost starts as the task's.  The network sees
    ``task.observe(x)`` (the observation the state was recovered from: observations are full-state).

    With ``wrap_angles`` (default) the angle components (:func:`learning.policies.angle_dims`) are compared
    with the target modulo 2π (:class:`~controllers.costs.PeriodicQuadraticCost`).  A stateless policy
    needs this: it plans every call from the observation alone, so with a plain quadratic cost the branch
    of the angle (which side of the target the pendulum hangs on) flips as the pendulum passes the bottom,
    and the plan with it.  Measured on PendulumSwingUp (32 held-out episodes, horizon 20, 5 cold iLQR
    iterations, float32): plain cost with the task's terminal weight −879 (34 % success); periodic cost,
    terminal weight ×10 −688 (59 %); periodic cost, terminal weight = running weight −124 (100 %).

    The default ranges are small (ρ = 0.5, δ = 0.1) because the untrained cost is already good and PPO
    should refine it, not replace it: on PendulumSwingUp (PPO's tuned settings, seed 0, 16 held-out
    episodes) ρ = 2, δ = 0.5 fell from −124 to −768 after 4 096 steps; ρ = 0.5, δ = 0.1 gave −142 and −125
    after 4 096 and 8 192.

    Args:
        task: the task (its ``mpc_cost`` must be a :class:`~controllers.costs.QuadraticCost`).
        horizon: planning horizon.
        net_arch: hidden sizes of the network.
        log_scale_range: ρ (0 keeps the weights fixed).
        target_offset: δ, a float or an ``(n,)`` sequence (0 keeps the target fixed).
        activation_fn: of the hidden layers.
        wrap_angles: compare angles modulo 2π (above).
        terminal_factor: ``Q_T⁰ = terminal_factor · Q_{T-1}⁰``; None keeps the task's terminal weight.
        per_step: a per-step cost map (the cost network of Actor-Critic MPC, Romero et al., TRO 2025): the
            network outputs ``s_q, s_t`` per knot ``t = 0..T`` and ``s_r`` per control step ``t = 0..T-1``
            (``(T+1)·n + T·m + (T+1)·n`` outputs), so ``Q_t = D_{q,t} Q_t⁰ D_{q,t}``, ``R_t = D_{r,t} R⁰
            D_{r,t}`` and ``x*_t = x*⁰ + δ tanh s_{t,t}`` vary along the horizon.  Still zero at
            construction: the untrained cost is the task's.
    """

    def __init__(self, task: Task, horizon: int, net_arch: list[int] = (64, 64), *,
                 log_scale_range: float = 0.5, target_offset: float | list[float] = 0.1,
                 activation_fn: type[nn.Module] = nn.Tanh, wrap_angles: bool = True,
                 terminal_factor: float | None = None, per_step: bool = False):
        super().__init__()
        base = task.mpc_cost(horizon, dtype=torch.float32)
        if not isinstance(base, QuadraticCost):
            raise TypeError(f"LearnedTaskCost: task {task.name} has a {type(base).__name__} MPC cost; only a "
                            "QuadraticCost can be re-weighted")
        if base.N is not None or base.q is not None or base.r is not None:
            raise ValueError("LearnedTaskCost: the task's cost has cross or linear terms; only Q, R, x_ref, "
                             "u_ref are supported")
        self.task, self.horizon = task, horizon
        n, m = task.n, task.m
        Q = base.Q if base.Q.dim() == 3 else base.Q.expand(horizon + 1, n, n)
        R = base.R if base.R.dim() == 3 else base.R.expand(1, m, m)
        if terminal_factor is not None:
            if not math.isfinite(terminal_factor) or terminal_factor < 0:
                raise ValueError(f"LearnedTaskCost: argument 'terminal_factor' must be a finite number >= 0 "
                                 f"or None, got {terminal_factor!r}")
            Q = Q.clone()
            Q[-1] = terminal_factor * Q[-2]
        self.register_buffer("Q0", Q.detach().clone())
        self.register_buffer("R0", R.detach().clone())
        x_ref = base.x_ref if base.x_ref is not None else torch.zeros(n)
        self.register_buffer("x_ref0", x_ref.detach().clone().reshape(-1, n)[-1])
        u_ref = base.u_ref
        self.register_buffer("u_ref0", None if u_ref is None else u_ref.detach().clone())
        self.log_scale_range = float(log_scale_range)
        off = torch.as_tensor(target_offset, dtype=torch.float32).expand(n).clone()
        self.register_buffer("target_offset", off)
        periodic = torch.zeros(n, dtype=torch.bool)
        if wrap_angles:
            periodic[angle_dims(task)] = True
        self.register_buffer("periodic", periodic if bool(periodic.any()) else None)
        self.per_step = bool(per_step)
        self.n_out = (2 * (horizon + 1) * n + horizon * m) if self.per_step else 2 * n + m
        sizes = [task.obs_dim, *net_arch]
        self.net = nn.Sequential(*_mlp(sizes, activation_fn), nn.Linear(sizes[-1], self.n_out))
        nn.init.zeros_(self.net[-1].weight)
        nn.init.zeros_(self.net[-1].bias)

    def parameters_from_obs(self, obs: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """``(q_scale, r_scale, target)`` for observations ``(*B, obs_dim)``: ``(*B, n), (*B, m), (*B, n)``,
        or with ``per_step`` ``(*B, T+1, n), (*B, T, m), (*B, T+1, n)``."""
        n, m, T = self.task.n, self.task.m, self.horizon
        s = torch.tanh(self.net(obs))
        K, J = (T + 1, T) if self.per_step else (1, 1)
        sq, sr, st = s.split([K * n, J * m, K * n], dim=-1)
        shape = (lambda v, k, d: v.unflatten(-1, (k, d))) if self.per_step else (lambda v, k, d: v)
        q_scale = torch.exp(self.log_scale_range * shape(sq, K, n))
        r_scale = torch.exp(self.log_scale_range * shape(sr, J, m))
        target = self.x_ref0 + self.target_offset * shape(st, K, n)
        return q_scale, r_scale, target

    def forward(self, x: Tensor) -> QuadraticCost | PeriodicQuadraticCost:
        q_scale, r_scale, target = self.parameters_from_obs(self.task.observe(x))
        if not self.per_step:  # one knot, broadcast along the horizon
            q_scale, r_scale, target = q_scale[..., None, :], r_scale[..., None, :], target[..., None, :]
        dq, dr = q_scale.sqrt(), r_scale.sqrt()  # (*B, T+1 or 1, n), (*B, T or 1, m)
        Q = self.Q0 * (dq[..., :, None] * dq[..., None, :])  # (*B, T+1, n, n)
        R = self.R0 * (dr[..., :, None] * dr[..., None, :])  # (*B, T or 1, m, m)
        cost = QuadraticCost(Q=Q, R=R, x_ref=target, u_ref=self.u_ref0, check=False)
        return cost if self.periodic is None else PeriodicQuadraticCost(cost, self.periodic)


class _MPCHead(nn.Module):
    """What the MPC heads share (SB3's ``mlp_extractor`` interface around the ``act_and_plan`` each subclass
    defines: ``features -> (action, next plan or None)``): the actor
    latent is the action, recorded plans for :class:`~learning.mpc_warmstart.PlanInObservation`, a critic
    MLP ``value_net`` on the observation part of the features."""

    task: Task
    value_net: nn.Module
    record_plans: bool = False
    recorded_plan: Tensor | None = None

    def forward_actor(self, features: Tensor) -> Tensor:
        a, plan = self.act_and_plan(features)
        if self.record_plans and plan is not None:
            self.recorded_plan = plan.detach()
        return a

    def pop_plan(self) -> Tensor | None:
        """The warm start recorded by the last rollout call (then forgotten), or None."""
        plan, self.recorded_plan = self.recorded_plan, None
        return plan

    def forward_critic(self, features: Tensor) -> Tensor:
        return self.value_net(features[..., :self.task.obs_dim])

    def forward(self, features: Tensor) -> tuple[Tensor, Tensor]:
        return self.forward_actor(features), self.forward_critic(features)


class MPCExtractor(_MPCHead):
    """SB3 ``mlp_extractor`` whose actor latent is the MPC action ``u / u_max`` and whose critic latent
    is an MLP of the observation (``forward``, ``forward_actor``, ``forward_critic``, ``latent_dim_pi``,
    ``latent_dim_vf`` as SB3's ``MlpExtractor``).  No hidden state: every call is a cold solve, or, with
    ``warm_start``, one warm-started from the plan carried in the features.

    Args:
        task: the task (its ``system`` is the MPC's model, ``u_max`` its limits).
        features_dim: size of the observation features (SB3's ``FlattenExtractor``: ``obs_dim``).
        horizon, max_iter, grad, options: of the MPC (``options`` overrides ``max_iter`` and ``compile``).
        compile: iLQR's time sweeps and the implicit gradient's LQ kernels as compiled programs
            (:attr:`~controllers.ilqr.ILQROptions.compile`; the first call builds them, a few seconds each,
            cached on disk): the same actions and gradients to round-off, several times fewer kernel launches.
        cost_net_arch, log_scale_range, target_offset, wrap_angles, terminal_factor: of
            :class:`LearnedTaskCost`.
        vf_arch, activation_fn: the critic MLP.
        per_step: a per-step cost map (:class:`LearnedTaskCost`).
        warm_start: the features are ``[observation, plan]``: the observation followed by the warm start
            of the solve, ``T·m`` controls normalized by ``u_max`` (the previous step's plan shifted by one
            step, zeros for a cold start), which :class:`learning.mpc_warmstart.PlanInObservation` appends
            to the environment's observation.  The action stays a deterministic function of the stored
            features, so PPO's recomputed log-probabilities equal the rollout's; the plan is an input (no
            gradient flows into it).  The critic sees the observation only.

    With ``warm_start``, :meth:`act_and_plan` also returns the next warm start (the solve's controls shifted
    by one step, normalized, no graph); while :attr:`record_plans` is True (SB3's rollout calls, set by
    :meth:`MPCActorCriticPolicy.forward`) :meth:`forward_actor` keeps it in :attr:`recorded_plan` for the
    environment wrapper to collect (:meth:`pop_plan`).

    A non-finite MPC action (a solve that failed, e.g. on a NaN observation) would make PPO's Gaussian and
    every later update NaN: it is replaced by 0 (no action) and counted in the buffer
    ``nonfinite_actions`` (no host sync), which the caller can read and report.
    """

    def __init__(self, task: Task, features_dim: int, *, horizon: int, max_iter: int = 5,
                 grad: str = "implicit", options: ILQROptions | None = None, compile: bool = True,
                 cost_net_arch: list[int] = (64, 64), log_scale_range: float = 0.5,
                 target_offset: float | list[float] = 0.1, vf_arch: list[int] = (64, 64),
                 activation_fn: type[nn.Module] = nn.Tanh, wrap_angles: bool = True,
                 terminal_factor: float | None = None, per_step: bool = False, warm_start: bool = False):
        super().__init__()
        self.warm_start = bool(warm_start)
        plan_dim = horizon * task.m if self.warm_start else 0
        if features_dim != task.obs_dim + plan_dim:
            what = f"observation ({task.obs_dim}) plus the plan ({plan_dim})" if plan_dim else \
                f"observation ({task.obs_dim})"
            raise ValueError(f"MPCExtractor: features of size {features_dim}, expected the task's {what}; "
                             "use SB3's FlattenExtractor")
        self.task = task
        self.record_plans = False
        self.recorded_plan: Tensor | None = None
        cost = LearnedTaskCost(task, horizon, list(cost_net_arch), log_scale_range=log_scale_range,
                               target_offset=target_offset, activation_fn=activation_fn,
                               wrap_angles=wrap_angles, terminal_factor=terminal_factor, per_step=per_step)
        umax = torch.tensor(task.u_max(), dtype=torch.float32)
        opts = options if options is not None else ILQROptions(max_iter=max_iter, compile=bool(compile))
        self.mpc = MPCPolicy(task.system, horizon, cost, u_lower=-umax, u_upper=umax, grad=grad, options=opts)
        self.register_buffer("u_max", umax)
        self.register_buffer("nonfinite_actions", torch.zeros((), dtype=torch.int64), persistent=False)
        dims = torch.zeros(task.n, dtype=torch.bool)
        dims[angle_dims(task)] = True
        self.register_buffer("angle_mask", dims)
        vf = list(vf_arch)
        self.value_net = nn.Sequential(*_mlp([task.obs_dim, *vf], activation_fn))
        self.latent_dim_pi = task.m
        self.latent_dim_vf = vf[-1] if vf else task.obs_dim

    def state(self, obs: Tensor) -> Tensor:
        """The state the MPC plans from: ``task.state_from_obs`` with angles within ``±π`` of the
        (untrained) cost target."""
        x = self.task.state_from_obs(obs)
        c = self.mpc.cost.x_ref0
        centered = torch.remainder(x - c + math.pi, 2 * math.pi) - math.pi + c
        return torch.where(self.angle_mask, centered, x)

    def split(self, features: Tensor) -> tuple[Tensor, Tensor | None]:
        """``(observation (*B, obs_dim), warm start (*B, T, m) in physical units or None)``."""
        d = self.task.obs_dim
        if not self.warm_start:
            return features, None
        plan = features[..., d:].unflatten(-1, (self.mpc.horizon, self.task.m))
        plan = torch.nan_to_num(plan, nan=0.0).clamp(-1.0, 1.0)  # a warm start only: keep it in the box
        return features[..., :d], plan * self.u_max

    def act_and_plan(self, features: Tensor) -> tuple[Tensor, Tensor | None]:
        """``(action u/u_max (*B, m), next warm start (*B, T·m) normalized, or None without warm_start)``:
        one MPC solve from ``features`` (cold, or warm-started by their plan)."""
        obs, u0 = self.split(features)
        x = self.state(obs)
        st = None
        if u0 is not None:
            B = x.shape[:-1]
            st = MPCState(u=u0.to(x.dtype), converged=torch.zeros(B, dtype=torch.bool, device=x.device),
                          iterations=torch.zeros(B, dtype=torch.int64, device=x.device))
        u, nxt = self.mpc(x, st)
        a = u / self.u_max
        finite = torch.isfinite(a)
        self.nonfinite_actions += (~finite).sum()
        a = torch.where(finite, a, torch.zeros((), dtype=a.dtype, device=a.device))
        plan = (nxt.u / self.u_max).clamp(-1.0, 1.0).flatten(-2) if self.warm_start else None
        return a, plan



class MPCActorCriticPolicy(ActorCriticPolicy):
    """SB3 actor-critic policy with an MPC head (module docstring); use with PPO or A2C.

    Keyword args (besides ``ActorCriticPolicy``'s; ``net_arch`` is the critic's: a list, or a dict whose
    ``"vf"`` entry is used):
        task: a :class:`~learning.envs.task.Task` or its name (required).
        horizon: MPC horizon (default :data:`DEFAULT_MPC_HORIZON`, else 20).
        max_iter: iLQR iterations per call (cold start every call).
        grad: ``"implicit"`` (default) or ``"unrolled"`` gradients through the solve.
        ilqr_options: a full :class:`~controllers.ilqr.ILQROptions` (overrides ``max_iter`` and ``compile``).
        compile: compiled solver sweeps (default True; :class:`MPCExtractor`).
        cost_net_arch, log_scale_range, target_offset, wrap_angles: of :class:`LearnedTaskCost`.
        terminal_factor: of :class:`LearnedTaskCost` (default :data:`DEFAULT_TERMINAL_FACTOR`, else None:
            the task's terminal weight).
        log_std_init: initial log standard deviation of the normalized action (default -1: the initial
            policy is a good controller, so exploration starts smaller than SB3's 0).
        per_step: a per-step cost map (:class:`LearnedTaskCost`).
        warm_start: warm-start each solve from the plan carried in the observation (:class:`MPCExtractor`;
            the environment must be wrapped in :class:`learning.mpc_warmstart.PlanInObservation`, e.g. by
            :func:`learning.mpc_warmstart.make_warm_mpc_ppo`).

    On a :class:`~learning.envs.quadrotor.QuadrotorTrack` task (``QuadrotorCircle``,
    ``QuadrotorFigureEight``) the head is the error-state MPC on the manifold instead
    (:class:`learning.mpc_head_quadrotor.ErrorStateMPCExtractor`: the network re-weights the expert's cost
    and moves its position targets; a QP solved to optimality, so stateless); ``max_iter``,
    ``ilqr_options``, ``compile``, ``wrap_angles`` and ``terminal_factor`` do not apply there.
    """

    def __init__(self, observation_space: spaces.Space, action_space: spaces.Space, lr_schedule, *,
                 task: Task | str, horizon: int | None = None, max_iter: int = 5, grad: str = "implicit",
                 ilqr_options: ILQROptions | None = None, compile: bool = True,
                 cost_net_arch: list[int] | None = None,
                 log_scale_range: float = 0.5, target_offset: float | list[float] = 0.1,
                 wrap_angles: bool = True, terminal_factor: float | None = None,
                 log_std_init: float = -1.0, ortho_init: bool = False, use_sde: bool = False,
                 per_step: bool = False, warm_start: bool = False, **kwargs):
        if ortho_init:
            raise ValueError("MPCActorCriticPolicy: ortho_init=True would overwrite the cost network's zero "
                             "output layer (the critic gets orthogonal init anyway)")
        if use_sde:
            raise ValueError("MPCActorCriticPolicy: gSDE is not supported (Gaussian noise on the MPC action)")
        if str(grad) not in ("implicit", "unrolled", "GradMode.IMPLICIT", "GradMode.UNROLLED"):
            raise ValueError(f"MPCActorCriticPolicy: grad must be 'implicit' or 'unrolled', got {grad!r}")
        t = make_task(task)
        if not isinstance(action_space, spaces.Box) or action_space.shape != (t.m,):
            raise ValueError(f"MPCActorCriticPolicy: expected a Box action space of shape ({t.m},), got "
                             f"{action_space}")
        self.task_arg = task
        self.mpc_task = t
        self.horizon = horizon if horizon is not None else DEFAULT_MPC_HORIZON.get(t.name, 20)
        self.max_iter, self.grad, self.ilqr_options = max_iter, grad, ilqr_options
        self.compile_sweeps = bool(compile)  # not ``self.compile``: nn.Module.compile is a method
        self.cost_net_arch = [64, 64] if cost_net_arch is None else list(cost_net_arch)
        self.log_scale_range, self.target_offset = log_scale_range, target_offset
        self.wrap_angles = bool(wrap_angles)
        self.per_step, self.warm_start = bool(per_step), bool(warm_start)
        self.terminal_factor = (terminal_factor if terminal_factor is not None
                                else DEFAULT_TERMINAL_FACTOR.get(t.name))
        super().__init__(observation_space, action_space, lr_schedule, ortho_init=False, use_sde=False,
                         log_std_init=log_std_init, **kwargs)

    def _build_mlp_extractor(self) -> None:
        from learning.envs.quadrotor import QuadrotorTrack

        arch = self.net_arch
        vf = arch.get("vf", [64, 64]) if isinstance(arch, dict) else list(arch)
        if isinstance(self.mpc_task, QuadrotorTrack):  # the error-state MPC on the manifold
            from learning.mpc_head_quadrotor import ErrorStateMPCExtractor

            self.mlp_extractor = ErrorStateMPCExtractor(
                self.mpc_task, self.features_dim, horizon=self.horizon, grad=self.grad,
                cost_net_arch=self.cost_net_arch, activation_fn=self.activation_fn,
                log_scale_range=self.log_scale_range, target_offset=self.target_offset, vf_arch=vf,
                per_step=self.per_step, warm_start=self.warm_start)
            return
        self.mlp_extractor = MPCExtractor(
            self.mpc_task, self.features_dim, horizon=self.horizon, max_iter=self.max_iter, grad=self.grad,
            options=self.ilqr_options, compile=self.compile_sweeps, cost_net_arch=self.cost_net_arch,
            log_scale_range=self.log_scale_range,
            target_offset=self.target_offset, vf_arch=vf, activation_fn=self.activation_fn,
            wrap_angles=self.wrap_angles, terminal_factor=self.terminal_factor, per_step=self.per_step,
            warm_start=self.warm_start)

    def forward(self, obs: Tensor, deterministic: bool = False) -> tuple[Tensor, Tensor, Tensor]:
        """SB3's rollout call; with ``warm_start`` the extractor records the next plan meanwhile."""
        self.mlp_extractor.record_plans = self.warm_start
        try:
            return super().forward(obs, deterministic)
        finally:
            self.mlp_extractor.record_plans = False

    def _build(self, lr_schedule) -> None:
        super()._build(lr_schedule)  # ortho_init is False: nothing initialized there
        if not isinstance(self.action_dist, DiagGaussianDistribution):
            raise ValueError("MPCActorCriticPolicy: only a Gaussian action distribution is supported")
        self.action_net = nn.Identity()  # the latent is the mean action
        # the critic as SB3's MlpPolicy initializes it
        self.mlp_extractor.value_net.apply(partial(self.init_weights, gain=np.sqrt(2)))
        self.value_net.apply(partial(self.init_weights, gain=1.0))
        self.optimizer = self.optimizer_class(self.parameters(), lr=lr_schedule(1), **self.optimizer_kwargs)

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.pop("ortho_init", None)
        data.pop("use_sde", None)
        data.update(task=self.task_arg, horizon=self.horizon, max_iter=self.max_iter, grad=self.grad,
                    ilqr_options=self.ilqr_options, compile=self.compile_sweeps,
                    cost_net_arch=self.cost_net_arch,
                    log_scale_range=self.log_scale_range, target_offset=self.target_offset,
                    wrap_angles=self.wrap_angles, terminal_factor=self.terminal_factor,
                    per_step=self.per_step, warm_start=self.warm_start)
        return data


def make_mpc_ppo(task: Task | str = "PendulumSwingUp", *, num_envs: int = 8, env_kwargs: dict | None = None,
                 policy_kwargs: dict | None = None, **ppo_kwargs) -> PPO:
    """A PPO model with an :class:`MPCActorCriticPolicy` on :class:`~learning.sb3.SB3VecEnv` (float32).

    Args:
        task: task instance or name.
        num_envs: environments of the vector env.
        env_kwargs: more arguments of :class:`~learning.sb3.SB3VecEnv` (``max_episode_steps``...).
        policy_kwargs: of the policy (``horizon``, ``max_iter``, ``grad``...; ``task`` is set here).
        **ppo_kwargs: of ``PPO`` (``n_steps``, ``batch_size``, ``learning_rate``, ``seed``, ``device``...).
    """
    from learning.sb3 import SB3VecEnv

    t = make_task(task)
    env = SB3VecEnv(t, num_envs, **(env_kwargs or {}))
    pk = dict(policy_kwargs or {})
    pk["task"] = task
    ppo_kwargs.setdefault("device", "cpu")
    return PPO(MPCActorCriticPolicy, env, policy_kwargs=pk, **ppo_kwargs)
