"""Imitation of unknown dynamics through the differentiable MPC (issue 26 §4; Amos et al. 2018, §5.2).

An expert plans with iLQR (:func:`controllers.ilqr.ilqr`, seed 004 §8, Algorithm 5) over ``T = 20`` steps on
the true model; a learner plans with the same cost on a model whose physical parameters ``θ`` are unknown.
From demonstrations — start states ``x_0`` and the expert's optimal control sequences ``u*_{0:T-1}`` — the
learner fits ``θ`` by minimizing the imitation loss

    L(θ) = 1/(N T m) Σ_i Σ_t ‖u_t(x_0^i; θ) − u*_t(x_0^i)‖²,

with ``du(θ)/dθ`` from the implicit gradient of the iLQR solution (``grad="implicit"``: the KKT conditions
at the returned point, :mod:`controllers.implicit`).  ``θ`` is log-parametrized (positive) and fitted in
two phases (``optimizer="lbfgs+gauss_newton"``): L-BFGS on ``L``'s gradient (one backward pass per
evaluation, strong-Wolfe line search) for ``warmup = 30`` evaluations, then Gauss-Newton with
Levenberg-Marquardt damping on the residuals ``u − u*`` (their Jacobian by ``T·m`` backward passes through
the implicit gradient).  Measured reasons (cart-pole, 10 demos): L-BFGS alone left the pole mass 1.6 % off
after 100 evaluations (the Gauss-Newton matrix has condition number ~10⁴: the pole mass moves the controls
little); Gauss-Newton alone reaches 10⁻⁵ in ~40 evaluations on three seeds but on the fourth its first,
greedy steps lengthen the pole and then drive the pole mass to 0, a spurious minimum (loss 32 against
206 at the start); L-BFGS first, then Gauss-Newton, reaches ≤ 3·10⁻⁵ on all four.  Each phase alone is
available (``"gauss_newton"``, ``"lbfgs"``, and ``"adam"``).

**Setup** (:func:`imitation_setup`; the systems of :mod:`controllers.systems`, ``dt = 0.05``):

* pendulum ``x = [θ, ω]`` (``θ = π`` upright), true ``(g, m, l) = (10, 1, 1)``, learner starts from
  ``(15, 3, 0.5)`` (Amos et al.'s values); cost ``Σ_t (x_t − x̄)ᵀ Q (x_t − x̄) + r u_t²`` with
  ``x̄ = [π, 0]``, ``Q = diag(1, 0.1)``, ``r = 10⁻³`` on ``x_0 .. x_T``, ``u_0 .. u_{T-1}`` (Amos et al.'s
  weights 1, 1, 0.1 on ``(cos, sin, θ̇)`` and 10⁻³ on ``u`` give ``≈ θ̃² + 0.1 ω²`` near upright; ours is the
  quadratic in the unwrapped angle), ``|τ| ≤ 20`` (below);
* cart-pole ``x = [p, θ, ṗ, θ̇]``, true ``(g, m_c, m_p, l) = (9.8, 1, 0.1, 0.5)``, learner from
  ``(9.8, 3, 0.1, 1)``; ``x̄ = [0, π, 0, 0]``, ``Q = diag(0.1, 1, 0.1, 0.1)``, ``r = 10⁻³``, ``|F| ≤ 100``
  (Amos et al.'s force limit).

Start states (seeded ``torch.Generator``): ``θ_0 ∈ π + U(−1, 1)``, velocities ``U(−1, 1)``, cart position
``U(−0.5, 0.5)``.  The pendulum's torque limit is ours, ``|τ| ≤ 20`` (``u_limit=`` changes it): with Amos et
al.'s limit of 2 from starts anywhere on the circle every expert control is on its bound (measured: 100 % of
them from ``θ_0 ∈ π + U(−π, π)``; 68 % even within 0.5 rad of upright); a clamped control does not depend on
``θ`` at all, and the loss reaches 0 at wrong parameters — the data carry no information.  With ``|τ| ≤ 10``
(15-20 % of the expert's controls clamped) the loss over ``(g/l, 1/(m l²))`` is a staircase of flat terraces
(each a pattern of controls the learner clamps and the expert does not) around a curved valley
``g m l ≈ 10``; from Amos et al.'s start seed 3 stops on a terrace (identifiable error 6.8, with the default
optimizer and with L-BFGS alone; Gauss-Newton alone stops on one for seeds 1-3), the other seeds reach
10⁻⁹.  With ``|τ| ≤ 20`` (3 % clamped) all four reach 10⁻⁹.  The expert's demos are one batched solve from
zero controls (:func:`learning.demos.expert_demos`); held-out starts are drawn from the same generator
first, so the held-out set of a seed is the same for every ``n_train`` and the training sets are nested.

**Identifiability.**  The controls depend on ``θ`` only through the model's step, i.e. through the
acceleration (semi-implicit Euler, :mod:`controllers.systems._mechanical`).

* Pendulum (:meth:`~controllers.systems.pendulum.Pendulum.acceleration`, damping ``b``)::

      ω̇ = (u − b ω) / (m l²) − (g / l) sin θ = c u − β ω − a sin θ,
      a = g / l,   c = 1 / (m l²),   β = b / (m l²).

  Only two combinations of ``(g, m, l)`` are identifiable (``b = 0``): any ``(g, m, l)`` with the
  same ``(a, c)`` gives the same model, the same optimal controls and the same loss — the direction
  ``d log(g, m, l) ∝ (1, −2, 1)`` is a null direction of ``du/d log θ``.  The physical parameters found
  depend on the start and the path; they cannot be "within 1 %" except by luck.  Measured: from Amos et
  al.'s start, with the default optimizer, every seed ends at ``(g, m, l) = (6.609, 2.289, 0.661)``
  (errors 34 %, 129 %, 34 %), the point with the true ``(a, c)`` nearest to the start in ``log θ``:
  gradient steps never move along the null direction (Gauss-Newton alone, with its per-parameter scaling,
  ends elsewhere on that line).  The goal is judged on ``(a, c)``, reported under ``"g/l"`` and
  ``"1/(m l^2)"``.
* Cart-pole (:meth:`~controllers.systems.cartpole.CartPole.acceleration`), with ``μ = m_p / m_c``,
  ``s = sin θ``, ``c = cos θ``::

      p̈ = (F / m_c + μ s (l θ̇² + g c)) / (1 + μ s²),
      θ̈ = −(F c / (m_c l) + μ θ̇² s c + (1 + μ) (g / l) s) / (1 + μ s²).

  The coefficient of ``F`` in ``p̈`` gives ``m_c`` and (through its dependence on ``s``) ``μ``, hence
  ``m_p``; the ``θ̇² s`` term gives ``μ l``, hence ``l``; the ``s c`` term gives ``μ g``, hence ``g``.  The
  map from ``(g, m_c, m_p, l)`` to the model is injective: all four physical parameters are identifiable,
  and the identifiable combinations are the physical parameters themselves (the Jacobian of the expert's
  controls w.r.t. ``log θ``, :func:`control_jacobian`, has rank 4 at the data; the pendulum's rank 2).

  Identifiability of the *model* is necessary, not sufficient: the controls must also respond to every
  direction (clamped controls do not; the torque limit above is chosen for that), which the rank of
  ``du/d log θ`` at the data shows (:func:`control_jacobian`).

**Unconverged solves are never silently dropped.**  Every loss evaluation records each training sample's
solver status (:class:`~controllers.problem.SolverStatus`).  ``unconverged="include"`` (default here)
keeps a non-converged sample with the implicit gradient at its last iterate (exact only for the problem
linearized there, :func:`controllers.ilqr.ilqr`); ``"exclude"`` removes it from that evaluation's mean, so
that every gradient is the exact one of an optimal plan.  The default differs from :mod:`learning.ioc`'s
(``"exclude"``, whose LQ solvers always converge) for a measured reason: dropping a sample from the loss
lets the fit lower the loss by leaving samples unconverged.  Cart-pole, 100 demos, seeds 0-3: with
``"exclude"`` three of four seeds ended 15-100 % off (36-161 excluded solves, loss evaluations at
parameters where many solves hit the iteration cap); with ``"include"`` seed 1 reached 1.4e-5 (138
non-converged solves counted).  A third policy — the error kept in the value, the gradient excluded — is
not provided yet.  Either way the history lists,
per evaluation, which samples did not converge and why, and how many were excluded.  A sample whose solve
returned non-finite controls (a failed input, a diverged rollout) or whose demo is non-finite cannot be
included: under both policies it counts as the worst possible error ``(2 u_limit)²`` with a zero gradient
(:func:`imitation_loss`) and is counted in ``n_nonfinite``; an evaluation with no usable sample at all has
that loss too (never 0, which would read as a perfect fit).  The record of :func:`learn_dynamics` is strict
JSON: a non-finite value (e.g. parameters overflowed by a too large step) is written as ``null`` and its
path listed in ``"nonfinite_values"``.

**Baselines** (in each record of :func:`learn_dynamics`): system identification — the same parameters
fitted by Levenberg-Marquardt to the demos' state transitions ``(x_t, u_t) → x_{t+1}`` (least squares on
the predicted next state; states are observed here, the imitation learner sees only ``x_0`` and ``u*``) and
the held-out imitation error of an MPC with the identified parameters; behaviour cloning — an MLP
(:class:`learning.bc.MLPPolicy`) and an LSTM mapping ``x_0`` to the whole sequence ``u_{0:T-1}``
(``u_max · tanh``), trained by full-batch Adam on the same training starts.

**Non-realizable variant** (``expert_damping > 0``, pendulum): the expert's pendulum has damping ``b``; the
learner's damping is fixed at 0 and it fits ``(g, m, l)`` anyway.  The relative errors are then against the
expert's ``(g, m, l)`` and its ``(a, c)``; the record also holds the expert's ``β = b / (m l²)``.
Measured (``b = 0.5``, 10 demos, 4 seeds): the learner compensates with ``g/l`` 18-21 % and ``1/(m l²)``
5-8 % too large; held-out MSE 1.1-2.1·10⁻² (system identification on the transitions: 1.2-2.0·10⁻²;
the initial model 21-31; behaviour cloning 0.6-3.8).

Held-out imitation MSE: the learner's MPC (learned parameters, solved from zero controls like the expert)
against the expert's controls on ``n_test`` held-out starts, in squared control units (N²m² for the
pendulum, N² for the cart-pole; ``u_limit`` is in the record to normalize).

**Under torchrun** (``W > 1`` ranks of :mod:`torch.distributed`, every rank calling :func:`learn_dynamics`
with the same arguments; ``docs/distributed.md``): every rank draws the same starts and solves the expert's
demos (one batched solve, unchanged), then each rank solves only its contiguous block of the training demos
(:func:`learning.distributed.shard`) in every loss evaluation.  The loss is the global mean: one all-reduce
of this rank's sum (included errors plus the worst error per non-finite sample) and count per evaluation.
L-BFGS gets the global gradient: each rank backpropagates its sum over the global count and the gradient of
``log θ`` is all-reduced after the backward (``θ`` is a plain tensor, not an ``nn.Module``: this explicit
all-reduce of ``.grad`` is the analogue of DistributedDataParallel's).  Gauss-Newton gathers the residuals
and Jacobian rows of every rank in sample order, so that every rank forms the same normal equations and
takes the same step.  The per-sample statuses are gathered for the history (global sample indices), so
every rank's history is the same; the held-out evaluation runs on every rank unchanged (same parameters,
same numbers); the baselines run on rank 0 only and its baseline records and the slowest rank's times are
shared, so that every rank returns the same record (plus ``"world_size"``).  A single process runs none of
this and is bit-for-bit what it was; ``W`` ranks match it to round-off (the sums are taken in another order).
"""

