"""Warm-started MPC head for PPO: the previous step's plan travels in the observation.

Why.  The MPC head of :mod:`learning.mpc_policy` solves every call cold, a few iLQR iterations from zero
controls, because PPO recomputes the log-probabilities of stored observations and they must equal the
rollout's.  On CartPoleSwingUp that cold policy is poor (measured, 16 held-out episodes, horizon 25,
5 iterations, float32: return 17.4 ± 2.7, 99.97 % of the solves not certified, 55 % of the actions on
the force limit), while the same head warm-started from the shifted previous plan returns 179.3 ± 0.3
(the task's MPC expert, horizon 30, 20 iterations, warm-started: 178.4 ± 0.4) — PPO started from the former.
After PPO (the task's PPO settings, learning rate 3e-4, seed 0, the same 16 held-out episodes) the
warm-started head returns 179.4 ± 0.3 after 20 480 environment steps and, with the per-step cost map,
179.4 ± 0.3 after 10 240; plain PPO 47.6 ± 3.3 and 44.7 ± 4.4 at the same steps: the head keeps its MPC
prior, and PPO neither improves nor degrades it measurably within that budget.  Per step at batch 1 it
costs ~26× the MLP (16 ms against 0.6 ms, compiled sweeps; 62 ms uncompiled).

How, keeping the log-probabilities consistent.  The warm start is made part of the observation:
:class:`PlanInObservation` appends to each environment's observation the plan the policy computed at the
previous step, shifted by one step and normalized by ``u_max`` (``T·m`` numbers in ``[-1, 1]``; zeros, a
cold start, at the first step of an episode).  The policy (``MPCActorCriticPolicy(warm_start=True)``)
solves from ``[observation, plan]`` and is a deterministic function of it, so SB3's rollout buffer stores
exactly what the action depended on, and PPO's re-evaluation of a stored sample gives the rollout's mean
action and log-probability (up to the round-off of a different batch).  The plan is an input: no gradient
flows into it, and the implicit iLQR gradient reaches the cost network as before.

The plan reaches the wrapper from the policy: during SB3's rollout call (``policy.forward``) the extractor
records the next plan (:meth:`~learning.mpc_policy.MPCExtractor.pop_plan`), and :meth:`PlanInObservation.
step_wait` collects it — a missing plan (the wrapper not attached to the policy, or a step not preceded by
a rollout call) is an error, never a silent cold start.

Evaluation on the task's own observations: :class:`WarmStartMPCPPO` (a ``PPO``) is also a
:class:`learning.policies.Policy` (``act``/``reset``): it keeps one plan per environment between calls
(cold-started per element by ``reset(done)``) and returns the deterministic (mean) action, so
``learning.evaluate.evaluate(model, task)`` runs it as it runs any policy.
"""

from __future__ import annotations

import numpy as np
import torch
from gymnasium import spaces
from stable_baselines3 import PPO
from stable_baselines3.common.vec_env import VecEnv, VecEnvWrapper
from torch import Tensor

from learning.envs.single import make_task
from learning.envs.task import Task
from learning.mpc_policy import DEFAULT_MPC_HORIZON, MPCActorCriticPolicy

__all__ = ["PlanInObservation", "WarmStartMPCPPO", "make_warm_mpc_ppo", "warm_start_setup"]


class PlanInObservation(VecEnvWrapper):
    """An SB3 ``VecEnv`` wrapper whose observation is ``[observation, plan]`` (module docstring).

    Args:
        venv: the environments (e.g. :class:`learning.sb3.SB3VecEnv`), Box observations ``(obs_dim,)``.
        horizon, m: the plan is ``horizon · m`` normalized controls.

    :meth:`attach` the policy (an ``MPCActorCriticPolicy(warm_start=True)``) before stepping.  For an
    episode that ended, ``infos[i]["terminal_observation"]`` carries the plan computed at its last step
    and the returned observation (the next episode's first) a zero plan.
    """

    def __init__(self, venv: VecEnv, horizon: int, m: int):
        box = venv.observation_space
        if not isinstance(box, spaces.Box) or len(box.shape) != 1:
            raise ValueError(f"PlanInObservation: expected a flat Box observation space, got {box}")
        if int(horizon) < 1 or int(m) < 1:
            raise ValueError(f"PlanInObservation: 'horizon' and 'm' must be positive, got {horizon}, {m}")
        self.plan_dim = int(horizon) * int(m)
        ones = np.ones(self.plan_dim, dtype=box.dtype)
        space = spaces.Box(np.concatenate([box.low, -ones]), np.concatenate([box.high, ones]),
                           dtype=box.dtype)
        super().__init__(venv, observation_space=space)
        self.policy: MPCActorCriticPolicy | None = None
        self._plan = np.zeros((self.num_envs, self.plan_dim), dtype=box.dtype)

    def attach(self, policy: MPCActorCriticPolicy) -> None:
        """The policy whose rollout calls produce the plans."""
        if not getattr(policy, "warm_start", False):
            raise ValueError("PlanInObservation.attach: the policy must be an MPCActorCriticPolicy built "
                             "with warm_start=True")
        self.policy = policy

    def _augment(self, obs: np.ndarray, plan: np.ndarray) -> np.ndarray:
        return np.concatenate([obs, plan.astype(obs.dtype, copy=False)], axis=-1)

    def reset(self) -> np.ndarray:
        self._plan = np.zeros_like(self._plan)
        if self.policy is not None:
            self.policy.mlp_extractor.pop_plan()  # a plan from before the reset is stale
        return self._augment(self.venv.reset(), self._plan)

    def _collect(self) -> np.ndarray:
        if self.policy is None:
            raise RuntimeError("PlanInObservation: no policy attached (call attach(policy) first)")
        plan = self.policy.mlp_extractor.pop_plan()
        if plan is None or tuple(plan.shape) != (self.num_envs, self.plan_dim):
            got = None if plan is None else tuple(plan.shape)
            raise RuntimeError(f"PlanInObservation: expected a plan of shape ({self.num_envs}, "
                               f"{self.plan_dim}) from the policy's rollout call before this step, got {got}")
        return plan.detach().cpu().numpy().astype(self._plan.dtype)

    def step_wait(self):
        plan = self._collect()
        obs, rewards, dones, infos = self.venv.step_wait()
        for i in np.flatnonzero(dones):
            term = infos[i].get("terminal_observation")
            if term is not None:
                infos[i]["terminal_observation"] = self._augment(term, plan[i])
        plan[dones.astype(bool)] = 0.0  # a new episode starts cold
        self._plan = plan
        return self._augment(obs, plan), rewards, dones, infos


