"""``liecontrol cookbook list|run``: the seed-004 cookbook (Calinon, *A Math Cookbook for Robot
Manipulation*) as runnable examples on the library.

``list`` prints every example with its seed section.  ``run NAME... | --all`` imports each example file by
path, calls its ``run(out)`` (one intra-op thread unless ``--threads``), times it, and writes its figure
``OUT/NAME.png`` and the outcomes of all examples run to ``OUT/outcomes.json``: per example its section,
title, seconds, the named checks (booleans: the task's outcome, e.g. "target reached within 1e-6") and
values (a non-finite value as ``null``).  An example that raises (or calls ``sys.exit``) is recorded with
its error and the others still run; a name given twice runs once.  The exit status is
1 when any check failed or any example raised.
"""

from __future__ import annotations

import importlib.util
import math
import sys
import time
import traceback
from pathlib import Path

import torch

from liecontrol._cookbook_index import Example, discover
from liecontrol.report import fmt, print_table, write_result

__all__ = ["run", "run_example", "load_example"]


def load_example(ex: Example):
    """Import the example's file as a module (a unique name per file; not added to ``sys.modules``)."""
    spec = importlib.util.spec_from_file_location(f"liecontrol_cookbook_example_{ex.name}", ex.path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _check_outcome(name: str, outcome) -> tuple[dict, dict]:
    """The checks and values of an example's return value, or ``TypeError`` saying what is malformed."""
    if not isinstance(outcome, dict) or set(outcome) != {"checks", "values"}:
        raise TypeError(f"{name}.run must return {{'checks': ..., 'values': ...}}, got {outcome!r:.200}")
    checks, values = outcome["checks"], outcome["values"]
    if not isinstance(checks, dict) or not checks or not all(isinstance(v, bool) for v in checks.values()):
        raise TypeError(f"{name}.run: 'checks' must be a non-empty dict of bools, got {checks!r:.200}")
    if not isinstance(values, dict) or not all(
            isinstance(v, (int, float)) and not isinstance(v, bool) for v in values.values()):
        raise TypeError(f"{name}.run: 'values' must be a dict of numbers, got {values!r:.200}")
    return checks, values


def run_example(ex: Example, out: Path | None) -> dict:
    """Run one example; its record (``ok`` is False when a check failed or the example raised)."""
    rec: dict = {"name": ex.name, "section": ex.section, "title": ex.title}
    t0 = time.perf_counter()
    try:
        mod = load_example(ex)
        checks, values = _check_outcome(ex.name, mod.run(out))
    except KeyboardInterrupt:
        raise
    except BaseException as e:  # one broken example (even one calling sys.exit) must not hide the others
        rec.update(seconds=time.perf_counter() - t0, ok=False, error=f"{type(e).__name__}: {e}",
                   checks={}, values={})
        traceback.print_exc(file=sys.stderr)
        return rec
    # strict JSON has no NaN/inf: a non-finite value is recorded as null
    values = {k: (v if not isinstance(v, float) or math.isfinite(v) else None) for k, v in values.items()}
    rec.update(seconds=time.perf_counter() - t0, ok=all(checks.values()), checks=checks, values=values)
    if out is not None:
        rec["figure"] = str(out / f"{ex.name}.png")
    return rec


def _list(examples: list[Example]) -> int:
    print_table([{"section": e.section, "name": e.name, "title": e.title} for e in examples],
                ["section", "name", "title"])
    return 0


def _row(rec: dict) -> dict:
    failed = [k for k, v in rec["checks"].items() if not v]
    status = "error" if "error" in rec else "ok" if rec["ok"] else "FAILED: " + ", ".join(failed)
    n = len(rec["checks"])
    return {"section": rec["section"], "name": rec["name"], "s": fmt(rec["seconds"], ".2f"),
            "checks": f"{n - len(failed)}/{n}", "status": status}


def run(args) -> int:
    examples = discover(args.examples)
    if args.subcommand == "list":
        return _list(examples)
    by_name = {e.name: e for e in examples}
    chosen = examples if args.all else [by_name[n] for n in dict.fromkeys(args.names)]  # once each
    out = None if args.no_plots else Path(args.out)
    torch.set_num_threads(args.threads)
    records = []
    for ex in chosen:
        if not args.quiet:
            print(f"cookbook: {ex.name} (§{ex.section}) ...", file=sys.stderr, flush=True)
        records.append(run_example(ex, out))
    print_table([_row(r) for r in records], ["section", "name", "s", "checks", "status"])
    result = {"examples": records, "ok": all(r["ok"] for r in records)}
    write_result(Path(args.out) / "outcomes.json", result)
    if args.json:
        write_result(args.json, result)
    bad = [r["name"] for r in records if not r["ok"]]
    if bad:
        print(f"cookbook: {len(bad)} of {len(records)} failed: {', '.join(bad)}", file=sys.stderr)
        return 1
    return 0
