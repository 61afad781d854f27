"""Recursive Riccati LQR/LQT against the lifted least-squares oracle, a dense KKT solve and the seed's
augmented-state and least-squares-recursive formulations."""

import dataclasses

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from lq_oracle import D, dense_kkt, random_problem, spd

from controllers import lifted, riccati
from controllers.costs import QuadraticCost
from controllers.dynamics import LinearDynamics, rollout
from controllers.problem import LQProblem, Reason

FIELDS = ("Q", "R", "x_ref", "u_ref", "N", "q", "r")


@pytest.mark.parametrize("features", [dict(), dict(drift=False, cross=False, refs=False, linear=False),
                                      dict(tv=False), dict(b=(2, 3), T=3)])
@pytest.mark.parametrize("grad", ["implicit", "unrolled", "none"])
def test_riccati_matches_lifted_and_kkt(features, grad):
    g = torch.Generator().manual_seed(0)
    p = random_problem(g, **features)
    sol = riccati.solve(p, grad=grad)
    ref = lifted.solve_lifted(p)
    torch.testing.assert_close(sol.u, ref.u, atol=1e-9, rtol=0)
    torch.testing.assert_close(sol.x, ref.x, atol=1e-9, rtol=0)
    torch.testing.assert_close(sol.cost, ref.cost, atol=1e-9, rtol=1e-12)
    x, u = dense_kkt(p)
    torch.testing.assert_close(sol.u, u, atol=1e-9, rtol=0)
    assert sol.status.all_converged
    # the policy reproduces the trajectory: u_t = K_t x_t + k_t and x = rollout(u)
    torch.testing.assert_close((sol.K @ sol.x[..., :-1, :, None]).squeeze(-1) + sol.k, sol.u)
    torch.testing.assert_close(rollout(p.dynamics, p.x0, sol.u), sol.x)


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 10_000), T=st.integers(1, 7), n=st.integers(1, 4), m=st.integers(1, 3))
def test_riccati_lifted_agree_random_sizes(seed, T, n, m):
    g = torch.Generator().manual_seed(seed)
    p = random_problem(g, b=(2,), T=T, n=n, m=m)
    torch.testing.assert_close(riccati.solve(p).u, lifted.solve_lifted(p).u, atol=1e-9, rtol=0)


def test_feedback_gains_are_optimal_from_any_state():
    """The gains are the closed-loop optimum: re-solving from a perturbed x_t gives u_t = K_t x_t + k_t."""
    g = torch.Generator().manual_seed(1)
    p = random_problem(g, b=(2,), T=6)
    sol = riccati.solve(p)
    t = 3
    xt = sol.x[:, t] + torch.randn(2, p.n, dtype=D, generator=g)
    cut = lambda v, k, lo: None if v is None else v[(Ellipsis, slice(lo, None)) + (slice(None),) * k]
    d = p.dynamics
    c = p.cost
    sub = LQProblem(LinearDynamics(cut(d.A, 2, t), cut(d.B, 2, t), cut(d.c, 1, t)),
                    QuadraticCost(cut(c.Q, 2, t), cut(c.R, 2, t), x_ref=cut(c.x_ref, 1, t),
                                  u_ref=cut(c.u_ref, 1, t), N=cut(c.N, 2, t), q=cut(c.q, 1, t),
                                  r=cut(c.r, 1, t)), xt)
    ref = lifted.solve_lifted(sub)
    torch.testing.assert_close((sol.K[:, t] @ xt.unsqueeze(-1)).squeeze(-1) + sol.k[:, t], ref.u[:, 0],
                               atol=1e-9, rtol=0)


def _stage_min_eig(cost, T):
    """Smallest eigenvalue of the stage matrices of [x̃; u] (and of the terminal Q̃) over batch and time."""
    Q, R = cost.Q, cost.R.expand(*cost.Q.shape[:-3], T, *cost.R.shape[-2:])
    N = cost.N if cost.N is not None else torch.zeros(*Q.shape[:-3], T, Q.shape[-1], R.shape[-1], dtype=D)
    W = torch.cat([torch.cat([Q[..., :T, :, :], N], -1), torch.cat([N.mT, R], -1)], -2)
    return min(torch.linalg.eigvalsh(W).amin().item(), torch.linalg.eigvalsh(Q[..., T, :, :]).amin().item())


