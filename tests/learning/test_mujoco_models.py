"""The MuJoCo env models (learning/_mujoco_models.py): exact obs->state maps, check_model, the costs against
the rewards' terms computed by MuJoCo's own kinematics, and short certified MPC runs inside the action box."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

mujoco = pytest.importorskip("mujoco")
gym = pytest.importorskip("gymnasium")
np = pytest.importorskip("numpy")

from controllers.costs import autograd_derivatives  # noqa: E402
from learning._mujoco_models import (  # noqa: E402
    IDPCost,
    ReacherCost,
    idp_state,
    idp_tip,
    inverted_double_pendulum_model,
    inverted_pendulum_model,
    ip_state,
    reacher_fingertip,
    reacher_model,
    reacher_state,
)
from learning.env_models import check_model  # noqa: E402
from learning.model_mpc import ModelMPC  # noqa: E402

F64 = torch.float64
IP, IDP, REACHER = "InvertedPendulum-v5", "InvertedDoublePendulum-v5", "Reacher-v5"
FACTORIES = {IP: inverted_pendulum_model, IDP: inverted_double_pendulum_model, REACHER: reacher_model}
STATE_MAPS = {IP: ip_state, IDP: idp_state, REACHER: reacher_state}


@pytest.fixture(scope="module")
def models():
    out = {}
    for eid, fac in FACTORIES.items():
        env = gym.make(eid)
        out[eid] = (env, fac(env))
    return out


def _qstate(env) -> torch.Tensor:
    d = env.unwrapped.data
    return torch.from_numpy(np.concatenate([d.qpos, d.qvel]).copy())


def _episode(env, seed: int, steps: int, scale: float = 1.0):
    """``(observations, states [qpos, qvel], actions, rewards)`` of random actions from ``reset(seed)``."""
    rng = np.random.default_rng(seed)
    obs, _ = env.reset(seed=seed)
    O, X, A, R = [obs], [_qstate(env)], [], []
    lo, hi = env.action_space.low, env.action_space.high
    for _ in range(steps):
        a = (scale * rng.uniform(lo, hi)).astype(env.action_space.dtype)
        obs, r, term, trunc, _ = env.step(a)
        O.append(obs)
        X.append(_qstate(env))
        A.append(a)
        R.append(r)
        if term:
            break
    return (torch.from_numpy(np.stack(O)), torch.stack(X), torch.from_numpy(np.stack(A)).to(F64),
            torch.tensor(R, dtype=F64))


# -------------------------------------------------------------------------------------------- obs -> state


@pytest.mark.parametrize("eid", [IP, IDP, REACHER])
def test_state_from_obs_is_exact(models, eid):
    env, md = models[eid]
    for seed in (0, 1):
        O, X, _, _ = _episode(env, seed, 12, scale=0.3)
        x = md.state_from_obs(O)
        assert x.shape == X.shape == (O.shape[0], md.n)
        assert torch.allclose(x, X, rtol=0, atol=1e-14)  # atan2(sin, cos) is the angle to round-off
        assert md.state_from_obs(O.float()).dtype == torch.float32
        assert torch.equal(md.state_from_obs(O.expand(2, *O.shape)), x.expand(2, *x.shape))  # batch dims


def test_reacher_state_recovers_the_unlimited_joint_modulo_two_pi(models):
    env, md = models[REACHER]
    env.reset(seed=0)
    u = env.unwrapped
    qpos, qvel = u.data.qpos.copy(), u.data.qvel.copy()
    qpos[0] = 2 * math.pi + 0.7  # joint0 is unlimited: one turn and a bit
    u.set_state(qpos, qvel)
    obs = torch.from_numpy(u._get_obs())[None]
    x = md.state_from_obs(obs)[0]
    ref = _qstate(env)
    assert abs(float(x[0]) - (float(ref[0]) - 2 * math.pi)) < 1e-14
    assert torch.allclose(x[1:], ref[1:], rtol=0, atol=1e-15)


@pytest.mark.parametrize("fn,k", [(ip_state, 4), (idp_state, 9), (reacher_state, 10)])
def test_state_maps_reject_bad_input(fn, k):
    with pytest.raises(ValueError, match="obs"):
        fn(torch.zeros(3, k + 1, dtype=F64))
    with pytest.raises(TypeError, match="obs"):
        fn(torch.zeros(3, k, dtype=torch.int64))
    # a NaN observation gives a NaN state for that row only
    obs = torch.zeros(2, k, dtype=F64)
    obs[0, 0] = math.nan
    x = fn(obs)
    assert torch.isfinite(x[1]).all()


@pytest.mark.parametrize("eid", [IP, IDP, REACHER])
def test_check_model_passes_on_env_and_vector_env(models, eid):
    env, md = models[eid]
    check_model(md, env)
    venv = gym.vector.SyncVectorEnv([lambda: gym.make(eid)] * 2)
    try:
        md2 = FACTORIES[eid](venv)  # the system of the vector env's first copy
        check_model(md2, venv)
        assert md2.n == md.n and md2.m == md.m
    finally:
        venv.close()
    assert md.options["tol_kkt"] >= 1e3 * md.system.derivative_accuracy  # certified at what FD allows


def test_check_model_rejects_a_model_with_another_time_step(models):
    """A MuJoCo model whose time step (or frame_skip) differs from the env's plans another env: an error
    naming both time steps, not a silently wrong MPC."""
    from controllers.systems.mujoco_system import MujocoSystem

    env, md = models[IP]
    mm = mujoco.MjModel.from_xml_path(env.unwrapped.fullpath)
    mm.opt.timestep = 2 * env.unwrapped.model.opt.timestep
    other = dataclasses.replace(md, system=MujocoSystem(mm, frame_skip=env.unwrapped.frame_skip))
    with pytest.raises(ValueError, match=r"dt = 0\.08 s but the env steps dt = 0\.04 s"):
        check_model(other, env)
    other = dataclasses.replace(md, system=MujocoSystem(env.unwrapped.model, frame_skip=1))
    with pytest.raises(ValueError, match="dt = 0.02 s but the env"):
        check_model(other, env)
    check_model(dataclasses.replace(md, system=MujocoSystem(env.unwrapped.model, frame_skip=2)), env)


# ------------------------------------------------------------------------------------------------ geometry


def _kinematics(mm, X: torch.Tensor):
    """MuJoCo's positions (site/body ``xpos``) at the states ``X (N, nq + nv)`` by ``mj_kinematics``."""
    d = mujoco.MjData(mm)
    out = []
    for x in X:
        d.qpos[:] = x[:mm.nq].numpy()
        mujoco.mj_kinematics(mm, d)
        out.append((d.site_xpos.copy(), d.xpos.copy()))
    return out


