"""Manifolds with ⊞ / ⊟ / ⊕ and the manifold parts of the error-state linearization (seed 003).

Seed 003 (*"On-manifold MPC"*) encapsulates a manifold 𝓜 of dimension n by three operations
(§III, Eq. 1-3, Table I)::

    x ⊞ δ   : 𝓜 × Rⁿ -> 𝓜        (δ in the homeomorphic space, Eq. 1)
    y ⊟ x   : 𝓜 × 𝓜 -> Rⁿ
    x ⊕ δᵉ  : 𝓜 × Rˡ -> 𝓜        (exogenous perturbation of size l, possibly l ≠ n, Eq. 3)

obeying the axioms of Eq. 2: ``x ⊞ 0 = x``, ``x ⊞ (y ⊟ x) = y``, ``(x ⊞ δ) ⊟ x = δ`` (δ small).
The discrete system is ``x_{k+1} = x_k ⊕ Δt f(x_k, u_k)`` (Eq. 14) and the error system
``δx = x ⊟ x^d`` is linearised (Eq. 20-22) as ``F_x = G_x + Δt G_f ∂f/∂δx``, ``F_u = Δt G_f ∂f/∂δu``
with the *manifold parts* (Eq. 23), for ``v = Δt f(x^d, u^d)``::

    G_x(x^d, v) = ∂/∂δ [((x^d ⊞ δ) ⊕ v) ⊟ (x^d ⊕ v)] at δ = 0        shape (*, n, n)
    G_f(x^d, v) = ∂/∂δ [(x^d ⊕ (v + δ)) ⊟ (x^d ⊕ v)] at δ = 0         shape (*, n, l)

Primitive manifolds (points are plain tensors; Table I and the Appendix, Eq. 41-46):

==================  ============  ====  ====  =====================================================
manifold            point         n     l     G_x / G_f (closed form)
==================  ============  ====  ====  =====================================================
``Rn(n)``           ``(*, n)``    n     n     I / I                                      (Eq. 41)
``SO2()``           ``(*, 2, 2)`` 1     1     1 / 1                                      (Eq. 42)
``SO3()``           ``(*, 3, 3)`` 3     3     Exp(-v) / A(v)ᵀ = J_r(v)                   (Eq. 43-44)
``SE3()``           ``(*, 4, 4)`` 6     6     Ad_{Exp(-v)} / J_r(v)        (⊞ = x·Exp(δ), Eq. 5; δ = [ρ, ω])
``S2(r)``           ``(*, 3)``    2     3     -B(y)ᵀ Exp(v) ⌊x^d⌋² B(x^d) / r²,
                                              -B(y)ᵀ Exp(v) ⌊x^d⌋² A(v)ᵀ / r²,  y = x^d ⊕ v  (Eq. 45)
``Surface(F, ...)`` ``(*, 3)``    2     2     I₂ / I₂                                    (Eq. 46)
``ProductManifold`` ``ProductState``  Σn  Σl  block diagonal                              (Eq. 13)
==================  ============  ====  ====  =====================================================

Exactness of Table I.  Every closed form above is the *exact* derivative of Eq. 23 at δ = 0, not a
first-order approximation of it: for the Lie groups the conjugation ``Exp(-v) Exp(δ) Exp(v) =
Exp(Ad_{Exp(-v)} δ)`` is exact, and for S² the "≈" in Eq. 45a only drops terms of order ‖δ‖²,
which do not contribute to the derivative at δ = 0 (the ⊟ map has derivative ``B(y)ᵀ⌊y⌋/r²`` at
its base point, and ``⌊Exp(v) x⌋ = Exp(v)⌊x⌋Exp(v)ᵀ``).  Measured against ``torch.func.jacrev`` of
the defining expression (float64, 2000 random ``(x^d, v)`` with ``‖v‖ ≤ 3`` for each radius 0.5, 1,
2; ``tests/torchlie/test_manifolds.py::test_s2_table_one_difference``): max |closed − autograd| =
1.1e-15 for G_x and 8.9e-16 for G_f, i.e. roundoff.  What *is* first order is the linearised error
map of G_f: ``(x^d ⊕ (v + δ)) ⊟ (x^d ⊕ v) − G_f δ`` measured 3.1e-3, 3.2e-5, 3.1e-7 (max over 200
samples) at ‖δ‖ = 1e-1, 1e-2, 1e-3, i.e. O(‖δ‖²).  The G_x map is even exactly linear,
``((x^d ⊞ δ) ⊕ v) ⊟ (x^d ⊕ v) = B(y)ᵀ Exp(v) B(x^d) δ`` (Exp(v) is an isometry), remainder 3e-16.
Every ``G_x``/``G_f`` also takes ``exact=True``, which differentiates the defining expression of
Eq. 23 with ``torch.func.jacrev`` instead (one reverse sweep per output row, batch summed out),
for manifolds a user adds without a closed form and as an independent check.

S² basis.  ``B(x) = [b₁ b₂]`` (Eq. 9-10) is the image of ``[e₁ e₂]`` under the minimal rotation
taking ``e₃`` to ``x/r`` on the upper hemisphere (``x_z ≥ 0``) and ``-e₃`` to ``x/r`` on the lower one
(columns swapped there), so ``b₁ × b₂ = x/r`` everywhere and both branches are free of their
singularities.  B is discontinuous across the equator (no continuous tangent frame exists on S²);
the axioms and Eq. 23 never differentiate B, so this is harmless.  ``y ⊟ x`` at the antipode of x
(cut locus, rotation axis undefined) returns ``(π, 0)``, a rotation about b₁(x); so does any y with
``sin∠(x, y) < eps``, which it reaches to ``r·eps``.  Next to the antipode the axis is taken from its
two tangent components ``B(x)ᵀ(x × y)`` (the rounding error of ``x × y`` is as long as the vector
itself there and points anywhere, also along x), so x ⊞ (y ⊟ x) = y to roundoff up to the antipode.

Points off the manifold (a non-orthogonal "rotation", a sphere point of the wrong radius, a
surface point off ``z = F(x, y)``, non-finite entries) are never used silently: every public
method raises ``ValueError`` naming the argument, or projects onto the manifold when called with
``project=True``.  The tolerance depends on the dtype, ``sqrt(eps)`` (float64 1.5e-8,
float32 3.5e-4; see :func:`manifold_tolerance`).  The checks are Python-level branches on data,
so inside ``torch.func.vmap`` check the points beforehand (``M.check(x)``) and pass
``check=False`` (the explicit "already checked" switch, also for solvers' inner loops) or
``project=True``.

Product states (:class:`ProductState`).  A product point is an immutable mapping of component
names to tensors (``x.p``, ``x.v``, ``x.R``), registered as a ``torch.utils._pytree`` node, with
tensor-like batch methods (indexing, ``reshape``, ``expand``, ``unsqueeze``, ``to``, ``detach``,
``stack``/``cat``).  Why this and not the alternatives: a frozen dataclass needs one class per
product (the component names are chosen by the user at run time, so the classes would have to be
generated dynamically, and each registered as a pytree and made picklable); a tensordict is an
extra heavy dependency with mutable semantics and its own batch-size bookkeeping, and it reaches
``torch.func`` through its own functional API.  The small pytree-registered mapping gives attribute
access by name, works directly with ``torch.func.vmap/jacrev/grad`` and ``torch.utils._pytree``
utilities, keeps autograd untouched (its leaves are ordinary tensors) and costs no dependency.
Each leaf records how many trailing dims are the point itself (1 for vectors, 2 for matrices),
so batch operations know which dims are batch dims.
"""

from __future__ import annotations

import abc
import dataclasses
import importlib
import keyword
import math
import types
from collections.abc import Callable, Iterable, Mapping
from typing import Any, NamedTuple

import torch
from torch.utils import _pytree as pytree

from torchlie._batch import check_same_device, check_tensor, small_angle_eps

__all__ = [
    "Manifold",
    "Rn",
    "SO2",
    "SO3",
    "SE3",
    "S2",
    "Surface",
    "ProductManifold",
    "ProductState",
    "SurfaceFit",
    "fit_quadratic_surface",
    "quadratic_surface",
    "manifold_tolerance",
]


def _group(name: str):
    # The group modules are imported on first use so that this module imports cheaply.
    return importlib.import_module(f"torchlie.{name}")


def manifold_tolerance(dtype: torch.dtype) -> float:
    """Tolerance for "this point lies on the manifold": ``sqrt(eps(dtype))``.

    float64 1.5e-8, float32 3.5e-4, float16 3.1e-2, bfloat16 8.8e-2 — loose enough for points that
    went through many roundoff-affected operations, tight enough to catch a wrong input.
    """
    return math.sqrt(torch.finfo(dtype).eps)


def _batch_of(t: torch.Tensor, k: int) -> torch.Size:
    return t.shape[: t.dim() - k]


