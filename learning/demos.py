"""Demonstrations for learning from demonstration (issue 26 §1; seed 004 §6, §7.3-7.7).

A :class:`Demonstrations` holds ``N`` demonstrations of equal length as batch-first tensors: what the
LQT-based movement primitives (one demo: DMP-like, §7.7; several: ProMP-like, with the mean and the
covariance per time step that minimal-intervention control uses) and inverse optimal control consume.

Time and control convention (the one of :mod:`controllers.problem` and of the seed's §7,
``x_{t+1} = A x_t + B u_t``): ``x (N, T, n)`` are states sampled every ``dt`` seconds, ``x[:, 0]`` at
time 0 and ``x[:, T-1]`` at ``(T-1) dt``; ``u (N, T-1, m)`` are the controls *between* samples,
``u[:, t]`` taking ``x[:, t]`` to ``x[:, t+1]`` (so a demo of ``T`` samples has ``T-1`` controls, as an
:class:`~controllers.ilqr.ILQRSolution` with ``x (T+1)`` and ``u (T)``; nothing is padded).
``ref (N, T, r)`` are optional per-sample references (a tracked target, a via-point signal).
``frames`` holds per-demo task data as tensors with leading dimension ``N`` (start/goal poses, a solver
status, the original length...): they follow the demos through :meth:`~Demonstrations.select`,
:meth:`~Demonstrations.split` and the variability generators.  ``meta`` is dataset-level JSON data
(its source, the list of operations applied under ``"history"``).

The ``.npz`` format (:meth:`Demonstrations.save`, :meth:`Demonstrations.load`; numpy's zip of ``.npy``
arrays, read with ``allow_pickle=False``):

==================  ============================================================================
key                 content
==================  ============================================================================
``format``          0-d unicode array ``"liecontrol.Demonstrations"``
``format_version``  0-d int64, ``1`` (a reader refuses a newer version)
``x``               ``(N, T, n)`` float32 or float64 (the dtype is kept)
``dt``              0-d float64, seconds between samples
``u``               optional, ``(N, T-1, m)``, same dtype as ``x``
``ref``             optional, ``(N, T, r)``, same dtype as ``x``
``frame/NAME``      optional, one per frame: ``(N, ...)`` bool, integer or floating
``meta_json``       0-d unicode array: ``json.dumps(meta)``
==================  ============================================================================

Any other key is an error on load (nothing is silently ignored).  Users' own arrays come in through
:meth:`Demonstrations.from_arrays` (numpy or torch, demos of different lengths time-normalized on
request), this project's per-sample behaviour-cloning demos through :meth:`Demonstrations.from_bc`.

Synthetic demos: :func:`expert_demos` (one batched iLQR solve) and :func:`mpc_demos` (closed-loop MPC)
from an expert, with the solver statuses in ``frames`` (non-converged elements are reported, dropped only
on request and then listed in ``meta["dropped"]``); human-like variability by :func:`time_warp` (a smooth
random monotone clock) and :func:`spatial_noise` (smooth low-frequency offsets); and :func:`handwriting`,
2-D handwriting-like letters generated here from a handful of spline control points each (§6.5).
"""

from __future__ import annotations

import json
import math
import re
import zipfile
import zlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from controllers import basis

__all__ = ["Demonstrations", "FORMAT", "FORMAT_VERSION", "time_warp", "spatial_noise", "expert_demos",
           "mpc_demos", "handwriting", "letter_stroke", "LETTERS"]

FORMAT = "liecontrol.Demonstrations"
FORMAT_VERSION = 1
_DTYPES = (torch.float32, torch.float64)
_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_.\-]*$")
_DT_RTOL = 1e-9


# --------------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------------


def _first_nonfinite(v: Tensor) -> tuple[int, int] | None:
    """``(demo, time step)`` of the first non-finite entry of ``v (N, T, ...)``, or ``None``."""
    bad = ~torch.isfinite(v.reshape(v.shape[0], v.shape[1], -1)).all(-1)  # (N, T)
    if not bool(bad.any()):
        return None
    i = int(torch.nonzero(bad.any(1)).flatten()[0])
    t = int(torch.nonzero(bad[i]).flatten()[0])
    return i, t


def _real_dtype(v: Tensor | np.ndarray) -> bool:
    """Whether a tensor / array holds real numbers (integers or floating; not bool, complex, str, object)."""
    if isinstance(v, Tensor):
        return v.dtype != torch.bool and not v.is_complex()
    return (v.dtype != np.bool_ and np.issubdtype(v.dtype, np.number)
            and not np.issubdtype(v.dtype, np.complexfloating))


def _real_scalar(v: Any, name: str, own: str, what: str) -> float:
    """``v`` as a Python float: a real number (int, float, numpy scalar, or a one-element real tensor /
    array); bools, strings, complex and non-numeric arrays are a TypeError naming ``name``."""
    if isinstance(v, (Tensor, np.ndarray)):
        if not _real_dtype(v):
            raise TypeError(f"{own}: '{name}' must be {what}, got an array of dtype {v.dtype}")
        if int(np.prod(v.shape)) != 1:
            raise ValueError(f"{own}: '{name}' must be a single number, got an array of shape "
                             f"{tuple(v.shape)}")
        return float(v.item())
    if isinstance(v, bool) or not isinstance(v, (int, float, np.floating, np.integer)):
        raise TypeError(f"{own}: '{name}' must be {what}, got {type(v).__name__}")
    return float(v)


def _positive_float(v: Any, name: str, own: str) -> float:
    v = _real_scalar(v, name, own, "a positive number")
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"{own}: '{name}' must be positive and finite, got {v!r}")
    return v


def _nonneg_float(v: Any, name: str, own: str) -> float:
    v = _real_scalar(v, name, own, "a non-negative number")
    if not (math.isfinite(v) and v >= 0):
        raise ValueError(f"{own}: '{name}' must be non-negative and finite, got {v!r}")
    return v


def _pos_int(v: Any, name: str, own: str, least: int = 1) -> int:
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or int(v) < least:
        raise ValueError(f"{own}: '{name}' must be an int >= {least}, got {v!r}")
    return int(v)


def _interp(y: Tensor, s_old: Tensor, s_new: Tensor) -> Tensor:
    """Piecewise-linear interpolation along time, batched: ``y (N, L, d)`` sampled at increasing phases
    ``s_old`` (``(L,)`` or ``(N, L)``), read at ``s_new`` (``(L',)`` or ``(N, L')``): ``(N, L', d)``.
    Outside ``[s_old[0], s_old[-1]]`` the end values are held (as ``numpy.interp``).  Differentiable in
    ``y`` and ``s_new``."""
    N, L, d = y.shape
    s_new = s_new.expand(N, s_new.shape[-1])
    if L == 1:
        return y.expand(N, s_new.shape[1], d)
    so = s_old.expand(N, L).contiguous()
    idx = (torch.searchsorted(so, s_new.contiguous(), right=True) - 1).clamp(0, L - 2)
    s0, s1 = so.gather(1, idx), so.gather(1, idx + 1)
    w = ((s_new - s0) / (s1 - s0)).clamp(0.0, 1.0).unsqueeze(-1)
    gi = idx.unsqueeze(-1).expand(-1, -1, d)
    y0, y1 = y.gather(1, gi), y.gather(1, gi + 1)
    return torch.lerp(y0, y1, w)  # exact at both ends of an interval (w = 0 and w = 1)


def _merge_strict(computed: dict, user: Mapping, what: str, own: str) -> dict:
    """``computed`` and the user's entries; a user entry under a computed name is a ValueError (the
    computed value is never silently replaced, nor the user's dropped)."""
    clash = sorted(set(computed) & set(user))
    if clash:
        raise ValueError(f"{own}: {what} name(s) {clash} are computed here; rename the user's {what}(s) "
                         f"(reserved: {sorted(computed)})")
    return {**computed, **user}


def _history(meta: Mapping[str, Any], entry: dict) -> dict:
    out = dict(meta)
    out["history"] = [*out.get("history", []), entry]
    return out


def _as_array(a: Any, what: str, own: str) -> Tensor:
    if isinstance(a, Tensor):
        t = a
    else:
        try:
            arr = np.asarray(a)
        except ValueError as e:  # ragged nested lists ("inhomogeneous shape")
            raise ValueError(f"{own}: {what} is not a rectangular numeric array: {e}") from None
        if arr.dtype == object or not (np.issubdtype(arr.dtype, np.number) or arr.dtype == np.bool_):
            raise TypeError(f"{own}: {what} must be a numeric array, got dtype {arr.dtype}")
        t = torch.from_numpy(np.array(arr, copy=True))
    if t.is_complex():
        raise TypeError(f"{own}: {what} must be real, got {t.dtype}")
    return t


