"""controllers.task_costs: every map's Jacobian against autograd and finite differences (away from the
ReLU kinks), the values against direct formulas, composition into a ResidualCost, batching and errors."""

import math

import pytest
import torch

from controllers.systems.arm import PlanarArm
from controllers.task_costs import (
    Map,
    avoid,
    bimanual_com,
    bimanual_hands,
    concat,
    cut,
    distance,
    manipulability,
    mean,
    on_joints,
    planar_com,
    planar_ee,
    residual_cost,
    state,
    track,
)

LENGTHS = (2.0, 2.0, 1.0)
D = torch.float64


def _autograd_jacobian(m: Map, x: torch.Tensor) -> torch.Tensor:
    """``∂f/∂x`` per time step by torch.func (an independent derivative)."""
    flat = x.reshape(-1, x.shape[-1])
    J = torch.func.vmap(torch.func.jacrev(lambda v: m.f(v[None])[0]))(flat)
    return J.reshape(*x.shape[:-1], m.p, x.shape[-1])


def _fd_jacobian(m: Map, x: torch.Tensor, h: float = 1e-6) -> torch.Tensor:
    cols = []
    for j in range(x.shape[-1]):
        dx = torch.zeros_like(x)
        dx[..., j] = h
        cols.append((m.f(x + dx) - m.f(x - dx)) / (2 * h))
    return torch.stack(cols, -1)


def _maps():
    g = torch.Generator().manual_seed(0)
    ee, com = planar_ee(LENGTHS), planar_com(LENGTHS)
    frame = torch.tensor([[math.cos(0.3), -math.sin(0.3)], [math.sin(0.3), math.cos(0.3)]], dtype=D)
    mu = torch.randn(4, 2, generator=g, dtype=D)
    V = torch.randn(4, 2, 2, generator=g, dtype=D)
    return {
        "state": state(3),
        "ee": ee,
        "ee_position": planar_ee(LENGTHS, orientation=False),
        "com": com,
        "track": track(ee, torch.tensor([1.0, 2.0, 0.5], dtype=D)),
        "cut_joint": cut(state(3), [-0.5, -1.0, -math.inf], [0.5, 1.0, 0.2]),
        "cut_object": cut(planar_ee(LENGTHS, orientation=False), [-0.3, -0.2], [0.3, 0.2],
                          center=[1.0, 1.5], frame=frame),
        "avoid": avoid(planar_ee(LENGTHS, orientation=False), mu, V @ V.mT + 0.5 * torch.eye(2, dtype=D)),
        "distance": distance(com, torch.tensor([0.5, 0.5], dtype=D), 1.3),
        "ellipse": distance(com, torch.tensor([0.5, 0.5], dtype=D),
                            Sigma=torch.tensor([[2.0, 0.3], [0.3, 0.5]], dtype=D)),
    }


