"""The rl-baselines3-zoo's tuned hyperparameters for the gymnasium environments the project has an MPC for
(:mod:`learning.env_models`), copied as data: what :mod:`learning.baselines` trains SB3 agents with on those
ids.

Source: :data:`ZOO_HP_SOURCE` — the files ``hyperparams/ppo.yml``, ``sac.yml`` and ``td3.yml`` of
DLR-RM/rl-baselines3-zoo at the commit named there.  Translation of the zoo's YAML:

* ``n_envs`` is kept (the number of training environments; the zoo's default is 1); ``n_timesteps`` (the
  zoo's training budget) is kept apart, in :data:`ZOO_TIMESTEPS`, for reference — the project's default
  budgets are smaller (:data:`learning.baselines.DEFAULT_BUDGETS`); ``policy: 'MlpPolicy'`` is the
  project's default policy and is dropped.
* ``policy_kwargs: "dict(...)"`` strings become a ``policy_kwargs`` dict (``net_arch``, ``log_std_init``,
  ``ortho_init``, ``activation_fn=nn.ReLU`` as the class ``torch.nn.ReLU``).
* ``noise_type`` / ``noise_std`` (TD3) are kept as they are and turned into SB3's ``action_noise`` by
  :func:`learning.baselines.make_agent` (``normal``: ``NormalActionNoise``, ``ornstein-uhlenbeck``:
  ``OrnsteinUhlenbeckActionNoise``, both with ``sigma = noise_std`` per action dimension, as the zoo does).
* ``lin_X`` schedules would be kept as strings and made linear schedules by ``make_agent``; no entry
  copied here has one.
* ``normalize: true`` (the zoo wraps the training env in ``VecNormalize``, observations and rewards, the
  reward's discount the algorithm's ``gamma``) is kept as the hyperparameter ``normalize: True``, which
  :func:`learning.baselines.make_agent` applies (:mod:`learning.sb3_normalize`; the entries listed in
  :data:`ZOO_NORMALIZE`: PPO on MountainCarContinuous-v0 and on the MuJoCo ids).
* The MuJoCo entries are the zoo's ``-v2`` ids (``InvertedPendulum-v2``, ``InvertedDoublePendulum-v2``,
  ``Reacher-v2``, PPO only) and ``HalfCheetah-v4`` (PPO, SAC, TD3); the project runs ``-v5`` (the same
  models and rewards up to details in gymnasium's changelog).  Where the zoo has no tuned entry (SAC and
  TD3 on the other MuJoCo ids) its ``default`` entry applies (SB3's defaults; TD3: Gaussian noise 0.1) —
  :func:`zoo_hyperparams` says so.
"""

from __future__ import annotations

import copy
from typing import Any

from torch import nn

__all__ = ["ZOO_HP_SOURCE", "ZOO_HYPERPARAMS", "ZOO_DEFAULT", "ZOO_TIMESTEPS", "ZOO_NORMALIZE",
           "zoo_hyperparams"]

ZOO_HP_SOURCE = ("rl-baselines3-zoo hyperparams/{ppo,sac,td3}.yml (DLR-RM/rl-baselines3-zoo at "
                 "22e3ff2450fd92033f7f032915e1f64894a09584)")

