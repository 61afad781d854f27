"""SE(3): rigid motions as homogeneous matrices ``(*, 4, 4)``; tangent vectors ξ = [v, ω] ``(*, 6)``.

The tangent ordering ``[v, ω]`` (translational part first) is seed 000 Eq. 2; ``ad`` is seed 000
Eq. 4.  The contract (shapes, Jacobian conventions, broadcasting) is written once in :mod:`torchlie`.
Formulas: Solà, Deray, Atchuthan, *A micro Lie theory* (2018), Eq. 172-180: ``exp([v, ω]) =
[[exp(ω), J_l(ω) v], [0, 1]]``, and the SE(3) Jacobians ``J_l([v, ω]) = [[J_l(ω), Q(v, ω)],
[0, J_l(ω)]]``, ``J_r(ξ) = J_l(-ξ)``.

Every closed-form coefficient has a Taylor branch near θ = 0 (safe-``where``), and ``log`` goes
through :func:`torchlie.so3.log`, which is accurate up to and including θ = π.
"""

from __future__ import annotations

import torch

from torchlie import so3 as _so3
from torchlie._batch import (
    batch_shape,
    broadcast_leading,
    check_same_device,
    check_tensor,
    float_dtype,
    horner,
    rng_device,
    scalar_param,
)

__all__ = [
    "exp",
    "log",
    "hat",
    "vee",
    "compose",
    "inverse",
    "act",
    "adjoint",
    "ad",
    "left_jacobian",
    "left_jacobian_inv",
    "right_jacobian",
    "right_jacobian_inv",
    "identity",
    "random",
    "interpolate",
    "from_rt",
    "to_rt",
]

DIM = 6
MATRIX = 4