@pytest.mark.parametrize("features", ["tracking", "tracking+cross", "all"])
def test_augmented_state_lqt_eq76_78(features):
    g = torch.Generator().manual_seed(2)
    kw = {"tracking": dict(linear=False, cross=False), "tracking+cross": dict(linear=False),
          "all": {}}[features]
    p = random_problem(g, b=(3,), T=5, **kw)
    dyn, cost, x0t, offset = riccati.augmented_lqt(p)
    assert dyn.A.shape[-1] == p.n + 1 and cost.x_ref is None
    # the augmented problem is PSD (seed Eq. 77): every stage matrix of [x̃; u], not just Q̃
    assert _stage_min_eig(cost, p.T) > -1e-12
    if features != "all":  # pure tracking: the same constants, nothing moved to the offset
        torch.testing.assert_close(offset, torch.zeros(3, dtype=D), atol=1e-12, rtol=0)
    else:  # linear terms make a stage negative somewhere: its minimum went to the offset
        assert bool((offset < -1e-3).all())
    aug = lifted.solve_lifted(LQProblem(dyn, cost, x0t))  # solved as plain regulation, by the oracle
    sol = riccati.solve(p)
    torch.testing.assert_close(aug.u, sol.u, atol=1e-9, rtol=0)
    torch.testing.assert_close(aug.x[..., :-1], sol.x, atol=1e-9, rtol=0)
    torch.testing.assert_close(aug.cost + offset, sol.cost, atol=1e-9, rtol=1e-12)
    # K̃ = [K, k] (Eq. 78) from the Riccati pass on the augmented problem, which certifies it
    saug = riccati.solve(LQProblem(dyn, cost, x0t))
    assert saug.status.reason_names() == ["CONVERGED"] * 3
    torch.testing.assert_close(saug.K[..., :-1], sol.K, atol=1e-9, rtol=0)
    torch.testing.assert_close(saug.K[..., -1], sol.k, atol=1e-9, rtol=0)
    # the seed's feedforward form: u = K (x - μ) + u_ff with u_ff = k + K μ  (Eq. 78, signs of this package)
    mu = p.cost.x_ref[:, :-1]
    uff = sol.k + (sol.K @ mu.unsqueeze(-1)).squeeze(-1)
    torch.testing.assert_close((sol.K @ (sol.x[:, :-1] - mu).unsqueeze(-1)).squeeze(-1) + uff, sol.u)


def _lifted_mats(p):
    T = p.T
    Sx, Su, _ = lifted.transfer_matrices(p.dynamics.A, p.dynamics.B, None, T)
    cc = p.cost.canonical(T)
    return Sx, Su, lifted.block_diag_time(cc.Q, T + 1), lifted.block_diag_time(cc.R, T)


def test_ls_recursive_gains_equal_riccati_eq79_81():
    g = torch.Generator().manual_seed(3)
    # LQR, and LQT through the augmented state (no u_ref / cross terms: Eq. 80 has none)
    for kw in (dict(drift=False, cross=False, refs=False, linear=False), dict(cross=False, linear=False)):
        p = random_problem(g, b=(2,), T=5, **kw)
        if p.cost.u_ref is not None:
            p = dataclasses.replace(p, cost=dataclasses.replace(p.cost, u_ref=None))
        dyn, cost, x0t, _ = riccati.augmented_lqt(p)
        pa = LQProblem(dyn.expand_time(5), cost, x0t)
        Sx, Su, Qb, Rb = _lifted_mats(pa)
        K, Fm, _ = riccati.ls_recursive_gains(Sx, Su, Qb, Rb, pa.dynamics.A, pa.dynamics.B)
        sol = riccati.solve(p)
        torch.testing.assert_close(K[..., :-1], sol.K, atol=1e-8, rtol=0)
        torch.testing.assert_close(K[..., -1], sol.k, atol=1e-8, rtol=0)
        torch.testing.assert_close(-(Fm @ x0t.unsqueeze(-1)).squeeze(-1).reshape(2, 5, p.m), sol.u)


