"""Ground vehicle (UGV) on a curved surface, seed 003 §VII-B (Eq. 35-40): the model on 𝓜 = S × SO(2)
for the error-state (on-manifold) MPC, a synthetic road standing in for the lidar map, its local
quadratic patches (Eq. 40), a simulator of the true vehicle and the reference generation of §VII-B-4.

Conventions (SI units throughout: m, s, rad, m/s, rad/s).

* State ``x = (p, R)`` (Eq. 36b), a :class:`~torchlie.manifolds.ProductState` with ``p`` ``(*B, 3)``,
  a point of the surface S = {z = F(x, y)}, and ``R`` ``(*B, 2, 2)`` ∈ SO(2), the rotation about the
  inertial z axis taking the inertial frame to the frame x', y', z of Fig. 8 (heading θ: ``R e₁ =
  [cos θ, sin θ]``).  The body axes are ``z_b = (−F'_x, −F'_y, 1)/√(1 + gᵀg)`` (surface normal) and
  ``x_b = [R e₁; gᵀR e₁]/√(1 + (gᵀR e₁)²)`` (the unit surface tangent whose horizontal projection is
  ``R e₁``), with ``g = [F'_x, F'_y]`` at p (Eq. 37b).
* Input ``u = [v, ω]`` ``(*B, 2)`` (Eq. 36b): speed v along x_b (m/s) and yaw rate ω about z_b (rad/s).
* Continuous model (Eq. 35): ``ṗ = x_b v``, ``Ṙ = R ⌊β ω⌋`` with ``β = z ᵀz_b``.
* Discrete model (Eq. 14, 36c): ``x_{k+1} = x_k ⊕ Δt f(x_k, u_k)``, ``f = [α R e₁ v; β ω]`` ``(*B, 3)``
  with ``α = 1/√(1 + (gᵀR e₁)²)``, ``β = 1/√(1 + gᵀg)`` (Eq. 37a); ⊕ on S moves (x, y) and lifts onto
  the surface, ⊕ on SO(2) is ``R Exp(·)``.  Perturbations δx = [δp (2: x-y of S), δR (1: angle)].
* Linearization (Eq. 38-39): :meth:`UGV.f_jacobians` returns the system-specific parts
  ``∂f(x ⊞ δx, u)/∂δx`` ``(*B, 3, 3)`` and ``∂f(x, u + δu)/∂δu`` ``(*B, 3, 2)``; the manifold parts
  G_x = I₃, G_f = I₃ (Eq. 42, 46) come from ``ugv.manifold.G_x/G_f`` or ``ugv.manifold.linearize``.
  Eq. 39c as printed has a typo: its denominator is ``√((1 + gᵀg)³)`` (it reads ``gᵀp``).

The pieces.

* :class:`SyntheticRoad`: the "true" road, an analytic height field h(x, y) (Gaussian hills, a
  cosine wave and a tilt; ≈1.95 m of height variation over the 32 m × 32 m mapped area, slopes up to
  ≈20°) with exact gradient and Hessian, and :meth:`~SyntheticRoad.sample_points`, noisy 3-D points
  standing in for the FAST-LIO lidar map (no data are downloaded).
* :class:`PatchedSurface`: quadratic patches (Eq. 40) fitted by least squares to the k nearest map
  points (in x-y) of centres along the path; as a :class:`~torchlie.manifolds.Surface` it evaluates the
  patch of the nearest centre (one batched gather).  This is the MPC's model of the road; the
  analytic road is the truth the simulator uses, so model and plant differ by the fit error (and the
  model surface has small jumps where the nearest centre changes: median 2 mm, max 1 cm with the
  defaults of :func:`ugv_scenario`).
* :class:`UGV`: the system above on any :class:`~torchlie.manifolds.Surface` (patched or exact).
* :class:`UGVSimulator`: Eq. 35 integrated by RK4 on the true road (input clamping, optional speed
  scale error).  Its states lie on the *true* road; to use one with a model on the patched surface,
  project it first (``ugv.manifold.project(x)`` keeps x, y and R and lifts z onto the model surface).
* :func:`ugv_reference` (§VII-B-4): a 2-D path (default :class:`FigureEightPath`) lifted onto a
  surface at constant 3-D speed, tangent orientations, yaw rates divided by ``z ᵀz_b``; padded for the
  MPC horizon.  :func:`ugv_scenario` builds road, map, patches, models, simulator and reference at once.

Everything is batched over leading dims and follows the inputs' dtype and device; Python loops run
over time (integration substeps, Newton iterations of the offline reference), never over batch
elements.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import NamedTuple, Protocol

import torch
from torch import Tensor

from torchlie._batch import broadcast_shapes, check_same_device, check_tensor
from torchlie.manifolds import SO2, ProductManifold, ProductState, Surface, fit_quadratic_surface

__all__ = [
    "SyntheticRoad",
    "FigureEightPath",
    "PatchedSurface",
    "UGV",
    "UGVSimulator",
    "UGVReference",
    "UGVScenario",
    "ugv_reference",
    "ugv_scenario",
    "ugv_manifold",
]

D64 = torch.float64


def ugv_manifold(surface: Surface) -> ProductManifold:
    """𝓜 = S × SO(2) (Eq. 36a), components ``p`` (the surface, 2 dims) and ``R`` (1 dim): n = l = 3."""
    if not isinstance(surface, Surface):
        raise TypeError(f"ugv_manifold: argument 'surface' must be a torchlie Surface, got "
                        f"{type(surface).__name__}")
    return ProductManifold({"p": surface, "R": SO2()})


def _as_surface(obj, name: str, fn: str) -> Surface:
    """A :class:`Surface` from a Surface or anything with a ``surface()`` method (road, patches)."""
    if isinstance(obj, Surface):
        return obj
    make = getattr(obj, "surface", None)
    if callable(make):
        s = make()
        if isinstance(s, Surface):
            return s
    raise TypeError(f"{fn}: argument '{name}' must be a torchlie Surface, a SyntheticRoad or a "
                    f"PatchedSurface, got {type(obj).__name__}")


def _rot(theta: Tensor) -> Tensor:
    """Rotation matrices ``(*, 2, 2)`` of angles ``(*)``."""
    c, s = torch.cos(theta), torch.sin(theta)
    return torch.stack((c, -s, s, c), -1).unflatten(-1, (2, 2))


def _check_state_structure(x, fn: str) -> tuple[Tensor, Tensor]:
    """``(p, R)`` of a ProductState with components p ``(*, 3)`` and R ``(*, 2, 2)`` (no value checks)."""
    if not isinstance(x, ProductState):
        raise TypeError(f"{fn}: argument 'x' must be a ProductState with components ['p', 'R'] (build "
                        f"one with ugv.manifold.state(p=..., R=...)), got {type(x).__name__}")
    if list(x.keys()) != ["p", "R"]:
        raise ValueError(f"{fn}: argument 'x' has components {list(x.keys())}, expected ['p', 'R']")
    p = check_tensor(x.p, (3,), "x.p", fn)
    R = check_tensor(x.R, (2, 2), "x.R", fn)
    check_same_device(fn, **{"x.p": p, "x.R": R})
    return p, R


# ------------------------------------------------------------------------------------------------
# the synthetic road (truth)
# ------------------------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True, eq=False)
class SyntheticRoad:
    """Analytic smooth road ``h(x, y)`` (m) standing in for the lidar-mapped road of §VII-B::

        h = Σᵢ Aᵢ exp(−|q − cᵢ|² / (2 sᵢ²)) + w cos(kᵀq + φ) + bᵀq,     q = (x, y)

    with exact gradient and Hessian.  The defaults (four hills/dips of 0.6-1.1 m, width 3-3.5 m, a
    0.25 m wave of wavelength ≈11.6 m, a 2 % / 1.5 % tilt) give heights in [−0.72, 1.23] m and slopes
    up to ≈20° over the mapped area ``extent`` = (x_min, x_max, y_min, y_max) = ±16 m.  Parameters are
    Python floats (the road is immutable); evaluation follows the dtype/device of the argument.
    """

    hill_centres: tuple[tuple[float, float], ...] = ((-6.0, 2.0), (4.0, -3.0), (9.0, 4.0), (-2.0, -6.0))
    hill_heights: tuple[float, ...] = (1.1, -0.8, 0.9, 0.6)
    hill_widths: tuple[float, ...] = (3.5, 3.0, 3.0, 3.5)
    wave: tuple[float, float, float, float] = (0.25, 0.45, 0.3, 0.3)  # amplitude w, kx, ky, phase φ
    tilt: tuple[float, float] = (0.02, -0.015)  # b
    extent: tuple[float, float, float, float] = (-16.0, 16.0, -16.0, 16.0)

    def __post_init__(self):
        n = len(self.hill_centres)
        if len(self.hill_heights) != n or len(self.hill_widths) != n:
            raise ValueError("SyntheticRoad: 'hill_centres', 'hill_heights' and 'hill_widths' must have "
                             "the same length")
        if any(not (w > 0) for w in self.hill_widths):
            raise ValueError(f"SyntheticRoad: 'hill_widths' must be positive, got {self.hill_widths}")
        x0, x1, y0, y1 = self.extent
        if not (x1 > x0 and y1 > y0):
            raise ValueError(f"SyntheticRoad: 'extent' must be (x_min, x_max, y_min, y_max) with "
                             f"min < max, got {self.extent}")

    def _params(self, like: Tensor):
        kw = dict(dtype=like.dtype, device=like.device)
        C = torch.tensor(self.hill_centres, **kw).reshape(-1, 2)
        A = torch.tensor(self.hill_heights, **kw)
        S2 = torch.tensor(self.hill_widths, **kw) ** 2
        w, kx, ky, phi = self.wave
        k = torch.tensor((kx, ky), **kw)
        b = torch.tensor(self.tilt, **kw)
        return C, A, S2, w, k, phi, b

    def _hills(self, xy: Tensor, fn: str):
        check_tensor(xy, (2,), "xy", fn)
        C, A, S2, w, k, phi, b = self._params(xy)
        d = xy.unsqueeze(-2) - C  # (*, I, 2)
        E = A * torch.exp(-(d * d).sum(-1) / (2 * S2))  # (*, I)
        th = (xy * k).sum(-1) + phi
        return d, E, S2, w, k, th, b

    def height(self, xy: Tensor) -> Tensor:
        """h(x, y) ``(*,)`` (m) for ``xy`` ``(*, 2)``."""
        d, E, S2, w, k, th, b = self._hills(xy, "SyntheticRoad.height")
        return E.sum(-1) + w * torch.cos(th) + (xy * b).sum(-1)

    def gradient(self, xy: Tensor) -> Tensor:
        """∇h = [h_x, h_y] ``(*, 2)`` for ``xy`` ``(*, 2)`` (or ``(*, 3)`` points: x, y are used)."""
        xy = xy[..., :2] if xy.dim() and xy.shape[-1] == 3 else xy
        d, E, S2, w, k, th, b = self._hills(xy, "SyntheticRoad.gradient")
        return -((E / S2).unsqueeze(-1) * d).sum(-2) - w * torch.sin(th).unsqueeze(-1) * k + b

    def hessian(self, xy: Tensor) -> Tensor:
        """∇²h ``(*, 2, 2)`` for ``xy`` ``(*, 2)`` (or ``(*, 3)`` points)."""
        xy = xy[..., :2] if xy.dim() and xy.shape[-1] == 3 else xy
        d, E, S2, w, k, th, b = self._hills(xy, "SyntheticRoad.hessian")
        eye = torch.eye(2, dtype=xy.dtype, device=xy.device)
        dd = d.unsqueeze(-1) * d.unsqueeze(-2) / (S2 * S2)[..., None, None] - eye / S2[..., None, None]
        H = (E[..., None, None] * dd).sum(-3)
        return H - (w * torch.cos(th))[..., None, None] * (k.unsqueeze(-1) * k)

    def surface(self, name: str = "road") -> Surface:
        """The exact road as a :class:`~torchlie.manifolds.Surface` (analytic F, ∇F, ∇²F)."""
        return Surface(self.height, self.gradient, self.hessian, name=name)

    def sample_points(self, n: int, *, noise_std: float = 0.02, generator: torch.Generator | None = None,
                      dtype: torch.dtype = D64, device=None) -> Tensor:
        """``n`` map points ``(n, 3)`` (m): x, y uniform over ``extent``, z = h(x, y) + noise_std·N(0, 1).

        Stands in for the lidar map (Livox-class range noise ≈ 2 cm, modelled as vertical noise only).
        Deterministic for a seeded ``generator``.
        """
        if not (isinstance(n, int) and n >= 1):
            raise ValueError(f"SyntheticRoad.sample_points: argument 'n' must be a positive int, got {n!r}")
        if not (noise_std >= 0 and math.isfinite(noise_std)):
            raise ValueError(f"SyntheticRoad.sample_points: argument 'noise_std' must be finite and "
                             f"nonnegative, got {noise_std}")
        if device is None and generator is not None:
            device = generator.device
        x0, x1, y0, y1 = self.extent
        u = torch.rand(n, 2, generator=generator, dtype=dtype, device=device)
        lo = torch.tensor((x0, y0), dtype=dtype, device=device)
        span = torch.tensor((x1 - x0, y1 - y0), dtype=dtype, device=device)
        xy = lo + u * span
        z = self.height(xy) + noise_std * torch.randn(n, generator=generator, dtype=dtype, device=device)
        return torch.cat((xy, z.unsqueeze(-1)), -1)


# ------------------------------------------------------------------------------------------------
# local quadratic patches (Eq. 40)
# ------------------------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True, eq=False)
class PatchedSurface:
    """Quadratic patches (Eq. 40) around centres ``c_j``; the surface is the patch of the nearest centre.

    Patch j is ``F_j(q) = γ₁dx² + γ₂dx dy + γ₃dy² + γ₄dx + γ₅dy + γ₆`` in coordinates relative to its
    centre, ``(dx, dy) = q − c_j`` (better conditioned than world coordinates; γ₆ is the height at the
    centre, γ₄, γ₅ the slope there).  At a query point q the nearest centre (Euclidean in x-y, ties to
    the lower index) is chosen by one ``argmin`` over all centres — O(batch · P) work, no loop — and
    its patch gives F, ∇F and ∇²F.  Far from every centre the patches are extrapolated: keep queries
    within about the fit radius of the path.

    Attributes:
        centres: ``(P, 2)`` patch centres (m).
        coefficients: ``(P, 6)`` γ of each patch in centre-relative coordinates.
        rms: ``(P,)`` RMS height residual of each fit (m; with noisy points ≈ the noise level).
        radius: ``(P,)`` x-y distance from each centre to its farthest neighbour used in the fit (m).
    """

    centres: Tensor
    coefficients: Tensor
    rms: Tensor
    radius: Tensor

    def __post_init__(self):
        fn = "PatchedSurface"
        check_tensor(self.centres, (2,), "centres", fn)
        check_tensor(self.coefficients, (6,), "coefficients", fn)
        if self.centres.dim() != 2 or self.coefficients.dim() != 2 or \
                self.centres.shape[0] != self.coefficients.shape[0] or self.centres.shape[0] == 0:
            raise ValueError(f"{fn}: 'centres' (P, 2) and 'coefficients' (P, 6) must have the same P ≥ 1, "
                             f"got {tuple(self.centres.shape)} and {tuple(self.coefficients.shape)}")

    @classmethod
    def fit(cls, points: Tensor, centres: Tensor, neighbours: int = 64) -> PatchedSurface:
        """Least-squares patches (Eq. 40) from the ``neighbours`` map points nearest (in x-y) to each centre.

        ``points`` ``(N, 3)`` (the map), ``centres`` ``(P, 2)``.  Uses
        :func:`~torchlie.manifolds.fit_quadratic_surface` on the centre-relative points, all P patches
        in one batched solve.  Raises ``ValueError`` naming the first patch whose neighbours do not
        determine a quadratic (e.g. collinear points).
        """
        fn = "PatchedSurface.fit"
        check_tensor(points, (3,), "points", fn)
        check_tensor(centres, (2,), "centres", fn)
        check_same_device(fn, points=points, centres=centres)
        if points.dim() != 2 or centres.dim() != 2 or centres.shape[0] == 0:
            raise ValueError(f"{fn}: 'points' must be (N, 3) and 'centres' (P, 2) with P ≥ 1, got "
                             f"{tuple(points.shape)} and {tuple(centres.shape)}")
        N = points.shape[0]
        if not (isinstance(neighbours, int) and 6 <= neighbours <= N):
            raise ValueError(f"{fn}: argument 'neighbours' must be an int in [6, N = {N}], "
                             f"got {neighbours!r}")
        if not bool(torch.isfinite(points).all()) or not bool(torch.isfinite(centres).all()):
            raise ValueError(f"{fn}: arguments 'points' and 'centres' must be finite")
        # k nearest in x-y, in blocks of centres so that the distance matrix stays ≤ ~4M entries
        block = max(1, (1 << 22) // N)
        idx, rad = [], []
        for i in range(0, centres.shape[0], block):
            d = torch.cdist(centres[i:i + block], points[:, :2])
            dk, ik = torch.topk(d, neighbours, dim=-1, largest=False)
            idx.append(ik)
            rad.append(dk[:, -1])
        idx, radius = torch.cat(idx), torch.cat(rad)
        local = points[idx]  # (P, K, 3)
        local = local - torch.cat((centres, torch.zeros_like(centres[:, :1])), -1).unsqueeze(-2)
        res = fit_quadratic_surface(local)
        if not bool(res.well_posed.all()):
            j = int(torch.nonzero(~res.well_posed)[0, 0])
            raise ValueError(f"{fn}: the neighbours of centre {j} ({centres[j].tolist()}) do not determine "
                             "a quadratic patch (degenerate layout, e.g. collinear points)")
        return cls(centres, res.coefficients, res.rms, radius)

    @property
    def num_patches(self) -> int:
        return self.centres.shape[0]

    def nearest(self, xy: Tensor) -> Tensor:
        """Index ``(*,)`` (int64) of the nearest centre to ``xy`` ``(*, 2)`` (or ``(*, 3)`` points)."""
        xy = xy[..., :2] if xy.dim() and xy.shape[-1] == 3 else xy
        check_tensor(xy, (2,), "xy", "PatchedSurface.nearest")
        C = self.centres.to(dtype=xy.dtype, device=xy.device)
        q = xy.detach()
        # |q − c|² up to the per-query constant |q|², as one matmul: (−2 q·c + |c|²)
        return torch.addmm((C * C).sum(-1), q.reshape(-1, 2), C.T, alpha=-2).argmin(-1).reshape(q.shape[:-1])

    def _local(self, xy: Tensor, fn: str):
        xy = xy[..., :2] if xy.dim() and xy.shape[-1] == 3 else xy
        check_tensor(xy, (2,), "xy", fn)
        j = self.nearest(xy)
        C = self.centres.to(dtype=xy.dtype, device=xy.device)[j]
        G = self.coefficients.to(dtype=xy.dtype, device=xy.device)[j]
        d = xy - C
        return d[..., 0], d[..., 1], G.unbind(-1)

    def height(self, xy: Tensor) -> Tensor:
        """F(x, y) ``(*,)`` of the nearest patch, for ``xy`` ``(*, 2)``."""
        x, y, (g1, g2, g3, g4, g5, g6) = self._local(xy, "PatchedSurface.height")
        return g1 * x * x + g2 * x * y + g3 * y * y + g4 * x + g5 * y + g6

    def gradient(self, xy: Tensor) -> Tensor:
        """[F'_x, F'_y] ``(*, 2)`` of the nearest patch."""
        x, y, (g1, g2, g3, g4, g5, _) = self._local(xy, "PatchedSurface.gradient")
        return torch.stack((2 * g1 * x + g2 * y + g4, g2 * x + 2 * g3 * y + g5), -1)

    def hessian(self, xy: Tensor) -> Tensor:
        """∇²F ``(*, 2, 2)`` of the nearest patch (constant per patch)."""
        x, _, (g1, g2, g3, _, _, _) = self._local(xy, "PatchedSurface.hessian")
        return torch.stack((2 * g1, g2, g2, 2 * g3), -1).unflatten(-1, (2, 2))

    def surface(self, name: str = "patched") -> Surface:
        """The patched road as a :class:`~torchlie.manifolds.Surface` (the MPC's model)."""
        return Surface(self.height, self.gradient, self.hessian, name=name)


# ------------------------------------------------------------------------------------------------
# the model (Eq. 35-39)
# ------------------------------------------------------------------------------------------------

def _alpha_beta(g: Tensor, c: Tensor):
    """s = gᵀR e₁, α, β of Eq. 37 and the helpers q = 1 + s², r = 1 + gᵀg."""
    s = (g * c).sum(-1)
    q = 1 + s * s
    r = 1 + (g * g).sum(-1)
    return s, q, torch.rsqrt(q), r, torch.rsqrt(r)


@dataclasses.dataclass(frozen=True, eq=False)
class UGV:
    """The UGV of seed 003 §VII-B on the surface ``surface``: the "manifold system" the error-state MPC uses.

    Attributes:
        surface: the road model S (a :class:`~torchlie.manifolds.Surface`: the patched road of
            :class:`PatchedSurface` for the MPC, or the exact road ``SyntheticRoad().surface()``).
        dt: sampling period Δt (s); 0.02 = the 50 Hz of the experiment.
        v_limits: (v_min, v_max) speed limits (m/s); default (0, 3.5): forward only (the reference
            drives at 2.4 m/s), 3.5 m/s is the top speed of the RoboMaster chassis used in the paper.
        omega_limit: |ω| ≤ omega_limit (rad/s); default 3 rad/s (≈170°/s; the reference's sharpest
            turn needs ≈0.9 rad/s at 2.4 m/s).
        manifold: 𝓜 = S × SO(2) (set from ``surface``); ``n = 3``, ``m = 2``.

    ``u_lower``/``u_upper`` are float64 ``(2,)`` tensors ``[v_min, −omega_limit]`` /
    ``[v_max, omega_limit]`` (cast them to the state's dtype/device).  The model itself does not
    clamp inputs (the MPC enforces the limits; :class:`UGVSimulator` clamps).

    Every method takes ``check=True``: ``x`` must be a ProductState on 𝓜 (``ValueError`` naming
    ``x.p``/``x.R`` and the first bad batch index otherwise, NaN included); with ``check=False``
    only shapes/dtypes are checked and a bad batch element affects only its own outputs.
    """

    surface: Surface
    dt: float = 0.02
    v_limits: tuple[float, float] = (0.0, 3.5)
    omega_limit: float = 3.0
    manifold: ProductManifold = dataclasses.field(init=False, repr=False)

    n = 3
    m = 2
    #: ``step``/``f`` ignore the time index
    time_invariant = True

    def __post_init__(self):
        object.__setattr__(self, "manifold", ugv_manifold(_as_surface(self.surface, "surface", "UGV")))
        object.__setattr__(self, "surface", self.manifold.components["p"])
        if not (isinstance(self.dt, (int, float)) and self.dt > 0 and math.isfinite(self.dt)):
            raise ValueError(f"UGV: argument 'dt' must be a positive finite float, got {self.dt!r}")
        lo, hi = self.v_limits
        if not (lo <= hi) or not (self.omega_limit > 0):
            raise ValueError(f"UGV: need v_limits[0] ≤ v_limits[1] and omega_limit > 0, got "
                             f"v_limits={self.v_limits}, omega_limit={self.omega_limit}")

    @property
    def u_lower(self) -> Tensor:
        return torch.tensor((float(self.v_limits[0]), -float(self.omega_limit)), dtype=D64)

    @property
    def u_upper(self) -> Tensor:
        return torch.tensor((float(self.v_limits[1]), float(self.omega_limit)), dtype=D64)

    # --- checks -----------------------------------------------------------------------------------
    def _inputs(self, x, u, fn: str, check: bool):
        if check:
            x = self.manifold.check_point(x, "x", fn)
        p, R = _check_state_structure(x, fn)
        check_tensor(u, (2,), "u", fn)
        check_same_device(fn, **{"x.p": p, "u": u})
        try:
            batch = broadcast_shapes(x.batch_shape, u.shape[:-1])
        except RuntimeError as e:
            raise ValueError(f"{fn}: batch shapes of 'x' {tuple(x.batch_shape)} and 'u' "
                             f"{tuple(u.shape[:-1])} do not broadcast") from e
        return x, p, R, u, batch

    def _parts(self, p: Tensor, R: Tensor, batch):
        g = self.surface.gradient(p).expand(*batch, 2)
        c = R[..., :, 0].expand(*batch, 2)  # R e₁
        return g, c

    # --- the interface ----------------------------------------------------------------------------
    def f(self, x: ProductState, u: Tensor, *, check: bool = True) -> Tensor:
        """Perturbation rate ``f(x, u) = [α R e₁ v; β ω]`` ``(*B, 3)`` of Eq. 36c (m/s, m/s, rad/s)."""
        x, p, R, u, batch = self._inputs(x, u, "UGV.f", check)
        g, c = self._parts(p, R, batch)
        _, _, alpha, _, beta = _alpha_beta(g, c)
        v, w = u[..., 0].expand(batch), u[..., 1].expand(batch)
        return torch.cat(((alpha * v).unsqueeze(-1) * c, (beta * w).unsqueeze(-1)), -1)

    def f_jacobians(self, x: ProductState, u: Tensor, *, check: bool = True) -> tuple[Tensor, Tensor]:
        """Analytic ``(∂f(x ⊞ δx, u)/∂δx (*B, 3, 3), ∂f(x, u + δu)/∂δu (*B, 3, 2))`` at 0 (Eq. 38-39).

        δx = [δp (x-y perturbation of S), δR (SO(2) angle)]; uses ∂g(p ⊞ δp)/∂δp = ∇²F and
        ∂((R ⊞ δR) e₁)/∂δR = R e₂ (Eq. 39d), and the corrected Eq. 39c (module docstring).
        """
        x, p, R, u, batch = self._inputs(x, u, "UGV.f_jacobians", check)
        g, c = self._parts(p, R, batch)
        H = self.surface.hessian(p).expand(*batch, 2, 2)
        c2 = R[..., :, 1].expand(*batch, 2)  # R e₂
        s, q, alpha, r, beta = _alpha_beta(g, c)
        v, w = u[..., 0].expand(batch), u[..., 1].expand(batch)
        k_a = -s * alpha / q  # −s / (1 + s²)^{3/2}
        da_dp = k_a.unsqueeze(-1) * (c.unsqueeze(-2) @ H).squeeze(-2)  # (*, 2)   Eq. 39a
        da_dR = k_a * (g * c2).sum(-1)  # (*,)   Eq. 39b
        db_dp = -(beta / r).unsqueeze(-1) * (g.unsqueeze(-2) @ H).squeeze(-2)  # (*, 2)   Eq. 39c
        top_p = v[..., None, None] * c.unsqueeze(-1) * da_dp.unsqueeze(-2)  # (*, 2, 2)
        top_R = (v * da_dR).unsqueeze(-1) * c + (v * alpha).unsqueeze(-1) * c2  # (*, 2)
        bottom = torch.cat((w.unsqueeze(-1) * db_dp, torch.zeros_like(w).unsqueeze(-1)), -1)  # (*, 3)
        df_dx = torch.cat((torch.cat((top_p, top_R.unsqueeze(-1)), -1), bottom.unsqueeze(-2)), -2)
        zero = torch.zeros_like(alpha)
        df_du = torch.stack((alpha * c[..., 0], zero, alpha * c[..., 1], zero, zero, beta), -1)
        return df_dx, df_du.unflatten(-1, (3, 2))

    def step(self, x: ProductState, u: Tensor, t: int = 0, *, check: bool = True) -> ProductState:
        """``x ⊕ Δt f(x, u)`` (Eq. 14, 36): the next state, on the surface; ``t`` is ignored."""
        x, *_ = self._inputs(x, u, "UGV.step", check)
        return self.manifold.oplus(x, self.dt * self.f(x, u, check=False), check=False)

    def body_axes(self, x: ProductState, *, check: bool = True) -> tuple[Tensor, Tensor]:
        """Body axes ``(x_b, z_b)``, each ``(*B, 3)`` unit vectors (module docstring)."""
        if check:
            x = self.manifold.check_point(x, "x", "UGV.body_axes")
        p, R = _check_state_structure(x, "UGV.body_axes")
        g = self.surface.gradient(p)
        c = R[..., :, 0]
        g, c = torch.broadcast_tensors(g, c)
        s, _, alpha, _, _ = _alpha_beta(g, c)
        xb = torch.cat((c, s.unsqueeze(-1)), -1) * alpha.unsqueeze(-1)
        return xb, self.surface.normal(p)


# ------------------------------------------------------------------------------------------------
# the simulator (truth)
# ------------------------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True, eq=False)
class UGVSimulator:
    """The vehicle on the true road: Eq. 35 integrated by RK4 over ``substeps`` substeps of ``dt/substeps``.

    Integrated coordinates: (x, y) and the heading increment φ since the start of the step
    (``ẋy = α(xy, R₀Exp(φ)) R₀Exp(φ) e₁ · speed_scale · v``, ``φ̇ = β(xy) ω``), which is Eq. 35 exactly
    (ż = ∇hᵀ ẋy follows from z = h(x, y)); the output is lifted exactly onto the road and
    ``R = R₀ Exp(φ)``.  The input is held over the step (zero-order hold) and clamped to
    ``[u_lower, u_upper]`` first.  ``speed_scale`` ≠ 1 models a speed (wheel radius / odometry) error
    of the plant that the MPC's model does not know.

    Attributes:
        road: the true road (a :class:`SyntheticRoad` or any :class:`~torchlie.manifolds.Surface`).
        dt: step (s); substeps: RK4 substeps per step; speed_scale: actual speed / commanded speed.
        u_lower, u_upper: input limits ``(v_min, ω_min)`` / ``(v_max, ω_max)`` applied by clamping.
        manifold: S_true × SO(2): the states :meth:`step` returns lie on it.
    """

    road: SyntheticRoad | Surface
    dt: float = 0.02
    substeps: int = 10
    speed_scale: float = 1.0
    u_lower: tuple[float, float] = (0.0, -3.0)
    u_upper: tuple[float, float] = (3.5, 3.0)
    manifold: ProductManifold = dataclasses.field(init=False, repr=False)

    def __post_init__(self):
        surface = _as_surface(self.road, "road", "UGVSimulator")
        object.__setattr__(self, "manifold", ugv_manifold(surface))
        if not (isinstance(self.dt, (int, float)) and self.dt > 0 and math.isfinite(self.dt)):
            raise ValueError(f"UGVSimulator: argument 'dt' must be a positive finite float, got {self.dt!r}")
        if not (isinstance(self.substeps, int) and self.substeps >= 1):
            raise ValueError(f"UGVSimulator: argument 'substeps' must be a positive int, "
                             f"got {self.substeps!r}")
        if not math.isfinite(self.speed_scale):
            raise ValueError(f"UGVSimulator: argument 'speed_scale' must be finite, got {self.speed_scale}")
        if not all(lo <= hi for lo, hi in zip(self.u_lower, self.u_upper)) or len(self.u_lower) != 2 \
                or len(self.u_upper) != 2:
            raise ValueError(f"UGVSimulator: need u_lower ≤ u_upper, two entries each, got {self.u_lower}, "
                             f"{self.u_upper}")

    @property
    def surface(self) -> Surface:
        return self.manifold.components["p"]

    def step(self, x: ProductState, u: Tensor, t: int = 0, *, check: bool = True) -> ProductState:
        """The true next state (on the true road) from ``x`` under ``u`` ``(*B, 2)`` held for ``dt``.

        Only x, y of ``x.p`` are used (z is re-lifted onto the true road), so a state of a model on
        another (e.g. patched) surface is accepted.  ``check=True`` requires ``x.R`` ∈ SO(2) and
        finite x, y (``ValueError`` otherwise); with ``check=False`` a bad element yields NaN in its
        own output only.  ``t`` is ignored.
        """
        fn = "UGVSimulator.step"
        p, R = _check_state_structure(x, fn)
        check_tensor(u, (2,), "u", fn)
        check_same_device(fn, **{"x.p": p, "u": u})
        if check:
            SO2().check_point(R, "x.R", fn)
            bad = ~torch.isfinite(p[..., :2]).all(-1)
            if bool(bad.any()):
                i = tuple(int(k) for k in torch.nonzero(bad)[0].tolist())
                raise ValueError(f"{fn}: argument 'x.p' has non-finite x, y at batch index {i}")
        batch = broadcast_shapes(p.shape[:-1], R.shape[:-2], u.shape[:-1])
        lo = torch.tensor(self.u_lower, dtype=u.dtype, device=u.device)
        hi = torch.tensor(self.u_upper, dtype=u.dtype, device=u.device)
        u = torch.minimum(torch.maximum(u, lo), hi)
        v = (self.speed_scale * u[..., 0]).expand(batch)
        w = u[..., 1].expand(batch)
        R0 = R.expand(*batch, 2, 2)
        xy = p[..., :2].expand(*batch, 2)
        phi = torch.zeros(batch, dtype=p.dtype, device=p.device)
        surf = self.surface

        def rhs(q, ph):
            c = (R0 @ torch.stack((torch.cos(ph), torch.sin(ph)), -1).unsqueeze(-1)).squeeze(-1)
            g = surf.gradient(q)
            _, _, alpha, _, beta = _alpha_beta(g, c)
            return (alpha * v).unsqueeze(-1) * c, beta * w

        h = self.dt / self.substeps
        for _ in range(self.substeps):
            k1 = rhs(xy, phi)
            k2 = rhs(xy + 0.5 * h * k1[0], phi + 0.5 * h * k1[1])
            k3 = rhs(xy + 0.5 * h * k2[0], phi + 0.5 * h * k2[1])
            k4 = rhs(xy + h * k3[0], phi + h * k3[1])
            xy = xy + (h / 6) * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0])
            phi = phi + (h / 6) * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])
        z = surf.height(xy)
        return ProductState({"p": torch.cat((xy, z.unsqueeze(-1)), -1), "R": R0 @ _rot(phi)},
                            {"p": 1, "R": 2})


