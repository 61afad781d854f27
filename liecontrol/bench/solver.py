"""``liecontrol bench solver``: the solver workloads of issue 23, each timed through the public API against
its anchor in the same run.

Every row times a public entry point, so a faster solver behind it (a compiled path) shows up here without
changing this file:

* ``quadrotor_step``: ``ErrorStateMPC.solve`` (quadrotor, H = 8, cold, ``reproduce quadrotor``'s batched
  problem) at B = 1 and 1024; anchor at B = 1: CasADi+IPOPT on the same problem, cold.
* ``pendulum_mpc_step``: ``MPCExpert("PendulumSwingUp").act`` (H = 40, warm-started, 20 iterations at most),
  B = 1, mean time per closed-loop step after the first; anchor: crocoddyl ``SolverBoxFDDP`` run as the same
  MPC (same problem, limits, iteration cap, angle rule, feasible warm start, one thread).
* ``pendulum_ilqr_iteration``: the same run, Σ step time / Σ iLQR iterations (both sides).
* ``cartpole_swingup_batch64``, ``pendulum_swingup_batch64``: ``ilqr`` on ``bench ilqr``'s 64 swing-ups
  (T = 100, 100 iterations at most), batched; anchor: crocoddyl one problem at a time, total (the pendulum
  twice: damped, crocoddyl with Python callbacks, and ``b=0``, all C++).
* ``car_parking_step``: ``MPCExpert("CarParking").act`` (H = 40), B = 16, mean per closed-loop step after
  the first; no anchor.
* ``mpc_head_fwd_bwd``: ``MPCActorCriticPolicy.evaluate_actions`` + ``backward`` (``learning.mpc_policy``,
  what a PPO update does) at B = 64 and 1024 on the pendulum and the cart-pole (``task`` key); anchor:
  SB3's ``ActorCriticPolicy`` (``MlpPolicy``, default architecture) doing the same.
* ``cookbook_manipulator``: ``ilqr`` (recursive and batch) and ``ilqr_lifted`` (Algorithm 4 with the
  transfer matrices of the linear dynamics built once) on the cookbook manipulator (seed 004 §9.1, one
  problem, :func:`cookbook_problem`); anchor: the cookbook's batch iLQR (§8.1, Eq. 108) in plain numpy
  (``_cookbook_anchor.py``) for as many iterations as each took; both costs are printed.  Then a batch
  of 64 starts by the recursive and the lifted solver, with ``per_one`` = its time over the same solver's
  time on one problem (the script solves one problem at a time: 64 of them cost 64 times one).
* ``cookbook_car``, ``cookbook_bicopter``: the same on the cookbook's nonlinear vehicles, the car of §9.15
  (``iLQR_car``: velocity inputs, Eq. 118, explicit Euler; :func:`cookbook_car_problem`) and the bicopter
  of §9.16 (``iLQR_bicopter``: absolute thrusts, Eq. 120, semi-implicit Euler like
  :class:`~controllers.systems.bicopter.Bicopter`; :func:`cookbook_bicopter_problem`), each driven to a
  final state over 100 steps (``--quick``: 20 and 30) from zero controls (car) or the hover thrust
  (bicopter), both sides; anchor: the scripts' batch iLQR on the nonlinear system in plain numpy
  (``_cookbook_vehicle_anchor.py``: a rollout loop, ``A_t, B_t``, the dense ``S_u`` and block-diagonal
  ``Q`` of Eq. 108).  Their batch rows are timed once after the warm-up unless ``--repeats`` is given (a
  batch of 64 by ``ilqr_lifted`` takes about a minute on one core).

Records (``--json PATH``): ``{"workload", "batch", "dtype", "device", "ours_ms", "anchor", "anchor_ms",
"ratio"}`` with ``ratio = anchor_ms / ours_ms`` (above 1: ours is faster), ``anchor``/``anchor_ms``/``ratio``
null where there is no anchor or it could not run (``anchor_note`` says why), plus descriptive keys
(``case``, ``horizon``, ``task``, ``system``, iterations, costs, episode returns).

Timing: :func:`liecontrol.report.time_ms` (median of ``--repeats`` calls after one warm-up call: the first
call may build or compile); a closed loop times every step's call after the first (cold) one and reports
their median.  ``--threads`` (default 1) pins torch and the anchors' subprocesses (crocoddyl, numpy's BLAS)
to that many threads.  crocoddyl and numpy anchors run in subprocesses of this interpreter and are float64
on the CPU whatever ``--dtype``/``--device`` say; the rows record what *ours* ran in.  Anchors that are not
installed give null anchor columns and a printed note, never a failure.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from liecontrol import _options
from liecontrol.report import print_table, restores_threads, sync, time_ms, write_json

__all__ = ["add_arguments", "run", "measure", "WORKLOADS", "Sizes", "DEFAULT_SIZES", "QUICK_SIZES",
           "COOKBOOK", "COOKBOOK_CAR", "COOKBOOK_BICOPTER", "cookbook_problem", "cookbook_car_problem",
           "cookbook_bicopter_problem", "cookbook_u_init"]

#: the command's options (``--workloads``, ``--device``, ``--dtype``, ``--threads``, ``--repeats``,
#: ``--quick``, ``--json``, ``--eager``), checked before this module is imported
add_arguments = _options.bench_solver
WORKLOADS = _options.SOLVER_WORKLOADS
COLUMNS = ["workload", "case", "batch", "dtype", "device", "ours_ms", "anchor", "anchor_ms", "ratio"]
_DTYPES = {"float32": torch.float32, "float64": torch.float64}


@dataclasses.dataclass(frozen=True)
class Sizes:
    """Problem sizes and repeat counts of one run (``None`` horizons: the task's default)."""

    quad_batches: tuple[int, ...] = (1, 1024)
    quad_horizon: int = 8
    pend_steps: int = 100  # timed closed-loop steps (after the first, cold one)
    pend_horizon: int | None = None
    car_batch: int = 16
    car_steps: int = 5
    car_horizon: int | None = None
    swing_batch: int = 64
    swing_horizon: int = 100
    swing_max_iter: int = 100
    head_batches: tuple[int, ...] = (64, 1024)
    repeats: int = 5
    swing_repeats: int = 1  # a batch of 64 swing-ups takes seconds
    cookbook_batch: int = 64
    cookbook_car_T: int | None = None  # control steps of the cookbook car (None: COOKBOOK_CAR's 100)
    cookbook_bicopter_T: int | None = None  # and of the bicopter (None: COOKBOOK_BICOPTER's 100)
    cookbook_vehicle_batch_repeats: int = 1  # the car's and bicopter's batches of 64 take up to a minute


DEFAULT_SIZES = Sizes()
QUICK_SIZES = Sizes(quad_batches=(1, 4), pend_steps=3, car_batch=2, car_steps=1,
                    car_horizon=8, swing_batch=2, swing_horizon=10, swing_max_iter=5, head_batches=(4,),
                    repeats=1, cookbook_batch=4, cookbook_car_T=20,
                    cookbook_bicopter_T=30)


@dataclasses.dataclass(frozen=True)
class _Ctx:
    sizes: Sizes
    dtype: torch.dtype
    device: torch.device
    threads: int
    repeats: int | None
    compile: bool = True

    def options(self, **kw):
        """iLQR options of our side: its time sweeps compiled unless ``--eager``."""
        from controllers.ilqr import ILQROptions

        return ILQROptions(compile=self.compile, **kw)

    def reps(self, default: int | None = None) -> int:
        return self.repeats if self.repeats is not None else (default or self.sizes.repeats)

    def time(self, fn: Callable[[], object], repeats: int | None = None) -> float:
        return time_ms(fn, repeats=self.reps(repeats), warmup=1, device=self.device)


def _record(ctx: _Ctx, workload: str, case: str, batch: int, ours_ms: float, anchor: str | None = None,
            anchor_ms: float | None = None, note: str | None = None, dtype: torch.dtype | None = None,
            **extra) -> dict:
    """One output record; the anchor columns are null unless both the anchor and its time are given."""
    if anchor is None or anchor_ms is None:
        anchor = anchor_ms = None
    rec = {"workload": workload, "batch": batch, "dtype": str(dtype or ctx.dtype).removeprefix("torch."),
           "device": str(ctx.device), "ours_ms": ours_ms, "anchor": anchor, "anchor_ms": anchor_ms,
           "ratio": anchor_ms / ours_ms if anchor_ms is not None and ours_ms else None, "case": case,
           "compiled": ctx.compile}
    if note:
        rec["anchor_note"] = note
    return {**rec, **extra}


def _subprocess(script: str, argv: list[str], threads: int) -> tuple[dict, str | None]:
    """Run ``script`` (a file of this folder) with this interpreter pinned to ``threads`` threads; returns
    its last stdout line as JSON, or ``({}, why)``."""
    env = {**os.environ, "OMP_NUM_THREADS": str(threads), "OPENBLAS_NUM_THREADS": str(threads),
           "MKL_NUM_THREADS": str(threads)}
    cmd = [sys.executable, str(Path(__file__).with_name(script)), *argv]
    try:
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=3600, env=env)
    except (subprocess.TimeoutExpired, OSError) as e:
        return {}, f"{type(e).__name__}: {e}"[:300]
    lines = res.stdout.strip().splitlines()
    if res.returncode != 0 or not lines:
        return {}, (res.stderr.strip().splitlines() or [f"exit code {res.returncode}, no output"])[-1][:300]
    try:
        r = json.loads(lines[-1])
    except ValueError as e:
        return {}, f"unreadable anchor output: {e}"[:300]
    if not r.get("ok"):
        return r, r.get("error") or "failed"
    return r, None


