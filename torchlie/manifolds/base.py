"""The contract every space implements, the one tolerance rule, and the helpers the spaces share.

One class per space carries two vocabularies (see the package docstring for the map):

* **⊞ / ⊟ / ⊕ (seed 003, "On-manifold MPC", §III, Eq. 1-3, Table I)** — chart coordinates::

      x ⊞ δ   : 𝓜 × Rⁿ -> 𝓜        (δ in the homeomorphic space, Eq. 1)
      y ⊟ x   : 𝓜 × 𝓜 -> Rⁿ
      x ⊕ δᵉ  : 𝓜 × Rˡ -> 𝓜        (exogenous perturbation of size l, possibly l ≠ n, Eq. 3)

  obeying the axioms of Eq. 2: ``x ⊞ 0 = x``, ``x ⊞ (y ⊟ x) = y``, ``(x ⊞ δ) ⊟ x = δ`` (δ small).
  The discrete system is ``x_{k+1} = x_k ⊕ Δt f(x_k, u_k)`` (Eq. 14) and the error system
  ``δx = x ⊟ x^d`` is linearised (Eq. 20-22) as ``F_x = G_x + Δt G_f ∂f/∂δx``, ``F_u = Δt G_f ∂f/∂δu``
  with the *manifold parts* (Eq. 23), for ``v = Δt f(x^d, u^d)``::

      G_x(x^d, v) = ∂/∂δ [((x^d ⊞ δ) ⊕ v) ⊟ (x^d ⊕ v)] at δ = 0        shape (*, n, n)
      G_f(x^d, v) = ∂/∂δ [(x^d ⊕ (v + δ)) ⊟ (x^d ⊕ v)] at δ = 0         shape (*, n, l)

  Every ``G_x``/``G_f`` also takes ``exact=True``, which differentiates the defining expression of
  Eq. 23 with ``torch.func.jacrev`` instead (one reverse sweep per output row, batch summed out);
  a space without a closed form (one a user adds) gets that path by default.

* **Exp / Log at a point (seed 004 §12, Riemannian statistics)** — ``exp_at(x, v)``, ``log_at(x, y)``,
  ``dist``, ``transport_matrix``/``transport`` (parallel transport), ``normal_basis``; tangent
  vectors are flat ``(*, tangent_size)`` vectors *in an orthonormal frame of the metric*, so the
  Karcher mean and the Gaussians of :mod:`torchlie.manifolds.statistics` are written once for every
  space (the :class:`RiemannianManifold` protocol).  Where a space has both vocabularies and they
  are the same map (Rⁿ, SO(2), SO(3), SE(3): ``exp_at(x, δ) = x ⊞ δ``, ``log_at(x, y) = y ⊟ x``) the
  class has one implementation; where they differ (the sphere: ⊟ gives 2-vectors in the basis
  B(x), ``log_at`` ambient 3-vectors) both are kept, each with its documented coordinates.

``has_boxplus`` / ``has_exp_log`` say which vocabularies a space has; calling a method of a missing
one raises ``NotImplementedError`` naming the space.

Off-manifold points.  Points off the manifold (a non-orthogonal "rotation", a sphere point of the
wrong radius, a surface point off ``z = F(x, y)``, an asymmetric "SPD" matrix, non-finite entries)
are never used silently: every public method raises ``ValueError`` naming the argument and the
first offending batch index, or projects onto the manifold when called with ``project=True``.
Every membership check compares with one tolerance, :func:`manifold_tolerance` (``sqrt(eps)`` of
the dtype).  The checks are Python-level branches on data, so inside ``torch.func.vmap`` check the
points beforehand (``M.check(x)``) and pass ``check=False`` (the explicit "already checked" switch,
also for solvers' inner loops such as the Karcher iteration) or ``project=True``.
"""

from __future__ import annotations

import abc
import importlib
import math
from typing import Protocol, runtime_checkable

import torch

from torchlie._batch import broadcast_shapes, check_same_device, check_tensor

__all__ = ["Manifold", "RiemannianManifold", "manifold_tolerance"]


