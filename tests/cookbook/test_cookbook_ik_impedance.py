"""The cookbook examples of §5 (IK, task prioritization) and §11 (impedance control, iLQR with torques): every
check holds, the plot is written, and the key values are within their stated bounds."""

from __future__ import annotations

import json


def _common(mod, res: dict, tmp_path) -> None:
    assert res["checks"] and all(res["checks"].values()), res["checks"]
    json.dumps(res)  # plain values
    assert (tmp_path / f"{mod.__name__.rsplit('.', 1)[-1]}.png").is_file()
    assert isinstance(mod.SECTION, str) and isinstance(mod.TITLE, str)


def test_ik_planar(tmp_path):
    from examples.cookbook import ik_planar as mod

    res = mod.run(tmp_path)
    _common(mod, res, tmp_path)
    v = res["values"]
    assert v["max_pos_err_reachable"] < 1e-6 and v["max_rot_err_reachable"] < 1e-6
    assert v["max_gap_unreachable"] < 1e-6


def test_ik_task_priority(tmp_path):
    from examples.cookbook import ik_task_priority as mod

    res = mod.run(tmp_path)
    _common(mod, res, tmp_path)
    v = res["values"]
    assert v["max_primary_residual"] <= 1e-9
    assert v["mean_secondary_distance_with"] < v["mean_secondary_distance_without"]
    assert v["fig12a_joint1_turn"] > 0.5 and v["fig12a_drift"] < 1e-4


def test_impedance_joint(tmp_path):
    from examples.cookbook import impedance_joint as mod

    res = mod.run(tmp_path)
    _common(mod, res, tmp_path)
    v = res["values"]
    assert v["final_error_compensated"] < 1e-6 and v["final_error_uncompensated"] > 0.1
    assert v["spring_gravity_balance"] < 1e-4


def test_impedance_task(tmp_path):
    from examples.cookbook import impedance_task as mod

    res = mod.run(tmp_path)
    _common(mod, res, tmp_path)
    v = res["values"]
    assert v["final_error_compensated"] < 1e-6 and v["final_error_uncompensated"] > 1e-2
    assert v["spring_gravity_balance"] < 1e-4


def test_ilqr_torque_arm(tmp_path):
    from examples.cookbook import ilqr_torque_arm as mod

    res = mod.run(tmp_path)
    _common(mod, res, tmp_path)
    v = res["values"]
    assert v["max_reach_error"] < 1e-2 and v["max_final_speed"] < 0.1
    assert v["final_cost_mean"] < 1e-2 * v["initial_cost_mean"]
    assert 0 < v["max_abs_torque"] < 1e3