def _expand_to(t: torch.Tensor, k: int, batch: torch.Size) -> torch.Tensor:
    if _batch_of(t, k) == batch:
        return t
    return t.expand(*batch, *t.shape[t.dim() - k:])


def _any_true(mask: torch.Tensor, fn: str, name: str, what: str) -> bool:
    try:
        return bool(mask.any())
    except RuntimeError as e:  # data-dependent control flow inside torch.func.vmap
        raise ValueError(
            f"{fn}: cannot check that argument '{name}' lies on {what} inside torch.func.vmap; "
            "check the points before the vmap (manifold.check(x)) and pass check=False (or "
            "project=True) inside it"
        ) from e


def _first_index(mask: torch.Tensor) -> tuple[int, ...]:
    flat = int(torch.nonzero(mask.reshape(-1))[0, 0])
    return tuple(int(i) for i in torch.unravel_index(torch.tensor(flat), mask.shape)) if mask.dim() else ()


# ------------------------------------------------------------------------------------------------
# the contract
# ------------------------------------------------------------------------------------------------

class Manifold(abc.ABC):
    """A manifold 𝓜 of dimension ``dim`` (n) with exogenous-perturbation size ``ext_dim`` (l).

    Public methods (shapes with any leading batch dims ``*``, broadcast between arguments):

    * ``boxplus(x, delta)``: x ⊞ δ, δ ``(*, n)`` -> point.
    * ``boxminus(y, x)``: y ⊟ x -> ``(*, n)``.
    * ``oplus(x, delta_e)``: x ⊕ δᵉ, δᵉ ``(*, l)`` -> point.
    * ``G_x(x_d, v)`` ``(*, n, n)`` and ``G_f(x_d, v)`` ``(*, n, l)``: the manifold parts of the
      error-state linearization (Eq. 23), ``v = Δt f(x_d, u_d)`` ``(*, l)``; closed form from
      Table I, or ``exact=True`` for ``torch.func.jacrev`` of the defining expression.
    * ``linearize(x_d, v, dt, df_dx, df_du)`` -> ``(F_x, F_u)`` of Eq. 21-22.
    * ``check(x, name)`` / ``project(x)`` / ``random(*batch, generator=)`` / ``identity(*batch)``.

    Every method that takes points checks them (``ValueError`` naming the argument when a point is
    off the manifold, tolerance :func:`manifold_tolerance`) unless called with ``project=True``,
    which projects them first, or ``check=False``, with which the caller vouches for points it
    has already checked (inside ``torch.func.vmap``, or in a solver's inner loop).  Points are
    plain tensors for the primitive manifolds and :class:`ProductState` for
    :class:`ProductManifold`.  dtype and device follow the inputs.
    """

    # --- implemented by subclasses ----------------------------------------------------------------
    @property
    @abc.abstractmethod
    def dim(self) -> int:  # n
        """Implemented by each concrete manifold."""

    @property
    @abc.abstractmethod
    def ext_dim(self) -> int:  # l
        """Implemented by each concrete manifold."""

    @property
    @abc.abstractmethod
    def event_shape(self) -> tuple[int, ...]:
        """Implemented by each concrete manifold."""

    def _describe(self) -> str:
        return repr(self)

    def _membership_error(self, x: torch.Tensor) -> torch.Tensor:
        """Nonnegative violation per batch element, comparable with :func:`manifold_tolerance`.

        Primitive manifolds implement it; a product checks its components through their own."""
        raise NotImplementedError(f"{self._name} checks points component by component")

    def _project(self, x: torch.Tensor) -> torch.Tensor:
        """Nearest point on the manifold (primitive manifolds; a product projects its components)."""
        raise NotImplementedError(f"{self._name} projects points component by component")

    @abc.abstractmethod
    def _boxplus(self, x, delta):
        """Implemented by each concrete manifold."""

    @abc.abstractmethod
    def _boxminus(self, y, x):
        """Implemented by each concrete manifold."""

    @abc.abstractmethod
    def _oplus(self, x, delta_e):
        """Implemented by each concrete manifold."""

    @abc.abstractmethod
    def _G_x(self, x_d, v):
        """Implemented by each concrete manifold."""

    @abc.abstractmethod
    def _G_f(self, x_d, v):
        """Implemented by each concrete manifold."""

    @abc.abstractmethod
    def _random(self, batch, generator, dtype, device):
        """Implemented by each concrete manifold."""

    @abc.abstractmethod
    def _identity(self, batch, dtype, device):
        """Implemented by each concrete manifold."""

    # --- shared machinery -------------------------------------------------------------------------
    @property
    def _name(self) -> str:
        return type(self).__name__

    def _batch_shape(self, x) -> torch.Size:
        return _batch_of(x, len(self.event_shape))

    def _check_point(self, x, name: str, fn: str, project: bool, check: bool = True):
        check_tensor(x, self.event_shape, name, fn)
        if project:
            return self._project(x)
        if not check:
            return x
        err = self._membership_error(x.detach())
        tol = manifold_tolerance(x.dtype)
        bad = ~(err <= tol)  # NaN counts as bad
        if _any_true(bad, fn, name, self._describe()):
            idx = _first_index(bad)
            worst = float(torch.nan_to_num(err, nan=float("inf")).max())
            raise ValueError(
                f"{fn}: argument '{name}' is not on {self._describe()}: violation {worst:.3g} > "
                f"tolerance {tol:.2g} for {x.dtype} (first bad batch index {idx}, "
                f"{int(bad.sum())} of {bad.numel()} bad); pass project=True to project it onto the manifold"
            )
        return x

    def check(self, x, name: str = "x", *, project: bool = False):
        """``x`` if it lies on the manifold, its projection if ``project``, else ``ValueError``."""
        return self._check_point(x, name, f"{self._name}.check", project)

    def project(self, x):
        """Nearest point on the manifold (closed form per manifold)."""
        return self._check_point(x, "x", f"{self._name}.project", True)

    def _vec(self, t, n: int, name: str, fn: str) -> torch.Tensor:
        return check_tensor(t, (n,), name, fn)

    def _same_device(self, fn: str, x, **tensors: torch.Tensor) -> None:
        leaf = x._first_leaf() if isinstance(x, ProductState) else x
        check_same_device(fn, x=leaf, **tensors)

    def boxplus(self, x, delta: torch.Tensor, *, project: bool = False, check: bool = True):
        """x ⊞ δ with δ ``(*, n)`` in the homeomorphic space (Eq. 1, Table I)."""
        fn = f"{self._name}.boxplus"
        x = self._check_point(x, "x", fn, project, check)
        delta = self._vec(delta, self.dim, "delta", fn)
        self._same_device(fn, x, delta=delta)
        return self._boxplus(x, delta)

    def boxminus(self, y, x, *, project: bool = False, check: bool = True) -> torch.Tensor:
        """y ⊟ x ``(*, n)``: the perturbation taking x to y (Eq. 1, Table I)."""
        fn = f"{self._name}.boxminus"
        y = self._check_point(y, "y", fn, project, check)
        x = self._check_point(x, "x", fn, project, check)
        self._same_device(fn, x, y=y._first_leaf() if isinstance(y, ProductState) else y)
        return self._boxminus(y, x)

    def oplus(self, x, delta_e: torch.Tensor, *, project: bool = False, check: bool = True):
        """x ⊕ δᵉ with the exogenous perturbation δᵉ ``(*, l)`` (Eq. 3, Table I)."""
        fn = f"{self._name}.oplus"
        x = self._check_point(x, "x", fn, project, check)
        delta_e = self._vec(delta_e, self.ext_dim, "delta_e", fn)
        self._same_device(fn, x, delta_e=delta_e)
        return self._oplus(x, delta_e)

    def _prep_G(self, x_d, v, fn: str, project: bool, check: bool):
        x_d = self._check_point(x_d, "x_d", fn, project, check)
        v = self._vec(v, self.ext_dim, "v", fn)
        self._same_device(fn, x_d, v=v)
        return x_d, v

    def G_x(self, x_d, v: torch.Tensor, *, exact: bool = False, project: bool = False,
            check: bool = True) -> torch.Tensor:
        """∂/∂δ [((x_d ⊞ δ) ⊕ v) ⊟ (x_d ⊕ v)] at δ = 0, ``(*, n, n)`` (Eq. 23, Table I)."""
        fn = f"{self._name}.G_x"
        x_d, v = self._prep_G(x_d, v, fn, project, check)
        if exact:
            return self._jacobian_at_zero(x_d, v, "x")
        return self._G_x(x_d, v)

    def G_f(self, x_d, v: torch.Tensor, *, exact: bool = False, project: bool = False,
            check: bool = True) -> torch.Tensor:
        """∂/∂δ [(x_d ⊕ (v + δ)) ⊟ (x_d ⊕ v)] at δ = 0, ``(*, n, l)`` (Eq. 23, Table I)."""
        fn = f"{self._name}.G_f"
        x_d, v = self._prep_G(x_d, v, fn, project, check)
        if exact:
            return self._jacobian_at_zero(x_d, v, "f")
        return self._G_f(x_d, v)

    def _jacobian_at_zero(self, x_d, v: torch.Tensor, which: str) -> torch.Tensor:
        """Autograd of the defining expression of Eq. 23 (the ``exact=True`` path).

        The batch elements are independent, so the Jacobian of the batch-summed output has the
        per-element Jacobians as its blocks: one ``jacrev`` with n rows, whatever the batch size.
        """
        n = self.dim
        batch = torch.broadcast_shapes(self._batch_shape(x_d), v.shape[:-1])
        y = self._oplus(x_d, v)
        in_dim = n if which == "x" else self.ext_dim
        zero = torch.zeros(*batch, in_dim, dtype=v.dtype, device=v.device)
        if which == "x":
            def expr(d):
                return self._boxminus(self._oplus(self._boxplus(x_d, d), v), y)
        else:
            def expr(d):
                return self._boxminus(self._oplus(x_d, v + d), y)

        def summed(d):
            return expr(d).reshape(-1, n).sum(0)

        J = torch.func.jacrev(summed)(zero)  # (n, *batch, in_dim)
        return J.movedim(0, -2)

    def linearize(self, x_d, v: torch.Tensor, dt: float, df_dx: torch.Tensor, df_du: torch.Tensor, *,
                  exact: bool = False, project: bool = False, check: bool = True
                  ) -> tuple[torch.Tensor, torch.Tensor]:
        """Error-system matrices of Eq. 21-22: ``F_x = G_x + Δt G_f ∂f/∂δx``, ``F_u = Δt G_f ∂f/∂δu``.

        ``df_dx`` ``(*, l, n)`` and ``df_du`` ``(*, l, m)`` are the system-specific parts (e.g.
        Eq. 34 for the quadrotor); returns ``F_x`` ``(*, n, n)`` and ``F_u`` ``(*, n, m)``.
        """
        fn = f"{self._name}.linearize"
        n, l = self.dim, self.ext_dim
        if not (isinstance(df_dx, torch.Tensor) and df_dx.dim() >= 2 and tuple(df_dx.shape[-2:]) == (l, n)):
            raise ValueError(f"{fn}: argument 'df_dx' must have shape (*, {l}, {n}), "
                             f"got {tuple(getattr(df_dx, 'shape', ()))}")
        if not (isinstance(df_du, torch.Tensor) and df_du.dim() >= 2 and df_du.shape[-2] == l):
            raise ValueError(f"{fn}: argument 'df_du' must have shape (*, {l}, m), "
                             f"got {tuple(getattr(df_du, 'shape', ()))}")
        Gx = self.G_x(x_d, v, exact=exact, project=project, check=check)
        Gf = self.G_f(x_d, v, exact=exact, project=project, check=check)
        return Gx + dt * (Gf @ df_dx), dt * (Gf @ df_du)

    def random(self, *batch, generator: torch.Generator | None = None, dtype: torch.dtype | None = None,
               device=None):
        """Random points of batch shape ``batch`` (distribution per manifold, for tests and demos)."""
        if len(batch) == 1 and isinstance(batch[0], (tuple, list, torch.Size)):
            batch = tuple(batch[0])
        dtype = dtype or torch.get_default_dtype()
        if generator is not None and device is None:
            device = generator.device
        return self._random(tuple(int(b) for b in batch), generator, dtype, device)

    def identity(self, *batch, dtype: torch.dtype | None = None, device=None):
        """A canonical point (origin, identity, north pole, surface point above the origin)."""
        if len(batch) == 1 and isinstance(batch[0], (tuple, list, torch.Size)):
            batch = tuple(batch[0])
        return self._identity(tuple(int(b) for b in batch), dtype or torch.get_default_dtype(), device)