from __future__ import annotations

import inspect
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import torch
from torch import Tensor, nn

from controllers.costs import QuadraticCost
from controllers.ilqr import ILQROptions, ILQRProblem, ILQRSolution, ilqr
from controllers.problem import Reason
from controllers.systems.cartpole import CartPole
from controllers.systems.pendulum import Pendulum
from learning import distributed as _dist
from learning.bc import MLPPolicy
from learning.demos import Demonstrations, expert_demos

__all__ = ["SYSTEMS", "EXPERT_OPTIONS", "ImitationSetup", "imitation_setup", "identifiable_combinations",
           "imitation_loss", "ImitationLoss", "control_jacobian", "learn_dynamics", "imitation_study",
           "system_identification", "behaviour_cloning"]

#: the systems :func:`imitation_setup` knows
SYSTEMS = ("pendulum", "cartpole")
_UNCONVERGED = ("include", "exclude")
_WARM = ("expert", "previous")
_OPTIMIZERS = ("lbfgs+gauss_newton", "gauss_newton", "lbfgs", "adam")
_BASELINES = ("sysid", "mlp", "lstm")
#: options of the expert's and every held-out solve (from zero controls the cart-pole takes up to ~400
#: iterations)
EXPERT_OPTIONS = ILQROptions(max_iter=500)

_SPEC = {
    "pendulum": dict(names=("gravity", "mass", "length"), true=(10.0, 1.0, 1.0), init=(15.0, 3.0, 0.5),
                     x_ref=(math.pi, 0.0), Q=(1.0, 0.1), r=1e-3, u_limit=20.0),
    "cartpole": dict(names=("gravity", "cart_mass", "pole_mass", "length"), true=(9.8, 1.0, 0.1, 0.5),
                     init=(9.8, 3.0, 0.1, 1.0), x_ref=(0.0, math.pi, 0.0, 0.0), Q=(0.1, 1.0, 0.1, 0.1),
                     r=1e-3, u_limit=100.0),
}


# --------------------------------------------------------------------------------------------------
# setup
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class ImitationSetup:
    """The expert's problem family and the learner's parameters (module docstring).

    Attributes:
        system: ``"pendulum"`` or ``"cartpole"``.
        param_names: the learned physical parameters, named as the fields of the model
            (:class:`~controllers.systems.pendulum.Pendulum`,
            :class:`~controllers.systems.cartpole.CartPole`).
        true_params, init_params: ``{name: float}`` the expert's and the learner's initial values.
        expert_damping: the expert pendulum's damping ``b`` (0: realizable; the learner's is always 0).
        horizon: ``T``.  dt: the model's time step.  u_limit: ``|u| ≤ u_limit``.
        cost: the :class:`~controllers.costs.QuadraticCost` shared by expert and learner.
    """

    system: str
    param_names: tuple[str, ...]
    true_params: Mapping[str, float]
    init_params: Mapping[str, float]
    expert_damping: float
    horizon: int
    dt: float
    u_limit: float
    cost: QuadraticCost

    @property
    def n(self) -> int:
        return self.cost.n

    @property
    def dtype(self) -> torch.dtype:
        return self.cost.Q.dtype

    @property
    def device(self) -> torch.device:
        return self.cost.Q.device

    def model(self, params: Mapping[str, Tensor | float], damping: float = 0.0) -> Pendulum | CartPole:
        """The model with the given physical parameters (floats or tensors, e.g. requiring grad)."""
        _check_names(self.param_names, params, "ImitationSetup.model", extra=False)
        kw = {k: params[k] for k in self.param_names}
        if self.system == "pendulum":
            return Pendulum(damping=damping, dt=self.dt, **kw)
        return CartPole(dt=self.dt, **kw)

    def expert_model(self) -> Pendulum | CartPole:
        return self.model(self.true_params, damping=self.expert_damping)

    def problem(self, model, x0: Tensor) -> ILQRProblem:
        """The planning problem from start states ``x0 (*B, n)`` on ``model``."""
        return ILQRProblem(dynamics=model, cost=self.cost, x0=x0, horizon=self.horizon,
                           u_lower=-self.u_limit, u_upper=self.u_limit)

    def sample_starts(self, count: int, generator: torch.Generator) -> Tensor:
        """``(count, n)`` start states: angle ``π + U(−1, 1)``, velocities ``U(−1, 1)``, cart position
        ``U(−0.5, 0.5)``."""
        if not isinstance(generator, torch.Generator):
            raise TypeError("ImitationSetup.sample_starts: 'generator' must be a torch.Generator")
        if isinstance(count, bool) or not isinstance(count, int) or count < 0:
            raise ValueError(f"ImitationSetup.sample_starts: 'count' must be an int >= 0, got {count!r}")
        w = 2 * torch.rand(count, self.n, generator=generator, dtype=torch.float64) - 1
        if self.system == "pendulum":
            x = torch.stack([math.pi + w[:, 0], w[:, 1]], -1)
        else:
            x = torch.stack([0.5 * w[:, 0], math.pi + w[:, 1], w[:, 2], w[:, 3]], -1)
        return x.to(dtype=self.dtype, device=self.device)