# --------------------------------------------------------------------------------------------------
# the .npz file
# --------------------------------------------------------------------------------------------------

_NPZ_ERRORS = (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error)


def _open_npz(path: str | Path, own: str) -> np.lib.npyio.NpzFile:
    """``numpy.load(path, allow_pickle=False)`` as an open ``.npz`` archive; anything else (a plain
    ``.npy``, a broken or truncated zip, a text file) is a ValueError naming ``path``."""
    try:
        z = np.load(Path(path), allow_pickle=False)
    except FileNotFoundError:
        raise
    except _NPZ_ERRORS as e:
        raise ValueError(f"{own}: {path} is not a {FORMAT} file (not a readable .npz archive: {e})") from None
    if not isinstance(z, np.lib.npyio.NpzFile):
        raise ValueError(f"{own}: {path} is not a {FORMAT} file (a plain .npy array, not an .npz archive)")
    return z


def _npz_member(z: np.lib.npyio.NpzFile, k: str, path: str | Path, own: str) -> np.ndarray:
    """The array stored under key ``k``; an unreadable member (an object array, which needs pickle; raw
    bytes that are not an ``.npy``; a corrupt entry) is a ValueError naming ``k`` and ``path``."""
    try:
        a = z[k]
    except _NPZ_ERRORS as e:
        raise ValueError(f"{own}: key '{k}' of {path} cannot be read as a .npy array: {e}") from None
    if not isinstance(a, np.ndarray):
        raise ValueError(f"{own}: key '{k}' of {path} is not a .npy array (got {type(a).__name__})")
    return a


def _npz_scalar(z: np.lib.npyio.NpzFile, k: str, path: str | Path, own: str, what: str) -> Any:
    """Key ``k`` as a Python value: a 0-d array of ``what`` (``"integer"``: an integer dtype;
    ``"real number"``: integer or floating; ``"string"``: unicode); bool is none of them."""
    a = _npz_member(z, k, path, own)
    ok = {"integer": a.dtype != np.bool_ and np.issubdtype(a.dtype, np.integer),
          "real number": _real_dtype(a),
          "string": a.dtype.kind == "U"}[what]
    if a.shape != () or not ok:
        raise ValueError(f"{own}: key '{k}' of {path} must be a 0-d {what}, got dtype {a.dtype} and shape "
                         f"{a.shape}")
    return str(a[()]) if what == "string" else a[()].item()


def _check_npz_keys(z: np.lib.npyio.NpzFile, keys: set[str], path: str | Path, own: str) -> None:
    """The ``format`` and ``format_version`` keys, no unknown key, the required keys present."""
    fmt = _npz_member(z, "format", path, own) if "format" in keys else None
    if fmt is None or fmt.shape != () or fmt.dtype.kind != "U" or str(fmt[()]) != FORMAT:
        raise ValueError(f"{own}: {path} is not a {FORMAT} file (no or another 'format' key)")
    if "format_version" not in keys:
        raise ValueError(f"{own}: {path} has no 'format_version'")
    ver = _npz_scalar(z, "format_version", path, own, "integer")
    if ver > FORMAT_VERSION:
        raise ValueError(f"{own}: {path} has format version {ver}, written by a newer version; this "
                         f"reader knows up to {FORMAT_VERSION}")
    if ver < 1:
        raise ValueError(f"{own}: {path} has an invalid format version {ver}")
    known = {"format", "format_version", "x", "dt", "u", "ref", "meta_json"}
    unknown = sorted(k for k in keys - known if not k.startswith("frame/"))
    if unknown:
        raise ValueError(f"{own}: {path} has unknown key(s) {unknown}")
    for k in ("x", "dt", "meta_json"):
        if k not in keys:
            raise ValueError(f"{own}: {path} lacks the required key '{k}'")


# --------------------------------------------------------------------------------------------------
# the container
# --------------------------------------------------------------------------------------------------



def _ragged_inputs(states, controls, refs, dtype, device, own: str
                   ) -> tuple[list[Tensor], list[Tensor] | None, list[Tensor] | None]:
    """Users' ragged ``states (T_i, n)``, ``controls (T_i - 1, m)`` and ``refs (T_i, r)`` as tensors of one
    dtype and device, checked (shapes, dimensions, finite values; errors name the demo index)."""
    if isinstance(states, (np.ndarray, Tensor)):
        if states.ndim != 3:
            raise ValueError(f"{own}: an array of states must be (N, T, n), got shape {tuple(states.shape)}")
        states = list(states)
    if isinstance(states, (str, bytes)) or not isinstance(states, Sequence) or len(states) == 0:
        raise ValueError(f"{own}: 'states' must be a non-empty sequence of (T_i, n) arrays")
    N = len(states)
    xs = [_as_array(a, f"states[{i}]", own) for i, a in enumerate(states)]

    def seq(v, name):
        if v is None:
            return None
        if isinstance(v, (np.ndarray, Tensor)):
            v = list(v)
        if not isinstance(v, Sequence) or len(v) != N:
            raise ValueError(f"{own}: '{name}' must be a sequence of {N} arrays (one per demo), got "
                             f"{len(v) if isinstance(v, Sequence) else type(v).__name__}")
        return [_as_array(a, f"{name}[{i}]", own) for i, a in enumerate(v)]

    us, rs = seq(controls, "controls"), seq(refs, "refs")
    if dtype is None:
        dtype = xs[0].dtype
        for t in xs + (us or []) + (rs or []):
            dtype = torch.promote_types(dtype, t.dtype)
        if not dtype.is_floating_point:
            dtype = torch.float64
    if dtype not in _DTYPES:
        raise TypeError(f"{own}: 'dtype' must be float32 or float64, got {dtype} (pass dtype=)")
    device = xs[0].device if device is None else torch.device(device)
    n = None
    for i, a in enumerate(xs):
        if a.dim() != 2 or a.shape[0] < 2 or a.shape[1] < 1:
            raise ValueError(f"{own}: states[{i}] must have shape (T_i, n) with T_i >= 2, got "
                             f"{tuple(a.shape)} (a 1-D signal a is a[:, None])")
        n = a.shape[1] if n is None else n
        if a.shape[1] != n:
            raise ValueError(f"{own}: states[{i}] has dimension n = {a.shape[1]}, states[0] has {n}")
    lengths = [a.shape[0] for a in xs]
    for name, vs, off in (("controls", us, 1), ("refs", rs, 0)):
        d = None
        for i, a in enumerate(vs or []):
            if a.dim() != 2 or a.shape[0] != lengths[i] - off:
                raise ValueError(f"{own}: {name}[{i}] must have shape ({lengths[i] - off}, ·) for "
                                 f"{lengths[i]} states, got {tuple(a.shape)}"
                                 + (" (one control per transition)" if off else ""))
            d = a.shape[1] if d is None else d
            if a.shape[1] != d:
                raise ValueError(f"{own}: {name}[{i}] has dimension {a.shape[1]}, {name}[0] has {d}")
    out = []
    for name, vs in (("states", xs), ("controls", us), ("refs", rs)):
        vs = None if vs is None else [a.to(device=device, dtype=dtype) for a in vs]
        for i, a in enumerate(vs or []):
            if not bool(torch.isfinite(a).all()):
                t = int(torch.nonzero(~torch.isfinite(a).reshape(a.shape[0], -1).all(-1)).flatten()[0])
                raise ValueError(f"{own}: {name}[{i}] has a non-finite value at time step {t}")
        out.append(vs)
    return out[0], out[1], out[2]


def _per_demo_dt(dt, N: int, own: str) -> list[float]:
    """``dt`` (one positive number, or one per demo) as ``N`` floats; every entry must be a real number
    (a bool or a string is a TypeError naming ``dt`` / ``dt[i]``)."""
    if isinstance(dt, (str, bytes)):
        raise TypeError(f"{own}: 'dt' must be a positive number or one per demo, got {type(dt).__name__}")
    if isinstance(dt, (np.ndarray, Tensor)) and dt.ndim > 0 or isinstance(dt, Sequence):
        if isinstance(dt, (np.ndarray, Tensor)):
            if not _real_dtype(dt):
                raise TypeError(f"{own}: 'dt' must hold real numbers, got dtype {dt.dtype}")
            dt = dt.detach().cpu().numpy() if isinstance(dt, Tensor) else dt
            dt = [float(v) for v in dt.reshape(-1)]
        if len(dt) != N:
            raise ValueError(f"{own}: 'dt' has {len(dt)} entries for {N} demos")
        return [_positive_float(v, f"dt[{i}]", own) for i, v in enumerate(dt)]
    return [_positive_float(dt, "dt", own)] * N


