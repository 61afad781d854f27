"""torchlie.manifolds.metric: geodesics of a varying metric G(x) (seed 004 §12.6) — a constant metric gives
the straight line; the Poincaré half-plane (G = I / y²) gives semicircles centred on the x axis and, on a
vertical, y growing geometrically, with the closed-form length arccosh(1 + |Δ|² / (2 y₀ y₁)); minimality
(straight line, perturbed paths); the planar arm's kinetic-energy metric; batched == loop; a NaN element
isolated; float32; gradients (path energy by gradcheck, the geodesic's implicit derivative vs finite
differences); bad input."""

import math

import pytest
import torch

from controllers.systems.arm import PlanarArm
from torchlie.manifolds.metric import GeodesicReason, geodesic, path_energy, path_length

D = torch.float64


def half_plane(x):
    return torch.eye(2, dtype=x.dtype, device=x.device) / (x[..., 1] ** 2)[..., None, None]


def _line(x0, x1, N):
    s = torch.linspace(0, 1, N + 1, dtype=x0.dtype)[:, None]
    return x0.unsqueeze(-2) + s * (x1 - x0).unsqueeze(-2)


def _circle_error(path, x0, x1):
    """Distance of the path's points to the semicircle through x0, x1 centred on the x axis."""
    c = ((x1 ** 2).sum(-1) - (x0 ** 2).sum(-1)) / (2 * (x1[..., 0] - x0[..., 0]))
    rad = ((x0[..., 0] - c) ** 2 + x0[..., 1] ** 2).sqrt()
    return (((path[..., 0] - c[..., None]) ** 2 + path[..., 1] ** 2).sqrt() - rad[..., None]).abs().amax(-1)


ARM = PlanarArm(links=3, lengths=(2.0, 2.0, 1.0))
Q0 = torch.tensor([[0.0, 0.0, 0.0], [math.pi / 2, -math.pi / 2, 0.3], [-0.5, 1.5, -1.0]], dtype=D)
Q1 = torch.tensor([[math.pi / 2, 1.0, 1.0], [-0.3, 1.2, -0.8], [1.5, -1.0, 1.2]], dtype=D)


def test_constant_metric_gives_the_straight_line():
    g = torch.Generator().manual_seed(0)
    M = torch.randn(3, 3, generator=g, dtype=D)
    A = M @ M.mT + 0.5 * torch.eye(3, dtype=D)
    x0, x1 = torch.randn(2, 3, generator=g, dtype=D), torch.randn(2, 3, generator=g, dtype=D)
    N = 10
    line = _line(x0, x1, N)
    # from a perturbed initial path, Newton comes back to the straight line (uniformly spaced)
    init = line + 0.3 * torch.randn(2, N + 1, 3, generator=g, dtype=D)
    r = geodesic(lambda x: A.expand(*x.shape, 3), x0, x1, N, init=init)
    assert bool(r.converged.all()) and r.reason.tolist() == [0, 0]
    torch.testing.assert_close(r.path, line, rtol=0, atol=1e-12)
    d = x1 - x0
    torch.testing.assert_close(r.energy, (d.unsqueeze(-2) @ A @ d.unsqueeze(-1))[..., 0, 0] / N)
    torch.testing.assert_close(r.length, (d.unsqueeze(-2) @ A @ d.unsqueeze(-1))[..., 0, 0].sqrt())


def test_half_plane_semicircles_and_closed_form_length():
    x0 = torch.tensor([[-1.0, 1.0], [0.0, 0.5], [1.0, 2.0]], dtype=D)
    x1 = torch.tensor([[1.0, 1.0], [2.0, 1.5], [-0.5, 0.3]], dtype=D)
    r = geodesic(half_plane, x0, x1, 96)
    assert bool(r.converged.all())
    assert float(_circle_error(r.path, x0, x1).max()) < 1e-4
    exact = torch.acosh(1 + ((x1 - x0) ** 2).sum(-1) / (2 * x0[:, 1] * x1[:, 1]))
    torch.testing.assert_close(r.length, exact, rtol=1e-4, atol=0)
    # the discretization error is O(h²): halving the steps quadruples it (roughly)
    r48 = geodesic(half_plane, x0, x1, 48)
    e96, e48 = _circle_error(r.path, x0, x1), _circle_error(r48.path, x0, x1)
    assert bool((e48 / e96 > 3).all()) and bool((e48 / e96 < 5).all())


