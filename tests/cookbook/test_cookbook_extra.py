"""The seed-004 §8.3 and §12.6 examples (examples/cookbook/ilqr_ls_gains.py on
controllers.ilqr_lifted.lifted_feedback_gains, examples/cookbook/manifold_geodesic.py on
torchlie.manifolds.metric): each task's outcome, checked from the numbers the example returns, plus the
figure."""

from examples.cookbook import ilqr_ls_gains, manifold_geodesic


def test_ls_gains_track_perturbed_starts(run_example):
    v = run_example(ilqr_ls_gains)
    assert v["gain_rel_error_vs_riccati"] < 1e-6
    assert v["max_final_error_closed_loop"] < 1e-2
    assert v["max_final_error_closed_loop"] < 0.1 * v["min_final_error_open_loop"]
    assert v["max_first_error_closed_loop"] < 0.1 * v["min_first_error_open_loop"]
    assert v["plan_first_via_error"] < 1e-2 and v["plan_final_via_error"] < 1e-2


def test_kinetic_energy_geodesic_beats_linear_interpolation(run_example):
    v = run_example(manifold_geodesic)
    assert v["max_energy_ratio_geodesic_over_linear"] <= 0.9
    assert v["min_energy_ratio_geodesic_over_linear"] < 0.8 and v["min_energy_drop"] > 0.1
    assert v["half_plane_max_circle_error"] < 1e-4
    assert v["half_plane_max_length_rel_error"] < 1e-4
