"""Linearization of batched nonlinear dynamics along a trajectory (for iLQR, seed 004 §8).

``x_{t+1} = f(x_t, u_t, t)`` is replaced around ``(x̄_t, ū_t)`` by the affine model
``x_{t+1} ≈ A_t x_t + B_t u_t + c_t`` with ``A_t = ∂f/∂x``, ``B_t = ∂f/∂u`` and
``c_t = f(x̄_t, ū_t, t) - A_t x̄_t - B_t ū_t`` — exactly the :class:`~controllers.problem.LinearDynamics`
form, so an LQ solver can take it as is.  Jacobians come from the dynamics' analytic ``jacobian`` when
it has one, otherwise from ``torch.func`` (``vmap`` of ``jacrev`` over the flattened batch), or from
``jacrev`` of the batch sum (``method="batch-sum"``), which needs only that ``f`` never mixes batch
elements.
"""

from __future__ import annotations

import enum
from collections.abc import Callable

import torch

from controllers.problem import LinearDynamics, NonlinearDynamics, enum_arg

__all__ = ["JacobianMethod", "jacobians", "linearize"]


class JacobianMethod(str, enum.Enum):
    AUTO = "auto"  #: analytic when available, else VMAP
    ANALYTIC = "analytic"  #: the dynamics' own ``jacobian(x, u, t)``
    VMAP = "vmap"  #: ``torch.func.vmap(torch.func.jacrev(f))`` over the flattened batch
    BATCH_SUM = "batch-sum"  #: ``torch.func.jacrev`` of ``f(x, u, t).sum(batch)``


def _as_dynamics(f) -> NonlinearDynamics | None:
    return f if isinstance(f, NonlinearDynamics) else None


def jacobians(f: NonlinearDynamics | Callable, x: torch.Tensor, u: torch.Tensor, t: int = 0,
              method: JacobianMethod | str = JacobianMethod.AUTO
              ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(f(x, u, t) (*B, n), ∂f/∂x (*B, n, n), ∂f/∂u (*B, n, m))`` at one time step.

    Args:
        f: a :class:`NonlinearDynamics` or a batched callable ``f(x, u, t)``.
        x: ``(*B, n)``; u: ``(*B, m)`` (batch dims broadcast).
    """
    method = enum_arg(JacobianMethod, method, "method", "jacobians")
    dyn = _as_dynamics(f)
    fn = dyn.f if dyn is not None else f
    if not callable(fn):
        raise TypeError("jacobians: 'f' must be a NonlinearDynamics or a callable, "
                        f"got {type(f).__name__}")
    bs = torch.broadcast_shapes(x.shape[:-1], u.shape[:-1])
    n, m = x.shape[-1], u.shape[-1]
    x = x.expand(*bs, n)
    u = u.expand(*bs, m)
    if method is JacobianMethod.AUTO:
        analytic = dyn is not None and dyn.jacobian is not None
        method = JacobianMethod.ANALYTIC if analytic else JacobianMethod.VMAP
    if method is JacobianMethod.ANALYTIC:
        if dyn is None or dyn.jacobian is None:
            raise ValueError("jacobians: method='analytic' needs a NonlinearDynamics with a 'jacobian'")
        A, B = dyn.jacobian(x, u, t)
        return fn(x, u, t), A.expand(*bs, n, n), B.expand(*bs, n, m)
    if method is JacobianMethod.VMAP:
        xf, uf = x.reshape(-1, n), u.reshape(-1, m)

        def single(xi, ui):
            y = fn(xi.unsqueeze(0), ui.unsqueeze(0), t).squeeze(0)
            return y, y

        (A, B), y = torch.func.vmap(torch.func.jacrev(single, argnums=(0, 1), has_aux=True))(xf, uf)
        return y.reshape(*bs, -1), A.reshape(*bs, -1, n), B.reshape(*bs, -1, m)
    # batch-sum: d/dx Σ_b f(x_b) has, for an element-wise-independent f, the per-element Jacobians
    nb = len(bs)

    def summed(xx, uu):
        y = fn(xx, uu, t)
        return y.sum(tuple(range(nb))) if nb else y, y

    (A, B), y = torch.func.jacrev(summed, argnums=(0, 1), has_aux=True)(x, u)  # (n_out, *B, n)
    A = A.movedim(0, -2) if nb else A
    B = B.movedim(0, -2) if nb else B
    return y, A, B


def linearize(f: NonlinearDynamics | Callable, x: torch.Tensor, u: torch.Tensor, t0: int = 0,
              method: JacobianMethod | str = JacobianMethod.AUTO, time_invariant: bool = False
              ) -> LinearDynamics:
    """Affine model ``A_t, B_t, c_t`` of ``f`` along ``x (*B, T, n)`` (or ``(*B, T+1, n)``, the last state
    is then ignored) and ``u (*B, T, m)``; time steps are ``t0 .. t0+T-1``.

    ``time_invariant=True`` evaluates all steps in one call with ``t = t0`` (for ``f`` that ignores
    ``t``), instead of a loop over time.
    """
    if x.dim() < 2 or u.dim() < 2:
        raise ValueError(f"linearize: x must be (*B, T, n) and u (*B, T, m), "
                         f"got {tuple(x.shape)}, {tuple(u.shape)}")
    T = u.shape[-2]
    if x.shape[-2] == T + 1:
        x = x[..., :T, :]
    if x.shape[-2] != T:
        raise ValueError(f"linearize: x must have T = {T} (or T+1) steps to match u, got {tuple(x.shape)}")
    bs = torch.broadcast_shapes(x.shape[:-2], u.shape[:-2])
    x = x.expand(*bs, T, x.shape[-1])
    u = u.expand(*bs, T, u.shape[-1])
    if time_invariant:
        y, A, B = jacobians(f, x, u, t0, method)
    else:
        outs = [jacobians(f, x[..., t, :], u[..., t, :], t0 + t, method) for t in range(T)]
        y = torch.stack([o[0] for o in outs], -2)
        A = torch.stack([o[1] for o in outs], -3)
        B = torch.stack([o[2] for o in outs], -3)
    c = y - (A @ x.unsqueeze(-1)).squeeze(-1) - (B @ u.unsqueeze(-1)).squeeze(-1)
    return LinearDynamics(A, B, c)