#: ``{env_id: {algo: hyperparameters}}`` as tuned by the zoo (translated: module docstring)
ZOO_HYPERPARAMS: dict[str, dict[str, dict[str, Any]]] = {
    "Pendulum-v1": {
        "ppo": dict(n_envs=4, n_steps=1024, gae_lambda=0.95, gamma=0.9, n_epochs=10, ent_coef=0.0,
                    learning_rate=1e-3, clip_range=0.2, use_sde=True, sde_sample_freq=4),
        "sac": dict(n_envs=1, learning_rate=1e-3),
        "td3": dict(n_envs=1, gamma=0.98, buffer_size=200_000, learning_starts=10_000, noise_type="normal",
                    noise_std=0.1, gradient_steps=1, train_freq=1, learning_rate=1e-3,
                    policy_kwargs=dict(net_arch=[400, 300])),
    },
    "MountainCarContinuous-v0": {
        "ppo": dict(n_envs=1, batch_size=256, n_steps=8, gamma=0.9999, learning_rate=7.77e-05,
                    ent_coef=0.00429, clip_range=0.1, n_epochs=10, gae_lambda=0.9, max_grad_norm=5,
                    vf_coef=0.19, use_sde=True, policy_kwargs=dict(log_std_init=-3.29, ortho_init=False)),
        "sac": dict(n_envs=1, learning_rate=3e-4, buffer_size=50_000, batch_size=512, ent_coef=0.1,
                    train_freq=32, gradient_steps=32, gamma=0.9999, tau=0.01, learning_starts=0, use_sde=True,
                    policy_kwargs=dict(log_std_init=-3.67, net_arch=[64, 64])),
        "td3": dict(n_envs=1, noise_type="ornstein-uhlenbeck", noise_std=0.5, gradient_steps=1, train_freq=1,
                    learning_rate=1e-3, batch_size=256, policy_kwargs=dict(net_arch=[400, 300])),
    },
    # the zoo's InvertedPendulum-v2 entry
    "InvertedPendulum-v5": {
        "ppo": dict(n_envs=1, batch_size=64, n_steps=32, gamma=0.999, learning_rate=0.000222425,
                    ent_coef=1.37976e-07, clip_range=0.4, n_epochs=5, gae_lambda=0.9, max_grad_norm=0.3,
                    vf_coef=0.19816),
    },
    # the zoo's InvertedDoublePendulum-v2 entry
    "InvertedDoublePendulum-v5": {
        "ppo": dict(n_envs=1, batch_size=512, n_steps=128, gamma=0.98, learning_rate=0.000155454,
                    ent_coef=1.05057e-06, clip_range=0.4, n_epochs=10, gae_lambda=0.8, max_grad_norm=0.5,
                    vf_coef=0.695929),
    },
    # the zoo's HalfCheetah-v4 entries (PPO's own; SAC and TD3: its "mujoco-defaults")
    "HalfCheetah-v5": {
        "ppo": dict(n_envs=1, batch_size=64, n_steps=512, gamma=0.98, learning_rate=2.0633e-05,
                    ent_coef=0.000401762, clip_range=0.1, n_epochs=20, gae_lambda=0.92, max_grad_norm=0.8,
                    vf_coef=0.58096,
                    policy_kwargs=dict(log_std_init=-2, ortho_init=False, activation_fn=nn.ReLU,
                                       net_arch=dict(pi=[256, 256], vf=[256, 256]))),
        "sac": dict(n_envs=1, learning_starts=10_000),
        "td3": dict(n_envs=1, learning_starts=10_000, noise_type="normal", noise_std=0.1, train_freq=1,
                    gradient_steps=1, learning_rate=1e-3, batch_size=256,
                    policy_kwargs=dict(net_arch=[400, 300])),
    },
    # the zoo's Reacher-v2 entry
    "Reacher-v5": {
        "ppo": dict(n_envs=1, batch_size=32, n_steps=512, gamma=0.9, learning_rate=0.000104019,
                    ent_coef=7.52585e-08, clip_range=0.3, n_epochs=5, gae_lambda=1.0, max_grad_norm=0.9,
                    vf_coef=0.950368),
    },
}

#: the zoo's ``default`` entries (environments it has not tuned): SB3's defaults, TD3 with Gaussian noise
ZOO_DEFAULT: dict[str, dict[str, Any]] = {
    "ppo": dict(n_envs=1),
    "sac": dict(n_envs=1),
    "td3": dict(n_envs=1, train_freq=1, gradient_steps=1, noise_type="normal", noise_std=0.1),
}

#: the zoo's training budgets (``n_timesteps``) of those entries; the ``default`` entry's is 1e6
ZOO_TIMESTEPS: dict[str, dict[str, int]] = {
    "Pendulum-v1": {"ppo": 100_000, "sac": 20_000, "td3": 20_000},
    "MountainCarContinuous-v0": {"ppo": 20_000, "sac": 50_000, "td3": 300_000},
    "InvertedPendulum-v5": {"ppo": 1_000_000},
    "InvertedDoublePendulum-v5": {"ppo": 1_000_000},
    "Reacher-v5": {"ppo": 1_000_000},
    "HalfCheetah-v5": {"ppo": 1_000_000, "sac": 1_000_000, "td3": 1_000_000},
}

#: the entries the zoo trains with ``normalize: true`` (VecNormalize): :func:`zoo_hyperparams` adds
#: ``normalize=True`` to them
ZOO_NORMALIZE: dict[str, tuple[str, ...]] = {
    "MountainCarContinuous-v0": ("ppo",),
    "InvertedPendulum-v5": ("ppo",),
    "InvertedDoublePendulum-v5": ("ppo",),
    "Reacher-v5": ("ppo",),
    "HalfCheetah-v5": ("ppo",),
}


def zoo_hyperparams(algo: str, env_id: str) -> tuple[dict[str, Any], str]:
    """``(hyperparameters, note)``: a copy of the zoo's tuned entry of ``algo`` on ``env_id`` (its
    ``default`` entry where it has none; the note then says so) — ``note`` is ``""`` for a tuned entry."""
    tuned = ZOO_HYPERPARAMS.get(env_id, {}).get(algo)
    if tuned is not None:
        out = _copy(tuned)
        if algo in ZOO_NORMALIZE.get(env_id, ()):
            out["normalize"] = True
        return out, ""
    return _copy(ZOO_DEFAULT[algo]), (f"no tuned rl-baselines3-zoo entry for {algo} on {env_id}: the zoo's "
                                      "default hyperparameters (SB3's defaults)")


def _copy(d: dict[str, Any]) -> dict[str, Any]:
    return copy.deepcopy(d)
