"""The batched vector env through the shipped conformance suite (against gymnasium's SyncVectorEnv over
the single env, to 1e-12 in float64), the suite's own power to catch broken envs, and the env's
contract on bad input."""

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.vector import AutoresetMode

import learning
from learning import TASKS, TaskEnv, TaskVectorEnv
from learning.conformance import check_against_sync, check_fresh_buffers, check_vector_env

learning.register_envs()


def _make(name, output="numpy", dtype=torch.float64, steps=13, N=5, device="cpu"):
    return lambda mode: TaskVectorEnv(name, N, max_episode_steps=steps, autoreset_mode=mode, dtype=dtype,
                                      output=output, device=device)


@pytest.mark.parametrize("name", sorted(TASKS))
def test_conformance_and_equivalence_to_the_single_env(name):
    single = lambda: gym.make(learning.env_id(name), max_episode_steps=13, dtype=torch.float64)
    report = check_vector_env(_make(name), single, tol=1e-12)
    assert len(report["checks"]) == 13


@pytest.mark.parametrize("name", sorted(TASKS))
def test_conformance_in_tensor_mode_float32(name):
    check_vector_env(_make(name, output="torch", dtype=torch.float32))


def test_cartpole_equivalence_through_terminations():
    """Bang-bang actions drive carts off the track: terminations (not only time limits) are compared."""
    name = "CartPoleSwingUp"
    ours = TaskVectorEnv(name, 6, max_episode_steps=500, dtype=torch.float64)
    singles = [gym.make(learning.env_id(name), max_episode_steps=500, dtype=torch.float64) for _ in range(6)]
    ours.reset(seed=4)
    for i, e in enumerate(singles):
        e.reset(seed=4 + i)
    terms = 0
    for k in range(300):
        a = np.full((6, 1), 1.0 if (k // 25) % 2 else -1.0)
        o, r, te, tr, _ = ours.step(a)
        for i, e in enumerate(singles):
            if k > 0 and prev_done[i]:  # noqa: F821 - NEXT_STEP: ours resets on this step
                oi, _ = e.reset()
                ri, tei, tri = 0.0, False, False
            else:
                oi, ri, tei, tri, _ = e.step(a[i])
            np.testing.assert_allclose(o[i], oi, rtol=0, atol=1e-12)
            assert (r[i], te[i], tr[i]) == (pytest.approx(ri, abs=1e-12), tei, tri)
        prev_done = te | tr  # noqa: F841
        terms += int(te.sum())
    assert terms >= 6


def test_make_vec_uses_the_vector_entry_point_and_passes_the_time_limit():
    env = gym.make_vec(learning.env_id("PendulumSwingUp"), num_envs=3)
    assert isinstance(env.unwrapped, TaskVectorEnv) and env.unwrapped.max_episode_steps == 200
    env = gym.make_vec(learning.env_id("PendulumSwingUp"), num_envs=3, max_episode_steps=4)
    env.reset(seed=0)
    flags = [env.step(np.zeros((3, 1), np.float32))[3] for _ in range(4)]
    assert not any(f.any() for f in flags[:3]) and flags[3].all()


class _AliasingEnv(TaskVectorEnv):
    """Broken on purpose: returns the same observation buffer every step."""

    def step(self, actions):
        o, *rest = super().step(actions)
        if not hasattr(self, "_buf"):
            self._buf = o
        self._buf[...] = o
        return (self._buf, *rest)


class _SeedEnv(TaskVectorEnv):
    """Broken on purpose: every environment gets the same seed."""

    def reset(self, *, seed=None, options=None):
        return super().reset(seed=None if seed is None else [seed] * self.num_envs, options=options)


class _NoZeroRewardEnv(TaskVectorEnv):
    """Broken on purpose: the NEXT_STEP reset step reports the reward of the ignored action."""

    def step(self, actions):
        ar = self._ended.clone()
        r_before = self.task.transition(self._x, torch.as_tensor(actions, dtype=self.dtype), self._scale)[2]
        o, r, te, tr, info = super().step(actions)
        r = np.where(ar.numpy(), r_before.numpy(), r)
        return o, r, te, tr, info


class _NoInvalidInfoEnv(TaskVectorEnv):
    """Broken on purpose: drops the flag of a non-finite action from the infos."""

    def step(self, actions):
        o, r, te, tr, info = super().step(actions)
        info.pop("invalid", None)
        info.pop("_invalid", None)
        return o, r, te, tr, info


class _ListSeedEnv(TaskVectorEnv):
    """Broken on purpose: a list of seeds is applied in reverse order."""

    def reset(self, *, seed=None, options=None):
        return super().reset(seed=seed[::-1] if isinstance(seed, list) else seed, options=options)


def test_the_suite_catches_broken_envs():
    single = lambda: gym.make(learning.env_id("PendulumSwingUp"), max_episode_steps=13, dtype=torch.float64)
    with pytest.raises(AssertionError, match="overwrote|modified"):
        check_fresh_buffers(lambda: _AliasingEnv("PendulumSwingUp", 4, dtype=torch.float64))
    for broken in (_SeedEnv, _NoZeroRewardEnv):
        make = lambda mode, broken=broken: broken("PendulumSwingUp", 4, max_episode_steps=13,
                                                  autoreset_mode=mode, dtype=torch.float64)
        with pytest.raises(AssertionError, match="differ from the reference"):
            check_against_sync(make, single, AutoresetMode.NEXT_STEP)
    # (in SAME_STEP mode an invalid step's flag sits in final_info, which the override does not touch)
    for broken, what, mode in ((_NoInvalidInfoEnv, "infos lack 'invalid'", AutoresetMode.NEXT_STEP),
                               (_ListSeedEnv, "list-seeded", AutoresetMode.SAME_STEP)):
        make = lambda mode, broken=broken: broken("PendulumSwingUp", 4, max_episode_steps=13,
                                                  autoreset_mode=mode, dtype=torch.float64)
        with pytest.raises(AssertionError, match=what):
            check_against_sync(make, single, mode)


def test_one_bad_environment_does_not_poison_the_batch():
    env = TaskVectorEnv("CartPoleSwingUp", 4, dtype=torch.float64)
    ref = TaskVectorEnv("CartPoleSwingUp", 4, dtype=torch.float64)
    env.reset(seed=0)
    ref.reset(seed=0)
    a = np.full((4, 1), 0.3)
    bad = a.copy()
    bad[2] = np.nan
    o, r, te, tr, info = env.step(bad)
    o_ref, r_ref, *_ = ref.step(a)
    keep = [0, 1, 3]
    np.testing.assert_array_equal(o[keep], o_ref[keep])
    np.testing.assert_array_equal(r[keep], r_ref[keep])
    assert tr.tolist() == [False, False, True, False] and not te.any()
    assert info["invalid"].tolist() == [False, False, True, False] and np.isfinite(o).all()
    o, r, te, tr, info = env.step(a)  # NEXT_STEP: env 2 restarts, the others go on
    assert r[2] == 0.0 and not tr.any() and "invalid" not in info


def test_bad_arguments_are_rejected_with_the_argument_named():
    with pytest.raises(ValueError, match="num_envs"):
        TaskVectorEnv("PendulumSwingUp", 0)
    with pytest.raises(ValueError, match="output"):
        TaskVectorEnv("PendulumSwingUp", 2, output="jax")
    with pytest.raises(ValueError, match="autoreset_mode"):
        TaskVectorEnv("PendulumSwingUp", 2, autoreset_mode="sometimes")
    env = TaskVectorEnv("PendulumSwingUp", 2, autoreset_mode="same_step")
    assert env.metadata["autoreset_mode"] is AutoresetMode.SAME_STEP
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros((2, 1)))
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"shape \(2, 1\)"):
        env.step(np.zeros((3, 1)))
    with pytest.raises(ValueError, match="reset_mask"):
        env.reset(options={"reset_mask": np.array([1, 0])})
    with pytest.raises(ValueError, match="seed"):
        env.reset(seed=[1, 2, 3])
    for bad in (1.5, True, "7", [1, True], [1.0, 2]):
        with pytest.raises(ValueError, match="seed"):
            env.reset(seed=bad)
    with pytest.raises(ValueError, match="at least one"):
        env.reset(options={"reset_mask": np.zeros(2, dtype=bool)})
    with pytest.raises(ValueError, match="num_envs"):
        TaskVectorEnv("PendulumSwingUp", True)
    assert TaskVectorEnv("PendulumSwingUp", np.int64(3)).num_envs == 3
    with pytest.raises(ValueError, match="seed"):
        TaskEnv("PendulumSwingUp").reset(seed=True)


