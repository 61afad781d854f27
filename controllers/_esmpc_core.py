"""The error-state MPC step as one pure program (private to :mod:`controllers.manifold_mpc`, issue 23).

:func:`step` is ``ErrorStateMPC.solve``'s numeric core written as a function of flat, batch-first tensors
with a fixed shape of work: the per-element input statuses (non-finite data, the limits' rule), the stand-ins
for bad elements, the manifold membership of the states (a flag, not an exception), the linearization
(:func:`~controllers.manifold_mpc.error_system`: the system's analytic Jacobians or ``torch.func``), then

* ``form="qp"``: the condensed QP (:func:`~controllers.manifold_mpc._condensed_qp`, its time recursion a
  :func:`controllers._compiled.scan`), its closed form (Eq. 31), and where that breaks a limit the box QP
  with a fixed budget (:func:`controllers.boxqp.box_qp_fixed`) and :func:`~controllers.boxqp.box_qp`'s
  certificate; in float64 for float32/half data, as the eager path;
* ``form="riccati"``: the O(N) Riccati recursion on the augmented state (``m`` Gauss–Jordan pivots a step,
  :func:`controllers._lq_kernels._eliminate`) and which elements break a limit,

and the NaN-ing of failed elements.  It runs eagerly (a Python loop per ``scan``: the reference the tests
compare against) or built by :func:`controllers._compiled.build` into one AOTInductor program with a dynamic
batch.  Nothing in it reads the host; what must raise or fall back is returned as ``flags``
``(3,)`` int64: no finite element at all, a state off the manifold, and some element that needs more than
the program did (``form="qp"``: a box QP the fixed budget did not certify; ``form="riccati"``: an element
that breaks a limit).  The caller reads it once.
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from controllers._compiled import scan, tracing
from controllers._validate import all_finite
from controllers.problem import Reason
from torchlie.manifolds import SO3

__all__ = ["Spec", "step", "system_key"]


@dataclass(frozen=True)
class Spec:
    """What shapes the program besides dtypes, devices and sizes (part of its cache key)."""

    system: Any
    N: int
    form: str  # "qp" or "riccati"
    bounded: bool
    jacobians: str
    names: tuple[str, ...] | None  # the components of a ProductState point; None: a tensor point
    ndims: tuple[int, ...]  # event dims of each leaf of a point
    weights_batched: bool  # Qs (B, N+1, n, n), R (B, m, m) and a (B,) weight reason; else (N+1, n, n), (m, m)
    limits_batched: bool  # lo, hi (B, N, m); else (N, m)
    warm: bool
    qp_iters: int
    tol: float | None
    gap_tol: float | None

    def key(self, sys_key: str) -> str:
        fields = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "system"}
        return f"{sys_key}|{fields}"


def system_key(system) -> str | None:
    """A text key of a dataclass system whose fields are plain numbers, strings, 0-dim tensors or its
    manifold (by ``repr``); ``None`` otherwise (that system's solves stay eager)."""
    if not dataclasses.is_dataclass(system):
        return None
    parts = [type(system).__module__ + "." + type(system).__qualname__]
    for f in dataclasses.fields(system):
        v = getattr(system, f.name)
        if isinstance(v, (bool, int, float, str)) or v is None:
            parts.append(f"{f.name}={v!r}")
        elif isinstance(v, Tensor) and v.dim() == 0 and not v.requires_grad:
            parts.append(f"{f.name}={v.item()!r}:{v.dtype}")
        elif v is getattr(system, "manifold", None):
            parts.append(f"{f.name}={v!r}")
        else:
            return None
    return ";".join(parts)


def _point(spec: Spec, leaves):
    if spec.names is None:
        return leaves[0]
    from torchlie.manifolds import ProductState  # noqa: PLC0415

    return ProductState(dict(zip(spec.names, leaves)), dict(zip(spec.names, spec.ndims)))


def _off_manifold(spec: Spec, leaves) -> Tensor:
    """``(*B,)`` bool: some component of the point is off its manifold (the eager ``M.check`` test)."""
    from torchlie.manifolds.base import manifold_tolerance  # noqa: PLC0415

    M = spec.system.manifold
    mans = [M] if spec.names is None else [M.components[c] for c in spec.names]
    out = None
    for man, leaf in zip(mans, leaves):
        err = _rotation_error(leaf) if isinstance(man, SO3) else man._membership_error(leaf)
        bad = ~(err <= manifold_tolerance(leaf.dtype))
        out = bad if out is None else out | bad
    return out


def _rotation_error(R: Tensor) -> Tensor:
    """SO(3)'s membership error (``torchlie.manifolds.groups._rotation_error``) with the determinant by
    cofactors: ``linalg.det`` is a library call outside a built program's kernels."""
    eye = torch.eye(3, dtype=R.dtype, device=R.device)
    orth = (R.transpose(-1, -2) @ R - eye).abs().amax(dim=(-1, -2))
    det = (torch.linalg.cross(R[..., 0, :], R[..., 1, :]) * R[..., 2, :]).sum(-1)
    return torch.maximum(orth, (det - 1).abs())


def _sanitize(spec: Spec, x0l, xrl, uref):
    """The eager ``_prepare``'s stand-ins: bad elements take the first good element's reference."""
    ok = all_finite(uref, 2)
    for a, b, k in zip(x0l, xrl, spec.ndims):
        ok = ok & all_finite(a, k) & all_finite(b, k).all(-1)
    good = ok.to(torch.int32).argmax().reshape(1)
    okx = [ok.reshape(-1, *([1] * (leaf.dim() - 1))) for leaf in xrl]
    xrl = [torch.where(o, leaf, leaf.index_select(0, good)) for o, leaf in zip(okx, xrl)]
    x0l = [torch.where(o.squeeze(1), a, b[:, 0]) for o, a, b in zip(okx, x0l, xrl)]
    uref = torch.where(ok[:, None, None], uref, torch.zeros((), dtype=uref.dtype, device=uref.device))
    return x0l, xrl, uref, ok


def _bounds(lo: Tensor, hi: Tensor, uref: Tensor):
    """As ``ErrorStateMPC._bounds``: limits on δu and the limits' reason codes."""
    lo, hi = lo.expand(uref.shape), hi.expand(uref.shape)
    nan = (torch.isnan(lo) | torch.isnan(hi)).flatten(-2).any(-1)
    crossed = ((lo > hi) | (lo == torch.inf) | (hi == -torch.inf)).flatten(-2).any(-1)
    reason = torch.where(nan, int(Reason.NONFINITE_INPUT),
                         torch.where(crossed, int(Reason.INFEASIBLE_BOUNDS), 0))
    bad = (reason != 0)[:, None, None]
    lo = torch.where(bad, -torch.inf, lo)
    hi = torch.where(bad, torch.inf, hi)
    return lo - uref, hi - uref, reason


def step(spec: Spec, *args: Tensor) -> tuple[Tensor, ...]:
    """One solve (module docstring).  ``args``: the leaves of ``x0`` ``(B, *event)``, those of ``x_ref``
    ``(B, N+1, *event)``, ``u_ref (B, N, m)``, the absolute limits, ``Qs``, ``R``, [the weights' reason
    codes], [the warm start (absolute)].  Returns ``(U, dX, cost, reason, kkt, clamped, more, flags)``
    with ``more (B,)`` the elements flagged in ``flags[2]``."""
    from controllers.manifold_mpc import _REFINE_DTYPES, error_system, first_failure, time_index  # noqa: PLC0415

    k = len(spec.ndims)
    x0l, xrl = list(args[:k]), list(args[k:2 * k])
    uref, lo, hi, Qs, R = args[2 * k:2 * k + 5]
    rest = list(args[2 * k + 5:])
    wreason = rest.pop(0) if spec.weights_batched else None
    warm = rest.pop(0) if spec.warm else None
    M = spec.system.manifold
    x0l, xrl, uref, ok = _sanitize(spec, x0l, xrl, uref)
    off = _off_manifold(spec, x0l) | _off_manifold(spec, xrl).any(-1)
    lo, hi, lreason = _bounds(lo, hi, uref)
    reason0 = first_failure(torch.where(ok, 0, int(Reason.NONFINITE_INPUT)),
                            *([wreason] if wreason is not None else []), lreason)
    x_ref = _point(spec, xrl)
    es = error_system(spec.system, x_ref, uref, jacobians=spec.jacobians)
    dx0 = M.boxminus(_point(spec, x0l), time_index(M, x_ref, 0), check=False)
    dtype = uref.dtype
    if spec.form == "qp":
        data = [es.A, es.B, es.c, dx0, Qs, R, lo, hi, None if warm is None else warm - uref]
        if dtype in _REFINE_DTYPES:
            data = [None if t is None else t.to(torch.float64) for t in data]
        dU, dX, cost, reason, kkt, clamped, more = _qp(spec, *data)
    else:
        dU, dX, cost, reason, kkt, clamped = _riccati(spec, es.A, es.B, es.c, dx0, Qs, R)
        more = ((dU < lo) | (dU > hi)).flatten(-2).any(-1) if spec.bounded else torch.zeros_like(ok)
    U = uref + dU.to(dtype)
    reason = first_failure(reason0, reason)
    good = reason0 == 0
    nan = torch.full((), torch.nan, dtype=dtype, device=U.device)
    flags = torch.stack([~ok.any(), off.any(), (more & good).any()]).to(torch.int64)
    return (torch.where(good[:, None, None], U, nan), torch.where(good[:, None, None], dX.to(dtype), nan),
            torch.where(good, cost.to(dtype), nan), reason, torch.where(good, kkt.to(dtype), nan),
            clamped & good[:, None, None], more & good, flags)


def _qp(spec: Spec, A, B, c, dx0, Qs, R, lo, hi, warm):
    """The condensed form (``ErrorStateMPC._solve_lq`` with ``solver="qp"``, ``riccati_first=False``)."""
    from controllers.manifold_mpc import ErrorSystem, _condensed_qp, _plan  # noqa: PLC0415

    N, m = spec.N, B.shape[-1]
    nb = dx0.shape[0]
    Su, free_x, H, g = _condensed_qp(ErrorSystem(A, B, c), dx0, Qs, R, None, None)
    L, info = torch.linalg.cholesky_ex(H)
    dU = -torch.cholesky_solve(g.unsqueeze(-1), L).squeeze(-1)
    reason = torch.where(info == 0, 0, int(Reason.SINGULAR_QUU))
    kkt = (H @ dU.unsqueeze(-1)).squeeze(-1).add(g).norm(dim=-1)
    clamped = torch.zeros(nb, N * m, dtype=torch.bool, device=g.device)
    more = torch.zeros(nb, dtype=torch.bool, device=g.device)
    if spec.bounded:
        lo, hi = lo.reshape(nb, N * m), hi.reshape(nb, N * m)
        viol = ((dU < lo) | (dU > hi)).any(-1)
        start = dU if warm is None else warm.reshape(nb, N * m)
        ops = (H, g, lo, hi, start, viol, dU, kkt, reason)
        if tracing():  # the box QP's work only when some element breaks a limit
            dU, kkt, clamped, reason, more = torch.cond(viol.any(), functools.partial(_box, spec),
                                                        functools.partial(_no_box, spec), ops)
        else:
            dU, kkt, clamped, reason, more = (_box if bool(viol.any()) else _no_box)(spec, *ops)
    dU, dX, cost = _plan(Su, free_x, dU, Qs, R, None, None)
    return dU, dX, cost, reason, kkt, clamped.reshape(nb, N, m), more


def _no_box(spec: Spec, H, g, lo, hi, start, viol, dU, kkt, reason):
    """No element breaks a limit: the closed form stands."""
    return (dU.clone(), kkt.clone(), torch.zeros_like(dU, dtype=torch.bool), reason.clone(),
            torch.zeros_like(viol))


def _box(spec: Spec, H, g, lo, hi, start, viol, dU, kkt, reason):
    """The box QP (``ErrorStateMPC._box``) for the elements ``viol`` whose closed form breaks a limit, from
    the closed form (or the warm start): :func:`~controllers.boxqp.box_qp_fixed` and its certificate;
    ``more``: those it did not certify (the caller solves them again with :func:`~controllers.boxqp.box_qp`;
    their reason here is ``MAX_ITERATIONS``)."""
    from controllers.boxqp import box_qp_fixed  # noqa: PLC0415
    from controllers.manifold_mpc import first_failure  # noqa: PLC0415

    start = torch.nan_to_num(start, nan=0.0)
    finite = (all_finite(H, 2) & all_finite(g, 1) & all_finite(start, 1)
              & ~torch.isnan(lo).any(-1) & ~torch.isnan(hi).any(-1))
    f1 = finite.unsqueeze(-1)
    eye = torch.eye(H.shape[-1], dtype=H.dtype, device=H.device)
    x, cert, cl, res = box_qp_fixed(torch.where(f1.unsqueeze(-1), H, eye), torch.where(f1, g, 0.0),
                                    torch.where(f1, lo, -torch.inf), torch.where(f1, hi, torch.inf),
                                    torch.where(f1, start, 0.0), spec.qp_iters, tol=spec.tol,
                                    gap_tol=spec.gap_tol)
    cert = cert & finite
    v1 = viol.unsqueeze(-1)
    failed = first_failure(reason, torch.full_like(reason, int(Reason.MAX_ITERATIONS)))
    return (torch.where(v1, x, dU), torch.where(viol, res, kkt), torch.where(v1, cl, False),
            torch.where(viol & ~cert, failed, reason), viol & ~cert)


def _riccati(spec: Spec, A, B, c, dx0, Qs, R):
    """The Riccati form (``riccati.solve`` on the error system) on the augmented state ``[δx; 1]``."""
    from controllers._lq_kernels import _eliminate  # noqa: PLC0415
    from controllers.manifold_mpc import _plan_cost  # noqa: PLC0415

    nb, N, n, m = dx0.shape[0], spec.N, dx0.shape[-1], B.shape[-1]
    dt, dev = dx0.dtype, dx0.device
    k = m + n + 1
    A, B, c = A.expand(nb, N, n, n), B.expand(nb, N, n, m), c.expand(nb, N, n)
    top = torch.cat([B, A, c.unsqueeze(-1)], -1)  # (nb, N, n, k): x̃' = F [u; x̃]
    last = torch.cat([torch.zeros(nb, N, 1, k - 1, dtype=dt, device=dev),
                      torch.ones(nb, N, 1, 1, dtype=dt, device=dev)], -1)
    F = torch.cat([top, last], -2)  # (nb, N, n+1, k)
    Rb = R.expand(*Qs.shape[:-3], m, m)
    Q = Qs[..., :N, :, :]
    z, lead = torch.zeros((), dtype=dt, device=dev), Q.shape[:-2]
    C = torch.cat([torch.cat([Rb.unsqueeze(-3).expand(*lead, m, m), z.expand(*lead, m, n + 1)], -1),
                   torch.cat([z.expand(*lead, n, m), Q, z.expand(*lead, n, 1)], -1),
                   z.expand(*lead, 1, k)], -2)  # blockdiag(R, Q_k, 0)
    P = Qs[..., N, :, :]
    VT = torch.cat([torch.cat([P, z.expand(*P.shape[:-2], n, 1)], -1), z.expand(*P.shape[:-2], 1, n + 1)], -2)
    VT = VT.expand(nb, n + 1, n + 1).contiguous()
    tm = (lambda t: t.movedim(1, 0)) if C.dim() == 4 else (lambda t: t)

    def back(t, carry, xs):
        Ft, Ct = xs
        E = torch.eye(k, dtype=dt, device=dev)[:m].unsqueeze(-1)
        H = Ft.mT @ carry[0] @ Ft + Ct
        S, V, inv = _eliminate(H, E, m)
        return (V.contiguous(),), (-S, inv)

    _, (Kt, piv) = scan(back, (VT,), [F.movedim(1, 0), tm(C)], N, reverse=True)
    ok = ((piv > 0) & torch.isfinite(piv)).all(-1).all(0)  # every pivot of H_uu positive: PD
    xt0 = torch.cat([dx0, torch.ones(nb, 1, dtype=dt, device=dev)], -1)

    def fwd(t, carry, xs):
        Kk, Fk = xs
        u = (Kk @ carry[0].unsqueeze(-1)).squeeze(-1)
        nxt = (Fk @ torch.cat([u, carry[0]], -1).unsqueeze(-1)).squeeze(-1)
        return (nxt,), (u, nxt[..., :n])

    _, (us, xs_) = scan(fwd, (xt0,), [Kt, F.movedim(1, 0)], N)
    dU = us.movedim(0, 1)
    dX = torch.cat([dx0.unsqueeze(1), xs_.movedim(0, 1)], 1)
    cost = _plan_cost(dX, dU, Qs, R, None, None)
    reason = torch.where(ok, 0, int(Reason.SINGULAR_QUU))
    nan = torch.full((), torch.nan, dtype=dt, device=dev)  # riccati.solve NaNs an element it failed
    dU, dX = torch.where(ok[:, None, None], dU, nan), torch.where(ok[:, None, None], dX, nan)
    zeros = torch.zeros(nb, dtype=dt, device=dev)
    return (dU, dX, torch.where(ok, cost, nan), reason, zeros,
            torch.zeros(nb, N, m, dtype=torch.bool, device=dev))
