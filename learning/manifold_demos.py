"""Demonstrations on manifolds: orientation, pose and stiffness demos, their Gaussian-on-manifold statistics
per time step, and tracking the mean with the on-manifold MPC (issue 26 §5; seed 004 §12.3, seed 003).

**Data.**  Demos of a rotation, a pose, a unit quaternion or an SPD (stiffness/manipulability) matrix are
kept in a :class:`~learning.demos.Demonstrations` with flat states ``x (N, T, n)``; the layout is fixed by
the *group*, recorded as ``meta["group"]``:

=========  ==========================  ==========  =====================================================
group      point                       flat ``n``  torchlie space (tangent size m)
=========  ==========================  ==========  =====================================================
``SO3``    rotation matrix ``(3, 3)``  9           :class:`~torchlie.manifolds.SO3` (3, body-frame ω)
``SE3``    homogeneous ``(4, 4)``      16          :class:`~torchlie.manifolds.SE3` (6, body ``[ρ, ω]``)
``S3``     quaternion ``(4,)``         4           :class:`~torchlie.manifolds.Sphere` (3) (4, ambient)
``SPD``    SPD matrix ``(k, k)``       k²          :class:`~torchlie.manifolds.SPD` (k) (k(k+1)/2, Mandel)
=========  ==========================  ==========  =====================================================

Matrices are flattened row-major; quaternions are ``(w, x, y, z)``.  :func:`demo_points` and
:func:`points_to_demos` convert between the two forms.

**Synthetic demos** (:func:`orientation_demos`, :func:`stiffness_demos`).  A smooth reference path
``x*(s) = Exp_b(ξ(s))`` on the manifold (``ξ`` a smooth tangent path at a base point ``b``; on SPD the
affine-invariant geodesic between two stiffness matrices), then human-like variability reusing
:mod:`learning.demos`: a random smooth time warp of the tangent path (:func:`~learning.demos.time_warp`)
and smooth offsets ``ε_i(t)`` in the tangent space (:func:`~learning.demos.spatial_noise` on zero
tangent demos, times an optional envelope), applied on the manifold: ``x_i(t) = Exp_{x*(τ_i(t))}(ε_i(t))``
(for SO(3)/SE(3) ``x*·Exp(ε)``: body-frame noise, the convention of the statistics below).

**Statistics** (:func:`manifold_statistics`, seed 004 §12.3).  Per time step ``t`` the Karcher mean
``μ_t = argmin Σ_i ‖Log_μ(x_{i,t})‖²`` by the seed's Gauss–Newton iteration ``u = 1/N Σ Log_μ(x_i)``,
``μ ← Exp_μ(u)``, and the tangent covariance ``Σ_t = 1/(N−1) Σ_i Log_μ(x_i) Log_μ(x_i)ᵀ``.  All T time
steps (and any leading batch dims) run as one batch of :func:`torchlie.manifolds.fit_gaussian`: one
Gauss–Newton loop, no loop over time.  Conventions (torchlie's): on SO(3)/SE(3)
``Log_μ(x) = Log(μ⁻¹ x)`` (the *right*/body convention, ``x = μ·Exp(ε)``), SE(3) tangent ``[ρ, ω]``; on
SE(3), which has no bi-invariant metric, the fixed point is the group (exponential) barycenter; on SPD the
affine-invariant ``Log`` in whitened Mandel coordinates; on S³ the sphere ``Log`` (Eq. 181) as an ambient
4-vector, so Σ is ``(4, 4)`` of rank 3 with ``Σ μ = 0``; for ``q = μ ⊗ exp(ω/2)`` it is
``Log_μ(q) = μ ⊗ (0, ω/2)``, i.e. ``Σ_S³ = ¼ M Σ_ω Mᵀ`` with ``M`` the 4×3 matrix of ``v ↦ μ ⊗ (0, v)``.
Quaternion double cover: each step's samples start aligned to one sample's hemisphere and are re-aligned
to the *current* mean's hemisphere at every Gauss–Newton step (so every ``Log`` takes the short way, a
rotation angle ≤ π: the SO(3) Karcher iteration in quaternion form); ``converged`` is the optimality
residual checked at the returned mean with that final alignment, and Σ uses it too.  The mean's sign is
then made continuous over time and fixed by making the largest-magnitude component of ``μ_0`` positive —
so ``q`` and ``−q`` inputs give identical statistics.  On SE(3) the tolerance is relative to the
translation scale (:func:`manifold_statistics`).

**Tracking** (:func:`track_mean`).  The mean path is the reference of the seed-003 error-state MPC
(:func:`controllers.manifold_mpc.error_system`, Eq. 20–23, on a kinematic system: :class:`BodyRateSO3`
here, :class:`controllers.pose_mpc.BodyTwistSE3` for poses) with the *time-varying* state precision
``Q_t = (Σ_t + λI)⁻¹`` (seed 004 §2, §12.3: a reference "with an associated required precision"): the
controller is stiff where the demos agree and compliant where they vary (minimal intervention).
:class:`~controllers.manifold_mpc.ErrorStateMPC` holds one ``Q`` for its whole horizon; this receding
loop is the same Riccati solve of the same error system with ``Q_{k..k+N}`` per stage (with a constant
precision it equals ``ErrorStateMPC(..., solver="riccati").solve``; the tests check it).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import torch
from torch import Tensor

from controllers import riccati
from controllers.costs import QuadraticCost
from controllers.dynamics import LinearDynamics
from controllers.manifold_mpc import error_system, manifold_step, time_slice
from controllers.problem import GradMode, LQProblem
from learning.demos import Demonstrations, spatial_noise, time_warp
from torchlie import so3
from torchlie.manifolds import SE3, SO3, SPD, Sphere, fit_gaussian, hemisphere_align

__all__ = [
    "GROUPS",
    "group_manifold",
    "demo_points",
    "points_to_demos",
    "orientation_demos",
    "stiffness_demos",
    "ManifoldStatistics",
    "manifold_statistics",
    "BodyRateSO3",
    "reference_controls",
    "MeanTrackingRun",
    "track_mean",
]

GROUPS = ("SO3", "SE3", "S3", "SPD")
_DTYPES = (torch.float32, torch.float64)


# --------------------------------------------------------------------------------------------------
# groups and layouts
# --------------------------------------------------------------------------------------------------


def _group_name(group: Any, fn: str) -> str:
    if isinstance(group, str):
        if group not in GROUPS:
            raise ValueError(f"{fn}: argument 'group' must be one of {GROUPS}, got {group!r}")
        return group
    if isinstance(group, SO3):
        return "SO3"
    if isinstance(group, SE3):
        return "SE3"
    if isinstance(group, SPD):
        return "SPD"
    if isinstance(group, Sphere) and group.d == 3 and group.r == 1.0:
        return "S3"
    raise TypeError(f"{fn}: argument 'group' must be one of {GROUPS} or a torchlie manifold SO3(), SE3(), "
                    f"Sphere(3), SPD(k), got {group!r}")


def group_manifold(group: str, spd_size: int | None = None):
    """The torchlie space of a group name (module table); ``spd_size`` k is needed for ``"SPD"``."""
    fn = "group_manifold"
    g = _group_name(group, fn)
    if g == "SPD":
        if isinstance(group, SPD):
            return group
        if isinstance(spd_size, bool) or not isinstance(spd_size, int) or spd_size < 1:
            raise ValueError(f"{fn}: argument 'spd_size' must be a positive int for group 'SPD', "
                             f"got {spd_size!r}")
        return SPD(spd_size)
    return {"SO3": SO3, "SE3": SE3, "S3": lambda: Sphere(3)}[g]()


def _flat_size(g: str, M) -> int:
    return math.prod(M.point_shape)


def demo_points(demos: Demonstrations, group: str | None = None) -> Tensor:
    """The states of ``demos`` as manifold points ``(N, T, *point_shape)`` (module table for the layout;
    ``group`` defaults to ``demos.meta["group"]``).  No membership check here (the statistics check)."""
    fn = "demo_points"
    if not isinstance(demos, Demonstrations):
        raise TypeError(f"{fn}: argument 'demos' must be a Demonstrations, got {type(demos).__name__}")
    g, M = _demos_group(demos, group, fn)
    return demos.x.reshape(demos.N, demos.T, *M.point_shape)


def _demos_group(demos: Demonstrations, group, fn: str):
    if group is None:
        group = demos.meta.get("group")
        if group is None:
            raise ValueError(f"{fn}: the demos have no meta['group']; pass group= one of {GROUPS}")
    g = _group_name(group, fn)
    n = demos.n
    if g == "SPD":
        k = math.isqrt(n)
        if k * k != n:
            raise ValueError(f"{fn}: SPD demos need x (N, T, k²) (a flattened k×k matrix), got n = {n}")
        M = group if isinstance(group, SPD) else SPD(k)
        if M.n != k:
            raise ValueError(f"{fn}: argument 'group' is SPD({M.n}) but the demos hold {k}×{k} matrices")
    else:
        M = group_manifold(g)
    if _flat_size(g, M) != n:
        raise ValueError(f"{fn}: group '{g}' needs x (N, T, {_flat_size(g, M)}), got n = {n}")
    return g, M


def points_to_demos(points: Tensor, group: str, dt: float, **fields: Any) -> Demonstrations:
    """Points ``(N, T, *point_shape)`` as :class:`~learning.demos.Demonstrations` with the flat layout of
    ``group``; ``meta["group"]`` is set (``fields``: the other ``Demonstrations`` fields, ``meta`` merged)."""
    fn = "points_to_demos"
    g = _group_name(group, fn)
    if not isinstance(points, Tensor):
        raise TypeError(f"{fn}: argument 'points' must be a torch.Tensor, got {type(points).__name__}")
    k = {"SO3": 2, "SE3": 2, "S3": 1, "SPD": 2}[g]
    if points.dim() != 2 + k:
        raise ValueError(f"{fn}: argument 'points' must have shape (N, T, *point_shape) for group '{g}', "
                         f"got {tuple(points.shape)}")
    M = group_manifold(g, points.shape[-1] if g == "SPD" else None)
    if tuple(points.shape[2:]) != tuple(M.point_shape):
        raise ValueError(f"{fn}: argument 'points' must have trailing shape {tuple(M.point_shape)} for group "
                         f"'{g}', got {tuple(points.shape)}")
    meta = dict(fields.pop("meta", {}))
    meta["group"] = g
    return Demonstrations(x=points.reshape(points.shape[0], points.shape[1], -1), dt=dt, meta=meta, **fields)


# --------------------------------------------------------------------------------------------------
# synthetic demos
# --------------------------------------------------------------------------------------------------


def _default_tangent(g: str, s: Tensor) -> Tensor:
    """The default smooth reference tangent path ``ξ(s)`` at the base point, ``(T, m)``."""
    a, b = torch.sin(math.pi * s), 1 - torch.cos(math.pi * s)
    w = torch.stack([0.8 * a, 0.5 * b, 1.4 * s], -1)                       # ‖ω‖ ≤ 1.9 rad < π
    if g == "SE3":
        rho = torch.stack([0.5 * s, 0.2 * a, 0.15 * b], -1)
        return torch.cat([rho, w], -1)
    return w


def _envelope(envelope, s: Tensor, fn: str) -> Tensor:
    if envelope is None:
        return torch.ones_like(s)
    if callable(envelope) and not isinstance(envelope, Tensor):
        e = envelope(s)
    else:
        e = envelope
    if not isinstance(e, Tensor) or e.shape != s.shape:
        raise ValueError(f"{fn}: argument 'envelope' must be a tensor (T,) = {tuple(s.shape)} or a callable "
                         f"of the phase s (T,) returning one")
    e = e.to(dtype=s.dtype, device=s.device)
    if not bool((torch.isfinite(e) & (e >= 0)).all()):
        raise ValueError(f"{fn}: argument 'envelope' must be finite and non-negative")
    return e


def _variability(ref_tangent: Tensor, n_demos: int, dt: float, generator: torch.Generator, noise, warp: float,
                 envelope, pin_ends: bool, n_basis: int, m: int, fn: str) -> tuple[Tensor, Tensor]:
    """Warped tangent paths ``(N, T, d)`` and smooth tangent offsets ``(N, T, m)`` (learning.demos)."""
    if isinstance(n_demos, bool) or not isinstance(n_demos, int) or n_demos < 1:
        raise ValueError(f"{fn}: argument 'n_demos' must be a positive int, got {n_demos!r}")
    T = ref_tangent.shape[0]
    path = Demonstrations(x=ref_tangent.expand(n_demos, *ref_tangent.shape).clone(), dt=dt)
    path = _renaming(("strength", "warp", fn), time_warp, path, warp, generator)
    zero = Demonstrations(x=ref_tangent.new_zeros(n_demos, T, m), dt=dt)
    eps = _renaming(("scale", "noise", fn), spatial_noise, zero, noise, generator, n_basis=n_basis,
                    pin_ends=pin_ends).x
    s = torch.linspace(0.0, 1.0, T, dtype=ref_tangent.dtype, device=ref_tangent.device)
    return path.x, eps * _envelope(envelope, s, fn)[:, None]


def _renaming(names: tuple[str, str, str], f: Callable, *args: Any, **kwargs: Any):
    """``f(*args, **kwargs)`` (a :mod:`learning.demos` helper); an error about its argument ``theirs`` is
    re-raised naming this function's argument ``ours`` (``names = (theirs, ours, fn)``)."""
    theirs, ours, fn = names
    try:
        return f(*args, **kwargs)
    except (TypeError, ValueError) as e:
        if f"'{theirs}'" not in str(e):
            raise
        raise type(e)(f"{fn}: " + str(e).replace(f"'{theirs}'", f"argument '{ours}'")) from e