def test_ls_recursive_full_precision_and_primitives_reproduce_open_loop():
    """With a full precision (cross-time) or control primitives, the Eq. 81 gains reproduce the lifted
    open-loop optimum in closed loop (what the seed's multi-agent and DMP examples rely on)."""
    g = torch.Generator().manual_seed(4)
    T, n, m = 8, 2, 2
    A = torch.eye(n, dtype=D) + 0.1 * torch.randn(n, n, dtype=D, generator=g)
    B = 0.5 * torch.eye(n, dtype=D)
    Q = spd(T + 1, k=n, g=g)
    p = LQProblem(LinearDynamics(A, B), QuadraticCost(Q, 0.1 * torch.eye(m, dtype=D),
                                                      x_ref=torch.randn(T + 1, n, dtype=D, generator=g)),
                  torch.randn(n, dtype=D, generator=g))
    dyn, cost, x0t, _ = riccati.augmented_lqt(p)
    pa = LQProblem(dyn.expand_time(T), cost, x0t)
    Sx, Su, Qb, Rb = _lifted_mats(pa)
    # couple x_2 and x_6 in the (augmented) precision
    Jm = torch.zeros(n, (T + 1) * (n + 1), dtype=D)
    Jm[:, 2 * (n + 1):2 * (n + 1) + n] = torch.eye(n, dtype=D)
    Jm[:, 6 * (n + 1):6 * (n + 1) + n] = -torch.eye(n, dtype=D)
    Qfull = Qb + 5.0 * Jm.T @ Jm
    from controllers import basis

    for Qm, Psi in ((Qfull, None), (Qb, lifted.control_primitives(basis.rbf(T, 3, dtype=D), m))):
        K, Fm, _ = riccati.ls_recursive_gains(Sx, Su, Qm, Rb, pa.dynamics.A, pa.dynamics.B, Psi=Psi)
        u_open = -(Fm @ x0t).reshape(T, m)
        x = x0t
        for t in range(T):
            u = K[t] @ x
            torch.testing.assert_close(u, u_open[t], atol=1e-9, rtol=0)
            x = pa.dynamics.step(x, u, t)
        # and u_open is the lifted optimum for that precision / subspace
        if Psi is None:
            ref = lifted.solve_lifted(pa, Qbig=Qm)
            torch.testing.assert_close(ref.u, u_open, atol=1e-9, rtol=0)


def test_batched_equals_loop_and_broadcasting():
    g = torch.Generator().manual_seed(5)
    p = random_problem(g, b=(3,), T=4)
    sol = riccati.solve(p)
    for i in range(3):
        d, c = p.dynamics, p.cost
        pi = LQProblem(LinearDynamics(d.A[i], d.B[i], d.c[i]),
                       QuadraticCost(*(getattr(c, k)[i] for k in FIELDS)),
                       p.x0[i])
        si = riccati.solve(pi)
        torch.testing.assert_close(si.u, sol.u[i])
        torch.testing.assert_close(si.K, sol.K[i])
    # shared (un-batched) dynamics and cost == manually expanded
    A, B = p.dynamics.A[0, :1], p.dynamics.B[0, :1]
    Q, R = p.cost.Q[0, :1], p.cost.R[0, :1]
    x0 = torch.randn(5, p.n, dtype=D, generator=g)
    shared = riccati.solve(LQProblem(LinearDynamics(A[0], B[0]), QuadraticCost(Q[0], R[0]), x0, horizon=4))
    expanded = riccati.solve(LQProblem(LinearDynamics(A.expand(5, 4, -1, -1), B.expand(5, 4, -1, -1)),
                                       QuadraticCost(Q.expand(5, 5, -1, -1), R.expand(5, 4, -1, -1)), x0))
    torch.testing.assert_close(shared.u, expanded.u)
    torch.testing.assert_close(shared.K, expanded.K)


def test_float32_close_to_float64():
    g = torch.Generator().manual_seed(6)
    p64 = random_problem(g, b=(16,), T=50, n=8, m=4, tv=False)
    sol64 = riccati.solve(p64)
    cast = lambda v: None if v is None else v.float()
    d, c = p64.dynamics, p64.cost
    p32 = LQProblem(LinearDynamics(cast(d.A), cast(d.B), cast(d.c)),
                    QuadraticCost(*(cast(getattr(c, k)) for k in FIELDS)),
                    p64.x0.float())
    sol32 = riccati.solve(p32)
    assert sol32.u.dtype == torch.float32
    err = (sol32.u.double() - sol64.u).abs().max() / sol64.u.abs().max()
    assert err < 1e-3