def test_a_longer_horizon_than_the_tasks_widens_the_proven_bounds():
    """The observation bound is proven for the horizon the env runs: overriding max_episode_steps
    rebuilds the task with it, so a pumped pendulum never leaves observation_space."""
    short = TaskVectorEnv("PendulumSwingUp", 4, dtype=torch.float64)
    long_ = TaskVectorEnv("PendulumSwingUp", 4, dtype=torch.float64, max_episode_steps=2000)
    assert long_.task.max_episode_steps == 2000
    assert long_.single_observation_space.high[2] > 5 * short.single_observation_space.high[2]
    obs, _ = long_.reset(seed=0)
    for _ in range(2000):  # pump: torque along the speed
        obs, *_ = long_.step(np.sign(obs[:, 2:3]) + (obs[:, 2:3] == 0))
        assert np.all(np.abs(obs) <= long_.single_observation_space.high)
    assert np.abs(obs[:, 2]).max() > short.single_observation_space.high[2]  # beyond the 200-step bound


def test_seeding_matches_sync_vector_env_convention_and_lists():
    env = TaskVectorEnv("CartPoleSwingUp", 3, dtype=torch.float64)
    o_int, _ = env.reset(seed=10)
    o_list, _ = env.reset(seed=[10, 11, 12])
    np.testing.assert_array_equal(o_int, o_list)
    o_mix, _ = env.reset(seed=[10, None, 12])
    np.testing.assert_array_equal(o_mix[[0, 2]], o_int[[0, 2]])


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device (none on this machine)")
@pytest.mark.parametrize("compiled", [False, True])
@pytest.mark.parametrize("name", sorted(TASKS))
def test_cuda_matches_cpu(name, compiled):
    cpu = TaskVectorEnv(name, 64, dtype=torch.float64, output="torch")
    gpu = TaskVectorEnv(name, 64, dtype=torch.float64, output="torch", device="cuda", compile=compiled)
    cpu.reset(seed=0)
    gpu.reset(seed=0)
    g = torch.Generator().manual_seed(0)
    for _ in range(250):
        a = torch.rand(64, cpu.task.m, generator=g, dtype=torch.float64) * 2 - 1
        oc, rc, tc, trc, _ = cpu.step(a)
        og, rg, tg, trg, _ = gpu.step(a.cuda())
        assert og.device.type == "cuda"
        torch.testing.assert_close(og.cpu(), oc, rtol=0, atol=1e-9)
        assert torch.equal(tg.cpu(), tc) and torch.equal(trg.cpu(), trc)


