"""``liecontrol bench lqr``: batched LQR, ours vs pypose and mpc.pytorch, measured in the same run.

The problem (same numbers for every solver) is written in the τ = [x; u] convention of both anchors::

    min Σ_{t<T} ½ τ_tᵀ C_t τ_t + p_tᵀ τ_t   s.t.  x_{t+1} = A x_t + B u_t + c,  x_0 given

with per-element random ``A, B, c`` (time-invariant, ``A`` scaled to spectral norm ≤ 0.98 so float32 stays
accurate over the horizon), SPD ``C_t`` with cross terms, and ``p_t``.  In this
package's conventions (:mod:`controllers.problem`) that is ``Q_t = ½ C_xx``, ``R_t = ½ C_uu``,
``N_t = ½ C_xu``, ``q_t = ½ p_x``, ``r_t = ½ p_u`` over ``T`` controls and ``T+1`` states with a zero
terminal cost (the anchors' last control sees no further state): the optimal controls coincide.

pypose (``pypose.module.LQR``) runs in this process; mpc.pytorch (``mpc.mpc.MPC`` with one LQR
iteration and no bounds) needs numpy < 2 and runs in ``.venv-mpc`` through ``_mpc_anchor.py`` (the
problem travels as an ``.npz`` file).  A failing anchor is reported with its error string as result.
Each solver is timed as the median of ``--repeats`` runs after warm-up; the in-process solvers (ours,
pypose) are timed interleaved, round after round, so load changes on a shared machine hit all alike.
Problem objects are built once, outside the timed region, for every solver.
Records with ``problem = "lqr"`` time the default eager solver on a problem object built once (as the
anchors' modules are), the forward pass with the cost prepared once (``riccati.prepare``: expansion,
stage matrices and per-element cost checks, as an MPC loop re-solving with the same cost holds them),
the forward+backward pass without (it needs the cost's graph), ``"lqr-cold"`` the
same with fresh problem objects built inside every timed call (construction, per-element validity
checks and the cost expansion included), ``"lqr-fused"`` the warm solver with ``fused=True`` (each
Riccati step's pivot updates as one ``torch.compile``'d kernel; compiled during warm-up).
The ``ours-float64`` rows give our float32 controls' distance to our float64 solution.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

from liecontrol import _options
from liecontrol.report import print_table, restores_threads, write_json

__all__ = ["add_arguments", "run", "make_problem", "run_bench"]

_COLUMNS = ["problem", "B", "T", "n", "m", "dtype", "pass", "ours_ms", "anchor", "anchor_ms", "speedup",
            "max_abs_diff_u"]


add_arguments = _options.bench_lqr


def make_problem(B: int, T: int, n: int, m: int, seed: int = 0) -> dict[str, np.ndarray]:
    """The benchmark problem as float64 numpy arrays (anchor convention, see module docstring)."""
    g = torch.Generator().manual_seed(seed)
    k = n + m
    A = torch.eye(n, dtype=torch.float64)
    A = A + 0.2 * torch.randn(B, n, n, dtype=torch.float64, generator=g) / n ** 0.5
    # contractive (spectral norm ≤ 0.98): a well-conditioned problem, so float32 results are comparable
    A = A * (0.98 / torch.linalg.matrix_norm(A, ord=2).clamp_min(0.98))[:, None, None]
    Bm = 0.3 * torch.randn(B, n, m, dtype=torch.float64, generator=g)
    c = 0.1 * torch.randn(B, n, dtype=torch.float64, generator=g)
    M = torch.randn(B, T, k, k, dtype=torch.float64, generator=g)
    C = M @ M.mT / k + torch.eye(k, dtype=torch.float64)
    p = torch.randn(B, T, k, dtype=torch.float64, generator=g)
    x0 = torch.randn(B, n, dtype=torch.float64, generator=g)
    return {"A": A.numpy(), "B": Bm.numpy(), "c": c.numpy(), "C": C.numpy(), "p": p.numpy(), "x0": x0.numpy()}


# --------------------------------------------------------------------------------------------------
# ours
# --------------------------------------------------------------------------------------------------


def _ours_inputs(prob: dict[str, np.ndarray], dtype: torch.dtype) -> dict[str, torch.Tensor]:
    t = {k: torch.from_numpy(v).to(dtype) for k, v in prob.items()}
    Bsz, n = t["x0"].shape
    C, p = t["C"], t["p"]
    zQ = torch.zeros(Bsz, 1, n, n, dtype=dtype)
    zq = torch.zeros(Bsz, 1, n, dtype=dtype)
    return {
        "A": t["A"].unsqueeze(1), "B": t["B"].unsqueeze(1), "c": t["c"].unsqueeze(1),
        "Q": torch.cat([0.5 * C[..., :n, :n], zQ], 1), "R": (0.5 * C[..., n:, n:]).contiguous(),
        "N": (0.5 * C[..., :n, n:]).contiguous(), "q": torch.cat([0.5 * p[..., :n], zq], 1),
        "r": (0.5 * p[..., n:]).contiguous(), "x0": t["x0"],
    }


def _ours_problem(inp: dict[str, torch.Tensor]):
    from controllers.costs import QuadraticCost
    from controllers.dynamics import LinearDynamics
    from controllers.problem import LQProblem

    return LQProblem(LinearDynamics(inp["A"], inp["B"], inp["c"]),
                     QuadraticCost(inp["Q"], inp["R"], N=inp["N"], q=inp["q"], r=inp["r"]), inp["x0"])


def _bench_ours(prob, dtype, fused=False, cold=False):
    """Our solver's timed callables ``{"fwd": fn, "fwd+bwd": fn}`` and controls (float32 and float64).

    ``cold``: build fresh problem objects inside every timed call (validation, per-element checks and
    the cost expansion are paid each time; nothing cached).
    """
    from controllers import riccati

    inp = _ours_inputs(prob, dtype)
    problem = _ours_problem(inp)
    sol = riccati.solve(problem, grad="none", fused=fused)
    if not sol.status.all_converged:
        raise RuntimeError(f"our solver flagged elements: {set(sol.status.reason_names())}")
    leaves = {k: v.clone().requires_grad_() for k, v in inp.items()}
    problem_g = _ours_problem(leaves)

    def fwdbwd():
        s = riccati.solve(_ours_problem(leaves) if cold else problem_g, fused=fused)
        (s.u.sum() + s.x.sum()).backward()

    if cold:
        fwd = lambda: riccati.solve(_ours_problem(inp), grad="none", fused=fused)
    else:
        prepared = riccati.prepare(problem.cost, problem.T, problem.batch_shape)
        fwd = lambda: riccati.solve(problem, grad="none", fused=fused, prepared=prepared)

    # float64 reference for the accuracy column
    sol64 = riccati.solve(_ours_problem(_ours_inputs(prob, torch.float64)), grad="none")
    return {"fns": {"fwd": fwd, "fwd+bwd": fwdbwd}, "u": sol.u.double(), "u64": sol64.u}


# --------------------------------------------------------------------------------------------------
# anchors
# --------------------------------------------------------------------------------------------------


def _err(e: BaseException) -> str:
    return f"failed: {type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}"[:240]


def _bench_pypose(prob, dtype):
    """pypose's timed callables and controls, or ``{"error": ...}``; a failing pass gets an error entry."""
    try:
        import pypose as pp
    except Exception as e:  # missing anchor
        return {"error": "missing: " + _err(e)}
    t = {k: torch.from_numpy(v).to(dtype) for k, v in prob.items()}
    Bsz, n = t["x0"].shape
    m = t["B"].shape[-1]
    T = t["C"].shape[1]

    def build(requires_grad: bool):
        lv = {k: v.clone().requires_grad_(requires_grad) for k, v in t.items()}
        lti = pp.module.LTI(lv["A"], lv["B"], torch.eye(n, dtype=dtype).expand(Bsz, n, n),
                            torch.zeros(Bsz, n, m, dtype=dtype), lv["c"], torch.zeros(Bsz, n, dtype=dtype))
        return lv, pp.module.LQR(lti, lv["C"], lv["p"], T)

    out: dict = {"fns": {}, "errors": {}}
    try:
        _, lqr = build(False)
        with torch.no_grad():
            x, u, _ = lqr(t["x0"])
        out["u"] = u.detach().double()
        out["fns"]["fwd"] = lambda: torch.no_grad()(lqr)(t["x0"])
    except Exception as e:
        return {"error": _err(e)}
    lv, lqr_g = build(True)

    def fwdbwd():
        x, u, _ = lqr_g(lv["x0"])
        (u.sum() + x.sum()).backward()

    try:
        fwdbwd()
        out["fns"]["fwd+bwd"] = fwdbwd
    except Exception as e:
        out["errors"]["fwd+bwd"] = _err(e)
    return out