def _noise_record(noise) -> float | list[float]:
    if isinstance(noise, (int, float)):
        return float(noise)
    return [float(v) for v in (noise.reshape(-1).tolist() if isinstance(noise, Tensor) else noise)]


def _check_common(T: int, dtype, generator, fn: str) -> None:
    if isinstance(T, bool) or not isinstance(T, int) or T < 2:
        raise ValueError(f"{fn}: argument 'T' must be an int >= 2, got {T!r}")
    if dtype not in _DTYPES:
        raise TypeError(f"{fn}: argument 'dtype' must be float32 or float64, got {dtype}")
    if not isinstance(generator, torch.Generator):
        raise TypeError(f"{fn}: argument 'generator' must be a torch.Generator (explicit randomness)")


def _tangent_path(xi, T: int, m: int, dtype, fn: str) -> Tensor:
    if not isinstance(xi, Tensor) or tuple(xi.shape) != (T, m) or not xi.dtype.is_floating_point:
        raise ValueError(f"{fn}: argument 'tangent_path' must be a float tensor ({T}, {m}), got "
                         f"{getattr(xi, 'shape', type(xi).__name__)}")
    if not bool(torch.isfinite(xi).all()):
        raise ValueError(f"{fn}: argument 'tangent_path' must be finite (it has NaN/inf entries)")
    return xi.to(dtype)


