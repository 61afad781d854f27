"""MujocoSystem: env equivalence, FD Jacobians vs mjd_transitionFD, manifold ⊕/⊖, autograd, bad input."""

from __future__ import annotations

import copy

import pytest
import torch

mujoco = pytest.importorskip("mujoco")
gym = pytest.importorskip("gymnasium")
np = pytest.importorskip("numpy")

from controllers.systems.mujoco_system import MujocoSystem  # noqa: E402

F64 = torch.float64

# a free-floating box resting on (slightly into) a plane, a ball-joint pendulum and an actuated hinge
XML = """<mujoco model="box_and_ball">
  <option timestep="0.005" integrator="Euler"/>
  <worldbody>
    <geom type="plane" size="2 2 .1"/>
    <body name="box" pos="0 0 .029"><freejoint/><geom type="box" size=".05 .04 .03" mass="1"/></body>
    <body name="pend" pos="1 0 1"><joint type="ball" damping="0.1"/>
      <geom type="capsule" fromto="0 0 0 .1 .05 -.3" size=".02"/></body>
    <body name="arm" pos="-1 0 1"><joint name="h" type="hinge" axis="0 1 0"/>
      <geom type="capsule" fromto="0 0 0 .3 0 0" size=".02"/></body>
  </worldbody>
  <actuator><motor joint="h" ctrlrange="-1 1" ctrllimited="true"/></actuator>
</mujoco>"""


def _state(m, d) -> torch.Tensor:
    return torch.from_numpy(np.concatenate([d.qpos, d.qvel, d.act]).copy())


def _transition_fd(m, x: torch.Tensor, u: torch.Tensor, eps: float = 1e-6):
    """Reference A, B from mujoco.mjd_transitionFD, one element at a time."""
    d = mujoco.MjData(m)
    As, Bs = [], []
    for xi, ui in zip(x.reshape(-1, x.shape[-1]), u.reshape(-1, u.shape[-1])):
        mujoco.mj_resetData(m, d)
        d.qpos[:], d.qvel[:] = xi[:m.nq].numpy(), xi[m.nq:m.nq + m.nv].numpy()
        d.act[:], d.ctrl[:] = xi[m.nq + m.nv:].numpy(), ui.numpy()
        n = 2 * m.nv + m.na
        A, B = np.zeros((n, n)), np.zeros((n, m.nu))
        mujoco.mjd_transitionFD(m, d, eps, True, A, B, None, None)
        As.append(torch.from_numpy(A))
        Bs.append(torch.from_numpy(B))
    return torch.stack(As), torch.stack(Bs)


def _box_ball(settle: int = 20, seed: int = 0):
    """The inline model, a state with the box in contact and a random ball orientation, and controls."""
    m = mujoco.MjModel.from_xml_string(XML)
    d = mujoco.MjData(m)
    rng = np.random.default_rng(seed)
    d.qvel[:] = rng.normal(size=m.nv) * 0.3
    for _ in range(settle):
        mujoco.mj_step(m, d)
    q = rng.normal(size=4)
    d.qpos[7:11] = q / np.linalg.norm(q)
    mujoco.mj_forward(m, d)
    assert d.ncon > 0  # the box touches the plane: contacts are part of the test
    return m, _state(m, d)


@pytest.fixture(scope="module")
def pendulum():
    return MujocoSystem.from_env(gym.make("InvertedPendulum-v5"))


# ------------------------------------------------------------------------------------------------------
# step == env.step
# ------------------------------------------------------------------------------------------------------


ENVS = ["InvertedPendulum-v5", "InvertedDoublePendulum-v5", "Reacher-v5", "Hopper-v5"]


