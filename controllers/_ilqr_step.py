"""One iteration of iLQR (private) as pure functions of tensors, and the same iteration as one program.

:func:`controllers.ilqr.ilqr`'s loop is made of these pieces: :func:`linearize` (Jacobians, cost
derivatives, the certificate's projected gradient), :func:`mark_certified`, the backward pass with its μ
retries (in ``ilqr``), :func:`stop_checks` and :func:`line_search`.  Each takes and returns an
:class:`Iterate` and never reads a tensor on the host, so that :func:`iteration` — all of them in a row,
the backward pass at the current μ — can be built as one program (:mod:`controllers._compiled`) and called
once per iteration, with one host read (its ``flags``) instead of ~5 and ~1 000 eager kernels.

The program serves the common case exactly: where the backward pass fails for an active element (μ must
grow and the pass be repeated, a data-dependent loop), its result is dropped and ``ilqr`` runs that
iteration eagerly from the same inputs.  It is used for time-invariant systems with analytic Jacobians and
plain-number parameters (:func:`controllers._compiled.fingerprint`), a :class:`QuadraticCost` or a
:class:`PeriodicQuadraticCost` (its tensors are program inputs: a new reference costs no rebuild), the
recursive method, and up to two limited controls or unlimited ones (:func:`can_compile_iteration`).
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

from controllers._ilqr_sweeps import (
    backward_pass,
    can_compile_iteration,
    forward_candidates,
    kkt_parts,
    run_flat,
)
from controllers._validate import time_major
from controllers.costs import PeriodicQuadraticCost, QuadraticCost, cost_derivatives
from controllers.dynamics import has_analytic_jacobian, trajectory_jacobians
from controllers.problem import Reason

__all__ = ["Settings", "Iterate", "Linearization", "linearize", "mark_certified", "stop_checks",
           "line_search", "grow", "kkt_relative", "pick", "iteration", "program_iteration",
           "program_supported"]


@dataclass(frozen=True)
class Settings:
    """The scalar options an iteration reads (:class:`controllers.ilqr.ILQROptions` with the dtype's
    defaults filled in); a program bakes them in (:meth:`key`)."""

    tol: float
    tol_cost: float
    tol_kkt: float
    mu_factor: float
    mu_min: float
    mu_max: float
    armijo: float
    steps: int  # line-search step sizes 1, ½, ¼, …

    @functools.cached_property
    def key(self) -> str:
        return ";".join(f"{f.name}={getattr(self, f.name)!r}" for f in dataclasses.fields(self))


class Iterate(NamedTuple):
    """The iterate and its bookkeeping: ``x (*B, T+1, n)``, ``u (*B, T, m)``, the rest ``(*B,)``."""

    x: Tensor
    u: Tensor
    J: Tensor
    mu: Tensor
    dmu: Tensor
    iters: Tensor
    ntiny: Tensor  # consecutive accepted steps whose decrease was measurably tiny
    reason: Tensor
    active: Tensor


class Linearization(NamedTuple):
    """The local model at the iterate, time-major, and the certificate's parts there."""

    A: Tensor
    B: Tensor
    gx: Tensor
    gu: Tensor
    Hxx: Tensor
    Hux: Tensor | None
    Huu: Tensor
    u: Tensor  # (T, *B, m)
    umax: Tensor  # (*B,) max |u|
    pg: Tensor  # (*B,) max |projected gradient|
    terms: Tensor  # (*B,) max of the gradient's terms


def kkt_floor(tol: float, tol_kkt: float) -> float:
    """The floor of :func:`kkt_relative`'s scale, ``tol / tol_kkt`` (0 for ``tol_kkt = 0``: nothing but an
    exactly zero residual is certified then, as without a floor)."""
    return tol / tol_kkt if tol_kkt > 0 else 0.0


def kkt_relative(pg: Tensor, terms: Tensor, curv: Tensor, umax: Tensor, floor: float = 0.0) -> Tensor:
    """The relative KKT residual ``max|pg| / max(max terms + c · ‖u‖∞, c · floor)``
    (:attr:`ILQROptions.tol_kkt`); ``curv`` is ``c``, the largest diagonal entry of the Riccati ``Q_uu,t``
    (0: the terms alone, stricter).  ``floor = tol / tol_kkt`` makes a residual whose Newton step
    ``|pg| / c`` is below the negligible-step tolerance ``tol`` pass: at an optimum where the terms and the
    controls are all ~0 (a pendulum held exactly upright) the ratio would otherwise be rounding over
    rounding."""
    scale = torch.maximum(terms + curv * umax, curv * floor)
    return pg / scale.clamp_min(torch.finfo(pg.dtype).tiny)


