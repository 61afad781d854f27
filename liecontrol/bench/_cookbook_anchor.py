"""Anchor side of ``liecontrol bench solver``'s ``cookbook_manipulator`` row: the seed-004 cookbook's batch
iLQR (§8.1, Algorithm 4, with the cost on ``f(x)`` of §9 / §9.1) in plain numpy, as its own scripts do it.

Runs standalone in a subprocess (so that ``OPENBLAS_NUM_THREADS`` pins numpy's BLAS to the bench's thread
count) and imports nothing from this project.

The problem (a planar arm under joint-velocity commands reaching end-effector poses at via points)::

    x_{t+1} = x_t + Δt u_t                                    (§9.1: A_t = I, B_t = Δt I)
    f^ee(x) = [ℓᵀ cos(L x), ℓᵀ sin(L x), 1ᵀ x]                (§4, L lower-triangular ones)
    c(x, u) = Σ_{t ∈ via} f(x_t)ᵀ Q f(x_t) + Σ_t u_tᵀ R u_t,   f(x_t) = f^ee(x_t) - μ_t     (Eq. 102, 106)

Each iteration (Algorithm 4): roll out, stack ``f`` and ``J = ∂f^ee/∂x`` at the via points, form the rows
of the transfer matrix ``S_u`` (``x = S_x x_0 + S_u u``, Appendix A) at those times and take the Gauss-Newton
step of Eq. 108::

    Δu = (S_uᵀ Jᵀ Q J S_u + R)⁻¹ (-S_uᵀ Jᵀ Q f - R u),

then the backtracking line search of Algorithm 1 (``α = 1, ½, ¼, ...`` down to ``alpha_min`` until the cost
does not increase).  It runs exactly ``iterations`` iterations (the count the compared solver took).

Usage::

    OPENBLAS_NUM_THREADS=1 python liecontrol/bench/_cookbook_anchor.py PROBLEM.npz [--repeats 3]

``PROBLEM.npz`` (``allow_pickle=False``): ``lengths (k,)``, ``dt``, ``T`` (control steps), ``x0 (k,)``,
``via_t (V,)`` (state indices 0..T), ``via_mu (V, 3)``, ``Q (3, 3)``, ``r`` (``R = r I``), ``iterations``,
``alpha_min``.  One JSON object goes to stdout: ``ok``, ``error``, ``ms`` (median wall time of one whole
solve over ``repeats`` runs after one warm-up), ``cost`` (final), ``costs`` (after each iteration),
``u`` (``T × k`` final controls, row-major).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time

import numpy as np


def forward_kinematics(x: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """``f^ee`` of joint angles ``x (..., k)``: ``(..., 3)`` position and orientation."""
    phi = np.cumsum(x, axis=-1)
    return np.stack([(lengths * np.cos(phi)).sum(-1), (lengths * np.sin(phi)).sum(-1), phi[..., -1]], -1)


def ee_jacobian(x: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """``∂f^ee/∂x (..., 3, k)``: column ``j`` sums the links from ``j`` on."""
    phi = np.cumsum(x, axis=-1)
    dx = np.cumsum((-lengths * np.sin(phi))[..., ::-1], -1)[..., ::-1]
    dy = np.cumsum((lengths * np.cos(phi))[..., ::-1], -1)[..., ::-1]
    return np.stack([dx, dy, np.ones_like(x)], -2)


class BatchILQR:
    """The problem of the module docstring with its constant matrices built once."""

    def __init__(self, d: dict):
        self.lengths = np.asarray(d["lengths"], float)
        self.k = self.lengths.shape[0]
        self.T, self.dt = int(d["T"]), float(d["dt"])
        self.x0 = np.asarray(d["x0"], float)
        self.via_t = np.asarray(d["via_t"], int)
        self.mu = np.asarray(d["via_mu"], float)
        V = self.via_t.shape[0]
        self.Qbig = np.kron(np.eye(V), np.asarray(d["Q"], float))  # blockdiag over the via points
        self.r = float(d["r"])
        self.alpha_min = float(d["alpha_min"])
        k, T = self.k, self.T
        # rows of S_u at the via points: x_t = x_0 + Δt Σ_{s<t} u_s
        self.Su = np.zeros((V * k, T * k))
        for i, t in enumerate(self.via_t):
            for s in range(t):
                self.Su[i * k:(i + 1) * k, s * k:(s + 1) * k] = self.dt * np.eye(k)

    def rollout(self, u: np.ndarray) -> np.ndarray:
        """States ``(T+1, k)`` from controls ``(T, k)``."""
        return np.concatenate([self.x0[None], self.x0 + self.dt * np.cumsum(u, 0)])

    def residual(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        xv = self.rollout(u)[self.via_t]
        return (forward_kinematics(xv, self.lengths) - self.mu).reshape(-1), xv

    def cost(self, u: np.ndarray) -> float:
        f, _ = self.residual(u)
        return float(f @ self.Qbig @ f + self.r * np.sum(u * u))

    def solve(self, iterations: int) -> tuple[np.ndarray, list[float]]:
        T, k = self.T, self.k
        u = np.zeros((T, k))
        costs = []
        for _ in range(iterations):
            f, xv = self.residual(u)
            J = np.zeros((f.shape[0], f.shape[0]))
            for i, Ji in enumerate(ee_jacobian(xv, self.lengths)):
                J[3 * i:3 * i + 3, k * i:k * i + k] = Ji
            JS = J @ self.Su
            H = JS.T @ self.Qbig @ JS + self.r * np.eye(T * k)
            g = JS.T @ self.Qbig @ f + self.r * u.reshape(-1)
            du = np.linalg.solve(H, -g).reshape(T, k)
            c0, alpha = self.cost(u), 1.0
            while self.cost(u + alpha * du) > c0 and alpha > self.alpha_min:
                alpha *= 0.5
            u = u + alpha * du
            costs.append(self.cost(u))
        return u, costs


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("npz")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    try:
        with np.load(args.npz, allow_pickle=False) as z:
            d = {key: z[key] for key in z.files}
        iterations = int(d["iterations"])
        times = []
        for i in range(1 + max(1, args.repeats)):  # the first run is a warm-up
            t0 = time.perf_counter()
            u, costs = BatchILQR(d).solve(iterations)
            if i:
                times.append(1e3 * (time.perf_counter() - t0))
        out = {"ok": True, "error": None, "ms": statistics.median(times),
               "cost": costs[-1] if costs else None, "costs": costs, "u": u.reshape(-1).tolist(),
               "numpy": np.__version__}
    except Exception as e:  # report, never crash the benchmark
        out = {"ok": False, "error": f"{type(e).__name__}: {e}".splitlines()[0][:300]}
    json.dump(out, sys.stdout)
    return 0


if __name__ == "__main__":
    sys.exit(main())
