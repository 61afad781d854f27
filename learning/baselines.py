"""RL baselines: stable-baselines3 PPO, SAC and TD3 on the batched task envs — or on a foreign gymnasium id
(``"Pendulum-v1"``, ``"InvertedPendulum-v5"``, ...) — with per-task defaults, learning curves measured by
:func:`learning.evaluate`, and weights saved in a form that loads safely.

* :data:`PPO_DEFAULTS` / :data:`SAC_DEFAULTS` / :data:`TD3_DEFAULTS`: hyperparameters by task name
  (``"*"`` the fallback);
  ``n_envs`` is the number of training environments, the rest are keyword arguments of the SB3 class.
  PendulumSwingUp uses rl-baselines3-zoo's tuned Pendulum-v1 settings (our task has Pendulum-v1's
  physics, reward and horizon; actions are normalized to ``[-1, 1]``).
* :func:`make_agent` builds an agent on an :class:`~learning.sb3.SB3VecEnv` (a natively batched env).
* Foreign gymnasium envs — a registered id outside the ``liecontrol/`` namespace (``"Pendulum-v1"``), an
  ``Env``, a ``VectorEnv`` or a factory of envs, made an :class:`~learning.env_source.EnvSource`: the
  agent trains on SB3's ``DummyVecEnv`` of ``Monitor``-wrapped envs — the ``Env`` given first (SB3 trains
  on the env it is given), then fresh copies — or on the ``VectorEnv`` given itself (its ``num_envs``
  sub-envs, through :class:`~learning.sb3.SB3VecEnv`); it is seeded as a task's (below), with the
  rl-baselines3-zoo's tuned hyperparameters where the zoo has the env's id
  (:mod:`learning.zoo_hyperparams`; the zoo's ``normalize: true`` is the hyperparameter ``normalize``:
  SB3's ``VecNormalize`` around the training env, :mod:`learning.sb3_normalize`), and is evaluated by
  :func:`learning.evaluate` on fresh copies of the env (actions in the env's units, observations normalized
  by the training statistics where ``normalize``), never on the env it trains on.  Only SB3's own policies
  (``"MlpPolicy"``) train there: the project's MPC policies need a task.
* TD3's ``noise_type`` (``"normal"`` / ``"ornstein-uhlenbeck"``) and ``noise_std`` are hyperparameters here
  (JSON, recordable) that :func:`make_agent` turns into SB3's ``action_noise``; a ``policy_kwargs`` entry
  of the hyperparameters is the policy's keyword arguments unless ``policy_kwargs`` is given; a string
  ``"lin_X"`` as ``learning_rate`` or ``clip_range`` is the zoo's linear schedule from ``X`` to 0.
* :func:`train` trains within a step budget and evaluates the deterministic policy every ``eval_every``
  environment steps on fixed held-out seeds (:func:`eval_seeds`; batched), giving a learning curve.
  It saves three files per run: ``model.zip`` (SB3's own format), ``policy.pt`` (the policy's plain
  ``state_dict``, loadable with ``torch.load(path, weights_only=True)``) and ``agent.json`` (algorithm,
  task, seed, hyperparameters, the policy by its registered name and its keyword arguments, curve,
  timings).
* :func:`load_agent` rebuilds the agent from ``policy.pt`` + ``agent.json`` (no pickle involved), for every
  policy the project trains: SB3's ``MlpPolicy`` and :class:`~learning.mpc_policy.MPCActorCriticPolicy`
  (others once :func:`register_policy` names them).  The policy is looked up by the name recorded, never
  imported from a path read from the file; its keyword arguments are JSON (:mod:`learning._policy_io`).
  It loads an SB3 ``.zip`` only when asked to explicitly (``trust_zip=True``): **SB3 zip files unpickle
  Python objects, so a model file from an untrusted source can execute arbitrary code when loaded.**

Seeds: training seed ``s`` seeds SB3 (torch, numpy, the action space) with ``s`` and gives training
environment ``i`` the env seed ``1000·s + i``; evaluation episodes use the env seeds ``10⁶ + j``, which
training never uses (for ``s < 1000`` and fewer than 1000 training environments).

TensorBoard: with ``tensorboard=True`` SB3 logs to ``out_dir/tb`` when the ``tensorboard`` package is
importable (it is not a dependency of this project); otherwise logging is skipped and
``TrainResult.notes`` says so.  The evaluation curve is logged there too (``eval/mean_return``,
``eval/success_rate``).

stable-baselines3 is imported only inside the functions.
"""

from __future__ import annotations

import copy
import json
import math
import time
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import torch

from learning._policy_io import POLICIES, decode, encode, policy_class, policy_name, register_policy
from learning.env_source import EnvSource, env_source, is_env_like
from learning.envs.single import int_arg, make_task
from learning.envs.task import Task
from learning.sb3_normalize import agent_of, load_obs_rms, save_obs_rms, wrap_normalize

__all__ = ["ALGOS", "PPO_DEFAULTS", "SAC_DEFAULTS", "TD3_DEFAULTS", "DEFAULT_BUDGETS", "FOREIGN_BUDGETS",
           "hyperparams", "default_budget", "is_foreign_id",
           "eval_seeds", "train_env_seed", "make_agent", "train", "TrainResult", "load_agent",
           "save_agent", "read_agent_meta", "steps_to_match", "mean_curve", "tensorboard_available",
           "EVAL_SEED0", "register_policy"]

ALGOS = ("ppo", "sac", "td3")

