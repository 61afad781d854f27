"""learning.evaluate on gymnasium environments the project did not write (learning.evaluate_env): equal to
a hand-written episode loop, Env / VectorEnv / id inputs, clipping and invalid actions, clear errors, and
the registered model MPC (learning.env_models, learning.model_mpc)."""

import math

import gymnasium as gym
import numpy as np
import pytest
import torch

from learning import evaluate
from learning.env_models import EnvModel, env_model, register_env_model
from learning.evaluate_env import is_foreign
from learning.model_mpc import ModelMPC


class _Tiny(gym.Env):
    """An unregistered env: ends after ``ends`` steps with ``info["is_success"] = (action > 0)``."""

    def __init__(self, obs_shape=(2,), ends=1):
        self.observation_space = gym.spaces.Box(-1.0, 1.0, obs_shape)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (1,))
        self.ends, self.t = ends, 0

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return np.zeros(self.observation_space.shape, dtype=np.float32), {}

    def step(self, a):
        self.t += 1
        done = self.t >= self.ends
        info = {"is_success": bool(a[0] > 0)} if done else {}
        return np.zeros(self.observation_space.shape, dtype=np.float32), 1.0, done, False, info


def _pd(o):
    """A torque law on Pendulum-v1's observation (saturates often: clipping is exercised)."""
    return -3.0 * o[:, 2:3] - 4.0 * o[:, 1:2]


def _hand_loop(policy, env_id: str, seed: int, clip=True, **kw):
    env = gym.make(env_id, **kw)
    o, _ = env.reset(seed=seed)
    R, L = 0.0, 0
    while True:
        a = policy(torch.as_tensor(o, dtype=torch.float64)[None])[0].numpy()
        if clip:
            a = np.clip(a, env.action_space.low, env.action_space.high)
        o, r, te, tr, _ = env.step(a.astype(env.action_space.dtype))
        R, L = R + r, L + 1
        if te or tr:
            return R, L


def test_id_equals_a_hand_written_loop_with_a_partial_last_round():
    r = evaluate(_pd, "Pendulum-v1", num_envs=3, episodes=5, seed=7, progress=False, timing_batch1=False)
    ref = [_hand_loop(_pd, "Pendulum-v1", s) for s in range(7, 12)]
    np.testing.assert_allclose(r.returns, [R for R, _ in ref], rtol=0, atol=1e-9)
    assert r.length.tolist() == [L for _, L in ref] == [200] * 5
    assert r.truncated.all() and not r.terminated.any() and not r.invalid.any()
    assert r.violations.sum() > 0  # the law saturates: clipped, counted
    assert r.meta["task"] == "Pendulum-v1" and r.meta["foreign_env"]
    assert math.isnan(r.summary()["success_rate"])  # Pendulum-v1 gives no is_success


def test_env_instance_and_vector_env_give_the_same_episodes():
    seeds = [2, 3]
    a = evaluate(_pd, gym.make("Pendulum-v1"), seeds=seeds, progress=False, timing_batch1=False)
    venv = gym.vector.SyncVectorEnv([lambda: gym.make("Pendulum-v1")] * 2)
    b = evaluate(_pd, venv, seeds=seeds, progress=False, timing_batch1=False)
    c = evaluate(_pd, "Pendulum-v1", seeds=seeds, progress=False, timing_batch1=False)
    np.testing.assert_array_equal(a.returns, c.returns)
    np.testing.assert_array_equal(b.returns, c.returns)
    assert a.meta["num_envs"] == 1 and b.meta["num_envs"] == 2


def test_terminating_env_lengths_and_max_episode_steps():
    """MountainCarContinuous terminates at the goal; a push to the right with the swing reaches it."""
    def pump(o):
        return torch.where(o[:, 1:2] >= 0, 1.0, -1.0).to(o.dtype)

    r = evaluate(pump, "MountainCarContinuous-v0", seeds=[0, 1], progress=False, timing_batch1=False)
    ref = [_hand_loop(pump, "MountainCarContinuous-v0", s) for s in (0, 1)]
    np.testing.assert_allclose(r.returns, [R for R, _ in ref], atol=1e-9)
    assert r.length.tolist() == [L for _, L in ref] and r.terminated.all()
    short = evaluate(pump, "MountainCarContinuous-v0", seeds=[0], max_episode_steps=10, progress=False,
                     timing_batch1=False)
    assert short.length.tolist() == [10] and short.truncated.all()