def test_per_element_failures_do_not_poison_the_batch():
    g = torch.Generator().manual_seed(7)
    p = random_problem(g, b=(4,), T=5, cross=False)
    x0 = p.x0.clone()
    x0[1, 0] = float("nan")
    R = p.cost.R.clone()
    R[2] = -R[2]  # element 2: R negative definite -> H_uu not PD
    bad = LQProblem(p.dynamics, dataclasses.replace(p.cost, R=R), x0)
    sol = riccati.solve(bad)
    good = riccati.solve(p)
    assert sol.status.reason_names() == ["CONVERGED", "NONFINITE_INPUT", "NOT_POSITIVE_DEFINITE", "CONVERGED"]
    for i in (0, 3):
        torch.testing.assert_close(sol.u[i], good.u[i])
    assert torch.isnan(sol.x[1]).any()
    # without the input check the solver itself detects the indefinite H_uu
    sol2 = riccati.solve(bad, check=False)
    assert int(sol2.status.reason[2]) == Reason.SINGULAR_QUU
    assert sol2.status.converged[[0, 3]].all()


def test_solve_rejects_non_problem():
    with pytest.raises(TypeError, match="LQProblem"):
        riccati.solve("not a problem")


def test_fused_kernel_matches_eager():
    """fused=True (torch.compile'd pivot updates) gives the eager solution and gradients."""
    g = torch.Generator().manual_seed(8)
    p = random_problem(g, b=(3,), T=4, n=3, m=2)
    eager = riccati.solve(p)
    fused = riccati.solve(p, fused=True)
    torch.testing.assert_close(fused.u, eager.u)
    torch.testing.assert_close(fused.K, eager.K)
    assert fused.status.all_converged
    x0 = p.x0.clone().requires_grad_()
    g1 = torch.autograd.grad(riccati.solve(dataclasses.replace(p, x0=x0)).cost.sum(), x0)[0]
    g2 = torch.autograd.grad(riccati.solve(dataclasses.replace(p, x0=x0), fused=True).cost.sum(), x0)[0]
    torch.testing.assert_close(g1, g2)
    with pytest.raises(ValueError, match="fused"):
        riccati.solve(p, grad="unrolled", fused=True)


def test_prepared_cost_is_reused_across_x0_and_dynamics():
    """A prepared cost (MPC: one cost, new x0 or dynamics every step) gives the same answer as a fresh
    solve and as the lifted oracle, and its input status matches the problem's."""
    g = torch.Generator().manual_seed(9)
    p = random_problem(g, b=(3,), T=5)
    prep = riccati.prepare(p.cost, p.T, p.batch_shape)
    first = riccati.solve(p, grad="none", prepared=prep)
    torch.testing.assert_close(first.u, riccati.solve(p, grad="none").u, atol=1e-12, rtol=0)
    x0 = torch.randn(3, p.n, dtype=D, generator=g)
    p2 = dataclasses.replace(p, x0=x0)
    torch.testing.assert_close(riccati.solve(p2, grad="none", prepared=prep).u, lifted.solve_lifted(p2).u,
                               atol=1e-9, rtol=0)
    d2 = dataclasses.replace(p.dynamics, A=1.01 * p.dynamics.A)
    p3 = dataclasses.replace(p, dynamics=d2)
    torch.testing.assert_close(riccati.solve(p3, grad="none", prepared=prep).u, lifted.solve_lifted(p3).u,
                               atol=1e-9, rtol=0)
    shared = random_problem(g, b=(), T=5)
    p4 = dataclasses.replace(shared, x0=torch.randn(4, shared.n, dtype=D, generator=g))
    prep4 = riccati.prepare(shared.cost, 5, p4.batch_shape)
    torch.testing.assert_close(riccati.solve(p4, grad="none", prepared=prep4).u, lifted.solve_lifted(p4).u,
                               atol=1e-9, rtol=0)
    assert torch.equal(prep.status, torch.zeros(3, dtype=torch.int64))


