"""The iLQR cost zoo of seed 004 §9 as residual terms ``f(x)`` with their Jacobians ``J(x)``.

iLQR's Gauss-Newton step (Eq. 108) needs, per time step, a residual ``f(x_t)`` and its Jacobian
``J(x_t) = ∂f/∂x_t``; the cost is ``Σ_t f(x_t)ᵀ Q_t f(x_t) + Σ_t u_tᵀ R u_t`` (:class:`~controllers.costs.
ResidualCost`).  The cookbook builds every task from a few such pieces, each a :class:`Map` here, composed:

* task maps ``g(x)``: :func:`state` (the state itself), :func:`planar_ee` (end-effector position and
  orientation of a planar arm, §4), :func:`planar_com` (its centre of mass, §9.5), composed with
  :func:`on_joints` (a chain on some of the joints: the two arms of the bimanual robot of §9.6),
  :func:`concat` and :func:`mean`, or any function with :func:`autograd_map`;
* residuals on a map: :func:`track` (``g(x) - μ_t``, §9.1), :func:`cut` (zero inside a box and the signed
  distance outside, in an optionally rotated object frame: bounded joint space §9.2, bounded task space
  §9.3, prismatic object boundaries §9.3.1), :func:`avoid` (ellipsoid obstacles, §9.7) and
  :func:`distance` (reaching or keeping a distance / an ellipse contour, §9.8) and :func:`manipulability`
  (the geodesic distance of ``J Jᵀ`` to a desired SPD matrix, §9.9);
* :func:`residual_cost` stacks terms ``(map, Q)`` into one :class:`~controllers.costs.ResidualCost` with a
  block-diagonal precision.

Shapes: a map takes ``x (*B, T+1, n)`` (any leading dims) and returns ``f (*B, T+1, p)`` and
``J (*B, T+1, p, n)``; targets and box limits broadcast against ``f`` (``(p,)``, ``(T+1, p)`` or batched).
The ReLU-like residuals (``cut``, ``avoid``) have the seed's piecewise Jacobians (0 or the map's Jacobian,
Fig. 22), which is also their derivative by autograd away from the kinks.  Everything is differentiable in
the targets, limits and shapes.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from controllers.costs import ResidualCost

__all__ = ["Map", "autograd_map", "state", "planar_ee", "planar_com", "on_joints", "concat", "mean", "track",
           "cut", "avoid", "distance", "manipulability", "residual_cost", "bimanual_hands", "bimanual_com",
           "BIMANUAL_LEFT", "BIMANUAL_RIGHT"]


@dataclass(frozen=True)
class Map:
    """A map of the state with its Jacobian: ``f(x (*B, T+1, n)) -> (*B, T+1, p)`` and
    ``J(x) -> (*B, T+1, p, n)``; ``p`` is its output size."""

    f: Callable[[Tensor], Tensor]
    J: Callable[[Tensor], Tensor]
    p: int

    def __call__(self, x: Tensor) -> tuple[Tensor, Tensor]:
        return self.f(x), self.J(x)


def _as(v, like: Tensor, name: str, fn: str) -> Tensor:
    t = torch.as_tensor(v, dtype=like.dtype, device=like.device)
    if not t.dtype.is_floating_point:
        raise TypeError(f"{fn}: argument '{name}' must be floating")
    return t


def state(n: int) -> Map:
    """The state itself, ``g(x) = x`` (``J = I``): bounds on joint angles (§9.2), a point mass's position."""
    if not isinstance(n, int) or n < 1:
        raise ValueError(f"state: argument 'n' must be a positive int, got {n!r}")

    def J(x: Tensor) -> Tensor:
        return torch.eye(n, dtype=x.dtype, device=x.device).expand(*x.shape, n)

    return Map(lambda x: x, J, n)


def _lengths(lengths, fn: str) -> Tensor:
    ell = torch.as_tensor(lengths, dtype=torch.float64) if not isinstance(lengths, Tensor) else lengths
    if ell.dim() != 1 or ell.numel() < 1:
        raise ValueError(f"{fn}: argument 'lengths' must be a 1-D sequence of link lengths, got shape "
                         f"{tuple(ell.shape)}")
    return ell


