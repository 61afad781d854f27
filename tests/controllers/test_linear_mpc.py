"""controllers.linear_mpc: the first control of the affine LQ problem against the Riccati solver (an
independent implementation), time-varying weights, clipping, dtypes and bad input."""

import math

import pytest
import torch

from controllers.linear_mpc import linear_mpc_action, lq_first_action
from controllers.riccati import lqr
from controllers.systems import Pendulum


def _problem(dtype=torch.float64, n=4, m=2, T=12, N=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    A = torch.randn(N, n, n, generator=g, dtype=torch.float64) * 0.25 + torch.eye(n, dtype=torch.float64)
    B = torch.randn(N, n, m, generator=g, dtype=torch.float64)
    c = torch.randn(N, n, generator=g, dtype=torch.float64)
    Q = torch.diag(torch.rand(n, generator=g, dtype=torch.float64) + 0.1).expand(T + 1, n, n).clone()
    Q[-1] *= 5
    R = torch.stack([torch.diag(torch.rand(m, generator=g, dtype=torch.float64) + 0.1) for _ in range(T)])
    xr = torch.randn(n, generator=g, dtype=torch.float64)
    ur = torch.randn(m, generator=g, dtype=torch.float64)
    x0 = torch.randn(N, n, generator=g, dtype=torch.float64)
    return [v.to(dtype) for v in (A, B, c, Q, R, xr, ur, x0)], T


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_first_control_and_gain_equal_the_riccati_solution(dtype):
    (A, B, c, Q, R, xr, ur, x0), T = _problem(dtype)
    u0, K0 = lq_first_action(A, B, c, Q, R, xr, ur, x0, T)
    q, r = -(Q @ xr), -(R @ ur)  # the canonical linear terms of (x - xr)'Q(x - xr) + (u - ur)'R(u - ur)
    _, u, K, _, _, ok = lqr(A[:, None], B[:, None], c[:, None], Q, R, None, q, r, x0, T, grad="none")
    tol = 1e-10 if dtype == torch.float64 else 2e-3
    assert bool(ok.all())
    torch.testing.assert_close(u0, u[:, 0], rtol=tol, atol=tol)
    torch.testing.assert_close(K0, -K[:, 0], rtol=tol, atol=tol)  # u = k - K0 x here, u = K x + k there
    # batched == one element at a time
    for b in range(3):
        ub, _ = lq_first_action(A[b], B[b], c[b], Q, R, xr, ur, x0[b], T)
        torch.testing.assert_close(ub, u0[b], rtol=tol, atol=tol)


def test_constant_weights_given_once_and_horizon_one():
    (A, B, c, Q, R, xr, ur, x0), T = _problem()
    full, _ = lq_first_action(A, B, c, Q[:1].expand(T + 1, -1, -1), R[:1].expand(T, -1, -1), xr, ur, x0, T)
    once, _ = lq_first_action(A, B, c, Q[:1], R[:1], xr, ur, x0, T)
    torch.testing.assert_close(once, full)
    # T = 1: minimize (u - ur)'R(u - ur) + (Ax + Bu + c - xr)'Q_T(...) in closed form
    u1, _ = lq_first_action(A, B, c, Q[-1:], R[:1], xr, ur, x0, 1)
    Bt = B.transpose(-1, -2)
    H = R[0] + Bt @ Q[-1] @ B
    rhs = (R[0] @ ur) - (Bt @ Q[-1] @ ((A @ x0.unsqueeze(-1)).squeeze(-1) + c - xr).unsqueeze(-1)).squeeze(-1)
    torch.testing.assert_close(u1, torch.linalg.solve(H, rhs))


def test_action_on_a_model_is_clipped_and_brakes_a_pendulum():
    pend = Pendulum(dt=0.05)
    D = torch.float64
    x = torch.tensor([[math.pi - 0.2, 0.0], [math.pi + 0.2, 0.0], [math.pi - 1.5, 0.0]], dtype=D)
    Q = torch.diag(torch.tensor([1.0, 0.1], dtype=D))[None]
    R = torch.tensor([[[0.01]]], dtype=D)
    xr, ur = torch.tensor([math.pi, 0.0], dtype=D), torch.zeros(1, dtype=D)
    u = linear_mpc_action(pend, x, torch.zeros(3, 1, dtype=D), Q, R, xr, ur, 30,
                          torch.tensor([-2.0], dtype=D), torch.tensor([2.0], dtype=D))
    assert u[0, 0] > 0 > u[1, 0]  # pushes back towards upright from either side
    assert u[2, 0] == 2.0  # far off: saturated at the limit


def test_bad_horizon():
    (A, B, c, Q, R, xr, ur, x0), _ = _problem()
    with pytest.raises(ValueError, match="horizon"):
        lq_first_action(A, B, c, Q, R, xr, ur, x0, 0)
