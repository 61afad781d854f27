"""Robustness to model mismatch: policies built on a nominal task, evaluated unchanged on perturbed ones.

The measurement of Actor-Critic MPC's claim (Romero et al., TRO 2025: "return under perturbed mass, drag
and arm length, without retraining"): every policy is built (trained, or for the MPC expert *planned*) on
the nominal task, then run by :func:`learning.evaluate.evaluate` on tasks whose physical parameters are
scaled, on the same episode seeds (the same initial states) for every perturbation.

**What can be perturbed** (:func:`perturbable_parameters`):

* A task with a ``model`` field (``CartPoleSwingUp``: ``cart_mass``, ``pole_mass``, ``length`` (the pole),
  ``gravity``; ``PendulumSwingUp``: ``mass``, ``length``, ``gravity``, ...): each numeric field of the
  model but its time step, **multiplied** by the factor (``pole_mass=1.3`` is a pole 30 % heavier).  A
  parameter whose nominal value is 0 cannot be scaled (the factor is refused).
* ``QuadrotorTrack`` (``QuadrotorCircle``, ``QuadrotorFigureEight``): ``mass`` multiplies the vehicle's
  mass (its ``mass_scale``: the commanded mass-normalized thrust produces ``a_T / mass``), and ``drag`` is
  the rotor-drag coefficient **itself** (1/s per body axis, a number or ``(d_x, d_y, d_z)``; the drag
  acceleration is ``−R D Rᵀ v``), *not* a factor: the nominal vehicle has no drag, so "30 % more" of it is
  undefined.  The value used for a "+30 %" drag perturbation is :data:`QUADROTOR_DRAG` ``= 0.3`` /s per
  axis — a drag that alone would slow the vehicle by about 26 % per second (``1 − e^{−0.3}``); at the
  circle's reference speed (1.9 m/s) it is a 0.57 m/s² deceleration, 6 % of g.  The quadrotor model is
  body-rate controlled (the rates are inputs, tracked perfectly), so it has **no arm length and no
  inertia**: asking for them is an error that says so, not a silently faked perturbation.

Any other name is a ``ValueError`` naming the factor and the task's perturbable parameters.

The "mpc" policy of a study (:func:`robustness_study`) is the expert of the **nominal** task, built once:
it plans with the nominal model while the perturbed vehicle moves (the expert of a perturbed task, e.g.
``task_expert(perturbed_task(...))``, would plan with the true model — the right thing for an expert, not
for a robustness study).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from typing import Any

import torch

from learning.envs.quadrotor import QuadrotorTrack
from learning.envs.single import make_task
from learning.envs.task import Task

__all__ = ["QUADROTOR_DRAG", "perturbable_parameters", "perturbed_task", "default_perturbations",
           "robustness_study", "records_table"]

#: rotor-drag coefficient (1/s, every body axis) of the quadrotor's "+30 %" drag perturbation
QUADROTOR_DRAG = 0.3

_QUAD_PARAMS = ("mass", "drag")
_NO_SUCH = {"arm_length", "arm", "length", "inertia", "moment_of_inertia"}


def _model_params(task: Task) -> tuple[str, ...]:
    model = getattr(task, "model", None)
    if model is None or not dataclasses.is_dataclass(model):
        return ()
    return tuple(f.name for f in dataclasses.fields(model)
                 if f.name != "dt" and isinstance(getattr(model, f.name), (int, float, torch.Tensor))
                 and not isinstance(getattr(model, f.name), bool))


def perturbable_parameters(task: Task | str) -> tuple[str, ...]:
    """The names :func:`perturbed_task` accepts for ``task`` (module docstring)."""
    t = make_task(task)
    return _QUAD_PARAMS if isinstance(t, QuadrotorTrack) else _model_params(t)


def _factor(value: Any, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < float(value) < math.inf:
        raise ValueError(f"perturbed_task: factor {name!r} must be a positive finite number, got {value!r}")
    return float(value)


def _unknown(t: Task, name: str) -> ValueError:
    known = ", ".join(perturbable_parameters(t)) or "none"
    if isinstance(t, QuadrotorTrack) and name in _NO_SUCH:
        return ValueError(f"perturbed_task: {t.name} has no {name!r}: its model is body-rate controlled (the "
                          f"body rates are inputs), so it has no arm length or inertia to perturb; "
                          f"perturbable: {known}")
    return ValueError(f"perturbed_task: {t.name} has no physical parameter {name!r} (perturbable: {known})")


def _drag(value: Any) -> tuple[float, float, float]:
    vals = (value,) * 3 if isinstance(value, (int, float)) and not isinstance(value, bool) else value
    try:
        out = tuple(float(v) for v in vals)
    except (TypeError, ValueError):
        out = ()
    if len(out) != 3 or not all(0 <= v < math.inf for v in out):
        raise ValueError(f"perturbed_task: 'drag' must be a non-negative coefficient (1/s) or three of them "
                         f"(d_x, d_y, d_z), got {value!r}")
    return out


def perturbed_task(task: Task | str, **factors: Any) -> Task:
    """``task`` (a :class:`Task` or its name) with physical parameters perturbed (module docstring):
    ``perturbed_task("CartPoleSwingUp", pole_mass=1.3)``, ``perturbed_task("QuadrotorCircle", mass=0.7)``,
    ``perturbed_task("QuadrotorCircle", drag=QUADROTOR_DRAG)``.  No factors: the task itself.

    Raises:
        ValueError: a name the task has no such parameter for (named in the message, with the task's
            perturbable parameters), a non-positive factor, a bad drag coefficient.
    """
    t = make_task(task)
    if not factors:
        return t
    if isinstance(t, QuadrotorTrack):
        changes: dict[str, Any] = {}
        for name, value in factors.items():
            if name == "mass":
                changes["mass_scale"] = float(t.mass_scale) * _factor(value, name)
            elif name == "drag":
                changes["drag"] = _drag(value)
            else:
                raise _unknown(t, name)
        return dataclasses.replace(t, **changes)
    params = _model_params(t)
    scaled = {}
    for name, value in factors.items():
        if name not in params:
            raise _unknown(t, name)
        f = _factor(value, name)
        nominal = getattr(t.model, name)
        if f != 1.0 and not bool(torch.any(torch.as_tensor(nominal) != 0)):
            raise ValueError(f"perturbed_task: {t.name}'s {name!r} is 0, a factor cannot perturb it")
        scaled[name] = nominal * f
    return dataclasses.replace(t, model=dataclasses.replace(t.model, **scaled))


def default_perturbations(task: Task | str) -> dict[str, dict[str, Any]]:
    """The default grid, label → factors: ``"nominal"`` (none), then each parameter alone at 0.7 and 1.3
    (cart-pole: ``pole_mass``, ``length``, ``cart_mass``; other model-based tasks: every perturbable
    parameter but gravity); the quadrotor: ``mass`` at 0.7 and 1.3 and ``drag`` at :data:`QUADROTOR_DRAG`
    (nominal 0)."""
    t = make_task(task)
    grid: dict[str, dict[str, Any]] = {"nominal": {}}
    if isinstance(t, QuadrotorTrack):
        names = ("mass",)
    elif t.name == "CartPoleSwingUp":
        names = ("pole_mass", "length", "cart_mass")
    else:
        names = tuple(n for n in _model_params(t) if n != "gravity"
                      and bool(torch.any(torch.as_tensor(getattr(t.model, n)) != 0)))
    for name in names:
        for f in (0.7, 1.3):
            grid[f"{name}×{f:g}"] = {name: f}
    if isinstance(t, QuadrotorTrack):
        grid[f"drag={QUADROTOR_DRAG:g}/s"] = {"drag": QUADROTOR_DRAG}
    return grid


def _seed_list(seeds: Sequence[int] | int | None, episodes: int) -> list[int]:
    if isinstance(episodes, bool) or not isinstance(episodes, int) or episodes < 1:
        raise ValueError(f"robustness_study: argument 'episodes' must be an int >= 1, got {episodes!r}")
    if seeds is None:
        return list(range(episodes))
    if isinstance(seeds, int) and not isinstance(seeds, bool):
        return [seeds + i for i in range(episodes)]
    out = [int(s) for s in seeds]
    if not out:
        raise ValueError("robustness_study: argument 'seeds' is empty")
    return out


def robustness_study(policies: Mapping[str, Any], task: Task | str,
                     perturbations: Mapping[str, Mapping[str, Any]] | None = None, *,
                     seeds: Sequence[int] | int | None = None, episodes: int = 8, num_envs: int | None = None,
                     max_episode_steps: int | None = None, dtype=torch.float64,
                     device: torch.device | str = "cpu", progress: bool = False) -> list[dict[str, Any]]:
    """Evaluate each policy, unchanged, on each perturbed version of ``task``.

    Args:
        policies: name → anything :func:`learning.policies.as_policy` accepts.  Each is made a policy
            **once, on the nominal task** (so ``"mpc"`` is the nominal task's expert, planning with the
            nominal model) and then run on every perturbed task.
        task: the nominal :class:`Task` or its name.
        perturbations: label → factors of :func:`perturbed_task` (default :func:`default_perturbations`).
        seeds: the episodes' seeds, the same for every perturbation and policy (same initial states): a
            list, or a first seed (then ``seed, …, seed+episodes-1``); default ``0, …, episodes-1``.
        episodes: number of episodes when ``seeds`` is not a list.
        num_envs: episodes run at once (default: all of them).
        max_episode_steps, dtype, device, progress: of :func:`learning.evaluate.evaluate`.

    Returns:
        one record per (policy, perturbation), policies outer: ``{"policy", "perturbation", "factors",
        "return_mean", "return_std", "success_rate", "final_error", "terminated_rate", "episodes"}``
        (population std over episodes; ``final_error`` the mean of the task's error at the final state;
        ``terminated_rate`` the fraction of episodes ended by a crash).
    """
    from learning.evaluate import evaluate
    from learning.policies import as_policy

    nominal = make_task(task)
    if not isinstance(policies, Mapping) or not policies:
        raise ValueError("robustness_study: argument 'policies' must be a non-empty dict name → policy")
    grid = default_perturbations(nominal) if perturbations is None else dict(perturbations)
    tasks = {label: perturbed_task(nominal, **dict(f)) for label, f in grid.items()}  # errors before any run
    seed_list = _seed_list(seeds, episodes)
    built = {name: as_policy(p, nominal) for name, p in policies.items()}
    records = []
    for name, pol in built.items():
        for label, t in tasks.items():
            res = evaluate(pol, t, seeds=seed_list, num_envs=num_envs or len(seed_list),
                           max_episode_steps=max_episode_steps, dtype=dtype, device=device, progress=progress,
                           timing_batch1=False, distributed=False)
            s = res.summary()
            records.append({"policy": name, "perturbation": label, "factors": dict(grid[label]),
                            "return_mean": s["return"]["mean"], "return_std": s["return"]["std"],
                            "success_rate": s["success_rate"], "final_error": s["final_error"]["mean"],
                            "terminated_rate": s["terminated_rate"], "episodes": s["episodes"]})
    return records


def records_table(records: Sequence[Mapping[str, Any]]) -> str:
    """A Markdown table of :func:`robustness_study`'s records (one row each)."""
    lines = ["| policy | perturbation | return (mean ± std) | success | final error | crashed |",
             "|---|---|---|---|---|---|"]
    for r in records:
        ret = f"{r['return_mean']:.1f} ± {r['return_std']:.1f}"
        lines.append(f"| {r['policy']} | {r['perturbation']} | {ret} | {100 * r['success_rate']:.0f} % "
                     f"| {r['final_error']:.3g} | {100 * r['terminated_rate']:.0f} % |")
    return "\n".join(lines)
