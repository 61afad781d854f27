"""Karcher means of noisy SPD matrices and of noisy quaternions (seed 004 §12.3).

Story. A robot measures the same stiffness ellipsoid many times (3×3 SPD matrices) and the same tool
orientation many times (unit quaternions, (w, x, y, z)). Both live on curved manifolds: averaging the
raw numbers is the wrong thing — the arithmetic mean of SPD matrices is "swollen" (biased toward
larger determinants), and averaging quaternions ignores that q and −q are one rotation.

The seed's recipe is the Gauss–Newton iteration for the Karcher (Fréchet) mean

    u = 1/N Σ_n Log_μ(x_n),     μ ← Exp_μ(u),

with the affine-invariant Exp/Log of SPD matrices (Eq. 185–186) and the sphere Exp/Log on S³
(Eq. 180–181). For these homogeneous manifolds it converges in a handful of iterations.

Steps:
1. parameters — number of samples, noise levels, seed (an explicit torch.Generator);
2. data — samples X_n = Exp_M(ε_n) around a known SPD matrix M (ε_n Gaussian in the whitened tangent
   coordinates), and q_n = q0 ⊗ exp(ω_n / 2) around a known rotation with random signs ±q_n;
3. solve — ``karcher_mean`` (torchlie.manifolds.statistics) on ``SPD(3)`` and on ``Sphere(3)``
   (after ``hemisphere_align``), both from ``torchlie.manifolds``;
4. report — the error of the Riemannian mean and of the naive Euclidean average against the truth,
   the iterations used, and (optionally, with matplotlib) the error after each Gauss–Newton iteration,
   saved as ``out/riemannian_mean/convergence.png``.

Run:  python examples/riemannian_mean.py [--samples 500] [--no-plots]
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import torch

from torchlie import so3
from torchlie.manifolds import SPD, Sphere, hemisphere_align, karcher_mean, spd_dist, sphere_dist

__all__ = ["main"]


def main(n_samples: int = 500, seed: int = 0, spd_noise: float = 0.3, rot_noise: float = 0.25,
         plot: bool = True, out_dir: str | Path = "out/riemannian_mean") -> dict:
    """Run the example; returns the errors, bounds and iteration counts (also printed)."""
    g = torch.Generator().manual_seed(seed)
    dt = torch.float64

    # ---- SPD(3): a stiffness-like ellipsoid M, samples X_n = Exp_M(ε_n) ------------------------
    spd = SPD(3)
    M = torch.tensor([[4.0, 1.0, 0.5], [1.0, 2.0, 0.3], [0.5, 0.3, 1.0]], dtype=dt)
    eps = spd_noise * torch.randn(n_samples, spd.tangent_size, generator=g, dtype=dt)
    Xs = spd.exp_at(M.expand(n_samples, 3, 3), eps)
    res_spd = karcher_mean(spd, Xs)
    err_spd = float(spd_dist(res_spd.mean, M))
    err_spd_euclid = float(spd_dist(Xs.mean(0), M))
    # the mean of N samples with whitened std σ has an error of about σ √(dim / N)
    bound_spd = 4 * spd_noise * math.sqrt(spd.dim / n_samples)

    # ---- S³: quaternions of R0 exp(ω_n), with random double-cover signs -------------------------
    R0 = so3.exp(torch.tensor([0.4, -2.0, 1.0], dtype=dt))
    Rs = R0 @ so3.exp(rot_noise * torch.randn(n_samples, 3, generator=g, dtype=dt))
    q = so3.to_quaternion(Rs)                                            # (w, x, y, z)
    signs = torch.where(torch.rand(n_samples, 1, generator=g) < 0.5, -1.0, 1.0).to(dt)
    q = hemisphere_align(q * signs, q[0] * signs[0])
    sphere = Sphere(3)
    res_q = karcher_mean(sphere, q)
    err_q = float(so3.angle(R0.mT @ so3.from_quaternion(res_q.mean)))
    q_euclid = torch.nn.functional.normalize(q.mean(0), dim=-1)
    err_q_euclid = float(so3.angle(R0.mT @ so3.from_quaternion(q_euclid)))
    bound_q = 4 * rot_noise * math.sqrt(3 / n_samples)

    out = {
        "spd": {"error": err_spd, "euclidean_error": err_spd_euclid, "bound": bound_spd,
                "iterations": int(res_spd.iterations), "converged": bool(res_spd.converged)},
        "quaternion": {"error_rad": err_q, "euclidean_error_rad": err_q_euclid, "bound_rad": bound_q,
                       "iterations": int(res_q.iterations), "converged": bool(res_q.converged)},
    }
    print(f"SPD(3), N={n_samples}, σ={spd_noise}: Karcher-mean error {err_spd:.4f} (affine-invariant), "
          f"arithmetic mean {err_spd_euclid:.4f}, bound {bound_spd:.4f}, "
          f"{out['spd']['iterations']} Gauss–Newton iterations")
    print(f"S³ quaternions, N={n_samples}, σ={rot_noise} rad: Karcher-mean error {err_q:.5f} rad, "
          f"normalized average {err_q_euclid:.5f} rad, bound {bound_q:.5f} rad, "
          f"{out['quaternion']['iterations']} iterations")

    if plot:
        try:
            import matplotlib
            matplotlib.use("Agg")
            import matplotlib.pyplot as plt
        except ImportError:                                  # matplotlib is optional here
            print("matplotlib not available; skipping the figure")
            return out
        ks = list(range(1, 9))
        e_spd = [float(spd_dist(karcher_mean(spd, Xs, max_iter=k).mean, res_spd.mean)) for k in ks]
        e_q = [float(sphere_dist(karcher_mean(sphere, q, max_iter=k).mean, res_q.mean)) for k in ks]
        fig, ax = plt.subplots(figsize=(5, 3.5))
        ax.semilogy(ks, [max(e, 1e-17) for e in e_spd], "o-", label="SPD(3)")
        ax.semilogy(ks, [max(e, 1e-17) for e in e_q], "s-", label="S³ (quaternions)")
        ax.set_xlabel("Gauss–Newton iterations")
        ax.set_ylabel("distance to the converged mean")
        ax.set_title("Karcher mean: convergence")
        ax.legend()
        fig.tight_layout()
        path = Path(out_dir)
        path.mkdir(parents=True, exist_ok=True)
        fig.savefig(path / "convergence.png", dpi=120)
        plt.close(fig)
        print(f"figure saved to {path / 'convergence.png'}")
    return out


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=500)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-plots", action="store_true")
    args = parser.parse_args()
    main(n_samples=args.samples, seed=args.seed, plot=not args.no_plots)
