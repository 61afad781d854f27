"""torchlie.quaternion ((w, x, y, z) order) against scipy's Rotation ((x, y, z, w) order), the
eigenvector method, torchlie.so3 and finite differences."""

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation, Slerp
from torch.autograd import gradcheck

from torchlie import quaternion as Q
from torchlie.testing import check_batching, rotation_vectors

F64 = torch.float64
SETTINGS = settings(max_examples=25, deadline=None)
quat_st = st.tuples(*[st.floats(-1, 1, allow_nan=False)] * 4).filter(lambda q: sum(c * c for c in q) > 0.1)


def _rot(q):
    """scipy Rotation of (w, x, y, z) quaternions."""
    return Rotation.from_quat(Q.to_xyzw(q.double()).numpy())


def _same_up_to_sign(a, b, atol):
    s = torch.where((a * b).sum(-1, keepdim=True) < 0, -1.0, 1.0).to(a.dtype)
    torch.testing.assert_close(a, s * b, atol=atol, rtol=0)


def _unit(seed, n=40):
    g = torch.Generator().manual_seed(seed)
    return Q.random(n, generator=g, dtype=F64)


# ---------------------------------------------------------------------------------------------- vs scipy
def test_conversions_match_scipy():
    w = rotation_vectors(200, torch.Generator().manual_seed(0))  # edge angles 0 … π and random, incl. π
    q = Q.exp(w)
    r = Rotation.from_rotvec(w.numpy())
    _same_up_to_sign(q, Q.from_xyzw(torch.from_numpy(r.as_quat())), 1e-15)
    torch.testing.assert_close(Q.to_matrix(q), torch.from_numpy(r.as_matrix()), atol=1e-15, rtol=0)
    R = torch.from_numpy(r.as_matrix())
    _same_up_to_sign(Q.from_matrix(R), Q.from_xyzw(torch.from_numpy(r.as_quat())), 1e-15)
    # log: the rotation vector (at angle exactly π, ω and −ω are both principal)
    lw = Q.log(q)
    ref = torch.from_numpy(r.as_rotvec())
    flip = torch.where(((lw + ref).norm(dim=-1) < 1e-12) & (ref.norm(dim=-1) > math.pi - 1e-6), -1.0, 1.0)
    torch.testing.assert_close(lw, flip.unsqueeze(-1) * ref, atol=1e-14, rtol=0)
    g = torch.Generator().manual_seed(1)
    p = torch.randn(q.shape[0], 3, generator=g, dtype=F64)
    torch.testing.assert_close(Q.act(q, p), torch.from_numpy(r.apply(p.numpy())), atol=1e-14, rtol=0)
    axis, angle = Q.to_axis_angle(q)
    torch.testing.assert_close(angle, torch.from_numpy(r.magnitude()), atol=1e-15, rtol=0)
    torch.testing.assert_close(Q.exp(axis * angle.unsqueeze(-1)), Q.canonicalize(q), atol=1e-15, rtol=0)
    ax = torch.randn(q.shape[0], 3, generator=g, dtype=F64)
    ang = 4 * torch.randn(q.shape[0], generator=g, dtype=F64)
    ref = Rotation.from_rotvec((ax / ax.norm(dim=-1, keepdim=True) * ang.unsqueeze(-1)).numpy())
    _same_up_to_sign(Q.from_axis_angle(ax, ang), Q.from_xyzw(torch.from_numpy(ref.as_quat())), 1e-14)


def test_multiply_and_slerp_match_scipy():
    p, q = _unit(2), _unit(3)
    pq = Q.multiply(p, q)
    _same_up_to_sign(pq, Q.from_xyzw(torch.from_numpy((_rot(p) * _rot(q)).as_quat())), 1e-15)
    torch.testing.assert_close(Q.to_matrix(pq), Q.to_matrix(p) @ Q.to_matrix(q), atol=1e-14, rtol=0)
    t = np.array([0.0, 0.25, 0.6, 1.0])
    for i in range(5):
        pair = Rotation.from_quat(np.stack((Q.to_xyzw(p[i]).numpy(), Q.to_xyzw(q[i]).numpy())))
        ref = Q.from_xyzw(torch.from_numpy(Slerp([0.0, 1.0], pair)(t).as_quat()))
        out = Q.slerp(p[i], q[i], torch.from_numpy(t))
        _same_up_to_sign(out, ref, 1e-14)
        # shortest path: the angle to p grows linearly to at most π/2 in quaternion space
        c = (out * p[i]).sum(-1).abs().clamp(max=1)
        half = torch.acos((p[i] * q[i]).sum().abs().clamp(max=1))
        torch.testing.assert_close(torch.acos(c), torch.from_numpy(t) * half, atol=1e-7, rtol=0)