def _base_point(M, base, dtype, fn: str) -> Tensor:
    ps = tuple(M.point_shape)
    if not isinstance(base, Tensor) or tuple(base.shape) != ps or not base.dtype.is_floating_point:
        raise ValueError(f"{fn}: argument 'base' must be one float tensor {ps} (a single base point), got "
                         f"{tuple(base.shape) if isinstance(base, Tensor) else type(base).__name__}")
    return _on_manifold(M, base.to(dtype), "base", fn)


def orientation_demos(n_demos: int = 8, T: int = 50, *, generator: torch.Generator, group: str = "SO3",
                      dt: float = 0.02, noise: float | Sequence[float] = 0.12, warp: float = 0.2,
                      envelope: Tensor | Callable[[Tensor], Tensor] | None = None, pin_ends: bool = False,
                      n_basis: int = 5, tangent_path: Tensor | None = None, base: Tensor | None = None,
                      random_signs: bool = False, dtype: torch.dtype = torch.float64) -> Demonstrations:
    """``n_demos`` orientation (``"SO3"``, ``"S3"``) or pose (``"SE3"``) demos of ``T`` steps (module doc).

    Reference ``x*(s) = b·Exp(ξ(s))`` with ``tangent_path`` ξ ``(T, m)`` (m = 3, or 6 ``[ρ, ω]`` for SE(3);
    default a smooth path of at most 1.9 rad) and ``base`` b (default identity; a rotation matrix, or a
    4×4 pose for SE(3)); demo ``i`` is ``x*(τ_i(t))·Exp(ε_i(t))`` with ``τ_i`` from
    :func:`~learning.demos.time_warp` (``warp``) and ``ε_i`` from :func:`~learning.demos.spatial_noise`
    (``noise``: the pointwise std in rad / m, one value or one per tangent coordinate; ``pin_ends``,
    ``n_basis`` passed on) times ``envelope(s)`` ``(T,)`` (a tensor or a callable of the phase s ∈ [0, 1]).
    ``"S3"`` stores the unit quaternions of the SO(3) demos, with random signs (q ≡ −q) when
    ``random_signs``.  The noise-free reference (unwarped) is ``frames["reference"]`` (N, T, n), repeated
    per demo.  Randomness from ``generator`` only.
    """
    fn = "orientation_demos"
    g = _group_name(group, fn)
    if g == "SPD":
        raise ValueError(f"{fn}: argument 'group' must be 'SO3', 'SE3' or 'S3' (stiffness_demos makes SPD "
                         "demos)")
    _check_common(T, dtype, generator, fn)
    M = SE3() if g == "SE3" else SO3()
    m = M.dim
    s = torch.linspace(0.0, 1.0, T, dtype=dtype)
    xi = _default_tangent(g, s) if tangent_path is None else _tangent_path(tangent_path, T, m, dtype, fn)
    b = M.identity(dtype=dtype) if base is None else _base_point(M, base, dtype, fn)
    xi_w, eps = _variability(xi, n_demos, dt, generator, noise, warp, envelope, pin_ends, n_basis, m, fn)
    pts = M.exp_at(M.exp_at(b, xi_w), eps)                                     # (N, T, *ps)
    ref = M.exp_at(b, xi).expand(n_demos, *pts.shape[1:])
    if g == "S3":
        pts, ref = so3.to_quaternion(pts), so3.to_quaternion(ref)
        if random_signs:
            flip = torch.rand(n_demos, T, 1, generator=generator, dtype=torch.float64) < 0.5
            pts = torch.where(flip, -pts, pts)
    meta = {"source": fn, "noise": _noise_record(noise), "warp": float(warp)}
    return points_to_demos(pts, g, dt, frames={"reference": ref.reshape(n_demos, T, -1).clone()}, meta=meta)


