"""iLQR's time sweeps as compiled programs (``ILQROptions(compile=True)``) against the eager reference.

The eager sweeps are the reference: the compiled ones must give the same values (to round-off), the same
statuses and the same iteration counts, for any batch size (one program serves them all), with one bad
element in the batch, and reload from the disk cache without building again.  Each program takes a few
seconds to build, so the tests share the suite's cache directory (tests/conftest.py).
"""

import dataclasses
import math
import os

import pytest
import torch

from controllers import _compiled
from controllers.costs import QuadraticCost
from controllers.dynamics import LinearDynamics
from controllers.ilqr import ILQROptions, ILQRProblem, ilqr
from controllers.problem import Reason
from controllers.systems import Pendulum

D = torch.float64


def _swingup(B: int, T: int = 30):
    g = torch.Generator().manual_seed(B)
    x0 = torch.stack([torch.rand(B, generator=g, dtype=D) * 2 - 1, torch.zeros(B, dtype=D)], -1)
    Q = torch.diag(torch.tensor([1.0, 0.1], dtype=D)).expand(T + 1, 2, 2).clone()
    Q[-1] *= 100
    cost = QuadraticCost(Q=Q, R=torch.tensor([[0.01]], dtype=D), x_ref=torch.tensor([math.pi, 0.0], dtype=D))
    return ILQRProblem(Pendulum(damping=0.1), cost, x0, T, u_lower=-2.0, u_upper=2.0)


def _both(problem, **kw):
    eager = ilqr(problem, grad="none", options=ILQROptions(max_iter=40, **kw))
    comp = ilqr(problem, grad="none", options=ILQROptions(max_iter=40, compile=True, **kw))
    return eager, comp


def _assert_same(a, b, tol=1e-9):
    torch.testing.assert_close(b.u, a.u, atol=tol, rtol=0, equal_nan=True)
    torch.testing.assert_close(b.x, a.x, atol=tol, rtol=0, equal_nan=True)
    torch.testing.assert_close(b.K, a.K, atol=tol * 1e3, rtol=0, equal_nan=True)
    torch.testing.assert_close(b.cost, a.cost, atol=tol, rtol=1e-12, equal_nan=True)
    assert torch.equal(b.status.reason, a.status.reason)
    assert torch.equal(b.status.iterations, a.status.iterations)
    assert torch.equal(b.clamped, a.clamped)


@pytest.mark.parametrize("B", [1, 5])
def test_limited_swingup_equals_the_eager_sweeps_at_any_batch_size(B):
    eager, comp = _both(_swingup(B))
    assert (eager.status.reason == int(Reason.CONVERGED)).all()
    assert eager.clamped.any()  # the limits bind: the clip path of the backward pass is exercised
    _assert_same(eager, comp)


def test_an_unbatched_problem_equals_the_eager_sweeps():
    p = _swingup(1)
    eager, comp = _both(ILQRProblem(p.dynamics, p.cost, p.x0[0], p.horizon, u_lower=-2.0, u_upper=2.0))
    assert comp.u.shape == (p.horizon, 1) and comp.status.reason.shape == ()
    _assert_same(eager, comp)


def test_a_bad_element_stays_its_own_in_the_compiled_sweeps():
    p = _swingup(4)
    x0 = p.x0.clone()
    x0[2, 0] = math.nan
    eager, comp = _both(ILQRProblem(p.dynamics, p.cost, x0, p.horizon, u_lower=-2.0, u_upper=2.0))
    assert comp.status.reason[2] == int(Reason.NONFINITE_INPUT)
    assert (comp.status.reason[[0, 1, 3]] == int(Reason.CONVERGED)).all()
    _assert_same(eager, comp)
    alone = ilqr(_swingup(4), grad="none", options=ILQROptions(max_iter=40, compile=True))
    torch.testing.assert_close(comp.u[[0, 1, 3]], alone.u[[0, 1, 3]], atol=1e-9, rtol=0)


