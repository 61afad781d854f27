"""The seed-004 §9 examples (examples/cookbook/ilqr_*.py on controllers.task_costs): each task's outcome,
checked from the trajectories the example returns its numbers for, plus the figure."""

from examples.cookbook import (
    ilqr_bimanual,
    ilqr_bounded,
    ilqr_distance,
    ilqr_init_state,
    ilqr_manipulability,
    ilqr_manipulator_com,
    ilqr_obstacle,
    ilqr_primitives,
)


def test_obstacles_avoided_and_target_reached(run_example):
    v = run_example(ilqr_obstacle)
    assert v["max_final_error"] < 1e-2 and v["max_depth"] <= 0.02
    assert v["straight_line_collisions"] >= v["batch"] // 2  # the obstacles are in the way


def test_centre_of_mass_kept_in_its_box(run_example):
    v = run_example(ilqr_manipulator_com)
    assert v["max_reach_error"] < 2e-2 and v["max_com_excess"] <= 1e-2
    assert v["targets_com_out_without_com_cost"] >= 3


def test_joint_limits_and_object_boundaries(run_example):
    v = run_example(ilqr_bounded)
    assert v["max_outside_object"] <= 1e-3 and v["max_joint_excess"] <= 1e-2
    assert v["certified_at_1e-6"] == 4


def test_distance_to_a_circle_and_an_ellipse_contour(run_example):
    v = run_example(ilqr_distance)
    assert v["max_circle_error"] <= 1e-3 and v["max_ellipse_error"] <= 2e-3
    assert v["max_off_nearest"] <= 0.05


def test_base_placement_by_initial_state_optimization(run_example):
    v = run_example(ilqr_init_state)
    assert v["max_via_error"] < 1e-2 and v["max_base_drift"] < 1e-2
    assert v["min_base_displacement"] > 1.0 and v["min_cost_ratio_fixed_over_free"] > 100


def test_control_primitives_and_coordination(run_example):
    v = run_example(ilqr_primitives)
    assert v["cost_full"] <= v["cost_primitives"] <= 1.1 * v["cost_full"] < v["cost_coordinated"]
    assert v["variables_primitives"] < v["variables_full"] / 5
    assert v["max_via_error"] < 0.05


def test_bimanual_reach_with_the_centre_of_mass_kept(run_example):
    v = run_example(ilqr_bimanual)
    assert v["max_target_error"] < 1e-2 and v["max_com_drift"] <= 1e-2 < v["min_com_drift_without_term"]


def test_manipulability_reached_on_the_spd_manifold(run_example):
    v = run_example(ilqr_manipulability)
    assert v["max_final_distance"] < 1e-2 < v["min_initial_distance"]
