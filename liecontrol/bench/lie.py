"""``liecontrol bench lie``: torchlie's group operations against pypose and roma, in one run.

For every group (so3, se3), op (exp, exp_quat, exp_mat, log, log_quat, log_mat, compose, act, inverse, and
the Jacobians Jr, Jl, Jr_inv, Jl_inv), dtype and batch size, each library is timed as the median of
``--repeats`` runs after warm-up, and the ratio anchor/ours is reported.  Unless the op says otherwise
each library works on its own native representation: pypose on quaternion LieTensors (``(x, y, z, w)``,
se3 ``(t, q)``), roma and torchlie on rotation/homogeneous matrices; conversions happen outside the
timed call.  The three logarithms differ only in what each side is given (the record's
``ours_input``/``anchor_input``):

* ``log``: each side its native form — torchlie and roma a matrix, pypose its quaternion.  Not like
  with like: a matrix log has to extract the rotation's quaternion first, pypose's starts from it.
* ``log_quat`` (so3 only): a unit quaternion on every side — ``torchlie.quaternion.log`` on ``(w, x, y,
  z)``, pypose's ``Log`` on its native quaternion LieTensor, ``roma.unitquat_to_rotvec`` on ``(x, y, z,
  w)``.
* ``log_mat``: a matrix on every side — ``so3.log``/``se3.log`` as in ``log``, pypose's
  ``mat2SO3(X).Log()``/``mat2SE3(X).Log()`` with its matrix-to-quaternion conversion inside the timed
  call (``check=False``: no orthogonality test), roma as in ``log``.

The exponentials likewise: ``exp`` returns each side's native form (torchlie and roma a matrix, pypose
a quaternion: 9 numbers against 4 per rotation), ``exp_quat`` (so3 only) a quaternion on every side
(``torchlie.quaternion.exp``, ``roma.rotvec_to_unitquat``) and ``exp_mat`` a matrix on every side
(pypose's ``Exp().matrix()`` timed).

pypose has a public Jacobian only for
so(3) (``LieTensor.Jr``); the other Jacobian anchors are the functions its ``Jinvp`` is built on
(``pypose.lietensor.operation.so3_Jl``/``so3_Jl_inv``/``se3_Jl``/``se3_Jl_inv``; J_r(x) = J_l(−x),
with −x computed outside the timed call).  ``ours_compiled_ms`` is the same torchlie function under
``torch.compile(fullgraph=True)`` — something neither anchor supports.  The round-trip error
``max |exp(log(X)) − X|`` is measured per library on rotation angles uniform in [0, π)
(``roundtrip_err``) and on angles within 1e-9..1e-3 of 0 and π (``roundtrip_err_edges``), always in
matrix form so the libraries are compared on one metric.
"""

from __future__ import annotations

import argparse
import math

import torch

from liecontrol import _options
from liecontrol.report import print_table, restores_threads, time_ms, write_json
from torchlie import quaternion, se3, so3

__all__ = ["add_arguments", "run", "measure"]

OPS = _options.LIE_OPS
# what a library's timed call is given for the group element (see the module docstring); tangent-input
# ops (exp, Jacobians) take ``(*, d)`` vectors on every side
_MATRIX, _QUAT = "matrix", "quaternion"
_PP_NATIVE = {"so3": "quaternion LieTensor", "se3": "(t, quaternion) LieTensor"}
_MAT_CONVERTED = "matrix (conversion timed)"


add_arguments = _options.bench_lie


# ------------------------------------------------------------------------------------------- samples

def _tangents(group: str, n: int, dtype, device, gen: torch.Generator, edges: bool = False) -> torch.Tensor:
    if edges:
        base = torch.tensor([0.0, 1e-9, 1e-6, 1e-3], dtype=torch.float64)
        th = torch.cat((base, math.pi - base[1:]))
        th = th.repeat(n // len(th) + 1)[:n]
    else:
        th = math.pi * torch.rand(n, generator=gen, dtype=torch.float64)
    axis = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen, dtype=torch.float64), dim=-1)
    w = th.unsqueeze(-1) * axis
    if group == "se3":
        w = torch.cat((torch.randn(n, 3, generator=gen, dtype=torch.float64), w), -1)
    return w.to(dtype=dtype, device=device)