def stiffness_demos(n_demos: int = 8, T: int = 50, *, generator: torch.Generator, start: Tensor | None = None,
                    end: Tensor | None = None, dt: float = 0.02, noise: float | Sequence[float] = 0.2,
                    warp: float = 0.2, envelope: Tensor | Callable[[Tensor], Tensor] | None = None,
                    pin_ends: bool = False, n_basis: int = 5,
                    dtype: torch.dtype = torch.float64) -> Demonstrations:
    """``n_demos`` demos of a k×k stiffness (or manipulability) matrix along ``T`` steps, group ``"SPD"``.

    Reference: the affine-invariant geodesic ``K*(s) = Exp_{K_a}(s·Log_{K_a}(K_b))`` from ``start`` K_a to
    ``end`` K_b (defaults: two 3×3 stiffness matrices in N/m, 200–900); demo ``i`` is
    ``Exp_{K*(τ_i(t))}(ε_i(t))`` with ε in the whitened Mandel coordinates (``noise``: std of a relative,
    log-scale perturbation; ``warp``, ``envelope``, ``pin_ends``, ``n_basis`` as in
    :func:`orientation_demos`).  ``frames["reference"]`` holds K*(s_t) per demo.
    """
    fn = "stiffness_demos"
    _check_common(T, dtype, generator, fn)
    if start is None:
        start = torch.tensor([[400.0, 100.0, 0.0], [100.0, 300.0, 50.0], [0.0, 50.0, 200.0]])
    if end is None:
        end = torch.tensor([[900.0, -150.0, 0.0], [-150.0, 250.0, 0.0], [0.0, 0.0, 600.0]])
    for name, K in (("start", start), ("end", end)):
        if not isinstance(K, Tensor) or K.dim() != 2:
            raise ValueError(f"{fn}: argument '{name}' must be a k×k SPD tensor, got "
                             f"{getattr(K, 'shape', type(K).__name__)}")
    if start.shape != end.shape:
        raise ValueError(f"{fn}: arguments 'start' and 'end' must have one shape, got {tuple(start.shape)} "
                         f"and {tuple(end.shape)}")
    M = SPD(start.shape[-1])
    Ka = M.check_point(start.to(dtype), "start", fn)
    Kb = M.check_point(end.to(dtype), "end", fn)
    s = torch.linspace(0.0, 1.0, T, dtype=dtype)
    xi = s[:, None] * M.log_at(Ka, Kb)                                        # (T, m): the geodesic
    xi_w, eps = _variability(xi, n_demos, dt, generator, noise, warp, envelope, pin_ends, n_basis,
                             M.tangent_size, fn)
    pts = M.exp_at(M.exp_at(Ka, xi_w, check=False), eps, check=False)
    pts = 0.5 * (pts + pts.mT)
    ref = M.exp_at(Ka, xi, check=False).expand(n_demos, T, *M.point_shape)
    meta = {"source": fn, "noise": _noise_record(noise), "warp": float(warp)}
    frames = {"reference": ref.reshape(n_demos, T, -1).clone()}
    return points_to_demos(pts, "SPD", dt, frames=frames, meta=meta)


# --------------------------------------------------------------------------------------------------
# statistics
# --------------------------------------------------------------------------------------------------


class ManifoldStatistics(NamedTuple):
    """Per-time-step Gaussians on a manifold (:func:`manifold_statistics`); batch ``(*B,)``.

    mean ``(*B, T, *point_shape)``; covariance ``(*B, T, m, m)`` in the tangent representation at the mean
    (module docstring); iterations ``(*B, T)`` Gauss–Newton steps; converged ``(*B, T)`` bool (the
    Gauss–Newton step ``1/N Σ Log_μ(x_i)``, i.e. the optimality residual, ≤ tol; on S³ checked at the
    returned mean); group: the group name; manifold: the torchlie space.
    """

    mean: Tensor
    covariance: Tensor
    iterations: Tensor
    converged: Tensor
    group: str
    manifold: Any


def _canonical_sign(mu: Tensor) -> Tensor:
    """±1 ``(*B, T, 1)``: the mean quaternions' signs continuous over time, with the largest-magnitude
    component of the first one positive (a rule invariant under q → −q)."""
    d = (mu[..., 1:, :] * mu[..., :-1, :]).sum(-1)
    step = torch.where(d < 0, -1.0, 1.0).to(mu.dtype)
    one = torch.ones(*mu.shape[:-2], 1, dtype=mu.dtype, device=mu.device)
    cont = torch.cat([one, torch.cumprod(step, -1)], -1)                                # (*B, T)
    first = mu[..., 0, :] * cont[..., :1]
    big = first.gather(-1, first.abs().argmax(-1, keepdim=True))
    s0 = torch.where(big < 0, -1.0, 1.0).to(mu.dtype)                                  # (*B, 1)
    return (cont * s0).unsqueeze(-1)


def _check_solver_options(max_iter, tol, unbiased, fn: str) -> None:
    if isinstance(max_iter, bool) or not isinstance(max_iter, int) or max_iter < 1:
        raise ValueError(f"{fn}: argument 'max_iter' must be an int >= 1, got {max_iter!r}")
    if tol is not None and (isinstance(tol, bool) or not isinstance(tol, (int, float))
                            or not (0 < tol < math.inf)):
        raise ValueError(f"{fn}: argument 'tol' must be None or a positive finite float, got {tol!r}")
    if not isinstance(unbiased, bool):
        raise TypeError(f"{fn}: argument 'unbiased' must be a bool, got {unbiased!r}")


