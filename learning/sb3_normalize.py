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
``torch.load(..., weights_only=True)`` and checked: real numbers, finite, ``var`` and ``count`` ≥ 0), never
with ``VecNormalize.save``, which pickles.  The reward
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
    """``env`` in SB3's ``VecNormalize`` when ``normalize`` is ``True`` or a non-empty dict of its keyword
    arguments (the zoo's convention: the reward's discount is the algorithm's ``gamma`` unless the dict names
    one); ``env`` itself when it is falsy (``False``, ``None``, ``{}``: what
    :func:`learning.baselines.load_agent` reads as "no normalize" too).  Anything else is a ``ValueError``
    naming the hyperparameter."""
    from stable_baselines3.common.vec_env import VecNormalize

    if normalize is None or normalize is False or (isinstance(normalize, dict) and not normalize):
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
    model still training is evaluated with the statistics of the moment.  Attributes other than ``model``
    and ``vecnorm`` are read from, and set on, the model."""

    def __init__(self, model, vecnorm):
        object.__setattr__(self, "model", model)
        object.__setattr__(self, "vecnorm", vecnorm)

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
        # only reached where normal lookup fails; "model" itself missing (copy/pickle build the object
        # without __init__) and special names must fail here, not recurse
        if name in ("model", "vecnorm") or (name.startswith("__") and name.endswith("__")):
            raise AttributeError(name)
        return getattr(self.model, name)

    def __setattr__(self, name: str, value) -> None:
        if name in ("model", "vecnorm"):
            object.__setattr__(self, name, value)
        else:
            setattr(self.model, name, value)

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


def _frozen_stats(normalize: Any, shape: tuple) -> Any:
    """What :class:`NormalizedModel` reads of a ``VecNormalize`` (``norm_obs``, ``clip_obs``, ``epsilon``,
    ``obs_rms``), for a model whose env is none: ``VecNormalize``'s defaults, or the values ``normalize``
    (``True`` or a dict of its keyword arguments) names."""
    import inspect
    from types import SimpleNamespace

    from stable_baselines3.common.running_mean_std import RunningMeanStd
    from stable_baselines3.common.vec_env import VecNormalize

    kw = {k: p.default for k, p in inspect.signature(VecNormalize.__init__).parameters.items()
          if k in ("norm_obs", "clip_obs", "epsilon")}
    if isinstance(normalize, dict):
        kw.update({k: normalize[k] for k in kw if k in normalize})
    return SimpleNamespace(obs_rms=RunningMeanStd(shape=shape), training=False, **kw)


def load_obs_rms(model, folder: str | Path, normalize: Any = True):
    """The model of a ``VecNormalize`` env with the observation statistics of ``folder/obs_rms.pt`` (read
    with ``weights_only=True``), its ``VecNormalize`` frozen (``training = False``): a
    :class:`NormalizedModel`, or ``model`` itself where the ``VecNormalize`` does not normalize
    observations (``norm_obs=False``: nothing was saved, nothing to load).  A model without a
    ``VecNormalize`` (an SB3 zip loaded without its env) gets one's settings from ``normalize`` (the
    hyperparameter).  A missing or unreadable file, or statistics of the wrong shape, not real, not finite,
    or negative (``var``, ``count``) are a ``ValueError`` naming the file."""
    from stable_baselines3.common.vec_env import unwrap_vec_normalize

    path = Path(folder) / OBS_RMS_FILE
    env = model.get_env()
    v = None if env is None else unwrap_vec_normalize(env)
    if v is None:
        if normalize is None or normalize is False:
            raise ValueError("load_obs_rms: the model's env is not a VecNormalize")
        v = _frozen_stats(normalize, tuple(model.observation_space.shape))
    if not v.norm_obs:
        return model
    if not path.is_file():
        raise ValueError(f"load_agent: {path} is missing: the agent was trained with normalize "
                         "(VecNormalize) and needs its observation statistics")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # not a torch file, truncated, or pickled objects (refused by weights_only)
        raise ValueError(f"load_agent: {path} cannot be read as plain tensors (written by "
                         f"learning.baselines.save_agent): {type(e).__name__}: {str(e)[:200]}") from None
    shape = v.obs_rms.mean.shape
    keys = ("mean", "var", "count")
    ok = (isinstance(state, dict) and set(keys) <= set(state)
          and all(isinstance(state[k], torch.Tensor) and not state[k].is_complex()
                  and state[k].dtype != torch.bool and state[k].layout == torch.strided
                  and state[k].device.type == "cpu" for k in keys)
          and tuple(state["mean"].shape) == shape and tuple(state["var"].shape) == shape
          and state["count"].numel() == 1)
    if not ok:
        raise ValueError(f"load_agent: {path} must hold tensors 'mean' and 'var' of shape {shape} and "
                         "'count' (one number), of real numbers (written by learning.baselines.save_agent)")
    mean, var, count = (state[k].detach().double().numpy().copy() for k in keys)
    if not (np.isfinite(mean).all() and np.isfinite(var).all() and np.isfinite(count).all()
            and (var >= 0).all() and (count >= 0).all()):
        raise ValueError(f"load_agent: {path}: the statistics must be finite, 'var' and 'count' >= 0 (the "
                         "file was edited, or not written by learning.baselines.save_agent)")
    v.obs_rms.mean, v.obs_rms.var, v.obs_rms.count = mean, var, float(count.reshape(()))
    v.training = False
    return NormalizedModel(model, v)
