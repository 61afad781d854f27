"""Magnus expansion and the ME2 linear pose prediction over a time horizon (seed 000).

Setting (seed 000, Eq. 6-17).  A pose follows the body-frame twists ``T_k`` (``[v, ω]``, seed 000
Eq. 2) as ``X_{k+1} = X_k exp(Δt T_k)`` (Eq. 6, 17).  Writing ``X(t) = X_0 exp(Ω(t))`` (Eq. 9), the
derivative of the exponential in this convention is the *right-trivialized* one,
``d/dt exp(Ω) = exp(Ω) (J_r(Ω) Ω')^``, so

    Ω' = dexp⁻¹_Ω U = J_r(Ω)⁻¹ U = Σ_n c_n ad_Ω^n U,      c_n = B⁺_n / n!      (Eq. 11)

with the Bernoulli numbers ``B⁺_n`` of the generating function ``z / (1 - e^{-z})`` (``B⁺_1 = +1/2``;
all other ``B⁺_n`` equal the usual ``B_n``, and the odd ones above 1 vanish).  Truncated at ``n = 2``
this is ME2 (Eq. 13): ``Ω' ≈ U + ½[Ω, U] + 1/12 [Ω, [Ω, U]]`` — the sign of the ½ term is the one of
the paper and belongs to the right-multiplied update of Eq. 6.  The other sign (``B_1 = -1/2``) gives
the left-trivialized ``J_l⁻¹``, which belongs to world-frame updates ``X_{k+1} = exp(Δt T_k) X_k``
(``side="left"`` below).

Two predictors of ``ξ_1 … ξ_H`` from twists ``T_0 … T_{H-1}`` are provided:

* **world frame** (the paper's Eq. 16): ``ξ = log X`` and, linearized at ``ξ_0 = log X_0``,
  ``ξ_{k+1} = ξ_0 + Δt dexp⁻¹_{ξ_0} (T_0 + … + T_k)`` — linear, so it is the model ``x_{k+1} = A x_k +
  B u_k`` of Eq. 5 with ``A = I`` and ``B = Δt dexp⁻¹_{ξ_0}`` (:func:`linear_model`).  Its accuracy
  depends on where ``X_0`` sits: as the rotation angle θ of ``X_0`` approaches π (the cut locus of
  ``log``) the order-2 series departs from ``J_r⁻¹`` (the first omitted term grows like θ⁴) and
  ``J_r⁻¹`` itself varies faster along the horizon, so the error of Eq. 16 grows several-fold; and
  ``log`` is discontinuous there, so ``ξ`` jumps when a path crosses θ = π.  Every tool-down
  orientation of a robot arm (``R = diag(1, -1, -1)`` and its yaw rotations) has θ = π exactly.
* **local frame**: ``X_k = X_0 exp(Ω_k)`` with ``Ω_0 = 0``; the ME2 recursion
  ``Ω_{k+1} = Ω_k + Δt (T_k + ½[Ω_k, T_k] + 1/12 [Ω_k, [Ω_k, T_k]])``.  It never sees the angle of
  ``X_0`` and keeps ``Ω`` small over a horizon, so it has no cut-locus problem; it is bilinear in
  ``(Ω, T)``, and :func:`linearize_local` gives its time-varying linearization ``(A_k, B_k)`` for an MPC.

The exact reference is :func:`integrate_exact` (Eq. 17).  All functions work for so(3) (tangent
``(*, 3)``, group ``(*, 3, 3)``) and se(3) (tangent ``(*, 6)``, group ``(*, 4, 4)``), chosen by the
trailing size of the tangent argument; any leading batch dims broadcast; dtype and device follow the
inputs; everything is differentiable.
"""

from __future__ import annotations

import enum
from fractions import Fraction
from functools import cache

import torch

from torchlie import se3, so3
from torchlie._batch import broadcast_leading, check_same_device, check_tensor

__all__ = [
    "Frame",
    "bernoulli_numbers",
    "dexp_inv_coefficients",
    "bracket",
    "dexp_inv_series",
    "dexp_inv",
    "predict_world",
    "predict_local",
    "predict_poses",
    "integrate_exact",
    "linear_model",
    "linearize_local",
    "world_poses",
    "local_poses",
]


class Frame(str, enum.Enum):
    """Which coordinates the ME2 predictor integrates in."""

    WORLD = "world"  # ξ = log X (seed 000 Eq. 16), linear in the twists
    LOCAL = "local"  # X = X_0 exp(Ω), Ω_0 = 0, ME2 recursion (Eq. 13 discretized)