# ------------------------------------------------------------------------------------------- libraries

_TANGENT_OPS = ("exp", "exp_quat", "exp_mat", "Jr", "Jl", "Jr_inv", "Jl_inv")


def _exp_io(op: str, output: str) -> str:
    """What a tangent-input op is given, and for the exponentials what it returns."""
    return f"tangent -> {output}" if op.startswith("exp") else "tangent"


class _NotApplicable(Exception):
    """An anchor library has no counterpart of the group or op: reported as "n/a", not a failure."""


class _Ours:
    name = "torchlie"

    def __init__(self, group):
        self.m = so3 if group == "so3" else se3

    def from_matrix(self, X):
        return X

    def to_matrix(self, X):
        return X

    def inputs(self, op):
        return _exp_io(op, _QUAT if op == "exp_quat" else _MATRIX) if op in _TANGENT_OPS else (
            _QUAT if op == "log_quat" else _MATRIX)

    def fns(self, X, Y, x, p, Xmat):
        m = self.m
        out = {
            "exp": (m.exp, (x,)),
            "exp_mat": (m.exp, (x,)),
            "log": (m.log, (X,)),
            "log_mat": (m.log, (X,)),
            "compose": (m.compose, (X, Y)),
            "act": (m.act, (X, p)),
            "inverse": (m.inverse, (X,)),
            "Jr": (m.right_jacobian, (x,)),
            "Jl": (m.left_jacobian, (x,)),
            "Jr_inv": (m.right_jacobian_inv, (x,)),
            "Jl_inv": (m.left_jacobian_inv, (x,)),
        }
        if m is so3:
            out["log_quat"] = (quaternion.log, (quaternion.from_matrix(X),))
            out["exp_quat"] = (quaternion.exp, (x,))
        return out

    def roundtrip(self, X):
        return self.m.exp(self.m.log(X))


class _Pypose:
    name = "pypose"

    def __init__(self, group):
        import pypose as pp

        self.pp, self.group = pp, group

    def from_matrix(self, X):
        pp = self.pp
        return pp.mat2SO3(X, check=False) if self.group == "so3" else pp.mat2SE3(X, check=False)

    def to_matrix(self, X):
        return X.matrix()

    def inputs(self, op):
        if op in _TANGENT_OPS:
            return _exp_io(op, _MAT_CONVERTED if op == "exp_mat" else _PP_NATIVE[self.group])
        return _MAT_CONVERTED if op == "log_mat" else _PP_NATIVE[self.group]

    def fns(self, X, Y, x, p, Xmat):
        from pypose.lietensor import operation as op

        pp = self.pp
        xl = pp.so3(x) if self.group == "so3" else pp.se3(x)
        jl, jl_inv = (op.so3_Jl, op.so3_Jl_inv) if self.group == "so3" else (op.se3_Jl, op.se3_Jl_inv)
        out = {
            "exp": (lambda a: a.Exp(), (xl,)),
            "exp_quat": (lambda a: a.Exp(), (xl,)),
            "exp_mat": (lambda a: a.Exp().matrix(), (xl,)),
            "log": (lambda a: a.Log(), (X,)),
            "log_quat": (lambda a: a.Log(), (X,)),
            "log_mat": (lambda m: self.from_matrix(m).Log(), (Xmat,)),
            "compose": (lambda a, b: a @ b, (X, Y)),
            "act": (lambda a, b: a.Act(b), (X, p)),
            "inverse": (lambda a: a.Inv(), (X,)),
            "Jr": (jl, (-x,)),
            "Jl": (jl, (x,)),
            "Jr_inv": (jl_inv, (-x,)),
            "Jl_inv": (jl_inv, (x,)),
        }
        if self.group == "so3":
            out["Jr"] = (lambda a: a.Jr(), (xl,))  # the public one
        return out

    def roundtrip(self, X):
        return X.Log().Exp()


