"""Batched SE(3): one call handles a hundred thousand poses, exactly, even at rotation angle π.

Story. A tracker produces many poses at once (every particle of a filter, every sample of a
trajectory optimizer). torchlie treats them as one tensor ``(N, 4, 4)``: every function takes any
leading batch dims, and the twist is ``ξ = [v, ω]`` (linear velocity first).

Steps:
1. parameters — the number of poses, the dtype, a seed (an explicit torch.Generator);
2. data — random twists, half of them with a rotation angle of exactly π (where the textbook
   log formula divides by sin θ = 0);
3. solve — exp, log, compose, inverse, act and interpolate on the whole batch in one call each;
4. report — the largest error of each identity: exp(log X) = X, X X⁻¹ = I, X(p) = R p + t, and the
   geodesic's end points X(0) = X0, X(1) = X1.

Run:  python examples/se3_batched.py [--poses 100000]
"""

from __future__ import annotations

import argparse
import math

import torch

from torchlie import se3

__all__ = ["main"]


def main(n_poses: int = 100_000, seed: int = 0, dtype: torch.dtype = torch.float64) -> dict:
    """Run the example; returns the largest error of each identity (also printed)."""
    g = torch.Generator().manual_seed(seed)
    xi = torch.randn(n_poses, 6, generator=g, dtype=dtype)
    axis = torch.nn.functional.normalize(xi[: n_poses // 2, 3:], dim=-1)
    xi[: n_poses // 2, 3:] = math.pi * axis                    # rotation angle exactly π
    X = se3.exp(xi)                                              # (N, 4, 4)
    Y = se3.exp(torch.randn(n_poses, 6, generator=g, dtype=dtype))
    p = torch.randn(n_poses, 3, generator=g, dtype=dtype)
    eye = torch.eye(4, dtype=dtype)
    path = se3.interpolate(X, Y, torch.tensor([[0.0], [1.0]], dtype=dtype).unsqueeze(-1))  # (2, N, 4, 4)
    out = {
        "poses": n_poses,
        "exp_log_roundtrip": float((se3.exp(se3.log(X)) - X).abs().max()),
        "compose_inverse": float((se3.compose(X, se3.inverse(X)) - eye).abs().max()),
        "act_vs_matrix": float((se3.act(X, p) - (X[:, :3, :3] @ p[..., None]).squeeze(-1)
                                 - X[:, :3, 3]).abs().max()),
        "interpolation_ends": float(max((path[0] - X).abs().max(), (path[1] - Y).abs().max())),
    }
    print(f"{n_poses} poses ({n_poses // 2} at angle π), {str(dtype).replace('torch.', '')}:")
    for key, value in out.items():
        if key != "poses":
            print(f"  {key:<20} largest error {value:.1e}")
    return out


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--poses", type=int, default=100_000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    main(n_poses=args.poses, seed=args.seed)