@pytest.mark.parametrize("name", ENVS)
def test_step_matches_gymnasium_env(name):
    env = gym.make(name)
    env.reset(seed=3)
    env.action_space.seed(3)
    inner = env.unwrapped
    sys = MujocoSystem.from_env(env)
    assert sys.frame_skip == inner.frame_skip and sys.dt == pytest.approx(inner.dt)
    xs, us, refs = [], [], []
    for _ in range(20):
        xs.append(_state(inner.model, inner.data))
        a = env.action_space.sample()
        env.step(a)
        us.append(torch.as_tensor(a, dtype=F64))
        refs.append(torch.from_numpy(np.concatenate([inner.data.qpos, inner.data.qvel]).copy()))
    # one batched call for all 20 transitions (each from the env's previous state)
    y = sys.step(torch.stack(xs), torch.stack(us))
    ref = torch.stack(refs)
    scale = 1 + ref.abs().amax()
    assert (y[:, :sys.nq + sys.nv] - ref).abs().max() <= 1e-12 * scale
    env.close()


def test_batched_equals_loop_and_dtypes(pendulum):
    g = torch.Generator().manual_seed(0)
    x = torch.randn(2, 3, 4, generator=g, dtype=F64) * 0.2
    u = torch.randn(3, 1, generator=g, dtype=F64)  # broadcasts against x's batch
    y = pendulum.step(x, u)
    assert y.shape == (2, 3, 4) and y.dtype == F64
    loop = torch.stack([torch.stack([pendulum.step(x[i, j], u[j]) for j in range(3)]) for i in range(2)])
    assert torch.equal(y, loop)
    y32 = pendulum.step(x.float(), u.float())
    assert y32.dtype == torch.float32
    assert torch.allclose(y32.double(), pendulum.step(x.float().double(), u.float().double()), atol=1e-6)
    A32, B32 = pendulum.jacobian(x.float(), u.float())
    assert A32.dtype == torch.float32 and A32.shape == (2, 3, 4, 4) and B32.shape == (2, 3, 4, 1)
    assert pendulum.step(torch.zeros(0, 4, dtype=F64), torch.zeros(0, 1, dtype=F64)).shape == (0, 4)


def test_threads_give_the_same_numbers():
    env = gym.make("Reacher-v5")
    s0, s2 = MujocoSystem.from_env(env), MujocoSystem.from_env(env, nthread=2)
    g = torch.Generator().manual_seed(1)
    x = torch.randn(16, s0.nx, generator=g, dtype=F64) * 0.1
    u = torch.randn(16, 6, s0.m, generator=g, dtype=F64)
    assert torch.equal(s0.rollout_states(x, u), s2.rollout_states(x, u))
    assert all(torch.equal(a, b) for a, b in zip(s0.jacobian(x, u[:, 0]), s2.jacobian(x, u[:, 0])))
    s2.close()
    with pytest.raises(RuntimeError, match="closed"):
        s2.step(x, u[:, 0])


# ------------------------------------------------------------------------------------------------------
# Jacobians
# ------------------------------------------------------------------------------------------------------


def test_fd_jacobian_matches_mjd_transitionFD_on_euler_copy():
    env = gym.make("InvertedDoublePendulum-v5")
    m = copy.deepcopy(env.unwrapped.model)
    m.opt.integrator = mujoco.mjtIntegrator.mjINT_EULER
    sys = MujocoSystem(m, frame_skip=1)
    g = torch.Generator().manual_seed(2)
    x = torch.randn(5, sys.nx, generator=g, dtype=F64) * 0.3
    u = (torch.rand(5, sys.m, generator=g, dtype=F64) - 0.5)  # inside ctrlrange [-1, 1]
    A, B = sys.jacobian(x, u)
    Ar, Br = _transition_fd(m, x, u)
    assert (A - Ar).abs().max() <= 1e-6 * Ar.abs().max()
    assert (B - Br).abs().max() <= 1e-6 * Br.abs().max()


