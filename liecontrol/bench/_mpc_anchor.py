"""mpc.pytorch anchor for ``liecontrol bench lqr`` — a standalone script for the separate environment.

Run as ``python _mpc_anchor.py PROBLEM.npz OUT.npz [--repeats R] [--dtype float32|float64] [--threads N]``
with the interpreter of the environment holding mpc.pytorch (numpy < 2).  It must not import this
project (that environment does not have it).  The problem file (``np.load(..., allow_pickle=False)``)
holds the LQR problem in the τ = [x; u] convention shared by pypose and mpc.pytorch::

    min Σ_{t<T} ½ τ_tᵀ C_t τ_t + p_tᵀ τ_t   s.t.  x_{t+1} = A x_t + B u_t + c,  x_0 = x0

with arrays ``A (Bt, n, n)``, ``B (Bt, n, m)``, ``c (Bt, n)``, ``C (Bt, T, k, k)``, ``p (Bt, T, k)``,
``x0 (Bt, n)``.  It prints one JSON object (``fwd_ms``, ``fwdbwd_ms`` or ``fwdbwd_error``, ``error``)
and writes the controls ``u (Bt, T, m)`` to ``OUT.npz``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
import traceback


def _time(fn, repeats: int, warmup: int = 1) -> float:
    for _ in range(warmup):
        fn()
    samples = []
    for _ in range(max(repeats, 1)):
        t0 = time.perf_counter()
        fn()
        samples.append(1e3 * (time.perf_counter() - t0))
    return statistics.median(samples)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("problem")
    ap.add_argument("out")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    ap.add_argument("--threads", type=int, default=0)
    args = ap.parse_args(argv)
    result: dict = {}
    try:
        import numpy as np
        import torch
        from mpc import mpc as mpc_mod

        if args.threads > 0:
            torch.set_num_threads(args.threads)
        dt = getattr(torch, args.dtype)
        with np.load(args.problem, allow_pickle=False) as z:
            arr = {k: torch.from_numpy(np.array(z[k])).to(dt) for k in ("A", "B", "c", "C", "p", "x0")}
        A, B, c, C, p, x0 = (arr[k] for k in ("A", "B", "c", "C", "p", "x0"))
        Bt, n, m = B.shape
        T = C.shape[1]

        def build(requires_grad: bool):
            leaves = [v.clone().requires_grad_(requires_grad) for v in (A, B, c, C, p, x0)]
            A_, B_, c_, C_, p_, x0_ = leaves
            F = torch.cat([A_, B_], -1).unsqueeze(0).expand(T - 1, Bt, n, n + m)
            f = c_.unsqueeze(0).expand(T - 1, Bt, n)
            cost = mpc_mod.QuadCost(C_.transpose(0, 1), p_.transpose(0, 1))
            return leaves, x0_, cost, mpc_mod.LinDx(F, f)

        def solve(requires_grad: bool):
            leaves, x0_, cost, dx = build(requires_grad)
            ctrl = mpc_mod.MPC(n, m, T, lqr_iter=1, exit_unconverged=False, detach_unconverged=False,
                               backprop=requires_grad, verbose=-1, n_batch=Bt)
            x, u, _ = ctrl(x0_, cost, dx)
            return leaves, x, u

        def fwd():
            with torch.no_grad():
                solve(False)

        result["fwd_ms"] = _time(fwd, args.repeats)
        _, _, u = solve(False)
        np.savez(args.out, u=u.detach().transpose(0, 1).double().numpy())

        def fwdbwd():
            leaves, x, u = solve(True)
            (u.sum() + x.sum()).backward()

        try:
            result["fwdbwd_ms"] = _time(fwdbwd, args.repeats)
        except Exception as e:  # the anchor's own failure is the result
            result["fwdbwd_error"] = f"{type(e).__name__}: {e}".splitlines()[0][:300]
    except Exception as e:
        result["error"] = f"{type(e).__name__}: {e}".splitlines()[0][:300]
        result["traceback"] = traceback.format_exc()[-2000:]
    print(json.dumps(result))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
