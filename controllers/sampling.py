"""Sampling-based trajectory optimization: MPPI and predictive sampling, batched, with an MPC wrapper.

Both methods improve a nominal control sequence ``U (*B, T, m)`` by random search around it; they need
only rollouts of the system and evaluations of the cost (no derivatives), so any
:class:`~controllers.dynamics.System` and any :class:`~controllers.costs.Cost` works, including costs
that are not smooth.  Every iteration draws ``K`` perturbations ``ε_k`` and rolls out the ``1 + K``
candidates ``V_0 = U`` (the current plan, ``ε_0 = 0``) and ``V_k = clip(U + ε_k)`` for the whole batch
at once: **one** rollout of ``(1 + K, *B)`` sequences per iteration.

* **MPPI** (Williams et al. 2017, *Information-theoretic MPC for model-based reinforcement learning*,
  Alg. 2): with the costs ``S_k`` of the candidates, ``w_k ∝ exp(-(S_k - min_j S_j) / λ)`` and
  ``U ← U + Σ_k w_k (V_k - U)``.  The update uses the *clipped* perturbations ``V_k - U``, so the new
  plan is a convex combination of feasible sequences and respects box limits.  The weighted update can
  be worse than the best candidate (a few good samples averaged with many poor ones, or a non-convex
  cost); :func:`plan` therefore evaluates the final update and returns the **better of the update and
  the best candidate seen** (``SamplingResult.fallback`` marks the elements where the best candidate
  won).  ``elites`` restricts the weights to the best ``elites`` candidates.
* **Predictive sampling** (Howell et al. 2022, *Predictive sampling: real-time behaviour synthesis
  with MuJoCo*): ``U ← argmin_k S_k`` over the candidates.

With ``include_nominal=True`` (default) the current plan ``V_0`` is one of the candidates at every
iteration, so **the returned plan is never worse than the (clipped) nominal under the model**, for both
methods.  With ``include_nominal=False`` ``V_0`` is still rolled out (its cost is reported) but takes no
weight and cannot be selected.

**Noise.** ``ε = σ ⊙ (M z)`` with ``z`` standard normal, ``σ`` the ``noise_sigma`` (float or ``(m,)``
per control, in the physical units of ``u``) and ``M (T, T_z)`` the smoothing map (:class:`NoiseSmoothing`):
``none`` (``M = I``, white noise), ``knots`` (``z`` on ``knots`` knots evenly spread over the horizon,
linearly interpolated in between: the dictionary ``φ`` of seed 004 §6, Eq. 23 with hat functions; the
variance between two knots drops to ``(1-a)² + a²`` of ``σ²``, ``a`` the fraction of the way), or
``lowpass`` (stationary AR(1) ``ε_t = β ε_{t-1} + sqrt(1-β²) σ z_t``: marginal standard deviation ``σ``
at every step, correlation ``β^{|t-s|}``).

**Randomness and reproducibility.** All draws come from the ``generator`` argument, one
``torch.randn`` per iteration of shape ``(*B, K, T_z, m)`` (batch first), or ``(K, T_z, m)`` shared by
the whole batch with ``common_noise=True``.  What holds: element ``b`` of a batched call equals a
single-element call that draws the same ``z`` — with ``common_noise=True`` that is any single-element
call whose generator has the same seed (a batched call equals the per-element loop exactly); with
independent noise, pass the draws explicitly (argument ``noise``, shape ``(I, *B, K, T_z, m)``).

**Layout.** Internally the candidates are stacked *in front of* the batch dims, ``(C, *B, T, m)``, so
that a cost or a system with batch dims of its own (one target or one pendulum length per element,
``(*B, ...)``) broadcasts against the element it belongs to.  The cost must accept the extra leading dim:
``evaluate(x (C, *B, T+1, n), u (C, *B, T, m)) -> (C, *B)``; a system with
``rollout_states(x0 (*B, n), u (*B, T, m)) -> (*B, T+1, n_x)`` (e.g. a MuJoCo model) is rolled out with it,
any other through :func:`controllers.dynamics.rollout`.

**Status.** ``finite (*B,)`` is False where ``x0`` has a NaN/inf entry or no candidate had a finite cost;
those elements get NaN plans, states and costs, and never touch the others (a non-finite ``x0`` is
replaced by zeros before the rollout).  A non-finite candidate cost counts as ``+inf`` (never selected,
zero weight).  Gradients are not cut: they flow through the selected candidates and the MPPI weights
(the plan is a piecewise-smooth function of the draws, of little use as a gradient; a sampling planner
is meant for ``torch.no_grad()``).

:class:`SamplingMPC` runs the planner in receding horizon with explicit state (:class:`SamplingState`
goes in and comes out, holding the shifted plan; nothing is stored on the controller).
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import torch
from torch import Tensor

from controllers._validate import all_finite, check_limit, enum_arg
from controllers.dynamics import check_system, rollout
from controllers.mpc import shift
from torchlie._batch import broadcast_shapes

__all__ = ["SamplingMethod", "NoiseSmoothing", "SamplingOptions", "SamplingResult", "plan",
           "smoothing_matrix", "SamplingState", "SamplingMPC"]


class SamplingMethod(str, enum.Enum):
    MPPI = "mppi"  #: weighted average of the candidates, ``w ∝ exp(-S/λ)`` (Williams et al. 2017)
    PREDICTIVE = "predictive"  #: keep the best candidate (Howell et al. 2022)


class NoiseSmoothing(str, enum.Enum):
    NONE = "none"  #: white noise, independent at every step
    KNOTS = "knots"  #: noise on ``knots`` knots, linearly interpolated (a piecewise-linear spline)
    LOWPASS = "lowpass"  #: stationary AR(1) low-pass filtered noise with coefficient ``lowpass``


def _positive_int(v, name: str) -> None:
    if not isinstance(v, int) or isinstance(v, bool) or v < 1:
        raise ValueError(f"SamplingOptions: field '{name}' must be an int >= 1, got {v!r}")


@dataclass(frozen=True, eq=False)
class SamplingOptions:
    """Options of :func:`plan` (module docstring).

    Attributes:
        samples: ``K`` perturbed candidates per iteration (the current plan is rolled out in addition).
        iterations: sample–update rounds per call.
        noise_sigma: ``σ``, a float or a ``(m,)`` tensor (one per control), standard deviation of the
            perturbations in the units of ``u``; ``>= 0``.
        temperature: ``λ > 0`` of MPPI (small: close to the best candidate; large: close to the mean).
        method: :class:`SamplingMethod` (``"mppi"`` or ``"predictive"``).
        smoothing: :class:`NoiseSmoothing` (``"none"``, ``"knots"``, ``"lowpass"``).
        knots: number of knots for ``smoothing="knots"`` (``>= 2``; capped at ``T``).
        lowpass: AR(1) coefficient ``β ∈ [0, 1)`` for ``smoothing="lowpass"``.
        include_nominal: the current plan is a candidate (never worse than the nominal; module docstring).
        elites: MPPI only: ``None`` (all candidates weighted) or the number of best candidates that get
            a weight.
        common_noise: one draw ``(K, T_z, m)`` shared by every batch element (independent by default).
    """

    samples: int = 256
    iterations: int = 1
    noise_sigma: float | Tensor = 1.0
    temperature: float = 1.0
    method: SamplingMethod | str = SamplingMethod.MPPI
    smoothing: NoiseSmoothing | str = NoiseSmoothing.NONE
    knots: int = 4
    lowpass: float = 0.5
    include_nominal: bool = True
    elites: int | None = None
    common_noise: bool = False

    def __post_init__(self) -> None:
        own = "SamplingOptions"
        _positive_int(self.samples, "samples")
        _positive_int(self.iterations, "iterations")
        object.__setattr__(self, "method", enum_arg(SamplingMethod, self.method, "method", own))
        object.__setattr__(self, "smoothing", enum_arg(NoiseSmoothing, self.smoothing, "smoothing", own))
        t = self.temperature
        if isinstance(t, bool) or not isinstance(t, (int, float)) or not math.isfinite(t) or t <= 0:
            raise ValueError(f"{own}: field 'temperature' must be a finite float > 0, got {t!r}")
        s = self.noise_sigma
        if isinstance(s, Tensor):
            if not s.dtype.is_floating_point or s.dim() > 1:
                raise ValueError(f"{own}: field 'noise_sigma' must be a float or a floating (m,) tensor, "
                                 f"got {s.dtype} {tuple(s.shape)}")
            if not bool(torch.isfinite(s).all() & (s >= 0).all()):
                raise ValueError(f"{own}: field 'noise_sigma' must be finite and >= 0")
        elif isinstance(s, bool) or not isinstance(s, (int, float)) or not (0 <= s < math.inf):
            raise ValueError(f"{own}: field 'noise_sigma' must be a finite float >= 0 or an (m,) tensor, "
                             f"got {s!r}")
        if not isinstance(self.knots, int) or isinstance(self.knots, bool) or self.knots < 2:
            raise ValueError(f"{own}: field 'knots' must be an int >= 2, got {self.knots!r}")
        b = self.lowpass
        if isinstance(b, bool) or not isinstance(b, (int, float)) or not 0 <= b < 1:
            raise ValueError(f"{own}: field 'lowpass' must be a float in [0, 1), got {b!r}")
        if self.elites is not None:
            _positive_int(self.elites, "elites")


@dataclass(frozen=True, eq=False)
class SamplingResult:
    """Result of :func:`plan` (batch shape ``*B`` of ``x0`` and ``u_nominal`` broadcast).

    Attributes:
        u: ``(*B, T, m)`` the new plan (within the limits).
        x: ``(*B, T+1, n_x)`` its rollout.
        cost: ``(*B,)`` its cost.
        nominal_cost: ``(*B,)`` cost of the (clipped) nominal; ``cost <= nominal_cost`` with
            ``include_nominal``.
        best_cost: ``(*B,)`` lowest cost among the perturbed samples of all iterations.
        update_cost: ``(*B,)`` cost of the last MPPI weighted update (predictive: equals ``cost``).
        fallback: ``(*B,)`` bool, MPPI only: the final update was worse than the best candidate seen,
            which was returned instead.
        costs_history: ``(*B, iterations + 1)`` cost of the iterate ``U_i`` (index 0: the nominal).
        finite: ``(*B,)`` bool, the element's ``x0`` and returned cost are finite (else NaN plan).
    """

    u: Tensor
    x: Tensor
    cost: Tensor
    nominal_cost: Tensor
    best_cost: Tensor
    update_cost: Tensor
    fallback: Tensor
    costs_history: Tensor
    finite: Tensor


def smoothing_matrix(options: SamplingOptions, T: int, dtype: torch.dtype = torch.float64,
                     device: torch.device | str | None = None) -> Tensor | None:
    """The map ``M (T, T_z)`` from standard normal draws ``z (…, T_z, m)`` to unit-scale noise ``M z``
    (module docstring); ``None`` for white noise (``M = I``, ``T_z = T``)."""
    mode = options.smoothing
    if mode is NoiseSmoothing.NONE or T == 1:
        return None
    t = torch.arange(T, dtype=dtype, device=device)
    if mode is NoiseSmoothing.KNOTS:
        k = min(options.knots, T)
        pos = torch.linspace(0, T - 1, k, dtype=dtype, device=device)
        h = (T - 1) / (k - 1)
        return (1 - (t[:, None] - pos[None, :]).abs() / h).clamp_min(0)  # hat functions (T, k)
    beta = options.lowpass
    lag = t[:, None] - t[None, :]
    M = torch.where(lag >= 0, beta ** lag.clamp_min(0), torch.zeros((), dtype=dtype, device=device))
    M[:, 1:] *= math.sqrt(1 - beta * beta)  # z_0 starts the stationary process, later z_s drive it
    return M


def _noise_dims(options: SamplingOptions, T: int) -> int:
    if options.smoothing is NoiseSmoothing.KNOTS and T > 1:
        return min(options.knots, T)
    return T


def _check_inputs(system, x0, u_nominal) -> tuple[Tensor, Tensor, torch.Size]:
    check_system(system, "plan", "system")
    n, m = int(system.n), int(system.m)
    for name, v in (("x0", x0), ("u_nominal", u_nominal)):
        if not isinstance(v, Tensor) or not v.dtype.is_floating_point:
            raise TypeError(f"plan: argument '{name}' must be a floating torch.Tensor, got "
                            f"{getattr(v, 'dtype', type(v).__name__)}")
    if x0.dim() < 1 or x0.shape[-1] != n:
        raise ValueError(f"plan: argument 'x0' must have shape (*B, {n}), got {tuple(x0.shape)}")
    if u_nominal.dim() < 2 or u_nominal.shape[-1] != m or u_nominal.shape[-2] < 1:
        raise ValueError(f"plan: argument 'u_nominal' must have shape (*B, T, {m}) with T >= 1, got "
                         f"{tuple(u_nominal.shape)}")
    if u_nominal.dtype != x0.dtype or u_nominal.device != x0.device:
        raise TypeError(f"plan: argument 'u_nominal' must have the dtype and device of x0 ({x0.dtype}, "
                        f"{x0.device}), got {u_nominal.dtype}, {u_nominal.device}")
    try:
        bs = broadcast_shapes(x0.shape[:-1], u_nominal.shape[:-2])
    except RuntimeError:
        raise ValueError(f"plan: batch dims of 'x0' {tuple(x0.shape)} and 'u_nominal' "
                         f"{tuple(u_nominal.shape)} do not broadcast") from None
    T = u_nominal.shape[-2]
    return x0.expand(*bs, n), u_nominal.expand(*bs, T, m), bs


def _limit(v, name: str, T: int, m: int, like: Tensor) -> Tensor | None:
    v = check_limit(v, name, "plan", T, m)
    if v is None:
        return None
    if isinstance(v, float):
        return torch.tensor(v, dtype=like.dtype, device=like.device)
    if v.dtype != like.dtype:
        raise TypeError(f"plan: argument '{name}' has dtype {v.dtype} but x0 has {like.dtype}")
    return v.to(like.device)


def _clip(u: Tensor, lo: Tensor | None, hi: Tensor | None) -> Tensor:
    if lo is not None:
        u = torch.maximum(u, lo)
    if hi is not None:
        u = torch.minimum(u, hi)
    return u


def _sigma(options: SamplingOptions, m: int, like: Tensor) -> Tensor | float:
    s = options.noise_sigma
    if not isinstance(s, Tensor):
        return float(s)
    if s.dim() == 1 and s.shape[0] not in (1, m):
        raise ValueError(f"plan: options.noise_sigma must be a float or have shape ({m},), "
                         f"got {tuple(s.shape)}")
    if s.dtype != like.dtype:
        raise TypeError(f"plan: options.noise_sigma has dtype {s.dtype} but x0 has {like.dtype}")
    return s.to(like.device)


def _draws(options: SamplingOptions, bs: torch.Size, Tz: int, m: int, like: Tensor, generator, noise
           ) -> Tensor | None:
    """Validated explicit draws ``(I, *B', K, T_z, m)``, or None (draw from ``generator`` per iteration)."""
    if noise is None:
        if not isinstance(generator, torch.Generator):
            raise TypeError("plan: argument 'generator' must be a torch.Generator (randomness is explicit), "
                            f"got {type(generator).__name__}")
        return None
    want = (options.iterations, options.samples, Tz, m)
    if not isinstance(noise, Tensor) or noise.dtype != like.dtype or noise.dim() < 4 or (
            noise.shape[0], *noise.shape[-3:]) != want:
        raise ValueError(f"plan: argument 'noise' must be a {like.dtype} tensor (I, *B, K, T_z, m) = "
                         f"({want[0]}, *B, {want[1]}, {want[2]}, {want[3]}), got "
                         f"{getattr(noise, 'shape', type(noise).__name__)}")
    try:
        broadcast_shapes(noise.shape[1:-3], bs)
    except RuntimeError:
        raise ValueError(f"plan: batch dims of argument 'noise' {tuple(noise.shape)} do not broadcast to "
                         f"{tuple(bs)}") from None
    return noise.to(like.device)


def _perturbations(i: int, options: SamplingOptions, bs, Tz: int, m: int, M, sigma, like, generator, noise
                   ) -> Tensor:
    """``ε (K, *B', T, m)`` of iteration ``i`` (``*B'``: the draw's batch dims, broadcasting to ``*B``)."""
    if noise is not None:
        z = noise[i]
    else:
        shape = (options.samples, Tz, m) if options.common_noise else (*bs, options.samples, Tz, m)
        z = torch.randn(shape, generator=generator, dtype=like.dtype, device=like.device)
    z = z.movedim(-3, 0)  # candidates in front of the batch dims, missing batch dims as singletons
    z = z.reshape(z.shape[0], *([1] * (len(bs) + 3 - z.dim())), *z.shape[1:])
    if M is not None:
        z = M @ z
    return z * sigma


def _evaluate(system, cost, x0: Tensor, u: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Roll out ``u (C, *B, T, m)`` from ``x0 (*B, n)``: ``x (C, *B, T+1, n_x)``, raw cost ``(C, *B)`` and
    the cost with non-finite values as ``+inf``."""
    x0c = x0.expand(u.shape[0], *x0.shape)
    fn = getattr(system, "rollout_states", None)
    x = fn(x0c, u) if callable(fn) else rollout(system, x0c, u)
    S = cost.evaluate(x, u)
    if not isinstance(S, Tensor) or S.shape != u.shape[:-2]:
        raise ValueError(f"plan: cost.evaluate(x {tuple(x.shape)}, u {tuple(u.shape)}) must return the "
                         f"leading dims {tuple(u.shape[:-2])} (it must accept extra leading batch dims), "
                         f"got {getattr(S, 'shape', type(S).__name__)}")
    inf = torch.full((), math.inf, dtype=S.dtype, device=S.device)
    return x, S, torch.where(torch.isnan(S), inf, S)


def _pick(V: Tensor, idx: Tensor) -> Tensor:
    """``V[idx[b], b]`` for ``V (C, *B, ...)`` and ``idx (*B,)``."""
    nb = idx.dim()
    index = idx.reshape(1, *idx.shape, *([1] * (V.dim() - 1 - nb))).expand(1, *V.shape[1:])
    return V.gather(0, index).squeeze(0)


def _weights(S: Tensor, eligible: Tensor, options: SamplingOptions) -> Tensor:
    """MPPI weights ``(C, *B)`` over the eligible candidates with finite cost; all zero where none."""
    S = torch.where(eligible, S, math.inf)
    if options.elites is not None and options.elites < S.shape[0]:
        kth = S.topk(options.elites, dim=0, largest=False).values[-1]
        S = torch.where(S <= kth, S, math.inf)
    smin = S.amin(0)
    z = torch.where(torch.isfinite(S), -(S - smin) / options.temperature, -math.inf)
    return torch.softmax(z, 0).nan_to_num(nan=0.0)


@dataclass
class _Best:
    """Best selectable candidate so far (mutable loop state of :func:`plan`, never returned)."""

    u: Tensor
    x: Tensor
    S: Tensor

    def update(self, V: Tensor, X: Tensor, S: Tensor) -> None:
        k = S.argmin(0)
        s = S.amin(0)
        better = s < self.S
        self.u = torch.where(better[..., None, None], _pick(V, k), self.u)
        self.x = torch.where(better[..., None, None], _pick(X, k), self.x)
        self.S = torch.where(better, s, self.S)


def _iterate(system, cost, x0, U, lo, hi, options, draw) -> tuple:
    """The sample–update loop (module docstring). Returns ``(U, X_U, S_U, best, history, best_sample)``."""
    mppi = options.method is SamplingMethod.MPPI
    best, history, sample_min = None, [], None
    for i in range(options.iterations):
        V = torch.cat([U.unsqueeze(0), _clip(U + draw(i), lo, hi)], 0)  # (1 + K, *B, T, m)
        X, _, S = _evaluate(system, cost, x0, V)
        history.append(S[0])
        eligible = torch.ones_like(S, dtype=torch.bool)
        eligible[0] = options.include_nominal
        Se = torch.where(eligible, S, math.inf)
        s = S[1:].amin(0)
        sample_min = s if sample_min is None else torch.minimum(sample_min, s)
        if best is None:
            best = _Best(U, X[0], torch.full_like(S[0], math.inf))
        best.update(V, X, Se)
        if mppi:
            w = _weights(S, eligible, options)
            U = U + (w[..., None, None] * (V - U)).sum(0)
        else:
            U = _pick(V, Se.argmin(0))
            last = Se.amin(0)
    if mppi:
        X_U, _, S_U = _evaluate(system, cost, x0, U.unsqueeze(0))
        X_U, S_U = X_U[0], S_U[0]
        history.append(S_U)
    else:  # the best selected plan of all iterations (the last one when the nominal is a candidate)
        U, X_U, S_U = best.u, best.x, best.S
        history.append(last)
    return U, X_U, S_U, best, torch.stack(history, -1), sample_min


def plan(system, cost, x0: Tensor, u_nominal: Tensor, *, u_lower=None, u_upper=None,
         options: SamplingOptions | None = None, generator: torch.Generator | None = None,
         noise: Tensor | None = None) -> SamplingResult:
    """Improve ``u_nominal`` by MPPI or predictive sampling (module docstring).

    Args:
        system: a :class:`~controllers.dynamics.System` (or anything with ``n``, ``m``, ``step`` and,
            preferred when present, ``rollout_states(x0, u)``).
        cost: a :class:`~controllers.costs.Cost` accepting extra leading dims (``(C, *B, T+1, n)`` in).
        x0: ``(*B, n)`` initial states.
        u_nominal: ``(*B, T, m)`` nominal controls (the batch dims of both broadcast).
        u_lower, u_upper: ``None``, floats or tensors broadcastable to ``(*B, T, m)``; every candidate
            (the nominal included) is clipped before its rollout, and what is evaluated is returned.
        options: :class:`SamplingOptions` (default ``SamplingOptions()``).
        generator: the ``torch.Generator`` of every draw, on the device of ``x0`` (required unless
            ``noise`` is given).
        noise: optional standard normal draws ``(I, *B', K, T_z, m)`` used instead of the generator
            (``I`` iterations, ``*B'`` broadcasting to ``*B``, ``T_z`` from :func:`smoothing_matrix`).

    Returns:
        :class:`SamplingResult`.
    """
    options = SamplingOptions() if options is None else options
    if not isinstance(options, SamplingOptions):
        raise TypeError(f"plan: argument 'options' must be a SamplingOptions, got {type(options).__name__}")
    if not callable(getattr(cost, "evaluate", None)):
        raise TypeError(f"plan: argument 'cost' must have evaluate(x, u) (controllers.costs.Cost), got "
                        f"{type(cost).__name__}")
    x0, u_nom, bs = _check_inputs(system, x0, u_nominal)
    T, m = u_nom.shape[-2:]
    lo, hi = (_limit(v, k, T, m, x0) for k, v in (("u_lower", u_lower), ("u_upper", u_upper)))
    sigma = _sigma(options, m, x0)
    Tz = _noise_dims(options, T)
    noise = _draws(options, bs, Tz, m, x0, generator, noise)
    M = smoothing_matrix(options, T, x0.dtype, x0.device)
    ok = all_finite(x0, 1)
    x0s = torch.where(ok[..., None], x0, torch.zeros((), dtype=x0.dtype, device=x0.device))

    def draw(i: int) -> Tensor:
        return _perturbations(i, options, bs, Tz, m, M, sigma, x0, generator, noise)

    U, X_U, S_U, best, hist, sample_min = _iterate(system, cost, x0s, _clip(u_nom, lo, hi), lo, hi,
                                                   options, draw)
    fallback = best.S < S_U
    u = torch.where(fallback[..., None, None], best.u, U)
    x = torch.where(fallback[..., None, None], best.x, X_U)
    c = torch.minimum(S_U, best.S)
    fin = ok & torch.isfinite(c)
    nan = torch.full((), math.nan, dtype=x0.dtype, device=x0.device)
    u, x = torch.where(fin[..., None, None], u, nan), torch.where(fin[..., None, None], x, nan)
    keep = lambda v: torch.where(fin, v, nan)  # noqa: E731
    return SamplingResult(u=u, x=x, cost=keep(c), nominal_cost=keep(hist[..., 0]), best_cost=keep(sample_min),
                          update_cost=keep(S_U), fallback=fallback & fin,
                          costs_history=torch.where(fin[..., None], hist, nan), finite=fin)


# --------------------------------------------------------------------------------------------------
# receding horizon
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class SamplingState:
    """Warm start of :class:`SamplingMPC` (immutable; every method returns a new state).

    Attributes:
        u: ``(*B, T, m)`` nominal controls of the next call (the previous plan shifted by one step),
            without a graph.
        cost: ``(*B,)`` predicted cost of the plan that produced it (NaN for a cold start).
    """

    u: Tensor
    cost: Tensor

    @property
    def batch_shape(self) -> torch.Size:
        return self.cost.shape

    def reset(self, done: Tensor) -> SamplingState:
        """Cold-start (zero plan) the elements where ``done`` (bool, the batch shape) is True."""
        if not isinstance(done, Tensor) or done.dtype != torch.bool or done.shape != self.batch_shape:
            raise ValueError(f"SamplingState.reset: argument 'done' must be a bool tensor of shape "
                             f"{tuple(self.batch_shape)}, got {getattr(done, 'shape', type(done).__name__)}")
        done = done.to(self.u.device)
        return SamplingState(u=torch.where(done[..., None, None], 0.0, self.u),
                             cost=torch.where(done, math.nan, self.cost))


@dataclass(frozen=True, eq=False)
class SamplingMPC:
    """Receding-horizon sampling MPC: ``(u0, next_state, result) = mpc(x, state, generator)``.

    Attributes:
        system, cost: as in :func:`plan`; the cost is over ``horizon`` steps and re-used at every call.
        horizon: ``T``.
        options: :class:`SamplingOptions`.
        u_lower, u_upper: control limits (as in :func:`plan`).
        fill: how the shifted plan's new last step is filled, ``"last"`` (repeat) or ``"zero"``
            (:func:`controllers.mpc.shift`).
    """

    system: object
    cost: object
    horizon: int
    options: SamplingOptions = SamplingOptions()
    u_lower: Tensor | float | None = None
    u_upper: Tensor | float | None = None
    fill: str = "last"

    def __post_init__(self) -> None:
        check_system(self.system, "SamplingMPC", "system")
        if not isinstance(self.horizon, int) or isinstance(self.horizon, bool) or self.horizon < 1:
            raise ValueError(f"SamplingMPC: field 'horizon' must be an int >= 1, got {self.horizon!r}")
        if self.fill not in ("last", "zero"):
            raise ValueError(f"SamplingMPC: field 'fill' must be 'last' or 'zero', got {self.fill!r}")
        if not isinstance(self.options, SamplingOptions):
            raise TypeError("SamplingMPC: field 'options' must be a SamplingOptions")

    def initial_state(self, batch_shape: int | tuple[int, ...] | torch.Size = (), *,
                      dtype: torch.dtype | None = None, device: torch.device | str | None = None
                      ) -> SamplingState:
        """A cold start (zero plan) for a batch of shape ``batch_shape``."""
        bs = (batch_shape,) if isinstance(batch_shape, int) else tuple(batch_shape)
        if any(not isinstance(b, int) or b < 0 for b in bs):
            raise ValueError(f"SamplingMPC.initial_state: argument 'batch_shape' must be an int or a tuple "
                             f"of non-negative ints, got {batch_shape!r}")
        dtype = torch.get_default_dtype() if dtype is None else dtype
        return SamplingState(u=torch.zeros(*bs, self.horizon, int(self.system.m), dtype=dtype, device=device),
                             cost=torch.full(bs, math.nan, dtype=dtype, device=device))

    def __call__(self, x: Tensor, state: SamplingState, generator: torch.Generator
                 ) -> tuple[Tensor, SamplingState, SamplingResult]:
        """Plan from ``x (*B, n)`` warm-started by ``state``; returns ``(u0 (*B, m), next_state, result)``.

        The next state holds the plan shifted by one step, detached; where the plan is not finite (a NaN
        state) the warm start restarts from zeros."""
        if not isinstance(state, SamplingState):
            raise TypeError(f"SamplingMPC: argument 'state' must be a SamplingState (initial_state()), got "
                            f"{type(state).__name__}")
        if state.u.shape[-2] != self.horizon:
            raise ValueError(f"SamplingMPC: the state's plan has horizon {state.u.shape[-2]}, expected "
                             f"{self.horizon}")
        res = plan(self.system, self.cost, x, state.u, u_lower=self.u_lower, u_upper=self.u_upper,
                   options=self.options, generator=generator)
        u = res.u.detach()
        u = torch.where(res.finite[..., None, None], u, torch.zeros((), dtype=u.dtype, device=u.device))
        nxt = SamplingState(u=shift(u, self.fill), cost=res.cost.detach())
        return res.u[..., 0, :], nxt, res
