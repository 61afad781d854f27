"""Edge cases of learning/distributed.py and its use in ``fit_cost`` and ``evaluate`` (issue 26 §6).

One launch of ``tests/learning/_ddp_adv_worker.py`` under ``python -m torch.distributed.run --standalone
--nproc_per_node=2`` (gloo, CPU) runs every case on both ranks; each rank's outcome is compared with the
other rank's and with the same case in one process here.  A case that raised on one rank only would leave
the other waiting in a collective: the subprocess timeout turns that into a failure, never a hung test.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

import learning.distributed as dh
from tests.learning.ddp_launch import load_worker, torchrun

WORKER = Path(__file__).with_name("_ddp_adv_worker.py")
REL_TOL = 1e-8  # as tests/learning/test_distributed.py: sums in another order, carried by L-BFGS


@pytest.fixture(scope="module")
def launched(tmp_path_factory):
    out = tmp_path_factory.mktemp("ddp_adv") / "r.pt"
    rc, log, _ = torchrun(WORKER, ["--out", str(out)], timeout=150)
    got = torch.load(out, weights_only=True) if out.exists() else {}
    if rc is None:  # a rank left waiting in a collective
        pytest.fail(f"the 2-process run hung after the cases {sorted(got)}: {log[-2000:]}")
    assert rc == 0, (sorted(got), log[-4000:])
    return got


def _same(a, b, what):
    if isinstance(a, torch.Tensor):
        assert a.shape == b.shape and a.dtype == b.dtype, what
        if a.is_floating_point():
            scale = float(b[torch.isfinite(b)].abs().max()) if bool(torch.isfinite(b).any()) else 1.0
            assert torch.allclose(a, b, rtol=0, atol=REL_TOL * scale, equal_nan=True), what
        else:
            assert torch.equal(a, b), what
    elif isinstance(a, dict):
        assert a.keys() == b.keys(), what
        for k in a:
            _same(a[k], b[k], f"{what}.{k}")
    elif isinstance(a, float):
        assert a == pytest.approx(b, rel=REL_TOL, nan_ok=True), what
    elif isinstance(a, list) and a and isinstance(a[0], float):
        assert a == pytest.approx(b, rel=REL_TOL, nan_ok=True), what
    else:
        assert a == b, what


@pytest.mark.parametrize("case", ["batched_u_lifted", "ilqr_shared_u", "nan_on_rank1", "rank1_all_unusable"])
def test_fit_cost_cases_match_one_process(launched, case):
    r0, r1 = launched[case]
    assert r0["ok"] and r1["ok"], (r0, r1)
    ref = load_worker(WORKER).run_case(case)["value"]
    for k in ("flat", "x", "u", "usable", "reason"):  # both ranks hold the same result, NaN rows included
        a, b = r0["value"][k], r1["value"][k]
        assert a.shape == b.shape and bool(((a == b) | (a != a) & (b != b)).all()), k
    _same(r0["value"], ref, case)
    if case == "batched_u_lifted":
        assert r0["value"]["x"].shape == (2, 3, 21, 4) and r0["value"]["u"].shape == (2, 3, 20, 2)
    if case == "nan_on_rank1":
        assert set(r0["value"]["history"]["unusable"]) == {1} and not bool(r0["value"]["usable"][4])
    if case == "rank1_all_unusable":
        assert set(r0["value"]["history"]["unusable"]) == {1}
        assert r0["value"]["usable"].tolist() == [True, True, False]


@pytest.mark.parametrize("case,kind,text", [
    ("none_usable", "ValueError", "no demo gave a finite solution"),
    ("none_usable_mixed", "ValueError", "the 2 finite solves did not converge")])
def test_no_usable_demo_raised_on_every_rank_with_every_status(launched, case, kind, text):
    outs = launched[case]
    ref = load_worker(WORKER).run_case(case)
    assert not ref["ok"] and ref["type"] == kind
    for o in outs:  # the same error on both ranks, naming the 5 demos' statuses (not the rank's own block)
        assert not o["ok"] and o["type"] == kind and text in o["message"], o
        assert o["message"] == ref["message"]


def test_an_exception_on_one_rank_is_raised_on_every_rank(launched):
    r0, r1 = launched["solver_raises_on_rank1"]
    assert (r1["type"], r1["message"]) == ("FloatingPointError", "injected failure")
    assert r0["type"] == "RankError" and "rank 1 raised FloatingPointError: injected failure" in r0["message"]


@pytest.mark.parametrize("case", ["one_seed", "uneven_rounds"])
def test_evaluate_cases_match_one_process(launched, case):
    r0, r1 = launched[case]
    assert r0 == r1 and r0["ok"], (r0, r1)
    ref = load_worker(WORKER).run_case(case)["value"]
    for k in ("seeds", "returns", "invalid", "length", "errors"):
        assert r0["value"][k] == ref[k], k
    assert r0["value"]["meta"]["world_size"] == 2


def test_evaluate_policy_failing_on_one_rank_and_bad_arguments(launched):
    r0, r1 = launched["policy_raises_on_rank1"]
    assert r0 == r1 and r0["ok"]  # a policy exception is a result (its episodes invalid), on every rank
    v = r0["value"]
    assert v["invalid"] == [False, False, True, True] and v["errors"][2].startswith("RuntimeError")
    for o in launched["bad_steps_one_seed"]:  # 1 seed, 2 ranks: rank 1 has no episode, yet raises too
        assert not o["ok"] and o["type"] == "ValueError" and "max_episode_steps" in o["message"], o


# ------------------------------------------------------------------------------------ no process group
def test_shard_bounds_edges_and_bad_arguments():
    assert [dh.shard_bounds(0, r, 3) for r in range(3)] == [(0, 0)] * 3
    assert [dh.shard_bounds(1, r, 3) for r in range(3)] == [(0, 1), (1, 1), (1, 1)]
    for args, name in (((3, 0.5, 2), "'r'"), ((3, 0, 2.0), "'w'"), ((3, True, 2), "'r'"), ((2.0,), "'n'")):
        with pytest.raises(ValueError, match=name):
            dh.shard_bounds(*args)


@pytest.mark.parametrize("env,match", [
    ({"WORLD_SIZE": "1"}, "RANK, MASTER_ADDR, MASTER_PORT not: launch with torchrun"),
    ({"WORLD_SIZE": "2", "RANK": "0"}, "MASTER_ADDR, MASTER_PORT not"),
    ({"WORLD_SIZE": "x", "RANK": "0", "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": "1"}, "WORLD_SIZE must"),
    ({"WORLD_SIZE": "2", "RANK": "2", "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": "1"}, "RANK 2 is not")])
def test_init_from_env_odd_environments(monkeypatch, env, match):
    for k in ("WORLD_SIZE", "RANK", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT"):
        monkeypatch.delenv(k, raising=False)
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    with pytest.raises(ValueError, match=match):
        dh.init_from_env()
    assert not dh.is_distributed()


def test_init_from_env_bad_device_and_raise_together_alone():
    for device in (3, None, "meta"):
        with pytest.raises(ValueError, match="'device'"):
            dh.init_from_env(None, device)
    dh.raise_together(None, "x")  # nothing failed: nothing raised
    with pytest.raises(KeyError):
        dh.raise_together(KeyError("k"), "x")  # one process: its own error
    with pytest.raises(dh.RankError, match="step: rank 1 raised ValueError: bad"):
        dh.raise_gathered(None, [None, ("ValueError", "bad")], "step")


def test_evaluate_distributed_flag_must_be_a_bool():
    from learning.evaluate import evaluate

    with pytest.raises(TypeError, match="'distributed'"):
        evaluate(lambda o: o[..., :1] * 0, "PendulumSwingUp", episodes=1, distributed="no")
