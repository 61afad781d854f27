"""Models of gymnasium environments the project did not write: what an MPC needs to act in them.

An RL agent learns a policy from the env's rewards; an MPC plans with a model instead.  An
:class:`EnvModel` is that model for one gymnasium id: the dynamics (a :class:`~controllers.dynamics.System`
in the env's units), the planning cost (the env's reward, negated, where it is smooth enough to plan
with), the map from the env's observation to the system's state, the action box and the planner's
settings.  ``knows`` states what the MPC is given that an RL agent is not (the model, and where the
cost differs from the reward).

:func:`env_model` looks one up by id (or from an env instance); :func:`register_env_model` adds one.
The shipped models:

========================  ===================================================================================
``Pendulum-v1``           :class:`controllers.systems.Pendulum` with Pendulum-v1's parameters (the rod
                          pendulum as an equivalent point mass, semi-implicit Euler, dt 0.05, the same as
                          :class:`learning.envs.PendulumSwingUp`); cost = the reward
                          ``φ² + 0.1 ω² + 0.001 u²`` with φ wrapped (:class:`~controllers.costs.
                          PeriodicQuadraticCost`), the last state's term 10 times (a value-to-go
                          stand-in); horizon 40.  Not modelled: the env clips ``|ω|`` to 8 rad/s.
``InvertedPendulum-v5``,  :class:`controllers.systems.MujocoSystem` of the env's own MjModel (its
``InvertedDoublePend``    ``frame_skip``, RK4); costs from the rewards (``learning._mujoco_models``: a
``ulum-v5``, ``Reacher``  quadratic about upright; the reward's penalties with a tip-height barrier in
``-v5``                   place of the alive bonus and the LQR cost-to-go at upright; the fingertip
                          distance, smoothed, and ``‖a‖²``).
``HalfCheetah-v5``        :class:`~controllers.systems.mujoco_system.MujocoSystem` of the env's own MjModel
                          (contacts); cost = minus the return exactly (``learning._mujoco_locomotion``:
                          the forward progress over the horizon, ``0.1 ‖a‖²``); planned by the sampling MPC
                          (:class:`learning.sampling_mpc.SamplingModelMPC`).
``MountainCarContinuous``  the env's dynamics exactly (:class:`learning._mountain_car.MountainCar`: clips,
``-v0``                   the inelastic left wall); cost = the reward's ``0.1 u²`` plus a terminal energy
                          deficit in place of the sparse +100 (:class:`~learning._mountain_car.
                          EnergyGoalCost`: pumping along the velocity is the least ``Σu²`` per joule).
========================  ===================================================================================

A model is checked against its env (:func:`check_model`): the spaces must be ``Box`` es, the action
dimension the system's ``m``, and the observation map must give ``(N, n)`` states.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from torch import Tensor

from learning.evaluate_env import check_box_env, env_id_of

__all__ = ["EnvModel", "env_model", "register_env_model", "ENV_MODELS", "check_model", "NEUTRAL_WRAPPERS"]


@dataclass(frozen=True, eq=False)
class EnvModel:
    """What an MPC needs to act in a gymnasium environment (module docstring).

    Attributes:
        env_id: the gymnasium id.
        system: the dynamics, ``step(x (*B, n), u (*B, m), t)`` in the env's units (one env step).
        cost: ``cost(horizon, dtype, device) -> Cost`` over ``horizon`` steps (``evaluate(x (*B, T+1, n),
            u (*B, T, m)) -> (*B,)``, :mod:`controllers.costs`).
        state_from_obs: ``(N, obs_dim) -> (N, n)`` observations to states (dtype and device kept).
        action_low, action_high: the env's action box ``(m,)``.
        obs_dim: the env's observation size (``None``: not checked), so that a policy refuses an
            observation of another width instead of reading its first columns.
        horizon, max_iter, random_starts, multistart, start_iter: the planner's defaults
            (:class:`learning.model_mpc.ModelMPC`; ``multistart=False``: one start, the previous plan;
            ``"start"``: the multi-start set at an episode's first step only; ``start_iter``: iterations of
            that first solve, ``None``: ``max_iter``).
        knows: what the MPC knows that an RL agent does not.
        options: ``ILQROptions`` overrides (e.g. tolerances for finite-difference Jacobians).
        planner: the MPC that ``"mpc"`` means on this env (:func:`learning.model_mpc.model_policy`):
            ``"ilqr"`` (:class:`~learning.model_mpc.ModelMPC`) or ``"sampling"``
            (:class:`~learning.sampling_mpc.SamplingModelMPC`, for contact-rich models and costs that are
            not smooth).
    """

    env_id: str
    system: Any
    cost: Callable[..., Any]
    state_from_obs: Callable[[Tensor], Tensor]
    action_low: tuple[float, ...]
    action_high: tuple[float, ...]
    obs_dim: int | None = None
    horizon: int = 30
    max_iter: int = 20
    random_starts: int = 0
    multistart: bool | str = True
    start_iter: int | None = None
    knows: str = ""
    options: dict[str, Any] = field(default_factory=dict)
    planner: str = "ilqr"

    @property
    def n(self) -> int:
        return int(self.system.n)

    @property
    def m(self) -> int:
        return int(self.system.m)


#: model factories by gymnasium id: ``factory(env or None) -> EnvModel``
ENV_MODELS: dict[str, Callable[[Any], EnvModel]] = {}


def register_env_model(env_id: str, factory: Callable[[Any], EnvModel]) -> None:
    """Register ``factory(env or None) -> EnvModel`` for ``env_id`` (replacing any earlier one)."""
    if not isinstance(env_id, str) or not callable(factory):
        raise TypeError("register_env_model: arguments must be an id (str) and a callable factory")
    ENV_MODELS[env_id] = factory


def _base_id(env_id: str) -> str:
    return env_id.split(":", 1)[-1]


def _unwrapped(env: Any) -> Any:
    return getattr(env, "unwrapped", env)


def env_model(env: Any) -> EnvModel:
    """The :class:`EnvModel` of a gymnasium id, ``Env`` or ``VectorEnv`` (checked against the env's spaces
    when an env is given).  An env without a registered model is a ``ValueError`` saying how to give one."""
    if isinstance(env, EnvModel):
        return env
    eid = env_id_of(env)
    if eid is None or _base_id(eid) not in ENV_MODELS:
        what = eid or type(_unwrapped(env)).__name__
        raise ValueError(f"env_model: no model is registered for {what!r} (known: "
                         f"{sorted(ENV_MODELS)}); an MPC on a foreign env needs a System, a cost and an "
                         "observation->state map: build an EnvModel and register_env_model(id, factory)")
    model = ENV_MODELS[_base_id(eid)](None if isinstance(env, str) else env)
    if not isinstance(env, str):
        check_model(model, env)
    return model


#: wrappers that change neither what the env observes nor what an action does (a model still fits)
NEUTRAL_WRAPPERS = ("TimeLimit", "OrderEnforcing", "PassiveEnvChecker", "RecordEpisodeStatistics",
                    "ClipAction", "RecordVideo", "HumanRendering", "RenderCollection")


def _first_env(env: Any):
    return env.envs[0] if isinstance(env, gym.vector.VectorEnv) and getattr(env, "envs", None) else env


def _check_built_as_registered(model: EnvModel, env: Any) -> None:
    """The env must be the registered one the model describes: no wrapper that changes observations or
    actions, no constructor arguments other than the registered defaults."""
    one, w = _first_env(env), _first_env(env)
    while isinstance(w, gym.Wrapper):
        if type(w).__name__ not in NEUTRAL_WRAPPERS:
            raise ValueError(f"env_model: the env is wrapped in {type(w).__name__}, which changes what "
                             f"the model of {model.env_id} sees or does; give the unwrapped env (or a model "
                             "of the wrapped one)")
        w = w.env
    spec = getattr(one, "spec", None)
    if spec is not None and spec.id in gym.registry:
        default = gym.registry[spec.id].kwargs or {}
        kwargs = dict(spec.kwargs or {})
        if isinstance(one, gym.vector.VectorEnv):  # gym.make_vec's own arguments (an AsyncVectorEnv's spec)
            for k in ("num_envs", "vectorization_mode", "vector_kwargs"):
                kwargs.pop(k, None)
            if all(getattr(w, "__name__", None) in NEUTRAL_WRAPPERS for w in kwargs.get("wrappers", ())):
                kwargs.pop("wrappers", None)
        changed = {k: v for k, v in kwargs.items() if default.get(k, v) != v or k not in default}
        if changed:
            raise ValueError(f"env_model: the env was made with {changed}, but the model of {model.env_id} "
                             "is for its registered defaults; build an EnvModel for these parameters")


def _check_time_step(model: EnvModel, env: Any) -> None:
    """The system's step must be the env's: ``system.dt`` equal to ``env.unwrapped.dt`` where both exist (a
    MuJoCo model with another ``opt.timestep`` or ``frame_skip`` plans a different env)."""
    one = _first_env(env)
    env_dt = getattr(getattr(one, "unwrapped", None), "dt", None)
    if env_dt is None and isinstance(one, gym.vector.VectorEnv):  # an AsyncVectorEnv: ask its workers
        try:
            env_dt = one.get_attr("dt")[0]
        except Exception:  # noqa: BLE001 - no dt to compare
            env_dt = None
    sys_dt = getattr(model.system, "dt", None)
    if isinstance(sys_dt, Tensor) and sys_dt.numel() == 1:
        sys_dt = float(sys_dt)
    if not all(isinstance(v, numbers.Real) and not isinstance(v, bool) for v in (env_dt, sys_dt)):
        return  # (numbers.Real: a numpy float32 dt is compared too)
    if not math.isclose(float(sys_dt), float(env_dt), rel_tol=1e-9, abs_tol=0.0):
        raise ValueError(f"env_model: the model of {model.env_id} steps dt = {float(sys_dt):g} s but the env "
                         f"steps dt = {float(env_dt):g} s (its MuJoCo time step x frame_skip); build the "
                         "system from this env (MujocoSystem.from_env) or with its time step")


def _clipped_action_space(env: Any):
    """The action space inside a ``ClipAction`` wrapper of ``env`` (or of its first sub-env), else ``None``:
    gymnasium 1.x's ``ClipAction`` widens the action space to ±inf and clips to the inner box, which is the
    box the model must match."""
    e = _first_env(env)
    while isinstance(e, gym.Wrapper):
        if isinstance(e, gym.wrappers.ClipAction):
            return e.env.action_space
        e = e.env
    return None


def check_model(model: EnvModel, env: Any) -> None:
    """A ``TypeError``/``ValueError`` naming the mismatch when ``model`` does not fit ``env``: its spaces
    (1-d ``Box`` es, the action dimension and bounds), the observation map's output shape, the time step
    (``system.dt`` against ``env.unwrapped.dt`` where both exist), and the env itself
    (:data:`NEUTRAL_WRAPPERS` only, the registered constructor arguments)."""
    vec = isinstance(env, gym.vector.VectorEnv)
    aspace = _clipped_action_space(env) or (env.single_action_space if vec else env.action_space)
    ospace = env.single_observation_space if vec else env.observation_space
    m = check_box_env(aspace, ospace, "env_model")
    if m != model.m:
        raise ValueError(f"env_model: the env has {m} actions but the model's system has m = {model.m}")
    lo, hi = np.asarray(aspace.low, dtype=np.float64), np.asarray(aspace.high, dtype=np.float64)
    if not (np.allclose(lo, model.action_low) and np.allclose(hi, model.action_high)):
        raise ValueError(f"env_model: the env's action box [{lo.tolist()}, {hi.tolist()}] differs from the "
                         f"model's [{list(model.action_low)}, {list(model.action_high)}] (a rescaling "
                         "wrapper?)")
    _check_built_as_registered(model, env)
    _check_time_step(model, env)
    if model.obs_dim is not None and tuple(ospace.shape) != (model.obs_dim,):
        raise ValueError(f"env_model: the env observes shape {tuple(ospace.shape)} but the model of "
                         f"{model.env_id} maps observations of size {model.obs_dim}")
    obs = torch.as_tensor(ospace.sample(), dtype=torch.float64).reshape(1, -1)
    x = model.state_from_obs(obs)
    if not isinstance(x, Tensor) or tuple(x.shape) != (1, model.n):
        got = tuple(x.shape) if isinstance(x, Tensor) else type(x).__name__
        raise ValueError(f"env_model: the observation map of {model.env_id} turns an observation of shape "
                         f"(1, {obs.shape[1]}) into {got}, expected (1, {model.n}) (the system's state)")


# ------------------------------------------------------------------------------------- Pendulum-v1


def _pendulum_state(obs: Tensor) -> Tensor:
    """``[cos φ, sin φ, ω]`` (φ = 0 upright) to the model's ``[θ, ω]`` (θ = φ + π, 0 hanging)."""
    return torch.stack([torch.atan2(-obs[..., 1], -obs[..., 0]), obs[..., 2]], -1)


