"""The MPC-headed SB3 policy (learning.mpc_policy): the untrained policy is the task's MPC, any batch size,
gradients into the cost network, no hidden state, PPO runs, save/load."""

import math

import pytest
import torch
from stable_baselines3 import PPO

from controllers.costs import PeriodicQuadraticCost, QuadraticCost
from controllers.ilqr import ILQROptions
from controllers.mpc import MPCPolicy
from learning.envs.single import make_task
from learning.mpc_policy import DEFAULT_TERMINAL_FACTOR, MPCActorCriticPolicy, make_mpc_ppo

H, IT = 10, 3  # short horizon, few iterations: fast tests
PK = dict(horizon=H, max_iter=IT)



def _model(task="PendulumSwingUp", **kw):
    return make_mpc_ppo(task, num_envs=2, n_steps=64, batch_size=64, n_epochs=1, seed=0,
                        policy_kwargs={**PK, **kw})


def _obs(task_name: str, N: int, seed: int = 0, near_goal: bool = True) -> torch.Tensor:
    """Observations (float32) of states around the goal (unsaturated MPC actions) and at random."""
    task = make_task(task_name)
    g = torch.Generator().manual_seed(seed)
    x = task.initial_state(torch.rand(N, task.n_noise, generator=g, dtype=torch.float64))
    if near_goal:
        ref = task.mpc_cost(H).x_ref.reshape(-1, task.n)[-1]
        x = ref + 0.3 * torch.randn(N, task.n, generator=g, dtype=torch.float64)
    return task.observe(x).float()


def _perturb(policy: MPCActorCriticPolicy, scale: float = 0.3, seed: int = 1) -> None:
    """Move the cost network off its zero output layer (a 'trained' policy)."""
    g = torch.Generator().manual_seed(seed)
    last = policy.mlp_extractor.mpc.cost.net[-1]
    with torch.no_grad():
        last.weight.copy_(scale * torch.randn(last.weight.shape, generator=g))
        last.bias.copy_(scale * torch.randn(last.bias.shape, generator=g))


class _TaskCostPeriodic(torch.nn.Module):
    """The reference cost built here from ``task.mpc_cost``: the angle compared modulo 2π with the target,
    the terminal weight ``factor`` times the running one (None: the task's)."""

    def __init__(self, task, horizon, angle, factor):
        super().__init__()
        c = task.mpc_cost(horizon, dtype=torch.float32)
        Q = c.Q.expand(horizon + 1, task.n, task.n).clone()
        if factor is not None:
            Q[-1] = factor * Q[-2]
        self.base = QuadraticCost(Q=Q, R=c.R, x_ref=c.x_ref, u_ref=c.u_ref)
        self.mask = torch.zeros(task.n, dtype=torch.bool)
        self.mask[angle] = True

    def forward(self, obs):
        return PeriodicQuadraticCost(self.base, self.mask)


@pytest.mark.parametrize("name", ["PendulumSwingUp", "CartPoleSwingUp"])
def test_untrained_policy_is_the_task_mpc(name):
    model = _model(name)
    task = make_task(name)
    obs = torch.cat([_obs(name, 6), _obs(name, 4, near_goal=False)])
    with torch.no_grad():
        a = model.policy._predict(obs, deterministic=True)
    umax = torch.tensor(task.u_max(), dtype=torch.float32)
    angle = {"PendulumSwingUp": 0, "CartPoleSwingUp": 1}[name]
    factor = DEFAULT_TERMINAL_FACTOR.get(name)
    assert model.policy.terminal_factor == factor
    ref = MPCPolicy(task.system, H, _TaskCostPeriodic(task, H, angle, factor), u_lower=-umax, u_upper=umax,
                    grad="none", options=ILQROptions(max_iter=IT))
    x = task.state_from_obs(obs)
    c = task.mpc_cost(H).x_ref.reshape(-1)
    ang = torch.zeros(task.n, dtype=torch.bool)
    ang[angle] = True  # the angle, taken around the target
    x = torch.where(ang, torch.remainder(x - c.float() + math.pi, 2 * math.pi) - math.pi + c.float(), x)
    u, _ = ref(x)
    assert a.dtype == torch.float32
    torch.testing.assert_close(a, u / umax, rtol=0, atol=1e-4)
    assert bool((a.abs() < 0.999).any())  # not all saturated: the comparison means something


