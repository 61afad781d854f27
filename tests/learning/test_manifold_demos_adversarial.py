"""Adversarial regression tests for learning.manifold_demos (issue 26 §5): each test pins one defect found by
probing the module against independent references and bad inputs; all fail on the current code."""

import inspect

import pytest
import torch

from learning.manifold_demos import (
    BodyRateSO3,
    manifold_statistics,
    orientation_demos,
    reference_controls,
    track_mean,
)
from torchlie import se3, so3

F64 = torch.float64


def _gen(seed=0):
    return torch.Generator().manual_seed(seed)


def _tracking_setup():
    d = orientation_demos(6, 12, generator=_gen(5))
    st = manifold_statistics(d)
    x0 = st.mean[0] @ so3.exp(torch.tensor([0.3, 0.1, -0.2], dtype=F64))
    return BodyRateSO3(d.dt), st, x0


# ------------------------------------------------------------------------------------------ statistics
def test_s3_converged_mean_is_a_karcher_mean_of_the_rotations():
    # Large spread (rotation angles up to ~π): after the refinement some aligned samples lie outside the
    # final mean's hemisphere (S³ distance > π/2, i.e. rotation angle > π taken the long way round), so the
    # returned S³ fixed point is not a stationary point of Σ‖Log(μ⁻¹R_i)‖² although it reports converged.
    # Independent check: the SO(3) Karcher optimality residual ‖1/N Σ_i Log(μ⁻¹ R_i)‖ (torchlie so3 log,
    # the same quantity scipy's Rotation.as_rotvec gives) must vanish wherever converged is True.
    R = so3.exp(1.2 * torch.randn(10, 8, 3, generator=_gen(2), dtype=F64))
    st = manifold_statistics(so3.to_quaternion(R), "S3")
    mu = so3.from_quaternion(st.mean)                                        # (T, 3, 3)
    residual = so3.log(mu.mT.unsqueeze(0) @ R).mean(0).norm(dim=-1)         # (T,)
    bad = st.converged & (residual > 1e-8)
    steps = bad.nonzero().flatten().tolist()
    assert not bool(bad.any()), f"converged but not a Karcher mean at steps {steps}: {residual[bad].tolist()}"


def test_float32_pose_statistics_converge_with_large_translations():
    # Poses with translations ~1000 (e.g. millimetres) in float32: the mean is accurate to ~1e-7 relative,
    # but the absolute step tolerance eps^0.75 ≈ 6e-6 is below the translation round-off (~1e-4), so no
    # time step ever reports converged (max_iter exhausted).  float64 on the same data converges.
    g = _gen(3)
    C = se3.random(4, generator=g, dtype=F64)
    C[..., :3, 3] = 1000.0 * torch.nn.functional.normalize(C[..., :3, 3], dim=-1)
    eps = torch.cat([10.0 * torch.randn(8, 4, 3, generator=g, dtype=F64),
                     0.1 * torch.randn(8, 4, 3, generator=g, dtype=F64)], -1)
    X = C @ se3.exp(eps)
    s64 = manifold_statistics(X, "SE3")
    s32 = manifold_statistics(X.float(), "SE3")
    assert bool(s64.converged.all())
    rel = ((s32.mean.double() - s64.mean)[..., :3, 3].abs().amax() / 1000.0).item()
    assert rel < 1e-5                                                         # the float32 answer is right
    assert bool(s32.converged.all()), s32.iterations.tolist()


def test_off_manifold_error_does_not_suggest_a_missing_argument():
    # The membership error says "pass project=True", but manifold_statistics has no 'project' argument.
    K = torch.diag(torch.tensor([1.0, 1.0, 1e-17], dtype=F64)).expand(3, 2, 3, 3)
    with pytest.raises(ValueError, match="demos") as ei:
        manifold_statistics(K, "SPD")
    if "project=True" in str(ei.value):
        assert "project" in inspect.signature(manifold_statistics).parameters, str(ei.value)


@pytest.mark.parametrize("kwargs,name", [({"tol": -1.0}, "tol"), ({"tol": float("nan")}, "tol"),
                                         ({"max_iter": 1.5}, "max_iter")])
def test_statistics_bad_solver_options_name_the_argument(kwargs, name):
    R = so3.exp(0.3 * torch.randn(5, 4, 3, generator=_gen(1), dtype=F64))
    with pytest.raises((ValueError, TypeError), match=f"'{name}'"):
        manifold_statistics(R, "SO3", **kwargs)


