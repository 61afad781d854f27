"""Gradients of ``controllers.ik.dls_joint_velocity`` (adversarial check after issue 22, D7): autograd through
the SVD gave NaN for a rank-deficient J (repeated zero singular values) even with damping 0.1, where the DLS
map is smooth; with a J shared by the batch every element's gradient was NaN.  References: central
differences (``torch.autograd.gradcheck``), the closed form ``Jᵀ (J Jᵀ + λ² I)⁻¹ ξ`` differentiated by
autograd through a dense solve, and a per-sample loop."""

import math

import torch
from torch.autograd import gradcheck

from controllers.ik import dls_joint_velocity

D = torch.float64


def _gen(seed):
    return torch.Generator().manual_seed(seed)


def _closed_form(J, xi, lam):
    A = J @ J.mT + (lam * lam)[..., None, None] * torch.eye(J.shape[-2], dtype=J.dtype)
    return (J.mT @ torch.linalg.solve(A, xi.unsqueeze(-1))).squeeze(-1)


def _rank_deficient(seed, m=6, n=7, r=3):
    g = _gen(seed)
    return torch.randn(m, r, dtype=D, generator=g) @ torch.randn(r, n, dtype=D, generator=g)


def test_damped_gradient_at_a_rank_deficient_J_matches_the_closed_form_and_central_differences():
    g = _gen(0)
    J = torch.randn(6, 7, dtype=D, generator=g)
    J[3:] = 0.0  # rank 3: a wrist singularity (the adversarial reproducer)
    xi = torch.randn(6, dtype=D, generator=g)
    lam = torch.tensor(0.1, dtype=D)
    Jg = J.clone().requires_grad_(True)
    (gJ,) = torch.autograd.grad(dls_joint_velocity(Jg, xi, lam).sum(), Jg)
    Jr = J.clone().requires_grad_(True)
    (gR,) = torch.autograd.grad(_closed_form(Jr, xi, lam).sum(), Jr)
    assert torch.isfinite(gJ).all()
    torch.testing.assert_close(gJ, gR, rtol=1e-9, atol=1e-9)
    # central differences in J, twist and λ (float64), at rank-deficient, rank-1, zero and full-rank J
    for Ji in (J, _rank_deficient(1), _rank_deficient(2, r=1), torch.zeros(6, 7, dtype=D),
               torch.randn(6, 7, dtype=D, generator=g), torch.eye(6, 7, dtype=D)):  # eye: σ all equal
        args = (Ji.clone().requires_grad_(True), xi.clone().requires_grad_(True),
                torch.tensor([0.1, 0.5], dtype=D, requires_grad=True))
        assert gradcheck(lambda a, b, c: dls_joint_velocity(a, b, c), args)
    # J (6, 4) of rank 2: J Jᵀ + λ² I is λ² I on the part of ξ outside the range of J
    J64 = torch.randn(6, 2, dtype=D, generator=g) @ torch.randn(2, 4, dtype=D, generator=g)
    args = (J64.requires_grad_(True), xi.clone().requires_grad_(True),
            torch.tensor(0.3, dtype=D, requires_grad=True))
    assert gradcheck(dls_joint_velocity, args)


def test_undamped_and_nullspace_gradients_match_central_differences():
    """λ = 0 (J⁺ ξ) and the null-space projector: smooth at a full-rank J (also with all singular values
    equal, where autograd through the SVD divides by zero)."""
    g = _gen(4)
    lo, hi = -torch.ones(7, dtype=D), 2 * torch.ones(7, dtype=D)
    for J in (torch.randn(6, 7, dtype=D, generator=g), torch.eye(6, 7, dtype=D)):
        args = (J.requires_grad_(True), torch.randn(6, dtype=D, generator=g, requires_grad=True),
                torch.rand(7, dtype=D, generator=g, requires_grad=True),
                torch.tensor(2.0, dtype=D, requires_grad=True))
        assert gradcheck(lambda a, b, q, k: dls_joint_velocity(a, b, 0.0, q, (lo, hi), k), args)
        assert gradcheck(lambda a, b, q, k: dls_joint_velocity(a, b, 0.05, q, (lo, hi), k), args)
    # J = A B of rank 3: J⁺ and I − J⁺ J jump where the rank changes, but are smooth along changes of A and B
    # (central differences are the reference there); the chain rule through J must give them
    A, B = torch.randn(6, 3, dtype=D, generator=g), torch.randn(3, 7, dtype=D, generator=g)
    xi, q = torch.randn(6, dtype=D, generator=g), torch.rand(7, dtype=D, generator=g)
    args = (A.requires_grad_(True), B.requires_grad_(True))
    assert gradcheck(lambda a, b: dls_joint_velocity(a @ b, xi, 0.0), args)
    assert gradcheck(lambda a, b: dls_joint_velocity(a @ b, xi, 0.0, q, (lo, hi)), args)
    assert gradcheck(lambda a, b: dls_joint_velocity(a @ b, xi, 0.1, q, (lo, hi)), args)


def test_one_bad_element_does_not_poison_the_gradient_of_a_shared_J():
    """J shared by the batch (rank-deficient), per-element λ and twists, one NaN twist: the values and the
    gradient of a loss over the finite elements equal the per-sample loop of the closed form."""
    g = _gen(6)
    J = _rank_deficient(7)
    xi = torch.randn(4, 6, dtype=D, generator=g)
    xi[2, 1] = math.nan
    lam = torch.tensor([0.1, 0.05, 0.1, 0.2], dtype=D)
    Jg = J.clone().requires_grad_(True)
    qd = dls_joint_velocity(Jg, xi, lam)
    assert torch.isnan(qd[2]).all() and torch.isfinite(qd[[0, 1, 3]]).all()
    good = torch.isfinite(qd).all(-1)
    (gJ,) = torch.autograd.grad(torch.where(good[:, None], qd, 0.0).pow(2).sum(), Jg)
    ref_g = torch.zeros_like(J)
    for i in (0, 1, 3):
        Ji = J.clone().requires_grad_(True)
        yi = _closed_form(Ji, xi[i], lam[i])
        torch.testing.assert_close(qd[i].detach(), yi.detach(), rtol=1e-9, atol=1e-9)
        ref_g += torch.autograd.grad(yi.pow(2).sum(), Ji)[0]
    torch.testing.assert_close(gJ, ref_g, rtol=1e-9, atol=1e-9)


def test_a_nan_jacobian_element_leaves_the_others_gradients_alone():
    g = _gen(8)
    J = torch.stack([_rank_deficient(9), torch.randn(6, 7, dtype=D, generator=g), _rank_deficient(10, r=5)])
    J[2, 4:] = 0.0  # two zero rows (a singular wrist)
    J[1, 0, 0] = math.inf
    xi = torch.randn(3, 6, dtype=D, generator=g)
    Jg = J.clone().requires_grad_(True)
    qd = dls_joint_velocity(Jg, xi, 0.1)
    (gJ,) = torch.autograd.grad(torch.nan_to_num(qd, nan=0.0).sum(), Jg)
    assert torch.isnan(qd[1]).all() and torch.equal(gJ[1], torch.zeros(6, 7, dtype=D))
    for i in (0, 2):
        Ji = J[i].clone().requires_grad_(True)
        (gi,) = torch.autograd.grad(_closed_form(Ji, xi[i], torch.tensor(0.1, dtype=D)).sum(), Ji)
        torch.testing.assert_close(gJ[i], gi, rtol=1e-9, atol=1e-9)
