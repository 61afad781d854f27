"""``liecontrol bench ilqr``: pendulum and cart-pole swing-up, our control-limited iLQR vs mpc.pytorch's
box-DDP MPC, pypose's MPC and crocoddyl's ``SolverBoxFDDP`` (C++), measured in the same run.

Both sides solve the same problem: the dynamics of :mod:`controllers.systems` (re-implemented in plain
torch in the anchor script, which runs in the separate mpc.pytorch environment), the same quadratic cost,
the same control limits and the same initial states (passed through an ``.npz``).  Costs are computed with
*our* cost function: ours on our trajectory, the anchor's on its own trajectory (``anchor_cost``) and, for
reference, its controls replayed open loop through our model (``anchor_cost_replayed``).  Threads are
pinned to the same number on both sides (``--threads``, default 1: on a shared CPU tiny batched kernels
are much faster single-threaded).  The gradient with respect to a dynamics parameter (pendulum and pole
length) is checked against central finite differences and printed.

crocoddyl (``_crocoddyl_anchor.py``, a subprocess of ``--croc-python``, by default this interpreter: the
``bench`` extra installs it) solves the batch one problem at a time in float64 (its Python bindings are
float64 only), so its rows compare against our solver in float64 on the same batch.  Its model is its own
(pinocchio + ``DifferentialActionModelFreeFwdDynamics`` + ``IntegratedActionModelEuler``, the same
semi-implicit Euler step as ours); before any figure is reported the bench feeds it our states and random
controls and compares its one-step map, Jacobians, open-loop rollout and cost with ours
(``model_dx``, ``rollout_dx``, ``jac_err``, ``cost_rel_err``) and refuses the comparison above
``CROC_STEP_TOL`` / ``CROC_ROLLOUT_TOL`` / ``CROC_COST_TOL``.  Pinocchio's ABA has no joint damping, so
the pendulum's damping runs as a Python actuation model (Python callbacks at every node); the pendulum
with ``b = 0`` (``pendulum swing-up (b=0)``, ours on the same problem) is the all-C++ comparison.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

from liecontrol import _options
from liecontrol.report import print_table, restores_threads, time_ms, write_json

__all__ = ["add_arguments", "run", "PROBLEMS"]

PROBLEMS: dict[str, dict] = {
    "pendulum": dict(n=2, dt=0.05, umax=3.0, Qd=[1.0, 0.1], QTd=[100.0, 10.0], R=0.01, target=[math.pi, 0.0],
                     params=[1.0, 1.0, 0.1, 9.81], x0_scale=[0.5, 0.5]),
    "cartpole": dict(n=4, dt=0.05, umax=10.0, Qd=[1.0, 1.0, 0.1, 0.1], QTd=[100.0, 100.0, 10.0, 10.0],
                     R=0.01, target=[0.0, math.pi, 0.0, 0.0], params=[1.0, 0.3, 0.5, 9.81],
                     x0_scale=[0.5, 0.3, 0.3, 0.3]),
}

COLUMNS = ["problem", "B", "T", "n", "m", "dtype", "pass", "ours_ms", "anchor", "anchor_ms", "speedup",
           "max_abs_diff_u", "ours_cost", "anchor_cost", "anchor_cost_replayed", "cost_ratio", "ours_iters",
           "anchor_iters", "converged", "anchor_converged"]
CROC_COLUMNS = ["problem", "B", "T", "dtype", "model_dx", "rollout_dx", "jac_err", "cost_rel_err", "match",
                "anchor_ms_per_problem", "cost_ratio_median", "cost_ratio_min", "cost_ratio_max", "anchor"]
CROC_STEP_TOL = 1e-12  # max |Δx| of one step from the same (x, u), float64
CROC_ROLLOUT_TOL = 1e-9  # max |Δx| of T-step open-loop rollouts of the same controls (chaos amplifies)
CROC_COST_TOL = 1e-12  # relative difference of the cost of the same trajectory
CROC_LABEL = "crocoddyl BoxFDDP (1 at a time)"


add_arguments = _options.bench_ilqr


def _x0(name: str, B: int, seed: int) -> np.ndarray:
    """Initial states near the hanging equilibrium, uniform in ``±x0_scale`` (float32)."""
    rng = np.random.default_rng(seed)
    s = np.asarray(PROBLEMS[name]["x0_scale"])
    return (rng.uniform(-1.0, 1.0, size=(B, len(s))) * s).astype(np.float32)


def _system(name: str, dtype: torch.dtype, length: torch.Tensor | float | None = None,
            params: list[float] | None = None):
    from controllers.systems import CartPole, Pendulum

    p = PROBLEMS[name]["params"] if params is None else params
    dt = PROBLEMS[name]["dt"]
    if name == "pendulum":
        return Pendulum(mass=p[0], length=p[1] if length is None else length, damping=p[2], gravity=p[3],
                        dt=dt)
    return CartPole(cart_mass=p[0], pole_mass=p[1], length=p[2] if length is None else length, gravity=p[3],
                    dt=dt)


def _problem(name: str, x0: torch.Tensor, T: int, length=None, params: list[float] | None = None):
    from controllers.costs import QuadraticCost
    from controllers.ilqr import ILQRProblem

    spec = PROBLEMS[name]
    dt = x0.dtype
    Qd = torch.diag(torch.tensor(spec["Qd"], dtype=dt))
    QT = torch.diag(torch.tensor(spec["QTd"], dtype=dt))
    cost = QuadraticCost(Q=torch.cat([Qd.expand(T, *Qd.shape), QT[None]]),
                         R=torch.tensor([[spec["R"]]], dtype=dt),
                         x_ref=torch.tensor(spec["target"], dtype=dt))
    return ILQRProblem(_system(name, dt, length, params), cost, x0, T, u_lower=-spec["umax"],
                       u_upper=spec["umax"])


def _anchor_python(args) -> Path | None:
    if args.anchor_python:
        p = Path(args.anchor_python)
    else:
        p = Path(__file__).resolve().parents[2] / ".venv-mpc" / "bin" / "python"
    return p if p.exists() else None


def _run_anchor(py: Path, name: str, x0: np.ndarray, T: int, args) -> dict:
    spec = PROBLEMS[name]
    with tempfile.TemporaryDirectory() as tmp:
        f = Path(tmp) / "problem.npz"
        np.savez(f, problem=np.array(name), x0=x0, T=np.array(T), dt=np.array(spec["dt"]),
                 umax=np.array(spec["umax"]), Qd=np.array(spec["Qd"]), QTd=np.array(spec["QTd"]),
                 R=np.array(spec["R"]), target=np.array(spec["target"]), params=np.array(spec["params"]),
                 lqr_iter=np.array(args.max_iter), eps=np.array(1e-4))
        script = Path(__file__).with_name("_mpc_ilqr_anchor.py")
        cmd = [str(py), str(script), str(f), "--threads", str(args.threads), "--repeats",
               str(args.anchor_repeats)]
        try:
            res = subprocess.run(cmd, capture_output=True, text=True, timeout=3600)
        except subprocess.TimeoutExpired:
            return {k: {"ok": False, "error": "timeout"} for k in ("mpc_pytorch", "pypose")}
    if res.returncode != 0 or not res.stdout.strip():
        err = (res.stderr.strip().splitlines() or ["no output"])[-1][:300]
        return {"mpc_pytorch": {"ok": False, "error": err}, "pypose": {"ok": False, "error": err}}
    return json.loads(res.stdout)


def _score(prob, u: torch.Tensor) -> torch.Tensor:
    """Cost ``(B,)`` of open-loop controls rolled out through our model, clipped to the limits."""
    from controllers.dynamics import rollout

    lo, hi = prob.bounds()
    u = torch.minimum(torch.maximum(u, lo), hi)
    x = rollout(prob.dynamics, prob.x0, u)
    return prob.cost.evaluate(x, u)


def _anchor_costs(prob, r: dict, ua: torch.Tensor, B: int, T: int, n: int) -> dict:
    """The anchor's cost with our cost function on its own trajectory (``anchor_cost``), and replayed
    open loop through our model (``anchor_cost_replayed``: a swing-up is chaotic, so float32 round-off
    between two implementations of the same equations can change an open-loop replay a lot)."""
    out = {"anchor_cost_replayed": float(_score(prob, ua).mean())}
    if r.get("x") is not None:
        xa = torch.tensor(r["x"], dtype=torch.float32).reshape(B, T + 1, n)
        lo, hi = prob.bounds()
        out["anchor_cost"] = float(prob.cost.evaluate(xa, torch.minimum(torch.maximum(ua, lo), hi)).mean())
    else:
        out["anchor_cost"] = out["anchor_cost_replayed"]
    return out


def _single_element_record(name: str, prob, x0: torch.Tensor, T: int, opts, args, r: dict) -> dict:
    """pypose's MPC on the first initial state alone (it fails on batches) against ours on the same one."""
    from controllers.ilqr import ilqr

    p1 = _problem(name, x0[:1], T)
    s1 = ilqr(p1, grad="none", options=opts)
    ms = time_ms(lambda: ilqr(p1, grad="none", options=opts), repeats=args.repeats, warmup=1)
    rec = {"problem": f"{name} swing-up", "B": 1, "T": T, "n": p1.n, "m": p1.m, "dtype": "float32",
           "pass": "fwd", "ours_ms": ms, "ours_cost": float(s1.cost[0]),
           "converged": f"{int(s1.status.converged.sum())}/1", "anchor": "pypose MPC (B=1)"}
    if not r.get("ok"):
        return {**rec, "anchor": "pypose MPC (B=1): FAILED", "anchor_error": r.get("error"),
                "anchor_ms": None, "speedup": None, "max_abs_diff_u": None, "anchor_cost": None}
    ua = torch.tensor(r["u"], dtype=torch.float32).reshape(1, T, p1.m)
    xa = torch.tensor(r["x"], dtype=torch.float32).reshape(1, T + 1, p1.n)
    # its own trajectory and its own (limit-violating) controls
    if (r.get("bound_violation") or 0.0) > 1e-6:
        rec["anchor"] = "pypose MPC (B=1, limits violated)"
    return {**rec, "anchor_ms": r["ms"], "speedup": r["ms"] / ms,
            "max_abs_diff_u": float((ua - s1.u).abs().max()),
            "anchor_cost": float(p1.cost.evaluate(xa, ua)[0]), "anchor_note": r.get("note")}