# ------------------------------------------------------------------------------------------------ quadrotor
def _quadrotor_problem(batch: int, horizon: int, dtype: torch.dtype, device: torch.device,
                       compile: bool = False):
    """The problem of ``reproduce quadrotor``'s batched timing: ``batch`` quadrotors at random points of the
    circle reference, each from its own perturbed state (seed 0); float64 built, then cast/moved; the MPC
    with ``compile`` (``ErrorStateMPC(compile=...)``, ``--eager`` turns it off)."""
    from controllers.manifold_mpc import ErrorStateMPC, riccati_terminal_weight
    from controllers.systems import quadrotor_flatness as qf
    from controllers.systems.quadrotor import Quadrotor
    from liecontrol.reproduce.quadrotor import weights
    from torchlie import so3

    D = torch.float64
    q = Quadrotor()
    Q, R = weights()
    xh, uh = q.hover(torch.zeros(3, dtype=D))
    P, _ = riccati_terminal_weight(q, xh, uh, Q, R)
    ref = qf.circle_ramp(pad=horizon + 2)
    g = torch.Generator().manual_seed(0)
    k = torch.randint(0, ref.t.shape[0] - horizon - 1, (batch,), generator=g)
    idx = k[:, None] + torch.arange(horizon + 1)
    p0 = ref.p[k] + 0.05 * torch.randn(batch, 3, generator=g, dtype=D)
    R0 = ref.R[k] @ so3.exp(0.05 * torch.randn(batch, 3, generator=g, dtype=D))

    def cast(t):
        return t.to(device=device, dtype=dtype)

    xr = q.state(cast(ref.p[idx]), cast(ref.v[idx]), cast(ref.R[idx]))
    x0 = q.state(cast(p0), cast(ref.v[k]), cast(R0))
    ur = cast(ref.u[idx[:, :-1]])
    mpc = ErrorStateMPC(q, horizon, cast(Q), cast(R), cast(P), grad="none", compile=compile)
    return q, mpc, x0, xr, ur, (Q, R, P, ref, k, idx, p0, R0)


