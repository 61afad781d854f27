"""Contracts at the controllers' entry points: inference mode works, nothing is cast silently, and a
bad mode string names its argument."""

import pytest
import torch

from controllers import lifted, riccati
from controllers.boxqp import box_qp
from controllers.costs import DiagonalQuadraticCost, QuadraticCost
from controllers.dynamics import jacobians
from controllers.ilqr import ILQRProblem, ilqr
from controllers.mpc import MPCPolicy
from controllers.systems import Pendulum
from tests.controllers.lq_oracle import random_problem

D64 = torch.float64


def test_lq_solvers_run_under_inference_mode():
    """Deployment runs controllers under torch.inference_mode(): solving, checking and preparing a cost
    work on inference tensors."""
    g = torch.Generator().manual_seed(0)
    p = random_problem(g)
    ref = riccati.solve(p, grad="none")
    with torch.inference_mode():
        pi = random_problem(torch.Generator().manual_seed(0))
        a = riccati.solve(pi, grad="none")
        b = lifted.solve_lifted(pi)
        again = riccati.solve(pi, grad="none", prepared=riccati.prepare(pi.cost, pi.T, pi.batch_shape))
    assert (a.u - ref.u).abs().max() < 1e-12
    assert (b.u - ref.u).abs().max() < 1e-9
    assert torch.equal(again.u, a.u)


def test_box_qp_refuses_to_cast_bounds_or_warm_start():
    H = torch.eye(2).expand(3, 2, 2)
    g = torch.ones(3, 2)
    with pytest.raises(TypeError, match="'lower'"):
        box_qp(H, g, torch.full((2,), -1.0, dtype=D64), 1.0)
    with pytest.raises(TypeError, match="'x0'"):
        box_qp(H, g, -1.0, 1.0, x0=torch.zeros(3, 2, dtype=D64))
    x = box_qp(H, g, -0.5, 0.5).x  # Python floats are converted, not refused
    assert x.dtype == torch.float32 and torch.allclose(x, torch.full((3, 2), -0.5))


def test_mpc_policy_refuses_mixed_dtypes():
    q, r, target = torch.tensor([1.0, 0.1], dtype=D64), torch.tensor([0.01]), torch.zeros(2, dtype=D64)
    with pytest.raises(TypeError, match="'r'"):
        DiagonalQuadraticCost(q, r, target, 5)
    pol = MPCPolicy(Pendulum(), 5, DiagonalQuadraticCost(q, r.double(), target, 5),
                    u_lower=torch.tensor([-1.0]), u_upper=1.0)
    with pytest.raises(TypeError, match="'u_lower'"):
        pol(torch.zeros(1, 2, dtype=D64))


def test_bad_mode_strings_name_the_argument():
    p = random_problem(torch.Generator().manual_seed(1))
    with pytest.raises(ValueError, match="argument 'grad' must be one of .*'implicit'"):
        riccati.solve(p, grad="bogus")
    sys = Pendulum()
    x0 = torch.zeros(2, 2, dtype=D64)
    cost = QuadraticCost(torch.eye(2, dtype=D64), 0.1 * torch.eye(1, dtype=D64))
    prob = ILQRProblem(sys, cost, x0, horizon=4)
    with pytest.raises(ValueError, match="argument 'method'"):
        ilqr(prob, method="newton")
    with pytest.raises(ValueError, match="argument 'grad'"):
        MPCPolicy(sys, 5, DiagonalQuadraticCost(torch.ones(2), torch.ones(1), torch.zeros(2), 5),
                  grad="magic")
    with pytest.raises(ValueError, match="argument 'method'"):
        jacobians(lambda x, u, t: x + u, torch.zeros(2), torch.zeros(2), method="guess")
