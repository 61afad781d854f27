"""Cookbook examples of seed 004 §10 (ergodic control): every outcome check holds, the figure is written,
and the key values respect the bounds stated in each example's docstring."""

from __future__ import annotations

from examples.cookbook.ergodic_hedac_2d import run as run_hedac_2d
from examples.cookbook.ergodic_smc_1d import run as run_smc_1d
from examples.cookbook.ergodic_smc_2d import run as run_smc_2d
from examples.cookbook.ergodic_smc_plan_1d import run as run_smc_plan_1d


def _all_checks(res: dict) -> None:
    failed = [k for k, v in res["checks"].items() if v is not True]
    assert not failed, f"failed checks: {failed}; values: {res['values']}"


def test_ergodic_smc_1d(tmp_path):
    res = run_smc_1d(tmp_path)
    _all_checks(res)
    assert (tmp_path / "ergodic_smc_1d.png").is_file()
    v = res["values"]
    assert v["ergodic_metric"] < 1e-3
    assert v["ergodic_metric"] < 0.02 * v["standing_still_metric"]
    assert v["ergodic_metric"] < 0.2 * v["uniform_sweep_metric"]
    assert v["max_time_fraction_error"] < 0.1


def test_ergodic_smc_2d(tmp_path):
    res = run_smc_2d(tmp_path)
    _all_checks(res)
    assert (tmp_path / "ergodic_smc_2d.png").is_file()
    v = res["values"]
    assert v["ergodic_metric"] < 2e-4
    assert v["ergodic_metric"] < 0.02 * v["standing_still_metric"]
    assert v["ergodic_metric"] < 0.1 * v["uniform_sweep_metric"]
    assert v["max_time_fraction_error"] < 0.1


def test_ergodic_hedac_2d(tmp_path):
    res = run_hedac_2d(tmp_path)
    _all_checks(res)
    assert (tmp_path / "ergodic_hedac_2d.png").is_file()
    v = res["values"]
    assert v["residual_final"] < 0.25 * v["residual_first"]
    assert v["ergodic_metric"] < 5e-4
    assert v["ergodic_metric"] < 0.1 * v["standing_still_metric"]
    assert v["ergodic_metric"] < 0.4 * v["uniform_sweep_metric"]
    assert v["max_time_fraction_error"] < 0.15


def test_ergodic_smc_plan_1d(tmp_path):
    res = run_smc_plan_1d(tmp_path)
    _all_checks(res)
    assert (tmp_path / "ergodic_smc_plan_1d.png").is_file()
    v = res["values"]
    assert v["ergodic_metric"] < 2e-5
    assert v["ergodic_metric"] < 0.01 * v["myopic_metric"]
