"""Independent references for box QPs ``min ½xᵀHx + gᵀx  s.t.  lo ≤ x ≤ hi`` (numpy, float64).

Nothing here imports the solver under test.  :func:`active_set_qp` is a textbook primal active-set method
(Nocedal & Wright, *Numerical Optimization*, 2nd ed., Algorithm 16.3, specialised to bounds): every
iterate is feasible, each subproblem is an exact equality-constrained solve on the current face, and it
stops when the face minimizer is feasible and every bound multiplier has the right sign, so its answer is
exact up to the rounding of those solves.  :func:`random_box_qp` builds the hard problem family of
issue 9 (log-spaced spectrum, warm starts on bounds, unbounded components).
"""

from __future__ import annotations

import numpy as np

__all__ = ["objective", "kkt_residual", "kkt_tolerance", "active_set_qp", "bvls_qp",
           "mp_kkt_check", "random_box_qp", "mp_minimizer", "mp_objective_difference", "objective_scale",
           "ill_conditioned_box_qp", "objective_gap_bound"]


def objective(H: np.ndarray, g: np.ndarray, x: np.ndarray) -> float:
    return float(0.5 * x @ H @ x + g @ x)


def kkt_residual(H, g, lo, hi, x) -> float:
    """``‖y − clip(y − ∇_y f, D^½ lo, D^½ hi)‖₂`` in the Jacobi-scaled variables ``y = D^½ x``,
    ``D = diag(H)`` (1 where not positive): the projected gradient of the scaled problem, zero exactly at
    KKT points and unchanged by the units of f and of each variable."""
    D = np.diag(H).copy()
    D[~(D > 0)] = 1.0
    s = np.sqrt(D)
    y, gy = s * x, (H @ x + g) / s
    return float(np.linalg.norm(y - np.clip(y - gy, s * lo, s * hi)))


def kkt_tolerance(H, g, x, tol: float) -> float:
    """The documented threshold of ``box_qp``'s certificate, ``tol·(‖g̃‖₂ + ‖H̃‖_F‖y‖₂)`` for the scaled
    problem ``H̃ = D^-½ H D^-½``, ``g̃ = D^-½ g``, ``y = D^½ x``."""
    D = np.diag(H).copy()
    D[~(D > 0)] = 1.0
    s = np.sqrt(D)
    return float(tol * (np.linalg.norm(g / s) + np.linalg.norm(H / np.outer(s, s)) * np.linalg.norm(s * x)))


def active_set_qp(H, g, lo, hi, x0=None, max_iter: int | None = None) -> np.ndarray:
    """Exact minimizer of one strictly convex box QP by a primal active-set method.

    The working set ``W`` holds the variables fixed on a bound.  Each iteration minimizes over the free
    variables with ``W`` fixed (a linear solve); if that point is feasible it checks the multipliers
    (``∂f/∂x_i ≥ 0`` on a lower bound, ``≤ 0`` on an upper one) and releases the most violated bound,
    otherwise it walks towards it until the first bound blocks and adds that bound to ``W``.
    """
    H = np.asarray(H, dtype=np.float64)
    g = np.asarray(g, dtype=np.float64)
    m = g.shape[0]
    lo = np.broadcast_to(np.asarray(lo, dtype=np.float64), (m,))
    hi = np.broadcast_to(np.asarray(hi, dtype=np.float64), (m,))
    x = np.clip(np.zeros(m) if x0 is None else np.asarray(x0, dtype=np.float64), lo, hi)
    at_lo, at_hi = x == lo, (x == hi) & (x != lo)
    max_iter = 20 * m + 50 if max_iter is None else max_iter
    for _ in range(max_iter):
        W = at_lo | at_hi
        F = ~W
        y = x.copy()
        if F.any():
            rhs = -(g[F] + H[np.ix_(F, W)] @ x[W])
            y[F] = np.linalg.solve(H[np.ix_(F, F)], rhs)
        d = y - x
        with np.errstate(divide="ignore", invalid="ignore"):
            t_lo = np.where(F & (d < 0), (lo - x) / d, np.inf)
            t_hi = np.where(F & (d > 0), (hi - x) / d, np.inf)
        t = np.minimum(t_lo, t_hi)
        j = int(np.argmin(t))
        if t[j] < 1.0:  # a bound blocks the way to the face minimizer: step to it and fix it
            x = x + t[j] * d
            x[F] = np.clip(x[F], lo[F], hi[F])
            if t_lo[j] <= t_hi[j]:
                x[j], at_lo[j] = lo[j], True
            else:
                x[j], at_hi[j] = hi[j], True
            continue
        x = y
        grad = H @ x + g
        lam = np.where(at_lo, grad, np.where(at_hi, -grad, np.inf))  # bound multipliers, must be ≥ 0
        scale = 1e-14 * (1.0 + np.abs(g).max() + np.abs(H).max() * np.abs(x[np.isfinite(x)]).max(initial=0))
        i = int(np.argmin(lam))
        if lam[i] >= -scale:
            return x
        at_lo[i] = at_hi[i] = False  # release the most violated bound
    raise RuntimeError("active_set_qp: no convergence (degenerate cycling?)")


