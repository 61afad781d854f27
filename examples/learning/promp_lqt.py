"""ProMP-like trajectory distribution as LQT with control primitives (issue 26 §3; seed 004 §7.3, Eq. 61-66).

Parameters: the handwriting-like letters ``S C U N`` (:func:`learning.demos.handwriting`), ``N_DEMOS = 8``
demos of ``T = 100`` samples over one second each, time-warped and spatially varied.

System: per letter a double integrator in the plane, ``x = [p; ṗ]``, ``u = p̈`` (Eq. 60, Eq. 192), and the
controls as control primitives ``u = Ψ w`` with ``K = 15`` normalized radial basis functions per
dimension (Eq. 66).  The whole trajectory is linear in ``z = [x_1; w]``: ``x = S_x x_1 + S_u Ψ w``
(Eq. 61).

Fit (:func:`learning.primitives.fit_promp`, the four letters in one batch): each demo's ``x_1`` from its
first samples and ``w`` by ridge least squares of its positions; the Gaussian ``N(μ_z, Σ_z)`` of the demos'
``z`` maps linearly to a state distribution ``N(S μ_z, S Σ_z Sᵀ)`` (seed §7.3: "a covariance matrix on w can
be converted to a covariance on u and on x ... as in ProMP").

Conditioning: each letter's distribution is conditioned (Gaussian conditioning in ``z``-space) on a via
point at ``t = 60``: the unconditioned mean there moved by ``(0.06, -0.06)`` (noise ``10⁻¹⁰``), and five
conditioned trajectories are sampled.

Plot: top row, per letter the demos (grey), the mean (black), the via point (red) and the conditioned
samples (colour); bottom row, each coordinate's mean ± 2σ band over time with the demos.

Outcome checks: ``conditioned_mean_through_via_point`` — the conditioned mean passes within ``10⁻⁶`` of
every via point; ``conditioned_samples_near_via_point`` — every conditioned sample within ``10⁻³`` of it;
``mean_reproduces_demo_mean`` — the unconditioned mean stays within ``10⁻²`` of the demos' mean at every
step (the basis functions' resolution); ``via_point_outside_unconditioned_mean`` — the via point is a real
change (the unconditioned mean misses it by more than ``0.05``); ``demos_inside_2sigma`` — at least 90 % of
the demos' samples lie inside the per-coordinate ±2σ band.
"""

from __future__ import annotations

from pathlib import Path

import torch

from learning.demos import handwriting
from learning.primitives import fit_promp, reproduction_error, via_point_error

SECTION = "7.3"
TITLE = "ProMP-like distribution as LQT with control primitives (handwriting letters)"

LETTERS = "SCUN"
N_DEMOS = 8
T = 100
K = 15
T_VIA = 60
OFFSET = (0.06, -0.06)
N_SAMPLES = 5


def run(out: Path | None = None) -> dict:
    """Fit, condition, sample; write ``out / "promp_lqt.png"`` when ``out`` is given; return the outcomes."""
    g = torch.Generator().manual_seed(11)
    demos = handwriting(LETTERS, N_DEMOS, T, generator=g)
    x = torch.stack([demos[c].x for c in LETTERS])  # (4, N, T, 2): four sets of demos, one batch
    pm = fit_promp(x, dt=demos[LETTERS[0]].dt, n_basis=K)
    mean = pm.state_mean()  # (4, T, 4)
    std = pm.state_marginal_cov().diagonal(dim1=-2, dim2=-1).sqrt()  # (4, T, 4)
    demo_mean = x.mean(1)
    mean_err = (mean[..., :2] - demo_mean).norm(dim=-1).amax()
    via = mean[:, T_VIA:T_VIA + 1, :2] + torch.tensor(OFFSET, dtype=x.dtype)  # (4, 1, 2)
    cond = pm.condition([T_VIA], via, noise=1e-10)
    samples = cond.sample(N_SAMPLES, g)  # (S, 4, T, 4)
    err_mean = via_point_error(cond.state_mean(), [T_VIA], via).amax()
    err_samples = via_point_error(samples, [T_VIA], via).amax()
    offset_unc = via_point_error(mean, [T_VIA], via).amin()
    inside = ((x - mean[:, None, :, :2]).abs() <= 2 * std[:, None, :, :2] + 1e-12).double().mean()
    rep = reproduction_error(x, pm.reproductions()).amax()
    if out is not None:
        _plot(Path(out), x, mean, std, via, samples, cond.state_mean())
    return {"checks": {"conditioned_mean_through_via_point": bool(err_mean < 1e-6),
                       "conditioned_samples_near_via_point": bool(err_samples < 1e-3),
                       "mean_reproduces_demo_mean": bool(mean_err < 1e-2),
                       "via_point_outside_unconditioned_mean": bool(offset_unc > 0.05),
                       "demos_inside_2sigma": bool(inside >= 0.9)},
            "values": {"via_point_error_mean": float(err_mean), "via_point_error_samples": float(err_samples),
                       "mean_vs_demo_mean_max": float(mean_err), "via_point_offset": float(offset_unc),
                       "fraction_inside_2sigma": float(inside), "max_demo_reproduction_rms": float(rep),
                       "n_basis": K, "n_demos": N_DEMOS, "T": T}}


def _plot(out: Path, x, mean, std, via, samples, cmean) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    L = x.shape[0]
    fig, axes = plt.subplots(2, L, figsize=(2.4 * L, 4.6))
    t = torch.arange(x.shape[2])
    for i in range(L):
        ax = axes[0, i]
        for d in x[i]:
            ax.plot(d[:, 0], d[:, 1], color="0.7", lw=0.8)
        ax.plot(mean[i, :, 0], mean[i, :, 1], "k", lw=1.5)
        for s in samples[:, i]:
            ax.plot(s[:, 0], s[:, 1], lw=0.8, alpha=0.8)
        ax.plot(cmean[i, :, 0], cmean[i, :, 1], "k--", lw=1)
        ax.plot(via[i, 0, 0], via[i, 0, 1], "o", color="tab:red", ms=5)
        ax.set_aspect("equal")
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_title(LETTERS[i], fontsize=9)
        ax = axes[1, i]
        for j, col in enumerate(("tab:blue", "tab:orange")):
            ax.fill_between(t, mean[i, :, j] - 2 * std[i, :, j], mean[i, :, j] + 2 * std[i, :, j], color=col,
                            alpha=0.3, lw=0)
            ax.plot(t, mean[i, :, j], color=col, lw=1)
            for d in x[i]:
                ax.plot(t, d[:, j], color=col, lw=0.3, alpha=0.6)
        ax.axvline(T_VIA, color="tab:red", lw=0.5)
        ax.tick_params(labelsize=6)
    axes[1, 0].set_ylabel("p₁, p₂: mean ± 2σ", fontsize=7)
    fig.suptitle("§7.3 LQT with control primitives as a ProMP: fit, via-point conditioning", fontsize=9)
    fig.tight_layout()
    fig.savefig(out / f"{Path(__file__).stem}.png", dpi=80)
    plt.close(fig)


if __name__ == "__main__":
    import json

    print(json.dumps(run(Path("out/learning")), indent=1))