def test_several_controls_and_two_batch_dims_equal_the_eager_sweeps():
    """A linear system with two inputs and a (2, 3) batch: Cholesky in the compiled backward pass; the
    rollouts stay eager (the system's matrices are not numbers a program can bake in)."""
    g = torch.Generator().manual_seed(1)
    n, m, T = 3, 2, 12
    A = torch.eye(n, dtype=D) + 0.1 * torch.randn(n, n, generator=g, dtype=D)
    Bm = torch.randn(n, m, generator=g, dtype=D)
    x0 = torch.randn(2, 3, n, generator=g, dtype=D)
    cost = QuadraticCost(Q=torch.eye(n, dtype=D), R=0.1 * torch.eye(m, dtype=D))
    p = ILQRProblem(LinearDynamics(A, Bm), cost, x0, T)
    eager, comp = _both(p)
    assert (comp.status.reason == int(Reason.CONVERGED)).all()
    _assert_same(eager, comp)


def test_a_built_program_is_loaded_from_disk_by_a_fresh_process(monkeypatch):
    p = _swingup(3)
    ref = ilqr(p, grad="none", options=ILQROptions(max_iter=40, compile=True))
    assert list(_compiled.cache_dir().glob("ilqr_*.pt2"))
    # a fresh process: nothing in memory, and building is not allowed
    monkeypatch.setattr(_compiled, "_PROGRAMS", {})

    def no_build(*a, **k):
        raise AssertionError("the program should have come from the disk cache")

    monkeypatch.setattr(_compiled, "_compile", no_build)
    again = ilqr(p, grad="none", options=ILQROptions(max_iter=40, compile=True))
    _assert_same(ref, again, tol=0.0)


def test_a_program_that_cannot_be_built_warns_and_runs_eagerly(monkeypatch, tmp_path):
    monkeypatch.setenv("LIECONTROL_CACHE", str(tmp_path))
    monkeypatch.setattr(_compiled, "_PROGRAMS", {})

    def broken(*a, **k):
        raise RuntimeError("no C++ compiler found")

    monkeypatch.setattr(_compiled, "_compile", broken)
    p = _swingup(2)
    msg = "could not build the compiled program 'ilqr_.*no C\\+\\+ compiler"
    with pytest.warns(RuntimeWarning, match=msg):
        comp = ilqr(p, grad="none", options=ILQROptions(max_iter=40, compile=True))
    _assert_same(ilqr(p, grad="none", options=ILQROptions(max_iter=40)), comp, tol=0.0)


def test_a_cached_file_that_does_not_load_is_rebuilt(monkeypatch, tmp_path):
    # a cache of its own: other test workers load the shared one at the same time
    monkeypatch.setenv("LIECONTROL_CACHE", str(tmp_path))
    monkeypatch.setattr(_compiled, "_PROGRAMS", {})
    p = _swingup(2)
    ref = ilqr(p, grad="none", options=ILQROptions(max_iter=40, compile=True))
    files = sorted(_compiled.cache_dir().glob("ilqr_kkt-*.pt2"))
    assert files
    for f in files:
        f.write_bytes(b"not a package")
    monkeypatch.setattr(_compiled, "_PROGRAMS", {})
    again = ilqr(p, grad="none", options=ILQROptions(max_iter=40, compile=True))
    _assert_same(ref, again, tol=0.0)
    used = [pr.path for pr in _compiled._PROGRAMS.values() if pr is not None and "ilqr_kkt" in pr.path]
    assert used and all(os.path.getsize(f) > 1000 for f in used)  # rebuilt in place