def _statistics_points(demos, group, fn: str):
    """``(g, M, points (*B, N, T, *ps))`` from :func:`manifold_statistics`'s ``demos``/``group``."""
    if isinstance(demos, Demonstrations):
        g, M = _demos_group(demos, group, fn)
        return g, M, demo_points(demos, g if not isinstance(group, SPD) else group)
    if not isinstance(demos, Tensor):
        raise TypeError(f"{fn}: argument 'demos' must be a Demonstrations or a tensor of points, got "
                        f"{type(demos).__name__}")
    if group is None:
        raise ValueError(f"{fn}: argument 'group' is needed with a tensor of points (one of {GROUPS})")
    g = _group_name(group, fn)
    M = group_manifold(group, demos.shape[-1] if g == "SPD" and demos.dim() >= 2 else None)
    k = len(M.point_shape)
    if demos.dim() < k + 2 or tuple(demos.shape[demos.dim() - k:]) != tuple(M.point_shape):
        shape = ", ".join(map(str, M.point_shape))
        raise ValueError(f"{fn}: argument 'demos' must be points (*B, N, T, {shape}) for group '{g}', "
                         f"got {tuple(demos.shape)}")
    return g, M, demos


def _on_manifold(M, x: Tensor, name: str, fn: str) -> Tensor:
    """``M.check_point`` with an error that names only this function's arguments (no ``project``)."""
    try:
        return M.check_point(x, name, fn)
    except ValueError as e:
        msg = str(e).split("; pass project=True")[0]
        raise ValueError(f"{msg}; project the points onto the manifold before calling {fn}") from e


def _sample_cov(L: Tensor, unbiased: bool) -> Tensor:
    """``1/(N−1) Σ_i L_i L_iᵀ`` (``1/N`` unless ``unbiased``) of tangent vectors ``(*B, N, m)``."""
    n = L.shape[-2]
    S = L.mT @ L / (n - 1 if unbiased else n)
    return 0.5 * (S + S.mT)


def _s3_statistics(M, x: Tensor, max_iter: int, tol: float | None, unbiased: bool):
    """Karcher mean on S³ of ``x (*B, N, 4)`` with the samples re-aligned to the current mean's hemisphere
    at every Gauss–Newton step: the SO(3) Karcher iteration in quaternion form.  Converged where the
    residual ``‖1/N Σ Log_μ(±x_i)‖`` at the *returned* μ, with the signs aligned to it, is ≤ tol."""
    tol = torch.finfo(x.dtype).eps ** 0.75 if tol is None else float(tol)
    x = hemisphere_align(x, x[..., :1, :])
    mu = x[..., 0, :]
    batch = mu.shape[:-1]
    iterations = torch.zeros(batch, dtype=torch.int64, device=x.device)
    converged = torch.zeros(batch, dtype=torch.bool, device=x.device)
    failed = torch.zeros_like(converged)
    for i in range(max_iter + 1):
        active = ~(converged | failed)
        if not bool(active.any()):
            break
        u = M.log_at(mu.unsqueeze(-2), hemisphere_align(x, mu.unsqueeze(-2)), check=False).mean(-2)
        finite = torch.isfinite(u).all(-1)
        failed = failed | (active & ~finite)
        converged = converged | (active & finite & (torch.linalg.vector_norm(u, dim=-1) <= tol))
        step = active & finite & ~converged
        if i == max_iter or not bool(step.any()):
            continue
        u = torch.where(step.unsqueeze(-1), u, torch.zeros_like(u))
        mu = torch.where(step.unsqueeze(-1), M.exp_at(mu, u, check=False), mu)
        iterations = iterations + step.to(torch.int64)
    L = M.log_at(mu.unsqueeze(-2), hemisphere_align(x, mu.unsqueeze(-2)), check=False)
    return mu, _sample_cov(L, unbiased), iterations, converged


def _se3_statistics(M, x: Tensor, max_iter: int, tol: float | None, unbiased: bool):
    """:func:`fit_gaussian` on SE(3) points ``(*B, N, 4, 4)`` in translation-normalized coordinates: the
    translations divided by ``s = max(1, max_i ‖t_i‖)`` per element (``(R, t) ↦ (R, t/s)`` is a group
    automorphism, ``Log`` maps to ``[ρ/s, ω]``), so the step tolerance is relative to the translation scale;
    mean and covariance are mapped back exactly."""
    s = torch.clamp(torch.linalg.vector_norm(x[..., :3, 3], dim=-1).amax(-1), min=1.0)     # (*B,)
    one = torch.ones_like(s)
    col = torch.stack([1 / s, 1 / s, 1 / s, one], -1).unsqueeze(-1)                       # (*B, 4, 1)
    W = torch.cat([torch.ones(*s.shape, 4, 3, dtype=x.dtype, device=x.device), col], -1)  # (*B, 4, 4)
    res = fit_gaussian(M, x * W.unsqueeze(-3), max_iter=max_iter, tol=tol, unbiased=unbiased)
    d = torch.stack([s, s, s, one, one, one], -1)                                          # (*B, 6)
    cov = res.covariance * (d.unsqueeze(-1) * d.unsqueeze(-2))
    return res.mean / W, cov, res.iterations, res.converged