@pytest.mark.parametrize("name", list(_maps()))
def test_jacobian_equals_autograd_and_finite_differences(name):
    m = _maps()[name]
    x = torch.randn(5, 7, 3, generator=torch.Generator().manual_seed(1), dtype=D)
    f, J = m(x)
    assert f.shape == (5, 7, m.p) and J.shape == (5, 7, m.p, 3)
    torch.testing.assert_close(J, _autograd_jacobian(m, x), rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(J, _fd_jacobian(m, x), rtol=1e-6, atol=1e-7)


def test_values_against_the_arm_model_and_direct_formulas():
    arm = PlanarArm(links=3, lengths=LENGTHS)
    q = torch.randn(6, 3, generator=torch.Generator().manual_seed(2), dtype=D)
    pts = arm.fk(q)  # base, joints, tip
    torch.testing.assert_close(planar_ee(LENGTHS).f(q)[..., :2], pts[..., -1, :])
    torch.testing.assert_close(planar_ee(LENGTHS).f(q)[..., 2], q.sum(-1))
    torch.testing.assert_close(planar_com(LENGTHS).f(q), pts[..., 1:, :].mean(-2))  # equal masses at joints
    # cut: zero inside, signed distance outside
    c = cut(state(2), [-1.0, 0.0], [1.0, 2.0])
    x = torch.tensor([[0.5, 1.0], [-3.0, 2.5], [1.5, -0.25]], dtype=D)
    torch.testing.assert_close(c.f(x), torch.tensor([[0.0, 0.0], [-2.0, 0.5], [0.5, -0.25]], dtype=D))
    # avoid: 1 at the centre, 0 on and outside the boundary
    a = avoid(state(2), torch.tensor([1.0, 1.0], dtype=D), torch.diag(torch.tensor([4.0, 1.0], dtype=D)))
    x = torch.tensor([[1.0, 1.0], [3.0, 1.0], [1.0, 1.5], [5.0, 5.0]], dtype=D)
    torch.testing.assert_close(a.f(x)[..., 0], torch.tensor([1.0, 0.0, 0.75, 0.0], dtype=D))
    # distance: zero on the sphere of radius r
    d = distance(state(2), torch.tensor([1.0, 1.0], dtype=D), 2.0)
    x = torch.tensor([[3.0, 1.0], [1.0, 1.0], [1.0, 5.0]], dtype=D)
    torch.testing.assert_close(d.f(x)[..., 0], torch.tensor([0.0, 1.0, -3.0], dtype=D))


def test_residual_cost_stacks_terms_block_diagonally():
    T = 6
    ee, com = planar_ee(LENGTHS), planar_com(LENGTHS)
    Q1 = torch.zeros(T + 1, 3, 3, dtype=D)
    Q1[-1] = torch.eye(3, dtype=D)
    Q2 = 0.5 * torch.eye(2, dtype=D)
    R = 1e-2 * torch.eye(3, dtype=D)
    cost = residual_cost([(track(ee, [1.0, 2.0, 0.0]), Q1), (cut(com, [-1.0, -1.0], [1.0, 0.5]), Q2)], R)
    g = torch.Generator().manual_seed(3)
    x = torch.randn(4, T + 1, 3, generator=g, dtype=D)
    u = torch.randn(4, T, 3, generator=g, dtype=D)
    f1 = ee.f(x) - torch.tensor([1.0, 2.0, 0.0], dtype=D)
    f2 = cut(com, [-1.0, -1.0], [1.0, 0.5]).f(x)
    want = ((f1.unsqueeze(-2) @ Q1).squeeze(-2) * f1).sum((-1, -2)) + ((f2 @ Q2) * f2).sum((-1, -2))
    want = want + ((u @ R) * u).sum((-1, -2))
    torch.testing.assert_close(cost.evaluate(x, u), want)
    # the Gauss-Newton derivatives (Eq. 104-105) are consistent with the value's autograd gradient
    gx, gu, *_ = cost.derivatives(x, u)
    xg = x.clone().requires_grad_(True)
    (dx,) = torch.autograd.grad(cost.evaluate(xg, u).sum(), xg)
    torch.testing.assert_close(gx, dx)


def test_float32_and_batched_targets_broadcast():
    mu = torch.randn(5, 1, 3, generator=torch.Generator().manual_seed(4))  # one target per problem
    m = track(planar_ee(LENGTHS), mu)
    x = torch.randn(5, 8, 3, generator=torch.Generator().manual_seed(5))
    f, J = m(x)
    assert f.dtype == torch.float32 and J.dtype == torch.float32
    for b in range(5):
        torch.testing.assert_close(f[b], track(planar_ee(LENGTHS), mu[b]).f(x[b]))


def test_bad_input_is_named():
    with pytest.raises(ValueError, match="'lower' must not exceed 'upper'"):
        cut(state(2), [1.0, 0.0], [0.0, 1.0])
    with pytest.raises(ValueError, match="'lower' has NaN"):
        cut(state(2), [math.nan, 0.0], None)
    with pytest.raises(ValueError, match="exactly one of 'radius' and 'Sigma'"):
        distance(state(2), [0.0, 0.0])
    with pytest.raises(ValueError, match="'radius' must be positive"):
        distance(state(2), [0.0, 0.0], -1.0)
    with pytest.raises(ValueError, match="3 joint angles"):
        planar_ee(LENGTHS).f(torch.zeros(2, 4, dtype=D))
    with pytest.raises(ValueError, match="'Sigma' must be"):
        avoid(state(2), [0.0, 0.0], torch.eye(3, dtype=D)).f(torch.zeros(1, 2, dtype=D))
    with pytest.raises(TypeError, match="must be a controllers.task_costs.Map"):
        track(lambda x: x, [0.0])
    with pytest.raises(ValueError, match=r"Q must end in \(3, 3\)"):
        residual_cost([(planar_ee(LENGTHS), torch.eye(2, dtype=D))], torch.eye(3, dtype=D))
    with pytest.raises(ValueError, match="at least one"):
        residual_cost([], torch.eye(3, dtype=D))


def test_bimanual_maps_against_the_chains_joint_positions():
    lengths = (1.5, 1.0, 0.8, 1.2, 0.6)
    x = torch.randn(7, 5, generator=torch.Generator().manual_seed(6), dtype=D)
    left = PlanarArm(links=3, lengths=(1.5, 1.0, 0.8)).fk(x[:, [0, 1, 2]])
    right = PlanarArm(links=3, lengths=(1.5, 1.2, 0.6)).fk(x[:, [0, 3, 4]])
    torch.testing.assert_close(bimanual_hands(lengths).f(x), torch.cat([left[:, -1], right[:, -1]], -1))
    # unit masses at the joints, two at the torso's tip (shared by both chains)
    com = (2 * left[:, 1] + left[:, 2] + left[:, 3] + right[:, 2] + right[:, 3]) / 6
    torch.testing.assert_close(bimanual_com(lengths).f(x), com)
    for m in (bimanual_hands(lengths), bimanual_com(lengths)):
        xs = x[:, None, :]
        torch.testing.assert_close(m.J(xs), _autograd_jacobian(m, xs), rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(m.J(xs), _fd_jacobian(m, xs), rtol=1e-6, atol=1e-7)
    with pytest.raises(ValueError, match="5 link lengths"):
        bimanual_hands((1.0, 1.0, 1.0))


def test_manipulability_residual_is_the_spd_geodesic_distance():
    from torchlie.manifolds import spd_dist

    S = torch.tensor([[2.0, 0.3], [0.3, 0.7]], dtype=D)
    m = manipulability(planar_ee(LENGTHS, orientation=False), S)
    x = torch.randn(3, 4, 3, generator=torch.Generator().manual_seed(7), dtype=D)
    f, J = m(x)
    Jee = planar_ee(LENGTHS, orientation=False).J(x)
    torch.testing.assert_close(f.norm(dim=-1), spd_dist(S, Jee @ Jee.mT))
    torch.testing.assert_close(J, _fd_jacobian(m, x), rtol=1e-6, atol=1e-7)
    # zero exactly at the desired ellipse
    q = torch.tensor([0.3, 0.9, -0.4], dtype=D)
    Jq = planar_ee(LENGTHS, orientation=False).J(q)
    m2 = manipulability(planar_ee(LENGTHS, orientation=False), Jq @ Jq.mT)
    assert m2.f(q).abs().max() < 1e-12


def test_combinators_check_their_arguments():
    with pytest.raises(ValueError, match="distinct indices"):
        on_joints(state(2), [0, 0], 3)
    with pytest.raises(ValueError, match="one output size"):
        mean(state(2), state(3))
    with pytest.raises(ValueError, match="2 maps but 3 weights"):
        mean(state(2), state(2), weights=[1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="at least one map"):
        concat()


def test_distance_broadcasts_per_element_and_step():
    """A radius per problem and a target per time step are per element and step, not all pairs."""
    ee = planar_ee(LENGTHS, orientation=False)
    x = torch.randn(4, 6, 3, generator=torch.Generator().manual_seed(8), dtype=D)
    r = torch.tensor([0.5, 1.0, 2.0, 4.0], dtype=D)
    mu = torch.randn(6, 2, generator=torch.Generator().manual_seed(9), dtype=D)
    m = distance(ee, mu, r[:, None])
    f, J = m(x)
    assert f.shape == (4, 6, 1) and J.shape == (4, 6, 1, 3)
    want = 1 - ((ee.f(x) - mu) ** 2).sum(-1) / r[:, None] ** 2
    torch.testing.assert_close(f[..., 0], want)
    torch.testing.assert_close(J, _fd_jacobian(m, x), rtol=1e-6, atol=1e-7)


def test_mixed_precision_dtypes_and_an_empty_cut_are_named():
    with pytest.raises(TypeError, match=r"terms\[1\] Q is torch.float64"):
        residual_cost([(state(2), torch.eye(2)), (state(3), torch.eye(3, dtype=D))], torch.eye(3))
    with pytest.raises(ValueError, match="give 'lower', 'upper' or both"):
        cut(state(2))
