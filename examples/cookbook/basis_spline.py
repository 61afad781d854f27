"""Concatenated Bézier curves: a spline with C¹ or C² joints (seed 004 §6.5; the cookbook's ``spline1d.py``).

Parameters: a 2-D path ``x(t) = (sin(3πt) e^{-t} + 0.5t, cos(2πt) t)`` on ``t ∈ [0, 1]``, observed at 200
random phases with Gaussian noise ``σ = 0.02`` (a seeded ``torch.Generator``); ``S = 6`` cubic Bézier
segments of equal length.

System: ``x = φ C v`` — ``φ`` the six side-by-side cubic Bernstein dictionaries (Eq. 26) of the local phase
of each segment, and the continuity matrix ``C`` (Eq. 45-46) mapping the free weights ``v`` to the control
points ``w = C v``: at each joint the last control point of a segment is the first of the next
(``w₄ = w₅``) and, for C¹, the neighbouring ones are symmetric (``w₆ = 2w₅ - w₃``, the pattern
``[[1, 0], [0, 1], [0, 1], [-1, 2]]``); for C² the second control point after the joint is fixed as well.
C¹: ``K_v = 4 + 5·2 = 14`` weights per coordinate, C²: ``4 + 5·1 = 9``.

Solve: least squares ``v̂ = (ΨᵀΨ)⁻¹Ψᵀx`` (Eq. 47, :func:`basis.fit`) for both coordinates at once, for the C¹
and the C² spline.

Plot: the data, both fitted paths, the joints and the C² spline's control points.

Checks:
  * ``continuous_at_joints``: at the 5 joints the derivatives of order ``0..k`` from the left and right
    segments agree to ``1e-10`` (relative to their size) for the ``C^k`` spline (k = 1, 2);
  * ``next_derivative_jumps``: the derivative of order ``k + 1`` does jump (by more than ``1e-3``) — the
    constraint is exactly ``C^k``, not more;
  * ``fit_error_below_bound``: the RMS distance of both fitted paths to the noise-free path on 500 phases is
    below ``0.02`` (the noise level);
  * ``c2_matches_bspline``: the C² fit equals scipy's least-squares cubic B-spline with the same interior
    knots (``make_lsq_spline``) within ``1e-9`` — the same function space, fitted independently.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch

SECTION = "6.5"
TITLE = "Concatenated Bézier curves (splines) with the continuity matrix"

F64 = torch.float64
S = 6  # segments
P = 3  # degree (cubic)


def path(t: torch.Tensor) -> torch.Tensor:
    """The noise-free path ``(2, *T)``."""
    return torch.stack([torch.sin(3 * math.pi * t) * torch.exp(-t) + 0.5 * t, torch.cos(2 * math.pi * t) * t])


def run(out: Path | None = None) -> dict:
    """Solve; write ``out / "basis_spline.png"`` when ``out`` is given; return the outcomes."""
    import numpy as np
    from scipy.interpolate import make_lsq_spline

    from controllers import basis

    gen = torch.Generator().manual_seed(0)
    t = torch.sort(torch.rand(200, dtype=F64, generator=gen)).values
    x = path(t) + 0.02 * torch.randn(2, 200, dtype=F64, generator=gen)
    tq = torch.linspace(0, 1, 500, dtype=F64)
    one, zero = torch.ones((), dtype=F64), torch.zeros((), dtype=F64)
    fits, gaps, jumps, rms = {}, {}, {}, {}
    for k in (1, 2):
        v = basis.fit(basis.spline(t, S, P, k), x)  # (2, K_v), Eq. (47)
        w = (v @ basis.continuity_matrix(S, P, k).T).reshape(2, S, P + 1)  # control points, w = C v
        gap, jump = 0.0, math.inf
        for j in range(k + 2):
            left = w[:, :-1] @ basis.bernstein_deriv(one, P + 1, order=j)  # end of segment s (local phase 1)
            right = w[:, 1:] @ basis.bernstein_deriv(zero, P + 1, order=j)  # start of segment s+1
            d = float(((left - right).abs() / (1 + left.abs())).max())
            if j <= k:
                gap = max(gap, d)
            else:
                jump = float((left - right).abs().min())
        xq = basis.spline(tq, S, P, k) @ v.T  # (500, 2)
        fits[k], gaps[k], jumps[k] = (v, w, xq), gap, jump
        rms[k] = float(((xq - path(tq).T) ** 2).sum(-1).mean().sqrt())
    knots = np.concatenate([np.zeros(P + 1), np.arange(1, S) / S, np.ones(P + 1)])
    ref = np.stack([make_lsq_spline(t.numpy(), x[i].numpy(), knots, k=P)(tq.numpy()) for i in range(2)], -1)
    bspline_gap = float(np.abs(fits[2][2].numpy() - ref).max())
    if out is not None:
        _plot(out, x, fits, path(tq))
    return {
        "checks": {
            "continuous_at_joints": max(gaps.values()) <= 1e-10,
            "next_derivative_jumps": min(jumps.values()) > 1e-3,
            "fit_error_below_bound": max(rms.values()) < 0.02,
            "c2_matches_bspline": bspline_gap <= 1e-9,
        },
        "values": {
            "n_weights_c1": int(fits[1][0].shape[-1]),
            "n_weights_c2": int(fits[2][0].shape[-1]),
            "joint_gap_c1": gaps[1],
            "joint_gap_c2": gaps[2],
            "min_jump_order2_c1": jumps[1],
            "min_jump_order3_c2": jumps[2],
            "rms_error_c1": rms[1],
            "rms_error_c2": rms[2],
            "c2_vs_bspline": bspline_gap,
        },
    }


def _plot(out: Path, x: torch.Tensor, fits: dict, xtrue: torch.Tensor) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(4.5, 3.6))
    ax.plot(x[0], x[1], ".", color="0.6", ms=2.5, label="data")
    ax.plot(xtrue[0], xtrue[1], "k:", lw=0.8, label="noise-free")
    for k, col in ((1, "tab:orange"), (2, "tab:blue")):
        ax.plot(fits[k][2][:, 0], fits[k][2][:, 1], color=col, lw=1.4, label=f"C{k} spline")
    w = fits[2][1]  # (2, S, 4)
    ax.plot(w[0].flatten(), w[1].flatten(), "s--", color="tab:blue", ms=3, lw=0.5, alpha=0.6,
            label="C² control points")
    joints = fits[2][1][:, 1:, 0]
    ax.plot(joints[0], joints[1], "o", color="k", ms=4, label="joints")
    ax.set(aspect="equal", title=f"{S} cubic Bézier segments, w = C v")
    ax.legend(fontsize=6, loc="best")
    fig.tight_layout()
    fig.savefig(out / f"{Path(__file__).stem}.png", dpi=80)
    plt.close(fig)


if __name__ == "__main__":
    import json

    print(json.dumps(run(Path("out/cookbook")), indent=1))
