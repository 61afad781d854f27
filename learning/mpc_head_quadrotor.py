"""The MPC head on the manifold: a cost network feeding the error-state MPC of seed 003, for PPO.

:class:`ErrorStateMPCExtractor` is the ``mlp_extractor`` that :class:`learning.mpc_policy.
MPCActorCriticPolicy` builds for a :class:`~learning.envs.quadrotor.QuadrotorTrack` task
(``QuadrotorCircle``, ``QuadrotorFigureEight``), whose MPC is not an iLQR on a flat state but the error-state
MPC on ``R³ × R³ × SO(3)`` (:class:`~controllers.manifold_mpc.ErrorStateMPC`, the task's expert
:class:`~learning.envs.quadrotor.QuadrotorTrackingExpert`).  From each observation:

* the state ``(p, v, R)`` and the phase ``k`` (``task.state_from_obs``), hence the reference of the next
  ``T`` steps from the task's table (position, velocity, attitude, flatness controls);
* a network ``s = tanh(net(obs))`` re-weights the expert's cost and moves its position target::

      Q = diag(q⁰ · exp(ρ s_q))   (9: position, velocity, attitude error),
      R = diag(r⁰ · exp(ρ s_r))   (4: thrust, body rates),
      p*_k = p_ref,k + δ s_p,k    (one offset, or with ``per_step`` one per knot k = 0..T: a cost map),

  with the expert's ``q⁰ = (100·1₃, 10·1₃, 10·1₃)``, ``r⁰ = (0.1, 0.1·1₃)`` and its terminal weight (the
  DARE solution at hover for ``q⁰, r⁰``, kept fixed).  The network's last layer is zero at construction, so
  **the untrained head is the task's expert** (same horizon, weights, limits and reference);
* one error-state MPC solve (a box QP under the thrust and rate limits, solved to its certificate) gives
  the action ``(u₀ − [g, 0, 0, 0]) / u_scale``, PPO's Gaussian mean; its implicit gradient (through the
  QP's active set) reaches ``Q``, ``R`` and the targets, hence the network.

**Stateless by construction.**  The QP is convex and solved to optimality, so the action does not depend on
the warm start: every call is a function of the observation alone and PPO's recomputed log-probabilities
equal the rollout's without carrying a plan.  ``warm_start=True`` is accepted for uniformity (the plan in the
observation then only speeds the active-set search).

A failed solve (NaN action, e.g. a non-finite observation) becomes action 0 and is counted in
``nonfinite_actions``, as in :class:`~learning.mpc_policy.MPCExtractor`.  Solves run in the observation's
dtype (float32 under SB3; the condensed QP itself runs in float64, :class:`ErrorStateMPC`).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from learning.envs.quadrotor import QuadrotorTrack, QuadrotorTrackingExpert
from learning.mpc_policy import _mlp, _MPCHead

__all__ = ["ErrorStateMPCExtractor"]


class ErrorStateMPCExtractor(_MPCHead):
    """SB3 ``mlp_extractor`` of :class:`~learning.mpc_policy.MPCActorCriticPolicy` on a
    :class:`QuadrotorTrack` (module docstring); the interface of :class:`~learning.mpc_policy.MPCExtractor`
    (``forward_actor``, ``forward_critic``, ``pop_plan`` shared with it).

    Args:
        task: the quadrotor task.
        features_dim: ``task.obs_dim`` (plus ``horizon · 4`` with ``warm_start``).
        horizon: of the MPC (the expert's 25 by default in the policy).
        grad: ``"implicit"`` (the QP's implicit gradient; ``"unrolled"`` is treated as implicit).
        cost_net_arch, activation_fn: the cost network.
        log_scale_range: ρ, the weights move by a factor of at most ``exp(±ρ)``.
        target_offset: δ (m), the largest move of the position target per axis.
        vf_arch: the critic MLP (on the observation).
        per_step: one position offset per knot (a cost map along the horizon) instead of one for all.
        warm_start: the features carry the previous plan (module docstring).
    """

    def __init__(self, task: QuadrotorTrack, features_dim: int, *, horizon: int, grad: str = "implicit",
                 cost_net_arch: list[int] = (64, 64), activation_fn: type[nn.Module] = nn.Tanh,
                 log_scale_range: float = 0.5, target_offset: float = 0.1, vf_arch: list[int] = (64, 64),
                 per_step: bool = False, warm_start: bool = False):
        super().__init__()
        from controllers.manifold_mpc import riccati_terminal_weight

        if not isinstance(task, QuadrotorTrack):
            raise TypeError("ErrorStateMPCExtractor: expected a QuadrotorTrack task, got "
                            f"{type(task).__name__}")
        self.warm_start, self.per_step = bool(warm_start), bool(per_step)
        plan_dim = horizon * task.m if self.warm_start else 0
        if features_dim != task.obs_dim + plan_dim:
            what = "the observation and the plan" if plan_dim else "the observation"
            raise ValueError(f"ErrorStateMPCExtractor: features of size {features_dim}, expected "
                             f"{task.obs_dim + plan_dim} ({what})")
        self.task, self.horizon, self.grad = task, int(horizon), str(grad)
        self.record_plans, self.recorded_plan = False, None
        w = QuadrotorTrackingExpert(task).weights
        q0 = torch.tensor(w["Q"], dtype=torch.float64)
        r0 = torch.tensor(w["R"], dtype=torch.float64)
        quad = task.system.quad
        x_h, u_h = quad.hover(torch.zeros(3, dtype=torch.float64))
        P, _ = riccati_terminal_weight(quad, x_h, u_h, torch.diag(q0), torch.diag(r0))
        self.register_buffer("q0", q0)  # float64, cast to the observations' dtype at use
        self.register_buffer("r0", r0)
        self.register_buffer("P0", P)
        self.log_scale_range, self.target_offset = float(log_scale_range), float(target_offset)
        knots = self.horizon + 1 if self.per_step else 1
        self.n_out = 9 + 4 + 3 * knots
        sizes = [task.obs_dim, *cost_net_arch]
        self.net = nn.Sequential(*_mlp(sizes, activation_fn), nn.Linear(sizes[-1], self.n_out))
        nn.init.zeros_(self.net[-1].weight)
        nn.init.zeros_(self.net[-1].bias)
        self.register_buffer("nonfinite_actions", torch.zeros((), dtype=torch.int64), persistent=False)
        vf = list(vf_arch)
        self.value_net = nn.Sequential(*_mlp([task.obs_dim, *vf], activation_fn))
        self.latent_dim_pi = task.m
        self.latent_dim_vf = vf[-1] if vf else task.obs_dim

    def cost(self, obs: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """``(Q (B, 9, 9), R (B, 4, 4), position offsets (B, T+1 or 1, 3))`` for observations
        ``(B, obs_dim)``."""
        s = torch.tanh(self.net(obs))
        sq, sr, sp = s.split([9, 4, self.n_out - 13], dim=-1)
        Q = torch.diag_embed(self.q0.to(s.dtype) * torch.exp(self.log_scale_range * sq))
        R = torch.diag_embed(self.r0.to(s.dtype) * torch.exp(self.log_scale_range * sr))
        return Q, R, self.target_offset * sp.unflatten(-1, (-1, 3))

    def _reference(self, x: Tensor, offset: Tensor):
        from torchlie.manifolds import ProductState

        task, T = self.task, self.horizon
        ref = task.reference(x.dtype, x.device)
        idx = (task.phase_index(x)[:, None] + torch.arange(T + 1, device=x.device)) % task.period_steps
        x_ref = ProductState({"p": ref["p"][idx] + offset, "v": ref["v"][idx], "R": ref["R"][idx]},
                             {"p": 1, "v": 1, "R": 2})
        return x_ref, ref["u"][idx[:, :T]]

    def _hover(self, like: Tensor) -> Tensor:
        g = torch.as_tensor(self.task.system.quad.gravity, dtype=like.dtype, device=like.device)
        return torch.cat([g.reshape(1), torch.zeros(3, dtype=like.dtype, device=like.device)])

    def act_and_plan(self, features: Tensor) -> tuple[Tensor, Tensor | None]:
        """``(action (B, 4) normalized, next plan (B, T·4) normalized or None without warm_start)``."""
        from controllers.manifold_mpc import ErrorStateMPC

        d, T = self.task.obs_dim, self.horizon
        obs = features[..., :d]
        lead = obs.shape[:-1]
        obs = obs.reshape(-1, d)
        x = self.task.state_from_obs(obs)
        Q, R, offset = self.cost(obs)
        x_ref, u_ref = self._reference(x, offset)
        hover, scale = self._hover(obs), self.task.u_scale(obs.dtype, obs.device)
        warm = None
        if self.warm_start:
            plan = torch.nan_to_num(features[..., d:].reshape(-1, T, 4), nan=0.0).clamp(-1.0, 1.0)
            warm = plan * scale + hover
        mpc = ErrorStateMPC(self.task.system.quad, T, Q, R, self.P0.to(obs.dtype).expand(Q.shape),
                            grad=self.grad if self.grad != "unrolled" else "implicit")
        sol = mpc.solve(self.task.system.point(x), x_ref, u_ref, warm=warm)
        a = (sol.u - hover) / scale
        finite = torch.isfinite(a)
        self.nonfinite_actions += (~finite).sum()
        a = torch.where(finite, a, torch.zeros((), dtype=a.dtype, device=a.device)).reshape(*lead, 4)
        if not self.warm_start:
            return a, None
        U = torch.cat([sol.U[:, 1:], sol.U[:, -1:]], 1).detach()
        nxt = torch.nan_to_num(((U - hover) / scale), nan=0.0).clamp(-1.0, 1.0).flatten(-2)
        return a, nxt.reshape(*lead, T * 4)