def _resample_ragged(xs: list[Tensor], us: list[Tensor] | None, rs: list[Tensor] | None, T: int
                     ) -> tuple[Tensor, Tensor | None, Tensor | None]:
    """Ragged demos time-normalized to ``T`` samples each (``T - 1`` controls) by one batched linear
    interpolation on the phase ``s ∈ [0, 1]``."""
    kw = dict(dtype=xs[0].dtype, device=xs[0].device)
    lengths = [a.shape[0] for a in xs]

    def pad(vs: list[Tensor], lens: list[int]) -> tuple[Tensor, Tensor]:
        """Stack ragged ``(L_i, d)`` as ``(N, Lmax, d)`` (last sample repeated) with phases ``(N, Lmax)``
        (``L_i`` in ``[0, 1]`` then increasing beyond 1)."""
        Lm = max(max(lens), 1)
        ys, ss = [], []
        for a, L, Lt in zip(vs, lens, lengths):
            s = basis.phases(Lt, **kw)[:L]
            extra = Lm - L
            ys.append(torch.cat([a, a[-1:].expand(extra, a.shape[1])]) if extra else a)
            ss.append(torch.cat([s, 2.0 + torch.arange(extra, **kw)]) if extra else s)
        return torch.stack(ys), torch.stack(ss)

    s_new = basis.phases(T, **kw)
    x = _interp(*pad(xs, lengths), s_new)
    u = None if us is None else _interp(*pad(us, [L - 1 for L in lengths]), s_new[:-1])
    ref = None if rs is None else _interp(*pad(rs, lengths), s_new)
    return x, u, ref

