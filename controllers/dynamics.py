"""Dynamics: the :class:`System` protocol, the two generic models, and the one place where a system is
stepped, rolled out and linearized.

A **system** is anything with

==================================  ===============================================================
``n: int``, ``m: int``              state and control dimensions (on a manifold: the tangent dimension)
``step(x, u, t) -> x_next``         one step, ``x (*B, n)``, ``u (*B, m)``, ``t`` a Python int
``jacobian(x, u, t) -> (A, B)``     *optional*: analytic ``∂step/∂x (*B, n, n)``, ``∂step/∂u (*B, n, m)``
``time_invariant: bool``            *optional* (False): ``step``/``jacobian`` ignore ``t`` and accept any
                                    leading dims, so a whole trajectory is one call (time folded into
                                    the batch)
``manifold``                        *optional* (None = Euclidean): a :mod:`torchlie.manifolds` space;
                                    then ``step`` is ``x ⊕ Δt f(x, u)`` and ``n`` is its tangent
                                    dimension (seed 003; used by the on-manifold MPC)
==================================  ===============================================================

:class:`LinearDynamics` (``x_{t+1} = A_t x_t + B_t u_t + c_t``), :class:`NonlinearDynamics` (a callable
with optional Jacobians) and the models of :mod:`controllers.systems` (``Pendulum``, ``CartPole``:
analytic Jacobians, time-invariant) are systems; so is any user class with these members
(:class:`System` is a ``typing.Protocol``, nothing to inherit).  The solvers never look inside a system
except through the functions below:

* :func:`step_all` — ``f(x_t, u_t, t)`` for every ``t`` at once (one call when time-invariant);
* :func:`rollout` — open-loop simulation ``x_0 .. x_T`` from ``x_0`` and ``u_0 .. u_{T-1}``;
* :func:`jacobians` — ``(f, ∂f/∂x, ∂f/∂u)`` at one step: the analytic ``jacobian`` when there is one,
  otherwise ``torch.func`` (``vmap`` of ``jacrev`` over the flattened batch), or ``jacrev`` of the
  batch sum (``method="batch-sum"``, which needs only that ``f`` never mixes batch elements);
* :func:`trajectory_jacobians` — time-major ``A (T, *B, n, n)``, ``B (T, *B, n, m)`` along a trajectory
  (what iLQR and its implicit gradient use);
* :func:`linearize` — the same as an affine :class:`LinearDynamics` ``A_t, B_t, c_t`` with
  ``c_t = f(x̄_t, ū_t, t) - A_t x̄_t - B_t ū_t``, ready for an LQ solver.

Shapes follow :mod:`controllers.problem` (batch first, ``x (*B, T+1, n)``, ``u (*B, T, m)``).
"""

from __future__ import annotations

import enum
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import torch

from controllers._validate import (
    all_finite,
    batch_dims,
    check_time,
    enum_arg,
    same_dtype_device,
    time_major,
    time_slice,
    timed,
)
from torchlie._batch import broadcast_shapes

__all__ = [
    "System",
    "LinearDynamics",
    "NonlinearDynamics",
    "JacobianMethod",
    "check_system",
    "is_time_invariant",
    "has_analytic_jacobian",
    "step_all",
    "rollout",
    "jacobians",
    "trajectory_jacobians",
    "linearize",
]


@runtime_checkable
class System(Protocol):
    """A discrete-time system (module docstring): ``n``, ``m`` and ``step(x, u, t)``; optionally
    ``jacobian``, ``time_invariant`` and ``manifold``."""

    n: int
    m: int

    def step(self, x: torch.Tensor, u: torch.Tensor, t: int) -> torch.Tensor: ...