def _casadi_b1(ctx: _Ctx, q, horizon: int, raw) -> tuple[float | None, str | None]:
    """CasADi+IPOPT (``liecontrol.bench._casadi_quadrotor``) on the first quadrotor, cold each call."""
    try:
        from liecontrol.bench._casadi_quadrotor import CasadiQuadrotorMPC
    except ImportError as e:
        return None, f"CasADi not installed ({e}; pip install -e '.[bench]')"
    Q, R, P, ref, k, idx, p0, R0 = raw
    mpc = CasadiQuadrotorMPC(horizon, q.dt, Q.numpy(), R.numpy(), P.numpy(), q.u_lower, q.u_upper)
    x0 = (p0[0].numpy(), ref.v[k[0]].numpy(), R0[0].numpy())
    xr = (ref.p[idx[0]].numpy(), ref.v[idx[0]].numpy(), ref.R[idx[0]].numpy())
    ur = ref.u[idx[0, :-1]].numpy()

    def solve():
        mpc.reset()
        return mpc.step(x0, xr, ur)

    ok = solve()[1]["success"]
    ms = time_ms(solve, repeats=ctx.reps(), warmup=0)
    return ms, None if ok else "IPOPT did not report success"


def _quadrotor(ctx: _Ctx) -> list[dict]:
    H = ctx.sizes.quad_horizon
    out = []
    for B in ctx.sizes.quad_batches:
        q, mpc, x0, xr, ur, raw = _quadrotor_problem(B, H, ctx.dtype, ctx.device, ctx.compile)
        sol = mpc.solve(x0, xr, ur)
        ms = ctx.time(lambda mpc=mpc, x0=x0, xr=xr, ur=ur: mpc.solve(x0, xr, ur))
        anchor = anchor_ms = note = None
        if B == 1:
            anchor = "CasADi+IPOPT NMPC (cold)"
            anchor_ms, note = _casadi_b1(ctx, q, H, raw)
        out.append(_record(ctx, "quadrotor_step", f"ErrorStateMPC H={H}", B, ms, anchor, anchor_ms, note,
                           horizon=H, not_converged=int((~sol.status.converged).sum())))
    return out


# ------------------------------------------------------------------------------------ closed-loop experts
def _closed_loop(task, policy, x0: torch.Tensor, steps: int, device: torch.device) -> dict:
    """``steps + 1`` control steps of ``policy`` on ``task`` from ``x0``; each ``act`` call timed alone.
    The first (cold) step is returned apart: ``ms``/``iterations`` are of steps 1..steps."""
    scale = task.u_scale(x0.dtype, x0.device)
    x, xs, us, ms, its, ret = x0, [x0], [], [], [], torch.zeros(x0.shape[0], dtype=x0.dtype, device=device)
    for _ in range(steps + 1):
        obs = task.observe(x)
        box: dict = {}
        t = time_ms(lambda obs=obs, box=box: box.setdefault("a", policy.act(obs)), repeats=1, warmup=0,
                    device=device)
        ms.append(t)
        its.append(policy.info()["iterations"].to(torch.float64))
        x, u, r, _, _ = task.transition(x, box["a"], scale)
        ret += r
        xs.append(x)
        us.append(u)
    sync(device)
    it = torch.stack(its[1:])  # (steps, B)
    return {"ms": ms[1:], "first_ms": ms[0], "iterations": it, "x": torch.stack(xs, -2),
            "u": torch.stack(us, -2), "return": ret}


def _per_step(ms) -> dict:
    """Mean time per step (the figure reported) and the spread of the steps."""
    v = np.asarray(ms, dtype=float)
    return {"mean": float(v.mean()), "median": float(np.median(v)), "max": float(v.max())}