def test_idp_tip_equals_mujoco_kinematics(models):
    env, md = models[IDP]
    gen = torch.Generator().manual_seed(0)
    scale = torch.tensor([1.6, 6.0, 6.0, 1, 1, 1], dtype=F64)
    X = (torch.rand(20, 6, generator=gen, dtype=F64) - 0.5) * scale
    ref = torch.tensor(np.stack([k[0][0][[0, 2]] for k in _kinematics(md.system.model, X)]))
    cost = md.cost(5)
    assert torch.allclose(idp_tip(X, cost.l1, cost.l2, cost.z0), ref, rtol=0, atol=1e-14)


def test_reacher_fingertip_equals_mujoco_kinematics(models):
    env, md = models[REACHER]
    mm = md.system.model
    gen = torch.Generator().manual_seed(1)
    X = torch.zeros(20, 8, dtype=F64)
    X[:, 0] = (torch.rand(20, generator=gen, dtype=F64) - 0.5) * 20  # several turns
    X[:, 1] = (torch.rand(20, generator=gen, dtype=F64) - 0.5) * 6
    X[:, 2:4] = (torch.rand(20, 2, generator=gen, dtype=F64) - 0.5) * 0.4
    tip_id = mujoco.mj_name2id(mm, mujoco.mjtObj.mjOBJ_BODY, "fingertip")
    tg_id = mujoco.mj_name2id(mm, mujoco.mjtObj.mjOBJ_BODY, "target")
    kin = _kinematics(mm, X)
    ref = torch.tensor(np.stack([k[1][tip_id] - k[1][tg_id] for k in kin]))
    rc = md.cost(5)
    assert abs(rc.dz) < 1e-15 and torch.allclose(ref[:, 2], torch.zeros(20, dtype=F64), atol=1e-15)
    assert torch.allclose(rc.offset(X), ref[:, :2], rtol=0, atol=1e-14)
    assert torch.allclose(reacher_fingertip(X, rc.l1, rc.l2, rc.base),
                          torch.tensor(np.stack([k[1][tip_id][:2] for k in kin])), rtol=0, atol=1e-14)