def _plain_riccati(inp: dict[str, torch.Tensor]):
    """A plain batched Riccati recursion (textbook form, one ``torch.linalg.solve`` per step): the
    reference point "an unoptimized batched loop" of the issue.  Returns ``(x, u)``."""
    A, B, c, Q, R, N, q, r, x0 = (inp[k] for k in ("A", "B", "c", "Q", "R", "N", "q", "r", "x0"))
    A, B, c = A[:, 0], B[:, 0], c[:, 0]
    T = R.shape[1]
    P, p = Q[:, T], q[:, T]
    Ks, ks = [None] * T, [None] * T
    for t in range(T - 1, -1, -1):
        Pc = (P @ c.unsqueeze(-1)).squeeze(-1) + p
        Qxx = Q[:, t] + A.mT @ P @ A
        Quu = R[:, t] + B.mT @ P @ B
        Qux = N[:, t].mT + B.mT @ P @ A
        qx = q[:, t] + (A.mT @ Pc.unsqueeze(-1)).squeeze(-1)
        qu = r[:, t] + (B.mT @ Pc.unsqueeze(-1)).squeeze(-1)
        sol = -torch.linalg.solve(Quu, torch.cat([Qux, qu.unsqueeze(-1)], -1))
        K, k = sol[..., :-1], sol[..., -1]
        P = Qxx + Qux.mT @ K
        P = 0.5 * (P + P.mT)
        p = qx + (Qux.mT @ k.unsqueeze(-1)).squeeze(-1)
        Ks[t], ks[t] = K, k
    x, xs, us = x0, [x0], []
    for t in range(T):
        u = (Ks[t] @ x.unsqueeze(-1)).squeeze(-1) + ks[t]
        x = (A @ x.unsqueeze(-1) + B @ u.unsqueeze(-1)).squeeze(-1) + c
        xs.append(x)
        us.append(u)
    return torch.stack(xs, 1), torch.stack(us, 1)