def _croc_pendulum(ctx: _Ctx, task, expert, x0: torch.Tensor, steps: int) -> tuple[dict | None, str | None]:
    """crocoddyl's BoxFDDP closed loop on the same problem (``_crocoddyl_mpc_anchor.py``), after its model
    check against our model (the ``bench ilqr`` tolerances)."""
    from controllers.dynamics import rollout
    from learning.policies import angle_dims
    from liecontrol.bench.ilqr import CROC_COST_TOL, CROC_ROLLOUT_TOL, CROC_STEP_TOL

    D, H, md = torch.float64, expert.horizon, task.system
    cost = task.mpc_cost(H, dtype=D)
    Qd, R = cost.Q[0].diagonal(), float(cost.R.reshape(-1)[0])
    target = cost.x_ref.reshape(-1, task.n)[-1].numpy()
    g = torch.Generator().manual_seed(1)
    umax = task.u_max()[0]
    u_check = (2 * torch.rand(2, H, 1, generator=g, dtype=D) - 1) * umax
    x_check = rollout(md, x0.to("cpu", D).expand(2, -1), u_check)
    mask = np.zeros(task.n, bool)
    mask[angle_dims(task)] = True
    with tempfile.TemporaryDirectory() as tmp:
        f, out = Path(tmp) / "problem.npz", Path(tmp) / "out.npz"
        np.savez(f, problem=np.array("pendulum"), T=np.array(H), dt=np.array(float(md.dt)),
                 umax=np.array(umax), Qd=Qd.numpy(), QTd=cost.Q[-1].diagonal().numpy(), R=np.array(R),
                 target=target, params=np.array([float(md.mass), float(md.length),
                                                             float(md.damping), float(md.gravity)]),
                 u_check=u_check.numpy(), x_check=x_check.numpy(), x_start=x0[0].to(D).cpu().numpy(),
                 steps=np.array(steps + 1), max_iter=np.array(expert.options.max_iter),
                 center=target, angle_mask=mask, hysteresis=np.array(expert.hysteresis))
        r, err = _subprocess("_crocoddyl_mpc_anchor.py", [str(f), str(out), "--threads", str(ctx.threads)],
                             ctx.threads)
        if r.get("missing"):
            return None, f"crocoddyl not installed ({r.get('error')}; pip install -e '.[bench]')"
        if err:
            return None, f"crocoddyl failed: {err}"
        with np.load(out, allow_pickle=False) as z:
            a = {k: z[k] for k in z.files}
    dx = float(np.abs(a["step_x"] - x_check[..., 1:, :].numpy()).max())
    droll = float(np.abs(a["rollout_x"] - x_check.numpy()).max())
    ours_c = cost.evaluate(x_check, u_check).numpy()
    dc = float((np.abs(a["check_cost"] - ours_c) / np.abs(ours_c)).max())
    if not (dx <= CROC_STEP_TOL and droll <= CROC_ROLLOUT_TOL and dc <= CROC_COST_TOL):
        return None, (f"crocoddyl model mismatch (step {dx:.1e}, rollout {droll:.1e}, cost {dc:.1e}): "
                      "not compared")
    a["note"] = r.get("note")
    return a, None


def _pendulum_expert(ctx: _Ctx) -> list[dict]:
    from learning.envs.single import make_task
    from learning.policies import MPCExpert

    task = make_task("PendulumSwingUp")
    expert = MPCExpert(task, ctx.sizes.pend_horizon, options=ctx.options(max_iter=20))
    H, S = expert.horizon, ctx.sizes.pend_steps
    # hanging 0.04π off the bottom, at rest: a genuine swing-up
    x0 = task.initial_state(torch.tensor([[0.02, 0.5]], dtype=torch.float64)).to(ctx.device, ctx.dtype)
    run = _closed_loop(task, expert, x0, S, ctx.device)
    step = _per_step(run["ms"])
    it_sum = float(run["iterations"].sum())
    iter_ms = sum(run["ms"]) / it_sum if it_sum > 0 else None
    a, note = _croc_pendulum(ctx, task, expert, x0, S)
    extra = {"horizon": H, "steps": S, "ours_iterations_per_step": it_sum / S,
             "ours_step_ms_median": step["median"], "ours_step_ms_max": step["max"],
             "ours_return": float(run["return"][0])}
    anchor = "crocoddyl BoxFDDP MPC (warm, 1 thread)"
    a_step = a_iter = None
    if a is not None:
        ms, iters = a["ms"][1:], a["iters"][1:]
        a_step = float(ms.mean())
        a_iter = float(ms.sum() / iters.sum()) if iters.sum() > 0 else None
        xa, ua = (torch.as_tensor(v) for v in (a["x"], a["u"]))
        extra.update(anchor_iterations_per_step=float(iters.mean()),
                     anchor_step_ms_median=float(np.median(ms)),
                     anchor_return=float(task.reward(xa[:-1], ua, xa[1:]).sum()), anchor_info=a.get("note"))
    case = f"PendulumSwingUp expert H={H}"
    return [_record(ctx, "pendulum_mpc_step", case, 1, step["mean"], anchor, a_step, note, **extra),
            _record(ctx, "pendulum_ilqr_iteration", case, 1, iter_ms, anchor, a_iter, note, **extra)]


def _car(ctx: _Ctx) -> list[dict]:
    from learning.envs.single import make_task
    from learning.policies import MPCExpert

    task = make_task("CarParking")
    expert = MPCExpert(task, ctx.sizes.car_horizon, options=ctx.options(max_iter=20))
    B = ctx.sizes.car_batch
    g = torch.Generator().manual_seed(0)
    noise = torch.rand(B, task.n_noise, generator=g, dtype=torch.float64)
    x0 = task.initial_state(noise).to(ctx.device, ctx.dtype)
    run = _closed_loop(task, expert, x0, ctx.sizes.car_steps, ctx.device)
    step = _per_step(run["ms"])
    return [_record(ctx, "car_parking_step", f"CarParking expert H={expert.horizon}", B, step["mean"],
                    horizon=expert.horizon, steps=ctx.sizes.car_steps, first_step_ms=run["first_ms"],
                    ours_step_ms_median=step["median"], ours_step_ms_max=step["max"],
                    ours_iterations_per_step=float(run["iterations"].mean()))]


