"""learning.evaluate / learning.policies: batched evaluation against single-env references, the MPC expert,
broken policies (NaN, exceptions, wrong shapes), the adapters and the JSON/plot outputs."""

import json
import math

import numpy as np
import pytest
import torch
from torch import nn

from learning import TaskEnv
from learning.envs.single import make_task
from learning.envs.task import angle_wrap
from learning.evaluate import EvalResult, evaluate
from learning.policies import (
    CallableAdapter,
    ModuleAdapter,
    MPCExpert,
    Policy,
    SB3Adapter,
    angle_dims,
    as_policy,
)

FIELDS = ("returns", "success", "final_error", "tracking_error", "effort", "violations", "invalid",
          "terminated", "truncated", "length")


class OpenLoop(Policy):
    """``a_t = 1.5 sin(0.3 t + 0.1)`` per element, ``t`` counted from the element's last reset (outside
    the action box half the time, so clipping is exercised)."""

    def __init__(self):
        self.k = None
        self.resets = []

    def act(self, obs):
        if self.k is None or self.k.shape[0] != obs.shape[0]:
            self.k = torch.zeros(obs.shape[0], dtype=obs.dtype)
        a = 1.5 * torch.sin(0.3 * self.k + 0.1)
        self.k = self.k + 1
        return a[:, None]

    def reset(self, done=None):
        self.resets.append(None if done is None else done.clone())
        if done is None or self.k is None:
            self.k = None
        else:
            self.k = torch.where(done, 0.0, self.k)


def feedback(obs):
    """A row-wise state feedback (batch-independent), saturating now and then."""
    return torch.tanh(obs @ torch.linspace(-0.9, 1.3, obs.shape[1], dtype=obs.dtype))[:, None] * 1.2


def reference(task_name, seed, steps, policy_of_step):
    """One episode of the single TaskEnv (float64) under ``policy_of_step(t, obs (1, d)) -> (1, m)``."""
    env = TaskEnv(task_name, dtype=torch.float64)
    task = env.task
    obs, _ = env.reset(seed=seed)
    x = torch.as_tensor(env.state)[None]
    ret, eff, viol, errs = 0.0, 0.0, 0, [float(task.error(x)[0])]
    term = trunc = invalid = False
    t = 0
    for t in range(1, steps + 1):
        a = policy_of_step(t - 1, torch.as_tensor(obs)[None]).numpy()[0]
        viol += int(np.isfinite(a).all() and (np.abs(a) > 1).any())
        obs, r, term, bad, info = env.step(a)
        u = np.clip(np.nan_to_num(a, nan=0.0, posinf=0.0, neginf=0.0), -1, 1) * np.asarray(task.u_max())
        ret += r
        eff += float((u * u).sum())
        x = torch.as_tensor(env.state)[None]
        errs.append(float(task.error(x)[0]))
        invalid = bool(info.get("invalid", False))
        if term or bad:
            break
    trunc = (not term) and (invalid or t >= steps)
    return dict(returns=ret, effort=eff, violations=viol, length=t, final_error=errs[-1],
                tracking_error=float(np.mean(errs)), terminated=term, truncated=trunc, invalid=invalid,
                success=bool(task.success(x)[0]) and not invalid)


def assert_episode(res, i, ref, tol=1e-12):
    for k, v in ref.items():
        got = getattr(res, k)[i]
        if isinstance(v, float):
            assert got == pytest.approx(v, rel=0, abs=tol), (k, i)
        else:
            assert got == v, (k, i)


def same_episodes(a, b, ia=slice(None), ib=slice(None)):
    for k in FIELDS:
        np.testing.assert_allclose(getattr(a, k)[ia], getattr(b, k)[ib], rtol=0, atol=1e-12, err_msg=k)