def _iters(it) -> str:
    """``"mean/max"`` of per-problem iteration counts."""
    it = np.asarray(it)
    return f"{it.mean():.1f}/{int(it.max())}"


def _croc_python(args) -> Path:
    return Path(args.croc_python) if args.croc_python else Path(sys.executable)


def _run_croc(py: Path, name: str, x0: torch.Tensor, T: int, params, u_check: torch.Tensor,
              x_check: torch.Tensor, args) -> dict:
    """crocoddyl's model check and one-at-a-time solves in a subprocess: the anchor's JSON with its arrays."""
    spec = PROBLEMS[name]
    with tempfile.TemporaryDirectory() as tmp:
        f, out = Path(tmp) / "problem.npz", Path(tmp) / "out.npz"
        np.savez(f, problem=np.array(name), x0=x0.numpy(), T=np.array(T), dt=np.array(spec["dt"]),
                 umax=np.array(spec["umax"]), Qd=np.array(spec["Qd"]), QTd=np.array(spec["QTd"]),
                 R=np.array(spec["R"]), target=np.array(spec["target"]), params=np.array(params, dtype=float),
                 max_iter=np.array(args.max_iter), u_check=u_check.numpy(), x_check=x_check.numpy())
        script = Path(__file__).with_name("_crocoddyl_anchor.py")
        cmd = [str(py), str(script), str(f), str(out), "--threads", str(args.threads), "--repeats",
               str(args.anchor_repeats)]
        try:
            res = subprocess.run(cmd, capture_output=True, text=True, timeout=3600,
                                 env={**os.environ, "OMP_NUM_THREADS": str(args.threads)})
        except (subprocess.TimeoutExpired, OSError) as e:
            return {"ok": False, "error": f"{type(e).__name__}: {e}"[:300]}
        lines = res.stdout.strip().splitlines()
        if res.returncode != 0 or not lines:
            err = (res.stderr.strip().splitlines() or [f"exit code {res.returncode}, no output"])[-1][:300]
            return {"ok": False, "error": err}
        try:
            r = json.loads(lines[-1])
            if r.get("ok"):
                with np.load(out, allow_pickle=False) as z:
                    r.update({k: z[k] for k in z.files})
        except (ValueError, OSError) as e:
            return {"ok": False, "error": f"unreadable anchor output: {type(e).__name__}: {e}"[:300]}
    return r