@dataclass(frozen=True, eq=False)
class Demonstrations:
    """``N`` demonstrations of ``T`` samples each (module docstring for the conventions).

    Attributes:
        x: ``(N, T, n)`` states, float32 or float64, ``T >= 2``.
        dt: seconds between samples (a positive float).
        u: ``(N, T-1, m)`` controls, ``u[:, t]`` taking ``x[:, t]`` to ``x[:, t+1]``, or ``None``.
        ref: ``(N, T, r)`` per-sample references, or ``None``.
        frames: ``{name: (N, ...) tensor}`` per-demo task data (names: letters, digits, ``_.-``).
        meta: JSON-able dataset-level metadata (stored as a deep copy).

    Every field is checked here: shapes, dtype (``x``, ``u``, ``ref`` share float32/float64 and the
    device), finite values (an error names the field, the demo index and the time step).

    No copy: ``x``, ``u``, ``ref`` and the frame tensors are kept by reference (``frames`` becomes a new
    dict, ``meta`` a deep copy), so the demos stay on the autograd graph of their inputs; modifying an input
    tensor in place afterwards changes these demos and bypasses the checks (pass ``x.clone()`` to decouple).
    """

    x: Tensor
    dt: float
    u: Tensor | None = None
    ref: Tensor | None = None
    frames: Mapping[str, Tensor] = field(default_factory=dict)
    meta: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        own = "Demonstrations"
        x = self.x
        if not isinstance(x, Tensor):
            raise TypeError(f"{own}: field 'x' must be a tensor (N, T, n), got {type(x).__name__}")
        if x.dtype not in _DTYPES:
            raise TypeError(f"{own}: field 'x' must be float32 or float64, got {x.dtype}")
        if x.dim() != 3 or x.shape[0] < 1 or x.shape[1] < 2 or x.shape[2] < 1:
            raise ValueError(f"{own}: field 'x' must have shape (N, T, n) with N >= 1, T >= 2, n >= 1, "
                             f"got {tuple(x.shape)}")
        N, T, _ = x.shape
        object.__setattr__(self, "dt", _positive_float(self.dt, "dt", own))
        for name, L, what in (("u", T - 1, "(N, T-1, m)"), ("ref", T, "(N, T, r)")):
            v = getattr(self, name)
            if v is None:
                continue
            if not isinstance(v, Tensor):
                raise TypeError(f"{own}: field '{name}' must be a tensor {what} or None")
            if v.dtype != x.dtype or v.device != x.device:
                raise TypeError(f"{own}: field '{name}' has dtype {v.dtype} on {v.device}, 'x' has {x.dtype} "
                                f"on {x.device}")
            if v.dim() != 3 or v.shape[0] != N or v.shape[1] != L or v.shape[2] < 1:
                hint = ""
                if name == "u" and v.dim() == 3 and v.shape[1] == T:
                    hint = (" (one control per transition: T samples have T-1 controls; drop the last "
                            "control or append the state it leads to)")
                raise ValueError(f"{own}: field '{name}' must have shape {what} = ({N}, {L}, ·), got "
                                 f"{tuple(v.shape)}{hint}")
        for name in ("x", "u", "ref"):
            v = getattr(self, name)
            if v is not None and (bad := _first_nonfinite(v)) is not None:
                raise ValueError(f"{own}: field '{name}' has a non-finite value in demo {bad[0]} at time "
                                 f"step {bad[1]}")
        if not isinstance(self.frames, Mapping):
            raise TypeError(f"{own}: field 'frames' must be a mapping name -> tensor (N, ...)")
        frames = {}
        for k, v in self.frames.items():
            if not isinstance(k, str) or not _NAME.match(k):
                raise ValueError(f"{own}: frame name {k!r} must be a string of letters, digits and _.- "
                                 "(not starting with a digit)")
            if not isinstance(v, Tensor):
                raise TypeError(f"{own}: frame '{k}' must be a tensor (N, ...), got {type(v).__name__}")
            if v.dim() < 1 or v.shape[0] != N:
                raise ValueError(f"{own}: frame '{k}' must have leading dimension N = {N}, got "
                                 f"{tuple(v.shape)}")
            if v.device != x.device:
                raise TypeError(f"{own}: frame '{k}' is on {v.device}, 'x' on {x.device}")
            if v.is_complex():
                raise TypeError(f"{own}: frame '{k}' must be real, got {v.dtype}")
            if v.dtype.is_floating_point and v.numel() > 0:
                bad = ~torch.isfinite(v.reshape(N, -1)).all(-1)
                if bool(bad.any()):
                    raise ValueError(f"{own}: frame '{k}' has a non-finite value in demo "
                                     f"{int(torch.nonzero(bad).flatten()[0])}")
            frames[k] = v
        object.__setattr__(self, "frames", frames)
        if not isinstance(self.meta, Mapping) or not all(isinstance(k, str) for k in self.meta):
            raise TypeError(f"{own}: field 'meta' must be a mapping with string keys")
        try:
            meta = json.loads(json.dumps(dict(self.meta), allow_nan=False))
        except (TypeError, ValueError) as e:
            raise TypeError(f"{own}: field 'meta' must be JSON-serialisable (no NaN/inf): {e}") from None
        object.__setattr__(self, "meta", meta)

    # --- sizes ----------------------------------------------------------------------------------------
    def __len__(self) -> int:
        return int(self.x.shape[0])

    @property
    def N(self) -> int:
        return int(self.x.shape[0])

    @property
    def T(self) -> int:
        return int(self.x.shape[1])

    @property
    def n(self) -> int:
        return int(self.x.shape[2])

    @property
    def m(self) -> int | None:
        return None if self.u is None else int(self.u.shape[2])

    @property
    def dtype(self) -> torch.dtype:
        return self.x.dtype

    @property
    def device(self) -> torch.device:
        return self.x.device

    @property
    def duration(self) -> float:
        """``(T-1) dt`` seconds."""
        return (self.T - 1) * self.dt

    def times(self) -> Tensor:
        """``(T,)`` sample times ``t dt`` (dtype and device of ``x``)."""
        return torch.arange(self.T, dtype=self.dtype, device=self.device) * self.dt

    def _replace(self, **kw) -> Demonstrations:
        d = dict(x=self.x, dt=self.dt, u=self.u, ref=self.ref, frames=self.frames, meta=self.meta)
        d.update(kw)
        return Demonstrations(**d)

    # --- selection ------------------------------------------------------------------------------------
    def select(self, idx: int | slice | Sequence[int] | Tensor | np.ndarray) -> Demonstrations:
        """The demos ``idx`` (an int keeps a batch of one; a slice, a sequence of ints, a long or bool
        tensor / array of length ``N``), in the given order; frames follow."""
        own = "Demonstrations.select"
        N = self.N
        if isinstance(idx, slice):
            ii = torch.arange(N, device=self.device)[idx]
        else:
            if isinstance(idx, (int, np.integer)) and not isinstance(idx, bool):
                idx = [int(idx)]
            ii = torch.as_tensor(np.asarray(idx) if not isinstance(idx, Tensor) else idx, device=self.device)
            if ii.numel() == 0:
                raise ValueError(f"{own}: the selection is empty (a Demonstrations holds at least one demo)")
            if ii.dtype == torch.bool:
                if ii.shape != (N,):
                    raise ValueError(f"{own}: a boolean mask must have shape ({N},), got {tuple(ii.shape)}")
                ii = torch.nonzero(ii).flatten()
            elif ii.dtype.is_floating_point or ii.dim() != 1:
                raise TypeError(f"{own}: 'idx' must be an int, a slice, or a 1-D sequence of ints / booleans")
            ii = ii.to(torch.int64)
            if ii.numel() and (int(ii.min()) < -N or int(ii.max()) >= N):
                raise IndexError(f"{own}: index out of range for {N} demos: {ii.tolist()}")
            ii = ii % N
        if ii.numel() == 0:
            raise ValueError(f"{own}: the selection is empty (a Demonstrations holds at least one demo)")
        return self._replace(x=self.x[ii], u=None if self.u is None else self.u[ii],
                             ref=None if self.ref is None else self.ref[ii],
                             frames={k: v[ii] for k, v in self.frames.items()})

    __getitem__ = select

    def split(self, n_train: int, generator: torch.Generator | None = None) -> tuple[Demonstrations,
                                                                                      Demonstrations]:
        """``(train, test)`` of whole demos: ``n_train`` of them and the rest.  With a ``generator`` the
        demos are shuffled first (``torch.randperm``), else the first ``n_train`` are the training set."""
        N = self.N
        if isinstance(n_train, bool) or not isinstance(n_train, (int, np.integer)) or not 0 < n_train < N:
            raise ValueError(f"Demonstrations.split: 'n_train' must be an int in [1, {N - 1}], got "
                             f"{n_train!r}")
        perm = (torch.randperm(N, generator=generator, device=generator.device).to(self.device)
                if generator is not None else torch.arange(N, device=self.device))
        return self.select(perm[:n_train]), self.select(perm[n_train:])

    @staticmethod
    def cat(demos: Sequence[Demonstrations]) -> Demonstrations:
        """Concatenate along the demos: same ``T``, ``n``, ``m``, ``r``, dtype, ``dt`` (to 1e-9 relative)
        and frame names, shapes and dtypes (no promotion); ``meta`` is the first one's (plus a ``history``
        entry)."""
        own = "Demonstrations.cat"
        demos = list(demos)
        if not demos or not all(isinstance(d, Demonstrations) for d in demos):
            raise ValueError(f"{own}: expected a non-empty sequence of Demonstrations")
        d0 = demos[0]
        for i, d in enumerate(demos[1:], 1):
            for what, a, b in (("T", d.T, d0.T), ("n", d.n, d0.n), ("m", d.m, d0.m),
                               ("dtype", d.dtype, d0.dtype),
                               ("ref dim", None if d.ref is None else d.ref.shape[2],
                                None if d0.ref is None else d0.ref.shape[2]),
                               ("frames", {k: tuple(v.shape[1:]) for k, v in d.frames.items()},
                                {k: tuple(v.shape[1:]) for k, v in d0.frames.items()})):
                if a != b:
                    raise ValueError(f"{own}: item {i} has {what} {a}, item 0 has {b}")
            if abs(d.dt - d0.dt) > _DT_RTOL * d0.dt:
                raise ValueError(f"{own}: item {i} has dt {d.dt}, item 0 has {d0.dt}")
            for k, v in d.frames.items():
                if v.dtype != d0.frames[k].dtype:
                    raise TypeError(f"{own}: frame '{k}' has dtype {v.dtype} in item {i}, "
                                    f"{d0.frames[k].dtype} in item 0 (convert it first; nothing is promoted)")
        return Demonstrations(
            x=torch.cat([d.x for d in demos]), dt=d0.dt,
            u=None if d0.u is None else torch.cat([d.u for d in demos]),
            ref=None if d0.ref is None else torch.cat([d.ref for d in demos]),
            frames={k: torch.cat([d.frames[k] for d in demos]) for k in d0.frames},
            meta=_history(d0.meta, {"op": "cat", "sizes": [d.N for d in demos]}))

    def to(self, dtype: torch.dtype | None = None,
           device: torch.device | str | None = None) -> Demonstrations:
        """``x``, ``u``, ``ref`` and the floating frames in ``dtype`` (float32/float64) on ``device``."""
        if dtype is not None and dtype not in _DTYPES:
            raise TypeError(f"Demonstrations.to: 'dtype' must be float32 or float64, got {dtype}")

        def cv(v, floating=True):
            if v is None:
                return None
            return v.to(device=device, dtype=dtype if (floating and v.dtype.is_floating_point) else None)

        return self._replace(x=cv(self.x), u=cv(self.u), ref=cv(self.ref),
                             frames={k: cv(v) for k, v in self.frames.items()})

    # --- time -----------------------------------------------------------------------------------------
    def resample(self, T: int) -> Demonstrations:
        """Time-normalize to ``T`` samples by linear interpolation over the phase ``s = t / duration``
        (``numpy.interp`` on each demo); ``dt`` becomes ``duration / (T-1)`` so the duration is kept.
        Controls are interpolated at the new control times (held after the last one): an interpolation,
        not controls that reproduce the new states through the dynamics.  Frames are per demo and kept."""
        T = _pos_int(T, "T", "Demonstrations.resample", least=2)
        kw = dict(dtype=self.dtype, device=self.device)
        s_old, s_new = basis.phases(self.T, **kw), basis.phases(T, **kw)
        u = None if self.u is None else _interp(self.u, s_old[:-1], s_new[:-1])
        ref = None if self.ref is None else _interp(self.ref, s_old, s_new)
        return self._replace(x=_interp(self.x, s_old, s_new), u=u, ref=ref, dt=self.duration / (T - 1),
                             meta=_history(self.meta, {"op": "resample", "from": self.T, "to": T}))

    def velocities(self) -> Tensor:
        """``(N, T, n)`` finite-difference velocities of ``x``: central differences inside, one-sided at
        the ends (``numpy.gradient(x, dt, axis=1)``)."""
        return torch.gradient(self.x, spacing=self.dt, dim=1)[0]

    def accelerations(self) -> Tensor:
        """``(N, T, n)``: :meth:`velocities` differentiated once more the same way."""
        return torch.gradient(self.velocities(), spacing=self.dt, dim=1)[0]

    # --- statistics over the demos (ProMP-like encodings, §7.7 minimal intervention) -----------------
    def _field(self, name: str, own: str) -> Tensor:
        if name not in ("x", "u", "ref"):
            raise ValueError(f"{own}: 'field' must be 'x', 'u' or 'ref', got {name!r}")
        v = getattr(self, name)
        if v is None:
            raise ValueError(f"{own}: these demonstrations have no '{name}'")
        return v

    def mean(self, field: str = "x") -> Tensor:
        """``(T, n)`` (``(T-1, m)`` for ``u``) mean over the demos at each time step."""
        return self._field(field, "Demonstrations.mean").mean(0)

    def covariance(self, field: str = "x", ddof: int = 1) -> Tensor:
        """``(T, n, n)`` covariance over the demos at each time step, ``Σ_t = Σ_i (x_it - μ_t)(x_it - μ_t)ᵀ /
        (N - ddof)`` (``ddof=1``: unbiased, ``numpy.cov``'s default; ``ddof=0``: maximum likelihood)."""
        own = "Demonstrations.covariance"
        v = self._field(field, own)
        if isinstance(ddof, bool) or not isinstance(ddof, int) or ddof < 0:
            raise ValueError(f"{own}: 'ddof' must be a non-negative int, got {ddof!r}")
        if self.N - ddof <= 0:
            raise ValueError(f"{own}: {self.N} demo(s) with ddof={ddof}: need N > ddof")
        c = v - v.mean(0)
        return torch.einsum("nti,ntj->tij", c, c) / (self.N - ddof)

    # --- files ----------------------------------------------------------------------------------------
    def save(self, path: str | Path, *, compress: bool = False) -> None:
        """Write the ``.npz`` file of the module docstring at exactly ``path`` (no extension added)."""
        own = "Demonstrations.save"

        def arr(v: Tensor, what: str) -> np.ndarray:
            try:
                return v.detach().cpu().contiguous().numpy()
            except TypeError as e:
                raise TypeError(f"{own}: {what} of dtype {v.dtype} cannot be stored in .npz: {e}") from None

        out: dict[str, np.ndarray] = {"format": np.array(FORMAT), "format_version": np.array(FORMAT_VERSION,
                                                                                          dtype=np.int64),
                                      "x": arr(self.x, "x"), "dt": np.array(self.dt, dtype=np.float64),
                                      "meta_json": np.array(json.dumps(self.meta, allow_nan=False))}
        if self.u is not None:
            out["u"] = arr(self.u, "u")
        if self.ref is not None:
            out["ref"] = arr(self.ref, "ref")
        for k, v in self.frames.items():
            out[f"frame/{k}"] = arr(v, f"frame '{k}'")
        with open(Path(path), "wb") as f:
            (np.savez_compressed if compress else np.savez)(f, **out)

    @classmethod
    def load(cls, path: str | Path) -> Demonstrations:
        """Read a file written by :meth:`save` (``allow_pickle=False``) and validate it.

        A file that is not an ``.npz`` of this format (a plain ``.npy``, a broken zip, another ``format``),
        a member that is not a numeric ``.npy`` array (an object array, raw bytes), a malformed ``dt`` /
        ``format_version`` / ``meta_json`` or an unknown key is a ValueError naming the key and ``path``."""
        own = "Demonstrations.load"
        with _open_npz(path, own) as z:
            keys = set(z.files)
            _check_npz_keys(z, keys, path, own)

            def tens(k: str) -> Tensor:
                a = _npz_member(z, k, path, own)
                if not (_real_dtype(a) or a.dtype == np.bool_):
                    raise ValueError(f"{own}: key '{k}' of {path} has non-numeric dtype {a.dtype}")
                return torch.from_numpy(np.array(a, copy=True))

            x = tens("x")
            u = tens("u") if "u" in keys else None
            ref = tens("ref") if "ref" in keys else None
            frames = {k[len("frame/"):]: tens(k) for k in sorted(keys) if k.startswith("frame/")}
            dt = _npz_scalar(z, "dt", path, own, "real number")
            try:
                meta = json.loads(_npz_scalar(z, "meta_json", path, own, "string"))
            except ValueError as e:
                raise ValueError(f"{own}: key 'meta_json' of {path} is not JSON: {e}") from None
        try:
            return cls(x=x, dt=dt, u=u, ref=ref, frames=frames, meta=meta)
        except (TypeError, ValueError) as e:
            raise type(e)(f"{own}: {path}: {e}") from None

    # --- users' own data ------------------------------------------------------------------------------
    @classmethod
    def from_arrays(cls, states: Sequence[Any] | np.ndarray | Tensor, controls: Sequence[Any] | None = None,
                    *, dt: float | Sequence[float], refs: Sequence[Any] | None = None,
                    resample: int | None = None, frames: Mapping[str, Any] | None = None,
                    meta: Mapping[str, Any] | None = None, dtype: torch.dtype | None = None,
                    device: torch.device | str | None = None) -> Demonstrations:
        """Demonstrations from users' arrays (numpy, torch or nested lists).

        Args:
            states: a sequence of ``(T_i, n)`` arrays (or one ``(N, T, n)`` array).
            controls: ``None`` or a sequence of ``(T_i - 1, m)`` arrays (one control per transition).
            dt: one time step for all, or one per demo; without resampling they must agree (to 1e-9
                relative).
            refs: ``None`` or a sequence of ``(T_i, r)`` arrays.
            resample: ``None``: every demo must have the same length; an int ``T``: each demo is
                time-normalized to ``T`` samples (as :meth:`resample`), the common ``dt`` is the mean
                duration over ``T-1``, and each demo's own ``duration`` (seconds) and ``length`` (samples)
                are kept as frames (a user frame of either name is then an error, never replaced).
            frames: per-demo arrays with leading dimension ``N``.
            dtype: float32/float64; default the promoted dtype of the inputs (integers: float64).

        Errors name the first offending demo index: a different length (without ``resample``), state
        dimension, control/reference shape or time step, a non-finite value.
        """
        own = "Demonstrations.from_arrays"
        xs, us, rs = _ragged_inputs(states, controls, refs, dtype, device, own)
        N, lengths = len(xs), [a.shape[0] for a in xs]
        dts = _per_demo_dt(dt, N, own)
        dtype, device = xs[0].dtype, xs[0].device
        user_frames = {} if frames is None else {k: _as_array(v, f"frame '{k}'", own).to(device)
                                                 for k, v in frames.items()}
        user_frames = {k: (v.to(dtype) if v.dtype.is_floating_point else v) for k, v in user_frames.items()}
        meta = dict(meta or {})
        if resample is None:
            for i, L in enumerate(lengths):
                if L != lengths[0]:
                    raise ValueError(f"{own}: demo {i} has {L} samples, demo 0 has {lengths[0]}; pass "
                                     "resample=T to time-normalize demos of different lengths")
            for i, v in enumerate(dts):
                if abs(v - dts[0]) > _DT_RTOL * dts[0]:
                    raise ValueError(f"{own}: demo {i} has dt {v}, demo 0 has {dts[0]}; pass resample=T to "
                                     "time-normalize demos with different time steps")
            return cls(x=torch.stack(xs), dt=dts[0], u=None if us is None else torch.stack(us),
                       ref=None if rs is None else torch.stack(rs), frames=user_frames, meta=meta)
        T = _pos_int(resample, "resample", own, least=2)
        x, u, ref = _resample_ragged(xs, us, rs, T)
        durations = [(L - 1) * d for L, d in zip(lengths, dts)]
        user_frames = _merge_strict({"duration": torch.tensor(durations, dtype=dtype, device=device),
                                     "length": torch.tensor(lengths, dtype=torch.int64, device=device)},
                                    user_frames, "frame", own)
        meta = _history(meta, {"op": "resample", "to": T})
        return cls(x=x, dt=sum(durations) / N / (T - 1), u=u, ref=ref, frames=user_frames, meta=meta)

    @classmethod
    def from_bc(cls, demos: Any, dt: float | None = None, *, physical: bool = True) -> Demonstrations:
        """Trajectories from this project's per-sample :class:`learning.bc.Demos` (one demo per episode).

        Every episode must have the same number ``L >= 2`` of samples with steps ``0 .. L-1`` (else an
        error names the episode).  ``x (E, L, n)`` are the env states; the action at step ``t`` takes
        ``x_t`` to ``x_{t+1}``, so ``u (E, L-1, m)`` are the first ``L-1`` actions and the last one (whose
        next state is not recorded) is the frame ``"u_last" (E, m)``; nothing is dropped: also the frames
        ``"obs" (E, L, obs_dim)``, ``"seed"``, ``"return"``, ``"success"`` per episode.  ``physical``:
        controls ``u = action · u_max`` of the task (else the normalized actions in ``[-1, 1]``).
        ``dt``: the task system's by default.
        """
        own = "Demonstrations.from_bc"
        for a in ("obs", "action", "state", "episode", "step", "seeds", "returns", "success", "task"):
            if not hasattr(demos, a):
                raise TypeError(f"{own}: expected a learning.bc.Demos, got {type(demos).__name__} "
                                f"(no attribute '{a}')")
        E = int(demos.seeds.shape[0])
        if E < 1 or demos.obs.shape[0] == 0:
            raise ValueError(f"{own}: the demos are empty")
        ep, st = demos.episode.to(torch.int64), demos.step.to(torch.int64)
        counts = torch.bincount(ep, minlength=E)
        L = int(counts[0])
        bad = torch.nonzero(counts != L).flatten()
        if bad.numel():
            e = int(bad[0])
            raise ValueError(f"{own}: episode {e} has {int(counts[e])} samples, episode 0 has {L}; "
                             "trajectories must have equal lengths (select episodes of one length)")
        if L < 2:
            raise ValueError(f"{own}: episodes have {L} sample(s); at least 2 are needed")
        order = torch.argsort(ep * (int(st.max()) + 1) + st, stable=True)
        steps = st[order].reshape(E, L)
        ok = (steps == torch.arange(L, device=steps.device)).all(1)
        if not bool(ok.all()):
            e = int(torch.nonzero(~ok).flatten()[0])
            raise ValueError(f"{own}: episode {e} has steps {steps[e].tolist()[:10]}..., expected 0..{L - 1}")
        x = demos.state[order].reshape(E, L, -1)
        a = demos.action[order].reshape(E, L, -1).to(x.dtype)
        meta: dict[str, Any] = {"source": "learning.bc.Demos", "task": str(demos.task)}
        task = None
        if physical or dt is None:
            if not demos.task:
                raise ValueError(f"{own}: the demos name no task; pass dt= and physical=False")
            from learning.envs.single import make_task

            task = make_task(str(demos.task))
        if physical:
            a = a * task.u_scale(a.dtype, a.device)
            meta["controls"] = "physical"
        else:
            meta["controls"] = "normalized action in [-1, 1]"
        if task is not None:
            meta["u_max"] = [float(v) for v in task.u_max()]
        if dt is None:
            dt = task.system.dt
        frames = {"obs": demos.obs[order].reshape(E, L, -1).to(x.dtype), "u_last": a[:, -1],
                  "seed": demos.seeds, "return": demos.returns.to(x.dtype), "success": demos.success}
        return cls(x=x, dt=dt, u=a[:, :-1].contiguous(), frames=frames, meta=meta)