def test_writes_that_bypass_the_version_counter_are_never_stale():
    """Writes through ``.data`` or a numpy view do not bump ``tensor._version``: a memo keyed on it would
    return the old answer without a sign.  Nothing is memoized any more: a plain solve sees the write, and
    a prepared cost is an explicit snapshot that is re-prepared by the caller."""
    g = torch.Generator().manual_seed(10)
    p = random_problem(g, b=(2,), T=4)
    riccati.solve(p, grad="none")
    v0 = p.cost.R._version
    p.cost.R.data.mul_(3.0)
    p.cost.x_ref.numpy()[...] += 1.0  # through numpy: no version bump either
    assert p.cost.R._version == v0
    torch.testing.assert_close(riccati.solve(p, grad="none").u, lifted.solve_lifted(p).u, atol=1e-9, rtol=0)
    prep = riccati.prepare(p.cost, 4, p.batch_shape)
    torch.testing.assert_close(riccati.solve(p, grad="none", prepared=prep).u, lifted.solve_lifted(p).u,
                               atol=1e-9, rtol=0)


def test_prepared_cost_contract():
    """A prepared cost is checked against the problem it is used with; errors name the argument."""
    g = torch.Generator().manual_seed(11)
    p = random_problem(g, b=(2,), T=4)
    prep = riccati.prepare(p.cost, 4, (2,))
    with pytest.raises(ValueError, match="argument 'prepared' needs grad='none'"):
        riccati.solve(p, prepared=prep)
    with pytest.raises(ValueError, match="argument 'prepared' was made for another problem"):
        riccati.solve(p, grad="none", prepared=riccati.prepare(p.cost, 4, (3, 2)))
    other = random_problem(torch.Generator().manual_seed(12), b=(2,), T=4)
    with pytest.raises(ValueError, match="another problem"):
        riccati.solve(p, grad="none", prepared=riccati.prepare(other.cost, 4, (2,)))
    with pytest.raises(ValueError, match="argument 'T'"):
        riccati.prepare(p.cost, 5, (2,))
    with pytest.raises(TypeError, match="argument 'cost'"):
        riccati.prepare(p.dynamics, 4)
    with pytest.raises(TypeError, match="argument 'prepared'"):
        riccati.solve(p, grad="none", prepared=(prep.C, prep.VT))
    # the cost's part of the input status travels with it: a bad element stays flagged, the other solved
    bad = dataclasses.replace(p.cost, R=p.cost.R.expand(2, *p.cost.R.shape[-3:]).clone())
    bad.R[1, 0, 0, 0] = -1.0
    pb = dataclasses.replace(p, cost=bad)
    sol = riccati.solve(pb, grad="none", prepared=riccati.prepare(bad, 4, pb.batch_shape))
    assert sol.status.reason_names() == ["CONVERGED", "NOT_POSITIVE_DEFINITE"]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_ls_recursive_gains_per_element_status(dtype):
    """A non-PD normal matrix in one element (here R = 0 and Q = 0: F is undefined) is that element's
    SINGULAR_QUU, with NaN outputs, instead of a LinAlgError for the batch; the other is unaffected."""
    g = torch.Generator().manual_seed(5)
    p = random_problem(g, b=(2,), T=4, drift=False, cross=False, refs=False, linear=False)
    pa = LQProblem(p.dynamics.expand_time(4), p.cost, p.x0)
    Sx, Su, Qb, Rb = _lifted_mats(pa)
    Qb, Rb = Qb.clone(), Rb.clone()
    Qb[1], Rb[1] = 0.0, 0.0
    args = [v.to(dtype) for v in (Sx, Su, Qb, Rb, pa.dynamics.A, pa.dynamics.B)]
    K, Fm, status = riccati.ls_recursive_gains(*args)
    assert status.reason_names() == ["CONVERGED", "SINGULAR_QUU"]
    assert bool(torch.isnan(K[1]).all()) and bool(torch.isfinite(K[0]).all())
    K0, F0, st0 = riccati.ls_recursive_gains(*[v[:1] for v in args])
    assert st0.all_converged
    torch.testing.assert_close(K[:1], K0)
    torch.testing.assert_close(Fm[:1], F0)
    if dtype == torch.float64:
        torch.testing.assert_close(K[0], riccati.solve(p).K[0], atol=1e-8, rtol=0)