def test_statistics_zero_demos_raise_a_clear_error():
    R = so3.exp(torch.zeros(0, 4, 3, dtype=F64))                             # N = 0
    with pytest.raises(ValueError, match="'demos'"):
        manifold_statistics(R, "SO3", unbiased=False)                        # now: ZeroDivisionError


# ------------------------------------------------------------------------------------------ tracking
def test_track_mean_batched_mean_with_one_start_broadcasts():
    # mean (*B, T, 3, 3) with B = 2 and one start x0 (3, 3): the docstring's (*B, ...) shapes broadcast
    # like torch.  Now: RuntimeError from torch.stack (x0 has no batch dim, the next states do).
    sys, st, x0 = _tracking_setup()
    mean2 = torch.stack([st.mean, st.mean @ so3.exp(torch.tensor([0.0, 0.0, 0.1], dtype=F64))])
    cov2 = torch.stack([st.covariance, 2 * st.covariance])
    run = track_mean(sys, mean2, cov2, x0, horizon=4, R=1.0)
    assert run.x.shape == (2, 12, 3, 3)
    for b in range(2):
        one = track_mean(sys, mean2[b], cov2[b], x0, horizon=4, R=1.0)
        assert torch.allclose(run.x[b], one.x, atol=1e-10)


def test_track_mean_batched_covariance_with_one_start_broadcasts():
    sys, st, x0 = _tracking_setup()
    cov2 = torch.stack([st.covariance, 4 * st.covariance])
    run = track_mean(sys, st.mean, cov2, x0, horizon=4, R=1.0)
    assert run.x.shape == (2, 12, 3, 3)
    one = track_mean(sys, st.mean, cov2[1], x0, horizon=4, R=1.0)
    assert torch.allclose(run.x[1], one.x, atol=1e-10)


def test_track_mean_rejects_an_indefinite_covariance():
    # A negative-definite "covariance" gives a negative-definite state weight Q_t; the Riccati solve still
    # reports success (reason 0) and the closed loop drifts away from the mean.  It must be rejected.
    sys, st, x0 = _tracking_setup()
    bad = -st.covariance - torch.eye(3, dtype=F64)
    with pytest.raises(ValueError, match="'covariance'"):
        track_mean(sys, st.mean, bad, x0, horizon=3, R=1.0)


def test_track_mean_rejects_non_finite_reference_controls():
    sys, st, x0 = _tracking_setup()
    u_ref = reference_controls(sys.manifold, st.mean, sys.dt).clone()
    u_ref[4, 1] = float("nan")                                               # now: NaN states, silently
    with pytest.raises(ValueError, match="'u_ref'"):
        track_mean(sys, st.mean, st.covariance, x0, horizon=3, u_ref=u_ref)


def test_track_mean_dtype_mismatch_names_the_argument():
    # mean float64 with x0 float32: the error comes from SO3.boxminus and names its 'x'/'y', not 'x0'.
    sys, st, x0 = _tracking_setup()
    with pytest.raises(TypeError, match="'x0'"):
        track_mean(sys, st.mean, st.covariance, x0.float(), horizon=3)


def test_track_mean_does_not_downcast_a_float64_R_silently():
    sys, st, x0 = _tracking_setup()
    with pytest.raises(TypeError, match="'R'"):
        track_mean(sys, st.mean.float(), st.covariance.float(), x0.float(), horizon=3,
                   R=torch.eye(3, dtype=F64))


def test_track_mean_incompatible_batches_raise_value_error():
    sys, st, x0 = _tracking_setup()
    with pytest.raises(ValueError, match="'x0'"):                            # now: RuntimeError from torch
        track_mean(sys, st.mean.expand(3, 12, 3, 3), st.covariance, x0.expand(2, 3, 3), horizon=3)