# ---------------------------------------------------------------------------------------------- swing-ups
def _swingups(ctx: _Ctx, name: str) -> list[dict]:
    """``bench ilqr``'s crocoddyl comparison (``_croc_compare``: model check, ours batched, crocoddyl one by
    one, float64 CPU); ours is re-timed here when another dtype or device was asked for."""
    from controllers.ilqr import ilqr
    from liecontrol.bench import ilqr as bi

    s = ctx.sizes
    B, T = s.swing_batch, s.swing_horizon
    args = argparse.Namespace(threads=ctx.threads, anchor_repeats=1, croc_python=None, seed=0,
                              max_iter=s.swing_max_iter, repeats=ctx.reps(s.swing_repeats))
    opts = ctx.options(max_iter=s.swing_max_iter)
    x0_np = bi._x0(name, B, 0)
    variants = [(f"{name} swing-up", None)]
    if name == "pendulum":
        p = bi.PROBLEMS[name]["params"]
        variants.append(("pendulum swing-up (b=0)", [p[0], p[1], 0.0, p[3]]))
    workload = f"{name}_swingup_batch64"
    out = []
    for label, params in variants:
        rec = bi._croc_compare(name, label, x0_np, T, args, opts, params)
        ours_ms, dtype = rec.get("ours_ms"), torch.float64
        if ours_ms is None or (ctx.device.type, ctx.dtype) != ("cpu", torch.float64):
            dtype = ctx.dtype
            prob = bi._problem(name, torch.as_tensor(x0_np).to(ctx.device, ctx.dtype), T, params=params)
            ours_ms = ctx.time(lambda prob=prob: ilqr(prob, grad="none", options=opts), s.swing_repeats)
        ok = rec.get("anchor") == bi.CROC_LABEL
        note = None if ok else f"{rec.get('anchor')}: {rec.get('anchor_error') or ''}".rstrip(": ")
        keep = ("ours_cost", "anchor_cost", "ours_iters", "anchor_iters", "converged", "anchor_converged",
                "model_dx")
        extra = {k: rec[k] for k in keep if rec.get(k) is not None}
        out.append(_record(ctx, workload, label, B, ours_ms, "crocoddyl BoxFDDP (one by one)",
                           rec.get("anchor_ms") if ok else None, note, dtype=dtype, horizon=T,
                           max_iter=s.swing_max_iter, **extra))
    return out


# -------------------------------------------------------------------------------------------- the MPC head
def _mpc_head(ctx: _Ctx) -> list[dict]:
    try:
        from stable_baselines3.common.policies import ActorCriticPolicy

        from learning.mpc_policy import MPCActorCriticPolicy
    except ImportError as e:
        print(f"mpc_head_fwd_bwd skipped: stable-baselines3 is not installed ({e})")
        return []
    from learning.envs.single import make_task
    from learning.vector import TaskVectorEnv

    out = []
    for name in ("PendulumSwingUp", "CartPoleSwingUp"):
        task = make_task(name)
        env = TaskVectorEnv(task, 1)
        spaces = (env.single_observation_space, env.single_action_space)
        torch.manual_seed(0)
        ours = MPCActorCriticPolicy(*spaces, lambda _: 3e-4, task=task, compile=ctx.compile).to(ctx.device)
        mlp = ActorCriticPolicy(*spaces, lambda _: 3e-4).to(ctx.device)
        for B in ctx.sizes.head_batches:
            g = torch.Generator().manual_seed(B)
            x = task.initial_state(torch.rand(B, task.n_noise, generator=g, dtype=torch.float64))
            obs = task.observe(x).to(ctx.device, torch.float32)
            act = (2 * torch.rand(B, task.m, generator=g) - 1).to(ctx.device)
            ms = {}
            for key, pol in (("ours", ours), ("mlp", mlp)):
                def fwd_bwd(pol=pol, obs=obs, act=act):
                    pol.zero_grad(set_to_none=True)
                    values, logp, ent = pol.evaluate_actions(obs, act)
                    (values.sum() - logp.sum() - ent.sum()).backward()

                ms[key] = ctx.time(fwd_bwd)
            out.append(_record(ctx, "mpc_head_fwd_bwd", f"{name} H={ours.horizon}", B, ms["ours"],
                               "SB3 MlpPolicy (fwd+bwd)", ms["mlp"], dtype=torch.float32, task=name,
                               horizon=ours.horizon, max_iter=ours.max_iter))
    return out


# ------------------------------------------------------------------------------------------------ cookbook
#: the cookbook manipulator (seed 004 §9.1, Fig. 23; the RCFS script iLQR_manipulator): three links of
#: lengths 2, 2, 1 under joint-velocity commands, Δt = 0.01, 49 control steps, end-effector pose (x, y,
#: orientation) at two via points (state indices 24 and 49, the figure's t = 25 and 50), identity
#: precision, control weight R = 1e-6 I, from x0 = (3π/4, -π/2, -π/4)
COOKBOOK = dict(lengths=(2.0, 2.0, 1.0), dt=1e-2, T=49, x0=(3 * math.pi / 4, -math.pi / 2, -math.pi / 4),
                via_t=(24, 49), via_mu=((2.0, 1.0, -math.pi / 6), (3.0, 1.0, -math.pi / 3)), r=1e-6,
                alpha_min=1e-3)

#: the cookbook car (seed 004 §9.15, Eq. 118; the RCFS script iLQR_car): the velocity-input car of
#: :class:`~controllers.systems.car_velocity.CarVelocity` (``params`` = wheelbase ℓ 0.5 m, Δt 0.1 s; explicit
#: Euler, Eq. 192), 100 control steps from rest at the origin to the state (4, 3, π/2, 0) (a quarter turn,
#: 5 m away): final-state precision ``qT I`` = 1e3 I and none before, R = 1e-3 I, from zero controls (at
#: zero speed the linearization cannot steer, ``B_t``'s steering entries vanish: the first iterations only
#: drive, then the plan turns)
COOKBOOK_CAR = dict(params=(0.5, 0.1), T=100, x0=(0.0,) * 4, target=(4.0, 3.0, math.pi / 2, 0.0), qT=1e3,
                    r=1e-3, u_init=(0.0, 0.0), alpha_min=1e-3)
