"""MPC: receding horizon with warm start, MPCPolicy as a differentiable module with explicit state."""

from __future__ import annotations

import math

import pytest
import torch
from torch import nn

from controllers.costs import DiagonalQuadraticCost, QuadraticCost
from controllers.ilqr import ILQROptions
from controllers.mpc import MPCPolicy, MPCState, run_mpc, shift
from controllers.systems import Pendulum

D64 = torch.float64
TIGHT = ILQROptions(max_iter=100, tol=1e-12, tol_cost=0.0)



def _cost(T, dtype=D64, target=math.pi):
    return DiagonalQuadraticCost(torch.tensor([1.0, 0.1], dtype=dtype), torch.tensor([0.05], dtype=dtype),
                                 torch.tensor([target, 0.0], dtype=dtype), T)


def _policy(T=10, umax=5.0, dtype=D64, system=None, options=TIGHT):
    return MPCPolicy(system or Pendulum(dt=0.05, damping=0.1), T, _cost(T, dtype),
                     u_lower=torch.tensor(-umax, dtype=dtype), u_upper=torch.tensor(umax, dtype=dtype),
                     options=options)


def test_shift():
    u = torch.arange(6.0).view(1, 3, 2)
    torch.testing.assert_close(shift(u), torch.tensor([[[2.0, 3.0], [4.0, 5.0], [4.0, 5.0]]]))
    torch.testing.assert_close(shift(u, "zero")[0, -1], torch.zeros(2))
    with pytest.raises(ValueError, match="fill"):
        shift(u, "mean")


def test_closed_loop_stabilizes_upright_and_warm_start_saves_iterations():
    p = Pendulum(dt=0.05, damping=0.1)
    T = 15
    Q = torch.diag(torch.tensor([1.0, 0.1], dtype=D64))
    cost = QuadraticCost(Q=torch.cat([Q.expand(T, 2, 2), 10 * Q[None]]), R=torch.tensor([[0.01]], dtype=D64),
                         x_ref=torch.tensor([math.pi, 0.0], dtype=D64))
    x0 = torch.tensor([[math.pi - 0.5, 0.0], [math.pi + 0.3, 0.5]], dtype=D64)
    warm = run_mpc(p, cost, x0, T, 40, u_lower=-5.0, u_upper=5.0)
    cold = run_mpc(p, cost, x0, T, 40, u_lower=-5.0, u_upper=5.0, warm_start=False)
    assert bool(warm.converged.all())
    assert float((warm.x[:, -1, 0] - math.pi).abs().max()) < 0.05
    assert float(warm.x[:, -1, 1].abs().max()) < 0.1
    assert bool((warm.u.abs() <= 5.0 + 1e-12).all())
    # same closed loop either way (the plans converge to the same optimum), fewer iterations warm
    torch.testing.assert_close(warm.x, cold.x, atol=1e-6, rtol=0)
    assert int(warm.iterations.sum()) < int(cold.iterations.sum())


def test_policy_state_is_explicit_and_batched_equals_loop():
    pol = _policy()
    obs = torch.tensor([[math.pi - 0.3, 0.0], [math.pi + 0.2, -0.4], [math.pi, 0.1]], dtype=D64)
    before = {k: v.clone() for k, v in pol.state_dict().items()}
    attrs = set(vars(pol))
    a, s = pol(obs)
    assert a.shape == (3, 1) and isinstance(s, MPCState) and s.u.shape == (3, 10, 1)
    assert set(vars(pol)) == attrs
    for k, v in pol.state_dict().items():
        torch.testing.assert_close(v, before[k])
    a2, _ = pol(obs)  # no hidden warm start: the same call gives the same action
    torch.testing.assert_close(a2, a)
    a3, _ = pol(obs, s)  # warm-started from the returned (shifted) plan: same optimum
    torch.testing.assert_close(a3, a, atol=1e-8, rtol=0)
    for b in range(3):
        ab, _ = pol(obs[b:b + 1])
        torch.testing.assert_close(ab, a[b:b + 1], atol=1e-10, rtol=0)


