"""The CasADi + IPOPT quadrotor NMPC anchor: its model and cost against an independent numpy/scipy
implementation, and its closed-loop behaviour (hover, recovery, tracking a moving reference)."""

import subprocess
import sys

import numpy as np
import pytest

ca = pytest.importorskip("casadi", reason="casadi is not installed (make bench-env installs the bench extra)")
Rotation = pytest.importorskip("scipy.spatial.transform").Rotation

from liecontrol.bench._casadi_quadrotor import CasadiQuadrotorMPC, run_closed_loop  # noqa: E402

G = 9.81
DT = 0.01
N = 8
E3 = np.array([0.0, 0.0, 1.0])
U_LO = np.array([0.0, -10.0, -10.0, -10.0])
U_HI = np.array([20.0, 10.0, 10.0, 10.0])
U_HOVER = np.array([G, 0.0, 0.0, 0.0])
# A short horizon (0.08 s) needs a terminal weight that stands in for the cost-to-go.
Q = np.repeat([100.0, 10.0, 1.0], 3)
P = np.repeat([1e5, 1e4, 1e2], 3)
RU = np.array([0.01, 1e-3, 1e-3, 1e-3])


def numpy_step(x, u, dt=DT, g=G):
    """The model written independently: Euler on p, v; R⁺ = R Exp(dt ω) with scipy's Exp."""
    p, v, rot = x
    return (
        p + dt * v,
        v + dt * (g * E3 - u[0] * rot @ E3),
        rot @ Rotation.from_rotvec(dt * np.asarray(u[1:])).as_matrix(),
    )


def make_mpc(**kw):
    args = dict(horizon=N, dt=DT, Q=Q, Ru=RU, P=P, u_lower=U_LO, u_upper=U_HI)
    args.update(kw)
    return CasadiQuadrotorMPC(**args)


def random_state(rng):
    return rng.normal(size=3), rng.normal(size=3), Rotation.random(random_state=rng).as_matrix()


def hover_ref():
    """A constant hover reference at the origin (one entry; ``run_closed_loop`` repeats it)."""
    return (np.zeros((1, 3)), np.zeros((1, 3)), np.eye(3)[None], U_HOVER[None])


def test_module_imports_without_casadi():
    code = (
        "import sys; sys.modules['casadi'] = None\n"
        "import liecontrol.bench._casadi_quadrotor as m\n"
        "assert m.CasadiQuadrotorMPC and m.run_closed_loop\n"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr


def test_model_matches_numpy():
    mpc = make_mpc()
    rng = np.random.default_rng(0)
    rates = [np.zeros(3), np.full(3, 1e-7), np.array([0.3, -0.2, 0.1]), np.array([40.0, -25.0, 60.0])]
    # Either side of the switch between Exp's series (θ² < 1e-4) and its closed form.
    unit = np.array([2.0, -1.0, 2.0]) / 3.0
    rates += [0.0099 / DT * unit, 0.0101 / DT * unit]
    rates += [rng.normal(scale=5.0, size=3) for _ in range(6)]
    for w in rates:
        x = random_state(rng)
        u = np.concatenate([[rng.uniform(0, 20)], w])
        got, want = mpc.dynamics(x, u), numpy_step(x, u)
        for a, b in zip(got, want):
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)


def test_model_jacobian_finite_and_correct_at_zero_rate():
    """Derivatives through Exp's series branch (ω = 0) and closed-form branch match finite differences."""
    mpc = make_mpc()
    z, u = ca.SX.sym("z", 15), ca.SX.sym("u", 4)
    jac = ca.Function("J", [z, u], [ca.jacobian(mpc._step_fn(z, u), u)])
    rng = np.random.default_rng(1)
    p, v, rot = random_state(rng)
    z0 = np.concatenate([p, v, rot.reshape(-1)])

    def flat(uu):
        pn, vn, rn = numpy_step((p, v, rot), uu)
        return np.concatenate([pn, vn, rn.reshape(-1)])

    for w in (np.zeros(3), np.array([0.02, -0.01, 0.03]), np.array([3.0, -2.0, 1.0])):
        u0 = np.concatenate([[G], w])
        j = np.asarray(jac(z0, u0))
        assert np.all(np.isfinite(j))
        h = 1e-6
        fd = np.stack([(flat(u0 + h * e) - flat(u0 - h * e)) / (2 * h) for e in np.eye(4)], axis=1)
        np.testing.assert_allclose(j, fd, rtol=0, atol=1e-8)


def test_state_error_is_so3_log():
    mpc = make_mpc()
    rng = np.random.default_rng(2)
    for angle in (0.0, 1e-9, 1e-5, 9e-5, 1.1e-4, 0.1, 1.0, 2.5, 3.0):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        x_ref = random_state(rng)
        delta = Rotation.from_rotvec(angle * axis).as_matrix()
        x = (x_ref[0] + rng.normal(size=3), x_ref[1] + rng.normal(size=3), x_ref[2] @ delta)
        e = mpc.state_error(x, x_ref)
        np.testing.assert_allclose(e[:3], x[0] - x_ref[0], atol=1e-14)
        np.testing.assert_allclose(e[3:6], x[1] - x_ref[1], atol=1e-14)
        want = Rotation.from_matrix(x_ref[2].T @ x[2]).as_rotvec()
        np.testing.assert_allclose(e[6:], want, rtol=0, atol=1e-12)