def _angles(x: Tensor, ell: Tensor, fn: str) -> tuple[Tensor, Tensor]:
    if x.shape[-1] != ell.shape[0]:
        raise ValueError(f"{fn}: the state must have {ell.shape[0]} joint angles (one per link), got "
                         f"shape {tuple(x.shape)}")
    return x.cumsum(-1), ell.to(dtype=x.dtype, device=x.device)


def planar_ee(lengths: Sequence[float] | Tensor, orientation: bool = True) -> Map:
    """End effector of a planar arm with joint angles ``x`` (§4): ``f^ee = [ℓᵀcos(Lx), ℓᵀsin(Lx), 1ᵀx]``
    (the last entry, the orientation, only with ``orientation``) and ``J^ee`` (Eq. 17-19)."""
    ell = _lengths(lengths, "planar_ee")

    def f(x: Tensor) -> Tensor:
        phi, e = _angles(x, ell, "planar_ee")
        rows = [(e * torch.cos(phi)).sum(-1), (e * torch.sin(phi)).sum(-1)]
        return torch.stack(rows + [phi[..., -1]] if orientation else rows, -1)

    def J(x: Tensor) -> Tensor:
        phi, e = _angles(x, ell, "planar_ee")
        # column j sums the links from j on
        rows = [(-e * torch.sin(phi)).flip(-1).cumsum(-1).flip(-1),
                (e * torch.cos(phi)).flip(-1).cumsum(-1).flip(-1)]
        if orientation:
            rows.append(torch.ones_like(x))
        return torch.stack(rows, -2)

    return Map(f, J, 3 if orientation else 2)


def planar_com(lengths: Sequence[float] | Tensor) -> Map:
    """Centre of mass of a planar arm with equal masses at the joints (the tips of the links, §9.5)::

        f^CoM = (1/D) Σ_j p_j,   p_j = Σ_{i≤j} ℓ_i [cos φ_i, sin φ_i],   φ = L x,

    so link ``i`` counts ``D - i + 1`` times (1-based) and ``∂f^CoM/∂x_a = (1/D) Σ_{i≥a} (D-i+1) ℓ_i
    [-sin φ_i, cos φ_i]``."""
    ell = _lengths(lengths, "planar_com")
    D = ell.shape[0]

    def weights(x: Tensor) -> tuple[Tensor, Tensor]:
        phi, e = _angles(x, ell, "planar_com")
        count = torch.arange(D, 0, -1, dtype=x.dtype, device=x.device)
        return phi, e * count / D

    def f(x: Tensor) -> Tensor:
        phi, w = weights(x)
        return torch.stack([(w * torch.cos(phi)).sum(-1), (w * torch.sin(phi)).sum(-1)], -1)

    def J(x: Tensor) -> Tensor:
        phi, w = weights(x)
        return torch.stack([(-w * torch.sin(phi)).flip(-1).cumsum(-1).flip(-1),
                            (w * torch.cos(phi)).flip(-1).cumsum(-1).flip(-1)], -2)

    return Map(f, J, 2)


def autograd_map(f: Callable[[Tensor], Tensor], p: int) -> Map:
    """A map whose Jacobian is taken by autograd, one backward pass per output row (the per-step residual
    ``f (*B, T+1, n) -> (*B, T+1, p)`` must not mix time steps or batch elements)."""
    if not callable(f) or not isinstance(p, int) or p < 1:
        raise TypeError("autograd_map: expected a callable f and a positive int p")

    def J(x: Tensor) -> Tensor:
        with torch.enable_grad():
            xg = x.detach().requires_grad_(True)
            y = f(xg)
            rows = [torch.autograd.grad(y[..., i].sum(), xg, retain_graph=i < p - 1)[0] for i in range(p)]
        return torch.stack(rows, -2)

    return Map(f, J, p)