#: first env seed of the held-out evaluation episodes
EVAL_SEED0 = 10**6
#: training environments of training seed ``s`` use the env seeds ``TRAIN_SEED_STRIDE·s + i``
TRAIN_SEED_STRIDE = 1000

#: PPO hyperparameters by task name (``"*"``: fallback); ``n_envs`` = training environments
PPO_DEFAULTS: dict[str, dict[str, Any]] = {
    # rl-baselines3-zoo's tuned Pendulum-v1 settings (reported there: -172 ± 104 after 1e5 steps)
    "PendulumSwingUp": dict(n_envs=4, n_steps=1024, batch_size=64, gae_lambda=0.95, gamma=0.9, n_epochs=10,
                            ent_coef=0.0, learning_rate=1e-3, clip_range=0.2, use_sde=True,
                            sde_sample_freq=4),
    # reward in [0, 1] per step over 200 steps: a longer discount than the pendulum's
    "CartPoleSwingUp": dict(n_envs=8, n_steps=256, batch_size=128, gae_lambda=0.95, gamma=0.98, n_epochs=10,
                            ent_coef=0.0, learning_rate=3e-4, clip_range=0.2, use_sde=True,
                            sde_sample_freq=4),
    "*": dict(n_envs=8, n_steps=256, batch_size=128, gae_lambda=0.95, gamma=0.98, n_epochs=10,
              ent_coef=0.0, learning_rate=3e-4, clip_range=0.2),
}

#: SAC hyperparameters by task name (``"*"``: fallback); unnamed ones are SB3's defaults
SAC_DEFAULTS: dict[str, dict[str, Any]] = {
    # rl-baselines3-zoo's tuned Pendulum-v1 settings (reported there: -157 ± 89 after 2e4 steps)
    "PendulumSwingUp": dict(n_envs=1, learning_rate=1e-3),
    "CartPoleSwingUp": dict(n_envs=1, learning_rate=1e-3, gamma=0.98),
    "*": dict(n_envs=1, learning_rate=1e-3, gamma=0.98),
}

#: TD3 hyperparameters by task name (``"*"``: fallback): SAC's learning rate and discount, Gaussian
#: exploration noise 0.1 (the zoo's default for TD3)
TD3_DEFAULTS: dict[str, dict[str, Any]] = {
    "*": dict(n_envs=1, learning_rate=1e-3, gamma=0.98, noise_type="normal", noise_std=0.1),
}

#: default training budgets (environment steps per training seed) by task name (TD3: SAC's budget),
#: chosen so that ``liecontrol compare TASK`` with 3 seeds finishes in at most about 15 min on a loaded
#: 2-core CPU (SAC does one gradient step per environment step: 25-60 steps/s there; PPO 700-1300 steps/s)
DEFAULT_BUDGETS: dict[str, dict[str, int]] = {
    # PPO matched the MPC's success by ~29k steps in every seed (measured); rl-zoo's figure is at 1e5
    "PendulumSwingUp": {"ppo": 60_000, "sac": 5_000},
    "CartPoleSwingUp": {"ppo": 100_000, "sac": 6_000},
    "*": {"ppo": 50_000, "sac": 4_000},
}

#: default training budgets on foreign gymnasium ids (``"*"``: fallback), a few minutes per agent on a
#: loaded 2-core CPU; the zoo's own budgets are :data:`learning.zoo_hyperparams.ZOO_TIMESTEPS` (Pendulum-v1:
#: PPO 1e5, SAC and TD3 2e4 — TD3's first 10⁴ steps there are random actions, fast, before any update)
FOREIGN_BUDGETS: dict[str, dict[str, int]] = {
    "Pendulum-v1": {"ppo": 60_000, "sac": 5_000, "td3": 15_000},
    "MountainCarContinuous-v0": {"ppo": 20_000, "sac": 5_000, "td3": 5_000},
    # the zoo's SAC and TD3 start learning after 10⁴ random steps here
    "HalfCheetah-v5": {"ppo": 50_000, "sac": 15_000, "td3": 15_000},
    "*": {"ppo": 50_000, "sac": 5_000, "td3": 5_000},
}


def _algo(algo: str) -> str:
    a = str(algo).lower()
    if a not in ALGOS:
        raise ValueError(f"argument 'algo' must be one of {list(ALGOS)}, got {algo!r}")
    return a


def is_foreign_id(task: Any) -> bool:
    """Whether ``task`` is a registered gymnasium id that is not one of the project's tasks."""
    from learning.evaluate_env import is_foreign

    return isinstance(task, str) and is_foreign(task)


def _target(task: Any, where: str) -> Task | EnvSource:
    """A :class:`Task`, or an :class:`~learning.env_source.EnvSource` of a foreign gymnasium id, ``Env``,
    ``VectorEnv`` or factory."""
    if isinstance(task, EnvSource) or is_foreign_id(task) or is_env_like(task):
        return env_source(task, where)
    return make_task(task)


def _name(target: Task | EnvSource) -> str:
    return target.name


def hyperparams(algo: str, task: Any) -> dict[str, Any]:
    """A copy of the default hyperparameters of ``algo`` on ``task`` (its name's entry, else ``"*"``; a
    foreign gymnasium env: the rl-baselines3-zoo's for its id,
    :func:`learning.zoo_hyperparams.zoo_hyperparams`)."""
    a = _algo(algo)
    target = _target(task, "hyperparams")
    if isinstance(target, EnvSource):
        from learning.zoo_hyperparams import zoo_hyperparams

        return zoo_hyperparams(a, target.name)[0]
    table = {"ppo": PPO_DEFAULTS, "sac": SAC_DEFAULTS, "td3": TD3_DEFAULTS}[a]
    return copy.deepcopy(table.get(target.name, table["*"]))