def test_fd_jacobian_rk4_against_rollout_differences(pendulum):
    """RK4 model (mjd_transitionFD refuses it): A, B against central differences of ``step`` itself at a
    different step size (1e-4: truncation error ~1e-8)."""
    g = torch.Generator().manual_seed(3)
    x = torch.randn(3, 4, generator=g, dtype=F64) * 0.2
    u = torch.randn(3, 1, generator=g, dtype=F64)
    A, B = pendulum.jacobian(x, u)
    h = 1e-4
    eye = torch.eye(4, dtype=F64)
    cols = [(pendulum.step(x + h * e, u) - pendulum.step(x - h * e, u)) / (2 * h) for e in eye]
    A_ref = torch.stack(cols, -1)
    B_ref = ((pendulum.step(x, u + h) - pendulum.step(x, u - h)) / (2 * h)).unsqueeze(-1)
    assert (A - A_ref).abs().max() <= 1e-6 * A_ref.abs().max()
    assert (B - B_ref).abs().max() <= 1e-6 * B_ref.abs().max()
    # and the linearization predicts a small step to second order
    dx = 1e-5 * torch.randn(3, 4, generator=g, dtype=F64)
    du = 1e-5 * torch.randn(3, 1, generator=g, dtype=F64)
    pred = (A @ dx.unsqueeze(-1) + B @ du.unsqueeze(-1)).squeeze(-1)
    true = pendulum.step(x + dx, u + du) - pendulum.step(x, u)
    assert (pred - true).abs().max() <= 1e-4 * true.abs().max()


def test_trajectory_jacobians_equal_per_step_jacobians(pendulum):
    g = torch.Generator().manual_seed(4)
    x0 = torch.randn(2, 4, generator=g, dtype=F64) * 0.1
    u = torch.randn(2, 5, 1, generator=g, dtype=F64)
    xs = pendulum.rollout_states(x0, u)
    A, B = pendulum.trajectory_jacobians(xs, u)
    assert A.shape == (2, 5, 4, 4) and B.shape == (2, 5, 4, 1)
    for t in range(5):
        At, Bt = pendulum.jacobian(xs[:, t], u[:, t])
        assert torch.equal(A[:, t], At) and torch.equal(B[:, t], Bt)


def test_control_on_its_limit_uses_a_one_sided_difference(pendulum):
    x = torch.tensor([0.0, 0.1, 0.0, 0.0], dtype=F64)
    hi = float(pendulum.ctrl_upper[0])
    _, B_in = pendulum.jacobian(x, torch.tensor([hi - 1e-3], dtype=F64))
    _, B_at = pendulum.jacobian(x, torch.tensor([hi], dtype=F64))
    _, B_out = pendulum.jacobian(x, torch.tensor([hi + 1.0], dtype=F64))
    assert (B_at - B_in).abs().max() <= 1e-3 * B_in.abs().max()  # the derivative inside, not half of it
    assert B_out.abs().max() == 0  # beyond the limit MuJoCo clamps: no effect


# ------------------------------------------------------------------------------------------------------
# manifold models (quaternions in qpos)
# ------------------------------------------------------------------------------------------------------


def test_oplus_ominus_match_mujoco_and_round_trip():
    m, x = _box_ball()
    sys = MujocoSystem(m)
    assert (sys.nx, sys.n, sys.euclidean) == (m.nq + m.nv, 2 * m.nv, False)
    g = torch.Generator().manual_seed(5)
    dx = torch.randn(6, sys.n, generator=g, dtype=F64)
    xp = sys.oplus(x, dx)  # broadcast: one point, six tangents
    for i in range(6):
        q = x[:m.nq].numpy().copy()
        mujoco.mj_integratePos(m, q, dx[i, :m.nv].numpy().copy(), 1.0)
        assert np.abs(xp[i, :m.nq].numpy() - q).max() <= 1e-14
        v = np.zeros(m.nv)
        mujoco.mj_differentiatePos(m, v, 1.0, x[:m.nq].numpy().copy(), xp[i, :m.nq].numpy().copy())
        assert np.abs(sys.ominus(xp[i], x)[:m.nv].numpy() - v).max() <= 1e-13
    assert torch.allclose(xp[:, m.nq:], x[m.nq:] + dx[:, m.nv:])
    # ⊖ inverts ⊕ for rotations below π (|ω| of each quaternion block here is below 3) ...
    small = dx * 0.5
    assert torch.allclose(sys.ominus(sys.oplus(x, small), x), small, atol=1e-12)
    # ... and ⊕ inverts ⊖ up to the sign of each quaternion
    y = sys.oplus(x, dx)
    back = sys.oplus(x, sys.ominus(y, x))
    sign = torch.sign((back[:, 3:7] * y[:, 3:7]).sum(-1, keepdim=True))
    assert torch.allclose(back[:, 3:7] * sign, y[:, 3:7], atol=1e-12)
    assert torch.allclose(back[:, :3], y[:, :3]) and torch.allclose(back[:, 11:], y[:, 11:], atol=1e-12)