def on_joints(g: Map, joints: Sequence[int], n: int) -> Map:
    """``g`` applied to the joints ``x[..., joints]`` of an ``n``-dimensional state, its Jacobian scattered
    into the columns of those joints (zero elsewhere): e.g. the left arm ``[0, 1, 2]`` and the right arm
    ``[0, 3, 4]`` of the bimanual robot of §9.6, which share the torso joint 0."""
    _check_map(g, "on_joints")
    idx = list(joints)
    if not idx or any(not isinstance(j, int) or not 0 <= j < n for j in idx) or len(set(idx)) != len(idx):
        raise ValueError(f"on_joints: argument 'joints' must be distinct indices in [0, {n}), got {joints!r}")

    def J(x: Tensor) -> Tensor:
        out = x.new_zeros(*x.shape[:-1], g.p, n)
        out[..., idx] = g.J(x[..., idx])
        return out

    return Map(lambda x: g.f(x[..., idx]), J, g.p)


def concat(*maps: Map) -> Map:
    """The maps' outputs concatenated (e.g. both hands of a bimanual robot, ``p = Σ p_i``)."""
    if not maps:
        raise ValueError("concat: give at least one map")
    for g in maps:
        _check_map(g, "concat")
    return Map(lambda x: torch.cat([g.f(x) for g in maps], -1),
               lambda x: torch.cat([g.J(x) for g in maps], -2), sum(g.p for g in maps))


def mean(*maps: Map, weights: Sequence[float] | None = None) -> Map:
    """Weighted average ``Σ_i a_i g_i(x)`` of maps of one size (weights default to ``1/len``): e.g. the
    centre of mass of a robot from the centres of its chains."""
    if not maps:
        raise ValueError("mean: give at least one map")
    for g in maps:
        _check_map(g, "mean")
    if len({g.p for g in maps}) != 1:
        raise ValueError(f"mean: the maps must have one output size, got {[g.p for g in maps]}")
    a = [1.0 / len(maps)] * len(maps) if weights is None else list(weights)
    if len(a) != len(maps):
        raise ValueError(f"mean: {len(maps)} maps but {len(a)} weights")
    return Map(lambda x: sum(w * g.f(x) for w, g in zip(a, maps)),
               lambda x: sum(w * g.J(x) for w, g in zip(a, maps)), maps[0].p)


#: joints of the left and right chains of the 5-link bimanual robot (§9.6): the torso joint 0 is shared
BIMANUAL_LEFT, BIMANUAL_RIGHT = (0, 1, 2), (0, 3, 4)


def _bimanual_chains(lengths, fn: str) -> tuple[tuple[float, ...], tuple[float, ...]]:
    ell = _lengths(lengths, fn)
    if ell.shape[0] != 5:
        raise ValueError(f"{fn}: argument 'lengths' must hold the 5 link lengths (torso, left upper and "
                         f"lower arm, right upper and lower arm), got {ell.shape[0]}")
    return tuple(ell[list(BIMANUAL_LEFT)].tolist()), tuple(ell[list(BIMANUAL_RIGHT)].tolist())


def bimanual_hands(lengths: Sequence[float] | Tensor) -> Map:
    """Both hands of the 5-link planar bimanual robot (§9.6, Fig. 26): a torso link (joint 0) carrying a
    left arm (joints 1-2) and a right arm (joints 3-4); ``f = [left xy, right xy]`` ``(p = 4)``."""
    left, right = _bimanual_chains(lengths, "bimanual_hands")
    return concat(on_joints(planar_ee(left, orientation=False), list(BIMANUAL_LEFT), 5),
                  on_joints(planar_ee(right, orientation=False), list(BIMANUAL_RIGHT), 5))


def bimanual_com(lengths: Sequence[float] | Tensor) -> Map:
    """Centre of mass of the bimanual robot with unit masses at the joints and two at the torso's tip (§9.6):
    ``(2 p_1 + p_2 + p_3 + p_4 + p_5) / 6``, the average of the two 3-link chains' centres of mass."""
    left, right = _bimanual_chains(lengths, "bimanual_com")
    return mean(on_joints(planar_com(left), list(BIMANUAL_LEFT), 5),
                on_joints(planar_com(right), list(BIMANUAL_RIGHT), 5))


def _check_map(g, fn: str) -> None:
    if not isinstance(g, Map):
        raise TypeError(f"{fn}: argument 'g' must be a controllers.task_costs.Map, got {type(g).__name__}")