# ------------------------------------------------------------------------------------------------
# reference generation (§VII-B-4)
# ------------------------------------------------------------------------------------------------

class Path2D(Protocol):
    """A smooth planar path: ``position(t)`` and ``velocity(t)`` = dc/dt, ``(*, 2)`` for ``t`` ``(*)``."""

    def position(self, t: Tensor) -> Tensor: ...

    def velocity(self, t: Tensor) -> Tensor: ...


@dataclasses.dataclass(frozen=True)
class FigureEightPath:
    """Lemniscate of Gerono ``c(t) = centre + Rot(rotation) [a sin t, b sin t cos t]`` (m), period 2π.

    The default (a = 11 m, b = 6 m) is 53.5 m long in x-y (54.1 m on the default road), crosses
    itself at the centre and has two sharp turns at its tips (curvature a/b² = 0.31 1/m, radius
    3.3 m; the tightest curvature, 0.37 1/m, is just before/after them).  Starts at the centre
    heading atan2(b, a) ≈ 28.6° (plus ``rotation``).
    """

    a: float = 11.0
    b: float = 6.0
    centre: tuple[float, float] = (0.0, 0.0)
    rotation: float = 0.0
    period: float = 2 * math.pi

    def _frame(self, t: Tensor, local: Tensor, translate: bool) -> Tensor:
        cr, sr = math.cos(self.rotation), math.sin(self.rotation)
        x, y = local.unbind(-1)
        out = torch.stack((cr * x - sr * y, sr * x + cr * y), -1)
        if translate:
            out = out + torch.tensor(self.centre, dtype=t.dtype, device=t.device)
        return out

    def position(self, t: Tensor) -> Tensor:
        s, c = torch.sin(t), torch.cos(t)
        return self._frame(t, torch.stack((self.a * s, self.b * s * c), -1), True)

    def velocity(self, t: Tensor) -> Tensor:
        return self._frame(t, torch.stack((self.a * torch.cos(t), self.b * torch.cos(2 * t)), -1), False)