def _pendulum_cost(horizon: int, dtype=torch.float64, device=None, terminal: float = 10.0):
    from controllers.costs import PeriodicQuadraticCost, QuadraticCost

    kw = dict(dtype=dtype, device=device)
    Q = torch.diag(torch.tensor([1.0, 0.1], **kw)).expand(horizon + 1, 2, 2).clone()
    Q[-1] *= terminal
    base = QuadraticCost(Q=Q, R=torch.tensor([[0.001]], **kw), x_ref=torch.tensor([math.pi, 0.0], **kw))
    return PeriodicQuadraticCost(base, torch.tensor([True, False], device=device))


def _pendulum_v1(env: Any = None) -> EnvModel:
    from learning.envs.pendulum import _gym_pendulum

    return EnvModel(
        env_id="Pendulum-v1", system=_gym_pendulum(), cost=_pendulum_cost, state_from_obs=_pendulum_state,
        action_low=(-2.0,), action_high=(2.0,), obs_dim=3, horizon=40, max_iter=20, random_starts=0,
        knows="the pendulum's equations of motion and parameters, and the reward as the planning cost")


register_env_model("Pendulum-v1", _pendulum_v1)


def _mountain_car_continuous(env: Any = None) -> EnvModel:
    from learning._mountain_car import mountain_car_model

    return mountain_car_model(env)


register_env_model("MountainCarContinuous-v0", _mountain_car_continuous)


def _mujoco(name: str, module: str = "_mujoco_models"):
    """A factory calling ``learning.<module>.<name>`` (imported on first use: MuJoCo is an extra)."""
    def factory(env: Any = None) -> EnvModel:
        import importlib

        return getattr(importlib.import_module(f"learning.{module}"), name)(env)

    return factory


register_env_model("InvertedPendulum-v5", _mujoco("inverted_pendulum_model"))
register_env_model("InvertedDoublePendulum-v5", _mujoco("inverted_double_pendulum_model"))
register_env_model("Reacher-v5", _mujoco("reacher_model"))
register_env_model("HalfCheetah-v5", _mujoco("half_cheetah_model", "_mujoco_locomotion"))