def test_policy_gradients_match_finite_differences():
    pol = _policy(umax=50.0)
    obs = torch.tensor([[math.pi - 0.3, 0.2], [math.pi + 0.2, -0.4]], dtype=D64)
    a, s = pol(obs)
    assert bool(s.converged.all())
    w = torch.tensor([[1.0], [-0.5]], dtype=D64)
    loss = (a * w).sum()
    params = dict(pol.named_parameters())
    grads = torch.autograd.grad(loss, list(params.values()))
    h = 1e-6
    for (name, p), g in zip(params.items(), grads):
        for i in range(p.numel()):
            with torch.no_grad():
                p.view(-1)[i] += h
                lp = float((pol(obs)[0] * w).sum())
                p.view(-1)[i] -= 2 * h
                lm = float((pol(obs)[0] * w).sum())
                p.view(-1)[i] += h
            fd = (lp - lm) / (2 * h)
            gi = float(g.view(-1)[i])
            assert abs(gi - fd) < 1e-5 * max(1.0, abs(fd)), (name, i, gi, fd)


def test_dynamics_parameter_is_registered_and_differentiable():
    length = nn.Parameter(torch.tensor(1.0, dtype=D64))
    pol = _policy(system=Pendulum(length=length, dt=0.05, damping=0.1), umax=50.0)
    assert any(p is length for p in pol.parameters())
    a, _ = pol(torch.tensor([[math.pi - 0.3, 0.2]], dtype=D64))
    a.sum().backward()
    assert length.grad is not None and float(length.grad.abs()) > 0


def test_as_action_head_of_a_network_trains():
    # an encoder maps a raw observation [cos θ, sin θ, ω] to the state the MPC head plans from; encoder and
    # MPC parameters are trained together to imitate a teacher MPC with another target
    torch.manual_seed(0)
    opts = ILQROptions(max_iter=50)
    teacher = MPCPolicy(Pendulum(dt=0.05, damping=0.1), 8, _cost(8, target=2.5), options=opts)
    student = _policy(T=8, umax=50.0, options=opts)
    enc = nn.Linear(3, 2).double()
    model = nn.ModuleDict({"enc": enc, "mpc": student})
    th = torch.linspace(1.5, 3.5, 12, dtype=D64)
    om = torch.linspace(-0.5, 0.5, 12, dtype=D64)
    x = torch.stack([th, om], -1)
    raw = torch.stack([torch.cos(th), torch.sin(th), om], -1)
    with torch.no_grad():
        target_a, _ = teacher(x)
        enc.weight.copy_(torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=D64))
        enc.bias.copy_(torch.tensor([math.pi, 0.0], dtype=D64))

    def loss_fn():
        a, _ = student(enc(raw))
        return ((a - target_a) ** 2).mean()

    opt = torch.optim.Adam(model.parameters(), lr=0.05)
    first = float(loss_fn().detach())
    for _ in range(15):
        opt.zero_grad()
        loss = loss_fn()
        loss.backward()
        assert enc.weight.grad is not None and student.cost.target.grad is not None
        opt.step()
    assert float(loss_fn().detach()) < 0.5 * first


def test_dtype_device_and_bad_input():
    pol = _policy(dtype=torch.float32, options=None)
    a, _ = pol(torch.tensor([[math.pi - 0.3, 0.0]]))
    assert a.dtype == torch.float32
    pol64 = pol.to(D64)
    assert pol64.cost.q_raw.dtype == D64 and pol64.u_lower.dtype == D64
    with pytest.raises(TypeError, match="dtype"):
        pol64(torch.zeros(1, 2))
    with pytest.raises(ValueError, match=r"obs must have shape \(\*B, 2\)"):
        pol64(torch.zeros(1, 3, dtype=D64))
    with pytest.raises(ValueError, match="positive"):
        DiagonalQuadraticCost(torch.tensor([1.0, -1.0]), torch.tensor([1.0]), torch.zeros(2), 5)
    with pytest.raises(TypeError, match="argument 'cost' must be an nn.Module"):
        MPCPolicy(Pendulum(), 5, QuadraticCost(torch.eye(2), torch.eye(1)))
    st = pol64.initial_state(4)
    assert st.u.shape == (4, 10, 1)


