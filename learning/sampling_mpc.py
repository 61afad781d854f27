"""A sampling-based MPC policy on any :class:`~learning.env_models.EnvModel`: :class:`SamplingModelMPC`, and
:func:`sampling_guess`, the same planner's plan as an initial guess for a gradient-based one.

At every step the observation is mapped to the model's state and the plan is improved by
:func:`controllers.sampling.plan` (MPPI or predictive sampling: random search around the nominal plan,
derivative-free, so a contact-rich model and a cost that is not smooth are fine) from the previous plan
shifted by one step (zero controls, clipped into the action box, at an episode's start).  The candidates
of all environments and samples are rolled out together: on a MuJoCo model one ``mujoco.rollout`` call of
``N (1 + K)`` sequences per iteration (:meth:`MujocoSystem.rollout_states
<controllers.systems.mujoco_system.MujocoSystem.rollout_states>`).  The first control of the plan is the
action.  With the nominal among the candidates (``include_nominal``, the default) the plan is never worse
under the model than the shifted previous one.

**Randomness.**  The draws are counter-based (:mod:`learning._counter_rng`, SplitMix64, then Box-Muller):
those of environment ``b`` at step ``t`` of its ``e``-th episode since :meth:`SamplingModelMPC.reset` are a
pure function of ``(seed + b, e, t)``.  So a batch of ``N`` environments acts exactly as ``N`` policies with
seeds ``seed, seed + 1, ...`` on one environment each (checked in the tests), independently of the batch
size and with no per-environment generator.

**Settings.**  ``horizon`` and ``options`` (:class:`~controllers.sampling.SamplingOptions`) default to
:data:`SAMPLING_DEFAULTS` for the model's id (tuned there, see its note), else the model's horizon and
``SamplingOptions(samples=128, noise_sigma=0.25 · the action box's half-width, smoothing="knots")``.
HalfCheetah-v5's were picked by the return of the first 100 steps of seeds 0, 1, 2
(``learning.evaluate(SamplingModelMPC(model, horizon=H, options=...), "HalfCheetah-v5", seeds=[0, 1, 2],
num_envs=3, max_episode_steps=100)``; MPPI, 128 samples, one iteration, horizon 20, ``λ = 0.5`` unless
stated; 2-core CPU shared with other jobs)::

    white noise σ 0.5 (chosen)    427 408 360      white σ 0.8          401 404 382
    white σ 0.5, λ 2.0            353 155 316      white σ 0.6, λ 0.25  268 317 230
    predictive sampling, σ 0.5    434 327 333      AR(1) β 0.5, σ 0.5   363 364 173
    horizon 12 / 30               254 192 302  /  330 254 314
    256 samples / 2 iterations    358 394 375  /  427 291 426
    knots (5): σ 0.3 / 0.5 / 0.8  104 83 95  /  285 100 241  /  285 293 243
    velocity_to_go 0.3 s          399 301 227

Smooth (knot) noise did worse than white noise here: the fast gaits switch the torques within a few
steps.  More samples or iterations did not show in these 100-step returns — but over full episodes more
samples do pay (below).

**Measured** on HalfCheetah-v5 with these defaults (full 1000-step episodes, seeds 0-4 in one batch;
``learning.evaluate(SamplingModelMPC("HalfCheetah-v5"), "HalfCheetah-v5", seeds=[0, 1, 2, 3, 4],
num_envs=5, timing_steps=50)``, float64, ``OMP_NUM_THREADS=1``, one thread on a 2-core CPU shared with
other jobs): return **5002 ± 535** (4257, 5299, 5829, 4942, 4685); 490 ms per MPC step at batch 5 and
76 ms at batch 1 (median; the env's ``dt`` is 50 ms, so not real time at this setting), nearly all of it in
``mujoco.rollout``.  The RL Zoo's HalfCheetah-v3 agents after 1M steps (:mod:`learning.zoo`): TQC 12090,
SAC 9535, PPO 5819 — the planner with the true model and the exact reward stays below all three, PPO
included, at this compute: an honest miss.  With 256 samples (``dataclasses.replace(options, samples=256)``,
seeds 0-2, ``num_envs=3``) the return was 5707 ± 77 (5638, 5815, 5669; against 4257, 5299, 5829 with
128 on the same seeds) at 596 ms per step at batch 3; with 512 samples (seeds 0-1, ``num_envs=2``) 5865 and
7167 (mean 6516, above PPO's 5819) at 528 ms per step at batch 2.  The return grows with the samples; SAC's
9535 and TQC's 12090 stay out of reach at any compute measured here.
(± is the standard deviation over seeds, ``np.std``; the Zoo's rows are for v3: the same reward, older
MuJoCo bindings.)

Not done: no certificate of optimality (:meth:`SamplingModelMPC.info` has no ``converged``); no
termination-aware cost (the model's cost is planned as given); gradients are not wanted (``no_grad``).
"""

