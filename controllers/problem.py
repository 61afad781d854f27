"""Problems and solutions for the LQT/LQR/iLQR solvers: frozen dataclasses on plain tensors.

Conventions (shared by every solver in :mod:`controllers`)
---------------------------------------------------------
* Time index ``t = 0 .. T``: states ``x_0 .. x_T`` (``(*B, T+1, n)``), controls ``u_0 .. u_{T-1}``
  (``(*B, T, m)``).  The seed (cookbook 004 §7) counts from 1; ``x_1`` there is ``x_0`` here.
* Linear dynamics ``x_{t+1} = A_t x_t + B_t u_t + c_t`` with ``A (*B, T, n, n)``, ``B (*B, T, n, m)``,
  ``c (*B, T, n)``.  Batch dims broadcast like torch; a time dim of size 1 broadcasts over time; a
  matrix without a time dim (``A (n, n)``, ``c (n,)``) is time-invariant and shared by the batch.
  To give a time-invariant matrix *per batch element* use a time dim of 1: ``A (B, 1, n, n)``.
  **One broadcasting rule for every entry point** (``riccati.solve``/``lqr``, ``lifted``, ``ilqr``
  in both formulations and all gradient modes, ``box_qp``, ``mpc``): the batch dims of every field,
  of ``x0`` and of control limits (``(*B, T, m)``) broadcast against each other like torch shapes,
  right-aligned; the solution has the broadcast batch shape, and a gradient has its input's own shape
  (summed over the dims it was broadcast along).  Shapes that do not broadcast are a ``ValueError``
  naming the fields (``tests/controllers/test_broadcasting.py``).
* Quadratic cost (seed Eq. 59, *without* a factor 1/2, linear terms with a factor 2), per step::

      l_t = dx_tᵀ Q_t dx_t + du_tᵀ R_t du_t + 2 dx_tᵀ N_t du_t + 2 q_tᵀ dx_t + 2 r_tᵀ du_t
      l_T = dx_Tᵀ Q_T dx_T + 2 q_Tᵀ dx_T,        dx_t = x_t - μ_t,  du_t = u_t - ν_t

  with ``Q (*B, T+1, n, n)`` (the last entry is the terminal precision; ``Q_0`` only matters when the
  initial state is optimized, Eq. 65), ``R (*B, T, m, m)``, optional references ``x_ref = μ``
  ``(*B, T+1, n)``, ``u_ref = ν`` ``(*B, T, m)``, cross terms ``N (*B, T, n, m)``, linear terms
  ``q (*B, T+1, n)``, ``r (*B, T, m)``.  Q may be full (off-diagonal, cross-agent) and may be zero at
  all but a few via-point times (:meth:`QuadraticCost.via_points`).  The total cost is ``Σ_t l_t``.
  :meth:`QuadraticCost.canonical` expands the references into the plain form
  ``xᵀQx + uᵀRu + 2xᵀNu + 2qᵀx + 2rᵀu + const`` used inside the solvers.
* Solutions (:class:`LQSolution`) carry the trajectory, the affine policy ``u_t = K_t x_t + k_t`` and
  per-batch-element :class:`SolverStatus` (converged, iterations, reason code from :class:`Reason`).

Checks: shapes, dtypes and devices are validated at construction; an error names the field and the
expected shape.  A non-symmetric Q/R is always an error.  Definiteness (Q ⪰ 0, R ≻ 0) is checked at
construction when the matrix is shared by the whole batch (then a bad matrix is a ``ValueError``);
when Q or R carries batch dims, :meth:`QuadraticCost.definite_mask` gives the per-element verdict and
the solvers report the failing elements with ``Reason.NOT_POSITIVE_DEFINITE`` instead of raising.
"""

from __future__ import annotations

import enum
from collections.abc import Callable
from dataclasses import dataclass, field

import torch

__all__ = [
    "Reason",
    "SolverStatus",
    "LinearDynamics",
    "NonlinearDynamics",
    "QuadraticCost",
    "CanonicalCost",
    "LQProblem",
    "LQSolution",
    "rollout",
    "time_slice",
    "enum_arg",
]


def enum_arg(cls, value, name: str, fn: str):
    """``cls(value)`` for a mode argument, with an error that names the argument and the choices."""
    try:
        return cls(value)
    except ValueError:
        choices = ", ".join(repr(m.value) for m in cls)
        raise ValueError(f"{fn}: argument '{name}' must be one of {choices} (a {cls.__name__}), "
                         f"got {value!r}") from None


