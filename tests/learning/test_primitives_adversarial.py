"""Adversarial regression tests for learning/primitives.py (issue 26 §3).

Each test pins a defect found by probing: it fails on the current code and passes once fixed.  Where the
math leaves the choice open (a redundant noiseless observation may be handled by a pseudo-inverse or be
refused), either a correct answer or a ``ValueError`` naming the argument is accepted; a silent NaN /
wrong answer / bare ``LinAlgError`` is not.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from learning.primitives import fit_dmp, fit_promp, perturbation_recovery, via_point_error
from tests.learning.demo_data import smooth_demos

D64 = torch.float64


def _model():
    pm = fit_promp(smooth_demos(), dt=0.04, n_basis=8)
    y = pm.state_mean()[[15], :2] + 0.05
    return pm, y


def _assert_conditioned_or_refused(make, ref_mean, t, y):
    """``make()`` is either refused with a ValueError, or gives the reference mean and passes through y."""
    try:
        c = make()
    except ValueError:
        return
    assert torch.isfinite(c.mean).all() and torch.isfinite(c.cov).all()
    torch.testing.assert_close(c.mean, ref_mean, atol=1e-6, rtol=1e-6)
    assert via_point_error(c.state_mean(), [t], y).max() < 1e-8


# ------------------------------------------------------------------------------ noiseless conditioning


def test_condition_two_identical_via_points_same_step_noiseless():
    # H has two identical row blocks -> H Σ Hᵀ singular; cholesky_ex's failure was ignored -> all-NaN mean
    pm, y = _model()
    ref = pm.condition([15], y).mean
    _assert_conditioned_or_refused(lambda: pm.condition([15, 15], torch.cat([y, y])), ref, 15, y)


def test_condition_twice_on_the_same_point_noiseless():
    # after an exact conditioning, H Σ' Hᵀ ≈ 0: conditioning again on the same (consistent) data must be a
    # no-op; it moved the mean by ~2e3
    pm, y = _model()
    c1 = pm.condition([15], y)
    _assert_conditioned_or_refused(lambda: c1.condition([15], y), c1.mean, 15, y)


def test_condition_rank_deficient_observation_noiseless():
    # C = [[1, 0, 0, 0], [2, 0, 0, 0]] with consistent targets (v, 2v): the result missed the via point
    # by 0.45
    pm, _ = _model()
    v = pm.state_mean()[15, 0] + 0.05
    C = torch.tensor([[1.0, 0, 0, 0], [2.0, 0, 0, 0]], dtype=D64)
    ref = pm.condition([15], v.reshape(1, 1), C=C[:1])
    try:
        c = pm.condition([15], torch.stack([v, 2 * v]).reshape(1, 2), C=C)
    except ValueError:
        return
    torch.testing.assert_close(c.mean, ref.mean, atol=1e-6, rtol=1e-6)
    assert (c.state_mean()[15, 0] - v).abs() < 1e-8


def test_condition_rejects_a_negative_definite_noise_covariance():
    # noise = -I was accepted; H Σ Hᵀ - I is indefinite, the failed Cholesky was ignored, a garbage mean
    # came out
    pm, y = _model()
    with pytest.raises(ValueError, match="noise"):
        pm.condition([10], y, noise=-torch.eye(2, dtype=D64)[None])


# ------------------------------------------------------------------------------ NaN isolation


def test_sample_nan_element_does_not_poison_the_batch():
    # linalg.eigh of the NaN element's covariance raised for the whole batch
    clean = smooth_demos(N=5, T=20, b=(2,))
    x = clean.clone()
    x[0, 2, 7, 1] = float("nan")
    s = fit_promp(x, dt=0.05, n_basis=5).sample(3, torch.Generator().manual_seed(0))
    ref = fit_promp(clean, dt=0.05, n_basis=5).sample(3, torch.Generator().manual_seed(0))  # same noise draws
    assert s.shape == (3, 2, 20, 4)
    torch.testing.assert_close(s[:, 1], ref[:, 1], atol=1e-10, rtol=1e-10)


def test_track_nan_element_does_not_poison_the_batch():
    # torch.linalg.cholesky of the NaN element's Σ_t raised for the whole batch
    x = smooth_demos(N=5, T=20, b=(2,)).clone()
    x[0, 2, 7, 1] = float("nan")
    pm = fit_promp(x, dt=0.05, n_basis=5)
    ref = fit_promp(x[1], dt=0.05, n_basis=5).track()
    tr = pm.track()
    torch.testing.assert_close(tr.x[1], ref.x, atol=1e-8, rtol=1e-8)
    assert bool(tr.status.converged[1]) and not bool(tr.status.converged[0])


def test_track_floor_zero_on_exactly_conditioned_start():
    # floor = 0 is accepted, but after given_start Σ_0 = 0 and a bare torch LinAlgError came out
    pm, _ = _model()
    c = pm.given_start(pm.state_mean()[0])
    try:
        tr = c.track(floor=0.0)
    except ValueError as e:
        assert "floor" in str(e)
        return
    assert torch.isfinite(tr.x).all()


# ------------------------------------------------------------------------------ gradients


def test_track_gradient_wrt_demos_gradcheck():
    # Riccati's default implicit mode returns K, k without a graph; track rolls out with them, so the gradient
    # of track().x w.r.t. the demos silently dropped the feedback law's dependence (relative error 1.0)
    x0 = smooth_demos(N=3, T=6)

    def f(x):
        return fit_promp(x, dt=0.1, n_basis=2, reg=1e-3).track(control_weight=1e-2, floor=1e-2).x

    torch.autograd.gradcheck(f, (x0.clone().requires_grad_(),), fast_mode=True)


def test_track_gradient_wrt_via_point_gradcheck():
    x0 = smooth_demos(N=4, T=8)
    pm = fit_promp(x0, dt=0.1, n_basis=3, reg=1e-3)
    y0 = pm.state_mean()[[5], :2] + 0.05

    def f(y):
        return pm.condition([5], y, noise=1e-2).track(control_weight=1e-2, floor=1e-2).x

    torch.autograd.gradcheck(f, (y0.clone().requires_grad_(),), fast_mode=True)


# ------------------------------------------------------------------------------ broadcasting / inputs


@pytest.mark.parametrize("shape", [(2,), (1, 2), (4, 1, 2)])
def test_dmp_reproduce_position_start_broadcasts(shape):
    # x0 given as positions (..., D) broadcasting with the N DMPs raised a RuntimeError from expand
    x = smooth_demos(N=3, T=30)
    dm = fit_dmp(x, dt=0.05, n_basis=10)
    p0 = torch.linspace(0.1, 0.4, math.prod(shape), dtype=D64).reshape(shape)
    r = dm.reproduce(x0=p0)
    bs = torch.broadcast_shapes(shape[:-1], (3,))
    ref = dm.reproduce(x0=p0.expand(*bs, 2).clone())
    torch.testing.assert_close(r.x, ref.x)
    torch.testing.assert_close(r.x[..., 0, :2], p0.expand(*bs, 2))


def test_via_point_error_accepts_numpy_steps():
    # the metrics accept numpy arrays (module docstring), but a numpy t_idx raised TypeError
    rng = np.random.default_rng(0)
    b, tg = rng.normal(size=(3, 10, 4)), rng.normal(size=(3, 2, 2))
    v = via_point_error(b, np.array([2, 7]), tg)
    np.testing.assert_allclose(v.numpy(), np.linalg.norm(b[:, [2, 7], :2] - tg, axis=-1))


def test_push_step_accepts_numpy_integer():
    # perturbation_recovery accepts np.int64 for 'at'; DMP.reproduce and ProMP.track refused it
    x = smooth_demos(N=3, T=30)
    push = torch.tensor([0.1, -0.1], dtype=D64)
    dm = fit_dmp(x, dt=0.05, n_basis=10)
    torch.testing.assert_close(dm.reproduce(perturbation=push, at=np.int64(5)).x,
                               dm.reproduce(perturbation=push, at=5).x)
    pm = fit_promp(x, dt=0.05, n_basis=5)
    torch.testing.assert_close(pm.track(perturbation=push, at=np.int64(5)).x,
                               pm.track(perturbation=push, at=5).x)
    nom = pm.track().x
    assert perturbation_recovery(nom, pm.track(perturbation=push, at=5).x, np.int64(5)).peak.min() > 0.1
