"""torchrun / DDP training and sharded evaluation (learning/distributed.py; issue 26 §6).

The end-to-end test launches ``python -m torch.distributed.run --standalone --nproc_per_node=2`` on
``tests/learning/_ddp_worker.py`` (gloo, CPU, one thread per process) and compares with the same work done
here in one process.  Tolerance of the learned parameters: 1e-8 relative.  Why not exact: the two ranks
solve blocks of 3 and 2 demos and the loss and gradient are sums over the ranks, so the floating-point sums
are taken in another order (round-off, ~1e-16 relative per evaluation); L-BFGS's curvature pairs and line
search then carry such differences from iteration to iteration (measured 1.7e-12 after 15 L-BFGS
iterations, 7e-16 after 25 Adam steps), and 1e-8 leaves room for another machine's BLAS.  What must be
exact: the parameters on the two ranks (identical all-reduced values and gradients, so identical steps), the
per-evaluation counters, the per-demo statuses, and the evaluation's per-episode results (each episode runs
on one rank with the same seed, and the policy is per element).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

import learning.distributed as dh
from learning.ioc import fit_cost
from tests.learning.ddp_launch import load_worker, torchrun

WORKER = Path(__file__).with_name("_ddp_worker.py")
REL_TOL = 1e-8


def _launch(out: Path) -> None:
    rc, log, _ = torchrun(WORKER, ["--out", str(out), "--backend", "gloo"])
    assert rc == 0, log[-6000:]


def test_two_processes_match_one_process(tmp_path):
    _launch(tmp_path / "ddp.pt")
    got = torch.load(tmp_path / "ddp.pt", weights_only=True)
    got["eval"]["meta"] = json.loads(got["eval"]["meta"])
    assert got["world_size"] == 2 and got["backend"] == "gloo"
    ref = load_worker(WORKER).run(torch.device("cpu"))
    for k in ("lbfgs", "adam"):
        g, r = got[k], ref[k]
        assert got["rank_spread"][k] == 0.0  # both ranks hold bit-identical parameters
        rel = float((g["flat"] - r["flat"]).norm() / r["flat"].norm())
        assert rel < REL_TOL, (k, rel)
        for name, p in r["params"].items():
            assert torch.allclose(g["params"][name], p, rtol=REL_TOL, atol=0.0), name
        assert r["history"]["loss"][-1] < 0.1 * r["history"]["loss"][0]  # the fit moved: a real comparison
        for key in ("not_converged", "excluded_not_converged", "unusable"):
            assert g["history"][key] == r["history"][key]
        np.testing.assert_allclose(g["history"]["loss"], r["history"]["loss"], rtol=REL_TOL, atol=0)
        assert abs(g["loss"] - r["loss"]) <= REL_TOL * r["loss"]
        # per-demo results gathered in demo order (uneven shards: 3 + 2 demos)
        assert g["x"].shape == r["x"].shape == (5, 21, 4)
        assert torch.allclose(g["x"], r["x"], rtol=0, atol=1e-8 * float(r["x"].abs().max()))
        assert torch.equal(g["usable"], r["usable"]) and torch.equal(g["reason"], r["reason"])
        assert torch.equal(g["iterations"], r["iterations"])
    ge, re = got["eval"], ref["eval"]  # evaluate: 7 seeds, 4 + 3 per rank, identical per episode
    assert ge["meta"]["world_size"] == 2 and "world_size" not in re["meta"]
    for key in ("seeds", "returns", "final_error", "length", "success"):
        assert np.array_equal(ge[key], re[key]), key
    assert np.array_equal(ge["error_curve"], re["error_curve"], equal_nan=True)
    assert ge["meta"]["episodes"] == re["meta"]["episodes"] == 7


# ------------------------------------------------------------------------------------ helpers alone
@pytest.mark.parametrize("w", [1, 2, 3, 5])
def test_shard_bounds_cover_every_item_once(w):
    for n in range(0, 13):
        blocks = [dh.shard_bounds(n, r, w) for r in range(w)]
        ref = np.array_split(np.arange(n), w)  # independent reference: numpy's split
        assert [list(range(a, b)) for a, b in blocks] == [list(x) for x in ref]
        assert sum(b - a for a, b in blocks) == n


def _fake_world(monkeypatch, r, w, blocks):
    """Pretend to be rank ``r`` of ``w``; ``all_gather`` returns the padded ``blocks`` of every rank."""
    monkeypatch.setattr(dh, "rank", lambda: r)
    monkeypatch.setattr(dh, "world_size", lambda: w)
    monkeypatch.setattr(dh, "_all_gather", lambda pad: [b.to(pad.dtype) for b in blocks])


@pytest.mark.parametrize("n,w", [(7, 3), (2, 3), (5, 2), (4, 4)])
def test_gather_along_restores_order_in_a_fake_world(monkeypatch, n, w):
    full = torch.arange(n * 2, dtype=torch.float64).reshape(n, 2) * 1.5
    flags = torch.arange(n) % 3 == 0
    for data in (full, flags):
        m = max(b - a for a, b in (dh.shard_bounds(n, r, w) for r in range(w)))
        blocks = []
        for r in range(w):  # every block padded to m rows with junk that must be trimmed
            a, b = dh.shard_bounds(n, r, w)
            junk = torch.full((m - (b - a), *data.shape[1:]), 7).to(data.dtype)
            blocks.append(torch.cat([data[a:b], junk]))
        for r in range(w):
            _fake_world(monkeypatch, r, w, blocks)
            sl = dh.shard(n)
            assert sl == slice(*dh.shard_bounds(n, r, w))
            out = dh.gather_along(data[sl], n)
            assert out.dtype == data.dtype and torch.equal(out, data)
            with pytest.raises(ValueError, match="rows"):
                dh.gather_along(data[: (sl.stop - sl.start) + 1], n)


def test_no_ops_without_a_process_group(monkeypatch):
    monkeypatch.delenv("WORLD_SIZE", raising=False)
    assert not dh.is_distributed() and dh.rank() == 0 and dh.world_size() == 1 and dh.is_main()
    assert dh.init_from_env() == torch.device("cpu") and not dh.is_distributed()
    t = torch.randn(5, 3, dtype=torch.float64)
    assert dh.shard(5) == slice(0, 5) and dh.all_reduce_sum(t) is t and dh.gather_along(t, 5) is t
    assert dh.gather_objects({"a": 1}) == [{"a": 1}]
    m = nn.Linear(2, 2)
    assert dh.wrap_ddp(m) is m
    dh.shutdown()  # nothing to leave


def test_bad_inputs(monkeypatch):
    with pytest.raises(ValueError, match="backend"):
        dh.init_from_env("mpi")
    with pytest.raises(ValueError, match="nccl"):
        dh.init_from_env("nccl", "cpu")
    with pytest.raises(ValueError, match="device"):
        dh.init_from_env(None, "meta")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="CUDA"):
            dh.init_from_env(None, "cuda")
    with pytest.raises(ValueError, match="'n'"):
        dh.shard_bounds(-1)
    with pytest.raises(ValueError, match="rank 2"):
        dh.shard_bounds(4, 2, 2)
    # fit_cost in a (fake) world of 2 ranks with a single demo: refused before any collective
    w = load_worker(WORKER)
    dyn, xd, init = w.problem(torch.device("cpu"))
    monkeypatch.setattr(dh, "world_size", lambda: 2)
    with pytest.raises(ValueError, match="1 demos cannot be shared by 2 ranks"):
        fit_cost(xd[:1], dyn, init, steps=1)