def test_from_matrix_every_branch_and_against_eigenvector_method():
    pi = math.pi
    ws = torch.tensor([[0, 0, 0], [pi, 0, 0], [0, pi, 0], [0, 0, pi], [pi - 1e-9, 0, 0], [0, 1e-9, pi - 1e-9],
                       [1.0, -2.0, 0.5], [2.0, 2.0, 2.0], [-2.2, 1.0, 1.8]], dtype=F64)
    R = torch.from_numpy(Rotation.from_rotvec(ws.numpy()).as_matrix())
    q = Q.from_matrix(R)
    # largest-diagonal branch used: w, x, y, z for the first four
    assert q.abs().argmax(-1)[:4].tolist() == [0, 1, 2, 3]
    assert (q[:, 0] >= 0).all()
    torch.testing.assert_close(Q.to_matrix(q), R, atol=1e-15, rtol=0)
    # Bar-Itzhack: q is the top eigenvector of a symmetric 4x4 matrix built from R
    r = R
    K = torch.stack((
        torch.stack((r[:, 0, 0] - r[:, 1, 1] - r[:, 2, 2], r[:, 1, 0] + r[:, 0, 1], r[:, 2, 0] + r[:, 0, 2],
                     r[:, 2, 1] - r[:, 1, 2]), -1),
        torch.stack((r[:, 1, 0] + r[:, 0, 1], r[:, 1, 1] - r[:, 0, 0] - r[:, 2, 2], r[:, 2, 1] + r[:, 1, 2],
                     r[:, 0, 2] - r[:, 2, 0]), -1),
        torch.stack((r[:, 2, 0] + r[:, 0, 2], r[:, 2, 1] + r[:, 1, 2], r[:, 2, 2] - r[:, 0, 0] - r[:, 1, 1],
                     r[:, 1, 0] - r[:, 0, 1]), -1),
        torch.stack((r[:, 2, 1] - r[:, 1, 2], r[:, 0, 2] - r[:, 2, 0], r[:, 1, 0] - r[:, 0, 1],
                     r[:, 0, 0] + r[:, 1, 1] + r[:, 2, 2]), -1),
    ), -2) / 3
    vec = torch.linalg.eigh(K).eigenvectors[..., -1]  # (x, y, z, w)
    _same_up_to_sign(q, Q.from_xyzw(vec), 1e-14)


def test_matrix_conversions_agree_with_so3():
    from torchlie import so3

    w = rotation_vectors(60, torch.Generator().manual_seed(4))
    q = Q.exp(w)
    torch.testing.assert_close(Q.to_matrix(q), so3.exp(w), atol=1e-14, rtol=0)
    R = so3.exp(w)
    _same_up_to_sign(Q.from_matrix(R), so3.to_quaternion(R), 1e-14)


# ---------------------------------------------------------------------------------------------- round trips
@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 2e-5)])
def test_exp_log_round_trips(dtype, tol):
    w = rotation_vectors(300, torch.Generator().manual_seed(5), dtype)
    q = Q.exp(w)
    assert q.dtype == dtype and q.shape == (w.shape[0], 4)
    assert ((q * q).sum(-1) - 1).abs().max() <= tol
    # exp(log(q)) = q up to sign, for q and −q and for w < 0
    for qq in (q, -q):
        assert (Q.exp(Q.log(qq)) - Q.canonicalize(qq)).abs().max() <= tol
    # log(exp(ω)) = ω where ω is principal (|ω| < π; at π the sign is a convention)
    lw = Q.log(q)
    inside = w.norm(dim=-1) < math.pi - 1e-5
    assert (lw - w)[inside].abs().max() <= tol * math.pi
    assert (lw.norm(dim=-1) <= math.pi + tol).all()
    # matrix round trip
    R = Q.to_matrix(q)
    assert (Q.to_matrix(Q.from_matrix(R)) - R).abs().max() <= tol
    _same_up_to_sign(Q.from_matrix(R), q, 2 * tol)


