"""``liecontrol reproduce me2``: seed 000 §4 — ME2 pose prediction over 300 ms horizons.

Two screw paths ``X*(α) = X_0 exp(α δ)`` of a Panda-like end effector (trajectory 1: 0.71 m and
0.94 rad; trajectory 2: 0.32 m and 0.90 rad, as in the paper), timed by a time-optimal trapezoidal
profile, sampled at Δt = 1 ms.  The ground-truth twists ``T*_k = log(X*_k⁻¹ X*_{k+1}) / Δt`` are
integrated exactly (Eq. 17) and predicted with ME2 over horizons that are reset to the ground truth at
every horizon start (Fig. 3), in the paper's world frame (Eq. 16, ``ξ = log X`` linearized at
``log X_0``) and in the local frame (``X = X_0 exp(Ω)``, ME2 recursion).  The paper does not give its
start poses; each path is run from a tilted start pose (rotation angle π/2, away from the cut locus of
``log``) and from the Panda's tool-down home orientation ``R = diag(1, -1, -1)`` (angle exactly π, on
the cut locus).

Outputs: Table 1 (printed), Fig. 2-4 as PNG under ``--out`` (default ``out/me2``), ``--json PATH``.
Timing: every horizon start of the path (sliding window, at least ``--timing-batch`` horizons, tiled)
predicted in one batched call by ME2 and by exact chaining, timed in the same run; per-step times are
the batched time divided by (horizons × steps).
"""

from __future__ import annotations

import argparse
import math
import statistics
import time
from dataclasses import dataclass
from pathlib import Path

import torch

from liecontrol import _options
from liecontrol.report import print_table, public, write_result
from liecontrol.reproduce._trajectory import (
    PANDA_LIMITS,
    alpha_limits,
    design_delta,
    ground_truth_twists,
    screw_path,
    trapezoid_profile,
)
from torchlie import magnus, se3, so3

__all__ = ["add_arguments", "run", "run_experiment", "start_poses", "path_specs", "pose_errors",
           "wobble_twists"]

_DTYPES = {"float64": torch.float64, "float32": torch.float32}


# ---------------------------------------------------------------------------------------------------------
# Scenario definition
# ---------------------------------------------------------------------------------------------------------


def _rot(axis: str, angle: float) -> torch.Tensor:
    v = {"x": [1.0, 0, 0], "y": [0, 1.0, 0], "z": [0, 0, 1.0]}[axis]
    return so3.exp(torch.tensor(v, dtype=torch.float64) * angle)


def _pose(R: torch.Tensor, p) -> torch.Tensor:
    X = torch.eye(4, dtype=torch.float64)
    X[:3, :3] = R
    X[:3, 3] = torch.tensor(p, dtype=torch.float64)
    return X


def start_poses() -> dict[str, torch.Tensor]:
    """The start poses (float64 ``(4, 4)``, base frame of a Panda, metres).

    ``tilted``: tool axis pointing forward, ``R = R_y(π/2)`` (rotation angle π/2, well inside (0, π));
    ``tool_down``: the Panda's home orientation ``diag(1, -1, -1)`` — rotation angle
    exactly π, on the cut locus of ``log``.
    """
    R_tilt = _rot("y", math.pi / 2)  # tool z-axis along world +x (pointing forward): angle π/2
    return {
        "tilted": _pose(R_tilt, [0.35, -0.30, 0.45]),
        "tool_down": _pose(torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64)),
                           [0.307, -0.30, 0.49]),
    }


@dataclass(frozen=True)
class PathSpec:
    """A path of the paper: world displacement [m] and body rotation vector [rad]."""

    name: str
    displacement: tuple[float, float, float]
    rotvec: tuple[float, float, float]


def _scaled(v, norm):
    n = math.sqrt(sum(c * c for c in v))
    return tuple(norm * c / n for c in v)


def path_specs() -> list[PathSpec]:
    """Trajectory 1 (‖p_f - p_0‖ = 0.71 m, 0.94 rad) and 2 (0.32 m, 0.90 rad); directions are ours."""
    return [
        PathSpec("traj-1", _scaled((0.15, 0.60, -0.10), 0.71), _scaled((0.3, 0.5, 0.8), 0.94)),
        PathSpec("traj-2", _scaled((0.20, 0.15, -0.15), 0.32), _scaled((-0.6, 0.2, 0.7), 0.90)),
    ]


