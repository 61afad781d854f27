"""Anchor side of ``liecontrol bench solver``'s ``cookbook_car`` and ``cookbook_bicopter`` rows: the seed-004
cookbook's batch iLQR (§8.1, Algorithm 4) on a nonlinear vehicle in plain numpy, as its scripts
``iLQR_car`` (§9.15) and ``iLQR_bicopter`` (§9.16) do it.

Runs standalone in a subprocess (so that ``OPENBLAS_NUM_THREADS`` pins numpy's BLAS to the bench's thread
count) and imports nothing from this project.

The systems (``system`` field of the problem file):

* ``"car"``, the velocity-input car of §9.15, ``x = [x₁, x₂, θ, ϕ]``, ``u = [u₁, u₂]``, wheelbase ``ℓ``::

      ẋ₁ = u₁ cos θ,  ẋ₂ = u₁ sin θ,  θ̇ = (u₁/ℓ) tan ϕ,  ϕ̇ = u₂,

  discretized by explicit Euler ``x⁺ = x + Δt f(x, u)``, whose Jacobians are Eq. 118 through Eq. 192
  (``A = I + Δt A_c``, ``B = Δt B_c``);
* ``"bicopter"``, §9.16, ``x = [x₁, x₂, θ, ẋ₁, ẋ₂, θ̇]``, ``u = [u₁, u₂]`` (absolute rotor thrusts)::

      ẍ₁ = -(u₁ + u₂) sin θ / m,  ẍ₂ = (u₁ + u₂) cos θ / m - g,  θ̈ = ℓ (u₁ - u₂) / I,

  discretized by semi-implicit Euler (``v⁺ = v + Δt a``, ``q⁺ = q + Δt v⁺``) with the exact Jacobians of
  that step built from Eq. 120's ``∂a/∂x``, ``∂a/∂u``: ``A = [[I + Δt² a_q, Δt I], [Δt a_q, I]]``,
  ``B = [[Δt² a_u], [Δt a_u]]`` (the discretization of ``controllers.systems.bicopter``, so that both sides
  solve the same problem).

The problem: from ``x_1`` (``x0``), reach ``μ`` (``target``) at the last state, with the tracking cost of
Eq. 106 on the stacked trajectory, ``Q`` block-diagonal over all ``T+1`` times (zero blocks except the last,
``Q_T``) and ``R = r I``::

    c(u) = (x - μ)ᵀ Q (x - μ) + uᵀ R u.

Each iteration (Algorithm 4): roll out ``x`` from ``u`` with a time loop; the analytic ``A_t, B_t`` along
it (Eq. 82, vectorized over time); the dense transfer matrix ``S_u ((T+1) n × T m)`` of Eq. 188 by its
recursion (block row ``t+1`` = ``A_t`` times block row ``t``, plus ``B_t`` in column ``t``, Appendix A);
the Gauss-Newton step of Eq. 87 / 108 with dense ``Q`` and ``R`` as the scripts form them::

    Δu = (S_uᵀ Q S_u + R)⁻¹ (-S_uᵀ Q (x - μ) - R u),

then the backtracking line search of Algorithm 1 (``α = 1, ½, ¼, ...`` while the cost increases and
``α > alpha_min``) and the update of Eq. 100, ``u ← u + α Δu``.  It runs exactly ``iterations`` iterations
(the count the compared solver took), from the given initial controls ``u_init``.

Usage::

    OPENBLAS_NUM_THREADS=1 python liecontrol/bench/_cookbook_vehicle_anchor.py PROBLEM.npz [--repeats 3]

``PROBLEM.npz`` (``allow_pickle=False``): ``system`` (``"car"`` or ``"bicopter"``), ``params``
(``[ℓ, Δt]`` for the car, ``[m, I, ℓ, g, Δt]`` for the bicopter), ``T`` (control steps), ``x0 (n,)``,
``target (n,)``, ``QT (n, n)``, ``r``, ``u_init (T, m)``, ``iterations``, ``alpha_min``.  One JSON object
goes to stdout: ``ok``, ``error``, ``ms`` (median wall time of one whole solve over ``repeats`` runs after
one warm-up), ``cost`` (final), ``costs`` (after each iteration), ``u`` (``T × m`` final controls,
row-major).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time

import numpy as np

SYSTEMS = ("car", "bicopter")


class Car:
    """The velocity-input car (module docstring), explicit Euler."""

    n, m = 4, 2

    def __init__(self, params):
        self.length, self.dt = (float(p) for p in params)

    def step(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """``x⁺ (..., 4)`` from ``x (..., 4)``, ``u (..., 2)``."""
        th, ph, v = x[..., 2], x[..., 3], u[..., 0]
        f = np.stack([v * np.cos(th), v * np.sin(th), v * np.tan(ph) / self.length, u[..., 1]], -1)
        return x + self.dt * f

    def jacobian(self, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``A (..., 4, 4)``, ``B (..., 4, 2)``: Eq. 118 through Eq. 192."""
        dt, length = self.dt, self.length
        th, ph, v = x[..., 2], x[..., 3], u[..., 0]
        c, s, tn = np.cos(th), np.sin(th), np.tan(ph)
        dtv = dt * v
        A = np.zeros(x.shape[:-1] + (4, 4)) + np.eye(4)
        A[..., 0, 2] = -dtv * s
        A[..., 1, 2] = dtv * c
        A[..., 2, 3] = dtv * (1 + tn * tn) / length
        B = np.zeros(x.shape[:-1] + (4, 2))
        B[..., 0, 0] = dt * c
        B[..., 1, 0] = dt * s
        B[..., 2, 0] = dt * tn / length
        B[..., 3, 1] = dt
        return A, B


