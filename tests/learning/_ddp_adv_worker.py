"""Worker of tests/learning/test_distributed_adversarial.py: edge cases of ``fit_cost`` and ``evaluate`` under
``python -m torch.distributed.run --standalone --nproc_per_node=2`` (gloo, CPU).

Each case of :data:`CASES` runs on every rank; its outcome (the result's tensors, or the exception's type and
message) is gathered from every rank, and rank 0 writes ``{case: [outcome of rank 0, outcome of rank 1]}`` to
``--out`` (``torch.save``).  :func:`run_case` is also what the test calls in one process for the reference.
A case that raised on one rank only would leave the other rank waiting in a collective: the test's subprocess
timeout is what catches that.
"""

from __future__ import annotations

import argparse
import importlib.util
from pathlib import Path

import torch

from controllers.ilqr import ILQROptions
from learning import distributed as dist_helpers
from learning import ioc
from learning.evaluate import evaluate
from learning.ioc import fit_cost

D64 = torch.float64
solve_demos = ioc._solve_demos
_spec = importlib.util.spec_from_file_location("_ddp_worker_base", Path(__file__).with_name("_ddp_worker.py"))
base = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(base)

#: fit_cost cases: (name, demos transform, keyword arguments); the demos are base.problem's 5 (T = 20)
FIT_CASES = ("batched_u_lifted", "ilqr_shared_u", "nan_on_rank1", "rank1_all_unusable", "none_usable",
             "none_usable_mixed", "solver_raises_on_rank1")
EVAL_CASES = ("one_seed", "uneven_rounds", "policy_raises_on_rank1", "bad_steps_one_seed")
CASES = FIT_CASES + EVAL_CASES


def _fit_inputs(name: str, xd: torch.Tensor) -> tuple[torch.Tensor, dict]:
    g = torch.Generator().manual_seed(5)
    nan = float("nan")
    if name == "batched_u_lifted":  # (2, 3, T+1, n) demos with their controls, the control error weighed
        x = torch.cat([xd, 0.5 * xd[:1]]).reshape(2, 3, *xd.shape[1:])
        u = 0.1 * torch.randn(2, 3, 20, 2, generator=g, dtype=D64)
        return x, dict(u_demo=u, control_weight=0.1, solver="lifted", steps=3)
    if name == "ilqr_shared_u":  # one control sequence (T, m) for every demo: the iLQR's warm start
        return xd, dict(u_demo=torch.zeros(20, 2, dtype=D64), solver="ilqr", steps=2)
    x = xd.clone()
    if name == "nan_on_rank1":  # demo 4 (rank 1's block is demos 3, 4) has a NaN sample
        x[4, 5, 0] = nan
        return x, dict(steps=3)
    if name == "rank1_all_unusable":  # 3 demos: rank 0 holds 0, 1; rank 1 holds demo 2, whose start is NaN
        x = x[:3].clone()
        x[2, 0, 1] = nan
        return x, dict(steps=3)
    if name == "none_usable":
        return torch.full_like(x, nan), dict(steps=2)
    if name == "solver_raises_on_rank1":
        return x, dict(steps=2)
    # none_usable_mixed: rank 0's demos non-finite, rank 1's finite but not converged (1 iLQR iteration)
    x[:3] = nan
    return x, dict(steps=2, solver="ilqr", options=ILQROptions(max_iter=1, tol_kkt=0.0))


def _policy(obs: torch.Tensor) -> torch.Tensor:
    return torch.tanh(-2.0 * obs[..., 1:2] - 0.5 * obs[..., -1:])


def _raises_on_rank1(obs: torch.Tensor) -> torch.Tensor:
    if dist_helpers.rank() == 1:
        raise RuntimeError("policy broke on rank 1")
    return _policy(obs)


def _eval_kwargs(name: str) -> dict:
    kw = dict(task="PendulumSwingUp", max_episode_steps=6, progress=False, timing_batch1=False)
    if name == "one_seed":
        return {**kw, "policy": _policy, "seeds": [3], "num_envs": 4}
    if name == "uneven_rounds":  # 7 seeds, 3 at a time: rank 0 runs 4 (rounds 3 + 1), rank 1 3
        return {**kw, "policy": _policy, "seeds": list(range(20, 27)), "num_envs": 3}
    if name == "policy_raises_on_rank1":
        return {**kw, "policy": _raises_on_rank1, "seeds": list(range(4)), "num_envs": 2}
    return {**kw, "policy": _policy, "seeds": [3], "max_episode_steps": 0}  # bad_steps_one_seed


def _outcome(fn) -> dict:
    try:
        return {"ok": True, "value": fn()}
    except Exception as e:  # the outcome of a case: what it raised, on this rank
        return {"ok": False, "type": type(e).__name__, "message": str(e)}


def run_case(name: str) -> dict:
    """One case on this process (every rank calls it); ``{"ok", "value" | "type", "message"}``."""
    if name in FIT_CASES:
        dyn, xd, init = base.problem(torch.device("cpu"))
        x, kw = _fit_inputs(name, xd)

        def fit():
            if name == "solver_raises_on_rank1":  # fault injection: rank 1's solve raises at the 2nd call
                calls = []

                def solve(*a, **k):
                    calls.append(1)
                    if dist_helpers.rank() == 1 and len(calls) == 2:
                        raise FloatingPointError("injected failure")
                    return solve_demos(*a, **k)
                ioc._solve_demos = solve
            try:
                r = fit_cost(x, dyn, init, **kw)
            finally:
                ioc._solve_demos = solve_demos
            return {"flat": torch.cat([p.detach().reshape(-1) for p in r.model.parameters()]),
                    "history": r.history, "loss": r.loss, "x": r.x, "u": r.u, "usable": r.usable,
                    "reason": r.status.reason}
        return _outcome(fit)

    def ev():
        r = evaluate(**_eval_kwargs(name))
        return {"seeds": r.seeds.tolist(), "returns": r.returns.tolist(), "invalid": r.invalid.tolist(),
                "length": r.length.tolist(), "errors": list(r.errors), "meta": dict(r.meta)}
    return _outcome(ev)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", required=True)
    ap.add_argument("--cases", nargs="+", default=list(CASES))
    a = ap.parse_args()
    torch.set_num_threads(1)
    dist_helpers.init_from_env("gloo", "cpu")
    try:
        out = {}
        for name in a.cases:
            out[name] = dist_helpers.gather_objects(run_case(name))
            if dist_helpers.is_main():  # written after every case: a later hang keeps the earlier ones
                torch.save(out, a.out)
    finally:
        dist_helpers.shutdown()


if __name__ == "__main__":
    main()