def test_unstable_long_horizon_against_50_digit_reference():
    """An unstable A over T = 40: Riccati and the dense KKT solve match a 50-digit solve; the lifted
    (transfer-matrix) least squares loses most of its digits here (S_u grows like ‖A‖^T), which is why
    it is not used as an oracle on such problems."""
    from mp_oracle import lq_cost

    T, n = 40, 2
    A = 1.15 * torch.tensor([[1.0, 0.1], [0.3, 1.05]], dtype=D).expand(T, n, n)
    B = torch.tensor([[0.0], [0.1]], dtype=D).expand(T, n, 1)
    Q, R = torch.eye(n, dtype=D).expand(T + 1, n, n), 0.01 * torch.eye(1, dtype=D).expand(T, 1, 1)
    x0 = torch.tensor([1.0, -0.5], dtype=D)
    mu = torch.randn(T + 1, n, dtype=D, generator=torch.Generator().manual_seed(0))
    J, _, us = lq_cost(A, B, None, Q, R, x0, x_ref=mu)
    u_ref = torch.tensor([[float(v) for v in row] for row in us], dtype=D)
    p = LQProblem(LinearDynamics(A, B), QuadraticCost(Q, R, x_ref=mu), x0)
    sol = riccati.solve(p)
    torch.testing.assert_close(sol.u, u_ref, atol=1e-11, rtol=0)
    torch.testing.assert_close(sol.cost, torch.tensor(float(J), dtype=D), atol=0, rtol=1e-12)
    torch.testing.assert_close(dense_kkt(p)[1], u_ref, atol=1e-10, rtol=0)


def test_a_failed_element_is_nan_and_adds_nothing_to_a_shared_gradient():
    """One element with a singular weight (R = 0, batched) is NaN in every output and reported; the
    gradient of a shared reference equals that of the good elements solved alone (issue 22 sweep)."""
    from controllers.costs import QuadraticCost
    from controllers.dynamics import LinearDynamics
    from controllers.problem import LQProblem, Reason

    D, T, n = torch.float64, 5, 2
    A = torch.tensor([[1.0, 0.1], [0.0, 1.0]], dtype=D)
    Bm = torch.tensor([[0.0], [0.1]], dtype=D)
    x0 = torch.tensor([[1.0, 0.0], [1.0, 0.0], [0.5, 0.2]], dtype=D)
    R = torch.full((3, 1, 1, 1), 0.1, dtype=D)
    R[1] = 0.0

    def grad_of(idx):
        mu = torch.tensor([0.3, -0.2], dtype=D, requires_grad=True)
        cost = QuadraticCost(Q=torch.eye(n, dtype=D), R=R[idx], x_ref=mu)
        sol = riccati.solve(LQProblem(LinearDynamics(A, Bm), cost, x0[idx], horizon=T))
        (g,) = torch.autograd.grad(torch.nan_to_num(sol.u).sum() + torch.nan_to_num(sol.cost).sum(), mu)
        return sol, g

    sol, g = grad_of([0, 1, 2])
    assert sol.status.reason.tolist() == [0, int(Reason.NOT_POSITIVE_DEFINITE), 0]
    for v in (sol.x[1], sol.u[1], sol.K[1], sol.k[1], sol.cost[1]):
        assert bool(torch.isnan(v).all())
    _, g_good = grad_of([0, 2])
    torch.testing.assert_close(g, g_good, rtol=1e-12, atol=1e-12)


