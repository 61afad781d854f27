"""Impedance control of torque-controlled arms (seed 004 §11.1-§11.2) on a planar arm.

The arm is :class:`~controllers.systems.PlanarArm`.

The robot (Eq. 169) ``τ = M(q) q̈ + c(q, q̇) + g(q) + h(q, q̇) + τ_ext`` is the arm's own forward dynamics
(:meth:`PlanarArm.acceleration`, Appendix E, with viscous friction ``h = b ∘ q̇``).  The controllers are the
set-point (``ẍ^d = 0``) forms of Eq. 170 and Eq. 172 with gravity compensation ``ĝ(q)``
(:meth:`PlanarArm.gravity_torque`)::

    joint space (Eq. 170):  τ = K^JP (q^d - q) + K^JV (q̇^d - q̇) + ĝ(q)
    task space  (Eq. 172):  τ = Jᵀ (K^P (f^d - f) + K^V (ḟ^d - ḟ)) + ĝ(q),     f = f^ee(q), ḟ = J q̇

With ``ĝ = g`` the closed loop is the mass-spring-damper of Eq. 171 and rests at the set point; without it
(``gravity_compensation=False``) it rests where the spring balances gravity, ``K (q^d - q) = g(q)``: a
steady-state error.  :func:`simulate` rolls any such feedback out on the arm's discrete step (the model the
MPC and the environments use).  Gains: a float, a vector ``(*B, d)`` (diagonal) or a matrix ``(*B, d, d)``.
"""

from __future__ import annotations

import numbers
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from controllers.systems.arm import PlanarArm

__all__ = ["ImpedanceRollout", "joint_impedance_torque", "simulate", "task_impedance_torque"]


def _check_arm_state(arm, x, fn: str) -> None:
    if not isinstance(arm, PlanarArm):
        raise TypeError(f"{fn}: argument 'arm' must be a controllers.systems.PlanarArm, "
                        f"got {type(arm).__name__}")
    if not isinstance(x, Tensor) or not x.is_floating_point():
        raise TypeError(f"{fn}: argument 'x' must be a floating-point torch.Tensor (*B, {arm.n})")
    if x.ndim < 1 or x.shape[-1] != arm.n:
        raise ValueError(f"{fn}: argument 'x' must have shape (*B, {arm.n}) = [q, q̇], got {tuple(x.shape)}")


def _vec(v, name: str, d: int, like: Tensor, fn: str) -> Tensor:
    """A reference ``(*B, d)`` in ``like``'s dtype/device."""
    if not isinstance(v, Tensor) or v.dtype != like.dtype:
        raise TypeError(f"{fn}: argument '{name}' must be a {like.dtype} tensor (*B, {d})")
    if v.ndim < 1 or v.shape[-1] != d:
        raise ValueError(f"{fn}: argument '{name}' must have shape (*B, {d}), got {tuple(v.shape)}")
    return v.to(like.device)


def _gain_apply(K, e: Tensor, name: str, fn: str) -> Tensor:
    """``K e`` for a gain given as a float, a diagonal ``(*B, d)`` or a matrix ``(*B, d, d)``."""
    d = e.shape[-1]
    if isinstance(K, numbers.Real) and not isinstance(K, bool):
        return float(K) * e
    if not isinstance(K, Tensor) or K.dtype != e.dtype:
        raise TypeError(f"{fn}: argument '{name}' must be a float or a {e.dtype} tensor (*B, {d}) or "
                        f"(*B, {d}, {d})")
    K = K.to(e.device)
    if K.ndim >= 2 and K.shape[-2:] == (d, d):
        return (K @ e[..., None])[..., 0]
    if K.ndim >= 1 and K.shape[-1] == d:
        return K * e
    if K.ndim == 0:
        return K * e
    raise ValueError(f"{fn}: argument '{name}' must be a float, (*B, {d}) or (*B, {d}, {d}), "
                     f"got {tuple(K.shape)}")


def joint_impedance_torque(arm: PlanarArm, x: Tensor, q_ref: Tensor, stiffness, damping, *,
                           qd_ref: Tensor | None = None, gravity_compensation: bool = True) -> Tensor:
    """Joint-space impedance torque ``τ (*B, k)`` (Eq. 170 with ``ẍ^d = 0``, ĉ and ĥ omitted):
    ``τ = K^JP (q^d - q) + K^JV (q̇^d - q̇) + ĝ(q)``.

    Args:
        arm: the model giving ``ĝ`` (:meth:`PlanarArm.gravity_torque`).
        x: ``(*B, 2k)`` state ``[q, q̇]``; ``q_ref``: ``(*B, k)`` set point ``q^d``; ``qd_ref``: ``q̇^d``
            (default 0).
        stiffness, damping: ``K^JP``, ``K^JV`` — float, ``(*B, k)`` (diagonal) or ``(*B, k, k)``.
        gravity_compensation: add ``ĝ(q)`` (``False``: a pure spring-damper, with a steady-state error under
            gravity).

    Differentiable in every tensor argument (and in the arm's tensor parameters).
    """
    fn = "joint_impedance_torque"
    _check_arm_state(arm, x, fn)
    k = arm.links
    q, qd = x[..., :k], x[..., k:]
    q_ref = _vec(q_ref, "q_ref", k, x, fn)
    ev = -qd if qd_ref is None else _vec(qd_ref, "qd_ref", k, x, fn) - qd
    tau = _gain_apply(stiffness, q_ref - q, "stiffness", fn) + _gain_apply(damping, ev, "damping", fn)
    return tau + arm.gravity_torque(q) if gravity_compensation else tau


