"""One rule for cost weights in every solver (issue 22 items 3 and 13, the QuadraticCost / iLQR / Riccati
part; controllers._validate.check_weight): a weight shared by the batch that has NaN, is not symmetric, or
is not PSD (Q) / PD (R) is a ValueError naming the field; a batched weight's defect is that element's status
(NONFINITE_INPUT, else NOT_POSITIVE_DEFINITE), reported before anything the solver finds, and the other
elements — values and the gradients of shared inputs — are what they are alone (per-sample reference)."""

from __future__ import annotations

import math

import pytest
import torch

from controllers import riccati
from controllers.costs import QuadraticCost
from controllers.dynamics import LinearDynamics
from controllers.ilqr import ILQROptions, ILQRProblem, ilqr
from controllers.problem import LQProblem
from controllers.systems import Pendulum

D = torch.float64
T = 8
R1 = torch.tensor([[0.05]], dtype=D)


def test_shared_weight_defects_are_value_errors():
    with pytest.raises(ValueError, match="'Q' has NaN"):  # was accepted: SINGULAR_QUU per element
        QuadraticCost(torch.tensor([[1.0, 0.0], [0.0, math.nan]], dtype=D), R1)
    with pytest.raises(ValueError, match="'R' has NaN"):
        QuadraticCost(torch.eye(2, dtype=D), torch.full((T, 1, 1), math.nan, dtype=D))
    with pytest.raises(ValueError, match="'Q' must be symmetric"):
        QuadraticCost(torch.tensor([[1.0, 0.5], [0.0, 1.0]], dtype=D), R1)
    with pytest.raises(ValueError, match="'Q' must be positive semi-definite"):
        QuadraticCost(torch.diag(torch.tensor([1.0, -0.1], dtype=D)), R1)
    with pytest.raises(ValueError, match="'R' must be positive definite"):
        QuadraticCost(torch.eye(2, dtype=D), -R1)


def _batched_weights():
    Q = torch.diag(torch.tensor([1.0, 0.1], dtype=D)).expand(4, T + 1, 2, 2).clone()
    Q[1, 3, 0, 0] = math.nan  # NONFINITE_INPUT
    Q[2, 2, 1, 1] = -1.0  # indefinite: NOT_POSITIVE_DEFINITE
    Q[3, :, 0, 1] = 0.3  # not symmetric (its symmetric part is PD): NOT_POSITIVE_DEFINITE (was a ValueError)
    return Q


EXPECTED = ["CONVERGED", "NONFINITE_INPUT", "NOT_POSITIVE_DEFINITE", "NOT_POSITIVE_DEFINITE"]


@pytest.mark.parametrize("method", ["recursive", "batch"])
@pytest.mark.parametrize("grad", ["implicit", "unrolled"])
def test_ilqr_batched_weight_defects_are_per_element(method, grad):
    x0 = torch.tensor([[0.3, 0.0], [-0.2, 0.5], [0.1, 0.1], [0.0, 0.2]], dtype=D)
    x_ref = torch.tensor([1.0, 0.0], dtype=D, requires_grad=True)
    opts = ILQROptions(tol=1e-13, tol_cost=0.0)

    def solve(Q, x0):
        cost = QuadraticCost(Q, R1, x_ref=x_ref)
        prob = ILQRProblem(Pendulum(dt=0.1), cost, x0, T, u_lower=-1.0, u_upper=1.0)
        return ilqr(prob, method=method, grad=grad, options=opts)

    sol = solve(_batched_weights(), x0)
    assert sol.status.reason_names() == EXPECTED  # main: NaN element DIVERGED, the others CONVERGED
    assert bool(torch.isnan(sol.u[1:]).all()) and bool(torch.isnan(sol.cost[1:]).all())
    alone = solve(_batched_weights()[0], x0[0])
    torch.testing.assert_close(sol.u[0], alone.u, atol=1e-12, rtol=0)
    # the shared reference's gradient is element 0's alone (the NaN element poisoned it on main)
    (g,) = torch.autograd.grad(sol.u[0].sum() + sol.cost[0], x_ref)
    (g0,) = torch.autograd.grad(alone.u.sum() + alone.cost, x_ref)
    torch.testing.assert_close(g, g0, atol=1e-10, rtol=1e-10)


def test_riccati_batched_weight_defects_are_per_element():
    A = torch.tensor([[1.0, 0.1], [0.0, 1.0]], dtype=D)
    B = torch.tensor([[0.0], [0.1]], dtype=D)
    x0 = torch.tensor([[1.0, 0.0], [0.5, 0.5], [-1.0, 0.2], [0.3, -0.3]], dtype=D)
    Q = _batched_weights()
    sol = riccati.solve(LQProblem(LinearDynamics(A, B), QuadraticCost(Q, R1), x0, T))
    assert sol.status.reason_names() == EXPECTED
    alone = riccati.solve(LQProblem(LinearDynamics(A, B), QuadraticCost(Q[0], R1), x0[0], T))
    torch.testing.assert_close(sol.u[0], alone.u, atol=1e-12, rtol=0)