# --------------------------------------------------------------------------------------------------
# status
# --------------------------------------------------------------------------------------------------


class Reason(enum.IntEnum):
    """Why a solver stopped, per batch element (stored as int64 codes in :attr:`SolverStatus.reason`)."""

    #: solved: an LQ problem in one pass; an iterative solver only where its optimality (KKT) residual was
    #: checked below tolerance at the returned point
    CONVERGED = 0
    NONFINITE_INPUT = 1  #: NaN/inf in x0 or in the problem data of this element
    NOT_POSITIVE_DEFINITE = 2  #: Q not PSD or R not PD for this element
    SINGULAR_QUU = 3  #: Q_uu (or the lifted normal matrix) not PD in the backward pass
    MAX_ITERATIONS = 4  #: iterative solver hit its iteration limit
    LINE_SEARCH_FAILED = 5  #: no step length decreased the cost
    DIVERGED = 6  #: non-finite values appeared while iterating
    #: no progress (a negligible step or cost decrease) at a point whose KKT residual is above tolerance:
    #: not a certified optimum (e.g. the inner QP could not find a descent direction)
    STALLED = 7


@dataclass(frozen=True, eq=False)
class SolverStatus:
    """Per-batch-element outcome: ``converged (*B,) bool``, ``iterations (*B,) int64``,
    ``reason (*B,) int64`` (codes of :class:`Reason`)."""

    converged: torch.Tensor
    iterations: torch.Tensor
    reason: torch.Tensor

    @staticmethod
    def from_reason(reason: torch.Tensor, iterations: torch.Tensor | int = 1) -> SolverStatus:
        reason = reason.to(torch.int64)
        it = torch.as_tensor(iterations, dtype=torch.int64, device=reason.device).expand(reason.shape)
        return SolverStatus(converged=reason == int(Reason.CONVERGED), iterations=it.clone(), reason=reason)

    @property
    def all_converged(self) -> bool:
        return bool(self.converged.all())

    def reason_names(self) -> list[str]:
        """The reasons as names, flattened over the batch in row-major order."""
        return [Reason(int(c)).name for c in self.reason.reshape(-1).tolist()]


# --------------------------------------------------------------------------------------------------
# shape helpers
# --------------------------------------------------------------------------------------------------


def _check_tensor(x, name: str, owner: str) -> torch.Tensor:
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{owner}: field '{name}' must be a torch.Tensor, got {type(x).__name__}")
    if not x.dtype.is_floating_point:
        raise TypeError(f"{owner}: field '{name}' must have a floating dtype, got {x.dtype}")
    return x


def _timed(x: torch.Tensor, trailing: tuple[int | None, ...], name: str, owner: str, expected: str
           ) -> torch.Tensor:
    """Check ``x`` is ``(*B, Tx, *trailing)`` or ``(*trailing)`` (then a time dim of 1 is inserted).

    ``None`` in ``trailing`` matches any size.  Returns a tensor with an explicit time dim.
    """
    _check_tensor(x, name, owner)
    k = len(trailing)

    def ok(shape: tuple[int, ...]) -> bool:
        return all(t is None or s == t for s, t in zip(shape, trailing))

    if x.dim() == k and ok(tuple(x.shape)):
        return x.unsqueeze(0)
    if x.dim() >= k + 1 and ok(tuple(x.shape[x.dim() - k:])):
        return x
    raise ValueError(f"{owner}: field '{name}' must have shape {expected}, got {tuple(x.shape)}")


def _same_dtype_device(owner: str, **tensors: torch.Tensor | None) -> None:
    items = [(k, v) for k, v in tensors.items() if v is not None]
    k0, t0 = items[0]
    for k, t in items[1:]:
        if t.dtype != t0.dtype:
            raise TypeError(f"{owner}: fields '{k0}' and '{k}' have different dtypes "
                            f"({t0.dtype} vs {t.dtype}); "
                            "cast explicitly (nothing is cast silently)")
        if t.device != t0.device:
            raise ValueError(f"{owner}: fields '{k0}' and '{k}' are on different devices "
                             f"({t0.device} vs {t.device})")


def _batch_shape(x: torch.Tensor, k: int) -> torch.Size:
    """Batch dims of a timed tensor with ``k`` trailing dims (time dim excluded)."""
    return x.shape[: x.dim() - k - 1]


