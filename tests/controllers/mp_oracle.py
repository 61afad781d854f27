"""A 50-digit reference for LQ problems (not a test file): condensed solve in mpmath.

Float64 solvers lose about ``cond · eps`` of accuracy; on problems with precisions of 1e8 or unstable
dynamics that is most of the digits, so no float64 formulation can be the oracle there.  This one
eliminates the dynamics exactly (``x = S_x x_0 + S_u u + s_c``, built in mpmath), solves the normal
equations of the condensed cost in 50-digit arithmetic and differentiates by central differences
with a step of ``1e-20`` (truncation error ``~1e-40``), so its gradients are exact to far below
float64 round-off.  One batch element at a time; fine for the small problems of the tests.
"""

from __future__ import annotations

import mpmath
import torch

DPS = 50


def _mp(v: torch.Tensor):
    """A float64 tensor as nested lists of exact mpf values."""
    if v.dim() == 0:
        return mpmath.mpf(float(v))
    return [_mp(w) for w in v]


def lq_cost(A, B, c, Q, R, x0, x_ref=None, u_ref=None, q=None, r=None, N=None, dps: int = DPS):
    """Optimal cost, states and controls of one LQT problem (conventions of ``controllers.problem``).

    Arguments are mpmath nested lists (or tensors, converted exactly) with explicit full time dims:
    ``A (T, n, n)``, ``B (T, n, m)``, ``c (T, n)`` or None, ``Q (T+1, n, n)``, ``R (T, m, m)``,
    ``x0 (n,)``, optional ``x_ref (T+1, n)``, ``u_ref (T, m)``, ``q (T+1, n)``, ``r (T, m)``,
    ``N (T, n, m)``.  Returns ``(J, x, u)`` with mpf entries.
    """
    args = [A, B, c, Q, R, x0, x_ref, u_ref, q, r, N]
    A, B, c, Q, R, x0, x_ref, u_ref, q, r, N = [
        _mp(v) if isinstance(v, torch.Tensor) else v for v in args]
    with mpmath.workdps(dps):
        T, n, m = len(A), len(A[0]), len(B[0][0])
        nu = T * m
        zero = mpmath.mpf(0)
        # x_t = a_t + S_t u  (a_t (n,), S_t (n, T m)) by the recursion
        a = [list(x0)]
        S = [[[zero] * nu for _ in range(n)]]
        for t in range(T):
            an, Sn = [], []
            for i in range(n):
                v = sum(A[t][i][j] * a[t][j] for j in range(n)) + (zero if c is None else c[t][i])
                row = [sum(A[t][i][j] * S[t][j][k] for j in range(n)) for k in range(nu)]
                for k in range(m):
                    row[t * m + k] += B[t][i][k]
                an.append(v)
                Sn.append(row)
            a.append(an)
            S.append(Sn)
        H = mpmath.zeros(nu, nu)
        g = mpmath.zeros(nu, 1)
        const = zero

        def add_quad(W, Srows, d):
            """Add (S u + d)ᵀ W (S u + d) to H, g, const (Srows: list of coefficient rows)."""
            nonlocal const
            k = len(W)
            WS = [[sum(W[i][j] * Srows[j][col] for j in range(k)) for col in range(nu)] for i in range(k)]
            Wd = [sum(W[i][j] * d[j] for j in range(k)) for i in range(k)]
            for p in range(nu):
                for s_ in range(nu):
                    H[p, s_] += sum(Srows[i][p] * WS[i][s_] for i in range(k))
                g[p] += sum(Srows[i][p] * Wd[i] for i in range(k))
            const += sum(d[i] * Wd[i] for i in range(k))

        def add_lin(w, Srows, d):
            """Add 2 wᵀ (S u + d)."""
            nonlocal const
            for p in range(nu):
                g[p] += sum(w[i] * Srows[i][p] for i in range(len(w)))
            const += 2 * sum(w[i] * d[i] for i in range(len(w)))

        def urows(t):
            return [[mpmath.mpf(1) if col == t * m + k else zero for col in range(nu)] for k in range(m)]

        for t in range(T + 1):
            dx = [a[t][i] - (zero if x_ref is None else x_ref[t][i]) for i in range(n)]
            add_quad(Q[t], S[t], dx)
            if q is not None:
                add_lin(q[t], S[t], dx)
        for t in range(T):
            du = [-(zero if u_ref is None else u_ref[t][k]) for k in range(m)]
            add_quad(R[t], urows(t), du)
            if r is not None:
                add_lin(r[t], urows(t), du)
            if N is not None:
                # 2 dxᵀ N du: symmetric quadratic form over the stacked [dx; du]
                dx = [a[t][i] - (zero if x_ref is None else x_ref[t][i]) for i in range(n)]
                rows = S[t] + urows(t)
                W = [[zero] * (n + m) for _ in range(n + m)]
                for i in range(n):
                    for k in range(m):
                        W[i][n + k] = N[t][i][k]
                        W[n + k][i] = N[t][i][k]
                add_quad(W, rows, dx + du)
        u = mpmath.lu_solve(H, -g)
        J = const + 2 * sum(g[p] * u[p] for p in range(nu)) + sum(
            u[p] * sum(H[p, s_] * u[s_] for s_ in range(nu)) for p in range(nu))
        us = [[u[t * m + k] for k in range(m)] for t in range(T)]
        xs = [[a[t][i] + sum(S[t][i][p] * u[p] for p in range(nu)) for i in range(n)] for t in range(T + 1)]
        return J, xs, us


def fd_gradient(fields: dict, name: str, index: tuple, loss, dps: int = DPS, h: str = "1e-20",
                sym: bool = False) -> float:
    """Central difference of ``loss(J, x, u)`` w.r.t. ``fields[name][index]`` in ``dps``-digit arithmetic.

    ``fields``: keyword arguments of :func:`lq_cost` as float64 tensors (one batch element);
    ``loss(J, x, u) -> mpf``.  ``sym``: perturb the entry and its transpose together (a symmetric
    matrix, index ``(..., i, j)``).  Returns a Python float.
    """
    with mpmath.workdps(dps):
        hh = mpmath.mpf(h)
        vals = []
        for sgn in (1, -1):
            kw = {k: (_mp(v) if isinstance(v, torch.Tensor) else v) for k, v in fields.items()}
            ref = kw[name]
            for i in index[:-1]:
                ref = ref[i]
            ref[index[-1]] = ref[index[-1]] + sgn * hh
            if sym:
                ref2 = kw[name]
                for i in (*index[:-2], index[-1]):
                    ref2 = ref2[i]
                ref2[index[-2]] = ref2[index[-2]] + sgn * hh
            vals.append(loss(*lq_cost(**kw, dps=dps)))
        return float((vals[0] - vals[1]) / (2 * hh))
