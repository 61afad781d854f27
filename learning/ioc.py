"""Inverse optimal control: learning LQT/iLQR costs and via points from demonstrations (issue 26 §2;
seed 004 §7.1-7.7, §8).

The forward model is the tracking cost of the seed (Eq. 59, no factor ½, :mod:`controllers.costs`)::

    c(x, u) = Σ_t (x_t - g)ᵀ Q_t (x_t - g) + Σ_t u_tᵀ R u_t + Σ_k Σ_t κ_k(t) (x_t - m_k)ᵀ P_k (x_t - m_k)

with ``Q_t = Q`` for ``t < T`` and ``Q_T = ρ Q`` (terminal factor ``ρ``), or one ``Q_t`` per step, a goal
``g``, and ``K`` via points (targets ``m_k``, precisions ``P_k``) whose precision is spread over time by a
normalized kernel ``κ_k(t)`` centred on a continuous time ``τ_k`` (:func:`time_weights`).  Everything is
a torch parameter of an :class:`LQTCostModel`, and :func:`fit_cost` fits it by backpropagating the
squared distance between the optimal trajectories from the demos' starts and the demos themselves
through the solver: the Riccati recursion with its implicit (KKT) backward pass
(:func:`controllers.riccati.solve`, ``grad="implicit"``), the batch least-squares LQT of Eq. 62
(:func:`controllers.lifted.solve_lifted`, autograd through one Cholesky solve) or, for a nonlinear system,
iLQR with implicit gradients (:func:`controllers.ilqr.ilqr`, ``grad="implicit"``).  All demos are solved
as one batch per evaluation.

**Parametrizations** (:class:`SPDWeight`).  A weight matrix is diagonal, ``W = diag(exp(s))``, or full,
``W = L Lᵀ`` with ``L`` lower triangular and ``L_ii = exp(s_i)`` (a Cholesky factor with a positive
diagonal: every real parameter vector gives a symmetric positive definite ``W``, and the map is one to
one).  The log scale suits weights spread over decades (the idea of
:class:`learning.bc.LearnableQuadraticCost`, here for full matrices, per-step stacks and via points).

**Scale.**  Multiplying the whole cost by ``c > 0`` changes no minimizer, so from demonstrations the
weights are identifiable only up to one common factor.  We fix it by fixing one weight: by default
``R_00`` (``SPDWeight(..., fix_first=True)`` for ``R``; with a Cholesky ``R`` it is ``L_00² = R_00`` that is
fixed).  Why ``R_00`` rather than ``trace Q``: it is one scalar (every other ratio stays free), it is a
plain parameter freeze (no projection inside the optimizer), and a control weight is always present and
positive definite (a state weight may legitimately be zero in a direction).  Weights from another
normalization compare after :func:`normalize_scale`.  One fixed weight suffices only when the cost couples
the whole system: a diagonal cost on a system made of independent parts (the ``D``-dimensional double
integrator of :func:`controllers.lqt_cookbook.double_integrator`, one axis per control) has one
unidentifiable scale *per part* (measured: with ``R_00`` fixed, the second axis' weights came out all
multiplied by 1.88 at zero loss) — fix one weight per part (e.g. all of ``R``, ``learn=False``) or couple
the parts (a full ``Q``, or dynamics that mix the controls).

**Via-point timing.**  The precision of via point ``k`` at step ``t`` is ``κ_k(t) P_k`` with either
(a) ``kernel="gaussian"``: ``κ_k(t) = exp(-(t-τ_k)²/2σ²) / Σ_s exp(-(s-τ_k)²/2σ²)`` over ``s = 0..T``
(smooth in ``τ``; a demo with a sharp via point is then approximated by a spread one — ``σ`` is fixed,
not learned, and should be about 1 step or more for a useful gradient), or (b) ``kernel="linear"``: the
precision is split linearly between the two steps around ``τ`` (``κ(⌊τ⌋) = 1 - (τ - ⌊τ⌋)``,
``κ(⌊τ⌋+1) = τ - ⌊τ⌋``), which reproduces a sharp via point exactly at integer ``τ`` but is only piecewise
smooth (kinks at integers).  Limits of both: the loss is not convex in ``τ`` — start within a few steps of
the true time (the basin is about the width of the kernel plus the time the movement takes to respond);
a ``τ`` outside ``[0, T]`` is reflected into it (slope ``±1``: a time pushed past an end by the optimizer's
momentum keeps a gradient back, where a clamp's zero gradient would freeze it), and :func:`fit_cost` stores
the reflected (used) time after each step; ``τ`` is identifiable only where the via point changes the
movement (a via point on the unconstrained path carries no timing information).

**Minimal intervention (§7.7).**  :func:`minimal_intervention` fits the ProMP-like distribution of
:func:`learning.primitives.fit_promp` and tracks its mean with the precision ``(Σ_t + floor I)⁻¹`` of the
demos' state covariance (:meth:`learning.primitives.ProMP.track`), and returns the feedback gains with
their norms next to the demos' variance: low gains where the demos vary, high where they agree.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Mapping
from typing import Any, NamedTuple

import torch
from torch import Tensor, nn

from controllers.costs import QuadraticCost
from controllers.dynamics import LinearDynamics
from controllers.problem import LQProblem, Reason, SolverStatus
from learning import distributed as _dist
from learning._checks import FLOAT_DTYPES, float_tensor
from learning.demos import Demonstrations

__all__ = ["SPDWeight", "time_weights", "ViaPoints", "LQTCostModel", "normalize_scale", "IOCLoss", "ioc_loss",
           "IOCResult", "fit_cost", "MinimalIntervention", "minimal_intervention"]

_SOLVERS = ("riccati", "lifted", "ilqr")


def _pos_int(v: Any, name: str, own: str, least: int = 1) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or v < least:
        raise ValueError(f"{own}: argument '{name}' must be an int >= {least}, got {v!r}")
    return v


def _pos_float(v: Any, name: str, own: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
        raise ValueError(f"{own}: argument '{name}' must be a positive finite number, got {v!r}")
    return float(v)


# --------------------------------------------------------------------------------------------------
# parametrizations
# --------------------------------------------------------------------------------------------------


class SPDWeight(nn.Module):
    """A symmetric positive definite weight ``W (*S, k, k)`` from unconstrained parameters (module docstring).

    Args:
        init: the initial weight: its positive diagonal entries ``(*S, k)`` for ``kind="diagonal"``, an SPD
            matrix ``(*S, k, k)`` for ``kind="full"``.  ``*S`` stacks independent weights (one per time step,
            one per via point); dtype and device follow ``init``.
        kind: ``"diagonal"`` — ``W = diag(exp(s))`` — or ``"full"`` — ``W = L Lᵀ``, ``L`` lower triangular
            with ``L_ii = exp(s_i)`` and free entries below the diagonal (Cholesky parametrization).
        fix_first: keep ``W_00`` (every stacked weight's) at its initial value — the scale normalization
            (module docstring): ``s_0`` is a buffer, not a parameter.
        learn: ``False`` keeps the whole weight fixed (buffers only).

    Parameters: ``log_diag`` ``(*S, k - fix_first)`` and, for ``"full"``, ``lower`` ``(*S, k(k-1)/2)``
    (row-major strictly-lower entries of ``L``).  A ``"full"`` ``init`` may be asymmetric at round-off
    (``|M - Mᵀ| <= 8 k eps max|M|``, ``eps`` of its dtype); it is symmetrized.

    Range of "SPD by construction": exact in real arithmetic for every parameter vector; in floating point
    ``W`` is SPD while every ``exp(s_i)`` is a finite normal number — ``|s_i| < 87`` in float32, ``< 708``
    in float64 (beyond, ``exp`` overflows to ``inf`` or underflows to 0 and ``W`` is singular or not finite)
    — and, for ``"full"``, while the condition number of ``W`` stays below about ``1/eps`` (``1e7`` in
    float32, ``1e16`` in float64): a product ``L Lᵀ`` with much larger off-diagonal entries than diagonal
    ones can round to an indefinite matrix.  Nothing is clamped.
    """

    def __init__(self, init: Tensor, kind: str = "diagonal", *, fix_first: bool = False, learn: bool = True):
        super().__init__()
        own = "SPDWeight"
        if kind not in ("diagonal", "full"):
            raise ValueError(f"{own}: argument 'kind' must be 'diagonal' or 'full', got {kind!r}")
        init = float_tensor(init, "init", own, finite=True).detach()
        if kind == "diagonal":
            if init.dim() < 1 or init.shape[-1] < 1:
                raise ValueError(f"{own}: kind='diagonal' needs the diagonal entries 'init' (*S, k), got "
                                 f"{tuple(init.shape)}")
            diag = init
        else:
            if init.dim() < 2 or init.shape[-1] != init.shape[-2] or init.shape[-1] < 1:
                raise ValueError(f"{own}: kind='full' needs an SPD matrix 'init' (*S, k, k), got "
                                 f"{tuple(init.shape)}")
            init = _symmetrized(init, own)
            L, info = torch.linalg.cholesky_ex(init)
            if bool((info != 0).any()):
                raise ValueError(f"{own}: argument 'init' must be positive definite")
            diag = L.diagonal(dim1=-2, dim2=-1)
        if bool((diag <= 0).any()):
            raise ValueError(f"{own}: argument 'init' must have positive diagonal entries")
        self.kind, self.k = kind, int(diag.shape[-1])
        self.fix_first, self.learn = bool(fix_first), bool(learn)
        log_d = diag.log()
        nf = 1 if fix_first else 0
        self._put("log_diag", log_d[..., nf:].clone(), learn)
        self.register_buffer("log_diag_fixed", log_d[..., :nf].clone())
        if kind == "full":
            i, j = torch.tril_indices(self.k, self.k, -1, device=init.device)
            self.register_buffer("_flat_idx", (i * self.k + j).to(torch.int64), persistent=False)
            self._put("lower", L[..., i, j].clone(), learn)

    def _put(self, name: str, value: Tensor, learn: bool) -> None:
        if learn and value.numel() > 0:  # (a 1×1 weight with fix_first has nothing left to learn)
            self.register_parameter(name, nn.Parameter(value))
        else:
            self.register_buffer(name, value)

    def factor(self) -> Tensor:
        """``(*S, k, k)``: ``L`` (``"full"``) or ``diag(exp(s/2))`` (``"diagonal"``), with ``W = L Lᵀ``."""
        log_d = torch.cat([self.log_diag_fixed, self.log_diag], -1)
        if self.kind == "diagonal":
            return torch.diag_embed((0.5 * log_d).exp())
        k = self.k
        flat = torch.zeros(*self.lower.shape[:-1], k * k, dtype=log_d.dtype, device=log_d.device)
        flat = flat.index_add(-1, self._flat_idx, self.lower)
        return flat.unflatten(-1, (k, k)) + torch.diag_embed(log_d.exp())

    def forward(self) -> Tensor:
        """The weight ``W (*S, k, k)`` (symmetric positive definite by construction)."""
        log_d = torch.cat([self.log_diag_fixed, self.log_diag], -1)
        if self.kind == "diagonal":
            return torch.diag_embed(log_d.exp())
        L = self.factor()
        return L @ L.mT

    def extra_repr(self) -> str:
        return f"kind={self.kind!r}, k={self.k}, fix_first={self.fix_first}, learn={self.learn}"


def _symmetrized(M: Tensor, own: str) -> Tensor:
    """``(M + Mᵀ)/2`` after checking ``|M - Mᵀ| <= 8 k eps max|M|`` (round-off of a product such as ``A Aᵀ``;
    ``eps`` of ``M``'s dtype, ``k`` its size)."""
    tol = 8 * M.shape[-1] * torch.finfo(M.dtype).eps * M.abs().amax((-1, -2), keepdim=True)
    if not bool(((M - M.mT).abs() <= tol).all()):
        raise ValueError(f"{own}: argument 'init' must be symmetric (to {M.dtype} round-off)")
    return 0.5 * (M + M.mT)


def _weight_matrix(w: SPDWeight | Tensor) -> Tensor:
    return w() if isinstance(w, SPDWeight) else w


# --------------------------------------------------------------------------------------------------
# via points with continuous timing
# --------------------------------------------------------------------------------------------------


def _fold_time(tau: Tensor, T: int) -> Tensor:
    """The time actually used for ``tau``: ``tau`` reflected into ``[0, T]`` (identity on ``[0, T]``).

    ``r = tau mod 2T``, ``fold = r`` for ``r <= T`` else ``2T - r``: continuous, slope ``±1`` everywhere (a
    time pushed past an end keeps a gradient that points back, unlike a clamp, whose zero gradient outside
    would freeze it) and idempotent, so :func:`fit_cost` can store ``fold(τ)`` after a step without changing
    the model.
    """
    r = torch.remainder(tau, 2 * T)
    return torch.where(r <= T, r, 2 * T - r)


def time_weights(tau: Tensor, T: int, kernel: str = "gaussian", width: float = 1.0) -> Tensor:
    """Normalized time kernels ``κ (*K, T+1)`` centred on continuous times ``tau (*K,)`` (module docstring).

    ``"gaussian"``: ``softmax_t(-(t - τ)² / 2 width²)`` over ``t = 0..T`` (sums to 1, smooth in ``τ``),
    evaluated as ``softmax_t(-((t - τ)² - min_s (s - τ)²) / width / width / 2)`` (the same value: a softmax is
    shift invariant) so that a tiny ``width`` gives its limit — all weight on the nearest step, or an even
    split between two equidistant steps — instead of ``softmax(-inf, ..., -inf) = NaN``.
    ``"linear"``: ``max(0, 1 - |t - τ|)`` (``width`` ignored): linear interpolation between the two steps
    around ``τ``, a sharp via point at integer ``τ``.  A ``τ`` outside ``[0, T]`` is reflected into it
    (``_fold_time``; slope ``±1``, never a frozen gradient).  Differentiable in ``tau``; dtype and device
    follow it.
    """
    own = "time_weights"
    if not isinstance(tau, Tensor) or tau.dtype not in FLOAT_DTYPES:
        raise TypeError(f"{own}: argument 'tau' must be a float32/float64 tensor (*K,)")
    T = _pos_int(T, "T", own)
    if kernel not in ("gaussian", "linear"):
        raise ValueError(f"{own}: argument 'kernel' must be 'gaussian' or 'linear', got {kernel!r}")
    width = _pos_float(width, "width", own)
    t = torch.arange(T + 1, dtype=tau.dtype, device=tau.device)
    d = t - _fold_time(tau, T).unsqueeze(-1)
    if kernel == "gaussian":
        d2 = d * d
        return torch.softmax(-0.5 * ((d2 - d2.amin(-1, keepdim=True)) / width / width), -1)
    return (1 - d.abs()).clamp_min(0)


class ViaPoints(nn.Module):
    """``K`` via points: targets ``m (K, n)``, precisions ``P (K, n, n)`` and continuous times ``τ (K,)``.

    Args:
        targets: ``(K, n)`` initial targets (a parameter with ``learn_targets``, else a buffer).
        times: ``(K,)`` initial times in ``[0, T]`` (steps, float; a parameter with ``learn_times``).
        precision: an :class:`SPDWeight` with ``*S = (K,)`` (learned, or fixed with ``learn=False``) or a
            fixed PSD tensor ``(K, n, n)`` / ``(n, n)`` (e.g. positions only: ``diag(p, p, 0, 0)``).
        kernel, width: the time kernel (:func:`time_weights`).
    """

    def __init__(self, targets: Tensor, times: Tensor, precision: SPDWeight | Tensor, *,
                 kernel: str = "gaussian", width: float = 1.0, learn_targets: bool = True,
                 learn_times: bool = True):
        super().__init__()
        own = "ViaPoints"
        targets = float_tensor(targets, "targets", own, finite=True).detach()
        if targets.dim() != 2:
            raise ValueError(f"{own}: argument 'targets' must be (K, n), got {tuple(targets.shape)}")
        K, n = targets.shape
        times = float_tensor(times, "times", own, like=targets, finite=True).detach()
        if times.shape != (K,):
            raise ValueError(f"{own}: argument 'times' must be ({K},) for {K} via points, got "
                             f"{tuple(times.shape)}")
        if kernel not in ("gaussian", "linear"):
            raise ValueError(f"{own}: argument 'kernel' must be 'gaussian' or 'linear', got {kernel!r}")
        self.kernel, self.width = kernel, _pos_float(width, "width", own)
        if isinstance(precision, SPDWeight):
            P = precision()
            if tuple(P.shape) != (K, n, n):
                raise ValueError(f"{own}: argument 'precision' must give ({K}, {n}, {n}), got "
                                 f"{tuple(P.shape)}")
            self.precision = precision
        else:
            P = float_tensor(precision, "precision", own, like=targets, finite=True)
            if P.shape[-2:] != (n, n) or P.dim() not in (2, 3) or (P.dim() == 3 and P.shape[0] != K):
                raise ValueError(f"{own}: argument 'precision' must be ({K}, {n}, {n}) or ({n}, {n}), got "
                                 f"{tuple(P.shape)}")
            psd = bool((torch.linalg.eigvalsh(P) >= -1e-12 * P.abs().amax()).all())
            if not torch.allclose(P, P.mT) or not psd:
                raise ValueError(f"{own}: argument 'precision' must be symmetric positive semi-definite")
            self.register_buffer("precision", P.expand(K, n, n).clone())
        for name, v, learn in (("targets", targets, learn_targets), ("times", times, learn_times)):
            if learn:
                self.register_parameter(name, nn.Parameter(v.clone()))
            else:
                self.register_buffer(name, v.clone())

    @property
    def K(self) -> int:
        return int(self.targets.shape[0])

    def weights(self, T: int) -> Tensor:
        """``(K, T+1)`` the time kernels :func:`time_weights` of the current times."""
        return time_weights(self.times, T, self.kernel, self.width)

    def forward(self, T: int) -> tuple[Tensor, Tensor]:
        """``(Qv (T+1, n, n), qv (T+1, n))``: the via points' per-step precision ``Σ_k κ_k(t) P_k`` and linear
        term ``-Σ_k κ_k(t) P_k m_k`` (the cost's convention: ``2 qᵀx``; constants dropped)."""
        W = self.weights(T)
        P = _weight_matrix(self.precision)
        Pm = (P @ self.targets.unsqueeze(-1)).squeeze(-1)  # (K, n)
        return torch.einsum("kt,kij->tij", W, P), -(W.mT @ Pm)


# --------------------------------------------------------------------------------------------------
# the cost model
# --------------------------------------------------------------------------------------------------


class LQTCostModel(nn.Module):
    """A learnable tracking cost (module docstring) as ``forward() -> QuadraticCost``.

    Args:
        Q: state weight: :class:`SPDWeight` or fixed tensor, ``(n, n)`` (time-invariant, ``Q_T = ρ Q``) or
            ``(T+1, n, n)`` (one per step; then ``terminal_factor`` must be 1 and not learned).
        R: control weight ``(m, m)`` or ``(T, m, m)``: :class:`SPDWeight` (normally ``fix_first=True``: the
            scale normalization) or a fixed PD tensor.
        horizon: ``T``.
        target: goal ``g (n,)`` of the running cost (default zero: regulation); a parameter with
            ``learn_target``.
        terminal_factor: ``ρ > 0``; learned on a log scale with ``learn_terminal``.
        via_points: optional :class:`ViaPoints`.

    The produced cost has ``Q (T+1, n, n)``, ``R`` and the linear term ``q (T+1, n)`` (no reference): it
    equals the model's cost up to a constant, which changes no solution.
    """

    def __init__(self, Q: SPDWeight | Tensor, R: SPDWeight | Tensor, horizon: int, *,
                 target: Tensor | None = None, learn_target: bool = False, terminal_factor: float = 1.0,
                 learn_terminal: bool = False, via_points: ViaPoints | None = None):
        super().__init__()
        own = "LQTCostModel"
        self.horizon = T = _pos_int(horizon, "horizon", own)
        terminal_factor = _pos_float(terminal_factor, "terminal_factor", own)
        Qm, Rm = _weight_matrix(Q), _weight_matrix(R)
        for name, M in (("Q", Qm), ("R", Rm)):
            float_tensor(M, name, own, finite=True)
            if M.dim() not in (2, 3) or M.shape[-1] != M.shape[-2]:
                raise ValueError(f"{own}: argument '{name}' must be a square (k, k) or per-step (S, k, k) "
                                 f"weight, got {tuple(M.shape)}")
        n, m = Qm.shape[-1], Rm.shape[-1]
        if Qm.dim() == 3 and Qm.shape[0] != T + 1:
            raise ValueError(f"{own}: a per-step 'Q' must be ({T + 1}, {n}, {n}), got {tuple(Qm.shape)}")
        if Rm.dim() == 3 and Rm.shape[0] != T:
            raise ValueError(f"{own}: a per-step 'R' must be ({T}, {m}, {m}), got {tuple(Rm.shape)}")
        if Qm.dim() == 3 and (terminal_factor != 1.0 or learn_terminal):
            raise ValueError(f"{own}: a per-step 'Q' has its own terminal weight: leave terminal_factor=1, "
                             "learn_terminal=False")
        if Rm.dtype != Qm.dtype or Rm.device != Qm.device:
            raise TypeError(f"{own}: 'Q' and 'R' must share dtype and device, got {Qm.dtype}, {Rm.dtype}")
        kw = dict(dtype=Qm.dtype, device=Qm.device)
        for name, W in (("Q", Q), ("R", R)):
            if isinstance(W, SPDWeight):
                self.add_module(name, W)
            else:
                self.register_buffer(name, W.detach().clone())
        if target is None:
            target = torch.zeros(n, **kw)
        target = float_tensor(target, "target", own, like=Qm, finite=True).detach()
        if target.shape != (n,):
            raise ValueError(f"{own}: argument 'target' must be ({n},), got {tuple(target.shape)}")
        if learn_target:
            self.target = nn.Parameter(target.clone())
        else:
            self.register_buffer("target", target.clone())
        lt = torch.tensor(math.log(terminal_factor), **kw)
        if learn_terminal:
            self.log_terminal = nn.Parameter(lt)
        else:
            self.register_buffer("log_terminal", lt)
        if via_points is not None:
            if not isinstance(via_points, ViaPoints):
                raise TypeError(f"{own}: argument 'via_points' must be a ViaPoints, got "
                                f"{type(via_points).__name__}")
            if via_points.targets.shape[-1] != n or via_points.targets.dtype != Qm.dtype:
                raise ValueError(f"{own}: via point targets must be (K, {n}) of dtype {Qm.dtype}")
            if bool(((via_points.times < 0) | (via_points.times > T)).any()):
                raise ValueError(f"{own}: via point times must lie in [0, {T}], got "
                                 f"{via_points.times.detach().tolist()}")
        self.via_points = via_points
        self.n, self.m = n, m

    @property
    def terminal_factor(self) -> Tensor:
        return self.log_terminal.exp()

    def state_weights(self) -> Tensor:
        """``(T+1, n, n)``: the running/terminal ``Q_t`` (without the via points)."""
        Qm = _weight_matrix(self.Q)
        if Qm.dim() == 3:
            return Qm
        T = self.horizon
        return torch.cat([Qm.expand(T, *Qm.shape), (self.terminal_factor * Qm)[None]])

    def forward(self) -> QuadraticCost:
        """The current :class:`~controllers.costs.QuadraticCost` ``(Q (T+1, n, n), R, q (T+1, n))``,
        differentiable in every parameter."""
        T = self.horizon
        Qs = self.state_weights()
        q = -(Qs @ self.target.unsqueeze(-1)).squeeze(-1)
        if self.via_points is not None:
            Qv, qv = self.via_points(T)
            Qs, q = Qs + Qv, q + qv
        return QuadraticCost(Q=Qs, R=_weight_matrix(self.R), q=q, check=False)

    def weights(self) -> dict[str, Tensor]:
        """Detached copies: ``Q``, ``R``, ``terminal_factor``, ``target`` and, with via points,
        ``via_targets``, ``via_times`` (the times used, in ``[0, T]``: :func:`time_weights`),
        ``via_precision``."""
        with torch.no_grad():
            out = {"Q": _weight_matrix(self.Q).clone(), "R": _weight_matrix(self.R).clone(),
                   "terminal_factor": self.terminal_factor.clone(), "target": self.target.detach().clone()}
            if self.via_points is not None:
                v = self.via_points
                out.update(via_targets=v.targets.detach().clone(),
                           via_times=_fold_time(v.times.detach(), self.horizon),
                           via_precision=_weight_matrix(v.precision).clone())
        return out


def normalize_scale(R: Tensor, *weights: Tensor) -> tuple[Tensor, ...]:
    """``(R / R_00, *(W / R_00))``: the weights of one cost brought to the normalization ``R_00 = 1`` (module
    docstring), e.g. to compare a learned cost with the one that generated the demos at another scale.

    ``R (*B, m, m)``; every ``W`` has the same leading batch dims ``*B`` followed by its own
    (``Q (*B, n, n)``, a terminal factor ``(*B,)``...).  Scaling a whole cost by ``c > 0`` leaves the result
    unchanged.
    """
    if not isinstance(R, Tensor) or R.dim() < 2 or R.shape[-1] != R.shape[-2]:
        raise ValueError("normalize_scale: argument 'R' must be a square tensor (*B, m, m)")
    s = R[..., 0, 0]
    if not bool((torch.isfinite(s) & (s > 0)).all()):
        raise ValueError("normalize_scale: argument 'R' must have a positive finite R_00 (every batch "
                         "element)")
    out = [R / s[..., None, None]]
    for i, W in enumerate(weights):
        if not isinstance(W, Tensor) or W.dim() < s.dim() or W.shape[:s.dim()] != s.shape:
            raise ValueError(f"normalize_scale: weight {i} must have the batch dims {tuple(s.shape)} of 'R' "
                             f"first, got {tuple(getattr(W, 'shape', ()))}")
        out.append(W / s.reshape(*s.shape, *([1] * (W.dim() - s.dim()))))
    return tuple(out)


# --------------------------------------------------------------------------------------------------
# loss and fit
# --------------------------------------------------------------------------------------------------


class IOCLoss(NamedTuple):
    """Result of :func:`ioc_loss`.

    Attributes:
        loss: 0-dim mean of ``per_demo`` over the usable demos (NaN when none is usable).
        per_demo: ``(*B,)`` mean squared state error ``mean_{t,i} (x_t - x̂_t)_i²`` (plus ``control_weight``
            times the control error); NaN where it is not finite (a non-finite solution or demo, or a finite
            demo so large that its squared error overflows).  A finite solve that did not converge reports
            its error at the last iterate here, whether or not it enters ``loss``.
        x: ``(*B, T+1, n)``, u: ``(*B, T, m)`` the optimal trajectories of the cost from the demos' starts.
        status: per-demo :class:`~controllers.problem.SolverStatus` of the solve.
        usable: ``(*B,)`` bool: the demos in ``loss`` — finite ``per_demo`` and, with
            ``unconverged="exclude"``, a converged solve.  The others contribute exactly zero to ``loss`` and
            to its gradient (masked with ``torch.where``, never multiplied by 0).
    """

    loss: Tensor
    per_demo: Tensor
    x: Tensor
    u: Tensor
    status: SolverStatus
    usable: Tensor


_UNCONVERGED = ("exclude", "include")


def _solve(cost: QuadraticCost, dynamics: Any, x0: Tensor, T: int, solver: str, u_init: Tensor | None,
           options: Any) -> tuple[Tensor, Tensor, SolverStatus]:
    if solver == "ilqr":
        from controllers.ilqr import ILQRProblem, ilqr

        sol = ilqr(ILQRProblem(dynamics, cost, x0, T), u_init, grad="implicit", options=options)
        return sol.x, sol.u, sol.status
    if not isinstance(dynamics, LinearDynamics):
        raise TypeError(f"ioc_loss: solver={solver!r} needs LinearDynamics (use solver='ilqr' for a "
                        f"nonlinear system), got {type(dynamics).__name__}")
    problem = LQProblem(dynamics, cost, x0, horizon=T)
    if solver == "lifted":
        from controllers.lifted import solve_lifted

        sol = solve_lifted(problem)
    else:
        from controllers.riccati import solve

        sol = solve(problem, grad="implicit")
    return sol.x, sol.u, sol.status


def _demo_tensors(demos: Demonstrations | Tensor, u_demo: Tensor | None, own: str
                  ) -> tuple[Tensor, Tensor | None]:
    if isinstance(demos, Demonstrations):
        if u_demo is not None:
            raise ValueError(f"{own}: pass the controls inside the Demonstrations, not as 'u_demo'")
        return demos.x, demos.u
    x = float_tensor(demos, "demos", own)  # a non-finite demo is reported per demo
    if x.dim() < 2 or x.shape[-2] < 2:
        raise ValueError(f"{own}: argument 'demos' must be a Demonstrations or states (*B, T+1, n) with "
                         f"T >= 1, got {tuple(x.shape)}")
    if u_demo is not None:
        u_demo = float_tensor(u_demo, "u_demo", own, like=x)
        if u_demo.dim() < 2 or u_demo.shape[-2] != x.shape[-2] - 1:
            raise ValueError(f"{own}: argument 'u_demo' must be (*B, {x.shape[-2] - 1}, m), got "
                             f"{tuple(u_demo.shape)}")
    return x, u_demo


def _loss_args(cost: Any, x_d: Tensor, u_d: Tensor | None, solver: str, control_weight: float,
               unconverged: str, own: str) -> tuple[QuadraticCost, float]:
    if solver not in _SOLVERS:
        raise ValueError(f"{own}: argument 'solver' must be one of {_SOLVERS}, got {solver!r}")
    if unconverged not in _UNCONVERGED:
        raise ValueError(f"{own}: argument 'unconverged' must be one of {_UNCONVERGED}, got {unconverged!r}")
    if isinstance(cost, LQTCostModel):
        cost = cost()
    if not isinstance(cost, QuadraticCost):
        raise TypeError(f"{own}: argument 'cost' must be a QuadraticCost or LQTCostModel, got "
                        f"{type(cost).__name__}")
    T = x_d.shape[-2] - 1
    if x_d.shape[-1] != cost.n:
        raise ValueError(f"{own}: the demos have state dimension {x_d.shape[-1]}, the cost {cost.n}")
    if cost.horizon not in (None, T):
        raise ValueError(f"{own}: the cost has horizon {cost.horizon}, the demos {T} steps "
                         f"(T+1 = {T + 1} samples)")
    if x_d.dtype != cost.dtype:
        raise TypeError(f"{own}: the demos are {x_d.dtype}, the cost {cost.dtype}")
    cw = float(control_weight)
    if not math.isfinite(cw) or cw < 0:
        raise ValueError(f"{own}: argument 'control_weight' must be >= 0, got {control_weight!r}")
    if cw > 0 and u_d is None:
        raise ValueError(f"{own}: control_weight > 0 needs demo controls")
    return cost, cw


def _solve_demos(cost: QuadraticCost, dynamics: Any, x_d: Tensor, solver: str, u_init: Tensor | None,
                 options: Any) -> tuple[Tensor, Tensor, SolverStatus]:
    """One batched solve from the demos' starts; a non-finite start is solved on a stand-in (zero) and
    reported (``NONFINITE_INPUT``, NaN trajectory): its NaN never reaches a shared gradient."""
    x0 = x_d[..., 0, :]
    bad0 = ~torch.isfinite(x0).all(-1)
    zero = torch.zeros((), dtype=x0.dtype, device=x0.device)
    if u_init is not None:
        u_init = torch.where(torch.isfinite(u_init), u_init, zero)
    x, u, status = _solve(cost, dynamics, torch.where(bad0[..., None], zero, x0), x_d.shape[-2] - 1, solver,
                          u_init, options)
    bad0 = bad0.expand(status.reason.shape)
    reason = torch.where(bad0, int(Reason.NONFINITE_INPUT), status.reason)
    status = SolverStatus(converged=reason == int(Reason.CONVERGED), iterations=status.iterations,
                          reason=reason)
    nan = torch.full((), math.nan, dtype=x.dtype, device=x.device)
    return torch.where(bad0[..., None, None], nan, x), torch.where(bad0[..., None, None], nan, u), status


def _per_demo_error(x: Tensor, u: Tensor, x_d: Tensor, u_d: Tensor | None, cw: float
                    ) -> tuple[Tensor, Tensor]:
    """``(per (*B,), finite (*B,))``: the squared errors and where they are finite (finite inputs and no
    overflow).  Non-finite differences are replaced (not multiplied) by zero, so their gradient is zero."""
    zero = torch.zeros((), dtype=x.dtype, device=x.device)
    finite = torch.isfinite(x).all((-1, -2)) & torch.isfinite(x_d).all((-1, -2))
    if cw > 0:
        finite = finite & torch.isfinite(u).all((-1, -2)) & torch.isfinite(u_d).all((-1, -2))
    keep = finite[..., None, None]
    per = torch.where(keep, x - x_d, zero).pow(2).mean((-1, -2))
    if cw > 0:
        per = per + cw * torch.where(keep, u - u_d, zero).pow(2).mean((-1, -2))
    return per, finite & torch.isfinite(per)


def ioc_loss(cost: QuadraticCost | LQTCostModel, dynamics: Any, demos: Demonstrations | Tensor,
             u_demo: Tensor | None = None, *, solver: str = "riccati", control_weight: float = 0.0,
             u_init: Tensor | None = None, options: Any = None, unconverged: str = "exclude") -> IOCLoss:
    """Imitation loss of a cost: solve from every demo's start (one batched solve) and compare.

    Args:
        cost: a :class:`~controllers.costs.QuadraticCost` (shared or batched like the demos) or an
            :class:`LQTCostModel` (called).
        dynamics: :class:`~controllers.dynamics.LinearDynamics` (``"riccati"``, ``"lifted"``) or any
            :class:`~controllers.dynamics.System` (``"ilqr"``).
        demos: a :class:`~learning.demos.Demonstrations` (``x (N, T+1, n)``, optional ``u (N, T, m)``) or a
            state tensor ``(*B, T+1, n)`` with optional ``u_demo (*B, T, m)``.
        solver: ``"riccati"`` (implicit Riccati gradients), ``"lifted"`` (Eq. 62, autograd through the
            Cholesky solve) or ``"ilqr"`` (implicit iLQR gradients).
        control_weight: weight of the control error (needs demo controls when > 0).
        u_init: iLQR initial controls ``(*B, T, m)``; options: :class:`~controllers.ilqr.ILQROptions`.
        unconverged: what to do with a finite solve whose status is not converged (iLQR out of
            iterations): ``"exclude"`` (default) leaves it out of ``loss`` (``usable`` False; its status says
            why), so every gradient is exact; ``"include"`` keeps it, with the implicit-function gradient
            evaluated at the last iterate — an *inexact* gradient (it assumes optimality there; measured
            10-30 % off after 2 iLQR iterations).

    A demo whose error is not finite (non-finite start or samples, non-finite solution, or a finite but
    huge demo whose squared error overflows) is never usable; loss and gradient then equal those of the
    other demos.
    """
    own = "ioc_loss"
    x_d, u_d = _demo_tensors(demos, u_demo, own)
    cost, cw = _loss_args(cost, x_d, u_d, solver, control_weight, unconverged, own)
    x, u, status = _solve_demos(cost, dynamics, x_d, solver, u_init, options)
    per, finite = _per_demo_error(x, u, x_d, u_d, cw)
    usable = finite if unconverged == "include" else finite & status.converged
    zero = torch.zeros((), dtype=per.dtype, device=per.device)
    loss = torch.where(usable, per, zero).sum() / usable.sum()
    per = torch.where(finite, per, torch.full_like(zero, math.nan))
    return IOCLoss(loss=loss, per_demo=per, x=x, u=u, status=status, usable=usable)


class IOCResult(NamedTuple):
    """Result of :func:`fit_cost`.

    Attributes:
        model: the fitted :class:`LQTCostModel` (a copy; the argument is not modified).
        loss: final loss (float).
        history: per evaluation: ``"loss"``, ``"not_converged"`` (demos whose solve was not certified),
            ``"excluded_not_converged"`` (of those, finite ones left out of the loss by
            ``unconverged="exclude"``), ``"unusable"`` (every demo left out of that evaluation's loss:
            non-finite errors and the excluded non-converged ones).
        status: per-demo :class:`~controllers.problem.SolverStatus` of the final solve.
        x, u: the final reproductions (detached).
        usable: ``(*B,)`` bool: the demos in the final loss.
    """

    model: LQTCostModel
    loss: float
    history: dict[str, list[float]]
    status: SolverStatus
    x: Tensor
    u: Tensor
    usable: Tensor | None = None


def _fit_args(model: Any, steps: Any, optimizer: str, solver: str, lr: Any, tol: Any, unconverged: str,
              own: str) -> tuple[int, float, float]:
    if not isinstance(model, LQTCostModel):
        raise TypeError(f"{own}: argument 'model' must be an LQTCostModel, got {type(model).__name__}")
    steps = _pos_int(steps, "steps", own)
    if optimizer not in ("lbfgs", "adam"):
        raise ValueError(f"{own}: argument 'optimizer' must be 'lbfgs' or 'adam', got {optimizer!r}")
    if solver not in _SOLVERS:
        raise ValueError(f"{own}: argument 'solver' must be one of {_SOLVERS}, got {solver!r}")
    if unconverged not in _UNCONVERGED:
        raise ValueError(f"{own}: argument 'unconverged' must be one of {_UNCONVERGED}, got {unconverged!r}")
    if isinstance(tol, bool) or not isinstance(tol, (int, float)) or not math.isfinite(tol) or tol < 0:
        raise ValueError(f"{own}: argument 'tol' must be a finite number >= 0, got {tol!r}")
    lr = (1.0 if optimizer == "lbfgs" else 0.05) if lr is None else _pos_float(lr, "lr", own)
    return steps, lr, float(tol)


def _project_times(model: LQTCostModel) -> None:
    """Store the via-point times as the times used (:func:`time_weights` reflects them into ``[0, T]``):
    the model is unchanged and its times stay valid for its constructor."""
    vp = model.via_points
    if vp is not None and isinstance(vp.times, nn.Parameter):
        with torch.no_grad():
            vp.times.copy_(_fold_time(vp.times, model.horizon))


def _no_usable_demo(out: IOCLoss, own: str) -> ValueError:
    finite = torch.isfinite(out.per_demo)
    if not bool(finite.any()):
        return ValueError(f"{own}: no demo gave a finite solution (status {out.status.reason_names()[:8]})")
    return ValueError(f"{own}: no usable demo: the {int(finite.sum())} finite solves did not converge "
                      f"(status {out.status.reason_names()[:8]}); raise the solver's iterations or pass "
                      "unconverged='include' (inexact gradients)")


def fit_cost(demos: Demonstrations | Tensor, dynamics: Any, model: LQTCostModel, *,
             u_demo: Tensor | None = None, steps: int = 100, lr: float | None = None,
             optimizer: str = "lbfgs", solver: str = "riccati", control_weight: float = 0.0,
             options: Any = None, tol: float = 0.0, unconverged: str = "exclude") -> IOCResult:
    """Fit the parameters of ``model`` to demonstrations (inverse optimal control, module docstring).

    Minimizes :func:`ioc_loss` (all demos in one batched solve per evaluation, gradients through the
    solver; ``unconverged`` as there: by default a non-converged demo is left out of that evaluation's
    loss and counted) with L-BFGS (strong-Wolfe line search, ``steps`` iterations, ``lr`` default 1) or Adam
    (``steps`` iterations, ``lr`` default 0.05).  With ``solver="ilqr"`` each solve is warm-started from the
    previous one (the first from the demo controls when given, else zero), held in this function, not in
    the solver.  Every evaluation records its loss and how many demos did not converge / were not usable;
    the final status and usability are returned per demo (never dropped silently).  Adam stops early when
    the loss is at most ``tol`` (finite, ``>= 0``); L-BFGS runs its ``steps`` iterations (at most
    ``2 steps`` evaluations).  Via-point times are stored as the times used (in ``[0, T]``) after every
    Adam step and after the L-BFGS run.  Raises ``ValueError`` when no demo is usable.  Both linear solvers
    give the same gradient; their speed depends on the machine: measured here (CPU, 1 thread, ``n = 4``,
    ``m = 2``, 4-8 demos) ``"lifted"`` (one dense Cholesky solve of size ``T m``) was 1.4-1.7x faster at
    ``T = 5..30`` and on par at ``T = 60..100``, where its ``O((T m)³)`` cost meets the Riccati sweep's
    Python loop over time; another machine measured ``"riccati"`` faster at ``T = 30`` — time both.

    **Under torchrun** (:mod:`learning.distributed`; an initialized process group with ``W > 1`` ranks, every
    rank calling ``fit_cost`` with the same demos and model): the demos' batch dims are flattened to
    ``(N, T+1, n)`` (``N >= W`` needed) and each rank solves one contiguous block of them; the model is
    wrapped in ``DistributedDataParallel`` (which starts every rank from rank 0's parameters).  The loss is
    the *global* mean over the usable demos — each rank backpropagates ``W · (its sum) / N_usable`` and DDP
    averages the gradients over the ``W`` ranks, so the gradient is the single-process one up to the order
    of the floating-point sums — and its value and the history's counters are all-reduced, so L-BFGS/Adam
    take the same step on every rank and the parameters stay identical.  The result (per-demo status,
    reproductions, usability) is gathered back in demo order on every rank.  A single process is unchanged.

    Returns:
        :class:`IOCResult` (the fitted copy of ``model``, history, status, reproductions).
    """
    own = "fit_cost"
    steps, lr, tol = _fit_args(model, steps, optimizer, solver, lr, tol, unconverged, own)
    x_d, u_d = _demo_tensors(demos, u_demo, own)
    model = copy.deepcopy(model)
    params = [p for p in model.parameters() if p.requires_grad]
    if not params:
        raise ValueError(f"{own}: the model has no learnable parameter")
    shards = _Shards(x_d, u_d, model, own) if _dist.world_size() > 1 else None
    if shards is not None:
        x_d, u_d = shards.x, shards.u
    hist: dict[str, list[float]] = {"loss": [], "not_converged": [], "excluded_not_converged": [],
                                    "unusable": []}
    warm: dict[str, Tensor | None] = {"u": None if u_d is None else u_d.detach()}

    def evaluate() -> tuple[IOCLoss, Tensor]:
        def loss() -> IOCLoss:
            return ioc_loss(model if shards is None else shards.ddp(), dynamics, x_d, u_d, solver=solver,
                            control_weight=control_weight, u_init=warm["u"] if solver == "ilqr" else None,
                            options=options, unconverged=unconverged)

        if shards is None:
            out = loss()
            objective, counts = out.loss, _counts(out)
        else:
            out, objective, counts = shards.reduce(loss)
        if counts[0] == 0:  # the counts are global: every rank raises, with every demo's status
            raise _no_usable_demo(out if shards is None else shards.gather(out), own)
        if solver == "ilqr":
            fin = torch.isfinite(out.u).all((-1, -2), keepdim=True)
            warm["u"] = torch.where(fin, out.u.detach(), out.u.new_zeros(()))
        hist["loss"].append(float(out.loss.detach()))
        for key, c in zip(("not_converged", "excluded_not_converged", "unusable"), counts[1:]):
            hist[key].append(c)
        return out, objective

    _optimize(evaluate, params, model, optimizer, steps, lr, tol, hist)
    with torch.no_grad():
        final, _ = evaluate()
    if shards is not None:
        final = shards.gather(final)
    return IOCResult(model=model, loss=float(final.loss), history=hist, status=final.status,
                     x=final.x.detach(), u=final.u.detach(), usable=final.usable)


def _counts(out: IOCLoss) -> list[int]:
    """``[usable, not converged, excluded not converged, unusable]`` demos of one evaluation."""
    nc = ~out.status.converged
    excl = nc & ~out.usable & torch.isfinite(out.per_demo)
    return [int(out.usable.sum()), int(nc.sum()), int(excl.sum()), int((~out.usable).sum())]


class _Shards:
    """This rank's block of the demos under torchrun and the collectives of :func:`fit_cost`."""

    def __init__(self, x_d: Tensor, u_d: Tensor | None, model: LQTCostModel, own: str):
        # the demos' batch shape as a single process sees it: that of x and u (T, m) or (*B, T, m) broadcast
        self.batch = x_d.shape[:-2] if u_d is None else torch.broadcast_shapes(x_d.shape[:-2], u_d.shape[:-2])
        self.n = math.prod(self.batch)
        self.w = _dist.world_size()
        self.own = own
        if self.n < self.w:
            raise ValueError(f"{own}: {self.n} demos cannot be shared by {self.w} ranks (at least one each)")
        sl = _dist.shard(self.n)
        self.x = x_d.expand(*self.batch, *x_d.shape[-2:]).reshape(self.n, *x_d.shape[-2:])[sl]
        self.u = None if u_d is None else u_d.expand(*self.batch, *u_d.shape[-2:]).reshape(
            self.n, *u_d.shape[-2:])[sl]
        self.ddp = _dist.wrap_ddp(model)

    def reduce(self, loss: Any) -> tuple[IOCLoss, Tensor, list[int]]:
        """``(out with the global loss, the objective to backpropagate, the global counts)`` of
        ``out = loss()`` on this rank's demos: one all-reduce of ``[sum of usable errors, counts, failed]``;
        the objective ``W · sum / N_usable`` gives, after DDP's average over ``W`` ranks, the gradient of the
        global mean.  When ``loss()`` raised on any rank, every rank raises (never a rank left waiting)."""
        try:
            out, error = loss(), None
        except Exception as e:
            out, error = None, e
        like = self.x
        local = like.new_zeros(()) if out is None else torch.where(out.usable, out.per_demo,
                                                                    like.new_zeros(())).sum()
        counts = [0] * 4 if out is None else _counts(out)
        flags = torch.tensor([*counts, error is not None], dtype=local.dtype, device=local.device)
        total = _dist.all_reduce_sum(torch.cat([local.detach()[None], flags]))
        if bool(total[-1] > 0):
            _dist.raise_together(error, self.own)
        n_use = total[1]
        return out._replace(loss=total[0] / n_use), local * (self.w / n_use), [int(c) for c in total[1:-1]]

    def gather(self, out: IOCLoss) -> IOCLoss:
        """The per-demo fields of every rank, in demo order, with the demos' batch shape."""
        def g(t: Tensor) -> Tensor:
            return _dist.gather_along(t, self.n).reshape(*self.batch, *t.shape[1:])

        st = out.status
        status = SolverStatus(converged=g(st.converged), iterations=g(st.iterations), reason=g(st.reason))
        return out._replace(per_demo=g(out.per_demo), x=g(out.x), u=g(out.u), status=status,
                            usable=g(out.usable))


def _optimize(evaluate: Any, params: list[Tensor], model: LQTCostModel, optimizer: str, steps: int, lr: float,
              tol: float, hist: dict[str, list[float]]) -> None:
    def closure() -> Tensor:
        opt.zero_grad()
        out, objective = evaluate()
        objective.backward()
        return out.loss

    if optimizer == "lbfgs":
        opt = torch.optim.LBFGS(params, lr=lr, max_iter=steps, max_eval=2 * steps, history_size=20,
                                tolerance_grad=0.0, tolerance_change=0.0, line_search_fn="strong_wolfe")
        opt.step(closure)
        _project_times(model)
        return
    opt = torch.optim.Adam(params, lr=lr)
    for _ in range(steps):
        if hist["loss"] and hist["loss"][-1] <= tol:
            break
        opt.step(closure)
        _project_times(model)


# --------------------------------------------------------------------------------------------------
# minimal intervention (§7.7)
# --------------------------------------------------------------------------------------------------


class MinimalIntervention(NamedTuple):
    """Result of :func:`minimal_intervention`.

    Attributes:
        K: ``(*B, T-1, D, n)`` feedback gains of the tracking LQT (``u_t = K_t x_t + k_t``).
        gain_norm: ``(*B, T-1)`` Frobenius norms ``‖K_t‖``.
        variance: ``(*B, T)`` the demos' positional variance per step (trace of the position block of the
            ProMP's state covariance ``Σ_t``).
        precision: ``(*B, T, n, n)`` the tracking precisions ``(Σ_t + floor I)⁻¹``.
        tracking: the :class:`~learning.primitives.Tracking` (closed-loop states, controls, status).
        promp: the fitted :class:`~learning.primitives.ProMP`.
    """

    K: Tensor
    gain_norm: Tensor
    variance: Tensor
    precision: Tensor
    tracking: Any
    promp: Any


def minimal_intervention(demos: Demonstrations | Tensor, *, dt: float | None = None, n_basis: int = 10,
                         control_weight: float = 1e-6, floor: float = 1e-6, x0: Tensor | None = None,
                         **promp_kw: Mapping[str, Any]) -> MinimalIntervention:
    """Minimal-intervention tracking controller from demonstrations (seed §7.7).

    Fits :func:`learning.primitives.fit_promp` (double integrator per position coordinate, ``n_basis`` basis
    functions; ``demos`` positions ``(N, T, D)`` or ``(*B, N, T, D)``) and runs
    :meth:`learning.primitives.ProMP.track` (precision ``(Σ_t + floor I)⁻¹``, control weight
    ``control_weight I``) from ``x0`` (default the mean start).  The gains are what the demos' covariance
    leaves: ``‖K_t‖`` is small where the demos vary (low precision ahead) and large where they agree.
    """
    from learning.primitives import fit_promp

    pm = fit_promp(demos, dt=dt, n_basis=n_basis, **promp_kw)
    tr = pm.track(x0, control_weight=control_weight, floor=floor)
    cov = pm.state_marginal_cov()
    var = cov[..., :pm.D, :pm.D].diagonal(dim1=-2, dim2=-1).sum(-1)
    return MinimalIntervention(K=tr.K, gain_norm=torch.linalg.matrix_norm(tr.K), variance=var,
                               precision=tr.precision, tracking=tr, promp=pm)
