"""``liecontrol learn costs|primitives|dynamics|manifold``: the learning-from-demonstration pipelines of
issue 26 (§2, §3, §4, §5; seed 004 §6, §7, §8, §12.3) end to end, each with checked outcomes, a figure, a
short ``report.md`` and a JSON record in ``--out`` (default ``out/learn/<pipeline>``).

``costs``
    Inverse optimal control (:mod:`learning.ioc`): demonstrations from an iLQR expert
    (:func:`learning.demos.expert_demos`) whose cost has known weights ``Q``, ``R``, terminal factor ``ρ`` and
    a via point (target and time); :func:`~learning.ioc.fit_cost` recovers them from the demos alone
    (``R_00 = 1`` fixed: the cost scale is unidentifiable).  Then minimal intervention (§7.7,
    :func:`~learning.ioc.minimal_intervention`) on the same demos with human-like variability
    (:func:`~learning.demos.time_warp`, :func:`~learning.demos.spatial_noise`): feedback gains low where
    the demos vary, high where they agree.
``primitives``
    Movement primitives as LQT (:mod:`learning.primitives`) on the handwriting letters of
    :func:`learning.demos.handwriting`: DMP-like reproduction of each demo and recovery from a mid-course
    push; ProMP-like distribution of each letter, its reproduction of the demos, minimal-intervention
    tracking through the same push, via-point conditioning and samples.  (``liecontrol bench primitives``
    compares the same primitives with DFKI's ``movement_primitives``; this command is the pipeline alone.)
``dynamics``
    Imitation of unknown dynamics (:func:`learning.imitation.imitation_study`, Amos et al. 2018's
    experiment): the pendulum's or cart-pole's parameters learned by backpropagating the imitation loss
    through the iLQR planner, next to system identification and MLP/LSTM behaviour cloning.  The JSON is a
    list of runs ``{"system", "n_train", "seed", "param_rel_err": {name: value}, "imitation_mse",
    "baselines": {...}, ...}`` (:data:`DYNAMICS_KEYS` first, then the extra keys of :data:`DYNAMICS_EXTRA`).
    The pendulum's ``(g, m, l)`` are not identifiable from controls; ``param_rel_err`` holds them and the
    identifiable combinations ``"g/l"`` and ``"1/(m l^2)"`` (the check is on those, ``"identifiable"``).
``manifold``
    Demonstrations on manifolds (:mod:`learning.manifold_demos`): per-step Gaussians (Karcher mean,
    tangent covariance) of SO(3) orientation demos (and of the same demos as S³ quaternions with random
    signs), the mean tracked by the on-manifold error-state MPC with precision ``(Σ_t + λI)⁻¹``, and a 3×3
    stiffness target (SPD, affine-invariant Karcher mean) learned from demos and compared with the true
    stiffness profile.

Every command prints a short table, returns exit status 1 when one of its checks fails (the checks and
their tolerances are listed in ``report.md`` and in the JSON under ``"checks"``/``"tolerances"``; for
``dynamics`` the JSON is the list of runs and the checks are in ``report.md`` only), 0 otherwise.  Non-finite
numbers are written as JSON ``null`` (:func:`learning.evaluate.jsonable`), never as ``NaN``.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import time
from pathlib import Path

import torch

from liecontrol._args import OptionError
from liecontrol._progress import bar, write
from liecontrol.report import fmt, markdown_cell, print_table, restores_threads

__all__ = ["PIPELINES", "DYNAMICS_KEYS", "DYNAMICS_EXTRA", "COSTS_TOL", "PRIMITIVES_TOL", "MANIFOLD_TOL",
           "DYNAMICS_TOL", "costs", "primitives", "dynamics", "dynamics_checks", "manifold", "run"]

PIPELINES = ("costs", "primitives", "dynamics", "manifold")
#: the keys every run of ``learn dynamics`` has, in this order (issue 26 §8) ...
DYNAMICS_KEYS = ("system", "n_train", "seed", "param_rel_err", "imitation_mse", "baselines")
#: ... followed by these (from :func:`learning.imitation.learn_dynamics`' record, where a non-finite value is
#: ``None`` and its path is listed in ``nonfinite_values``; ``history`` reduced to the loss and the largest
#: identifiable error per loss evaluation)
DYNAMICS_EXTRA = ("identifiable", "identifiable_rel_err_max", "params", "params_true", "params_init",
                  "imitation_mse_init", "unconverged", "expert_unconverged", "heldout_unconverged",
                  "evaluations", "final_loss", "u_limit", "n_test", "time_s", "nonfinite_values", "history")

COSTS_TOL = {"weights_rel_err": 1e-3, "via_target_err": 1e-3, "via_time_err_steps": 0.05,
             "reproduction_rms": 1e-4, "gain_ratio": 0.5}
#: positions in the letters' unit box: reproduction within 1 % of it; after the push of norm 0.14, the end
#: within 5 % of the push from the goal
PRIMITIVES_TOL = {"dmp_reproduction_rms": 1e-2, "dmp_push_to_goal": 7e-3, "promp_mean_rms": 1e-2,
                  "promp_push_to_goal": 7e-3, "via_mean_err": 1e-6, "via_sample_err": 1e-3}
#: ``stiffness_dist_factor``: the learned stiffness target's affine-invariant distance to the true profile,
#: averaged over time, at most this times ``σ √(m/N)`` (the expected norm of the mean of N offsets of std σ
#: in m = 6 tangent coordinates: the sampling error of the demos' own noise)
MANIFOLD_TOL = {"quaternion_gap_rad": 1e-8, "inside_95": 0.85, "tracking_final_over_initial": 0.01,
                "stiffness_dist_factor": 2.0}
STIFFNESS_NOISE = 0.3
#: ``manifold``: the tracking MPC starts at the first mean rotated by Exp of this rotation vector
START_OFFSET = (0.3, -0.2, 0.25)
DYNAMICS_TOL = {"identifiable_rel_err": 0.01}


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(int(seed))


# ---------------------------------------------------------------------------------------------- costs


def _ioc_problem(T: int = 30, dt: float = 0.1):
    """A planar double integrator whose control axes are rotated by 0.5 rad (so that a diagonal cost
    couples the two axes: one unidentifiable scale in all, fixed by ``R_00 = 1``), its goal and via-point
    precision."""
    from controllers.dynamics import LinearDynamics
    from controllers.lqt_cookbook import double_integrator

    kw = dict(dtype=torch.float64)
    di = double_integrator(2, dt)
    c, s = math.cos(0.5), math.sin(0.5)
    dyn = LinearDynamics(di.A, di.B @ torch.tensor([[c, -s], [s, c]], **kw))
    goal = torch.tensor([1.0, -0.5, 0.0, 0.0], **kw)
    P = torch.diag(torch.tensor([40.0, 40.0, 0.0, 0.0], **kw))
    return dyn, goal, P, T, dt


def _cost_model(q, r, rho: float, m, tau: float, learn: bool, T: int, goal, P):
    from learning.ioc import LQTCostModel, SPDWeight, ViaPoints

    vp = ViaPoints(m, torch.tensor([tau], dtype=m.dtype), P, kernel="gaussian", width=1.5,
                   learn_targets=learn, learn_times=learn)
    return LQTCostModel(SPDWeight(q, learn=learn), SPDWeight(r, fix_first=True, learn=learn), T, target=goal,
                        terminal_factor=rho, learn_terminal=learn, via_points=vp)


#: the expert's cost (``R_00 = 1``: the scale the learner fixes) and the learner's start
COSTS_TRUTH = {"Q": (2.0, 0.5, 0.3, 0.1), "R": (1.0, 3.0), "terminal_factor": 5.0, "via_target": (0.6, 1.1),
               "via_time": 12.4}
COSTS_INIT = {"Q": (1.0, 1.0, 1.0, 1.0), "R": (1.0, 1.0), "terminal_factor": 1.0, "via_target": (0.0, 0.0),
              "via_time": 10.0}


def _costs_model(spec: dict, learn: bool, T: int, goal, P):
    t = lambda v: torch.tensor(v, dtype=torch.float64)  # noqa: E731
    m = torch.cat([t(spec["via_target"]), t((0.0, 0.0))])[None]
    return _cost_model(t(spec["Q"]), t(spec["R"]), spec["terminal_factor"], m, spec["via_time"], learn, T,
                       goal, P)


def _learned_costs(w: dict) -> dict:
    return {"Q": w["Q"].diagonal().tolist(), "R": w["R"].diagonal().tolist(),
            "terminal_factor": float(w["terminal_factor"]), "via_target": w["via_targets"][0, :2].tolist(),
            "via_time": float(w["via_times"][0])}


def _costs_errors(learned: dict) -> dict:
    flat = lambda d: torch.tensor([*d["Q"], *d["R"], d["terminal_factor"]], dtype=torch.float64)  # noqa: E731
    ref = flat(COSTS_TRUTH)
    per = {k: [abs(a - b) / abs(b) for a, b in zip(learned[k], COSTS_TRUTH[k])] for k in ("Q", "R")}
    via = torch.tensor(learned["via_target"]) - torch.tensor(COSTS_TRUTH["via_target"])
    return {"weights_rel_err": float((flat(learned) - ref).norm() / ref.norm()),
            "Q_rel_err": per["Q"], "R_rel_err": per["R"],
            "terminal_factor_rel_err": abs(learned["terminal_factor"] / COSTS_TRUTH["terminal_factor"] - 1),
            "via_target_err": float(via.abs().max()),
            "via_time_err_steps": abs(learned["via_time"] - COSTS_TRUTH["via_time"])}


@restores_threads
def costs(*, n_demos: int = 8, steps: int = 80, seed: int = 0, warp: float = 0.1, noise: float = 0.02,
          threads: int = 1, quiet: bool = True) -> dict:
    """The ``costs`` pipeline (module docstring); returns its record (``"_fig"``: the figure's data)."""
    from controllers.ilqr import ILQRProblem
    from learning.demos import expert_demos, spatial_noise, time_warp
    from learning.ioc import fit_cost, minimal_intervention

    torch.set_num_threads(threads)
    t0 = time.perf_counter()
    dyn, goal, P, T, dt = _ioc_problem()
    g = _gen(seed)
    with bar(3, "learn costs", quiet, unit="stage") as b:
        x0 = 0.5 * torch.randn(n_demos, 4, generator=g, dtype=torch.float64)
        truth = _costs_model(COSTS_TRUTH, False, T, goal, P)
        with torch.no_grad():
            demos = expert_demos(ILQRProblem(dyn, truth(), x0, T), dt=dt)
        b.update()
        res = fit_cost(demos, dyn, _costs_model(COSTS_INIT, True, T, goal, P), steps=steps, solver="lifted")
        b.update()
        varied = spatial_noise(time_warp(demos, warp, g), noise, g, dims=[0, 1])
        mi = minimal_intervention(varied.x[..., :2], dt=dt, n_basis=10)
        b.update()
    learned = _learned_costs(res.model.weights())
    err = _costs_errors(learned)
    rms = float(((res.x - demos.x) ** 2).mean().sqrt())
    var, gain = mi.variance[:-1], mi.gain_norm
    i_var = int(var.argmax())
    ratio = float(gain[i_var] / gain.max())
    values = {**err, "reproduction_rms": rms, "final_loss": res.loss, "evaluations": len(res.history["loss"]),
              "not_converged_final": int((~res.status.converged).sum()),
              "expert_not_converged": int((~demos.frames["converged"]).sum()),
              "mi_most_varying_step": i_var, "mi_gain_at_most_varying": float(gain[i_var]),
              "mi_gain_max": float(gain.max()), "mi_gain_ratio": ratio}
    tol = COSTS_TOL
    checks = {"weights_recovered": err["weights_rel_err"] < tol["weights_rel_err"],
              "via_point_recovered": err["via_target_err"] < tol["via_target_err"]
              and err["via_time_err_steps"] < tol["via_time_err_steps"],
              "reproduction_matches_demos": rms < tol["reproduction_rms"],
              "all_solves_converged": bool(res.status.converged.all() and demos.frames["converged"].all()),
              "gains_low_where_demos_vary": ratio <= tol["gain_ratio"]}
    return {"pipeline": "costs", "settings": {"n_demos": n_demos, "steps": steps, "seed": seed, "warp": warp,
                                              "noise": noise, "T": T, "dt": dt},
            "truth": dict(COSTS_TRUTH), "init": dict(COSTS_INIT), "learned": learned, "checks": checks,
            "tolerances": dict(tol), "values": values, "loss_history": res.history["loss"],
            "minimal_intervention": {"variance": mi.variance.tolist(), "gain_norm": gain.tolist()},
            "time_s": time.perf_counter() - t0,
            "_fig": {"demos": demos.x, "repro": res.x, "varied": varied.x, "track": mi.tracking.x}}


def _costs_report(rec: dict) -> list[str]:
    tr, le, v = rec["truth"], rec["learned"], rec["values"]
    ini, c = rec["init"], markdown_cell
    rows = [(f"{k}_{i}{i}", tr[k][i], ini[k][i], le[k][i], c(e)) for k, errs in
            (("Q", v["Q_rel_err"]), ("R", v["R_rel_err"])) for i, e in enumerate(errs)]
    rows.append(("ρ (terminal)", tr["terminal_factor"], ini["terminal_factor"], le["terminal_factor"],
                 c(v["terminal_factor_rel_err"])))
    rows += [(f"via target m_{i}", tr["via_target"][i], ini["via_target"][i], le["via_target"][i],
              f"{c(abs(le['via_target'][i] - tr['via_target'][i]))} (abs)") for i in range(2)]
    rows.append(("via time τ [steps]", tr["via_time"], ini["via_time"], le["via_time"],
                 f"{c(v['via_time_err_steps'])} (abs)"))
    lines = ["| parameter | true | initial | learned | relative error |", "|---|---|---|---|---|"]
    lines += [f"| {a} | {c(b)} | {c(d)} | {c(e)} | {f} |" for a, b, d, e, f in rows]
    s = rec["settings"]
    return ([f"Demos: {s['n_demos']} optimal trajectories (one batched iLQR solve, `expert_demos`) of a "
             "planar double integrator with rotated control axes, T = 30, from random starts, under the cost "
             "of Eq. 59 with a via point spread by a Gaussian kernel (width 1.5 steps).  Learner "
             f"(`fit_cost`, L-BFGS, {s['steps']} iterations, batch least-squares LQT with autograd): every "
             "weight, the terminal factor, the via target and its time; `R_00 = 1` fixed (the cost scale is "
             "unidentifiable).", ""]
            + lines + ["", f"Final loss {c(v['final_loss'])} after {v['evaluations']} evaluations; "
                       f"reproduction RMS {c(v['reproduction_rms'])}.", "",
                       "Minimal intervention (§7.7): the same demos time-warped (strength "
                       f"{s['warp']}) and spatially varied (std {s['noise']}), a ProMP of their positions "
                       "tracked with precision (Σ_t + 10⁻⁶ I)⁻¹: gain ‖K_t‖ "
                       f"{markdown_cell(v['mi_gain_at_most_varying'])} where the demos vary most (step "
                       f"{v['mi_most_varying_step']}) against {markdown_cell(v['mi_gain_max'])} at most."])


def _costs_plot(rec: dict, path: Path) -> None:
    plt = _pyplot()
    f = rec["_fig"]
    fig, (a, b, c) = plt.subplots(1, 3, figsize=(12, 3.4))
    for i in range(f["demos"].shape[0]):
        a.plot(f["demos"][i, :, 0], f["demos"][i, :, 1], color="0.6", lw=2.5)
        a.plot(f["repro"][i, :, 0], f["repro"][i, :, 1], "k--", lw=1)
    a.plot(*rec["truth"]["via_target"], "o", color="tab:red", ms=9, mfc="none", label="true via point")
    a.plot(*rec["learned"]["via_target"], "x", color="tab:blue", ms=8, label="learned via point")
    a.set_aspect("equal")
    a.set_title("demos (grey), learned-cost optima (dashed)", fontsize=8)
    a.legend(fontsize=7)
    b.semilogy([max(v, 1e-32) for v in rec["loss_history"]])
    b.set_xlabel("loss evaluation")
    b.set_ylabel("IOC loss")
    b.set_title("fit_cost (L-BFGS)", fontsize=8)
    mi = rec["minimal_intervention"]
    c.plot(mi["variance"], color="tab:blue", label="demo variance tr Σ_t")
    c.set_xlabel("step")
    c.set_ylabel("variance", color="tab:blue")
    c2 = c.twinx()
    c2.plot(mi["gain_norm"], color="tab:red", label="‖K_t‖")
    c2.set_ylabel("feedback gain ‖K_t‖", color="tab:red")
    c.set_title("minimal intervention: gains vs variance", fontsize=8)
    _save(fig, path)


# ----------------------------------------------------------------------------------------- primitives


PUSH = (0.1, -0.1)
VIA_OFFSET = (0.06, -0.06)


def _primitive_fits(X, dt: float, at: int, t_via: int, g: torch.Generator) -> dict:
    """DMP and ProMP fitted to ``X (L, N, T, 2)``, reproduced, pushed, conditioned and sampled."""
    from learning.primitives import fit_dmp, fit_promp

    push = torch.tensor(PUSH, dtype=X.dtype)
    dmp = fit_dmp(X, dt=dt, n_basis=20)
    nominal, pushed = dmp.reproduce(), dmp.reproduce(perturbation=push, at=at)
    pm = fit_promp(X, dt=dt, n_basis=15)
    mean = pm.state_mean()
    track0, track = pm.track(), pm.track(perturbation=push, at=at)
    via = mean[:, t_via:t_via + 1, :2] + torch.tensor(VIA_OFFSET, dtype=X.dtype)
    cond = pm.condition([t_via], via)
    return {"dmp": nominal.x, "dmp_pushed": pushed.x, "promp": pm, "mean": mean, "track0": track0,
            "track": track, "via": via, "cond_mean": cond.state_mean(), "samples": cond.sample(5, g)}


def _primitive_metrics(X, f: dict, at: int, t_via: int) -> dict:
    from learning.primitives import perturbation_recovery, reproduction_error, via_point_error

    dmp_rep = reproduction_error(X, f["dmp"])
    dmp_goal = (f["dmp_pushed"][..., -1, :2] - X[..., -1, :]).norm(dim=-1)
    dmp_rec = perturbation_recovery(f["dmp"], f["dmp_pushed"], at, d=2)
    pm_rep = reproduction_error(X, f["promp"].reproductions())
    mean_rms = reproduction_error(X.mean(1), f["mean"])
    pm_goal = (f["track"].x[..., -1, :2] - f["mean"][..., -1, :2]).norm(dim=-1)
    pm_rec = perturbation_recovery(f["track0"].x, f["track"].x, at, d=2)
    via_mean = via_point_error(f["cond_mean"], [t_via], f["via"])
    via_samples = via_point_error(f["samples"], [t_via], f["via"])
    mx = lambda v: float(v.max())  # noqa: E731
    return {"dmp_reproduction_rms_max": mx(dmp_rep), "dmp_reproduction_rms_mean": float(dmp_rep.mean()),
            "dmp_push_to_goal_max": mx(dmp_goal), "dmp_push_peak_dev_mean": float(dmp_rec.peak.mean()),
            "promp_reproduction_rms_max": mx(pm_rep), "promp_mean_rms_max": mx(mean_rms),
            "promp_push_to_goal_max": mx(pm_goal), "promp_push_peak_dev_mean": float(pm_rec.peak.mean()),
            "via_offset": float((f["mean"][:, t_via, :2] - f["via"][:, 0]).norm(dim=-1).min()),
            "via_mean_err_max": mx(via_mean), "via_sample_err_max": mx(via_samples),
            "tracking_converged": bool(f["track"].status.converged.all()
                                       and f["track0"].status.converged.all()),
            "per_letter": {"dmp_reproduction_rms": dmp_rep.mean(-1).tolist(),
                           "promp_reproduction_rms": pm_rep.mean(-1).tolist(),
                           "promp_mean_rms": mean_rms.tolist(), "via_mean_err": via_mean[:, 0].tolist()}}


@restores_threads
def primitives(*, letters: str = "SCUN", n_demos: int = 8, T: int = 100, seed: int = 11, threads: int = 1,
               quiet: bool = True) -> dict:
    """The ``primitives`` pipeline (module docstring); returns its record (``"_fig"``: the figure's data)."""
    from learning.demos import handwriting

    torch.set_num_threads(threads)
    t0 = time.perf_counter()
    g = _gen(seed)
    at, t_via = T // 2, round(0.6 * (T - 1))
    with bar(2, "learn primitives", quiet, unit="stage") as b:
        demos = handwriting(letters, n_demos, T, generator=g)
        X = torch.stack([demos[c].x for c in letters])  # (L, N, T, 2)
        dt = demos[letters[0]].dt
        b.update()
        f = _primitive_fits(X, dt, at, t_via, g)
        b.update()
    v = _primitive_metrics(X, f, at, t_via)
    tol = PRIMITIVES_TOL
    checks = {"dmp_reproduces_demos": v["dmp_reproduction_rms_max"] < tol["dmp_reproduction_rms"],
              "dmp_recovers_from_push": v["dmp_push_to_goal_max"] < tol["dmp_push_to_goal"],
              "promp_mean_reproduces_demo_mean": v["promp_mean_rms_max"] < tol["promp_mean_rms"],
              "promp_tracking_recovers_from_push": v["promp_push_to_goal_max"] < tol["promp_push_to_goal"]
              and v["tracking_converged"],
              "conditioned_mean_through_via_point": v["via_mean_err_max"] < tol["via_mean_err"],
              "conditioned_samples_near_via_point": v["via_sample_err_max"] < tol["via_sample_err"]}
    settings = {"letters": letters, "n_demos": n_demos, "T": T, "seed": seed, "push": list(PUSH),
                "push_step": at, "via_step": t_via, "via_offset": list(VIA_OFFSET), "dmp_basis": 20,
                "promp_basis": 15}
    fig = {k: f[k] for k in ("dmp", "dmp_pushed", "mean", "via", "cond_mean", "samples")}
    return {"pipeline": "primitives", "settings": settings, "checks": checks, "tolerances": dict(tol),
            "values": v, "time_s": time.perf_counter() - t0, "_fig": {"X": X, **fig, "track": f["track"].x}}


def _primitives_report(rec: dict) -> list[str]:
    s, v = rec["settings"], rec["values"]
    p, c = v["per_letter"], markdown_cell
    lines = ["| letter | DMP reproduction RMS | ProMP reproduction RMS | ProMP mean vs demo mean | "
             "via-point error (conditioned mean) |", "|---|---|---|---|---|"]
    keys = ("dmp_reproduction_rms", "promp_reproduction_rms", "promp_mean_rms", "via_mean_err")
    lines += [f"| {x} | " + " | ".join(c(p[k][i]) for k in keys) + " |" for i, x in enumerate(s["letters"])]
    return ([f"Handwriting letters {' '.join(s['letters'])} (`learning.demos.handwriting`), {s['n_demos']} "
             f"demos of T = {s['T']} samples each.  DMP (`fit_dmp`, {s['dmp_basis']} basis functions, one "
             f"per demo, all in one batch); ProMP (`fit_promp`, {s['promp_basis']} basis functions, one per "
             f"letter).  Push {tuple(s['push'])} at step {s['push_step']}; via point at step "
             f"{s['via_step']}, the ProMP mean moved by {tuple(s['via_offset'])}.", ""] + lines +
            ["", f"Push recovery: DMP distance to the goal at the end {c(v['dmp_push_to_goal_max'])} "
             f"(max; peak deviation {c(v['dmp_push_peak_dev_mean'])} mean), ProMP minimal-intervention "
             f"tracking {c(v['promp_push_to_goal_max'])} (peak deviation "
             f"{c(v['promp_push_peak_dev_mean'])}).  Conditioned samples: via-point error "
             f"{c(v['via_sample_err_max'])} at most.", "",
             "The same primitives against DFKI's `movement_primitives` (fit and generation times too): "
             "`liecontrol bench primitives`."])


def _primitives_plot(rec: dict, path: Path) -> None:
    plt = _pyplot()
    f = rec["_fig"]
    L = f["X"].shape[0]
    fig, axes = plt.subplots(1, L, figsize=(2.8 * L, 3.0), squeeze=False)
    for i, ax in enumerate(axes[0]):
        for d in f["X"][i]:
            ax.plot(d[:, 0], d[:, 1], color="0.75", lw=0.8)
        ax.plot(f["dmp"][i, 0, :, 0], f["dmp"][i, 0, :, 1], "k--", lw=1, label="DMP (demo 1)")
        ax.plot(f["dmp_pushed"][i, 0, :, 0], f["dmp_pushed"][i, 0, :, 1], color="tab:red", lw=1,
                label="DMP pushed")
        ax.plot(f["mean"][i, :, 0], f["mean"][i, :, 1], "k", lw=1.5, label="ProMP mean")
        for smp in f["samples"][:, i]:
            ax.plot(smp[:, 0], smp[:, 1], lw=0.7, alpha=0.8)
        ax.plot(f["via"][i, 0, 0], f["via"][i, 0, 1], "o", color="tab:red", ms=5, label="via point")
        ax.set_aspect("equal")
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_title(rec["settings"]["letters"][i], fontsize=9)
    axes[0, 0].legend(fontsize=6)
    fig.suptitle("demos (grey), DMP reproduction and push, ProMP mean and via-point-conditioned samples",
                 fontsize=8)
    _save(fig, path)


# ------------------------------------------------------------------------------------------- dynamics


def _dynamics_run(rec: dict) -> dict:
    """A run of the JSON: :data:`DYNAMICS_KEYS`, then :data:`DYNAMICS_EXTRA` (history: two curves)."""
    out = {k: rec[k] for k in DYNAMICS_KEYS}
    for k in DYNAMICS_EXTRA:
        if k == "history":
            h = rec["history"]
            out[k] = {"loss": h["loss"], "identifiable_rel_err_max": h["identifiable_rel_err_max"],
                      "accepted": h["accepted"]}
        elif k in rec:
            out[k] = rec[k]
    return out


@restores_threads
def dynamics(system: str = "pendulum", *, n_train: int = 10, seeds: int = 4,
             baselines: tuple[str, ...] = ("sysid", "mlp", "lstm"), steps: int = 100, n_test: int = 50,
             unconverged: str = "include", threads: int = 1, quiet: bool = True, log=None) -> list[dict]:
    """The ``dynamics`` pipeline: :func:`learning.imitation.imitation_study` for seeds ``0 … seeds-1`` (one
    call per seed, for the progress bar); returns the runs (:func:`_dynamics_run`)."""
    from learning.imitation import imitation_study

    torch.set_num_threads(threads)
    runs = []
    with bar(seeds, f"learn dynamics {system}", quiet, unit="seed") as b:
        for s in range(seeds):
            recs = imitation_study(system, n_trains=(n_train,), seeds=(s,), steps=steps, n_test=n_test,
                                   baselines=tuple(baselines), unconverged=unconverged)
            runs += [_dynamics_run(r) for r in recs]
            r = runs[-1]
            if log is not None:
                e, mse = (fmt(r[k], missing="nan") for k in ("identifiable_rel_err_max", "imitation_mse"))
                log(f"{system} seed {s}: identifiable error {e}, held-out MSE {mse} ({fmt(r['time_s'])} s)")
            b.update()
    return runs


def dynamics_checks(runs: list[dict]) -> tuple[dict, dict]:
    """``(checks, tolerances)`` of a ``dynamics`` run: the identifiable parameters within 1 % on every seed
    (issue 26 §4's goal), the learned model imitating better than the initial one, every expert solve
    converged (the demos are optima)."""
    tol = DYNAMICS_TOL["identifiable_rel_err"]
    ok = lambda v: v is not None and math.isfinite(v)  # noqa: E731
    below = lambda a, b: ok(a) and ok(b) and a < b  # noqa: E731
    checks = {"identifiable_within_1_percent": all(below(r["identifiable_rel_err_max"], tol) for r in runs),
              "imitation_mse_below_initial": all(below(r["imitation_mse"], r["imitation_mse_init"])
                                                 for r in runs),
              "expert_solves_converged": all(r["expert_unconverged"] == 0 for r in runs)}
    return checks, {"identifiable_rel_err": tol}


def _dynamics_rows(runs: list[dict]) -> list[dict]:
    rows = []
    for r in runs:
        row = {"seed": r["seed"], "n_train": r["n_train"]}
        row.update({f"err {k}": r["param_rel_err"][k] for k in r["identifiable"]})
        row.update({"mse": r["imitation_mse"], "mse_init": r["imitation_mse_init"]})
        row.update({f"mse {k}": b.get("imitation_mse") for k, b in r["baselines"].items()})
        row.update({"unconv": r["unconverged"]["sample_solves"], "evals": r["evaluations"],
                    "time_s": r["time_s"]})
        rows.append(row)
    return rows


def _dynamics_report(runs: list[dict], settings: dict) -> list[str]:
    rows = _dynamics_rows(runs)
    cols = list(rows[0])
    r0 = runs[0]
    phys = [k for k in r0["params_true"] if k in r0["param_rel_err"] and k not in r0["identifiable"]]
    st = settings
    lines = [f"System {st['system']}, {st['n_train']} training demos, seeds 0 … {st['seeds'] - 1}, "
             f"{r0['n_test']} held-out starts, a budget of {st['steps']} loss evaluations (`evals`: those "
             f"taken), unconverged training solves: {st['unconverged']}; baselines: "
             f"{', '.join(st['baselines']) or 'none'}.  True "
             f"parameters {r0['params_true']}, learner's start {r0['params_init']}.  `err NAME`: relative "
             f"error of the identifiable parameters ({', '.join(r0['identifiable'])}); `mse`: held-out "
             "imitation MSE of the learned model (`mse_init`: the initial model; `mse sysid|mlp|lstm`: the "
             "baselines), in squared control units; `unconv`: non-converged learner solves over all "
             "evaluations (reported per sample in the JSON, none dropped silently).", "",
             "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    lines += ["| " + " | ".join(markdown_cell(r[c]) for c in cols) + " |" for r in rows]
    bad = [f"seed {r['seed']}: {', '.join(r['nonfinite_values'])}" for r in runs if r.get("nonfinite_values")]
    if bad:
        lines += ["", "Non-finite values (`null` in the JSON): " + "; ".join(bad) + "."]
    if phys:
        lines += ["", "Relative errors of the physical parameters, which the controls do not identify (any "
                  "values with the true identifiable combinations imitate the expert exactly): "
                  + "; ".join(f"seed {r['seed']}: " + ", ".join(f"{k} {markdown_cell(r['param_rel_err'][k])}"
                                                                 for k in phys) for r in runs) + "."]
    return lines


def _floored(values, floor: float) -> list[float]:
    """Values for a log axis: at least ``floor``; ``None`` (a non-finite value in the JSON) as NaN."""
    return [math.nan if v is None or not math.isfinite(v) else max(v, floor) for v in values]


def _dynamics_plot(runs: list[dict], path: Path) -> None:
    plt = _pyplot()
    fig, (a, b, c) = plt.subplots(1, 3, figsize=(12, 3.4))
    for r in runs:
        h = r["history"]
        a.semilogy(_floored(h["loss"], 1e-32), label=f"seed {r['seed']}")  # 1e-32: the plot's floor
        b.semilogy(_floored(h["identifiable_rel_err_max"], 1e-16), label=f"seed {r['seed']}")
    b.axhline(DYNAMICS_TOL["identifiable_rel_err"], color="k", lw=0.8, ls=":")
    a.set_xlabel("loss evaluation")
    a.set_ylabel("imitation loss")
    b.set_xlabel("loss evaluation")
    b.set_ylabel("largest identifiable relative error")
    a.legend(fontsize=7)
    names = ["learned", "initial", *runs[0]["baselines"]]
    for i, r in enumerate(runs):
        vals = [r["imitation_mse"], r["imitation_mse_init"], *(x.get("imitation_mse") for x in
                                                               r["baselines"].values())]
        xs = [j + 0.8 * i / max(len(runs), 1) for j in range(len(names))]
        c.bar(xs, _floored(vals, 1e-32),
              width=0.8 / max(len(runs), 1), label=f"seed {r['seed']}")
    c.set_yscale("log")
    c.set_xticks(range(len(names)), names, fontsize=7)
    c.set_ylabel("held-out imitation MSE")
    fig.suptitle(f"{runs[0]['system']}: parameters learned through the differentiable MPC "
                 f"({runs[0]['n_train']} demos)", fontsize=9)
    _save(fig, path)


# ------------------------------------------------------------------------------------------- manifold


def _orientation_part(n_demos: int, T: int, horizon: int, g: torch.Generator) -> dict:
    """SO(3) demos agreeing around s = 0.6, their statistics (also as S³), the mean tracked by the MPC."""
    from learning.manifold_demos import (
        BodyRateSO3,
        demo_points,
        manifold_statistics,
        orientation_demos,
        track_mean,
    )
    from torchlie import so3

    s = torch.linspace(0.0, 1.0, T, dtype=torch.float64)
    env = 1 - 0.9 * torch.exp(-((s - 0.6) / 0.08) ** 2)
    demos = orientation_demos(n_demos, T, generator=g, envelope=env, warp=0.05)
    st = manifold_statistics(demos)
    R = demo_points(demos)
    q = so3.to_quaternion(R)
    q = torch.where(torch.rand(n_demos, T, 1, generator=g, dtype=torch.float64) < 0.5, -q, q)
    st_q = manifold_statistics(q, "S3")
    e = so3.log(st.mean.mT @ R)
    maha = (e.unsqueeze(-2) @ torch.linalg.solve(st.covariance, e.unsqueeze(-1))).reshape(n_demos, T)
    x0 = st.mean[0] @ so3.exp(torch.tensor(START_OFFSET, dtype=torch.float64))
    trk = track_mean(BodyRateSO3(demos.dt), st.mean, st.covariance, x0, horizon=horizon, R=1.0,
                     regularization=1e-4)
    return {"R": R, "st": st, "st_q": st_q, "maha": maha, "track": trk,
            "q_gap": so3.angle(st.mean.mT @ so3.from_quaternion(st_q.mean)).max()}


def _stiffness_part(n_demos: int, T: int, g: torch.Generator) -> dict:
    """SPD stiffness demos, their Karcher (affine-invariant) and Euclidean means against the true profile."""
    from learning.manifold_demos import demo_points, manifold_statistics, stiffness_demos

    kd = stiffness_demos(n_demos, T, generator=g, noise=STIFFNESS_NOISE)
    ks = manifold_statistics(kd)
    K = demo_points(kd)
    ref = kd.frames["reference"][0].reshape(T, 3, 3)
    M = ks.manifold
    rel = lambda A: torch.linalg.matrix_norm(A - ref) / torch.linalg.matrix_norm(ref)  # noqa: E731
    return {"ks": ks, "K": K, "ref": ref, "rel_karcher": rel(ks.mean), "rel_euclid": rel(K.mean(0)),
            "dist_karcher": M.dist(ks.mean, ref, check=False),
            "dist_euclid": M.dist(K.mean(0), ref, check=False)}


@restores_threads
def manifold(*, n_demos: int = 12, T: int = 40, horizon: int = 8, seed: int = 3, threads: int = 1,
             quiet: bool = True) -> dict:
    """The ``manifold`` pipeline (module docstring); returns its record (``"_fig"``: the figure's data)."""
    torch.set_num_threads(threads)
    t0 = time.perf_counter()
    g = _gen(seed)
    with bar(2, "learn manifold", quiet, unit="stage") as b:
        o = _orientation_part(n_demos, T, horizon, g)
        b.update()
        k = _stiffness_part(n_demos, T, g)
        b.update()
    st, trk = o["st"], o["track"]
    err = trk.error.norm(dim=-1)
    var = torch.diagonal(st.covariance, dim1=-2, dim2=-1).sum(-1)
    gain = torch.linalg.matrix_norm(trk.gain, ord=2)
    inside = float((o["maha"] <= 7.815).double().mean())
    tol = MANIFOLD_TOL
    v = {"max_gauss_newton_iterations": int(max(st.iterations.max(), o["st_q"].iterations.max(),
                                                k["ks"].iterations.max())),
         "quaternion_mean_gap_rad": float(o["q_gap"]), "fraction_inside_95": inside,
         "variance_min": float(var.min()), "variance_max": float(var.max()),
         "tracking_error_initial_rad": float(err[0]), "tracking_error_final_rad": float(err[-1]),
         "tracking_error_max_after_half_rad": float(err[len(err) // 2:].max()),
         "gain_min": float(gain.min()), "gain_max": float(gain.max()),
         "stiffness_rel_err_karcher_max": float(k["rel_karcher"].max()),
         "stiffness_rel_err_euclid_max": float(k["rel_euclid"].max()),
         "stiffness_dist_karcher_mean": float(k["dist_karcher"].mean()),
         "stiffness_dist_euclid_mean": float(k["dist_euclid"].mean()),
         "stiffness_noise_scale": STIFFNESS_NOISE * math.sqrt(6 / n_demos)}
    checks = {"statistics_converged": bool(st.converged.all() and o["st_q"].converged.all()
                                           and k["ks"].converged.all()),
              "quaternion_mean_agrees": v["quaternion_mean_gap_rad"] < tol["quaternion_gap_rad"],
              "demos_inside_95_ellipsoids": inside >= tol["inside_95"],
              "tracking_error_reduced": v["tracking_error_final_rad"] < tol["tracking_final_over_initial"]
              * v["tracking_error_initial_rad"] and bool((trk.reason == 0).all()),
              "stiffness_target_recovered": v["stiffness_dist_karcher_mean"]
              <= tol["stiffness_dist_factor"] * v["stiffness_noise_scale"]}
    settings = {"n_demos": n_demos, "T": T, "horizon": horizon, "seed": seed}
    return {"pipeline": "manifold", "settings": settings, "checks": checks, "tolerances": dict(tol),
            "values": v,
            "per_step": {"variance": var.tolist(), "tracking_error": err.tolist(), "gain": gain.tolist(),
                         "stiffness_rel_err_karcher": k["rel_karcher"].tolist(),
                         "stiffness_rel_err_euclid": k["rel_euclid"].tolist()},
            "time_s": time.perf_counter() - t0,
            "_fig": {"R": o["R"], "mean": st.mean, "x": trk.x}}


def _manifold_report(rec: dict) -> list[str]:
    s, v, c = rec["settings"], rec["values"], markdown_cell
    pair = lambda a, b, sep=" / ": f"{c(v[a])}{sep}{c(v[b])}"  # noqa: E731
    rows = [("max Gauss–Newton iterations (SO(3), S³, SPD)", c(v["max_gauss_newton_iterations"])),
            ("S³ vs SO(3) mean rotation gap [rad]", c(v["quaternion_mean_gap_rad"])),
            ("demo samples inside their 95 % ellipsoid", c(v["fraction_inside_95"])),
            ("tr Σ_t min / max [rad²]", pair("variance_min", "variance_max")),
            ("tracking error initial → final [rad]",
             pair("tracking_error_initial_rad", "tracking_error_final_rad", " → ")),
            ("MPC gain ‖K_t‖ min / max", pair("gain_min", "gain_max")),
            ("stiffness target relative error (max over t), Karcher / Euclidean mean",
             pair("stiffness_rel_err_karcher_max", "stiffness_rel_err_euclid_max")),
            ("affine-invariant distance to the true stiffness (mean over t), Karcher / Euclidean",
             pair("stiffness_dist_karcher_mean", "stiffness_dist_euclid_mean")),
            ("sampling scale of the stiffness demos σ √(6/N)", c(v["stiffness_noise_scale"]))]
    return ([f"{s['n_demos']} SO(3) orientation demos of T = {s['T']} steps (`orientation_demos`, agreeing "
             "around s = 0.6), their per-step Karcher mean and tangent covariance (`manifold_statistics`; "
             "the same demos as unit quaternions with random signs for S³), the mean tracked from a start "
             f"{c(v['tracking_error_initial_rad'])} rad away by the error-state MPC (`track_mean`, horizon "
             f"{s['horizon']}, precision "
             "(Σ_t + 10⁻⁴ I)⁻¹); "
             f"{s['n_demos']} 3×3 stiffness demos (`stiffness_demos`, log-scale noise σ = {STIFFNESS_NOISE}) "
             "and their Karcher "
             "mean (affine-invariant) as the learned stiffness target, against the true profile.", "",
             "| quantity | value |", "|---|---|"] + [f"| {a} | {b} |" for a, b in rows])


def _manifold_plot(rec: dict, path: Path) -> None:
    plt = _pyplot()
    f, p = rec["_fig"], rec["per_step"]
    fig, axes = plt.subplots(1, 4, figsize=(13, 3.0))
    ax = axes[0]
    for zi in f["R"][..., :, 2]:
        ax.plot(zi[:, 0], zi[:, 1], color="0.7", lw=0.7)
    ax.plot(f["mean"][:, 0, 2], f["mean"][:, 1, 2], "k", lw=1.5, label="Karcher mean")
    ax.plot(f["x"][:, 0, 2], f["x"][:, 1, 2], "--", color="tab:red", lw=1.2, label="MPC")
    ax.set_aspect("equal")
    ax.set_title("tool z-axis (x–y)", fontsize=8)
    ax.legend(fontsize=6)
    axes[1].semilogy(p["variance"], color="tab:blue")
    axes[1].set_ylabel("tr Σ_t", color="tab:blue", fontsize=7)
    a2 = axes[1].twinx()
    a2.plot(p["gain"], color="tab:red")
    a2.set_ylabel("‖K_t‖", color="tab:red", fontsize=7)
    axes[1].set_title("variance and MPC gain", fontsize=8)
    axes[2].semilogy([max(e, 1e-16) for e in p["tracking_error"]], color="tab:red")
    axes[2].set_title("tracking error ‖Log(μ_t⁻¹ R_t)‖", fontsize=8)
    axes[3].plot(p["stiffness_rel_err_karcher"], label="Karcher (affine-invariant)")
    axes[3].plot(p["stiffness_rel_err_euclid"], "--", label="Euclidean")
    axes[3].set_title("stiffness target: relative error", fontsize=8)
    axes[3].legend(fontsize=6)
    for a in axes:
        a.tick_params(labelsize=6)
    _save(fig, path)


# ------------------------------------------------------------------------------------------ the command


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path) -> None:
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    _pyplot().close(fig)


def _write_json(path: str | Path, data) -> Path:
    """``data`` as JSON (non-finite numbers → ``null``, :func:`learning.evaluate.jsonable`), parents made."""
    from learning.evaluate import jsonable

    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps(jsonable(data), indent=1, allow_nan=False) + "\n")
    return p


def _checks_lines(checks: dict, tol: dict) -> list[str]:
    lines = ["", "## Checks", "", "| check | passed |", "|---|---|"]
    lines += [f"| {k} | {'yes' if v else '**NO**'} |" for k, v in checks.items()]
    return lines + ["", "Tolerances: " + ", ".join(f"{k} {markdown_cell(v)}" for k, v in tol.items()) + "."]


_REPORTS = {"costs": (_costs_report, _costs_plot), "primitives": (_primitives_report, _primitives_plot),
            "manifold": (_manifold_report, _manifold_plot)}
_TABLES = {"costs": ["weights_rel_err", "via_target_err", "via_time_err_steps", "reproduction_rms",
                     "mi_gain_ratio"],
           "primitives": ["dmp_reproduction_rms_max", "dmp_push_to_goal_max", "promp_mean_rms_max",
                          "promp_push_to_goal_max", "via_mean_err_max", "via_sample_err_max"],
           "manifold": ["quaternion_mean_gap_rad", "fraction_inside_95", "tracking_error_initial_rad",
                        "tracking_error_final_rad", "stiffness_dist_karcher_mean",
                        "stiffness_noise_scale"]}


def _run_pipeline(args: argparse.Namespace) -> tuple[object, dict, dict, list[str], object]:
    """``(json data, checks, tolerances, report lines, plot(path))`` of the chosen pipeline."""
    name, quiet = args.subcommand, args.quiet
    if name == "dynamics":
        runs = dynamics(args.system, n_train=args.n_train, seeds=args.seeds,
                        baselines=tuple(args.baselines), steps=args.steps, n_test=args.n_test,
                        unconverged=args.unconverged, threads=args.threads, quiet=quiet,
                        log=None if quiet else write)
        settings = {k: getattr(args, k) for k in ("system", "n_train", "seeds", "steps", "unconverged")}
        settings["baselines"] = list(args.baselines)
        checks, tol = dynamics_checks(runs)
        print_table(_dynamics_rows(runs), list(_dynamics_rows(runs)[0]))
        return runs, checks, tol, _dynamics_report(runs, settings), lambda p: _dynamics_plot(runs, p)
    kw = {"costs": ("n_demos", "steps", "seed", "warp", "noise"),
          "primitives": ("letters", "n_demos", "T", "seed"),
          "manifold": ("n_demos", "T", "horizon", "seed")}[name]
    fn = {"costs": costs, "primitives": primitives, "manifold": manifold}[name]
    opts = {k: getattr(args, k) for k in kw}
    if name == "primitives":
        opts["letters"] = "".join(opts["letters"])
    rec = fn(**opts, threads=args.threads, quiet=quiet)
    report, plot = _REPORTS[name]
    print_table([{"quantity": k, "value": rec["values"][k]} for k in _TABLES[name]], ["quantity", "value"])
    public = {k: v for k, v in rec.items() if not k.startswith("_")}
    return public, rec["checks"], rec["tolerances"], report(rec), lambda p: plot(rec, p)


def _prepare_out(args: argparse.Namespace) -> Path:
    """The output folder (made now, before minutes of work) and ``--json``'s folder; a folder the system
    refuses is an option error (exit status 2), never a traceback after the run."""
    root = Path(args.out) if args.out is not None else Path("out/learn") / args.subcommand
    for option, folder in (("--out", root), ("--json", Path(args.json).parent if args.json else None)):
        if folder is None:
            continue
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise OptionError(option, f"cannot create {folder}: {e.strerror or e}") from None
    return root


def _write(option: str, write, path: Path) -> Path:
    """``write(path)``, a system refusal reported as an error of ``option`` (exit status 2)."""
    try:
        write(path)
    except OSError as e:
        raise OptionError(option, f"cannot write {path}: {e.strerror or e}") from None
    return path


def _merged_report(path: Path, name: str, text: str) -> str:
    """``text`` (this pipeline's report, first) followed by the sections of the other ``learn`` pipelines
    already in ``path`` (several pipelines written into one ``--out`` keep every report)."""
    try:
        old = path.read_text()
    except (OSError, UnicodeDecodeError):
        return text
    others = [p for p in PIPELINES if p != name]
    keep = [q.rstrip("\n") + "\n" for q in re.split(r"(?m)^(?=# liecontrol learn )", old)
            if any(q.startswith(f"# liecontrol learn {p}\n") for p in others)]
    return "\n".join([text.rstrip("\n") + "\n", *keep])


def run(args: argparse.Namespace) -> int:
    """``liecontrol learn costs|primitives|dynamics|manifold`` (module docstring): 1 when a check fails."""
    name = args.subcommand
    t0 = time.perf_counter()
    root = _prepare_out(args)
    data, checks, tol, lines, plot = _run_pipeline(args)
    files = [_write("--out", lambda p: _write_json(p, data), root / f"{name}.json")]
    if args.json:
        files.append(_write("--json", lambda p: _write_json(p, data), Path(args.json)))
    figure = [] if args.no_plots else [f"![{name}]({name}.png)", ""]
    if not args.no_plots:
        files.append(_write("--out", plot, root / f"{name}.png"))
    took = time.perf_counter() - t0
    text = "\n".join([f"# liecontrol learn {name}", ""] + lines + _checks_lines(checks, tol) + [
        "", f"Wall time {took:.1f} s (torch threads {args.threads}).", ""] + figure)
    report = root / "report.md"
    files.append(_write("--out", lambda p: p.write_text(_merged_report(p, name, text)), report))
    failed = [k for k, v in checks.items() if not v]
    print(f"checks: {'all passed' if not failed else 'FAILED ' + ', '.join(failed)} ({len(checks)})")
    print(f"wrote {', '.join(map(str, files))} in {took:.0f} s")
    return 1 if failed else 0
