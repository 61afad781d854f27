"""The seed-004 §9.10-§9.15 examples (examples/cookbook/ilqr_*.py on controllers.task_costs_ext and
controllers.systems.car_velocity): each task's outcome, checked from the numbers the example returns, plus
the figure."""

from examples.cookbook import (
    ilqr_affordance,
    ilqr_car_velocity,
    ilqr_curvature,
    ilqr_decoupling,
    ilqr_spacetime,
)


def test_decoupled_commands_reach_the_targets(run_example):
    v = run_example(ilqr_decoupling)
    assert v["max_target_error"] < 1e-2
    assert v["max_coupling_ratio"] < 1e-2 and v["min_coupling_ratio_without_term"] > 0.5
    assert v["max_coupling_ratio"] < 1e-2 * v["min_coupling_ratio_without_term"]


def test_curvature_tracked_on_circles(run_example):
    v = run_example(ilqr_curvature)
    assert v["max_curvature_error"] <= 1e-4 and v["max_circle_error"] <= 1e-2
    assert v["min_circle_error_without_term"] > 5e-2 and v["min_speed"] >= 0.3


def test_both_cars_park(run_example):
    v = run_example(ilqr_car_velocity)
    for k in ("velocity", "acceleration"):
        assert v[f"{k}_max_position_error"] <= 1e-2 and v[f"{k}_max_heading_error"] <= 1e-2
        assert v[f"{k}_max_steering"] <= 0.61
    assert v["acceleration_max_final_speed"] <= 1e-2
    assert v["velocity_min_speed"] < 0  # the velocity car backs up for some start


def test_same_grasp_offset_at_picking_and_placing(run_example):
    v = run_example(ilqr_affordance)
    assert v["max_offset_mismatch"] <= 1e-2 and v["max_boundary_excess"] <= 1e-2
    assert v["min_grasp_offset"] > 0.1 and v["max_cost_ratio_free_over_predetermined"] < 1


def test_path_and_duration_optimized_together(run_example):
    v = run_example(ilqr_spacetime)
    assert v["max_via_error"] < 1e-2 and v["max_duration_rel_error"] <= 1e-2
    assert abs(v["duration"] - v["reference_duration"]) <= 1e-2 * v["reference_duration"]
    assert v["max_step_spread"] <= 1.01 and v["max_cost_ratio_to_fixed_timing"] < 1