class UGVReference(NamedTuple):
    """Output of :func:`ugv_reference`.

    ``states`` (``steps + horizon + 1``,) and ``inputs`` ``(steps + horizon, 2)``: an MPC run of
    ``steps`` steps with horizon H reads ``states[k : k + H + 1]`` and ``inputs[k : k + H]``.
    """

    states: ProductState  # p (T, 3) on the given surface, R (T, 2, 2); T = steps + horizon + 1
    inputs: Tensor  # (T - 1, 2): [speed, ω^d]
    params: Tensor  # (T,) path parameter of each sample
    steps: int  # number of steps of the nominal run (one traversal of [t_start, t_end])
    horizon: int
    length: float  # 3-D length steps · speed · dt of the nominal run (m)
    spacing_error: float  # max |‖p_{k+1} − p_k‖ − speed·dt| / (speed·dt) over all samples


def _lift(surface: Surface, path: Path2D, t: Tensor):
    xy, dxy = path.position(t), path.velocity(t)
    z = surface.height(xy)
    dz = (surface.gradient(xy) * dxy).sum(-1)
    return torch.cat((xy, z.unsqueeze(-1)), -1), torch.cat((dxy, dz.unsqueeze(-1)), -1)


def _cumulative_length(points_of: Callable[[Tensor], Tensor], t0: float, t1: float, n: int, like: Tensor):
    t = torch.linspace(t0, t1, n + 1, dtype=like.dtype, device=like.device)
    seg = torch.linalg.vector_norm(points_of(t).diff(dim=0), dim=-1)
    return t, torch.cat((torch.zeros_like(seg[:1]), seg.cumsum(0)))


