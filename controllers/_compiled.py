"""Solver sweeps as compiled programs (private): a time loop the compiler sees once, and a disk cache.

Two pieces, used by the solvers' hot loops:

* :func:`scan` — ``carry, ys = scan(body, carry, xs, T, reverse)``: the time recursion of a sweep written
  once.  Run eagerly it is a Python loop over ``xs``' time slices (the reference path); traced by
  :func:`build` it becomes one ``while_loop`` whose body is compiled once, so the program does not grow with
  the horizon (unrolling a 40-step sweep took minutes to compile; the loop takes seconds).
* :func:`build` — a pure function of tensors exported by ``torch.export`` with a dynamic batch dimension,
  built by AOTInductor into a ``.pt2`` package and cached on disk (``$LIECONTROL_CACHE`` or
  ``~/.cache/liecontrol``), keyed on everything that changes the program: the caller's key (static sizes,
  options, a fingerprint of the system), dtype, device, the torch version and the source of this package.
  A second process loads the package in milliseconds instead of building it again.

Why a ``while_loop`` under AOTInductor (measured on this machine, float64, one thread, Riccati sweep
``n + 1 = 3``, ``T = 40``): build 8 s once; a call 0.16 ms at B = 1 and 9.6 ms at B = 1024, against
~2 ms/15 ms for the eager sweep.  ``torch``'s ``scan`` operator fails to lower with a dynamic batch in
2.13 (a shape symbol of the batch is not bound inside the decomposed loop), so the loop is written here as
a ``while_loop`` with preallocated outputs.
"""

from __future__ import annotations

import contextlib
import hashlib
import inspect
import logging
import os
import tempfile
import threading
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path

import torch

__all__ = ["scan", "tracing", "build", "fingerprint", "cache_dir", "Program"]

_STATE = threading.local()


def tracing() -> bool:
    """True while :func:`build` traces a program (solver code then emits ``while_loop``s)."""
    return getattr(_STATE, "tracing", False)


@contextlib.contextmanager
def _tracing():
    old = tracing()
    _STATE.tracing = True
    try:
        yield
    finally:
        _STATE.tracing = old


def scan(body: Callable, carry: tuple, xs: Sequence[torch.Tensor], T: int, reverse: bool = False,
         unroll: int | None = None) -> tuple[tuple, tuple]:
    """``for t in (reversed) range(T): carry, y_t = body(t, carry, [x[t] for x in xs])``; returns the final
    carry and the ``y_t`` stacked along a new leading time dim (in time order).  ``t`` is an int eagerly and
    ``None`` in a traced program (a program serves time-invariant steps only).

    ``xs`` are time-major tensors (time dim first, size ``T`` or 1 for a quantity shared by every step);
    ``carry`` and ``y_t`` are tuples of tensors.  ``body`` must not close over tensors that depend on the
    program's inputs (pass them in ``xs`` with a time dim of 1).  Eagerly a Python loop; under
    :func:`build`'s trace one loop operator whose body is compiled once, ``unroll`` time steps per loop
    iteration (default :data:`UNROLL`; 1 for a large body, whose copies would multiply the build time).
    """
    if T < 1:
        raise ValueError(f"scan: T must be >= 1, got {T}")
    order = range(T - 1, -1, -1) if reverse else range(T)
    if not tracing():
        slices = [x.unbind(0) if x.shape[0] > 1 else [x[0]] * T for x in xs]
        ys = [None] * T
        for t in order:
            carry, ys[t] = body(t, carry, [s[t] for s in slices])
        return carry, tuple(torch.stack(y) for y in zip(*ys))
    return _scan_loop(body, carry, xs, T, reverse, UNROLL if unroll is None else unroll)


#: time steps per iteration of a traced loop: the ``while_loop`` copies its output buffers once per iteration,
#: so taking several steps per iteration divides that traffic (and the per-iteration overhead) by as much
UNROLL = int(os.environ.get("LIECONTROL_SCAN_UNROLL", "4"))


