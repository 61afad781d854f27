"""End-effector pose tracking MPC with twist inputs, in three formulations on the same QP (issue 11 §4).

The plant is a pose ``X ∈ SE(3)`` driven by body twists ``T = [v, ω]`` (``X_{k+1} = X_k exp(Δt T_k)``,
seed 000 Eq. 6); the MPC tracks a reference ``X*_0 … X*_N`` with reference twists ``T*_0 … T*_{N-1}``::

    min_T  Σ_{k<N} ‖e_k‖²_Q + ‖T_k − T*_k‖²_R + ‖e_N‖²_P      T_lower ≤ T_k ≤ T_upper

The three ``frame`` s differ in the state they predict and hence in the error ``e_k``:

``"world"`` (seed 000, the paper's Eq. 16 as Eq. 5)
    state ``ξ = log X ∈ R⁶`` and the *linear* model ``ξ_{k+1} = ξ_k + Δt D T_k`` with ``D = dexp⁻¹_{ξ_0}``
    (the order-2 Bernoulli series, ME2, or the closed form ``J_r(ξ_0)⁻¹`` with ``order=None``) frozen at the
    current pose ``ξ_0``; ``e_k = ξ_k − log X*_k``.  A linear MPC: the QP is exact for the model.  Its
    weak spot is ``log`` itself: near rotation angle π (the cut locus, where every tool-down orientation
    of an arm sits) two nearby poses can have logarithms 2π apart, and the MPC then turns the long way.
``"local"`` (ME2 in the local frame)
    ``X = X_0 exp(Ω)`` about the *current* pose, ``Ω_0 = 0`` and the ME2 recursion
    ``Ω_{k+1} = Ω_k + Δt dexp⁻¹_series(Ω_k) T_k`` (seed 000 Eq. 13); ``e_k = Ω_k − log(X_0⁻¹ X*_k)``.
    Bilinear in ``(Ω, T)``: linearized about the reference (time-varying ``A_k``, ``B_k``, Algorithm 1
    of seed 003 on R⁶).  ``Ω`` stays small over a horizon, so it has no cut-locus problem.
``"se3"`` (seed 003 Algorithm 1 on SE(3))
    the error state ``e_k = X_k ⊟ X*_k = log(X*_k⁻¹ X_k)`` on the exact model, linearized about the
    reference with the closed-form ``G_x = Ad_{exp(−Δt T*)}``, ``G_f = J_r(Δt T*)``.

All three are :class:`~controllers.manifold_mpc.ErrorStateMPC` s (one solver: the condensed box QP, the
closed form when no limit binds, the certified :func:`~controllers.boxqp.box_qp` otherwise), so they are
batched, return per-element statuses and are differentiable in the poses, twists and weights.

A bound on the twist *magnitude* (``‖v‖ ≤ v_max``, ``‖ω‖ ≤ ω_max``) is not a box; :func:`twist_box`
gives the inscribed box ``|v_i| ≤ v_max/√3``, ``|ω_i| ≤ ω_max/√3``, which guarantees the magnitudes.
"""

from __future__ import annotations

import copy
import math

import torch
from torch import Tensor

from controllers._validate import all_finite, broadcast_batch
from controllers.manifold_mpc import ErrorStateMPC, ErrorStateSolution
from controllers.problem import GradMode
from torchlie import magnus, se3
from torchlie._batch import broadcast_shapes
from torchlie.manifolds import SE3, Rn

__all__ = ["FRAMES", "BodyTwistSE3", "ME2WorldModel", "ME2LocalModel", "PoseMPC", "twist_box"]

FRAMES = ("world", "local", "se3")


def _matvec(D: Tensor, u: Tensor) -> Tensor:
    """``D (*B, d, d)`` applied to ``u (*B, …, d)`` (any extra axes of ``u`` after ``*B``)."""
    extra = u.dim() - 1 - (D.dim() - 2)
    D = D.reshape(*D.shape[:-2], *(1,) * max(extra, 0), *D.shape[-2:])
    return (D @ u.unsqueeze(-1)).squeeze(-1)