# ------------------------------------------------------------------------------------------ demos
@pytest.mark.parametrize("base", [[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
                                  torch.eye(3, dtype=F64).expand(2, 3, 3)])
def test_orientation_demos_bad_base_names_the_argument(base):
    # a list: AttributeError ('list' has no .to); a batch of bases: RuntimeError from broadcasting
    with pytest.raises((ValueError, TypeError), match="'base'"):
        orientation_demos(3, 5, generator=_gen(), base=base)


@pytest.mark.parametrize("kwargs,name", [({"noise": -1.0}, "noise"), ({"noise": [0.1, 0.2]}, "noise"),
                                         ({"warp": -1.0}, "warp")])
def test_orientation_demos_bad_variability_names_the_argument(kwargs, name):
    # now the errors come from learning.demos and name its 'scale' / 'strength'
    with pytest.raises(ValueError, match=f"'{name}'"):
        orientation_demos(3, 5, generator=_gen(), **kwargs)


# ------------------------------------------------------------------------------------------ defect 14 and
# the behaviour kept while fixing the others
def test_unbiased_must_be_a_bool():
    R = so3.exp(0.3 * torch.randn(5, 4, 3, generator=_gen(1), dtype=F64))
    with pytest.raises(TypeError, match="'unbiased'"):
        manifold_statistics(R, "SO3", unbiased=0)


def test_orientation_demos_non_finite_tangent_path_names_the_argument():
    xi = torch.zeros(5, 3, dtype=F64)
    xi[2, 1] = float("nan")
    with pytest.raises(ValueError, match="'tangent_path'"):
        orientation_demos(3, 5, generator=_gen(), tangent_path=xi)


def test_demos_errors_of_other_arguments_are_not_relabelled():
    with pytest.raises(ValueError, match="'n_basis'") as ei:
        orientation_demos(3, 5, generator=_gen(), n_basis=0)
    assert "'noise'" not in str(ei.value)


def test_track_mean_refuses_an_asymmetric_covariance_and_symmetrises_round_off():
    sys, st, x0 = _tracking_setup()
    skew = torch.tensor([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 0.0]], dtype=F64)
    scale = float(st.covariance.abs().max())
    with pytest.raises(ValueError, match="'covariance'.*symmetric"):
        track_mean(sys, st.mean, st.covariance + 0.1 * scale * skew, x0, horizon=3, R=1.0)
    tiny = st.covariance + 1e-12 * scale * skew                              # round-off: used as ½(Σ + Σᵀ)
    a = track_mean(sys, st.mean, tiny, x0, horizon=3, R=1.0)
    b = track_mean(sys, st.mean, 0.5 * (tiny + tiny.mT), x0, horizon=3, R=1.0)
    assert torch.equal(a.x, b.x)


def test_track_mean_non_finite_covariance_block_spoils_only_its_element():
    sys, st, x0 = _tracking_setup()
    cov2 = torch.stack([st.covariance, st.covariance.clone()])
    cov2[1, 3, 0, 0] = float("nan")
    run = track_mean(sys, st.mean, cov2, x0, horizon=4, R=1.0)
    one = track_mean(sys, st.mean, st.covariance, x0, horizon=4, R=1.0)
    assert torch.allclose(run.x[0], one.x, atol=1e-12)


def test_s3_statistics_gradient_matches_finite_differences():
    q0 = so3.to_quaternion(so3.exp(0.8 * torch.randn(4, 1, 3, generator=_gen(4), dtype=F64)))
    d0 = 0.01 * torch.randn(4, 1, 4, generator=_gen(5), dtype=F64)

    def f(d):
        q = torch.nn.functional.normalize(q0 + d, dim=-1)
        st = manifold_statistics(q, "S3")
        return st.mean * st.mean[..., :1].sign(), st.covariance

    assert torch.autograd.gradcheck(f, (d0.requires_grad_(),), atol=1e-6)


def test_se3_float64_statistics_are_invariant_to_the_translation_units():
    # the translation normalisation is exact: metres and millimetres give the same mean and Σ (ρ scaled)
    X = se3.random(6, 3, generator=_gen(6), dtype=F64)
    mm = X.clone()
    mm[..., :3, 3] *= 1000.0
    a, b = manifold_statistics(X, "SE3"), manifold_statistics(mm, "SE3")
    assert torch.allclose(b.mean[..., :3, 3], 1000.0 * a.mean[..., :3, 3], rtol=1e-9, atol=1e-9)
    assert torch.allclose(b.mean[..., :3, :3], a.mean[..., :3, :3], atol=1e-10)
    d = torch.tensor([1000.0] * 3 + [1.0] * 3, dtype=F64)
    assert torch.allclose(b.covariance, a.covariance * d[:, None] * d, rtol=1e-8, atol=1e-10)
