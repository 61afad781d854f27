"""Anchor side of ``liecontrol bench solver``'s pendulum MPC rows: crocoddyl's ``SolverBoxFDDP`` (C++) run as
a receding-horizon MPC on the PendulumSwingUp problem, one thread, warm-started from step to step.

Runs standalone in a subprocess, like ``_crocoddyl_anchor.py`` (the ``bench ilqr`` anchor), whose problem
builder (``build``: pinocchio model, costs, limits) and model check (``model_check``) it re-uses: the problem
file has the same keys (``problem``, ``params``, ``dt``, ``umax``, ``Qd``, ``QTd``, ``R``, ``target``, ``T``
the horizon, ``u_check``/``x_check`` for the check) plus

* ``x_start (n,)``: the initial state of the closed loop, ``steps``: control steps, ``max_iter``: iterations
  at most per solve;
* ``center (n,)``, ``angle_mask (n,)``, ``hysteresis``: how the state planned from takes its angles — the
  rule of ``learning.policies.MPCAdapter``: continue the previous planning state's branch while it stays
  within ``π + hysteresis`` of the center, else the branch within ``±π`` of it.

Each step: the previous plan shifted by one step (last control repeated; zeros at the first step) is rolled
out from the current state and passed as a *feasible* warm start; ``solve`` runs at most ``max_iter``
iterations; the first control drives crocoddyl's own model one step (the plant; the caller's model check
shows it is the caller's step).  The timed part is the rollout of the warm start and the solve.

Usage::

    python liecontrol/bench/_crocoddyl_mpc_anchor.py PROBLEM.npz OUT.npz [--threads 1]

``OUT.npz``: the model check of ``_crocoddyl_anchor.model_check`` and the closed loop: ``x (steps+1, n)``
(simulated states), ``u (steps, m)``, ``ms (steps,)`` (wall time of each step's rollout + solve),
``iters (steps,)``, ``converged (steps,)``.  One JSON object goes to stdout: ``ok``, ``error``, ``missing``
(crocoddyl could not be imported), ``versions``, ``note``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
import traceback

import _crocoddyl_anchor as base  # the file next to this one (its folder is sys.path[0] for a script)
import numpy as np


def branch(prev: np.ndarray | None, x: np.ndarray, center: np.ndarray, mask: np.ndarray,
           hysteresis: float) -> np.ndarray:
    """The state planned from: angle components (``mask``) on the branch of ``prev`` while within
    ``π + hysteresis`` of ``center``, else within ``±π`` of ``center``."""
    two_pi = 2 * math.pi
    centered = np.remainder(x - center + math.pi, two_pi) - math.pi + center
    if prev is not None:
        cont = prev + np.remainder(x - prev + math.pi, two_pi) - math.pi
        centered = np.where(np.abs(cont - center) <= math.pi + hysteresis, cont, centered)
    return np.where(mask, centered, x)


def closed_loop(d: dict, running, terminal, actuated: list[int], threads: int) -> dict:
    import crocoddyl

    T, steps, max_iter = int(d["T"]), int(d["steps"]), int(d["max_iter"])
    center, mask = np.asarray(d["center"], float), np.asarray(d["angle_mask"], bool)
    hyst = float(d["hysteresis"])
    x = np.asarray(d["x_start"], np.float64)
    n, nu = x.shape[0], running.nu
    plan_x = branch(None, x, center, mask, hyst)
    pb = crocoddyl.ShootingProblem(plan_x, [running] * T, terminal)
    if pb.nthreads != threads:
        pb.nthreads = threads
    solver = crocoddyl.SolverBoxFDDP(pb)
    data = running.createData()
    us = [np.zeros(nu) for _ in range(T)]
    out = {"x": np.empty((steps + 1, n)), "u": np.empty((steps, len(actuated))), "ms": np.empty(steps),
           "iters": np.empty(steps, np.int64), "converged": np.empty(steps, bool)}
    out["x"][0] = x
    for k in range(steps):
        t0 = time.perf_counter()
        pb.x0 = plan_x
        converged = solver.solve(pb.rollout(us), us, max_iter, True)
        out["ms"][k] = 1e3 * (time.perf_counter() - t0)
        out["iters"][k], out["converged"][k] = solver.iter, bool(converged)
        plan = [np.array(u) for u in solver.us]
        running.calc(data, x, plan[0])
        x = np.array(data.xnext)
        out["x"][k + 1], out["u"][k] = x, plan[0][actuated]
        us = plan[1:] + [plan[-1]]
        plan_x = branch(plan_x, x, center, mask, hyst)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("npz")
    ap.add_argument("out")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)
    try:
        import crocoddyl
        import pinocchio
    except ImportError as e:
        json.dump({"ok": False, "missing": True, "error": f"{type(e).__name__}: {e}"}, sys.stdout)
        return 0
    info = {"versions": {"crocoddyl": crocoddyl.__version__, "pinocchio": pinocchio.__version__}}
    try:
        d = base._load(args.npz)
        running, terminal, py_cb, actuated = base.build(d)
        arrays = base.model_check(d, running, terminal, actuated)
        arrays.update(closed_loop(d, running, terminal, actuated, args.threads))
        np.savez(args.out, **arrays)
        note = (f"crocoddyl {info['versions']['crocoddyl']} / pinocchio {info['versions']['pinocchio']}, "
                "warm start: the shifted plan rolled out (feasible), "
                + ("damping by a Python actuation model" if py_cb else "all C++"))
        out = {"ok": True, "error": None, "missing": False, "note": note, **info}
    except Exception as e:  # report, never crash the benchmark
        out = {"ok": False, "missing": False, "error": f"{type(e).__name__}: {e}".splitlines()[0][:300],
               "trace": traceback.format_exc()[-800:], **info}
    json.dump(out, sys.stdout)
    return 0


if __name__ == "__main__":
    sys.exit(main())