class BodyTwistSE3:
    """A pose driven by its body twist: ``X ⊕ Δt T = X exp(Δt T)`` on SE(3) (``f(X, T) = T``)."""

    m = 6

    def __init__(self, dt: float):
        self.manifold, self.n, self.dt = SE3(), 6, float(dt)

    def f(self, x: Tensor, u: Tensor) -> Tensor:
        return u

    def f_jacobians(self, x: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        eye = torch.eye(6, dtype=u.dtype, device=u.device)
        return u.new_zeros(*u.shape, 6), eye.expand(*u.shape[:-1], 6, 6)


class ME2WorldModel:
    """Seed 000 Eq. 16 as a system on R⁶: ``ξ ⊕ Δt T = ξ + Δt D T``, ``D = dexp⁻¹_{ξ_0}`` frozen at
    ``xi0 (*B, 6)`` (the order-``order`` series, or the closed form ``J_r(ξ_0)⁻¹`` for ``order=None``)."""

    m = 6

    def __init__(self, xi0: Tensor, dt: float, order: int | None = 2):
        self.manifold, self.n, self.dt = Rn(6), 6, float(dt)
        self.D = magnus.dexp_inv(xi0) if order is None else magnus.dexp_inv_series(xi0, order)

    def f(self, x: Tensor, u: Tensor) -> Tensor:
        return _matvec(self.D, u)

    def f_jacobians(self, x: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        batch = broadcast_shapes(x.shape[:-1], u.shape[:-1])
        extra = len(batch) - (self.D.dim() - 2)
        D = self.D.reshape(*self.D.shape[:-2], *(1,) * max(extra, 0), 6, 6)
        return u.new_zeros(*batch, 6, 6), D.expand(*batch, 6, 6)


class ME2LocalModel:
    """The local-frame ME2 recursion as a system on R⁶: ``Ω ⊕ Δt T = Ω + Δt Σ_{n≤order} c_n ad_Ω^n T``
    (``X = X_0 exp(Ω)``; seed 000 Eq. 13), with analytic Jacobians
    (:func:`torchlie.magnus.linearize_local`)."""

    m = 6

    def __init__(self, dt: float, order: int = 2):
        self.manifold, self.n, self.dt, self.order = Rn(6), 6, float(dt), int(order)

    def f(self, x: Tensor, u: Tensor) -> Tensor:
        return _matvec(magnus.dexp_inv_series(x, self.order), u)

    def f_jacobians(self, x: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        x, u = torch.broadcast_tensors(x, u)
        A, B = magnus.linearize_local(x, u, 1.0, self.order)
        return A - torch.eye(6, dtype=A.dtype, device=A.device), B


def twist_box(v_max: float, w_max: float, *, dtype: torch.dtype = torch.float64, device=None
              ) -> tuple[Tensor, Tensor]:
    """``(lower, upper)`` ``(6,)``: the box inscribed in ``‖v‖ ≤ v_max``, ``‖ω‖ ≤ w_max`` (each component
    within ``max/√3``), so any twist in the box respects both magnitudes."""
    for name, val in (("v_max", v_max), ("w_max", w_max)):
        if isinstance(val, bool) or not isinstance(val, (int, float)) or not (val > 0):
            raise ValueError(f"twist_box: argument '{name}' must be a positive number, got {val!r}")
    s = 1.0 / math.sqrt(3.0)
    hi = torch.tensor([v_max * s] * 3 + [w_max * s] * 3, dtype=dtype, device=device)
    return -hi, hi


def _check_pose(X, name: str, fn: str, tail: int, like: Tensor | None = None) -> None:
    """``X`` a tensor of poses ``(*B, 4, 4)`` (``tail``: ``(*B, N+1, 4, 4)``) on SE(3) within torchlie's
    manifold tolerance for its dtype (``ValueError`` naming ``name``; non-finite poses are left to the
    per-element status ``NONFINITE_INPUT``), with ``like``'s dtype and device (``TypeError``)."""
    if not isinstance(X, Tensor):
        raise TypeError(f"{fn}: argument '{name}' must be a torch.Tensor of 4x4 poses, "
                        f"got {type(X).__name__}")
    if X.dim() < 2 + tail or X.shape[-2:] != (4, 4):
        raise ValueError(f"{fn}: argument '{name}' must be a tensor of 4x4 poses with shape "
                         f"{'(*B, N+1, 4, 4)' if tail else '(*B, 4, 4)'}, got {tuple(X.shape)}")
    if like is not None and (X.dtype != like.dtype or X.device != like.device):
        raise TypeError(f"{fn}: argument '{name}' must have X's dtype and device "
                        f"({like.dtype}, {like.device}), got {X.dtype} on {X.device}; cast explicitly")
    fin = all_finite(X, 2)[..., None, None]
    _SE3.check_point(torch.where(fin, X.detach(), torch.eye(4, dtype=X.dtype, device=X.device)), name, fn)


_SE3 = SE3()


class PoseMPC:
    """Pose tracking MPC over body twists (module docstring), ``frame`` ``"world"``, ``"local"`` or ``"se3"``.

    Args:
        frame: see the module docstring.
        horizon: N steps of ``dt`` seconds.
        Q, R, P: weights on the 6-d pose error (``[translation, rotation]``) and on ``T − T*``; ``(6,)``
            diagonals or ``(6, 6)`` matrices (``P`` defaults to ``Q``).
        u_lower, u_upper: box on the twist, broadcastable to ``(*B, N, 6)`` (e.g. :func:`twist_box`);
            ``None`` for none.
        order: the Bernoulli series order of the ME2 models (2 = the paper; ``None`` in the world frame for
            the closed form ``J_r⁻¹``).
        grad, qp_options: as in :class:`~controllers.manifold_mpc.ErrorStateMPC`.
    """

    def __init__(self, frame: str, horizon: int, dt: float, Q: Tensor, R: Tensor, P: Tensor | None = None, *,
                 u_lower: Tensor | float | None = None, u_upper: Tensor | float | None = None,
                 order: int | None = 2, grad: GradMode | str = GradMode.IMPLICIT,
                 qp_options: dict | None = None):
        fn = "PoseMPC"
        if frame not in FRAMES:
            raise ValueError(f"{fn}: argument 'frame' must be one of {FRAMES}, got {frame!r}")
        if isinstance(dt, bool) or not isinstance(dt, (int, float)) or not (dt > 0 and math.isfinite(dt)):
            raise ValueError(f"{fn}: argument 'dt' must be a positive finite float, got {dt!r}")
        if order is None and frame != "world":
            raise ValueError(f"{fn}: argument 'order' may be None (closed form) only for frame='world'")
        if order is not None and (isinstance(order, bool) or not isinstance(order, int) or order < 0):
            raise ValueError(f"{fn}: argument 'order' must be a non-negative int (or None in the world "
                             f"frame), got {order!r}")
        self.frame, self.N, self.dt, self.order = frame, horizon, float(dt), order
        self._kw = dict(P=P, u_lower=u_lower, u_upper=u_upper, solver="qp", grad=grad, qp_options=qp_options)
        self._Q, self._R = Q, R
        # the world model depends on the current pose: its MPC is built per solve (validation only, cheap)
        proto = {"world": lambda: ME2WorldModel(torch.zeros(6, dtype=torch.float64), dt, order),
                 "local": lambda: ME2LocalModel(dt, order),
                 "se3": lambda: BodyTwistSE3(dt)}[frame]()
        self._mpc = ErrorStateMPC(proto, horizon, Q, R, **self._kw)

    def solve(self, X: Tensor, X_ref: Tensor, T_ref: Tensor, *, warm: Tensor | None = None
              ) -> ErrorStateSolution:
        """One step: ``X (*B, 4, 4)`` the current pose, ``X_ref (*B, N+1, 4, 4)``, ``T_ref (*B, N, 6)``.

        Returns the :class:`~controllers.manifold_mpc.ErrorStateSolution`: ``u`` is the body twist to apply,
        ``dx`` the predicted errors ``e_k`` in this frame's coordinates.
        """
        fn = "PoseMPC.solve"
        _check_pose(X, "X", fn, 0)
        _check_pose(X_ref, "X_ref", fn, 1, like=X)
        if X_ref.shape[-3] != self.N + 1:
            raise ValueError(f"{fn}: argument 'X_ref' must hold N+1 = {self.N + 1} poses, "
                             f"got {X_ref.shape[-3]}")
        if not isinstance(T_ref, Tensor):
            raise TypeError(f"{fn}: argument 'T_ref' must be a torch.Tensor, got {type(T_ref).__name__}")
        if T_ref.dtype != X.dtype or T_ref.device != X.device:
            raise TypeError(f"{fn}: argument 'T_ref' must have X's dtype and device ({X.dtype}, {X.device}), "
                            f"got {T_ref.dtype} on {T_ref.device}; cast explicitly")
        if T_ref.dim() < 2 or T_ref.shape[-2:] != (self.N, 6):
            raise ValueError(f"{fn}: argument 'T_ref' must have shape (*B, N, 6) = (*B, {self.N}, 6), "
                             f"got {tuple(T_ref.shape)}")
        broadcast_batch(fn, {"X": X.shape[:-2], "X_ref": X_ref.shape[:-3], "T_ref": T_ref.shape[:-2]})
        if self.frame == "se3":
            return self._mpc.solve(X, X_ref, T_ref, warm=warm)
        if self.frame == "world":
            xi0 = se3.log(X)
            # the model of a non-finite pose is built at ξ = 0: its element is reported NONFINITE_INPUT from
            # xi0 below, and no NaN enters the linearization, whose backward would reach shared weights
            xi_model = torch.where(all_finite(xi0, 1)[..., None], xi0, torch.zeros((), dtype=xi0.dtype))
            mpc = copy.copy(self._mpc)  # validated once in __init__; only the model depends on the pose
            mpc.system = ME2WorldModel(xi_model, self.dt, self.order)
            return mpc.solve(xi0, se3.log(X_ref), T_ref, warm=warm)
        omega_ref = se3.log(se3.inverse(X).unsqueeze(-3) @ X_ref)  # (*B, N+1, 6): log(X⁻¹ X*_k)
        return self._mpc.solve(torch.zeros_like(omega_ref[..., 0, :]), omega_ref, T_ref, warm=warm)

    __call__ = solve
