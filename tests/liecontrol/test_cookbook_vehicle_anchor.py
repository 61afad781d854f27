"""The numpy anchor of the cookbook car and bicopter (``liecontrol/bench/_cookbook_vehicle_anchor.py``): its
models are the library's (``CarVelocity``, ``Bicopter`` with absolute thrusts) step for step, its ``S_u`` is
the Jacobian of its rollout, and its command line reports a solve or an error."""

from __future__ import annotations

import importlib.util
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from controllers.dynamics import rollout
from controllers.systems.bicopter import Bicopter
from controllers.systems.car_velocity import CarVelocity
from liecontrol.bench import solver

_PATH = Path(solver.__file__).with_name("_cookbook_vehicle_anchor.py")
_spec = importlib.util.spec_from_file_location("cookbook_vehicle_anchor_under_test", _PATH)
anchor = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(anchor)

D = torch.float64
CAR = (0.7, 0.05)  # ℓ, Δt: not the defaults, so that a parameter read in the wrong place shows
BICOPTER = (1.7, 0.9, 0.4, 9.5, 0.03)  # m, I, ℓ, g, Δt


def _models(name):
    if name == "car":
        return anchor.make_system("car", CAR), CarVelocity(length=CAR[0], dt=CAR[1])
    m, inertia, arm, g, dt = BICOPTER
    return (anchor.make_system("bicopter", BICOPTER),
            Bicopter(mass=m, inertia=inertia, arm=arm, gravity=g, dt=dt, hover_relative=False))


def _random_xu(name, shape, seed=0):
    g = torch.Generator().manual_seed(seed)
    n = 4 if name == "car" else 6
    x = 2 * torch.rand(*shape, n, generator=g, dtype=D) - 1
    if name == "car":
        x[..., 3] *= 1.2  # steering angle well inside (-π/2, π/2)
    x[..., 2] *= math.pi
    u = 4 * torch.rand(*shape, 2, generator=g, dtype=D) - 2
    if name == "bicopter":
        u = u + 10.0  # absolute thrusts around hover
    return x, u


@pytest.mark.parametrize("name", ["car", "bicopter"])
def test_step_and_jacobian_are_the_library_models(name):
    ours, lib = _models(name)
    x, u = _random_xu(name, (5, 7))
    np.testing.assert_allclose(ours.step(x.numpy(), u.numpy()), lib.step(x, u).numpy(), rtol=0, atol=1e-12)
    A, B = ours.jacobian(x.numpy(), u.numpy())
    A_lib, B_lib = lib.jacobian(x, u)
    assert A.shape == (5, 7, lib.n, lib.n) and B.shape == (5, 7, lib.n, 2)
    np.testing.assert_allclose(A, A_lib.numpy(), rtol=0, atol=1e-12)
    np.testing.assert_allclose(B, B_lib.numpy(), rtol=0, atol=1e-12)
    # one state at a time (the rollout's use) gives the same numbers
    x1, u1 = x[1, 2], u[1, 2]
    np.testing.assert_allclose(ours.step(x1.numpy(), u1.numpy()), lib.step(x1, u1).numpy(), rtol=0,
                               atol=1e-12)


def _problem(name, T, iterations, x0=None, u_init=None):
    n = 4 if name == "car" else 6
    g = np.random.default_rng(3)
    return {"system": np.array(name), "params": np.asarray(CAR if name == "car" else BICOPTER),
            "T": np.array(T), "x0": g.uniform(-0.3, 0.3, n) if x0 is None else x0,
            "target": np.linspace(0.5, 1.0, n), "QT": 1e3 * np.eye(n), "r": np.array(1e-2),
            "u_init": (np.full((T, 2), 8.0) if name == "bicopter" else np.full((T, 2), 0.3))
            if u_init is None else u_init,
            "iterations": np.array(iterations), "alpha_min": np.array(1e-3)}


@pytest.mark.parametrize("name", ["car", "bicopter"])
def test_rollout_and_transfer_matrix_are_the_library_rollout_and_its_jacobian(name):
    T = 6
    d = _problem(name, T, 1)
    prob = anchor.BatchILQR(d)
    _, lib = _models(name)
    u = torch.as_tensor(d["u_init"]) + 0.1 * torch.randn(T, 2, generator=torch.Generator().manual_seed(1),
                                                          dtype=D)
    x0 = torch.as_tensor(d["x0"])
    x_lib = rollout(lib.dynamics(), x0, u)
    x = prob.rollout(u.numpy())
    np.testing.assert_allclose(x, x_lib.numpy(), rtol=0, atol=1e-12)
    # S_u = ∂x/∂u of the rollout (Eq. 188), by autograd through the library's model
    J = torch.autograd.functional.jacobian(lambda v: rollout(lib.dynamics(), x0, v), u)
    Su = prob.transfer(x, u.numpy())
    np.testing.assert_allclose(Su, J.reshape((T + 1) * lib.n, T * 2).numpy(), rtol=0, atol=1e-10)
    # the dense cost of the script is the library's QuadraticCost on the same trajectory
    e = x[-1] - d["target"]
    assert prob.cost(u.numpy()) == pytest.approx(1e3 * e @ e + 1e-2 * float((u * u).sum()), rel=1e-12)


@pytest.mark.parametrize("name", ["car", "bicopter"])
def test_command_line_solves_and_reports(name, tmp_path, capsys):
    f = tmp_path / "p.npz"
    np.savez(f, **_problem(name, 15, 4))
    assert anchor.main([str(f), "--repeats", "1"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["ok"] and out["error"] is None and out["ms"] > 0
    assert len(out["costs"]) == 4 and len(out["u"]) == 15 * 2
    assert out["cost"] == out["costs"][-1]
    # Algorithm 1's line search: on these problems each iteration lowers the cost, and by far overall
    d = _problem(name, 15, 4)
    c0 = anchor.BatchILQR(d).cost(d["u_init"])
    assert all(b <= a for a, b in zip([c0, *out["costs"]], out["costs"]))
    assert out["cost"] < 0.5 * c0


def test_command_line_reports_a_bad_problem(tmp_path, capsys):
    f = tmp_path / "p.npz"
    np.savez(f, **{**_problem("car", 5, 1), "system": np.array("boat")})
    assert anchor.main([str(f)]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["ok"] is False and "boat" in out["error"]