def default_budget(algo: str, task: Any) -> int:
    """Default training budget (environment steps) of ``algo`` on ``task`` (:data:`DEFAULT_BUDGETS`, TD3
    taking SAC's where a task names none; a foreign id: :data:`FOREIGN_BUDGETS`)."""
    a = _algo(algo)
    target = _target(task, "default_budget")
    if isinstance(target, EnvSource):
        return int(FOREIGN_BUDGETS.get(target.name, FOREIGN_BUDGETS["*"])[a])
    row = DEFAULT_BUDGETS.get(target.name, DEFAULT_BUDGETS["*"])
    return int(row.get(a, row["sac"]))


def eval_seeds(episodes: int) -> list[int]:
    """The env seeds of ``episodes`` held-out evaluation episodes."""
    return [EVAL_SEED0 + j for j in range(int(episodes))]


def train_env_seed(seed: int) -> int:
    """The env seed of training environment 0 for training seed ``seed`` (environment ``i``: ``+ i``)."""
    return TRAIN_SEED_STRIDE * int(seed)


def tensorboard_available() -> bool:
    """Whether SB3 can log to TensorBoard here (the ``tensorboard`` package is importable)."""
    try:
        from stable_baselines3.common.logger import SummaryWriter
    except ImportError:
        return False
    return SummaryWriter is not None


def _sb3_class(algo: str):
    from stable_baselines3 import PPO, SAC, TD3

    return {"ppo": PPO, "sac": SAC, "td3": TD3}[_algo(algo)]


def _schedule(v: Any) -> Any:
    """The zoo's ``"lin_X"`` as SB3's linear schedule from ``X`` (progress 1) to 0; other values as is."""
    if isinstance(v, str) and v.startswith("lin_"):
        x = float(v[4:])
        return lambda progress_remaining: progress_remaining * x
    return v


def _sb3_kwargs(kw: dict[str, Any], action_space) -> dict[str, Any]:
    """Hyperparameters as SB3's class takes them: ``noise_type``/``noise_std`` -> ``action_noise``, ``lin_``
    schedules -> callables (module docstring)."""
    kw = dict(kw)
    noise_type, noise_std = kw.pop("noise_type", None), kw.pop("noise_std", None)
    if noise_type is not None:
        from stable_baselines3.common.noise import NormalActionNoise, OrnsteinUhlenbeckActionNoise

        m = int(np.prod(action_space.shape))
        sigma = float(0.1 if noise_std is None else noise_std) * np.ones(m)
        kinds = {"normal": NormalActionNoise, "ornstein-uhlenbeck": OrnsteinUhlenbeckActionNoise}
        if noise_type not in kinds:
            raise ValueError(f"hyperparameter 'noise_type' must be one of {sorted(kinds)}, "
                             f"got {noise_type!r}")
        kw["action_noise"] = kinds[noise_type](mean=np.zeros(m), sigma=sigma)
    elif noise_std is not None:
        raise ValueError("hyperparameter 'noise_std' given without 'noise_type'")
    for k in ("learning_rate", "clip_range"):
        if k in kw:
            kw[k] = _schedule(kw[k])
    return kw


def make_agent(algo: str, task: Any, seed: int = 0, num_envs: int | None = None,
               tensorboard_log: str | Path | None = None, device: str = "cpu",
               params: dict[str, Any] | None = None, policy: Any = "MlpPolicy",
               policy_kwargs: dict[str, Any] | None = None):
    """A fresh SB3 agent (``PPO``, ``SAC`` or ``TD3``, ``MlpPolicy``) on ``num_envs`` batched training
    environments of ``task`` (an :class:`~learning.sb3.SB3VecEnv` in a ``VecMonitor``; a foreign gymnasium
    env: a ``DummyVecEnv`` of ``Monitor``-wrapped envs — the ``Env`` given first, then copies — or the
    ``VectorEnv`` given, module docstring).

    Args:
        algo: ``"ppo"``, ``"sac"`` or ``"td3"``.
        task: a :class:`Task` or its name, or a foreign gymnasium env: a registered id, an ``Env``, a
            ``VectorEnv`` or a factory of envs (module docstring).
        seed: training seed (module docstring for the env seeds it implies).
        num_envs: training environments (default: the hyperparameters' ``n_envs``; a ``VectorEnv`` given:
            its ``num_envs``, and another value is a ``ValueError``).
        tensorboard_log: folder for SB3's TensorBoard logs (needs the ``tensorboard`` package).
        device: torch device of the networks.
        params: hyperparameters (default :func:`hyperparams`); ``n_envs`` is taken out of them, a
            ``policy_kwargs`` entry is used when ``policy_kwargs`` is ``None``.
        policy, policy_kwargs: SB3's policy (class or name) and its arguments, e.g.
            :class:`learning.mpc_policy.MPCActorCriticPolicy` with ``{"task": task}``; with
            ``"warm_start": True`` (PPO only) the env is wrapped in
            :class:`learning.mpc_warmstart.PlanInObservation` and the agent is a
            :class:`~learning.mpc_warmstart.WarmStartMPCPPO`.
    """
    from stable_baselines3.common.vec_env import VecMonitor

    from learning.sb3 import SB3VecEnv

    task = _target(task, "make_agent")
    kw = hyperparams(algo, task) if params is None else copy.deepcopy(dict(params))
    n = (int_arg(kw.pop("n_envs", 1), "params['n_envs']", "make_agent") if num_envs is None
         else int_arg(num_envs, "num_envs", "make_agent"))
    kw.pop("n_envs", None)
    algo_cls = _sb3_class(algo)
    if isinstance(task, EnvSource):  # a foreign gymnasium env
        ours = (policy in POLICIES if isinstance(policy, str)
                else not getattr(policy, "__module__", "").startswith("stable_baselines3"))
        if ours or (policy_kwargs or {}).get("warm_start"):
            raise ValueError(f"make_agent: on the gymnasium env {task.name!r} only SB3's own policies train "
                             f"(e.g. 'MlpPolicy'), got policy {policy!r}; the project's MPC policies need a "
                             "task")
        env = _training_env(task, num_envs if task.is_vector else n)
    else:
        venv = SB3VecEnv(task, n)
        if isinstance(policy, str) and policy in POLICIES:  # a registered name (SB3 knows only its aliases)
            policy = policy_class(algo_cls, policy)
        if (policy_kwargs or {}).get("warm_start"):  # the MPC head's plan rides in the observation
            from learning.mpc_warmstart import warm_start_setup

            venv, algo_cls = warm_start_setup(venv, task, algo, policy, policy_kwargs)
        env = VecMonitor(venv)
    if policy_kwargs is not None:
        kw["policy_kwargs"] = dict(policy_kwargs)
    env = wrap_normalize(env, kw.pop("normalize", False), kw.get("gamma", 0.99))
    kw = _sb3_kwargs(kw, env.action_space)
    model = algo_cls(policy, env, seed=int(seed), device=device,
                     tensorboard_log=None if tensorboard_log is None else str(tensorboard_log),
                     verbose=0, **kw)
    model.env.seed(train_env_seed(seed))  # SB3 seeded the envs with `seed`; ours are disjoint per seed
    return model


