"""A MuJoCo model as a batched, differentiable :class:`~controllers.dynamics.System`.

:class:`MujocoSystem` wraps an ``MjModel`` (or an XML file, or a gymnasium MuJoCo env) so that the solvers of
:mod:`controllers` (iLQR, MPC, the implicit gradients) can plan on it:

* the state is ``x = [qpos (nq), qvel (nv), act (na)]`` (size ``nx``), the control ``u`` the actuator
  ``ctrl`` (size ``m = nu``, what gymnasium's ``env.step(action)`` writes into ``data.ctrl``);
* ``step(x, u, t)`` advances ``frame_skip`` MuJoCo steps with the control held, for any leading batch dims,
  in **one** ``mujoco.rollout`` call on a thread pool owned by the instance;
* ``jacobian(x, u, t)`` gives ``A = ∂x⁺/∂x``, ``B = ∂x⁺/∂u`` by batched central finite differences (all
  ``2 (n + m)`` perturbed rollouts of all batch elements in one call), for every integrator, or by
  ``mjd_transitionFD`` where it applies and is faster (``jacobian_method``);
* ``step`` is differentiable in ``x`` and ``u`` (a ``torch.autograd.Function`` whose backward uses those
  Jacobians), never in the model's parameters;
* ``rollout_states`` (a whole open-loop control sequence) and ``trajectory_jacobians`` (the Jacobians along a
  whole trajectory) are one rollout call each.

``mujoco`` is imported lazily (inside the constructor and the functions), so :mod:`controllers` imports
without it.
"""

from __future__ import annotations

import math
import os
from typing import Any

import torch

from controllers.ilqr import ILQROptions
from torchlie import quaternion as quat
from torchlie._batch import broadcast_shapes

__all__ = ["MujocoSystem"]

_T0 = 1.0  # data.time at the start of every rollout: MuJoCo's automatic reset sets time to 0 (detected)
_MAXVAL = 1e10  # mjMAXVAL: MuJoCo resets a state with a larger entry (masked before the call)
_FREE, _BALL = 0, 1  # mjtJoint values of the two joints with a quaternion in qpos
_JACOBIAN_METHODS = ("auto", "rollout", "transition_fd")


def _load_model(model: Any, owner: str):
    """``(MjModel, frame_skip of an env or None)`` from a model, an XML path or a gymnasium MuJoCo env."""
    import mujoco

    if isinstance(model, mujoco.MjModel):
        return model, None
    if isinstance(model, (str, os.PathLike)):
        return mujoco.MjModel.from_xml_path(os.fspath(model)), None
    inner = getattr(model, "unwrapped", None)
    if inner is not None and hasattr(model, "step") and hasattr(model, "action_space"):
        mm = getattr(inner, "model", None)
        if not isinstance(mm, mujoco.MjModel):
            raise TypeError(f"{owner}: the gymnasium env {type(inner).__name__} is not MuJoCo-based "
                            "(its unwrapped env has no MjModel 'model')")
        return mm, int(inner.frame_skip)
    raise TypeError(f"{owner}: argument 'model' must be a mujoco.MjModel, a path to an MJCF/URDF file or a "
                    f"gymnasium MuJoCo env, got {type(model).__name__}")