def _check_time(sizes: dict[str, int], want: int, owner: str, what: str) -> None:
    for name, s in sizes.items():
        if s not in (1, want):
            raise ValueError(f"{owner}: field '{name}' has {s} time steps, expected 1 or {want} ({what})")


def _versions(*tensors: torch.Tensor | None) -> tuple:
    """In-place version counters of the tensors: part of every cache key, so that a cached quantity is
    recomputed after its data changed in place (e.g. an ``nn.Parameter`` after an optimizer step)."""
    # inference-mode tensors have no version counter and cannot be modified in place outside inference
    # mode, so their identity is enough
    return tuple(-1 if v is None else ("inference", id(v)) if v.is_inference() else v._version
                 for v in tensors)


def time_slice(x: torch.Tensor | None, t: int, k: int) -> torch.Tensor | None:
    """Entry ``t`` of a timed tensor with ``k`` trailing dims (a time dim of 1 broadcasts)."""
    if x is None:
        return None
    d = x.dim() - k - 1
    return x.select(d, t if x.shape[d] > 1 else 0)


def _symmetric(M: torch.Tensor, name: str, owner: str) -> None:
    Md = M.detach()
    # one scalar per check (NaN entries are the non-finite check's business: NaN > tol is False)
    asym = float(torch.sub(Md, Md.mT).abs_().amax()) if Md.numel() else 0.0
    if not asym > 0.0:
        return
    scale = max(float(Md.abs().amax()), 1.0)
    if asym > 1e3 * torch.finfo(M.dtype).eps * scale:
        raise ValueError(f"{owner}: field '{name}' must be symmetric (max |{name} - {name}ᵀ| = "
                         f"{asym:.3g}); symmetrize it with ({name} + {name}ᵀ)/2")


def _all_finite(v: torch.Tensor, k: int) -> torch.Tensor:
    """``(...)`` bool over the leading dims: all of the last ``k`` dims finite.  ``max |v|`` is NaN or inf
    exactly when an entry is (amax propagates NaN), and is several times cheaper than ``isfinite().all()``."""
    v = v.detach()
    if k == 0:
        return torch.isfinite(v)
    return torch.isfinite(v.flatten(-k).abs().amax(-1)) if v.numel() else torch.ones(
        v.shape[:v.dim() - k], dtype=torch.bool, device=v.device)


def _psd_mask(M: torch.Tensor, strict: bool) -> torch.Tensor:
    """``(...)`` bool over the leading dims: M ⪰ 0 (``strict``: M ≻ 0) up to a dtype tolerance.

    One batched Cholesky of ``M + δ I`` (``δ`` = a dtype tolerance times the largest diagonal entry,
    0 when ``strict``): several times cheaper than eigenvalues, and exact zeros (via-point precisions)
    pass.  Non-finite matrices are reported as definite here (they are the non-finite check's business).
    """
    Md = M.detach()
    finite = _all_finite(Md, 2)
    eye = torch.eye(Md.shape[-1], dtype=Md.dtype, device=Md.device)
    if not bool(finite.all()):
        Md = torch.where(finite[..., None, None], Md, eye)
    if not strict:
        scale = Md.diagonal(dim1=-2, dim2=-1).abs().amax(-1).clamp_min(1.0)
        Md = Md + (1e2 * torch.finfo(Md.dtype).eps * Md.shape[-1] * scale)[..., None, None] * eye
    _, info = torch.linalg.cholesky_ex(Md)
    return (info == 0) | ~finite


