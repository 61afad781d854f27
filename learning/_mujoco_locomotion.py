"""A model of a gymnasium MuJoCo locomotion env for a model-based MPC: :func:`half_cheetah_model`.

**HalfCheetah-v5** (gymnasium's ``half_cheetah_v5.py``; ``a ∈ [-1, 1]⁶``, ``frame_skip = 5``,
``dt = 0.05``; no termination, 1000 steps).  The system is a
:class:`~controllers.systems.mujoco_system.MujocoSystem` of the env's own ``MjModel``
(``x = [qpos (9), qvel (9)]``, ``n = 18``; ``step`` is ``env.step`` to round-off, contacts included).

*Observation → state* (:func:`half_cheetah_state`).  The observation is ``[qpos[1:] (8), qvel (9)]``: by
default (``exclude_current_positions_from_observation=True``) it drops ``qpos[0]``, the root's x position.
The map puts **0** there.  Nothing is lost: the floor is an infinite plane, so the dynamics do not depend
on the x position (translating the whole cheetah along x translates its future), and the cost below only
uses differences of it.  The map is exact for every other coordinate.

*Reward and cost* (:class:`ForwardRewardCost`).  After a step from ``x_t`` with action ``a_t`` the env
pays ``r_t = w_f (p_{t+1} − p_t) / dt − w_c ‖a_t‖²`` with ``p = qpos[0]`` (``forward_reward_weight``
``w_f = 1``, ``ctrl_cost_weight`` ``w_c = 0.1``, read from the env when one is given, as
``learning._mujoco_models`` does for Reacher).  The planning cost of a plan is minus its return::

    J = Σ_{t<T} −r_t = −w_f (p_T − p_0) / dt + w_c Σ_{t<T} ‖u_t‖²  (−  w_f τ v_T  if velocity_to_go = τ > 0)

— exact (the forward terms telescope), so ``−Σ rewards`` of a real trajectory equals ``J`` of its states
and actions to round-off (the env penalizes the action it is given, MuJoCo applies it clamped to
``ctrlrange``: the planners only send actions inside the box, where the two agree).  The optional
``velocity_to_go`` (seconds, default 0: the reward exactly) adds the forward velocity at the horizon's end
held for ``τ`` seconds, a value-to-go stand-in for short horizons.  The cost is not smooth enough for
iLQR's Gauss-Newton model to help much (linear in the state, no curvature): it is meant for the sampling
planner (:class:`learning.sampling_mpc.SamplingModelMPC`); the iLQR settings of the model are the
system's FD-aware defaults and were not tuned.  Measured with the sampling MPC (its module docstring):
5002 ± 535 over seeds 0-4 with 128 samples, 6516 over seeds 0-1 with 512 (the RL Zoo's best, TQC: 12090).

Not done: Hopper-v5 (its healthy-state termination needs a barrier like InvertedDoublePendulum's);
the env's ``exclude_current_positions_from_observation=False`` variant (a different observation size:
:func:`half_cheetah_model` refuses an env that was built with it).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from learning._mujoco_models import _check_obs, _options, _system

__all__ = ["half_cheetah_model", "half_cheetah_state", "ForwardRewardCost", "HALF_CHEETAH"]

HALF_CHEETAH = "HalfCheetah-v5"


def half_cheetah_state(obs: Tensor) -> Tensor:
    """HalfCheetah-v5: ``[qpos[1:] (8), qvel (9)] (*B, 17)`` to ``x = [0, qpos[1:], qvel] (*B, 18)`` (the
    root's x position, which the observation drops, is set to 0: module docstring)."""
    _check_obs(obs, 17, "half_cheetah_state")
    return torch.cat([torch.zeros_like(obs[..., :1]), obs], -1)


@dataclass(frozen=True, eq=False)
class ForwardRewardCost:
    """Minus the return of a forward-running task, ``J = −w_f (x_T[i] − x_0[i]) / dt + w_c Σ_t ‖u_t‖²
    − w_f τ x_T[j]`` (module docstring): ``i`` = ``position_index`` (the root's x in ``qpos``),
    ``j`` = ``velocity_index`` (its velocity in ``x``), ``τ`` = ``velocity_to_go``.

    ``evaluate(x (*B, T+1, n), u (*B, T, m)) -> (*B,)`` (any leading dims, dtype and device of ``x``); no
    ``derivatives`` (autograd gives them; the cost is linear in ``x``).
    """

    dt: float
    n: int
    m: int
    forward_weight: float = 1.0
    ctrl_weight: float = 0.1
    position_index: int = 0
    velocity_index: int = 9
    velocity_to_go: float = 0.0

    def __post_init__(self) -> None:
        if not isinstance(self.dt, (int, float)) or not self.dt > 0:
            raise ValueError(f"ForwardRewardCost: field 'dt' must be a positive number, got {self.dt!r}")
        for name in ("forward_weight", "ctrl_weight", "velocity_to_go"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not v >= 0:
                raise ValueError(f"ForwardRewardCost: field '{name}' must be a number >= 0, got {v!r}")
        for name, hi in (("position_index", self.n), ("velocity_index", self.n)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v < hi:
                raise ValueError(f"ForwardRewardCost: field '{name}' must be an int in [0, {hi}), got {v!r}")

    def evaluate(self, x: Tensor, u: Tensor) -> Tensor:
        if (not isinstance(x, Tensor) or not isinstance(u, Tensor) or x.dim() < 2 or u.dim() < 2
                or x.shape[-1] != self.n or u.shape[-1] != self.m or x.shape[-2] != u.shape[-2] + 1):
            raise ValueError(f"ForwardRewardCost.evaluate: expected x (*B, T+1, {self.n}), "
                             f"u (*B, T, {self.m}), got {tuple(getattr(x, 'shape', ()))} and "
                             f"{tuple(getattr(u, 'shape', ()))}")
        i = self.position_index
        J = (-self.forward_weight / self.dt) * (x[..., -1, i] - x[..., 0, i])
        J = J + self.ctrl_weight * (u * u).sum((-1, -2))
        if self.velocity_to_go > 0:
            J = J - self.forward_weight * self.velocity_to_go * x[..., -1, self.velocity_index]
        return J

    def rewards(self, x: Tensor, u: Tensor) -> Tensor:
        """The env's per-step rewards ``r_t (*B, T)`` along ``x (*B, T+1, n)``, ``u (*B, T, m)``."""
        i = self.position_index
        return (self.forward_weight / self.dt) * (x[..., 1:, i] - x[..., :-1, i]) - self.ctrl_weight * (
            u * u).sum(-1)


def half_cheetah_model(env: Any = None, *, horizon: int = 20, max_iter: int = 3, velocity_to_go: float = 0.0,
                       options: dict[str, Any] | None = None):
    """The :class:`~learning.env_models.EnvModel` of ``HalfCheetah-v5`` (module docstring).

    ``horizon``: the planners' default horizon (env steps); ``max_iter``, ``options``: iLQR settings
    (:class:`learning.model_mpc.ModelMPC`, untuned); ``velocity_to_go``: :class:`ForwardRewardCost`'s."""
    from learning.env_models import EnvModel

    system, single = _system(env, HALF_CHEETAH)
    inner = getattr(single, "unwrapped", single)
    if not getattr(inner, "_exclude_current_positions_from_observation", True):
        raise ValueError("half_cheetah_model: the env observes qpos[0] "
                         "(exclude_current_positions_from_observation=False); the model is for the default")
    wf = float(getattr(inner, "_forward_reward_weight", 1.0))
    wc = float(getattr(inner, "_ctrl_cost_weight", 0.1))
    vx = system.nq  # qvel[0] in x = [qpos, qvel]
    fc = ForwardRewardCost(dt=system.dt, n=system.nx, m=system.m, forward_weight=wf, ctrl_weight=wc,
                           position_index=0, velocity_index=vx, velocity_to_go=float(velocity_to_go))

    def cost(h: int, dtype=torch.float64, device=None):
        return fc

    lo = tuple(float(v) for v in single.action_space.low)
    hi = tuple(float(v) for v in single.action_space.high)
    return EnvModel(
        env_id=HALF_CHEETAH, system=system, cost=cost, state_from_obs=half_cheetah_state,
        action_low=lo, action_high=hi, obs_dim=17, horizon=horizon, max_iter=max_iter, random_starts=0,
        multistart=False, options=_options(system, options), planner="sampling",
        knows="the env's MjModel (dynamics with contacts) and the reward exactly (minus the return as the "
              "cost); the x position the observation drops, to which neither is sensitive")
