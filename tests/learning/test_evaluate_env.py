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
    with pytest.raises(ValueError, match="max_episode_steps"):
        evaluate(_pd, gym.make("Pendulum-v1"), seeds=[0], max_episode_steps=5, progress=False)
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