def test_log_ignores_sign_and_scale():
    q = _unit(6)
    q = torch.cat((q, Q.identity(1, dtype=F64)))
    for qq in (-q, 2.5 * q, -0.1 * q):
        torch.testing.assert_close(Q.log(qq), Q.log(q), atol=1e-14, rtol=0)
        torch.testing.assert_close(Q.to_matrix(qq), Q.to_matrix(q), atol=1e-14, rtol=0)
        torch.testing.assert_close(Q.act(qq, q[:, 1:]), Q.act(q, q[:, 1:]), atol=1e-14, rtol=0)


@SETTINGS
@given(a=quat_st, b=quat_st, c=quat_st)
def test_algebra_axioms(a, b, c):
    p, q, r = (torch.tensor(v, dtype=F64) for v in (a, b, c))
    torch.testing.assert_close(Q.multiply(Q.multiply(p, q), r), Q.multiply(p, Q.multiply(q, r)),
                               atol=1e-14, rtol=0)
    e = Q.identity(dtype=F64)
    torch.testing.assert_close(Q.multiply(p, e), p, atol=0, rtol=0)
    torch.testing.assert_close(Q.multiply(p, Q.inverse(p)), e, atol=1e-14, rtol=0)
    torch.testing.assert_close(Q.conjugate(Q.multiply(p, q)), Q.multiply(Q.conjugate(q), Q.conjugate(p)),
                               atol=1e-15, rtol=0)
    torch.testing.assert_close(Q.normalize(p).norm(), torch.tensor(1.0, dtype=F64), atol=1e-15, rtol=0)
    # rotation action is q p q⁻¹ in quaternion algebra
    pure = torch.cat((torch.zeros(1, dtype=F64), r[1:]))
    ref = Q.multiply(Q.multiply(q, pure), Q.inverse(q))
    torch.testing.assert_close(Q.act(q, r[1:]), ref[1:], atol=1e-14, rtol=0)
    torch.testing.assert_close(Q.to_xyzw(p)[[3, 0, 1, 2]], p)
    torch.testing.assert_close(Q.from_xyzw(Q.to_xyzw(p)), p)


@SETTINGS
@given(a=quat_st, t=st.floats(0, 1))
def test_slerp_properties(a, t):
    p = Q.normalize(torch.tensor(a, dtype=F64))
    q = Q.multiply(p, Q.exp(torch.tensor([0.3, -1.0, 2.0], dtype=F64)))
    torch.testing.assert_close(Q.slerp(p, q, 0.0), p, atol=1e-15, rtol=0)
    torch.testing.assert_close(Q.slerp(p, q, 1.0), q, atol=1e-14, rtol=0)
    torch.testing.assert_close(Q.slerp(p, -q, t), Q.slerp(p, q, t), atol=1e-14, rtol=0)  # shortest path
    torch.testing.assert_close(Q.slerp(p, p, t), p, atol=1e-15, rtol=0)


