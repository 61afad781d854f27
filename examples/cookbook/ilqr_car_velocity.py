"""Parking a car with velocity or acceleration inputs by iLQR (seed 004 §9.15; the cookbook's
``iLQR_car.py``).

Two kinematic cars with wheelbase ``ℓ = 0.5``, discretized by explicit Euler (Eq. 192) with ``Δt = 0.15``:

* velocity input (:class:`controllers.systems.car_velocity.CarVelocity`, Eq. 118): ``x = [x₁, x₂, θ, ϕ]``,
  ``u = [u₁, u₂]`` the rear-wheel speed and the steering rate;
* acceleration input (:class:`controllers.systems.Car`, Eq. 119): ``x = [x₁, x₂, θ, v, ϕ]``, ``u₁`` the
  rear-wheel acceleration, so the speed is a state and changes smoothly.

Both park at the origin facing ``θ = 0`` after ``T = 30`` steps, from a batch of four start poses: the cost
tracks the zero state at the last step (``Q_T = 10³ I``: pose, steering angle and, for the second car, speed),
keeps the steering angle within ``|ϕ| ≤ 0.6`` rad at every step by the bounded-state residual of §9.2
(:func:`controllers.task_costs.cut`, weight 10³), and ``R = 10⁻² I``.

Checks, for each car: every element CONVERGED; the final pose within tolerance, ``‖(x₁, x₂)‖ ≤ 10⁻²`` and
``|θ| ≤ 10⁻²`` rad (and the acceleration car's final speed ``|v| ≤ 10⁻²``); the steering angle never beyond
0.6 rad by more than 0.01 (the bound is a penalty, and it is active: the values record a largest
steering angle at the bound).
"""

from __future__ import annotations

import math
from pathlib import Path

import torch

from controllers.ilqr import ILQROptions, ILQRProblem, ilqr
from controllers.systems.car import Car
from controllers.systems.car_velocity import CarVelocity
from controllers.task_costs import cut, on_joints, residual_cost, state, track

SECTION = "9.15"
TITLE = "Car steering: parking with velocity and acceleration inputs (iLQR)"

T, DT, LENGTH = 30, 0.15, 0.5
PHI_MAX = 0.6
STARTS = ((-2.0, 1.0, 0.0), (-1.5, -1.0, math.pi / 4), (-2.5, 0.5, -math.pi / 6), (-1.0, 1.5, -math.pi / 3))


def problem(car, dtype: torch.dtype = torch.float64) -> ILQRProblem:
    """Parking ``car`` (a :class:`CarVelocity` or a :class:`Car`) from :data:`STARTS`; the steering angle is
    the last state entry of both."""
    kw = dict(dtype=dtype)
    n = car.n
    x0 = torch.zeros(len(STARTS), n, **kw)
    x0[:, :3] = torch.tensor(STARTS, **kw)
    Q = torch.zeros(T + 1, n, n, **kw)
    Q[-1] = 1e3 * torch.eye(n, **kw)
    steer = on_joints(state(1), [n - 1], n)
    cost = residual_cost([(track(state(n), torch.zeros(n, **kw)), Q),
                          (cut(steer, -PHI_MAX, PHI_MAX), 1e3 * torch.eye(1, **kw))],
                         1e-2 * torch.eye(2, **kw))
    return ILQRProblem(car, cost, x0, T)


def run(out: Path | None = None) -> dict:
    opts = ILQROptions(max_iter=100)
    cars = {"velocity": CarVelocity(length=LENGTH, dt=DT), "acceleration": Car(length=LENGTH, dt=DT)}
    sols = {k: ilqr(problem(c), grad="none", options=opts) for k, c in cars.items()}
    checks, values = {}, {}
    for k, s in sols.items():
        xT = s.x[:, -1]
        pos, head = xT[:, :2].norm(dim=-1), xT[:, 2].abs()
        steer = s.x[..., -1].abs().amax(-1)
        speed = s.u[..., 0] if k == "velocity" else s.x[..., 3]
        ok = (pos <= 1e-2) & (head <= 1e-2)
        if k == "acceleration":
            ok = ok & (xT[:, 3].abs() <= 1e-2)
            values["acceleration_max_final_speed"] = float(xT[:, 3].abs().max())
        checks[f"{k}_converged"] = bool(s.status.converged.all())
        checks[f"{k}_parked"] = bool(ok.all())
        checks[f"{k}_steering_bounded"] = bool((steer <= PHI_MAX + 0.01).all())
        values.update({f"{k}_max_position_error": float(pos.max()),
                       f"{k}_max_heading_error": float(head.max()), f"{k}_max_steering": float(steer.max()),
                       f"{k}_min_speed": float(speed.min()),
                       f"{k}_max_iterations": int(s.status.iterations.max())})
    if out is not None:
        _plot(out, sols)
    return {"checks": checks, "values": values}


def _plot(out: Path, sols: dict) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    fig, axes = plt.subplots(1, 2, figsize=(7, 3.2), sharey=True)
    for ax, (k, s) in zip(axes, sols.items()):
        for b in range(s.x.shape[0]):
            x = s.x[b]
            ax.plot(x[:, 0], x[:, 1], "k-", lw=1)
            idx = torch.arange(0, T + 1, 5)
            ax.quiver(x[idx, 0], x[idx, 1], torch.cos(x[idx, 2]), torch.sin(x[idx, 2]), color="tab:blue",
                      scale=12, width=0.005)
        ax.plot(0, 0, "o", color="tab:red", ms=4)
        ax.set_aspect("equal")
        ax.set_title(f"§9.15 {k} input", fontsize=9)
    fig.tight_layout()
    fig.savefig(out / f"{Path(__file__).stem}.png", dpi=80)
    plt.close(fig)


if __name__ == "__main__":
    import json

    print(json.dumps(run(Path("out/cookbook")), indent=1))