def test_the_fingerprint_follows_the_fields_and_the_source_of_the_class(tmp_path, monkeypatch):
    import importlib
    import sys

    src = ("from dataclasses import dataclass\n@dataclass(frozen=True)\nclass Sys:\n    k: float = 1.0\n"
           "    def step(self, x, u, t):\n        return x + {} * u\n")
    mod = tmp_path / "fp_user_system.py"
    mod.write_text(src.format("self.k"))
    monkeypatch.syspath_prepend(str(tmp_path))
    m1 = importlib.import_module("fp_user_system")
    a, b = _compiled.fingerprint(m1.Sys()), _compiled.fingerprint(m1.Sys(k=2.0))
    assert a is not None and a != b
    mod.write_text(src.format("2 * self.k"))
    del sys.modules["fp_user_system"]
    m2 = importlib.import_module("fp_user_system")
    assert _compiled.fingerprint(m2.Sys()) != a  # same fields, other code: another program
    # a batched or differentiable parameter cannot be baked into a program
    assert _compiled.fingerprint(Pendulum(length=torch.ones(3, 1, dtype=D))) is None
    assert _compiled.fingerprint(Pendulum(length=torch.tensor(1.0, dtype=D, requires_grad=True))) is None
    other = _compiled.fingerprint(Pendulum(length=torch.tensor(1.5, dtype=D)))
    assert other is not None and other != _compiled.fingerprint(Pendulum())


def test_implicit_gradients_through_compiled_solves_equal_the_eager_ones():
    """``ILQROptions(compile=True)`` also compiles the implicit step (the LQ solve and its adjoint sweeps)."""
    p = _swingup(3)
    grads = []
    for comp in (False, True):
        R = torch.tensor([[0.01]], dtype=D, requires_grad=True)
        ref = torch.tensor([math.pi, 0.0], dtype=D, requires_grad=True)
        cost = QuadraticCost(Q=p.cost.Q, R=R, x_ref=ref)
        # wide limits: free controls depend on R (a clamped one does not)
        prob = ILQRProblem(p.dynamics, cost, p.x0, p.horizon, u_lower=-30.0, u_upper=30.0)
        sol = ilqr(prob, options=ILQROptions(max_iter=60, compile=comp))
        assert (sol.status.reason == int(Reason.CONVERGED)).all() and not sol.clamped.all()
        (sol.u.square().sum() + sol.x[..., -1, 1].sum()).backward()
        grads.append((sol.u.detach(), R.grad, ref.grad))
    for a, b in zip(*grads):
        torch.testing.assert_close(b, a, atol=1e-9, rtol=1e-9)
    assert grads[0][1].abs().item() > 0 and grads[0][2].abs().sum().item() > 0


# ---- the whole iteration as one program (controllers._ilqr_step)


def _iteration_programs():
    return [k for k, v in _compiled._PROGRAMS.items() if k[0] == "ilqr_iteration" and v is not None]


def test_the_swingup_runs_one_program_per_iteration():
    """Pendulum (analytic Jacobians, numbers for parameters), a QuadraticCost, one limited control: the
    iteration program serves it (the tests above compare it with the eager loop)."""
    ilqr(_swingup(2), grad="none", options=ILQROptions(max_iter=40, compile=True))
    assert _iteration_programs()


def test_a_periodic_cost_with_a_batched_reference_and_two_batch_dims_equals_the_eager_loop():
    """The cost's tensors are program inputs: a reference per element (batched, flattened with the batch)
    next to shared weights, on a (2, 3) batch, and the periodic wrap of the angle."""
    from controllers.costs import PeriodicQuadraticCost

    T = 25
    g = torch.Generator().manual_seed(7)
    x0 = torch.stack([torch.rand(2, 3, generator=g, dtype=D) * 6 - 3, torch.zeros(2, 3, dtype=D)], -1)
    ref = torch.stack([math.pi + 0.3 * torch.randn(2, 3, generator=g, dtype=D), torch.zeros(2, 3, dtype=D)],
                      -1)
    Q = torch.diag(torch.tensor([1.0, 0.1], dtype=D)).expand(T + 1, 2, 2).clone()
    Q[-1] *= 50
    base = QuadraticCost(Q=Q, R=torch.tensor([[0.02]], dtype=D), x_ref=ref.unsqueeze(-2))
    cost = PeriodicQuadraticCost(base, torch.tensor([True, False]))
    p = ILQRProblem(Pendulum(damping=0.05), cost, x0, T, u_lower=-3.0, u_upper=3.0)
    eager, comp = _both(p)
    assert comp.u.shape == (2, 3, T, 1)
    assert (eager.status.reason == int(Reason.CONVERGED)).sum() >= 4
    _assert_same(eager, comp)
    assert any("periodic=True" in k[1] for k in _iteration_programs())