class _Roma:
    name = "roma"

    def __init__(self, group):
        if group != "so3":
            raise _NotApplicable("roma has no SE(3) exponential/logarithm")
        import roma

        self.roma = roma

    def from_matrix(self, X):
        return X

    def to_matrix(self, X):
        return X

    def inputs(self, op):
        return _exp_io(op, _QUAT if op == "exp_quat" else _MATRIX) if op in _TANGENT_OPS else (
            _QUAT if op == "log_quat" else _MATRIX)

    def fns(self, X, Y, x, p, Xmat):
        r = self.roma
        return {
            "exp": (r.rotvec_to_rotmat, (x,)),
            "exp_quat": (r.rotvec_to_unitquat, (x,)),
            "exp_mat": (r.rotvec_to_rotmat, (x,)),
            "log": (r.rotmat_to_rotvec, (X,)),
            "log_quat": (r.unitquat_to_rotvec, (quaternion.to_xyzw(quaternion.from_matrix(X)),)),
            "log_mat": (r.rotmat_to_rotvec, (X,)),
            "compose": (lambda a, b: r.rotmat_composition((a, b)), (X, Y)),
            "act": (lambda a, b: (a @ b.unsqueeze(-1)).squeeze(-1), (X, p)),
            "inverse": (r.rotmat_inverse, (X,)),
        }

    def roundtrip(self, X):
        return self.roma.rotvec_to_rotmat(self.roma.rotmat_to_rotvec(X))


def _anchor(cls, group):
    try:
        return cls(group), None
    except ImportError as e:
        return None, f"missing ({e.name or e})"
    except _NotApplicable as e:
        return None, f"n/a ({e})"


def _roundtrip_err(lib, X_mat) -> float:
    with torch.no_grad():
        Xn = lib.from_matrix(X_mat)
        back = lib.to_matrix(lib.roundtrip(Xn))
        return (back - X_mat).abs().max().item()


# ------------------------------------------------------------------------------------------- measurement

def measure(groups=("so3", "se3"), ops=OPS, dtypes=("float32", "float64"), batches=(1, 1000, 100000),
            devices=None, repeats: int = 9, compile_ours: bool = True, log=print) -> list[dict]:
    """Run the benchmark and return its records (see the module docstring)."""
    if devices is None:
        devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    records: list[dict] = []
    gen = torch.Generator().manual_seed(0)
    for device in devices:
        for group in groups:
            ours = _Ours(group)
            anchors = [(_Pypose, *_anchor(_Pypose, group)), (_Roma, *_anchor(_Roma, group))]
            for dtype_name in dtypes:
                dtype = getattr(torch, dtype_name)
                # accuracy, once per (group, dtype, device), on 20000 samples
                Xacc = ours.m.exp(_tangents(group, 20000, torch.float64, device, gen))
                Xedge = ours.m.exp(_tangents(group, 20000, torch.float64, device, gen, edges=True))
                err = {"torchlie": (_roundtrip_err(ours, Xacc.to(dtype)),
                                    _roundtrip_err(ours, Xedge.to(dtype)))}
                for cls, lib, _why in anchors:
                    if lib is not None:
                        try:
                            err[cls.name] = (_roundtrip_err(lib, Xacc.to(dtype)),
                                             _roundtrip_err(lib, Xedge.to(dtype)))
                        except Exception as e:  # an anchor's failure is its result
                            err[cls.name] = (f"failed: {type(e).__name__}", None)
                for batch in batches:
                    x = _tangents(group, batch, dtype, device, gen)
                    X = ours.m.exp(x)
                    Y = ours.m.exp(_tangents(group, batch, dtype, device, gen))
                    p = torch.randn(batch, 3, generator=gen, dtype=torch.float64).to(dtype=dtype,
                                                                                     device=device)
                    our_fns = ours.fns(X, Y, x, p, X)
                    for op in ops:
                        if op not in our_fns:  # log_quat: torchlie has no quaternion form of SE(3)
                            continue
                        fn, args = our_fns[op]
                        ours_ms = time_ms(lambda fn=fn, args=args: fn(*args), repeats=repeats, device=device,
                                          min_time_s=0.002)
                        comp_ms = None
                        if compile_ours:
                            try:
                                cf = torch.compile(fn, fullgraph=True, dynamic=False)
                                comp_ms = time_ms(lambda cf=cf, args=args: cf(*args), repeats=repeats,
                                                  device=device, min_time_s=0.002)
                            except Exception as e:  # report, don't crash the benchmark
                                log(f"torch.compile failed for {group}.{op}: {type(e).__name__}: {e}")
                        for cls, lib, why in anchors:
                            rec = {"group": group, "op": op, "dtype": dtype_name, "batch": batch,
                                   "device": str(device), "ours_ms": ours_ms, "ours_compiled_ms": comp_ms,
                                   "anchor": cls.name, "anchor_ms": None, "speedup": None,
                                   "speedup_compiled": None,
                                   "roundtrip_err": err["torchlie"][0],
                                   "roundtrip_err_edges": err["torchlie"][1],
                                   "anchor_roundtrip_err": None, "anchor_roundtrip_err_edges": None,
                                   "anchor_status": "ok", "ours_input": ours.inputs(op),
                                   "anchor_input": lib.inputs(op) if lib is not None else None}
                            if lib is None:
                                rec["anchor_status"] = why
                                records.append(rec)
                                continue
                            rec["anchor_roundtrip_err"], rec["anchor_roundtrip_err_edges"] = err[cls.name]
                            try:
                                afns = lib.fns(lib.from_matrix(X), lib.from_matrix(Y), x, p, X)
                            except Exception as e:
                                rec["anchor_status"] = f"failed: {type(e).__name__}: {e}"
                                records.append(rec)
                                continue
                            if op not in afns:
                                rec["anchor_status"] = "n/a (op not provided)"
                                records.append(rec)
                                continue
                            afn, aargs = afns[op]
                            try:
                                a_ms = time_ms(lambda afn=afn, aargs=aargs: afn(*aargs), repeats=repeats,
                                               device=device, min_time_s=0.002)
                            except Exception as e:
                                rec["anchor_status"] = f"failed: {type(e).__name__}: {e}"
                                records.append(rec)
                                continue
                            rec["anchor_ms"] = a_ms
                            rec["speedup"] = a_ms / ours_ms
                            rec["speedup_compiled"] = a_ms / comp_ms if comp_ms else None
                            records.append(rec)
    return records