def test_lqr_core_backward_skips_an_element_whose_huu_is_not_pd():
    """The functional core (no validation) with H_uu indefinite for one element: that element's garbage
    outputs contribute nothing to the gradient of a shared linear term."""
    D, B, T, n, m = torch.float64, 3, 5, 2, 1
    A = torch.tensor([[1.0, 0.1], [0.0, 1.0]], dtype=D).expand(B, T, n, n)
    Bm = torch.tensor([[0.0], [0.1]], dtype=D).expand(B, T, n, m)
    Q = torch.eye(n, dtype=D).expand(B, T + 1, n, n)
    R = torch.full((B, T, m, m), 0.1, dtype=D)
    R[1] = -1.0
    x0 = torch.tensor([[1.0, 0.0], [1.0, 0.0], [0.5, 0.2]], dtype=D)

    def grad_of(idx):
        q = torch.tensor([0.3, -0.2], dtype=D, requires_grad=True)
        k = len(idx)
        x, u, K, kk, J, ok = riccati.lqr(A[idx], Bm[idx], None, Q[idx], R[idx], None, q.expand(k, T + 1, n),
                                         None, x0[idx], T)
        (g,) = torch.autograd.grad(u.sum() + J.sum(), q)
        return ok.all(-1), g

    ok, g = grad_of([0, 1, 2])
    assert ok.tolist() == [True, False, True]
    _, g_good = grad_of([0, 2])
    torch.testing.assert_close(g, g_good, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("grad", ["none", "implicit", "unrolled"])
def test_scaling_the_cost_does_not_change_the_plan(grad):
    """Q and R scaled together leave the minimizer unchanged; the pivot row of the elimination once lost
    its 1 against H_uu ≳ 1/ε (a cost scaled by 1e16 gave u0 17 % off, by 1e20 a plan of 800, CONVERGED)."""
    from controllers.costs import QuadraticCost
    from controllers.dynamics import LinearDynamics
    from controllers.problem import LQProblem

    D = torch.float64
    A = torch.tensor([[1.0, 0.1], [0.0, 1.0]], dtype=D)
    B = torch.tensor([[0.005, 0.0], [0.1, 0.02]], dtype=D)
    x0 = torch.tensor([[0.5, -0.2]], dtype=D)
    R = torch.diag(torch.tensor([0.1, 0.3], dtype=D))
    sols = []
    for s in (1.0, 1e16, 1e20):
        cost = QuadraticCost(Q=torch.eye(2, dtype=D) * s, R=R * s)
        sols.append(riccati.solve(LQProblem(LinearDynamics(A, B), cost, x0, 6), grad=grad))
    for sol in sols[1:]:
        torch.testing.assert_close(sol.u, sols[0].u, rtol=1e-12, atol=1e-13)
    if grad != "unrolled":  # the fused kernel (torch.compile) runs the same elimination
        cost = QuadraticCost(Q=torch.eye(2, dtype=D) * 1e20, R=R * 1e20)
        fused = riccati.solve(LQProblem(LinearDynamics(A, B), cost, x0, 6), grad=grad, fused=True)
        torch.testing.assert_close(fused.u, sols[0].u, rtol=1e-12, atol=1e-13)


@pytest.mark.parametrize("grad", ["implicit", "unrolled"])
@pytest.mark.parametrize("bad", ["x0 inf", "R nan at one step", "Q not PSD", "x_ref nan"])
def test_an_input_failure_adds_nothing_to_a_shared_dynamics_gradient(grad, bad):
    """An element whose inputs failed is solved on stand-in data: the gradient of a shared A from the
    good element equals that of the good element alone (before: NaN, as 0·inf)."""
    import math

    from controllers.costs import QuadraticCost
    from controllers.dynamics import LinearDynamics
    from controllers.problem import LQProblem

    D, T = torch.float64, 6
    A0 = torch.tensor([[1.0, 0.1], [0.0, 1.0]], dtype=D)
    B = torch.tensor([[0.005], [0.1]], dtype=D)
    x0 = torch.tensor([[1.0, 0.0], [0.5, -0.2]], dtype=D)
    R = torch.full((2, T, 1, 1), 0.1, dtype=D)
    Q = torch.eye(2, dtype=D).repeat(2, 1, 1, 1)
    if bad == "x0 inf":
        x0[1, 0] = math.inf
    elif bad == "R nan at one step":
        R[1, 2] = math.nan
    elif bad == "Q not PSD":
        Q[1, 0, 1, 1] = -1.0
    x_ref = torch.ones(2, T + 1, 2, dtype=D)
    if bad == "x_ref nan":  # enters the canonical q and constant before any stand-in of the LQ data
        x_ref[1, 0, 0] = math.nan

    def grad_of(idx):
        A = A0.clone().requires_grad_(True)
        w = torch.tensor(1.0, dtype=D, requires_grad=True)  # a shared weight scale
        cost = QuadraticCost(Q=Q[idx] * w, R=R[idx], x_ref=x_ref[idx])
        sol = riccati.solve(LQProblem(LinearDynamics(A, B), cost, x0[idx], T), grad=grad)
        gA, gw = torch.autograd.grad(sol.u[0].sum() + sol.cost[0], (A, w))
        return sol, gA, gw

    sol, gA, gw = grad_of([0, 1])
    assert sol.status.reason[0] == 0 and sol.status.reason[1] != 0
    _, gA_alone, gw_alone = grad_of([0])
    torch.testing.assert_close(gA, gA_alone, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(gw, gw_alone, rtol=1e-12, atol=1e-14)
