"""SB3's ``VecNormalize`` as the rl-baselines3-zoo uses it (``normalize: true``), made safe to evaluate, save
and load: :class:`NormalizedModel`, :func:`wrap_normalize`, :func:`agent_of`.

The zoo wraps the training env in ``VecNormalize`` (observations and rewards normalized by running
statistics, the reward's discount the algorithm's ``gamma``) and evaluates on an env whose observation
statistics are the training env's, frozen, with raw rewards.  Here the hyperparameter ``normalize`` (``True``,
or a dict of ``VecNormalize`` keyword arguments) does the same: :func:`learning.baselines.make_agent` wraps
the training env (:func:`wrap_normalize`), and the agent is handed out as a :class:`NormalizedModel` — the
SB3 model whose ``predict`` first normalizes the observation by the training statistics (exactly
``VecNormalize.normalize_obs``: ``clip((obs − mean) / sqrt(var + ε), ±clip_obs)`` in float32) — so that
:func:`learning.evaluate`, on any env, sees the raw env and the env's own rewards.  Every other attribute
(``policy``, ``save``, ``num_timesteps``, ...) is the model's.

The statistics are saved as plain tensors (``obs_rms.pt``: ``mean``, ``var``, ``count``; loaded with
``torch.load(..., weights_only=True)``), never with ``VecNormalize.save``, which pickles.  The reward
statistics serve training only and are not saved: a loaded agent evaluates, it does not resume training with
the same reward scale.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

__all__ = ["NormalizedModel", "wrap_normalize", "agent_of", "save_obs_rms", "load_obs_rms", "OBS_RMS_FILE"]

#: the file next to ``policy.pt`` holding the observation statistics
OBS_RMS_FILE = "obs_rms.pt"


def wrap_normalize(env, normalize: Any, gamma: float):
    """``env`` in SB3's ``VecNormalize`` when ``normalize`` is ``True`` or a dict of its keyword arguments
    (the zoo's convention: the reward's discount is the algorithm's ``gamma`` unless the dict names one);
    ``env`` itself when it is falsy.  Anything else is a ``ValueError`` naming the hyperparameter."""
    from stable_baselines3.common.vec_env import VecNormalize

    if normalize is None or normalize is False:
        return env
    if normalize is True:
        kw: dict[str, Any] = {}
    elif isinstance(normalize, dict):
        kw = dict(normalize)
    else:
        raise ValueError(f"hyperparameter 'normalize' must be true/false or a dict of VecNormalize keyword "
                         f"arguments, got {normalize!r}")
    kw.setdefault("gamma", float(gamma))
    try:
        return VecNormalize(env, **kw)
    except TypeError as e:
        raise ValueError(f"hyperparameter 'normalize': {e}") from None


class NormalizedModel:
    """An SB3 model trained on a ``VecNormalize`` env, whose ``predict`` normalizes raw observations by that
    env's observation statistics (module docstring).  ``vecnorm`` is read when ``predict`` is called, so a
    model still training is evaluated with the statistics of the moment."""

    def __init__(self, model, vecnorm):
        self.model = model
        self.vecnorm = vecnorm

    def normalize_obs(self, obs) -> np.ndarray:
        v = self.vecnorm
        if not v.norm_obs:
            return np.asarray(obs)
        rms = v.obs_rms
        out = np.clip((np.asarray(obs) - rms.mean) / np.sqrt(rms.var + v.epsilon), -v.clip_obs, v.clip_obs)
        return out.astype(np.float32)

    def predict(self, observation, state=None, episode_start=None, deterministic: bool = False):
        return self.model.predict(self.normalize_obs(observation), state=state, episode_start=episode_start,
                                  deterministic=deterministic)

    def __getattr__(self, name: str):
        return getattr(self.model, name)

    def __repr__(self) -> str:
        return f"NormalizedModel({type(self.model).__name__})"


def agent_of(model):
    """``model`` as a policy acting on raw observations: a :class:`NormalizedModel` when it trains on a
    ``VecNormalize`` env (with normalized observations), else ``model`` itself."""
    from stable_baselines3.common.vec_env import unwrap_vec_normalize

    if isinstance(model, NormalizedModel):
        return model
    env = model.get_env()
    v = None if env is None else unwrap_vec_normalize(env)
    return model if v is None or not v.norm_obs else NormalizedModel(model, v)


def save_obs_rms(agent, folder: str | Path) -> str | None:
    """Write the observation statistics of a :class:`NormalizedModel` to ``folder/obs_rms.pt`` (plain
    float64 tensors); returns the path (``None`` for another model: nothing to save)."""
    if not isinstance(agent, NormalizedModel):
        return None
    rms = agent.vecnorm.obs_rms
    path = Path(folder) / OBS_RMS_FILE
    torch.save({"mean": torch.as_tensor(np.asarray(rms.mean, dtype=np.float64)),
                "var": torch.as_tensor(np.asarray(rms.var, dtype=np.float64)),
                "count": torch.tensor(float(rms.count), dtype=torch.float64)}, path)
    return str(path)


def load_obs_rms(model, folder: str | Path) -> NormalizedModel:
    """The model of a ``VecNormalize`` env with the observation statistics of ``folder/obs_rms.pt`` (read
    with ``weights_only=True``), its ``VecNormalize`` frozen (``training = False``); a missing file or
    statistics of the wrong shape are a ``ValueError`` naming the file."""
    from stable_baselines3.common.vec_env import unwrap_vec_normalize

    path = Path(folder) / OBS_RMS_FILE
    v = unwrap_vec_normalize(model.get_env())
    if v is None:
        raise ValueError("load_obs_rms: the model's env is not a VecNormalize")
    if not path.is_file():
        raise ValueError(f"load_agent: {path} is missing: the agent was trained with normalize "
                         "(VecNormalize) and needs its observation statistics")
    state = torch.load(path, map_location="cpu", weights_only=True)
    shape = v.obs_rms.mean.shape
    ok = (isinstance(state, dict) and {"mean", "var", "count"} <= set(state)
          and all(isinstance(state[k], torch.Tensor) for k in ("mean", "var", "count"))
          and tuple(state["mean"].shape) == shape and tuple(state["var"].shape) == shape)
    if not ok:
        raise ValueError(f"load_agent: {path} must hold tensors 'mean' and 'var' of shape {shape} and "
                         "'count' (written by learning.baselines.save_agent)")
    v.obs_rms.mean = state["mean"].double().numpy().copy()
    v.obs_rms.var = state["var"].double().numpy().copy()
    v.obs_rms.count = float(state["count"])
    v.training = False
    return NormalizedModel(model, v)