def bvls_qp(H, g, lo, hi) -> np.ndarray:
    """The same QP through scipy's bounded-variable least squares: ``½xᵀHx + gᵀx = ½‖Lᵀx − b‖² + c``
    with ``H = LLᵀ`` and ``Lb = −g`` (Stark & Parker's BVLS, another active-set method)."""
    from scipy.linalg import cholesky, solve_triangular
    from scipy.optimize import lsq_linear

    L = cholesky(H, lower=True)
    b = -solve_triangular(L, g, lower=True)
    r = lsq_linear(L.T, b, bounds=(lo, hi), method="bvls", tol=1e-15, lsmr_tol=None, max_iter=10_000)
    return r.x


def mp_kkt_check(H, g, lo, hi, x, dps: int = 40) -> tuple[float, float]:
    """Exact check of a claimed minimizer in ``dps``-digit arithmetic (mpmath).

    Takes the face of ``x`` (variables exactly on a bound stay there), solves that face's equality-constrained
    minimizer in high precision and returns ``(max |x − x_face|, min multiplier)``; the claim is exact up to
    float64 rounding when the first is ~``eps·‖x‖·cond`` and the second is ``≥ 0`` (then ``x_face`` is the
    KKT point, hence the unique minimizer of a strictly convex problem).
    """
    import mpmath

    m = len(g)
    at_lo, at_hi = x == lo, (x == hi) & (x != lo)
    F = [i for i in range(m) if not (at_lo[i] or at_hi[i])]
    with mpmath.workdps(dps):
        Hm = mpmath.matrix([[mpmath.mpf(float(v)) for v in row] for row in H])
        gm = [mpmath.mpf(float(v)) for v in g]
        xf = [mpmath.mpf(float(v)) for v in x]
        if F:
            A = mpmath.matrix([[Hm[i, j] for j in F] for i in F])
            b = mpmath.matrix([-(gm[i] + sum(Hm[i, j] * xf[j] for j in range(m) if j not in F)) for i in F])
            sol = mpmath.lu_solve(A, b)
            for k, i in enumerate(F):
                xf[i] = sol[k]
        grad = [gm[i] + sum(Hm[i, j] * xf[j] for j in range(m)) for i in range(m)]
        lam = [grad[i] if at_lo[i] else -grad[i] for i in range(m) if at_lo[i] or at_hi[i]]
        feasible = all(lo[i] <= xf[i] <= hi[i] for i in F)
        dev = max(float(abs(xf[i] - mpmath.mpf(float(x[i])))) for i in range(m))
        return (dev if feasible else np.inf), (float(min(lam)) if lam else np.inf)


