"""The MPC head on the manifold (:mod:`learning.mpc_head_quadrotor`): untrained it is the task's expert,
its gradient reaches the cost network and matches finite differences, batched equals one by one, the
warm start does not change the action (a QP solved to optimality), PPO's recomputed log-probabilities equal
the rollout's, and a bad observation is contained."""

import numpy as np
import pytest
import torch

from learning.envs.single import make_task
from learning.mpc_head_quadrotor import ErrorStateMPCExtractor
from learning.mpc_policy import MPCActorCriticPolicy, make_mpc_ppo

H = 10


@pytest.fixture(scope="module")
def task():
    return make_task("QuadrotorCircle")


def _obs(task, n, seed=0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    x = task.initial_state(torch.rand(n, 10, generator=g, dtype=torch.float64))
    return task.observe(x).to(dtype)


def _head(task, **kw):
    torch.manual_seed(0)
    return ErrorStateMPCExtractor(task, task.obs_dim + (H * 4 if kw.get("warm_start") else 0), horizon=H,
                                  **kw).double()


def test_untrained_head_is_the_expert(task):
    obs = _obs(task, 6)
    ext = _head(task)
    expert = task.expert(horizon=H)
    with torch.no_grad():
        a, _ = ext.act_and_plan(obs)
    torch.testing.assert_close(a, expert.act(obs), rtol=0, atol=1e-9)
    assert bool(expert.info()["converged"].all())


def test_gradient_reaches_the_cost_network_and_matches_finite_differences(task):
    obs = _obs(task, 3, seed=1)
    ext = _head(task, per_step=True)
    last = ext.net[-1]
    with torch.no_grad():  # a generic cost (not the zero-initialized one), small: the active set stays
        last.bias.copy_(0.3 * torch.randn(last.bias.shape, generator=torch.Generator().manual_seed(2),
                                          dtype=torch.float64))
    w = torch.randn(3, 4, generator=torch.Generator().manual_seed(3), dtype=torch.float64)

    def f(bias):
        with torch.no_grad():
            last.bias.copy_(bias)
        a, _ = ext.act_and_plan(obs)
        return (a * w).sum()

    b0 = last.bias.detach().clone()
    ext.zero_grad()
    f(b0).backward()
    g = last.bias.grad.clone()
    assert g[:9].abs().sum() > 0 and g[9:13].abs().sum() > 0 and g[13:].abs().sum() > 0  # Q, R and targets
    eps = 1e-6
    for i in (0, 4, 9, 12, 13, 20, 13 + 3 * H):
        e = torch.zeros_like(b0)
        e[i] = eps
        with torch.no_grad():
            fd = (f(b0 + e) - f(b0 - e)) / (2 * eps)
        assert float(g[i]) == pytest.approx(float(fd), rel=1e-4, abs=1e-7), i


def test_batched_equals_one_by_one_and_warm_start_does_not_change_the_action(task):
    obs = _obs(task, 5, seed=4)
    ext = _head(task)
    with torch.no_grad():
        ext.net[-1].bias.normal_(0, 0.5, generator=torch.Generator().manual_seed(5))
        a, _ = ext.act_and_plan(obs)
        single = torch.cat([ext.act_and_plan(obs[i:i + 1])[0] for i in range(5)])
    torch.testing.assert_close(a, single, rtol=0, atol=1e-10)
    warm = _head(task, warm_start=True)
    warm.load_state_dict(ext.state_dict())
    with torch.no_grad():
        a0, plan = warm.act_and_plan(torch.cat([obs, torch.zeros(5, H * 4, dtype=obs.dtype)], -1))
        a1, _ = warm.act_and_plan(torch.cat([obs, plan], -1))  # warm-started from a (different) plan
        noise = torch.rand(5, H * 4, generator=torch.Generator().manual_seed(6), dtype=obs.dtype) * 2 - 1
        a2, _ = warm.act_and_plan(torch.cat([obs, noise], -1))
    assert plan.shape == (5, H * 4) and bool((plan.abs() <= 1).all())
    torch.testing.assert_close(a0, a, rtol=0, atol=1e-8)
    torch.testing.assert_close(a1, a, rtol=0, atol=1e-8)
    torch.testing.assert_close(a2, a, rtol=0, atol=1e-8)


def test_a_bad_observation_is_contained(task):
    obs = _obs(task, 4, seed=7)
    ext = _head(task)
    with torch.no_grad():
        good, _ = ext.act_and_plan(obs)
        bad = obs.clone()
        bad[1, 0] = float("nan")
        a, _ = ext.act_and_plan(bad)
    assert int(ext.nonfinite_actions) == 4  # the four controls of element 1
    assert bool((a[1] == 0).all())
    torch.testing.assert_close(a[[0, 2, 3]], good[[0, 2, 3]], rtol=0, atol=1e-10)


def test_ppo_log_probabilities_are_consistent_and_training_moves_the_cost(task):
    model = make_mpc_ppo(task, num_envs=2, n_steps=8, batch_size=16, n_epochs=1, seed=0,
                         policy_kwargs={"horizon": H, "per_step": True})
    pol = model.policy
    assert isinstance(pol, MPCActorCriticPolicy) and isinstance(pol.mlp_extractor, ErrorStateMPCExtractor)
    obs = _obs(task, 4, seed=8, dtype=torch.float32)
    with torch.no_grad():
        actions, _, logp = pol(obs)
        _, logp2, _ = pol.evaluate_actions(obs, actions)
    torch.testing.assert_close(logp2, logp, rtol=0, atol=1e-5)
    before = pol.mlp_extractor.net[-1].weight.detach().clone()
    model.learn(16)
    assert not torch.equal(pol.mlp_extractor.net[-1].weight, before)
    assert int(pol.mlp_extractor.nonfinite_actions) == 0
    assert np.isfinite(pol.mlp_extractor.net[-1].weight.detach().numpy()).all()


def test_wrong_features_and_task_are_refused(task):
    with pytest.raises(ValueError, match="features of size"):
        ErrorStateMPCExtractor(task, task.obs_dim + 1, horizon=H)
    with pytest.raises(TypeError, match="QuadrotorTrack"):
        ErrorStateMPCExtractor(make_task("PendulumSwingUp"), 3, horizon=H)


def test_quadrotor_head_agent_reloads_safely(task, tmp_path):
    from learning import baselines as bl

    pk = {"task": task.name, "horizon": H, "per_step": True}
    res = bl.train("ppo", task, 16, seed=0, eval_every=16, eval_episodes=1, out_dir=tmp_path,
                   params={"n_envs": 2, "n_steps": 8, "batch_size": 16, "n_epochs": 1},
                   policy="MPCActorCriticPolicy", policy_kwargs=pk, tensorboard=False)
    with torch.no_grad():
        g = torch.Generator().manual_seed(9)
        res.model.policy.mlp_extractor.net[-1].bias.normal_(0, 0.5, generator=g)
    bl.save_agent(res, tmp_path)
    loaded = bl.load_agent(tmp_path)
    obs = _obs(task, 3, seed=10, dtype=torch.float32).numpy()
    np.testing.assert_array_equal(loaded.predict(obs, deterministic=True)[0],
                                  res.model.predict(obs, deterministic=True)[0])