def manifold_tolerance(dtype: torch.dtype) -> float:
    """Tolerance of every "this lies on the manifold" check: ``sqrt(eps(dtype))``.

    float64 1.5e-8, float32 3.5e-4, float16 3.1e-2, bfloat16 8.8e-2 — loose enough for points that
    went through many roundoff-affected operations (k steps of ``x ⊕ Δt f`` drift by about k·eps),
    tight enough to catch a wrong input.  Compared with it: the orthogonality and determinant of
    rotations, the last row of SE(3) matrices, the relative radius error of sphere points, the
    relative normal component of sphere tangent vectors, the surface height error, the relative
    asymmetry of SPD matrices, of their tangent vectors and of covariances.  (Positive
    definiteness is not a tolerance: an SPD point needs ``λ_min > n·eps·λ_max``.)

    Why this rule: ``torchlie.manifolds`` (⊞/⊟) used √eps and ``torchlie.riemannian`` (Exp/Log)
    1e-10 / 1e-4 / 1e-2 (float64 / float32 / other) before the two were merged.  Both test suites
    pass under either rule (measured by swapping them): every test that expects a rejection is off
    by ≥ 1e-6 in float64, which both reject, and "1e-6 off is accepted in float32" holds under both,
    so no check needed the tighter float64 value.  √eps is one formula for every dtype (1e-2 was
    1.3 ulps of bfloat16, less than a correctly rounded normalization guarantees) and gives float32
    rollouts room (3.5e-4 ≈ 2900 eps, against 840).  A point accepted within the tolerance is used as
    given, so results inherit its O(tolerance) error; pass ``project=True`` where they must be exact
    to roundoff.
    """
    return math.sqrt(torch.finfo(dtype).eps)


# ------------------------------------------------------------------------------------------------
# helpers shared by the spaces
# ------------------------------------------------------------------------------------------------

def _group(name: str):
    # The group modules are imported on first use so that this package imports cheaply.
    return importlib.import_module(f"torchlie.{name}")


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
    """Batch index of the first True entry of ``mask`` (row-major), ``()`` when there is none."""
    idx = torch.nonzero(mask)
    return tuple(int(i) for i in idx[0].tolist()) if idx.shape[0] else ()


def _over_tolerance(err: torch.Tensor, fn: str, name: str, what: str) -> tuple[int, ...] | None:
    """The one tolerance comparison of the package: batch index of the first element whose
    nonnegative violation ``err`` exceeds :func:`manifold_tolerance` (NaN counts as exceeding), or
    None when every element is within it.  Every membership check calls it."""
    bad = ~(err <= manifold_tolerance(err.dtype))
    return _first_index(bad) if _any_true(bad, fn, name, what) else None


def _eye(n: int, batch, like: torch.Tensor) -> torch.Tensor:
    return torch.eye(n, dtype=like.dtype, device=like.device).expand(*batch, n, n)


def _dot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return (a * b).sum(-1, keepdim=True)


def _safe_norm(v: torch.Tensor) -> torch.Tensor:
    """‖v‖ ``(*, 1)`` with a zero (finite) gradient at v = 0."""
    n2 = _dot(v, v)
    pos = n2 > 0
    return torch.where(pos, torch.sqrt(torch.where(pos, n2, torch.ones_like(n2))), torch.zeros_like(n2))


def _sym(A: torch.Tensor) -> torch.Tensor:
    return 0.5 * (A + A.transpose(-1, -2))


def _check_symmetric(X: torch.Tensor, name: str, fn: str, what: str) -> None:
    """``ValueError`` unless the relative asymmetry of X is within :func:`manifold_tolerance`."""
    scale = torch.clamp(X.abs().amax(dim=(-1, -2)), min=torch.finfo(X.dtype).tiny)
    err = (X - X.transpose(-1, -2)).abs().amax(dim=(-1, -2)) / scale
    i = _over_tolerance(err, fn, name, "the symmetric matrices")
    if i is not None:
        raise ValueError(f"{fn}: argument '{name}' is not symmetric ({what}): relative asymmetry "
                         f"{float(err[i]):.3g} > tolerance {manifold_tolerance(X.dtype):.2g} at batch "
                         f"index {i}; pass project=True to symmetrize it")


# ------------------------------------------------------------------------------------------------
# the contract
# ------------------------------------------------------------------------------------------------

_VOCABULARY = {
    "boxplus": "⊞/⊟/⊕ and G_x/G_f (seed 003)",
    "exp_log": "exp_at/log_at/dist/transport (seed 004 §12)",
}


