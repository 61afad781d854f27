"""Report helpers of the application layer: timing, tables and JSON records, shared by the ``bench``,
``reproduce`` (and later ``compare``/``learn``) subcommands of the ``liecontrol`` command.

Absolute times drift on a shared machine; what a benchmark reports is the ratio anchor/ours measured
in the same run, with each side timed as the median of several runs after warm-up.
"""

from __future__ import annotations

import functools
import json
import math
import statistics
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import torch

__all__ = ["time_ms", "fmt", "print_table", "write_json", "sync", "restores_threads", "public",
           "write_result", "markdown_cell"]


def sync(device: torch.device | str | None = None) -> None:
    """Wait for queued CUDA work (no-op on CPU)."""
    if device is not None and torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


def time_ms(fn: Callable[[], object], repeats: int = 7, warmup: int = 2,
            device: torch.device | str | None = None, min_time_s: float = 0.0) -> float:
    """Median wall time of ``fn()`` in milliseconds over ``repeats`` runs after ``warmup`` runs.

    With ``min_time_s`` > 0 each timed sample loops ``fn`` until that much time has passed and reports
    the time per call, which keeps sub-millisecond calls above the timer's resolution.
    """
    for _ in range(warmup):
        fn()
    sync(device)
    samples = []
    for _ in range(max(repeats, 1)):
        n = 0
        t0 = time.perf_counter()
        while True:
            fn()
            n += 1
            sync(device)
            dt = time.perf_counter() - t0
            if dt >= min_time_s:
                break
        samples.append(1e3 * dt / n)
    return statistics.median(samples)


def fmt(v: object, spec: str | None = None, missing: str = "-") -> str:
    """The one number formatter of the reports: ``missing`` for ``None``; with ``spec``,
    ``format(v, spec)``; else a float to 3 significant digits (``1.23e-05`` below 0.01 and from 1e5 on,
    no decimals from 100 on) and anything else by ``str``."""
    if v is None:
        return missing
    if spec is not None:
        return format(v, spec)
    if isinstance(v, float):
        if not math.isfinite(v):
            return str(v)
        if v == 0:
            return "0"
        a = abs(v)
        return f"{v:.2e}" if a < 1e-2 or a >= 1e5 else f"{v:.3g}" if a < 100 else f"{v:.0f}"
    return str(v)


def print_table(rows: Sequence[dict], columns: Sequence[str], file=None) -> None:
    """Print ``rows`` (dicts) as an aligned text table with the given columns."""
    cells = [[c for c in columns]] + [[fmt(r.get(c)) for c in columns] for r in rows]
    widths = [max(len(row[i]) for row in cells) for i in range(len(columns))]
    for k, row in enumerate(cells):
        print("  ".join(s.rjust(w) for s, w in zip(row, widths)), file=file)
        if k == 0:
            print("  ".join("-" * w for w in widths), file=file)


def write_json(path: str | Path, records: list[dict]) -> None:
    """Write ``records`` as a JSON list (parent folders are created)."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps(records, indent=1, default=float) + "\n")


def restores_threads(fn):
    """Decorator: a benchmark may set torch's intra-op thread count; the caller gets its own back."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        n = torch.get_num_threads()
        try:
            return fn(*args, **kwargs)
        finally:
            torch.set_num_threads(n)

    return wrapper


def public(result: dict) -> dict:
    """``result`` without its private entries (keys starting with ``_``: raw curves for the figures)."""
    return {k: v for k, v in result.items() if not k.startswith("_")}


def write_result(path: str | Path, data: dict) -> Path:
    """Write one JSON result ``data`` to ``path`` (parent folders are created); returns the path."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps(data, indent=1) + "\n")
    return p


def markdown_cell(v) -> str:
    """A table cell of a ``report.md``: :func:`fmt`, empty for ``None``."""
    return fmt(v, missing="")