def imitation_setup(system: str, *, expert_damping: float = 0.0, dtype: torch.dtype = torch.float64,
                    device: torch.device | str | None = None, horizon: int = 20,
                    u_limit: float | None = None) -> ImitationSetup:
    """The :class:`ImitationSetup` of ``system`` (``"pendulum"`` or ``"cartpole"``; module docstring).

    ``expert_damping > 0`` (pendulum only) makes the expert non-realizable for the learner."""
    own = "imitation_setup"
    if system not in SYSTEMS:
        raise ValueError(f"{own}: 'system' must be one of {SYSTEMS}, got {system!r}")
    if dtype not in (torch.float32, torch.float64):
        raise TypeError(f"{own}: 'dtype' must be torch.float32 or torch.float64, got {dtype}")
    if isinstance(expert_damping, bool) or not isinstance(expert_damping, (int, float)) \
            or not math.isfinite(expert_damping) or expert_damping < 0:
        raise ValueError(f"{own}: 'expert_damping' must be a finite float >= 0, got {expert_damping!r}")
    if expert_damping > 0 and system != "pendulum":
        raise ValueError(f"{own}: 'expert_damping' is for the pendulum (the cart-pole model has no damping)")
    if isinstance(horizon, bool) or not isinstance(horizon, int) or horizon < 1:
        raise ValueError(f"{own}: 'horizon' must be a positive int, got {horizon!r}")
    try:
        device = None if device is None else torch.device(device)
    except (RuntimeError, TypeError) as e:
        raise ValueError(f"{own}: 'device' must be a torch.device or its name, got {device!r}") from e
    s = _SPEC[system]
    u_limit = s["u_limit"] if u_limit is None else _positive_float(u_limit, "u_limit", own)
    kw = dict(dtype=dtype, device=device)
    cost = QuadraticCost(Q=torch.diag(torch.tensor(s["Q"], **kw)), R=torch.tensor([[s["r"]]], **kw),
                         x_ref=torch.tensor(s["x_ref"], **kw))
    names = s["names"]
    return ImitationSetup(system=system, param_names=names, true_params=dict(zip(names, s["true"])),
                          init_params=dict(zip(names, s["init"])), expert_damping=float(expert_damping),
                          horizon=horizon, dt=0.05, u_limit=u_limit, cost=cost)


def identifiable_combinations(system: str, params: Mapping[str, Any]) -> dict[str, Any]:
    """The identifiable combinations of the physical parameters (module docstring): pendulum
    ``{"g/l": g / l, "1/(m l^2)": 1 / (m l²)}``; cart-pole: the four physical parameters themselves.
    Values are floats (finite, > 0) or tensors (not read), as given; names other than the system's are
    ignored (e.g. a record's ``"damping"``)."""
    own = "identifiable_combinations"
    if system not in SYSTEMS:
        raise ValueError(f"{own}: 'system' must be one of {SYSTEMS}, got {system!r}")
    names = _SPEC[system]["names"]
    _check_names(names, params, own, extra=True)
    for k in names:
        _check_value(params[k], k, own)
    return _combinations(system, params)


def _combinations(system: str, params: Mapping[str, Any]) -> dict[str, Any]:
    """:func:`identifiable_combinations` unchecked (a float 0 gives ``inf``, not an error)."""
    if system == "pendulum":
        g, m, l_ = params["gravity"], params["mass"], params["length"]
        return {"g/l": _div(g, l_), "1/(m l^2)": _div(1.0, m * l_ * l_)}
    return {k: params[k] for k in _SPEC["cartpole"]["names"]}


def _div(a: Any, b: Any) -> Any:
    if isinstance(b, Tensor) or isinstance(a, Tensor) or b != 0:
        return a / b
    return math.nan if a == 0 or math.isnan(a) else math.copysign(math.inf, a)


def _check_names(names: Sequence[str], params: Any, own: str, *, extra: bool) -> None:
    """``params`` a mapping with every name of ``names`` (and no other unless ``extra``)."""
    if not isinstance(params, Mapping):
        raise TypeError(f"{own}: 'params' must be a mapping {{name: value}} of {list(names)}, got "
                        f"{type(params).__name__}")
    missing = [k for k in names if k not in params]
    unknown = [] if extra else [k for k in params if k not in names]
    if missing or unknown:
        what = " and ".join(([f"lacks {missing}"] if missing else []) +
                            ([f"has unknown names {unknown}"] if unknown else []))
        raise ValueError(f"{own}: 'params' {what} (needs {'' if extra else 'exactly '}{list(names)})")


def _check_value(v: Any, k: str, own: str, dtype: torch.dtype | None = None,
                 batch: int | None = None) -> None:
    """A parameter value: a finite float > 0, or a tensor (of ``dtype``, shape ``()``, ``(1,)`` or
    ``(batch,)``; its values are not read: autograd passes through them)."""
    if isinstance(v, Tensor):
        if dtype is not None and v.dtype != dtype:
            raise TypeError(f"{own}: params[{k!r}] has dtype {v.dtype}; the setup's is {dtype} "
                            f"(no silent cast)")
        if v.dim() > 1 or v.numel() not in (1, batch or 1):
            raise ValueError(f"{own}: params[{k!r}] must be a scalar tensor or of shape ({batch or 1},), got "
                             f"{tuple(v.shape)}")
    elif isinstance(v, bool) or not isinstance(v, (int, float)):
        raise TypeError(f"{own}: params[{k!r}] must be a float or a tensor, got {type(v).__name__}")
    elif not math.isfinite(v) or v <= 0:
        raise ValueError(f"{own}: params[{k!r}] must be a finite float > 0, got {v!r}")


def _check_params(setup: Any, params: Any, own: str, batch: int | None = None) -> None:
    """``params``: exactly ``setup.param_names``, each value as :func:`_check_value`."""
    _check_names(setup.param_names, params, own, extra=False)
    for k in setup.param_names:
        _check_value(params[k], k, own, setup.dtype, batch)


def _check_setup(setup: Any, own: str) -> None:
    if not isinstance(setup, ImitationSetup):
        raise TypeError(f"{own}: 'setup' must be an ImitationSetup (imitation_setup()), got "
                        f"{type(setup).__name__}")


def _check_setup_x0(setup: Any, x0: Any, options: Any, own: str) -> int:
    """``setup`` an :class:`ImitationSetup`, ``x0`` a ``(N, n)`` tensor of its dtype, ``N ≥ 1``; returns N."""
    _check_setup(setup, own)
    if options is not None and not isinstance(options, ILQROptions):
        raise TypeError(f"{own}: 'options' must be an ILQROptions or None, got {type(options).__name__}")
    _check_states(x0, "x0", setup, own)
    return x0.shape[0]


def _check_states(x: Any, name: str, setup: ImitationSetup, own: str) -> None:
    if not isinstance(x, Tensor) or not x.is_floating_point():
        raise TypeError(f"{own}: '{name}' must be a floating tensor (N, {setup.n}) of dtype {setup.dtype}, "
                        f"got {x.dtype if isinstance(x, Tensor) else type(x).__name__}")
    if x.dtype != setup.dtype:
        raise TypeError(f"{own}: '{name}' has dtype {x.dtype} but the setup's is {setup.dtype} (make the "
                        f"setup with imitation_setup(dtype=...); no silent cast)")
    if x.dim() != 2 or x.shape[-1] != setup.n or x.shape[0] < 1:
        raise ValueError(f"{own}: '{name}' must be a tensor (N, {setup.n}) with N >= 1, got {tuple(x.shape)}")


def _check_controls(u: Any, name: str, shape: tuple[int, ...], dtype: torch.dtype, own: str) -> None:
    if not isinstance(u, Tensor) or u.dtype != dtype:
        got = u.dtype if isinstance(u, Tensor) else type(u).__name__
        raise TypeError(f"{own}: '{name}' must be a tensor of dtype {dtype} (the states'), got {got}")
    if tuple(u.shape) != shape:
        raise ValueError(f"{own}: '{name}' must be a tensor {shape}, got {tuple(u.shape)}")


# --------------------------------------------------------------------------------------------------
# the imitation loss and its gradient
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class ImitationLoss:
    """One evaluation of the imitation loss.

    Attributes:
        loss: 0-d, the mean over included samples of ``mean_{t,j} (u − u*)²`` (differentiable).
        per_sample: ``(N,)`` each sample's MSE (NaN where the plan or the demo is non-finite).
        included: ``(N,)`` bool, the samples in ``loss`` with their own error (not: non-finite samples,
            counted as the largest error, and with ``unconverged="exclude"`` non-converged ones).
        solution: the learner's :class:`~controllers.ilqr.ILQRSolution` (per-sample ``status``).
    """

    loss: Tensor
    per_sample: Tensor
    included: Tensor
    solution: ILQRSolution