def test_nan_action_ends_that_episode_only():
    def pol(o):
        a = _pd(o)
        a[0] = math.nan
        return a

    r = evaluate(pol, "Pendulum-v1", seeds=[0, 1], progress=False, timing_batch1=False)
    assert r.invalid.tolist() == [True, False] and r.length.tolist() == [1, 200]

    def ref_pol(o):  # after the first episode ends, the second env runs _pd
        return _pd(o)

    assert r.returns[1] == pytest.approx(_hand_loop(ref_pol, "Pendulum-v1", 1)[0], abs=1e-9)


def test_policy_exception_and_wrong_shape_are_reported_per_round():
    def boom(o):
        raise RuntimeError("kaput")

    r = evaluate(boom, "Pendulum-v1", seeds=[0, 1], progress=False, timing_batch1=False)
    assert r.invalid.all() and all("kaput" in e for e in r.errors)
    r = evaluate(lambda o: torch.zeros(o.shape[0], 3, dtype=o.dtype), "Pendulum-v1", seeds=[0],
                 progress=False, timing_batch1=False)
    assert r.invalid.all() and "shape" in r.errors[0]


def test_bad_envs_give_clear_errors():
    with pytest.raises(TypeError, match="action space must be a gymnasium.spaces.Box"):
        evaluate(lambda o: 0, "CartPole-v1", seeds=[0], progress=False)
    venv = gym.vector.SyncVectorEnv([lambda: gym.make("Pendulum-v1")],
                                    autoreset_mode=gym.vector.AutoresetMode.DISABLED)
    with pytest.raises(ValueError, match="DISABLED"):
        evaluate(_pd, venv, seeds=[0], progress=False)
    with pytest.raises(ValueError, match="task_kwargs"):
        evaluate(_pd, gym.make("Pendulum-v1"), seeds=[0], task_kwargs={"g": 2.0}, progress=False)
    with pytest.raises(TypeError, match="1-d"):
        evaluate(lambda o: 0, _Tiny(obs_shape=(2, 2)), seeds=[0], max_episode_steps=3, progress=False)
    with pytest.raises(ValueError, match="no episode limit"):
        evaluate(lambda o: 0, _Tiny(), seeds=[0], progress=False)
    assert is_foreign("Pendulum-v1") and not is_foreign("PendulumSwingUp")
    assert not is_foreign("liecontrol/PendulumSwingUp-v0") and not is_foreign("NoSuchEnv-v9")


def test_env_model_lookup_and_checks():
    with pytest.raises(ValueError, match="no model is registered"):
        env_model("MountainCar-v0")
    md = env_model(gym.make("Pendulum-v1"))
    assert (md.n, md.m) == (2, 1)

    def bad(env):
        return EnvModel(env_id="Pendulum-v1", system=md.system, cost=md.cost,
                        state_from_obs=lambda o: o, action_low=(-2.0,), action_high=(2.0,))

    register_env_model("PendulumBadMap-v1", bad)
    try:
        gym.register("PendulumBadMap-v1", entry_point="gymnasium.envs.classic_control:PendulumEnv",
                     max_episode_steps=200)
        with pytest.raises(ValueError, match="observation map"):
            env_model(gym.make("PendulumBadMap-v1"))
    finally:
        gym.registry.pop("PendulumBadMap-v1", None)
        from learning.env_models import ENV_MODELS
        ENV_MODELS.pop("PendulumBadMap-v1", None)


def test_mpc_on_pendulum_v1_holds_a_start_near_upright():
    """The registered model MPC as ``"mpc"``: from the episodes' own random starts, short episodes; the
    multi-start keeps the certificate on every solve, and the actions stay in the box."""
    r = evaluate("mpc", "Pendulum-v1", seeds=[0, 5], max_episode_steps=3, progress=False,
                 timing_batch1=False)
    assert r.meta["policy"].startswith("ModelMPC") and r.length.tolist() == [3, 3]
    assert r.violations.sum() == 0 and r.nonconverged.max() == 0
    pol = ModelMPC("Pendulum-v1", horizon=30)
    o = torch.tensor([[math.cos(0.07), math.sin(0.07), 0.0]], dtype=torch.float64)  # 4 degrees off upright
    a = pol.act(o)
    assert -2.0 <= float(a) < 0.0  # brakes (pushes back towards upright), no swing
    assert bool(pol.info()["converged"].all())


