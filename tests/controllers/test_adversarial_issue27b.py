"""Adversarial regression tests (issue 27b) for the new MuJoCo code: mjd_transitionFD where control
clamping is disabled, zero-step rollouts and actuator-free models, and TangentILQR in float32 / with
foreign-dtype or malformed arguments."""

from __future__ import annotations

import copy
import importlib.util
import pathlib

import pytest
import torch

mujoco = pytest.importorskip("mujoco")
gym = pytest.importorskip("gymnasium")

from controllers.dynamics import rollout  # noqa: E402
from controllers.systems.mujoco_system import MujocoSystem  # noqa: E402

F64 = torch.float64
_EX = pathlib.Path(__file__).resolve().parents[2] / "examples" / "mujoco_free_body_mpc.py"


def _example():
    spec = importlib.util.spec_from_file_location("mujoco_free_body_mpc_adv27b", _EX)
    ex = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(ex)
    return ex


def _euler_pendulum(clamp: bool = True):
    m = copy.deepcopy(gym.make("InvertedPendulum-v5").unwrapped.model)  # ctrlrange [-3, 3], ctrllimited
    m.opt.integrator = mujoco.mjtIntegrator.mjINT_EULER
    if not clamp:
        m.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CLAMPCTRL)
    return m


def test_jacobian_where_control_clamping_is_disabled_is_the_derivative_of_step():
    """With mjDSBL_CLAMPCTRL a control beyond ctrlrange acts unclamped, but mjd_transitionFD still keeps its
    perturbations inside ctrlrange (a zero column).  'auto' used it: B was 0 for u = 5, -7."""
    m = _euler_pendulum(clamp=False)
    sys = MujocoSystem(m)
    x = torch.tensor([0.01, 0.1, 0.2, -0.3], dtype=F64).expand(3, 4)
    u = torch.tensor([[5.0], [-7.0], [0.5]], dtype=F64)
    assert not sys.uses_transition_fd()
    _, B = sys.jacobian(x, u)
    h = 1e-6
    ref = (sys.step(x, u + h) - sys.step(x, u - h)) / (2 * h)  # independent: differences of step
    assert ref.abs().min() > 1e-3  # the control acts beyond the range
    torch.testing.assert_close(B[..., 0], ref, rtol=1e-6, atol=1e-9)
    with pytest.raises(ValueError, match="clamping"):
        MujocoSystem(m, jacobian_method="transition_fd").jacobian(x, u)
    # with clamping on (the default) the fast path is still taken, and a control beyond the range has B = 0
    on = MujocoSystem(_euler_pendulum())
    assert on.uses_transition_fd()
    assert on.jacobian(x, u)[1][:2].abs().max() == 0


def test_zero_step_rollouts_broadcast_and_actuator_free_models_step():
    p = MujocoSystem(_euler_pendulum())
    x0 = torch.tensor([0.1, 0.0, 0.0, 0.0], dtype=F64)
    U0 = torch.zeros(3, 0, 1, dtype=F64)
    X = rollout(p, x0, U0)  # was (1, 4): u's batch dims dropped at T = 0
    assert X.shape == (3, 1, 4) and torch.equal(X[:, 0], x0.expand(3, 4))
    Xs = p.rollout_states(x0.expand(3, 4), U0)  # was a reshape RuntimeError
    assert Xs.shape == (3, 1, 4) and torch.equal(Xs[:, 0], x0.expand(3, 4))
    # a model without actuators (m = 0): step and rollout of a batch (was a reshape RuntimeError)
    free = MujocoSystem(mujoco.MjModel.from_xml_string(
        '<mujoco><worldbody><body><joint type="hinge" axis="0 1 0"/><geom size=".1" pos=".2 0 0"/></body>'
        '</worldbody></mujoco>'))
    xf = torch.tensor([[0.3, 0.0], [0.5, 0.1]], dtype=F64)
    y = free.step(xf, torch.zeros(2, 0, dtype=F64))
    Y = free.rollout_states(xf, torch.zeros(2, 3, 0, dtype=F64))
    assert y.shape == (2, 2) and Y.shape == (2, 4, 2)
    torch.testing.assert_close(Y[:, 1], y, rtol=0, atol=0)
    torch.testing.assert_close(free.step(xf[1], torch.zeros(0, dtype=F64)), y[1], rtol=0, atol=0)
    A, B = free.jacobian(xf, torch.zeros(2, 0, dtype=F64))
    assert A.shape == (2, 2, 2) and B.shape == (2, 2, 0) and A.isfinite().all()


@pytest.fixture(scope="module")
def body():
    ex = _example()
    s = ex.make_system()
    yield ex, s
    s.close()


def test_tangent_ilqr_in_float32_plans_as_in_float64(body):
    """float32's 0.1 (the torque limit) lies above float64's: a control on the limit was outside the model's
    ctrlrange, where MuJoCo clamps it and its Jacobian column is 0, and the float32 solve stalled after one
    step at a cost 0.4% above float64's (765.4 vs 762.6)."""
    ex, s = body
    mpc = ex.make_mpc(s, horizon=4, max_iter=6)
    x0, xr = ex.start_and_target()
    p64, p32 = mpc.solve(x0, xr), mpc.solve(x0.float(), xr)
    assert p32.u.dtype == p32.cost.dtype == torch.float32
    assert bool(p64.converged) and bool(p32.converged) and not bool(p32.stalled)
    assert abs(float(p32.cost) - float(p64.cost)) <= 1e-5 * float(p64.cost)
    u = p32.u.double()
    assert (u <= s.ctrl_upper).all() and (u >= s.ctrl_lower).all()  # inside the model's own range
    assert (u >= s.ctrl_upper - 1e-6).any()  # and some torque on its limit (the case that failed)


def test_tangent_ilqr_arguments_are_converted_or_refused_clearly(body):
    from controllers.mujoco_mpc import TangentILQR

    ex, s = body
    mpc = ex.make_mpc(s, horizon=3, max_iter=2)
    x0, xr = ex.start_and_target()
    ref = mpc.solve(x0.float(), xr)
    # u_init of another dtype follows x0 (was: TypeError from MujocoSystem.rollout_states)
    p = mpc.solve(x0.float(), xr, u_init=torch.zeros(3, 6, dtype=F64))
    assert p.u.dtype == torch.float32 and torch.equal(p.u, ref.u)
    with pytest.raises(ValueError, match="u_init"):
        mpc.solve(x0, xr, u_init=[[0.0] * 6] * 3)  # was AttributeError
    with pytest.raises(ValueError, match="u_lower"):
        TangentILQR(s, torch.ones(12), torch.ones(6), 3, u_lower=torch.zeros(5))  # was a RuntimeError
    with pytest.raises(ValueError, match="u_upper"):
        TangentILQR(s, torch.ones(12), torch.ones(6), 3, u_upper=float("nan"))
    # a scalar limit still broadcasts
    assert torch.equal(TangentILQR(s, torch.ones(12), torch.ones(6), 3, u_upper=2.0).u_upper,
                       torch.full((6,), 2.0, dtype=F64))