def imitation_loss(setup: ImitationSetup, params: Mapping[str, Tensor | float], x0: Tensor,
                   u_expert: Tensor, *, u_init: Tensor | None = None, grad: str = "implicit",
                   unconverged: str = "include", options: ILQROptions | None = None) -> ImitationLoss:
    """``L(θ)`` on start states ``x0 (N, n)`` against the expert's ``u_expert (N, T, m)``.

    The learner model (damping 0) with ``params`` plans by :func:`controllers.ilqr.ilqr` (``grad`` its
    :class:`~controllers.problem.GradMode`), warm-started from ``u_init`` (zeros when ``None``).
    ``params``: exactly ``setup.param_names``; floats finite and > 0, or tensors of the setup's dtype,
    shared (shape ``()``) or per sample (``(N,)``).  ``unconverged``: ``"include"`` (default; module
    docstring for why) keeps non-converged samples (implicit gradient at their last iterate, inexact),
    ``"exclude"`` drops them from the mean (every gradient is then exact).  A sample whose plan or demo
    is non-finite (a failed input, a diverged rollout) is never in ``included``: it counts in the mean as the
    largest error a plan within the limits can have, ``(2 u_limit)²`` per control, with a zero gradient (its
    NaNs never reach the others' gradient) — so that a step into parameters where the solver diverges is
    never read as a perfect fit (measured: before this rule, a cart-pole fit whose 50 solves all diverged
    saw loss 0 and stopped there).  When no sample is usable at all (every one excluded), ``loss`` is that
    largest error too."""
    return _imitation(setup, params, x0, u_expert, u_init=u_init, grad=grad, unconverged=unconverged,
                      options=options)[0]


def _imitation(setup: ImitationSetup, params: Mapping[str, Tensor | float], x0: Tensor, u_expert: Tensor, *,
               u_init: Tensor | None = None, grad: str = "implicit", unconverged: str = "include",
               options: ILQROptions | None = None) -> tuple[ImitationLoss, Tensor, Tensor]:
    """:func:`imitation_loss` (checked) and the sum and the count its mean divides (0-d; ``loss`` is
    ``total / count``, or the largest error when ``count`` is 0): the terms a sharded run all-reduces."""
    own = "imitation_loss"
    if unconverged not in _UNCONVERGED:
        raise ValueError(f"{own}: 'unconverged' must be one of {_UNCONVERGED}, got {unconverged!r}")
    N = _check_setup_x0(setup, x0, options, own)
    _check_controls(u_expert, "u_expert", (N, setup.horizon, 1), x0.dtype, own)
    _check_params(setup, params, own, batch=N)
    gate: dict[str, Tensor] = {}
    sol = ilqr(setup.problem(setup.model(_gated(setup, params, N, gate)), x0), u_init, grad=grad,
               options=options)
    per, finite = _per_sample_error(sol.u, u_expert)
    inc = finite if unconverged == "include" else finite & sol.status.converged
    gate["keep"] = inc
    worst = (2.0 * setup.u_limit) ** 2
    n_bad = (~finite).sum().to(per.dtype)
    count = inc.sum().to(per.dtype) + n_bad
    total = torch.where(inc, per, torch.zeros((), dtype=per.dtype, device=per.device)).sum() + worst * n_bad
    loss = torch.where(count > 0, total / count.clamp(min=1), worst)
    per = torch.where(finite, per, math.nan).detach()
    return ImitationLoss(loss=loss, per_sample=per, included=inc, solution=sol), total, count


def _gated(setup: ImitationSetup, params: Mapping[str, Tensor | float], N: int, gate: dict[str, Tensor]
           ) -> dict[str, Tensor | float]:
    """``params`` with each one that requires grad expanded to ``(N,)`` and its gradient zeroed, by a hook,
    for the samples not in ``gate["keep"]`` (filled after the solve): the implicit backward of a diverged
    sample can be NaN even for a zero cotangent, and a shared parameter would sum that NaN into every
    gradient."""
    out: dict[str, Tensor | float] = {}
    for k in setup.param_names:
        v = params[k]
        if isinstance(v, Tensor) and v.requires_grad and torch.is_grad_enabled():
            v = v.expand(N)
            v.register_hook(lambda g: torch.where(gate["keep"], g, torch.zeros((), dtype=g.dtype,
                                                                                 device=g.device)))
        out[k] = v
    return out


def _per_sample_error(u: Tensor, u_expert: Tensor) -> tuple[Tensor, Tensor]:
    """``mean_{t,j} (u − u*)²`` per sample ``(N,)`` and whether it is finite; the difference is masked
    before squaring, so that a non-finite sample's gradient is exactly 0 (``0 · NaN`` would be NaN)."""
    ok = torch.isfinite(u).flatten(1).all(-1) & torch.isfinite(u_expert).flatten(1).all(-1)
    d = torch.where(ok[:, None, None], u - u_expert, torch.zeros((), dtype=u.dtype, device=u.device))
    per = d.square().mean((-2, -1))
    return per, ok & torch.isfinite(per)


def control_jacobian(setup: ImitationSetup, params: Mapping[str, float], x0: Tensor,
                     u_init: Tensor | None = None, options: ILQROptions | None = None, *,
                     unconverged: str = "exclude") -> Tensor:
    """``du*/d log θ`` ``(N·T·m, p)`` of the learner's plans from ``x0 (N, n)`` at ``params`` (floats or
    scalar tensors; implicit gradients, one backward pass per control); its rank says which parameter
    directions the controls can identify.  The rows of a sample whose plan is non-finite, and with
    ``unconverged="exclude"`` (default) of a sample whose solve did not converge (its implicit gradient is
    not exact), are NaN — never a silent zero; ``"include"`` keeps the latter's rows."""
    own = "control_jacobian"
    if unconverged not in _UNCONVERGED:
        raise ValueError(f"{own}: 'unconverged' must be one of {_UNCONVERGED}, got {unconverged!r}")
    N = _check_setup_x0(setup, x0, options, own)
    _check_params(setup, params, own)
    z = torch.stack([torch.as_tensor(params[k], dtype=setup.dtype, device=setup.device).reshape(())
                     for k in setup.param_names]).detach().log().requires_grad_()
    with torch.enable_grad():
        sol = ilqr(setup.problem(setup.model(dict(zip(setup.param_names, z.exp()))), x0), u_init,
                   grad="implicit", options=options)
        u = sol.u.reshape(-1)
        eye = torch.eye(u.numel(), dtype=u.dtype, device=u.device)
        rows = [torch.autograd.grad(u, z, e, retain_graph=True)[0] for e in eye]
    bad = ~torch.isfinite(sol.u).flatten(1).all(-1)
    if unconverged == "exclude":
        bad = bad | ~sol.status.converged
    J = torch.stack(rows).reshape(N, -1, z.numel())
    return torch.where(bad[:, None, None], math.nan, J).reshape(-1, z.numel())


# --------------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------------


def _rel_err(system: str, params: Mapping[str, float], truth: Mapping[str, float]) -> dict[str, float]:
    out = {k: abs(float(params[k]) - truth[k]) / abs(truth[k]) for k in truth}
    if system == "pendulum":
        c, ct = _combinations(system, params), _combinations(system, truth)
        out.update({k: abs(float(c[k]) - ct[k]) / abs(ct[k]) for k in ct})
    return out


def _identifiable_names(system: str) -> list[str]:
    return list(_combinations(system, dict.fromkeys(_SPEC[system]["names"], 1.0)))


def _heldout_mse(setup: ImitationSetup, params: Mapping[str, float], x0: Tensor, u_expert: Tensor
                 ) -> tuple[float, int]:
    """Held-out MSE of the MPC with ``params`` (solved from zeros) and its number of unconverged solves;
    parameters that are not finite and positive (an overflowed fit) are not solved: NaN, all unconverged."""
    if not all(math.isfinite(float(v)) and float(v) > 0 for v in params.values()):
        return math.nan, int(x0.shape[0])
    with torch.no_grad():
        sol = ilqr(setup.problem(setup.model({k: float(v) for k, v in params.items()}), x0), grad="none",
                   options=EXPERT_OPTIONS)
    return float(((sol.u - u_expert) ** 2).mean()), int((~sol.status.converged).sum())


def _positive_int(v: Any, name: str, own: str) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or v < 1:
        raise ValueError(f"{own}: '{name}' must be a positive int, got {v!r}")
    return v