# ------------------------------------------------------------------------------------------------- (a)
@pytest.mark.parametrize("name", ["PendulumSwingUp", "CartPoleSwingUp"])
def test_open_loop_and_feedback_policies_equal_single_env_references(name):
    steps, seeds = 40, [5, 6, 7, 8, 9]
    ol = OpenLoop()
    res = evaluate(ol, name, num_envs=3, seeds=seeds, max_episode_steps=steps, progress=False,
                   timing_batch1=False)
    for i, s in enumerate(seeds):  # two rounds (3 + 2 environments)
        assert_episode(res, i, reference(name, s, steps, lambda t, o: 1.5 * torch.sin(
            torch.tensor([[0.3 * t + 0.1]], dtype=torch.float64))))
    assert res.violations.sum() > 0 and not res.invalid.any()
    # the policy is reset at each round, and only the environments that ended are reset within one
    masks = [d for d in ol.resets if d is not None]
    assert all(d.dtype == torch.bool for d in masks)
    assert sum(d is None for d in ol.resets) >= 2

    res = evaluate(feedback, name, num_envs=3, seeds=seeds, max_episode_steps=steps, progress=False,
                   timing_batch1=False)
    for i, s in enumerate(seeds):
        assert_episode(res, i, reference(name, s, steps, lambda t, o: feedback(o)))
    if name == "CartPoleSwingUp":  # the feedback drives some carts off the track: early terminations
        assert res.terminated.any() and (res.length < steps).any()
    assert np.isnan(res.error_curve[res.length < steps, -1]).all()


# ------------------------------------------------------------------------------------------------- (b)
def test_mpc_expert_solves_the_pendulum_and_reports_its_solver():
    from controllers.ilqr import ILQROptions, ILQRProblem
    from controllers.mpc import mpc_step

    task = make_task("PendulumSwingUp")
    expert = MPCExpert(task, horizon=40, max_iter=3)
    seen = []

    class Recorder(Policy):
        def act(self, obs):
            a = expert.act(obs)
            seen.append({k: v.clone() for k, v in expert.info().items()})
            return a

        def reset(self, done=None):
            expert.reset(done)

        def info(self):
            return expert.info()

    T = 80
    res = evaluate(Recorder(), task, num_envs=8, max_episode_steps=T, progress=False, timing_steps=3)
    assert res.success.mean() >= 0.75  # 8/8 when written
    assert (res.violations == 0).all()  # the MPC respects ±u_max: never clipped
    its = torch.stack([s["iterations"] for s in seen[:T]]).double()  # (T, 8); the rest is batch-1 timing
    conv = torch.stack([s["converged"] for s in seen[:T]])
    np.testing.assert_allclose(res.iterations, its.mean(0).numpy(), rtol=0, atol=1e-12)
    np.testing.assert_allclose(res.nonconverged, (~conv).double().mean(0).numpy(), rtol=0, atol=1e-12)
    assert ((res.iterations >= 0) & (res.iterations <= 3)).all()  # 0: the warm start was certified
    assert (res.solver_steps == T).all()
    s = res.summary()
    assert s["iterations_mean"] == pytest.approx(float(its.mean()))
    assert s["nonconverged_rate"] == pytest.approx(float((~conv).double().mean()))
    assert res.step_ms.size == T and res.step_ms_batch1.size == 3

    # the expert's first step is the solver's: mpc_step from the state, cold, in float64, u/u_max
    obs = task.observe(task.initial_state(torch.rand(4, 2, dtype=torch.float64,
                                                     generator=torch.Generator().manual_seed(5))))
    fresh = MPCExpert(task, horizon=20, max_iter=5)
    a = fresh.act(obs)
    assert a.dtype == torch.float64
    x = task.state_from_obs(obs)
    x = torch.stack([math.pi + angle_wrap(x[:, 0] - math.pi), x[:, 1]], -1)  # θ around the target π
    prob = ILQRProblem(task.system, task.mpc_cost(20), x, 20, u_lower=-2.0, u_upper=2.0)
    u, nxt, sol = mpc_step(prob, None, grad="none", options=ILQROptions(max_iter=5))
    torch.testing.assert_close(a, u / 2.0, rtol=0, atol=1e-12)
    assert torch.equal(fresh.info()["iterations"], sol.status.iterations)
    assert torch.equal(fresh.info()["converged"], sol.status.converged)
    # float32 observations are solved in float32
    assert fresh.act(obs.float()).dtype == torch.float32