@restores_threads
def run(args: argparse.Namespace) -> int:
    if args.threads:
        torch.set_num_threads(args.threads)
    records = measure(groups=args.groups, ops=args.ops, dtypes=args.dtypes, batches=args.batches,
                      devices=args.devices, repeats=args.repeats, compile_ours=not args.no_compile)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads; times in ms (median of "
          f"{args.repeats}); speedup = anchor_ms / ours_ms")
    cols = ["group", "op", "dtype", "batch", "ours_ms", "ours_compiled_ms", "anchor", "anchor_ms", "speedup",
            "speedup_compiled", "anchor_status", "ours_input", "anchor_input"]
    print_table(records, cols)
    print()
    print("round-trip error max|exp(log X) - X| (uniform angles in [0, pi) / within 1e-9..1e-3 of 0 and pi):")
    seen = set()
    acc_rows = []
    for r in records:
        key = (r["group"], r["dtype"], r["device"])
        if key + ("torchlie",) not in seen:
            seen.add(key + ("torchlie",))
            acc_rows.append({"group": r["group"], "dtype": r["dtype"], "library": "torchlie",
                             "roundtrip_err": r["roundtrip_err"], "edges": r["roundtrip_err_edges"]})
        if r["anchor_status"] == "ok" or r["anchor_roundtrip_err"] is not None:
            if key + (r["anchor"],) not in seen:
                seen.add(key + (r["anchor"],))
                acc_rows.append({"group": r["group"], "dtype": r["dtype"], "library": r["anchor"],
                                 "roundtrip_err": r["anchor_roundtrip_err"],
                                 "edges": r["anchor_roundtrip_err_edges"]})
    print_table(acc_rows, ["group", "dtype", "library", "roundtrip_err", "edges"])
    if args.json:
        write_json(args.json, records)
        print(f"wrote {len(records)} records to {args.json}")
    return 0