def _eye(n: int, batch, like: torch.Tensor) -> torch.Tensor:
    return torch.eye(n, dtype=like.dtype, device=like.device).expand(*batch, n, n)


def _rotation_error(R: torch.Tensor) -> torch.Tensor:
    n = R.shape[-1]
    eye = torch.eye(n, dtype=R.dtype, device=R.device)
    orth = (R.transpose(-1, -2) @ R - eye).abs().amax(dim=(-1, -2))
    det = torch.linalg.det(R) if n != 2 else R[..., 0, 0] * R[..., 1, 1] - R[..., 0, 1] * R[..., 1, 0]
    return torch.maximum(orth, (det - 1).abs())


def _project_rotation(M: torch.Tensor) -> torch.Tensor:
    """Nearest rotation to ``M`` (see :func:`torchlie.so3.project`, exact first derivative)."""
    return _group("so3").project(M)


# ------------------------------------------------------------------------------------------------
# primitive manifolds
# ------------------------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class Rn(Manifold):
    """Euclidean space Rⁿ: ⊞ = ⊕ = +, ⊟ = − (Eq. 4); G_x = G_f = Iₙ (Eq. 41)."""

    n: int

    def __post_init__(self):
        if isinstance(self.n, bool) or not isinstance(self.n, int) or self.n < 1:
            raise ValueError(f"Rn: argument 'n' must be a positive int, got {self.n!r}")

    @property
    def dim(self) -> int:
        return self.n

    @property
    def ext_dim(self) -> int:
        return self.n

    @property
    def event_shape(self) -> tuple[int, ...]:
        return (self.n,)

    def _describe(self) -> str:
        return f"R^{self.n} (finite entries)"

    def _membership_error(self, x):
        return torch.where(torch.isfinite(x).all(-1), 0.0, math.inf).to(x.dtype)

    def _project(self, x):
        return x

    def _boxplus(self, x, delta):
        return x + delta

    def _boxminus(self, y, x):
        return y - x

    def _oplus(self, x, delta_e):
        return x + delta_e

    def _G_x(self, x_d, v):
        return _eye(self.n, torch.broadcast_shapes(x_d.shape[:-1], v.shape[:-1]), v)

    def _G_f(self, x_d, v):
        return self._G_x(x_d, v)

    def _random(self, batch, generator, dtype, device):
        return torch.randn(*batch, self.n, generator=generator, dtype=dtype, device=device)

    def _identity(self, batch, dtype, device):
        return torch.zeros(*batch, self.n, dtype=dtype, device=device)


@dataclasses.dataclass(frozen=True)
class SO2(Manifold):
    """SO(2) as 2×2 rotation matrices, tangent θ ``(*, 1)``: ⊞ = ⊕ = x·Exp(δ), y ⊟ x = Log(x⁻¹y)
    (Eq. 5, 7); G_x = G_f = 1 (Eq. 42, exact because SO(2) is abelian)."""

    @property
    def dim(self) -> int:
        return 1

    @property
    def ext_dim(self) -> int:
        return 1

    @property
    def event_shape(self) -> tuple[int, ...]:
        return (2, 2)

    def _describe(self) -> str:
        return "SO(2) (orthogonal 2x2 matrices with det +1)"

    def _membership_error(self, x):
        return _rotation_error(x)

    def _project(self, x):
        # nearest rotation in Frobenius norm: angle atan2(c - b, a + d) of M = [[a, b], [c, d]]
        th = torch.atan2(x[..., 1, 0] - x[..., 0, 1], x[..., 0, 0] + x[..., 1, 1])
        return _group("so2").exp(th.unsqueeze(-1))

    def _boxplus(self, x, delta):
        return x @ _group("so2").exp(delta)

    def _boxminus(self, y, x):
        return _group("so2").log(x.transpose(-1, -2) @ y)

    def _oplus(self, x, delta_e):
        return x @ _group("so2").exp(delta_e)

    def _G_x(self, x_d, v):
        batch = torch.broadcast_shapes(x_d.shape[:-2], v.shape[:-1])
        return torch.ones(*batch, 1, 1, dtype=v.dtype, device=v.device)

    def _G_f(self, x_d, v):
        return self._G_x(x_d, v)

    def _random(self, batch, generator, dtype, device):
        return _group("so2").random(*batch, generator=generator, dtype=dtype, device=device)

    def _identity(self, batch, dtype, device):
        return torch.eye(2, dtype=dtype, device=device).expand(*batch, 2, 2).clone()


