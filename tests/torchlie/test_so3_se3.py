"""SO(3) and SE(3): values against independent references (scipy, torch.linalg.matrix_exp), group
axioms, Jacobian definitions by finite differences, gradients by gradcheck, batching, transforms
(vmap, jacrev, compile) and bad input."""

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from torchlie import se3, so3
from torchlie.testing import angles_near_edges, check_batching, fd_jacobian, rotation_vectors

F64, F32 = torch.float64, torch.float32
GROUPS = {"so3": (so3, 3, 3), "se3": (se3, 6, 4)}


def tangents(mod, n, gen, dtype=F64):
    w = rotation_vectors(n, gen, dtype)
    if mod is so3:
        return w
    return torch.cat((torch.randn(w.shape[0], 3, generator=gen, dtype=F64).to(dtype), w), -1)


@pytest.fixture
def gen():
    return torch.Generator().manual_seed(1234)


# ---------------------------------------------------------------------------------------------- values

def test_so3_exp_log_against_scipy(gen):
    w = rotation_vectors(300, gen)
    R = so3.exp(w)
    Rs = torch.from_numpy(Rotation.from_rotvec(w.numpy()).as_matrix())
    assert (R - Rs).abs().max() < 1e-14
    # principal log: same rotation vector as scipy away from the π ambiguity
    ws = torch.from_numpy(Rotation.from_matrix(R.numpy()).as_rotvec())
    keep = w.norm(dim=-1) < math.pi - 1e-6
    assert (so3.log(R)[keep] - ws[keep]).abs().max() < 1e-12
    q = so3.to_quaternion(R)
    qs = torch.from_numpy(Rotation.from_matrix(R.numpy()).as_quat(scalar_first=True))
    qs = torch.where(qs[:, :1] < 0, -qs, qs)
    assert (q[keep] - qs[keep]).abs().max() < 1e-12
    assert (so3.from_quaternion(q) - R).abs().max() < 1e-14


def test_se3_exp_against_matrix_exp(gen):
    xi = tangents(se3, 300, gen)
    assert (se3.exp(xi) - torch.linalg.matrix_exp(se3.hat(xi))).abs().max() < 1e-13


@pytest.mark.parametrize("name", ["so3", "se3"])
def test_roundtrip_accuracy_everywhere(name, gen):
    """exp(log(X)) == X to 1e-12 (float64) / 2e-5 (float32), incl. angles within 1e-9 of 0 and π."""
    mod, _, _ = GROUPS[name]
    xi = tangents(mod, 3000, gen)
    for dtype, tol in ((F64, 1e-12), (F32, 2e-5)):
        X = mod.exp(xi).to(dtype)
        err = (mod.exp(mod.log(X)) - X).abs().max().item()
        assert err <= tol, (dtype, err)


@pytest.mark.parametrize("name", ["so3", "se3"])
def test_log_is_principal_and_inverts_exp(name, gen):
    mod, _, _ = GROUPS[name]
    xi = tangents(mod, 500, gen)
    back = mod.log(mod.exp(xi))
    assert (back[..., -3:].norm(dim=-1) <= math.pi + 1e-12).all()
    keep = xi[..., -3:].norm(dim=-1) < math.pi - 1e-7
    assert (back[keep] - xi[keep]).abs().max() < 1e-9


def test_log_at_exactly_pi_and_zero():
    for axis in torch.eye(3, dtype=F64):
        R = so3.exp(math.pi * axis)
        w = so3.log(R)
        assert abs(w.norm().item() - math.pi) < 1e-14
        assert (so3.exp(w) - R).abs().max() < 1e-14
    R = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=F64))  # Panda tool-down orientation
    assert torch.allclose(so3.log(R).abs(), torch.tensor([math.pi, 0, 0], dtype=F64), atol=1e-15)
    assert (so3.log(so3.identity(dtype=F64)) == 0).all()
    assert (se3.log(se3.identity(dtype=F64)) == 0).all()
    assert so3.angle(R).item() == pytest.approx(math.pi, abs=1e-15)


@pytest.mark.parametrize("theta", [0.0, 1e-9, 1e-5, 1e-3, 0.3, math.pi - 1e-9])
def test_float32_small_angles_are_exact(theta):
    """No accuracy loss in float32 at small angles (pypose's float32 Jr is 5 % off at θ = 1e-3)."""
    w64 = theta * torch.tensor([0.6, -0.48, 0.64], dtype=F64)
    for f in (so3.exp, so3.right_jacobian, so3.left_jacobian_inv):
        ref = f(w64)
        assert (f(w64.float()).double() - ref).abs().max() < 5e-7
    xi = torch.cat((torch.tensor([0.3, -1.0, 2.0], dtype=F64), w64))
    for f in (se3.exp, se3.right_jacobian, se3.left_jacobian_inv):
        assert (f(xi.float()).double() - f(xi)).abs().max() < 2e-6