def pick(v: Tensor, idx: Tensor) -> Tensor:
    """``v (S, *B, ...)``, ``idx (*B,)`` -> ``v[idx[b], b, ...]``."""
    extra = v.dim() - 1 - idx.dim()
    i = idx.view(1, *idx.shape, *([1] * extra)).expand(1, *v.shape[1:])
    return torch.gather(v, 0, i).squeeze(0)


def grow(mu: Tensor, dmu: Tensor, where: Tensor, s: Settings) -> tuple[Tensor, Tensor]:
    """The regularization schedule's growth (Tassa et al.) where ``where``."""
    f = s.mu_factor
    dmu = torch.where(where, torch.clamp(dmu * f, min=f), dmu)
    mu = torch.where(where, torch.clamp(mu * dmu, min=s.mu_min), mu)
    return mu, dmu


def linearize(dyn, cost, x: Tensor, u: Tensor, lo_tm, hi_tm, bs: torch.Size, compiled: bool) -> Linearization:
    """Jacobians and cost derivatives along ``(x, u)``, time-major, and the certificate's parts there."""
    T, nb = u.shape[-2], len(bs)
    A, B = trajectory_jacobians(dyn, x, u)
    gx, gu, Hxx, Hux, Huu = cost_derivatives(cost, x, u)
    gx_tm, gu_tm = gx.movedim(-2, 0), gu.movedim(-2, 0)
    u_tm = u.movedim(-2, 0)
    pg, terms = kkt_parts(A, B, gx_tm, gu_tm, u_tm, lo_tm, hi_tm, bs, compiled)
    return Linearization(A, B, gx_tm, gu_tm, time_major(Hxx, 2, T + 1, nb), time_major(Hux, 2, T, nb),
                         time_major(Huu, 2, T, nb), u_tm, u.abs().flatten(-2).amax(-1), pg, terms)


def mark_certified(it: Iterate, lin: Linearization, s: Settings) -> Iterate:
    """The last accepted step barely lowered the cost: done if certified here.  Before the backward pass the
    certificate is judged on the gradient's terms alone (stricter: no curvature yet).  Otherwise steps go on
    (a decrease below ``tol_cost·|J|`` can leave a gradient well above ``tol_kkt`` on a flat valley; Newton
    steps remove it) until the step itself is negligible."""
    cert = kkt_relative(lin.pg, lin.terms, torch.zeros_like(lin.pg), lin.umax) <= s.tol_kkt
    done = it.active & (it.ntiny >= 1) & cert
    return it._replace(reason=torch.where(done, int(Reason.CONVERGED), it.reason), active=it.active & ~done)


def stop_checks(it: Iterate, lin: Linearization, k: Tensor, curv: Tensor | None, s: Settings) -> Iterate:
    """After the backward pass: the certificate with its curvature (``curv``; None for the batch form: the
    terms alone), and Δ_min of Algorithms 4-5 — a negligible step is converged if certified, else stalled."""
    cert = kkt_relative(lin.pg, lin.terms, torch.zeros_like(lin.pg) if curv is None else curv,
                        lin.umax, kkt_floor(s.tol, s.tol_kkt)) <= s.tol_kkt
    done = it.active & (it.ntiny >= 1) & cert
    reason = torch.where(done, int(Reason.CONVERGED), it.reason)
    active = it.active & ~done
    kmax = k.abs().amax(dim=(0, -1))
    small = active & (kmax <= s.tol * (1 + lin.umax))
    reason = torch.where(small, torch.where(cert, int(Reason.CONVERGED), int(Reason.STALLED)), reason)
    return it._replace(reason=reason, active=active & ~small)


