"""Anchor side of ``liecontrol bench ilqr``: crocoddyl's ``SolverBoxFDDP`` (C++) on the same swing-ups, one
problem at a time.

Runs standalone in a subprocess (a crash of the C++ library cannot take the benchmark down) and imports
nothing from this project.  The models are crocoddyl's own C++ ones on a pinocchio model built by hand:

* pendulum: one revolute joint about x (``JointModelRX``), a point mass ``m`` at ``(0, 0, -l)`` (``θ = 0``
  hanging down), gravity ``(0, 0, -g)`` set explicitly;
* cart-pole: a prismatic joint along y (``JointModelPY``) carrying the cart mass ``m_c``, and a revolute
  joint about x carrying a point mass ``m_p`` at ``(0, 0, -l)``, so that the pole tip is at
  ``(p + l sin θ, -l cos θ)`` as in ``controllers.systems.CartPole``.  crocoddyl has no C++ actuation model
  that drives the first joint alone (``ActuationModelFloatingBase`` leaves the *root* joint unactuated), so
  both joints get ``ActuationModelFull`` and the pole torque is boxed to ``[0, 0]``: BoxFDDP keeps it at
  exactly 0, and the problem is the bench's one;

with ``DifferentialActionModelFreeFwdDynamics`` (pinocchio's ABA) and ``IntegratedActionModelEuler``, whose
step ``v⁺ = v + dt a``, ``q⁺ = q + dt v + dt² a`` is the semi-implicit (symplectic) Euler step of
``controllers.systems._mechanical``.  Pinocchio's ABA ignores ``model.damping``, so the pendulum's viscous
damping ``τ - b ω`` is an actuation model written here in Python (``DampedActuation``): with ``b ≠ 0`` every
node calls back into Python twice per iteration, which slows crocoddyl down; with ``b = 0`` the C++
``ActuationModelFull`` is used and the whole solve runs in C++.

Costs: ``CostModelResidual`` on ``ResidualModelState`` / ``ResidualModelControl`` with
``ActivationModelWeightedQuad`` (``½ Σ wᵢ rᵢ²``).  crocoddyl's Euler integrator multiplies the running cost
by ``dt`` and the terminal node (``dt = 0``) takes the cost as is, so the weights ``2 Qd / dt``,
``2 R / dt`` (running) and ``2 QTd`` (terminal) give exactly the bench's cost::

    Σ_{t<T} (x_t - x*)ᵀ diag(Qd) (x_t - x*) + R u_t²  +  (x_T - x*)ᵀ diag(QTd) (x_T - x*).

Versions: libcrocoddyl 3.2.1 is compiled against pinocchio 4.0.0 but links ``libpinocchio_default.so`` by an
unversioned name and requires ``libpinocchio`` unpinned, so pip pairs it with the newest (4.1.0), whose
``ModelTpl`` has four new members (acceleration and jerk limits) ahead of ``gravity``: crocoddyl's forward
dynamics then run without gravity (torques still act).  The ``bench`` extra pins the pair; the caller's
model check (gravity is in every step) refuses any other mismatch.

Usage::

    python liecontrol/bench/_crocoddyl_anchor.py PROBLEM.npz OUT.npz [--threads 1] [--repeats 1]

``PROBLEM.npz`` (loaded with ``allow_pickle=False``) holds ``problem`` ("pendulum" | "cartpole"),
``x0 (B, n)`` float64, ``T``, ``dt``, ``umax``, ``Qd (n,)``, ``QTd (n,)``, ``R``, ``target (n,)``,
``params`` (system parameters), ``max_iter``, and for the model check ``u_check (B, T, m)`` with the
caller's rollout ``x_check (B, T+1, n)`` of those controls.

``OUT.npz`` receives the model check: ``step_x (B, T, n)`` (crocoddyl's step from each ``x_check[:, t]``
under ``u_check[:, t]``), ``step_Fx (B, T, n, n)``, ``step_Fu (B, T, n, m)`` (its Jacobians there),
``rollout_x (B, T+1, n)`` (crocoddyl's own rollout of ``u_check``), ``check_cost (B,)`` (its cost of
``(x_check, u_check)``); and the solves: ``xs (B, T+1, n)``, ``us (B, T, m)`` (its own trajectory),
``iters (B,)``, ``converged (B,)``, ``feasible (B,)``, ``cost (B,)`` (its own cost), ``ms (B,)`` (wall time of
each problem: shooting problem, solver, initial rollout and solve).  One JSON object goes to stdout:
``ok``, ``error``, ``missing`` (crocoddyl could not be imported), ``versions``, ``python_callbacks``,
``note``.

Both sides start from zero controls (the rollout of ``u = 0``, passed as a feasible guess) and stop at
``max_iter`` iterations; crocoddyl keeps its own stopping test (``th_stop``).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
import traceback

import numpy as np


def _load(path: str) -> dict:
    with np.load(path, allow_pickle=False) as z:
        d = {k: z[k] for k in z.files}
    d["problem"] = str(d["problem"])
    return d


def _damped_actuation_class(crocoddyl):
    class DampedActuation(crocoddyl.ActuationModelAbstract):
        """Fully actuated joints with viscous damping: ``τ = u - b v`` (Python callbacks)."""

        def __init__(self, state, damping: float):
            crocoddyl.ActuationModelAbstract.__init__(self, state, state.nv)
            self.b, self.nq, nv = float(damping), state.nq, state.nv
            self.dtau_dx = np.hstack([np.zeros((nv, state.nq)), -self.b * np.eye(nv)])
            self.eye = np.eye(nv)

        def calc(self, data, x, u):
            data.tau[:] = u - self.b * x[self.nq:]

        def calcDiff(self, data, x, u):  # noqa: N802 (crocoddyl's name)
            data.dtau_dx = self.dtau_dx
            data.dtau_du = self.eye

        def commands(self, data, x, tau):
            data.u[:] = tau + self.b * x[self.nq:]

        def torqueTransform(self, data, x, u):  # noqa: N802
            data.Mtau = self.eye

    return DampedActuation


def _pinocchio_model(pin, d: dict):
    """The pinocchio model of the pendulum or cart-pole (θ = 0 hanging down) and its damping."""
    model = pin.Model()
    zero3 = np.zeros((3, 3))
    if d["problem"] == "pendulum":
        mass, length, damping, g = (float(v) for v in d["params"])
        j = model.addJoint(0, pin.JointModelRX(), pin.SE3.Identity(), "hinge")
        bob = pin.Inertia(mass, np.array([0.0, 0.0, -length]), zero3)
        model.appendBodyToJoint(j, bob, pin.SE3.Identity())
    elif d["problem"] == "cartpole":
        mc, mp, length, g = (float(v) for v in d["params"])
        damping = 0.0
        j = model.addJoint(0, pin.JointModelPY(), pin.SE3.Identity(), "cart")
        model.appendBodyToJoint(j, pin.Inertia(mc, np.zeros(3), zero3), pin.SE3.Identity())
        j = model.addJoint(j, pin.JointModelRX(), pin.SE3.Identity(), "pole")
        model.appendBodyToJoint(j, pin.Inertia(mp, np.array([0.0, 0.0, -length]), zero3), pin.SE3.Identity())
    else:
        raise ValueError(f"unknown problem {d['problem']!r}")
    model.gravity.linear = np.array([0.0, 0.0, -g])
    return model, damping


def build(d: dict):
    """``(running, terminal, python_callbacks, actuated)`` crocoddyl action models of the problem in ``d``;
    ``actuated`` lists the columns of crocoddyl's control that are the bench's control."""
    import crocoddyl
    import pinocchio as pin

    model, damping = _pinocchio_model(pin, d)
    state = crocoddyl.StateMultibody(model)
    if damping != 0.0:
        actuation = _damped_actuation_class(crocoddyl)(state, damping)
    else:
        actuation = crocoddyl.ActuationModelFull(state)
    nu = actuation.nu
    dt = float(d["dt"])
    target = np.asarray(d["target"], dtype=np.float64)

    def state_cost(w):
        return crocoddyl.CostModelResidual(state, crocoddyl.ActivationModelWeightedQuad(np.asarray(w, float)),
                                           crocoddyl.ResidualModelState(state, target, nu))

    running_costs = crocoddyl.CostModelSum(state, nu)
    running_costs.addCost("x", state_cost(2.0 * np.asarray(d["Qd"]) / dt), 1.0)
    running_costs.addCost("u", crocoddyl.CostModelResidual(
        state, crocoddyl.ActivationModelWeightedQuad(np.full(nu, 2.0 * float(d["R"]) / dt)),
        crocoddyl.ResidualModelControl(state, nu)), 1.0)
    terminal_costs = crocoddyl.CostModelSum(state, nu)
    terminal_costs.addCost("x", state_cost(2.0 * np.asarray(d["QTd"])), 1.0)
    dam = crocoddyl.DifferentialActionModelFreeFwdDynamics
    running = crocoddyl.IntegratedActionModelEuler(dam(state, actuation, running_costs), dt)
    terminal = crocoddyl.IntegratedActionModelEuler(dam(state, actuation, terminal_costs), 0.0)
    umax = float(d["umax"])
    actuated = [0]  # pendulum: the hinge torque; cart-pole: the cart force (the pole torque is boxed to 0)
    lb, ub = np.zeros(nu), np.zeros(nu)
    lb[actuated], ub[actuated] = -umax, umax
    running.u_lb, running.u_ub = lb, ub
    return running, terminal, damping != 0.0, actuated


def _full_u(u: np.ndarray, nu: int, actuated: list[int]) -> np.ndarray:
    out = np.zeros((*u.shape[:-1], nu))
    out[..., actuated] = u
    return out


def model_check(d: dict, running, terminal, actuated: list[int]) -> dict:
    """crocoddyl's one-step map, Jacobians, rollout and cost on the caller's states and controls."""
    import crocoddyl

    xc = np.asarray(d["x_check"], np.float64)
    uc = _full_u(np.asarray(d["u_check"], np.float64), running.nu, actuated)
    B, T1, n = xc.shape
    T = T1 - 1
    step_x = np.empty((B, T, n))
    Fx = np.empty((B, T, n, n))
    Fu = np.empty((B, T, n, len(actuated)))
    roll = np.empty((B, T + 1, n))
    cost = np.empty(B)
    data = running.createData()
    for b in range(B):
        for t in range(T):
            running.calc(data, xc[b, t], uc[b, t])
            running.calcDiff(data, xc[b, t], uc[b, t])
            step_x[b, t] = data.xnext
            Fx[b, t] = np.reshape(data.Fx, (n, n))
            Fu[b, t] = np.reshape(data.Fu, (n, running.nu))[:, actuated]
        pb = crocoddyl.ShootingProblem(xc[b, 0], [running] * T, terminal)
        roll[b] = np.asarray(pb.rollout(list(uc[b])))
        cost[b] = pb.calc(list(xc[b]), list(uc[b]))
    return {"step_x": step_x, "step_Fx": Fx, "step_Fu": Fu, "rollout_x": roll, "check_cost": cost}


def solve_all(d: dict, running, terminal, actuated: list[int], threads: int, repeats: int) -> dict:
    """``SolverBoxFDDP`` on each initial state in turn from zero controls, ``max_iter`` iterations at most."""
    import crocoddyl

    x0 = np.asarray(d["x0"], np.float64)
    B, n = x0.shape
    T, nu, m = int(d["T"]), running.nu, len(actuated)
    max_iter = int(d["max_iter"])
    out = {"xs": np.empty((B, T + 1, n)), "us": np.empty((B, T, m)), "iters": np.empty(B, np.int64),
           "converged": np.empty(B, bool), "feasible": np.empty(B, bool), "cost": np.empty(B),
           "ms": np.empty(B), "unactuated_max": np.empty(B)}
    th_stop = None
    for b in range(B):
        times = []
        for _ in range(max(1, repeats)):
            t0 = time.perf_counter()
            pb = crocoddyl.ShootingProblem(x0[b], [running] * T, terminal)
            if pb.nthreads != threads:  # a wheel built without multithreading warns and stays at 1
                pb.nthreads = threads
            solver = crocoddyl.SolverBoxFDDP(pb)
            th_stop = solver.th_stop
            us0 = [np.zeros(nu)] * T
            converged = solver.solve(pb.rollout(us0), us0, max_iter, True)
            times.append(1e3 * (time.perf_counter() - t0))
        out["ms"][b] = statistics.median(times)
        out["xs"][b] = np.asarray(solver.xs)
        us = np.asarray(solver.us).reshape(T, nu)
        out["us"][b] = us[:, actuated]
        out["unactuated_max"][b] = np.abs(np.delete(us, actuated, axis=1)).max(initial=0.0)
        out["iters"][b] = solver.iter
        out["converged"][b] = bool(converged)
        out["feasible"][b] = bool(solver.isFeasible)
        out["cost"][b] = solver.cost
    out["th_stop"] = np.array(np.nan if th_stop is None else th_stop)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("npz")
    ap.add_argument("out")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeats", type=int, default=1)
    args = ap.parse_args(argv)
    try:
        import crocoddyl
        import pinocchio
    except ImportError as e:
        json.dump({"ok": False, "missing": True, "error": f"{type(e).__name__}: {e}"}, sys.stdout)
        return 0
    info = {"versions": {"crocoddyl": crocoddyl.__version__, "pinocchio": pinocchio.__version__}}
    try:
        d = _load(args.npz)
        running, terminal, py_cb, actuated = build(d)
        arrays = model_check(d, running, terminal, actuated)
        arrays.update(solve_all(d, running, terminal, actuated, args.threads, args.repeats))
        np.savez(args.out, **arrays)
        note = (f"crocoddyl {info['versions']['crocoddyl']} / pinocchio {info['versions']['pinocchio']}, "
                f"th_stop={float(arrays['th_stop']):g}, "
                + ("damping by a Python actuation model (2 callbacks per node)" if py_cb else "all C++"))
        out = {"ok": True, "error": None, "missing": False, "python_callbacks": py_cb, "note": note, **info}
    except Exception as e:  # report, never crash the benchmark
        out = {"ok": False, "missing": False, "error": f"{type(e).__name__}: {e}".splitlines()[0][:300],
               "trace": traceback.format_exc()[-800:], **info}
    json.dump(out, sys.stdout)
    return 0


if __name__ == "__main__":
    sys.exit(main())