def track(g: Map, mu) -> Map:
    """Tracking residual ``f = g(x) - μ_t`` (§9.1), ``J = J_g``; ``μ`` broadcasts against ``(*B, T+1, p)``."""
    _check_map(g, "track")
    return Map(lambda x: g.f(x) - _as(mu, x, "mu", "track"), g.J, g.p)


def cut(g: Map, lower=None, upper=None, *, center=None, frame=None) -> Map:
    """Zero inside the box ``[lower, upper]`` and the signed distance to it outside (§9.2-9.3.1)::

        e = Uᵀ (g(x) - μ),    f^cut_i = e_i - clip(e_i, lower_i, upper_i),    J = diag(e ∉ box) Uᵀ J_g,

    with ``μ = center`` (default 0) and the box axes ``U = frame`` (default ``I``; ``(p, p)``, or batched
    ``(*B, 1, p, p)`` / ``(*B, T+1, p, p)`` with the time dim); ``lower``, ``upper`` and ``center``
    broadcast against ``(*B, T+1, p)`` (a batched limit ``(*B, 1, p)``):
    ``g = state(n)`` bounds joint angles (§9.2), ``g = planar_ee(...)`` the end effector (§9.3), a rotated
    ``frame`` an object's prismatic boundaries (§9.3.1).  ``None`` or ``±inf`` limits are open sides; a
    ``lower > upper`` box is a ``ValueError`` where the limits are plain numbers."""
    _check_map(g, "cut")
    if lower is None and upper is None:
        raise ValueError("cut: give 'lower', 'upper' or both (with neither the residual is identically zero)")
    for name, v in (("lower", lower), ("upper", upper)):
        if v is not None and not isinstance(v, Tensor) and torch.as_tensor(v).isnan().any():
            raise ValueError(f"cut: argument '{name}' has NaN entries")
    if (lower is not None and upper is not None and not isinstance(lower, Tensor)
            and not isinstance(upper, Tensor)
            and bool((torch.as_tensor(lower, dtype=torch.float64)
                      > torch.as_tensor(upper, dtype=torch.float64)).any())):
        raise ValueError(f"cut: 'lower' must not exceed 'upper', got {lower} and {upper}")

    def e_of(x: Tensor) -> Tensor:
        v = g.f(x)
        if center is not None:
            v = v - _as(center, x, "center", "cut")
        if frame is not None:
            v = (v.unsqueeze(-2) @ _as(frame, x, "frame", "cut")).squeeze(-2)  # Uᵀ v as a row: vᵀ U
        return v

    def clip(e: Tensor) -> Tensor:
        lo = None if lower is None else _as(lower, e, "lower", "cut")
        hi = None if upper is None else _as(upper, e, "upper", "cut")
        return torch.clamp(e, lo, hi)

    def f(x: Tensor) -> Tensor:
        e = e_of(x)
        return e - clip(e)

    def J(x: Tensor) -> Tensor:
        e = e_of(x)
        Jg = g.J(x)
        if frame is not None:
            Jg = _as(frame, x, "frame", "cut").mT @ Jg
        return (e != clip(e)).to(x.dtype).unsqueeze(-1) * Jg

    return Map(f, J, g.p)


def _precision(Sigma, x: Tensor, fn: str, p: int) -> Tensor:
    S = _as(Sigma, x, "Sigma", fn)
    if S.dim() < 2 or S.shape[-2:] != (p, p):
        raise ValueError(f"{fn}: argument 'Sigma' must be (K, {p}, {p}) or ({p}, {p}) ellipsoid shapes, got "
                         f"{tuple(S.shape)}")
    return torch.linalg.inv(S)