def line_search(dyn, cost, x0: Tensor, it: Iterate, K, k: Tensor, dV1: Tensor, dV2: Tensor, lo, hi,
                bs: torch.Size, s: Settings, dyn_key: str | None) -> tuple[Iterate, Tensor]:
    """Every step size at once (Eq. 101), the first that passes Armijo's test is taken, and the μ schedule
    (shrink on success, grow on failure); returns the next iterate and ``accept (*B,)``."""
    x, u, J, mu, dmu = it.x, it.u, it.J, it.mu, it.dmu
    kw = dict(dtype=J.dtype, device=J.device)
    alphas = 0.5 ** torch.arange(s.steps, **kw)
    xc, uc = forward_candidates(dyn, x0, x, u, K, k, alphas, lo, hi, bs, dyn_key)
    Jc = cost.evaluate(xc, uc).expand(s.steps, *bs)
    a = alphas.view(-1, *([1] * len(bs)))
    expected = -(a * dV1 + a * a * dV2)
    okc = torch.isfinite(Jc) & (J - Jc > s.armijo * expected.clamp_min(0))
    # below round-off the cost cannot confirm a decrease: trust the local model for the full step, which
    # keeps the last Newton steps (quadratic convergence) and the solution accurate to ~eps
    noise = 64 * torch.finfo(J.dtype).eps * J.abs().clamp_min(1.0)
    first_ok = okc[0] | (torch.isfinite(Jc[0]) & (expected[0].abs() <= noise) & (Jc[0] <= J + noise))
    okc = torch.cat([first_ok.unsqueeze(0), okc[1:]])
    anyok = okc.any(0)
    first = torch.argmax(okc.to(torch.int8), dim=0)
    active = it.active
    accept = active & anyok
    Jn = pick(Jc, first)
    improvement = J - Jn
    x = torch.where(accept[..., None, None], pick(xc, first), x)
    u = torch.where(accept[..., None, None], pick(uc, first), u)
    Jnew = torch.where(accept, Jn, J)
    iters = it.iters + active.to(torch.int64)
    dmu_s = torch.clamp(dmu / s.mu_factor, max=1 / s.mu_factor)
    mu_s = mu * dmu_s
    mu_s = torch.where(mu_s > s.mu_min, mu_s, torch.zeros((), **kw))
    mu = torch.where(accept, mu_s, mu)
    dmu = torch.where(accept, dmu_s, dmu)
    failed = active & ~anyok
    mu, dmu = grow(mu, dmu, failed, s)
    over = failed & (mu > s.mu_max)
    reason = torch.where(over, int(Reason.LINE_SEARCH_FAILED), it.reason)
    # a measured (not round-off) small decrease: stop at the next point if it is certified (checked there);
    # below round-off keep taking Newton steps until the step itself is negligible
    tiny = accept & (improvement <= s.tol_cost * J.abs()) & (pick(expected, first) > noise)
    ntiny = torch.where(tiny, it.ntiny + 1, torch.zeros_like(it.ntiny))
    return Iterate(x, u, Jnew, mu, dmu, iters, ntiny, reason, active & ~over), accept


def iteration(dyn, cost, x0: Tensor, it: Iterate, lo, hi, s: Settings, dyn_key: str | None = None
              ) -> tuple[Iterate, Tensor]:
    """One whole iteration at the current μ (no retry), pure: the next iterate and ``flags (4,)`` int64 —
    [any element active after :func:`mark_certified`, any active element whose backward pass failed (the
    result is then void: run the iteration eagerly), any active after :func:`stop_checks`, any active at
    the end].  Where the first or third is 0 the iterate's statuses are final and ``x``, ``u``, ``J`` are
    unchanged (nothing was active to move)."""
    bs = it.J.shape
    lo_tm = None if lo is None else lo.movedim(-2, 0)
    hi_tm = None if hi is None else hi.movedim(-2, 0)
    lin = linearize(dyn, cost, it.x, it.u, lo_tm, hi_tm, bs, False)
    it = mark_certified(it, lin, s)
    pre = it.active.any()
    dlo = None if lo is None else lo_tm - lin.u
    dhi = None if hi is None else hi_tm - lin.u
    bw = backward_pass(lin.A, lin.B, lin.gx, lin.gu, lin.Hxx, lin.Hux, lin.Huu, it.mu, dlo, dhi, None, bs)
    fail = (it.active & ~bw.ok).any()
    it = stop_checks(it, lin, bw.k, bw.curv, s)
    stop = it.active.any()
    it, _ = line_search(dyn, cost, x0, it, bw.K, bw.k, bw.dV1, bw.dV2, lo, hi, bs, s, dyn_key)
    return it, torch.stack([pre, fail, stop, it.active.any()]).to(torch.int64)