def _find_wrapper(env) -> PlanInObservation | None:
    while env is not None:
        if isinstance(env, PlanInObservation):
            return env
        env = getattr(env, "venv", None)
    return None


class WarmStartMPCPPO(PPO):
    """``PPO`` for an ``MPCActorCriticPolicy(warm_start=True)`` on a :class:`PlanInObservation` env (it
    attaches the policy to the wrapper), and a :class:`learning.policies.Policy` on the task's plain
    observations: :meth:`act` keeps the plans between calls, :meth:`reset` cold-starts them."""

    _eval_plan: Tensor | None = None

    def _setup_model(self) -> None:
        super()._setup_model()
        self._attach()

    def set_env(self, env, force_reset: bool = True) -> None:
        super().set_env(env, force_reset)
        self._attach()

    def _attach(self) -> None:
        w = _find_wrapper(self.env)
        if w is None and self.env is not None:
            raise ValueError("WarmStartMPCPPO: the environment must be wrapped in PlanInObservation")
        if w is not None:
            w.attach(self.policy)

    @torch.no_grad()
    def act(self, obs: Tensor) -> Tensor:
        """Deterministic (mean) action ``(N, m)`` for the task's observations ``(N, obs_dim)``."""
        ext = self.policy.mlp_extractor
        o = obs.to(device=self.device, dtype=torch.float32)
        plan = self._eval_plan
        if plan is None or plan.shape[0] != o.shape[0]:
            plan = torch.zeros(o.shape[0], self.policy.horizon * ext.task.m, dtype=o.dtype, device=o.device)
        a, self._eval_plan = ext.act_and_plan(torch.cat([o, plan], -1))
        return a.clamp(-1.0, 1.0).to(device=obs.device, dtype=obs.dtype)

    def reset(self, done: Tensor | None = None) -> None:
        """Cold-start every plan (``done`` None) or those of the elements where ``done``."""
        plan = self._eval_plan
        if done is None or plan is None or tuple(done.shape) != (plan.shape[0],):
            self._eval_plan = None
        else:
            self._eval_plan = torch.where(done.to(plan.device)[:, None], 0.0, plan)


def make_warm_mpc_ppo(task: Task | str = "CartPoleSwingUp", *, num_envs: int = 8,
                      env_kwargs: dict | None = None, policy_kwargs: dict | None = None,
                      **ppo_kwargs) -> WarmStartMPCPPO:
    """A :class:`WarmStartMPCPPO` with an ``MPCActorCriticPolicy(warm_start=True)`` on
    ``PlanInObservation(SB3VecEnv(task, num_envs))`` (float32); arguments as
    :func:`learning.mpc_policy.make_mpc_ppo`."""
    from learning.sb3 import SB3VecEnv

    t = make_task(task)
    pk = dict(policy_kwargs or {})
    pk["task"], pk["warm_start"] = task, True
    horizon = pk.get("horizon") or DEFAULT_MPC_HORIZON.get(t.name, 20)
    pk["horizon"] = int(horizon)
    env = PlanInObservation(SB3VecEnv(t, num_envs, **(env_kwargs or {})), pk["horizon"], t.m)
    ppo_kwargs.setdefault("device", "cpu")
    return WarmStartMPCPPO(MPCActorCriticPolicy, env, policy_kwargs=pk, **ppo_kwargs)


def warm_start_setup(venv: VecEnv, task: Task, algo: str, policy,
                     policy_kwargs: dict) -> tuple[VecEnv, type]:
    """``(PlanInObservation(venv), WarmStartMPCPPO)`` for a policy built with ``warm_start=True``
    (:func:`learning.baselines.make_agent`); a ``ValueError`` for another algorithm or policy."""
    from learning._policy_io import policy_class

    cls = policy_class(PPO, policy) if isinstance(policy, str) else policy
    if str(algo).lower() != "ppo" or cls is not MPCActorCriticPolicy:
        raise ValueError("argument 'policy_kwargs': warm_start=True needs PPO with MPCActorCriticPolicy, "
                         f"got algo {algo!r}, policy {policy!r}")
    horizon = policy_kwargs.get("horizon") or DEFAULT_MPC_HORIZON.get(task.name, 20)
    return PlanInObservation(venv, int(horizon), task.m), WarmStartMPCPPO