def random_box_qp(rng: np.random.Generator, m: int, cond: float, *, frac_on_bound: float = 0.4,
                  frac_unbounded: float = 0.1):
    """One strictly convex box QP with ``cond(H) = cond`` and a warm start with ``frac_on_bound`` of its
    variables put on a bound (the others uniform in ``[-1, 1]`` projected on the box, which puts some more
    there).  ``H = U diag(s) Uᵀ`` with Haar ``U`` and log-spaced ``s`` in ``[1/cond, 1]``
    (times a random overall scale); ``g`` is large enough that a good share of the bounds is active at
    the solution.  Each bound is ``±inf`` with probability ``frac_unbounded``.

    Returns ``(H, g, lo, hi, x0)`` as float64 numpy arrays.
    """
    Q, R = np.linalg.qr(rng.standard_normal((m, m)))
    U = Q * np.sign(np.diag(R))
    s = np.logspace(0.0, -np.log10(cond), m) * 10.0 ** rng.uniform(-1, 1)
    H = (U * s) @ U.T
    H = 0.5 * (H + H.T)
    lo = -rng.uniform(0.1, 1.5, m)
    hi = rng.uniform(0.1, 1.5, m)
    lo[rng.random(m) < frac_unbounded] = -np.inf
    hi[rng.random(m) < frac_unbounded] = np.inf
    # g = −H x_u with an unconstrained minimizer x_u well outside the box, plus a plain random part
    x_u = 2.0 * rng.standard_normal(m)
    g = -H @ x_u + s.max() * 0.3 * rng.standard_normal(m)
    x0 = rng.uniform(-1.0, 1.0, m)
    on = rng.random(m) < frac_on_bound
    up = rng.random(m) < 0.5
    x0 = np.where(on & up & np.isfinite(hi), hi, np.where(on & np.isfinite(lo), lo, x0))
    return H, g, lo, hi, np.clip(x0, lo, hi)


def objective_scale(H, g, x) -> float:
    """``½|xᵀHx| + |gᵀx|``: the size of the objective's terms that ``box_qp``'s gap tolerance is
    relative to."""
    return float(0.5 * abs(x @ H @ x) + abs(g @ x))


def mp_objective_difference(H, g, x, y, dps: int = 50) -> float:
    """``f(x) − f(y)`` computed exactly (``dps`` digits) for float64 data and points: free of the
    cancellation that limits a float64 evaluation of ``f`` to ``eps·|x|ᵀ|H||x|``."""
    import mpmath

    with mpmath.workdps(dps):
        d = [mpmath.mpf(float(a)) - mpmath.mpf(float(b)) for a, b in zip(x, y)]
        s = [mpmath.mpf(float(a)) + mpmath.mpf(float(b)) for a, b in zip(x, y)]
        m = len(d)
        # f(x) − f(y) = dᵀ(g + ½H(x + y)) with d = x − y
        total = mpmath.mpf(0)
        for i in range(m):
            hs = mpmath.fsum(mpmath.mpf(float(H[i, j])) * s[j] for j in range(m))
            total += d[i] * (mpmath.mpf(float(g[i])) + hs / 2)
        return float(total)