# --------------------------------------------------------------------------------------------------
# human-like variability
# --------------------------------------------------------------------------------------------------


def _check_demos(d: Any, own: str) -> Demonstrations:
    if not isinstance(d, Demonstrations):
        raise TypeError(f"{own}: 'demos' must be a Demonstrations, got {type(d).__name__}")
    return d


def _randn(shape, generator: torch.Generator, like: Tensor, own: str) -> Tensor:
    if not isinstance(generator, torch.Generator):
        raise TypeError(f"{own}: 'generator' must be a torch.Generator (explicit randomness)")
    z = torch.randn(*shape, generator=generator, dtype=torch.float64, device=generator.device)
    return z.to(device=like.device, dtype=like.dtype)


def time_warp(demos: Demonstrations, strength: float, generator: torch.Generator, *, n_basis: int = 4,
              return_phase: bool = False) -> Demonstrations | tuple[Demonstrations, Tensor]:
    """A random smooth monotone time warp per demo (human-like timing variability), endpoints fixed.

    Each demo gets a warped clock ``τ(s) = ∫_0^s e^{g} / ∫_0^1 e^{g}`` on the phase ``s ∈ [0, 1]``, with a
    log-rate ``g(s) = Σ_k w_k φ_k(s)`` on ``n_basis`` Gaussian RBFs (seed Eq. 25,
    :func:`controllers.basis.rbf`), ``w_k ~ N(0, strength²)``: the local speed varies by factors around
    ``e^{±strength}``, ``τ(0) = 0``, ``τ(1) = 1`` (the integral by the trapezoidal rule on the ``T``
    samples).  The rate is scale-free (``τ`` is normalized), so it is computed as ``e^{g - max g}``: no
    overflow at any strength.  ``τ`` is strictly increasing in exact arithmetic and for moderate strengths;
    at very large strengths (rate ratios beyond the floating-point range, strength of order 50 or more)
    some steps round to zero and ``τ`` is only non-decreasing.  ``strength = 0`` is exactly the identity
    (``τ`` = the uniform phases, the demos returned unchanged up to the history entry; the generator is
    advanced as for any strength).
    The new sample ``t`` is the old trajectory read at ``τ(s_t)`` (linear interpolation); ``u`` (read at
    the control times) and ``ref`` are warped alike, ``T``, ``dt`` and the frames are kept.  Warped controls
    are an interpolation, not controls that reproduce the new states through the dynamics.

    Returns the warped demos, and with ``return_phase`` also ``τ (N, T)`` (the original phase of each new
    sample).
    """
    own = "time_warp"
    d = _check_demos(demos, own)
    strength = _nonneg_float(strength, "strength", own)
    K = _pos_int(n_basis, "n_basis", own)
    kw = dict(dtype=d.dtype, device=d.device)
    s = basis.phases(d.T, **kw)
    w = _randn((d.N, K), generator, d.x, own) * strength
    g = w @ basis.rbf(s, K).T  # (N, T)
    if strength == 0.0:
        tau = s.expand(d.N, d.T).clone()  # exactly the identity (a normalized cumsum is off by ulps)
    else:
        rate = torch.exp(g - g.max(dim=1, keepdim=True).values)  # in (0, 1]: no overflow
        inc = 0.5 * (rate[:, 1:] + rate[:, :-1])
        c = torch.cat([torch.zeros(d.N, 1, **kw), torch.cumsum(inc, 1)], 1)
        tau = c / c[:, -1:]
        tau = torch.cat([torch.zeros(d.N, 1, **kw), tau[:, 1:-1], torch.ones(d.N, 1, **kw)], 1)
    out = d._replace(x=_interp(d.x, s, tau),
                     u=None if d.u is None else _interp(d.u, s[:-1], tau[:, :-1]),
                     ref=None if d.ref is None else _interp(d.ref, s, tau),
                     meta=_history(d.meta, {"op": "time_warp", "strength": strength, "n_basis": K}))
    return (out, tau) if return_phase else out


