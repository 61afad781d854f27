"""Ridge, weighted and constrained least squares: fitting cubic polynomials (seed 004 §3.4-3.5).

Parameters: 4 noisy data sets ``(t_i, y_i)``, ``i = 1..30``, ``t ∈ [0, 1]``, each a scaled sine plus noise; in
each, 3 samples are outliers (offset by +1.5).  The model is a cubic ``y(t) = φ(t)ᵀ x`` with
``φ(t) = [1, t, t², t³]``, so ``A = [φ(t_i)ᵀ] (30×4)`` and ``b = [y_i]``.

Solve (all 4 data sets in one batched call each):

* ridge regression (Eq. 13): :func:`controllers.optim.least_squares` with ``ridge = α = 1e-3``;
* weighted least squares (Eq. 14): weights ``W = diag(w)`` with ``w = 1`` on the inliers and ``1e-3`` on the
  outliers;
* constrained least squares (§3.5, Eq. 17 by its KKT system):
  :func:`controllers.optim.constrained_least_squares`, the cubic forced through the first and last samples'
  noise-free values and flat at ``t = 0`` (``Cx = d`` with 3 rows).

References (other formulations): ridge as an ordinary least-squares problem on the stacked rows
``[A; √α I] x ≈ [b; 0]`` and the weighted problem as ``√W A x ≈ √W b``, both by :func:`scipy.linalg.lstsq`;
the constrained problem by the null-space method (``x = x_p + N z``, ``N`` = :func:`scipy.linalg.null_space`
of ``C``, ``z`` by :func:`scipy.linalg.lstsq`).

Plot: the data (outliers circled) and the three fits of the first data set.

Checks:
  * ``ridge_cost_matches_scipy`` / ``weighted_cost_matches_scipy`` / ``constrained_cost_matches_nullspace``:
    every data set's optimal cost equals the reference's within a relative ``1e-10``;
  * ``constraint_satisfied``: ``‖Cx − d‖_∞ ≤ 1e-10`` for every data set;
  * ``constraints_cost_something``: the constrained optimum's cost is no lower than the unconstrained one's
    (``A† b``), as adding constraints can only raise the minimum.

Values also report how far each fit is from the noise-free curve on the inliers: down-weighting the outliers
(weighted) keeps the fit close to it, the ridge fit (all samples weighted equally) is pulled by the outliers.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

SECTION = "3.5"
TITLE = "Ridge, weighted and constrained least squares"

F64 = torch.float64
ALPHA = 1e-3


def data(B: int = 4, m: int = 30, seed: int = 0):
    """``t (m,)``, ``A (m, 4)``, ``b (B, m)``, outlier mask ``(B, m)``, noise-free curves ``(B, m)``."""
    g = torch.Generator().manual_seed(seed)
    t = torch.linspace(0.0, 1.0, m, dtype=F64)
    amp = 0.5 + torch.rand(B, 1, generator=g, dtype=F64)
    clean = amp * torch.sin(2.5 * t)
    b = clean + 0.05 * torch.randn(B, m, generator=g, dtype=F64)
    out = torch.zeros(B, m, dtype=torch.bool)
    idx = torch.stack([torch.randperm(m - 2, generator=g)[:3] + 1 for _ in range(B)])
    out.scatter_(1, idx, True)
    b = b + 1.5 * out
    A = torch.stack([t ** k for k in range(4)], -1)
    return t, A, b, out, clean


def _cost(A, b, x, w=None):
    r = (A @ x.unsqueeze(-1)).squeeze(-1) - b
    return (r * r * (1.0 if w is None else w)).sum(-1)


def run(out: Path | None = None) -> dict:
    """Solve; write ``out / "optim_least_squares.png"`` when ``out`` is given; return the outcomes."""
    import scipy.linalg

    from controllers.optim import constrained_least_squares, least_squares

    t, A, b, outlier, clean = data()
    B, m = b.shape
    w = torch.where(outlier, 1e-3, 1.0).to(F64)
    # constraints: y(0) = clean(0), y(1) = clean(1), y'(0) = 0
    C = torch.tensor([[1.0, 0.0, 0.0, 0.0], [1.0, 1.0, 1.0, 1.0], [0.0, 1.0, 0.0, 0.0]], dtype=F64)
    d = torch.stack([clean[:, 0], clean[:, -1], torch.zeros(B, dtype=F64)], -1)

    x_ridge = least_squares(A, b, ridge=ALPHA)
    x_w = least_squares(A, b, weights=torch.diag_embed(w))
    x_c = constrained_least_squares(A, b, C, d).x
    x_ls = least_squares(A, b)

    c_ridge = _cost(A, b, x_ridge) + ALPHA * (x_ridge ** 2).sum(-1)
    c_w = _cost(A, b, x_w, w)
    c_c = _cost(A, b, x_c)
    c_ls = _cost(A, b, x_ls)

    An, bn, wn, Cn, dn = A.numpy(), b.numpy(), np.sqrt(w.numpy()), C.numpy(), d.numpy()
    ref_ridge, ref_w, ref_c = [], [], []
    N = scipy.linalg.null_space(Cn)
    for k in range(B):
        stacked = np.vstack([An, np.sqrt(ALPHA) * np.eye(4)])
        xr = scipy.linalg.lstsq(stacked, np.concatenate([bn[k], np.zeros(4)]))[0]
        ref_ridge.append(np.sum((An @ xr - bn[k]) ** 2) + ALPHA * np.sum(xr ** 2))
        xw = scipy.linalg.lstsq(wn[k][:, None] * An, wn[k] * bn[k])[0]
        ref_w.append(np.sum(wn[k] ** 2 * (An @ xw - bn[k]) ** 2))
        xp = scipy.linalg.lstsq(Cn, dn[k])[0]
        z = scipy.linalg.lstsq(An @ N, bn[k] - An @ xp)[0]
        xc = xp + N @ z
        ref_c.append(np.sum((An @ xc - bn[k]) ** 2))

    def rel(a: torch.Tensor, ref: list) -> float:
        r = torch.tensor(ref, dtype=F64)
        return float(((a - r).abs() / r.abs()).max())

    violation = float((C @ x_c.unsqueeze(-1)).squeeze(-1).sub(d).abs().max())
    errs = {"ridge": rel(c_ridge, ref_ridge), "weighted": rel(c_w, ref_w), "constrained": rel(c_c, ref_c)}
    if out is not None:
        _plot(out, t, b[0], outlier[0], {"ridge (Eq. 13)": x_ridge[0], "weighted (Eq. 14)": x_w[0],
                                         "constrained (Eq. 17)": x_c[0]})
    return {
        "checks": {
            "ridge_cost_matches_scipy": errs["ridge"] <= 1e-10,
            "weighted_cost_matches_scipy": errs["weighted"] <= 1e-10,
            "constrained_cost_matches_nullspace": errs["constrained"] <= 1e-10,
            "constraint_satisfied": violation <= 1e-10,
            "constraints_cost_something": bool((c_c >= c_ls).all()),
        },
        "values": {
            "batch": B,
            "ridge_cost_rel_error": errs["ridge"],
            "weighted_cost_rel_error": errs["weighted"],
            "constrained_cost_rel_error": errs["constrained"],
            "constraint_violation": violation,
            "max_inlier_error_weighted": _inlier_error(A, x_w, clean, outlier),
            "max_inlier_error_ridge": _inlier_error(A, x_ridge, clean, outlier),
        },
    }


def _inlier_error(A, x, clean, outlier) -> float:
    """Largest ``|φ(t_i)ᵀ x − y_clean(t_i)|`` over the inliers."""
    return float(((A @ x.unsqueeze(-1)).squeeze(-1) - clean)[~outlier].abs().max())


def _plot(out: Path, t, y, outlier, fits: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(4.5, 3.2))
    ax.plot(t, y, "k.", ms=4, label="data")
    ax.plot(t[outlier], y[outlier], "o", mfc="none", mec="r", ms=7, label="outliers")
    tt = torch.linspace(0, 1, 200, dtype=F64)
    Phi = torch.stack([tt ** k for k in range(4)], -1)
    for name, x in fits.items():
        ax.plot(tt, Phi @ x, lw=1.2, label=name)
    ax.set(xlabel="t", ylabel="y", title="Cubic fits, data set 1")
    ax.legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(out / f"{Path(__file__).stem}.png", dpi=80)
    plt.close(fig)


if __name__ == "__main__":
    import json

    print(json.dumps(run(Path("out/cookbook")), indent=1))