def test_mpc_angle_branch_is_continuous_through_upright_and_does_not_chatter_at_hanging():
    task = make_task("PendulumSwingUp")
    expert = MPCExpert(task, horizon=5, max_iter=1)
    assert angle_dims(task) == [0] and angle_dims(make_task("CartPoleSwingUp")) == [1]

    def planned(theta):  # the θ the MPC plans from for raw angles theta (N,)
        obs = task.observe(torch.stack([theta, torch.zeros_like(theta)], -1))
        return expert._branch(task.state_from_obs(obs))[:, 0]

    # first step: the branch around the target π ([0, 2π))
    torch.testing.assert_close(planned(torch.tensor([-3.0, 0.2, 3.0], dtype=torch.float64)),
                               torch.tensor([2 * math.pi - 3.0, 0.2, 3.0], dtype=torch.float64))
    # crossing upright (π → π + 0.2, seen by state_from_obs as -π + 0.2) continues, no 2π jump
    th = planned(torch.tensor([math.pi + 0.2, -0.01, 0.01], dtype=torch.float64))
    torch.testing.assert_close(th[0], torch.tensor(math.pi + 0.2, dtype=torch.float64))
    # hanging at the cut (0 and 2π are the same pendulum) keeps its branch from step to step
    assert th[1] < 0 and planned(torch.tensor([0.0, 0.01, 0.02], dtype=torch.float64))[1] < 0.1
    # an episode that ends forgets its branch
    expert.reset(torch.tensor([True, False, False]))
    assert torch.isnan(expert._prev[0]).all() and torch.isfinite(expert._prev[1:]).all()


# ------------------------------------------------------------------------------------------------- (c)
def test_a_nan_in_one_env_ends_only_that_episode():
    name, steps, seeds, bad = "CartPoleSwingUp", 30, [0, 1, 2, 3], 2

    def broken(obs):
        a = feedback(obs)
        if obs.shape[0] == 4:
            a[bad] = math.nan if obs[bad, 0] > -10 else math.inf
        return a

    res = evaluate(broken, name, num_envs=4, seeds=seeds, max_episode_steps=steps, progress=False,
                   timing_batch1=False)
    clean = evaluate(feedback, name, num_envs=3, seeds=[0, 1, 3], max_episode_steps=steps, progress=False,
                     timing_batch1=False)
    assert res.invalid.tolist() == [False, False, True, False]
    assert res.length[bad] == 1 and res.truncated[bad] and not res.success[bad]
    assert res.errors == [""] * 4  # an invalid action is not an exception
    same_episodes(res, clean, [0, 1, 3], slice(None))
    assert res.summary()["invalid_count"] == 1


# ------------------------------------------------------------------------------------------------- (d)
def test_a_raising_policy_is_reported_not_fatal():
    calls = [0]

    def flaky(obs):
        calls[0] += 1
        if calls[0] == 5:
            raise RuntimeError("solver exploded")
        return feedback(obs)

    steps = 20
    res = evaluate(flaky, "PendulumSwingUp", num_envs=2, seeds=[10, 11, 12, 13], max_episode_steps=steps,
                   progress=False, timing_batch1=False)
    # the 5th call is in the first round: both of its episodes end there, flagged, with the message
    assert res.invalid.tolist() == [True, True, False, False]
    assert res.errors[:2] == ["RuntimeError: solver exploded"] * 2 and res.errors[2:] == ["", ""]
    assert res.length.tolist() == [4, 4, steps, steps]
    ok = evaluate(feedback, "PendulumSwingUp", num_envs=2, seeds=[12, 13], max_episode_steps=steps,
                  progress=False, timing_batch1=False)
    same_episodes(res, ok, slice(2, 4))
    assert np.isfinite(res.returns).all()

    def always(obs):
        raise ValueError("nope")

    res = evaluate(always, "PendulumSwingUp", num_envs=3, max_episode_steps=steps, progress=False)
    assert res.invalid.all() and (res.length == 0).all() and all("ValueError: nope" in e for e in res.errors)
    assert res.summary()["success_rate"] == 0.0 and res.step_ms_batch1.size == 0
    res.table()

    wrong = evaluate(lambda obs: torch.zeros(obs.shape[0], 2), "PendulumSwingUp", num_envs=2,
                     max_episode_steps=steps, progress=False, timing_batch1=False)
    assert wrong.invalid.all() and "shape" in wrong.errors[0]