def _check_dims(dims: Any, n: int, own: str) -> list[int]:
    """``dims`` (``None``: all ``n``) as distinct ints in ``[0, n)``; a float or bool entry is an error."""
    if dims is None:
        return list(range(n))
    if isinstance(dims, (str, bytes)) or not isinstance(dims, (Sequence, np.ndarray, Tensor)):
        raise TypeError(f"{own}: 'dims' must be a sequence of state indices, got {type(dims).__name__}")
    dims = list(dims.tolist() if isinstance(dims, (np.ndarray, Tensor)) else dims)
    for j in dims:
        if isinstance(j, (bool, np.bool_)) or not isinstance(j, (int, np.integer)):
            raise TypeError(f"{own}: 'dims' must hold ints (state indices), got {j!r} in {dims}")
    dims = [int(j) for j in dims]
    if not dims or len(set(dims)) != len(dims) or not all(0 <= j < n for j in dims):
        raise ValueError(f"{own}: 'dims' must be distinct state indices in [0, {n}), got {dims}")
    return dims


def _scale_vector(scale: Any, k: int, kw: dict, own: str) -> tuple[Tensor, Any]:
    """``scale`` as ``(k,)`` non-negative finite values (dtype/device ``kw``) and its JSON record: a real
    scalar (Python/numpy number, 0-d tensor/array) is repeated, else ``k`` values (one per dim).  A tensor
    keeps its autograd graph."""
    if isinstance(scale, (bool, np.bool_, str, bytes)):
        raise TypeError(f"{own}: 'scale' must be a non-negative number or {k} of them, got {scale!r}")
    if isinstance(scale, (int, float, np.integer, np.floating)):
        return torch.full((k,), _nonneg_float(scale, "scale", own), **kw), float(scale)
    if isinstance(scale, (np.ndarray, Tensor)) and not _real_dtype(scale):
        raise TypeError(f"{own}: 'scale' must hold real numbers, got dtype {scale.dtype}")
    try:
        sc = torch.as_tensor(scale, **kw).reshape(-1)
    except (TypeError, ValueError, RuntimeError) as e:
        raise TypeError(f"{own}: 'scale' must be a non-negative number or {k} of them: {e}") from None
    if sc.numel() == 1 and (isinstance(scale, (np.ndarray, Tensor)) and scale.ndim == 0):
        sc = sc.expand(k)
    if sc.numel() != k or not bool((torch.isfinite(sc) & (sc >= 0)).all()):
        raise ValueError(f"{own}: 'scale' must be a non-negative float or {k} of them (one per dim)")
    rec = float(sc[0]) if isinstance(scale, (np.ndarray, Tensor)) and scale.ndim == 0 else sc.tolist()
    return sc, rec