# ---------------------------------------------------------------------------------------------------------
# Errors and prediction over reset horizons
# ---------------------------------------------------------------------------------------------------------


def wobble_twists(delta: torch.Tensor, prof, lin_amp: float = 0.05, rot_amp: float = 0.3,
                  freq_hz: float = 1.5) -> torch.Tensor:
    """A body-twist perturbation ``(K, 6)`` that does not commute with ``δ``.

    On the paper's screw paths every twist is parallel to ``δ``, so the twists commute, Ω = Σ Δt T_k
    exactly and the local-frame ME2 recursion is exact to rounding.  Adding this perturbation (a
    sinusoid of ``lin_amp`` m/s and ``rot_amp`` rad/s at ``freq_hz``, orthogonal to ``ρ_δ`` and ``φ_δ``,
    scaled by the speed profile so the motion still starts and ends at rest) makes the comparison of
    the two frames informative.
    """
    t = prof.t[:-1]
    env = prof.alpha_dot[:-1] / prof.v_peak
    s = torch.sin(2 * math.pi * freq_hz * t) * env
    e = torch.tensor([0.0, 0.0, 1.0], dtype=delta.dtype)

    def ortho(v):
        u = torch.linalg.cross(v, e)
        if float(torch.linalg.vector_norm(u)) < 1e-6 * float(torch.linalg.vector_norm(v)):
            u = torch.linalg.cross(v, torch.tensor([1.0, 0.0, 0.0], dtype=delta.dtype))
        return u / torch.linalg.vector_norm(u)

    w = torch.cat([lin_amp * ortho(delta[:3]), rot_amp * ortho(delta[3:])])
    return s[:, None] * w