def test_huge_finite_actions_are_clipped_not_flagged_in_float32():
    env = TaskVectorEnv("PendulumSwingUp", 2)
    ref = TaskVectorEnv("PendulumSwingUp", 2)
    env.reset(seed=0)
    ref.reset(seed=0)
    o, r, te, tr, info = env.step(np.array([[1e39], [-1e300]]))
    o2, r2, *_ = ref.step(np.array([[1.0], [-1.0]], np.float32))
    assert not tr.any() and "invalid" not in info
    np.testing.assert_array_equal(o, o2)
    o, r, te, tr, info = env.step(np.array([[np.inf], [0.0]]))
    assert tr.tolist() == [True, False] and info["invalid"].tolist() == [True, False]


def test_first_reset_with_a_partial_mask_is_refused():
    env = TaskVectorEnv("PendulumSwingUp", 3)
    with pytest.raises(ValueError, match="first reset"):
        env.reset(options={"reset_mask": np.array([True, False, False])})


def test_learnable_model_parameters_leave_no_graph_in_the_env():
    from controllers.systems import Pendulum
    from learning import PendulumSwingUp

    length = torch.nn.Parameter(torch.tensor(2.0 / 3.0))
    task = PendulumSwingUp(model=Pendulum(mass=0.75, length=length, gravity=10.0, dt=0.05))
    env = TaskVectorEnv(task, 3, output="torch")
    o, _ = env.reset(seed=0)
    o, r, *_ = env.step(torch.zeros(3, 1))
    assert not o.requires_grad and not r.requires_grad and not env.state.requires_grad