#: the cookbook bicopter (seed 004 §9.16, Eq. 120; the RCFS script iLQR_bicopter):
#: :class:`~controllers.systems.bicopter.Bicopter` with its defaults (``params`` = m 2.5 kg, I 1.2 kg m²,
#: ℓ 0.5 m, g 9.81, Δt 0.05 s; semi-implicit Euler, the seed's absolute thrusts), 100 control steps from
#: rest at the origin to rest, level, at (1, 1): Q_T = 1e3 I and none before, R = 1e-2 I, from the hover
#: thrust m g / 2 of each rotor.  (R acts on the absolute thrusts, so holding hover costs about 300 and
#: dominates; with R = 1e-3 the script's plain Gauss-Newton creeps in its last digits, the recursive solver
#: stops in 31 iterations where the script's cost still differs in the 7th digit.)
COOKBOOK_BICOPTER = dict(params=(2.5, 1.2, 0.5, 9.81, 0.05), T=100, x0=(0.0,) * 6,
                         target=(1.0, 1.0, 0.0, 0.0, 0.0, 0.0), qT=1e3, r=1e-2, u_init=(2.5 * 9.81 / 2,) * 2,
                         alpha_min=1e-3)


def cookbook_problem(dtype: torch.dtype = torch.float64, device=None):
    """The cookbook manipulator as an :class:`~controllers.ilqr.ILQRProblem`: kinematics of
    :class:`~controllers.systems.arm.PlanarArm`, :class:`~controllers.dynamics.LinearDynamics` ``(I, Δt I)``
    and a :class:`~controllers.costs.ResidualCost` with the analytic Jacobian (seed 004 Eq. 102-105)."""
    from controllers.costs import ResidualCost
    from controllers.dynamics import LinearDynamics
    from controllers.ilqr import ILQRProblem
    from controllers.systems.arm import PlanarArm

    c, kw = COOKBOOK, dict(dtype=dtype, device=device)
    k, T = len(c["lengths"]), c["T"]
    arm = PlanarArm(links=k, lengths=c["lengths"])
    mu = torch.zeros(T + 1, 3, **kw)
    Q = torch.zeros(T + 1, 3, 3, **kw)
    for t, m in zip(c["via_t"], c["via_mu"]):
        mu[t] = torch.tensor(m, **kw)
        Q[t] = torch.eye(3, **kw)

    def residual(x):
        return torch.cat([arm.end_effector(x), x.sum(-1, keepdim=True)], -1) - mu

    def jacobian(x):
        return torch.cat([arm.ee_jacobian(x), torch.ones_like(x)[..., None, :]], -2)

    cost = ResidualCost(residual, Q, c["r"] * torch.eye(k, **kw), jacobian=jacobian)
    eye = torch.eye(k, **kw)
    return ILQRProblem(LinearDynamics(eye, c["dt"] * eye), cost, torch.tensor(c["x0"], **kw), T)


def _vehicle_problem(system, c: dict, dtype: torch.dtype, device, horizon: int | None):
    """``system`` reaching ``c["target"]`` at the last of ``horizon`` (default ``c["T"]``) steps: a
    :class:`~controllers.costs.QuadraticCost` with ``Q_t = 0`` for ``t < T``, ``Q_T = qT I``, ``R = r I``
    (seed 004 Eq. 106 with a final target)."""
    from controllers.costs import QuadraticCost
    from controllers.ilqr import ILQRProblem

    kw = dict(dtype=dtype, device=device)
    T, n = horizon or c["T"], system.n
    Q = torch.zeros(T + 1, n, n, **kw)
    Q[-1] = c["qT"] * torch.eye(n, **kw)
    cost = QuadraticCost(Q, c["r"] * torch.eye(system.m, **kw), x_ref=torch.tensor(c["target"], **kw))
    return ILQRProblem(system.dynamics(), cost, torch.tensor(c["x0"], **kw), T)


def cookbook_car_problem(dtype: torch.dtype = torch.float64, device=None, horizon: int | None = None):
    """The cookbook car (:data:`COOKBOOK_CAR`) as an :class:`~controllers.ilqr.ILQRProblem` over ``horizon``
    control steps (default 100); its initial controls: :func:`cookbook_u_init`."""
    from controllers.systems.car_velocity import CarVelocity

    length, dt = COOKBOOK_CAR["params"]
    return _vehicle_problem(CarVelocity(length=length, dt=dt), COOKBOOK_CAR, dtype, device, horizon)


def cookbook_bicopter_problem(dtype: torch.dtype = torch.float64, device=None, horizon: int | None = None):
    """The cookbook bicopter (:data:`COOKBOOK_BICOPTER`, absolute thrusts) as an
    :class:`~controllers.ilqr.ILQRProblem` over ``horizon`` control steps (default 100); its initial
    controls (hover thrust): :func:`cookbook_u_init`."""
    from controllers.systems.bicopter import Bicopter

    mass, inertia, arm, gravity, dt = COOKBOOK_BICOPTER["params"]
    system = Bicopter(mass=mass, inertia=inertia, arm=arm, gravity=gravity, dt=dt, hover_relative=False)
    return _vehicle_problem(system, COOKBOOK_BICOPTER, dtype, device, horizon)