@dataclass
class TrainResult:
    """What :func:`train` did: the trained ``model`` (where the hyperparameters ``normalize``, a
    :class:`~learning.sb3_normalize.NormalizedModel`: it acts on raw observations), its learning curve
    (``steps``: environment steps at each evaluation, ``returns``: mean evaluation return, ``success``:
    success rate), the wall time of training alone (evaluations excluded) and of the evaluations, the saved
    files and notes."""

    model: Any
    algo: str
    task: str
    seed: int
    steps: list[int]
    returns: list[float]
    success: list[float]
    train_time_s: float
    eval_time_s: float
    num_timesteps: int
    params: dict[str, Any]
    paths: dict[str, str] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    #: the policy's keyword arguments as :func:`train` was given them (recorded in ``agent.json``)
    policy_kwargs: dict[str, Any] = field(default_factory=dict)

    def curve(self) -> dict[str, list]:
        return {"steps": list(self.steps), "returns": list(self.returns), "success": list(self.success)}


def _curve_point(model, task: Task | EnvSource, seeds: list[int]) -> tuple[float, float]:
    """``(mean return, success rate)``; the success rate is NaN on an env that defines no success."""
    from learning.evaluate import evaluate

    r = evaluate(model, task, seeds=seeds, num_envs=len(seeds), dtype=torch.float32, progress=False,
                 timing_batch1=False)
    succ = float(np.mean(r.success)) if r.meta.get("success_defined", True) else math.nan
    return float(np.mean(r.returns)), succ


def _foreign_notes(algo: str, src: EnvSource, kw: dict[str, Any], zoo: bool,
                   num_envs: int | None) -> list[str]:
    """What :func:`train` says of a foreign env: the hyperparameters' source, the zoo's ``VecNormalize``
    (applied, or left out by the ``params`` given), and which envs train and evaluate; a ``VectorEnv`` given
    sets ``kw["n_envs"]``."""
    from learning.zoo_hyperparams import ZOO_HP_SOURCE, ZOO_NORMALIZE, zoo_hyperparams

    notes = []
    if zoo:
        note = zoo_hyperparams(algo, src.name)[1]
        notes.append(note or f"{algo} hyperparameters on {src.name}: {ZOO_HP_SOURCE}")
    if kw.get("normalize"):
        notes.append(f"{algo} trains on VecNormalize (normalize: {json.dumps(kw['normalize'])}, as the zoo "
                     "does): observations and rewards normalized by running statistics; its evaluations "
                     "normalize observations by the training statistics and sum the env's own rewards")
    elif algo in ZOO_NORMALIZE.get(src.name, ()):
        notes.append(f"the zoo trains {algo} on {src.name} with VecNormalize (normalize: true); not applied "
                     "here (the hyperparameters given have no 'normalize'): the agent sees raw observations "
                     "and rewards")
    if src.is_vector:
        k = src.instance.num_envs
        if num_envs is not None and int(num_envs) != k:
            raise ValueError(f"train: argument 'num_envs' is {num_envs} but the VectorEnv given has {k} "
                             "sub-envs (the agent trains on it as it is)")
        if int(kw.get("n_envs", k)) != k:
            notes.append(f"{algo} trains on the {k} sub-envs of the VectorEnv given (the hyperparameters "
                         f"name n_envs={kw['n_envs']})")
        kw["n_envs"] = k
        notes.append(f"{algo} trains on the VectorEnv given; its evaluations run on fresh copies of one "
                     f"sub-env ({src.how})")
    elif src.instance is not None:
        notes.append(f"{algo} trains on the env given (and copies of it, {src.how}, where it has more "
                     "than one training env); its evaluations run on fresh copies")
    return notes