def _params_at(points_of, t0: float, t1: float, lengths: Tensor, density: int = 20000) -> Tensor:
    """Parameters at which the polyline arc length of ``points_of`` from ``t0`` reaches ``lengths`` (sorted).

    The grid covers [t0, t1] and is extended (doubling) until it reaches ``lengths[-1]``.
    """
    span = t1 - t0
    for _ in range(8):
        n = max(16, int(density * span / (t1 - t0)))
        t, s = _cumulative_length(points_of, t0, t0 + span, n, lengths)
        if s[-1] >= lengths[-1]:
            break
        span *= 2
    else:
        raise ValueError("ugv_reference: the path is too short for the requested samples")
    i = torch.searchsorted(s, lengths).clamp(1, s.shape[0] - 1)
    w = ((lengths - s[i - 1]) / (s[i] - s[i - 1]).clamp_min(torch.finfo(s.dtype).tiny)).clamp(0, 1)
    return t[i - 1] + w * (t[i] - t[i - 1])


def ugv_reference(surface, path: Path2D | None = None, *, speed: float = 2.4, dt: float = 0.02,
                  horizon: int = 45, t_start: float = 0.0, t_end: float | None = None,
                  dtype: torch.dtype = D64, device=None, tol: float = 1e-13,
                  max_newton: int = 30) -> UGVReference:
    """Reference states and inputs on ``surface`` along ``path`` at constant 3-D speed (§VII-B-4).

    * Positions ``p^d_k = [c(t_k), F(c(t_k))]`` with consecutive 3-D distances ``speed · dt`` (chord,
      not arc): a polyline arc-length guess refined by Newton on all chord constraints at once (the
      bidiagonal Newton system solved by a cumulative product/sum), to ``tol`` relative.
    * ``R^d_k`` tangent to the 2-D path (heading of c'(t_k)); the yaw rate from consecutive headings,
      divided by ``z ᵀz_b(p^d_k) = β`` to get the body rate: ``ω^d_k = wrap(θ_{k+1} − θ_k) / (dt β(p^d_k))``;
      ``u^d_k = [speed, ω^d_k]``.
    * ``steps`` = the number of chords that end within [t_start, t_end] (t_end defaults to one period
      of the path); ``horizon`` further samples continue along the path (a closed path simply
      continues into its next lap), so the last MPC step still sees a full horizon.

    ``surface`` is a :class:`~torchlie.manifolds.Surface`, :class:`SyntheticRoad` or
    :class:`PatchedSurface`; the states lie on it (use the MPC's model surface so that the reference
    is on the MPC's manifold).  On a patched surface the height jumps slightly where the nearest
    centre changes, so a chord constraint can miss by up to the jump: ``spacing_error`` reports it.
    Generate in float64 (the default) and cast: float32 roundoff of 10 m coordinates alone is ≈1e-4
    of the 4.8 cm spacing.
    """
    fn = "ugv_reference"
    surf = _as_surface(surface, "surface", fn)
    path = FigureEightPath() if path is None else path
    if not (callable(getattr(path, "position", None)) and callable(getattr(path, "velocity", None))):
        raise TypeError(f"{fn}: argument 'path' must have position(t) and velocity(t) methods")
    if not (speed > 0 and dt > 0 and math.isfinite(speed * dt)):
        raise ValueError(f"{fn}: 'speed' and 'dt' must be positive and finite, got {speed}, {dt}")
    if not (isinstance(horizon, int) and horizon >= 0):
        raise ValueError(f"{fn}: argument 'horizon' must be a nonnegative int, got {horizon!r}")
    if t_end is None:
        t_end = t_start + float(getattr(path, "period", 2 * math.pi))
    if not t_end > t_start:
        raise ValueError(f"{fn}: need t_end > t_start, got {t_start}, {t_end}")
    like = torch.zeros((), dtype=dtype, device=device)
    ds = speed * dt

    def points_of(t):
        return _lift(surf, path, t)[0]

    _, s = _cumulative_length(points_of, t_start, t_end, 20000, like)
    # a generous sample count from the dense polyline (≥ the chord count: chords are shorter than arcs,
    # and on a patched surface the dense polyline also counts every height jump); trimmed below
    steps_guess = int(math.floor(float(s[-1]) / ds + 1e-9))
    if steps_guess < 1:
        raise ValueError(f"{fn}: the path is shorter than one step of speed·dt = {ds} m")
    total = steps_guess + horizon + 2
    lengths = ds * torch.arange(total + 1, dtype=dtype, device=device)
    t = _params_at(points_of, t_start, t_end, lengths)

    # Newton on r_k = ‖P(t_k) − P(t_{k−1})‖ − ds, k = 1..total, t_0 fixed:
    #   b_k Δ_k + a_k Δ_{k−1} = −r_k  =>  Δ_k = c_k + d_k Δ_{k−1}  =>  Δ_k = D_k Σ_{j≤k} c_j / D_j
    err = math.inf
    for _ in range(max_newton):
        P, dP = _lift(surf, path, t)
        diff = P[1:] - P[:-1]
        dist = torch.linalg.vector_norm(diff, dim=-1)
        r = dist - ds
        err = float(r.abs().max()) / ds
        if not math.isfinite(err):
            raise ValueError(f"{fn}: the surface or path returned non-finite values along the path")
        if err <= tol:
            break
        e = diff / dist.unsqueeze(-1)
        b = (e * dP[1:]).sum(-1)
        a = -(e * dP[:-1]).sum(-1)
        if not bool((b > 0).all() and (a < 0).all()):
            break  # a chord would not grow with its end parameter (path folding back): keep the guess
        cc, d = -r / b, -a / b
        D = torch.cumprod(d, 0)
        step = D * torch.cumsum(cc / D, 0)
        t = torch.cat((t[:1], t[1:] + step))
    # steps: the chords that end within [t_start, t_end]; keep `horizon` samples after them
    steps = int((t[1:] <= t_end).sum())
    if steps < 1 or steps + horizon + 1 > t.shape[0]:
        raise RuntimeError(f"{fn}: could not place the samples along the path (steps {steps}, "
                           f"{t.shape[0]} samples)")
    t = t[: steps + horizon + 1]
    P, dP = _lift(surf, path, t)
    err = float((torch.linalg.vector_norm(P.diff(dim=0), dim=-1) - ds).abs().max()) / ds

    vel = dP[:, :2]
    theta = torch.atan2(vel[:, 1], vel[:, 0])
    R = _rot(theta)
    dth = theta.diff()
    dth = torch.atan2(torch.sin(dth), torch.cos(dth))
    g = surf.gradient(P[:-1])
    beta = torch.rsqrt(1 + (g * g).sum(-1))
    omega = dth / (dt * beta)
    inputs = torch.stack((torch.full_like(omega, speed), omega), -1)
    states = ugv_manifold(surf).state(p=P, R=R)
    return UGVReference(states, inputs, t, steps, horizon, steps * ds, err)