def _quadratic(g: Map, mu, Sigma, x: Tensor, fn: str) -> tuple[Tensor, Tensor, Tensor]:
    """``e_k = d_kᵀ Σ_k⁻¹ d_k`` with ``d_k = g(x) - μ_k`` for ``K`` shapes and ``∂e_k/∂x = 2 d_kᵀ Σ_k⁻¹ J_g``:
    ``e (*B, T+1, K)``, ``de (*B, T+1, K, n)``."""
    P = _precision(Sigma, x, fn, g.p)
    m = _as(mu, x, "mu", fn)
    if m.shape[-1] != g.p:
        raise ValueError(f"{fn}: argument 'mu' must end in the map's size {g.p}, got {tuple(m.shape)}")
    if m.dim() == 1:
        m = m.unsqueeze(0)
    if P.dim() == 2:
        P = P.unsqueeze(0)
    d = g.f(x).unsqueeze(-2) - m  # (*B, T+1, K, p)
    Pd = (P @ d.unsqueeze(-1)).squeeze(-1)
    e = (d * Pd).sum(-1)
    de = 2 * Pd @ g.J(x)  # (*B, T+1, K, n)
    return e, de, m


def avoid(g: Map, mu, Sigma) -> Map:
    """Ellipsoid obstacles (§9.7): ``f_k = max(0, 1 - e_k)``, ``e_k = (g(x) - μ_k)ᵀ Σ_k⁻¹ (g(x) - μ_k)``,
    which is 1 at a centre and 0 on and outside the boundary; ``J_k = -[e_k < 1] 2 (g(x) - μ_k)ᵀ Σ_k⁻¹ J_g``.
    ``mu (K, p)`` or ``(p,)`` centres and ``Sigma (K, p, p)`` or ``(p, p)`` shapes (``Σ = V Vᵀ``, the
    columns of ``V`` the principal axes), shared by the batch; batched ones carry the time dim,
    ``(*B, 1, K, p)`` and ``(*B, 1, K, p, p)``; one residual entry per obstacle."""
    _check_map(g, "avoid")
    K = 1 if torch.as_tensor(mu).dim() <= 1 else torch.as_tensor(mu).shape[-2]

    def f(x: Tensor) -> Tensor:
        e, _, _ = _quadratic(g, mu, Sigma, x, "avoid")
        return torch.relu(1 - e)

    def J(x: Tensor) -> Tensor:
        e, de, _ = _quadratic(g, mu, Sigma, x, "avoid")
        return -(e < 1).to(x.dtype).unsqueeze(-1) * de

    return Map(f, J, K)


def distance(g: Map, mu, radius=None, *, Sigma=None) -> Map:
    """Reaching or keeping a distance ``r`` to a target ``μ`` (§9.8): ``f = 1 - e``, ``e = ‖g(x) - μ‖² / r²``
    (0 on the sphere of radius ``r``), ``J = -2 (g(x) - μ)ᵀ J_g / r²``; with ``Sigma`` instead of ``radius``,
    ``e = (g(x) - μ)ᵀ Σ⁻¹ (g(x) - μ)``: the contour of an ellipse.  Per element and step: ``μ`` broadcasts
    against ``(*B, T+1, p)``, ``radius`` against ``(*B, T+1)`` (a radius per problem: ``(*B, 1)``) and
    ``Sigma`` against ``(*B, T+1, p, p)``."""
    _check_map(g, "distance")
    if (radius is None) == (Sigma is None):
        raise ValueError("distance: give exactly one of 'radius' and 'Sigma'")
    if radius is not None and not isinstance(radius, Tensor) and not float(radius) > 0:
        raise ValueError(f"distance: argument 'radius' must be positive, got {radius!r}")

    def parts(x: Tensor) -> tuple[Tensor, Tensor]:
        d = g.f(x) - _as(mu, x, "mu", "distance")
        if Sigma is not None:
            S = _as(Sigma, x, "Sigma", "distance")
            if S.dim() < 2 or S.shape[-2:] != (g.p, g.p):
                raise ValueError(f"distance: argument 'Sigma' must end in ({g.p}, {g.p}), got "
                                 f"{tuple(S.shape)}")
            Pd = (torch.linalg.inv(S) @ d.unsqueeze(-1)).squeeze(-1)
        else:
            r = _as(radius, x, "radius", "distance")
            Pd = d / (r * r).unsqueeze(-1)
        return d, Pd

    def f(x: Tensor) -> Tensor:
        d, Pd = parts(x)
        return 1 - (d * Pd).sum(-1, keepdim=True)

    def J(x: Tensor) -> Tensor:
        _, Pd = parts(x)
        return -2 * Pd.unsqueeze(-2) @ g.J(x)

    return Map(f, J, 1)


