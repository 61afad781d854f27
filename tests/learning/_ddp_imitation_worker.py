"""Worker for tests/learning/test_distributed_imitation.py (issue 26 §6): run under torchrun, e.g.

    python -m torch.distributed.run --standalone --nproc_per_node=2 tests/learning/_ddp_imitation_worker.py \\
        --out r.pt --backend gloo

Runs :func:`learning.imitation.learn_dynamics` on 5 demos (2 ranks: blocks of 3 and 2) in four settings
(:data:`RUNS`): the pendulum and the cart-pole with the default L-BFGS-then-Gauss-Newton fit (the pendulum
with the system-identification and MLP baselines), the pendulum with solves capped at 2 iterations
(unconverged and excluded samples on both ranks, and an evaluation where every sample is excluded) and the
pendulum with a huge Adam step (non-finite solves: the worst-error terms of the loss).  Rank 0 writes to
``--out`` (``torch.save``, only tensors and plain values: ``torch.load(..., weights_only=True)`` reads it)
each run's learned parameters and record (a JSON string), the largest parameter difference between the
ranks and whether every rank's record equals rank 0's.  Without torchrun it runs in one process (the
reference the test compares with, via :func:`run`).
"""

from __future__ import annotations

import argparse
import json

import torch

from controllers.ilqr import ILQROptions
from learning import distributed as dist_helpers
from learning.imitation import learn_dynamics

N_TRAIN = 5
#: name -> (system, learn_dynamics keyword arguments)
RUNS = {
    "pendulum": ("pendulum", dict(steps=10, warmup=5, n_test=1, baselines=("sysid", "mlp"), bc_epochs=5)),
    "cartpole": ("cartpole", dict(steps=6, warmup=3, n_test=1, baselines=())),
    "unconverged": ("pendulum", dict(steps=6, warmup=3, n_test=3, options=ILQROptions(max_iter=2),
                                     warm_start="previous", unconverged="exclude", baselines=())),
    "nonfinite": ("pendulum", dict(steps=4, n_test=3, optimizer="adam", lr=50.0, baselines=())),
}


def run(device: torch.device) -> dict:
    """Every run of :data:`RUNS`: ``{name: {"params": (p,) float64 tensor (NaN for a non-finite value),
    "record": JSON string}}``; every rank returns its own (equal, the test checks)."""
    out = {}
    for name, (system, kw) in RUNS.items():
        rec = learn_dynamics(system, N_TRAIN, 0, device=device, **kw)
        vals = [float("nan") if v is None else v for v in rec["params"].values()]
        out[name] = {"params": torch.tensor(vals, dtype=torch.float64),
                     "record": json.dumps(rec, sort_keys=True, allow_nan=False)}
    return out


def _difference(a: torch.Tensor, b: torch.Tensor) -> float:
    """Largest ``|a − b|``; NaN in both is equal, NaN in one only is ``inf``."""
    d = torch.where(a.isnan() & b.isnan(), 0.0, (a - b).abs())
    return float(torch.nan_to_num(d, nan=torch.inf).max())


def _rank_checks(out: dict) -> tuple[dict, dict]:
    """``(largest |parameter difference| to rank 0, every rank's record == rank 0's)`` per run."""
    spread, equal = {}, {}
    for name, r in out.items():
        parts = dist_helpers.gather_objects((r["params"], r["record"]))
        spread[name] = max(_difference(p, parts[0][0]) for p, _ in parts)
        equal[name] = all(rec == parts[0][1] for _, rec in parts)
    return spread, equal


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", required=True)
    ap.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    ap.add_argument("--backend", default=None, choices=("gloo", "nccl"))
    a = ap.parse_args()
    torch.set_num_threads(1)
    device = dist_helpers.init_from_env(a.backend, a.device)
    try:
        out = run(device)
        spread, equal = _rank_checks(out)
        if dist_helpers.is_main():
            backend = torch.distributed.get_backend() if dist_helpers.is_distributed() else None
            torch.save({"runs": out, "rank_spread": spread, "records_equal": equal, "backend": backend,
                        "world_size": dist_helpers.world_size()}, a.out)
    finally:
        dist_helpers.shutdown()


if __name__ == "__main__":
    main()