# ---------------------------------------------------------------------------------------------- gradients
def test_gradcheck_every_function_including_identity():
    g = torch.Generator().manual_seed(7)
    q = torch.cat((Q.identity(1, dtype=F64), Q.exp(torch.tensor([[1e-9, 0, 0], [0, 0.04, 0.0]], dtype=F64)),
                   Q.exp(torch.tensor([[math.pi - 1e-3, 0, 0]], dtype=F64)), _unit(8, 4)))
    q[-1] = -q[-1]  # a w < 0 element
    w = torch.cat((torch.zeros(1, 3, dtype=F64), torch.tensor([[1e-9, 0, 0], [0.02, -0.1, 0.1]], dtype=F64),
                   2 * torch.randn(5, 3, generator=g, dtype=F64)))
    q = q.requires_grad_(True)
    w = w.requires_grad_(True)
    R = Q.to_matrix(q.detach()).requires_grad_(True)
    p = torch.randn(8, 3, generator=g, dtype=F64).requires_grad_(True)
    qb = _unit(9, 8).requires_grad_(True)
    t = torch.rand(8, generator=g, dtype=F64).requires_grad_(True)
    angle = torch.randn(8, generator=g, dtype=F64).requires_grad_(True)
    assert gradcheck(Q.exp, (w,))
    assert gradcheck(Q.log, (q,))
    assert gradcheck(Q.from_matrix, (R,))
    for f in (Q.to_matrix, Q.conjugate, Q.inverse, Q.normalize, Q.to_xyzw, Q.from_xyzw, Q.canonicalize):
        assert gradcheck(f, (q,)), f.__name__
    assert gradcheck(Q.multiply, (q, qb))
    assert gradcheck(Q.act, (q, p))
    assert gradcheck(Q.slerp, (q, qb, t))
    assert gradcheck(Q.slerp, (q, q.detach().clone(), t))  # identical end points (a copy: q gets perturbed)
    assert gradcheck(Q.from_axis_angle, (p, angle))
    assert gradcheck(lambda x: Q.to_axis_angle(x)[0], (q[3:],))
    assert gradcheck(lambda x: Q.to_axis_angle(x)[1], (q[3:],))


def test_gradients_exact_and_finite_at_zero_and_pi():
    # d log(exp(ω))/dω = I at 0, 1e-9 and up to π
    w = torch.tensor([[0.0, 0, 0], [1e-9, 0, 0], [0, math.pi - 1e-9, 0], [0, 0, math.pi]], dtype=F64)
    J = torch.func.vmap(torch.func.jacrev(lambda v: Q.log(Q.exp(v))))(w)
    torch.testing.assert_close(J, torch.eye(3, dtype=F64).expand_as(J), atol=1e-8, rtol=0)
    torch.testing.assert_close(J[:2], torch.eye(3, dtype=F64).expand(2, 3, 3), atol=1e-15, rtol=0)
    # ∂ to_matrix(exp(ω))/∂ω at 0 = the so(3) generators
    G = torch.func.jacrev(lambda v: Q.to_matrix(Q.exp(v)))(torch.zeros(3, dtype=F64)).permute(2, 0, 1)
    gens = torch.tensor([[[0, 0, 0], [0, 0, -1], [0, 1, 0]], [[0, 0, 1], [0, 0, 0], [-1, 0, 0]],
                         [[0, -1, 0], [1, 0, 0], [0, 0, 0]]], dtype=F64)
    torch.testing.assert_close(G, gens, atol=1e-15, rtol=0)
    # finite gradients at exactly π (w = 0) and at the identity for every non-smooth-looking map
    Rpi = torch.from_numpy(Rotation.from_rotvec([[math.pi, 0, 0], [0, 0, 0], [1.0, 2.0, 2.0]]).as_matrix())
    cases = ((Q.from_matrix, Rpi), (Q.log, Q.from_matrix(Rpi)),
             (lambda v: Q.to_axis_angle(v)[1], Q.identity(3)),
             (lambda v: Q.slerp(v, v, 0.5), Q.from_matrix(Rpi)))
    for f, x in cases:
        x = x.clone().double().requires_grad_(True)
        f(x).sum().backward()
        assert torch.isfinite(x.grad).all()