def _croc_compare(name: str, label: str, x0_np: np.ndarray, T: int, args, opts, params=None,
                  anchor_params=None) -> dict:
    """crocoddyl's SolverBoxFDDP on each problem of the batch in turn vs ours on the whole batch, float64.

    First the model check: from our rollout of random controls within the limits, crocoddyl's one-step map,
    Jacobians, own rollout and cost against ours.  A mismatch is reported instead of any comparison.
    ``anchor_params`` (default ``params``) are the physical parameters handed to the anchor (tests use it
    to show that the check refuses a different model).
    """
    from controllers.dynamics import rollout
    from controllers.ilqr import ilqr

    spec = PROBLEMS[name]
    params = list(spec["params"] if params is None else params)
    x0 = torch.as_tensor(x0_np).to(torch.float64)  # the float32 initial states, exactly
    prob = _problem(name, x0, T, params=params)
    B, n, m = x0.shape[0], prob.n, prob.m
    none = dict.fromkeys(["ours_ms", "anchor_ms", "speedup", "max_abs_diff_u", "ours_cost", "anchor_cost",
                          "anchor_cost_replayed", "cost_ratio"])
    base = {"problem": label, "B": B, "T": T, "n": n, "m": m, "dtype": "float64", "pass": "fwd", **none}
    py = _croc_python(args)
    if not py.exists():
        return {**base, "anchor": "crocoddyl: missing", "anchor_error": f"{py} not found"}
    gen = torch.Generator().manual_seed(args.seed + 1)
    u_check = (2 * torch.rand(B, T, m, generator=gen, dtype=torch.float64) - 1) * spec["umax"]
    x_check = rollout(prob.dynamics, x0, u_check)
    r = _run_croc(py, name, x0, T, params if anchor_params is None else anchor_params, u_check, x_check, args)
    if r.get("missing"):
        return {**base, "anchor": "crocoddyl: missing (pip install -e '.[bench]')",
                "anchor_error": r.get("error")}
    if not r.get("ok"):
        return {**base, "anchor": "crocoddyl BoxFDDP: FAILED", "anchor_error": r.get("error")}
    A, Bj = prob.dynamics.jacobian(x_check[..., :-1, :], u_check)
    ours_check_cost = prob.cost.evaluate(x_check, u_check).numpy()
    chk = {"model_dx": float(np.abs(r["step_x"] - x_check[..., 1:, :].numpy()).max()),
           "rollout_dx": float(np.abs(r["rollout_x"] - x_check.numpy()).max()),
           "jac_err": float(max(np.abs(r["step_Fx"] - A.numpy()).max(),
                                np.abs(r["step_Fu"] - Bj.numpy()).max())),
           "cost_rel_err": float((np.abs(r["check_cost"] - ours_check_cost) / np.abs(ours_check_cost)).max()),
           "anchor_note": r.get("note"), "anchor_versions": r.get("versions")}
    ok = (chk["model_dx"] <= CROC_STEP_TOL and chk["rollout_dx"] <= CROC_ROLLOUT_TOL  # False on NaN too
          and chk["cost_rel_err"] <= CROC_COST_TOL)
    chk["match"] = "yes" if ok else "NO"
    if not ok:
        return {**base, **chk, "anchor": f"crocoddyl: MODEL MISMATCH (max |dx| {chk['model_dx']:.1e}), "
                                         "not compared"}
    sol = ilqr(prob, grad="none", options=opts)
    ours_ms = time_ms(lambda: ilqr(prob, grad="none", options=opts), repeats=args.repeats, warmup=1)
    xs, us = torch.as_tensor(r["xs"]), torch.as_tensor(r["us"])
    lo, hi = prob.bounds()
    anchor_cost = prob.cost.evaluate(xs, torch.minimum(torch.maximum(us, lo), hi))  # (B,), its own rollout
    ratio = (sol.cost / anchor_cost).numpy()
    total = float(r["ms"].sum())
    return {**base, **chk, "anchor": CROC_LABEL, "ours_ms": ours_ms, "anchor_ms": total,
            "anchor_ms_per_problem": total / B, "speedup": total / ours_ms,
            "max_abs_diff_u": float((us - sol.u).abs().max()),
            "ours_cost": float(sol.cost.mean()), "anchor_cost": float(anchor_cost.mean()),
            "anchor_cost_replayed": float(_score(prob, us).mean()),
            "anchor_cost_own": float(r["cost"].mean()),
            "cost_ratio": float(sol.cost.mean() / anchor_cost.mean()),
            "cost_ratio_median": float(np.median(ratio)),
            "cost_ratio_min": float(ratio.min()), "cost_ratio_max": float(ratio.max()),
            "ours_iters": _iters(sol.status.iterations), "anchor_iters": _iters(r["iters"]),
            "converged": f"{int(sol.status.converged.sum())}/{B}",
            "anchor_converged": f"{int(r['converged'].sum())}/{B}",
            "anchor_feasible": f"{int(r['feasible'].sum())}/{B}",
            "anchor_unactuated_max": float(r["unactuated_max"].max()),
            "ours_cost_per_problem": sol.cost.tolist(), "anchor_cost_per_problem": anchor_cost.tolist(),
            "ours_iters_per_problem": sol.status.iterations.tolist(),
            "anchor_iters_per_problem": r["iters"].tolist(), "anchor_ms_per_problem_list": r["ms"].tolist()}


