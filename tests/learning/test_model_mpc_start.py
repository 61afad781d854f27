"""ModelMPC's real-time scheme (``multistart="start"``, ``start_iter``): an episode's first solve from the
multi-start set with the start settings, the later ones from the shifted plan with the running settings —
per element, so that a batch whose elements start their episodes at different steps is solved as each
element alone would be."""

from __future__ import annotations

import math

import pytest
import torch

gym = pytest.importorskip("gymnasium")

from learning.model_mpc import ModelMPC  # noqa: E402

F64 = torch.float64


def _obs(angles, rates):
    a, w = torch.tensor(angles, dtype=F64), torch.tensor(rates, dtype=F64)
    return torch.stack([torch.cos(a), torch.sin(a), w], -1)  # Pendulum-v1: [cos φ, sin φ, ω], φ = 0 upright


def _pol(**kw):
    return ModelMPC("Pendulum-v1", horizon=15, **kw)


def test_first_solve_is_the_multistart_one_and_later_solves_are_short():
    obs = _obs([0.07, 2.5, -3.0], [0.0, 1.0, -0.5])
    rt = _pol(multistart="start", start_iter=20, max_iter=1)
    full = _pol(multistart=True, max_iter=20)
    a0 = rt.act(obs)
    assert torch.equal(a0, full.act(obs))  # the same guesses, the same settings: the same solve
    assert torch.equal(rt.last_cost, full.last_cost)
    assert torch.equal(rt.info()["iterations"], full.info()["iterations"])
    assert rt.start_options.max_iter == 20 and rt.options.max_iter == 1
    # the start near upright is planned as braking, not as the full swing a zero start converges to
    assert rt.last_cost[0] < 1.0
    rt.act(obs)
    assert int(rt.info()["iterations"].max()) <= 1
    with pytest.raises(ValueError, match="multistart"):
        _pol(multistart="sometimes")
    with pytest.raises(ValueError, match="start_iter"):
        _pol(start_iter=0)


def test_elements_that_start_an_episode_are_solved_as_alone():
    obs = _obs([0.07, 2.5, -3.0], [0.0, 1.0, -0.5])
    nxt = _obs([0.1, 2.3, -2.9], [0.2, 0.5, -0.4])
    rt = _pol(multistart="start", start_iter=20, max_iter=2)
    rt.act(obs)
    steady = _pol(multistart="start", start_iter=20, max_iter=2)
    steady.act(obs)
    rt.reset(torch.tensor([False, True, False]))
    a = rt.act(nxt)
    its = rt.info()["iterations"]
    # element 1 starts afresh: as a new policy's first action on its observation alone
    fresh = _pol(multistart="start", start_iter=20, max_iter=2)
    torch.testing.assert_close(a[1:2], fresh.act(nxt[1:2]), rtol=0, atol=1e-12)
    assert int(its[1]) == int(fresh.info()["iterations"][0])
    # elements 0 and 2 go on from their plans with the running settings, as without the reset
    b = steady.act(nxt)
    torch.testing.assert_close(a[[0, 2]], b[[0, 2]], rtol=0, atol=1e-12)
    assert int(its[[0, 2]].max()) <= 2
    assert math.isfinite(float(rt.last_cost[1]))


def test_same_settings_solve_the_batch_once(monkeypatch):
    """Without a start setting of its own (the default), a reset element does not split the batch."""
    import learning.model_mpc as mm

    calls = []
    real = mm.ilqr_multistart
    monkeypatch.setattr(mm, "ilqr_multistart",
                        lambda p, U, **kw: calls.append(p.x0.shape) or real(p, U, **kw))
    pol = _pol(max_iter=3, multistart=False)
    obs = _obs([0.5, 1.0], [0.0, 0.0])
    pol.act(obs)
    pol.reset(torch.tensor([True, False]))
    pol.act(obs)
    assert calls == [(2, 2), (2, 2)]


def test_the_sampling_planner_joins_the_guesses_and_never_makes_a_certified_plan_worse(monkeypatch):
    """``sampling_start=True``: one more guess, the MPPI plan from the first guess; the chosen plan's cost is
    never above the plan chosen without it where that one was certified (a superset of guesses)."""
    import learning.model_mpc as mm

    sizes = []
    real = mm.ilqr_multistart
    monkeypatch.setattr(mm, "ilqr_multistart",
                        lambda p, U, **kw: sizes.append(U.shape[1]) or real(p, U, **kw))
    obs = _obs([3.1, 2.0, -1.0, 0.3], [0.0, -1.0, 2.0, 0.5])
    base, samp = _pol(max_iter=15), _pol(max_iter=15, sampling_start=True)
    base.act(obs)
    samp.act(obs)
    assert sizes[1] == sizes[0] + 1
    ok = base.info()["converged"]
    assert ok.any()
    assert (samp.last_cost[ok] <= base.last_cost[ok] + 1e-9).all()
    # the same seed repeats exactly
    again = _pol(max_iter=15, sampling_start=True)
    assert torch.equal(again.act(obs), _pol(max_iter=15, sampling_start=True).act(obs))