def manipulability(g: Map, S) -> Map:
    """Manipulability tracking (§9.9, Eq. 111): the residual ``f = vec(log(S^{-1/2} M(x) S^{-1/2}))``, with
    ``M(x) = J_g(x) J_g(x)ᵀ`` the manipulability ellipsoid of the map ``g`` (its end effector, centre of
    mass, ...) and ``S (q, q)`` (or batched) the desired one; ``vec`` keeps the lower triangle with the
    off-diagonal entries times √2 (the whitened Mandel coordinates of :class:`torchlie.manifolds.SPD`), so
    ``‖f‖² = ‖log(S^{-1/2} M S^{-1/2})‖_F²`` is the squared affine-invariant geodesic distance.  Its
    Jacobian is taken by autograd (exact at repeated eigenvalues)."""
    from torchlie.manifolds import SPD

    _check_map(g, "manipulability")
    space = SPD(g.p)

    def f(x: Tensor) -> Tensor:
        Jg = g.J(x)
        return space.log_at(_as(S, x, "S", "manipulability"), Jg @ Jg.mT, check=False)

    return autograd_map(f, space.dim)


def _block_diag_precision(Qs: list[Tensor], ps: list[int]) -> Tensor:
    """Block-diagonal ``(*B, T, P, P)`` from per-term precisions ``(p, p)``, ``(T, p, p)`` or batched."""
    shapes = [Q.shape[:-2] for Q in Qs]
    lead = torch.broadcast_shapes(*shapes)
    P = sum(ps)
    out = Qs[0].new_zeros(*lead, P, P)
    o = 0
    for Q, p in zip(Qs, ps):
        out[..., o:o + p, o:o + p] = Q
        o += p
    return out


def residual_cost(terms: Sequence[tuple[Map, Tensor]], R: Tensor) -> ResidualCost:
    """One :class:`~controllers.costs.ResidualCost` ``Σ_t Σ_i f_i(x_t)ᵀ Q_i,t f_i(x_t) + Σ_t u_tᵀ R_t u_t``
    from terms ``(map, Q_i)``, ``Q_i`` of shape ``(p_i, p_i)``, ``(T+1, p_i, p_i)`` (e.g. zero except at via
    points) or batched; the residuals are concatenated and the precisions placed block-diagonally."""
    if not terms:
        raise ValueError("residual_cost: argument 'terms' must hold at least one (map, Q) pair")
    for i, t in enumerate(terms):
        if not (isinstance(t, tuple) and len(t) == 2 and isinstance(t[0], Map) and isinstance(t[1], Tensor)):
            raise TypeError(f"residual_cost: terms[{i}] must be a (Map, Q tensor) pair")
        if t[1].dim() < 2 or t[1].shape[-2:] != (t[0].p, t[0].p):
            raise ValueError(f"residual_cost: terms[{i}] Q must end in ({t[0].p}, {t[0].p}) (the map's "
                             f"size), got {tuple(t[1].shape)}")
    for i, (_, q) in enumerate(terms):
        if q.dtype != terms[0][1].dtype or q.device != terms[0][1].device:
            raise TypeError(f"residual_cost: terms[{i}] Q is {q.dtype} on {q.device}, terms[0] Q is "
                            f"{terms[0][1].dtype} on {terms[0][1].device}: give every precision in one dtype")
    if not isinstance(R, Tensor) or R.dtype != terms[0][1].dtype:
        raise TypeError(f"residual_cost: 'R' must be a tensor of the precisions' dtype {terms[0][1].dtype}")
    maps = [m for m, _ in terms]
    Q = _block_diag_precision([q for _, q in terms], [m.p for m in maps])

    def residual(x: Tensor) -> Tensor:
        return torch.cat([m.f(x) for m in maps], -1)

    def jacobian(x: Tensor) -> Tensor:
        return torch.cat([m.J(x) for m in maps], -2)

    return ResidualCost(residual, Q, R, jacobian=jacobian)