def _grad_check(name: str, B: int, T: int, seed: int, max_iter: int) -> dict:
    """d(Σ cost)/d(length) by the implicit gradient and by central finite differences (float64)."""
    from controllers.ilqr import ILQROptions, ilqr

    opts = ILQROptions(max_iter=max(max_iter, 200), tol=1e-11, tol_cost=0.0)
    x0 = torch.as_tensor(_x0(name, B, seed), dtype=torch.float64)
    L0 = float(PROBLEMS[name]["params"][1 if name == "pendulum" else 2])
    L = torch.tensor(L0, dtype=torch.float64, requires_grad=True)
    sol = ilqr(_problem(name, x0, T, L), options=opts)
    w = torch.linspace(-1.0, 1.0, T, dtype=torch.float64).view(1, T, 1)
    loss = sol.cost.sum() + (sol.u * w).sum()
    (g,) = torch.autograd.grad(loss, L)
    h = 1e-5 * max(1.0, L0)
    vals = []
    for Lv in (L0 + h, L0 - h):
        s = ilqr(_problem(name, x0, T, torch.tensor(Lv, dtype=torch.float64)), grad="none", options=opts)
        vals.append(float(s.cost.sum() + (s.u * w).sum()))
    fd = (vals[0] - vals[1]) / (2 * h)
    rel = abs(float(g) - fd) / max(1e-12, abs(fd))
    return {"problem": f"{name}: d(loss)/d(length)", "B": B, "T": T, "dtype": "float64",
            "grad_implicit": float(g), "grad_fd": fd, "rel_err": rel,
            "converged": int(sol.status.converged.sum()), "clamped": int(sol.clamped.sum())}