def _cross(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return torch.linalg.cross(a, b, dim=-1)


def _assemble(R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """[[R, t], [0, 1]] ``(*, 4, 4)`` from R ``(*, 3, 3)`` and t ``(*, 3)`` (same leading dims)."""
    bottom = torch.zeros(*R.shape[:-2], 1, 4, dtype=R.dtype, device=R.device)
    bottom[..., 0, 3] = 1
    return torch.cat((torch.cat((R, t.unsqueeze(-1)), -1), bottom), -2)


def from_rt(R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Homogeneous matrix from a rotation ``(*, 3, 3)`` and a translation ``(*, 3)`` (broadcast)."""
    check_tensor(R, (3, 3), "R", "se3.from_rt")
    check_tensor(t, (3,), "t", "se3.from_rt")
    check_same_device("se3.from_rt", R=R, t=t)
    R, t = broadcast_leading(R, 2, t, 1, "se3.from_rt", ("R", "t"))
    return _assemble(R, t)


def to_rt(X: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Split a homogeneous matrix ``(*, 4, 4)`` into R ``(*, 3, 3)`` and t ``(*, 3)`` (views)."""
    check_tensor(X, (4, 4), "X", "se3.to_rt")
    return X[..., :3, :3], X[..., :3, 3]


# --------------------------------------------------------------------------------------------------
# algebra
# --------------------------------------------------------------------------------------------------

def hat(xi: torch.Tensor) -> torch.Tensor:
    """ξ = [v, ω] ``(*, 6)`` -> ξ^ = [[ω̂, v], [0, 0]] ``(*, 4, 4)`` (seed 000 Eq. 1)."""
    check_tensor(xi, (6,), "xi", "se3.hat")
    top = torch.cat((_so3._hat(xi[..., 3:]), xi[..., :3].unsqueeze(-1)), -1)
    return torch.cat((top, torch.zeros_like(top[..., :1, :])), -2)


def vee(Xi: torch.Tensor) -> torch.Tensor:
    """``(*, 4, 4)`` algebra matrix -> [v, ω] ``(*, 6)``."""
    check_tensor(Xi, (4, 4), "Xi", "se3.vee")
    return torch.cat((Xi[..., :3, 3], _so3._vee(Xi[..., :3, :3])), -1)


def _ad(xi: torch.Tensor) -> torch.Tensor:
    W, V = _so3._hat(xi[..., 3:]), _so3._hat(xi[..., :3])
    return torch.cat((torch.cat((W, V), -1), torch.cat((torch.zeros_like(W), W), -1)), -2)


def ad(xi: torch.Tensor) -> torch.Tensor:
    """ad_ξ = [[ω̂, v̂], [0, ω̂]] ``(*, 6, 6)``, so ``ad_ξ1 ξ2 = [ξ1, ξ2]`` (seed 000 Eq. 4)."""
    check_tensor(xi, (6,), "xi", "se3.ad")
    return _ad(xi)


# --------------------------------------------------------------------------------------------------
# exp / log
# --------------------------------------------------------------------------------------------------

def _exp(xi: torch.Tensor) -> torch.Tensor:
    vx, vy, vz, wx, wy, wz = _so3._soa(xi, 6)
    theta2 = wx * wx + wy * wy + wz * wz
    k = _so3._coeffs(theta2, "a b c cos")
    r = _so3._rot_entries(wx, wy, wz, k)
    b, c = k["b"], k["c"]
    # t = J_l(ω) v = (1 − c θ²) v + b ω×v + c (ω·v) ω
    s = 1 - c * theta2
    cwv = c * (wx * vx + wy * vy + wz * vz)
    tx = s * vx + b * (wy * vz - wz * vy) + cwv * wx
    ty = s * vy + b * (wz * vx - wx * vz) + cwv * wy
    tz = s * vz + b * (wx * vy - wy * vx) + cwv * wz
    z, o = torch.zeros_like(theta2), torch.ones_like(theta2)
    out = torch.stack((r[0], r[1], r[2], tx, r[3], r[4], r[5], ty, r[6], r[7], r[8], tz, z, z, z, o), -1)
    return out.reshape(*xi.shape[:-1], 4, 4)


def exp(xi: torch.Tensor) -> torch.Tensor:
    """Exponential map ξ = [v, ω] ``(*, 6)`` -> X ``(*, 4, 4)``."""
    check_tensor(xi, (6,), "xi", "se3.exp")
    return _exp(xi)


# d(θ) = 1/θ² − (1 + cos θ)/(2 θ sin θ) = Σ_k 4^k |B_2k| y^(k−1)/(4 (2k)!) in y = θ²/4 (B: Bernoulli numbers),
# to y⁵: below the switch (y < 0.025 in float64, 0.125 otherwise) the next term is < 1e-16 (1e-12) of d
_D_SERIES = (1 / 12, 1 / 180, 1 / 1890, 1 / 18900, 1 / 187110, 691 / 1277025750)


def _log(X: torch.Tensor) -> torch.Tensor:
    # one pass over X's top 3×4 block gives K's rows for the rotation (see torchlie.so3), then t's
    K = _so3._k_rows(X.reshape(-1, 16)[:, :12], _so3.POS_SE3, (3, 7, 11))
    w, a, aw, n = _so3._log_tail(_so3._shepperd_row(K))
    t = K[16:]
    # d = (1 − (θ/2) cot(θ/2))/θ², the ω̂² coefficient of J_l(ω)⁻¹, with θ/2 = a and cot a = |w|/n from
    # the quaternion: no sin or cos.  In y = a² = θ²/4: the series below the switch, where the closed
    # form cancels (its derivative's error is ~ε/(4y)); safe-where: the closed form divides by 4y + 1
    # there, the series sees y clamped to the switch, and lerp with 0/1 weights selects exactly.
    y = a * a
    sw = 0.025 if y.dtype == torch.float64 else 0.125
    small = (y < sw).to(y.dtype)
    yc = torch.clamp(y, max=sw)
    one = y.new_ones(())
    series = torch.add(one * _D_SERIES[-2], yc, alpha=_D_SERIES[-1])
    for c in reversed(_D_SERIES[:-2]):
        series = torch.addcmul(one * c, series, yc)
    d = torch.lerp((1 - a * aw / n) / torch.add(small, y, alpha=4), series, small)
    # v = J_l(ω)⁻¹ t = (1 − d θ²) t − ½ ω×t + d (ω·t) ω  (the cross product entry by entry: cheaper
    # than torch.linalg.cross)
    b = torch.addcmul(torch.addcmul(one, d, y, value=-4) * t, d * (w * t).sum(0), w)
    (wx, wy, wz), (tx, ty, tz) = w, t
    vx = torch.addcmul(torch.addcmul(b[0], wz, ty, value=0.5), wy, tz, value=-0.5)
    vy = torch.addcmul(torch.addcmul(b[1], wx, tz, value=0.5), wz, tx, value=-0.5)
    vz = torch.addcmul(torch.addcmul(b[2], wy, tx, value=0.5), wx, ty, value=-0.5)
    out = w.new_empty(w.shape[1], 6)
    out[:, 0], out[:, 1], out[:, 2] = vx, vy, vz
    out[:, 3:].t().copy_(w)  # see torchlie.so3._aos
    return out.reshape(*X.shape[:-2], 6)


def log(X: torch.Tensor) -> torch.Tensor:
    """Logarithm X ``(*, 4, 4)`` -> principal ξ = [v, ω] ``(*, 6)`` with ``|ω| ≤ π``."""
    check_tensor(X, (4, 4), "X", "se3.log")
    return _log(X)


# --------------------------------------------------------------------------------------------------
# group operations
# --------------------------------------------------------------------------------------------------

def compose(X1: torch.Tensor, X2: torch.Tensor) -> torch.Tensor:
    """X1 X2 = [[R1 R2, R1 t2 + t1], [0, 1]] with broadcasting over leading dims.

    Reads only the top 3×4 blocks of the arguments; the bottom row is exactly [0, 0, 0, 1].
    """
    check_tensor(X1, (4, 4), "X1", "se3.compose")
    check_tensor(X2, (4, 4), "X2", "se3.compose")
    check_same_device("se3.compose", X1=X1, X2=X2)
    bottom = torch.tensor((0.0, 0.0, 0.0, 1.0), dtype=X1.dtype, device=X1.device)
    if torch.compiler.is_compiling():
        # inductor fuses this broadcast product-sum into one loop; a batched matmul of tiny matrices
        # stays an opaque, per-matrix library call
        # (with the bottom rows replaced by [0, 0, 0, 1], the 4×4 product is the SE(3) one)
        keep = torch.ones(4, 1, dtype=X1.dtype, device=X1.device)
        keep[3] = 0
        fill = torch.zeros(4, 4, dtype=X1.dtype, device=X1.device)
        fill[3] = bottom
        A, B = torch.addcmul(fill, X1, keep), torch.addcmul(fill, X2, keep)
        return (A.unsqueeze(-1) * B.unsqueeze(-3)).sum(-2)
    if X1.device.type != "cpu" or X1.dtype == torch.float64:
        top = torch.matmul(X1[..., :3, :3], X2[..., :3, :])
        top[..., 3] += X1[..., :3, 3]
        return torch.cat((top, bottom.expand(*top.shape[:-2], 1, 4)), -2)
    # On CPU a batched matmul of 4×4 matrices costs ~120 ns a matrix whatever the dtype; row i of
    # [R1 R2, R1 t2] as three multiply-adds of X2's rows is memory-bound, so cheaper in float32 (not
    # in float64, where reading the strided rows costs more than the matmul's arithmetic; measured)
    rows = [_so3._row_times(X1, X2, i, 3) for i in range(3)]
    out = torch.stack((*rows, bottom.expand_as(rows[0])), -2)
    out[..., :3, 3] += X1[..., :3, 3]
    return out


# X⁻¹'s row-major entries as indices into X's: Rᵀ, with t (overwritten by −Rᵀ t) and the bottom row
_INV_INDEX = (0, 4, 8, 3, 1, 5, 9, 7, 2, 6, 10, 11, 12, 13, 14, 15)


def inverse(X: torch.Tensor) -> torch.Tensor:
    """X⁻¹ = [[Rᵀ, −Rᵀ t], [0, 1]]."""
    check_tensor(X, (4, 4), "X", "se3.inverse")
    if torch.compiler.is_compiling():
        return _assemble(X[..., :3, :3].transpose(-1, -2), -(X[..., :3, :3] * X[..., :3, 3:]).sum(-2))
    # one gather permutes Rᵀ's entries in the matrices' own layout (a transposing copy or a batched
    # matmul of the whole block costs several times more)
    Xf = X.reshape(*X.shape[:-2], 16)
    out = Xf.gather(-1, torch.tensor(_INV_INDEX, device=X.device).expand(Xf.shape)).view(X.shape)
    if X.dtype == torch.float64:
        # −Rᵀ t as the batched row-vector product −tᵀ R: in float64 about twice as fast on CPU as the
        # three multiply-adds below, whose inner loops are only 3 long (measured; a tie in float32)
        tn = torch.matmul(X[..., :3, 3].unsqueeze(-2), X[..., :3, :3]).squeeze(-2)
    else:
        # −Rᵀ t = −Σ_k R[k, :] t_k: three multiply-adds on rows
        tn = X[..., 0, :3] * X[..., 0, 3:]
        tn = torch.addcmul(torch.addcmul(tn, X[..., 1, :3], X[..., 1, 3:]), X[..., 2, :3], X[..., 2, 3:])
    out[..., :3, 3] = tn.neg_()
    out[..., 3, :] = torch.tensor((0.0, 0.0, 0.0, 1.0), dtype=X.dtype, device=X.device)
    return out


def act(X: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """Transform points: X ``(*, 4, 4)``, p ``(*, 3)`` -> R p + t ``(*, 3)`` (leading dims broadcast)."""
    check_tensor(X, (4, 4), "X", "se3.act")
    check_tensor(p, (3,), "p", "se3.act")
    check_same_device("se3.act", X=X, p=p)
    # t + Σ_k R[:, k] p_k as three fused multiply-adds (several times faster than a batched matmul
    # of 3×3 by 3×1 plus an add); the first one allocates the (broadcast) output
    out = torch.addcmul(X[..., :3, 3], X[..., :3, 0], p[..., 0:1])
    return out.addcmul_(X[..., :3, 1], p[..., 1:2]).addcmul_(X[..., :3, 2], p[..., 2:3])


def adjoint(X: torch.Tensor) -> torch.Tensor:
    """Ad_X = [[R, t̂ R], [0, R]] ``(*, 6, 6)``: ``X exp(ξ) X⁻¹ = exp(Ad_X ξ)``."""
    check_tensor(X, (4, 4), "X", "se3.adjoint")
    R, t = X[..., :3, :3], X[..., :3, 3]
    return torch.cat((torch.cat((R, _so3._hat(t) @ R), -1), torch.cat((torch.zeros_like(R), R), -1)), -2)


# --------------------------------------------------------------------------------------------------
# Jacobians
# --------------------------------------------------------------------------------------------------

# Taylor coefficients (in θ²) of b = (1 − cos θ)/θ², k1 = (θ − sin θ)/θ³ (J's c),
# k2 = (θ² + 2 cos θ − 2)/(2θ⁴) and k3 = (2θ − 3 sin θ + θ cos θ)/(2θ⁵)
_SERIES_B = (1 / 2, -1 / 24, 1 / 720, -1 / 40320, 1 / 3628800)
_SERIES_K1 = (1 / 6, -1 / 120, 1 / 5040, -1 / 362880, 1 / 39916800)
_SERIES_K2 = (1 / 24, -1 / 720, 1 / 40320, -1 / 3628800, 1 / 479001600)
_SERIES_K3 = (1 / 120, -1 / 2520, 1 / 120960, -1 / 9979200, 1 / 1245404160)


def _jac_coeffs(theta2: torch.Tensor, need_b: bool = True) -> tuple[torch.Tensor | None, ...]:
    """``(b, k1, k2, k3)`` of J_l(ω) = I + b ω̂ + k1 ω̂² and of Q (see :func:`_q_entries`).

    One switch and one sin/cos for all four: the series (to θ⁸) below θ² = 0.05 (float64) / 0.5,
    the closed forms above, safe-``where`` style (closed forms on θ² + 1 where the series is taken,
    series on θ² clamped to the switch elsewhere) and selected by exact 0/1 blends.
    """
    sw = 0.05 if theta2.dtype == torch.float64 else 0.5
    small, big = _so3._mask(theta2 < sw, theta2.dtype)
    t2 = theta2 + small
    th = torch.sqrt(t2)
    s, co = torch.sin(th), torch.cos(th)
    x = torch.clamp(theta2, max=sw)
    t4 = t2 * t2
    blend = _so3._blend
    b = blend(small, big, horner(x, _SERIES_B), (1 - co) / t2) if need_b else None
    k1 = blend(small, big, horner(x, _SERIES_K1), (th - s) / (t2 * th))
    k2 = blend(small, big, horner(x, _SERIES_K2), (t2 + 2 * co - 2) / (2 * t4))
    k3 = blend(small, big, horner(x, _SERIES_K3), (2 * th - 3 * s + th * co) / (2 * t4 * th))
    return b, k1, k2, k3


def _q_entries(v, w, theta2, k1, k2, k3, sign: float, scale: float = 1.0) -> tuple[torch.Tensor, ...]:
    """Row-major entries of ``scale · Q(sign·v, sign·ω)``, Q the off-diagonal block of J_l (Solà Eq. 180).

    Eq. 180 is a sum of products of ω̂ and v̂; with ``â b̂ = b aᵀ − (a·b) I``, ``ω̂ v̂ ω̂ = −σ ω̂`` and
    ``ω̂² = ω ωᵀ − θ² I`` (σ = ω·v) it collapses to outer products, with no 3×3 matrix product:
    ``Q = û + k1 (v ωᵀ + ω vᵀ) − 2 k3 σ ω ωᵀ + 2 σ (k3 θ² − k1) I`` with
    ``u = (½ − k2 θ²) v + (2 k2 − k1) σ ω``.  Under ξ → −ξ only û changes sign.
    """
    vx, vy, vz = v
    wx, wy, wz = w
    sig = wx * vx + wy * vy + wz * vz
    al = (sign * scale) * (0.5 - k2 * theta2)
    be = ((sign * scale) * (2 * k2 - k1)) * sig
    ux, uy, uz = (torch.addcmul(al * vc, be, wc) for vc, wc in ((vx, wx), (vy, wy), (vz, wz)))
    p = (-2 * scale) * k3 * sig
    dd = (2 * scale) * sig * (k3 * theta2 - k1)
    if scale != 1.0:
        k1 = scale * k1
    gx, gy, gz = k1 * vx, k1 * vy, k1 * vz
    hx, hy = p * wx, p * wy
    # symmetric part: S_ij = k1 (v_i ω_j + ω_i v_j) + p ω_i ω_j (+ dd on the diagonal)
    sxy = torch.addcmul(torch.addcmul(gx * wy, gy, wx), hx, wy)
    sxz = torch.addcmul(torch.addcmul(gx * wz, gz, wx), hx, wz)
    syz = torch.addcmul(torch.addcmul(gy * wz, gz, wy), hy, wz)
    q00 = torch.addcmul(dd, torch.add(hx, gx, alpha=2), wx)
    q11 = torch.addcmul(dd, torch.add(hy, gy, alpha=2), wy)
    q22 = torch.addcmul(dd, torch.addcmul(gz * 2, p, wz), wz)
    return (q00, sxy - uz, sxz + uy,
            sxy + uz, q11, syz - ux,
            sxz - uy, syz + ux, q22)


def _six_by_six(D: tuple[torch.Tensor, ...], T: tuple[torch.Tensor, ...], shape) -> torch.Tensor:
    """[[D, T], [0, D]] ``(*shape, 6, 6)`` from the row-major entries of the 3×3 blocks, one stack."""
    z = torch.zeros_like(D[0])
    rows = (*D[0:3], *T[0:3], *D[3:6], *T[3:6], *D[6:9], *T[6:9],
            z, z, z, *D[0:3], z, z, z, *D[3:6], z, z, z, *D[6:9])
    return torch.stack(rows, -1).reshape(*shape, 6, 6)


def _jac(xi: torch.Tensor, sign: float) -> torch.Tensor:
    """J_l(sign·ξ) = [[J_l(sign·ω), Q(sign·v, sign·ω)], [0, J_l(sign·ω)]], entry by entry (SoA)."""
    vx, vy, vz, wx, wy, wz = _so3._soa(xi, 6)
    theta2 = wx * wx + wy * wy + wz * wz
    b, k1, k2, k3 = _jac_coeffs(theta2)
    J = _so3._sym_skew_entries(wx, wy, wz, 1 - k1 * theta2, sign * b, k1)
    Q = _q_entries((vx, vy, vz), (wx, wy, wz), theta2, k1, k2, k3, sign)
    return _six_by_six(J, Q, xi.shape[:-1])


def _jac_inv(xi: torch.Tensor, sign: float) -> torch.Tensor:
    """J_l(sign·ξ)⁻¹ = [[J⁻¹, −J⁻¹ Q J⁻¹], [0, J⁻¹]] (block-triangular inverse), J = J_l(sign·ω)."""
    vx, vy, vz, wx, wy, wz = _so3._soa(xi, 6)
    theta2 = wx * wx + wy * wy + wz * wz
    d = _so3._coeffs(theta2, "d")["d"]
    _, k1, k2, k3 = _jac_coeffs(theta2, need_b=False)
    Ji = _so3._sym_skew_entries(wx, wy, wz, 1 - d * theta2, -0.5 * sign, d)
    minus_Q = _q_entries((vx, vy, vz), (wx, wy, wz), theta2, k1, k2, k3, sign, scale=-1.0)
    return _six_by_six(Ji, _so3._mat3(Ji, _so3._mat3(minus_Q, Ji)), xi.shape[:-1])


def left_jacobian(xi: torch.Tensor) -> torch.Tensor:
    """J_l(ξ) ``(*, 6, 6)``: ``exp(ξ + δ) ≈ exp(J_l δ) exp(ξ)``."""
    check_tensor(xi, (6,), "xi", "se3.left_jacobian")
    return _jac(xi, 1.0)


def right_jacobian(xi: torch.Tensor) -> torch.Tensor:
    """J_r(ξ) = J_l(−ξ) ``(*, 6, 6)``: ``exp(ξ + δ) ≈ exp(ξ) exp(J_r δ)``."""
    check_tensor(xi, (6,), "xi", "se3.right_jacobian")
    return _jac(xi, -1.0)


def left_jacobian_inv(xi: torch.Tensor) -> torch.Tensor:
    """J_l(ξ)⁻¹ in closed form (block-triangular inverse)."""
    check_tensor(xi, (6,), "xi", "se3.left_jacobian_inv")
    return _jac_inv(xi, 1.0)


def right_jacobian_inv(xi: torch.Tensor) -> torch.Tensor:
    """J_r(ξ)⁻¹ = J_l(−ξ)⁻¹ in closed form."""
    check_tensor(xi, (6,), "xi", "se3.right_jacobian_inv")
    return _jac_inv(xi, -1.0)


# --------------------------------------------------------------------------------------------------
# constructors
# --------------------------------------------------------------------------------------------------

def identity(*batch, dtype: torch.dtype | None = None, device=None) -> torch.Tensor:
    """Identity transforms ``(*batch, 4, 4)``."""
    shape = batch_shape(batch, "se3.identity")
    return torch.eye(4, dtype=float_dtype(dtype, "se3.identity"), device=device).expand(*shape, 4, 4).clone()


def random(*batch, generator: torch.Generator | None = None, dtype: torch.dtype | None = None,
           device=None, scale: float = 1.0) -> torch.Tensor:
    """Random transforms ``(*batch, 4, 4)``: Haar-uniform rotation, translation ~ N(0, scale² I)."""
    shape = batch_shape(batch, "se3.random")
    dtype = float_dtype(dtype, "se3.random")
    device = rng_device(generator, device)
    R = _so3.random(*shape, generator=generator, dtype=dtype, device=device)
    t = scale * torch.randn(*shape, 3, generator=generator, dtype=dtype, device=device)
    return _assemble(R, t)


def interpolate(X0: torch.Tensor, X1: torch.Tensor, t) -> torch.Tensor:
    """Geodesic ``X0 exp(t log(X0⁻¹ X1))`` (constant twist); ``t`` a float or a broadcasting tensor."""
    check_tensor(X0, (4, 4), "X0", "se3.interpolate")
    check_tensor(X1, (4, 4), "X1", "se3.interpolate")
    check_same_device("se3.interpolate", X0=X0, X1=X1)
    X0, X1 = broadcast_leading(X0, 2, X1, 2, "se3.interpolate", ("X0", "X1"))
    xi = _log(inverse(X0) @ X1)
    t = scalar_param(t, xi, "se3.interpolate", "t", "X0")
    return X0 @ _exp(xi * t.unsqueeze(-1))