class Manifold(abc.ABC):
    """A manifold 𝓜 of dimension ``dim`` (n); the two vocabularies of the package docstring.

    Common to every space:

    * ``dim`` (n), ``event_shape`` = ``point_shape`` (trailing shape of one point);
    * ``check(x, name)`` / ``check_point(x, name, fn)`` / ``project(x)`` — see below;
    * ``random(*batch, generator=)`` / ``identity(*batch)``.

    ⊞ vocabulary (``has_boxplus``; shapes with any leading batch dims ``*``, broadcast between
    arguments):

    * ``boxplus(x, delta)``: x ⊞ δ, δ ``(*, n)`` -> point.
    * ``boxminus(y, x)``: y ⊟ x -> ``(*, n)``.
    * ``oplus(x, delta_e)``: x ⊕ δᵉ, δᵉ ``(*, l)`` -> point (``ext_dim`` = l).
    * ``G_x(x_d, v)`` ``(*, n, n)`` and ``G_f(x_d, v)`` ``(*, n, l)``: the manifold parts of the
      error-state linearization (Eq. 23), ``v = Δt f(x_d, u_d)`` ``(*, l)``; closed form from
      Table I, or ``exact=True`` for ``torch.func.jacrev`` of the defining expression.
    * ``linearize(x_d, v, dt, df_dx, df_du)`` -> ``(F_x, F_u)`` of Eq. 21-22.

    Exp/Log vocabulary (``has_exp_log``; tangent vectors ``(*, m)``, m = ``tangent_size``, in an
    orthonormal frame of the metric; the :class:`RiemannianManifold` protocol):

    * ``exp_at(x, v)``, ``log_at(x, y)``, ``dist(x, y)``, ``transport_matrix(x, y)`` ``(*, m, m)``,
      ``transport(x, y, v)``, ``normal_basis(x)`` (``(*, m, m − dim)`` or None when m = dim),
      ``check_tangent(x, v)``.

    Every method that takes points checks them (``ValueError`` naming the argument when a point is
    off the manifold, tolerance :func:`manifold_tolerance`) unless called with ``project=True``,
    which projects them first, or ``check=False``, with which the caller vouches for points it
    has already checked (inside ``torch.func.vmap``, or in a solver's inner loop); shapes, dtypes
    and devices are checked either way (metadata only, no device synchronization).  Points are
    plain tensors for the primitive manifolds and :class:`~torchlie.manifolds.ProductState` for
    :class:`~torchlie.manifolds.ProductManifold`.  dtype and device follow the inputs.

    A subclass implements ``dim``, ``event_shape``, ``_membership_error``, ``_project``,
    ``_random``, ``_identity`` and the hooks of the vocabularies it has: ``ext_dim``, ``_boxplus``,
    ``_boxminus``, ``_oplus`` (and optionally the closed forms ``_G_x``, ``_G_f``); ``_exp``,
    ``_log``, ``_tm`` (and ``tangent_size``, ``_tangent``, ``normal_basis`` when the tangent
    representation is not Rⁿ).
    """

    # --- implemented by every space -----------------------------------------------------------------
    @property
    @abc.abstractmethod
    def dim(self) -> int:  # n
        """Implemented by each concrete manifold."""

    @property
    @abc.abstractmethod
    def event_shape(self) -> tuple[int, ...]:
        """Implemented by each concrete manifold."""

    @property
    def point_shape(self) -> tuple[int, ...]:
        """Trailing shape of one point (the Exp/Log vocabulary's name for ``event_shape``)."""
        return self.event_shape

    def _describe(self) -> str:
        return repr(self)

    def _membership_error(self, x: torch.Tensor) -> torch.Tensor:
        """Nonnegative violation per batch element, comparable with :func:`manifold_tolerance`.

        Primitive manifolds implement it; a product checks its components through their own."""
        raise NotImplementedError(f"{self._name} checks points component by component")

    def _project(self, x: torch.Tensor, name: str, fn: str) -> torch.Tensor:
        """Nearest point on the manifold (primitive manifolds; a product projects its components)."""
        raise NotImplementedError(f"{self._name} projects points component by component")

    def _random(self, batch, generator, dtype, device):
        raise NotImplementedError(f"{self._name} has no random points")

    def _identity(self, batch, dtype, device):
        raise NotImplementedError(f"{self._name} has no canonical point")

    # --- which vocabularies -----------------------------------------------------------------------
    @property
    def has_boxplus(self) -> bool:
        """Whether ⊞/⊟/⊕ and G_x/G_f of seed 003 are defined (the space can be an MPC state)."""
        return type(self)._boxplus is not Manifold._boxplus

    @property
    def has_exp_log(self) -> bool:
        """Whether exp_at/log_at/transport are defined (the statistics functions accept it)."""
        return type(self)._exp is not Manifold._exp

    def _lacks(self, vocabulary: str, fn: str) -> NotImplementedError:
        return NotImplementedError(f"{fn}: {self!r} has no {_VOCABULARY[vocabulary]}")

    def _require(self, vocabulary: str, fn: str) -> None:
        if not getattr(self, f"has_{vocabulary}"):
            raise self._lacks(vocabulary, fn)

    # --- ⊞ hooks ----------------------------------------------------------------------------------
    @property
    def ext_dim(self) -> int:  # l
        """Size l of the exogenous perturbation of ⊕ (⊞ vocabulary)."""
        raise self._lacks("boxplus", f"{self._name}.ext_dim")

    def _boxplus(self, x, delta):
        raise self._lacks("boxplus", f"{self._name}.boxplus")

    def _boxminus(self, y, x):
        raise self._lacks("boxplus", f"{self._name}.boxminus")

    def _oplus(self, x, delta_e):
        raise self._lacks("boxplus", f"{self._name}.oplus")

    def _G_x(self, x_d, v):
        return self._jacobian_at_zero(x_d, v, "x")  # no closed form: autograd of Eq. 23

    def _G_f(self, x_d, v):
        return self._jacobian_at_zero(x_d, v, "f")

    # --- Exp/Log hooks ----------------------------------------------------------------------------
    @property
    def tangent_size(self) -> int:  # m
        """Length m of a tangent vector of the Exp/Log vocabulary (``dim`` unless documented)."""
        return self.dim

    def _exp(self, x, v):
        raise self._lacks("exp_log", f"{self._name}.exp_at")

    def _log(self, x, y):
        raise self._lacks("exp_log", f"{self._name}.log_at")

    def _tm(self, x, y):
        raise self._lacks("exp_log", f"{self._name}.transport_matrix")

    def _tangent(self, x, v, name: str, fn: str, project: bool):
        """Tangent-space membership of v at x (the sphere checks or projects; Rᵐ needs nothing)."""
        return v

    def normal_basis(self, x: torch.Tensor) -> torch.Tensor | None:
        """Orthonormal basis ``(*, m, m − dim)`` of the non-tangent part of Rᵐ (None when m = dim)."""
        return None

    # --- shared machinery -------------------------------------------------------------------------
    @property
    def _name(self) -> str:
        return type(self).__name__

    def _batch_shape(self, x) -> torch.Size:
        return _batch_of(x, len(self.event_shape))

    def _leaf(self, x) -> torch.Tensor:
        """A tensor of the point ``x`` (its device and dtype stand for the point's)."""
        return x

    def _check_point(self, x, name: str, fn: str, project: bool, check: bool = True):
        check_tensor(x, self.event_shape, name, fn)
        if project:
            return self._project(x, name, fn)
        if not check:
            return x
        err = self._membership_error(x.detach())
        idx = _over_tolerance(err, fn, name, self._describe())
        if idx is not None:
            tol = manifold_tolerance(x.dtype)
            bad = ~(err <= tol)  # NaN counts as bad
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

    def check_point(self, x, name: str = "x", fn: str = "", project: bool = False):
        """:meth:`check` with the calling function ``fn`` named in the messages (Exp/Log vocabulary)."""
        return self._check_point(x, name, fn or f"{self._name}.check_point", project)

    def project(self, x):
        """Nearest point on the manifold (closed form per manifold)."""
        return self._check_point(x, "x", f"{self._name}.project", True)

    def _vec(self, t, n: int, name: str, fn: str) -> torch.Tensor:
        return check_tensor(t, (n,), name, fn)

    def _same_device(self, fn: str, x, **tensors: torch.Tensor) -> None:
        check_same_device(fn, x=self._leaf(x), **tensors)

    # --- ⊞ vocabulary (seed 003) ----------------------------------------------------------------------
    def boxplus(self, x, delta: torch.Tensor, *, project: bool = False, check: bool = True):
        """x ⊞ δ with δ ``(*, n)`` in the homeomorphic space (Eq. 1, Table I)."""
        fn = f"{self._name}.boxplus"
        self._require("boxplus", fn)
        x = self._check_point(x, "x", fn, project, check)
        delta = self._vec(delta, self.dim, "delta", fn)
        self._same_device(fn, x, delta=delta)
        return self._boxplus(x, delta)

    def boxminus(self, y, x, *, project: bool = False, check: bool = True) -> torch.Tensor:
        """y ⊟ x ``(*, n)``: the perturbation taking x to y (Eq. 1, Table I)."""
        fn = f"{self._name}.boxminus"
        self._require("boxplus", fn)
        y = self._check_point(y, "y", fn, project, check)
        x = self._check_point(x, "x", fn, project, check)
        self._same_device(fn, x, y=self._leaf(y))
        return self._boxminus(y, x)

    def oplus(self, x, delta_e: torch.Tensor, *, project: bool = False, check: bool = True):
        """x ⊕ δᵉ with the exogenous perturbation δᵉ ``(*, l)`` (Eq. 3, Table I)."""
        fn = f"{self._name}.oplus"
        self._require("boxplus", fn)
        x = self._check_point(x, "x", fn, project, check)
        delta_e = self._vec(delta_e, self.ext_dim, "delta_e", fn)
        self._same_device(fn, x, delta_e=delta_e)
        return self._oplus(x, delta_e)

    def _prep_G(self, x_d, v, fn: str, project: bool, check: bool):
        self._require("boxplus", fn)
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
        batch = broadcast_shapes(self._batch_shape(x_d), v.shape[:-1])
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
        self._require("boxplus", fn)
        n, l = self.dim, self.ext_dim
        if not (isinstance(df_dx, torch.Tensor) and df_dx.dim() >= 2 and tuple(df_dx.shape[-2:]) == (l, n)):
            raise ValueError(f"{fn}: argument 'df_dx' must have shape (*, {l}, {n}), "
                             f"got {tuple(getattr(df_dx, 'shape', ()))}")
        if not (isinstance(df_du, torch.Tensor) and df_du.dim() >= 2 and df_du.shape[-2] == l):
            raise ValueError(f"{fn}: argument 'df_du' must have shape (*, {l}, m), "
                             f"got {tuple(getattr(df_du, 'shape', ()))}")
        if exact:
            Gx = self.G_x(x_d, v, exact=True, project=project, check=check)
            Gf = self.G_f(x_d, v, exact=True, project=project, check=check)
            return Gx + dt * (Gf @ df_dx), dt * (Gf @ df_du)
        x_d, v = self._prep_G(x_d, v, fn, project, check)
        return self._linearize(x_d, v, dt, df_dx, df_du)

    #: G_x = G_f = I exactly (Rⁿ, SO(2), surfaces: Table I); lets products skip the matrix products
    _G_identity: bool = False

    def _linearize(self, x_d, v, dt, df_dx, df_du):
        """``(G_x + Δt G_f ∂f/∂δx, Δt G_f ∂f/∂δu)`` on checked arguments (products override it)."""
        Gx, Gf = self._G_x(x_d, v), self._G_f(x_d, v)
        return Gx + dt * (Gf @ df_dx), dt * (Gf @ df_du)

    # --- Exp/Log vocabulary (seed 004 §12) ----------------------------------------------------------
    def _check_tangent(self, x, v, name: str, fn: str, project: bool, check: bool):
        check_tensor(v, (self.tangent_size,), name, fn)
        self._same_device(fn, x, **{name: v})
        if project or check:
            return self._tangent(x, v, name, fn, project)
        return v

    def check_tangent(self, x, v, name: str = "v", fn: str = "", project: bool = False) -> torch.Tensor:
        """``v`` ``(*, m)`` if it is a tangent vector at ``x`` (projected onto T_x if ``project``)."""
        return self._check_tangent(x, v, name, fn or f"{self._name}.check_tangent", project, True)

    def _points(self, fn: str, check: bool, project: bool, **points):
        self._require("exp_log", fn)
        out = [self._check_point(p, name, fn, project, check) for name, p in points.items()]
        if len(out) > 1:
            check_same_device(fn, **{name: self._leaf(p) for name, p in zip(points, out)})
        return out

    def exp_at(self, x, v, *, check: bool = True, project: bool = False) -> torch.Tensor:
        """Exp_x(v): the end point of the geodesic from x with initial velocity v ``(*, m)``."""
        fn = f"{self._name}.exp_at"
        (x,) = self._points(fn, check, project, x=x)
        v = self._check_tangent(x, v, "v", fn, project, check)
        return self._exp(x, v)

    def log_at(self, x, y, *, check: bool = True, project: bool = False) -> torch.Tensor:
        """Log_x(y) ``(*, m)``: the initial velocity of the geodesic from x reaching y at time 1."""
        x, y = self._points(f"{self._name}.log_at", check, project, x=x, y=y)
        return self._log(x, y)

    def dist(self, x, y, *, check: bool = True, project: bool = False) -> torch.Tensor:
        """Geodesic distance ‖Log_x(y)‖ ``(*,)`` (zero, finite gradient at x = y)."""
        x, y = self._points(f"{self._name}.dist", check, project, x=x, y=y)
        return _safe_norm(self._log(x, y)).squeeze(-1)

    def transport_matrix(self, x, y, *, check: bool = True, project: bool = False) -> torch.Tensor:
        """Parallel transport T_x -> T_y along the geodesic as a matrix ``(*, m, m)``."""
        x, y = self._points(f"{self._name}.transport_matrix", check, project, x=x, y=y)
        return self._tm(x, y)

    def transport(self, x, y, v, *, check: bool = True, project: bool = False) -> torch.Tensor:
        """Parallel transport of v ∈ T_x to T_y along the geodesic, ``(*, m)``."""
        fn = f"{self._name}.transport"
        x, y = self._points(fn, check, project, x=x, y=y)
        v = self._check_tangent(x, v, "v", fn, project, check)
        return (self._tm(x, y) @ v.unsqueeze(-1)).squeeze(-1)

    # --- sampling -----------------------------------------------------------------------------------
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
        """A canonical point (origin, identity, north pole, surface point above the origin, I)."""
        if len(batch) == 1 and isinstance(batch[0], (tuple, list, torch.Size)):
            batch = tuple(batch[0])
        return self._identity(tuple(int(b) for b in batch), dtype or torch.get_default_dtype(), device)


