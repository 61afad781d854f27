"""One element whose iLQR iterate overflows (absurd parameters) must not poison the implicit gradient of a
parameter shared with the others: its own controls are masked by the user, the others' gradient is the
one they have alone (found by the adversarial check of learning.imitation; 0·NaN reached the sum)."""

import math

import pytest
import torch

from controllers.costs import QuadraticCost
from controllers.ilqr import ILQRProblem, ilqr
from controllers.systems.pendulum import Pendulum

D64 = torch.float64


def _grad(scale: torch.Tensor, x0: torch.Tensor) -> tuple[torch.Tensor, list[str]]:
    """d/dg of the squared finite controls, gravity = g·scale per element (g shared, requires grad)."""
    g = torch.tensor(10.0, dtype=D64, requires_grad=True)
    cost = QuadraticCost(Q=torch.diag(torch.tensor([1.0, 0.1], dtype=D64)),
                         R=torch.tensor([[1e-3]], dtype=D64), x_ref=torch.tensor([math.pi, 0.0], dtype=D64))
    lim = torch.tensor([20.0], dtype=D64)
    p = Pendulum(gravity=g * scale, mass=1.0, length=scale.new_tensor(1.0), dt=0.05)
    sol = ilqr(ILQRProblem(p, cost, x0, 20, u_lower=-lim, u_upper=lim), grad="implicit")
    loss = torch.where(torch.isfinite(sol.u), sol.u, 0.0).square().sum()
    (dg,) = torch.autograd.grad(loss, g)
    return dg, sol.status.reason_names()


@pytest.mark.parametrize("absurd", [1e30, 1e200])
def test_overflowing_element_does_not_poison_shared_gradient(absurd):
    x0 = torch.tensor([[3.0, 0.1], [3.1, 0.0]], dtype=D64)
    both, reasons = _grad(torch.tensor([1.0, absurd], dtype=D64), x0)
    alone, reasons1 = _grad(torch.tensor([1.0], dtype=D64), x0[:1])
    assert reasons[0] == reasons1[0] == "CONVERGED" and reasons[1] != "CONVERGED"
    assert torch.isfinite(both)
    assert torch.allclose(both, alone, rtol=1e-9, atol=0), (both, alone)
