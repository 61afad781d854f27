"""Perturbed tasks and the robustness study (learning.robustness)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from learning.envs import CartPoleSwingUp, PendulumSwingUp, QuadrotorTrack
from learning.evaluate import evaluate
from learning.policies import task_expert
from learning.robustness import (
    QUADROTOR_DRAG,
    default_perturbations,
    perturbable_parameters,
    perturbed_task,
    records_table,
    robustness_study,
)
from learning.vector import TaskVectorEnv

D = torch.float64


def test_perturbed_cartpole_changes_the_acceleration_by_the_closed_form():
    nom = CartPoleSwingUp()
    t = perturbed_task("CartPoleSwingUp", pole_mass=1.3, length=0.7)
    assert (nom.model.pole_mass, nom.model.length) == (0.3, 0.5)  # the nominal task is not touched
    mc, mp, ln, g = 1.0, 0.3 * 1.3, 0.5 * 0.7, 9.81
    x = torch.tensor([[0.1, 0.7, -0.3, 2.0], [0.0, 3.0, 1.0, -1.0]], dtype=D)
    u = torch.tensor([[4.0], [-2.0]], dtype=D)
    s, c, w = torch.sin(x[:, 1]), torch.cos(x[:, 1]), x[:, 3]
    Dn = mc + mp * s * s
    thdd = -(u[:, 0] * c + mp * ln * w * w * s * c + (mc + mp) * g * s) / (ln * Dn)
    pdd = (u[:, 0] + mp * s * (ln * w * w + g * c)) / Dn
    want = torch.stack([pdd, thdd], -1)
    torch.testing.assert_close(t.model.acceleration(x, u), want, rtol=1e-14, atol=1e-14)
    assert not torch.allclose(t.step(x, u), nom.step(x, u))
    assert perturbed_task(nom, cart_mass=0.7).model.cart_mass == pytest.approx(0.7)


def test_perturbed_quadrotor_mass_and_drag():
    t = perturbed_task("QuadrotorCircle", mass=1.3, drag=QUADROTOR_DRAG)
    assert isinstance(t, QuadrotorTrack) and t.mass_scale == pytest.approx(1.3)
    assert t.drag == (0.3, 0.3, 0.3) and t.system.quad.drag == (0.3, 0.3, 0.3)
    assert perturbed_task(t, mass=0.5).mass_scale == pytest.approx(0.65)  # factors compose
    assert perturbed_task("QuadrotorFigureEight", drag=(0.1, 0.2, 0.0)).shape == "figure8"
    # the vector env steps the perturbed model: level, moving east at 2 m/s, thrust a_T = g
    x = torch.cat([torch.zeros(3), torch.tensor([0.0, 2.0, 0.0]), torch.eye(3).reshape(9), torch.zeros(1)])
    y = t.step(x[None].double(), torch.zeros(1, 4, dtype=D))
    dv = (y[0, 3:6] - x[3:6].double()) / t.dt
    torch.testing.assert_close(dv, torch.tensor([0.0, -0.3 * 2.0, 9.81 - 9.81 / 1.3], dtype=D),
                               rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("task, name, words", [
    ("CartPoleSwingUp", "arm_length", "no physical parameter 'arm_length'"),
    ("QuadrotorCircle", "arm_length", "body-rate controlled"),
    ("QuadrotorCircle", "inertia", "no arm length or inertia"),
    ("QuadrotorCircle", "pole_mass", "no physical parameter 'pole_mass'"),
    ("CartPoleSwingUp", "dt", "no physical parameter 'dt'"),
])
def test_unknown_factor_is_an_error_naming_it(task, name, words):
    with pytest.raises(ValueError, match=words):
        perturbed_task(task, **{name: 1.3})
    with pytest.raises(ValueError, match=name):
        robustness_study({"zero": lambda o: torch.zeros(o.shape[0], 4)}, task, {"bad": {name: 1.3}})


@pytest.mark.parametrize("kwargs, name", [
    (dict(pole_mass=-1.0), "pole_mass"), (dict(length=0.0), "length"),
    (dict(cart_mass=math.inf), "cart_mass"), (dict(length="1"), "length")])
def test_bad_factor_values(kwargs, name):
    with pytest.raises(ValueError, match=name):
        perturbed_task("CartPoleSwingUp", **kwargs)
    with pytest.raises(ValueError, match="drag"):
        perturbed_task("QuadrotorCircle", drag=(0.1, -0.1, 0.0))
    with pytest.raises(ValueError, match="damping"):  # nominal 0: a factor cannot perturb it
        perturbed_task(PendulumSwingUp(), damping=1.3)


def test_defaults_are_identical():
    nom = CartPoleSwingUp()
    assert perturbed_task(nom) is nom
    same = perturbed_task(nom, pole_mass=1.0, length=1.0)
    g = torch.Generator().manual_seed(0)
    x, u = torch.randn(16, 4, generator=g, dtype=D), torch.randn(16, 1, generator=g, dtype=D)
    assert torch.equal(same.step(x, u), nom.step(x, u))
    # the quadrotor: the default obs bound is the nominal-model formula, and a unit perturbation is a no-op
    q, q1 = QuadrotorTrack(), perturbed_task("QuadrotorCircle", mass=1.0, drag=0.0)
    ref = q._reference_f64()
    nxt = torch.roll(torch.arange(q.period_steps), -1)
    dv = float((ref.v[nxt] - ref.v).abs().max())
    ev = q.velocity_limit + q.dt * 3 * q.gravity + dv
    assert q.obs_high()[3] == ev * (1.0 + 1e-6)
    assert np.array_equal(q.obs_high(), q1.obs_high())
    xq = q.initial_state(torch.rand(8, q.n_noise, generator=g, dtype=D))
    uq = torch.rand(8, 4, generator=g, dtype=D) * 2 - 1
    assert torch.equal(q.step(xq, uq), q1.step(xq, uq))
    assert torch.equal(q.reference()["u"], q1.reference()["u"])
    assert set(default_perturbations(q)) == {"nominal", "mass×0.7", "mass×1.3", "drag=0.3/s"}
    assert perturbable_parameters(q) == ("mass", "drag")


@pytest.mark.parametrize("factors", [dict(mass=0.7), dict(mass=1.3, drag=1.0)])
def test_perturbed_quadrotor_observations_stay_within_obs_high(factors):
    task = perturbed_task("QuadrotorCircle", **factors)
    N = 32
    env = TaskVectorEnv(task, N, dtype=D, autoreset_mode="same_step", output="torch")
    high = torch.as_tensor(env.single_observation_space.high, dtype=D)
    env.reset(seed=0)
    g = torch.Generator().manual_seed(1)
    ends = 0
    for _ in range(200):
        a = torch.where(torch.rand(N, 4, generator=g, dtype=D) < 0.5, -1.0, 1.0).to(D)
        o, r, te, tr, info = env.step(a)
        assert (o.abs() <= high).all()
        if "final_obs" in info:
            assert (info["final_obs"][info["_final_obs"]].abs() <= high).all()
            ends += int(info["_final_obs"].sum())
    assert ends > N


def test_nominal_mpc_loses_return_on_the_heavier_quadrotor_and_the_study_records_it():
    """The nominal expert commands hover at a_T = g: on a vehicle 30 % heavier it sags below the lap, so
    every episode's return drops (same seeds = same initial states); the perturbed task's own expert
    (planning with the true mass) recovers most of it.  The study gives the same numbers as ``evaluate``."""
    nom = QuadrotorTrack()
    heavy = perturbed_task(nom, mass=1.3)
    kw = dict(seeds=[0, 1, 2], max_episode_steps=40, progress=False, timing_batch1=False)
    expert = task_expert(nom, 10)
    r_nom = evaluate(expert, nom, **kw)
    r_heavy = evaluate(expert, heavy, **kw)
    r_own = evaluate(task_expert(heavy, 10), heavy, **kw)
    assert (r_heavy.returns < r_nom.returns).all()
    assert (r_own.returns > r_heavy.returns).all()
    policies = {"mpc": expert, "hover": lambda o: torch.zeros(o.shape[0], 4, dtype=o.dtype)}
    recs = robustness_study(policies, nom, {"nominal": {}, "heavy": {"mass": 1.3}}, seeds=[0, 1, 2],
                            max_episode_steps=40)
    assert [(r["policy"], r["perturbation"]) for r in recs] == [
        ("mpc", "nominal"), ("mpc", "heavy"), ("hover", "nominal"), ("hover", "heavy")]
    keys = {"policy", "perturbation", "factors", "return_mean", "return_std", "success_rate", "final_error",
            "terminated_rate", "episodes"}
    assert all(set(r) == keys and r["episodes"] == 3 for r in recs)
    assert recs[1]["factors"] == {"mass": 1.3}
    assert recs[0]["return_mean"] == pytest.approx(float(r_nom.returns.mean()), rel=1e-12)
    assert recs[1]["return_mean"] == pytest.approx(float(r_heavy.returns.mean()), rel=1e-12)
    assert recs[1]["return_std"] == pytest.approx(float(r_heavy.returns.std()), rel=1e-9)
    assert recs[1]["final_error"] == pytest.approx(float(r_heavy.final_error.mean()), rel=1e-12)
    assert "| mpc | heavy |" in records_table(recs)


def test_study_builds_the_mpc_string_on_the_nominal_task():
    """``"mpc"`` is the nominal expert (plans with the nominal model), not the perturbed task's own."""
    nom = QuadrotorTrack()
    heavy = perturbed_task(nom, mass=1.3)
    kw = dict(seeds=[4, 5], max_episode_steps=15)
    (rec,) = robustness_study({"mpc": "mpc"}, nom, {"heavy": {"mass": 1.3}}, **kw)
    own = evaluate(task_expert(heavy), heavy, progress=False, timing_batch1=False, **kw)
    nominal = evaluate(task_expert(nom), heavy, progress=False, timing_batch1=False, **kw)
    assert rec["return_mean"] == pytest.approx(float(nominal.returns.mean()), rel=1e-12)
    assert rec["return_mean"] != pytest.approx(float(own.returns.mean()), rel=1e-6)
    with pytest.raises(ValueError, match="policies"):
        robustness_study({}, nom)
    with pytest.raises(ValueError, match="episodes"):
        robustness_study({"mpc": "mpc"}, nom, episodes=0)