def test_hover_returns_hover_input():
    mpc = make_mpc()
    ref = (np.zeros((N + 1, 3)), np.zeros((N + 1, 3)), np.tile(np.eye(3), (N + 1, 1, 1)))
    u, info = mpc.step((np.zeros(3), np.zeros(3), np.eye(3)), ref, np.tile(U_HOVER, (N, 1)))
    assert info["success"], info["status"]
    np.testing.assert_allclose(u, U_HOVER, rtol=0, atol=1e-5)
    assert info["cost"] < 1e-8
    assert info["solve_time"] > 0 and info["iterations"] >= 0
    # Again, now from the shifted warm start.
    u, info = mpc.step((np.zeros(3), np.zeros(3), np.eye(3)), ref, np.tile(U_HOVER, (N, 1)))
    assert info["success"], info["status"]
    np.testing.assert_allclose(u, U_HOVER, rtol=0, atol=1e-5)


def test_closed_loop_recovers_from_offset_and_tilt():
    mpc = make_mpc()
    tilt = Rotation.from_rotvec(np.deg2rad(20.0) * np.array([1.0, 1.0, 0.0]) / np.sqrt(2)).as_matrix()
    x0 = (np.array([0.3, 0.0, 0.0]), np.zeros(3), tilt)
    steps = int(round(1.5 / DT))
    out = run_closed_loop(mpc, numpy_step, x0, hover_ref(), steps)
    assert out["p"].shape == (steps + 1, 3) and out["u"].shape == (steps, 4)
    assert out["R"].shape == (steps + 1, 3, 3) and out["solve_time"].shape == (steps,)
    assert out["success"].all(), set(out["status"])
    assert np.all(out["u"] >= U_LO) and np.all(out["u"] <= U_HI)
    assert np.all(out["solve_time"] > 0)
    err = np.linalg.norm(out["p"], axis=1)
    assert err[0] == pytest.approx(0.3)
    assert err[-1] < 0.02
    # The attitude and velocity settle as well (the quadrotor is back to hover, not passing through).
    assert np.linalg.norm(Rotation.from_matrix(out["R"][-1]).as_rotvec()) < np.deg2rad(2.0)
    assert np.linalg.norm(out["v"][-1]) < 0.05


def test_closed_loop_tracks_moving_reference():
    mpc = make_mpc()
    steps = int(round(1.5 / DT))
    t = DT * np.arange(steps + N + 1)
    p_ref = np.stack([t, np.zeros_like(t), np.zeros_like(t)], axis=1)
    v_ref = np.tile([1.0, 0.0, 0.0], (len(t), 1))
    ref = (p_ref, v_ref, np.tile(np.eye(3), (len(t), 1, 1)), np.tile(U_HOVER, (len(t), 1)))
    # The reference is consistent with the model: rolling it forward with u = hover reproduces it.
    x = (p_ref[0], v_ref[0], np.eye(3))
    for k in range(5):
        x = numpy_step(x, U_HOVER)
        np.testing.assert_allclose(x[0], p_ref[k + 1], atol=1e-12)
    out = run_closed_loop(mpc, numpy_step, (np.zeros(3), np.zeros(3), np.eye(3)), ref, steps)
    assert out["success"].all(), set(out["status"])
    assert np.all(out["u"] >= U_LO) and np.all(out["u"] <= U_HI)
    err = np.linalg.norm(out["p"] - p_ref[: steps + 1], axis=1)
    assert err[-1] < 0.02
    assert np.linalg.norm(out["v"][-1] - v_ref[0]) < 0.05


def test_bad_inputs_name_the_argument():
    with pytest.raises(ValueError, match="Q"):
        make_mpc(Q=np.ones(8))
    with pytest.raises(ValueError, match="Ru"):
        make_mpc(Ru=np.ones(3))
    with pytest.raises(ValueError, match="horizon"):
        make_mpc(horizon=0)
    with pytest.raises(ValueError, match="dt"):
        make_mpc(dt=-0.1)
    with pytest.raises(ValueError, match="u_lower"):
        make_mpc(u_lower=U_HI, u_upper=U_LO)
    mpc = make_mpc()
    x0 = (np.zeros(3), np.zeros(3), np.eye(3))
    ref = (np.zeros((N + 1, 3)), np.zeros((N + 1, 3)), np.tile(np.eye(3), (N + 1, 1, 1)))
    u_ref = np.tile(U_HOVER, (N, 1))
    with pytest.raises(ValueError, match=r"x0\.p"):
        mpc.step((np.zeros(2), np.zeros(3), np.eye(3)), ref, u_ref)
    with pytest.raises(ValueError, match=r"x0\.R"):
        mpc.step((np.zeros(3), np.zeros(3), 2 * np.eye(3)), ref, u_ref)
    with pytest.raises(ValueError, match=r"x_ref\.p"):
        mpc.step(x0, (np.zeros((N, 3)), ref[1], ref[2]), u_ref)
    with pytest.raises(ValueError, match="u_ref"):
        mpc.step(x0, ref, u_ref[:-1])
    with pytest.raises(ValueError, match=r"ref\.u"):
        run_closed_loop(mpc, numpy_step, x0, (*hover_ref()[:3], np.zeros((1, 3))), 1)