@dataclasses.dataclass(frozen=True)
class SO3(Manifold):
    """SO(3) as rotation matrices, tangent ω ``(*, 3)``: ⊞ = ⊕ = x·Exp(δ), y ⊟ x = Log(x⁻¹y) (Eq. 5,
    8); G_x = Exp(-v) (Eq. 43a) and G_f = A(v)ᵀ (Eq. 43b-44), where A(v) of Eq. 44 is the left
    Jacobian, so A(v)ᵀ = J_l(-v) = J_r(v)."""

    @property
    def dim(self) -> int:
        return 3

    @property
    def ext_dim(self) -> int:
        return 3

    @property
    def event_shape(self) -> tuple[int, ...]:
        return (3, 3)

    def _describe(self) -> str:
        return "SO(3) (orthogonal 3x3 matrices with det +1)"

    def _membership_error(self, x):
        return _rotation_error(x)

    def _project(self, x):
        return _project_rotation(x)

    def _boxplus(self, x, delta):
        return x @ _group("so3").exp(delta)

    def _boxminus(self, y, x):
        return _group("so3").log(x.transpose(-1, -2) @ y)

    def _oplus(self, x, delta_e):
        return x @ _group("so3").exp(delta_e)

    def _G_x(self, x_d, v):
        G = _group("so3").exp(-v)
        return G.expand(*torch.broadcast_shapes(x_d.shape[:-2], v.shape[:-1]), 3, 3)

    def _G_f(self, x_d, v):
        J = _group("so3").right_jacobian(v)
        return J.expand(*torch.broadcast_shapes(x_d.shape[:-2], v.shape[:-1]), 3, 3)

    def _random(self, batch, generator, dtype, device):
        return _group("so3").random(*batch, generator=generator, dtype=dtype, device=device)

    def _identity(self, batch, dtype, device):
        return torch.eye(3, dtype=dtype, device=device).expand(*batch, 3, 3).clone()


@dataclasses.dataclass(frozen=True)
class SE3(Manifold):
    """SE(3) as homogeneous 4×4 matrices, tangent ``[ρ, ω]`` ``(*, 6)`` (translation first):
    ⊞ = ⊕ = x·Exp(δ), y ⊟ x = Log(x⁻¹y) (Eq. 5); G_x = Ad_{Exp(-v)}, G_f = J_r(v) (the SE(3)
    counterparts of Eq. 43, both exact: ``Exp(-v) Exp(δ) Exp(v) = Exp(Ad_{Exp(-v)} δ)`` and
    ``Exp(v + δ) = Exp(v) Exp(J_r(v) δ + O(δ²))``)."""

    @property
    def dim(self) -> int:
        return 6

    @property
    def ext_dim(self) -> int:
        return 6

    @property
    def event_shape(self) -> tuple[int, ...]:
        return (4, 4)

    def _describe(self) -> str:
        return "SE(3) (homogeneous 4x4 matrices: rotation block in SO(3), last row [0, 0, 0, 1])"

    def _membership_error(self, x):
        last = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=x.dtype, device=x.device)
        row = (x[..., 3, :] - last).abs().amax(-1)
        return torch.maximum(_rotation_error(x[..., :3, :3]), row)

    def _project(self, x):
        R = _project_rotation(x[..., :3, :3])
        top = torch.cat((R, x[..., :3, 3:]), -1)
        last = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=x.dtype, device=x.device).expand(*x.shape[:-2], 1, 4)
        return torch.cat((top, last), -2)

    def _boxplus(self, x, delta):
        return x @ _group("se3").exp(delta)

    def _boxminus(self, y, x):
        se3 = _group("se3")
        return se3.log(se3.inverse(x) @ y)

    def _oplus(self, x, delta_e):
        return x @ _group("se3").exp(delta_e)

    def _G_x(self, x_d, v):
        se3 = _group("se3")
        G = se3.adjoint(se3.exp(-v))
        return G.expand(*torch.broadcast_shapes(x_d.shape[:-2], v.shape[:-1]), 6, 6)

    def _G_f(self, x_d, v):
        J = _group("se3").right_jacobian(v)
        return J.expand(*torch.broadcast_shapes(x_d.shape[:-2], v.shape[:-1]), 6, 6)

    def _random(self, batch, generator, dtype, device):
        return _group("se3").random(*batch, generator=generator, dtype=dtype, device=device)

    def _identity(self, batch, dtype, device):
        return torch.eye(4, dtype=dtype, device=device).expand(*batch, 4, 4).clone()


def _sphere_basis(u: torch.Tensor) -> torch.Tensor:
    """Orthonormal tangent basis ``B(u)`` ``(*, 3, 2)`` of the unit vector u, with ``b₁ × b₂ = u``.

    Upper hemisphere: columns of the minimal rotation taking e₃ to u; lower: of the one taking -e₃
    to u, swapped to keep the frame right-handed.  Each branch is evaluated on a harmless
    denominator where it is not taken (safe ``where``), so gradients stay finite.
    """
    a, b, c = u.unbind(-1)
    up = c >= 0
    one = torch.ones_like(c)
    du = torch.where(up, 1 + c, one)
    dl = torch.where(up, one, 1 - c)
    b1_up = torch.stack((1 - a * a / du, -a * b / du, -a), -1)
    b2_up = torch.stack((-a * b / du, 1 - b * b / du, -b), -1)
    p1 = torch.stack((1 - a * a / dl, -a * b / dl, a), -1)
    p2 = torch.stack((-a * b / dl, 1 - b * b / dl, b), -1)
    m = up.unsqueeze(-1)
    return torch.stack((torch.where(m, b1_up, p2), torch.where(m, b2_up, p1)), -1)


@dataclasses.dataclass(frozen=True)
class S2(Manifold):
    """Two-sphere S²_r = {x ∈ R³ : ‖x‖ = r} (Eq. 9-11, 45), points ``(*, 3)``, n = 2, l = 3.

    ``x ⊞ δ = Exp(B(x) δ) x`` (δ ∈ R², Eq. 10); ``y ⊟ x = B(x)ᵀ θ ⌊x⌋y/‖⌊x⌋y‖``,
    ``θ = atan2(‖⌊x⌋y‖, xᵀy)`` (Eq. 9); ``x ⊕ ω = Exp(ω) x`` (ω ∈ R³, Eq. 11).
    ``G_x = -B(y)ᵀ Exp(v)⌊x_d⌋² B(x_d)/r²``, ``G_f = -B(y)ᵀ Exp(v)⌊x_d⌋² A(v)ᵀ/r²``, y = x_d ⊕ v
    (Eq. 45a-b; exact at δ = 0 despite the "≈" of Eq. 45a, see the module docstring for the
    measured difference).  B is described in the module docstring.
    """

    r: float = 1.0

    def __post_init__(self):
        r = self.r
        if isinstance(r, bool) or not isinstance(r, (int, float)) or not math.isfinite(r) or r <= 0:
            raise ValueError(f"S2: argument 'r' must be a positive finite float, got {r!r}")
        object.__setattr__(self, "r", float(r))

    @property
    def dim(self) -> int:
        return 2

    @property
    def ext_dim(self) -> int:
        return 3

    @property
    def event_shape(self) -> tuple[int, ...]:
        return (3,)

    def _describe(self) -> str:
        return f"the sphere of radius {self.r:g} (relative radius error)"

    def _membership_error(self, x):
        return (torch.linalg.vector_norm(x, dim=-1) - self.r).abs() / self.r

    def _project(self, x):
        nrm = torch.linalg.vector_norm(x, dim=-1, keepdim=True)
        zero = ~(nrm > 0)
        if _any_true(zero, f"{self._name}.project", "x", "a sphere (nonzero vector needed)"):
            raise ValueError(f"{self._name}: argument 'x' contains a zero or non-finite vector "
                             f"(first at batch index {_first_index(zero.squeeze(-1))}); it cannot be "
                             "projected onto the sphere")
        return x * (self.r / nrm)

    def basis(self, x: torch.Tensor, *, project: bool = False) -> torch.Tensor:
        """The tangent basis B(x) ``(*, 3, 2)`` of Eq. 9 (orthonormal, ``b₁ × b₂ = x/r``)."""
        x = self._check_point(x, "x", "S2.basis", project)
        return _sphere_basis(x / torch.linalg.vector_norm(x, dim=-1, keepdim=True))

    def _B(self, x):
        return _sphere_basis(x / torch.linalg.vector_norm(x, dim=-1, keepdim=True))

    def _boxplus(self, x, delta):
        phi = (self._B(x) @ delta.unsqueeze(-1)).squeeze(-1)
        return (_group("so3").exp(phi) @ x.unsqueeze(-1)).squeeze(-1)

    def _boxminus(self, y, x):
        u = x / torch.linalg.vector_norm(x, dim=-1, keepdim=True)
        yh = y / torch.linalg.vector_norm(y, dim=-1, keepdim=True)
        u, yh = torch.broadcast_tensors(u, yh)
        # Rotation axis ⌊u⌋ŷ in the basis of T_u: p = B(u)ᵀ(u × ŷ), sin θ = ‖p‖.  Its length and
        # direction come from these two tangent components only.  Near the antipode u × ŷ is a few
        # ulps long and its rounding error has a component along u of the same size; normalising
        # the 3-vector and then projecting with B(u)ᵀ (as before) dropped that part and shortened
        # y ⊟ x (3.1374 instead of π, round trip off by 4e-3 at r = 1).
        p = (self._B(u).transpose(-1, -2) @ torch.linalg.cross(u, yh, dim=-1).unsqueeze(-1)).squeeze(-1)
        s2 = (p * p).sum(-1)
        c = (u * yh).sum(-1)
        series = (s2 < small_angle_eps(s2.dtype) ** 2) & (c > 0)
        # sin θ below eps: θ is π to within eps, so any axis lands on y to r·eps; the axis b₁(x),
        # i.e. (π, 0), is the deterministic choice (also at exactly -x, where none is defined)
        antipodal = (s2 < torch.finfo(s2.dtype).eps ** 2) & (c <= 0)
        one = torch.ones_like(s2)
        s = torch.sqrt(torch.where(series | antipodal, one, s2))
        k_big = torch.atan2(s, c) / s
        cs = torch.where(series, c, one)
        t2 = s2 / (cs * cs)
        # θ/sin θ = atan(t)/(t cos θ) with t = tan θ
        k_small = (1 - t2 * (1 / 3 - t2 * (1 / 5 - t2 / 7))) / cs
        d = torch.where(series, k_small, k_big).unsqueeze(-1) * p
        pi_e1 = torch.cat((torch.full_like(d[..., :1], math.pi), torch.zeros_like(d[..., 1:])), -1)
        return torch.where(antipodal.unsqueeze(-1), pi_e1, d)

    def _oplus(self, x, delta_e):
        return (_group("so3").exp(delta_e) @ x.unsqueeze(-1)).squeeze(-1)

    def _table(self, x_d, v, right):
        so3 = _group("so3")
        x_d, v = torch.broadcast_tensors(x_d, v)
        R = so3.exp(v)
        y = (R @ x_d.unsqueeze(-1)).squeeze(-1)
        X = so3.hat(x_d)
        return -(self._B(y).transpose(-1, -2) @ R @ X @ X @ right) / (self.r ** 2)

    def _G_x(self, x_d, v):
        x_d, v = torch.broadcast_tensors(x_d, v)
        return self._table(x_d, v, self._B(x_d))

    def _G_f(self, x_d, v):
        x_d, v = torch.broadcast_tensors(x_d, v)
        return self._table(x_d, v, _group("so3").right_jacobian(v))

    def _random(self, batch, generator, dtype, device):
        x = torch.randn(*batch, 3, generator=generator, dtype=dtype, device=device)
        x = torch.where(torch.linalg.vector_norm(x, dim=-1, keepdim=True) > 0, x, torch.ones_like(x))
        return x * (self.r / torch.linalg.vector_norm(x, dim=-1, keepdim=True))

    def _identity(self, batch, dtype, device):
        e3 = torch.tensor([0.0, 0.0, self.r], dtype=dtype, device=device)
        return e3.expand(*batch, 3).clone()


