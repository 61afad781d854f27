"""The MPC head's warm start carried in the observation (learning.mpc_warmstart) and its per-step cost map
(learning.mpc_policy.LearnedTaskCost(per_step=True)): the untrained policy is the warm-started task MPC,
PPO's recomputed log-probabilities equal the rollout's, gradients reach the cost network (implicit ==
finite differences), and misuse is an error."""

import math

import numpy as np
import pytest
import torch

from controllers.costs import PeriodicQuadraticCost, QuadraticCost
from controllers.ilqr import ILQROptions
from controllers.mpc import MPCPolicy, MPCState
from learning.envs.single import make_task
from learning.mpc_policy import LearnedTaskCost, MPCExtractor
from learning.mpc_warmstart import PlanInObservation, WarmStartMPCPPO, make_warm_mpc_ppo

H, IT = 8, 3  # short horizon, few iterations: fast tests
PK = dict(horizon=H, max_iter=IT, compile=False)


def _model(task="CartPoleSwingUp", num_envs=4, **kw):
    return make_warm_mpc_ppo(task, num_envs=num_envs, n_steps=16, batch_size=64, n_epochs=1, seed=0,
                             policy_kwargs={**PK, **kw})


def _perturb(net: torch.nn.Module, scale: float = 0.3, seed: int = 1) -> None:
    """Move a cost network off its zero output layer (a 'trained' policy)."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        net[-1].weight.copy_(scale * torch.randn(net[-1].weight.shape, generator=g))
        net[-1].bias.copy_(scale * torch.randn(net[-1].bias.shape, generator=g))


def _reference_mpc(task, dtype=torch.float32) -> MPCPolicy:
    """The task's MPC built here from ``task.mpc_cost``: angles compared modulo 2π with the target."""
    c = task.mpc_cost(H, dtype=dtype)
    mask = torch.zeros(task.n, dtype=torch.bool)
    mask[1] = True  # the cart-pole's angle

    class Cost(torch.nn.Module):
        def forward(self, obs):
            return PeriodicQuadraticCost(QuadraticCost(Q=c.Q, R=c.R, x_ref=c.x_ref), mask)

    umax = torch.tensor(task.u_max(), dtype=dtype)
    return MPCPolicy(task.system, H, Cost(), u_lower=-umax, u_upper=umax, grad="none",
                     options=ILQROptions(max_iter=IT))


def _features(task, N: int, seed: int = 0) -> torch.Tensor:
    """``[observation, plan]`` (float32): states around upright (unsaturated actions), random plans."""
    g = torch.Generator().manual_seed(seed)
    x = torch.tensor([0.0, math.pi, 0.0, 0.0]) + 0.2 * torch.randn(N, task.n, generator=g)
    plan = 0.3 * torch.randn(N, H * task.m, generator=g)
    return torch.cat([task.observe(x), plan], -1)


@pytest.mark.parametrize("per_step", [False, True])
def test_untrained_warm_started_head_is_the_warm_started_task_mpc(per_step):
    task = make_task("CartPoleSwingUp")
    ex = MPCExtractor(task, task.obs_dim + H, horizon=H, max_iter=IT, compile=False, warm_start=True,
                      per_step=per_step)
    f = _features(task, 6)
    with torch.no_grad():
        a, plan = ex.act_and_plan(f)
        x = task.state_from_obs(f[:, :5])
        x[:, 1] = torch.remainder(x[:, 1], 2 * math.pi)  # within ±π of the target π
        umax = torch.tensor(task.u_max())
        warm = MPCState(u=f[:, 5:, None] * umax, converged=torch.zeros(6, dtype=torch.bool),
                        iterations=torch.zeros(6, dtype=torch.int64))
        ref = _reference_mpc(task)
        u, nxt = ref(x, warm)
        u_cold, _ = ref(x)
    torch.testing.assert_close(a, u / umax, rtol=0, atol=1e-5)
    torch.testing.assert_close(plan, (nxt.u / umax).clamp(-1, 1).flatten(-2), rtol=0, atol=1e-5)
    assert float((u - u_cold).abs().max()) > 1e-3  # the warm start does change the (unconverged) solve
    assert bool((a.abs() < 0.999).any())