# ------------------------------------------------------------------------------------------------
# everything at once
# ------------------------------------------------------------------------------------------------

class UGVScenario(NamedTuple):
    """Output of :func:`ugv_scenario`."""

    road: SyntheticRoad  # the truth
    points: Tensor  # (N, 3) the noisy map
    patches: PatchedSurface  # the fitted model road
    model: UGV  # the MPC's model, on the patched surface
    exact_model: UGV  # the same model on the exact road (for comparisons)
    simulator: UGVSimulator  # the plant, on the exact road
    reference: UGVReference  # on the patched surface (the MPC's manifold)
    height_rms: float  # RMS of F_patched − h along the reference positions (m)
    height_max: float  # max |F_patched − h| along the reference positions (m)
    slope_max_error: float  # max ‖∇F_patched − ∇h‖ along the reference positions (dimensionless)


def ugv_scenario(*, seed: int = 0, road: SyntheticRoad | None = None, path: Path2D | None = None,
                 n_points: int = 40000, noise_std: float = 0.02, patch_spacing: float = 0.25,
                 neighbours: int = 64, speed: float = 2.4, dt: float = 0.02, horizon: int = 45,
                 substeps: int = 10, speed_scale: float = 1.0, dtype: torch.dtype = D64,
                 device=None) -> UGVScenario:
    """The §VII-B setup end to end: road, noisy map (seeded), patches every ``patch_spacing`` m of the
    path (covering the run and its horizon padding), model/exact model/simulator and the reference
    on the patched surface, with the patch fit's height/slope errors along the reference.
    """
    road = SyntheticRoad() if road is None else road
    path = FigureEightPath() if path is None else path
    gen = torch.Generator(device="cpu" if device is None else device).manual_seed(seed)
    points = road.sample_points(n_points, noise_std=noise_std, generator=gen, dtype=dtype, device=device)
    t0 = 0.0
    t1 = t0 + float(getattr(path, "period", 2 * math.pi))
    like = torch.zeros((), dtype=dtype, device=device)
    _, s2 = _cumulative_length(path.position, t0, t1, 20000, like)
    cover = float(s2[-1]) + (horizon + 2) * speed * dt + patch_spacing
    lengths = torch.arange(0.0, cover, patch_spacing, dtype=dtype, device=device)
    centres = path.position(_params_at(path.position, t0, t1, lengths))
    patches = PatchedSurface.fit(points, centres, neighbours)
    ref = ugv_reference(patches, path, speed=speed, dt=dt, horizon=horizon, t_start=t0, t_end=t1,
                        dtype=dtype, device=device)
    xy = ref.states.p[..., :2]
    dz = patches.height(xy) - road.height(xy)
    dg = torch.linalg.vector_norm(patches.gradient(xy) - road.gradient(xy), dim=-1)
    return UGVScenario(
        road, points, patches,
        UGV(patches.surface(), dt), UGV(road.surface(), dt),
        UGVSimulator(road, dt, substeps, speed_scale), ref,
        float(dz.pow(2).mean().sqrt()), float(dz.abs().max()), float(dg.max()),
    )
