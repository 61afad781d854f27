"""Adversarial regression tests (issue 27b): ModelMPC's settings and per-element episode starts, and
check_model on asynchronous vector envs."""

from __future__ import annotations

import dataclasses

import pytest
import torch

gym = pytest.importorskip("gymnasium")

from controllers.ilqr import ILQROptions  # noqa: E402
from learning.env_models import check_model, env_model  # noqa: E402
from learning.model_mpc import ModelMPC  # noqa: E402

F64 = torch.float64


def _obs(angles, rates):
    a, w = torch.tensor(angles, dtype=F64), torch.tensor(rates, dtype=F64)
    return torch.stack([torch.cos(a), torch.sin(a), w], -1)


def test_max_iter_given_with_options_is_not_dropped():
    """``max_iter`` and ``options`` together: the solver ran options.max_iter, max_iter silently ignored."""
    pol = ModelMPC("Pendulum-v1", horizon=10, max_iter=7, options=ILQROptions(max_iter=3, tol_kkt=1e-5))
    assert pol.options.max_iter == 7 and pol.options.tol_kkt == 1e-5
    assert ModelMPC("Pendulum-v1", options=ILQROptions(max_iter=3)).options.max_iter == 3  # options alone
    r = pol.replace()
    assert r.options == pol.options and r.start_options == pol.start_options


def test_batch_elements_with_nan_or_a_fresh_start_do_not_change_the_others():
    """A NaN observation gives that element NaN and no certificate, the others their own solves; a partial
    reset with a start setting (start_iter) splits the batch, each part as solved alone."""
    obs = _obs([0.5, 1.0, 2.0], [0.0, 0.3, -0.2])
    bad = obs.clone()
    bad[1, 2] = float("nan")
    pol = ModelMPC("Pendulum-v1", horizon=10, max_iter=5)
    a = pol.act(bad)
    ref = ModelMPC("Pendulum-v1", horizon=10, max_iter=5)
    torch.testing.assert_close(a[[0, 2]], ref.act(obs[[0, 2]]), rtol=0, atol=1e-12)
    assert a[1].isnan().all() and not bool(pol.info()["converged"][1])
    # multistart=False with start_iter: the reset element's solve is the fresh policy's
    run = ModelMPC("Pendulum-v1", horizon=10, max_iter=1, start_iter=10, multistart=False)
    run.act(obs)
    run.reset(torch.tensor([False, False, True]))
    a = run.act(obs)
    fresh = ModelMPC("Pendulum-v1", horizon=10, max_iter=1, start_iter=10, multistart=False)
    torch.testing.assert_close(a[2:], fresh.act(obs[2:]), rtol=0, atol=1e-12)
    assert int(run.info()["iterations"][:2].max()) <= 1


def test_observation_of_the_wrong_width_is_refused():
    """EnvModel.obs_dim: an observation of another width is refused, not read by its first columns."""
    pol = ModelMPC("Pendulum-v1", horizon=5, max_iter=2)
    with pytest.raises(ValueError, match=r"'obs' must have shape \(N, 3\)"):
        pol.act(torch.zeros(2, 4, dtype=F64))
    import learning.env_models as em

    bad = dataclasses.replace(em.env_model("Pendulum-v1"), obs_dim=4)
    with pytest.raises(ValueError, match="observes shape"):
        check_model(bad, gym.make("Pendulum-v1"))


def test_check_model_accepts_an_async_vector_env_and_checks_its_time_step():
    """An AsyncVectorEnv's spec carries make_vec's own arguments (num_envs, vectorization_mode): env_model
    refused an unchanged env as 'made with {num_envs: 2, ...}', and its dt (in the workers) went unchecked."""
    venv = gym.make_vec("InvertedPendulum-v5", num_envs=2, vectorization_mode="async")
    try:
        md = env_model(venv)
        assert md.env_id == "InvertedPendulum-v5"
        from controllers.systems.mujoco_system import MujocoSystem

        other = dataclasses.replace(md, system=MujocoSystem(md.system.model, frame_skip=1))  # dt 0.02 vs 0.04
        with pytest.raises(ValueError, match="dt"):
            check_model(other, venv)
    finally:
        venv.close()
    venv = gym.make_vec("InvertedPendulum-v5", num_envs=2, vectorization_mode="async", frame_skip=4)
    try:
        with pytest.raises(ValueError, match="frame_skip"):
            env_model(venv)
    finally:
        venv.close()
