"""Anchor side of ``liecontrol bench ilqr``: mpc.pytorch's box-DDP MPC and pypose's MPC on the same problems.

Runs standalone in the separate environment that holds mpc.pytorch (numpy < 2), so it imports nothing
from this project: the pendulum and cart-pole dynamics (semi-implicit Euler, the same equations as
``controllers.systems``) and the quadratic cost are written here again in plain torch.

Usage::

    .venv-mpc/bin/python liecontrol/bench/_mpc_ilqr_anchor.py PROBLEM.npz [--threads 1] [--repeats 1]

``PROBLEM.npz`` (loaded with ``allow_pickle=False``) holds ``problem`` ("pendulum" | "cartpole"),
``x0 (B, n)``, ``T``, ``dt``, ``umax``, ``Qd (n,)``, ``QTd (n,)``, ``R``, ``target (n,)``, ``params``
(system parameters), ``lqr_iter`` and ``eps``.  Cost (per element)::

    Σ_{t<T} (x_t - x*)ᵀ diag(Qd) (x_t - x*) + R u_t²  +  (x_T - x*)ᵀ diag(QTd) (x_T - x*)

mpc.pytorch charges ``½ τᵀ C τ + cᵀ τ`` on ``τ_t = [x_t, u_t]`` for ``t = 0 .. T_a - 1``; with
``T_a = T + 1``, ``C_t = 2 diag(Qd, R)`` (``t < T``), ``C_T = 2 diag(QTd, R)`` and ``c_t = -C_t [x*, 0]``
it is the same objective up to a constant (the extra control ``u_T`` only costs ``R u_T²`` and is 0 at
the optimum).

Prints one JSON object on stdout: ``{"mpc_pytorch": {...}, "pypose": {...}, "pypose_b1": {...}}`` (the
last: pypose on the first initial state alone, when it fails on the batch) with ``ok``, ``error``,
``ms`` (median wall time of one solve), ``u`` ((B, T, m) nested lists), ``x`` ((B, T+1, n), the anchor's own
rollout) and anchor-specific notes.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
import traceback

import numpy as np
import torch
from torch import nn


class PendulumDx(nn.Module):
    """x = [θ, ω], u = [τ]; m l² ω̇ = τ - b ω - m g l sin θ; semi-implicit Euler."""

    def __init__(self, params, dt):
        super().__init__()
        self.mass, self.length, self.damping, self.gravity = (float(v) for v in params)
        self.dt = float(dt)

    def forward(self, x, u):
        th, om = x[:, 0], x[:, 1]
        ml2 = self.mass * self.length**2
        acc = (u[:, 0] - self.damping * om) / ml2 - self.gravity / self.length * torch.sin(th)
        om1 = om + self.dt * acc
        return torch.stack([th + self.dt * om1, om1], 1)

    def grad_input(self, x, u):
        th = x[:, 0]
        ml2 = self.mass * self.length**2
        dt = self.dt
        a_q = -self.gravity / self.length * torch.cos(th)
        a_v = torch.full_like(th, -self.damping / ml2)
        a_u = torch.full_like(th, 1.0 / ml2)
        A = torch.stack([torch.stack([1 + dt * dt * a_q, dt + dt * dt * a_v], 1),
                         torch.stack([dt * a_q, 1 + dt * a_v], 1)], 1)
        B = torch.stack([dt * dt * a_u, dt * a_u], 1).unsqueeze(2)
        return A, B


class CartPoleDx(nn.Module):
    """x = [p, θ, ṗ, θ̇], u = [F]; point-mass pole, θ = 0 down; semi-implicit Euler."""

    def __init__(self, params, dt):
        super().__init__()
        self.mc, self.mp, self.length, self.gravity = (float(v) for v in params)
        self.dt = float(dt)

    def _acc(self, th, om, F):
        s, c = torch.sin(th), torch.cos(th)
        D = self.mc + self.mp * s * s
        pdd = (F + self.mp * s * (self.length * om * om + self.gravity * c)) / D
        thdd = -(F * c + self.mp * self.length * om * om * s * c + (self.mc + self.mp) * self.gravity * s) \
            / (self.length * D)
        return pdd, thdd

    def forward(self, x, u):
        p, th, pd, om = x.unbind(1)
        pdd, thdd = self._acc(th, om, u[:, 0])
        pd1 = pd + self.dt * pdd
        om1 = om + self.dt * thdd
        return torch.stack([p + self.dt * pd1, th + self.dt * om1, pd1, om1], 1)

    def grad_input(self, x, u):
        # Jacobians of the continuous accelerations by hand, then the Euler step's chain rule
        th, om, F = x[:, 1], x[:, 3], u[:, 0]
        mc, mp, L, g, dt = self.mc, self.mp, self.length, self.gravity, self.dt
        s, c = torch.sin(th), torch.cos(th)
        D = mc + mp * s * s
        dD = 2 * mp * s * c
        N1 = F + mp * s * (L * om * om + g * c)
        dN1 = mp * (c * L * om * om + g * (c * c - s * s))
        N2 = -(F * c + mp * L * om * om * s * c + (mc + mp) * g * s)
        dN2 = -(-F * s + mp * L * om * om * (c * c - s * s) + (mc + mp) * g * c)
        pdd_th = (dN1 * D - N1 * dD) / (D * D)
        thdd_th = (dN2 * D - N2 * dD) / (L * D * D)
        pdd_om = 2 * mp * s * L * om / D
        thdd_om = -2 * mp * om * s * c / D
        pdd_u = 1.0 / D
        thdd_u = -c / (L * D)
        z = torch.zeros_like(th)
        one = torch.ones_like(th)
        # semi-implicit Euler: velocity rows [dt a_q, I + dt a_v], position rows [I, 0] + dt · velocity rows
        v_rows = [torch.stack([z, dt * pdd_th, one, dt * pdd_om], 1),
                  torch.stack([z, dt * thdd_th, z, one + dt * thdd_om], 1)]
        q_rows = [torch.stack([one, dt * dt * pdd_th, dt * one, dt * dt * pdd_om], 1),
                  torch.stack([z, one + dt * dt * thdd_th, z, dt * one + dt * dt * thdd_om], 1)]
        A = torch.stack([q_rows[0], q_rows[1], v_rows[0], v_rows[1]], 1)
        B = torch.stack([dt * dt * pdd_u, dt * dt * thdd_u, dt * pdd_u, dt * thdd_u], 1).unsqueeze(2)
        return A, B


def _load(path):
    with np.load(path, allow_pickle=False) as z:
        d = {k: z[k] for k in z.files}
    d["problem"] = str(d["problem"])
    return d


def _model(d):
    cls = PendulumDx if d["problem"] == "pendulum" else CartPoleDx
    return cls(d["params"], d["dt"])


def _median_ms(fn, repeats):
    times, out = [], None
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        out = fn()
        times.append(1e3 * (time.perf_counter() - t0))
    return statistics.median(times), out


def run_mpc_pytorch(d, repeats):
    from mpc import mpc as mpc_mod
    from mpc.mpc import GradMethods, QuadCost

    x0 = torch.as_tensor(d["x0"])
    B, n = x0.shape
    m, T = 1, int(d["T"])
    dt = x0.dtype
    Ta = T + 1
    Qd = torch.as_tensor(d["Qd"], dtype=dt)
    QTd = torch.as_tensor(d["QTd"], dtype=dt)
    R = float(d["R"])
    target = torch.as_tensor(d["target"], dtype=dt)
    C = torch.zeros(Ta, B, n + m, n + m, dtype=dt)
    c = torch.zeros(Ta, B, n + m, dtype=dt)
    for t in range(Ta):
        q = QTd if t == T else Qd
        Ct = 2 * torch.diag(torch.cat([q, torch.tensor([R], dtype=dt)]))
        C[t] = Ct
        c[t] = -(Ct[:, :n] @ target)
    dx = _model(d)
    umax = float(d["umax"])

    def solve():
        ctrl = mpc_mod.MPC(n, m, Ta, u_lower=-umax, u_upper=umax, lqr_iter=int(d["lqr_iter"]),
                           eps=float(d["eps"]), grad_method=GradMethods.ANALYTIC, exit_unconverged=False,
                           detach_unconverged=False, backprop=False, verbose=-1, n_batch=B)
        x, u, cost = ctrl(x0, QuadCost(C, c), dx)
        return x, u

    ms, (x, u) = _median_ms(solve, repeats)
    u = u[:T].permute(1, 0, 2).contiguous()  # (B, T, m), batch first
    x = x[: T + 1].permute(1, 0, 2).contiguous()  # (B, T+1, n): its own rollout x_0 .. x_T
    return {"ok": True, "error": None, "ms": ms, "u": u.tolist(), "x": x.tolist(),
            "note": f"lqr_iter={int(d['lqr_iter'])}, eps={float(d['eps'])}, T_a=T+1, analytic Jacobians"}


def run_pypose(d, repeats):
    import pypose as pp

    x0 = torch.as_tensor(d["x0"])
    B, n = x0.shape
    m, T = 1, int(d["T"])
    dt = x0.dtype
    model = _model(d)

    class System(pp.module.NLS):
        def __init__(self):
            super().__init__()

        def state_transition(self, state, input, t=None):
            shp = state.shape
            return model(state.reshape(-1, n), input.reshape(-1, m)).reshape(shp)

        def observation(self, state, input, t=None):
            return state

    Qd = torch.as_tensor(d["Qd"], dtype=dt)
    R = float(d["R"])
    target = torch.as_tensor(d["target"], dtype=dt)
    Ct = 2 * torch.diag(torch.cat([Qd, torch.tensor([R], dtype=dt)]))
    Q = Ct.expand(B, T, n + m, n + m).clone()
    p = (-(Ct[:, :n] @ target)).expand(B, T, n + m).clone()
    umax = float(d["umax"])
    solver = pp.module.MPC(System(), Q, p, T, stepper=pp.utils.ReduceToBason(steps=int(d["lqr_iter"])))

    def solve():
        x, u, _ = solver(float(d["dt"]), x0, u_lower=-umax * torch.ones(B, T, m, dtype=dt),
                         u_upper=umax * torch.ones(B, T, m, dtype=dt))
        return x, u

    try:
        ms, (x, u) = _median_ms(solve, repeats)
    except Exception as e:  # the anchor's failure is its result
        return {"ok": False, "error": f"{type(e).__name__}: {e}".splitlines()[0][:300], "ms": None, "u": None,
                "note": f"pypose MPC with batch {B}"}
    u = u.reshape(B, T, m)
    viol = float((u.abs() - umax).clamp_min(0).max())
    return {"ok": True, "error": None, "ms": ms, "u": u.tolist(), "x": x.reshape(B, T + 1, n).tolist(),
            "note": f"max bound violation {viol:.3g} (|u| <= {umax:g} requested; pypose ignores the limits)",
            "bound_violation": viol}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("npz")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--skip-pypose", action="store_true")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    d = _load(args.npz)
    out = {}
    d1 = dict(d, x0=d["x0"][:1])  # pypose fails for batch > 1: also run it on the first element alone
    runs = (("mpc_pytorch", run_mpc_pytorch, d), ("pypose", run_pypose, d), ("pypose_b1", run_pypose, d1))
    for name, fn, data in runs:
        if name.startswith("pypose") and args.skip_pypose:
            continue
        if name == "pypose_b1" and (out.get("pypose", {}).get("ok") or len(d["x0"]) == 1):
            continue
        try:
            out[name] = fn(data, args.repeats)
        except Exception as e:  # report, never crash the benchmark
            out[name] = {"ok": False, "error": f"{type(e).__name__}: {e}".splitlines()[0][:300], "ms": None,
                         "u": None, "trace": traceback.format_exc()[-800:]}
    json.dump(out, sys.stdout)
    return 0


if __name__ == "__main__":
    sys.exit(main())