@dataclass(frozen=True, eq=False)
class LinearDynamics:
    """``x_{t+1} = A_t x_t + B_t u_t + c_t``.

    Args:
        A: ``(*B, T, n, n)``, ``(*B, 1, n, n)`` or ``(n, n)`` (time-invariant, shared).
        B: ``(*B, T, n, m)``, ``(*B, 1, n, m)`` or ``(n, m)``.
        c: optional drift ``(*B, T, n)``, ``(*B, 1, n)`` or ``(n,)``.

    Stored with an explicit time dim (a ``(n, n)`` A becomes ``(1, n, n)``).
    """

    A: torch.Tensor
    B: torch.Tensor
    c: torch.Tensor | None = None

    def __post_init__(self) -> None:
        own = "LinearDynamics"
        A = timed(self.A, (None, None), "A", own, "(*B, T, n, n) or (n, n)")
        n = A.shape[-1]
        if A.shape[-2] != n:
            raise ValueError(f"{own}: field 'A' must be square (*B, T, n, n), got {tuple(self.A.shape)}")
        B = timed(self.B, (n, None), "B", own, f"(*B, T, {n}, m) or ({n}, m) with n={n} from A")
        c = None if self.c is None else timed(self.c, (n,), "c", own, f"(*B, T, {n}) or ({n},)")
        same_dtype_device(own, A=A, B=B, c=c)
        sizes = {"A": A.shape[-3], "B": B.shape[-3]}
        if c is not None:
            sizes["c"] = c.shape[-2]
        T = max(sizes.values())
        check_time(sizes, T, own, "all time-varying fields must share one horizon")
        try:
            broadcast_shapes(batch_dims(A, 2), batch_dims(B, 2),
                                   *([] if c is None else [batch_dims(c, 1)]))
        except RuntimeError as e:
            raise ValueError(f"{own}: batch dims of A {tuple(A.shape)}, B {tuple(B.shape)}"
                             f"{'' if c is None else f', c {tuple(c.shape)}'} do not broadcast") from e
        object.__setattr__(self, "A", A)
        object.__setattr__(self, "B", B)
        object.__setattr__(self, "c", c)

    @property
    def n(self) -> int:
        return self.A.shape[-1]

    @property
    def m(self) -> int:
        return self.B.shape[-1]

    @property
    def horizon(self) -> int | None:
        """Number of time steps if any field is time-varying, else ``None``."""
        T = max(self.A.shape[-3], self.B.shape[-3], 1 if self.c is None else self.c.shape[-2])
        return T if T > 1 else None

    @property
    def time_invariant(self) -> bool:
        return self.A.shape[-3] == 1 and self.B.shape[-3] == 1 and (self.c is None or self.c.shape[-2] == 1)

    @property
    def batch_shape(self) -> torch.Size:
        return broadcast_shapes(batch_dims(self.A, 2), batch_dims(self.B, 2),
                                      *([] if self.c is None else [batch_dims(self.c, 1)]))

    @property
    def dtype(self) -> torch.dtype:
        return self.A.dtype

    @property
    def device(self) -> torch.device:
        return self.A.device

    def step(self, x: torch.Tensor, u: torch.Tensor, t: int) -> torch.Tensor:
        """``x_{t+1}`` from ``x (*B, n)``, ``u (*B, m)``."""
        A, B, c = time_slice(self.A, t, 2), time_slice(self.B, t, 2), time_slice(self.c, t, 1)
        y = (A @ x.unsqueeze(-1) + B @ u.unsqueeze(-1)).squeeze(-1)
        return y if c is None else y + c

    def finite_mask(self) -> torch.Tensor:
        """``(*B,)`` bool: A, B, c finite for the element (computed on every call: nothing is memoized)."""
        fin = torch.ones((), dtype=torch.bool, device=self.device)
        for v, d in ((self.A, 3), (self.B, 3), (self.c, 2)):
            if v is not None:
                fin = fin & all_finite(v, d)
        return fin

    def expand_time(self, T: int) -> LinearDynamics:
        """Same dynamics with every field expanded (a view) to ``T`` time steps."""
        A = self.A.expand(*self.A.shape[:-3], T, *self.A.shape[-2:])
        B = self.B.expand(*self.B.shape[:-3], T, *self.B.shape[-2:])
        c = None if self.c is None else self.c.expand(*self.c.shape[:-2], T, self.n)
        return LinearDynamics(A, B, c)


