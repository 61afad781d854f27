"""Spectral multiscale coverage (SMC) on a line segment (seed 004 §10.1.1; the cookbook's
``ergodic_control_SMC_1D.py``).

Parameters: the domain ``x ∈ [0, ℓ]``, ``ℓ = 1`` (mirrored to a signal of period ``L = 2ℓ``), ``K = 12``
cosine basis functions ``φ_k(x) = cos(2πkx/L)/L`` (Eq. 123), weights ``Λ_k = (1 + k²)^{-1}`` (Eq. 130).
The spatial distribution ``ĝ`` is a mixture of three Gaussians with weights ``α = (0.2, 0.3, 0.5)``; its
coefficients ``ŵ_k`` come in closed form from the Gaussian, shift and combination properties of Table 1.

System: a velocity-controlled agent ``ẋ = u``, ``|u| ≤ u_max = 1``, ``Δt = 0.01``, ``T = 1000`` steps;
three independent problems (three starting points) are solved at once, as one batch.

Solve: at each step the time-averaged coefficients ``w_k`` (Eq. 127, updated recursively) are compared
with ``ŵ_k`` and the myopic controller ``u = u_max sign(−Σ_k Λ_k (w_k − ŵ_k) ∇φ_k(x))`` (Eq. 138) moves the
agent; no random numbers are used.

Plot: the target density and the density reconstructed from ``w`` (left), ``x(t)`` (middle), the ergodic
metric ``ε = ½ Σ Λ_k (w_k − ŵ_k)²`` (Eq. 129) over time (right).

Checks (every problem of the batch):
  * ``metric_below_bound``: final ``ε < 1e-3``;
  * ``far_below_standing_still``: final ``ε`` below 2 % of the metric of an agent standing at its start;
  * ``below_uniform_sweep``: final ``ε`` below 20 % of the metric of a uniform (lawnmower) coverage;
  * ``metric_decreases``: ``ε`` at ``T/10``, ``T/2``, ``T`` strictly decreasing, final below 5 % of ``ε_1``;
  * ``time_proportional_to_weights``: the fraction of time within ``2σ_j`` of each ``μ_j`` is within 0.1
    of ``0.954 α_j`` (the mass of that interval under ``ĝ``);
  * ``stays_in_domain``: ``0 ≤ x ≤ ℓ`` (nothing clamps it: the cosine basis has zero slope at the walls).
"""

from __future__ import annotations

from pathlib import Path

import torch

from controllers import ergodic as E

SECTION = "10.1.1"
TITLE = "Spectral ergodic control (SMC), 1-D"


def _reconstruct(w: torch.Tensor, x: torch.Tensor, K: int, ell: float) -> torch.Tensor:
    """Density ``Σ_k w_k φ_k(x) / ‖φ_k‖²`` on ``[0, ℓ]`` from cosine coefficients ``w (*B, K)``."""
    norm2 = torch.full((K,), ell / (2 * (2 * ell) ** 2), dtype=w.dtype)
    norm2[0] = ell / (2 * ell) ** 2
    return (E.fourier_basis(x, n_basis=K, length=ell) * (w / norm2)[..., None, :]).sum(-1)


def run(out: Path | None = None) -> dict:
    """Solve; write ``out / "ergodic_smc_1d.png"`` when ``out`` is given; return the outcomes."""
    dt64 = torch.float64
    K, ell, T, dt, u_max = 12, 1.0, 1000, 0.01, 1.0
    alpha = torch.tensor([0.2, 0.3, 0.5], dtype=dt64)
    mu = torch.tensor([[0.2], [0.5], [0.8]], dtype=dt64)
    sd = torch.tensor([0.04, 0.06, 0.06], dtype=dt64)
    w_hat = E.gmm_fourier_coefficients(alpha, mu, (sd ** 2)[:, None, None], n_basis=K, length=ell)
    lam = E.sobolev_weights(1, K, dtype=dt64)

    x0 = torch.tensor([0.05, 0.45, 0.95], dtype=dt64)[:, None, None]      # (B=3, N=1, D=1)
    r = E.smc_rollout(x0, w_hat, n_steps=T, dt=dt, u_max=u_max, n_basis=K, length=ell, weights=lam)
    eps = r.metric                                                         # (3, T)
    x = r.x[..., 0, 0]                                                     # (3, T)

    still = E.ergodic_metric(E.fourier_basis(x0[:, 0], n_basis=K, length=ell), w_hat, lam)
    uniform = torch.zeros(K, dtype=dt64)
    uniform[0] = 1.0 / (2 * ell)                                           # ŵ of the uniform density
    sweep = E.ergodic_metric(uniform, w_hat, lam)
    frac = ((x[..., None] - mu[:, 0]).abs() < 2 * sd).to(dt64).mean(-2)  # (3, J)
    final = eps[:, -1]
    checks = {
        "metric_below_bound": bool((final < 1e-3).all()),
        "far_below_standing_still": bool((final < 0.02 * still).all()),
        "below_uniform_sweep": bool((final < 0.2 * sweep).all()),
        "metric_decreases": bool(((eps[:, T // 10 - 1] > eps[:, T // 2 - 1]) & (eps[:, T // 2 - 1] > final)
                                  & (final < 0.05 * eps[:, 0])).all()),
        "time_proportional_to_weights": bool(((frac - 0.954 * alpha).abs() < 0.1).all()),
        "stays_in_domain": bool(((r.x >= 0) & (r.x <= ell)).all()),
    }
    values = {
        "ergodic_metric": float(final.max()),
        "standing_still_metric": float(still.min()),
        "uniform_sweep_metric": float(sweep),
        "max_time_fraction_error": float((frac - 0.954 * alpha).abs().max()),
    }
    if out is not None:
        grid = torch.linspace(0, ell, 200, dtype=dt64)[:, None]
        target = E.gmm_density(grid, alpha, mu, (sd ** 2)[:, None, None])
        _plot(out, grid[:, 0], target, _reconstruct(r.w, grid, K, ell), x, eps, dt)
    return {"checks": checks, "values": values}


def _plot(out: Path, grid, target, recon, x, eps, dt) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    out.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(1, 3, figsize=(10, 3))
    ax[0].plot(grid, target, "r", lw=2, label="target ĝ")
    for b in range(recon.shape[0]):
        ax[0].plot(grid, recon[b], "k", lw=0.8, alpha=0.7, label="from w" if b == 0 else None)
    ax[0].set_xlabel("x")
    ax[0].legend(fontsize=7)
    t = torch.arange(x.shape[-1]) * dt
    for b in range(x.shape[0]):
        ax[1].plot(t, x[b], lw=0.7)
        ax[2].semilogy(t, eps[b], lw=0.9)
    ax[1].set_xlabel("t")
    ax[1].set_ylabel("x(t)")
    ax[2].set_xlabel("t")
    ax[2].set_ylabel("ε")
    fig.tight_layout()
    fig.savefig(out / f"{Path(__file__).stem}.png", dpi=80)
    plt.close(fig)


if __name__ == "__main__":
    import json
    print(json.dumps(run(Path("out/cookbook")), indent=1))