# ------------------------------------------------------------------------------------------------- (e)
def _same(a, b):
    if isinstance(a, dict):
        assert a.keys() == b.keys()
        for k in a:
            _same(a[k], b[k])
    elif isinstance(b, float) and not math.isfinite(b):
        assert a is None
    elif isinstance(b, float):
        assert a == pytest.approx(b, rel=1e-15)
    else:
        assert a == b


def test_json_round_trip_table_and_plot(tmp_path):
    res = evaluate(OpenLoop(), "CartPoleSwingUp", num_envs=3, episodes=4, max_episode_steps=25,
                   progress=True, timing_steps=5)
    assert isinstance(res, EvalResult)
    p = tmp_path / "r.json"
    res.to_json(p)
    text = p.read_text()
    assert "NaN" not in text and "Infinity" not in text
    data = json.loads(text)
    s = res.summary()
    _same(data["summary"], s)  # OpenLoop gives no solver info: NaN figures become null
    assert data["summary"]["iterations_mean"] is None
    assert data["episodes"]["returns"] == pytest.approx(res.returns.tolist(), rel=1e-15)
    assert data["episodes"]["seeds"] == [0, 1, 2, 3]
    assert len(data["error_curve"]) == 4 and len(data["error_curve"][0]) == 26
    assert s["episodes"] == 4 and s["num_envs"] == 3 and s["step_ms_batch1"]["calls"] == 5
    tab = res.table(per_episode=True)
    assert "success rate" in tab and len(tab.splitlines()) > 4 + 16
    png = tmp_path / "r.png"
    res.plot(png)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


# ------------------------------------------------------------------------------------------------- (f)
def test_sb3_like_models_modules_and_callables():
    seeds, steps = [3, 4, 5], 15

    class Predictor:
        def predict(self, obs, deterministic=False):
            assert isinstance(obs, np.ndarray) and deterministic
            return feedback(torch.as_tensor(obs)).numpy(), None

    torch.manual_seed(0)
    net = nn.Sequential(nn.Linear(3, 8), nn.Tanh(), nn.Linear(8, 1)).double()
    assert isinstance(as_policy(Predictor()), SB3Adapter)
    assert isinstance(as_policy(net), ModuleAdapter)
    assert isinstance(as_policy(feedback), CallableAdapter)
    kw = dict(seeds=seeds, num_envs=3, max_episode_steps=steps, progress=False, timing_batch1=False)
    base = evaluate(feedback, "PendulumSwingUp", **kw)
    same_episodes(evaluate(Predictor(), "PendulumSwingUp", **kw), base)
    with torch.no_grad():
        ref = evaluate(lambda o: net(o), "PendulumSwingUp", **kw)
    same_episodes(evaluate(net, "PendulumSwingUp", **kw), ref)
    # a float32 module sees float32 observations; (N,) actions of a one-control task are accepted
    net32 = nn.Sequential(nn.Linear(3, 1), nn.Flatten(0))
    r32 = evaluate(net32, "PendulumSwingUp", **kw)
    with torch.no_grad():
        same_episodes(r32, evaluate(lambda o: net32(o.float()).double(), "PendulumSwingUp", **kw))

    from stable_baselines3 import PPO

    from learning.sb3 import SB3VecEnv

    model = PPO("MlpPolicy", SB3VecEnv("PendulumSwingUp", 2, dtype=torch.float64), n_steps=8, seed=0,
                device="cpu")
    r = evaluate(model, "PendulumSwingUp", **kw)
    assert np.isfinite(r.returns).all() and (r.violations == 0).all()  # SB3 clips to the action space
    assert r.meta["policy"] == "SB3Adapter(PPO)"


# ------------------------------------------------------------------------------------------------- (g)
def test_batched_equals_each_seed_alone():
    seeds, steps = [3, 7, 11, 12, 20], 40
    both = evaluate(feedback, "CartPoleSwingUp", num_envs=5, seeds=seeds, max_episode_steps=steps,
                    progress=False, timing_batch1=False)
    for i, s in enumerate(seeds):
        one = evaluate(feedback, "CartPoleSwingUp", num_envs=1, seeds=[s], max_episode_steps=steps,
                       progress=False, timing_batch1=False)
        same_episodes(both, one, [i], [0])
        np.testing.assert_allclose(both.error_curve[i], one.error_curve[0], rtol=0, atol=1e-12)
    assert both.terminated.any()