def test_untrained_head_swings_the_pendulum_up_statelessly():
    """The MPC head with its defaults (horizon 20, 5 cold iLQR iterations per call, float32, no memory
    between calls) solves the swing-up from the held-out initial states: the periodic cost is what makes a
    stateless MPC work (with a plain quadratic one the branch of the angle flips at the bottom)."""
    from learning.evaluate import evaluate

    model = make_mpc_ppo("PendulumSwingUp", num_envs=2, n_steps=64, batch_size=64, seed=0)
    assert model.policy.horizon == 20 and model.policy.max_iter == 5
    r = evaluate(model, "PendulumSwingUp", num_envs=8, seed=1_000_000, dtype=torch.float32, progress=False,
                 timing_batch1=False)
    assert bool(r.success.all()), r.final_error
    assert float(r.returns.mean()) > -200, r.returns  # the tuned PPO of BENCHMARKS.md: -147 over 32 episodes


def test_implicit_gradient_of_the_action_equals_finite_differences():
    """d(action)/d(cost network output bias) through the periodic cost and the implicit iLQR gradient,
    float64, converged solves on unsaturated states, against central differences."""
    from learning.mpc_policy import MPCExtractor

    task = make_task("PendulumSwingUp")
    ex = MPCExtractor(task, task.obs_dim, horizon=12, options=ILQROptions(max_iter=200), terminal_factor=1.0)
    ex = ex.double()
    g = torch.Generator().manual_seed(4)
    with torch.no_grad():
        ex.mpc.cost.net[-1].weight.copy_(0.1 * torch.randn(ex.mpc.cost.net[-1].weight.shape, generator=g))
    x = torch.tensor([[math.pi + 0.02, 0.03], [math.pi - 0.01, -0.04], [-math.pi + 0.015, 0.02]],
                     dtype=torch.float64)
    obs = task.observe(x)  # the third is the first turn's upright, seen from the other branch
    bias = ex.mpc.cost.net[-1].bias
    a = ex.forward_actor(obs)
    assert bool((a.abs() < 0.99).all())
    J = torch.stack([torch.autograd.grad(a[i, 0], bias, retain_graph=True)[0] for i in range(3)])
    assert float(J.abs().max()) > 1e-3  # the action does depend on the cost network
    h = 1e-6
    for j in range(bias.numel()):
        with torch.no_grad():
            bias[j] += h
            ap = ex.forward_actor(obs)
            bias[j] -= 2 * h
            am = ex.forward_actor(obs)
            bias[j] += h
        fd = (ap - am)[:, 0] / (2 * h)
        torch.testing.assert_close(J[:, j], fd, rtol=1e-5, atol=1e-7)


def test_a_nonfinite_mpc_action_is_replaced_and_counted():
    """A NaN observation makes that element's solve fail: its action is 0 (PPO's Gaussian stays finite),
    the others equal their solve alone, and the replacement is counted, not silent."""
    from learning.mpc_policy import MPCExtractor

    task = make_task("PendulumSwingUp")
    ex = MPCExtractor(task, task.obs_dim, horizon=8).double()
    obs = task.observe(torch.tensor([[0.3, 0.0], [1.0, 0.5]], dtype=torch.float64))
    bad = torch.cat([obs[:1], torch.full_like(obs[:1], math.nan), obs[1:]])
    assert int(ex.nonfinite_actions) == 0
    a = ex.forward_actor(bad)
    assert a[1].tolist() == [0.0] * task.m and int(ex.nonfinite_actions) == task.m
    torch.testing.assert_close(a[[0, 2]], ex.forward_actor(obs), rtol=0, atol=1e-12)


