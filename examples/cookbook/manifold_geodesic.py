"""Geodesics of a smoothly varying metric: minimum-kinetic-energy arm motion (seed 004 §12.6, Figure 48
left).

Parameters and system: a planar 3-link arm (lengths 2, 2, 1, unit masses) whose joint-space metric is its
mass matrix ``G(q) = M(q)`` (:meth:`controllers.systems.arm.PlanarArm.mass_matrix`), so that a displacement
``Δq`` costs ``Δqᵀ M(q) Δq`` — twice the kinetic energy of moving along it in unit time.  Three pairs of
joint configurations ``(q_0, q_1)`` are solved at once.

Solve: :func:`torchlie.manifolds.metric.geodesic` minimizes the discretized path energy
``E = Σ_k Δq_kᵀ M(q̄_k) Δq_k`` (``N = 32`` segments, ``M`` at the midpoints) over the interior points by
damped Newton, from the straight line in joint space — the baseline that ignores inertia (Figure 48's
dashed lines).  The same solver is then run on the Poincaré half-plane ``G(x) = I / y²``, whose geodesics
are known in closed form (semicircles centred on the x axis, length
``arccosh(1 + |x_1 - x_0|² / (2 y_0 y_1))``).

Checks: every geodesic is CONVERGED (Newton decrement certified at the returned path), its endpoints are
exactly ``q_0, q_1``, and its energy is at least 10 % below the linear interpolation's for every pair; on the
half-plane every point lies within 1e-4 of the semicircle and the length matches the closed form within
1e-4 (relative).  The plot shows the arm along both motions and the half-plane geodesics.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch

from controllers.systems.arm import PlanarArm
from torchlie.manifolds.metric import geodesic, path_energy

SECTION = "12.6"
TITLE = "Geodesics of a varying metric: minimum kinetic energy arm motion"

N = 32
ARM = PlanarArm(links=3, lengths=(2.0, 2.0, 1.0))


def poses(dtype=torch.float64) -> tuple[torch.Tensor, torch.Tensor]:
    """``(3, 3)`` start and goal joint configurations."""
    q0 = torch.tensor([[0.0, 0.0, 0.0], [math.pi / 2, -math.pi / 2, 0.3], [-0.5, 1.5, -1.0]], dtype=dtype)
    q1 = torch.tensor([[math.pi / 2, 1.0, 1.0], [-0.3, 1.2, -0.8], [1.5, -1.0, 1.2]], dtype=dtype)
    return q0, q1


def half_plane(x: torch.Tensor) -> torch.Tensor:
    """Poincaré half-plane metric ``I / y²`` ``(*, 2, 2)``."""
    return torch.eye(2, dtype=x.dtype, device=x.device) / (x[..., 1] ** 2)[..., None, None]


def run(out: Path | None = None) -> dict:
    q0, q1 = poses()
    geo = geodesic(ARM.mass_matrix, q0, q1, N)
    s = torch.linspace(0, 1, N + 1, dtype=q0.dtype)[:, None]
    line = q0.unsqueeze(-2) + s * (q1 - q0).unsqueeze(-2)
    e_line = path_energy(ARM.mass_matrix, line)
    ratio = geo.energy / e_line
    endpoints = bool((geo.path[:, 0] == q0).all() and (geo.path[:, -1] == q1).all())
    # the half-plane: semicircles centred on the x axis, closed-form lengths
    x0 = torch.tensor([[-1.0, 1.0], [0.0, 0.5], [1.0, 2.0]], dtype=torch.float64)
    x1 = torch.tensor([[1.0, 1.0], [2.0, 1.5], [-0.5, 0.3]], dtype=torch.float64)
    hp = geodesic(half_plane, x0, x1, 96)
    c = ((x1 ** 2).sum(-1) - (x0 ** 2).sum(-1)) / (2 * (x1[:, 0] - x0[:, 0]))
    rad = ((x0[:, 0] - c) ** 2 + x0[:, 1] ** 2).sqrt()
    circle_err = (((hp.path[..., 0] - c[:, None]) ** 2 + hp.path[..., 1] ** 2).sqrt() - rad[:, None]).abs()
    exact = torch.acosh(1 + ((x1 - x0) ** 2).sum(-1) / (2 * x0[:, 1] * x1[:, 1]))
    len_err = ((hp.length - exact).abs() / exact).max()
    if out is not None:
        _plot(out, geo.path, line, hp.path, c, rad)
    return {"checks": {"arm_geodesics_converged": bool(geo.converged.all()),
                       "arm_endpoints_exact": endpoints,
                       "energy_at_least_10pct_below_linear": bool((ratio <= 0.9).all()),
                       "half_plane_converged": bool(hp.converged.all()),
                       "half_plane_on_semicircle_1e-4": bool(circle_err.max() < 1e-4),
                       "half_plane_length_closed_form_1e-4": bool(len_err < 1e-4)},
            "values": {"max_energy_ratio_geodesic_over_linear": float(ratio.max()),
                       "min_energy_ratio_geodesic_over_linear": float(ratio.min()),
                       "max_energy_drop": float((e_line - geo.energy).max()),
                       "min_energy_drop": float((e_line - geo.energy).min()),
                       "max_newton_iterations": int(geo.iterations.max()),
                       "half_plane_max_circle_error": float(circle_err.max()),
                       "half_plane_max_length_rel_error": float(len_err)}}


def _plot(out: Path, path, line, hp, c, rad) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(8, 3.6))
    b = 0
    for k in range(0, N + 1, 4):
        pg, pl = ARM.fk(path[b, k]), ARM.fk(line[b, k])
        ax.plot(pl[:, 0], pl[:, 1], "--", color="tab:red", lw=0.8, alpha=0.6)
        ax.plot(pg[:, 0], pg[:, 1], "-", color="tab:blue", lw=1.0, alpha=0.8)
    eg, el = ARM.end_effector(path[b]), ARM.end_effector(line[b])
    ax.plot(el[:, 0], el[:, 1], "--", color="tab:red", lw=1.5, label="linear in q")
    ax.plot(eg[:, 0], eg[:, 1], "-", color="tab:blue", lw=1.5, label="geodesic of M(q)")
    ax.set_aspect("equal")
    ax.legend(fontsize=7)
    ax.set_title("§12.6 kinetic-energy geodesic", fontsize=9)
    th = torch.linspace(0, math.pi, 200, dtype=hp.dtype)
    for i in range(hp.shape[0]):
        bx.plot(c[i] + rad[i] * torch.cos(th), rad[i] * torch.sin(th), color="0.8", lw=1)
        bx.plot(hp[i, :, 0], hp[i, :, 1], ".", ms=2)
    bx.axhline(0, color="k", lw=0.5)
    bx.set_aspect("equal")
    bx.set_title("half-plane G = I/y²: semicircles", fontsize=9)
    fig.tight_layout()
    fig.savefig(out / f"{Path(__file__).stem}.png", dpi=80)
    plt.close(fig)


if __name__ == "__main__":
    import json

    print(json.dumps(run(Path("out/cookbook")), indent=1))
