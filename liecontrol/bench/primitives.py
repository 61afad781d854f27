"""``liecontrol bench primitives``: movement primitives as LQT (issue 26 §3; :mod:`learning.primitives`) side
by side with DFKI's ``movement_primitives`` (DMP and ProMP) on the same demos, in the same run.

Demos: :func:`learning.demos.handwriting` (2-D letters in a unit box, ``--n-demos`` per letter, ``--T``
samples over 1 s, ``dt = 1/(T-1)``; generator seed 0), float64 on the CPU, the same arrays on both sides
(ours as tensors, the anchor's as numpy copies).  Lengths are in units of the letters' box.

DMP — ours: :func:`~learning.primitives.fit_dmp` (an LQT per demo, double integrator, 20 RBFs, all demos in
one batch) and :meth:`~learning.primitives.DMP.reproduce` (closed loop ``u = û + K (x - x̂)``); anchor:
``movement_primitives.dmp.DMP(2, execution_time=1, dt, n_weights_per_dim=20)`` (its defaults
``alpha_y = 25``, ``beta_y = 6.25``, RK4 steps), one ``imitate`` per demo, rolled out step by step with
``step`` after ``configure(start_y, start_yd)`` so that both sides start from the demo's
``[p_0; (p_1 - p_0)/dt]`` (``open_loop`` starts at rest; its error is printed as a note).

* ``reproduction_rms``: RMS over time of ``‖p_t - demo_t‖`` of each demo's own DMP from the demo's start,
  mean over all demos of all letters (``max`` in the JSON).
* ``push_final_to_goal``, ``push_peak_dev``: the position is pushed by ``(0.1, -0.1)`` at step ``T // 2``
  (ours: ``reproduce(perturbation=, at=)``; the anchor: its state ``current_y`` moved between two ``step``
  calls) and integrated on: distance to the demo's last sample at the end, and the largest distance to the
  unpushed run from the push on (:func:`~learning.primitives.perturbation_recovery`); mean over demos.
* ``fit_ms``: fitting every demo of every letter (ours one batched call, the anchor a loop of ``imitate``).
* ``generate_ms``: ``--n-generate`` reproductions of the first letter's first demo from as many starts
  ``p_0 + 0.05 ε`` (``ε ~ N(0, I)``, seed 1) — ours one batched ``reproduce(x0=...)``, the anchor a loop of
  step-wise rollouts.

ProMP — ours: :func:`~learning.primitives.fit_promp` (an LQT with control primitives: a double integrator
whose accelerations are ``Ψ w`` on 10 RBFs per dimension; a Gaussian on ``[x_1; w]`` by ridge least squares
per demo and the sample covariance; all letters in one batch); anchor: ``movement_primitives.promp.ProMP(2,
n_weights_per_dim=10)`` (positions ``= Φ w`` on 10 RBFs, fitted by its EM ``imitate``), one per letter.

* ``reproduction_rms``: RMS over time of the distance between the mean trajectory and the demos' pointwise
  mean, mean over letters.
* ``push_final_to_goal``, ``push_peak_dev``: ours :meth:`~learning.primitives.ProMP.track` (minimal
  intervention LQT) with the same push at ``T // 2`` (goal: the mean's last position, deviation from the
  unpushed tracking); the anchor's ProMP has no feedback controller: "not supported", null.
* ``via_point_err``: conditioned (noiselessly) on the first demo's position at step ``round(0.6 (T-1))``
  (ours ``condition``, the anchor ``condition_position(t = step·dt, t_max = 1)``): distance of the
  conditioned mean at that step, mean over letters (``max`` in the JSON).  DMP: not applicable (neither
  side's DMP conditions on via points).
* ``fit_ms``: every letter (ours one batched call, the anchor a loop of EM fits).
* ``generate_ms``: ``--n-generate`` samples of the first letter's distribution (ours ``sample``, one batched
  call, full states; the anchor ``sample_trajectories``, positions).

Timing: :func:`liecontrol.report.time_ms`, median of ``--repeats`` after one warm-up call, both sides in this
process with torch's intra-op threads and numpy's BLAS pinned to ``--threads`` (threadpoolctl when it is
installed, else the loaded OpenBLAS's ``set_num_threads``).  Records (``--json``): one per (method, metric,
side) with ``value``, ``unit`` (``box`` or ``ms``) and on the anchor's rows ``ratio = anchor / ours`` (above
1: ours is lower, i.e. faster or more accurate).  A missing anchor gives null anchor values and a note.
"""