def mp_minimizer(H, g, lo, hi, x, dps: int = 50, max_changes: int = 30) -> np.ndarray:
    """The minimizer of a strictly convex box QP (float64 data taken exactly), found in ``dps``-digit
    arithmetic from a guess ``x`` (another solver's answer) and proved by its KKT conditions.

    Starting from the face of ``x`` (variables exactly on a bound held there), it solves the face's
    equality-constrained problem exactly; a free variable out of the box is put on the bound it crosses
    most, a held variable with a negative multiplier is released, until the face solution is feasible
    with multipliers ≥ 0: then it is the KKT point, hence the minimizer (whatever path led there).
    Returns it rounded to float64; raises if that is not reached in ``max_changes`` face changes.
    """
    import mpmath

    m = len(g)
    lo = np.broadcast_to(np.asarray(lo, dtype=np.float64), (m,))
    hi = np.broadcast_to(np.asarray(hi, dtype=np.float64), (m,))
    at_lo, at_hi = x == lo, (x == hi) & (x != lo)
    with mpmath.workdps(dps):
        Hm = mpmath.matrix([[mpmath.mpf(float(v)) for v in row] for row in H])
        gm = [mpmath.mpf(float(v)) for v in g]
        lom = [mpmath.mpf(float(v)) for v in lo]
        him = [mpmath.mpf(float(v)) for v in hi]
        tiny = mpmath.mpf(10) ** (-(dps // 2))
        for _ in range(max_changes):
            F = [i for i in range(m) if not (at_lo[i] or at_hi[i])]
            xf = [lom[i] if at_lo[i] else him[i] if at_hi[i] else mpmath.mpf(0) for i in range(m)]
            if F:
                A = mpmath.matrix([[Hm[i, j] for j in F] for i in F])
                b = mpmath.matrix([-(gm[i] + mpmath.fsum(Hm[i, j] * xf[j] for j in range(m) if j not in F))
                                   for i in F])
                sol = mpmath.cholesky_solve(A, b)
                for k, i in enumerate(F):
                    xf[i] = sol[k]
            excess = [(max(lom[i] - xf[i], xf[i] - him[i]), i) for i in F]
            worst, i = max(excess, default=(mpmath.mpf(0), -1))
            if worst > 0:
                at_lo[i], at_hi[i] = bool(xf[i] < lom[i]), bool(xf[i] > him[i])
                continue
            grad = [gm[i] + mpmath.fsum(Hm[i, j] * xf[j] for j in range(m)) for i in range(m)]
            lam = [(grad[i] if at_lo[i] else -grad[i], i) for i in range(m) if at_lo[i] or at_hi[i]]
            low, i = min(lam, default=(mpmath.mpf(0), -1))
            scale = tiny * (1 + max(abs(v) for v in grad))
            if low < -scale and lo[i] != hi[i]:
                at_lo[i] = at_hi[i] = False
                continue
            return np.array([float(v) for v in xf])
    raise RuntimeError("mp_minimizer: no KKT point reached")


def ill_conditioned_box_qp(rng: np.random.Generator, m: int, cond: float, *, g_scale: float | None = None):
    """A box QP whose difficulty is its conditioning (issue 22): ``H = U diag(s) Uᵀ`` with Haar ``U`` and
    log-spaced ``s`` in ``[1/cond, 1]`` (times a random overall scale), box ``[-1, 1]``, and a small
    random ``g`` (default ``100/cond`` times ``max(s)``): the unconstrained minimizer is large only along
    the weakest directions, so the solution has most variables free and a few on bounds, and a point
    that is wrong by a box width along a weak direction still has a small gradient.

    Returns ``(H, g, lo, hi)`` as float64 numpy arrays.
    """
    Q, R = np.linalg.qr(rng.standard_normal((m, m)))
    U = Q * np.sign(np.diag(R))
    s = np.logspace(0.0, -np.log10(cond), m) * 10.0 ** rng.uniform(-1, 1)
    H = (U * s) @ U.T
    H = 0.5 * (H + H.T)
    g = (100.0 / cond if g_scale is None else g_scale) * s.max() * rng.standard_normal(m)
    return H, g, -np.ones(m), np.ones(m)


def objective_gap_bound(H, g, lo, hi, x) -> float:
    """The documented bound of ``box_qp``'s certificate on ``f(x) − min f`` (numpy, float64): in the
    Jacobi-scaled variables with ``H̃ₛ = H̃ + mεI``, ``F`` the variables not exactly on a bound,
    ``d = H̃ₛ,FF⁻¹ γ̃_F``, the bound multipliers ``ν = γ̃ − H̃ₛ d`` projected on their sign (``e`` the
    removed part), ``½ γ̃_F·d_F + ½ eᵀH̃ₛ⁻¹e``; ``inf`` if ``H̃ₛ`` has no Cholesky factor."""
    m = len(g)
    D = np.diag(H).copy()
    D[~(D > 0)] = 1.0
    s = np.sqrt(D)
    Hs = H / np.outer(s, s) + m * np.finfo(np.float64).eps * np.eye(m)
    try:
        np.linalg.cholesky(Hs)
    except np.linalg.LinAlgError:
        return np.inf
    gt = (H @ x + g) / s
    on_lo, on_hi = x == lo, x == hi
    F = ~(on_lo | on_hi)
    d = np.zeros(m)
    d[F] = np.linalg.solve(Hs[np.ix_(F, F)], gt[F])
    nu = gt - Hs @ d
    lam = np.where(on_lo & ~on_hi, np.maximum(nu, 0), np.where(on_hi & ~on_lo, np.minimum(nu, 0), nu))
    e = np.where(F, 0.0, nu - lam)
    return float(0.5 * gt[F] @ d[F] + 0.5 * e @ np.linalg.solve(Hs, e))