# ---------------------------------------------------------------------------------------------- batching
def test_batched_flattened_loop_broadcasting_vmap_compile():
    q, r = _unit(10, 12).reshape(3, 4, 4), _unit(11, 12).reshape(3, 4, 4)
    p = torch.randn(3, 4, 3, generator=torch.Generator().manual_seed(0), dtype=F64)
    R = Q.to_matrix(q)
    check_batching(Q.from_matrix, (R,), (2,), atol=1e-15)
    check_batching(Q.log, (q,), (1,), atol=1e-15)
    check_batching(Q.exp, (p,), (1,), atol=1e-15)
    check_batching(Q.multiply, (q, r), (1, 1), atol=1e-15)
    check_batching(Q.act, (q, p), (1, 1), atol=1e-15)
    check_batching(lambda a, b: Q.slerp(a, b, 0.3), (q, r), (1, 1), atol=1e-15)
    torch.testing.assert_close(Q.multiply(q[:1], r), Q.multiply(q[:1].expand(3, 4, 4), r))
    torch.testing.assert_close(Q.act(q[0, 0], p), Q.act(q[0, 0].expand(3, 4, 4), p))
    ts = torch.linspace(0, 1, 6, dtype=F64).unsqueeze(-1)  # (T, 1) with batch (4,) -> (T, 4, 4)
    assert Q.slerp(q[0], r[0], ts).shape == (6, 4, 4)
    torch.testing.assert_close(torch.func.vmap(Q.from_matrix)(R[0]), Q.from_matrix(R[0]), atol=0, rtol=0)
    J = torch.func.vmap(torch.func.jacrev(Q.log))(q[0])
    assert J.shape == (4, 3, 4) and torch.isfinite(J).all()
    f = torch.compile(Q.from_matrix, fullgraph=True, dynamic=False)
    torch.testing.assert_close(f(R[0]), Q.from_matrix(R[0]), atol=1e-15, rtol=0)


# ---------------------------------------------------------------------------------------------- constructors
def test_identity_and_random_uniform_on_s3():
    from scipy.stats import kstest

    assert Q.identity(2, 3).shape == (2, 3, 4) and Q.identity((2,), dtype=F64).dtype == F64
    torch.testing.assert_close(Q.identity(dtype=F64), torch.tensor([1.0, 0, 0, 0], dtype=F64))
    q = Q.random(4000, generator=torch.Generator().manual_seed(0), dtype=F64)
    assert torch.equal(q, Q.random(4000, generator=torch.Generator().manual_seed(0), dtype=F64))
    torch.testing.assert_close(q.norm(dim=-1), torch.ones(4000, dtype=F64), atol=1e-15, rtol=0)
    # uniform on S³: E[q qᵀ] = I/4, and the rotation angle has the Haar CDF (θ − sin θ)/π
    torch.testing.assert_close(q.T @ q / 4000, torch.eye(4, dtype=F64) / 4, atol=0.02, rtol=0)
    _, angle = Q.to_axis_angle(q)
    assert kstest(angle.numpy(), lambda th: (th - np.sin(th)) / np.pi).pvalue > 1e-3
    assert (q[:, 0] < 0).any()  # not canonicalised


# ---------------------------------------------------------------------------------------------- bad input
def test_bad_input_names_argument_and_shape():
    with pytest.raises(ValueError, match=r"quaternion.log.*'q'.*\(\*, 4\)"):
        Q.log(torch.zeros(2, 3))
    with pytest.raises(ValueError, match=r"'R'.*\(\*, 3, 3\)"):
        Q.from_matrix(torch.zeros(4, 4))
    with pytest.raises(ValueError, match=r"'omega'.*\(\*, 3\)"):
        Q.exp(torch.zeros(4))
    with pytest.raises(TypeError, match="'q'.*floating"):
        Q.to_matrix(torch.zeros(4, dtype=torch.int64))
    with pytest.raises(TypeError, match="'p'.*'q'.*dtype"):
        Q.multiply(Q.identity(dtype=F64), Q.identity(dtype=torch.float32))
    with pytest.raises(ValueError, match="do not broadcast"):
        Q.multiply(Q.identity(2), Q.identity(3))
    with pytest.raises(TypeError, match="'angle'"):
        Q.from_axis_angle(torch.ones(3), "1.0")


def test_nan_stays_in_its_element():
    R = Q.to_matrix(_unit(12, 5))
    R[1, 0, 0] = float("nan")
    q = Q.from_matrix(R)
    bad = torch.tensor([False, True, False, False, False])
    assert torch.isfinite(q[~bad]).all() and torch.isnan(q[bad]).any()
    for out in (Q.log(q), Q.multiply(q, q), Q.slerp(q, q.flip(0)[[4, 3, 2, 1, 0]], 0.5), Q.to_matrix(q)):
        assert torch.isfinite(out[~bad]).all() and torch.isnan(out[bad]).any()