def manifold_statistics(demos: Demonstrations | Tensor, group: str | Any | None = None, *, max_iter: int = 30,
                        tol: float | None = None, unbiased: bool = True) -> ManifoldStatistics:
    """Karcher mean and tangent covariance per time step (seed 004 §12.3; module docstring).

    demos: a :class:`~learning.demos.Demonstrations` (flat layout of the module table; ``group`` defaults
    to ``meta["group"]``), or points ``(*B, N, T, *point_shape)`` with ``group`` given (a name of
    :data:`GROUPS` or the torchlie space).  All ``(*B, T)`` means are one batched Gauss–Newton solve
    (:func:`torchlie.manifolds.fit_gaussian`; ``max_iter`` an int ≥ 1; ``tol`` a positive float, default
    eps^0.75 of the dtype, on the norm of the step / optimality residual ``1/N Σ Log_μ(x_i)``).  On SE(3)
    the residual is measured with the translations divided by ``s = max(1, max_i ‖t_i‖)`` of each step's
    samples, so the tolerance is *relative* to the data's translation scale (absolute for ``‖t‖ ≤ 1``):
    float32 poses with translations of 1000 converge like those of 1.  Σ uses ``1/(N−1)``
    (``unbiased=False``: ``1/N``; N = 1 needs it; ``unbiased`` must be a bool).  On S³ ``converged`` is
    the residual checked at the returned mean with every sample aligned to its hemisphere, i.e. a Karcher
    mean of the rotations.  Points off the manifold raise ``ValueError`` naming the batch index.
    Differentiable in the points.
    """
    fn = "manifold_statistics"
    _check_solver_options(max_iter, tol, unbiased, fn)
    g, M, pts = _statistics_points(demos, group, fn)
    if pts.dtype not in _DTYPES:
        raise TypeError(f"{fn}: the points must be float32 or float64, got {pts.dtype}")
    k = len(M.point_shape)
    n_samples = pts.shape[pts.dim() - k - 2]
    if n_samples == 0:
        raise ValueError(f"{fn}: argument 'demos' holds no demonstrations (N = 0)")
    if unbiased and n_samples < 2:
        raise ValueError(f"{fn}: the unbiased covariance needs N >= 2 demos, got {n_samples}; pass "
                         "unbiased=False")
    pts = _on_manifold(M, pts, "demos", fn)                                  # index (*B, N, T) if off
    x = pts.movedim(pts.dim() - k - 2, pts.dim() - k - 1)                   # (*B, T, N, *ps)
    if g == "S3":
        mean, cov, iterations, converged = _s3_statistics(M, x, max_iter, tol, unbiased)
        mean = mean * _canonical_sign(mean)                                  # Σ is even in the sign
        return ManifoldStatistics(mean, cov, iterations, converged, g, M)
    if g == "SE3":
        return ManifoldStatistics(*_se3_statistics(M, x, max_iter, tol, unbiased), g, M)
    res = fit_gaussian(M, x, max_iter=max_iter, tol=tol, unbiased=unbiased)
    return ManifoldStatistics(res.mean, res.covariance, res.iterations, res.converged, g, M)