def _bench_plain(prob, dtype):
    inp = _ours_inputs(prob, dtype)
    with torch.no_grad():
        _, u = _plain_riccati(inp)
    leaves = {k: v.clone().requires_grad_() for k, v in inp.items()}

    def fwdbwd():
        x, u = _plain_riccati(leaves)
        (u.sum() + x.sum()).backward()

    return {"fns": {"fwd": lambda: torch.no_grad()(_plain_riccati)(inp), "fwd+bwd": fwdbwd},
            "u": u.double(), "errors": {}}


def _time_interleaved(fns: dict[str, object], repeats: int, warmup: int = 2) -> dict[str, float]:
    """Median wall time (ms) of each callable, run in rotating order round after round, so that a change
    of machine load during the run affects every solver alike."""
    import statistics
    import time

    names = list(fns)
    for name in names:
        for _ in range(warmup):
            fns[name]()
    samples: dict[str, list[float]] = {k: [] for k in names}
    for r in range(max(repeats, 1)):
        order = names[r % len(names):] + names[:r % len(names)]
        for name in order:
            t0 = time.perf_counter()
            fns[name]()
            samples[name].append(1e3 * (time.perf_counter() - t0))
    return {k: statistics.median(v) for k, v in samples.items()}


def _default_mpc_python() -> str:
    root = Path(__file__).resolve().parents[2]
    return str(root / ".venv-mpc" / "bin" / "python")


def _bench_mpc(prob, dtype_name, repeats, threads, python):
    py = python or _default_mpc_python()
    if not os.path.exists(py):
        return {"error": f"missing: no interpreter at {py}"}
    script = Path(__file__).with_name("_mpc_anchor.py")
    with tempfile.TemporaryDirectory() as d:
        pin, pout = os.path.join(d, "problem.npz"), os.path.join(d, "u.npz")
        np.savez(pin, **prob)
        cmd = [py, str(script), pin, pout, "--repeats", str(repeats), "--dtype", dtype_name,
               "--threads", str(threads)]
        try:
            res = subprocess.run(cmd, capture_output=True, text=True, timeout=1800)
        except Exception as e:
            return {"error": _err(e)}
        lines = [ln for ln in res.stdout.splitlines() if ln.startswith("{")]
        if not lines:
            tail = (res.stderr or res.stdout).strip().splitlines()[-1:] or ["no output"]
            return {"error": f"failed: exit {res.returncode}: {tail[0][:200]}"}
        info = json.loads(lines[-1])
        if "error" in info:
            return {"error": "failed: " + info["error"]}
        with np.load(pout, allow_pickle=False) as z:
            info["u"] = torch.from_numpy(np.array(z["u"]))
    return info