# ---------------------------------------------------------------------------------------------- Jacobians

@pytest.mark.parametrize("name", ["so3", "se3"])
def test_jacobians_match_their_definition(name, gen):
    mod, d, _ = GROUPS[name]
    xs = tangents(mod, 6, gen)
    xs = xs[xs[..., -3:].norm(dim=-1) < math.pi - 1e-3]  # FD steps must not cross the cut locus
    for x in xs:
        X = mod.exp(x)
        Jr = fd_jacobian(lambda y, X=X: mod.log(mod.compose(mod.inverse(X), mod.exp(y))), x)
        Jl = fd_jacobian(lambda y, X=X: mod.log(mod.compose(mod.exp(y), mod.inverse(X))), x)
        assert (Jr - mod.right_jacobian(x)).abs().max() < 1e-7
        assert (Jl - mod.left_jacobian(x)).abs().max() < 1e-7
        eye = torch.eye(d, dtype=F64)
        assert (mod.right_jacobian_inv(x) @ mod.right_jacobian(x) - eye).abs().max() < 1e-10
        assert (mod.left_jacobian_inv(x) @ mod.left_jacobian(x) - eye).abs().max() < 1e-10
        # J_l = Ad_exp(x) J_r
        assert (mod.left_jacobian(x) - mod.adjoint(X) @ mod.right_jacobian(x)).abs().max() < 1e-12


@pytest.mark.parametrize("name", ["so3", "se3"])
def test_jacobians_near_zero_use_exact_series(name):
    """Against an independent reference: J_l(x) = Σ_k ad_x^k/(k+1)!, J_r(x) = J_l(−x)."""
    mod, d, _ = GROUPS[name]
    for s in (0.0, 1e-12, 1e-6, 1e-3, 0.05, 0.3, 1.5):
        x = s * torch.linspace(0.3, 1.0, d, dtype=F64)
        A = mod.ad(x)
        Jl = sum(torch.linalg.matrix_power(A, k) / float(math.factorial(k + 1)) for k in range(30))
        Jr = sum(torch.linalg.matrix_power(-A, k) / float(math.factorial(k + 1)) for k in range(30))
        assert (mod.left_jacobian(x) - Jl).abs().max() < 1e-14
        assert (mod.right_jacobian(x) - Jr).abs().max() < 1e-14
        assert (mod.left_jacobian_inv(x) - torch.linalg.inv(Jl)).abs().max() < 1e-13


@pytest.mark.parametrize("name", ["so3", "se3"])
def test_jacobians_continuous_across_the_series_switch(name):
    """Both sides of every small-angle switch (θ² = 0.01, 0.05 in float64; 0.1, 0.5 in float32) agree
    with the series reference Σ_k ad_x^k/(k+1)! (closed forms lose ~eps/θ² just above a switch)."""
    mod, d, _ = GROUPS[name]
    axis = torch.nn.functional.normalize(torch.linspace(0.3, 1.0, 3, dtype=F64), dim=0)
    for dtype, switches, tol in ((F64, (1e-2, 5e-2), 5e-14), (F32, (1e-1, 5e-1), 1e-6)):
        for sw in switches:
            for th2 in (sw * (1 - 1e-6), sw, sw * (1 + 1e-6)):
                w = math.sqrt(th2) * axis
                x = w if d == 3 else torch.cat((torch.tensor([0.3, -0.7, 1.1], dtype=F64), w))
                A = mod.ad(x)
                Jl = sum(torch.linalg.matrix_power(A, k) / float(math.factorial(k + 1)) for k in range(30))
                Jr = sum(torch.linalg.matrix_power(-A, k) / float(math.factorial(k + 1)) for k in range(30))
                xd = x.to(dtype)
                for f, ref in ((mod.left_jacobian, Jl), (mod.right_jacobian, Jr),
                               (mod.left_jacobian_inv, torch.linalg.inv(Jl)),
                               (mod.right_jacobian_inv, torch.linalg.inv(Jr))):
                    assert (f(xd).double() - ref).abs().max() < tol, (dtype, th2, f.__name__)


# ---------------------------------------------------------------------------------------------- axioms