def train(algo: str, task: Any, budget_steps: int, seed: int = 0, eval_every: int | None = None,
          eval_episodes: int = 16, out_dir: str | Path | None = None, *, num_envs: int | None = None,
          params: dict[str, Any] | None = None, tensorboard: bool = True, device: str = "cpu",
          log=None, policy: Any = "MlpPolicy", policy_kwargs: dict[str, Any] | None = None,
          max_train_s: float | None = None) -> TrainResult:
    """Train ``algo`` on ``task`` for ``budget_steps`` environment steps and record its learning curve.

    The deterministic policy is evaluated (:func:`learning.evaluate`, all ``eval_episodes`` episodes in
    one batch, seeds :func:`eval_seeds`) before training, every ``eval_every`` steps (default: a tenth of
    the budget; at the start of the first rollout past each multiple, i.e. after the updates of the
    previous one) and at the end (on a foreign gymnasium id: on the id, the success rate NaN unless the env
    gives ``info["is_success"]``).  A PPO budget below one rollout (``n_steps · n_envs``) shortens the rollout
    to fit.  SB3 counts steps per batch of environments, so an evaluation happens at
    the first multiple of ``num_envs`` past each ``k·eval_every``, and PPO ends at its first full rollout
    past the budget.  With ``out_dir``, ``model.zip``, ``policy.pt`` and ``agent.json`` are written there
    (:func:`save_agent`) and TensorBoard logs go to ``out_dir/tb`` when possible.  ``log(str)`` receives a
    line per evaluation.  ``policy``/``policy_kwargs`` go to :func:`make_agent`.  With ``max_train_s``
    training also stops once its own wall time (evaluations excluded) exceeds that many seconds (an
    equal-wall-time comparison); ``num_timesteps`` then tells how far it got.

    With ``out_dir``, everything :func:`load_agent` needs must be recordable, and is checked before
    training: ``policy`` an SB3 alias or a registered policy (:func:`register_policy`), ``params`` and
    ``policy_kwargs`` JSON-encodable (:mod:`learning._policy_io`) — else a ``TypeError`` naming it.
    """
    from stable_baselines3.common.callbacks import BaseCallback

    algo = _algo(algo)
    task = _target(task, "train")
    name = _name(task)
    budget_steps = int_arg(budget_steps, "budget_steps", "train")
    every = max(1, budget_steps // 10) if eval_every is None else int_arg(eval_every, "eval_every", "train")
    seeds = eval_seeds(int_arg(eval_episodes, "eval_episodes", "train"))
    kw = hyperparams(algo, task) if params is None else dict(params)
    if num_envs is not None:
        kw["n_envs"] = int_arg(num_envs, "num_envs", "train")
    notes: list[str] = []
    if isinstance(task, EnvSource):
        check_episode_limit(task, "train")
        notes += _foreign_notes(algo, task, kw, params is None, num_envs)
    if algo == "ppo":
        n_envs, n_steps = int(kw.get("n_envs", 1)), int(kw.get("n_steps", 2048))
        if n_envs * n_steps > budget_steps:  # a budget below one rollout: shorter rollouts, not overshoot
            kw["n_steps"] = max(2, budget_steps // n_envs)
            kw["batch_size"] = min(int(kw.get("batch_size", 64)), kw["n_steps"] * n_envs)
            notes.append(f"PPO rollout shortened to n_steps={kw['n_steps']} to fit the budget")
    if algo != "ppo" and int(kw.get("learning_starts", 100)) >= budget_steps:
        notes.append(f"{algo}: learning_starts={int(kw.get('learning_starts', 100))} >= the budget of "
                     f"{budget_steps} steps: the agent took random actions only and was never updated")
    if out_dir is not None:  # what save_agent will record: fail now, not after training
        policy_name(_sb3_class(algo), policy)
        encode(kw, "train: argument 'params'")
        encode(policy_kwargs or {}, "train: argument 'policy_kwargs'")
    tb = None
    if tensorboard and out_dir is not None:
        if tensorboard_available():
            tb = Path(out_dir) / "tb"
        else:
            notes.append("TensorBoard logging skipped: the 'tensorboard' package is not installed")
    model = make_agent(algo, task, seed, tensorboard_log=tb, device=device, params=kw, policy=policy,
                       policy_kwargs=policy_kwargs)
    agent = agent_of(model)  # acts on raw observations (normalized inside where the env is VecNormalize)
    curve: dict[str, list] = {"steps": [], "returns": [], "success": []}
    clock = {"eval": 0.0}

    def point(steps: int) -> None:
        t0 = time.perf_counter()
        ret, succ = _curve_point(agent, task, seeds)
        clock["eval"] += time.perf_counter() - t0
        curve["steps"].append(int(steps))
        curve["returns"].append(ret)
        curve["success"].append(succ)
        if log is not None:
            log(f"{name} {algo} seed {seed}: {steps} steps, eval return {ret:.1f}, success {succ:.2f}")

    class _Curve(BaseCallback):
        def __init__(self):
            super().__init__()
            self.next = every

        def _on_rollout_start(self) -> None:
            # here the updates that follow the previous rollout are done: the policy is the one trained
            # on exactly num_timesteps steps (evaluating in _on_step would see PPO's pre-update policy)
            if self.num_timesteps >= self.next:
                point(self.num_timesteps)
                self.logger.record("eval/mean_return", curve["returns"][-1])
                self.logger.record("eval/success_rate", curve["success"][-1])
                while self.next <= self.num_timesteps:
                    self.next += every

        def _on_step(self) -> bool:
            if max_train_s is None:
                return True
            return time.perf_counter() - clock["start"] - (clock["eval"] - clock["e0"]) < max_train_s

    point(0)
    e0, t0 = clock["eval"], time.perf_counter()
    clock["start"], clock["e0"] = t0, e0
    model.learn(total_timesteps=budget_steps, callback=_Curve(), tb_log_name=f"{algo}_seed{seed}")
    wall = time.perf_counter() - t0
    train_time = wall - (clock["eval"] - e0)  # the evaluations during training are not training time
    if curve["steps"][-1] == model.num_timesteps:  # evaluated before the last update: again, after it
        for k in curve:
            curve[k].pop()
    point(model.num_timesteps)
    res = TrainResult(model=agent, algo=algo, task=name, seed=int(seed), steps=curve["steps"],
                      returns=curve["returns"], success=curve["success"], train_time_s=train_time,
                      eval_time_s=clock["eval"], num_timesteps=int(model.num_timesteps), params=kw,
                      notes=notes, policy_kwargs=dict(policy_kwargs or {}))
    if out_dir is not None:
        res.paths = save_agent(res, out_dir, budget_steps=budget_steps, eval_episodes=eval_episodes)
    return res


def save_agent(res: TrainResult, out_dir: str | Path, **extra) -> dict[str, str]:
    """Write ``model.zip`` (SB3's format), ``policy.pt`` (``model.policy.state_dict()``, plain tensors) and
    ``agent.json`` (everything :func:`load_agent` needs to rebuild the agent — the policy by its registered
    name, its keyword arguments ``res.policy_kwargs`` — plus the curve and timings) into ``out_dir``;
    returns their paths.  A policy or argument that cannot be recorded is a ``TypeError`` (before any file
    is written)."""
    from learning.evaluate import jsonable

    algo_cls = _sb3_class(res.algo)
    rebuild = {"policy": policy_name(algo_cls, type(res.model.policy)),
               "policy_kwargs": encode(res.policy_kwargs, "save_agent: policy_kwargs"),
               "params": encode(res.params, "save_agent: params")}
    d = Path(out_dir)
    d.mkdir(parents=True, exist_ok=True)
    paths = {"zip": str(d / "model.zip"), "pt": str(d / "policy.pt"), "json": str(d / "agent.json")}
    res.model.save(paths["zip"])
    rms = save_obs_rms(res.model, d)  # VecNormalize's observation statistics, plain tensors
    if rms is not None:
        paths["obs_rms"] = rms
    state = {k: v.detach().cpu().clone() for k, v in res.model.policy.state_dict().items()}
    torch.save(state, paths["pt"])
    meta = {"algo": res.algo, "task": res.task, "seed": res.seed, **rebuild,
            "spaces": _spaces_record(res.model), "num_timesteps": res.num_timesteps,
            "train_time_s": res.train_time_s, "eval_time_s": res.eval_time_s, "curve": res.curve(),
            "notes": res.notes, **extra}
    Path(paths["json"]).write_text(json.dumps(jsonable(meta), indent=1, allow_nan=False) + "\n")
    return paths


def _spaces_record(model) -> dict[str, Any]:
    """The agent's observation and action spaces as JSON (a ``Box``: shape, dtype, bounds; else its text),
    which :func:`load_agent` checks an agent of a foreign env against."""
    from learning.evaluate import jsonable

    def one(sp):
        if isinstance(getattr(sp, "low", None), np.ndarray):
            return jsonable({"shape": list(sp.shape), "dtype": str(sp.dtype), "low": sp.low, "high": sp.high})
        return {"text": str(sp)}

    return {"observation": one(model.observation_space), "action": one(model.action_space)}


def read_agent_meta(path: str | Path) -> dict[str, Any]:
    """The ``agent.json`` next to (or in) ``path``."""
    p = Path(path)
    meta = (p if p.is_dir() else p.parent) / "agent.json"
    if not meta.is_file():
        raise FileNotFoundError(f"no agent.json at {meta} (written by learning.baselines.train)")
    return json.loads(meta.read_text())


#: the JSON types of the ``agent.json`` entries :func:`load_agent` reads, and of the hyperparameters and
#: policy keyword arguments the project records (others are passed on unchecked); ``None``: null allowed
_META_TYPES: dict[str, tuple] = {"algo": (str,), "task": (str,), "params": (dict,), "policy": (str,),
                                 "policy_kwargs": (dict, None), "seed": (int,), "num_timesteps": (int,)}
_NUM = (int, float)
_PARAM_TYPES: dict[str, tuple] = {
    **dict.fromkeys(("n_envs", "n_steps", "batch_size", "n_epochs", "sde_sample_freq", "buffer_size",
                     "learning_starts", "gradient_steps", "target_update_interval", "train_freq"), (int,)),
    **dict.fromkeys(("gamma", "gae_lambda", "tau", "max_grad_norm", "vf_coef", "noise_std"), _NUM),
    **dict.fromkeys(("learning_rate", "clip_range"), (*_NUM, str)), "noise_type": (str,),
    "policy_kwargs": (dict,),
    **dict.fromkeys(("use_sde", "normalize_advantage"), (bool,)), "normalize": (bool, dict)}
_POLICY_KWARG_TYPES: dict[str, tuple] = {
    "net_arch": (list, dict), "cost_net_arch": (list, None), "activation_fn": (type,),
    "optimizer_class": (type,), "optimizer_kwargs": (dict, None), "ortho_init": (bool,), "use_sde": (bool,),
    "wrap_angles": (bool,),
    "share_features_extractor": (bool,), "log_std_init": _NUM, "log_scale_range": _NUM, "horizon": (int,),
    "max_iter": (int,), "task": (str,), "grad": (str,), "terminal_factor": (*_NUM, None),
    "per_step": (bool,), "warm_start": (bool,), "compile": (bool,)}


def _check_types(d: dict, types: dict[str, tuple], where: str) -> None:
    """Each entry of ``d`` named in ``types`` has one of its types (a bool is not a number; ``None`` allows
    null) — else a ``ValueError`` naming ``where`` and the key."""
    for key, allowed in types.items():
        if key not in d:
            continue
        v = d[key]
        ok = (v is None and None in allowed) or any(
            t is not None and isinstance(v, t) and (t is bool or not isinstance(v, bool)) for t in allowed)
        if not ok:
            names = " or ".join("null" if t is None else t.__name__ for t in allowed)
            raise ValueError(f"load_agent: {where}: key {key!r} must be {names}, got {type(v).__name__} "
                             f"{v!r} (the file was edited, or not written by learning.baselines)")


def _checked_meta(meta: Any, path: Path) -> dict[str, Any]:
    """``agent.json``'s content with its entries' types checked, ``params``/``policy_kwargs`` decoded."""
    if not isinstance(meta, dict):
        raise ValueError(f"load_agent: {path} must hold a JSON object, got {type(meta).__name__}")
    for key in ("algo", "task", "params"):
        if key not in meta:
            raise ValueError(f"load_agent: {path}: key {key!r} is missing")
    _check_types(meta, _META_TYPES, str(path))
    meta = dict(meta, params=decode(meta["params"]), policy_kwargs=decode(meta.get("policy_kwargs") or {}))
    _check_types(meta["params"], _PARAM_TYPES, f"{path} ['params']")
    _check_types(meta["policy_kwargs"], _POLICY_KWARG_TYPES, f"{path} ['policy_kwargs']")
    return meta


def load_agent(path: str | Path, algo: str | None = None, task: Task | str | None = None, *,
               trust_zip: bool = False, device: str = "cpu"):
    """The agent saved by :func:`train` in ``path`` (its folder or its ``policy.pt``), rebuilt safely.

    The agent is built afresh by :func:`make_agent` from the hyperparameters, the policy (looked up by the
    name recorded: an SB3 alias or a :func:`register_policy` entry) and its keyword arguments in
    ``agent.json``, and its policy weights are read with ``torch.load(..., weights_only=True)``: plain
    tensors, no code runs.  A file written before policies were recorded holds an ``MlpPolicy``.  An agent
    made on a foreign gymnasium env (``task`` in ``agent.json`` is its id, or its class's name) is rebuilt on
    copies of it (``task``: the env, a factory or its id; needed where it has no registered id).

    ``path`` may instead name an SB3 ``.zip``; it is loaded only with ``trust_zip=True``.  **Warning:**
    SB3 zip files contain pickled Python objects that ``load`` unpickles, so a model file from an
    untrusted source can execute arbitrary code on your machine — load only zips you made yourself.
    ``algo`` (and ``task``) are needed for a zip without an ``agent.json`` beside it; a zip whose
    ``agent.json`` names ``normalize`` is handed out with the ``obs_rms.pt`` beside it (a
    :class:`~learning.sb3_normalize.NormalizedModel`).

    ``agent.json`` is checked before anything is built: an entry of the wrong JSON type (``params`` or
    ``policy_kwargs`` not an object, ``seed`` not an int, a recorded hyperparameter or policy argument of the
    wrong type, e.g. ``n_steps: "32"``), hyperparameters or policy arguments that SB3 or the policy refuse,
    and weights that do not fit the policy described are a ``ValueError`` naming the file and the key.  An
    agent of a foreign env is also checked against the env given: its observation and action spaces must
    be those recorded (``agent.json``'s ``spaces``; the same id built with other wrappers or arguments is a
    ``ValueError``; files written before spaces were recorded are not checked).
    """
    p = Path(path)
    if p.suffix == ".zip":
        if not trust_zip:
            raise ValueError(f"load_agent: refusing to load the SB3 zip {p} without trust_zip=True: SB3 "
                             "unpickles objects from it, which can execute code; load the safe policy.pt "
                             "instead, or pass trust_zip=True for a file you made yourself")
        if algo is None:
            algo = read_agent_meta(p)["algo"]
        env = None if task is None else _one_env(_target(task, "load_agent"))
        model = _sb3_class(algo).load(str(p), env=env, device=device)
        meta_path = p.parent / "agent.json"  # trained with normalize: the zip's policy wants normalized obs
        norm = (_checked_meta(read_agent_meta(p), meta_path)["params"].get("normalize")
                if meta_path.is_file() else None)
        return load_obs_rms(model, p.parent, norm) if norm else model
    pt = p / "policy.pt" if p.is_dir() else p
    meta_path = pt.parent / "agent.json"
    meta = _checked_meta(read_agent_meta(pt), meta_path)
    algo = meta["algo"] if algo is None else _algo(algo)
    if algo != meta["algo"]:
        raise ValueError(f"load_agent: {pt} holds a {meta['algo']} agent, not {algo}")
    try:
        task = _target(meta["task"] if task is None else task, "load_agent")
    except ValueError as e:
        if task is not None:
            raise
        raise ValueError(f"load_agent: {pt} was trained on {meta['task']!r}, neither a task nor a registered "
                         "gymnasium id: pass task= the env (or a factory of it)") from e
    if _name(task) != meta["task"]:
        raise ValueError(f"load_agent: {pt} was trained on {meta['task']}, not {_name(task)}")
    if isinstance(task, EnvSource):  # rebuilt on copies: the env given is not stepped
        task = task.detached()
    policy_label = meta.get("policy", "MlpPolicy")
    policy = policy_class(_sb3_class(algo), policy_label)
    pk = meta["policy_kwargs"]
    try:  # values of the right type may still be out of range, or keys unknown to SB3 / the policy
        model = make_agent(algo, task, meta.get("seed", 0), device=device, params=meta["params"],
                           policy=policy, policy_kwargs=pk or None)
    except (TypeError, ValueError, AssertionError, KeyError) as e:
        raise ValueError(f"load_agent: {meta_path}: keys 'params' / 'policy_kwargs' do not build a {algo} "
                         f"agent with the policy {policy_label!r}: {type(e).__name__}: {e}") from e
    state = torch.load(pt, map_location=device, weights_only=True)
    try:
        model.policy.load_state_dict(state)
    except RuntimeError as e:
        raise ValueError(f"load_agent: the weights in {pt} do not fit the policy that {meta_path} describes "
                         f"(keys 'policy' / 'policy_kwargs'): {e}") from e
    saved = meta.get("spaces")
    if isinstance(task, EnvSource) and isinstance(saved, dict):  # same id, other wrappers or arguments?
        now = _spaces_record(model)
        for k in ("observation", "action"):
            if k in saved and saved[k] != now[k]:
                raise ValueError(f"load_agent: {pt} was trained on {meta['task']} with the {k} space "
                                 f"{saved[k]}, but the env given has {now[k]} (other wrappers or arguments; "
                                 f"{meta_path}, key 'spaces')")
    model.num_timesteps = meta.get("num_timesteps", 0)
    if meta["params"].get("normalize"):
        return load_obs_rms(model, pt.parent)
    return model


def _training_env(src: EnvSource, n: int | None):
    """SB3's training env of a foreign gymnasium env: the ``VectorEnv`` given (its ``num_envs``; ``n``, when
    given, must agree), else a ``DummyVecEnv`` of ``n`` ``Monitor``-wrapped envs (the ``Env`` given first);
    in SB3's ``VecCheckNan``, so that a NaN/inf observation or reward from the env is a ``ValueError`` saying
    so, not an error deep in the policy's distribution."""
    from stable_baselines3.common.vec_env import DummyVecEnv, VecCheckNan, VecMonitor

    from learning.sb3 import SB3VecEnv

    if src.is_vector:
        k = src.instance.num_envs
        if n is not None and int(n) != k:
            raise ValueError(f"make_agent: argument 'num_envs' is {n} but the VectorEnv given has {k} "
                             "sub-envs (the agent trains on it as it is)")
        return VecCheckNan(VecMonitor(SB3VecEnv(src.instance)), raise_exception=True)
    return VecCheckNan(DummyVecEnv([partial(_monitored, f) for f in src.training_factories(n)]),
                       raise_exception=True)


def check_episode_limit(src: EnvSource, where: str) -> None:
    """A ``ValueError`` unless the copies of ``src`` end their episodes (a ``TimeLimit``, or a spec's
    ``max_episode_steps``): the held-out evaluations run whole episodes."""
    from learning.env_source import episode_limit

    if episode_limit(src) is None:
        raise ValueError(f"{where}: the env {src.name!r} has no episode limit (no max_episode_steps in its "
                         "spec, no TimeLimit wrapper) and the evaluations run whole episodes: wrap it in "
                         "gymnasium.wrappers.TimeLimit(env, max_episode_steps) (or register it with one)")


def _monitored(make):
    from stable_baselines3.common.monitor import Monitor

    return Monitor(make())


def _one_env(target: Task | EnvSource):
    """One training-style SB3 env of a task or of copies of a foreign env."""
    if isinstance(target, EnvSource):
        return _training_env(target.detached(), 1)
    from learning.sb3 import SB3VecEnv

    return SB3VecEnv(target, 1)


def mean_curve(curves: list[dict[str, list]], key: str = "returns") -> tuple[np.ndarray, np.ndarray,
                                                                               np.ndarray, np.ndarray]:
    """``(steps, mean, min, max)`` of ``key`` over several curves, on the steps they all have (a ``None``
    value, e.g. a success rate read back from JSON where the env defines none, counts as NaN)."""
    if not curves:
        raise ValueError("mean_curve: no curves")
    common = sorted(set.intersection(*(set(int(s) for s in c["steps"]) for c in curves)))
    rows = []
    for c in curves:
        at = {int(s): (math.nan if v is None else float(v)) for s, v in zip(c["steps"], c[key])}
        rows.append([at[s] for s in common])
    v = np.asarray(rows, dtype=np.float64).reshape(len(curves), len(common))
    return np.asarray(common, dtype=np.int64), v.mean(0), v.min(0), v.max(0)


def steps_to_match(steps, values, target: float, tol: float = 1e-9) -> int | None:
    """The first of ``steps`` at which ``values`` reaches ``target`` (``value ≥ target − tol``), or
    ``None`` when it never does (or ``target`` is not finite)."""
    if target is None or not math.isfinite(float(target)):
        return None
    for s, v in zip(steps, values):
        if v is not None and math.isfinite(float(v)) and float(v) >= float(target) - tol:
            return int(s)
    return None
