"""SO(3): 3-D rotations as rotation matrices ``(*, 3, 3)``; tangent vectors ω ``(*, 3)``.

The contract (shapes, Jacobian conventions, broadcasting) is written once in :mod:`torchlie`.
Formulas: Solà, Deray, Atchuthan, *A micro Lie theory for state estimation in robotics* (2018),
Eq. 143-146 (exp/log, right and left Jacobians and their inverses); the log goes through the
unit quaternion of the rotation (Shepperd's largest-diagonal branch) so that it stays accurate at
every angle, including within 1e-9 of π, where the usual ``(R - Rᵀ)/(2 sin θ)`` formula breaks down.

Small-angle branches use the safe-``where`` pattern: the closed form is evaluated on a harmless
argument where the Taylor series is taken, so values *and* gradients are finite at exactly 0.
"""

from __future__ import annotations

import torch

from torchlie._batch import (
    _is_wrapped,
    _plain,
    batch_shape,
    broadcast_leading,
    broadcast_shapes,
    check_same_device,
    check_tensor,
    float_dtype,
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
    "angle",
    "project",
    "to_quaternion",
    "from_quaternion",
]

DIM = 3  # dimension of the tangent space
MATRIX = 3  # size of the group matrix


# --------------------------------------------------------------------------------------------------
# scalar coefficient functions of θ² with safe small-angle series
# --------------------------------------------------------------------------------------------------

def _switch(dtype: torch.dtype) -> float:
    """θ² below which the Taylor series (to θ⁶ relative) is used: exact to the dtype's resolution."""
    return 1e-2 if dtype == torch.float64 else 1e-1