# --------------------------------------------------------------------------------------------------
# driver
# --------------------------------------------------------------------------------------------------


@restores_threads
def run_bench(B=256, T=50, n=8, m=4, dtype="float32", repeats=7, seed=0, threads=1,
              anchors=("pypose", "mpc", "plain"), mpc_python=None, fused=False) -> list[dict]:
    """Run the benchmark and return the records (see the module docstring).

    With ``fused`` a second set of records (``problem = "lqr-fused"``) times ``riccati.solve(...,
    fused=True)`` (torch.compile'd pivot kernel) against the same anchor timings.
    """
    if threads > 0:
        torch.set_num_threads(threads)
    dt = getattr(torch, dtype)
    prob = make_problem(B, T, n, m, seed)
    variants = {"lqr": _bench_ours(prob, dt), "lqr-cold": _bench_ours(prob, dt, cold=True)}
    if fused:
        try:
            variants["lqr-fused"] = _bench_ours(prob, dt, fused=True)
        except Exception as e:  # torch.compile unavailable: say so, keep the eager figures
            print(f"lqr-fused skipped: {_err(e)}", file=sys.stderr)
    results = {}
    if "pypose" in anchors:
        results["pypose"] = _bench_pypose(prob, dt)
    if "plain" in anchors:
        results["plain-riccati"] = _bench_plain(prob, dt)
    # in-process solvers: timed interleaved, per pass
    for pas in ("fwd", "fwd+bwd"):
        fns = {("ours", k): v["fns"][pas] for k, v in variants.items()}
        fns.update({("anchor", k): v["fns"][pas] for k, v in results.items() if pas in v.get("fns", {})})
        times = _time_interleaved(fns, repeats)
        key = "fwd_ms" if pas == "fwd" else "fwdbwd_ms"
        for (kind, name), ms in times.items():
            (variants if kind == "ours" else results)[name][key] = ms
    for res in results.values():
        for pas, msg in res.get("errors", {}).items():
            res["fwd_error" if pas == "fwd" else "fwdbwd_error"] = msg
    if "mpc" in anchors:
        results["mpc.pytorch"] = _bench_mpc(prob, dtype, repeats, threads, mpc_python)
    records = []
    for problem_name, ours in variants.items():
        base = {"problem": problem_name, "B": B, "T": T, "n": n, "m": m, "dtype": dtype}
        for name, res in results.items():
            for pas, key in (("fwd", "fwd_ms"), ("fwd+bwd", "fwdbwd_ms")):
                rec = dict(base, **{"pass": pas, "ours_ms": ours[key], "anchor": name})
                if "error" in res:
                    rec.update(anchor_ms=res["error"], speedup=None, max_abs_diff_u=None)
                elif key not in res:
                    rec.update(anchor_ms=res.get(key.replace("_ms", "_error"), "failed"), speedup=None,
                               max_abs_diff_u=float((res["u"] - ours["u"]).abs().max()))
                else:
                    rec.update(anchor_ms=res[key], speedup=res[key] / ours[key],
                               max_abs_diff_u=float((res["u"] - ours["u"]).abs().max()))
                records.append(rec)
        # our own float32 error against our float64 solution (context for the anchors' differences)
        records.append(dict(base, **{"pass": "fwd", "ours_ms": ours["fwd_ms"], "anchor": "ours-float64",
                                     "anchor_ms": None, "speedup": None,
                                     "max_abs_diff_u": float((ours["u"] - ours["u64"]).abs().max())}))
    return records


def run(args: argparse.Namespace) -> int:
    anchors = tuple(args.anchors)
    records = run_bench(B=args.batch, T=args.horizon, n=args.state_dim, m=args.control_dim, dtype=args.dtype,
                        repeats=args.repeats,
                        seed=args.seed, threads=args.threads, anchors=anchors, mpc_python=args.mpc_python,
                        fused=not args.no_fused)
    print(f"LQR B={args.batch} T={args.horizon} n={args.state_dim} m={args.control_dim} {args.dtype}, "
          f"torch threads {args.threads}; speedup = anchor_ms / ours_ms (same run)")
    print_table(records, _COLUMNS)
    if args.json:
        write_json(args.json, records)
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    p = argparse.ArgumentParser()
    add_arguments(p)
    sys.exit(run(p.parse_args()))