# ---------------------------------------------------------------------------------------------------------
# Bernoulli series
# ---------------------------------------------------------------------------------------------------------


@cache
def bernoulli_numbers(n: int) -> tuple[Fraction, ...]:
    """Exact Bernoulli numbers ``B_0 … B_n`` in the convention ``B_1 = -1/2`` (``z / (e^z - 1)``)."""
    if not isinstance(n, int) or n < 0:
        raise ValueError(f"bernoulli_numbers: argument 'n' must be a non-negative int, got {n!r}")
    B = [Fraction(1)]
    for m in range(1, n + 1):
        s = Fraction(0)
        binom = 1  # C(m+1, k), updated incrementally
        for k in range(m):
            s += binom * B[k]
            binom = binom * (m + 1 - k) // (k + 1)
        B.append(-s / (m + 1))
    return tuple(B)


@cache
def dexp_inv_coefficients(order: int, side: str = "right") -> tuple[float, ...]:
    """Coefficients ``c_0 … c_order`` of ``dexp⁻¹_x = Σ c_n ad_x^n`` (seed 000 Eq. 11).

    ``side="right"``: ``J_r⁻¹ = ad/(1 - e^{-ad})``, ``c_1 = +1/2`` (the paper's Eq. 13);
    ``side="left"``: ``J_l⁻¹ = ad/(e^{ad} - 1)``, ``c_1 = -1/2``.
    """
    _check_side(side, "dexp_inv_coefficients")
    B = bernoulli_numbers(order)
    fact = 1
    out = []
    for n, b in enumerate(B):
        if n > 0:
            fact *= n
        c = b / fact
        if n == 1 and side == "right":
            c = -c
        out.append(float(c))
    return tuple(out)


def _check_side(side: str, fn: str) -> None:
    if side not in ("right", "left"):
        raise ValueError(f"{fn}: argument 'side' must be 'right' or 'left', got {side!r}")


def _check_order(order, fn: str) -> None:
    if isinstance(order, bool) or not isinstance(order, int) or order < 0:
        raise ValueError(f"{fn}: argument 'order' must be a non-negative int, got {order!r}")


def _group_of(x, name: str, fn: str):
    """so3 or se3, from the trailing size of a tangent argument."""
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{fn}: argument '{name}' must be a torch.Tensor of shape (*, 3) for so(3) or "
                        f"(*, 6) for se(3), got {type(x).__name__}")
    d = x.shape[-1] if x.dim() > 0 else None
    if d == 3:
        return so3
    if d == 6:
        return se3
    raise ValueError(f"{fn}: argument '{name}' must have shape (*, 3) for so(3) or (*, 6) for se(3), "
                     f"got {tuple(x.shape)}")