from __future__ import annotations

import ctypes
import time
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
import torch

from liecontrol.report import fmt, print_table, restores_threads, time_ms, write_json

__all__ = ["run", "measure", "Sizes", "DEFAULT_SIZES", "QUICK_SIZES", "ANCHOR", "COLUMNS"]

ANCHOR = "movement_primitives"
COLUMNS = ["method", "metric", "side", "value", "unit", "ratio", "note"]
PUSH = (0.1, -0.1)  # the mid-course push of the positions
START_NOISE = 0.05  # std of the perturbed starts of the DMP generation
VIA_FRACTION = 0.6
DMP_BASIS = 20
PROMP_BASIS = 10
DEMO_SEED, START_SEED, SAMPLE_SEED = 0, 1, 2


@dataclass(frozen=True)
class Sizes:
    """The sizes of one run."""

    letters: str = "SCUN"
    n_demos: int = 8
    T: int = 100
    n_generate: int = 1000
    repeats: int = 3


DEFAULT_SIZES = Sizes()
QUICK_SIZES = Sizes(letters="SC", n_demos=4, T=40, n_generate=20, repeats=1)


# ------------------------------------------------------------------------------------------ thread pinning


def _openblas_handles() -> list[tuple[Callable, Callable]]:
    """``(get, set)`` thread-count functions of the OpenBLAS libraries loaded in this process."""
    try:
        with open("/proc/self/maps") as f:
            paths = {line.split()[-1] for line in f if "openblas" in line.lower() and "/" in line}
    except OSError:
        return []
    out = []
    for path in sorted(paths):
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for get_name, set_name in (("openblas_get_num_threads", "openblas_set_num_threads"),
                                   ("scipy_openblas_get_num_threads64_", "scipy_openblas_set_num_threads64_"),
                                   ("openblas_get_num_threads64_", "openblas_set_num_threads64_")):
            get, set_ = getattr(lib, get_name, None), getattr(lib, set_name, None)
            if get is not None and set_ is not None:
                get.restype = ctypes.c_int
                set_.argtypes = [ctypes.c_int]
                out.append((get, set_))
                break
    return out


