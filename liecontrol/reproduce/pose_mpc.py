"""``liecontrol reproduce pose-mpc``: seed 000's ME2 linear pose MPC on a Franka Panda, against seed 003's
SE(3) error-state MPC (issue 11 §4).

Three controllers (:class:`controllers.pose_mpc.PoseMPC`) with the same horizon, weights and twist bounds
command the body twist of the Panda's flange:

* ``world`` — the paper's linear MPC: state ``ξ = log X``, model ``ξ_{k+1} = ξ_k + Δt dexp⁻¹_{ξ_0} T_k``
  (Eq. 16 in the form of Eq. 5, ME2 series);
* ``local`` — the same idea in the local frame: ``X = X_0 exp(Ω)`` about the current pose, ME2 recursion;
* ``se3`` — Algorithm 1 of seed 003 on SE(3): error state ``log(X*⁻¹ X)`` on the exact model.

The arm is not the MPC's model: the commanded twist becomes joint velocities by damped least squares with
joint-limit avoidance in the null space (:func:`controllers.ik.resolved_rate_step`), scaled to the Panda's
joint speed limits, held for the control period; the pose is the forward kinematics of the joint angles
(pytorch-kinematics on the shipped URDF).  References are the screw paths of ``reproduce me2`` (same
start poses and trajectories, trapezoidal timing at a quarter of the Panda's Cartesian speed limits),
sampled at the MPC's 100 Hz, held at the end.  Each path is run twice: from the reference's start pose
(``on_path``), and from a start offset by 2.7 cm and 0.1 rad about the tool's x axis (``offset``).  From
the tool-down start pose (rotation angle exactly π) that rotation carries the arm across the cut locus of
``log``: the world-frame MPC sees an error of ~2π where the real one is 0.1 rad.

The arm's start configuration is chosen among IK solutions of the start pose (the ready pose, the IK seeds
and random starts): the one from which a feed-forward resolved-rate controller follows the whole path with
the smallest error (the others run into joint limits on the longer paths).  The report also runs the
batched IK benchmark of §4: 1,000 random reachable goals (FK of uniform random joint angles).

Outputs under ``--out`` (default ``out/pose_mpc``): ``errors.png``, ``cut_locus.png``, ``paths.png``,
``report.md``; ``--json PATH``.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import torch

from controllers.ik import resolved_rate_step, solve_ik
from controllers.pose_mpc import FRAMES, PoseMPC, twist_box
from controllers.systems.panda import Panda
from liecontrol import _options
from liecontrol.report import (
    markdown_cell,
    print_table,
    public,
    restores_threads,
    time_ms,
    write_result,
)
from liecontrol.reproduce._trajectory import (
    PANDA_LIMITS,
    alpha_limits,
    design_delta,
    ground_truth_twists,
    screw_path,
    trapezoid_profile,
)
from liecontrol.reproduce.me2 import path_specs, pose_errors, start_poses
from torchlie import se3, so3

__all__ = ["add_arguments", "run", "run_experiment", "reference", "start_configuration", "closed_loop"]

D = torch.float64
LABELS = {"world": "ME2 world (paper)", "local": "ME2 local", "se3": "SE(3) error-state"}
OFFSET = (0.02, -0.01, 0.015, 0.10, 0.0, 0.0)  # body twist of the offset start: 2.7 cm, 0.1 rad about tool x
STARTS = ("on_path", "offset")
IK_TARGET = 0.95


def reference(X0: torch.Tensor, spec, dt: float, velocity_scale: float, acceleration_scale: float):
    """The screw path of ``reproduce me2`` from ``X0``: poses ``(K+1, 4, 4)`` and body twists ``(K, 6)``."""
    limits = PANDA_LIMITS.scaled(velocity_scale, acceleration_scale)
    delta = design_delta(X0[:3, :3], torch.tensor(spec.displacement, dtype=D),
                         torch.tensor(spec.rotvec, dtype=D))
    va, aa = alpha_limits(delta, limits)
    prof = trapezoid_profile(va, aa, dt)
    X = screw_path(X0, delta, prof.alpha)
    return X, ground_truth_twists(X, dt)


def start_configuration(robot: Panda, X: torch.Tensor, T: torch.Tensor, dt: float, *, n_random: int = 60,
                        seed: int = 0) -> tuple[torch.Tensor, float]:
    """Joint angles at ``X[0]`` from which the arm can follow the path: IK from the ready pose, the IK seeds
    and ``n_random`` random starts (one batch), then every solution follows the path with feed-forward
    ``T_k`` plus a pose feedback through :func:`resolved_rate_step` (one batch); the one with the smallest
    worst position error wins.  Returns ``(q (7,), worst error [m])``."""
    g = torch.Generator().manual_seed(seed)
    starts = torch.cat([robot.home(D)[None], robot.ik_seeds(D), robot.random_q(n_random, g, D)])
    ik = solve_ik(robot, X[0].expand(starts.shape[0], 4, 4), starts, max_iter=100, pos_tol=1e-7, rot_tol=1e-7)
    ok = ik.success
    if not bool(ok.any()):
        raise ValueError("start_configuration: no IK solution for the start pose")
    q = ik.q[ok]
    worst = torch.zeros(q.shape[0], dtype=D)
    for k in range(T.shape[0]):
        e = se3.log(se3.inverse(robot.fk(q)) @ X[k])
        q, _ = resolved_rate_step(robot, q, T[k] + 0.5 * e / dt, dt)
        worst = torch.maximum(worst, pose_errors(robot.fk(q), X[k + 1])[0])
    best = int(worst.argmin())
    return ik.q[ok][best], float(worst[best])


def closed_loop(robot: Panda, mpc: PoseMPC, q0: torch.Tensor, X: torch.Tensor, T: torch.Tensor, steps: int
                ) -> dict:
    """Run ``mpc`` on the arm for ``steps`` periods along ``X (≥ steps+N+1, 4, 4)``, ``T (≥ steps+N, 6)``."""
    N, dt = mpc.N, mpc.dt
    q, warm = q0.clone(), None
    poses, twists, times, reasons, clamped = [robot.fk(q)], [], [], [], []
    for k in range(steps):
        Xc = poses[-1]
        t0 = time.perf_counter()
        sol = mpc.solve(Xc, X[k:k + N + 1], T[k:k + N], warm=warm)
        times.append(time.perf_counter() - t0)
        warm = torch.cat([sol.U[1:], sol.U[-1:]]).detach()
        q, _ = resolved_rate_step(robot, q, sol.u, dt)
        poses.append(robot.fk(q))
        twists.append(sol.u)
        reasons.append(int(sol.status.reason))
        clamped.append(bool(sol.clamped[0].any()))
    P = torch.stack(poses)
    lin, ang = pose_errors(P, X[:steps + 1])
    turn = torch.linalg.vector_norm(so3.log(P[:-1, :3, :3].transpose(-1, -2) @ P[1:, :3, :3]), dim=-1)
    return {"poses": P, "lin": lin, "ang": ang, "twists": torch.stack(twists),
            "solve_s": torch.tensor(times), "reasons": torch.tensor(reasons),
            "clamped": torch.tensor(clamped), "turned_rad": float(turn.sum())}


def _ik_benchmark(robot: Panda, goals: int) -> dict:
    """§4's IK figure: FK of ``goals`` uniform random configurations, solved from the ready pose (plus one
    seed lane), at most 30 iterations, 1 mm / 0.01 rad."""
    g = torch.Generator().manual_seed(11)
    target = robot.fk(robot.random_q(goals, g, D))
    t0 = time.perf_counter()
    r = solve_ik(robot, target, seeds=robot.ik_seeds(D)[:1], max_iter=30)
    secs = time.perf_counter() - t0
    s = r.success
    return {"goals": goals, "success_rate": float(s.double().mean()),
            "max_iterations": int(r.iterations.max()),
            "median_iterations": float(r.iterations[s].double().median()) if bool(s.any()) else None,
            "seconds": secs, "target_rate": IK_TARGET}


def _batch_ms(frame: str, N: int, dt: float, Q, R, lo, hi, X: torch.Tensor, T: torch.Tensor, batch: int,
              repeats: int) -> tuple[float, int]:
    """One batched solve of ``batch`` arms at windows along the path, each 2 mm / 2 mrad off it (a tracking
    state); returns (ms, number of arms whose plan has a twist on a bound)."""
    g = torch.Generator().manual_seed(3)
    K = T.shape[0]
    idx = torch.arange(batch) % max(K - N, 1)
    win = idx[:, None] + torch.arange(N + 1)[None]
    Xr, Tr = X[win], T[win[:, :N]]
    Xc = Xr[:, 0] @ se3.exp(0.002 * torch.randn(batch, 6, generator=g, dtype=D))
    mpc = PoseMPC(frame, N, dt, Q, R, u_lower=lo, u_upper=hi, grad="none")
    with torch.no_grad():
        active = int(mpc.solve(Xc, Xr, Tr).clamped.flatten(1).any(1).sum())
        return time_ms(lambda: mpc.solve(Xc, Xr, Tr), repeats=repeats, warmup=1), active


@restores_threads
def run_experiment(*, horizon: int = 30, dt: float = 0.01, velocity_scale: float = 0.25,
                   acceleration_scale: float = 0.1, weights=(100.0, 30.0, 1e-2), batch: int = 256,
                   ik_goals: int = 1000, threads: int = 1, quick: bool = False) -> dict:
    """Every (start pose, path, start) × frame; the JSON-ready result, with curves under ``"_curves"``."""
    torch.set_num_threads(threads)
    robot = Panda()
    qp, qr, r = weights
    Q = torch.tensor([qp] * 3 + [qr] * 3, dtype=D)
    R = torch.full((6,), r, dtype=D)
    lo, hi = twist_box(PANDA_LIMITS.v_lin, PANDA_LIMITS.v_rot)
    mpcs = {f: PoseMPC(f, horizon, dt, Q, R, u_lower=lo, u_upper=hi, grad="none") for f in FRAMES}
    specs = path_specs()[1:] if quick else path_specs()
    rows, curves, timing = [], {}, {}
    for pose_name, X0 in start_poses().items():
        for spec in specs:
            X, T = reference(X0, spec, dt, velocity_scale, acceleration_scale)
            K = T.shape[0]
            settle = K if quick else K + int(round(0.5 / dt))
            Xp = torch.cat([X, X[-1:].expand(settle + horizon + 1 - X.shape[0], 4, 4)])
            Tp = torch.cat([T, T.new_zeros(settle + horizon - K, 6)])
            q_path, feas = start_configuration(robot, X, T, dt, n_random=12 if quick else 60)
            case = f"{spec.name}@{pose_name}"
            for start in STARTS:
                q0 = q_path
                if start == "offset":
                    Xs = X[0] @ se3.exp(torch.tensor(OFFSET, dtype=D))
                    q0 = solve_ik(robot, Xs, q_path, max_iter=100, pos_tol=1e-7, rot_tol=1e-7).q
                for f in FRAMES:
                    res = closed_loop(robot, mpcs[f], q0, Xp, Tp, settle)
                    n_h = min(horizon, settle)  # skip one horizon: the offset's transient
                    lin, ang = res["lin"], res["ang"]
                    rows.append({
                        "path": case, "start": start, "frame": f, "method": LABELS[f],
                        "pos_max_mm": float(lin.max()) * 1e3,
                        "pos_rms_mm": float(lin.pow(2).mean().sqrt()) * 1e3,
                        "pos_max_after_mm": float(lin[n_h:].max()) * 1e3,
                        "ang_max_deg": math.degrees(float(ang.max())),
                        "ang_max_after_deg": math.degrees(float(ang[n_h:].max())),
                        "final_pos_mm": float(lin[-1]) * 1e3, "final_ang_deg": math.degrees(float(ang[-1])),
                        "turned_rad": res["turned_rad"],
                        "ms_median": float(res["solve_s"].median()) * 1e3,
                        "ms_max": float(res["solve_s"].max()) * 1e3,
                        "bound_active_frac": float(res["clamped"].double().mean()),
                        "not_converged": int((res["reasons"] != 0).sum()), "steps": settle,
                        "start_angle_rad": float(torch.linalg.vector_norm(so3.log(res["poses"][0, :3, :3]))),
                    })
                    curves[(case, start, f)] = res
            ref_turn = torch.linalg.vector_norm(so3.log(X[:-1, :3, :3].transpose(-1, -2) @ X[1:, :3, :3]),
                                                dim=-1)
            curves[(case, "ref")] = {"X": Xp, "turned_rad": float(ref_turn.sum()), "feasibility_m": feas}
            if not timing:
                reps = 3 if quick else 5
                for f in FRAMES:
                    ms, active = _batch_ms(f, horizon, dt, Q, R, lo, hi, X, T, batch, reps)
                    timing[f] = {"single_ms": None, "batch_ms": ms, "batch_bound_active": active}
    for f in FRAMES:
        med = torch.tensor([rw["ms_median"] for rw in rows if rw["frame"] == f]).median()
        timing[f]["single_ms"] = float(med)
    result = {
        "horizon": horizon, "dt": dt, "threads": threads, "quick": quick, "batch": batch,
        "velocity_scale": velocity_scale, "acceleration_scale": acceleration_scale,
        "weights": {"Q_translation": qp, "Q_rotation": qr, "R": r},
        "twist_bounds": {"v_max_mps": PANDA_LIMITS.v_lin, "w_max_radps": PANDA_LIMITS.v_rot,
                         "box_component": [float(hi[0]), float(hi[3])]},
        "offset": list(OFFSET), "rows": rows, "timing": timing,
        "reference_turn_rad": {k[0]: v["turned_rad"] for k, v in curves.items() if k[1] == "ref"},
        "start_feasibility_mm": {k[0]: 1e3 * v["feasibility_m"] for k, v in curves.items() if k[1] == "ref"},
        "ik": _ik_benchmark(robot, 100 if quick else ik_goals),
        "_curves": curves,
    }
    return result


_COLS = ("path", "start", "method", "pos_max_mm", "pos_rms_mm", "pos_max_after_mm", "ang_max_deg",
         "ang_max_after_deg", "turned_rad", "ms_median", "bound_active_frac", "not_converged")


def _findings(result: dict) -> list[str]:
    rows = result["rows"]
    out = []

    def pick(frame, start, pose):
        return [r for r in rows if r["frame"] == frame and r["start"] == start and r["path"].endswith(pose)]

    for pose in ("tilted", "tool_down"):
        for start in STARTS:
            parts = []
            for f in FRAMES:
                rs = pick(f, start, pose)
                if rs:
                    parts.append(f"{LABELS[f]} {max(r['pos_max_after_mm'] for r in rs):.3g} mm / "
                                 f"{max(r['ang_max_after_deg'] for r in rs):.3g}°")
            if parts:
                out.append(f"- {pose} start, {start}: worst error after the first horizon — "
                           + "; ".join(parts))
    bad = [r for r in rows if r["frame"] == "world" and r["ang_max_deg"] > 90]
    for r in bad:
        ref = result["reference_turn_rad"][r["path"]]
        out.append(f"- cut locus: world frame on {r['path']} ({r['start']}, start angle "
                   f"{r['start_angle_rad']:.4f} rad) turned the tool {r['turned_rad']:.2f} rad where the "
                   f"reference turns {ref:.2f} rad (attitude error up to {r['ang_max_deg']:.0f}°)")
    ik = result["ik"]
    met = ik["success_rate"] >= IK_TARGET and ik["max_iterations"] <= 30
    out.append(f"- batched IK, {ik['goals']} random reachable goals: {100 * ik['success_rate']:.1f} % solved "
               f"to 1 mm / 0.01 rad within {ik['max_iterations']} iterations "
               f"(target ≥ {100 * IK_TARGET:.0f} % within 30) — {'met' if met else 'MISSED'}")
    return out


def write_report(result: dict, out: Path, figures: list[Path]) -> Path:
    head = "| " + " | ".join(_COLS) + " |\n|" + "---|" * len(_COLS) + "\n"
    body = "".join("| " + " | ".join(markdown_cell(r.get(c)) for c in _COLS) + " |\n" for r in result["rows"])
    tim = result["timing"]
    trow = "".join(f"| {LABELS[f]} | {tim[f]['single_ms']:.3g} | {tim[f]['batch_ms']:.3g} "
                   f"({tim[f]['batch_bound_active']} with a bound active) |\n" for f in FRAMES)
    w, tb = result["weights"], result["twist_bounds"]
    text = f"""# End-effector pose MPC on a Franka Panda (seed 000 Eq. 16 vs seed 003 on SE(3))

