"""Spheres: the class :class:`Sphere` (Sᵈ of radius r; ``S2(r)`` is ``Sphere(2, r)``) and the functional
core ``sphere_exp/log/dist/transport/transport_matrix`` on unit vectors (seed 003 Eq. 9-11, 45;
seed 004 Eq. 179-183).

Two coordinate systems, two different maps, both kept on the one class:

* **⊞ / ⊟ / ⊕ (seed 003, S² only)** — chart coordinates in the tangent basis B(x) ``(*, 3, 2)``:
  ``x ⊞ δ = Exp(B(x) δ) x`` (δ ∈ R², Eq. 10), ``y ⊟ x = B(x)ᵀ θ ⌊x⌋y/‖⌊x⌋y‖``,
  ``θ = atan2(‖⌊x⌋y‖, xᵀy)`` (Eq. 9), ``x ⊕ ω = Exp(ω) x`` (ω ∈ R³, Eq. 11).  δ is a rotation
  *angle* vector: ``x ⊞ (π, 0) = −x`` for every r.
* **Exp / Log at a point (seed 004, any d)** — ambient tangent vectors ``(*, d+1)`` ⟂ x:
  ``Exp_x(u) = x cos(‖u‖/r) + r (u/‖u‖) sin(‖u‖/r)`` (Eq. 180 scaled to radius r),
  ``Log_x(y)`` of length r·θ (Eq. 181), so ``dist`` is the arc length.  On the unit sphere this is
  exactly the functional core ``sphere_exp``/``sphere_log``.

On S² they describe the same geodesics: ``x ⊞ δ = exp_at(x, (B(x)δ) × x)`` and
``log_at(x, y) = (B(x)(y ⊟ x)) × x`` (the rotation axis B(x)δ turned into the velocity of x; tested).

S² basis.  ``B(x) = [b₁ b₂]`` (Eq. 9-10) is the image of ``[e₁ e₂]`` under the minimal rotation
taking ``e₃`` to ``x/r`` on the upper hemisphere (``x_z ≥ 0``) and ``-e₃`` to ``x/r`` on the lower one
(columns swapped there), so ``b₁ × b₂ = x/r`` everywhere and both branches are free of their
singularities.  B is discontinuous across the equator (no continuous tangent frame exists on S²);
the axioms and Eq. 23 never differentiate B, so this is harmless.  ``y ⊟ x`` at the antipode of x
(cut locus, rotation axis undefined) returns ``(π, 0)``, a rotation about b₁(x); so does any y with
``sin∠(x, y) < eps``, which it reaches to ``r·eps``.  Next to the antipode the axis is taken from its
two tangent components ``B(x)ᵀ(x × y)`` (the rounding error of ``x × y`` is as long as the vector
itself there and points anywhere, also along x), so x ⊞ (y ⊟ x) = y to roundoff up to the antipode.

Exactness of Table I on S² (Eq. 45)::

    G_x = -B(y)ᵀ Exp(v) ⌊x^d⌋² B(x^d) / r²,   G_f = -B(y)ᵀ Exp(v) ⌊x^d⌋² A(v)ᵀ / r²,   y = x^d ⊕ v

are the *exact* derivatives of Eq. 23 at δ = 0: the "≈" in Eq. 45a only drops terms of order ‖δ‖²,
which do not contribute to the derivative at δ = 0 (the ⊟ map has derivative ``B(y)ᵀ⌊y⌋/r²`` at
its base point, and ``⌊Exp(v) x⌋ = Exp(v)⌊x⌋Exp(v)ᵀ``).  Measured against ``torch.func.jacrev`` of
the defining expression (float64, 2000 random ``(x^d, v)`` with ``‖v‖ ≤ 3`` for each radius 0.5, 1,
2; ``tests/torchlie/test_manifolds.py::test_s2_table_one_difference``): max |closed − autograd| =
1.1e-15 for G_x and 8.9e-16 for G_f, i.e. roundoff.  What *is* first order is the linearised error
map of G_f: ``(x^d ⊕ (v + δ)) ⊟ (x^d ⊕ v) − G_f δ`` measured 3.1e-3, 3.2e-5, 3.1e-7 (max over 200
samples) at ‖δ‖ = 1e-1, 1e-2, 1e-3, i.e. O(‖δ‖²).  The G_x map is even exactly linear,
``((x^d ⊞ δ) ⊕ v) ⊟ (x^d ⊕ v) = B(y)ᵀ Exp(v) B(x^d) δ`` (Exp(v) is an isometry), remainder 3e-16.

Exp/Log conventions at the edges.
* **Log at x = y** is 0 with finite gradients (removable singularity, series branch).
  **At the antipode** (``‖y − (xᵀy)x‖ ≤ eps`` with ``xᵀy < 0``) the geodesic is not unique; Log
  returns the vector of length π along a deterministic direction ``e(x)``: the unit projection onto
  T_x of the basis vector ``e_k`` with ``k = argmin |x_k|``. Since ``e(−x) = e(x)``, both transport
  forms (Eq. 182, 183) reduce there to the reflection ``I − 2 e eᵀ`` and agree. Gradients are finite
  everywhere; near the antipode they are large (≈ π/‖y − (xᵀy)x‖), as the geometry dictates.
* **Statistics** keep covariances in ambient coordinates as in seed 004 (Σ x = 0), inverted and
  log-determined on the tangent space only through ``normal_basis`` (``(Σ + x xᵀ)⁻¹ − x xᵀ`` is the
  pseudo-inverse on T_x). No frame choice is needed, so there is no hairy-ball discontinuity there.
* **Quaternions (S³)**: q and −q are one rotation; the sphere statistics treat them as two points.
  Align samples to one hemisphere first (:func:`hemisphere_align`).

Membership: the relative radius error ``|‖x‖ − r| / r`` (for the functional core, r = 1) and, for
tangent vectors, the relative normal component ``|x̂ᵀv| / max(‖v‖, 1)``, both against
:func:`~torchlie.manifolds.manifold_tolerance`; ``project=True`` normalizes points (a zero or
non-finite vector raises) and removes the normal component of tangent vectors.
"""