class GoalCost(nn.Module):
    """A cost module that reads its target from the observation: obs = [θ, ω, θ_goal] -> plan on [θ, ω]."""

    def __init__(self, T):
        super().__init__()
        self.T = T
        self.log_q = nn.Parameter(torch.zeros(2, dtype=D64))

    def forward(self, obs):
        w = torch.cat([self.log_q.exp() * torch.tensor([1.0, 0.1], dtype=D64), torch.zeros(1, dtype=D64)])
        goal = torch.stack([obs[..., 2], torch.zeros_like(obs[..., 2]), obs[..., 2]], -1)  # (*B, 3)
        return QuadraticCost(Q=torch.diag_embed(w).expand(self.T + 1, 3, 3),
                             R=torch.tensor([[0.05]], dtype=D64), x_ref=goal.unsqueeze(-2), check=False)


class GoalPendulum(Pendulum):
    """The pendulum with the goal carried along in the state (constant), so the observation is the state."""

    n = 3

    def step(self, x, u, t=0):
        return torch.cat([super().step(x[..., :2], u, t), x[..., 2:]], -1)

    def jacobian(self, x, u, t=0):
        A, B = super().jacobian(x[..., :2], u, t)
        A3 = torch.zeros(*A.shape[:-2], 3, 3, dtype=A.dtype)
        A3[..., :2, :2] = A
        A3[..., 2, 2] = 1.0
        return A3, torch.cat([B, torch.zeros(*B.shape[:-2], 1, 1, dtype=B.dtype)], -2)


def test_any_cost_module_goal_conditioned_matches_a_fixed_cost_per_element():
    """A cost module whose target comes from the observation: each element equals the policy with that
    element's goal as a fixed cost, and the module's parameters get gradients."""
    T = 8
    sys3 = GoalPendulum(dt=0.05, damping=0.1)
    pol = MPCPolicy(sys3, T, GoalCost(T), u_lower=-5.0 * torch.ones(1, dtype=D64),
                    u_upper=5.0 * torch.ones(1, dtype=D64), options=TIGHT)
    obs = torch.tensor([[2.9, 0.0, math.pi], [0.1, 0.2, 0.5]], dtype=D64)
    a, _ = pol(obs)
    for i in range(2):
        fixed = MPCPolicy(Pendulum(dt=0.05, damping=0.1), T, _cost(T, target=float(obs[i, 2])),
                          u_lower=-5.0 * torch.ones(1, dtype=D64), u_upper=5.0 * torch.ones(1, dtype=D64),
                          options=TIGHT)
        with torch.no_grad():
            fixed.cost.q_raw.copy_(torch.log(torch.expm1(torch.tensor([1.0, 0.1], dtype=D64))))
            fixed.cost.terminal_factor = 1.0
        ai, _ = fixed(obs[i:i + 1, :2])
        torch.testing.assert_close(a[i:i + 1], ai, atol=1e-8, rtol=0)
    a.sum().backward()
    assert pol.cost.log_q.grad is not None and bool(torch.isfinite(pol.cost.log_q.grad).all())


def test_state_reset_of_selected_elements_and_batch_shapes():
    """A vector env resets the elements whose episode ended: their warm start is cold again, the others'
    is kept; the initial state takes a batch shape; a (2, 3) batch of observations equals the flat one."""
    pol = _policy(T=6)
    st = pol.initial_state((2, 3))
    assert st.u.shape == (2, 3, 6, 1) and st.batch_shape == (2, 3) and st.u.dtype == D64
    assert pol.initial_state(4).u.shape == (4, 6, 1)
    obs = math.pi + 0.2 * torch.randn(2, 3, 2, dtype=D64, generator=torch.Generator().manual_seed(0))
    a, s1 = pol(obs, st)
    af, _ = pol(obs.reshape(6, 2))
    torch.testing.assert_close(a.reshape(6, 1), af, atol=1e-10, rtol=0)
    done = torch.tensor([[True, False, False], [False, False, True]])
    s2 = s1.reset(done)
    assert bool((s2.u[done] == 0).all()) and torch.equal(s2.u[~done], s1.u[~done])
    assert not bool(s2.converged[done].any()) and torch.equal(s2.converged[~done], s1.converged[~done])
    assert bool((s2.iterations[done] == 0).all())
    with pytest.raises(ValueError, match="argument 'done'"):
        s1.reset(torch.zeros(3, dtype=torch.bool))
    with pytest.raises(TypeError, match="argument 'done'"):
        s1.reset(torch.zeros(2, 3))
    with pytest.raises(ValueError, match="argument 'batch_shape'"):
        MPCState.cold((2, -1), 6, 1)