def test_half_plane_vertical_geodesic_is_geometric():
    x0, x1 = torch.tensor([0.3, 0.5], dtype=D), torch.tensor([0.3, 4.0], dtype=D)
    N = 64
    r = geodesic(half_plane, x0, x1, N)
    assert bool(r.converged)
    torch.testing.assert_close(r.path[:, 0], torch.full((N + 1,), 0.3, dtype=D), rtol=0, atol=1e-12)
    y = 0.5 * 8.0 ** (torch.arange(N + 1, dtype=D) / N)  # constant speed: log y linear
    torch.testing.assert_close(r.path[:, 1], y, rtol=1e-4, atol=0)
    torch.testing.assert_close(r.length, torch.tensor(math.log(8.0), dtype=D), rtol=1e-4, atol=0)


def test_geodesic_is_a_minimum_and_has_constant_speed():
    N = 24
    r = geodesic(ARM.mass_matrix, Q0, Q1, N)
    assert bool(r.converged.all())
    assert bool((r.path[:, 0] == Q0).all()) and bool((r.path[:, -1] == Q1).all())
    line = _line(Q0, Q1, N)
    assert bool((r.energy < 0.95 * path_energy(ARM.mass_matrix, line)).all())
    assert bool((r.length < path_length(ARM.mass_matrix, line)).all())
    # small perturbations of the interior raise the energy (a local minimum, not only stationary)
    g = torch.Generator().manual_seed(1)
    for _ in range(3):
        p = r.path.clone()
        p[:, 1:-1] += 1e-3 * torch.randn(p[:, 1:-1].shape, generator=g, dtype=D)
        assert bool((path_energy(ARM.mass_matrix, p) > r.energy).all())
    # constant metric speed: L² = N E up to the discretization (Cauchy-Schwarz: L² <= N E always)
    assert bool((r.length ** 2 <= N * r.energy * (1 + 1e-12)).all())
    torch.testing.assert_close(r.length ** 2, N * r.energy, rtol=1e-3, atol=0)


def test_batched_equals_loop_and_nan_is_isolated():
    q0 = Q0.clone()
    q0[1, 0] = float("nan")
    r = geodesic(ARM.mass_matrix, q0, Q1, 16)
    assert r.reason.tolist() == [int(GeodesicReason.CONVERGED), int(GeodesicReason.NONFINITE),
                                 int(GeodesicReason.CONVERGED)]
    assert bool(torch.isnan(r.path[1]).all()) and bool(torch.isnan(r.energy[1]))
    for b in (0, 2):
        rb = geodesic(ARM.mass_matrix, q0[b], Q1[b], 16)
        torch.testing.assert_close(r.path[b], rb.path, rtol=0, atol=1e-10)
        assert bool(rb.converged)
    # broadcasting: one start, several goals (*B = (2, 1) x (3,))
    rr = geodesic(half_plane, torch.tensor([[0.0, 1.0]], dtype=D).expand(2, 1, 2),
                  torch.tensor([[1.0, 1.0], [2.0, 0.5], [-1.0, 2.0]], dtype=D), 16)
    assert rr.path.shape == (2, 3, 17, 2) and bool(rr.converged.all())


def test_float32():
    x0 = torch.tensor([[-1.0, 1.0], [0.0, 0.5]])
    x1 = torch.tensor([[1.0, 1.0], [2.0, 1.5]])
    r = geodesic(half_plane, x0, x1, 32)
    assert r.path.dtype == torch.float32 and r.energy.dtype == torch.float32
    assert bool(r.converged.all())
    r64 = geodesic(half_plane, x0.double(), x1.double(), 32)
    torch.testing.assert_close(r.path.double(), r64.path, rtol=0, atol=1e-4)