def _autograd_gradient(F: Callable, xy: torch.Tensor) -> torch.Tensor:
    def f(p):
        return F(p).sum()

    return torch.func.grad(f)(xy)


@dataclasses.dataclass(frozen=True)
class Surface(Manifold):
    """2-D height surface S = {x ∈ R³ : z = F(x, y)} (Eq. 12, 46), points ``(*, 3)``, n = l = 2.

    ``x ⊞ δ = x ⊕ δ = [E₁₂ᵀx + δ; F(E₁₂ᵀx + δ)]``, ``y ⊟ x = E₁₂ᵀ(y − x)`` (perturbations in the
    x-y plane); G_x = G_f = I₂ (Eq. 46).

    ``F(xy)`` maps ``(*, 2)`` to ``(*,)``; ``grad_F(xy)`` -> ``(*, 2)`` = [F'_x, F'_y] and
    ``hess_F(xy)`` -> ``(*, 2, 2)`` are the derivatives the system-specific parts need (Eq. 37-39);
    when omitted they are computed from F by autograd.  :func:`quadratic_surface` builds all three
    from the coefficients of Eq. 40.  The callables must be torch functions of their argument
    (they are differentiated through by ``exact=True`` and by autograd users); tensors they close
    over do not move with ``.to()`` of the points.
    """

    F: Callable[[torch.Tensor], torch.Tensor] = dataclasses.field(repr=False)
    grad_F: Callable[[torch.Tensor], torch.Tensor] | None = dataclasses.field(default=None, repr=False)
    hess_F: Callable[[torch.Tensor], torch.Tensor] | None = dataclasses.field(default=None, repr=False)
    name: str = "F"

    def __post_init__(self):
        for field in ("F", "grad_F", "hess_F"):
            f = getattr(self, field)
            if (field == "F" or f is not None) and not callable(f):
                raise TypeError(f"Surface: argument '{field}' must be callable, got {type(f).__name__}")

    @property
    def dim(self) -> int:
        return 2

    @property
    def ext_dim(self) -> int:
        return 2

    @property
    def event_shape(self) -> tuple[int, ...]:
        return (3,)

    def _describe(self) -> str:
        return f"the surface z = {self.name}(x, y) (|z - F| / (1 + |z|))"

    def height(self, xy: torch.Tensor) -> torch.Tensor:
        """F(x, y) for ``xy`` ``(*, 2)``: shape ``(*,)`` (broadcast with F's own batch, if any)."""
        z = self.F(xy)
        if not isinstance(z, torch.Tensor):
            raise TypeError(f"Surface: F must return a tensor, got {type(z).__name__}")
        batch = xy.shape[:-1]
        if z.dim() == len(batch) + 1 and z.shape[-1] == 1:
            z = z.squeeze(-1)
        try:
            out = torch.broadcast_shapes(z.shape, batch)
        except RuntimeError:
            out = None
        if out is None or len(out) != max(len(batch), z.dim()):
            raise ValueError(f"Surface: F(xy) must return shape {tuple(batch)} for xy of shape "
                             f"{tuple(xy.shape)}, got {tuple(z.shape)}")
        return z.expand(out)

    def _grad_xy(self, xy: torch.Tensor) -> torch.Tensor:
        g = self.grad_F(xy) if self.grad_F is not None else _autograd_gradient(self.height, xy)
        if not isinstance(g, torch.Tensor) or g.shape[-1:] != (2,):
            raise ValueError("Surface: grad_F(xy) must return shape (*, 2), "
                             f"got {tuple(getattr(g, 'shape', ()))}")
        return g.expand(*torch.broadcast_shapes(g.shape[:-1], xy.shape[:-1]), 2)

    def gradient(self, x: torch.Tensor) -> torch.Tensor:
        """g = [F'_x, F'_y] ``(*, 2)`` at ``x`` ``(*, 3)`` or ``(*, 2)`` (only x, y are used; Eq. 37b)."""
        return self._grad_xy(x[..., :2])

    def hessian(self, x: torch.Tensor) -> torch.Tensor:
        """∇²F ``(*, 2, 2)`` = [[F''_xx, F''_xy], [F''_yx, F''_yy]] at ``x`` (Eq. 39d)."""
        xy = x[..., :2]
        if self.hess_F is not None:
            H = self.hess_F(xy)
        else:
            flat = xy.reshape(-1, 2)
            H = torch.func.vmap(torch.func.jacrev(self._grad_xy))(flat).reshape(*xy.shape[:-1], 2, 2)
        if not isinstance(H, torch.Tensor) or H.shape[-2:] != (2, 2):
            raise ValueError("Surface: hess_F(xy) must return shape (*, 2, 2), "
                             f"got {tuple(getattr(H, 'shape', ()))}")
        return H.expand(*torch.broadcast_shapes(H.shape[:-2], xy.shape[:-1]), 2, 2)

    def normal(self, x: torch.Tensor) -> torch.Tensor:
        """Unit upward normal ``(−F'_x, −F'_y, 1)/√(1 + gᵀg)`` ``(*, 3)`` (the z_b axis of Eq. 35)."""
        g = self.gradient(x)
        n = torch.cat((-g, torch.ones_like(g[..., :1])), -1)
        return n / torch.linalg.vector_norm(n, dim=-1, keepdim=True)

    def _membership_error(self, x):
        z = x[..., 2]
        return (z - self.height(x[..., :2])).abs() / (1 + z.abs())

    def _project(self, x):
        return self._lift(x[..., :2])

    def _lift(self, xy):
        z = self.height(xy)
        return torch.cat((xy.expand(*z.shape, 2), z.unsqueeze(-1)), -1)

    def _boxplus(self, x, delta):
        return self._lift(x[..., :2] + delta)

    def _boxminus(self, y, x):
        return y[..., :2] - x[..., :2]

    def _oplus(self, x, delta_e):
        return self._lift(x[..., :2] + delta_e)

    def _G_x(self, x_d, v):
        return _eye(2, torch.broadcast_shapes(x_d.shape[:-1], v.shape[:-1]), v)

    def _G_f(self, x_d, v):
        return self._G_x(x_d, v)

    def _random(self, batch, generator, dtype, device):
        return self._lift(torch.randn(*batch, 2, generator=generator, dtype=dtype, device=device))

    def _identity(self, batch, dtype, device):
        return self._lift(torch.zeros(*batch, 2, dtype=dtype, device=device))


