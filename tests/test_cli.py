"""The ``liecontrol`` command: help, dispatch, the demo's outcome and the bench's records."""

import json
import subprocess
import sys

import pytest
import torch

from liecontrol import cli
from torchlie import so3


def test_help_lists_every_command(capsys):
    assert cli.main([]) == 0
    out = capsys.readouterr().out
    for word in ("demo", "bench", "reproduce"):
        assert word in out
    with pytest.raises(SystemExit) as e:
        cli.main(["--help"])
    assert e.value.code == 0


def test_unknown_command_is_a_usage_error():
    with pytest.raises(SystemExit) as e:
        cli.main(["frobnicate"])
    assert e.value.code == 2


def test_console_script_entry_point_runs():
    r = subprocess.run([sys.executable, "-m", "liecontrol", "bench", "--help"], capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0 and "lie" in r.stdout


def test_demo_reaches_its_accuracy(tmp_path, capsys, monkeypatch):
    from liecontrol import demo

    monkeypatch.setattr(demo, "return_gap_note", lambda duel, horizon=None: "NOTE: why the returns differ")
    args = ["demo", "--out", str(tmp_path), "--pairs", "64", "--clouds", "8", "--pendulums", "4",
            "--num-envs", "6", "--budget-steps", "64", "--quiet"]
    assert cli.main(args) == 0
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["interpolation"]["twist_constancy_err"] < 1e-10
    assert summary["averaging"]["karcher_err_max"] < 1e-10
    # the naive projected matrix average is biased; the Karcher mean is not
    assert summary["averaging"]["naive_rotation_err_mean"] > 1e3 * summary["averaging"]["karcher_err_max"]
    assert summary["roundtrip_edges"]["float64"] < 1e-12 and summary["roundtrip_edges"]["float32"] < 2e-5
    swing = summary["swingup"]
    assert swing["upright"] == swing["batch"] == 4 and swing["max_abs_u"] <= 3.0 + 1e-9
    assert swing["clamped_fraction"] > 0.1  # the limits are active: the pendulum has to pump
    assert swing["grad_length_median_rel_err"] < 1e-6
    duel = summary["mpc_vs_rl"]
    assert duel["envs"] == 6 and duel["ppo_steps"] >= 64  # SB3 collects whole rollouts
    assert duel["mpc"]["success_rate"] == 1.0 and duel["mpc"]["final_error_median"] < 1e-3  # no training
    assert duel["mpc"]["invalid"] == duel["ppo"]["invalid"] == 0
    # demo.return_gap_note's line (tests/test_plots.py: when and what) is printed right after the table
    lines = capsys.readouterr().out.splitlines()
    ppo_row = next(i for i, line in enumerate(lines) if line.strip().startswith("PPO "))
    assert lines[ppo_row + 1].strip() == "NOTE: why the returns differ"
    for name in ("se3_interpolation.png", "se3_averaging.png", "pendulum_swingup.png", "mpc_vs_ppo.png"):
        assert (tmp_path / name).stat().st_size > 1000


def test_bench_lie_writes_records(tmp_path):
    path = tmp_path / "lie.json"
    assert cli.main(["bench", "lie", "--batches", "8", "--dtypes", "float64", "--ops", "exp", "log",
                     "--repeats", "1", "--no-compile", "--json", str(path)]) == 0
    recs = json.loads(path.read_text())
    keys = {"group", "op", "dtype", "batch", "ours_ms", "anchor", "anchor_ms", "speedup", "roundtrip_err"}
    assert recs and all(keys <= set(r) for r in recs)
    assert {r["group"] for r in recs} == {"so3", "se3"} and {r["op"] for r in recs} == {"exp", "log"}
    for r in recs:
        assert r["roundtrip_err"] < 1e-12
        if r["anchor_status"] == "ok":
            assert r["speedup"] == pytest.approx(r["anchor_ms"] / r["ours_ms"])
        else:  # a missing or inapplicable anchor is reported, not a crash
            assert r["anchor_ms"] is None and r["anchor_status"]


def test_bench_lie_log_rows_compare_like_with_like(tmp_path):
    """log_quat: a quaternion on every side (so3 only); log_mat: a matrix on every side, pypose's time
    including its own matrix -> quaternion conversion; every record says what each side was given."""
    path = tmp_path / "lie.json"
    assert cli.main(["bench", "lie", "--batches", "16", "--dtypes", "float32", "--ops", "log", "log_quat",
                     "log_mat", "--repeats", "1", "--no-compile", "--json", str(path)]) == 0
    recs = json.loads(path.read_text())
    ops = {(r["group"], r["op"]) for r in recs}
    assert ops == {("so3", "log"), ("so3", "log_quat"), ("so3", "log_mat"),
                   ("se3", "log"), ("se3", "log_mat")}  # torchlie has no quaternion form of SE(3)
    for r in recs:
        assert r["ours_input"] == ("quaternion" if r["op"] == "log_quat" else "matrix")
        if r["anchor"] == "pypose" and r["anchor_status"] == "ok":
            assert r["anchor_input"] == ("matrix (conversion timed)" if r["op"] == "log_mat"
                                         else "quaternion LieTensor" if r["group"] == "so3"
                                         else "(t, quaternion) LieTensor")
        if r["anchor"] == "roma" and r["anchor_status"] == "ok":
            assert r["anchor_input"] == ("quaternion" if r["op"] == "log_quat" else "matrix")


def test_bench_lie_exp_rows_compute_the_same_thing(tmp_path):
    """exp_quat / exp_mat: every library's timed call returns the same rotation in the same form
    (quaternions up to sign and component order, matrices entry by entry)."""
    from liecontrol.bench import lie as bl
    from torchlie import quaternion

    gen = torch.Generator().manual_seed(3)
    x = bl._tangents("so3", 64, torch.float64, "cpu", gen)
    X = so3.exp(x)
    ours = bl._Ours("so3").fns(X, X, x, x, X)
    q_ours = ours["exp_quat"][0](*ours["exp_quat"][1])
    R_ours = ours["exp_mat"][0](*ours["exp_mat"][1])
    assert torch.allclose(quaternion.to_matrix(q_ours), X, atol=1e-14) and torch.equal(R_ours, X)
    for cls in (bl._Pypose, bl._Roma):
        lib, why = bl._anchor(cls, "so3")
        if lib is None:
            continue
        f = lib.fns(lib.from_matrix(X), lib.from_matrix(X), x, x, X)
        plain = lambda t: torch.Tensor(t).as_subclass(torch.Tensor)  # noqa: E731 (pypose's LieTensor)
        q = quaternion.from_xyzw(plain(f["exp_quat"][0](*f["exp_quat"][1])))
        q = q * torch.sign((q * q_ours).sum(-1, keepdim=True))
        assert torch.allclose(q, q_ours, atol=1e-12), cls.name
        assert torch.allclose(plain(f["exp_mat"][0](*f["exp_mat"][1])), X, atol=1e-12), cls.name
        assert lib.inputs("exp_mat").endswith("(conversion timed)" if cls is bl._Pypose else "matrix")