def test_same_step_invalid_flags_are_in_final_info_like_sync_vector_env():
    env = TaskVectorEnv("PendulumSwingUp", 2, autoreset_mode="same_step", dtype=torch.float64)
    env.reset(seed=0)
    o, r, te, tr, info = env.step(np.array([[np.nan], [0.0]]))
    assert "invalid" not in info and info["final_info"]["invalid"].tolist() == [True, False]
    assert info["_final_obs"].tolist() == [True, False]


def _lockstep(envs: dict, steps: int, seed: int, nan_at: int):
    """Step every env with the same actions (a NaN in env 2 at ``nan_at``, bang-bang pushes that end
    cart-pole episodes early) and assert identical outputs and info keys; returns the numbers of ended and
    of terminated episodes seen."""
    ref_name, ref = next(iter(envs.items()))
    for e in envs.values():
        e.reset(seed=seed)
    g = torch.Generator().manual_seed(seed)
    N, ended, terminated = ref.num_envs, 0, 0
    for k in range(steps):
        base = torch.rand(N, 2 * ref.task.m, generator=g, dtype=torch.float64) * 3 - 1.5
        a = base[:, ::2] if k % 2 else base[:, :ref.task.m].contiguous()  # odd steps: a strided view
        assert a.is_contiguous() == (k % 2 == 0) or N == 1  # a (1, m) view is dense anyway
        a[:, 0] += torch.where(torch.arange(N) % 2 == 0, 1.0, -1.0) * ((k // 20) % 2 * 2 - 1)
        if k == nan_at and N > 2:
            a[2] = float("nan")
        outs = {name: e.step(a) for name, e in envs.items()}
        o0 = outs[ref_name]
        for name, o in outs.items():
            for u, v in zip(o0[:4], o[:4]):
                torch.testing.assert_close(v, u, rtol=0, atol=1e-12, msg=lambda m, w=(name, k): f"{w}: {m}")
            assert o[4].keys() == o0[4].keys(), (name, k, o[4].keys(), o0[4].keys())
            for key, val in o0[4].items():
                if isinstance(val, torch.Tensor):
                    torch.testing.assert_close(o[4][key], val, rtol=0, atol=1e-12)
        ended += int((o0[2] | o0[3]).sum())
        terminated += int(o0[2].sum())
    return ended, terminated


def test_aot_env_passes_conformance_and_equals_eager_at_any_batch_size():
    """compile="aot" builds one library per (task, dtype, device, horizon, reset variant) with a dynamic
    batch size: the conformance suite (every autoreset mode, against SyncVectorEnv over the single env)
    and a lock-step comparison with the eager env at N = 1 and 7, NaN action and autoresets included."""
    name = "PendulumSwingUp"
    make = lambda mode: TaskVectorEnv(name, 5, max_episode_steps=13, autoreset_mode=mode, dtype=torch.float64,
                                      output="torch", compile="aot")
    single = lambda: gym.make(learning.env_id(name), max_episode_steps=13, dtype=torch.float64)
    check_vector_env(make, single, tol=1e-12)
    for mode in (AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP):
        for N in (1, 7):
            envs = {c: TaskVectorEnv(name, N, max_episode_steps=13, autoreset_mode=mode, dtype=torch.float64,
                                     output="torch", compile=c) for c in (False, "aot")}
            assert _lockstep(envs, 40, seed=N, nan_at=5)[0] >= 2 * N  # T = 13: two ends in 40 steps


@pytest.mark.parametrize("mode", [AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP])
def test_torch_compiled_env_equals_eager_through_terminations(mode):
    name = "CartPoleSwingUp"
    envs = {c: TaskVectorEnv(name, 6, max_episode_steps=60, autoreset_mode=mode, dtype=torch.float64,
                             output="torch", compile=c) for c in (False, True)}
    ended, terminated = _lockstep(envs, 150, seed=2, nan_at=30)
    assert ended >= 12 and terminated >= 3  # episodes ended by termination too, not only the time limit


def test_partial_reset_in_next_step_mode_restarts_only_the_masked_ones():
    """A reset_mask that leaves an ended environment ended: the next step still restarts it."""
    env = TaskVectorEnv("PendulumSwingUp", 3, max_episode_steps=2, dtype=torch.float64, output="torch")
    env.reset(seed=0)
    a = torch.zeros(3, 1, dtype=torch.float64)
    env.step(a)
    _, _, _, trunc, _ = env.step(a)
    assert trunc.all()
    o, _ = env.reset(options={"reset_mask": np.array([True, False, False])})
    assert env.elapsed_steps.tolist() == [0, 2, 2]
    o, r, te, tr, _ = env.step(a)  # envs 1 and 2 restart here (reward 0), env 0 steps
    assert env.elapsed_steps.tolist() == [1, 0, 0] and r[1:].tolist() == [0.0, 0.0] and r[0] != 0


def test_bad_compile_argument_is_refused():
    with pytest.raises(ValueError, match="compile"):
        TaskVectorEnv("PendulumSwingUp", 2, compile="fast")


def test_complex_or_non_numeric_actions_are_refused_naming_the_actions():
    """Issue 22 item 13: a complex action lost its imaginary part silently (numpy's ComplexWarning only)."""
    env = TaskVectorEnv("PendulumSwingUp", 2)
    env.reset(seed=0)
    state = env.state
    for bad in (np.array([[0.5 + 1j], [0.0]]), torch.tensor([[0.5 + 1j], [0.0]]), np.array([["a"], ["b"]])):
        with pytest.raises(TypeError, match="TaskVectorEnv.step: actions must be real numbers"):
            env.step(bad)
    assert torch.equal(env.state, state)  # nothing was stepped
    # integer and bool actions are real: accepted, as their float values
    ref = TaskVectorEnv("PendulumSwingUp", 2)
    ref.reset(seed=0)
    o, *_ = env.step(np.array([[1], [0]]))
    o2, *_ = ref.step(np.array([[1.0], [0.0]], np.float32))
    np.testing.assert_array_equal(o, o2)


def test_a_device_torch_cannot_use_is_refused_in_the_constructor(monkeypatch):
    """Issue 22 item 12: device='cuda' on a CPU-only torch failed with torch's assertion deep inside."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)  # a CPU-only torch, on any machine
    with pytest.raises(ValueError, match="'device'.*no CUDA"):
        TaskVectorEnv("PendulumSwingUp", 2, device="cuda")
    with pytest.raises(ValueError, match="'device'"):
        TaskVectorEnv("PendulumSwingUp", 2, device="gpu0")


def test_the_meta_device_is_refused_in_the_constructor():
    """device='meta' (shapes without values) was accepted and failed at reset with torch's
    'Tensor.item() cannot be called on meta tensors'."""
    with pytest.raises(ValueError, match="'device'.*'meta'"):
        TaskVectorEnv("PendulumSwingUp", 2, device="meta")
    with pytest.raises(ValueError, match="'device'.*'meta'"):
        TaskVectorEnv("PendulumSwingUp", 2, device=torch.device("meta"))
