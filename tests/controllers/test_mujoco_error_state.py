"""Error-state planning on a MujocoSystem with quaternions in qpos: ⊕/⊖ at the double cover and at π, tangent
Jacobians against differences of ⊖∘step∘⊕, TangentILQR reaching a target pose (batched == per-sample), and the
free-body example's outcome (manifold vs Euclidean residual)."""

from __future__ import annotations

import importlib.util
import math
import pathlib

import pytest
import torch

mujoco = pytest.importorskip("mujoco")

from controllers.mujoco_mpc import TangentILQR  # noqa: E402
from controllers.systems.mujoco_system import MujocoSystem  # noqa: E402

F64 = torch.float64
_EX = pathlib.Path(__file__).resolve().parents[2] / "examples" / "mujoco_free_body_mpc.py"
_spec = importlib.util.spec_from_file_location("mujoco_free_body_mpc", _EX)
ex = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(ex)


def _quat(angle: float, axis) -> torch.Tensor:
    a = torch.tensor(axis, dtype=F64)
    return torch.cat([torch.tensor([math.cos(angle / 2)], dtype=F64), math.sin(angle / 2) * a / a.norm()])


def _point(pos, q, vel=None) -> torch.Tensor:
    return torch.cat([torch.tensor(pos, dtype=F64), q, torch.zeros(6, dtype=F64) if vel is None else vel])


@pytest.fixture(scope="module")
def body():
    s = ex.make_system()
    yield s
    s.close()


def _same_pose(a: torch.Tensor, b: torch.Tensor, atol: float) -> bool:
    """Points equal with the quaternion up to its sign."""
    sign = torch.sign((a[..., 3:7] * b[..., 3:7]).sum(-1, keepdim=True))
    return (torch.allclose(a[..., :3], b[..., :3], atol=atol)
            and torch.allclose(a[..., 7:], b[..., 7:], atol=atol)
            and torch.allclose(a[..., 3:7] * sign, b[..., 3:7], atol=atol))


def test_oplus_ominus_at_the_double_cover_and_at_pi(body):
    y = _point([0.1, 0.2, 0.3], _quat(0.7, [0.3, -1.0, 0.2]))
    # the double cover: -q is the same attitude, the error is zero
    x = y.clone()
    x[3:7] = -x[3:7]
    assert body.ominus(x, y).abs().max() <= 1e-15
    # exactly π about a tilted axis, and just below/above it: |x ⊖ y| = angle ≤ π, y ⊕ (x ⊖ y) = x
    axis = torch.tensor([0.0, 0.6, 0.8], dtype=F64)
    for ang in (math.pi - 1e-6, math.pi, math.pi + 1e-6, 2 * math.pi - 0.3):
        rel = _quat(ang, axis.tolist())  # x = y ⊗ rel, angle wrapped to the principal one by ⊖
        x = y.clone()
        x[3:7] = torch.stack([y[3] * rel[0] - (y[4:7] * rel[1:]).sum(),
                              *(y[3] * rel[1:] + rel[0] * y[4:7] + torch.linalg.cross(y[4:7], rel[1:]))])
        d = body.ominus(x, y)
        principal = ang if ang <= math.pi else 2 * math.pi - ang
        assert abs(float(d[3:6].norm()) - principal) <= 1e-9
        assert abs(abs(float(d[3:6] @ axis)) - principal) <= 1e-9  # along ±axis
        assert _same_pose(body.oplus(y, d), x, 1e-12)
        # MuJoCo's mj_differentiatePos gives the same tangent (at π: the same up to the sign)
        v = torch.zeros(6, dtype=F64).numpy()
        mujoco.mj_differentiatePos(body.model, v, 1.0, y[:7].numpy().copy(), x[:7].numpy().copy())
        v = torch.from_numpy(v)
        assert torch.allclose(d[:6], v, atol=1e-9) or (ang == math.pi and torch.allclose(d[3:6], -v[3:6]))


@pytest.mark.parametrize("method", ["rollout", "transition_fd"])
def test_tangent_jacobians_match_differences_of_ominus_step_oplus(method):
    system = MujocoSystem(ex.make_system().model, frame_skip=5, jacobian_method=method)
    g = torch.Generator().manual_seed(0)
    x = _point([0.3, -0.2, 0.8], _quat(2.6, [1.0, 1.0, 0.5]), torch.randn(6, generator=g, dtype=F64))
    u = torch.tensor([1.0, -2.0, 9.0, 0.05, -0.03, 0.02], dtype=F64)
    A, B = system.jacobian(x, u)
    h = 1e-5
    E = torch.eye(system.n, dtype=F64) * h
    y = system.step(x, u)
    Ad = (system.ominus(system.step(system.oplus(x, E), u), y)
          - system.ominus(system.step(system.oplus(x, -E), u), y)).mT / (2 * h)
    Eu = torch.eye(system.m, dtype=F64) * h
    Bd = (system.ominus(system.step(x, u + Eu), y) - system.ominus(system.step(x, u - Eu), y)).mT / (2 * h)
    assert (A - Ad).abs().max() <= 1e-6 * Ad.abs().max()
    assert (B - Bd).abs().max() <= 1e-6 * Bd.abs().max()
    # the attitude block is not the identity at this large rotation rate: tangent coordinates matter
    assert (A[3:6, 3:6] - torch.eye(3, dtype=F64)).abs().max() > 1e-3
    system.close()


def _starts() -> torch.Tensor:
    return torch.stack([_point([0.3, -0.2, 0.8], _quat(math.radians(150), [1.0, 1.0, 0.5])),
                        _point([-0.2, 0.1, 1.1], _quat(math.radians(120), [0.0, 1.0, -0.3])),
                        _point([0.0, 0.0, 1.0], _quat(math.radians(179), [0.2, 0.1, 1.0]))])


