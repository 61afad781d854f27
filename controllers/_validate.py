"""Argument checks and shape helpers shared by the problem, dynamics and cost types (private).

Every check raises with the owner and the field named (``"LQProblem: field 'x0' must ..."``); the
per-element masks (:func:`all_finite`, :func:`psd_mask`) return booleans over the batch dims instead, so
that one bad element is reported in its status and never stops the batch.
"""

from __future__ import annotations

import torch

from torchlie._batch import broadcast_shapes


def enum_arg(cls, value, name: str, fn: str):
    """``cls(value)`` for a mode argument, with an error that names the argument and the choices."""
    try:
        return cls(value)
    except ValueError:
        choices = ", ".join(repr(m.value) for m in cls)
        raise ValueError(f"{fn}: argument '{name}' must be one of {choices} (a {cls.__name__}), "
                         f"got {value!r}") from None

def check_tensor(x, name: str, owner: str) -> torch.Tensor:
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{owner}: field '{name}' must be a torch.Tensor, got {type(x).__name__}")
    if not x.dtype.is_floating_point:
        raise TypeError(f"{owner}: field '{name}' must have a floating dtype, got {x.dtype}")
    return x


def timed(x: torch.Tensor, trailing: tuple[int | None, ...], name: str, owner: str, expected: str
           ) -> torch.Tensor:
    """Check ``x`` is ``(*B, Tx, *trailing)`` or ``(*trailing)`` (then a time dim of 1 is inserted).

    ``None`` in ``trailing`` matches any size.  Returns a tensor with an explicit time dim.
    """
    check_tensor(x, name, owner)
    k = len(trailing)

    def ok(shape: tuple[int, ...]) -> bool:
        return all(t is None or s == t for s, t in zip(shape, trailing))

    if x.dim() == k and ok(tuple(x.shape)):
        return x.unsqueeze(0)
    if x.dim() >= k + 1 and ok(tuple(x.shape[x.dim() - k:])):
        return x
    raise ValueError(f"{owner}: field '{name}' must have shape {expected}, got {tuple(x.shape)}")


def same_dtype_device(owner: str, **tensors: torch.Tensor | None) -> None:
    items = [(k, v) for k, v in tensors.items() if v is not None]
    k0, t0 = items[0]
    for k, t in items[1:]:
        if t.dtype != t0.dtype:
            raise TypeError(f"{owner}: fields '{k0}' and '{k}' have different dtypes "
                            f"({t0.dtype} vs {t.dtype}); "
                            "cast explicitly (nothing is cast silently)")
        if t.device != t0.device:
            raise ValueError(f"{owner}: fields '{k0}' and '{k}' are on different devices "
                             f"({t0.device} vs {t.device})")


def batch_dims(x: torch.Tensor, k: int) -> torch.Size:
    """Batch dims of a timed tensor with ``k`` trailing dims (time dim excluded)."""
    return x.shape[: x.dim() - k - 1]


def check_time(sizes: dict[str, int], want: int, owner: str, what: str) -> None:
    for name, s in sizes.items():
        if s not in (1, want):
            raise ValueError(f"{owner}: field '{name}' has {s} time steps, expected 1 or {want} ({what})")


def time_slice(x: torch.Tensor | None, t: int, k: int) -> torch.Tensor | None:
    """Entry ``t`` of a timed tensor with ``k`` trailing dims (a time dim of 1 broadcasts)."""
    if x is None:
        return None
    d = x.dim() - k - 1
    return x.select(d, t if x.shape[d] > 1 else 0)


def check_symmetric(M: torch.Tensor, name: str, owner: str) -> None:
    Md = M.detach()
    # one scalar per check (NaN entries are the non-finite check's business: NaN > tol is False)
    asym = float(torch.sub(Md, Md.mT).abs_().amax()) if Md.numel() else 0.0
    if not asym > 0.0:
        return
    scale = max(float(Md.abs().amax()), 1.0)
    if asym > 1e3 * torch.finfo(M.dtype).eps * scale:
        raise ValueError(f"{owner}: field '{name}' must be symmetric (max |{name} - {name}ᵀ| = "
                         f"{asym:.3g}); symmetrize it with ({name} + {name}ᵀ)/2")


