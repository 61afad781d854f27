"""Random LQ problems and an independent dense KKT oracle shared by the controller tests (not a test file)."""

import torch

from controllers.costs import QuadraticCost
from controllers.dynamics import LinearDynamics
from controllers.problem import LQProblem

D = torch.float64


def spd(*shape, k, g, eps=0.2, dtype=D):
    M = torch.randn(*shape, k, k, dtype=dtype, generator=g)
    return M @ M.mT / k + eps * torch.eye(k, dtype=dtype)


def random_problem(g, b=(3,), T=6, n=4, m=2, *, drift=True, cross=True, refs=True, linear=True,
                   tv=True, dtype=D):
    """A random well-posed LQT problem with every feature switched on by default."""
    Ta = T if tv else 1
    A = torch.eye(n, dtype=dtype) + 0.4 * torch.randn(*b, Ta, n, n, dtype=dtype, generator=g)
    B = torch.randn(*b, Ta, n, m, dtype=dtype, generator=g)
    c = 0.3 * torch.randn(*b, Ta, n, dtype=dtype, generator=g) if drift else None
    Q = spd(*b, T + 1, k=n, g=g, dtype=dtype)
    R = spd(*b, T, k=m, g=g, dtype=dtype)
    kw = {}
    if cross:
        kw["N"] = 0.05 * torch.randn(*b, T, n, m, dtype=dtype, generator=g)
    if refs:
        kw["x_ref"] = torch.randn(*b, T + 1, n, dtype=dtype, generator=g)
        kw["u_ref"] = 0.5 * torch.randn(*b, T, m, dtype=dtype, generator=g)
    if linear:
        kw["q"] = 0.5 * torch.randn(*b, T + 1, n, dtype=dtype, generator=g)
        kw["r"] = 0.5 * torch.randn(*b, T, m, dtype=dtype, generator=g)
    x0 = torch.randn(*b, n, dtype=dtype, generator=g)
    return LQProblem(LinearDynamics(A, B, c), QuadraticCost(Q, R, **kw), x0, horizon=T)


def dense_kkt(problem):
    """Solve one batch element at a time with a dense KKT system over (x_0..x_T, u_0..u_{T-1}).

    Built from the raw problem fields (not from the solvers' canonical form): the Hessian of
    Σ (x-μ)ᵀQ(x-μ) + (u-ν)ᵀR(u-ν) + 2(x-μ)ᵀN(u-ν) + 2qᵀ(x-μ) + 2rᵀ(u-ν) and the dynamics as equality
    constraints.  Returns x (*B, T+1, n), u (*B, T, m).
    """
    T, n, m = problem.T, problem.n, problem.m
    bs = problem.batch_shape
    d, c = problem.dynamics.expand_time(T), problem.cost
    E = lambda v, *s: None if v is None else v.expand(*bs, *s)
    A, B = E(d.A, T, n, n), E(d.B, T, n, m)
    cd = E(d.c, T, n)
    Q, R = E(c.Q, T + 1, n, n), E(c.R, T, m, m)
    N = E(c.N, T, n, m)
    mu, nu = E(c.x_ref, T + 1, n), E(c.u_ref, T, m)
    q, r = E(c.q, T + 1, n), E(c.r, T, m)
    x0 = problem.x0.expand(*bs, n)
    nx, nu_ = (T + 1) * n, T * m
    nz = nx + nu_
    ncon = (T + 1) * n
    xs, us = [], []
    idxs = torch.cartesian_prod(*[torch.arange(s) for s in bs]).reshape(-1, len(bs)).tolist() if bs else [[]]
    for idx in idxs:
        i = tuple(idx)
        H = torch.zeros(nz, nz, dtype=x0.dtype)
        gv = torch.zeros(nz, dtype=x0.dtype)
        xi = lambda t: slice(t * n, (t + 1) * n)
        ui = lambda t: slice(nx + t * m, nx + (t + 1) * m)
        for t in range(T + 1):
            H[xi(t), xi(t)] += 2 * Q[i][t]
            mut = torch.zeros(n, dtype=x0.dtype) if mu is None else mu[i][t]
            gv[xi(t)] += -2 * Q[i][t] @ mut + (0 if q is None else 2 * q[i][t])
        for t in range(T):
            H[ui(t), ui(t)] += 2 * R[i][t]
            nut = torch.zeros(m, dtype=x0.dtype) if nu is None else nu[i][t]
            mut = torch.zeros(n, dtype=x0.dtype) if mu is None else mu[i][t]
            gv[ui(t)] += -2 * R[i][t] @ nut + (0 if r is None else 2 * r[i][t])
            if N is not None:
                H[xi(t), ui(t)] += 2 * N[i][t]
                H[ui(t), xi(t)] += 2 * N[i][t].T
                gv[xi(t)] += -2 * N[i][t] @ nut
                gv[ui(t)] += -2 * N[i][t].T @ mut
        G = torch.zeros(ncon, nz, dtype=x0.dtype)
        h = torch.zeros(ncon, dtype=x0.dtype)
        G[0:n, xi(0)] = torch.eye(n, dtype=x0.dtype)
        h[0:n] = x0[i]
        for t in range(T):
            rows = slice((t + 1) * n, (t + 2) * n)
            G[rows, xi(t + 1)] = torch.eye(n, dtype=x0.dtype)
            G[rows, xi(t)] = -A[i][t]
            G[rows, ui(t)] = -B[i][t]
            h[rows] = 0 if cd is None else cd[i][t]
        K = torch.zeros(nz + ncon, nz + ncon, dtype=x0.dtype)
        K[:nz, :nz], K[:nz, nz:], K[nz:, :nz] = H, G.T, G
        sol = torch.linalg.solve(K, torch.cat([-gv, h]))
        xs.append(sol[:nx].reshape(T + 1, n))
        us.append(sol[nx:nz].reshape(T, m))
    return torch.stack(xs).reshape(*bs, T + 1, n), torch.stack(us).reshape(*bs, T, m)