## Setup
- Arm: Panda kinematics from pytorch-kinematics on the shipped URDF.  Commanded body twists become joint
  velocities by damped least squares (λ = 0.01) with joint-limit avoidance in the null space, scaled to
  the joint speed limits, held for Δt = {result['dt']} s; the pose is the FK of the joint angles (so the
  MPCs' model, X ← X exp(Δt T), is only approximately what the arm does).
- References: the screw paths of `reproduce me2` (traj-1: 0.71 m / 0.94 rad, traj-2: 0.32 m / 0.90 rad)
  from its two start poses (tilted: rotation angle π/2; tool_down: R = diag(1, −1, −1), angle exactly π),
  trapezoidal timing at {result['velocity_scale']} of the Panda's Cartesian speed limits, held at the end.
  `on_path`: the arm starts on the reference; `offset`: 2.7 cm and 0.1 rad about the tool x axis away
  (from tool_down that rotation crosses the cut locus of log).
- Three MPCs, horizon N = {result['horizon']} ({result['horizon'] * result['dt'] * 1e3:.0f} ms, the paper's
  horizon length), same weights Q = diag({w['Q_translation']}·I, {w['Q_rotation']}·I), R = {w['R']}·I, P = Q,
  twist bounds ‖v‖ ≤ {tb['v_max_mps']} m/s, ‖ω‖ ≤ {tb['w_max_radps']} rad/s (the Panda's) enforced by the
  inscribed box (|v_i| ≤ {tb['box_component'][0]:.3g}, |ω_i| ≤ {tb['box_component'][1]:.3g}); one box-QP
  solver for all three (closed form when no bound binds, certified box QP otherwise).
  - world: ξ = log X, ξ_{{k+1}} = ξ_k + Δt dexp⁻¹_{{ξ_0}} T_k (Eq. 16 as Eq. 5, ME2 series);
  - local: X = X_0 exp(Ω) about the current pose, ME2 recursion, linearized about the reference;
  - se3: seed 003 Algorithm 1 on SE(3), error log(X*⁻¹ X).
- Compute: wall-clock per MPC step, {result['threads']} thread(s), float64.
{'- QUICK run: one path per start pose, short runs, 100 IK goals.' if result['quick'] else ''}

## Tracking (errors in mm and degrees; "after" = after the first horizon)
{head}{body}
## Compute per step (ms)
| method | one arm (median) | {result['batch']} arms in one batched solve |
|---|---|---|
{trow}
## Findings
{chr(10).join(_findings(result))}

## What differs from the paper, and why
- The paper evaluates Eq. 16 as a predictor (open loop, reset every horizon: `reproduce me2`); it gives no
  closed-loop MPC numbers, so this table is the comparison the paper motivates, not a reproduction.
- Poses are kinematic (a velocity-controlled arm), no dynamics or torque limits.
- The paper does not give its start poses or weights; the start poses are those of `reproduce me2`.
"""
    if figures:
        text += "\n## Figures\n" + "".join(f"- `{p.name}`\n" for p in figures)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "report.md"
    path.write_text(text)
    return path


def save_figures(result: dict, out: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    curves, dt = result["_curves"], result["dt"]
    cases = sorted({k[0] for k in curves})
    paths = []
    fig, axes = plt.subplots(len(cases), 4, figsize=(15, 2.3 * len(cases)), squeeze=False)
    for i, case in enumerate(cases):
        for j, start in enumerate(STARTS):
            for f in FRAMES:
                c = curves.get((case, start, f))
                if c is None:
                    continue
                t = torch.arange(c["lin"].shape[0]) * dt
                axes[i, 2 * j].semilogy(t, c["lin"] * 1e3 + 1e-6, label=LABELS[f])
                axes[i, 2 * j + 1].semilogy(t, torch.rad2deg(c["ang"]) + 1e-6, label=LABELS[f])
            axes[i, 2 * j].set_ylabel(f"{case}\n{start}: pos [mm]")
            axes[i, 2 * j + 1].set_ylabel("attitude [deg]")
    axes[0, 0].legend(fontsize=7)
    for ax in axes[-1]:
        ax.set_xlabel("t [s]")
    fig.tight_layout()
    paths.append(out / "errors.png")
    fig.savefig(paths[-1], dpi=100)
    plt.close(fig)
    cut = [c for c in cases if c.endswith("tool_down")]
    if cut:
        fig, axes = plt.subplots(len(STARTS), len(cut), figsize=(5.5 * len(cut), 3.0 * len(STARTS)),
                                 squeeze=False)
        for i, start in enumerate(STARTS):
            for ax, case in zip(axes[i], cut):
                ref = curves[(case, "ref")]["X"]
                n = curves[(case, start, "world")]["poses"].shape[0]
                t = torch.arange(n) * dt
                ax.plot(t, torch.linalg.vector_norm(so3.log(ref[:n, :3, :3]), dim=-1), "k--", lw=0.8,
                        label="reference")
                for f in FRAMES:
                    P = curves[(case, start, f)]["poses"]
                    ax.plot(t, torch.linalg.vector_norm(so3.log(P[:, :3, :3]), dim=-1), label=LABELS[f])
                ax.axhline(math.pi, color="grey", lw=0.5)
                ax.set_title(f"{case}, {start}: rotation angle of X")
                ax.set_ylabel("‖log R‖ [rad] (π = cut locus)")
        for ax in axes[-1]:
            ax.set_xlabel("t [s]")
        axes[0, 0].legend(fontsize=7)
        fig.tight_layout()
        paths.append(out / "cut_locus.png")
        fig.savefig(paths[-1], dpi=100)
        plt.close(fig)
    fig = plt.figure(figsize=(4.5 * len(cases), 4.2))
    for i, case in enumerate(cases):
        ax = fig.add_subplot(1, len(cases), i + 1, projection="3d")
        ref = curves[(case, "ref")]["X"][:, :3, 3]
        ax.plot(ref[:, 0], ref[:, 1], ref[:, 2], "k--", lw=0.8, label="reference")
        for f in FRAMES:
            p = curves[(case, "offset", f)]["poses"][:, :3, 3]
            ax.plot(p[:, 0], p[:, 1], p[:, 2], lw=1.0, label=LABELS[f])
        ax.set_title(f"{case} (offset start)")
    fig.axes[0].legend(fontsize=7)
    fig.tight_layout()
    paths.append(out / "paths.png")
    fig.savefig(paths[-1], dpi=100)
    plt.close(fig)
    return paths


add_arguments = _options.reproduce_pose_mpc


def run(args: argparse.Namespace) -> int:
    result = run_experiment(horizon=args.horizon, dt=args.dt, velocity_scale=args.velocity_scale,
                            batch=args.batch, ik_goals=args.ik_goals, threads=args.threads, quick=args.quick)
    print_table(result["rows"], _COLS)
    for f in FRAMES:
        t = result["timing"][f]
        print(f"{LABELS[f]}: {t['single_ms']:.3g} ms per step (one arm), "
              f"{t['batch_ms']:.3g} ms for {result['batch']} arms")
    for line in _findings(result):
        print(line)
    out = Path(args.out)
    figures = [] if args.no_plots else save_figures(result, out)
    report = write_report(result, out, figures)
    for p in [*figures, report]:
        print(f"wrote {p}")
    if args.json:
        print(f"wrote {write_result(args.json, public(result))}")
    return 0