def test_tangent_fd_jacobian_matches_mjd_transitionFD_with_contacts():
    m, x = _box_ball()
    sys = MujocoSystem(m)
    u = torch.tensor([0.4], dtype=F64)
    A, B = sys.jacobian(x, u)
    Ar, Br = _transition_fd(m, x[None], u[None])
    assert A.shape == (sys.n, sys.n) and B.shape == (sys.n, 1)
    assert (A - Ar[0]).abs().max() <= 1e-6 * Ar.abs().max()
    assert (B - Br[0]).abs().max() <= 1e-6 * Br.abs().max()


def test_manifold_step_gradient_matches_finite_differences():
    """gradcheck in point coordinates: the backward maps the tangent Jacobians through ∂(y ⊕ δ)/∂δ and
    ∂(z ⊖ x)/∂z (a radial change of a quaternion has no effect, on MuJoCo's step as on ⊖)."""
    m, x = _box_ball()
    sys = MujocoSystem(m)
    xx = x.clone().requires_grad_(True)
    uu = torch.tensor([0.2], dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, b: sys.step(a, b), (xx, uu), eps=1e-6, atol=1e-5, rtol=1e-4)


# ------------------------------------------------------------------------------------------------------
# differentiability
# ------------------------------------------------------------------------------------------------------


def test_step_gradcheck(pendulum):
    g = torch.Generator().manual_seed(6)
    x = (torch.randn(2, 4, generator=g, dtype=F64) * 0.2).requires_grad_(True)
    u = torch.randn(2, 1, generator=g, dtype=F64).requires_grad_(True)
    # FD Jacobians (h = 1e-6) against gradcheck's own differences: agree to ~derivative_accuracy · scale
    assert torch.autograd.gradcheck(lambda a, b: pendulum.step(a, b), (x, u), eps=1e-6, atol=1e-6, rtol=1e-5)


def test_rollout_states_value_and_adjoint_gradient(pendulum):
    g = torch.Generator().manual_seed(7)
    x0 = torch.randn(3, 4, generator=g, dtype=F64) * 0.1
    u = torch.randn(3, 6, 1, generator=g, dtype=F64)
    xs = pendulum.rollout_states(x0, u)
    x, loop = x0, [x0]
    for t in range(6):
        x = pendulum.step(x, u[:, t])
        loop.append(x)
    assert torch.equal(xs, torch.stack(loop, 1))
    # the adjoint backward (one trajectory_jacobians call) == autograd through six chained steps
    w = torch.randn(3, 7, 4, generator=g, dtype=F64)
    a0, au = x0.clone().requires_grad_(True), u.clone().requires_grad_(True)
    ga = torch.autograd.grad((pendulum.rollout_states(a0, au) * w).sum(), (a0, au))
    b0, bu = x0.clone().requires_grad_(True), u.clone().requires_grad_(True)
    x, chain = b0, [b0]
    for t in range(6):
        x = pendulum.step(x, bu[:, t])
        chain.append(x)
    gb = torch.autograd.grad((torch.stack(chain, 1) * w).sum(), (b0, bu))
    assert all(torch.allclose(p, q, rtol=1e-10, atol=1e-12) for p, q in zip(ga, gb))
    small = (x0[:1].clone().requires_grad_(True), u[:1, :3].clone().requires_grad_(True))
    assert torch.autograd.gradcheck(lambda a, b: pendulum.rollout_states(a, b), small, eps=1e-6, atol=1e-5,
                                    rtol=1e-4)


