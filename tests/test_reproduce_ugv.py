"""`liecontrol reproduce ugv` (seed 003 §VII-B) on a short segment of the path: outcome, outputs, bad input.

One quick run (100 steps = 4.8 m at 2.4 m/s, horizon 45, a batched step of 4 vehicles) through the
command's ``add_arguments``/``run``; the full path is measured by hand (see the module docstring)."""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import math

import pytest
import torch

from liecontrol.reproduce import ugv

STEPS = 100


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="liecontrol reproduce ugv")
    ugv.add_arguments(p)
    return p


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("ugv")
    out, js = tmp / "figs", tmp / "ugv.json"
    args = _parser().parse_args(["--quick", "--steps", str(STEPS), "--batch", "4", "--out", str(out),
                                 "--json", str(js)])
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        rc = ugv.run(args)
    return rc, json.loads(js.read_text()), out, buf.getvalue()


def test_quick_run_tracks_the_reference(quick):
    rc, r, _, _ = quick
    assert rc == 0
    assert r["steps"] == STEPS and r["horizon"] == 45 and r["rate_hz"] == 50 and r["speed_mps"] == 2.4
    # from the reference start: the target, and far below it (the model error is the patch fit, cm)
    assert r["pos_err_max_m"] < ugv.TARGET_POS_M
    assert r["pos_err_max_m"] < 0.03 and r["pos_err_xy_max_m"] < 0.01
    assert r["pos_err_rms_m"] <= r["pos_err_max_m"]
    assert r["yaw_err_max_rad"] < math.radians(1.0)
    assert r["not_converged"] == 0 and r["pos_target_met"]
    assert 2.2 < r["v_range_mps"][0] <= r["v_range_mps"][1] < 2.6  # ≈ the reference's 2.4 m/s
    # from 0.3 m and 10° off: the error starts at the offset and converges below the target within 2 s
    o = r["offset"]
    assert 0.29 < o["pos_err_max_m"] < 0.4
    assert o["settle_s"] is not None and o["settle_s"] < ugv.TRANSIENT_S
    assert o["pos_err_max_after_transient_m"] < 0.03
    assert o["not_converged"] == 0
    # timing: recorded, positive; the batched step solved every vehicle
    assert 0 < r["step_ms_median"] <= r["step_ms_p90"] <= r["step_ms_max"]
    assert r["batch"] == 4 and r["step_ms_batch"] > 0 and r["batch_not_converged"] == 0


def test_quick_run_outputs(quick):
    _, r, out, text = quick
    for f in ("path.png", "errors.png", "compute.png"):
        assert (out / f).stat().st_size > 1000, f
    keys = ("pos_err_max_m", "pos_err_rms_m", "pos_err_xy_max_m", "yaw_err_max_rad", "yaw_err_rms_rad",
            "step_ms_median", "step_ms_p90", "step_ms_max", "step_ms_batch", "batch", "horizon", "steps",
            "not_converged")
    for k in keys:
        assert k in r, k
        assert math.isfinite(r[k]), k
    assert {"fit_height_rms_m", "fit_height_max_m", "path_slope_max_deg"} <= set(r["road"])
    assert r["weights"]["Q_diag"] == [100.0, 100.0, 10.0] and r["targets"]["pos_err_max_m"] == 0.1
    md = (out / "report.md").read_text()
    for s in ("## Setup", "## Results", "0.1 m", "20 ms", "What matches", "What does not match"):
        assert s in md, s
    assert "pos max [m]" in text and "targets:" in text and "wrote" in text


@pytest.mark.parametrize("kwargs,match", [
    ({"horizon": 0}, "horizon"),
    ({"horizon": 2.5}, "horizon"),
    ({"steps": 0}, "steps"),
    ({"batch": -1}, "batch"),
    ({"q_pos": -1.0}, "q_pos"),
    ({"r_omega": float("nan")}, "r_omega"),
    ({"dtype": torch.int32}, "dtype"),
    ({"offset_deg": 120.0}, "offset_deg"),
])
def test_bad_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        ugv.run_experiment(**kwargs)


def test_too_many_steps():
    with pytest.raises(ValueError, match="must be at most 1127"):
        ugv.run_experiment(steps=10_000, batch=0, offset_run=False)


@pytest.mark.parametrize("argv", [["--horizon", "0"], ["--steps", "x"], ["--dtype", "float16"],
                                  ["--q-pos", "0"], ["--batch", "-2"]])
def test_bad_command_line(argv, capsys):
    with pytest.raises(SystemExit):
        _parser().parse_args(argv)
    assert "error" in capsys.readouterr().err