def test_device_follows_input_and_mismatch_is_rejected():
    m = torch.device("meta")
    for f, shape in ((Q.from_matrix, (4, 3, 3)), (Q.log, (4, 4)), (Q.exp, (4, 3)), (Q.to_matrix, (4, 4))):
        assert f(torch.zeros(*shape, device=m)).device == m, f.__name__
    assert Q.slerp(torch.zeros(2, 4, device=m), torch.zeros(2, 4, device=m), 0.5).device == m
    assert Q.random(2, device=m).device == m and Q.identity(2, device=m).device == m
    with pytest.raises(ValueError, match="'q' and 'p' are on different devices"):
        Q.act(torch.zeros(4), torch.zeros(3, device=m))
    with pytest.raises(ValueError, match="'p' and 't' are on different devices"):
        Q.slerp(torch.zeros(4), torch.zeros(4), torch.tensor(0.5, device=m))


# ---------------------------------------------------------------------------------------------- log vs mpmath
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_log_and_its_derivative_against_mpmath_at_every_angle(dtype):
    """log(±c q) = θ u for q = (cos θ/2, sin θ/2 u) (60-digit reference), and its derivative along the
    group — d/dε log(q ⊗ exp(ε δ)) = J_r(ω)⁻¹ δ, the closed form in mpmath — at angles 0 … π, without
    the small-angle series it used to have; finite and one-sided (the branch returned) at exactly π."""
    mp = pytest.importorskip("mpmath")
    mp.mp.dps = 60
    eps = torch.finfo(dtype).eps

    def hat(w):
        return mp.matrix([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])

    def jr_inv(w):
        w = [mp.mpf(float(c)) for c in w]
        th = mp.sqrt(sum(c * c for c in w))
        d = mp.mpf(1) / 12 if th == 0 else 1 / th**2 - (1 + mp.cos(th)) / (2 * th * mp.sin(th))
        W = hat(w)
        J = mp.eye(3) + W / 2 + d * W * W
        return torch.tensor([[float(J[i, j]) for j in range(3)] for i in range(3)], dtype=F64)

    half = torch.cat((torch.zeros(3, 1, dtype=F64), 0.5 * torch.eye(3, dtype=F64)), -1)  # (0, δ/2)
    angles = [0.0, 1e-12, 1e-9, 1e-6, 1e-3, 0.05, 0.3, 1.0, 2.0, 3.0, math.pi - 1e-6, math.pi - 1e-9]
    for axis in ((0.6, -0.48, 0.64), (0.0, 0.0, 1.0), (-2.0, 1.0, 2.0)):
        u = [mp.mpf(c) for c in axis]
        nu = mp.sqrt(sum(c * c for c in u))
        u = [c / nu for c in u]
        for theta in angles:
            th = mp.mpf(theta)
            qm = [mp.cos(th / 2)] + [mp.sin(th / 2) * c for c in u]
            ref = torch.tensor([float(th * c) for c in u], dtype=F64)
            for scale in (1.0, -1.0, 2.5, -0.1):
                q = torch.tensor([float(scale * c) for c in qm], dtype=dtype)
                w = Q.log(q)
                assert w.dtype == dtype
                assert (w.double() - ref).abs().max() <= 4 * eps * math.pi, (theta, scale)
                J = torch.autograd.functional.jacobian(Q.log, q).double()  # (3, 4)
                G = torch.stack([J @ Q.multiply(q.double(), half[k]) for k in range(3)], -1)
                tol = 2e-6 if dtype == torch.float32 else 4e-15
                assert (G - jr_inv(w)).abs().max() <= tol, (theta, scale)
    # exactly π: w = ±0 picks the branch (both are logarithms), the derivative is that branch's
    for w0 in (0.0, -0.0):
        q = torch.tensor([w0, 0.6, -0.48, 0.64], dtype=dtype)
        w = Q.log(q)
        sign = math.copysign(1.0, w0)
        assert (w.double() - sign * math.pi * torch.tensor([0.6, -0.48, 0.64], dtype=F64)).abs().max() < 4e-7
        J = torch.autograd.functional.jacobian(Q.log, q).double()
        assert torch.isfinite(J).all()
        G = torch.stack([J @ Q.multiply(q.double(), half[k]) for k in range(3)], -1)
        assert (G - jr_inv(w)).abs().max() < 1e-6