# ------------------------------------------------------------------------------------------------
# quadratic surface patch (Eq. 40)
# ------------------------------------------------------------------------------------------------

def quadratic_surface(gamma: torch.Tensor, name: str = "quadratic") -> Surface:
    """Surface of Eq. 40, ``F = γ₁x² + γ₂xy + γ₃y² + γ₄x + γ₅y + γ₆``, with analytic ∇F and ∇²F.

    ``gamma`` ``(*G, 6)``; ``*G`` broadcasts with the batch of the points the surface is used on
    by torch's (right-aligned) rules, so one patch per batch element (e.g. one per reference point
    as in seed 003 §VII-B-4) needs ``*G`` equal to the points' batch shape; for fitted patches
    ``(P, 6)`` evaluated on points ``(P, N, 2)`` pass ``gamma.unsqueeze(-2)``.
    """
    check_tensor(gamma, (6,), "gamma", "quadratic_surface")
    g1, g2, g3, g4, g5, g6 = gamma.unbind(-1)

    def F(xy):
        x, y = xy[..., 0], xy[..., 1]
        return g1 * x * x + g2 * x * y + g3 * y * y + g4 * x + g5 * y + g6

    def grad_F(xy):
        x, y = xy[..., 0], xy[..., 1]
        return torch.stack((2 * g1 * x + g2 * y + g4, g2 * x + 2 * g3 * y + g5), -1)

    def hess_F(xy):
        H = torch.stack((2 * g1, g2, g2, 2 * g3), -1).reshape(*gamma.shape[:-1], 2, 2)
        return H.expand(*torch.broadcast_shapes(gamma.shape[:-1], xy.shape[:-1]), 2, 2)

    return Surface(F, grad_F, hess_F, name=name)


class SurfaceFit(NamedTuple):
    """Result of :func:`fit_quadratic_surface` (per batch element)."""

    coefficients: torch.Tensor  # (*, 6) γ of Eq. 40 in the points' own coordinates
    rms: torch.Tensor  # (*,) weighted RMS of the height residuals
    well_posed: torch.Tensor  # (*,) bool: the design matrix has full rank 6 (to dtype tolerance)

    def surface(self, name: str = "quadratic") -> Surface:
        """The fitted :class:`Surface` (see :func:`quadratic_surface`)."""
        return quadratic_surface(self.coefficients, name=name)


def fit_quadratic_surface(points: torch.Tensor, weights: torch.Tensor | None = None) -> SurfaceFit:
    """Least-squares fit of the quadratic patch of Eq. 40 to 3-D points, batched.

    ``points`` ``(*, N, 3)`` (N ≥ 6), optional ``weights`` ``(*, N)`` ≥ 0.  Minimizes
    ``Σ w_i (z_i − F(x_i, y_i))²``.  For conditioning the x-y coordinates are centred and scaled
    per batch element, the problem is solved by SVD there and the coefficients are mapped back
    exactly.  A degenerate layout (all points on a line, fewer than 6 with positive weight) gives
    ``well_posed = False`` and the minimum-norm solution for that element only; the rest of the
    batch is unaffected.  Differentiable w.r.t. points and weights for well-posed elements.
    """
    fn = "fit_quadratic_surface"
    check_tensor(points, (3,), "points", fn)
    if points.dim() < 2:
        raise ValueError(f"{fn}: argument 'points' must have shape (*, N, 3), got {tuple(points.shape)}")
    N = points.shape[-2]
    if N < 6:
        raise ValueError(f"{fn}: argument 'points' needs N ≥ 6 points to fit 6 coefficients, got {N}")
    if not bool(torch.isfinite(points).all()):
        raise ValueError(f"{fn}: argument 'points' contains non-finite entries")
    if weights is None:
        weights = torch.ones(points.shape[:-1], dtype=points.dtype, device=points.device)
    else:
        check_tensor(weights, (N,), "weights", fn)
        check_same_device(fn, points=points, weights=weights)
        if not bool(((weights >= 0) & torch.isfinite(weights)).all()):
            raise ValueError(f"{fn}: argument 'weights' must be finite and nonnegative")
    batch = torch.broadcast_shapes(points.shape[:-2], weights.shape[:-1])
    points = points.expand(*batch, N, 3)
    w = weights.expand(*batch, N)
    wsum = w.sum(-1, keepdim=True)
    wn = w / torch.where(wsum > 0, wsum, torch.ones_like(wsum))
    xy, z = points[..., :2], points[..., 2]
    center = (wn.unsqueeze(-1) * xy).sum(-2)  # (*, 2)
    d = xy - center.unsqueeze(-2)
    scale2 = (wn * (d * d).sum(-1)).sum(-1)
    s = torch.sqrt(torch.where(scale2 > 0, scale2, torch.ones_like(scale2)))  # (*,)
    X, Y = (d / s[..., None, None]).unbind(-1)
    A = torch.stack((X * X, X * Y, Y * Y, X, Y, torch.ones_like(X)), -1)  # (*, N, 6)
    sw = torch.sqrt(w)
    Aw, zw = A * sw.unsqueeze(-1), z * sw
    U, S, Vh = torch.linalg.svd(Aw, full_matrices=False)
    cut = S[..., :1] * (max(N, 6) * torch.finfo(points.dtype).eps * 10)
    keep = S > cut
    Sinv = torch.where(keep, 1 / torch.where(keep, S, torch.ones_like(S)), torch.zeros_like(S))
    g = (Vh.transpose(-1, -2) @ (Sinv.unsqueeze(-1) * (U.transpose(-1, -2) @ zw.unsqueeze(-1)))).squeeze(-1)
    well_posed = keep.all(-1)
    res = z - (A @ g.unsqueeze(-1)).squeeze(-1)
    rms = torch.sqrt((wn * res * res).sum(-1))
    # back to the original coordinates: X = (x - cx)/s, Y = (y - cy)/s
    a1, a2, a3, a4, a5, a6 = g.unbind(-1)
    cx, cy = center.unbind(-1)
    s2 = s * s
    gamma = torch.stack((
        a1 / s2,
        a2 / s2,
        a3 / s2,
        (-2 * a1 * cx - a2 * cy) / s2 + a4 / s,
        (-a2 * cx - 2 * a3 * cy) / s2 + a5 / s,
        (a1 * cx * cx + a2 * cx * cy + a3 * cy * cy) / s2 - (a4 * cx + a5 * cy) / s + a6,
    ), -1)
    return SurfaceFit(gamma, rms, well_posed)


# ------------------------------------------------------------------------------------------------
# product states
# ------------------------------------------------------------------------------------------------

_Leaf = Any  # torch.Tensor or ProductState (or, inside torch.func internals, any pytree leaf)