from __future__ import annotations

import dataclasses
import math
from types import MappingProxyType
from typing import Any

import torch
from torch import Tensor

from controllers.mpc import shift
from controllers.sampling import SamplingOptions, _noise_dims, plan
from learning._counter_rng import _srl, keys_of_seeds, mix64
from learning.env_models import EnvModel, env_model
from learning.policies import Policy

__all__ = ["SamplingModelMPC", "sampling_guess", "SAMPLING_DEFAULTS", "default_sampling"]

#: tuned ``(horizon, SamplingOptions fields)`` per gymnasium id (module docstring, "Settings")
SAMPLING_DEFAULTS: MappingProxyType = MappingProxyType({
    "HalfCheetah-v5": (20, dict(samples=128, iterations=1, noise_sigma=0.5, temperature=0.5,
                                method="mppi", smoothing="none")),
})

_TWO_PI = 2.0 * math.pi


def default_sampling(model: EnvModel) -> tuple[int, SamplingOptions]:
    """``(horizon, SamplingOptions)`` for ``model``: :data:`SAMPLING_DEFAULTS` of its id, else its horizon
    and 128 knot-smoothed samples of standard deviation a quarter of the action box's half-width."""
    if model.env_id in SAMPLING_DEFAULTS:
        h, kw = SAMPLING_DEFAULTS[model.env_id]
        return h, SamplingOptions(**kw)
    lo = torch.tensor(model.action_low, dtype=torch.float64)
    hi = torch.tensor(model.action_high, dtype=torch.float64)
    half = torch.where(torch.isfinite(hi - lo), 0.5 * (hi - lo), torch.ones_like(lo))
    return model.horizon, SamplingOptions(samples=128, noise_sigma=0.25 * half, smoothing="knots")


def _int(v, name: str, minimum: int, who: str) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or v < minimum:
        raise ValueError(f"{who}: argument '{name}' must be an int >= {minimum}, got {v!r}")
    return v


def _steps_table(k: int, device) -> Tensor:
    """``j · golden (mod 2⁶⁴)`` for ``j = 1..k`` (int64 wraps), the stream offsets of SplitMix64."""
    golden = -7046029254386353131  # 0x9E3779B97F4A7C15 as a signed int64
    return torch.arange(1, k + 1, dtype=torch.int64, device=device) * golden


def _normals(key: Tensor, counter: Tensor, shape: tuple[int, ...], dtype, table: Tensor | None = None
             ) -> Tensor:
    """Standard normal draws ``(N, *shape)``, a pure function of the int64 ``key (N,)`` and
    ``counter (N,)`` per row (SplitMix64 uniforms, Box-Muller on pairs)."""
    k = math.prod(shape)
    h = (k + 1) // 2
    steps = _steps_table(2 * h, key.device) if table is None else table[:2 * h]
    z = mix64(mix64(key ^ mix64(counter)).unsqueeze(-1) + steps)
    u = _srl(z, 11).to(torch.float64) * 2.0 ** -53  # [0, 1), 53 bits
    r = torch.sqrt(-2.0 * torch.log1p(-u[:, :h]))  # 1 - u in (0, 1]
    th = _TWO_PI * u[:, h:]
    out = torch.cat([r * torch.cos(th), r * torch.sin(th)], -1)[:, :k]
    return out.reshape(key.shape[0], *shape).to(dtype)


def _options_for(options: SamplingOptions, like: Tensor) -> SamplingOptions:
    """``options`` with a tensor ``noise_sigma`` in ``like``'s dtype (the planner requires it)."""
    s = options.noise_sigma
    if isinstance(s, Tensor) and s.dtype != like.dtype:
        return dataclasses.replace(options, noise_sigma=s.to(like.dtype))
    return options


def _box(model: EnvModel, like: Tensor) -> tuple[Tensor, Tensor]:
    kw = dict(dtype=like.dtype, device=like.device)
    return torch.tensor(model.action_low, **kw), torch.tensor(model.action_high, **kw)