def bracket(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Lie bracket ``[x, y] = ad_x y`` of so(3) ``(*, 3)`` or se(3) ``(*, 6)`` vectors (seed 000 Eq. 3-4).

    Computed with cross products (no 6×6 matrix); leading dims broadcast.
    """
    fn = "bracket"
    _group_of(x, "x", fn)
    d = x.shape[-1]
    check_tensor(x, (d,), "x", fn)
    check_tensor(y, (d,), "y", fn)
    check_same_device(fn, x=x, y=y)
    x, y = torch.broadcast_tensors(x, y)
    if d == 3:
        return torch.linalg.cross(x, y, dim=-1)
    r1, p1 = x[..., :3], x[..., 3:]
    r2, p2 = y[..., :3], y[..., 3:]
    cr = torch.linalg.cross
    return torch.cat([cr(p1, r2, dim=-1) + cr(r1, p2, dim=-1), cr(p1, p2, dim=-1)], dim=-1)


def dexp_inv_series(x: torch.Tensor, order: int, *, side: str = "right") -> torch.Tensor:
    """Truncated Bernoulli series ``Σ_{n=0}^{order} c_n ad_x^n`` of ``dexp⁻¹_x`` (seed 000 Eq. 11-13).

    Args:
        x: so(3) ``(*, 3)`` or se(3) ``(*, 6)`` tangent vector.
        order: highest power of ``ad_x`` kept; ``order=2`` is ME2 (Eq. 13); ``order=0`` the identity.
        side: ``"right"`` (default) approximates ``J_r(x)⁻¹``, the inverse derivative for the update
            ``X exp(Δt T)`` of seed 000; ``"left"`` approximates ``J_l(x)⁻¹``.

    Returns:
        ``(*, d, d)``.  Converges to :func:`dexp_inv` for rotation angles below 2π.
    """
    fn = "dexp_inv_series"
    G = _group_of(x, "x", fn)
    check_tensor(x, (x.shape[-1],), "x", fn)
    _check_order(order, fn)
    _check_side(side, fn)
    c = dexp_inv_coefficients(order, side)
    d = x.shape[-1]
    eye = torch.eye(d, dtype=x.dtype, device=x.device).expand(*x.shape[:-1], d, d)
    if order == 0:
        return eye.clone()
    A = G.ad(x)
    # Horner: c_0 + A (c_1 + A (c_2 + …)).
    M = c[order] * eye
    for n in range(order - 1, -1, -1):
        M = c[n] * eye + A @ M
    return M


def dexp_inv(x: torch.Tensor, *, side: str = "right") -> torch.Tensor:
    """Closed form of ``dexp⁻¹_x``, ``(*, d, d)``: ``J_r(x)⁻¹`` (``side="right"``) or ``J_l(x)⁻¹``.

    With ``X_{k+1} = X_k exp(Δt T_k)`` and ``X = X_0 exp(Ω)``: ``Ω' = dexp_inv(Ω) @ T`` (seed 000 Eq. 10-11).
    """
    fn = "dexp_inv"
    G = _group_of(x, "x", fn)
    check_tensor(x, (x.shape[-1],), "x", fn)
    _check_side(side, fn)
    return G.right_jacobian_inv(x) if side == "right" else G.left_jacobian_inv(x)


# ---------------------------------------------------------------------------------------------------------
# Horizon prediction
# ---------------------------------------------------------------------------------------------------------


def _dt_tensor(dt, like: torch.Tensor, fn: str) -> torch.Tensor:
    """``dt`` (float or tensor broadcastable to the batch) as a tensor of shape ``(*B, 1, 1)`` or ``()``."""
    if isinstance(dt, torch.Tensor):
        if not dt.dtype.is_floating_point:
            raise TypeError(f"{fn}: argument 'dt' must be a float or a floating tensor, got {dt.dtype}")
        check_same_device(fn, twists=like, dt=dt)
        return dt if dt.dim() == 0 else dt[..., None, None]
    if isinstance(dt, bool) or not isinstance(dt, (int, float)):
        raise TypeError(f"{fn}: argument 'dt' must be a float or a tensor of shape (*B,), "
                        f"got {type(dt).__name__}")
    if not dt > 0:
        raise ValueError(f"{fn}: argument 'dt' must be positive, got {dt}")
    return torch.tensor(float(dt), dtype=like.dtype, device=like.device)


def _check_twists(twists, d: int | None, fn: str) -> torch.Tensor:
    if d is None:
        _group_of(twists, "twists", fn)
        d = twists.shape[-1]
    if not isinstance(twists, torch.Tensor) or twists.dim() < 2:
        got = tuple(twists.shape) if isinstance(twists, torch.Tensor) else type(twists).__name__
        raise ValueError(f"{fn}: argument 'twists' must have shape (*B, H, {d}), got {got}")
    check_tensor(twists, (twists.shape[-2], d), "twists", fn)
    if twists.shape[-2] == 0:
        raise ValueError(f"{fn}: argument 'twists' must hold at least one step (H >= 1), "
                         f"got {tuple(twists.shape)}")
    return twists


def _dexp_inv_at(x: torch.Tensor, order: int | None) -> torch.Tensor:
    return dexp_inv(x) if order is None else dexp_inv_series(x, order)


def predict_world(xi0: torch.Tensor, twists: torch.Tensor, dt, order: int | None = 2) -> torch.Tensor:
    """World-frame ME2 horizon prediction, seed 000 Eq. 16.

    ``ξ_{k+1} = ξ_0 + Δt dexp⁻¹_{ξ_0} (T_0 + … + T_k)`` for ``k = 0 … H-1``.

    Args:
        xi0: ``(*B, d)`` with ``ξ_0 = log X_0`` (d = 3 for so(3), 6 for se(3)).
        twists: ``(*B, H, d)`` body-frame twists ``T_0 … T_{H-1}`` (``X_{k+1} = X_k exp(Δt T_k)``).
        dt: time step (float, or tensor broadcastable to ``(*B,)``).
        order: truncation of the Bernoulli series (2 = ME2, the paper); ``None`` for the closed form
            ``J_r(ξ_0)⁻¹`` (the exact first-order linearization).

    Returns:
        ``(*B, H, d)`` = ``ξ_1 … ξ_H``; poses are ``exp(ξ_k)`` (:func:`world_poses`).
    """
    fn = "predict_world"
    _group_of(xi0, "xi0", fn)
    d = xi0.shape[-1]
    check_tensor(xi0, (d,), "xi0", fn)
    _check_twists(twists, d, fn)
    if order is not None:
        _check_order(order, fn)
    check_same_device(fn, xi0=xi0, twists=twists)
    h = _dt_tensor(dt, twists, fn)
    xi0, twists = broadcast_leading(xi0, 1, twists, 2, fn, ("xi0", "twists"))
    B = h * _dexp_inv_at(xi0, order)  # (*B, d, d)
    S = torch.cumsum(twists, dim=-2)  # (*B, H, d)
    return xi0.unsqueeze(-2) + S @ B.transpose(-1, -2)


def predict_local(twists: torch.Tensor, dt, order: int = 2) -> torch.Tensor:
    """Local-frame ME2 horizon prediction: ``Ω_1 … Ω_H`` with ``X_k = X_0 exp(Ω_k)``.

    ``Ω_0 = 0``, ``Ω_{k+1} = Ω_k + Δt Σ_{n=0}^{order} c_n ad_{Ω_k}^n T_k``; ``order=2`` is
    ``Ω_k + Δt (T_k + ½[Ω_k, T_k] + 1/12 [Ω_k, [Ω_k, T_k]])`` (seed 000 Eq. 13, explicit Euler).
    ``order=0`` is the plain sum ``Δt (T_0 + … + T_k)``.  A loop over the H steps, batched over ``*B``.

    Args:
        twists: ``(*B, H, d)``; dt: float or tensor broadcastable to ``(*B,)``; order: see above.

    Returns:
        ``(*B, H, d)``; poses are ``X_0 exp(Ω_k)`` (:func:`local_poses`).
    """
    fn = "predict_local"
    _check_twists(twists, None, fn)
    _check_order(order, fn)
    c = dexp_inv_coefficients(order, "right")
    A = _dt_tensor(dt, twists, fn) * twists  # (*B, H, d)
    if order == 0:
        return torch.cumsum(A, dim=-2)
    H = twists.shape[-2]
    omega = torch.zeros_like(A[..., 0, :])
    out = []
    for k in range(H):
        a = A[..., k, :]
        term = a
        step = a
        for n in range(1, order + 1):
            term = bracket(omega, term)
            if c[n] != 0.0:
                step = step + c[n] * term
        omega = omega + step
        out.append(omega)
    return torch.stack(out, dim=-2)


def linearize_local(omega: torch.Tensor, twists: torch.Tensor, dt, order: int = 2
                    ) -> tuple[torch.Tensor, torch.Tensor]:
    """Jacobians of one local ME2 step ``f(Ω, T) = Ω + Δt Σ c_n ad_Ω^n T`` at ``(Ω_k, T_k)``.

    For a time-varying linear MPC around a nominal ``(Ω̄_k, T̄_k)``:
    ``δΩ_{k+1} = A_k δΩ_k + B_k δT_k``.

    Args:
        omega: ``(*B, H, d)`` nominal ``Ω_0 … Ω_{H-1}``; twists: ``(*B, H, d)`` nominal twists.

    Returns:
        ``(A, B)``, each ``(*B, H, d, d)``: ``A_k = ∂f/∂Ω``, ``B_k = Δt dexp_inv_series(Ω_k, order)``.
    """
    fn = "linearize_local"
    G = _group_of(omega, "omega", fn)
    d = omega.shape[-1]
    check_tensor(omega, (d,), "omega", fn)
    _check_twists(twists, d, fn)
    _check_order(order, fn)
    check_same_device(fn, omega=omega, twists=twists)
    omega, twists = broadcast_leading(omega, 1, twists, 1, fn, ("omega", "twists"))
    h = _dt_tensor(dt, twists, fn)
    if h.dim() > 0:
        h = h[..., None]  # (*B, 1, 1, 1)
    c = dexp_inv_coefficients(order, "right")
    eye = torch.eye(d, dtype=omega.dtype, device=omega.device)
    adO = G.ad(omega)
    # d/dΩ of ad_Ω^n T: with y_n = ad_Ω y_{n-1}, y_0 = T: dy_n = -ad_{y_{n-1}} dΩ + ad_Ω dy_{n-1}.
    J = torch.zeros_like(adO)
    y = twists
    dsum = torch.zeros_like(adO)
    for n in range(1, order + 1):
        J = -G.ad(y) + adO @ J
        y = (adO @ y.unsqueeze(-1)).squeeze(-1)
        if c[n] != 0.0:
            dsum = dsum + c[n] * J
    A = eye + h * dsum
    Bm = h * dexp_inv_series(omega, order)
    return A, Bm


def linear_model(xi0: torch.Tensor, dt, order: int | None = 2) -> tuple[torch.Tensor, torch.Tensor]:
    """Matrices ``(A, B)`` of ``ξ_{k+1} = A ξ_k + B T_k`` equivalent to Eq. 16 (seed 000 Eq. 5).

    ``A = I`` and ``B = Δt dexp⁻¹_{ξ_0}`` (series of ``order``, or the closed form for ``None``), both
    ``(*B, d, d)``.  Rolling this model out from ``ξ_0`` reproduces :func:`predict_world` exactly.
    """
    fn = "linear_model"
    _group_of(xi0, "xi0", fn)
    d = xi0.shape[-1]
    check_tensor(xi0, (d,), "xi0", fn)
    if order is not None:
        _check_order(order, fn)
    h = _dt_tensor(dt, xi0, fn)
    Bm = h * _dexp_inv_at(xi0, order)
    A = torch.eye(d, dtype=xi0.dtype, device=xi0.device).expand(Bm.shape).clone()
    return A, Bm


def _group_matrix_check(X, n: int, name: str, fn: str) -> torch.Tensor:
    return check_tensor(X, (n, n), name, fn)


def integrate_exact(X0: torch.Tensor, twists: torch.Tensor, dt) -> torch.Tensor:
    """Exact chained integration ``X_{k+1} = X_k exp(Δt T_k)`` (seed 000 Eq. 17).

    Args:
        X0: ``(*B, n, n)`` start poses (n = 3 for SO(3) with twists ``(*, 3)``, 4 for SE(3) with ``(*, 6)``).
        twists: ``(*B, H, d)``; dt: float or tensor broadcastable to ``(*B,)``.

    Returns:
        ``(*B, H, n, n)`` = ``X_1 … X_H``.  All exponentials are taken in one batched call; the
        products are chained over the H steps.
    """
    fn = "integrate_exact"
    G = _group_of(twists, "twists", fn)
    _check_twists(twists, None, fn)
    n = 3 if twists.shape[-1] == 3 else 4
    _group_matrix_check(X0, n, "X0", fn)
    check_same_device(fn, X0=X0, twists=twists)
    h = _dt_tensor(dt, twists, fn)
    E = G.exp(h * twists)  # (*B, H, n, n)
    X0, E = broadcast_leading(X0, 2, E, 3, fn, ("X0", "twists"))
    X = X0
    out = []
    for k in range(E.shape[-3]):
        X = X @ E[..., k, :, :]
        out.append(X)
    return torch.stack(out, dim=-3)


def world_poses(xi: torch.Tensor) -> torch.Tensor:
    """``X_k = exp(ξ_k)`` for a world-frame prediction ``(*, d)`` -> ``(*, n, n)``."""
    G = _group_of(xi, "xi", "world_poses")
    return G.exp(xi)


def local_poses(X0: torch.Tensor, omega: torch.Tensor) -> torch.Tensor:
    """``X_k = X_0 exp(Ω_k)`` for a local-frame prediction: X0 ``(*B, n, n)``, omega ``(*B, H, d)``."""
    fn = "local_poses"
    G = _group_of(omega, "omega", fn)
    n = 3 if omega.shape[-1] == 3 else 4
    _group_matrix_check(X0, n, "X0", fn)
    check_same_device(fn, X0=X0, omega=omega)
    return X0.unsqueeze(-3) @ G.exp(omega)


def predict_poses(X0: torch.Tensor, twists: torch.Tensor, dt, frame: Frame | str = Frame.WORLD,
                  order: int | None = 2) -> torch.Tensor:
    """Predicted poses ``X_1 … X_H`` ``(*B, H, n, n)`` from ``X_0`` and twists, in either ``frame``.

    World frame: ``exp(predict_world(log X_0, …))``; local frame: ``X_0 exp(predict_local(…))``.
    """
    fn = "predict_poses"
    try:
        frame = Frame(frame)
    except ValueError:
        raise ValueError(f"{fn}: argument 'frame' must be 'world' or 'local' (a magnus.Frame), "
                         f"got {frame!r}") from None
    G = _group_of(twists, "twists", fn)
    n = 3 if twists.shape[-1] == 3 else 4
    _group_matrix_check(X0, n, "X0", fn)
    if frame is Frame.WORLD:
        return G.exp(predict_world(G.log(X0), twists, dt, order))
    if order is None:
        raise ValueError(f"{fn}: the local frame needs an integer 'order' (the series truncation), got None")
    return local_poses(X0, predict_local(twists, dt, order))