def cookbook_u_init(c: dict, prob) -> torch.Tensor:
    """Initial controls ``(T, m)`` of the problem ``prob`` built from ``c``: ``c["u_init"]`` at every step."""
    return torch.tensor(c["u_init"], dtype=prob.dtype, device=prob.device).expand(prob.T, prob.m)


def _cookbook_starts(prob, batch: int, seed: int = 0, spread: float = 0.2):
    """The problem from ``batch`` starts: the script's own and perturbations of it, uniform in ``±spread`` in
    every state coordinate (rad for the manipulator; m, rad, m/s for the vehicles)."""
    from controllers.ilqr import ILQRProblem

    g = torch.Generator().manual_seed(seed)
    d = spread * (2 * torch.rand(batch, prob.n, generator=g, dtype=torch.float64) - 1)
    d[0] = 0
    x0 = prob.x0 + d.to(dtype=prob.x0.dtype, device=prob.x0.device)
    return ILQRProblem(prob.dynamics, prob.cost, x0, prob.T)


def _cookbook_anchor(ctx: _Ctx, prob, iters: int) -> tuple[dict, str | None]:
    with tempfile.TemporaryDirectory() as tmp:
        f = Path(tmp) / "cookbook.npz"
        np.savez(f, **{k: np.asarray(v) for k, v in COOKBOOK.items()}, Q=np.eye(3), iterations=iters)
        return _subprocess("_cookbook_anchor.py", [str(f), "--repeats", str(ctx.reps())], ctx.threads)


def _vehicle_anchor(system: str, c: dict, ctx: _Ctx, prob, iters: int) -> tuple[dict, str | None]:
    """``_cookbook_vehicle_anchor.py`` on the problem ``prob`` built from ``c`` (its horizon)."""
    n, T = prob.n, prob.T
    with tempfile.TemporaryDirectory() as tmp:
        f = Path(tmp) / f"{system}.npz"
        np.savez(f, system=np.array(system), params=np.asarray(c["params"], float), T=np.array(T),
                 x0=np.asarray(c["x0"], float), target=np.asarray(c["target"], float),
                 QT=c["qT"] * np.eye(n), r=np.array(float(c["r"])),
                 u_init=np.tile(np.asarray(c["u_init"], float), (T, 1)), iterations=np.array(iters),
                 alpha_min=np.array(float(c["alpha_min"])))
        return _subprocess("_cookbook_vehicle_anchor.py", [str(f), "--repeats", str(ctx.reps())], ctx.threads)


@dataclasses.dataclass(frozen=True)
class _CookbookCase:
    """One cookbook workload: its problem on our side (and initial controls, ``None``: zeros), and the
    numpy script's run on the same problem for a given iteration count."""

    system: str
    anchor: str
    problem: Callable[[_Ctx], object]
    u_init: Callable[[object], torch.Tensor | None]
    run_anchor: Callable[[_Ctx, object, int], tuple[dict, str | None]]
    slow_batch: bool = False  # time the batch rows ``cookbook_vehicle_batch_repeats`` times (not ``repeats``)
    #: the solvers of the batch rows.  The vehicles' batch is the recursive solver's alone: ``ilqr_lifted``
    #: on nonlinear dynamics builds dense transfer matrices per element, and every element runs to the
    #: slowest one's iteration count (64 cars 50 s, 64 bicopters 69 s a call: 116x / 64x one problem)
    batch_methods: tuple[str, ...] = ("recursive", "lifted")


_COOKBOOK_CASES = {
    "cookbook_manipulator": _CookbookCase(
        "manipulator", "numpy batch iLQR (cookbook §8.1/§9.1)",
        lambda ctx: cookbook_problem(ctx.dtype, ctx.device), lambda prob: None, _cookbook_anchor),
    "cookbook_car": _CookbookCase(
        "car", "numpy batch iLQR (cookbook §8.1/§9.15)",
        lambda ctx: cookbook_car_problem(ctx.dtype, ctx.device, ctx.sizes.cookbook_car_T),
        lambda prob: cookbook_u_init(COOKBOOK_CAR, prob),
        lambda ctx, prob, iters: _vehicle_anchor("car", COOKBOOK_CAR, ctx, prob, iters), slow_batch=True,
        batch_methods=("recursive",)),
    "cookbook_bicopter": _CookbookCase(
        "bicopter", "numpy batch iLQR (cookbook §8.1/§9.16)",
        lambda ctx: cookbook_bicopter_problem(ctx.dtype, ctx.device, ctx.sizes.cookbook_bicopter_T),
        lambda prob: cookbook_u_init(COOKBOOK_BICOPTER, prob),
        lambda ctx, prob, iters: _vehicle_anchor("bicopter", COOKBOOK_BICOPTER, ctx, prob, iters),
        slow_batch=True, batch_methods=("recursive",)),
}


