"""``liecontrol demo``: a batched SE(3) showcase that prints accuracy figures and writes plots.

1. **Geodesic interpolation of 4096 pose pairs at 64 instants in one call** — checked against its
   defining property (the body twist ``log(X(t)⁻¹ X(t + dt))/dt`` is constant along the path) and
   against the end poses.
2. **Averaging noisy poses**: 512 independent clouds of 200 noisy observations each of an unknown
   pose, averaged on the group by Gauss-Newton (the Karcher mean, ``M ← M exp(mean log(M⁻¹ X_i))``);
   the error to the true pose is compared with the naive average of rotation matrices projected back
   onto SO(3).
3. **Exactness at the edges**: exp∘log round trip at angles exactly 0, 1e-9 and π in float32 and float64.
4. **A differentiable controller**: 64 pendulums swung up at once by control-limited iLQR
   (|τ| ≤ 3 N m, too weak to lift the pendulum directly: it must pump), and the implicit gradient of
   each optimal cost with respect to its pendulum's length, checked by finite differences (an element
   whose solver switches between two local optima within ±h disagrees; the count says how many).

5. **What the toolkit is for: MPC and RL side by side.**  The pendulum swing-up task (Pendulum-v1's
   physics and reward) on hundreds of batched environments: the iLQR MPC expert with zero training and a
   PPO agent trained inside the demo (never downloaded; a fixed step budget), evaluated on the same
   held-out seeds by :func:`learning.evaluate` — success, return, final error, time per control step.

Results are printed and written to ``OUT/summary.json``; plots go to ``OUT/*.png`` (``--out``, default
``out/demo``).  Steps 4 and 5 show progress bars on stderr (``--quiet``: none).
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import torch

from liecontrol import _options
from liecontrol._progress import bar, sb3_callback
from torchlie import se3, so3

__all__ = ["add_arguments", "run", "karcher_mean_se3", "interpolation_check", "averaging_check",
           "swingup_check", "shared_bins", "cube_limits", "return_gap_note"]


add_arguments = _options.demo


def karcher_mean_se3(X: torch.Tensor, iters: int = 10, tol: float = 1e-12) -> tuple[torch.Tensor, int]:
    """Karcher mean of poses ``X (*B, N, 4, 4)`` over dim −3 by Gauss-Newton; returns (mean, iterations)."""
    M = X[..., 0, :, :]
    for k in range(1, iters + 1):
        step = se3.log(se3.compose(se3.inverse(M).unsqueeze(-3), X)).mean(-2)
        M = se3.compose(M, se3.exp(step))
        if step.abs().max() < tol:
            return M, k
    return M, iters


def interpolation_check(pairs: int, steps: int, gen: torch.Generator, dtype=torch.float64) -> dict:
    X0 = se3.random(pairs, generator=gen, dtype=dtype)
    X1 = se3.random(pairs, generator=gen, dtype=dtype)
    t = torch.linspace(0, 1, steps, dtype=dtype)
    t0 = time.perf_counter()
    path = se3.interpolate(X0.unsqueeze(1), X1.unsqueeze(1), t.unsqueeze(0))  # (pairs, steps, 4, 4)
    elapsed = time.perf_counter() - t0
    twist = se3.log(se3.compose(se3.inverse(path[:, :-1]), path[:, 1:])) * (steps - 1)
    direct = se3.log(se3.compose(se3.inverse(X0), X1))
    return {
        "pairs": pairs, "steps": steps, "seconds": elapsed,
        "twist_constancy_err": (twist - direct.unsqueeze(1)).abs().max().item(),
        "endpoint_err": max((path[:, 0] - X0).abs().max().item(), (path[:, -1] - X1).abs().max().item()),
        "_path": path[:3],
    }


def averaging_check(clouds: int, per_cloud: int, gen: torch.Generator, noise: float = 0.3,
                    dtype=torch.float64) -> dict:
    truth = se3.random(clouds, generator=gen, dtype=dtype)
    eps = noise * torch.randn(clouds, per_cloud, 6, generator=gen, dtype=dtype)
    eps = eps - eps.mean(1, keepdim=True)  # the sample mean of the noise is exactly 0: truth is the mean
    X = se3.compose(truth.unsqueeze(1), se3.exp(eps))
    t0 = time.perf_counter()
    M, iters = karcher_mean_se3(X, iters=20)
    elapsed = time.perf_counter() - t0
    karcher_err = se3.log(se3.compose(se3.inverse(truth), M)).norm(dim=-1)
    # naive: average the matrices, project the rotation onto SO(3)
    naive = X.mean(1)
    naive_R = so3.project(naive[..., :3, :3])
    naive_err = so3.log(truth[..., :3, :3].transpose(-1, -2) @ naive_R).norm(dim=-1)
    karcher_rot_err = so3.log(truth[..., :3, :3].transpose(-1, -2) @ M[..., :3, :3]).norm(dim=-1)
    return {
        "clouds": clouds, "per_cloud": per_cloud, "noise_rad": noise, "iterations": iters, "seconds": elapsed,
        "karcher_err_max": karcher_err.max().item(), "naive_rotation_err_mean": naive_err.mean().item(),
        "_karcher_err": karcher_err, "_naive_err": naive_err, "_karcher_rot_err": karcher_rot_err,
    }


def edge_check() -> dict:
    out = {}
    for dtype in (torch.float32, torch.float64):
        errs = []
        for th in (0.0, 1e-9, 1e-4, math.pi - 1e-9, math.pi):
            xi = torch.tensor([0.3, -0.2, 0.5, th * 0.6, th * 0.0, th * 0.8], dtype=torch.float64)
            X = se3.exp(xi).to(dtype)
            errs.append((se3.exp(se3.log(X)) - X).abs().max().item())
        out[str(dtype).replace("torch.", "")] = max(errs)
    return out


def _swingup_problem(x0: torch.Tensor, T: int, length):
    from controllers.costs import QuadraticCost
    from controllers.ilqr import ILQRProblem
    from controllers.systems import Pendulum

    dt = x0.dtype
    Q = torch.diag(torch.tensor([1.0, 0.1], dtype=dt))
    QT = torch.diag(torch.tensor([100.0, 10.0], dtype=dt))
    cost = QuadraticCost(Q=torch.cat((Q.expand(T, 2, 2), QT[None])), R=torch.tensor([[0.01]], dtype=dt),
                         x_ref=torch.tensor([math.pi, 0.0], dtype=dt))
    return ILQRProblem(Pendulum(length=length, damping=0.1, dt=0.05), cost, x0, T, u_lower=-3.0, u_upper=3.0)


def swingup_check(batch: int, gen: torch.Generator, T: int = 100, quiet: bool = True) -> dict:
    """Control-limited iLQR swing-up of ``batch`` pendulums and d(cost)/d(length) two ways (a progress bar
    over the three solves unless ``quiet``)."""
    from controllers.ilqr import ILQROptions, ilqr

    x0 = 0.5 * (torch.rand(batch, 2, generator=gen, dtype=torch.float64) - 0.5)
    # tight tolerances: the finite-difference check needs solutions converged far below its step
    opts = ILQROptions(max_iter=300, tol=1e-11, tol_cost=0.0)
    # one length per pendulum, so one backward pass gives every element's own derivative
    length = torch.ones(batch, dtype=torch.float64, requires_grad=True)
    progress = bar(3, "[4] iLQR solves (swing-up, then length +-h)", quiet, unit="solve")
    t0 = time.perf_counter()
    sol = ilqr(_swingup_problem(x0, T, length), options=opts)
    elapsed = time.perf_counter() - t0
    progress.update()
    (grad,) = torch.autograd.grad(sol.cost.sum(), length)
    h = 1e-5
    with torch.no_grad():
        plus, minus = (ilqr(_swingup_problem(x0, T, length.detach() + s * h), options=opts, grad="none").cost
                       for s in (1, -1))
        progress.update(2)
    progress.close()
    fd = (plus - minus) / (2 * h)
    rel = (grad - fd).abs() / fd.abs().clamp_min(1e-12)
    x = sol.x.detach()
    upright = ((x[:, -1, 0] - math.pi).abs() < 0.1) & (x[:, -1, 1].abs() < 0.5)
    return {"batch": batch, "T": T, "seconds": elapsed, "converged": int(sol.status.converged.sum()),
            "upright": int(upright.sum()), "max_abs_u": float(sol.u.detach().abs().max()),
            "clamped_fraction": float(sol.clamped.double().mean()),
            "grad_length_median_rel_err": float(rel.median()),
            "grad_length_agree_1e-6": int((rel < 1e-6).sum()),
            "grad_length_example": (float(grad[0]), float(fd[0])),
            "_x": x[:8], "_u": sol.u.detach()[:8]}


_EVAL_SEED = 1_000_000  # held-out evaluation seeds: disjoint from every training seed of learning.baselines


def mpc_vs_rl(envs: int, ppo_steps: int, seed: int = 0, quiet: bool = True) -> dict:
    """The MPC expert (zero training) and a PPO agent trained here for ``ppo_steps`` steps, evaluated on
    the same ``envs`` held-out pendulum swing-ups in one batch each (section 5 of the module docstring);
    progress bars of the evaluations and the training unless ``quiet``."""
    from learning.baselines import make_agent
    from learning.evaluate import evaluate

    task = "PendulumSwingUp"
    kw = dict(num_envs=envs, episodes=envs, seed=_EVAL_SEED, progress=not quiet)
    t0 = time.perf_counter()
    mpc = evaluate("mpc", task, **kw)
    t_mpc = time.perf_counter() - t0
    t0 = time.perf_counter()
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # SB3's small networks train fastest on one thread (measured)
    try:
        agent = make_agent("ppo", task, seed=seed)
        with bar(ppo_steps, "[5] PPO training", quiet) as progress:
            agent.learn(total_timesteps=ppo_steps, callback=sb3_callback(progress))
    finally:
        torch.set_num_threads(threads)
    t_train = time.perf_counter() - t0
    rl = evaluate(agent, task, dtype=torch.float32, **kw)  # as trained: float32 observations
    out = {"task": task, "envs": envs, "ppo_steps": int(agent.num_timesteps), "ppo_train_s": t_train,
           "mpc_eval_s": t_mpc}
    for name, r in (("mpc", mpc), ("ppo", rl)):
        sm = r.summary()
        out[name] = {"success_rate": sm["success_rate"], "return_mean": sm["return"]["mean"],
                     "return_std": sm["return"]["std"], "final_error_median": sm["final_error"]["median"],
                     "step_ms_median": sm["step_ms"]["median"], "invalid": sm["invalid_count"]}
        out["_" + name] = r
    return out


def shared_bins(*samples, bins: int = 30):
    """Histogram bin edges spanning the finite values of every sample, so that histograms drawn with
    them compare bin by bin."""
    import numpy as np

    values = np.concatenate([np.asarray(x, dtype=float).ravel() for x in samples])
    values = values[np.isfinite(values)]
    return np.histogram_bin_edges(values if values.size else np.zeros(1), bins=bins)


def cube_limits(points, margin: float = 0.1):
    """``(low, high)`` of one cube holding every row of ``points (k, 3)``: equal axes for a 3-D plot."""
    import numpy as np

    p = np.asarray(points, dtype=float).reshape(-1, 3)
    centre = (p.min(0) + p.max(0)) / 2
    half = (1 + margin) * max(float((p.max(0) - p.min(0)).max()) / 2, 1e-9)
    return centre - half, centre + half


def return_gap_note(duel: dict, horizon: int | None = None) -> str | None:
    """One line saying why the MPC's mean return is below PPO's, or None when it is not."""
    mpc, ppo = duel["mpc"], duel["ppo"]
    if not mpc["return_mean"] < ppo["return_mean"]:
        return None
    if horizon is None:
        from learning.policies import DEFAULT_HORIZON

        horizon = DEFAULT_HORIZON.get(duel.get("task", ""), 30)
    return (f"MPC's mean return ({mpc['return_mean']:.0f}) is below PPO's ({ppo['return_mean']:.0f}): PPO "
            f"is trained to maximize this episode return, while the MPC, untrained, minimizes its own "
            f"{horizon}-step cost (the reward's weights with a 10x terminal weight) and swings up on a "
            f"different schedule; success (upright at the end): MPC {100 * mpc['success_rate']:.0f} %, "
            f"PPO {100 * ppo['success_rate']:.0f} %.")


def _save(fig, path: Path, files: list[str]) -> None:
    import matplotlib.pyplot as plt

    fig.savefig(path, dpi=110)
    plt.close(fig)
    files.append(str(path))


def _plot_interpolation(ax, interp: dict) -> None:
    import numpy as np

    paths = interp["_path"]
    for i, path in enumerate(paths):
        p = path[:, :3, 3].numpy()
        ax.plot(p[:, 0], p[:, 1], p[:, 2], color="0.5", lw=1, label=None if i else "geodesic (position)")
        for j, X in enumerate(path[::8]):
            o = X[:3, 3].numpy()
            for k, (c, name) in enumerate(zip("rgb", "xyz")):
                d = 0.25 * X[:3, k].numpy()
                ax.plot([o[0], o[0] + d[0]], [o[1], o[1] + d[1]], [o[2], o[2] + d[2]], color=c, lw=1.2,
                        label=None if i or j else f"pose frame: {name} axis")
        ax.scatter(*p[0], color="k", marker="o", s=30, label="start X0" if i == 0 else None)
        ax.scatter(*p[-1], color="k", marker="s", s=30, label="end X1" if i == 0 else None)
    lo, hi = cube_limits(np.concatenate([path[:, :3, 3].numpy() for path in paths]))
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_zlim(lo[2], hi[2])
    ax.set_box_aspect((1, 1, 1))
    ax.set_xlabel("x")
    ax.set_ylabel("y")
    ax.set_zlabel("z")
    ax.legend(fontsize=7, loc="upper left")
    ax.set_title(f"SE(3) geodesics (3 of {interp['pairs']}, computed in one call)")


def _plot_averaging(ax, avg: dict) -> None:
    import numpy as np
    from matplotlib.ticker import LogLocator

    naive = np.maximum(avg["_naive_err"].numpy(), 1e-18)
    karcher = max(float(avg["_karcher_rot_err"].max()), 1e-18)  # exactly 0 cannot sit on a log axis
    bins = np.geomspace(naive.min() / 1.1, naive.max() * 1.1, 30)
    ax.hist(naive, bins=bins, alpha=0.7, label="naive matrix average (projected onto SO(3))")
    ax.axvline(karcher, color="k", ls="--", label=f"Karcher mean: largest error ({karcher:.0e} rad)")
    ax.set_xscale("log")
    ax.set_xlim(karcher / 10, naive.max() * 10)
    ax.xaxis.set_major_locator(LogLocator(numticks=7))
    ax.set_xlabel("rotation error to the true pose [rad] (log scale)")
    ax.set_ylabel("clouds")
    ax.legend(fontsize=8, loc="upper center")
    ax.set_title(f"averaging {avg['clouds']} clouds of {avg['per_cloud']} noisy poses")


def _plot_duel(fig, a1, a2, duel: dict) -> None:
    import numpy as np

    from learning.evaluate import error_band

    runs = {name: duel["_" + name] for name in ("mpc", "ppo")}
    bins = shared_bins(*(r.returns for r in runs.values()))
    for name, color in (("mpc", "C0"), ("ppo", "C1")):
        r, m = runs[name], duel[name]
        label = f"{name.upper()}: success {100 * m['success_rate']:.0f} %, return {m['return_mean']:.0f}"
        a1.hist(r.returns, bins=bins, alpha=0.6, color=color, label=label)
        t = np.arange(r.error_curve.shape[1]) * 0.05
        median, lo, hi = error_band(r.error_curve)
        a2.plot(t, median, color=color, label=f"{name.upper()} median")
        a2.fill_between(t, lo, hi, color=color, alpha=0.2, label=f"{name.upper()} 10-90 % of episodes")
    a1.set_xlabel("episode return")
    a1.set_ylabel("episodes")
    a1.legend(fontsize=8)
    a2.set_xlabel("time [s]")
    a2.set_ylabel("|angle from upright| [rad]")
    a2.set_ylim(bottom=0)
    a2.legend(fontsize=8)
    fig.suptitle(f"pendulum swing-up on {duel['envs']} batched envs: MPC (no training) vs PPO "
                 f"({duel['ppo_steps']} steps, trained in the demo)")
    note = return_gap_note(duel)
    if note is not None:
        fig.text(0.5, 0.01, note, ha="center", va="bottom", fontsize=7, wrap=True)


def _plot(out: Path, interp: dict, avg: dict, swing: dict | None = None, duel: dict | None = None
          ) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files: list[str] = []
    fig = plt.figure(figsize=(6.5, 6))
    _plot_interpolation(fig.add_subplot(projection="3d"), interp)
    fig.tight_layout()
    _save(fig, out / "se3_interpolation.png", files)

    fig, ax = plt.subplots(figsize=(6.5, 4))
    _plot_averaging(ax, avg)
    fig.text(0.5, 0.01, "The noise of each cloud is constructed to average to zero, so the true pose is its "
             "exact Karcher mean:\nthe Karcher error is round-off; the naive average's is bias.",
             ha="center", va="bottom", fontsize=7)
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    _save(fig, out / "se3_averaging.png", files)

    if swing is not None:
        fig, axes = plt.subplots(2, 1, figsize=(6, 4.6), sharex=True)
        t = 0.05 * torch.arange(swing["_x"].shape[1])
        for xi, ui in zip(swing["_x"], swing["_u"]):
            axes[0].plot(t.numpy(), xi[:, 0].numpy(), lw=1)
            axes[1].step(t[:-1].numpy(), ui[:, 0].numpy(), where="post", lw=1)
        axes[0].axhline(math.pi, color="k", ls="--", lw=0.8)
        axes[0].set_ylabel("angle [rad]")
        axes[1].set_ylabel("torque [N m]")
        axes[1].set_xlabel("t [s]")
        axes[0].set_title(f"iLQR swing-up, |u| <= 3: {swing['upright']}/{swing['batch']} upright "
                          f"({min(8, swing['batch'])} shown)")
        fig.tight_layout()
        _save(fig, out / "pendulum_swingup.png", files)
    if duel is not None:
        fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4.4))
        _plot_duel(fig, a1, a2, duel)
        fig.tight_layout(rect=(0, 0.06, 1, 1))
        _save(fig, out / "mpc_vs_ppo.png", files)
    return files


def run(args: argparse.Namespace) -> int:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    gen = torch.Generator().manual_seed(args.seed)
    interp = interpolation_check(args.pairs, 64, gen)
    print(f"[1] geodesic interpolation: {interp['pairs']} pairs x {interp['steps']} instants in "
          f"{1e3 * interp['seconds']:.1f} ms; twist constancy error {interp['twist_constancy_err']:.1e}, "
          f"end-pose error {interp['endpoint_err']:.1e}")
    avg = averaging_check(args.clouds, 200, gen)
    print(f"[2] Karcher mean of {avg['clouds']} clouds x {avg['per_cloud']} poses "
          f"(noise {avg['noise_rad']} rad): {avg['iterations']} Gauss-Newton iterations, "
          f"{1e3 * avg['seconds']:.1f} ms; max error to the true pose {avg['karcher_err_max']:.1e} "
          f"(naive projected matrix average: mean rotation error {avg['naive_rotation_err_mean']:.1e} rad)")
    edges = edge_check()
    print(f"[3] exp(log(X)) round trip at angles 0, 1e-9, 1e-4, pi-1e-9, pi: float32 {edges['float32']:.1e}, "
          f"float64 {edges['float64']:.1e}")
    swing = swingup_check(args.pendulums, gen, quiet=args.quiet)
    print(f"[4] control-limited iLQR swing-up of {swing['batch']} pendulums (|u| <= 3, T = {swing['T']}): "
          f"{swing['upright']}/{swing['batch']} upright at the end, {swing['converged']} converged, "
          f"max |u| {swing['max_abs_u']:.3f}, {100 * swing['clamped_fraction']:.0f} % of controls on a "
          f"bound, {1e3 * swing['seconds']:.0f} ms; d(cost)/d(length) per pendulum, implicit vs finite "
          f"differences: median rel. err. {swing['grad_length_median_rel_err']:.1e}, "
          f"{swing['grad_length_agree_1e-6']}/{swing['batch']} agree to 1e-6 (e.g. "
          f"{swing['grad_length_example'][0]:.4f} vs {swing['grad_length_example'][1]:.4f})")
    print(f"[5] MPC vs RL: the MPC expert and PPO (trained here for about {args.budget_steps} steps, whole "
          f"rollouts) on {args.num_envs} batched pendulum swing-ups", flush=True)
    duel = mpc_vs_rl(args.num_envs, args.budget_steps, args.seed, quiet=args.quiet)
    print(f"[5] MPC vs RL on {duel['envs']} batched pendulum swing-ups (same held-out seeds; PPO trained "
          f"here for {duel['ppo_steps']} steps in {duel['ppo_train_s']:.0f} s):")
    print("    policy  success  return (mean ± std)  final |angle| (median)  ms per batched step")
    for name in ("mpc", "ppo"):
        m = duel[name]
        print(f"    {name.upper():<6}  {100 * m['success_rate']:5.1f} %  {m['return_mean']:8.1f} ± "
              f"{m['return_std']:<8.1f}  {m['final_error_median']:.1e}                 "
              f"{m['step_ms_median']:.2f}")
    note = return_gap_note(duel)
    if note is not None:
        print(f"    {note}")
    summary = {"interpolation": {k: v for k, v in interp.items() if not k.startswith("_")},
               "averaging": {k: v for k, v in avg.items() if not k.startswith("_")},
               "roundtrip_edges": edges,
               "swingup": {k: v for k, v in swing.items() if not k.startswith("_")},
               "mpc_vs_rl": {k: v for k, v in duel.items() if not k.startswith("_")}}
    files = [] if args.no_plots else _plot(out, interp, avg, swing, duel)
    (out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    for f in files + [str(out / "summary.json")]:
        print(f"wrote {f}")
    return 0