def _scan_loop(body, carry, xs, T, reverse, unroll):
    """The traced form of :func:`scan`: a ``while_loop`` over blocks of ``unroll`` time steps with
    preallocated outputs (the first ``(T - 1) % unroll + 1`` steps are taken before the loop, which also
    allocates the outputs).

    torch's own ``scan`` operator fills its outputs in place, but with a dynamic batch it fails to lower in
    2.13 unless the batch size is passed into the loop, and then it crashed or returned wrong rollouts in
    iLQR's sweeps (ARCHITECTURE.md); the ``while_loop`` writes each block into copies of its output buffers
    (``index_copy``), which costs little at the batch sizes of a control loop and grows with ``T × batch``."""
    from torch._higher_order_ops.while_loop import while_loop

    nc, k = len(carry), max(1, unroll)
    step = -1 if reverse else 1
    order = list(range(T - 1, -1, -1)) if reverse else list(range(T))
    peel = (T - 1) % k + 1
    dev = xs[0].device if xs else carry[0].device

    def at(x, idx):  # time slice idx (a tensor of one index) of x
        return x.index_select(0, idx).squeeze(0) if x.shape[0] > 1 else x[0].clone()

    ys0 = []
    for t in order[:peel]:
        carry, y = body(None, carry, [x[t] if x.shape[0] > 1 else x[0] for x in xs])
        ys0.append((t, y))
    bufs = tuple(y.new_zeros(T, *y.shape) for y in ys0[0][1])
    for t, y in ys0:
        idx = torch.full((1,), t, device=dev)
        bufs = tuple(b.index_copy(0, idx, v.unsqueeze(0)) for b, v in zip(bufs, y))
    if peel == T:
        return carry, bufs
    i0 = torch.full((), order[peel], dtype=torch.int64, device=dev)

    def cond(i, *rest):
        return (i >= 0) if reverse else (i < T)

    def loop_body(i, *rest):
        c, b = tuple(rest[:nc]), rest[nc:]
        for j in range(k):
            idx = (i + j * step).reshape(1)
            c, y = body(None, c, [at(x, idx) for x in xs])
            b = tuple(bb.index_copy(0, idx, yy.unsqueeze(0)) for bb, yy in zip(b, y))
        # a carry that aliases an input is not allowed in a while_loop body
        return (i + k * step, *(v.clone() for v in c), *b)

    out = while_loop(cond, loop_body, (i0, *carry, *bufs))
    return tuple(out[1:1 + nc]), tuple(out[1 + nc:])


# --------------------------------------------------------------------------------------------------
# building and caching
# --------------------------------------------------------------------------------------------------


def cache_dir() -> Path:
    """Where built programs live: ``$LIECONTROL_CACHE`` or ``~/.cache/liecontrol`` (``aoti/`` below it)."""
    root = os.environ.get("LIECONTROL_CACHE") or os.path.join(os.path.expanduser("~"), ".cache", "liecontrol")
    return Path(root) / "aoti"


_SOURCE_HASH: list[str] = []


def _source_hash() -> str:
    """A hash of the source of the packages a program is traced from (a code change rebuilds)."""
    if not _SOURCE_HASH:
        h = hashlib.sha256(torch.__version__.encode())
        here = Path(__file__).resolve().parent
        for pkg in (here, here.parent / "torchlie"):
            for f in sorted(pkg.rglob("*.py")):
                h.update(f.read_bytes())
        _SOURCE_HASH.append(h.hexdigest()[:16])
    return _SOURCE_HASH[0]


_CLASS_SOURCE: dict[type, str | None] = {}  # a class -> hash of its module's file (read once per process)


def fingerprint(obj) -> str | None:
    """A text key of a system or cost whose fields are plain numbers, strings or 0-dim tensors (their values
    are baked into a program), with a hash of the file that defines its class; ``None`` when a field is
    anything else (a batched parameter, a tensor that requires grad), the object is not a dataclass, or its
    source file cannot be read: such a solve stays on the eager path.  (Code the class calls in other
    modules of the user's is not in the key: edit it and clear the cache, :func:`cache_dir`.)"""
    import dataclasses

    if not dataclasses.is_dataclass(obj):
        return None
    cls = type(obj)
    if cls not in _CLASS_SOURCE:
        try:  # the program bakes in the class's code: a change to its module must rebuild
            _CLASS_SOURCE[cls] = hashlib.sha256(Path(inspect.getfile(cls)).read_bytes()).hexdigest()[:16]
        except (OSError, TypeError):
            _CLASS_SOURCE[cls] = None
    src = _CLASS_SOURCE[cls]
    if src is None:
        return None
    parts = [type(obj).__module__ + "." + type(obj).__qualname__, src]
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        if isinstance(v, (bool, int, float, str)) or v is None:
            parts.append(f"{f.name}={v!r}")
        elif isinstance(v, torch.Tensor) and v.dim() == 0 and not v.requires_grad:
            parts.append(f"{f.name}={v.item()!r}:{v.dtype}")
        else:
            return None
    return ";".join(parts)


class Program:
    """A built package: call it with the tensors it was built for (any batch size)."""

    def __init__(self, path: str):
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*LeafSpec.*", category=FutureWarning)  # torch's own
            self._model = torch._inductor.aoti_load_package(path)
        # the loader's flat entry point skips the pytree wrapper (~50 µs a call on CPU)
        self._run = getattr(getattr(self._model, "loader", None), "run", None)
        self.path = path

    def __call__(self, *args: torch.Tensor) -> tuple[torch.Tensor, ...]:
        if self._run is not None:
            return tuple(self._run(list(args)))
        return tuple(self._model(*args))