from __future__ import annotations

import dataclasses
import math

import torch

from torchlie._batch import broadcast_shapes, check_same_device, check_tensor, small_angle_eps
from torchlie.manifolds.base import (
    Manifold,
    _any_true,
    _dot,
    _first_index,
    _group,
    _over_tolerance,
    _safe_norm,
    manifold_tolerance,
)

__all__ = [
    "Sphere",
    "S2",
    "sphere_exp",
    "sphere_log",
    "sphere_dist",
    "sphere_transport",
    "sphere_transport_matrix",
    "hemisphere_align",
]


# ------------------------------------------------------------------------------------------------
# S² tangent basis (seed 003 Eq. 9-10)
# ------------------------------------------------------------------------------------------------

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


# ------------------------------------------------------------------------------------------------
# unit sphere Sᵈ, unchecked kernels (seed 004 Eq. 179-183)
# ------------------------------------------------------------------------------------------------

def _antipodal_direction(x: torch.Tensor) -> torch.Tensor:
    # e(x): unit projection onto T_x of the basis vector least aligned with x; e(-x) = e(x).
    k = x.abs().argmin(dim=-1, keepdim=True)
    ek = torch.zeros_like(x).scatter(-1, k, 1.0)
    e = ek - x.gather(-1, k) * x
    return e / torch.linalg.vector_norm(e, dim=-1, keepdim=True)