@restores_threads
def run(args) -> int:
    from controllers.ilqr import ILQROptions, ilqr

    torch.set_num_threads(args.threads)
    B, T = args.batch, args.horizon
    py = None if args.no_anchor else _anchor_python(args)
    opts = ILQROptions(max_iter=args.max_iter)
    records: list[dict] = []
    for name in args.problems:
        x0_np = _x0(name, B, args.seed)
        x0 = torch.as_tensor(x0_np)
        prob = _problem(name, x0, T)
        n, m = prob.n, prob.m
        sol = ilqr(prob, grad="none", options=opts)
        ours_ms = time_ms(lambda prob=prob: ilqr(prob, grad="none", options=opts), repeats=args.repeats,
                          warmup=1)
        ours_cost = float(sol.cost.mean())
        base = {"problem": f"{name} swing-up", "B": B, "T": T, "n": n, "m": m, "dtype": "float32",
                "pass": "fwd",
                "ours_ms": ours_ms, "ours_cost": ours_cost, "ours_iters": _iters(sol.status.iterations),
                "converged": f"{int(sol.status.converged.sum())}/{B}"}
        if args.no_anchor:
            records.append({**base, "anchor": "skipped", "anchor_ms": None, "speedup": None,
                            "max_abs_diff_u": None, "anchor_cost": None})
        elif py is None:
            records.append({**base, "anchor": "missing (.venv-mpc)", "anchor_ms": None, "speedup": None,
                            "max_abs_diff_u": None, "anchor_cost": None})
        else:
            out = _run_anchor(py, name, x0_np, T, args)
            for key, label in (("mpc_pytorch", "mpc.pytorch box-DDP"), ("pypose", "pypose MPC")):
                r = out.get(key, {"ok": False, "error": "not run"})
                if not r.get("ok"):
                    records.append({**base, "anchor": f"{label}: FAILED", "anchor_error": r.get("error"),
                                    "anchor_ms": None, "speedup": None, "max_abs_diff_u": None,
                                    "anchor_cost": None})
                    continue
                ua = torch.tensor(r["u"], dtype=torch.float32).reshape(B, T, m)
                rec = {**base, "anchor": label, "anchor_ms": r["ms"], "speedup": r["ms"] / ours_ms,
                       "max_abs_diff_u": float((ua - sol.u).abs().max())}
                rec.update(_anchor_costs(prob, r, ua, B, T, n))
                rec["cost_ratio"] = ours_cost / rec["anchor_cost"]
                if r.get("note"):
                    rec["anchor_note"] = r["note"]
                records.append(rec)
            r1 = out.get("pypose_b1")
            if r1 is not None:
                records.append(_single_element_record(name, prob, x0, T, opts, args, r1))
        if not (args.no_anchor or args.no_croc):
            variants = [(f"{name} swing-up", None)]
            if name == "pendulum":  # damping 0: crocoddyl without Python callbacks, ours on the same problem
                p = PROBLEMS[name]["params"]
                variants.append(("pendulum swing-up (b=0)", [p[0], p[1], 0.0, p[3]]))
            for label, params in variants:
                records.append(_croc_compare(name, label, x0_np, T, args, opts, params))
    # forward + backward (implicit gradient w.r.t. the pendulum length) at the target size
    if "pendulum" in args.problems:
        x0 = torch.as_tensor(_x0("pendulum", B, args.seed))

        def fwd_bwd():
            L = torch.tensor(PROBLEMS["pendulum"]["params"][1], requires_grad=True)
            s = ilqr(_problem("pendulum", x0, T, L), options=opts)
            torch.autograd.grad(s.cost.sum(), L)

        records.append({"problem": "pendulum swing-up, d cost/d length", "B": B, "T": T, "n": 2, "m": 1,
                        "dtype": "float32", "pass": "fwd+bwd",
                        "ours_ms": time_ms(fwd_bwd, repeats=args.repeats, warmup=1), "anchor": "-",
                        "anchor_ms": None, "speedup": None, "max_abs_diff_u": None, "ours_cost": None,
                        "anchor_cost": None})
    print_table(records, COLUMNS)
    croc = [r for r in records if "model_dx" in r]
    if croc:
        print()
        print(f"crocoddyl model check (our rollout of random controls, float64; refused above one-step "
              f"{CROC_STEP_TOL:g} / rollout {CROC_ROLLOUT_TOL:g} / cost {CROC_COST_TOL:g}) and per-problem "
              "figures (cost ratio = ours / crocoddyl, per problem):")
        print_table(croc, CROC_COLUMNS)
    grads = []
    for name in args.problems:
        grads.append(_grad_check(name, args.grad_batch, T, args.seed, args.max_iter))
    print()
    print("gradient w.r.t. a dynamics parameter (pole/pendulum length), implicit vs central finite "
          "differences:")
    print_table(grads, ["problem", "B", "T", "dtype", "grad_implicit", "grad_fd", "rel_err", "converged",
                        "clamped"])
    for r in records:
        if r.get("anchor_note"):
            print(f"note [{r['problem']} / {r['anchor']}]: {r['anchor_note']}")
        if r.get("anchor_error"):
            print(f"error [{r['problem']} / {r['anchor']}]: {r['anchor_error']}")
    if args.json:
        write_json(args.json, records + grads)
    return 0


if __name__ == "__main__":  # pragma: no cover
    ap = argparse.ArgumentParser()
    add_arguments(ap)
    sys.exit(run(ap.parse_args()))
