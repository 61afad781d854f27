"""Handwriting-like demonstrations: generate, save, load, summarize (issue 26 §1; seed 004 §6.5, §7.7).

Parameters: the letters ``S C U N``, ``N_DEMOS = 8`` demos of ``T = 100`` samples over one second each.

Demos: each letter is a clean C¹ spline of cubic Bézier segments on a handful of control points
(:func:`learning.demos.letter_stroke`, seed §6.5), copied ``N_DEMOS`` times and varied like a human writer
would: a smooth random monotone time warp (:func:`learning.demos.time_warp`, speed varying by factors
around ``e^{±0.3}``) and smooth spatial offsets of pointwise standard deviation ``NOISE · sin(π s)`` with
``NOISE = 0.02`` in a unit box (:func:`learning.demos.spatial_noise`, ends pinned).  Nothing is
downloaded.

Storage: every letter's :class:`~learning.demos.Demonstrations` is written to the documented ``.npz``
format and read back (``allow_pickle=False``).

Summary and plot: the demos in the plane with the mean over demos at each time step (what a ProMP-like
primitive encodes, seed §7.7), and each coordinate's mean ± 2 std band over time (the covariance per time
step of :meth:`~learning.demos.Demonstrations.covariance`).

Outcome checks: ``round_trip_exact`` — the loaded demos equal the saved ones bit for bit (states, time
step, frames, metadata); ``demos_near_clean_stroke`` — every sample of every demo lies within
``5 · NOISE`` of its letter's clean stroke (the warp moves samples *along* the stroke, the offsets have
standard deviation at most ``NOISE``); ``ends_on_stroke`` — every demo starts and ends on the stroke's
first and last control points (to 1e-12).
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import torch

from learning.demos import Demonstrations, handwriting, letter_stroke

SECTION = "7.7"
TITLE = "Handwriting-like demonstrations (generate, save/load, mean ± std)"

LETTERS = "SCUN"
N_DEMOS = 8
T = 100
NOISE = 0.02
WARP = 0.3


def _same(a: Demonstrations, b: Demonstrations) -> bool:
    return (torch.equal(a.x, b.x) and a.x.dtype == b.x.dtype and a.dt == b.dt and a.u is None and b.u is None
            and a.frames.keys() == b.frames.keys()
            and all(torch.equal(a.frames[k], b.frames[k]) for k in a.frames) and a.meta == b.meta)


def run(out: Path | None = None) -> dict:
    """Generate, round-trip and summarize the letters; write ``out / "demos_handwriting.png"`` (and the
    ``.npz`` files) when ``out`` is given; return the outcomes."""
    g = torch.Generator().manual_seed(7)
    demos = handwriting(LETTERS, N_DEMOS, T, generator=g, warp=WARP, noise=NOISE)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(out) if out is not None else Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        loaded = {}
        for c, d in demos.items():
            path = folder / f"demos_handwriting_{c}.npz"
            d.save(path)
            loaded[c] = Demonstrations.load(path)
    round_trip = all(_same(demos[c], loaded[c]) for c in demos)
    max_dist, ends_err = 0.0, 0.0
    for c, d in loaded.items():
        dense = letter_stroke(c, 4000)
        dist = torch.cdist(d.x.reshape(-1, 2), dense).min(-1).values
        max_dist = max(max_dist, float(dist.max()))
        pts = torch.tensor(d.meta["control_points"], dtype=d.dtype)
        ends_err = max(ends_err, float((d.x[:, 0] - pts[0]).abs().max()),
                       float((d.x[:, -1] - pts[-1]).abs().max()))
    std_mid = float(torch.stack([d.covariance().diagonal(dim1=-2, dim2=-1)[T // 2] for d in loaded.values()])
                    .sqrt().mean())
    if out is not None:
        _plot(Path(out), loaded)
    return {"checks": {"round_trip_exact": bool(round_trip),
                       "demos_near_clean_stroke": bool(max_dist <= 5 * NOISE),
                       "ends_on_stroke": bool(ends_err <= 1e-12)},
            "values": {"max_distance_to_stroke": max_dist, "bound": 5 * NOISE, "ends_error": ends_err,
                       "mean_std_at_mid_movement": std_mid, "letters": len(loaded),
                       "demos_per_letter": N_DEMOS}}


def _plot(out: Path, demos: dict[str, Demonstrations]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    k = len(demos)
    fig, axs = plt.subplots(2, k, figsize=(2.2 * k, 4.2))
    for j, (c, d) in enumerate(demos.items()):
        ax = axs[0, j]
        for x in d.x:
            ax.plot(x[:, 0], x[:, 1], lw=0.6, color="0.6")
        mu = d.mean()
        ax.plot(mu[:, 0], mu[:, 1], lw=2, color="C3")
        ax.plot(*d.x[0, 0], "ko", ms=3)
        ax.set_aspect("equal")
        ax.set_title(c)
        ax.set_xticks([])
        ax.set_yticks([])
        ax = axs[1, j]
        t = d.times()
        sd = d.covariance().diagonal(dim1=-2, dim2=-1).sqrt()
        for i, col in ((0, "C0"), (1, "C1")):
            ax.fill_between(t, mu[:, i] - 2 * sd[:, i], mu[:, i] + 2 * sd[:, i], color=col, alpha=0.3)
            ax.plot(t, mu[:, i], color=col, lw=1.2, label=f"x{i + 1}")
        ax.set_xlabel("t [s]")
        if j == 0:
            ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / f"{Path(__file__).stem}.png", dpi=80)
    plt.close(fig)


if __name__ == "__main__":
    import json

    print(json.dumps(run(Path("out/learning")), indent=1))