def test_per_step_cost_map_shapes_zero_init_and_formula():
    task = make_task("CartPoleSwingUp")
    n, m = task.n, task.m
    cm = LearnedTaskCost(task, H, [16], per_step=True).double()
    assert cm.n_out == 2 * (H + 1) * n + H * m
    x = torch.tensor([[0.1, 2.0, 0.0, 0.3], [0.0, 3.0, -0.2, 0.1], [0.2, -1.0, 0.1, 0.0]],
                     dtype=torch.float64)
    b32 = task.mpc_cost(H, dtype=torch.float32)  # the buffers are float32 (SB3's dtype), here cast up
    base = QuadraticCost(Q=b32.Q.double(), R=b32.R.double(), x_ref=b32.x_ref.double())
    c0 = cm(x).base
    torch.testing.assert_close(c0.Q, base.Q.expand(3, H + 1, n, n), rtol=0, atol=0)  # zero init: the task's
    torch.testing.assert_close(c0.R.expand(3, H, m, m), base.R.expand(3, H, m, m), rtol=0, atol=0)
    torch.testing.assert_close(c0.x_ref.expand(3, H + 1, n), base.x_ref.expand(3, H + 1, n), rtol=0, atol=0)
    _perturb(cm.net)
    qs, rs, tg = cm.parameters_from_obs(task.observe(x))
    assert qs.shape == (3, H + 1, n) and rs.shape == (3, H, m) and tg.shape == (3, H + 1, n)
    c = cm(x).base
    for b in range(3):
        for t in (0, H // 2, H):
            D = torch.diag(qs[b, t].sqrt())
            torch.testing.assert_close(c.Q[b, t], D @ base.Q[t] @ D)
        for t in (0, H - 1):
            torch.testing.assert_close(c.R[b, t], rs[b, t] * base.R.reshape(m, m))
    assert float((c.Q[:, 0] - c.Q[:, H // 2]).detach().abs().max()) > 1e-3  # weights vary along the horizon
    assert float((c.x_ref[:, 0] - c.x_ref[:, -1]).detach().abs().max()) > 1e-3
    rho, delta = cm.log_scale_range, cm.target_offset
    assert bool((qs.log().abs() <= rho + 1e-12).all())
    assert bool(((tg - cm.x_ref0).abs() <= delta + 1e-12).all())


def test_implicit_gradient_of_the_warm_started_per_step_head_equals_finite_differences():
    """d(action)/d(cost network output bias), float64, converged solves near upright (pendulum), against
    central differences on a spread of the per-step outputs (Q at t = 0 and T, R, targets)."""
    task = make_task("PendulumSwingUp")
    T = 6
    ex = MPCExtractor(task, task.obs_dim + T, horizon=T, options=ILQROptions(max_iter=200), warm_start=True,
                      per_step=True, terminal_factor=1.0).double()
    _perturb(ex.mpc.cost.net, 0.1, seed=4)
    x = torch.tensor([[math.pi + 0.02, 0.03], [math.pi - 0.01, -0.04]], dtype=torch.float64)
    f = torch.cat([task.observe(x), 0.01 * torch.ones(2, T, dtype=torch.float64)], -1)
    bias = ex.mpc.cost.net[-1].bias
    a = ex.forward_actor(f)
    assert bool((a.abs() < 0.99).all())
    J = torch.stack([torch.autograd.grad(a[i, 0], bias, retain_graph=True)[0] for i in range(2)])
    assert float(J.abs().max()) > 1e-3
    n, m = task.n, task.m
    K = (T + 1) * n  # outputs: s_q (K), then s_r (T·m), then s_t (K)
    idx = [0, 1, T * n, T * n + 1, K, K + T * m - 1, K + T * m, K + T * m + T * n + 1]  # t = 0 and the last
    h = 1e-6
    for j in idx:
        with torch.no_grad():
            bias[j] += h
            ap = ex.forward_actor(f)
            bias[j] -= 2 * h
            am = ex.forward_actor(f)
            bias[j] += h
        torch.testing.assert_close(J[:, j], (ap - am)[:, 0] / (2 * h), rtol=1e-5, atol=1e-7)


def _collect(model) -> None:
    """One rollout of ``n_steps`` into the model's buffer (what ``PPO.learn`` does first)."""
    total, cb = model._setup_learn(model.n_steps * model.n_envs, callback=None)
    cb.on_training_start(locals(), globals())
    model.collect_rollouts(model.env, cb, model.rollout_buffer, n_rollout_steps=model.n_steps)


@pytest.mark.parametrize("per_step", [False, True])
def test_recomputed_log_probs_equal_the_rollouts(per_step):
    model = _model(per_step=per_step)
    _perturb(model.policy.mlp_extractor.mpc.cost.net)
    _collect(model)
    buf = model.rollout_buffer
    obs = torch.as_tensor(buf.observations.reshape(-1, buf.observations.shape[-1]))
    acts = torch.as_tensor(buf.actions.reshape(-1, 1))
    with torch.no_grad():
        _, logp, _ = model.policy.evaluate_actions(obs, acts)
        plans = obs[:, 5:].clone()
        obs[:, 5:] = 0.0  # the same states, cold: another policy
        _, logp_cold, _ = model.policy.evaluate_actions(obs, acts)
    ref = torch.as_tensor(buf.log_probs.reshape(-1))
    torch.testing.assert_close(logp, ref, rtol=0, atol=1e-4)
    assert float((logp_cold - ref).abs().max()) > 1e-2  # the carried plan is what makes them equal
    # the plan of step k+1 is the one of step k's solve, shifted: its first H-1 controls continue it
    P = plans.reshape(model.n_steps, model.n_envs, H)
    first = torch.as_tensor(buf.episode_starts[0]).bool()
    assert bool(first.all()) and float(P[0].abs().max()) == 0.0  # a cold start after the reset
    assert float(P[1:].abs().max()) > 0 and float(P[1:].abs().max()) <= 1.0


def test_evaluation_adapter_keeps_and_resets_plans():
    from learning.evaluate import evaluate

    model = _model(num_envs=2)
    task = make_task("CartPoleSwingUp")
    obs = _features(task, 3)[:, :5]
    ex = model.policy.mlp_extractor
    model.reset()
    a1 = model.act(obs)
    a2 = model.act(obs)
    with torch.no_grad():
        b1, p1 = ex.act_and_plan(torch.cat([obs, torch.zeros(3, H)], -1))
        b2, _ = ex.act_and_plan(torch.cat([obs, p1], -1))
    torch.testing.assert_close(a1, b1, rtol=0, atol=0)
    torch.testing.assert_close(a2, b2, rtol=0, atol=0)
    model.reset(torch.tensor([True, False, False]))
    torch.testing.assert_close(model._eval_plan[0], torch.zeros(H), rtol=0, atol=0)
    assert float(model._eval_plan[1:].abs().max()) > 0
    r = evaluate(model, task, num_envs=2, max_episode_steps=10, dtype=torch.float32, progress=False,
                 timing_batch1=False)
    assert all(e == "" for e in r.errors) and np.isfinite(r.returns).all()


def test_save_load_round_trip(tmp_path):
    model = _model(per_step=True)
    _perturb(model.policy.mlp_extractor.mpc.cost.net)
    f = _features(make_task("CartPoleSwingUp"), 5).numpy()
    a, _ = model.predict(f, deterministic=True)
    model.save(tmp_path / "m.zip")
    loaded = WarmStartMPCPPO.load(tmp_path / "m.zip", device="cpu")
    assert loaded.policy.warm_start and loaded.policy.per_step
    b, _ = loaded.predict(f, deterministic=True)
    assert (a == b).all()


def test_misuse_is_an_error():
    from learning.sb3 import SB3VecEnv

    task = make_task("CartPoleSwingUp")
    with pytest.raises(ValueError, match="plan"):
        MPCExtractor(task, task.obs_dim, horizon=H, warm_start=True, compile=False)
    env = PlanInObservation(SB3VecEnv(task, 2), H, 1)
    env.reset()
    with pytest.raises(RuntimeError, match="attach"):
        env.step(np.zeros((2, 1), dtype=np.float32))
    plain = make_warm_mpc_ppo(task, num_envs=2, n_steps=16, batch_size=32, policy_kwargs=PK)
    env.attach(plain.policy)
    env.step_async(np.zeros((2, 1), dtype=np.float32))
    with pytest.raises(RuntimeError, match="rollout call"):  # no rollout call produced a plan
        env.step_wait()
    from learning.mpc_policy import make_mpc_ppo

    with pytest.raises(ValueError, match="warm_start=True"):
        env.attach(make_mpc_ppo(task, num_envs=2, n_steps=16, batch_size=32, policy_kwargs=PK).policy)
    with pytest.raises(ValueError, match="PlanInObservation"):
        WarmStartMPCPPO("MlpPolicy", SB3VecEnv(task, 2), n_steps=16, batch_size=32)


def test_baselines_train_a_warm_started_head_and_reload_it_safely(tmp_path):
    """``learning.baselines`` wraps the env and picks WarmStartMPCPPO for ``warm_start``; the saved agent
    (policy.pt + agent.json, no pickle) reloads with the same plans and actions."""
    from learning import baselines as bl

    task = make_task("CartPoleSwingUp")
    pk = {"task": task.name, **PK, "warm_start": True, "per_step": True}
    res = bl.train("ppo", task, 32, seed=0, eval_every=32, eval_episodes=1, out_dir=tmp_path,
                   params={"n_envs": 2, "n_steps": 16, "batch_size": 32, "n_epochs": 1},
                   policy="MPCActorCriticPolicy", policy_kwargs=pk, tensorboard=False)
    assert isinstance(res.model, WarmStartMPCPPO)
    _perturb(res.model.policy.mlp_extractor.mpc.cost.net)
    bl.save_agent(res, tmp_path)
    loaded = bl.load_agent(tmp_path)
    assert isinstance(loaded, WarmStartMPCPPO) and loaded.policy.warm_start and loaded.policy.per_step
    obs = task.observe(task.initial_state(torch.rand(3, 4, generator=torch.Generator().manual_seed(2))))
    for model in (res.model, loaded):
        model.reset()
    for _ in range(3):  # the plans carried between calls stay equal too
        torch.testing.assert_close(loaded.act(obs.float()), res.model.act(obs.float()), rtol=0, atol=0)


@pytest.mark.parametrize("algo, policy", [("sac", "MPCActorCriticPolicy"), ("ppo", "MlpPolicy")])
def test_baselines_refuse_warm_start_without_the_mpc_head_and_ppo(algo, policy):
    from learning import baselines as bl

    with pytest.raises(ValueError, match="warm_start=True needs PPO with MPCActorCriticPolicy"):
        bl.make_agent(algo, "CartPoleSwingUp", params={"n_envs": 2}, policy=policy,
                      policy_kwargs={"task": "CartPoleSwingUp", "warm_start": True})