@contextmanager
def _numpy_threads(n: int):
    """Pin numpy's BLAS to ``n`` threads inside the block; yields how (or why not)."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        threadpool_limits = None
    if threadpool_limits is not None:
        with threadpool_limits(limits=n):
            yield "threadpoolctl"
        return
    handles = _openblas_handles()
    before = [get() for get, _ in handles]
    for _, set_ in handles:
        set_(n)
    try:
        yield "OpenBLAS set_num_threads" if handles else "not pinned (no threadpoolctl, no OpenBLAS found)"
    finally:
        for (_, set_), b in zip(handles, before):
            set_(b)


# ------------------------------------------------------------------------------------------ the demos


@dataclass(frozen=True)
class _Data:
    X: torch.Tensor  # (L, N, T, 2) float64
    dt: float
    t_via: int
    via: torch.Tensor  # (L, 1, 2) the first demo's position at t_via
    starts: torch.Tensor  # (n_generate, 1, 2) perturbed starts of the first letter's first demo

    @property
    def duration(self) -> float:
        return self.dt * (self.X.shape[-2] - 1)


def _data(sizes: Sizes) -> _Data:
    from learning.demos import handwriting

    g = torch.Generator().manual_seed(DEMO_SEED)
    demos = handwriting(sizes.letters, sizes.n_demos, sizes.T, generator=g)
    X = torch.stack([demos[c].x for c in dict.fromkeys(sizes.letters.upper())])
    dt = demos[sizes.letters[0].upper()].dt
    t_via = round(VIA_FRACTION * (sizes.T - 1))
    gs = torch.Generator().manual_seed(START_SEED)
    starts = X[0, 0, 0] + START_NOISE * torch.randn(sizes.n_generate, 1, 2, generator=gs, dtype=X.dtype)
    return _Data(X=X, dt=dt, t_via=t_via, via=X[:, 0, t_via].unsqueeze(-2), starts=starts)


def _median_time(fn: Callable[[], object], repeats: int) -> float:
    return time_ms(fn, repeats=repeats, warmup=1)


# ------------------------------------------------------------------------------------------ ours


def _ours(data: _Data, sizes: Sizes) -> dict[tuple[str, str], dict]:
    from learning.primitives import (
        fit_dmp,
        fit_promp,
        perturbation_recovery,
        reproduction_error,
        via_point_error,
    )

    X, dt, T = data.X, data.dt, data.X.shape[-2]
    at = T // 2
    push = torch.tensor(PUSH, dtype=X.dtype)
    out: dict[tuple[str, str], dict] = {}

    # DMP
    dmp = fit_dmp(X, dt=dt, n_basis=DMP_BASIS)
    nominal = dmp.reproduce()
    err = reproduction_error(X, nominal.x)
    out["DMP", "reproduction_rms"] = {"value": float(err.mean()), "max": float(err.max())}
    pushed = dmp.reproduce(perturbation=push, at=at)
    rec = perturbation_recovery(nominal.x, pushed.x, at, d=2)
    to_goal = (pushed.x[..., -1, :2] - X[..., -1, :]).norm(dim=-1)
    out["DMP", "push_final_to_goal"] = {"value": float(to_goal.mean()), "max": float(to_goal.max())}
    out["DMP", "push_peak_dev"] = {"value": float(rec.peak.mean()), "max": float(rec.peak.max())}
    out["DMP", "fit_ms"] = {"value": _median_time(lambda: fit_dmp(X, dt=dt, n_basis=DMP_BASIS),
                                                  sizes.repeats)}
    one = fit_dmp(X[0, :1], dt=dt, n_basis=DMP_BASIS)  # batch (1,): the first letter's first demo
    gen = one.reproduce(x0=data.starts)
    assert gen.x.shape == (sizes.n_generate, 1, T, 4)
    out["DMP", "generate_ms"] = {"value": _median_time(lambda: one.reproduce(x0=data.starts), sizes.repeats)}

    # ProMP
    pm = fit_promp(X, dt=dt, n_basis=PROMP_BASIS)
    mu = pm.mean_trajectory()
    err = reproduction_error(X.mean(-3), mu)
    out["ProMP", "reproduction_rms"] = {"value": float(err.mean()), "max": float(err.max())}
    track0 = pm.track()
    track = pm.track(perturbation=push, at=at)
    rec = perturbation_recovery(track0.x, track.x, at, d=2)
    to_goal = (track.x[..., -1, :2] - mu[..., -1, :2]).norm(dim=-1)
    out["ProMP", "push_final_to_goal"] = {"value": float(to_goal.mean()), "max": float(to_goal.max())}
    out["ProMP", "push_peak_dev"] = {"value": float(rec.peak.mean()), "max": float(rec.peak.max())}
    cond = pm.condition([data.t_via], data.via)
    via = via_point_error(cond.mean_trajectory(), [data.t_via], data.via)
    out["ProMP", "via_point_err"] = {"value": float(via.mean()), "max": float(via.max())}
    out["ProMP", "fit_ms"] = {"value": _median_time(lambda: fit_promp(X, dt=dt, n_basis=PROMP_BASIS),
                                                    sizes.repeats)}
    first = fit_promp(X[0], dt=dt, n_basis=PROMP_BASIS)
    g = torch.Generator().manual_seed(SAMPLE_SEED)
    assert first.sample(sizes.n_generate, g).shape == (sizes.n_generate, T, 4)
    out["ProMP", "generate_ms"] = {"value": _median_time(lambda: first.sample(sizes.n_generate, g),
                                                         sizes.repeats)}
    return out


# ------------------------------------------------------------------------------------------ the anchor


def _rollout(m, y0: np.ndarray, yd0: np.ndarray, T: int, push: np.ndarray | None = None,
             at: int | None = None) -> np.ndarray:
    """``(T, D)`` positions of the anchor's DMP ``m`` integrated step by step from ``(y0, yd0)``; with
    ``push``, its state ``current_y`` is moved by ``push`` once it has reached step ``at``."""
    m.configure(start_y=y0, start_yd=yd0)
    m.reset()
    Y = np.empty((T, y0.shape[0]))
    Y[0] = y = y0
    yd = yd0
    for t in range(1, T):
        y, yd = m.step(y, yd)
        if push is not None and t == at:
            m.current_y += push
            y = m.current_y.copy()
        Y[t] = y
    return Y


def _anchor(data: _Data, sizes: Sizes) -> dict[tuple[str, str], dict]:
    from movement_primitives.dmp import DMP as TheirDMP
    from movement_primitives.promp import ProMP as TheirProMP

    from learning.primitives import perturbation_recovery, reproduction_error, via_point_error

    X = data.X.numpy()
    L, N, T, D = X.shape
    dt, duration = data.dt, data.duration
    at = T // 2
    push = np.asarray(PUSH)
    times = np.linspace(0.0, duration, T)
    out: dict[tuple[str, str], dict] = {}

    # DMP
    def fit_dmps() -> list:
        dmps = []
        for i in range(L * N):
            m = TheirDMP(D, execution_time=duration, dt=dt, n_weights_per_dim=DMP_BASIS)
            m.imitate(times.copy(), X.reshape(L * N, T, D)[i])
            dmps.append(m)
        return dmps

    dmps = fit_dmps()
    flat = X.reshape(L * N, T, D)
    v0 = (flat[:, 1] - flat[:, 0]) / dt  # the demos' start velocities (ours: the same forward difference)
    nominal = np.stack([_rollout(m, flat[i, 0], v0[i], T) for i, m in enumerate(dmps)])
    err = reproduction_error(flat, nominal)
    open_loop = []
    for i, m in enumerate(dmps):  # the anchor's own open loop starts at rest (start_yd = 0)
        m.configure(start_y=flat[i, 0], start_yd=np.zeros(D))
        Y = m.open_loop()[1][:T]
        open_loop.append(Y if Y.shape[0] == T else np.full((T, D), np.nan))
    err_ol = reproduction_error(flat, np.stack(open_loop))
    out["DMP", "reproduction_rms"] = {"value": float(err.mean()), "max": float(err.max()),
                                      "open_loop_value": float(err_ol.mean())}
    pushed = np.stack([_rollout(m, flat[i, 0], v0[i], T, push, at) for i, m in enumerate(dmps)])
    rec = perturbation_recovery(nominal, pushed, at, d=D)
    to_goal = np.linalg.norm(pushed[:, -1] - flat[:, -1], axis=-1)
    out["DMP", "push_final_to_goal"] = {"value": float(to_goal.mean()), "max": float(to_goal.max())}
    out["DMP", "push_peak_dev"] = {"value": float(rec.peak.mean()), "max": float(rec.peak.max())}
    out["DMP", "fit_ms"] = {"value": _median_time(fit_dmps, sizes.repeats)}
    first, starts = dmps[0], data.starts[:, 0].numpy()

    def generate_dmp() -> np.ndarray:
        return np.stack([_rollout(first, s, v0[0], T) for s in starts])

    assert generate_dmp().shape == (sizes.n_generate, T, D)
    out["DMP", "generate_ms"] = {"value": _median_time(generate_dmp, sizes.repeats)}

    # ProMP
    def fit_promps() -> list:
        ps = []
        for letter in range(L):
            p = TheirProMP(D, n_weights_per_dim=PROMP_BASIS)
            p.imitate([times.copy() for _ in range(N)], X[letter])
            ps.append(p)
        return ps

    promps = fit_promps()
    mu = np.stack([p.mean_trajectory(times.copy()) for p in promps])
    err = reproduction_error(X.mean(1), mu)
    out["ProMP", "reproduction_rms"] = {"value": float(err.mean()), "max": float(err.max())}
    note = "not supported (no feedback controller)"
    out["ProMP", "push_final_to_goal"] = {"value": None, "note": note}
    out["ProMP", "push_peak_dev"] = {"value": None, "note": note}
    targets = data.via.numpy()  # (L, 1, D)
    cond = np.stack([p.condition_position(targets[k, 0], t=data.t_via * dt, t_max=duration)
                     .mean_trajectory(times.copy()) for k, p in enumerate(promps)])
    via = via_point_error(cond, [data.t_via], targets)
    out["ProMP", "via_point_err"] = {"value": float(via.mean()), "max": float(via.max())}
    out["ProMP", "fit_ms"] = {"value": _median_time(fit_promps, sizes.repeats)}
    rs = np.random.RandomState(SAMPLE_SEED)
    assert promps[0].sample_trajectories(times.copy(), sizes.n_generate, rs).shape == (sizes.n_generate, T, D)
    out["ProMP", "generate_ms"] = {"value": _median_time(
        lambda: promps[0].sample_trajectories(times.copy(), sizes.n_generate, rs), sizes.repeats)}
    return out


# ------------------------------------------------------------------------------------------ records

_METRICS = (("DMP", "reproduction_rms"), ("DMP", "push_final_to_goal"), ("DMP", "push_peak_dev"),
            ("DMP", "fit_ms"), ("DMP", "generate_ms"),
            ("ProMP", "reproduction_rms"), ("ProMP", "push_final_to_goal"), ("ProMP", "push_peak_dev"),
            ("ProMP", "via_point_err"), ("ProMP", "fit_ms"), ("ProMP", "generate_ms"))


def _records(ours: dict, theirs: dict | None, why: str | None, sizes: Sizes, threads: int, pinning: str
             ) -> list[dict]:
    common = {"bench": "primitives", "letters": sizes.letters, "n_demos": sizes.n_demos, "T": sizes.T,
              "n_generate": sizes.n_generate, "repeats": sizes.repeats, "threads": threads,
              "numpy_threads": pinning, "dtype": "float64", "device": "cpu", "seed": DEMO_SEED}
    recs = []
    for method, metric in _METRICS:
        unit = "ms" if metric.endswith("_ms") else "box"
        mine = ours[method, metric]
        recs.append({"method": method, "metric": metric, "side": "ours", **mine, "unit": unit, "ratio": None,
                     **common})
        other = dict(theirs[method, metric]) if theirs is not None else {"value": None,
                                                                          "note": f"{ANCHOR} missing: {why}"}
        a, o = other.get("value"), mine["value"]
        ratio = a / o if a is not None and o else None
        recs.append({"method": method, "metric": metric, "side": ANCHOR, **other, "unit": unit,
                     "ratio": ratio, **common})
    return recs


def measure(sizes: Sizes = DEFAULT_SIZES, threads: int = 1, log=print) -> list[dict]:
    """The records of one run (module docstring)."""
    torch.set_num_threads(threads)
    with _numpy_threads(threads) as pinning:
        data = _data(sizes)
        log(f"measuring ours (learning.primitives) on {len(sizes.letters)} letters x {sizes.n_demos} demos, "
            f"T = {sizes.T} ...")
        ours = _ours(data, sizes)
        theirs, why = None, None
        try:
            import movement_primitives.dmp  # noqa: F401
            import movement_primitives.promp  # noqa: F401
        except ImportError as e:
            why = f"{type(e).__name__}: {e}"
        if why is None:
            log(f"measuring {ANCHOR} ...")
            theirs = _anchor(data, sizes)
    return _records(ours, theirs, why, sizes, threads, pinning)


def _print(records: list[dict]) -> None:
    print_table(records, COLUMNS)
    print(f"ratio = {ANCHOR} / ours (above 1: ours is lower, i.e. faster or more accurate); lengths in units "
          "of the letters' box")
    r0 = records[0]
    print(f"sizes: letters {r0['letters']}, {r0['n_demos']} demos each, T = {r0['T']}, {r0['n_generate']} "
          f"generated, median of {r0['repeats']} after a warm-up, {r0['threads']} thread(s) (numpy: "
          f"{r0['numpy_threads']}), demo seed {r0['seed']}; push {PUSH} at T // 2; via point at "
          f"round({VIA_FRACTION} (T-1))")
    for r in records:
        if r["side"] == ANCHOR and r.get("open_loop_value") is not None:
            print(f"note: {ANCHOR} DMP reproduction by its own open_loop (starting at rest): "
                  f"{fmt(r['open_loop_value'])} (the row: step-wise from the demo's start velocity, like "
                  "ours)")
    print("note: DMP via points are not applicable (neither side's DMP conditions on via points)")


@restores_threads
def run(args) -> int:
    base = QUICK_SIZES if args.quick else DEFAULT_SIZES
    pick = lambda v, d: d if v is None else v  # noqa: E731
    sizes = Sizes(letters="".join(pick(args.letters, base.letters)),
                  n_demos=pick(args.n_demos, base.n_demos), T=pick(args.T, base.T),
                  n_generate=pick(args.n_generate, base.n_generate), repeats=pick(args.repeats, base.repeats))
    t0 = time.perf_counter()
    records = measure(sizes, threads=args.threads)
    _print(records)
    print(f"elapsed {time.perf_counter() - t0:.1f} s")
    if args.json:
        write_json(args.json, records)
    return 0