def spatial_noise(demos: Demonstrations, scale: float | Sequence[float] | Tensor,
                  generator: torch.Generator, *, n_basis: int = 5, pin_ends: bool = True,
                  dims: Sequence[int] | None = None) -> Demonstrations:
    """Smooth random offsets of the states (human-like spatial variability).

    Per demo and per state dimension ``j`` in ``dims`` (all by default), the offset is
    ``ε(s) = scale_j · e(s) · Σ_k w_k φ_k(s) / ‖φ(s)‖`` with ``n_basis`` Gaussian RBFs ``φ`` (Eq. 25) and
    ``w_k ~ N(0, 1)``: a low-frequency signal whose pointwise standard deviation is exactly
    ``scale_j · e(s)``, with the envelope ``e(s) = sin(π s)`` when ``pin_ends`` (start and end unchanged,
    ``scale`` reached at mid-movement) or ``e = 1``.  Fewer basis functions give smoother offsets.  ``u``,
    ``ref``, ``dt`` and the frames are kept (offset states no longer match the controls through the
    dynamics).
    """
    own = "spatial_noise"
    d = _check_demos(demos, own)
    K = _pos_int(n_basis, "n_basis", own)
    dims = _check_dims(dims, d.n, own)
    kw = dict(dtype=d.dtype, device=d.device)
    sc, rec = _scale_vector(scale, len(dims), kw, own)
    s = basis.phases(d.T, **kw)
    phi = basis.rbf(s, K)
    phi = phi / phi.norm(dim=-1, keepdim=True)  # (T, K), unit rows
    w = _randn((d.N, K, len(dims)), generator, d.x, own)
    eps = torch.einsum("tk,nkd->ntd", phi, w) * sc
    if pin_ends:
        env = torch.sin(math.pi * s)
        env = torch.cat([env.new_zeros(1), env[1:-1], env.new_zeros(1)])  # exactly 0 at both ends
        eps = eps * env[:, None]
    off = torch.zeros(d.N, d.T, d.n, **kw)
    off[..., dims] = eps
    return d._replace(x=d.x + off, meta=_history(d.meta, {"op": "spatial_noise", "scale": rec, "n_basis": K,
                                                          "pin_ends": bool(pin_ends), "dims": dims}))


# --------------------------------------------------------------------------------------------------
# experts
# --------------------------------------------------------------------------------------------------


_KEEP = ("all", "finite", "converged")


def _dt_of(system: Any, dt: Any, own: str) -> float:
    if dt is None:
        dt = getattr(system, "dt", None)
        if dt is None:
            raise ValueError(f"{own}: the system has no 'dt' attribute; pass dt=")
    return _positive_float(dt, "dt", own)


def _finish(own: str, x: Tensor, u: Tensor, dt: float, ok_finite: Tensor, converged: Tensor, reason_names,
            frames: dict[str, Tensor], keep: str, meta: dict) -> Demonstrations:
    """Keep / drop elements per ``keep`` and build the demos; ``frames`` already flat ``(N, ...)`` (with
    ``"index"``); ``meta["dropped"]`` is filled here."""
    N = x.shape[0]
    if keep == "all":
        keep_mask = ok_finite
        if not bool(ok_finite.all()):
            i = int(torch.nonzero(~ok_finite).flatten()[0])
            raise ValueError(f"{own}: element {i} ({reason_names[i]}) has a non-finite trajectory; pass "
                             "keep='finite' or keep='converged' to drop such elements (listed in "
                             "meta['dropped'])")
    else:
        keep_mask = ok_finite & converged if keep == "converged" else ok_finite
    drop = torch.nonzero(~keep_mask).flatten().tolist()
    meta["dropped"] = {"count": len(drop), "index": drop, "reason": [reason_names[i] for i in drop],
                       "rule": keep}
    if len(drop) == N:
        raise ValueError(f"{own}: keep={keep!r} drops all {N} elements (reasons: "
                         f"{sorted(set(reason_names))})")
    kept = torch.nonzero(keep_mask).flatten()
    return Demonstrations(x=x[kept], dt=dt, u=u[kept], frames={k: v[kept] for k, v in frames.items()},
                          meta=meta)


def _flat_frames(frames: Mapping[str, Any] | None, bs: torch.Size, N: int, device,
                 own: str) -> dict[str, Tensor]:
    out = {}
    for k, v in (frames or {}).items():
        t = _as_array(v, f"frame '{k}'", own).to(device)
        if tuple(t.shape[:len(bs)]) != tuple(bs):
            raise ValueError(f"{own}: frame '{k}' must have leading dims {tuple(bs)} (the batch), got "
                             f"{tuple(t.shape)}")
        out[k] = t.reshape(N, *t.shape[len(bs):])
    return out


def _expert_records(sol: Any, problem: Any, method: Any, frames: Mapping[str, Any] | None,
                    meta: Mapping[str, Any] | None, own: str):
    """From an iLQR solution: flat ``x (N, T+1, n)``, ``u (N, T, m)``, the finite mask, the reason names,
    the frames and the meta of :func:`expert_demos` (the user's merged, clashes refused)."""
    from controllers.problem import Reason

    bs = sol.x.shape[:-2]
    N = int(math.prod(bs))
    x = sol.x.reshape(N, problem.T + 1, problem.n)
    u = sol.u.reshape(N, problem.T, problem.m)
    reason = sol.status.reason.reshape(N)
    names = [Reason(int(c)).name for c in reason.tolist()]
    ok = torch.isfinite(x).flatten(1).all(1) & torch.isfinite(u).flatten(1).all(1)
    zero = torch.zeros((), dtype=x.dtype, device=x.device)
    fr = _merge_strict({"index": torch.arange(N, device=x.device),
                        "converged": sol.status.converged.reshape(N), "reason": reason,
                        "iterations": sol.status.iterations.reshape(N),
                        "cost": torch.where(ok, sol.cost.reshape(N), zero).detach(),
                        "kkt_residual": torch.where(ok, sol.kkt_residual.reshape(N), zero).detach()},
                       _flat_frames(frames, bs, N, x.device, own), "frame", own)
    md = _merge_strict({"source": "expert_demos", "solver": "ilqr",
                        "method": str(getattr(method, "value", method)), "batch_shape": list(bs),
                        "reasons": {str(int(r)): r.name for r in Reason},
                        "converged": int(sol.status.converged.sum()), "total": N, "dropped": None},
                       dict(meta or {}), "meta key", own)
    return x, u, ok, names, fr, md


def expert_demos(problem: Any, u_init: Tensor | None = None, *, dt: float | None = None, options: Any = None,
                 method: str = "recursive", keep: str = "all", frames: Mapping[str, Any] | None = None,
                 meta: Mapping[str, Any] | None = None) -> Demonstrations:
    """Demonstrations from an iLQR expert: one batched :func:`controllers.ilqr.ilqr` solve of ``problem``
    (an :class:`~controllers.ilqr.ILQRProblem` with batched start states ``x0 (*B, n)``).

    No gradients: the solve runs with ``grad="none"`` and the demos are detached data even when the problem's
    tensors require grad (as :func:`mpc_demos`); differentiate the solver itself
    (:func:`controllers.ilqr.ilqr` with ``grad=``) where a gradient is wanted.

    The ``prod(B)`` solutions (flattened row-major) become demos ``x (N, T+1, n)``, ``u (N, T, m)`` with
    ``dt`` from the system's ``dt`` attribute (or the argument).  Frames: ``"index"`` (the element's
    flat batch index), ``"converged"`` (bool, the solver's certified status), ``"reason"`` (int64
    :class:`~controllers.problem.Reason` codes, their names in ``meta["reasons"]``), ``"iterations"``,
    ``"cost"``, ``"kkt_residual"``, plus the user's ``frames`` (leading dims ``B``).  ``keep``:
    ``"all"`` keeps every element (non-converged ones are flagged; a non-finite trajectory is an error
    naming the element), ``"finite"`` drops non-finite ones, ``"converged"`` keeps only converged ones;
    what is dropped is listed in ``meta["dropped"]`` (count, indices, reasons).  A user frame or ``meta``
    key under one of the computed names above (or ``"dropped"``, ``"source"``...) is a ValueError, never
    silently overridden.
    """
    from controllers.ilqr import ILQRProblem, ilqr

    own = "expert_demos"
    if not isinstance(problem, ILQRProblem):
        raise TypeError(f"{own}: 'problem' must be a controllers.ilqr.ILQRProblem, got "
                        f"{type(problem).__name__}")
    if keep not in _KEEP:
        raise ValueError(f"{own}: 'keep' must be one of {_KEEP}, got {keep!r}")
    if problem.dtype not in _DTYPES:
        raise TypeError(f"{own}: the problem's dtype must be float32 or float64, got {problem.dtype}")
    dt = _dt_of(problem.dynamics, dt, own)
    sol = ilqr(problem, u_init, method=method, grad="none", options=options)
    x, u, ok, names, fr, md = _expert_records(sol, problem, method, frames, meta, own)
    return _finish(own, x.detach(), u.detach(), dt, ok, fr["converged"], names, fr, keep, md)


