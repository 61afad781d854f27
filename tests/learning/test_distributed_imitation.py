"""learn_dynamics under torchrun (learning/imitation.py, issue 26 §6).

The end-to-end test launches ``python -m torch.distributed.run --standalone --nproc_per_node=2`` on
``tests/learning/_ddp_imitation_worker.py`` (gloo, CPU, one thread per process; 5 training demos, so the
ranks hold blocks of 3 and 2) and compares with the same runs done here in one process: the default
L-BFGS-then-Gauss-Newton fit on the pendulum (with two baselines) and the cart-pole, a pendulum fit with
unconverged solves on both ranks, and one with non-finite solves.

Tolerance of the learned parameters: 1e-8 relative.  Why not exact: each rank solves a batch of 3 or 2
demos instead of 5, and the loss is a sum over the ranks, so floating-point sums are taken in another order
(~1e-16 relative per evaluation); L-BFGS's curvature pairs and line search and Levenberg-Marquardt's
accept/reject decisions carry such differences from evaluation to evaluation.  Measured on this machine:
0 (bit-identical) for the four runs here; 5.1e-14 (pendulum, 14 evaluations) and 2.5e-14 (cart-pole, 10)
with more evaluations and other starts (``n_test=3``); 1e-8 leaves room for another machine's BLAS.
What must be exact: the two ranks' parameters and whole records (identical all-reduced values and
gradients, gathered Jacobians, so identical steps), and the per-evaluation counters (unconverged /
excluded / non-finite samples, their indices and reasons, accepted steps).  The loss history is compared
to 1e-8 of the first loss (the last losses of a converged fit, ~1e-15, are round-off themselves).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

import learning.distributed as dh
from controllers.ilqr import ILQROptions, ilqr
from learning import imitation as im
from tests.learning.ddp_launch import load_worker, torchrun

WORKER = Path(__file__).with_name("_ddp_imitation_worker.py")
REL_TOL = 1e-8
D64 = torch.float64
COUNTERS = ("n_unconverged", "n_excluded", "n_nonfinite", "unconverged_samples", "unconverged_reasons",
            "accepted")


def _launch_and_run_reference(out: Path) -> dict:
    """Start the 2-process run, compute the 1-process reference meanwhile (in this process), wait."""
    rc, log, ref = torchrun(WORKER, ["--out", str(out), "--backend", "gloo"],
                            meanwhile=lambda: load_worker(WORKER).run(torch.device("cpu")))
    assert rc == 0, log[-6000:]
    return ref


def _assert_params_close(g: torch.Tensor, r: torch.Tensor) -> None:
    assert torch.equal(g.isnan(), r.isnan())  # an overflowed parameter (None in the record) on both
    ok = ~r.isnan()
    assert torch.allclose(g[ok], r[ok], rtol=REL_TOL, atol=0.0), (g, r)


def test_two_processes_match_one_process(tmp_path):
    ref = _launch_and_run_reference(tmp_path / "ddp.pt")
    got = torch.load(tmp_path / "ddp.pt", weights_only=True)
    assert got["world_size"] == 2 and got["backend"] == "gloo"
    for name in ref:
        assert got["rank_spread"][name] == 0.0 and got["records_equal"][name], name  # ranks identical
        _assert_params_close(got["runs"][name]["params"], ref[name]["params"])
        g, r = json.loads(got["runs"][name]["record"]), json.loads(ref[name]["record"])
        assert g["world_size"] == 2 and "world_size" not in r
        gh, rh = g["history"], r["history"]
        for key in COUNTERS:
            assert gh[key] == rh[key], (name, key)
        assert g["evaluations"] == r["evaluations"] and g["unconverged"] == r["unconverged"]
        np.testing.assert_allclose(gh["loss"], rh["loss"], rtol=REL_TOL, atol=REL_TOL * rh["loss"][0])
        if r["imitation_mse"] is not None:
            assert abs(g["imitation_mse"] - r["imitation_mse"]) <= REL_TOL * r["imitation_mse_init"]
    # the runs are in the regimes they are there for
    pend, unc, bad = (json.loads(ref[k]["record"]) for k in ("pendulum", "unconverged", "nonfinite"))
    assert pend["final_loss"] < 1e-6 * pend["history"]["loss"][0] and pend["evaluations"] > 5  # GN ran
    samples = sum(unc["history"]["unconverged_samples"], [])
    assert min(samples) < 3 <= max(samples)  # unconverged samples on both ranks' blocks (0-2 | 3-4)
    assert 5 in unc["history"]["n_excluded"] and 0 < min(unc["history"]["n_excluded"])
    assert sum(bad["history"]["n_nonfinite"]) > 0
    g = json.loads(got["runs"]["pendulum"]["record"])
    assert g["baselines"]["sysid"]["params"] == pytest.approx(pend["baselines"]["sysid"]["params"],
                                                              rel=REL_TOL, abs=0)
    assert g["baselines"]["mlp"]["imitation_mse"] == pytest.approx(pend["baselines"]["mlp"]["imitation_mse"],
                                                                   rel=REL_TOL, abs=0)


# ------------------------------------------------------------------------- the reduction in a fake world
def _fake_rank(monkeypatch, r: int, other: torch.Tensor) -> None:
    """Pretend to be rank ``r`` of 2; an all-reduce adds ``other`` (the other rank's contribution)."""
    monkeypatch.setattr(dh, "rank", lambda: r)
    monkeypatch.setattr(dh, "world_size", lambda: 2)
    monkeypatch.setattr(dh, "all_reduce_sum", lambda t: t + other)


@pytest.mark.parametrize("case", ["mixed", "all_excluded"])
def test_sharded_loss_and_gradient_equal_one_process(monkeypatch, case):
    setup = im.imitation_setup("pendulum")
    x0 = setup.sample_starts(5, torch.Generator().manual_seed(0))
    ue = ilqr(setup.problem(setup.expert_model(), x0), grad="none", options=im.EXPERT_OPTIONS).u
    opts = ILQROptions(max_iter=3 if case == "mixed" else 1)
    if case == "mixed":  # block 0-2: 0, 1 unconverged (excluded); block 3-4: 3 unconverged, 4 non-finite
        x0[4, 0] = math.nan
        u_init = ue.clone()
        u_init[[1, 3]] = 0.0
    else:  # every solve unconverged (1 iteration from zeros): no usable sample anywhere
        u_init = torch.zeros_like(ue)
    z = torch.tensor([12.0, 1.3, 0.9], dtype=D64).log().requires_grad_()

    def params():
        return dict(zip(setup.param_names, z.exp()))

    one = im.imitation_loss(setup, params(), x0, ue, u_init=u_init, options=opts, unconverged="exclude")
    g_one, = torch.autograd.grad(one.loss, z)
    worst = (2 * setup.u_limit) ** 2
    if case == "mixed":
        assert one.included.tolist() == [False, False, True, False, False]
        assert not one.solution.status.converged[[0, 1, 3]].any()
        expected = (one.per_sample[2] + worst) / 2  # closed form of the global mean
    else:
        assert not one.included.any()
        expected = torch.tensor(worst, dtype=D64)
    blocks = (slice(0, 3), slice(3, 5))
    parts = [im._imitation(setup, params(), x0[b], ue[b], u_init=u_init[b], options=opts,
                           unconverged="exclude") for b in blocks]
    sums = [torch.stack([total.detach(), count, torch.zeros((), dtype=D64)]) for _, total, count in parts]
    losses, grads = [], []
    for r, part in enumerate(parts):
        _fake_rank(monkeypatch, r, sums[1 - r])
        shard = im._Shard(5, "test")
        assert shard.block == blocks[r]
        res = shard.loss(lambda part=part: part, worst, x0)
        assert res.included is part[0].included  # the block's own fields
        loss = res.loss
        losses.append(loss.detach())
        grads.append(torch.autograd.grad(loss, z, allow_unused=True)[0] if loss.requires_grad else None)
    assert torch.equal(losses[0], losses[1])  # the same value on every rank
    assert torch.allclose(losses[0], one.loss.detach(), rtol=1e-14, atol=0)
    assert torch.allclose(losses[0], expected, rtol=1e-14, atol=0)
    g_sum = sum(torch.zeros_like(z) if g is None else g for g in grads)  # what reduce_grad all-reduces
    assert torch.allclose(g_sum, g_one, rtol=1e-12, atol=1e-300)
    assert (case == "mixed") == bool(g_one.abs().max() > 0)  # a real gradient where samples are usable


# ------------------------------------------------------------------------------------ single process
def test_single_process_calls_no_collective_and_loss_is_imitation_loss(monkeypatch):
    def refuse(*a, **k):
        raise AssertionError("a collective was called without a process group")

    for name in ("all_reduce_sum", "gather_along", "gather_objects", "shard"):
        monkeypatch.setattr(dh, name, refuse)
    assert not dh.is_distributed() and dh.world_size() == 1
    rec = im.learn_dynamics("pendulum", 3, 0, steps=4, warmup=2, n_test=1, baselines=())
    assert "world_size" not in rec and rec["evaluations"] == 4
    # the first evaluation is the public imitation_loss on the same training demos, bit for bit
    setup = im.imitation_setup("pendulum")
    gen = torch.Generator().manual_seed(0)
    x_test = setup.sample_starts(1, gen)
    x_train = setup.sample_starts(3, gen)
    ue = ilqr(setup.problem(setup.expert_model(), torch.cat([x_train, x_test])), grad="none",
              options=im.EXPERT_OPTIONS).u[:3]
    z0 = torch.tensor([setup.init_params[k] for k in setup.param_names], dtype=D64).log()
    first = im.imitation_loss(setup, dict(zip(setup.param_names, z0.exp())), x_train, ue, u_init=ue)
    assert rec["history"]["loss"][0] == float(first.loss)


def test_a_failure_on_one_rank_is_raised_on_every_rank(monkeypatch):
    like = torch.zeros((), dtype=D64)
    ok = (None, torch.ones((), dtype=D64), torch.ones((), dtype=D64))

    def boom():
        raise ValueError("boom")

    for r, run, other, match, exc in ((0, boom, 0.0, "boom", ValueError),  # this rank failed: its own error
                                      (1, lambda: ok, 1.0, "rank 0 raised ValueError: boom", dh.RankError)):
        _fake_rank(monkeypatch, r, torch.tensor([0.0, 0.0, other], dtype=D64))
        monkeypatch.setattr(dh, "gather_objects", lambda obj: [("ValueError", "boom"), None])
        with pytest.raises(exc, match=match):
            im._Shard(5, "test").loss(run, 1.0, like)


def test_too_few_demos_for_the_ranks_is_refused_before_any_collective(monkeypatch):
    monkeypatch.setattr(dh, "world_size", lambda: 2)
    monkeypatch.setattr(dh, "all_reduce_sum", lambda t: pytest.fail("collective called"))
    with pytest.raises(ValueError, match="1 training demos cannot be shared by 2 ranks"):
        im.learn_dynamics("pendulum", 1, 0, steps=1, n_test=1, baselines=())
