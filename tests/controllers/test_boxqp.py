"""Box-QP: against exhaustive active-set enumeration and scipy's L-BFGS-B, batching, bad elements."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from controllers.boxqp import BoxQPStatus, box_qp, masked_hessian


def _random_qp(gen, nb, m, dtype=torch.float64, scale=3.0):
    A = torch.randn(nb, m, m, generator=gen, dtype=dtype)
    H = A @ A.mT + 0.3 * torch.eye(m, dtype=dtype)
    # per-element scale of g: small ones leave every bound inactive, large ones activate some
    s = scale * torch.rand(nb, 1, generator=gen, dtype=dtype) ** 2
    g = s * torch.randn(nb, m, generator=gen, dtype=dtype)
    lo = -torch.rand(nb, m, generator=gen, dtype=dtype) - 0.1
    hi = torch.rand(nb, m, generator=gen, dtype=dtype) + 0.1
    return H, g, lo, hi


def _enumerate(H, g, lo, hi):
    """Exact solution of one small box QP: try every (free, lower, upper) assignment, keep the best."""
    m = len(g)
    best, bestf = None, np.inf
    for assign in itertools.product((0, 1, 2), repeat=m):
        x = np.zeros(m)
        fixed = np.array([a != 0 for a in assign])
        for i, a in enumerate(assign):
            if a == 1:
                x[i] = lo[i]
            elif a == 2:
                x[i] = hi[i]
        fr = ~fixed
        if fr.any():
            rhs = -(g[fr] + H[np.ix_(fr, fixed)] @ x[fixed])
            x[fr] = np.linalg.solve(H[np.ix_(fr, fr)], rhs)
        if np.all(x >= lo - 1e-12) and np.all(x <= hi + 1e-12):
            f = 0.5 * x @ H @ x + g @ x
            if f < bestf - 1e-14:
                best, bestf = x, f
    return best


def test_against_enumeration_and_regime():
    gen = torch.Generator().manual_seed(0)
    H, g, lo, hi = _random_qp(gen, 40, 4)
    res = box_qp(H, g, lo, hi)
    assert bool(res.converged.all()), res.status
    n_clamped = res.clamped.sum(-1)
    # the regime: elements with some (not all) bounds active, and elements with none active
    assert bool(((n_clamped > 0) & (n_clamped < 4)).any())
    assert bool((n_clamped == 0).any())
    for b in range(40):
        ref = _enumerate(H[b].numpy(), g[b].numpy(), lo[b].numpy(), hi[b].numpy())
        np.testing.assert_allclose(res.x[b].numpy(), ref, atol=1e-9)
    # clamped variables sit on a bound; free ones have zero gradient
    grad = g + (H @ res.x.unsqueeze(-1)).squeeze(-1)
    on_bound = (res.x == lo) | (res.x == hi)
    assert bool(on_bound[res.clamped].all())
    assert float(grad[res.free].abs().max()) < 1e-9


def test_against_scipy_lbfgsb():
    scipy_opt = pytest.importorskip("scipy.optimize")
    gen = torch.Generator().manual_seed(1)
    H, g, lo, hi = _random_qp(gen, 10, 6)
    res = box_qp(H, g, lo, hi)
    assert bool(res.converged.all())
    assert int(res.clamped.sum()) > 0 and int(res.free.sum()) > 0
    for b in range(10):
        Hb, gb = H[b].numpy(), g[b].numpy()
        r = scipy_opt.minimize(lambda x, Hb=Hb, gb=gb: 0.5 * x @ Hb @ x + gb @ x, np.zeros(6),
                               jac=lambda x, Hb=Hb, gb=gb: Hb @ x + gb,
                               bounds=list(zip(lo[b].numpy(), hi[b].numpy())), method="L-BFGS-B",
                               options={"ftol": 1e-15, "gtol": 1e-12, "maxiter": 1000})
        np.testing.assert_allclose(res.x[b].numpy(), r.x, atol=1e-6)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), m=st.integers(1, 4))
def test_batched_equals_loop_and_warm_start(seed, m):
    gen = torch.Generator().manual_seed(seed)
    H, g, lo, hi = _random_qp(gen, 5, m)
    res = box_qp(H, g, lo, hi)
    for b in range(5):
        one = box_qp(H[b], g[b], lo[b], hi[b])
        torch.testing.assert_close(one.x, res.x[b], atol=1e-10, rtol=0)
        assert int(one.status) in (0, 1, 2)
        ref = _enumerate(H[b].numpy(), g[b].numpy(), lo[b].numpy(), hi[b].numpy())
        np.testing.assert_allclose(one.x.numpy(), ref, atol=1e-8)
    # a warm start at the solution converges in at most one iteration to the same point
    warm = box_qp(H, g, lo, hi, x0=res.x)
    torch.testing.assert_close(warm.x, res.x, atol=1e-10, rtol=0)
    assert int(warm.iterations.max()) <= 1


def test_unbounded_equals_newton_and_all_clamped():
    gen = torch.Generator().manual_seed(2)
    H, g, _, _ = _random_qp(gen, 3, 3)
    res = box_qp(H, g, -torch.inf, torch.inf)
    torch.testing.assert_close(res.x, torch.linalg.solve(H, -g), atol=1e-10, rtol=0)
    assert bool(res.free.all())
    # a huge gradient pushes everything to the bounds
    res = box_qp(H, 1e4 * torch.ones(3, 3, dtype=torch.float64), -1.0, 1.0)
    assert bool((res.x == -1).all())
    assert bool((res.status == BoxQPStatus.ALL_CLAMPED).all())


def test_bad_elements_do_not_poison_batch():
    gen = torch.Generator().manual_seed(3)
    H, g, lo, hi = _random_qp(gen, 4, 3)
    ref = box_qp(H, g, lo, hi)
    H2, g2 = H.clone(), g.clone()
    g2[1, 0] = torch.nan
    H2[2] = -torch.eye(3, dtype=torch.float64)  # negative definite, unbounded box -> not PD
    lo2, hi2 = lo.clone(), hi.clone()
    lo2[2], hi2[2] = -torch.inf, torch.inf
    res = box_qp(H2, g2, lo2, hi2)
    assert int(res.status[1]) == BoxQPStatus.NON_FINITE
    assert bool(torch.isnan(res.x[1]).all())
    assert int(res.status[2]) == BoxQPStatus.NOT_POSITIVE_DEFINITE
    for b in (0, 3):
        torch.testing.assert_close(res.x[b], ref.x[b])
        assert bool(res.converged[b])


def test_float32_and_broadcast_bounds():
    gen = torch.Generator().manual_seed(4)
    H, g, _, _ = _random_qp(gen, 6, 2)
    res32 = box_qp(H.float(), g.float(), -0.5, 0.5)
    res64 = box_qp(H, g, torch.tensor([-0.5, -0.5], dtype=torch.float64), 0.5)
    assert res32.x.dtype == torch.float32
    torch.testing.assert_close(res32.x.double(), res64.x, atol=1e-5, rtol=0)


def test_masked_hessian_zeroes_clamped_rows():
    H = torch.tensor([[2.0, 0.5], [0.5, 3.0]], dtype=torch.float64)
    free = torch.tensor([True, False])
    Hm = masked_hessian(H, free)
    torch.testing.assert_close(Hm, torch.tensor([[2.0, 0.0], [0.0, 1.0]], dtype=torch.float64))


def test_bad_input_errors():
    H = torch.eye(2)
    with pytest.raises(ValueError, match="H must have shape"):
        box_qp(torch.ones(2, 3), torch.ones(2), -1.0, 1.0)
    with pytest.raises(ValueError, match="g must have shape"):
        box_qp(H, torch.ones(3), -1.0, 1.0)
    with pytest.raises(ValueError, match="lower must be <= upper"):
        box_qp(H, torch.ones(2), 1.0, -1.0)
    with pytest.raises(TypeError):
        box_qp(H, torch.ones(2, dtype=torch.float64), -1.0, 1.0)