def _sphere_log_theta(x: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Log_x(y) (Eq. 181) and the angle θ ``(*, 1)``; safe at x = y and at the antipode."""
    x, y = torch.broadcast_tensors(x, y)
    c = _dot(x, y)
    w = y - c * x
    w = w - _dot(x, w) * x                       # second Gram–Schmidt pass: w ⟂ x to rounding
    s2 = _dot(w, w)
    tau = small_angle_eps(x.dtype)
    # antipode: sin θ below eps, so θ = π to within eps and any direction lands on y to eps (a
    # √eps switch, as before, replaced Log by π e(x) up to 1.5e-8 from −x: round trip off by 1.5e-8)
    anti_tol = torch.finfo(x.dtype).eps
    small = (s2 < tau * tau) & (c > 0)
    anti = (s2 <= anti_tol * anti_tol) & (c <= 0)
    regular = ~(small | anti)
    s = torch.sqrt(torch.where(regular, s2, torch.ones_like(s2)))
    # near x = y: atan2(s, c)/s = atan(t)/(t c), t = s/c  (series in t², exact off the manifold too)
    c_safe = torch.where(small, c, torch.ones_like(c))
    t2 = s2 / (c_safe * c_safe)
    ratio_small = (1 - t2 / 3 + t2 * t2 / 5) / c_safe
    ratio = torch.where(regular, torch.atan2(s, c) / s, ratio_small)
    u = ratio * w
    u = torch.where(anti, math.pi * _antipodal_direction(x), u)
    theta = torch.where(regular, torch.atan2(s, c),
                        torch.where(anti, torch.full_like(c, math.pi), _safe_norm(u)))
    return u, theta


def _sphere_exp(x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    n2 = _dot(u, u)
    tau = small_angle_eps(u.dtype)
    small = n2 < tau * tau
    n = torch.sqrt(torch.where(small, torch.ones_like(n2), n2))
    sinc = torch.where(small, 1 - n2 / 6 + n2 * n2 / 120, torch.sin(n) / n)
    cos = torch.where(small, 1 - n2 / 2 + n2 * n2 / 24, torch.cos(n))
    return x * cos + u * sinc


def _transport_coeffs(u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    # a = (cos θ − 1)/θ², b = sin θ/θ with θ = ‖u‖ (series below the small-angle switch)
    t2 = _dot(u, u)
    tau = small_angle_eps(u.dtype)
    small = t2 < tau * tau
    t = torch.sqrt(torch.where(small, torch.ones_like(t2), t2))
    t2s = torch.where(small, torch.ones_like(t2), t2)
    a = torch.where(small, -0.5 + t2 / 24 - t2 * t2 / 720, (torch.cos(t) - 1) / t2s)
    b = torch.where(small, 1 - t2 / 6 + t2 * t2 / 120, torch.sin(t) / t)
    return a, b


def _sphere_transport_matrix(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    u, _ = _sphere_log_theta(x, y)
    x = x.expand_as(u)
    a, b = _transport_coeffs(u)
    eye = torch.eye(u.shape[-1], dtype=u.dtype, device=u.device)
    return eye + (a * u - b * x).unsqueeze(-1) * u.unsqueeze(-2)


def _sphere_transport_182(x: torch.Tensor, y: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    u, theta = _sphere_log_theta(x, y)
    u_back, _ = _sphere_log_theta(y, x)
    t2 = theta * theta
    tau = small_angle_eps(u.dtype)
    small = t2 < tau * tau
    uv = _dot(u, v)
    literal = v - uv / torch.where(small, torch.ones_like(t2), t2) * (u + u_back)
    # removable singularity at x = y: the same expression expanded in θ (equal to Eq. 183 there)
    a, b = _transport_coeffs(u)
    limit = v + (a * u - b * x) * uv
    return torch.where(small, limit, literal)


def _check_sphere_tangent(x: torch.Tensor, v: torch.Tensor, name: str, fn: str,
                          project: bool) -> torch.Tensor:
    """v ⟂ the unit vector x to :func:`manifold_tolerance` (relative), or its projection onto T_x."""
    dot = (x * v).sum(-1, keepdim=True)
    if project:
        return v - dot * x
    scale = torch.clamp(torch.linalg.vector_norm(v, dim=-1), min=1.0)
    err = dot.squeeze(-1).abs() / scale
    i = _over_tolerance(err, fn, name, "the tangent space")
    if i is not None:
        raise ValueError(f"{fn}: argument '{name}' is not tangent at the base point: |xᵀ{name}| = "
                         f"{float(err[i]):.3g} (relative) > tolerance {manifold_tolerance(v.dtype):.2g} "
                         f"at batch index {i}; pass project=True to project it onto the tangent space")
    return v


# ------------------------------------------------------------------------------------------------
# the class
# ------------------------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class Sphere(Manifold):
    """The sphere Sᵈ_r = {x ∈ R^{d+1} : ‖x‖ = r}, points ``(*, d+1)``; ``dim`` = d.

    Exp/Log vocabulary, every d (seed 004 Eq. 179-183): tangent vectors ambient ``(*, d+1)`` ⟂ x
    (``tangent_size`` = d+1, rank d; ``normal_basis(x)`` = x/r), transport of Eq. 183.
    ``Sphere(3)`` holds unit quaternions (w, x, y, z); ``Sphere(2)`` directions/normals.

    ⊞ vocabulary, d = 2 only (seed 003 Eq. 9-11, 45; ``has_boxplus``): n = 2, l = 3,
    ``x ⊞ δ = Exp(B(x) δ) x``, ``y ⊟ x = B(x)ᵀ θ ⌊x⌋y/‖⌊x⌋y‖``, ``x ⊕ ω = Exp(ω) x``;
    ``G_x = -B(y)ᵀ Exp(v)⌊x_d⌋² B(x_d)/r²``, ``G_f = -B(y)ᵀ Exp(v)⌊x_d⌋² A(v)ᵀ/r²``, y = x_d ⊕ v
    (Eq. 45a-b; exact at δ = 0 despite the "≈" of Eq. 45a, see the module docstring for the
    measured difference).  B and both coordinate systems are described in the module docstring.
    """

    d: int
    r: float = 1.0

    def __post_init__(self):
        d, r = self.d, self.r
        if isinstance(d, bool) or not isinstance(d, int) or d < 1:
            raise ValueError(f"Sphere: argument 'd' must be an int >= 1, got {d!r}")
        if isinstance(r, bool) or not isinstance(r, (int, float)) or not math.isfinite(r) or r <= 0:
            raise ValueError(f"Sphere: argument 'r' must be a positive finite float, got {r!r}")
        object.__setattr__(self, "r", float(r))

    @property
    def dim(self) -> int:
        return self.d

    @property
    def ext_dim(self) -> int:
        self._require("boxplus", f"{self._name}.ext_dim")
        return 3

    @property
    def event_shape(self) -> tuple[int, ...]:
        return (self.d + 1,)

    @property
    def tangent_size(self) -> int:
        return self.d + 1

    @property
    def has_boxplus(self) -> bool:
        return self.d == 2

    def _describe(self) -> str:
        where = "the unit sphere" if self.r == 1.0 else f"the sphere of radius {self.r:g}"
        return f"{where} in R^{self.d + 1} (relative radius error)"

    def _membership_error(self, x):
        return (torch.linalg.vector_norm(x, dim=-1) - self.r).abs() / self.r

    def _project(self, x, name, fn):
        nrm = torch.linalg.vector_norm(x, dim=-1, keepdim=True)
        bad = ~(torch.isfinite(nrm) & (nrm > 0)).squeeze(-1)
        if _any_true(bad, fn, name, "a sphere (nonzero vector needed)"):
            raise ValueError(f"{fn}: argument '{name}' contains a zero or non-finite vector "
                             f"(first at batch index {_first_index(bad)}); it cannot be projected "
                             "onto the sphere")
        return x / nrm * self.r

    def _random(self, batch, generator, dtype, device):
        x = torch.randn(*batch, self.d + 1, generator=generator, dtype=dtype, device=device)
        x = torch.where(torch.linalg.vector_norm(x, dim=-1, keepdim=True) > 0, x, torch.ones_like(x))
        return x * (self.r / torch.linalg.vector_norm(x, dim=-1, keepdim=True))

    def _identity(self, batch, dtype, device):
        pole = torch.zeros(self.d + 1, dtype=dtype, device=device)
        pole[-1] = self.r
        return pole.expand(*batch, self.d + 1).clone()

    # --- ⊞ vocabulary (S²) ----------------------------------------------------------------------------
    def basis(self, x: torch.Tensor, *, project: bool = False) -> torch.Tensor:
        """The tangent basis B(x) ``(*, 3, 2)`` of Eq. 9 (orthonormal, ``b₁ × b₂ = x/r``; S² only)."""
        self._require("boxplus", f"{self._name}.basis")
        x = self._check_point(x, "x", f"{self._name}.basis", project)
        return self._B(x)

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

    # --- Exp/Log vocabulary (every d; the unit-sphere kernels scaled by r, exact for r = 1) ----------
    def _exp(self, x, v):
        r = self.r
        return r * _sphere_exp(x / r, v / r)

    def _log(self, x, y):
        r = self.r
        return r * _sphere_log_theta(x / r, y / r)[0]

    def _tm(self, x, y):
        return _sphere_transport_matrix(x / self.r, y / self.r)

    def _tangent(self, x, v, name, fn, project):
        return _check_sphere_tangent(x / self.r, v, name, fn, project)

    def normal_basis(self, x):
        return (x / self.r).unsqueeze(-1)


def S2(r: float = 1.0) -> Sphere:
    """The two-sphere S²_r of seed 003 (Eq. 9-11, 45): ``Sphere(2, r)``, with ⊞/⊟/⊕ and G_x/G_f."""
    return Sphere(2, r)


# ------------------------------------------------------------------------------------------------
# functional core on unit vectors (seed 004 Eq. 179-183)
# ------------------------------------------------------------------------------------------------

def _prep_sphere(fn: str, **pts: torch.Tensor) -> tuple[Sphere, list[torch.Tensor]]:
    """Check shapes, dtypes and devices; returns the unit sphere of the arguments' size."""
    out = []
    for name, t in pts.items():
        check_tensor(t, (t.shape[-1],) if isinstance(t, torch.Tensor) and t.dim() else (2,), name, fn)
        out.append(t)
    ref = out[0]
    for (name, t) in list(pts.items())[1:]:
        if t.shape[-1] != ref.shape[-1]:
            raise ValueError(f"{fn}: argument '{name}' must have shape (*, {ref.shape[-1]}) like "
                             f"'{next(iter(pts))}', got {tuple(t.shape)}")
    check_same_device(fn, **pts)
    try:
        broadcast_shapes(*(t.shape[:-1] for t in out))
    except RuntimeError as e:
        raise ValueError(f"{fn}: batch shapes {[tuple(t.shape[:-1]) for t in out]} of "
                         f"{list(pts)} do not broadcast") from e
    if ref.shape[-1] < 2:
        raise ValueError(f"{fn}: argument '{next(iter(pts))}' must have shape (*, d+1) with d >= 1, "
                         f"got {tuple(ref.shape)}")
    return Sphere(ref.shape[-1] - 1), out


def sphere_exp(x: torch.Tensor, u: torch.Tensor, *, project: bool = False) -> torch.Tensor:
    """Exp_x(u) = x cos‖u‖ + (u/‖u‖) sin‖u‖ (seed 004 Eq. 180).

    x ``(*, d+1)`` unit vector, u ``(*, d+1)`` tangent at x (xᵀu = 0); returns ``(*, d+1)``.
    Exact series near u = 0 (finite gradients there). ``project=True`` normalizes x and projects u
    onto T_x instead of raising ``ValueError``.  Equals ``Sphere(d).exp_at(x, u)``.
    """
    fn = "sphere_exp"
    S, (x, u) = _prep_sphere(fn, x=x, u=u)
    x = S._check_point(x, "x", fn, project)
    u = S._tangent(x, u, "u", fn, project)
    return _sphere_exp(x, u)


def sphere_log(x: torch.Tensor, y: torch.Tensor, *, project: bool = False) -> torch.Tensor:
    """Log_x(y) = d(x, y) (y − xᵀy x)/‖y − xᵀy x‖ (seed 004 Eq. 181), ``(*, d+1)`` tangent at x.

    Returns 0 at y = x (finite gradients) and, at the antipode y = −x, the length-π vector along the
    deterministic direction described in the module docstring.  Equals ``Sphere(d).log_at(x, y)``.
    """
    fn = "sphere_log"
    S, (x, y) = _prep_sphere(fn, x=x, y=y)
    x = S._check_point(x, "x", fn, project)
    y = S._check_point(y, "y", fn, project)
    return _sphere_log_theta(x, y)[0]


def sphere_dist(x: torch.Tensor, y: torch.Tensor, *, project: bool = False) -> torch.Tensor:
    """Geodesic distance arccos(xᵀy) (seed 004 Eq. 179) ``(*,)``, computed as atan2(‖y − xᵀy x‖, xᵀy).

    The atan2 form is accurate near 0 and π, where arccos loses half the digits; equals ‖Log_x(y)‖.
    The gradient at x = y is 0 (a subgradient of the non-differentiable point).
    """
    fn = "sphere_dist"
    S, (x, y) = _prep_sphere(fn, x=x, y=y)
    x = S._check_point(x, "x", fn, project)
    y = S._check_point(y, "y", fn, project)
    return _sphere_log_theta(x, y)[1].squeeze(-1)


def sphere_transport_matrix(x: torch.Tensor, y: torch.Tensor, *, project: bool = False) -> torch.Tensor:
    """A_{x→y} of seed 004 Eq. 183 ``(*, d+1, d+1)``: Γ_{x→y}(v) = A v, Σ_∥ = A Σ Aᵀ.

    A = −x sin‖u‖ ūᵀ + ū cos‖u‖ ūᵀ + (I − ūūᵀ), u = Log_x(y), ū = u/‖u‖, evaluated as
    I + ((cos θ − 1)/θ² u − (sin θ/θ) x) uᵀ, which is smooth (A = I at x = y).
    """
    fn = "sphere_transport_matrix"
    S, (x, y) = _prep_sphere(fn, x=x, y=y)
    x = S._check_point(x, "x", fn, project)
    y = S._check_point(y, "y", fn, project)
    return _sphere_transport_matrix(x, y)


def sphere_transport(x: torch.Tensor, y: torch.Tensor, v: torch.Tensor, *, form: int = 182,
                     project: bool = False) -> torch.Tensor:
    """Parallel transport Γ_{x→y}(v) of v ∈ T_x S^d along the geodesic, ``(*, d+1)``.

    ``form=182``: v − (Log_x(y)ᵀv / d(x,y)²)(Log_x(y) + Log_y(x)) (seed 004 Eq. 182), with its removable
    singularity at x = y replaced by its Taylor limit; ``form=183``: the linear map A_{x→y} v of
    Eq. 183. The two are equal (tested); both preserve inner products and land in T_y.
    """
    fn = "sphere_transport"
    if form not in (182, 183):
        raise ValueError(f"{fn}: argument 'form' must be 182 or 183 (seed equation number), got {form!r}")
    S, (x, y, v) = _prep_sphere(fn, x=x, y=y, v=v)
    x = S._check_point(x, "x", fn, project)
    y = S._check_point(y, "y", fn, project)
    v = S._tangent(x, v, "v", fn, project)
    if form == 183:
        return (_sphere_transport_matrix(x, y) @ v.unsqueeze(-1)).squeeze(-1)
    return _sphere_transport_182(x, y, v)


def hemisphere_align(q: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
    """Flip the sign of each q ``(*, k)`` whose dot product with ``reference`` (broadcast) is negative.

    For unit quaternions (w, x, y, z) q and −q are the same rotation; statistics on S³ need the samples
    in one hemisphere. Unchecked apart from shapes; returns ``(*, k)``.
    """
    check_tensor(q, (q.shape[-1],) if isinstance(q, torch.Tensor) and q.dim() else (4,), "q",
                 "hemisphere_align")
    check_tensor(reference, (q.shape[-1],), "reference", "hemisphere_align")
    s = torch.where(_dot(q, reference) < 0, -1.0, 1.0).to(q.dtype)
    return q * s