class ProductState:
    """A point of a :class:`ProductManifold`: named components, batched like a tensor.

    ``x.R`` / ``x["R"]`` give a component; ``x[0]``, ``x[:, 1]``, ``x[mask]`` index the *batch*
    dims of every component; ``reshape``, ``expand``, ``unsqueeze``, ``to``, ``detach``, ``clone``,
    ``requires_grad_`` act on all components; ``replace(R=...)`` returns a copy with some
    components swapped; ``ProductState.stack``/``cat`` join states along a batch dim.
    Immutable, and registered as a pytree node (see the module docstring for why), so
    ``torch.func.vmap``/``jacrev``/``grad`` and ``torch.utils._pytree.tree_map`` accept it.

    Built by :meth:`ProductManifold.state` (which checks the points); the constructor takes the
    components and, per tensor component, the number of trailing dims that are the point itself
    (``event_ndims``), and broadcasts the components' batch dims to one batch shape.
    """

    __slots__ = ("_data", "_event_ndims")

    def __init__(self, components: Mapping[str, _Leaf], event_ndims: Mapping[str, int]):
        if not isinstance(components, Mapping) or not components:
            raise TypeError("ProductState: argument 'components' must be a non-empty mapping name -> tensor")
        data: dict[str, _Leaf] = {}
        nd: dict[str, int] = {}
        for name, t in components.items():
            _check_component_name(name, "ProductState")
            if isinstance(t, ProductState):
                data[name] = t
                continue
            if not isinstance(t, torch.Tensor):
                raise TypeError(f"ProductState: component '{name}' must be a tensor or ProductState, "
                                f"got {type(t).__name__}")
            k = event_ndims.get(name) if isinstance(event_ndims, Mapping) else None
            if not isinstance(k, int) or k < 0 or t.dim() < k:
                raise ValueError(f"ProductState: 'event_ndims' must give the point dims (≤ {t.dim()}) "
                                 f"of component '{name}', got {k!r}")
            data[name], nd[name] = t, k
        shapes = [_leaf_batch(t, nd.get(n)) for n, t in data.items()]
        try:
            batch = torch.broadcast_shapes(*shapes)
        except RuntimeError as e:
            raise ValueError("ProductState: the components' batch shapes do not broadcast: "
                             + ", ".join(f"'{n}' {tuple(s)}" for n, s in zip(data, shapes))) from e
        data = {n: _leaf_expand(t, nd.get(n), batch) for n, t in data.items()}
        object.__setattr__(self, "_data", data)
        object.__setattr__(self, "_event_ndims", nd)

    @classmethod
    def _make(cls, data: Mapping[str, _Leaf], event_ndims: Mapping[str, int]) -> ProductState:
        obj = object.__new__(cls)
        object.__setattr__(obj, "_data", dict(data))
        object.__setattr__(obj, "_event_ndims", dict(event_ndims))
        return obj

    def __reduce__(self):
        return (ProductState._make, (self._data, self._event_ndims))

    # --- access -----------------------------------------------------------------------------------
    def __getattr__(self, name: str):
        if name.startswith("_"):
            raise AttributeError(name)
        try:
            return self._data[name]
        except KeyError:
            raise AttributeError(f"ProductState has no component {name!r}; components: "
                                 f"{list(self._data)}") from None

    def __setattr__(self, name, value):
        raise AttributeError("ProductState is immutable; use x.replace(name=value)")

    def keys(self):
        return self._data.keys()

    def values(self):
        return self._data.values()

    def items(self):
        return self._data.items()

    def __contains__(self, name) -> bool:
        return name in self._data

    def to_dict(self) -> dict[str, _Leaf]:
        return dict(self._data)

    @property
    def event_ndims(self) -> Mapping[str, int]:
        return types.MappingProxyType(self._event_ndims)

    def replace(self, **components: _Leaf) -> ProductState:
        """Copy with some components replaced (batch shapes broadcast again)."""
        unknown = set(components) - set(self._data)
        if unknown:
            raise ValueError(f"ProductState.replace: unknown components {sorted(unknown)}; "
                             f"components: {list(self._data)}")
        return ProductState({**self._data, **components}, self._event_ndims)

    # --- tensor-like properties -------------------------------------------------------------------
    def _first_leaf(self):
        t = next(iter(self._data.values()))
        return t._first_leaf() if isinstance(t, ProductState) else t

    @property
    def batch_shape(self) -> torch.Size:
        name, t = next(iter(self._data.items()))
        return _leaf_batch(t, self._event_ndims.get(name))

    @property
    def shape(self) -> torch.Size:
        """Alias of ``batch_shape`` (the shape that indexing and reshape act on)."""
        return self.batch_shape

    @property
    def ndim(self) -> int:
        return len(self.batch_shape)

    @property
    def dtype(self) -> torch.dtype:
        return self._first_leaf().dtype

    @property
    def device(self) -> torch.device:
        return self._first_leaf().device

    @property
    def requires_grad(self) -> bool:
        return any(t.requires_grad for t in pytree.tree_leaves(self) if isinstance(t, torch.Tensor))

    def __len__(self) -> int:
        b = self.batch_shape
        if not b:
            raise TypeError("len() of a ProductState with no batch dims")
        return b[0]

    # --- batch operations -------------------------------------------------------------------------
    def _map(self, f: Callable[[torch.Tensor, int], torch.Tensor]) -> ProductState:
        out = {}
        for name, t in self._data.items():
            out[name] = t._map(f) if isinstance(t, ProductState) else f(t, self._event_ndims[name])
        return ProductState._make(out, self._event_ndims)

    def __getitem__(self, key):
        if isinstance(key, str):
            try:
                return self._data[key]
            except KeyError:
                raise KeyError(f"ProductState has no component {key!r}; "
                               f"components: {list(self._data)}") from None
        idx = key if isinstance(key, tuple) else (key,)
        nb = self.ndim
        if any(i is Ellipsis for i in idx):
            if sum(i is Ellipsis for i in idx) > 1:
                raise IndexError("ProductState: an index can only have a single ellipsis ('...')")
            used = sum(_index_consumes(i) for i in idx if i is not Ellipsis)
            pos = next(j for j, i in enumerate(idx) if i is Ellipsis)
            idx = idx[:pos] + (slice(None),) * max(nb - used, 0) + idx[pos + 1:]
        if sum(_index_consumes(i) for i in idx) > nb:
            raise IndexError(f"ProductState: too many indices for batch shape {tuple(self.batch_shape)} "
                             "(indexing acts on the batch dims only; use x.name for a component)")
        return self._map(lambda t, k: t[idx])

    def reshape(self, *shape) -> ProductState:
        """Reshape the batch dims (the point dims are kept)."""
        shape = _shape_arg(shape)
        return self._map(lambda t, k: t.reshape(*shape, *t.shape[t.dim() - k:]))

    def view(self, *shape) -> ProductState:
        shape = _shape_arg(shape)
        return self._map(lambda t, k: t.view(*shape, *t.shape[t.dim() - k:]))

    def flatten(self) -> ProductState:
        """All batch dims flattened into one."""
        return self.reshape(-1)

    def expand(self, *shape) -> ProductState:
        shape = _shape_arg(shape)
        return self._map(lambda t, k: t.expand(*shape, *t.shape[t.dim() - k:]))

    def unsqueeze(self, dim: int) -> ProductState:
        """Insert a batch dim at ``dim`` (negative counts from the end of the batch dims)."""
        nb = self.ndim
        d = dim if dim >= 0 else dim + nb + 1
        if not 0 <= d <= nb:
            raise IndexError(f"ProductState.unsqueeze: dim {dim} out of range for {nb} batch dims")
        return self._map(lambda t, k: t.unsqueeze(d))

    def squeeze(self, dim: int) -> ProductState:
        nb = self.ndim
        d = dim if dim >= 0 else dim + nb
        if not 0 <= d < nb:
            raise IndexError(f"ProductState.squeeze: dim {dim} out of range for {nb} batch dims")
        return self._map(lambda t, k: t.squeeze(d))

    def to(self, *args, **kwargs) -> ProductState:
        """``Tensor.to`` on every component (device and/or dtype)."""
        return self._map(lambda t, k: t.to(*args, **kwargs))

    def detach(self) -> ProductState:
        return self._map(lambda t, k: t.detach())

    def clone(self) -> ProductState:
        return self._map(lambda t, k: t.clone())

    def contiguous(self) -> ProductState:
        return self._map(lambda t, k: t.contiguous())

    def requires_grad_(self, requires_grad: bool = True) -> ProductState:
        for t in pytree.tree_leaves(self):
            t.requires_grad_(requires_grad)
        return self

    @staticmethod
    def stack(states: Iterable[ProductState], dim: int = 0) -> ProductState:
        """Stack states of equal batch shape along a new batch dim."""
        states = list(states)
        if not states:
            raise ValueError("ProductState.stack: argument 'states' is empty")
        nb = states[0].ndim
        d = dim if dim >= 0 else dim + nb + 1
        return _zip_map(states, lambda ts, k: torch.stack(ts, d))

    @staticmethod
    def cat(states: Iterable[ProductState], dim: int = 0) -> ProductState:
        """Concatenate states along an existing batch dim."""
        states = list(states)
        if not states:
            raise ValueError("ProductState.cat: argument 'states' is empty")
        nb = states[0].ndim
        d = dim if dim >= 0 else dim + nb
        return _zip_map(states, lambda ts, k: torch.cat(ts, d))

    def __repr__(self) -> str:
        parts = []
        for name, t in self._data.items():
            if isinstance(t, ProductState):
                parts.append(f"{name}={t!r}")
            elif isinstance(t, torch.Tensor):
                parts.append(f"{name}: {tuple(t.shape)} {str(t.dtype).replace('torch.', '')}")
            else:
                parts.append(f"{name}: {type(t).__name__}")
        try:
            b = f", batch_shape={tuple(self.batch_shape)}"
        except Exception:  # leaves that are not tensors (inside torch.func internals)
            b = ""
        return f"ProductState({', '.join(parts)}{b})"


def _leaf_batch(t, k) -> torch.Size:
    if isinstance(t, ProductState):
        return t.batch_shape
    return t.shape[: t.dim() - k]


def _leaf_expand(t, k, batch):
    if isinstance(t, ProductState):
        return t if t.batch_shape == batch else t.expand(*batch)
    return _expand_to(t, k, batch)


def _shape_arg(shape) -> tuple[int, ...]:
    if len(shape) == 1 and isinstance(shape[0], (tuple, list, torch.Size)):
        return tuple(shape[0])
    return tuple(shape)


def _index_consumes(i) -> int:
    if i is None:
        return 0
    if isinstance(i, torch.Tensor) and i.dtype == torch.bool:
        return i.dim()
    return 1


