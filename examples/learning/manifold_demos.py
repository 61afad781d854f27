"""Orientation demos on SO(3): per-step Gaussians on the manifold, tracked by the error-state MPC, and a
stiffness (SPD) target learned from demos (issue 26 §5; seed 004 §12.3, seed 003 Algorithm 1).

Parameters: ``N_DEMOS = 12`` demos of a tool orientation, ``T = 40`` steps of ``dt = 0.02`` s
(:func:`learning.manifold_demos.orientation_demos`): a smooth reference rotation path ``R*(s) = Exp(ξ(s))``
(at most 1.9 rad from the start), a small random time warp, and smooth body-frame noise ``R·Exp(ε)`` of
std 0.12 rad times an envelope ``1 − 0.9 exp(−((s − 0.6)/0.08)²)``: the demonstrators agree on the
orientation around ``s = 0.6`` (a grasp) and vary elsewhere.

Statistics (seed 004 §12.3, :func:`~learning.manifold_demos.manifold_statistics`): per step the Karcher
mean ``μ_t`` (Gauss–Newton ``u = 1/N Σ Log(μ⁻¹R_i)``, ``μ ← μ Exp(u)``, all steps in one batch) and the
body-frame tangent covariance ``Σ_t``.  The same demos as unit quaternions with random signs (q ≡ −q) give
the same mean rotation (the S³ statistics align the hemispheres).

System and control (seed 003): the kinematic rotation ``R_{k+1} = R_k Exp(Δt ω_k)``
(:class:`~learning.manifold_demos.BodyRateSO3`), the error-state MPC (horizon 8, ``R = I``) tracking the
mean with the reference body rates ``Log(μ_t⁻¹ μ_{t+1})/Δt`` and the per-step precision
``Q_t = (Σ_t + 10⁻⁴ I)⁻¹`` (:func:`~learning.manifold_demos.track_mean`), from a start rotated 0.45 rad
away from ``μ_0``.

Stiffness target: ``N_DEMOS`` demos of a 3×3 stiffness matrix along the affine-invariant geodesic between
two stiffnesses with log-scale noise 0.3 (:func:`~learning.manifold_demos.stiffness_demos`); the per-step
Karcher mean (affine-invariant) against the Euclidean average.

Plot: (1) the tool z-axis ``R e_z`` of the demos (grey), of the mean (black) with its 2σ covariance
ellipses (the body covariance pushed through ``δz = −R [e_z]× δω``, projected on x–y), and the closed
loop (red); (2) the total variance ``tr Σ_t`` and the MPC's feedback gain ‖K_t‖ over time; (3) the tracking
error ``‖Log(μ_t⁻¹ R_t)‖``; (4) ``det`` of the Karcher and of the Euclidean stiffness means.

Outcome checks: ``statistics_converged`` — every step's Gauss–Newton certified (step ≤ eps^¾);
``quaternion_mean_agrees`` — the S³ mean rotation equals the SO(3) one within ``10⁻⁸`` rad;
``demos_inside_95_ellipsoids`` — at least 85 % of the demo samples have ``Log(μ⁻¹R)ᵀ Σ⁻¹ Log(μ⁻¹R) ≤
7.81`` (χ²₃ 95 %); ``tracking_error_reduced`` — the final error is below 1 % of the initial one;
``stiffer_where_demos_agree`` — the spectral norm of the feedback gain at the tightest step (smallest
``λ_max(Σ_t)``) exceeds twice that at the loosest step (largest ``λ_min(Σ_t)``), whose variance is at least
5x larger in every direction; ``spd_det_is_geometric_mean`` — ``det`` of the Karcher
mean equals the geometric mean of the demos' determinants (relative 10⁻⁸); ``euclidean_mean_swells_det`` —
the Euclidean mean's determinant exceeds the Karcher mean's at every step.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch

from learning.manifold_demos import (
    BodyRateSO3,
    demo_points,
    manifold_statistics,
    orientation_demos,
    stiffness_demos,
    track_mean,
)
from torchlie import so3

SECTION = "12.3"
TITLE = "Orientation demos on SO(3): Gaussians per step tracked by the on-manifold MPC; SPD stiffness target"

N_DEMOS = 12
T = 40
HORIZON = 8
CHI2_3_95 = 7.815


def run(out: Path | None = None) -> dict:
    """Generate, fit, track; write ``out / "manifold_demos.png"`` when ``out`` is given; return outcomes."""
    g = torch.Generator().manual_seed(3)
    s = torch.linspace(0.0, 1.0, T, dtype=torch.float64)
    env = 1 - 0.9 * torch.exp(-((s - 0.6) / 0.08) ** 2)
    demos = orientation_demos(N_DEMOS, T, generator=g, envelope=env, warp=0.05)
    st = manifold_statistics(demos)
    R = demo_points(demos)                                                  # (N, T, 3, 3)

    # the same demos as quaternions with random signs
    q = so3.to_quaternion(R)
    q = torch.where(torch.rand(N_DEMOS, T, 1, generator=g, dtype=torch.float64) < 0.5, -q, q)
    st_q = manifold_statistics(q, "S3")
    q_gap = so3.angle(st.mean.mT @ so3.from_quaternion(st_q.mean)).max()

    # demos inside the 95 % ellipsoids of their per-step Gaussians
    e = so3.log(st.mean.mT @ R)                                             # (N, T, 3)
    maha = (e.unsqueeze(-2) @ torch.linalg.solve(st.covariance, e.unsqueeze(-1))).squeeze(-1).squeeze(-1)
    inside = float((maha <= CHI2_3_95).double().mean())

    # tracking the mean from a perturbed start, precision (Σ_t + λI)⁻¹
    x0 = st.mean[0] @ so3.exp(torch.tensor([0.3, -0.2, 0.25], dtype=torch.float64))
    run_ = track_mean(BodyRateSO3(demos.dt), st.mean, st.covariance, x0, horizon=HORIZON, R=1.0,
                      regularization=1e-4)
    err = run_.error.norm(dim=-1)
    var = torch.diagonal(st.covariance, dim1=-2, dim2=-1).sum(-1)
    gain = torch.linalg.matrix_norm(run_.gain, ord=2)
    # tightest step: smallest largest variance; loosest: largest smallest variance (every direction looser)
    ev = torch.linalg.eigvalsh(st.covariance[:-1])
    lo, hi = int(ev[:, -1].argmin()), int(ev[:, 0].argmax())

    # stiffness target
    kd = stiffness_demos(N_DEMOS, T, generator=g, noise=0.3)
    ks = manifold_statistics(kd)
    K = demo_points(kd)
    ld_karcher = torch.linalg.slogdet(ks.mean)[1]
    ld_geo = torch.linalg.slogdet(K)[1].mean(0)
    ld_euclid = torch.linalg.slogdet(K.mean(0))[1]

    if out is not None:
        _plot(out, R, st.mean, st.covariance, run_.x, var, gain, err, ld_karcher, ld_euclid)
    checks = {
        "statistics_converged": bool(st.converged.all() and st_q.converged.all() and ks.converged.all()),
        "quaternion_mean_agrees": bool(q_gap < 1e-8),
        "demos_inside_95_ellipsoids": inside >= 0.85,
        "tracking_error_reduced": bool(err[-1] < 0.01 * err[0]) and bool((run_.reason == 0).all()),
        "stiffer_where_demos_agree": bool(ev[hi, 0] >= 5 * ev[lo, -1]) and bool(gain[lo] > 2 * gain[hi]),
        "spd_det_is_geometric_mean": bool(((ld_karcher - ld_geo).abs() < 1e-8).all()),
        "euclidean_mean_swells_det": bool((ld_euclid > ld_karcher).all()),
    }
    values = {
        "max_gauss_newton_iterations": int(st.iterations.max()),
        "quaternion_mean_gap_rad": float(q_gap),
        "fraction_inside_95": inside,
        "initial_error_rad": float(err[0]),
        "final_error_rad": float(err[-1]),
        "tight_step": lo,
        "loose_step": hi,
        "tight_step_max_variance": float(ev[lo, -1]),
        "loose_step_min_variance": float(ev[hi, 0]),
        "gain_at_low_variance": float(gain[lo]),
        "gain_at_high_variance": float(gain[hi]),
        "max_det_ratio_euclid_over_karcher": float(torch.exp(ld_euclid - ld_karcher).max()),
    }
    return {"checks": checks, "values": values}


def _plot(out: Path, R, mean, cov, xcl, var, gain, err, ld_k, ld_e) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    fig, axes = plt.subplots(1, 4, figsize=(12, 2.9))
    ax = axes[0]
    z = R[..., :, 2]                                                         # (N, T, 3)
    for zi in z:
        ax.plot(zi[:, 0], zi[:, 1], color="0.7", lw=0.7)
    zm = mean[..., :, 2]
    ax.plot(zm[:, 0], zm[:, 1], "k", lw=1.5, label="mean")
    ez = torch.tensor([0.0, 0.0, 1.0], dtype=mean.dtype)
    th = torch.linspace(0, 2 * math.pi, 60, dtype=mean.dtype)
    circ = torch.stack([torch.cos(th), torch.sin(th)], 0)
    for t in range(0, mean.shape[0], 3):
        J = -(mean[t] @ so3.hat(ez))[:2]                                     # δz_xy = J δω
        C = J @ cov[t] @ J.T
        evals, evecs = torch.linalg.eigh(C)
        pts = evecs @ (2 * evals.clamp(min=0).sqrt()[:, None] * circ)
        ax.plot(zm[t, 0] + pts[0], zm[t, 1] + pts[1], color="tab:blue", lw=0.7)
    zc = xcl[..., :, 2]
    ax.plot(zc[:, 0], zc[:, 1], color="tab:red", lw=1.2, label="MPC")
    ax.set_aspect("equal")
    ax.set_title("tool z-axis (x–y), 2σ", fontsize=8)
    ax.legend(fontsize=6)
    t = torch.arange(mean.shape[0])
    ax = axes[1]
    ax.semilogy(t, var, color="tab:blue")
    ax.set_ylabel("tr Σ_t", fontsize=7, color="tab:blue")
    ax2 = ax.twinx()
    ax2.plot(t[:-1], gain, color="tab:red")
    ax2.set_ylabel("‖K_t‖", fontsize=7, color="tab:red")
    ax.set_title("variance and MPC gain", fontsize=8)
    ax = axes[2]
    ax.semilogy(t, err.clamp(min=1e-16), color="tab:red")
    ax.set_title("tracking error ‖Log(μ⁻¹R)‖", fontsize=8)
    ax = axes[3]
    ax.plot(t, ld_k, label="Karcher (affine-inv.)")
    ax.plot(t, ld_e, "--", label="Euclidean")
    ax.set_title("log det of the stiffness mean", fontsize=8)
    ax.legend(fontsize=6)
    for a in axes:
        a.tick_params(labelsize=6)
    fig.tight_layout()
    fig.savefig(out / f"{Path(__file__).stem}.png", dpi=80)
    plt.close(fig)


if __name__ == "__main__":
    import json
    print(json.dumps(run(Path("out/learning")), indent=1))