# --------------------------------------------------------------------------------------------------
# dynamics
# --------------------------------------------------------------------------------------------------


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
    _cache: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        own = "LinearDynamics"
        A = _timed(self.A, (None, None), "A", own, "(*B, T, n, n) or (n, n)")
        n = A.shape[-1]
        if A.shape[-2] != n:
            raise ValueError(f"{own}: field 'A' must be square (*B, T, n, n), got {tuple(self.A.shape)}")
        B = _timed(self.B, (n, None), "B", own, f"(*B, T, {n}, m) or ({n}, m) with n={n} from A")
        c = None if self.c is None else _timed(self.c, (n,), "c", own, f"(*B, T, {n}) or ({n},)")
        _same_dtype_device(own, A=A, B=B, c=c)
        sizes = {"A": A.shape[-3], "B": B.shape[-3]}
        if c is not None:
            sizes["c"] = c.shape[-2]
        T = max(sizes.values())
        _check_time(sizes, T, own, "all time-varying fields must share one horizon")
        try:
            torch.broadcast_shapes(_batch_shape(A, 2), _batch_shape(B, 2),
                                   *([] if c is None else [_batch_shape(c, 1)]))
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
        return torch.broadcast_shapes(_batch_shape(self.A, 2), _batch_shape(self.B, 2),
                                      *([] if self.c is None else [_batch_shape(self.c, 1)]))

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
        """``(*B,)`` bool: A, B, c finite for the element (cached; recomputed after in-place changes)."""
        key = ("finite", _versions(self.A, self.B, self.c))
        if key not in self._cache:
            fin = torch.ones((), dtype=torch.bool, device=self.device)
            for v, d in ((self.A, 3), (self.B, 3), (self.c, 2)):
                if v is not None:
                    fin = fin & _all_finite(v, d)
            self._cache.clear()
            self._cache[key] = fin
        return self._cache[key]

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
            without it :func:`controllers.linearize.linearize` uses ``torch.func``.
    """

    f: Callable[[torch.Tensor, torch.Tensor, int], torch.Tensor]
    n: int
    m: int
    jacobian: Callable[[torch.Tensor, torch.Tensor, int], tuple[torch.Tensor, torch.Tensor]] | None = None

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


def rollout(dynamics: LinearDynamics | NonlinearDynamics, x0: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """Simulate ``x (*B, T+1, n)`` from ``x0 (*B, n)`` and open-loop controls ``u (*B, T, m)``."""
    T = u.shape[-2]
    xs = [x0]
    for t in range(T):
        xs.append(dynamics.step(xs[-1], u[..., t, :], t))
    shape = torch.broadcast_shapes(*[x.shape for x in xs])
    return torch.stack([x.expand(shape) for x in xs], dim=-2)


# --------------------------------------------------------------------------------------------------
# costs
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class CanonicalCost:
    """``Σ_t xᵀQx + uᵀRu + 2xᵀNu + 2qᵀx + 2rᵀu + const`` (references expanded); ``N``/``r`` may be None.

    Shapes as in :class:`QuadraticCost` (explicit time dims); ``const (*B,)`` or a 0-dim tensor.
    """

    Q: torch.Tensor
    R: torch.Tensor
    q: torch.Tensor | None
    r: torch.Tensor | None
    N: torch.Tensor | None
    const: torch.Tensor


@dataclass(frozen=True, eq=False)
class QuadraticCost:
    """Quadratic tracking cost (module docstring; seed 004 Eq. 59 with full precision matrices).

    Args:
        Q: ``(*B, T+1, n, n)``, ``(*B, 1, n, n)`` or ``(n, n)``; symmetric PSD.
        R: ``(*B, T, m, m)``, ``(*B, 1, m, m)`` or ``(m, m)``; symmetric PD.
        x_ref: μ, ``(*B, T+1, n)`` / ``(*B, 1, n)`` / ``(n,)``.
        u_ref: ν, ``(*B, T, m)`` / ``(*B, 1, m)`` / ``(m,)``.
        N: cross term ``(*B, T, n, m)`` / ``(n, m)``.
        q, r: linear terms on the deviations, ``(*B, T+1, n)`` and ``(*B, T, m)``.
        check: verify symmetry and (for matrices shared by the batch) definiteness at construction.
    """

    Q: torch.Tensor
    R: torch.Tensor
    x_ref: torch.Tensor | None = None
    u_ref: torch.Tensor | None = None
    N: torch.Tensor | None = None
    q: torch.Tensor | None = None
    r: torch.Tensor | None = None
    check: bool = field(default=True, repr=False)
    _cache: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        own = "QuadraticCost"
        Q = _timed(self.Q, (None, None), "Q", own, "(*B, T+1, n, n) or (n, n)")
        n = Q.shape[-1]
        if Q.shape[-2] != n:
            raise ValueError(f"{own}: field 'Q' must be square (*B, T+1, n, n), got {tuple(self.Q.shape)}")
        R = _timed(self.R, (None, None), "R", own, "(*B, T, m, m) or (m, m)")
        m = R.shape[-1]
        if R.shape[-2] != m:
            raise ValueError(f"{own}: field 'R' must be square (*B, T, m, m), got {tuple(self.R.shape)}")
        opt = {}
        if self.x_ref is not None:
            opt["x_ref"] = _timed(self.x_ref, (n,), "x_ref", own, f"(*B, T+1, {n}) or ({n},)")
        if self.u_ref is not None:
            opt["u_ref"] = _timed(self.u_ref, (m,), "u_ref", own, f"(*B, T, {m}) or ({m},)")
        if self.N is not None:
            opt["N"] = _timed(self.N, (n, m), "N", own, f"(*B, T, {n}, {m}) or ({n}, {m})")
        if self.q is not None:
            opt["q"] = _timed(self.q, (n,), "q", own, f"(*B, T+1, {n}) or ({n},)")
        if self.r is not None:
            opt["r"] = _timed(self.r, (m,), "r", own, f"(*B, T, {m}) or ({m},)")
        _same_dtype_device(own, Q=Q, R=R, **opt)
        # horizons: state-indexed fields have T+1 entries, control-indexed ones T
        Ts = {"R": R.shape[-3]}
        for k in ("u_ref", "N", "r"):
            if k in opt:
                Ts[k] = opt[k].shape[-2 if k != "N" else -3]
        Tx = {"Q": Q.shape[-3]}
        for k in ("x_ref", "q"):
            if k in opt:
                Tx[k] = opt[k].shape[-2]
        T_from_u = max(Ts.values())
        T_from_x = max(Tx.values()) - 1
        T = max(T_from_u, T_from_x)
        if T >= 1:
            _check_time(Ts, T, own, "control-indexed fields R, u_ref, N, r have T entries")
            _check_time(Tx, T + 1, own, "state-indexed fields Q, x_ref, q have T+1 entries")
        trailing = {"Q": 2, "R": 2, "x_ref": 1, "u_ref": 1, "N": 2, "q": 1, "r": 1}
        allf = {"Q": Q, "R": R, **opt}
        try:
            torch.broadcast_shapes(*[_batch_shape(v, trailing[k]) for k, v in allf.items()])
        except RuntimeError as e:
            shapes = ", ".join(f"{k} {tuple(v.shape)}" for k, v in allf.items())
            raise ValueError(f"{own}: batch dims do not broadcast: {shapes}") from e
        object.__setattr__(self, "Q", Q)
        object.__setattr__(self, "R", R)
        for k, v in opt.items():
            object.__setattr__(self, k, v)
        if self.check:
            _symmetric(Q, "Q", own)
            _symmetric(R, "R", own)
            if Q.dim() == 3 and not bool(_psd_mask(Q, strict=False).all()):
                raise ValueError(f"{own}: field 'Q' must be positive semi-definite at every time step")
            if R.dim() == 3 and not bool(_psd_mask(R, strict=True).all()):
                raise ValueError(f"{own}: field 'R' must be positive definite at every time step")

    # ---- properties
    @property
    def n(self) -> int:
        return self.Q.shape[-1]

    @property
    def m(self) -> int:
        return self.R.shape[-1]

    @property
    def horizon(self) -> int | None:
        """``T`` if any field is time-varying (a time dim > 1), else ``None``."""
        T = 0
        for k, d in (("R", -3), ("u_ref", -2), ("N", -3), ("r", -2)):
            v = getattr(self, k)
            if v is not None and v.shape[d] > 1:
                T = max(T, v.shape[d])
        for k, d in (("Q", -3), ("x_ref", -2), ("q", -2)):
            v = getattr(self, k)
            if v is not None and v.shape[d] > 1:
                T = max(T, v.shape[d] - 1)
        return T if T >= 1 else None

    @property
    def batch_shape(self) -> torch.Size:
        tr = {"Q": 2, "R": 2, "x_ref": 1, "u_ref": 1, "N": 2, "q": 1, "r": 1}
        return torch.broadcast_shapes(*[_batch_shape(getattr(self, k), d) for k, d in tr.items()
                                        if getattr(self, k) is not None])

    @property
    def dtype(self) -> torch.dtype:
        return self.Q.dtype

    @property
    def device(self) -> torch.device:
        return self.Q.device

    # ---- constructors
    @staticmethod
    def via_points(T: int, times: list[int] | torch.Tensor, targets: torch.Tensor, precision: torch.Tensor,
                   R: torch.Tensor) -> QuadraticCost:
        """Sparse via-point cost: precision zero except at ``times`` (ints in ``[0, T]``).

        Args:
            targets: ``(*B, K, n)`` via points (one per time in ``times``).
            precision: ``(n, n)``, ``(K, n, n)`` or ``(*B, K, n, n)``: the precision at each via point.
            R: control weight as in :class:`QuadraticCost`.
        """
        own = "QuadraticCost.via_points"
        times_t = torch.as_tensor(times, dtype=torch.int64).reshape(-1)
        K = times_t.numel()
        _check_tensor(targets, "targets", own)
        if targets.dim() < 2 or targets.shape[-2] != K:
            raise ValueError(f"{own}: argument 'targets' must have shape (*B, {K}, n) "
                             f"for {K} via-point times, "
                             f"got {tuple(targets.shape)}")
        if bool(((times_t < 0) | (times_t > T)).any()):
            raise ValueError(f"{own}: argument 'times' must lie in [0, {T}], got {times_t.tolist()}")
        if times_t.unique().numel() != K:
            raise ValueError(f"{own}: argument 'times' must not repeat, got {times_t.tolist()}")
        n = targets.shape[-1]
        _check_tensor(precision, "precision", own)
        if precision.shape[-2:] != (n, n):
            raise ValueError(f"{own}: argument 'precision' must have shape (*B, {K}, {n}, {n}) "
                             f"or ({n}, {n}), "
                             f"got {tuple(precision.shape)}")
        if precision.dim() == 2:
            precision = precision.expand(K, n, n)
        dev, dt = targets.device, targets.dtype
        batch = torch.broadcast_shapes(targets.shape[:-2], precision.shape[:-3])
        Q = torch.zeros(*batch, T + 1, n, n, dtype=dt, device=dev)
        mu = torch.zeros(*batch, T + 1, n, dtype=dt, device=dev)
        idx = times_t.to(dev)
        Q = Q.index_copy(-3, idx, precision.expand(*batch, K, n, n).to(dt))
        mu = mu.index_copy(-2, idx, targets.expand(*batch, K, n))
        return QuadraticCost(Q=Q, R=R, x_ref=mu)

    # ---- evaluation
    def canonical(self, T: int) -> CanonicalCost:
        """Expand the references for horizon ``T``:
        ``Σ dxᵀQdx + ... = Σ xᵀQx + uᵀRu + 2xᵀNu + 2q'ᵀx + 2r'ᵀu + const``.

        ``Q``, ``R``, ``N`` keep their (possibly broadcast) time dims; ``q'``/``r'`` get full time dims
        ``T+1``/``T`` when a reference or linear term is present (else ``None``); ``const (*B,)``.
        """
        Q, R, N = self.Q, self.R, self.N
        mu, nu = _expand_t(self.x_ref, T + 1, 1), _expand_t(self.u_ref, T, 1)
        q, r = _expand_t(self.q, T + 1, 1), _expand_t(self.r, T, 1)
        const = torch.zeros((), dtype=Q.dtype, device=Q.device)
        qc, rc = q, r
        if mu is not None:
            Qmu = (Q @ mu.unsqueeze(-1)).squeeze(-1)
            qc = -Qmu if qc is None else qc - Qmu
            const = const + (mu * Qmu).sum((-1, -2))
            if q is not None:
                const = const - 2 * (q * mu).sum((-1, -2))
        if nu is not None:
            Rnu = (R @ nu.unsqueeze(-1)).squeeze(-1)
            rc = -Rnu if rc is None else rc - Rnu
            const = const + (nu * Rnu).sum((-1, -2))
            if r is not None:
                const = const - 2 * (r * nu).sum((-1, -2))
        if N is not None:
            # 2(x-μ)ᵀN(u-ν) = 2xᵀNu - 2(Nν)ᵀx - 2(Nᵀμ)ᵀu + 2μᵀNν   (μ on steps 0..T-1)
            if nu is not None:
                Nnu = (N @ nu.unsqueeze(-1)).squeeze(-1)
                Nnu = torch.cat([Nnu, torch.zeros_like(Nnu[..., :1, :])], dim=-2)
                qc = -Nnu if qc is None else qc - Nnu
            if mu is not None:
                NTmu = (N.mT @ mu[..., :-1, :].unsqueeze(-1)).squeeze(-1)
                rc = -NTmu if rc is None else rc - NTmu
                if nu is not None:
                    const = const + 2 * (NTmu * nu).sum((-1, -2))
        return CanonicalCost(Q=Q, R=R, q=qc, r=rc, N=N, const=const)

    def evaluate(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """Total cost ``(*B,)`` of a trajectory ``x (*B, T+1, n)``, ``u (*B, T, m)``."""
        T = u.shape[-2]
        if x.shape[-2] != T + 1:
            raise ValueError(f"QuadraticCost.evaluate: x must have T+1 = {T + 1} steps, got {tuple(x.shape)}")
        dx = x if self.x_ref is None else x - self.x_ref
        du = u if self.u_ref is None else u - self.u_ref
        c = (dx.unsqueeze(-2) @ self.Q @ dx.unsqueeze(-1)).squeeze(-1).squeeze(-1)
        c = _time_sum(c, T + 1)
        cu = (du.unsqueeze(-2) @ self.R @ du.unsqueeze(-1)).squeeze(-1).squeeze(-1)
        c = c + _time_sum(cu, T)
        if self.N is not None:
            cn = (dx[..., :-1, :].unsqueeze(-2) @ self.N @ du.unsqueeze(-1)).squeeze(-1).squeeze(-1)
            c = c + 2 * _time_sum(cn, T)
        if self.q is not None:
            c = c + 2 * _time_sum((self.q * dx).sum(-1), T + 1)
        if self.r is not None:
            c = c + 2 * _time_sum((self.r * du).sum(-1), T)
        return c

    def definite_mask(self) -> torch.Tensor:
        """``(*B,)`` bool: Q_t ⪰ 0 and R_t ≻ 0 at every time step of each batch element.

        Computed once per cost object and cached (recomputed if a field was modified in place).
        """
        key = ("definite", _versions(self.Q, self.R))
        if key not in self._cache:
            okQ = _psd_mask(self.Q, strict=False).all(-1)
            okR = _psd_mask(self.R, strict=True).all(-1)
            self._evict(key[0])
            self._cache[key] = okQ & okR
        return self._cache[key]

    def finite_mask(self) -> torch.Tensor:
        """``(*B,)`` bool: every field of the element is finite (cached like :meth:`definite_mask`)."""
        key = ("finite", self.versions())
        if key not in self._cache:
            trc = {"Q": 3, "R": 3, "x_ref": 2, "u_ref": 2, "N": 3, "q": 2, "r": 2}
            fin = torch.ones((), dtype=torch.bool, device=self.device)
            for k, d in trc.items():
                v = getattr(self, k)
                if v is not None:
                    fin = fin & _all_finite(v, d)
            self._evict(key[0])
            self._cache[key] = fin
        return self._cache[key]

    def _evict(self, kind: str) -> None:
        for k in [k for k in self._cache if k[0] == kind]:
            del self._cache[k]

    def versions(self) -> tuple:
        """In-place version counters of all fields (the key of the cached per-cost quantities)."""
        return _versions(self.Q, self.R, self.x_ref, self.u_ref, self.N, self.q, self.r)


def _expand_t(v: torch.Tensor | None, T: int, k: int) -> torch.Tensor | None:
    """Expand (a view) the time dim of a timed tensor with ``k`` trailing dims to ``T``."""
    if v is None:
        return None
    d = v.dim() - k - 1
    return v.expand(*v.shape[:d], T, *v.shape[d + 1:])


def _time_sum(v: torch.Tensor, T: int) -> torch.Tensor:
    """Sum a per-step quantity ``(*B, Tv)`` over ``T`` steps (``Tv == 1`` broadcasts over time)."""
    return v.sum(-1) * (T if v.shape[-1] == 1 else 1)


# --------------------------------------------------------------------------------------------------
# problem and solution
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class LQProblem:
    """A batched linear-quadratic (tracking) problem.

    Args:
        dynamics: :class:`LinearDynamics`.
        cost: :class:`QuadraticCost`.
        x0: initial state ``(*B, n)`` or ``(n,)``.
        horizon: ``T``; may be omitted when some field is time-varying (then it must agree).
    """

    dynamics: LinearDynamics
    cost: QuadraticCost
    x0: torch.Tensor
    horizon: int | None = None

    def __post_init__(self) -> None:
        own = "LQProblem"
        if not isinstance(self.dynamics, LinearDynamics):
            raise TypeError(f"{own}: field 'dynamics' must be a LinearDynamics, "
                            f"got {type(self.dynamics).__name__}")
        if not isinstance(self.cost, QuadraticCost):
            raise TypeError(f"{own}: field 'cost' must be a QuadraticCost, got {type(self.cost).__name__}")
        n, m = self.dynamics.n, self.dynamics.m
        if self.cost.n != n or self.cost.m != m:
            raise ValueError(f"{own}: cost is for n={self.cost.n}, m={self.cost.m} "
                             f"but dynamics has n={n}, m={m}")
        _check_tensor(self.x0, "x0", own)
        if self.x0.dim() < 1 or self.x0.shape[-1] != n:
            raise ValueError(f"{own}: field 'x0' must have shape (*B, {n}), got {tuple(self.x0.shape)}")
        _same_dtype_device(own, A=self.dynamics.A, Q=self.cost.Q, x0=self.x0)
        hs = {k: v for k, v in (("dynamics", self.dynamics.horizon), ("cost", self.cost.horizon))
              if v is not None}
        T = self.horizon
        if T is None:
            if not hs:
                raise ValueError(f"{own}: cannot infer the horizon (every field is time-invariant); "
                                 "pass horizon=T")
            T = max(hs.values())
        if not isinstance(T, int) or isinstance(T, bool) or T < 1:
            raise ValueError(f"{own}: field 'horizon' must be a positive int, got {T!r}")
        for k, h in hs.items():
            if h != T:
                raise ValueError(f"{own}: {k} has horizon {h} but the problem horizon is {T}")
        object.__setattr__(self, "horizon", T)
        try:
            self.batch_shape  # noqa: B018
        except RuntimeError as e:
            raise ValueError(f"{own}: batch dims of x0 {tuple(self.x0.shape)}, dynamics "
                             f"{tuple(self.dynamics.batch_shape)} and cost {tuple(self.cost.batch_shape)} "
                             "do not broadcast") from e

    @property
    def T(self) -> int:
        return self.horizon  # type: ignore[return-value]

    @property
    def n(self) -> int:
        return self.dynamics.n

    @property
    def m(self) -> int:
        return self.dynamics.m

    @property
    def batch_shape(self) -> torch.Size:
        return torch.broadcast_shapes(self.x0.shape[:-1], self.dynamics.batch_shape, self.cost.batch_shape)

    @property
    def dtype(self) -> torch.dtype:
        return self.x0.dtype

    @property
    def device(self) -> torch.device:
        return self.x0.device

    def input_status(self) -> torch.Tensor:
        """``(*B,)`` int64 :class:`Reason` codes from the inputs alone (non-finite data, bad definiteness)."""
        bs = self.batch_shape
        reason = torch.zeros(bs, dtype=torch.int64, device=self.device)
        fin = _all_finite(self.x0, 1).expand(bs)
        fin = fin & self.dynamics.finite_mask().expand(bs) & self.cost.finite_mask().expand(bs)
        if self.cost.Q.dim() > 3 or self.cost.R.dim() > 3:
            definite = self.cost.definite_mask().expand(bs)
            reason = torch.where(definite, reason, int(Reason.NOT_POSITIVE_DEFINITE))
        reason = torch.where(fin, reason, int(Reason.NONFINITE_INPUT))
        return reason


@dataclass(frozen=True, eq=False)
class LQSolution:
    """Solution of an LQ problem (or of iLQR at its last iterate).

    Attributes:
        x: ``(*B, T+1, n)`` optimal states.
        u: ``(*B, T, m)`` optimal controls.
        K: ``(*B, T, m, n)`` feedback gains, ``k``: ``(*B, T, m)`` feedforward: ``u_t = K_t x_t + k_t``
            (sign convention: *plus*; the seed's ``-K_t`` is ``K`` here).
        cost: ``(*B,)`` optimal total cost.
        status: per-element :class:`SolverStatus`.
        V, v: optional value function ``x_tᵀ V_t x_t + 2 v_tᵀ x_t + const`` (``(*B, T+1, n, n)``,
            ``(*B, T+1, n)``) when the solver computes it.
    """

    x: torch.Tensor
    u: torch.Tensor
    K: torch.Tensor
    k: torch.Tensor
    cost: torch.Tensor
    status: SolverStatus
    V: torch.Tensor | None = None
    v: torch.Tensor | None = None