class Bicopter:
    """The planar bicopter (module docstring), semi-implicit Euler, absolute thrusts."""

    n, m = 6, 2

    def __init__(self, params):
        self.mass, self.inertia, self.arm, self.gravity, self.dt = (float(p) for p in params)

    def acceleration(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        th = x[..., 2]
        u1, u2 = u[..., 0], u[..., 1]
        T = u1 + u2
        return np.stack([-T * np.sin(th) / self.mass, T * np.cos(th) / self.mass - self.gravity,
                         (u1 - u2) * (self.arm / self.inertia)], -1)

    def step(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """``x⁺ (..., 6)``: ``v⁺ = v + Δt a``, ``q⁺ = q + Δt v⁺``."""
        dt = self.dt
        v1 = x[..., 3:] + dt * self.acceleration(x, u)
        return np.concatenate([x[..., :3] + dt * v1, v1], -1)

    def jacobian(self, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``A (..., 6, 6)``, ``B (..., 6, 2)`` of :meth:`step` from Eq. 120's ``∂a/∂θ`` and ``∂a/∂u``."""
        dt, mass = self.dt, self.mass
        th = x[..., 2]
        s, c = np.sin(th), np.cos(th)
        T = u[..., 0] + u[..., 1]
        bs = x.shape[:-1]
        a_q = np.zeros(bs + (3, 3))
        a_q[..., 0, 2] = -T * c / mass
        a_q[..., 1, 2] = -T * s / mass
        a_u = np.zeros(bs + (3, 2))
        a_u[..., 0, :] = (-s / mass)[..., None]
        a_u[..., 1, :] = (c / mass)[..., None]
        k = self.arm / self.inertia
        a_u[..., 2, 0], a_u[..., 2, 1] = k, -k
        eye = np.eye(3)
        Av = np.concatenate([dt * a_q, np.broadcast_to(eye, bs + (3, 3))], -1)  # a_v = 0
        Aq = np.concatenate([np.broadcast_to(eye, bs + (3, 3)), np.zeros(bs + (3, 3))], -1) + dt * Av
        Bv = dt * a_u
        return np.concatenate([Aq, Av], -2), np.concatenate([dt * Bv, Bv], -2)


def make_system(name: str, params):
    if name == "car":
        return Car(params)
    if name == "bicopter":
        return Bicopter(params)
    raise ValueError(f"system must be one of {SYSTEMS}, got {name!r}")


class BatchILQR:
    """The problem of the module docstring with its constant matrices built once."""

    def __init__(self, d: dict):
        self.sys = make_system(str(d["system"]), np.asarray(d["params"], float))
        n, m = self.sys.n, self.sys.m
        self.T = T = int(d["T"])
        self.x0 = np.asarray(d["x0"], float).reshape(n)
        self.mu = np.tile(np.asarray(d["target"], float).reshape(n), T + 1)  # μ stacked over time
        self.Q = np.zeros(((T + 1) * n, (T + 1) * n))  # dense block diagonal: only the last block is set
        self.Q[T * n:, T * n:] = np.asarray(d["QT"], float).reshape(n, n)
        self.R = float(d["r"]) * np.eye(T * m)
        self.u_init = np.asarray(d["u_init"], float).reshape(T, m)
        self.alpha_min = float(d["alpha_min"])

    def rollout(self, u: np.ndarray) -> np.ndarray:
        """States ``(T+1, n)`` from controls ``(T, m)``, one step at a time."""
        x = np.zeros((self.T + 1, self.sys.n))
        x[0] = self.x0
        for t in range(self.T):
            x[t + 1] = self.sys.step(x[t], u[t])
        return x

    def cost(self, u: np.ndarray, x: np.ndarray | None = None) -> float:
        e = (self.rollout(u) if x is None else x).reshape(-1) - self.mu
        uf = u.reshape(-1)
        return float(e @ self.Q @ e + uf @ self.R @ uf)

    def transfer(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """``S_u ((T+1) n, T m)`` of Eq. 188 along ``(x, u)`` by the recursion of Appendix A."""
        n, m, T = self.sys.n, self.sys.m, self.T
        A, B = self.sys.jacobian(x[:-1], u)
        Su = np.zeros(((T + 1) * n, T * m))
        for t in range(T):
            Su[(t + 1) * n:(t + 2) * n] = A[t] @ Su[t * n:(t + 1) * n]
            Su[(t + 1) * n:(t + 2) * n, t * m:(t + 1) * m] = B[t]
        return Su

    def solve(self, iterations: int) -> tuple[np.ndarray, list[float]]:
        u = self.u_init.copy()
        costs = []
        for _ in range(iterations):
            x = self.rollout(u)
            Su = self.transfer(x, u)
            e = x.reshape(-1) - self.mu
            SQ = Su.T @ self.Q
            du = np.linalg.solve(SQ @ Su + self.R, -SQ @ e - self.R @ u.reshape(-1)).reshape(u.shape)
            c0, alpha = self.cost(u, x), 1.0
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