# ------------------------------------------------------------------------------------------------ costs


def test_idp_cost_is_the_rewards_penalties(models):
    env, md = models[IDP]
    O, X, A, R = _episode(env, 3, 8, scale=0.2)
    assert R.shape[0] == 8  # not terminated: the alive bonus was paid every step
    cost = md.cost(8)
    kin = _kinematics(md.system.model, X)
    tip = torch.tensor(np.stack([k[0][0][[0, 2]] for k in kin]))
    hand = 0.01 * tip[:, 0] ** 2 + (tip[:, 1] - 2) ** 2 + 1e-3 * X[:, 4] ** 2 + 5e-3 * X[:, 5] ** 2
    assert torch.allclose(cost.penalty(X), hand, rtol=0, atol=1e-13)
    # the env evaluates the tip at the last RK4 stage of its last substep, not at the new state: ~1e-5 m
    assert torch.allclose(10.0 - cost.penalty(X[1:]), R, rtol=0, atol=1e-3)
    # the barrier: nothing while the tip is well above y_min, a cost below it
    def barrier(z):
        return cost.stage(z) - cost.penalty(z) - cost.cart * z[..., 0] ** 2 - cost.cart_vel * z[..., 3] ** 2

    sp = torch.nn.functional.softplus((cost.y_min - tip[:, 1]) / cost.width)
    assert torch.allclose(barrier(X), cost.barrier * (cost.width * sp) ** 2, rtol=1e-9, atol=1e-15)
    assert float(barrier(X[:6]).max()) < 1e-6  # the tip well above y_min in the first steps: ~nothing
    low = X[:1].clone()
    low[0, 1] = 0.9  # tip near 1.0 m
    assert float(barrier(low)) > 1.0
    # the trajectory cost: x_1..x_T with the last weighted, plus r Σu², plus the cost-to-go at x_T
    J = cost.evaluate(X[None], A[None])[0]
    w = torch.ones(9, dtype=F64)
    w[0], w[-1] = 0, cost.terminal
    hand = (w * cost.stage(X)).sum() + cost.r * (A ** 2).sum() + X[-1] @ cost.P @ X[-1]
    assert torch.allclose(J, hand, rtol=1e-14, atol=0)


def test_idp_value_to_go_solves_the_riccati_equation(models):
    scipy_linalg = pytest.importorskip("scipy.linalg")
    env, md = models[IDP]
    cost = md.cost(5)
    x0 = torch.zeros(1, 6, dtype=F64)
    A, B = md.system.jacobian(x0, torch.zeros(1, 1, dtype=F64))
    H = torch.autograd.functional.hessian(cost.stage, x0[0])
    ref = scipy_linalg.solve_discrete_are(A[0].numpy(), B[0].numpy(), 0.5 * H.numpy(), np.array([[cost.r]]))
    assert torch.allclose(cost.P, torch.from_numpy(ref), rtol=1e-8, atol=1e-8 * float(cost.P.abs().max()))
    assert torch.linalg.eigvalsh(cost.P).min() > 0
    with pytest.raises(ValueError, match="P"):
        IDPCost(P=torch.eye(5, dtype=F64))


def test_reacher_cost_is_the_reward_smoothed(models):
    env, md = models[REACHER]
    O, X, A, R = _episode(env, 4, 10)
    rc = md.cost(10)
    assert (rc.w_dist, rc.w_ctrl) == (1.0, 1.0)  # v5's weights
    mm = md.system.model
    tip_id = mujoco.mj_name2id(mm, mujoco.mjtObj.mjOBJ_BODY, "fingertip")
    tg_id = mujoco.mj_name2id(mm, mujoco.mjtObj.mjOBJ_BODY, "target")
    dist = torch.tensor([float(np.linalg.norm(k[1][tip_id] - k[1][tg_id])) for k in _kinematics(mm, X)],
                        dtype=F64)
    d = rc.smoothing
    w = torch.ones(11, dtype=F64)
    w[0], w[-1] = 0, rc.terminal
    hand = (w * (torch.sqrt(dist ** 2 + d * d) - d)).sum() + (A ** 2).sum()
    J = rc.evaluate(X[None], A[None])[0]
    assert torch.allclose(J, hand, rtol=1e-13, atol=0)
    # against the env's rewards: the smoothing is at most δ a step (and the env's stale kinematics ~1e-5)
    J1 = dataclasses.replace(rc, terminal=1.0).evaluate(X[None], A[None])[0]
    assert -10 * d - 1e-3 <= float(J1 + R.sum()) <= 1e-3