@runtime_checkable
class RiemannianManifold(Protocol):
    """What the Karcher-mean / Gaussian code of :mod:`torchlie.manifolds.statistics` needs.

    Points have trailing shape ``point_shape``; tangent vectors are flat ``(*, tangent_size)``
    vectors in an orthonormal frame of the metric (see the package table), spanning a
    ``dim``-dimensional tangent space. ``normal_basis(x)`` returns an orthonormal basis
    ``(*, tangent_size, tangent_size − dim)`` of the part of R^m that is *not* tangent (None when
    m == dim). All methods broadcast leading dims and take ``check=True`` (validate points, raise
    ``ValueError`` naming the argument) and ``project=False`` (project off-manifold inputs instead
    of raising); solvers validate once and pass ``check=False``.  Every :class:`Manifold` with
    ``has_exp_log`` implements it; so may a user's class that is not a :class:`Manifold`.
    """

    point_shape: tuple[int, ...]
    tangent_size: int
    dim: int

    def check_point(self, x: torch.Tensor, name: str = "x", fn: str = "",
                    project: bool = False) -> torch.Tensor: ...

    def check_tangent(self, x: torch.Tensor, v: torch.Tensor, name: str = "v", fn: str = "",
                      project: bool = False) -> torch.Tensor: ...

    def exp_at(self, x: torch.Tensor, v: torch.Tensor, *, check: bool = True,
               project: bool = False) -> torch.Tensor: ...

    def log_at(self, x: torch.Tensor, y: torch.Tensor, *, check: bool = True,
               project: bool = False) -> torch.Tensor: ...

    def dist(self, x: torch.Tensor, y: torch.Tensor, *, check: bool = True,
             project: bool = False) -> torch.Tensor: ...

    def transport_matrix(self, x: torch.Tensor, y: torch.Tensor, *, check: bool = True,
                         project: bool = False) -> torch.Tensor: ...

    def transport(self, x: torch.Tensor, y: torch.Tensor, v: torch.Tensor, *, check: bool = True,
                  project: bool = False) -> torch.Tensor: ...

    def normal_basis(self, x: torch.Tensor) -> torch.Tensor | None: ...