def test_gradients():
    g = torch.Generator().manual_seed(2)
    path = torch.tensor([[0.0, 1.0], [0.4, 1.5], [1.0, 1.2], [1.5, 0.8]], dtype=D)
    path = path + 0.01 * torch.randn(path.shape, generator=g, dtype=D)
    assert torch.autograd.gradcheck(lambda p: path_energy(half_plane, p), (path.requires_grad_(),))
    assert torch.autograd.gradcheck(lambda p: path_length(half_plane, p), (path,))
    # the geodesic's derivative w.r.t. its endpoint (implicit function theorem) vs central differences
    x0 = torch.tensor([0.0, 1.0], dtype=D)
    x1 = torch.tensor([1.5, 0.8], dtype=D, requires_grad=True)
    w = torch.randn(9, 2, generator=g, dtype=D)

    def f(end):
        return (geodesic(half_plane, x0, end, 8, tol=1e-12).path * w).sum()

    (grad,) = torch.autograd.grad(f(x1), x1)
    h = 1e-5
    fd = torch.stack([(f(x1.detach() + h * e) - f(x1.detach() - h * e)) / (2 * h)
                      for e in torch.eye(2, dtype=D)])
    torch.testing.assert_close(grad, fd, rtol=1e-5, atol=1e-7)
    # ... and w.r.t. a tensor the metric closes over: G = diag(1, c) / y²
    c = torch.tensor(2.0, dtype=D, requires_grad=True)

    def fc(cv):
        def G(x):
            return torch.diag(torch.stack([torch.ones((), dtype=D), cv])) / (x[..., 1] ** 2)[..., None, None]
        return (geodesic(G, x0, x1.detach(), 8, tol=1e-12).path * w).sum()

    (gc,) = torch.autograd.grad(fc(c), c)
    fdc = (fc(c.detach() + h) - fc(c.detach() - h)) / (2 * h)
    torch.testing.assert_close(gc, fdc, rtol=1e-5, atol=1e-7)
    assert abs(float(gc)) > 1e-3
    # the value is the same with and without the graph
    with torch.no_grad():
        plain = geodesic(half_plane, x0, x1, 8, tol=1e-12).path
    torch.testing.assert_close(geodesic(half_plane, x0, x1, 8, tol=1e-12).path.detach(), plain, rtol=0,
                               atol=0)


def test_bad_input():
    x0, x1 = torch.zeros(2, dtype=D), torch.ones(2, dtype=D)
    with pytest.raises(TypeError, match="'G'"):
        geodesic("metric", x0, x1)
    with pytest.raises(TypeError, match="'x0'"):
        geodesic(half_plane, torch.zeros(2, dtype=torch.int64), x1)
    with pytest.raises(ValueError, match="'x1'"):
        geodesic(half_plane, x0, torch.ones(3, dtype=D))
    with pytest.raises(TypeError, match="dtype"):
        geodesic(half_plane, x0, x1.float())
    with pytest.raises(ValueError, match="'steps'"):
        geodesic(half_plane, x0, x1, 1)
    with pytest.raises(ValueError, match="broadcast"):
        geodesic(half_plane, torch.zeros(2, 2, dtype=D), torch.ones(3, 2, dtype=D))
    with pytest.raises(ValueError, match="'G' must map"):
        geodesic(lambda x: torch.eye(3, dtype=D), x0 + 1, x1 + 1)
    with pytest.raises(ValueError, match="'init'"):
        geodesic(half_plane, x0 + 1, x1 + 1, 4, init=torch.zeros(4, 2, dtype=D))
    with pytest.raises(ValueError, match="'path'"):
        path_energy(half_plane, torch.ones(1, 2, dtype=D))
    with pytest.raises(TypeError, match="'G'"):
        path_length(None, torch.ones(3, 2, dtype=D))