def pose_errors(X_pred: torch.Tensor, X_ref: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Linear error ‖p_pred - p_ref‖ [m] and angular error ∠(R_predᵀ R_ref) [rad] of ``(*, 4, 4)`` poses."""
    lin = torch.linalg.vector_norm(X_pred[..., :3, 3] - X_ref[..., :3, 3], dim=-1)
    R = X_pred[..., :3, :3].transpose(-1, -2) @ X_ref[..., :3, :3]
    ang = torch.linalg.vector_norm(so3.log(R), dim=-1)
    return lin, ang


def _horizon_batch(X: torch.Tensor, T: torch.Tensor, starts: torch.Tensor, H: int):
    """Start poses ``(M, 4, 4)``, twists ``(M, H, 6)`` (zero-padded after the end) and a validity mask."""
    K = T.shape[0]
    Tp = torch.cat([T, T.new_zeros(H, 6)], dim=0)
    starts = starts.to(T.device)
    steps = torch.arange(H, device=T.device)
    idx = starts[:, None] + steps[None, :] + 1  # target index of each predicted step
    T_h = Tp[starts[:, None] + steps[None, :]]
    return X[starts], T_h, idx <= K, idx


def _stats(lin: torch.Tensor, ang: torch.Tensor) -> dict:
    lin_mm, ang_deg = lin * 1e3, torch.rad2deg(ang)
    return {
        "lin_avg_mm": float(lin_mm.mean()), "lin_max_mm": float(lin_mm.max()),
        "lin_std_mm": float(lin_mm.std()),
        "ang_avg_deg": float(ang_deg.mean()), "ang_max_deg": float(ang_deg.max()),
        "ang_std_deg": float(ang_deg.std()),
    }


def _predict_reset(X: torch.Tensor, T: torch.Tensor, dt: float, H: int) -> dict:
    """Errors of the three predictors over horizons of H steps, reset to ground truth at each start."""
    K = T.shape[0]
    starts = torch.arange(0, K, H)
    X0, T_h, valid, idx = _horizon_batch(X, T, starts, H)
    X_ex = magnus.integrate_exact(X0, T_h, dt)
    preds = {
        "world": magnus.predict_poses(X0, T_h, dt, "world", order=2),
        "local": magnus.predict_poses(X0, T_h, dt, "local", order=2),
        "world_closed_form": magnus.predict_poses(X0, T_h, dt, "world", order=None),
    }
    out = {"t": (idx[valid].to(X.dtype) * dt)}
    for k, Xp in preds.items():
        lin, ang = pose_errors(Xp, X_ex)
        out[k] = (lin[valid], ang[valid])
    lin, ang = pose_errors(X_ex, X[idx.clamp(max=K)])
    out["exact_vs_path"] = (lin[valid], ang[valid])
    return out


# ---------------------------------------------------------------------------------------------------------
# Timing
# ---------------------------------------------------------------------------------------------------------


def _time_batched(X: torch.Tensor, T: torch.Tensor, dt: float, H: int, batch: int, repeats: int,
                  dtype: torch.dtype) -> dict:
    """Per-step times [µs] of ME2 (world, local) and exact chaining on one batch of ≥ ``batch`` horizons."""
    K = T.shape[0]
    n = max(batch, K)
    starts = torch.arange(n) % K
    X0, T_h, _, _ = _horizon_batch(X, T, starts, H)
    X0, T_h = X0.to(dtype), T_h.to(dtype)
    fns = {
        "me2": lambda: magnus.predict_world(se3.log(X0), T_h, dt, order=2),
        "local": lambda: magnus.predict_local(T_h, dt, order=2),
        "exact": lambda: magnus.integrate_exact(X0, T_h, dt),
    }
    samples: dict[str, list[float]] = {k: [] for k in fns}
    with torch.no_grad():
        for f in fns.values():  # warm-up
            f()
        for _ in range(repeats):  # interleaved, so drift on a shared machine hits all three alike
            for k, f in fns.items():
                t0 = time.perf_counter()
                f()
                samples[k].append((time.perf_counter() - t0) * 1e6 / (n * H))
    out = {"horizons": n, "steps": H, "repeats": repeats, "dtype": str(dtype).replace("torch.", "")}
    for k, s in samples.items():
        out[f"{k}_avg_us"] = statistics.fmean(s)
        out[f"{k}_med_us"] = statistics.median(s)
        out[f"{k}_max_us"] = max(s)
    out["ratio_me2_over_exact"] = out["me2_med_us"] / out["exact_med_us"]
    out["ratio_local_over_exact"] = out["local_med_us"] / out["exact_med_us"]
    return out


# ---------------------------------------------------------------------------------------------------------
# Experiment
# ---------------------------------------------------------------------------------------------------------


def run_experiment(*, dt: float = 1e-3, horizon: int = 300, fig4_horizons=(10, 25, 50, 100, 200, 300, 500),
                   velocity_scale: float = 0.25, acceleration_scale: float = 0.1, timing_batch: int = 1000,
                   timing_horizon: int | None = None, repeats: int = 7,
                   timing_dtype: torch.dtype = torch.float64,
                   scenarios: tuple[str, ...] = ("tilted", "tool_down"), wobble: bool = True) -> dict:
    """Run the experiment; returns the JSON-ready result with the raw curves under ``"_curves"``."""
    limits = PANDA_LIMITS.scaled(velocity_scale, acceleration_scale)
    poses = start_poses()
    result: dict = {
        "dt": dt, "horizon_steps": horizon,
        "limits": {"v_lin_mps": limits.v_lin, "a_lin_mps2": limits.a_lin, "v_rot_radps": limits.v_rot,
                   "a_rot_radps2": limits.a_rot, "velocity_scale_of_panda": velocity_scale,
                   "acceleration_scale_of_panda": acceleration_scale},
        "start_poses": {k: {"p_m": v[:3, 3].tolist(), "R": v[:3, :3].tolist(),
                            "rotation_angle_rad": float(torch.linalg.vector_norm(so3.log(v[:3, :3])))}
                        for k, v in poses.items() if k in scenarios},
        "traj": [], "fig4": {"H": list(fig4_horizons)},
    }
    curves: dict = {}
    cases = []
    for scen in scenarios:
        X0 = poses[scen]
        for spec in path_specs():
            name = spec.name if scen == "tilted" else f"{spec.name}@{scen}"
            delta = design_delta(X0[:3, :3], torch.tensor(spec.displacement, dtype=torch.float64),
                                 torch.tensor(spec.rotvec, dtype=torch.float64))
            va, aa = alpha_limits(delta, limits)
            prof = trapezoid_profile(va, aa, dt)
            X = screw_path(X0, delta, prof.alpha)
            T = ground_truth_twists(X, dt)
            cases.append((name, scen, X0, delta, prof, X, T))
            if wobble and scen == "tilted":
                Tw = T + wobble_twists(delta, prof)
                Xw = torch.cat([X0[None], magnus.integrate_exact(X0, Tw, dt)], dim=0)
                cases.append((name + "+wobble", scen, X0, delta, prof, Xw, Tw))
    for name, scen, X0, delta, prof, X, T in cases:
        Xf = X[-1]
        R_angles = torch.linalg.vector_norm(so3.log(X[:, :3, :3]), dim=-1)
        res = _predict_reset(X, T, dt, horizon)
        entry = {
            "name": name, "start_pose": scen, "wobble": name.endswith("+wobble"),
            "disp_m": float(torch.linalg.vector_norm(Xf[:3, 3] - X0[:3, 3])),
            "rot_rad": float(torch.linalg.vector_norm(se3.log(se3.inverse(X0) @ Xf)[3:])),
            "duration_s": prof.duration, "steps": int(T.shape[0]),
            "peak_lin_speed_mps": prof.v_peak * float(torch.linalg.vector_norm(delta[:3])),
            "peak_rot_speed_radps": prof.v_peak * float(torch.linalg.vector_norm(delta[3:])),
            "path_angle_min_rad": float(R_angles.min()), "path_angle_max_rad": float(R_angles.max()),
            "world": _stats(*res["world"]), "local": _stats(*res["local"]),
            "world_closed_form": _stats(*res["world_closed_form"]),
            "exact_vs_path": _stats(*res["exact_vs_path"]),
        }
        w, lo = entry["world"], entry["local"]
        entry["local_improvement_lin"] = w["lin_avg_mm"] / max(lo["lin_avg_mm"], 1e-300)
        entry["local_improvement_ang"] = w["ang_avg_deg"] / max(lo["ang_avg_deg"], 1e-300)
        tim = _time_batched(X, T, dt, timing_horizon or horizon, timing_batch, repeats, timing_dtype)
        entry["timing"] = tim
        entry["time_ratio_me2_over_exact"] = tim["ratio_me2_over_exact"]
        entry["time_ratio_local_over_exact"] = tim["ratio_local_over_exact"]
        f4 = {f"{fr}_{q}": [] for fr in ("world", "local", "world_closed_form")
              for q in ("lin_avg_mm", "ang_avg_deg")}
        for Hh in fig4_horizons:
            r = _predict_reset(X, T, dt, Hh)
            for fr in ("world", "local", "world_closed_form"):
                f4[f"{fr}_lin_avg_mm"].append(float(r[fr][0].mean()) * 1e3)
                f4[f"{fr}_ang_avg_deg"].append(float(torch.rad2deg(r[fr][1]).mean()))
        result["fig4"][name] = f4
        result["traj"].append(entry)
        curves[name] = {"t": res["t"], "world": res["world"], "local": res["local"],
                        "alpha_t": prof.t, "alpha": prof.alpha}
    result["_curves"] = curves
    return result


# ---------------------------------------------------------------------------------------------------------
# Report
# ---------------------------------------------------------------------------------------------------------


def print_report(result: dict, file=None) -> None:
    print(f"seed 000 §4 — ME2 horizon prediction, Δt = {result['dt'] * 1e3:g} ms, "
          f"horizon = {result['horizon_steps']} steps, reset to ground truth at each horizon start",
          file=file)
    lim = result["limits"]
    print(f"Cartesian limits: {lim['v_lin_mps']:.3g} m/s, {lim['a_lin_mps2']:.3g} m/s², "
          f"{lim['v_rot_radps']:.3g} rad/s, {lim['a_rot_radps2']:.3g} rad/s² "
          f"(Panda limits × {lim['velocity_scale_of_panda']:g} in speed, × "
          f"{lim['acceleration_scale_of_panda']:g} in acceleration)", file=file)
    for k, v in result["start_poses"].items():
        print(f"start pose {k}: p = {[round(c, 3) for c in v['p_m']]} m, rotation angle "
              f"{v['rotation_angle_rad']:.4f} rad", file=file)
    rows = []
    for e in result["traj"]:
        t = e["timing"]
        rows.append({"trajectory": f"ref {e['name']}", "avg [µs]": t["exact_avg_us"],
                     "max [µs]": t["exact_max_us"], "rel [%]": 100.0})
        for fr, key, tk in (("world", "world", "me2"), ("local", "local", "local"),
                            ("world J_r⁻¹", "world_closed_form", None)):
            s = e[key]
            row = {"trajectory": f"{e['name']} {fr}",
                   "lin avg [mm]": s["lin_avg_mm"], "lin max [mm]": s["lin_max_mm"],
                   "lin std [mm]": s["lin_std_mm"], "ang avg [°]": s["ang_avg_deg"],
                   "ang max [°]": s["ang_max_deg"], "ang std [°]": s["ang_std_deg"]}
            if tk is not None:
                row.update({"avg [µs]": t[f"{tk}_avg_us"], "max [µs]": t[f"{tk}_max_us"],
                            "rel [%]": 100.0 * t[f"{tk}_med_us"] / t["exact_med_us"]})
            rows.append(row)
    cols = ["trajectory", "avg [µs]", "max [µs]", "rel [%]", "lin avg [mm]", "lin max [mm]", "lin std [mm]",
            "ang avg [°]", "ang max [°]", "ang std [°]"]
    print("\nTable 1 (compute time per predicted step, batched; errors vs exact integration Eq. 17)",
          file=file)
    print_table(rows, cols, file=file)
    print("\nduration, speeds and timing batch:", file=file)
    for e in result["traj"]:
        t = e["timing"]
        print(f"  {e['name']}: ‖Δp‖ = {e['disp_m']:.3f} m, rotation {e['rot_rad']:.3f} rad, "
              f"{e['duration_s']:.3f} s, peak {e['peak_lin_speed_mps']:.3f} m/s / "
              f"{e['peak_rot_speed_radps']:.3f} rad/s, path angle {e['path_angle_min_rad']:.3f}–"
              f"{e['path_angle_max_rad']:.3f} rad; local/world error ratio "
              f"1/{e['local_improvement_lin']:.3g} (lin), 1/{e['local_improvement_ang']:.3g} (ang); "
              f"timing: {t['horizons']} horizons × {t['steps']} steps, "
              f"{t['dtype']}, ME2/exact = {100 * t['ratio_me2_over_exact']:.1f} %, "
              f"local/exact = {100 * t['ratio_local_over_exact']:.1f} %", file=file)
    f4 = result["fig4"]
    print("\nFig. 4: average linear error [mm] vs horizon H [steps] (world ME2 / world J_r⁻¹ / local ME2)",
          file=file)
    rows4 = []
    for name in [e["name"] for e in result["traj"]]:
        row = {"trajectory": name}
        c = f4[name]
        for H, w, cf, lo in zip(f4["H"], c["world_lin_avg_mm"], c["world_closed_form_lin_avg_mm"],
                                c["local_lin_avg_mm"]):
            row[f"H={H}"] = f"{w:.3g}/{cf:.3g}/{lo:.2g}"
        rows4.append(row)
    print_table(rows4, ["trajectory"] + [f"H={H}" for H in f4["H"]], file=file)


def save_figures(result: dict, out: Path) -> list[Path]:
    """Fig. 2 (α(t)), Fig. 3 (errors along the paths) and Fig. 4 (average error vs H) as PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    curves = result["_curves"]
    names = list(curves)
    paths = []

    fig, ax = plt.subplots(figsize=(6, 3.5))
    for n in names:
        if "@" not in n and "+" not in n:
            ax.plot(curves[n]["alpha_t"].numpy(), curves[n]["alpha"].numpy(), label=n)
    ax.set_xlabel("t [s]")
    ax.set_ylabel("α")
    ax.set_title("Fig. 2: normalized α(t), time-optimal trapezoidal velocity")
    ax.legend()
    fig.tight_layout()
    paths.append(out / "fig2_alpha.png")
    fig.savefig(paths[-1], dpi=120)
    plt.close(fig)

    fig, axes = plt.subplots(len(names), 2, figsize=(11, 2.6 * len(names)), squeeze=False)
    for i, n in enumerate(names):
        c = curves[n]
        t = c["t"].numpy()
        panels = ((0, 1e3, "linear error [mm]"), (1, 180 / math.pi, "angular error [°]"))
        for j, (idx, scale, unit) in enumerate(panels):
            ax = axes[i, j]
            for fr, style in (("world", "-"), ("local", "-")):
                ax.semilogy(t, (c[fr][idx] * scale).clamp(min=1e-12).numpy(), style, lw=0.8, label=fr)
            ax.set_ylabel(unit)
            ax.set_title(n, fontsize=9)
            if i == len(names) - 1:
                ax.set_xlabel("t [s]")
            ax.legend(fontsize=7)
    fig.suptitle(f"Fig. 3: ME2 prediction error, horizon {result['horizon_steps']} steps, "
                 "reset to ground truth (log scale, floored at 1e-12)")
    fig.tight_layout()
    paths.append(out / "fig3_error_along_path.png")
    fig.savefig(paths[-1], dpi=120)
    plt.close(fig)

    f4 = result["fig4"]
    fig, axes = plt.subplots(1, 2, figsize=(13, 4.2))
    H_ms = [h * result["dt"] * 1e3 for h in f4["H"]]
    colors = plt.get_cmap("tab10")
    for i, n in enumerate(names):
        styles = (("world", "-o"), ("local", "--s")) + ((("world_closed_form", ":"),) if "+" not in n else ())
        for fr, ls in styles:
            kw = {"color": colors(i % 10), "ms": 3, "label": f"{n} {fr.replace('_closed_form', ' J_r⁻¹')}"}
            axes[0].loglog(H_ms, [max(v, 1e-15) for v in f4[n][f"{fr}_lin_avg_mm"]], ls, **kw)
            axes[1].loglog(H_ms, [max(v, 1e-15) for v in f4[n][f"{fr}_ang_avg_deg"]], ls, **kw)
    axes[0].set_ylabel("average linear error [mm]")
    axes[1].set_ylabel("average angular error [°]")
    for ax in axes:
        ax.set_xlabel("horizon [ms]")
        ax.grid(True, which="both", lw=0.3)
    axes[1].legend(fontsize=7, loc="center left", bbox_to_anchor=(1.02, 0.5))
    fig.suptitle("Fig. 4: average error vs horizon length (world ME2: solid, world closed-form J_r⁻¹: "
                 "dotted, local ME2: dashed — exact to rounding on the paper's paths)", fontsize=10)
    fig.tight_layout()
    paths.append(out / "fig4_error_vs_horizon.png")
    fig.savefig(paths[-1], dpi=120)
    plt.close(fig)
    return paths


# ---------------------------------------------------------------------------------------------------------
# CLI
# ---------------------------------------------------------------------------------------------------------




add_arguments = _options.reproduce_me2


def run(args: argparse.Namespace) -> int:
    result = run_experiment(
        dt=args.dt, horizon=args.horizon, fig4_horizons=tuple(args.fig4_horizons),
        velocity_scale=args.velocity_scale, acceleration_scale=args.acceleration_scale,
        timing_batch=args.timing_batch, timing_horizon=args.timing_horizon, repeats=args.repeats,
        timing_dtype=_DTYPES[args.timing_dtype],
        scenarios=("tilted",) if args.no_cut_locus else ("tilted", "tool_down"), wobble=not args.no_wobble,
    )
    print_report(result)
    if not args.no_plots:
        for p in save_figures(result, Path(args.out)):
            print(f"wrote {p}")
    if args.json:
        print(f"wrote {write_result(args.json, public(result))}")
    return 0