def mpc_demos(system: Any, cost: Any, x0: Tensor, horizon: int, steps: int, *, dt: float | None = None,
              u_lower=None, u_upper=None, simulator: Any = None, options: Any = None, keep: str = "all",
              frames: Mapping[str, Any] | None = None,
              meta: Mapping[str, Any] | None = None) -> Demonstrations:
    """Demonstrations from a closed-loop MPC expert (:func:`controllers.mpc.run_mpc`, batched over the
    start states ``x0 (*B, n)``): ``x (N, steps+1, n)``, ``u (N, steps, m)``.  Frames: ``"index"``,
    ``"converged"`` (every solve along the demo converged), ``"converged_steps" (N, steps)``,
    ``"iterations" (N, steps)`` and the user's; ``keep`` as in :func:`expert_demos` (``"converged"``:
    demos whose every solve converged).  A user frame or ``meta`` key under a computed name is a ValueError.

    No gradients: :func:`~controllers.mpc.run_mpc` runs without a graph and the demos are detached data even
    when ``x0`` or the cost's tensors require grad (as :func:`expert_demos`)."""
    from controllers.mpc import run_mpc

    own = "mpc_demos"
    if keep not in _KEEP:
        raise ValueError(f"{own}: 'keep' must be one of {_KEEP}, got {keep!r}")
    if not isinstance(x0, Tensor) or x0.dtype not in _DTYPES or x0.dim() < 1:
        raise TypeError(f"{own}: 'x0' must be a float32/float64 tensor (*B, n)")
    steps = _pos_int(steps, "steps", own)
    dt = _dt_of(system, dt, own)
    ro = run_mpc(system, cost, x0, horizon, steps, u_lower=u_lower, u_upper=u_upper, simulator=simulator,
                 options=options)
    bs = ro.x.shape[:-2]
    N = int(math.prod(bs))
    x = ro.x.reshape(N, steps + 1, -1)
    u = ro.u.reshape(N, steps, -1)
    conv_steps = ro.converged.reshape(N, steps)
    conv = conv_steps.all(1)
    ok = torch.isfinite(x).flatten(1).all(1) & torch.isfinite(u).flatten(1).all(1)
    names = ["CONVERGED" if c else ("NONFINITE" if not f else "NOT_CONVERGED")
             for c, f in zip(conv.tolist(), ok.tolist())]
    fr = _merge_strict({"index": torch.arange(N, device=x.device), "converged": conv,
                        "converged_steps": conv_steps, "iterations": ro.iterations.reshape(N, steps)},
                       _flat_frames(frames, bs, N, x.device, own), "frame", own)
    md = _merge_strict({"source": "mpc_demos", "solver": "mpc (ilqr)", "horizon": int(horizon),
                        "batch_shape": list(bs), "converged": int(conv.sum()), "total": N, "dropped": None},
                       dict(meta or {}), "meta key", own)
    return _finish(own, x.detach(), u.detach(), dt, ok, conv, names, fr, keep, md)


# --------------------------------------------------------------------------------------------------
# handwriting-like letters (generated here)
# --------------------------------------------------------------------------------------------------

# Each letter: the free weights v of a C¹ spline of cubic Bézier segments (§6.5, Eq. 45-46) in a unit box:
# the first 4 rows are the first segment's control points, then 2 per further segment (its second inner
# control point and its end point; the first inner one mirrors the previous inner point about the joint).
# A segment whose inner point equals its end point ends at rest, so a corner is a cusp (as pen strokes turn).
_LETTERS: dict[str, list[tuple[float, float]]] = {
    "S": [(0.80, 0.85), (0.60, 1.02), (0.18, 1.00), (0.20, 0.75),
          (0.80, 0.55), (0.80, 0.30),
          (0.35, -0.02), (0.15, 0.15)],
    "C": [(0.85, 0.80), (0.70, 1.02), (0.18, 1.00), (0.15, 0.50),
          (0.70, -0.02), (0.85, 0.20)],
    "U": [(0.15, 1.00), (0.15, 0.50), (0.15, 0.00), (0.50, 0.00),
          (0.85, 0.50), (0.85, 1.00)],
    "N": [(0.15, 0.00), (0.15, 0.50), (0.15, 1.00), (0.15, 1.00),
          (0.85, 0.00), (0.85, 0.00),
          (0.85, 1.00), (0.85, 1.00)],
    "Z": [(0.15, 1.00), (0.50, 1.00), (0.85, 1.00), (0.85, 1.00),
          (0.15, 0.00), (0.15, 0.00),
          (0.85, 0.00), (0.85, 0.00)],
    "W": [(0.05, 1.00), (0.15, 0.50), (0.30, 0.00), (0.30, 0.00),
          (0.50, 0.70), (0.50, 0.70),
          (0.70, 0.00), (0.70, 0.00),
          (0.95, 1.00), (0.95, 1.00)],
}
#: the letters :func:`handwriting` knows
LETTERS = "".join(_LETTERS)


def _letter_points(letter: str, own: str) -> list[tuple[float, float]]:
    if not isinstance(letter, str) or letter.upper() not in _LETTERS:
        raise ValueError(f"{own}: unknown letter {letter!r}; known: {LETTERS!r}")
    return _LETTERS[letter.upper()]


def letter_stroke(letter: str, T: int | Tensor = 100, *, order: int = 0, dtype: torch.dtype = torch.float64,
                  device: torch.device | str | None = None) -> Tensor:
    """The clean stroke of ``letter`` (one of :data:`LETTERS`): ``(T, 2)`` positions at ``T`` phases evenly
    spaced in ``[0, 1]`` (or at the given phases ``(*S,)`` → ``(*S, 2)``), or their ``order``-th derivative
    with respect to the phase.  A C¹ spline of cubic Bézier segments (:func:`controllers.basis.spline`) on
    the letter's control points; it starts at the first control point and ends at the last."""
    own = "letter_stroke"
    pts = _letter_points(letter, own)
    S = (len(pts) - 4) // 2 + 1
    t = T if isinstance(T, Tensor) else basis.phases(_pos_int(T, "T", own, least=1), dtype, device)
    v = torch.tensor(pts, dtype=t.dtype, device=t.device)
    return basis.spline(t, n_segments=S, degree=3, continuity=1, order=order) @ v


def handwriting(letters: str = "SCUN", n_demos: int = 8, T: int = 100, *, generator: torch.Generator,
                duration: float = 1.0, warp: float = 0.3, noise: float = 0.02, n_basis: int = 5,
                dtype: torch.dtype = torch.float64, device: torch.device | str | None = None
                ) -> dict[str, Demonstrations]:
    """2-D handwriting-like demos generated here (no download): for each letter, ``n_demos`` copies of its
    clean stroke (:func:`letter_stroke`, in a unit box) varied by :func:`time_warp` (``strength=warp``) and
    :func:`spatial_noise` (``scale=noise``, ``n_basis`` RBFs, ends pinned), ``T`` samples over ``duration``
    seconds.  Returns ``{letter: Demonstrations}`` with ``x (n_demos, T, 2)`` positions, no controls, frames
    ``"start"``/``"goal"`` (the stroke's ends, ``(n_demos, 2)``), and ``meta`` naming the letter, its control
    points and the variability.  Every demo starts and ends exactly on the clean stroke's ends; its
    pointwise offset from the (re-timed) stroke has standard deviation ``noise · sin(π s)``."""
    own = "handwriting"
    if not isinstance(letters, str) or not letters:
        raise ValueError(f"{own}: 'letters' must be a non-empty string of {LETTERS!r}")
    for c in letters:
        _letter_points(c, own)
    n_demos = _pos_int(n_demos, "n_demos", own)
    T = _pos_int(T, "T", own, least=2)
    duration = _positive_float(duration, "duration", own)
    warp = _nonneg_float(warp, "warp", own)
    noise = _nonneg_float(noise, "noise", own)
    if dtype not in _DTYPES:
        raise TypeError(f"{own}: 'dtype' must be float32 or float64, got {dtype}")
    out = {}
    for c in dict.fromkeys(letters.upper()):
        clean = letter_stroke(c, T, dtype=dtype, device=device)
        ends = clean[[0, -1]]
        d = Demonstrations(x=clean.expand(n_demos, T, 2).clone(), dt=duration / (T - 1),
                           frames={"start": ends[0].expand(n_demos, 2).clone(),
                                   "goal": ends[1].expand(n_demos, 2).clone()},
                           meta={"source": "liecontrol handwriting", "letter": c,
                                 "control_points": [list(p) for p in _LETTERS[c]],
                                 "warp": float(warp), "noise": float(noise)})
        d = time_warp(d, warp, generator)
        out[c] = spatial_noise(d, noise, generator, n_basis=n_basis, pin_ends=True)
    return out