class _StepFn(torch.autograd.Function):
    """``x⁺ = step(x, u)``; backward by the finite-difference Jacobians at ``(x, u)`` (module docstring)."""

    @staticmethod
    def forward(ctx, sys: MujocoSystem, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        y = sys._simulate(x, u.unsqueeze(-2), keep_all=False)
        ctx.sys = sys
        ctx.save_for_backward(x, u, y)
        return y

    @staticmethod
    def backward(ctx, g: torch.Tensor):
        sys: MujocoSystem = ctx.sys
        x, u, y = ctx.saved_tensors
        A, B = sys._jacobians(x, u)
        gt = g if sys.euclidean else sys._point_to_tangent_cotangent(y, g)
        gx = (gt.unsqueeze(-2) @ A).squeeze(-2)
        gu = (gt.unsqueeze(-2) @ B).squeeze(-2)
        if not sys.euclidean:
            gx = sys._tangent_to_point_cotangent(x, gx)
        return None, gx, gu


class _RolloutFn(torch.autograd.Function):
    """``x_0 .. x_T`` from ``x_0`` and ``u``; backward by the adjoint recursion on the FD Jacobians."""

    @staticmethod
    def forward(ctx, sys: MujocoSystem, x0: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        xs = sys._simulate(x0, u, keep_all=True)
        ctx.sys = sys
        ctx.save_for_backward(xs, u)
        return xs

    @staticmethod
    def backward(ctx, g: torch.Tensor):
        sys: MujocoSystem = ctx.sys
        xs, u = ctx.saved_tensors
        T = u.shape[-2]
        A, B = sys._jacobians(xs[..., :T, :], u)  # (*B, T, n, n), (*B, T, n, m)
        lam = g[..., T, :]  # cotangent of x_T in point coordinates
        gu = []
        for t in range(T - 1, -1, -1):
            lt = lam if sys.euclidean else sys._point_to_tangent_cotangent(xs[..., t + 1, :], lam)
            gu.append((lt.unsqueeze(-2) @ B[..., t, :, :]).squeeze(-2))
            gx = (lt.unsqueeze(-2) @ A[..., t, :, :]).squeeze(-2)
            if not sys.euclidean:
                gx = sys._tangent_to_point_cotangent(xs[..., t, :], gx)
            lam = g[..., t, :] + gx
        return None, lam, torch.stack(gu[::-1], -2)


class MujocoSystem:
    """A MuJoCo model as a discrete-time :class:`~controllers.dynamics.System` (module docstring).

    Args:
        model: a ``mujoco.MjModel``, a path (``str``/``Path``) to an MJCF/URDF file, or a gymnasium MuJoCo
            env (``gym.make("InvertedPendulum-v5")``: its ``unwrapped.model`` and ``frame_skip``; see
            :meth:`from_env`).
            The model is used as is (not copied): changing its fields changes the system.
        frame_skip: MuJoCo steps per system step (the control is held over them); default: the env's own,
            else 1.  A value that disagrees with the env's is a ``ValueError``.
        nthread: threads of the rollout pool owned by the instance (``None``/0/1: the calling thread).
        fd_eps: the step ``h`` of the finite differences of :meth:`jacobian` (default ``1e-6`` central,
            ``1.5e-8`` ≈ ``√ε`` forward).
        fd_scheme: ``'central'`` (default: ``2 (n + m)`` perturbed steps a Jacobian, error ``~ε/h + h²``) or
            ``'forward'`` (``n + m + 1``, error ``~ε/h + h``: half the MuJoCo time for a certificate about
            1e3 times looser, :attr:`derivative_accuracy`).
        jacobian_method: ``'auto'`` (default), ``'rollout'`` or ``'transition_fd'``: how :meth:`jacobian`
            differences (*Derivatives* below).

    **State and control.**  ``x = [qpos (nq), qvel (nv), act (na)]``, a point of size ``nx = nq + nv + na``;
    ``u`` (size ``m = nu``) is ``data.ctrl`` (clamped to ``ctrlrange`` by MuJoCo where the actuator is
    ``ctrllimited``).  ``step(x, u, t)`` is ``frame_skip`` calls of ``mj_step`` from that state with time,
    warm-start and the other inputs (``qfrc_applied``, mocap, ...) at the model's defaults, exactly what
    ``env.step(u)`` does to ``data.qpos``/``data.qvel`` (to round-off: at most 4e-16 measured, Hopper's
    contacts included: the constraint solver converges fully, so the env's ``qacc_warmstart``, which ``x``
    does not carry, does not show).  ``t`` is ignored (``time_invariant``).  Results follow ``x``'s dtype
    and device (MuJoCo computes in float64 on the CPU); ``u`` must have ``x``'s dtype.

    **Manifold models.**  With quaternions in ``qpos`` (free and ball joints, ``nq > nv``) the state is not
    Euclidean: ``n = 2 nv + na`` is the tangent dimension and ``nx`` the point size; :meth:`oplus`
    (``mj_integratePos`` semantics, quaternions ``(w, x, y, z)`` times ``exp`` of the local angular
    increment) and :meth:`ominus` (``mj_differentiatePos`` semantics) move between them, and ``jacobian``
    is taken in the tangent space (``A = ∂(step(x ⊕ δx, u) ⊖ step(x, u))/∂δx``, as ``mjd_transitionFD``).
    ``controllers.ilqr`` plans on Euclidean models as is (``n == nx``, ⊕/⊖ are ``+``/``−``).  A manifold
    model plugs into the error-state planners (:mod:`controllers.manifold_mpc`): the error ``δx = x ⊖ x̄``
    about a linearization trajectory obeys ``δx⁺ ≈ A δx + B δu + (step(x̄, ū) ⊖ x̄⁺)`` with ``A, B`` from
    :meth:`trajectory_jacobians`, and a ``ManifoldSystem`` adapter has ``f(x, u) = (step(x, u) ⊖ x) / dt``
    with ``oplus`` as its ⊕.  :class:`controllers.mujoco_mpc.TangentILQR` plans on this error state directly
    (batched iterated LQ with control limits; residual ``x ⊖ x_ref``).

    **Derivatives.**  ``jacobian`` (and :meth:`trajectory_jacobians`) are central differences with step
    ``h = fd_eps`` (one-sided, inside the range, for a control within ``h`` of its ``ctrlrange``): all
    ``2 (n + m)`` perturbed rollouts of all elements in one ``mujoco.rollout`` call, for every integrator
    (``mjd_transitionFD`` refuses RK4, the integrator of gymnasium's pendulum, reacher and hopper XMLs).
    Their relative error is about ``derivative_accuracy = ε/h + h²`` (``ε`` = float64's machine epsilon:
    the rounding of the rollouts divided by ``h``, plus the truncation error of the central difference
    with unit-scale third derivatives; 2.2e-10 at the default ``h = 1e-6``); a contact that switches within
    ``h`` makes the difference a secant, as for any FD scheme.  ``fd_scheme='forward'`` takes one side
    (``n + m + 1`` rollouts: the nominal step and one perturbation per coordinate; the lower side for a
    control at its upper limit), error ``ε/h + h`` (3e-8 at its default ``h = 1.5e-8``):
    :meth:`ilqr_options` then certifies at ``tol_kkt = 3e-5``, not 1e-6.

    **Fast path** (``jacobian_method``): for the integrators ``mjd_transitionFD`` accepts (Euler, implicit,
    implicitfast and, in MuJoCo 4, discrete; not RK4) the same centred differences come from one
    ``mjd_transitionFD`` call per element and MuJoCo step (it skips the position stages for velocity and
    control perturbations), in the same tangent coordinates; for ``frame_skip = k > 1`` the substep states
    come from one rollout call and the per-substep Jacobians are chained, ``A = A_{k-1}···A_0``,
    ``B = Σ_s A_{k-1}···A_{s+1} B_s`` (a Python loop over elements and substeps, of C calls only).  Both
    paths agree to FD accuracy (1e-12 relative at ``k = 1``, ≤ 6e-10 at ``k = 2, 5``).  Measured (2 CPU
    cores shared with other jobs, one thread, interleaved best of 9; Euler copies of InvertedPendulum and
    Reacher, and the free body of ``examples/mujoco_free_body_mpc.py``), rollout time / transition_fd
    time per ``jacobian`` call, batch 1 and 64: ``k = 1``: pendulum 2.6 / 1.5, reacher 2.4 / 1.6, free
    body 8.7 / 2.1; ``k = 2``: 1.0 / 1.1, 1.1 / 1.3, 3.7 / 1.7; ``k = 5``: 0.97 / 1.14, 1.13 / 1.31,
    2.7 / 1.6 (the rollout path also pays the torch ``⊕``/``⊖`` of the perturbed states, which is what
    makes quaternion models gain most).  So ``'auto'`` (the default) takes ``mjd_transitionFD`` whenever
    the integrator allows it and there is no thread pool (nor disabled clamping of a limited control),
    at every ``frame_skip`` and batch size (a
    choice by batch size would make batched and per-element Jacobians differ at FD accuracy), and the rollouts
    otherwise: always for RK4 (every gymnasium XML) and with ``nthread > 1``, where the rollouts run in
    parallel and the loop would not (that case not measured); ``'rollout'`` and ``'transition_fd'`` force
    one path (the latter refuses RK4, a ``ValueError``).
    :meth:`uses_transition_fd` says which one a call takes.

    ``step`` and :meth:`rollout_states` are differentiable
    in ``x`` and ``u`` (``torch.autograd.Function`` s whose backward applies these Jacobians, by the adjoint
    recursion along a rollout): gradients flow to ``x0``, costs and whatever produced the controls — but
    not to the model's parameters (masses, lengths, ...: MuJoCo's own ``MjModel`` is not a tensor), and the
    backward is not differentiable again (second derivatives of the dynamics are zero to autograd, so an
    implicit iLQR gradient uses the Gauss–Newton Hessian of the dynamics).

    **Bad input.**  ``x`` or ``u`` of the wrong size is a ``ValueError`` naming ``nx``/``m`` and the
    model; a batch element with a NaN/inf in ``x`` or ``u`` (or an entry of ``x`` above MuJoCo's 1e10), or
    whose simulation diverges (MuJoCo then warns, writes ``MUJOCO_LOG.TXT`` and resets it; the reset is
    detected from its clock), gives NaN for that element only: bad rows are replaced by the model's default
    state before the call (no MuJoCo warning for them), and every element is its own rollout (on the
    ``mjd_transitionFD`` path a divergence inside the call is detected from MuJoCo's bad-qacc warning
    counter).
    """

    time_invariant = True

    def __init__(self, model: Any, frame_skip: int | None = None, nthread: int | None = None,
                 fd_eps: float | None = None, jacobian_method: str = "auto",
                 fd_scheme: str = "central") -> None:
        import mujoco
        from mujoco import rollout as mj_rollout

        own = "MujocoSystem"
        mm, env_fs = _load_model(model, own)
        if frame_skip is None:
            frame_skip = 1 if env_fs is None else env_fs
        elif env_fs is not None and frame_skip != env_fs:
            raise ValueError(f"{own}: frame_skip={frame_skip!r} disagrees with the env's own frame_skip="
                             f"{env_fs}; leave it None to take the env's")
        if not isinstance(frame_skip, int) or isinstance(frame_skip, bool) or frame_skip < 1:
            raise ValueError(f"{own}: argument 'frame_skip' must be an int >= 1, got {frame_skip!r}")
        if nthread is not None and (not isinstance(nthread, int) or isinstance(nthread, bool) or nthread < 0):
            raise ValueError(f"{own}: argument 'nthread' must be None or an int >= 0, got {nthread!r}")
        if fd_scheme not in ("central", "forward"):
            raise ValueError(f"{own}: argument 'fd_scheme' must be 'central' or 'forward', got {fd_scheme!r}")
        if fd_eps is None:
            fd_eps = 1e-6 if fd_scheme == "central" else 1.5e-8
        if isinstance(fd_eps, bool) or not isinstance(fd_eps, (int, float)) or not (0.0 < fd_eps < 1.0):
            raise ValueError(f"{own}: argument 'fd_eps' must be a float in (0, 1), got {fd_eps!r}")
        if jacobian_method not in _JACOBIAN_METHODS:
            raise ValueError(f"{own}: argument 'jacobian_method' must be one of {_JACOBIAN_METHODS}, "
                             f"got {jacobian_method!r}")
        rk4 = int(mm.opt.integrator) == int(mujoco.mjtIntegrator.mjINT_RK4)
        if jacobian_method == "transition_fd" and rk4:
            raise ValueError(f"{own}: jacobian_method='transition_fd' needs an integrator that "
                             "mujoco.mjd_transitionFD supports (not RK4, the model's); "
                             "use 'auto' or 'rollout'")
        self.jacobian_method = jacobian_method
        self.model, self.frame_skip, self.fd_eps, self.fd_scheme = mm, frame_skip, float(fd_eps), fd_scheme
        self.nthread = 0 if nthread is None or nthread < 2 else nthread
        self.name = mm.names.split(b"\0", 1)[0].decode() or "unnamed"
        self.nq, self.nv, self.na, self.m = mm.nq, mm.nv, mm.na, mm.nu
        self.nx, self.n = self.nq + self.nv + self.na, 2 * self.nv + self.na
        self.euclidean = self.nq == self.nv
        self.dt = float(mm.opt.timestep) * frame_skip
        self._init_state(mujoco)
        self._init_joints()
        self._datas = [mujoco.MjData(mm) for _ in range(max(self.nthread, 1))]
        self._pool = mj_rollout.Rollout(nthread=self.nthread)

    @classmethod
    def from_env(cls, env: Any, nthread: int | None = None, fd_eps: float | None = None,
                 jacobian_method: str = "auto", fd_scheme: str = "central") -> MujocoSystem:
        """The system of a gymnasium MuJoCo env (its ``unwrapped.model`` and ``frame_skip``)."""
        if isinstance(env, (str, os.PathLike)) or not hasattr(env, "unwrapped"):
            raise TypeError(f"MujocoSystem.from_env: argument 'env' must be a gymnasium MuJoCo env, "
                            f"got {type(env).__name__}")
        return cls(env, nthread=nthread, fd_eps=fd_eps, jacobian_method=jacobian_method, fd_scheme=fd_scheme)

    def _init_state(self, mujoco) -> None:
        """The template full-physics state (defaults, time ``_T0``) and the control limits."""
        mm = self.model
        self._spec = int(mujoco.mjtState.mjSTATE_FULLPHYSICS)
        d = mujoco.MjData(mm)
        mujoco.mj_resetData(mm, d)
        s = torch.empty(mujoco.mj_stateSize(mm, self._spec), dtype=torch.float64)
        mujoco.mj_getState(mm, d, s.numpy(), self._spec)
        s[0] = _T0
        self._template = s
        self._nsensor = mm.nsensordata
        clamp = not (mm.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_CLAMPCTRL))
        lim = torch.as_tensor(mm.actuator_ctrllimited, dtype=torch.bool) & clamp
        rng = torch.as_tensor(mm.actuator_ctrlrange, dtype=torch.float64).reshape(self.m, 2)
        inf = torch.tensor(math.inf, dtype=torch.float64)
        self.ctrl_lower = torch.where(lim, rng[:, 0], -inf)
        self.ctrl_upper = torch.where(lim, rng[:, 1], inf)

    def _init_joints(self) -> None:
        """Index maps of qpos/qvel: Euclidean coordinates and quaternion blocks (free and ball joints)."""
        mm = self.model
        pe, de, pq, dq = [], [], [], []
        for j in range(mm.njnt):
            typ, pa, da = int(mm.jnt_type[j]), int(mm.jnt_qposadr[j]), int(mm.jnt_dofadr[j])
            if typ == _FREE:
                pe += range(pa, pa + 3)
                de += range(da, da + 3)
                pq.append(list(range(pa + 3, pa + 7)))
                dq.append(list(range(da + 3, da + 6)))
            elif typ == _BALL:
                pq.append(list(range(pa, pa + 4)))
                dq.append(list(range(da, da + 3)))
            else:  # hinge, slide: one coordinate each
                pe.append(pa)
                de.append(da)
        long = dict(dtype=torch.long)
        self._pe, self._de = torch.tensor(pe, **long), torch.tensor(de, **long)
        self._pq = torch.tensor(pq, **long).reshape(-1, 4)
        self._dq = torch.tensor(dq, **long).reshape(-1, 3)

    def close(self) -> None:
        """Shut the rollout thread pool down (the instance cannot step afterwards)."""
        if self._pool is not None:
            self._pool.close()
            self._pool = None

    def __repr__(self) -> str:
        return (f"MujocoSystem(model={self.name!r}, nx={self.nx}, n={self.n}, m={self.m}, "
                f"frame_skip={self.frame_skip}, dt={self.dt:g}, nthread={self.nthread}, "
                f"jacobian_method={self.jacobian_method!r})")

    # ----------------------------------------------------------------------------------------------
    # accuracy of the derivatives and solver settings that respect it
    # ----------------------------------------------------------------------------------------------

    @property
    def derivative_accuracy(self) -> float:
        """Relative error estimate of the FD Jacobians (class docstring; ``h = fd_eps``): ``ε/h + h²``
        central, ``ε/h + h`` forward."""
        h = self.fd_eps
        return torch.finfo(torch.float64).eps / h + (h * h if self.fd_scheme == "central" else h)

    def ilqr_options(self, dtype: torch.dtype = torch.float64, **overrides: Any) -> ILQROptions:
        """:class:`~controllers.ilqr.ILQROptions` whose tolerances are no tighter than the FD Jacobians allow.

        ``tol_kkt = max(default, 1e3 · derivative_accuracy)`` and ``tol = max(default, 10 ·
        derivative_accuracy)`` (defaults of :class:`~controllers.ilqr.ILQROptions` for ``dtype``): the KKT
        certificate is evaluated with the same inexact ``B_tᵀ λ``, whose relative error grows with the horizon
        and the conditioning of the costate recursion, hence the margin.  ``overrides`` replace any field
        (e.g. ``max_iter=20``).  At the default ``fd_eps`` (accuracy 2.2e-10) these are the float64 defaults.

        Measured (InvertedPendulum-v5, horizon 25, 16 starts x 10 MPC steps, ``u ∈ [-3, 3]``, max_iter 50):
        ``fd_eps = 1e-9`` (accuracy 2.2e-7): default options 119 CONVERGED / 12 STALLED / 29
        MAX_ITERATIONS (19.7 s per MPC step), these options 156 CONVERGED / 4 STALLED (1.9 s).  At
        ``fd_eps = 1e-6`` the defaults give 152 CONVERGED / 8 STALLED; those 8 stall with a KKT residual of
        1-4e-6 that does not change with ``fd_eps`` from 1e-7 to 1e-5 — near the upright equilibrium, where
        ``‖u‖∞ ≪ 1``, the solver's step test ``tol · (1 + ‖u‖∞)`` is absolute while ``tol_kkt`` is relative:
        not a derivative-accuracy effect.
        """
        single = dtype not in (torch.float64,)
        acc = self.derivative_accuracy
        fields = dict(tol_kkt=max(1e-3 if single else 1e-6, 1e3 * acc),
                      tol=max(1e-4 if single else 1e-8, 10 * acc))
        fields.update(overrides)
        return ILQROptions(**fields)

    # ----------------------------------------------------------------------------------------------
    # checks and the one place where MuJoCo runs
    # ----------------------------------------------------------------------------------------------

    def _check(self, fn: str, x: torch.Tensor, u: torch.Tensor, u_dims: int = 1, x_name: str = "x") -> None:
        """``ValueError``/``TypeError`` naming the argument unless ``x (*B, nx)``, ``u (*B, [T,] m)``."""
        for name, v in ((x_name, x), ("u", u)):
            if not isinstance(v, torch.Tensor) or not v.dtype.is_floating_point:
                raise TypeError(f"MujocoSystem.{fn}: argument '{name}' must be a floating tensor, "
                                f"got {v.dtype if isinstance(v, torch.Tensor) else type(v).__name__}")
        if x.dim() < 1 or x.shape[-1] != self.nx:
            raise ValueError(f"MujocoSystem.{fn}: argument '{x_name}' must have shape (*B, {self.nx}) "
                             f"(nx = nq + nv + na = {self.nq} + {self.nv} + {self.na} of model "
                             f"'{self.name}'), got {tuple(x.shape)}")
        want = f"(*B, T, {self.m})" if u_dims == 2 else f"(*B, {self.m})"
        if u.dim() < u_dims or u.shape[-1] != self.m:
            raise ValueError(f"MujocoSystem.{fn}: argument 'u' must have shape {want} "
                             f"(m = nu of model '{self.name}'), got {tuple(u.shape)}")
        if u.dtype != x.dtype:
            raise TypeError(f"MujocoSystem.{fn}: argument 'u' has dtype {u.dtype}, '{x_name}' has {x.dtype}")

    def _run(self, xf: torch.Tensor, uf: torch.Tensor, substeps: bool = False) -> torch.Tensor:
        """States after each of ``T`` system steps, ``(N, T, nx)`` float64, from ``xf (N, nx)`` and
        ``uf (N, T, m)`` (float64, CPU): one ``mujoco.rollout`` call of ``T · frame_skip`` MuJoCo steps
        (``substeps``: after every MuJoCo step, ``(N, T · frame_skip, nx)``).
        NaN for rows with a non-finite (or > 1e10) state, a non-finite control, or that diverged (MuJoCo's
        reset restarts the clock)."""
        N, T, fs = uf.shape[0], uf.shape[1], self.frame_skip
        if self._pool is None:
            raise RuntimeError("MujocoSystem: the rollout pool was closed (close()); build a new system")
        nan = torch.full((), math.nan, dtype=torch.float64)
        if N == 0 or T == 0:
            return xf.new_empty(N, T * fs if substeps else T, self.nx)
        ok = (xf.abs() <= _MAXVAL).all(-1) & torch.isfinite(uf).flatten(1).all(-1)  # NaN fails too
        init = self._template.expand(N, -1).clone()
        init[:, 1:1 + self.nx] = torch.where(ok[:, None], xf, self._template[1:1 + self.nx])
        ctrl = torch.where(ok[:, None, None], uf, 0.0)
        ctrl = (ctrl.repeat_interleave(fs, dim=1) if fs > 1 else ctrl).contiguous()
        import numpy as np

        state = np.empty((N, T * fs, init.shape[1]))
        sensor = np.empty((N, T * fs, self._nsensor))
        self._pool.rollout([self.model] * N, self._datas, init.numpy(), ctrl.numpy(), skip_checks=True,
                           nstep=T * fs, state=state, sensordata=sensor)
        every = 1 if substeps else fs
        st = torch.from_numpy(state)[:, every - 1::every, :]
        ts = self.model.opt.timestep
        expected = _T0 + ts * every * torch.arange(1, st.shape[1] + 1, dtype=torch.float64)
        diverged = ((st[..., 0] - expected).abs() > 0.5 * ts).cummax(-1).values
        good = ok[:, None] & ~diverged
        return torch.where(good[..., None], st[..., 1:1 + self.nx], nan)

    def _simulate(self, x: torch.Tensor, u: torch.Tensor, keep_all: bool) -> torch.Tensor:
        """From ``x (*B, nx)`` under ``u (*B, T, m)``: ``(*B, T+1, nx)`` (``keep_all``) or the last state."""
        bs = broadcast_shapes(x.shape[:-1], u.shape[:-2])
        T = u.shape[-2]
        f64 = dict(dtype=torch.float64, device="cpu")
        xf = x.detach().expand(*bs, self.nx).reshape(-1, self.nx).to(**f64)
        uf = u.detach().expand(*bs, T, self.m).reshape(xf.shape[0], T, self.m).to(**f64)  # T or m may be 0
        out = self._run(xf, uf)
        if keep_all:
            out = torch.cat([xf.unsqueeze(1), out], 1).reshape(*bs, T + 1, self.nx)
        else:
            out = out[:, -1, :].reshape(*bs, self.nx)
        return out.to(dtype=x.dtype, device=x.device)

    def _fd_jacobians(self, x: torch.Tensor, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Finite differences (``fd_scheme``) ``A (*B, n, n)``, ``B (*B, n, m)`` at ``x (*B, nx)``,
        ``u (*B, m)``: all perturbed steps of all elements in one rollout call."""
        bs = broadcast_shapes(x.shape[:-1], u.shape[:-1])
        f64 = dict(dtype=torch.float64, device="cpu")
        xf = x.detach().expand(*bs, self.nx).reshape(-1, self.nx).to(**f64)
        uf = u.detach().expand(*bs, self.m).reshape(xf.shape[0], self.m).to(**f64)
        N, n, m, h = xf.shape[0], self.n, self.m, self.fd_eps
        E = torch.eye(n, dtype=torch.float64) * h
        lo, hi = self.ctrl_lower, self.ctrl_upper
        up = torch.where(uf <= hi, torch.minimum(uf + h, hi), uf + h)  # inside ctrlrange where u is
        dn = torch.where(uf >= lo, torch.maximum(uf - h, lo), uf - h)
        if self.fd_scheme == "forward":  # one side per coordinate (the lower one for a control at its top)
            up = torch.where(up > uf, up, dn)
            xs = torch.cat([self.oplus(xf[:, None, :], E), xf[:, None, :].expand(N, m + 1, self.nx)], 1)
            Uup = uf[:, None, :] + torch.diag_embed(up - uf)
            us = torch.cat([uf[:, None, :].expand(N, n, m), Uup, uf[:, None, :]], 1)
            k = n + m + 1
        else:
            xs = torch.cat([self.oplus(xf[:, None, :], E), self.oplus(xf[:, None, :], -E),
                            xf[:, None, :].expand(N, 2 * m, self.nx)], 1)
            Uup = uf[:, None, :] + torch.diag_embed(up - uf)
            Udn = uf[:, None, :] + torch.diag_embed(dn - uf)
            us = torch.cat([uf[:, None, :].expand(N, 2 * n, m), Uup, Udn], 1)
            k = 2 * (n + m)
        Y = self._run(xs.reshape(N * k, self.nx), us.reshape(N * k, 1, m))[:, 0].reshape(N, k, self.nx)
        if self.fd_scheme == "forward":
            y0 = Y[:, -1:]
            A = self.ominus(Y[:, :n], y0.expand(N, n, self.nx)).mT / h
            du = up - uf
            B = (self.ominus(Y[:, n:n + m], y0.expand(N, m, self.nx)) / du[..., None]).mT
        else:
            A = self.ominus(Y[:, :n], Y[:, n:2 * n]).mT / (2 * h)
            du = torch.diagonal(Uup, dim1=-2, dim2=-1) - torch.diagonal(Udn, dim1=-2, dim2=-1)
            B = (self.ominus(Y[:, 2 * n:2 * n + m], Y[:, 2 * n + m:]) / du[..., None]).mT
        kw = dict(dtype=x.dtype, device=x.device)
        return A.reshape(*bs, n, n).to(**kw), B.reshape(*bs, n, m).to(**kw)

    def uses_transition_fd(self) -> bool:
        """Whether :meth:`jacobian` takes the ``mjd_transitionFD`` path now (class docstring, *Derivatives*):
        ``jacobian_method='transition_fd'``, or ``'auto'`` with a supported integrator (not RK4), control
        clamping not disabled where an actuator is ``ctrllimited`` (``mjd_transitionFD`` would still keep
        its perturbations inside ``ctrlrange``: a zero column for a control beyond it) and no thread pool
        (``nthread`` 0/1).  Read at every call: the model's options may have been changed."""
        import mujoco

        mm = self.model
        rk4 = int(mm.opt.integrator) == int(mujoco.mjtIntegrator.mjINT_RK4)
        # mjd_transitionFD keeps a ctrllimited control's perturbations inside ctrlrange (zero column outside)
        # even where the model's clamping is disabled (mjDSBL_CLAMPCTRL) and such a control acts unclamped
        unclamped = bool(mm.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_CLAMPCTRL)) and bool(
            mm.actuator_ctrllimited.any())
        if self.jacobian_method == "transition_fd":
            if rk4 or unclamped:
                why = "integrator is now RK4" if rk4 else "control clamping is disabled (mjDSBL_CLAMPCTRL)"
                raise ValueError(f"MujocoSystem: jacobian_method='transition_fd' but the model's {why}, "
                                 "where mujoco.mjd_transitionFD does not apply; use 'auto' or 'rollout'")
            return True
        return self.jacobian_method == "auto" and not rk4 and not unclamped and self.nthread == 0

    def _jacobians(self, x: torch.Tensor, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``A (*B, n, n)``, ``B (*B, n, m)`` by the path :meth:`uses_transition_fd` picks."""
        return self._tfd_jacobians(x, u) if self.uses_transition_fd() else self._fd_jacobians(x, u)

    def _tfd_jacobians(self, x: torch.Tensor, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``mjd_transitionFD`` (centred or forward by ``fd_scheme``, step ``fd_eps``) per element and
        MuJoCo step, chained over the
        ``frame_skip`` substeps: ``A = A_{k-1}···A_0``, ``B = Σ_s A_{k-1}···A_{s+1} B_s`` at the substep
        states of one rollout call (skipped for ``frame_skip = 1``).  NaN for bad or diverging elements."""
        import mujoco
        import numpy as np

        bs = broadcast_shapes(x.shape[:-1], u.shape[:-1])
        f64 = dict(dtype=torch.float64, device="cpu")
        xf = x.detach().expand(*bs, self.nx).reshape(-1, self.nx).to(**f64)
        uf = u.detach().expand(*bs, self.m).reshape(xf.shape[0], self.m).to(**f64)
        N, n, m, fs, nx = xf.shape[0], self.n, self.m, self.frame_skip, self.nx
        ok = (xf.abs() <= _MAXVAL).all(-1) & torch.isfinite(uf).all(-1)
        x0 = torch.where(ok[:, None], xf, self._template[1:1 + nx])
        u0 = torch.where(ok[:, None], uf, 0.0)
        if fs > 1:  # the states at the start of substeps 1 .. fs-1
            sub = self._run(x0, u0[:, None, :], substeps=True)[:, :fs - 1]
            ok &= torch.isfinite(sub).flatten(1).all(-1)
            xs = torch.cat([x0[:, None], torch.where(ok[:, None, None], sub, self._template[1:1 + nx])], 1)
        else:
            xs = x0[:, None]
        st = self._template.expand(N, fs, -1).clone()
        st[..., 1:1 + nx] = xs
        st[..., 0] = _T0 + self.model.opt.timestep * torch.arange(fs, dtype=torch.float64)
        An, Bn = np.zeros((N, fs, n, n)), np.zeros((N, fs, n, m))
        stn, un, okn = st.numpy(), u0.numpy(), ok.numpy().copy()
        mm, d, h, spec = self.model, self._datas[0], self.fd_eps, self._spec
        centred = self.fd_scheme == "central"
        badqacc = d.warning[int(mujoco.mjtWarning.mjWARN_BADQACC)]
        tfd, set_state = mujoco.mjd_transitionFD, mujoco.mj_setState
        for i in range(N):  # one C call per element and substep (cheaper than 2 (n + m) rollouts of it)
            if not okn[i]:
                continue
            for k in range(fs):
                set_state(mm, d, stn[i, k], spec)
                d.ctrl[:] = un[i]
                before = badqacc.number
                tfd(mm, d, h, centred, An[i, k], Bn[i, k], None, None)
                if badqacc.number != before:  # MuJoCo reset a diverging state inside the call
                    okn[i] = False
        A, B = torch.from_numpy(An[:, 0]), torch.from_numpy(Bn[:, 0])
        for k in range(1, fs):
            Ak = torch.from_numpy(An[:, k])
            A, B = Ak @ A, Ak @ B + torch.from_numpy(Bn[:, k])
        good = torch.from_numpy(okn)[:, None, None]
        A, B = torch.where(good, A, math.nan), torch.where(good, B, math.nan)
        kw = dict(dtype=x.dtype, device=x.device)
        return A.reshape(*bs, n, n).to(**kw), B.reshape(*bs, n, m).to(**kw)

    # ----------------------------------------------------------------------------------------------
    # the System protocol and the batched trajectory calls
    # ----------------------------------------------------------------------------------------------

    def step(self, x: torch.Tensor, u: torch.Tensor, t: int = 0) -> torch.Tensor:
        """``x⁺ (*B, nx)`` after ``frame_skip`` MuJoCo steps from ``x (*B, nx)`` with ``u (*B, m)`` held
        (batch dims broadcast; one rollout call).  Differentiable in ``x`` and ``u`` (class docstring)."""
        self._check("step", x, u)
        if torch.is_grad_enabled() and (x.requires_grad or u.requires_grad):
            bs = broadcast_shapes(x.shape[:-1], u.shape[:-1])
            return _StepFn.apply(self, x.expand(*bs, self.nx), u.expand(*bs, self.m))
        return self._simulate(x, u.unsqueeze(-2), keep_all=False)

    def jacobian(self, x: torch.Tensor, u: torch.Tensor, t: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
        """Tangent-space ``A = ∂x⁺/∂x (*B, n, n)``, ``B = ∂x⁺/∂u (*B, n, m)`` by finite differences
        (class docstring; no graph: constants to autograd)."""
        self._check("jacobian", x, u)
        return self._jacobians(x, u)

    def rollout_states(self, x0: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """Open-loop ``x (*B, T+1, nx)`` (``x_0 = x0``) from ``x0 (*B, nx)`` and ``u (*B, T, m)``, each
        ``u_t`` held for ``frame_skip`` MuJoCo steps: one rollout call of ``T · frame_skip`` steps for all
        elements.  Differentiable in ``x0`` and ``u`` (backward: the adjoint recursion on
        :meth:`trajectory_jacobians`)."""
        self._check("rollout_states", x0, u, u_dims=2, x_name="x0")
        if torch.is_grad_enabled() and (x0.requires_grad or u.requires_grad):
            bs = broadcast_shapes(x0.shape[:-1], u.shape[:-2])
            return _RolloutFn.apply(self, x0.expand(*bs, self.nx), u.expand(*bs, *u.shape[-2:]))
        return self._simulate(x0, u, keep_all=True)

    def trajectory_jacobians(self, x: torch.Tensor, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Batch-first ``A (*B, T, n, n)``, ``B (*B, T, n, m)`` along ``x (*B, T+1 or T, nx)``,
        ``u (*B, T, m)`` (steps ``0 .. T-1``): one rollout call (time folded into the batch).  For the
        time-major layout of :func:`controllers.dynamics.trajectory_jacobians` use ``A.movedim(-3, 0)``."""
        self._check("trajectory_jacobians", x, u, u_dims=2)
        T = u.shape[-2]
        if x.dim() < 2 or x.shape[-2] not in (T, T + 1):
            raise ValueError(f"MujocoSystem.trajectory_jacobians: argument 'x' must have shape (*B, {T}+1 or "
                             f"{T}, {self.nx}) to match u {tuple(u.shape)}, got {tuple(x.shape)}")
        return self._jacobians(x[..., :T, :], u)

    # ----------------------------------------------------------------------------------------------
    # the state space: ⊕ / ⊖ (mj_integratePos / mj_differentiatePos) in torch
    # ----------------------------------------------------------------------------------------------

    def oplus(self, x: torch.Tensor, dx: torch.Tensor) -> torch.Tensor:
        """``x ⊕ dx (*B, nx)`` for a point ``x (*B, nx)`` and a tangent ``dx (*B, n)`` (batch dims broadcast).

        ``qpos`` as ``mj_integratePos(qpos, dq, 1)``: Euclidean coordinates (hinge, slide, a free joint's
        position) add; a quaternion ``q`` ``(w, x, y, z)`` becomes ``normalize(q) ⊗ exp(ω)`` with ``ω`` the
        local (body-frame) rotation vector; ``qvel`` and ``act`` add.  Differentiable (torch ops)."""
        if self.euclidean:
            return x + dx
        bs = broadcast_shapes(x.shape[:-1], dx.shape[:-1])
        x, dx = x.expand(*bs, self.nx), dx.expand(*bs, self.n)
        nq, nv = self.nq, self.nv
        qpos, dq = x[..., :nq], dx[..., :nv]
        dev = x.device
        pos = qpos[..., self._pe.to(dev)] + dq[..., self._de.to(dev)]
        q = quat.normalize(qpos[..., self._pq.to(dev)])
        qn = quat.multiply(q, quat.exp(dq[..., self._dq.to(dev)]))
        new = torch.zeros_like(qpos).index_copy(-1, self._pe.to(dev), pos)
        new = new.index_copy(-1, self._pq.reshape(-1).to(dev), qn.flatten(-2))
        return torch.cat([new, x[..., nq:] + dx[..., nv:]], -1)

    def ominus(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """``x ⊖ y (*B, n)`` for points ``x``, ``y (*B, nx)``: the tangent with ``y ⊕ (x ⊖ y) = x`` (up to the
        sign of the quaternions, ``q`` and ``−q`` being one rotation).

        ``qpos`` as ``mj_differentiatePos(dq, 1, y, x)``: Euclidean coordinates subtract, a quaternion pair
        gives ``log(ȳ ⊗ x)``, the principal rotation vector (angle ≤ π; scale-invariant in both);
        ``qvel`` and ``act`` subtract.  Differentiable (torch ops)."""
        if self.euclidean:
            return x - y
        bs = broadcast_shapes(x.shape[:-1], y.shape[:-1])
        x, y = x.expand(*bs, self.nx), y.expand(*bs, self.nx)
        nq, nv, dev = self.nq, self.nv, x.device
        pe, pq = self._pe.to(dev), self._pq.to(dev)
        d_pos = x[..., pe] - y[..., pe]
        d_rot = quat.log(quat.multiply(quat.conjugate(y[..., pq]), x[..., pq]))
        new = x.new_zeros(*bs, nv).index_copy(-1, self._de.to(dev), d_pos)
        new = new.index_copy(-1, self._dq.reshape(-1).to(dev), d_rot.flatten(-2))
        return torch.cat([new, x[..., nq:] - y[..., nq:]], -1)

    def _point_to_tangent_cotangent(self, y: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
        """``g ∂(y ⊕ δ)/∂δ|₀ (*B, n)`` for a cotangent ``g (*B, nx)`` at the point ``y``."""
        with torch.enable_grad():
            d = torch.zeros(*y.shape[:-1], self.n, dtype=y.dtype, device=y.device, requires_grad=True)
            (out,) = torch.autograd.grad(self.oplus(y.detach(), d), d, g)
        return out

    def _tangent_to_point_cotangent(self, x: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
        """``h ∂(z ⊖ x)/∂z|_{z=x} (*B, nx)`` for a tangent cotangent ``h (*B, n)`` at the point ``x``."""
        with torch.enable_grad():
            z = x.detach().clone().requires_grad_(True)
            (out,) = torch.autograd.grad(self.ominus(z, x.detach()), z, h)
        return out