def task_impedance_torque(arm: PlanarArm, x: Tensor, f_ref: Tensor, stiffness, damping, *,
                          fd_ref: Tensor | None = None, gravity_compensation: bool = True) -> Tensor:
    """Task-space impedance torque ``τ (*B, k)`` on the end-effector position (Eq. 172 with ``f̈^d = 0``):
    ``τ = Jᵀ (K^P (f^d - f) + K^V (ḟ^d - ḟ)) + ĝ(q)``, ``f = f^ee(q)``, ``ḟ = J q̇`` (``J`` of
    :meth:`PlanarArm.ee_jacobian`; ``Jᵀ w`` maps the wrench to joint torques, the principle of virtual work).

    Args:
        f_ref: ``(*B, 2)`` end-effector set point ``f^d``; ``fd_ref``: its velocity (default 0).
        stiffness, damping: ``K^P``, ``K^V`` — float, ``(*B, 2)`` or ``(*B, 2, 2)``.
        the others: as :func:`joint_impedance_torque`.

    A redundant arm (``k > 2``) is not held in the null space of ``J`` by this law (only by the arm's own
    joint damping).
    """
    fn = "task_impedance_torque"
    _check_arm_state(arm, x, fn)
    k = arm.links
    q, qd = x[..., :k], x[..., k:]
    f_ref = _vec(f_ref, "f_ref", 2, x, fn)
    J = arm.ee_jacobian(q)
    fdot = (J @ qd[..., None])[..., 0]
    ev = -fdot if fd_ref is None else _vec(fd_ref, "fd_ref", 2, x, fn) - fdot
    w = _gain_apply(stiffness, f_ref - arm.end_effector(q), "stiffness", fn) + _gain_apply(damping, ev,
                                                                                            "damping", fn)
    tau = (J.mT @ w[..., None])[..., 0]
    return tau + arm.gravity_torque(q) if gravity_compensation else tau


@dataclass(frozen=True, eq=False)
class ImpedanceRollout:
    """Closed-loop trajectory of :func:`simulate`: ``x (*B, T+1, 2k)`` and the torques ``u (*B, T, k)``."""

    x: Tensor
    u: Tensor


def simulate(arm: PlanarArm, x0: Tensor, controller: Callable[[Tensor, int], Tensor], steps: int,
             tau_ext: Tensor | None = None) -> ImpedanceRollout:
    """Roll a feedback ``τ_t = controller(x_t, t)`` out on :meth:`PlanarArm.step` (semi-implicit Euler of the
    forward dynamics, Appendix E) for ``steps`` steps from ``x0 (*B, 2k)``.

    ``tau_ext`` (``(*B, k)``, optional) is a constant external joint torque ``τ_ext`` of Eq. 169 (it enters
    the dynamics with the opposite sign of the actuation, ``τ - τ_ext``).  Differentiable (autograd through
    the steps).  Returns :class:`ImpedanceRollout`.
    """
    fn = "simulate"
    _check_arm_state(arm, x0, fn)
    if not callable(controller):
        raise TypeError(f"{fn}: argument 'controller' must be callable (x (*B, 2k), t) -> τ (*B, k)")
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 0:
        raise ValueError(f"{fn}: argument 'steps' must be an int >= 0, got {steps!r}")
    if tau_ext is not None:
        tau_ext = _vec(tau_ext, "tau_ext", arm.links, x0, fn)
    xs, us = [x0], []
    x = x0
    for t in range(steps):
        u = controller(x, t)
        if not isinstance(u, Tensor) or u.shape[-1] != arm.links:
            raise ValueError(f"{fn}: the controller must return torques (*B, {arm.links}), got "
                             f"{tuple(u.shape) if isinstance(u, Tensor) else type(u).__name__}")
        x = arm.step(x, u if tau_ext is None else u - tau_ext)
        xs.append(x)
        us.append(u)
    bs = x.shape[:-1]
    X = torch.stack([v.expand(*bs, arm.n) for v in xs], -2)
    U = torch.stack([v.expand(*bs, arm.links) for v in us], -2) if us else x0.new_zeros(*bs, 0, arm.links)
    return ImpedanceRollout(x=X, u=U)
