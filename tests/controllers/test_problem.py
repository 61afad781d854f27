"""controllers.problem: LQProblem horizon and batch validation, per-element input status."""

import pytest
import torch

from controllers.costs import QuadraticCost
from controllers.dynamics import LinearDynamics
from controllers.problem import LQProblem, Reason, SolverStatus
from tests.controllers.lq_oracle import spd

D = torch.float64


def test_problem_horizon_and_errors():
    A, B = torch.eye(3, dtype=D), torch.ones(3, 1, dtype=D)
    cost = QuadraticCost(torch.eye(3, dtype=D), torch.eye(1, dtype=D))
    with pytest.raises(ValueError, match="cannot infer the horizon"):
        LQProblem(LinearDynamics(A, B), cost, torch.zeros(3, dtype=D))
    p = LQProblem(LinearDynamics(A, B), cost, torch.zeros(3, dtype=D), horizon=7)
    assert p.T == 7 and p.batch_shape == ()
    with pytest.raises(ValueError, match="'x0' must have shape \\(\\*B, 3\\)"):
        LQProblem(LinearDynamics(A, B), cost, torch.zeros(2, dtype=D), horizon=7)
    with pytest.raises(ValueError, match="horizon 4 but the problem horizon is 7"):
        LQProblem(LinearDynamics(A.expand(4, 3, 3), B), cost, torch.zeros(3, dtype=D), horizon=7)
    cost2 = QuadraticCost(torch.eye(2, dtype=D), torch.eye(1, dtype=D))
    with pytest.raises(ValueError, match="n=2"):
        LQProblem(LinearDynamics(A, B), cost2, torch.zeros(3, dtype=D), horizon=3)


def test_input_status_per_element():
    g = torch.Generator().manual_seed(4)
    b, n, m, T = 4, 3, 2, 5
    Q = spd(b, 1, k=n, g=g)
    Q[2, 0] = -Q[2, 0]  # element 2: Q negative definite
    x0 = torch.randn(b, n, dtype=D, generator=g)
    x0[1, 0] = float("nan")  # element 1: NaN initial state
    p = LQProblem(LinearDynamics(torch.eye(n, dtype=D), torch.ones(n, m, dtype=D)),
                  QuadraticCost(Q, torch.eye(m, dtype=D)), x0, horizon=T)
    st = SolverStatus.from_reason(p.input_status())
    assert st.reason_names() == ["CONVERGED", "NONFINITE_INPUT", "NOT_POSITIVE_DEFINITE", "CONVERGED"]
    assert st.converged.tolist() == [True, False, False, True]
    assert st.reason[1] == Reason.NONFINITE_INPUT