@dataclass(frozen=True, eq=False)
class NonlinearDynamics:
    """``x_{t+1} = f(x_t, u_t, t)`` for a batched callable ``f``.

    Args:
        f: ``f(x (*B, n), u (*B, m), t) -> (*B, n)``, batched over any leading dims, no mixing across
            the batch.  ``t`` is a Python int (the time step), which ``f`` may ignore.
        n, m: state and control dimensions.
        jacobian: optional analytic Jacobians ``jacobian(x, u, t) -> (A (*B, n, n), B (*B, n, m))``;
            without it :func:`linearize` uses ``torch.func``.
        time_invariant: ``f`` and ``jacobian`` ignore ``t`` and accept any leading dims, so a whole
            trajectory is evaluated in one call (:class:`System`).
    """

    f: Callable[[torch.Tensor, torch.Tensor, int], torch.Tensor]
    n: int
    m: int
    jacobian: Callable[[torch.Tensor, torch.Tensor, int], tuple[torch.Tensor, torch.Tensor]] | None = None
    time_invariant: bool = False

    def __post_init__(self) -> None:
        if not callable(self.f):
            raise TypeError("NonlinearDynamics: field 'f' must be callable f(x, u, t), "
                            f"got {type(self.f).__name__}")
        if self.jacobian is not None and not callable(self.jacobian):
            raise TypeError("NonlinearDynamics: field 'jacobian' must be callable "
                            "jacobian(x, u, t) -> (A, B)")
        for name in ("n", "m"):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise ValueError(f"NonlinearDynamics: field '{name}' must be a positive int, got {v!r}")

    def step(self, x: torch.Tensor, u: torch.Tensor, t: int) -> torch.Tensor:
        if x.shape[-1] != self.n or u.shape[-1] != self.m:
            raise ValueError(f"NonlinearDynamics.step: expected x (*B, {self.n}) and u (*B, {self.m}), "
                             f"got {tuple(x.shape)} and {tuple(u.shape)}")
        return self.f(x, u, t)


# --------------------------------------------------------------------------------------------------
# dispatch: the only code that steps, rolls out or differentiates a system
# --------------------------------------------------------------------------------------------------


def check_system(d: Any, owner: str, name: str = "dynamics") -> None:
    """``TypeError`` naming ``owner``/``name`` unless ``d`` satisfies :class:`System`."""
    ok = (callable(getattr(d, "step", None)) and isinstance(getattr(d, "n", None), int)
          and isinstance(getattr(d, "m", None), int))
    if not ok:
        raise TypeError(f"{owner}: field '{name}' must be a system with integer n, m and step(x, u, t) "
                        f"(a LinearDynamics, a NonlinearDynamics or a model from controllers.systems); "
                        f"got {type(d).__name__}")
    jac = getattr(d, "jacobian", None)
    if jac is not None and not callable(jac):
        raise TypeError(f"{owner}: attribute 'jacobian' of field '{name}' must be callable or None")


def is_time_invariant(d: Any) -> bool:
    """Whether ``step``/``jacobian`` may be called once on a whole trajectory (time folded into the batch)."""
    return not isinstance(d, LinearDynamics) and bool(getattr(d, "time_invariant", False))


def has_analytic_jacobian(d: Any) -> bool:
    """Whether the Jacobians need no autograd (linear dynamics, or an analytic ``jacobian``)."""
    return isinstance(d, LinearDynamics) or callable(getattr(d, "jacobian", None))


def _full_batch(d: Any, x: torch.Tensor, u: torch.Tensor, t0: int) -> torch.Size:
    """Batch shape of a step along ``x (*B, T, n)``, ``u (*B, T, m)``, including the batch dims of the
    system's own parameters (e.g. one pendulum length per element), learnt from one step."""
    y = d.step(x[..., 0, :], u[..., 0, :], t0)
    return broadcast_shapes(x.shape[:-2], u.shape[:-2], y.shape[:-1])


