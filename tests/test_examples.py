"""Every example script runs and reaches its outcome (small sizes; the scripts' defaults are larger).
``examples/riemannian_mean.py`` is tested in tests/torchlie/test_manifolds_riemannian.py."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_se3_batched_identities_hold_at_pi():
    from examples.se3_batched import main

    out = main(n_poses=2000)
    assert out["poses"] == 2000
    for key in ("exp_log_roundtrip", "compose_inverse", "act_vs_matrix", "interpolation_ends"):
        assert out[key] < 1e-12, key


def test_lqr_tracking_reaches_the_target_and_both_solvers_agree():
    from examples.lqr_tracking import main

    out = main(batch=8, horizon=30)
    assert out["converged"] == 8 and out["final_distance_max"] < 1e-2
    assert out["riccati_vs_lifted_u"] < 1e-7 and out["riccati_vs_lifted_cost"] < 1e-8


def test_ilqr_swingup_pumps_up_and_its_gradient_matches_finite_differences():
    from examples.ilqr_swingup import main

    out = main(batch=3)
    assert out["upright"] == out["converged"] == 3
    assert out["max_abs_u"] <= 3.0 + 1e-9
    assert out["on_limit_fraction"] > 0.5  # the limit is what it pumps against
    assert out["grad_rel_err_median"] < 1e-6


def test_evaluate_policy_scores_both_policies_on_the_same_episodes():
    from examples.evaluate_policy import main

    out = main(episodes=4)
    assert out["mpc"]["success_rate"] == 1.0
    assert out["energy pumping"]["success_rate"] == 1.0
    assert out["energy pumping"]["return_mean"] < 0 and out["mpc"]["return_mean"] < 0


def test_an_example_runs_as_a_script():
    r = subprocess.run([sys.executable, "examples/se3_batched.py", "--poses", "10"], cwd=ROOT,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "largest error" in r.stdout


def test_mpc_head_on_the_manifold_starts_as_the_expert_and_trains():
    from examples.learning.mpc_head_quadrotor import main

    out = main(steps=128, episodes=2, horizon=6)
    assert all(out["checks"].values()), out
    assert 0 <= out["heavier_vehicle"]["success_rate"] <= 1


def test_gym_pendulum_mpc_brakes_where_the_single_start_swings():
    from examples.learning.gym_pendulum_mpc import main

    out = main(episodes=2, steps=10, horizon=20, hold_steps=8)
    assert all(out["checks"].values()), out


def test_sb3_on_your_own_env_trains_on_the_instance_and_scores_on_copies():
    from examples.learning.sb3_on_your_env import main

    out = main(steps=256, episodes=2)
    assert all(out["checks"].values()), out
    assert out["copies"] == "copy.deepcopy(env)" and out["curve"]["steps"][-1] == 256
