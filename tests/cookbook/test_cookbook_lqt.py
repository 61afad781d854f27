"""The seed-004 §7 / Appendix C examples (examples/cookbook/lqt_*.py on controllers.lqt_cookbook): each task's
outcome, checked from the values the example returns, plus the figure."""

from examples.cookbook import lqt_dmp, lqt_multiagent_meeting, lqt_nullspace, lqt_tennis_serve


def test_nullspace_paths_keep_the_via_points(run_example):
    v = run_example(lqt_nullspace)
    assert v["via_point_error"] < 1e-2 and v["max_via_point_change"] < 1e-8
    assert v["null_space_dim"] == 2 * lqt_nullspace.T - 4  # two via points x two positions constrained
    assert v["family_spread"] > 0.1 and v["secondary_cost_nullspace"] < v["secondary_cost_primary"]


def test_dmp_reproduces_and_recovers(run_example):
    v = run_example(lqt_dmp)
    assert v["max_reproduction_error"] < 2e-2
    assert v["final_error_shifted_start"] < 1e-2 and v["final_error_perturbed"] < 1e-2
    assert v["max_deviation_perturbed"] > 0.2


def test_agents_meet_and_reach_targets(run_example):
    v = run_example(lqt_multiagent_meeting)
    assert v["meet_distance_nominal"] < 1e-2 and v["meet_distance_drop_pickup"] < 1e-2
    assert v["meet_distance_pushed"] < 2e-2 and v["max_final_error"] < 1e-2
    assert v["scenarios"] == 4


def test_tennis_ball_hit_and_on_target(run_example):
    v = run_example(lqt_tennis_serve)
    assert v["max_hit_distance"] < 1e-2 and v["max_target_error"] < 1e-2
    assert v["min_release_upward_speed"] > 0.5 and v["min_hit_velocity_change"] > 1.0
    assert v["max_hands_error"] < 1e-2
