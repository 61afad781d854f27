"""HalfCheetah-v5's model (learning._mujoco_locomotion) and the sampling MPC (learning.sampling_mpc).

Checked against the env itself: the cost is minus the env's return along a real trajectory, the
observation map reproduces the env's state, and the model's rollout from the mapped state (x position
0) is the env's trajectory translated along x.  The policy: a batch equals the per-environment loop with
seeds ``seed + b``; ``reset(done)`` touches only the done elements; the planner lowers the cost below its
initial guess.  Small sample counts and horizons keep it fast (the measured returns are in the report
of issue 27, not asserted here).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

gym = pytest.importorskip("gymnasium")
pytest.importorskip("mujoco")

import learning  # noqa: E402
from controllers.sampling import SamplingOptions  # noqa: E402
from learning._mujoco_locomotion import ForwardRewardCost, half_cheetah_model, half_cheetah_state  # noqa: E402
from learning.env_models import env_model  # noqa: E402
from learning.sampling_mpc import SamplingModelMPC, _normals, sampling_guess  # noqa: E402

ID = "HalfCheetah-v5"
SMALL = SamplingOptions(samples=8, noise_sigma=0.5, temperature=0.5, smoothing="knots", knots=3)


@pytest.fixture(scope="module")
def model():
    return env_model(ID)


def _trajectory(seed: int = 3, steps: int = 25):
    """States ``[qpos, qvel]``, observations, actions and rewards of a real episode with random actions."""
    env = gym.make(ID)
    obs, _ = env.reset(seed=seed)
    d = env.unwrapped.data
    xs, os_, us, rs = [np.concatenate([d.qpos, d.qvel])], [obs], [], []
    rng = np.random.default_rng(seed)
    for _ in range(steps):
        a = rng.uniform(-1.0, 1.0, 6)
        obs, r, *_ = env.step(a)
        xs.append(np.concatenate([d.qpos, d.qvel]))
        os_.append(obs)
        us.append(a)
        rs.append(r)
    env.close()
    t = lambda v: torch.tensor(np.asarray(v), dtype=torch.float64)  # noqa: E731
    return t(xs), t(os_), t(us), t(rs)


def test_cost_is_minus_the_env_return(model):
    X, _, U, R = _trajectory()
    cost = model.cost(U.shape[0])
    assert float(X[:, 0].abs().max()) > 0.05  # the cheetah moved: the forward term is tested
    torch.testing.assert_close(cost.evaluate(X, U), -R.sum(), rtol=0, atol=1e-11)
    torch.testing.assert_close(cost.rewards(X, U), R, rtol=0, atol=1e-12)
    # leading batch dims (the planner's (C, *B, ...)) give the same values
    Xb, Ub = torch.stack([X, X.flip(0)]), torch.stack([U, U.flip(0)])
    torch.testing.assert_close(cost.evaluate(Xb[None], Ub[None])[0],
                               torch.stack([cost.evaluate(X, U), cost.evaluate(X.flip(0), U.flip(0))]))


def test_observation_map_and_translation_invariance(model):
    X, O, U, _ = _trajectory(seed=5)
    S = half_cheetah_state(O)
    assert S.shape == (O.shape[0], 18)
    assert torch.equal(S[:, 0], torch.zeros(O.shape[0], dtype=torch.float64))
    assert torch.equal(S[:, 1:], X[:, 1:])  # qpos[1:], qvel exactly
    # the model from the mapped state (x position 0) is the env's trajectory shifted by its x position
    Xm = model.system.rollout_states(S[0], U)
    shifted = X.clone()
    shifted[:, 0] -= X[0, 0]
    torch.testing.assert_close(Xm, shifted, rtol=0, atol=1e-9)
    cost = model.cost(U.shape[0])
    torch.testing.assert_close(cost.evaluate(Xm, U), cost.evaluate(X, U), rtol=0, atol=1e-9)


def test_registered_and_checked_against_the_env():
    env = gym.make(ID)
    md = env_model(env)  # check_model runs against the env's spaces
    assert md.env_id == ID and md.n == 18 and md.m == 6
    assert md.action_low == (-1.0,) * 6 and md.action_high == (1.0,) * 6
    assert md.cost(5).forward_weight == 1.0 and md.cost(5).ctrl_weight == 0.1
    env.close()
    env = gym.make(ID, ctrl_cost_weight=0.3, forward_reward_weight=2.0)
    fc = half_cheetah_model(env).cost(5)  # the weights are read from the env
    assert (fc.forward_weight, fc.ctrl_weight) == (2.0, 0.3)
    env.close()


def test_batched_equals_per_env_loop(model):
    _, O, _, _ = _trajectory(seed=1, steps=3)
    obs = O[:3]
    batched = SamplingModelMPC(model, horizon=6, options=SMALL, seed=4)
    singles = [SamplingModelMPC(model, horizon=6, options=SMALL, seed=4 + b) for b in range(3)]
    for step in range(3):
        o = obs.roll(step, 0)  # a different state each step, the plan carried over
        a = batched.act(o)
        ref = torch.cat([p.act(o[b:b + 1]) for b, p in enumerate(singles)])
        torch.testing.assert_close(a, ref, rtol=0, atol=1e-12)
        assert a.shape == (3, 6) and bool(((a >= -1) & (a <= 1)).all())
    info = batched.info()
    assert info["iterations"].shape == (3,) and info["cost"].shape == (3,)
    # a different seed draws different noise
    other = SamplingModelMPC(model, horizon=6, options=SMALL, seed=5)
    same = SamplingModelMPC(model, horizon=6, options=SMALL, seed=4)
    assert not torch.allclose(other.act(obs[:1]), same.act(obs[:1]))


def test_reset_done_touches_only_done_elements(model):
    _, O, _, _ = _trajectory(seed=2, steps=2)
    obs = O[:2]
    a, b = (SamplingModelMPC(model, horizon=6, options=SMALL) for _ in range(2))
    a.act(obs)
    b.act(obs)
    a.reset(torch.tensor([True, False]))
    ua, ub = a.act(obs), b.act(obs)
    torch.testing.assert_close(ua[1], ub[1], rtol=0, atol=0)
    assert not torch.allclose(ua[0], ub[0])
    # a new episode draws new noise: element 0 is cold-started but does not repeat its first episode's draws
    first = SamplingModelMPC(model, horizon=6, options=SMALL).act(obs)
    assert not torch.allclose(ua[0], first[0])
    a.reset()  # all: the same as a fresh policy
    fresh = SamplingModelMPC(model, horizon=6, options=SMALL)
    torch.testing.assert_close(a.act(obs), fresh.act(obs), rtol=0, atol=0)


def test_planner_improves_on_its_initial_guess(model):
    _, O, _, _ = _trajectory(seed=0, steps=1)
    x = half_cheetah_state(O[:2])
    T = 10
    cost = model.cost(T)
    opts = SamplingOptions(samples=32, iterations=3, noise_sigma=0.5, temperature=0.5, smoothing="knots",
                           knots=4)
    U0 = torch.zeros(2, T, 6, dtype=torch.float64)
    U = sampling_guess(model, x, T, options=opts, seed=0)
    J0 = cost.evaluate(model.system.rollout_states(x, U0), U0)
    J = cost.evaluate(model.system.rollout_states(x, U), U)
    assert U.shape == (2, T, 6) and bool(((U >= -1) & (U <= 1)).all())
    assert bool((J < J0 - 0.1).all()), (J, J0)  # it runs forward: lower cost than standing still
    torch.testing.assert_close(sampling_guess(model, x, T, options=opts, seed=0), U)  # seeded
    # batched guess == per-element guesses with seeds seed + b
    U1 = sampling_guess(model, x[1:], T, options=opts, seed=1)
    torch.testing.assert_close(U[1:], U1, rtol=0, atol=1e-12)


def test_other_model_default_options_float32():
    # a model without tuned settings: the default options (a per-control tensor sigma), float32 observations
    pol = SamplingModelMPC("InvertedPendulum-v5", horizon=8)
    obs = torch.tensor([[0.0, 0.1, 0.0, 0.0], [0.2, -0.1, 0.0, 0.3]], dtype=torch.float32)
    a = pol.act(obs)
    assert a.dtype == torch.float32 and a.shape == (2, 1) and bool((a.abs() <= 3).all())
    assert bool(torch.isfinite(pol.info()["cost"]).all())
    # the pole leans right (+angle): push the cart right to catch it
    assert float(a[0, 0]) > 0


def test_counter_normals_are_standard_normal():
    key = torch.tensor([11, 12], dtype=torch.int64)
    z = _normals(key, torch.zeros(2, dtype=torch.int64), (50_000,), torch.float64)
    assert z.shape == (2, 50_000)
    assert float(z.mean().abs()) < 0.015 and abs(float(z.std()) - 1.0) < 0.015
    assert abs(float((z.abs() < 1).double().mean()) - 0.6827) < 0.01
    assert not torch.allclose(z[0, :100], z[1, :100])
    z2 = _normals(key, torch.ones(2, dtype=torch.int64), (10,), torch.float64)
    assert not torch.allclose(z[:, :10], z2)  # another counter, other draws


def test_evaluate_runs_the_policy_briefly(model):
    import learning

    pol = SamplingModelMPC(model, horizon=5, options=SMALL)
    r = learning.evaluate(pol, ID, seeds=[0, 1], num_envs=2, max_episode_steps=3, progress=False,
                          timing_batch1=False)
    assert np.isfinite(r.returns).all() and (r.length == 3).all()


def test_bad_input(model):
    with pytest.raises(ValueError, match="obs"):
        half_cheetah_state(torch.zeros(2, 18, dtype=torch.float64))
    with pytest.raises(TypeError, match="obs"):
        half_cheetah_state(torch.zeros(2, 17, dtype=torch.int64))
    cost = model.cost(4)
    with pytest.raises(ValueError, match="expected x"):
        cost.evaluate(torch.zeros(4, 18, dtype=torch.float64), torch.zeros(4, 6, dtype=torch.float64))
    with pytest.raises(ValueError, match="dt"):
        ForwardRewardCost(dt=0.0, n=18, m=6)
    with pytest.raises(ValueError, match="position_index"):
        ForwardRewardCost(dt=0.05, n=18, m=6, position_index=18)
    with pytest.raises(ValueError, match="horizon"):
        SamplingModelMPC(model, horizon=0)
    with pytest.raises(ValueError, match="common_noise"):
        SamplingModelMPC(model, options=SamplingOptions(common_noise=True))
    with pytest.raises(TypeError, match="options"):
        SamplingModelMPC(model, options={"samples": 3})
    with pytest.raises(ValueError, match="fill"):
        SamplingModelMPC(model, fill="mean")
    pol = SamplingModelMPC(model, horizon=3, options=SMALL)
    with pytest.raises(ValueError, match="obs"):
        pol.act(torch.zeros(17, dtype=torch.float64))
    with pytest.raises(TypeError, match="done"):
        pol.reset(torch.tensor([1, 0]))
    with pytest.raises(ValueError, match="'x'"):
        sampling_guess(model, torch.zeros(2, 17, dtype=torch.float64), 3)
    with pytest.raises(ValueError, match="u_init"):
        sampling_guess(model, torch.zeros(2, 18, dtype=torch.float64), 3,
                       u_init=torch.zeros(2, 4, 6, dtype=torch.float64))
    env = gym.make(ID, exclude_current_positions_from_observation=False)
    with pytest.raises(ValueError, match="exclude_current_positions"):
        half_cheetah_model(env)
    env.close()


def test_mpc_on_half_cheetah_means_the_sampling_planner():
    """The model names its planner: "mpc" on HalfCheetah-v5 is the sampling MPC, on Pendulum-v1 iLQR."""
    from learning.model_mpc import ModelMPC, model_policy

    assert isinstance(model_policy("HalfCheetah-v5"), SamplingModelMPC)
    assert model_policy("HalfCheetah-v5", horizon=7).horizon == 7
    assert isinstance(model_policy("Pendulum-v1"), ModelMPC)
    r = learning.evaluate("mpc", "HalfCheetah-v5", seeds=[0], num_envs=1, max_episode_steps=3,
                          progress=False, timing_batch1=False)
    assert r.meta["policy"].startswith("SamplingModelMPC") and r.length[0] == 3
