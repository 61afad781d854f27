"""learning.demos: the Demonstrations container, its .npz format, users' arrays, behaviour-cloning demos,
human-like variability, expert demos and the handwriting letters (issue 26 §1)."""

import json
import math

import numpy as np
import pytest
import torch

from learning.demos import (
    FORMAT,
    LETTERS,
    Demonstrations,
    expert_demos,
    handwriting,
    letter_stroke,
    mpc_demos,
    spatial_noise,
    time_warp,
)

DTYPES = [torch.float32, torch.float64]


def _demos(N=5, T=12, n=3, m=2, r=1, dtype=torch.float64, seed=0):
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(N, T, n, generator=g, dtype=torch.float64).to(dtype)
    u = torch.randn(N, T - 1, m, generator=g, dtype=torch.float64).to(dtype)
    ref = torch.randn(N, T, r, generator=g, dtype=torch.float64).to(dtype)
    frames = {"goal": torch.randn(N, n, generator=g, dtype=torch.float64).to(dtype),
              "ok": torch.arange(N) % 2 == 0, "id": torch.arange(N) * 10}
    return Demonstrations(x=x, dt=0.1, u=u, ref=ref, frames=frames, meta={"source": "test", "k": [1, 2]})


# ------------------------------------------------------------------------------------- validation
def test_validation_names_field_demo_and_step():
    d = _demos()
    x = d.x.clone()
    x[3, 7, 1] = math.nan
    with pytest.raises(ValueError, match=r"field 'x'.*demo 3 at time step 7"):
        Demonstrations(x=x, dt=0.1)
    u = d.u.clone()
    u[1, 0, 0] = math.inf
    with pytest.raises(ValueError, match=r"field 'u'.*demo 1 at time step 0"):
        Demonstrations(x=d.x, dt=0.1, u=u)
    with pytest.raises(ValueError, match=r"T-1.*one control per transition"):
        Demonstrations(x=d.x, dt=0.1, u=torch.zeros(5, 12, 2, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"'ref'"):
        Demonstrations(x=d.x, dt=0.1, ref=torch.zeros(5, 11, 1, dtype=torch.float64))
    with pytest.raises(TypeError, match="'u' has dtype"):
        Demonstrations(x=d.x, dt=0.1, u=d.u.float())
    with pytest.raises(ValueError, match="frame 'goal' must have leading dimension N = 5"):
        Demonstrations(x=d.x, dt=0.1, frames={"goal": torch.zeros(4, 3)})
    g = torch.zeros(5, 3)
    g[2, 1] = math.nan
    with pytest.raises(ValueError, match="frame 'goal' has a non-finite value in demo 2"):
        Demonstrations(x=d.x, dt=0.1, frames={"goal": g})
    with pytest.raises(ValueError, match="'dt' must be positive"):
        Demonstrations(x=d.x, dt=0.0)
    with pytest.raises(TypeError, match="float32 or float64"):
        Demonstrations(x=d.x.half(), dt=0.1)
    with pytest.raises(ValueError, match=r"T >= 2"):
        Demonstrations(x=d.x[:, :1], dt=0.1)
    with pytest.raises(TypeError, match="JSON"):
        Demonstrations(x=d.x, dt=0.1, meta={"a": object()})
    with pytest.raises(ValueError, match="frame name"):
        Demonstrations(x=d.x, dt=0.1, frames={"a/b": torch.zeros(5)})


def test_meta_is_copied_and_frames_dict_is_own():
    meta = {"a": [1, 2]}
    frames = {"g": torch.zeros(5)}
    d = Demonstrations(x=torch.zeros(5, 3, 1), dt=1.0, frames=frames, meta=meta)
    meta["a"].append(3)
    frames["h"] = torch.zeros(5)
    assert d.meta == {"a": [1, 2]} and set(d.frames) == {"g"}


# ------------------------------------------------------------------------------------- selection
def test_select_split_cat_to():
    d = _demos(N=6)
    s = d[[4, 1]]
    assert torch.equal(s.x, d.x[[4, 1]]) and torch.equal(s.u, d.u[[4, 1]])
    assert torch.equal(s.frames["id"], torch.tensor([40, 10])) and s.meta == d.meta
    assert torch.equal(d.select(torch.arange(6) >= 4).x, d.x[4:]) and len(d[2]) == 1 and len(d[1:3]) == 2
    with pytest.raises(IndexError):
        d.select([6])
    with pytest.raises(ValueError, match="empty"):
        d.select([])
    tr, te = d.split(4, generator=torch.Generator().manual_seed(1))
    ids = torch.cat([tr.frames["id"], te.frames["id"]])
    assert len(tr) == 4 and len(te) == 2 and sorted(ids.tolist()) == list(range(0, 60, 10))
    tr0, _ = d.split(4)
    assert torch.equal(tr0.x, d.x[:4])
    with pytest.raises(ValueError, match="n_train"):
        d.split(6)
    c = Demonstrations.cat([tr, te])
    assert len(c) == 6 and torch.equal(c.frames["id"], ids)
    with pytest.raises(ValueError, match="item 1 has T"):
        Demonstrations.cat([d, d.resample(20)])
    f = d.to(dtype=torch.float32)
    assert f.x.dtype == f.u.dtype == f.ref.dtype == f.frames["goal"].dtype == torch.float32
    assert f.frames["id"].dtype == torch.int64 and f.frames["ok"].dtype == torch.bool


# ------------------------------------------------------------------------------------- time & stats
@pytest.mark.parametrize("dtype", DTYPES)
def test_resample_matches_numpy_interp_and_keeps_duration(dtype):
    d = _demos(T=13, dtype=dtype)
    r = d.resample(30)
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    s_old, s_new = np.linspace(0, 1, 13), np.linspace(0, 1, 30)
    x, u, ref = d.x.double().numpy(), d.u.double().numpy(), d.ref.double().numpy()
    for i in range(len(d)):
        for j in range(d.n):
            np.testing.assert_allclose(r.x[i, :, j].double(), np.interp(s_new, s_old, x[i, :, j]), atol=tol)
        for j in range(d.m):
            np.testing.assert_allclose(r.u[i, :, j].double(), np.interp(s_new[:-1], s_old[:-1], u[i, :, j]),
                                       atol=tol)
        np.testing.assert_allclose(r.ref[i, :, 0].double(), np.interp(s_new, s_old, ref[i, :, 0]), atol=tol)
    assert r.x.dtype == dtype and r.T == 30 and r.u.shape == (5, 29, 2)
    assert r.duration == pytest.approx(d.duration, rel=1e-12)
    assert r.meta["history"][-1] == {"op": "resample", "from": 13, "to": 30}


def test_velocities_accelerations_match_numpy_gradient():
    d = _demos()
    v = np.gradient(d.x.numpy(), 0.1, axis=1)
    np.testing.assert_allclose(d.velocities(), v, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(d.accelerations(), np.gradient(v, 0.1, axis=1), rtol=1e-12, atol=1e-10)
    np.testing.assert_allclose(d.times(), 0.1 * np.arange(12), atol=1e-15)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("ddof", [0, 1])
def test_mean_covariance_match_numpy(dtype, ddof):
    d = _demos(N=7, dtype=dtype)
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    x = d.x.double().numpy()
    C = d.covariance(ddof=ddof)
    assert C.shape == (12, 3, 3) and C.dtype == dtype
    for t in range(d.T):
        np.testing.assert_allclose(C[t].double(), np.cov(x[:, t].T, ddof=ddof), atol=tol)
    np.testing.assert_allclose(d.mean().double(), x.mean(0), atol=tol)
    Cu = np.cov(d.u.double().numpy()[:, 3].T, ddof=ddof)
    np.testing.assert_allclose(d.covariance("u", ddof).double()[3], Cu, atol=tol)
    with pytest.raises(ValueError, match="need N > ddof"):
        d[0].covariance(ddof=1)
    with pytest.raises(ValueError, match="no 'u'"):
        Demonstrations(x=d.x, dt=1.0).mean("u")


# ------------------------------------------------------------------------------------- files
@pytest.mark.parametrize("dtype", DTYPES)
def test_npz_round_trip_exact(tmp_path, dtype):
    d = _demos(dtype=dtype)
    p = tmp_path / "d.npz"
    d.save(p)
    with np.load(p, allow_pickle=False) as z:  # the documented keys, no pickle needed
        assert set(z.files) == {"format", "format_version", "x", "dt", "u", "ref", "meta_json", "frame/goal",
                                "frame/ok", "frame/id"}
        assert str(z["format"][()]) == FORMAT and json.loads(str(z["meta_json"][()])) == d.meta
    e = Demonstrations.load(p)
    assert e.x.dtype == dtype and torch.equal(e.x, d.x) and torch.equal(e.u, d.u)
    assert torch.equal(e.ref, d.ref)
    assert e.dt == d.dt and e.meta == d.meta and e.frames.keys() == d.frames.keys()
    for k in d.frames:
        assert e.frames[k].dtype == d.frames[k].dtype and torch.equal(e.frames[k], d.frames[k])
    x_only = Demonstrations(x=d.x, dt=0.25)
    x_only.save(tmp_path / "x.npz", compress=True)
    e = Demonstrations.load(tmp_path / "x.npz")
    assert e.u is None and e.ref is None and e.frames == {} and torch.equal(e.x, d.x) and e.dt == 0.25


def test_npz_load_errors(tmp_path):
    d = _demos()
    p = tmp_path / "d.npz"
    d.save(p)
    with np.load(p) as z:
        arrs = {k: z[k] for k in z.files}

    def write(name, **changes):
        a = {**arrs, **changes}
        a = {k: v for k, v in a.items() if v is not None}
        q = tmp_path / name
        with open(q, "wb") as f:
            np.savez(f, **a)
        return q

    with pytest.raises(ValueError, match="not a liecontrol.Demonstrations file"):
        Demonstrations.load(write("foreign.npz", format=np.array("something else")))
    with pytest.raises(ValueError, match="format version 2, written by a newer version"):
        Demonstrations.load(write("newer.npz", format_version=np.array(2)))
    with pytest.raises(ValueError, match=r"unknown key\(s\) \['extra'\]"):
        Demonstrations.load(write("extra.npz", extra=np.zeros(3)))
    with pytest.raises(ValueError, match="lacks the required key 'x'"):
        Demonstrations.load(write("nox.npz", x=None))
    bad = arrs["x"].copy()
    bad[2, 4, 0] = np.nan
    with pytest.raises(ValueError, match="demo 2 at time step 4"):
        Demonstrations.load(write("nan.npz", x=bad))


# ------------------------------------------------------------------------------------- users' arrays
@pytest.mark.parametrize("dtype", DTYPES)
def test_from_arrays_equal_lengths_numpy_and_torch(dtype):
    rng = np.random.default_rng(0)
    npdt = np.float32 if dtype == torch.float32 else np.float64
    xs = [rng.standard_normal((10, 2)).astype(npdt) for _ in range(3)]
    us = [rng.standard_normal((9, 1)).astype(npdt) for _ in range(3)]
    d = Demonstrations.from_arrays(xs, us, dt=[0.05, 0.05, 0.05])
    assert d.x.dtype == dtype and torch.equal(d.x, torch.from_numpy(np.stack(xs))) and d.dt == 0.05
    assert torch.equal(d.u, torch.from_numpy(np.stack(us)))
    t = Demonstrations.from_arrays([torch.from_numpy(a) for a in xs], dt=0.05)
    assert torch.equal(t.x, d.x)
    whole = Demonstrations.from_arrays(np.stack(xs), dt=0.05)
    assert torch.equal(whole.x, d.x)
    ints = Demonstrations.from_arrays([np.arange(8).reshape(4, 2)] * 2, dt=1.0)
    assert ints.x.dtype == torch.float64


def test_from_arrays_errors_name_the_demo():
    rng = np.random.default_rng(1)
    xs = [rng.standard_normal((10, 2)) for _ in range(4)]
    with pytest.raises(ValueError, match="demo 2 has 7 samples, demo 0 has 10; pass resample"):
        Demonstrations.from_arrays(xs[:2] + [xs[2][:7], xs[3][:5]], dt=0.1)
    with pytest.raises(ValueError, match=r"states\[1\] has dimension n = 3, states\[0\] has 2"):
        Demonstrations.from_arrays([xs[0], rng.standard_normal((10, 3))], dt=0.1)
    bad = xs[3].copy()
    bad[5, 1] = np.nan
    with pytest.raises(ValueError, match=r"states\[3\] has a non-finite value at time step 5"):
        Demonstrations.from_arrays(xs[:3] + [bad], dt=0.1)
    with pytest.raises(ValueError, match="demo 2 has dt 0.2, demo 0 has 0.1"):
        Demonstrations.from_arrays(xs[:3], dt=[0.1, 0.1, 0.2])
    with pytest.raises(ValueError, match=r"controls\[1\] must have shape \(9, ·\).*one control per"):
        Demonstrations.from_arrays(xs[:2], [np.zeros((9, 1)), np.zeros((10, 1))], dt=0.1)
    with pytest.raises(ValueError, match="non-empty"):
        Demonstrations.from_arrays([], dt=0.1)
    with pytest.raises(ValueError, match=r"states\[0\] must have shape \(T_i, n\)"):
        Demonstrations.from_arrays([np.zeros(10)], dt=0.1)
    with pytest.raises(ValueError, match="'dt' has 2 entries for 4 demos"):
        Demonstrations.from_arrays(xs, dt=[0.1, 0.1])


def test_from_arrays_resample_time_normalizes_each_demo():
    rng = np.random.default_rng(2)
    lens, dts = [10, 17, 6], [0.1, 0.05, 0.2]
    xs = [np.cumsum(rng.standard_normal((L, 2)), 0) for L in lens]
    us = [rng.standard_normal((L - 1, 1)) for L in lens]
    d = Demonstrations.from_arrays(xs, us, dt=dts, resample=25)
    s = np.linspace(0, 1, 25)
    for i, (a, b, L) in enumerate(zip(xs, us, lens)):
        so = np.linspace(0, 1, L)
        for j in range(2):
            np.testing.assert_allclose(d.x[i, :, j], np.interp(s, so, a[:, j]), atol=1e-12)
        np.testing.assert_allclose(d.u[i, :, 0], np.interp(s[:-1], so[:-1], b[:, 0]), atol=1e-12)
    dur = [(L - 1) * t for L, t in zip(lens, dts)]
    np.testing.assert_allclose(d.frames["duration"], dur, rtol=1e-12)
    assert d.frames["length"].tolist() == lens and d.dt == pytest.approx(np.mean(dur) / 24, rel=1e-12)


# ------------------------------------------------------------------------------------- bc demos
def _bc_demos(lengths, seed=0):
    from learning.bc import Demos
    from learning.envs.single import make_task

    task = make_task("PendulumSwingUp")
    g = torch.Generator().manual_seed(seed)
    obs, act, st, ep, step = [], [], [], [], []
    for e, L in enumerate(lengths):
        x = torch.tensor([[0.1 * e, 0.0]], dtype=torch.float64)
        for t in range(L):
            a = torch.rand(1, 1, generator=g, dtype=torch.float64) * 2 - 1
            obs.append(task.observe(x))
            act.append(a)
            st.append(x)
            ep.append(e)
            step.append(t)
            x = task.step(x, a * task.u_scale(torch.float64, "cpu"))
    E = len(lengths)
    return task, Demos(obs=torch.cat(obs), action=torch.cat(act), state=torch.cat(st),
                       episode=torch.tensor(ep), step=torch.tensor(step), seeds=torch.arange(E),
                       returns=torch.zeros(E, dtype=torch.float64), success=torch.ones(E, dtype=torch.bool),
                       length=torch.tensor(lengths), task=task.name)


def test_from_bc_connects_per_sample_demos():
    task, bc = _bc_demos([6, 6, 6])
    d = Demonstrations.from_bc(bc)
    assert d.x.shape == (3, 6, 2) and d.u.shape == (3, 5, 1) and d.dt == task.system.dt
    np.testing.assert_allclose(task.step(d.x[:, :-1].reshape(-1, 2), d.u.reshape(-1, 1)),
                               d.x[:, 1:].reshape(-1, 2), atol=1e-12)
    scale = task.u_scale(torch.float64, "cpu")
    a = bc.action.reshape(3, 6, 1)
    assert torch.equal(d.frames["u_last"], a[:, -1] * scale)
    assert d.frames["obs"].shape == (3, 6, bc.obs.shape[1])
    n = Demonstrations.from_bc(bc, physical=False)
    assert torch.equal(n.u, a[:, :-1]) and n.meta["controls"].startswith("normalized")
    _, uneven = _bc_demos([6, 6, 4, 6])
    with pytest.raises(ValueError, match="episode 2 has 4 samples, episode 0 has 6"):
        Demonstrations.from_bc(uneven)


# ------------------------------------------------------------------------------------- variability
@pytest.mark.parametrize("dtype", DTYPES)
def test_time_warp_monotone_endpoints_and_interpolation(dtype):
    d = _demos(N=6, T=40, dtype=dtype)
    w, tau = time_warp(d, 0.5, torch.Generator().manual_seed(3), return_phase=True)
    assert tau.shape == (6, 40) and tau.dtype == dtype
    assert bool((tau[:, 1:] > tau[:, :-1]).all())
    assert bool((tau[:, 0] == 0).all()) and bool((tau[:, -1] == 1).all())
    assert float((tau - torch.linspace(0, 1, 40, dtype=dtype)).abs().max()) > 0.02  # it does warp
    assert torch.equal(w.x[:, 0], d.x[:, 0]) and torch.equal(w.x[:, -1], d.x[:, -1])
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    s = np.linspace(0, 1, 40)
    for i in range(6):
        for j in range(3):
            ref = np.interp(tau[i].double(), s, d.x[i, :, j].double())
            np.testing.assert_allclose(w.x[i, :, j].double(), ref, atol=tol)
        np.testing.assert_allclose(w.u[i, :, 0].double(),
                                   np.interp(tau[i, :-1].double(), s[:-1], d.u[i, :, 0].double()), atol=tol)
    assert w.T == d.T and w.dt == d.dt and torch.equal(w.frames["id"], d.frames["id"])
    again = time_warp(d, 0.5, torch.Generator().manual_seed(3))
    assert torch.equal(again.x, w.x)
    ident = time_warp(d, 0.0, torch.Generator().manual_seed(3))
    np.testing.assert_allclose(ident.x.double(), d.x.double(), atol=tol)
    with pytest.raises(TypeError, match="torch.Generator"):
        time_warp(d, 0.5, 3)


@pytest.mark.parametrize("dtype", DTYPES)
def test_spatial_noise_std_and_smoothness(dtype):
    x = torch.zeros(400, 60, 2, dtype=dtype)
    d = Demonstrations(x=x, dt=0.01)
    scale = 0.3
    e = spatial_noise(d, scale, torch.Generator().manual_seed(4), pin_ends=False).x.double()
    # pointwise std is `scale` by construction: pooled over demos and time, to sampling error
    assert float(e.std()) == pytest.approx(scale, rel=0.08)
    assert float(e.std(0).min()) > 0.8 * scale and float(e.std(0).max()) < 1.2 * scale
    # smooth: second differences far below those of white noise of the same std (sqrt(6) scale)
    d2 = e[:, 2:] - 2 * e[:, 1:-1] + e[:, :-2]
    assert float(d2.std()) < 0.05 * math.sqrt(6) * scale
    pinned = spatial_noise(d, [scale, 0.0], torch.Generator().manual_seed(4)).x
    assert bool((pinned[:, [0, -1]] == 0).all()) and bool((pinned[..., 1] == 0).all())
    mid = pinned[:, 30, 0].double()
    assert float(mid.std()) == pytest.approx(scale * math.sin(math.pi * 30 / 59), rel=0.15)
    only = spatial_noise(_demos(dtype=dtype), 0.1, torch.Generator().manual_seed(0), dims=[1])
    base = _demos(dtype=dtype)
    assert torch.equal(only.x[..., [0, 2]], base.x[..., [0, 2]]) and not torch.equal(only.x, base.x)
    assert torch.equal(only.u, base.u)
    with pytest.raises(ValueError, match="dims"):
        spatial_noise(d, 0.1, torch.Generator(), dims=[5])


# ------------------------------------------------------------------------------------- experts
def _pendulum_problem(x0, T=40, goal=1.0):
    from controllers.costs import QuadraticCost
    from controllers.ilqr import ILQRProblem
    from controllers.systems import Pendulum

    Q = torch.diag(torch.tensor([0.1, 0.01], dtype=torch.float64)).expand(T + 1, 2, 2).clone()
    Q[-1] = torch.diag(torch.tensor([1000.0, 100.0], dtype=torch.float64))
    cost = QuadraticCost(Q=Q, R=0.01 * torch.eye(1, dtype=torch.float64),
                         x_ref=torch.tensor([goal, 0.0], dtype=torch.float64))
    sys = Pendulum(dt=0.05)
    return sys, ILQRProblem(sys, cost, x0, T)


def test_expert_demos_satisfy_dynamics_and_reach_goal():
    x0 = torch.tensor([[0.0, 0.0], [0.2, 0.0], [-0.3, 0.5], [0.5, -0.2]], dtype=torch.float64)
    sys, prob = _pendulum_problem(x0)
    d = expert_demos(prob, frames={"goal": torch.ones(4, 1, dtype=torch.float64)})
    assert d.x.shape == (4, 41, 2) and d.u.shape == (4, 40, 1) and d.dt == 0.05
    assert float((sys.step(d.x[:, :-1], d.u) - d.x[:, 1:]).abs().max()) < 1e-10
    assert torch.equal(d.x[:, 0], x0)
    assert float((d.x[:, -1, 0] - 1.0).abs().max()) < 0.02
    assert bool(d.frames["converged"].all()) and d.frames["index"].tolist() == [0, 1, 2, 3]
    assert d.meta["dropped"]["count"] == 0 and d.frames["goal"].shape == (4, 1)


def test_expert_demos_report_and_drop_only_on_request():
    from controllers.ilqr import ILQROptions

    x0 = torch.tensor([[0.0, 0.0], [0.2, 0.0], [math.nan, 0.0], [0.5, -0.2]], dtype=torch.float64)
    _, prob = _pendulum_problem(x0)
    with pytest.raises(ValueError, match=r"element 2 \(NONFINITE_INPUT\).*keep="):
        expert_demos(prob)
    d = expert_demos(prob, keep="finite")
    assert d.frames["index"].tolist() == [0, 1, 3]
    assert d.meta["dropped"] == {"count": 1, "index": [2], "reason": ["NONFINITE_INPUT"], "rule": "finite"}
    # too few iterations: nothing converges; kept and flagged by default, dropped (and counted) on request
    _, prob = _pendulum_problem(x0[[0, 1, 3]])
    few = expert_demos(prob, options=ILQROptions(max_iter=1))
    assert len(few) == 3 and not bool(few.frames["converged"].any())
    assert few.meta["reasons"][str(int(few.frames["reason"][0]))] == "MAX_ITERATIONS"
    with pytest.raises(ValueError, match="drops all 3 elements"):
        expert_demos(prob, options=ILQROptions(max_iter=1), keep="converged")
    mixed = expert_demos(_pendulum_problem(x0)[1], options=ILQROptions(max_iter=100), keep="converged")
    assert mixed.meta["dropped"]["index"] == [2] and bool(mixed.frames["converged"].all())


def test_mpc_demos_closed_loop():
    x0 = torch.tensor([[0.0, 0.0], [0.3, 0.1]], dtype=torch.float64)
    sys, prob = _pendulum_problem(x0, T=10)
    d = mpc_demos(sys, prob.cost, x0, 10, 12)
    assert d.x.shape == (2, 13, 2) and d.u.shape == (2, 12, 1)
    assert d.frames["converged_steps"].shape == (2, 12)
    assert float((sys.step(d.x[:, :-1], d.u) - d.x[:, 1:]).abs().max()) < 1e-12
    assert bool(d.frames["converged"].all())


# ------------------------------------------------------------------------------------- handwriting
def test_letter_strokes_start_and_end_on_their_control_points():
    for c in LETTERS:
        st = letter_stroke(c, 50)
        d = Demonstrations(x=st[None], dt=0.02)
        assert bool(torch.isfinite(d.velocities()).all())
        assert torch.allclose(st[[0, -1]], letter_stroke(c, torch.tensor([0.0, 1.0], dtype=torch.float64)))
    with pytest.raises(ValueError, match="unknown letter"):
        letter_stroke("Q")


@pytest.mark.parametrize("dtype", DTYPES)
def test_handwriting_deterministic_close_to_stroke(dtype):
    noise = 0.02
    a = handwriting("SCUNZW", 6, 80, generator=torch.Generator().manual_seed(0), noise=noise, dtype=dtype)
    b = handwriting("SCUNZW", 6, 80, generator=torch.Generator().manual_seed(0), noise=noise, dtype=dtype)
    c = handwriting("SCUNZW", 6, 80, generator=torch.Generator().manual_seed(1), noise=noise, dtype=dtype)
    assert list(a) == list("SCUNZW")
    for k, d in a.items():
        assert d.x.shape == (6, 80, 2) and d.x.dtype == dtype and d.meta["letter"] == k
        assert torch.equal(d.x, b[k].x) and not torch.equal(d.x, c[k].x)
        pts = torch.tensor(d.meta["control_points"], dtype=dtype)
        assert torch.equal(d.x[:, 0], pts[0].expand(6, 2)) and torch.equal(d.x[:, -1], pts[-1].expand(6, 2))
        assert torch.equal(d.frames["goal"][0], pts[-1])
        dense = letter_stroke(k, 4000, dtype=dtype)
        dist = torch.cdist(d.x.reshape(-1, 2), dense).min(-1).values
        assert float(dist.max()) < 5 * noise
        # demos differ from each other (variability), and from the clean stroke sampled at the same times
        assert float((d.x - letter_stroke(k, 80, dtype=dtype)).abs().max()) > noise
        assert bool(torch.isfinite(d.velocities()).all())


def test_handwriting_example(tmp_path):
    from examples.learning.demos_handwriting import run
    from liecontrol.cookbook import _check_outcome

    res = run(tmp_path)
    checks, values = _check_outcome("demos_handwriting", res)
    assert all(checks.values()), checks
    assert (tmp_path / "demos_handwriting.png").stat().st_size > 0
    assert values["max_distance_to_stroke"] <= values["bound"] and values["ends_error"] <= 1e-12


def test_resample_and_variability_are_differentiable_in_the_states():
    x = torch.randn(2, 7, 2, dtype=torch.float64, requires_grad=True)

    def f(x):
        d = Demonstrations(x=x, dt=0.1)
        w = time_warp(d, 0.4, torch.Generator().manual_seed(0))
        return spatial_noise(w, 0.1, torch.Generator().manual_seed(1)).resample(11).x

    assert torch.autograd.gradcheck(f, (x,))