def test_reacher_cost_derivatives_against_autograd():
    rc = ReacherCost(terminal=3.0)
    gen = torch.Generator().manual_seed(2)
    x = torch.randn(3, 6, 8, generator=gen, dtype=F64) * 0.5
    u = torch.randn(3, 5, 2, generator=gen, dtype=F64)
    gx, gu, Hxx, Hux, Huu = rc.derivatives(x, u)
    agx, agu, aHxx, _, aHuu = autograd_derivatives(rc, x, u)
    assert torch.allclose(gx, agx, rtol=1e-12, atol=1e-13) and torch.allclose(gu, agu, rtol=1e-12, atol=0)
    assert torch.allclose(Huu.expand_as(aHuu), aHuu)
    assert torch.linalg.eigvalsh(Hxx).min() > -1e-12  # Gauss-Newton: positive semidefinite
    assert Hux is None
    for bad in (dict(smoothing=0.0), dict(l1=-1.0)):
        with pytest.raises(ValueError, match="ReacherCost"):
            ReacherCost(**bad)
    with pytest.raises(ValueError, match="expected x"):
        rc.evaluate(x[..., :7], u)


def test_costs_follow_the_dtype(models):
    rc, ic = models[REACHER][1].cost(4), models[IDP][1].cost(4)
    gen = torch.Generator().manual_seed(3)
    for cost, n, m in ((rc, 8, 2), (ic, 6, 1)):
        x = torch.randn(2, 5, n, generator=gen, dtype=F64) * 0.2
        u = torch.randn(2, 4, m, generator=gen, dtype=F64) * 0.2
        J64 = cost.evaluate(x, u)
        J32 = cost.evaluate(x.float(), u.float())
        assert J32.dtype == torch.float32 and torch.allclose(J32.double(), J64, rtol=1e-5, atol=1e-6)
    g32 = rc.derivatives(x.new_zeros(2, 5, 8).float(), u.new_zeros(2, 4, 2).float())
    assert all(v is None or v.dtype == torch.float32 for v in g32)


def test_idp_cost_rejects_bad_fields():
    with pytest.raises(ValueError, match="IDPCost"):
        IDPCost(width=0.0)
    with pytest.raises(ValueError, match="IDPCost"):
        IDPCost(barrier=-1.0)


def test_ip_cost_is_quadratic_about_upright(models):
    env, md = models[IP]
    c = md.cost(4)
    x = torch.tensor([[0.1, -0.05, 0.2, 0.3]], dtype=F64).expand(5, 4)[None]
    u = torch.full((1, 4, 1), 0.5, dtype=F64)
    q = torch.tensor([1.0, 10.0, 0.1, 0.1], dtype=F64)
    stage = (q * x[0, 0] ** 2).sum()
    assert torch.allclose(c.evaluate(x, u)[0], (4 + 10) * stage + 4 * 0.01 * 0.25, rtol=1e-14, atol=0)


# ------------------------------------------------------------------------------------------------ MPC


@pytest.mark.parametrize("eid,horizon", [(IP, 10), (IDP, 8), (REACHER, 10)])
def test_short_mpc_run_in_box_and_certified(models, eid, horizon):
    env, md = models[eid]
    venv = gym.vector.SyncVectorEnv([lambda: gym.make(eid)] * 2)
    pol = ModelMPC(md, horizon=horizon, max_iter=30, multistart=False)
    obs, _ = venv.reset(seed=[5, 6])
    lo, hi = torch.tensor(md.action_low, dtype=F64), torch.tensor(md.action_high, dtype=F64)
    try:
        for _ in range(3):
            a = pol.act(torch.from_numpy(obs))
            assert a.shape == (2, md.m) and torch.isfinite(a).all()
            assert bool(((a >= lo) & (a <= hi)).all())
            assert bool(pol.info()["converged"].all()), pol.info()
            obs, r, term, trunc, _ = venv.step(a.numpy())
            assert not term.any()
    finally:
        venv.close()