@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), name=st.sampled_from(["so3", "se3"]))
def test_group_axioms_and_adjoint_identities(seed, name):
    mod, d, n = GROUPS[name]
    g = torch.Generator().manual_seed(seed)
    X, Y, Z = (mod.random(4, generator=g, dtype=F64) for _ in range(3))
    eye = mod.identity(4, dtype=F64)
    assert (mod.compose(mod.compose(X, Y), Z) - mod.compose(X, mod.compose(Y, Z))).abs().max() < 1e-12
    assert (mod.compose(X, mod.inverse(X)) - eye).abs().max() < 1e-12
    assert (mod.compose(eye, X) - X).abs().max() == 0
    x, y = 0.5 * torch.randn(4, d, generator=g, dtype=F64), 0.5 * torch.randn(4, d, generator=g, dtype=F64)
    AdX = mod.adjoint(X)
    Adx = (AdX @ x.unsqueeze(-1)).squeeze(-1)
    # X exp(x) X⁻¹ = exp(Ad_X x);  Ad_X ad_x Ad_X⁻¹ = ad_{Ad_X x};  Ad_{XY} = Ad_X Ad_Y
    assert (mod.compose(mod.compose(X, mod.exp(x)), mod.inverse(X)) - mod.exp(Adx)).abs().max() < 1e-12
    assert (AdX @ mod.ad(x) @ torch.linalg.inv(AdX) - mod.ad(Adx)).abs().max() < 1e-11
    assert (mod.adjoint(mod.compose(X, Y)) - AdX @ mod.adjoint(Y)).abs().max() < 1e-12
    # ad_x y = vee([x^, y^]) and exp(x) = exp(ad_x) on the adjoint representation
    lie = mod.hat(x) @ mod.hat(y) - mod.hat(y) @ mod.hat(x)
    assert (mod.vee(lie) - (mod.ad(x) @ y.unsqueeze(-1)).squeeze(-1)).abs().max() < 1e-12
    assert (mod.adjoint(mod.exp(x)) - torch.linalg.matrix_exp(mod.ad(x))).abs().max() < 1e-12
    assert (mod.vee(mod.hat(x)) - x).abs().max() == 0


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), t=st.floats(0, 1))
def test_interpolate_is_geodesic(seed, t):
    g = torch.Generator().manual_seed(seed)
    for mod in (so3, se3):
        X, Y = mod.random(3, generator=g, dtype=F64), mod.random(3, generator=g, dtype=F64)
        assert (mod.interpolate(X, Y, 0.0) - X).abs().max() < 1e-12
        assert (mod.interpolate(X, Y, 1.0) - Y).abs().max() < 1e-10
        half = mod.interpolate(X, Y, 0.5)
        # the midpoint is equidistant from both ends
        d1 = mod.log(mod.compose(mod.inverse(X), half)).norm(dim=-1)
        d2 = mod.log(mod.compose(mod.inverse(half), Y)).norm(dim=-1)
        assert (d1 - d2).abs().max() < 1e-9
        Zt = mod.interpolate(X, Y, t)
        assert Zt.shape == X.shape


def test_act_and_inverse():
    g = torch.Generator().manual_seed(0)
    X = se3.random(5, generator=g, dtype=F64)
    p = torch.randn(5, 3, generator=g, dtype=F64)
    ph = torch.cat((p, torch.ones(5, 1, dtype=F64)), -1)
    assert (se3.act(X, p) - (X @ ph.unsqueeze(-1)).squeeze(-1)[:, :3]).abs().max() < 1e-14
    assert (se3.inverse(X) - torch.linalg.inv(X)).abs().max() < 1e-12
    R = so3.random(5, generator=g, dtype=F64)
    ref = torch.from_numpy(Rotation.from_matrix(R.numpy()).apply(p.numpy()))
    assert (so3.act(R, p) - ref).abs().max() < 1e-14
    # broadcasting: one transform applied to a cloud of points
    cloud = torch.randn(7, 5, 3, generator=g, dtype=F64)
    assert se3.act(X, cloud).shape == (7, 5, 3)
    assert (se3.act(X[0], cloud) - torch.stack([se3.act(X[0], c) for c in cloud])).abs().max() == 0


def test_se3_inverse_batches_strides_and_exact_bottom_row():
    g = torch.Generator().manual_seed(2)
    X = se3.random(2, 3, 5, generator=g, dtype=F64)
    Xi = se3.inverse(X)
    assert Xi.shape == X.shape and Xi.is_contiguous()
    assert (Xi - torch.linalg.inv(X)).abs().max() < 1e-12
    assert (se3.inverse(Xi) - X).abs().max() < 1e-12
    # non-contiguous input and a single matrix
    Xs = X.transpose(0, 2)
    assert (se3.inverse(Xs) - torch.linalg.inv(Xs)).abs().max() < 1e-12
    assert (se3.inverse(X[1, 2, 3]) - Xi[1, 2, 3]).abs().max() == 0
    # the bottom row is the constant [0, 0, 0, 1], whatever the input's bottom row holds
    Y = X.clone()
    Y[..., 3, :] = 7.0
    assert (se3.inverse(Y)[..., 3, :] == torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=F64)).all()
    assert (se3.inverse(Y)[..., :3, :] == Xi[..., :3, :]).all()
    for dtype in (F32, F64):
        assert se3.inverse(X.to(dtype)).dtype == dtype