def _cookbook(ctx: _Ctx, workload: str) -> list[dict]:
    """One problem by ``ilqr`` (recursive, batch) and ``ilqr_lifted`` against the numpy script at the same
    iteration count, then a batch of ``cookbook_batch`` starts (no anchor: the script solves one problem;
    ``per_one`` is the batch's time over the same solver's time on one)."""
    from controllers.ilqr import ilqr
    from controllers.ilqr_lifted import ilqr_lifted

    case = _COOKBOOK_CASES[workload]
    prob = case.problem(ctx)
    u0 = case.u_init(prob)
    w0 = None if u0 is None else u0.reshape(-1)  # u = Ψ w with Ψ = I: w is u stacked in time
    solvers = {
        "recursive": lambda pr: ilqr(pr, method="recursive", grad="none", options=ctx.options(), u_init=u0),
        "batch": lambda pr: ilqr(pr, method="batch", grad="none", options=ctx.options(), u_init=u0),
        "lifted": lambda pr: ilqr_lifted(pr, w_init=w0),
    }
    out, one = [], {}
    for method, solve in solvers.items():
        sol = solve(prob)
        iters = int(sol.status.iterations)
        ms = one[method] = ctx.time(lambda solve=solve: solve(prob))
        r, err = case.run_anchor(ctx, prob, iters)
        extra = {"system": case.system, "horizon": prob.T, "method": method, "iterations": iters,
                 "ours_cost": float(sol.cost), "status": sol.status.reason_names()[0]}
        if err is None:
            ua = torch.tensor(r["u"], dtype=torch.float64).reshape(sol.u.shape)
            extra.update(anchor_cost=r["cost"], max_abs_diff_u=float((ua - sol.u.double().cpu()).abs().max()))
        out.append(_record(ctx, workload, f"{case.system} {method}", 1, ms, case.anchor,
                           r.get("ms") if err is None else None,
                           None if err is None else f"numpy anchor failed: {err}", **extra))
    batch = _cookbook_starts(prob, ctx.sizes.cookbook_batch)
    reps = ctx.sizes.cookbook_vehicle_batch_repeats if case.slow_batch else None
    for method in case.batch_methods:
        sol = solvers[method](batch)
        ms = ctx.time(lambda method=method: solvers[method](batch), reps)
        out.append(_record(ctx, workload, f"{case.system} {method}", batch.x0.shape[0], ms,
                           system=case.system, horizon=prob.T, method=method, per_one=ms / one[method],
                           iterations=int(sol.status.iterations.max()),
                           iterations_median=float(sol.status.iterations.double().median()),
                           converged=int(sol.status.converged.sum())))
    return out


# ------------------------------------------------------------------------------------------------- driver
_RUNNERS: dict[str, Callable[[_Ctx], list[dict]]] = {
    "quadrotor_step": _quadrotor,
    "pendulum_mpc_step": _pendulum_expert,
    "pendulum_ilqr_iteration": _pendulum_expert,
    "cartpole_swingup_batch64": lambda ctx: _swingups(ctx, "cartpole"),
    "pendulum_swingup_batch64": lambda ctx: _swingups(ctx, "pendulum"),
    "car_parking_step": _car,
    "mpc_head_fwd_bwd": _mpc_head,
    "cookbook_manipulator": lambda ctx: _cookbook(ctx, "cookbook_manipulator"),
    "cookbook_car": lambda ctx: _cookbook(ctx, "cookbook_car"),
    "cookbook_bicopter": lambda ctx: _cookbook(ctx, "cookbook_bicopter"),
}


def measure(workloads=WORKLOADS, *, sizes: Sizes = DEFAULT_SIZES, dtype: torch.dtype = torch.float64,
            device: str = "cpu", threads: int = 1, repeats: int | None = None, compile: bool = True,
            log=print) -> list[dict]:
    """The records of ``workloads`` (module docstring), in the order of :data:`WORKLOADS`."""
    ctx = _Ctx(sizes, dtype, torch.device(device), threads, repeats, compile)
    done, records = set(), []
    for w in WORKLOADS:
        fn = _RUNNERS[w]
        if w not in workloads or fn in done:
            continue
        done.add(fn)
        log(f"measuring {w} ...")
        records += [r for r in fn(ctx) if r["workload"] in workloads]
    return records


def _print(records: list[dict]) -> None:
    print_table(records, COLUMNS)
    print("ratio = anchor_ms / ours_ms (above 1: ours is faster); anchors run on the CPU in float64")
    for r in records:
        if r["workload"].startswith("cookbook_") and "anchor_cost" in r:
            print(f"cookbook {r['system']} ({r['method']}): cost ours {r['ours_cost']:.9g} after "
                  f"{r['iterations']} iterations ({r['status']}), numpy anchor {r['anchor_cost']:.9g} after "
                  f"as many (max |du| {r['max_abs_diff_u']:.1e})")
        if r["workload"] == "pendulum_mpc_step" and "anchor_return" in r:
            print(f"pendulum closed loop ({r['steps'] + 1} steps): return ours {r['ours_return']:.4g}, "
                  f"crocoddyl {r['anchor_return']:.4g}; iterations per step ours "
                  f"{r['ours_iterations_per_step']:.2f}, crocoddyl {r['anchor_iterations_per_step']:.2f}")
    notes: dict[str, list[str]] = {}
    for r in records:
        for key in ("anchor_note", "anchor_info"):
            if r.get(key):
                notes.setdefault(r[key], []).append(r["workload"])
    for text, where in notes.items():
        print(f"note [{', '.join(dict.fromkeys(where))}]: {text}")


@restores_threads
def run(args) -> int:
    torch.set_num_threads(args.threads)
    sizes = QUICK_SIZES if args.quick else DEFAULT_SIZES
    records = measure(args.workloads, sizes=sizes, dtype=_DTYPES[args.dtype], device=args.device,
                      compile=not args.eager,
                      threads=args.threads, repeats=args.repeats)
    _print(records)
    if args.json:
        write_json(args.json, records)
    return 0


if __name__ == "__main__":  # pragma: no cover
    ap = argparse.ArgumentParser()
    add_arguments(ap)
    sys.exit(run(ap.parse_args()))