def test_arguments_and_gym_ids():
    r = evaluate(feedback, "liecontrol/PendulumSwingUp-v0", num_envs=4, episodes=2, max_episode_steps=3,
                 progress=False, timing_batch1=False)
    assert r.meta["num_envs"] == 2 and r.episodes == 2
    with pytest.raises(ValueError):
        evaluate(feedback, "PendulumSwingUp", seeds=[], progress=False)
    with pytest.raises(TypeError):
        as_policy(42)


def test_a_float64_action_beyond_float32_is_evaluated_as_the_env_applies_it():
    """Issue 22 item 13: evaluate cast a float64 1e39 to inf before clipping (episode invalid after one step,
    0 violations) while the envs clip it to the bound.  Reference: TaskEnv stepped by hand."""
    seeds = [3, 4]
    for policy in (lambda o: np.full((o.shape[0], 1), 1e39),  # numpy float64 (CallableAdapter)
                   lambda o: torch.full((o.shape[0], 1), -1e300, dtype=torch.float64)):
        res = evaluate(policy, "PendulumSwingUp", seeds=seeds, num_envs=2, dtype=torch.float32,
                       progress=False, timing_batch1=False)
        for i, s in enumerate(seeds):
            env = TaskEnv("PendulumSwingUp", dtype=torch.float32)
            obs, _ = env.reset(seed=s)
            total, steps = 0.0, 0
            for _ in range(env.task.max_episode_steps):
                a = np.asarray(policy(torch.as_tensor(obs)[None]))[0]
                obs, r, term, trunc, info = env.step(a)
                total, steps = total + r, steps + 1
                assert not info.get("invalid", False)
                if term or trunc:
                    break
            x = torch.as_tensor(env.state)[None]
            assert not res.invalid[i] and res.errors[i] == ""
            assert res.length[i] == steps and res.violations[i] == steps
            assert res.returns[i] == pytest.approx(total, rel=1e-5)
            assert res.final_error[i] == pytest.approx(float(env.task.error(x)[0]), rel=1e-5, abs=1e-6)


def test_a_complex_action_is_a_policy_error_not_a_real_part():
    """Issue 22 item 13: complex actions lost their imaginary part silently; now the policy's error
    (its episodes invalid, the message naming the action)."""
    for policy in (lambda o: torch.full((o.shape[0], 1), 0.5 + 1j), lambda o: np.full((o.shape[0], 1), 0.5j)):
        res = evaluate(policy, "PendulumSwingUp", seeds=[0, 1], num_envs=2, progress=False,
                       timing_batch1=False)
        assert res.invalid.all() and (res.length == 0).all()
        assert all("TypeError" in e and "action must be real numbers" in e for e in res.errors)


def test_counts_that_are_not_ints_are_refused_not_truncated():
    """Issue 22 sweep: max_episode_steps=2.7 ran 2-step episodes and seeds=[1.5] ran seed 1, silently."""
    for kw, name in ((dict(max_episode_steps=2.7), "max_episode_steps"), (dict(seeds=[1.5]), "seeds"),
                     (dict(episodes=2.0), "episodes"), (dict(num_envs=1.5), "num_envs"),
                     (dict(timing_steps=0.5), "timing_steps"), (dict(seeds=[-1]), "seeds")):
        with pytest.raises(ValueError, match=f"evaluate: argument '{name}' must be an int"):
            evaluate(feedback, "PendulumSwingUp", progress=False, timing_batch1=False, **kw)
    with pytest.raises(ValueError, match="'device'"):
        evaluate(feedback, "PendulumSwingUp", device="nonsense", progress=False)
    r = evaluate(feedback, "PendulumSwingUp", seeds=[np.int64(3)], max_episode_steps=np.int32(2),
                 progress=False, timing_batch1=False)  # numpy ints are ints
    assert r.length.tolist() == [2]