def test_compose_same_function_in_every_dtype():
    """float32 (rows of multiply-adds) and float64 (matmul) give one function: the SE(3) product of the
    top 3×4 blocks with the bottom row exactly [0, 0, 0, 1]; the identity composes exactly."""
    g = torch.Generator().manual_seed(4)
    X, Y = se3.random(6, generator=g, dtype=F64), se3.random(6, generator=g, dtype=F64)
    X[..., 3, :], Y[..., 3, :] = 5.0, -3.0  # ignored
    ref = torch.cat((X[..., :3, :3] @ Y[..., :3, :] + torch.cat((torch.zeros(6, 3, 3, dtype=F64),
                                                                X[..., :3, 3:]), -1),
                     torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=F64).expand(6, 1, 4)), -2)
    for dtype, tol in ((F64, 1e-14), (F32, 1e-5)):
        Z = se3.compose(X.to(dtype), Y.to(dtype))
        assert (Z.double() - ref).abs().max() < tol
        assert (Z[..., 3, :] == torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=dtype)).all()
        eye = se3.identity(6, dtype=dtype)
        assert torch.equal(se3.compose(eye, Y.to(dtype))[..., :3, :], Y.to(dtype)[..., :3, :])
        R, S = so3.random(6, generator=g, dtype=dtype), so3.random(6, generator=g, dtype=dtype)
        assert (so3.compose(R, S).double() - R.double() @ S.double()).abs().max() < tol
        assert torch.equal(so3.compose(so3.identity(6, dtype=dtype), R), R)


def test_random_is_uniform_on_so3():
    """Haar measure: the angle density is (1 − cos θ)/π, so E[θ] = π/2 + 2/π and E[R] = 0."""
    R = so3.random(40000, generator=torch.Generator().manual_seed(7), dtype=F64)
    th = so3.angle(R)
    assert abs(th.mean().item() - (math.pi / 2 + 2 / math.pi)) < 0.02
    assert R.mean(0).abs().max() < 0.02
    assert (R.transpose(-1, -2) @ R - torch.eye(3, dtype=F64)).abs().max() < 1e-14
    assert torch.allclose(torch.linalg.det(R), torch.ones((), dtype=F64))


def test_random_generator_reproducible():
    a = se3.random(3, generator=torch.Generator().manual_seed(5))
    b = se3.random(3, generator=torch.Generator().manual_seed(5))
    assert torch.equal(a, b)
    assert a.dtype == torch.get_default_dtype()
    assert so3.identity(2, 3, dtype=F64).shape == (2, 3, 3, 3)


# ---------------------------------------------------------------------------------------------- gradients

EDGE = [0.0, 1e-9, 1e-4, 0.2, 1.0, math.pi - 1e-3]


@pytest.mark.parametrize("fn", ["exp", "left_jacobian", "right_jacobian", "left_jacobian_inv",
                                "right_jacobian_inv", "hat", "ad"])
@pytest.mark.parametrize("name", ["so3", "se3"])
def test_gradcheck_tangent_functions(fn, name):
    mod, d, _ = GROUPS[name]
    axis = torch.nn.functional.normalize(torch.linspace(0.4, 1.3, 3, dtype=F64), dim=0)
    x = torch.stack([th * axis for th in EDGE])
    if d == 6:
        x = torch.cat((torch.tensor([[0.3, -0.2, 1.0]], dtype=F64).expand(len(EDGE), 3), x), -1)
    assert torch.autograd.gradcheck(getattr(mod, fn), (x.clone().requires_grad_(),))