def _positive_float(v: Any, name: str, own: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
        raise ValueError(f"{own}: '{name}' must be a finite float > 0, got {v!r}")
    return float(v)


def _fit_log_params(loss_fn, z0: Tensor, steps: int, lr: float, tol: float, optimizer: str = "lbfgs",
                    on_eval=None, reduce_grad=None) -> Tensor:
    """Minimize ``loss_fn(z)`` over ``z = log θ`` from ``z0`` by L-BFGS or Adam; ``steps`` loss evaluations
    (L-BFGS may finish its line search past it); ``on_eval(z, out)`` after each evaluation.
    ``reduce_grad(g)``: applied to ``z.grad`` after every backward (under torchrun :meth:`_Shard.reduce_grad`,
    the sum of the ranks' gradients; ``None``: the gradient as it is)."""
    z = z0.detach().clone().requires_grad_()
    if optimizer == "lbfgs":
        opt = torch.optim.LBFGS([z], lr=lr, max_iter=steps, max_eval=steps, tolerance_grad=tol,
                                tolerance_change=1e-3 * tol, history_size=20, line_search_fn="strong_wolfe")
    else:
        opt = torch.optim.Adam([z], lr=lr)

    def closure():
        opt.zero_grad(set_to_none=True)
        with torch.enable_grad():
            res = loss_fn(z)
            loss = res if isinstance(res, Tensor) else res[0]
            if loss.requires_grad:
                loss.backward()
            else:  # nothing included: a zero gradient, never a missing one
                z.grad = torch.zeros_like(z)
        if reduce_grad is not None:
            z.grad = reduce_grad(z.grad)
        if on_eval is not None:
            on_eval(z.detach().clone(), res)
        return loss.detach()

    if optimizer == "lbfgs":
        opt.step(closure)
    else:
        for _ in range(steps):
            opt.step(closure)
    return z.detach()


def _levenberg_marquardt(evaluate, z0: Tensor, steps: int, tol: float, on_eval=None, max_step: float = 0.5,
                         max_rejected: int = 6, ftol: float = 1e-6) -> Tensor:
    """Gauss-Newton with Levenberg-Marquardt damping on ``½ ‖r(z)‖²``.

    ``evaluate(z) -> (loss, r (K,), jacobian, aux)`` with ``jacobian()`` returning ``J = dr/dz (K, p)``
    (called only for accepted points).  Step ``(JᵀJ + λ D) d = −Jᵀ r`` with ``D = diag(JᵀJ)`` (Marquardt's
    scaling, floored) and ``‖d‖∞`` capped at ``max_step`` (a trust region in ``log θ``: from a far start an
    uncapped step can jump to a spurious minimum, e.g. a cart-pole without pole mass), ``λ`` divided by 3 on a
    decrease, multiplied by 4 otherwise.  Stops on a zero gradient ``Jᵀ r`` (e.g. no usable sample) or a
    non-finite step, after ``steps`` evaluations, on an accepted step with
    ``‖d‖∞ ≤ tol`` or a relative decrease below ``ftol`` (a spurious minimum on a boundary such as
    ``m_p → 0`` is approached by ever smaller decreases), a loss of 0, or ``max_rejected`` rejected steps in a
    row (``λ`` grown 4⁶-fold without a decrease: the round-off floor of the solves).
    ``on_eval(z, loss, aux, accepted)`` after each evaluation."""
    z = z0.detach().clone()
    loss, r, jac, aux = evaluate(z)
    if on_eval is not None:
        on_eval(z, loss, aux, True)
    evals, lam, rejected = 1, 1e-3, 0
    while evals < steps and loss > 0:
        J = jac()
        A, g = J.mT @ J, J.mT @ r
        D = A.diagonal().clamp(min=1e-12 * float(A.diagonal().max().clamp(min=1e-300)))
        d = torch.linalg.solve(A + lam * torch.diag(D), -g)
        if not bool(torch.isfinite(d).all()) or not bool((g != 0).any()):
            break  # no information (e.g. every sample excluded: J = 0) or a failed solve: never a NaN step
        d = d * (max_step / d.abs().max().clamp(min=max_step))  # at most a factor e^max_step per parameter
        zn = z + d
        loss_prev = loss
        loss_n, r_n, jac_n, aux_n = evaluate(zn)
        evals += 1
        ok = bool(loss_n < loss)
        if on_eval is not None:
            on_eval(zn, loss_n, aux_n, ok)
        if ok:
            z, loss, r, jac = zn, loss_n, r_n, jac_n
            lam, rejected = max(lam / 3, 1e-12), 0
            if float(d.abs().max()) <= tol or loss_n > (1 - ftol) * loss_prev:
                break
        else:
            lam, rejected = lam * 4, rejected + 1
            if rejected >= max_rejected or lam > 1e10:
                break
            jac = _cached(J)
    return z


def _cached(J: Tensor):
    return lambda: J


# --------------------------------------------------------------------------------------------------
# baselines
# --------------------------------------------------------------------------------------------------


def system_identification(setup: ImitationSetup, demos: Demonstrations, *, steps: int = 100,
                          tol: float = 1e-12) -> dict[str, float]:
    """Fit the learner's parameters (log, from ``setup.init_params``, damping 0) to the demos' transitions
    ``(x_t, u_t) → x_{t+1}`` by Levenberg-Marquardt on ``mean_t Σ_j (f_θ(x_t, u_t) − x_{t+1})_j² / σ_j²``
    (``σ_j²``: the variance of coordinate ``j`` of the next states; the Jacobian by forward-mode autograd
    through the model's step); returns ``{name: value}``."""
    _check_sysid_args(setup, demos, steps, tol)
    x, u = demos.x[:, :-1], demos.u
    x1 = demos.x[:, 1:]
    w = x1.var((0, 1)).clamp(min=1e-12).rsqrt() / math.sqrt(x1.numel() / x1.shape[-1])  # per-coordinate scale

    def resid(z):
        model = setup.model(dict(zip(setup.param_names, z.exp())))
        return ((model.step(x, u) - x1) * w).reshape(-1)

    def evaluate(z):
        r = resid(z)
        jac = lambda: torch.autograd.functional.jacobian(resid, z, vectorize=True, strategy="forward-mode")
        return float((r * r).sum()), r, jac, None

    z0 = torch.tensor([setup.init_params[k] for k in setup.param_names], dtype=setup.dtype,
                      device=setup.device).log()
    with torch.enable_grad():
        z = _levenberg_marquardt(evaluate, z0, steps, tol)
    return dict(zip(setup.param_names, z.exp().tolist()))


def _check_sysid_args(setup: Any, demos: Any, steps: Any, tol: Any) -> None:
    own = "system_identification"
    _check_setup(setup, own)
    if not isinstance(demos, Demonstrations) or demos.u is None:
        raise TypeError(f"{own}: 'demos' must be Demonstrations with controls")
    if demos.n != setup.n or demos.m != 1:
        raise ValueError(f"{own}: 'demos' have states of dimension {demos.n} and controls of {demos.m}; the "
                         f"{setup.system} setup needs {setup.n} and 1")
    if demos.dtype != setup.dtype:
        raise TypeError(f"{own}: 'demos' have dtype {demos.dtype} but the setup's is {setup.dtype} "
                        f"(no silent cast)")
    _positive_int(steps, "steps", own)
    _positive_float(tol, "tol", own)


class _LSTMPlanner(nn.Module):
    """``x0 (N, n) → u (N, T, m)``: an LSTM fed the standardized start state and the time ``t / T``."""

    def __init__(self, n: int, m: int, T: int, hidden: int, mean: Tensor, std: Tensor, u_limit: float):
        super().__init__()
        self.T, self.u_limit = T, u_limit
        self.lstm = nn.LSTM(n + 1, hidden, batch_first=True)
        self.head = nn.Linear(hidden, m)
        self.register_buffer("mean", mean.detach().clone())
        self.register_buffer("std", std.detach().clone())

    def forward(self, x0: Tensor) -> Tensor:
        z = ((x0 - self.mean) / self.std)[:, None, :].expand(-1, self.T, -1)
        t = torch.linspace(0, 1, self.T, dtype=x0.dtype, device=x0.device)
        t = t[None, :, None].expand(x0.shape[0], -1, 1)
        h, _ = self.lstm(torch.cat([z, t], -1))
        return self.u_limit * torch.tanh(self.head(h))


def behaviour_cloning(setup: ImitationSetup, x0: Tensor, u_expert: Tensor, x0_test: Tensor, u_test: Tensor, *,
                      kind: str = "mlp", epochs: int = 1000, lr: float = 3e-3, hidden: int = 64,
                      seed: int = 0) -> dict[str, float]:
    """Behaviour cloning ``x_0 → u_{0:T-1}`` (``u_limit · tanh``): an MLP (:class:`learning.bc.MLPPolicy`,
    two hidden layers) or an LSTM, full-batch Adam on the training starts; deterministic given ``seed``.
    Returns ``{"imitation_mse": held-out MSE, "train_mse": ..., "time_s": ...}``.  Shapes: ``x0 (N, n)``,
    ``u_expert (N, T, 1)``, ``x0_test (M, n)``, ``u_test (M, T, 1)``, all of the setup's dtype and finite
    (a non-finite demo is refused, naming its index: it would poison every weight)."""
    _check_bc_args(setup, x0, u_expert, x0_test, u_test, kind, epochs, lr, hidden, seed)
    t0 = time.perf_counter()
    N, T, m = u_expert.shape
    mean, std = x0.mean(0), x0.std(0, unbiased=False).clamp(min=1e-3)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        if kind == "mlp":
            net = MLPPolicy(setup.n, T * m, (hidden, hidden), mean=mean, std=std).to(x0.dtype)

            def predict(s):
                return setup.u_limit * net(s).reshape(s.shape[0], T, m)
        else:
            net = _LSTMPlanner(setup.n, m, T, hidden // 2, mean, std, setup.u_limit).to(x0.dtype)
            predict = net
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    scale = setup.u_limit ** 2
    with torch.enable_grad():
        for _ in range(epochs):
            loss = ((predict(x0) - u_expert) ** 2).mean() / scale
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
    with torch.no_grad():
        train = float(((predict(x0) - u_expert) ** 2).mean())
        test = float(((predict(x0_test) - u_test) ** 2).mean())
    return {"imitation_mse": test, "train_mse": train, "time_s": time.perf_counter() - t0}


# --------------------------------------------------------------------------------------------------
# learning
# --------------------------------------------------------------------------------------------------


def _check_bc_args(setup, x0, u_expert, x0_test, u_test, kind, epochs, lr, hidden, seed) -> None:
    """:func:`behaviour_cloning`'s arguments checked (each error names its argument)."""
    own = "behaviour_cloning"
    if kind not in ("mlp", "lstm"):
        raise ValueError(f"{own}: 'kind' must be 'mlp' or 'lstm', got {kind!r}")
    _check_setup_x0(setup, x0, None, own)
    _check_states(x0_test, "x0_test", setup, own)
    T = u_expert.shape[1] if isinstance(u_expert, Tensor) and u_expert.dim() == 3 else setup.horizon
    _check_controls(u_expert, "u_expert", (x0.shape[0], T, 1), setup.dtype, own)
    _check_controls(u_test, "u_test", (x0_test.shape[0], T, 1), setup.dtype, own)
    for name, v in (("x0", x0), ("u_expert", u_expert), ("x0_test", x0_test), ("u_test", u_test)):
        bad = torch.nonzero(~torch.isfinite(v).flatten(1).all(-1)).flatten()
        if bad.numel():
            raise ValueError(f"{own}: '{name}' has a non-finite value in demo {int(bad[0])}")
    _positive_int(epochs, "epochs", own)
    _positive_float(lr, "lr", own)
    if isinstance(hidden, bool) or not isinstance(hidden, int) or hidden < 2:
        raise ValueError(f"{own}: 'hidden' must be an int >= 2, got {hidden!r}")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ValueError(f"{own}: 'seed' must be an int >= 0, got {seed!r}")


def learn_dynamics(system: str, n_train: int = 10, seed: int = 0, *, steps: int = 100,
                   lr: float | None = None, optimizer: str = "lbfgs+gauss_newton", tol: float = 1e-10,
                   n_test: int = 50, unconverged: str = "include", warm_start: str = "expert",
                   expert_damping: float = 0.0, max_step: float = 0.5, u_limit: float | None = None,
                   warmup: int = 30,
                   baselines: Sequence[str] = _BASELINES, bc_epochs: int = 1000,
                   options: ILQROptions | None = None, dtype: torch.dtype = torch.float64,
                   device: torch.device | str | None = None) -> dict[str, Any]:
    """Learn the physical parameters of ``system`` from ``n_train`` expert demonstrations by
    backpropagating the imitation loss through the iLQR planner (module docstring).

    Args:
        system: ``"pendulum"`` or ``"cartpole"``.
        n_train: training start states; ``seed``: the generator of all starts (held-out first).
        steps: loss evaluations (one learner solve each; L-BFGS may finish its last line search past it).
        optimizer: ``"lbfgs+gauss_newton"`` (default: ``warmup`` evaluations of L-BFGS, then Gauss-Newton),
            ``"gauss_newton"``: Levenberg-Marquardt on the residuals ``u − u*`` with the Jacobian
            ``du/d log θ`` from ``T·m`` implicit backward passes (one copy of ``θ`` per sample, so a pass
            gives every sample's row at once); ``"lbfgs"`` (strong-Wolfe line search on ``L``'s gradient, one
            backward pass per evaluation) or ``"adam"``.
        warmup: L-BFGS evaluations before Gauss-Newton (``"lbfgs+gauss_newton"``).
        lr: step size of L-BFGS (1.0) or Adam (0.05); unused by Gauss-Newton.
        tol: Gauss-Newton stops on an accepted step with ``‖Δ log θ‖∞ ≤ tol``; L-BFGS when
            ``|∇L̃|∞ ≤ tol`` (``L̃ = L / u_limit²``) or a step changes ``L̃`` or ``log θ`` by less than
            ``tol / 1000``.
        n_test: held-out start states for the imitation MSE.
        unconverged: ``"include"`` (default) or ``"exclude"`` non-converged training solves (module
            docstring: why the default differs from :mod:`learning.ioc`'s).
        warm_start: ``"expert"`` (each solve starts from the expert's controls) or ``"previous"`` (from the
            previous evaluation's controls; zeros first).
        expert_damping: the expert pendulum's damping (non-realizable when > 0; the learner's is 0).
        max_step: Gauss-Newton's largest step in ``log θ`` (a factor ``e^max_step`` per parameter).
        u_limit: the control limit of expert and learner (``None``: the system's, module docstring).
        baselines: any of ``"sysid"``, ``"mlp"``, ``"lstm"``.  bc_epochs: Adam epochs of the BC baselines.
        options: :class:`~controllers.ilqr.ILQROptions` of the learner's training solves (the expert and the
            held-out solves use the defaults).

    Returns:
        A JSON-able record: ``system``, ``n_train``, ``seed``, ``param_rel_err`` (``{name: |θ − θ*| / |θ*|}``
        for every physical parameter and, for the pendulum, the combinations ``"g/l"``, ``"1/(m l^2)"``),
        ``identifiable`` (the names the 1 % goal is judged on) and ``identifiable_rel_err_max``, ``params``,
        ``params_true``, ``params_init``, ``imitation_mse`` (held-out, learned model) and
        ``imitation_mse_init`` (held-out, initial model), ``baselines`` (``{"sysid": {"params",
        "param_rel_err", "imitation_mse"}, "mlp": {...}, "lstm": {...}}``), ``unconverged`` (the policy, the
        total of unconverged / excluded / non-finite sample solves over all evaluations, the reasons),
        ``expert_unconverged`` (expert solves, training and held-out), ``heldout_unconverged`` (the learned
        model's held-out solves), ``history`` (per loss evaluation, trial points of Gauss-Newton included:
        ``loss``, ``accepted``, ``identifiable_rel_err_max``, ``params`` per name, ``n_unconverged``,
        ``n_excluded``, ``n_nonfinite``, ``unconverged_samples`` — indices — and ``unconverged_reasons``),
        ``evaluations``, ``final_loss``, ``realizable``, ``expert_damping``, ``u_limit``, ``n_test``,
        ``time_learn_s`` (data, learning and held-out evaluation) and ``time_s`` (baselines included),
        ``nonfinite_values`` (the paths of values that were NaN/inf, written as ``None``: strict JSON);
        under torchrun also ``world_size`` (the same record on every rank; module docstring).

    Raises:
        ValueError, TypeError: a bad argument (naming it); ValueError under torchrun with fewer training demos
            than ranks.
    """
    setup, lr = _validated_learn_args(dict(locals()), "learn_dynamics")
    shard = _Shard(n_train, "learn_dynamics") if _dist.world_size() > 1 else None
    t_start = time.perf_counter()
    gen = torch.Generator().manual_seed(seed)
    x_test = setup.sample_starts(n_test, gen)
    x_train = setup.sample_starts(n_train, gen)
    demos = expert_demos(setup.problem(setup.expert_model(), torch.cat([x_train, x_test])), keep="all",
                         options=EXPERT_OPTIONS)
    u_train, u_test = demos.u[:n_train], demos.u[n_train:]
    names, truth = setup.param_names, dict(setup.true_params)
    hist = _History(system, names, truth, shard)
    solve = _training_solver(setup, x_train, u_train, unconverged, warm_start, options, shard)
    z0 = torch.tensor([setup.init_params[k] for k in names], dtype=setup.dtype, device=setup.device).log()
    z = _fit_params(setup, solve, z0, u_train, hist, optimizer=optimizer, steps=steps, warmup=warmup, lr=lr,
                    tol=tol, max_step=max_step)
    learned = dict(zip(names, z.exp().tolist()))
    err = _rel_err(system, learned, truth)
    mse, held_unconv = _heldout_mse(setup, learned, x_test, u_test)
    mse0, _ = _heldout_mse(setup, dict(setup.init_params), x_test, u_test)
    t_learn = time.perf_counter() - t_start

    def run_baselines():
        return _run_baselines(setup, baselines, demos.select(list(range(n_train))), x_train, u_train, x_test,
                              u_test, truth, hist.ident, bc_epochs, seed)

    if shard is None:
        base, t_all = run_baselines(), time.perf_counter() - t_start
    else:
        base, t_learn, t_all = shard.from_rank0(run_baselines, t_learn, t_start)
    rec = {"system": system, "n_train": n_train, "seed": seed, "param_rel_err": err,
           "identifiable": hist.ident, "identifiable_rel_err_max": _max(err[k] for k in hist.ident),
           "params": learned, "params_true": _params_true(setup), "params_init": dict(setup.init_params),
           "realizable": setup.expert_damping == 0, "expert_damping": setup.expert_damping,
           "imitation_mse": mse, "imitation_mse_init": mse0, "u_limit": setup.u_limit, "n_test": n_test,
           "baselines": base, "unconverged": hist.summary(unconverged),
           "expert_unconverged": int((~demos.frames["converged"]).sum()), "heldout_unconverged": held_unconv,
           "evaluations": len(hist.h["loss"]), "final_loss": hist.h["loss"][-1], "history": hist.h,
           "time_s": t_all, "time_learn_s": t_learn}
    if shard is not None:
        rec["world_size"] = shard.w
    found: list[str] = []
    rec = _strict_json(rec, "", found)
    rec["nonfinite_values"] = found
    return rec


_LEARN_SIGNATURE = inspect.signature(learn_dynamics)


def _validated_learn_args(a: dict[str, Any], own: str) -> tuple[ImitationSetup, float]:
    """:func:`learn_dynamics`' arguments (``a``: by name) checked; its setup and step size."""
    _check_learn_args(own, a["system"], a["n_train"], a["n_test"], a["steps"], a["seed"], a["optimizer"],
                      a["warmup"], a["tol"], a["unconverged"], a["warm_start"], a["baselines"], a["options"],
                      a["bc_epochs"], a["max_step"])
    lr = a["lr"] if a["lr"] is not None else (0.05 if a["optimizer"] == "adam" else 1.0)
    setup = imitation_setup(a["system"], expert_damping=a["expert_damping"], dtype=a["dtype"],
                            device=a["device"], u_limit=a["u_limit"])
    return setup, _positive_float(lr, "lr", own)


class _Shard:
    """This rank's block of the training demos under torchrun and the collectives of :func:`learn_dynamics`
    (:mod:`learning.distributed`; built only when the world has more than one rank)."""

    def __init__(self, n: int, own: str):
        self.n, self.w, self.own = n, _dist.world_size(), own
        if n < self.w:
            raise ValueError(f"{own}: {n} training demos cannot be shared by {self.w} ranks (at least one "
                             f"each; use n_train >= {self.w} or fewer processes)")
        self.block = _dist.shard(n)

    def loss(self, run, worst: float, like: Tensor) -> ImitationLoss:
        """``res`` of ``(res, total, count) = run()`` (:func:`_imitation` on this rank's block) with the
        global loss: one all-reduce of ``[total, count, failed]`` (``total``: the sum of included errors plus
        the worst error per non-finite sample, differentiable).  Its value is ``Σ total / Σ count`` (the
        worst error when ``Σ count = 0``), as one process computes it, the same number on every rank; its
        gradient is this rank's share ``∇total / Σ count`` (a straight-through sum
        ``value + (share − share.detach())``), which :meth:`reduce_grad` sums over the ranks.  When
        ``run()`` raised on any rank every rank raises (:func:`learning.distributed.raise_together`), so that
        none waits in a collective.  ``like``: a tensor of the setup's dtype and device."""
        try:
            (res, total, count), error = run(), None
        except Exception as e:
            res, total, count, error = None, like.new_zeros(()), like.new_zeros(()), e
        failed = like.new_tensor(float(error is not None))
        g = _dist.all_reduce_sum(torch.stack([total.detach(), count, failed]))
        if bool(g[2] > 0):
            _dist.raise_together(error, self.own)
        value = torch.where(g[1] > 0, g[0] / g[1].clamp(min=1), worst)
        share = torch.where(g[1] > 0, total / g[1].clamp(min=1), 0.0)
        return replace(res, loss=value + (share - share.detach()))

    def reduce_grad(self, grad: Tensor) -> Tensor:
        """The sum over the ranks of the gradient of ``log θ`` (a plain tensor, not an ``nn.Module``: this
        explicit all-reduce after each backward is what DistributedDataParallel does to a module's
        gradients, as a sum since :meth:`loss` already divides by the global count)."""
        return _dist.all_reduce_sum(grad)

    def gather(self, t: Tensor) -> Tensor:
        """Every rank's block of a per-sample ``t (n_r, ...)`` in sample order: ``(n, ...)``."""
        return _dist.gather_along(t, self.n)

    def from_rank0(self, baselines, t_learn: float, t_start: float) -> tuple[dict[str, Any], float, float]:
        """``(baselines(), time_learn_s, time_s)`` on every rank, so that every rank returns the same record:
        the baselines run on rank 0 only (an exception there is raised on every rank), the times are the
        slowest rank's."""
        base, error = None, None
        if _dist.is_main():
            try:
                base = baselines()
            except Exception as e:
                error = e
        _dist.raise_together(error, f"{self.own} (baselines)")
        parts = _dist.gather_objects((base, t_learn, time.perf_counter() - t_start))
        return parts[0][0], max(p[1] for p in parts), max(p[2] for p in parts)


def _training_solver(setup: ImitationSetup, x_train: Tensor, u_train: Tensor, unconverged: str,
                     warm_start: str, options: ILQROptions | None, shard: _Shard | None = None):
    """``solve(params) -> ImitationLoss`` on the training demos, warm-started as ``warm_start`` says.  Under
    torchrun (``shard``) on this rank's block only, with the global loss (:meth:`_Shard.loss`); the other
    fields are the block's, and each rank keeps the warm starts of its own block."""
    if shard is not None:
        x_train, u_train = x_train[shard.block], u_train[shard.block]
    warm = {"u": u_train if warm_start == "expert" else None}

    def solve(params):
        def run():
            return _imitation(setup, params, x_train, u_train, u_init=warm["u"], unconverged=unconverged,
                              options=options)

        res = run()[0] if shard is None else shard.loss(run, (2.0 * setup.u_limit) ** 2, x_train)
        if warm_start == "previous":
            u = res.solution.u.detach()
            warm["u"] = torch.where(torch.isfinite(u), u, torch.zeros((), dtype=u.dtype, device=u.device))
        return res

    return solve


def _params_true(setup: ImitationSetup) -> dict[str, float]:
    out = dict(setup.true_params)
    if setup.expert_damping > 0:
        out["damping"] = setup.expert_damping
        out["b/(m l^2)"] = setup.expert_damping / (out["mass"] * out["length"] ** 2)
    return out


def _max(values) -> float:
    """``max`` that returns NaN when any value is NaN (Python's ``max`` depends on the order then)."""
    vals = [float(v) for v in values]
    return math.nan if any(math.isnan(v) for v in vals) else max(vals)


def _strict_json(obj: Any, path: str, found: list[str]) -> Any:
    """``obj`` with every non-finite float replaced by ``None``, its path appended to ``found``."""
    if isinstance(obj, dict):
        return {k: _strict_json(v, f"{path}.{k}" if path else str(k), found) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_strict_json(v, f"{path}[{i}]", found) for i, v in enumerate(obj)]
    if isinstance(obj, float) and not math.isfinite(obj):
        found.append(path)
        return None
    return obj


def _check_learn_args(own, system, n_train, n_test, steps, seed, optimizer, warmup, tol, unconverged,
                      warm_start, baselines, options, bc_epochs, max_step) -> None:
    """:func:`learn_dynamics`' arguments checked (each error names its argument)."""
    if system not in SYSTEMS:
        raise ValueError(f"{own}: 'system' must be one of {SYSTEMS}, got {system!r}")
    for name, v in (("n_train", n_train), ("n_test", n_test), ("steps", steps), ("warmup", warmup),
                    ("bc_epochs", bc_epochs)):
        _positive_int(v, name, own)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ValueError(f"{own}: 'seed' must be an int >= 0, got {seed!r}")
    if optimizer not in _OPTIMIZERS:
        raise ValueError(f"{own}: 'optimizer' must be one of {_OPTIMIZERS}, got {optimizer!r}")
    _positive_float(tol, "tol", own)
    _positive_float(max_step, "max_step", own)
    if unconverged not in _UNCONVERGED:
        raise ValueError(f"{own}: 'unconverged' must be one of {_UNCONVERGED}, got {unconverged!r}")
    if warm_start not in _WARM:
        raise ValueError(f"{own}: 'warm_start' must be one of {_WARM}, got {warm_start!r}")
    if not isinstance(baselines, (str, Sequence, set, frozenset)):
        raise TypeError(f"{own}: 'baselines' must be a sequence of {_BASELINES}, got {baselines!r}")
    if isinstance(baselines, str) or not all(b in _BASELINES for b in baselines):
        raise ValueError(f"{own}: 'baselines' must be a sequence of {_BASELINES}, got {baselines!r}")
    if options is not None and not isinstance(options, ILQROptions):
        raise TypeError(f"{own}: 'options' must be an ILQROptions or None")


class _History:
    """The per-evaluation history of :func:`learn_dynamics` (every learner solve, trial points included)."""

    def __init__(self, system: str, names, truth, shard: _Shard | None = None):
        self.system, self.names, self.truth, self.shard = system, names, truth, shard
        self.ident = _identifiable_names(system)
        self.h: dict[str, Any] = {"loss": [], "accepted": [], "identifiable_rel_err_max": [],
                                  "params": {k: [] for k in names}, "n_unconverged": [], "n_excluded": [],
                                  "n_nonfinite": [], "unconverged_samples": [], "unconverged_reasons": []}

    def record(self, z: Tensor, loss: float, res: ImitationLoss, accepted: bool) -> None:
        """One evaluation; under torchrun the per-sample fields of every rank's block are gathered first, so
        that the indices are global and every rank records the same."""
        h, st = self.h, res.solution.status
        conv, reason, included, per = st.converged, st.reason, res.included, res.per_sample
        if self.shard is not None:
            conv, reason, included, per = (self.shard.gather(t) for t in (conv, reason, included, per))
        bad = torch.nonzero(~conv).flatten().tolist()
        p = dict(zip(self.names, z.exp().tolist()))
        err = _rel_err(self.system, p, self.truth)
        h["loss"].append(float(loss))
        h["accepted"].append(bool(accepted))
        h["identifiable_rel_err_max"].append(_max(err[k] for k in self.ident))
        for k in self.names:
            h["params"][k].append(p[k])
        h["n_unconverged"].append(len(bad))
        h["n_excluded"].append(int((~included).sum()))
        h["n_nonfinite"].append(int((~torch.isfinite(per)).sum()))
        h["unconverged_samples"].append(bad)
        h["unconverged_reasons"].append([Reason(int(reason[i])).name for i in bad])

    def summary(self, policy: str) -> dict[str, Any]:
        """Totals over all evaluations: unconverged / excluded / non-finite sample solves and the reasons."""
        reasons: dict[str, int] = {}
        for rs in self.h["unconverged_reasons"]:
            for r in rs:
                reasons[r] = reasons.get(r, 0) + 1
        return {"policy": policy, "sample_solves": sum(self.h["n_unconverged"]),
                "excluded": sum(self.h["n_excluded"]), "nonfinite": sum(self.h["n_nonfinite"]),
                "reasons": reasons}


def _fit_params(setup: ImitationSetup, solve, z0: Tensor, u_train: Tensor, hist: _History, *, optimizer: str,
                steps: int, warmup: int, lr: float, tol: float, max_step: float) -> Tensor:
    """The learner's ``log θ`` after ``steps`` loss evaluations by ``optimizer`` (:func:`learn_dynamics`);
    under torchrun (``hist.shard``) ``solve`` works on this rank's block of ``u_train``."""
    scale, shard = setup.u_limit ** 2, hist.shard

    def loss_fn(z):
        res = solve(dict(zip(setup.param_names, z.exp())))
        return res.loss / scale, res

    def first_order(z, budget, method):
        return _fit_log_params(loss_fn, z, budget, lr, tol, method,
                               lambda z, out: hist.record(z, float(out[0].detach()) * scale, out[1], True),
                               None if shard is None else shard.reduce_grad)

    if optimizer == "lbfgs+gauss_newton":
        z0 = first_order(z0, min(warmup, steps), "lbfgs")
    if optimizer in ("gauss_newton", "lbfgs+gauss_newton") and len(hist.h["loss"]) < steps:
        left = steps - len(hist.h["loss"])
        u_own = u_train if shard is None else u_train[shard.block]
        return _levenberg_marquardt(_gauss_newton_model(setup, solve, u_own, shard), z0, left, tol,
                                    max_step=max_step, on_eval=hist.record)
    if optimizer in ("lbfgs", "adam"):
        return first_order(z0, steps, optimizer)
    return z0


def _gauss_newton_model(setup: ImitationSetup, solve, u_train: Tensor, shard: _Shard | None = None):
    """``evaluate(z) -> (loss, r, jac, res)`` for :func:`_levenberg_marquardt`: the weighted residuals
    ``u − u*`` of the included samples and their Jacobian ``dr/d log θ`` by ``T·m`` implicit backward passes
    (one copy of ``θ`` per sample, so one pass gives every sample's row).  Under torchrun (``shard``;
    ``solve`` and ``u_train`` are this rank's block) the inclusion flags, the residuals and the Jacobian rows
    of every rank are gathered in sample order, so that every rank holds the whole ``r`` and ``J`` and
    forms the same normal equations ``JᵀJ d = −Jᵀr`` (then the same step) as one process."""
    names, N, Tm = setup.param_names, u_train.shape[0], setup.horizon
    P, dtype = len(names), u_train.dtype
    gather = (lambda t: t) if shard is None else shard.gather

    def evaluate(z):
        zz = z.expand(N, P).clone().requires_grad_()
        with torch.enable_grad():
            res = solve(dict(zip(names, zz.exp().unbind(-1))))
        inc = res.included
        w = inc.to(dtype) / math.sqrt(max(int(gather(inc).sum()), 1) * Tm)
        u = res.solution.u.reshape(N, Tm)
        diff = torch.where(inc[:, None], u.detach() - u_train.reshape(N, Tm), 0.0)
        r = gather(diff * w[:, None]).reshape(-1)

        def jac():
            if not u.requires_grad:
                return gather(torch.zeros(N, Tm, P, dtype=dtype, device=z.device)).reshape(-1, P)
            cols = [torch.autograd.grad(u[:, t], zz, w, retain_graph=t < Tm - 1)[0] for t in range(Tm)]
            J = torch.where(inc[:, None, None], torch.stack(cols, 1), 0.0)  # excluded rows: 0, never NaN
            return gather(J).reshape(-1, P)

        return float(res.loss.detach()), r, jac, res

    return evaluate


def _run_baselines(setup: ImitationSetup, baselines, train_demos, x_train, u_train, x_test, u_test, truth,
                   ident, bc_epochs: int, seed: int) -> dict[str, Any]:
    """The system-identification and behaviour-cloning baselines' records."""
    base: dict[str, Any] = {}
    if "sysid" in baselines:
        t0 = time.perf_counter()
        p_id = system_identification(setup, train_demos)
        e_id = _rel_err(setup.system, p_id, truth)
        base["sysid"] = {"params": p_id, "param_rel_err": e_id,
                         "identifiable_rel_err_max": _max(e_id[k] for k in ident),
                         "imitation_mse": _heldout_mse(setup, p_id, x_test, u_test)[0],
                         "time_s": time.perf_counter() - t0}
    for kind in ("mlp", "lstm"):
        if kind in baselines:
            base[kind] = behaviour_cloning(setup, x_train, u_train, x_test, u_test, kind=kind,
                                           epochs=bc_epochs, seed=seed)
    return base


def imitation_study(system: str, n_trains: Sequence[int] = (10, 50, 100), seeds: Sequence[int] = (0, 1, 2, 3),
                    **kwargs: Any) -> list[dict[str, Any]]:
    """:func:`learn_dynamics` for every ``n_train`` in ``n_trains`` and every seed (keyword arguments passed
    on); a list of records, ``n_train``-major.  Every run's arguments are checked before the first runs."""
    own = "imitation_study"
    n_trains, seeds = _int_tuple(n_trains, "n_trains", own), _int_tuple(seeds, "seeds", own)
    for n in n_trains:
        for s in seeds:
            try:
                bound = _LEARN_SIGNATURE.bind(system, n, s, **kwargs)
            except TypeError as e:
                raise TypeError(f"{own}: {e} (keyword arguments are learn_dynamics')") from e
            bound.apply_defaults()
            _validated_learn_args(bound.arguments, own)
    return [learn_dynamics(system, n, s, **kwargs) for n in n_trains for s in seeds]


def _int_tuple(v: Any, name: str, own: str) -> tuple:
    if isinstance(v, (int, str)):
        raise TypeError(f"{own}: '{name}' must be a sequence of ints, got {v!r}")
    try:
        out = tuple(v)
    except TypeError:
        raise TypeError(f"{own}: '{name}' must be a sequence of ints, got {type(v).__name__}") from None
    if not out:
        raise ValueError(f"{own}: '{name}' must not be empty")
    return out
