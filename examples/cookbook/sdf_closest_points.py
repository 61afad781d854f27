"""Closest points between two shapes encoded as SDFs (seed 004 §6.4, Eq. 40-44).

Parameters: an ellipse (half-axes ``0.6, 0.35``) and a rounded square (``|x/0.45|⁴ + |y/0.45|⁴ = 1``), each
fitted as an SDF from 64 contour points with the eikonal cost (§6.8, :func:`controllers.sdf.fit_sdf`, five
cubic Bézier segments per input with C¹ joints, both shapes in one batch); four relative placements: a point
``t₂`` of shape 2 is ``A t₂ + b`` in the frame of shape 1 (``A`` a rotation by ``θ``).

System: the pair ``t = [t₁; t₂]``, each in its shape's frame, the residuals ``f₁(t₁)``, ``f₂(t₂)`` and
``A t₂ + b - t₁`` with the Jacobian of Eq. (41) built from the SDF gradients (Eq. 38).

Solve: the prioritized Gauss–Newton step of Eq. (43)-(44),
``t ← t - α₁ J₁₂†[f₁; f₂] - α₂ N₁₂ J₃† (A t₂ + b - t₁)``, ``α₁ = 1``, ``α₂ = 0.5``
(:func:`controllers.sdf.closest_points_prioritized`), all four placements in one batch; the points are put on
the contours first and moved closer in the nullspace of that task.  For comparison, the plain Gauss–Newton of
Eq. (40)-(42) with weight ``β = 0.1`` on the distance term (:func:`controllers.sdf.closest_points`), a penalty
formulation whose points stop off the contours.

Reference: brute force on a dense grid — the zero crossings of each fitted SDF along the edges of a
``400 × 400`` grid (linear interpolation, no gradients), shape 2's moved by ``(A, b)``, and the smallest
distance between the two point sets.

Plot: the four placements in the frame of shape 1 with the zero level sets and the closest segments.

Checks:
  * ``converged``: every placement certified (``|f₁|, |f₂| ≤ 1e-10`` and the projected gradient
    ``‖N₁₂ J₃ᵀ(A t₂ + b - t₁)‖ ≤ 1e-10`` at the returned points);
  * ``points_on_zero_level``: ``|f₁(t₁)|, |f₂(t₂)| ≤ 1e-9`` — both points on their shape's zero level set;
  * ``distance_matches_brute_force``: the distance ``‖A t₂ + b - t₁‖`` is within ``1e-3`` of the brute-force
    distance (and not below it by more than that: it is the closest pair);
  * ``plain_penalty_converged``: the plain Gauss–Newton run is certified (``‖2Jᵀf‖ ≤ 1e-8``) and its points
    lie off the contours (``|f₁| > 1e-3``), as a penalty formulation predicts.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch

SECTION = "6.4"
TITLE = "Closest points between two SDF shapes (prioritized Gauss–Newton)"

F64 = torch.float64
LO, HI = (-1.0, -1.0), (1.0, 1.0)
THETA = (0.3, 1.2, -0.7, 2.4)
OFFSET = ((1.55, 0.35), (0.3, 1.35), (-1.45, -0.6), (1.1, -1.15))


def contours(n: int) -> torch.Tensor:
    th = torch.linspace(0, 2 * math.pi, n + 1, dtype=F64)[:-1]
    c, s = th.cos(), th.sin()
    ellipse = torch.stack([0.6 * c, 0.35 * s], -1)
    square = torch.stack([0.45 * c.sign() * c.abs().sqrt(), 0.45 * s.sign() * s.abs().sqrt()], -1)
    return torch.stack([ellipse, square])


def zero_crossings(f: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """Points where ``f (n, n)`` on the grid ``g (n,)²`` changes sign along grid edges (linear
    interpolation)."""
    X, Y = torch.meshgrid(g, g, indexing="ij")
    P = torch.stack([X, Y], -1)
    out = []
    for a, b, pa, pb in ((f[:-1], f[1:], P[:-1], P[1:]), (f[:, :-1], f[:, 1:], P[:, :-1], P[:, 1:])):
        m = (a * b) < 0
        lam = (a[m] / (a[m] - b[m]))[:, None]
        out.append(pa[m] + lam * (pb[m] - pa[m]))
    return torch.cat(out)


def run(out: Path | None = None) -> dict:
    """Solve; write ``out / "sdf_closest_points.png"`` when ``out`` is given; return the outcomes."""
    from controllers import sdf

    fit = sdf.fit_sdf(contours(64), LO, HI, eikonal_weight=0.01, tol=1e-7, max_iter=60)
    s1 = sdf.SDF(fit.sdf.w[0], fit.sdf.lower, fit.sdf.upper, fit.sdf.basis)
    s2 = sdf.SDF(fit.sdf.w[1], fit.sdf.lower, fit.sdf.upper, fit.sdf.basis)
    th = torch.tensor(THETA, dtype=F64)
    A = torch.stack([torch.stack([th.cos(), -th.sin()], -1), torch.stack([th.sin(), th.cos()], -1)], -2)
    b = torch.tensor(OFFSET, dtype=F64)
    res = sdf.closest_points_prioritized(s1, s2, A, b, alpha1=1.0, alpha2=0.5, tol=1e-10, max_iter=300)
    plain = sdf.closest_points(s1, s2, A, b, weight=0.1, tol=1e-8, max_iter=300)
    # brute force on the fitted SDFs' zero sets
    g = torch.linspace(-1, 1, 400, dtype=F64)
    grid = torch.stack(torch.meshgrid(g, g, indexing="ij"), -1)[..., None, :]  # (n, n, 1, 2)
    F = sdf.sdf_value(fit.sdf, grid)  # (n, n, 2)
    z1, z2 = zero_crossings(F[..., 0], g), zero_crossings(F[..., 1], g)
    z2w = z2 @ A.mT + b[:, None, :]  # (4, N2, 2) in the frame of shape 1
    brute = torch.cdist(z1.expand(4, -1, -1), z2w).amin((-1, -2))
    gap = (res.distance - brute).abs()
    if out is not None:
        _plot(out, z1, z2w, res)
    return {
        "checks": {
            "converged": bool(res.converged.all()),
            "points_on_zero_level": float(torch.maximum(res.f1.abs(), res.f2.abs()).max()) <= 1e-9,
            "distance_matches_brute_force": float(gap.max()) <= 1e-3,
            "plain_penalty_converged": bool(plain.converged.all()) and bool((plain.f1.abs() > 1e-3).all()),
        },
        "values": {
            "n_placements": int(b.shape[0]),
            "min_distance": float(res.distance.min()),
            "max_distance": float(res.distance.max()),
            "max_gap_vs_brute_force": float(gap.max()),
            "max_abs_f_at_points": float(torch.maximum(res.f1.abs(), res.f2.abs()).max()),
            "max_iterations": int(res.iterations.max()),
            "plain_shorter_everywhere": int(bool((plain.distance < res.distance).all())),
            "plain_max_abs_f1": float(plain.f1.abs().max()),
            "plain_max_iterations": int(plain.iterations.max()),
        },
    }


def _plot(out: Path, z1: torch.Tensor, z2w: torch.Tensor, res) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(4.5, 4.5))
    ax.plot(z1[:, 0], z1[:, 1], ".", color="tab:blue", ms=0.6)
    for i in range(z2w.shape[0]):
        ax.plot(z2w[i, :, 0], z2w[i, :, 1], ".", color="tab:green", ms=0.6)
        p, q = res.p1[i], res.p2_in_1[i]
        ax.plot([p[0], q[0]], [p[1], q[1]], "o-", color="tab:red", ms=3, lw=1.2)
    ax.set(aspect="equal", title="closest points, Eq. (43)-(44)")
    fig.tight_layout()
    fig.savefig(out / f"{Path(__file__).stem}.png", dpi=80)
    plt.close(fig)


if __name__ == "__main__":
    import json

    print(json.dumps(run(Path("out/cookbook")), indent=1))
