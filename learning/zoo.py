"""Published scores of trained RL agents, for the tables that put an MPC beside them.

The source is the rl-baselines3-zoo's ``benchmark.md`` (DLR-RM/rl-baselines3-zoo, the file at commit
``0088472b8cb622732bdbc4aa3d0d0abde86c67ed``): the mean (and std) episode return of each trained agent,
deterministic policy, over ``eval_timesteps`` of evaluation after ``n_timesteps`` of training — one training
run each ("not a quantitative benchmark", as the file itself says).  Only the environments this project
runs an MPC on are copied here; the table has no rows for MuJoCo's ``InvertedPendulum``,
``InvertedDoublePendulum`` or ``Reacher``, and its MuJoCo rows are for ``-v3`` environments (the same models
and rewards as ``-v5`` up to details listed in gymnasium's changelog).
"""

from __future__ import annotations

__all__ = ["ZOO_SOURCE", "ZOO_SCORES", "zoo_scores", "zoo_best"]

ZOO_SOURCE = ("rl-baselines3-zoo benchmark.md (DLR-RM/rl-baselines3-zoo at "
              "0088472b8cb622732bdbc4aa3d0d0abde86c67ed)")

#: ``{env_id: {algo: (mean_reward, std_reward, n_timesteps)}}`` as published
ZOO_SCORES: dict[str, dict[str, tuple[float, float, str]]] = {
    "Pendulum-v1": {
        "a2c": (-162.965, 103.210, "1M"), "ars": (-212.540, 160.444, "2M"), "ddpg": (-152.099, 94.282, "20k"),
        "ppo": (-172.225, 104.159, "100k"), "sac": (-156.995, 88.714, "20k"),
        "td3": (-151.855, 90.227, "20k"), "trpo": (-174.631, 127.577, "100k"),
    },
    "MountainCarContinuous-v0": {
        "a2c": (91.166, 0.255, "100k"), "ars": (96.672, 0.784, "500k"), "ddpg": (93.512, 0.048, "300k"),
        "ppo": (88.343, 2.572, "20k"), "sac": (94.679, 1.134, "50k"), "td3": (93.483, 0.075, "300k"),
        "tqc": (63.641, 45.259, "50k"), "trpo": (92.489, 0.355, "50k"),
    },
    "Hopper-v3": {
        "a2c": (733.454, 376.574, "1M"), "ars": (3343.919, 5.730, "7M"), "ppo": (2410.435, 10.026, "1M"),
        "sac": (2325.547, 1129.676, "1M"), "td3": (3606.390, 4.027, "1M"), "tqc": (3754.199, 8.276, "1M"),
        "trpo": (3618.386, 356.768, "1M"),
    },
    "HalfCheetah-v3": {
        "a2c": (3041.174, 157.265, "1M"), "ars": (4815.192, 1340.752, "12M"),
        "ppo": (5819.099, 663.530, "1M"), "sac": (9535.451, 100.470, "1M"), "td3": (9655.666, 969.916, "1M"),
        "tqc": (12089.939, 127.440, "1M"), "trpo": (1785.476, 68.672, "1M"),
    },
}

#: our env ids whose published rows are for another version of the same environment
_ALIASES = {"Hopper-v5": "Hopper-v3", "HalfCheetah-v5": "HalfCheetah-v3"}


def zoo_scores(env_id: str) -> dict[str, tuple[float, float, str]]:
    """The published rows of ``env_id`` (``{}`` when the zoo's table has none; ``-v5`` MuJoCo ids read the
    ``-v3`` rows)."""
    return dict(ZOO_SCORES.get(_ALIASES.get(env_id, env_id), {}))


def zoo_best(env_id: str) -> tuple[str, float] | None:
    """``(algo, mean return)`` of the best published agent on ``env_id``, or ``None``."""
    rows = zoo_scores(env_id)
    if not rows:
        return None
    algo = max(rows, key=lambda a: rows[a][0])
    return algo, rows[algo][0]