def test_an_iteration_whose_backward_pass_fails_is_run_again_eagerly(monkeypatch):
    """Where the program reports a failed backward pass (μ must grow: a data-dependent retry) its result
    is dropped and that iteration runs eagerly from the same point: here every iteration reports one, and
    the returned iterate is a garbage one that must never be used."""
    import controllers.ilqr as il

    def failing(dyn, dyn_key, cost, x0, it, lo, hi, bs, s):
        garbage = it._replace(x=torch.full_like(it.x, math.nan), u=torch.full_like(it.u, math.nan))
        return garbage, torch.tensor([1, 1, 1, 1])

    monkeypatch.setattr(il, "program_iteration", failing)
    p = _swingup(3)
    eager, comp = _both(p)  # (the eager iterations still run their sweeps as programs: round-off apart)
    assert (comp.status.reason == int(Reason.CONVERGED)).all()
    _assert_same(eager, comp)


def test_the_iteration_program_stops_where_the_eager_loop_stops():
    """``max_iter`` reached mid-way (MAX_ITERATIONS, a cost history of max_iter + 1 rows) and a solve
    that converges in a few iterations: statuses, counts and histories as the eager loop's."""
    p = _swingup(4)
    for it in (3, 40):
        a = ilqr(p, grad="none", options=ILQROptions(max_iter=it))
        b = ilqr(p, grad="none", options=ILQROptions(max_iter=it, compile=True))
        _assert_same(a, b)
        assert b.cost_history.shape == a.cost_history.shape
        torch.testing.assert_close(b.cost_history, a.cost_history, atol=1e-9, rtol=1e-12)
    assert (a.status.reason == int(Reason.CONVERGED)).all()
    short = ilqr(p, grad="none", options=ILQROptions(max_iter=3, compile=True)).status
    assert (short.reason == int(Reason.MAX_ITERATIONS)).any() and (short.iterations <= 3).all()


def test_float32_swingup_equals_the_eager_loop():
    p = _swingup(3)
    c = p.cost
    cost = QuadraticCost(Q=c.Q.float(), R=c.R.float(), x_ref=c.x_ref.float())
    p32 = ILQRProblem(p.dynamics, cost, p.x0.float(), p.horizon, u_lower=-2.0, u_upper=2.0)
    eager, comp = _both(p32)
    assert comp.u.dtype == torch.float32
    assert (eager.status.reason == int(Reason.CONVERGED)).all()
    _assert_same(eager, comp, tol=1e-4)


# ---- two limited controls: the box QPs of the backward pass inside the program


@dataclasses.dataclass(frozen=True)
class Skater:
    """A point on a slope pushed by two limited forces: ``x = [p₁, p₂]``, ``u = [f₁, f₂]``,
    ``x⁺ = x + dt (u − c x + s sin(p₂, p₁))`` (a small system: its program builds quickly)."""

    dt: float = 0.1
    c: float = 0.2
    s: float = 0.5
    n = 2
    m = 2
    time_invariant = True

    def step(self, x, u, t=0):
        return x + self.dt * (u - self.c * x + self.s * torch.sin(x.flip(-1)))

    def jacobian(self, x, u, t=0):
        eye = torch.eye(2, dtype=x.dtype, device=x.device)
        cos = torch.cos(x.flip(-1))
        swap = torch.stack([torch.stack([torch.zeros_like(cos[..., 0]), cos[..., 0]], -1),
                            torch.stack([cos[..., 1], torch.zeros_like(cos[..., 1])], -1)], -2)
        A = eye + self.dt * (self.s * swap - self.c * eye)
        return A, (self.dt * eye).expand(*x.shape[:-1], 2, 2)


