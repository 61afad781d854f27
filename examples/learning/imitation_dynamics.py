"""Imitation of unknown dynamics through the differentiable MPC (issue 26 §4; Amos et al. 2018's pendulum;
seed 004 §8: the iLQR planner, differentiated at its solution).

Parameters: a pendulum ``x = [θ, ω]`` whose expert plans with iLQR over ``T = 20`` steps (``dt = 0.05``,
``|τ| ≤ 20``, cost ``(θ − π)² + 0.1 ω² + 10⁻³ τ²`` per step) on the true ``(g, m, l) = (10, 1, 1)``;
``N_TRAIN = 10`` start states near upright and ``N_TEST = 20`` held-out ones (seed 0).

System: the learner plans with the same cost on a pendulum with unknown ``(g, m, l)``, started from
Amos et al.'s ``(15, 3, 0.5)``.

Solve (:func:`learning.imitation.learn_dynamics`): minimize the mean squared difference between the learner's
and the expert's control sequences over ``log (g, m, l)``, Gauss-Newton on the residuals with their Jacobian
by backpropagation through the iLQR solution (implicit gradients).  Only ``g/l`` and ``1/(m l²)`` are
identifiable from the controls (the model's acceleration is ``(u − b ω)/(m l²) − (g/l) sin θ``): the
physical parameters end wherever the path took them along the unidentifiable direction ``(1, −2, 1)`` in
``log (g, m, l)``.

Plot: relative error of the two identifiable combinations and of the three physical parameters against the
loss evaluations (log scale).

Outcome checks: ``identifiable_within_1_percent`` — ``g/l`` and ``1/(m l²)`` within 1 % of the truth;
``imitation_mse_below_initial`` — the held-out imitation MSE of the learned model is below the initial
model's (by a factor 10⁶ at least: ``imitation_mse_reduced_1e6``).
"""

from __future__ import annotations

from pathlib import Path

from learning.imitation import learn_dynamics

SECTION = "8"
TITLE = "Imitation of unknown pendulum dynamics through the differentiable MPC"
N_TRAIN, N_TEST, SEED, STEPS = 10, 20, 0, 30


def run(out: Path | None = None) -> dict:
    """Learn ``(g, m, l)`` from demos; write ``out / "imitation_dynamics.png"`` when ``out`` is given."""
    rec = learn_dynamics("pendulum", N_TRAIN, SEED, steps=STEPS, n_test=N_TEST, baselines=())
    err = rec["param_rel_err"]
    if out is not None:
        _plot(Path(out), rec)
    mse, mse0 = rec["imitation_mse"], rec["imitation_mse_init"]
    return {"checks": {"identifiable_within_1_percent": bool(rec["identifiable_rel_err_max"] < 0.01),
                       "imitation_mse_below_initial": bool(mse < mse0),
                       "imitation_mse_reduced_1e6": bool(mse < 1e-6 * mse0)},
            "values": {"rel_err_g_over_l": float(err["g/l"]), "rel_err_inv_ml2": float(err["1/(m l^2)"]),
                       "rel_err_gravity": float(err["gravity"]), "rel_err_mass": float(err["mass"]),
                       "rel_err_length": float(err["length"]), "imitation_mse": float(rec["imitation_mse"]),
                       "imitation_mse_init": float(rec["imitation_mse_init"]),
                       "evaluations": int(rec["evaluations"]), "n_train": N_TRAIN}}


def _plot(out: Path, rec: dict) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    h = rec["history"]
    p = h["params"]
    truth = rec["params_true"]
    it = range(len(h["loss"]))
    series = {
        "g/l": [abs(g / l_ / (truth["gravity"] / truth["length"]) - 1)
                for g, l_ in zip(p["gravity"], p["length"])],
        "1/(m l²)": [abs(truth["mass"] * truth["length"] ** 2 / (m * l_ * l_) - 1)
                     for m, l_ in zip(p["mass"], p["length"])],
    }
    fig, ax = plt.subplots(figsize=(5, 3.2))
    for k, v in series.items():
        ax.semilogy(it, [max(e, 1e-16) for e in v], lw=2, label=f"{k} (identifiable)")
    for k in ("gravity", "mass", "length"):
        ax.semilogy(it, [max(abs(v / truth[k] - 1), 1e-16) for v in p[k]], ls="--", lw=1, label=k)
    ax.axhline(0.01, color="k", lw=0.8, ls=":")
    ax.set_xlabel("loss evaluation")
    ax.set_ylabel("relative error")
    ax.legend(fontsize=7)
    ax.set_title("pendulum: parameters learned by imitation", fontsize=9)
    fig.tight_layout()
    fig.savefig(out / f"{Path(__file__).stem}.png", dpi=80)
    plt.close(fig)


if __name__ == "__main__":
    import json
    print(json.dumps(run(Path("out/learning")), indent=1))