def test_float_limits_take_the_policy_dtype():
    """Float limits are numbers, not tensors of the default dtype: a float64 policy under a float32 default
    dtype (and a float32 one) runs with u_lower=-2.0, u_upper=2.0; a tensor limit keeps its dtype and moves
    with .to()."""
    assert torch.get_default_dtype() == torch.float32
    for dtype in (D64, torch.float32):
        pol = MPCPolicy(Pendulum(), 5, _cost(5, dtype), u_lower=-2.0, u_upper=2.0)
        a, _ = pol(torch.full((4, 2), 0.5, dtype=dtype), pol.initial_state(4))
        assert a.dtype == dtype and bool((a.abs() <= 2.0 + 1e-6).all())
    pol = MPCPolicy(Pendulum(), 5, _cost(5, torch.float32), u_lower=torch.tensor([-2.0]), u_upper=2.0).to(D64)
    assert pol.u_lower.dtype == D64 and pol.u_upper == 2.0
    with pytest.raises(TypeError, match="argument 'u_lower'"):
        MPCPolicy(Pendulum(), 5, _cost(5), u_lower="-2")


def test_per_step_limits_are_kept_and_bad_shapes_are_named():
    """A (T, m) limit applies per step (the plan equals one with that limit as an ILQRProblem field); a
    shape that does not broadcast is a ValueError with the shape the user passed (it was flattened)."""
    T = 5
    step_hi = torch.tensor([[0.5], [1.0], [1.5], [2.0], [2.5]], dtype=D64)
    pol = MPCPolicy(Pendulum(), T, _cost(T), u_lower=-3.0, u_upper=step_hi)
    obs = torch.tensor([[0.2, 0.0], [-0.3, 0.5]], dtype=D64)
    state = pol.initial_state(2)
    a, new = pol(obs, state)
    from controllers.ilqr import ILQRProblem, ilqr

    ref = ilqr(ILQRProblem(Pendulum(), _cost(T)(obs), obs, T, u_lower=-3.0, u_upper=step_hi), grad="none")
    torch.testing.assert_close(a, ref.u[..., 0, :], rtol=0, atol=1e-9)
    with pytest.raises(ValueError, match=r"argument 'u_upper'.*\(5, 3\)"):
        MPCPolicy(Pendulum(), T, _cost(T), u_upper=torch.ones(5, 3, dtype=D64))


class _FixedCost(nn.Module):
    """A cost module without parameters or buffers: the cost follows the observation's dtype."""

    def __init__(self, T):
        super().__init__()
        self.T = T

    def forward(self, obs):
        kw = dict(dtype=obs.dtype, device=obs.device)
        return QuadraticCost(Q=torch.diag(torch.tensor([1.0, 0.1], **kw)).expand(self.T + 1, 2, 2),
                             R=torch.tensor([[0.05]], **kw),
                             x_ref=torch.tensor([math.pi, 0.0], **kw).expand(*obs.shape[:-1], 1, 2))


def test_a_policy_without_tensors_follows_the_observation_dtype():
    """No parameters and float limits: the policy has no dtype of its own, so float64 and float32
    observations both run (the same plan up to float32 resolution); a warm start of another dtype is a
    clear error, and initial_state takes the dtype asked for."""
    pol = MPCPolicy(Pendulum(), 6, _FixedCost(6), u_lower=-2.0, u_upper=2.0, options=TIGHT)
    obs = torch.tensor([[math.pi - 0.4, 0.1], [0.3, 0.0]], dtype=D64)
    st64 = pol.initial_state(2, dtype=D64)
    assert st64.u.dtype == D64
    a64, _ = pol(obs, st64)
    a32, _ = pol(obs.float(), pol.initial_state(2, dtype=torch.float32))
    assert a64.dtype == D64 and a32.dtype == torch.float32
    torch.testing.assert_close(a32.double(), a64, atol=1e-3, rtol=0)
    with pytest.raises(TypeError, match="warm start"):
        pol(obs, pol.initial_state(2, dtype=torch.float32))
    with pytest.raises(TypeError, match="argument 'dtype'"):
        _policy().initial_state(2, dtype=torch.float32)
