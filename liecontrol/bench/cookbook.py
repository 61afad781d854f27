"""``liecontrol bench cookbook``: the cookbook's own scripts as anchors (seed 004, "Robotics Codes From
Scratch").

Three problems, each solved by ``ilqr`` (recursive and batch methods) and ``ilqr_lifted`` and, for as many
iterations as each took, by the script's published algorithm (the batch iLQR of §8.1, Eq. 87 / 108) in
plain numpy, a subprocess pinned to ``--threads``:

* the manipulator of §9.1 (``iLQR_manipulator``: 3 links, two end-effector via points, 49 velocity
  commands; ``_cookbook_anchor.py``);
* the car of §9.15 (``iLQR_car``: velocity inputs, Eq. 118; 100 steps to a parked pose;
  ``_cookbook_vehicle_anchor.py``);
* the bicopter of §9.16 (``iLQR_bicopter``: absolute thrusts, Eq. 120; 100 steps from hover thrust to a
  point 1.4 m away; ``_cookbook_vehicle_anchor.py``).

Then ``--batch`` starts of each are solved in one call by the recursive and the lifted solver.  The goals
of issue 25 are printed with their verdicts, per problem:

* one problem no slower than the script: ``ratio = anchor_ms / ours_ms ≥ 1`` for the fastest of ours;
* a batch of 64 at most 5 times one: ``per_one = batch_ms / one_ms ≤ 5`` for the same solver.

The rows are :mod:`liecontrol.bench.solver`'s ``cookbook_manipulator``, ``cookbook_car`` and
``cookbook_bicopter`` workloads (one implementation).
"""

from __future__ import annotations

import dataclasses

import torch

from liecontrol.bench.solver import DEFAULT_SIZES, QUICK_SIZES, _print, measure
from liecontrol.report import fmt, write_json

__all__ = ["run", "goals", "WORKLOADS"]

#: the workloads of :mod:`liecontrol.bench.solver` this command measures
WORKLOADS = ("cookbook_manipulator", "cookbook_car", "cookbook_bicopter")


def _goals_one(records: list[dict], goal_batch: int, prefix: str) -> list[str]:
    one = [r for r in records if r["batch"] == 1 and r.get("anchor_ms") is not None]
    lines = []
    if one:
        best = min(one, key=lambda r: r["ours_ms"])
        lines.append(f"{prefix}one problem: fastest of ours is {best['method']} at "
                     f"{fmt(best['ours_ms'])} ms, the script {fmt(best['anchor_ms'])} ms after "
                     f"{best['iterations']} iterations: ratio "
                     f"{fmt(best['ratio'])} (goal >= 1: {'met' if best['ratio'] >= 1 else 'MISSED'})")
    for r in records:
        if r["batch"] > 1:
            verdict = (f"goal <= 5: {'met' if r['per_one'] <= 5 else 'MISSED'}" if r["batch"] == goal_batch
                       else f"the goal is for a batch of {goal_batch}: no verdict")
            lines.append(f"{prefix}batch of {r['batch']} by {r['method']}: {fmt(r['ours_ms'])} ms, "
                         f"{fmt(r['per_one'])} x one problem ({verdict}), "
                         f"{r['converged']} of {r['batch']} certified"
                         + (f", iterations median {fmt(r['iterations_median'])} / max {r['iterations']} (the "
                            "batch runs to its slowest element's count)" if "iterations_median" in r else ""))
    return lines


def goals(records: list[dict], goal_batch: int = 64) -> list[str]:
    """The verdict lines of the two speed goals, per workload (records grouped by ``workload``, in order of
    appearance; each line starts with the record's ``system`` when there are several): the fastest of ours
    on one problem (smallest time) against the script, and each batch row against its solver on one
    problem — a verdict only for a batch of ``goal_batch`` (the goal's size); other sizes are reported
    without one."""
    groups: dict[object, list[dict]] = {}
    for r in records:
        groups.setdefault(r.get("workload"), []).append(r)
    lines = []
    for key, rows in groups.items():
        name = rows[0].get("system", key)
        prefix = f"{name}: " if len(groups) > 1 and name is not None else ""
        lines += _goals_one(rows, goal_batch, prefix)
    return lines


def run(args) -> int:
    torch.set_num_threads(args.threads)
    sizes = QUICK_SIZES if args.quick else DEFAULT_SIZES
    if args.batch is not None:
        sizes = dataclasses.replace(sizes, cookbook_batch=args.batch)
    records = measure(list(WORKLOADS), sizes=sizes, threads=args.threads, repeats=args.repeats,
                      compile=False)
    _print(records)
    for line in goals(records):
        print(line)
    if args.json:
        write_json(args.json, records)
    return 0