def _skater(B: int, dtype=D, T: int = 20):
    g = torch.Generator().manual_seed(11)
    x0 = (torch.rand(B, 2, generator=g, dtype=D) * 4 - 2).to(dtype)
    Q = torch.diag(torch.tensor([1.0, 2.0], dtype=dtype)).expand(T + 1, 2, 2).clone()
    Q[-1] *= 20
    R = torch.tensor([[0.05, 0.02], [0.02, 0.08]], dtype=dtype)
    cost = QuadraticCost(Q=Q, R=R, x_ref=torch.tensor([1.5, -1.0], dtype=dtype))
    return ILQRProblem(Skater(), cost, x0, T, u_lower=torch.tensor([-1.0, -0.6], dtype=dtype),
                       u_upper=torch.tensor([0.8, 1.0], dtype=dtype))


def test_two_limited_controls_run_one_program_per_iteration_and_equal_the_eager_loop():
    """(float32 inside the program: the box QP is solved and certified as box_qp does, in float64 —
    tests/controllers/test_boxqp.py::test_the_fixed_two_variable_box_qp_is_box_qp_where_it_certifies.)"""
    dtype = D
    p = _skater(6, dtype)
    eager, comp = _both(p)
    assert (eager.status.reason == int(Reason.CONVERGED)).all()
    assert eager.clamped.any() and (~eager.clamped).any()  # the box QPs have clamped and free controls
    assert any("m=2;bounded=True" in k[1] for k in _iteration_programs())
    _assert_same(eager, comp)


def test_a_final_pass_whose_box_qp_the_program_cannot_certify_is_run_again_eagerly(monkeypatch):
    """The gains at the returned point come from a backward-pass program whose box QPs are box_qp's first
    step; where it reports an uncertified element the pass runs again eagerly.  Here the program's result
    is replaced by garbage marked failed: the returned gains must still equal the eager loop's."""
    import controllers._ilqr_sweeps as sw

    real, calls = sw.run_flat, []

    def uncertified(name, key, fn, args, layout, bs, out_lead):
        out = real(name, key, fn, args, layout, bs, out_lead)
        if name != "ilqr_backward":
            return out
        calls.append(key)
        return (torch.full_like(out[0], math.nan), torch.full_like(out[1], math.nan), out[2],
                torch.zeros_like(out[3]), *out[4:])

    monkeypatch.setattr(sw, "run_flat", uncertified)
    eager, comp = _both(_skater(3))
    assert calls and all("m=2;bounded=True" in k for k in calls)
    assert (comp.status.reason == int(Reason.CONVERGED)).all()
    _assert_same(eager, comp)


@dataclasses.dataclass(frozen=True)
class _AutogradSkater(Skater):
    """The skater without its analytic Jacobian: no iteration program serves it (its Jacobians come from
    autograd), so each iteration runs eagerly around compiled sweeps."""

    jacobian = None


def test_an_eager_iteration_runs_its_first_backward_pass_as_a_program_and_equals_the_eager_loop(monkeypatch):
    """Two limited controls in an iteration that is not one program (a MuJoCo model, a system without
    analytic Jacobians): the iteration's first backward pass is a program too (its box QPs box_qp's first
    step, rerun eagerly where one is uncertified); μ's retries run eagerly.  Same plan, statuses and
    iteration counts as the eager loop."""
    import controllers._ilqr_sweeps as sw

    real, keys = sw.run_flat, []

    def spy(name, key, fn, args, layout, bs, out_lead):
        keys.append(name)
        return real(name, key, fn, args, layout, bs, out_lead)

    monkeypatch.setattr(sw, "run_flat", spy)
    p = dataclasses.replace(_skater(4), dynamics=_AutogradSkater())
    eager = ilqr(p, grad="none", options=ILQROptions(max_iter=40))
    assert not keys
    comp = ilqr(p, grad="none", options=ILQROptions(max_iter=40, compile=True))
    assert (eager.status.reason == int(Reason.CONVERGED)).all()
    assert "ilqr_iteration" not in keys
    # one pass per iteration and the final one (μ's retries, if any, are eager)
    assert keys.count("ilqr_backward") >= int(comp.status.iterations.max()) + 1
    _assert_same(eager, comp)