def test_ilqr_solves_on_fd_jacobians_and_gives_x0_gradients(pendulum):
    from controllers.costs import QuadraticCost
    from controllers.ilqr import ILQRProblem, ilqr

    kw = dict(dtype=F64)
    cost = QuadraticCost(Q=torch.diag(torch.tensor([1.0, 10.0, 0.1, 0.1], **kw)), R=0.1 * torch.eye(1, **kw))
    x0 = torch.tensor([[0.1, 0.15, 0.0, 0.0], [-0.1, -0.1, 0.2, 0.0]], **kw, requires_grad=True)
    opts = pendulum.ilqr_options(max_iter=30)
    assert opts.tol_kkt >= 1e3 * pendulum.derivative_accuracy
    sol = ilqr(ILQRProblem(pendulum, cost, x0, 10, u_lower=-3.0, u_upper=3.0), options=opts)
    assert bool(sol.status.converged.all())
    # the states are the MuJoCo rollout of the returned controls
    assert torch.allclose(sol.x.detach(), pendulum.rollout_states(x0.detach(), sol.u.detach()), atol=1e-12)
    # implicit gradient of the optimal cost w.r.t. x0 == finite differences of re-solves
    (gx,) = torch.autograd.grad(sol.cost.sum(), x0)
    h = 1e-5
    for i in range(4):
        e = torch.zeros(2, 4, **kw)
        e[:, i] = h
        cp = ilqr(ILQRProblem(pendulum, cost, x0.detach() + e, 10, -3.0, 3.0), grad="none", options=opts).cost
        cm = ilqr(ILQRProblem(pendulum, cost, x0.detach() - e, 10, -3.0, 3.0), grad="none", options=opts).cost
        assert torch.allclose(gx[:, i], (cp - cm) / (2 * h), rtol=1e-4, atol=1e-6)


# ------------------------------------------------------------------------------------------------------
# bad input
# ------------------------------------------------------------------------------------------------------