def test_unregistered_envs_vector_envs_and_same_step_success():
    """An env instance without a spec: its TimeLimit or max_episode_steps bounds the episode; a VectorEnv
    with more sub-envs than seeds is padded; SAME_STEP's ending info (final_info) gives the success."""
    one = evaluate(lambda o: torch.ones(o.shape[0], 1), gym.wrappers.TimeLimit(_Tiny(ends=9), 4), seeds=[0],
                   progress=False)
    assert one.length.tolist() == [4] and one.truncated.all()
    short = evaluate(lambda o: torch.ones(o.shape[0], 1), _Tiny(ends=9), seeds=[0], max_episode_steps=2,
                     progress=False)
    assert short.length.tolist() == [2]
    for mode in (gym.vector.AutoresetMode.NEXT_STEP, gym.vector.AutoresetMode.SAME_STEP):
        venv = gym.vector.SyncVectorEnv([_Tiny] * 4, autoreset_mode=mode)
        r = evaluate(lambda o: torch.tensor([[1.0], [-1.0], [1.0], [-1.0]])[: o.shape[0]], venv, seeds=[0, 1],
                     max_episode_steps=5, progress=False, timing_batch1=False)
        assert r.success.tolist() == [True, False] and r.meta["success_defined"], mode
        assert r.length.tolist() == [1, 1] and r.summary()["success_rate"] == 0.5


def test_float32_policy_dtype_still_sums_returns_in_float64():
    def push(o):
        return torch.full((o.shape[0], 1), 0.3, dtype=o.dtype)

    r = evaluate(push, "MountainCarContinuous-v0", seeds=[0], dtype=torch.float32, progress=False,
                 timing_batch1=False)
    assert r.returns[0] == _hand_loop(push, "MountainCarContinuous-v0", 0)[0]


def test_the_model_mpc_refuses_an_env_it_does_not_describe():
    with pytest.raises(ValueError, match="registered defaults"):
        evaluate("mpc", "Pendulum-v1", seeds=[0], task_kwargs={"g": 2.0}, progress=False)
    with pytest.raises(ValueError, match="action box"):
        ModelMPC(gym.wrappers.RescaleAction(gym.make("Pendulum-v1"), -1.0, 1.0))
    with pytest.raises(ValueError, match="NormalizeObservation"):
        ModelMPC(gym.wrappers.NormalizeObservation(gym.make("Pendulum-v1")))
    assert ModelMPC(gym.wrappers.RecordEpisodeStatistics(gym.make("Pendulum-v1"))).model.m == 1


def test_linear_model_mpc_holds_pendulum_v1_near_upright():
    """The linear MPC (one linearization a step) on the Pendulum-v1 model, its periodic cost wrapped: from
    10 degrees either side of upright (on both branches of the angle cut) it holds the pendulum up."""
    from learning.model_mpc import LinearModelMPC

    pol = LinearModelMPC("Pendulum-v1", horizon=30)
    sysm = pol.model.system
    x = torch.tensor([[math.pi - 0.17, 0.0], [-math.pi + 0.17, 0.0]], dtype=torch.float64)
    worst = 0.0
    for _ in range(60):
        obs = torch.stack([-torch.cos(x[:, 0]), -torch.sin(x[:, 0]), x[:, 1]], -1)
        u = pol.act(obs)
        assert bool(((u >= -2) & (u <= 2)).all())
        x = sysm.step(x, u)
        worst = max(worst, float(torch.remainder(x[:, 0], 2 * math.pi).sub(math.pi).abs().max()))
    assert worst < 0.2 and pol.info() is None
    with pytest.raises(ValueError, match="not quadratic"):
        LinearModelMPC("MountainCarContinuous-v0")