# --------------------------------------------------------------------------------------------------
# tracking the mean with the error-state MPC
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class BodyRateSO3:
    """A rotation driven by its body angular velocity: ``R ⊕ Δt ω = R·Exp(Δt ω)`` on SO(3) (``f(R, ω) = ω``;
    the SO(3) counterpart of :class:`controllers.pose_mpc.BodyTwistSE3`)."""

    dt: float
    m = 3
    n = 3

    @property
    def manifold(self) -> SO3:
        return SO3()

    def f(self, x: Tensor, u: Tensor) -> Tensor:
        return u

    def f_jacobians(self, x: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        eye = torch.eye(3, dtype=u.dtype, device=u.device)
        return u.new_zeros(*u.shape, 3), eye.expand(*u.shape[:-1], 3, 3)


def reference_controls(manifold, mean: Tensor, dt: float) -> Tensor:
    """``u_t = Log_{μ_t}(μ_{t+1}) / Δt`` ``(*B, T-1, m)``: the body velocities that take a kinematic system
    (``f(x, u) = u``, :class:`BodyRateSO3`, ``BodyTwistSE3``) exactly along the mean path ``(*B, T, *ps)``."""
    k = len(manifold.point_shape)
    a = mean[(..., slice(0, -1)) + (slice(None),) * k]
    b = mean[(..., slice(1, None)) + (slice(None),) * k]
    return manifold.log_at(a, b) / dt


@dataclass(frozen=True, eq=False)
class MeanTrackingRun:
    """A closed-loop run of :func:`track_mean` over K steps.

    Attributes:
        x: ``(*B, K+1, *point_shape)`` the states.
        u: ``(*B, K, m)`` the applied controls.
        error: ``(*B, K+1, n)`` ``x_k ⊟ μ_k`` (tangent at the mean, the covariance's convention).
        gain: ``(*B, K, m, n)`` the feedback gain of each solve's first stage (``δu = K δx + k``).
        precision: ``(*B, max(T, K+N+1), n, n)`` the stage weights ``(Σ_t + λI)⁻¹`` (the last one repeated
            past the end of the demos).
        reason: ``(*B, K)`` the solves' :class:`~controllers.problem.Reason` codes.
    """

    x: Tensor
    u: Tensor
    error: Tensor
    gain: Tensor
    precision: Tensor
    reason: Tensor


def _pad_time(t: Tensor, k: int, extra: int) -> Tensor:
    """Repeat the last time entry (time dim at ``-k-1``) ``extra`` times."""
    last = t[(..., slice(-1, None)) + (slice(None),) * k]
    reps = [1] * t.dim()
    reps[t.dim() - k - 1] = extra
    return torch.cat([t, last.repeat(*reps)], t.dim() - k - 1)


def _track_tensors(mean, covariance, x0, u_ref, fn: str) -> None:
    """Types, dtypes and devices: every tensor argument float32/float64 with the mean's dtype and device."""
    for name, t in (("mean", mean), ("covariance", covariance), ("x0", x0), ("u_ref", u_ref)):
        if name == "u_ref" and t is None:
            continue
        if not isinstance(t, Tensor) or t.dtype not in _DTYPES:
            raise TypeError(f"{fn}: argument '{name}' must be a float32/float64 tensor, got "
                            f"{getattr(t, 'dtype', type(t).__name__)}")
        if t.dtype != mean.dtype:
            raise TypeError(f"{fn}: argument '{name}' has dtype {t.dtype} but 'mean' has {mean.dtype}; "
                            "they must match (nothing is cast silently)")
        if t.device != mean.device:
            raise ValueError(f"{fn}: argument '{name}' is on {t.device} but 'mean' is on {mean.device}")


def _track_shapes(M, m: int, mean: Tensor, covariance: Tensor, x0: Tensor, u_ref, fn: str):
    """Shapes checked and broadcast like torch: ``(T, mean, covariance, x0, u_ref)`` with one batch ``B``."""
    n, k, ps = M.dim, len(M.point_shape), tuple(M.point_shape)
    if mean.dim() < k + 1 or tuple(mean.shape[mean.dim() - k:]) != ps or mean.shape[mean.dim() - k - 1] < 2:
        raise ValueError(f"{fn}: argument 'mean' must be (*B, T, {', '.join(map(str, ps))}) with "
                         f"T >= 2, got {tuple(mean.shape)}")
    T = mean.shape[mean.dim() - k - 1]
    if covariance.dim() < 3 or covariance.shape[-2:] != (n, n) or covariance.shape[-3] != T:
        raise ValueError(f"{fn}: argument 'covariance' must be (*B, {T}, {n}, {n}), got "
                         f"{tuple(covariance.shape)}")
    if x0.dim() < k or tuple(x0.shape[x0.dim() - k:]) != ps:
        raise ValueError(f"{fn}: argument 'x0' must be (*B, {', '.join(map(str, ps))}), got "
                         f"{tuple(x0.shape)}")
    if u_ref is not None and (u_ref.dim() < 2 or u_ref.shape[-2:] != (T - 1, m)):
        raise ValueError(f"{fn}: argument 'u_ref' must be (*B, {T - 1}, {m}), got {tuple(u_ref.shape)}")
    batches = {"mean": mean.shape[:-k - 1], "covariance": covariance.shape[:-3],
               "x0": x0.shape[:x0.dim() - k]}
    if u_ref is not None:
        batches["u_ref"] = u_ref.shape[:-2]
    try:
        B = torch.broadcast_shapes(*batches.values())
    except RuntimeError:
        got = ", ".join(f"'{a}' {tuple(b)}" for a, b in batches.items())
        raise ValueError(f"{fn}: the batch shapes of the arguments must broadcast, got {got}") from None
    mean = mean.expand(*B, *mean.shape[-k - 1:])
    u_ref = None if u_ref is None else u_ref.expand(*B, T - 1, m)
    return T, mean, covariance.expand(*B, T, n, n), x0.expand(*B, *ps), u_ref


def _check_covariance(cov: Tensor, fn: str) -> None:
    """``ValueError`` unless every finite ``(n, n)`` block is symmetric (relative asymmetry ≤ √eps) and
    positive semi-definite (smallest eigenvalue ≥ −√eps·largest magnitude).  Blocks with a NaN/inf entry
    are left to the solve: they only spoil their own batch element."""
    tol = math.sqrt(torch.finfo(cov.dtype).eps)
    fin = torch.isfinite(cov).all(-1).all(-1)
    C = torch.where(fin[..., None, None], cov, torch.zeros_like(cov))
    scale = torch.clamp(C.abs().amax(dim=(-1, -2)), min=torch.finfo(C.dtype).tiny)
    asym = (C - C.mT).abs().amax(dim=(-1, -2)) / scale
    if bool((asym > tol).any()):
        raise ValueError(f"{fn}: argument 'covariance' must be symmetric: relative asymmetry "
                         f"{float(asym.max()):.3g} > {tol:.2g}")
    lam = torch.linalg.eigvalsh(0.5 * (C + C.mT))
    bad = lam[..., 0] < -tol * lam.abs().amax(-1)
    if bool(bad.any()):
        raise ValueError(f"{fn}: argument 'covariance' must be positive semi-definite: smallest eigenvalue "
                         f"{float(lam[..., 0].min()):.3g} (batch index {tuple(bad.nonzero()[0].tolist())})")


def _track_R(R, m: int, mean: Tensor, fn: str) -> Tensor:
    if isinstance(R, (int, float)) and not isinstance(R, bool):
        if not (0 < R < math.inf):
            raise ValueError(f"{fn}: argument 'R' must be positive, got {R!r}")
        return float(R) * torch.eye(m, dtype=mean.dtype, device=mean.device)
    if not isinstance(R, Tensor) or R.shape not in ((m,), (m, m)):
        raise ValueError(f"{fn}: argument 'R' must be a positive float or a ({m},)/({m}, {m}) tensor, got "
                         f"{getattr(R, 'shape', R)!r}")
    if R.dtype != mean.dtype or R.device != mean.device:
        raise TypeError(f"{fn}: argument 'R' has dtype {R.dtype} on {R.device} but 'mean' has {mean.dtype} "
                        f"on {mean.device}; they must match (nothing is cast silently)")
    Rm = torch.diag_embed(R) if R.dim() == 1 else R
    if not bool(torch.isfinite(Rm).all()) or not torch.allclose(Rm, Rm.mT) or \
            not bool((torch.linalg.eigvalsh(Rm) > 0).all()):
        raise ValueError(f"{fn}: argument 'R' must be symmetric positive definite")
    return Rm


def _track_args(system, mean: Tensor, covariance: Tensor, x0: Tensor, horizon, R, regularization, u_ref,
                steps, fn: str):
    """:func:`track_mean`'s arguments checked and broadcast to one batch ``B``:
    ``(M, n, m, k, T, steps, R (m, m), mean, covariance, x0, u_ref)``."""
    M = getattr(system, "manifold", None)
    if M is None or not getattr(M, "has_boxplus", False) or not hasattr(system, "f"):
        raise TypeError(f"{fn}: argument 'system' must be a ManifoldSystem (manifold with ⊞/⊟/⊕, m, dt, f), "
                        f"got {type(system).__name__}")
    n, m, k = M.dim, int(system.m), len(M.point_shape)
    _track_tensors(mean, covariance, x0, u_ref, fn)
    T, mean, covariance, x0, u_ref = _track_shapes(M, m, mean, covariance, x0, u_ref, fn)
    if isinstance(horizon, bool) or not isinstance(horizon, int) or horizon < 1:
        raise ValueError(f"{fn}: argument 'horizon' must be a positive int, got {horizon!r}")
    if isinstance(regularization, bool) or not isinstance(regularization, (int, float)) or \
            not (0 < regularization < math.inf):
        raise ValueError(f"{fn}: argument 'regularization' must be a positive finite float, got "
                         f"{regularization!r}")
    steps = T - 1 if steps is None else steps
    if isinstance(steps, bool) or not isinstance(steps, int) or not (1 <= steps <= T - 1):
        raise ValueError(f"{fn}: argument 'steps' must be an int in [1, {T - 1}], got {steps!r}")
    Rm = _track_R(R, m, mean, fn)
    _check_covariance(covariance, fn)
    M.check(mean, "mean")
    M.check(x0, "x0")
    if u_ref is None:
        u_ref = reference_controls(M, mean, system.dt)
    elif not bool(torch.isfinite(u_ref).all()):
        raise ValueError(f"{fn}: argument 'u_ref' must be finite (it has NaN/inf entries)")
    return M, n, m, k, T, steps, Rm, mean, covariance, x0, u_ref


def _stage_data(mean: Tensor, covariance: Tensor, u_ref: Tensor, regularization: float, k: int, T: int,
                last: int) -> tuple[Tensor, Tensor, Tensor]:
    """Mean ``(*B, L+1, *ps)``, precisions ``(Σ_t + λI)⁻¹`` ``(*B, L+1, n, n)`` and controls
    ``(*B, L, m)`` up to stage ``L = max(last, T-1)``: the last mean/precision and a zero control held."""
    n = covariance.shape[-1]
    eye = torch.eye(n, dtype=mean.dtype, device=mean.device)
    prec = torch.linalg.inv(0.5 * (covariance + covariance.mT) + regularization * eye)
    prec = 0.5 * (prec + prec.mT)
    pad = last + 1 - T
    if pad > 0:
        mean, prec = _pad_time(mean, k, pad), _pad_time(prec, 2, pad)
    zeros = u_ref.new_zeros(*u_ref.shape[:-2], max(last - (T - 1), 0), u_ref.shape[-1])
    return mean, prec, torch.cat([u_ref, zeros], -2)


def track_mean(system, mean: Tensor, covariance: Tensor, x0: Tensor, *, horizon: int = 10,
               R: Tensor | float = 1e-2, regularization: float = 1e-4, u_ref: Tensor | None = None,
               steps: int | None = None, grad: GradMode | str = GradMode.IMPLICIT) -> MeanTrackingRun:
    """Track the demos' mean from ``x0`` with the error-state MPC and per-step precisions (module docstring).

    At step k the error system (seed 003 Eq. 20–23, :func:`~controllers.manifold_mpc.error_system`) is
    linearized about the mean window ``μ_k … μ_{k+N}`` with the reference controls; the LQ problem
    ``min Σ_j ‖δx_j‖²_{Q_{k+j}} + ‖δu_j‖²_R`` with ``Q_t = (Σ_t + λI)⁻¹`` (λ = ``regularization``, in squared
    tangent units: a zero-variance step gets precision 1/λ) is solved by the Riccati recursion
    (:func:`controllers.riccati.solve`), ``u = ū_k + δu_0`` is applied and the system moves on
    (:func:`~controllers.manifold_mpc.manifold_step`).  Beyond the end the mean, the last precision and a
    zero control are held.

    system: a :class:`~controllers.manifold_mpc.ManifoldSystem` on the mean's manifold (e.g.
    :class:`BodyRateSO3`, ``BodyTwistSE3``); mean ``(*B, T, *point_shape)``; covariance ``(*B, T, n, n)``
    (e.g. :func:`manifold_statistics`); x0 ``(*B, *point_shape)``; R a float (times I) or ``(m,)``/``(m, m)``;
    u_ref ``(*B, T-1, m)`` finite (default :func:`reference_controls`, exact for ``f(x, u) = u``); steps
    default T-1.  The batch shapes ``*B`` of mean, covariance, x0 and u_ref broadcast like torch (e.g. one
    start for a batch of means); incompatible ones raise ``ValueError``.  All tensors, R included, must
    have the mean's dtype and device (``TypeError`` otherwise; nothing is cast).  The covariance must be
    symmetric positive semi-definite (relative asymmetry and negative eigenvalues within √eps of the
    dtype, else ``ValueError``); that round-off asymmetry is removed by using ``½(Σ + Σᵀ)``.  A block with
    a NaN/inf entry is not rejected: it only spoils its own batch element.
    """
    fn = "track_mean"
    M, n, m, k, T, steps, Rm, mean, covariance, x0, u_ref = _track_args(
        system, mean, covariance, x0, horizon, R, regularization, u_ref, steps, fn)
    N = horizon
    mean_p, prec_p, u_p = _stage_data(mean, covariance, u_ref, regularization, k, T, steps + N)
    x = x0
    xs, us, gains, reasons = [x0], [], [], []
    for t in range(steps):
        xr = time_slice(M, mean_p, slice(t, t + N + 1))
        ur = u_p[..., t:t + N, :]
        es = error_system(system, xr, ur)
        dx0 = M.boxminus(x, time_slice(M, xr, slice(0, 1)).squeeze(-k - 1), check=False)
        cost = QuadraticCost(Q=prec_p[..., t:t + N + 1, :, :], R=Rm, check=False)
        sol = riccati.solve(LQProblem(LinearDynamics(es.A, es.B, es.c), cost, dx0, horizon=N), grad=grad)
        u = ur[..., 0, :] + sol.u[..., 0, :]
        x = manifold_step(system, x, u)
        xs.append(x)
        us.append(u)
        gains.append(sol.K[..., 0, :, :])
        reasons.append(sol.status.reason)
    X = torch.stack(xs, -k - 1)
    mu = time_slice(M, mean_p, slice(0, steps + 1))
    err = M.boxminus(X, mu, check=False)
    return MeanTrackingRun(x=X, u=torch.stack(us, -2), error=err, gain=torch.stack(gains, -3),
                           precision=prec_p, reason=torch.stack(reasons, -1))