def test_nonfinite_or_diverging_element_does_not_poison_the_others(pendulum, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # MuJoCo logs the diverging element's warning to ./MUJOCO_LOG.TXT
    g = torch.Generator().manual_seed(8)
    x = torch.randn(4, 4, generator=g, dtype=F64) * 0.1
    u = torch.randn(4, 1, generator=g, dtype=F64)
    clean_y, (clean_A, clean_B) = pendulum.step(x, u), pendulum.jacobian(x, u)
    huge = x.clone()
    huge[0, 0] = 1e20  # above MuJoCo's 1e10: masked before the call (MuJoCo never sees it, nothing logged)
    assert torch.isnan(pendulum.step(huge, u)[0]).all() and not (tmp_path / "MUJOCO_LOG.TXT").exists()
    xb, ub = x.clone(), u.clone()
    xb[1, 2] = float("nan")
    ub[2, 0] = float("inf")
    xb[3, 3] = 5e9  # finite, but the simulation diverges (MuJoCo resets it: detected from its clock)
    y = pendulum.step(xb, ub)
    assert (tmp_path / "MUJOCO_LOG.TXT").exists()  # the divergence did happen inside MuJoCo
    A, B = pendulum.jacobian(xb, ub)
    assert torch.isnan(y[1:]).all() and torch.isnan(A[1:]).all() and torch.isnan(B[1:]).all()
    assert torch.equal(y[0], clean_y[0]) and torch.equal(A[0], clean_A[0]) and torch.equal(B[0], clean_B[0])
    us = torch.randn(4, 3, 1, generator=g, dtype=F64)
    us[2, 1, 0] = float("nan")
    xs = pendulum.rollout_states(x, us)
    assert torch.isnan(xs[2, 1:]).all() and torch.isfinite(xs[[0, 1, 3]]).all()
    assert torch.equal(xs[0], pendulum.rollout_states(x[:1], us[:1])[0])


def test_bad_input_raises_clear_errors(pendulum):
    x, u = torch.zeros(2, 4, dtype=F64), torch.zeros(2, 1, dtype=F64)
    with pytest.raises(ValueError, match=r"'x'.*\(\*B, 4\).*inverted pendulum"):
        pendulum.step(torch.zeros(2, 5, dtype=F64), u)
    with pytest.raises(ValueError, match=r"'u'.*\(\*B, 1\)"):
        pendulum.step(x, torch.zeros(2, 2, dtype=F64))
    with pytest.raises(TypeError, match="dtype"):
        pendulum.step(x, u.float())
    with pytest.raises(ValueError, match=r"'x'.*match u"):
        pendulum.trajectory_jacobians(torch.zeros(2, 7, 4, dtype=F64), torch.zeros(2, 5, 1, dtype=F64))
    env = gym.make("InvertedPendulum-v5")
    with pytest.raises(ValueError, match="frame_skip=3.*frame_skip=2"):
        MujocoSystem(env, frame_skip=3)
    with pytest.raises(ValueError, match="frame_skip"):
        MujocoSystem(env.unwrapped.model, frame_skip=0)
    with pytest.raises(TypeError, match="MjModel"):
        MujocoSystem(3.0)
    with pytest.raises(TypeError, match="not MuJoCo-based"):
        MujocoSystem.from_env(gym.make("CartPole-v1"))
    with pytest.raises(ValueError, match="fd_eps"):
        MujocoSystem(env.unwrapped.model, fd_eps=0.0)


# ------------------------------------------------------------------------------------------------------
# the mjd_transitionFD fast path (jacobian_method)
# ------------------------------------------------------------------------------------------------------


def _euler_copy(name: str):
    m = copy.deepcopy(gym.make(name).unwrapped.model)
    m.opt.integrator = mujoco.mjtIntegrator.mjINT_EULER
    return m


@pytest.mark.parametrize("frame_skip", [1, 3])
def test_transition_fd_path_equals_rollout_path(frame_skip):
    """Chained per-substep mjd_transitionFD == differences of whole frame_skip rollouts, to FD accuracy,
    on a hinge model and on the free/ball model (tangent coordinates, contacts), controls on a limit too."""
    m = _euler_copy("InvertedDoublePendulum-v5")
    g = torch.Generator().manual_seed(3)
    x = torch.randn(6, m.nq + m.nv, generator=g, dtype=F64) * 0.2
    u = torch.rand(6, m.nu, generator=g, dtype=F64) - 0.5
    u[0], u[1] = 1.0, -1.0  # on the ctrlrange limits: one-sided differences inside the range, both paths
    mb, xb = _box_ball()
    ub = torch.tensor([[0.3], [-1.0]], dtype=F64)
    for model, xs, us in ((m, x, u), (mb, xb.expand(2, -1), ub)):
        fast = MujocoSystem(model, frame_skip=frame_skip, jacobian_method="transition_fd")
        slow = MujocoSystem(model, frame_skip=frame_skip, jacobian_method="rollout")
        assert fast.uses_transition_fd() and not slow.uses_transition_fd()
        (A1, B1), (A2, B2) = fast.jacobian(xs, us), slow.jacobian(xs, us)
        assert A1.shape == A2.shape == (xs.shape[0], fast.n, fast.n)
        assert (A1 - A2).abs().max() <= 1e-7 * A2.abs().max()
        assert (B1 - B2).abs().max() <= 1e-7 * B2.abs().max()
        # trajectory_jacobians and the autograd backward go through the same dispatch
        T1 = fast.trajectory_jacobians(xs[:, None, :], us[:, None, :])
        assert torch.equal(T1[0][:, 0], A1) and torch.equal(T1[1][:, 0], B1)


def test_transition_fd_path_dtype_batch_and_bad_elements():
    m = _euler_copy("InvertedPendulum-v5")
    sys = MujocoSystem(m, jacobian_method="transition_fd", frame_skip=2)
    g = torch.Generator().manual_seed(4)
    x = torch.randn(2, 3, sys.nx, generator=g, dtype=F64) * 0.1
    u = torch.rand(2, 3, 1, generator=g, dtype=F64) - 0.5
    x[0, 1, 2] = float("nan")
    A, B = sys.jacobian(x, u)
    assert A.shape == (2, 3, 4, 4) and B.shape == (2, 3, 4, 1)
    bad = torch.zeros(2, 3, dtype=torch.bool)
    bad[0, 1] = True
    assert A[bad].isnan().all() and A[~bad].isfinite().all() and B[~bad].isfinite().all()
    Al, Bl = sys.jacobian(x[1, 2], u[1, 2])
    assert torch.equal(Al, A[1, 2]) and torch.equal(Bl, B[1, 2])  # batched == one element
    A32, _ = sys.jacobian(x[1].float(), u[1].float())
    assert A32.dtype == torch.float32 and torch.allclose(A32.double(), A[1], rtol=1e-5, atol=1e-6)


def test_jacobian_method_choice_and_errors(pendulum):
    m = _euler_copy("InvertedPendulum-v5")
    assert MujocoSystem(m).uses_transition_fd()  # auto, Euler, frame_skip 1
    assert MujocoSystem(m, frame_skip=2).uses_transition_fd()
    assert not MujocoSystem(m, nthread=2).uses_transition_fd()  # the rollouts run on the pool
    assert not pendulum.uses_transition_fd()  # RK4
    with pytest.raises(ValueError, match="jacobian_method"):
        MujocoSystem(m, jacobian_method="analytic")
    with pytest.raises(ValueError, match="RK4"):
        MujocoSystem(pendulum.model, frame_skip=2, jacobian_method="transition_fd")
    fast = MujocoSystem(m, jacobian_method="transition_fd")
    m.opt.integrator = mujoco.mjtIntegrator.mjINT_RK4  # changed after construction: refused at the call
    with pytest.raises(ValueError, match="RK4"):
        fast.jacobian(torch.zeros(fast.nx, dtype=F64), torch.zeros(1, dtype=F64))


@pytest.mark.parametrize("frame_skip", [1, 2])
def test_transition_fd_path_marks_a_diverging_element(frame_skip, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # MuJoCo logs the diverging element's warning to ./MUJOCO_LOG.TXT
    sys = MujocoSystem(_euler_copy("InvertedPendulum-v5"), frame_skip=frame_skip,
                       jacobian_method="transition_fd")
    g = torch.Generator().manual_seed(9)
    x = torch.randn(3, 4, generator=g, dtype=F64) * 0.1
    u = torch.rand(3, 1, generator=g, dtype=F64) - 0.5
    clean_A, clean_B = sys.jacobian(x, u)
    xb = x.clone()
    xb[1, 3] = 5e9  # finite, but MuJoCo diverges and resets it inside the call
    A, B = sys.jacobian(xb, u)
    assert (tmp_path / "MUJOCO_LOG.TXT").exists()
    assert A[1].isnan().all() and B[1].isnan().all()
    assert torch.equal(A[[0, 2]], clean_A[[0, 2]]) and torch.equal(B[[0, 2]], clean_B[[0, 2]])


# ------------------------------------------------------------------------------------------------------
# forward differences, and open-loop rollouts in one call
# ------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("method", ["rollout", "transition_fd"])
def test_forward_differences_agree_with_central_to_their_accuracy(method):
    """``fd_scheme='forward'``: ``n + m + 1`` perturbed steps; the Jacobians equal the central ones to the
    forward scheme's accuracy (~3e-8), on a hinge model (RK4 for the rollout path, an Euler copy for
    mjd_transitionFD) and on the free/ball model with contacts (tangent coordinates), a control on each limit
    (one-sided inward)."""
    m = _euler_copy("InvertedDoublePendulum-v5") if method == "transition_fd" else \
        gym.make("InvertedDoublePendulum-v5").unwrapped.model
    g = torch.Generator().manual_seed(5)
    x = torch.randn(5, m.nq + m.nv, generator=g, dtype=F64) * 0.2
    u = torch.rand(5, m.nu, generator=g, dtype=F64) - 0.5
    u[0], u[1] = 1.0, -1.0
    mb, xb = _box_ball()
    mb.opt.integrator = mujoco.mjtIntegrator.mjINT_EULER
    # contacts: the differences are secants of a stiff, nonsmooth response (1e-4 there, 3e-6 on the hinges)
    ub = torch.tensor([[0.3], [1.0]], dtype=F64)
    for model, xs, us, tol in ((m, x, u, 3e-6), (mb, xb.expand(2, -1), ub, 1e-4)):
        fwd = MujocoSystem(model, jacobian_method=method, fd_scheme="forward")
        ctr = MujocoSystem(model, jacobian_method=method)
        assert fwd.fd_eps == 1.5e-8 and ctr.fd_eps == 1e-6
        assert 2e-8 < fwd.derivative_accuracy < 4e-8 < ctr.derivative_accuracy * 1e3
        (A1, B1), (A2, B2) = fwd.jacobian(xs, us), ctr.jacobian(xs, us)
        assert (A1 - A2).abs().max() <= tol * A2.abs().max()
        assert (B1 - B2).abs().max() <= tol * B2.abs().max()
        assert (A1 - A2).abs().max() > 0  # a different scheme, not the same numbers
        assert fwd.ilqr_options().tol_kkt == pytest.approx(1e3 * fwd.derivative_accuracy)


def test_forward_differences_count_their_rollouts(pendulum, monkeypatch):
    fwd = MujocoSystem(pendulum.model, frame_skip=pendulum.frame_skip, fd_scheme="forward")
    rows = []
    real = fwd._run

    def spy(xf, uf, **kw):
        rows.append(xf.shape[0])
        return real(xf, uf, **kw)

    monkeypatch.setattr(fwd, "_run", spy)
    fwd.jacobian(torch.zeros(3, 4, dtype=F64), torch.zeros(3, 1, dtype=F64))
    assert rows == [3 * (4 + 1 + 1)]  # one call: n + m + 1 steps per element
    with pytest.raises(ValueError, match="fd_scheme"):
        MujocoSystem(pendulum.model, fd_scheme="backward")


def test_open_loop_rollout_runs_in_one_call_and_equals_stepping(pendulum, monkeypatch):
    """controllers.dynamics.rollout on a MujocoSystem is one rollout_states call (not T steps), equal to
    stepping (the warm start MuJoCo carries across steps inside one call does not show here)."""
    from controllers.dynamics import rollout

    g = torch.Generator().manual_seed(2)
    x0 = torch.randn(3, 4, generator=g, dtype=F64) * 0.1
    u = torch.rand(3, 7, 1, generator=g, dtype=F64) * 2 - 1
    steps = [x0]
    for t in range(7):
        steps.append(pendulum.step(steps[-1], u[:, t]))
    calls = []
    real = pendulum._run
    monkeypatch.setattr(pendulum, "_run", lambda xf, uf, **kw: calls.append(uf.shape) or real(xf, uf, **kw))
    X = rollout(pendulum, x0, u)
    assert calls == [(3, 7, 1)]
    assert X.shape == (3, 8, 4)
    assert (X - torch.stack(steps, 1)).abs().max() <= 1e-12
    # broadcast: one initial state for a batch of control sequences
    Xb = rollout(pendulum, x0[0], u)
    assert Xb.shape == (3, 8, 4) and torch.equal(Xb[0], rollout(pendulum, x0[0], u[0]))