def test_planner_reaches_target_pose_and_batched_equals_per_sample(body):
    q = torch.tensor([10.0] * 6 + [1.0] * 6, dtype=F64)
    mpc = TangentILQR(body, q, torch.tensor([1e-3] * 3 + [1.0] * 3, dtype=F64), 30, Q_terminal=100 * q,
                      max_iter=25)
    x0 = _starts()
    xr = _point([0.0, 0.0, 1.0], torch.tensor([-1.0, 0.0, 0.0, 0.0], dtype=F64))  # -q of the identity
    hover = torch.tensor([0.0, 0.0, 9.81, 0.0, 0.0, 0.0], dtype=F64)
    plan = mpc.solve(x0, xr, hover)
    assert plan.u.shape == (3, 30, 6) and plan.x.shape == (3, 31, 13)
    assert plan.converged.all() and not plan.stalled.any()
    err = body.ominus(plan.x[:, -1], xr)  # 120° .. 179° at the start, 1.5 s of horizon
    assert err[:, :3].norm(dim=-1).max() < 1e-3 and err[:, 3:6].norm(dim=-1).max() < math.radians(1.0)
    assert err[:, 6:].norm(dim=-1).max() < 5e-3
    assert ((plan.x[..., 3:7].norm(dim=-1) - 1).abs() <= 1e-12).all()  # unit quaternions all along
    assert (plan.u >= mpc.u_lower).all() and (plan.u <= mpc.u_upper).all()
    assert torch.allclose(body.rollout_states(x0, plan.u), plan.x)  # the plan is its own rollout
    u_hover = hover.expand(3, 30, 6)
    assert (plan.cost < mpc.cost(body.rollout_states(x0, u_hover), u_hover, xr, hover)).all()
    # batched == per-sample: the same iterations and cost; the controls to the solver's tolerance (the cost
    # is flat along some directions: round-off of the batched products, 1e-10 after one iteration, moves
    # the converged controls by up to ~2e-6 with cost changes of 1e-10, measured)
    for i in range(3):
        one = mpc.solve(x0[i], xr, hover)
        assert torch.allclose(one.cost, plan.cost[i], rtol=1e-9, atol=0)
        assert (one.u - plan.u[i]).abs().max() <= 1e-4
        assert int(one.iterations) == int(plan.iterations[i])
        assert bool(one.converged) == bool(plan.converged[i])


def test_planner_bad_input(body):
    q = torch.ones(12, dtype=F64)
    with pytest.raises(ValueError, match="'Q'"):
        TangentILQR(body, torch.ones(13, dtype=F64), torch.ones(6, dtype=F64), 5)  # 13 = nx, not n
    with pytest.raises(ValueError, match="'R'"):
        TangentILQR(body, q, torch.zeros(6, dtype=F64), 5)
    with pytest.raises(ValueError, match="'residual'"):
        TangentILQR(body, q, torch.ones(6, dtype=F64), 5, residual="flat")
    with pytest.raises(ValueError, match="'horizon'"):
        TangentILQR(body, q, torch.ones(6, dtype=F64), 0)
    with pytest.raises(TypeError, match="'system'"):
        TangentILQR(object(), q, torch.ones(6, dtype=F64), 5)
    mpc = TangentILQR(body, q, torch.ones(6, dtype=F64), 5)
    with pytest.raises(ValueError, match="'x0'"):
        mpc.solve(torch.zeros(12, dtype=F64), torch.zeros(13, dtype=F64))
    with pytest.raises(ValueError, match="'u_init'"):
        mpc.solve(_starts()[0], _starts()[1], u_init=torch.zeros(4, 6, dtype=F64))


def test_free_body_example_outcome():
    """Receding horizon from 150° to the upright pose given as -q: the manifold residual turns the short way
    (150°) and settles; the Euclidean one (quaternion numbers as a vector) heads for +q's antipode, turning
    the long way (> 180°) and is still off after the same time."""
    out = ex.main(steps=50)
    man, euc = out["manifold"], out["euclidean"]
    assert man["position_error"] < 1e-3 and man["attitude_error_rad"] < math.radians(0.5)
    assert man["velocity_error"] < 2e-2 and man["max_quaternion_norm_deviation"] < 1e-12
    assert abs(math.degrees(man["rotation_travelled_rad"]) - 150) < 5
    assert math.degrees(euc["rotation_travelled_rad"]) > 180
    assert euc["attitude_error_rad"] > 10 * man["attitude_error_rad"]


def test_planner_trajectory_reference_and_a_bad_element(body):
    q = torch.tensor([10.0] * 6 + [1.0] * 6, dtype=F64)
    mpc = TangentILQR(body, q, torch.tensor([1e-3] * 3 + [1.0] * 3, dtype=F64), 6, max_iter=3)
    x0 = _starts()
    x0[1, 2] = float("nan")
    xr = _point([0.0, 0.0, 1.0], torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=F64))
    hover = torch.tensor([0.0, 0.0, 9.81, 0.0, 0.0, 0.0], dtype=F64)
    goal = mpc.solve(x0, xr, hover)
    traj = mpc.solve(x0, xr.expand(7, 13), hover, trajectory=True)  # the goal as a constant trajectory
    ok = torch.tensor([True, False, True])
    assert torch.equal(goal.u[ok], traj.u[ok]) and torch.equal(goal.cost[ok], traj.cost[ok])
    assert goal.stalled[1] and not goal.converged[1] and goal.cost[1].isnan()
    assert goal.cost[ok].isfinite().all() and (goal.iterations[ok] > 0).all()
    with pytest.raises(ValueError, match="trajectory=True"):
        mpc.solve(x0, xr, hover, trajectory=True)
