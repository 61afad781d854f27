"""Multidimensional spectral multiscale coverage (SMC) with several agents (seed 004 §10.1.2; the
cookbook's ``ergodic_control_SMC_2D.py``).

Parameters: the domain ``[0, ℓ]²``, ``ℓ = 1`` (mirrored to period ``L = 2ℓ``, Fig. 42-(d)), ``K = 10``
basis functions per dimension, i.e. ``K² = 100`` functions ``φ_k(x) = L^{-2} cos(V_1 x_1) ⊙ cos(V_2 x_2)``
(Eq. 155) with gradients (Eq. 156), weights ``Λ_k = (1 + ‖k‖²)^{-3/2}`` (Eq. 149).  Two problems are
solved in one batch, each a mixture of two Gaussians (weights ``0.4, 0.6``, correlated covariances, as in
Fig. 42-(a)), whose coefficients ``ŵ_k`` come in closed form (Table 1 extended to 2-D).

System: ``N = 3`` velocity-controlled agents ``ẋ_i = u_i``, ``‖u_i‖ ≤ u_max = 1``, ``Δt = 0.01``,
``T = 800`` steps per problem; the agents share one set of time-averaged coefficients ``w`` (Eq. 145).

Solve: the myopic controller ``u_i = u_max ũ_i/‖ũ_i‖``, ``ũ_i = −∇φ(x_i)ᵀ Λ (w − ŵ)`` (Eq. 159) for all
agents of both problems at once (a loop over time only).

Plot: for each problem, the target density with the agents' paths, and ``ε`` (Eq. 147) over time.

Checks (both problems):
  * ``metric_below_bound``: final ``ε < 2e-4``;
  * ``far_below_standing_still``: final ``ε`` below 2 % of the metric of the agents standing at their start;
  * ``below_uniform_sweep``: final ``ε`` below 10 % of the metric of a uniform (lawnmower) coverage;
  * ``metric_decreases``: ``ε`` at ``T/10``, ``T/2``, ``T`` strictly decreasing, final below 5 % of ``ε_1``;
  * ``time_proportional_to_weights``: the fraction of agent-time within Mahalanobis distance 2 of each
    component is within 0.1 of ``(1 − e^{-2}) α_j`` (that region's mass under ``ĝ``);
  * ``stays_in_domain``: every agent stays in ``[0, ℓ]²`` (nothing clamps it).
"""

from __future__ import annotations

import math
from pathlib import Path

import torch

from controllers import ergodic as E

SECTION = "10.1.2"
TITLE = "Spectral ergodic control (SMC), 2-D, several agents"


def run(out: Path | None = None) -> dict:
    """Solve; write ``out / "ergodic_smc_2d.png"`` when ``out`` is given; return the outcomes."""
    f64 = torch.float64
    K, ell, T, dt, u_max = 10, 1.0, 800, 0.01, 1.0
    alpha = torch.tensor([[0.4, 0.6], [0.4, 0.6]], dtype=f64)                       # (B=2, J=2)
    mu = torch.tensor([[[0.5, 0.7], [0.6, 0.3]], [[0.25, 0.25], [0.7, 0.65]]], dtype=f64)
    sigma = torch.tensor([[[[0.01, 0.008], [0.008, 0.01]], [[0.01, -0.006], [-0.006, 0.01]]],
                          [[[0.006, 0.0], [0.0, 0.006]], [[0.02, 0.01], [0.01, 0.012]]]], dtype=f64)
    w_hat = E.gmm_fourier_coefficients(alpha, mu, sigma, n_basis=K, length=ell)  # (2, K²)
    lam = E.sobolev_weights(2, K, dtype=f64)

    x0 = torch.tensor([[[0.1, 0.1], [0.2, 0.9], [0.9, 0.9]],
                       [[0.5, 0.1], [0.1, 0.5], [0.9, 0.2]]], dtype=f64)            # (B=2, N=3, D=2)
    r = E.smc_rollout(x0, w_hat, n_steps=T, dt=dt, u_max=u_max, n_basis=K, length=ell, weights=lam)
    eps = r.metric                                                                   # (2, T)
    final = eps[:, -1]

    still = E.ergodic_metric(E.fourier_basis(x0, n_basis=K, length=ell).mean(-2), w_hat, lam)
    uniform = torch.zeros(K * K, dtype=f64)
    uniform[0] = 1.0 / (2 * ell) ** 2
    sweep = E.ergodic_metric(uniform, w_hat, lam)
    # fraction of agent-time within Mahalanobis distance 2 of each component
    d = r.x[..., None, :] - mu[:, None, None]                                        # (2, T, N, J, 2)
    m2 = (d[..., None, :] @ torch.linalg.solve(sigma[:, None, None], d[..., None]))[..., 0, 0]
    frac = (m2 < 4).to(f64).mean((1, 2))                                             # (2, J)
    expected = (1 - math.exp(-2)) * alpha
    checks = {
        "metric_below_bound": bool((final < 2e-4).all()),
        "far_below_standing_still": bool((final < 0.02 * still).all()),
        "below_uniform_sweep": bool((final < 0.1 * sweep).all()),
        "metric_decreases": bool(((eps[:, T // 10 - 1] > eps[:, T // 2 - 1]) & (eps[:, T // 2 - 1] > final)
                                  & (final < 0.05 * eps[:, 0])).all()),
        "time_proportional_to_weights": bool(((frac - expected).abs() < 0.1).all()),
        "stays_in_domain": bool(((r.x >= 0) & (r.x <= ell)).all()),
    }
    values = {
        "ergodic_metric": float(final.max()),
        "standing_still_metric": float(still.min()),
        "uniform_sweep_metric": float(sweep.min()),
        "max_time_fraction_error": float((frac - expected).abs().max()),
    }
    if out is not None:
        _plot(out, alpha, mu, sigma, r.x, eps, ell, dt)
    return {"checks": checks, "values": values}


def _plot(out: Path, alpha, mu, sigma, x, eps, ell, dt) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    out.mkdir(parents=True, exist_ok=True)
    n = 80
    c = torch.linspace(0, ell, n, dtype=mu.dtype)
    pts = torch.stack(torch.meshgrid(c, c, indexing="ij"), -1).reshape(-1, 2)
    fig, ax = plt.subplots(1, 3, figsize=(10, 3.2))
    for b in range(2):
        dens = E.gmm_density(pts, alpha[b], mu[b], sigma[b]).reshape(n, n)
        ax[b].contourf(c, c, dens.T, levels=12, cmap="Greys")
        for i in range(x.shape[-2]):
            ax[b].plot(x[b, :, i, 0], x[b, :, i, 1], lw=0.6)
            ax[b].plot(x[b, 0, i, 0], x[b, 0, i, 1], "ko", ms=3)
        ax[b].set_aspect("equal")
        ax[b].set_title(f"problem {b}", fontsize=9)
        ax[2].semilogy(torch.arange(eps.shape[-1]) * dt, eps[b], label=f"problem {b}")
    ax[2].set_xlabel("t")
    ax[2].set_ylabel("ε")
    ax[2].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / f"{Path(__file__).stem}.png", dpi=80)
    plt.close(fig)


if __name__ == "__main__":
    import json
    print(json.dumps(run(Path("out/cookbook")), indent=1))