def _mask(cond: torch.Tensor, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """A boolean condition as complementary 0/1 float masks ``(m, 1 − m)``."""
    m = cond.to(dtype)
    return m, 1 - m


def _blend(m: torch.Tensor, mc: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``a`` where ``m == 1`` and ``b`` where ``mc == 1``, exactly (``x·1 + y·0 = x`` for finite y).

    Used instead of ``torch.where``, which is not vectorized on CPU and costs ~20 multiplications
    per call; both branches must be finite everywhere (the safe-``where`` pattern guarantees it),
    and then the gradient of the unselected branch is multiplied by an exact zero.
    """
    return torch.addcmul(a * m, b, mc)


def _coeffs(theta2: torch.Tensor, need: str) -> dict[str, torch.Tensor]:
    """Coefficients of θ² used by exp and the Jacobians.

    ``a = sin θ/θ``, ``b = (1 - cos θ)/θ²``, ``c = (θ - sin θ)/θ³``, ``cos = cos θ``,
    ``d = (1/θ²)(1 - θ sin θ / (2(1 - cos θ)))`` (the ω̂² coefficient of J⁻¹).
    Below :func:`_switch` the Taylor series (to the θ⁶ term) is taken, above it the closed form.
    Branch-free and safe: the closed forms see θ² + 1 ≥ 1 where the series is used, and the series
    see θ² clamped to the switch where the closed form is used, so both stay finite everywhere and
    no NaN or inf reaches autograd.
    """
    sw = _switch(theta2.dtype)
    small, big = _mask(theta2 < sw, theta2.dtype)
    t2 = theta2 + small
    th = torch.sqrt(t2)
    x = torch.clamp(theta2, max=sw)
    out: dict[str, torch.Tensor] = {}
    if "a" in need or "d" in need or "c" in need:
        s = torch.sin(th)
    if "b" in need or "cos" in need or "d" in need:
        co = torch.cos(th)
    if "a" in need:
        out["a"] = _blend(small, big, 1 - x / 6 * (1 - x / 20 * (1 - x / 42 * (1 - x / 72))), s / th)
    if "b" in need or "cos" in need:
        out["b"] = _blend(small, big, 0.5 - x / 24 * (1 - x / 30 * (1 - x / 56 * (1 - x / 90))),
                          (1 - co) / t2)
    if "cos" in need:
        # cos θ = 1 − θ² b: exact to the dtype's absolute resolution, no branch of its own
        out["cos"] = 1 - theta2 * out["b"]
    if "c" in need:
        out["c"] = _blend(small, big, 1 / 6 - x / 120 * (1 - x / 42 * (1 - x / 72 * (1 - x / 110))),
                          (th - s) / (t2 * th))
    if "d" in need:
        # d = 1/12 + θ²/720 + θ⁴/30240 + θ⁶/1209600 + ...
        out["d"] = _blend(small, big, 1 / 12 + x / 720 + x * x / 30240 + x * x * x / 1209600,
                          (1 - th * s / (2 * (1 - co))) / t2)
    return out


# --------------------------------------------------------------------------------------------------
# algebra
# --------------------------------------------------------------------------------------------------

def _hat(w: torch.Tensor) -> torch.Tensor:
    x, y, z = w.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack((o, -z, y, z, o, -x, -y, x, o), dim=-1).reshape(*w.shape[:-1], 3, 3)


def hat(omega: torch.Tensor) -> torch.Tensor:
    """ω ``(*, 3)`` -> skew-symmetric ω̂ ``(*, 3, 3)`` with ``ω̂ p = ω × p`` (seed 000 Eq. 1)."""
    check_tensor(omega, (3,), "omega", "so3.hat")
    return _hat(omega)


def vee(Omega: torch.Tensor) -> torch.Tensor:
    """Skew matrix ``(*, 3, 3)`` -> ω ``(*, 3)``; the symmetric part of a non-skew input is ignored."""
    check_tensor(Omega, (3, 3), "Omega", "so3.vee")
    return _vee(Omega)


def _vee(M: torch.Tensor) -> torch.Tensor:
    return 0.5 * torch.stack((M[..., 2, 1] - M[..., 1, 2], M[..., 0, 2] - M[..., 2, 0],
                              M[..., 1, 0] - M[..., 0, 1]), dim=-1)


def ad(omega: torch.Tensor) -> torch.Tensor:
    """ad_ω = ω̂ ``(*, 3, 3)``: ``ad_ω η = ω × η`` (seed 000 Eq. 3)."""
    check_tensor(omega, (3,), "omega", "so3.ad")
    return _hat(omega)


# --------------------------------------------------------------------------------------------------
# exp / log
# --------------------------------------------------------------------------------------------------

def _soa(x: torch.Tensor, k: int) -> tuple[torch.Tensor, ...]:
    """The ``k`` trailing components of ``x`` ``(*B, k)`` as contiguous flat tensors ``(prod(B),)``.

    One transposing copy up front makes every following elementwise op run on contiguous memory,
    which is several times faster than operating on strided component views.
    """
    if torch.compiler.is_compiling():
        # inductor fuses the whole kernel into one loop: strided reads are free there, a copy is not
        return x.reshape(-1, k).unbind(-1)
    return x.reshape(-1, k).t().contiguous().unbind(0)


def _mat3(a: tuple[torch.Tensor, ...], b: tuple[torch.Tensor, ...]) -> tuple[torch.Tensor, ...]:
    """Row-major entries of the product of two 3×3 matrices given by their row-major entries
    (component tensors): 27 fused multiply-adds on contiguous rows instead of a per-matrix matmul."""
    return tuple(torch.addcmul(torch.addcmul(a[3 * i] * b[j], a[3 * i + 1], b[3 + j]), a[3 * i + 2], b[6 + j])
                 for i in range(3) for j in range(3))


def _sym_skew_entries(wx, wy, wz, diag, k_skew, k_outer) -> tuple[torch.Tensor, ...]:
    """Row-major entries of ``diag I + k_skew ω̂ + k_outer ω ωᵀ`` from the components of ω
    (Rodrigues' R, the Jacobians and their inverses all have this form); ``k_skew`` may be a float."""
    qx, qy, qz = k_outer * wx, k_outer * wy, k_outer * wz
    hx, hy, hz = k_skew * wx, k_skew * wy, k_skew * wz
    qxy, qxz, qyz = qx * wy, qx * wz, qy * wz
    return (torch.addcmul(diag, qx, wx), qxy - hz, qxz + hy,
            qxy + hz, torch.addcmul(diag, qy, wy), qyz - hx,
            qxz - hy, qyz + hx, torch.addcmul(diag, qz, wz))


def _rot_entries(wx, wy, wz, k) -> tuple[torch.Tensor, ...]:
    """Row-major entries of R = cos θ I + a ω̂ + b ω ωᵀ from the components of ω."""
    return _sym_skew_entries(wx, wy, wz, k["cos"], k["a"], k["b"])


def _exp(w: torch.Tensor) -> torch.Tensor:
    wx, wy, wz = _soa(w, 3)
    k = _coeffs(wx * wx + wy * wy + wz * wz, "a b cos")
    return torch.stack(_rot_entries(wx, wy, wz, k), -1).reshape(*w.shape[:-1], 3, 3)


def exp(omega: torch.Tensor) -> torch.Tensor:
    """Exponential map ω ``(*, 3)`` -> R ``(*, 3, 3)`` (Rodrigues)."""
    check_tensor(omega, (3,), "omega", "so3.exp")
    return _exp(omega)


def _quat_from_entries(r: tuple[torch.Tensor, ...]) -> tuple[torch.Tensor, ...]:
    """Quaternion components ``(w, x, y, z)``, w ≥ 0, from the 9 row-major entries of R.

    Shepperd's method, batched without Python branching: of the four formulas, the one whose
    ``4 q_i² = d_i`` is largest is selected elementwise, so the divisor ``2 sqrt(d_i) ≥ 2`` never
    approaches zero.  Only the selected formula receives gradient, and every candidate is finite.
    """
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = r
    tr = r00 + r11 + r22
    d0, d1, d2, d3 = 1 + tr, 1 + r00 - r11 - r22, 1 - r00 + r11 - r22, 1 - r00 - r11 + r22
    # elementwise argmax of (d0, d1, d2, d3) as masks (a reduction over a stacked dim is much slower)
    e0 = (d0 >= d1) & (d0 >= d2) & (d0 >= d3)
    e1 = ~e0 & (d1 >= d2) & (d1 >= d3)
    e2 = ~(e0 | e1) & (d2 >= d3)
    m0, m1, m2 = e0.to(tr.dtype), e1.to(tr.dtype), e2.to(tr.dtype)
    m3 = 1 - m0 - m1 - m2  # one-hot: exactly one of m0..m3 is 1

    def pick(v0, v1, v2, v3):  # exact selection (see _blend)
        return torch.addcmul(torch.addcmul(torch.addcmul(v0 * m0, v1, m1), v2, m2), v3, m3)

    dsel = pick(d0, d1, d2, d3)
    a21, a02, a10 = r21 - r12, r02 - r20, r10 - r01
    b10, b02, b21 = r10 + r01, r02 + r20, r21 + r12
    # dsel ≥ 1 (the four d_i sum to 4), so the divisor never approaches zero
    h = 0.5 * torch.rsqrt(dsel)
    # numerators of (w, x, y, z) for the branches (w, x, y, z) — see the docstring
    qw = pick(dsel, a21, a02, a10) * h
    qx = pick(a21, dsel, b10, b02) * h
    qy = pick(a02, b10, dsel, b21) * h
    qz = pick(a10, b02, b21, dsel) * h
    sgn = 1 - 2 * (qw < 0).to(qw.dtype)
    return qw * sgn, qx * sgn, qy * sgn, qz * sgn


# The logarithm goes through Shepperd's matrix K = 4 q qᵀ of the unit quaternion q = (w, x, y, z) of R,
# which is linear in R: diagonal d_i = 4 q_i² (1 + tr R, 1 + r00 − r11 − r22, …), off-diagonal 4 w x =
# r21 − r12, …, 4 x y = r01 + r10, ….  Row k of K is 4 q_k q, the quaternion up to the factor 4 q_k; the
# row with the largest d_k (≥ 1, as the four sum to 4) is the quaternion scaled by 4 q_k ≥ 2 with no
# division at all, and the log only needs q up to a positive scale and its sign (see _log_tail).
# K's 16 entries are rows of one (16, N) tensor (structure of arrays), the rows of K in the order
# (w, y, x, z) so that the two first-round matches of the largest-d_k tournament (w vs x, y vs z) are the
# (2, 4, N) halves K[0:8] vs K[8:16].
_K_ENTRIES = ("d0", "a21", "a02", "a10", "a02", "b10", "d2", "b21",
              "a21", "d1", "b10", "b02", "a10", "b02", "b21", "d3")
# each entry as (sign, index into the row-major r00 … r22); the d_i also get + 1
_K_TERMS = {"d0": ((1, 0), (1, 4), (1, 8)), "d1": ((1, 0), (-1, 4), (-1, 8)),
            "d2": ((-1, 0), (1, 4), (-1, 8)), "d3": ((-1, 0), (-1, 4), (1, 8)),
            "a21": ((1, 7), (-1, 5)), "a02": ((1, 2), (-1, 6)), "a10": ((1, 3), (-1, 1)),
            "b10": ((1, 3), (1, 1)), "b02": ((1, 2), (1, 6)), "b21": ((1, 7), (1, 5))}
# flat positions of r00 … r22 in a flattened (*, 3, 3) rotation / (*, 4, 4) homogeneous matrix
POS_SO3 = (0, 1, 2, 3, 4, 5, 6, 7, 8)
POS_SE3 = (0, 1, 2, 4, 5, 6, 8, 9, 10)
_K_COEF: dict = {}


def _k_coef(width: int, pos: tuple[int, ...], extra: tuple[int, ...], dtype, device) -> torch.Tensor:
    """``(16 + len(extra), width)`` matrix of ±1/0 mapping a flattened matrix to K's entries (less the 1
    on the diagonal) followed by the entries at ``extra``; built once per dtype and device."""
    key = (width, pos, extra, dtype, device)
    C = _K_COEF.get(key)
    if C is None:
        with torch.inference_mode(False):  # a cached inference tensor could not be saved for backward
            C = torch.zeros(16 + len(extra), width, dtype=torch.float64)
            for i, name in enumerate(_K_ENTRIES):
                for s, j in _K_TERMS[name]:
                    C[i, pos[j]] = s
            for i, j in enumerate(extra):
                C[16 + i, j] = 1
            C = _K_COEF[key] = C.to(dtype=dtype, device=device)
    return C


def _k_rows(Xf: torch.Tensor, pos: tuple[int, ...], extra: tuple[int, ...] = ()) -> torch.Tensor:
    """K's 16 entries, then the entries ``extra`` of ``Xf`` ``(N, width)``, as rows of a ``(16 + e, N)``
    tensor (see above).

    On CPU one small matrix product with the ±1/0 coefficients does it (the same sums of two or three
    entries as the elementwise form, up to their order), reading the matrices in their own layout:
    several times cheaper than the transposing copy plus 14 additions it replaces (measured).  It is
    only taken where float32 products are exact (``torch.get_float32_matmul_precision() ==
    "highest"``; "high"/"medium" may round the inputs to bfloat16); elsewhere, on GPUs and under
    ``torch.compile`` (where the elementwise form fuses into one kernel) the entries are computed
    elementwise.
    """
    dt = Xf.dtype
    if (Xf.device.type == "cpu" and not torch.compiler.is_compiling()
            and (dt == torch.float64 or (dt == torch.float32
                                         and torch.get_float32_matmul_precision() == "highest"))):
        K = torch.mm(_k_coef(Xf.shape[-1], pos, extra, dt, Xf.device), Xf.t())
        K[0:16:9].add_(1)  # d0, d1
        K[6:16:9].add_(1)  # d2, d3
        return K
    e = Xf.unbind(-1)
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = (e[p] for p in pos)
    a21, a02, a10 = r21 - r12, r02 - r20, r10 - r01
    b10, b02, b21 = r10 + r01, r02 + r20, r21 + r12
    d0, d1 = 1 + r00 + r11 + r22, 1 + r00 - r11 - r22
    d2, d3 = 1 - r00 + r11 - r22, 1 - r00 - r11 + r22
    return torch.stack((d0, a21, a02, a10, a02, b10, d2, b21,
                        a21, d1, b10, b02, a10, b02, b21, d3, *(e[j] for j in extra)))


def _shepperd_row(K: torch.Tensor) -> torch.Tensor:
    """The row of K ``(16, N)`` with the largest diagonal entry: ``4 q_k (w, x, y, z)`` ``(4, N)``.

    A two-round tournament, without Python branching: w vs x and y vs z, then the two winners, each
    round a comparison of diagonal entries and one ``lerp`` with 0/1 weights (exact: PyTorch's lerp
    returns ``end`` itself for weight 1), which is cheaper than any mask arithmetic or ``torch.where``
    on CPU.  Only the selected row receives gradient.
    """
    N = K.shape[-1]
    lo, hi = K[0:16:6][:2].detach(), K[9:16:6].detach()  # (d0, d2), (d1, d3)
    c2 = _greater(hi, lo)
    m = torch.maximum(lo, hi)
    c = _greater(m[1], m[0])
    K4 = K[:16].view(2, 2, 4, N)
    q2 = torch.lerp(K4[0], K4[1], c2.unsqueeze(1))
    return torch.lerp(q2[0], q2[1], c)


def _greater(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``a > b`` as 1.0/0.0 in their dtype: ``(a − b).gt_(0)``, several times cheaper on CPU than
    ``(a > b).to(dtype)`` (measured), except where the in-place comparison has no vmap batching rule."""
    if torch.compiler.is_compiling() or _is_wrapped is None or _is_wrapped(a) or _is_wrapped(b):
        return (a > b).to(a.dtype)
    return torch.sub(a, b).gt_(0)


_TINY: dict = {}


def _log_tail(q: torch.Tensor, out: torch.Tensor | None = None
              ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(ω, a, |w|, n)`` for a quaternion ``q`` ``(4, N)`` of any scale and sign; ω ``(3, N)``, written
    into ``out`` if given (an out= kernel: only for arguments without autograd, see :func:`_plain`).

    With ``s = ±1`` the sign of w (+1 at w = +0), ``a = atan2(n, s w) = θ/2 ∈ [0, π/2]``, ``n = |(x, y,
    z)|`` and ``ω = (2 s a/n) (x, y, z)``: the logarithm of s q (that of q).  Scale-invariant and accurate
    to the dtype's resolution at every angle, π included; at exactly π (w = 0) the derivative is that of
    the branch returned (s w rather than |w|, whose derivative vanishes at 0).  No series is needed near
    θ = 0: ``atan2(n, |w|)/n`` is accurate for any n > 0 (and so is its autograd derivative, to absolute
    ε), so n² is only kept away from 0 — at ``√tiny``, where 2a/n = 2/|w| to far below ε — and values
    and gradients stay finite at θ = 0.
    """
    w, v = q[0], q[1:]
    floor = _TINY.get(q.dtype)
    if floor is None:
        floor = _TINY[q.dtype] = torch.finfo(q.dtype).tiny ** 0.5
    n = torch.addcmul(torch.addcmul(v[0] * v[0], v[1], v[1]), v[2], v[2]).clamp_min_(floor).sqrt_()
    s = torch.copysign(w.new_ones(()), w)
    aw = w * s
    a = torch.atan2(n, aw)
    f = (a / n).mul_(s).mul_(2)
    return (v * f if out is None else torch.mul(v, f, out=out)), a, aw, n


def _log(R: torch.Tensor) -> torch.Tensor:
    q = _shepperd_row(_k_rows(R.reshape(-1, 9), POS_SO3))
    if _plain(R):  # ω straight into the transposed view of the (N, 3) result
        out = R.new_empty(q.shape[1], 3)
        _log_tail(q, out.t())
        return out.reshape(*R.shape[:-2], 3)
    return _aos(_log_tail(q)[0]).reshape(*R.shape[:-2], 3)


def _aos(rows: torch.Tensor) -> torch.Tensor:
    """``(k, N)`` rows -> contiguous ``(N, k)``: a copy into the transposed view of a new tensor, about
    twice as fast on CPU as ``torch.stack(rows, -1)`` or ``rows.t().contiguous()`` (measured)."""
    out = rows.new_empty(rows.shape[1], rows.shape[0])
    out.t().copy_(rows)
    return out


def _to_quaternion(R: torch.Tensor) -> torch.Tensor:
    q = torch.stack(_quat_from_entries(_soa(R.reshape(*R.shape[:-2], 9), 9)), -1).reshape(*R.shape[:-2], 4)
    return q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)


def log(R: torch.Tensor) -> torch.Tensor:
    """Logarithm R ``(*, 3, 3)`` -> principal ω ``(*, 3)`` with ``|ω| ≤ π``.

    Exact to the dtype's resolution at every angle (via the quaternion, see module docstring).
    At exactly θ = π both ±ω are logarithms; the one returned is fixed by the quaternion sign.
    """
    check_tensor(R, (3, 3), "R", "so3.log")
    return _log(R)


def to_quaternion(R: torch.Tensor) -> torch.Tensor:
    """Rotation matrix ``(*, 3, 3)`` -> unit quaternion ``(*, 4)`` in ``(w, x, y, z)`` order, w ≥ 0."""
    check_tensor(R, (3, 3), "R", "so3.to_quaternion")
    return _to_quaternion(R)


def from_quaternion(q: torch.Tensor) -> torch.Tensor:
    """Quaternion ``(*, 4)`` in ``(w, x, y, z)`` order (normalized here) -> rotation matrix ``(*, 3, 3)``."""
    check_tensor(q, (4,), "q", "so3.from_quaternion")
    q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    return torch.stack((
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ), dim=-1).reshape(*q.shape[:-1], 3, 3)


def angle(R: torch.Tensor) -> torch.Tensor:
    """Rotation angle θ ∈ [0, π] of R ``(*, 3, 3)`` (accurate near 0 and π)."""
    check_tensor(R, (3, 3), "R", "so3.angle")
    q = _to_quaternion(R)
    return 2 * torch.atan2(torch.linalg.vector_norm(q[..., 1:], dim=-1), q[..., 0])


# --------------------------------------------------------------------------------------------------
# group operations
# --------------------------------------------------------------------------------------------------

def compose(R1: torch.Tensor, R2: torch.Tensor) -> torch.Tensor:
    """R1 R2 with broadcasting over leading dims."""
    check_tensor(R1, (3, 3), "R1", "so3.compose")
    check_tensor(R2, (3, 3), "R2", "so3.compose")
    check_same_device("so3.compose", R1=R1, R2=R2)
    if torch.compiler.is_compiling():
        # inductor fuses this broadcast product-sum into one loop; a batched matmul of tiny matrices
        # stays an opaque, per-matrix library call
        return (R1.unsqueeze(-1) * R2.unsqueeze(-3)).sum(-2)
    if R1.device.type != "cpu" or R1.dtype == torch.float64:
        return torch.matmul(R1, R2)
    # On CPU a batched matmul of 3×3 matrices costs ~60 ns a matrix whatever the dtype; row i of the
    # product as three multiply-adds of R2's rows is memory-bound, so cheaper in float32 (and not
    # in float64, where reading the strided rows costs more than the matmul's arithmetic; measured).
    if _plain(R1, R2):
        # the rows accumulate in place in the output (out= kernels): no temporaries, no final copy;
        # ~20 % faster than stacking the rows (measured), but out= supports neither autograd nor vmap
        out = R1.new_empty(broadcast_shapes(R1.shape, R2.shape))
        for i in range(3):
            o = out[..., i, :]
            torch.mul(R1[..., i, 0:1], R2[..., 0, :], out=o)
            o.addcmul_(R1[..., i, 1:2], R2[..., 1, :]).addcmul_(R1[..., i, 2:3], R2[..., 2, :])
        return out
    return torch.stack([_row_times(R1, R2, i, 3) for i in range(3)], -2)


def _row_times(A: torch.Tensor, B: torch.Tensor, i: int, k: int) -> torch.Tensor:
    """Row ``i`` of ``A[..., :, :k] @ B[..., :k, :]`` as ``k`` multiply-adds of B's rows."""
    out = A[..., i, 0:1] * B[..., 0, :]
    for j in range(1, k):
        out = torch.addcmul(out, A[..., i, j:j + 1], B[..., j, :])
    return out


def inverse(R: torch.Tensor) -> torch.Tensor:
    """R⁻¹ = Rᵀ."""
    check_tensor(R, (3, 3), "R", "so3.inverse")
    return R.transpose(-1, -2)


def act(R: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """Rotate points: R ``(*, 3, 3)``, p ``(*, 3)`` -> R p ``(*, 3)`` (leading dims broadcast)."""
    check_tensor(R, (3, 3), "R", "so3.act")
    check_tensor(p, (3,), "p", "so3.act")
    check_same_device("so3.act", R=R, p=p)
    out = R[..., :, 0] * p[..., 0:1]  # Σ_k R[:, k] p_k by fused multiply-adds (see se3.act)
    return out.addcmul_(R[..., :, 1], p[..., 1:2]).addcmul_(R[..., :, 2], p[..., 2:3])


def adjoint(R: torch.Tensor) -> torch.Tensor:
    """Ad_R = R: ``R exp(ω) Rᵀ = exp(R ω)``."""
    check_tensor(R, (3, 3), "R", "so3.adjoint")
    return R


# --------------------------------------------------------------------------------------------------
# Jacobians
# --------------------------------------------------------------------------------------------------

def _jac(w: torch.Tensor, sign: float) -> torch.Tensor:
    # J_l(ω) = I + b ω̂ + c ω̂²,  J_r(ω) = J_l(-ω)  (Solà Eq. 145-146), with ω̂² = ωωᵀ - θ² I
    wx, wy, wz = _soa(w, 3)
    theta2 = wx * wx + wy * wy + wz * wz
    k = _coeffs(theta2, "b c")
    e = _sym_skew_entries(wx, wy, wz, 1 - k["c"] * theta2, sign * k["b"], k["c"])
    return torch.stack(e, -1).reshape(*w.shape[:-1], 3, 3)


def _jac_inv(w: torch.Tensor, sign: float) -> torch.Tensor:
    # J_l⁻¹(ω) = I - ½ ω̂ + d ω̂²  (Solà Eq. 146), d = 1/θ² - (1 + cos θ)/(2 θ sin θ)
    wx, wy, wz = _soa(w, 3)
    theta2 = wx * wx + wy * wy + wz * wz
    d = _coeffs(theta2, "d")["d"]
    e = _sym_skew_entries(wx, wy, wz, 1 - d * theta2, -0.5 * sign, d)
    return torch.stack(e, -1).reshape(*w.shape[:-1], 3, 3)


def left_jacobian(omega: torch.Tensor) -> torch.Tensor:
    """J_l(ω) ``(*, 3, 3)``: ``exp(ω + δ) ≈ exp(J_l δ) exp(ω)``."""
    check_tensor(omega, (3,), "omega", "so3.left_jacobian")
    return _jac(omega, 1.0)


def right_jacobian(omega: torch.Tensor) -> torch.Tensor:
    """J_r(ω) = J_l(-ω) ``(*, 3, 3)``: ``exp(ω + δ) ≈ exp(ω) exp(J_r δ)``."""
    check_tensor(omega, (3,), "omega", "so3.right_jacobian")
    return _jac(omega, -1.0)


def left_jacobian_inv(omega: torch.Tensor) -> torch.Tensor:
    """J_l(ω)⁻¹ in closed form (singular at |ω| = 2π; finite for principal ω, |ω| ≤ π)."""
    check_tensor(omega, (3,), "omega", "so3.left_jacobian_inv")
    return _jac_inv(omega, 1.0)


def right_jacobian_inv(omega: torch.Tensor) -> torch.Tensor:
    """J_r(ω)⁻¹ = J_l(-ω)⁻¹ in closed form."""
    check_tensor(omega, (3,), "omega", "so3.right_jacobian_inv")
    return _jac_inv(omega, -1.0)


# --------------------------------------------------------------------------------------------------
# constructors
# --------------------------------------------------------------------------------------------------

def identity(*batch, dtype: torch.dtype | None = None, device=None) -> torch.Tensor:
    """Identity rotations of shape ``(*batch, 3, 3)``."""
    shape = batch_shape(batch, "so3.identity")
    return torch.eye(3, dtype=float_dtype(dtype, "so3.identity"), device=device).expand(*shape, 3, 3).clone()


def random(*batch, generator: torch.Generator | None = None, dtype: torch.dtype | None = None,
           device=None) -> torch.Tensor:
    """Uniform (Haar) random rotations ``(*batch, 3, 3)``: normalized Gaussian quaternions."""
    shape = batch_shape(batch, "so3.random")
    dtype = float_dtype(dtype, "so3.random")
    device = rng_device(generator, device)
    q = torch.randn(*shape, 4, generator=generator, dtype=dtype, device=device)
    # a Gaussian 4-vector of norm 0 has probability 0; guard anyway so no NaN can appear
    q = torch.where(torch.linalg.vector_norm(q, dim=-1, keepdim=True) > 0, q, torch.ones_like(q))
    return from_quaternion(q)


def interpolate(R0: torch.Tensor, R1: torch.Tensor, t) -> torch.Tensor:
    """Geodesic ``R0 exp(t log(R0ᵀ R1))``; ``t`` a float or a tensor broadcasting with the batch."""
    check_tensor(R0, (3, 3), "R0", "so3.interpolate")
    check_tensor(R1, (3, 3), "R1", "so3.interpolate")
    check_same_device("so3.interpolate", R0=R0, R1=R1)
    R0, R1 = broadcast_leading(R0, 2, R1, 2, "so3.interpolate", ("R0", "R1"))
    w = _log(R0.transpose(-1, -2) @ R1)
    t = scalar_param(t, w, "so3.interpolate", "t", "R0")
    return R0 @ _exp(w * t.unsqueeze(-1))


def project(M: torch.Tensor) -> torch.Tensor:
    """Nearest rotation (Frobenius) to ``M`` ``(*, 3, 3)``, with a first derivative that is exact.

    The value is the SVD solution ``U diag(1, 1, det(UVᵀ)) Vᵀ``.  The
    derivative of that SVD through autograd is undefined at the points that matter most here —
    rotations themselves, where all singular values coincide — so it is attached analytically:
    with signed singular values σ = D S, ``dR = U_D Ω Vᵀ``, ``Ω_ij = (A − Aᵀ)_ij / (σ_i + σ_j)``,
    ``A = U_Dᵀ dM V`` (from ``M = R H``, ``Rᵀ dM − dMᵀ R = ΩH + HΩ`` in the V basis).  It is
    finite whenever the nearest rotation is unique (σ_i + σ_j ≠ 0).  Higher derivatives are not
    provided (U, S, V enter as constants).
    """
    check_tensor(M, (3, 3), "M", "so3.project")
    Md = M.detach()
    U, S, Vh = torch.linalg.svd(Md)
    det = torch.linalg.det(U @ Vh)
    sign = torch.where(det < 0, -1.0, 1.0).to(S.dtype).unsqueeze(-1)
    d = torch.cat((torch.ones_like(S[..., :2]), sign), -1)
    Ud = U * d.unsqueeze(-2)
    R = Ud @ Vh
    sig = S * d
    den = sig.unsqueeze(-1) + sig.unsqueeze(-2)
    ok = den.abs() > torch.finfo(S.dtype).eps * S[..., :1, None].clamp(min=1.0)
    Fm = torch.where(ok, 1 / torch.where(ok, den, torch.ones_like(den)), torch.zeros_like(den))
    A = Ud.transpose(-1, -2) @ (M - Md) @ Vh.transpose(-1, -2)
    return R + Ud @ (Fm * (A - A.transpose(-1, -2))) @ Vh