# --------------------------------------------------------------------------------------------------
# the iteration as a program
# --------------------------------------------------------------------------------------------------

# the fields of a QuadraticCost and their event dims (time included) after its normalization
_FIELDS = (("Q", 3), ("R", 3), ("x_ref", 2), ("u_ref", 2), ("N", 3), ("q", 2), ("r", 2))


def _cost_leaves(cost) -> tuple[str, list[Tensor], list] | None:
    """``(structure key, tensors, run_flat layouts)`` of a (periodic) quadratic cost, None for other costs;
    a field with batch dims is flattened with the batch, a shared one passes as it is."""
    base, periodic = (cost.base, cost.periodic) if isinstance(cost, PeriodicQuadraticCost) else (cost, None)
    if type(base) is not QuadraticCost:
        return None
    names, tensors, layout = [], [], []
    for name, ev in _FIELDS:
        v = getattr(base, name)
        if v is not None:
            names.append(name)
            tensors.append(v)
            layout.append(None if v.dim() == ev else (0, ev))
    if periodic is not None:
        tensors.append(periodic)
        layout.append(None)
    return f"cost={','.join(names)};periodic={periodic is not None}", tensors, layout


def _cost_from(names: tuple[str, ...], periodic: bool, tensors: tuple[Tensor, ...]):
    """The cost of :func:`_cost_leaves`' tensors (inside a program: no checks, the original passed them)."""
    base = object.__new__(QuadraticCost)
    for name, _ in _FIELDS:
        object.__setattr__(base, name, None)
    object.__setattr__(base, "check", False)
    for name, v in zip(names, tensors):
        object.__setattr__(base, name, v)
    if not periodic:
        return base
    cost = object.__new__(PeriodicQuadraticCost)
    object.__setattr__(cost, "base", base)
    object.__setattr__(cost, "periodic", tensors[len(names)])
    return cost


def program_supported(dyn, cost, dyn_key: str | None, m: int, bounded: bool, recursive: bool) -> bool:
    """Whether :func:`program_iteration` can serve this problem (module docstring)."""
    return (dyn_key is not None and recursive and has_analytic_jacobian(dyn)
            and can_compile_iteration(m, bounded) and _cost_leaves(cost) is not None)


def program_iteration(dyn, dyn_key: str, cost, x0: Tensor, it: Iterate, lo, hi, bs: torch.Size, s: Settings
                      ) -> tuple[Iterate, Tensor]:
    """:func:`iteration` as one program (built once per structure; the batch flattened), or run eagerly
    where no program can be built here."""
    key, ctensors, clayout = _cost_leaves(cost)
    base = cost.base if isinstance(cost, PeriodicQuadraticCost) else cost
    names = tuple(name for name, _ in _FIELDS if getattr(base, name) is not None)
    periodic = isinstance(cost, PeriodicQuadraticCost)
    bounded = lo is not None
    nl = 2 if bounded else 0

    def fn(x0, x, u, J, mu, dmu, iters, ntiny, reason, active, *rest):
        c = _cost_from(names, periodic, tuple(rest[nl:]))
        lims = rest[:nl] if bounded else (None, None)
        nxt, flags = iteration(dyn, c, x0, Iterate(x, u, J, mu, dmu, iters, ntiny, reason, active), *lims, s)
        return (*nxt, flags)

    args = (x0, *it, *((lo, hi) if bounded else ()), *ctensors)
    layout = ((0, 1), (0, 2), (0, 2)) + ((0, 0),) * 7 + ((0, 2),) * nl + tuple(clayout)
    T, n, m = it.u.shape[-2], it.x.shape[-1], it.u.shape[-1]
    out = run_flat("ilqr_iteration", f"{dyn_key};{key};T={T};n={n};m={m};bounded={bounded};{s.key}", fn,
                   args, layout, bs, (0,) * 9 + (None,))
    return Iterate(*out[:9]), out[9]