def test_any_batch_size_batched_equals_loop():
    model = _model()
    _perturb(model.policy)
    obs = torch.cat([_obs("PendulumSwingUp", 40), _obs("PendulumSwingUp", 24, near_goal=False)])
    with torch.no_grad():
        loop = torch.cat([model.policy._predict(o[None], deterministic=True) for o in obs])
        for B in (1, 7, 64):
            a = model.policy._predict(obs[:B], deterministic=True)
            assert a.shape == (B, 1)
            torch.testing.assert_close(a, loop[:B], rtol=0, atol=1e-4)


def test_ppo_loss_gradients_reach_the_cost_network():
    model = _model()
    pol = model.policy
    obs = _obs("PendulumSwingUp", 16)
    actions = torch.zeros(16, 1)
    adv = torch.randn(16, generator=torch.Generator().manual_seed(0))
    values, log_prob, entropy = pol.evaluate_actions(obs, actions)
    loss = -(adv * log_prob).mean() + 0.5 * values.pow(2).mean() - 0.01 * entropy.mean()
    pol.optimizer.zero_grad()
    loss.backward()
    grads = {n: p.grad for n, p in pol.named_parameters() if "mpc.cost.net" in n}
    assert grads and all(g is not None and bool(torch.isfinite(g).all()) for g in grads.values())
    assert float(grads["mlp_extractor.mpc.cost.net.4.weight"].abs().sum()) > 0
    # the cost network's parameters are in the (rebuilt) optimizer
    opt_ids = {id(p) for grp in pol.optimizer.param_groups for p in grp["params"]}
    assert all(id(p) in opt_ids for p in pol.parameters())
    assert isinstance(pol.action_net, torch.nn.Identity)


def test_unrolled_gradients_flow_too():
    model = _model(grad="unrolled")
    obs = _obs("PendulumSwingUp", 8)
    _, log_prob, _ = model.policy.evaluate_actions(obs, torch.zeros(8, 1))
    log_prob.sum().backward()
    g = model.policy.mlp_extractor.mpc.cost.net[-1].weight.grad
    assert g is not None and bool(torch.isfinite(g).all()) and float(g.abs().sum()) > 0


def test_evaluate_actions_has_no_hidden_state():
    model = _model()
    _perturb(model.policy)
    obs = _obs("PendulumSwingUp", 12, near_goal=False)
    acts = torch.rand(12, 1, generator=torch.Generator().manual_seed(2)) * 2 - 1
    with torch.no_grad():
        first = model.policy.evaluate_actions(obs, acts)
        model.policy._predict(_obs("PendulumSwingUp", 5, seed=3), deterministic=False)  # an unrelated call
        second = model.policy.evaluate_actions(obs, acts)
    for u, v in zip(first, second):
        assert torch.equal(u, v)


def test_tiny_ppo_learn_save_load(tmp_path):
    model = _model()
    model.learn(total_timesteps=256)
    obs = _obs("PendulumSwingUp", 5, near_goal=False).numpy()
    a, _ = model.predict(obs, deterministic=True)
    assert a.shape == (5, 1) and (abs(a) <= 1).all()
    model.save(tmp_path / "m.zip")
    loaded = PPO.load(tmp_path / "m.zip", device="cpu")
    assert isinstance(loaded.policy, MPCActorCriticPolicy) and loaded.policy.horizon == H
    b, _ = loaded.predict(obs, deterministic=True)
    assert (a == b).all()
    # plain state_dict round trip
    torch.save(model.policy.state_dict(), tmp_path / "sd.pt")
    fresh = _model()
    fresh.policy.load_state_dict(torch.load(tmp_path / "sd.pt", weights_only=True))
    c, _ = fresh.predict(obs, deterministic=True)
    assert (a == c).all()


def test_rejects_what_it_cannot_do():
    with pytest.raises(ValueError, match="ortho_init"):
        _model(ortho_init=True)
    with pytest.raises(TypeError, match="QuadraticCost"):
        _model("ArmReach")
