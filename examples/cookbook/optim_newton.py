"""Gradient descent vs Newton's method, 1-D and 2-D (seed 004 §3.1-3.2; the cookbook's ``Newton_method1D.py``
/ ``Newton_method2D.py``).

Parameters: two smooth costs with one minimum each, not quadratic (so Newton's method needs several steps),
and a batch of starting points for each:

* 1-D: ``c(x) = x⁴/4 − x + ½ e^{−x}``, 6 starts in ``[−2, 3]``;
* 2-D: ``c(x) = ½ (x₁ − 1)² + 10 (x₂ − ½ x₁²)² + 0.1 x₂⁴`` (a bent valley), 8 starts on a circle of radius 2.

Solve: :func:`controllers.optim.gradient_descent` (``x_{k+1} = x_k − α g(x_k)``, §3.1) and
:func:`controllers.optim.newton` (``x_{k+1} = x_k − α H(x_k)⁻¹ g(x_k)``, Eq. 9), both with the backtracking
line search of Algorithm 1 (``α = 1`` halved until the cost decreases), every start of a cost in one
batched call; gradients and Hessians by :mod:`torch.func`.

Reference: the minimizer found by a dense-grid search (a grid over ``[−3, 3]ⁿ``, then finer grids around the
best point, down to a spacing of ``1e-6``).

Plot: the 1-D cost with both iterate sequences from one start, and the 2-D contours with the paths (the
first steps of gradient descent from one start, Newton from two).

Checks:
  * ``gd_reaches_grid_minimizer`` / ``newton_reaches_grid_minimizer``: every start converged (gradient norm
    below its tolerance at the returned point: ``1e-6`` for gradient descent, ``1e-10`` for Newton) and lies
    within ``1e-4`` of the grid minimizer;
  * ``newton_far_fewer_iterations``: the most iterations any start needs with Newton, times 5, is below the
    fewest any start needs with gradient descent.
"""

from __future__ import annotations

from pathlib import Path

import torch

SECTION = "3.2"
TITLE = "Gradient descent vs Newton's method (1-D and 2-D)"

F64 = torch.float64


def cost_1d(x: torch.Tensor) -> torch.Tensor:
    """``(*B, 1) -> (*B,)``."""
    x = x[..., 0]
    return 0.25 * x ** 4 - x + 0.5 * torch.exp(-x)


def cost_2d(x: torch.Tensor) -> torch.Tensor:
    """``(*B, 2) -> (*B,)``."""
    x1, x2 = x[..., 0], x[..., 1]
    return 0.5 * (x1 - 1) ** 2 + 10 * (x2 - 0.5 * x1 ** 2) ** 2 + 0.1 * x2 ** 4


def grid_minimizer(cost, n: int, h_final: float = 1e-6) -> torch.Tensor:
    """Dense-grid search: a grid over ``[−3, 3]ⁿ``, then grids of 401 points a side over ``±2h`` around the
    best point so far (spacing ``h/100``), until the spacing is below ``h_final``."""
    m = 6001 if n == 1 else 601
    h = 6.0 / (m - 1)
    axes = [torch.linspace(-3.0, 3.0, m, dtype=F64)] * n
    while True:
        pts = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, n)
        best = pts[cost(pts).argmin()]
        if h <= h_final:
            return best
        axes = [torch.linspace(float(c) - 2 * h, float(c) + 2 * h, 401, dtype=F64) for c in best]
        h = 4 * h / 400


def starts() -> tuple[torch.Tensor, torch.Tensor]:
    x1 = torch.tensor([-2.0, -1.0, 0.0, 0.5, 2.0, 3.0], dtype=F64)[:, None]
    a = torch.arange(8, dtype=F64) * (2 * torch.pi / 8) + 0.3
    x2 = 2.0 * torch.stack([a.cos(), a.sin()], -1)
    return x1, x2