def _check_obs(obs: Any, who: str) -> None:
    if not isinstance(obs, Tensor) or obs.dim() != 2 or not obs.is_floating_point():
        got = f"{tuple(obs.shape)} {obs.dtype}" if isinstance(obs, Tensor) else type(obs).__name__
        raise ValueError(f"{who}: argument 'obs' must be a floating tensor (N, obs_dim), got {got}")


def _draws(options: SamplingOptions, seeds: Tensor, counter: Tensor, T: int, m: int, dtype,
           table: Tensor | None = None) -> Tensor:
    """The ``noise`` argument of :func:`~controllers.sampling.plan`: ``(I, N, K, T_z, m)``."""
    Tz = _noise_dims(options, T)
    z = _normals(keys_of_seeds(seeds), counter, (options.iterations, options.samples, Tz, m), dtype, table)
    return z.movedim(1, 0)


class SamplingModelMPC(Policy):
    """Sampling-based MPC (MPPI or predictive sampling) on an :class:`EnvModel` (module docstring).

    Args:
        model: an :class:`EnvModel`, or a gymnasium id / ``Env`` / ``VectorEnv`` with a registered model.
        horizon: planning steps (default: :func:`default_sampling`).
        options: a :class:`~controllers.sampling.SamplingOptions` (default: :func:`default_sampling`);
            ``common_noise`` must be False (the draws are per environment).
        seed: environment ``b`` of a batch draws with seed ``seed + b``.
        fill: how the shifted plan's new last step is filled, ``"last"`` or ``"zero"``.

    :meth:`act` ``(N, obs_dim) -> (N, m)`` (dtype and device of ``obs``; NaN for an environment whose state
    is not finite); :meth:`reset` ``(done (N,) bool or None)``; :meth:`info`: ``iterations (N,)``,
    ``cost (N,)`` (the plan's predicted cost), ``fallback (N,)`` (MPPI's update lost to the best sample).
    """

    def __init__(self, model: EnvModel | Any, *, horizon: int | None = None,
                 options: SamplingOptions | None = None, seed: int = 0, fill: str = "last"):
        self.model = env_model(model)
        h0, o0 = default_sampling(self.model)
        self.horizon = _int(h0 if horizon is None else horizon, "horizon", 1, "SamplingModelMPC")
        self.options = o0 if options is None else options
        if not isinstance(self.options, SamplingOptions):
            raise TypeError(f"SamplingModelMPC: argument 'options' must be a SamplingOptions, got "
                            f"{type(self.options).__name__}")
        if self.options.common_noise:
            raise ValueError("SamplingModelMPC: options.common_noise must be False (each environment "
                             "draws its own noise, module docstring)")
        self.seed = _int(seed, "seed", 0, "SamplingModelMPC")
        if fill not in ("last", "zero"):
            raise ValueError(f"SamplingModelMPC: argument 'fill' must be 'last' or 'zero', got {fill!r}")
        self.fill = fill
        self._plan: Tensor | None = None
        self._step: Tensor | None = None  # (N,) steps since each environment's episode began
        self._episode: Tensor | None = None  # (N,) episodes since reset(None)
        self._table: Tensor | None = None
        self._cost: dict[tuple, Any] = {}
        self._info: dict[str, Tensor] | None = None

    def _cost_for(self, x: Tensor):
        key = (x.dtype, x.device)
        if key not in self._cost:
            self._cost[key] = self.model.cost(self.horizon, dtype=x.dtype, device=x.device)
        return self._cost[key]

    def _cold(self, N: int, lo: Tensor, hi: Tensor) -> Tensor:
        z = torch.zeros(N, self.horizon, self.model.m, dtype=lo.dtype, device=lo.device)
        return torch.minimum(torch.maximum(z, lo), hi)

    @torch.no_grad()
    def act(self, obs: Tensor) -> Tensor:
        _check_obs(obs, "SamplingModelMPC.act")
        x = self.model.state_from_obs(obs)
        N, m, T = x.shape[0], self.model.m, self.horizon
        lo, hi = _box(self.model, x)
        if self._plan is None or self._plan.shape[0] != N or self._plan.dtype != x.dtype:
            self._plan = self._cold(N, lo, hi)
            self._step = torch.zeros(N, dtype=torch.int64, device=x.device)
            self._episode = torch.zeros(N, dtype=torch.int64, device=x.device)
        k = 2 * ((math.prod((self.options.iterations, self.options.samples,
                             _noise_dims(self.options, T), m)) + 1) // 2)
        if self._table is None or self._table.shape[0] < k or self._table.device != x.device:
            self._table = _steps_table(k, x.device)
        seeds = self.seed + torch.arange(N, dtype=torch.int64, device=x.device)
        counter = (self._episode << 32) + self._step
        noise = _draws(self.options, seeds, counter, T, m, x.dtype, self._table)
        res = plan(self.model.system, self._cost_for(x), x, self._plan.to(x.device), u_lower=lo, u_upper=hi,
                   options=_options_for(self.options, x), noise=noise)
        u = torch.where(res.finite[:, None, None], res.u, self._cold(N, lo, hi))
        self._plan = shift(u, self.fill)
        self._step = self._step + 1
        self._info = {"iterations": torch.full((N,), float(self.options.iterations), dtype=torch.float64,
                                                device=x.device),
                      "cost": res.cost, "fallback": res.fallback}
        return res.u[:, 0].to(dtype=obs.dtype)

    def reset(self, done: Tensor | None = None) -> None:
        if done is not None and (not isinstance(done, Tensor) or done.dtype != torch.bool or done.dim() != 1):
            raise TypeError("SamplingModelMPC.reset: argument 'done' must be None or a bool tensor (N,)")
        if done is None or self._plan is None or done.shape != self._plan.shape[:1]:
            self._plan = self._step = self._episode = None  # all: every environment starts afresh
        else:
            d = done.to(self._plan.device)
            lo, hi = _box(self.model, self._plan)
            self._plan = torch.where(d[:, None, None], self._cold(d.shape[0], lo, hi), self._plan)
            self._step = torch.where(d, 0, self._step)
            self._episode = self._episode + d.long()
        self._info = None

    def info(self) -> dict[str, Tensor] | None:
        return self._info

    def __repr__(self) -> str:
        o = self.options
        return (f"SamplingModelMPC({self.model.env_id}, horizon={self.horizon}, method={o.method.value}, "
                f"samples={o.samples}, iterations={o.iterations}, seed={self.seed})")


@torch.no_grad()
def sampling_guess(model: EnvModel | Any, x: Tensor, horizon: int, *, u_init: Tensor | None = None,
                   options: SamplingOptions | None = None, seed: int = 0) -> Tensor:
    """The sampling planner's plan ``U (N, T, m)`` from states ``x (N, n)``, an initial guess for iLQR.

    Args:
        model: an :class:`EnvModel` (or an id / env with a registered model): its system, cost and box.
        x: ``(N, n)`` states (the model's, not observations).
        horizon: ``T``.
        u_init: ``(N, T, m)`` the nominal to improve (default zeros, clipped into the box).
        options: :class:`SamplingOptions` (default: :func:`default_sampling`'s).
        seed: element ``b`` draws with seed ``seed + b`` (counter 0: the same call gives the same plan).

    Where an element's state is not finite, its guess is ``u_init`` clipped into the box.
    """
    model = env_model(model)
    T = _int(horizon, "horizon", 1, "sampling_guess")
    if not isinstance(x, Tensor) or not x.is_floating_point() or x.dim() != 2 or x.shape[1] != model.n:
        got = f"{tuple(x.shape)} {x.dtype}" if isinstance(x, Tensor) else type(x).__name__
        raise ValueError(f"sampling_guess: argument 'x' must be a floating tensor (N, {model.n}), got {got}")
    N, m = x.shape[0], model.m
    lo, hi = _box(model, x)
    if u_init is None:
        u_init = torch.zeros(N, T, m, dtype=x.dtype, device=x.device)
    elif not isinstance(u_init, Tensor) or u_init.shape != (N, T, m) or u_init.dtype != x.dtype:
        raise ValueError(f"sampling_guess: argument 'u_init' must be a {x.dtype} tensor ({N}, {T}, {m}), got "
                         f"{getattr(u_init, 'shape', type(u_init).__name__)}")
    u_init = torch.minimum(torch.maximum(u_init.to(x.device), lo), hi)
    opts = default_sampling(model)[1] if options is None else options
    if not isinstance(opts, SamplingOptions) or opts.common_noise:
        raise ValueError("sampling_guess: argument 'options' must be a SamplingOptions with "
                         "common_noise=False")
    seeds = _int(seed, "seed", 0, "sampling_guess") + torch.arange(N, dtype=torch.int64, device=x.device)
    noise = _draws(opts, seeds, torch.zeros(N, dtype=torch.int64, device=x.device), T, m, x.dtype)
    res = plan(model.system, model.cost(T, dtype=x.dtype, device=x.device), x, u_init, u_lower=lo,
               u_upper=hi, options=_options_for(opts, x), noise=noise)
    return torch.where(res.finite[:, None, None], res.u, u_init)