@pytest.mark.parametrize("name", ["so3", "se3"])
def test_gradcheck_group_functions(name):
    mod, d, _ = GROUPS[name]
    g = torch.Generator().manual_seed(3)
    axis = torch.nn.functional.normalize(torch.tensor([0.2, -0.5, 0.8], dtype=F64), dim=0)
    w = torch.stack([th * axis for th in EDGE[:-1] + [math.pi - 1e-2]])
    x = w if d == 3 else torch.cat((torch.randn(len(w), 3, generator=g, dtype=F64), w), -1)
    X = mod.exp(x).requires_grad_()
    Y = mod.random(len(w), generator=g, dtype=F64).requires_grad_()
    p = torch.randn(len(w), 3, generator=g, dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(mod.log, (X,))
    assert torch.autograd.gradcheck(mod.compose, (X, Y))
    assert torch.autograd.gradcheck(mod.inverse, (X,))
    assert torch.autograd.gradcheck(mod.act, (X, p))
    assert torch.autograd.gradcheck(mod.adjoint, (X,))
    assert torch.autograd.gradcheck(lambda a, b: mod.interpolate(a, b, 0.3), (X, Y))


@pytest.mark.parametrize("name", ["so3", "se3"])
def test_gradients_finite_at_identity_and_pi(name):
    mod, d, _ = GROUPS[name]
    Xs = [mod.identity(dtype=F64), mod.exp(torch.cat((torch.ones(d - 3, dtype=F64),
                                                       torch.tensor([0.0, 0.0, math.pi], dtype=F64))))]
    Xs.append(torch.diag(torch.tensor([1.0, -1.0, -1.0] + ([1.0] if d == 6 else []), dtype=F64)))
    for X in Xs:
        X = X.clone().requires_grad_()
        (g,) = torch.autograd.grad(mod.log(X).square().sum() + mod.log(X).sum(), X)
        assert torch.isfinite(g).all()
    x = torch.zeros(d, dtype=F64, requires_grad=True)
    for f in (mod.exp, mod.left_jacobian, mod.right_jacobian_inv):
        (g,) = torch.autograd.grad(f(x).sum(), x)
        assert torch.isfinite(g).all()
        (g2,) = torch.autograd.grad(torch.func.grad(lambda y, f=f: f(y).square().sum())(x).sum(), x)
        assert torch.isfinite(g2).all()


@pytest.mark.parametrize("name", ["so3", "se3"])
def test_exp_derivative_three_ways(name, gen):
    """d exp(x)/dx: analytic (from J_r: dX = X (J_r δ)^), torch.func.jacrev and finite differences."""
    mod, d, n = GROUPS[name]
    x = tangents(mod, 3, gen)[-3]
    analytic = torch.stack([mod.exp(x) @ mod.hat(mod.right_jacobian(x)[:, i]) for i in range(d)], -1)
    autodiff = torch.func.jacrev(mod.exp)(x)
    fd = fd_jacobian(mod.exp, x)
    assert (analytic - autodiff).abs().max() < 1e-12
    assert (analytic - fd).abs().max() < 1e-8


# ---------------------------------------------------------------------------------------------- batching

@pytest.mark.parametrize("name", ["so3", "se3"])
def test_batched_equals_flattened_equals_loop(name, gen):
    mod, d, n = GROUPS[name]
    x = tangents(mod, 21, gen)[:24].reshape(2, 3, 4, d)
    check_batching(mod.exp, [x], [1])
    check_batching(mod.right_jacobian_inv, [x], [1])
    X = mod.exp(x)
    check_batching(mod.log, [X], [2])
    Y = mod.exp(x.flip(0))
    check_batching(mod.compose, [X, Y], [2, 2])
    # broadcasting == manual expansion
    assert torch.equal(mod.compose(X[:1], Y), mod.compose(X[:1].expand_as(Y), Y))


@pytest.mark.parametrize("name", ["so3", "se3"])
def test_vmap_jacrev_and_compile(name, gen):
    mod, d, n = GROUPS[name]
    x = tangents(mod, 5, gen)[-6:]
    assert torch.allclose(torch.func.vmap(mod.exp)(x), mod.exp(x), atol=1e-15)
    X = mod.exp(x)
    assert torch.allclose(torch.func.vmap(mod.log)(X), mod.log(X), atol=1e-15)
    J = torch.func.vmap(torch.func.jacrev(mod.log))(X)
    assert J.shape == (6, d, n, n) and torch.isfinite(J).all()
    torch._dynamo.reset()
    f = torch.compile(lambda a, b: mod.log(mod.compose(mod.exp(a), b)), fullgraph=True, dynamic=False)
    out = f(x, X)
    assert torch.allclose(out, mod.log(mod.compose(mod.exp(x), X)), atol=1e-12)


@pytest.mark.parametrize("name", ["so3", "se3"])
def test_inverse_compose_and_jacobians_under_transforms(name, gen):
    """vmap (batched and broadcast arguments), jacrev and compile(fullgraph) of the kernels that
    assemble their output from per-entry rows (the Jacobians) or write into their own output (inverse)."""
    mod, d, n = GROUPS[name]
    x = tangents(mod, 5, gen)[-6:]
    X, Y = mod.exp(x), mod.exp(x.flip(0))
    vmap, jacrev = torch.func.vmap, torch.func.jacrev
    assert (vmap(mod.inverse)(X) - mod.inverse(X)).abs().max() < 1e-15
    assert (vmap(mod.compose)(X, Y) - mod.compose(X, Y)).abs().max() < 1e-15
    assert (vmap(mod.compose, in_dims=(None, 0))(X[0], Y) - mod.compose(X[0], Y)).abs().max() < 1e-15
    # float32 takes the row-by-row path on CPU (float64 a matmul): same transforms, same values
    X32, Y32 = X.float(), Y.float()
    for dims in ((0, 0), (0, None), (None, 0)):
        a, b = (X32 if dims[0] == 0 else X32[0]), (Y32 if dims[1] == 0 else Y32[0])
        assert (vmap(mod.compose, in_dims=dims)(a, b) - mod.compose(a, b)).abs().max() == 0
    Jc32 = vmap(jacrev(mod.compose, argnums=(0, 1)))(X32, Y32)
    Jc64 = vmap(jacrev(mod.compose, argnums=(0, 1)))(X, Y)
    assert all((a.double() - b).abs().max() < 1e-5 for a, b in zip(Jc32, Jc64))
    # jacrev of inverse along the group (X exp(δ)), where it must agree with the matrix inverse
    def along(inv):
        return vmap(jacrev(lambda dl, Z: inv(mod.compose(Z, mod.exp(dl)))))(torch.zeros_like(x), X)
    assert (along(mod.inverse) - along(torch.linalg.inv)).abs().max() < 1e-12
    fns = (mod.left_jacobian, mod.right_jacobian, mod.left_jacobian_inv, mod.right_jacobian_inv)
    for f in fns:
        assert (vmap(f)(x) - f(x)).abs().max() < 1e-15
        J = vmap(jacrev(f))(x)
        assert J.shape == (6, d, d, d) and torch.isfinite(J).all()
        assert (J[2] - torch.autograd.functional.jacobian(f, x[2])).abs().max() < 1e-12
    torch._dynamo.reset()
    for f, args in [(mod.inverse, (X,)), *((f, (x,)) for f in fns)]:
        cf = torch.compile(f, fullgraph=True, dynamic=False)
        assert (cf(*args) - f(*args)).abs().max() < 1e-12


def test_dtype_and_device_follow_inputs():
    for dtype in (F32, F64):
        x = torch.randn(2, 6, dtype=dtype)
        for out in (se3.exp(x), se3.log(se3.exp(x)), se3.left_jacobian(x), so3.exp(x[:, 3:])):
            assert out.dtype == dtype and out.device == x.device
    assert se3.identity(dtype=F64, device="cpu").dtype == F64


# ---------------------------------------------------------------------------------------------- bad input

def test_bad_input_errors_name_the_argument():
    with pytest.raises(ValueError, match=r"'xi'.*\(\*, 6\)"):
        se3.exp(torch.zeros(4, 3))
    with pytest.raises(ValueError, match=r"'X'.*\(\*, 4, 4\)"):
        se3.log(torch.zeros(3, 3))
    with pytest.raises(TypeError, match="'omega'.*floating"):
        so3.exp(torch.zeros(3, dtype=torch.int64))
    with pytest.raises(TypeError, match="'R'.*torch.Tensor"):
        so3.log([[1, 0, 0], [0, 1, 0], [0, 0, 1]])
    with pytest.raises(ValueError, match="'p'"):
        se3.act(se3.identity(), torch.zeros(4))
    with pytest.raises(TypeError, match="dtypes"):
        so3.compose(so3.identity(dtype=F32), so3.identity(dtype=F64))
    with pytest.raises(ValueError, match="do not broadcast"):
        so3.interpolate(so3.identity(2), so3.identity(3), 0.5)


def test_nan_stays_in_its_element():
    x = torch.randn(5, 6, dtype=F64)
    x[2, 4] = float("nan")
    X = se3.exp(x)
    assert torch.isnan(X[2]).any() and torch.isfinite(X[[0, 1, 3, 4]]).all()
    X = se3.exp(torch.randn(5, 6, dtype=F64))
    X[1, 0, 0] = float("nan")
    xi = se3.log(X)
    assert torch.isnan(xi[1]).any() and torch.isfinite(xi[[0, 2, 3, 4]]).all()


def test_angles_near_edges_cover_zero_and_pi():
    a = angles_near_edges(F64)
    assert (a == 0).any() and (a == math.pi).any()


# ---------------------------------------------------------------------------------------------- log vs mpmath
# so3.log / se3.log against 60-digit references at and near the edges, in both dtypes, values and the
# derivative along the group (d/dε log(X exp(ε δ)) = J_r⁻¹ δ, a textbook closed form evaluated in mpmath)

LOG_ANGLES = [0.0, 1e-12, 1e-9, 1e-6, 1e-3, 0.0999, 0.1001, 0.3162, 0.3163, 1.0, 2.0, 3.0,
              math.pi - 1e-6, math.pi - 1e-9, math.pi]
LOG_AXES = [(0.6, -0.48, 0.64), (1.0, 0.0, 0.0), (0.0, 0.0, 1.0), (0.0, -0.6, 0.8), (-2.0, 1.0, 2.0)]


def _mp():
    mpmath = pytest.importorskip("mpmath")
    mpmath.mp.dps = 60
    return mpmath


def _mp_hat(mp, w):
    return mp.matrix([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])


def _mp_rotation(mp, axis, theta):
    """R = I + sin θ û + (1 − cos θ) û² and ω = θ u, in mpmath."""
    u = [mp.mpf(c) for c in axis]
    nu = mp.sqrt(sum(c * c for c in u))
    u = [c / nu for c in u]
    th = mp.mpf(theta)
    U = _mp_hat(mp, u)
    return mp.eye(3) + mp.sin(th) * U + (1 - mp.cos(th)) * U * U, [th * c for c in u]


def _mp_jr_inv(mp, w):
    """J_r(ω)⁻¹ = I + ½ ω̂ + (1/θ² − (1 + cos θ)/(2 θ sin θ)) ω̂²  (Solà Eq. 146 with ω → −ω)."""
    w = [mp.mpf(float(c)) for c in w]
    th = mp.sqrt(sum(c * c for c in w))
    d = mp.mpf(1) / 12 if th == 0 else 1 / th**2 - (1 + mp.cos(th)) / (2 * th * mp.sin(th))
    W = _mp_hat(mp, w)
    return mp.eye(3) + W / 2 + d * W * W


def _to_torch(mp_mat, rows, cols, dtype=F64):
    return torch.tensor([[float(mp_mat[i, j]) for j in range(cols)] for i in range(rows)], dtype=dtype)


def _along_group(f, X, hat):
    """d/dε f(X exp(ε E_k)) at ε = 0 for the generators E_k = hat(e_k), from f's autograd Jacobian."""
    J = torch.autograd.functional.jacobian(f, X).double()
    n = J.dim() - X.dim()
    d = 3 if X.shape[-1] == 3 else 6
    cols = [torch.tensordot(J, X.double() @ hat(torch.eye(d, dtype=F64)[k]), dims=X.dim()) for k in range(d)]
    assert n == 1
    return torch.stack(cols, -1)


@pytest.mark.parametrize("dtype", [F64, F32])
def test_so3_log_and_its_derivative_against_mpmath_at_every_angle(dtype):
    mp = _mp()
    eps = torch.finfo(dtype).eps
    for axis in LOG_AXES:
        for theta in LOG_ANGLES:
            Rm, wm = _mp_rotation(mp, axis, theta)
            R = _to_torch(Rm, 3, 3, dtype)
            w = so3.log(R)
            assert w.dtype == dtype and torch.isfinite(w).all()
            ref = torch.tensor([float(c) for c in wm], dtype=F64)
            err = (w.double() - ref).abs().max().item()
            if math.pi - theta < 10 * eps:  # rounds to (or is) angle π: ±ω are both logarithms
                err = min(err, (w.double() + ref).abs().max().item())
            assert err <= 4 * eps * math.pi, (dtype, axis, theta, err)
            # derivative along the group: J_r⁻¹ of the logarithm returned (finite at 0 and π too)
            G = _along_group(so3.log, R, so3.hat)
            Jref = _to_torch(_mp_jr_inv(mp, w), 3, 3)
            gerr = (G - Jref).abs().max().item()
            assert gerr <= (2e-6 if dtype == F32 else 4e-15), (dtype, axis, theta, gerr)


def test_so3_log_exactly_at_pi_with_a_zero_quaternion_scalar():
    """At angle exactly π (w = ±0 for every Shepperd row) the value is ±π u and the derivative is the
    one-sided J_r⁻¹ of the branch returned — not the average of both sides that |w| would give."""
    mp = _mp()
    for diag in ((1.0, -1.0, -1.0), (-1.0, 1.0, -1.0), (-1.0, -1.0, 1.0)):
        for dtype in (F64, F32):
            R = torch.diag(torch.tensor(diag, dtype=dtype))
            w = so3.log(R)
            assert (w.abs().double() - math.pi * (torch.tensor(diag) > 0).double()).abs().max() < 4e-7
            G = _along_group(so3.log, R, so3.hat)
            assert (G - _to_torch(_mp_jr_inv(mp, w), 3, 3)).abs().max() < 1e-6


def _mp_se3_log_v(mp, w, t):
    """v = J_l(ω)⁻¹ t = t − ½ ω×t + d ω×(ω×t), d = 1/θ² − (1 + cos θ)/(2 θ sin θ)  (Solà Eq. 146)."""
    w = [mp.mpf(float(c)) for c in w]
    t = mp.matrix([mp.mpf(float(c)) for c in t])
    th = mp.sqrt(sum(c * c for c in w))
    d = mp.mpf(1) / 12 if th == 0 else 1 / th**2 - (1 + mp.cos(th)) / (2 * th * mp.sin(th))
    W = _mp_hat(mp, w)
    return (mp.eye(3) - W / 2 + d * W * W) * t


def _mp_se3_jr_inv(mp, xi):
    """SE(3) J_r(ξ)⁻¹ = [[J⁻¹, −J⁻¹ Q J⁻¹], [0, J⁻¹]], J = J_r(ω), Q = Q(−v, −ω) (Solà Eq. 179-180)."""
    v, w = [-mp.mpf(float(c)) for c in xi[:3]], [-mp.mpf(float(c)) for c in xi[3:]]
    th = mp.sqrt(sum(c * c for c in w))
    if th == 0:
        k1, k2, k3 = mp.mpf(1) / 6, -mp.mpf(1) / 24, mp.mpf(1) / 120
    else:
        k1 = (th - mp.sin(th)) / th**3
        k2 = (1 - th**2 / 2 - mp.cos(th)) / th**4
        k3 = (th - mp.sin(th) - th**3 / 6) / th**5
    V, W = _mp_hat(mp, v), _mp_hat(mp, w)
    Q = (V / 2 + k1 * (W * V + V * W + W * V * W) - k2 * (W * W * V + V * W * W - 3 * W * V * W)
         - (k2 - 3 * k3) / 2 * (W * V * W * W + W * W * V * W))
    Ji = _mp_jr_inv(mp, xi[3:])
    J = mp.zeros(6, 6)
    top = -Ji * Q * Ji
    for i in range(3):
        for j in range(3):
            J[i, j] = J[i + 3, j + 3] = Ji[i, j]
            J[i, j + 3] = top[i, j]
    return J


@pytest.mark.parametrize("dtype", [F64, F32])
def test_se3_log_against_mpmath_and_its_derivative_at_every_angle(dtype):
    """Including both sides of the series switch of d (θ² = 0.01 in float64, 0.1 in float32)."""
    mp = _mp()
    eps = torch.finfo(dtype).eps
    t = torch.tensor([0.3, -1.0, 2.0], dtype=F64)
    for axis in LOG_AXES[:3]:
        for theta in LOG_ANGLES:
            Rm, wm = _mp_rotation(mp, axis, theta)
            X = torch.eye(4, dtype=F64)
            X[:3, :3], X[:3, 3] = _to_torch(Rm, 3, 3), t
            X = X.to(dtype)
            xi = se3.log(X)
            assert xi.dtype == dtype and torch.isfinite(xi).all()
            w = xi[3:].double()
            ref_w = torch.tensor([float(c) for c in wm], dtype=F64)
            if math.pi - theta < 10 * eps and (w + ref_w).abs().max() < (w - ref_w).abs().max():
                ref_w = -ref_w
            assert (w - ref_w).abs().max() <= 4 * eps * math.pi, (dtype, axis, theta)
            # v for the ω returned and the translation as stored: the closed form in 40 digits
            v_ref = torch.tensor([float(c) for c in _mp_se3_log_v(mp, xi[3:], X[:3, 3])], dtype=F64)
            assert (xi[:3].double() - v_ref).abs().max() <= 16 * eps, (dtype, axis, theta)
            G = _along_group(se3.log, X, se3.hat)
            Jref = _to_torch(_mp_se3_jr_inv(mp, xi), 6, 6)
            gerr = (G - Jref).abs().max().item()
            assert gerr <= (4e-6 if dtype == F32 else 8e-15), (dtype, axis, theta, gerr)


def test_log_paths_agree():
    """The fast paths (no autograd: written straight into the output; CPU matrix product for K) and the
    general ones (autograd, vmap, the elementwise K used on GPUs and when float32 matmuls may round)
    compute one function."""
    g = torch.Generator().manual_seed(9)
    for dtype in (F64, F32):
        w = rotation_vectors(200, g, dtype)
        R = so3.exp(w)
        X = se3.exp(torch.cat((torch.randn(w.shape[0], 3, generator=g, dtype=F64).to(dtype), w), -1))
        for mod, Y in ((so3, R), (se3, X)):
            plain = mod.log(Y)
            assert torch.equal(plain, mod.log(Y.clone().requires_grad_()).detach())
            assert plain.is_contiguous()
            tol = 4 * torch.finfo(dtype).eps * (4 if mod is so3 else 16)  # summation order differs
            assert (torch.func.vmap(mod.log)(Y) - plain).abs().max() <= tol
            old = torch.get_float32_matmul_precision()
            try:
                torch.set_float32_matmul_precision("medium")  # float32: K elementwise
                assert (mod.log(Y) - plain).abs().max() <= tol
            finally:
                torch.set_float32_matmul_precision(old)
    # so3.compose in float32 (rows accumulated in the output without autograd) is the stacked-rows path
    A, B = so3.random(50, generator=g), so3.random(50, generator=g)
    assert torch.equal(so3.compose(A, B), so3.compose(A.clone().requires_grad_(), B).detach())
    assert torch.equal(so3.compose(A[:1], B), so3.compose(A[:1].expand_as(B), B))
    assert (so3.compose(A, B).double() - A.double() @ B.double()).abs().max() < 1e-6
    # se3.inverse in float64 (−tᵀR as a batched matmul) against the matrix inverse
    X = se3.random(50, generator=g, dtype=F64)
    assert (se3.inverse(X) - torch.linalg.inv(X)).abs().max() < 1e-14