def _zip_map(states: list[ProductState], f) -> ProductState:
    first = states[0]
    for s in states[1:]:
        if not isinstance(s, ProductState) or list(s.keys()) != list(first.keys()):
            raise ValueError("ProductState: all states must have the same components in the same order")
    out = {}
    for name, t in first.items():
        comps = [s[name] for s in states]
        out[name] = _zip_map(comps, f) if isinstance(t, ProductState) else f(comps, first._event_ndims[name])
    return ProductState._make(out, first._event_ndims)


_RESERVED = {n for n in dir(ProductState) if not n.startswith("_")} | {"project"}


def _check_component_name(name, where: str) -> None:
    ok = isinstance(name, str) and name.isidentifier() and not keyword.iskeyword(name)
    if not ok or name.startswith("_"):
        raise ValueError(f"{where}: component name {name!r} must be a Python identifier not starting "
                         "with '_'")
    if name in _RESERVED:
        raise ValueError(f"{where}: component name {name!r} is reserved (a ProductState method or "
                         "attribute has that name)")


def _ps_flatten(s: ProductState):
    return list(s._data.values()), (tuple(s._data.keys()), tuple(sorted(s._event_ndims.items())))


def _ps_unflatten(values, context) -> ProductState:
    names, nd = context
    return ProductState._make(dict(zip(names, values)), dict(nd))


def _ps_flatten_with_keys(s: ProductState):
    return [(pytree.GetAttrKey(n), t) for n, t in s._data.items()], _ps_flatten(s)[1]


pytree.register_pytree_node(
    ProductState,
    _ps_flatten,
    _ps_unflatten,
    serialized_type_name="torchlie.manifolds.ProductState",
    flatten_with_keys_fn=_ps_flatten_with_keys,
)


# ------------------------------------------------------------------------------------------------
# product manifold
# ------------------------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True, eq=True)
class ProductManifold(Manifold):
    """Cartesian product 𝓜₁ × … × 𝓜ₖ with named components (Eq. 13).

    ``ProductManifold({"p": Rn(3), "v": Rn(3), "R": SO3()})`` is the quadrotor state space of
    Eq. 33 (n = 9, l = 9); ``ProductManifold({"s": Surface(F, gF, hF), "R": SO2()})`` the ground
    vehicle of Eq. 36 (n = 3, l = 3).  Points are :class:`ProductState`; tangent vectors δ ``(*, n)``
    and exogenous perturbations δᵉ ``(*, l)`` are the components' vectors concatenated in
    component order (``slices``/``ext_slices`` give the ranges); ``G_x``/``G_f`` are block
    diagonal.  Components may themselves be products.
    """

    components: Mapping[str, Manifold]

    def __post_init__(self):
        comps = self.components
        if not isinstance(comps, Mapping) or not comps:
            raise TypeError("ProductManifold: argument 'components' must be a non-empty mapping "
                            "name -> Manifold")
        for name, m in comps.items():
            _check_component_name(name, "ProductManifold")
            if not isinstance(m, Manifold):
                raise TypeError(f"ProductManifold: component '{name}' must be a Manifold, "
                                f"got {type(m).__name__}")
        object.__setattr__(self, "components", types.MappingProxyType(dict(comps)))

    def __hash__(self):
        return hash(tuple(self.components.items()))

    def __eq__(self, other):
        return isinstance(other, ProductManifold) and tuple(self.components.items()) == tuple(
            other.components.items())

    def __repr__(self):
        return "ProductManifold(" + ", ".join(f"{n}={m!r}" for n, m in self.components.items()) + ")"

    @property
    def dim(self) -> int:
        return sum(m.dim for m in self.components.values())

    @property
    def ext_dim(self) -> int:
        return sum(m.ext_dim for m in self.components.values())

    @property
    def event_shape(self) -> tuple[int, ...]:
        raise AttributeError("a ProductManifold point is a ProductState, not one tensor")

    def _ranges(self, attr: str) -> dict[str, slice]:
        out, i = {}, 0
        for name, m in self.components.items():
            d = getattr(m, attr)
            out[name] = slice(i, i + d)
            i += d
        return out

    @property
    def slices(self) -> Mapping[str, slice]:
        """Range of each component in a tangent vector δ ``(*, n)``."""
        return types.MappingProxyType(self._ranges("dim"))

    @property
    def ext_slices(self) -> Mapping[str, slice]:
        """Range of each component in an exogenous perturbation δᵉ ``(*, l)``."""
        return types.MappingProxyType(self._ranges("ext_dim"))

    def _event_ndims(self) -> dict[str, int]:
        return {n: len(m.event_shape) for n, m in self.components.items()
                if not isinstance(m, ProductManifold)}

    def _batch_shape(self, x) -> torch.Size:
        return x.batch_shape

    def _describe(self) -> str:
        return repr(self)

    def _check_point(self, x, name: str, fn: str, project: bool, check: bool = True):
        if not isinstance(x, ProductState):
            raise TypeError(f"{fn}: argument '{name}' must be a ProductState with components "
                            f"{list(self.components)} (build one with manifold.state(...)), "
                            f"got {type(x).__name__}")
        if list(x.keys()) != list(self.components):
            raise ValueError(f"{fn}: argument '{name}' has components {list(x.keys())}, expected "
                             f"{list(self.components)}")
        out = {}
        dev = None
        for cname, m in self.components.items():
            t = m._check_point(x[cname], f"{name}.{cname}", fn, project, check)
            leaf = t._first_leaf() if isinstance(t, ProductState) else t
            if dev is None:
                dev, dt, first = leaf.device, leaf.dtype, cname
            elif leaf.device != dev or leaf.dtype != dt:
                raise ValueError(f"{fn}: components '{name}.{first}' and '{name}.{cname}' differ in "
                                 f"device or dtype ({dev}, {dt} vs {leaf.device}, {leaf.dtype})")
            out[cname] = t
        return ProductState(out, self._event_ndims())

    def state(self, *, project: bool = False, **components) -> ProductState:
        """Build a checked :class:`ProductState`, e.g. ``M.state(p=p, v=v, R=R)``."""
        missing = [n for n in self.components if n not in components]
        extra = [n for n in components if n not in self.components]
        if missing or extra:
            raise ValueError(f"ProductManifold.state: expected components {list(self.components)}; "
                             f"missing {missing}, unexpected {extra}")
        for cname, t in components.items():
            m = self.components[cname]
            if not isinstance(m, ProductManifold):
                check_tensor(t, m.event_shape, cname, "ProductManifold.state")
        raw = ProductState({n: components[n] for n in self.components}, self._event_ndims())
        return self._check_point(raw, "x", "ProductManifold.state", project)

    def _split(self, d: torch.Tensor, attr: str) -> dict[str, torch.Tensor]:
        return {n: d[..., sl] for n, sl in self._ranges(attr).items()}

    def _boxplus(self, x, delta):
        parts = self._split(delta, "dim")
        return ProductState({n: m._boxplus(x[n], parts[n]) for n, m in self.components.items()},
                            self._event_ndims())

    def _boxminus(self, y, x):
        outs = [m._boxminus(y[n], x[n]) for n, m in self.components.items()]
        batch = torch.broadcast_shapes(*(o.shape[:-1] for o in outs))
        return torch.cat([o.expand(*batch, o.shape[-1]) for o in outs], -1)

    def _oplus(self, x, delta_e):
        parts = self._split(delta_e, "ext_dim")
        return ProductState({n: m._oplus(x[n], parts[n]) for n, m in self.components.items()},
                            self._event_ndims())

    def _block_diag(self, blocks: list[torch.Tensor], cols: list[int]) -> torch.Tensor:
        batch = torch.broadcast_shapes(*(b.shape[:-2] for b in blocks))
        total = sum(cols)
        rows, start = [], 0
        for b, c in zip(blocks, cols):
            b = b.expand(*batch, *b.shape[-2:])
            r = b.shape[-2]
            left = b.new_zeros(*batch, r, start)
            right = b.new_zeros(*batch, r, total - start - c)
            rows.append(torch.cat((left, b, right), -1))
            start += c
        return torch.cat(rows, -2)

    def _G_x(self, x_d, v):
        parts = self._split(v, "ext_dim")
        blocks = [m._G_x(x_d[n], parts[n]) for n, m in self.components.items()]
        return self._block_diag(blocks, [m.dim for m in self.components.values()])

    def _G_f(self, x_d, v):
        parts = self._split(v, "ext_dim")
        blocks = [m._G_f(x_d[n], parts[n]) for n, m in self.components.items()]
        return self._block_diag(blocks, [m.ext_dim for m in self.components.values()])

    def _random(self, batch, generator, dtype, device):
        comps = self.components.items()
        return ProductState({n: m._random(batch, generator, dtype, device) for n, m in comps},
                            self._event_ndims())

    def _identity(self, batch, dtype, device):
        return ProductState({n: m._identity(batch, dtype, device) for n, m in self.components.items()},
                            self._event_ndims())
