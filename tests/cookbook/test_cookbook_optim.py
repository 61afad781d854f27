"""The seed-004 §3 examples (examples/cookbook/optim_*.py on controllers.optim): each task's outcome, checked
from the values the example returns, plus the figure."""

from examples.cookbook import optim_gauss_newton, optim_least_squares, optim_newton


def test_gradient_descent_and_newton_reach_the_grid_minimum(run_example):
    v = run_example(optim_newton)
    for dim in ("1d", "2d"):
        assert v[f"gd_error_{dim}"] <= 1e-4 and v[f"newton_error_{dim}"] <= 1e-4
        assert v[f"newton_iterations_max_{dim}"] * 5 < v[f"gd_iterations_min_{dim}"]
        assert v[f"newton_iterations_max_{dim}"] >= 2  # not quadratic: Newton needs more than one step


def test_gauss_newton_ik_reaches_every_target(run_example):
    v = run_example(optim_gauss_newton)
    assert v["batch"] == 24 and v["max_residual"] < 1e-10
    assert v["max_closed_form_gap"] <= 1e-8 and v["analytic_vs_autodiff"] <= 1e-9
    assert 0 < v["elbow_up_count"] <= 24


def test_ridge_weighted_constrained_least_squares(run_example):
    v = run_example(optim_least_squares)
    assert v["constraint_violation"] <= 1e-10
    for k in ("ridge", "weighted", "constrained"):
        assert v[f"{k}_cost_rel_error"] <= 1e-10
    # down-weighting the outliers keeps the fit near the noise-free curve; the ridge fit is pulled away
    assert v["max_inlier_error_weighted"] < 0.15 < v["max_inlier_error_ridge"]