def _fold_time(d: Any, x: torch.Tensor, u: torch.Tensor, t0: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``x``, ``u`` time-major ``(T, *B, ·)`` with every batch dim of the step present, so that time is
    folded into the batch *in front of* the parameters' batch dims, never aligned with them."""
    bs = _full_batch(d, x, u, t0)
    T = u.shape[-2]
    return (x[..., :T, :].expand(*bs, T, x.shape[-1]).movedim(-2, 0),
            u.expand(*bs, T, u.shape[-1]).movedim(-2, 0))


def step_all(d: System, x: torch.Tensor, u: torch.Tensor, t0: int = 0) -> torch.Tensor:
    """``f(x_t, u_t, t0 + t)`` for all ``t``: ``x (*B, T, n)``, ``u (*B, T, m)`` -> ``(*B, T, n)``."""
    if is_time_invariant(d):
        return d.step(*_fold_time(d, x, u, t0), t0).movedim(0, -2)
    return torch.stack([d.step(x[..., t, :], u[..., t, :], t0 + t) for t in range(u.shape[-2])], -2)


def rollout(d: System, x0: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """Simulate ``x (*B, T+1, n)`` from ``x0 (*B, n)`` and open-loop controls ``u (*B, T, m)``.

    A time-invariant system with a ``rollout_states(x0, u)`` method (a simulator that runs a whole control
    sequence in one call, e.g. :class:`~controllers.systems.mujoco_system.MujocoSystem`) runs it there."""
    whole = getattr(d, "rollout_states", None)
    if callable(whole) and getattr(d, "time_invariant", False) and u.shape[-2] > 0:
        bs = broadcast_shapes(x0.shape[:-1], u.shape[:-2])
        return whole(x0.expand(*bs, x0.shape[-1]), u.expand(*bs, *u.shape[-2:]))
    xs = [x0]
    for t in range(u.shape[-2]):
        xs.append(d.step(xs[-1], u[..., t, :], t))
    shape = broadcast_shapes(*[v.shape for v in xs], (*u.shape[:-2], x0.shape[-1]))  # u's batch too, T = 0
    return torch.stack([v.expand(shape) for v in xs], dim=-2)


class JacobianMethod(str, enum.Enum):
    AUTO = "auto"  #: analytic when available, else VMAP
    ANALYTIC = "analytic"  #: the system's own ``jacobian(x, u, t)``
    VMAP = "vmap"  #: ``torch.func.vmap(torch.func.jacrev(f))`` over the flattened batch
    BATCH_SUM = "batch-sum"  #: ``torch.func.jacrev`` of ``f(x, u, t).sum(batch)``


def _step_fn(f) -> Callable | None:
    if isinstance(f, NonlinearDynamics):
        return f.f
    if callable(getattr(f, "step", None)):
        return f.step
    return f if callable(f) else None


def jacobians(f: System | Callable, x: torch.Tensor, u: torch.Tensor, t: int = 0,
              method: JacobianMethod | str = JacobianMethod.AUTO
              ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(f(x, u, t) (*B, n), ∂f/∂x (*B, n, n), ∂f/∂u (*B, n, m))`` at one time step.

    Args:
        f: a system (:class:`System`) or a batched callable ``f(x, u, t)``.
        x: ``(*B, n)``; u: ``(*B, m)`` (batch dims broadcast).
        method: :class:`JacobianMethod`.
    """
    return _jacobians(f, x, u, t, enum_arg(JacobianMethod, method, "method", "jacobians"), True)


def _jacobians(f, x: torch.Tensor, u: torch.Tensor, t: int, method: JacobianMethod, value: bool):
    """:func:`jacobians`; without ``value`` the first output is None where computing it costs a call."""
    fn = _step_fn(f)
    if fn is None:
        raise TypeError(f"jacobians: 'f' must be a system or a callable f(x, u, t), got {type(f).__name__}")
    jac = None if isinstance(f, LinearDynamics) else getattr(f, "jacobian", None)
    bs = broadcast_shapes(x.shape[:-1], u.shape[:-1])
    n, m = x.shape[-1], u.shape[-1]
    x = x.expand(*bs, n)
    u = u.expand(*bs, m)
    y = (lambda: fn(x, u, t) if value else None)
    if isinstance(f, LinearDynamics) and method in (JacobianMethod.AUTO, JacobianMethod.ANALYTIC):
        A, B = time_slice(f.A, t, 2), time_slice(f.B, t, 2)
        full = broadcast_shapes(bs, A.shape[:-2], B.shape[:-2])  # per-element matrices
        return y(), A.expand(*full, n, n), B.expand(*full, n, m)
    if method is JacobianMethod.AUTO:
        method = JacobianMethod.ANALYTIC if jac is not None else JacobianMethod.VMAP
    if method is JacobianMethod.ANALYTIC:
        if jac is None:
            raise ValueError("jacobians: method='analytic' needs a system with a 'jacobian'")
        A, B = jac(x, u, t)
        # a model's parameters may carry batch dims of their own (e.g. one pendulum length per element)
        full = broadcast_shapes(bs, A.shape[:-2], B.shape[:-2])
        return y(), A.expand(*full, n, n), B.expand(*full, n, m)
    if method is JacobianMethod.VMAP:
        xf, uf = x.reshape(-1, n), u.reshape(-1, m)

        def single(xi, ui):
            y = fn(xi.unsqueeze(0), ui.unsqueeze(0), t).squeeze(0)
            return y, y

        (A, B), y = torch.func.vmap(torch.func.jacrev(single, argnums=(0, 1), has_aux=True))(xf, uf)
        k = y.shape[-1]  # explicit sizes: -1 is ambiguous for an empty batch
        return y.reshape(*bs, k), A.reshape(*bs, k, n), B.reshape(*bs, k, m)
    # batch-sum: d/dx Σ_b f(x_b) has, for an element-wise-independent f, the per-element Jacobians
    nb = len(bs)

    def summed(xx, uu):
        y = fn(xx, uu, t)
        return y.sum(tuple(range(nb))) if nb else y, y

    (A, B), y = torch.func.jacrev(summed, argnums=(0, 1), has_aux=True)(x, u)  # (n_out, *B, n)
    A = A.movedim(0, -2) if nb else A
    B = B.movedim(0, -2) if nb else B
    return y, A, B


def trajectory_jacobians(d: System, x: torch.Tensor, u: torch.Tensor, t0: int = 0,
                         method: JacobianMethod | str = JacobianMethod.AUTO,
                         time_invariant: bool | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Time-major ``A (T, *B, n, n)``, ``B (T, *B, n, m)`` of ``step`` along ``x (*B, T[+1], n)``,
    ``u (*B, T, m)`` at steps ``t0 .. t0+T-1``.

    Linear dynamics return their matrices (batch dims right-aligned with the trajectory's, singletons
    where shared; views); a time-invariant system (``time_invariant``, default: the system's own flag)
    is evaluated in one call; otherwise one :func:`jacobians` call per step.
    """
    T = u.shape[-2]
    if isinstance(d, LinearDynamics):
        nb = max(x.dim(), u.dim()) - 2
        return time_major(d.A, 2, T, nb), time_major(d.B, 2, T, nb)
    ti = is_time_invariant(d) if time_invariant is None else time_invariant
    method = enum_arg(JacobianMethod, method, "method", "trajectory_jacobians")
    if ti:
        _, A, B = _jacobians(d, *_fold_time(d, x, u, t0), t0, method, False)
        return A, B
    As, Bs = [], []
    for t in range(T):
        _, A, B = _jacobians(d, x[..., t, :], u[..., t, :], t0 + t, method, False)
        As.append(A)
        Bs.append(B)
    return torch.stack(As), torch.stack(Bs)


def linearize(f: System | Callable, x: torch.Tensor, u: torch.Tensor, t0: int = 0,
              method: JacobianMethod | str = JacobianMethod.AUTO, time_invariant: bool | None = None
              ) -> LinearDynamics:
    """Affine model ``A_t, B_t, c_t`` of ``f`` along ``x (*B, T, n)`` (or ``(*B, T+1, n)``, the last state
    is then ignored) and ``u (*B, T, m)``; time steps are ``t0 .. t0+T-1``.

    ``time_invariant=True`` evaluates all steps in one call with ``t = t0`` (for ``f`` that ignores
    ``t``); ``None`` takes the system's own flag (:class:`System`).
    """
    if x.dim() < 2 or u.dim() < 2:
        raise ValueError(f"linearize: x must be (*B, T, n) and u (*B, T, m), "
                         f"got {tuple(x.shape)}, {tuple(u.shape)}")
    T = u.shape[-2]
    if x.shape[-2] == T + 1:
        x = x[..., :T, :]
    if x.shape[-2] != T:
        raise ValueError(f"linearize: x must have T = {T} (or T+1) steps to match u, got {tuple(x.shape)}")
    if _step_fn(f) is None:
        raise TypeError(f"linearize: 'f' must be a system or a callable f(x, u, t), got {type(f).__name__}")
    sys = f if callable(getattr(f, "step", None)) else NonlinearDynamics(f, x.shape[-1], u.shape[-1])
    # the batch shape includes the system's own (per-element parameters or matrices)
    bs = _full_batch(sys, x, u, t0)
    x = x.expand(*bs, T, x.shape[-1])
    u = u.expand(*bs, T, u.shape[-1])
    ti = is_time_invariant(sys) if time_invariant is None else time_invariant
    A, B = trajectory_jacobians(sys, x, u, t0, method, ti)
    A = A.movedim(0, -3).expand(*bs, T, *A.shape[-2:])
    B = B.movedim(0, -3).expand(*bs, T, *B.shape[-2:])
    if ti:
        y = _step_fn(sys)(x.movedim(-2, 0), u.movedim(-2, 0), t0).movedim(0, -2)
    else:
        y = step_all(sys, x, u, t0)
    c = y - (A @ x.unsqueeze(-1)).squeeze(-1) - (B @ u.unsqueeze(-1)).squeeze(-1)
    return LinearDynamics(A, B, c)