def check_weight(M: torch.Tensor, name: str, owner: str, *, strict: bool, shared: bool
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """The one rule for a cost weight ``M (..., k, k)`` (``Q``: symmetric PSD, ``strict=False``; ``R``:
    symmetric PD, ``strict=True``), for every solver.

    Returns ``(finite, sound)``, bools over the leading dims: every entry finite; symmetric (up to
    ``1e3 ε`` of its largest entry, as :func:`check_symmetric`) and definite (:func:`psd_mask`).  With
    ``shared=True`` (a weight without batch dims, the same for every element) a defect is the caller's
    error: a ``ValueError`` naming the field (NaN/inf, not symmetric, not PSD/PD), checked in that order.
    A batched weight never raises: the solver reports its elements (``NONFINITE_INPUT`` where not finite,
    else ``NOT_POSITIVE_DEFINITE`` where not sound), so one bad element never stops the batch.
    """
    finite = all_finite(M, 2)
    Md = M.detach()
    safe = torch.where(finite[..., None, None], Md, torch.zeros((), dtype=Md.dtype, device=Md.device))
    asym = (safe - safe.mT).abs().flatten(-2).amax(-1) if Md.numel() else torch.zeros(finite.shape,
                                                                                        dtype=Md.dtype)
    scale = safe.abs().flatten(-2).amax(-1).clamp_min(1.0) if Md.numel() else torch.ones_like(asym)
    symmetric = asym <= 1e3 * torch.finfo(Md.dtype).eps * scale
    sound = symmetric & psd_mask(Md, strict=strict)
    if shared:
        kind = "positive definite" if strict else "positive semi-definite"
        if not bool(finite.all()):
            raise ValueError(f"{owner}: field '{name}' has NaN or inf entries (a weight shared by the batch "
                             "must be finite)")
        if not bool(symmetric.all()):
            raise ValueError(f"{owner}: field '{name}' must be symmetric (max |{name} - {name}ᵀ| = "
                             f"{float(asym.max()):.3g}); symmetrize it with ({name} + {name}ᵀ)/2")
        if not bool(sound.all()):
            raise ValueError(f"{owner}: field '{name}' must be {kind} at every time step")
    return finite, sound


def check_limit(v, name: str, owner: str, T: int, m: int, what: str = "argument", batch: tuple = ()):
    """The one rule for a control limit ``u_lower``/``u_upper`` (``name``) of a problem with horizon ``T``
    and ``m`` controls: ``None``, a real number, or a floating tensor broadcastable to ``(*B, T, m)`` (time
    dim 1 or ``T``, control dim 1 or ``m``).  A number that is NaN, or that no control satisfies
    (``u_lower = +inf``, ``u_upper = -inf``), is a ``ValueError``; tensors are checked per element by the
    solver (a NaN entry: ``NONFINITE_INPUT``; crossed or unsatisfiable: ``INFEASIBLE_BOUNDS``).  Returns a
    number as a float, anything else unchanged; ``what`` names the kind of input and ``batch`` the batch
    shape ``B`` (when known) in messages."""
    import math  # noqa: PLC0415

    if v is None:
        return None
    if isinstance(v, bool) or not isinstance(v, (int, float, torch.Tensor)):
        raise TypeError(f"{owner}: {what} '{name}' must be None, a real number or a tensor broadcastable to "
                        f"(*B, {T}, {m}), got {type(v).__name__}")
    if not isinstance(v, torch.Tensor):
        if math.isnan(v):
            raise ValueError(f"{owner}: {what} '{name}' is NaN (use ±inf or None for no limit)")
        if v == (math.inf if name == "u_lower" else -math.inf):
            raise ValueError(f"{owner}: {what} '{name}' is {v} (no control satisfies it; use {-v} or None "
                             "for no limit)")
        return float(v)
    if not v.dtype.is_floating_point:
        raise TypeError(f"{owner}: {what} '{name}' must have a floating dtype, got {v.dtype}")
    if v.dim() > 0 and (v.shape[-1] not in (1, m) or (v.dim() > 1 and v.shape[-2] not in (1, T))):
        want = (*batch, T, m) if batch else f"(*B, {T}, {m})"
        raise ValueError(f"{owner}: {what} '{name}' must broadcast to (*B, T, m) = {want} (time and control "
                         f"dims 1 or {T} and 1 or {m}), got {tuple(v.shape)}")
    return v


def all_finite(v: torch.Tensor, k: int) -> torch.Tensor:
    """``(...)`` bool over the leading dims: all of the last ``k`` dims finite.  ``max |v|`` is NaN or inf
    exactly when an entry is (amax propagates NaN), and is several times cheaper than ``isfinite().all()``."""
    v = v.detach()
    if k == 0:
        return torch.isfinite(v)
    return torch.isfinite(v.flatten(-k).abs().amax(-1)) if v.numel() else torch.ones(
        v.shape[:v.dim() - k], dtype=torch.bool, device=v.device)


def psd_mask(M: torch.Tensor, strict: bool) -> torch.Tensor:
    """``(...)`` bool over the leading dims: M ⪰ 0 (``strict``: M ≻ 0) up to a dtype tolerance.

    One batched Cholesky of ``M + δ I`` (``δ`` = a dtype tolerance times the largest diagonal entry,
    0 when ``strict``): several times cheaper than eigenvalues, and exact zeros (via-point precisions)
    pass.  Non-finite matrices are reported as definite here (they are the non-finite check's business).
    """
    Md = M.detach()
    finite = all_finite(Md, 2)
    eye = torch.eye(Md.shape[-1], dtype=Md.dtype, device=Md.device)
    if not bool(finite.all()):
        Md = torch.where(finite[..., None, None], Md, eye)
    if not strict:
        scale = Md.diagonal(dim1=-2, dim2=-1).abs().amax(-1).clamp_min(1.0)
        Md = Md + (1e2 * torch.finfo(Md.dtype).eps * Md.shape[-1] * scale)[..., None, None] * eye
    _, info = torch.linalg.cholesky_ex(Md)
    return (info == 0) | ~finite


def expand_time_dim(v: torch.Tensor | None, T: int, k: int) -> torch.Tensor | None:
    """Expand (a view) the time dim of a timed tensor with ``k`` trailing dims to ``T``."""
    if v is None:
        return None
    d = v.dim() - k - 1
    return v.expand(*v.shape[:d], T, *v.shape[d + 1:])


def time_sum(v: torch.Tensor, T: int) -> torch.Tensor:
    """Sum a per-step quantity ``(*B, Tv)`` over ``T`` steps (``Tv == 1`` broadcasts over time)."""
    return v.sum(-1) * (T if v.shape[-1] == 1 else 1)


def time_major(v: torch.Tensor | None, k: int, T: int, nb: int) -> torch.Tensor | None:
    """Batch-first timed tensor with ``k`` trailing dims -> time-major ``(T, *b, ...)`` with ``nb`` batch
    dims (singletons inserted where the tensor is shared, so batch dims stay right-aligned), expanded to
    ``T`` steps (a view)."""
    if v is None:
        return None
    d = v.dim() - k - 1
    v = v.movedim(d, 0)
    v = v.reshape(v.shape[0], *([1] * (nb - d)), *v.shape[1:])
    return v.expand(T, *v.shape[1:])


def broadcast_batch(owner: str, shapes: dict[str, torch.Size], note: str = "") -> torch.Size:
    """The broadcast of the named batch shapes, or a ``ValueError`` naming every field and its shape."""
    try:
        return broadcast_shapes(*shapes.values())
    except RuntimeError as e:
        named = ", ".join(f"{k} {tuple(v)}" for k, v in shapes.items())
        raise ValueError(f"{owner}: batch dims do not broadcast: {named}{note}") from e