class _Wrap(torch.nn.Module):
    def __init__(self, fn):
        super().__init__()
        self.fn = fn

    def forward(self, *args):
        return tuple(self.fn(*args))


_PROGRAMS: dict[tuple, Program | None] = {}
_LOCK = threading.Lock()


def build(name: str, key: str, fn: Callable, args: tuple[torch.Tensor, ...], batch_dims: Sequence[int | None]
          ) -> Program | None:
    """The program of ``fn(*args)`` with a dynamic batch size, built once and cached (memory and disk);
    ``None`` when it cannot be built or loaded here (no C++ compiler, an unwritable cache, an operation
    export cannot trace): a ``RuntimeWarning`` says why, once per program, and the caller runs eagerly.

    ``batch_dims[i]`` is the batch dim of ``args[i]`` (``None``: no batch dim).  ``key`` must name everything
    that changes the traced program besides dtypes, devices and the shapes of non-batch dims, which are
    added here.  Looking up a built program costs a dict access (no hashing of tensors).  A cached file
    that does not load (truncated, from another build) is rebuilt once.  Called while another program is
    traced, ``None`` (without a warning): the caller's eager code is traced into that program.
    """
    if tracing():  # called from inside a program being built: its body is traced into that program
        return None
    sig = (name, key, tuple((x.shape if d is None else x.shape[:d] + x.shape[d + 1:], x.dtype, str(x.device),
                             d) for x, d in zip(args, batch_dims)))
    if sig in _PROGRAMS:
        return _PROGRAMS[sig]
    with _LOCK:
        if sig not in _PROGRAMS:
            _PROGRAMS[sig] = _build_or_load(name, sig, fn, args, batch_dims)
    return _PROGRAMS[sig]


def _build_or_load(name, sig, fn, args, batch_dims) -> Program | None:
    # (UNROLL is read from the environment: a program traced with another value is another program)
    digest = hashlib.sha256(f"{sig}|{_source_hash()}|unroll={UNROLL}".encode()).hexdigest()[:24]
    path = cache_dir() / f"{name}-{digest}.pt2"
    try:
        for attempt in range(2):
            if not path.exists():
                _compile(fn, tuple(_example(x, d) for x, d in zip(args, batch_dims)), batch_dims, path)
            try:
                return Program(str(path))
            except Exception:
                if attempt:
                    raise
                path.unlink(missing_ok=True)  # a file that does not load: build it again
    except Exception as e:  # noqa: BLE001 — any failure of the toolchain means: run eagerly
        warnings.warn(f"liecontrol: could not build the compiled program '{name}' ({type(e).__name__}: "
                      f"{str(e).splitlines()[0] if str(e) else ''}); running it eagerly",
                      RuntimeWarning, stacklevel=4)
    return None


def _example(x: torch.Tensor, d: int | None) -> torch.Tensor:
    """A stand-in of ``x`` with a batch of 2 at dim ``d`` (the trace must not specialize on a size of 1)."""
    if d is None:
        return x
    shape = list(x.shape)
    shape[d] = 2
    return torch.zeros(shape, dtype=x.dtype, device=x.device)


def _compile(fn, example, batch_dims, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    b = torch.export.Dim("batch", min=1)
    shapes = tuple(None if d is None else {d: b} for d in batch_dims)
    with torch.no_grad(), _tracing(), warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*LeafSpec.*", category=FutureWarning)
        warnings.filterwarnings("ignore", message=".*c-shim.*")
        # torch's own deprecations inside export/inductor, not ours to act on
        warnings.filterwarnings("ignore", category=FutureWarning, module=r"torch\..*")
        warnings.filterwarnings("ignore", category=DeprecationWarning, module=r"torch\..*")
        # inductor logs one line per linalg call it routes through its proxy executor: noise to a user
        ir_log = logging.getLogger("torch._inductor.ir")
        level = ir_log.level
        ir_log.setLevel(logging.ERROR)
        try:
            ep = torch.export.export(_Wrap(fn), example, dynamic_shapes=(shapes,))  # forward(*args)
            _package(ep, path)
        finally:
            ir_log.setLevel(level)


def _package(ep, path: Path) -> None:
    """AOTInductor-compile the exported program ``ep`` into the package file ``path``."""
    # built next to its final place and renamed: a concurrent process never loads half a file
    fd, tmp = tempfile.mkstemp(suffix=".pt2", dir=path.parent)
    os.close(fd)
    try:
        torch._inductor.aoti_compile_and_package(ep, package_path=tmp)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)