def run(out: Path | None = None) -> dict:
    """Solve; write ``out / "optim_newton.png"`` when ``out`` is given; return the outcomes."""
    from controllers.optim import gradient_descent, newton

    checks: dict[str, bool] = {"gd_reaches_grid_minimizer": True, "newton_reaches_grid_minimizer": True,
                               "newton_far_fewer_iterations": True}
    values: dict[str, float | int] = {}
    results = {}
    for name, cost, x0 in zip(("1d", "2d"), (cost_1d, cost_2d), starts()):
        ref = grid_minimizer(cost, x0.shape[-1])
        gd = gradient_descent(cost, x0, tol=1e-6, max_iter=5000)
        nt = newton(cost, x0, tol=1e-10)
        gd_err = float((gd.x - ref).norm(dim=-1).max())
        nt_err = float((nt.x - ref).norm(dim=-1).max())
        checks["gd_reaches_grid_minimizer"] &= bool(gd.converged.all()) and gd_err <= 1e-4
        checks["newton_reaches_grid_minimizer"] &= bool(nt.converged.all()) and nt_err <= 1e-4
        checks["newton_far_fewer_iterations"] &= int(nt.iterations.max()) * 5 < int(gd.iterations.min())
        values.update({f"gd_error_{name}": gd_err, f"newton_error_{name}": nt_err,
                       f"gd_iterations_min_{name}": int(gd.iterations.min()),
                       f"gd_iterations_max_{name}": int(gd.iterations.max()),
                       f"newton_iterations_max_{name}": int(nt.iterations.max())})
        results[name] = (cost, x0, ref)
    if out is not None:
        _plot(out, results)
    return {"checks": {k: bool(v) for k, v in checks.items()}, "values": values}


def _path(solver, cost, x0: torch.Tensor, steps: int, **kw) -> torch.Tensor:
    """Iterates ``x_1 .. x_K`` from one start; Algorithm 1 restarts at ``α = 1`` every iteration, so chained
    one-step calls give exactly the iterates of one long call."""
    xs = [x0]
    for _ in range(steps):
        r = solver(cost, xs[-1], max_iter=1, **kw)
        if int(r.iterations) == 0:
            break
        xs.append(r.x)
    return torch.stack(xs)


def _plot(out: Path, results: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from controllers.optim import gradient_descent, newton

    out.mkdir(parents=True, exist_ok=True)
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(8, 3.4))
    cost, x0, ref = results["1d"]
    s = x0[-1]
    t = torch.linspace(-2.2, 3.2, 400, dtype=F64)[:, None]
    a1.plot(t[:, 0], cost(t), "k-", lw=1)
    for solver, col, lab, kw in ((gradient_descent, "tab:blue", "gradient descent", {"tol": 1e-6}),
                                 (newton, "tab:red", "Newton", {"tol": 1e-10})):
        p = _path(solver, cost, s, 25, **kw)
        a1.plot(p[:, 0], cost(p), "o-", color=col, ms=3, lw=0.8, label=f"{lab} (first {len(p) - 1} steps)")
    a1.plot(ref[0], cost(ref[None])[0], "k*", ms=10, label="grid minimum")
    a1.set(xlabel="x", ylabel="c(x)", title="1-D", ylim=(-1.5, 20))
    a1.legend(fontsize=6)
    cost, x0, ref = results["2d"]
    g = torch.linspace(-2.5, 2.5, 200, dtype=F64)
    X, Y = torch.meshgrid(g, g, indexing="xy")
    a2.contour(X, Y, cost(torch.stack([X, Y], -1)).log1p(), 20, linewidths=0.5)
    runs = ((gradient_descent, "tab:blue", {"tol": 1e-6}, (0,)), (newton, "tab:red", {"tol": 1e-10}, (0, 4)))
    for solver, col, kw, which in runs:
        for i in which:
            p = _path(solver, cost, x0[i], 40, **kw)
            a2.plot(p[:, 0], p[:, 1], "o-", color=col, ms=2, lw=0.8)
    a2.plot(ref[0], ref[1], "k*", ms=10)
    a2.set(xlabel="x₁", ylabel="x₂", title="2-D (blue: GD, first 40 steps; red: Newton)", aspect="equal")
    fig.tight_layout()
    fig.savefig(out / f"{Path(__file__).stem}.png", dpi=80)
    plt.close(fig)


if __name__ == "__main__":
    import json

    print(json.dumps(run(Path("out/cookbook")), indent=1))
