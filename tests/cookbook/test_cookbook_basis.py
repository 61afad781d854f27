"""The seed-004 §6 examples (examples/cookbook/basis_*.py, sdf_*.py on controllers.basis and controllers.sdf):
each task's outcome, checked from the values the example returns, plus the figure."""

from examples.cookbook import basis_spline, basis_surface, sdf_closest_points, sdf_fit


def test_bezier_surface_fit(run_example):
    v = run_example(basis_surface)
    assert v["n_weights"] == 100 and v["max_gap_vs_dense_lstsq"] <= 1e-7
    assert max(v["max_error_sin"], v["max_error_gauss"]) <= 3e-3 and v["max_error_poly"] <= 1e-8
    assert v["max_grad_error_poly"] <= 1e-6


def test_concatenated_bezier_spline(run_example):
    v = run_example(basis_spline)
    assert v["n_weights_c1"] == 14 and v["n_weights_c2"] == 9  # 4 + 5 (3 - k) free weights per coordinate
    assert v["joint_gap_c1"] <= 1e-10 and v["joint_gap_c2"] <= 1e-10
    assert v["min_jump_order2_c1"] > 1e-3 and v["min_jump_order3_c2"] > 1e-3
    assert v["rms_error_c1"] < 0.02 and v["rms_error_c2"] < 0.02 and v["c2_vs_bspline"] <= 1e-9


def test_sdf_fit_with_eikonal_cost(run_example):
    v = run_example(sdf_fit)
    assert v["n_shapes"] == 3 and v["max_level_set_distance"] < 0.02
    assert v["eikonal_rms_max"] < 0.13 < v["eikonal_rms_max_without_eikonal"]
    assert v["circle_max_error_in_band"] < 0.05 and v["n_sign_points"] > 1000


def test_sdf_closest_points(run_example):
    v = run_example(sdf_closest_points)
    assert v["n_placements"] == 4 and v["max_abs_f_at_points"] <= 1e-9
    assert v["max_gap_vs_brute_force"] <= 1e-3
    # the penalty formulation (Eq. 40-42) returns shorter segments between points off the contours
    assert v["plain_shorter_everywhere"] == 1 and 0 < v["min_distance"] <= v["max_distance"]
    assert v["plain_max_abs_f1"] > 1e-3
