"""Bézier surfaces: basis functions with a 2-D input (seed 004 §6.3-6.4; the cookbook's ``spline2d.py``).

Parameters: three height fields on ``[0, 1]²`` — ``sin(2πt₁) cos(πt₂)``, a Gaussian bump
``exp(-‖t - (0.4, 0.6)‖² / 0.2)`` and the polynomial ``t₁² - t₂ + t₁ t₂³`` — each observed at the same 400
scattered points ``t_m`` (a seeded ``torch.Generator``), without noise.

System: the Bézier surface ``x(t) = Ψ(t) w`` with ``Ψ(t) = φ(t₁) ⊗ φ(t₂)`` (Eq. 30), ``φ`` the ``K = 10``
Bernstein polynomials of degree 9 (Eq. 26), so ``P = K² = 100`` weights per surface; its gradient
``∇x = ∇Ψ(t) w`` with ``∂Ψ/∂t₁ = φ'(t₁) ⊗ φ(t₂)``, ``∂Ψ/∂t₂ = φ(t₁) ⊗ φ'(t₂)`` (Eq. 35-37).

Solve: the three weight vectors at once by least squares ``ŵ = (ΨᵀΨ)⁻¹Ψᵀx`` (Eq. 47, :func:`basis.fit`, normal
equations, batched over the three surfaces) on ``Ψ`` built row by row with :func:`basis.tensor_basis`.
Reference: ``torch.linalg.lstsq`` (QR) on the dense matrix assembled independently with ``torch.kron`` of the
rows of ``φ(t₁)`` and ``φ(t₂)``.

Plot: the three fitted surfaces as colour maps with the data points.

Checks:
  * ``matches_dense_lstsq``: on 2,500 held-out grid points ``t_q`` the fitted surfaces agree with the
    reference's within ``1e-7`` (the weights themselves may differ along the ill-conditioned directions of the
    degree-9 Bernstein basis, not the surfaces);
  * ``fit_error_below_bound``: ``max_q |x(t_q) - x_true(t_q)| ≤ 3e-3`` for every surface (``≤ 1e-8`` for the
    polynomial, which a degree-(9, 9) surface represents exactly);
  * ``gradient_error_below_bound``: the analytic gradient (Eq. 37) is within ``0.1`` of the true gradient
    (``1e-6`` for the polynomial) on the held-out points (the largest errors are at the corners).
"""

from __future__ import annotations

import functools
import math
from pathlib import Path

import torch

SECTION = "6.3"
TITLE = "Bézier surfaces: 2-D inputs by Kronecker products of Bernstein bases"

F64 = torch.float64
K = 10


def _fields(t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The three true height fields ``(3, *T)`` and their gradients ``(3, *T, 2)``."""
    u, v = t[..., 0], t[..., 1]
    s, c = torch.sin(2 * math.pi * u), torch.cos(math.pi * v)
    g = torch.exp(-((u - 0.4) ** 2 + (v - 0.6) ** 2) / 0.2)
    x = torch.stack([s * c, g, u ** 2 - v + u * v ** 3])
    dx = torch.stack([
        torch.stack([2 * math.pi * torch.cos(2 * math.pi * u) * c,
                     -math.pi * s * torch.sin(math.pi * v)], -1),
        torch.stack([-2 * (u - 0.4) / 0.2 * g, -2 * (v - 0.6) / 0.2 * g], -1),
        torch.stack([2 * u + v ** 3, -1 + 3 * u * v ** 2], -1),
    ])
    return x, dx


def run(out: Path | None = None) -> dict:
    """Solve; write ``out / "basis_surface.png"`` when ``out`` is given; return the outcomes."""
    from controllers import basis

    gen = torch.Generator().manual_seed(0)
    t = torch.rand(400, 2, dtype=F64, generator=gen)
    x, _ = _fields(t)  # (3, M)
    bern = functools.partial(basis.bernstein_deriv, K=K)
    Psi = basis.tensor_basis(t, bern)  # (M, P), Eq. (30)
    w = basis.fit(Psi, x)  # (3, P), Eq. (47)
    # reference: dense Kronecker rows and a QR least-squares solve
    phi1, phi2 = basis.bernstein(t[:, 0], K), basis.bernstein(t[:, 1], K)
    dense = torch.stack([torch.kron(phi1[m:m + 1], phi2[m:m + 1])[0] for m in range(t.shape[0])])
    w_ref = torch.linalg.lstsq(dense, x.T).solution.T
    # held-out grid
    g = torch.linspace(0, 1, 50, dtype=F64)
    tq = torch.stack(torch.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
    xq, dxq = _fields(tq)
    f, df = basis.tensor_grad(tq, w[:, None, :], bern)  # (3, Q), (3, Q, 2), Eq. (37)
    err = (f - xq).abs().amax(-1)
    # the reference surfaces on the same grid (weights differ only along ill-conditioned directions)
    ref_gap = float((basis.tensor_eval(tq, w_ref[:, None, :], bern) - f).abs().max())
    gerr = (df - dxq).abs().amax((-1, -2))
    if out is not None:
        _plot(out, t, f.reshape(3, 50, 50))
    return {
        "checks": {
            "matches_dense_lstsq": ref_gap <= 1e-7,
            "fit_error_below_bound": bool((err <= 3e-3).all()) and float(err[2]) <= 1e-8,
            "gradient_error_below_bound": bool((gerr <= 0.1).all()) and float(gerr[2]) <= 1e-6,
        },
        "values": {
            "n_points": int(t.shape[0]),
            "n_weights": int(w.shape[-1]),
            "max_gap_vs_dense_lstsq": ref_gap,
            "max_error_sin": float(err[0]),
            "max_error_gauss": float(err[1]),
            "max_error_poly": float(err[2]),
            "max_grad_error_sin": float(gerr[0]),
            "max_grad_error_gauss": float(gerr[1]),
            "max_grad_error_poly": float(gerr[2]),
        },
    }


def _plot(out: Path, t: torch.Tensor, f: torch.Tensor) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    fig, axs = plt.subplots(1, 3, figsize=(9, 3.2))
    names = ("sin(2πt₁)cos(πt₂)", "Gaussian bump", "t₁² − t₂ + t₁t₂³")
    for ax, fi, name in zip(axs, f, names):
        ax.imshow(fi.T.numpy(), origin="lower", extent=(0, 1, 0, 1), cmap="viridis")
        ax.plot(t[:, 0], t[:, 1], ".", color="w", ms=1.5)
        ax.set(title=name, xlabel="t₁", ylabel="t₂")
    fig.suptitle(f"Bézier surfaces, Ψ = φ ⊗ φ, K = {K}", fontsize=9)
    fig.tight_layout()
    fig.savefig(out / f"{Path(__file__).stem}.png", dpi=80)
    plt.close(fig)


if __name__ == "__main__":
    import json

    print(json.dumps(run(Path("out/cookbook")), indent=1))
